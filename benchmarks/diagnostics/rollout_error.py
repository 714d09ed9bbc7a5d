"""How far does the model of the observation drift when rolled forward? Its h-step error on a MuJoCo env.

Acting looks ``lookahead_depth`` steps ahead through the model of the observation
(:class:`~cme_agent.lookahead.LookaheadPlanner`), so its one-step error is not enough: a
prediction is fed back as the next input, and an input off the fit's data can turn a small error
into a large one. This trains (or loads) ``CMEPolicyIteration("CMEPolicy", env_id, seed=seed,
**kwargs)`` (default kwargs: the model of the observation with 500 waves) for ``--steps`` env steps,
then from ``--starts`` states of its deterministic episodes (env seeded seed + 20,000, simulator
states recorded) rolls ``--horizon`` steps of one action sequence each through the model and
through the simulator (MuJoCo's ``set_state``):

- ``random``: actions uniform in the action box (what a lookahead over the candidates tries);
- ``agent``: the actions the agent takes along the true rollout (closed loop on the true states).

The error at step h is |s^_h - s_h| per observation dim in units of the std of s' on the model's
fit data, averaged over the rollouts the simulator has not ended by step h (a terminated rollout
leaves the average): the report gives its mean over dims and its worst dim.
Each seed's model goes to results/<stem>/<env>_seed<k>.zip and its record to .json (scratch); the
report to results/<stem>.md (stem default rollout_error_<env>).

    python -m benchmarks.diagnostics.rollout_error --env-id InvertedDoublePendulum-v5 --seeds 0 1 --steps 10000
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from benchmarks.common import SeedFiles, command_line, map_seeds, markdown_table, write_markdown
from benchmarks.diagnostics.gap_decomposition import (
    COLLECTION_SEED_OFFSET,
    mujoco_parser,
    recorded_row,
    simulate,
    visited_states,
)
from cme_agent import CMEPolicyIteration
from cme_agent.lookahead import LookaheadPlanner

WAVES = {"model_update": {"kind": "observation", "change_fourier": 500}}
"""The default ``--kwargs``: the model of the observation with waves, the one a deep rollout asks most of."""
SOURCES = ("random", "agent")
REPORTED_STEPS = (1, 2, 3, 5, 8, 13, 20)
"""The steps h the report shows (those within ``--horizon``)."""


def rollout_errors(
    step: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    start: torch.Tensor,
    actions: torch.Tensor,
    true_obs: torch.Tensor,
    ended: torch.Tensor,
    std: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The model rolled from ``start`` with ``actions``, its error against the true rollout at each step.

    :param step: the model, (N, obs_dim) states and (N, act_dim) actions -> (N, obs_dim) next states
    :param start: (N, obs_dim) the first states
    :param actions: (H, N, act_dim) the action of each step
    :param true_obs: (H, N, obs_dim) the true state after each step
    :param ended: (H, N) whether the true rollout has terminated by that step (inclusive)
    :param std: (obs_dim,) the unit of the error per dim
    :return: (H, obs_dim) the mean |s^_h - s_h| / std over the rollouts going on at step h (nan where
        none is), and (H,) how many are
    """
    errors, counts, predicted = [], [], start
    for h in range(len(actions)):
        predicted = step(predicted, actions[h])
        going_on = ~ended[h]
        error = ((predicted - true_obs[h]).abs() / std)[going_on]
        errors.append(error.mean(dim=0) if len(error) else torch.full_like(std, float("nan")))
        counts.append(int(going_on.sum()))
    return torch.stack(errors), torch.tensor(counts)


