"""``feature_selection.action_scale``: a Box action enters psi's kernels scaled, so each kernel
spans more of the action range; a Discrete action's one-hot enters unscaled."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium import spaces
from gymnasium.envs.classic_control import PendulumEnv

from cme_agent import CMEPolicyIteration
from cme_agent.config import FeatureSelectionConfig
from cme_agent.dynamics import CMEDynamics
from cme_agent.kernel_bank import gaussian_kernel

OBS_SPACE = spaces.Box(np.full(2, -4.0, np.float32), np.full(2, 4.0, np.float32), dtype=np.float32)
BOX_ACTIONS = spaces.Box(np.full(1, -2.0, np.float32), np.full(1, 2.0, np.float32), dtype=np.float32)


def _with_centres(dynamics: CMEDynamics, n: int = 6) -> CMEDynamics:
    """The model with n kernel features at fixed centres in normalised (state, action) units."""
    generator = torch.Generator().manual_seed(0)
    width = dynamics.obs_encoder.dim + dynamics.action_encoder.dim
    centres = torch.rand(n, width, generator=generator) * 0.4 - 0.2
    dynamics.grow(centres, torch.full((n,), 0.15), torch.zeros(dynamics.weights.shape[0], n))
    return dynamics


def test_psi_is_the_kernel_on_the_scaled_action():
    dynamics = _with_centres(CMEDynamics(OBS_SPACE, BOX_ACTIONS, {"kind": "fourier", "max_width": 11}, action_scale=0.25))
    obs, actions = torch.tensor([[1.0, -2.0], [0.5, 0.0]]), torch.tensor([[2.0], [-1.0]])  # actions at +1, -0.5 normalised
    z = torch.cat([dynamics.obs_encoder.normalize(obs), torch.tensor([[0.25], [-0.125]])], dim=1)
    expected = gaussian_kernel(z, dynamics.psi.centres, dynamics.psi.inv_two_sq_bandwidth)
    assert torch.allclose(dynamics.features(obs, actions), expected)
    # the factorised form (the greedy step's) reads the same scale
    factorised = dynamics.state_factor(obs) * dynamics.action_factor(actions)
    assert torch.allclose(factorised, expected, atol=1e-6)


def test_a_smaller_scale_makes_each_kernel_span_more_actions():
    obs = torch.zeros(201, 2)
    actions = torch.linspace(-2, 2, 201).unsqueeze(1)

    def share_above_half_peak(scale: float) -> float:
        """The share of the action range on which a feature exceeds half its peak, mean over features."""
        dynamics = _with_centres(CMEDynamics(OBS_SPACE, BOX_ACTIONS, {"kind": "fourier", "max_width": 11}, action_scale=scale))
        psi = dynamics.features(obs, actions)
        return float((psi > 0.5 * psi.amax(dim=0)).float().mean())

    # half width at half maximum of a Gaussian: 1.18 h in z_a, i.e. 1.18 h / scale of the normalised range [-1, 1]
    assert share_above_half_peak(1.0) == pytest.approx(2.35 * 0.15 / 2, abs=0.03)
    assert share_above_half_peak(0.25) == pytest.approx(min(1.0, 2.35 * 0.15 / 0.25 / 2), abs=0.1)


def test_a_discrete_action_enters_unscaled():
    discrete = CMEDynamics(OBS_SPACE, spaces.Discrete(3), {"kind": "fourier", "max_width": 11}, action_scale=0.2)
    assert float(discrete.action_scale) == 1.0
    assert torch.equal(discrete.encode_actions(torch.tensor([0, 2])), torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))


def test_a_model_saved_before_the_scale_loads_unscaled():
    dynamics = CMEDynamics(OBS_SPACE, BOX_ACTIONS, {"kind": "fourier", "max_width": 11}, action_scale=0.2)
    state = dynamics.state_dict()
    del state["action_scale"]
    dynamics.load_state_dict(state)
    assert float(dynamics.action_scale) == 1.0


def test_the_scale_is_checked():
    with pytest.raises(ValueError, match=r"feature_selection\.action_scale"):
        FeatureSelectionConfig(action_scale=0.0)
    with pytest.raises(ValueError, match=r"feature_selection\.action_scale"):
        FeatureSelectionConfig(action_scale=float("nan"))


def test_the_agent_passes_it_to_the_model_and_it_survives_save_load(tmp_path, pendulum_kwargs):
    pendulum_kwargs["feature_selection"] = {**pendulum_kwargs["feature_selection"], "action_scale": 0.5}
    agent = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **pendulum_kwargs)
    assert float(agent.dynamics.action_scale) == 0.5
    assert float(CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0).dynamics.action_scale) == 0.2  # the preset's
    no_preset = gym.wrappers.TimeLimit(PendulumEnv(), 200)  # no env id, so no preset
    assert float(CMEPolicyIteration("CMEPolicy", no_preset, seed=0).dynamics.action_scale) == 1.0  # the default
    agent.learn(200)
    agent.save(tmp_path / "agent")
    loaded = CMEPolicyIteration.load(tmp_path / "agent")
    assert float(loaded.dynamics.action_scale) == 0.5
    obs = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 2.0], [-1.0, 0.0, -3.0]], dtype=np.float32)
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], agent.predict(obs, deterministic=True)[0])


def test_policy_kwargs_refuse_it_and_say_where_it_goes():
    with pytest.raises(ValueError, match=r"feature_selection=\{'action_scale'"):
        CMEPolicyIteration("CMEPolicy", "Pendulum-v1", policy_kwargs={"action_scale": 0.5})
