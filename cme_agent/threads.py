"""How many CPU threads torch may use while an agent learns.

The agent's matrices are small to mid-sized (hundreds to a few thousand rows and columns), where a
second torch thread gains up to 1.7 times on an idle machine and loses up to 2.5 times on a busy one:
``python -m benchmarks.threads`` measures it (``results/threads.md``). ``learn()`` therefore runs
at :data:`DEFAULT_THREADS` unless told otherwise, in the Python API and in ``train.py`` alike.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch

from cme_agent.config import check_positive_int

DEFAULT_THREADS = 1
"""torch's intra-op CPU threads during ``learn()``. Measured on 2 cores (``results/threads.md``):
with the machine to itself, 2 threads take 0.59-0.75 of the wall-clock time of 1 on the agent's
workloads; beside one other busy process they take 1.7-2.5 times as long (a Cholesky of 256 x 256,
11 times). A process among others (a shared machine, a sweep of several runs) is better off at 1;
a run with the machine to itself may pass ``n_threads=2`` or more."""


def check_threads(n_threads: int | None) -> int | None:
    """Validate a thread count: an integer >= 1, or None (torch's own setting, left as it is).

    :param n_threads: the count a user gave
    :return: the same count
    """
    if n_threads is not None:
        check_positive_int("n_threads", n_threads)
    return n_threads


@contextlib.contextmanager
def torch_threads(n_threads: int | None) -> Iterator[None]:
    """Run the block with torch's intra-op CPU threads set to ``n_threads``, then put the
    caller's setting back (None: the block runs at the caller's setting, nothing changes).

    :param n_threads: threads for the block, or None
    """
    previous = torch.get_num_threads()
    if n_threads is not None:
        torch.set_num_threads(n_threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous)
