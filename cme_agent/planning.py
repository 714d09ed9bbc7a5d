"""Policy evaluation (paper eq. (7)), smoothed policy improvement (section 2.2) and the soft
(KL-regularised) policy of :class:`~cme_agent.config.ImprovementConfig`.

Shapes: n = |C| states in the collection, p = width of phi, q = width of psi.

The evaluation's large products (A^T A, A A^T, A^T r, with A an n x p matrix) run in the
input dtype (float32 by default); only the small p x p (or n x n) system is solved in
float64 (:mod:`cme_agent.linalg`: a blocked Cholesky in place for the symmetric
Bellman-residual systems, whose products are built as their lower triangle).
Ridges are added in place. When n < p the solver switches to the dual form,
an n x n system, which gives the same weights to rounding (the push-through identity
``(X^T A + lambda I)^{-1} X^T = X^T (A X^T + lambda I)^{-1}``). With a cheap Gram matrix of phi
the dual system is built from the factors of A instead (:class:`FactoredResidual`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from cme_agent.linalg import gram_solve, lower_gram, lower_solve_, transposed_product

SYSTEM_BYTES_PER_ENTRY = 8
"""Bytes per entry of the evaluation's m x m system, m = min(|C|, p): the float64 system, built as
its lower triangle and factorised in place."""

MATRIX_BYTES_PER_ENTRY = 12
"""Bytes per entry of the evaluation's |C| x p float32 matrices: Phi_C, Phi'_C and A."""


def evaluation_memory_bytes(width: int, collection_size: int) -> int:
    """Peak bytes the exact evaluation holds for a phi of width p on a collection of n states:
    ``12 n p`` (three n x p float32 matrices) + ``8 min(n, p)^2`` (the system, see
    :data:`SYSTEM_BYTES_PER_ENTRY`).

    :param width: p, the width of phi
    :param collection_size: n = |C|
    :return: bytes
    """
    smaller = min(width, collection_size)
    return MATRIX_BYTES_PER_ENTRY * collection_size * width + SYSTEM_BYTES_PER_ENTRY * smaller * smaller


def _ridge(diagonal_sum: torch.Tensor, width: int, l2: float) -> float:
    """lambda = l2 * mean diag of the p x p normal equations = l2 * trace / p (floored at 1e-12 l2)."""
    return l2 * max(float(diagonal_sum) / width, 1e-12)


def bellman_residual_weights(
    phi: torch.Tensor, next_phi: torch.Tensor, rewards: torch.Tensor, gamma: float, l2: float
) -> torch.Tensor:
    """Bellman residual minimisation, eq. (7):
    ``w = argmin_w ||Phi_C w - (r + gamma Phi'_C w)||^2 + lambda ||w||^2``, solved exactly.

    With A = Phi_C - gamma Phi'_C and lambda = l2 * mean diag(A^T A) = l2 ||A||_F^2 / p, the
    primal solution ``(A^T A + lambda I) w = A^T r`` is used when n >= p, and the equal dual
    one ``w = A^T (A A^T + lambda I)^{-1} r`` when n < p.

    :param phi: (n, p) Phi_C, phi at the states of C
    :param next_phi: (n, p) Phi'_C = E_model[phi~(S') | s_i, pi(s_i)] (= Psi_C B^T in feature form)
    :param rewards: (n,) expected rewards r(s_i, pi(s_i))
    :param gamma: discount factor
    :param l2: ridge, relative to the mean diagonal of the normal equations
    :return: (p,) value weights w, V(s) = <w, phi(s)>, in phi's dtype
    """
    residual_map = torch.add(phi, next_phi, alpha=-gamma)  # one pass, no (n, p) temporary
    n, p = residual_map.shape
    ridge = _ridge(torch.linalg.vector_norm(residual_map).square(), p, l2)
    if n >= p:
        weights = gram_solve(residual_map.T, residual_map.T @ rewards.to(residual_map.dtype), ridge)
    else:
        weights = transposed_product(residual_map, gram_solve(residual_map, rewards, ridge))
    return weights.to(phi.dtype)


@dataclass
class FactoredResidual:
    """The residual map of eq. (7), ``A = Phi_C - gamma Phi'_C``, kept in its factors when the
    model's successor features are ``Phi'_C = c Phi_C + Psi_C B^T`` (c = 1 with feature dynamics,
    else 0): ``A = a Phi_C - Psi_C M^T`` with ``a = 1 - gamma c`` and ``M = gamma B``. With a
    cheap Gram matrix of phi (an RBF grid's, from its one-dimensional factors) the dual system
    costs O(n^2 q + n q^2 + n p q) instead of O(n^2 p): the form for a wide phi and |C| < p.

    :param phi: (n, p) Phi_C
    :param phi_gram: builds ``scale * Phi_C Phi_C^T`` from a scale, as a new (n, n) float64 lower
        triangle (e.g. :meth:`~cme_agent.state_features.RBFGrid.gram` at the states of C)
    :param psi: (n, q) Psi_C = psi(s_i, pi(s_i)) (or E_pi[psi(s_i, A)])
    :param transition: (p, q) B, the rows of the model that predict phi
    :param gamma: discount factor
    :param keeps_phi: c = 1, the model predicts the change phi~(s') - phi(s)
    """

    phi: torch.Tensor
    phi_gram: Callable[[float], torch.Tensor]
    psi: torch.Tensor
    transition: torch.Tensor
    gamma: float
    keeps_phi: bool

    @property
    def scale(self) -> float:
        """a = 1 - gamma c, the coefficient of Phi_C in A."""
        return 1 - self.gamma if self.keeps_phi else 1.0

    def matvec(self, w: torch.Tensor) -> torch.Tensor:
        """A w: (p,) -> (n,), matrix-vector products only."""
        return (self.phi @ w).mul_(self.scale).sub_(self.psi @ (self.transition.T @ w), alpha=self.gamma)

    def rmatvec(self, alpha: torch.Tensor) -> torch.Tensor:
        """A^T alpha in float64: (n,) -> (p,)."""
        psi_part = transposed_product(self.transition.T, transposed_product(self.psi, alpha))
        return transposed_product(self.phi, alpha).mul_(self.scale).sub_(psi_part, alpha=self.gamma)

    def lower_gram(self) -> torch.Tensor:
        """The lower triangle of A A^T in float64, ``a^2 Phi Phi^T + H Psi^T + Psi H^T`` with
        ``H = Psi (M^T M) / 2 - a Phi M`` (n, q); the products run in phi's dtype."""
        transition = self.transition * self.gamma
        half = torch.addmm(self.phi @ transition, self.psi, transition.T @ transition, beta=-self.scale, alpha=0.5)
        return lower_gram(half, other=self.psi, add_to=self.phi_gram(self.scale**2))


def factored_dual_weights(residual: FactoredResidual, rewards: torch.Tensor, l2: float) -> torch.Tensor:
    """Eq. (7) in its dual form ``w = A^T (A A^T + lambda I)^{-1} r`` on a
    :class:`FactoredResidual` (A is never formed): the weights of
    :func:`bellman_residual_weights` to rounding.

    :param residual: A in its factors
    :param rewards: (n,) expected rewards r(s_i, pi(s_i))
    :param l2: ridge, relative to the mean diagonal of the normal equations
    :return: (p,) value weights w, in phi's dtype
    """
    system = residual.lower_gram()
    ridge = _ridge(system.diagonal().sum(), residual.phi.shape[1], l2)  # trace(A A^T) = ||A||_F^2
    alpha = lower_solve_(system, rewards, ridge, residual.lower_gram)
    return residual.rmatvec(alpha).to(residual.phi.dtype)


def factored_is_cheaper(n: int, p: int, q: int) -> bool:
    """Whether the :class:`FactoredResidual` dual system costs fewer flops than the dense one,
    beyond the n p q product both forms need: ``2 n^2 q`` (the lower triangle of H Psi^T +
    Psi H^T) + ``2 n q^2`` (H) + ``2 p q^2`` (M^T M) against ``n^2 p`` (A A^T's lower triangle).
    Only in the dual case n < p.

    :param n: |C|
    :param p: width of phi
    :param q: width of psi
    """
    return n < p and 2 * q * (n * n + n * q + p * q) < n * n * p


def bellman_residual_rms(
    phi: torch.Tensor, next_phi: torch.Tensor, rewards: torch.Tensor, gamma: float, w: torch.Tensor
) -> float:
    """Root-mean-square Bellman residual of w over C under the model, ``||Phi w - r - gamma Phi' w|| / sqrt(n)``."""
    residual = (phi @ w).sub_(next_phi @ w, alpha=gamma).sub_(rewards)  # matrix-vector products only
    return float(residual.pow(2).mean().sqrt())


def smooth(previous: torch.Tensor, estimate: torch.Tensor, omega: float) -> torch.Tensor:
    """Policy improvement, Q_k = (1 - omega) Q_{k-1} + omega Q^_k, on the linear weights of Q.

    psi only grows by appending, so the previous weights are zero-padded to the new width
    (docs/design.md, "Q needs no history"): no history of earlier Q functions is kept.

    :param previous: (q_old,) weights of Q_{k-1}
    :param estimate: (q_new,) weights of Q^_k, q_new >= q_old
    :param omega: step in [0, 1]
    :return: (q_new,) weights of Q_k
    """
    padded = torch.nn.functional.pad(previous, (0, estimate.shape[0] - previous.shape[0]))
    return (1 - omega) * padded + omega * estimate


SPREAD_FLOOR = 1e-6
"""The spread of Q over the candidates is floored at this fraction of Q's root-mean-square size
(and at 1e-12): a Q that does not depend on the action gives the uniform policy, and its float
rounding is not amplified into preferences."""


def softmax_policy(values: torch.Tensor, inverse_temperature: torch.Tensor | float) -> torch.Tensor:
    """The soft policy ``pi(a|s) = exp(beta Q(s, a) - logsumexp_b beta Q(s, b))`` over candidates.

    Computed from ``Q - max_a Q`` (the logsumexp shift), so it is exact for any beta >= 0,
    beta = inf included: then pi is uniform over the maximisers, the greedy policy.

    :param values: (N, K) Q at every state and candidate action
    :param inverse_temperature: beta >= 0, a float or a 0-dim tensor
    :return: (N, K) probabilities, each row on the simplex
    """
    shifted = values - values.amax(dim=1, keepdim=True)
    logits = torch.where(shifted == 0, torch.zeros_like(shifted), shifted * inverse_temperature)  # no 0 * inf
    return torch.softmax(logits, dim=1)


def action_spread(values: torch.Tensor) -> torch.Tensor:
    """The spread of Q over the candidate actions, ``sigma = sqrt(mean_s var_a Q(s, a))`` (the
    standard deviation over the candidates, root-mean-square over the states), floored at
    :data:`SPREAD_FLOOR` times the root-mean-square of Q: the scale of the soft improvement's beta.

    :param values: (N, K) Q at states and candidate actions
    :return: 0-dim tensor sigma > 0
    """
    spread = values.var(dim=1, unbiased=False).mean().sqrt()
    floor = (SPREAD_FLOOR * values.square().mean().sqrt()).clamp_min(1e-12)
    return torch.maximum(spread, floor)


def expected_candidate_features(
    state_factor: torch.Tensor,
    action_factor: torch.Tensor,
    probabilities: torch.Tensor,
    out: torch.Tensor | None = None,
    scratch: torch.Tensor | None = None,
) -> torch.Tensor:
    """``E_pi[psi(s, A)] = sum_a pi(a|s) psi(s, a) = S(s) * (pi(s) @ A)`` for the factorised psi
    (psi(s, a)[j] = S[s, j] A[a, j]): one (N, K) x (K, q) product, as greedy's gather costs.

    :param state_factor: (N, q) S
    :param action_factor: (K, q) A at the candidates
    :param probabilities: (N, K) pi(a|s)
    :param out: (N, q) buffer for the result, or None
    :param scratch: (N, q) buffer for pi @ A, or None
    :return: (N, q)
    """
    mixed = torch.mm(probabilities, action_factor) if scratch is None else torch.mm(probabilities, action_factor, out=scratch)
    return torch.mul(state_factor, mixed) if out is None else torch.mul(state_factor, mixed, out=out)
