"""The pure pieces of benchmarks/diagnostics/gap_decomposition.py (no training): R^2 and the best fit
on phi, the fine action search on a known quadratic, the ranking and attribution figures on
synthetic numbers, and the MuJoCo pieces: the state round trip, Monte-Carlo values, the exact
Q^pi and the episode loop against SB3's evaluation."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch

from benchmarks.diagnostics import gap_decomposition as gd
from benchmarks.diagnostics.true_dynamics_planning import r_squared

pytest.importorskip("mujoco")

MUJOCO_ENVS = ("InvertedDoublePendulum-v5", "Reacher-v5")


def _constant_agent(action: np.ndarray, gamma: float) -> Any:
    """An agent stand-in whose policy is one fixed action, with SB3's batched ``predict``."""
    return SimpleNamespace(gamma=gamma, predict=lambda obs, deterministic=True: (np.tile(action, (len(obs), 1)), None))


def _random_walk(env_id: str, steps: int, seed: int) -> tuple[gd.Visited, np.ndarray, list[tuple[Any, ...]]]:
    """States of a random-action run with their simulator states, its actions and what each step returned."""
    env = gym.make(env_id)
    obs, _ = env.reset(seed=seed)
    rows, actions, results = [], [], []
    for _ in range(steps):
        data = env.unwrapped.data
        rows.append((obs.copy(), data.qpos.copy(), data.qvel.copy()))
        action = env.action_space.sample()
        obs, reward, terminated, _, _ = env.step(action)
        actions.append(action)
        results.append((obs.copy(), reward, terminated))
        if terminated:
            obs, _ = env.reset()
    obs_rows, qpos, qvel = (np.array(column) for column in zip(*rows, strict=True))
    return gd.Visited(obs_rows, qpos, qvel, np.zeros(len(rows), dtype=int)), np.array(actions), results


def test_r_squared_of_perfect_mean_and_known_predictions() -> None:
    phi = torch.eye(4)
    targets = np.array([1.0, 2.0, 3.0, 4.0])
    assert r_squared(torch.tensor([1.0, 2.0, 3.0, 4.0]), phi, targets) == pytest.approx(1.0)
    assert r_squared(torch.full((4,), 2.5), phi, targets) == pytest.approx(0.0)
    # residuals (1, 0, 0, -1): 1 - 0.5 / 1.25
    assert r_squared(torch.tensor([2.0, 2.0, 3.0, 3.0]), phi, targets) == pytest.approx(0.6)


def test_best_phi_fit_reaches_one_on_a_linear_target_and_not_on_noise() -> None:
    rng = np.random.default_rng(0)
    phi = torch.as_tensor(rng.normal(size=(400, 20)), dtype=torch.float32)
    train = np.arange(400) % 2 == 0
    linear = phi.double().numpy() @ rng.normal(size=20)
    held_out, fitted = gd.best_phi_fit(phi, linear, train)
    assert held_out > 0.999 and fitted > 0.999
    held_out, fitted = gd.best_phi_fit(phi, rng.normal(size=400), train)
    assert held_out < 0.1 and fitted > held_out  # noise: some fitted on the training half, nothing carried over


@pytest.mark.parametrize("dims", [1, 2])
def test_fine_grid_finds_the_top_of_a_quadratic(dims: int) -> None:
    rng = np.random.default_rng(dims)
    low, high = -np.ones(dims), np.ones(dims)
    fine = gd.fine_actions(low, high, rng, gd.FINE_GRID, gd.FINE_SAMPLES)
    assert fine.shape == (gd.FINE_GRID[dims] ** dims, dims)
    tops = rng.uniform(-1, 1, size=(50, dims))  # the best action of each of 50 states
    q = -((fine[None] - tops[:, None]) ** 2).sum(axis=2)  # (50, F)
    best = fine[q.argmax(axis=1)]
    half_step = 1.0 / (gd.FINE_GRID[dims] - 1)  # the grid's step is 2 / (n - 1)
    assert np.abs(best - tops).max() <= half_step + 1e-12


