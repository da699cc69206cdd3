"""Exact geometry of the arena: the lidar and the clearance to the nearest surface.

Walls are the four sides of the square [0, size]^2 with gaps; obstacles are circles (spheres cut
by the lidar plane). Every function works on a batch of N worlds at once.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np
from numpy.typing import NDArray

from qnav.contracts import motion
from qnav.contracts.observation import LidarSpec
from qnav.sim.config import WALLS, ArenaConfig

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class WallSegments:
    """The solid parts of the walls as axis-aligned segments."""

    start: F64
    """(K, 2) segment start points."""
    end: F64
    """(K, 2) segment end points."""


@cache
def wall_segments(arena: ArenaConfig) -> WallSegments:
    """Split each wall at its openings into solid segments."""
    size = arena.size_m
    corners = {
        "south": ((0.0, 0.0), (1.0, 0.0)),
        "east": ((size, 0.0), (0.0, 1.0)),
        "north": ((0.0, size), (1.0, 0.0)),
        "west": ((0.0, 0.0), (0.0, 1.0)),
    }
    starts, ends = [], []
    for wall in WALLS:
        origin, axis = np.array(corners[wall][0]), np.array(corners[wall][1])
        gaps = sorted(
            (o.centre_m - o.width_m / 2, o.centre_m + o.width_m / 2)
            for o in arena.openings
            if o.wall == wall
        )
        cursor = 0.0
        for low, high in [*gaps, (size, size)]:
            if low > cursor:
                starts.append(origin + axis * cursor)
                ends.append(origin + axis * low)
            cursor = max(cursor, high)
    return WallSegments(
        start=np.array(starts, dtype=np.float64), end=np.array(ends, dtype=np.float64)
    )


def clearance(xy: F64, arena: ArenaConfig, obstacle_xy: F64, obstacle_radius_m: float) -> F64:
    """Distance from each robot centre (N, 2) to the nearest wall or obstacle surface of the
    arena (`contracts.motion.clearance` with its solid wall segments)."""
    segments = wall_segments(arena)
    return motion.clearance(xy, segments.start, segments.end, obstacle_xy, obstacle_radius_m)


def circles_clearance(xy: F64, centre_xy: F64, radius_m: float) -> F64:
    """(N,) distance from each point (N, 2) to the nearest surface of its circles (N, M, 2);
    +inf where it has none."""
    if centre_xy.shape[1] == 0:
        return np.full(xy.shape[0], np.inf)
    dx = centre_xy[..., 0] - xy[:, 0, None]
    dy = centre_xy[..., 1] - xy[:, 1, None]
    nearest: F64 = np.sqrt((dx * dx + dy * dy).min(axis=1)) - radius_m
    return nearest


def cast_lidar(
    pose: F64,
    lidar: LidarSpec,
    arena: ArenaConfig,
    obstacle_xy: F64,
    obstacle_radius_m: float,
) -> NDArray[np.float32]:
    """Ranges (N, B) from each pose (N, 3) along the lidar's beams.

    Rays leave the arena through the openings and see nothing beyond; a ray that meets nothing
    within the maximum range reads +inf (no return), as ROS lidar drivers report it.

    Walls are computed densely (every beam meets the box). Openings and obstacles cover few
    beams, so each is handled on the contiguous run of beam indices its angular extent covers.
    """
    beam_cos, beam_sin = _beam_trig(lidar)
    cos_h = np.cos(pose[:, 2:3]).astype(np.float32)
    sin_h = np.sin(pose[:, 2:3]).astype(np.float32)
    x = pose[:, 0:1].astype(np.float32)
    y = pose[:, 1:2].astype(np.float32)
    # World-frame beam directions by the angle-sum identities: no per-beam trigonometry.
    dx = cos_h * beam_cos - sin_h * beam_sin
    dy = sin_h * beam_cos + cos_h * beam_sin
    size = np.float32(arena.size_m)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_dx, inv_dy = 1.0 / dx, 1.0 / dy
        # From inside the box one of the two candidate walls per axis lies behind (negative t);
        # a beam parallel to an axis gives +inf and -inf, and the maximum picks +inf.
        ranges = np.minimum(
            np.maximum((size - x) * inv_dx, -x * inv_dx),
            np.maximum((size - y) * inv_dy, -y * inv_dy),
        )
    flat = ranges.reshape(-1)
    num_beams = lidar.num_beams
    if arena.openings:
        owner, beam = _beams_through_openings(pose, lidar, arena)
        flat[owner * num_beams + beam] = np.inf
    ranges[ranges > lidar.max_range_m] = np.inf
    return add_circles_to_scan(ranges, pose, lidar, obstacle_xy, obstacle_radius_m)


def cast_rotating_lidar(
    beam_pose: F64,
    lidar: LidarSpec,
    arena: ArenaConfig,
    beam_obstacle_xy: F64,
    obstacle_radius_m: float,
) -> NDArray[np.float32]:
    """The scan (B,) of a lidar whose beams leave one after another while the car and the
    obstacles move: beam j cast from the car's pose `beam_pose[j]` (B, 3) among the obstacles'
    centres `beam_obstacle_xy[j]` (B, M, 2) at its own time.

    Each beam is the beam of a whole scan from its own pose (the diagonal of B scans: about 10 ms
    for 720 beams), so it is exactly what `cast_lidar` gives a car frozen at that time.
    """
    beams = np.arange(lidar.num_beams)
    every = cast_lidar(beam_pose, lidar, arena, beam_obstacle_xy, obstacle_radius_m)
    return np.asarray(every[beams, beams])


def add_circles_to_scan(
    ranges: NDArray[np.float32],
    pose: F64,
    lidar: LidarSpec,
    obstacle_xy: F64,
    obstacle_radius_m: float,
    *,
    scale_m: float = 1.0,
) -> NDArray[np.float32]:
    """Scans (N, B) taken from poses (N, 3) as they read with circles (N, M, 2) added, in place.

    `ranges` holds what the beams see without the circles, in metres divided by `scale_m` (1 for
    raw ranges; the maximum range for encoded scans, whose values a circle can only lower). The
    learner uses this to put freshly drawn obstacles into stored obstacle-free scans.
    """
    if obstacle_xy.shape[1]:
        owner, beam, distance = _beams_on_circles(pose, lidar, obstacle_xy, obstacle_radius_m)
        visible = distance <= lidar.max_range_m
        np.minimum.at(
            ranges.reshape(-1),
            owner[visible] * lidar.num_beams + beam[visible],
            (distance[visible] / scale_m).astype(np.float32),
        )
    return ranges


@cache
def _beam_trig(lidar: LidarSpec) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    angles = lidar.beam_angles_rad()
    return np.cos(angles).astype(np.float32), np.sin(angles).astype(np.float32)


def _ragged(
    first: NDArray[np.int64], count: NDArray[np.int64]
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """For runs (first[i], count[i]): the run index and the value of every element, flattened."""
    count = np.maximum(count, 0)
    run = np.repeat(np.arange(first.size), count)
    starts = np.cumsum(count) - count
    offset = np.arange(run.size) - np.repeat(starts, count)
    return run, first[run] + offset


def _beam_run(
    start_rad: F64, span_rad: F64, lidar: LidarSpec
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """First beam index and beam count of the closed angular interval [start, start + span]."""
    increment = lidar.angle_increment_rad
    first = np.ceil(start_rad / increment).astype(np.int64)
    last = np.floor((start_rad + span_rad) / increment).astype(np.int64)
    return first, last - first + 1


def _beams_through_openings(
    pose: F64, lidar: LidarSpec, arena: ArenaConfig
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(world, beam) of every ray that leaves through an opening: those aimed between its jambs."""
    jambs = opening_jambs(arena)  # (G, 2, 2)
    offset = jambs[None] - pose[:, None, None, :2]  # (N, G, 2, 2)
    bearing = np.arctan2(offset[..., 1], offset[..., 0]) - pose[:, None, None, 2]
    start = np.mod(bearing[..., 0], 2 * np.pi)
    span = np.mod(bearing[..., 1] - bearing[..., 0] + np.pi, 2 * np.pi) - np.pi
    # Seen from inside the box an opening subtends less than pi: order its jambs by angle.
    start = np.where(span < 0, np.mod(start + span, 2 * np.pi), start)
    first, count = _beam_run(start.reshape(-1), np.abs(span).reshape(-1), lidar)
    run, beam = _ragged(first, count)
    return run // jambs.shape[0], beam % lidar.num_beams


