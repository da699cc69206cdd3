"""The world as pure functions over a batch of N worlds: reset, step and observe.

State is a tuple of arrays; functions return new state and never mutate their inputs. A thin
stateful shell, `BatchedWorld`, adds automatic resets for the learner, the evaluator and the
gymnasium interface.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple, TypeVar

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.errors import ConfigError
from qnav.contracts.motion import (
    IncrementDynamics,
    Outcome,
    move_obstacles,
    outcome,
    step_robot,
    wrap_angle,
)
from qnav.contracts.observation import (
    LidarSpec,
    encode_frame,
    obstacle_features,
    target_features,
)
from qnav.sim import rng, room, sensor
from qnav.sim.config import WorldConfig
from qnav.sim.geometry import cast_lidar, cast_rotating_lidar, clearance
from qnav.sim.layouts import Layouts, layout_indices, layouts_of
from qnav.sim.raycast import cast_circles
from qnav.sim.room import first_valid
from qnav.sim.task import reward

F64 = NDArray[np.float64]

_CANDIDATES = 64
"""Rejection-sampling candidates per placement. Each is accepted with probability 1/4 or more
(a target seen from a corner of the spawn square), so all 64 fail with probability below 1e-8;
then the first candidate is used, clipped into the square."""

# Random streams of an episode's key (one per quantity drawn at reset).
_ROBOT, _TARGET, _OBSTACLE_XY, _OBSTACLE_HEADING, _OBSTACLE_SPEED = range(1, 6)


class WorldState(NamedTuple):
    """Everything that evolves in N worlds."""

    pose: F64
    """(N, 3) robot x, y in metres and heading in radians, in [-pi, pi)."""
    velocity: F64
    """(N, 2) forward speed (m/s) and turn rate (rad/s); zero under increment dynamics."""
    target_xy: F64
    """(N, 2) target position."""
    obstacle_xy: F64
    """(N, M, 2) obstacle centres."""
    obstacle_velocity: F64
    """(N, M, 2) obstacle velocities."""
    steps: NDArray[np.int64]
    """(N,) steps taken in the current episode."""
    seed: NDArray[np.int64]
    """(N,) each world's seed."""
    episode: NDArray[np.int64]
    """(N,) each world's episode counter, which with the seed fixes the episode's layout."""
    layout: NDArray[np.int64] | None = None
    """(N,) each world's static layout (`sim.layouts`; None: the paper's room, no layouts)."""
    obstacle_motion: F64 | None = None
    """(N, M, 3) each obstacle's heading, walking speed and 1 while it walks, 0 while it stands
    (`sim.room.walk`); None where obstacles move in straight lines (the paper's)."""


class Observation(NamedTuple):
    """What the robot senses, in physical units, plus the exact clearance used by the task."""

    pose: F64
    """(N, 3) robot pose, as a motion-capture system reports it."""
    target_xy: F64
    """(N, 2) target position."""
    scan_m: NDArray[np.float32] | None
    """(N, B) lidar ranges in metres, +inf for no return; None without a lidar."""
    clearance_m: F64
    """(N,) distance to the nearest surface (the paper's closest lidar reading d_l)."""
    obstacle_xy: F64
    """(N, M, 2) obstacle centres, as the onboard tracker reports them (here exact)."""
    obstacle_velocity: F64
    """(N, M, 2) obstacle velocities, as the onboard tracker reports them (here exact)."""
    layout: NDArray[np.int64] | None = None
    """(N,) the static layout each robot is in, for agents given the map (`sim.mapplan`);
    None in the paper's room."""

    def target_features(self) -> F64:
        """(N, 3) distance to target and sin, cos of its bearing."""
        return target_features(self.pose, self.target_xy)

    def obstacle_features(self) -> NDArray[np.float32]:
        """(N, OBSTACLE_FEATURES) the encoded obstacle inputs (`contracts.observation`)."""
        return obstacle_features(self.pose, self.obstacle_xy, self.obstacle_velocity)

    def frames(self, max_range_m: float, obstacle_inputs: bool = False) -> NDArray[np.float32]:
        """(N, F) network frames (`contracts.observation.encode_frame`), followed by the encoded
        obstacles for a network given obstacle inputs."""
        frames = encode_frame(self.scan_m, self.target_features(), max_range_m)
        if not obstacle_inputs:
            return frames
        return np.concatenate([frames, self.obstacle_features()], axis=-1)