def test_fine_actions_sample_the_box_above_two_dims() -> None:
    low, high = np.array([-1.0, 0.0, -2.0]), np.array([1.0, 0.5, 2.0])
    fine = gd.fine_actions(low, high, np.random.default_rng(0), gd.FINE_GRID, 300)
    assert fine.shape == (300, 3) and (fine >= low).all() and (fine <= high).all()


def test_action_set_metrics_on_a_quadratic_with_three_candidates() -> None:
    fine = np.linspace(-1, 1, 41)[:, None]
    candidates = np.array([[-1.0], [0.0], [1.0]])
    actions = np.concatenate([fine, candidates])
    tops = np.array([0.5, 1.0])  # best actions: between two candidates, and on one
    q = -((actions[None, :, 0] - tops[:, None]) ** 2)
    chosen = np.array([-0.25, -0.0])  # pi(s): 0 at the first state (Q = -0.25), 1 at the second
    metrics = gd.action_set_metrics(q[:, -3:], q, chosen, actions[q.argmax(axis=1)], value_spread=0.5)
    assert metrics["gap_fine"] == pytest.approx(0.125)  # (0.25 + 0) / 2
    assert metrics["gap_fine_rel"] == pytest.approx(0.25)
    assert metrics["regret_chosen"] == pytest.approx(0.0)  # pi(s) is the best candidate at both
    assert metrics["chosen_near_best"] == pytest.approx(0.5)  # only at the second state
    assert metrics["fine_best_abs"] == pytest.approx(0.75)


def test_ranking_metrics_count_agreement_and_regret() -> None:
    exact = np.array([[1.0, 3.0, 2.0], [5.0, 4.0, 0.0]])
    metrics = gd.ranking_metrics(exact, {"a": np.array([1, 0]), "b": np.array([2, 2])})
    assert metrics == {
        "exact_regret_a": 0.0,
        "exact_agrees_a": 1.0,
        "exact_regret_b": pytest.approx(3.0),  # (1 + 5) / 2
        "exact_agrees_b": 0.0,
    }


def test_phi_ranks_count_the_directions_the_states_use() -> None:
    rng = np.random.default_rng(0)
    basis = rng.normal(size=(3, 50))  # 200 states whose features span 3 of 50 directions
    phi = torch.as_tensor(rng.normal(size=(200, 3)) @ basis, dtype=torch.float32)
    assert gd.phi_ranks(phi) == {"phi_rank_99": 3, "phi_rank_999": 3}
    assert gd.phi_ranks(torch.as_tensor(rng.normal(size=(200, 50)), dtype=torch.float32))["phi_rank_99"] > 40


def test_attribution_splits_the_returns_and_names_the_largest_part() -> None:
    returns = {
        "agent": 100.0,
        "lookahead_model_w": 80.0,
        "lookahead_true_w": 300.0,
        "lookahead_true_w_fine": 350.0,
        "lookahead_exact": 900.0,
        "lookahead_exact_fine": 850.0,
    }
    parts = gd.attribution(returns, reference=1000.0)
    assert [name for name, _ in parts] == [*(name for name, _, _ in gd.PARTS), gd.REST]
    assert [gain for _, gain in parts] == [-20.0, 220.0, 50.0, 600.0, -50.0, 100.0]  # the rest from the best, 900
    assert gd.largest_part(parts[: len(gd.PARTS)]) == ("value representation (phi, eq. (7) on C)", 600.0)
    assert len(gd.attribution(returns, reference=None)) == len(gd.PARTS)


def test_obs_decoding_error_of_the_true_features_is_the_decoders_floor() -> None:
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(200, 3))
    next_obs = obs + 0.1 * rng.normal(size=(200, 3))
    phi_next = torch.as_tensor(np.concatenate([next_obs, np.ones((200, 1))], axis=1), dtype=torch.float32)
    train = np.arange(200) % 2 == 0
    model, floor = gd.obs_decoding_errors(phi_next, phi_next, obs, next_obs, train, ~train)
    assert model == floor and floor < 1e-3  # linear features: the decoder is exact
    stale = torch.as_tensor(np.concatenate([obs, np.ones((200, 1))], axis=1), dtype=torch.float32)  # predicts no change
    model, _ = gd.obs_decoding_errors(phi_next, stale, obs, next_obs, train, ~train)
    assert model == pytest.approx(1.0, abs=1e-3)


