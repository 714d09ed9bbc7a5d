"""Policy evaluation (paper eq. (7)) and smoothed policy improvement (section 2.2).

Shapes: n = |C| states in the collection, p = width of phi, q = width of psi.
"""

from __future__ import annotations

import torch


def _regularised_solve(lhs: torch.Tensor, rhs: torch.Tensor, l2: float) -> torch.Tensor:
    """Solve (lhs + l2 * mean(diag(lhs)) I) w = rhs in float64; the ridge keeps any system solvable."""
    lhs, rhs = lhs.double(), rhs.double()
    scale = lhs.diagonal().abs().mean().clamp_min(1e-12)
    eye = torch.eye(lhs.shape[0], dtype=lhs.dtype, device=lhs.device)
    return torch.linalg.solve(lhs + l2 * scale * eye, rhs)


def bellman_residual_weights(
    phi: torch.Tensor, next_phi: torch.Tensor, rewards: torch.Tensor, gamma: float, l2: float
) -> torch.Tensor:
    """Bellman residual minimisation, eq. (7):
    ``w = argmin_w ||Phi_C w - (r + gamma Phi'_C w)||^2 + ridge``, solved exactly.

    :param phi: (n, p) Phi_C, phi at the states of C
    :param next_phi: (n, p) Phi'_C = E_model[phi~(S') | s_i, pi(s_i)] (= Psi_C B^T in feature form)
    :param rewards: (n,) expected rewards r(s_i, pi(s_i))
    :param gamma: discount factor
    :param l2: ridge, relative to the mean diagonal of the normal equations
    :return: (p,) value weights w, V(s) = <w, phi(s)>
    """
    residual_map = (phi - gamma * next_phi).double()
    return _regularised_solve(residual_map.T @ residual_map, residual_map.T @ rewards.double(), l2).to(phi.dtype)


def lstd_weights(phi: torch.Tensor, next_phi: torch.Tensor, rewards: torch.Tensor, gamma: float, l2: float) -> torch.Tensor:
    """The fixed point of the projected Bellman equation (LSTD), the alternative to eq. (7):
    ``Phi_C^T (Phi_C - gamma Phi'_C) w = Phi_C^T r``. Arguments and result as
    :func:`bellman_residual_weights`."""
    phi64 = phi.double()
    lhs = phi64.T @ (phi64 - gamma * next_phi.double())
    return _regularised_solve(lhs, phi64.T @ rewards.double(), l2).to(phi.dtype)


def bellman_residual_descent(
    phi: torch.Tensor,
    next_phi: torch.Tensor,
    rewards: torch.Tensor,
    gamma: float,
    l2: float,
    initial: torch.Tensor,
    steps: int,
) -> torch.Tensor:
    """Eq. (7) by gradient descent warm-started from the previous weights:
    O(|C| p^2 + steps p^2), as in the paper's complexity statement.

    Minimises ``(1/2n) ||A w - r||^2 + (l2 s / 2) ||w||^2`` with ``A = Phi_C - gamma Phi'_C``,
    s the mean diagonal of A^T A / n, by Nesterov's accelerated gradient with step 1/L.

    :param initial: (p,) starting weights (the previous w, zero-padded if needed)
    :param steps: number of gradient steps
    :return: (p,) value weights
    """
    residual_map = (phi - gamma * next_phi).double()
    n = residual_map.shape[0]
    gram = residual_map.T @ residual_map / n
    ridge = l2 * gram.diagonal().mean().clamp_min(1e-12)
    gram = gram + ridge * torch.eye(gram.shape[0], dtype=gram.dtype, device=gram.device)
    target = residual_map.T @ rewards.double() / n
    lipschitz = float(torch.linalg.eigvalsh(gram)[-1])
    w = initial.double().clone()
    previous = w.clone()
    for step in range(steps):
        lookahead = w + (step / (step + 3)) * (w - previous)
        previous = w
        w = lookahead - (gram @ lookahead - target) / lipschitz
    return w.to(phi.dtype)


def bellman_residual_rms(
    phi: torch.Tensor, next_phi: torch.Tensor, rewards: torch.Tensor, gamma: float, w: torch.Tensor
) -> float:
    """Root-mean-square Bellman residual of w over C under the model, ``||Phi w - r - gamma Phi' w|| / sqrt(n)``."""
    return float(((phi - gamma * next_phi) @ w - rewards).pow(2).mean().sqrt())


def smooth(previous: torch.Tensor, estimate: torch.Tensor, omega: float) -> torch.Tensor:
    """Policy improvement, Q_k = (1 - omega) Q_{k-1} + omega Q^_k, on the linear weights of Q.

    psi only grows by appending, so the previous weights are zero-padded to the new width
    (DESIGN.md, fact 2): no history of earlier Q functions is kept.

    :param previous: (q_old,) weights of Q_{k-1}
    :param estimate: (q_new,) weights of Q^_k, q_new >= q_old
    :param omega: step in [0, 1]
    :return: (q_new,) weights of Q_k
    """
    padded = torch.nn.functional.pad(previous, (0, estimate.shape[0] - previous.shape[0]))
    return (1 - omega) * padded + omega * estimate
