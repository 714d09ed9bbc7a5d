"""Is it the model or the planner? The agent's planning step redone with the true dynamics.

PointGoal2D-v0 (``cme_agent/envs/point_goal.py``) has its dynamics and reward in closed form
(``PointGoal2D.transition``). This script trains ``CMEPolicyIteration("CMEPolicy",
"PointGoal2D-v0", seed=seed)`` (library defaults, plus ``--kwargs``) for ``--steps`` env steps,
draws a collection C as the agent does (``draw_collection``: a ``uniform_fraction`` of it uniform
over the observation box, the rest from D) and takes the agent's greedy policy pi there. Then:

- **value**: the weights w of V^pi(s) = <w, phi(s)> by eq. (7) (Bellman residual minimisation with
  the agent's ridge), once through the model (E_model[phi(S') | s, pi(s)] and the model's reward,
  what the agent solves) and once through the true dynamics (phi of the true next state, the true
  reward); each scored by R^2 against the Monte-Carlo value of pi on C (true rollouts of pi,
  ``horizon`` steps, gamma^horizon < 1e-3);
- **return** (10 episodes on an env seeded seed + 10,000, as unseen_envs.py) of the agent, and of
  the one-step lookahead through the true dynamics, argmax_a r(s, a) + gamma <w, phi(s')> over the
  agent's candidate actions, on the model's w and on the true w. Agent -> lookahead on the model's
  w: what the model's error costs in the improvement step; lookahead on the model's w -> on the true
  w: what it costs in the evaluation step; the true w's return is what this phi, C and candidate
  set can do from pi in one round of policy iteration with a perfect model, and
  ``return_true_iterated`` what they do after ``--rounds`` more rounds on the true dynamics (each
  round evaluates the lookahead policy of the last w on C by eq. (7), as the agent's rounds do);
- **model error** on C at pi's actions, apart on C's uniform and data parts: the mean of
  |E_model[phi(S')] - phi(s')| over the mean true change |phi(s') - phi(s)|, and the RMS error of
  the model's reward.

Writes results/<stem>.md.

    python -m benchmarks.diagnostics.true_dynamics_planning --seeds 0 1 2 --steps 5000
"""

from __future__ import annotations

import argparse
import json
import math
from typing import Any

import numpy as np
import torch
from stable_baselines3.common.env_util import make_vec_env

from benchmarks.common import add_seed_arguments, command_line, map_seeds, markdown_table, seed_table, with_cme, write_markdown
from benchmarks.unseen_envs import CUSTOM_ENV, EVAL_EPISODES, EVAL_SEED_OFFSET, evaluate
from cme_agent import CMEPolicyIteration
from cme_agent.envs.point_goal import PointGoal2D
from cme_agent.planning import bellman_residual_weights

METRICS = (
    "return_agent",
    "return_lookahead_model_w",
    "return_lookahead_true_w",
    "return_true_iterated",
    "r2_model_w",
    "r2_true_w",
    "phi_error_uniform",
    "phi_error_data",
    "reward_rmse_uniform",
    "reward_rmse_data",
)


class Lookahead:
    """argmax_a r(s, a) + gamma <w, phi(s')> over the candidates through the true dynamics, with
    SB3's ``predict``.

    :param agent: the trained agent (its phi, candidates and gamma)
    :param weights: (p,) value weights w
    """

    def __init__(self, agent: CMEPolicyIteration, weights: torch.Tensor) -> None:
        self.agent, self.weights = agent, weights
        self.candidates = agent.policy.candidates.numpy().astype(np.float64)  # (K, act_dim)
        self.env = PointGoal2D()

    def predict(self, observation: np.ndarray, state: Any = None, episode_start: Any = None, deterministic: bool = True):
        """(N, 4) observations -> (N, 2) actions."""
        n, k = len(observation), len(self.candidates)
        states = np.repeat(np.asarray(observation, dtype=np.float64), k, axis=0)
        successors, rewards = self.env.transition(states, np.tile(self.candidates, (n, 1)))
        values = phi_of(self.agent, successors) @ self.weights
        scores = rewards.reshape(n, k) + self.agent.gamma * values.numpy().reshape(n, k)
        return self.candidates[scores.argmax(axis=1)].astype(np.float32), None


