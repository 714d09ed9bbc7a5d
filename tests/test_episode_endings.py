"""benchmarks/episode_endings.py: how evaluation episodes end, counted on CartPole-v1 with fixed policies."""

from __future__ import annotations

import gymnasium as gym
import numpy as np

from benchmarks.diagnostics.episode_endings import TERMINATION_BOUNDS, episode_endings


class ConstantPolicy:
    """Always the same action, in SB3's ``predict`` form."""

    def __init__(self, action: int) -> None:
        self.action = action

    def predict(self, obs: np.ndarray, deterministic: bool = True) -> tuple[int, None]:
        return self.action, None


def test_pushing_one_way_drops_the_pole_in_every_episode() -> None:
    env = gym.make("CartPole-v1")
    env.reset(seed=0)
    row = episode_endings(ConstantPolicy(1), env, TERMINATION_BOUNDS["cartpole"], episodes=5)
    assert row["past pole angle"] == 5 and row["past cart position"] == 0 and row["truncated"] == 0
    assert row["return_mean"] < 20  # a constant push tips the pole within a few dozen steps
    assert set(row) >= {f"mean abs obs[{i}]" for i in range(4)}


def test_a_short_time_limit_counts_as_truncation_not_termination() -> None:
    env = gym.make("CartPole-v1", max_episode_steps=3)
    env.reset(seed=0)
    row = episode_endings(ConstantPolicy(0), env, TERMINATION_BOUNDS["cartpole"], episodes=4)
    assert row["truncated"] == 4 and row["past pole angle"] == 0 and row["past cart position"] == 0
    assert row["return_mean"] == 3.0
