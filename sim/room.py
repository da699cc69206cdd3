"""A room that is not the simulator's square: walls along a polygon, boxes on the floor that no
map holds, obstacles of several sizes and shapes, and obstacles that turn, stop and start.

Everything the lidar can meet is a circle or a segment, and one ray caster (`cast_rays`) casts
them all: the room's walls and the clutter's sides are segments; a moving obstacle is a cylinder
(one circle), a box (four segments, turned to its heading) or a walking person's two legs (two
small circles side by side that swing along the heading as it walks). Sizes, shapes and the
clutter are drawn from each episode's key (`sim.rng`), so they need no state: only where each
obstacle heads, how fast it walks and whether it walks (`WorldState.obstacle_motion`) evolve.

None of this runs in the paper's scenarios: `sim.world` calls it where a setting asks for it
(`WorldConfig.realistic`, `ObstacleConfig.walks`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import cache
from typing import NamedTuple, Protocol

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.motion import wrap_angle
from qnav.sim import rng
from qnav.sim.config import WorldConfig
from qnav.sim.geometry import wall_segments

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

CYLINDER, BOX, LEGS = 0, 1, 2
"""An obstacle's kind."""
LEG_RADIUS_M = 0.06
"""Radius of each of a person's legs."""
LEG_SPACING_M = 0.25
"""Between the centres of a person's legs, across the walking direction."""
STRIDE_M = 0.3
"""How far apart along the walking direction a walking person's legs swing at most."""
GAIT_PERIOD_S = 1.0
"""Time of one swing of both legs."""
PARKED_M = 1.0e6
"""Where an unused circle or segment slot sits: beyond every lidar's range."""
CANDIDATES = 256
"""Rejection-sampling candidates per placement in a room (more than the square's 64: a room
with clutter rejects more)."""

# Random streams of an episode's key (sim.world uses 1-5, sim.layouts 17).
_KIND, _SIZE, _PHASE, _CLUTTER_XY, _CLUTTER_SIZE, _CLUTTER_YAW = range(40, 46)
_ROBOT, _HEADING, _TARGET, _OBSTACLE_XY = range(46, 50)
_WALK_HEADING, _WALK_SPEED, _WALK_STOP = range(50, 53)


class RoomState(Protocol):
    """What the room's geometry reads of a world's state (`sim.world.WorldState` is one)."""

    @property
    def pose(self) -> F64:
        """(N, 3) the robot's pose."""

    @property
    def obstacle_xy(self) -> F64:
        """(N, M, 2) obstacle centres."""

    @property
    def obstacle_velocity(self) -> F64:
        """(N, M, 2) obstacle velocities."""

    @property
    def obstacle_motion(self) -> F64 | None:
        """(N, M, 3) the obstacles' walking state, or None (they move in straight lines)."""

    @property
    def steps(self) -> I64:
        """(N,) steps taken in the episode."""

    @property
    def seed(self) -> I64:
        """(N,) each world's seed."""

    @property
    def episode(self) -> I64:
        """(N,) each world's episode."""


class Bodies(NamedTuple):
    """Each obstacle's shape, drawn once per episode."""

    kind: I64
    """(N, M) CYLINDER, BOX or LEGS."""
    half: F64
    """(N, M, 2) a cylinder's radius (twice), a box's half length and half width, the legs'
    radius and half their spacing."""
    phase: F64
    """(N, M) the gait's phase at the episode's start."""

    def bounding_m(self) -> F64:
        """(N, M) the radius of the circle round each obstacle's centre that holds it."""
        box = np.hypot(self.half[..., 0], self.half[..., 1])
        legs = self.half[..., 1] + self.half[..., 0] + STRIDE_M / 2
        return np.where(self.kind == BOX, box, np.where(self.kind == LEGS, legs, self.half[..., 0]))


