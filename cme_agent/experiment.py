"""What ``train.py`` does with a composed Hydra config: build, train, evaluate, save, summarise."""

from __future__ import annotations

import json
import logging
import shlex
import signal
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from hydra.utils import get_class, instantiate
from omegaconf import DictConfig, OmegaConf
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import VecEnv

from cme_agent.algorithm import CMEPolicyIteration
from cme_agent.callbacks import IterationCheckpoint, PeriodicEvaluation, StopOnSignal, TrainingAbandonedError
from cme_agent.dashboards import EVAL_SEED_OFFSET, training_dashboards
from cme_agent.pictures import PictureCallback
from cme_agent.presets import preset_for
from cme_agent.references import Reference, controller_fraction, reference_returns
from cme_agent.run_log import configure_run_logger
from cme_agent.settings import changed_kwargs_note
from cme_agent.threads import torch_threads

log = logging.getLogger(__name__)  # under Hydra: stdout and the run directory's train.log

# SIGINT: Ctrl-C; SIGTERM: kill's default and SLURM's preemption; SIGUSR2: submitit_slurm's warning
# signal_delay_s before the time limit
STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGUSR2") if hasattr(signal, name))


PRESET_CHOICE = "presets@agent"
"""The config group under which Hydra composes an env's preset into ``agent``
(``conf/agent_env/cme_<env>.yaml``: ``/presets@agent: <env id>``)."""


def preset_line(cfg: DictConfig, choices: Mapping[str, Any], overrides: Sequence[str] = ()) -> str:
    """The log line saying which preset file Hydra composed into ``cfg.agent``, if any, which of
    its keys the command line overrode, and which of the env's kwargs differ from the registered
    env's the preset was tuned on.

    :param cfg: the composed config
    :param choices: the config group choices of the composition (Hydra's ``runtime.choices``)
    :param overrides: the run's command-line overrides (Hydra's ``overrides.task``)
    """
    name = choices.get(PRESET_CHOICE)
    if name is None:
        return f"No tuned preset composed for {cfg.env.id}: the library defaults (conf/agent/cme.yaml) and your overrides"
    line = f"Applied the tuned preset cme_agent/presets/{name}.yaml (composed by Hydra)"
    if name != cfg.env.id:
        line += f" to {cfg.env.id}"
    preset_keys = _dotted_keys(preset_for(name) or {})
    given = sorted({item.split("=", 1)[0].lstrip("+~") for item in overrides})
    overridden = [
        key
        for key in given
        if key.startswith("agent.")
        and any(leaf == key[6:] or leaf.startswith(f"{key[6:]}.") or key[6:].startswith(f"{leaf}.") for leaf in preset_keys)
    ]
    if overridden:
        line += f"; your overrides of {', '.join(overridden)} win over it"
    note = changed_kwargs_note(cfg.env.id, OmegaConf.to_container(cfg.env.kwargs, resolve=True))
    if note is not None:
        line += f"; {note}: add '~agent_env' for the library defaults"
    return line


def _dotted_keys(settings: Mapping[str, Any], prefix: str = "") -> list[str]:
    """Dotted names of the non-mapping values of nested settings (``evaluation.collection_size``)."""
    keys: list[str] = []
    for key, value in settings.items():
        keys += _dotted_keys(value, f"{prefix}{key}.") if isinstance(value, Mapping) else [f"{prefix}{key}"]
    return keys


def resume_run_dir(resume: str | None, default: str) -> str:
    """``hydra.run.dir`` of conf/config.yaml (resolver ``cme_run_dir``): a run resumed from a
    checkpoint continues in the checkpoint's folder; a new run goes to ``default``."""
    return str(Path(resume).parent) if resume else default


def resume_command(overrides: Sequence[str], checkpoint: Path, script: str = "train.py") -> str:
    """The shell command that resumes a run: ``script`` with the run's overrides and ``resume=checkpoint``.

    :param overrides: the command-line overrides of the run (Hydra's ``overrides.task``)
    :param checkpoint: the checkpoint to resume from
    :param script: the Hydra app, as it was invoked
    """
    kept = [item for item in overrides if item.split("=", 1)[0].lstrip("+~") != "resume"]
    return shlex.join(["python", script, *kept, f"resume={checkpoint}"])


