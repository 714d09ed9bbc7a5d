"""Does planning through a model of the observation hold in the loop, and does looking ahead help?

Trains ``CMEPolicyIteration("CMEPolicy", env_id, seed=seed)`` (library defaults plus ``--kwargs``)
for ``--steps`` env steps; its transitions (stored and held out) are D, and the agent lends phi,
gamma, omega, the candidate actions and its exploration noise. Then each mode (a model and a
lookahead depth) starts from that same D and repeats, up to ``--until`` env steps:

1. plan on D through the model: ``--rounds`` rounds of eq. (7) on a collection C of
   ``--collection`` states, a ``--uniform`` share of them uniform over the agent's observation
   box (known terminal states left out, as the agent's C) and the rest drawn from D, greedy over
   the candidates, smoothed by omega (:func:`observation_model.plan`);
2. evaluate the policy that looks ``depth`` steps ahead through the model: ``--episodes``
   episodes from the starts of action_robustness.py;
3. act ``--every`` env steps with that policy, Gaussian noise of the agent's ``noise_std``
   (in half-ranges) on every action, and add them to D.

Models: ``observation`` (:class:`cme_agent.dynamics.observation.ObservationModel`, refit on D at every round)
or ``true`` (the simulator's step from the observation, with the env's reward and termination;
envs whose observation is (qpos, qvel), e.g. InvertedPendulum-v5). The depth-d lookahead acts by
the exhaustive search (K^d leaves per action) of

    L_0(s) = <w, phi(s)>,  L_d(s) = max_a [r(s, a) + gamma (1 - P_term(s'_a)) L_{d-1}(s'_a)],

s'_a the model's next state; depth 1 is the greedy step of eq. (7)'s planner. The report gives,
per mode, every evaluation per seed, the mean of those from ``--late`` env steps on and how many
of them reach ``--target``. Records and the agents go to results/<stem>/ (scratch), the report to
results/<stem>.md.

    python -m benchmarks.diagnostics.planner_in_loop --env-id InvertedPendulum-v5 --seeds 0 1 2 3 4
"""

from __future__ import annotations

import argparse
import json
import statistics
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from benchmarks.common import SeedFiles, command_line, map_seeds, markdown_table, write_markdown
from benchmarks.diagnostics import observation_model as om
from benchmarks.diagnostics.action_robustness import add_episode_arguments, run_episodes
from benchmarks.diagnostics.gap_decomposition import recorded_row
from cme_agent import CMEPolicyIteration
from cme_agent.buffer import Transitions

MODELS = ("observation", "true")
LOOP_SEED_OFFSET = 30_000
"""The loop's own env is seeded seed + 30,000, apart from training and the evaluation's starts."""


