"""save() / load() / checkpoints of the agent in the safe format of :mod:`cme_agent.serialization`.

The agent contributes two things: its constructor arguments as plain data
(``_constructor_kwargs``) and its counters (``_COUNTERS``). Everything else (the policy with
its model, whose grown tensors load at their saved size q, the RNG states, the exploration
state and, in checkpoints, the transition stores) travels as tensors.
"""

from __future__ import annotations

import dataclasses
import io
import json
import pathlib
from typing import Any, ClassVar, TypeVar

import torch
from stable_baselines3.common.type_aliases import GymEnv
from stable_baselines3.common.utils import check_for_correct_spaces
from torch import nn

from cme_agent.serialization import (
    FORMAT,
    META,
    TENSORS,
    ModelFileError,
    meta_from_bytes,
    model_path,
    read_members,
    space_from_dict,
    space_to_dict,
    tensors_from_bytes,
    tensors_to_bytes,
    write_atomically,
)

SelfPersistent = TypeVar("SelfPersistent", bound="PersistenceMixin")
BUFFER_FORMAT = "cme_agent.replay_buffer/1"
BUFFERS = "buffers.pt"


def plain(value: Any) -> Any:
    """Config dataclasses and tuples as JSON-ready builtins; a module or callable as the marker ``"custom"``."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return plain(dataclasses.asdict(value))
    if isinstance(value, dict):
        return {key: plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(item) for item in value]
    if isinstance(value, nn.Module) or callable(value):
        return "custom"
    return value


def _json_safe(mapping: dict[str, Any]) -> dict[str, Any]:
    """The items of ``mapping`` that survive a JSON round trip (e.g. env kwargs)."""
    safe = {}
    for key, value in mapping.items():
        try:
            json.dumps(value)
        except TypeError:
            continue
        safe[key] = value
    return safe


class PersistenceMixin:
    """Safe ``save``/``load``, ``save_replay_buffer``/``load_replay_buffer`` for CMEPolicyIteration."""

    _COUNTERS: ClassVar[tuple[str, ...]] = (
        "num_timesteps",
        "_episode_num",
        "iteration",
        "reward_source",
        "env_id",
        "seed",
    )

    def _constructor_kwargs(self) -> dict[str, Any]:
        raise NotImplementedError

    @property
    def replay_buffer(self) -> Any:
        """The transition store D (the name SB3's ``CheckpointCallback`` looks for)."""
        return self.store

    def _tensor_state(self, include_buffers: bool) -> dict[str, Any]:
        state: dict[str, Any] = {
            "policy": self.policy.state_dict(),
            "torch_rng": self._torch_rng.get_state(),
        }
        if self._behaviour is not None:
            state["behaviour"] = self._behaviour.state_dict()
        if self.box.pending:
            state["outside_states"] = self.box.pending  # a pending expansion (observation.expand_after)
        if include_buffers:
            state["buffers"] = self._buffer_state()
        return state

    def _buffer_state(self) -> dict[str, Any]:
        return {"store": self.store.state_dict(), "holdout": self.holdout.state_dict()}

    def save(self, path: str | pathlib.Path | io.BufferedIOBase, exclude: Any = None, include: Any = None) -> None:
        """Save the agent to a zip file, atomically.

        :param path: destination (``.zip`` is added when there is no suffix)
        :param exclude: unused (SB3 signature)
        :param include: ``["replay_buffer"]`` also stores the transitions: a checkpoint from
            which ``learn(..., reset_num_timesteps=False)`` continues with nothing lost
        """
        meta = {
            "format": FORMAT,
            "class": type(self).__name__,
            "init": self._constructor_kwargs(),
            "state": {**{name: getattr(self, name) for name in self._COUNTERS}, "model_step_scale": self.trainer.step_scale},
            "env_kwargs": _json_safe(self.env_kwargs),
            "observation_space": space_to_dict(self.observation_space),
            "action_space": space_to_dict(self.action_space),
            "numpy_rng": self._np_rng.bit_generator.state,
        }
        tensors = self._tensor_state(include_buffers=include is not None and "replay_buffer" in include)
        write_atomically(model_path(path), {META: json.dumps(meta).encode(), TENSORS: tensors_to_bytes(tensors)})

    @classmethod
    def load(  # type: ignore[override]
        cls: type[SelfPersistent],
        path: str | pathlib.Path | io.BufferedIOBase,
        env: GymEnv | None = None,
        device: torch.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        **kwargs: Any,
    ) -> SelfPersistent:
        """Load an agent saved by :meth:`save`, without unpickling anything but tensors.

        :param path: the model file
        :param env: the env to continue training on (its spaces must match), or None
        :param device: torch device
        :param custom_objects: unused (SB3 signature)
        :param print_system_info: unused (SB3 signature)
        :param force_reset: unused: a loaded agent always resets its env before learning
        :param kwargs: constructor arguments that cannot be saved: ``reward_fn`` for a model
            trained with a user reward, ``policy_kwargs={"phi": module}`` for a custom phi
        :raises ModelFileError: foreign, truncated or unsafe file, or a mismatching one
        """
        members = read_members(path, (META, TENSORS))
        meta = meta_from_bytes(members[META])
        if meta.get("class") != cls.__name__:
            raise ModelFileError(f"{path} holds a {meta.get('class')}, not a {cls.__name__}: use {meta.get('class')}.load()")
        tensors = tensors_from_bytes(members[TENSORS])
        observation_space = space_from_dict(meta["observation_space"])
        action_space = space_from_dict(meta["action_space"])
        init = cls._merge_unsaved(_as_trained(meta["init"]), kwargs)
        if env is not None:
            env = cls._wrap_env(env, init.get("verbose", 0))
            check_for_correct_spaces(env, observation_space, action_space)
        model = cls("CMEPolicy", env, device=device, _init_setup_model=False, **init)
        model.observation_space, model.action_space = observation_space, action_space
        state = dict(meta["state"])
        step_scale = state.pop("model_step_scale", 1.0)
        for name, value in state.items():
            setattr(model, name, value)
        model.env_kwargs = meta["env_kwargs"]
        model._setup_model()
        model.trainer.step_scale = step_scale
        model._restore(tensors, meta["numpy_rng"])
        return model

    @staticmethod
    def _merge_unsaved(init: dict[str, Any], kwargs: dict[str, Any]) -> dict[str, Any]:
        """Constructor arguments from the file, completed by what the caller passes again."""
        init = {**init, **{key: value for key, value in kwargs.items() if key != "policy_kwargs"}}
        policy_kwargs = dict(init.get("policy_kwargs") or {})
        policy_kwargs.update(kwargs.get("policy_kwargs") or {})
        if policy_kwargs.get("phi") == "custom":
            raise ModelFileError("this model uses a custom phi: pass policy_kwargs={'phi': <the same module>} to load()")
        init["policy_kwargs"] = policy_kwargs
        return init

    def _restore(self, tensors: dict[str, Any], numpy_rng: dict[str, Any]) -> None:
        try:
            if "behaviour" in tensors and self.env is not None:
                self._behaviour = self._make_behaviour()  # draws from the RNG: before its state is restored
                self._behaviour.load_state_dict(tensors["behaviour"])
            self.policy.load_state_dict(tensors["policy"], strict=True)  # resizes the grown tensors to the saved q
            self._torch_rng.set_state(tensors["torch_rng"])
            self.box.pending = list(tensors.get("outside_states", []))
            self._np_rng.bit_generator.state = numpy_rng
        except (RuntimeError, KeyError, TypeError, ValueError) as error:
            raise ModelFileError(f"the model file does not match its own description: {error}") from error
        if "buffers" in tensors:
            self._load_buffer_state(tensors["buffers"])

    def _load_buffer_state(self, state: dict[str, Any]) -> None:
        self.store.load_state_dict(state["store"])
        self.holdout.load_state_dict(state["holdout"])

    def save_replay_buffer(self, path: str | pathlib.Path) -> None:
        """Save the transition stores (D and the held-out transitions) atomically (SB3's convention)."""
        meta = json.dumps({"format": BUFFER_FORMAT}).encode()
        write_atomically(path, {META: meta, BUFFERS: tensors_to_bytes(self._buffer_state())})

    def load_replay_buffer(self, path: str | pathlib.Path, truncate_last_traj: bool = True) -> None:
        """Replace the transition stores by those saved with :meth:`save_replay_buffer`."""
        members = read_members(path, (META, BUFFERS))
        try:
            fmt = json.loads(members[META]).get("format")
        except (json.JSONDecodeError, AttributeError) as error:
            raise ModelFileError(f"{path} is not a cme_agent replay buffer file") from error
        if fmt != BUFFER_FORMAT:
            raise ModelFileError(f"{path} is not a cme_agent replay buffer file (format {fmt!r})")
        self._load_buffer_state(tensors_from_bytes(members[BUFFERS]))


def _as_trained(init: dict[str, Any]) -> dict[str, Any]:
    """The saved constructor arguments, completed with the defaults the file was trained under
    where a later release changed them: a file without ``model_update.method`` (written before
    it existed) learned B by SGD, which its run continues with."""
    model_update = init.get("model_update")
    if isinstance(model_update, dict) and "method" not in model_update:
        return {**init, "model_update": {**model_update, "method": "sgd"}}
    return init
