"""benchmarks/diagnostics/observation_model.py: the planner through a model, the CME model's
reading, the observation model as the planner sees it, and the measurement of a briefly trained agent."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import linear_system

from benchmarks.diagnostics import observation_model as om
from cme_agent import CMEPolicyIteration

pytest.importorskip("mujoco")


@pytest.fixture(scope="module")
def agent() -> CMEPolicyIteration:
    return CMEPolicyIteration("CMEPolicy", "InvertedPendulum-v5", seed=0).learn(300)


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


def test_the_planners_view_of_the_observation_model_weighs_phi_by_going_on(agent: CMEPolicyIteration) -> None:
    data = agent.store.get(slice(0, len(agent.store)))
    model = om.fitted(agent, data)
    states, candidates = data.obs[:4], agent.policy.candidates
    next_phi, rewards = om.as_model(agent, model.step)(states, candidates)
    next_obs, going_on, expected = model.step(states, candidates)
    assert next_phi.shape == (4, len(candidates), agent.dynamics.p)
    torch.testing.assert_close(next_phi[1, 2], agent.dynamics.phi(next_obs[1 * len(candidates) + 2][None])[0] * going_on[5])
    torch.testing.assert_close(rewards.reshape(-1), expected)


def test_fit_scores_give_each_dims_r2_and_the_termination_accuracy(agent: CMEPolicyIteration) -> None:
    scores = om.fit_scores(om.fitted(agent, linear_system(2000, 0)), linear_system(500, 1))
    assert np.isnan(scores["change_r2"][:2]).all()  # s_0 and s_1 change by a constant: no R^2
    assert min(scores["change_r2"][2:]) > 0.999
    assert scores["termination_accuracy"] > 0.95
