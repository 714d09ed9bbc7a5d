"""Learning quality and stability of CMEPolicyIteration on the Gymnasium classics, 10 seeds.

Each run trains with the Hydra config of its env (exactly what ``python train.py env=<name>``
runs: the library's defaults and the env's preset, cme_agent/presets/<env id>.yaml) and pauses every
1,000 env steps for an evaluation: 10 episodes of the deterministic policy from fixed random
starts (the same at every evaluation of a seed, seeded apart from training,
:func:`cme_agent.experiment.make_eval_env`). Per env the report gives: how many seeds
reached the target and the median env steps to it, the final return (the last policy, not
the best one seen) as mean +- std over seeds, the worst seed's final return, and the worst
evaluation after the target was first reached (a collapse). Writes results/<stem>.md,
results/<stem>.csv and results/<stem>.png (every seed's curve and their mean).

Each finished run is kept in results/<stem>/<env>_seed<k>.json, so an interrupted benchmark
resumes where it stopped (rerun the same command); ``--report-only`` rewrites the report
from the records.

    python -m benchmarks.learning_quality --envs pendulum cartpole --seeds 0 1 2 [--workers 2]
    python -m benchmarks.learning_quality --stem learning_quality_soft --overrides agent.improvement.method=soft
    python -m benchmarks.learning_quality --envs --env-id InvertedPendulum-v5 --steps 5000 --target 950 \
        --kwargs '{"gamma": 0.95}' --stem lq_inverted_pendulum
    python -m benchmarks.learning_quality --envs --env-id InvertedPendulumKnownReward-v5 --steps 5000 --target 950 \
        --stem probe_ip_known_reward      # the exact reward given (benchmarks/known_reward_envs.py)
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import torch
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.logger import Logger, configure
from stable_baselines3.common.monitor import Monitor

from benchmarks import known_reward_envs  # noqa: F401  (registers the suite's envs with their exact reward under new ids)
from benchmarks.common import (
    RESULTS,
    command_line,
    compose_config,
    markdown_table,
    plot_learning_curves,
    save_record,
    write_report,
)
from benchmarks.unseen_envs import EVAL_SEED_OFFSET
from cme_agent import CMEPolicyIteration
from cme_agent.experiment import build_agent, make_env, make_eval_env

TARGETS = {  # env config: target return; the step budget is the env config's total_timesteps
    "pendulum": -200.0,
    "cartpole": 475.0,
    "acrobot": -100.0,
    "mountain_car": -130.0,
    "mountain_car_continuous": 90.0,
}
PERIOD = 1_000
"""Env steps between evaluations."""


def episode_returns(model: Any, env: gym.Env, episodes: int = 10) -> dict[str, float]:
    """Mean and std of the return of the deterministic policy over ``episodes`` episodes."""
    returns, _ = evaluate_policy(model, env, n_eval_episodes=episodes, return_episode_rewards=True)
    return {"return_mean": statistics.mean(returns), "return_std": statistics.pstdev(returns)}


def train_with_evaluations(
    env_name: str,
    seed: int,
    overrides: list[str],
    budget: int,
    period: int = PERIOD,
    evaluate: Callable[[Any, gym.Env], dict[str, float]] = episode_returns,
    logger: Logger | None = None,
) -> list[dict[str, Any]]:
    """Train the Hydra config ``env=<env_name>`` for ``budget`` env steps, evaluating every
    ``period`` steps on a fresh evaluation env (:func:`cme_agent.experiment.make_eval_env`: the
    seed's fixed starts, the same at every evaluation); one row per evaluation.

    :param evaluate: (model, fresh evaluation env) -> the row's statistics, ``return_mean`` among them
    :param logger: the agent's logger (default: one that writes nothing)
    """
    torch.set_num_threads(1)
    cfg = compose_config([f"env={env_name}", f"seed={seed}", "verbose=0", *overrides])
    model = build_agent(cfg, make_env(cfg))
    model.set_logger(configure(None, []) if logger is None else logger)
    return evaluation_loop(model, lambda: make_eval_env(cfg), env_name, seed, budget, period, evaluate)


def evaluation_loop(
    model: Any,
    make_evaluation_env: Callable[[], gym.Env],
    env_name: str,
    seed: int,
    budget: int,
    period: int,
    evaluate: Callable[[Any, gym.Env], dict[str, float]],
) -> list[dict[str, Any]]:
    """Train ``model`` until it has taken ``budget`` env steps, pausing every ``period`` steps to
    ``evaluate`` it on a fresh ``make_evaluation_env()``; one row per pause (with the training
    seconds so far and q). ``env_name`` and ``seed`` label the rows."""
    rows, train_seconds = [], 0.0
    while model.num_timesteps < budget:
        start = time.perf_counter()
        model.learn(min(period, budget - model.num_timesteps), reset_num_timesteps=False)
        train_seconds += time.perf_counter() - start
        row = {"env": env_name, "seed": seed, "steps": model.num_timesteps, "iteration": getattr(model, "iteration", None)}
        row.update(evaluate(model, make_evaluation_env()))
        row.update(n_features=getattr(model, "q", 0), train_seconds=round(train_seconds, 1))
        rows.append(row)
        print(
            f"{env_name} seed {seed} steps {model.num_timesteps}: {row['return_mean']:.1f} (q={row['n_features']})", flush=True
        )
    return rows


def train_gym_id(
    env_id: str,
    seed: int,
    kwargs: dict[str, Any],
    budget: int,
    period: int = PERIOD,
    evaluate: Callable[[Any, gym.Env], dict[str, float]] = episode_returns,
) -> list[dict[str, Any]]:
    """Train ``CMEPolicyIteration("CMEPolicy", env_id, seed=seed, **kwargs)`` (the library's
    defaults, and the env's preset if it has one) for ``budget`` env steps, evaluating every
    ``period`` steps on a fresh ``env_id`` seeded ``seed + EVAL_SEED_OFFSET`` (the same starts at
    every evaluation); one row per evaluation."""
    torch.set_num_threads(1)
    model = CMEPolicyIteration("CMEPolicy", env_id, seed=seed, **kwargs)
    model.set_logger(configure(None, []))

    def evaluation_env() -> gym.Env:
        env = Monitor(gym.make(env_id))
        env.reset(seed=seed + EVAL_SEED_OFFSET)
        return env

    return evaluation_loop(model, evaluation_env, env_id, seed, budget, period, evaluate)


@dataclass(frozen=True)
class Job:
    """One seed of one env: the Hydra config ``env`` with ``overrides`` (``steps`` None: the
    config's budget), or with ``steps`` given the Gymnasium id ``env`` with constructor
    ``kwargs`` (JSON); its record goes to results/<stem>/<env>_seed<seed>.json."""

    env: str
    seed: int
    overrides: tuple[str, ...]
    stem: str
    steps: int | None = None
    kwargs: str = "{}"

    @property
    def record(self) -> Path:
        return RESULTS / self.stem / f"{self.env}_seed{self.seed}.json"


def run_one(job: Job) -> list[dict[str, Any]]:
    """One seed of one env, read from its record if an earlier run of the benchmark finished it."""
    if job.record.exists():
        return json.loads(job.record.read_text())["curve"]
    if job.steps is None:
        budget = int(compose_config([f"env={job.env}"]).total_timesteps)
        curve = train_with_evaluations(job.env, job.seed, list(job.overrides), budget)
    else:
        curve = train_gym_id(job.env, job.seed, json.loads(job.kwargs), job.steps)
    record = {"overrides": list(job.overrides), "kwargs": job.kwargs, "command": command_line(), "curve": curve}
    save_record(job.record, record)
    return curve


def summarise(env_name: str, curves: list[list[dict[str, Any]]], target: float) -> list[Any]:
    """One row of the report: reach, final returns, worst seed, worst evaluation after the target."""
    finals = [curve[-1]["return_mean"] for curve in curves]
    reached = [next((i for i, row in enumerate(curve) if row["return_mean"] >= target), None) for curve in curves]
    steps_to = [curve[i]["steps"] for curve, i in zip(curves, reached, strict=True) if i is not None]
    after = [min(row["return_mean"] for row in curve[i:]) for curve, i in zip(curves, reached, strict=True) if i is not None]
    spread = statistics.stdev(finals) if len(finals) > 1 else 0.0
    return [
        env_name,
        curves[0][-1]["steps"],
        f"{target:g}",
        f"{len(steps_to)}/{len(curves)}",
        f"{statistics.median(steps_to):.0f}" if steps_to else "-",
        f"{statistics.mean(finals):.1f} +- {spread:.1f}",
        f"{min(finals):.0f}",
        f"{min(after):.0f}" if after else "-",
        ", ".join(f"{f:.0f}" for f in finals),
        f"{statistics.mean(curve[-1]['train_seconds'] for curve in curves):.0f}",
        f"{statistics.mean(curve[-1]['n_features'] for curve in curves):.0f}",
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="*", default=list(TARGETS), choices=list(TARGETS))
    parser.add_argument("--seeds", nargs="+", type=int, default=list(range(10)))
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--overrides", nargs="*", default=[], help="Hydra overrides for every run")
    parser.add_argument(
        "--env-id", help="also a Gymnasium id at the library's defaults (its preset if any), with --steps and --target"
    )
    parser.add_argument("--steps", type=int, help="--env-id: env steps per run")
    parser.add_argument("--target", type=float, help="--env-id: the return that counts as solved")
    parser.add_argument("--kwargs", default="{}", help="--env-id: constructor arguments of CMEPolicyIteration, as JSON")
    parser.add_argument("--stem", default="learning_quality", help="name of the results/<stem>.{md,csv,png} files")
    parser.add_argument("--report-only", action="store_true", help="report the runs on record, train nothing")
    args = parser.parse_args()
    if args.env_id and (args.steps is None or args.target is None):
        parser.error("--env-id needs --steps and --target")
    targets = {**{name: TARGETS[name] for name in args.envs}, **({args.env_id: args.target} if args.env_id else {})}
    jobs = [Job(name, seed, tuple(args.overrides), args.stem) for name in args.envs for seed in args.seeds]
    if args.env_id:
        jobs += [Job(args.env_id, seed, (), args.stem, args.steps, args.kwargs) for seed in args.seeds]
    if args.report_only:
        jobs = [job for job in jobs if job.record.exists()]
    start = time.perf_counter()
    with multiprocessing.get_context("spawn").Pool(args.workers) as pool:
        results = pool.map(run_one, jobs, chunksize=1)
    curves: dict[str, list[list[dict[str, Any]]]] = {}
    for job, curve in zip(jobs, results, strict=True):
        curves.setdefault(job.env, []).append(curve)
    header = [
        "env",
        "steps",
        "target",
        "seeds at target",
        "median steps to target",
        "final return (mean +- std)",
        "worst seed",
        "worst eval after target",
        "per seed (final)",
        "train s",
        "q",
    ]
    table = markdown_table(header, [summarise(env_name, runs, targets[env_name]) for env_name, runs in curves.items()])
    seeds = sorted({job.seed for job in jobs})
    made_by = sorted({json.loads(job.record.read_text())["command"] for job in jobs})
    text = (
        f"# Learning quality of CMEPolicyIteration\n\nCommand: `{command_line()}`; the runs: "
        + "; ".join(f"`{command}`" for command in made_by)
        + "\n\n"
        f"Seeds {seeds}; every {PERIOD:,} env steps an evaluation: 10 episodes of the deterministic policy from "
        "fixed random starts (the same at every evaluation of a seed, seeded apart from training). Final return = "
        "the last evaluation (the last policy, not the best one seen); 'median steps to target' over the seeds "
        "that reached it; 'worst eval after target' = the lowest evaluation of any seed after its first at or "
        f"above the target. Wall-clock of this invocation {time.perf_counter() - start:.0f} s with {args.workers} "
        f"workers (runs on record are read, not rerun).\n\n{table}\n"
    )
    write_report(args.stem, text, results)
    panels = {name: (runs, targets[name], "target") for name, runs in curves.items()}
    plot_learning_curves(panels, f"{args.stem}.png")


if __name__ == "__main__":
    main()
