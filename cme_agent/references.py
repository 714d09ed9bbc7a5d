"""Reference returns that give an evaluation's return a scale: random actions on every env, and a
scripted controller where an env has one (Quadcopter-v0's :class:`~cme_agent.envs.QuadcopterPController`).

``train.py`` evaluates them after training on the evaluation episodes of the run (the same
seeded starts as the agent's evaluations), prints them beside the agent's return with the
fraction of the controller's return, and keeps them in ``summary.json``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from stable_baselines3.common.evaluation import evaluate_policy

from cme_agent.envs import QuadcopterPController

RANDOM = "random actions"
"""The name of the uniformly random policy's reference."""

CONTROLLERS: dict[str, tuple[str, Callable[[gym.Env], Any]]] = {
    "Quadcopter-v0": ("scripted controller", QuadcopterPController.from_env),
}
"""Scripted controllers by env id: a name, and a function making the controller (anything with
SB3's ``predict``) for an env; add yours here to have ``train.py`` report against it."""


class RandomPolicy:
    """Uniformly random actions, with SB3's ``predict`` (for ``evaluate_policy``).

    :param action_space: the env's action space
    :param seed: seed of the action draws
    """

    def __init__(self, action_space: spaces.Space, seed: int) -> None:
        self.action_space = action_space
        self.action_space.seed(seed)

    def predict(
        self,
        observation: np.ndarray,
        state: Any = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, None]:
        """One random action per observation of the batch ``(n_envs, ...)``."""
        return np.stack([self.action_space.sample() for _ in range(len(observation))]), None


@dataclass(frozen=True)
class Reference:
    """The return of a reference policy on a run's evaluation episodes.

    :param name: what the policy is (``"random actions"``, ``"scripted controller"``)
    :param mean_reward: mean return over the episodes
    :param std_reward: standard deviation of the return over the episodes
    """

    name: str
    mean_reward: float
    std_reward: float

    def as_dict(self) -> dict[str, float]:
        """The numbers, for ``summary.json``."""
        return {"mean_reward": self.mean_reward, "std_reward": self.std_reward}


def reference_returns(env_id: str | None, make_eval_env: Callable[[], gym.Env], n_episodes: int, seed: int) -> list[Reference]:
    """Random actions and, where ``env_id`` has one (:data:`CONTROLLERS`), the scripted controller,
    each on ``n_episodes`` episodes of a fresh ``make_eval_env()``: the starts of the run's evaluations.

    :param env_id: the env's registered id (None: random actions only)
    :param make_eval_env: returns a fresh, seeded evaluation env (``cme_agent.experiment.make_eval_env``)
    :param n_episodes: episodes per reference
    :param seed: seed of the random actions
    :return: the references, the random one first
    """
    policies: list[tuple[str, Callable[[gym.Env], Any]]] = [(RANDOM, lambda env: RandomPolicy(env.action_space, seed))]
    if env_id in CONTROLLERS:
        policies.append(CONTROLLERS[env_id])
    references = []
    for name, make_policy in policies:
        env = make_eval_env()
        mean, std = evaluate_policy(make_policy(env), env, n_eval_episodes=n_episodes, deterministic=True)
        env.close()
        references.append(Reference(name, float(mean), float(std)))
    return references


def controller_fraction(mean_reward: float, references: list[Reference]) -> float | None:
    """The agent's return as a fraction of the scripted controller's (None: no controller, or
    a controller return <= 0, where a ratio says nothing).

    :param mean_reward: the agent's mean return on the same episodes
    :param references: from :func:`reference_returns`
    """
    controllers = [reference for reference in references if reference.name != RANDOM]
    if not controllers or controllers[0].mean_reward <= 0:
        return None
    return mean_reward / controllers[0].mean_reward