class Transition(NamedTuple):
    """What one step produced in each world."""

    reward: F64
    """(N,) reward of the step."""
    outcome: NDArray[np.int8]
    """(N,) Outcome of the step (RUNNING, SUCCESS or COLLISION)."""
    terminated: NDArray[np.bool_]
    """(N,) the episode ended at the target or in a collision."""
    truncated: NDArray[np.bool_]
    """(N,) the episode ran out of steps without ending."""


def step_outcome(config: WorldConfig, distance_m: F64, clearance_m: F64) -> NDArray[np.int8]:
    """(N,) each world's Outcome at its robot's distance to the target and clearance: SUCCESS
    within the world's reach radius, COLLISION within the robot's radius of a surface, else
    RUNNING (the simulator's `step` and the sim-car of the stack both judge by this)."""
    return outcome(distance_m, clearance_m, config.robot_radius_m, config.reach_m)


def reset(
    config: WorldConfig, seed: NDArray[np.integer], episode: NDArray[np.integer]
) -> WorldState:
    """Start one episode in each world; its layout depends only on (seed, episode) of that world."""
    seeds = np.asarray(seed, dtype=np.int64)
    episodes = np.asarray(episode, dtype=np.int64)
    n = seeds.shape[0]
    keys = rng.episode_keys(seeds, episodes)
    size, margin = config.arena.size_m, config.spawn.wall_margin_m
    layouts = layouts_of(config.layout)
    layout = None
    m = config.obstacles.count
    if config.realistic:
        robot_xy, heading, target_xy, obstacle_xy = room.spawn(config, keys)
    elif layouts is not None:
        layout = layout_indices(config.layout, len(layouts), keys, episodes)
        robot_xy, heading = layouts.start_pose[layout, :2], layouts.start_pose[layout, 2]
        target_xy = layouts.goal_xy[layout]
    else:
        robot = rng.uniform(keys, _ROBOT, (3,))
        robot_xy = margin + (size - 2 * margin) * robot[:, :2]
        heading = 2 * math.pi * robot[:, 2] - math.pi
        target_xy = targets_around(config, robot_xy, rng.uniform(keys, _TARGET, (_CANDIDATES, 2)))
    if not config.realistic:
        radius = config.obstacles.radius_m
        low, high = obstacle_box(config, layout)
        obstacle_candidates = (
            low[:, None]
            + radius
            + ((high - low)[:, None] - 2 * radius)
            * rng.uniform(keys, _OBSTACLE_XY, (m, _CANDIDATES, 2))
        )
        gap = np.linalg.norm(obstacle_candidates - robot_xy[:, None, None, :], axis=-1) - radius
        obstacle_xy = first_valid(
            obstacle_candidates.reshape(n * m, _CANDIDATES, 2),
            (gap >= config.spawn.obstacle_clearance_m).reshape(n * m, _CANDIDATES),
        ).reshape(n, m, 2)
    direction = 2 * math.pi * rng.uniform(keys, _OBSTACLE_HEADING, (m,))
    speed = obstacle_speeds(config, rng.uniform(keys, _OBSTACLE_SPEED, (m, _CANDIDATES, 2)))
    obstacle_velocity = np.stack([np.cos(direction), np.sin(direction)], axis=-1) * speed[..., None]
    return WorldState(
        pose=np.concatenate([robot_xy, heading[:, None]], axis=1),
        velocity=np.zeros((n, 2)),
        target_xy=target_xy,
        obstacle_xy=obstacle_xy,
        obstacle_velocity=obstacle_velocity,
        steps=np.zeros(n, dtype=np.int64),
        seed=seeds,
        episode=episodes,
        layout=layout,
        obstacle_motion=room.motion_of(obstacle_velocity) if config.obstacles.walks else None,
    )


