"""State feature maps phi: S -> R^p on which values are linear, V(s) = <w, phi(s)>.

Every map ends with a constant feature 1. With absorbing terminal states (phi = 0 there),
the model's prediction of that constant is the continuation probability, which makes
termination part of the learned dynamics.

The default phi (``phi.kind="auto"``) keeps p within ``phi.max_width`` (1,000) whatever the
observation dimension: an RBF grid of up to 11 points per grid dimension where one of at least
7 points per dimension fits (at most 3 grid dimensions at the default budget), random Fourier
features of length scale ``max(0.3, 0.1 obs_dim)`` beyond: a grid cannot resolve more dims
within the budget, and a length scale growing with the dimension keeps Fourier features able to
fit value-like targets (``python -m benchmarks.diagnostics.phi_basis``; docs/results.md).
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Callable
from typing import ClassVar

import torch
from torch import nn

from cme_agent.config import EvaluationConfig, StateFeatureConfig, collection_size_for
from cme_agent.encoding import ObservationEncoder
from cme_agent.linalg import GRAM_BLOCK, gram_blocks, random_cosines
from cme_agent.planning import evaluation_memory_bytes

DEFAULT_GRID_RESOLUTION = 11
"""Points per grid dimension of the default grid, where the budget allows."""
MIN_GRID_RESOLUTION = 7
"""Fewest points per grid dimension of a useful default grid; below it ``auto`` picks Fourier features."""
FOURIER_BANDWIDTH_PER_DIM = 0.1
"""Default Fourier length scale per observation dim, in normalised units ..."""
MIN_FOURIER_BANDWIDTH = 0.3
"""... and its floor: the default length scale is ``max(0.3, 0.1 obs_dim)``."""
DATA_BANDWIDTH_PER_SQRT_DIM = 0.4
"""Default Fourier length scale with ``phi.metric="data"``: ``0.4 sqrt(obs_dim)`` standard deviations."""
CONSTANT_DIM = 1e-6
"""A dim whose standard deviation in the data is at most this times max(1, |mean|) is constant."""
WARN_WIDTH = 4000
"""A phi wider than this gets a warning with the memory the evaluation will take."""
MAX_MEMORY_FRACTION = 0.5
"""A phi whose evaluation needs more than this fraction of physical memory is refused."""


class StateFeatureMap(nn.Module):
    """Base of the phi maps: ``forward`` (N, obs_dim) -> (N, p), the ``width`` p, and the
    regression targets of the model built from phi."""

    width: int
    fast_gram: ClassVar[bool] = False
    """Whether ``gram(obs, scale)`` gives ``Phi Phi^T`` cheaper than from Phi: policy evaluation
    may then solve eq. (7) on the factors of its residual map."""
    follows_data: bool = False
    """Whether phi's coordinates are fitted on observations (:meth:`fit`)."""

    @property
    def needs_fit(self) -> bool:
        """Whether phi waits for its first :meth:`fit`."""
        return False

    def fit(self, obs: torch.Tensor) -> str:
        """Fit phi's coordinates on observations (N, obs_dim), env units; the caller refits
        whatever was learned on the old phi. :return: a line for the log."""
        raise NotImplementedError(f"{type(self).__name__} has no coordinates to fit")

    def values(self, obs: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        """<w, phi(s)>: (N, obs_dim), (p,) -> (N,)."""
        return self(obs) @ weights

    def successor_targets(
        self, next_obs: torch.Tensor, continuation: torch.Tensor, obs: torch.Tensor | None = None
    ) -> torch.Tensor:
        """The model's regression targets ``continuation * phi(s') (- phi(s))``.

        :param next_obs: (N, obs_dim) successors s'
        :param continuation: (N,) 1 - terminated
        :param obs: (N, obs_dim) states s, or None for the targets phi~(s') alone
        :return: (N, p)
        """
        target = self(next_obs).mul_(continuation[:, None])
        return target if obs is None else target.sub_(self(obs))


class RBFGrid(StateFeatureMap):
    """Gaussian radial basis functions on a regular grid over the grid coordinates of the encoder.

    phi(s) is the tensor product of one-dimensional Gaussian bumps, one factor per grid
    dimension; periodic dimensions (angles) wrap around. Output: (N, prod(resolution) + 1).

    :param encoder: gives the grid coordinates (angles first, all in [-1, 1])
    :param resolution: bumps per grid dimension (one value broadcasts to all)
    :param width: bump standard deviation in grid spacings
    """

    fast_gram: ClassVar[bool] = True

    def __init__(self, encoder: ObservationEncoder, resolution: tuple[int, ...], width: float) -> None:
        super().__init__()
        n_dims = encoder.grid_dim
        if len(resolution) == 1:
            resolution = resolution * n_dims
        if len(resolution) != n_dims:
            raise ValueError(
                f"phi.resolution has {len(resolution)} entries but phi's grid has {n_dims} dims (angles count once)"
            )
        self.encoder = encoder
        self.resolution = tuple(resolution)
        self.periodic = encoder.periodic
        for dim, (points, periodic) in enumerate(zip(resolution, self.periodic, strict=True)):
            centres = torch.arange(points) * (2 / points) - 1 if periodic else torch.linspace(-1, 1, points)
            spacing = 2 / points if periodic else 2 / (points - 1)
            self.register_buffer(f"centres_{dim}", centres.float())
            self.register_buffer(f"inv_two_var_{dim}", torch.tensor(1 / (2 * (width * spacing) ** 2)))

    @property
    def width(self) -> int:
        """p: grid points plus the constant."""
        return math.prod(self.resolution) + 1

    def bumps(self, obs: torch.Tensor) -> list[torch.Tensor]:
        """The one-dimensional factors of phi: one (N, resolution[d]) matrix of Gaussian bumps per
        grid dimension d. :param obs: (N, obs_dim) observations."""
        coords = self.encoder.grid_coordinates(obs)
        factors = []
        for dim, periodic in enumerate(self.periodic):
            diff = coords[:, dim : dim + 1] - getattr(self, f"centres_{dim}")
            if periodic:
                diff = torch.remainder(diff + 1, 2) - 1
            factors.append(torch.exp(-(diff**2) * getattr(self, f"inv_two_var_{dim}")))
        return factors

    @staticmethod
    def _write_grid(out: torch.Tensor, factors: list[torch.Tensor], subtract: bool = False) -> None:
        """Write (or, with ``subtract``, subtract) the tensor product of ``factors`` into the grid
        part of ``out`` (N, p), in place. The product of every factor but the first is built from
        the last factor backwards, so that each product's inner dimension is the long one (one
        vectorised pass per product); the first factor is applied as the product is written."""
        tail = RBFGrid._tail(factors)
        grid = out[:, :-1].unflatten(1, (factors[0].shape[1], -1))
        if subtract:
            grid.addcmul_(factors[0][:, :, None], tail[:, None, :], value=-1)
        else:
            torch.mul(factors[0][:, :, None], tail[:, None, :], out=grid)

    @staticmethod
    def _tail(factors: list[torch.Tensor]) -> torch.Tensor:
        """The tensor product of every factor but the first, (N, prod_{d>0} r_d), from the last backwards."""
        tail = factors[-1] if len(factors) > 1 else factors[0].new_ones(factors[0].shape[0], 1)
        for factor in reversed(factors[1:-1]):
            tail = (factor[:, :, None] * tail[:, None, :]).flatten(1)
        return tail

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """:param obs: (N, obs_dim) observations. :return: (N, p) features."""
        if obs.requires_grad and torch.is_grad_enabled():  # differentiable (out= is not) for a caller taking gradients
            factors = self.bumps(obs)
            grid = (factors[0][:, :, None] * self._tail(factors)[:, None, :]).flatten(1)
            return torch.cat([grid, obs.new_ones(obs.shape[0], 1)], dim=1)
        out = obs.new_empty(obs.shape[0], self.width)
        out[:, -1] = 1
        self._write_grid(out, self.bumps(obs))
        return out

    def gram(self, obs: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
        """The lower triangle of ``Phi Phi^T`` (by blocks of rows, as
        :func:`~cme_agent.linalg.lower_gram`) in float64, from the factors of the tensor product:
        ``<phi(s), phi(t)> = 1 + prod_d <bumps_d(s), bumps_d(t)>``, O(N^2 sum_d r_d) instead of
        O(N^2 p).

        :param obs: (N, obs_dim) observations
        :param scale: a factor applied to the result
        :return: (N, N) float64, the blocks above the diagonal unset
        """
        factors = [factor.double() for factor in self.bumps(obs)]
        n = obs.shape[0]
        out = factors[0].new_empty(n, n)
        scratch = factors[0].new_empty(min(GRAM_BLOCK, n), n)
        for start, stop in gram_blocks(n):
            block = torch.mm(factors[0][start:stop], factors[0][:stop].T, out=out[start:stop, :stop])
            for factor in factors[1:]:
                block.mul_(torch.mm(factor[start:stop], factor[:stop].T, out=scratch[: stop - start, :stop]))
            block.add_(1).mul_(scale)
        return out

    def successor_targets(
        self, next_obs: torch.Tensor, continuation: torch.Tensor, obs: torch.Tensor | None = None
    ) -> torch.Tensor:
        """``continuation * phi(s') (- phi(s))`` in one pass over the (N, p) output: the
        continuation scales the first factor, and phi(s) is subtracted by a fused multiply-add
        from its factors (no (N, p) temporaries).

        :param next_obs: (N, obs_dim) successors s'
        :param continuation: (N,) 1 - terminated
        :param obs: (N, obs_dim) states s, or None for the targets phi~(s') alone
        :return: (N, p)
        """
        factors = self.bumps(next_obs)
        factors[0] = factors[0] * continuation[:, None]
        out = next_obs.new_empty(next_obs.shape[0], self.width)
        self._write_grid(out, factors)
        out[:, -1] = continuation
        if obs is not None:
            self._write_grid(out, self.bumps(obs), subtract=True)
            out[:, -1] -= 1
        return out


class RandomFourierFeatures(StateFeatureMap):
    """Random Fourier features of a Gaussian kernel.

    phi(s) = (sqrt(2 / D) cos(W z + b), 1) with W ~ N(0, 1/bw^2), b ~ U[0, 2 pi), and z the
    observation normalised by its box (``metric="box"``) or by the data's per-dim mean and
    standard deviation (``metric="data"``, set by :meth:`fit`). Output: (N, D + 1). (cos, sin)
    angle pairs make it periodic by construction.

    :param encoder: normalises observations
    :param n_fourier: D, the number of random features
    :param bandwidth: kernel length scale, in box units or standard deviations
    :param seed: seed of the fixed random projection
    :param metric: ``"box"`` or ``"data"``
    """

    def __init__(
        self, encoder: ObservationEncoder, n_fourier: int, bandwidth: float, seed: int = 0, metric: str = "box"
    ) -> None:
        super().__init__()
        self.encoder = encoder
        self.follows_data = metric == "data"
        generator = torch.Generator().manual_seed(seed)
        self.register_buffer("projection", torch.randn(encoder.dim, n_fourier, generator=generator) / bandwidth)
        self.register_buffer("phase", torch.rand(n_fourier, generator=generator) * 2 * math.pi)
        if self.follows_data:
            self.register_buffer("mean", torch.zeros(encoder.dim))
            self.register_buffer("inv_std", torch.ones(encoder.dim))
            self.register_buffer("fitted", torch.tensor(False))

    @property
    def width(self) -> int:
        """p: the random features plus the constant."""
        return int(self.phase.numel()) + 1

    @property
    def needs_fit(self) -> bool:
        """Whether the data metric waits for its first :meth:`fit`."""
        return self.follows_data and not bool(self.fitted)

    def fit(self, obs: torch.Tensor) -> str:
        """Set the data metric: per dim, the mean and the inverse standard deviation of ``obs``
        (N, obs_dim), 0 for a dim constant in it (left out of phi).

        :return: a line for the log
        """
        mean, std = obs.mean(dim=0), obs.std(dim=0) if obs.shape[0] > 1 else torch.zeros_like(obs[0])
        varies = std > CONSTANT_DIM * mean.abs().clamp_min(1)
        self.mean.copy_(mean)
        self.inv_std.copy_(torch.where(varies, 1 / std.clamp_min(1e-30), torch.zeros_like(std)))
        self.fitted.fill_(True)
        left_out = f"; dims {varies.logical_not().nonzero().flatten().tolist()} constant, left out" if not varies.all() else ""
        return f"phi's metric fitted on {obs.shape[0]} observations (per-dim mean and standard deviation){left_out}"

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """:param obs: (N, obs_dim) observations. :return: (N, p) features."""
        features = math.sqrt(2 / self.phase.numel()) * self.cosines(obs)
        return torch.cat([features, torch.ones_like(features[:, :1])], dim=1)

    def values(self, obs: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        """<w, phi(s)> without building phi's constant column or its scaled copy: (N, obs_dim), (p,) -> (N,)."""
        return self.cosines(obs) @ weights[:-1] * math.sqrt(2 / self.phase.numel()) + weights[-1]

    def cosines(self, obs: torch.Tensor) -> torch.Tensor:
        """cos(W z + b): (N, obs_dim) -> (N, D), in place where no gradient is taken."""
        z = (obs - self.mean) * self.inv_std if self.follows_data else self.encoder.normalize(obs)
        return random_cosines(z, self.projection, self.phase)


class CustomStateFeatures(StateFeatureMap):
    """Wraps a user-supplied map obs (N, obs_dim) -> (N, p0) and appends the constant feature.

    :param feature_map: an ``nn.Module`` (its parameters are saved with the policy) or a
        callable on tensors
    :param obs_dim: observation dimension, used to probe the output width
    """

    def __init__(self, feature_map: nn.Module | Callable[[torch.Tensor], torch.Tensor], obs_dim: int) -> None:
        super().__init__()
        self.feature_map = feature_map
        probe = feature_map(torch.zeros(2, obs_dim))
        if probe.ndim != 2 or probe.shape[0] != 2:
            raise ValueError(f"a custom phi must map (N, {obs_dim}) to (N, p); it returned shape {tuple(probe.shape)}")
        self._width = int(probe.shape[1]) + 1

    @property
    def width(self) -> int:
        """p: the user's features plus the constant."""
        return self._width

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """:param obs: (N, obs_dim) observations. :return: (N, p) features."""
        features = self.feature_map(obs)
        return torch.cat([features, torch.ones_like(features[:, :1])], dim=1)


def largest_resolution(grid_dim: int, max_width: int) -> int:
    """The largest r >= 2 with r^grid_dim + 1 <= max_width (2 when even that does not fit).

    :param grid_dim: dimensions of the grid (an angle pair counts once)
    :param max_width: budget on p
    """
    points = 2
    while (points + 1) ** grid_dim + 1 <= max_width:
        points += 1
    return points


def default_resolution(grid_dim: int, max_width: int) -> int | None:
    """Points per dimension of the default grid: the largest r <= 11 with r^grid_dim + 1 <= max_width.

    :param grid_dim: dimensions of the grid (an angle pair counts once)
    :param max_width: budget on p
    :return: r, or None when r would be below 7 (the grid is then too coarse to be useful)
    """
    points = min(largest_resolution(grid_dim, max_width), DEFAULT_GRID_RESOLUTION)
    return points if points >= MIN_GRID_RESOLUTION else None


def physical_memory_bytes(device: torch.device | str | None = None) -> int | None:
    """Memory the evaluation can use: a CUDA device's total memory, else this machine's
    physical memory (``os.sysconf``); None where it cannot be read.

    :param device: where the evaluation runs (None: the CPU)
    """
    device = torch.device("cpu" if device is None else device)
    if device.type == "cuda":
        return int(torch.cuda.get_device_properties(device).total_memory)
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def check_phi_memory(width: int, collection_size: int, source: str, device: torch.device | str | None = None) -> None:
    """Warn about a wide phi, and refuse one whose evaluation cannot fit in memory.

    Above :data:`WARN_WIDTH` features a ``UserWarning`` names p and the memory of the
    evaluation (:func:`~cme_agent.planning.evaluation_memory_bytes`); above
    :data:`MAX_MEMORY_FRACTION` of physical memory a ``ValueError`` gives both numbers.

    :param width: p, the width of phi
    :param collection_size: |C| the evaluation will use
    :param source: the setting that made this phi, for the messages (``"phi.resolution=[11]"``)
    :param device: where the evaluation runs (None: the CPU)
    """
    needed = evaluation_memory_bytes(width, collection_size)
    detail = (
        f"{source} makes phi {width:,} features wide: the evaluation holds |C| x p = {collection_size:,} x {width:,} "
        f"float32 matrices and a {min(width, collection_size):,}^2 float64 system, {needed / 2**30:.2f} GiB"
    )
    total = physical_memory_bytes(device)
    if total is not None and needed > MAX_MEMORY_FRACTION * total:
        where = "this machine's" if device is None or torch.device(device).type == "cpu" else f"{device}'s"
        raise ValueError(
            f"{detail}, more than {MAX_MEMORY_FRACTION:.0%} of {where} {total / 2**30:.1f} GiB: "
            f"use fewer features (the default phi keeps p <= phi.max_width=1000) or a smaller evaluation.collection_size"
        )
    if width > WARN_WIDTH:
        warnings.warn(f"{detail} per evaluation round (the default phi keeps p <= 1000)", UserWarning, stacklevel=3)


def make_state_features(
    phi: StateFeatureConfig | nn.Module | Callable[[torch.Tensor], torch.Tensor],
    encoder: ObservationEncoder,
    evaluation: EvaluationConfig | None = None,
    device: torch.device | str | None = None,
) -> StateFeatureMap:
    """Build phi from its config, or wrap a user-supplied map, and check its memory.

    ``kind="auto"``: an RBF grid when ``resolution`` is given or :func:`default_resolution`
    finds a useful one within ``max_width``, else random Fourier features. Defaults:
    ``resolution`` from :func:`default_resolution` (for a grid without one, the budget is
    respected down to 2 points per dimension), ``n_fourier = max_width - 1``, ``bandwidth =
    max(0.3, 0.1 obs_dim)`` box units or ``0.4 sqrt(obs_dim)`` standard deviations (``metric="data"``).
    ``metric="data"`` with ``kind="rbf_grid"`` is refused: a grid lives on the box.

    :param phi: a :class:`StateFeatureConfig`, or a user map obs (N, obs_dim) -> (N, p0)
    :param encoder: the observation encoder
    :param evaluation: the evaluation settings, for |C| in the memory check (None: defaults)
    :param device: where the evaluation will run, for the memory check (None: the CPU)
    :return: a module with a ``width`` attribute (p), obs (N, obs_dim) -> (N, p)
    """
    if isinstance(phi, StateFeatureConfig) and phi.metric == "data" and phi.kind == "rbf_grid":
        raise ValueError("phi.metric='data' is for Fourier features (phi.kind 'fourier' or 'auto'); a grid lives on the box")
    if not isinstance(phi, StateFeatureConfig):
        module: nn.Module = CustomStateFeatures(phi, encoder.dim)
        source = "the custom phi"
    else:
        resolution = phi.resolution
        if resolution is None and phi.kind != "fourier":
            points = default_resolution(encoder.grid_dim, phi.max_width)
            if points is None and phi.kind == "rbf_grid":
                points = largest_resolution(encoder.grid_dim, phi.max_width)
            resolution = None if points is None else (points,)
        if resolution is not None and phi.kind != "fourier":
            module = RBFGrid(encoder, resolution, phi.width)
            source = f"phi.resolution={list(module.resolution)}"
        else:
            n_fourier = phi.max_width - 1 if phi.n_fourier is None else phi.n_fourier
            if phi.metric == "data":
                bandwidth = DATA_BANDWIDTH_PER_SQRT_DIM * math.sqrt(encoder.dim)
            else:
                bandwidth = max(MIN_FOURIER_BANDWIDTH, FOURIER_BANDWIDTH_PER_DIM * encoder.dim)
            bandwidth = bandwidth if phi.bandwidth is None else phi.bandwidth
            module = RandomFourierFeatures(encoder, n_fourier, bandwidth, metric=phi.metric)
            source = f"phi.n_fourier={n_fourier}"
    width = int(module.width)
    check_phi_memory(width, collection_size_for(width, evaluation or EvaluationConfig()), source, device)
    return module
