"""Tests of Quadcopter-v0: the Pelican model of QUADCOPTER.md, the env and its helpers."""

import inspect
import sys
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import stable_baselines3.common.env_checker as sb3_env_checker
import torch
import yaml
from gymnasium.utils import env_checker as gym_env_checker
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor

import cme_agent.envs  # noqa: F401  (registers Quadcopter-v0)
from cme_agent.envs import quadcopter_dynamics as dyn
from cme_agent.envs.quadcopter import QuadcopterEnv
from cme_agent.envs.quadcopter_controller import QuadcopterPController

CONFIG = Path(__file__).resolve().parents[1] / "conf" / "env" / "quadcopter.yaml"
DT = 0.02


# --- helpers: flying the model directly, PID at 50 Hz -------------------------------------


def fly(desired_velocity: tuple[float, float, float], seconds: float) -> np.ndarray:
    """States (T + 1, 13) of the PID-flown model from hover at 5 m altitude, no noise."""
    state, pid = dyn.hover_state((0.0, 0.0, -5.0)), dyn.VelocityPID()
    states = [state]
    for _ in range(round(seconds / DT)):
        state = dyn.rk2_step(state, dyn.autopilot_commands(*pid(state, desired_velocity)))
        states.append(state)
    return np.array(states)


def world_velocity(states: np.ndarray) -> np.ndarray:
    """NED velocities (T, 3) of states (T, 13): D^T (u, v, w)."""
    return np.array([dyn.rotation_matrix(*s[3:6]).T @ s[6:9] for s in states])


def time_to(values: np.ndarray, level: float) -> float:
    """First time (s) at which a 50 Hz series reaches a level."""
    reached = np.flatnonzero(values >= level)
    assert reached.size, f"never reached {level} (max {values.max():.3f})"
    return reached[0] * DT


STEPS = {  # name: (desired NED velocity, NED axis, sign of that axis's response)
    "north": ((1.0, 0.0, 0.0), 0, 1.0),
    "east": ((0.0, 1.0, 0.0), 1, 1.0),
    "climb": ((0.0, 0.0, -1.0), 2, -1.0),
}


# --- physics -------------------------------------------------------------------------------


def test_hover_holds_altitude() -> None:
    states = fly((0.0, 0.0, 0.0), 10.0)
    drift = np.abs(states[:, :3] - states[0, :3]).max()
    assert drift < 0.05, f"hover drifted {drift:.4f} m in 10 s"


@pytest.mark.parametrize("name", list(STEPS))
def test_velocity_step_response(name: str) -> None:
    desired, axis, sign = STEPS[name]
    states = fly(desired, 6.0)
    velocity = world_velocity(states)
    response = sign * velocity[:, axis]
    assert time_to(response, 0.9) <= 3.0
    assert response.max() < 1.3, f"overshoot to {response.max():.3f} m/s"
    others = np.delete(velocity, axis, axis=1)  # the body-frame PID couples tilt and climb
    assert np.abs(others).max() < 0.1, "motion on an axis that was not commanded"
    assert np.abs(states[:, 5]).max() < 0.01, "yaw drifted"


@pytest.mark.parametrize(
    ("name", "reference_t90", "reference_peak"),
    [("north", 1.2, 1.06), ("east", 1.2, 1.06), ("climb", 0.6, None)],
)
def test_reference_figures(name: str, reference_t90: float, reference_peak: float | None) -> None:
    """The figures at the end of QUADCOPTER.md, for a literal implementation."""
    desired, axis, sign = STEPS[name]
    response = sign * world_velocity(fly(desired, 6.0))[:, axis]
    assert time_to(response, 0.9) == pytest.approx(reference_t90, abs=0.05)
    if reference_peak is not None:
        assert response.max() == pytest.approx(reference_peak, abs=0.01)
    hover = fly((0.0, 0.0, 0.0), 10.0)
    assert np.abs(hover[:, 2] - hover[0, 2]).max() < 1e-3