def obstacle_box(config: WorldConfig, layout: NDArray[np.int64] | None) -> tuple[F64, F64]:
    """(N or 1, 1, 2) the low and high corners of the box each world's obstacles move in: the
    room, or the box round each world's layout (`Layouts.boxes`)."""
    layouts = layouts_of(config.layout)
    if layouts is None or layout is None:
        return np.zeros((1, 1, 2)), np.full((1, 1, 2), config.arena.size_m)
    box = layouts.boxes[layout]
    return box[:, None, 0, :], box[:, None, 1, :]


def targets_around(config: WorldConfig, robot_xy: F64, draw: F64) -> F64:
    """Targets (N, 2) by the spawn law, from uniform draws (N, K, 2) in [0, 1).

    Uniform over the part of the annulus dmin <= d <= dmax around each robot position that lies
    in the spawn square: area-uniform candidates in the annulus, the first inside the square.
    """
    size, margin = config.arena.size_m, config.spawn.wall_margin_m
    lo, hi = config.spawn.target_min_distance_m, config.spawn.target_max_distance_m
    reach = np.sqrt(lo * lo + (hi * hi - lo * lo) * draw[..., 0])
    angle = 2 * math.pi * draw[..., 1]
    candidates = robot_xy[:, None, :] + reach[..., None] * np.stack(
        [np.cos(angle), np.sin(angle)], axis=-1
    )
    inside = ((candidates >= margin) & (candidates <= size - margin)).all(-1)
    return np.clip(first_valid(candidates, inside), margin, size - margin)


def obstacle_speeds(config: WorldConfig, u: F64) -> F64:
    """Obstacle speeds (...) ~ Normal(mean, std) truncated to [min, max], by rejection, from
    uniform draws (..., K, 2) in [0, 1): K Box-Muller candidates, the first inside the range."""
    params = config.obstacles
    normal = np.sqrt(-2.0 * np.log1p(-u[..., 0])) * np.cos(2 * math.pi * u[..., 1])
    speed = params.speed_mean_mps + params.speed_std_mps * normal
    valid = (speed >= params.speed_min_mps) & (speed <= params.speed_max_mps)
    choice = np.argmax(valid, axis=-1)
    chosen = np.take_along_axis(speed, choice[..., None], axis=-1)[..., 0]
    return np.clip(chosen, params.speed_min_mps, params.speed_max_mps)


RobotPath = tuple[F64, F64]
"""The robot's path over a control period: times (K,) relative to its end, ascending to 0, and
poses (N, K, 3) then."""


def robot_path(config: WorldConfig, state: WorldState, action: NDArray[np.integer]) -> RobotPath:
    """The path the robots take over the coming control period under `action`: their poses at
    the dynamics' physics steps (increment dynamics: at the period's start and end, the move
    read as taken at a steady rate), the last one the pose `step` gives."""
    period_s, dynamics = config.control_period_s, config.dynamics
    steps = 1
    if not isinstance(dynamics, IncrementDynamics):
        steps = max(1, round(period_s / dynamics.physics_dt_s))
    poses = [state.pose]
    for k in range(1, steps + 1):
        moved, _ = step_robot(state.pose, state.velocity, action, dynamics, period_s * k / steps)
        poses.append(moved)
    return period_s * (np.arange(steps + 1) / steps - 1.0), np.stack(poses, axis=1)


