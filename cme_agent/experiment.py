"""What ``train.py`` does with a composed Hydra config: build, train, evaluate, save, summarise."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import torch
from hydra.utils import get_class, instantiate
from omegaconf import DictConfig, OmegaConf
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.logger import configure
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import VecEnv

import cme_agent  # noqa: F401  (registers the custom envs)
from cme_agent.callbacks import IterationCheckpoint


def make_env(cfg: DictConfig) -> VecEnv:
    """The training envs: ``cfg.n_envs`` copies of ``cfg.env.id`` made with ``cfg.env.kwargs``, seeded."""
    kwargs = OmegaConf.to_container(cfg.env.kwargs, resolve=True)
    return make_vec_env(cfg.env.id, n_envs=cfg.n_envs, seed=cfg.seed, env_kwargs=kwargs)


def build_agent(cfg: DictConfig, env: VecEnv) -> BaseAlgorithm:
    """Instantiate ``cfg.agent`` on ``env``; a bad value stops the run with a message naming its key."""
    try:
        return instantiate(cfg.agent, env=env, seed=cfg.seed, verbose=cfg.verbose, _convert_="all")
    except Exception as error:  # Hydra wraps constructor errors in InstantiationException
        cause = error.__cause__ if error.__cause__ is not None else error
        if isinstance(cause, (ValueError, TypeError, AssertionError)):  # SB3 asserts on unsupported action spaces
            raise SystemExit(f"Invalid configuration: {cause}") from cause
        raise


def resume_agent(cfg: DictConfig, env: VecEnv) -> BaseAlgorithm:
    """Load the checkpoint ``cfg.resume`` (written by a run of the same config) to continue on ``env``."""
    agent_class = get_class(cfg.agent._target_)
    model = agent_class.load(cfg.resume, env=env)
    if model.num_timesteps >= cfg.total_timesteps:
        raise SystemExit(
            f"the checkpoint {cfg.resume} already has {model.num_timesteps} >= total_timesteps={cfg.total_timesteps} steps"
        )
    print(f"resuming from {cfg.resume} at {model.num_timesteps} steps")
    return model


def make_eval_env(cfg: DictConfig) -> gym.Env:
    """A fresh (Monitor-wrapped) ``cfg.env``, its random starts seeded apart from training's
    (``cfg.seed + 10_000``): every evaluation of a seed, agent or reference controller, flies the same starts."""
    env = Monitor(gym.make(cfg.env.id, **OmegaConf.to_container(cfg.env.kwargs, resolve=True)))
    env.reset(seed=cfg.seed + 10_000)
    return env


def evaluate(model: BaseAlgorithm, cfg: DictConfig) -> tuple[float, float]:
    """Mean and std of the return over ``cfg.eval_episodes`` episodes of the deterministic policy,
    on :func:`make_eval_env`."""
    env = make_eval_env(cfg)
    mean, std = evaluate_policy(model, env, n_eval_episodes=cfg.eval_episodes, deterministic=True)
    env.close()
    return float(mean), float(std)


def run(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Train the agent of ``cfg`` on its env, evaluate it, and write into ``run_dir`` the
    TensorBoard events, ``progress.csv``, ``model.zip`` and ``summary.json``.

    :param cfg: the composed config (conf/config.yaml)
    :param run_dir: the run directory
    :return: the summary
    """
    run_dir.mkdir(parents=True, exist_ok=True)
    if cfg.torch_threads:
        torch.set_num_threads(cfg.torch_threads)
    env = make_env(cfg)
    model = resume_agent(cfg, env) if cfg.resume else build_agent(cfg, env)
    formats = ["stdout", "csv", "tensorboard"] if cfg.verbose else ["csv", "tensorboard"]
    model.set_logger(configure(str(run_dir), formats))
    callbacks = [IterationCheckpoint(run_dir / "checkpoint.zip", cfg.checkpoint_every)] if cfg.checkpoint_every else []
    start = time.perf_counter()
    model.learn(
        total_timesteps=cfg.total_timesteps - model.num_timesteps,
        callback=callbacks,
        progress_bar=cfg.progress_bar,
        reset_num_timesteps=not cfg.resume,
    )
    train_seconds = time.perf_counter() - start
    model.save(run_dir / "model.zip")
    mean, std = evaluate(model, cfg)
    model.logger.record("eval/mean_reward", mean)
    model.logger.record("eval/std_reward", std)
    model.logger.dump(step=model.num_timesteps)
    summary = {
        "env": cfg.env.id,
        "agent": type(model).__name__,
        "seed": cfg.seed,
        "total_timesteps": model.num_timesteps,
        "eval_episodes": cfg.eval_episodes,
        "eval_mean_reward": mean,
        "eval_std_reward": std,
        "train_seconds": train_seconds,
        "q": getattr(model, "q", None),
        "run_dir": str(run_dir),
    }
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    print(
        f"{cfg.env.id} seed {cfg.seed}: return {mean:.1f} +- {std:.1f} over {cfg.eval_episodes} episodes "
        f"after {model.num_timesteps} steps ({train_seconds:.0f} s); run dir {run_dir}"
    )
    env.close()
    return summary
