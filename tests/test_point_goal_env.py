"""PointGoal2D-v0 (cme_agent/envs/point_goal.py): registered by ``import cme_agent``, a valid
Gymnasium env, seeded starts, the documented dynamics and reward, and 100-step episodes."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import cme_agent  # noqa: F401  (registers PointGoal2D-v0)
from cme_agent.envs.point_goal import PointGoal2D

ENV_ID = "PointGoal2D-v0"


@pytest.mark.filterwarnings("ignore:.*infinity")  # unbounded observations by design: the checker warns
def test_registered_env_passes_gymnasiums_checker() -> None:
    env = gym.make(ENV_ID)
    assert isinstance(env.unwrapped, PointGoal2D)
    check_env(env.unwrapped)
    assert env.observation_space == gym.spaces.Box(-np.inf, np.inf, (4,), np.float32)
    assert env.action_space == gym.spaces.Box(-1.0, 1.0, (2,), np.float32)


def test_reset_is_deterministic_for_a_seed_and_starts_at_rest_in_the_unit_square() -> None:
    first, _ = gym.make(ENV_ID).reset(seed=7)
    again, _ = gym.make(ENV_ID).reset(seed=7)
    other, _ = gym.make(ENV_ID).reset(seed=8)
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first, other)
    for obs in (first, other):
        assert obs.dtype == np.float32 and obs.shape == (4,)
        assert np.all(np.abs(obs[:2]) <= 1.0) and np.all(obs[2:] == 0.0)


def test_step_follows_the_documented_dynamics_and_reward() -> None:
    env = PointGoal2D(goal=(0.5, -0.25), dt=0.2, damping=0.8)
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(20):
        state = np.concatenate([rng.uniform(-2, 2, 2), rng.uniform(-1, 1, 2)])
        action = rng.uniform(-2.0, 2.0, 2)  # outside [-1, 1]^2 too: the env clips
        env.state = state.copy()
        obs, reward, terminated, truncated, info = env.step(action)
        force = np.clip(action, -1.0, 1.0)
        velocity = 0.8 * state[2:] + 0.2 * force
        position = state[:2] + 0.2 * velocity
        np.testing.assert_allclose(env.state, np.concatenate([position, velocity]), rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(obs, env.state.astype(np.float32))
        expected = -np.linalg.norm(position - np.array([0.5, -0.25])) - 0.05 * float(force @ force)
        assert reward == pytest.approx(expected, rel=1e-12, abs=1e-12)
        assert (terminated, truncated, info) == (False, False, {})


def test_reward_is_zero_at_the_goal_at_rest_and_negative_elsewhere() -> None:
    env = PointGoal2D()
    env.reset(seed=0)
    env.state = np.array([*env.goal, 0.0, 0.0])
    _, reward, *_ = env.step(np.zeros(2, dtype=np.float32))
    assert reward == 0.0
    _, reward, *_ = env.step(np.array([1.0, 0.0], dtype=np.float32))
    assert reward < 0.0


def test_transition_matches_step_and_leaves_the_state_alone() -> None:
    env = PointGoal2D()
    env.reset(seed=1)
    rng = np.random.default_rng(1)
    states = np.concatenate([rng.uniform(-2, 2, (10, 2)), rng.uniform(-1, 1, (10, 2))], axis=1)
    actions = rng.uniform(-1.5, 1.5, (10, 2))
    before = env.state.copy()
    successors, rewards = env.transition(states, actions)
    assert successors.shape == (10, 4) and rewards.shape == (10,)
    np.testing.assert_array_equal(env.state, before)
    for state, action, successor, reward in zip(states, actions, successors, rewards, strict=True):
        env.state = state.copy()
        _, step_reward, *_ = env.step(action)
        np.testing.assert_array_equal(env.state, successor)
        assert step_reward == reward


def test_episodes_are_truncated_after_100_steps_and_never_terminated() -> None:
    env = gym.make(ENV_ID)
    assert env.spec is not None and env.spec.max_episode_steps == 100
    env.reset(seed=0)
    ends = [env.step(env.action_space.sample())[2:4] for _ in range(100)]
    assert all(not terminated for terminated, _ in ends)
    assert [truncated for _, truncated in ends] == [False] * 99 + [True]


def test_the_env_itself_never_ends_an_episode() -> None:
    env = PointGoal2D()
    env.reset(seed=0)
    for _ in range(300):
        _, _, terminated, truncated, _ = env.step(np.ones(2, dtype=np.float32))
        assert not terminated and not truncated
