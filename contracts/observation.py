"""The observation contract: lidar beam convention, scan and target encoding, the k-frame window.

The simulator produces, and the car's drivers deliver, observations in physical units (metres,
radians). The functions here turn them into network inputs. The learner, the exporter and the
onboard runtime all call these, so the encoding exists in exactly one place.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.settings import check_range

WINDOW_LENGTH = 5
"""Observations per network input (the paper's k): the current one and the four before it."""

TARGET_FEATURES = 3
"""Per-step target features: distance to target, sin and cos of its bearing."""

OBSTACLE_SLOTS = 5
"""Obstacles a network given obstacle inputs sees per frame, nearest first (the paper's worlds
hold 5)."""
OBSTACLE_SLOT_FEATURES = 5
"""Per obstacle: seen (1) or an empty slot (0), its centre ahead and to the left of the robot,
and its velocity along the robot's heading and to its left."""
OBSTACLE_FEATURES = OBSTACLE_SLOTS * OBSTACLE_SLOT_FEATURES
"""Per-frame obstacle features of a network given obstacle inputs (beyond the paper)."""
OBSTACLE_POSITION_SCALE_M = 5.0
"""Obstacle offsets are divided by this (the ranges that matter for a dodge are a few metres)."""
OBSTACLE_SPEED_SCALE_M_S = 1.0
"""Obstacle velocities are divided by this."""


@dataclass(frozen=True)
class LidarSpec:
    """A planar lidar: `num_beams` beams equally spaced over [0, 2*pi), counter-clockwise, beam 0
    pointing along the robot's heading (REP 103: x forward, y left)."""

    SECTION = "lidar"

    num_beams: int = 720
    """Readings per scan (the paper's 720)."""
    max_range_m: float = 20.0
    """Longest reading; beyond it the lidar reports no return (+inf), as a ROS driver does."""

    def __post_init__(self) -> None:
        check_range(self, "num_beams", self.num_beams, 1, 100_000)
        check_range(self, "max_range_m", self.max_range_m, 1e-3, 1e4, exclusive_low=True)

    @property
    def angle_increment_rad(self) -> float:
        """Angle between consecutive beams."""
        return 2.0 * math.pi / self.num_beams

    def beam_angles_rad(self) -> NDArray[np.float64]:
        """Beam angles relative to the heading, in [0, 2*pi)."""
        return np.arange(self.num_beams, dtype=np.float64) * self.angle_increment_rad


def distance_scale_m(lidar: LidarSpec | None) -> float:
    """The length that scales distances for the network: the lidar's maximum range, or the
    default lidar's for the toy car that has none (its target distance is scaled the same)."""
    return (lidar or LidarSpec()).max_range_m


def encode_scan(scan_m: NDArray[np.floating], max_range_m: float) -> NDArray[np.float32]:
    """Scale ranges to [0, 1] as the paper does (divide by the maximum range).

    No return (+inf or NaN) reads as the maximum range; negative readings read as 0.
    """
    # clip(nan_to_num(scan), 0, max) in two ufuncs: maximum keeps NaN (and, with 0 first, a -0
    # reading, as clip does) and fmin then turns NaN and +inf into the maximum range.
    scan = np.asarray(scan_m, dtype=np.float32)
    encoded = np.empty_like(scan)
    np.maximum(0.0, scan, out=encoded)
    np.fmin(encoded, max_range_m, out=encoded)
    encoded /= np.float32(max_range_m)
    return encoded


def target_features(
    pose: NDArray[np.floating], target_xy: NDArray[np.floating]
) -> NDArray[np.float64]:
    """(d_g, sin(phi), cos(phi)) for poses (..., 3) = (x, y, heading) and targets (..., 2).

    d_g is the distance to the target in metres; phi is the target's bearing from the robot's
    heading, counter-clockwise positive. At the target itself phi is taken as 0.
    """
    pose = np.asarray(pose, dtype=np.float64)
    delta = np.asarray(target_xy, dtype=np.float64) - pose[..., :2]
    cos_h, sin_h = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    ahead = cos_h * delta[..., 0] + sin_h * delta[..., 1]
    left = -sin_h * delta[..., 0] + cos_h * delta[..., 1]
    distance = np.hypot(ahead, left)
    safe = np.where(distance > 0.0, distance, 1.0)
    return np.stack(
        [
            distance,
            np.where(distance > 0, left / safe, 0.0),
            np.where(distance > 0, ahead / safe, 1.0),
        ],
        axis=-1,
    )


def target_features_of(
    x_m: float, y_m: float, heading_rad: float, target_x_m: float, target_y_m: float
) -> tuple[float, float, float]:
    """`target_features` of one pose and one target, in plain floats: the same values (the
    same operations, in the same order, numpy's own sin, cos and hypot), without the per-call
    cost of a dozen numpy operations on three numbers (the controller calls this per decision).
    """
    dx, dy = target_x_m - x_m, target_y_m - y_m
    cos_h, sin_h = float(np.cos(heading_rad)), float(np.sin(heading_rad))
    ahead = cos_h * dx + sin_h * dy
    left = -sin_h * dx + cos_h * dy
    distance = float(np.hypot(ahead, left))
    if distance > 0.0:
        return distance, left / distance, ahead / distance
    return distance, 0.0, 1.0


def encode_target(features: NDArray[np.floating], max_range_m: float) -> NDArray[np.float32]:
    """Scale the target distance like the lidar (divide by the maximum range); sin and cos as is."""
    encoded = np.array(features, dtype=np.float32, copy=True)
    encoded[..., 0] /= np.float32(max_range_m)
    return encoded


def obstacle_features(
    pose: NDArray[np.floating],
    obstacle_xy: NDArray[np.floating],
    obstacle_velocity: NDArray[np.floating],
) -> NDArray[np.float32]:
    """Encoded obstacle inputs (..., OBSTACLE_FEATURES) for poses (..., 3) among obstacles
    (..., M, 2) with velocities (..., M, 2), all in the room's frame.

    The nearest `OBSTACLE_SLOTS` obstacles, nearest first, each as (1, ahead, left, forward
    speed, leftward speed) in the robot's frame, scaled by `OBSTACLE_POSITION_SCALE_M` and
    `OBSTACLE_SPEED_SCALE_M_S`; empty slots (fewer obstacles) are all zero. In simulation the
    obstacles are the world's own; on the car they are the onboard tracker's estimate.
    """
    pose = np.asarray(pose, dtype=np.float64)
    xy = np.asarray(obstacle_xy, dtype=np.float64)
    velocity = np.asarray(obstacle_velocity, dtype=np.float64)
    cos_h, sin_h = np.cos(pose[..., 2])[..., None], np.sin(pose[..., 2])[..., None]
    delta = xy - pose[..., None, :2]
    ahead = cos_h * delta[..., 0] + sin_h * delta[..., 1]
    left = -sin_h * delta[..., 0] + cos_h * delta[..., 1]
    forward = cos_h * velocity[..., 0] + sin_h * velocity[..., 1]
    leftward = -sin_h * velocity[..., 0] + cos_h * velocity[..., 1]
    slots = np.stack(
        [
            np.ones_like(ahead),
            ahead / OBSTACLE_POSITION_SCALE_M,
            left / OBSTACLE_POSITION_SCALE_M,
            forward / OBSTACLE_SPEED_SCALE_M_S,
            leftward / OBSTACLE_SPEED_SCALE_M_S,
        ],
        axis=-1,
    )  # (..., M, OBSTACLE_SLOT_FEATURES)
    order = np.argsort(np.hypot(ahead, left), axis=-1, kind="stable")[..., :OBSTACLE_SLOTS]
    nearest = np.take_along_axis(slots, order[..., None], axis=-2)
    encoded = np.zeros((*pose.shape[:-1], OBSTACLE_SLOTS, OBSTACLE_SLOT_FEATURES), np.float32)
    encoded[..., : nearest.shape[-2], :] = nearest
    return encoded.reshape(*pose.shape[:-1], OBSTACLE_FEATURES)


def encode_frame(
    scan_m: NDArray[np.floating] | None, features: NDArray[np.floating], max_range_m: float
) -> NDArray[np.float32]:
    """One network input frame (..., B + 3): the encoded scan followed by the encoded target.

    Without a lidar (scan_m is None) the frame is the encoded target alone (..., 3).
    """
    target = encode_target(features, max_range_m)
    if scan_m is None:
        return target
    return np.concatenate([encode_scan(scan_m, max_range_m), target], axis=-1)


class FrameWindow:
    """The last k frames of each of N streams, oldest first, for the recurrent policy.

    At the start of an episode the window is filled with copies of its first frame: the network
    always sees k frames, and a standing start looks like a robot that has not moved.
    """

    def __init__(self, num_streams: int, frame_size: int, length: int = WINDOW_LENGTH) -> None:
        self.frames = np.zeros((num_streams, length, frame_size), dtype=np.float32)
        self.fresh = np.ones(num_streams, dtype=bool)
        """Streams whose next frame begins an episode."""

    def restart(self, streams: NDArray[np.intp] | None = None) -> None:
        """The next frame of `streams` (all by default) begins a new episode."""
        self.fresh[slice(None) if streams is None else streams] = True

    def advance(self, frames: NDArray[np.float32]) -> NDArray[np.float32]:
        """Take one frame per stream (N, frame_size), starting or extending each window as its
        stream requires; returns the windows (N, k, frame_size)."""
        if not self.fresh.any():  # the usual step: slices, not gathers of every stream
            self.push(frames)
        elif self.fresh.all():
            self.frames[:] = frames[:, None, :]
        else:
            fresh = np.flatnonzero(self.fresh)
            self.start(fresh, frames[fresh])
            ongoing = np.flatnonzero(~self.fresh)
            self.push(frames[ongoing], ongoing)
        self.fresh[:] = False
        return self.frames

    def start(self, streams: NDArray[np.intp], first_frames: NDArray[np.float32]) -> None:
        """Begin new episodes in `streams` with their first frames (S, frame_size)."""
        self.frames[streams] = first_frames[:, None, :]

    def push(self, frames: NDArray[np.float32], streams: NDArray[np.intp] | None = None) -> None:
        """Append one frame per stream (all streams, or those listed), dropping the oldest."""
        index = slice(None) if streams is None else streams
        self.frames[index, :-1] = self.frames[index, 1:]
        self.frames[index, -1] = frames
