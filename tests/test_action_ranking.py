"""The measurements of benchmarks/action_ranking.py (no training): its metrics on Q arrays built by
hand, and its one-step Q of the simulator and of an untrained model on InvertedPendulum-v5."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from benchmarks.diagnostics import action_ranking
from cme_agent import CMEPolicyIteration


def test_metrics_of_an_exact_a_shrunk_and_a_reversed_model() -> None:
    true_q = np.random.default_rng(0).normal(size=(50, 7))
    exact = action_ranking.ranking_metrics(true_q, true_q)
    assert exact["r2"] == pytest.approx(1.0) and exact["centred_corr"] == pytest.approx(1.0)
    assert exact["best_agrees"] == 1.0 and exact["gap_rmse"] == pytest.approx(0.0, abs=1e-12)
    # half the gaps plus a per-state offset: ranks every state's actions right, gaps half as wide
    shrunk = action_ranking.ranking_metrics(true_q, 0.5 * true_q + np.arange(50.0)[:, None])
    assert shrunk["centred_corr"] == pytest.approx(1.0) and shrunk["best_agrees"] == 1.0
    assert shrunk["model_gap_std"] == pytest.approx(0.5 * shrunk["true_gap_std"])
    assert shrunk["r2"] < 0.0  # the offsets are errors of Q itself
    reversed_ = action_ranking.ranking_metrics(true_q, -true_q)
    assert reversed_["centred_corr"] == pytest.approx(-1.0) and reversed_["best_agrees"] == 0.0


def test_one_step_values_of_the_simulator_and_of_an_untrained_model() -> None:
    pytest.importorskip("mujoco")
    import gymnasium as gym

    agent = CMEPolicyIteration("CMEPolicy", "InvertedPendulum-v5", seed=0)
    agent.evaluator.value_weights = torch.linspace(-1.0, 1.0, agent.dynamics.p)
    env = gym.make("InvertedPendulum-v5")
    env.reset(seed=0)
    agent.dynamics.obs_encoder.fit(torch.randn(100, 4) * 0.1)  # the box the random phase would estimate
    states = action_ranking.visited_states(agent, env, n=4, noise=0.5, seed=1)
    actions = np.array([[-3.0], [0.0], [3.0]], dtype=np.float32)
    true_q, model_q = action_ranking.one_step_values(agent, env, states, actions)
    assert true_q.shape == model_q.shape == (4, 3)
    outcomes = []  # the backup, step by step: r, plus gamma <w, phi(s')> unless the step terminated
    for i, (qpos, qvel, _) in enumerate(states):
        for j, action in enumerate(actions):
            env.unwrapped.set_state(qpos, qvel)
            successor, reward, terminated, _, _ = env.step(action)
            value = float(
                agent.dynamics.phi(torch.as_tensor(successor[None], dtype=torch.float32)) @ agent.evaluator.value_weights
            )
            assert true_q[i, j] == pytest.approx(reward + (0.0 if terminated else agent.gamma * value), rel=1e-5, abs=1e-5)
            outcomes.append(terminated)
    assert any(outcomes) and not all(outcomes)  # both kinds of step were checked
    # q = 0: the model predicts no change and a learned reward of 0, whatever the action
    phi = agent.dynamics.phi(torch.as_tensor(np.asarray([s[2] for s in states]), dtype=torch.float32))
    expected = agent.gamma * (phi @ agent.evaluator.value_weights).numpy()
    np.testing.assert_allclose(model_q, np.repeat(expected[:, None], 3, axis=1), rtol=1e-5, atol=1e-5)
