"""PointGoal2D-v0: a damped 2-D point mass that must reach a goal position only the env knows.

A small continuous-control task whose reward the agent has to learn (no ``reward_function``):
the goal appears in the reward, not in the observation. Its dynamics and reward are deterministic
and in closed form (:meth:`PointGoal2D.transition`), so what an agent learns can be checked
against the truth.
"""

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

ACTION_COST = 0.05
"""Weight of the squared force in the reward (reward units per unit of force squared)."""


class PointGoal2D(gym.Env[np.ndarray, np.ndarray]):
    """Push a point mass in the plane to a fixed goal and keep it there.

    **Observation**: ``(x, y, vx, vy)``, position and velocity, ``Box(-inf, inf, (4,))``,
    float32 (the float64 state rounded).

    **Action**: a force ``a = (ax, ay)``, ``Box(-1, 1, (2,))``, float32; a force outside
    [-1, 1]^2 is clipped to it.

    **Transition**: deterministic, ``v' = damping * v + dt * a`` then ``p' = p + dt * v'``.

    **Reward**: ``-|p' - goal| - 0.05 |a|^2`` of the position *after* the step and the clipped
    force (``|.|`` the Euclidean norm): at most 0, at the goal at rest.

    **Episode end**: never terminated; ``PointGoal2D-v0`` is truncated after 100 steps by the
    ``TimeLimit`` wrapper of ``gymnasium.make`` (the env itself never truncates).

    **Start**: position uniform in [-1, 1]^2 drawn from ``self.np_random`` (so ``reset(seed=s)``
    repeats it), velocity zero.

    :param goal: the goal position ``(x, y)``, shape ``(2,)``, in position units.
    :param dt: time step of one env step (time units).
    :param damping: fraction of the velocity kept from one step to the next, in [0, 1].
    """

    metadata: dict[str, Any] = {"render_modes": []}  # noqa: RUF012
    observation_names = ("x", "y", "vx", "vy")
    """A name per observation dim (the TensorBoard pictures' axes)."""

    def __init__(self, goal: tuple[float, float] = (0.6, -0.4), dt: float = 0.1, damping: float = 0.9) -> None:
        self.observation_space = spaces.Box(-np.inf, np.inf, (4,), np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.goal = np.asarray(goal, dtype=np.float64)
        self.dt, self.damping = dt, damping
        self.state = np.zeros(4)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Start at a uniform random position in [-1, 1]^2, at rest.

        :param seed: seed of ``self.np_random`` (None: keep the current generator).
        :param options: unused.
        :return: the observation, shape ``(4,)``, float32, and an empty info dict.
        """
        super().reset(seed=seed)
        self.state = np.concatenate([self.np_random.uniform(-1.0, 1.0, 2), np.zeros(2)])
        return self.state.astype(np.float32), {}

    def transition(self, states: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The dynamics and reward on a batch, without touching the env's state.

        :param states: states ``(x, y, vx, vy)``, shape ``(N, 4)``.
        :param actions: forces, shape ``(N, 2)``, clipped to [-1, 1].
        :return: the next states, shape ``(N, 4)``, float64, and the rewards, shape ``(N,)``.
        """
        force = np.clip(np.asarray(actions, dtype=np.float64), -1.0, 1.0)
        velocity = self.damping * states[:, 2:] + self.dt * force
        successors = np.concatenate([states[:, :2] + self.dt * velocity, velocity], axis=1)
        offset = successors[:, :2] - self.goal
        return successors, -np.sqrt(_row_dots(offset)) - ACTION_COST * _row_dots(force)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """One step of :meth:`transition` from the current state.

        :param action: the force, shape ``(2,)``.
        :return: observation ``(4,)`` float32, reward, terminated (always False), truncated
            (always False), an empty info dict.
        """
        successors, rewards = self.transition(self.state[None], np.asarray(action)[None])
        self.state = successors[0]
        return self.state.astype(np.float32), float(rewards[0]), False, False, {}


def _row_dots(rows: np.ndarray) -> np.ndarray:
    """(N, d) -> (N,) each row's dot product with itself, computed as a 1-D ``x @ x`` is (so
    that a batch of one repeats the env's step bit for bit)."""
    return (rows[:, None, :] @ rows[:, :, None])[:, 0, 0]
