"""Does the greedy policy survive small changes of its actions? The same Q, acted on differently.

Trains (or loads) ``CMEPolicyIteration("CMEPolicy", env_id, seed=seed)`` as gap_decomposition.py
does, then runs ``--episodes`` episodes from fixed starts for each way of acting on the trained Q:

- ``agent``: the greedy action, as trained;
- ``noise <e>``: the greedy action plus uniform noise in +-e of the action's half-range, per dim;
- ``refined``: the greedy action refined by ``--refine-steps`` steps of projected ascent on the
  same Q (``action_search.refine_steps``), and how far that moves it (``refine_move``: mean
  |refined - greedy| in half-ranges, on the states of the agent's own episodes).

Per mode it reports the return, the episode length and the mean over episodes of the largest
|obs[watch]| reached (``--watch``: 0 is the cart's position on the MuJoCo pendulums). On a MuJoCo
env it also starts at rest with qpos[0] (the cart's position on the pendulums) at each of
``--offsets`` and compares the model's Q at the candidate actions with the exact Q^pi there
(gap_decomposition.exact_q: one true step, then true rollouts of pi): ``regret`` is the exact Q^pi
lost by the model's pick; ``phi_error`` the model's one-step error there, mean over the candidates of
|E_model[phi~(S')] - phi~(s')| over |phi~(s') - phi(s)| (as gap_decomposition.py); ``data_near`` the
share of the agent's stored transitions whose obs[watch] lies within ``NEAR`` of the start's. A policy whose
return falls under noise far smaller than its candidates' spacing holds only by an exact action
(e.g. a zero force that keeps the cart still), and a refinement that moves the action by as much
fails for the same reason, not because it exploits the model. Each seed's model goes to
results/<stem>/<env>_seed<k>.zip and its record to .json (scratch); the report to results/<stem>.md.

    python -m benchmarks.diagnostics.action_robustness --env-id InvertedPendulum-v5 --seeds 0 1 2 3 4
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from benchmarks.common import SeedFiles, add_seed_arguments, command_line, map_seeds, markdown_table, write_markdown
from benchmarks.diagnostics.gap_decomposition import (
    COLLECTION_SEED_OFFSET,
    Steps,
    Visited,
    exact_q,
    recorded_row,
    simulate_all,
)
from benchmarks.diagnostics.true_dynamics_planning import rollout_horizon
from cme_agent import CMEPolicyIteration

NOISE_LEVELS = (0.05, 0.1, 0.2)
"""Default half-widths of the uniform action noise, in units of the action's half-range."""
OFFSETS = (-0.6, -0.4, -0.2, 0.0, 0.2, 0.4, 0.6)
"""Default starts: qpos[0] (env units), the rest of the state at the env's initial one, at rest."""
COLUMNS = ("return", "length", "max_abs_watched")
LARGE_REGRET = 0.5
"""A regret of the model's pick above this (reward units) is counted apart in the report."""
OFFSET_MEANS = ("regret", "phi_error", "data_near")
"""The per-start numbers averaged over seeds, per offset, in the report."""
NEAR = 0.05
"""Half-width (env units of obs[watch]) of the window in which stored states count as data near a start."""


class ActingRule:
    """The trained agent's greedy action, perturbed by uniform noise or refined on the same Q.

    :param agent: the trained agent (Box actions)
    :param noise: half-width of the uniform noise, in half-ranges of the action (0: none)
    :param refine_steps: projected-ascent steps from the greedy candidate (0: none)
    :param seed: the noise's generator seed
    """

    def __init__(self, agent: CMEPolicyIteration, noise: float = 0.0, refine_steps: int = 0, seed: int = 0) -> None:
        space = agent.action_space
        if not isinstance(space, gym.spaces.Box):
            raise ValueError(f"action_robustness needs a Box action space, not {space}")
        self.agent, self.noise, self.rng = agent, noise, np.random.default_rng(seed)
        self.low, self.high = space.low, space.high
        self.search = dataclasses.replace(agent.policy.action_search, refine_steps=refine_steps)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """The action at one observation (obs_dim,) -> (act_dim,), inside the action box."""
        policy = self.agent.policy
        trained, policy.action_search = policy.action_search, self.search
        try:
            action, _ = self.agent.predict(obs, deterministic=True)
        finally:
            policy.action_search = trained
        half_range = (self.high - self.low) / 2
        action = action + self.rng.uniform(-self.noise, self.noise, size=action.shape) * half_range
        return np.clip(action, self.low, self.high).astype(self.low.dtype)


