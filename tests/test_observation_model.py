"""benchmarks/diagnostics/observation_model.py: the observation model's fits, the planner through
a model, and the measurement of a briefly trained agent."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from benchmarks.diagnostics import observation_model as om
from cme_agent import CMEPolicyIteration
from cme_agent.buffer import Transitions

pytest.importorskip("mujoco")


@pytest.fixture(scope="module")
def agent() -> CMEPolicyIteration:
    return CMEPolicyIteration("CMEPolicy", "InvertedPendulum-v5", seed=0).learn(300)


def synthetic(n: int, seed: int) -> Transitions:
    """A linear system in 4 dims with one action, terminated where |s'_1| > 0.15 (both sides), reward 1 - s'_0^2."""
    g = torch.Generator().manual_seed(seed)
    obs = 0.1 * torch.randn(n, 4, generator=g)
    actions = 2 * torch.rand(n, 1, generator=g) - 1
    change = obs @ torch.tensor([[0.0, 0.0, 0.1, 0.0], [0.0, 0.0, 0.0, 0.1], [0.0, 0.0, 0.0, 0.3], [0.0, 0.0, 0.0, 0.0]])
    next_obs = obs + change + actions * torch.tensor([0.0, 0.0, 0.05, -0.1]) + 0.01
    return Transitions(obs, actions, 1 - next_obs[:, 0].square(), next_obs, next_obs[:, 1].abs() > 0.15)


def test_the_observation_model_recovers_a_linear_system(agent: CMEPolicyIteration) -> None:
    model = om.ObservationModel(agent, synthetic(2000, 0))
    test = synthetic(500, 1)
    actions = test.actions.double()
    np.testing.assert_allclose(model.next_obs(test.obs, actions).numpy(), test.next_obs.double().numpy(), atol=1e-4)
    # the reward is quadratic in s': the ridge on [s', s'^2, 1, a, a^2] holds it
    rewards = model.reward_features(test.next_obs.double(), actions) @ model.reward
    np.testing.assert_allclose(rewards.numpy(), test.rewards.double().numpy(), atol=1e-3)
    scores = om.fit_scores(model, test)
    assert np.isnan(scores["change_r2"][:2]).all()  # s_0 and s_1 change by a constant: no R^2
    assert min(scores["change_r2"][2:]) > 0.999
    assert scores["termination_accuracy"] > 0.95  # a two-sided boundary: the quadratic features carry it


def test_a_two_sided_termination_needs_the_quadratic_features() -> None:
    data = synthetic(2000, 2)
    x = data.next_obs.double()
    linear = om.logistic(torch.cat([x, torch.ones(len(x), 1, dtype=x.dtype)], dim=1), data.terminated.double())
    both = om.logistic(om.quadratic(x / x.std(dim=0)), data.terminated.double())
    accuracy_linear = (
        ((torch.cat([x, torch.ones(len(x), 1, dtype=x.dtype)], 1) @ linear > 0) == data.terminated).double().mean()
    )
    accuracy_quadratic = ((om.quadratic(x / x.std(dim=0)) @ both > 0) == data.terminated).double().mean()
    assert accuracy_quadratic > 0.97 > accuracy_linear + 0.05


def test_the_planner_values_a_state_that_never_changes_at_its_discounted_reward(agent: CMEPolicyIteration) -> None:
    def standing_still(obs: torch.Tensor, candidates: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        phi = agent.dynamics.phi(obs)
        return phi[:, None].expand(-1, len(candidates), -1), torch.ones(len(obs), len(candidates))

    states = agent.store.get(slice(0, 200)).obs
    weights = om.plan(agent, standing_still, states, rounds=30)
    values = agent.dynamics.phi(states) @ weights
    expected = (1 - (1 - agent.omega) ** 30) / (1 - agent.gamma)  # V = 1 / (1 - gamma), smoothed over 30 rounds
    np.testing.assert_allclose(values.numpy(), expected, rtol=0.05)


def test_the_greedy_rule_takes_the_candidate_of_largest_reward(agent: CMEPolicyIteration) -> None:
    candidates = agent.policy.candidates

    def rewarding_the_last(obs: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        rewards = torch.arange(len(actions), dtype=torch.float32).expand(len(obs), -1)
        return torch.zeros(len(obs), len(actions), agent.dynamics.p), rewards

    act = om.greedy_rule(agent, rewarding_the_last, torch.zeros(agent.dynamics.p))
    np.testing.assert_array_equal(act(np.zeros(4, dtype=np.float32)), candidates[-1].numpy())


def test_the_cme_model_reads_the_agents_prediction(agent: CMEPolicyIteration) -> None:
    states, candidates = agent.store.get(slice(0, 5)).obs, agent.policy.candidates
    next_phi, rewards = om.CmeModel(agent)(states, candidates)
    assert next_phi.shape == (5, len(candidates), agent.dynamics.p) and rewards.shape == (5, len(candidates))
    dynamics = agent.dynamics
    with torch.no_grad():
        s, a = states[2:3], candidates[1:2]
        phi, psi = dynamics.phi(s), dynamics.features(s, a)
        predicted, _ = dynamics.read(phi, psi @ dynamics.readout())
        reward = dynamics.expected_reward(s, a, phi, psi)
    np.testing.assert_allclose(next_phi[2, 1].numpy(), predicted[0].numpy(), rtol=1e-5, atol=1e-6)
    assert float(rewards[2, 1]) == pytest.approx(float(reward[0]), abs=1e-5)


def test_measure_reports_every_mode(agent: CMEPolicyIteration) -> None:
    row = om.measure(agent, "InvertedPendulum-v5", seed=0, episodes=2, collection=200, rounds=3)
    assert list(row["returns"]) == list(om.MODES)
    assert all(0 <= value <= 1000 for value in row["returns"].values())
    assert len(row["change_r2"]) == 4
    assert min(row["change_r2"]) > 0.9  # InvertedPendulum's one step is close to linear in (s, a)
    assert 0.5 <= row["termination_accuracy"] <= 1
