"""Hydra: every env config composes into a working agent; train.py writes its run directory."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from cme_agent.config import AgentConfig
from cme_agent.experiment import make_env, make_eval_env
from cme_agent.presets import preset_for
from tests.conftest import run_train

ROOT = Path(__file__).resolve().parents[1]
ENV_CONFIGS = sorted(p.stem for p in (ROOT / "conf" / "env").glob("*.yaml"))


def _compose(overrides):
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        return compose(config_name="config", overrides=overrides)


def test_every_classic_env_has_a_config():
    assert {"pendulum", "mountain_car_continuous", "mountain_car", "cartpole", "acrobot"} <= set(ENV_CONFIGS)


@pytest.mark.parametrize("agent_name", ["cme", "kernel"])
@pytest.mark.parametrize("env_name", ENV_CONFIGS)
def test_env_config_composes_into_an_agent(env_name, agent_name):
    cfg = _compose([f"env={env_name}", f"agent={agent_name}"])
    env = make_env(cfg)
    agent = instantiate(cfg.agent, env=env, seed=0, _convert_="all")
    assert type(agent).__name__ == cfg.agent._target_.rsplit(".", 1)[1]
    assert agent.gamma == cfg.agent.gamma == preset_for(cfg.env.id).get("gamma", AgentConfig().gamma)
    assert agent.policy.dynamics.phi.width > 1
    env.close()


def test_eval_env_follows_the_config_and_its_starts_the_seed():
    cfg = _compose(["env=pendulum", "seed=3"])
    first, again = make_eval_env(cfg).reset()[0], make_eval_env(cfg).reset()[0]
    assert first.tolist() == again.tolist()  # an agent and a reference fly the same starts
    assert first.tolist() != make_env(cfg).reset()[0].tolist()  # not training's
    assert first.tolist() != make_eval_env(_compose(["env=pendulum", "seed=4"])).reset()[0].tolist()
    quadcopter = make_eval_env(_compose(["env=quadcopter", "env.kwargs.agent_dt=0.3"]))
    assert quadcopter.unwrapped.agent_dt == 0.3  # overrides of env.kwargs reach the env


def test_presets_apply_and_command_line_overrides_win():
    """The Hydra config holds no second copy of the presets: it composes the package's preset file
    (cme_agent/presets/<env id>.yaml) into the agent's settings, and what the command line sets wins."""
    cfg = _compose(["env=pendulum", "agent.gamma=0.95"])
    assert list(cfg.agent.policy_kwargs.phi.resolution) == preset_for("Pendulum-v1")["policy_kwargs"]["phi"]["resolution"]
    agent = instantiate(cfg.agent, env=cfg.env.id, seed=0, _convert_="all")
    assert agent.policy.dynamics.phi.width == 21 * 15 + 1 and agent.omega == 0.2  # the preset
    assert agent.gamma == 0.95  # the override
    assert agent.preset_message is None  # composed by Hydra: the agent does not apply the preset again
    cartpole = _compose(["env=cartpole"])
    assert instantiate(cartpole.agent, env=cartpole.env.id, seed=0, _convert_="all").gamma == 0.995


def test_train_writes_events_model_and_summary(tmp_path):
    result = run_train(
        tmp_path,
        "total_timesteps=300",
        "eval_episodes=2",
        "verbose=0",
        "agent.steps_per_iteration=100",
        "agent.model_update.n_steps=20",
        "agent.evaluation.collection_size=300",
        "agent.exploration.random_steps=100",
    )
    assert result.returncode == 0, result.stderr
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["env"] == "Pendulum-v1" and summary["total_timesteps"] == 300
    assert summary["q"] > 0
    assert list(tmp_path.glob("events.out.tfevents.*"))
    assert (tmp_path / "model.zip").exists() and (tmp_path / "progress.csv").exists()
    assert "return" in result.stdout
    preset_line = "Applied the tuned preset cme_agent/presets/Pendulum-v1.yaml (composed by Hydra)"
    assert f"{preset_line}; your overrides of agent.evaluation.collection_size win over it" in result.stdout


@pytest.mark.parametrize(
    "override, message",
    [
        ("agent.gamma=1.5", "gamma=1.5 is invalid"),
        ("agent.feature_selection.bandwidths=[-0.2]", "bandwidths"),
        ("agent.gamm=0.5", "gamm"),
    ],
)
def test_train_refuses_bad_configuration_clearly(tmp_path, override, message):
    result = run_train(tmp_path, override)
    assert result.returncode != 0
    assert message in result.stderr + result.stdout
    assert "Traceback" not in result.stderr


def test_multirun_sweep_writes_one_run_directory_per_seed(tmp_path):
    command = [
        sys.executable,
        str(ROOT / "train.py"),
        "-m",
        "seed=0,1",
        "total_timesteps=200",
        "eval_episodes=1",
        "verbose=0",
        "agent.steps_per_iteration=100",
        "agent.model_update.n_steps=10",
        "agent.evaluation.collection_size=300",
        "agent.exploration.random_steps=100",
        f"hydra.sweep.dir={tmp_path}",
    ]
    result = subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    seeds = [json.loads((tmp_path / str(job) / "summary.json").read_text())["seed"] for job in (0, 1)]
    assert seeds == [0, 1]