def run_episodes(env_id: str, act: ActingRule, episodes: int, seed: int, watch: int) -> tuple[dict[str, float], np.ndarray]:
    """``episodes`` episodes of ``act`` from the starts of ``seed``.

    :return: the means over episodes of ``COLUMNS`` (return, length, largest |obs[watch]|) and the
        (T, obs_dim) observations the actions were taken at
    """
    env = gym.make(env_id)
    returns, lengths, reached, visited = [], [], [], []
    for episode in range(episodes):
        obs, _ = env.reset(seed=seed + COLLECTION_SEED_OFFSET + episode)
        total, steps, largest, done = 0.0, 0, abs(float(obs[watch])), False
        while not done:
            visited.append(obs)
            obs, reward, terminated, truncated, _ = env.step(act(obs))
            total, steps, largest = total + float(reward), steps + 1, max(largest, abs(float(obs[watch])))
            done = terminated or truncated
        returns.append(total)
        lengths.append(steps)
        reached.append(largest)
    env.close()
    means = [statistics.mean(values) for values in (returns, lengths, reached)]
    return dict(zip(COLUMNS, means, strict=True)), np.asarray(visited, dtype=np.float32)


@torch.no_grad()
def refine_move(agent: CMEPolicyIteration, states: np.ndarray, refine_steps: int) -> float:
    """Mean |refined - greedy| action over ``states`` (T, obs_dim) and action dims, in half-ranges."""
    greedy = np.stack([ActingRule(agent)(s) for s in states])
    refined = np.stack([ActingRule(agent, refine_steps=refine_steps)(s) for s in states])
    space = agent.action_space
    return float(np.mean(np.abs(refined - greedy) / ((space.high - space.low) / 2)))


@torch.no_grad()
def picks_at_offsets(
    agent: CMEPolicyIteration, env_id: str, offsets: tuple[float, ...], watch: int = 0
) -> list[dict[str, Any]]:
    """The model's Q and the exact Q^pi at the candidates from rest with qpos[0] at each offset,
    with the model's one-step error there and the data near each start.

    :param watch: the observation dim on which stored states count as near a start (:data:`NEAR`)
    :return: per offset: ``model_q`` and ``exact_q`` (K,) lists, ``regret``, the exact Q^pi of the
        best candidate minus that of the model's pick, ``phi_error`` and ``data_near`` (module
        docstring); empty where the env has no ``set_state``
    """
    sim = gym.make(env_id).unwrapped
    if not offsets or not hasattr(sim, "set_state"):
        return []
    sim.reset(seed=0)
    qpos = np.repeat(sim.init_qpos[None].astype(np.float64), len(offsets), axis=0)
    qpos[:, 0] = offsets
    qvel = np.zeros((len(offsets), sim.init_qvel.size))
    obs = []
    for position, velocity in zip(qpos, qvel, strict=True):
        sim.set_state(position, velocity)
        obs.append(sim._get_obs())
    starts = Visited(np.asarray(obs), qpos, qvel, np.arange(len(offsets)))
    candidates = agent.policy.candidates.numpy()
    steps = simulate_all(sim, starts, candidates)
    exact = exact_q(agent, sim, steps, rollout_horizon(agent.gamma))
    model = agent.policy.candidate_q_values(torch.as_tensor(starts.obs, dtype=torch.float32)).numpy()
    sim.close()
    errors = one_step_errors(agent, starts.obs, candidates, steps)
    stored = torch.cat([store.get(slice(0, len(store))).obs[:, watch] for store in (agent.store, agent.holdout)]).numpy()
    return [
        {
            "offset": x,
            "model_q": model[i].tolist(),
            "exact_q": exact[i].tolist(),
            "regret": float(exact[i].max() - exact[i, model[i].argmax()]),
            "phi_error": float(errors[i]),
            "data_near": float(np.mean(np.abs(stored - starts.obs[i, watch]) <= NEAR)),
        }
        for i, x in enumerate(offsets)
    ]


