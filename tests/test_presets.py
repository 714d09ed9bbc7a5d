"""The preset registry: one source of truth for per-env settings, merged under the user's; the
package's preset files are what Hydra composes, over conf/agent/cme.yaml's library defaults."""

import dataclasses
from pathlib import Path

import gymnasium as gym
import pytest
import yaml
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import cme_agent  # noqa: F401  (registers Quadcopter-v0 and ToyChain-v0)
from cme_agent.config import AgentConfig, EvaluationConfig, ObservationConfig, StateFeatureConfig, build_config
from cme_agent.encoding import ObservationEncoder
from cme_agent.presets import (
    GROUPS,
    POLICY_GROUPS,
    apply_preset,
    check_settings,
    merge_settings,
    preset_files,
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
    # the velocity dims' box is estimated from data (max_half_range below their bounds), expanded
    # as soon as an iteration outgrows it
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


def _defaults(cls):
    """A config dataclass's fields and defaults, as plain YAML values."""
    return {name: _plain(value) for name, value in dataclasses.asdict(cls()).items()}


def _cme_yaml():
    return OmegaConf.to_container(OmegaConf.load(ROOT / "conf" / "agent" / "cme.yaml"))


RUN_SWITCHES = {"_target_": "cme_agent.CMEPolicyIteration", "policy": "CMEPolicy", "reset_envs_each_iteration": False}
"""conf/agent/cme.yaml's keys that are not settings of the config dataclasses (besides ``preset``)."""


def test_the_hydra_agent_config_lists_every_setting_at_its_library_default():
    """conf/agent/cme.yaml: every field of the config dataclasses with its default, so the file cannot drift."""
    config = _cme_yaml()
    assert set(config) == {*RUN_SWITCHES, "preset", *AgentConfig.__dataclass_fields__, *GROUPS, "policy_kwargs"}
    assert {key: config[key] for key in RUN_SWITCHES} == RUN_SWITCHES
    assert config["preset"] is False  # Hydra composes the preset (conf/agent_env/cme_<env>.yaml); the agent must not again
    expected = {
        **{key: _defaults(AgentConfig)[key] for key in AgentConfig.__dataclass_fields__},
        **{group: _defaults(cls) for group, cls in GROUPS.items()},
        "policy_kwargs": {group: _defaults(cls) for group, cls in POLICY_GROUPS.items()},
    }
    # the ridge of model_update.l2 is derived from the method (None in the dataclass, written in on construction)
    expected["model_update"]["l2"] = None
    actual = {key: value for key, value in config.items() if key not in (*RUN_SWITCHES, "preset")}
    assert actual == expected
    for name, value in _leaves(actual):  # 1 is not 1.0: YAML's types match the dataclasses'
        default = _lookup(expected, name)
        assert type(value) is type(default), (name, value, default)


def _compose(overrides):
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        return compose(config_name="config", overrides=overrides)


@pytest.mark.parametrize("agent", ["cme", "kernel"])
@pytest.mark.parametrize("env_name", sorted(ENV_IDS))
def test_hydra_composes_the_package_preset_over_the_library_defaults(env_name, agent):
    """Hydra reads the package's preset file (conf/agent_env/<agent>_<env>.yaml): the composed agent
    holds the preset's values, the library defaults elsewhere; the agent does not apply it again."""
    cfg = _compose([f"env={env_name}", f"agent={agent}"])
    composed = OmegaConf.to_container(cfg.agent)
    assert composed["preset"] is False
    preset = preset_for(ENV_IDS[env_name])
    for name, value in _leaves(preset):
        if agent == "kernel" and name == "steps_per_iteration":
            continue  # conf/agent_env/kernel_toy.yaml sets its own
        assert _plain(_lookup(composed, name)) == _plain(value), name
    defaults = _cme_yaml()
    preset_names = {name for name, _ in _leaves(preset)}
    for name, value in _leaves(defaults):
        if name not in preset_names and name not in ("_target_", "steps_per_iteration"):
            assert _lookup(composed, name) == value, name


def test_command_line_overrides_win_over_the_composed_preset():
    cfg = _compose(["env=pendulum", "agent.gamma=0.9", "agent.evaluation.rounds=3", "agent.evaluation.collection_size=500"])
    assert cfg.agent.gamma == 0.9 and cfg.agent.evaluation.rounds == 3 and cfg.agent.evaluation.collection_size == 500
    assert cfg.agent.omega == 0.2 and list(cfg.agent.policy_kwargs.phi.resolution) == [21, 15]  # the preset's


def test_without_a_preset_the_library_defaults_apply():
    """An env config without conf/agent_env/cme_<env>.yaml (here: the entry removed) gets cme.yaml's defaults."""
    cfg = _compose(["env=pendulum", "~agent_env"])
    agent = OmegaConf.to_container(cfg.agent)
    assert agent == _cme_yaml()


def test_the_preset_files_are_the_registered_presets_and_load_as_hydra_reads_them():
    files = preset_files()
    assert set(files) == set(registered_presets())
    for env_id, file in files.items():
        assert _plain(OmegaConf.to_container(OmegaConf.create(file.read_text()))) == _plain(preset_for(env_id)), env_id
        assert yaml.safe_load(file.read_text()) == preset_for(env_id), env_id  # plain YAML reads the same values


def test_a_bad_preset_file_is_refused_naming_it(tmp_path):
    from cme_agent.presets import load_preset_file

    bad = tmp_path / "MyEnv-v0.yaml"
    bad.write_text("evaluation:\n  rounds: 0\n")
    with pytest.raises(ValueError, match=r"evaluation\.rounds=0 is invalid"):
        load_preset_file(bad, "MyEnv-v0")
    bad.write_text("gama: 0.9\n")
    with pytest.raises(ValueError, match=r"preset of 'MyEnv-v0' \(MyEnv-v0\.yaml\) has unknown key\(s\) \['gama'\]"):
        load_preset_file(bad, "MyEnv-v0")


def test_top_level_settings_are_checked_and_defaulted_by_agent_config():
    from cme_agent.config import AgentConfig

    assert build_config(AgentConfig, {"gamma": 0.9}, "agent") == AgentConfig(gamma=0.9, omega=0.2, steps_per_iteration=200)
    with pytest.raises(ValueError, match=r"gamma=1\.5 is invalid"):
        check_settings({"gamma": 1.5})
    with pytest.raises(ValueError, match=r"steps_per_iteration=0 is invalid"):
        check_settings({"steps_per_iteration": 0})