def drop(state: tuple[float, ...], seconds: float) -> np.ndarray:
    """States (T + 1, 13) with the dynamics driven directly at throttle 0, level attitude."""
    states = [state]
    for _ in range(round(seconds / DT)):
        states.append(dyn.rk2_step(states[-1], dyn.autopilot_commands(0.0, 0.0, 0.0, 0.0)))
    return np.array(states)


def test_throttle_zero_falls() -> None:
    """At th = 0 the thrust decays to Cth0 at rate tau0 and the craft falls towards the
    terminal speed where gravity, idle thrust and drag balance; with the rotors already at
    idle thrust, the fall starts at nearly g."""
    states = drop(dyn.hover_state((0.0, 0.0, -50.0)), 6.0)
    times = np.arange(len(states)) * DT
    expected_thrust = dyn.CTH0 + (dyn.HOVER_THRUST - dyn.CTH0) * np.exp(-dyn.TAU0 * times)
    np.testing.assert_allclose(states[:, 12], expected_thrust, rtol=0.01)
    assert np.all(np.diff(states[1:, 2]) > 0), "not falling"
    terminal = (dyn.GRAVITY - dyn.CTH0 / dyn.MASS) / -dyn.KW
    assert world_velocity(states[-1:])[0, 2] == pytest.approx(terminal, rel=0.01)
    assert np.abs(states[:, 3:6]).max() < 1e-12, "attitude changed"

    idle = (*dyn.hover_state((0.0, 0.0, -50.0))[:12], dyn.CTH0)
    first = drop(idle, DT)
    acceleration = (first[1, 8] - first[0, 8]) / DT
    assert acceleration == pytest.approx(dyn.GRAVITY, rel=0.06)


# --- one RK2 step, by hand from QUADCOPTER.md -----------------------------------------------


def page_derivative(
    x: np.ndarray, pt: float, rl: float, th: float, ya: float, wind_ned: np.ndarray, noise: np.ndarray
) -> np.ndarray:
    """The state derivative written out from QUADCOPTER.md, independently of the package."""
    g, mass, dt, voltage = 9.81, 1.68, 0.02, 12.0
    pq0, pq1, pq2, r0, r1 = -3.25060e-4, 1.79797e2, -24.3536, -4.81783e-3, -5.08944
    cth0, cth1, cth2, cvb0, cvb1 = 6.63881e-1, 7.44649e-4, 2.39855e-6, -18.0007, 4.23754
    tau0, tau1, kuv, kw = 3.07321, 46.8004, -4.97391e-1, -1.35341
    max_rate = np.deg2rad(150.0)
    pt_u, rl_u = -pt / np.deg2rad(0.025), -rl / np.deg2rad(0.025)
    th_u, ya_u = 4097 * th, -ya / np.deg2rad(254.760 / 2047)
    phi, theta, psi = x[3:6]
    uvw, (p, q, r), thrust = x[6:9], x[9:12], x[12]
    c, s = np.cos, np.sin
    d = np.array(
        [
            [c(theta) * c(psi), c(theta) * s(psi), -s(theta)],
            [-c(phi) * s(psi) + s(phi) * s(theta) * c(psi),
             c(phi) * c(psi) + s(phi) * s(theta) * s(psi), s(phi) * c(theta)],
            [s(phi) * s(psi) + c(phi) * s(theta) * c(psi),
             -s(phi) * c(psi) + c(phi) * s(theta) * s(psi), c(phi) * c(theta)],
        ]
    )  # fmt: skip
    out = np.zeros(13)
    out[0:3] = d.T @ uvw
    out[3] = p + q * s(phi) * np.tan(theta) + r * c(phi) * np.tan(theta)
    out[4] = q * c(phi) - r * s(phi)
    out[5] = (q * s(phi) + r * c(phi)) / c(theta)
    for i, (rate, angle, command) in enumerate([(p, phi, rl_u), (q, theta, pt_u)]):
        rate_dot = pq1 * (pq0 * command - angle) + pq2 * rate
        pushes_further = (rate > max_rate and rate_dot > 0) or (rate < -max_rate and rate_dot < 0)
        out[9 + i] = 0.0 if pushes_further else rate_dot
    out[11] = r0 * ya_u + r1 * r
    d_thrust = cth0 + cth1 * th_u + cth2 * th_u**2 - thrust
    if th_u < 300:
        out[12] = tau0 * d_thrust
    else:
        tau = d_thrust / dt if abs(d_thrust) < tau1 * dt else np.sign(d_thrust) * tau1
        ceiling = cvb0 + cvb1 * voltage
        out[12] = (ceiling - thrust) / dt if thrust + tau * dt > ceiling else tau
    a = np.array([0.0, 0.0, -(thrust + out[12] * dt)]) / mass + d @ np.array([0.0, 0.0, g])
    u, v, w = uvw
    wind_u, wind_v, wind_w = d @ wind_ned
    out[6] = -q * w + r * v + a[0] + kuv * (u - wind_u)
    out[7] = -r * u + p * w + a[1] + kuv * (v - wind_v)
    out[8] = -p * v + q * u + a[2] + kw * (w - wind_w)
    out[6:12] += noise
    return out


