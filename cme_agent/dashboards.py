"""What a training run shows: evaluation curves, returns by behaviour, pictures and a progress bar.

:func:`training_dashboards` assembles the callbacks of :mod:`cme_agent.callbacks` and
:mod:`cme_agent.pictures` into one :class:`Dashboards` callback. ``train.py``
(:func:`cme_agent.experiment.run`) passes one to ``learn()``; ``CMEPolicyIteration.learn(eval_env=...)``
builds the same one (:func:`with_dashboards`), so a run from Python shows the dashboards of a
run of ``train.py``.
"""

from __future__ import annotations

import pathlib
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import gymnasium as gym
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback, CallbackList, ConvertCallback, ProgressBarCallback
from stable_baselines3.common.env_util import is_wrapped
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.type_aliases import MaybeCallback
from stable_baselines3.common.vec_env import VecEnv

from cme_agent.callbacks import EpisodeReturnsByBehaviour, PeriodicEvaluation
from cme_agent.pictures import PictureCallback

EVAL_SEED_OFFSET = 10_000
"""The evaluation env's starts are seeded with the agent's seed plus this: apart from training's,
and the same for every evaluation of a run (``train.py``'s ``seed + 10_000``)."""

EvalEnv = gym.Env | VecEnv | str | Callable[[], gym.Env | VecEnv]
"""What ``eval_env=`` takes: an env id, an env, a VecEnv, or a function returning a fresh (seeded) env."""


class EvaluationProgressBar(ProgressBarCallback):
    """SB3's progress bar (tqdm + rich: steps, elapsed time, ETA), its description the last
    evaluation's return (``eval -143.2 +- 27.2``).

    :param evaluation: the periodic evaluation whose results to show (None: a plain bar)
    """

    def __init__(self, evaluation: PeriodicEvaluation | None = None) -> None:
        super().__init__()
        self.evaluation = evaluation

    def _describe(self) -> None:
        if self.evaluation is not None and self.evaluation.evaluations:
            last = self.evaluation.evaluations[-1]
            self.pbar.set_description(f"eval {last.mean_reward:.1f} +- {last.std_reward:.1f}", refresh=False)

    def _on_rollout_start(self) -> None:
        self._describe()

    def _on_training_end(self) -> None:
        self._describe()
        super()._on_training_end()


class Dashboards(CallbackList):
    """The callbacks of a run's dashboards, as one callback for ``learn(callback=...)``.

    When ``learn()`` ends having taken all its steps (not stopped by a callback, e.g. on Ctrl-C by
    :class:`~cme_agent.callbacks.StopOnSignal`), the final policy is evaluated, unless the last
    evaluation already was of it; then its children end (pictures of the last iteration, the bar).

    :param evaluation: the periodic evaluation (None: none)
    :param others: the other callbacks (returns by behaviour, pictures, progress bar)
    """

    def __init__(self, evaluation: PeriodicEvaluation | None, others: list[BaseCallback]) -> None:
        super().__init__(([evaluation] if evaluation is not None else []) + others)
        self.evaluation = evaluation

    def _on_training_end(self) -> None:
        completed = self.model.num_timesteps >= self.model._total_timesteps
        last = self.evaluation.evaluations[-1].timesteps if self.evaluation and self.evaluation.evaluations else None
        if completed and self.evaluation is not None and last != self.model.num_timesteps:
            self.evaluation.evaluate()
        super()._on_training_end()


def evaluation_env_factory(
    eval_env: EvalEnv, seed: int, env_id: str | None = None, env_kwargs: Mapping[str, Any] | None = None
) -> tuple[Callable[[], gym.Env | VecEnv], bool]:
    """A function returning the evaluation env, its starts seeded with ``seed`` at every call, so
    that every evaluation flies the same starts and the curve moves with the policy only.

    :param eval_env: an env id (made fresh, Monitor-wrapped, for each evaluation; with the training
        env's make-kwargs ``env_kwargs`` when it is the training env's id ``env_id``), a gym env
        (Monitor-wrapped once, reseeded before each evaluation), a VecEnv (reseeded likewise), or
        a function returning a fresh env (used as it is: it seeds its env itself)
    :param seed: the seed of the evaluation episodes' starts
    :param env_id: the training env's registered id
    :param env_kwargs: the training env's make-kwargs
    :return: the factory, and whether each env it returns is to be closed after its evaluation
    """
    if isinstance(eval_env, str):
        kwargs = dict(env_kwargs or {}) if eval_env == env_id else {}

        def make() -> gym.Env:
            env = Monitor(gym.make(eval_env, **kwargs))
            env.reset(seed=seed)
            return env

        return make, True
    if isinstance(eval_env, VecEnv):
        vec_env = eval_env

        def reseed_vec() -> VecEnv:
            vec_env.seed(seed)  # used by the reset evaluate_policy starts with
            return vec_env

        return reseed_vec, False
    if isinstance(eval_env, gym.Env):
        env = eval_env if is_wrapped(eval_env, Monitor) else Monitor(eval_env)

        def reseed() -> gym.Env:
            env.reset(seed=seed)  # evaluate_policy's reset continues from this seeded generator
            return env

        return reseed, False
    if callable(eval_env):
        return eval_env, True
    raise TypeError(f"eval_env must be an env id, a gym env, a VecEnv or a function returning one, got {eval_env!r}")