def bodies(config: WorldConfig, keys: NDArray[np.uint64]) -> Bodies:
    """The shapes of each world's obstacles in its episode (keys (N,): `rng.episode_keys`)."""
    o, m = config.obstacles, config.obstacles.count
    draw = rng.uniform(keys, _KIND, (m,))
    kind = np.where(
        draw < o.box_share, BOX, np.where(draw < o.box_share + o.legs_share, LEGS, CYLINDER)
    )
    high = o.radius_max_m or o.radius_m
    size = o.radius_m + (high - o.radius_m) * rng.uniform(keys, _SIZE, (m, 2))
    half = np.where((kind == CYLINDER)[..., None], size[..., :1], size)
    half = np.where((kind == LEGS)[..., None], np.array([LEG_RADIUS_M, LEG_SPACING_M / 2]), half)
    return Bodies(kind.astype(np.int64), half, 2 * math.pi * rng.uniform(keys, _PHASE, (m,)))


@cache
def room_walls(config: WorldConfig) -> F64:
    """(S, 4) the room's solid walls as segments (x0, y0, x1, y1): the polygon's sides, or the
    square arena's walls less their openings."""
    corners = np.array(config.room.corners, dtype=np.float64)
    if corners.size:
        return np.concatenate([corners, np.roll(corners, -1, axis=0)], axis=1)
    segments = wall_segments(config.arena)
    return np.concatenate([segments.start, segments.end], axis=1)


@cache
def bounding_walls(config: WorldConfig) -> F64:
    """(S, 4) the walls obstacles bounce off: the polygon's sides, or the square's four whole
    sides (an obstacle does not leave through an opening)."""
    if config.room.corners:
        return room_walls(config)
    s = config.arena.size_m
    return np.array([[0, 0, s, 0], [s, 0, s, s], [s, s, 0, s], [0, s, 0, 0]], dtype=np.float64)


def inside_room(config: WorldConfig, xy: F64) -> NDArray[np.bool_]:
    """(...) whether each point (..., 2) lies inside the room (even-odd rule on the polygon)."""
    if not config.room.corners:
        size = config.arena.size_m
        return np.asarray(((xy >= 0) & (xy <= size)).all(-1))
    walls = room_walls(config)
    x, y = xy[..., 0, None], xy[..., 1, None]
    x0, y0, x1, y1 = walls.T
    straddles = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        crossing_x = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    return np.asarray(((straddles & (x < crossing_x)).sum(-1) % 2) == 1)


def box_sides(centre: F64, yaw: F64, half: F64) -> F64:
    """(..., 4, 4) the four sides (x0, y0, x1, y1) of boxes with centres (..., 2), headings
    (...) and half length and width (..., 2)."""
    forward = np.stack([np.cos(yaw), np.sin(yaw)], axis=-1) * half[..., :1]
    left = np.stack([-np.sin(yaw), np.cos(yaw)], axis=-1) * half[..., 1:]
    corners = np.stack(
        [centre + forward + left, centre - forward + left, centre - forward - left],
        axis=-2,
    )
    corners = np.concatenate([corners, (centre + forward - left)[..., None, :]], axis=-2)
    return np.concatenate([corners, np.roll(corners, -1, axis=-2)], axis=-1)


def segment_distance(xy: F64, segments: F64) -> F64:
    """(..., S) each point's (..., 2) distance to each segment (..., S, 4) (broadcast)."""
    px, py = xy[..., 0, None], xy[..., 1, None]
    sx, sy = segments[..., 0], segments[..., 1]
    dx, dy = segments[..., 2] - sx, segments[..., 3] - sy
    length_sq = np.maximum(dx * dx + dy * dy, 1e-18)
    t = np.clip(((px - sx) * dx + (py - sy) * dy) / length_sq, 0.0, 1.0)
    ex, ey = px - (sx + t * dx), py - (sy + t * dy)
    return np.asarray(np.sqrt(ex * ex + ey * ey))


