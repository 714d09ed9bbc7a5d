"""Model of the AscTec Pelican quadcopter: airframe dynamics and velocity PID.

The model is that of ``QUADCOPTER.md`` (the calibrated QRSim Pelican of De Nardi, 2013),
written literally from that page; each function names the section it implements.

A state is a tuple of 13 Python floats (shape ``(13,)``),
``(px, py, pz, phi, theta, psi, u, v, w, p, q, r, F)``: position in the NED world frame
(m; z points down, altitude is ``-pz``), ZYX Euler angles roll, pitch, yaw (rad),
body-frame linear velocity (m/s), body angular rates (rad/s) and total rotor thrust (N).
Plain floats and the ``math`` module are several times faster than numpy on vectors this
small, which is what lets the environment run thousands of physics steps per second.
Every function also accepts numpy arrays wherever it takes a sequence of floats.
"""

import math
from collections.abc import Sequence

import numpy as np

State = tuple[float, ...]
"""A state: 13 floats ``(px, py, pz, phi, theta, psi, u, v, w, p, q, r, F)``."""

# Section "Dynamics": constants of the calibrated model.
GRAVITY = 9.81  # m/s^2
MASS = 1.68  # kg
PQ0 = -3.25060e-4
PQ1 = 1.79797e2
PQ2 = -24.3536
R0 = -4.81783e-3
R1 = -5.08944
CTH0 = 6.63881e-1
CTH1 = 7.44649e-4
CTH2 = 2.39855e-6
CVB0 = -18.0007
CVB1 = 4.23754
TAU0 = 3.07321
TAU1 = 46.8004
KUV = -4.97391e-1
KW = -1.35341
LOW_THROTTLE_LIMIT = 300.0  # autopilot units
MAX_ANGULAR_RATE = math.radians(150.0)  # rad/s
PHYSICS_DT = 0.02  # s, the integration step and the PID period (50 Hz)
HOVER_THRUST = MASS * GRAVITY  # N

# Section "Airframe commands": limits and conversions to the autopilot's units.
MAX_TILT_COMMAND = 0.9  # rad, pitch and roll
MAX_YAW_RATE_COMMAND = 4.5  # rad/s
BATTERY_VOLTAGE = 12.0  # V
TILT_TO_AUTOPILOT = -1.0 / math.radians(0.025)
THROTTLE_TO_AUTOPILOT = 4097.0
YAW_RATE_TO_AUTOPILOT = -1.0 / math.radians(254.760 / 2047)
MAX_THRUST = CVB0 + CVB1 * BATTERY_VOLTAGE  # N, the battery's thrust ceiling

# Section "Velocity PID": gains and limits.
PID_MAX_SPEED = 3.0  # m/s, per body-frame component of the set-point
PID_TILT_GAINS = (0.25, 0.003, 0.05)  # proportional, integral, derivative
PID_MAX_TILT = 0.34  # rad
PID_HOVER_THROTTLE = 0.59
PID_THROTTLE_GAINS = (-0.2, -0.002)  # proportional, integral
PID_YAW_GAIN = 6.0  # 1/s
PID_MAX_YAW_RATE = 4.4  # rad/s

NO_WIND = (0.0, 0.0, 0.0)
NO_NOISE = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def _clip(value: float, low: float, high: float) -> float:
    return low if value < low else high if value > high else value


def _dcm(sph: float, cph: float, sth: float, cth: float, sps: float, cps: float) -> tuple[float, ...]:
    """World -> body rotation D from the sines and cosines of roll, pitch and yaw.

    :return: the 9 entries of D, row by row.
    """
    return (
        cth * cps,
        cth * sps,
        -sth,
        -cph * sps + sph * sth * cps,
        cph * cps + sph * sth * sps,
        sph * cth,
        sph * sps + cph * sth * cps,
        -sph * cps + cph * sth * sps,
        cph * cth,
    )


def rotation_elements(phi: float, theta: float, psi: float) -> tuple[float, ...]:
    """Rotation D from the NED world frame to the body frame (section "Frames and state").

    :param phi: roll (rad).
    :param theta: pitch (rad).
    :param psi: yaw (rad).
    :return: the 9 entries of D, row by row: ``v_body = D @ v_world``.
    """
    return _dcm(math.sin(phi), math.cos(phi), math.sin(theta), math.cos(theta), math.sin(psi), math.cos(psi))


def rotation_matrix(phi: float, theta: float, psi: float) -> np.ndarray:
    """Rotation D from the NED world frame to the body frame, as a matrix.

    :param phi: roll (rad).
    :param theta: pitch (rad).
    :param psi: yaw (rad).
    :return: D, shape ``(3, 3)``: ``v_body = D @ v_world`` and ``v_world = D.T @ v_body``.
    """
    return np.array(rotation_elements(phi, theta, psi)).reshape(3, 3)


