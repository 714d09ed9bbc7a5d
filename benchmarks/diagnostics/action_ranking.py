"""Does the learned model tell the actions apart? One-step Q under the model vs under the simulator.

The agent chooses actions by ``Q^(s, a) = r(s, a) + gamma <w, E_model[phi(S') | s, a]>``. This
script trains ``CMEPolicyIteration("CMEPolicy", env_id, seed=seed)`` (library defaults, plus
``--kwargs``), then takes ``--states`` states from the agent's own episodes (its deterministic
action plus Gaussian noise of ``--noise`` action units, so the states are the ones it meets)
and, at each, ``--actions`` actions evenly spaced over the action box. For each (s, a) it
compares the agent's Q^ with the same backup on the true next state: the simulator is reset to
s (MuJoCo's ``set_state``) and stepped with a, giving ``r + gamma <w, phi(s')>`` (0 after
termination), with the agent's own value weights w. Only the model differs between the two.

Per seed it reports R^2 of Q^ over all (s, a); within each state, with both centred on their
mean over the actions (what the greedy step compares), their correlation, the spread of the
true and of the model's gaps (std) and the RMS of their difference; and the share of states at
which the model's best action is the true best. Writes results/<stem>.md.

    python -m benchmarks.diagnostics.action_ranking                     # InvertedPendulum-v5, seeds 0-2
    python -m benchmarks.diagnostics.action_ranking --kwargs '{"gamma": 0.95}' --stem action_ranking_gamma95
"""

from __future__ import annotations

import argparse
import json
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from benchmarks.common import add_seed_arguments, command_line, map_seeds, markdown_table, seed_table, with_cme, write_markdown
from cme_agent import CMEPolicyIteration

METRICS = ("r2", "centred_corr", "best_agrees", "true_gap_std", "model_gap_std", "gap_rmse")


def visited_states(agent: CMEPolicyIteration, env: gym.Env, n: int, noise: float, seed: int) -> list[tuple[np.ndarray, ...]]:
    """(qpos, qvel, obs) of n states from the agent's noised episodes on a MuJoCo env."""
    rng, low, high = np.random.default_rng(seed), env.action_space.low, env.action_space.high
    obs, _ = env.reset(seed=seed)
    states = []
    while len(states) < n:
        data = env.unwrapped.data
        states.append((data.qpos.copy(), data.qvel.copy(), obs.copy()))
        action, _ = agent.predict(obs, deterministic=True)
        action = np.clip(action + rng.normal(0.0, noise, size=action.shape), low, high).astype(np.float32)
        obs, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            obs, _ = env.reset(seed=int(rng.integers(2**31)))
    return states


