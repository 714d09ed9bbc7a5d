"""Does planning on a fixed model converge? The learning curves' swings with the model held still.

Each run trains the Hydra config of its env (as ``python train.py env=<name>``, the env's
budget unless ``--steps``), then freezes everything but the planner: no new data, no feature
selection, no model update. It runs ``--blocks`` more blocks of ``evaluation.rounds``
evaluation/improvement rounds (exactly those of an iteration, a fresh collection C each round)
and after each block, and once before the first, measures

- ``return_mean``: the deterministic policy's true return, 10 episodes from the seed's fixed
  random starts (as learning_quality.py);
- ``value_bias``: the model's one-step optimism in the policy's value on those episodes, and
  ``slope``: the share of the true feature change the model predicts there
  (benchmarks/diagnostics/model_exploitation.py);
- ``changed``: the share of 1,000 fixed states of D whose greedy action differs from the policy
  the training ended with.

If the planner converged on a fixed model, the return would settle after a block or two; a
return that keeps moving while the model does not is the planner's doing, and a value bias that
rises as the return falls is the planner exploiting the model's error. Writes
results/<stem>.md and .csv (one row per measurement); each finished seed is kept in results/<stem>/ (rerun the same
command to resume; ``--report-only`` rewrites the report).

    python -m benchmarks.diagnostics.fixed_model_planning --env pendulum --seeds 0 1 2 3 4 5 6 7 8 9 --workers 2
"""

from __future__ import annotations

import argparse
import itertools
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from stable_baselines3.common.logger import configure

from benchmarks.common import RESULTS, command_line, compose_config, markdown_table, run_recorded, write_report
from benchmarks.diagnostics.model_exploitation import evaluate_with_model_errors
from benchmarks.learning_quality import TARGETS
from cme_agent.experiment import build_agent, make_env, make_eval_env

PROBE_STATES = 1_000
"""States of D on which the change of the greedy action is counted."""
MOVED = 20.0
"""A return that ends more than this (reward units) above or below where training left it has moved."""


@dataclass(frozen=True)
class Job:
    """One seed of ``env``: ``steps`` env steps of training (None: the config's budget), then
    ``blocks`` blocks of planning on the frozen model; its record goes to results/<stem>/."""

    env: str
    seed: int
    steps: int | None
    blocks: int
    overrides: tuple[str, ...]
    stem: str

    @property
    def record(self) -> Path:
        """results/<stem>/<env>_seed<seed>.json"""
        return RESULTS / self.stem / f"{self.env}_seed{self.seed}.json"


def plan_on_fixed_model(job: Job) -> list[dict[str, Any]]:
    """Train, then plan on the frozen model; one row per measurement (block 0: as trained)."""
    torch.set_num_threads(1)
    cfg = compose_config([f"env={job.env}", f"seed={job.seed}", "verbose=0", *job.overrides])
    model = build_agent(cfg, make_env(cfg))
    model.set_logger(configure(None, []))
    model.learn(job.steps or int(cfg.total_timesteps))
    probes = model.store.sample(PROBE_STATES, torch.Generator().manual_seed(job.seed)).obs
    trained_actions = model.policy.act(probes)
    rows = []
    for block in range(job.blocks + 1):
        if block > 0:
            with torch.no_grad():
                for _ in range(model.evaluation_config.rounds):
                    collection = model.draw_collection()
                    model.policy_improvement(model.policy_evaluation(collection), collection)
        row = {"env": job.env, "seed": job.seed, "block": block, "rounds": block * model.evaluation_config.rounds}
        row.update(evaluate_with_model_errors(model, make_eval_env(cfg)))
        row["changed"] = float((model.policy.act(probes) != trained_actions).reshape(PROBE_STATES, -1).any(1).float().mean())
        rows.append(row)
        print(f"{job.env} seed {job.seed} block {block}: {row['return_mean']:.1f}", flush=True)
    return rows


