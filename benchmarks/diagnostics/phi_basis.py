"""Which phi at a budget of p = 1,000 features: a value-fitting proxy (about 3 minutes on one thread, d = 20 dominates).

For observation dims d = 2..20 on the box [-1, 1]^d, four known value-like targets are fitted
by the evaluation's ridge least squares (lambda = 1e-4 mean diag, eq. (7) with gamma = 0) on
|C| = 10 p uniform states, and scored by R^2 on 3,000 held-out states. Bases, each about
p = 1,000 wide: the RBF grid of the default resolution (the largest r <= 11 whose r^d + 1 fits),
an additive grid (sums of 1-D bumps, (p - 1) / d per dim), and random Fourier features at a
fixed length scale 0.3 (the former default), at c sqrt(d) and at the
default max(0.3, 0.1 d).

    python -m benchmarks.diagnostics.phi_basis            # prints one line per (d, target)
"""

from __future__ import annotations

import math

import numpy as np
import torch
from gymnasium import spaces

from cme_agent.config import ObservationConfig
from cme_agent.encoding import ObservationEncoder
from cme_agent.state_features import RandomFourierFeatures, RBFGrid

BUDGET = 1000
DIMS = (2, 3, 4, 5, 6, 8, 12, 20)
SCALES = (0.2, 0.5)


def targets(d: int, generator: torch.Generator) -> dict[str, callable]:
    """Value-like functions on [-1, 1]^d: a sharp ridge, a wave, pairwise interactions, a bump."""
    u = torch.randn(d, generator=generator)
    u2 = torch.randn(d, generator=generator)
    u, u2 = u / u.norm(), u2 / u2.norm()
    return {
        "ridge": lambda x: torch.tanh(5 * (x @ u)),
        "wave": lambda x: torch.sin(2 * math.pi * (x @ u)) * torch.cos(math.pi * (x @ u2)),
        "pairwise": lambda x: (x[:, :-1] * x[:, 1:]).sum(1) / math.sqrt(d - 1),
        "bump": lambda x: torch.exp(-((x - 0.3) ** 2).sum(1) / (0.5 * d)),
    }


def additive(x: torch.Tensor, points: int) -> torch.Tensor:
    """Sums of 1-D bumps: phi = (bumps of x_1, ..., bumps of x_d, 1)."""
    centres = torch.linspace(-1, 1, points)
    spacing = 2 / (points - 1)
    features = torch.exp(-((x[:, :, None] - centres) ** 2) / (2 * spacing**2)).reshape(x.shape[0], -1)
    return torch.cat([features, torch.ones_like(features[:, :1])], dim=1)


def r_squared(train: torch.Tensor, test: torch.Tensor, y: torch.Tensor, y_test: torch.Tensor) -> float:
    """Held-out R^2 of the ridge fit of y on the features (the evaluation's ridge, float64 solve)."""
    gram = (train.T @ train).double()
    gram.diagonal().add_(1e-4 * float(gram.diagonal().mean()))
    w = torch.linalg.solve(gram, (train.T @ y).double()).float()
    return float(1 - ((test @ w - y_test) ** 2).mean() / y_test.var())


def main() -> None:
    torch.set_num_threads(1)
    generator = torch.Generator().manual_seed(0)
    for d in DIMS:
        encoder = ObservationEncoder(spaces.Box(-1.0, 1.0, (d,), np.float32), ObservationConfig())
        x = torch.rand(10 * BUDGET, d, generator=generator) * 2 - 1
        x_test = torch.rand(3000, d, generator=generator) * 2 - 1
        bases: dict[str, torch.nn.Module | callable] = {}
        points = math.floor((BUDGET - 1) ** (1 / d) + 1e-9)
        if points >= 3:
            bases[f"grid{min(points, 11)}"] = RBFGrid(encoder, (min(points, 11),), 1.0)
        bases[f"additive{(BUDGET - 1) // d}"] = lambda obs, k=(BUDGET - 1) // d: additive(obs, k)
        bases["rff0.3"] = RandomFourierFeatures(encoder, BUDGET - 1, 0.3)
        for scale in SCALES:
            bases[f"rff{scale}sqrt(d)"] = RandomFourierFeatures(encoder, BUDGET - 1, scale * math.sqrt(d))
        bases["rff_default"] = RandomFourierFeatures(encoder, BUDGET - 1, max(0.3, 0.1 * d))
        features = {name: (basis(x), basis(x_test)) for name, basis in bases.items()}
        for name, target in targets(d, generator).items():
            y, y_test = target(x), target(x_test)
            scores = {basis: r_squared(train, test, y, y_test) for basis, (train, test) in features.items()}
            print(f"d={d:2d} {name:8s} " + "  ".join(f"{basis}={score:.3f}" for basis, score in scores.items()), flush=True)


if __name__ == "__main__":
    main()