def rollout_horizon(gamma: float) -> int:
    """H, the length of a Monte-Carlo rollout: the least with gamma^H < 1e-3."""
    return math.ceil(math.log(1e-3) / math.log(gamma))


def phi_of(agent: CMEPolicyIteration, states: np.ndarray) -> torch.Tensor:
    """phi(s) of the agent: (N, 4) states -> (N, p), float32."""
    with torch.no_grad():
        return agent.dynamics.phi(torch.as_tensor(states, dtype=torch.float32))


def greedy_actions(agent: CMEPolicyIteration, states: np.ndarray) -> np.ndarray:
    """pi(s), the agent's greedy actions: (N, 4) -> (N, 2)."""
    with torch.no_grad():
        return agent.policy.greedy(torch.as_tensor(states, dtype=torch.float32))[0].numpy().astype(np.float64)


def monte_carlo_values(agent: CMEPolicyIteration, states: np.ndarray, horizon: int) -> np.ndarray:
    """V^pi(s) = sum_t gamma^t r_t over ``horizon`` true steps of pi: (N, 4) -> (N,)."""
    env, values, discount = PointGoal2D(), np.zeros(len(states)), 1.0
    for _ in range(horizon):
        states, rewards = env.transition(states, greedy_actions(agent, states))
        values += discount * rewards
        discount *= agent.gamma
    return values


