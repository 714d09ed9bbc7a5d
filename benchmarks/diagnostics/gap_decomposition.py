"""Where does the agent lose on a MuJoCo env? The gap split into the model, the value and the action set.

Trains ``CMEPolicyIteration("CMEPolicy", env_id, seed=seed)`` (library defaults, plus ``--kwargs``)
for ``--steps`` env steps, then measures its greedy policy pi with its own phi, gamma and ridge,
resetting the simulator to recorded states (MuJoCo's ``set_state``) to get true next states
(phi~(s') below is phi of the next state, 0 after termination; H is the rollout length, with
gamma^H < 1e-3; Monte-Carlo rollouts have no time limit):

- **C**: ``--collection`` states with their ``qpos``, ``qvel``: half from the agent's
  deterministic episodes (env seeded seed + 20,000), half from its episodes with its training
  noise (``exploration.noise_std`` of the action half-range; seed + 20,001), at most a tenth of
  each half from one episode. The agent's own C is half uniform over its box (states that have no
  simulator state); the noisy half stands in for it. Fits on C are scored on its odd episodes;
- **model error** at pi's actions on C's deterministic half: ``phi_error`` the mean
  |E_model[phi~(S')] - phi~(s')| over the mean true change |phi~(s') - phi(s)| (as
  true_dynamics_planning.py), ``phi_error_spread`` the same error over the mean distance of
  phi~(s') from its mean (where pi barely moves, the change is near 0), the RMS error of the
  model's reward (``reward_std``: the true reward's std), ``continuation_at_falls`` the model's
  P(no termination) at the transitions that do terminate, and the raw next observation read from
  phi by a linear ridge decoder fitted on (phi(s'), s') of C's even episodes: on the odd ones, the
  RMS error of the decoded model prediction over the RMS true change per observation dim that
  changes, averaged (``obs_error``; ``obs_error_decoder``: the same for phi(s'), the decoder's floor);
- **value**: w of V^pi = <w, phi> by eq. (7) on C with the agent's ridge, through the model
  (``model_w``: E_model[phi~(S')] and the model's reward at pi's actions, what the agent solves)
  and through the true transitions (``true_w``), each scored by R^2 against the Monte-Carlo value of
  pi (``r2_model_w``, ``r2_true_w``); ``r2_phi_fit``: the best R^2 any w reaches, a ridge fit of the
  Monte-Carlo values on phi of the even episodes (best of a ridge grid, so a little optimistic;
  ``r2_phi_fit_train``: the same fit on its own rows); ``phi_rank_99``, ``phi_rank_999``: how many
  singular directions of phi on C hold 99% and 99.9% of its energy (of p);
- **action set** on ``--states`` states of C's deterministic half, on the true one-step lookahead
  Q(s, a) = r(s, a) + gamma (1 - done) <w_true, phi(s')>, maximised over the agent's candidates and
  over a fine set (41 per dim for one action dim, 21 x 21 for two, else 2,000 uniform samples; the
  candidates included): ``vtrue_gap_fine`` the mean gap, ``vtrue_gap_fine_rel`` over the std of
  V_true on C, ``vtrue_regret_chosen`` Q at the best candidate minus Q at pi(s),
  ``vtrue_chosen_near_best`` the share of states where Q at pi(s) is within 1% of the state's range
  of Q over the fine set from the fine best, ``vtrue_fine_best_abs`` the mean |a| of the fine best
  (in action half-ranges). The same on the exact Q^pi(s, a) = r + gamma (1 - done) V^pi(s'), V^pi
  by H - 1 true steps of pi from s', on ``--exact-states`` of those states with a coarser fine set
  (41 per dim for one dim, 11 x 11 for two, else 256 samples): ``exact_*`` (the spread is the
  Monte-Carlo values' std); and the candidates ranked by it: ``exact_agrees_<who>`` the share of
  states where the agent (pi(s)), the lookahead on the model's w or on the true w picks the best
  candidate, ``exact_regret_<who>`` the mean Q^pi lost by the pick;
- **returns** (10 episodes, env seeded seed + 10,000 as in unseen_envs.py: on one env reset with
  that seed once, as SB3's evaluation on ``make_vec_env``; every episode cut after ``--max-steps``,
  and the two exact lookaheads, which roll out pi from every action at every step, over the first
  ``--exact-episodes`` only; ``paired_return_*``: every policy over those first episodes, the
  same starts, on which the attribution is made) of the agent and of the one-step
  lookaheads through the true dynamics, each argmax_a from the simulator's state: on the model's w
  over the candidates, on the true w over the candidates, on the true w over the fine set, on the
  exact Q^pi over the candidates (the exact one-step policy improvement of pi) and over a fine
  set (41 per dim for one action dim, 5 x 5 for two, else 64 samples; candidates included); and
  ``return_true_iterated``: the lookahead on the true w after ``--rounds`` more rounds of policy
  iteration on the true transitions of C (each round's lookahead policy evaluated by eq. (7)).
  Attribution, the return gained by each step: agent -> lookahead on the model's w (the model in
  the improvement step) -> on the true w (the model in the evaluation step) -> with the fine
  actions (the action set, on V_true); true w -> exact Q^pi (the value's representation: phi,
  eq. (7) on C) -> with the fine actions (the action set, on exact values); and SAC's return at
  20,000 steps (``results/unseen_envs.md``) minus the best of those lookaheads (what one
  step of lookahead from pi leaves);
- **where episodes end**, for each of those policies: InvertedDoublePendulum-v5 (ends only
  when the tip's height y <= 1) the length, the share terminated and, over the falls, the tip's
  y, the cart's |x| and the share at its rail (|x| > 0.95), the lower link's |angle| and the upper
  link's absolute |angle| (rad); Reacher-v5 (no termination) the final distance to the target and
  the episode's summed distance and control costs.

Each seed's model goes to results/<stem>/<env>_seed<k>.zip and its measurements to
results/<stem>/<env>_seed<k>.json; a rerun reuses both (scratch, not committed). Writes
results/<stem>.md (stem default gap_decomposition_<env>). One seed's measurement takes a few
minutes of one core beyond its training.

    python -m benchmarks.diagnostics.gap_decomposition --env-id InvertedDoublePendulum-v5 --seeds 0 1 2 --steps 10000
    python -m benchmarks.diagnostics.gap_decomposition --env-id Reacher-v5 --seeds 0 1 2 --steps 10000
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from benchmarks.common import (
    SeedFiles,
    add_seed_arguments,
    command_line,
    map_seeds,
    markdown_table,
    save_record,
    seed_table,
    with_cme,
    write_markdown,
)
from benchmarks.diagnostics.true_dynamics_planning import phi_of, r_squared, rollout_horizon
from benchmarks.unseen_envs import EVAL_EPISODES, EVAL_SEED_OFFSET
from cme_agent import CMEPolicyIteration
from cme_agent.planning import bellman_residual_weights

COLLECTION_SEED_OFFSET = 20_000
"""C's episodes start from an env seeded seed + 20,000, apart from training and evaluation."""
SAC_REFERENCE = {"InvertedDoublePendulum-v5": 9359.9, "Reacher-v5": -5.1}
"""SAC's final return at 20,000 env steps, mean of seeds 0-4 (results/unseen_envs.md)."""
FINE_GRID = {1: 41, 2: 21}
"""Points per action dim of the fine grid, by action dim; above, uniform samples."""
FINE_SAMPLES = 2_000
EXACT_GRID = {1: 41, 2: 11}
"""The same for the exact Q^pi, whose every action costs a rollout from every state."""
EXACT_SAMPLES = 256
RETURN_EXACT_GRID = {1: 41, 2: 5}
"""The same for the exact lookahead's episodes, which roll out every action at every step."""
RETURN_EXACT_SAMPLES = 64
NEAR_BEST = 0.01
"""'Within 1%': Q at the action within this share of the state's range of Q over the fine set."""
RAIL = 0.95
"""InvertedDoublePendulum's cart at its rail: |x| above this (the slider's range is [-1, 1])."""
PHI_FIT_RIDGES = (1e-8, 1e-6, 1e-4, 1e-2, 1.0)
"""Ridges (relative to the mean diagonal of phi's Gram matrix) tried by the best fit of V on phi."""
PHI_CHUNK = 8_192
"""Rows of phi built at a time (8,192 x 1,000 float32: 32 MB)."""
POLICIES = (
    "agent",
    "lookahead_model_w",
    "lookahead_true_w",
    "lookahead_true_w_fine",
    "lookahead_exact",
    "lookahead_exact_fine",
    "true_iterated",
)
MODEL_METRICS = (
    "phi_error",
    "phi_error_spread",
    "reward_rmse",
    "reward_std",
    "obs_error",
    "obs_error_decoder",
    "continuation_at_falls",
)
VALUE_METRICS = ("r2_model_w", "r2_true_w", "r2_phi_fit", "r2_phi_fit_train")
ENERGY_SHARES = (0.99, 0.999)
"""phi's effective width on C: the directions that hold these shares of its energy."""
RANK_METRICS = tuple(f"phi_rank_{str(share)[2:]}" for share in ENERGY_SHARES)
ACTION_METRICS = tuple(
    f"vtrue_{key}" for key in ("gap_fine", "gap_fine_rel", "regret_chosen", "chosen_near_best", "fine_best_abs")
)
EXACT_METRICS = tuple(f"exact_{key}" for key in ("gap_fine", "gap_fine_rel", "chosen_near_best", "fine_best_abs"))
RANKING_METRICS = tuple(f"exact_{kind}_{name}" for name in ("agent", "model_w", "true_w") for kind in ("regret", "agrees"))
RETURN_METRICS = tuple(f"return_{policy}" for policy in POLICIES)
PAIRED_METRICS = tuple(f"paired_return_{policy}" for policy in POLICIES)
PARTS = (
    ("model in the improvement step", "agent", "lookahead_model_w"),
    ("model in the evaluation step", "lookahead_model_w", "lookahead_true_w"),
    ("action set, on V_true", "lookahead_true_w", "lookahead_true_w_fine"),
    ("value representation (phi, eq. (7) on C)", "lookahead_true_w", "lookahead_exact"),
    ("action set, on the exact Q^pi", "lookahead_exact", "lookahead_exact_fine"),
)
"""The attribution: each part is the return gained by the step from one policy to another."""
REST = "left to SAC after the best lookahead"


