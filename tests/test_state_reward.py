"""A learned reward's state part ``<c, phi(s)>`` (``model_update.state_reward``): ridge regression
on all of D from normal equations accumulated as D grows, restarted when the box changes phi;
psi's reward row learns the rest; all of it survives save/load."""

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

OBS_SPACE = spaces.Box(-np.ones(2, np.float32), np.ones(2, np.float32), dtype=np.float32)
ACTION_SPACE = spaces.Box(-np.ones(1, np.float32), np.ones(1, np.float32), dtype=np.float32)


def _state_reward(obs: torch.Tensor) -> torch.Tensor:
    """A smooth reward of the state alone, (N, 2) -> (N,)."""
    return -obs.norm(dim=1) + 0.5 * obs[:, 0]


def _transitions(n: int, seed: int, low: float = -1.0, high: float = 1.0) -> Transitions:
    generator = torch.Generator().manual_seed(seed)
    obs = low + (high - low) * torch.rand(n, 2, generator=generator)
    actions = torch.rand(n, 1, generator=generator) * 2 - 1
    return Transitions(obs, actions, _state_reward(obs), obs.clone(), torch.zeros(n, dtype=torch.bool))


def _dynamics(state_reward: bool = True, **phi: object) -> CMEDynamics:
    return CMEDynamics(OBS_SPACE, ACTION_SPACE, {"kind": "fourier", "max_width": 201, **phi}, state_reward=state_reward)


def test_accumulated_equations_give_the_ridge_fit_on_all_of_d():
    data = _transitions(3000, 0)
    in_parts = _dynamics()
    assert in_parts.update_state_reward(data[:1000], 1e-3) == 1000
    assert in_parts.update_state_reward(data[1000:], 1e-3) == 3000
    at_once = _dynamics()
    at_once.update_state_reward(data, 1e-3)
    torch.testing.assert_close(in_parts.state_reward, at_once.state_reward, rtol=1e-5, atol=1e-6)
    phi = at_once.phi(data.obs).double()
    gram = phi.T @ phi
    gram.diagonal().add_(1e-3 * float(gram.diagonal().mean()) + 1e-12)
    direct = torch.linalg.solve(gram, phi.T @ data.rewards.double())
    torch.testing.assert_close(at_once.state_reward, direct.float(), rtol=1e-5, atol=1e-6)


def test_the_fit_holds_on_unseen_states_and_the_reward_row_learns_the_rest():
    dynamics = _dynamics()
    dynamics.update_state_reward(_transitions(3000, 0), 1e-3)
    unseen = _transitions(500, 1)
    phi = dynamics.phi(unseen.obs)
    no_psi = torch.zeros(500, 0)
    predicted = dynamics.linear_reward(phi, no_psi)  # psi empty: the state part alone
    residual = predicted - unseen.rewards
    assert float(residual.pow(2).mean() / unseen.rewards.var()) < 0.02  # R^2 > 0.98 off the training points
    target = dynamics.targets(unseen)[:, -1] * dynamics.reward_scale
    torch.testing.assert_close(target, unseen.rewards - phi @ dynamics.state_reward)  # the row's target: the rest
    without = _dynamics(state_reward=False)
    assert float(without.linear_reward(phi, no_psi).abs().max()) == 0.0  # the learned row alone: 0 off psi
    torch.testing.assert_close(without.targets(unseen)[:, -1], unseen.rewards)


def test_a_changed_box_restarts_the_equations_from_all_of_d():
    space = spaces.Box(np.full(2, -np.inf, np.float32), np.full(2, np.inf, np.float32), dtype=np.float32)
    dynamics = CMEDynamics(space, ACTION_SPACE, {"kind": "fourier", "max_width": 201}, state_reward=True)
    first = _transitions(1000, 0)
    dynamics.obs_encoder.fit(first.obs)
    assert dynamics.state_reward_restarts()  # nothing accumulated yet
    dynamics.update_state_reward(first, 1e-3)
    assert not dynamics.state_reward_restarts()
    wide = _transitions(1000, 1, -3.0, 3.0)
    dynamics.obs_encoder.expand(wide.obs)
    assert dynamics.state_reward_restarts()  # phi changed with the box
    both = first.concat(wide)
    assert dynamics.update_state_reward(both, 1e-3) == 2000  # started over: not 3000 rows
    fresh = CMEDynamics(space, ACTION_SPACE, {"kind": "fourier", "max_width": 201}, state_reward=True)
    fresh.load_state_dict(dynamics.state_dict())
    fresh.state_reward_rows.zero_()
    fresh.update_state_reward(both, 1e-3)
    torch.testing.assert_close(dynamics.state_reward, fresh.state_reward, rtol=1e-5, atol=1e-6)


