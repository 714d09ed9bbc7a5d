"""The growing feature bank psi: S x A -> R^q of Gaussian kernels (paper section 2.2).

Feature j is ``psi_j(z) = exp(-||z - c_j||^2 / (2 h_j^2))`` on the normalised state-action
``z = (z_s, z_a)``. The bank only ever grows by appending, which is what lets the smoothed
Q weights be zero-padded instead of keeping a history (DESIGN.md, fact 2).
"""

from __future__ import annotations

import torch
from torch import nn


def gaussian_kernel(x: torch.Tensor, centres: torch.Tensor, inv_two_sq_bandwidth: torch.Tensor) -> torch.Tensor:
    """Gaussian kernel values between points and centres, one bandwidth per centre.

    :param x: (N, d) points
    :param centres: (q, d) centres
    :param inv_two_sq_bandwidth: (q,) values 1 / (2 h^2)
    :return: (N, q) kernel values in (0, 1]
    """
    sq_dist = (x * x).sum(1, keepdim=True) - 2 * x @ centres.T + (centres * centres).sum(1)
    return torch.exp(-sq_dist.clamp_min(0) * inv_two_sq_bandwidth)


class KernelBank(nn.Module):
    """psi as an ``nn.Module`` whose size q grows by :meth:`append`.

    :param state_dim: width of the normalised state part z_s
    :param action_dim: width of the normalised action part z_a
    :param n_features: initial q (0 for a new agent; the saved size when loading)
    """

    def __init__(self, state_dim: int, action_dim: int, n_features: int = 0) -> None:
        super().__init__()
        self.state_dim = state_dim
        self.register_buffer("centres", torch.zeros(n_features, state_dim + action_dim))
        self.register_buffer("inv_two_sq_bandwidth", torch.ones(n_features))

    @property
    def n_features(self) -> int:
        """q, the number of features."""
        return int(self.inv_two_sq_bandwidth.numel())

    def forward(self, z_state: torch.Tensor, z_action: torch.Tensor) -> torch.Tensor:
        """psi at paired state-actions.

        :param z_state: (N, state_dim) normalised states
        :param z_action: (N, action_dim) normalised actions
        :return: (N, q)
        """
        return gaussian_kernel(torch.cat([z_state, z_action], dim=1), self.centres, self.inv_two_sq_bandwidth)

    def factors(self, z_state: torch.Tensor, z_action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The state and action factors of psi for all N x K pairs at once.

        A Gaussian on a concatenation factorises, psi_j(s, a) = S[n, j] * A[k, j], so Q over all
        candidate actions is one product ``(S * theta) @ A.T`` instead of N * K kernel rows.

        :param z_state: (N, state_dim) normalised states
        :param z_action: (K, action_dim) normalised candidate actions
        :return: S (N, q) and A (K, q)
        """
        split = self.state_dim
        state_part = gaussian_kernel(z_state, self.centres[:, :split], self.inv_two_sq_bandwidth)
        action_part = gaussian_kernel(z_action, self.centres[:, split:], self.inv_two_sq_bandwidth)
        return state_part, action_part

    def append(self, centres: torch.Tensor, bandwidths: torch.Tensor) -> None:
        """Append features.

        :param centres: (l, state_dim + action_dim) new centres in normalised units
        :param bandwidths: (l,) their bandwidths h
        """
        self.centres = torch.cat([self.centres, centres.to(self.centres)])
        self.inv_two_sq_bandwidth = torch.cat([self.inv_two_sq_bandwidth, (1 / (2 * bandwidths**2)).to(self.centres)])