_CLUTTER: dict[tuple[int, int], F64] = {}
"""Each episode's clutter by (the world's settings' hash, the episode's key): drawn once, read
every step."""
_CLUTTER_KEPT = 100_000
"""Episodes whose clutter is kept before the store is emptied."""


def clutter_boxes(config: WorldConfig, keys: NDArray[np.uint64]) -> F64:
    """(N, K, 5) each episode's boxes on the floor: centre x, y, half length, half width, yaw;
    each inside the room, clear of its walls by 0.1 m (else the first draw). Drawn once per
    episode (`draw_clutter`) and kept."""
    world = hash(config)
    missing = np.array([k for k in keys.tolist() if (world, k) not in _CLUTTER], np.uint64)
    if missing.size:
        if len(_CLUTTER) > _CLUTTER_KEPT:
            _CLUTTER.clear()
        for key, boxes in zip(missing.tolist(), draw_clutter(config, missing), strict=True):
            _CLUTTER[(world, key)] = boxes
    boxes = [_CLUTTER[(world, key)] for key in keys.tolist()]
    return np.stack(boxes).reshape(keys.shape[0], config.clutter.boxes, 5)


def draw_clutter(config: WorldConfig, keys: NDArray[np.uint64]) -> F64:
    """`clutter_boxes` drawn afresh from the episodes' keys (N,)."""
    k, c = config.clutter.boxes, config.clutter
    size = config.arena.size_m
    span = c.size_max_m - c.size_min_m
    half = (c.size_min_m + span * rng.uniform(keys, _CLUTTER_SIZE, (k, 2))) / 2
    yaw = 2 * math.pi * rng.uniform(keys, _CLUTTER_YAW, (k,))
    xy = size * rng.uniform(keys, _CLUTTER_XY, (k, CANDIDATES, 2))
    reach = np.hypot(half[..., 0], half[..., 1])[..., None]
    valid = inside_room(config, xy) & (
        segment_distance(xy, room_walls(config)).min(-1) >= reach + 0.1
    )
    n = keys.shape[0]
    centre = first_valid(xy.reshape(n * k, CANDIDATES, 2), valid.reshape(n * k, CANDIDATES))
    return np.concatenate([centre.reshape(n, k, 2), half, yaw[..., None]], axis=-1)


def static_segments(config: WorldConfig, clutter: F64, *, bounce: bool = False) -> F64:
    """(N, S, 4) every static segment of each world: the room's walls (with `bounce`, the walls
    obstacles bounce off: `bounding_walls`) and its clutter's sides."""
    n = clutter.shape[0]
    solid = bounding_walls(config) if bounce else room_walls(config)
    walls = np.broadcast_to(solid, (n, *solid.shape))
    sides = box_sides(clutter[..., :2], clutter[..., 4], clutter[..., 2:4]).reshape(n, -1, 4)
    return np.concatenate([walls, sides], axis=1)


def first_valid(candidates: F64, valid: NDArray[np.bool_]) -> F64:
    """candidates (N, K, D), valid (N, K) -> (N, D): the first valid candidate (else the first)."""
    choice = np.argmax(valid, axis=1)
    return np.take_along_axis(candidates, choice[:, None, None], axis=1)[:, 0, :]


def free_of(config: WorldConfig, xy: F64, statics: F64, margin_m: F64 | float) -> NDArray[np.bool_]:
    """(N, K) whether points (N, K, 2) lie inside the room at least `margin_m` from every static
    segment (N, S, 4) of their world."""
    distance = segment_distance(xy, statics[:, None]).min(-1)
    return np.asarray(inside_room(config, xy) & (distance >= margin_m))


class Spawn(NamedTuple):
    """Where an episode in a room starts."""

    robot_xy: F64
    """(N, 2) the robot."""
    heading: F64
    """(N,) its heading."""
    target_xy: F64
    """(N, 2) the target."""
    obstacle_xy: F64
    """(N, M, 2) the obstacles' centres."""


