"""KernelPolicyIteration: the 'Kernel' baseline of the paper's experiments (section 3.1).

The same policy-iteration loop as :class:`~cme_agent.CMEPolicyIteration`; only the owners of the
two steps that learn the model differ (:class:`KernelFeatures`, :class:`KernelRidgeTrainer`).
There is no feature selection: every collected state-action becomes a kernel feature, and the
CME is relearned every iteration by kernel ridge regression on all data collected so far, in
O(|D|^3). psi still only grows by appending, so the Q smoothing is unchanged. As in the paper,
it should be run with less data per iteration to stay feasible.
"""

from __future__ import annotations

from typing import Any

import torch
from stable_baselines3.common.logger import Logger

from cme_agent.algorithm import CMEPolicyIteration
from cme_agent.buffer import Transitions, TransitionStore
from cme_agent.config import FeatureSelectionConfig, ModelUpdateConfig, check_non_negative, check_positive
from cme_agent.dynamics.cme import CMEDynamics
from cme_agent.dynamics.kernel_regression import kernel_ridge_weights
from cme_agent.dynamics.selection import FeatureSelector, record_growth
from cme_agent.dynamics.trainer import ModelTrainer
from cme_agent.persistence import plain


class KernelFeatures(FeatureSelector):
    """No selection: a kernel centred at every new state-action joins psi, with zero weights
    that the next model update sets.

    :param config: the ``feature_selection`` settings (unused)
    :param bandwidth: width of every kernel, in normalised state-action units
    """

    def __init__(self, config: FeatureSelectionConfig, bandwidth: float) -> None:
        super().__init__(config)
        self.bandwidth = bandwidth

    def select(
        self, dynamics: CMEDynamics, new_data: Transitions, store: TransitionStore, generator: torch.Generator, logger: Logger
    ) -> int:
        """Add a kernel at each of the m new state-actions; return m."""
        z = dynamics.encode(new_data.obs, new_data.actions)
        bandwidths = torch.full((len(z),), self.bandwidth, dtype=z.dtype, device=z.device)
        dynamics.grow(z, bandwidths, dynamics.weights.new_zeros(dynamics.weights.shape[0], len(z)))
        return record_growth(logger, len(z), dynamics.q)


class KernelRidgeTrainer(ModelTrainer):
    """B = Y^T (K + n lambda I)^{-1} relearned on ALL training data each iteration, O(|D|^3).

    :param config: the ``model_update`` settings (only ``holdout_*`` and ``feature_dynamics`` are used)
    :param l2: ridge lambda of the kernel regression
    """

    def __init__(self, config: ModelUpdateConfig, l2: float) -> None:
        super().__init__(config)
        self.l2 = l2

    def fit(
        self, dynamics: CMEDynamics, store: TransitionStore, generator: torch.Generator, logger: Logger, iteration: int
    ) -> None:
        """Kernel ridge regression of the targets on psi over all of D; logs ``train/model_loss_train``."""
        psi, targets = dynamics.regression_data(store.get(slice(0, len(store))))
        dynamics.weights = kernel_ridge_weights(psi, targets, self.l2)
        logger.record("train/model_loss_train", float(dynamics.loss(psi, targets)))


class KernelPolicyIteration(CMEPolicyIteration):
    """Policy iteration with a batch kernel ridge regression CME, relearned on all data each iteration.

    :param kernel_bandwidth: width of the Gaussian kernel, in normalised state-action units
    :param kernel_l2: ridge lambda of the kernel regression
    :param kwargs: as :class:`~cme_agent.CMEPolicyIteration` (``feature_selection`` and
        ``model_update`` other than ``holdout_*`` and ``feature_dynamics`` are unused; the kind is the CME)
    """

    def __init__(self, *args: Any, kernel_bandwidth: float = 0.3, kernel_l2: float = 1e-4, **kwargs: Any) -> None:
        check_positive("kernel_bandwidth", kernel_bandwidth)
        check_non_negative("kernel_l2", kernel_l2)
        self.kernel_bandwidth = kernel_bandwidth
        self.kernel_l2 = kernel_l2
        model_update = plain(kwargs.pop("model_update", None) or {})
        if model_update.get("kind", "cme") not in ("auto", "cme"):
            raise ValueError(f"model_update.kind={model_update['kind']!r} is invalid for the Kernel baseline: a CME")
        super().__init__(*args, model_update={**model_update, "kind": "cme"}, **kwargs)

    def _constructor_kwargs(self) -> dict[str, Any]:
        return {**super()._constructor_kwargs(), "kernel_bandwidth": self.kernel_bandwidth, "kernel_l2": self.kernel_l2}

    def _make_model_learners(self) -> tuple[FeatureSelector, ModelTrainer]:
        return (
            KernelFeatures(self.feature_selection_config, self.kernel_bandwidth),
            KernelRidgeTrainer(self.model_update_config, self.kernel_l2),
        )
