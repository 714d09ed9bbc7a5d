"""The preset registry: one source of truth for per-env settings, merged under the user's."""

import dataclasses
from pathlib import Path

import gymnasium as gym
import pytest
import yaml

import cme_agent  # noqa: F401  (registers Quadcopter-v0 and ToyChain-v0)
from cme_agent.config import EvaluationConfig, ObservationConfig, StateFeatureConfig, build_config
from cme_agent.encoding import ObservationEncoder
from cme_agent.presets import (
    GROUPS,
    POLICY_GROUPS,
    apply_preset,
    check_settings,
    merge_settings,
    preset_for,
    register_preset,
    registered_presets,
)
from cme_agent.state_features import make_state_features

ROOT = Path(__file__).resolve().parents[1]
ENV_IDS = {path.stem: yaml.safe_load(path.read_text())["env"]["id"] for path in sorted((ROOT / "conf" / "env").glob("*.yaml"))}
"""conf/env/<name>.yaml -> its env id."""

OLD_OBSERVATION_FACTS = {
    "Pendulum-v1": {"angle_pairs": [[0, 1]]},
    # since 2026-12 the velocity dims' box is estimated from data (max_half_range below their bounds),
    # expanded as soon as an iteration outgrows it
    "Acrobot-v1": {"angle_pairs": [[0, 1], [2, 3]], "max_half_range": 5.0, "expand_after": 1},
    "CartPole-v1": {"low": [-2.4, -3.0, -0.21, -3.5], "high": [2.4, 3.0, 0.21, 3.5]},
}
"""The observation facts the library held in code before they moved into the presets."""


def _plain(value):
    """Tuples to lists, recursively, so YAML and Python values compare equal."""
    if isinstance(value, dict):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(item) for item in value]
    return value


