"""Feature selection of Algorithm 1: matching pursuit over kernels at the new points (eq. (5))."""

from __future__ import annotations

import torch
from stable_baselines3.common.logger import Logger

from cme_agent.buffer import Transitions, TransitionStore
from cme_agent.config import FeatureSelectionConfig
from cme_agent.dynamics.cme import CMEDynamics
from cme_agent.dynamics.matching_pursuit import matching_pursuit


class FeatureSelector:
    """Owns how psi grows (``feature_selection``): the dictionary of Gaussian kernels centred at
    the m new state-actions at every bandwidth, matching pursuit on the model residual over a
    fixed-size subsample of D, and the budget on q.

    :param config: the ``feature_selection`` settings
    """

    def __init__(self, config: FeatureSelectionConfig) -> None:
        self.config = config

    def budget(self, q: int) -> int:
        """Features this iteration may add: ``max_features``, less where ``max_total_features`` is near.

        :param q: the current number of features
        """
        return int(min(self.config.max_features, self.config.max_total_features - q))

    def select(
        self,
        dynamics: CMEDynamics,
        new_data: Transitions,
        store: TransitionStore,
        generator: torch.Generator,
        logger: Logger,
    ) -> int:
        """Eq. (5): matching pursuit on the residual Y - B psi over the new points plus
        ``subsample_size`` transitions of D; the picked atoms join psi and their weights times
        theta_k join B as new columns.

        Logs ``train/features_added``, ``train/n_features`` and ``train/mp_residual_reduction``.

        :param dynamics: the model, grown in place
        :param new_data: the m transitions of this iteration (the dictionary's centres)
        :param store: D
        :param generator: the agent's torch RNG
        :param logger: SB3's logger
        :return: the number of features added
        """
        config = self.config
        budget = self.budget(dynamics.q)
        added = 0
        if len(new_data) > 0 and budget > 0:
            batch = new_data.concat(store.sample(config.subsample_size, generator))
            if (message := dynamics.calibrate_reward_row(batch.rewards, batch.terminated)) is not None:
                logger.info(message)
            z = dynamics.encode(batch.obs, batch.actions)
            residual = dynamics.targets(batch) - dynamics.predict(dynamics.psi(z))  # (N, p_out)
            bandwidths = torch.tensor(config.bandwidths, dtype=z.dtype, device=z.device)
            atoms, columns = dynamics.dictionary(z, z[: len(new_data)], bandwidths, config.control_affine)
            result = matching_pursuit(atoms, residual, config.threshold, budget, config.orthogonal)
            picked = columns[result.indices]
            dynamics.grow(picked.centres, picked.bandwidths, config.theta * result.weights.T, picked.action_basis)
            if result.energy_before > 0:
                logger.record("train/mp_residual_reduction", 1 - result.energy_after / result.energy_before)
            added = len(result.indices)
        return record_growth(logger, added, dynamics.q)


def record_growth(logger: Logger, added: int, q: int) -> int:
    """Log ``train/features_added`` and ``train/n_features`` (q); return ``added``."""
    logger.record("train/features_added", added)
    logger.record("train/n_features", q)
    return added
