"""Helpers shared by the benchmark scripts: composing the Hydra configs, writing results."""

from __future__ import annotations

import argparse
import csv
import functools
import json
import multiprocessing
import os
import platform
import resource
import shlex
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Protocol

import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "results"


def compose_config(overrides: list[str]) -> DictConfig:
    """The config ``python train.py <overrides>`` would run with."""
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        return compose(config_name="config", overrides=overrides)


def command_line() -> str:
    """The command that is running, as a user would type it from the repository root, and the
    commit of the code it ran (with ``+changes`` if the work tree differed from it)."""
    script = Path(sys.argv[0]).resolve()
    if script.suffix == ".py" and script.is_relative_to(ROOT / "benchmarks"):  # a benchmark, run as a module
        program = ["-m", ".".join(script.relative_to(ROOT).with_suffix("").parts)]
    else:  # e.g. pytest's entry point
        program = [str(script.relative_to(ROOT) if script.is_relative_to(ROOT) else script)]
    command = " ".join(["python", *program, *(shlex.quote(a) for a in sys.argv[1:])])
    return f"{command}` at commit `{code_version()}"


def machine() -> str:
    """The CPU and the BLAS code path a run used: runs at one commit round differently, and so
    differ from the first iteration, on CPUs whose MKL kernels differ (AVX2 against AVX-512)."""
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            model = next((line.split(":", 1)[1].strip() for line in cpuinfo if line.startswith("model name")), "")
    except OSError:
        model = ""
    forced = os.environ.get("MKL_ENABLE_INSTRUCTIONS")
    path = f"torch {torch.backends.cpu.get_cpu_capability()}" + (f", MKL_ENABLE_INSTRUCTIONS={forced}" if forced else "")
    return f"{model or platform.processor() or 'unknown CPU'} ({path})"


def code_version() -> str:
    """``git describe``-like id of the code: the short commit hash, ``+changes`` if tracked files
    outside ``results/`` differ from it (the outputs a run writes do not make its code dirty)."""
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True)
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", "--", ".", ":(exclude)results"],
            cwd=ROOT,
            capture_output=True,
            text=True,
        )
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return commit.stdout.strip() + ("+changes" if dirty.stdout.strip() else "")


def resident_bytes() -> int:
    """Current resident set size of this process (Linux), in bytes."""
    with open("/proc/self/statm") as handle:
        return int(handle.read().split()[1]) * resource.getpagesize()


def markdown_table(header: list[str], rows: list[list[Any]]) -> str:
    """A GitHub-flavoured markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)


class SeedFiles:
    """Where a diagnostic's seed job keeps its files: a frozen job dataclass with ``env_id``,
    ``seed`` and ``stem`` fields inherits :attr:`path`."""

    env_id: str
    seed: int
    stem: str

    @property
    def path(self) -> Path:
        """results/<stem>/<env>_seed<k>, without a suffix: the agent is its .zip, the record its .json."""
        return RESULTS / self.stem / f"{self.env_id}_seed{self.seed}"


def add_seed_arguments(parser: argparse.ArgumentParser, stem: str) -> None:
    """The arguments of a benchmark that trains one agent per seed and measures it: ``--seeds``,
    ``--steps``, ``--kwargs`` (constructor arguments as JSON), ``--workers`` and ``--stem``."""
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--steps", type=int, default=5000, help="env steps of training before the measurement")
    parser.add_argument("--kwargs", default="{}", help="constructor arguments as JSON (default: none)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--stem", default=stem)


def map_seeds(run_seed: Callable[[Any], dict[str, Any]], jobs: Sequence[Any], workers: int) -> list[dict[str, Any]]:
    """``run_seed`` (a module-level function) on every job, ``workers`` at a time in fresh processes."""
    with multiprocessing.get_context("spawn").Pool(min(workers, len(jobs))) as pool:
        return pool.map(run_seed, jobs)


def seed_table(rows: list[dict[str, Any]], columns: Sequence[str], metrics: Sequence[str]) -> list[list[Any]]:
    """One table row per seed (``columns`` as they are, ``metrics`` to 3 decimals), then, with more
    than one seed, the metrics' mean +- std over the seeds."""
    table = [[*(row[key] for key in columns), *(f"{row[key]:.3f}" for key in metrics)] for row in rows]
    if len(rows) > 1:
        spread = [f"{statistics.mean(r[k] for r in rows):.3f} +- {statistics.stdev(r[k] for r in rows):.3f}" for k in metrics]
        table.append(["mean +- std", *([""] * (len(columns) - 1)), *spread])
    return table


