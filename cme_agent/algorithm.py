"""CMEPolicyIteration: policy iteration with an online CME dynamics model (paper Algorithm 1).

Each iteration of :meth:`CMEPolicyIteration.learn` is one pass of Algorithm 1:

1. :meth:`~CMEPolicyIteration.data_acquisition` -- m env steps of the greedy policy mixed
   with a noisy version of it, aggregated into the store D;

then :meth:`~CMEPolicyIteration.train_iteration` on the new data:

2. :meth:`~CMEPolicyIteration.feature_selection` -- matching pursuit, eq. (5);
3. :meth:`~CMEPolicyIteration.model_update` -- the regularised loss of eq. (6) minimised exactly
   on a fixed-size sample of D (the default), or the paper's SGD steps on it;
4. ``evaluation.rounds`` times on a fresh collection C of states:
   :meth:`~CMEPolicyIteration.policy_evaluation` (eq. (7)) and
   :meth:`~CMEPolicyIteration.policy_improvement` (Q smoothing).

Every step touches a fixed-size sample of D or only the m new transitions, so the cost of an
iteration grows with q (the number of features), never with |D|. The model (encoders, phi,
psi, B and the expected reward) is one module, :class:`~cme_agent.dynamics.CMEDynamics`, the
policy's submodule ``dynamics``; the policy holds the Q weights and the action search.
"""

from __future__ import annotations

import contextlib
import functools
import inspect
import math
import re
import sys
import time
import warnings
from collections.abc import Iterator
from typing import Any, TypeVar

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback
from stable_baselines3.common.utils import safe_mean
from stable_baselines3.common.vec_env import VecEnv

from cme_agent.buffer import Transitions, TransitionStore
from cme_agent.config import (
    AgentConfig,
    EvaluationConfig,
    ExplorationConfig,
    FeatureSelectionConfig,
    ImprovementConfig,
    ModelUpdateConfig,
    build_config,
    collection_size_for,
)
from cme_agent.dynamics import CMEDynamics, matching_pursuit
from cme_agent.exploration import BehaviourPolicy
from cme_agent.persistence import PersistenceMixin, plain
from cme_agent.planning import (
    FactoredResidual,
    bellman_residual_descent,
    bellman_residual_rms,
    bellman_residual_weights,
    factored_dual_weights,
    factored_is_cheaper,
    lstd_weights,
)
from cme_agent.policy import CMEPolicy, GreedyStep, SoftStep
from cme_agent.presets import GROUPS, TOP_LEVEL_KEYS, apply_preset
from cme_agent.rewards import RewardSpec, StepReward, resolve_reward
from cme_agent.state_features import RBFGrid

SelfCME = TypeVar("SelfCME", bound="CMEPolicyIteration")


def _check_spaces(observation_space: spaces.Space, action_space: spaces.Space) -> None:
    """Refuse, naming the space, what the agent cannot handle."""
    if not (isinstance(observation_space, spaces.Box) and len(observation_space.shape) == 1):
        raise ValueError(f"CMEPolicyIteration needs a 1-D Box observation space, got {observation_space}")
    if not (
        isinstance(action_space, spaces.Discrete) or (isinstance(action_space, spaces.Box) and len(action_space.shape) == 1)
    ):
        raise ValueError(f"CMEPolicyIteration needs a Discrete or 1-D Box action space, got {action_space}")


SET_BY_THE_AGENT = {
    "feature_dynamics": "model_update={'feature_dynamics': ...}",
    "state_reward": "model_update={'state_reward': ...}",
    "off_data_reward": "model_update={'off_data_reward': ...}",
    "action_scale": "feature_selection={'action_scale': ...}",
    "reward": "reward_fn=...",
    "evaluation": "evaluation=...",
    "improvement": "improvement=...",
}
"""Arguments of :class:`CMEPolicy` that the agent passes itself, and where a user sets them."""