def report(env: str, curves: list[list[dict[str, Any]]], seeds: list[int], runs: list[str], wall: float, workers: int) -> str:
    """The markdown report: the return per block and seed, and how far it moved."""
    blocks = len(curves[0])
    rounds = [row["rounds"] for row in curves[0]]
    per_seed = [
        [seed, *(f"{row['return_mean']:.0f}" for row in curve), f"{curve[-1]['changed']:.2f}"]
        for seed, curve in zip(seeds, curves, strict=True)
    ]
    means = [statistics.mean(curve[b]["return_mean"] for curve in curves) for b in range(blocks)]
    stds = [statistics.pstdev(curve[b]["return_mean"] for curve in curves) for b in range(blocks)]
    per_seed.append(["mean +- std", *(f"{m:.1f} +- {s:.1f}" for m, s in zip(means, stds, strict=True)), ""])
    moves = [curve[-1]["return_mean"] - curve[0]["return_mean"] for curve in curves]
    up, down = sum(move > MOVED for move in moves), sum(move < -MOVED for move in moves)
    changes = [
        (later["value_bias"] - earlier["value_bias"], later["return_mean"] - earlier["return_mean"])
        for curve in curves
        for earlier, later in itertools.pairwise(curve)
    ]
    corr = float(np.corrcoef(*zip(*changes, strict=True))[0, 1]) if len(changes) > 2 else float("nan")
    falls = [(bias, ret) for bias, ret in changes if ret < -MOVED]
    return "\n".join(
        [
            f"# Planning on a fixed model: {env}",
            "",
            f"Command: `{command_line()}`; the runs: {'; '.join(f'`{run}`' for run in runs)}. Seeds {seeds}. "
            f"Each seed trains its env's config, then plans on the frozen model (no data, no features, no model "
            f"update) in blocks of {rounds[1] if blocks > 1 else 0} evaluation/improvement rounds; after each block "
            "the deterministic policy flies 10 episodes from the seed's fixed random starts "
            f"(benchmarks/diagnostics/fixed_model_planning.py). Wall-clock {wall:.0f} s with {workers} workers.",
            "",
            f"**After {rounds[-1]} more rounds on the same model the return moved by more than {MOVED:g}: up on "
            f"{up} seeds, down on {down}, within {MOVED:g} on {len(curves) - up - down}** "
            f"(change per seed: {', '.join(f'{move:+.0f}' for move in moves)}). Between consecutive measurements "
            f"({len(changes)} pairs) the change of the return correlates with the change of the model's value bias "
            f"on the policy's episodes at {corr:.2f}; in the {len(falls)} falls by more than {MOVED:g} the bias rose in "
            f"{sum(bias > 0 for bias, _ in falls)}.",
            "",
            markdown_table(
                ["seed", *(f"return after {r} rounds" for r in rounds), f"greedy actions changed after {rounds[-1]}"],
                per_seed,
            ),
            "",
        ]
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="pendulum", choices=list(TARGETS), help="a Hydra env config")
    parser.add_argument("--steps", type=int, help="env steps of training (default: the env config's budget)")
    parser.add_argument("--blocks", type=int, default=3, help="blocks of evaluation.rounds rounds on the frozen model")
    parser.add_argument("--seeds", nargs="+", type=int, default=list(range(10)))
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--overrides", nargs="*", default=[], help="Hydra overrides for every run")
    parser.add_argument("--stem", default="fixed_model_planning")
    parser.add_argument("--report-only", action="store_true", help="report the runs on record, train nothing")
    args = parser.parse_args()
    jobs = [Job(args.env, seed, args.steps, args.blocks, tuple(args.overrides), args.stem) for seed in args.seeds]
    curves, runs, wall = run_recorded(jobs, plan_on_fixed_model, args.workers, args.report_only, args.stem)
    write_report(args.stem, report(args.env, curves, args.seeds, runs, wall, args.workers), curves)


if __name__ == "__main__":
    main()
