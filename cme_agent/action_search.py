"""Continuous search of the greedy action: projected ascent on Q(s, .) from the best candidate."""

from __future__ import annotations

from collections.abc import Callable

import torch

GROW = 1.2
"""Factor of a coordinate's step after a kept move whose gradient kept its sign (Rprop's) ..."""
SHRINK = 0.5
"""... and after its gradient changed sign, or after a refused move (every coordinate of the row)."""


def projected_ascent(
    q: Callable[[torch.Tensor], torch.Tensor], start: torch.Tensor, steps: int, step_size: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Maximise ``q`` over the box [-1, 1]^d from ``start``, row by row: sign-gradient ascent with
    one step length per coordinate (Rprop), projected on the box, each move kept only where it
    raises q.

    Each step moves every coordinate by its step length in the direction of its partial
    derivative and clips to the box. A move that raises q is kept, and each coordinate's step then
    grows by :data:`GROW` where its derivative kept its sign and shrinks by :data:`SHRINK` where it
    flipped (it stepped over the maximum); a move that does not raise q is refused and the row's
    steps shrink. So q never falls, no point leaves the box, and the steps are free of q's scale
    and of how unevenly it curves along the coordinates.

    :param q: differentiable values at paired rows, (N, d) -> (N,)
    :param start: (N, d) starting points in [-1, 1]^d (normalised actions)
    :param steps: steps (each one forward and one backward pass of q)
    :param step_size: first step length of every coordinate, in normalised units
    :return: (N, d) the points reached and (N,) q there
    """
    point, step = start.detach(), torch.full_like(start, step_size).detach()
    value, grad = _value_and_gradient(q, point)
    for _ in range(steps):
        proposal = (point + step * grad.sign()).clamp_(-1, 1)
        proposed, proposed_grad = _value_and_gradient(q, proposal)
        kept = (proposed > value)[:, None]
        same_sign = proposed_grad * grad > 0
        step = torch.where(kept & same_sign, step * GROW, step * SHRINK)
        point = torch.where(kept, proposal, point)
        value, grad = torch.where(kept[:, 0], proposed, value), torch.where(kept, proposed_grad, grad)
    return point, value


def _value_and_gradient(q: Callable[[torch.Tensor], torch.Tensor], point: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """q at the (N, d) rows and its gradient in each row, both detached: (N,), (N, d)."""
    with torch.enable_grad():
        point = point.detach().requires_grad_(True)
        value = q(point)
        (grad,) = torch.autograd.grad(value.sum(), point)
    return value.detach(), grad
