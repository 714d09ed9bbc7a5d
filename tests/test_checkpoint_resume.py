"""Checkpoints hold everything; a resumed run continues where the interrupted one stopped."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import torch
from stable_baselines3.common.env_util import make_vec_env

from cme_agent import CMEPolicyIteration
from cme_agent.callbacks import IterationCheckpoint

ROOT = Path(__file__).resolve().parents[1]


def _agent(pendulum_kwargs, env=None):
    env = env if env is not None else make_vec_env("Pendulum-v1", n_envs=1, seed=0)
    return CMEPolicyIteration("CMEPolicy", env, seed=1, reset_envs_each_iteration=True, **pendulum_kwargs)


def test_checkpoint_holds_the_transition_store(tmp_path, pendulum_kwargs):
    model = _agent(pendulum_kwargs)
    model.learn(300)
    model.save(tmp_path / "ckpt.zip", include=["replay_buffer"])
    loaded = CMEPolicyIteration.load(tmp_path / "ckpt.zip", env=make_vec_env("Pendulum-v1", n_envs=1, seed=0))
    assert len(loaded.store) == len(model.store) and len(loaded.holdout) == len(model.holdout)
    assert torch.equal(loaded.store.get(slice(0, len(loaded.store))).obs, model.store.get(slice(0, len(model.store))).obs)
    assert loaded.iteration == model.iteration == 3
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    fresh = _agent(pendulum_kwargs)
    fresh.load_replay_buffer(tmp_path / "buffer.pkl")
    assert len(fresh.store) == len(model.store)


def test_resumed_run_ends_with_the_same_parameters(tmp_path, pendulum_kwargs):
    uninterrupted = _agent(pendulum_kwargs)
    uninterrupted.learn(500)

    interrupted = _agent(pendulum_kwargs)
    interrupted.learn(300, callback=IterationCheckpoint(tmp_path / "ckpt.zip", every=1))
    # the last checkpoint is of the end of learn() (300 steps): resume from there
    resumed = CMEPolicyIteration.load(tmp_path / "ckpt.zip", env=make_vec_env("Pendulum-v1", n_envs=1, seed=123))
    assert resumed.num_timesteps == 300
    resumed.learn(200, reset_num_timesteps=False)
    assert resumed.num_timesteps == 500
    for name in ("theta_psi", "theta_phi"):
        assert torch.equal(getattr(resumed.policy, name), getattr(uninterrupted.policy, name)), name
    assert torch.equal(resumed.dynamics.weights, uninterrupted.dynamics.weights)
    assert torch.equal(resumed.policy.dynamics.psi.centres, uninterrupted.policy.dynamics.psi.centres)


def test_train_resumes_after_sigkill(tmp_path):
    run_dir = tmp_path / "run"
    common = [
        sys.executable,
        str(ROOT / "train.py"),
        "total_timesteps=1500",
        "eval_episodes=1",
        "verbose=0",
        "checkpoint_every=1",
        "agent.steps_per_iteration=100",
        "agent.model_update.n_steps=20",
        "agent.evaluation.collection_size=300",
        "agent.evaluation.rounds=1",
        "agent.exploration.random_steps=100",
    ]
    process = subprocess.Popen([*common, f"hydra.run.dir={run_dir}"], cwd=tmp_path)
    checkpoint = run_dir / "checkpoint.zip"
    deadline = time.time() + 240
    while time.time() < deadline and process.poll() is None:
        if checkpoint.exists() and json.loads(_meta(checkpoint))["state"]["num_timesteps"] >= 300:
            break
        time.sleep(0.2)
    assert process.poll() is None, "training finished before it could be killed"
    os.kill(process.pid, signal.SIGKILL)
    process.wait()
    steps_at_kill = json.loads(_meta(checkpoint))["state"]["num_timesteps"]
    assert 300 <= steps_at_kill < 1500
    resumed_dir = tmp_path / "resumed"
    result = subprocess.run(
        [*common, f"resume={checkpoint}", f"hydra.run.dir={resumed_dir}"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    assert f"resuming from {checkpoint} at {steps_at_kill} steps" in result.stdout
    summary = json.loads((resumed_dir / "summary.json").read_text())
    assert summary["total_timesteps"] == 1500


def _meta(path):
    import zipfile

    with zipfile.ZipFile(path) as archive:
        return archive.read("cme_agent.json")
