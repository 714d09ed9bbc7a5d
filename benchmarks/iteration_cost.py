"""Cost of one iteration: against its FLOP floor, and against the size of D (docs/design.md, fact 1).

An agent of the Pendulum-v1 config (|C| = 8,000, p = 316, K = 21, 5 rounds) is grown to
q features by :meth:`~cme_agent.CMEPolicyIteration.train_iteration` on random transitions.
Then one iteration (``train_iteration`` on 200 new transitions, the model restored afterwards
so q stays fixed) is timed in thread CPU time (1 torch thread), with D of two sizes
(5,000 and 50,000 transitions), alternately over several repeats. Its matrix FLOPs are
counted by ``torch.utils.flop_counter``; the floor is that count at this machine's float32
GEMM rate, measured in the same run on the iteration's largest product. Also times matching
pursuit picking 50 features from 1,000 candidates on a 2,000-point subsample.

    python -m benchmarks.iteration_cost [--repeats 5] [--q 2000]
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import statistics
import time

import gymnasium as gym
import numpy as np
import torch
from hydra.utils import instantiate
from stable_baselines3.common.logger import configure
from torch.utils.flop_counter import FlopCounterMode

from benchmarks.common import command_line, compose_config, markdown_table, write_markdown
from cme_agent import CMEPolicyIteration
from cme_agent.dynamics import matching_pursuit

aten = torch.ops.aten
PHASES = ("feature_selection", "model_update", "policy_evaluation", "policy_improvement")
M = 200


def random_transitions(n: int, seed: int) -> tuple[np.ndarray, ...]:
    """n Pendulum-v1 transitions under random actions: obs, actions, rewards, next_obs, terminated."""
    env = gym.make("Pendulum-v1")
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    columns: list[list] = [[], [], [], [], []]
    for _ in range(n):
        action = rng.uniform(-2, 2, size=1).astype(np.float32)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        for column, value in zip(columns, (obs, action, reward, next_obs, terminated), strict=True):
            column.append(value)
        obs = env.reset()[0] if terminated or truncated else next_obs
    return tuple(np.asarray(column) for column in columns)


def make_agent(seed: int, collection_size: int) -> CMEPolicyIteration:
    """The Pendulum-v1 config with no budget on q (so an iteration at q still runs matching pursuit)."""
    overrides = ["env=pendulum", "agent.feature_selection.max_total_features=inf"]
    overrides.append(f"agent.evaluation.collection_size={collection_size}")
    agent = instantiate(compose_config(overrides).agent, env="Pendulum-v1", seed=seed, _convert_="all")
    agent.set_logger(configure(None, []))
    return agent


def add_block(agent: CMEPolicyIteration, block: tuple[np.ndarray, ...]) -> None:
    """Append a block of transitions to D and run one training iteration on it."""
    before = len(agent.store)
    agent.store.add(*block)
    agent.train_iteration(agent.store.get(slice(before, len(agent.store))))


def grow(agent: CMEPolicyIteration, data: tuple[np.ndarray, ...], target_q: int) -> int:
    """Train on successive blocks of M transitions until q >= target_q (one evaluation round per
    iteration, to get there sooner); returns the transitions used."""
    config, start = agent.evaluation_config, 0
    agent.evaluation_config = dataclasses.replace(config, rounds=1)
    while agent.q < target_q:
        add_block(agent, tuple(column[start : start + M] for column in data))
        start += M
    agent.evaluation_config = config
    return start


def timed_iteration(agent: CMEPolicyIteration, block: tuple[np.ndarray, ...]) -> tuple[float, dict[str, float]]:
    """Thread CPU seconds of one iteration on ``block`` and its wall seconds per phase; the agent is restored."""
    saved = copy.deepcopy(agent.policy), agent.store.size, agent._torch_rng.get_state()
    agent._phase_seconds = {}
    start = time.thread_time()
    add_block(agent, block)
    seconds = time.thread_time() - start
    agent.policy, agent.store.size = saved[0], saved[1]
    agent._torch_rng.set_state(saved[2])
    return seconds, dict(agent._phase_seconds)


def product_flops(*shapes: torch.Size, out_shape: torch.Size | None = None, **kwargs: object) -> int:
    """2 m k n FLOPs of the product of the last two operands, (m, k) x (k, n) or (m, k) x (k,)."""
    (m, k), right = shapes[-2], shapes[-1]
    return 2 * m * k * (right[1] if len(right) == 2 else 1)


UNCOUNTED_PRODUCTS = {op: product_flops for op in (aten.addmm_, aten.mv, aten.addmv, aten.addmv_)}
"""Products ``torch.utils.flop_counter`` does not count (in-place and matrix-vector forms): the SGD
step's ``addmm_`` alone is a third of an iteration's FLOPs."""


def counted_flops(agent: CMEPolicyIteration, block: tuple[np.ndarray, ...]) -> int:
    """Matrix FLOPs of one iteration on ``block`` (the agent is restored)."""
    counter = FlopCounterMode(display=False, custom_mapping=UNCOUNTED_PRODUCTS)
    with counter:
        timed_iteration(agent, block)
    return counter.get_total_flops()


def gemm_rate(n: int, q: int, p: int, repeats: int) -> float:
    """Best float32 GEMM rate (FLOP per thread-CPU second) of an (n, q) x (q, p) product."""
    generator = torch.Generator().manual_seed(0)
    a, b = torch.rand(n, q, generator=generator), torch.rand(q, p, generator=generator)
    out = torch.empty(n, p)
    best = float("inf")
    for _ in range(repeats):
        start = time.thread_time()
        torch.mm(a, b, out=out)
        best = min(best, time.thread_time() - start)
    return 2 * n * q * p / best


def matching_pursuit_seconds(repeats: int) -> float:
    generator = torch.Generator().manual_seed(0)
    atoms = torch.exp(-torch.rand(2000, 1000, generator=generator) * 5)
    residual = torch.randn(2000, 316, generator=generator)
    times = []
    for _ in range(repeats):
        start = time.thread_time()
        result = matching_pursuit(atoms, residual, threshold=1e-9, max_atoms=50)
        times.append(time.thread_time() - start)
        assert len(result.indices) == 50
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--q", type=int, default=2000, help="features to grow before timing")
    parser.add_argument("--collection-size", type=int, default=8000, help="|C|")
    parser.add_argument("--small", type=int, default=5_000)
    parser.add_argument("--large", type=int, default=50_000)
    args = parser.parse_args()
    torch.set_num_threads(1)

    data = random_transitions(args.large + M * (args.repeats + 2), seed=0)
    small = make_agent(0, args.collection_size)
    used = grow(small, data, args.q)
    large = make_agent(0, args.collection_size)
    large.policy = copy.deepcopy(small.policy)
    large.store.add(*(column[used : args.large] for column in data))
    large.store.add(*(column[:used] for column in data))
    small.store.add(*(column[used : max(args.small, used)] for column in data))
    q, p = small.q, small.dynamics.p
    print(f"|D| = {len(small.store)} vs {len(large.store)}, q = {q}, p = {p}, |C| = {args.collection_size}", flush=True)

    blocks = [tuple(column[args.large + i * M : args.large + (i + 1) * M] for column in data) for i in range(args.repeats + 1)]
    flops = counted_flops(small, blocks[-1])
    cpu: dict[str, list[float]] = {"small": [], "large": []}
    phases: dict[str, list[dict[str, float]]] = {"small": [], "large": []}
    rates, floor_ratios = [], []
    for block in blocks[: args.repeats]:
        rates.append(gemm_rate(args.collection_size, q, p, repeats=3))  # next to each timing: the load varies
        for name, agent in (("small", small), ("large", large)):
            seconds, by_phase = timed_iteration(agent, block)
            cpu[name].append(seconds)
            phases[name].append(by_phase)
        floor_ratios.append(cpu["small"][-1] / (flops / rates[-1]))
    rate = statistics.median(rates)
    floor = flops / rate
    rows = []
    for phase in PHASES:
        medians = [statistics.median(t.get(phase, 0.0) for t in phases[name]) for name in ("small", "large")]
        rows.append([f"{phase} (wall)", f"{medians[0]:.3f}", f"{medians[1]:.3f}", f"{medians[1] / max(medians[0], 1e-9):.2f}"])
    totals = [statistics.median(cpu[name]) for name in ("small", "large")]
    rows.append(["**iteration (thread CPU)**", f"{totals[0]:.3f}", f"{totals[1]:.3f}", f"{totals[1] / totals[0]:.2f}"])
    header = ["phase", f"s at \\|D\\|={len(small.store)}", f"s at \\|D\\|={len(large.store)}", "ratio"]
    mp_seconds = matching_pursuit_seconds(args.repeats)
    text = (
        f"# Seconds per iteration: against the FLOP floor and against |D|\n\nCommand: `{command_line()}` "
        f"(1 torch thread, median of {args.repeats} alternated repeats; Pendulum-v1 config, m = {M}, "
        f"q = {q} features, p = {p}, |C| = {args.collection_size}, "
        f"K = {small.policy.candidates.shape[0]}, {small.evaluation_config.rounds} rounds).\n\n"
        f"**FLOP floor**: one iteration does {flops / 1e9:.1f} GFLOP of matrix products "
        f"(torch.utils.flop_counter, with the in-place and matrix-vector products it misses); "
        f"at this machine's float32 GEMM rate, measured in the same run on an "
        f"({args.collection_size}, {q}) x ({q}, {p}) product just before each repeat (median "
        f"{rate / 1e9:.1f} GFLOP/s per thread), that is a floor of **{floor:.2f} s**. The iteration took "
        f"**{totals[0]:.2f} s** of thread CPU time at |D| = {len(small.store)}: "
        f"**{statistics.median(floor_ratios):.2f}x its floor** (median of the repeats' ratios, each to the rate "
        f"measured next to it: {', '.join(f'{ratio:.2f}' for ratio in floor_ratios)}).\n\n"
        f"{markdown_table(header, rows)}\n\n"
        f"Matching pursuit, 2,000-point subsample x 1,000 candidates x p = 316, 50 picks: {mp_seconds:.3f} s.\n"
    )
    write_markdown("iteration_cost", text)


if __name__ == "__main__":
    main()