def spawn(config: WorldConfig, keys: NDArray[np.uint64]) -> Spawn:
    """The spawn law of the paper's room (`sim.world.reset`) in any room: the robot and the
    target at least `spawn.wall_margin_m` from the walls and the clutter, the target 0.5-3 m away
    (`spawn.target_*`), the obstacles inside the room clear of the walls and the clutter and at
    least `spawn.obstacle_clearance_m` from the robot."""
    n, size = keys.shape[0], config.arena.size_m
    margin = config.spawn.wall_margin_m
    statics = static_segments(config, clutter_boxes(config, keys))
    xy = margin + (size - 2 * margin) * rng.uniform(keys, _ROBOT, (CANDIDATES, 2))
    robot_xy = first_valid(xy, free_of(config, xy, statics, margin))
    heading = 2 * math.pi * rng.uniform(keys, _HEADING, ()) - math.pi
    lo, hi = config.spawn.target_min_distance_m, config.spawn.target_max_distance_m
    draw = rng.uniform(keys, _TARGET, (CANDIDATES, 2))
    reach = np.sqrt(lo * lo + (hi * hi - lo * lo) * draw[..., 0])
    angle = 2 * math.pi * draw[..., 1]
    xy = robot_xy[:, None] + reach[..., None] * np.stack([np.cos(angle), np.sin(angle)], -1)
    target_xy = first_valid(xy, free_of(config, xy, statics, margin))
    m = config.obstacles.count
    bounding = bodies(config, keys).bounding_m()  # (N, M)
    xy = size * rng.uniform(keys, _OBSTACLE_XY, (m, CANDIDATES, 2))  # (N, M, K, 2)
    flat = xy.reshape(n, m * CANDIDATES, 2)
    reach = np.repeat(bounding, CANDIDATES, axis=1)
    gap = np.linalg.norm(flat - robot_xy[:, None], axis=-1) - reach
    valid = free_of(config, flat, statics, reach) & (gap >= config.spawn.obstacle_clearance_m)
    obstacle_xy = first_valid(xy.reshape(n * m, CANDIDATES, 2), valid.reshape(n * m, CANDIDATES))
    return Spawn(robot_xy, heading, target_xy, obstacle_xy.reshape(n, m, 2))


def motion_of(velocity: F64) -> F64:
    """(N, M, 3) the walking state of obstacles moving at `velocity` (N, M, 2): heading, walking
    speed, and 1 for walking."""
    heading = np.arctan2(velocity[..., 1], velocity[..., 0])
    speed = np.hypot(velocity[..., 0], velocity[..., 1])
    return np.stack([heading, speed, np.ones_like(speed)], axis=-1)


def _normal(keys: NDArray[np.uint64], stream: int, steps: I64) -> F64:
    """(N, M) standard normal draws, one per obstacle of each world at its step."""
    u1 = rng.uniform_at(keys, stream, steps)
    u2 = rng.uniform_at(keys, stream + 100, steps)
    return np.asarray(np.sqrt(-2.0 * np.log1p(-u1)) * np.cos(2 * math.pi * u2))


def obstacle_keys(keys: NDArray[np.uint64], count: int) -> NDArray[np.uint64]:
    """(N, M) a key per obstacle of each world's episode."""
    return rng.episode_keys(keys[:, None], np.arange(count)[None, :])


def walk(config: WorldConfig, motion: F64, keys: NDArray[np.uint64], steps: I64) -> tuple[F64, F64]:
    """One control period's random walk of the obstacles' motion (N, M, 3) at each world's step:
    the heading and the walking speed change by Gaussian steps, a walker stops and a stopped one
    walks on by chance (`ObstacleConfig`); the new motion and velocities (N, M, 2)."""
    o = config.obstacles
    per = obstacle_keys(keys, motion.shape[1])
    at = np.broadcast_to(steps[:, None], per.shape)
    heading = motion[..., 0] + o.heading_walk_rad * _normal(per, _WALK_HEADING, at)
    speed = np.clip(
        motion[..., 1] + o.speed_walk_mps * _normal(per, _WALK_SPEED, at),
        o.speed_min_mps,
        o.speed_max_mps,
    )
    walking = motion[..., 2]
    if o.stop_probability:
        chance = rng.uniform_at(per, _WALK_STOP, at)
        walking = np.where(
            walking > 0, chance >= o.stop_probability, chance < o.start_probability
        ).astype(np.float64)
    moved = np.stack([wrap_angle(heading), speed, walking], axis=-1)
    return moved, velocity_of(moved)