@pytest.mark.parametrize("env_id", MUJOCO_ENVS)
def test_state_round_trip_gives_the_recorded_step(env_id: str) -> None:
    states, actions, results = _random_walk(env_id, 60, seed=3)
    steps = gd.simulate(gym.make(env_id).unwrapped, states.qpos, states.qvel, actions)
    for i, (next_obs, reward, terminated) in enumerate(results):
        np.testing.assert_allclose(steps.obs[i], next_obs, rtol=0, atol=1e-9)
        assert steps.rewards[i] == pytest.approx(reward, abs=1e-9) and steps.terminated[i] == terminated
    grid = gd.simulate_all(gym.make(env_id).unwrapped, states.subset(np.arange(5)), actions[:3])
    assert grid.obs.shape == (5, 3, len(next_obs))
    np.testing.assert_allclose(grid.obs[2, 2], steps.obs[2], atol=1e-9)  # state 2 with its own action


@pytest.mark.parametrize("env_id", MUJOCO_ENVS)
def test_monte_carlo_value_and_exact_q_agree_with_a_hand_rollout(env_id: str) -> None:
    gamma, horizon = 0.9, 30  # the pendulum falls within the horizon (a terminal step ends the sum); the arm never ends
    states, _, _ = _random_walk(env_id, 5, seed=1)
    action = np.full(gym.make(env_id).action_space.shape, 0.3, dtype=np.float32)
    agent, sim = _constant_agent(action, gamma), gym.make(env_id).unwrapped
    values = gd.monte_carlo_values(agent, sim, states, horizon)
    for i in range(len(states.obs)):
        env = gym.make(env_id).unwrapped
        env.reset(seed=0)
        env.set_state(states.qpos[i], states.qvel[i])
        expected, discount = 0.0, 1.0
        for _ in range(horizon):
            _, reward, terminated, _, _ = env.step(action)
            expected += discount * reward
            discount *= gamma
            if terminated:
                break
        assert values[i] == pytest.approx(expected, rel=1e-9)
    # Q^pi at pi's own action is V^pi: one true step, then H - 1 steps of pi
    steps = gd.simulate(sim, states.qpos, states.qvel, np.tile(action, (len(states.obs), 1)))
    np.testing.assert_allclose(gd.exact_q(agent, sim, steps, horizon), values, rtol=1e-9)


def test_episode_loop_matches_sb3_evaluation_and_ends_falls_below_the_height() -> None:
    from stable_baselines3.common.env_util import make_vec_env

    from benchmarks.unseen_envs import ZeroAgent, evaluate

    env_id, seed = "InvertedDoublePendulum-v5", 10_003
    agent = ZeroAgent(gym.make(env_id).action_space)
    episodes = gd.run_episodes(lambda obs, env: agent.predict(obs[None])[0][0], env_id, seed, 4)
    reference = evaluate(agent, make_vec_env(env_id, n_envs=1, seed=seed), 4)
    assert np.mean([e["return"] for e in episodes]) == pytest.approx(reference["return_mean"], rel=1e-6)
    assert all(e["terminated"] and e["tip_y"] <= 1.0 for e in episodes)  # doing nothing: the poles fall
    summary = gd.ending_summary(episodes)
    assert summary["terminated"] == 1.0 and summary["fall_tip_y"] <= 1.0 and "final_distance" not in summary
    cut = gd.run_episodes(lambda obs, env: agent.predict(obs[None])[0][0], env_id, seed, 4, max_steps=3)
    assert [e["length"] for e in cut] == [3] * 4 and not any(e["terminated"] for e in cut)