@torch.no_grad()
def one_step_values(
    agent: CMEPolicyIteration, env: gym.Env, states: list[tuple[np.ndarray, ...]], actions: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Q under the simulator and under the model at every state and action: two (n_states, n_actions) arrays."""
    dynamics, weights, gamma = agent.dynamics, agent.evaluator.value_weights, agent.gamma
    true_q, model_q = np.empty((len(states), len(actions))), np.empty((len(states), len(actions)))
    action_batch = torch.as_tensor(actions, dtype=torch.float32)
    for i, (qpos, qvel, obs) in enumerate(states):
        steps = []
        for action in actions:
            env.unwrapped.set_state(qpos, qvel)
            successor, reward, terminated, _, _ = env.step(action)
            steps.append((successor, reward, terminated))
        successors, rewards, terminated = (np.asarray(column) for column in zip(*steps, strict=True))
        next_values = (dynamics.phi(torch.as_tensor(successors, dtype=torch.float32)) @ weights).numpy()
        true_q[i] = rewards + gamma * np.where(terminated, 0.0, next_values)
        obs_batch = torch.as_tensor(obs, dtype=torch.float32).expand(len(actions), -1)
        phi, psi = dynamics.phi(obs_batch), dynamics.features(obs_batch, action_batch)
        expected_next_value = dynamics.expected_next_phi(phi, psi) @ weights
        model_q[i] = (dynamics.expected_reward(obs_batch, action_batch, phi, psi) + gamma * expected_next_value).numpy()
    return true_q, model_q


def ranking_metrics(true_q: np.ndarray, model_q: np.ndarray) -> dict[str, float]:
    """The report's figures from the two (n_states, n_actions) Q arrays."""
    r2 = 1 - ((true_q - model_q) ** 2).sum() / ((true_q - true_q.mean()) ** 2).sum()
    true_gap, model_gap = true_q - true_q.mean(1, keepdims=True), model_q - model_q.mean(1, keepdims=True)
    corr = (true_gap * model_gap).sum() / np.sqrt((true_gap**2).sum() * (model_gap**2).sum())
    return {
        "r2": float(r2),
        "centred_corr": float(corr),
        "best_agrees": float(np.mean(true_q.argmax(1) == model_q.argmax(1))),
        "true_gap_std": float(true_gap.std()),
        "model_gap_std": float(model_gap.std()),
        "gap_rmse": float(np.sqrt(((true_gap - model_gap) ** 2).mean())),
    }


def run_seed(job: tuple[str, int, int, dict[str, Any], int, int, float]) -> dict[str, Any]:
    """Train one agent and measure it: (env_id, seed, steps, kwargs, n_states, n_actions, noise) -> its row."""
    env_id, seed, steps, kwargs, n_states, n_actions, noise = job
    torch.set_num_threads(1)
    agent = CMEPolicyIteration("CMEPolicy", env_id, seed=seed, **with_cme(kwargs)).learn(steps)
    env = gym.make(env_id)
    if not hasattr(env.unwrapped, "set_state"):
        raise ValueError(f"{env_id} is not a MuJoCo env: this benchmark resets the simulator with set_state")
    box = env.action_space
    actions = np.linspace(box.low, box.high, n_actions, dtype=np.float32)
    states = visited_states(agent, env, n_states, noise * float(np.mean(box.high - box.low)) / 2, seed + 10_000)
    metrics = ranking_metrics(*one_step_values(agent, env, states, actions))
    print(env_id, seed, {key: round(value, 3) for key, value in metrics.items()}, flush=True)
    return {"seed": seed, "q": agent.q, **metrics}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="InvertedPendulum-v5", help="a MuJoCo env id with a Box action space")
    add_seed_arguments(parser, "action_ranking")
    parser.add_argument("--states", type=int, default=300)
    parser.add_argument("--actions", type=int, default=7, help="actions per state, evenly spaced over the box")
    parser.add_argument(
        "--noise", type=float, default=0.25, help="behaviour noise std, as a fraction of the action half-range"
    )
    args = parser.parse_args()
    kwargs = json.loads(args.kwargs)
    jobs = [(args.env, seed, args.steps, kwargs, args.states, args.actions, args.noise) for seed in args.seeds]
    rows = map_seeds(run_seed, jobs, args.workers)
    header, table = ["seed", "q", *METRICS], seed_table(rows, ["seed", "q"], METRICS)
    text = (
        f"# Does the model tell the actions apart? {args.env}\n\n"
        f"Command: `{command_line()}`.\n\n"
        f'`CMEPolicyIteration("CMEPolicy", {args.env!r}, seed=seed, **{kwargs})` trained for {args.steps} env steps; '
        f"{args.states} states of its own episodes (noise {args.noise} of the action half-range), "
        f"{args.actions} actions each. "
        "Q under the simulator is `r + gamma <w, phi(s')>` on the true next state, under the model "
        "`r_model + gamma <w, E_model[phi(S')]>`, with the agent's own value weights w. r2: over all (s, a); "
        "centred_corr, true_gap_std, model_gap_std, gap_rmse: of Q minus its mean over the actions at the same "
        "state; best_agrees: share of states where the model's best action is the true best.\n\n"
        + markdown_table(header, table)
        + "\n"
    )
    write_markdown(args.stem, text)


if __name__ == "__main__":
    main()