@dataclass
class Steps:
    """Simulated transitions, all arrays with the same leading shape (...,).

    :param obs: (..., obs_dim) next observations
    :param rewards: (...,) rewards
    :param terminated: (...,) whether the next state is terminal
    :param qpos: (..., nq) next positions
    :param qvel: (..., nv) next velocities
    """

    obs: np.ndarray
    rewards: np.ndarray
    terminated: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray

    def take(self, rows: np.ndarray) -> Steps:
        """The transitions at ``rows`` of the leading dimension (an index or mask array)."""
        return Steps(self.obs[rows], self.rewards[rows], self.terminated[rows], self.qpos[rows], self.qvel[rows])

    def reshape(self, *shape: int) -> Steps:
        """The same transitions with leading shape ``shape``."""
        return Steps(
            self.obs.reshape(*shape, -1),
            self.rewards.reshape(shape),
            self.terminated.reshape(shape),
            self.qpos.reshape(*shape, -1),
            self.qvel.reshape(*shape, -1),
        )


@dataclass
class Visited:
    """States of the agent's episodes with their simulator states.

    :param obs: (N, obs_dim) observations
    :param qpos: (N, nq) positions
    :param qvel: (N, nv) velocities
    :param episode: (N,) index of the episode each came from
    """

    obs: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray
    episode: np.ndarray

    def subset(self, rows: np.ndarray) -> Visited:
        """The states at ``rows`` (an index or mask array)."""
        return Visited(self.obs[rows], self.qpos[rows], self.qvel[rows], self.episode[rows])


def simulate(sim: Any, qpos: np.ndarray, qvel: np.ndarray, actions: np.ndarray) -> Steps:
    """One true step from each state: the simulator reset there (``set_state``) and stepped.

    :param sim: an unwrapped MuJoCo env (no time limit); its state is overwritten
    :param qpos: (N, nq) positions
    :param qvel: (N, nv) velocities
    :param actions: (N, act_dim) actions in env units
    :return: the N transitions
    """
    n = len(qpos)
    obs = np.empty((n, sim.observation_space.shape[0]))
    rewards, terminated = np.empty(n), np.empty(n, dtype=bool)
    next_qpos, next_qvel = np.empty_like(qpos, dtype=np.float64), np.empty_like(qvel, dtype=np.float64)
    for i in range(n):
        sim.set_state(qpos[i], qvel[i])
        obs[i], rewards[i], terminated[i], _, _ = sim.step(actions[i])
        next_qpos[i], next_qvel[i] = sim.data.qpos, sim.data.qvel
    return Steps(obs, rewards, terminated, next_qpos, next_qvel)


