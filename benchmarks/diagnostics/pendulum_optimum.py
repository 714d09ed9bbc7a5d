"""The optimal return of Pendulum-v1 on each seed's evaluation starts, and the agent's gap to it.

The learning-quality protocol evaluates every seed on 10 fixed random starts of its own
(:func:`cme_agent.experiment.make_eval_env`), so a seed's return depends on how hard its starts
are as much as on its policy. This script solves Pendulum-v1 by finite-horizon dynamic programming
on a fine (angle, angular velocity) grid with the simulator's own dynamics and the agent's
candidate torques, then flies that optimal policy through the same protocol (``evaluate_policy``
on the seed's evaluation env), and sets each seed's optimum beside the final returns of a
``benchmarks/learning_quality.py`` run:

    python -m benchmarks.diagnostics.pendulum_optimum --compare learning_quality_pendulum_1dc5c62
    python -m benchmarks.diagnostics.pendulum_optimum --grid 181 161 --stem pendulum_optimum_coarse   # the grid check

Writes ``results/<stem>.md``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Sequence

import numpy as np
from stable_baselines3.common.evaluation import evaluate_policy

from benchmarks.common import RESULTS, command_line, compose_config, markdown_table, write_markdown
from cme_agent.experiment import make_eval_env

GRAVITY, TIME_STEP, MAX_SPEED, MAX_TORQUE, HORIZON = 10.0, 0.05, 8.0, 2.0, 200
"""Pendulum-v1's constants (m = l = 1): m/s^2, s, rad/s, N m, steps of an episode."""


def angle_normalize(angle: np.ndarray) -> np.ndarray:
    """Angle in [-pi, pi) (rad), as Pendulum-v1's cost sees it."""
    return (angle + np.pi) % (2 * np.pi) - np.pi


