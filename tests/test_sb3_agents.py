"""SB3 baselines through the Hydra CLI: conf/agent/{sac,td3,ppo,dqn}.yaml with the zoo's
hyperparameters per env (conf/agent_env/<agent>_<env>.yaml; for the CME agent that file composes
the package's preset, cme_agent/presets/<env id>.yaml)."""

import inspect
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from hydra import compose, initialize_config_dir
from hydra.utils import get_class
from omegaconf import DictConfig
from stable_baselines3 import SAC
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise
from stable_baselines3.common.type_aliases import TrainFrequencyUnit
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from cme_agent.experiment import build_agent, make_env
from tests.conftest import run_train

ROOT = Path(__file__).resolve().parents[1]
SB3_AGENTS = ("sac", "td3", "ppo", "dqn")
BOX_ENVS = ("pendulum", "mountain_car_continuous")
DISCRETE_ENVS = ("mountain_car", "cartpole", "acrobot")
VALID_PAIRS = sorted(
    [(agent, env) for agent in ("sac", "td3") for env in BOX_ENVS]
    + [("ppo", env) for env in BOX_ENVS + DISCRETE_ENVS]
    + [("dqn", env) for env in DISCRETE_ENVS]
)
NESTED = ("policy_kwargs", "action_noise", "train_freq")  # zoo keys checked by the dedicated tests below


def _compose(*overrides: str) -> DictConfig:
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        return compose(config_name="config", overrides=["verbose=0", *overrides])


def _build(agent: str, env: str) -> tuple[BaseAlgorithm, DictConfig]:
    """The agent ``train.py agent=<agent> env=<env>`` would train (constructed, not trained), and its config."""
    cfg = _compose(f"agent={agent}", f"env={env}")
    return build_agent(cfg, make_env(cfg)), cfg


def _zoo_settings(agent: str, env: str) -> dict[str, Any]:
    """The ``agent:`` section of ``conf/agent_env/<agent>_<env>.yaml``, as written."""
    return yaml.safe_load((ROOT / "conf" / "agent_env" / f"{agent}_{env}.yaml").read_text())["agent"]


def _stored(model: Any, key: str) -> Any:
    """The value SB3 keeps for constructor argument ``key`` (clip_range becomes a schedule)."""
    value = getattr(model, key)
    return value(1.0) if key == "clip_range" else value


def test_every_valid_pair_has_a_zoo_config_and_no_other() -> None:
    files = {tuple(p.stem.split("_", 1)) for p in (ROOT / "conf" / "agent_env").glob("*.yaml")}
    assert {pair for pair in files if pair[0] in SB3_AGENTS} == set(VALID_PAIRS)


@pytest.mark.filterwarnings("ignore:You have specified a mini-batch size")  # ppo_mountain_car_continuous: the zoo's
@pytest.mark.parametrize(("agent", "env"), VALID_PAIRS)
def test_pair_composes_into_the_sb3_agent_with_zoo_settings(agent: str, env: str) -> None:
    model, cfg = _build(agent, env)
    assert type(model).__name__ == agent.upper()
    assert model.n_envs == cfg.n_envs and model.device.type == "cpu"
    zoo = _zoo_settings(agent, env)
    for key, value in zoo.items():
        if key not in NESTED:
            assert _stored(model, key) == value, key
    assert zoo.get("policy_kwargs", {}).items() <= model.policy_kwargs.items()
    model.env.close()


@pytest.mark.parametrize("agent", SB3_AGENTS)
def test_generic_agent_config_holds_sb3_defaults(agent: str) -> None:
    """conf/agent/<agent>.yaml promises SB3's own defaults (but for the device: the CPU)."""
    settings = yaml.safe_load((ROOT / "conf" / "agent" / f"{agent}.yaml").read_text())
    algorithm = get_class(settings.pop("_target_"))
    assert (settings.pop("policy"), settings.pop("device")) == ("MlpPolicy", "cpu")
    parameters = inspect.signature(algorithm).parameters
    assert {key: parameters[key].default for key in settings} == settings


def test_generic_defaults_reach_an_agent_without_a_zoo_config() -> None:
    """ToyChain-v0 has no sac_toy.yaml: the agent gets conf/agent/sac.yaml alone."""
    model, cfg = _build("sac", "toy")
    assert not (ROOT / "conf" / "agent_env" / "sac_toy.yaml").exists()
    for key in ("learning_rate", "buffer_size", "learning_starts", "batch_size", "tau", "gamma", "gradient_steps"):
        assert getattr(model, key) == inspect.signature(SAC).parameters[key].default == cfg.agent[key], key
    model.env.close()


def test_td3_exploration_noise_and_episodic_updates_are_instantiated() -> None:
    pendulum, _ = _build("td3", "pendulum")
    assert isinstance(pendulum.action_noise, NormalActionNoise)
    np.testing.assert_array_equal(pendulum.action_noise._sigma, [0.1])
    assert (pendulum.train_freq.frequency, pendulum.train_freq.unit) == (1, TrainFrequencyUnit.EPISODE)
    car, _ = _build("td3", "mountain_car_continuous")
    assert isinstance(car.action_noise, OrnsteinUhlenbeckActionNoise)
    np.testing.assert_array_equal(car.action_noise._sigma, [0.5])
    assert car.action_noise().shape == car.action_space.shape
    for model in (pendulum, car):
        model.env.close()


def test_train_py_runs_ppo_and_writes_summary_and_tensorboard(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    result = run_train(
        run_dir,
        "agent=ppo",
        "env=cartpole",
        "total_timesteps=256",
        "eval_episodes=1",
        "agent.n_steps=64",
        "agent.batch_size=32",
        "verbose=0",
    )
    assert result.returncode == 0, result.stderr
    summary = json.loads((run_dir / "summary.json").read_text())
    assert (summary["agent"], summary["env"]) == ("PPO", "CartPole-v1")
    assert summary["total_timesteps"] == 8 * 64, "one rollout of n_steps on each of the zoo's 8 envs"
    assert (run_dir / "model.zip").exists() and (run_dir / "progress.csv").exists()
    (events,) = run_dir.glob("events.out.tfevents.*")
    scalars = set(EventAccumulator(str(events)).Reload().Tags()["scalars"])
    assert {"rollout/ep_rew_mean", "time/fps", "train/value_loss", "eval/mean_reward"} <= scalars


def test_train_py_refuses_an_agent_that_cannot_act_in_the_env(tmp_path: Path) -> None:
    result = run_train(tmp_path / "run", "agent=dqn", "env=pendulum", "verbose=0")
    assert result.returncode != 0
    output = result.stdout + result.stderr
    assert "only supports" in output and "Discrete" in output and "Box" in output
    assert "Traceback" not in output
