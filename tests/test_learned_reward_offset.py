"""What a learned reward predicts off the data: psi's kernels fade away from the visited
state-actions, so its reward row predicts its own offset there, the least of 0 and the first
batch's non-terminal rewards, while on the data it fits r."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium import spaces

from cme_agent import CMEPolicyIteration
from cme_agent.buffer import Transitions
from cme_agent.dynamics import CMEDynamics

OBS_SPACE = spaces.Box(np.full(2, -4.0, np.float32), np.full(2, 4.0, np.float32), dtype=np.float32)
ACTION_SPACE = spaces.Box(-np.ones(1, np.float32), np.ones(1, np.float32), dtype=np.float32)


def _costs(n: int, seed: int) -> Transitions:
    """Transitions in the box's centre [-1, 1]^2 with a cost (negative reward) of the state, (N,)."""
    generator = torch.Generator().manual_seed(seed)
    obs = torch.rand(n, 2, generator=generator) * 2 - 1
    actions = torch.rand(n, 1, generator=generator) * 2 - 1
    rewards = -1.0 - obs.pow(2).sum(dim=1)  # in [-3, -1]
    return Transitions(obs, actions, rewards, obs.clone(), torch.zeros(n, dtype=torch.bool))


def _fitted() -> tuple[CMEDynamics, Transitions]:
    """A model whose psi has kernels at 300 of the data's state-actions and B by ridge on them."""
    dynamics = CMEDynamics(OBS_SPACE, ACTION_SPACE, {"kind": "fourier", "max_width": 101})
    data = _costs(2000, 0)
    dynamics.calibrate_reward_row(data.rewards[:500], data.terminated[:500])
    z = dynamics.encode(data.obs[:300], data.actions[:300])
    dynamics.grow(z, torch.full((300,), 0.15), torch.zeros(dynamics.p + 1, 300))
    dynamics.refit_weights(data, 1e-6)
    return dynamics, data


def _reward(dynamics: CMEDynamics, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    return dynamics.expected_reward(obs, actions, dynamics.phi(obs), dynamics.features(obs, actions))


def test_on_the_data_it_fits_the_reward_and_off_it_the_row_predicts_its_offset():
    dynamics, data = _fitted()
    unseen = _costs(500, 1)  # between the kernels' centres
    error = _reward(dynamics, unseen.obs, unseen.actions) - unseen.rewards
    assert float(error.pow(2).mean() / unseen.rewards.var()) < 0.05
    far = torch.tensor([[3.8, 3.8], [-3.8, 3.8], [3.8, -3.8]])  # the box's corners: psi ~ 0
    assert float(dynamics.features(far, torch.zeros(3, 1)).abs().max()) < 1e-6
    least = float(data.rewards[:500].min())
    torch.testing.assert_close(_reward(dynamics, far, torch.zeros(3, 1)), torch.full((3,), least), atol=1e-3, rtol=0)
    assert least < -2.9  # the first batch's least cost, not the mean


def test_the_offset_is_set_once_before_the_first_feature():
    dynamics, _ = _fitted()
    offset = float(dynamics.reward_offset)
    dynamics.calibrate_reward_row(torch.tensor([-50.0, 10.0]), torch.zeros(2, dtype=torch.bool))  # q > 0: units fixed
    assert float(dynamics.reward_offset) == offset


@pytest.mark.parametrize(
    "rewards, terminated, offset",
    [
        ([-3.0, -1.0, -2.0], [False, False, False], -3.0),  # costs: the worst one seen
        ([9.3, 9.1, -1.5], [False, False, True], 0.0),  # an alive bonus: a fall's reward does not count, never above 0
        ([1.0, 1.0, 0.0], [False, False, True], 0.0),  # InvertedPendulum's: as the offset-free row
        ([2.0, -0.5, -4.0], [False, False, True], -0.5),  # the least non-terminal reward
        ([-2.0, -3.0], [True, True], 0.0),  # no non-terminal reward: 0
    ],
)
def test_the_offset_is_the_least_of_0_and_the_non_terminal_rewards(rewards, terminated, offset):
    dynamics = CMEDynamics(OBS_SPACE, ACTION_SPACE, {"kind": "fourier", "max_width": 101})
    dynamics.calibrate_reward_row(torch.tensor(rewards), torch.tensor(terminated))
    assert float(dynamics.reward_offset) == offset


def test_the_agent_sets_it_from_its_first_batch_says_so_and_it_survives_save_load(tmp_path: Path, capsys):
    from gymnasium.envs.classic_control import PendulumEnv

    env = gym.wrappers.TimeLimit(PendulumEnv(), 200)  # no id: the reward is learned, every reward <= 0
    agent = CMEPolicyIteration("CMEPolicy", env, seed=0, steps_per_iteration=100, verbose=1)
    assert agent.reward_source == "learned"
    agent.learn(300)
    offset = float(agent.dynamics.reward_offset)
    assert offset < -1.0 and offset >= float(agent.store.get(slice(0, len(agent.store))).rewards.min())
    said = capsys.readouterr().out
    assert f"off the data the model predicts {offset:.4g} (the least of 0 and its non-terminal rewards)" in said
    assert said.count("Learned reward:") == 1  # once, before the first feature
    agent.save(tmp_path / "agent")
    loaded = CMEPolicyIteration.load(tmp_path / "agent", env=env)
    assert float(loaded.dynamics.reward_offset) == offset
    obs = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 2.0]], dtype=np.float32)
    assert np.array_equal(loaded.predict(obs, deterministic=True)[0], agent.predict(obs, deterministic=True)[0])


def test_a_model_saved_before_the_offset_loads_with_offset_zero():
    dynamics, _ = _fitted()
    state = dynamics.state_dict()
    del state["reward_offset"]
    new = CMEDynamics(OBS_SPACE, ACTION_SPACE, {"kind": "fourier", "max_width": 101})
    new.load_state_dict(state)
    assert float(new.reward_offset) == 0.0
    torch.testing.assert_close(new.weights, dynamics.weights)
