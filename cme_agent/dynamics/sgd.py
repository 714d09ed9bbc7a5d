"""Online refinement of B by stochastic gradient descent (paper eq. (6))."""

from __future__ import annotations

import torch

from cme_agent.devices import host_reads_are_free


def sgd_step(weights: torch.Tensor, psi: torch.Tensor, targets: torch.Tensor, learning_rate: float, l2: float) -> None:
    """One minibatch step of eq. (6), in place:
    ``B <- B + eta (1/b) sum_j (y_j - B psi_j) psi_j^T - eta lambda B``.

    The step is normalised, ``eta = learning_rate / mean_j ||psi_j||^2`` (normalised least
    mean squares): the largest eigenvalue of the minibatch Gram matrix is at most that mean,
    so any ``learning_rate`` in (0, 2) is stable whatever the number q of features.

    :param weights: (p, q) the model B, updated in place
    :param psi: (b, q) features psi(s_j, a_j) of the minibatch
    :param targets: (b, p) regression targets y_j (phi(s'_j), or phi(s'_j) - phi(s_j));
        overwritten (the step's error is computed in their place: no copy, no allocation)
    :param learning_rate: normalised step in (0, 2)
    :param l2: ridge coefficient lambda
    """
    mean_sq_norm = torch.linalg.vector_norm(psi).square() / psi.shape[0]
    eta = learning_rate / mean_sq_norm.clamp_min(1e-12)  # a 0-dim tensor: no host synchronisation
    error = targets.addmm_(psi, weights.T, alpha=-1).mul_(eta / psi.shape[0])
    if host_reads_are_free(weights.device):  # the decay rides on the product: one pass over B
        weights.addmm_(error.T, psi, beta=1 - float(eta) * l2)
    else:  # no host synchronisation: the decay is a pass of its own
        weights.mul_(1 - eta * l2).addmm_(error.T, psi)
