"""The Dynamic Window Approach (Fox, Burgard, Thrun 1997) with the paper's three actions: the
local planner a roboticist would run against a learned policy, on the same robot, lidar and
control period, with no map.

At each decision it rolls out candidate action sequences over `horizon_s` from the robot's pose
and its velocity (estimated from its last two poses, as a car would), with the world's own
motion model: each first action held, or followed by forward after 1 .. H - 1 steps. The lidar's
returns are the obstacles. A rollout that comes within the robot's radius plus `margin_m` of a
return is inadmissible; the others are scored as Fox et al. score them, by a weighted sum of each
term divided by its sum over the admissible rollouts:

- heading: pi minus the angle between the rollout's final heading and the goal seen from there;
- clearance: the rollout's least distance to a return beyond the robot's disc, up to
  `clearance_cap_m`;
- velocity: its final forward speed.

The best rollout's first action is taken; with none admissible, the robot turns towards the
side with more room. The weights and horizon were tuned on generated validation worlds
(`qnav lab tune-dwa`; never on BARN's), and are the defaults here (docs/barn.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.actions import NUM_ACTIONS, Action
from qnav.contracts.motion import step_robot, wrap_angle
from qnav.contracts.settings import check_range
from qnav.sim.config import WorldConfig
from qnav.sim.world import Observation

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class DwaSettings:
    """How the DWA baseline scores its rollouts. The defaults won a random search on generated
    cave validation worlds, never BARN's (docs/barn.md, "Baselines")."""

    SECTION = "dwa"

    heading_weight: float = 0.91
    """Weight of the heading term (Fox et al.: 2 of 2.4 in all)."""
    clearance_weight: float = 0.11
    """Weight of the clearance term."""
    velocity_weight: float = 0.31
    """Weight of the velocity term."""
    horizon_s: float = 1.0
    """How far ahead each rollout runs."""
    margin_m: float = 0.02
    """Clearance beyond the robot's radius that an admissible rollout keeps from every return."""
    clearance_cap_m: float = 1.0
    """Clearance beyond this scores no more."""
    beam_stride: int = 2
    """Use every this-many-th lidar beam as an obstacle point."""
    oscillation_reset_m: float = 0.3
    """After a turn, the opposite turn is ruled out until the robot has moved this far
    (ROS base_local_planner's oscillation suppression; 0: never ruled out)."""

    def __post_init__(self) -> None:
        for name in ("heading_weight", "clearance_weight", "velocity_weight", "margin_m"):
            check_range(self, name, getattr(self, name), 0.0, 1e3)
        check_range(self, "horizon_s", self.horizon_s, 0.0, 60.0, exclusive_low=True)
        check_range(self, "clearance_cap_m", self.clearance_cap_m, 0.0, 1e3, exclusive_low=True)
        check_range(self, "beam_stride", self.beam_stride, 1, 1000)
        check_range(self, "oscillation_reset_m", self.oscillation_reset_m, 0.0, 1e3)


def rollout_sequences(steps: int) -> NDArray[np.int64]:
    """(S, steps) the candidate sequences: each action held, and each turn followed by forward
    after 1 .. steps - 1 steps."""
    sequences = [np.full(steps, action) for action in range(NUM_ACTIONS)]
    for turn in (Action.LEFT, Action.RIGHT):
        for k in range(1, steps):
            sequence = np.full(steps, Action.FORWARD)
            sequence[:k] = turn
            sequences.append(sequence)
    return np.array(sequences, dtype=np.int64)


