"""The CME model and its SGD update (eq. (6))."""

import pytest
import torch

from cme_agent.dynamics import CMEModel, sgd_step


@pytest.mark.parametrize("learning_rate", [0.1, 0.5, 1.5])
def test_sgd_lowers_the_loss_for_fixed_psi(learning_rate):
    generator = torch.Generator().manual_seed(0)
    psi = torch.rand(2000, 50, generator=generator) ** 4
    truth = torch.randn(6, 50, generator=generator)
    targets = psi @ truth.T + 0.01 * torch.randn(2000, 6, generator=generator)
    model = CMEModel(6, 50, feature_dynamics=False, learn_reward=False)
    initial = float(model.loss(psi, targets))
    for _ in range(300):
        batch = torch.randint(2000, (64,), generator=generator)
        sgd_step(model.weights, psi[batch], targets[batch], learning_rate, l2=1e-6)
    final = float(model.loss(psi, targets))
    assert final < 0.5 * initial


def test_sgd_step_is_equation_6():
    psi = torch.tensor([[1.0, 2.0]])
    targets = torch.tensor([[3.0]])
    weights = torch.tensor([[0.5, -1.0]])
    sgd_step(weights, psi, targets, learning_rate=0.5, l2=0.1)
    eta = 0.5 / 5.0  # normalised by ||psi||^2
    expected = torch.tensor([[0.5, -1.0]]) * (1 - eta * 0.1) + eta * (3.0 - (0.5 - 2.0)) * psi
    assert torch.allclose(weights, expected)


def test_targets_feature_dynamics_and_absorbing_terminal_states():
    model = CMEModel(3, 0, feature_dynamics=True, learn_reward=True)
    phi = torch.tensor([[1.0, 0.0, 1.0], [0.0, 1.0, 1.0]])
    next_phi = torch.tensor([[0.0, 1.0, 1.0], [1.0, 0.0, 1.0]])
    targets = model.targets(phi, next_phi, torch.tensor([False, True]), torch.tensor([2.0, -1.0]))
    assert torch.equal(targets[0, :3], next_phi[0] - phi[0])
    assert torch.equal(targets[1, :3], -phi[1])  # terminal: phi(s') = 0
    assert torch.equal(targets[:, 3], torch.tensor([2.0, -1.0]))


def test_termination_probability_is_read_off_the_constant_feature():
    model = CMEModel(2, 2, feature_dynamics=True, learn_reward=False)
    model.weights[1] = torch.tensor([-0.25, 0.0])  # constant row: E[1 - done] - 1 = -P(done)
    constant, weights = model.termination_weights()
    psi = torch.tensor([[1.0, 0.0]])
    assert float(constant + psi @ weights) == pytest.approx(0.25)
