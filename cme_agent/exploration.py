"""The behaviour policy of data acquisition: the greedy policy mixed with a noisy version of it
(paper section 2.2, after Ross & Bagnell 2012).

Each episode of each env is exploratory with probability ``explore_fraction``. Exploratory
episodes add Gaussian noise to Box actions, or take uniformly random Discrete actions with
probability ``epsilon``. With ``repeat`` > 1 exploration is temporally extended: a random
action is held for ``repeat`` steps (ez-greedy, Dabney et al. 2021) and Box noise is an AR(1)
process with correlation time ``repeat`` steps and the same marginal std, which is what lets
sparse-reward tasks (Mountain Car, Acrobot) be reached by chance at all.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from gymnasium import spaces

from cme_agent.config import ExplorationConfig


class BehaviourPolicy:
    """Per-env exploration state and the actions it takes.

    :param action_space: a ``Discrete`` or 1-D ``Box`` space
    :param config: exploration settings
    :param rng: the agent's numpy generator (all draws come from it, in a fixed order)
    :param n_envs: number of envs stepped together
    """

    def __init__(self, action_space: spaces.Space, config: ExplorationConfig, rng: np.random.Generator, n_envs: int) -> None:
        self.space = action_space
        self.config = config
        self.rng = rng
        self.discrete = isinstance(action_space, spaces.Discrete)
        self.explore = rng.random(n_envs) < config.explore_fraction
        self.held = self._uniform(n_envs)
        self.hold_left = np.zeros(n_envs, dtype=np.int64)
        self.noise = np.zeros((n_envs, *action_space.shape))

    def _uniform(self, n: int) -> np.ndarray:
        if self.discrete:
            return self.rng.integers(self.space.n, size=n)
        return self.rng.uniform(self.space.low, self.space.high, size=(n, *self.space.shape)).astype(self.space.dtype)

    def _held_random(self, mask: np.ndarray) -> np.ndarray:
        """Random actions for the envs in ``mask``, each held for ``repeat`` steps once drawn."""
        fresh = mask & (self.hold_left == 0)
        self.held[fresh] = self._uniform(len(mask))[fresh]
        self.hold_left[fresh] = self.config.repeat
        self.hold_left[mask] -= 1
        return self.held

    def __call__(self, greedy: Callable[[], np.ndarray], random_phase: bool) -> np.ndarray:
        """The actions of all envs for one step.

        :param greedy: returns the greedy actions of all envs (called only when needed)
        :param random_phase: act uniformly at random (the first ``random_steps`` steps)
        :return: (n_envs,) Discrete or (n_envs, act_dim) Box actions
        """
        n = len(self.explore)
        if random_phase:
            return self._held_random(np.ones(n, dtype=bool)).copy()
        actions = greedy()
        if self.discrete:
            starting = self.rng.random(n) < self.config.epsilon
            random_pick = self.explore & ((self.hold_left > 0) | starting)
            return np.where(random_pick, self._held_random(random_pick), actions)
        rho = 1.0 - 1.0 / self.config.repeat
        half_range = (self.space.high - self.space.low) / 2
        innovation = self.rng.normal(0.0, self.config.noise_std, size=self.noise.shape) * half_range
        self.noise = rho * self.noise + np.sqrt(1 - rho**2) * innovation
        return np.clip(actions + self.noise * self.explore[:, None], self.space.low, self.space.high).astype(self.space.dtype)

    def end_episodes(self, dones: np.ndarray) -> None:
        """For each env whose episode ended: decide afresh whether the next one explores, drop held actions and noise."""
        redraw = self.rng.random(len(dones)) < self.config.explore_fraction
        self.explore = np.where(dones, redraw, self.explore)
        self.hold_left[dones] = 0
        self.noise[dones] = 0.0

    _STATE = ("explore", "held", "hold_left", "noise")

    def state_dict(self) -> dict[str, torch.Tensor]:
        """Per-env exploration state as tensors, for checkpoints."""
        return {name: torch.from_numpy(np.array(getattr(self, name), copy=True)) for name in self._STATE}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Restore a :meth:`state_dict` taken with the same number of envs."""
        if len(state["explore"]) != len(self.explore):
            raise ValueError(f"exploration state of {len(state['explore'])} envs, but there are {len(self.explore)}")
        for name in self._STATE:
            setattr(self, name, state[name].numpy().astype(getattr(self, name).dtype))
