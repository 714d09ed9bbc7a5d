"""predict(): shapes for single and batched observations, and SB3's evaluation helper."""

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.evaluation import evaluate_policy

from cme_agent import CMEPolicyIteration


@pytest.fixture(scope="module")
def pendulum_model():
    from tests.conftest import small_kwargs

    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **small_kwargs())
    model.learn(300)
    return model


def test_predict_shapes_box(pendulum_model):
    obs = gym.make("Pendulum-v1").reset(seed=1)[0]
    action, state = pendulum_model.predict(obs, deterministic=True)
    assert action.shape == (1,) and state is None
    assert -2.0 <= float(action[0]) <= 2.0
    batch = np.stack([obs] * 5)
    actions, _ = pendulum_model.predict(batch, deterministic=True)
    assert actions.shape == (5, 1)
    assert np.allclose(actions, action)


def test_predict_shapes_discrete(cartpole_kwargs):
    model = CMEPolicyIteration("CMEPolicy", "CartPole-v1", seed=0, **cartpole_kwargs)
    model.learn(200)
    obs = gym.make("CartPole-v1").reset(seed=0)[0]
    action, _ = model.predict(obs)
    assert action.shape == () and int(action) in (0, 1)
    actions, _ = model.predict(np.stack([obs] * 3))
    assert actions.shape == (3,)


def test_evaluate_policy_runs(pendulum_model):
    mean, std = evaluate_policy(pendulum_model, pendulum_model.get_env(), n_eval_episodes=2)
    assert np.isfinite(mean) and np.isfinite(std)
