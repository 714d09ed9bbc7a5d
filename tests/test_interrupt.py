"""Interruptions lose nothing: SIGINT/SIGTERM finish the iteration, checkpoint, save and stop;
resume continues in the same run directory and TensorBoard run."""

import csv
import json
import os
import shlex
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from cme_agent import CMEPolicyIteration
from cme_agent.callbacks import StopOnSignal
from cme_agent.experiment import make_env, resume_agent
from cme_agent.run_log import configure_run_logger
from tests.conftest import ROOT

PIPES = {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE}
SMALL = [
    "verbose=0",
    "eval_every=200",
    "eval_episodes=1",
    "checkpoint_every=0",  # only the checkpoint of the interruption
    "agent.steps_per_iteration=100",
    "agent.model_update.n_steps=20",
    "agent.evaluation.collection_size=300",
    "agent.evaluation.rounds=1",
    "agent.exploration.random_steps=100",
    "agent.policy_kwargs.phi.resolution=[9,7]",
]


class SignalAt(BaseCallback):
    """Send ``signum`` to this process once training reaches ``steps``."""

    def __init__(self, steps: int, signum: int) -> None:
        super().__init__()
        self.steps, self.signum, self.sent = steps, signum, False

    def _on_step(self) -> bool:
        if not self.sent and self.num_timesteps >= self.steps:
            self.sent = True
            os.kill(os.getpid(), self.signum)
        return True


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_signal_finishes_the_iteration_and_resumes_exactly(tmp_path, pendulum_kwargs, signum):
    def agent(env_seed):
        env = make_vec_env("Pendulum-v1", n_envs=1, seed=env_seed)
        return CMEPolicyIteration("CMEPolicy", env, seed=1, reset_envs_each_iteration=True, **pendulum_kwargs)

    uninterrupted = agent(0)
    uninterrupted.learn(500)
    before = signal.getsignal(signum)
    interrupted = agent(0)
    stop = StopOnSignal(tmp_path / "checkpoint.zip", verbose=0)
    interrupted.learn(500, callback=[SignalAt(250, signum), stop])
    assert stop.stopped and stop.received == signum
    assert stop.checkpoint_steps == 300  # the iteration under way at step 250 was finished
    assert interrupted.num_timesteps == 301  # learn() stopped after one more step
    assert signal.getsignal(signum) is before  # the handler is put back
    resumed = CMEPolicyIteration.load(tmp_path / "checkpoint.zip", env=make_vec_env("Pendulum-v1", n_envs=1, seed=5))
    resumed.learn(200, reset_num_timesteps=False)
    assert resumed.num_timesteps == 500
    assert torch.equal(resumed.dynamics.weights, uninterrupted.dynamics.weights)
    for name in ("theta_psi", "theta_phi"):
        assert torch.equal(getattr(resumed.policy, name), getattr(uninterrupted.policy, name)), name


def _wait_for_step(process, progress, steps, timeout=240):
    deadline = time.time() + timeout
    while time.time() < deadline and process.poll() is None:
        if progress.exists():
            lines = progress.read_text().splitlines()
            if len(lines) > 1:
                column = lines[0].split(",").index("time/total_timesteps")
                if any(line.split(",")[column] and float(line.split(",")[column]) >= steps for line in lines[1:]):
                    return
        time.sleep(0.05)


