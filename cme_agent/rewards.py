"""Reward and termination functions, an input of Algorithm 1.

A :class:`RewardSpec` says what the agent knows of the reward:
``R(s, a, s') = step_reward(s, a) + terminal_bonus * [s' terminal]``. The planner uses the
expected reward ``step_reward(s, a) + terminal_bonus * P(terminate | s, a)``, the termination
probability coming from the learned model. ``is_terminal`` keeps terminal states out of the
planning collection C. Exact specs ship for the Gymnasium classics; custom envs may provide
``reward_function(obs, action)`` and ``termination_function(obs)`` methods; otherwise the
agent learns the reward by regression on psi (see :mod:`cme_agent.dynamics.model`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import gymnasium as gym
import torch

StepReward = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""(obs (N, obs_dim), action (N, act_dim) or (N,) indices) -> (N,) reward, torch ops only."""
Termination = Callable[[torch.Tensor], torch.Tensor]
"""(obs (N, obs_dim)) -> (N,) bool, True where the state is terminal."""


@dataclass(frozen=True)
class RewardSpec:
    """What the agent knows of the reward.

    :param step_reward: r(s, a) paid on every step, differentiable torch ops
    :param terminal_bonus: paid in addition on a step whose s' is terminal
    :param is_terminal: terminal states (kept out of C), or None if unknown
    """

    step_reward: StepReward
    terminal_bonus: float = 0.0
    is_terminal: Termination | None = None


def _pendulum_reward(obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    angle = torch.atan2(obs[:, 1], obs[:, 0])
    torque = action[:, 0].clamp(-2.0, 2.0)
    return -(angle**2 + 0.1 * obs[:, 2] ** 2 + 0.001 * torque**2)


def _constant_reward(value: float) -> StepReward:
    def reward(obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return torch.full((obs.shape[0],), value, dtype=obs.dtype, device=obs.device)

    return reward


def _action_cost(obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    return -0.1 * action[:, 0] ** 2


def _mountain_car_goal(goal_position: float) -> Termination:
    def is_terminal(obs: torch.Tensor) -> torch.Tensor:
        return (obs[:, 0] >= goal_position) & (obs[:, 1] >= 0)

    return is_terminal


def _cartpole_terminal(obs: torch.Tensor) -> torch.Tensor:
    return (obs[:, 0].abs() > 2.4) | (obs[:, 2].abs() > 12 * 2 * math.pi / 360)


def _acrobot_terminal(obs: torch.Tensor) -> torch.Tensor:
    cos1, sin1, cos2, sin2 = obs[:, 0], obs[:, 1], obs[:, 2], obs[:, 3]
    return -cos1 - (cos1 * cos2 - sin1 * sin2) > 1.0


KNOWN_REWARDS: dict[str, RewardSpec] = {
    "Pendulum-v1": RewardSpec(_pendulum_reward),
    "MountainCarContinuous-v0": RewardSpec(_action_cost, 100.0, _mountain_car_goal(0.45)),
    "MountainCar-v0": RewardSpec(_constant_reward(-1.0), 0.0, _mountain_car_goal(0.5)),
    "CartPole-v1": RewardSpec(_constant_reward(1.0), 0.0, _cartpole_terminal),
    "Acrobot-v1": RewardSpec(_constant_reward(-1.0), 1.0, _acrobot_terminal),
}
"""Exact reward specs of the Gymnasium classics, by env id (default env arguments)."""


def register_reward(env_id: str, spec: RewardSpec) -> None:
    """Make ``spec`` the known reward of every env with id ``env_id``."""
    KNOWN_REWARDS[env_id] = spec


def env_reward_spec(env: gym.Env) -> RewardSpec | None:
    """The spec an env provides through ``reward_function`` / ``termination_function`` methods."""
    unwrapped = env.unwrapped
    reward = getattr(unwrapped, "reward_function", None)
    if not callable(reward):
        return None
    terminal = getattr(unwrapped, "termination_function", None)
    return RewardSpec(reward, 0.0, terminal if callable(terminal) else None)


def resolve_reward(
    user_reward: RewardSpec | StepReward | None, env_id: str | None, env: gym.Env | None
) -> tuple[RewardSpec | None, str]:
    """Choose the reward the agent plans with, in order: the user's, the known spec of the
    env id, the env's own methods; None means it must be learned.

    :return: the spec (or None) and its source: ``"user"``, ``"known"``, ``"env"`` or ``"learned"``
    """
    if user_reward is not None:
        return (user_reward if isinstance(user_reward, RewardSpec) else RewardSpec(user_reward)), "user"
    if env_id in KNOWN_REWARDS:
        return KNOWN_REWARDS[env_id], "known"
    spec = env_reward_spec(env) if env is not None else None
    return (spec, "env") if spec is not None else (None, "learned")
