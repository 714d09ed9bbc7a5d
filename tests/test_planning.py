"""Policy evaluation (eq. (7)) and Q smoothing."""

import pytest
import torch

from cme_agent.planning import bellman_residual_weights, smooth


def _finite_mdp(n_states=6, n_actions=2, seed=0):
    generator = torch.Generator().manual_seed(seed)
    transitions = torch.rand(n_states, n_actions, n_states, generator=generator) ** 3
    transitions /= transitions.sum(-1, keepdim=True)
    rewards = torch.randn(n_states, n_actions, generator=generator)
    policy = torch.randint(n_actions, (n_states,), generator=generator)
    return transitions.double(), rewards.double(), policy


@pytest.mark.parametrize("feature_dynamics", [True, False])
def test_evaluation_recovers_the_exact_value_of_a_finite_mdp(feature_dynamics):
    n_states, n_actions, gamma = 6, 2, 0.9
    transitions, rewards, policy = _finite_mdp(n_states, n_actions)
    states = torch.arange(n_states)
    p_pi = transitions[states, policy]
    r_pi = rewards[states, policy]
    exact = torch.linalg.solve(torch.eye(n_states, dtype=torch.float64) - gamma * p_pi, r_pi)

    # one-hot phi over states, one-hot psi over state-actions: the CME B psi is exact
    phi = torch.eye(n_states, dtype=torch.float64)
    weights = torch.zeros(n_states, n_states * n_actions, dtype=torch.float64)
    for s in range(n_states):
        for a in range(n_actions):
            weights[:, s * n_actions + a] = transitions[s, a] - (phi[s] if feature_dynamics else 0)
    psi = torch.nn.functional.one_hot(states * n_actions + policy, n_states * n_actions).double()
    next_phi = psi @ weights.T + (phi if feature_dynamics else 0)

    w = bellman_residual_weights(phi, next_phi, r_pi, gamma, l2=1e-12)
    assert torch.allclose(phi @ w, exact, atol=1e-6)


def test_evaluation_survives_a_singular_system():
    phi = torch.ones(10, 4)  # rank one
    w = bellman_residual_weights(phi, phi, torch.ones(10), 0.9, l2=1e-4)
    assert torch.isfinite(w).all()


def test_smoothing_zero_pads_the_previous_q():
    previous = torch.tensor([1.0, 2.0])
    estimate = torch.tensor([3.0, 4.0, 5.0, 6.0])
    smoothed = smooth(previous, estimate, omega=0.25)
    assert torch.allclose(smoothed, torch.tensor([0.75 + 0.75, 1.5 + 1.0, 1.25, 1.5]))
    assert torch.equal(smooth(previous, estimate, omega=1.0), estimate)


def test_smoothing_equals_smoothing_the_q_functions():
    """With psi grown by appending, smoothing the weights is smoothing Q pointwise."""
    generator = torch.Generator().manual_seed(0)
    psi_new = torch.rand(50, 7, generator=generator)
    psi_old = psi_new[:, :4]  # the old bank is a prefix of the new one
    previous, estimate = torch.randn(4, generator=generator), torch.randn(7, generator=generator)
    q_smoothed = psi_new @ smooth(previous, estimate, 0.3)
    assert torch.allclose(q_smoothed, 0.7 * psi_old @ previous + 0.3 * psi_new @ estimate, atol=1e-6)