def rotating_scans(
    config: WorldConfig,
    state: WorldState,
    path: RobotPath | None = None,
    lidar: LidarSpec | None = None,
) -> NDArray[np.float32]:
    """(N, B) the scans of a lidar (`lidar`, else the world's) whose turn of
    `config.lidar_turn_s` ends at `state`: beam j leaves j / B of the turn after its start, from
    the robot's pose then (interpolated along `path`, the period's; None: the robot stood still)
    and among the obstacles where they were then (moved back from `state`: their bounces off the
    walls are reversible)."""
    lidar, turn_s = lidar or config.lidar, config.lidar_turn_s
    assert lidar is not None
    before_s: F64 = turn_s - turn_s / lidar.num_beams * np.arange(lidar.num_beams, dtype=float)
    times_s, poses = path if path is not None else (np.zeros(1), state.pose[:, None])
    radius = config.obstacles.radius_m
    scans = []
    for row in range(state.pose.shape[0]):
        heading = np.unwrap(poses[row, :, 2])
        beam_pose = np.stack(
            [np.interp(-before_s, times_s, track) for track in (*poses[row, :, :2].T, heading)],
            axis=1,
        )
        beam_obstacle_xy, _ = move_obstacles(
            state.obstacle_xy[row],
            -state.obstacle_velocity[row],
            radius,
            config.arena.size_m,
            before_s[:, None, None],
        )
        scans.append(cast_rotating_lidar(beam_pose, lidar, config.arena, beam_obstacle_xy, radius))
    return np.stack(scans)


def static_cylinders(config: WorldConfig, state: WorldState) -> tuple[Layouts, F64] | None:
    """Each world's layout and its cylinders (N, K, 2); None without layouts."""
    layouts = layouts_of(config.layout)
    if layouts is None or state.layout is None:
        return None
    return layouts, layouts.cylinders_of(state.layout)


def observe(config: WorldConfig, state: WorldState, path: RobotPath | None = None) -> Observation:
    """The observation in each world (with a rotating lidar, `config.lidar_turn_s`, its scans
    taken along `path`, the period's: `rotating_scans`; with a motion-capture latency, the pose
    read from along it), as the car's sensors give it (`config.sensor`: `sim.sensor`)."""
    statics = static_cylinders(config, state)
    if statics is not None:
        return _observe_layouts(config, state, *statics)
    if config.realistic:
        scan = None
        if config.lidar is not None:
            scan = room.room_scan(config, state, sensor.readings_of(config), path)
        gap = np.minimum(*room.room_clearance(config, state))
    else:
        scan, gap = _square_room(config, state, path)
    pose = state.pose
    effects = config.sensor
    if effects.scan_effects or effects.pose_effects:
        keys = sensor.step_keys(state.seed, state.episode, state.steps)
        if effects.scan_effects and scan is not None and config.lidar is not None:
            scan = sensor.sensed_scans(effects, config.lidar.num_beams, scan, keys)
        if effects.pose_effects:
            pose = sensor.measured_poses(effects, _pose_measured(config, state, path), keys)
    return Observation(pose, state.target_xy, scan, gap, state.obstacle_xy, state.obstacle_velocity)


def _square_room(
    config: WorldConfig, state: WorldState, path: RobotPath | None
) -> tuple[NDArray[np.float32] | None, F64]:
    """The scans (N, R) of the paper's room (R: the lidar's readings, `sensor.lidar_readings`,
    else its beams) and the clearances (N,)."""
    radius = config.obstacles.radius_m
    lidar = config.lidar
    if lidar is not None and config.sensor.lidar_readings:
        lidar = LidarSpec(num_beams=config.sensor.lidar_readings, max_range_m=lidar.max_range_m)
    scan = None
    if lidar is not None and config.lidar_turn_s:
        scan = rotating_scans(config, state, path, lidar)
    elif lidar is not None:
        scan = cast_lidar(state.pose, lidar, config.arena, state.obstacle_xy, radius)
    gap = clearance(state.pose[:, :2], config.arena, state.obstacle_xy, radius)
    return scan, gap


