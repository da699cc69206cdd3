"""How the car and the obstacles move, and when a step ends: the model the simulator steps and
the controller's look-ahead predicts with.

One definition serves both sides, so the onboard look-ahead (`controller.lookahead`) forecasts
with exactly the motion the policy was trained in; the policy file carries the training world's
dynamics settings (`contracts.policy_file.PolicyContract.motion`). Pure numpy, N worlds at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.actions import NUM_ACTIONS, forward_command, turn_command
from qnav.contracts.settings import check_range

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class InertiaDynamics:
    """A body with inertia and damping driven by force and torque (the paper's Tables I and II).

    Forward applies the force whose steady speed is `max_speed_mps`; a turn applies the torque
    whose steady rate is `max_turn_rate_radps` and no force, so the robot turns in place once its
    speed has decayed. Velocities relax exponentially towards those steady values.
    """

    SECTION = "dynamics"

    kind: Literal["inertia"] = "inertia"
    """Dynamics model name."""
    max_speed_mps: float = 0.5
    """Steady forward speed under the forward action (paper: 0.5 m/s)."""
    max_turn_rate_radps: float = 0.5
    """Steady turn rate under a turn action (paper: 0.5 rad/s)."""
    linear_time_constant_s: float = 0.5
    """Mass over linear damping: the time to reach 63% of a speed change (paper: not given)."""
    angular_time_constant_s: float = 0.5
    """Inertia over angular damping: the time to reach 63% of a turn-rate change (not given)."""
    physics_dt_s: float = 0.05
    """Integration step inside one control period; velocities are integrated exactly."""

    def __post_init__(self) -> None:
        check_range(self, "max_speed_mps", self.max_speed_mps, 0.0, 10.0, exclusive_low=True)
        check_range(
            self, "max_turn_rate_radps", self.max_turn_rate_radps, 0.0, 10.0, exclusive_low=True
        )
        check_range(
            self,
            "linear_time_constant_s",
            self.linear_time_constant_s,
            0.0,
            100.0,
            exclusive_low=True,
        )
        check_range(
            self,
            "angular_time_constant_s",
            self.angular_time_constant_s,
            0.0,
            100.0,
            exclusive_low=True,
        )
        check_range(self, "physics_dt_s", self.physics_dt_s, 0.0, 1.0, exclusive_low=True)


@dataclass(frozen=True)
class IncrementDynamics:
    """Every action moves the body by a constant step, no velocity memory (Tables III-IV)."""

    SECTION = "dynamics"

    kind: Literal["increment"] = "increment"
    """Dynamics model name."""
    forward_step_m: float = 0.2
    """Distance moved by one forward action (paper: 0.2 m)."""
    turn_step_rad: float = 0.2
    """Rotation by one turn action (paper: 0.2 rad)."""

    def __post_init__(self) -> None:
        check_range(self, "forward_step_m", self.forward_step_m, 0.0, 10.0, exclusive_low=True)
        check_range(self, "turn_step_rad", self.turn_step_rad, 0.0, math.pi, exclusive_low=True)


Dynamics = InertiaDynamics | IncrementDynamics


def step_robot(
    pose: F64, velocity: F64, action: NDArray[np.integer], dynamics: Dynamics, period_s: float
) -> tuple[F64, F64]:
    """Advance poses (N, 3) and velocities (N, 2) by one control period under either model."""
    if isinstance(dynamics, IncrementDynamics):
        return step_increment(pose, velocity, action, dynamics)
    return step_inertia(pose, velocity, action, dynamics, period_s)


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
    position: F64,
    velocity: F64,
    radius_m: float | F64,
    size_m: float | F64,
    period_s: float | F64,
    *,
    origin_m: float | F64 = 0.0,
) -> tuple[F64, F64]:
    """Straight-line motion, reflecting specularly off the walls of the box from `origin_m` to
    `origin_m + size_m` (the room: [0, size]^2; exact for one bounce per axis); the radii, the
    box's corners and `period_s` may be arrays that broadcast against the positions."""
    low, high = origin_m + radius_m, origin_m + size_m - radius_m
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


class Outcome(IntEnum):
    """How a step left the episode."""

    RUNNING = 0
    SUCCESS = 1
    COLLISION = 2


def outcome(
    distance_to_target_m: F64,
    clearance_m: F64,
    robot_radius_m: float,
    reach_m: float | None = None,
) -> NDArray[np.int8]:
    """SUCCESS within `reach_m` of the target (default l, the robot's radius, as the paper),
    else COLLISION within l of a surface, else RUNNING.

    Reaching the target is checked first: a robot that touches the target and a wall in the same
    step has reached the target.
    """
    success = distance_to_target_m < (robot_radius_m if reach_m is None else reach_m)
    collision = ~success & (clearance_m < robot_radius_m)
    return np.where(
        success, Outcome.SUCCESS, np.where(collision, Outcome.COLLISION, Outcome.RUNNING)
    ).astype(np.int8)


def distance_to_segments(points: F64, start: F64, end: F64) -> F64:
    """(N,) each point's (N, 2) distance to the nearest of the segments start (K, 2) -> end."""
    # Written per coordinate: numpy's reductions over a length-2 axis cost more than the
    # arithmetic, and the look ahead calls this for millions of points. Each value is the same
    # sum of the same products as the vector form, and sqrt is monotone, so the minimum of the
    # squares gives the same distance bit for bit.
    px, py = points[:, 0, None], points[:, 1, None]
    sx, sy = start[:, 0], start[:, 1]
    dx, dy = end[:, 0] - sx, end[:, 1] - sy
    t = np.clip(((px - sx) * dx + (py - sy) * dy) / (dx * dx + dy * dy), 0.0, 1.0)
    ex, ey = px - (sx + t * dx), py - (sy + t * dy)
    distance: F64 = np.sqrt((ex * ex + ey * ey).min(axis=1))
    return distance


def clearance(
    xy: F64, wall_start: F64, wall_end: F64, obstacle_xy: F64, obstacle_radius_m: float
) -> F64:
    """Distance from each robot centre (N, 2) to the nearest wall segment or obstacle surface
    (obstacle centres (N, M, 2)).

    This is the exact value that the minimum of a dense lidar scan approximates (the paper's d_l).
    """
    wall_distance = distance_to_segments(xy, wall_start, wall_end)
    if obstacle_xy.shape[1] == 0:
        return wall_distance
    ox = obstacle_xy[..., 0] - xy[:, 0, None]
    oy = obstacle_xy[..., 1] - xy[:, 1, None]
    obstacle_distance: F64 = np.sqrt((ox * ox + oy * oy).min(axis=1)) - obstacle_radius_m
    return np.minimum(wall_distance, obstacle_distance)
