"""CMEDynamics: the model mu(s, a) = B psi(s, a) of E[phi~(S') | s, a], owned end to end
(paper eq. (1), section 2.3).

One module holds everything the model is made of and everything computed from it: the
encoders of observations and actions, the state features phi, the growing kernel bank psi
and the weights B; the regression inputs and targets of a batch, the loss and the SGD step
of eq. (6); the matching-pursuit dictionary of eq. (5); :meth:`CMEDynamics.grow`, the only
place where q changes; the expected successor features; and the expected reward, composed
once from the known step reward, the termination probability and (when the reward is not
known) a learned reward row of B.

Regression target of a transition: the continuation-weighted successor feature
``phi~(s') = (1 - terminated) phi(s')`` (terminal states are absorbing with phi = 0), minus
``phi(s)`` in the feature-dynamics form of section 2.3. Since phi ends with a constant 1, the
model's last phi row predicts the continuation probability; when the reward is learned, one
more row regresses ``(r - reward_offset) / reward_scale`` on psi: the whole reward less an
offset, the least of 0 and the first batch's non-terminal rewards; where psi's kernels fade,
off the data, the model predicts that offset (:meth:`CMEDynamics.calibrate_reward_row`).

Shapes: N a batch, p = width of phi, q = width of psi, p_out = p (+ 1 with a learned reward).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from gymnasium import spaces
from torch import nn

from cme_agent.buffer import Transitions
from cme_agent.config import EvaluationConfig, ObservationConfig, StateFeatureConfig, build_config
from cme_agent.dynamics.sgd import sgd_step
from cme_agent.encoding import ActionEncoder, ObservationEncoder
from cme_agent.kernel_bank import JOINT, STATE_ONLY, KernelBank, resize_buffers
from cme_agent.rewards import RewardSpec
from cme_agent.state_features import make_state_features

PhiSpec = StateFeatureConfig | dict[str, Any] | nn.Module | Callable[[torch.Tensor], torch.Tensor] | None


TARGET_ELEMENTS = 2**22
"""Largest block of SGD targets built at once (16 MiB of float32): with a wide phi (CartPole's
preset: p = 2,836) the targets of all 200 minibatches would take about 300 MB, three times over."""


REFIT_ROWS = 4096
"""Rows of psi built at once by :meth:`CMEDynamics.refit_weights` (32 MiB of float32 at q = 2,000)."""


@dataclass
class Dictionary:
    """What each column of :meth:`CMEDynamics.dictionary` is: (c, d) centres, (c,) bandwidths, (c,) action basis codes."""

    centres: torch.Tensor
    bandwidths: torch.Tensor
    action_basis: torch.Tensor

    def __getitem__(self, index: torch.Tensor) -> Dictionary:
        return Dictionary(self.centres[index], self.bandwidths[index], self.action_basis[index])


def _zero_reward(obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    return torch.zeros(obs.shape[0], dtype=obs.dtype, device=obs.device)


class CMEDynamics(nn.Module):
    """The CME model of the dynamics and of the expected reward.

    :param observation_space: a 1-D ``Box``
    :param action_space: a 1-D ``Box`` or a ``Discrete``
    :param phi: the state feature map: a :class:`StateFeatureConfig` or its dict, or a user map
        (``nn.Module`` or callable) from obs (N, obs_dim) to (N, p0)
    :param observation: normalisation bounds and angle pairs (:class:`ObservationConfig` or dict)
    :param feature_dynamics: regress phi~(s') - phi(s) (section 2.3) instead of phi~(s')
    :param reward: the known reward; None: learn it by regression on psi (one more row of B)
    :param evaluation: the evaluation settings, for the memory check of phi (None: defaults)
    :param action_scale: the weight of a Box action in psi's input (``feature_selection.action_scale``;
        a Discrete action's one-hot enters unscaled)
    """

    def __init__(
        self,
        observation_space: spaces.Box,
        action_space: spaces.Box | spaces.Discrete,
        phi: PhiSpec = None,
        observation: ObservationConfig | dict[str, Any] | None = None,
        feature_dynamics: bool = True,
        reward: RewardSpec | None = None,
        evaluation: EvaluationConfig | None = None,
        action_scale: float = 1.0,
    ) -> None:
        super().__init__()
        self.obs_encoder = ObservationEncoder(observation_space, build_config(ObservationConfig, observation, "observation"))
        self.action_encoder = ActionEncoder(action_space)
        phi_config = phi if callable(phi) else build_config(StateFeatureConfig, phi, "phi")
        self.phi = make_state_features(phi_config, self.obs_encoder, evaluation)
        self.psi = KernelBank(self.obs_encoder.dim, self.action_encoder.dim)
        self.feature_dynamics = feature_dynamics
        self.learn_reward = reward is None
        self.reward = reward if reward is not None else RewardSpec(_zero_reward)
        self.register_buffer("weights", torch.zeros(self.p + int(self.learn_reward), 0))
        self.register_buffer("reward_scale", torch.ones(()))
        self.register_buffer("reward_offset", torch.zeros(()))
        self.register_buffer(
            "action_scale", torch.tensor(1.0 if self.action_encoder.discrete else float(action_scale), dtype=torch.float64)
        )

    # ------------------------------------------------------------------ sizes
    @property
    def p(self) -> int:
        """p, the width of phi (its last feature is the constant 1)."""
        return self.phi.width

    @property
    def q(self) -> int:
        """q, the width of psi: the number of selected kernel features."""
        return self.psi.q

    @property
    def phi_weights(self) -> torch.Tensor:
        """(p, q): the rows of B that predict phi."""
        return self.weights[: self.p]

    # ------------------------------------------------------------------ inputs and targets
    def encode(self, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Normalised state-actions z = (z_s, z_a): (N, obs_dim), (N, ...) -> (N, obs_dim + action_dim)."""
        return torch.cat([self.encode_states(obs), self.encode_actions(actions)], dim=1)

    def encode_states(self, obs: torch.Tensor) -> torch.Tensor:
        """z_s, the state part of psi's input: the observation normalised by its box: (N, obs_dim) -> (N, obs_dim)."""
        return self.obs_encoder.normalize(obs)

    def encode_actions(self, actions: torch.Tensor) -> torch.Tensor:
        """z_a, the action part of psi's input: a Box action normalised to [-1, 1] times
        ``feature_selection.action_scale``, or a Discrete action's one-hot: (N, act_dim) or (N,) -> (N, action_dim)."""
        return self.action_encoder.encode(actions).mul_(self.action_scale)

    def features(self, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """psi(s, a) at paired states and actions: (N, obs_dim), (N, ...) -> (N, q)."""
        return self.psi(self.encode(obs, actions))

    def state_factor(self, obs: torch.Tensor) -> torch.Tensor:
        """S (N, q), psi(s, a)[j] = S[s, j] * A[a, j]: :param obs: (N, obs_dim) observations."""
        return self.psi.state_factor(self.encode_states(obs))

    def action_factor(self, actions: torch.Tensor) -> torch.Tensor:
        """A (K, q), the action factor of psi: :param actions: (K, ...) actions in env units."""
        return self.psi.action_factor(self.encode_actions(actions))

    def targets(self, batch: Transitions) -> torch.Tensor:
        """Regression targets y of a batch: (N, p_out), phi~(s') (- phi(s)) (and the reward row's
        ``(r - reward_offset) / reward_scale``)."""
        continuation = (~batch.terminated).to(batch.next_obs)
        target = self.phi.successor_targets(batch.next_obs, continuation, batch.obs if self.feature_dynamics else None)
        if self.learn_reward:
            rewards = (batch.rewards - self.reward_offset) / self.reward_scale
            target = torch.cat([target, rewards.unsqueeze(1)], dim=1)
        return target

    def regression_data(self, batch: Transitions) -> tuple[torch.Tensor, torch.Tensor]:
        """Inputs psi (N, q) and targets y (N, p_out) of a batch."""
        return self.features(batch.obs, batch.actions), self.targets(batch)

    def calibrate_reward_row(self, rewards: torch.Tensor, terminated: torch.Tensor) -> str | None:
        """Before the first feature, scale the learned reward row to unit spread and shift it by
        the least of 0 and the batch's non-terminal rewards: what the model then predicts off the
        data. Where rewards are costs that is the
        worst cost seen, a pessimism; it is never above 0, the offset-free row's value off the
        data; and a terminal transition's reward (a fall's, without the alive bonus) does not
        count, the termination model already pricing the fall. Both stay fixed: B's row is
        learned in their units.

        :param rewards: (N,) the first feature-selection batch's rewards
        :param terminated: (N,) bool, which of them ended in a terminal state
        :return: a log line when it calibrated (a learned reward and q = 0), else None
        """
        if not self.learn_reward or self.q > 0:
            return None
        self.reward_scale.fill_(float(rewards.std().clamp_min(1e-3)))
        non_terminal = rewards[~terminated]
        self.reward_offset.fill_(min(0.0, float(non_terminal.min())) if len(non_terminal) else 0.0)
        return (
            f"Learned reward: {float(rewards.min()):.4g} to {float(rewards.max()):.4g} in the first batch; "
            f"off the data the model predicts {float(self.reward_offset):.4g} (the least of 0 and its non-terminal rewards)."
        )

    # ------------------------------------------------------------------ loss and updates
    def predict(self, psi: torch.Tensor) -> torch.Tensor:
        """B psi: :param psi: (N, q). :return: (N, p_out)."""
        return psi @ self.weights.T

    def loss(self, psi: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
        """Mean squared residual per transition, (1/N) sum_i ||y_i - B psi_i||^2 (loss (4) / N)."""
        return ((targets - self.predict(psi)) ** 2).sum(1).mean()

    def sgd_update(self, batches: Transitions, batch_size: int, learning_rate: float, l2: float) -> None:
        """Consecutive minibatch steps of eq. (6) on B, in place.

        The kernel operands of all steps are built at once, the targets a few minibatches at a
        time (at most :data:`TARGET_ELEMENTS` floats, whatever phi's width); neither depends on
        B. Each step's psi goes into one reused buffer that stays in the CPU's cache, and the
        steps themselves are sequential.

        :param batches: the minibatches of all steps, concatenated in order (a multiple of ``batch_size``)
        :param batch_size: transitions per step
        :param learning_rate: normalised step in (0, 2) (see :func:`~cme_agent.dynamics.sgd.sgd_step`)
        :param l2: ridge coefficient lambda
        """
        points = self.psi.points(self.encode(batches.obs, batches.actions))
        buffer = self.weights.new_empty(min(batch_size, len(batches)), self.q)
        span = batch_size * max(1, TARGET_ELEMENTS // (batch_size * self.weights.shape[0]))  # bounded memory for wide phi
        for start in range(0, len(batches), span):
            targets = self.targets(batches[start : start + span])
            for step in range(0, len(targets), batch_size):
                step_targets = targets[step : step + batch_size]
                rows = slice(start + step, start + step + len(step_targets))
                psi = self.psi.from_points(points[rows], out=buffer[: len(step_targets)])
                sgd_step(self.weights, psi, step_targets, learning_rate, l2)

    def refit_weights(self, batch: Transitions, l2: float) -> float:
        """B by ridge regression on a batch, ``B^T = (Psi^T Psi + (N l2 + eps) I)^{-1} Psi^T Y``
        (loss (4) with the ridge of eq. (6)), the normal equations accumulated in float64 a
        block of rows at a time (eps = 1e-6 of their mean diagonal keeps the solve defined).

        :param batch: N transitions (e.g. a sample of D)
        :param l2: ridge coefficient lambda
        :return: the new B's mean squared residual on the batch, (1/N) sum_i ||y_i - B psi_i||^2,
            from the same sums: ``(sum ||y||^2 - 2 <B, Y^T Psi> + <B Psi^T Psi, B>) / N``
        """
        gram = self.weights.new_zeros(self.q, self.q, dtype=torch.float64)
        cross = self.weights.new_zeros(self.q, self.weights.shape[0], dtype=torch.float64)
        target_energy = 0.0
        for start in range(0, len(batch), REFIT_ROWS):
            psi, targets = self.regression_data(batch[start : start + REFIT_ROWS])
            gram += (psi.T @ psi).double()
            cross += (psi.T @ targets).double()
            target_energy += float(targets.double().square().sum())
        system = gram.clone()
        system.diagonal().add_(len(batch) * l2 + 1e-6 * float(gram.diagonal().mean().clamp_min(1e-12)))
        solution = torch.linalg.solve(system, cross)  # (q, p_out): B^T
        self.weights = solution.T.to(self.weights)
        residual = target_energy - 2 * float((solution * cross).sum()) + float((solution * (gram @ solution)).sum())
        return max(residual, 0.0) / len(batch)

    def expand_observation_box(self, obs: torch.Tensor, batch: Transitions, l2: float) -> str:
        """Widen the estimated observation box to cover ``obs`` (:meth:`ObservationEncoder.expand`)
        and carry the model into the new coordinates: psi's centres keep their env-unit
        positions (:meth:`KernelBank.move_states`), phi follows the box by construction (a data
        metric is refit on ``obs`` and ``batch``'s states), and B, whose targets phi changed, is
        refit on ``batch`` (:meth:`refit_weights`).

        :param obs: (N, obs_dim) observations the box must cover, env units
        :param batch: transitions B is refit on
        :param l2: ridge coefficient of the refit
        :return: the encoder's log line
        """
        encoder = self.obs_encoder
        center, half_range = encoder.center.clone(), encoder.half_range.clone()
        message = encoder.expand(obs)
        shift = (center - encoder.center) / encoder.half_range
        self.psi.move_states(half_range / encoder.half_range, shift)
        if self.phi.follows_data:
            message += "; " + self.phi.fit(torch.cat([obs, batch.obs, batch.next_obs]))
        if self.q > 0:
            self.refit_weights(batch, l2)
        return message

    def dictionary(
        self, z: torch.Tensor, centres: torch.Tensor, bandwidths: torch.Tensor, control_affine: bool = False
    ) -> tuple[torch.Tensor, Dictionary]:
        """The candidate atoms of eq. (5): Gaussian kernels centred at ``centres`` at every
        bandwidth, and with ``control_affine`` also, per centre and bandwidth, the state kernel
        alone and the state kernel times each action coordinate (:mod:`cme_agent.kernel_bank`).

        :param z: (n, d) normalised state-actions where the atoms are evaluated
        :param centres: (m, d) normalised centres (the new state-actions)
        :param bandwidths: (b,) bandwidths h
        :param control_affine: add the atoms that ignore the action and those linear in it
        :return: the (n, c) atoms and what each column is (:class:`Dictionary`)
        """
        codes = [JOINT] + ([STATE_ONLY, *range(self.action_encoder.dim)] if control_affine else [])
        m, b = len(centres), len(bandwidths)
        columns = Dictionary(
            centres=centres.repeat(len(codes) * b, 1),
            bandwidths=bandwidths.repeat_interleave(m).repeat(len(codes)),
            action_basis=torch.tensor(codes, device=z.device).repeat_interleave(m * b),
        )
        bank = KernelBank(self.psi.state_dim, self.action_encoder.dim).to(z)
        bank.append(columns.centres, columns.bandwidths, columns.action_basis)
        return bank(z), columns

    def grow(
        self, centres: torch.Tensor, bandwidths: torch.Tensor, weights: torch.Tensor, action_basis: torch.Tensor | None = None
    ) -> None:
        """Append features to psi and their weights to B, B_k = (B_{k-1}, weights): the only
        place q changes.

        :param centres: (l, d) normalised centres
        :param bandwidths: (l,) bandwidths
        :param weights: (p_out, l) columns of B for the new features
        :param action_basis: (l,) the atoms' action basis codes (None: joint Gaussians)
        """
        self.psi.append(centres, bandwidths, action_basis)
        self.weights = torch.cat([self.weights, weights.to(self.weights)], dim=1)

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any, **kwargs: Any) -> None:
        resize_buffers(self, state_dict, prefix, {"weights": 1})
        if prefix + "reward_offset" not in state_dict:  # saved before the offset: the row learned r itself
            state_dict[prefix + "reward_offset"] = torch.zeros_like(self.reward_offset)
        if prefix + "action_scale" not in state_dict:  # saved before the scale: the action entered psi unscaled
            state_dict[prefix + "action_scale"] = torch.ones_like(self.action_scale)
        metric = state_dict.pop(prefix + "state_metric", None)  # files of the removed learned metric
        if metric is not None and not torch.equal(metric, torch.ones_like(metric)):
            raise ValueError(
                "this model was saved with psi's learned metric (model_update.metric_every > 0), which the library no "
                "longer has: its kernels would be read on the wrong length scales"
            )
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    # ------------------------------------------------------------------ what planning reads
    def expected_next_phi(self, phi: torch.Tensor, psi: torch.Tensor) -> torch.Tensor:
        """E_model[phi~(S') | s, a]: (N, p) from phi(s) (N, p) and psi(s, a) (N, q)."""
        return self.read(phi, psi @ self.readout())[0]

    def readout(self) -> torch.Tensor:
        """(q, p + 1): the linear maps planning reads psi through, ``[B_phi^T, c_psi]``, so that
        one product ``psi @ readout`` gives both E_model[phi~(S')] (less phi(s) with feature
        dynamics) and the model's part of the reward (:meth:`read`); contiguous, for the product."""
        return torch.cat([self.phi_weights.T, self.reward_weights()[1].unsqueeze(1)], dim=1)

    def read(self, phi: torch.Tensor, psi_read: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """E_model[phi~(S') | s, a] and the model's part of the expected reward
        (:meth:`linear_reward`) from ``psi @ readout()``.

        :param phi: (N, p) phi(s)
        :param psi_read: (N, p + 1) psi(s, a) @ :meth:`readout` (or E_pi[psi(s, A)] @ readout), modified in place
        :return: E_model[phi~(S')] (N, p), a view of ``psi_read``, and the reward part (N,)
        """
        predicted, reward = psi_read[:, : self.p], psi_read[:, self.p]
        reward = reward + phi @ self.reward_weights()[0]
        return predicted.add_(phi) if self.feature_dynamics else predicted, reward

    def reward_weights(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The model's linear part of the expected reward,
        ``r(s, a) = step_reward(s, a) + <c_phi, phi(s)> + <c_psi, psi(s, a)>``:
        the terminal bonus times P_model(terminate | s, a) (read off the constant row of phi:
        E[1 - done] = 1 + B_const psi with feature dynamics), plus the learned reward row, its
        offset on phi's constant.

        :return: c_phi (p,) and c_psi (q,)
        """
        c_phi = self.weights.new_zeros(self.p)
        c_psi = self.weights.new_zeros(self.q)
        bonus = self.reward.terminal_bonus
        if bonus:
            c_psi -= bonus * self.weights[self.p - 1]
            if not self.feature_dynamics:
                c_phi[-1] += bonus
        if self.learn_reward:
            c_psi += self.weights[-1] * self.reward_scale
            c_phi[-1] += self.reward_offset
        return c_phi, c_psi

    def expected_reward(self, obs: torch.Tensor, actions: torch.Tensor, phi: torch.Tensor, psi: torch.Tensor) -> torch.Tensor:
        """r(s, a) = step reward + terminal bonus * P_model(terminate | s, a) + learned reward.

        :param obs: (N, obs_dim) states
        :param actions: (N, ...) actions in env units
        :param phi: (N, p) phi(s)
        :param psi: (N, q) psi(s, a)
        :return: (N,)
        """
        return self.reward.step_reward(obs, actions) + self.linear_reward(phi, psi)

    def linear_reward(self, phi: torch.Tensor, psi: torch.Tensor) -> torch.Tensor:
        """The model's part of the expected reward, ``<c_phi, phi(s)> + <c_psi, psi(s, a)>``
        (:meth:`reward_weights`); linear, so at E_pi[psi(s, A)] it is the expectation under pi.

        :param phi: (N, p) phi(s)
        :param psi: (N, q) psi(s, a), or its expectation under a policy
        :return: (N,)
        """
        c_phi, c_psi = self.reward_weights()
        return phi @ c_phi + psi @ c_psi

    def backup_weights(self, value_weights: torch.Tensor, gamma: float) -> tuple[torch.Tensor, torch.Tensor]:
        """The linear weights of ``Q^(s, a) = r(s, a) + gamma <w, E_model[phi~(S') | s, a]>``
        beyond the step reward: Q^ = step_reward + <theta_phi, phi(s)> + <theta_psi, psi(s, a)>.

        :param value_weights: (p,) w
        :param gamma: discount factor
        :return: theta_phi (p,) and theta_psi (q,)
        """
        c_phi, c_psi = self.reward_weights()
        theta_psi = c_psi.add_(self.phi_weights.T @ value_weights, alpha=gamma)
        theta_phi = c_phi.add_(value_weights, alpha=gamma) if self.feature_dynamics else c_phi
        return theta_phi, theta_psi