class DwaAgent:
    """The DWA baseline acting in a batch of worlds (`sim.evaluate.Agent`)."""

    def __init__(self, config: WorldConfig, num_worlds: int, settings: DwaSettings | None = None):
        if config.lidar is None:
            raise ValueError("DWA needs a lidar")
        self.config = config
        self.settings = settings or DwaSettings()
        steps = max(1, round(self.settings.horizon_s / config.control_period_s))
        self.sequences = rollout_sequences(steps)
        angles = config.lidar.beam_angles_rad()[:: self.settings.beam_stride]
        self._beam_cos, self._beam_sin = np.cos(angles), np.sin(angles)
        self._last_pose = np.full((num_worlds, 3), np.nan)
        self._turn = np.full(num_worlds, Action.FORWARD, dtype=np.int64)
        """The turn each world last chose (FORWARD: none to hold to)."""
        self._turn_xy = np.zeros((num_worlds, 2))
        """Where that turn began."""

    def start(self, worlds: NDArray[np.intp], episodes: NDArray[np.int64]) -> None:
        """New episodes: no earlier pose to estimate the velocity from, no turn held."""
        self._last_pose[worlds] = np.nan
        self._turn[worlds] = Action.FORWARD

    def velocity(self, pose: F64) -> F64:
        """(N, 2) forward speed and turn rate over the last period (0 at an episode's start)."""
        moved = pose[:, :2] - self._last_pose[:, :2]
        heading = pose[:, 2]
        speed = moved[:, 0] * np.cos(heading) + moved[:, 1] * np.sin(heading)
        rate = wrap_angle(pose[:, 2] - self._last_pose[:, 2])
        velocity = np.stack([speed, rate], axis=1) / self.config.control_period_s
        return np.nan_to_num(velocity, nan=0.0)

    def act(self, observation: Observation) -> NDArray[np.int64]:
        assert observation.scan_m is not None
        pose = observation.pose
        velocity = self.velocity(pose)
        self._last_pose = pose.copy()
        paths = self.rollouts(pose, velocity)  # (N, S, T, 3)
        points = self.points(pose, observation.scan_m)  # (N, P, 2)
        gap = self.clearances(paths, points)  # (N, S)
        # Nearer than the margin already, a rollout that comes no nearer is admissible.
        now = np.min(observation.scan_m, axis=1) - self.config.robot_radius_m
        needed = np.minimum(self.settings.margin_m, now - 1e-3)[:, None]
        admissible = (gap >= needed) & ~self.ruled_out(pose)
        action = self.choose(paths, gap, observation.target_xy, admissible)
        action = np.where(admissible.any(axis=1), action, roomier_turn(observation.scan_m))
        self.hold_turns(pose, action)
        return action

    def ruled_out(self, pose: F64) -> NDArray[np.bool_]:
        """(N, S) rollouts whose first action is the opposite of a turn still held."""
        moved = np.linalg.norm(pose[:, :2] - self._turn_xy, axis=1)
        held = (self._turn != Action.FORWARD) & (moved < self.settings.oscillation_reset_m)
        opposite = np.where(self._turn == Action.LEFT, Action.RIGHT, Action.LEFT)
        ruled: NDArray[np.bool_] = held[:, None] & (self.sequences[None, :, 0] == opposite[:, None])
        return ruled

    def hold_turns(self, pose: F64, action: NDArray[np.int64]) -> None:
        """Remember each new turn and where it began; forget turns once the robot has moved."""
        moved = np.linalg.norm(pose[:, :2] - self._turn_xy, axis=1)
        self._turn = np.where(
            moved >= self.settings.oscillation_reset_m, Action.FORWARD, self._turn
        )
        new = (action != Action.FORWARD) & (action != self._turn)
        self._turn = np.where(new, action, self._turn)
        self._turn_xy[new] = pose[new, :2]

    def rollouts(self, pose: F64, velocity: F64) -> F64:
        """(N, S, T, 3) the poses after each step of each candidate sequence."""
        n, (s, t) = pose.shape[0], self.sequences.shape
        now, speed = np.repeat(pose, s, axis=0), np.repeat(velocity, s, axis=0)
        actions = np.tile(self.sequences, (n, 1))
        poses = []
        for k in range(t):
            now, speed = step_robot(
                now, speed, actions[:, k], self.config.dynamics, self.config.control_period_s
            )
            poses.append(now)
        return np.stack(poses, axis=1).reshape(n, s, t, 3)

    def points(self, pose: F64, scan_m: NDArray[np.float32]) -> F64:
        """(N, P, 2) the returns in the room's frame (far away where a beam saw nothing)."""
        ranges = scan_m[:, :: self.settings.beam_stride].astype(np.float64)
        ranges = np.where(np.isfinite(ranges), ranges, 1e6)
        cos_h, sin_h = np.cos(pose[:, 2:3]), np.sin(pose[:, 2:3])
        ahead, left = ranges * self._beam_cos, ranges * self._beam_sin
        x = pose[:, 0:1] + cos_h * ahead - sin_h * left
        y = pose[:, 1:2] + sin_h * ahead + cos_h * left
        return np.stack([x, y], axis=-1)

    def clearances(self, paths: F64, points: F64) -> F64:
        """(N, S) each rollout's least distance to a return, less the robot's radius."""
        n, s, t, _ = paths.shape
        xy = paths[..., :2].reshape(n, s * t, 1, 2).astype(np.float32)
        returns = points[:, None, :, :].astype(np.float32)
        d2 = np.square(xy - returns).sum(axis=-1).min(axis=-1).reshape(n, s, t)
        nearest: F64 = np.sqrt(d2.min(axis=2).astype(np.float64))
        return nearest - self.config.robot_radius_m

    def choose(
        self, paths: F64, gap: F64, target_xy: F64, admissible: NDArray[np.bool_]
    ) -> NDArray[np.int64]:
        """The first action of each world's best admissible rollout (the first sequence's where
        none is admissible)."""
        settings = self.settings
        final = paths[:, :, -1, :]
        to_goal = target_xy[:, None, :] - final[..., :2]
        bearing = np.arctan2(to_goal[..., 1], to_goal[..., 0])
        heading = math.pi - np.abs(wrap_angle(bearing - final[..., 2]))
        clearance = np.clip(gap, 0.0, settings.clearance_cap_m)
        last_step = paths[:, :, -1, :2] - paths[:, :, -2, :2] if paths.shape[2] > 1 else None
        speed = (
            np.linalg.norm(last_step, axis=-1) / self.config.control_period_s
            if last_step is not None
            else np.zeros_like(gap)
        )
        score = np.zeros_like(gap)
        for weight, term in (
            (settings.heading_weight, heading),
            (settings.clearance_weight, clearance),
            (settings.velocity_weight, speed),
        ):
            total = np.where(admissible, term, 0.0).sum(axis=1, keepdims=True)
            score += weight * term / np.where(total > 0, total, 1.0)
        score = np.where(admissible, score, -np.inf)
        best = np.argmax(score, axis=1)
        return np.asarray(self.sequences[best, 0], dtype=np.int64)


def roomier_turn(scan_m: NDArray[np.float32]) -> NDArray[np.int64]:
    """(N,) a turn towards the side (left half or right half of the scan) with more room."""
    beams = scan_m.shape[1]
    ranges = np.where(np.isfinite(scan_m), scan_m, 20.0)
    left = ranges[:, 1 : beams // 2].mean(axis=1)
    right = ranges[:, beams // 2 + 1 :].mean(axis=1)
    return np.where(left >= right, Action.LEFT, Action.RIGHT).astype(np.int64)
