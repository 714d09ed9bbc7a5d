"""CMEPolicy: the greedy policy of the smoothed Q function (paper section 2.2), or the soft
policy of KL-regularised policy iteration (:class:`~cme_agent.config.ImprovementConfig`).

``Q_k(s, a) = r(s, a) + <theta_phi, phi(s)> + <theta_psi, psi(s, a)>``, where r is the known
step reward and the weights accumulate gamma <w, B psi>, the expected terminal bonus and a
learned reward (:meth:`~cme_agent.dynamics.CMEDynamics.backup_weights`). The policy owns the
Q weights and the search over candidate actions; the model (phi, psi, B, the reward) is its
submodule ``dynamics``. Acting greedily costs O(q) per candidate action, whatever the iteration.

theta_psi may be shorter than q: features added since the last improvement have weight 0
in Q (the zero-padding of docs/design.md), so Q reads only the first ``len(theta_psi)`` of them.

With ``improvement.method="soft"`` the same weights hold the average Qbar_k = (1/k) sum_j Q^_j of
the k estimates so far (the running sum is k Qbar_k: the same zero-padding, no history), and
the policy is pi(a|s) = softmax_a(beta_k Qbar_k(s, a)) over the candidates (:meth:`CMEPolicy.soft_step`).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import PyTorchObs
from stable_baselines3.common.utils import is_vectorized_observation

from cme_agent.action_search import at_points, projected_ascent
from cme_agent.config import (
    LOOKAHEAD_REFINE_STEPS,
    ActionSearchConfig,
    EvaluationConfig,
    ImprovementConfig,
    ObservationConfig,
    build_config,
)
from cme_agent.dynamics.cme import CMEDynamics, PhiSpec
from cme_agent.kernel_bank import kernel_from_points, kernel_points, resize_buffers
from cme_agent.lookahead import LEAF_LIMIT, LookaheadPlanner, default_depth
from cme_agent.planning import action_spread, expected_candidate_features, smooth, softmax_policy
from cme_agent.rewards import RewardSpec

SPREAD_STATES = 1024
"""States of C (evenly strided) on which the spread of Q over the candidates is measured, for beta."""

BLOCK_ELEMENTS = 2**18
"""Elements (1 MiB of float32) of one block of rows of the state factor in :meth:`CMEPolicy.greedy_step`."""


def _row_blocks(n: int, width: int) -> list[slice]:
    """Slices of ``n`` rows in blocks of about :data:`BLOCK_ELEMENTS` elements of ``width`` columns."""
    size = max(1, BLOCK_ELEMENTS // max(width, 1))
    return [slice(start, min(start + size, n)) for start in range(0, n, size)]


def _write_block(psi: torch.Tensor, readout: torch.Tensor | None, out: torch.Tensor, rows: slice) -> None:
    """Complete the rows ``rows`` of a step's output from their psi, (block, q): psi @ readout
    into ``out[rows]`` (one cache-resident product), or nothing when psi was written there in place."""
    if readout is not None:
        torch.mm(psi, readout, out=out[rows])


@dataclass
class GreedyStep:
    """The greedy policy at a batch of states, with the features planning reuses.

    :param actions: (N, act_dim) Box actions in env units, or (N,) Discrete indices
    :param values: (N,) Q_k at those actions
    :param phi: (N, p) phi(s)
    :param psi: (N, q) psi(s, pi(s)), or (N, m) psi(s, pi(s)) @ readout when the step was given
        a readout (psi itself is then never stored)
    """

    actions: torch.Tensor
    values: torch.Tensor
    phi: torch.Tensor
    psi: torch.Tensor


@dataclass
class SoftStep:
    """The soft policy at a batch of states, with the expectations its evaluation needs.

    :param probabilities: (N, K) pi(a|s) over the candidates
    :param values: (N,) E_pi[Qbar_k(s, A)]
    :param phi: (N, p) phi(s)
    :param psi: (N, q) E_pi[psi(s, A)] = S(s) * (pi(s) @ A), or (N, m) E_pi[psi(s, A)] @ readout
        when the step was given a readout
    :param step_rewards: (N,) E_pi[step_reward(s, A)]
    """

    probabilities: torch.Tensor
    values: torch.Tensor
    phi: torch.Tensor
    psi: torch.Tensor
    step_rewards: torch.Tensor


class CMEPolicy(BasePolicy):
    """Greedy policy over candidate actions of the smoothed Q function.

    :param observation_space: a 1-D ``Box``
    :param action_space: a 1-D ``Box`` or a ``Discrete``
    :param lr_schedule: unused (SB3 signature); the model's step size lives in the algorithm
    :param phi: the state feature map (see :class:`~cme_agent.dynamics.CMEDynamics`)
    :param observation: normalisation bounds and angle pairs (:class:`ObservationConfig` or dict)
    :param action_search: greedy search over Box actions (:class:`ActionSearchConfig` or dict)
    :param candidate_seed: seed of the sampled action candidates (Box actions, high dims)
    :param feature_dynamics: the model regresses phi~(s') - phi(s) (section 2.3)
    :param reward: the known reward; None: the model learns it
    :param action_scale: the weight of a Box action in psi's input (``feature_selection.action_scale``; Discrete: unscaled)
    :param evaluation: the evaluation settings, for the memory check of phi (None: defaults)
    :param improvement: the improvement step (:class:`ImprovementConfig` or dict; None: the
        paper's smoothed greedy step)
    :param model_kind: ``model_update.kind``: ``"observation"`` plans and acts through a
        :class:`~cme_agent.lookahead.LookaheadPlanner` (the submodule ``lookahead``) instead of Q's
        weights; ``"auto"`` holds the planner until :meth:`choose_model`
    :param gamma: the discount factor the lookahead acts with (``model_kind="observation"``)
    :param change_fourier: ``model_update.change_fourier``, the waves of the model of the observation's change
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        lr_schedule: Callable[[float], float] | None = None,
        phi: PhiSpec = None,
        observation: ObservationConfig | dict[str, Any] | None = None,
        action_search: ActionSearchConfig | dict[str, Any] | None = None,
        candidate_seed: int = 0,
        feature_dynamics: bool = True,
        reward: RewardSpec | None = None,
        evaluation: EvaluationConfig | None = None,
        improvement: ImprovementConfig | dict[str, Any] | None = None,
        action_scale: float = 1.0,
        model_kind: str = "cme",
        gamma: float = 0.95,
        change_fourier: int = 0,
    ) -> None:
        super().__init__(observation_space, action_space, squash_output=False)
        self.phi_spec = phi
        self.action_search = build_config(ActionSearchConfig, action_search, "action_search")
        self.improvement = build_config(ImprovementConfig, improvement, "improvement")
        if self.soft and isinstance(action_space, spaces.Box) and (self.action_search.refine_steps or 0) > 0:
            raise ValueError(
                f"action_search.refine_steps={self.action_search.refine_steps} is invalid with improvement.method='soft': "
                "must be 0 (the soft policy is a distribution over the fixed candidates; refined actions are not among them)"
            )
        self.candidate_seed = candidate_seed
        self.observation_config = build_config(ObservationConfig, observation, "observation")
        self.dynamics = CMEDynamics(
            observation_space,
            action_space,
            phi=phi,
            observation=self.observation_config,
            feature_dynamics=feature_dynamics,
            reward=reward,
            evaluation=evaluation,
            action_scale=action_scale,
        )
        self.register_buffer("theta_phi", torch.zeros(self.dynamics.p))
        self.register_buffer("theta_psi", torch.zeros(0))
        # soft improvement only: n_k, the (decayed) count of estimates averaged, and beta_k on Qbar_k
        self.register_buffer("improvements", torch.zeros(()))
        self.register_buffer("inverse_temperature", torch.zeros(()))
        self.register_buffer("candidates", self._make_candidates())
        self._candidate_factor: tuple[tuple[int, int], torch.Tensor] | None = None
        self._weighted_candidates: tuple[torch.Tensor, tuple[int, int], torch.Tensor] | None = None
        self.model_kind, self.gamma, self.change_fourier = model_kind, gamma, change_fourier
        self.lookahead = self._make_lookahead(reward)

    def _make_lookahead(self, reward: RewardSpec | None) -> LookaheadPlanner | None:
        """The planner through the model of the observation, or None with the CME."""
        depth = self.action_search.lookahead_depth
        if self.model_kind == "auto" and self.soft:
            self.model_kind = "cme"  # the soft policy belongs to the CME
        if self.model_kind == "cme":
            if depth not in (None, 1):
                raise ValueError(
                    f"action_search.lookahead_depth={depth} is invalid with model_update.kind={self.model_kind!r}: "
                    "looking ahead needs the model of the observation (model_update.kind='observation')"
                )
            return None
        if self.soft:
            raise ValueError(
                "improvement.method='soft' is invalid with model_update.kind='observation': it acts by lookahead "
                "with the smoothed greedy step (pass improvement={'method': 'smoothed_greedy'} where an env's preset sets it)"
            )
        n_candidates = len(self.candidates)
        depth = default_depth(n_candidates) if depth is None else depth
        if n_candidates**depth > LEAF_LIMIT:
            raise ValueError(
                f"action_search.lookahead_depth={depth} is invalid with {n_candidates} candidate actions: "
                f"{n_candidates}^{depth} leaves per action, more than {LEAF_LIMIT:,}; pass a smaller depth"
            )
        obs_dim, waves = self.observation_space.shape[0], self.change_fourier
        return LookaheadPlanner(obs_dim, self.action_space, self.dynamics.p, depth, self.gamma, reward, waves)

    def choose_model(self, kind: str) -> None:
        """Settle ``model_kind="auto"``: keep the lookahead with ``"observation"``, drop it with ``"cme"``."""
        self.model_kind = kind
        if kind == "cme":
            self.lookahead = None

    def _make_candidates(self) -> torch.Tensor:
        """Candidate actions in env units: all Discrete actions (K,), or a Box grid / sample (K, act_dim)."""
        encoder = self.dynamics.action_encoder
        if encoder.discrete:
            return torch.arange(encoder.n_actions)
        dims = encoder.dim
        search = self.action_search
        if dims <= search.max_grid_dims:
            axis = torch.linspace(-1, 1, search.grid_size) if search.grid_points is None else torch.tensor(search.grid_points)
            encoded = torch.tensor(list(itertools.product(axis.tolist(), repeat=dims)), dtype=torch.float32)
        else:
            generator = torch.Generator().manual_seed(self.candidate_seed)
            sampled = torch.rand(search.n_samples, dims, generator=generator) * 2 - 1
            encoded = torch.cat([torch.zeros(1, dims), sampled])
        return encoder.decode(encoded)

    @property
    def device(self) -> torch.device:
        """The device of the policy's tensors (it has buffers, no parameters)."""
        return self.theta_phi.device

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            phi=self.phi_spec,
            observation=self.observation_config,
            action_search=self.action_search,
            candidate_seed=self.candidate_seed,
            feature_dynamics=self.dynamics.feature_dynamics,
            improvement=self.improvement,
            action_scale=float(self.dynamics.action_scale),
            model_kind=self.model_kind,
            gamma=self.gamma,
            change_fourier=self.change_fourier,
        )
        return data

    @property
    def refine_steps(self) -> int:
        """``action_search.refine_steps``, or by default :data:`LOOKAHEAD_REFINE_STEPS` with the lookahead where its
        reward varies, else 0 (with a constant reward the ascent follows only the errors of g and V between neighbouring
        actions: InvertedPendulum-v5's balancing fell from 1,000 to 53-448 in its first 3,000 steps)."""
        steps = self.action_search.refine_steps
        if steps is None:
            return LOOKAHEAD_REFINE_STEPS if self.lookahead is not None and self.lookahead.reward_varies else 0
        return steps

    @property
    def refines(self) -> bool:
        """Whether greedy Box actions are refined from the best candidate (:attr:`refine_steps`)."""
        return not self.dynamics.action_encoder.discrete and self.refine_steps > 0

    @property
    def soft(self) -> bool:
        """Whether the policy is the soft policy of KL-regularised policy iteration."""
        return self.improvement.method == "soft"

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any, **kwargs: Any) -> None:
        resize_buffers(self, state_dict, prefix, {"theta_psi": 0})
        for name in ("improvements", "inverse_temperature"):  # files written before the soft improvement
            if prefix + "theta_phi" in state_dict:
                state_dict.setdefault(prefix + name, torch.zeros((), device=state_dict[prefix + "theta_phi"].device))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    # ------------------------------------------------------------------ Q
    def q_values(self, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Q_k at paired states and actions (differentiable in the actions): (N, obs_dim), (N, ...) -> (N,)."""
        dynamics, k = self.dynamics, self.theta_psi.shape[0]
        psi = dynamics.features(obs, actions)
        return dynamics.reward.step_reward(obs, actions) + dynamics.phi(obs) @ self.theta_phi + psi[:, :k] @ self.theta_psi

    def candidate_factor(self) -> torch.Tensor:
        """A (K, q), the action factor of psi at the candidates, kept until psi changes."""
        key = (self.dynamics.psi.version, self.dynamics.q)
        if self._candidate_factor is None or self._candidate_factor[0] != key:
            self._candidate_factor = (key, self.dynamics.action_factor(self.candidates))
        return self._candidate_factor[1]

    def weighted_candidates(self) -> torch.Tensor:
        """(K, len(theta_psi)): the candidates' action factor times theta_psi, so that
        ``S(s) @ weighted.T`` is psi's part of Q at every candidate; kept until psi or theta_psi change."""
        theta = self.theta_psi
        key = (self.dynamics.psi.version, theta._version)
        cached = self._weighted_candidates
        if cached is None or cached[0] is not theta or cached[1] != key:
            cached = (theta, key, self.candidate_factor()[:, : theta.shape[0]] * theta)
            self._weighted_candidates = cached
        return cached[2]

    def candidate_q_values(
        self, obs: torch.Tensor, phi: torch.Tensor | None = None, state_factor: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Q_k at every candidate action, one (N, q) x (q, K) product.

        :param obs: (N, obs_dim) states
        :param phi: (N, p) phi(s), if already computed
        :param state_factor: (N, q) the state factor S of psi at the states, if already computed
        :return: (N, K)
        """
        phi = self.dynamics.phi(obs) if phi is None else phi
        state_factor = self.dynamics.state_factor(obs) if state_factor is None else state_factor
        q_used = self.theta_psi.shape[0]
        values = torch.addmm(self._candidate_step_rewards(obs), state_factor[:, :q_used], self.weighted_candidates().T)
        return values.add_((phi @ self.theta_phi).unsqueeze(1))

    def greedy_step(self, obs: torch.Tensor, readout: torch.Tensor | None = None) -> GreedyStep:
        """pi_{k+1} = greedy(Q_k) at a batch of states: the best candidate, refined by projected
        ascent if configured, with phi(s) and psi(s, pi(s)) = S(s) * A(pi(s)) built from the
        same state factor S. S is built in blocks of rows small enough to stay in the CPU's
        cache, and each block is used (Q over the candidates, then psi, then psi @ readout)
        before the next.

        :param obs: (N, obs_dim) observations
        :param readout: (q, m) what psi is read through (e.g.
            :meth:`~cme_agent.dynamics.CMEDynamics.readout`): the step returns
            psi(s, pi(s)) @ readout, (N, m), and never stores the (N, q) psi; None: psi itself
        """
        dynamics, n, q_used = self.dynamics, obs.shape[0], self.theta_psi.shape[0]
        phi, points, out, blocks, (state_buffer, scratch) = self._blocked_inputs(obs, readout)
        state_weights, factor, weighted = dynamics.psi.state_weights(), self.candidate_factor(), self.weighted_candidates()
        state_only = phi @ self.theta_phi
        base = self._candidate_step_rewards(obs) + state_only.unsqueeze(1)
        values, best = base.new_empty(n), torch.empty(n, dtype=torch.long, device=obs.device)
        refine = self.refines
        refined = []
        for rows in blocks:
            length = rows.stop - rows.start
            state = kernel_from_points(points[rows], state_weights, out=state_buffer[:length])
            torch.max(torch.addmm(base[rows], state[:, :q_used], weighted.T), dim=1, out=(values[rows], best[rows]))
            if refine:
                start = self.candidates[best[rows]]
                block_actions, values[rows] = self._refine(obs[rows], state[:, :q_used], start, values[rows], state_only[rows])
                refined.append(block_actions)
                chosen_factor = dynamics.action_factor(block_actions)
            else:
                chosen_factor = torch.index_select(factor, 0, best[rows], out=scratch[:length])
            destination = chosen_factor if readout is not None else out[rows]
            _write_block(torch.mul(state, chosen_factor, out=destination), readout, out, rows)
        actions = torch.cat(refined) if refined else self.candidates[best]
        return GreedyStep(actions, values, phi, out)

    def soft_step(self, obs: torch.Tensor, readout: torch.Tensor | None = None) -> SoftStep:
        """pi_{k+1}(a|s) = softmax_a(beta_k Qbar_k(s, a)) over the candidates (proportional to
        exp(beta_k / k sum_{j<=k} Q^_j(s, a))), with what evaluating it needs: phi(s), the
        expected psi ``E_pi[psi(s, A)] = S(s) * (pi(s) @ A)`` (the factorised psi: one
        (N, K) x (K, q) product, as greedy's gather costs) and the expected step reward. S is
        built in blocks of rows as in :meth:`greedy_step`, each used before the next.

        :param obs: (N, obs_dim) observations
        :param readout: (q, m) what E_pi[psi(s, A)] is read through, as in :meth:`greedy_step`; None: psi itself
        """
        q_used = self.theta_psi.shape[0]
        phi, points, out, blocks, (state_buffer, mixed) = self._blocked_inputs(obs, readout)
        state_weights, factor, weighted = (
            self.dynamics.psi.state_weights(),
            self.candidate_factor(),
            self.weighted_candidates(),
        )
        step_rewards = self._candidate_step_rewards(obs)
        values = step_rewards + (phi @ self.theta_phi).unsqueeze(1)  # (N, K), completed block by block
        probabilities = torch.empty_like(values)
        for rows in blocks:
            length = rows.stop - rows.start
            state = kernel_from_points(points[rows], state_weights, out=state_buffer[:length])
            values[rows] = torch.addmm(values[rows], state[:, :q_used], weighted.T)
            probabilities[rows] = softmax_policy(values[rows], self.inverse_temperature)
            destination = mixed[:length] if readout is not None else out[rows]
            expected = expected_candidate_features(state, factor, probabilities[rows], out=destination, scratch=mixed[:length])
            _write_block(expected, readout, out, rows)
        return SoftStep(probabilities, (probabilities * values).sum(1), phi, out, (probabilities * step_rewards).sum(1))

    def probabilities(self, obs: torch.Tensor) -> torch.Tensor:
        """The soft policy pi(a|s) over the candidates (without Q's state-only term, which does
        not change it): (N, obs_dim) -> (N, K)."""
        q_used = self.theta_psi.shape[0]
        weighted = self.candidate_factor()[:, :q_used] * self.theta_psi
        state = self.dynamics.state_factor(obs)[:, :q_used]
        return softmax_policy(torch.addmm(self._candidate_step_rewards(obs), state, weighted.T), self.inverse_temperature)

    def _blocked_inputs(
        self, obs: torch.Tensor, readout: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[slice], tuple[torch.Tensor, ...]]:
        """What :meth:`greedy_step` and :meth:`soft_step` build before their loop over blocks of
        rows: phi(s) (N, p), the state factor's points operand (N, state_dim + 2), the output
        (N, q) for psi or (N, m) for psi @ readout, the blocks, and two (block, q) scratch
        buffers reused by every block."""
        q = self.dynamics.q
        points = kernel_points(self.dynamics.encode_states(obs))
        out = obs.new_empty(obs.shape[0], q if readout is None else readout.shape[1])
        blocks = _row_blocks(obs.shape[0], q)
        buffers = obs.new_empty(2, blocks[0].stop if blocks else 0, q).unbind(0)
        return self.dynamics.phi(obs), points, out, blocks, buffers

    def _candidate_step_rewards(self, obs: torch.Tensor) -> torch.Tensor:
        """The known step reward at every state and candidate action: (N, obs_dim) -> (N, K)."""
        n, k = obs.shape[0], self.candidates.shape[0]
        pairs_obs = obs.unsqueeze(1).expand(n, k, *obs.shape[1:]).reshape(n * k, *obs.shape[1:])
        pairs_actions = self.candidates.expand(n, *self.candidates.shape).reshape(n * k, *self.candidates.shape[1:])
        return self.dynamics.reward.step_reward(pairs_obs, pairs_actions).reshape(n, k)

    def greedy(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The greedy actions and their Q values (with the lookahead: its actions and their looked-ahead
        values; a refined first action's is its best path's, open loop): (N, obs_dim) -> (N, act_dim) or (N,), and (N,)."""
        if self.lookahead is not None:
            actions, values, later = self.lookahead.greedy(self.dynamics.phi, obs, self.candidates)
            if not self.refines:
                return actions, values

            def q(states: torch.Tensor, path: torch.Tensor, encoded: torch.Tensor) -> torch.Tensor:
                decoded = self.dynamics.action_encoder.decode(encoded)
                return self.lookahead.action_values(self.dynamics.phi, states, decoded, path)

            return self._ascend(at_points(q, obs, later), actions, values)
        step = self.greedy_step(obs)
        return step.actions, step.values

    def _refine(
        self, obs: torch.Tensor, state: torch.Tensor, actions: torch.Tensor, values: torch.Tensor, state_only: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Projected ascent on Q(s, .) from the best candidate (:func:`projected_ascent`); a step
        recomputes only Q's terms in a, on the state factor S already built.

        :param obs: (N, obs_dim) observations
        :param state: (N, len(theta_psi)) their state factor S
        :param actions: (N, act_dim) the best candidates, in env units
        :param values: (N,) their Q
        :param state_only: (N,) Q's term without the action, <theta_phi, phi(s)>
        :return: the refined actions (N, act_dim) and their Q (N,), never below the candidate's
        """
        return self._ascend(at_points(self._q_in_action, obs, state, state_only), actions, values)

    def _ascend(
        self, q: Callable[[torch.Tensor], torch.Tensor], actions: torch.Tensor, values: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """:func:`projected_ascent` on ``q`` (of M normalised actions per row, (N, M, act_dim) -> (N, M)) from the best
        candidates (N, act_dim) in env units and their values (N,): the refined actions in env units and
        their values, each kept only where it beats the candidate's."""
        encoder, search = self.dynamics.action_encoder, self.action_search
        encoded, refined_values = projected_ascent(q, encoder.encode(actions), self.refine_steps, search.refine_lr)
        better = refined_values > values
        return torch.where(better.unsqueeze(1), encoder.decode(encoded), actions), torch.where(better, refined_values, values)

    def _q_in_action(
        self, obs: torch.Tensor, state: torch.Tensor, state_only: torch.Tensor, encoded: torch.Tensor
    ) -> torch.Tensor:
        """Q at normalised actions, differentiable in them: r(s, a) + <theta_psi, S(s) * A(a)> + <theta_phi, phi(s)>.

        :param obs: (N, obs_dim) observations
        :param state: (N, len(theta_psi)) their state factor S
        :param state_only: (N,) <theta_phi, phi(s)>
        :param encoded: (N, act_dim) actions in [-1, 1]^act_dim
        :return: (N,)
        """
        actions = self.dynamics.action_encoder.decode(encoded)
        factor = self.dynamics.action_factor(actions)[:, : state.shape[1]]
        return self.dynamics.reward.step_reward(obs, actions) + (state * factor) @ self.theta_psi + state_only

    def act(self, obs: torch.Tensor) -> torch.Tensor:
        """The greedy action, for acting: the best candidate (refined if configured), without
        Q's state-only term <theta_phi, phi(s)>, which does not change the argmax.

        :param obs: (N, obs_dim) observations
        :return: (N, act_dim) Box actions in env units or (N,) Discrete indices
        """
        if self.refines:
            return self.greedy(obs)[0]
        state = self.dynamics.state_factor(obs)[:, : self.theta_psi.shape[0]]
        return self.candidates[
            torch.addmm(self._candidate_step_rewards(obs), state, self.weighted_candidates().T).argmax(dim=1)
        ]

    def sample(self, obs: torch.Tensor) -> torch.Tensor:
        """Candidate actions drawn from the soft policy pi(.|s) (torch's default generator).

        :param obs: (N, obs_dim) observations
        :return: (N, act_dim) Box actions in env units or (N,) Discrete indices
        """
        return self.candidates[torch.multinomial(self.probabilities(obs), 1).squeeze(1)]

    def _act(self, obs: torch.Tensor, deterministic: bool) -> torch.Tensor:
        """The greedy action (by lookahead through the model of the observation with that model),
        or with the soft improvement and ``deterministic=False`` a draw from pi."""
        if self.lookahead is not None:
            return self.greedy(obs)[0]
        return self.sample(obs) if self.soft and not deterministic else self.act(obs)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> torch.Tensor:
        """The greedy action; with the soft improvement and ``deterministic=False``, a draw from pi
        (exploration belongs to learn())."""
        assert isinstance(observation, torch.Tensor)
        return self._act(observation.float(), deterministic)

    def predict(
        self,
        observation: np.ndarray,
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """The greedy action of one observation (obs_dim,) or a batch (N, obs_dim), as SB3's
        ``BasePolicy.predict`` returns it, by a short path (this policy has no train/eval modes
        and its actions lie in the action space by construction).

        :param observation: the observation(s)
        :param state: unused (no recurrent state); returned as given
        :param episode_start: unused
        :param deterministic: with the soft improvement, False draws the action from pi (True:
            the argmax of the summed Q); the smoothed greedy policy is deterministic either way
        :return: the action(s) and ``state``
        """
        if isinstance(observation, tuple) and len(observation) == 2 and isinstance(observation[1], dict):
            return super().predict(observation, state, episode_start, deterministic)  # SB3's error for the Gym/VecEnv mix-up
        obs = np.asarray(observation, dtype=np.float32)
        vectorized = is_vectorized_observation(obs, self.observation_space)
        with torch.no_grad():
            actions = self._act(
                torch.as_tensor(obs.reshape(-1, *self.observation_space.shape), device=self.device), deterministic
            )
        actions = actions.cpu().numpy().reshape((-1, *self.action_space.shape))
        return (actions if vectorized else actions.squeeze(axis=0)), state

    # ------------------------------------------------------------------ improvement
    def restart(self) -> None:
        """Forget Q (theta_phi, theta_psi = 0, the soft average's count and beta_k), as before the
        first improvement: after the model moved to new coordinates, the old weights mean nothing."""
        self.theta_phi = torch.zeros_like(self.theta_phi)
        self.theta_psi = self.theta_psi.new_zeros(0)
        self.improvements.zero_()
        self.inverse_temperature.zero_()
        if self.lookahead is not None:
            self.lookahead.restart()

    def improve(self, value_weights: torch.Tensor, gamma: float, omega: float, states: torch.Tensor | None = None) -> None:
        """Policy improvement on the linear weights of Q, with
        ``Q^_k(s, a) = r(s, a) + gamma <w_k, E_model[phi~(S') | s, a]>``:

        - smoothed greedy (section 2.2): Q_k = (1 - omega) Q_{k-1} + omega Q^_k; pi_{k+1} = greedy(Q_k);
        - soft (KL-regularised): n_k = decay n_{k-1} + 1, Qbar_k = Qbar_{k-1} + (Q^_k - Qbar_{k-1}) / n_k,
          so the running sum n_k Qbar_k = sum_j decay^{k-j} Q^_j, zero-padded as psi grows;
          pi_{k+1} = softmax(beta_k Qbar_k) (:meth:`soft_step`);
        - through the model of the observation: w itself is smoothed (:meth:`LookaheadPlanner.improve`).

        :param value_weights: (p,) w_k from policy evaluation (eq. (7))
        :param gamma: discount factor
        :param omega: smoothing step in (0, 1] (smoothed greedy only)
        :param states: (N, obs_dim) states where the spread of Qbar_k over the candidates is
            measured (soft only: the collection C; an even stride of :data:`SPREAD_STATES` of them is used)
        """
        if self.lookahead is not None:  # the value weights themselves are smoothed: acting looks ahead on V
            self.lookahead.improve(value_weights, omega)
            return
        theta_phi, theta_psi = self.dynamics.backup_weights(value_weights, gamma)
        if not self.soft:
            self.theta_phi = smooth(self.theta_phi, theta_phi, omega)
            self.theta_psi = smooth(self.theta_psi, theta_psi, omega)
            return
        self.improvements.mul_(self.improvement.decay).add_(1)  # n_k = decay n_{k-1} + 1
        step = 1.0 / float(self.improvements)
        self.theta_phi = smooth(self.theta_phi, theta_phi, step)
        self.theta_psi = smooth(self.theta_psi, theta_psi, step)
        self.inverse_temperature = self._inverse_temperature(states)

    def _inverse_temperature(self, states: torch.Tensor | None) -> torch.Tensor:
        """beta_k = beta n_k / sigma(Qbar_k), sigma from :func:`action_spread` on the states:
        pi_{k+1} proportional to exp(beta_k / n_k sum_j decay^{k-j} Q^_j), free of the reward's unit.

        :param states: (N, obs_dim) states for the spread
        :return: 0-dim tensor beta_k
        """
        beta_sum = torch.as_tensor(self.improvement.beta, dtype=self.theta_phi.dtype, device=self.device) * self.improvements
        if states is None:
            raise ValueError("the soft improvement measures Q's spread on states: pass states= to improve()")
        stride = max(1, states.shape[0] // SPREAD_STATES)
        return beta_sum / action_spread(self.candidate_q_values(states[::stride][:SPREAD_STATES]))
