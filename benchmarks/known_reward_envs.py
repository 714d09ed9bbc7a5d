"""Two suite envs under new ids whose exact reward the agent is given: a diagnostic.

The suite's envs (benchmarks/unseen_envs.py) make the agent learn its reward, and on
InvertedPendulum-v5 its termination too. Under these ids the same envs come with their exact
:class:`~cme_agent.rewards.RewardSpec` (registered with :func:`~cme_agent.rewards.register_reward`),
so a run with ``--env-id <id>`` separates what the learned reward costs from what the model and
the planner cost. Importing this module registers both ids (the spawned job processes import it too).

    python -m benchmarks.learning_quality --envs --env-id InvertedPendulumKnownReward-v5 --steps 5000 --target 950
"""

from __future__ import annotations

import gymnasium as gym
import torch

from benchmarks.unseen_envs import CUSTOM_ENV
from cme_agent.envs.point_goal import PointGoal2D
from cme_agent.rewards import RewardSpec, register_reward

INVERTED_PENDULUM = "InvertedPendulumKnownReward-v5"
POINT_GOAL = "PointGoal2DKnownReward-v0"
POLE_LIMIT = 0.2
"""InvertedPendulum-v5 terminates where |pole angle| (observation 1) exceeds it, in rad."""


def _alive(obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """InvertedPendulum-v5's reward ``1 - [s' terminal]``: its step part, 1 on every step, (N,)."""
    return torch.ones(obs.shape[0], dtype=obs.dtype, device=obs.device)


def _pole_fallen(obs: torch.Tensor) -> torch.Tensor:
    """(N, 4) observations -> (N,) True where InvertedPendulum-v5 terminates (or is not finite)."""
    return (obs[:, 1].abs() > POLE_LIMIT) | ~torch.isfinite(obs).all(dim=1)


def point_goal_reward(env: PointGoal2D) -> RewardSpec:
    """PointGoal2D's reward ``-|p' - goal| - 0.05 |a|^2`` written as r(s, a): p' follows from
    (s, a) by its deterministic step (velocity damped, then the clipped force added).

    :param env: an instance, for its goal, time step and damping
    """
    goal = torch.as_tensor(env.goal)

    def reward(obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        force = action.clamp(-1.0, 1.0)
        velocity = env.damping * obs[:, 2:] + env.dt * force
        position = obs[:, :2] + env.dt * velocity
        return -torch.linalg.vector_norm(position - goal.to(obs), dim=1) - 0.05 * (force**2).sum(dim=1)

    return RewardSpec(reward)


if INVERTED_PENDULUM not in gym.registry:
    gym.register(
        INVERTED_PENDULUM, entry_point="gymnasium.envs.mujoco.inverted_pendulum_v5:InvertedPendulumEnv", max_episode_steps=1000
    )
    register_reward(INVERTED_PENDULUM, RewardSpec(_alive, terminal_bonus=-1.0, is_terminal=_pole_fallen))
if POINT_GOAL not in gym.registry:
    gym.register(POINT_GOAL, entry_point=PointGoal2D, max_episode_steps=gym.spec(CUSTOM_ENV).max_episode_steps)
    register_reward(POINT_GOAL, point_goal_reward(PointGoal2D()))
