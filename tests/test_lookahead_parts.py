"""The measurements of benchmarks/diagnostics/lookahead_parts.py (no long training): PointGoal2D's step in
torch, the transitions with parts swapped for the truth, the optimum's bound, and the row of a short run."""

from __future__ import annotations

import functools
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from benchmarks.diagnostics import lookahead_parts as lp
from cme_agent import CMEPolicyIteration
from cme_agent.envs.point_goal import PointGoal2D


def _states(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.concatenate([rng.uniform(-2, 2, (n, 2)), rng.uniform(-0.5, 0.5, (n, 2))], axis=1)


def test_the_torch_step_is_the_envs_step() -> None:
    rng = np.random.default_rng(0)
    states, actions = _states(rng, 50), rng.uniform(-1.5, 1.5, (50, 2))  # outside the box too: both clip
    env = PointGoal2D()
    successors, rewards = env.transition(states, actions)
    torch_next, torch_rewards = lp.true_transition(env, torch.as_tensor(states), torch.as_tensor(actions))
    np.testing.assert_allclose(torch_next.numpy(), successors, atol=1e-12)
    np.testing.assert_allclose(torch_rewards.numpy(), rewards, atol=1e-9)


@pytest.fixture(scope="module")
def agent() -> CMEPolicyIteration:
    model = CMEPolicyIteration("CMEPolicy", "PointGoal2D-v0", seed=0, verbose=0).learn(600)
    assert model.policy.lookahead is not None  # auto chose the model of the observation
    return model


def test_each_swap_takes_its_parts_from_the_env(agent: CMEPolicyIteration) -> None:
    planner, env = agent.policy.lookahead, PointGoal2D()
    rng = np.random.default_rng(1)
    obs = torch.as_tensor(_states(rng, 20), dtype=torch.float32)
    actions = torch.as_tensor(rng.uniform(-1, 1, (20, 2)), dtype=torch.float32)
    learned_next, learned_going_on, learned_rewards = planner.transition(obs, actions)
    true_next, true_rewards = (part.float() for part in lp.true_transition(env, obs, actions))
    truth = lp.swapped(planner, "truth", env)(obs, actions)
    torch.testing.assert_close(truth[0], true_next)
    torch.testing.assert_close(truth[2], true_rewards)
    assert bool((truth[1] == 1).all())
    true_reward = lp.swapped(planner, "true_reward", env)(obs, actions)
    torch.testing.assert_close(true_reward[0], learned_next)
    torch.testing.assert_close(true_reward[2], true_rewards)
    true_dynamics = lp.swapped(planner, "true_dynamics", env)(obs, actions)
    torch.testing.assert_close(true_dynamics[0], true_next)
    model = planner.model
    stay = 1 - model.terminates(true_next)
    expected = stay * model.reward(true_next, actions) + (1 - stay) * model.terminal_reward
    torch.testing.assert_close(true_dynamics[2], expected.float())
    assert not torch.allclose(true_dynamics[2], true_rewards)  # the learned reward is not the env's
    assert lp.swapped(planner, "model", env)(obs, actions)[2].equal(learned_rewards)
    assert learned_going_on.shape == (20,)


def test_the_optimum_is_above_simple_controllers() -> None:
    starts = np.array([[-0.8, 0.7, 0.0, 0.0], [0.5, -0.3, 0.0, 0.0]])
    env, goal = PointGoal2D(), PointGoal2D().goal

    def controller_return(gain: float, damping: float) -> float:
        total = 0.0
        for start in starts:
            env.state = start.copy()
            for _ in range(lp.EPISODE_STEPS):
                total += env.step(gain * (goal - env.state[:2]) - damping * env.state[2:])[1]
        return total / len(starts)

    best = lp.optimum(starts, iterations=300, polish=50)
    assert best <= 0.0
    for gain, damping in ((0.0, 0.0), (1.0, 1.0), (3.0, 2.0), (5.0, 4.0)):
        assert best > controller_return(gain, damping), (gain, damping)


def test_a_short_run_measures_every_swap(agent: CMEPolicyIteration, monkeypatch: pytest.MonkeyPatch) -> None:
    starts, trained = lp.episode_starts, SimpleNamespace(learn=lambda steps: agent)
    monkeypatch.setattr(lp, "CMEPolicyIteration", lambda *args, **kwargs: trained)  # the fixture's agent
    monkeypatch.setattr(lp, "episode_starts", lambda seed: starts(seed)[:2])
    monkeypatch.setattr(lp, "returns", functools.partial(lp.returns, steps=20))
    monkeypatch.setattr(lp, "optimum", functools.partial(lp.optimum, iterations=20, polish=5))
    search = agent.policy.action_search
    row = lp.run_seed((0, 600, {}, 2))
    assert set(lp.METRICS) <= set(row) and row["seed"] == 0
    assert all(np.isfinite(row[key]) and row[key] < 0 for key in lp.METRICS)
    assert row["truth_grid"] != row["model_grid"]  # the swap reaches the acting
    assert agent.policy.action_search == search and "transition" not in vars(agent.policy.lookahead)  # restored