def make_env(cfg: DictConfig) -> VecEnv:
    """The training envs: ``cfg.n_envs`` copies of ``cfg.env.id`` made with ``cfg.env.kwargs``, seeded."""
    kwargs = OmegaConf.to_container(cfg.env.kwargs, resolve=True)
    return make_vec_env(cfg.env.id, n_envs=cfg.n_envs, seed=cfg.seed, env_kwargs=kwargs)


def _thread_kwargs(cfg: DictConfig) -> dict[str, Any]:
    """``n_threads`` for a CME agent (it applies it in ``learn()``); SB3's agents take none."""
    return {"n_threads": cfg.n_threads} if issubclass(get_class(cfg.agent._target_), CMEPolicyIteration) else {}


def build_agent(cfg: DictConfig, env: VecEnv) -> BaseAlgorithm:
    """Instantiate ``cfg.agent`` on ``env``; a bad value stops the run with a message naming its key."""
    try:
        return instantiate(cfg.agent, env=env, seed=cfg.seed, verbose=cfg.verbose, **_thread_kwargs(cfg), _convert_="all")
    except Exception as error:  # Hydra wraps constructor errors in InstantiationException
        cause = error.__cause__ if error.__cause__ is not None else error
        if isinstance(cause, (ValueError, TypeError, AssertionError)):  # SB3 asserts on unsupported action spaces
            raise SystemExit(f"Invalid configuration: {cause}") from cause
        raise


def resume_agent(cfg: DictConfig, env: VecEnv) -> BaseAlgorithm:
    """Load the checkpoint ``cfg.resume`` (written by a run of the same config) to continue on ``env``."""
    agent_class = get_class(cfg.agent._target_)
    model = agent_class.load(cfg.resume, env=env, **_thread_kwargs(cfg))
    if model.num_timesteps >= cfg.total_timesteps:
        raise SystemExit(
            f"the checkpoint {cfg.resume} already has {model.num_timesteps} >= total_timesteps={cfg.total_timesteps} steps"
        )
    # The env's own state (its half-finished episodes, its RNG) is not in a checkpoint: the resumed
    # run starts fresh episodes. Seed them apart from the run's first ones (cfg.seed), which it
    # would otherwise replay; with reset_envs_each_iteration the agent reseeds the envs anyway.
    env.seed(int(np.random.SeedSequence([cfg.seed, model.num_timesteps]).generate_state(1)[0]))
    log.info(f"resuming from {cfg.resume} at {model.num_timesteps} steps")
    return model


def make_eval_env(cfg: DictConfig) -> gym.Env:
    """A fresh (Monitor-wrapped) ``cfg.env``, its random starts seeded apart from training's
    (``cfg.seed + 10_000``): every evaluation of a seed, agent or reference controller, flies the same starts."""
    env = Monitor(gym.make(cfg.env.id, **OmegaConf.to_container(cfg.env.kwargs, resolve=True)))
    env.reset(seed=cfg.seed + EVAL_SEED_OFFSET)
    return env


def evaluate(model: BaseAlgorithm, cfg: DictConfig) -> tuple[float, float]:
    """Mean and std of the return over ``cfg.eval_episodes`` episodes of the deterministic policy,
    on :func:`make_eval_env`."""
    env = make_eval_env(cfg)
    mean, std = evaluate_policy(model, env, n_eval_episodes=cfg.eval_episodes, deterministic=True)
    env.close()
    return float(mean), float(std)


