"""Which part of the model of the observation costs the return? Its lookahead with parts swapped for the truth.

PointGoal2D-v0 (``cme_agent/envs/point_goal.py``) has its dynamics and reward in closed form. This
script trains ``CMEPolicyIteration("CMEPolicy", "PointGoal2D-v0", seed=seed)`` (library defaults,
where ``model_update.kind="auto"`` chooses the model of the observation, plus ``--kwargs``) for
``--steps`` env steps, then runs the trained agent (its value weights w unchanged) with its
lookahead planning through four transitions (``LookaheadPlanner.transition``):

- ``model``: the learned dynamics, termination and reward (the agent as trained);
- ``truth``: the env's dynamics and reward;
- ``true_reward``: the learned s' with the env's reward (the learned dynamics alone);
- ``true_dynamics``: the env's s' with the learned termination and reward at it (the learned reward alone);

each over the agent's candidate actions (``*_grid``) and with the first action refined by
``--refine-steps`` of projected ascent through that transition (``*_refined``,
``action_search.refine_steps``). Every return is of the same 10 episodes (an env seeded
seed + 10,000, reset as ``make_vec_env`` resets it). ``optimum`` is the best return of those
episodes, by trajectory optimisation of the 100 forces through the true dynamics (the env is
deterministic, so an open-loop optimum is the closed-loop one): Adam, then L-BFGS, on forces
``tanh(u)``.

Writes results/<stem>.md.

    python -m benchmarks.diagnostics.lookahead_parts --seeds 0 1 2 --steps 10000
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from benchmarks.common import add_seed_arguments, command_line, map_seeds, markdown_table, seed_table, write_markdown
from benchmarks.unseen_envs import CUSTOM_ENV, EVAL_EPISODES, EVAL_SEED_OFFSET
from cme_agent import CMEPolicyIteration
from cme_agent.envs.point_goal import ACTION_COST, PointGoal2D
from cme_agent.lookahead import LookaheadPlanner

TRANSITIONS = ("model", "truth", "true_reward", "true_dynamics")
METRICS = (*(f"{name}_{search}" for name in TRANSITIONS for search in ("grid", "refined")), "optimum")
EPISODE_STEPS = 100
"""PointGoal2D-v0's time limit."""

Transition = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor, torch.Tensor]]


