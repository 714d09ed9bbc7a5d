"""benchmarks/diagnostics/planner_in_loop.py: the lookahead, the simulator's step, the data
collection and a short loop on a briefly trained agent."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from benchmarks.diagnostics import observation_model as om
from benchmarks.diagnostics import planner_in_loop as pil
from cme_agent import CMEPolicyIteration

pytest.importorskip("mujoco")


@pytest.fixture(scope="module")
def agent() -> CMEPolicyIteration:
    return CMEPolicyIteration("CMEPolicy", "InvertedPendulum-v5", seed=0).learn(300)


def delayed_reward(obs: torch.Tensor, candidates: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """s' = s + a on a line; a step up costs 0.2, reaching s' >= 2 pays 1, s' <= -3 ends the episode."""
    next_obs = (obs.unsqueeze(1) + candidates.unsqueeze(0)).reshape(-1, 1)
    ups = (candidates[:, 0] > 0).float().repeat(len(obs))
    rewards = (next_obs[:, 0] >= 2).float() - 0.2 * ups
    return next_obs, (next_obs[:, 0] > -3).float(), rewards


def zero_phi(obs: torch.Tensor) -> torch.Tensor:
    return torch.zeros(len(obs), 1)


CANDIDATES = torch.tensor([[-1.0], [1.0]])


def test_looking_ahead_finds_a_delayed_reward_that_the_greedy_step_misses() -> None:
    start = np.zeros(1, dtype=np.float32)
    greedy = pil.lookahead_rule(zero_phi, delayed_reward, CANDIDATES, torch.zeros(1), 0.9, depth=1)
    deeper = pil.lookahead_rule(zero_phi, delayed_reward, CANDIDATES, torch.zeros(1), 0.9, depth=2)
    assert greedy(start)[0] == -1.0  # the step up costs now, its payoff is two steps away
    assert deeper(start)[0] == 1.0  # -0.2 + 0.9 (1 - 0.2) = 0.52 > 0, the best of going down
    with pytest.raises(ValueError, match="depth=0"):
        pil.lookahead_rule(zero_phi, delayed_reward, CANDIDATES, torch.zeros(1), 0.9, depth=0)


def test_the_lookahead_stops_at_a_terminal_state() -> None:
    # from -2 a step down ends the episode; with a value of 10 everywhere else, going on is worth more
    value_ten = pil.lookahead_rule(
        lambda obs: torch.ones(len(obs), 1), delayed_reward, CANDIDATES, torch.tensor([10.0]), 0.9, 1
    )
    assert value_ten(np.array([-2.0], dtype=np.float32))[0] == 1.0


def test_depth_one_is_the_greedy_step_of_the_planner(agent: CMEPolicyIteration) -> None:
    data = agent.store.get(slice(0, len(agent.store)))
    model = om.fitted(agent, data)
    step = model.step
    weights = torch.randn(agent.dynamics.p, generator=torch.Generator().manual_seed(0))
    lookahead = pil.lookahead_rule(agent.dynamics.phi, step, agent.policy.candidates, weights, agent.gamma, 1)
    greedy = om.greedy_rule(agent, om.as_model(agent, step), weights)
    for obs in data.obs[:20].numpy():
        np.testing.assert_array_equal(lookahead(obs), greedy(obs))


def test_the_simulator_step_is_the_envs_step() -> None:
    env = gym.make("InvertedPendulum-v5")
    obs, _ = env.reset(seed=3)
    obs, *_ = env.step(np.array([0.5], dtype=np.float32))
    action = np.array([-1.0], dtype=np.float32)
    next_obs, reward, terminated, *_ = env.step(action)
    predicted, alive, rewards = pil.SimulatorStepper("InvertedPendulum-v5")(
        torch.as_tensor(obs)[None], torch.as_tensor(action)[None]
    )
    np.testing.assert_allclose(predicted[0].numpy(), next_obs, atol=1e-6)
    assert float(alive[0]) == (0.0 if terminated else 1.0)
    assert float(rewards[0]) == pytest.approx(reward)


def test_the_simulator_step_refuses_an_observation_that_is_not_the_state() -> None:
    with pytest.raises(SystemExit, match="not \\(qpos, qvel\\)"):
        pil.SimulatorStepper("Reacher-v5")


def test_collect_acts_within_the_bounds_and_goes_on_after_an_episode_ends() -> None:
    env = gym.make("InvertedPendulum-v5")
    obs, _ = env.reset(seed=0)
    data, last = pil.collect(env, obs, lambda o: np.array([3.0], dtype=np.float32), 120, 0.3, np.random.default_rng(0))
    assert len(data) == 120 and data.terminated.any()  # full push topples the pole within 120 steps
    assert (data.actions.abs() <= 3.0).all() and (data.actions < 3.0).any()  # the noise moves actions, clipped to the box
    assert not np.allclose(last, data.obs[0].numpy())


def test_a_short_loop_evaluates_each_mode_at_each_plan(agent: CMEPolicyIteration, tmp_path) -> None:
    n = len(agent.store) + len(agent.holdout)
    job = pil.Job("InvertedPendulum-v5", 0, 300, {}, ("observation",), (1, 2), n + 150, 100, 1, 500, 0.5, 3, str(tmp_path))
    row = pil.measure(agent, job)
    assert row["steps"] == [n, n + 100, n + 150]
    assert set(row["returns"]) == {"observation d1", "observation d2"}
    assert all(len(values) == 3 and min(values) >= 1 for values in row["returns"].values())


def test_the_collection_mixes_uniform_states_over_the_box_with_states_of_d(agent: CMEPolicyIteration) -> None:
    data = agent.store.get(slice(0, len(agent.store)))
    job = pil.Job("InvertedPendulum-v5", 0, 300, {}, ("observation",), (1,), 0, 0, 1, 200, 0.5, 1, "")
    states = pil.collection(agent, data, job, torch.Generator().manual_seed(0))
    assert states.shape == (200, data.obs.shape[1])
    from_data = (states[:, None, :] == data.obs[None]).all(-1).any(-1)
    assert int(from_data.sum()) == 100  # the uniform half lands on no stored state
    box = agent.dynamics.obs_encoder
    assert (box.normalize(states[:100]).abs() <= 1 + 1e-5).all()  # uniform draws lie in the box
