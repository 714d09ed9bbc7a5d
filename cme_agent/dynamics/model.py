"""The conditional mean embedding model mu(s, a) = B psi(s, a) (paper eq. (1), section 2.3).

The regression target of a transition is the continuation-weighted successor feature
``phi~(s') = (1 - terminated) phi(s')`` (terminal states are absorbing with phi = 0), minus
``phi(s)`` in the feature-dynamics form of section 2.3. Since phi ends with a constant 1, the
model's last phi row predicts the continuation probability. When the reward is not known,
one more row regresses the (scaled) reward on the same psi features.
"""

from __future__ import annotations

import torch
from torch import nn


class CMEModel(nn.Module):
    """B in R^{p_out x q}, where p_out = p, plus one row when the reward is learned.

    :param n_state_features: p, the width of phi (its last feature is the constant 1)
    :param n_features: q, the current width of psi
    :param feature_dynamics: regress phi~(s') - phi(s) (section 2.3) instead of phi~(s')
    :param learn_reward: add a row that regresses r / reward_scale on psi
    """

    def __init__(self, n_state_features: int, n_features: int, feature_dynamics: bool, learn_reward: bool) -> None:
        super().__init__()
        self.n_state_features = n_state_features
        self.feature_dynamics = feature_dynamics
        self.learn_reward = learn_reward
        self.register_buffer("weights", torch.zeros(n_state_features + int(learn_reward), n_features))
        self.register_buffer("reward_scale", torch.ones(()))

    @property
    def phi_weights(self) -> torch.Tensor:
        """(p, q): the rows of B that predict phi."""
        return self.weights[: self.n_state_features]

    def targets(
        self, phi: torch.Tensor, next_phi: torch.Tensor, terminated: torch.Tensor, rewards: torch.Tensor
    ) -> torch.Tensor:
        """Regression targets of a batch.

        :param phi: (N, p) phi(s)
        :param next_phi: (N, p) phi(s')
        :param terminated: (N,) bool, s' terminal
        :param rewards: (N,) rewards
        :return: (N, p_out)
        """
        target = next_phi * (~terminated).unsqueeze(1).to(next_phi)
        if self.feature_dynamics:
            target = target - phi
        if self.learn_reward:
            target = torch.cat([target, (rewards / self.reward_scale).unsqueeze(1)], dim=1)
        return target

    def predict(self, psi: torch.Tensor) -> torch.Tensor:
        """:param psi: (N, q). :return: (N, p_out) predicted targets B psi."""
        return psi @ self.weights.T

    def loss(self, psi: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
        """Mean squared residual per transition, (1/N) sum_i ||y_i - B psi_i||^2 (loss (4) / N)."""
        return ((targets - self.predict(psi)) ** 2).sum(1).mean()

    def expected_next_phi(self, phi: torch.Tensor, psi: torch.Tensor) -> torch.Tensor:
        """E_model[phi~(S') | s, a]: (N, p) from phi(s) (N, p) and psi(s, a) (N, q)."""
        predicted = psi @ self.phi_weights.T
        return phi + predicted if self.feature_dynamics else predicted

    def reward_weights(self) -> torch.Tensor:
        """(q,) weights of the learned expected reward r(s, a) = <weights, psi(s, a)>."""
        if not self.learn_reward:
            raise RuntimeError("this model does not learn the reward")
        return self.weights[-1] * self.reward_scale

    def termination_weights(self) -> tuple[float, torch.Tensor]:
        """P(terminate | s, a) = c + <v, psi(s, a)>, read off the constant row of phi: (c, v (q,))."""
        constant_row = self.weights[self.n_state_features - 1]
        return (0.0, -constant_row) if self.feature_dynamics else (1.0, -constant_row)

    def append(self, new_weights: torch.Tensor) -> None:
        """B_k = (B_{k-1}, new_weights): :param new_weights: (p_out, l) columns for new features."""
        self.weights = torch.cat([self.weights, new_weights.to(self.weights)], dim=1)
