"""Planning and acting through a model of the observation (``model_update.kind="observation"``).

The CME predicts E[phi(S') | s, a], which cannot be rolled forward; the
:class:`~cme_agent.dynamics.observation.ObservationModel` predicts s^' itself, whether the
episode goes on (g = 1 - P(terminated | s^')) and the reward. Through it:

- policy evaluation is eq. (7) with ``E[phi~(S') | s, a] = g phi(s^')`` at the greedy candidate,
  ``a = argmax_a r + gamma g <w, phi(s^')>`` under the current (smoothed) w;
- improvement smooths the value weights, w_k = (1 - omega) w_{k-1} + omega w^_k (section 2.2 on V);
- acting looks d steps ahead over the K candidates (K^d leaves) with V = <w, phi> at the leaves:
  ``L_0(s) = <w, phi(s)>, L_d(s) = max_a [r(s, a) + gamma g(s^'_a) L_{d-1}(s^'_a)]``; d = 1 is the
  greedy step. Greedy acting on eq. (7)'s value is fragile where three looked-ahead steps are not
  (docs/results.md, the planner in the loop).

A known reward (:class:`~cme_agent.rewards.RewardSpec`) replaces the learned one, and its
``is_terminal`` the learned termination. Discrete actions enter the model one-hot.
"""

from __future__ import annotations

import dataclasses

import torch
from gymnasium import spaces
from stable_baselines3.common.logger import Logger
from torch import nn

from cme_agent.buffer import Transitions
from cme_agent.dynamics.observation import ObservationModel, change_r2
from cme_agent.planning import bellman_residual_rms, bellman_residual_weights, smooth
from cme_agent.rewards import RewardSpec
from cme_agent.state_features import StateFeatureMap

MAX_LEAVES = 1000
"""Largest K^d of the default lookahead depth (:func:`default_depth`)."""
DEFAULT_DEPTH = 3
"""The default lookahead depth where its K^d leaves are at most :data:`MAX_LEAVES`."""
LEAF_LIMIT = 10**6
"""Most K^d leaves a lookahead depth d may have (each leaf is a model step and a phi row per action)."""
BLOCK_ROWS = 4096
"""Next states whose phi is built at once (phi (rows, p) in float32 at p = 1,000: 16 MiB)."""
PLANNING_PAIRS = 2**17
"""State-candidate pairs eq. (7)'s greedy step compares per round at most: with |C| states it
compares a fresh draw of PLANNING_PAIRS // |C| of the candidates each round (all of them when that
many fit). Each pair costs a phi evaluation: 257 candidates at 10,000 states would be 2.6 million
phi rows a round. Acting compares all of them."""
STEP_ROWS = 2**15
"""State-candidate pairs the model steps at once (its float64 features: 32 MiB per 128 of them)."""


def default_depth(n_candidates: int) -> int:
    """:data:`DEFAULT_DEPTH` where ``n_candidates ** DEFAULT_DEPTH <= MAX_LEAVES``, else 1 (greedy)."""
    return DEFAULT_DEPTH if n_candidates**DEFAULT_DEPTH <= MAX_LEAVES else 1


