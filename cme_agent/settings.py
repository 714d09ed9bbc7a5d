"""What the agent is built from: its settings (preset, user arguments, validated groups) and its env's identity."""

from __future__ import annotations

import inspect
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.envs.registration import load_env_creator
from stable_baselines3.common.preprocessing import is_image_space, is_image_space_channels_first
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
from cme_agent.rewards import RewardSpec, StepReward, resolve_reward

SET_BY_THE_AGENT = {
    "feature_dynamics": "model_update={'feature_dynamics': ...}",
    "action_scale": "feature_selection={'action_scale': ...}",
    "reward": "reward_fn=...",
    "evaluation": "evaluation=...",
    "improvement": "improvement=...",
    "model_kind": "model_update={'kind': ...}",
    "gamma": "gamma=...",
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
    env_id: str | None,
    given: Mapping[str, Any],
    policy_class: type,
    agent_arguments: set[str],
    env_kwargs: Mapping[str, Any] | None = None,
) -> AgentSettings:
    """The user's settings over the preset of ``env_id``, each group validated.

    The preset applies also to an env made with other arguments than the registered env's
    (``gym.make("Pendulum-v1", g=9.81)``): its facts about the observation (angle pairs, bounds)
    still hold, and its tuning is the nearest there is; the log line then says which arguments
    differ, and ``preset=False`` gives the library defaults instead.

    :param env_id: the env's registered id (None: no preset)
    :param given: the constructor's arguments by name (None values: not given)
    :param policy_class: the policy class, whose constructor ``policy_kwargs`` must fit
    :param agent_arguments: the agent constructor's argument names, to point a misplaced key there
    :param env_kwargs: the env's make-kwargs (its spec's), compared with the registered env's
    """
    settings, message = apply_preset(env_id, given)
    note = changed_kwargs_note(env_id, env_kwargs or {})
    if message is not None and note is not None:
        message += f"; {note}: pass preset=False for the library defaults"
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


def check_policy(policy: str | type, aliases: Mapping[str, type]) -> None:
    """Refuse a policy name the agent does not have, saying which it has (SB3 says only
    ``Policy MlpPolicy unknown``).

    :param policy: the ``policy`` argument of the constructor, a name or a class
    :param aliases: the agent's ``policy_aliases``
    """
    if isinstance(policy, str) and policy not in aliases:
        names = " or ".join(f"{name!r}" for name in aliases)
        raise ValueError(
            f"unknown policy {policy!r}: this agent's policy is {names} (or the class itself); SB3's MlpPolicy, "
            "CnnPolicy and MultiInputPolicy are the networks of its own algorithms, which this agent has none of"
        )


def check_spaces(observation_space: spaces.Space, action_space: spaces.Space) -> None:
    """Refuse, naming the space and what to do about it, what the agent cannot handle."""
    if not (isinstance(observation_space, spaces.Box) and len(observation_space.shape) == 1):
        raise ValueError(f"CMEPolicyIteration needs a 1-D Box observation space, got {_observation_advice(observation_space)}")
    if not (
        isinstance(action_space, spaces.Discrete) or (isinstance(action_space, spaces.Box) and len(action_space.shape) == 1)
    ):
        raise ValueError(f"CMEPolicyIteration needs a Discrete or 1-D Box action space, got {action_space}")


def _observation_advice(space: spaces.Space) -> str:
    """The observation space as a user knows it, and the wrapper that makes it a 1-D Box where there is one."""
    flatten = "gymnasium.wrappers.FlattenObservation(env) makes it one"
    if is_image_space(space):
        # SB3 hands the agent a channels-last image transposed to channels first: name no order
        channels, height, width = space.shape if is_image_space_channels_first(space) else np.roll(space.shape, 1)
        return (
            f"an image of {height} x {width} pixels with {channels} channels: the agent plans over state vectors, "
            "so give it the env's state (most envs have a non-pixel version) or image features of your own "
            "(a gymnasium.ObservationWrapper)"
        )
    if isinstance(space, (spaces.Dict, spaces.Tuple)):
        return f"{space}: {flatten}, the entries concatenated"
    if isinstance(space, spaces.Discrete):
        return f"{space}: {flatten}, a one-hot vector"
    if isinstance(space, (spaces.Box, spaces.MultiDiscrete, spaces.MultiBinary)):
        return f"{space}: {flatten}, the values in a row"
    return str(space)


