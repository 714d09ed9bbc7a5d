"""The evaluation's dual solve: the blocked in-place Cholesky of ``cme_agent.linalg`` against
LAPACK's ``torch.linalg.cholesky_ex`` + ``torch.cholesky_solve`` on the same float64 system.

CartPole's preset evaluates on |C| = 2,000 states with p = 2,836 features, so each round solves
(A A^T + lambda I) x = r with A of shape (2,000, 2,836). Both paths get the same lower-triangle
Gram product (:func:`~cme_agent.linalg.lower_gram`); thread CPU seconds, 1 torch thread, the best
of ``--repeats`` alternated runs. Writes results/dual_solve.md.

    python -m benchmarks.diagnostics.dual_solve [--rows 2000] [--width 2836] [--repeats 5]
"""

from __future__ import annotations

import argparse
import time

import torch

from benchmarks.common import command_line, markdown_table, write_markdown
from cme_agent.linalg import cholesky_, cholesky_solve, lower_gram


def lapack(system: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """Factor and solve with torch's LAPACK path (copies into column-major order, tril, the solve's copy)."""
    factor, _ = torch.linalg.cholesky_ex(system)
    return torch.cholesky_solve(rhs.unsqueeze(1), factor).squeeze(1)


def blocked(system: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """Factor in place by blocks and solve by blocked substitution."""
    cholesky_(system)
    return cholesky_solve(system, rhs)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rows", type=int, default=2000, help="|C|, the size of the dual system")
    parser.add_argument("--width", type=int, default=2836, help="p, the width of phi")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(1)
    generator = torch.Generator().manual_seed(0)
    matrix = torch.randn(args.rows, args.width, generator=generator)
    rhs = torch.randn(args.rows, dtype=torch.float64, generator=generator)
    start = time.thread_time()
    gram = lower_gram(matrix, torch.float64)
    gram_seconds = time.thread_time() - start
    gram.diagonal().add_(1.0)
    best = {"lapack": float("inf"), "blocked": float("inf")}
    solutions = {}
    for _ in range(args.repeats):
        for name, solve in (("lapack", lapack), ("blocked", blocked)):
            system = gram.clone()
            start = time.thread_time()
            solutions[name] = solve(system, rhs)
            best[name] = min(best[name], time.thread_time() - start)
    difference = float((solutions["lapack"] - solutions["blocked"]).abs().max())
    scale = float(solutions["lapack"].abs().max())
    rows = [[name, f"{1000 * seconds:.1f}"] for name, seconds in best.items()]
    text = (
        f"# The dual solve: blocked Cholesky vs LAPACK\n\nCommand: `{command_line()}` (thread CPU, 1 torch thread, "
        f"best of {args.repeats} alternated runs)\n\nSystem: A A^T + I with A ({args.rows}, {args.width}) float32 "
        f"random normal, the Gram product in float64 ({1000 * gram_seconds:.0f} ms for the lower triangle, the "
        f"same for both).\n\n{markdown_table(['factor + solve', 'ms'], rows)}\n\nLargest difference of the "
        f"solutions: {difference:.2g} (largest entry {scale:.2g}).\n"
    )
    write_markdown("dual_solve", text)


if __name__ == "__main__":
    main()