def pendulum_step(angle: np.ndarray, speed: np.ndarray, torque: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pendulum-v1's transition and reward, elementwise.

    :param angle: angles (rad), any shape
    :param speed: angular velocities (rad/s), the same shape
    :param torque: the torque (N m), in [-2, 2]
    :return: next angle, next angular velocity, reward, each of the input's shape
    """
    reward = -(angle_normalize(angle) ** 2 + 0.1 * speed**2 + 0.001 * torque**2)
    next_speed = np.clip(speed + (1.5 * GRAVITY * np.sin(angle) + 3.0 * torque) * TIME_STEP, -MAX_SPEED, MAX_SPEED)
    return angle + next_speed * TIME_STEP, next_speed, reward


class Grid:
    """A periodic angle grid times an angular-velocity grid, with bilinear interpolation.

    :param n_angle: grid points over [-pi, pi) (periodic)
    :param n_speed: grid points over [-8, 8] rad/s
    """

    def __init__(self, n_angle: int, n_speed: int) -> None:
        self.n_angle, self.n_speed = n_angle, n_speed
        self.angles = np.linspace(-np.pi, np.pi, n_angle, endpoint=False)
        self.speeds = np.linspace(-MAX_SPEED, MAX_SPEED, n_speed)

    def interpolate(self, values: np.ndarray, angle: np.ndarray, speed: np.ndarray) -> np.ndarray:
        """``values`` (shape (n_angle, n_speed)) read at the points (angle, speed) (any shape)."""
        x = (angle_normalize(angle) + np.pi) / (2 * np.pi / self.n_angle)
        i0 = np.floor(x).astype(np.int64)
        fx = x - i0
        i0 %= self.n_angle
        i1 = (i0 + 1) % self.n_angle
        y = np.clip((speed + MAX_SPEED) / (self.speeds[1] - self.speeds[0]), 0.0, self.n_speed - 1 - 1e-9)
        j0 = np.floor(y).astype(np.int64)
        fy = y - j0
        j1 = np.minimum(j0 + 1, self.n_speed - 1)
        return (values[i0, j0] * (1 - fx) + values[i1, j0] * fx) * (1 - fy) + (
            values[i0, j1] * (1 - fx) + values[i1, j1] * fx
        ) * fy


def solve(grid: Grid, torques: np.ndarray, horizon: int = HORIZON) -> list[np.ndarray]:
    """Finite-horizon dynamic programming: ``values[k]`` is the optimal return with ``k`` steps to go.

    :param torques: the candidate torques (N m), shape (K,)
    :return: horizon + 1 arrays of shape (n_angle, n_speed), undiscounted (Pendulum's return)
    """
    angle, speed = np.meshgrid(grid.angles, grid.speeds, indexing="ij")
    transitions = [pendulum_step(angle, speed, float(torque)) for torque in torques]
    values = [np.zeros_like(angle)]
    for _ in range(horizon):
        best = np.full_like(angle, -np.inf)
        for next_angle, next_speed, reward in transitions:
            np.maximum(best, reward + grid.interpolate(values[-1], next_angle, next_speed), out=best)
        values.append(best)
    return values


class OptimalPendulumPolicy:
    """The greedy policy of the dynamic programme, with SB3's ``predict`` so that ``evaluate_policy``
    flies it like an agent. It counts the steps of the episode (Pendulum-v1 ends after 200).

    :param grid: the grid of ``values``
    :param values: :func:`solve`'s output
    :param torques: the candidate torques (N m), shape (K,)
    """

    def __init__(self, grid: Grid, values: list[np.ndarray], torques: np.ndarray) -> None:
        self.grid, self.values, self.torques, self.step = grid, values, torques, 0

    def predict(
        self,
        observation: np.ndarray,
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, None]:
        """Torque of shape (1, 1) for an observation (cos, sin, angular velocity) of shape (1, 3)."""
        if episode_start is not None and episode_start[0]:
            self.step = 0
        cos, sin, speed = observation[0]
        angle = np.arctan2(sin, cos)
        to_go = self.values[max(HORIZON - self.step - 1, 0)]
        scores = [
            reward + self.grid.interpolate(to_go, a, s)
            for a, s, reward in (pendulum_step(angle, speed, t) for t in self.torques)
        ]
        self.step += 1
        return np.array([[self.torques[int(np.argmax(scores))]]], dtype=np.float32), None


def optimal_returns(policy: OptimalPendulumPolicy, seed: int, episodes: int = 10) -> list[float]:
    """Returns of ``policy`` on seed ``seed``'s evaluation starts, by learning_quality's protocol."""
    env = make_eval_env(compose_config(["env=pendulum", f"seed={seed}"]))
    returns, _ = evaluate_policy(policy, env, n_eval_episodes=episodes, return_episode_rewards=True)
    env.close()
    return [float(r) for r in returns]


def agent_finals(stem: str) -> dict[int, float]:
    """Final evaluation return per seed of a learning_quality run saved in ``results/<stem>/`` (its records
    are ``pendulum_seed<k>.json`` with ``--envs pendulum``, ``Pendulum-v1_seed<k>.json`` with ``--env-id``)."""
    finals = {}
    folder = RESULTS / stem
    for path in sorted([*folder.glob("pendulum_seed*.json"), *folder.glob("Pendulum-v1_seed*.json")]):
        curve = json.loads(path.read_text())["curve"]
        finals[int(curve[-1]["seed"])] = float(curve[-1]["return_mean"])
    return finals


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", nargs="+", type=int, default=list(range(10)))
    parser.add_argument("--grid", nargs=2, type=int, default=[361, 321], metavar=("N_ANGLE", "N_SPEED"))
    parser.add_argument(
        "--torques", type=int, default=21, help="candidate torques, evenly spaced over [-2, 2] (the preset's 21)"
    )
    parser.add_argument("--compare", nargs="*", default=[], help="learning_quality stems whose final returns to set beside")
    parser.add_argument("--stem", default="pendulum_optimum")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    grid, torques = Grid(*args.grid), np.linspace(-MAX_TORQUE, MAX_TORQUE, args.torques)
    policy = OptimalPendulumPolicy(grid, solve(grid, torques), torques)
    optimum = {seed: optimal_returns(policy, seed) for seed in args.seeds}
    finals = {stem: agent_finals(stem) for stem in args.compare}
    header = ["seed", "optimum (mean of 10 starts)", "per start", *(f"{stem}: final (gap)" for stem in args.compare)]
    rows = []
    for seed, returns in optimum.items():
        mean = statistics.mean(returns)
        cells = [f"{finals[s][seed]:.1f} ({finals[s][seed] - mean:+.1f})" if seed in finals[s] else "-" for s in args.compare]
        rows.append([seed, f"{mean:.1f}", ", ".join(f"{r:.0f}" for r in returns), *cells])
    means = [statistics.mean(r) for r in optimum.values()]
    summary = [
        f"Optimum over the seeds: mean {statistics.mean(means):.1f}, worst seed {min(means):.1f}, best {max(means):.1f}."
    ]
    for stem in args.compare:
        gaps = [finals[stem][seed] - statistics.mean(optimum[seed]) for seed in optimum if seed in finals[stem]]
        if gaps:
            summary.append(
                f"`{stem}`: gap to the optimum mean {statistics.mean(gaps):+.1f}, "
                f"largest {min(gaps):+.1f} ({len(gaps)} seeds)."
            )
    write_markdown(
        args.stem,
        f"# Pendulum-v1: the optimum on each seed's evaluation starts\n\nCommand: `{command_line()}`.\n\n"
        f"Finite-horizon dynamic programming ({HORIZON} steps, undiscounted: the env's return) on a {args.grid[0]} x "
        f"{args.grid[1]} grid of angle x angular velocity with Pendulum-v1's dynamics and {args.torques} candidate torques, "
        "bilinear interpolation; its greedy policy flown by `evaluate_policy` on each seed's evaluation env "
        "(`make_eval_env`: the fixed starts of `benchmarks/learning_quality.py`, 10 episodes). A gap is a final "
        f"return minus the seed's optimum. {time.perf_counter() - start:.0f} s.\n\n"
        + " ".join(summary)
        + "\n\n"
        + markdown_table(header, rows)
        + "\n",
    )


if __name__ == "__main__":
    main()
