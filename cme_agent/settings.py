"""What the agent is built from: its settings (preset, user arguments, validated groups) and its env's identity."""

from __future__ import annotations

import inspect
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecEnv

from cme_agent.config import (
    AgentConfig,
    EvaluationConfig,
    ExplorationConfig,
    FeatureSelectionConfig,
    ImprovementConfig,
    ModelUpdateConfig,
    build_config,
)
from cme_agent.presets import GROUPS, TOP_LEVEL_KEYS, apply_preset

SET_BY_THE_AGENT = {
    "feature_dynamics": "model_update={'feature_dynamics': ...}",
    "action_scale": "feature_selection={'action_scale': ...}",
    "reward": "reward_fn=...",
    "evaluation": "evaluation=...",
    "improvement": "improvement=...",
}
"""Arguments of :class:`~cme_agent.policy.CMEPolicy` that the agent passes itself, and where a user sets them."""


@dataclass(frozen=True)
class AgentSettings:
    """The validated settings of one agent: the user's arguments over the env's preset.

    :param agent: gamma, omega and steps_per_iteration
    :param feature_selection: matching pursuit, eq. (5)
    :param model_update: how B is learned, eq. (6)
    :param evaluation: policy evaluation, eq. (7)
    :param exploration: the behaviour policy
    :param improvement: the policy improvement step
    :param policy_kwargs: arguments of the policy (phi, observation, action_search)
    :param preset_message: a log line naming the preset applied and the keys the user overrode (None: no preset)
    """

    agent: AgentConfig
    feature_selection: FeatureSelectionConfig
    model_update: ModelUpdateConfig
    evaluation: EvaluationConfig
    exploration: ExplorationConfig
    improvement: ImprovementConfig
    policy_kwargs: dict[str, Any]
    preset_message: str | None


def resolve_settings(
    env_id: str | None, given: Mapping[str, Any], policy_class: type, agent_arguments: set[str]
) -> AgentSettings:
    """The user's settings over the preset of ``env_id``, each group validated.

    :param env_id: the env's registered id (None: no preset)
    :param given: the constructor's arguments by name (None values: not given)
    :param policy_class: the policy class, whose constructor ``policy_kwargs`` must fit
    :param agent_arguments: the agent constructor's argument names, to point a misplaced key there
    """
    settings, message = apply_preset(env_id, given)
    groups = {group: build_config(cls, settings.get(group), group) for group, cls in GROUPS.items()}
    policy_kwargs = dict(settings.get("policy_kwargs", {}))
    check_policy_kwargs(policy_class, policy_kwargs, agent_arguments)
    return AgentSettings(
        agent=build_config(AgentConfig, {key: settings[key] for key in TOP_LEVEL_KEYS if key in settings}, "agent"),
        policy_kwargs=policy_kwargs,
        preset_message=message,
        **groups,
    )


def check_policy_kwargs(policy_class: type, policy_kwargs: Mapping[str, Any], agent_arguments: set[str]) -> None:
    """Refuse, by name, a ``policy_kwargs`` key the policy does not take, saying where it
    belongs when it is a setting of the agent (``feature_selection``, ``gamma``, ...)."""
    parameters = inspect.signature(policy_class.__init__).parameters
    if any(parameter.kind is inspect.Parameter.VAR_KEYWORD for parameter in parameters.values()):
        return
    accepted = set(parameters) - {"self", "observation_space", "action_space", "lr_schedule"} - set(SET_BY_THE_AGENT)
    for key in policy_kwargs:
        if key in accepted:
            continue
        if key in SET_BY_THE_AGENT or key in agent_arguments:
            where = SET_BY_THE_AGENT.get(key, f"{key}=...")
            raise ValueError(
                f"policy_kwargs['{key}'] is a setting of the agent, not of {policy_class.__name__}: "
                f"pass {where} to CMEPolicyIteration(...) (in a Hydra config, under agent:)"
            )
        raise ValueError(
            f"policy_kwargs['{key}'] is not a setting of {policy_class.__name__}: it takes {', '.join(sorted(accepted))}"
        )


def check_spaces(observation_space: spaces.Space, action_space: spaces.Space) -> None:
    """Refuse, naming the space, what the agent cannot handle."""
    if not (isinstance(observation_space, spaces.Box) and len(observation_space.shape) == 1):
        raise ValueError(f"CMEPolicyIteration needs a 1-D Box observation space, got {observation_space}")
    if not (
        isinstance(action_space, spaces.Discrete) or (isinstance(action_space, spaces.Box) and len(action_space.shape) == 1)
    ):
        raise ValueError(f"CMEPolicyIteration needs a Discrete or 1-D Box action space, got {action_space}")


def env_identity(env: VecEnv | None) -> tuple[str | None, dict[str, Any]]:
    """The registered id and make-kwargs of the env (None, {} without a spec), to find its reward again after load()."""
    spec = env.get_attr("spec", [0])[0] if env is not None else None
    return (spec.id, dict(spec.kwargs)) if spec is not None else (None, {})


def local_env(env: VecEnv | None, env_id: str | None, env_kwargs: Mapping[str, Any], remake: bool) -> gym.Env | None:
    """An instance of the env in this process, to read its ``reward_function``: the first env
    of the VecEnv (a SubprocVecEnv sends a copy), or one made from the env id.

    :param env: the agent's VecEnv, or None
    :param env_id: the env's registered id
    :param env_kwargs: its make-kwargs
    :param remake: without a VecEnv, make the env from its id (a loaded model whose reward was the env's)
    """
    if env is not None:
        try:
            return env.get_attr("unwrapped", [0])[0]
        except Exception:  # an env that cannot travel between processes: make one here if it has an id
            pass
    if env_id is not None and (remake or env is not None):
        return gym.make(env_id, **env_kwargs)
    return None


def env_name(env: VecEnv | None, env_id: str | None) -> str:
    """The env's id, else the class name of its first env, for messages."""
    if env_id is not None or env is None:
        return repr(env_id)
    try:
        return type(env.get_attr("unwrapped", [0])[0]).__name__
    except Exception:  # an env that cannot travel between processes
        return "the env (no registered id)"
