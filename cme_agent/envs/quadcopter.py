"""Quadcopter-v0: navigation of the simulated AscTec Pelican to a fixed target.

The paper's fourth experiment (PAPER.md section 3.2); the model is that of
``QUADCOPTER.md``, implemented in :mod:`cme_agent.envs.quadcopter_dynamics`.
"""

import math
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from cme_agent.envs import quadcopter_dynamics as dyn
from cme_agent.envs.quadcopter_render import render_frame

ArrayLike3 = Sequence[float] | np.ndarray

OBSERVATION_POSITION_MARGIN = 1.0  # m, room outside the bounding box for terminal states
OBSERVATION_MAX_SPEED = 15.0  # m/s, body-frame linear velocities
OBSERVATION_MAX_RATE = 2.0 * math.pi  # rad/s, body angular rates
OBSERVATION_MAX_THRUST = 50.0  # N, above the battery's ceiling of about 32.9 N


def quadcopter_reward(
    position: torch.Tensor | np.ndarray, target: torch.Tensor | np.ndarray, sigma: float
) -> torch.Tensor | np.ndarray:
    """The task's reward ``r(s, a) = exp(-||target - s_xyz||^2 / (2 sigma^2))`` (eq. of 3.2).

    Written with operators common to numpy and torch, so it takes either; the environment
    evaluates it in torch on its float32 observation, so that :meth:`QuadcopterEnv.reward_function`
    on the same observation reproduces the environment's reward bit for bit.

    :param position: positions ``s_xyz`` in the NED frame (m), shape ``(..., 3)``.
    :param target: target position in the NED frame (m), shape ``(3,)``, same type as
        ``position``.
    :param sigma: width of the reward (m).
    :return: rewards in (0, 1], shape ``(...)``.
    """
    error = target - position
    squared_distance = error[..., 0] ** 2 + error[..., 1] ** 2 + error[..., 2] ** 2
    exponent = -squared_distance / (2.0 * sigma**2)
    return torch.exp(exponent) if isinstance(exponent, torch.Tensor) else np.exp(exponent)


def quadcopter_termination(
    position: torch.Tensor | np.ndarray,
    low: torch.Tensor | np.ndarray,
    high: torch.Tensor | np.ndarray,
) -> torch.Tensor | np.ndarray:
    """Crash test: altitude below 0 (``pz > 0`` in NED) or outside the bounding box.

    Takes numpy arrays or torch tensors alike (comparisons are exact in both).

    :param position: positions in the NED frame (m), shape ``(..., 3)``.
    :param low: lower corner of the bounding box (m), shape ``(3,)``.
    :param high: upper corner of the bounding box (m), shape ``(3,)``.
    :return: True where the state is terminal, shape ``(...)``, bool.
    """
    return (position[..., 2] > 0) | (position < low).any(-1) | (position > high).any(-1)


def _vector3(value: ArrayLike3, name: str) -> np.ndarray:
    """A finite 3-vector as a float64 array, or a ValueError naming ``name``."""
    try:
        vector = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}") from error
    if vector.shape != (3,) or not np.all(np.isfinite(vector)):
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    return vector


def _positive(value: float, name: str) -> float:
    if not value > 0 or not math.isfinite(value):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return float(value)


