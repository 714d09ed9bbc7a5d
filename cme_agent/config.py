"""Typed, validated hyperparameter groups of :class:`~cme_agent.CMEPolicyIteration`.

Each group is a frozen dataclass that checks its values on construction, so a bad value fails
when the agent is built, with an error that names the key, the value and the allowed range.
``conf/agent/cme.yaml`` lists every field at its default (a test keeps the two equal); plain
dicts (from Hydra or Python) are converted by :func:`build_config`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

ConfigT = TypeVar("ConfigT")


def check(key: str, value: Any, ok: bool, allowed: str) -> None:
    """Raise a ``ValueError`` naming ``key``, ``value`` and the allowed range unless ``ok``.

    :param key: dotted name of the setting, as a user would write it (``evaluation.l2``)
    :param value: the value given
    :param ok: whether the value is acceptable
    :param allowed: the allowed range, in words (``"in (0, 1)"``)
    """
    if not ok:
        raise ValueError(f"{key}={value!r} is invalid: must be {allowed}")


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def check_positive(key: str, value: Any) -> None:
    """Check that ``value`` is a finite number > 0."""
    check(key, value, _is_number(value) and value > 0, "a finite number > 0")


def check_positive_int(key: str, value: Any) -> None:
    """Check that ``value`` is an integer >= 1."""
    check(key, value, isinstance(value, int) and not isinstance(value, bool) and value >= 1, "an integer >= 1")


def check_non_negative(key: str, value: Any) -> None:
    """Check that ``value`` is a finite number >= 0."""
    check(key, value, _is_number(value) and value >= 0, "a finite number >= 0")


def check_unit_interval(key: str, value: Any, *, open_low: bool = False, open_high: bool = False) -> None:
    """Check that ``value`` lies in the unit interval, with the ends open or closed as asked."""
    low_ok = _is_number(value) and (value > 0 if open_low else value >= 0)
    high_ok = _is_number(value) and (value < 1 if open_high else value <= 1)
    allowed = f"in {'(' if open_low else '['}0, 1{')' if open_high else ']'}"
    check(key, value, low_ok and high_ok, allowed)


def check_choice(key: str, value: Any, choices: Sequence[str]) -> None:
    """Check that ``value`` is one of ``choices``."""
    check(key, value, value in choices, f"one of {list(choices)}")


def check_list(key: str, value: Any) -> None:
    """Check that ``value`` is a list or tuple, naming the key when a scalar was given instead
    (``feature_selection.bandwidths=-0.3`` rather than ``[-0.3]``)."""
    if not isinstance(value, (list, tuple)):
        hint = f" (write [{value!r}] for a single value)" if isinstance(value, (int, float, str)) else ""
        raise ValueError(f"{key}={value!r} is invalid: must be a list{hint}")


@dataclass(frozen=True)
class AgentConfig:
    """The top-level settings of the policy iteration (the constructor arguments outside the groups).

    :param gamma: discount factor in (0, 1)
    :param omega: step of the Q smoothing Q_k = (1 - omega) Q_{k-1} + omega Q^_k, in (0, 1]
    :param steps_per_iteration: m, env steps collected per iteration (all envs together)
    """

    # defaults for an env without a preset (every preset pins its own gamma and omega): on an
    # unseen env (InvertedPendulum-v5) 0.95 and 0.2 learned more than 0.98 and 0.5
    gamma: float = 0.95
    omega: float = 0.2
    steps_per_iteration: int = 200

    def __post_init__(self) -> None:
        check_unit_interval("gamma", self.gamma, open_low=True, open_high=True)
        check_unit_interval("omega", self.omega, open_low=True)
        check_positive_int("steps_per_iteration", self.steps_per_iteration)


@dataclass(frozen=True)
class FeatureSelectionConfig:
    """Matching pursuit over a data-dependent kernel dictionary (paper eq. (5), section 2.2).

    :param bandwidths: widths of the Gaussian kernels of the dictionary, in normalised
        state-action units (each input dimension scaled to [-1, 1], a Box action then times
        ``action_scale``); one atom per new point and bandwidth
    :param threshold: stop when the best atom removes less than this fraction of the
        current residual energy
    :param max_features: cap on the features added per iteration
    :param max_total_features: budget on q: once reached no feature is added, so the cost of an
        iteration stops growing altogether (``inf``: no budget; ``math.inf`` in Python, ``.inf``
        in YAML, ``inf`` on the command line. None is refused: it means 'not given' everywhere)
    :param subsample_size: size of the random subsample of D the residual is measured on
    :param theta: step theta_k in [0, 1] applied to the new weights, B_k = (B_{k-1}, theta B_new)
    :param orthogonal: refit the weights of the picked atoms jointly by least squares
        (orthogonal matching pursuit) instead of keeping the greedy weights
    :param action_scale: weight of a Box action in psi's kernel distances: the action,
        normalised to [-1, 1], is multiplied by it before the kernels, so a kernel of bandwidth h
        spans h / action_scale of the action's normalised range. Below 1 each kernel covers
        more actions, and what the model learns about one action's effect at a state carries to
        its neighbours: the greedy step ranks actions the data hold few of by a smooth model of
        their effect, not by the kernels of the few actions taken there. A Discrete action's
        one-hot is not scaled (its actions have no neighbours)
    :param control_affine: add to the dictionary, per new point and bandwidth, the state kernel
        alone and the state kernel times each normalised action coordinate (for a Discrete
        action, each one-hot entry): psi can then represent a feature change affine in the
        action, f(s) + G(s) a, from few atoms, and extends what one action taught to the others
    """

    bandwidths: tuple[float, ...] = (0.15, 0.3, 0.6)
    threshold: float = 0.002
    max_features: int = 80
    max_total_features: int | float = 2000
    subsample_size: int = 2000
    theta: float = 1.0
    orthogonal: bool = False
    # 1.0: the presets' 0.2 (kernels 5x wider in the action) was not reliably better on an unseen env
    action_scale: float = 1.0
    control_affine: bool = False

    def __post_init__(self) -> None:
        check_list("feature_selection.bandwidths", self.bandwidths)
        check("feature_selection.bandwidths", self.bandwidths, len(self.bandwidths) > 0, "a non-empty list")
        for bandwidth in self.bandwidths:
            check_positive("feature_selection.bandwidths", bandwidth)
        check_unit_interval("feature_selection.threshold", self.threshold, open_low=True, open_high=True)
        check_positive_int("feature_selection.max_features", self.max_features)
        budget = self.max_total_features
        check(
            "feature_selection.max_total_features",
            budget,
            budget == math.inf or (isinstance(budget, int) and not isinstance(budget, bool) and budget >= 1),
            "an integer >= 1, or inf (write inf for no budget)",
        )
        check_positive_int("feature_selection.subsample_size", self.subsample_size)
        check_unit_interval("feature_selection.theta", self.theta, open_low=True)
        check_positive("feature_selection.action_scale", self.action_scale)
        check("feature_selection.control_affine", self.control_affine, isinstance(self.control_affine, bool), "a bool")


MODEL_UPDATE_L2 = {"sgd": 1e-6, "ridge": 1e-4}
"""How B is learned each iteration (``model_update.method``), and the default ridge of each."""
MODEL_UPDATE_METHODS = tuple(MODEL_UPDATE_L2)
MODEL_KINDS = ("auto", "cme", "observation")
"""What the agent models (``model_update.kind``): the paper's CME of phi, the observation itself, or
the one the first data points to."""


@dataclass(frozen=True)
class ModelUpdateConfig:
    """How B is learned each iteration: the paper's stochastic gradient descent on the
    regularised loss (eq. (6)), or its exact minimiser on a fixed-size sample of D.

    :param method: ``"ridge"`` (B minimising loss (4) plus the ridge of eq. (6) exactly, solved
        from its normal equations on ``refit_size`` transitions of D, all of D while it holds
        fewer: O(refit_size q (q + p) + q^3) an iteration, flat in |D|) or ``"sgd"`` (eq. (6),
        the paper's online update: ``n_steps`` minibatch steps from the current B). The exact
        fit is the default: it learned faster than SGD on CartPole-v1 and Acrobot-v1
    :param refit_size: transitions of D that ``method="ridge"`` fits B on, and that B is refit
        on when the observation box expands
    :param n_steps: SGD steps per iteration (each on a minibatch drawn from D)
    :param batch_size: transitions per minibatch
    :param learning_rate: normalised step size in (0, 2): the step is
        ``learning_rate / mean ||psi||^2`` (normalised least mean squares), stable for any q
    :param l2: ridge coefficient lambda of eq. (6) (None: :data:`MODEL_UPDATE_L2` of ``method``,
        1e-6 for ``"sgd"``, whose few steps from the last B regularise it already, 1e-4 for
        ``"ridge"``, whose exact solve has only lambda)
    :param holdout_fraction: fraction of the collected transitions kept out of training, on
        which ``train/model_loss`` is measured
    :param holdout_size: held-out transitions sampled per iteration to measure the loss
    :param feature_dynamics: regress phi(s') - phi(s) (section 2.3) instead of phi(s')
    :param kind: ``"cme"`` (the paper's model, E[phi(S') | s, a] ~ B psi(s, a), with ``method``)
        or ``"observation"`` (the next observation, termination and reward,
        :class:`~cme_agent.dynamics.observation.ObservationModel`, refit each iteration on
        ``refit_size`` transitions of D; it can be rolled forward, so acting looks
        ``action_search.lookahead_depth`` steps ahead, :class:`~cme_agent.lookahead.LookaheadPlanner`)
        or ``"auto"``, chosen at the first iteration: ``"observation"`` where a linear model of
        s' - s reaches a held-out R^2 of ``auto_r2`` on every dim, else ``"cme"`` (and ``"cme"``
        with the soft improvement, which is the CME's)
    :param auto_r2: the held-out R^2 in (0, 1] that ``kind="auto"`` asks of every dim
    :param change_fourier: random Fourier features ("waves") of the standardised (s, a) beside [s, a, 1] in the model
        of the observation's change (0: linear; 500, with ``kind="observation"``: Reacher-v5 -6.8 at 5,000 steps against the
        CME's -11.6, InvertedDoublePendulum-v5 below the CME)
    """

    method: str = "ridge"
    refit_size: int = 20_000
    n_steps: int = 200
    batch_size: int = 128
    learning_rate: float = 0.5
    l2: float | None = None
    holdout_fraction: float = 0.1
    holdout_size: int = 1000
    feature_dynamics: bool = True
    kind: str = "auto"
    auto_r2: float = 0.99
    change_fourier: int = 0

    def __post_init__(self) -> None:
        check_choice("model_update.method", self.method, MODEL_UPDATE_METHODS)
        check_choice("model_update.kind", self.kind, MODEL_KINDS)
        check_unit_interval("model_update.auto_r2", self.auto_r2, open_low=True)
        check_positive_int("model_update.refit_size", self.refit_size)
        waves = self.change_fourier
        check(
            "model_update.change_fourier",
            waves,
            isinstance(waves, int) and not isinstance(waves, bool) and waves >= 0,
            "an integer >= 0",
        )
        if self.l2 is None:  # frozen: the method's ridge is written in once, so the config says what ran
            object.__setattr__(self, "l2", MODEL_UPDATE_L2[self.method])
        check_positive_int("model_update.n_steps", self.n_steps)
        check_positive_int("model_update.batch_size", self.batch_size)
        check(
            "model_update.learning_rate",
            self.learning_rate,
            _is_number(self.learning_rate) and 0 < self.learning_rate < 2,
            "in (0, 2)",
        )
        check_non_negative("model_update.l2", self.l2)
        check_unit_interval("model_update.holdout_fraction", self.holdout_fraction, open_high=True)
        check_positive_int("model_update.holdout_size", self.holdout_size)


MIN_COLLECTION_SIZE = 2000
"""Smallest default |C|: below it the uniform and data halves of C are thin."""
COLLECTION_PER_FEATURE = 10
"""Default |C| per feature of phi: a well-determined evaluation (|C| >= 10 p)."""
MAX_COLLECTION_SIZE = 20_000
"""Cap of the default |C|: past it the evaluation is solved in its dual form instead."""


@dataclass(frozen=True)
class EvaluationConfig:
    """Policy evaluation on a collection C of states (paper eq. (7)).

    The Bellman residual of eq. (7) is minimised exactly (regularised least squares, in its dual
    form when |C| < p).

    :param collection_size: number of states in C (None: follows the width p of phi, see
        :func:`collection_size_for`)
    :param uniform_fraction: fraction of C drawn uniformly over the state box; the rest is
        drawn from the states in D
    :param l2: ridge coefficient, relative to the mean diagonal of the normal equations
    :param rounds: evaluation/improvement rounds per iteration on the same model
    """

    collection_size: int | None = None
    uniform_fraction: float = 0.5
    l2: float = 1e-4
    rounds: int = 5

    def __post_init__(self) -> None:
        if self.collection_size is not None:
            check_positive_int("evaluation.collection_size", self.collection_size)
        check_unit_interval("evaluation.uniform_fraction", self.uniform_fraction)
        check_positive("evaluation.l2", self.l2)
        check_positive_int("evaluation.rounds", self.rounds)


def collection_size_for(width: int, config: EvaluationConfig) -> int:
    """|C| for a phi of width p: the configured size, or by default
    ``min(max(2,000, 10 p), 20,000)`` (at least 10 states per feature within the cap).

    :param width: p, the width of phi (constant feature included)
    :param config: the evaluation settings
    :return: the number of states in C
    """
    if config.collection_size is not None:
        return config.collection_size
    return min(max(MIN_COLLECTION_SIZE, COLLECTION_PER_FEATURE * width), MAX_COLLECTION_SIZE)


IMPROVEMENT_METHODS = ("smoothed_greedy", "soft")
"""The policy improvement steps: the paper's greedy step on the smoothed Q, and KL-regularised
(softmax) policy iteration."""


@dataclass(frozen=True)
class ImprovementConfig:
    """Policy improvement: the paper's smoothed greedy step or KL-regularised (softmax) policy iteration.

    ``"smoothed_greedy"`` (section 2.2): Q_k = (1 - omega) Q_{k-1} + omega Q^_k and
    pi_{k+1} = greedy(Q_k). ``"soft"`` (Politex, Abbasi-Yadkori et al. 2019; Vieillard et al.
    2020): pi_{k+1}(a|s) proportional to exp(beta_k / n_k * sum_{j<=k} decay^{k-j} Q^_j(s, a))
    over the candidate actions, n_k = sum_{j<=k} decay^{k-j} (= k without decay): mirror
    descent on the policy, pi_{k+1} proportional to pi_k^decay exp(eta Q^_k) (KL-regularised,
    and entropy-regularised when decay < 1). The policy keeps the weighted average
    Qbar_k = (1/n_k) sum_j decay^{k-j} Q^_j (omega is not used) and an inverse temperature
    beta_k on it. Acting (``predict(deterministic=True)``) takes the argmax of Qbar_k, which
    is the argmax of the summed Q.

    :param method: ``"smoothed_greedy"`` (the paper's, the default) or ``"soft"``
    :param beta: soft only: beta_k = beta * n_k / sigma_k, sigma_k the spread of Qbar_k over the
        candidates (:func:`cme_agent.planning.action_spread`): a candidate one spread better than
        the average gets e^{beta} times its weight per improvement, whatever the reward's unit
    :param decay: soft only, in (0, 1]: weight of the past sum per improvement (1: the plain
        sum, every estimate kept; below 1 the policy forgets estimates of older models over
        about 1 / (1 - decay) improvements and its beta_k stops growing at beta / (1 - decay))
    """

    method: str = "smoothed_greedy"
    # beta 0.5, decay 0.9 (on Pendulum-v1's preset): beta 1.0 collapsed on a seed; the plain sum
    # (decay 1) learns too slowly, as the estimates of early, poor models keep their weight
    beta: float = 0.5
    decay: float = 0.9

    def __post_init__(self) -> None:
        check_choice("improvement.method", self.method, IMPROVEMENT_METHODS)
        check_positive("improvement.beta", self.beta)
        check_unit_interval("improvement.decay", self.decay, open_low=True)


@dataclass(frozen=True)
class ExplorationConfig:
    """Behaviour policy of data acquisition: the greedy policy mixed with a noisy version.

    :param random_steps: env steps of uniformly random actions before the first greedy ones
    :param explore_fraction: probability that an episode is run with the exploratory policy
    :param noise_std: Box actions: std of the Gaussian noise added in exploratory episodes,
        as a fraction of the half-range of each action dimension
    :param epsilon: Discrete actions: probability of a uniformly random action per step in
        exploratory episodes
    :param repeat: temporally extended exploration: random actions are held for this many
        steps and Box noise has this correlation time (1: independent per step)
    """

    random_steps: int = 400
    explore_fraction: float = 0.3
    noise_std: float = 0.3
    epsilon: float = 0.3
    repeat: int = 1

    def __post_init__(self) -> None:
        check(
            "exploration.random_steps",
            self.random_steps,
            isinstance(self.random_steps, int) and self.random_steps >= 0,
            "an integer >= 0",
        )
        check_unit_interval("exploration.explore_fraction", self.explore_fraction)
        check_non_negative("exploration.noise_std", self.noise_std)
        check_unit_interval("exploration.epsilon", self.epsilon)
        check_positive_int("exploration.repeat", self.repeat)


@dataclass(frozen=True)
class StateFeatureConfig:
    """The state feature map phi on which values are linear, V(s) = <w, phi(s)>.

    :param kind: ``"auto"`` (an RBF grid where one of a useful resolution fits ``max_width``,
        random Fourier features beyond; see :func:`cme_agent.state_features.make_state_features`),
        ``"rbf_grid"`` (Gaussian bumps on a grid over the normalised observation; angles
        periodic) or ``"fourier"`` (random Fourier features)
    :param resolution: grid points per grid dimension (one int for all, or one per
        dimension; an angle given as (cos, sin) is one periodic dimension); None: the largest
        up to 11 per dimension whose grid fits ``max_width``. Given, it also makes ``"auto"``
        a grid.
    :param max_width: budget on p, the width of phi (constant feature included), that the
        defaults respect; explicit ``resolution`` or ``n_fourier`` may exceed it
    :param width: RBF width in grid spacings
    :param n_fourier: number of random Fourier features (None: ``max_width - 1``)
    :param bandwidth: length scale of the random Fourier features, in the units of ``metric``
        (None: ``max(0.3, 0.1 obs_dim)`` box units, or ``0.4 sqrt(obs_dim)`` standard deviations)
    :param metric: the coordinates the random Fourier features measure length in: ``"box"``
        (the observation normalised by its box, as psi's kernels) or ``"data"`` (each dim
        centred and divided by its standard deviation in the data, fitted on the first data and
        refit when the observation box expands; a dim constant in the data is left out until
        then). Grids are always on the box.
    """

    kind: str = "auto"
    resolution: tuple[int, ...] | None = None
    max_width: int = 1000
    width: float = 1.0
    n_fourier: int | None = None
    bandwidth: float | None = None
    metric: str = "box"

    def __post_init__(self) -> None:
        check_choice("phi.kind", self.kind, ("auto", "rbf_grid", "fourier"))
        check_choice("phi.metric", self.metric, ("box", "data"))
        if isinstance(self.resolution, int) and not isinstance(self.resolution, bool):
            object.__setattr__(self, "resolution", (self.resolution,))  # one value for all dims
        if self.resolution is not None:
            check_list("phi.resolution", self.resolution)
            check("phi.resolution", self.resolution, len(self.resolution) > 0, "a non-empty list")
            for points in self.resolution:
                check("phi.resolution", points, isinstance(points, int) and points >= 2, "integers >= 2")
        check(
            "phi.max_width",
            self.max_width,
            isinstance(self.max_width, int) and not isinstance(self.max_width, bool) and self.max_width >= 2,
            "an integer >= 2",
        )
        check_positive("phi.width", self.width)
        if self.n_fourier is not None:
            check_positive_int("phi.n_fourier", self.n_fourier)
        if self.bandwidth is not None:
            check_positive("phi.bandwidth", self.bandwidth)


LOOKAHEAD_REFINE_STEPS = 5
"""Default refinement steps of the lookahead's first action: its grid of 3 per dim cost PointGoal2D about 3.5 of
return against the refined action (the CME keeps 0: its presets were measured without)."""


@dataclass(frozen=True)
class ActionSearchConfig:
    """How greedy actions are found for Box action spaces (Discrete ones are enumerated).

    :param grid_size: candidates per action dimension on a regular grid, used when the action
        has at most ``max_grid_dims`` dimensions
    :param grid_points: the grid's values per action dimension instead, in normalised units
        [-1, 1] (e.g. ``[-1, -0.2, 0, 0.2, 1]``: small actions beside the full push); None: the
        regular grid of ``grid_size``
    :param max_grid_dims: largest action dimension searched on a grid
    :param n_samples: uniformly sampled candidates (fixed at construction) in higher dimensions
    :param refine_steps: steps of :func:`~cme_agent.action_search.projected_ascent` from the best candidate, on Q
        through psi (the CME) or on the first action's looked-ahead value through the model of the observation;
        None: :data:`LOOKAHEAD_REFINE_STEPS` with the model of the observation where its reward varies, else 0
    :param refine_lr: step of the refinement, in normalised action units
    :param lookahead_depth: env steps the action looks ahead through the model of the
        observation (``model_update.kind="observation"`` only; 1: greedy on Q); None: 3 where
        the K^3 leaves of K candidates are at most 1,000, else 1
    """

    # 3 per dim (full push either way, or none): the greedy step ranks far-apart actions, where the
    # model's errors matter less than between neighbours of a fine grid (an env whose control cost
    # wants small actions, or a preset such as Pendulum-v1's, sets more)
    grid_size: int = 3
    grid_points: tuple[float, ...] | None = None
    max_grid_dims: int = 2
    n_samples: int = 256
    refine_steps: int | None = None
    refine_lr: float = 0.05
    lookahead_depth: int | None = None

    def __post_init__(self) -> None:
        check(
            "action_search.grid_size",
            self.grid_size,
            isinstance(self.grid_size, int) and self.grid_size >= 2,
            "an integer >= 2",
        )
        if self.grid_points is not None:
            check_list("action_search.grid_points", self.grid_points)
            points = list(self.grid_points)
            check(
                "action_search.grid_points",
                self.grid_points,
                len(points) >= 2 and all(_is_number(x) and -1 <= x <= 1 for x in points) and len(set(points)) == len(points),
                "a list of at least 2 distinct numbers in [-1, 1] (normalised action units)",
            )
        check_positive_int("action_search.max_grid_dims", self.max_grid_dims)
        check_positive_int("action_search.n_samples", self.n_samples)
        check(
            "action_search.refine_steps",
            self.refine_steps,
            self.refine_steps is None or (isinstance(self.refine_steps, int) and self.refine_steps >= 0),
            "an integer >= 0, or null (the default: 5 with the model of the observation where its reward varies, else 0)",
        )
        check_positive("action_search.refine_lr", self.refine_lr)
        if self.lookahead_depth is not None:
            check_positive_int("action_search.lookahead_depth", self.lookahead_depth)


@dataclass(frozen=True)
class ObservationConfig:
    """How observations are normalised to [-1, 1] per dimension.

    Dims whose bounds are neither given here nor usable in the space (infinite, or a
    half-range above ``max_half_range``) get a box estimated from the first data: the
    ``quantile`` and ``1 - quantile`` quantiles widened by ``margin`` of their range on each
    side, then frozen (:meth:`cme_agent.encoding.ObservationEncoder.fit`).

    :param low: lower bound per dimension, env units (default: the observation space's, when
        usable; else estimated from data)
    :param high: upper bound per dimension, env units (default: as ``low``)
    :param angle_pairs: index pairs (i, j) of observation dims holding (cos, sin) of an angle;
        phi treats each as one periodic dimension
    :param quantile: lower quantile of the estimated box, in (0, 0.5)
    :param margin: widening of the estimated box on each side, as a fraction of its range
    :param max_half_range: space bounds with a wider half-range (env units) are treated as
        unknown
    :param expand_outside: when more than this share of an iteration's new observations lies
        outside the estimated box (in some estimated dim), the box is expanded to cover those observations, the
        model carried into the new coordinates (psi's centres moved, B refit on D) and planning
        restarted (:meth:`cme_agent.dynamics.CMEDynamics.expand_observation_box`); in (0, 1]
    :param expand_after: expand only when this many successive iterations had more than
        ``expand_outside`` of their new observations outside, to cover all of theirs (1: the
        first such iteration expands it; 2, the default: one policy's excursion that the next
        policy does not repeat leaves the box, and phi's resolution, as they are)
    :param max_expansions: at most this many expansions per run (0: the first box is final)
    """

    low: tuple[float, ...] | None = None
    high: tuple[float, ...] | None = None
    angle_pairs: tuple[tuple[int, int], ...] = field(default_factory=tuple)
    quantile: float = 0.01
    margin: float = 0.1
    max_half_range: float = 1e3
    expand_outside: float = 0.05
    expand_after: int = 2
    max_expansions: int = 4

    def __post_init__(self) -> None:
        for name, bound in (("observation.low", self.low), ("observation.high", self.high)):
            if bound is not None:
                check_list(name, bound)
                for value in bound:
                    check(name, bound, _is_number(value), "a list of finite numbers")
        if self.low is not None and self.high is not None:
            check("observation.low", self.low, len(self.low) == len(self.high), "as long as observation.high")
            for lo, hi in zip(self.low, self.high, strict=True):
                check("observation.high", self.high, hi > lo, "> observation.low in every dim")
        check_list("observation.angle_pairs", self.angle_pairs)
        for pair in self.angle_pairs:
            check(
                "observation.angle_pairs",
                self.angle_pairs,
                isinstance(pair, (list, tuple)) and len(pair) == 2 and pair[0] != pair[1],
                "pairs of distinct indices",
            )
        check(
            "observation.quantile",
            self.quantile,
            _is_number(self.quantile) and 0 <= self.quantile < 0.5,
            "in [0, 0.5)",
        )
        check_non_negative("observation.margin", self.margin)
        check_positive("observation.max_half_range", self.max_half_range)
        check_unit_interval("observation.expand_outside", self.expand_outside, open_low=True)
        check(
            "observation.expand_after",
            self.expand_after,
            isinstance(self.expand_after, int) and not isinstance(self.expand_after, bool) and self.expand_after >= 1,
            "an integer >= 1",
        )
        check(
            "observation.max_expansions",
            self.max_expansions,
            isinstance(self.max_expansions, int) and not isinstance(self.max_expansions, bool) and self.max_expansions >= 0,
            "an integer >= 0",
        )


def _as_tuple(value: Any) -> Any:
    """Lists (from YAML or OmegaConf) to tuples, recursively, so configs are hashable."""
    if isinstance(value, (list, tuple)) or (hasattr(value, "__iter__") and type(value).__name__ == "ListConfig"):
        return tuple(_as_tuple(item) for item in value)
    return value


def build_config(cls: type[ConfigT], value: ConfigT | Mapping[str, Any] | None, group: str) -> ConfigT:
    """Build the dataclass ``cls`` from an instance, a mapping of its fields, or ``None``.

    :param cls: the config dataclass
    :param value: an instance (returned as is), a mapping (unknown keys refused), or None
        (defaults)
    :param group: the group's name, used in error messages
    :return: the validated config
    """
    if value is None:
        return cls()
    if isinstance(value, cls):
        return value
    if not isinstance(value, Mapping) and type(value).__name__ != "DictConfig":
        raise TypeError(f"{group} must be a mapping or a {cls.__name__}, got {type(value).__name__}")
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(value.keys()) - names)
    if unknown:
        raise ValueError(f"{group} has unknown key(s) {unknown}; known keys: {sorted(names)}")
    return cls(**{key: _as_tuple(item) for key, item in value.items()})


def as_dict(config: Any) -> dict[str, Any]:
    """A config dataclass as a plain dict of builtins (for saving and logging)."""
    return dataclasses.asdict(config)