def test_off_with_a_known_reward_and_refused_for_a_very_wide_phi():
    pendulum = gym.make("Pendulum-v1")
    agent = CMEPolicyIteration("CMEPolicy", pendulum, seed=0)  # a gym.make id: the known reward
    assert agent.reward_source == "known" and not agent.dynamics.fits_state_reward
    with pytest.warns(UserWarning, match="model_update.state_reward is off: phi is 4,097 features wide"):
        wide = _dynamics(n_fourier=4096, max_width=5000)
    assert not wide.fits_state_reward and "state_reward" not in wide.state_dict()


def test_agent_fits_it_each_iteration_and_it_survives_save_load(tmp_path: Path):
    from gymnasium.envs.classic_control import PendulumEnv

    env = gym.wrappers.TimeLimit(PendulumEnv(), 200)  # no id: the reward is learned
    agent = CMEPolicyIteration("CMEPolicy", env, seed=0, steps_per_iteration=100, model_update={"state_reward": True})
    assert agent.reward_source == "learned" and agent.dynamics.fits_state_reward
    agent.learn(300)
    assert int(agent.dynamics.state_reward_rows) == len(agent.store) and float(agent.dynamics.state_reward.abs().sum()) > 0
    agent.save(tmp_path / "agent")
    loaded = CMEPolicyIteration.load(tmp_path / "agent", env=env)
    for name in ("state_reward", "state_reward_gram", "state_reward_moments", "state_reward_rows"):
        torch.testing.assert_close(getattr(loaded.dynamics, name), getattr(agent.dynamics, name))
    obs = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 2.0]], dtype=np.float32)
    assert np.array_equal(loaded.predict(obs, deterministic=True)[0], agent.predict(obs, deterministic=True)[0])
    off = CMEPolicyIteration("CMEPolicy", env, seed=0, model_update={"state_reward": False})
    assert not off.dynamics.fits_state_reward


def test_a_model_saved_before_the_state_reward_loads_with_c_zero():
    old = _dynamics(state_reward=False)
    old.calibrate_reward_row(torch.tensor([0.0, 2.0]), torch.zeros(2, dtype=torch.bool))
    new = _dynamics()
    new.load_state_dict(old.state_dict())
    assert float(new.state_reward.abs().sum()) == 0.0 and new.state_reward_restarts()
    assert float(new.reward_scale) == float(old.reward_scale)


def test_an_expansion_fits_the_state_reward_again_before_b_is_refit():
    space = spaces.Box(np.full(2, -np.inf, np.float32), np.full(2, np.inf, np.float32), dtype=np.float32)

    def model() -> CMEDynamics:
        dynamics = CMEDynamics(space, ACTION_SPACE, {"kind": "fourier", "max_width": 201}, state_reward=True)
        dynamics.obs_encoder.fit(first.obs)
        dynamics.update_state_reward(first, 1e-3)
        z = dynamics.encode(first.obs[:100], first.actions[:100])
        dynamics.grow(z, torch.full((100,), 0.3), torch.zeros(dynamics.p + 1, 100))
        return dynamics

    first, wide = _transitions(1000, 0), _transitions(1000, 1, -3.0, 3.0)
    both = first.concat(wide)
    states = torch.cat([wide.obs, wide.next_obs])
    expanded = model()
    expanded.expand_observation_box(states, both, 1e-6, both, 1e-3)
    assert not expanded.state_reward_restarts()  # fit in the new box, on all of D
    stale = model()
    stale.expand_observation_box(states, both, 1e-6)  # without D: B refit against the old box's c
    stale.update_state_reward(both, 1e-3)
    torch.testing.assert_close(stale.state_reward, expanded.state_reward)
    refit = model()
    refit.expand_observation_box(states, both, 1e-6)
    refit.update_state_reward(both, 1e-3)
    refit.refit_weights(both, 1e-6)  # B against the new c: what the expansion with D gives at once
    torch.testing.assert_close(expanded.weights, refit.weights, rtol=1e-4, atol=1e-4)
    assert float((stale.weights[-1] - expanded.weights[-1]).abs().max()) > 1e-2  # the stale c shows in B's row