def velocity_of(motion: F64) -> F64:
    """(N, M, 2) the velocities of obstacles in the walking state `motion` (N, M, 3)."""
    speed = motion[..., 1] * motion[..., 2]
    return np.stack([np.cos(motion[..., 0]), np.sin(motion[..., 0])], axis=-1) * speed[..., None]


def bounce(xy: F64, moved: F64, velocity: F64, reach_m: F64, statics: F64) -> tuple[F64, F64]:
    """Obstacles (N, M) that would come within their reach (N, M) of a static segment
    (N, S, 4) by moving from `xy` to `moved` stay where they were and turn their velocity
    (N, M, 2) as a mirror along the nearest such segment turns it."""
    distance = segment_distance(moved, statics[:, None])  # (N, M, S)
    nearest = distance.argmin(-1)
    hit = np.take_along_axis(distance, nearest[..., None], -1)[..., 0] < reach_m
    segment = np.take_along_axis(statics, nearest.reshape(nearest.shape[0], -1, 1), axis=1)
    along = segment[..., 2:] - segment[..., :2]
    along = along / np.maximum(np.linalg.norm(along, axis=-1, keepdims=True), 1e-12)
    mirrored = 2 * np.sum(velocity * along, -1, keepdims=True) * along - velocity
    # Away from the segment (a mirrored velocity that still approaches it is reversed).
    before = segment_distance(xy, segment[:, :, None])[..., 0]
    after = segment_distance(xy + 1e-3 * mirrored, segment[:, :, None])[..., 0]
    mirrored = np.where((after < before)[..., None], -velocity, mirrored)
    return np.where(hit[..., None], xy, moved), np.where(hit[..., None], mirrored, velocity)


def cast_rays(
    origin: F64,
    direction: F64,
    circles: F64,
    segments: Sequence[F64],
    max_range_m: float,
) -> NDArray[np.float32]:
    """(N, R) the range along each ray, from `origin` (N, R, 2) along the unit `direction`
    (N, R, 2), to the nearest circle (x, y, radius) of `circles` (N, R or 1, C, 3) or segment
    (x0, y0, x1, y1) of each of `segments` (N, R or 1, S, 4); +inf for none within
    `max_range_m`. A ray from inside a circle reads 0. In float32, as `sim.geometry`'s lidar."""
    f32 = np.float32
    ox, oy = origin[..., 0, None].astype(f32), origin[..., 1, None].astype(f32)
    dx, dy = direction[..., 0, None].astype(f32), direction[..., 1, None].astype(f32)
    best = np.full(origin.shape[:-1], np.inf, dtype=f32)
    if circles.shape[-2]:
        round_ = circles.astype(f32)
        cx, cy, r = round_[..., 0] - ox, round_[..., 1] - oy, round_[..., 2]
        along = cx * dx + cy * dy
        inside = cx * cx + cy * cy - r * r
        disc = along * along - inside
        near = along - np.sqrt(np.maximum(disc, f32(0.0)))
        near = np.where(
            inside <= 0, f32(0.0), np.where((disc >= 0) & (near >= 0), near, f32(np.inf))
        )
        np.minimum(best, near.min(-1), out=best)
    for group in segments:
        if not group.shape[-2]:
            continue
        side = group.astype(f32)
        wx, wy = side[..., 0] - ox, side[..., 1] - oy
        ex, ey = side[..., 2] - side[..., 0], side[..., 3] - side[..., 1]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            inverse = f32(1.0) / (dx * ey - dy * ex)
            t = (wx * ey - wy * ex) * inverse
            u = (wx * dy - wy * dx) * inverse
        hit = np.isfinite(inverse) & (t >= 0) & (u >= 0) & (u <= 1)
        np.minimum(best, np.where(hit, t, f32(np.inf)).min(-1), out=best)
    best[best > max_range_m] = np.inf
    return best


