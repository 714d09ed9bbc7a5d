"""Callbacks of our own, in SB3's callback framework.

All of them act at iteration boundaries (``on_rollout_start``, which CMEPolicyIteration calls at
the start of each iteration's data acquisition, and SB3's algorithms at the start of each
rollout) or read what ``on_step`` sees, and none draws from the agent's random generators: a run
gives the same agent with them as without them.
"""

from __future__ import annotations

import dataclasses
import pathlib
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from types import FrameType
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.utils import safe_mean
from stable_baselines3.common.vec_env import VecEnv


class IterationCheckpoint(BaseCallback):
    """Save a resumable checkpoint (model + transition store + RNG state) at iteration boundaries,
    every ``every`` iterations and at the end of training.

    It hooks ``on_rollout_start``, which the agent calls at the start of each iteration's data
    acquisition, so a checkpoint always holds a whole number of iterations; the file is
    replaced atomically, so a crash leaves the previous checkpoint intact. When ``learn()`` ends
    having taken all its steps, the end is checkpointed too, so the checkpoint is never older
    than the model saved after training and a run shorter than ``every`` iterations has one; a
    ``learn()`` stopped by a callback (e.g. :class:`StopOnSignal`, which writes its own) is not.

    :param path: the checkpoint file (overwritten each time)
    :param every: iterations between checkpoints
    :param verbose: 1 to print a line per checkpoint
    """

    def __init__(self, path: str | pathlib.Path, every: int = 1, verbose: int = 0) -> None:
        super().__init__(verbose)
        if every < 1:
            raise ValueError(f"checkpoint every={every} is invalid: must be an integer >= 1")
        self.path = pathlib.Path(path)
        self.every = every
        self._rollouts = 0

    def _on_rollout_start(self) -> None:
        if self._rollouts > 0 and self._rollouts % self.every == 0:
            self._save()
        self._rollouts += 1

    def _on_training_end(self) -> None:
        if self.model.num_timesteps >= self.model._total_timesteps:  # completed, at an iteration boundary
            self._save()

    def _save(self) -> None:
        self.model.save(self.path, include=["replay_buffer"])
        if self.verbose:
            print(f"checkpoint at {self.model.num_timesteps} steps: {self.path}")

    def _on_step(self) -> bool:
        return True


@dataclasses.dataclass(frozen=True)
class Evaluation:
    """One evaluation of the deterministic policy.

    :param timesteps: env steps of training behind the evaluated policy
    :param returns: the return of each episode
    :param lengths: the length of each episode
    """

    timesteps: int
    returns: tuple[float, ...]
    lengths: tuple[int, ...]

    @property
    def mean_reward(self) -> float:
        return float(np.mean(self.returns))

    @property
    def std_reward(self) -> float:
        return float(np.std(self.returns))

    @property
    def mean_ep_length(self) -> float:
        return float(np.mean(self.lengths))

    def as_dict(self) -> dict[str, float]:
        """The evaluation as plain data (``summary.json`` keeps a list of these)."""
        return {
            "timesteps": self.timesteps,
            "mean_reward": self.mean_reward,
            "std_reward": self.std_reward,
            "mean_ep_length": self.mean_ep_length,
        }