def run(
    cfg: DictConfig,
    run_dir: Path,
    overrides: Sequence[str] = (),
    script: str = "train.py",
    choices: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Train the agent of ``cfg`` on its env, evaluating it every ``cfg.eval_every`` steps and at
    the end, and write into ``run_dir`` the TensorBoard events, ``progress.csv``,
    ``evaluations.npz``, ``checkpoint.zip`` (every ``cfg.checkpoint_every`` iterations and at the
    end), ``model.zip`` and ``summary.json``; torch runs at ``cfg.n_threads`` CPU threads.

    SIGINT, SIGTERM or SIGUSR2 stop training at the end of the iteration under way (a second one at once):
    the checkpoint, ``model.zip`` and a summary marked ``"interrupted": true`` are written, the
    command that resumes is printed, and the process exits with status 128 + the signal number.
    A run resumed from a checkpoint of ``run_dir`` continues its logs and evaluation curve. A run
    that fails (a refused setting, an env that cannot be made, an error in training) logs the
    error, so that the run directory's ``train.log`` says why.

    :param cfg: the composed config (conf/config.yaml)
    :param run_dir: the run directory
    :param overrides: the run's command-line overrides (for the resume command)
    :param script: the Hydra app as invoked (for the resume command)
    :param choices: the config group choices of the composition (Hydra's ``runtime.choices``), to
        log which env preset was composed into a CME agent's settings (None: not logged)
    :return: the summary
    """
    run_dir.mkdir(parents=True, exist_ok=True)
    try:
        return _train(cfg, run_dir, overrides, script, choices)
    except SystemExit as stop:
        if isinstance(stop.code, str):  # a refused configuration or checkpoint, said in one line
            log.error(stop.code)
        raise
    except Exception as error:  # the traceback follows on stderr (Hydra's report)
        log.error(f"the run failed: {type(error).__name__}: {error}")
        raise


def _train(
    cfg: DictConfig, run_dir: Path, overrides: Sequence[str], script: str, choices: Mapping[str, Any] | None
) -> dict[str, Any]:
    """:func:`run` without its logging of errors."""
    env = make_env(cfg)
    model = resume_agent(cfg, env) if cfg.resume else build_agent(cfg, env)
    if choices is not None and not cfg.resume and isinstance(model, CMEPolicyIteration):
        log.info(preset_line(cfg, choices, overrides))
    resumed_at = model.num_timesteps if cfg.resume else None
    model.set_logger(configure_run_logger(run_dir, cfg.verbose, resumed_at, cfg.log_interval))
    try:
        dashboards = training_dashboards(
            model,
            lambda: make_eval_env(cfg),
            cfg.eval_every,
            cfg.eval_episodes,
            log_path=run_dir / "evaluations.npz",
            pictures=_pictures(cfg) if cfg.pictures_every else False,
            progress_bar=cfg.progress_bar,
        )
        periodic = [IterationCheckpoint(run_dir / "checkpoint.zip", cfg.checkpoint_every)] if cfg.checkpoint_every else []
    except ValueError as error:
        raise SystemExit(f"Invalid configuration: {error}") from error
    evaluation = dashboards.evaluation
    stop = StopOnSignal(run_dir / "checkpoint.zip", STOP_SIGNALS, restore_on_training_end=False)
    start = time.perf_counter()
    try:
        with torch_threads(cfg.n_threads):  # SB3's agents; a CME agent sets its n_threads (the same) itself
            model.learn(
                total_timesteps=cfg.total_timesteps - model.num_timesteps,
                callback=[dashboards, *periodic, stop],  # the final evaluation and checkpoint at the end of learn()
                reset_num_timesteps=not cfg.resume,
            )
        train_seconds = time.perf_counter() - start
        model.save(run_dir / "model.zip")
    except TrainingAbandonedError as abandoned:
        summary = _summary(cfg, model, run_dir, evaluation, time.perf_counter() - start, model.num_timesteps)
        _report_interruption(summary, abandoned.signum, run_dir, overrides, script, abandoned=True)
        raise SystemExit(128 + abandoned.signum) from None
    finally:
        stop.restore()
        env.close()
    if stop.stopped:  # the checkpoint's step: learn() went one env step further
        summary = _summary(cfg, model, run_dir, evaluation, train_seconds, stop.checkpoint_steps)
        _report_interruption(summary, stop.received, run_dir, overrides, script, abandoned=False)
        raise SystemExit(128 + stop.received)
    references = reference_returns(cfg.env.id, lambda: make_eval_env(cfg), cfg.eval_episodes, cfg.seed)
    summary = _summary(cfg, model, run_dir, evaluation, train_seconds, model.num_timesteps, interrupted=False)
    summary["references"] = {reference.name: reference.as_dict() for reference in references}
    summary["fraction_of_controller"] = controller_fraction(summary["eval_mean_reward"], references)
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    log.info(
        f"{cfg.env.id} seed {cfg.seed}: return {summary['eval_mean_reward']:.1f} +- {summary['eval_std_reward']:.1f} "
        f"over {cfg.eval_episodes} episodes after {model.num_timesteps} steps ({train_seconds:.0f} s)"
        f"{_scale(summary['fraction_of_controller'], references)}; run dir {run_dir}"
    )
    return summary


def _scale(fraction: float | None, references: Sequence[Reference]) -> str:
    """The references of the final log line (random actions first in ``references``):
    ``; 0.95 of the scripted controller's 43.1 +- 2.0; random actions: 1.2 +- 0.8``."""
    random, *controllers = references
    parts = [
        f"{fraction:.2f} of the {controller.name}'s {controller.mean_reward:.1f} +- {controller.std_reward:.1f}"
        if fraction is not None
        else f"{controller.name}: {controller.mean_reward:.1f} +- {controller.std_reward:.1f}"
        for controller in controllers
    ]
    parts.append(f"{random.name}: {random.mean_reward:.1f} +- {random.std_reward:.1f}")
    return "".join(f"; {part}" for part in parts)


def _summary(
    cfg: DictConfig,
    model: BaseAlgorithm,
    run_dir: Path,
    evaluation: PeriodicEvaluation,
    train_seconds: float,
    steps: int,
    interrupted: bool = True,
) -> dict[str, Any]:
    """The content of ``summary.json``: the last evaluation, the whole evaluation curve, the run's facts."""
    last = evaluation.evaluations[-1] if evaluation.evaluations else None
    return {
        "env": cfg.env.id,
        "agent": type(model).__name__,
        "seed": cfg.seed,
        "total_timesteps": steps,
        "eval_episodes": cfg.eval_episodes,
        "eval_mean_reward": last.mean_reward if last else None,
        "eval_std_reward": last.std_reward if last else None,
        "evaluations": [item.as_dict() for item in evaluation.evaluations],
        "train_seconds": train_seconds,
        "q": getattr(model, "q", None),
        "interrupted": interrupted,
        "run_dir": str(run_dir),
    }


def _pictures(cfg: DictConfig) -> PictureCallback:
    """The TensorBoard pictures of ``cfg`` (V(s), greedy action, held-out model error, psi's centres)."""
    return PictureCallback(
        every=cfg.pictures_every,
        picture_dims=None if cfg.picture_dims is None else OmegaConf.to_container(cfg.picture_dims),
        resolution=cfg.picture_resolution,
        fixed=OmegaConf.to_container(cfg.picture_fixed) if cfg.picture_fixed else None,
    )


def _report_interruption(
    summary: dict[str, Any], signum: int, run_dir: Path, overrides: Sequence[str], script: str, abandoned: bool
) -> None:
    """Write the summary of an interrupted run with its checkpoint, and log the command that resumes from it."""
    checkpoint = run_dir / "checkpoint.zip"
    name, steps = signal.Signals(signum).name, summary["total_timesteps"]
    if abandoned:
        what = f"{name} received twice: training abandoned mid-iteration at {steps} steps; wrote summary.json"
    else:
        what = f"{name} received: stopped at {steps} steps; wrote checkpoint.zip, model.zip and summary.json"
    summary["checkpoint"] = str(checkpoint) if checkpoint.exists() else None
    summary["resume_command"] = resume_command(overrides, checkpoint, script) if checkpoint.exists() else None
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    if summary["resume_command"]:
        log.info(f"{what} in {run_dir}; resume (from this directory) with:\n  {summary['resume_command']}")
    else:
        log.info(f"{what} in {run_dir}; no checkpoint was written yet: nothing to resume from")
