"""Peak memory and time of ``CMEPolicyIteration("CMEPolicy", env_id).learn(steps)`` with no
settings at all (the budget: at most 1 GiB at the defaults), as a new user runs it: torch's default
thread count, a fresh process per run (peak RSS of the whole process: torch, SB3 and the env
included), repeated because the peak varies from run to run with the allocator's heap.
Writes results/defaults_memory.md.

    python -m benchmarks.defaults_memory [--envs CartPole-v1 Pendulum-v1 InvertedPendulum-v5] [--steps 400] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

from benchmarks.common import command_line, markdown_table, write_markdown

PROBE = r"""
import json, resource, sys, time
from cme_agent import CMEPolicyIteration  # registers the package's envs (PointGoal2D-v0)
model = CMEPolicyIteration("CMEPolicy", sys.argv[1])
start = time.perf_counter()
model.learn(int(sys.argv[2]))
seconds, peak = time.perf_counter() - start, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({"seconds": seconds, "peak_mib": peak, "q": model.q}))
"""


def probe(env_id: str, steps: int) -> dict[str, float]:
    """One fresh process: learn ``steps`` at the defaults; its wall seconds in learn(), peak RSS and q."""
    result = subprocess.run([sys.executable, "-c", PROBE, env_id, str(steps)], capture_output=True, text=True, check=True)
    return json.loads(result.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=["CartPole-v1", "Pendulum-v1", "InvertedPendulum-v5", "PointGoal2D-v0"])
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    rows = []
    for env_id in args.envs:
        runs = [probe(env_id, args.steps) for _ in range(args.repeats)]
        print(env_id, runs, flush=True)
        rows.append(
            [
                env_id,
                ", ".join(f"{run['peak_mib']:.0f}" for run in runs),
                f"{max(run['peak_mib'] for run in runs):.0f}",
                ", ".join(f"{run['seconds']:.1f}" for run in runs),
                ", ".join(str(run["q"]) for run in runs),
            ]
        )
    header = ["env", "peak RSS per run (MiB)", "largest (MiB)", "learn() wall s per run", "q per run"]
    text = (
        f"# Peak memory at the library defaults\n\nCommand: `{command_line()}`\n\n"
        f'`CMEPolicyIteration("CMEPolicy", env_id).learn({args.steps})`, no settings, no seed, torch\'s default '
        f"threads, one fresh process per run ({args.repeats} per env); peak RSS of the whole process.\n\n"
        f"{markdown_table(header, rows)}\n"
    )
    write_markdown("defaults_memory", text)


if __name__ == "__main__":
    main()
