"""Clear words: a scalar where a list is expected, and invalid combinations, name the key."""

import math

import pytest

from cme_agent import CMEPolicyIteration
from cme_agent.config import (
    ActionSearchConfig,
    FeatureSelectionConfig,
    ObservationConfig,
    StateFeatureConfig,
    build_config,
)


@pytest.mark.parametrize(
    "cls, group, values, message",
    [
        (
            FeatureSelectionConfig,
            "feature_selection",
            {"bandwidths": -0.3},
            r"feature_selection\.bandwidths=-0\.3 is invalid: must be a list \(write \[-0\.3\]",
        ),
        (
            FeatureSelectionConfig,
            "feature_selection",
            {"bandwidths": "0.3"},
            r"feature_selection\.bandwidths='0\.3' is invalid: must be a list",
        ),
        (StateFeatureConfig, "phi", {"resolution": 2.5}, r"phi\.resolution=2\.5 is invalid: must be a list"),
        (
            ActionSearchConfig,
            "action_search",
            {"grid_points": 0.2},
            r"action_search\.grid_points=0\.2 is invalid: must be a list",
        ),
        (ActionSearchConfig, "action_search", {"grid_points": [0.0, 2.0]}, r"action_search\.grid_points=.*in \[-1, 1\]"),
        (ActionSearchConfig, "action_search", {"grid_points": [0.5, 0.5]}, r"action_search\.grid_points=.*distinct"),
        (ObservationConfig, "observation", {"low": -1.0, "high": [1.0]}, r"observation\.low=-1\.0 is invalid: must be a list"),
        (ObservationConfig, "observation", {"high": 2}, r"observation\.high=2 is invalid: must be a list"),
        (ObservationConfig, "observation", {"angle_pairs": 0}, r"observation\.angle_pairs=0 is invalid: must be a list"),
        (
            ObservationConfig,
            "observation",
            {"angle_pairs": [0, 1]},
            r"observation\.angle_pairs=\(0, 1\) is invalid: must be pairs",
        ),
        (
            ObservationConfig,
            "observation",
            {"low": [0.0, float("inf")], "high": [1.0, 2.0]},
            r"observation\.low=.*finite numbers",
        ),
    ],
)
def test_a_scalar_for_a_list_names_the_key(cls, group, values, message):
    with pytest.raises(ValueError, match=message):
        build_config(cls, values, group)


def test_one_resolution_for_all_dims_is_still_accepted():
    assert build_config(StateFeatureConfig, {"resolution": 9}, "phi").resolution == (9,)
    assert StateFeatureConfig(resolution=9).resolution == (9,)
    assert build_config(FeatureSelectionConfig, {"bandwidths": [0.3]}, "feature_selection").bandwidths == (0.3,)


def test_phi_settings_are_range_checked():
    with pytest.raises(ValueError, match=r"phi\.kind='grid' is invalid"):
        StateFeatureConfig(kind="grid")
    with pytest.raises(ValueError, match=r"phi\.max_width=1 is invalid"):
        StateFeatureConfig(max_width=1)
    with pytest.raises(ValueError, match=r"phi\.n_fourier=0 is invalid"):
        StateFeatureConfig(n_fourier=0)
    with pytest.raises(ValueError, match=r"observation\.quantile=0\.5 is invalid"):
        ObservationConfig(quantile=0.5)


def test_no_feature_budget_is_written_inf():
    """None means 'not given' everywhere, so 'no budget on q' is spelled inf only."""
    assert build_config(
        FeatureSelectionConfig, {"max_total_features": float("inf")}, "feature_selection"
    ).max_total_features == float("inf")
    assert FeatureSelectionConfig(max_total_features=math.inf).max_total_features == math.inf
    with pytest.raises(ValueError, match=r"feature_selection\.max_total_features=None is invalid: .*write inf for no budget"):
        FeatureSelectionConfig(max_total_features=None)
    with pytest.raises(ValueError, match=r"feature_selection\.max_total_features=-inf is invalid"):
        FeatureSelectionConfig(max_total_features=-math.inf)
    with pytest.raises(ValueError, match=r"feature_selection\.max_total_features=2\.5 is invalid"):
        FeatureSelectionConfig(max_total_features=2.5)


@pytest.mark.parametrize(
    "policy_kwargs, message",
    [
        (
            {"feature_selection": {"bandwidths": [0.1]}},
            r"policy_kwargs\['feature_selection'\] is a setting of the agent, not of CMEPolicy: pass feature_selection=\.\.\.",
        ),
        ({"gamma": 0.9}, r"policy_kwargs\['gamma'\] is a setting of the agent.*pass gamma=\.\.\."),
        ({"feature_dynamics": False}, r"pass model_update=\{'feature_dynamics': \.\.\.\}"),
        ({"evaluation": {"l2": 1e-3}}, r"policy_kwargs\[.evaluation.\] is a setting of the agent.*pass evaluation=\.\.\."),
        ({"net_arch": [64, 64]}, r"policy_kwargs\['net_arch'\] is not a setting of CMEPolicy: it takes action_search, .*phi"),
    ],
)
def test_a_policy_kwargs_key_the_policy_does_not_take_is_named(policy_kwargs, message):
    with pytest.raises(ValueError, match=message):
        CMEPolicyIteration("CMEPolicy", "Pendulum-v1", policy_kwargs=policy_kwargs)