def test_sigint_to_train_py_leaves_model_summary_and_a_checkpoint_to_resume(tmp_path):
    run_dir = tmp_path / "run"
    command = [sys.executable, str(ROOT / "train.py"), "total_timesteps=1500", *SMALL]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    process = subprocess.Popen(
        [*command, f"hydra.run.dir={run_dir}"],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    _wait_for_step(process, run_dir / "progress.csv", 300)
    assert process.poll() is None, "training finished before it could be interrupted"
    process.send_signal(signal.SIGINT)
    stdout, stderr = process.communicate(timeout=120)
    assert process.returncode == 128 + signal.SIGINT, stderr
    assert "Traceback" not in stderr and "SIGINT received: finishing the iteration under way" in stderr
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["interrupted"] is True
    steps = summary["total_timesteps"]
    assert 300 <= steps < 1500 and steps % 100 == 0  # an iteration boundary (at or after the signal)
    assert CMEPolicyIteration.load(run_dir / "model.zip").q > 0
    assert summary["checkpoint"] == str(run_dir / "checkpoint.zip")
    assert summary["resume_command"] in stdout
    assert [e["timesteps"] for e in summary["evaluations"]] == list(range(200, steps + 1, 200))

    resume = shlex.split(summary["resume_command"])
    assert resume[0] == "python" and resume[-1] == f"resume={run_dir / 'checkpoint.zip'}"
    result = subprocess.run(
        [sys.executable, *resume[1:]], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300
    )  # as printed: no hydra.run.dir, the run continues in the checkpoint's directory
    assert result.returncode == 0, result.stderr
    assert f"resuming from {run_dir / 'checkpoint.zip'} at {steps} steps" in result.stdout
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["interrupted"] is False and summary["total_timesteps"] == 1500
    expected = [*range(200, 1500, 200), 1500]
    assert [e["timesteps"] for e in summary["evaluations"]] == expected
    assert not (tmp_path / "outputs").exists()
    events = EventAccumulator(str(run_dir))
    events.Reload()  # one TensorBoard run: the evaluations of both processes, none twice
    assert [e.step for e in events.Scalars("eval/mean_reward")] == expected
    np.testing.assert_allclose(
        [e.value for e in events.Scalars("eval/mean_reward")], [e["mean_reward"] for e in summary["evaluations"]], rtol=1e-6
    )
    progress = (run_dir / "progress.csv").read_text().splitlines()
    column = progress[0].split(",").index("time/iterations")
    assert [int(line.split(",")[column]) for line in progress[1:] if line.split(",")[column]] == list(range(1, 16))


def test_resumed_logs_drop_what_followed_the_checkpoint(tmp_path):
    """After a crash at step 500, a run resumed from the checkpoint of step 300 rewrites 400 and 500."""
    logger = configure_run_logger(tmp_path, verbose=0)
    for step in range(100, 600, 100):
        logger.record("time/total_timesteps", step)
        logger.record("train/value", float(step))
        logger.dump(step)
    logger.close()
    logger = configure_run_logger(tmp_path, verbose=0, resumed_at=300)
    for step in (400, 500):
        logger.record("time/total_timesteps", step)
        logger.record("train/value", -float(step))
        logger.record("train/new_key", 1.0)
        logger.dump(step)
    logger.close()
    rows = list(csv.DictReader((tmp_path / "progress.csv").open()))
    assert [(r["time/total_timesteps"], r["train/value"], r["train/new_key"]) for r in rows] == [
        ("100", "100.0", ""),
        ("200", "200.0", ""),
        ("300", "300.0", ""),
        ("400", "-400.0", "1.0"),
        ("500", "-500.0", "1.0"),
    ]
    events = EventAccumulator(str(tmp_path))
    events.Reload()
    assert [(e.step, e.value) for e in events.Scalars("train/value")] == [
        (100, 100.0),
        (200, 200.0),
        (300, 300.0),
        (400, -400.0),
        (500, -500.0),
    ]


def test_resumed_episodes_do_not_replay_the_runs_first(tmp_path, pendulum_kwargs):
    """The env's state is not in a checkpoint: a resumed run starts fresh episodes, seeded apart from the run's first."""
    model = CMEPolicyIteration("CMEPolicy", make_vec_env("Pendulum-v1", n_envs=1, seed=0), seed=0, **pendulum_kwargs)
    model.learn(200)
    model.save(tmp_path / "checkpoint.zip", include=["replay_buffer"])
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        cfg = compose(config_name="config", overrides=["seed=0", f"resume={tmp_path / 'checkpoint.zip'}"])
    env = make_env(cfg)
    assert resume_agent(cfg, env).num_timesteps == 200
    assert not np.array_equal(env.reset(), make_env(cfg).reset())
