"""Normalised encodings of observations and actions, shared by phi, psi and the C sampler.

Every observation dimension is mapped affinely to [-1, 1] from configured or space bounds;
an angle given as a (cos, sin) pair stays as is for psi, and becomes one periodic coordinate
(angle / pi in [-1, 1)) for the grid of phi. Box actions are mapped to [-1, 1], Discrete
actions to one-hot vectors.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from gymnasium import spaces

from cme_agent.config import ObservationConfig

KNOWN_OBSERVATIONS: dict[str, ObservationConfig] = {
    "Pendulum-v1": ObservationConfig(angle_pairs=((0, 1),)),
    "Acrobot-v1": ObservationConfig(angle_pairs=((0, 1), (2, 3))),
    "CartPole-v1": ObservationConfig(low=(-2.4, -3.0, -0.21, -3.5), high=(2.4, 3.0, 0.21, 3.5)),
}
"""Facts about the observations of known envs (angle pairs; finite bounds where the space has
none), used when ``policy_kwargs`` gives no ``observation``."""


def _bound(values: tuple[float, ...] | None, default: np.ndarray, name: str) -> np.ndarray:
    bound = default.astype(np.float64) if values is None else np.asarray(values, dtype=np.float64)
    if bound.shape != default.shape:
        raise ValueError(f"observation.{name} has {bound.size} values but the observation has {default.size} dims")
    return bound


class ObservationEncoder(torch.nn.Module):
    """Maps Box observations to normalised coordinates.

    :param space: the observation space (a 1-D ``Box``)
    :param config: bounds and angle pairs; bounds default to the space's where finite
    """

    def __init__(self, space: spaces.Box, config: ObservationConfig) -> None:
        super().__init__()
        low = _bound(config.low, space.low, "low")
        high = _bound(config.high, space.high, "high")
        angle_dims = {dim for pair in config.angle_pairs for dim in pair}
        for dim in angle_dims:
            if not 0 <= dim < space.shape[0]:
                raise ValueError(f"observation.angle_pairs names dim {dim}, but the observation has {space.shape[0]} dims")
            low[dim], high[dim] = -1.0, 1.0
        infinite = [i for i in range(low.size) if not (np.isfinite(low[i]) and np.isfinite(high[i]))]
        if infinite:
            raise ValueError(
                f"observation space {space} has infinite bounds in dims {infinite}: give the agent "
                "finite observation.low / observation.high for normalisation"
            )
        self.angle_pairs = [tuple(int(i) for i in pair) for pair in config.angle_pairs]
        self.linear_dims = [i for i in range(low.size) if i not in angle_dims]
        self.register_buffer("center", torch.as_tensor((high + low) / 2, dtype=torch.float32))
        self.register_buffer("half_range", torch.as_tensor((high - low) / 2, dtype=torch.float32))

    @property
    def dim(self) -> int:
        """Width of :meth:`normalize`'s output (the observation dimension)."""
        return int(self.center.numel())

    @property
    def grid_dim(self) -> int:
        """Width of :meth:`grid_coordinates`' output: one per angle pair and linear dim."""
        return len(self.angle_pairs) + len(self.linear_dims)

    @property
    def periodic(self) -> list[bool]:
        """Which grid coordinates are periodic (the angles come first)."""
        return [True] * len(self.angle_pairs) + [False] * len(self.linear_dims)

    def normalize(self, obs: torch.Tensor) -> torch.Tensor:
        """:param obs: (N, obs_dim) observations. :return: (N, obs_dim), each dim in [-1, 1]."""
        return (obs - self.center) / self.half_range

    def grid_coordinates(self, obs: torch.Tensor) -> torch.Tensor:
        """Coordinates for the grid of phi: (N, grid_dim), angles first as angle / pi.

        :param obs: (N, obs_dim) observations
        """
        angles = [torch.atan2(obs[:, j], obs[:, i]) / math.pi for i, j in self.angle_pairs]
        linear = self.normalize(obs)[:, self.linear_dims]
        return torch.cat([torch.stack(angles, dim=1) if angles else linear[:, :0], linear], dim=1)

    def sample_uniform(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """Draw ``n`` observations uniformly over the normalisation box (angles uniform on the circle).

        :return: (n, obs_dim) observations in env units
        """
        unit = (torch.rand(n, self.dim, generator=generator) * 2 - 1).to(self.center.device)
        obs = self.center + unit * self.half_range
        for i, j in self.angle_pairs:
            angle = unit[:, i] * math.pi
            obs[:, i], obs[:, j] = torch.cos(angle), torch.sin(angle)
        return obs


class ActionEncoder(torch.nn.Module):
    """Maps actions in env units to the normalised action part of psi's input.

    :param space: a 1-D ``Box`` (mapped to [-1, 1]) or a ``Discrete`` (one-hot)
    """

    def __init__(self, space: spaces.Box | spaces.Discrete) -> None:
        super().__init__()
        self.discrete = isinstance(space, spaces.Discrete)
        if self.discrete:
            self.n_actions = int(space.n)
            low, high = np.zeros(1), np.ones(1)
        else:
            low, high = space.low.astype(np.float64), space.high.astype(np.float64)
        self.register_buffer("low", torch.as_tensor(low, dtype=torch.float32))
        self.register_buffer("high", torch.as_tensor(high, dtype=torch.float32))

    @property
    def dim(self) -> int:
        """Width of the encoding: the number of actions (Discrete) or the action dim (Box)."""
        return self.n_actions if self.discrete else int(self.low.numel())

    def encode(self, actions: torch.Tensor) -> torch.Tensor:
        """:param actions: (N, act_dim) Box actions or (N,) Discrete indices. :return: (N, dim)."""
        if self.discrete:
            return torch.nn.functional.one_hot(actions.long().reshape(-1), self.n_actions).to(self.low.dtype)
        return 2 * (actions - self.low) / (self.high - self.low) - 1

    def decode(self, encoded: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`encode` for Box actions: (N, act_dim) in [-1, 1] to env units,
        clamped to the bounds (float rounding must never step outside the space)."""
        actions = self.low + (encoded.clamp(-1, 1) + 1) * (self.high - self.low) / 2
        return torch.minimum(torch.maximum(actions, self.low), self.high)
