"""Matching pursuit (eq. (5)): never raises the loss, finds the atoms that explain the residual,
stops when nothing helps."""

import sys

import pytest
import torch

from cme_agent.dynamics import matching_pursuit


def _loss(atoms, residual, result, theta=1.0):
    return float(((residual.double() - theta * atoms[:, result.indices].double() @ result.weights.double()) ** 2).sum())


@pytest.mark.parametrize("orthogonal", [False, True])
@pytest.mark.parametrize("seed", range(5))
def test_never_raises_the_loss_for_any_theta(seed, orthogonal):
    generator = torch.Generator().manual_seed(seed)
    atoms = torch.rand(200, 60, generator=generator)
    residual = torch.randn(200, 7, generator=generator)
    result = matching_pursuit(atoms, residual, threshold=1e-4, max_atoms=25, orthogonal=orthogonal)
    assert len(result.indices) > 0
    before = float((residual.double() ** 2).sum())
    assert result.energy_before == pytest.approx(before)
    assert _loss(atoms, residual, result) == pytest.approx(result.energy_after, rel=1e-6)
    for theta in (0.1, 0.5, 1.0):
        assert _loss(atoms, residual, result, theta) <= before


def test_recovers_the_atoms_of_a_sparse_residual():
    generator = torch.Generator().manual_seed(0)
    atoms = torch.rand(300, 40, generator=generator)
    weights = torch.randn(2, 5, generator=generator)
    residual = atoms[:, [3, 17]] @ weights
    result = matching_pursuit(atoms, residual, threshold=1e-6, max_atoms=10, orthogonal=True)
    assert set(result.indices.tolist()) >= {3, 17}
    assert result.energy_after < 1e-6 * result.energy_before


def test_stops_when_no_atom_helps():
    generator = torch.Generator().manual_seed(0)
    atoms = torch.randn(100, 10, generator=generator)
    residual = torch.randn(100, 3, generator=generator)
    q, _ = torch.linalg.qr(atoms)
    residual = residual - q @ (q.T @ residual)  # orthogonal to every atom
    result = matching_pursuit(atoms, residual, threshold=1e-3, max_atoms=10)
    assert len(result.indices) == 0
    assert result.energy_after == result.energy_before


def test_relative_threshold_limits_the_picks():
    generator = torch.Generator().manual_seed(1)
    atoms = torch.rand(200, 80, generator=generator)
    residual = torch.randn(200, 4, generator=generator)
    loose = matching_pursuit(atoms, residual, threshold=1e-5, max_atoms=50)
    strict = matching_pursuit(atoms, residual, threshold=0.05, max_atoms=50)
    assert len(strict.indices) < len(loose.indices)
    assert len(matching_pursuit(atoms, residual, threshold=1e-5, max_atoms=3).indices) <= 3


def test_fast_update_matches_plain_matching_pursuit():
    generator = torch.Generator().manual_seed(2)
    atoms = torch.rand(150, 30, generator=generator).double()
    residual = torch.randn(150, 5, generator=generator).double()
    result = matching_pursuit(atoms, residual, threshold=1e-6, max_atoms=5)
    remaining, chosen = residual.clone(), []
    for _ in range(5):  # the textbook version: recompute every score from the residual
        scores = ((atoms.T @ remaining) ** 2).sum(1) / (atoms**2).sum(0)
        j = int(scores.argmax())
        chosen.append(j)
        remaining -= atoms[:, j : j + 1] @ (atoms[:, j] @ remaining / (atoms[:, j] ** 2).sum()).unsqueeze(0)
    assert sorted(set(chosen)) == result.indices.tolist()
    assert float((remaining**2).sum()) == pytest.approx(result.energy_after, rel=1e-8)


def test_a_negligible_atom_gets_no_infinite_weight():
    """Found by hypothesis: a lone atom of 1.2e-38 once got the weight 1e38 / 1e-76 = inf."""
    atoms = torch.tensor([[1.1754944e-38], [0.0], [0.0], [0.0], [0.0]])
    result = matching_pursuit(atoms, torch.randn(5, 1, generator=torch.Generator().manual_seed(0)), 0.25, max_atoms=10)
    assert len(result.indices) == 0 and torch.isfinite(result.weights).all()


@pytest.mark.parametrize("orthogonal", [False, True])
def test_running_every_pick_after_the_stop_changes_nothing(orthogonal, monkeypatch):
    """A GPU runs all max_atoms picks (no synchronisation to read the stopping flag); the picks
    after the stopping rule held must add nothing."""
    generator = torch.Generator().manual_seed(4)
    atoms = torch.exp(-torch.rand(300, 120, generator=generator) * 5)
    residual = atoms[:, :4] @ torch.randn(4, 7, generator=generator) + 0.01 * torch.randn(300, 7, generator=generator)
    early = matching_pursuit(atoms, residual, threshold=0.02, max_atoms=60, orthogonal=orthogonal)
    assert 0 < len(early.indices) < 60  # the rule stops it before the cap
    module = sys.modules["cme_agent.dynamics.matching_pursuit"]  # the package exports a function of that name
    monkeypatch.setattr(module, "host_reads_are_free", lambda device: False)
    every = matching_pursuit(atoms, residual, threshold=0.02, max_atoms=60, orthogonal=orthogonal)
    assert torch.equal(every.indices, early.indices)
    assert torch.equal(every.weights, early.weights)
    assert every.energy_after == early.energy_after and every.energy_before == early.energy_before
