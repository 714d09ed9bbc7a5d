"""Cost per iteration against the size of D: the paper's central claim (DESIGN.md, fact 1).

Two agents with the same model (same q, same psi, same B) differ only in |D| (5,000 vs
50,000 Pendulum transitions). Each phase of one iteration is timed on both, alternately, over
several repeats, restoring the model after each so q stays fixed; the medians and their
ratio are printed and written to results/iteration_cost.md. Also times matching pursuit
picking 50 features from 1,000 candidates on a 2,000-point subsample.

    python benchmarks/iteration_cost.py [--repeats 7] [--q 600]
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time

import gymnasium as gym
import numpy as np
import torch
from common import RESULTS, command_line, compose_config, markdown_table
from hydra.utils import instantiate
from stable_baselines3.common.logger import configure

from cme_agent import CMEPolicyIteration
from cme_agent.dynamics import matching_pursuit

PHASES = ("feature_selection", "model_update", "policy_evaluation", "policy_improvement")


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


def make_agent(seed: int) -> CMEPolicyIteration:
    cfg = compose_config(["env=pendulum"])
    agent = instantiate(cfg.agent, env="Pendulum-v1", seed=seed, _convert_="all")
    agent.set_logger(configure(None, []))
    return agent


def grow(agent: CMEPolicyIteration, data: tuple[np.ndarray, ...], target_q: int, m: int) -> None:
    """Run feature selection and model updates on successive blocks of m transitions until q >= target_q."""
    start = 0
    while agent.n_features < target_q:
        block = tuple(column[start : start + m] for column in data)
        before = len(agent.store)
        agent.store.add(*block)
        agent.feature_selection(agent.store.get(slice(before, len(agent.store))))
        agent.model_update()
        start += m


def time_iteration(agent: CMEPolicyIteration, new_block: tuple[np.ndarray, ...]) -> dict[str, float]:
    """Seconds of each phase of one iteration on new_block; the agent's model is restored afterwards."""
    saved = copy.deepcopy(agent.policy), copy.deepcopy(agent.model), agent.n_features, agent.store.size
    agent._phase_seconds = {}
    agent.store.add(*new_block)
    agent.feature_selection(agent.store.get(slice(saved[-1], len(agent.store))))
    agent.model_update()
    for _ in range(agent.evaluation_config.rounds):
        agent.policy_improvement(agent.policy_evaluation(agent.draw_collection()))
    seconds = dict(agent._phase_seconds)
    agent.policy, agent.model, agent.n_features, agent.store.size = saved
    return seconds


def matching_pursuit_seconds(repeats: int) -> float:
    generator = torch.Generator().manual_seed(0)
    atoms = torch.exp(-torch.rand(2000, 1000, generator=generator) * 5)
    residual = torch.randn(2000, 316, generator=generator)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = matching_pursuit(atoms, residual, threshold=1e-9, max_atoms=50)
        times.append(time.perf_counter() - start)
        assert len(result.indices) == 50
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--q", type=int, default=600, help="features to grow before timing")
    parser.add_argument("--small", type=int, default=5_000)
    parser.add_argument("--large", type=int, default=50_000)
    args = parser.parse_args()
    torch.set_num_threads(1)

    m = 200
    data = random_transitions(args.large + m * (args.repeats + 1), seed=0)
    small, large = make_agent(0), make_agent(0)
    grow(small, data, args.q, m)
    large.policy, large.model = copy.deepcopy(small.policy), copy.deepcopy(small.model)
    large.store.add(*(column[small.store.size : args.large] for column in data))
    large.store.add(*(column[: small.store.size] for column in data))
    small.store.add(*(column[small.store.size : args.small] for column in data))
    print(f"|D| = {len(small.store)} vs {len(large.store)}, q = {small.n_features}, p = {small.policy.phi.width}")

    timings: dict[str, list[dict[str, float]]] = {"small": [], "large": []}
    for repeat in range(args.repeats):
        block = tuple(column[args.large + repeat * m : args.large + (repeat + 1) * m] for column in data)
        for name, agent in (("small", small), ("large", large)):
            timings[name].append(time_iteration(agent, block))

    rows = []
    for phase in (*PHASES, "total"):
        medians = []
        for name in ("small", "large"):
            values = [sum(t.values()) if phase == "total" else t.get(phase, 0.0) for t in timings[name]]
            medians.append(statistics.median(values))
        rows.append([phase, f"{medians[0]:.4f}", f"{medians[1]:.4f}", f"{medians[1] / max(medians[0], 1e-9):.2f}"])
    header = ["phase", f"s at \\|D\\|={len(small.store)}", f"s at \\|D\\|={len(large.store)}", "ratio"]
    table = markdown_table(header, rows)
    mp_seconds = matching_pursuit_seconds(args.repeats)
    text = (
        f"# Seconds per iteration against |D|\n\nCommand: `{command_line()}` (1 torch thread, median of "
        f"{args.repeats} alternated repeats; Pendulum-v1 config, m = {m}, q = {small.n_features} features, "
        f"p = {small.policy.phi.width}).\n\n{table}\n\n"
        f"Matching pursuit, 2,000-point subsample x 1,000 candidates x p = 316, 50 picks: {mp_seconds:.3f} s.\n"
    )
    print(text)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "iteration_cost.md").write_text(text)


if __name__ == "__main__":
    main()
