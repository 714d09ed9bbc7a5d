"""How the evaluation episodes of one training run end: which termination condition ends them.

Trains the Hydra config ``env=<name>`` (the library's defaults and the env's preset) for one seed,
evaluating every 1,000 env steps as ``benchmarks/learning_quality.py`` does (10 episodes of the
deterministic policy from the seed's fixed starts). Per evaluation it counts the episodes cut by
the time limit and, of those that terminated, the ones whose last observation is past each of the
env's termination bounds (``TERMINATION_BOUNDS``; CartPole-v1: the cart's position beyond 2.4,
the pole's angle beyond 12 degrees), with the mean |observation| over all steps of the episodes.
It tells a policy that drops the pole from one that balances it and lets the cart drift off the
track. Writes results/<stem>.md and results/<stem>.csv.

    python -m benchmarks.diagnostics.episode_endings --env cartpole --seed 2 --steps 7000
"""

from __future__ import annotations

import argparse
import statistics
from typing import Any

import gymnasium as gym
import numpy as np

from benchmarks.common import command_line, markdown_table, write_report
from benchmarks.learning_quality import PERIOD, train_with_evaluations

TERMINATION_BOUNDS: dict[str, dict[str, tuple[int, float]]] = {
    "cartpole": {"cart position": (0, 2.4), "pole angle": (2, 12 * 2 * np.pi / 360)},
}
"""Per env config: the termination conditions as (observation index, bound on its absolute value)."""


def episode_endings(model: Any, env: gym.Env, bounds: dict[str, tuple[int, float]], episodes: int = 10) -> dict[str, float]:
    """Run ``episodes`` deterministic episodes and count how they end.

    :param bounds: name -> (observation index, bound on |obs[index]|) of each termination condition
    :return: ``return_mean``, ``truncated`` (episodes cut by the time limit), ``past <name>`` per
        bound (terminated episodes whose last observation is past it) and ``mean abs obs[i]`` per
        observation dimension over all steps
    """
    returns, truncated, past, visited = [], 0, dict.fromkeys(bounds, 0), []
    for _ in range(episodes):
        obs, _ = env.reset()
        total, terminated, cut = 0.0, False, False
        while not (terminated or cut):
            action, _ = model.predict(obs, deterministic=True)
            obs, reward, terminated, cut, _ = env.step(action)
            total += float(reward)
            visited.append(np.abs(obs))
        returns.append(total)
        truncated += int(cut and not terminated)
        for name, (index, bound) in bounds.items():
            past[name] += int(terminated and abs(obs[index]) > bound)
    row: dict[str, float] = {"return_mean": statistics.mean(returns), "truncated": truncated}
    row.update({f"past {name}": count for name, count in past.items()})
    row.update({f"mean abs obs[{i}]": round(float(value), 3) for i, value in enumerate(np.mean(visited, axis=0))})
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="cartpole", help="env config name (conf/env/<name>.yaml)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=7_000, help="env steps of training")
    parser.add_argument("--overrides", nargs="*", default=[], help="Hydra overrides, e.g. agent.omega=0.7")
    parser.add_argument("--stem", default=None, help="output file stem (default episode_endings_<env>_seed<seed>)")
    args = parser.parse_args()
    bounds = TERMINATION_BOUNDS.get(args.env, {})
    rows = train_with_evaluations(
        args.env, args.seed, args.overrides, args.steps, PERIOD, lambda model, env: episode_endings(model, env, bounds)
    )
    keys = [key for key in rows[0] if key in ("steps", "return_mean", "truncated") or key.startswith(("past", "mean abs"))]
    table = markdown_table(keys, [[row[key] if key != "return_mean" else f"{row[key]:.1f}" for key in keys] for row in rows])
    stem = args.stem or f"episode_endings_{args.env}_seed{args.seed}"
    text = (
        f"# How the evaluation episodes end: {args.env}, seed {args.seed}\n\n"
        f"Command: `{command_line()}`\n\n"
        f"Every {PERIOD:,} env steps, 10 episodes of the deterministic policy from the seed's fixed starts: "
        "the episodes cut by the time limit, the terminated ones whose last observation is past each termination "
        "bound, and the mean |observation| per dimension over all their steps.\n\n"
        f"{table}\n"
    )
    write_report(stem, text, [rows])


if __name__ == "__main__":
    main()