def training_dashboards(
    model: BaseAlgorithm,
    eval_env: EvalEnv | None = None,
    eval_every: int = 1000,
    n_eval_episodes: int = 10,
    log_path: str | pathlib.Path | None = None,
    pictures: PictureCallback | bool = True,
    progress_bar: bool = False,
    given: MaybeCallback = None,
) -> Dashboards:
    """The dashboards of ``train.py`` for ``model``, as one callback for ``learn(callback=...)``.

    - with ``eval_env``: :class:`~cme_agent.callbacks.PeriodicEvaluation` every ``eval_every``
      env steps and of the final policy (``eval/mean_reward``, ``eval/std_reward``,
      ``eval/mean_ep_length``), starts seeded with the agent's seed + 10,000;
    - for CMEPolicyIteration: :class:`~cme_agent.callbacks.EpisodeReturnsByBehaviour`
      (``rollout/greedy_ep_rew_mean``, ``rollout/explore_ep_rew_mean``) and the TensorBoard
      pictures (:class:`~cme_agent.pictures.PictureCallback`, drawn only when the logger writes
      TensorBoard), each unless ``given`` holds one already;
    - with ``progress_bar``: a progress bar showing the last evaluation's return.

    None of them draws from the agent's random generators: a run is the same with them as without.

    :param model: the agent
    :param eval_env: the evaluation env (see :func:`evaluation_env_factory`); None: no evaluation
    :param eval_every: env steps between evaluations (0: only of the final policy)
    :param n_eval_episodes: episodes per evaluation
    :param log_path: ``evaluations.npz`` to write every evaluation into (None: none)
    :param pictures: True: the default pictures (every 10 iterations); False: none; or the callback to use
    :param progress_bar: show a progress bar (then pass ``progress_bar=False`` to ``learn()``)
    :param given: the user's callbacks, whose kinds are not added twice
    :raises ValueError: a bad ``eval_every`` or ``n_eval_episodes``
    """
    evaluation = None
    if eval_env is not None:
        seed = (model.seed or 0) + EVAL_SEED_OFFSET
        env_id, env_kwargs = getattr(model, "env_id", None), getattr(model, "env_kwargs", None)
        make_env, close = evaluation_env_factory(eval_env, seed, env_id, env_kwargs)
        evaluation = PeriodicEvaluation(make_env, eval_every, n_eval_episodes, log_path=log_path, close=close)
    present = {type(callback) for callback in _flatten(given)}
    others: list[BaseCallback] = []
    if hasattr(model, "_behaviour"):  # the CME agents' noisy and greedy episodes
        if not any(issubclass(kind, EpisodeReturnsByBehaviour) for kind in present):
            others.append(EpisodeReturnsByBehaviour())
        if pictures and not any(issubclass(kind, PictureCallback) for kind in present):
            others.append(pictures if isinstance(pictures, PictureCallback) else PictureCallback())
    if progress_bar:
        others.append(EvaluationProgressBar(evaluation))
    return Dashboards(evaluation, others)


def with_dashboards(
    model: BaseAlgorithm,
    callback: MaybeCallback,
    eval_env: EvalEnv | None,
    eval_every: int,
    n_eval_episodes: int,
    progress_bar: bool,
) -> tuple[list[BaseCallback], bool]:
    """The callbacks of ``learn()``: the user's and, unless they hold a :class:`Dashboards`
    already (``train.py``'s), the dashboards of :func:`training_dashboards`.

    :param model: the agent
    :param callback: the user's callback(s)
    :param eval_env: the evaluation env of ``learn(eval_env=...)`` (None: no evaluation)
    :param eval_every: env steps between evaluations
    :param n_eval_episodes: episodes per evaluation
    :param progress_bar: whether ``learn()`` was asked for a progress bar
    :return: the callbacks, and whether SB3's own progress bar is still wanted
    :raises ValueError: ``eval_env`` given beside a :class:`Dashboards` that has its own
    """
    items = callback if isinstance(callback, list) else [callback]
    # a function is a callback too (SB3 converts a lone one itself, not one inside a list)
    given = [item if isinstance(item, BaseCallback) else ConvertCallback(item) for item in items if item is not None]
    if any(isinstance(item, Dashboards) for item in _flatten(given)):
        if eval_env is not None:
            raise ValueError("eval_env= and a Dashboards callback both evaluate: give the env to training_dashboards()")
        return given, progress_bar
    dashboards = training_dashboards(model, eval_env, eval_every, n_eval_episodes, progress_bar=progress_bar, given=given)
    return [dashboards, *given], False


def _flatten(callback: MaybeCallback) -> Iterator[BaseCallback]:
    """Every callback in ``callback``, the members of lists and CallbackLists included."""
    if isinstance(callback, list):
        for item in callback:
            yield from _flatten(item)
    elif isinstance(callback, CallbackList):
        yield callback
        for item in callback.callbacks:
            yield from _flatten(item)
    elif isinstance(callback, BaseCallback):
        yield callback
