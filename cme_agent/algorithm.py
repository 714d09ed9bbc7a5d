"""CMEPolicyIteration: policy iteration with an online CME dynamics model (paper Algorithm 1).

Each iteration of :meth:`CMEPolicyIteration.learn` is one pass of Algorithm 1, one call per step
into the step's owner: data acquisition into D; feature selection, eq. (5) (:class:`FeatureSelector`);
the model update, eq. (6) (:class:`ModelTrainer`); then ``evaluation.rounds`` times policy
evaluation, eq. (7) (:class:`PolicyEvaluator`), and improvement (:meth:`CMEPolicy.improve`).
This module holds the set-up, the loop and the logging. Every step touches a fixed-size sample
of D or only the m new transitions, so an iteration's cost grows with q, never with |D|.
"""

from __future__ import annotations

import contextlib
import inspect
import math
import sys
import time
from collections.abc import Iterator
from typing import Any, TypeVar

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback
from stable_baselines3.common.utils import safe_mean

from cme_agent.buffer import Transitions, TransitionStore, vector_step_successors
from cme_agent.config import EvaluationConfig, ExplorationConfig, FeatureSelectionConfig, ImprovementConfig, ModelUpdateConfig
from cme_agent.dashboards import EvalEnv, with_dashboards
from cme_agent.dynamics import CMEDynamics
from cme_agent.dynamics.box import ObservationBox
from cme_agent.dynamics.selection import FeatureSelector
from cme_agent.dynamics.trainer import ModelTrainer
from cme_agent.evaluation import PolicyEvaluator
from cme_agent.exploration import BehaviourPolicy
from cme_agent.persistence import PersistenceMixin, plain
from cme_agent.policy import CMEPolicy
from cme_agent.presets import GROUPS
from cme_agent.rewards import RewardSpec, StepReward
from cme_agent.settings import (
    agent_reward,
    check_policy,
    check_spaces,
    env_identity,
    env_name,
    resolve_settings,
    reward_message,
)
from cme_agent.threads import DEFAULT_THREADS, check_threads, torch_threads

SelfCME = TypeVar("SelfCME", bound="CMEPolicyIteration")


