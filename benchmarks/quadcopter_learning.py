"""CMEPolicyIteration on Quadcopter-v0 against the scripted controller (the paper's Figure 3).

Trains ``python train.py env=quadcopter``'s config for several seeds, evaluating every
``--eval-every`` steps: 10 episodes of the deterministic policy (random starts), return and
final distance to the target. The scripted proportional controller is evaluated on the same
episodes. Writes results/quadcopter_learning.md, results/quadcopter_learning.csv and, with
matplotlib, results/quadcopter_learning.png (mean and individual runs, controller as a line).

    python -m benchmarks.quadcopter_learning --seeds 0 1 2 [--steps 20000] [--workers 2]
"""

from __future__ import annotations

import argparse
import multiprocessing
import statistics
from collections.abc import Sequence
from functools import partial
from typing import Any

import gymnasium as gym

from benchmarks.common import command_line, compose_config, markdown_table, plot_learning_curves, write_report
from benchmarks.learning_quality import train_with_evaluations
from cme_agent.envs import QuadcopterPController
from cme_agent.experiment import make_eval_env


def flight_statistics(model: Any, env: gym.Env, episodes: int = 10) -> dict[str, float]:
    """Mean return and mean final distance to the target over ``episodes`` episodes."""
    returns, distances = [], []
    for _ in range(episodes):
        obs, info = env.reset()
        total, done = 0.0, False
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, reward, terminated, truncated, info = env.step(action)
            total += float(reward)
            done = terminated or truncated
        returns.append(total)
        distances.append(info["distance_to_target"])
    return {
        "return_mean": statistics.mean(returns),
        "return_std": statistics.pstdev(returns),
        "final_distance": statistics.mean(distances),
    }


def controller_statistics(seed: int, overrides: Sequence[str] = ()) -> dict[str, float]:
    """The scripted controller on the evaluation episodes of ``seed``, in the env the agent's runs
    fly (``overrides`` such as ``env.kwargs.agent_dt=0.2`` apply to it too)."""
    env = make_eval_env(compose_config(["env=quadcopter", f"seed={seed}", *overrides]))
    return flight_statistics(QuadcopterPController.from_env(env.unwrapped), env)


def run_seed(seed: int, steps: int, period: int, overrides: list[str]) -> list[dict[str, Any]]:
    return train_with_evaluations("quadcopter", seed, overrides, steps, period, flight_statistics)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--steps", type=int, default=20_000)
    parser.add_argument("--eval-every", type=int, default=2_000)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--overrides", nargs="*", default=[])
    args = parser.parse_args()
    job = partial(run_seed, steps=args.steps, period=args.eval_every, overrides=args.overrides)
    with multiprocessing.get_context("spawn").Pool(args.workers) as pool:
        curves = pool.map(job, args.seeds, chunksize=1)
    controller = [controller_statistics(seed, args.overrides) for seed in args.seeds]
    reference = statistics.mean(c["return_mean"] for c in controller)
    rows = []
    for seed, curve, ctrl in zip(args.seeds, curves, controller, strict=True):
        final = curve[-1]
        rows.append(
            [
                seed,
                f"{final['return_mean']:.1f}",
                f"{ctrl['return_mean']:.1f}",
                f"{final['return_mean'] / ctrl['return_mean']:.2f}",
                f"{final['final_distance']:.2f}",
                f"{ctrl['final_distance']:.2f}",
            ]
        )
    fractions = [curve[-1]["return_mean"] / ctrl["return_mean"] for curve, ctrl in zip(curves, controller, strict=True)]
    spread = statistics.stdev(fractions) if len(fractions) > 1 else 0.0
    header = ["seed", "CME return", "controller return", "fraction", "CME final distance (m)", "controller final distance (m)"]
    text = (
        f"# CMEPolicyIteration on Quadcopter-v0\n\nCommand: `{command_line()}`\n\n"
        f"Final evaluation after {args.steps} env steps: 10 episodes of the deterministic policy per seed (random starts), "
        f"the scripted controller on the same starts. Fraction of the controller's return: "
        f"{statistics.mean(fractions):.2f} +- {spread:.2f} (mean +- std over {len(fractions)} seeds; target 0.80).\n\n"
        f"{markdown_table(header, rows)}\n"
    )
    write_report("quadcopter_learning", text, curves)
    plot_learning_curves({"Quadcopter-v0": (curves, reference, "scripted controller")}, "quadcopter_learning.png")


if __name__ == "__main__":
    main()
