"""The loop of learn(): seeding, rewards, logging, bad data, device."""

import gymnasium as gym
import numpy as np
import pytest
import torch
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.logger import configure

from cme_agent import CMEPolicyIteration
from cme_agent.rewards import KNOWN_REWARDS


def test_same_seed_same_parameters_and_returns(pendulum_kwargs):
    results = []
    for _ in range(2):
        model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=3, **pendulum_kwargs)
        model.learn(300)
        env = gym.make("Pendulum-v1")
        env.reset(seed=7)
        returns, _ = evaluate_policy(model, env, n_eval_episodes=2, return_episode_rewards=True)
        results.append((model.policy.theta_psi.clone(), model.dynamics.weights.clone(), returns))
    assert torch.equal(results[0][0], results[1][0])
    assert torch.equal(results[0][1], results[1][1])
    assert results[0][2] == results[1][2]
    other = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=4, **pendulum_kwargs).learn(300)
    same_shape = other.dynamics.weights.shape == results[0][1].shape
    assert not same_shape or not torch.equal(other.dynamics.weights, results[0][1])  # another seed, another model


@pytest.mark.parametrize("env_id", sorted(KNOWN_REWARDS))
def test_known_rewards_match_the_env(env_id):
    """The shipped r(s, a) + terminal bonus * [s' terminal] equals the env's reward, and
    is_terminal(s') equals its termination flag, on random rollouts."""
    spec = KNOWN_REWARDS[env_id]
    try:
        env = gym.make(env_id)
    except gym.error.DependencyNotInstalled as missing:  # e.g. a MuJoCo id registered by benchmarks/
        pytest.skip(str(missing))
    obs, _ = env.reset(seed=0)
    env.action_space.seed(0)
    for _ in range(300):
        action = env.action_space.sample()
        next_obs, reward, terminated, truncated, _ = env.step(action)
        obs_t = torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0)
        action_t = torch.as_tensor(np.asarray(action)).reshape(1, -1) if np.ndim(action) else torch.tensor([int(action)])
        expected = float(spec.step_reward(obs_t, action_t)) + spec.terminal_bonus * terminated
        assert reward == pytest.approx(expected, abs=1e-4)
        if spec.is_terminal is not None:
            assert bool(spec.is_terminal(torch.as_tensor(next_obs).unsqueeze(0))) == terminated
        obs = next_obs if not (terminated or truncated) else env.reset()[0]


def test_unknown_reward_is_learned_and_said(capsys, pendulum_kwargs):
    from gymnasium.envs.classic_control import PendulumEnv

    env = gym.wrappers.TimeLimit(PendulumEnv(), 200)  # made without gym.make: no id, no known reward
    model = CMEPolicyIteration("CMEPolicy", env, seed=0, verbose=1, **pendulum_kwargs)
    assert model.reward_source == "learned" and model.dynamics.learn_reward
    model.learn(300)
    assert "reward is learned" in capsys.readouterr().out
    states = torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    psi = model.dynamics.features(states, torch.zeros(2, 1))
    learned = psi @ model.dynamics.reward_weights()[1]
    assert learned[0] > learned[1]  # upright beats hanging


def test_tensorboard_keys(tmp_path, pendulum_kwargs):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, tensorboard_log=str(tmp_path), **pendulum_kwargs)
    model.learn(400, tb_log_name="run")
    events = EventAccumulator(str(next(tmp_path.glob("run_*")))).Reload()
    keys = set(events.Tags()["scalars"])
    expected = {
        "rollout/ep_rew_mean",
        "time/fps",
        "train/model_loss",
        "train/n_features",
        "train/features_added",
        "train/bellman_residual",
        "train/q_mean",
        "time/data_acquisition",
        "time/feature_selection",
        "time/model_update",
        "time/policy_evaluation",
        "time/policy_improvement",
    }
    assert expected <= keys, expected - keys


def test_non_finite_observation_stops_learning(pendulum_kwargs):
    class BrokenPendulum(gym.Wrapper):
        def step(self, action):
            obs, reward, terminated, truncated, info = self.env.step(action)
            if self.env.unwrapped._elapsed == 50:
                obs = obs.copy()
                obs[2] = np.nan
            self.env.unwrapped._elapsed += 1
            return obs, reward, terminated, truncated, info

    env = gym.make("Pendulum-v1")
    env.unwrapped._elapsed = 0
    model = CMEPolicyIteration("CMEPolicy", BrokenPendulum(env), seed=0, **pendulum_kwargs)
    model.set_logger(configure(None, []))
    with pytest.raises(ValueError, match=r"non-finite observation at step 51"):
        model.learn(300)
    assert torch.isfinite(model.dynamics.weights).all()


def test_device_is_honoured(pendulum_kwargs):
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", device="cpu", **pendulum_kwargs)
    assert model.device.type == "cpu" and model.policy.device.type == "cpu"
    assert model.dynamics.weights.device.type == "cpu"


def test_feature_budget_caps_q(pendulum_kwargs):
    kwargs = {**pendulum_kwargs, "feature_selection": {"subsample_size": 300, "max_features": 20, "max_total_features": 30}}
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **kwargs)
    model.learn(500)
    assert model.q == 30
    assert model.dynamics.weights.shape[1] == model.policy.theta_psi.shape[0] == 30


def test_non_finite_reward_stops_learning(pendulum_kwargs):
    class InfiniteReward(gym.Wrapper):
        def step(self, action):
            obs, _, terminated, truncated, info = self.env.step(action)
            return obs, float("inf"), terminated, truncated, info

    model = CMEPolicyIteration("CMEPolicy", InfiniteReward(gym.make("Pendulum-v1")), seed=0, **pendulum_kwargs)
    model.set_logger(configure(None, []))
    with pytest.raises(ValueError, match=r"non-finite reward at step 1 \(env 0\): inf"):
        model.learn(100)
    assert len(model.store) + len(model.holdout) == 0


def test_diverging_model_update_is_undone_and_backed_off(pendulum_kwargs, monkeypatch):
    sgd = {**pendulum_kwargs["model_update"], "method": "sgd"}  # the guard of the SGD update
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **{**pendulum_kwargs, "model_update": sgd})
    model.set_logger(configure(None, []))
    model.learn(200)
    weights = model.dynamics.weights.clone()

    def explode(weights, psi, targets, learning_rate, l2):
        weights.mul_(1e30)

    monkeypatch.setattr("cme_agent.dynamics.cme.sgd_step", explode)
    with pytest.warns(RuntimeWarning, match="model update diverged"):
        model.model_update()
    assert torch.equal(model.dynamics.weights, weights)
    assert model.trainer.step_scale == 0.5
