"""Endurance: a long Pendulum-v1 run, recording memory and seconds per iteration (issue 5).

Trains ``python train.py``'s default config for ``--steps`` env steps and records, at every
iteration: the process's resident memory, the bytes held by the transition stores, q, and the
seconds the iteration took (all phases). Memory should grow only with the store (reported as
bytes per transition) and time per iteration should stay flat. Writes results/endurance.csv,
results/endurance.md and, with matplotlib, results/endurance.png.

    python benchmarks/endurance.py [--steps 200000]
"""

from __future__ import annotations

import argparse
import csv
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from common import RESULTS, command_line, compose_config, resident_bytes
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import configure

from cme_agent.experiment import build_agent, make_env


class IterationRecorder(BaseCallback):
    """Records one row per iteration, at the iteration boundary (``on_rollout_start``), and
    appends it to ``csv_path`` at once (a long run cut short keeps its rows).

    :param csv_path: the CSV file (overwritten)
    """

    FIELDS = ("iteration", "transitions", "store_bytes", "rss_bytes", "q", "seconds", "cpu_seconds")

    def __init__(self, csv_path: Path) -> None:
        super().__init__()
        self.rows: list[dict[str, float]] = []
        self.csv_path = csv_path
        with open(csv_path, "w", newline="") as handle:
            csv.DictWriter(handle, fieldnames=self.FIELDS).writeheader()
        self._last = time.perf_counter()
        self._last_cpu = time.process_time()

    def _on_rollout_start(self) -> None:
        now, now_cpu = time.perf_counter(), time.process_time()
        model = self.model
        if model.iteration > 0:
            self.rows.append(
                {
                    "iteration": model.iteration,
                    "transitions": len(model.store) + len(model.holdout),
                    "store_bytes": model.store.nbytes + model.holdout.nbytes,
                    "rss_bytes": resident_bytes(),
                    "q": model.n_features,
                    "seconds": now - self._last,
                    "cpu_seconds": now_cpu - self._last_cpu,
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
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
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
    parser.add_argument("--report-only", action="store_true", help="redraw from results/endurance.csv, train nothing")
    args = parser.parse_args()
    if args.report_only:
        with open(RESULTS / "endurance.csv", newline="") as handle:
            report(
                [{key: float(value) for key, value in row.items()} for row in csv.DictReader(handle)], args.steps, args.seed
            )
        return
    torch.set_num_threads(1)
    cfg = compose_config([f"seed={args.seed}", "verbose=0", *args.overrides])
    model = build_agent(cfg, make_env(cfg))
    model.set_logger(configure(None, []))
    RESULTS.mkdir(exist_ok=True)
    recorder = IterationRecorder(RESULTS / "endurance.csv")
    model.learn(args.steps, callback=recorder)
    report(recorder.rows, args.steps, args.seed)


if __name__ == "__main__":
    main()