class QuadcopterEnv(gym.Env[np.ndarray, np.ndarray]):
    """Fly a simulated Pelican quadcopter to a target and hover there.

    **Observation**: the 13-dim state ``(px, py, pz, phi, theta, psi, u, v, w, p, q, r, F)``
    (float32): position in the NED world frame (m; altitude is ``-pz``), roll, pitch, yaw
    (rad), body-frame linear velocity (m/s), body angular rates (rad/s), rotor thrust (N).
    It is clipped into finite bounds: the bounding box widened by
    ``OBSERVATION_POSITION_MARGIN`` (so that a terminal state stays terminal), +-pi for the
    angles, +-``OBSERVATION_MAX_SPEED`` for the velocities, +-``OBSERVATION_MAX_RATE`` for
    the rates and [0, ``OBSERVATION_MAX_THRUST``] for the thrust; a flight that does not
    end in a crash stays far inside them.

    **Action**: ``Box(-1, 1, (3,))``, the desired NED velocity divided by ``max_speed``.
    It is held for ``agent_dt`` seconds, while the velocity PID (50 Hz) flies the airframe,
    integrated by RK2 at 0.02 s.

    **Reward**: ``exp(-||target - position||^2 / (2 sigma^2))`` of the state at the start
    of the step, i.e. ``reward_function(obs_before_step, action)``.

    **Episode end**: terminated when the altitude goes below 0 or the craft leaves the
    bounding box (checked at the end of each agent step); truncated after ``time_limit``.

    :param target: target position in the NED frame (m), shape ``(3,)``.
    :param start: mean start position in the NED frame (m), shape ``(3,)``.
    :param start_radius: the start is drawn uniformly in a ball of this radius (m) around
        ``start``; the craft starts hovering there.
    :param sigma: width of the reward (m).
    :param max_speed: desired speed per axis at action +-1 (m/s), at most 3 (the PID's limit).
    :param agent_dt: duration of one agent step (s), a multiple of 0.02 s; 10 physics steps at the
        default 0.2 s (at 0.1 s the effect of one greedy choice is too small for CMEPolicyIteration's model).
    :param time_limit: episode length before truncation (s).
    :param process_noise: standard deviation of the Gaussian noise added to the linear and
        angular accelerations (m/s^2, rad/s^2) at each physics step; the calibrated
        simulator uses 0.2.
    :param wind: constant wind velocity in the NED frame (m/s), shape ``(3,)``.
    :param bounding_box_low: lower corner of the allowed region in NED (m), shape ``(3,)``.
    :param bounding_box_high: upper corner of the allowed region in NED (m), shape ``(3,)``.
    :param render_mode: None, ``"rgb_array"`` or ``"human"``.
    :param render_size: height of the rendered image (pixels); its width is twice that.
    """

    observation_names = (
        "x, north [m]",
        "y, east [m]",
        "z, down [m]",
        "roll phi [rad]",
        "pitch theta [rad]",
        "yaw psi [rad]",
        "u, body forward [m/s]",
        "v, body right [m/s]",
        "w, body down [m/s]",
        "roll rate p [rad/s]",
        "pitch rate q [rad/s]",
        "yaw rate r [rad/s]",
        "thrust F [N]",
    )
    """A name per observation dim, with its unit (the TensorBoard pictures' axes)."""

    # Gymnasium's class attribute; __init__ replaces it with a copy whose fps is 1 / agent_dt.
    metadata = {"render_modes": ["human", "rgb_array"], "render_fps": 5}  # noqa: RUF012

    def __init__(
        self,
        target: ArrayLike3 = (3.0, 2.0, -4.0),
        start: ArrayLike3 = (0.0, 0.0, -2.0),
        start_radius: float = 0.5,
        sigma: float = 1.5,
        max_speed: float = 2.0,
        agent_dt: float = 0.2,
        time_limit: float = 20.0,
        process_noise: float = 0.0,
        wind: ArrayLike3 = (0.0, 0.0, 0.0),
        bounding_box_low: ArrayLike3 = (-5.0, -5.0, -10.0),
        bounding_box_high: ArrayLike3 = (10.0, 10.0, 0.0),
        render_mode: str | None = None,
        render_size: int = 240,
    ) -> None:
        self.target = _vector3(target, "target")
        self.start = _vector3(start, "start")
        self.wind = _vector3(wind, "wind")
        self.bounding_box_low = _vector3(bounding_box_low, "bounding_box_low")
        self.bounding_box_high = _vector3(bounding_box_high, "bounding_box_high")
        self.sigma = _positive(sigma, "sigma")
        self.max_speed = _positive(max_speed, "max_speed")
        self.agent_dt = _positive(agent_dt, "agent_dt")
        self.time_limit = _positive(time_limit, "time_limit")
        self.start_radius = float(start_radius)
        self.process_noise = float(process_noise)
        self.render_mode = render_mode
        self.render_size = int(render_size)
        # The upper corner of the allowed region: the bounding box, capped at the ground.
        self._allowed_high = self.bounding_box_high.copy()
        self._allowed_high[2] = min(self._allowed_high[2], 0.0)
        self._validate()
        self.physics_steps = round(self.agent_dt / dyn.PHYSICS_DT)
        self.max_episode_steps = math.ceil(self.time_limit / self.agent_dt - 1e-9)
        self.metadata = {**self.metadata, "render_fps": round(1.0 / self.agent_dt)}

        position_low = self.bounding_box_low - OBSERVATION_POSITION_MARGIN
        position_high = self._allowed_high + OBSERVATION_POSITION_MARGIN
        limits = np.array(
            [math.pi] * 3 + [OBSERVATION_MAX_SPEED] * 3 + [OBSERVATION_MAX_RATE] * 3
        )  # angles, body velocities, body rates
        self._obs_low = np.concatenate([position_low, -limits, [0.0]]).astype(np.float32)
        self._obs_high = np.concatenate([position_high, limits, [OBSERVATION_MAX_THRUST]]).astype(np.float32)
        self.observation_space = spaces.Box(self._obs_low, self._obs_high, dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(3,), dtype=np.float32)

        self._wind = tuple(self.wind.tolist())
        self._pid = dyn.VelocityPID()
        self._state: dyn.State = dyn.hover_state(self.start)
        self._obs = self._observe()
        self._steps = 0
        self._trail: list[tuple[float, float, float]] = []
        self._window: Any = None
        self._clock: Any = None

    def _validate(self) -> None:
        """Raise a ValueError naming the first inconsistent constructor argument."""
        if not np.all(self.bounding_box_low < self.bounding_box_high):
            raise ValueError("bounding_box_low must be below bounding_box_high on every axis")
        if not (self.start_radius >= 0 and math.isfinite(self.start_radius)):
            raise ValueError(f"start_radius must be >= 0, got {self.start_radius!r}")
        if not (self.process_noise >= 0 and math.isfinite(self.process_noise)):
            raise ValueError(f"process_noise must be >= 0, got {self.process_noise!r}")
        if self.max_speed > dyn.PID_MAX_SPEED:
            raise ValueError(f"max_speed must be at most {dyn.PID_MAX_SPEED} m/s")
        steps = round(self.agent_dt / dyn.PHYSICS_DT)
        if steps < 1 or abs(steps * dyn.PHYSICS_DT - self.agent_dt) > 1e-9:
            raise ValueError(f"agent_dt must be a multiple of {dyn.PHYSICS_DT} s")
        if self.time_limit < self.agent_dt:
            raise ValueError("time_limit must be at least agent_dt")
        low, high = self.bounding_box_low, self._allowed_high
        if np.any(self.target < low) or np.any(self.target > high):
            raise ValueError("target must lie in the bounding box, at altitude >= 0")
        if np.any(self.start - self.start_radius <= low) or np.any(self.start + self.start_radius >= high):
            raise ValueError("start +- start_radius must lie in the bounding box, above ground")
        if self.render_mode is not None and self.render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None")
        if self.render_size < 64:
            raise ValueError(f"render_size must be at least 64 pixels, got {self.render_size}")

    def reward_function(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The reward r(s, a) of a batch, as the environment computes it.

        :param obs: observations, shape ``(N, 13)``, float.
        :param action: actions in env units, shape ``(N, 3)`` (the reward ignores them).
        :return: rewards, shape ``(N,)``, in ``obs``'s dtype.
        """
        target = torch.as_tensor(self.target, dtype=obs.dtype, device=obs.device)
        return quadcopter_reward(obs[..., :3], target, self.sigma)

    def termination_function(self, obs: torch.Tensor) -> torch.Tensor:
        """Which states of a batch are terminal (altitude below 0 or outside the box).

        :param obs: observations, shape ``(N, 13)``, float.
        :return: terminal flags, shape ``(N,)``, bool.
        """
        position = obs[..., :3].to(torch.float64)
        low = torch.as_tensor(self.bounding_box_low, device=obs.device)
        high = torch.as_tensor(self.bounding_box_high, device=obs.device)
        return quadcopter_termination(position, low, high)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Start hovering at a random point of the start ball.

        :param seed: seed of ``self.np_random`` (start point and process noise).
        :param options: unused.
        :return: the first observation, shape ``(13,)``, and the info dict.
        """
        super().reset(seed=seed)
        self._state = dyn.hover_state(self.start + self._start_offset())
        self._pid.reset()
        self._steps = 0
        self._obs = self._observe()
        self._trail = [self._state[:3]]
        if self.render_mode == "human":
            self.render()
        return self._obs.copy(), self._info()

    def _start_offset(self) -> np.ndarray:
        """A point drawn uniformly in the ball of radius ``start_radius`` (m), shape (3,)."""
        if self.start_radius == 0:
            return np.zeros(3)
        direction = self.np_random.normal(size=3)
        radius = self.start_radius * self.np_random.uniform() ** (1.0 / 3.0)
        return radius * direction / np.linalg.norm(direction)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Hold the desired velocity ``max_speed * action`` for ``agent_dt`` seconds.

        :param action: shape ``(3,)``, in [-1, 1] (clipped).
        :return: observation ``(13,)``, reward of the state at the start of the step,
            terminated, truncated, info.
        """
        action = np.clip(np.asarray(action, dtype=np.float32), -1.0, 1.0)
        obs_batch, action_batch = torch.from_numpy(self._obs[None]), torch.from_numpy(action[None])
        reward = float(self.reward_function(obs_batch, action_batch)[0])
        desired_velocity = (self.max_speed * action.astype(np.float64)).tolist()
        state = self._state
        for noise in self._process_noise():
            commands = dyn.autopilot_commands(*self._pid(state, desired_velocity))
            state = dyn.rk2_step(state, commands, self._wind, noise)
        self._state = state
        self._steps += 1
        self._obs = self._observe()
        self._trail.append(state[:3])
        terminated = bool(quadcopter_termination(self._obs[:3], self.bounding_box_low, self.bounding_box_high))
        truncated = self._steps >= self.max_episode_steps
        if self.render_mode == "human":
            self.render()
        return self._obs.copy(), reward, terminated, truncated, self._info()

    def _process_noise(self) -> list[Sequence[float]]:
        """Noise on ``(u', v', w', p', q', r')`` for each physics step of an agent step."""
        if self.process_noise == 0:
            return [dyn.NO_NOISE] * self.physics_steps
        return self.np_random.normal(0.0, self.process_noise, (self.physics_steps, 6)).tolist()

    def _observe(self) -> np.ndarray:
        """The state as a float32 observation clipped into the observation space."""
        obs = np.array(self._state, dtype=np.float32)
        return np.clip(obs, self._obs_low, self._obs_high, out=obs)

    def _info(self) -> dict[str, Any]:
        distance = math.dist(self._state[:3], self.target)
        return {"distance_to_target": distance, "time": self._steps * self.agent_dt}

    def render(self) -> np.ndarray | None:
        """Top view (x-y) and side view (x-altitude) of the craft, its trail and the target.

        :return: for ``"rgb_array"``, a uint8 image of shape ``(render_size, 2 * render_size,
            3)``; None for ``"human"`` (the frame is shown in a pygame window) and when
            ``render_mode`` is None.
        """
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode=...")
            return None
        frame = render_frame(
            trail=np.array(self._trail),
            attitude=self._state[3:6],
            target=self.target,
            sigma=self.sigma,
            low=self.bounding_box_low,
            high=self.bounding_box_high,
            height=self.render_size,
        )
        if self.render_mode == "rgb_array":
            return frame
        self._show(frame)
        return None

    def _show(self, frame: np.ndarray) -> None:
        """Display a frame in a pygame window at ``metadata["render_fps"]``."""
        try:
            import pygame
        except ImportError as error:
            raise gym.error.DependencyNotInstalled('render_mode="human" needs pygame: run `pip install pygame`') from error
        if self._window is None or not pygame.display.get_init():  # another env may have quit pygame
            pygame.init()
            pygame.display.set_caption("Quadcopter-v0")
            self._window = pygame.display.set_mode((frame.shape[1], frame.shape[0]))
            self._clock = pygame.time.Clock()
        pygame.event.pump()
        self._window.blit(pygame.surfarray.make_surface(frame.swapaxes(0, 1)), (0, 0))
        pygame.display.flip()
        self._clock.tick(self.metadata["render_fps"])

    def close(self) -> None:
        """Close the pygame window, if one was opened."""
        if self._window is not None:
            import pygame

            pygame.display.quit()
            pygame.quit()
            self._window = None
