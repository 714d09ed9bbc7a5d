"""Scripted reference controller for Quadcopter-v0: fly towards the target.

A baseline and a sanity check of the task: if this cannot reach the target and hover
there, neither can a learned policy.
"""

from typing import Any

import gymnasium as gym
import numpy as np

from cme_agent.envs.quadcopter import ArrayLike3, QuadcopterEnv


class QuadcopterPController:
    """Proportional position controller: desired velocity ``gain * (target - position)``.

    The desired velocity is scaled down, keeping its direction, so that its norm is at most
    ``speed_limit``, then divided by ``max_speed`` and clipped to [-1, 1] per axis, which
    is the environment's action. It has SB3's ``predict`` signature, so
    ``stable_baselines3.common.evaluation.evaluate_policy(controller, env)`` works.

    :param target: target position in NED (m), shape ``(3,)``.
    :param max_speed: the environment's speed at action 1 (m/s).
    :param gain: proportional gain (1/s).
    :param speed_limit: largest desired speed (m/s); ``max_speed`` when None.
    """

    def __init__(
        self,
        target: ArrayLike3,
        max_speed: float,
        gain: float = 1.0,
        speed_limit: float | None = None,
    ) -> None:
        self.target = np.array(target, dtype=np.float64)
        if self.target.shape != (3,):
            raise ValueError(f"target must have shape (3,), got {self.target.shape}")
        for name, value in (("max_speed", max_speed), ("gain", gain), ("speed_limit", speed_limit)):
            if value is not None and not value > 0:
                raise ValueError(f"{name} must be positive, got {value!r}")
        self.max_speed = float(max_speed)
        self.gain = float(gain)
        self.speed_limit = self.max_speed if speed_limit is None else float(speed_limit)

    @classmethod
    def from_env(cls, env: gym.Env, **kwargs: Any) -> "QuadcopterPController":
        """A controller for a (possibly wrapped) Quadcopter-v0 environment.

        :param env: the environment, whose unwrapped env is a ``QuadcopterEnv``.
        :param kwargs: ``gain`` and ``speed_limit``, see the class.
        """
        quadcopter = env.unwrapped
        if not isinstance(quadcopter, QuadcopterEnv):
            raise TypeError(f"env must be a QuadcopterEnv, got {type(quadcopter).__name__}")
        return cls(quadcopter.target, quadcopter.max_speed, **kwargs)

    def action(self, observation: np.ndarray) -> np.ndarray:
        """Actions for a batch of observations.

        :param observation: observations, shape ``(N, 13)``.
        :return: actions in [-1, 1], shape ``(N, 3)``, float32.
        """
        velocity = self.gain * (self.target - observation[:, :3])
        speed = np.linalg.norm(velocity, axis=1, keepdims=True)
        velocity *= np.minimum(1.0, self.speed_limit / np.maximum(speed, 1e-12))
        return np.clip(velocity / self.max_speed, -1.0, 1.0).astype(np.float32)

    def predict(
        self,
        observation: np.ndarray,
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, None]:
        """SB3-style prediction.

        :param observation: one observation ``(13,)`` or a batch ``(N, 13)``.
        :param state: unused (the controller is stateless).
        :param episode_start: unused.
        :param deterministic: unused (the controller is deterministic).
        :return: the action ``(3,)`` or actions ``(N, 3)``, and None for the state.
        """
        observation = np.asarray(observation, dtype=np.float64)
        actions = self.action(observation.reshape(-1, observation.shape[-1]))
        return (actions[0] if observation.ndim == 1 else actions), None
