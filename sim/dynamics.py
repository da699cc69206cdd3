"""Motion of the robot and the obstacles over one control period, for N worlds at once."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from contracts.actions import NUM_ACTIONS, forward_command, turn_command
from sim.config import IncrementDynamics, InertiaDynamics

F64 = NDArray[np.float64]


def step_inertia(
    pose: F64, velocity: F64, action: NDArray[np.integer], params: InertiaDynamics, period_s: float
) -> tuple[F64, F64]:
    """Advance poses (N, 3) and velocities (N, 2) = (forward m/s, turn rad/s) by one period.

    Velocities follow first-order lags towards the commanded steady values; each physics step
    integrates them exactly and moves the body along the mean heading of that step.
    """
    speed_target = forward_command(action) * params.max_speed_mps
    rate_target = turn_command(action) * params.max_turn_rate_radps
    return step_velocity_lag(
        pose, velocity, speed_target, rate_target, params=params, period_s=period_s
    )


def step_velocity_lag(
    pose: F64,
    velocity: F64,
    speed_target_mps: F64,
    rate_target_radps: F64,
    *,
    params: InertiaDynamics,
    period_s: float,
) -> tuple[F64, F64]:
    """`step_inertia` for any commanded velocities (N,) rather than the action table's.

    The MAVLink test vehicle drives with this: a throttle or a guided velocity target sets the
    steady speed the lag approaches.
    """
    speed_target, rate_target = speed_target_mps, rate_target_radps
    substeps = max(1, round(period_s / params.physics_dt_s))
    dt = period_s / substeps
    tau_v, tau_w = params.linear_time_constant_s, params.angular_time_constant_s
    decay_v, decay_w = math.exp(-dt / tau_v), math.exp(-dt / tau_w)
    x, y, heading = pose[:, 0], pose[:, 1], pose[:, 2]
    speed, rate = velocity[:, 0], velocity[:, 1]
    for _ in range(substeps):
        # Exact integrals of v(t) and w(t) over the step, and their end values.
        distance = speed_target * dt + (speed - speed_target) * tau_v * (1.0 - decay_v)
        turned = rate_target * dt + (rate - rate_target) * tau_w * (1.0 - decay_w)
        mid_heading = heading + 0.5 * turned
        x = x + distance * np.cos(mid_heading)
        y = y + distance * np.sin(mid_heading)
        heading = heading + turned
        speed = speed_target + (speed - speed_target) * decay_v
        rate = rate_target + (rate - rate_target) * decay_w
    return np.stack([x, y, wrap_angle(heading)], axis=1), np.stack([speed, rate], axis=1)


def step_increment(
    pose: F64, velocity: F64, action: NDArray[np.integer], params: IncrementDynamics
) -> tuple[F64, F64]:
    """Forward moves a constant distance along the heading; a turn rotates a constant angle."""
    heading = wrap_angle(pose[:, 2] + turn_command(action) * params.turn_step_rad)
    distance = forward_command(action) * params.forward_step_m
    moved = np.stack(
        [pose[:, 0] + distance * np.cos(heading), pose[:, 1] + distance * np.sin(heading), heading],
        axis=1,
    )
    return moved, np.zeros_like(velocity)


def move_obstacles(
    position: F64, velocity: F64, radius_m: float, size_m: float, period_s: float
) -> tuple[F64, F64]:
    """Straight-line motion, reflecting specularly off the walls (exact for one bounce per axis)."""
    low, high = radius_m, size_m - radius_m
    moved = position + velocity * period_s
    below, above = moved < low, moved > high
    moved = np.where(below, 2 * low - moved, np.where(above, 2 * high - moved, moved))
    return moved, np.where(below | above, -velocity, velocity)


def wrap_angle(angle: F64) -> F64:
    """Angles wrapped to [-pi, pi)."""
    return (angle + math.pi) % (2 * math.pi) - math.pi


def action_velocities(
    dynamics: InertiaDynamics | IncrementDynamics, period_s: float
) -> list[tuple[float, float]]:
    """(forward m/s, turn rad/s) each action commands, in `Action` order.

    With inertia these are the steady velocities the lags approach; with increments, the step
    spread over one control period (what a real car must do to match the simulator).
    """
    actions = np.arange(NUM_ACTIONS)
    if isinstance(dynamics, InertiaDynamics):
        speed, rate = dynamics.max_speed_mps, dynamics.max_turn_rate_radps
    else:
        speed, rate = dynamics.forward_step_m / period_s, dynamics.turn_step_rad / period_s
    return [
        (float(f * speed), float(t * rate))
        for f, t in zip(forward_command(actions), turn_command(actions), strict=True)
    ]
