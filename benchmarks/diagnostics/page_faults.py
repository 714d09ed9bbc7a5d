"""What fresh pages cost CartPole's training: minor page faults and thread CPU per env step of
``learn(2000)`` at CartPole-v1's preset, in fresh processes, with glibc's defaults and with glibc
told to keep freed memory (``MALLOC_MMAP_THRESHOLD_``, ``MALLOC_TRIM_THRESHOLD_``,
``MALLOC_TOP_PAD_``: a setting of the user's process, which the library leaves alone).
Alternated runs, 1 torch thread. Writes results/page_faults.md.

    python -m benchmarks.diagnostics.page_faults [--repeats 2] [--steps 2000]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile

from benchmarks.common import ROOT, command_line, markdown_table, write_markdown

CHILD = r"""
import json, resource, sys, time
import torch
from cme_agent import CMEPolicyIteration
torch.set_num_threads(1)
model = CMEPolicyIteration("CMEPolicy", "CartPole-v1", seed=0, verbose=0)
before, start = resource.getrusage(resource.RUSAGE_SELF).ru_minflt, time.thread_time()
model.learn(int(sys.argv[1]))
seconds, faults = time.thread_time() - start, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
print(json.dumps({"ms_per_step": 1000 * seconds / model.num_timesteps, "minor_faults": faults}))
"""

KEEP_FREED_MEMORY = {
    "MALLOC_MMAP_THRESHOLD_": "1000000000",
    "MALLOC_TRIM_THRESHOLD_": "4000000000",
    "MALLOC_TOP_PAD_": "100000000",
}


def run(steps: int, keep_memory: bool) -> dict[str, float]:
    """One fresh process; its printed JSON."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", **(KEEP_FREED_MEMORY if keep_memory else {})}
    result = subprocess.run(
        [sys.executable, "-c", CHILD, str(steps)], env=env, capture_output=True, text=True, cwd=tempfile.gettempdir()
    )
    if result.returncode != 0:
        raise RuntimeError(result.stderr[-3000:])
    return json.loads(result.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--steps", type=int, default=2000)
    args = parser.parse_args()
    runs: dict[bool, list[dict[str, float]]] = {False: [], True: []}
    for _ in range(args.repeats):
        for keep_memory in (False, True):
            runs[keep_memory].append(run(args.steps, keep_memory))
            print(keep_memory, runs[keep_memory][-1], flush=True)
    rows = [
        [
            "glibc kept freed memory" if keep else "glibc defaults",
            ", ".join(f"{r['ms_per_step']:.1f}" for r in runs[keep]),
            f"{statistics.median(r['ms_per_step'] for r in runs[keep]):.1f}",
            f"{statistics.median(r['minor_faults'] for r in runs[keep]):,.0f}",
        ]
        for keep in (False, True)
    ]
    settings = " ".join(f"{key}={value}" for key, value in KEEP_FREED_MEMORY.items())
    text = (
        f"# Page faults of CartPole's training\n\nCommand: `{command_line()}` (CartPole-v1 preset, seed 0, "
        f"learn({args.steps}), a fresh process per run, 1 torch thread, {args.repeats} alternated runs per row; "
        f"'kept freed memory' = `{settings}`)\n\n"
        f"{markdown_table(['allocator', 'ms per env step, per run', 'median', 'minor page faults (median)'], rows)}\n"
    )
    write_markdown("page_faults", text)


if __name__ == "__main__":
    main()
