"""Policy evaluation of Algorithm 1: value weights of the current policy on a collection C (eq. (7))."""

from __future__ import annotations

import functools

import torch
from stable_baselines3.common.logger import Logger

from cme_agent.buffer import TransitionStore
from cme_agent.config import EvaluationConfig, collection_size_for
from cme_agent.dynamics.cme import CMEDynamics
from cme_agent.planning import (
    FactoredResidual,
    bellman_residual_rms,
    bellman_residual_weights,
    factored_dual_weights,
    factored_is_cheaper,
)
from cme_agent.policy import CMEPolicy, GreedyStep, SoftStep


class PolicyEvaluator:
    """Owns policy evaluation (``evaluation``): the collection C and the solve of eq. (7), in its
    primal form or, where phi's Gram matrix is cheap and that costs less, in its dual form on
    the factors of the residual map.

    :param config: the ``evaluation`` settings
    :param gamma: the discount factor, in (0, 1)
    """

    def __init__(self, config: EvaluationConfig, gamma: float) -> None:
        self.config = config
        self.gamma = gamma
        self.value_weights: torch.Tensor | None = None
        """(p,) the last w (what the diagnostics of benchmarks/ read; None after phi changed)."""

    def restart(self) -> None:
        """Forget the last value weights (phi changed: they belong to the old features)."""
        self.value_weights = None

    def draw_collection(self, dynamics: CMEDynamics, store: TransitionStore, generator: torch.Generator) -> torch.Tensor:
        """The collection C of eq. (7): |C| states (``collection_size``, by default following p), a
        ``uniform_fraction`` of them uniform over the normalisation box (terminal states excluded),
        the rest drawn from D.

        :param dynamics: the model (its box, its width p and the termination rule)
        :param store: D
        :param generator: the agent's torch RNG
        :return: (|C|, obs_dim) states
        """
        size = collection_size_for(dynamics.p, self.config)
        n_uniform = round(self.config.uniform_fraction * size)
        uniform = dynamics.obs_encoder.sample_uniform(2 * n_uniform, generator)
        is_terminal = dynamics.reward.is_terminal
        if is_terminal is not None:
            uniform = uniform[~is_terminal(uniform)]
        uniform = uniform[:n_uniform]
        from_data = store.sample(size - len(uniform), generator).obs
        return torch.cat([uniform, from_data])

    def evaluate(
        self, policy: CMEPolicy, states: torch.Tensor, logger: Logger, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """Eq. (7): w minimising ``||Phi_C w - (r + gamma Phi'_C w)||^2`` plus a ridge, with
        ``Phi'_C`` the model's expected next phi at the policy's actions. A soft policy is
        evaluated in expectation over the candidates: ``Phi'_C = sum_a pi(a|s) E_model[phi~(S') | s, a]``
        and the rewards likewise (both linear in psi, read at E_pi[psi(s, A)]). With the model of
        the observation, :meth:`LookaheadPlanner.evaluate <cme_agent.lookahead.LookaheadPlanner.evaluate>`.

        Logs ``train/bellman_residual``, ``train/q_mean``, ``train/value_mean`` and, for a soft
        policy, ``train/policy_entropy`` and ``train/inverse_temperature``.

        :param policy: the policy to evaluate (its model is ``policy.dynamics``)
        :param states: (|C|, obs_dim) the collection C
        :param logger: SB3's logger
        :param generator: the agent's torch RNG (the lookahead planner's draw of candidates)
        :return: (p,) value weights w, V(s) = <w, phi(s)>
        """
        config, dynamics = self.config, policy.dynamics
        if policy.lookahead is not None:
            lookahead = policy.lookahead
            self.value_weights = lookahead.evaluate(dynamics.phi, states, policy.candidates, config.l2, logger, generator)
            return self.value_weights
        factored = self.factored(dynamics, len(states))
        step = _policy_step(policy, states, None if factored else dynamics.readout(), logger)
        if factored:  # psi (|C|, q) is kept instead of Phi'_C (|C|, p); A A^T comes from phi's Gram matrix
            rewards = _step_rewards(dynamics, states, step) + dynamics.linear_reward(step.phi, step.psi)
            gram = functools.partial(dynamics.phi.gram, states)
            residual = FactoredResidual(step.phi, gram, step.psi, dynamics.phi_weights, self.gamma, dynamics.feature_dynamics)
            weights = factored_dual_weights(residual, rewards, config.l2)
            rms = float(residual.matvec(weights).sub_(rewards).square_().mean().sqrt())
        else:  # psi was read through B block by block: (|C|, q) is never stored
            next_phi, model_rewards = dynamics.read(step.phi, step.psi)
            rewards = _step_rewards(dynamics, states, step) + model_rewards
            weights = bellman_residual_weights(step.phi, next_phi, rewards, self.gamma, config.l2)
            rms = bellman_residual_rms(step.phi, next_phi, rewards, self.gamma, weights)
        self.value_weights = weights
        logger.record("train/bellman_residual", rms)
        logger.record("train/q_mean", float(step.values.mean()))
        logger.record("train/value_mean", float((step.phi @ weights).mean()))
        return weights

    def factored(self, dynamics: CMEDynamics, size: int) -> bool:
        """Whether eq. (7) is solved on the factors of its residual map (:class:`FactoredResidual`):
        in its dual form, with a phi whose Gram matrix is cheap, where that costs less than the
        primal solve.

        :param dynamics: the model (phi, p and q)
        :param size: |C|
        """
        return dynamics.phi.fast_gram and factored_is_cheaper(size, dynamics.p, dynamics.q)


def _policy_step(
    policy: CMEPolicy, states: torch.Tensor, readout: torch.Tensor | None, logger: Logger
) -> GreedyStep | SoftStep:
    """The policy's step on C (greedy, or soft with its entropy logged), psi read through ``readout``."""
    if not policy.soft:
        return policy.greedy_step(states, readout)
    step = policy.soft_step(states, readout)
    probabilities = step.probabilities
    entropy = -(probabilities * probabilities.clamp_min(1e-30).log()).sum(1).mean()  # nats; log K is uniform
    logger.record("train/policy_entropy", float(entropy))
    logger.record("train/inverse_temperature", float(policy.inverse_temperature))
    return step


def _step_rewards(dynamics: CMEDynamics, states: torch.Tensor, step: GreedyStep | SoftStep) -> torch.Tensor:
    """The known step reward at the policy's actions on C (its expectation for the soft policy): (|C|,)."""
    return step.step_rewards if isinstance(step, SoftStep) else dynamics.reward.step_reward(states, step.actions)