def _pose_measured(config: WorldConfig, state: WorldState, path: RobotPath | None) -> F64:
    """(N, 3) where the robots were when the motion capture measured the pose the car reads
    with this observation: `sensor.pose_latency_s` before it, along `path` (None: they stood)."""
    latency_s = config.sensor.pose_latency_s
    if not latency_s or path is None:
        return state.pose
    then = room.poses_at(path[0], path[1], np.array([-latency_s]))[:, 0]
    then[:, 2] = wrap_angle(then[:, 2])
    return then


def _observe_layouts(
    config: WorldConfig, state: WorldState, layouts: Layouts, cylinders: F64
) -> Observation:
    """`observe` in worlds of static layouts: no room walls, the layout's cylinders and the
    moving obstacles."""
    radius = config.obstacles.radius_m
    pose = state.pose
    n = pose.shape[0]
    beams = config.lidar.num_beams if config.lidar is not None else 0
    scan = np.full((n, beams), np.inf, dtype=np.float32)
    gap = np.full(n, np.inf)
    cast_circles(scan, gap, pose, config.lidar, cylinders, radius_m=layouts.cylinder_radius_m)
    if state.obstacle_xy.shape[1]:
        cast_circles(scan, gap, pose, config.lidar, state.obstacle_xy, radius_m=radius)
    return Observation(
        pose,
        state.target_xy,
        scan if config.lidar is not None else None,
        gap,
        state.obstacle_xy,
        state.obstacle_velocity,
        state.layout,
    )


def step(
    config: WorldConfig, state: WorldState, action: NDArray[np.integer]
) -> tuple[WorldState, Observation, Transition]:
    """Apply one action per world for one control period."""
    action = np.asarray(action)
    pose, velocity = step_robot(
        state.pose, state.velocity, action, config.dynamics, config.control_period_s
    )
    obstacle_xy, obstacle_velocity, motion = _moved_obstacles(config, state)
    new_state = state._replace(
        pose=pose,
        velocity=velocity,
        obstacle_xy=obstacle_xy,
        obstacle_velocity=obstacle_velocity,
        steps=state.steps + 1,
        obstacle_motion=motion,
    )
    timed = config.lidar_turn_s or config.sensor.pose_latency_s
    path = robot_path(config, state, action) if timed else None
    observation = observe(config, new_state, path)
    distance = np.linalg.norm(state.target_xy - pose[:, :2], axis=1)
    result = step_outcome(config, distance, observation.clearance_m)
    terminated = result != Outcome.RUNNING
    truncated = ~terminated & (new_state.steps >= config.max_episode_steps)
    transition = Transition(
        reward=reward(
            distance, observation.clearance_m, config.robot_radius_m, config.reward, config.reach_m
        ),
        outcome=result,
        terminated=terminated,
        truncated=truncated,
    )
    return new_state, observation, transition


def _moved_obstacles(config: WorldConfig, state: WorldState) -> tuple[F64, F64, F64 | None]:
    """The obstacles' centres, velocities and walking state after one control period: a random
    walk of their motion first (`ObstacleConfig.walks`: `sim.room.walk`), then straight on,
    bouncing off the room's walls (the paper's `move_obstacles` in its square; off every static
    segment, clutter too, in a polygon room or among clutter: `sim.room.bounce`)."""
    velocity, motion = state.obstacle_velocity, state.obstacle_motion
    keys = (
        rng.episode_keys(state.seed, state.episode)
        if config.realistic or motion is not None
        else None
    )
    if motion is not None:
        assert keys is not None
        motion, velocity = room.walk(config, motion, keys, state.steps)
    period_s = config.control_period_s
    if config.room.corners or config.clutter.boxes:
        assert keys is not None
        reach = room.bodies(config, keys).bounding_m()
        statics = room.static_segments(config, room.clutter_boxes(config, keys), bounce=True)
        moved = state.obstacle_xy + velocity * period_s
        xy, velocity = room.bounce(state.obstacle_xy, moved, velocity, reach, statics)
    else:
        radius: float | F64 = config.obstacles.radius_m
        if config.obstacles.shaped:
            assert keys is not None
            radius = room.bodies(config, keys).bounding_m()[..., None]
        low, high = obstacle_box(config, state.layout)
        xy, velocity = move_obstacles(
            state.obstacle_xy, velocity, radius, high - low, period_s, origin_m=low
        )
    if motion is not None:
        walking = motion[..., 2:] > 0
        heading = np.arctan2(velocity[..., 1], velocity[..., 0])
        motion = np.concatenate(
            [np.where(walking, heading[..., None], motion[..., :1]), motion[..., 1:]], axis=-1
        )
    return xy, velocity, motion