def simulate_all(sim: Any, states: Visited, actions: np.ndarray) -> Steps:
    """Every action of a set from every state: (N,) states, (F, act_dim) actions -> Steps of shape (N, F)."""
    n, f = len(states.qpos), len(actions)
    flat = simulate(sim, np.repeat(states.qpos, f, axis=0), np.repeat(states.qvel, f, axis=0), np.tile(actions, (n, 1)))
    return flat.reshape(n, f)


def state_values(agent: CMEPolicyIteration, obs: np.ndarray, weights: torch.Tensor) -> np.ndarray:
    """<w, phi(s)> in chunks of rows (phi of all of them may not fit): (..., obs_dim), (p,) or (p, m) -> (...,) or (..., m)."""
    flat = obs.reshape(-1, obs.shape[-1])
    values = np.concatenate(
        [(phi_of(agent, flat[i : i + PHI_CHUNK]) @ weights).numpy() for i in range(0, len(flat), PHI_CHUNK)]
    ).astype(np.float64)
    return values.reshape(*obs.shape[:-1], *weights.shape[1:])


def lookahead_q(agent: CMEPolicyIteration, steps: Steps, weights: torch.Tensor) -> np.ndarray:
    """True one-step lookahead r + gamma (1 - done) <w, phi(s')> of transitions of any leading shape."""
    next_values = state_values(agent, steps.obs, weights)
    return steps.rewards + agent.gamma * np.where(steps.terminated, 0.0, next_values)


def fine_actions(
    low: np.ndarray, high: np.ndarray, rng: np.random.Generator, grid: dict[int, int], samples: int
) -> np.ndarray:
    """A fine action set: a grid of ``grid[d]`` points per dim for d action dims, else ``samples``
    uniform samples.

    :param low: (act_dim,) lower bounds
    :param high: (act_dim,) upper bounds
    :param rng: draws the samples
    :param grid: points per dim, by number of action dims
    :param samples: number of uniform samples where ``grid`` has no entry
    :return: (F, act_dim) actions
    """
    dims = len(low)
    if dims in grid:
        axes = [np.linspace(lo, hi, grid[dims]) for lo, hi in zip(low, high, strict=True)]
        return np.array(list(itertools.product(*axes)))
    return rng.uniform(low, high, size=(samples, dims))


def action_set_metrics(
    q_candidates: np.ndarray, q_fine: np.ndarray, q_chosen: np.ndarray, fine_best: np.ndarray, value_spread: float
) -> dict[str, float]:
    """The action-set figures from one-step lookahead values at N states.

    :param q_candidates: (N, K) Q at the agent's candidates
    :param q_fine: (N, F) Q at the fine set (which contains the candidates)
    :param q_chosen: (N,) Q at the agent's action pi(s)
    :param fine_best: (N, act_dim) the fine set's best action, in units of the action half-range
    :param value_spread: std of V over C, the unit of ``gap_fine_rel``
    :return: ``gap_fine`` (mean best over the fine set minus best over the candidates),
        ``gap_fine_rel`` (that over ``value_spread``), ``regret_chosen`` (mean best candidate minus
        pi(s)), ``chosen_near_best`` (share of states where pi(s) is within ``NEAR_BEST`` of the
        state's range of Q over the fine set from the fine best), ``fine_best_abs`` (mean |a*|)
    """
    best_fine, best_candidate = q_fine.max(axis=1), q_candidates.max(axis=1)
    q_range = best_fine - q_fine.min(axis=1)
    gap = best_fine - best_candidate
    return {
        "gap_fine": float(gap.mean()),
        "gap_fine_rel": float(gap.mean() / value_spread),
        "regret_chosen": float((best_candidate - q_chosen).mean()),
        "chosen_near_best": float(np.mean(best_fine - q_chosen <= NEAR_BEST * q_range)),
        "fine_best_abs": float(np.abs(fine_best).mean()),
    }


def best_phi_fit(phi: torch.Tensor, targets: np.ndarray, train: np.ndarray) -> tuple[float, float]:
    """The best held-out R^2 of a ridge fit of ``targets`` on phi: fit on the ``train`` rows,
    scored on the others, best over ``PHI_FIT_RIDGES``; and that fit's R^2 on its own rows (near 1
    with a low held-out one: phi can take V's shape at the data but does not carry it between
    episodes).

    :param phi: (N, p) features
    :param targets: (N,) values
    :param train: (N,) bool, the rows fitted
    :return: held-out R^2, training R^2
    """
    x, y = phi[train].double(), torch.as_tensor(targets[train], dtype=torch.float64)
    gram, moment = x.T @ x, x.T @ y
    scale = float(gram.diagonal().mean())
    scores = []
    for ridge in PHI_FIT_RIDGES:
        weights = torch.linalg.solve(gram + ridge * scale * torch.eye(len(gram), dtype=gram.dtype), moment).float()
        scores.append((r_squared(weights, phi[~train], targets[~train]), r_squared(weights, phi[train], targets[train])))
    return max(scores)


def phi_ranks(phi: torch.Tensor) -> dict[str, int]:
    """How many of phi's p directions the states use: the number of singular values of phi on them
    that hold each share of ``ENERGY_SHARES`` of the squared sum (a few dozen of 1,000: phi's
    resolution is spent off the data). :param phi: (N, p) phi at the states."""
    energy = torch.linalg.svdvals(phi.double()).square().cumsum(0)
    energy /= energy[-1].clone()
    return {f"phi_rank_{str(share)[2:]}": int((energy < share).sum()) + 1 for share in ENERGY_SHARES}


def attribution(returns: dict[str, float], reference: float | None) -> list[tuple[str, float]]:
    """The return gained by each step of ``PARTS``: agent -> lookahead on the model's w -> on the
    true w -> with the fine actions, and true w -> the exact Q^pi -> with the fine actions; and, with
    ``reference`` (SAC's return), what is left from the best of those lookaheads to it.

    :param returns: policy -> return (over the same episodes)
    :return: (part, gain) in the order of ``PARTS``, then the rest
    """
    parts = [(name, returns[after] - returns[before]) for name, before, after in PARTS]
    if reference is not None:
        parts.append((REST, reference - max(returns[after] for _, _, after in PARTS)))
    return parts


def largest_part(parts: Sequence[tuple[str, float]]) -> tuple[str, float]:
    """The part that gains most return."""
    return max(parts, key=lambda part: part[1])


