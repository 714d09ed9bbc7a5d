"""The aggregated transition store D of Algorithm 1.

Transitions live in preallocated tensors whose capacity doubles when full, so appending is
amortised O(1) and memory is linear in |D|. Every consumer reads a fixed-size random sample
(:meth:`TransitionStore.sample`) or the newest block, never the whole store: the cost of an
iteration does not grow with |D|.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class Transitions:
    """A batch of transitions; N is the batch size.

    :param obs: (N, obs_dim) states s
    :param actions: (N, act_dim) Box actions, or (N,) Discrete action indices
    :param rewards: (N,) rewards r
    :param next_obs: (N, obs_dim) successor states s' (the true last state after a time limit)
    :param terminated: (N,) True where s' is terminal (absorbing, value 0)
    """

    obs: torch.Tensor
    actions: torch.Tensor
    rewards: torch.Tensor
    next_obs: torch.Tensor
    terminated: torch.Tensor

    def __len__(self) -> int:
        return int(self.rewards.shape[0])

    def __getitem__(self, rows: slice) -> Transitions:
        """The transitions of a slice of rows (views, no copy)."""
        return Transitions(*(tensor[rows] for tensor in vars(self).values()))

    def concat(self, other: Transitions) -> Transitions:
        """This batch followed by ``other``."""
        pairs = zip(vars(self).values(), vars(other).values(), strict=True)
        return Transitions(*(torch.cat([mine, theirs]) for mine, theirs in pairs))


class TransitionStore:
    """Append-only store of transitions in doubling tensors.

    :param obs_dim: observation dimension
    :param action_shape: () for Discrete actions, (act_dim,) for Box actions
    :param device: torch device of the tensors
    :param capacity: initial capacity (doubled as needed)
    """

    _FIELDS = ("obs", "actions", "rewards", "next_obs", "terminated")

    def __init__(
        self, obs_dim: int, action_shape: tuple[int, ...], device: torch.device | str = "cpu", capacity: int = 1024
    ) -> None:
        self.size = 0
        action_dtype = torch.float32 if action_shape else torch.long
        self._data = {
            "obs": torch.empty(capacity, obs_dim, device=device),
            "actions": torch.empty(capacity, *action_shape, dtype=action_dtype, device=device),
            "rewards": torch.empty(capacity, device=device),
            "next_obs": torch.empty(capacity, obs_dim, device=device),
            "terminated": torch.empty(capacity, dtype=torch.bool, device=device),
        }

    def __len__(self) -> int:
        return self.size

    @property
    def capacity(self) -> int:
        """Number of transitions the tensors can hold before the next doubling."""
        return int(self._data["rewards"].shape[0])

    @property
    def nbytes(self) -> int:
        """Bytes allocated by the store's tensors."""
        return sum(t.element_size() * t.numel() for t in self._data.values())

    def add(
        self, obs: np.ndarray, actions: np.ndarray, rewards: np.ndarray, next_obs: np.ndarray, terminated: np.ndarray
    ) -> None:
        """Append a batch of transitions (arrays with a leading batch dimension)."""
        n = len(rewards)
        if self.size + n > self.capacity:
            self._grow(max(2 * self.capacity, self.size + n))
        batch = dict(zip(self._FIELDS, (obs, actions, rewards, next_obs, terminated), strict=True))
        for name, tensor in self._data.items():
            tensor[self.size : self.size + n] = torch.as_tensor(np.asarray(batch[name]), dtype=tensor.dtype).reshape(
                n, *tensor.shape[1:]
            )
        self.size += n

    def _grow(self, capacity: int) -> None:
        for name, tensor in self._data.items():
            grown = torch.empty(capacity, *tensor.shape[1:], dtype=tensor.dtype, device=tensor.device)
            grown[: self.size] = tensor[: self.size]
            self._data[name] = grown

    def get(self, indices: torch.Tensor | slice) -> Transitions:
        """The transitions at ``indices`` (a LongTensor or a slice within ``[0, len)``)."""
        if isinstance(indices, slice):
            indices = torch.arange(*indices.indices(self.size), device=self._data["rewards"].device)
        return Transitions(**{name: tensor[indices] for name, tensor in self._data.items()})

    def state_dict(self) -> dict[str, torch.Tensor]:
        """The stored transitions (without the spare capacity), for saving."""
        return {name: tensor[: self.size].clone() for name, tensor in self._data.items()}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Replace the contents by a :meth:`state_dict`; shapes and dtypes must match this store."""
        sizes = {int(tensor.shape[0]) for tensor in state.values()}
        if set(state) != set(self._data) or len(sizes) != 1:
            raise ValueError(f"a transition store needs the fields {sorted(self._data)} of one length")
        for name, tensor in self._data.items():
            if state[name].shape[1:] != tensor.shape[1:] or state[name].dtype != tensor.dtype:
                found = f"shape {tuple(state[name].shape)}, dtype {state[name].dtype}"
                raise ValueError(f"stored {name} has {found}; expected rows of {tuple(tensor.shape[1:])}, {tensor.dtype}")
        self.size = 0
        self._data = {name: tensor[:0].clone() for name, tensor in self._data.items()}
        self._grow(max(sizes.pop(), 1))
        for name, tensor in state.items():
            self._data[name][: len(tensor)] = tensor.to(self._data[name].device)
        self.size = len(state["rewards"])

    def sample(self, n: int, generator: torch.Generator) -> Transitions:
        """``n`` transitions drawn uniformly with replacement: O(n), whatever |D|."""
        if self.size == 0:
            raise RuntimeError("cannot sample from an empty transition store")
        indices = torch.randint(self.size, (n,), generator=generator).to(self._data["rewards"].device)
        return self.get(indices)


def vector_step_successors(
    new_obs: np.ndarray, rewards: np.ndarray, dones: np.ndarray, infos: list[dict], step: int
) -> tuple[np.ndarray, np.ndarray]:
    """The successors and termination flags of one VecEnv step: a finished episode's successor
    is its true last observation, and a time-limit truncation is not a termination.

    :param new_obs: (n_envs, obs_dim) what ``VecEnv.step`` returned (reset observations where done)
    :param rewards: (n_envs,) the rewards
    :param dones: (n_envs,) bool, episode ends
    :param infos: the step's infos (``terminal_observation``, ``TimeLimit.truncated``)
    :param step: the agent's env step count, for the error message
    :return: (n_envs, obs_dim) float32 successors and (n_envs,) bool terminations
    :raises ValueError: a non-finite observation or reward, before it reaches the model
    """
    next_obs = np.array(new_obs, dtype=np.float32, copy=True)
    terminated = np.zeros(len(dones), dtype=bool)
    for i, done in enumerate(dones):
        if done:
            next_obs[i] = infos[i]["terminal_observation"]
            terminated[i] = not infos[i].get("TimeLimit.truncated", False)
    for name, values in (("observation", next_obs), ("reward", rewards)):
        bad = ~np.isfinite(np.asarray(values, dtype=np.float64).reshape(len(dones), -1)).all(axis=1)
        if bad.any():
            env_index = int(np.flatnonzero(bad)[0])
            raise ValueError(
                f"the env returned a non-finite {name} at step {step} (env {env_index}): "
                f"{np.asarray(values)[env_index].tolist()}; learning stopped before it reached the model"
            )
    return next_obs, terminated
