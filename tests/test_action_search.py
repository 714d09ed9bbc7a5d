"""Continuous action search: projected ascent on Q(s, .) finds a concave Q's maximiser from any
start in the box, never leaves the box, never lowers Q, and the policy's greedy step uses it."""

import numpy as np
import pytest
import torch
from gymnasium import spaces

from cme_agent import CMEPolicy, RewardSpec
from cme_agent.action_search import at_points, projected_ascent


def quadratic(target: torch.Tensor, curvature: torch.Tensor, seen: list[torch.Tensor] | None = None):
    """q(a) = -sum_d c_d (a_d - target_d)^2 + 3 (an anisotropic concave quadratic) at points (..., d) -> (...),
    recording the points it is asked at."""

    def q(points: torch.Tensor) -> torch.Tensor:
        if seen is not None:
            seen.append(points.detach().clone())
        return 3.0 - ((points - target) ** 2 * curvature).sum(dim=-1)

    return q


def starts(dim: int, n: int = 64) -> torch.Tensor:
    """Random points of [-1, 1]^dim and every corner the rows allow."""
    generator = torch.Generator().manual_seed(dim)
    random = torch.rand(n, dim, generator=generator) * 2 - 1
    corners = torch.tensor(np.array(np.meshgrid(*[[-1.0, 1.0]] * dim)).reshape(dim, -1).T[:n], dtype=torch.float32)
    return torch.cat([random, corners])


@pytest.mark.parametrize("dim", [1, 2, 6])
def test_finds_an_interior_maximiser_from_any_start_within_the_box(dim: int) -> None:
    target = torch.linspace(-0.7, 0.6, dim)
    curvature = torch.logspace(0, 2, dim)  # condition number 100 in six dims
    seen: list[torch.Tensor] = []
    start = starts(dim)
    points, values = projected_ascent(quadratic(target, curvature, seen), start, steps=80, step_size=0.05)
    assert (points - target).abs().max() < 0.02
    assert torch.allclose(values, quadratic(target, curvature)(points))
    assert all(bool((p.abs() <= 1).all()) for p in seen)  # every point asked at, not only the last, in the box


def test_a_maximiser_outside_the_box_is_found_on_its_face() -> None:
    target, curvature = torch.tensor([1.8, -0.3, -2.5]), torch.tensor([1.0, 10.0, 0.1])
    points, _ = projected_ascent(quadratic(target, curvature), starts(3), steps=80, step_size=0.05)
    expected = target.clamp(-1, 1)
    assert (points - expected).abs().max() < 0.02
    assert bool((points.abs() <= 1).all())


def test_q_never_falls_and_zero_steps_return_the_start() -> None:
    generator = torch.Generator().manual_seed(3)
    weights = torch.randn(8, 4, generator=generator)

    def bumpy(points: torch.Tensor) -> torch.Tensor:  # not concave: many local maxima
        return torch.sin(points @ weights.T * 3).sum(dim=-1)

    start = starts(4)
    points, values = projected_ascent(bumpy, start, steps=20, step_size=0.3)
    assert bool((values >= bumpy(start) - 1e-6).all()) and torch.allclose(values, bumpy(points))
    same, same_values = projected_ascent(bumpy, start, steps=0, step_size=0.3)
    assert torch.equal(same, start) and torch.allclose(same_values, bumpy(start))


def test_greedy_step_of_a_six_dim_box_policy_finds_the_known_maximiser_within_the_bounds() -> None:
    low = np.array([-2.0, -1.0, 0.0, -0.5, -3.0, 1.0], np.float32)
    high = np.array([2.0, 1.0, 1.0, 0.5, 3.0, 2.0], np.float32)
    best = torch.tensor([0.7, -0.4, 0.25, 0.5, -1.0, 1.6])  # the fourth on its upper bound
    curvature = torch.tensor([1.0, 3.0, 10.0, 1.0, 0.3, 5.0])
    reward = RewardSpec(lambda obs, a: -(((a - best) ** 2) * curvature).sum(dim=1))  # Q = r while theta is 0
    policy = CMEPolicy(
        spaces.Box(-1.0, 1.0, (2,), np.float32),
        spaces.Box(low, high),
        phi={"resolution": [5]},
        reward=reward,
        action_search={"n_samples": 64, "refine_steps": 80},
    )
    obs = torch.rand(5, 2) * 2 - 1
    actions, values = policy.greedy(obs)
    assert bool((actions >= torch.as_tensor(low)).all() and (actions <= torch.as_tensor(high)).all())
    assert (actions - best).abs().max() < 0.03
    assert torch.allclose(values, reward.step_reward(obs, actions), atol=1e-5)
    assert torch.allclose(policy.act(obs), actions)


def test_at_points_pairs_each_row_with_its_own_points() -> None:
    generator = torch.Generator().manual_seed(5)
    states, weights = torch.randn(4, 3, generator=generator), torch.randn(3, generator=generator)
    points = torch.rand(4, 7, 2, generator=generator) * 2 - 1

    def q_rows(rows: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:  # paired rows: (N, 3), (N, 2) -> (N,)
        return rows @ weights * actions[:, 0] - actions[:, 1].square()

    values = at_points(q_rows, states)(points)
    expected = torch.stack([q_rows(states[i].expand(7, 3), points[i]) for i in range(4)])
    assert values.shape == (4, 7) and torch.allclose(values, expected)