RK2_CASES = {  # name: (state, (pt, rl, th, ya)), covering every branch of the thrust and rate models
    "thrust rising fast": (
        [1.0, -2.0, -3.0, 0.1, -0.2, 0.3, 1.0, -0.5, 0.3, 0.2, -0.1, 0.05, 14.0],
        (0.1, -0.05, 0.62, 0.5),
    ),
    "thrust near target": (
        [0.5, 0.3, -4.0, -0.15, 0.12, -0.4, -0.7, 0.9, -0.2, -0.3, 0.25, -0.1, 17.5],
        (-0.2, 0.15, 0.6, -1.0),
    ),
    "battery ceiling": (
        [0.0, 0.0, -2.0, 0.05, 0.05, 0.05, 0.5, 0.5, -0.5, 0.1, 0.1, 0.1, 32.5],
        (0.3, 0.3, 0.9, 2.0),
    ),
    "angular rate limit": (
        [0.0, 0.0, -2.0, 0.1, -0.1, 0.2, 0.2, -0.2, 0.1, 3.0, -3.0, 0.5, 15.0],
        (-0.9, 0.9, 0.7, 4.0),
    ),
    "low throttle": (
        [0.0, 0.0, -2.0, 0.2, 0.1, -0.1, 0.3, 0.1, 0.4, -0.2, 0.3, -0.2, 10.0],
        (0.05, -0.1, 0.05, -3.0),
    ),
}


@pytest.mark.parametrize("name", list(RK2_CASES))
def test_rk2_step_matches_hand_integration(name: str) -> None:
    state, commands = (np.array(x, dtype=np.float64) for x in RK2_CASES[name])
    wind = np.array([1.5, -0.5, 0.2])
    noise = np.array([0.1, -0.2, 0.05, 0.3, -0.1, 0.2])
    start = page_derivative(state, *commands, wind, noise)
    end = page_derivative(state + DT * start, *commands, wind, noise)
    expected = state + DT / 2 * (start + end)
    actual = dyn.rk2_step(tuple(state), dyn.autopilot_commands(*commands), wind, noise)
    np.testing.assert_allclose(actual, expected, rtol=0, atol=1e-9)
    assert np.abs(expected - state).max() > 1e-3, "the step should move the state"


# --- the environment -------------------------------------------------------------------------


@pytest.mark.parametrize("render_mode", [None, "rgb_array"])
def test_env_checkers_pass_without_warnings(render_mode: str | None) -> None:
    for check in (gym_env_checker.check_env, sb3_env_checker.check_env):
        env = gym.make("Quadcopter-v0", process_noise=0.2, render_mode=render_mode)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            check(env.unwrapped)
        assert not caught, [str(w.message) for w in caught]