class StepResult(NamedTuple):
    """One step of a `BatchedWorld`."""

    observation: Observation
    """What to act on next: the first observation of a new episode where one just ended."""
    next_observation: Observation
    """The observation the step led to, before any automatic reset (for bootstrapping)."""
    transition: Transition
    """Reward, outcome, terminated and truncated of the step."""


class BatchedWorld:
    """N worlds stepped together, each starting its next episode as soon as one ends.

    World i uses seed `seed + i`; its k-th episode is the same as the k-th episode of a lone
    world with that seed.
    """

    def __init__(self, config: WorldConfig, num_worlds: int, seed: int = 0) -> None:
        if num_worlds < 1:
            raise ConfigError(f"num_worlds = {num_worlds} is out of range: allowed [1, inf)")
        self.config = config
        self.num_worlds = num_worlds
        self.state = reset(config, seed + np.arange(num_worlds), np.zeros(num_worlds, np.int64))

    def reset(self, seed: int | None = None) -> Observation:
        """Start new episodes everywhere (with fresh seeds if given) and observe them."""
        n = self.num_worlds
        seeds = self.state.seed if seed is None else seed + np.arange(n, dtype=np.int64)
        episodes = self.state.episode + 1 if seed is None else np.zeros(n, np.int64)
        self.state = reset(self.config, seeds, episodes)
        return observe(self.config, self.state)

    def step(self, action: NDArray[np.integer]) -> StepResult:
        """Step every world; worlds whose episode ended start the next one."""
        self.state, next_observation, transition = step(self.config, self.state, action)
        done = transition.terminated | transition.truncated
        observation = next_observation
        if done.any():
            index = np.flatnonzero(done)
            fresh = reset(self.config, self.state.seed[index], self.state.episode[index] + 1)
            self.state = scatter(self.state, index, fresh)
            observation = scatter(next_observation, index, observe(self.config, fresh))
        return StepResult(observation, next_observation, transition)


Rows = TypeVar("Rows", WorldState, Observation)


def scatter(whole: Rows, index: NDArray[np.intp], part: Rows) -> Rows:
    """A copy of `whole` (arrays with one row per world) whose rows `index` come from `part`."""
    fields: list[Any] = []
    for array, rows in zip(whole, part, strict=True):
        if array is None or rows is None:
            fields.append(None)
            continue
        merged = np.array(array, copy=True)
        merged[index] = rows
        fields.append(merged)
    return type(whole)(*fields)


def concatenate_rows(parts: Sequence[Rows]) -> Rows:
    """The rows of each of `parts` (arrays with one row per world), one after another."""
    fields: list[Any] = [
        None if column[0] is None else np.concatenate(column) for column in zip(*parts, strict=True)
    ]
    return type(parts[0])(*fields)


def take_rows(whole: Rows, index: NDArray[np.intp]) -> Rows:
    """The rows `index` of `whole` (arrays with one row per world), in that order."""
    fields: list[Any] = [None if array is None else array[index] for array in whole]
    return type(whole)(*fields)
