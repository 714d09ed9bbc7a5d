"""The first mistakes of a user new to the agent get words that say what to do: SB3's policy names,
observation spaces a wrapper fixes, image observations in the user's own shape, and an env made
with other kwargs than the one its preset was tuned on."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces
from hydra import compose, initialize_config_dir

from cme_agent import CMEPolicyIteration
from cme_agent.experiment import preset_line
from cme_agent.settings import changed_env_kwargs
from tests.conftest import ROOT


class SpaceEnv(gym.Env):
    """An env with the given observation space and a Box action, for the constructor's checks."""

    action_space = spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self, observation_space: spaces.Space) -> None:
        self.observation_space = observation_space

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action: np.ndarray) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        return self.observation_space.sample(), 0.0, False, False, {}


@pytest.mark.parametrize("policy", ["MlpPolicy", "CnnPolicy"])
def test_sb3_policy_names_get_this_agents_name(policy):
    with pytest.raises(ValueError, match=rf"unknown policy '{policy}': this agent's policy is 'CMEPolicy'"):
        CMEPolicyIteration(policy, "Pendulum-v1")


@pytest.mark.parametrize(
    ("space", "advice"),
    [
        (spaces.Dict({"position": spaces.Box(-1, 1, (2,)), "velocity": spaces.Box(-1, 1, (2,))}), "FlattenObservation"),
        (spaces.Tuple((spaces.Box(-1, 1, (2,)), spaces.Discrete(3))), "FlattenObservation"),
        (spaces.Discrete(5), "FlattenObservation(env) makes it one, a one-hot vector"),
        (spaces.Box(-1, 1, (4, 3)), "FlattenObservation"),
    ],
)
def test_a_space_a_wrapper_fixes_names_the_wrapper(space, advice):
    with pytest.raises(ValueError, match="needs a 1-D Box observation space") as refused:
        CMEPolicyIteration("CMEPolicy", SpaceEnv(space))
    assert advice in str(refused.value)


@pytest.mark.parametrize("shape", [(64, 48, 3), (3, 64, 48)])
def test_an_image_is_described_in_pixels_and_channels_not_sb3s_transposed_shape(shape):
    """SB3 transposes a channels-last image to (3, 64, 48) before the agent sees it."""
    with pytest.raises(ValueError, match="an image of 64 x 48 pixels with 3 channels") as refused:
        CMEPolicyIteration("CMEPolicy", SpaceEnv(spaces.Box(0, 255, shape, np.uint8)))
    assert "(3, 64, 48)" not in str(refused.value)


def test_a_preset_on_an_env_made_with_other_kwargs_says_so():
    changed = CMEPolicyIteration("CMEPolicy", gym.make("MountainCarContinuous-v0", goal_velocity=0.05), seed=0)
    assert changed.preset_message.startswith("Applied the tuned preset of 'MountainCarContinuous-v0'")
    assert "this one is made with goal_velocity=0.05 (registered: 0)" in changed.preset_message
    assert "preset=False" in changed.preset_message
    assert changed.gamma == CMEPolicyIteration("CMEPolicy", "MountainCarContinuous-v0", seed=0).gamma  # still applied
    for same in (gym.make("MountainCarContinuous-v0"), gym.make("MountainCarContinuous-v0", goal_velocity=0)):
        assert "made with" not in CMEPolicyIteration("CMEPolicy", same, seed=0).preset_message


def _compose(overrides):
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        return compose(config_name="config", overrides=overrides)


def test_train_py_says_so_too_and_not_for_the_configs_own_kwargs():
    cfg = _compose(["env=pendulum", "+env.kwargs.g=9.81"])
    line = preset_line(cfg, {"presets@agent": "Pendulum-v1"})
    assert "this one is made with g=9.81 (registered: 10.0)" in line
    for name in ("quadcopter", "pendulum", "cartpole", "toy"):  # the env configs list the defaults: nothing to say
        cfg = _compose([f"env={name}"])
        assert changed_env_kwargs(cfg.env.id, dict(cfg.env.kwargs)) == {}, name