def test_make_with_yaml_kwargs() -> None:
    kwargs = yaml.safe_load(CONFIG.read_text())["env"]["kwargs"]
    parameters = set(inspect.signature(QuadcopterEnv).parameters)
    assert set(kwargs) == parameters, "conf/env/quadcopter.yaml must list every argument"
    env = gym.make("Quadcopter-v0", **kwargs)
    assert env.spec.max_episode_steps is None
    obs, _ = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    np.testing.assert_array_equal(env.unwrapped.target, kwargs["target"])


def test_truncation_at_time_limit() -> None:
    env = QuadcopterEnv(time_limit=3.0, agent_dt=0.2)
    env.reset(seed=0)
    steps, terminated, truncated = 0, False, False
    while not (terminated or truncated):
        _, reward, terminated, truncated, _ = env.step(np.zeros(3, dtype=np.float32))
        assert type(reward) is float and type(terminated) is bool and type(truncated) is bool
        steps += 1
    assert (steps, terminated, truncated) == (15, False, True)


@pytest.mark.parametrize(
    ("kwargs", "action"),
    [
        ({}, (0.0, 0.0, 1.0)),  # descend into the ground
        ({"bounding_box_high": (4.0, 10.0, 0.0)}, (1.0, 0.0, 0.0)),  # leave the box north
        ({"bounding_box_low": (-5.0, -5.0, -5.0)}, (0.0, 0.0, -1.0)),  # through the ceiling
    ],
)
def test_reward_and_termination_functions_match_steps(kwargs: dict, action: tuple) -> None:
    env = QuadcopterEnv(process_noise=0.2, **kwargs)
    obs, _ = env.reset(seed=3)
    rng = np.random.default_rng(0)
    before, actions, rewards, after, terminals = [], [], [], [], []
    for step in range(200):
        a = rng.uniform(-1, 1, 3) if step < 5 else np.array(action)
        next_obs, reward, terminated, truncated, _ = env.step(a.astype(np.float32))
        before.append(obs)
        actions.append(a)
        rewards.append(reward)
        after.append(next_obs)
        terminals.append(terminated)
        obs = next_obs
        if terminated or truncated:
            break
    assert terminals[-1], "the rollout should end in a crash"
    expected = env.reward_function(torch.as_tensor(np.array(before)), torch.as_tensor(np.array(actions)))
    assert expected.dtype == torch.float32
    assert torch.equal(torch.tensor(rewards, dtype=torch.float32), expected)
    flags = env.termination_function(torch.as_tensor(np.array(after)))
    assert flags.tolist() == terminals


def test_reward_uses_the_state_at_the_start_of_the_step() -> None:
    env = QuadcopterEnv(start_radius=0.0, sigma=1.0)
    obs, _ = env.reset(seed=0)
    _, reward, *_ = env.step(np.ones(3, dtype=np.float32))
    distance = np.linalg.norm(env.target - obs[:3])
    assert reward == pytest.approx(np.exp(-(distance**2) / 2.0), rel=1e-6)


def rollout(env: QuadcopterEnv, seed: int, steps: int = 40) -> np.ndarray:
    """Observations (steps + 1, 13) under a fixed sequence of random actions."""
    observations = [env.reset(seed=seed)[0]]
    actions = np.random.default_rng(1).uniform(-0.5, 0.5, (steps, 3)).astype(np.float32)
    observations += [env.step(action)[0] for action in actions]
    return np.array(observations)


def test_seeding_is_deterministic_with_process_noise() -> None:
    first = rollout(QuadcopterEnv(process_noise=0.2), seed=7)
    second = rollout(QuadcopterEnv(process_noise=0.2), seed=7)
    np.testing.assert_array_equal(first, second)
    # With a fixed start point, only the seeded process noise tells two seeds apart.
    fixed_start = [rollout(QuadcopterEnv(process_noise=0.2, start_radius=0.0), seed) for seed in (7, 8)]
    np.testing.assert_array_equal(fixed_start[0][0], fixed_start[1][0])
    assert not np.allclose(fixed_start[0], fixed_start[1])