def true_policy_iteration(
    agent: CMEPolicyIteration, states: np.ndarray, phi: torch.Tensor, weights: torch.Tensor, rounds: int
) -> torch.Tensor:
    """``rounds`` rounds of policy iteration on the true dynamics from value weights w: each the
    lookahead policy of w on C, evaluated by eq. (7) on its true transitions.

    :param states: (|C|, 4) the collection C
    :param phi: (|C|, p) phi of C
    :param weights: (p,) the first w
    :return: (p,) the last w
    """
    env, blocks = PointGoal2D(), np.array_split(states, max(1, len(states) // 1000))  # (1000 * K, p) at a time
    for _ in range(rounds):
        policy = Lookahead(agent, weights)
        actions = np.concatenate([policy.predict(block)[0] for block in blocks])
        successors, rewards = env.transition(states, actions.astype(np.float64))
        rewards = torch.as_tensor(rewards, dtype=torch.float32)
        weights = bellman_residual_weights(phi, phi_of(agent, successors), rewards, agent.gamma, agent.evaluation_config.l2)
    return weights


def r_squared(weights: torch.Tensor, phi: torch.Tensor, targets: np.ndarray) -> float:
    """R^2 of <w, phi(s)> against ``targets``: (p,), (N, p), (N,)."""
    residual = (phi @ weights).numpy().astype(np.float64) - targets
    return float(1.0 - (residual**2).mean() / targets.var())


def run_seed(job: tuple[int, int, dict[str, Any], int]) -> dict[str, Any]:
    """Train one agent and measure it: (seed, steps, kwargs, rounds) -> its row."""
    seed, steps, kwargs, rounds = job
    torch.set_num_threads(1)
    agent = CMEPolicyIteration("CMEPolicy", CUSTOM_ENV, seed=seed, **with_cme(kwargs)).learn(steps)
    dynamics, gamma, l2 = agent.dynamics, agent.gamma, agent.evaluation_config.l2
    with torch.no_grad():
        collection = agent.draw_collection()  # (|C|, 4)
        states = collection.numpy().astype(np.float64)
        actions = greedy_actions(agent, states)
        successors, rewards = PointGoal2D().transition(states, actions)
        phi, true_next = phi_of(agent, states), phi_of(agent, successors)
        action_tensor = torch.as_tensor(actions, dtype=torch.float32)
        psi = dynamics.features(collection, action_tensor)
        model_rewards = dynamics.expected_reward(collection, action_tensor, phi, psi)
        model_next, _ = dynamics.read(phi, psi @ dynamics.readout())
        true_rewards = torch.as_tensor(rewards, dtype=torch.float32)
        weights = {
            "model_w": bellman_residual_weights(phi, model_next, model_rewards, gamma, l2),
            "true_w": bellman_residual_weights(phi, true_next, true_rewards, gamma, l2),
        }
        iterated = true_policy_iteration(agent, states, phi, weights["true_w"], rounds)
    values = monte_carlo_values(agent, states, rollout_horizon(gamma))
    eval_env = make_vec_env(CUSTOM_ENV, n_envs=1, seed=seed + EVAL_SEED_OFFSET)
    row: dict[str, Any] = {"seed": seed, "q": dynamics.q, "C": len(states)}
    row["return_agent"] = evaluate(agent, eval_env, EVAL_EPISODES)["return_mean"]
    for name, w in weights.items():
        eval_env.seed(seed + EVAL_SEED_OFFSET)
        row[f"return_lookahead_{name}"] = evaluate(Lookahead(agent, w), eval_env, EVAL_EPISODES)["return_mean"]
        row[f"r2_{name}"] = r_squared(w, phi, values)
    eval_env.seed(seed + EVAL_SEED_OFFSET)
    row["return_true_iterated"] = evaluate(Lookahead(agent, iterated), eval_env, EVAL_EPISODES)["return_mean"]
    n_uniform = round(agent.evaluation_config.uniform_fraction * len(states))
    errors = (model_next - true_next).norm(dim=1)
    changes = (true_next - phi).norm(dim=1)
    reward_errors = model_rewards - true_rewards
    for part, rows in (("uniform", slice(0, n_uniform)), ("data", slice(n_uniform, None))):
        row[f"phi_error_{part}"] = float(errors[rows].mean() / changes[rows].mean())
        row[f"reward_rmse_{part}"] = float(reward_errors[rows].square().mean().sqrt())
    print(seed, {key: round(float(row[key]), 3) for key in METRICS}, flush=True)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_seed_arguments(parser, "true_dynamics_planning")
    parser.add_argument(
        "--rounds", type=int, default=5, help="rounds of policy iteration on the true dynamics after the first"
    )
    args = parser.parse_args()
    kwargs = json.loads(args.kwargs)
    rows = map_seeds(run_seed, [(seed, args.steps, kwargs, args.rounds) for seed in args.seeds], args.workers)
    columns = ["seed", "q", "C"]
    header, table = [*columns, *METRICS], seed_table(rows, columns, METRICS)
    text = (
        f"# Is it the model or the planner? {CUSTOM_ENV}, the planning step with the true dynamics\n\n"
        f"Command: `{command_line()}`.\n\n"
        f'`CMEPolicyIteration("CMEPolicy", {CUSTOM_ENV!r}, seed=seed, **{kwargs})` trained for {args.steps} env '
        "steps; C drawn as the agent draws it, pi its greedy policy. return_agent: the agent's deterministic "
        f"return ({EVAL_EPISODES} episodes, env seeded seed + {EVAL_SEED_OFFSET:,}); return_lookahead_model_w / "
        "_true_w: the one-step lookahead through the true dynamics over the agent's candidates on the value "
        "weights of pi solved by eq. (7) through the model / through the true next states and rewards (same "
        f"C, same ridge); return_true_iterated: the same lookahead after {args.rounds} more rounds of policy "
        "iteration on the true dynamics (each round's lookahead policy evaluated on C by eq. (7)); "
        "r2_*: those values against the Monte-Carlo value of pi on C; phi_error_*: mean "
        "|E_model[phi(S')] - phi(s')| over mean |phi(s') - phi(s)| on C's uniform / data part at pi's "
        "actions; reward_rmse_*: RMS error of the model's reward there.\n\n" + markdown_table(header, table) + "\n"
    )
    write_markdown(args.stem, text)


if __name__ == "__main__":
    main()
