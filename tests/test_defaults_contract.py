"""The SB3 contract with library defaults (no phi or observation settings, only small budgets):
learn() on a VecEnv of 3, callbacks, save/load, evaluate_policy; on CartPole-v1 (its preset is
what a user gets) and on a 6-dim env with infinite observation bounds, whose box is estimated
from data. A custom env's own reward function is found through a SubprocVecEnv."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium import spaces
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import SubprocVecEnv, VecEnv

from cme_agent import CMEPolicyIteration
from tests.conftest import CountingCallback

N_ENVS = 3

SMALL_BUDGETS: dict[str, Any] = {
    "steps_per_iteration": 100,
    "evaluation": {"collection_size": 500, "rounds": 1},
    "feature_selection": {"subsample_size": 300, "max_features": 20},
    "model_update": {"n_steps": 20, "batch_size": 64, "holdout_size": 100},
    "exploration": {"random_steps": 100},
}
"""Sizes only, so that each test takes seconds: no phi, observation or reward settings."""


class PointMass3D(gym.Env):
    """A 3-D point mass pushed towards the origin: observation (position, velocity), unbounded;
    action a force in [-1, 1]^3; reward -|x|^2 - 0.01 |a|^2, known only to the env (it has no
    ``reward_function``). Episodes are truncated after 50 steps.
    """

    observation_space = spaces.Box(-np.inf, np.inf, (6,), np.float32)
    action_space = spaces.Box(-1.0, 1.0, (3,), np.float32)
    dt = 0.1
    horizon = 50

    def __init__(self) -> None:
        self.state = np.zeros(6, dtype=np.float32)
        self.steps = 0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self.state = np.concatenate([self.np_random.uniform(-1, 1, 3), np.zeros(3)]).astype(np.float32)
        self.steps = 0
        return self.state.copy(), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        force = np.clip(np.asarray(action, dtype=np.float32), -1.0, 1.0)
        position, velocity = self.state[:3], self.state[3:]
        reward = -float(position @ position) - 0.01 * float(force @ force)
        velocity = velocity + self.dt * force
        self.state = np.concatenate([position + self.dt * velocity, velocity]).astype(np.float32)
        self.steps += 1
        return self.state.copy(), reward, False, self.steps >= self.horizon, {}


class PointMass3DWithReward(PointMass3D):
    """The same env, telling the agent its reward (``reward_function``, torch ops)."""

    def reward_function(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        force = action.clamp(-1.0, 1.0)
        return -(obs[:, :3] ** 2).sum(dim=1) - 0.01 * (force**2).sum(dim=1)


ENVS: dict[str, Callable[[], VecEnv]] = {
    "CartPole-v1": lambda: make_vec_env("CartPole-v1", n_envs=N_ENVS, seed=0),
    "PointMass3D": lambda: make_vec_env(PointMass3D, n_envs=N_ENVS, seed=0),
}


def _probe_observations(env: VecEnv, n_steps: int = 20) -> np.ndarray:
    """Observations of a short random rollout of ``env``, (n_steps * n_envs, obs_dim)."""
    env.action_space.seed(1)
    observations = [env.reset()]
    for _ in range(n_steps - 1):
        observations.append(env.step(np.stack([env.action_space.sample() for _ in range(env.num_envs)]))[0])
    return np.concatenate(observations)


@pytest.mark.parametrize("env_name", list(ENVS))
def test_learn_with_a_vec_env_of_three_counts_one_callback_call_per_vector_step(env_name: str) -> None:
    model = CMEPolicyIteration("CMEPolicy", ENVS[env_name](), seed=0, **SMALL_BUDGETS)
    callback = CountingCallback()
    model.learn(300, callback=callback)
    assert model.num_timesteps == 300
    assert callback.calls == 300 // N_ENVS  # one call per vector step
    assert len(model.store) + len(model.holdout) == 300
    assert model.iteration == 3
    assert model.q > 0
    assert not model.dynamics.obs_encoder.needs_fit


@pytest.mark.parametrize("env_name", list(ENVS))
def test_a_callback_returning_false_stops_learning(env_name: str) -> None:
    model = CMEPolicyIteration("CMEPolicy", ENVS[env_name](), seed=0, **SMALL_BUDGETS)
    callback = CountingCallback(stop_after=40)  # in the second iteration (34 vector steps each)
    model.learn(3000, callback=callback)
    assert callback.calls == 40
    assert model.num_timesteps == 40 * N_ENVS
    assert model.iteration == 1


@pytest.mark.parametrize("env_name", list(ENVS))
def test_save_load_keeps_predictions_and_evaluate_policy_runs(env_name: str, tmp_path: Path) -> None:
    env = ENVS[env_name]()
    model = CMEPolicyIteration("CMEPolicy", env, seed=0, **SMALL_BUDGETS)
    model.learn(200)
    model.save(tmp_path / "model.zip")
    loaded = CMEPolicyIteration.load(tmp_path / "model.zip")

    encoder, loaded_encoder = model.dynamics.obs_encoder, loaded.dynamics.obs_encoder
    assert not loaded_encoder.needs_fit
    assert torch.equal(loaded_encoder.center, encoder.center)
    assert torch.equal(loaded_encoder.half_range, encoder.half_range)
    if env_name == "PointMass3D":  # infinite bounds: the box was estimated, a finite one
        assert encoder.fit_dims == list(range(6))
        assert torch.isfinite(encoder.half_range).all() and bool((encoder.half_range > 0).all())

    observations = _probe_observations(ENVS[env_name]())
    actions, _ = model.predict(observations, deterministic=True)
    loaded_actions, _ = loaded.predict(observations, deterministic=True)
    np.testing.assert_array_equal(loaded_actions, actions)
    assert actions.shape == (len(observations), *env.action_space.shape)
    assert env.action_space.contains(actions[0])

    mean_return, std_return = evaluate_policy(loaded, ENVS[env_name](), n_eval_episodes=3)
    assert np.isfinite(mean_return) and np.isfinite(std_return)

    resumed = CMEPolicyIteration.load(tmp_path / "model.zip", env=ENVS[env_name]())
    resumed.learn(100, reset_num_timesteps=False)  # a loaded model goes on learning
    assert resumed.iteration == model.iteration + 1
    assert 0 <= resumed.num_timesteps - (model.num_timesteps + 100) < N_ENVS  # whole vector steps


def test_set_env_on_a_model_loaded_without_env(tmp_path: Path) -> None:
    model = CMEPolicyIteration("CMEPolicy", ENVS["PointMass3D"](), seed=0, **SMALL_BUDGETS)
    model.learn(100)
    model.save(tmp_path / "model.zip")
    loaded = CMEPolicyIteration.load(tmp_path / "model.zip")
    loaded.set_env(ENVS["PointMass3D"]())
    loaded.learn(100, reset_num_timesteps=False)
    assert loaded.iteration == model.iteration + 1


def _env_with_reward() -> gym.Env:
    return PointMass3DWithReward()


def _env_without_reward() -> gym.Env:
    return PointMass3D()


@pytest.mark.parametrize(("make_env", "source"), [(_env_with_reward, "env"), (_env_without_reward, "learned")])
def test_the_reward_function_of_a_custom_env_is_found_through_a_subproc_vec_env(
    make_env: Callable[[], gym.Env], source: str
) -> None:
    env = SubprocVecEnv([make_env, make_env], start_method="fork")
    try:
        model = CMEPolicyIteration("CMEPolicy", env, seed=0, **SMALL_BUDGETS)
        assert model.reward_source == source
        assert model.dynamics.learn_reward == (source == "learned")
        if source == "env":  # the planner's reward is the env's own function
            obs, action = torch.tensor([[1.0, 2.0, 0.0, 5.0, 5.0, 5.0]]), torch.tensor([[1.0, 0.0, 0.0]])
            assert model.dynamics.reward.step_reward(obs, action).tolist() == pytest.approx([-5.01])
        model.learn(200)
        assert model.num_timesteps == 200 and model.q > 0
    finally:
        env.close()
