"""Pictures of what the agent has learned, and its hyperparameters, in TensorBoard.

Over a 2-D slice of the state box (or the whole box, when the state folds to 1 or 2 dims:
Pendulum's (cos, sin, velocity) is angle x velocity, MountainCar is position x velocity,
ToyChain is the position), four pictures:

- ``pictures/value``: V(s) = max_a Q(s, a), the value of the greedy action;
- ``pictures/greedy_action``: the greedy action (one panel per action dim, or the Discrete index);
- ``pictures/model_error``: the model's squared error ``||y - B psi(s, a)||^2`` on the held-out
  transitions, averaged per cell of the slice (grey: no held-out transition there);
- ``pictures/feature_centres``: the state part of psi's kernel centres.

With ``model_update.kind="observation"`` the value and action are the lookahead's, the model
error is that of s', and there are no feature centres (no psi).

A (cos, sin) angle pair is one coordinate, the angle in radians. On a slice of a higher-dim
state, V and the action are drawn with the other coordinates held fixed (at the box centre,
angle 0, or given values); the held-out errors and the centres cannot be held fixed and are
projected onto the slice. :class:`PictureCallback` draws them every N iterations and logs the
hyperparameters with SB3's ``HParam`` for TensorBoard's HParams tab.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.envs.registration import load_env_creator
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import HParam, Image, TensorBoardOutputFormat

from cme_agent.encoding import ObservationEncoder
from cme_agent.heatmaps import COOLWARM, Axis, category_map, heatmap, number, scatter
from cme_agent.persistence import plain

OBSERVATION_NAMES: dict[str, tuple[str, ...]] = {
    "Pendulum-v1": ("cos theta", "sin theta", "theta dot [rad/s]"),
    "MountainCar-v0": ("position", "velocity"),
    "MountainCarContinuous-v0": ("position", "velocity"),
    "ToyChain-v0": ("position x",),
    "CartPole-v1": ("cart position", "cart velocity", "pole angle [rad]", "pole angular velocity"),
    "Acrobot-v1": ("cos theta1", "sin theta1", "cos theta2", "sin theta2", "theta1 dot", "theta2 dot"),
}
"""Axis names of the observation dims of some envs that do not name them (else ``obs[i]``)."""

ANGLE_NAMES: dict[str, dict[int, str]] = {
    "Pendulum-v1": {0: "theta [rad]"},
    "Acrobot-v1": {0: "theta1 [rad]", 2: "theta2 [rad]"},
}
"""Axis names of angle pairs (keyed by the pair's cos index) of some envs."""

ACTION_NAMES: dict[str, tuple[str, ...]] = {
    "CartPole-v1": ("0: push left", "1: push right"),
    "MountainCar-v0": ("0: push left", "1: no push", "2: push right"),
    "Acrobot-v1": ("0: torque -1", "1: torque 0", "2: torque +1"),
    "ToyChain-v0": ("0: left", "1: stay", "2: right"),
}
"""Legend names of the Discrete actions of some envs (else ``action i``)."""

HOLDOUT_SAMPLES = 8192
"""Held-out transitions (evenly spaced over the store) whose model errors are binned."""

PICTURE_TAGS = ("pictures/value", "pictures/greedy_action", "pictures/model_error", "pictures/feature_centres")
DEFAULT_METRICS = ("eval/mean_reward", "rollout/ep_rew_mean", "train/model_loss")
"""Scalars that TensorBoard's HParams tab shows against the hyperparameters."""


def observation_names(env_id: str | None) -> tuple[str, ...] | None:
    """Axis names of the observation dims of a registered env: those its class declares
    (``observation_names``, as :class:`~cme_agent.envs.quadcopter.QuadcopterEnv` does), else
    :data:`OBSERVATION_NAMES`' (None: neither).

    :param env_id: the env's registered id
    """
    if env_id is not None and env_id in gym.registry:
        entry_point = gym.spec(env_id).entry_point
        try:
            creator = load_env_creator(entry_point) if isinstance(entry_point, str) else entry_point
        except (ImportError, AttributeError):  # an entry point that does not load here
            creator = None
        declared = getattr(creator, "observation_names", None)
        if declared is not None:
            return tuple(declared)
    return OBSERVATION_NAMES.get(env_id)


@dataclass(frozen=True)
class FoldedDim:
    """One coordinate of the folded state: a linear observation dim, or an angle from a (cos, sin) pair.

    :param name: axis name, units included
    :param indices: the observation dims it is made of: ``(i,)`` or the pair ``(cos_index, sin_index)``
    :param low: lower end of the coordinate's range (env units; -pi for an angle)
    :param high: upper end (pi for an angle)
    """

    name: str
    indices: tuple[int, ...]
    low: float
    high: float

    @property
    def is_angle(self) -> bool:
        return len(self.indices) == 2


def folded_dims(
    encoder: ObservationEncoder, names: Sequence[str] | None = None, angle_names: Mapping[int, str] | None = None
) -> list[FoldedDim]:
    """The coordinates of the folded state, in the order of their first observation dim.

    :param encoder: the agent's observation encoder (its box must be known: ``not encoder.needs_fit``)
    :param names: a name per observation dim (default ``obs[i]``)
    :param angle_names: a name per angle pair, keyed by its cos index (default ``angle(obs[i], obs[j]) [rad]``)
    :return: one :class:`FoldedDim` per angle pair and per linear dim
    """
    names = list(names) if names is not None else [f"obs[{i}]" for i in range(encoder.dim)]
    angle_names = angle_names or {}
    center, half = encoder.center.double().cpu().numpy(), encoder.half_range.double().cpu().numpy()
    dims = [
        FoldedDim(angle_names.get(i, f"angle({names[i]}, {names[j]}) [rad]"), (i, j), -math.pi, math.pi)
        for i, j in encoder.angle_pairs
    ]
    dims += [FoldedDim(names[i], (i,), float(center[i] - half[i]), float(center[i] + half[i])) for i in encoder.linear_dims]
    return sorted(dims, key=lambda dim: min(dim.indices))


def choose_dims(dims: Sequence[FoldedDim], picture_dims: Sequence[int] | None) -> list[int]:
    """The (one or two) folded coordinates a picture spans.

    :param dims: the folded coordinates (:func:`folded_dims`)
    :param picture_dims: observation dims (an angle pair is chosen by either of its dims), x
        first; None: the first two coordinates (or the only one)
    :return: indices into ``dims``
    """
    if picture_dims is None:
        return list(range(min(2, len(dims))))
    chosen = []
    for obs_dim in picture_dims:
        matches = [k for k, dim in enumerate(dims) if obs_dim in dim.indices]
        if not matches:
            last = max(max(dim.indices) for dim in dims)
            raise ValueError(f"picture_dims names observation dim {obs_dim}, but the observation has dims 0..{last}")
        chosen.append(matches[0])
    if not 1 <= len(chosen) <= 2 or len(set(chosen)) != len(chosen):
        raise ValueError(
            f"picture_dims={list(picture_dims)} must name one or two different coordinates (an angle pair is one)"
        )
    return chosen


def fold(obs: torch.Tensor, dims: Sequence[FoldedDim]) -> np.ndarray:
    """Folded coordinates of observations: (N, obs_dim) -> (N, len(dims)), angles in radians."""
    columns = [
        torch.atan2(obs[:, dim.indices[1]], obs[:, dim.indices[0]]) if dim.is_angle else obs[:, dim.indices[0]] for dim in dims
    ]
    return torch.stack(columns, dim=1).double().cpu().numpy()


def cell_centres(dim: FoldedDim, n: int) -> np.ndarray:
    """The centres of ``n`` equal cells spanning the coordinate's range: (n,)."""
    edges = np.linspace(dim.low, dim.high, n + 1)
    return (edges[:-1] + edges[1:]) / 2


def grid_observations(
    encoder: ObservationEncoder,
    dims: Sequence[FoldedDim],
    shown: Sequence[int],
    resolution: int,
    fixed: Mapping[int, float] | None = None,
) -> torch.Tensor:
    """Observations at the cell centres of the slice: (ny * nx, obs_dim), row-major with x fastest.

    :param encoder: the observation encoder (its box gives the default values of the other dims)
    :param dims: the folded coordinates
    :param shown: the one or two coordinates (indices into ``dims``) the slice spans, x first
    :param resolution: cells per shown coordinate
    :param fixed: values of the other coordinates, keyed by observation dim (an angle pair by
        either dim, its value in radians); default: the box centre, angle 0
    :return: observations in env units on the encoder's device
    """
    fixed = dict(fixed or {})
    coordinates = []
    for k, dim in enumerate(dims):
        if k in shown:
            coordinates.append(cell_centres(dim, resolution))
        else:
            given = [fixed[i] for i in dim.indices if i in fixed]
            coordinates.append(np.array([given[0] if given else 0.0 if dim.is_angle else (dim.low + dim.high) / 2]))
    order = list(reversed(shown)) + [k for k in range(len(dims)) if k not in shown]  # y slowest, x fastest
    mesh = np.meshgrid(*[coordinates[k] for k in order], indexing="ij")
    points = {k: mesh[position].reshape(-1) for position, k in enumerate(order)}
    obs = np.zeros((points[0].size, encoder.dim), dtype=np.float64)
    for k, dim in enumerate(dims):
        if dim.is_angle:
            obs[:, dim.indices[0]], obs[:, dim.indices[1]] = np.cos(points[k]), np.sin(points[k])
        else:
            obs[:, dim.indices[0]] = points[k]
    return torch.as_tensor(obs, dtype=encoder.center.dtype, device=encoder.center.device)


def bin_mean(coordinates: np.ndarray, values: np.ndarray, dims: Sequence[FoldedDim], resolution: int) -> np.ndarray:
    """Mean of values per cell of a regular grid; NaN where no point fell.

    :param coordinates: (N, k) folded coordinates of the points (k = len(dims), 1 or 2; x first)
    :param values: (N,) values
    :param dims: the k coordinates the grid spans (points outside their ranges are dropped)
    :param resolution: cells per coordinate
    :return: (resolution,) for k = 1, or (resolution, resolution) indexed [y, x] for k = 2
    """
    cells = []
    inside = np.ones(len(values), dtype=bool)
    for column, dim in enumerate(dims):
        position = (coordinates[:, column] - dim.low) / (dim.high - dim.low) * resolution
        inside &= (position >= 0) & (position <= resolution)
        cells.append(np.clip(np.floor(position).astype(np.int64), 0, resolution - 1))
    flat = cells[0] if len(dims) == 1 else cells[1] * resolution + cells[0]
    size = resolution ** len(dims)
    total = np.bincount(flat[inside], weights=values[inside], minlength=size)
    count = np.bincount(flat[inside], minlength=size)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return mean.reshape((resolution,) * len(dims))


def error_resolution(n_points: int, n_dims: int, resolution: int, per_cell: int = 4) -> int:
    """Cells per axis of the held-out error map: about ``per_cell`` points per cell if they
    were spread evenly, between 4 and ``resolution``."""
    return int(np.clip(math.floor((n_points / per_cell) ** (1 / n_dims)), 4, resolution))


def holdout_errors(agent: BaseAlgorithm, max_samples: int = HOLDOUT_SAMPLES) -> tuple[torch.Tensor, np.ndarray]:
    """The model's squared error ``||y - B psi(s, a)||^2`` (in phi's units) on held-out transitions;
    with the model of the observation, its error in s' (:meth:`LookaheadPlanner.prediction_errors`).

    :param agent: a :class:`~cme_agent.CMEPolicyIteration`
    :param max_samples: at most this many transitions, evenly spaced over the held-out store
        (deterministic: no random number is drawn from the agent)
    :return: their states (n, obs_dim) and errors (n,)
    """
    n, lookahead = len(agent.holdout), agent.policy.lookahead
    if n == 0 or (agent.q == 0 and lookahead is None):
        return torch.zeros(0, agent.dynamics.obs_encoder.dim), np.zeros(0)
    indices = torch.linspace(0, n - 1, min(n, max_samples)).round().long().to(agent.device)
    batch = agent.holdout.get(indices)
    if lookahead is not None:
        obs, errors = lookahead.prediction_errors(batch)
        return obs, errors.cpu().numpy()
    psi, targets = agent.dynamics.regression_data(batch)
    errors = ((targets - agent.dynamics.predict(psi)) ** 2).sum(1)
    return batch.obs, errors.double().cpu().numpy()


def _axes(dims: Sequence[FoldedDim], shown: Sequence[int]) -> tuple[Axis, Axis | None]:
    x = Axis(dims[shown[0]].name, dims[shown[0]].low, dims[shown[0]].high)
    y = Axis(dims[shown[1]].name, dims[shown[1]].low, dims[shown[1]].high) if len(shown) == 2 else None
    return x, y


def _slice_note(dims: Sequence[FoldedDim], shown: Sequence[int], fixed: Mapping[int, float] | None) -> str:
    others = [k for k in range(len(dims)) if k not in shown]
    if not others:
        return "the whole state box"
    fixed = fixed or {}
    values = []
    for k in others:
        given = [fixed[i] for i in dims[k].indices if i in fixed]
        value = given[0] if given else 0.0 if dims[k].is_angle else (dims[k].low + dims[k].high) / 2
        values.append(f"{dims[k].name}={value:.3g}")
    return "slice at " + ", ".join(values)


def _action_pictures(
    actions: np.ndarray,
    space: spaces.Space,
    shape: tuple[int, ...],
    axes: tuple[Axis, Axis | None],
    title: list[str],
    names: Sequence[str] | None = None,
) -> np.ndarray:
    """The greedy action map: a Discrete index with a legend, or one panel per Box dim side by side."""
    if isinstance(space, spaces.Discrete):
        if names is None or len(names) != int(space.n):
            names = [f"action {i}" for i in range(int(space.n))]
        return category_map(actions.reshape(shape), names, *axes, ["greedy action (Discrete)", *title])
    panels = [
        heatmap(
            actions[:, d].reshape(shape),
            *axes,
            [f"greedy action [{d}] (env units, bar: the action space)", *title],
            colormap=COOLWARM,
            value_range=(float(space.low[d]), float(space.high[d])),
        )
        for d in range(actions.shape[1])
    ]
    return np.concatenate(panels, axis=1)


@torch.no_grad()
def value_title(agent: BaseAlgorithm) -> str:
    """What the value picture shows: max_a Q, or the lookahead's value."""
    lookahead = agent.policy.lookahead
    if lookahead is None:
        return "V(s) = max_a Q(s, a)"
    return f"L_{lookahead.depth}(s): the best {lookahead.depth}-step lookahead through the model of s', <w, phi> at its leaves"


def agent_pictures(
    agent: BaseAlgorithm,
    picture_dims: Sequence[int] | None = None,
    resolution: int = 64,
    fixed: Mapping[int, float] | None = None,
    names: Sequence[str] | None = None,
) -> dict[str, np.ndarray]:
    """Draw the value, greedy action, held-out model error and feature centres over a slice.

    Nothing is drawn (an empty dict) while the observation box is still to be estimated from
    data. No random number is drawn and no state of the agent changes.

    :param agent: a :class:`~cme_agent.CMEPolicyIteration`
    :param picture_dims: the observation dims of the slice, x first (an angle pair is chosen by
        either of its dims); None: the first two folded coordinates (or the only one)
    :param resolution: cells per axis (V and the action are computed at resolution^2 states)
    :param fixed: values of the coordinates off the slice, keyed by observation dim (an angle
        pair's value in radians); default: the box centre, angle 0
    :param names: axis names of the observation dims (default: the env's, :func:`observation_names`, else ``obs[i]``)
    :return: tag (:data:`PICTURE_TAGS`) -> (H, W, 3) uint8 RGB image
    """
    encoder = agent.dynamics.obs_encoder
    if encoder.needs_fit:
        return {}
    env_id = getattr(agent, "env_id", None)
    known = names or observation_names(env_id)
    known = known if known is not None and len(known) == encoder.dim else None  # a name per dim, or none
    dims = folded_dims(encoder, known, None if names else ANGLE_NAMES.get(env_id))
    shown = choose_dims(dims, picture_dims)
    axes = _axes(dims, shown)
    shape = (resolution,) if len(shown) == 1 else (resolution, resolution)
    head = f"iteration {agent.iteration}, {agent.num_timesteps} steps, q={agent.q}"
    note = [f"{head}; {_slice_note(dims, shown, fixed)}"]
    projected = "" if len(shown) == len(dims) else "; projected onto the slice's axes (other coordinates: any value)"

    obs = grid_observations(encoder, dims, shown, resolution, fixed)
    actions, values = agent.policy.greedy(obs)
    values = values.double().cpu().numpy()
    pictures = {
        "pictures/value": heatmap(values.reshape(shape), *axes, [value_title(agent), *note]),
        "pictures/greedy_action": _action_pictures(
            actions.cpu().numpy(), agent.action_space, shape, axes, note, ACTION_NAMES.get(env_id)
        ),
    }

    held_obs, errors = holdout_errors(agent)
    shown_dims = [dims[k] for k in shown]
    cells = error_resolution(errors.size, len(shown), resolution)
    error_map = bin_mean(fold(held_obs, shown_dims), errors, shown_dims, cells)
    mean = f"{errors.mean():.3g}" if errors.size else "n/a"
    measure = "||y - B psi(s, a)||^2" if agent.policy.lookahead is None else "of s', mean_i ((s'_i - s^'_i) / std_i)^2"
    error_title = (
        f"model error {measure}, mean per cell of {errors.size} held-out transitions (all: {mean}); "
        f"{'x'.join([str(cells)] * len(shown))} cells, log colour, grey: no data"
    )
    pictures["pictures/model_error"] = heatmap(error_map, *axes, [error_title + projected, head], log_scale=True)

    if agent.policy.lookahead is not None:  # no psi: a value and an action looked ahead through the model of s'
        return pictures
    centres = agent.dynamics.psi.centres[:, : agent.dynamics.psi.state_dim]
    centre_obs = encoder.center + centres * encoder.half_range
    coordinates = fold(centre_obs, shown_dims)
    y = coordinates[:, 1] if len(shown) == 2 else None
    bandwidths = (1 / (2 * agent.dynamics.psi.inv_two_sq_bandwidth)).sqrt().double().cpu().numpy()
    values, groups = np.unique(np.round(bandwidths, 6), return_inverse=True)
    names = [f"h = {number(value)}" for value in values]
    what = f"feature centres (state part of psi's {agent.q} kernels; h: bandwidth, normalised units)"
    centre_title = [what + projected, head]
    pictures["pictures/feature_centres"] = scatter(coordinates[:, 0], y, *axes, centre_title, groups, names)
    return pictures


def _flatten(prefix: str, value: Any, out: dict[str, bool | str | float | int]) -> None:
    if isinstance(value, dict):
        for key, item in value.items():
            _flatten(f"{prefix}.{key}" if prefix else str(key), item, out)
    elif isinstance(value, (bool, int, float, str)):
        out[prefix] = value
    else:  # lists, None: shown as text (the HParams tab takes numbers, strings and booleans)
        out[prefix] = str(value)


def agent_hparams(agent: BaseAlgorithm) -> dict[str, bool | str | float | int]:
    """The agent's resolved settings as flat, dotted keys, for SB3's ``HParam``.

    :param agent: a :class:`~cme_agent.CMEPolicyIteration` (or any agent with ``_constructor_kwargs``)
    :return: e.g. ``{"env_id": "Pendulum-v1", "gamma": 0.95, "feature_selection.max_features": 20, ...}``
    """
    settings = plain(agent._constructor_kwargs()) if hasattr(agent, "_constructor_kwargs") else {}
    settings = {key: value for key, value in settings.items() if key not in ("verbose", "tensorboard_log")}
    flat: dict[str, bool | str | float | int] = {
        "algorithm": type(agent).__name__,
        "env_id": str(getattr(agent, "env_id", None)),
    }
    _flatten("", settings, flat)
    return flat


class PictureCallback(BaseCallback):
    """Draw :func:`agent_pictures` into TensorBoard every ``every`` iterations, and log the
    hyperparameters (:func:`agent_hparams`) with SB3's ``HParam`` at the start of training.

    The pictures of iteration k are drawn at the start of iteration k + 1 (``on_rollout_start``)
    and after the last one (``on_training_end``), and written at the step count at which the
    agent logged iteration k's scalars. They are written to the logger's TensorBoard output
    only (images have no place in stdout or CSV); without one, nothing is drawn.

    :param every: iterations between pictures (>= 1)
    :param picture_dims: observation dims of the slice, x first (an angle pair by either of its
        dims); None: the first two folded coordinates
    :param resolution: cells per axis
    :param fixed: values of the coordinates off the slice, keyed by observation dim
    :param hparams: log the hyperparameters at the start of training
    :param metrics: scalar tags the HParams tab shows against the hyperparameters
    :param verbose: 0 silent, 1 a line per drawing
    """

    def __init__(
        self,
        every: int = 10,
        picture_dims: Sequence[int] | None = None,
        resolution: int = 64,
        fixed: Mapping[int, float] | None = None,
        hparams: bool = True,
        metrics: Sequence[str] = DEFAULT_METRICS,
        verbose: int = 0,
    ) -> None:
        super().__init__(verbose)
        if not isinstance(every, int) or every < 1:
            raise ValueError(f"pictures every={every} is invalid: must be an integer >= 1")
        if resolution < 2:
            raise ValueError(f"pictures resolution={resolution} is invalid: must be an integer >= 2")
        self.every, self.resolution = every, resolution
        self.fixed = {int(key): float(value) for key, value in (fixed or {}).items()}  # Hydra keys may be strings
        self.hparams, self.metrics = hparams, tuple(metrics)
        self.picture_dims = None if picture_dims is None else [int(dim) for dim in picture_dims]
        self._drawn_at: int | None = None

    def _tensorboard(self) -> list[TensorBoardOutputFormat]:
        return [output for output in self.logger.output_formats if isinstance(output, TensorBoardOutputFormat)]

    def _on_training_start(self) -> None:
        if self.hparams and self._tensorboard():
            hparam = HParam(agent_hparams(self.model), {metric: 0.0 for metric in self.metrics})
            self.logger.record("hparams", hparam, exclude=("stdout", "log", "json", "csv"))

    def _on_rollout_start(self) -> None:
        if self.model.iteration > 0 and self.model.iteration % self.every == 0:
            self.draw()

    def _on_training_end(self) -> None:
        self.draw()

    def draw(self) -> None:
        """Draw the pictures of the agent as it is now, once per iteration, into TensorBoard."""
        writers = self._tensorboard()
        if not writers or self._drawn_at == self.model.iteration or self.model.iteration == 0:
            return
        pictures = agent_pictures(self.model, self.picture_dims, self.resolution, self.fixed)
        if not pictures:
            return
        self._drawn_at = self.model.iteration
        values = {tag: Image(picture, "HWC") for tag, picture in pictures.items()}
        for writer in writers:
            writer.write(values, dict.fromkeys(values), step=self.model.num_timesteps)
        if self.verbose:
            print(f"pictures of iteration {self.model.iteration} written at step {self.model.num_timesteps}")

    def _on_step(self) -> bool:
        return True
