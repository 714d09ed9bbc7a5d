"""Learning quality of CMEPolicyIteration on the Gymnasium classics, several seeds.

Each run trains with the Hydra config of its env (exactly what ``python train.py env=<name>``
runs) and pauses every ``--eval-every`` steps for an evaluation: 10 episodes of the
deterministic policy from random starts on a separate env. The table reports the FINAL
evaluation (the last policy, not the best one seen) as mean +- std over seeds, the targets of
issue 2, and the first step count at which an evaluation reached the target. Writes
results/learning_quality.md, results/learning_quality.csv and, with matplotlib,
results/learning_quality.png.

    python benchmarks/learning_quality.py --envs pendulum cartpole --seeds 0 1 2 [--workers 2]
"""

from __future__ import annotations

import argparse
import multiprocessing
import statistics
import time
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import torch
from common import command_line, compose_config, markdown_table, plot_learning_curves, write_report
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.logger import Logger, configure

from cme_agent.experiment import build_agent, make_env, make_eval_env

TARGETS = {  # env config: (target return, evaluation period); the step budget is the env config's total_timesteps
    "pendulum": (-200.0, 600),
    "cartpole": (475.0, 1_000),
    "acrobot": (-100.0, 1_000),
    "mountain_car": (-130.0, 2_000),
    "mountain_car_continuous": (90.0, 3_000),
}


def budget(env_name: str) -> int:
    """The env-step budget of an env config (conf/env/<name>.yaml, ``total_timesteps``): the one place it is set."""
    return int(compose_config([f"env={env_name}"]).total_timesteps)


def episode_returns(model: Any, env: gym.Env, episodes: int) -> dict[str, float]:
    """Mean and std of the return of the deterministic policy over ``episodes`` episodes."""
    returns, _ = evaluate_policy(model, env, n_eval_episodes=episodes, return_episode_rewards=True)
    return {"return_mean": statistics.mean(returns), "return_std": statistics.pstdev(returns)}


def train_with_evaluations(
    env_name: str,
    seed: int,
    overrides: list[str],
    budget: int,
    period: int,
    evaluate: Callable[[Any, gym.Env], dict[str, float]] = lambda model, env: episode_returns(model, env, 10),
    logger: Logger | None = None,
) -> list[dict[str, Any]]:
    """Train the Hydra config ``env=<env_name>`` for ``budget`` steps, evaluating every ``period``
    steps on a separate env seeded apart from training; one row per evaluation.

    :param logger: the agent's logger (default: one that writes nothing)
    """
    torch.set_num_threads(1)
    cfg = compose_config([f"env={env_name}", f"seed={seed}", "verbose=0", *overrides])
    model = build_agent(cfg, make_env(cfg))
    model.set_logger(configure(None, []) if logger is None else logger)
    eval_env = make_eval_env(cfg)
    rows, train_seconds = [], 0.0
    while model.num_timesteps < budget:
        start = time.perf_counter()
        model.learn(min(period, budget - model.num_timesteps), reset_num_timesteps=False)
        train_seconds += time.perf_counter() - start
        row = {"env": env_name, "seed": seed, "steps": model.num_timesteps, "iteration": getattr(model, "iteration", None)}
        row.update(evaluate(model, eval_env))
        row.update(n_features=getattr(model, "q", 0), train_seconds=round(train_seconds, 1))
        rows.append(row)
        print(
            f"{env_name} seed {seed} steps {model.num_timesteps}: {row['return_mean']:.1f} (q={row['n_features']})", flush=True
        )
    return rows


def run_one(job: tuple[str, int, list[str]]) -> list[dict[str, Any]]:
    """One seed of one env with its config's budget and the evaluation period from TARGETS."""
    env_name, seed, overrides = job
    return train_with_evaluations(env_name, seed, overrides, budget(env_name), TARGETS[env_name][1])


def summarise(env_name: str, curves: list[list[dict[str, Any]]]) -> list[Any]:
    target = TARGETS[env_name][0]
    finals = [curve[-1]["return_mean"] for curve in curves]
    reached = [next((row["steps"] for row in curve if row["return_mean"] >= target), None) for curve in curves]
    spread = statistics.stdev(finals) if len(finals) > 1 else 0.0
    return [
        env_name,
        curves[0][-1]["steps"],
        f"{target:g}",
        f"{statistics.mean(finals):.1f} +- {spread:.1f}",
        ", ".join(f"{f:.0f}" for f in finals),
        "yes" if statistics.mean(finals) >= target else "no",
        ", ".join("-" if r is None else str(r) for r in reached),
        f"{statistics.mean(curve[-1]['train_seconds'] for curve in curves):.0f}",
        f"{statistics.mean(curve[-1]['n_features'] for curve in curves):.0f}",
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=list(TARGETS), choices=list(TARGETS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--overrides", nargs="*", default=[], help="Hydra overrides for every run")
    parser.add_argument("--stem", default="learning_quality", help="name of the results/<stem>.{md,csv,png} files")
    args = parser.parse_args()
    jobs = [(env_name, seed, args.overrides) for env_name in args.envs for seed in args.seeds]
    start = time.perf_counter()
    with multiprocessing.get_context("spawn").Pool(args.workers) as pool:
        results = pool.map(run_one, jobs, chunksize=1)
    curves: dict[str, list[list[dict[str, Any]]]] = {}
    for (env_name, _, _), curve in zip(jobs, results, strict=True):
        curves.setdefault(env_name, []).append(curve)
    header = [
        "env",
        "steps",
        "target",
        "final return (mean +- std)",
        "per seed",
        "target met",
        "steps to target",
        "train s",
        "q",
    ]
    table = markdown_table(header, [summarise(env_name, runs) for env_name, runs in curves.items()])
    text = (
        f"# Learning quality of CMEPolicyIteration\n\nCommand: `{command_line()}`\n\n"
        f"Seeds {args.seeds}; final return = 10-episode evaluation of the deterministic policy after the last "
        f"training step (random starts, seeded apart from training); 'steps to target' = first evaluation at or above "
        f"the target. Wall-clock {time.perf_counter() - start:.0f} s on this machine with {args.workers} workers.\n\n{table}\n"
    )
    write_report(args.stem, text, results)
    panels = {name: (runs, TARGETS[name][0], "target") for name, runs in curves.items()}
    plot_learning_curves(panels, f"{args.stem}.png")


if __name__ == "__main__":
    main()