def changed_env_kwargs(env_id: str | None, env_kwargs: Mapping[str, Any]) -> dict[str, tuple[Any, Any]]:
    """The make-kwargs of an env that differ from the registered env's, ``render_mode`` aside.

    :param env_id: the env's registered id (None or unregistered: nothing to compare with)
    :param env_kwargs: the kwargs the env was made with (its spec's)
    :return: name -> (the env's value, the registered env's: its spec's kwargs, else the
        constructor's default; None where it has neither)
    """
    if env_id is None or env_id not in gym.registry:
        return {}
    spec = gym.spec(env_id)
    try:
        creator = load_env_creator(spec.entry_point) if isinstance(spec.entry_point, str) else spec.entry_point
        parameters = inspect.signature(creator).parameters
    except (ImportError, AttributeError, TypeError, ValueError):  # a creator without a readable signature
        parameters = {}
    changed = {}
    for name, value in env_kwargs.items():
        default = parameters[name].default if name in parameters else None
        registered = spec.kwargs.get(name, None if default is inspect.Parameter.empty else default)
        if name != "render_mode" and not _equal(value, registered):
            changed[name] = (value, registered)
    return changed


def changed_kwargs_note(env_id: str | None, env_kwargs: Mapping[str, Any]) -> str | None:
    """The words for the log when a preset meets an env made with other kwargs than the registered
    env's (:func:`changed_env_kwargs`), e.g. ``it was tuned on the registered env, and this one is
    made with goal_velocity=0.05 (registered: 0)``; None when none differ."""
    changed = changed_env_kwargs(env_id, env_kwargs)
    if not changed:
        return None
    made = ", ".join(f"{name}={value!r} (registered: {registered!r})" for name, (value, registered) in changed.items())
    return f"it was tuned on the registered env, and this one is made with {made}"


def _equal(first: Any, second: Any) -> bool:
    """Equality of kwargs values, a list equal to the tuple or array of the same numbers."""
    try:
        return bool(np.array_equal(np.asarray(first), np.asarray(second)))
    except (TypeError, ValueError):  # values numpy cannot compare
        return first == second


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


def agent_reward(
    reward_fn: RewardSpec | StepReward | None,
    saved_source: str | None,
    env: VecEnv | None,
    env_id: str | None,
    env_kwargs: Mapping[str, Any],
) -> tuple[RewardSpec | None, str]:
    """The reward the agent plans with and its source (:func:`~cme_agent.rewards.resolve_reward`);
    a loaded model keeps the source it was trained with.

    :param reward_fn: the user's reward, or None
    :param saved_source: the source a loaded model was trained with (None: a new agent)
    :param env: the agent's VecEnv, or None
    :param env_id: the env's registered id
    :param env_kwargs: its make-kwargs
    :return: the spec (None: learned) and ``"user"``, ``"known"``, ``"env"`` or ``"learned"``
    """
    if saved_source == "user" and reward_fn is None:
        raise ValueError("this model was trained with a user-supplied reward: pass reward_fn= to load()")
    if saved_source == "learned":
        return None, "learned"
    return resolve_reward(reward_fn, env_id, local_env(env, env_id, env_kwargs, remake=saved_source == "env"))


def reward_message(source: str, name: str) -> str:
    """The log line naming the reward the agent plans with.

    :param source: ``"user"``, ``"known"``, ``"env"`` or ``"learned"``
    :param name: the env's name for messages (:func:`env_name`)
    """
    if source == "learned":
        return (
            f"No reward function is known for env {name}: the reward is learned by regression, on psi with the CME, "
            "on features of s' with the model of the observation (pass reward_fn= for a known one)."
        )
    return f"Planning with the {source} reward of env {name}."
