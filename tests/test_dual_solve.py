"""Exact policy evaluation in primal and dual form, float32 products, and the evaluation's settings."""

import pytest
import torch

from cme_agent.config import EvaluationConfig, collection_size_for
from cme_agent.planning import bellman_residual_weights


def _rbf(x: torch.Tensor, points: int) -> torch.Tensor:
    """Gaussian bumps on a regular grid over [-1, 1]^d, plus the constant: (n, points^d + 1)."""
    centres = torch.linspace(-1, 1, points, dtype=x.dtype)
    spacing = 2 / (points - 1)
    features = torch.ones(x.shape[0], 1, dtype=x.dtype)
    for dim in range(x.shape[1]):
        bumps = torch.exp(-((x[:, dim : dim + 1] - centres) ** 2) / (2 * spacing**2))
        features = (features[:, :, None] * bumps[:, None, :]).reshape(x.shape[0], -1)
    return torch.cat([features, torch.ones_like(features[:, :1])], dim=1)


def _problem(n: int, dims: int, points: int, seed: int = 0):
    """phi at n states, phi at their model successors (a smooth drift plus noise), a reward bump; float64."""
    generator = torch.Generator().manual_seed(seed)
    x = torch.rand(n, dims, generator=generator, dtype=torch.float64) * 2 - 1
    successors = x + 0.05 * torch.tanh(x.flip(1)) + 0.01 * torch.randn(n, dims, generator=generator, dtype=torch.float64)
    return _rbf(x, points), _rbf(successors.clamp(-1.2, 1.2), points), torch.exp(-(x**2).sum(1) / 0.3)


def _primal_reference(phi, next_phi, rewards, gamma, l2):
    """The textbook primal solve, all in float64 with an explicit ridge matrix."""
    phi, next_phi, rewards = phi.double(), next_phi.double(), rewards.double()
    residual_map = phi - gamma * next_phi
    lhs = residual_map.T @ residual_map
    ridge = l2 * lhs.diagonal().abs().mean()
    return torch.linalg.solve(lhs + ridge * torch.eye(lhs.shape[0], dtype=torch.float64), residual_map.T @ rewards)


@pytest.mark.parametrize("n, points", [(300, 15), (200, 5)])  # p = 226 < n = 300: primal; p = 26 < 200 primal too
def test_dual_equals_primal_where_both_fit(n, points):
    """The dual w = X^T (M X^T + lambda I)^{-1} r (n < p) and the primal (n >= p) equal the reference (float64)."""
    phi, next_phi, rewards = _problem(n, 2, points)
    primal = bellman_residual_weights(phi, next_phi, rewards, 0.95, 1e-4)
    # the same problem with fewer states than features takes the dual branch; compare with the primal reference
    few = slice(0, phi.shape[1] - 1)
    dual = bellman_residual_weights(phi[few], next_phi[few], rewards[few], 0.95, 1e-4)
    assert torch.allclose(primal, _primal_reference(phi, next_phi, rewards, 0.95, 1e-4), rtol=1e-7, atol=1e-9)
    reference = _primal_reference(phi[few], next_phi[few], rewards[few], 0.95, 1e-4)
    assert torch.allclose(dual, reference, rtol=1e-6, atol=1e-8)


def test_fewer_states_than_features_uses_the_dual_and_fits_the_collection():
    phi, next_phi, rewards = _problem(150, 2, 21)  # n = 150 < p = 442
    w = bellman_residual_weights(phi, next_phi, rewards, 0.9, 1e-8)
    assert w.shape == (442,) and torch.isfinite(w).all()
    residual = (phi - 0.9 * next_phi) @ w - rewards
    assert float(residual.abs().max()) < 1e-3 * float(rewards.abs().max())
    reference = _primal_reference(phi, next_phi, rewards, 0.9, 1e-8)
    values, reference_values = phi @ w, phi @ reference
    assert float((values - reference_values).norm()) < 1e-5 * float(reference_values.norm())
    assert torch.allclose(w, reference, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize(
    "n, dims, points, tolerance",
    [(4000, 2, 15, 1e-3), (400, 2, 21, 1e-2)],  # primal (p = 226), dual (p = 442)
)
def test_float32_products_match_an_all_float64_reference(n, dims, points, tolerance):
    """Float32 inputs: the values phi w stay within the tolerance of the float64 solve on the same (rounded) inputs."""
    phi, next_phi, rewards = (t.float() for t in _problem(n, dims, points))
    w = bellman_residual_weights(phi, next_phi, rewards, 0.98, 1e-4)
    assert w.dtype == torch.float32
    reference = phi.double() @ _primal_reference(phi, next_phi, rewards, 0.98, 1e-4)
    error = float((phi.double() @ w.double() - reference).norm() / reference.norm())
    assert error < tolerance


def test_collection_size_follows_the_width_of_phi():
    default = EvaluationConfig()
    assert default.collection_size is None
    assert collection_size_for(12, default) == 2000
    assert collection_size_for(316, default) == 3160
    assert collection_size_for(1000, default) == 10_000
    assert collection_size_for(5000, default) == 20_000  # the cap
    assert collection_size_for(5000, EvaluationConfig(collection_size=300)) == 300


def test_float32_rewards_with_float64_features_are_accepted():
    phi, next_phi, rewards = _problem(100, 1, 5)
    assert bellman_residual_weights(phi, next_phi, rewards.float(), 0.9, 1e-4).dtype == torch.float64
