"""phi's data metric (``phi.metric="data"``): Fourier features in the data's per-dim standard
deviations, fitted on the first data, refit when the box expands, kept by save/load."""

import numpy as np
import pytest
import torch
from gymnasium import spaces

from cme_agent import CMEPolicyIteration
from cme_agent.config import ObservationConfig, StateFeatureConfig
from cme_agent.encoding import ObservationEncoder
from cme_agent.state_features import RandomFourierFeatures, make_state_features

UNBOUNDED = spaces.Box(-np.inf, np.inf, (5,), np.float32)
CARTPOLE_DATA_METRIC = {
    "preset": False,
    "model_update": {"kind": "cme"},
    "policy_kwargs": {"phi": {"kind": "fourier", "metric": "data", "max_width": 200}},
}


def data_phi(seed: int = 0) -> RandomFourierFeatures:
    phi = make_state_features(StateFeatureConfig(metric="data"), ObservationEncoder(UNBOUNDED, ObservationConfig()))
    assert isinstance(phi, RandomFourierFeatures) and phi.follows_data and phi.needs_fit
    return phi


def test_the_data_metric_makes_phi_free_of_each_dims_units() -> None:
    generator = torch.Generator().manual_seed(0)
    obs = torch.randn(500, 5, generator=generator) * torch.tensor([1.0, 0.01, 30.0, 2.0, 5.0]) + 7
    rescaled = obs * torch.tensor([100.0, 1.0, 0.1, 1.0, 3.0]) - 4  # other units, other origins
    phi, other = data_phi(), data_phi()
    phi.fit(obs)
    other.fit(rescaled)
    assert not phi.needs_fit
    torch.testing.assert_close(phi(obs[:50]), other(rescaled[:50]), atol=1e-4, rtol=0)
    # in box units the wide third dim would dominate and the narrow second one vanish: here each counts
    for dim in (1, 2):
        moved = obs[:50].clone()
        moved[:, dim] += obs[:, dim].std()
        assert float((phi(moved) - phi(obs[:50])).norm(dim=1).mean()) > 0.3


def test_a_constant_dim_is_left_out_until_a_refit_sees_it_vary() -> None:
    obs = torch.randn(200, 5, generator=torch.Generator().manual_seed(1))
    obs[:, 4] = 0.0  # e.g. a contact force that is zero while nothing touches
    phi = data_phi()
    message = phi.fit(obs)
    assert "dims [4] constant, left out" in message
    assert phi.inv_std[4] == 0
    touched = obs[:10].clone()
    touched[:, 4] = 50.0
    torch.testing.assert_close(phi(touched), phi(obs[:10]))  # no effect, not cos of a huge number
    varied = obs.clone()
    varied[:, 4] = torch.linspace(-1, 1, 200)
    assert "constant" not in phi.fit(varied) and phi.inv_std[4] > 0


def test_a_grid_with_the_data_metric_is_refused() -> None:
    with pytest.raises(ValueError, match=r"phi\.metric='data' is for Fourier features"):
        make_state_features(
            StateFeatureConfig(kind="rbf_grid", metric="data"), ObservationEncoder(UNBOUNDED, ObservationConfig())
        )
    with pytest.raises(ValueError, match=r"phi\.metric"):
        StateFeatureConfig(metric="whitened")


def test_the_agent_fits_the_metric_on_its_first_data_and_save_load_keeps_it(tmp_path) -> None:
    model = CMEPolicyIteration("CMEPolicy", "CartPole-v1", seed=0, **CARTPOLE_DATA_METRIC)
    phi = model.dynamics.phi
    assert phi.needs_fit
    model.learn(600)
    assert not phi.needs_fit
    states = torch.cat([model.store.get(slice(0, len(model.store))).obs])
    assert float(phi.mean[0]) == pytest.approx(float(states[:, 0].mean()), abs=0.05)
    path = tmp_path / "model.zip"
    model.save(path)
    loaded = CMEPolicyIteration.load(path)
    assert loaded.dynamics.phi.follows_data
    for name in ("mean", "inv_std", "fitted"):
        torch.testing.assert_close(getattr(loaded.dynamics.phi, name), getattr(phi, name))
    obs = np.random.default_rng(0).normal(0, 0.2, (32, 4)).astype(np.float32)
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])


def test_a_box_expansion_refits_the_metric() -> None:
    model = CMEPolicyIteration("CMEPolicy", "CartPole-v1", seed=0, **CARTPOLE_DATA_METRIC)
    model.learn(400)
    phi, dynamics = model.dynamics.phi, model.dynamics
    before = phi.inv_std.clone()
    batch = model.store.get(slice(0, len(model.store)))
    far = batch.obs[:100] * 4
    message = dynamics.expand_observation_box(far, batch, 1e-3)
    assert "phi's metric fitted" in message
    assert not torch.equal(phi.inv_std, before)
    torch.testing.assert_close(phi.mean, torch.cat([far, batch.obs, batch.next_obs]).mean(dim=0))
