"""Normalised encodings of observations and actions, shared by phi, psi and the C sampler.

Every observation dimension is mapped affinely to [-1, 1] from configured or space bounds,
or, where neither is usable (infinite or absurdly wide bounds), from a box estimated from the
first data (and expanded, a few times at most, when later data outgrows it); an angle given as
a (cos, sin) pair stays as is for psi, and becomes one periodic coordinate (angle / pi in
[-1, 1)) for the grid of phi. Box actions are mapped to [-1, 1], Discrete actions to one-hot
vectors.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from gymnasium import spaces

from cme_agent.config import ObservationConfig

PYTHON_BOUNDS_HINT = 'policy_kwargs={"observation": {"low": [...], "high": [...]}}'
"""How a user gives the normalisation box, shown wherever bounds are refused or missing."""

LOGGED_DIMS = 8
"""Estimated dims whose box :meth:`ObservationEncoder.fit` spells out in its log line."""

NARROW = 1e-3
"""An estimated half-range below this fraction of max(1, |centre|) is a constant's (:meth:`ObservationEncoder.fit`)."""

MAX_FIT_ROWS = 100_000
"""Observations the quantiles of :meth:`ObservationEncoder.fit` are taken over (evenly spaced rows)."""


def _bound(values: tuple[float, ...] | None, default: np.ndarray, name: str) -> np.ndarray:
    bound = default.astype(np.float64) if values is None else np.asarray(values, dtype=np.float64)
    if bound.shape != default.shape:
        raise ValueError(
            f"observation.{name} has {bound.size} values but the observation has {default.size} dims: "
            f"give one per dim, {PYTHON_BOUNDS_HINT}"
        )
    return bound