def test_observations_are_fresh_arrays() -> None:
    env = QuadcopterEnv()
    obs, _ = env.reset(seed=0)
    next_obs, *_ = env.step(np.zeros(3, dtype=np.float32))
    obs[:] = 0.0
    assert next_obs is not obs and np.any(next_obs != 0)
    _, reward, *_ = env.step(np.zeros(3, dtype=np.float32))
    assert reward > 0.0, "mutating a returned observation must not change the env"


@pytest.mark.parametrize(
    ("argument", "value"),
    [
        ("target", (1.0, 2.0)),
        ("target", (20.0, 0.0, -4.0)),
        ("start", (0.0, 0.0, float("nan"))),
        ("start_radius", -1.0),
        ("sigma", 0.0),
        ("max_speed", 4.0),
        ("agent_dt", 0.05),
        ("time_limit", -1.0),
        ("process_noise", -0.1),
        ("wind", "strong"),
        ("bounding_box_low", (11.0, -5.0, -10.0)),
        ("render_mode", "ansi"),
        ("render_size", 10),
    ],
)
def test_bad_arguments_raise(argument: str, value: object) -> None:
    with pytest.raises(ValueError, match=argument):
        QuadcopterEnv(**{argument: value})


# --- the scripted controller -----------------------------------------------------------------


def test_scripted_controller_reaches_and_holds_the_target() -> None:
    env = QuadcopterEnv()
    controller = QuadcopterPController.from_env(env)
    obs, _ = env.reset(seed=0)
    distances, done = [], False
    while not done:
        action, _ = controller.predict(obs)
        obs, _, terminated, truncated, info = env.step(action)
        distances.append(info["distance_to_target"])
        done = terminated or truncated
    assert not terminated
    last_five_seconds = distances[-round(5.0 / env.agent_dt) :]
    assert max(last_five_seconds) < 0.5, f"final distance {distances[-1]:.3f} m"


def test_controller_predict_batches_and_evaluate_policy() -> None:
    env = Monitor(QuadcopterEnv(time_limit=10.0, agent_dt=0.1))  # 100 steps, at most 100 of reward
    controller = QuadcopterPController.from_env(env, gain=0.8)
    observations = np.zeros((4, 13), dtype=np.float32)
    actions, state = controller.predict(observations)
    assert actions.shape == (4, 3) and state is None
    assert controller.predict(observations[0])[0].shape == (3,)
    assert np.all(np.abs(actions) <= 1.0)
    mean_return, _ = evaluate_policy(controller, env, n_eval_episodes=2)
    assert mean_return > 50.0


# --- rendering -----------------------------------------------------------------------------


def test_rgb_array_render_changes_as_the_craft_moves() -> None:
    env = QuadcopterEnv(render_mode="rgb_array", render_size=120)
    env.reset(seed=0)
    first = env.render()
    assert first.dtype == np.uint8 and first.shape == (120, 240, 3)
    for _ in range(10):
        env.step(np.array([1.0, 0.0, -1.0], dtype=np.float32))
    second = env.render()
    assert second.shape == first.shape
    assert np.count_nonzero(np.any(first != second, axis=2)) > 20


def test_human_render_without_pygame_says_how_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "pygame", None)
    env = QuadcopterEnv(render_mode="human")
    with pytest.raises(gym.error.DependencyNotInstalled, match="pip install pygame"):
        env.reset(seed=0)


def test_human_render_opens_a_pygame_window(monkeypatch: pytest.MonkeyPatch) -> None:
    pygame = pytest.importorskip("pygame")
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    monkeypatch.setenv("SDL_AUDIODRIVER", "dummy")
    env = QuadcopterEnv(render_mode="human", render_size=100)
    env.reset(seed=0)
    assert env.step(np.zeros(3, dtype=np.float32))[0].shape == (13,)
    assert pygame.display.get_surface().get_size() == (200, 100)
    env.close()
    assert not pygame.display.get_init()
