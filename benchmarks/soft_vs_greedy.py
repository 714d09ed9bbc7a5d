"""A/B of the improvement step on Pendulum-v1: smoothed greedy (the default) vs soft.

One run per call (the tuned preset, one BLAS thread), evaluated every 1,000 env steps with the
deterministic policy on 10 fixed starts (reset seeds 10,000-10,009, not used in training);
prints one JSON line with the curve. The 10-seed benchmark of issue 15 is a separate script.

    python benchmarks/soft_vs_greedy.py soft 0 6000 --beta 0.5 --decay 0.9
    python benchmarks/soft_vs_greedy.py greedy 0 6000
"""

from __future__ import annotations

import argparse
import json
import time

import gymnasium as gym
import numpy as np
import torch

from cme_agent import CMEPolicyIteration

EVAL_SEEDS = range(10_000, 10_010)
"""Reset seeds of the evaluation episodes: fixed starts, the same for every run."""


def fixed_start_return(model: CMEPolicyIteration) -> float:
    """Mean return of the deterministic policy over the episodes started from :data:`EVAL_SEEDS`."""
    env = gym.make("Pendulum-v1")
    returns = []
    for seed in EVAL_SEEDS:
        obs, _ = env.reset(seed=seed)
        total, done = 0.0, False
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, reward, terminated, truncated, _ = env.step(action)
            total, done = total + float(reward), terminated or truncated
        returns.append(total)
    return float(np.mean(returns))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("method", choices=["greedy", "soft"])
    parser.add_argument("seed", type=int)
    parser.add_argument("steps", type=int)
    parser.add_argument("--beta", type=float, default=None, help="improvement.beta (soft; default: the library's)")
    parser.add_argument("--decay", type=float, default=None, help="improvement.decay (soft; default: the library's)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    improvement = {"method": "soft", "beta": args.beta, "decay": args.decay} if args.method == "soft" else None
    if improvement is not None:
        improvement = {key: value for key, value in improvement.items() if value is not None}
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=args.seed, improvement=improvement)
    curve, start = [], time.perf_counter()
    for done in range(1000, args.steps + 1, 1000):
        model.learn(1000, reset_num_timesteps=done == 1000)
        curve.append(round(fixed_start_return(model)))
    summary = {"method": args.method, "improvement": improvement, "seed": args.seed, "curve": curve}
    print(json.dumps({**summary, "seconds": round(time.perf_counter() - start)}), flush=True)


if __name__ == "__main__":
    main()