class Lookahead:
    """argmax_a r(s, a) + gamma (1 - done) <w, phi(s')> over an action set, through the true
    dynamics from the simulator state of the env it acts in.

    :param agent: the trained agent (its phi and gamma)
    :param weights: (p,) value weights w
    :param actions: (F, act_dim) the action set
    :param env_id: the env (a scratch copy is stepped)
    """

    def __init__(self, agent: CMEPolicyIteration, weights: torch.Tensor, actions: np.ndarray, env_id: str) -> None:
        self.agent, self.weights, self.actions = agent, weights, actions
        self.sim = gym.make(env_id).unwrapped

    def __call__(self, obs: np.ndarray, env: gym.Env) -> np.ndarray:
        """The best action at the env's current simulator state: (obs_dim,) -> (act_dim,)."""
        data, f = env.unwrapped.data, len(self.actions)
        steps = simulate(self.sim, np.tile(data.qpos, (f, 1)), np.tile(data.qvel, (f, 1)), self.actions)
        return self.actions[lookahead_q(self.agent, steps, self.weights).argmax()].astype(np.float32)


class ExactLookahead:
    """argmax_a Q^pi(s, a) over an action set, Q^pi by true rollouts of the agent's policy pi from
    each successor (:func:`exact_q`): the exact one-step policy improvement of pi, from the
    simulator state of the env it acts in.

    :param agent: the trained agent (pi and gamma)
    :param actions: (F, act_dim) the action set
    :param env_id: the env (a scratch copy is stepped)
    :param horizon: rollout length, gamma^horizon < 1e-3
    """

    def __init__(self, agent: CMEPolicyIteration, actions: np.ndarray, env_id: str, horizon: int) -> None:
        self.agent, self.actions, self.horizon = agent, actions, horizon
        self.sim = gym.make(env_id).unwrapped

    def __call__(self, obs: np.ndarray, env: gym.Env) -> np.ndarray:
        """The best action at the env's current simulator state: (obs_dim,) -> (act_dim,)."""
        data, f = env.unwrapped.data, len(self.actions)
        steps = simulate(self.sim, np.tile(data.qpos, (f, 1)), np.tile(data.qvel, (f, 1)), self.actions)
        return self.actions[exact_q(self.agent, self.sim, steps, self.horizon).argmax()].astype(np.float32)


def agent_policy(agent: CMEPolicyIteration) -> Callable[[np.ndarray, gym.Env], np.ndarray]:
    """The agent's deterministic action, as a policy of :func:`run_episodes`."""
    return lambda obs, env: agent.predict(obs, deterministic=True)[0]


def run_episodes(
    policy: Callable[[np.ndarray, gym.Env], np.ndarray], env_id: str, seed: int, episodes: int, max_steps: int | None = None
) -> list[dict[str, Any]]:
    """``episodes`` episodes on one env seeded ``seed`` at its first reset, as SB3's
    ``evaluate_policy`` on ``make_vec_env(env_id, seed=seed)`` runs them (a cut episode leaves the
    next ones' starts as they are: the env draws them at reset).

    :param policy: (obs, env) -> action; the env gives the simulator state
    :param max_steps: cut every episode after this many steps (None: the env's time limit)
    :return: per episode: ``return``, ``length``, ``terminated``, the summed step infos
        (``sum_<key>``) and the end state (:func:`episode_end`)
    """
    env, records = gym.make(env_id), []
    for episode in range(episodes):
        obs, _ = env.reset(seed=seed if episode == 0 else None)
        record: dict[str, Any] = {"return": 0.0, "length": 0, "terminated": False}
        done = False
        while not done:
            obs, reward, terminated, truncated, info = env.step(policy(obs, env))
            record["return"] += float(reward)
            record["length"] += 1
            for key, value in info.items():
                if np.isscalar(value):
                    record[f"sum_{key}"] = record.get(f"sum_{key}", 0.0) + float(value)
            done = terminated or truncated or record["length"] == max_steps
        record["terminated"] = bool(terminated)
        records.append({**record, **episode_end(env_id, env.unwrapped, obs)})
    return records


def episode_end(env_id: str, sim: Any, obs: np.ndarray) -> dict[str, float]:
    """What the last state of an episode shows: InvertedDoublePendulum's tip height, cart position
    and link angles (rad); Reacher's distance from the fingertip to the target; else nothing."""
    if env_id.startswith("InvertedDoublePendulum"):
        x, lower, upper = (float(v) for v in sim.data.qpos[:3])
        return {"tip_y": float(sim.data.site_xpos[0][2]), "x": x, "lower_angle": lower, "upper_angle": lower + upper}
    if env_id.startswith("Reacher"):
        return {"distance": float(np.linalg.norm(obs[-2:]))}
    return {}


def ending_summary(episodes: list[dict[str, Any]]) -> dict[str, float]:
    """The means over episodes that the report shows of how they end (fall figures over the
    episodes that terminated only)."""
    summary = {
        "return": statistics.mean(e["return"] for e in episodes),
        "length": statistics.mean(e["length"] for e in episodes),
        "terminated": statistics.mean(float(e["terminated"]) for e in episodes),
    }
    falls = [e for e in episodes if e["terminated"] and "tip_y" in e]
    if falls:
        summary["fall_tip_y"] = statistics.mean(e["tip_y"] for e in falls)
        summary["fall_abs_x"] = statistics.mean(abs(e["x"]) for e in falls)
        summary["fall_at_rail"] = statistics.mean(float(abs(e["x"]) > RAIL) for e in falls)
        summary["fall_abs_lower_angle"] = statistics.mean(abs(e["lower_angle"]) for e in falls)
        summary["fall_abs_upper_angle"] = statistics.mean(abs(e["upper_angle"]) for e in falls)
    if "distance" in episodes[0]:
        summary["final_distance"] = statistics.mean(e["distance"] for e in episodes)
        summary["distance_cost"] = -statistics.mean(e.get("sum_reward_dist", 0.0) for e in episodes)
        summary["control_cost"] = -statistics.mean(e.get("sum_reward_ctrl", 0.0) for e in episodes)
    return summary