def obstacle_heading(state_motion: F64 | None, velocity: F64) -> tuple[F64, NDArray[np.bool_]]:
    """(N, M) each obstacle's heading and whether it walks, from its walking state (N, M, 3) or,
    without one, its velocity (N, M, 2)."""
    speed = np.hypot(velocity[..., 0], velocity[..., 1])
    if state_motion is not None:
        return state_motion[..., 0], speed > 0
    return np.arctan2(velocity[..., 1], velocity[..., 0]), speed > 0


def moving_shapes(
    shapes: Bodies, xy: F64, heading: F64, walking: NDArray[np.bool_], time_s: F64
) -> tuple[F64, F64]:
    """The circles (N, T, 2M, 3) and segments (N, T, 4M, 4) of the obstacles (N, M) with centres
    `xy` (N, T, M, 2) at T instants `time_s` (N, T): a cylinder's circle, a person's two legs
    (swinging along the heading while it walks), a box's four sides; unused slots parked."""
    n, t, m = xy.shape[:3]
    forward = np.stack([np.cos(heading), np.sin(heading)], axis=-1)[:, None]  # (N, 1, M, 2)
    left = np.stack([-forward[..., 1], forward[..., 0]], axis=-1)
    kind = shapes.kind[:, None]
    swing = (STRIDE_M / 2) * np.sin(
        shapes.phase[:, None] + 2 * math.pi * time_s[..., None] / GAIT_PERIOD_S
    )
    swing = np.where(walking[:, None], swing, 0.0)[..., None]
    spread = shapes.half[:, None, :, 1:]
    legs = np.stack([xy + spread * left + swing * forward, xy - spread * left - swing * forward], 2)
    round_xy = np.where((kind == LEGS)[:, :, None, :, None], legs, xy[:, :, None])  # (N,T,2,M,2)
    radius = np.broadcast_to(shapes.half[:, None, None, :, 0], (n, t, 2, m))
    used = np.stack([kind != BOX, kind == LEGS], axis=2)  # (N, 1, 2, M)
    circles = np.concatenate([round_xy, radius[..., None]], axis=-1)
    circles = np.where(used[..., None], circles, np.array([PARKED_M, PARKED_M, 0.0]))
    sides = box_sides(xy, np.broadcast_to(heading[:, None], (n, t, m)), shapes.half[:, None])
    sides = np.where((kind == BOX)[..., None, None], sides, PARKED_M)
    return circles.reshape(n, t, 2 * m, 3), sides.reshape(n, t, 4 * m, 4)


def poses_at(times_s: F64, poses: F64, at_s: F64) -> F64:
    """(N, R, 3) the poses (N, K, 3) taken at `times_s` (K,), ascending, interpolated linearly
    (the heading unwrapped) at the instants `at_s` (R,) within them."""
    heading = np.unwrap(poses[..., 2], axis=1)
    track = np.concatenate([poses[..., :2], heading[..., None]], axis=-1)
    upper = np.clip(np.searchsorted(times_s, at_s), 1, len(times_s) - 1)
    weight = (at_s - times_s[upper - 1]) / (times_s[upper] - times_s[upper - 1])
    weight = np.clip(weight, 0.0, 1.0)[None, :, None]
    return np.asarray(track[:, upper - 1] * (1 - weight) + track[:, upper] * weight)


class Surfaces(NamedTuple):
    """Everything the lidar can meet in N worlds at T instants."""

    circles: F64
    """(N, T, C, 3) the obstacles' circles: cylinders and legs (unused slots parked)."""
    sides: F64
    """(N, T, 4M, 4) the moving boxes' sides (unused slots parked)."""
    statics: F64
    """(N, 1, S, 4) the walls and the clutter's sides."""


