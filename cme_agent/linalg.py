"""The dense linear algebra of policy evaluation (paper eq. (7)): Gram products built as their
lower triangle and symmetric systems solved by a blocked Cholesky factorisation, in place.

Why blocked and not ``torch.linalg.cholesky``: LAPACK's path copies the system into
column-major order, zeroes the upper triangle of the result (``tril``) and copies the factor
again for the solve. The left-looking blocks here spend their time in matrix products and small
factorisations, work in place on the row-major system, and check positive definiteness once at
the end (no host synchronisation per block on a GPU); ``python -m benchmarks.diagnostics.dual_solve``
compares the two.

Shapes: m the size of the system, k the inner dimension of a Gram product.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

GRAM_BLOCK = 256
"""Rows per block of :func:`lower_gram` and of the factorisation: the diagonal blocks are the
only work done twice."""


def gram_blocks(size: int) -> list[tuple[int, int]]:
    """The row blocks ``(start, stop)`` of :data:`GRAM_BLOCK` rows in which the Gram products are
    built and factored: :param size: the number of rows."""
    return [(start, min(start + GRAM_BLOCK, size)) for start in range(0, size, GRAM_BLOCK)]


def lower_gram(
    matrix: torch.Tensor,
    dtype: torch.dtype | None = None,
    other: torch.Tensor | None = None,
    add_to: torch.Tensor | None = None,
) -> torch.Tensor:
    """The lower triangle (by blocks of :data:`GRAM_BLOCK` rows) of ``matrix @ matrix.T``, or with
    ``other`` of the symmetric ``matrix @ other.T + other @ matrix.T``: about half the FLOPs of
    the full product; the blocks above the diagonal are left unset (never read).

    :param matrix: (m, k), any strides (e.g. the transpose of a (k, m) matrix)
    :param dtype: the result's dtype (None: matrix's); the products run in matrix's dtype, each
        block into one reused scratch block, converted as it is written (no full-size copy)
    :param other: (m, k), or None for the Gram matrix of ``matrix`` alone
    :param add_to: (m, m) a lower triangle the products are added to, in place (its dtype is the
        result's); None: a new matrix
    :return: (m, m)
    """
    m = matrix.shape[0]
    out = matrix.new_empty(m, m, dtype=dtype) if add_to is None else add_to
    in_place = out.dtype == matrix.dtype and add_to is None
    scratch = None if in_place else matrix.new_empty(min(GRAM_BLOCK, m), m)  # reused by every block
    for start, stop in gram_blocks(m):
        block = out[start:stop, :stop] if in_place else scratch[: stop - start, :stop]
        torch.mm(matrix[start:stop], (matrix if other is None else other)[:stop].T, out=block)
        if other is not None:
            block.addmm_(other[start:stop], matrix[:stop].T)
        if add_to is not None:
            out[start:stop, :stop].add_(block)
        elif not in_place:
            out[start:stop, :stop].copy_(block)
    return out


def cholesky_(system: torch.Tensor) -> torch.Tensor:
    """Factor a symmetric positive definite system ``A = L L^T`` in place, left-looking by blocks.

    Block column j: ``A[j:, j] -= L[j:, :j] L[j, :j]^T`` (one product), then the diagonal block is
    factored and the panel below it solved against that factor. Only the lower triangle of A is
    read; on return it holds L and the diagonal blocks' upper triangles are 0 (the blocks above
    them are untouched).

    :param system: (m, m) float tensor, its lower triangle the system; overwritten
    :return: a 0-dim int tensor, 0 when every diagonal block was positive definite (read it once,
        after the factorisation: no synchronisation per block)
    """
    failed = torch.zeros((), dtype=torch.int32, device=system.device)
    for start, stop in gram_blocks(system.shape[0]):
        column = system[start:, start:stop]
        if start:
            column.addmm_(system[start:, :start], system[start:stop, :start].T, alpha=-1)
        factor, info = torch.linalg.cholesky_ex(column[: stop - start])
        column[: stop - start] = factor
        failed = failed + info
        if stop < system.shape[0]:
            column[stop - start :] = torch.linalg.solve_triangular(factor.mT, column[stop - start :], upper=True, left=False)
    return failed


def cholesky_solve(factor: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """Solve ``L L^T x = rhs`` by blocked forward and back substitution.

    :param factor: (m, m) L in its lower triangle, as left by :func:`cholesky_`
    :param rhs: (m,) right-hand side, factor's dtype
    :return: (m,) x
    """
    blocks = gram_blocks(factor.shape[0])
    y = rhs.clone()
    for start, stop in blocks:
        if start:
            y[start:stop].addmv_(factor[start:stop, :start], y[:start], alpha=-1)
        y[start:stop] = torch.linalg.solve_triangular(factor[start:stop, start:stop], y[start:stop, None], upper=False)[:, 0]
    for start, stop in reversed(blocks):
        if stop < factor.shape[0]:
            y[start:stop].addmv_(factor[stop:, start:stop].T, y[stop:], alpha=-1)
        diagonal = factor[start:stop, start:stop]
        y[start:stop] = torch.linalg.solve_triangular(diagonal.mT, y[start:stop, None], upper=True)[:, 0]
    return y


def lower_solve_(system: torch.Tensor, rhs: torch.Tensor, ridge: float, rebuild: Callable[[], torch.Tensor]) -> torch.Tensor:
    """Solve ``(S + ridge I) x = rhs`` for a symmetric S given by its float64 lower triangle, by
    Cholesky in place (:func:`cholesky_`). Where rounding made the system not positive definite
    (a tiny ridge on a singular Gram matrix), ``rebuild()`` gives S again and it is solved by LU,
    symmetrised.

    :param system: (m, m) float64, S in its lower triangle; overwritten
    :param rhs: (m,) right-hand side
    :param ridge: lambda, in the units of S
    :param rebuild: builds S's lower triangle again (for the fallback)
    :return: (m,) float64 solution
    """
    system.diagonal().add_(ridge)
    if int(cholesky_(system)) == 0:
        return cholesky_solve(system, rhs.double())
    lower = rebuild().tril_()
    lower.diagonal().add_(ridge)
    return torch.linalg.solve(lower + lower.tril(-1).T, rhs.double())


def gram_solve(matrix: torch.Tensor, rhs: torch.Tensor, ridge: float) -> torch.Tensor:
    """Solve (matrix matrix^T + ridge I) x = rhs in float64 by Cholesky (:func:`lower_solve_`), the
    product built as its lower triangle (:func:`lower_gram`, products in matrix's dtype): half
    the FLOPs and, for the solve, a third of LU's.

    :param matrix: (m, k) any float dtype and strides
    :param rhs: (m,) right-hand side
    :param ridge: lambda, in the units of the Gram matrix
    :return: (m,) float64 solution
    """
    return lower_solve_(lower_gram(matrix, torch.float64), rhs, ridge, lambda: lower_gram(matrix, torch.float64))


def transposed_product(matrix: torch.Tensor, other: torch.Tensor, rows: int = 128) -> torch.Tensor:
    """``matrix^T other`` in float64, a block of rows at a time: neither operand is copied whole
    to float64 (each block is converted as it is used).

    :param matrix: (n, p)
    :param other: (n,) or (n, r)
    :return: (p,) or (p, r) float64
    """
    out = torch.zeros(matrix.shape[1], *other.shape[1:], dtype=torch.float64, device=matrix.device)
    accumulate = out.addmv_ if other.dim() == 1 else out.addmm_
    for start in range(0, matrix.shape[0], rows):
        accumulate(matrix[start : start + rows].T.double(), other[start : start + rows].double())
    return out


def random_cosines(inputs: torch.Tensor, projection: torch.Tensor, phase: torch.Tensor) -> torch.Tensor:
    """cos(x W + b), the random Fourier features' waves, in place where no gradient is taken: (N, d), (d, D), (D,) ->
    (N, D)."""
    angles = (inputs @ projection).add_(phase)
    return angles.cos() if angles.requires_grad else angles.cos_()
