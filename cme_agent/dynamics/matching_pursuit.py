"""Vector-valued matching pursuit on the model residual (paper eq. (5)).

With the candidate atoms G (n x c) evaluated on the subsample and the residual R (n x p),
atom j removes ``score_j = ||G_j^T R||^2 / ||G_j||^2`` of the residual energy when given its
least-squares weights ``b = G_j^T R / ||G_j||^2``. ``C = G^T R`` is computed once; after a
pick, ``C <- C - (G^T G_j) b^T`` costs O(c (n + p)) (docs/design.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

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
    C = transposed_product(G, residual)  # float64, no float64 copy of the (n, p) residual
    energy_before = torch.linalg.vector_norm(residual, dtype=torch.float64).square()
    energy = energy_before.clone()
    weights = torch.zeros_like(C)  # (c, p): summed weights of each atom (an atom may be picked again)
    picked = torch.zeros(C.shape[0], dtype=torch.bool, device=C.device)
    active = torch.ones((), dtype=torch.bool, device=C.device)
    for _ in range(max_atoms):  # no host synchronisation on a GPU, no (c, p) temporary per pick
        score, j = torch.max(torch.linalg.vector_norm(C, dim=1).square_().mul_(inverse_norms), dim=0)
        active &= (score > 0) & (score >= threshold * energy)
        if _stops_early(C.device) and not active:
            break
        j = j.view(1)
        b = C.index_select(0, j).mul_(inverse_norms[j] * active)  # (1, p), zero once stopped
        C.addmm_(G.T @ G.index_select(1, j), b, alpha=-1)
        weights.index_add_(0, j, b)
        picked.index_put_((j,), active.view(1) | picked.index_select(0, j))
        energy = torch.where(active, (energy - score).clamp_min(0), energy)
    indices = picked.nonzero().squeeze(1)
    if len(indices) == 0:
        return PursuitResult(indices, residual.new_zeros(0, residual.shape[1]), float(energy_before), float(energy_before))
    weights = weights[indices]
    if orthogonal:
        R = residual.double()
        weights = _least_squares_refit(G[:, indices], R)
        energy = ((R - G[:, indices] @ weights) ** 2).sum()
    return PursuitResult(indices, weights.to(dtype), float(energy_before), float(torch.minimum(energy, energy_before)))


def _stops_early(device: torch.device) -> bool:
    """Whether the picks may stop as soon as the stopping rule holds: reading the flag is free on
    the CPU, a host synchronisation on a GPU (which runs all ``max_atoms`` picks, zero after the stop)."""
    return device.type == "cpu"


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
