"""Sweeps on real engines: Hydra's submitit launcher (the code path of submitit_slurm, run locally)
and Hydra's Optuna sweeper with the shipped search space; the SLURM example config composes."""

import json
import os
import subprocess
import sys

import pytest
import yaml
from hydra import compose, initialize_config_dir

from tests.conftest import ROOT

SMALL = [
    "verbose=0",
    "total_timesteps=200",
    "eval_every=0",
    "eval_episodes=1",
    "checkpoint_every=0",
    "agent.model_update.n_steps=20",
    "agent.evaluation.rounds=1",
    "agent.exploration.random_steps=100",
    "agent.policy_kwargs.phi.resolution=[9,7]",
]


def _multirun(sweep_dir, *overrides):
    command = [sys.executable, str(ROOT / "train.py"), "-m", f"hydra.sweep.dir={sweep_dir}", *SMALL, *overrides]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=sweep_dir.parent, env=env)


def test_submitit_local_sweep_writes_one_summary_per_job(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    result = _multirun(tmp_path / "sweep", "hydra/launcher=submitit_local", "hydra.launcher.timeout_min=5", "seed=0,1")
    assert result.returncode == 0, result.stderr[-3000:]
    summaries = [json.loads((tmp_path / "sweep" / str(job) / "summary.json").read_text()) for job in (0, 1)]
    assert [s["seed"] for s in summaries] == [0, 1]
    assert all(s["total_timesteps"] == 200 and not s["interrupted"] for s in summaries)
    jobs = [path for path in (tmp_path / "sweep" / ".submitit").iterdir() if path.name.isdigit()]
    assert len(jobs) == 2  # two submitit jobs (processes) ran them, each logging its run
    logs = [log.read_text() for job in jobs for log in job.glob("*_log.out")]
    assert sorted(sum(f"seed {seed}: return" in log for seed in (0, 1)) for log in logs) == [1, 1]


def test_optuna_sweep_maximises_the_final_evaluation(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper")
    result = _multirun(tmp_path / "sweep", "+sweep=optuna", "hydra.sweeper.n_trials=2")
    assert result.returncode == 0, result.stderr[-3000:]
    summaries = [json.loads((tmp_path / "sweep" / str(trial) / "summary.json").read_text()) for trial in (0, 1)]
    best = yaml.safe_load((tmp_path / "sweep" / "optimization_results.yaml").read_text())
    assert best["best_value"] == pytest.approx(max(s["eval_mean_reward"] for s in summaries))
    assert set(best["best_params"]) == {
        "agent.gamma",
        "agent.omega",
        "agent.steps_per_iteration",
        "agent.feature_selection.threshold",
        "agent.evaluation.collection_size",
        "agent.exploration.explore_fraction",
    }
    trial = yaml.safe_load((tmp_path / "sweep" / "0" / ".hydra" / "overrides.yaml").read_text())
    assert any(item.startswith("agent.gamma=") for item in trial)


def test_slurm_example_composes_into_the_submitit_slurm_launcher():
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        cfg = compose(
            config_name="config",
            overrides=["hydra/launcher=slurm_example", "hydra.launcher.partition=cpu"],
            return_hydra_config=True,
        )
    launcher = cfg.hydra.launcher
    assert launcher._target_ == "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"
    assert launcher.partition == "cpu" and launcher.signal_delay_s > 0 and launcher.max_num_timeout == 0
