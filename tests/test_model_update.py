"""The CME model (CMEDynamics): targets, the SGD update of eq. (6), the reward it composes."""

import numpy as np
import pytest
import torch
from gymnasium import spaces

from cme_agent import RewardSpec
from cme_agent.buffer import Transitions
from cme_agent.dynamics import CMEDynamics, sgd_step

OBS = spaces.Box(-1.0, 1.0, (2,), np.float32)
ACTIONS = spaces.Box(-1.0, 1.0, (1,), np.float32)


def _dynamics(feature_dynamics: bool = True, reward: RewardSpec | None = None) -> CMEDynamics:
    """phi(s) = (s, 1): p = 3."""
    return CMEDynamics(OBS, ACTIONS, phi=lambda obs: obs, feature_dynamics=feature_dynamics, reward=reward)


def _transitions(n: int, seed: int = 0) -> Transitions:
    generator = torch.Generator().manual_seed(seed)
    obs = torch.rand(n, 2, generator=generator) * 2 - 1
    actions = torch.rand(n, 1, generator=generator) * 2 - 1
    next_obs = (0.9 * obs + 0.1 * actions).clamp(-1, 1)
    return Transitions(obs, actions, -(obs**2).sum(1), next_obs, torch.rand(n, generator=generator) < 0.1)


@pytest.mark.parametrize("learning_rate", [0.1, 0.5, 1.5])
def test_sgd_lowers_the_loss_for_fixed_psi(learning_rate):
    generator = torch.Generator().manual_seed(0)
    psi = torch.rand(2000, 50, generator=generator) ** 4
    truth = torch.randn(6, 50, generator=generator)
    targets = psi @ truth.T + 0.01 * torch.randn(2000, 6, generator=generator)
    weights = torch.zeros(6, 50)
    initial = float(((targets - psi @ weights.T) ** 2).sum(1).mean())
    for _ in range(300):
        batch = torch.randint(2000, (64,), generator=generator)
        sgd_step(weights, psi[batch], targets[batch], learning_rate, l2=1e-6)
    final = float(((targets - psi @ weights.T) ** 2).sum(1).mean())
    assert final < 0.5 * initial


@pytest.mark.parametrize("reads_are_free", [True, False])  # the CPU's path, and the GPU's (no host read of eta)
def test_sgd_step_is_equation_6(reads_are_free, monkeypatch):
    monkeypatch.setattr("cme_agent.dynamics.sgd.host_reads_are_free", lambda device: reads_are_free)
    psi = torch.tensor([[1.0, 2.0]])
    targets = torch.tensor([[3.0]])
    weights = torch.tensor([[0.5, -1.0]])
    sgd_step(weights, psi, targets, learning_rate=0.5, l2=0.1)
    eta = 0.5 / 5.0  # normalised by ||psi||^2
    expected = torch.tensor([[0.5, -1.0]]) * (1 - eta * 0.1) + eta * (3.0 - (0.5 - 2.0)) * psi
    assert torch.allclose(weights, expected)


@pytest.mark.parametrize("target_elements", [2**22, 50])  # one block of targets, or one minibatch per block
def test_sgd_update_is_consecutive_steps_of_equation_6(target_elements, monkeypatch):
    monkeypatch.setattr("cme_agent.dynamics.cme.TARGET_ELEMENTS", target_elements)
    """Building the targets and kernel operands of all minibatches at once does not change the steps."""
    dynamics = _dynamics(reward=None)
    data = _transitions(400)
    z = dynamics.encode(data.obs[:30], data.actions[:30])
    dynamics.grow(z, torch.full((30,), 0.5), torch.zeros(dynamics.weights.shape[0], 30))
    reference = dynamics.weights.clone()
    for step in range(0, 400, 20):
        part = data[step : step + 20]
        psi, targets = dynamics.regression_data(part)
        sgd_step(reference, psi, targets, 0.5, 1e-4)
    dynamics.sgd_update(data, batch_size=20, learning_rate=0.5, l2=1e-4)
    assert torch.allclose(dynamics.weights, reference, atol=1e-6)
    assert not torch.equal(reference, torch.zeros_like(reference))


def test_targets_feature_dynamics_and_absorbing_terminal_states():
    dynamics = _dynamics(feature_dynamics=True, reward=None)
    obs = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    next_obs = torch.tensor([[0.0, 1.0], [1.0, 0.0]])
    batch = Transitions(obs, torch.zeros(2, 1), torch.tensor([2.0, -1.0]), next_obs, torch.tensor([False, True]))
    targets = dynamics.targets(batch)
    phi, next_phi = dynamics.phi(obs), dynamics.phi(next_obs)
    assert torch.equal(targets[0, :3], next_phi[0] - phi[0])
    assert torch.equal(targets[1, :3], -phi[1])  # terminal: phi(s') = 0
    assert torch.equal(targets[:, 3], torch.tensor([2.0, -1.0]))


@pytest.mark.parametrize("feature_dynamics", [True, False])
def test_expected_reward_reads_the_termination_probability_off_the_constant_feature(feature_dynamics):
    bonus = 10.0
    dynamics = _dynamics(feature_dynamics, reward=RewardSpec(lambda obs, a: -a[:, 0], terminal_bonus=bonus))
    dynamics.grow(torch.zeros(2, 3), torch.ones(2), torch.zeros(3, 2))
    # constant row: E[1 - done] - 1 = -P(done) with feature dynamics, E[1 - done] without
    dynamics.weights[2] = torch.tensor([-0.25, 0.0]) if feature_dynamics else torch.tensor([0.75, 0.0])
    obs, actions = torch.zeros(1, 2), torch.full((1, 1), 0.5)
    psi = torch.tensor([[1.0, 0.0]])
    reward = dynamics.expected_reward(obs, actions, dynamics.phi(obs), psi)
    assert float(reward) == pytest.approx(-0.5 + bonus * 0.25)


def test_backup_weights_are_the_q_of_the_model():
    """<theta, (phi, psi)> + step reward = r(s, a) + gamma <w, E_model[phi(S')]>."""
    dynamics = _dynamics(True, reward=RewardSpec(lambda obs, a: -a[:, 0], terminal_bonus=2.0))
    generator = torch.Generator().manual_seed(1)
    dynamics.grow(torch.rand(5, 3, generator=generator), torch.ones(5), torch.randn(3, 5, generator=generator))
    data = _transitions(10)
    phi, psi = dynamics.phi(data.obs), dynamics.features(data.obs, data.actions)
    w, gamma = torch.randn(3, generator=generator), 0.9
    theta_phi, theta_psi = dynamics.backup_weights(w, gamma)
    q = dynamics.reward.step_reward(data.obs, data.actions) + phi @ theta_phi + psi @ theta_psi
    expected = dynamics.expected_reward(data.obs, data.actions, phi, psi) + gamma * dynamics.expected_next_phi(phi, psi) @ w
    assert torch.allclose(q, expected, atol=1e-5)
