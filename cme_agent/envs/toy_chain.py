"""ToyChain-v0: navigation on a noisy Markov chain over the interval [-1, 1].

The paper's first benchmark (PAPER.md section 3.1) is "a navigation task on a simple Markov
chain on an interval S subset R"; the paper gives no more detail, so this is our design of it.
The state is a position, the action a desired step, and the reward a Gaussian bump around a
goal that lies far from where the episodes start.
"""

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from cme_agent.config import check, check_non_negative, check_positive, check_positive_int
from cme_agent.envs.quadcopter_render import TARGET, TRAIL, Color, draw_polyline, fill_disc

LOW, HIGH = -1.0, 1.0  # ends of the interval S
DISCRETE_STEPS = np.array([-1.0, 0.0, 1.0])  # Discrete(3) action -> step direction: left, stay, right
AXIS: Color = (120, 120, 120)
AGENT: Color = (30, 30, 30)
BACKGROUND: Color = (250, 250, 250)
PADDING = 10  # pixels left and right of the interval


def toy_chain_reward(position: torch.Tensor, goal: float, sigma: float) -> torch.Tensor:
    """The reward ``exp(-(x - goal)^2 / (2 sigma^2))`` of positions x.

    :param position: positions x, shape ``(...)``.
    :param goal: centre of the reward bump, in [-1, 1].
    :param sigma: width of the reward bump (same unit as x).
    :return: rewards in (0, 1], shape ``(...)``, in ``position``'s dtype.
    """
    return torch.exp(-((position - goal) ** 2) / (2.0 * sigma**2))


def _in_interval(key: str, value: float) -> None:
    """Check that ``value`` is a number in [-1, 1], or raise a ValueError naming ``key``."""
    is_number = isinstance(value, (int, float)) and not isinstance(value, bool)
    check(key, value, is_number and LOW <= value <= HIGH, f"a number in [{LOW}, {HIGH}]")