@torch.no_grad()
def one_step_errors(agent: CMEPolicyIteration, obs: np.ndarray, candidates: np.ndarray, steps: Steps) -> np.ndarray:
    """Per state, the mean over the candidates of the model's one-step error
    |E_model[phi~(S')] - phi~(s')| / |phi~(s') - phi(s)|.

    :param obs: (N, obs_dim) states
    :param candidates: (K, act_dim) actions
    :param steps: the true transitions from every state under every candidate, of shape (N, K)
    :return: (N,)
    """
    n, k = steps.rewards.shape
    dynamics = agent.dynamics
    states = torch.as_tensor(np.repeat(obs, k, axis=0), dtype=torch.float32)
    actions = torch.as_tensor(np.tile(candidates, (n, 1)), dtype=torch.float32)
    phi = dynamics.phi(states)
    predicted, _ = dynamics.read(phi, dynamics.features(states, actions) @ dynamics.readout())
    alive = torch.as_tensor(~steps.terminated.reshape(-1), dtype=torch.float32).unsqueeze(1)
    true_next = dynamics.phi(torch.as_tensor(steps.obs.reshape(n * k, -1), dtype=torch.float32)) * alive
    ratio = (predicted - true_next).norm(dim=1) / (true_next - phi).norm(dim=1).clamp_min(1e-12)
    return ratio.reshape(n, k).mean(dim=1).numpy()


def measure(
    agent: CMEPolicyIteration,
    env_id: str,
    episodes: int,
    seed: int,
    watch: int,
    noise: tuple[float, ...],
    refine_steps: int,
    offsets: tuple[float, ...] = (),
) -> dict[str, Any]:
    """Every mode's means over ``episodes`` episodes, the refinement's move on the agent's own
    states, and the picks from rest at ``offsets`` (:func:`picks_at_offsets`)."""
    modes: dict[str, dict[str, float]] = {}
    modes["agent"], own_states = run_episodes(env_id, ActingRule(agent), episodes, seed, watch)
    for level in noise:
        modes[f"noise {level:g}"], _ = run_episodes(env_id, ActingRule(agent, noise=level, seed=seed), episodes, seed, watch)
    modes["refined"], _ = run_episodes(env_id, ActingRule(agent, refine_steps=refine_steps), episodes, seed, watch)
    return {
        "modes": modes,
        "refine_move": refine_move(agent, own_states, refine_steps),
        "offsets": picks_at_offsets(agent, env_id, offsets, watch),
    }


@dataclass(frozen=True)
class Job(SeedFiles):
    """One seed: train ``env_id`` for ``steps`` env steps (constructor arguments ``kwargs``), then
    act on its Q in each mode; files under results/<stem>/."""

    env_id: str
    seed: int
    steps: int
    kwargs: dict[str, Any]
    episodes: int
    watch: int
    noise: tuple[float, ...]
    refine_steps: int
    offsets: tuple[float, ...]
    stem: str


def run_seed(job: Job) -> dict[str, Any]:
    """Train (or load) one agent and measure it, or read the record of an earlier run."""
    row = recorded_row(
        job,
        lambda agent: measure(agent, job.env_id, job.episodes, job.seed, job.watch, job.noise, job.refine_steps, job.offsets),
    )
    print(job.env_id, job.seed, {mode: round(values["return"], 1) for mode, values in row["modes"].items()}, flush=True)
    return row


