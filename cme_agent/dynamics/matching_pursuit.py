"""Vector-valued matching pursuit on the model residual (paper eq. (5)).

With the candidate atoms G (n x c) evaluated on the subsample and the residual R (n x p),
atom j removes ``score_j = ||G_j^T R||^2 / ||G_j||^2`` of the residual energy when given its
least-squares weights ``b = G_j^T R / ||G_j||^2``. ``C0 = G^T R`` is computed once; after t
picks the correlations are ``C_t = C0 - sum_s g_s b_s^T`` with ``g_s = G^T G_{j_s}``, which is
never formed: the scores' squared row norms are updated per pick from ``C0 b`` and the earlier
picks, O(c (n + p) + t (c + p)) reading C0 once, where updating C in place reads and writes it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from cme_agent.devices import host_reads_are_free
from cme_agent.linalg import transposed_product


@dataclass
class PursuitResult:
    """The atoms picked by :func:`matching_pursuit`.

    :param indices: (l,) distinct column indices of the picked atoms in G
    :param weights: (l, p) their weights b_j (rows of B_new^T)
    :param energy_before: ||R||^2, loss (5) before the picks
    :param energy_after: loss (5) after the picks (with the returned weights)
    """

    indices: torch.Tensor
    weights: torch.Tensor
    energy_before: float
    energy_after: float


def matching_pursuit(
    atoms: torch.Tensor, residual: torch.Tensor, threshold: float, max_atoms: int, orthogonal: bool = False
) -> PursuitResult:
    """Greedily pick atoms that most reduce err_k of eq. (5), ||R - sum_j g_j b_j^T||^2.

    Works in float64 so that the energy bookkeeping is exact enough for the guarantee that
    no pick raises the loss. Stops when the best atom removes less than ``threshold`` times
    the current residual energy, when nothing reduces it, or after ``max_atoms`` picks.

    :param atoms: (n, c) candidate features g_j evaluated at the n subsample points
    :param residual: (n, p) model residual R at those points
    :param threshold: relative stopping threshold in (0, 1)
    :param max_atoms: cap on the number of picks
    :param orthogonal: refit the weights of all picked atoms jointly by least squares at the end
    :return: the picked atoms and their weights
    """
    dtype = atoms.dtype
    G = atoms.double()
    norms = (G * G).sum(0)
    # negligible atoms are never picked: relative to the largest, and absolutely, where 1 / ||G_j||^2
    # would overflow the weights' dtype (sqrt of its smallest normal number, ~1e-19 for float32)
    floor = (norms.max() * 1e-12).clamp_min(torch.finfo(dtype).tiny ** 0.5)
    inverse_norms = torch.where(norms > floor, 1 / norms.clamp_min(1e-300), 0.0)
    C0 = transposed_product(G, residual)  # float64, no float64 copy of the (n, p) residual
    energy_before = torch.linalg.vector_norm(residual, dtype=torch.float64).square()
    energy = energy_before.clone()
    # C_t = C0 - sum_{s<t} g_s b_s^T is never formed: its squared row norms are updated per pick and
    # its row j is rebuilt from the picks so far (one read of C0 per pick instead of a rank-1 update)
    squared_norms = torch.linalg.vector_norm(C0, dim=1).square_()  # (c,) ||C_t[i]||^2, no (c, p) temporary
    picks = torch.zeros(max_atoms, dtype=torch.long, device=C0.device)
    steps = C0.new_zeros(max_atoms, C0.shape[1])  # (max_atoms, p): b_t
    couplings = C0.new_zeros(C0.shape[0], max_atoms)  # (c, max_atoms): g_t = G^T G_{j_t}
    taken = torch.zeros(max_atoms, dtype=torch.bool, device=C0.device)
    active = torch.ones((), dtype=torch.bool, device=C0.device)
    count = 0
    for t in range(max_atoms):  # no host synchronisation on a GPU, no (c, p) temporary per pick
        score, j = torch.max(squared_norms * inverse_norms, dim=0)
        active &= (score > 0) & (score >= threshold * energy)
        if host_reads_are_free(C0.device) and not active:  # a GPU runs all max_atoms picks, zero after the stop
            break
        j = j.view(1)  # index_select, not indexing by a 0-dim tensor (which reads it on the host)
        row = C0.index_select(0, j)[0].sub_(couplings.index_select(0, j)[0, :t] @ steps[:t])  # C_t[j]
        b = row.mul_(inverse_norms.index_select(0, j) * active)  # (p,), zero once stopped
        g = G.T @ G.index_select(1, j)[:, 0]  # (c,)
        correlations = (C0 @ b).sub_(couplings[:, :t] @ (steps[:t] @ b))  # <C_t[i], b>
        squared_norms.addcmul_(g, correlations, value=-2).addcmul_(g.square(), b.square().sum()).clamp_min_(0)
        picks[t], steps[t], couplings[:, t], taken[t] = j[0], b, g, active
        energy = torch.where(active, (energy - score).clamp_min(0), energy)
        count = t + 1
    chosen = taken[:count]
    indices, slots = torch.unique(picks[:count][chosen], return_inverse=True)  # an atom may be picked again
    if len(indices) == 0:
        return PursuitResult(indices, residual.new_zeros(0, residual.shape[1]), float(energy_before), float(energy_before))
    weights = C0.new_zeros(len(indices), C0.shape[1]).index_add_(0, slots, steps[:count][chosen])
    if orthogonal:
        R = residual.double()
        weights = _least_squares_refit(G[:, indices], R)
        energy = ((R - G[:, indices] @ weights) ** 2).sum()
    return PursuitResult(indices, weights.to(dtype), float(energy_before), float(torch.minimum(energy, energy_before)))


def _least_squares_refit(selected: torch.Tensor, residual: torch.Tensor) -> torch.Tensor:
    """Joint least-squares weights of the selected atoms: argmin_W ||R - G_S W||^2.

    A tiny ridge (1e-10 of the mean diagonal) keeps the solve defined for near-collinear atoms.

    :param selected: (n, l) the picked atoms
    :param residual: (n, p)
    :return: (l, p) weights
    """
    gram = selected.T @ selected
    ridge = 1e-10 * gram.diagonal().mean() * torch.eye(gram.shape[0], dtype=gram.dtype, device=gram.device)
    return torch.linalg.solve(gram + ridge, selected.T @ residual)
