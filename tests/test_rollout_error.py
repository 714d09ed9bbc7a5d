"""benchmarks/diagnostics/rollout_error.py: the h-step error of a rolled-out model on known systems, and the
simulator's lockstep rollouts (MuJoCo) against stepping the env itself."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from benchmarks.diagnostics.rollout_error import rollout_errors, true_rollout

A = torch.tensor([[1.0, 0.1], [0.0, 1.0]])
B = torch.tensor([[0.0], [0.1]])


def linear_rollout(start: torch.Tensor, actions: torch.Tensor, a: torch.Tensor = A) -> torch.Tensor:
    """s_{h+1} = A s_h + B a_h from ``start`` (N, 2) with ``actions`` (H, N, 1): (H, N, 2)."""
    states, s = [], start
    for action in actions:
        s = s @ a.T + action @ B.T
        states.append(s)
    return torch.stack(states)


def test_an_exact_model_has_no_error_and_the_ended_rollouts_leave_the_average() -> None:
    generator = torch.Generator().manual_seed(0)
    start, actions = torch.randn(6, 2, generator=generator), torch.randn(4, 6, 1, generator=generator)
    true = linear_rollout(start, actions)
    ended = torch.zeros(4, 6, dtype=torch.bool)
    ended[2:, 0] = True  # rollout 0 ends at step 3
    ended[3, 1] = True
    errors, counts = rollout_errors(lambda s, a: s @ A.T + a @ B.T, start, actions, true, ended, torch.ones(2))
    assert errors.shape == (4, 2) and counts.tolist() == [6, 6, 5, 4]
    torch.testing.assert_close(errors, torch.zeros(4, 2), atol=1e-6, rtol=0)


def test_a_model_error_compounds_with_the_steps_in_units_of_each_dims_std() -> None:
    generator = torch.Generator().manual_seed(1)
    start, actions = torch.randn(50, 2, generator=generator), torch.randn(6, 50, 1, generator=generator)
    true = linear_rollout(start, actions)
    wrong = A + torch.tensor([[0.0, 0.0], [0.0, 0.02]])  # the velocity decays 2% too slowly per step
    ended = torch.zeros(6, 50, dtype=torch.bool)
    ended[:, :10] = torch.arange(6)[:, None] >= 1  # 10 rollouts end after their first step
    std = torch.tensor([1.0, 0.5])
    errors, counts = rollout_errors(lambda s, a: s @ wrong.T + a @ B.T, start, actions, true, ended, std)
    going_on = ~ended[-1]
    expected = (linear_rollout(start, actions, wrong)[-1] - true[-1]).abs()[going_on] / std
    torch.testing.assert_close(errors[-1], expected.mean(dim=0))
    assert counts.tolist() == [50, 40, 40, 40, 40, 40]
    assert bool((errors[1:, 1] > errors[:-1, 1]).all())  # the velocity's error grows every step
    assert float(errors[0, 0]) == 0.0 < float(errors[1, 0])  # and reaches the position a step later


def test_the_lockstep_rollouts_match_the_env_stepped_from_each_start() -> None:
    pytest.importorskip("mujoco")
    env_id, horizon = "InvertedDoublePendulum-v5", 12
    env, sim = gym.make(env_id), gym.make(env_id).unwrapped
    starts, rng = [], np.random.default_rng(0)
    for seed in range(3):
        obs, _ = env.reset(seed=seed)
        starts.append((obs, env.unwrapped.data.qpos.copy(), env.unwrapped.data.qvel.copy()))
    obs, qpos, qvel = (np.stack(parts) for parts in zip(*starts, strict=True))
    plan = rng.uniform(-1, 1, size=(horizon, 3, 1)).astype(np.float32)
    calls = iter(plan)
    actions, states, ended = true_rollout(sim, qpos, qvel, obs, lambda current: next(calls), horizon)
    np.testing.assert_array_equal(actions, plan)
    assert ended.any(axis=0).any()  # full pushes for 12 steps topple at least one
    for i, seed in enumerate(range(3)):
        env.reset(seed=seed)
        done = False
        for h in range(horizon):
            if not done:
                step_obs, _, done, _, _ = env.step(plan[h, i])
                np.testing.assert_allclose(states[h, i], step_obs, atol=1e-6)
            assert bool(ended[h, i]) == done
