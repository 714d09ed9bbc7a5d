"""Normalisation without given bounds: a box estimated once from data, frozen, saved with the model."""

import numpy as np
import pytest
import torch
from gymnasium import spaces

from cme_agent.config import ObservationConfig, StateFeatureConfig
from cme_agent.encoding import ObservationEncoder
from cme_agent.state_features import make_state_features

INF = np.inf
SPACE = spaces.Box(
    np.array([-1.0, -INF, 0.0, -1e6, -2.0], np.float32), np.array([1.0, INF, INF, 1e6, 2.0], np.float32), dtype=np.float32
)
"""dim 0 finite, 1 infinite, 2 half-infinite, 3 absurdly wide, 4 finite."""


def _data(n=2000, seed=0):
    generator = torch.Generator().manual_seed(seed)
    obs = torch.randn(n, 5, generator=generator)
    obs[:, 0] = obs[:, 0].clamp(-1, 1)
    obs[:, 1] = 50 + 10 * obs[:, 1]
    obs[:, 2] = obs[:, 2].abs() * 3
    obs[:, 3] = 7.0  # constant
    obs[:, 4] = obs[:, 4].clamp(-2, 2)
    return obs


def test_unusable_bounds_are_estimated_from_data_and_frozen():
    encoder = ObservationEncoder(SPACE, ObservationConfig())
    assert encoder.needs_fit and encoder.fit_dims == [1, 2, 3]
    message = encoder.fit(_data())
    assert not encoder.needs_fit and bool(encoder.fitted)
    assert "2000 observations" in message and "1: [" in message and "\n" not in message
    low, high = encoder.center - encoder.half_range, encoder.center + encoder.half_range
    data = _data()
    q01, q99 = torch.quantile(data[:, 1], 0.01), torch.quantile(data[:, 1], 0.99)
    assert float(low[1]) == pytest.approx(float(q01 - 0.1 * (q99 - q01)), rel=1e-5)
    assert float(high[1]) == pytest.approx(float(q99 + 0.1 * (q99 - q01)), rel=1e-5)
    assert float(low[2]) == 0.0  # clipped to the space's finite side
    assert float(encoder.half_range[3]) == pytest.approx(7.0) and float(encoder.center[3]) == pytest.approx(7.0)
    normalised = encoder.normalize(data)
    assert torch.isfinite(normalised).all()
    assert float(normalised[:, 3].abs().max()) == 0.0  # a constant dim maps to 0, no division by zero
    with pytest.raises(RuntimeError, match="frozen"):
        encoder.fit(data)


@pytest.mark.parametrize("constant", [0.0, 7.0])
def test_a_dim_constant_in_the_first_data_keeps_a_later_value_or_a_small_error_at_its_own_size(constant):
    encoder = ObservationEncoder(SPACE, ObservationConfig())
    data = _data()
    data[:, 3] = constant
    data[:3, 3] = constant + 10.0  # rarer than the quantiles: the bulk is constant
    encoder.fit(data)
    scale = max(1.0, constant)
    assert float(encoder.half_range[3]) == pytest.approx(scale)
    later = data[:2].clone()
    later[:, 3] = torch.tensor([constant + 10.0, constant + 1e-3])  # the cart at its rail; a model's error
    normalised = encoder.normalize(later)[:, 3]
    torch.testing.assert_close(normalised, torch.tensor([10.0, 1e-3]) / scale)


def test_dims_with_finite_bounds_keep_the_spaces():
    encoder = ObservationEncoder(SPACE, ObservationConfig())
    encoder.fit(_data())
    assert encoder.center[[0, 4]].tolist() == [0.0, 0.0]
    assert encoder.half_range[[0, 4]].tolist() == [1.0, 2.0]
    finite = ObservationEncoder(spaces.Box(-3.0, 5.0, (2,), np.float32), ObservationConfig())
    assert not finite.needs_fit and finite.fit_dims == []
    assert finite.center.tolist() == [1.0, 1.0] and finite.half_range.tolist() == [4.0, 4.0]


def test_explicit_bounds_override_estimation():
    config = ObservationConfig(low=(-1.0, -5.0, 0.0, 0.0, -1.0), high=(1.0, 5.0, 3.0, 10.0, 1.0))
    encoder = ObservationEncoder(SPACE, config)
    assert not encoder.needs_fit
    assert encoder.half_range.tolist() == [1.0, 5.0, 1.5, 5.0, 1.0]
    with pytest.raises(RuntimeError, match="frozen"):
        encoder.fit(_data())


def test_before_fitting_normalising_says_the_box_comes_from_the_first_data():
    encoder = ObservationEncoder(SPACE, ObservationConfig())
    python_form = r'policy_kwargs=\{"observation": \{"low": \[\.\.\.\], "high": \[\.\.\.\]\}\}'
    for call in (lambda: encoder.normalize(_data(3)), lambda: encoder.sample_uniform(3, torch.Generator())):
        with pytest.raises(RuntimeError, match=r"dims \[1, 2, 3\] have no usable bounds.*first data.*" + python_form):
            call()


def test_fitted_box_survives_state_dict_save_and_load(tmp_path):
    encoder = ObservationEncoder(SPACE, ObservationConfig())
    encoder.fit(_data())
    phi = make_state_features(StateFeatureConfig(), encoder)
    path = tmp_path / "phi.pt"
    torch.save(phi.state_dict(), path)

    fresh_encoder = ObservationEncoder(SPACE, ObservationConfig())
    fresh = make_state_features(StateFeatureConfig(), fresh_encoder)
    assert fresh_encoder.needs_fit
    fresh.load_state_dict(torch.load(path))
    assert not fresh_encoder.needs_fit
    probe = _data(50, seed=1)
    assert torch.equal(fresh_encoder.normalize(probe), encoder.normalize(probe))
    assert torch.equal(fresh(probe), phi(probe))


def test_estimated_box_on_a_wide_half_range_is_configurable():
    wide = spaces.Box(-50.0, 50.0, (1,), np.float32)
    assert not ObservationEncoder(wide, ObservationConfig()).needs_fit
    assert ObservationEncoder(wide, ObservationConfig(max_half_range=10.0)).needs_fit
    encoder = ObservationEncoder(wide, ObservationConfig(max_half_range=10.0, quantile=0.0, margin=0.0))
    encoder.fit(torch.linspace(-2, 4, 101)[:, None])
    assert encoder.center.tolist() == [1.0] and encoder.half_range.tolist() == [3.0]


def test_fit_refuses_bad_data():
    encoder = ObservationEncoder(SPACE, ObservationConfig())
    with pytest.raises(ValueError, match=r"\(N >= 1, 5\)"):
        encoder.fit(torch.zeros(0, 5))
    with pytest.raises(ValueError, match="non-finite"):
        encoder.fit(torch.full((4, 5), float("nan")))
    assert encoder.needs_fit


def test_the_log_line_of_a_wide_observation_stays_one_short_line():
    encoder = ObservationEncoder(spaces.Box(-np.inf, np.inf, (40,), np.float32), ObservationConfig())
    message = encoder.fit(torch.randn(100, 40))
    assert "\n" not in message and "7: [" in message and "8: [" not in message and "and 32 more" in message
