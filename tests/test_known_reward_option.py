"""``model_update.known_reward``: learn a reward the agent knows, as if it were unknown."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import pytest
import torch

from cme_agent import CMEPolicyIteration
from cme_agent.config import ModelUpdateConfig
from cme_agent.rewards import KNOWN_REWARDS

SMALL = {"steps_per_iteration": 100, "evaluation": {"collection_size": 300}, "exploration": {"random_steps": 100}}


def _agent(**kwargs) -> CMEPolicyIteration:
    return CMEPolicyIteration("CMEPolicy", "CartPole-v1", seed=0, **SMALL, **kwargs)


def test_by_default_a_known_reward_is_planned_with():
    assert ModelUpdateConfig().known_reward is True
    agent = CMEPolicyIteration("CMEPolicy", "Acrobot-v1", seed=0, **SMALL)  # a preset without the key
    assert agent.reward_source == "known" and agent.dynamics.reward is KNOWN_REWARDS["Acrobot-v1"]
    assert not agent.dynamics.learn_reward


def test_false_learns_a_known_reward_and_true_keeps_it():
    assert _agent().reward_source == "known"
    agent = _agent(model_update={"known_reward": False})
    assert agent.reward_source == "learned" and agent.dynamics.learn_reward


def test_false_learns_it_on_psi_and_says_so(capsys):
    agent = _agent(model_update={"known_reward": False}, verbose=1)
    assert agent.reward_source == "learned" and agent.dynamics.learn_reward
    agent.learn(200)
    assert "is learned by regression on psi (model_update.known_reward=False)" in capsys.readouterr().out
    # CartPole pays +1 on every step: on the data the learned reward is about 1
    batch = agent.store.get(slice(0, len(agent.store)))
    dynamics = agent.dynamics
    with torch.no_grad():
        rewards = dynamics.expected_reward(
            batch.obs, batch.actions, dynamics.phi(batch.obs), dynamics.features(batch.obs, batch.actions)
        )
    assert float(rewards.mean()) == pytest.approx(1.0, abs=0.1)


def test_a_user_reward_still_wins():
    def reward(obs, action):
        return obs[:, 0] * 0.0 + 2.0

    agent = _agent(model_update={"known_reward": False}, reward_fn=reward)
    assert agent.reward_source == "user" and not agent.dynamics.learn_reward


def test_a_model_trained_with_a_user_reward_still_asks_for_it_on_load(tmp_path: Path):
    def reward(obs, action):
        return obs[:, 0] * 0.0 + 2.0

    _agent(model_update={"known_reward": False}, reward_fn=reward).save(tmp_path / "m")
    with pytest.raises(ValueError, match=r"pass reward_fn= to load\(\)"):
        CMEPolicyIteration.load(tmp_path / "m", env=gym.make("CartPole-v1"))


def test_it_survives_save_load(tmp_path: Path):
    agent = _agent(model_update={"known_reward": False})
    agent.learn(200)
    agent.save(tmp_path / "m")
    loaded = CMEPolicyIteration.load(tmp_path / "m", env=gym.make("CartPole-v1"))
    assert loaded.reward_source == "learned" and loaded.dynamics.learn_reward
    assert loaded.model_update_config.known_reward is False


def test_a_non_bool_is_refused():
    with pytest.raises(ValueError, match=r"model_update\.known_reward"):
        ModelUpdateConfig(known_reward="no")