def _beams_on_circles(
    pose: F64, lidar: LidarSpec, centre_xy: F64, radius_m: float
) -> tuple[NDArray[np.int64], NDArray[np.int64], F64]:
    """(world, beam, range) of every beam that meets one of the circles (N, M, 2)."""
    num_circles = centre_xy.shape[1]
    offset = centre_xy - pose[:, None, :2]
    cos_h, sin_h = np.cos(pose[:, 2:3]), np.sin(pose[:, 2:3])
    # Centres in the robot frame; a circle covers the beams within asin(r / D) of its bearing.
    ahead = (cos_h * offset[..., 0] + sin_h * offset[..., 1]).reshape(-1)
    left = (-sin_h * offset[..., 0] + cos_h * offset[..., 1]).reshape(-1)
    distance_sq = ahead * ahead + left * left
    inside = distance_sq <= radius_m * radius_m
    half = np.where(
        inside,
        np.pi,
        np.arcsin(np.minimum(1.0, radius_m / np.sqrt(np.maximum(distance_sq, 1e-300)))),
    )
    bearing = np.arctan2(left, ahead)
    first, count = _beam_run(bearing - half, 2 * half, lidar)
    count = np.minimum(count, lidar.num_beams)
    run, beam = _ragged(first, count)
    beam %= lidar.num_beams
    beam_cos, beam_sin = lidar_angles_f64(lidar)
    along = ahead[run] * beam_cos[beam] + left[run] * beam_sin[beam]
    disc = along * along - (distance_sq[run] - radius_m * radius_m)
    near = np.where(disc >= 0, along - np.sqrt(np.maximum(disc, 0.0)), np.inf)
    # A sensor inside a circle touches its surface: range 0.
    near = np.where(inside[run], 0.0, np.where(near >= 0, near, np.inf))
    return run // num_circles, beam, near


@cache
def lidar_angles_f64(lidar: LidarSpec) -> tuple[F64, F64]:
    """Cosine and sine of each beam angle."""
    angles = lidar.beam_angles_rad()
    return np.cos(angles), np.sin(angles)


@cache
def opening_jambs(arena: ArenaConfig) -> F64:
    """(G, 2, 2) the two end points of each opening."""
    size = arena.size_m
    jambs = []
    for opening in arena.openings:
        low, high = opening.centre_m - opening.width_m / 2, opening.centre_m + opening.width_m / 2
        fixed = {"south": 0.0, "west": 0.0, "north": size, "east": size}[opening.wall]
        if opening.wall in ("south", "north"):
            jambs.append([[low, fixed], [high, fixed]])
        else:
            jambs.append([[fixed, low], [fixed, high]])
    return np.array(jambs, dtype=np.float64).reshape(-1, 2, 2)
