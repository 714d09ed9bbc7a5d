"""The run directory holds what the README promises: a checkpoint of the end of training even in a
run shorter than checkpoint_every, and, when a launch fails, the error in its train.log."""

from __future__ import annotations

import json

import torch
from stable_baselines3.common.env_util import make_vec_env

from cme_agent import CMEPolicyIteration
from cme_agent.callbacks import IterationCheckpoint
from tests.conftest import CountingCallback, run_train

SMALL = [
    "eval_every=0",
    "eval_episodes=1",
    "verbose=0",
    "agent.steps_per_iteration=100",
    "agent.evaluation.collection_size=300",
    "agent.exploration.random_steps=100",
]


def test_a_run_shorter_than_checkpoint_every_leaves_a_checkpoint_of_its_end(tmp_path):
    result = run_train(tmp_path, "total_timesteps=300", "checkpoint_every=10", *SMALL)
    assert result.returncode == 0, result.stderr
    checkpoint = CMEPolicyIteration.load(tmp_path / "checkpoint.zip", env=make_vec_env("Pendulum-v1", seed=1))
    model = CMEPolicyIteration.load(tmp_path / "model.zip")
    assert checkpoint.num_timesteps == model.num_timesteps == 300  # the end of training, as model.zip
    assert torch.equal(checkpoint.dynamics.weights, model.dynamics.weights)
    assert len(checkpoint.store) + len(checkpoint.holdout) == 300  # resumable: it holds the data
    checkpoint.learn(100, reset_num_timesteps=False)
    assert checkpoint.num_timesteps == 400


def test_a_stopped_learn_keeps_the_checkpoint_of_its_last_boundary(tmp_path, pendulum_kwargs):
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **pendulum_kwargs)
    path = tmp_path / "checkpoint.zip"
    model.learn(400, callback=[IterationCheckpoint(path, every=2), CountingCallback(stop_after=350)])
    assert CMEPolicyIteration.load(path).num_timesteps == 200  # not the half iteration after it


def test_a_launch_that_fails_at_construction_says_why_in_train_log(tmp_path):
    result = run_train(tmp_path, "agent.gamma=1.5", *SMALL)
    assert result.returncode != 0
    log = (tmp_path / "train.log").read_text()
    assert "Invalid configuration: gamma=1.5 is invalid" in log
    assert "Traceback" not in result.stderr


def test_a_launch_whose_env_cannot_be_made_has_the_error_in_train_log(tmp_path):
    result = run_train(tmp_path, "env.id=NoSuchEnv-v0", *SMALL)
    assert result.returncode != 0
    log = (tmp_path / "train.log").read_text()
    assert "the run failed: NameNotFound" in log and "NoSuchEnv" in log
    assert not (tmp_path / "summary.json").exists()


def test_checkpoint_every_0_writes_no_checkpoint_even_at_the_end(tmp_path):
    result = run_train(tmp_path, "total_timesteps=200", "checkpoint_every=0", *SMALL)
    assert result.returncode == 0, result.stderr
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["total_timesteps"] == 200 and not summary["interrupted"]
    assert not (tmp_path / "checkpoint.zip").exists()  # checkpoint_every=0: none, not even at the end
