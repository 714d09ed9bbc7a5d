"""benchmarks/diagnostics/action_robustness.py: the acting rules on one trained Q (as trained,
noisy, refined), the episodes they run and the measurement of a briefly trained agent."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from benchmarks.diagnostics import action_robustness as ar
from benchmarks.diagnostics.gap_decomposition import Visited, simulate_all
from cme_agent import CMEPolicyIteration

pytest.importorskip("mujoco")


@pytest.fixture(scope="module")
def agent() -> CMEPolicyIteration:
    return CMEPolicyIteration("CMEPolicy", "InvertedPendulum-v5", seed=0, model_update={"kind": "cme"}).learn(300)


@pytest.fixture(scope="module")
def states(agent: CMEPolicyIteration) -> np.ndarray:
    return agent.store.get(slice(0, 50)).obs.numpy()


def test_the_plain_rule_is_the_agents_greedy_action(agent: CMEPolicyIteration, states: np.ndarray) -> None:
    rule = ar.ActingRule(agent)
    for obs in states[:10]:
        np.testing.assert_array_equal(rule(obs), agent.predict(obs, deterministic=True)[0])


def test_noise_moves_the_action_within_its_half_width_and_the_box(agent: CMEPolicyIteration, states: np.ndarray) -> None:
    plain, noisy = ar.ActingRule(agent), ar.ActingRule(agent, noise=0.2, seed=1)
    half_range = (agent.action_space.high - agent.action_space.low) / 2
    moves = []
    for obs in states:
        action = noisy(obs)
        assert agent.action_space.contains(action)
        moves.append(np.abs(action - plain(obs)) / half_range)
    moves = np.concatenate(moves)
    assert moves.max() <= 0.2 + 1e-6
    assert moves.mean() > 0.02  # not the greedy action in disguise


def test_the_refined_rule_raises_q_and_restores_the_agents_search(agent: CMEPolicyIteration, states: np.ndarray) -> None:
    trained = agent.policy.action_search
    refined = ar.ActingRule(agent, refine_steps=10)
    obs = torch.as_tensor(states)
    greedy_actions = torch.as_tensor(np.stack([ar.ActingRule(agent)(s) for s in states]))
    refined_actions = torch.as_tensor(np.stack([refined(s) for s in states]))
    assert agent.policy.action_search is trained and agent.policy.refine_steps == 0
    with torch.no_grad():
        q_greedy, q_refined = agent.policy.q_values(obs, greedy_actions), agent.policy.q_values(obs, refined_actions)
    assert bool((q_refined >= q_greedy - 1e-5).all())
    assert bool((q_refined > q_greedy + 1e-6).any())  # the refinement moved somewhere
    assert ar.refine_move(agent, states, 10) > 0


def test_a_discrete_action_space_is_refused() -> None:
    discrete = CMEPolicyIteration("CMEPolicy", "CartPole-v1", seed=0)
    with pytest.raises(ValueError, match="Box action space"):
        ar.ActingRule(discrete)


def test_measure_reports_every_mode(agent: CMEPolicyIteration) -> None:
    row = ar.measure(
        agent, "InvertedPendulum-v5", episodes=2, seed=0, watch=0, noise=(0.1,), refine_steps=3, offsets=(-0.3, 0.0)
    )
    assert list(row["modes"]) == ["agent", "noise 0.1", "refined"]
    for values in row["modes"].values():
        assert set(values) == set(ar.COLUMNS)
        assert values["length"] >= 1 and 0 <= values["return"] <= values["length"]  # IP: at most 1 per step
        assert values["max_abs_watched"] >= 0
    assert row["refine_move"] >= 0
    assert [pick["offset"] for pick in row["offsets"]] == [-0.3, 0.0]
    for pick in row["offsets"]:
        k = len(agent.policy.candidates)
        assert len(pick["model_q"]) == len(pick["exact_q"]) == k
        best = int(np.argmax(pick["model_q"]))
        assert pick["regret"] == pytest.approx(max(pick["exact_q"]) - pick["exact_q"][best])


def test_exact_q_from_the_centre_at_rest_follows_the_true_step(agent: CMEPolicyIteration) -> None:
    # from rest at the centre the pole stays up for a while under any force: Q^pi >= 1 (first reward) at every candidate
    (pick,) = ar.picks_at_offsets(agent, "InvertedPendulum-v5", (0.0,))
    assert min(pick["exact_q"]) >= 1.0
    assert pick["model_q"] == pytest.approx(agent.policy.candidate_q_values(torch.zeros(1, 4))[0].tolist(), abs=1e-5)
    assert ar.picks_at_offsets(agent, "InvertedPendulum-v5", ()) == []


def test_data_near_counts_the_stored_states_around_each_start(agent: CMEPolicyIteration) -> None:
    centre, far = ar.picks_at_offsets(agent, "InvertedPendulum-v5", (0.0, 0.9))
    stored = torch.cat([agent.store.get(slice(0, len(agent.store))).obs, agent.holdout.get(slice(0, len(agent.holdout))).obs])
    assert centre["data_near"] == pytest.approx(float((stored[:, 0].abs() <= ar.NEAR).double().mean()))
    assert centre["data_near"] > 0.5  # the episodes start within 0.01 of the centre
    assert far["data_near"] == 0.0
    assert far["phi_error"] > 0 and np.isfinite(far["phi_error"])


def test_one_step_errors_are_the_models_relative_error_per_candidate(agent: CMEPolicyIteration, states: np.ndarray) -> None:
    sim = gym.make("InvertedPendulum-v5").unwrapped
    sim.reset(seed=0)
    # stored observations of IP are (qpos, qvel), so each is its own simulator state
    chosen = states[:3].astype(np.float64)
    starts = Visited(chosen, chosen[:, :2], chosen[:, 2:], np.arange(3))
    candidates = agent.policy.candidates.numpy()
    steps = simulate_all(sim, starts, candidates)
    errors = ar.one_step_errors(agent, chosen, candidates, steps)
    dynamics = agent.dynamics
    for i in range(3):
        per_candidate = []
        for j in range(len(candidates)):
            s = torch.as_tensor(chosen[i : i + 1], dtype=torch.float32)
            a = torch.as_tensor(candidates[j : j + 1])
            with torch.no_grad():
                phi = dynamics.phi(s)
                predicted, _ = dynamics.read(phi, dynamics.features(s, a) @ dynamics.readout())
                true_next = dynamics.phi(torch.as_tensor(steps.obs[i, j : j + 1], dtype=torch.float32))
            true_next = true_next * (0.0 if steps.terminated[i, j] else 1.0)
            per_candidate.append(float((predicted - true_next).norm() / (true_next - phi).norm()))
        assert errors[i] == pytest.approx(np.mean(per_candidate), rel=1e-4)
