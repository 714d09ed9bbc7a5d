"""Would a model of the observation plan better on the agent's own data? The CME against it, one planner.

Trains (or loads) ``CMEPolicyIteration("CMEPolicy", env_id, seed=seed)`` (library defaults plus
``--kwargs``) for ``--steps`` env steps, as action_robustness.py does, then plans on its stored
transitions with two models and one planner, and acts greedily on each (``--episodes`` episodes
from the starts of action_robustness.py):

- ``agent``: the agent as trained;
- ``cme``: the agent's own model, E_model[phi~(S') | s, a] and the expected reward read from psi;
- ``observation``: a model of the observation (:class:`cme_agent.dynamics.observation.ObservationModel`:
  the change s' - s linear in [s, a, 1], P(terminated | s') by logistic regression and the
  reward by ridge regression on quadratic features of s'), so that
  E[phi~(S')] ~ (1 - P(terminated | s^')) phi(s^') at the predicted s^' (:func:`as_model`).

The planner, the same for both models: C is ``--collection`` states drawn from the stored ones;
``--rounds`` rounds of eq. (7) on C, each greedy over the agent's candidates, the value weights
smoothed by the agent's omega; acting is greedy on the last Q through the same model. Also
reported: the observation model's held-out R^2 of the change per observation dim and its held-out
accuracy on termination (the agent's holdout transitions). Each seed's model goes to
results/<stem>/<env>_seed<k>.zip and its record to .json (scratch); the report to results/<stem>.md.

    python -m benchmarks.diagnostics.observation_model --env-id InvertedPendulum-v5 --seeds 0 1 2 3 4
"""

from __future__ import annotations

import argparse
import json
import statistics
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch

from benchmarks.common import SeedFiles, command_line, map_seeds, markdown_table, write_markdown
from benchmarks.diagnostics.action_robustness import add_episode_arguments, run_episodes
from benchmarks.diagnostics.gap_decomposition import recorded_row
from cme_agent import CMEPolicyIteration
from cme_agent.buffer import Transitions
from cme_agent.dynamics.observation import ObservationModel
from cme_agent.planning import bellman_residual_weights

MODES = ("agent", "cme", "observation")


class Model(Protocol):
    def __call__(self, obs: torch.Tensor, candidates: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """E[phi~(S')] (N, K, p) and the expected reward (N, K) at (N, obs_dim) states and (K, act_dim) candidates."""
        ...


Stepper = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor, torch.Tensor]]
"""A model that predicts the next state: at (N, obs_dim) states and (K, act_dim) candidates, the next states
(N K, obs_dim), the probability of going on (N K,) and the reward (N K,), state-major
(:meth:`ObservationModel.step`)."""


def fitted(agent: CMEPolicyIteration, data: Transitions) -> ObservationModel:
    """The observation model of ``agent``'s spaces fitted on ``data``."""
    model = ObservationModel(agent.observation_space.shape[0], agent.action_space.shape[0])
    model.fit(data)
    return model