class PeriodicEvaluation(BaseCallback):
    """Evaluate the deterministic policy every ``eval_every`` env steps, at the first iteration
    boundary at or after each multiple, on an env of its own; log ``eval/mean_reward``,
    ``eval/std_reward`` and ``eval/mean_ep_length`` at the current ``num_timesteps``.

    Unlike SB3's ``EvalCallback`` (which counts ``on_step`` calls, i.e. vector steps, and evaluates
    mid-rollout), it counts env steps and evaluates the policy an iteration has just produced; each
    evaluation runs on a fresh env from ``make_eval_env``, so with a seeded factory every
    evaluation flies the same starts and the curve moves with the policy only. The evaluations
    are kept in :attr:`evaluations` and, with ``log_path``, in SB3's ``evaluations.npz`` format
    (``timesteps``, ``results``, ``ep_lengths``). When learning continues from a checkpoint in the
    same folder, the evaluations of that file up to the checkpoint's step are kept and the later
    ones (of the interrupted run, to be redone) dropped.

    :param make_eval_env: returns a fresh (Monitor-wrapped, seeded) evaluation env
    :param eval_every: env steps between evaluations; 0: only when :meth:`evaluate` is called
    :param n_eval_episodes: episodes per evaluation
    :param log_path: ``evaluations.npz`` to write (None: none)
    :param close: close each env after its evaluation (False: ``make_eval_env`` hands out an env
        that lives on, e.g. the user's own, reseeded each time)
    :param verbose: 1 to print a line per evaluation
    """

    def __init__(
        self,
        make_eval_env: Callable[[], gym.Env | VecEnv],
        eval_every: int,
        n_eval_episodes: int = 10,
        log_path: str | pathlib.Path | None = None,
        close: bool = True,
        verbose: int = 0,
    ) -> None:
        super().__init__(verbose)
        if eval_every < 0:
            raise ValueError(f"eval_every={eval_every} is invalid: must be an integer >= 0")
        if n_eval_episodes < 1:
            raise ValueError(f"n_eval_episodes={n_eval_episodes} is invalid: must be an integer >= 1")
        self.make_eval_env = make_eval_env
        self.eval_every = eval_every
        self.n_eval_episodes = n_eval_episodes
        self.log_path = pathlib.Path(log_path) if log_path is not None else None
        self.close = close
        self.evaluations: list[Evaluation] = []
        self._next = 0

    def _on_training_start(self) -> None:
        steps = self.model.num_timesteps
        if not self.evaluations and self.log_path is not None and self.log_path.exists():
            with np.load(self.log_path) as saved:
                self.evaluations = [
                    Evaluation(int(t), tuple(map(float, r)), tuple(map(int, n)))
                    for t, r, n in zip(saved["timesteps"], saved["results"], saved["ep_lengths"], strict=True)
                ]
        self.evaluations = [evaluation for evaluation in self.evaluations if evaluation.timesteps <= steps]
        self._next = (steps // self.eval_every + 1) * self.eval_every if self.eval_every else 0

    def _on_rollout_start(self) -> None:
        if self.eval_every and self.model.num_timesteps >= self._next:
            self.evaluate()
            self._next = (self.model.num_timesteps // self.eval_every + 1) * self.eval_every

    def _on_step(self) -> bool:
        return True

    def evaluate(self) -> Evaluation:
        """Evaluate the policy now (e.g. the final one after ``learn()``), log and keep the result."""
        env = self.make_eval_env()
        returns, lengths = evaluate_policy(
            self.model, env, n_eval_episodes=self.n_eval_episodes, deterministic=True, return_episode_rewards=True
        )
        if self.close:
            env.close()
        evaluation = Evaluation(self.model.num_timesteps, tuple(map(float, returns)), tuple(map(int, lengths)))
        self.evaluations.append(evaluation)
        if self.log_path is not None:
            np.savez(
                self.log_path,
                timesteps=[e.timesteps for e in self.evaluations],
                results=[e.returns for e in self.evaluations],
                ep_lengths=[e.lengths for e in self.evaluations],
            )
        self.logger.record("eval/mean_reward", evaluation.mean_reward)
        self.logger.record("eval/std_reward", evaluation.std_reward)
        self.logger.record("eval/mean_ep_length", evaluation.mean_ep_length)
        self.logger.record("time/total_timesteps", evaluation.timesteps, exclude="tensorboard")
        self.logger.dump(step=evaluation.timesteps)
        if self.verbose:
            print(f"evaluation at {evaluation.timesteps} steps: {evaluation.mean_reward:.1f} +- {evaluation.std_reward:.1f}")
        return evaluation


class EpisodeReturnsByBehaviour(BaseCallback):
    """Log the returns of CMEPolicyIteration's training episodes by the policy that acted:
    ``rollout/greedy_ep_rew_mean`` (episodes of the greedy policy) apart from
    ``rollout/explore_ep_rew_mean`` (episodes of its noisy version), each the mean over the
    episodes of that kind that ended in the iteration (not recorded when none did). Episodes
    with steps in the initial uniformly random phase (``exploration.random_steps``) are neither.

    SB3's ``rollout/ep_rew_mean`` averages the last ``stats_window_size`` episodes of both kinds.
    It reads Monitor's ``info["episode"]`` in ``on_step``, which the agent calls before it draws
    the next episodes' behaviour.

    :param verbose: unused (SB3 signature)
    """

    def __init__(self, verbose: int = 0) -> None:
        super().__init__(verbose)
        self._returns: dict[str, list[float]] = {"greedy": [], "explore": []}

    def _on_step(self) -> bool:
        explore = self.model._behaviour.explore
        random_steps = self.model.exploration_config.random_steps
        n_envs = len(explore)
        for index, (done, info) in enumerate(zip(self.locals["dones"], self.locals["infos"], strict=True)):
            if done and "episode" in info:
                first_step = self.model.num_timesteps - n_envs * int(info["episode"]["l"])  # num_timesteps before it
                if first_step >= random_steps:
                    self._returns["explore" if explore[index] else "greedy"].append(float(info["episode"]["r"]))
        return True

    def _on_rollout_end(self) -> None:
        for kind, returns in self._returns.items():
            if returns:
                self.logger.record(f"rollout/{kind}_ep_rew_mean", safe_mean(returns))
            returns.clear()


class TrainingAbandonedError(KeyboardInterrupt):
    """A second interrupting signal: ``learn()`` was left mid-iteration (the agent is not in a state to save)."""

    def __init__(self, signum: int) -> None:
        super().__init__(f"{signal.Signals(signum).name} received twice: training abandoned mid-iteration")
        self.signum = signum


class StopOnSignal(BaseCallback):
    """Stop ``learn()`` cleanly on SIGINT (Ctrl-C) or SIGTERM (what SLURM sends before it kills
    a job): the iteration under way is finished, a checkpoint of its end is written at the next
    iteration boundary, and ``on_step`` then returns False, which ends ``learn()`` after that one
    step (whose transition the checkpoint does not hold). A second signal raises
    :class:`TrainingAbandonedError` at once.

    The handlers are installed by ``on_training_start`` (only in the main thread, where Python
    delivers signals) and the previous ones put back by ``on_training_end`` or :meth:`restore`.

    :param checkpoint_path: where to write the checkpoint (``save(..., include=["replay_buffer"])``)
    :param signals: the signals to catch
    :param restore_on_training_end: put the previous handlers back when ``learn()`` ends; False
        keeps them (a signal then only sets :attr:`received`) until :meth:`restore` is called,
        e.g. to cover the saving and evaluation that follow ``learn()``
    :param verbose: 1 to print what happens on stderr
    """

    def __init__(
        self,
        checkpoint_path: str | pathlib.Path,
        signals: Sequence[signal.Signals] = (signal.SIGINT, signal.SIGTERM),
        restore_on_training_end: bool = True,
        verbose: int = 1,
    ) -> None:
        super().__init__(verbose)
        self.checkpoint_path = pathlib.Path(checkpoint_path)
        self.signals = tuple(signals)
        self.restore_on_training_end = restore_on_training_end
        self.received: int | None = None
        self.checkpoint_steps: int | None = None
        self._previous: dict[int, Any] = {}

    @property
    def stopped(self) -> bool:
        """Whether training was stopped by a signal (the checkpoint is written)."""
        return self.checkpoint_steps is not None

    def _on_training_start(self) -> None:
        if threading.current_thread() is threading.main_thread():
            for signum in self.signals:
                self._previous[signum] = signal.signal(signum, self._handle)

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.received is not None:
            raise TrainingAbandonedError(signum)
        self.received = signum
        if self.verbose:
            print(
                f"\n{signal.Signals(signum).name} received: finishing the iteration under way, then a checkpoint "
                "and stop (send it again to abandon the iteration)",
                file=sys.stderr,
                flush=True,
            )

    def _on_rollout_start(self) -> None:
        if self.received is not None and self.checkpoint_steps is None:
            self.model.save(self.checkpoint_path, include=["replay_buffer"])
            self.checkpoint_steps = self.model.num_timesteps

    def _on_step(self) -> bool:
        return not self.stopped

    def _on_training_end(self) -> None:
        if self.restore_on_training_end:
            self.restore()

    def restore(self) -> None:
        """Put back the signal handlers found at ``on_training_start`` (again: nothing)."""
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()