def _leaves(settings, prefix=""):
    for key, value in settings.items():
        if isinstance(value, dict):
            yield from _leaves(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value


def _lookup(settings, dotted):
    for key in dotted.split("."):
        settings = settings[key]
    return settings


def test_every_env_config_has_a_preset():
    assert set(ENV_IDS.values()) == set(registered_presets())


@pytest.mark.parametrize("env_id", sorted(OLD_OBSERVATION_FACTS))
def test_presets_hold_the_old_observation_facts(env_id):
    assert _plain(preset_for(env_id)["policy_kwargs"]["observation"]) == OLD_OBSERVATION_FACTS[env_id]


@pytest.mark.parametrize("env_id", sorted(set(ENV_IDS.values())))
def test_every_preset_builds_valid_configs_for_its_env(env_id):
    preset = preset_for(env_id)
    check_settings(preset, env_id)
    env = gym.make(env_id)
    policy_kwargs = preset.get("policy_kwargs", {})
    encoder = ObservationEncoder(
        env.observation_space, build_config(ObservationConfig, policy_kwargs.get("observation"), "observation")
    )
    phi = make_state_features(build_config(StateFeatureConfig, policy_kwargs.get("phi"), "phi"), encoder)
    assert phi.width > 1
    env.close()


@pytest.mark.parametrize("env_id", sorted(set(ENV_IDS.values())))
def test_presets_pin_the_planner_settings_they_were_measured_with(env_id):
    """The library's planner defaults are chosen for envs without a preset; each preset keeps the
    gamma, omega and (Box actions) candidate grid its env was measured with, so a change of those
    defaults cannot move the classics."""
    preset = preset_for(env_id)
    assert {"gamma", "omega"} <= set(preset)
    env = gym.make(env_id)
    if isinstance(env.action_space, gym.spaces.Box):
        assert "grid_size" in preset["policy_kwargs"]["action_search"]
    env.close()


def test_merge_user_overrides_a_nested_key_and_keeps_the_rest():
    preset = {
        "gamma": 0.98,
        "evaluation": {"collection_size": 8000, "l2": 1e-4},
        "policy_kwargs": {"phi": {"resolution": [21, 15]}},
    }
    user = {"evaluation": {"collection_size": 300}, "omega": 0.3}
    merged = merge_settings(preset, user)
    assert merged == {
        "gamma": 0.98,
        "omega": 0.3,
        "evaluation": {"collection_size": 300, "l2": 1e-4},
        "policy_kwargs": {"phi": {"resolution": [21, 15]}},
    }
    assert preset["evaluation"]["collection_size"] == 8000 and user == {"evaluation": {"collection_size": 300}, "omega": 0.3}


def test_merge_none_means_not_given():
    preset = {"gamma": 0.98, "evaluation": {"collection_size": 8000}, "exploration": {"repeat": 5}}
    user = {"gamma": None, "evaluation": {"collection_size": None, "rounds": 2}, "exploration": None, "omega": None}
    assert merge_settings(preset, user) == {
        "gamma": 0.98,
        "evaluation": {"collection_size": 8000, "rounds": 2},
        "exploration": {"repeat": 5},
    }
    assert merge_settings({}, {"evaluation": {"l2": None, "rounds": 3}}) == {"evaluation": {"rounds": 3}}


def test_merge_non_mapping_user_values_replace_whole():
    custom_phi = object()
    preset = {"policy_kwargs": {"phi": {"resolution": [21, 15]}, "observation": {"angle_pairs": [[0, 1]]}}}
    merged = merge_settings(preset, {"policy_kwargs": {"phi": custom_phi, "observation": {"angle_pairs": []}}})
    assert merged["policy_kwargs"]["phi"] is custom_phi
    assert merged["policy_kwargs"]["observation"] == {"angle_pairs": []}
    config = StateFeatureConfig(kind="fourier")
    assert merge_settings(preset, {"policy_kwargs": {"phi": config}})["policy_kwargs"]["phi"] is config


def test_apply_preset_names_the_preset_and_the_overrides():
    settings, message = apply_preset("Pendulum-v1", {"omega": 0.5, "evaluation": {"rounds": 2}})
    assert settings["omega"] == 0.5 and settings["evaluation"] == {"collection_size": 8000, "rounds": 2}
    assert "'Pendulum-v1'" in message and "override omega" in message and "rounds" not in message
    _, message = apply_preset("Pendulum-v1", {"evaluation": EvaluationConfig(rounds=2)})
    assert message.endswith("override evaluation")  # a whole group replaced by a config instance
    settings, message = apply_preset(None, {"gamma": 0.9, "omega": None})
    assert settings == {"gamma": 0.9} and message is None


def test_preset_for_returns_a_copy_and_unknown_ids_none():
    preset_for("Pendulum-v1")["evaluation"]["collection_size"] = 1
    assert preset_for("Pendulum-v1")["evaluation"]["collection_size"] == 8000
    assert preset_for("NoSuchEnv-v0") is None and preset_for(None) is None


def test_register_preset_checks_and_replaces(monkeypatch):
    from cme_agent import presets

    monkeypatch.setattr(presets, "_PRESETS", dict(presets._PRESETS))
    register_preset("MyEnv-v0", {"gamma": 0.9, "evaluation": {"rounds": 2}})
    assert preset_for("MyEnv-v0") == {"gamma": 0.9, "evaluation": {"rounds": 2}}
    with pytest.raises(ValueError, match=r"evaluation\.rounds=0 is invalid"):
        register_preset("MyEnv-v0", {"evaluation": {"rounds": 0}})
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['gama'\]"):
        register_preset("MyEnv-v0", {"gama": 0.9})
    with pytest.raises(ValueError, match=r"unknown policy_kwargs key\(s\) \['ph'\]"):
        register_preset("MyEnv-v0", {"policy_kwargs": {"ph": {}}})
    assert preset_for("MyEnv-v0") == {"gamma": 0.9, "evaluation": {"rounds": 2}}


def test_the_hydra_agent_config_lists_every_setting_and_reads_the_presets():
    """conf/agent/cme.yaml: every config field as null, so a composed config is the preset plus overrides."""
    proposed = yaml.safe_load((ROOT / "conf" / "agent" / "cme.yaml").read_text())
    for group, cls in GROUPS.items():
        assert set(proposed[group]) == {f.name for f in dataclasses.fields(cls)}, group
    for group, cls in POLICY_GROUPS.items():
        assert set(proposed["policy_kwargs"][group]) == {f.name for f in dataclasses.fields(cls)}, group
    run_switches = ("reset_envs_each_iteration",)  # how a run goes, not a tuned setting: explicit in the YAML
    user = {key: value for key, value in proposed.items() if key not in ("_target_", "policy", *run_switches)}
    assert all(value is None for _, value in _leaves(user))
    user["evaluation"]["rounds"] = 3  # a command-line override
    settings, _ = apply_preset("Pendulum-v1", user)
    check_settings(settings)
    assert settings["omega"] == 0.2 and settings["evaluation"] == {"collection_size": 8000, "rounds": 3}


def test_top_level_settings_are_checked_and_defaulted_by_agent_config():
    from cme_agent.config import AgentConfig

    assert build_config(AgentConfig, {"gamma": 0.9}, "agent") == AgentConfig(gamma=0.9, omega=0.2, steps_per_iteration=200)
    with pytest.raises(ValueError, match=r"gamma=1\.5 is invalid"):
        check_settings({"gamma": 1.5})
    with pytest.raises(ValueError, match=r"steps_per_iteration=0 is invalid"):
        check_settings({"steps_per_iteration": 0})
