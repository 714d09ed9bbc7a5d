"""The default phi keeps its width p within the budget in any dimension; wide choices warn or are refused."""

import numpy as np
import pytest
import torch
from gymnasium import spaces

from cme_agent import state_features
from cme_agent.config import EvaluationConfig, ObservationConfig, StateFeatureConfig, build_config
from cme_agent.encoding import ObservationEncoder
from cme_agent.planning import evaluation_memory_bytes
from cme_agent.state_features import (
    RandomFourierFeatures,
    RBFGrid,
    default_resolution,
    make_state_features,
    physical_memory_bytes,
)


def _encoder(obs_dim: int, n_angle_pairs: int = 0) -> ObservationEncoder:
    pairs = tuple((2 * k, 2 * k + 1) for k in range(n_angle_pairs))
    return ObservationEncoder(spaces.Box(-1.0, 1.0, (obs_dim,), np.float32), ObservationConfig(angle_pairs=pairs))


@pytest.mark.parametrize("n_angle_pairs", [0, 1, 2])
@pytest.mark.parametrize("obs_dim", range(1, 21))
def test_default_width_stays_within_budget(obs_dim, n_angle_pairs):
    if 2 * n_angle_pairs > obs_dim:
        pytest.skip("not enough dims for the angle pairs")
    encoder = _encoder(obs_dim, n_angle_pairs)
    phi = make_state_features(StateFeatureConfig(), encoder)
    assert 2 <= phi.width <= 1000
    features = phi(encoder.sample_uniform(5, torch.Generator().manual_seed(0)))
    assert features.shape == (5, phi.width) and torch.isfinite(features).all()
    assert torch.all(features[:, -1] == 1)


def test_default_is_the_grid_where_a_useful_one_fits_and_fourier_beyond():
    assert make_state_features(StateFeatureConfig(), _encoder(1)).width == 11 + 1
    assert make_state_features(StateFeatureConfig(), _encoder(2)).width == 11**2 + 1  # 122: fits
    assert make_state_features(StateFeatureConfig(), _encoder(3, 1)).width == 11**2 + 1  # angle pair counts once
    three = make_state_features(StateFeatureConfig(), _encoder(3))
    assert isinstance(three, RBFGrid) and three.resolution == (9, 9, 9)  # 10^3 + 1 > 1000
    four = make_state_features(StateFeatureConfig(), _encoder(4))
    assert isinstance(four, RandomFourierFeatures) and four.width == 1000  # a 5-point grid is too coarse
    assert default_resolution(4, 1000) is None and default_resolution(4, 2402) == 7
    assert default_resolution(3, 1001) == 10 and default_resolution(2, 10**6) == 11


def test_budget_and_fourier_defaults_follow_max_width():
    phi = make_state_features(StateFeatureConfig(max_width=300), _encoder(8))
    assert isinstance(phi, RandomFourierFeatures) and phi.width == 300
    assert float(phi.projection.std()) == pytest.approx(1 / 0.8, rel=0.1)  # length scale 0.1 obs_dim
    low_dim = make_state_features(StateFeatureConfig(kind="fourier"), _encoder(2))
    assert float(low_dim.projection.std()) == pytest.approx(1 / 0.3, rel=0.1)  # floored at 0.3
    grid = make_state_features(StateFeatureConfig(kind="rbf_grid"), _encoder(5))  # forced grid: the budget still holds
    assert isinstance(grid, RBFGrid) and grid.width <= 1000 and grid.resolution == (3,) * 5


def test_explicit_resolution_is_honoured():
    phi = make_state_features(StateFeatureConfig(resolution=(21, 15)), _encoder(3, 1))
    assert isinstance(phi, RBFGrid) and phi.resolution == (21, 15) and phi.width == 316
    assert make_state_features(build_config(StateFeatureConfig, {"resolution": 4}, "phi"), _encoder(4)).width == 4**4 + 1
    fourier = make_state_features(StateFeatureConfig(kind="fourier", n_fourier=600, bandwidth=0.4), _encoder(2))
    assert fourier.width == 601


def test_a_wide_explicit_phi_warns_with_width_and_memory():
    with pytest.warns(UserWarning, match=r"phi\.resolution=\[9, 9, 9, 9\] makes phi 6,562 features wide.*GiB"):
        make_state_features(StateFeatureConfig(resolution=(9,)), _encoder(4), EvaluationConfig(collection_size=500))


def test_a_phi_that_cannot_fit_in_memory_is_refused_with_the_number(monkeypatch):
    assert physical_memory_bytes() > 0  # read from os.sysconf on this machine
    monkeypatch.setattr(state_features, "physical_memory_bytes", lambda device=None: 16 * 2**30)
    with pytest.raises(ValueError, match=r"1,771,562 features wide.*GiB, more than 50% of this machine's 16.0 GiB"):
        make_state_features(StateFeatureConfig(resolution=(11,)), _encoder(6))
    make_state_features(StateFeatureConfig(resolution=(11,)), _encoder(2))  # 122 features: fine


def test_memory_estimate_counts_the_matrices_and_the_smaller_system():
    assert evaluation_memory_bytes(1000, 10_000) == 12 * 10_000 * 1000 + 8 * 1000**2
    assert evaluation_memory_bytes(3000, 2000) == 12 * 2000 * 3000 + 8 * 2000**2  # dual: n x n


def test_on_a_cuda_device_the_memory_check_reads_the_devices_memory(monkeypatch):
    class Properties:
        total_memory = 8 * 2**30

    monkeypatch.setattr(torch.cuda, "get_device_properties", lambda device: Properties())
    assert physical_memory_bytes("cuda:0") == 8 * 2**30
    with pytest.raises(ValueError, match=r"more than 50% of cuda:0's 8.0 GiB"):
        make_state_features(StateFeatureConfig(resolution=(11,)), _encoder(5), device="cuda:0")