def _check_policy_kwargs(policy_class: type, policy_kwargs: dict[str, Any]) -> None:
    """Refuse, by name, a ``policy_kwargs`` key the policy does not take, saying where it
    belongs when it is a setting of the agent (``feature_selection``, ``gamma``, ...)."""
    parameters = inspect.signature(policy_class.__init__).parameters
    if any(parameter.kind is inspect.Parameter.VAR_KEYWORD for parameter in parameters.values()):
        return
    accepted = set(parameters) - {"self", "observation_space", "action_space", "lr_schedule"} - set(SET_BY_THE_AGENT)
    agent_arguments = set(inspect.signature(CMEPolicyIteration.__init__).parameters) - {"self", "policy", "env"}
    for key in policy_kwargs:
        if key in accepted:
            continue
        if key in SET_BY_THE_AGENT or key in agent_arguments:
            where = SET_BY_THE_AGENT.get(key, f"{key}=...")
            raise ValueError(
                f"policy_kwargs['{key}'] is a setting of the agent, not of {policy_class.__name__}: "
                f"pass {where} to CMEPolicyIteration(...) (in a Hydra config, under agent:)"
            )
        raise ValueError(
            f"policy_kwargs['{key}'] is not a setting of {policy_class.__name__}: it takes {', '.join(sorted(accepted))}"
        )


