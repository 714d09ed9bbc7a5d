"""The 'Kernel' baseline: every data point a feature, B relearned by kernel ridge regression."""

import torch

from cme_agent import KernelPolicyIteration
from cme_agent.dynamics.kernel_regression import kernel_ridge_weights


def test_kernel_ridge_weights_solve_the_regularised_system():
    generator = torch.Generator().manual_seed(0)
    x = torch.rand(40, 2, generator=generator)
    gram = torch.exp(-(torch.cdist(x, x) ** 2) / 0.1)
    targets = torch.randn(40, 3, generator=generator)
    weights = kernel_ridge_weights(gram, targets, l2=1e-3)
    residual = (gram.double() + 40 * 1e-3 * torch.eye(40, dtype=torch.float64)) @ weights.T.double() - targets.double()
    assert residual.abs().max() < 1e-4


def test_every_point_is_a_feature_and_b_is_the_kernel_solution(pendulum_kwargs):
    model = KernelPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, kernel_l2=1e-3, **pendulum_kwargs)
    model.learn(300)
    assert model.q == len(model.store) == model.policy.theta_psi.shape[0]
    psi, targets = model.dynamics.regression_data(model.store.get(slice(0, len(model.store))))
    expected = kernel_ridge_weights(psi, targets, 1e-3)
    assert torch.allclose(model.dynamics.weights, expected, atol=1e-5)