def true_rollout(
    sim: Any, qpos: np.ndarray, qvel: np.ndarray, obs: np.ndarray, act: Callable[[np.ndarray], np.ndarray], horizon: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """H true steps from each state, all rollouts in lockstep (a terminated one steps on; its later states are not scored).

    :param sim: an unwrapped MuJoCo env (no time limit); its state is overwritten
    :param qpos: (N, nq) positions
    :param qvel: (N, nv) velocities
    :param obs: (N, obs_dim) their observations
    :param act: (N, obs_dim) true states -> (N, act_dim) actions, called at each step
    :param horizon: H
    :return: the actions (H, N, act_dim) the rollouts took, the states after each step (H, N, obs_dim) and
        whether each had terminated by then (H, N)
    """
    taken, states, ended = [], [], []
    done = np.zeros(len(obs), dtype=bool)
    for _ in range(horizon):
        action = act(obs)
        steps = simulate(sim, qpos, qvel, action)
        done = done | steps.terminated
        qpos, qvel, obs = steps.qpos, steps.qvel, steps.obs
        taken.append(action)
        states.append(obs)
        ended.append(done.copy())
    return np.stack(taken), np.stack(states), np.stack(ended)


def action_sources(
    agent: CMEPolicyIteration, box: gym.spaces.Box, rng: np.random.Generator
) -> dict[str, Callable[[np.ndarray], np.ndarray]]:
    """Per source of :data:`SOURCES`, the actions at the true states: (N, obs_dim) -> (N, act_dim)."""

    def uniform(obs: np.ndarray) -> np.ndarray:
        return rng.uniform(box.low, box.high, size=(len(obs), *box.shape)).astype(np.float32)

    def own(obs: np.ndarray) -> np.ndarray:
        return agent.predict(obs.astype(np.float32), deterministic=True)[0].reshape(len(obs), *box.shape)

    return {"random": uniform, "agent": own}


@torch.no_grad()
def measure(agent: CMEPolicyIteration, job: Job) -> dict[str, Any]:
    """The errors of the module docstring for one trained agent: per source, the mean over dims and the
    worst dim at each step, and the rollouts going on."""
    planner = agent.policy.lookahead
    if not isinstance(planner, LookaheadPlanner):
        raise SystemExit(f"the agent has no model of the observation (model kind {agent.policy.model_kind!r}): see --kwargs")
    sim, rng = gym.make(job.env_id).unwrapped, np.random.default_rng(job.seed)
    box = gym.make(job.env_id).action_space
    starts = visited_states(agent, job.env_id, job.starts, job.seed + COLLECTION_SEED_OFFSET)
    std = planner.model.std.float()

    def model_step(obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        return planner.transition(obs, actions)[0]

    row: dict[str, Any] = {"starts": len(starts.obs), "std": std.tolist()}
    for source, act in action_sources(agent, box, rng).items():
        actions, states, ended = true_rollout(sim, starts.qpos, starts.qvel, starts.obs, act, job.horizon)
        tensors = (torch.as_tensor(a, dtype=torch.float32) for a in (starts.obs, actions, states))
        errors, counts = rollout_errors(model_step, *tensors, torch.as_tensor(ended), std)
        worst = errors.max(dim=1).values
        row[source] = {
            "mean": errors.mean(dim=1).tolist(),
            "worst": worst.tolist(),
            "count": counts.tolist(),
            "per_dim": errors.tolist(),
        }
    return row


@dataclass(frozen=True)
class Job(SeedFiles):
    """One seed: train ``env_id`` with ``seed`` for ``steps`` env steps (constructor arguments ``kwargs``),
    then roll ``horizon`` steps from ``starts`` states; files under results/<stem>/."""

    env_id: str
    seed: int
    steps: int
    kwargs: dict[str, Any]
    starts: int
    horizon: int
    stem: str


def run_seed(job: Job) -> dict[str, Any]:
    """Train (or load) one agent and measure it, or read the record of an earlier run: its row."""
    row = recorded_row(job, lambda agent: measure(agent, job))
    for source in SOURCES:
        print(job.env_id, job.seed, source, [round(x, 3) for x in row[source]["worst"]], flush=True)
    return row


def report(args: argparse.Namespace, rows: list[dict[str, Any]]) -> str:
    """The markdown report: per source, a row per seed, a column per reported step."""
    shown = [h for h in REPORTED_STEPS if h <= args.horizon]
    sections = [
        f"# How far the model of the observation drifts on {args.env_id}: its h-step error\n",
        f"Command: `{command_line()}`.\n",
        f'`CMEPolicyIteration("CMEPolicy", {args.env_id!r}, seed=seed, **{json.loads(args.kwargs)})` trained for '
        f"{args.steps} env steps; {args.starts} starts from its deterministic episodes. Each cell: the mean |s^_h - s_h| "
        "over observation dims / the worst dim, in units of the std of s' on the model's fit data, over the rollouts "
        "going on at step h (in brackets: how many). Defined in the module docstring of "
        "`benchmarks/diagnostics/rollout_error.py`.\n",
    ]
    for source in SOURCES:
        header = ["seed", *(f"h = {h}" for h in shown)]
        table = [
            [row["seed"], *(f"{r['mean'][h - 1]:.3f} / {r['worst'][h - 1]:.3f} ({r['count'][h - 1]})" for h in shown)]
            for row in rows
            for r in [row[source]]
        ]
        title = "uniform random actions" if source == "random" else "the agent's own actions along the true rollout"
        sections += [f"## {title}\n", markdown_table(header, table) + "\n"]
    return "\n".join(sections)


def main() -> None:
    parser = mujoco_parser(__doc__)
    parser.add_argument("--starts", type=int, default=500, help="states the rollouts start from")
    parser.add_argument("--horizon", type=int, default=8, help="H: steps of each rollout")
    parser.set_defaults(workers=1, kwargs=json.dumps(WAVES))
    args = parser.parse_args()
    args.stem = args.stem or f"rollout_error_{args.env_id}"
    kwargs = json.loads(args.kwargs)
    jobs = [Job(args.env_id, seed, args.steps, kwargs, args.starts, args.horizon, args.stem) for seed in args.seeds]
    write_markdown(args.stem, report(args, map_seeds(run_seed, jobs, args.workers)))


if __name__ == "__main__":
    main()
