"""Tuned settings per env id: the one source of truth for per-env hyperparameters.

A preset is a nested dict of constructor arguments of :class:`~cme_agent.CMEPolicyIteration`
(``gamma``, ``omega``, ``steps_per_iteration``, the groups ``feature_selection``,
``model_update``, ``evaluation``, ``exploration``, ``improvement`` and ``policy_kwargs`` with ``phi``,
``observation`` and ``action_search``). It holds the measured settings of an env and the facts
about its observation (angle pairs, finite bounds where the space has none).

The presets are data files of this package, one per env id (``cme_agent/presets/Pendulum-v1.yaml``),
read and checked at import. The constructor applies the preset of its env under the user's
arguments (:func:`apply_preset`); Hydra composes the same files, as the config group ``presets``
(search path ``pkg://cme_agent``), between ``conf/agent/cme.yaml``'s library defaults and the
command line (``conf/agent_env/cme_<env>.yaml``).
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Mapping
from importlib import resources
from typing import TYPE_CHECKING, Any

from omegaconf import OmegaConf

from cme_agent.config import (
    ActionSearchConfig,
    AgentConfig,
    EvaluationConfig,
    ExplorationConfig,
    FeatureSelectionConfig,
    ImprovementConfig,
    ModelUpdateConfig,
    ObservationConfig,
    StateFeatureConfig,
    build_config,
)

if TYPE_CHECKING:
    from importlib.resources.abc import Traversable

GROUPS: dict[str, type] = {
    "feature_selection": FeatureSelectionConfig,
    "model_update": ModelUpdateConfig,
    "evaluation": EvaluationConfig,
    "exploration": ExplorationConfig,
    "improvement": ImprovementConfig,
}
"""Config groups of the constructor and their dataclasses."""

POLICY_GROUPS: dict[str, type] = {
    "phi": StateFeatureConfig,
    "observation": ObservationConfig,
    "action_search": ActionSearchConfig,
}
"""Config groups of ``policy_kwargs`` and their dataclasses."""

TOP_LEVEL_KEYS = tuple(field.name for field in dataclasses.fields(AgentConfig))
"""Constructor arguments outside the groups (:class:`~cme_agent.config.AgentConfig`)."""

PRESET_SUFFIX = ".yaml"
"""The presets are the files ``<env id>.yaml`` of this package (``cme_agent/presets/Pendulum-v1.yaml``)."""


def preset_files() -> dict[str, Traversable]:
    """The preset files shipped in the package, by env id."""
    return {
        entry.name[: -len(PRESET_SUFFIX)]: entry
        for entry in resources.files(__name__).iterdir()
        if entry.is_file() and entry.name.endswith(PRESET_SUFFIX)
    }


def load_preset_file(file: Traversable, env_id: str) -> dict[str, Any]:
    """Read and check one preset file, with OmegaConf's YAML reader as Hydra reads it.

    :param file: the YAML file (values only: a nested mapping of constructor arguments)
    :param env_id: the env id it is the preset of, for error messages
    """
    settings = OmegaConf.to_container(OmegaConf.create(file.read_text(encoding="utf-8")), resolve=True)
    if not isinstance(settings, dict):
        raise ValueError(f"the preset file of {env_id!r} ({file.name}) must hold a mapping of settings")
    check_settings(settings, f"the preset of {env_id!r} ({file.name})")
    return settings


def check_settings(settings: Mapping[str, Any], source: str = "settings") -> None:
    """Refuse settings that are not valid constructor arguments of ``CMEPolicyIteration``.

    Every group is built into its config dataclass (so values are range-checked); None values
    count as not given.

    :param settings: nested dict of constructor arguments
    :param source: what the settings are, for error messages (``"preset 'Pendulum-v1'"``)
    """
    known = (*TOP_LEVEL_KEYS, *GROUPS, "policy_kwargs")
    unknown = sorted(set(settings) - set(known))
    if unknown:
        raise ValueError(f"{source} has unknown key(s) {unknown}; known keys: {sorted(known)}")
    given = _drop_none(settings)
    build_config(AgentConfig, {key: given[key] for key in TOP_LEVEL_KEYS if key in given}, "agent")
    for group, cls in GROUPS.items():
        build_config(cls, given.get(group), group)
    policy_kwargs = given.get("policy_kwargs", {})
    unknown = sorted(set(policy_kwargs) - set(POLICY_GROUPS))
    if unknown:
        raise ValueError(f"{source} has unknown policy_kwargs key(s) {unknown}; known keys: {sorted(POLICY_GROUPS)}")
    for group, cls in POLICY_GROUPS.items():
        value = policy_kwargs.get(group)
        if value is None or isinstance(value, (Mapping, cls)):  # a custom phi module is not checked here
            build_config(cls, value, group)


def register_preset(env_id: str, settings: Mapping[str, Any]) -> None:
    """Make ``settings`` the preset of every env with id ``env_id`` (replacing any earlier one).

    :param env_id: the Gymnasium id (``"Pendulum-v1"``)
    :param settings: nested dict of constructor arguments, checked by :func:`check_settings`
    """
    check_settings(settings, f"the preset of {env_id!r}")
    _PRESETS[env_id] = copy.deepcopy(dict(settings))


def preset_for(env_id: str | None) -> dict[str, Any] | None:
    """The preset of an env id, as a fresh copy (None: no preset, or no id).

    :param env_id: the Gymnasium id of the env, or None for an env without one
    """
    if env_id is None or env_id not in _PRESETS:
        return None
    return copy.deepcopy(_PRESETS[env_id])


def registered_presets() -> list[str]:
    """The env ids that have a preset."""
    return sorted(_PRESETS)


def _drop_none(settings: Mapping[str, Any]) -> dict[str, Any]:
    """A copy without the None values (not given), nested mappings included."""
    return {
        key: _drop_none(value) if isinstance(value, Mapping) else value for key, value in settings.items() if value is not None
    }


def merge_settings(preset: Mapping[str, Any], user: Mapping[str, Any]) -> dict[str, Any]:
    """Deep merge of the user's settings over a preset.

    The user wins on any key; where both hold a mapping (a group such as ``evaluation`` or
    ``policy_kwargs.phi``) they are merged key by key; a user value of None means 'not given'
    and keeps the preset's. Anything else the user gives (a config dataclass, a custom phi
    module, a list) replaces the preset's value whole. None values are dropped from the
    result, so what the result lacks takes the library default.

    :param preset: the preset (not modified)
    :param user: the user's settings (not modified)
    :return: a new nested dict
    """
    merged = _drop_none(copy.deepcopy(dict(preset)))
    for key, value in user.items():
        if value is None:
            continue
        if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
            merged[key] = merge_settings(merged[key], value)
        else:
            merged[key] = _drop_none(value) if isinstance(value, Mapping) else value
    return merged


def apply_preset(env_id: str | None, user: Mapping[str, Any]) -> tuple[dict[str, Any], str | None]:
    """The settings to build the agent with: the user's over the preset of ``env_id``.

    :param env_id: the Gymnasium id of the env (None: no preset)
    :param user: the user's constructor arguments (None values: not given)
    :return: the merged settings, and a line for the log naming the preset and the keys the
        user overrode (None when the env has no preset)
    """
    preset = preset_for(env_id)
    if preset is None:
        return _drop_none(user), None
    preset_keys = _leaf_keys(preset)
    overridden = sorted(
        key
        for key in _leaf_keys(_drop_none(user))
        if key in preset_keys or any(name.startswith(f"{key}.") for name in preset_keys)  # a whole group replaced
    )
    message = f"Applied the tuned preset of {env_id!r} (cme_agent.presets)"
    if overridden:
        message += f"; your arguments override {', '.join(overridden)}"
    return merge_settings(preset, user), message


def _leaf_keys(settings: Mapping[str, Any], prefix: str = "") -> set[str]:
    """Dotted names of the non-mapping values (``evaluation.collection_size``)."""
    keys: set[str] = set()
    for key, value in settings.items():
        name = f"{prefix}{key}"
        keys |= _leaf_keys(value, f"{name}.") if isinstance(value, Mapping) else {name}
    return keys


_PRESETS: dict[str, dict[str, Any]] = {env_id: load_preset_file(file, env_id) for env_id, file in preset_files().items()}
"""The registered presets by env id: the package's files, then what :func:`register_preset` added."""