class CMEPolicyIteration(PersistenceMixin, BaseAlgorithm):
    """Policy iteration with an online conditional-mean-embedding model of the dynamics
    (Lever, Stafford & Shawe-Taylor, 2014), with the stable-baselines3 interface.

    :param policy: ``"CMEPolicy"`` or the class
    :param env: the environment (a Gymnasium env, a VecEnv, or an env id)
    :param gamma: discount factor in (0, 1)
    :param omega: step of the Q smoothing Q_k = (1 - omega) Q_{k-1} + omega Q^_k, in (0, 1]
    :param steps_per_iteration: m, env steps collected per iteration (all envs together)
    :param feature_selection: matching pursuit settings (:class:`FeatureSelectionConfig` or dict)
    :param model_update: the model and how it is learned (:class:`ModelUpdateConfig` or dict): the CME, B by eq. (6), or a
        model of s' that acting looks ahead through; by default the latter where s' - s is linear in (s, a)
    :param evaluation: policy evaluation settings (:class:`EvaluationConfig` or dict)
    :param exploration: behaviour policy settings (:class:`ExplorationConfig` or dict)
    :param improvement: the policy improvement step (:class:`ImprovementConfig` or dict): the
        paper's smoothed greedy step (default) or KL-regularised (soft) policy iteration
    :param reward_fn: the reward r(s, a), a :class:`RewardSpec` or a torch callable ``(obs (N, obs_dim), action) -> (N,)``;
        default: the env id's known reward, the env's own ``reward_function``, else a reward learned
        by regression. Not saved with the model: pass it again to ``load()``.
    :param reset_envs_each_iteration: start every iteration's data acquisition with fresh episodes,
        seeded from the agent's RNG: the run is then a deterministic function of the agent's state at
        iteration boundaries, so a run resumed from a checkpoint ends exactly as an uninterrupted one
    :param preset: apply the tuned settings of the env id where the package has some
        (:mod:`cme_agent.presets`) under the arguments given; False: the library defaults for
        every argument not given
    :param policy_kwargs: arguments of :class:`CMEPolicy` (phi, observation, action_search)
    :param stats_window_size: episodes averaged in ``rollout/ep_rew_mean``
    :param tensorboard_log: TensorBoard log folder (None: no TensorBoard)
    :param verbose: 0 silent, 1 info
    :param seed: seed of every random draw of the agent
    :param device: torch device (``"auto"``: CUDA if available)
    :param n_threads: torch's CPU threads while :meth:`learn` runs (the caller's put back after); default
        :data:`~cme_agent.threads.DEFAULT_THREADS` (1, fastest on a shared machine: ``python -m benchmarks.threads``);
        None: torch's own setting, left as it is. Like ``device``, not saved: pass it to ``load()`` again
    :param _init_setup_model: build the model at construction (False when loading)
    """

    policy_aliases = {"CMEPolicy": CMEPolicy}  # noqa: RUF012
    policy: CMEPolicy

    def __init__(
        self,
        policy: str | type[CMEPolicy],
        env: GymEnv | str | None,
        gamma: float | None = None,
        omega: float | None = None,
        steps_per_iteration: int | None = None,
        feature_selection: FeatureSelectionConfig | dict[str, Any] | None = None,
        model_update: ModelUpdateConfig | dict[str, Any] | None = None,
        evaluation: EvaluationConfig | dict[str, Any] | None = None,
        exploration: ExplorationConfig | dict[str, Any] | None = None,
        improvement: ImprovementConfig | dict[str, Any] | None = None,
        reward_fn: RewardSpec | StepReward | None = None,
        reset_envs_each_iteration: bool = False,
        preset: bool = True,
        policy_kwargs: dict[str, Any] | None = None,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: torch.device | str = "auto",
        n_threads: int | None = DEFAULT_THREADS,
        _init_setup_model: bool = True,
    ) -> None:
        self.n_threads = check_threads(n_threads)
        check_policy(policy, self.policy_aliases)  # before SB3's bare "Policy MlpPolicy unknown"
        super().__init__(
            policy,
            env,
            learning_rate=0.0,  # SB3's schedule is not used: the model's step is model_update.learning_rate
            policy_kwargs=policy_kwargs,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            support_multi_env=True,
            seed=seed,
        )
        self.env_id, self.env_kwargs = env_identity(self.env)
        given = {
            "gamma": gamma,
            "omega": omega,
            "steps_per_iteration": steps_per_iteration,
            "feature_selection": feature_selection,
            "model_update": model_update,
            "evaluation": evaluation,
            "exploration": exploration,
            "improvement": improvement,
            "policy_kwargs": policy_kwargs,
        }
        # a loaded agent's saved settings are complete: its preset was applied when it was built
        settings = resolve_settings(
            self.env_id if preset and _init_setup_model else None,
            given,
            self.policy_class,
            set(inspect.signature(CMEPolicyIteration.__init__).parameters) - {"self", "policy", "env"},
            self.env_kwargs,
        )
        self.gamma, self.omega = settings.agent.gamma, settings.agent.omega
        self.steps_per_iteration = settings.agent.steps_per_iteration
        self.feature_selection_config = settings.feature_selection
        self.model_update_config = settings.model_update
        self.evaluation_config = settings.evaluation
        self.exploration_config = settings.exploration
        self.improvement_config = settings.improvement
        self.policy_kwargs = settings.policy_kwargs
        self.preset_message = settings.preset_message
        self.learning_rate = self.model_update_config.learning_rate
        self.reward_fn = reward_fn
        self.reset_envs_each_iteration = reset_envs_each_iteration
        self.stats_window_size = stats_window_size
        self._behaviour: BehaviourPolicy | None = None
        self.iteration = 0
        if self.env is not None:
            check_spaces(self.observation_space, self.action_space)
        if _init_setup_model:
            self._setup_model()

    # ------------------------------------------------------------------ set-up
    def _setup_model(self) -> None:
        """Build the policy (the model is its submodule ``dynamics``), the stores, the step owners, the RNGs."""
        if self.seed is None:
            self.seed = int(np.random.SeedSequence().generate_state(1)[0])
        self.set_random_seed(self.seed)
        self._torch_rng = torch.Generator().manual_seed(self.seed)
        self._np_rng = np.random.default_rng(self.seed)
        self.policy_kwargs = {"candidate_seed": self.seed, **self.policy_kwargs}
        # a loaded model keeps the reward source it was trained with
        reward, self.reward_source = agent_reward(
            self.reward_fn, getattr(self, "reward_source", None), self.env, self.env_id, self.env_kwargs
        )
        self.policy = self.policy_class(
            self.observation_space,
            self.action_space,
            feature_dynamics=self.model_update_config.feature_dynamics,
            action_scale=self.feature_selection_config.action_scale,
            reward=reward,
            evaluation=self.evaluation_config,
            improvement=self.improvement_config,
            model_kind=self.model_update_config.kind,
            gamma=self.gamma,
            change_fourier=self.model_update_config.change_fourier,
            **self.policy_kwargs,
        ).to(self.device)
        action_shape = () if isinstance(self.action_space, spaces.Discrete) else self.action_space.shape
        obs_dim = self.observation_space.shape[0]
        self.store = TransitionStore(obs_dim, action_shape, self.device)
        self.holdout = TransitionStore(obs_dim, action_shape, self.device)
        self.selector, self.trainer = self._make_model_learners()
        self.box = ObservationBox()
        self.evaluator = PolicyEvaluator(self.evaluation_config, self.gamma)
        self._phase_seconds: dict[str, float] = {}

    def _make_model_learners(self) -> tuple[FeatureSelector, ModelTrainer]:
        """The owners of feature selection and of the model update."""
        return FeatureSelector(self.feature_selection_config), ModelTrainer(self.model_update_config)

    @property
    def dynamics(self) -> CMEDynamics:
        """The CME model of the dynamics and the reward (the policy's submodule)."""
        return self.policy.dynamics

    @property
    def q(self) -> int:
        """q, the number of selected kernel features of psi."""
        return self.policy.dynamics.q

    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        """Continue on ``env`` (its spaces must match). Unlike SB3's agents any number of envs
        is accepted: the behaviour policy is rebuilt for it at the next ``learn()``.

        :param env: a Gymnasium env or a VecEnv
        :param force_reset: start fresh episodes at the next ``learn()``
        """
        vec_env = self._wrap_env(env, self.verbose)
        self.n_envs = vec_env.num_envs
        super().set_env(vec_env, force_reset)

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        return ["policy"], []

    # ------------------------------------------------------------------ Algorithm 1
    def learn(
        self: SelfCME,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 1,
        tb_log_name: str = "CME",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
        eval_env: EvalEnv | None = None,
        eval_every: int = 1000,
        n_eval_episodes: int = 10,
    ) -> SelfCME:
        """Run Algorithm 1 until ``total_timesteps`` env steps have been taken, torch at ``n_threads`` CPU threads.

        The dashboards of ``train.py`` come along (:func:`~cme_agent.dashboards.training_dashboards`): the returns
        of the greedy and the noisy training episodes apart (``rollout/greedy_ep_rew_mean``, ``rollout/explore_ep_rew_mean``),
        the pictures whenever the logger writes TensorBoard (``tensorboard_log=``), and with ``eval_env`` the deterministic
        policy's ``eval/mean_reward`` every ``eval_every`` env steps and at the end; a callback of either kind replaces it.

        :param total_timesteps: env steps to take (all envs together)
        :param callback: called once per env step (``on_step``); training stops when it returns False
        :param log_interval: iterations between log dumps (SB3's table on stdout at ``verbose=1``, TensorBoard)
        :param tb_log_name: name of the TensorBoard run
        :param reset_num_timesteps: start counting from 0 (else continue the count)
        :param progress_bar: show a progress bar (tqdm + rich) with the ETA and, with
            ``eval_env``, the last evaluation's return
        :param eval_env: the env to evaluate the deterministic policy on: an env id (the
            training env's make-kwargs when it is its id), an env, a VecEnv or a function
            returning a fresh env; its starts are seeded with the agent's seed + 10,000, the
            same for every evaluation. None: no evaluation
        :param eval_every: env steps between evaluations, at the first iteration boundary at or
            after each multiple (0: only of the final policy)
        :param n_eval_episodes: episodes per evaluation
        :return: the trained agent
        """
        if self.env is None:
            raise ValueError(
                "this agent has no env to learn on (it was loaded without one): pass it to "
                "CMEPolicyIteration.load(path, env=...) or call set_env(env) before learn()"
            )
        callback, progress_bar = with_dashboards(self, callback, eval_env, eval_every, n_eval_episodes, progress_bar)
        with torch_threads(self.n_threads):
            total_timesteps, callback = self._setup_learn(
                total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar
            )
            callback.on_training_start(locals(), globals())
            self._announce_settings()
            if self._behaviour is None or len(self._behaviour.explore) != self.n_envs:
                self._behaviour = self._make_behaviour()
            while self.num_timesteps < total_timesteps:
                steps = min(self.steps_per_iteration, total_timesteps - self.num_timesteps)
                self._phase_seconds = {}
                new_data = self.data_acquisition(callback, math.ceil(steps / self.n_envs))
                if new_data is None:
                    break
                self.train_iteration(new_data)
                if log_interval > 0 and self.iteration % log_interval == 0:
                    self.dump_logs()
            callback.on_training_end()
        return self

    @torch.no_grad()
    def train_iteration(self, new_data: Transitions) -> None:
        """Everything of one iteration after data acquisition (Algorithm 1, lines 2-5): the observation box, the
        model's kind (once), feature selection, the model update, then ``evaluation.rounds`` times evaluation and
        improvement on a fresh collection C.

        :param new_data: the transitions this iteration collected (already in the store D)
        """
        self.iteration += 1
        self.observation_box(new_data)
        self.model_choice()
        self.feature_selection(new_data)
        self.model_update()
        for _ in range(self.evaluation_config.rounds):
            collection = self.draw_collection()
            value_weights = self.policy_evaluation(collection)
            self.policy_improvement(value_weights, collection)

    def data_acquisition(self, callback: BaseCallback, n_steps: int) -> Transitions | None:
        """Data acquisition: ``n_steps`` steps of every env with the behaviour policy; the
        transitions are aggregated into D (a fraction is held out to measure the model).

        :param callback: ``on_step`` is called once per env step
        :param n_steps: steps per env
        :return: the new training transitions, or None if the callback stopped training
        """
        start = len(self.store)
        callback.on_rollout_start()  # an iteration boundary: checkpoints are taken here
        if self.reset_envs_each_iteration:
            self._reset_envs()
        with self._timed("data_acquisition"):
            for _ in range(n_steps):
                random_phase = self.num_timesteps < self.exploration_config.random_steps or self.dynamics.obs_encoder.needs_fit
                actions = self._behaviour(lambda: self.policy.predict(self._last_obs, deterministic=True)[0], random_phase)
                new_obs, rewards, dones, infos = self.env.step(actions)
                self.num_timesteps += self.env.num_envs
                next_obs, terminated = vector_step_successors(new_obs, rewards, dones, infos, self.num_timesteps)
                held_out = self._np_rng.random(len(dones)) < self.model_update_config.holdout_fraction
                for store, mask in ((self.store, ~held_out), (self.holdout, held_out)):
                    if mask.any():
                        store.add(self._last_obs[mask], actions[mask], rewards[mask], next_obs[mask], terminated[mask])
                callback.update_locals(locals())
                if not callback.on_step():
                    return None
                self._update_info_buffer(infos, dones)
                self._last_obs = new_obs
                self._behaviour.end_episodes(dones)
        callback.on_rollout_end()
        return self.store.get(slice(start, len(self.store)))

    def observation_box(self, new_data: Transitions) -> None:
        """:meth:`ObservationBox.update`; after an expansion planning restarts (Q and w belonged to the old phi)."""
        if self.box.update(self.dynamics, new_data, self.store, self.holdout, self.trainer, self._torch_rng, self.logger):
            self.policy.restart()
            self.evaluator.restart()

    def model_choice(self) -> None:
        """``model_update.kind="auto"``, once: the model the first data points to (:meth:`ModelTrainer.choose_kind`)."""
        if self.policy.model_kind == "auto":
            self.model_update_config = self.trainer.choose_kind(self.policy, self.store, self.holdout, self.logger)

    def feature_selection(self, new_data: Transitions) -> int:
        """Feature selection, eq. (5), at the new data (:meth:`FeatureSelector.select`): features added (none without psi)."""
        with self._timed("feature_selection"):
            if self.policy.lookahead is not None:
                return 0
            return self.selector.select(self.dynamics, new_data, self.store, self._torch_rng, self.logger)

    def model_update(self) -> None:
        """The model update (:class:`ModelTrainer`): B by eq. (6), or the model of the observation refit."""
        args = (self.store, self.holdout, self._torch_rng, self.logger)
        with self._timed("model_update"):
            if self.policy.lookahead is not None:
                return self.trainer.fit_observation_model(self.policy.lookahead, *args)
            self.trainer.update(self.dynamics, *args, self.iteration)

    def draw_collection(self) -> torch.Tensor:
        """The collection C of eq. (7) (:meth:`PolicyEvaluator.draw_collection`): (|C|, obs_dim) states."""
        with self._timed("policy_evaluation"):
            return self.evaluator.draw_collection(self.dynamics, self.store, self._torch_rng)

    def policy_evaluation(self, states: torch.Tensor) -> torch.Tensor:
        """Policy evaluation, eq. (7), on C (|C|, obs_dim) (:meth:`PolicyEvaluator.evaluate`): (p,) value weights w."""
        with self._timed("policy_evaluation"):
            return self.evaluator.evaluate(self.policy, states, self.logger, self._torch_rng)

    def policy_improvement(self, value_weights: torch.Tensor, states: torch.Tensor | None = None) -> None:
        """Policy improvement (:meth:`CMEPolicy.improve`), on the linear weights of Q (zero-padded,
        no history): Q_k = (1 - omega) Q_{k-1} + omega Q^_k and pi_{k+1} = greedy(Q_k), or with
        ``improvement.method="soft"`` the average Qbar_k of the Q^_j and pi_{k+1} = softmax(beta_k Qbar_k).

        :param value_weights: (p,) w_k from :meth:`policy_evaluation`
        :param states: (|C|, obs_dim) the collection C, where the soft improvement measures the
            spread of Q for beta_k (None: a fresh collection is drawn when needed)
        """
        with self._timed("policy_improvement"):
            if states is None and self.policy.soft:
                states = self.draw_collection()
            self.policy.improve(value_weights, self.gamma, self.omega, states)

    # ------------------------------------------------------------------ helpers
    def _make_behaviour(self) -> BehaviourPolicy:
        return BehaviourPolicy(self.action_space, self.exploration_config, self._np_rng, self.n_envs)

    def _reset_envs(self) -> None:
        """Fresh episodes in every env, seeded from the agent's RNG (``reset_envs_each_iteration``)."""
        self.env.seed(int(self._np_rng.integers(2**31 - 1)))
        self._last_obs = self.env.reset()
        self._behaviour.end_episodes(np.ones(self.n_envs, dtype=bool))

    def _constructor_kwargs(self) -> dict[str, Any]:
        """The constructor arguments as plain data (for :meth:`save`)."""
        names = ("gamma", "omega", "steps_per_iteration", "reset_envs_each_iteration", "stats_window_size", "tensorboard_log")
        groups = {group: plain(getattr(self, f"{group}_config")) for group in GROUPS}
        plain_names = {name: getattr(self, name) for name in (*names, "verbose", "seed")}
        return {**plain_names, **groups, "policy_kwargs": plain(self.policy_kwargs)}

    @contextlib.contextmanager
    def _timed(self, phase: str) -> Iterator[None]:
        """Add the wall-clock seconds of the block to ``time/<phase>`` of this iteration."""
        start = time.perf_counter()
        yield
        self._phase_seconds[phase] = self._phase_seconds.get(phase, 0.0) + time.perf_counter() - start

    # ------------------------------------------------------------------ logging
    def _announce_settings(self) -> None:
        """Say which preset was applied and which reward the agent plans with."""
        if self.preset_message is not None and self.verbose >= 1:
            self.logger.info(self.preset_message)
        if self.reward_source == "learned" or self.verbose >= 1:  # a learned reward is always said
            self.logger.info(reward_message(self.reward_source, env_name(self.env, self.env_id)))

    def dump_logs(self) -> None:
        """Write SB3's rollout/time keys, our train/ keys and the seconds of each phase."""
        time_elapsed = max((time.time_ns() - self.start_time) / 1e9, sys.float_info.epsilon)
        fps = int((self.num_timesteps - self._num_timesteps_at_start) / time_elapsed)
        self.logger.record("time/iterations", self.iteration, exclude="tensorboard")
        if self.ep_info_buffer:
            self.logger.record("rollout/ep_rew_mean", safe_mean([info["r"] for info in self.ep_info_buffer]))
            self.logger.record("rollout/ep_len_mean", safe_mean([info["l"] for info in self.ep_info_buffer]))
        self.logger.record("time/fps", fps)
        self.logger.record("time/time_elapsed", int(time_elapsed), exclude="tensorboard")
        self.logger.record("time/total_timesteps", self.num_timesteps, exclude="tensorboard")
        for phase, seconds in self._phase_seconds.items():
            self.logger.record(f"time/{phase}", seconds)
        self.logger.record("train/transitions", len(self.store) + len(self.holdout))
        self.logger.dump(step=self.num_timesteps)
