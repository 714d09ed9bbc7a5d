"""learn() and predict() against an earlier commit, A/B in one run.

Three workloads, each run by both versions of the code in subprocesses (1 torch thread, timed
in thread CPU seconds, the two versions alternating):

- ``quickstart``: the README quickstart of commit 6add98b, Pendulum-v1 with omega=0.2,
  |C| = 8,000, phi 21 x 15 (today's Pendulum-v1 preset), ``learn(6000)``, seed 0, then
  the return over 10 evaluation episodes on fixed starts;
- ``predict``: ``model.predict(obs, deterministic=True)`` on one observation, averaged over
  2,000 calls on the trained quickstart model;
- ``cartpole``: CartPole-v1 at its preset (gamma 0.99, phi 5 x 7 x 9 x 9, today's bounds),
  training seconds per env step over ``learn(2000)`` (seed 0, or each of ``--cartpole-seeds``);
- ``agreement``: the quickstart's first 400 steps (random actions, 2 iterations: the same data in
  both versions), then q and the norms of B and of the Q weights.

The baseline is the commit given by ``--baseline``, checked out into a scratch git worktree and
imported in place of this checkout (same interpreter and packages: only cme_agent differs).

    python -m benchmarks.learn_speed [--baseline 6add98b] [--repeats 1] [--stem learn_speed] [--workloads cartpole]
        [--cartpole-seeds 0 1 2]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks.common import ROOT, command_line, markdown_table, write_markdown

WORKLOAD = r"""
import json, sys, time
import gymnasium as gym
import numpy as np
import torch
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor
from cme_agent import CMEPolicyIteration

torch.set_num_threads(1)
name, seed = sys.argv[1], int(sys.argv[2])
if name == "agreement":
    model = CMEPolicyIteration(
        "CMEPolicy", "Pendulum-v1", seed=0, omega=0.2,
        evaluation={"collection_size": 8000}, policy_kwargs={"phi": {"resolution": [21, 15]}},
    )
    model.learn(400)
    weights = model.policy.dynamics.weights if hasattr(model.policy, "dynamics") else model.model.weights
    print(json.dumps({"q": weights.shape[1], "B": weights.double().norm().item(),
                      "theta_psi": model.policy.theta_psi.double().norm().item(),
                      "theta_phi": model.policy.theta_phi.double().norm().item()}))
    sys.exit()
if name == "cartpole":
    model = CMEPolicyIteration(
        "CMEPolicy", "CartPole-v1", seed=seed, gamma=0.99,
        policy_kwargs={"phi": {"resolution": [5, 7, 9, 9]},
                       "observation": {"low": [-2.4, -3.0, -0.21, -3.5], "high": [2.4, 3.0, 0.21, 3.5]}},
    )
    start = time.thread_time()
    model.learn(2000)
    seconds_per_step = (time.thread_time() - start) / model.num_timesteps
    print(json.dumps({"seconds_per_step": seconds_per_step, "q": model.policy.theta_psi.numel()}))
    sys.exit()
model = CMEPolicyIteration(
    "CMEPolicy", "Pendulum-v1", seed=0, omega=0.2,
    evaluation={"collection_size": 8000}, policy_kwargs={"phi": {"resolution": [21, 15]}},
)
start = time.thread_time()
model.learn(6000)
learn_seconds = time.thread_time() - start
env = Monitor(gym.make("Pendulum-v1"))
env.reset(seed=10_000)
mean, std = evaluate_policy(model, env, n_eval_episodes=10, deterministic=True)
obs = np.asarray(env.reset(seed=1)[0])
for _ in range(100):
    model.predict(obs, deterministic=True)
start = time.thread_time()
for _ in range(2000):
    model.predict(obs, deterministic=True)
predict_seconds = (time.thread_time() - start) / 2000
print(json.dumps({"learn_seconds": learn_seconds, "return_mean": mean, "return_std": std,
                  "predict_seconds": predict_seconds, "q": model.policy.theta_psi.numel()}))