def save_record(path: Path, record: dict[str, Any]) -> None:
    """Write ``record`` as JSON atomically (an interrupted job never leaves a broken file)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_suffix(".tmp")
    temporary.write_text(json.dumps(record, indent=1))
    os.replace(temporary, path)


def write_markdown(stem: str, text: str) -> None:
    """Print ``text`` and write it to results/<stem>.md."""
    print(text)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{stem}.md").write_text(text)


def write_csv(path: Path, rows: Sequence[dict[str, Any]]) -> None:
    """``rows`` as a CSV whose columns are every key of any row, in order of first appearance."""
    fields = list(dict.fromkeys(key for row in rows for key in row))
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)


def write_report(stem: str, text: str, curves: list[list[dict[str, Any]]]) -> None:
    """Print ``text`` and write it to results/<stem>.md, the learning curves (one row per
    evaluation, all runs) to results/<stem>.csv."""
    write_markdown(stem, text)
    write_csv(RESULTS / f"{stem}.csv", [row for curve in curves for row in curve])


def pyplot() -> Any:
    """matplotlib.pyplot with the Agg backend, or None without matplotlib (extra ``plots``)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: no figures (pip install -e '.[plots]')")
        return None
    return plt


def plot_learning_curves(panels: dict[str, tuple[list[list[dict[str, Any]]], float, str]], filename: str) -> None:
    """One panel per entry: each run's evaluation returns, their mean, and a reference line;
    saved as results/<filename> with the command in the title. Needs matplotlib (extra ``plots``).

    :param panels: title -> (runs, each a list of rows with ``steps`` and ``return_mean``;
        reference value; reference label)
    :param filename: the PNG file name
    """
    plt = pyplot()
    if plt is None:
        return
    fig, axes = plt.subplots(1, len(panels), figsize=(max(4.5 * len(panels), 7.0), 3.6), squeeze=False)
    for ax, (title, (runs, reference, reference_label)) in zip(axes[0], panels.items(), strict=True):
        steps = [row["steps"] for row in runs[0]]
        for run in runs:
            ax.plot(steps, [row["return_mean"] for row in run], alpha=0.35)
        mean = [sum(run[i]["return_mean"] for run in runs) / len(runs) for i in range(len(steps))]
        ax.plot(steps, mean, color="black", linewidth=2, label=f"mean of {len(runs)} seeds")
        ax.axhline(reference, color="red", linestyle="--", label=reference_label)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("env steps")
        ax.set_ylabel("evaluation return (10 episodes)")
        ax.legend(fontsize=8)
    fig.suptitle(command_line().replace("`", ""), fontsize=7)
    fig.tight_layout()
    fig.savefig(RESULTS / filename, dpi=100)


class RecordedJob(Protocol):
    """A benchmark job whose finished run is kept in one JSON record."""

    seed: int
    overrides: tuple[str, ...]

    @property
    def record(self) -> Path: ...


def _recorded(compute: Callable[[Any], list[dict[str, Any]]], job: RecordedJob) -> list[dict[str, Any]]:
    """The job's rows from its record if an earlier invocation finished it, else ``compute(job)``, then recorded."""
    if job.record.exists():
        return json.loads(job.record.read_text())["curve"]
    rows = compute(job)
    save_record(job.record, {"overrides": list(job.overrides), "command": command_line(), "curve": rows})
    return rows


def run_recorded(
    jobs: Sequence[RecordedJob], compute: Callable[[Any], list[dict[str, Any]]], workers: int, report_only: bool, stem: str
) -> tuple[list[list[dict[str, Any]]], list[str], float]:
    """Run ``compute`` (a module-level function) on every job not on record, ``workers`` at a time
    in fresh processes; with ``report_only`` train nothing and refuse missing records.

    :return: every job's rows, the commands (with their commits) that made the records, and the
        wall-clock seconds
    """
    if report_only:
        missing = [job.seed for job in jobs if not job.record.exists()]
        if missing:
            raise SystemExit(f"--report-only: no record for seeds {missing} in results/{stem}/")
    start = time.perf_counter()
    with multiprocessing.get_context("spawn").Pool(min(workers, len(jobs))) as pool:
        curves = pool.map(functools.partial(_recorded, compute), jobs)
    runs = sorted({json.loads(job.record.read_text())["command"] for job in jobs})
    return curves, runs, time.perf_counter() - start


def with_cme(kwargs: dict[str, Any]) -> dict[str, Any]:
    """``kwargs`` of ``CMEPolicyIteration`` with ``model_update.kind="cme"`` unless they name a kind: the
    diagnostics measure the paper's CME, which the default ``kind="auto"`` replaces where s' - s is
    linear in (s, a) (InvertedPendulum-v5, PointGoal2D-v0)."""
    return {**kwargs, "model_update": {"kind": "cme", **kwargs.get("model_update", {})}}