def as_model(agent: CMEPolicyIteration, step: Stepper) -> Model:
    """The planner's view of a stepper: E[phi~(S')] = P(going on) phi(s^') (N, K, p) and the reward (N, K)."""

    @torch.no_grad()
    def model(obs: torch.Tensor, candidates: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        next_obs, going_on, rewards = step(obs, candidates)
        n, k = len(obs), len(candidates)
        return (agent.dynamics.phi(next_obs) * going_on.unsqueeze(1)).reshape(n, k, -1), rewards.reshape(n, k)

    return model


class CmeModel:
    """The agent's own model: E_model[phi~(S')] read from psi (:meth:`CMEDynamics.read`) and its expected reward."""

    def __init__(self, agent: CMEPolicyIteration) -> None:
        self.dynamics = agent.dynamics

    @torch.no_grad()
    def __call__(self, obs: torch.Tensor, candidates: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        dynamics, n, k = self.dynamics, len(obs), len(candidates)
        states, actions = obs.repeat_interleave(k, dim=0), candidates.repeat(n, *([1] * (candidates.dim() - 1)))
        phi, psi = dynamics.phi(states), dynamics.features(states, actions)
        predicted, _ = dynamics.read(phi, psi @ dynamics.readout())
        return predicted.reshape(n, k, -1), dynamics.expected_reward(states, actions, phi, psi).reshape(n, k)


@torch.no_grad()
def plan(agent: CMEPolicyIteration, model: Model, states: torch.Tensor, rounds: int) -> torch.Tensor:
    """Smoothed policy iteration on C through ``model``: (|C|, obs_dim) states -> (p,) value weights.

    Each round: pi = greedy over the candidates of Q = r + gamma <w, E[phi~(S')]>, w_k by eq. (7)
    at pi's actions, w <- (1 - omega) w + omega w_k.
    """
    next_phi, rewards = model(states, agent.policy.candidates)
    phi, rows = agent.dynamics.phi(states), torch.arange(len(states))
    weights = torch.zeros(phi.shape[1])
    for _ in range(rounds):
        pick = (rewards + agent.gamma * next_phi @ weights).argmax(dim=1)
        w = bellman_residual_weights(phi, next_phi[rows, pick], rewards[rows, pick], agent.gamma, agent.evaluation_config.l2)
        weights = (1 - agent.omega) * weights + agent.omega * w
    return weights


def greedy_rule(agent: CMEPolicyIteration, model: Model, weights: torch.Tensor) -> Callable[[np.ndarray], np.ndarray]:
    """The action at one observation: the candidate of largest r + gamma <w, E[phi~(S')]> through ``model``."""
    candidates = agent.policy.candidates

    @torch.no_grad()
    def act(obs: np.ndarray) -> np.ndarray:
        next_phi, rewards = model(torch.as_tensor(obs, dtype=torch.float32)[None], candidates)
        return candidates[int((rewards[0] + agent.gamma * next_phi[0] @ weights).argmax())].numpy()

    return act


@torch.no_grad()
def fit_scores(model: ObservationModel, holdout: Transitions) -> dict[str, Any]:
    """The observation model on held-out transitions: R^2 of the change per obs dim (dims that do
    not change: nan) and the accuracy of P(terminated | s') > 1/2."""
    moving = ~holdout.terminated
    obs, next_obs = holdout.obs.double()[moving], holdout.next_obs.double()[moving]
    actions = holdout.actions.double().reshape(len(holdout.obs), -1)[moving]
    change = next_obs - obs
    residual = model.next_obs(obs, actions) - next_obs
    variance = change.var(dim=0)
    r2 = torch.where(variance > 1e-12, 1 - residual.square().mean(dim=0) / variance.clamp_min(1e-12), float("nan"))
    predicted = model.terminates(holdout.next_obs) > 0.5
    return {"change_r2": r2.tolist(), "termination_accuracy": float((predicted == holdout.terminated).double().mean())}


def measure(agent: CMEPolicyIteration, env_id: str, seed: int, episodes: int, collection: int, rounds: int) -> dict[str, Any]:
    """The returns of the three modes (module docstring) and the observation model's held-out fit."""
    data, holdout = (store.get(slice(0, len(store))) for store in (agent.store, agent.holdout))
    rows = torch.randperm(len(data), generator=torch.Generator().manual_seed(seed))[:collection]
    states = data.obs[rows]
    observation = as_model(agent, fitted(agent, data.concat(holdout)).step)
    rules: dict[str, Callable[[np.ndarray], np.ndarray]] = {"agent": lambda obs: agent.predict(obs, deterministic=True)[0]}
    for name, model in (("cme", CmeModel(agent)), ("observation", observation)):
        rules[name] = greedy_rule(agent, model, plan(agent, model, states, rounds))
    returns = {name: run_episodes(env_id, rule, episodes, seed, watch=0)[0]["return"] for name, rule in rules.items()}
    return {"returns": returns, **fit_scores(fitted(agent, data), holdout)}


@dataclass(frozen=True)
class Job(SeedFiles):
    """One seed: train ``env_id`` for ``steps`` env steps (constructor arguments ``kwargs``), then
    plan on its data with each model; files under results/<stem>/."""

    env_id: str
    seed: int
    steps: int
    kwargs: dict[str, Any]
    episodes: int
    collection: int
    rounds: int
    stem: str


def run_seed(job: Job) -> dict[str, Any]:
    """Train (or load) one agent and measure it, or read the record of an earlier run."""
    row = recorded_row(job, lambda agent: measure(agent, job.env_id, job.seed, job.episodes, job.collection, job.rounds))
    print(job.env_id, job.seed, {mode: round(value, 1) for mode, value in row["returns"].items()}, flush=True)
    return row


def report(args: argparse.Namespace, rows: list[dict[str, Any]]) -> str:
    """The markdown report: the return of each mode per seed, and the observation model's fit."""
    table = [
        [
            row["seed"],
            *(f"{row['returns'][mode]:.1f}" for mode in MODES),
            f"{row['termination_accuracy']:.3f}",
            ", ".join("-" if np.isnan(v) else f"{v:.2f}" for v in row["change_r2"]),
        ]
        for row in rows
    ]
    means = [f"{statistics.mean(row['returns'][mode] for row in rows):.1f}" for mode in MODES]
    table.append(["mean", *means, "", ""])
    return "\n".join(
        [
            f"# Planning on the agent's data through its model or a model of the observation: {args.env_id}\n",
            f"Command: `{command_line()}`.\n",
            f'`CMEPolicyIteration("CMEPolicy", {args.env_id!r}, seed=seed, **{json.loads(args.kwargs)})` trained for '
            f"{args.steps} env steps, then {args.rounds} rounds of eq. (7) on {args.collection} stored states with each "
            f"model and {args.episodes} episodes of each policy; seeds {args.seeds}. Definitions: the module docstring of "
            "`benchmarks/diagnostics/observation_model.py`.\n",
            markdown_table(
                [
                    "seed",
                    *(f"return: {mode}" for mode in MODES),
                    "termination accuracy",
                    "held-out R^2 of the change per obs dim",
                ],
                table,
            )
            + "\n",
        ]
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_episode_arguments(parser)
    parser.add_argument("--collection", type=int, default=2000, help="states of C, drawn from the stored ones")
    parser.add_argument("--rounds", type=int, default=30, help="rounds of evaluation and improvement")
    args = parser.parse_args()
    args.stem = args.stem or f"observation_model_{args.env_id}"
    settings = (args.episodes, args.collection, args.rounds, args.stem)
    jobs = [Job(args.env_id, seed, args.steps, json.loads(args.kwargs), *settings) for seed in args.seeds]
    write_markdown(args.stem, report(args, map_seeds(run_seed, jobs, args.workers)))


if __name__ == "__main__":
    main()
