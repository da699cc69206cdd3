"""Sampling strategies over the replay storage: which stored steps, which targets, which
obstacles.

Beside the storage (`training.replay`), as Stable-Baselines3 keeps HER's goal selection beside
its buffer. A batch is drawn in three steps, each a strategy of its own:

1. the stored steps: uniformly (the paper), or in proportion to their last |TD error|
   (prioritized replay, Schaul et al. 2016), with importance weights;
2. each step's target (`Relabel`): fresh in the arena (the paper), around the robot (local), a
   position reached later (hindsight), or the episode's own;
3. each step's obstacles: the episode's own, or, with a probability, fresh ones moving along
   the stored path (`redraw_obstacles_in_windows`).

The reward and termination are then recomputed for that target and those obstacles
(`EpisodeReplay.transitions_at`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.motion import move_obstacles
from qnav.sim.config import WorldConfig
from qnav.sim.geometry import add_circles_to_scan
from qnav.sim.layouts import layouts_of
from qnav.sim.world import obstacle_speeds, targets_around
from qnav.training.config import Relabel
from qnav.training.replay import Batch, EpisodeReplay, Seen

_LOCAL_CANDIDATES = 64
"""Candidates per local target (as in the simulator's spawn)."""
_OBSTACLE_CANDIDATES = 8
"""Candidate paths per re-drawn obstacle; the first that never touches the robot before the
sampled step is used (each is accepted with probability about 0.9, so all 8 fail with
probability about 1e-8)."""
_SPEED_CANDIDATES = 8
"""Box-Muller candidates per re-drawn obstacle speed; each lies in the speed range with
probability about 0.9."""


def sample(
    replay: EpisodeReplay,
    batch_size: int,
    rng: np.random.Generator,
    relabel: Relabel,
    *,
    n_step: int = 1,
    gamma: float = 0.97,
    obstacle_redraw_probability: float = 0.0,
) -> Batch:
    """Random transitions of the replay, drawn uniformly, each with its own target drawn by
    `relabel` and, with probability `obstacle_redraw_probability`, fresh obstacles in place of
    its episode's own."""
    stored = replay.transitions()
    now = stored[rng.integers(0, stored.size, batch_size)]
    redraw = None
    if obstacle_redraw_probability > 0.0 and replay.has_obstacles:
        redraw = rng.random(batch_size) < obstacle_redraw_probability
    targets = draw_targets(replay, now, rng, relabel)
    seen = None
    if redraw is not None and redraw.any():
        seen = redraw_obstacles_in_windows(replay, now, n_step, redraw, rng)
    return replay.transitions_at(now, targets, n_step, gamma, seen=seen)


def draw_targets(
    replay: EpisodeReplay, now: NDArray[np.int64], rng: np.random.Generator, relabel: Relabel
) -> NDArray[np.float64]:
    """A target (N, 2) for each transition leaving frames `now`, as `relabel` says."""
    if relabel == "none":
        return replay.own_target[now]
    if relabel == "hindsight":
        # A position reached after this step, in the same episode ("future" strategy).
        later = rng.integers(now + 1, replay.last[now] + 1)
        return replay.pose[later, :2]
    layouts = layouts_of(replay.config.layout)
    if layouts is not None:  # fresh targets anywhere in the box that holds the layouts
        low_xy, high_xy = layouts.box()
        return rng.uniform(low_xy, high_xy, size=(now.size, 2))
    low = replay.config.spawn.wall_margin_m
    high = replay.config.arena.size_m - low
    if relabel == "local":
        draws = rng.random((now.size, _LOCAL_CANDIDATES, 2))
        return targets_around(replay.config, replay.pose[now, :2], draws)
    return rng.uniform(low, high, size=(now.size, 2))


def redraw_obstacles_in_windows(
    replay: EpisodeReplay,
    now: NDArray[np.int64],
    n_step: int,
    redraw: NDArray[np.bool_],
    rng: np.random.Generator,
) -> Seen:
    """What the transitions' windows (N, k + n) see, with fresh obstacles where `redraw` (N,)
    is true and the stored ones elsewhere."""
    frame_index = replay.window_index(now, n_step)
    scans, clearances = replay.scan[frame_index], replay.clearance[frame_index]
    rows = np.flatnonzero(redraw)
    pose = replay.pose[frame_index[rows]]
    centres, _ = draw_obstacle_paths(
        replay.config,
        pose,
        np.diff(frame_index[rows], axis=1) > 0,
        history=replay.window,
        rng=rng,
    )
    scans[rows], clearances[rows] = view_with_obstacles(
        replay.config,
        pose,
        centres,
        replay.walls_scan[frame_index[rows]],
        replay.walls_clearance[frame_index[rows]],
    )
    return Seen(scans, clearances)


def draw_obstacle_paths(
    config: WorldConfig,
    pose: NDArray[np.float64],
    moving: NDArray[np.bool_],
    *,
    history: int,
    rng: np.random.Generator,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Fresh obstacle centres and velocities (N, T, M, 2) along robot paths (N, T, 3).

    The obstacles never react to the robot, so its stored path is as possible among any other
    obstacles as among those it met: like the paper's re-drawn targets, a fresh set per sample
    lets one stored step teach about many layouts.

    Each obstacle starts at a uniform position in the arena with a uniform heading and the
    simulator's speed law, and moves by the simulator's own `move_obstacles`, one control period
    per step where `moving` (N, T - 1) is true (frames repeated at an episode's start or end
    stand still). It stays clear of the robot over the first `history` frames (up to the sampled
    step, which the episode survived): of `_OBSTACLE_CANDIDATES` paths, the first that does is
    used.
    """
    n, frames = pose.shape[:2]
    obstacles = config.obstacles
    m, radius, size = obstacles.count, obstacles.radius_m, config.arena.size_m
    shape = (n, m, _OBSTACLE_CANDIDATES)
    xy = radius + (size - 2 * radius) * rng.random((*shape, 2))
    heading = 2 * np.pi * rng.random(shape)
    # One speed per obstacle, shared by its candidate paths (each candidate still moves at a
    # speed from the simulator's law; only one of them is kept).
    speed = obstacle_speeds(config, rng.random((n, m, 1, _SPEED_CANDIDATES, 2)))
    velocity = np.stack([np.cos(heading), np.sin(heading)], axis=-1) * speed[..., None]
    path = [(xy, velocity)]
    for step in range(frames - 1):
        if step + 1 == history:
            path = _first_clear_candidate(config, pose, path)
            xy, velocity = path[-1]
        moved, turned = move_obstacles(xy, velocity, radius, size, config.control_period_s)
        advance = moving[:, step, None, None, None]
        xy, velocity = np.where(advance, moved, xy), np.where(advance, turned, velocity)
        path.append((xy, velocity))
    if len(path) <= history:
        path = _first_clear_candidate(config, pose, path)
    centres = np.stack([frame for frame, _ in path], axis=1)[:, :, :, 0]
    velocities = np.stack([frame for _, frame in path], axis=1)[:, :, :, 0]
    return centres, velocities


CandidatePaths = list[tuple[NDArray[np.float64], NDArray[np.float64]]]
"""Obstacle centres and velocities (N, M, C, 2) per frame, for C candidate paths."""


def _first_clear_candidate(
    config: WorldConfig, pose: NDArray[np.float64], path: CandidatePaths
) -> CandidatePaths:
    """Keep, of each obstacle's candidate paths, the first that stays clear of the robot so
    far (else the first): the path with C = 1."""
    history = len(path)
    centres = np.stack([frame for frame, _ in path], axis=1)  # (N, history, M, C, 2)
    gap = np.linalg.norm(centres - pose[:, :history, None, None, :2], axis=-1)
    clear = (gap - config.obstacles.radius_m >= config.robot_radius_m).all(axis=1)  # (N, M, C)
    index = np.argmax(clear, axis=2)[:, :, None, None]

    def keep(array: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.take_along_axis(array, index, axis=2)

    return [(keep(xy), keep(velocity)) for xy, velocity in path]


def view_with_obstacles(
    config: WorldConfig,
    pose: NDArray[np.float64],
    centres: NDArray[np.float64],
    walls_scan: NDArray[np.float32],
    walls_clearance: NDArray[np.float64],
) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
    """Encoded scans (N, T, B) and clearances (N, T) from poses (N, T, 3) among obstacles
    (N, T, M, 2), given what the poses see without them."""
    n, frames, m = centres.shape[:3]
    radius = config.obstacles.radius_m
    flat_pose, flat_centres = pose.reshape(n * frames, 3), centres.reshape(n * frames, m, 2)
    scans = walls_scan.copy()
    if config.lidar is not None:
        add_circles_to_scan(
            scans.reshape(n * frames, -1),
            flat_pose,
            config.lidar,
            flat_centres,
            radius,
            scale_m=config.lidar.max_range_m,
        )
    gap = np.linalg.norm(centres - pose[:, :, None, :2], axis=-1).min(axis=-1) - radius
    return scans, np.minimum(walls_clearance, gap)