def visited_states(
    agent: CMEPolicyIteration, env_id: str, n: int, seed: int, noise: float = 0.0, first_episode: int = 0
) -> Visited:
    """n states of the agent's episodes (env seeded ``seed`` at its first reset), at most n // 10
    from one episode, with their simulator states.

    :param noise: std of Gaussian noise added to the agent's action, as a fraction of the action
        half-range (0: its deterministic episodes)
    :param first_episode: the index of the first episode (to keep indices apart between calls)
    """
    env, cap, rng = gym.make(env_id), max(1, n // 10), np.random.default_rng(seed)
    box = env.action_space
    half_range = (box.high - box.low) / 2
    obs_rows, qpos_rows, qvel_rows, episodes = [], [], [], []
    episode = 0
    while len(obs_rows) < n:
        obs, _ = env.reset(seed=seed if episode == 0 else None)
        for _ in range(min(cap, n - len(obs_rows))):
            data = env.unwrapped.data
            obs_rows.append(obs.copy())
            qpos_rows.append(data.qpos.copy())
            qvel_rows.append(data.qvel.copy())
            episodes.append(first_episode + episode)
            action = agent.predict(obs, deterministic=True)[0]
            if noise > 0:
                action = np.clip(action + rng.normal(0.0, noise * half_range), box.low, box.high).astype(np.float32)
            obs, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                break
        episode += 1
    return Visited(np.array(obs_rows), np.array(qpos_rows), np.array(qvel_rows), np.array(episodes))


def collection(agent: CMEPolicyIteration, env_id: str, n: int, seed: int) -> tuple[Visited, np.ndarray]:
    """C: half of n states from the agent's deterministic episodes (env seeded ``seed``), half
    from its episodes with the exploration noise of training (``exploration.noise_std``; env seeded
    ``seed`` + 1), as the agent's C mixes states of its own and of its data.

    :return: C and the (n,) mask of its deterministic part
    """
    own = visited_states(agent, env_id, n - n // 2, seed)
    noisy = visited_states(agent, env_id, n // 2, seed + 1, agent.exploration_config.noise_std, int(own.episode.max()) + 1)
    states = Visited(*(np.concatenate([a, b]) for a, b in zip(vars(own).values(), vars(noisy).values(), strict=True)))
    return states, np.arange(n) < len(own.obs)


def monte_carlo_values(agent: CMEPolicyIteration, sim: Any, states: Visited, horizon: int) -> np.ndarray:
    """V^pi(s) = sum_t gamma^t r_t over ``horizon`` true steps of pi (no time limit; a terminal
    step ends the sum), all rollouts in lockstep: (N,) states -> (N,)."""
    obs, qpos, qvel = states.obs.copy(), states.qpos.copy(), states.qvel.copy()
    values, alive, discount = np.zeros(len(obs)), np.ones(len(obs), dtype=bool), 1.0
    for _ in range(horizon):
        rows = np.flatnonzero(alive)
        if not len(rows):
            break
        actions = agent.predict(obs[rows].astype(np.float32), deterministic=True)[0]
        steps = simulate(sim, qpos[rows], qvel[rows], actions)
        values[rows] += discount * steps.rewards
        obs[rows], qpos[rows], qvel[rows] = steps.obs, steps.qpos, steps.qvel
        alive[rows[steps.terminated]] = False
        discount *= agent.gamma
    return values


def exact_q(agent: CMEPolicyIteration, sim: Any, steps: Steps, horizon: int) -> np.ndarray:
    """Q^pi(s, a) = r + gamma (1 - done) V^pi(s') with V^pi by true rollouts of pi from s'
    (``horizon`` - 1 steps): the exact one-step lookahead, for transitions of any leading shape."""
    flat = steps.reshape(steps.rewards.size)
    alive = np.flatnonzero(~flat.terminated)
    successors = Visited(flat.obs[alive], flat.qpos[alive], flat.qvel[alive], np.zeros(len(alive), dtype=int))
    next_values = np.zeros(len(flat.rewards))
    next_values[alive] = monte_carlo_values(agent, sim, successors, horizon - 1)
    return (flat.rewards + agent.gamma * next_values).reshape(steps.rewards.shape)


def ranking_metrics(exact: np.ndarray, picks: dict[str, np.ndarray]) -> dict[str, float]:
    """How well each way of choosing among the candidates ranks them by the exact Q^pi.

    :param exact: (N, K) Q^pi at the candidates
    :param picks: name -> (N,) the index of the candidate it chooses
    :return: ``exact_regret_<name>`` (mean of the best Q^pi minus Q^pi at the pick) and
        ``exact_agrees_<name>`` (share of states where the pick is the best) per name
    """
    best, rows = exact.max(axis=1), np.arange(len(exact))
    metrics = {}
    for name, pick in picks.items():
        metrics[f"exact_regret_{name}"] = float((best - exact[rows, pick]).mean())
        metrics[f"exact_agrees_{name}"] = float(np.mean(exact[rows, pick] >= best))
    return metrics


def obs_decoding_errors(
    phi_next: torch.Tensor,
    model_next: torch.Tensor,
    obs: np.ndarray,
    next_obs: np.ndarray,
    train: np.ndarray,
    test: np.ndarray,
) -> tuple[float, float]:
    """The raw next observation read from phi by a linear ridge decoder fitted on (phi(s'), s') of
    the ``train`` rows; on the ``test`` rows, the RMS error of the decoded model prediction over the
    RMS true change, per observation dim that changes, then averaged; and the same for the decoded
    phi(s') (the decoder's own floor). Terminal transitions belong in neither mask (phi~ = 0 there).

    :param phi_next: (N, p) phi of the true next states
    :param model_next: (N, p) E_model[phi~(S')]
    :param obs: (N, obs_dim) states
    :param next_obs: (N, obs_dim) true next states
    :param train: (N,) bool, the rows the decoder is fitted on
    :param test: (N,) bool, the rows scored
    """
    x, y = phi_next[train].double(), torch.as_tensor(next_obs[train], dtype=torch.float64)
    gram = x.T @ x
    ridge = 1e-6 * float(gram.diagonal().mean()) * torch.eye(len(gram), dtype=gram.dtype)
    decoder = torch.linalg.solve(gram + ridge, x.T @ y)
    change = np.sqrt(((next_obs[test] - obs[test]) ** 2).mean(axis=0))
    moving = change > 1e-9  # e.g. Reacher's target position never changes within an episode

    def error(features: torch.Tensor) -> float:
        decoded = (features[test].double() @ decoder).numpy()
        rms = np.sqrt(((decoded - next_obs[test]) ** 2).mean(axis=0))
        return float((rms[moving] / change[moving]).mean())

    return error(model_next), error(phi_next)


def trained_agent(env_id: str, seed: int, steps: int, kwargs: dict[str, Any], path: Path) -> tuple[CMEPolicyIteration, float]:
    """The agent trained for ``steps`` env steps, with its transitions: loaded from ``path`` if an
    earlier run saved it, else trained and saved there. :return: the agent and the seconds of
    training (0 if loaded)."""
    if path.exists():
        agent = CMEPolicyIteration.load(path)
        if agent.num_timesteps < steps:
            raise SystemExit(f"{path} was trained for {agent.num_timesteps} steps, not {steps}: use another --stem")
        return agent, 0.0
    start = time.perf_counter()
    agent = CMEPolicyIteration("CMEPolicy", env_id, seed=seed, **with_cme(kwargs)).learn(steps)
    agent.save(path, include=["replay_buffer"])
    return agent, time.perf_counter() - start


@torch.no_grad()
def measure(agent: CMEPolicyIteration, job: Job) -> dict[str, Any]:
    """Every measurement of the module docstring on one trained agent: its row (metrics, episode endings)."""
    env_id, seed, n_states, n_exact = job.env_id, job.seed, job.states, job.exact_states
    dynamics, gamma, l2 = agent.dynamics, agent.gamma, agent.evaluation_config.l2
    sim, rng = gym.make(env_id).unwrapped, np.random.default_rng(seed)
    horizon = rollout_horizon(gamma)
    row: dict[str, Any] = {"q": dynamics.q, "p": dynamics.p, "horizon": horizon}

    # C and pi's true transitions on it
    states, own = collection(agent, env_id, job.collection, seed + COLLECTION_SEED_OFFSET)
    row["C"], row["C_episodes"] = len(states.obs), int(states.episode.max()) + 1
    held_out = states.episode % 2 == 1  # odd episodes: where fits on C are scored
    obs = torch.as_tensor(states.obs, dtype=torch.float32)
    actions = agent.predict(states.obs.astype(np.float32), deterministic=True)[0]
    true = simulate(sim, states.qpos, states.qvel, actions)
    continuation = torch.as_tensor(~true.terminated, dtype=torch.float32).unsqueeze(1)
    phi, phi_next = phi_of(agent, states.obs), phi_of(agent, true.obs)
    true_next = phi_next * continuation  # phi~(s'): 0 after termination
    true_rewards = torch.as_tensor(true.rewards, dtype=torch.float32)

    # 1. the model's one-step prediction at pi's actions, on C's deterministic part (the agent's own states)
    action_tensor = torch.as_tensor(actions, dtype=torch.float32)
    psi = dynamics.features(obs, action_tensor)
    model_rewards = dynamics.expected_reward(obs, action_tensor, phi, psi)
    model_next, _ = dynamics.read(phi, psi @ dynamics.readout())
    mine = torch.as_tensor(own)
    errors, changes = (model_next - true_next).norm(dim=1), (true_next - phi).norm(dim=1)
    row["phi_error"] = float(errors[mine].mean() / changes[mine].mean())
    spread = (true_next[mine] - true_next[mine].mean(dim=0)).norm(dim=1).mean()  # where pi barely moves s, the change is ~0
    row["phi_error_spread"] = float(errors[mine].mean() / spread)
    row["reward_rmse"] = float((model_rewards - true_rewards)[mine].square().mean().sqrt())
    row["reward_std"] = float(true_rewards[mine].std())
    falls = torch.as_tensor(own & true.terminated)
    row["continuation_at_falls"] = float(model_next[falls, -1].mean()) if bool(falls.any()) else float("nan")
    moving = ~true.terminated
    row["obs_error"], row["obs_error_decoder"] = obs_decoding_errors(
        phi_next, model_next, states.obs, true.obs, moving & ~held_out, moving & held_out
    )

    # 2. V^pi by eq. (7) through the model and through the true transitions, against Monte Carlo
    weights = {
        "model_w": bellman_residual_weights(phi, model_next, model_rewards, gamma, l2),
        "true_w": bellman_residual_weights(phi, true_next, true_rewards, gamma, l2),
    }
    values = monte_carlo_values(agent, sim, states, horizon)
    for name, w in weights.items():
        row[f"r2_{name}"] = r_squared(w, phi[held_out], values[held_out])
    row["r2_phi_fit"], row["r2_phi_fit_train"] = best_phi_fit(phi, values, ~held_out)
    row.update(phi_ranks(phi))
    row["mc_value_mean"], row["mc_value_std"] = float(values.mean()), float(values.std())

    # 3. the action set at a sample of C's deterministic part: on V_true, then on the exact Q^pi
    box = gym.make(env_id).action_space
    low, high = box.low.astype(np.float64), box.high.astype(np.float64)
    centre, half_range = (high + low) / 2, (high - low) / 2
    candidates = agent.policy.candidates.numpy().astype(np.float64)
    k = len(candidates)
    fine = np.concatenate([fine_actions(low, high, rng, FINE_GRID, FINE_SAMPLES), candidates])  # candidates last
    sample = rng.choice(np.flatnonzero(own), size=min(n_states, int(own.sum())), replace=False)
    q_fine = lookahead_q(agent, simulate_all(sim, states.subset(sample), fine), weights["true_w"])
    q_chosen = lookahead_q(agent, true.take(sample), weights["true_w"])
    fine_best = (fine[q_fine.argmax(axis=1)] - centre) / half_range
    metrics = action_set_metrics(q_fine[:, -k:], q_fine, q_chosen, fine_best, float((phi @ weights["true_w"]).std()))
    row.update({f"vtrue_{key}": value for key, value in metrics.items()})

    candidate_steps = simulate_all(sim, states, candidates)
    exact_rows = sample[:n_exact]
    exact_set = np.concatenate([fine_actions(low, high, rng, EXACT_GRID, EXACT_SAMPLES), candidates])
    exact = exact_q(agent, sim, simulate_all(sim, states.subset(exact_rows), exact_set), horizon)
    agent_pick = np.abs(candidates[None] - actions[exact_rows][:, None]).sum(axis=2).argmin(axis=1)  # pi(s)'s candidate
    exact_best = (exact_set[exact.argmax(axis=1)] - centre) / half_range
    chosen = exact[np.arange(len(exact_rows)), len(exact_set) - k + agent_pick]
    metrics = action_set_metrics(exact[:, -k:], exact, chosen, exact_best, float(values.std()))
    row.update({f"exact_{key}": value for key, value in metrics.items() if key != "regret_chosen"})
    sampled = candidate_steps.take(exact_rows)
    picks = {"agent": agent_pick, **{name: lookahead_q(agent, sampled, w).argmax(axis=1) for name, w in weights.items()}}
    row.update(ranking_metrics(exact[:, -k:], picks))

    # rounds of policy iteration on the true transitions of C, from the true w
    iterated = weights["true_w"]
    for _ in range(job.rounds):
        best = lookahead_q(agent, candidate_steps, iterated).argmax(axis=1)
        pick = np.arange(len(best))
        chosen_next = phi_of(agent, candidate_steps.obs[pick, best])
        chosen_next *= torch.as_tensor(~candidate_steps.terminated[pick, best], dtype=torch.float32).unsqueeze(1)
        chosen_rewards = torch.as_tensor(candidate_steps.rewards[pick, best], dtype=torch.float32)
        iterated = bellman_residual_weights(phi, chosen_next, chosen_rewards, gamma, l2)

    # 4. returns, 5. where the episodes end
    exact_fine = np.concatenate([fine_actions(low, high, rng, RETURN_EXACT_GRID, RETURN_EXACT_SAMPLES), candidates])
    policies: dict[str, Callable[[np.ndarray, gym.Env], np.ndarray]] = {
        "agent": agent_policy(agent),
        "lookahead_model_w": Lookahead(agent, weights["model_w"], candidates, env_id),
        "lookahead_true_w": Lookahead(agent, weights["true_w"], candidates, env_id),
        "lookahead_true_w_fine": Lookahead(agent, weights["true_w"], fine, env_id),
        "lookahead_exact": ExactLookahead(agent, candidates, env_id, horizon),
        "lookahead_exact_fine": ExactLookahead(agent, exact_fine, env_id, horizon),
        "true_iterated": Lookahead(agent, iterated, candidates, env_id),
    }
    row["endings"] = {}
    for name, policy in policies.items():
        count = job.exact_episodes if isinstance(policy, ExactLookahead) else EVAL_EPISODES  # a rollout per action per step
        episodes = run_episodes(policy, env_id, seed + EVAL_SEED_OFFSET, count, job.max_steps)
        row["endings"][name] = ending_summary(episodes)
        row[f"return_{name}"] = row["endings"][name]["return"]
        row[f"paired_return_{name}"] = statistics.mean(e["return"] for e in episodes[: job.exact_episodes])
    return row


@dataclass(frozen=True)
class Job(SeedFiles):
    """One seed's run: train ``env_id`` with ``seed`` for ``steps`` env steps (constructor
    arguments ``kwargs``), then measure on ``collection`` states, the action set on ``states`` of
    them, the exact Q^pi on ``exact_states``, with ``rounds`` rounds of true policy iteration;
    the exact lookaheads' returns over ``exact_episodes`` episodes, every episode cut after
    ``max_steps``; files under results/<stem>/."""

    env_id: str
    seed: int
    steps: int
    kwargs: dict[str, Any]
    collection: int
    states: int
    exact_states: int
    rounds: int
    exact_episodes: int
    max_steps: int
    stem: str


def recorded_row(job: Any, measure_agent: Callable[[CMEPolicyIteration], dict[str, Any]]) -> dict[str, Any]:
    """One seed's row: read from the record of an earlier run (``job.path`` .json), else the agent
    trained (or loaded, :func:`trained_agent`) and measured by ``measure_agent``, then recorded.

    :param job: a frozen dataclass with ``env_id``, ``seed``, ``steps``, ``kwargs`` and ``path``
    :param measure_agent: the trained agent -> its measurements
    :return: the seed, the measurements, and the seconds of training and measuring
    """
    torch.set_num_threads(1)
    record = job.path.with_suffix(".json")
    if record.exists():
        return json.loads(record.read_text())["row"]
    agent, train_seconds = trained_agent(job.env_id, job.seed, job.steps, job.kwargs, job.path.with_suffix(".zip"))
    start = time.perf_counter()
    row = {"seed": job.seed, **measure_agent(agent)}
    row["train_s"], row["measure_s"] = round(train_seconds), round(time.perf_counter() - start)
    save_record(record, {"command": command_line(), "job": vars(job), "row": row})
    return row


def run_seed(job: Job) -> dict[str, Any]:
    """Train (or load) one agent and measure it, or read the record of an earlier run: its row."""
    row = recorded_row(job, lambda agent: measure(agent, job))
    print(job.env_id, job.seed, {key: round(float(row[key]), 3) for key in (*RETURN_METRICS, *VALUE_METRICS)}, flush=True)
    return row


def attribution_table(
    rows: list[dict[str, Any]], reference: float | None
) -> tuple[list[str], list[list[Any]], list[tuple[str, float]]]:
    """The attribution per seed and its mean: the table's header, rows, and the mean gain per part."""
    per_seed = [attribution({policy: row[f"paired_return_{policy}"] for policy in POLICIES}, reference) for row in rows]
    means = [(name, statistics.mean(parts[i][1] for parts in per_seed)) for i, (name, _) in enumerate(per_seed[0])]
    header = ["part", *(f"seed {row['seed']}" for row in rows), "mean"]
    table = [[name, *(f"{parts[i][1]:+.2f}" for parts in per_seed), f"{mean:+.2f}"] for i, (name, mean) in enumerate(means)]
    return header, table, means


def endings_table(rows: list[dict[str, Any]]) -> tuple[list[str], list[list[Any]]]:
    """Per policy, the means over seeds of how its evaluation episodes end (with the number of
    seeds that have a value: the fall figures need an episode that fell)."""
    keys = list(dict.fromkeys(key for row in rows for summary in row["endings"].values() for key in summary))
    table = []
    for policy in POLICIES:
        cells = []
        for key in keys:
            values = [row["endings"][policy][key] for row in rows if key in row["endings"][policy]]
            cells.append(f"{statistics.mean(values):.3f} ({len(values)})" if values else "-")
        table.append([policy, *cells])
    return ["policy", *keys], table


def summary_paragraph(env_id: str, rows: list[dict[str, Any]], means: list[tuple[str, float]], max_steps: int) -> str:
    """The generated verdict: the parts by size, the policies whose returns the cut after
    ``max_steps`` bounds, and the model, value and action-set figures beside them."""
    keys = (
        "phi_error",
        "phi_error_spread",
        "continuation_at_falls",
        *VALUE_METRICS,
        *ACTION_METRICS,
        *EXACT_METRICS,
        *RANKING_METRICS,
    )
    m = {key: statistics.mean(row[key] for row in rows) for key in keys}
    ranked = sorted(means[: len(PARTS)], key=lambda part: -part[1])
    (name, gain), (runner_up, second) = ranked[0], ranked[1]
    cut = [p for p in POLICIES if all(row["endings"][p]["length"] >= max_steps for row in rows)]
    text = (
        f"**{env_id}, mean of {len(rows)} seeds: the largest part is the {name} ({gain:+.2f} return), then the "
        f"{runner_up} ({second:+.2f}).** Return gained per step: "
        + "; ".join(f"{part} {value:+.2f}" for part, value in means)
        + ". "
    )
    if cut:
        text += (
            f"{', '.join(cut)} ran every episode to the cut ({max_steps} steps): its return, and the part it ends, "
            "are lower bounds. "
        )
    falls = "" if math.isnan(m["continuation_at_falls"]) else f", P(continue) at true falls {m['continuation_at_falls']:.2f}"
    return text + (
        f"Model: its phi error at pi's actions is {m['phi_error']:.2f} of the true change ({m['phi_error_spread']:.3f} of "
        f"phi(s')'s spread; the first is large where pi barely moves the state){falls}. "
        f"Value, R^2 against Monte Carlo on the held-out half of C: through the model {m['r2_model_w']:.3f}, through "
        f"the true transitions {m['r2_true_w']:.3f}, the best fit on phi {m['r2_phi_fit']:.3f} (on its own training half "
        f"{m['r2_phi_fit_train']:.3f}). "
        f"Ranking the candidates by the exact Q^pi: the agent picks the best at {m['exact_agrees_agent']:.0%} of states "
        f"(regret {m['exact_regret_agent']:.3f}), the lookahead on the model's w at {m['exact_agrees_model_w']:.0%} "
        f"({m['exact_regret_model_w']:.3f}), on the true w at {m['exact_agrees_true_w']:.0%} "
        f"({m['exact_regret_true_w']:.3f}). "
        f"Action set: on the exact Q^pi the candidates' best is {m['exact_gap_fine']:.4f} below the fine best "
        f"({m['exact_gap_fine_rel']:.1%} of V's spread; on V_true {m['vtrue_gap_fine']:.4f}, "
        f"{m['vtrue_gap_fine_rel']:.1%}), the agent's action within 1% of the fine best at "
        f"{m['exact_chosen_near_best']:.0%} of states, and the fine best action's mean |a| is "
        f"{m['exact_fine_best_abs']:.2f} of the half-range."
    )


def report(args: argparse.Namespace, rows: list[dict[str, Any]]) -> str:
    """The markdown report of all seeds."""
    env_id, reference = args.env_id, SAC_REFERENCE.get(args.env_id)
    columns = ["seed", "q", "C"]
    head, attribution_rows, means = attribution_table(rows, reference)
    endings_header, endings_rows = endings_table(rows)
    model_metrics = [m for m in MODEL_METRICS if not all(math.isnan(row[m]) for row in rows)]

    widths = f"phi's effective width on C (p = {rows[0].get('p')}): singular directions with 99% / 99.9% of its energy\n"

    def table(metrics: Sequence[str]) -> str:
        return markdown_table([*columns, *metrics], seed_table(rows, columns, metrics)) + "\n"

    sections = [
        f"# Where the agent loses on {env_id}: model, value, action set\n",
        f"Command: `{command_line()}`.\n",
        f'`CMEPolicyIteration("CMEPolicy", {env_id!r}, seed=seed, **{json.loads(args.kwargs)})` trained for {args.steps} '
        f"env steps. C: {args.collection} states of its episodes, half deterministic, half with its exploration noise "
        f"(simulator states recorded); the action set on {args.states} states of the deterministic half, the exact "
        f"Q^pi (rollouts of pi, gamma^H < 1e-3) on {args.exact_states} of those; returns over {EVAL_EPISODES} episodes "
        f"on an env seeded seed + {EVAL_SEED_OFFSET:,}. Every figure is defined in the module docstring of "
        "`benchmarks/diagnostics/gap_decomposition.py`.\n",
        f"## Returns (episodes cut after {args.max_steps} steps; the exact lookaheads over {args.exact_episodes} episodes, "
        f"the others over {EVAL_EPISODES})\n",
        table(RETURN_METRICS),
        f"The same policies over the first {args.exact_episodes} episodes (the same starts for all):\n",
        table(PAIRED_METRICS),
        f"Attribution on those first {args.exact_episodes} episodes: the return gained by each step (the last row: SAC's "
        f"full-length 20,000-step return, {reference}, minus the best lookahead's):\n",
        markdown_table(head, attribution_rows) + "\n",
        "## Model error at pi's actions (C's deterministic half; obs_error*: C's held-out half)\n",
        table(model_metrics),
        "## Value of pi: R^2 against Monte Carlo (C's held-out half)\n",
        table(VALUE_METRICS),
        *([widths, table(RANK_METRICS)] if all(key in row for row in rows for key in RANK_METRICS) else []),
        "## Action set, on the true one-step lookahead with V_true = <w_true, phi>\n",
        table(ACTION_METRICS),
        "## Action set and ranking, on the exact Q^pi (rollouts of pi from every successor)\n",
        table(EXACT_METRICS),
        table(RANKING_METRICS),
        "## Where the evaluation episodes end (mean over seeds; in brackets, the seeds with a value)\n",
        markdown_table(endings_header, endings_rows) + "\n",
        "## Verdict\n",
        summary_paragraph(env_id, rows, means, args.max_steps) + "\n",
    ]
    return "\n".join(sections)


def mujoco_parser(description: str) -> argparse.ArgumentParser:
    """The parser of a diagnostic on a MuJoCo env: ``--env-id`` (InvertedDoublePendulum-v5 by default) and the seed
    arguments, the stem left to the diagnostic (empty)."""
    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env-id", default="InvertedDoublePendulum-v5", help="a MuJoCo env id with a Box action space")
    add_seed_arguments(parser, "")
    return parser


def main() -> None:
    parser = mujoco_parser(__doc__)
    parser.add_argument("--collection", type=int, default=2_000, help="|C|: states for eq. (7), the model error and R^2")
    parser.add_argument("--states", type=int, default=500, help="states of C where the action set is measured on V_true")
    parser.add_argument("--exact-states", type=int, default=100, help="states of those where the exact Q^pi is rolled out")
    parser.add_argument("--rounds", type=int, default=5, help="rounds of policy iteration on the true transitions of C")
    parser.add_argument(
        "--exact-episodes", type=int, default=3, help="episodes of the exact lookaheads (and of the attribution)"
    )
    parser.add_argument("--max-steps", type=int, default=100, help="every evaluation episode is cut after this many steps")
    parser.set_defaults(workers=1)
    args = parser.parse_args()
    args.stem = args.stem or f"gap_decomposition_{args.env_id}"
    kwargs = json.loads(args.kwargs)
    fields = (
        *(args.steps, kwargs, args.collection, args.states, args.exact_states, args.rounds),
        *(args.exact_episodes, args.max_steps, args.stem),
    )
    rows = map_seeds(run_seed, [Job(args.env_id, seed, *fields) for seed in args.seeds], args.workers)
    write_markdown(args.stem, report(args, rows))


if __name__ == "__main__":
    main()
