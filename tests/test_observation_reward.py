"""The learned reward of the model of the observation: a cone such as -|p' - goal| is in its span."""

from __future__ import annotations

import dataclasses

import torch
from conftest import linear_system

from cme_agent.buffer import Transitions
from cme_agent.dynamics.observation import REWARD_PROJECTIONS, ObservationModel, quadratic, ridge

GOAL = torch.tensor([0.6, -0.4], dtype=torch.float64)


def point_mass(n: int, seed: int) -> Transitions:
    """s = (x, y, vx, vy); s' by a damped step; r = -|p' - GOAL| - 0.05 |a|^2 (PointGoal2D's reward)."""
    generator = torch.Generator().manual_seed(seed)
    obs = torch.cat([torch.rand(n, 2, generator=generator) * 3 - 1.5, torch.randn(n, 2, generator=generator) * 0.3], 1)
    actions = torch.rand(n, 2, generator=generator) * 2 - 1
    velocity = 0.9 * obs[:, 2:] + 0.1 * actions
    next_obs = torch.cat([obs[:, :2] + 0.1 * velocity, velocity], dim=1)
    rewards = -(next_obs[:, :2].double() - GOAL).norm(dim=1) - 0.05 * actions.double().square().sum(dim=1)
    return Transitions(obs.float(), actions.float(), rewards.float(), next_obs.float(), torch.zeros(n, dtype=torch.bool))


def test_a_cone_reward_is_fitted_where_quadratic_features_alone_miss_its_tip() -> None:
    train, test = point_mass(4000, seed=0), point_mass(1000, seed=1)
    model = ObservationModel(obs_dim=4, act_dim=2)
    model.fit(train)
    next_obs, actions = test.next_obs.double(), test.actions.double()
    error = float((model.reward(next_obs, actions) - test.rewards.double()).square().mean().sqrt())
    quadratic_only = torch.cat([quadratic(model.standardise(train.next_obs.double())), train.actions.double()], 1)
    weights = ridge(torch.cat([quadratic_only, train.actions.double().square()], 1), train.rewards.double())
    test_features = torch.cat([quadratic(model.standardise(next_obs)), actions, actions.square()], 1)
    quadratic_error = float((test_features @ weights - test.rewards.double()).square().mean().sqrt())
    assert error < 0.5 * quadratic_error, (error, quadratic_error)
    grid = torch.linspace(-1.2, 1.2, 49, dtype=torch.float64)
    positions = torch.cartesian_prod(grid, grid)
    at_rest = torch.cat([positions, torch.zeros(len(positions), 2, dtype=torch.float64)], dim=1)
    best = positions[int(model.reward(at_rest, torch.zeros(len(positions), 2)).argmax())]
    assert float((best - GOAL).norm()) < 0.15, best


def test_a_model_saved_before_the_projections_loads_and_predicts_as_it_did() -> None:
    model = ObservationModel(obs_dim=4, act_dim=2)
    model.fit(point_mass(500, seed=2))
    old = {key: value.clone() for key, value in model.state_dict().items() if key not in ("projections", "offsets")}
    old["reward_weights"] = old["reward_weights"][:-REWARD_PROJECTIONS]
    loaded = ObservationModel(obs_dim=4, act_dim=2)
    loaded.load_state_dict(old)
    data = point_mass(50, seed=3)
    features = torch.cat([quadratic(model.standardise(data.next_obs.double())), data.actions.double()], 1)
    expected = torch.cat([features, data.actions.double().square()], 1) @ old["reward_weights"]
    torch.testing.assert_close(loaded.reward(data.next_obs, data.actions), expected)
    torch.testing.assert_close(loaded.next_obs(data.obs, data.actions), model.next_obs(data.obs, data.actions))


def test_the_reward_of_ending_is_learned_apart_and_weighed_by_the_termination() -> None:
    data = linear_system(4000, seed=4)  # terminated where |s'_1| > 0.15
    data = dataclasses.replace(data, rewards=torch.where(data.terminated, -10.0, 1.0))
    model = ObservationModel(obs_dim=4, act_dim=1)
    model.fit(data)
    assert float(model.terminal_reward) == -10.0
    torch.testing.assert_close(model.reward(data.next_obs, data.actions), torch.ones(len(data), dtype=torch.float64))
    calm, falling = torch.zeros(1, 4), torch.tensor([[0.0, 0.3, 0.0, 0.0]])  # s'_1 stays near 0, or passes 0.15
    _, going_on, rewards = model.step(torch.cat([calm, falling]), torch.zeros(1, 1))
    assert going_on[0] > 0.9 > 0.1 > going_on[1]
    torch.testing.assert_close(rewards, going_on * 1.0 + (1 - going_on) * -10.0)
