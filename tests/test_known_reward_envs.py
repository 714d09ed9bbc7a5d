"""benchmarks/known_reward_envs.py: the reward given to the agent under the diagnostic ids is
the env's own, step by step, and the agent plans with it."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from benchmarks import known_reward_envs
from cme_agent import CMEPolicyIteration
from cme_agent.rewards import KNOWN_REWARDS


def _rewards_along_a_random_episode(env_id: str, steps: int) -> tuple[list[float], list[float], list[bool], list[bool]]:
    """The env's rewards and terminations, and the spec's, along ``steps`` random actions."""
    spec = KNOWN_REWARDS[env_id]
    env = gym.make(env_id)
    obs, _ = env.reset(seed=3)
    actions = np.random.default_rng(3).uniform(env.action_space.low, env.action_space.high, (steps, *env.action_space.shape))
    given, true, given_end, true_end = [], [], [], []
    for action in actions:
        s, a = torch.as_tensor(obs, dtype=torch.float64)[None], torch.as_tensor(action, dtype=torch.float64)[None]
        obs, reward, terminated, truncated, _ = env.step(action.astype(np.float32))
        ended = bool(spec.is_terminal(torch.as_tensor(obs, dtype=torch.float64)[None])) if spec.is_terminal else False
        given.append(float(spec.step_reward(s, a)) + spec.terminal_bonus * ended)
        true.append(float(reward))
        given_end.append(ended)
        true_end.append(terminated)
        if terminated or truncated:
            break
    return given, true, given_end, true_end


def test_the_point_goal_reward_is_the_envs() -> None:
    given, true, given_end, true_end = _rewards_along_a_random_episode(known_reward_envs.POINT_GOAL, 100)
    assert len(true) == 100 and not any(true_end) and not any(given_end)
    np.testing.assert_allclose(given, true, rtol=1e-5, atol=1e-5)  # the env's float32 observations


def test_the_inverted_pendulum_reward_and_termination_are_the_envs() -> None:
    pytest.importorskip("mujoco")
    given, true, given_end, true_end = _rewards_along_a_random_episode(known_reward_envs.INVERTED_PENDULUM, 1000)
    assert true_end[-1] and given_end == true_end  # random torques drop the pole
    assert given == true and true[-1] == 0.0 and set(true[:-1]) == {1.0}


def test_the_agent_plans_with_the_given_reward() -> None:
    agent = CMEPolicyIteration("CMEPolicy", known_reward_envs.POINT_GOAL, seed=0)
    assert agent.reward_source == "known" and agent.dynamics.reward is KNOWN_REWARDS[known_reward_envs.POINT_GOAL]