class ToyChainEnv(gym.Env[np.ndarray, np.ndarray | int]):
    """Reach and stay near a goal on a noisy one-dimensional chain.

    **Observation**: the position ``x`` in [-1, 1], ``Box(-1, 1, (1,))``, float32.

    **Action**: by default ``Box(-1, 1, (1,))``, the desired step as a fraction of
    ``step_size`` (clipped to [-1, 1]); with ``discrete_actions=True``, ``Discrete(3)``:
    0 = left (-1), 1 = stay (0), 2 = right (+1).

    **Transition**: ``x' = clip(x + step_size * a + noise_std * eps, -1, 1)``, with
    ``eps ~ N(0, 1)`` drawn from ``self.np_random``; ``x'`` is rounded to float32, the
    observation's precision, which is the state itself.

    **Reward**: ``exp(-(x - goal)^2 / (2 sigma^2))`` of the state ``x`` at the *start* of the
    step, i.e. ``reward_function(obs_before_step, action)``, so that an agent that plans with
    ``reward_function`` knows the reward exactly.

    **Episode end**: never terminated; truncated after ``max_steps`` steps. The task is to
    reach the goal *and hold it*: the return (at most about ``max_steps`` minus the travel
    time) measures both. Terminating at the goal would pay for a single visit, and the agent
    would have to learn that termination from chance visits before it could plan for it.
    ``termination_function`` is therefore always False.

    **Start**: ``x_0`` uniform in ``[start_low, start_high]``; by default 11 to 15 full steps
    from the goal, where the reward is below 0.002, so that a random policy's return is
    about 0.5 while a good policy's is about 39 (of 50 steps).

    :param goal: centre of the reward bump, in [-1, 1].
    :param sigma: width of the reward bump (same unit as x), > 0.
    :param start_low: lower end of the start interval, in [-1, 1].
    :param start_high: upper end of the start interval, in [start_low, 1].
    :param step_size: largest step per action (unit of x per step), in (0, 2].
    :param noise_std: standard deviation of the Gaussian transition noise (unit of x), >= 0.
    :param max_steps: steps per episode before truncation, >= 1.
    :param discrete_actions: ``Discrete(3)`` actions (left, stay, right) instead of ``Box``.
    :param render_mode: None or ``"rgb_array"``.
    :param render_size: width of the rendered image (pixels), >= 64; its height is half that.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}  # noqa: RUF012

    def __init__(
        self,
        goal: float = 0.6,
        sigma: float = 0.3,
        start_low: float = -0.9,
        start_high: float = -0.5,
        step_size: float = 0.1,
        noise_std: float = 0.02,
        max_steps: int = 50,
        discrete_actions: bool = False,
        render_mode: str | None = None,
        render_size: int = 240,
    ) -> None:
        _in_interval("goal", goal)
        check_positive("sigma", sigma)
        _in_interval("start_low", start_low)
        _in_interval("start_high", start_high)
        check("start_high", start_high, start_high >= start_low, f"at least start_low={start_low!r}")
        check_positive("step_size", step_size)
        check("step_size", step_size, step_size <= HIGH - LOW, f"at most {HIGH - LOW}, the interval's length")
        check_non_negative("noise_std", noise_std)
        check_positive_int("max_steps", max_steps)
        check("discrete_actions", discrete_actions, isinstance(discrete_actions, bool), "a bool")
        check("render_mode", render_mode, render_mode in [None, *self.metadata["render_modes"]], "None or 'rgb_array'")
        check("render_size", render_size, isinstance(render_size, int) and render_size >= 64, "an integer >= 64")
        self.goal, self.sigma = float(goal), float(sigma)
        self.start_low, self.start_high = float(start_low), float(start_high)
        self.step_size, self.noise_std = float(step_size), float(noise_std)
        self.max_steps, self.discrete_actions = max_steps, discrete_actions
        self.render_mode, self.render_size = render_mode, render_size

        self.observation_space = spaces.Box(LOW, HIGH, shape=(1,), dtype=np.float32)
        self.action_space: spaces.Space = (
            spaces.Discrete(3) if discrete_actions else spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)
        )
        self._obs = np.zeros(1, dtype=np.float32)
        self._steps = 0

    def reward_function(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The reward r(s, a) of a batch, as the environment computes it.

        :param obs: observations, shape ``(N, 1)``, float.
        :param action: actions, shape ``(N, 1)`` (Box) or ``(N,)`` (Discrete); the reward
            ignores them.
        :return: rewards, shape ``(N,)``, in ``obs``'s dtype.
        """
        return toy_chain_reward(obs[:, 0], self.goal, self.sigma)

    def termination_function(self, obs: torch.Tensor) -> torch.Tensor:
        """Which states of a batch are terminal: none (episodes only end by truncation).

        :param obs: observations, shape ``(N, 1)``, float.
        :return: terminal flags, shape ``(N,)``, bool, all False.
        """
        return torch.zeros(obs.shape[0], dtype=torch.bool, device=obs.device)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Start at a point drawn uniformly in ``[start_low, start_high]``.

        :param seed: seed of ``self.np_random`` (start point and transition noise).
        :param options: unused.
        :return: the first observation, shape ``(1,)``, and the info dict.
        """
        super().reset(seed=seed)
        self._obs = np.array([self.np_random.uniform(self.start_low, self.start_high)], dtype=np.float32)
        self._steps = 0
        return self._obs.copy(), self._info()

    def step(self, action: np.ndarray | int) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Move by ``step_size * a`` plus Gaussian noise, clipped to [-1, 1].

        :param action: Box: shape ``(1,)``, in [-1, 1] (clipped); Discrete: 0, 1 or 2.
        :return: observation ``(1,)``, reward of the state at the start of the step,
            terminated (always False), truncated, info.
        """
        direction, action_batch = self._direction(action)
        reward = float(self.reward_function(torch.from_numpy(self._obs[None]), action_batch)[0])
        noise = self.noise_std * self.np_random.normal() if self.noise_std > 0 else 0.0
        position = float(self._obs[0]) + self.step_size * direction + noise
        self._obs = np.array([np.clip(position, LOW, HIGH)], dtype=np.float32)
        self._steps += 1
        return self._obs.copy(), reward, False, self._steps >= self.max_steps, self._info()

    def _direction(self, action: np.ndarray | int) -> tuple[float, torch.Tensor]:
        """The step direction in [-1, 1] of an action (Box: clipped; Discrete: left, stay, right),
        and the action as a batch of one for :meth:`reward_function`: shape ``(1, 1)`` or ``(1,)``."""
        if self.discrete_actions:
            return float(DISCRETE_STEPS[int(action)]), torch.tensor([int(action)])
        clipped = np.clip(np.asarray(action, dtype=np.float32).reshape(1, 1), -1.0, 1.0)
        return float(clipped[0, 0]), torch.from_numpy(clipped)

    def _info(self) -> dict[str, Any]:
        """Distance from the position to the goal (unit of x) and steps taken this episode."""
        return {"distance_to_goal": abs(float(self._obs[0]) - self.goal), "steps": self._steps}

    def render(self) -> np.ndarray | None:
        """The interval (grey), the reward bump over it (green, a line at the goal), the start
        interval (blue, under the axis) and the agent (black disc).

        :return: for ``"rgb_array"``, a uint8 image of shape ``(render_size // 2, render_size,
            3)``; None when ``render_mode`` is None.
        """
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode='rgb_array'")
            return None
        width, height = self.render_size, self.render_size // 2
        image = np.full((height, width, 3), BACKGROUND, dtype=np.uint8)
        axis_row, bump_height = 0.8 * height, 0.6 * height
        positions = np.linspace(LOW, HIGH, width)
        bump = toy_chain_reward(torch.from_numpy(positions), self.goal, self.sigma).numpy()
        columns = PADDING + (positions - LOW) / (HIGH - LOW) * (width - 1 - 2 * PADDING)
        draw_polyline(image, np.stack([columns, axis_row - bump_height * bump], 1), TARGET, width=2)
        draw_polyline(image, np.stack([columns[[0, -1]], [axis_row, axis_row]], 1), AXIS, width=2)
        goal_column = np.interp(self.goal, positions, columns)
        draw_polyline(image, np.array([[goal_column, axis_row], [goal_column, axis_row - bump_height]]), TARGET)
        agent_column = np.interp(float(self._obs[0]), positions, columns)
        fill_disc(image, np.array([agent_column, axis_row]), max(height / 15.0, 3.0), AGENT)
        start = np.interp([self.start_low, self.start_high], positions, columns)
        draw_polyline(image, np.stack([start, [axis_row + 5.0] * 2], 1), TRAIL, width=2)
        return image