def autopilot_commands(pitch: float, roll: float, throttle: float, yaw_rate: float) -> tuple[float, float, float, float]:
    """Clip airframe commands to their limits and scale them to autopilot units.

    Section "Airframe commands".

    :param pitch: commanded pitch ``pt`` (rad), clipped to +-0.9.
    :param roll: commanded roll ``rl`` (rad), clipped to +-0.9.
    :param throttle: commanded throttle ``th`` (unitless), clipped to [0, 1].
    :param yaw_rate: commanded yaw rate ``ya`` (rad/s), clipped to +-4.5.
    :return: ``(pt_u, rl_u, th_u, ya_u)`` in autopilot units.
    """
    return (
        _clip(pitch, -MAX_TILT_COMMAND, MAX_TILT_COMMAND) * TILT_TO_AUTOPILOT,
        _clip(roll, -MAX_TILT_COMMAND, MAX_TILT_COMMAND) * TILT_TO_AUTOPILOT,
        _clip(throttle, 0.0, 1.0) * THROTTLE_TO_AUTOPILOT,
        _clip(yaw_rate, -MAX_YAW_RATE_COMMAND, MAX_YAW_RATE_COMMAND) * YAW_RATE_TO_AUTOPILOT,
    )


def _limited_rate_derivative(rate: float, derivative: float) -> float:
    """Zero an angular acceleration that would push ``|rate|`` further past the limit."""
    if (rate > MAX_ANGULAR_RATE and derivative > 0.0) or (rate < -MAX_ANGULAR_RATE and derivative < 0.0):
        return 0.0
    return derivative


def thrust_derivative(thrust: float, throttle_u: float, dt: float = PHYSICS_DT) -> float:
    """Rate of change F' of the total rotor thrust (section "Dynamics", item "Thrust").

    :param thrust: current thrust F (N).
    :param throttle_u: commanded throttle ``th_u`` (autopilot units, 0 to 4097).
    :param dt: integration step (s).
    :return: F' (N/s).
    """
    delta = CTH0 + CTH1 * throttle_u + CTH2 * throttle_u * throttle_u - thrust
    if throttle_u < LOW_THROTTLE_LIMIT:
        return TAU0 * delta
    rate = delta / dt if abs(delta) < TAU1 * dt else math.copysign(TAU1, delta)
    if thrust + rate * dt > MAX_THRUST:
        return (MAX_THRUST - thrust) / dt
    return rate


def state_derivative(
    state: Sequence[float],
    commands: Sequence[float],
    wind: Sequence[float] = NO_WIND,
    noise: Sequence[float] = NO_NOISE,
    dt: float = PHYSICS_DT,
) -> State:
    """Time derivative of the state (section "Dynamics").

    :param state: the state, 13 floats (see the module docstring).
    :param commands: ``(pt_u, rl_u, th_u, ya_u)`` in autopilot units, from
        :func:`autopilot_commands`.
    :param wind: wind velocity in the NED world frame (m/s), shape ``(3,)``; it enters the
        drag terms rotated into the body frame, ``(wind_u, wind_v, wind_w) = D @ wind``.
    :param noise: process noise added to ``(u', v', w', p', q', r')``, shape ``(6,)``
        (m/s^2 and rad/s^2).
    :param dt: integration step (s); the thrust model looks one step ahead.
    :return: the derivative, 13 floats in the state's units per second.
    """
    _, _, _, phi, theta, psi, u, v, w, p, q, r, thrust = state
    pitch_u, roll_u, throttle_u, yaw_rate_u = commands
    sph, cph = math.sin(phi), math.cos(phi)
    sth, cth = math.sin(theta), math.cos(theta)
    tth = sth / cth
    d11, d12, d13, d21, d22, d23, d31, d32, d33 = _dcm(sph, cph, sth, cth, math.sin(psi), math.cos(psi))
    thrust_dot = thrust_derivative(thrust, throttle_u, dt)
    wind_u = d11 * wind[0] + d12 * wind[1] + d13 * wind[2]
    wind_v = d21 * wind[0] + d22 * wind[1] + d23 * wind[2]
    wind_w = d31 * wind[0] + d32 * wind[1] + d33 * wind[2]
    lift = -(thrust + thrust_dot * dt) / MASS
    return (
        d11 * u + d21 * v + d31 * w,
        d12 * u + d22 * v + d32 * w,
        d13 * u + d23 * v + d33 * w,
        p + q * sph * tth + r * cph * tth,
        q * cph - r * sph,
        (q * sph + r * cph) / cth,
        -q * w + r * v + d13 * GRAVITY + KUV * (u - wind_u) + noise[0],
        -r * u + p * w + d23 * GRAVITY + KUV * (v - wind_v) + noise[1],
        -p * v + q * u + lift + d33 * GRAVITY + KW * (w - wind_w) + noise[2],
        _limited_rate_derivative(p, PQ1 * (PQ0 * roll_u - phi) + PQ2 * p) + noise[3],
        _limited_rate_derivative(q, PQ1 * (PQ0 * pitch_u - theta) + PQ2 * q) + noise[4],
        R0 * yaw_rate_u + R1 * r + noise[5],
        thrust_dot,
    )