class ObservationEncoder(torch.nn.Module):
    """Maps Box observations to normalised coordinates.

    Bounds come from ``config.low/high`` where given, else from the space where usable
    (finite, half-range at most ``config.max_half_range``). The remaining dims are estimated by
    :meth:`fit` from the first data; until then :attr:`needs_fit` is True and normalising
    raises; :meth:`expand` widens them later. The box (``center``, ``half_range``), the
    ``fitted`` flag and the count of ``expansions`` are buffers, so a fitted box is saved and
    loaded with the state dict.

    :param space: the observation space (a 1-D ``Box``)
    :param config: bounds, angle pairs and how to estimate missing bounds
    """

    def __init__(self, space: spaces.Box, config: ObservationConfig) -> None:
        super().__init__()
        self.config = config
        low = _bound(config.low, space.low, "low")
        high = _bound(config.high, space.high, "high")
        angle_dims = {dim for pair in config.angle_pairs for dim in pair}
        for dim in angle_dims:
            if not 0 <= dim < space.shape[0]:
                raise ValueError(f"observation.angle_pairs names dim {dim}, but the observation has {space.shape[0]} dims")
            low[dim], high[dim] = -1.0, 1.0
        self.space_low, self.space_high = low.copy(), high.copy()
        unusable = ~(np.isfinite(low) & np.isfinite(high)) | ((high - low) / 2 > config.max_half_range)
        self.fit_dims = [int(i) for i in np.flatnonzero(unusable)]
        """Dims whose box is estimated from data by :meth:`fit`."""
        low[self.fit_dims], high[self.fit_dims] = np.nan, np.nan
        self.angle_pairs = [tuple(int(i) for i in pair) for pair in config.angle_pairs]
        self.linear_dims = [i for i in range(low.size) if i not in angle_dims]
        self.register_buffer("center", torch.as_tensor((high + low) / 2, dtype=torch.float32))
        self.register_buffer("half_range", torch.as_tensor((high - low) / 2, dtype=torch.float32))
        self.register_buffer("fitted", torch.tensor(not self.fit_dims))
        self.register_buffer("expansions", torch.zeros((), dtype=torch.long))
        self._ready = not self.fit_dims
        self.register_load_state_dict_post_hook(ObservationEncoder._after_load)

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any, **kwargs: Any) -> None:
        state_dict.setdefault(prefix + "expansions", torch.zeros((), dtype=torch.long))  # files before expand()
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @staticmethod
    def _after_load(module: torch.nn.Module, incompatible_keys: Any) -> None:
        """A loaded encoder is ready when the loaded ``fitted`` flag says so."""
        assert isinstance(module, ObservationEncoder)
        module._ready = bool(module.fitted)

    @property
    def needs_fit(self) -> bool:
        """Whether some dims still wait for :meth:`fit` (their box is estimated from data)."""
        return not self._ready

    def fit(self, obs: torch.Tensor) -> str:
        """Estimate the box of the dims without usable bounds from observations, and freeze it.

        Per dim: the quantiles q and 1 - q (``config.quantile``) widened by ``config.margin``
        of their range on each side, clipped to the space's bound where that side is finite;
        a dim whose half-range is below :data:`NARROW` ``max(1, |centre|)`` (constant in the bulk of the
        data) gets the half-range ``max(1, |centre|)``, its own magnitude: a value it takes later, or a
        model's small error there, then stays of its size in normalised units instead of thousands of
        half-ranges (InvertedDoublePendulum-v5's constraint force is 0 until the cart meets its rail).
        At most 100,000 evenly spaced rows are used. A second call is refused: phi's centres and psi's kernels are
        placed in the frozen coordinates (:meth:`expand` widens a fitted box, for a caller that
        moves them).

        :param obs: (N, obs_dim) observations in env units (N >= 1), e.g. the states and
            successors of the random phase
        :return: a one-line description of the chosen box, for the log
        """
        if not self.needs_fit:
            raise RuntimeError(
                "the observation box is already fitted (or given) and frozen: phi and psi live in its coordinates"
            )
        lower, upper = self._estimate(obs)
        self._set_box(lower, upper)
        self.fitted.fill_(True)
        self._ready = True
        q = self.config.quantile
        return (
            f"observation box estimated from {obs.shape[0]} observations (quantiles {q:g}..{1 - q:g}, "
            f"margin {self.config.margin:g}) for dims {self._describe()}; expanded if the data of "
            f"observation.expand_after={self.config.expand_after} successive iterations falls outside "
            f"(at most observation.max_expansions={self.config.max_expansions} times); "
            f"to give it yourself pass {PYTHON_BOUNDS_HINT}"
        )

    def expand(self, obs: torch.Tensor) -> str:
        """Widen the estimated box to cover new observations: per estimated dim, the union of
        the current box and the box :meth:`fit` would estimate from ``obs``. It never shrinks,
        so whatever was inside stays inside; given and space bounds never change. The caller
        moves whatever lives in the normalised coordinates (psi's centres, B: see
        :meth:`~cme_agent.dynamics.CMEDynamics.expand_observation_box`).

        :param obs: (N, obs_dim) observations in env units, e.g. the states of the iteration that outgrew the box
        :return: a one-line description of the new box, for the log
        """
        if self.needs_fit or not self.fit_dims:
            raise RuntimeError("only a fitted box of estimated dims can be expanded: fit() it first")
        lower, upper = self._estimate(obs)
        index = torch.as_tensor(self.fit_dims)
        center, half = self.center[index].double().cpu(), self.half_range[index].double().cpu()
        self._set_box(torch.minimum(lower, center - half), torch.maximum(upper, center + half))
        self.expansions.add_(1)
        return (
            f"observation box expanded to cover {obs.shape[0]} observations (expansion {int(self.expansions)}) "
            f"for dims {self._describe()}"
        )

    def outside_share(self, obs: torch.Tensor) -> float:
        """Share of observations outside the box in some estimated dim (0 when no dim is estimated).

        :param obs: (N, obs_dim) observations in env units
        """
        if not self.fit_dims or obs.shape[0] == 0:
            return 0.0
        z = self.normalize(obs)[:, self.fit_dims]
        return float((z.abs() > 1).any(dim=1).float().mean())

    def _estimate(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The quantile box of :meth:`fit` over the estimated dims: lower and upper (len(fit_dims),) float64."""
        if obs.ndim != 2 or obs.shape[1] != self.dim or obs.shape[0] == 0:
            raise ValueError(f"fit needs (N >= 1, {self.dim}) observations, got shape {tuple(obs.shape)}")
        rows = torch.linspace(0, obs.shape[0] - 1, min(obs.shape[0], MAX_FIT_ROWS)).round().long()
        data = obs[rows.to(obs.device)][:, self.fit_dims].double().cpu()
        if not torch.isfinite(data).all():
            raise ValueError("fit got non-finite observations")
        q = self.config.quantile
        lower = torch.quantile(data, q, dim=0)
        upper = torch.quantile(data, 1 - q, dim=0)
        spread = upper - lower
        lower = lower - self.config.margin * spread
        upper = upper + self.config.margin * spread
        space_low = torch.as_tensor(self.space_low[self.fit_dims])
        space_high = torch.as_tensor(self.space_high[self.fit_dims])
        lower = torch.where(torch.isfinite(space_low), torch.maximum(lower, space_low), lower)
        upper = torch.where(torch.isfinite(space_high), torch.minimum(upper, space_high), upper)
        return lower, upper

    def _set_box(self, lower: torch.Tensor, upper: torch.Tensor) -> None:
        center = (upper + lower) / 2
        half_range, magnitude = (upper - lower) / 2, center.abs().clamp_min(1.0)
        half_range = torch.where(half_range < NARROW * magnitude, magnitude, half_range)
        index = torch.as_tensor(self.fit_dims, device=self.center.device)
        self.center[index] = center.to(self.center)
        self.half_range[index] = half_range.to(self.half_range)

    def _describe(self) -> str:
        index = torch.as_tensor(self.fit_dims, device=self.center.device)
        center, half_range = self.center[index].tolist(), self.half_range[index].tolist()
        boxes = [f"{d}: [{c - h:.4g}, {c + h:.4g}]" for d, c, h in zip(self.fit_dims, center, half_range, strict=True)]
        return ", ".join(boxes[:LOGGED_DIMS]) + (f" and {len(boxes) - LOGGED_DIMS} more" if len(boxes) > LOGGED_DIMS else "")

    def _check_ready(self) -> None:
        if not self._ready:
            raise RuntimeError(
                f"observation dims {self.fit_dims} have no usable bounds (infinite, or half-range > "
                f"{self.config.max_half_range:g}): their normalisation box is estimated from the first data "
                f"(ObservationEncoder.fit), which has not happened yet; to give it yourself pass {PYTHON_BOUNDS_HINT}"
            )

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
        """:param obs: (N, obs_dim) observations. :return: (N, obs_dim), each dim in [-1, 1] inside the box."""
        self._check_ready()
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
        self._check_ready()
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
