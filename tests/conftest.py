"""Shared fixtures: small agent settings that keep each learn() call to a second or two."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import torch
from stable_baselines3.common.callbacks import BaseCallback

from cme_agent.buffer import Transitions
from cme_agent.presets import preset_for

ROOT = Path(__file__).resolve().parents[1]


def _observation_facts(env_id: str) -> dict[str, Any]:
    return preset_for(env_id)["policy_kwargs"]["observation"]


PENDULUM_POLICY = {"phi": {"resolution": [9, 7]}, "observation": _observation_facts("Pendulum-v1")}
CARTPOLE_POLICY = {"phi": {"resolution": [3, 3, 5, 5]}, "observation": _observation_facts("CartPole-v1")}
"""Small grids for quick tests; the observation facts (angle pairs, bounds) are the presets'."""


def small_kwargs(**overrides: Any) -> dict[str, Any]:
    """Agent arguments for quick tests: few steps per iteration, small samples."""
    kwargs: dict[str, Any] = {
        "steps_per_iteration": 100,
        "feature_selection": {"subsample_size": 300, "max_features": 20},
        "model_update": {"n_steps": 20, "batch_size": 64, "holdout_size": 100},
        "evaluation": {"collection_size": 300, "rounds": 2},
        "exploration": {"random_steps": 100},
        "policy_kwargs": PENDULUM_POLICY,
    }
    kwargs.update(overrides)
    return kwargs


@pytest.fixture
def pendulum_kwargs() -> dict[str, Any]:
    return small_kwargs()


@pytest.fixture
def cartpole_kwargs() -> dict[str, Any]:
    return small_kwargs(policy_kwargs=CARTPOLE_POLICY)


def run_train(run_dir: Path, *overrides: str) -> subprocess.CompletedProcess:
    """``python train.py <overrides>`` writing into ``run_dir``, one BLAS thread (a shared machine)."""
    command = [sys.executable, str(ROOT / "train.py"), f"hydra.run.dir={run_dir}", *overrides]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=run_dir.parent, env=env)


class CountingCallback(BaseCallback):
    """Counts ``on_step`` calls; returns False at call ``stop_after`` (None: never)."""

    def __init__(self, stop_after: int | None = None) -> None:
        super().__init__()
        self.calls = 0
        self.stop_after = stop_after

    def _on_step(self) -> bool:
        self.calls += 1
        return self.stop_after is None or self.calls < self.stop_after


def linear_system(n: int, seed: int) -> Transitions:
    """A linear system in 4 dims with one action, terminated where |s'_1| > 0.15 (both sides), reward 1 - s'_0^2;
    s_0 and s_1 change by a constant."""
    g = torch.Generator().manual_seed(seed)
    obs = 0.1 * torch.randn(n, 4, generator=g)
    actions = 2 * torch.rand(n, 1, generator=g) - 1
    change = obs @ torch.tensor([[0.0, 0.0, 0.1, 0.0], [0.0, 0.0, 0.0, 0.1], [0.0, 0.0, 0.0, 0.3], [0.0, 0.0, 0.0, 0.0]])
    next_obs = obs + change + actions * torch.tensor([0.0, 0.0, 0.05, -0.1]) + 0.01
    return Transitions(obs, actions, 1 - next_obs[:, 0].square(), next_obs, next_obs[:, 1].abs() > 0.15)
