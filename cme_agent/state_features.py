"""State feature maps phi: S -> R^p on which values are linear, V(s) = <w, phi(s)>.

Every map ends with a constant feature 1. With absorbing terminal states (phi = 0 there),
the model's prediction of that constant is the continuation probability, which makes
termination part of the learned dynamics.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import nn

from cme_agent.config import StateFeatureConfig
from cme_agent.encoding import ObservationEncoder

MAX_GRID_FEATURES = 50_000
"""Largest RBF grid accepted; beyond it, phi.kind=fourier is the tool."""


class RBFGrid(nn.Module):
    """Gaussian radial basis functions on a regular grid over the grid coordinates of the encoder.

    phi(s) is the tensor product of one-dimensional Gaussian bumps, one factor per grid
    dimension; periodic dimensions (angles) wrap around. Output: (N, prod(resolution) + 1).

    :param encoder: gives the grid coordinates (angles first, all in [-1, 1])
    :param resolution: bumps per grid dimension (one value broadcasts to all)
    :param width: bump standard deviation in grid spacings
    """

    def __init__(self, encoder: ObservationEncoder, resolution: tuple[int, ...], width: float) -> None:
        super().__init__()
        n_dims = encoder.grid_dim
        if len(resolution) == 1:
            resolution = resolution * n_dims
        if len(resolution) != n_dims:
            raise ValueError(
                f"phi.resolution has {len(resolution)} entries but phi's grid has {n_dims} dims (angles count once)"
            )
        if math.prod(resolution) > MAX_GRID_FEATURES:
            raise ValueError(
                f"phi.resolution={list(resolution)} makes a grid of {math.prod(resolution):,} features over {n_dims} dims "
                f"(limit {MAX_GRID_FEATURES:,}): use phi.kind=fourier for high-dimensional observations"
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

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """:param obs: (N, obs_dim) observations. :return: (N, p) features."""
        coords = self.encoder.grid_coordinates(obs)
        features = torch.ones(obs.shape[0], 1, device=obs.device, dtype=obs.dtype)
        for dim, periodic in enumerate(self.periodic):
            diff = coords[:, dim : dim + 1] - getattr(self, f"centres_{dim}")
            if periodic:
                diff = torch.remainder(diff + 1, 2) - 1
            bumps = torch.exp(-(diff**2) * getattr(self, f"inv_two_var_{dim}"))
            features = (features[:, :, None] * bumps[:, None, :]).reshape(obs.shape[0], -1)
        return torch.cat([features, torch.ones_like(features[:, :1])], dim=1)


class RandomFourierFeatures(nn.Module):
    """Random Fourier features of a Gaussian kernel on the normalised observation.

    phi(s) = (sqrt(2 / D) cos(W z + b), 1) with z the normalised observation, W ~ N(0, 1/bw^2),
    b ~ U[0, 2 pi). Output: (N, D + 1). (cos, sin) angle pairs make it periodic by construction.

    :param encoder: normalises observations
    :param n_fourier: D, the number of random features
    :param bandwidth: kernel length scale in normalised units
    :param seed: seed of the fixed random projection
    """

    def __init__(self, encoder: ObservationEncoder, n_fourier: int, bandwidth: float, seed: int = 0) -> None:
        super().__init__()
        self.encoder = encoder
        generator = torch.Generator().manual_seed(seed)
        self.register_buffer("projection", torch.randn(encoder.dim, n_fourier, generator=generator) / bandwidth)
        self.register_buffer("phase", torch.rand(n_fourier, generator=generator) * 2 * math.pi)

    @property
    def width(self) -> int:
        """p: the random features plus the constant."""
        return int(self.phase.numel()) + 1

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """:param obs: (N, obs_dim) observations. :return: (N, p) features."""
        z = self.encoder.normalize(obs)
        features = math.sqrt(2 / self.phase.numel()) * torch.cos(z @ self.projection + self.phase)
        return torch.cat([features, torch.ones_like(features[:, :1])], dim=1)


class CustomStateFeatures(nn.Module):
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


def make_state_features(
    phi: StateFeatureConfig | nn.Module | Callable[[torch.Tensor], torch.Tensor], encoder: ObservationEncoder
) -> nn.Module:
    """Build phi from its config, or wrap a user-supplied map.

    :param phi: a :class:`StateFeatureConfig`, or a user map obs (N, obs_dim) -> (N, p0)
    :param encoder: the observation encoder
    :return: a module with a ``width`` attribute (p), obs (N, obs_dim) -> (N, p)
    """
    if not isinstance(phi, StateFeatureConfig):
        return CustomStateFeatures(phi, encoder.dim)
    if phi.kind == "rbf_grid":
        return RBFGrid(encoder, phi.resolution, phi.width)
    return RandomFourierFeatures(encoder, phi.n_fourier, phi.bandwidth)