class CMEPolicyIteration(PersistenceMixin, BaseAlgorithm):
    """Policy iteration with an online conditional-mean-embedding model of the dynamics
    (Lever, Stafford & Shawe-Taylor, 2014), with the stable-baselines3 interface.

    :param policy: ``"CMEPolicy"`` or the class
    :param env: the environment (a Gymnasium env, a VecEnv, or an env id)
    :param gamma: discount factor in (0, 1)
    :param omega: step of the Q smoothing Q_k = (1 - omega) Q_{k-1} + omega Q^_k, in (0, 1]
    :param steps_per_iteration: m, env steps collected per iteration (all envs together)
    :param feature_selection: matching pursuit settings (:class:`FeatureSelectionConfig` or dict)
    :param model_update: how B is learned: an exact ridge refit (default) or SGD, eq. (6) (:class:`ModelUpdateConfig` or dict)
    :param evaluation: policy evaluation settings (:class:`EvaluationConfig` or dict)
    :param exploration: behaviour policy settings (:class:`ExplorationConfig` or dict)
    :param improvement: the policy improvement step (:class:`ImprovementConfig` or dict): the
        paper's smoothed greedy step (default) or KL-regularised (soft) policy iteration
    :param reward_fn: the reward r(s, a) as a :class:`RewardSpec` or a torch callable
        ``(obs (N, obs_dim), action) -> (N,)``; default: the known reward of the env id, the
        env's own ``reward_function``, or else a reward learned by regression on psi. Not saved
        with the model: pass it again to ``load()``.
    :param reset_envs_each_iteration: start every iteration's data acquisition with fresh
        episodes, the envs reset with seeds drawn from the agent's RNG: the run is then a
        deterministic function of the agent's state at iteration boundaries, so a run resumed
        from a checkpoint ends exactly as an uninterrupted one
    :param policy_kwargs: arguments of :class:`CMEPolicy` (phi, observation, action_search)
    :param stats_window_size: episodes averaged in ``rollout/ep_rew_mean``
    :param tensorboard_log: TensorBoard log folder (None: no TensorBoard)
    :param verbose: 0 silent, 1 info
    :param seed: seed of every random draw of the agent
    :param device: torch device (``"auto"``: CUDA if available)
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
        policy_kwargs: dict[str, Any] | None = None,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: torch.device | str = "auto",
        _init_setup_model: bool = True,
    ) -> None:
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
        self.env_id, self.env_kwargs = self._env_identity(self.env)
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
        settings, self.preset_message = apply_preset(self.env_id if _init_setup_model else None, given)
        agent = build_config(AgentConfig, {key: settings[key] for key in TOP_LEVEL_KEYS if key in settings}, "agent")
        self.gamma, self.omega, self.steps_per_iteration = agent.gamma, agent.omega, agent.steps_per_iteration
        groups = {group: build_config(cls, settings.get(group), group) for group, cls in GROUPS.items()}
        self.feature_selection_config: FeatureSelectionConfig = groups["feature_selection"]
        self.model_update_config: ModelUpdateConfig = groups["model_update"]
        self.evaluation_config: EvaluationConfig = groups["evaluation"]
        self.exploration_config: ExplorationConfig = groups["exploration"]
        self.improvement_config: ImprovementConfig = groups["improvement"]
        self.policy_kwargs = settings.get("policy_kwargs", {})
        _check_policy_kwargs(self.policy_class, self.policy_kwargs)
        self.learning_rate = self.model_update_config.learning_rate
        self.reward_fn = reward_fn
        self.reset_envs_each_iteration = reset_envs_each_iteration
        self.stats_window_size = stats_window_size
        self._behaviour: BehaviourPolicy | None = None
        self._value_weights: torch.Tensor | None = None
        # (2N, obs_dim) new observations of each successive iteration that outgrew the box so far
        self._outside_states: list[torch.Tensor] = []
        self.iteration = 0
        self.model_step_scale = 1.0
        if self.env is not None:
            _check_spaces(self.observation_space, self.action_space)
        if _init_setup_model:
            self._setup_model()

    @staticmethod
    def _env_identity(env: VecEnv | None) -> tuple[str | None, dict[str, Any]]:
        """The registered id and make-kwargs of the env, to find its reward again after load()."""
        spec = env.get_attr("spec", [0])[0] if env is not None else None
        return (spec.id, dict(spec.kwargs)) if spec is not None else (None, {})

    # ------------------------------------------------------------------ set-up
    def _setup_model(self) -> None:
        """Build the policy (with the model as its submodule ``dynamics``), the stores and the RNGs."""
        if self.seed is None:
            self.seed = int(np.random.SeedSequence().generate_state(1)[0])
        seed = self.seed
        self.set_random_seed(seed)
        self._torch_rng = torch.Generator().manual_seed(seed)
        self._np_rng = np.random.default_rng(seed)
        kwargs = dict(self.policy_kwargs)
        kwargs.setdefault("candidate_seed", seed)
        self.policy_kwargs = kwargs
        reward, self.reward_source = self._resolve_reward()
        self.policy = self.policy_class(
            self.observation_space,
            self.action_space,
            feature_dynamics=self.model_update_config.feature_dynamics,
            state_reward=self.model_update_config.state_reward,
            off_data_reward=self.model_update_config.off_data_reward,
            action_scale=self.feature_selection_config.action_scale,
            reward=reward,
            evaluation=self.evaluation_config,
            improvement=self.improvement_config,
            **kwargs,
        ).to(self.device)
        action_shape = () if isinstance(self.action_space, spaces.Discrete) else self.action_space.shape
        obs_dim = self.observation_space.shape[0]
        self.store = TransitionStore(obs_dim, action_shape, self.device)
        self.holdout = TransitionStore(obs_dim, action_shape, self.device)
        self._phase_seconds: dict[str, float] = {}

    @property
    def dynamics(self) -> CMEDynamics:
        """The CME model of the dynamics and the reward (the policy's submodule)."""
        return self.policy.dynamics

    @property
    def q(self) -> int:
        """q, the number of selected kernel features of psi."""
        return self.policy.dynamics.q

    def _resolve_reward(self) -> tuple[RewardSpec | None, str]:
        """The reward to plan with and its source; a loaded model keeps the source it was trained with."""
        saved_source = getattr(self, "reward_source", None)
        if saved_source == "user" and self.reward_fn is None:
            raise ValueError("this model was trained with a user-supplied reward: pass reward_fn= to load()")
        if saved_source == "learned" or (self.reward_fn is None and not self.model_update_config.known_reward):
            return None, "learned"
        return resolve_reward(self.reward_fn, self.env_id, self._local_env(remake=saved_source == "env"))

    def _local_env(self, remake: bool) -> gym.Env | None:
        """An instance of the env in this process, to read its ``reward_function``: the first env
        of any VecEnv (a SubprocVecEnv sends a copy), or one made from the env id.

        :param remake: without a VecEnv, make the env from its id (a loaded model whose reward was the env's)
        """
        if self.env is not None:
            try:
                return self.env.get_attr("unwrapped", [0])[0]
            except Exception:  # an env that cannot travel between processes: make one here if it has an id
                pass
        if self.env_id is not None and (remake or self.env is not None):
            return gym.make(self.env_id, **self.env_kwargs)
        return None

    def _env_name(self) -> str:
        """The env's id, else its class name, for messages."""
        if self.env_id is not None or self.env is None:
            return repr(self.env_id)
        return re.findall(r"<(\w+)", self.env.env_method("__str__", indices=[0])[0])[-1]

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
    ) -> SelfCME:
        """Run Algorithm 1 until ``total_timesteps`` env steps have been taken.

        :param total_timesteps: env steps to take (all envs together)
        :param callback: called once per env step (``on_step``); training stops when it returns False
        :param log_interval: iterations between log dumps
        :param tb_log_name: name of the TensorBoard run
        :param reset_num_timesteps: start counting from 0 (else continue the count)
        :param progress_bar: show a progress bar (tqdm + rich)
        :return: the trained agent
        """
        if self.env is None:
            raise ValueError(
                "this agent has no env to learn on (it was loaded without one): pass it to "
                "CMEPolicyIteration.load(path, env=...) or call set_env(env) before learn()"
            )
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
        """Everything of one iteration after data acquisition (Algorithm 1, lines 2-5): feature
        selection, the model update, then ``evaluation.rounds`` times evaluation and improvement
        on a fresh collection C.

        :param new_data: the transitions this iteration collected (already in the store D)
        """
        self.iteration += 1
        self._fit_observation_box(new_data)
        self.state_reward_regression()
        self.feature_selection(new_data)
        self.model_update()
        for _ in range(self.evaluation_config.rounds):
            collection = self.draw_collection()
            value_weights = self.policy_evaluation(collection)
            self.policy_improvement(value_weights, collection)

    def _fit_observation_box(self, new_data: Transitions) -> None:
        """Observation dims without usable bounds get their box from the data so far (the random
        phase). Later, when more than ``observation.expand_outside`` of an iteration's new
        observations fall outside it in ``observation.expand_after`` successive iterations, the
        box is expanded to cover those iterations' new observations (at most
        ``observation.max_expansions`` times): psi's centres keep their place, B is refit on
        a sample of D (:meth:`refit_sample`; after the state reward, with ``state_reward``, on all of D) and planning
        restarts (Q's weights belonged to the old phi). The new observations, not all of D, set
        the expansion: the quantiles of D would leave out a drift that is a small share of D (a
        cart pushed off centre for the first time), and the policy would meet the box's edge
        again at once.

        :param new_data: the transitions of this iteration
        """
        encoder = self.dynamics.obs_encoder
        if encoder.needs_fit:
            self.logger.info(encoder.fit(self._observed_states()))
            return
        config = encoder.config
        if not encoder.fit_dims or int(encoder.expansions) >= config.max_expansions or len(new_data) == 0:
            return
        new_states = torch.cat([new_data.obs, new_data.next_obs])
        if encoder.outside_share(new_states) <= config.expand_outside:
            self._outside_states = []
            return
        self._outside_states.append(new_states)
        if len(self._outside_states) < config.expand_after:
            return
        new_states, self._outside_states = torch.cat(self._outside_states), []
        config = self.model_update_config
        data = self.store.get(slice(0, len(self.store))) if self.dynamics.fits_state_reward else None
        sample = self.refit_sample()
        self.logger.info(self.dynamics.expand_observation_box(new_states, sample, config.l2, data, config.state_reward_l2))
        self.policy.restart()
        self._value_weights = None
        self.logger.record("train/observation_box_expansions", int(encoder.expansions))

    def state_reward_regression(self) -> None:
        """With a learned reward, its state part ``<c, phi(s)>``: ridge regression on all of D,
        its normal equations updated with the transitions not yet in them (all of D after the
        box changed); the learned row of B then fits the rest (``model_update.state_reward``)."""
        dynamics = self.dynamics
        if not dynamics.fits_state_reward:
            return
        with self._timed("state_reward"):
            start = 0 if dynamics.state_reward_restarts() else int(dynamics.state_reward_rows)
            dynamics.update_state_reward(
                self.store.get(slice(start, len(self.store))), self.model_update_config.state_reward_l2
            )

    def _observed_states(self) -> torch.Tensor:
        """(2 |D|, obs_dim): every state and successor of D and of the held-out transitions."""
        data = [store.get(slice(0, len(store))) for store in (self.store, self.holdout) if len(store) > 0]
        return torch.cat([tensor for batch in data for tensor in (batch.obs, batch.next_obs)])

    def _make_behaviour(self) -> BehaviourPolicy:
        return BehaviourPolicy(self.action_space, self.exploration_config, self._np_rng, self.n_envs)

    def _reset_envs(self) -> None:
        """Fresh episodes in every env, seeded from the agent's RNG (``reset_envs_each_iteration``)."""
        self.env.seed(int(self._np_rng.integers(2**31 - 1)))
        self._last_obs = self.env.reset()
        self._behaviour.end_episodes(np.ones(self.n_envs, dtype=bool))

    def _constructor_kwargs(self) -> dict[str, Any]:
        """The constructor arguments as plain data (for :meth:`save`)."""
        return {
            "gamma": self.gamma,
            "omega": self.omega,
            "steps_per_iteration": self.steps_per_iteration,
            "feature_selection": plain(self.feature_selection_config),
            "model_update": plain(self.model_update_config),
            "evaluation": plain(self.evaluation_config),
            "exploration": plain(self.exploration_config),
            "improvement": plain(self.improvement_config),
            "reset_envs_each_iteration": self.reset_envs_each_iteration,
            "policy_kwargs": plain(self.policy_kwargs),
            "stats_window_size": self.stats_window_size,
            "tensorboard_log": self.tensorboard_log,
            "verbose": self.verbose,
            "seed": self.seed,
        }

    @contextlib.contextmanager
    def _timed(self, phase: str) -> Iterator[None]:
        """Add the wall-clock seconds of the block to ``time/<phase>`` of this iteration."""
        start = time.perf_counter()
        yield
        self._phase_seconds[phase] = self._phase_seconds.get(phase, 0.0) + time.perf_counter() - start

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
                self._store(self._last_obs, actions, rewards, new_obs, dones, infos)
                callback.update_locals(locals())
                if not callback.on_step():
                    return None
                self._update_info_buffer(infos, dones)
                self._last_obs = new_obs
                self._behaviour.end_episodes(dones)
        callback.on_rollout_end()
        return self.store.get(slice(start, len(self.store)))

    def _store(
        self,
        obs: np.ndarray,
        actions: np.ndarray,
        rewards: np.ndarray,
        new_obs: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """Append one vector step to D (or the held-out store); the successor of a finished
        episode is its true last observation, and a time-limit truncation is not a termination."""
        next_obs = np.array(new_obs, dtype=np.float32, copy=True)
        terminated = np.zeros(len(dones), dtype=bool)
        for i, done in enumerate(dones):
            if done:
                next_obs[i] = infos[i]["terminal_observation"]
                terminated[i] = not infos[i].get("TimeLimit.truncated", False)
        for name, values in (("observation", next_obs), ("reward", rewards)):
            bad = ~np.isfinite(np.asarray(values, dtype=np.float64).reshape(len(dones), -1)).all(axis=1)
            if bad.any():
                env_index = int(np.flatnonzero(bad)[0])
                raise ValueError(
                    f"the env returned a non-finite {name} at step {self.num_timesteps} (env {env_index}): "
                    f"{np.asarray(values)[env_index].tolist()}; learning stopped before it reached the model"
                )
        held_out = self._np_rng.random(len(dones)) < self.model_update_config.holdout_fraction
        for store, mask in ((self.store, ~held_out), (self.holdout, held_out)):
            if mask.any():
                store.add(obs[mask], actions[mask], rewards[mask], next_obs[mask], terminated[mask])

    def feature_selection(self, new_data: Transitions) -> int:
        """Feature selection, eq. (5): matching pursuit on the model residual over a random
        subsample of D (plus the new points), with a dictionary of Gaussian kernels centred at
        the m new state-actions at every bandwidth; picked atoms join psi, their weights times
        theta_k join B.

        :param new_data: the transitions collected in this iteration (the dictionary's centres)
        :return: the number of features added
        """
        config, dynamics = self.feature_selection_config, self.dynamics
        with self._timed("feature_selection"):
            budget = config.max_features
            if config.max_total_features is not None:
                budget = min(budget, config.max_total_features - dynamics.q)
            if len(new_data) == 0 or budget <= 0:
                return self._record_features_added(0)
            batch = new_data.concat(self.store.sample(config.subsample_size, self._torch_rng))
            if (message := dynamics.calibrate_reward_row(batch.rewards, batch.terminated)) is not None:
                self.logger.info(message)
            z = dynamics.encode(batch.obs, batch.actions)
            residual = dynamics.targets(batch) - dynamics.predict(dynamics.psi(z))
            centres = z[: len(new_data)]
            bandwidths = torch.tensor(config.bandwidths, dtype=z.dtype, device=z.device)
            atoms, columns = dynamics.dictionary(z, centres, bandwidths, config.control_affine)
            result = matching_pursuit(atoms, residual, config.threshold, budget, config.orthogonal)
            picked = columns[result.indices]
            dynamics.grow(picked.centres, picked.bandwidths, config.theta * result.weights.T, picked.action_basis)
            if result.energy_before > 0:
                self.logger.record("train/mp_residual_reduction", 1 - result.energy_after / result.energy_before)
            return self._record_features_added(len(result.indices))

    def _record_features_added(self, added: int) -> int:
        self.logger.record("train/features_added", added)
        self.logger.record("train/n_features", self.q)
        return added

    def _sample_minibatches(self, n_batches: int, batch_size: int) -> Transitions:
        """``n_batches`` minibatches of D, concatenated (drawn one after another, as SGD uses them)."""
        indices = [torch.randint(len(self.store), (batch_size,), generator=self._torch_rng) for _ in range(n_batches)]
        return self.store.get(torch.cat(indices).to(self.device))

    def model_update(self) -> None:
        """Update the CME model B: with ``model_update.method="ridge"`` (the default) the exact
        minimiser of eq. (6)'s regularised loss on a fixed-size sample of D (:meth:`refit_sample`),
        whatever B was before; with ``"sgd"`` the paper's update, ``n_steps`` SGD steps of eq. (6)
        on minibatches drawn from D.

        A diverging SGD update (non-finite B, or the loss on a check batch up tenfold) is undone,
        the step size halved for the rest of the run, and a warning issued.
        """
        config, dynamics = self.model_update_config, self.dynamics
        with self._timed("model_update"):
            if dynamics.q == 0:
                return
            if config.method == "ridge":
                self.logger.record("train/model_loss_train", dynamics.refit_weights(self.refit_sample(), config.l2))
                self._record_holdout_loss()
                return
            check_psi, check_targets = dynamics.regression_data(self.store.sample(config.batch_size * 4, self._torch_rng))
            loss_before = float(dynamics.loss(check_psi, check_targets))
            backup = dynamics.weights.clone()
            learning_rate = config.learning_rate * self.model_step_scale
            batches = self._sample_minibatches(config.n_steps, config.batch_size)
            dynamics.sgd_update(batches, config.batch_size, learning_rate, config.l2)
            loss_after = float(dynamics.loss(check_psi, check_targets))
            if not (math.isfinite(loss_after) and loss_after <= 10 * loss_before + 1e-8):
                dynamics.weights.copy_(backup)
                self.model_step_scale /= 2
                warnings.warn(
                    f"model update diverged at iteration {self.iteration} (check loss {loss_before:.3g} -> {loss_after:.3g}); "
                    f"update undone, step size halved to {config.learning_rate * self.model_step_scale:.3g}",
                    RuntimeWarning,
                    stacklevel=2,
                )
            self.logger.record("train/model_loss_train", loss_after)
            self.logger.record("train/model_step_scale", self.model_step_scale)
            self._record_holdout_loss()

    def refit_sample(self) -> Transitions:
        """The transitions B is refit on: all of D while it holds at most
        ``model_update.refit_size`` of them, else that many drawn uniformly (with replacement,
        so the cost stays O(refit_size) however large D grows)."""
        size = self.model_update_config.refit_size
        if len(self.store) > size:
            return self.store.sample(size, self._torch_rng)
        return self.store.get(slice(0, len(self.store)))

    def _record_holdout_loss(self) -> None:
        """Log ``train/model_loss``: the model's mean squared error on held-out transitions."""
        if len(self.holdout) > 0:
            psi, targets = self.dynamics.regression_data(
                self.holdout.sample(self.model_update_config.holdout_size, self._torch_rng)
            )
            self.logger.record("train/model_loss", float(self.dynamics.loss(psi, targets)))

    def draw_collection(self) -> torch.Tensor:
        """The collection C of eq. (7): |C| states (``collection_size``, by default following p), a
        ``uniform_fraction`` of them uniform over the normalisation box (terminal states excluded),
        the rest drawn from D.

        :return: (|C|, obs_dim) states
        """
        config = self.evaluation_config
        size = collection_size_for(self.dynamics.p, config)
        with self._timed("policy_evaluation"):
            n_uniform = round(config.uniform_fraction * size)
            uniform = self.dynamics.obs_encoder.sample_uniform(2 * n_uniform, self._torch_rng)
            is_terminal = self.dynamics.reward.is_terminal
            if is_terminal is not None:
                uniform = uniform[~is_terminal(uniform)]
            uniform = uniform[:n_uniform]
            from_data = self.store.sample(size - len(uniform), self._torch_rng).obs
            return torch.cat([uniform, from_data])

    def policy_evaluation(self, states: torch.Tensor) -> torch.Tensor:
        """Policy evaluation, eq. (7): value weights w of the current policy on C, by Bellman
        residual minimisation (or LSTD), exactly or by warm-started gradient descent. The greedy
        policy is evaluated at its actions; the soft one in expectation over the candidates,
        ``Phi'_C = sum_a pi(a|s) E_model[phi~(S') | s, a]`` and the rewards likewise (both are
        linear in psi, so they are read at E_pi[psi(s, A)]).

        :param states: (|C|, obs_dim) the collection C
        :return: (p,) value weights w, V(s) = <w, phi(s)>
        """
        config, dynamics = self.evaluation_config, self.dynamics
        with self._timed("policy_evaluation"):
            if self._factored_evaluation(len(states)):
                return self._factored_policy_evaluation(states)
            readout = dynamics.readout()  # psi is read block by block, never stored: (|C|, q) is the big array
            step = self._policy_step(states, readout)
            next_phi, model_rewards = dynamics.read(step.phi, step.psi)
            rewards = self._step_rewards(states, step) + model_rewards
            phi = step.phi
            if config.solver == "gd":
                initial = self._value_weights if self._value_weights is not None else torch.zeros_like(phi[0])
                weights = bellman_residual_descent(phi, next_phi, rewards, self.gamma, config.l2, initial, config.gd_steps)
            elif config.method == "lstd":
                weights = lstd_weights(phi, next_phi, rewards, self.gamma, config.l2)
            else:
                weights = bellman_residual_weights(phi, next_phi, rewards, self.gamma, config.l2)
            self._record_evaluation(step, weights, bellman_residual_rms(phi, next_phi, rewards, self.gamma, weights))
            return weights

    def _factored_evaluation(self, size: int) -> bool:
        """Whether eq. (7) is solved on the factors of its residual map
        (:class:`~cme_agent.planning.FactoredResidual`): the exact Bellman residual in its dual
        form (|C| < p), with a phi whose Gram matrix is cheap (an RBF grid), where that costs less."""
        config = self.evaluation_config
        return (
            config.method == "bellman_residual"
            and config.solver == "lstsq"
            and isinstance(self.dynamics.phi, RBFGrid)
            and factored_is_cheaper(size, self.dynamics.p, self.dynamics.q)
        )

    def _factored_policy_evaluation(self, states: torch.Tensor) -> torch.Tensor:
        """:meth:`policy_evaluation` on the factors of A = Phi_C - gamma Phi'_C: psi (|C|, q) is
        kept instead of Phi'_C (|C|, p), and A A^T is built from the RBF grid's Gram matrix."""
        dynamics = self.dynamics
        step = self._policy_step(states, None)
        rewards = self._step_rewards(states, step) + dynamics.linear_reward(step.phi, step.psi)
        gram = functools.partial(dynamics.phi.gram, states)
        residual = FactoredResidual(step.phi, gram, step.psi, dynamics.phi_weights, self.gamma, dynamics.feature_dynamics)
        weights = factored_dual_weights(residual, rewards, self.evaluation_config.l2)
        rms = float(residual.matvec(weights).sub_(rewards).square_().mean().sqrt())
        self._record_evaluation(step, weights, rms)
        return weights

    def _policy_step(self, states: torch.Tensor, readout: torch.Tensor | None) -> GreedyStep | SoftStep:
        """The policy's step on C (greedy, or soft with its entropy logged), psi read through ``readout``."""
        if not self.policy.soft:
            return self.policy.greedy_step(states, readout)
        step = self.policy.soft_step(states, readout)
        self._record_soft_policy(step.probabilities)
        return step

    def _step_rewards(self, states: torch.Tensor, step: GreedyStep | SoftStep) -> torch.Tensor:
        """The known step reward at the policy's actions on C (its expectation for the soft policy): (|C|,)."""
        return step.step_rewards if isinstance(step, SoftStep) else self.dynamics.reward.step_reward(states, step.actions)

    def _record_evaluation(self, step: GreedyStep | SoftStep, weights: torch.Tensor, residual_rms: float) -> None:
        """Keep w for the warm start and log the Bellman residual, the mean Q and the mean V on C."""
        self._value_weights = weights
        self.logger.record("train/bellman_residual", residual_rms)
        self.logger.record("train/q_mean", float(step.values.mean()))
        self.logger.record("train/value_mean", float((step.phi @ weights).mean()))

    def _record_soft_policy(self, probabilities: torch.Tensor) -> None:
        """Log the soft policy's mean entropy on C (nats; log K is uniform) and its beta_k."""
        entropy = -(probabilities * probabilities.clamp_min(1e-30).log()).sum(1).mean()
        self.logger.record("train/policy_entropy", float(entropy))
        self.logger.record("train/inverse_temperature", float(self.policy.inverse_temperature))

    def policy_improvement(self, value_weights: torch.Tensor, states: torch.Tensor | None = None) -> None:
        """Policy improvement (:meth:`CMEPolicy.improve`), on the linear weights of Q (zero-padded,
        no history): Q_k = (1 - omega) Q_{k-1} + omega Q^_k and pi_{k+1} = greedy(Q_k), or with
        ``improvement.method="soft"`` the average Qbar_k of the Q^_j and pi_{k+1} = softmax(beta_k Qbar_k).

        :param value_weights: (p,) w_k from :meth:`policy_evaluation`
        :param states: (|C|, obs_dim) the collection C, where the soft improvement measures the
            spread of Q for beta_k (None: a fresh collection is drawn when needed)
        """
        with self._timed("policy_improvement"):
            if states is None and self.policy.soft and self.improvement_config.scale == "spread":
                states = self.draw_collection()
            self.policy.improve(value_weights, self.gamma, self.omega, states)

    # ------------------------------------------------------------------ logging
    def _announce_settings(self) -> None:
        """Say which preset was applied and which reward the agent plans with."""
        if self.preset_message is not None and self.verbose >= 1:
            self.logger.info(self.preset_message)
        if self.reward_source == "learned" and not self.model_update_config.known_reward:
            self.logger.info(
                f"The reward of env {self._env_name()} is learned by regression on psi (model_update.known_reward=False)."
            )
        elif self.reward_source == "learned":
            self.logger.info(
                f"No reward function is known for env {self._env_name()}: the reward is learned by regression on psi "
                "(pass reward_fn= for a known one)."
            )
        elif self.verbose >= 1:
            self.logger.info(f"Planning with the {self.reward_source} reward of env {self._env_name()}.")

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
