"""The measurements of benchmarks/reward_model_error.py (no long training): PointGoal2D's closed-form
reward against the env's own steps, and the probe's rows on a short run."""

from __future__ import annotations

import numpy as np
import torch

from benchmarks.diagnostics import reward_model_error
from benchmarks.unseen_envs import CUSTOM_ENV
from cme_agent import CMEPolicyIteration
from cme_agent.envs.point_goal import PointGoal2D


def test_true_reward_is_the_envs_reward():
    env = PointGoal2D()
    rng = np.random.default_rng(0)
    obs, actions, rewards = [], [], []
    for _ in range(50):
        env.state = np.concatenate([rng.uniform(-2, 2, 2), rng.uniform(-0.5, 0.5, 2)])
        action = rng.uniform(-1.5, 1.5, 2)  # outside the box too: the env clips
        obs.append(env.state.astype(np.float32))
        actions.append(action)
        rewards.append(env.step(action)[1])
    computed = reward_model_error.true_reward(env, torch.as_tensor(np.array(obs)), torch.as_tensor(np.array(actions)))
    np.testing.assert_allclose(computed.numpy(), rewards, rtol=1e-5, atol=1e-5)


def test_probe_rows_after_a_short_run():
    model = CMEPolicyIteration(
        "CMEPolicy",
        CUSTOM_ENV,
        seed=0,
        steps_per_iteration=100,
        exploration={"random_steps": 100},
        model_update={"kind": "cme"},
    )
    probe = reward_model_error.RewardErrorProbe(seed=0, every=200)
    model.learn(400, callback=probe)
    assert [row["steps"] for row in probe.rows] == [200, 400]
    assert 0 < probe.rows[0]["q"] <= probe.rows[1]["q"] <= model.dynamics.q
    for row in probe.rows:
        for where in ("data", "uniform"):
            for which in ("random", "greedy"):
                bias, mae, largest = (row[f"{where}_{which}_{stat}"] for stat in ("bias", "mae", "max"))
                assert abs(bias) <= mae + 1e-3 and largest >= bias - 1e-2
        assert len(row["box_half_range"]) == 4
