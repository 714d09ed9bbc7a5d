"""How many torch CPU threads the agent's workloads run fastest at, idle and beside a busy process.

The question behind ``CMEPolicyIteration(n_threads=...)``'s default (``cme_agent.threads.DEFAULT_THREADS``).
Each workload runs at 1 and at 2 torch threads, on an idle machine and beside one busy process (a
spinning subprocess this script starts and stops itself), the four settings alternating, each
``--repeats`` times; the table gives the median wall-clock seconds and the median CPU seconds of
the process (all its threads together), and the ratios of 2 threads to 1.

- agent workloads: ``learn()`` of ``--iterations`` iterations from one checkpoint, taken after
  ``--warmup`` env steps of training at 1 thread (so every setting starts from the same agent):
  Pendulum-v1 and CartPole-v1 at their presets, and Pendulum-v1 with a wide phi (41 x 31 RBFs,
  p = 1,272, \\|C\\| = 16,000);
- matrix workloads: a float32 matrix product (n x n) @ (n x n) and a Cholesky factorisation of an
  n x n SPD matrix, n = 256, 1,024 and 2,048 (q, p and |C| range over these sizes).

    python -m benchmarks.threads [--repeats 2] [--warmup 1000] [--iterations 2] [--stem threads]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from stable_baselines3.common.env_util import make_vec_env

from benchmarks.common import command_line, markdown_table, write_markdown
from cme_agent import CMEPolicyIteration
from cme_agent.threads import torch_threads

THREADS = (1, 2)
LOADS = ("idle", "busy")
AGENTS: dict[str, tuple[str, dict[str, Any]]] = {
    "Pendulum-v1 preset (p = 316, \\|C\\| = 8,000)": ("Pendulum-v1", {}),
    "CartPole-v1 preset (p = 2,836, \\|C\\| = 2,000)": ("CartPole-v1", {}),
    "Pendulum-v1, wide phi (p = 1,272, \\|C\\| = 16,000)": (
        "Pendulum-v1",
        {"policy_kwargs": {"phi": {"resolution": [41, 31]}}, "evaluation": {"collection_size": 16_000}},
    ),
}
"""Agent workloads: env id and constructor arguments over the preset."""
SIZES = (256, 1024, 2048)
"""n of the matrix workloads."""


class BusyProcess:
    """A subprocess spinning one core, for the 'busy' setting; started and stopped by ``with``."""

    def __enter__(self) -> BusyProcess:
        self.process = subprocess.Popen([sys.executable, "-c", "while True: pass"])
        time.sleep(0.5)  # let it reach the scheduler's steady state
        return self

    def __exit__(self, *exc: object) -> None:
        self.process.terminate()
        self.process.wait()


def timed(work: Callable[[], object]) -> tuple[float, float]:
    """Wall-clock and process CPU seconds (all threads) of ``work()``."""
    wall, cpu = time.perf_counter(), time.process_time()
    work()
    return time.perf_counter() - wall, time.process_time() - cpu


def agent_workload(
    env_id: str, kwargs: dict[str, Any], checkpoint: Path, warmup: int, iterations: int
) -> Callable[[int], tuple[float, float]]:
    """Train ``warmup`` steps at 1 thread and save ``checkpoint``; return the measured work:
    ``iterations`` iterations of ``learn()`` from that checkpoint at a thread count (loading untimed)."""
    model = CMEPolicyIteration("CMEPolicy", make_vec_env(env_id, seed=0), seed=0, n_threads=1, **kwargs)
    model.learn(warmup)
    model.save(checkpoint, include=["replay_buffer"])
    steps = iterations * model.steps_per_iteration

    def measured(n_threads: int) -> tuple[float, float]:
        agent = CMEPolicyIteration.load(checkpoint, env=make_vec_env(env_id, seed=1), n_threads=n_threads)
        return timed(lambda: agent.learn(steps, reset_num_timesteps=False))

    return measured


def matrix_workload(kind: str, n: int) -> Callable[[int], tuple[float, float]]:
    """A matrix product or a Cholesky factorisation of size n, repeated to last about 0.3 s at 1 thread."""
    generator = torch.Generator().manual_seed(n)
    a = torch.randn(n, n, generator=generator)
    spd = a @ a.T + n * torch.eye(n)
    operation = (lambda: a @ a) if kind == "matmul" else (lambda: torch.linalg.cholesky(spd))
    with torch_threads(1):
        start = time.perf_counter()
        operation()
        repeats = max(1, round(0.3 / max(time.perf_counter() - start, 1e-6)))

    def measured(n_threads: int) -> tuple[float, float]:
        with torch_threads(n_threads):
            return timed(lambda: [operation() for _ in range(repeats)])

    return measured


def measure(
    workloads: dict[str, Callable[[int], tuple[float, float]]], repeats: int
) -> dict[tuple[str, str, int], list[tuple[float, float]]]:
    """Every workload at every (load, threads) setting, ``repeats`` times, the order of the
    settings reversed every other repeat: (wall, CPU) seconds by (workload, load, threads)."""
    times: dict[tuple[str, str, int], list[tuple[float, float]]] = {}
    for repeat in range(repeats):
        for load in LOADS if repeat % 2 == 0 else reversed(LOADS):
            with BusyProcess() if load == "busy" else contextlib.nullcontext():
                for name, workload in workloads.items():
                    for n_threads in THREADS if repeat % 2 == 0 else reversed(THREADS):
                        wall, cpu = workload(n_threads)
                        times.setdefault((name, load, n_threads), []).append((wall, cpu))
                        print(f"{name}, {load}, {n_threads} threads: {wall:.3f} s wall, {cpu:.3f} s CPU", flush=True)
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--warmup", type=int, default=1000, help="env steps of training before the agent's checkpoint")
    parser.add_argument("--iterations", type=int, default=2, help="iterations of learn() measured per agent workload")
    parser.add_argument("--stem", default="threads")
    args = parser.parse_args()
    started, load_before = time.perf_counter(), os.getloadavg()
    with tempfile.TemporaryDirectory() as folder:
        workloads = {
            name: agent_workload(env_id, kwargs, Path(folder) / f"agent{index}.zip", args.warmup, args.iterations)
            for index, (name, (env_id, kwargs)) in enumerate(AGENTS.items())
        }
        workloads |= {f"{kind} n = {n:,}": matrix_workload(kind, n) for kind in ("matmul", "cholesky") for n in SIZES}
        times = measure(workloads, args.repeats)
    load_after = os.getloadavg()

    def median(name: str, load: str, n_threads: int, column: int) -> float:
        return statistics.median(item[column] for item in times[name, load, n_threads])

    rows = []
    for name in workloads:
        cells = [name]
        for load in LOADS:
            one_wall, two_wall = median(name, load, 1, 0), median(name, load, 2, 0)
            one_cpu, two_cpu = median(name, load, 1, 1), median(name, load, 2, 1)
            cells += [f"{one_wall:.3f} / {two_wall:.3f}", f"**{two_wall / one_wall:.2f}**", f"{two_cpu / one_cpu:.2f}"]
        rows.append(cells)
    header = [
        "workload",
        "idle: wall s, 1 / 2 threads",
        "idle: wall 2/1",
        "idle: CPU 2/1",
        "busy: wall s, 1 / 2 threads",
        "busy: wall 2/1",
        "busy: CPU 2/1",
    ]
    text = (
        "# torch threads: 1 or 2, idle and beside a busy process\n\n"
        f"Command: `{command_line()}`, {os.cpu_count()} CPUs, torch {torch.__version__} "
        f"(default {torch.get_num_threads()} threads here), {time.perf_counter() - started:.0f} s. "
        f"Load average (1 min) {load_before[0]:.2f} before, {load_after[0]:.2f} after: 'idle' is this machine as "
        "others left it, 'busy' the same plus one spinning process of this script's.\n\n"
        f"Median of {args.repeats} alternated repeats. Agent workloads: `learn()` of {args.iterations} iterations from a "
        f"checkpoint taken after {args.warmup:,} env steps; matrix workloads: float32 (n x n) @ (n x n) and "
        "Cholesky of an n x n SPD matrix, repeated to about 0.3 s. wall 2/1 below 1: 2 threads are faster; "
        "CPU 2/1: the CPU time the second thread costs (all threads of the process).\n\n" + markdown_table(header, rows) + "\n"
    )
    write_markdown(args.stem, text)


if __name__ == "__main__":
    main()