def blocked_values(phi: StateFeatureMap, states: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """<w, phi(s)> at many states, phi built :data:`BLOCK_ROWS` rows at a time: (M, obs_dim) -> (M,)."""
    return torch.cat([phi.values(states[start : start + BLOCK_ROWS], weights) for start in range(0, len(states), BLOCK_ROWS)])


class LookaheadPlanner(nn.Module):
    """The model of the observation, the value weights w and the procedures that use them (module docstring).

    :param obs_dim: the observation's dims
    :param action_space: a 1-D Box or a Discrete
    :param width: p, the width of phi
    :param depth: d >= 1, env steps acting looks ahead
    :param gamma: discount factor of planning and acting
    :param reward: the known reward (None: the model's learned reward and termination)
    :param change_fourier: the waves of the model's change (0: linear)
    """

    def __init__(
        self,
        obs_dim: int,
        action_space: spaces.Space,
        width: int,
        depth: int,
        gamma: float,
        reward: RewardSpec | None,
        change_fourier: int = 0,
    ) -> None:
        super().__init__()
        if depth < 1:
            raise ValueError(f"lookahead depth={depth} is invalid: must be >= 1")
        self.n_actions = int(action_space.n) if isinstance(action_space, spaces.Discrete) else None
        self.model = ObservationModel(obs_dim, self.n_actions or int(action_space.shape[0]), change_fourier)
        self.register_buffer("value_weights", torch.zeros(width))
        self.depth, self.gamma, self.reward_spec = depth, gamma, reward

    @property
    def reward_varies(self) -> bool:
        """Whether the reward planning sees varies: the env's known reward, or a learned one fitted on unequal rewards."""
        return self.reward_spec is not None or bool(self.model.reward_range[1] > self.model.reward_range[0])

    def model_actions(self, actions: torch.Tensor) -> torch.Tensor:
        """Actions as the model reads them: Box (N, act_dim) as they are, Discrete (N,) one-hot (N, n), float64."""
        if self.n_actions is None:
            return actions.double().reshape(len(actions), -1)
        return nn.functional.one_hot(actions.long(), self.n_actions).double()

    def fit(self, data: Transitions, holdout: Transitions | None = None, logger: Logger | None = None) -> None:
        """Refit the model on ``data`` (a fixed-size sample of D: the cost is flat in |D|), and log
        its :meth:`holdout_error` on ``holdout`` as ``train/model_loss``."""
        self.model.fit(dataclasses.replace(data, actions=self.model_actions(data.actions)))
        if holdout is not None and logger is not None:
            logger.record("train/model_loss", self.holdout_error(holdout))

    def change_r2(self, train: Transitions, holdout: Transitions) -> torch.Tensor:
        """:func:`~cme_agent.dynamics.observation.change_r2` with the actions as the model reads them: (obs_dim,)."""
        return change_r2(*(dataclasses.replace(data, actions=self.model_actions(data.actions)) for data in (train, holdout)))

    @torch.no_grad()
    def prediction_errors(self, data: Transitions) -> tuple[torch.Tensor, torch.Tensor]:
        """The squared error of s^' per transition, mean over dims in units of s''s std, on the
        non-terminal transitions of ``data``: their states (n, obs_dim) and errors (n,), float64."""
        going_on = ~data.terminated
        predicted = self.model.next_obs(data.obs[going_on], self.model_actions(data.actions[going_on]))
        return data.obs[going_on], ((predicted - data.next_obs[going_on].double()) / self.model.std).square().mean(dim=1)

    def holdout_error(self, data: Transitions) -> float:
        """The mean of :meth:`prediction_errors` over ``data``."""
        return float(self.prediction_errors(data)[1].mean())

    def transition(self, obs: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Paired rows, differentiable in the actions: s^' (N, obs_dim), g = P(going on) (N,) and the
        reward (N,), float32; the known reward and termination where given.

        :param obs: (N, obs_dim) observations
        :param actions: (N, act_dim) Box actions or (N,) Discrete indices, env units
        """
        next_obs, going_on, rewards = (part.float() for part in self.model.transition(obs, self.model_actions(actions)))
        spec = self.reward_spec
        if spec is not None:
            if spec.is_terminal is not None:
                going_on = (~spec.is_terminal(next_obs)).float()
            rewards = spec.step_reward(obs.float(), actions).float() + spec.terminal_bonus * (1 - going_on)
        return next_obs, going_on, rewards

    def step(self, obs: torch.Tensor, candidates: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`transition` of every state with every candidate, state-major, :data:`STEP_ROWS` pairs at
        a time: (N K, obs_dim), (N K,), (N K,).

        :param obs: (N, obs_dim) observations
        :param candidates: (K, act_dim) Box actions or (K,) Discrete indices, env units
        """
        k, size = len(candidates), max(1, STEP_ROWS // len(candidates))
        blocks = []
        for start in range(0, len(obs), size):
            states = obs[start : start + size]
            actions = candidates.repeat(len(states), *([1] * (candidates.dim() - 1)))
            blocks.append(self.transition(states.repeat_interleave(k, dim=0), actions))
        return tuple(torch.cat(parts) for parts in zip(*blocks, strict=True))

    @torch.no_grad()
    def evaluate(
        self,
        phi: StateFeatureMap,
        states: torch.Tensor,
        candidates: torch.Tensor,
        l2: float,
        logger: Logger,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Eq. (7) through the model at the greedy candidates of the current w (module docstring),
        greedy over at most :data:`PLANNING_PAIRS` state-candidate pairs.

        Logs ``train/bellman_residual``, ``train/q_mean`` and ``train/value_mean``.

        :param phi: the state features
        :param states: (n, obs_dim) the collection C
        :param candidates: (K, ...) candidate actions
        :param l2: ridge of eq. (7), relative to the mean diagonal of its normal equations
        :param logger: SB3's logger
        :param generator: draws the candidates compared when not all of them fit :data:`PLANNING_PAIRS`
        :return: (p,) value weights w^_k
        """
        compared = max(1, PLANNING_PAIRS // len(states))
        if len(candidates) > compared:
            candidates = candidates[torch.randperm(len(candidates), generator=generator)[:compared]]
        n, k, gamma = len(states), len(candidates), self.gamma
        next_obs, going_on, rewards = self.step(states, candidates)
        values = (rewards + gamma * going_on * blocked_values(phi, next_obs, self.value_weights)).reshape(n, k)
        q_values, pick = values.max(dim=1)
        chosen = torch.arange(n) * k + pick
        state_phi = phi(states)
        next_phi = phi(next_obs[chosen]) * going_on[chosen].unsqueeze(1)
        weights = bellman_residual_weights(state_phi, next_phi, rewards[chosen], gamma, l2)
        logger.record("train/bellman_residual", bellman_residual_rms(state_phi, next_phi, rewards[chosen], gamma, weights))
        logger.record("train/q_mean", float(q_values.mean()))
        logger.record("train/value_mean", float((state_phi @ weights).mean()))
        return weights

    def improve(self, value_weights: torch.Tensor, omega: float) -> None:
        """w_k = (1 - omega) w_{k-1} + omega w^_k.

        :param value_weights: (p,) w^_k from :meth:`evaluate`
        :param omega: smoothing step in (0, 1]
        """
        self.value_weights = smooth(self.value_weights, value_weights, omega)

    def restart(self) -> None:
        """Forget w (phi moved to new coordinates)."""
        self.value_weights = torch.zeros_like(self.value_weights)

    @torch.no_grad()
    def greedy(
        self, phi: StateFeatureMap, obs: torch.Tensor, candidates: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The first action of the best d-step path, its value L_d(s) and the path's later actions:
        (N, obs_dim) -> (N, ...) candidates, (N,) and (N, d - 1, ...) candidates."""
        values, paths = self.backed_up_paths(phi, obs, candidates, self.depth - 1)
        best = values.argmax(dim=1)
        rows = torch.arange(len(obs))
        return candidates[best], values[rows, best], candidates[paths[rows, best]]

    def action_values(
        self, phi: StateFeatureMap, obs: torch.Tensor, actions: torch.Tensor, later: torch.Tensor
    ) -> torch.Tensor:
        """The value of each state's own first action followed by the given later actions, open loop:
        r_0 + gamma g_0 (r_1 + ... + gamma g_{d-1} <w, phi(s_d)>), differentiable in the actions. With
        ``later`` the best path's (:meth:`greedy`) it is L_d at the path's first action and, by the
        envelope theorem, has L_d's slope in the first action wherever the best path does not switch:
        the continuous search of the first action at d model steps a point instead of K^(d-1) leaves.

        :param phi: the state features
        :param obs: (N, obs_dim) observations
        :param actions: (N, act_dim) the first Box actions, env units
        :param later: (N, d - 1, act_dim) the actions of the later steps
        :return: (N,)
        """
        steps = []
        for action in (actions, *later.unbind(1)):
            obs, going_on, rewards = self.transition(obs, action)
            steps.append((going_on, rewards))
        value = blocked_values(phi, obs, self.value_weights)
        for going_on, rewards in reversed(steps):
            value = rewards + self.gamma * going_on * value
        return value

    def backed_up_paths(
        self, phi: StateFeatureMap, obs: torch.Tensor, candidates: torch.Tensor, remaining: int
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """r + gamma g L_remaining(s^'_a) at every state and candidate and, after each, the candidate indices of
        the best path of the ``remaining`` steps below it: (N, obs_dim) -> (N, K), (N, K, remaining) int64."""
        next_obs, going_on, rewards = self.step(obs, candidates)
        if remaining == 0:
            tail, paths = blocked_values(phi, next_obs, self.value_weights), next_obs.new_empty(len(next_obs), 0).long()
        else:
            values, below = self.backed_up_paths(phi, next_obs, candidates, remaining - 1)
            tail, best = values.max(dim=1)
            paths = torch.cat([best.unsqueeze(1), below[torch.arange(len(best)), best]], dim=1)
        k = len(candidates)
        return (rewards + self.gamma * going_on * tail).reshape(len(obs), k), paths.reshape(len(obs), k, remaining)