def true_transition(env: PointGoal2D, obs: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """PointGoal2D's step in torch, differentiable in the actions: (N, 4), (N, 2) -> s' (N, 4), r (N,), float64."""
    force = actions.double().clamp(-1, 1)
    velocity = env.damping * obs.double()[:, 2:] + env.dt * force
    position = obs.double()[:, :2] + env.dt * velocity
    goal = torch.as_tensor(env.goal)
    distance = ((position - goal).square().sum(dim=1) + 1e-12).sqrt()  # smooth at the goal for the gradient
    return torch.cat([position, velocity], dim=1), -distance - ACTION_COST * force.square().sum(dim=1)


def swapped(planner: LookaheadPlanner, name: str, env: PointGoal2D) -> Transition:
    """The planner's transition with the parts ``name`` says taken from the env (module docstring)."""
    learned = planner.transition

    def transition(obs: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        next_obs, going_on, _ = learned(obs, actions)
        true_next, true_rewards = true_transition(env, obs, actions)
        if name == "truth":
            return true_next.float(), torch.ones_like(going_on), true_rewards.float()
        if name == "true_reward":
            return next_obs, going_on, true_rewards.float()
        model = planner.model  # "true_dynamics": the learned termination and reward at the true s'
        stay = 1 - model.terminates(true_next)
        at_true = stay * model.reward(true_next, planner.model_actions(actions)) + (1 - stay) * model.terminal_reward
        return true_next.float(), stay.float(), at_true.float()

    return learned if name == "model" else transition


def episode_starts(seed: int) -> np.ndarray:
    """The first observations of the 10 evaluation episodes: (10, 4)."""
    env = gym.make(CUSTOM_ENV)
    return np.stack([env.reset(seed=seed if episode == 0 else None)[0] for episode in range(EVAL_EPISODES)])


def returns(agent: CMEPolicyIteration, starts: np.ndarray, steps: int = EPISODE_STEPS) -> float:
    """Mean return of the agent's deterministic actions from each start, ``steps`` steps each."""
    env, total = PointGoal2D(), 0.0
    for start in starts:
        env.state = start.astype(np.float64)
        for _ in range(steps):
            total += env.step(agent.predict(env.state.astype(np.float32), deterministic=True)[0])[1]
    return total / len(starts)


def optimum(starts: np.ndarray, iterations: int = 1500, polish: int = 500) -> float:
    """The best mean return from ``starts`` (N, 4): open-loop forces tanh(u) through the true dynamics,
    ``iterations`` Adam steps then at most ``polish`` L-BFGS iterations."""
    env, obs = PointGoal2D(), torch.as_tensor(starts, dtype=torch.float64)
    controls = torch.zeros(len(obs), EPISODE_STEPS, 2, dtype=torch.float64, requires_grad=True)

    def mean_return() -> torch.Tensor:
        state, total = obs, torch.zeros((), dtype=torch.float64)
        for step in range(EPISODE_STEPS):
            state, rewards = true_transition(env, state, torch.tanh(controls[:, step]))
            total = total + rewards.sum()
        return total / len(obs)

    adam = torch.optim.Adam([controls], lr=0.05)
    for _ in range(iterations):
        adam.zero_grad()
        (-mean_return()).backward()
        adam.step()
    lbfgs = torch.optim.LBFGS([controls], max_iter=polish, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        lbfgs.zero_grad()
        loss = -mean_return()
        loss.backward()
        return loss

    lbfgs.step(closure)
    with torch.no_grad():
        return float(mean_return())


def run_seed(job: tuple[int, int, dict[str, Any], int]) -> dict[str, Any]:
    """Train one agent and measure it: (seed, steps, kwargs, refine_steps) -> its row."""
    seed, steps, kwargs, refine_steps = job
    torch.set_num_threads(1)
    agent = CMEPolicyIteration("CMEPolicy", CUSTOM_ENV, seed=seed, **kwargs).learn(steps)
    planner, policy = agent.policy.lookahead, agent.policy
    if planner is None:
        raise ValueError(f"the agent of seed {seed} runs the CME, not the model of the observation: nothing to swap")
    starts, env, search = episode_starts(seed + EVAL_SEED_OFFSET), PointGoal2D(), policy.action_search
    row: dict[str, Any] = {"seed": seed}
    for name in TRANSITIONS:
        planner.transition = swapped(planner, name, env)
        for label, steps_of_search in (("grid", 0), ("refined", refine_steps)):
            policy.action_search = dataclasses.replace(search, refine_steps=steps_of_search)
            row[f"{name}_{label}"] = returns(agent, starts)
        del planner.transition  # back to the class's method
    policy.action_search = search
    row["optimum"] = optimum(starts)
    print(seed, {key: round(float(row[key]), 3) for key in METRICS}, flush=True)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_seed_arguments(parser, "lookahead_parts")
    parser.add_argument("--refine-steps", type=int, default=10, help="projected-ascent steps of the refined columns")
    args = parser.parse_args()
    kwargs = json.loads(args.kwargs)
    rows = map_seeds(run_seed, [(seed, args.steps, kwargs, args.refine_steps) for seed in args.seeds], args.workers)
    text = (
        f"# Which part of the model of the observation costs the return? {CUSTOM_ENV}\n\n"
        f"Command: `{command_line()}`.\n\n"
        f'`CMEPolicyIteration("CMEPolicy", {CUSTOM_ENV!r}, seed=seed, **{kwargs})` trained for {args.steps} env '
        f"steps, then its return ({EVAL_EPISODES} episodes, env seeded seed + {EVAL_SEED_OFFSET:,}) with its "
        "lookahead through: the model (as trained); the truth; the learned s' with the true reward "
        "(true_reward); the true s' with the learned termination and reward (true_dynamics). *_grid: over "
        f"the agent's candidates; *_refined: the first action refined by {args.refine_steps} projected-ascent "
        "steps through that transition. optimum: the best return of those episodes, by trajectory "
        "optimisation through the true dynamics.\n\n"
        + markdown_table(["seed", *METRICS], seed_table(rows, ["seed"], METRICS))
        + "\n"
    )
    write_markdown(args.stem, text)


if __name__ == "__main__":
    main()
