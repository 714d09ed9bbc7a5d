"""KernelPolicyIteration: the 'Kernel' baseline of the paper's experiments (section 3.1).

The same policy-iteration loop as :class:`~cme_agent.CMEPolicyIteration`; only the two steps
that learn the model differ (:meth:`~KernelPolicyIteration.feature_selection` and
:meth:`~KernelPolicyIteration.model_update`). There is no feature selection: every collected
state-action becomes a kernel feature, and the CME is relearned every iteration by kernel ridge
regression on all data collected so far, in O(|D|^3). psi
still only grows by appending, so the Q smoothing is unchanged. As in the paper, it should
be run with less data per iteration to stay feasible.
"""

from __future__ import annotations

from typing import Any

import torch

from cme_agent.algorithm import CMEPolicyIteration
from cme_agent.buffer import Transitions
from cme_agent.config import check_non_negative, check_positive
from cme_agent.dynamics.kernel_regression import kernel_ridge_weights


class KernelPolicyIteration(CMEPolicyIteration):
    """Policy iteration with a batch kernel ridge regression CME, relearned on all data each iteration.

    :param kernel_bandwidth: width of the Gaussian kernel, in normalised state-action units
    :param kernel_l2: ridge lambda of the kernel regression
    :param kwargs: as :class:`~cme_agent.CMEPolicyIteration` (``feature_selection`` and
        ``model_update`` other than ``holdout_*`` and ``feature_dynamics`` are unused)
    """

    def __init__(self, *args: Any, kernel_bandwidth: float = 0.3, kernel_l2: float = 1e-4, **kwargs: Any) -> None:
        check_positive("kernel_bandwidth", kernel_bandwidth)
        check_non_negative("kernel_l2", kernel_l2)
        self.kernel_bandwidth = kernel_bandwidth
        self.kernel_l2 = kernel_l2
        super().__init__(*args, **kwargs)

    def _constructor_kwargs(self) -> dict[str, Any]:
        return {**super()._constructor_kwargs(), "kernel_bandwidth": self.kernel_bandwidth, "kernel_l2": self.kernel_l2}

    def feature_selection(self, new_data: Transitions) -> int:
        """No selection: a kernel centred at every new state-action joins psi (with zero weights,
        set by the next :meth:`model_update`).

        :param new_data: the transitions collected in this iteration
        :return: the number of features added (all of them)
        """
        dynamics = self.dynamics
        with self._timed("feature_selection"):
            z = dynamics.encode(new_data.obs, new_data.actions)
            bandwidths = torch.full((len(z),), self.kernel_bandwidth, dtype=z.dtype, device=z.device)
            dynamics.grow(z, bandwidths, dynamics.weights.new_zeros(dynamics.weights.shape[0], len(z)))
            return self._record_features_added(len(z))

    def model_update(self) -> None:
        """Relearn B = Y^T (K + n lambda I)^{-1} on ALL training data, O(|D|^3)."""
        dynamics = self.dynamics
        with self._timed("model_update"):
            if dynamics.q == 0:
                return
            psi, targets = dynamics.regression_data(self.store.get(slice(0, len(self.store))))
            dynamics.weights = kernel_ridge_weights(psi, targets, self.kernel_l2)
            self.logger.record("train/model_loss_train", float(dynamics.loss(psi, targets)))
            self._record_holdout_loss()