"""


WORKLOADS = ("agreement", "quickstart", "cartpole")


def checkout(commit: str) -> Path:
    """A scratch git worktree of ``commit`` (made once, reused)."""
    path = Path(tempfile.gettempdir()) / f"cme_agent_baseline_{commit}"
    if not path.exists():
        subprocess.run(["git", "worktree", "add", "--detach", str(path), commit], cwd=ROOT, check=True, capture_output=True)
    return path


def run(source: Path, workload: str, seed: int = 0) -> dict[str, float]:
    """Run a workload with ``source``'s cme_agent first on the path; its printed JSON (the
    cartpole workload trains with ``seed``; the others always with seed 0)."""
    env = {"PYTHONPATH": str(source), "OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"}
    result = subprocess.run(
        [sys.executable, "-c", WORKLOAD, workload, str(seed)],
        env=env,
        capture_output=True,
        text=True,
        cwd=tempfile.gettempdir(),
    )
    if result.returncode != 0:
        raise RuntimeError(f"{workload} at {source} failed:\n{result.stderr[-3000:]}")
    return json.loads(result.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--baseline", default="6add98b", help="commit to compare against")
    parser.add_argument("--repeats", type=int, default=1, help="alternated runs of each workload per version")
    parser.add_argument("--stem", default="learn_speed", help="name of the results/<stem>.md file")
    parser.add_argument("--workloads", nargs="+", default=list(WORKLOADS), choices=WORKLOADS, help="which workloads to run")
    parser.add_argument(
        "--cartpole-seeds",
        nargs="+",
        type=int,
        default=[0],
        help="seeds of the cartpole workload (its cost follows the q a seed reaches: several seeds compare like with like)",
    )
    args = parser.parse_args()
    versions = {"baseline": checkout(args.baseline), "current": ROOT}
    workloads = [w for w in WORKLOADS if w in args.workloads]
    results: dict[str, dict[str, list[dict[str, float]]]] = {w: {v: [] for v in versions} for w in workloads}
    for _ in range(args.repeats):
        for workload in results:
            for seed in args.cartpole_seeds if workload == "cartpole" else [0]:
                for version, source in versions.items():
                    results[workload][version].append(run(source, workload, seed) | {"seed": seed})
                    print(workload, version, results[workload][version][-1], flush=True)

    def median(workload: str, version: str, key: str) -> float:
        return statistics.median(r[key] for r in results[workload][version])

    rows = []
    for label, workload, key, scale, unit in (
        ("quickstart learn(6000)", "quickstart", "learn_seconds", 1.0, "s"),
        ("predict, one observation", "quickstart", "predict_seconds", 1e3, "ms"),
        ("CartPole training per env step", "cartpole", "seconds_per_step", 1e3, "ms"),
    ):
        if workload not in results:
            continue
        before, after = median(workload, "baseline", key) * scale, median(workload, "current", key) * scale
        rows.append([label, f"{before:.3g} {unit}", f"{after:.3g} {unit}", f"{before / after:.2f}x"])
    text = (
        f"# learn() and predict() against commit {args.baseline}\n\nCommand: `{command_line()}` (thread CPU "
        f"seconds, 1 torch thread, medians of {args.repeats} alternated run(s) per version; the baseline is "
        f"commit {args.baseline} in a scratch worktree, same interpreter and packages).\n\n"
        f"{markdown_table(['workload', args.baseline, 'this commit', 'speed-up'], rows)}\n"
    )
    if "cartpole" in results:
        pairs = "; ".join(
            f"seed {before['seed']}: {before['seconds_per_step'] * 1e3:.1f} ms at q = {before['q']} vs "
            f"{after['seconds_per_step'] * 1e3:.1f} ms at q = {after['q']}"
            for before, after in zip(results["cartpole"]["baseline"], results["cartpole"]["current"], strict=True)
        )
        text += f"\nCartPole runs ({args.baseline} vs this commit; the cost grows with the q a run reaches): {pairs}.\n"
    if "quickstart" in results:
        returns = {
            version: ", ".join(f"{r['return_mean']:.2f} +- {r['return_std']:.2f}" for r in results["quickstart"][version])
            for version in versions
        }
        text += (
            f"\nQuickstart evaluation return (10 episodes, fixed starts, seed 0): {args.baseline}: "
            f"{returns['baseline']}; this commit: {returns['current']}.\n"
        )
    if "agreement" in results:
        agreement = {version: results["agreement"][version][0] for version in versions}
        norms = "; ".join(
            f"{key}: {agreement['baseline'][key]:.6g} vs {agreement['current'][key]:.6g}"
            for key in ("q", "B", "theta_psi", "theta_phi")
        )
        text += (
            f"\nAfter the same 400 random-phase steps (2 iterations, the same data), {args.baseline} vs this commit "
            f"(q, then Frobenius norms): {norms}.\n"
        )
    write_markdown(args.stem, text)


if __name__ == "__main__":
    main()