def report(args: argparse.Namespace, rows: list[dict[str, Any]]) -> str:
    """The markdown report: per mode, each column's mean over seeds (per seed in brackets)."""
    table = []
    for mode in rows[0]["modes"]:
        cells = []
        for column in COLUMNS:
            per_seed = [row["modes"][mode][column] for row in rows]
            cells.append(f"{statistics.mean(per_seed):.3g} ({', '.join(f'{v:.3g}' for v in per_seed)})")
        table.append([mode, *cells])
    moves = [row["refine_move"] for row in rows]
    return "\n".join(
        [
            f"# The greedy policy on {args.env_id} under small changes of its actions\n",
            f"Command: `{command_line()}`.\n",
            f'`CMEPolicyIteration("CMEPolicy", {args.env_id!r}, seed=seed, **{json.loads(args.kwargs)})` trained for '
            f"{args.steps} env steps, then {args.episodes} episodes per mode on the same Q; seeds {args.seeds}. Each cell: "
            "the mean over seeds (per seed in brackets); noise in half-ranges of the action; the watched column is "
            f"the largest |obs[{args.watch}]| of an episode. Definitions: the module docstring of "
            "`benchmarks/diagnostics/action_robustness.py`.\n",
            markdown_table(["mode", "return", "episode length", f"largest abs(obs[{args.watch}])"], table) + "\n",
            f"The refinement ({args.refine_steps} steps) moves the greedy action by {statistics.mean(moves):.3f} "
            f"half-ranges on average ({', '.join(f'{m:.3f}' for m in moves)}).\n",
            *offsets_section(rows),
        ]
    )


def offsets_section(rows: list[dict[str, Any]]) -> list[str]:
    """The picks from rest at each offset, seed by seed: the model's Q and the exact Q^pi per candidate."""
    if not rows[0]["offsets"]:
        return []

    def values(numbers: list[float]) -> str:
        return ", ".join(f"{v:.2f}" for v in numbers)

    table = [
        [
            row["seed"],
            f"{pick['offset']:+g}",
            values(pick["model_q"]),
            values(pick["exact_q"]),
            f"{pick['regret']:.2f}",
            f"{pick['phi_error']:.2f}",
            f"{pick['data_near']:.3f}",
        ]
        for row in rows
        for pick in row["offsets"]
    ]
    regrets = [pick["regret"] for row in rows for pick in row["offsets"]]
    wrong, large = sum(r > 0 for r in regrets), sum(r > LARGE_REGRET for r in regrets)
    by_offset = [
        [f"{pick['offset']:+g}", *(f"{statistics.mean(r['offsets'][i][key] for r in rows):.3g}" for key in OFFSET_MEANS)]
        for i, pick in enumerate(rows[0]["offsets"])
    ]
    return [
        f"From rest with qpos[0] at each offset: the model's pick loses exact Q^pi at {wrong} of {len(table)} starts, "
        f"more than {LARGE_REGRET:g} at {large}. Means over seeds per offset (data near: within {NEAR:g} of the "
        "start's watched dim):\n",
        markdown_table(["qpos[0]", "regret", "model's phi error", "data near"], by_offset) + "\n",
        markdown_table(
            [
                "seed",
                "qpos[0]",
                "model Q per candidate",
                "exact Q^pi per candidate",
                "regret",
                "model's phi error",
                "data near",
            ],
            table,
        )
        + "\n",
    ]


def add_episode_arguments(parser: argparse.ArgumentParser) -> None:
    """``--env-id`` (a Box action space), the seed arguments (one worker by default) and ``--episodes``."""
    parser.add_argument("--env-id", default="InvertedPendulum-v5", help="an env id with a Box action space")
    add_seed_arguments(parser, "")
    parser.add_argument("--episodes", type=int, default=10, help="episodes per mode and seed")
    parser.set_defaults(workers=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_episode_arguments(parser)
    parser.add_argument("--watch", type=int, default=0, help="the observation dim whose largest |value| is reported")
    parser.add_argument("--noise", nargs="+", type=float, default=list(NOISE_LEVELS), help="noise half-widths (half-ranges)")
    parser.add_argument("--refine-steps", type=int, default=10, help="projected-ascent steps of the refined mode")
    parser.add_argument("--offsets", nargs="*", type=float, default=list(OFFSETS), help="qpos[0] of the starts at rest")
    args = parser.parse_args()
    args.stem = args.stem or f"action_robustness_{args.env_id}"
    settings = (args.episodes, args.watch, tuple(args.noise), args.refine_steps, tuple(args.offsets), args.stem)
    jobs = [Job(args.env_id, seed, args.steps, json.loads(args.kwargs), *settings) for seed in args.seeds]
    write_markdown(args.stem, report(args, map_seeds(run_seed, jobs, args.workers)))


if __name__ == "__main__":
    main()
