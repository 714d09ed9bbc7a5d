"""benchmarks/pendulum_optimum.py: its dynamics are Pendulum-v1's, its grid interpolates exactly at
the nodes and wraps the angle, and its optimal policy flown by the evaluation protocol beats doing
nothing on the same starts."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from stable_baselines3.common.evaluation import evaluate_policy

from benchmarks.common import compose_config
from benchmarks.diagnostics import pendulum_optimum as po
from cme_agent.experiment import make_eval_env


def test_step_is_the_simulators():
    env = gym.make("Pendulum-v1").unwrapped
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(50):
        angle, speed, torque = rng.uniform(-4, 4), rng.uniform(-8, 8), rng.uniform(-2, 2)
        env.state = np.array([angle, speed])
        observation, reward, *_ = env.step(np.array([torque], dtype=np.float32))
        next_angle, next_speed, expected_reward = po.pendulum_step(np.array(angle), np.array(speed), float(np.float32(torque)))
        np.testing.assert_allclose(observation, [np.cos(next_angle), np.sin(next_angle), next_speed], rtol=1e-5, atol=1e-5)
        assert abs(reward - expected_reward) < 1e-4


def test_interpolation_is_exact_at_nodes_and_periodic_in_the_angle():
    grid = po.Grid(12, 9)
    values = np.random.default_rng(1).normal(size=(12, 9))
    angle, speed = np.meshgrid(grid.angles, grid.speeds, indexing="ij")
    np.testing.assert_allclose(grid.interpolate(values, angle, speed), values, atol=1e-12)
    np.testing.assert_allclose(grid.interpolate(values, angle + 2 * np.pi, speed), values, atol=1e-12)
    midpoint = grid.interpolate(values, np.array(grid.angles[3] + np.pi / 12), np.array(grid.speeds[4]))
    np.testing.assert_allclose(midpoint, 0.5 * (values[3, 4] + values[4, 4]))


def test_one_step_value_is_the_best_reward():
    grid, torques = po.Grid(24, 17), np.linspace(-2, 2, 5)
    values = po.solve(grid, torques, horizon=1)
    angle, speed = np.meshgrid(grid.angles, grid.speeds, indexing="ij")
    np.testing.assert_allclose(values[1], -(po.angle_normalize(angle) ** 2 + 0.1 * speed**2))  # torque 0 is best


class ZeroTorque:
    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        return np.zeros((1, 1), dtype=np.float32), None


def test_optimal_policy_beats_doing_nothing_on_the_protocols_starts():
    grid, torques = po.Grid(61, 41), np.linspace(-2, 2, 9)
    policy = po.OptimalPendulumPolicy(grid, po.solve(grid, torques), torques)
    optimal = po.optimal_returns(policy, seed=0, episodes=3)
    env = make_eval_env(compose_config(["env=pendulum", "seed=0"]))
    idle, _ = evaluate_policy(ZeroTorque(), env, n_eval_episodes=3, return_episode_rewards=True)
    assert len(optimal) == 3
    assert np.mean(optimal) > np.mean(idle) + 100
