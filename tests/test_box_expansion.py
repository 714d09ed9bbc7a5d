"""An estimated observation box that later data outgrows is expanded: the box covers the new
data and never shrinks, psi's features keep their env-unit centres, B is refit on D, planning
restarts, and all of it survives save/load."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium import spaces
from stable_baselines3.common.logger import configure

from cme_agent import CMEPolicyIteration
from cme_agent.buffer import Transitions
from cme_agent.config import ObservationConfig
from cme_agent.dynamics import CMEDynamics
from cme_agent.dynamics.box import observed_states
from cme_agent.encoding import ObservationEncoder

INF = np.inf
SPACE = spaces.Box(np.array([-INF, -1.0], np.float32), np.array([INF, 1.0], np.float32), dtype=np.float32)
"""dim 0 unbounded (estimated), dim 1 bounded (never changes)."""


def _obs(n: int, spread: float, seed: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    obs = torch.rand(n, 2, generator=generator) * 2 - 1
    obs[:, 0] *= spread
    return obs


def test_expand_covers_new_data_never_shrinks_and_keeps_given_dims():
    encoder = ObservationEncoder(SPACE, ObservationConfig())
    encoder.fit(_obs(500, 1.0, 0))
    low, high = encoder.center - encoder.half_range, encoder.center + encoder.half_range
    wide = _obs(500, 5.0, 1)
    assert encoder.outside_share(wide) > 0.5
    message = encoder.expand(torch.cat([_obs(500, 1.0, 0), wide]))
    assert "expansion 1" in message and int(encoder.expansions) == 1
    assert encoder.outside_share(wide) < 0.05
    new_low, new_high = encoder.center - encoder.half_range, encoder.center + encoder.half_range
    assert float(new_low[0]) <= float(low[0]) and float(new_high[0]) >= float(high[0])
    assert float(new_low[1]) == -1.0 and float(new_high[1]) == 1.0  # a space bound: untouched
    encoder.expand(_obs(500, 0.1, 2))  # narrower data: the box does not shrink
    assert float(encoder.center[0] - encoder.half_range[0]) == pytest.approx(float(new_low[0]))


def test_expand_is_refused_before_fit_and_without_estimated_dims():
    with pytest.raises(RuntimeError, match="fit"):
        ObservationEncoder(SPACE, ObservationConfig()).expand(_obs(10, 1.0, 0))
    bounded = ObservationEncoder(SPACE, ObservationConfig(low=(-1.0, -1.0), high=(1.0, 1.0)))
    assert bounded.outside_share(_obs(10, 9.0, 0)) == 0.0  # given bounds are never expanded
    with pytest.raises(RuntimeError, match="fit"):
        bounded.expand(_obs(10, 1.0, 0))


def _transitions(obs: torch.Tensor, seed: int) -> Transitions:
    generator = torch.Generator().manual_seed(seed)
    actions = torch.rand(obs.shape[0], 1, generator=generator) * 2 - 1
    next_obs = obs.clone()
    next_obs[:, 0] += 0.1 * actions[:, 0]
    return Transitions(obs, actions, -(obs**2).sum(1), next_obs, torch.zeros(obs.shape[0], dtype=torch.bool))


def test_expansion_keeps_psi_centres_in_env_units_and_refits_b():
    dynamics = CMEDynamics(SPACE, spaces.Box(-1.0, 1.0, (1,), np.float32), phi={"resolution": [7, 5]})
    early = _transitions(_obs(400, 1.0, 0), 0)
    dynamics.obs_encoder.fit(torch.cat([early.obs, early.next_obs]))
    z = dynamics.encode(early.obs[:40], early.actions[:40])
    dynamics.grow(z, torch.full((40,), 0.3), torch.zeros(dynamics.weights.shape[0], 40))
    dynamics.refit_weights(early, l2=1e-6)
    at_centres = dynamics.features(early.obs[:40], early.actions[:40]).diagonal()
    assert torch.allclose(at_centres, torch.ones(40))  # each kernel peaks at its centre

    late = _transitions(_obs(400, 4.0, 1), 1)
    data = early.concat(late)
    before = dynamics.weights.clone()
    dynamics.expand_observation_box(torch.cat([data.obs, data.next_obs]), data, l2=1e-6)
    moved = dynamics.features(early.obs[:40], early.actions[:40]).diagonal()
    assert torch.allclose(moved, torch.ones(40), atol=1e-5)  # same env-unit centres in the new coordinates
    psi, targets = dynamics.regression_data(data)
    refit_loss = float(dynamics.loss(psi, targets))
    dynamics.weights = before
    assert refit_loss < float(dynamics.loss(psi, targets))  # the old B is wrong for the new phi


class Drifting(gym.Env):
    """A 1-D mass whose reachable velocity grows far beyond what random actions reach in 100 steps:
    observation (position, velocity), unbounded; pushing always one way keeps accelerating it."""

    observation_space = spaces.Box(-INF, INF, (2,), np.float32)
    action_space = spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.state, self.steps = np.zeros(2, np.float32), 0
        return self.state.copy(), {}

    def step(self, action):
        self.steps += 1
        self.state = self.state + np.array([0.1 * self.state[1], 0.1 * float(action[0])], np.float32)
        return self.state.copy(), float(self.state[1]), False, self.steps >= 100, {}  # reward: go fast


SMALL = {
    "steps_per_iteration": 100,
    "evaluation": {"collection_size": 300, "rounds": 1},
    "feature_selection": {"subsample_size": 200, "max_features": 20},
    # the CME, whose box this is: its reward fit on psi alone (0 off the data, above this env's early rewards)
    # draws the agent off the box, which is what these tests need; with the state reward on phi it stays inside
    "model_update": {"kind": "cme", "n_steps": 20, "batch_size": 64, "holdout_size": 50},
    "exploration": {"random_steps": 100},
}


def test_an_agent_expands_its_box_as_the_data_outgrows_it_and_saves_it(tmp_path: Path):
    # more expansions allowed than iterations: every iteration's data is covered or triggers one
    unlimited = {"observation": {"max_expansions": 10}}
    model = CMEPolicyIteration("CMEPolicy", Drifting(), seed=0, policy_kwargs=unlimited, **SMALL)
    model.learn(600)
    encoder = model.dynamics.obs_encoder
    assert 1 <= int(encoder.expansions) <= 5
    states = observed_states(model.store, model.holdout)
    assert encoder.outside_share(states) < 0.05  # the box covers D after the last expansion
    model.save(tmp_path / "model.zip")
    loaded = CMEPolicyIteration.load(tmp_path / "model.zip")
    assert int(loaded.dynamics.obs_encoder.expansions) == int(encoder.expansions)
    assert torch.equal(loaded.dynamics.obs_encoder.half_range, encoder.half_range)
    obs = states[:50].numpy()
    assert np.array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])


def test_no_expansion_when_disabled_or_bounds_are_given():
    frozen = CMEPolicyIteration("CMEPolicy", Drifting(), seed=0, policy_kwargs={"observation": {"max_expansions": 0}}, **SMALL)
    frozen.learn(400)
    assert int(frozen.dynamics.obs_encoder.expansions) == 0
    given = CMEPolicyIteration(
        "CMEPolicy", Drifting(), seed=0, policy_kwargs={"observation": {"low": [-1, -1], "high": [1, 1]}}, **SMALL
    )
    given.learn(400)
    assert int(given.dynamics.obs_encoder.expansions) == 0


@pytest.mark.parametrize(
    "key, value",
    [("expand_outside", 0.0), ("expand_outside", 1.5), ("max_expansions", -1), ("expand_after", 0), ("expand_after", 1.5)],
)
def test_invalid_expansion_settings_name_the_key(key, value):
    with pytest.raises(ValueError, match=f"observation.{key}"):
        ObservationConfig(**{key: value})


def test_an_expansion_covers_the_new_observations_that_triggered_it():
    """A drift that is a small share of D (here 20 of about 3,600 transitions, under the 1%
    quantile of D) is covered by the expansion it triggers, so the policy does not meet the box's
    edge again at once."""
    model = CMEPolicyIteration("CMEPolicy", Drifting(), seed=0, **SMALL)
    model.learn(100)  # the random phase: the box is fitted on it
    encoder = model.dynamics.obs_encoder
    early = model.store.get(slice(0, len(model.store)))
    for _ in range(40):  # D grows to about 3,600 transitions inside the box
        model.store.add(early.obs, early.actions, early.rewards, early.next_obs, early.terminated)
    far = early[:20]
    shift = torch.tensor([1.0, 0.0]) * 3 * encoder.half_range
    drift = Transitions(far.obs + shift, far.actions, far.rewards, far.next_obs + shift, far.terminated)
    model.store.add(drift.obs, drift.actions, drift.rewards, drift.next_obs, drift.terminated)
    new_states = torch.cat([drift.obs, drift.next_obs])
    assert encoder.outside_share(new_states) == 1.0
    for _ in range(model.dynamics.obs_encoder.config.expand_after):  # the drift persists
        model.observation_box(drift)
    assert int(encoder.expansions) == 1
    assert encoder.outside_share(new_states) == 0.0


def _shifted(batch: Transitions, shift: torch.Tensor) -> Transitions:
    return Transitions(batch.obs + shift, batch.actions, batch.rewards, batch.next_obs + shift, batch.terminated)


def test_with_expand_after_one_excursion_leaves_the_box_and_successive_ones_expand_it(tmp_path: Path):
    """``observation.expand_after=2`` (the default): an iteration that outgrows the box, followed by one that
    stays inside, changes nothing; two in a row expand it to cover both, also across save/load."""
    model = CMEPolicyIteration("CMEPolicy", Drifting(), seed=0, **SMALL)
    assert model.dynamics.obs_encoder.config.expand_after == 2
    model.learn(100)  # the random phase: the box is fitted on it
    encoder = model.dynamics.obs_encoder
    early = model.store.get(slice(0, len(model.store)))[:50]
    half_range = encoder.half_range.clone()
    right = _shifted(early, torch.tensor([3.0, 0.0]) * half_range)
    left = _shifted(early, torch.tensor([-5.0, 0.0]) * half_range)

    model.observation_box(right)
    model.observation_box(early)  # back inside: the excursion is forgotten
    model.observation_box(right)
    assert int(encoder.expansions) == 0 and torch.equal(encoder.half_range, half_range)

    model.save(tmp_path / "pending.zip", include=["replay_buffer"])
    loaded = CMEPolicyIteration.load(tmp_path / "pending.zip", env=Drifting())
    loaded.set_logger(configure(None, []))  # what learn() would set up
    for agent in (model, loaded):
        agent.observation_box(left)  # the second in a row: covers both excursions
        box = agent.dynamics.obs_encoder
        assert int(box.expansions) == 1
        assert box.outside_share(torch.cat([right.obs, right.next_obs, left.obs, left.next_obs])) == 0.0
    assert torch.equal(loaded.dynamics.obs_encoder.half_range, encoder.half_range)

    at_once = CMEPolicyIteration("CMEPolicy", Drifting(), seed=0, policy_kwargs={"observation": {"expand_after": 1}}, **SMALL)
    at_once.learn(100)
    at_once.observation_box(_shifted(early, torch.tensor([3.0, 0.0]) * at_once.dynamics.obs_encoder.half_range))
    assert int(at_once.dynamics.obs_encoder.expansions) == 1