def rk2_step(
    state: Sequence[float],
    commands: Sequence[float],
    wind: Sequence[float] = NO_WIND,
    noise: Sequence[float] = NO_NOISE,
    dt: float = PHYSICS_DT,
) -> State:
    """Advance the state by one second-order Runge-Kutta (Heun) step (section "Dynamics").

    ``x1 = x + dt f(x)``, ``x' = x + dt (f(x) + f(x1)) / 2``, with the commands, wind and
    noise held over the step.

    :param state: the state, 13 floats.
    :param commands: ``(pt_u, rl_u, th_u, ya_u)`` in autopilot units.
    :param wind: wind velocity in the NED world frame (m/s), shape ``(3,)``.
    :param noise: process noise on ``(u', v', w', p', q', r')``, shape ``(6,)``.
    :param dt: step length (s), 0.02 in the model.
    :return: the state after ``dt``, 13 floats.
    """
    start = state_derivative(state, commands, wind, noise, dt)
    euler = [x + dt * dx for x, dx in zip(state, start, strict=True)]
    end = state_derivative(euler, commands, wind, noise, dt)
    half_dt = 0.5 * dt
    return tuple([x + half_dt * (dx0 + dx1) for x, dx0, dx1 in zip(state, start, end, strict=True)])


def hover_state(position: Sequence[float]) -> State:
    """Hovering state at a position: zero angles, velocities and rates, ``F = mass * g``.

    :param position: ``(px, py, pz)`` in the NED world frame (m).
    :return: the state, 13 floats.
    """
    return (*(float(x) for x in position), *(0.0,) * 9, HOVER_THRUST)


class VelocityPID:
    """Velocity controller turning a desired NED velocity into airframe commands.

    Section "Velocity PID" (50 Hz, desired yaw 0). Its integrators, previous errors and
    previous set-point are the controller's state; :meth:`reset` zeroes them at the start
    of an episode. Each update adds the current raw error to the integrators before using
    them (``sum(e)`` includes this step's ``e``), and uses ``de/dt = (e - e_prev) / dt``
    unless the set-point differs from the previous update's, when ``de/dt = 0``.

    :param dt: controller period (s), used by the derivative term.
    """

    def __init__(self, dt: float = PHYSICS_DT) -> None:
        self.dt = dt
        self.reset()

    def reset(self) -> None:
        """Zero the integrators, the previous errors and the previous set-point."""
        self._integral = (0.0, 0.0, 0.0)
        self._previous_error = (0.0, 0.0)  # x and y; the throttle has no derivative term
        self._setpoint = (0.0, 0.0, 0.0)

    def __call__(self, state: Sequence[float], desired_velocity: Sequence[float]) -> tuple[float, float, float, float]:
        """One controller update.

        :param state: the current state, 13 floats.
        :param desired_velocity: the set-point ``vd``, desired velocity in the NED world
            frame (m/s), shape ``(3,)``.
        :return: airframe commands ``(pt, rl, th, ya)``: pitch (rad), roll (rad),
            throttle (unitless) and yaw rate (rad/s), for :func:`autopilot_commands`.
        """
        _, _, _, phi, theta, psi, u, v, w = state[:9]
        vx, vy, vz = setpoint = tuple(float(x) for x in desired_velocity)
        d11, d12, d13, d21, d22, d23, d31, d32, d33 = rotation_elements(phi, theta, psi)
        error_x = -(_clip(d11 * vx + d12 * vy + d13 * vz, -PID_MAX_SPEED, PID_MAX_SPEED) - u)
        error_y = _clip(d21 * vx + d22 * vy + d23 * vz, -PID_MAX_SPEED, PID_MAX_SPEED) - v
        error_z = _clip(d31 * vx + d32 * vy + d33 * vz, -PID_MAX_SPEED, PID_MAX_SPEED) - w
        sum_x, sum_y, sum_z = self._integral
        sum_x, sum_y, sum_z = sum_x + error_x, sum_y + error_y, sum_z + error_z
        if setpoint == self._setpoint:
            previous_x, previous_y = self._previous_error
            rate_x, rate_y = (error_x - previous_x) / self.dt, (error_y - previous_y) / self.dt
        else:
            rate_x = rate_y = 0.0
        self._integral = (sum_x, sum_y, sum_z)
        self._previous_error = (error_x, error_y)
        self._setpoint = setpoint
        kp, ki, kd = PID_TILT_GAINS
        pitch = _clip(kp * error_x + ki * sum_x + kd * rate_x, -PID_MAX_TILT, PID_MAX_TILT)
        roll = _clip(kp * error_y + ki * sum_y + kd * rate_y, -PID_MAX_TILT, PID_MAX_TILT)
        kp_z, ki_z = PID_THROTTLE_GAINS
        throttle = _clip(PID_HOVER_THROTTLE + kp_z * error_z + ki_z * sum_z, 0.0, 1.0)
        yaw_rate = _clip(PID_YAW_GAIN * (0.0 - psi), -PID_MAX_YAW_RATE, PID_MAX_YAW_RATE)
        return pitch, roll, throttle, yaw_rate
