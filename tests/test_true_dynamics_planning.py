"""The measurements of benchmarks/true_dynamics_planning.py (no long training): PointGoal2D's batched
transition against its own steps, the Monte-Carlo value and the true-dynamics lookahead built by
hand, and the rows of a short run."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from benchmarks.diagnostics import true_dynamics_planning as tdp
from benchmarks.unseen_envs import CUSTOM_ENV
from cme_agent import CMEPolicyIteration
from cme_agent.envs.point_goal import PointGoal2D
from cme_agent.planning import bellman_residual_weights


def _states(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.concatenate([rng.uniform(-2, 2, (n, 2)), rng.uniform(-0.5, 0.5, (n, 2))], axis=1)


def test_transition_repeats_the_envs_step_bit_for_bit() -> None:
    rng = np.random.default_rng(0)
    states, actions = _states(rng, 50), rng.uniform(-1.5, 1.5, (50, 2))  # outside the box too: the env clips
    successors, rewards = PointGoal2D().transition(states, actions)
    env = PointGoal2D()
    for state, action, successor, reward in zip(states, actions, successors, rewards, strict=True):
        env.state = state.copy()
        _, step_reward, *_ = env.step(action)
        assert np.array_equal(env.state, successor) and step_reward == reward


def test_monte_carlo_value_of_standing_still(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(tdp, "greedy_actions", lambda agent, states: np.zeros((len(states), 2)))
    states = np.array([[0.6, -0.4, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [-1.0, 1.0, 0.0, 0.0]])
    gamma, horizon = 0.9, 20
    values = tdp.monte_carlo_values(SimpleNamespace(gamma=gamma), states, horizon)
    distances = np.linalg.norm(states[:, :2] - PointGoal2D().goal, axis=1)  # at rest: the point stays put
    np.testing.assert_allclose(values, -distances * (1 - gamma**horizon) / (1 - gamma), rtol=1e-12, atol=1e-12)
    assert values[0] == 0.0


@pytest.mark.parametrize("scale", [0.0, 1.0])
def test_lookahead_is_the_one_step_backup_through_the_env(scale: float) -> None:
    agent = CMEPolicyIteration("CMEPolicy", CUSTOM_ENV, seed=0)
    agent.dynamics.obs_encoder.fit(torch.randn(200, 4))  # the box the random phase would estimate
    weights = scale * torch.randn(agent.dynamics.p, generator=torch.Generator().manual_seed(1))
    states = _states(np.random.default_rng(2), 8)
    chosen, _ = tdp.Lookahead(agent, weights).predict(states.astype(np.float32))
    env, candidates = PointGoal2D(), agent.policy.candidates.numpy()
    for state, action in zip(states.astype(np.float32), chosen, strict=True):
        scores = []
        for candidate in candidates:
            env.state = state.astype(np.float64)
            successor, reward, *_ = env.step(candidate)
            scores.append(reward + agent.gamma * float(tdp.phi_of(agent, successor[None].astype(np.float64)) @ weights))
        np.testing.assert_array_equal(action, candidates[int(np.argmax(scores))])
    if scale == 0.0:  # w = 0: the best immediate reward, where one step barely moves the point: no force
        assert not chosen.any()
    else:  # not one action everywhere: the check above compared real choices
        assert len({tuple(a) for a in chosen}) > 1


def test_true_policy_iteration_evaluates_each_rounds_lookahead_policy() -> None:
    agent = CMEPolicyIteration("CMEPolicy", CUSTOM_ENV, seed=0)
    agent.dynamics.obs_encoder.fit(torch.randn(200, 4))
    states = _states(np.random.default_rng(3), 40)
    phi = tdp.phi_of(agent, states)
    weights = torch.randn(agent.dynamics.p, generator=torch.Generator().manual_seed(4))
    assert torch.equal(tdp.true_policy_iteration(agent, states, phi, weights, 0), weights)
    expected = weights
    for _ in range(2):  # by hand: the lookahead's actions, their true transitions, eq. (7)
        actions, _ = tdp.Lookahead(agent, expected).predict(states)
        successors, rewards = PointGoal2D().transition(states, actions.astype(np.float64))
        expected = bellman_residual_weights(
            phi,
            tdp.phi_of(agent, successors),
            torch.as_tensor(rewards, dtype=torch.float32),
            agent.gamma,
            agent.evaluation_config.l2,
        )
    torch.testing.assert_close(tdp.true_policy_iteration(agent, states, phi, weights, 2), expected)


def test_rows_of_a_short_run() -> None:
    kwargs = {
        "steps_per_iteration": 100,
        "exploration": {"random_steps": 100},
        "evaluation": {"collection_size": 300, "rounds": 2},
        "feature_selection": {"subsample_size": 300, "max_features": 20},
    }
    row = tdp.run_seed((0, 300, kwargs, 2))
    assert row["seed"] == 0 and row["C"] == 300 and 0 < row["q"]
    for key in tdp.METRICS:
        assert math.isfinite(row[key])
    for key in ("return_agent", "return_lookahead_model_w", "return_lookahead_true_w"):
        assert -1000.0 < row[key] <= 0.0  # 100 steps of rewards in (-10, 0]
    assert row["r2_model_w"] <= 1.0 and row["r2_true_w"] <= 1.0
    for part in ("uniform", "data"):
        assert row[f"phi_error_{part}"] >= 0.0 and row[f"reward_rmse_{part}"] >= 0.0
