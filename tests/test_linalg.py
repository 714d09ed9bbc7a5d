"""The evaluation's linear algebra: lower-triangle Gram products and the blocked Cholesky solve."""

import pytest
import torch

from cme_agent.linalg import GRAM_BLOCK, cholesky_, cholesky_solve, gram_solve, lower_gram, transposed_product


@pytest.mark.parametrize("rows", [1, 255, 256, 700])  # one block, a block exactly, ragged blocks
def test_lower_gram_is_the_lower_triangle_of_the_product(rows):
    matrix = torch.randn(rows, 37, generator=torch.Generator().manual_seed(rows))
    lower = lower_gram(matrix)
    full = matrix @ matrix.T
    blocks = torch.arange(rows) // GRAM_BLOCK
    on_or_below = blocks[:, None] >= blocks[None, :]  # block rows at or below the diagonal
    assert torch.allclose(lower[on_or_below], full[on_or_below], atol=1e-4)
    strided = lower_gram(matrix.T.contiguous().T)  # any strides
    assert torch.allclose(strided[on_or_below], lower[on_or_below], atol=1e-4)
    wide = lower_gram(matrix, torch.float64)
    assert wide.dtype == torch.float64 and torch.allclose(wide[on_or_below], full[on_or_below].double(), atol=1e-4)


@pytest.mark.parametrize("rows", [1, 300, 700])
def test_lower_gram_of_a_pair_is_the_symmetric_product_added_in_place(rows):
    generator = torch.Generator().manual_seed(rows)
    matrix, other = torch.randn(rows, 11, generator=generator), torch.randn(rows, 11, generator=generator)
    base = torch.randn(rows, rows, generator=generator, dtype=torch.float64)
    expected = base + (matrix @ other.T + other @ matrix.T).double()
    blocks = torch.arange(rows) // GRAM_BLOCK
    on_or_below = blocks[:, None] >= blocks[None, :]
    result = lower_gram(matrix, other=other, add_to=base.clone())
    assert result.dtype == torch.float64 and torch.allclose(result[on_or_below], expected[on_or_below], atol=1e-4)
    alone = lower_gram(matrix, torch.float64, other=other)
    assert torch.allclose(alone[on_or_below], (expected - base)[on_or_below], atol=1e-4)


def _spd(size: int, seed: int) -> torch.Tensor:
    matrix = torch.randn(size, size + 3, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
    return matrix @ matrix.T + 0.1 * torch.eye(size, dtype=torch.float64)


@pytest.mark.parametrize("size", [1, 256, 300, 600])  # one block, a block exactly, ragged blocks
def test_blocked_cholesky_equals_lapack_and_solves(size):
    system = _spd(size, size)
    rhs = torch.randn(size, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    factor = torch.tril(system)  # only the lower triangle is read
    assert int(cholesky_(factor)) == 0
    assert torch.allclose(factor.tril(), torch.linalg.cholesky(system), atol=1e-9)
    solution = cholesky_solve(factor, rhs)
    assert torch.allclose(system @ solution, rhs, atol=1e-8 * float(system.abs().max()))


def test_blocked_cholesky_reports_an_indefinite_system():
    system = _spd(400, 0)
    system[350, 350] = -1e3  # not positive definite, in the second block
    assert int(cholesky_(system.clone())) != 0


@pytest.mark.parametrize("rank, ridge", [(40, 1e-3), (5, 0.0)])  # positive definite; singular: the LU fallback
def test_gram_solve_equals_the_full_system(rank, ridge):
    generator = torch.Generator().manual_seed(rank)
    matrix = (torch.randn(300, rank, generator=generator) @ torch.randn(rank, 40, generator=generator)).T  # (40, 300)
    rhs = matrix.double() @ torch.randn(300, dtype=torch.float64, generator=generator)  # in the range: consistent
    solution = gram_solve(matrix, rhs, ridge)
    system = matrix.double() @ matrix.double().T + ridge * torch.eye(40, dtype=torch.float64)
    assert torch.allclose(system @ solution, rhs, rtol=1e-3, atol=1e-3 * float(rhs.abs().max()))


@pytest.mark.parametrize("columns", [(), (7,)])  # a vector, a matrix
def test_transposed_product_is_the_float64_product(columns):
    generator = torch.Generator().manual_seed(3)
    matrix, other = torch.randn(300, 11, generator=generator), torch.randn(300, *columns, generator=generator)
    product = transposed_product(matrix, other, rows=128)  # ragged blocks
    assert product.dtype == torch.float64
    assert torch.allclose(product, matrix.double().T @ other.double(), atol=1e-10)
