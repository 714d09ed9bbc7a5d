"""Is a run interrupted mid-way and resumed the same as an uninterrupted one?

For each seed, ``python train.py seed=S <overrides>`` runs twice: once through, and once sent
SIGINT when its progress.csv reaches ``--interrupt-at`` steps (it finishes that iteration,
checkpoints and exits) and then resumed with the command it printed, in the same run directory.
The two final evaluations (``eval_episodes`` episodes of the deterministic policy, the same starts)
are compared seed by seed, and so are the evaluation curves before and after the interruption.

With the default config the env's half-finished episode is not part of a checkpoint: the resumed
run starts fresh episodes, so its data, and from there its policy, differ from the uninterrupted
run's. With ``agent.reset_envs_each_iteration=true`` every iteration starts fresh, seeded episodes,
and a resumed run is the uninterrupted run exactly.

    python -m benchmarks.interrupt_resume --seeds 0 1 2 3 4 [--workers 2] [--overrides key=value ...]

Writes results/<stem>.md and results/<stem>.csv (every evaluation of every run). Each finished run
is kept in results/interrupt_resume_runs/<stem>/, so a rerun skips it and an interrupted benchmark
continues where it stopped.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shlex
import signal
import statistics
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from benchmarks.common import RESULTS, ROOT, command_line, compose_config, markdown_table, write_report

ENV = {**os.environ, "OMP_NUM_THREADS": "1"}
QUIET = {"stdout": subprocess.DEVNULL, "stderr": subprocess.PIPE}


def _finished(run_dir: Path) -> dict[str, Any] | None:
    """The summary of a run that ran to its end, else None."""
    path = run_dir / "summary.json"
    if not path.exists():
        return None
    summary = json.loads(path.read_text())
    return None if summary.get("interrupted") else summary


def _progress_steps(progress: Path) -> int:
    """The last step logged in a progress.csv (0 if none yet)."""
    if not progress.exists():
        return 0
    with progress.open(newline="") as handle:
        steps = [row.get("time/total_timesteps") for row in csv.DictReader(handle)]
    return max((int(float(step)) for step in steps if step), default=0)


def uninterrupted(run_dir: Path, seed: int, overrides: list[str]) -> dict[str, Any]:
    """``python train.py seed=S <overrides>`` in ``run_dir``, to its end."""
    if (summary := _finished(run_dir)) is None:
        command = [sys.executable, str(ROOT / "train.py"), f"seed={seed}", *overrides, f"hydra.run.dir={run_dir}"]
        subprocess.run(command, cwd=ROOT, env=ENV, check=True, capture_output=True, text=True)
        summary = _finished(run_dir)
    return summary


def interrupted(run_dir: Path, seed: int, overrides: list[str], interrupt_at: int) -> tuple[dict[str, Any], int]:
    """The same run sent SIGINT at ``interrupt_at`` steps, then resumed with the command it printed.

    :return: the final summary and the step the run stopped at (its checkpoint's)
    """
    at_stop = run_dir / "summary_at_interruption.json"
    if not at_stop.exists():
        if not (run_dir / "summary.json").exists():
            command = [sys.executable, str(ROOT / "train.py"), f"seed={seed}", *overrides, f"hydra.run.dir={run_dir}"]
            process = subprocess.Popen(
                command, cwd=ROOT, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
            )
            while process.poll() is None and _progress_steps(run_dir / "progress.csv") < interrupt_at:
                time.sleep(0.2)
            process.send_signal(signal.SIGINT)
            _, stderr = process.communicate()
            if process.returncode != 128 + signal.SIGINT:
                raise RuntimeError(f"seed {seed}: the run was not interrupted (exit {process.returncode}): {stderr[-2000:]}")
        at_stop.write_text((run_dir / "summary.json").read_text())
    stopped = json.loads(at_stop.read_text())
    if (summary := _finished(run_dir)) is None:
        resume = shlex.split(stopped["resume_command"])
        subprocess.run([sys.executable, *resume[1:]], cwd=ROOT, env=ENV, check=True, capture_output=True, text=True)
        summary = _finished(run_dir)
    return summary, stopped["total_timesteps"]


def compare(seed: int, plain: dict[str, Any], resumed: dict[str, Any], stopped_at: int) -> list[Any]:
    """One row of the report."""
    curve = {e["timesteps"]: e["mean_reward"] for e in plain["evaluations"]}
    resumed_curve = {e["timesteps"]: e["mean_reward"] for e in resumed["evaluations"]}
    before = all(resumed_curve[t] == r for t, r in curve.items() if t <= stopped_at)
    after = all(resumed_curve[t] == r for t, r in curve.items() if t > stopped_at)
    return [
        seed,
        f"{plain['eval_mean_reward']:.1f} +- {plain['eval_std_reward']:.1f}",
        stopped_at,
        f"{resumed['eval_mean_reward']:.1f} +- {resumed['eval_std_reward']:.1f}",
        f"{resumed['eval_mean_reward'] - plain['eval_mean_reward']:+.1f}",
        "yes" if before else "NO",
        "yes" if after else "no",
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--overrides", nargs="*", default=[], help="train.py overrides of both runs")
    parser.add_argument("--interrupt-at", type=int, default=None, help="steps (default: half of total_timesteps)")
    parser.add_argument("--workers", type=int, default=1, help="runs at once (each a train.py process)")
    parser.add_argument("--stem", default="interrupt_resume", help="name of the results files")
    args = parser.parse_args()
    total = int(compose_config(args.overrides).total_timesteps)
    interrupt_at = args.interrupt_at or total // 2
    runs = RESULTS / "interrupt_resume_runs" / args.stem
    command, start = command_line(), time.perf_counter()  # the code version the runs start with
    with ThreadPoolExecutor(args.workers) as pool:
        plain_jobs = {s: pool.submit(uninterrupted, runs / f"uninterrupted_{s}", s, args.overrides) for s in args.seeds}
        resumed_jobs = {
            s: pool.submit(interrupted, runs / f"interrupted_{s}", s, args.overrides, interrupt_at) for s in args.seeds
        }
        plain = {s: job.result() for s, job in plain_jobs.items()}
        resumed = {s: job.result() for s, job in resumed_jobs.items()}
    rows, curves = [], []
    for seed in args.seeds:
        rows.append(compare(seed, plain[seed], *resumed[seed]))
        for name, summary in (("uninterrupted", plain[seed]), ("resumed", resumed[seed][0])):
            curves.append([{"seed": seed, "run": name, **e} for e in summary["evaluations"]])
    plain_finals = [plain[s]["eval_mean_reward"] for s in args.seeds]
    resumed_finals = [resumed[s][0]["eval_mean_reward"] for s in args.seeds]
    differences = [r - p for r, p in zip(resumed_finals, plain_finals, strict=True)]
    header = ["seed", "uninterrupted: final return", "stopped at (steps)", "interrupted + resumed: final return"]
    header += ["difference", "curves equal before the stop", "curves equal after it"]
    text = "\n".join(
        [
            f"# Interrupted and resumed vs uninterrupted ({total} steps, SIGINT at {interrupt_at})",
            "",
            f"Command: `{command}`; {time.perf_counter() - start:.0f} s.",
            "",
            markdown_table(header, rows),
            "",
            f"Mean final return over {len(args.seeds)} seeds: uninterrupted {_mean_std(plain_finals)}, "
            f"resumed {_mean_std(resumed_finals)}; paired difference {_mean_std(differences, se=True)}.",
            "",
        ]
    )
    write_report(args.stem, text, curves)


def _mean_std(values: list[float], se: bool = False) -> str:
    """``mean +- std`` (or the standard error with ``se``) of ``values``."""
    if len(values) < 2:
        return f"{statistics.mean(values):+.1f}"
    spread = statistics.stdev(values) / (len(values) ** 0.5 if se else 1)
    return f"{statistics.mean(values):+.1f} +- {spread:.1f}" + (" (SE)" if se else " (std)")


if __name__ == "__main__":
    main()
