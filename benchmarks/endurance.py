"""Endurance: a long Pendulum-v1 run, recording memory and seconds per iteration.

Trains ``python train.py``'s default config for ``--steps`` env steps and records, at every
iteration: the process's resident memory, the bytes held by the transition stores, q, and the
seconds the iteration took (all phases). Memory should grow only with the store (reported as
bytes per transition) and time per iteration should stay flat. Writes results/endurance.csv,
results/endurance.md and, with matplotlib, results/endurance.png.

The run writes a resumable checkpoint every ``--checkpoint-every`` iterations; ``--resume``
continues an interrupted run from it (the CSV keeps the rows up to the checkpoint's iteration;
resident memory restarts from a fresh process, which the CSV's ``resumed`` column marks).

    python -m benchmarks.endurance [--steps 200000] [--resume]
"""

from __future__ import annotations

import argparse
import csv
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from hydra.utils import get_class
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import configure

from benchmarks.common import RESULTS, command_line, compose_config, pyplot, resident_bytes
from cme_agent.callbacks import IterationCheckpoint
from cme_agent.experiment import build_agent, make_env

CHECKPOINT = RESULTS / "endurance_checkpoint.zip"


class IterationRecorder(BaseCallback):
    """Records one row per iteration, at the iteration boundary (``on_rollout_start``), and
    appends it to ``csv_path`` at once (a long run cut short keeps its rows).

    :param csv_path: the CSV file
    :param rows: the rows already recorded (those of the run being resumed; empty for a new run);
        the file is rewritten with them
    """

    FIELDS = ("iteration", "transitions", "store_bytes", "rss_bytes", "q", "seconds", "cpu_seconds", "resumed")

    def __init__(self, csv_path: Path, rows: list[dict[str, float]]) -> None:
        super().__init__()
        self.rows = list(rows)
        self.csv_path = csv_path
        with open(csv_path, "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=self.FIELDS)
            writer.writeheader()
            writer.writerows(self.rows)
        self._last = time.perf_counter()
        self._last_cpu = time.process_time()
        self._start = 0

    def _init_callback(self) -> None:
        self._start = self.model.iteration  # > 0 when resuming: that iteration's row is already recorded

    def _on_rollout_start(self) -> None:
        now, now_cpu = time.perf_counter(), time.process_time()
        model = self.model
        if model.iteration > self._start:
            self.rows.append(
                {
                    "iteration": model.iteration,
                    "transitions": len(model.store) + len(model.holdout),
                    "store_bytes": model.store.nbytes + model.holdout.nbytes,
                    "rss_bytes": resident_bytes(),
                    "q": model.q,
                    "seconds": now - self._last,
                    "cpu_seconds": now_cpu - self._last_cpu,
                    "resumed": int(self._start > 0 and model.iteration == self._start + 1),
                }
            )
            with open(self.csv_path, "a", newline="") as handle:
                csv.DictWriter(handle, fieldnames=self.FIELDS).writerow(self.rows[-1])
        self._last, self._last_cpu = now, now_cpu

    def _on_step(self) -> bool:
        return True


def report(rows: list[dict[str, float]], steps: int, seed: int) -> None:
    """Write results/endurance.md (and .png) from the per-iteration rows of a run."""
    transitions = np.array([row["transitions"] for row in rows], dtype=float)
    rss = np.array([row["rss_bytes"] for row in rows], dtype=float)
    slope = np.polyfit(transitions[len(rows) // 10 :], rss[len(rows) // 10 :], 1)[0]
    tenth = max(len(rows) // 10, 1)
    early = statistics.median(row["cpu_seconds"] for row in rows[tenth : 2 * tenth])
    late = statistics.median(row["cpu_seconds"] for row in rows[-tenth:])
    reached = f"{rows[-1]['transitions']:.0f} of {steps}"
    text = (
        f"# Endurance: {steps} env steps on Pendulum-v1\n\n"
        f"Command: `{command_line()}` (seed {seed}, 1 torch thread; `--report-only` redraws from the CSV of "
        f"`--steps {steps}`). Env steps recorded: {reached}.\n\n"
        f"- iterations: {len(rows)}; q at the end: {rows[-1]['q']:.0f}\n"
        f"- transition store: {rows[-1]['store_bytes'] / rows[-1]['transitions']:.1f} bytes allocated per transition "
        f"(doubling capacity), {rows[-1]['store_bytes'] / 2**20:.1f} MiB at the end\n"
        f"- resident memory: {rss[0] / 2**20:.0f} MiB after the first iteration, {rss[-1] / 2**20:.0f} MiB at the end; "
        f"fitted growth {slope:.0f} bytes per transition\n"
        f"- CPU seconds per iteration (median; process CPU time, robust to other load on the machine): {early:.2f} in the "
        f"second tenth of the run, {late:.2f} in the last tenth (ratio {late / early:.2f})\n"
    )
    print(text)
    (RESULTS / "endurance.md").write_text(text)
    plt = pyplot()
    if plt is None:
        return
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.5))
    axes[0].plot(transitions, rss / 2**20, label="resident memory")
    axes[0].plot(transitions, np.array([row["store_bytes"] for row in rows]) / 2**20, label="transition store")
    axes[0].set_xlabel("transitions")
    axes[0].set_ylabel("MiB")
    axes[0].legend()
    axes[1].plot(transitions, [row["cpu_seconds"] for row in rows], linewidth=0.5)
    axes[1].set_xlabel("transitions")
    axes[1].set_ylabel("CPU seconds per iteration")
    axes[2].plot(transitions, [row["q"] for row in rows])
    axes[2].set_xlabel("transitions")
    axes[2].set_ylabel("q (features)")
    fig.suptitle(command_line(), fontsize=8)
    fig.tight_layout()
    fig.savefig(RESULTS / "endurance.png", dpi=100)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=200_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--overrides", nargs="*", default=[])
    parser.add_argument("--checkpoint-every", type=int, default=10, help="iterations between checkpoints")
    parser.add_argument(
        "--resume", action="store_true", help=f"continue the run checkpointed in {CHECKPOINT.name}, if there is one"
    )
    parser.add_argument("--report-only", action="store_true", help="redraw from results/endurance.csv, train nothing")
    args = parser.parse_args()
    if args.report_only:
        report(read_rows(), args.steps, args.seed)
        return
    torch.set_num_threads(1)
    cfg = compose_config([f"seed={args.seed}", "verbose=0", *args.overrides])
    env = make_env(cfg)
    if args.resume and not CHECKPOINT.exists():
        print(f"--resume: no {CHECKPOINT}, starting a fresh run")
    if args.resume and CHECKPOINT.exists():
        model = get_class(cfg.agent._target_).load(CHECKPOINT, env=env)
        rows = [row for row in read_rows() if row["iteration"] <= model.iteration]
        print(f"resuming from {CHECKPOINT} at iteration {model.iteration}, {model.num_timesteps} steps")
    else:
        model, rows = build_agent(cfg, env), []
    model.set_logger(configure(None, []))
    RESULTS.mkdir(exist_ok=True)
    recorder = IterationRecorder(RESULTS / "endurance.csv", rows)
    checkpoint = IterationCheckpoint(CHECKPOINT, args.checkpoint_every)
    model.learn(args.steps - model.num_timesteps, callback=[recorder, checkpoint], reset_num_timesteps=not args.resume)
    report(recorder.rows, args.steps, args.seed)


def read_rows() -> list[dict[str, float]]:
    """The rows of results/endurance.csv (a CSV written before the ``resumed`` column reads as never resumed)."""
    with open(RESULTS / "endurance.csv", newline="") as handle:
        return [{"resumed": 0.0, **{key: float(value) for key, value in row.items()}} for row in csv.DictReader(handle)]


if __name__ == "__main__":
    main()
