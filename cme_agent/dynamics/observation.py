"""A model of the observation itself, the alternative to the CME that planning by lookahead needs.

The CME predicts E[phi(S') | s, a], never S' itself, so it cannot be rolled forward. This model
predicts the next observation, whether the episode goes on and the reward:

- s^' = s + W^T [s, a, 1] (followed by random Fourier features of the standardised (s, a) with
  ``model_update.change_fourier``), W by ridge regression on the non-terminal transitions;
- P(terminated | s') = sigmoid(u^T f(s')), f = [z, z^2, 1] of the standardised s' (a two-sided
  boundary such as |angle| > 0.2 needs the squares), u by L2-regularised logistic regression;
- the reward of going on, r(s', a) = v^T [f(s'), a, a^2, |P^T z + b|, |L (z - c)|], v by ridge regression on the
  non-terminal transitions (a small ridge: a reward quadratic in s' and a stays exact), within the
  range of their rewards, and the mean reward of the terminal ones, r_end: a step is worth
  g r(s', a) + (1 - g) r_end. The last features are M random
  projections of z, each folded at a random offset: a norm is an average of such terms
  (E_w |w^T x| is proportional to |x| for directions w uniform on the sphere), so a reward such as
  -|p' - goal| (a cone, which quadratic features fit badly at its tip) is in their span. The
  directions are drawn in a learned metric: a first fit with directions uniform on the sphere gives the
  reward's gradients in z, their expected outer product M = E[grad grad^T] (the EGOP, large along the
  directions the reward changes with) maps the directions to M w / |M w|, and the reward is fitted
  again on those. A reward of a few of the dims gets all its folds there (PointGoal2D's cone of the
  position: near-goal RMSE 0.006 against 0.032 with the directions uniform in the 4 dims). The folds' kinks
  lie where their offsets fall, so the fitted cone's tip can miss the goal by a few hundredths, and a planner
  rests where the fitted reward peaks: K cones |L (z - c_j)| centred at rows of the fit's data (dense where the
  agent dwells) with L = M^(1/2) put a tip at the data's own states (on a PointGoal2D agent's data the peak
  moved from 0.046 to 0.006 off the goal). Each
  feature is held within the range it had on the data (z per dim, each fold's argument): off the data
  the reward stays at what it was at the data's edge instead of growing linearly, as a planner would
  otherwise find (a cone fitted inside the data rose to its top 2 away from the goal).

Every fit is a fixed-size linear solve (or a few L-BFGS steps) in its feature count: the cost is
linear in the transitions it is given, and the weights are buffers (saved with the module).
Box actions only.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from cme_agent.buffer import Transitions
from cme_agent.linalg import random_cosines

RIDGE = 1e-6
"""Ridge of the least-squares fits, relative to the number of rows."""
REWARD_RIDGE = 1e-8
"""Ridge of the reward's fit: with RIDGE the projections would stand in for part of a quadratic reward
(errors of 5e-3 on a reward quadratic in s'; 5e-5 with this one, and the same fit of a cone)."""
LOGISTIC_L2 = 1e-4
"""L2 weight of the termination's logistic regression (on the mean log-loss)."""
LOGISTIC_ITERATIONS = 200
"""L-BFGS iterations of the termination's fit."""
REWARD_PROJECTIONS = 256
"""M, the folded random projections |P^T z + b| among the reward's features."""
PROJECTION_OFFSET = 2.0
"""The offsets b are uniform in [-PROJECTION_OFFSET, PROJECTION_OFFSET] standard deviations."""
PROJECTION_SEED = 0
"""Seed of the raw directions and b: fixed, so a refit on the same data gives the same P and the agent's RNG is not
drawn from."""
METRIC_ROWS = 2_000
"""Most transitions the first fit and the metric are computed on (evenly spaced among the fit's): the metric
needs the reward's shape, not its detail, and the second fit stays the only one on all of them."""
CHANGE_LENGTH_SCALE = 2.0
"""The length scale of the change model's waves, in standard deviations times sqrt(d): Reacher-v5's change from
random actions, held-out R^2 0.98-1.0 on its joint and fingertip dims (500 waves; linear: below 0.05)."""
METRIC_FLOOR = 1e-6
"""Each eigenvalue of the metric M is at least this fraction of its largest: no direction maps to zero."""
REWARD_CONES = 64
"""K, the cones |L (z - c_j)| among the reward's features, centred at K rows of the fit's data."""
CONE_ROUNDING = 1e-3
"""Each cone is sqrt(|L (z - c_j)|^2 + CONE_ROUNDING^2): its gradient stays finite at its centre (a row of the data)."""


def quadratic(x: torch.Tensor) -> torch.Tensor:
    """[x, x^2, 1]: (N, d) -> (N, 2 d + 1)."""
    return torch.cat([x, x.square(), torch.ones(len(x), 1, dtype=x.dtype)], dim=1)


def affine(obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """[s, a, 1]: (N, obs_dim), (N, act_dim) -> (N, obs_dim + act_dim + 1)."""
    return torch.cat([obs, actions, torch.ones(len(obs), 1, dtype=obs.dtype)], dim=1)


def ridge(features: torch.Tensor, targets: torch.Tensor, scale: float = RIDGE) -> torch.Tensor:
    """argmin_W ||features W - targets||^2 + scale n ||W||^2: (N, f), (N, ...) -> (f, ...)."""
    gram = features.T @ features + scale * len(features) * torch.eye(features.shape[1], dtype=features.dtype)
    return torch.linalg.solve(gram, features.T @ targets)


def logistic(features: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Weights u of P(label 1) = sigmoid(features u), by L-BFGS on the mean log-loss + LOGISTIC_L2 ||u||^2:
    (N, f), (N,) -> (f,)."""
    weights = torch.zeros(features.shape[1], dtype=features.dtype, requires_grad=True)
    optimiser = torch.optim.LBFGS([weights], max_iter=LOGISTIC_ITERATIONS)

    def loss() -> torch.Tensor:
        optimiser.zero_grad()
        value = torch.nn.functional.binary_cross_entropy_with_logits(features @ weights, labels)
        value = value + LOGISTIC_L2 * weights.square().sum()
        value.backward()
        return value

    with torch.enable_grad():
        optimiser.step(loss)
    return weights.detach()


class ChangeFeatures(nn.Module):
    """The inputs of the change model: [s, a, 1], followed by D random Fourier features
    sqrt(2 / D) cos(W x + b) of x = (s, a) standardised per dim and held within its range on the fit's data,
    W ~ N(0, 1 / (CHANGE_LENGTH_SCALE^2 d)), d = obs_dim + act_dim (D = 0: the linear model). The range keeps a
    rolled-out s^' off the data from reaching waves the fit never saw: a dim constant there (InvertedDoublePendulum's
    constraint force) would otherwise turn a 1e-3 error into a thousand standard deviations.

    :param obs_dim: the observation's dims
    :param act_dim: the Box action's dims
    :param n_fourier: D
    """

    def __init__(self, obs_dim: int, act_dim: int, n_fourier: int) -> None:
        super().__init__()
        dims = obs_dim + act_dim
        generator = torch.Generator().manual_seed(PROJECTION_SEED)
        scale = CHANGE_LENGTH_SCALE * dims**0.5
        self.register_buffer("projection", torch.randn(dims, n_fourier, generator=generator, dtype=torch.float64) / scale)
        self.register_buffer("phase", torch.rand(n_fourier, generator=generator, dtype=torch.float64) * 2 * torch.pi)
        self.register_buffer("mean", torch.zeros(dims, dtype=torch.float64))
        self.register_buffer("std", torch.ones(dims, dtype=torch.float64))
        self.register_buffer("input_range", unbounded_range(dims))
        self.width = dims + 1 + n_fourier

    def fit(self, obs: torch.Tensor, actions: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        """Standardise (s, a) on these transitions, keep the range of the standardised inputs, and return W of s' - s
        by ridge regression on the features: (N, obs_dim), (N, act_dim), (N, obs_dim) float64 -> (width, obs_dim)."""
        inputs = torch.cat([obs, actions], dim=1)
        self.mean.copy_(inputs.mean(dim=0))
        self.std.copy_(inputs.std(dim=0).clamp_min(1e-6))
        standardised = (inputs - self.mean) / self.std
        self.input_range.copy_(torch.stack([standardised.min(dim=0).values, standardised.max(dim=0).values]))
        return ridge(self(obs, actions), next_obs - obs)

    def forward(self, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """:param obs: (N, obs_dim). :param actions: (N, act_dim). :return: (N, width)."""
        linear = affine(obs, actions)
        return torch.cat([linear, self.waves(linear)], dim=1) if self.phase.numel() else linear

    def predict(self, obs: torch.Tensor, actions: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        """features(s, a) @ W without stacking the features: (N, obs_dim), (N, act_dim), (width, m) -> (N, m)."""
        linear = affine(obs, actions)
        if not self.phase.numel():
            return linear @ weights
        return torch.addmm(linear @ weights[: linear.shape[1]], self.waves(linear), weights[linear.shape[1] :])

    def waves(self, linear: torch.Tensor) -> torch.Tensor:
        """sqrt(2 / D) cos(W x + b) of [s, a, 1] (N, d + 1), x within its range: (N, D), in place where no gradient is
        taken."""
        standardised = ((linear[:, :-1] - self.mean) / self.std).clamp(*self.input_range)
        waves = random_cosines(standardised, self.projection, self.phase)
        return waves.mul_((2 / self.phase.numel()) ** 0.5)


def change_r2(train: Transitions, holdout: Transitions, n_fourier: int = 0) -> torch.Tensor:
    """Held-out R^2 of the model of the change on :class:`ChangeFeatures` with ``n_fourier`` waves (0: linear), per
    dim: W by ridge regression on ``train``'s non-terminal transitions, R^2 = 1 - SSE / SST of s' - s on
    ``holdout``'s (a dim whose change is constant there counts as explained where W predicts it):
    (obs_dim,) float64. Actions as the model reads them, (N, act_dim).
    """
    fitted, measured = (transition_rows(data, ~data.terminated) for data in (train, holdout))
    features = ChangeFeatures(fitted[0].shape[1], fitted[1].shape[1], n_fourier)
    change = features.fit(*fitted)
    obs, actions, next_obs = measured
    target = next_obs - obs
    errors = (target - features(obs, actions) @ change).square().sum(dim=0)
    spread = (target - target.mean(dim=0)).square().sum(dim=0)
    return 1 - errors / spread.clamp_min(1e-12)


def unbounded_range(dims: int) -> torch.Tensor:
    """The range (-inf, inf) of ``dims`` features: (2, dims) float64, lower bounds first."""
    return torch.tensor([[-torch.inf], [torch.inf]], dtype=torch.float64).repeat(1, dims)


def transition_rows(data: Transitions, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(s, a, s') of ``rows`` of ``data`` in float64, a as (n, act_dim)."""
    obs = data.obs[rows].double()
    return obs, data.actions[rows].double().reshape(len(obs), -1), data.next_obs[rows].double()


class ObservationModel(nn.Module):
    """s^' = s + W^T [s, a, 1]; P(terminated | s') on quadratic features of s'; the reward of going on
    on those, a, a^2, folded random projections and cones in the reward's metric, and of ending (module docstring).

    :param obs_dim: the observation's dims
    :param act_dim: the Box action's dims
    """

    def __init__(self, obs_dim: int, act_dim: int, change_fourier: int = 0) -> None:
        super().__init__()
        self.obs_dim, self.act_dim = obs_dim, act_dim
        state_features = 2 * obs_dim + 1
        self.change_features = ChangeFeatures(obs_dim, act_dim, change_fourier)
        self.register_buffer("change", torch.zeros(self.change_features.width, obs_dim, dtype=torch.float64))
        self.register_buffer("mean", torch.zeros(obs_dim, dtype=torch.float64))
        self.register_buffer("std", torch.ones(obs_dim, dtype=torch.float64))
        generator = torch.Generator().manual_seed(PROJECTION_SEED)
        directions = torch.randn(obs_dim, REWARD_PROJECTIONS, generator=generator, dtype=torch.float64)
        self.register_buffer("directions", directions / directions.norm(dim=0, keepdim=True), persistent=False)
        self.register_buffer("projections", self.directions.clone())
        offsets = (2 * torch.rand(REWARD_PROJECTIONS, generator=generator, dtype=torch.float64) - 1) * PROJECTION_OFFSET
        self.register_buffer("offsets", offsets)
        self.register_buffer("cone_metric", torch.eye(obs_dim, dtype=torch.float64))
        self.register_buffer("cone_centres", torch.zeros(REWARD_CONES, obs_dim, dtype=torch.float64))
        reward_features = state_features + 2 * act_dim + REWARD_PROJECTIONS + REWARD_CONES
        self.register_buffer("reward_weights", torch.zeros(reward_features, dtype=torch.float64))
        self.register_buffer("z_range", unbounded_range(obs_dim))
        self.register_buffer("fold_range", unbounded_range(REWARD_PROJECTIONS))
        self.register_buffer("reward_range", torch.tensor([-torch.inf, torch.inf], dtype=torch.float64))
        self.register_buffer("termination", torch.zeros(state_features, dtype=torch.float64))
        self.register_buffer("terminal_reward", torch.zeros((), dtype=torch.float64))

    def fit(self, data: Transitions) -> None:
        """Fit W, the standardisation of s', v, r_end and u on ``data`` (Box actions (N, act_dim)), in float64."""
        obs, next_obs = data.obs.double(), data.next_obs.double()
        actions = data.actions.double().reshape(len(obs), self.act_dim)
        going_on = ~data.terminated
        self.change.copy_(self.change_features.fit(obs[going_on], actions[going_on], next_obs[going_on]))
        self.mean.copy_(next_obs.mean(dim=0))
        self.std.copy_(next_obs.std(dim=0).clamp_min(1e-6))
        rewards = data.rewards.double()
        self.fit_reward_of_going_on(next_obs[going_on], actions[going_on], rewards[going_on])
        self.terminal_reward.copy_(rewards[~going_on].mean() if (~going_on).any() else torch.zeros((), dtype=torch.float64))
        self.termination.copy_(logistic(quadratic(self.standardise(next_obs)), data.terminated.double()))

    def fit_reward_of_going_on(self, next_obs: torch.Tensor, actions: torch.Tensor, rewards: torch.Tensor) -> None:
        """P and L in the reward's metric (from a first fit on at most METRIC_ROWS evenly spaced transitions; a
        constant reward keeps the raw directions and L = I), the cones' centres at K rows, then v on all the
        transitions, and the range of their rewards: (N, obs_dim), (N, act_dim), (N,) float64, the non-terminal
        transitions."""
        generator = torch.Generator().manual_seed(PROJECTION_SEED)
        self.cone_centres.copy_(self.standardise(next_obs[torch.randint(len(next_obs), (REWARD_CONES,), generator=generator)]))
        self.projections.copy_(self.directions)
        self.cone_metric.copy_(torch.eye(self.obs_dim, dtype=torch.float64))
        if rewards.max() > rewards.min():
            rows = slice(None, None, -(-len(rewards) // METRIC_ROWS))
            self.fit_reward(next_obs[rows], actions[rows], rewards[rows])
            self.set_metric(self.reward_metric(next_obs[rows], actions[rows]))
        self.fit_reward(next_obs, actions, rewards)
        self.reward_range.copy_(torch.stack([rewards.min(), rewards.max()]))

    def fit_reward(self, next_obs: torch.Tensor, actions: torch.Tensor, rewards: torch.Tensor) -> None:
        """v of the reward of going on by ridge regression on its features with the current P and L, and the range
        of z and of each fold's argument there: (N, obs_dim), (N, act_dim), (N,) float64."""
        z = self.standardise(next_obs)
        self.z_range.copy_(torch.stack([z.min(dim=0).values, z.max(dim=0).values]))
        folds = z @ self.projections + self.offsets
        self.fold_range.copy_(torch.stack([folds.min(dim=0).values, folds.max(dim=0).values]))
        self.reward_weights.copy_(ridge(self.reward_features(next_obs, actions), rewards, REWARD_RIDGE))

    def reward_metric(self, next_obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """M = E[grad_z r grad_z r^T] of the fitted reward over the given transitions (the expected gradient outer
        product), its eigenvalues floored at METRIC_FLOOR of the largest and scaled to a largest of 1:
        (N, obs_dim), (N, act_dim) float64 -> (obs_dim, obs_dim)."""
        with torch.enable_grad():
            z = self.standardise(next_obs).requires_grad_(True)
            fitted = self.reward_features(z * self.std + self.mean, actions) @ self.reward_weights
            (gradients,) = torch.autograd.grad(fitted.sum(), z)
        values, vectors = torch.linalg.eigh(gradients.T @ gradients / len(z))
        largest = values.max().clamp_min(torch.finfo(values.dtype).tiny)
        return vectors @ torch.diag(values.clamp_min(METRIC_FLOOR * largest) / largest) @ vectors.T

    def set_metric(self, metric: torch.Tensor) -> None:
        """P = M w / |M w| of the raw directions w and L = M^(1/2): (obs_dim, obs_dim) M, symmetric positive."""
        mapped = metric @ self.directions
        self.projections.copy_(mapped / mapped.norm(dim=0, keepdim=True))
        values, vectors = torch.linalg.eigh(metric)
        self.cone_metric.copy_(vectors @ torch.diag(values.clamp_min(0).sqrt()) @ vectors.T)

    def _load_from_state_dict(self, state_dict: dict[str, torch.Tensor], prefix: str, *args: Any, **kwargs: Any) -> None:
        if prefix + "projections" not in state_dict and prefix + "reward_weights" in state_dict:  # saved before them
            state_dict[prefix + "projections"], state_dict[prefix + "offsets"] = self.projections, self.offsets
            padding = torch.zeros(REWARD_PROJECTIONS, dtype=torch.float64)
            state_dict[prefix + "reward_weights"] = torch.cat([state_dict[prefix + "reward_weights"], padding])
            state_dict[prefix + "reward_range"] = self.reward_range  # and r_end 0 until the next fit
            state_dict[prefix + "terminal_reward"] = self.terminal_reward
        if prefix + "change_features.mean" not in state_dict and prefix + "change" in state_dict:  # saved linear, before them
            fresh = self.change_features.state_dict()
            state_dict.update({f"{prefix}change_features.{name}": value for name, value in fresh.items()})
        if prefix + "change_features.input_range" not in state_dict and prefix + "change" in state_dict:  # saved before it
            state_dict[prefix + "change_features.input_range"] = unbounded_range(self.change_features.mean.numel())
        if prefix + "fold_range" not in state_dict and prefix + "reward_weights" in state_dict:  # saved before the ranges
            state_dict[prefix + "z_range"] = unbounded_range(self.obs_dim)
            state_dict[prefix + "fold_range"] = unbounded_range(REWARD_PROJECTIONS)
        if prefix + "cone_centres" not in state_dict and prefix + "reward_weights" in state_dict:  # saved before the cones
            state_dict[prefix + "cone_metric"], state_dict[prefix + "cone_centres"] = self.cone_metric, self.cone_centres
            padding = torch.zeros(REWARD_CONES, dtype=torch.float64)
            state_dict[prefix + "reward_weights"] = torch.cat([state_dict[prefix + "reward_weights"], padding])
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def standardise(self, next_obs: torch.Tensor) -> torch.Tensor:
        """z = (s' - mean) / std: (N, obs_dim) -> (N, obs_dim)."""
        return (next_obs - self.mean) / self.std

    def reward_parts(self, next_obs: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The blocks of :meth:`reward_features`: [z, z^2, 1] (N, 2 obs_dim + 1), a and a^2 (N, act_dim) each,
        |P^T z + b| (N, M) and the cones |L (z - c_j)| (N, K), z and P^T z + b each within its range on the fit's
        data."""
        z = self.standardise(next_obs).clamp(*self.z_range)
        folds = affine(z, z[:, :0]) @ torch.cat([self.projections, self.offsets[None]])  # one pass over (N, M)
        cones = torch.cdist(z @ self.cone_metric, self.cone_centres @ self.cone_metric).hypot(
            torch.tensor(CONE_ROUNDING, dtype=z.dtype)
        )
        if folds.requires_grad:
            return quadratic(z), actions, actions.square(), folds.clamp(*self.fold_range).abs(), cones
        return quadratic(z), actions, actions.square(), folds.clamp_(*self.fold_range).abs_(), cones

    def reward_features(self, next_obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """[z, z^2, 1, a, a^2, |P^T z + b|, |L (z - c)|] (:meth:`reward_parts`): (N, obs_dim), (N, act_dim) ->
        (N, 2 obs_dim + 1 + 2 act_dim + M + K)."""
        return torch.cat(self.reward_parts(next_obs, actions), dim=1)

    def next_obs(self, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """s^': (N, obs_dim), (N, act_dim) -> (N, obs_dim), float64."""
        obs = obs.double()
        return obs + self.change_features.predict(obs, actions.double(), self.change)

    def terminates(self, next_obs: torch.Tensor) -> torch.Tensor:
        """P(terminated | s'): (N, obs_dim) -> (N,), float64."""
        return torch.sigmoid(quadratic(self.standardise(next_obs.double())) @ self.termination)

    def reward(self, next_obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """r(s', a) of going on, within the range of the rewards it was fitted on (the projections grow linearly off the
        data, and a planner heads for any state it over-rates and shuns any it under-rates): (N, obs_dim),
        (N, act_dim) -> (N,), float64."""
        parts = self.reward_parts(next_obs.double(), actions.double())
        weights = self.reward_weights.split([part.shape[1] for part in parts])
        fitted = sum(part @ weight for part, weight in zip(parts, weights, strict=True))  # the features never stacked
        return fitted.clamp(*self.reward_range)

    def transition(self, obs: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Paired rows, differentiable in both: s^' (N, obs_dim), the probability of going on g (N,) and
        the reward g r(s^', a) + (1 - g) r_end (N,), float64.

        :param obs: (N, obs_dim) observations
        :param actions: (N, act_dim) Box actions
        """
        predicted = self.next_obs(obs, actions)
        going_on = 1 - self.terminates(predicted)
        rewards = going_on * self.reward(predicted, actions) + (1 - going_on) * self.terminal_reward
        return predicted, going_on, rewards

    def step(self, obs: torch.Tensor, candidates: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`transition` of every state with every candidate, state-major: (N K, obs_dim), (N K,)
        and (N K,), float32.

        :param obs: (N, obs_dim) observations
        :param candidates: (K, act_dim) Box actions
        """
        n, k = len(obs), len(candidates)
        actions = candidates.double().reshape(k, self.act_dim).repeat(n, 1)
        return tuple(part.float() for part in self.transition(obs.double().repeat_interleave(k, dim=0), actions))
