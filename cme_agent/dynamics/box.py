"""The observation box of dims without usable bounds: estimated from the first data, expanded later."""

from __future__ import annotations

import torch
from stable_baselines3.common.logger import Logger

from cme_agent.buffer import Transitions, TransitionStore
from cme_agent.dynamics.cme import CMEDynamics
from cme_agent.dynamics.trainer import ModelTrainer


class ObservationBox:
    """Owns the estimated normalisation box (``policy_kwargs.observation``), and beside it phi's
    data metric (``phi.metric="data"``): both are fitted on the data of the random phase. Later,
    when more than ``expand_outside`` of an iteration's new observations fall outside the box in
    ``expand_after`` successive iterations, it is expanded to cover those iterations' new
    observations (at most ``max_expansions`` times): psi's centres keep their place, a data metric
    is refit, and B is refit on the trainer's sample of D. The new observations, not all of D, set
    the expansion: the quantiles of D would leave out a drift that is a small share of D, and the
    policy would meet the box's edge again at once.
    """

    def __init__(self) -> None:
        self.pending: list[torch.Tensor] = []
        """(2 m, obs_dim) new observations of each successive iteration that outgrew the box so far (saved)."""

    def update(
        self,
        dynamics: CMEDynamics,
        new_data: Transitions,
        store: TransitionStore,
        holdout: TransitionStore,
        trainer: ModelTrainer,
        generator: torch.Generator,
        logger: Logger,
    ) -> bool:
        """Fit the box (and phi's data metric) on the first data, or expand it (and refit phi's
        metric) when the new data has outgrown it.

        Logs the encoder's line and ``train/observation_box_expansions``.

        :param dynamics: the model (its observation encoder, psi and B are changed in place)
        :param new_data: the transitions of this iteration
        :param store: D
        :param holdout: the held-out transitions (they count for the first fit)
        :param trainer: the model trainer, whose sample of D B is refit on after an expansion
        :param generator: the agent's torch RNG
        :param logger: SB3's logger
        :return: True when the box was expanded: the values planned in the old coordinates are void
        """
        encoder = dynamics.obs_encoder
        if encoder.needs_fit or dynamics.phi.needs_fit:
            states = observed_states(store, holdout)
            for coordinates in (encoder, dynamics.phi):
                if coordinates.needs_fit:
                    logger.info(coordinates.fit(states))
            return False
        config = encoder.config
        if not encoder.fit_dims or int(encoder.expansions) >= config.max_expansions or len(new_data) == 0:
            return False
        new_states = torch.cat([new_data.obs, new_data.next_obs])
        if encoder.outside_share(new_states) <= config.expand_outside:
            self.pending = []
            return False
        self.pending.append(new_states)
        if len(self.pending) < config.expand_after:
            return False
        new_states, self.pending = torch.cat(self.pending), []
        sample = trainer.refit_sample(store, generator)
        logger.info(dynamics.expand_observation_box(new_states, sample, trainer.config.l2))
        logger.record("train/observation_box_expansions", int(encoder.expansions))
        return True


def observed_states(store: TransitionStore, holdout: TransitionStore) -> torch.Tensor:
    """(2 |D|, obs_dim): every state and successor of D and of the held-out transitions."""
    data = [part.get(slice(0, len(part))) for part in (store, holdout) if len(part) > 0]
    return torch.cat([tensor for batch in data for tensor in (batch.obs, batch.next_obs)])
