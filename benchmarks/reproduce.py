"""Reproduce the paper's experiments, against the Kernel baseline and SB3, into results/.

One training run per (agent, env, seed), shared by every figure and table that needs it. Each
run trains the Hydra config ``python train.py agent=<agent> env=<env> seed=<seed>`` would run
(budget and evaluation period set here), evaluates the deterministic policy on 10 episodes
every few iterations, logs the seconds of every phase of every iteration, and is saved at once
to ``<out>/runs/<agent>-<env>-seed<seed>.json``. A run already saved is not run again: an
interrupted reproduction continues where it stopped, and ``--report-only`` redraws the
figures from the saved runs. Then it writes, into ``<out>``:

- ``figure1.{png,md}``: evaluation return per iteration, MP (agent=cme) and Kernel
  (agent=kernel), mean and standard error over seeds, on Toy, Mountain Car and Pendulum;
- ``figure2.{png,md}``: model-learning time (feature selection + model update) per iteration on
  Mountain Car, MP and Kernel, with fitted growth exponents, and a scaling run of MP alone to
  100,000 transitions: seconds per phase and memory against |D|;
- ``figure3.{png,md}``: Quadcopter-v0 return per iteration, the mean and each run, with the
  scripted controller's return as a line;
- ``sample_efficiency.md``: env steps (and wall-clock) to reach each env's threshold, MP vs
  Kernel vs the best SB3 algorithm;
- beside each report, its CSV: every evaluation (figure 2: every iteration's seconds) of every
  run it draws.

MP's runs on Mountain Car keep the paper's SGD update (``PAPER_UPDATE``); every other run is the
config ``train.py`` would run, its env's preset included.

    python -m benchmarks.reproduce --quick    # a few minutes, 2 seeds and short runs, into results/quick/
    python -m benchmarks.reproduce            # the full version (10 seeds, 5 for the table), into results/
    python -m benchmarks.reproduce --only figure2 --report-only   # redraw from saved runs
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from functools import cache, partial
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.logger import KVWriter, Logger

from benchmarks.common import (
    RESULTS,
    code_version,
    command_line,
    compose_config,
    machine,
    markdown_table,
    pyplot,
    resident_bytes,
    save_record,
    write_csv,
)
from benchmarks.learning_quality import TARGETS, episode_returns, train_with_evaluations
from benchmarks.quadcopter_learning import controller_statistics, flight_statistics
from cme_agent.config import AgentConfig
from cme_agent.presets import apply_preset

FIGURE1_ENVS = ("toy", "mountain_car", "pendulum")
PAPER_UPDATE = {"mountain_car": ["agent.model_update.method=sgd"]}
"""Overrides of agent=cme's runs per env: Mountain Car's (figures 1 and 2, the table's row) keep the
paper's SGD update of B (eq. (6)), whose cost per iteration figure 2 measures against Kernel's;
the library's preset refits B exactly (docs/results.md, "Mountain Car's preset refits B")."""
TABLE_ENVS = ("pendulum", "cartpole", "mountain_car", "acrobot", "mountain_car_continuous")
# Iterations of the policy-iteration agents per env (MP and Kernel alike: the paper compares per
# iteration, Kernel collecting half the data per iteration), and the evaluation period in iterations.
# These are the protocol of the paper's figures, counted in iterations, not an env-step budget: the
# env-step budget of a training run is the env config's total_timesteps (conf/env/<name>.yaml).
ITERATIONS = {
    "toy": (20, 2),
    "mountain_car": (60, 5),
    "pendulum": (30, 3),
    "cartpole": (50, 5),
    "acrobot": (50, 5),
    "mountain_car_continuous": (30, 3),
    "quadcopter": (100, 10),
}
# SB3 algorithms whose action space fits, with their env-step budget (the zoo trains longer; these
# budgets are several times the policy-iteration agents').
SB3_AGENTS = {
    "pendulum": (("sac", "td3", "ppo"), 20_000),
    "cartpole": (("ppo", "dqn"), 50_000),
    "mountain_car": (("dqn", "ppo"), 100_000),
    "acrobot": (("dqn", "ppo"), 50_000),
    "mountain_car_continuous": (("sac", "td3", "ppo"), 50_000),
}
SB3_EVALUATIONS = 20  # evaluations per SB3 run


@dataclass(frozen=True)
class Profile:
    """What a reproduction runs: the seeds of each part and the length of the runs.

    :param figure_seeds: seeds of figures 1 and 3
    :param table_seeds: seeds of the sample-efficiency table
    :param scale: fraction of the full iterations (and SB3 budgets) each run gets
    :param scaling_steps: env steps of figure 2's MP scaling run
    :param table_envs: envs of the sample-efficiency table
    :param sb3_agents: at most this many SB3 algorithms per env (the first ones of SB3_AGENTS)
    :param out: where the figures, tables and runs go
    """

    figure_seeds: tuple[int, ...]
    table_seeds: tuple[int, ...]
    scale: float
    scaling_steps: int
    table_envs: tuple[str, ...] = TABLE_ENVS
    sb3_agents: int = 3
    out: Path = field(default=RESULTS)


PROFILES = {
    "full": Profile(figure_seeds=tuple(range(10)), table_seeds=tuple(range(5)), scale=1.0, scaling_steps=100_000),
    "quick": Profile(
        figure_seeds=(0, 1),
        table_seeds=(0,),
        scale=0.2,
        scaling_steps=6_000,
        table_envs=("pendulum", "mountain_car"),
        sb3_agents=1,
        out=RESULTS / "quick",
    ),
}


@dataclass(frozen=True)
class Run:
    """One training run: ``python train.py agent=<agent> env=<env> seed=<seed>`` for ``steps`` env
    steps, evaluated every ``eval_every`` env steps."""

    agent: str
    env: str
    seed: int
    steps: int
    eval_every: int
    tag: str = ""

    @property
    def name(self) -> str:
        return run_name(self.agent, self.env, self.seed, self.tag)


def run_name(agent: str, env: str, seed: int, tag: str = "") -> str:
    """The file stem of a saved run."""
    return f"{agent}-{env}-seed{seed}" + (f"-{tag}" if tag else "")


def policy_iteration_run(agent: str, env: str, seed: int, profile: Profile) -> Run:
    """A run of agent=cme or agent=kernel for ITERATIONS[env] (scaled) iterations."""
    iterations, period = ITERATIONS[env]
    iterations = max(math.ceil(iterations * profile.scale), 2)
    period = max(min(period, iterations // 2), 1)
    per_iteration = steps_per_iteration(agent, env)
    return Run(agent, env, seed, iterations * per_iteration, period * per_iteration)


@cache
def steps_per_iteration(agent: str, env: str) -> int:
    """Env steps per iteration of agent=cme or agent=kernel on ``env`` (composing a config takes a while)."""
    cfg = compose_config([f"agent={agent}", f"env={env}"])
    settings, _ = apply_preset(cfg.env.id, {"steps_per_iteration": cfg.agent.steps_per_iteration})  # null: the preset's
    return int(settings.get("steps_per_iteration", AgentConfig().steps_per_iteration))


def planned_runs(parts: Sequence[str], profile: Profile) -> list[Run]:
    """Every run the parts need, most informative first, without repeats."""
    runs: list[Run] = []
    if "figure2" in parts:
        runs.append(Run("cme", "mountain_car", 0, profile.scaling_steps, profile.scaling_steps, tag="scaling"))
    if "figure1" in parts or "figure2" in parts:
        envs = FIGURE1_ENVS if "figure1" in parts else ("mountain_car",)
        runs += [policy_iteration_run(a, e, s, profile) for s in profile.figure_seeds for e in envs for a in ("cme", "kernel")]
    if "figure3" in parts:
        runs += [policy_iteration_run("cme", "quadcopter", s, profile) for s in profile.figure_seeds]
    if "table" in parts:
        for seed in profile.table_seeds:
            for env in profile.table_envs:
                runs += [policy_iteration_run(a, env, seed, profile) for a in ("cme", "kernel")]
                agents, budget = SB3_AGENTS[env]
                steps = int(budget * profile.scale)
                runs += [Run(a, env, seed, steps, steps // SB3_EVALUATIONS) for a in agents[: profile.sb3_agents]]
    unique = {run.name: run for run in runs}
    if len(unique) < len(runs):  # the same (agent, env, seed) asked for twice must agree on its length
        for run in runs:
            assert unique[run.name] == run, f"conflicting runs {run} and {unique[run.name]}"
    return list(unique.values())


class IterationLog(KVWriter):
    """Keeps, from each of the agent's per-iteration log dumps, the seconds of every phase, |D|, q
    and the process's resident memory."""

    def __init__(self) -> None:
        self.rows: list[dict[str, float]] = []

    def write(self, key_values: dict[str, Any], key_excluded: dict[str, Any], step: int = 0) -> None:
        if "time/model_update" not in key_values:
            return
        row = {key.split("/")[1]: float(value) for key, value in key_values.items() if key.startswith("time/")}
        row.update(
            transitions=float(key_values["train/transitions"]),
            q=float(key_values.get("train/n_features", 0)),
            rss_bytes=float(resident_bytes()),
        )
        self.rows.append(row)

    def close(self) -> None:
        pass


def run_overrides(run: Run) -> list[str]:
    """The Hydra overrides a run trains with: its agent, and for agent=cme its env's ``PAPER_UPDATE``."""
    return [f"agent={run.agent}", *(PAPER_UPDATE.get(run.env, []) if run.agent == "cme" else [])]


def execute(job: tuple[Run, Path]) -> str:
    """Train one run and save it (atomically) as JSON; return a line for the progress log."""
    run, path = job
    log = IterationLog()
    start = time.perf_counter()
    evaluate: Callable[[Any, gym.Env], dict[str, float]] = (
        flight_statistics if run.env == "quadcopter" else partial(episode_returns, episodes=10)
    )
    logger = Logger(None, [log])
    evaluations = train_with_evaluations(run.env, run.seed, run_overrides(run), run.steps, run.eval_every, evaluate, logger)
    record = {
        "run": asdict(run),
        "commit": code_version(),
        "machine": machine(),
        "seconds": time.perf_counter() - start,
        "evaluations": evaluations,
        "iterations": log.rows,
    }
    save_record(path, record)
    return f"{run.name}: {evaluations[-1]['return_mean']:.1f} after {run.steps} steps ({record['seconds']:.0f} s)"


def run_all(runs: list[Run], directory: Path, workers: int) -> None:
    """Execute the runs not saved yet in ``directory``, ``workers`` at a time, each in a fresh process."""
    directory.mkdir(parents=True, exist_ok=True)
    todo = [(run, directory / f"{run.name}.json") for run in runs if not (directory / f"{run.name}.json").exists()]
    print(f"{len(runs) - len(todo)} of {len(runs)} runs already saved in {directory}; running {len(todo)}", flush=True)
    if not todo:
        return
    with multiprocessing.get_context("spawn").Pool(workers, maxtasksperchild=1) as pool:
        for done, line in enumerate(pool.imap_unordered(execute, todo, chunksize=1), start=1):
            print(f"[{done}/{len(todo)}] {line}", flush=True)


def load_runs(directory: Path, agent: str, env: str, seeds: Sequence[int], tag: str = "") -> list[dict[str, Any]]:
    """The saved runs of ``agent`` on ``env`` for those of ``seeds`` that exist."""
    paths = [directory / f"{run_name(agent, env, seed, tag)}.json" for seed in seeds]
    return [json.loads(path.read_text()) for path in paths if path.exists()]


def mean_and_se(values: Sequence[float]) -> tuple[float, float]:
    """Mean and standard error of the mean (0 for a single value)."""
    spread = statistics.stdev(values) / math.sqrt(len(values)) if len(values) > 1 else 0.0
    return statistics.mean(values), spread


def curve(runs: list[dict[str, Any]], key: str = "return_mean") -> tuple[list[int], list[float], list[float]]:
    """Iterations, mean and standard error over runs of ``key`` at each evaluation all runs share."""
    shared = min(len(run["evaluations"]) for run in runs)
    iterations = [runs[0]["evaluations"][i]["iteration"] for i in range(shared)]
    stats = [mean_and_se([run["evaluations"][i][key] for run in runs]) for i in range(shared)]
    return iterations, [m for m, _ in stats], [s for _, s in stats]


def model_seconds(row: dict[str, float]) -> float:
    """Model-learning seconds of one iteration: feature selection plus model update."""
    return row.get("feature_selection", 0.0) + row["model_update"]


def growth_exponent(sizes: Sequence[float], seconds: Sequence[float]) -> float:
    """Slope of log(seconds) against log(size), fitted on the second half of the points: the
    exponent of a power law seconds ~ size^k (0: flat, 3: cubic)."""
    half = len(sizes) // 2
    return float(np.polyfit(np.log(sizes[half:]), np.log(np.maximum(seconds[half:], 1e-9)), 1)[0])


def save_figure(fig: Any, path: Path) -> None:
    fig.suptitle(command_line().replace("`", ""), fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def provenance(runs_dir: Path, runs: Sequence[dict[str, Any]]) -> str:
    """The command drawing a figure and the commits of the code that made the saved ``runs`` it draws."""
    commits = sorted({run["commit"] for run in runs})
    return f"Command: `{command_line()}`. Runs (in `{runs_dir.name}/`) made at commit `{', '.join(commits) or 'none'}`."


def write_text(path: Path, text: str) -> None:
    print(text)
    path.write_text(text)


def write_runs_csv(path: Path, runs: Sequence[dict[str, Any]], rows: str = "evaluations") -> None:
    """Every row of every run's ``rows`` (``evaluations`` or ``iterations``) as one CSV, each
    prefixed with its run's env, agent, seed, tag, env-step budget and commit."""
    prefix = ("env", "agent", "seed", "tag")
    write_csv(
        path,
        [
            {key: run["run"][key] for key in prefix} | {"budget": run["run"]["steps"], "commit": run["commit"]} | row
            for run in runs
            for row in run[rows]
        ],
    )


def figure1(profile: Profile, runs_dir: Path) -> None:
    """Return per iteration, MP vs Kernel, mean and SE over seeds, on FIGURE1_ENVS."""
    plt = pyplot()
    fig, axes = (None, [None] * len(FIGURE1_ENVS)) if plt is None else plt.subplots(1, 3, figsize=(14, 3.8))
    rows, drawn = [], []
    for ax, env in zip(axes, FIGURE1_ENVS, strict=True):
        finals = {}
        for agent, label in (("cme", "MP"), ("kernel", "Kernel")):
            runs = load_runs(runs_dir, agent, env, profile.figure_seeds)
            if not runs:
                continue
            drawn += runs
            iterations, mean, se = curve(runs)
            finals[label] = (mean[-1], se[-1], len(runs), statistics.mean(mean))
            if ax is not None:
                ax.plot(iterations, mean, label=f"{label} ({len(runs)} seeds, {runs[0]['run']['steps']} steps)")
                ax.fill_between(iterations, np.subtract(mean, se), np.add(mean, se), alpha=0.25)
        if ax is not None:
            ax.set_title(compose_config([f"env={env}"]).env.id, fontsize=10)
            ax.set_xlabel("iteration")
            ax.set_ylabel("evaluation return (10 episodes)")
            ax.legend(fontsize=8)
        if "MP" in finals and "Kernel" in finals:
            (mp, mp_se, n_mp, mp_avg), (kernel, kernel_se, n_kernel, kernel_avg) = finals["MP"], finals["Kernel"]
            verdict = "yes" if mp >= kernel - kernel_se else "no"
            mp_cell, kernel_cell = f"{mp:.1f} +- {mp_se:.1f} ({n_mp})", f"{kernel:.1f} +- {kernel_se:.1f} ({n_kernel})"
            rows.append([env, mp_cell, kernel_cell, verdict, f"{mp_avg:.1f}", f"{kernel_avg:.1f}"])
    if fig is not None:
        save_figure(fig, profile.out / "figure1.png")
    header = [
        "env",
        "MP final (seeds)",
        "Kernel final (seeds)",
        "MP >= Kernel - SE",
        "MP mean over curve",
        "Kernel mean over curve",
    ]
    write_text(
        profile.out / "figure1.md",
        f"# Figure 1: return per iteration, MP vs Kernel\n\n{provenance(runs_dir, drawn)}\n\n"
        "Evaluation return (10 episodes of the deterministic policy, random starts) at the last iteration, mean +- "
        "standard error over seeds; 'mean over curve' averages the mean curve over all evaluated iterations. MP collects "
        "agent=cme's steps per iteration, Kernel half as many.\n\n"
        f"{markdown_table(header, rows)}\n\n![figure 1](figure1.png)\n",
    )
    write_runs_csv(profile.out / "figure1.csv", drawn)


def figure2(profile: Profile, runs_dir: Path) -> None:
    """Model-learning time per iteration on Mountain Car (MP vs Kernel) and MP's scaling run."""
    lines, series, drawn = [], {}, []
    for agent, label in (("cme", "MP"), ("kernel", "Kernel")):
        runs = load_runs(runs_dir, agent, "mountain_car", profile.figure_seeds)
        if not runs:
            continue
        drawn += runs
        shared = min(len(run["iterations"]) for run in runs)
        seconds = [statistics.median(model_seconds(run["iterations"][i]) for run in runs) for i in range(shared)]
        sizes = [runs[0]["iterations"][i]["transitions"] for i in range(shared)]
        features = [statistics.median(run["iterations"][i]["q"] for run in runs) for i in range(shared)]
        early, late = statistics.median(seconds[3:6]), statistics.median(seconds[-3:])
        q_early, q_late = statistics.median(features[3:6]), statistics.median(features[-3:])
        series[label] = (sizes, seconds)
        lines.append(
            f"- {label} ({len(runs)} seeds, median over seeds): {early * 1000:.1f} ms at iterations 4-6, {late * 1000:.1f} ms "
            f"at the last 3 (of {shared}); ratio {late / early:.2f}; fitted growth exponent in |D| "
            f"{growth_exponent(sizes, seconds):.2f}; q {q_early:.0f} at iterations 4-6, {q_late:.0f} at the last 3, "
            f"so per feature the ratio is {(late / q_late) / (early / q_early):.2f}"
        )
    scaling = load_runs(runs_dir, "cme", "mountain_car", [0], tag="scaling")
    drawn += scaling
    if scaling:
        rows = scaling[0]["iterations"]
        sizes = [row["transitions"] for row in rows]
        tenth = max(len(rows) // 10, 1)
        for phase in ("data_acquisition", "feature_selection", "model_update", "policy_evaluation", "policy_improvement"):
            early = statistics.median(row[phase] for row in rows[tenth : 2 * tenth])
            late = statistics.median(row[phase] for row in rows[-tenth:])
            exponent = growth_exponent(sizes, [row[phase] for row in rows])
            lines.append(
                f"- MP scaling run, {phase}: {early * 1000:.1f} ms per iteration in the second tenth, {late * 1000:.1f} ms "
                f"in the last tenth (ratio {late / early:.2f}; growth exponent {exponent:.2f})"
            )
        growth = np.polyfit(sizes[tenth:], [row["rss_bytes"] for row in rows[tenth:]], 1)[0]
        lines.append(
            f"- MP scaling run: {sizes[-1]:.0f} transitions, q {rows[-1]['q']:.0f}; resident memory "
            f"{rows[0]['rss_bytes'] / 2**20:.0f} MiB after iteration 1, {rows[-1]['rss_bytes'] / 2**20:.0f} MiB at the end "
            f"(fitted {growth:.0f} bytes per transition)"
        )
    write_text(
        profile.out / "figure2.md",
        f"# Figure 2: model-learning time per iteration\n\n{provenance(runs_dir, drawn)}\n\n"
        "Model-learning time = feature selection + model update (wall-clock, one torch thread; the machine is shared, "
        "so medians). The target: MP's last iteration within 1.5x of iteration 5, Kernel's growing more than "
        "10x.\n\n" + "\n".join(lines) + "\n\n![figure 2](figure2.png)\n",
    )
    write_runs_csv(profile.out / "figure2.csv", drawn, rows="iterations")
    plt = pyplot()
    if plt is None:
        return
    fig, axes = plt.subplots(1, 3, figsize=(14, 3.8))
    for label, (_, seconds) in series.items():
        axes[0].plot(range(1, len(seconds) + 1), seconds, label=label)
    axes[0].set_yscale("log")
    axes[0].set_xlabel("iteration")
    axes[0].set_ylabel("model-learning seconds (median over seeds)")
    axes[0].set_title("MountainCar-v0: MP vs Kernel", fontsize=10)
    axes[0].legend(fontsize=8)
    if scaling:
        rows = scaling[0]["iterations"]
        sizes = [row["transitions"] for row in rows]
        for phase in ("data_acquisition", "feature_selection", "model_update", "policy_evaluation", "policy_improvement"):
            axes[1].plot(sizes, [row[phase] for row in rows], linewidth=0.7, label=phase)
        axes[1].set_xlabel("|D| (transitions)")
        axes[1].set_ylabel("seconds per iteration")
        axes[1].set_title("MP alone: seconds per phase", fontsize=10)
        axes[1].legend(fontsize=7)
        axes[2].plot(sizes, [row["rss_bytes"] / 2**20 for row in rows], color="tab:blue")
        axes[2].set_ylabel("resident memory (MiB)", color="tab:blue")
        axes[2].set_xlabel("|D| (transitions)")
        axes[2].set_title("MP alone: memory and q", fontsize=10)
        features = axes[2].twinx()
        features.plot(sizes, [row["q"] for row in rows], color="tab:orange")
        features.set_ylabel("q (features)", color="tab:orange")
    save_figure(fig, profile.out / "figure2.png")


def collapse_distances(runs: list[dict[str, Any]], reference: float, from_steps: int) -> tuple[list[float], list[float]]:
    """Final distances to the target (m) of the evaluations from ``from_steps`` env steps on, split
    into collapses (return under half of ``reference``, the controller's) and the others."""
    collapsed, others = [], []
    for run in runs:
        for row in run["evaluations"]:
            if row["steps"] >= from_steps:
                (collapsed if row["return_mean"] < reference / 2 else others).append(row["final_distance"])
    return collapsed, others


def distance_summary(distances: Sequence[float]) -> str:
    """``median M m (range A to B m)`` of final distances, or ``none``."""
    if not distances:
        return "none"
    return f"median {statistics.median(distances):.2f} m (range {min(distances):.2f} to {max(distances):.2f} m)"


def figure3(profile: Profile, runs_dir: Path) -> None:
    """Quadcopter return per iteration: each run, their mean, the scripted controller's return."""
    runs = load_runs(runs_dir, "cme", "quadcopter", profile.figure_seeds)
    if not runs:
        return
    seeds = [run["run"]["seed"] for run in runs]
    controller = [controller_statistics(seed) for seed in seeds]
    reference = statistics.mean(c["return_mean"] for c in controller)
    fractions = [run["evaluations"][-1]["return_mean"] / c["return_mean"] for run, c in zip(runs, controller, strict=True)]
    finals = [run["evaluations"][-1] for run in runs]
    rows = [
        [seed, f"{final['return_mean']:.1f}", f"{c['return_mean']:.1f}", f"{fraction:.2f}", f"{final['final_distance']:.2f}"]
        for seed, final, c, fraction in zip(seeds, finals, controller, fractions, strict=True)
    ]
    mean, se = mean_and_se(fractions)
    spread = se * math.sqrt(len(fractions))  # the std over seeds
    distances = [final["final_distance"] for final in finals]
    second_half = runs[0]["run"]["steps"] // 2
    collapsed, others = collapse_distances(runs, reference, second_half)
    header = ["seed", "CME return", "controller return", "fraction", "CME final distance (m)"]
    write_text(
        profile.out / "figure3.md",
        f"# Figure 3: Quadcopter-v0\n\n{provenance(runs_dir, runs)}\n\n"
        f"Final evaluation after {runs[0]['run']['steps']} env steps (10 episodes, random starts); fraction of the scripted "
        f"controller's return on the same starts: {mean:.2f} +- {se:.2f} (mean +- SE over {len(runs)} seeds; "
        f"std {spread:.2f}, {sum(f >= 0.8 for f in fractions)} of {len(runs)} seeds at 0.80 or more). "
        f"Final distance to the target: {distance_summary(distances)}.\n\n"
        f"Collapses: of the {len(collapsed) + len(others)} evaluations from {second_half} steps on, {len(collapsed)} "
        f"score under half the controller's return; their final distance to the target is {distance_summary(collapsed)}, "
        f"that of the others {distance_summary(others)}.\n\n"
        f"{markdown_table(header, rows)}\n\n![figure 3](figure3.png)\n",
    )
    write_runs_csv(profile.out / "figure3.csv", runs)
    plt = pyplot()
    if plt is None:
        return
    fig, ax = plt.subplots(figsize=(7, 4))
    for run in runs:
        ax.plot([r["iteration"] for r in run["evaluations"]], [r["return_mean"] for r in run["evaluations"]], alpha=0.35)
    iterations, mean_curve, _ = curve(runs)
    ax.plot(iterations, mean_curve, color="black", linewidth=2, label=f"mean of {len(runs)} runs")
    ax.axhline(reference, color="red", linestyle="--", label="scripted controller")
    ax.set_xlabel("iteration")
    ax.set_ylabel("evaluation return (10 episodes)")
    ax.legend(fontsize=8)
    save_figure(fig, profile.out / "figure3.png")


def reach(run: dict[str, Any], threshold: float) -> tuple[int, float] | None:
    """Env steps and training seconds at the first evaluation at or above ``threshold``."""
    for row in run["evaluations"]:
        if row["return_mean"] >= threshold:
            return row["steps"], row["train_seconds"]
    return None


def efficiency(runs: list[dict[str, Any]], threshold: float) -> dict[str, Any]:
    """Steps and seconds to the threshold (median over the seeds that reached it) and final returns."""
    reached = [r for r in (reach(run, threshold) for run in runs) if r is not None]
    finals = [run["evaluations"][-1]["return_mean"] for run in runs]
    return {
        "reached": len(reached),
        "seeds": len(runs),
        "steps": statistics.median(r[0] for r in reached) if reached else math.inf,
        "seconds": statistics.median(r[1] for r in reached) if reached else math.inf,
        "final": f"{statistics.mean(finals):.1f} +- {statistics.stdev(finals) if len(finals) > 1 else 0.0:.1f}",
        "budget": runs[0]["run"]["steps"],
        "train_seconds": statistics.mean(run["evaluations"][-1]["train_seconds"] for run in runs),
    }


def efficiency_cells(name: str, stats: dict[str, Any]) -> list[Any]:
    steps = "-" if not stats["reached"] else f"{stats['steps']:.0f}"
    seconds = "-" if not stats["reached"] else f"{stats['seconds']:.0f}"
    return [
        name,
        f"{steps} ({stats['reached']}/{stats['seeds']})",
        seconds,
        stats["final"],
        stats["budget"],
        f"{stats['train_seconds']:.0f}",
    ]


def sample_efficiency(profile: Profile, runs_dir: Path) -> None:
    """Steps to each env's threshold: MP, Kernel, every SB3 algorithm, and the best SB3 one."""
    best_rows, all_rows, drawn = [], [], []
    for env in profile.table_envs:
        threshold = TARGETS[env]
        agents = ["cme", "kernel", *SB3_AGENTS[env][0][: profile.sb3_agents]]
        loaded = {a: runs for a in agents if (runs := load_runs(runs_dir, a, env, profile.table_seeds))}
        drawn += [run for runs in loaded.values() for run in runs]
        stats = {a: efficiency(runs, threshold) for a, runs in loaded.items()}
        sb3 = [a for a in stats if a not in ("cme", "kernel")]
        best = min(sb3, key=lambda a: (-stats[a]["reached"], stats[a]["steps"]), default=None)
        for agent in stats:
            name = {"cme": "MP", "kernel": "Kernel"}.get(agent, agent.upper())
            all_rows.append([env, f"{threshold:g}", *efficiency_cells(name, stats[agent])])
            if agent in ("cme", "kernel") or agent == best:
                best_rows.append(
                    [env, f"{threshold:g}", *efficiency_cells(name if agent != best else f"best SB3: {name}", stats[agent])]
                )
    header = [
        "env",
        "threshold",
        "agent",
        "steps to threshold (seeds reached)",
        "seconds to threshold",
        "final return",
        "budget",
        "train s",
    ]
    write_text(
        profile.out / "sample_efficiency.md",
        f"# Sample efficiency: env steps to each env's threshold\n\n{provenance(runs_dir, drawn)}\n\n"
        f"Seeds {list(profile.table_seeds)} (n in 'k/n' counts those with a saved run). "
        "Steps (and training wall-clock seconds) to the first evaluation (10 episodes, "
        "deterministic policy) at or above the threshold: median over the seeds that reached it within the budget, and "
        "how many did. Final return: mean +- std over seeds at the end of the budget. 'Best SB3' is the SB3 algorithm "
        "that reached the threshold on the most seeds, then in the fewest steps.\n\n"
        f"{markdown_table(header, best_rows)}\n\n## Every algorithm\n\n{markdown_table(header, all_rows)}\n",
    )
    write_runs_csv(profile.out / "sample_efficiency.csv", drawn)


PARTS = {"figure1": figure1, "figure2": figure2, "figure3": figure3, "table": sample_efficiency}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="a few minutes: 2 seeds, short runs, into results/quick/")
    parser.add_argument("--only", nargs="+", choices=list(PARTS), default=list(PARTS), help="the parts to make")
    parser.add_argument("--workers", type=int, default=2, help="runs in parallel (one process and torch thread each)")
    parser.add_argument("--report-only", action="store_true", help="draw from the saved runs, run nothing")
    args = parser.parse_args()
    profile = PROFILES["quick" if args.quick else "full"]
    runs_dir = profile.out / "runs"
    start = time.perf_counter()
    if not args.report_only:
        run_all(planned_runs(args.only, profile), runs_dir, args.workers)
    profile.out.mkdir(parents=True, exist_ok=True)
    for part in args.only:
        PARTS[part](profile, runs_dir)
    print(f"reproduce.py ({'quick' if args.quick else 'full'}, parts {args.only}) took {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