def surfaces_at(config: WorldConfig, state: RoomState, before_s: F64) -> Surfaces:
    """Every world's surfaces `before_s` (T,) seconds before `state`: the obstacles' shapes as
    they are at `state` (a box's heading, the legs' swing), moved back along their velocities;
    the walls and the clutter."""
    keys = rng.episode_keys(state.seed, state.episode)
    shapes = bodies(config, keys)
    statics = static_segments(config, clutter_boxes(config, keys))
    heading, walking = obstacle_heading(state.obstacle_motion, state.obstacle_velocity)
    time_s = np.asarray(state.steps[:, None] * config.control_period_s, dtype=np.float64)
    circles, sides = moving_shapes(shapes, state.obstacle_xy[:, None], heading, walking, time_s)
    n, m = state.obstacle_xy.shape[:2]
    if before_s.any():
        back = -state.obstacle_velocity[:, None] * before_s[:, None, None]  # (N, T, M, 2)
        t = before_s.shape[0]
        shift = np.concatenate([back, np.zeros((n, t, m, 1))], -1)[:, :, None]  # (N,T,1,M,3)
        circles = (circles.reshape(n, 1, 2, m, 3) + shift).reshape(n, t, 2 * m, 3)
        moved = sides.reshape(n, 1, m, 4, 4) + np.tile(back, 2)[:, :, :, None]
        sides = moved.reshape(n, t, 4 * m, 4)
    return Surfaces(circles, sides, statics[:, None])


RobotPath = tuple[F64, F64]
"""The robot's path over a control period (`sim.world.robot_path`): times (K,), poses (N, K, 3)."""


def room_scan(
    config: WorldConfig, state: RoomState, readings: int, path: RobotPath | None
) -> NDArray[np.float32]:
    """(N, R) the lidar's `readings` ranges in each room, reading i at i 2 pi / R from the
    heading; with a rotating lidar (`lidar_turn_s`) each cast from the robot's pose at its own
    time (along `path`, the period's; None: the robot stood still) among the obstacles where
    they were then (moved back along their velocities)."""
    assert config.lidar is not None
    angles = np.arange(readings) * (2 * math.pi / readings)
    before_s: F64 = np.zeros(1)
    poses = state.pose[:, None]
    if config.lidar_turn_s:
        turn_s = config.lidar_turn_s
        before_s = np.asarray(turn_s - turn_s / readings * np.arange(readings), np.float64)
        if path is not None:
            poses = poses_at(path[0], path[1], -before_s)
    surfaces = surfaces_at(config, state, before_s)
    angle = poses[..., 2] + angles
    origin = np.broadcast_to(poses[..., :2], (*angle.shape, 2))
    direction = np.stack([np.cos(angle), np.sin(angle)], axis=-1)
    segments = (surfaces.sides, surfaces.statics)
    return cast_rays(origin, direction, surfaces.circles, segments, config.lidar.max_range_m)


def room_clearance(config: WorldConfig, state: RoomState) -> tuple[F64, F64]:
    """(N,) each robot's distance to the nearest static surface (walls and clutter) and to the
    nearest moving obstacle's."""
    circles, sides, statics = surfaces_at(config, state, np.zeros(1))
    xy = state.pose[:, None, :2]  # (N, 1, 2) against (N, 1, C, ...)
    static = segment_distance(xy, statics).min(-1)[:, 0]
    moving = segment_distance(xy, sides).min(-1, initial=np.inf)[:, 0]
    rounds = np.hypot(circles[..., 0] - xy[..., 0, None], circles[..., 1] - xy[..., 1, None])
    rounds = (rounds - circles[..., 2]).min(-1, initial=np.inf)[:, 0]
    return np.asarray(static), np.minimum(moving, rounds)
