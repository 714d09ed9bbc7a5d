"""The learned reward's error along a run on PointGoal2D-v0 (a diagnostic).

PointGoal2D-v0 (``cme_agent/envs/point_goal.py``) is the unseen-env suite's env whose reward comes
only from the env, so the agent learns it as B's reward row; its true expected reward is known
in closed form (``true_reward``). Trains ``CMEPolicyIteration("CMEPolicy", "PointGoal2D-v0")``
with ``--kwargs`` and, every 1,000 env steps, evaluates the deterministic policy (10 episodes,
seeded apart from training) and measures the model's expected reward minus the true one at
2,000 states of D and 2,000 states drawn uniformly over the observation box, each with uniformly
random actions and with the agent's own (greedy) actions: mean (bias), mean absolute and largest
error. Positive errors at greedy actions are what the planner exploits. Writes
results/<stem>.md and results/<stem>.csv.

    python -m benchmarks.diagnostics.reward_model_error --seed 2 --steps 16000 --stem reward_model_error_pg_s2
    python -m benchmarks.diagnostics.reward_model_error --seed 2 --kwargs '{"model_update": {"l2": 0.001}}' --stem ...
"""

from __future__ import annotations

import argparse
import json
from typing import Any

import gymnasium as gym
import torch
from stable_baselines3.common.callbacks import BaseCallback

from benchmarks.common import command_line, markdown_table, with_cme, write_report
from benchmarks.learning_quality import episode_returns
from benchmarks.unseen_envs import CUSTOM_ENV, EVAL_SEED_OFFSET
from cme_agent import CMEPolicyIteration
from cme_agent.envs.point_goal import PointGoal2D

STATES = 2000
"""States of each kind (from D, uniform over the box) the error is measured at."""


def true_reward(env: PointGoal2D, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """PointGoal2D's reward of one step from ``obs`` (N, 4) with ``actions`` (N, 2): (N,)."""
    return torch.as_tensor(env.transition(obs.double().numpy(), actions.double().numpy())[1])


def model_reward(model: CMEPolicyIteration, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """The model's expected reward r(s, a) at ``obs`` (N, 4) and ``actions`` (N, 2): (N,)."""
    dynamics = model.dynamics
    with torch.no_grad():
        return dynamics.expected_reward(obs, actions, dynamics.phi(obs), dynamics.features(obs, actions)).double()


def evaluate(model: CMEPolicyIteration, seed: int) -> float:
    """Mean return of the deterministic policy over 10 episodes seeded apart from training."""
    env = gym.make(CUSTOM_ENV)
    env.reset(seed=seed + EVAL_SEED_OFFSET)
    try:
        return episode_returns(model, env)["return_mean"]
    finally:
        env.close()


class RewardErrorProbe(BaseCallback):
    """Every ``every`` env steps, when an iteration's data are collected (before the model learns
    from them: the model and policy measured are those that collected them): the evaluation and
    the reward errors.

    :param seed: the run's seed (evaluation episodes and the probe's draws derive from it)
    :param every: env steps between measurements
    """

    def __init__(self, seed: int, every: int = 1000) -> None:
        super().__init__()
        self.seed, self.every = seed, every
        self.env = PointGoal2D()
        self.rows: list[dict[str, Any]] = []

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        model = self.model
        steps = model.num_timesteps
        if steps == 0 or steps % self.every or model.dynamics.obs_encoder.needs_fit:
            return
        generator = torch.Generator().manual_seed(self.seed)
        data = model.store.get(torch.randint(0, len(model.store), (STATES,), generator=generator)).obs.float()
        uniform = model.dynamics.obs_encoder.sample_uniform(STATES, generator).float()
        row: dict[str, Any] = {"steps": steps, "return_mean": round(evaluate(model, self.seed), 1), "q": model.dynamics.q}
        for where, states in (("data", data), ("uniform", uniform)):
            random_actions = torch.rand(STATES, 2, generator=generator) * 2 - 1
            greedy_actions = torch.as_tensor(model.predict(states.numpy(), deterministic=True)[0]).float()
            for which, actions in (("random", random_actions), ("greedy", greedy_actions)):
                error = model_reward(model, states, actions) - true_reward(self.env, states, actions)
                row[f"{where}_{which}_bias"] = round(float(error.mean()), 3)
                row[f"{where}_{which}_mae"] = round(float(error.abs().mean()), 3)
                row[f"{where}_{which}_max"] = round(float(error.max()), 2)
        row["box_half_range"] = [round(float(h), 2) for h in model.dynamics.obs_encoder.half_range]
        print(row, flush=True)
        self.rows.append(row)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=2)
    parser.add_argument("--steps", type=int, default=16_000)
    parser.add_argument("--kwargs", default="{}", help="constructor arguments of CMEPolicyIteration, as JSON")
    parser.add_argument("--stem", default="reward_model_error")
    args = parser.parse_args()
    torch.set_num_threads(1)
    model = CMEPolicyIteration("CMEPolicy", CUSTOM_ENV, seed=args.seed, verbose=0, **with_cme(json.loads(args.kwargs)))
    probe = RewardErrorProbe(args.seed)
    model.learn(args.steps, callback=probe)
    header = ["steps", "return", "q"] + [
        f"{where} {which} {stat}"
        for where in ("data", "uniform")
        for which in ("random", "greedy")
        for stat in ("bias", "mae", "max")
    ]
    rows = [[value for key, value in row.items() if key != "box_half_range"] for row in probe.rows]
    text = (
        f"# The learned reward's error on {CUSTOM_ENV}, seed {args.seed}\n\nCommand: `{command_line()}`\n\n"
        f"Constructor arguments: `{args.kwargs}`. Every 1,000 env steps: 'return' = the deterministic policy's mean "
        f"over 10 episodes; then the model's expected reward minus the true one at {STATES} states of D and {STATES} "
        "states uniform over the observation box, with uniformly random actions and with the agent's greedy "
        "actions: mean (bias), mean absolute (mae) and largest (max) error.\n\n"
        + markdown_table(header, rows)
        + "\n\nObservation box half-ranges (x, y, vx, vy) per row: "
        + "; ".join(f"{row['steps']}: {row['box_half_range']}" for row in probe.rows)
        + "\n"
    )
    write_report(args.stem, text, [probe.rows])


if __name__ == "__main__":
    main()