class SimulatorStepper:
    """The simulator's step from an observation that is (qpos, qvel), with the env's reward and termination.

    :param env_id: a MuJoCo env id whose observation is the concatenated (qpos, qvel)
    """

    def __init__(self, env_id: str) -> None:
        self.sim = gym.make(env_id).unwrapped
        obs, _ = self.sim.reset(seed=0)
        self.nq = self.sim.model.nq
        state = np.concatenate([self.sim.data.qpos, self.sim.data.qvel])
        if obs.shape != state.shape or not np.allclose(obs, state):
            raise SystemExit(f"--models true: {env_id}'s observation is not (qpos, qvel)")

    def __call__(self, obs: torch.Tensor, candidates: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        rows = [self._step(state, action) for state in obs.double().numpy() for action in candidates.numpy()]
        next_obs, alive, rewards = zip(*rows, strict=True)
        return torch.as_tensor(np.stack(next_obs), dtype=torch.float32), torch.tensor(alive), torch.tensor(rewards)

    def _step(self, state: np.ndarray, action: np.ndarray) -> tuple[np.ndarray, float, float]:
        self.sim.set_state(state[: self.nq], state[self.nq :])
        next_obs, reward, terminated, _, _ = self.sim.step(action)
        return next_obs, 0.0 if terminated else 1.0, float(reward)


def lookahead_rule(
    phi: Callable[[torch.Tensor], torch.Tensor],
    step: om.Stepper,
    candidates: torch.Tensor,
    weights: torch.Tensor,
    gamma: float,
    depth: int,
) -> Callable[[np.ndarray], np.ndarray]:
    """The action of the depth-``depth`` lookahead (module docstring) at one observation.

    :param phi: the state features, (N, obs_dim) -> (N, p)
    :param step: the model
    :param candidates: (K, act_dim) candidate actions
    :param weights: (p,) value weights w
    :param gamma: discount factor
    :param depth: d >= 1
    """
    if depth < 1:
        raise ValueError(f"depth={depth} is invalid: must be >= 1")

    def backed_up(obs: torch.Tensor, remaining: int) -> torch.Tensor:
        """r + gamma P(going on) L_{remaining}(s'_a) at every candidate: (N, obs_dim) -> (N, K)."""
        next_obs, alive, rewards = step(obs, candidates)
        tail = phi(next_obs) @ weights if remaining == 0 else backed_up(next_obs, remaining - 1).max(dim=1).values
        return (rewards + gamma * alive * tail).reshape(len(obs), len(candidates))

    @torch.no_grad()
    def act(obs: np.ndarray) -> np.ndarray:
        return candidates[int(backed_up(torch.as_tensor(obs, dtype=torch.float32)[None], depth - 1).argmax())].numpy()

    return act


def collect(
    env: gym.Env, obs: np.ndarray, act: Callable[[np.ndarray], np.ndarray], steps: int, noise: float, rng: np.random.Generator
) -> tuple[Transitions, np.ndarray]:
    """``steps`` env steps of ``act`` plus N(0, noise) half-ranges on every action, clipped to the box.

    :return: the transitions and the observation to go on from
    """
    low, high = env.action_space.low, env.action_space.high
    rows = []
    for _ in range(steps):
        action = np.clip(act(obs) + rng.normal(0.0, noise, size=low.shape) * (high - low) / 2, low, high).astype(np.float32)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        rows.append((obs, action, reward, next_obs, terminated))
        obs = next_obs
        if terminated or truncated:
            obs, _ = env.reset()
    columns = [np.asarray(column) for column in zip(*rows, strict=True)]
    kinds = (torch.float32, torch.float32, torch.float32, torch.float32, torch.bool)
    return Transitions(*(torch.as_tensor(c, dtype=kind) for c, kind in zip(columns, kinds, strict=True))), obs


def run_mode(agent: CMEPolicyIteration, data: Transitions, job: Job, model_name: str, depth: int) -> list[float]:
    """One mode's loop (module docstring) from ``data``: the return of each evaluation."""
    env, rng = gym.make(job.env_id), np.random.default_rng(job.seed)
    obs, _ = env.reset(seed=job.seed + LOOP_SEED_OFFSET)
    noise, candidates, returns = agent.exploration_config.noise_std, agent.policy.candidates, []
    simulator = SimulatorStepper(job.env_id) if model_name == "true" else None
    while True:
        step = simulator or om.fitted(agent, data).step
        generator = torch.Generator().manual_seed(job.seed * 1_000 + len(returns))
        weights = om.plan(agent, om.as_model(agent, step), collection(agent, data, job, generator), job.rounds)
        act = lookahead_rule(agent.dynamics.phi, step, candidates, weights, agent.gamma, depth)
        returns.append(run_episodes(job.env_id, act, job.episodes, job.seed, watch=0)[0]["return"])
        if len(data) >= job.until:
            return returns
        new, obs = collect(env, obs, act, min(job.every, job.until - len(data)), noise, rng)
        data = data.concat(new)


def collection(agent: CMEPolicyIteration, data: Transitions, job: Job, generator: torch.Generator) -> torch.Tensor:
    """C: (|C|, obs_dim) states, a ``job.uniform`` share uniform over the observation box (known
    terminal states left out), the rest drawn from D without replacement."""
    n_uniform = round(job.uniform * job.collection)
    uniform = agent.dynamics.obs_encoder.sample_uniform(2 * n_uniform, generator)
    if agent.dynamics.reward.is_terminal is not None:
        uniform = uniform[~agent.dynamics.reward.is_terminal(uniform)]
    from_data = data.obs[torch.randperm(len(data), generator=generator)[: job.collection - min(n_uniform, len(uniform))]]
    return torch.cat([uniform[:n_uniform], from_data])


def measure(agent: CMEPolicyIteration, job: Job) -> dict[str, Any]:
    """Every mode's evaluations, from the agent's transitions, and the env steps they were made at."""
    data = agent.store.get(slice(0, len(agent.store))).concat(agent.holdout.get(slice(0, len(agent.holdout))))
    start = len(data)
    returns = {f"{name} d{depth}": run_mode(agent, data, job, name, depth) for name in job.models for depth in job.depths}
    steps = [min(start + i * job.every, job.until) for i in range(len(next(iter(returns.values()))))]
    return {"steps": steps, "returns": returns}


@dataclass(frozen=True)
class Job(SeedFiles):
    """One seed: train for ``steps`` env steps, then every mode's loop up to ``until``; files under results/<stem>/."""

    env_id: str
    seed: int
    steps: int
    kwargs: dict[str, Any]
    models: tuple[str, ...]
    depths: tuple[int, ...]
    until: int
    every: int
    episodes: int
    collection: int
    uniform: float
    rounds: int
    stem: str


def run_seed(job: Job) -> dict[str, Any]:
    """Train (or load) one agent and run every mode, or read the record of an earlier run."""
    row = recorded_row(job, lambda agent: measure(agent, job))
    print(job.env_id, job.seed, {mode: [round(r) for r in values] for mode, values in row["returns"].items()}, flush=True)
    return row


def summary(rows: list[dict[str, Any]], late: int, target: float) -> list[list[Any]]:
    """Per mode: the mean of every evaluation from ``late`` env steps on, how many reach ``target``, and the mean per step."""
    table = []
    for mode in rows[0]["returns"]:
        later = [r for row in rows for s, r in zip(row["steps"], row["returns"][mode], strict=True) if s >= late]
        by_step = [statistics.mean(row["returns"][mode][i] for row in rows) for i in range(len(rows[0]["steps"]))]
        reached = f"{sum(r >= target for r in later)}/{len(later)}"
        table.append(
            [mode, f"{statistics.mean(later):.1f}" if later else "-", reached, ", ".join(f"{r:.0f}" for r in by_step)]
        )
    return table


def report(args: argparse.Namespace, rows: list[dict[str, Any]]) -> str:
    """The markdown report: the summary per mode, then every evaluation per seed."""
    steps = rows[0]["steps"]
    per_seed = [
        [row["seed"], mode, ", ".join(f"{r:.0f}" for r in row["returns"][mode])] for mode in rows[0]["returns"] for row in rows
    ]
    return "\n".join(
        [
            f"# Planning in the loop through a model of the observation: {args.env_id}\n",
            f"Command: `{command_line()}`.\n",
            f'`CMEPolicyIteration("CMEPolicy", {args.env_id!r}, seed=seed, **{json.loads(args.kwargs)})` trained for '
            f"{args.steps} env steps; then each mode plans ({args.rounds} rounds of eq. (7) on {args.collection} states, "
            f"a share {args.uniform:g} of them uniform over the box), "
            f"evaluates ({args.episodes} episodes) and acts {args.every} env steps, up to {args.until}; seeds {args.seeds}. "
            "Definitions: the module docstring of `benchmarks/diagnostics/planner_in_loop.py`.\n",
            markdown_table(
                [
                    "mode",
                    f"mean return from {args.late} steps",
                    f"evaluations >= {args.target:g}",
                    f"mean return at {steps} steps",
                ],
                summary(rows, args.late, args.target),
            )
            + "\n",
            markdown_table(["seed", "mode", f"returns at {steps} steps"], per_seed) + "\n",
        ]
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_episode_arguments(parser)
    parser.set_defaults(steps=1000)
    parser.add_argument("--models", nargs="+", choices=MODELS, default=["observation"], help="the models planned through")
    parser.add_argument("--depths", nargs="+", type=int, default=[1, 3], help="lookahead depths of acting")
    parser.add_argument("--until", type=int, default=6000, help="env steps (training included) at which each loop stops")
    parser.add_argument("--every", type=int, default=1000, help="env steps acted between two plans")
    parser.add_argument("--collection", type=int, default=2000, help="states of C, drawn from D")
    parser.add_argument("--uniform", type=float, default=0.0, help="share of C uniform over the observation box")
    parser.add_argument("--rounds", type=int, default=30, help="rounds of evaluation and improvement per plan")
    parser.add_argument("--late", type=int, default=3000, help="env steps from which evaluations are summarised")
    parser.add_argument("--target", type=float, default=950.0, help="the return counted in the summary")
    args = parser.parse_args()
    args.stem = args.stem or f"planner_in_loop_{args.env_id}"
    settings = (
        tuple(args.models),
        tuple(args.depths),
        args.until,
        args.every,
        args.episodes,
        args.collection,
        args.uniform,
        args.rounds,
    )
    jobs = [Job(args.env_id, seed, args.steps, json.loads(args.kwargs), *settings, args.stem) for seed in args.seeds]
    write_markdown(args.stem, report(args, map_seeds(run_seed, jobs, args.workers)))


if __name__ == "__main__":
    main()
