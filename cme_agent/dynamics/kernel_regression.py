"""Batch kernel ridge regression of the CME (Grunewalder et al. 2012), the 'Kernel' baseline.

mu(s, a) = sum_i beta_i(s, a) y_i with beta(s, a) = (K + n lambda I)^{-1} k((s, a), .), that
is B = Y^T (K + n lambda I)^{-1} on psi = the kernels centred at every data point.
Solving it costs O(n^3) in the number n of transitions, which is the point of the comparison.
"""

from __future__ import annotations

import torch


def kernel_ridge_weights(gram: torch.Tensor, targets: torch.Tensor, l2: float) -> torch.Tensor:
    """B = Y^T (K + n lambda I)^{-1}, solved by Cholesky in float64.

    :param gram: (n, n) kernel matrix K of the data
    :param targets: (n, p) regression targets Y
    :param l2: ridge lambda (scaled by n, as in the loss (1/2n) sum ||.||^2 + lambda/2 ||B||^2)
    :return: (p, n) weights B
    """
    n = gram.shape[0]
    system = gram.double() + n * l2 * torch.eye(n, dtype=torch.float64, device=gram.device)
    factor = torch.linalg.cholesky(system)
    return torch.cholesky_solve(targets.double(), factor).T.to(targets.dtype)
