"""The model update of Algorithm 1: B learned each iteration, exactly (ridge) or by SGD (eq. (6))."""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import TYPE_CHECKING

import torch
from stable_baselines3.common.logger import Logger

from cme_agent.buffer import Transitions, TransitionStore
from cme_agent.config import ModelUpdateConfig
from cme_agent.dynamics.cme import CMEDynamics

if TYPE_CHECKING:
    from cme_agent.lookahead import LookaheadPlanner
    from cme_agent.policy import CMEPolicy

MIN_HELD_OUT = 10
"""Fewest held-out non-terminal transitions ``kind="auto"`` measures R^2 on; with fewer it keeps the CME."""
DIVERGENCE_FACTOR = 10.0
"""An SGD update that multiplies the loss on a check batch by more than this is undone."""


class ModelTrainer:
    """Owns how B is learned (``model_update``): the exact ridge refit on a fixed-size sample of
    D or the paper's SGD steps, the guard against a diverging SGD step and the held-out loss.

    Every call touches a fixed-size sample of D (or only its new rows), so its cost is flat in |D|.

    :param config: the ``model_update`` settings
    """

    def __init__(self, config: ModelUpdateConfig) -> None:
        self.config = config
        self.step_scale = 1.0
        """Multiplier of ``learning_rate``, halved each time an SGD update diverged (saved with the agent)."""

    def refit_sample(self, store: TransitionStore, generator: torch.Generator) -> Transitions:
        """The transitions B is refit on: all of D while it holds at most ``refit_size`` of them,
        else that many drawn uniformly with replacement (the cost stays O(refit_size)).

        :param store: D
        :param generator: the agent's torch RNG
        """
        if len(store) > self.config.refit_size:
            return store.sample(self.config.refit_size, generator)
        return store.get(slice(0, len(store)))

    def choose_kind(
        self, policy: CMEPolicy, store: TransitionStore, holdout: TransitionStore, logger: Logger
    ) -> ModelUpdateConfig:
        """``kind="auto"``: ``"observation"`` where the linear model of s' - s fitted on the first
        ``refit_size`` transitions of D reaches a held-out R^2 of ``auto_r2`` on every dim
        (:meth:`LookaheadPlanner.change_r2` on the first ``holdout_size`` held-out ones), else
        ``"cme"``; the policy is told (:meth:`CMEPolicy.choose_model`) and the choice said. It draws
        nothing from the agent's RNG, so a run is the one that kind would have made from the start.

        :param policy: the agent's policy, whose ``model_kind`` is ``"auto"``
        :param store: D
        :param holdout: the held-out transitions
        :param logger: SB3's logger
        :return: the settings with the chosen kind
        """
        held_out = holdout.get(slice(0, min(len(holdout), self.config.holdout_size)))
        if int((~held_out.terminated).sum()) < MIN_HELD_OUT:
            kind, reason = "cme", f"fewer than {MIN_HELD_OUT} held-out transitions to measure a linear model on"
        else:
            r2 = policy.lookahead.change_r2(store.get(slice(0, min(len(store), self.config.refit_size))), held_out)
            worst = int(r2.argmin())
            kind = "observation" if float(r2[worst]) >= self.config.auto_r2 else "cme"
            reason = (
                f"a linear model of s' - s explains a held-out R^2 of {float(r2[worst]):.3f} of observation dim "
                f"{worst}, its worst (the model of the observation needs {self.config.auto_r2} on every dim)"
            )
        policy.choose_model(kind)
        said = "the model of the observation (acting looks ahead)" if kind == "observation" else "the CME"
        logger.info(f"model_update.kind='auto' chose {said}: {reason}")
        self.config = dataclasses.replace(self.config, kind=kind)
        return self.config

    def fit_observation_model(
        self,
        lookahead: LookaheadPlanner,
        store: TransitionStore,
        holdout: TransitionStore,
        generator: torch.Generator,
        logger: Logger,
    ) -> None:
        """With ``kind="observation"``: refit the model of the observation on :meth:`refit_sample`
        and log its error on ``holdout_size`` held-out transitions as ``train/model_loss``.

        :param lookahead: the planner that owns the model
        :param store: D
        :param holdout: the held-out transitions
        :param generator: the agent's torch RNG
        :param logger: SB3's logger
        """
        held_out = holdout.sample(self.config.holdout_size, generator) if len(holdout) else None
        lookahead.fit(self.refit_sample(store, generator), held_out, logger)

    def update(
        self,
        dynamics: CMEDynamics,
        store: TransitionStore,
        holdout: TransitionStore,
        generator: torch.Generator,
        logger: Logger,
        iteration: int,
    ) -> None:
        """Learn B on D: with ``method="ridge"`` the
        exact minimiser of loss (4) plus eq. (6)'s ridge on :meth:`refit_sample`; with ``"sgd"``
        ``n_steps`` minibatch steps of eq. (6).
        A diverging SGD update (non-finite B, or the loss on a check batch up tenfold) is undone
        and the step halved for the rest of the run, with a warning.

        Logs ``train/model_loss_train``, ``train/model_loss`` (held out) and, with SGD,
        ``train/model_step_scale``.

        :param dynamics: the model, updated in place
        :param store: D
        :param holdout: the held-out transitions
        :param generator: the agent's torch RNG
        :param logger: SB3's logger
        :param iteration: the iteration number, for the divergence warning
        """
        if dynamics.q == 0:
            return
        self.fit(dynamics, store, generator, logger, iteration)
        if len(holdout) > 0:
            psi, targets = dynamics.regression_data(holdout.sample(self.config.holdout_size, generator))
            logger.record("train/model_loss", float(dynamics.loss(psi, targets)))

    def fit(
        self, dynamics: CMEDynamics, store: TransitionStore, generator: torch.Generator, logger: Logger, iteration: int
    ) -> None:
        """B's update on D (ridge or SGD, as configured); logs ``train/model_loss_train``.

        :param dynamics: the model, q > 0
        :param store: D
        :param generator: the agent's torch RNG
        :param logger: SB3's logger
        :param iteration: the iteration number, for the divergence warning
        """
        config = self.config
        if config.method == "ridge":
            logger.record("train/model_loss_train", dynamics.refit_weights(self.refit_sample(store, generator), config.l2))
            return
        logger.record("train/model_loss_train", self._sgd_update(dynamics, store, generator, iteration))
        logger.record("train/model_step_scale", self.step_scale)

    def _sgd_update(self, dynamics: CMEDynamics, store: TransitionStore, generator: torch.Generator, iteration: int) -> float:
        """``n_steps`` SGD steps of eq. (6) on consecutive minibatches of D, undone if they diverge.

        :return: the loss on the check batch after the update (mean squared residual per transition)
        """
        config = self.config
        check_psi, check_targets = dynamics.regression_data(store.sample(config.batch_size * 4, generator))
        loss_before = float(dynamics.loss(check_psi, check_targets))
        backup = dynamics.weights.clone()
        indices = [torch.randint(len(store), (config.batch_size,), generator=generator) for _ in range(config.n_steps)]
        batches = store.get(torch.cat(indices).to(dynamics.weights.device))
        dynamics.sgd_update(batches, config.batch_size, config.learning_rate * self.step_scale, config.l2)
        loss_after = float(dynamics.loss(check_psi, check_targets))
        if not (math.isfinite(loss_after) and loss_after <= DIVERGENCE_FACTOR * loss_before + 1e-8):
            dynamics.weights.copy_(backup)
            self.step_scale /= 2
            warnings.warn(
                f"model update diverged at iteration {iteration} (check loss {loss_before:.3g} -> {loss_after:.3g}); "
                f"update undone, step size halved to {config.learning_rate * self.step_scale:.3g}",
                RuntimeWarning,
                stacklevel=3,
            )
        return loss_after
