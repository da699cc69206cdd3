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

from dataclasses import replace
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from qnav.contracts import lookahead
from qnav.contracts.actions import NUM_ACTIONS
from qnav.contracts.lookahead import candidate_sequences, random_blocks_needed
from qnav.contracts.motion import Outcome, move_obstacles
from qnav.contracts.observation import encode_frame, obstacle_features
from qnav.sim import world
from qnav.sim.config import WorldConfig
from qnav.sim.geometry import add_circles_to_scan
from qnav.sim.world import WorldState, lookahead_model, obstacle_speeds, targets_around
from qnav.training.config import Relabel
from qnav.training.replay import Batch, DoomBounds, EpisodeReplay, Seen

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
    priority_exponent: float = 0.0,
    priority_correction: float = 1.0,
    doom_rows: int = 0,
) -> Batch:
    """Random transitions of the replay, each with its own target drawn by `relabel` and, with
    probability `obstacle_redraw_probability`, fresh obstacles in place of its episode's own.

    Transitions are drawn uniformly, or with `priority_exponent` > 0 in proportion to their
    priority to that power, with importance weights (N p)^-`priority_correction` scaled to at
    most 1 in `Batch.weight`. With `doom_rows` > 0, up to that many of the transitions among
    re-drawn obstacles carry every action's fate by a search over continuations (`doom_bounds`)."""
    now, weight = choose_steps(replay, batch_size, rng, priority_exponent, priority_correction)
    redraw = None
    if obstacle_redraw_probability > 0.0 and replay.has_obstacles:
        redraw = rng.random(batch_size) < obstacle_redraw_probability
    targets = draw_targets(replay, now, rng, relabel)
    seen = None
    if redraw is not None and redraw.any():
        seen = redraw_obstacles_in_windows(replay, now, n_step, redraw, rng)
    batch = replay.transitions_at(now, targets, n_step, gamma, seen=seen)
    doom = None
    if doom_rows > 0 and seen is not None and seen.obstacles_now is not None:
        doom = doom_bounds(
            replay, now, targets, seen.obstacles_now, gamma=gamma, max_rows=doom_rows, rng=rng
        )
    return batch._replace(stored=now, weight=weight, doom=doom)


DOOM_HORIZON_S = 4.0
"""How far ahead `doom_bounds` searches (as the planner's doom labels, `lab.oracle`)."""
DOOM_ROWS = 64
"""Transitions of a batch searched for `doom_bounds` (the search costs more than the rest of
the batch's sampling)."""
_DOOM_RANDOM_TAILS = 16
"""Random continuations searched beside the structured ones."""


def doom_bounds(
    replay: EpisodeReplay,
    now: NDArray[np.int64],
    target: NDArray[np.float64],
    obstacles_now: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]],
    *,
    gamma: float,
    max_rows: int,
    rng: np.random.Generator,
) -> DoomBounds:
    """Every action's fate from the stored states `now` (N,) for the targets (N, 2), among the
    obstacles at s_t (centres, velocities (N, M, 2), known where (N,)), for up to `max_rows`
    of the known rows: after each first action, the look ahead's structured continuations and a
    few random ones are played for `DOOM_HORIZON_S` with the obstacles' exact future.

    The obstacles never react to the robot, so the search is exact for every action, taken or
    not. A doomed action (every continuation collides) is worth at most the collision reward
    discounted to the latest collision: a bound from search that TD's own bootstrap never
    carries (docs/learner.md)."""
    config = replay.config
    centres, velocities, known = obstacles_now
    rows = np.flatnonzero(known)[:max_rows]
    horizon = max(1, round(DOOM_HORIZON_S / config.control_period_s))
    random = rng.integers(0, NUM_ACTIONS, size=(_DOOM_RANDOM_TAILS, random_blocks_needed(horizon)))
    tails = np.unique(candidate_sequences(random, horizon)[:, : horizon - 1], axis=0)
    first = np.repeat(np.arange(NUM_ACTIONS), tails.shape[0])
    sequences = np.concatenate([first[:, None], np.tile(tails, (NUM_ACTIONS, 1))], axis=1)
    start = Situation(
        replay.pose[now[rows]],
        replay.velocity[now[rows]],
        target[rows],
        centres[rows],
        velocities[rows],
    )
    rollouts = lookahead.simulate(lookahead_model(config), start, sequences)
    shape = (rows.size, NUM_ACTIONS, tails.shape[0])
    collided = (rollouts.outcome == Outcome.COLLISION).reshape(shape)
    latest = rollouts.end_step.reshape(shape).max(axis=2)
    doomed = np.zeros((now.size, NUM_ACTIONS), dtype=bool)
    doomed[rows] = collided.all(axis=2)
    bound = np.zeros((now.size, NUM_ACTIONS), dtype=np.float32)
    bound[rows] = config.reward.collision_reward * gamma ** (latest - 1.0)
    # The best surviving continuation of each action that is not doomed, played for k steps in
    # the simulator: its return plus a value after it is what the action is worth at least.
    score = np.where(collided, -np.inf, rollouts.score.reshape(shape))
    row, action = np.nonzero(~collided.all(axis=2))
    best = score[row, action].argmax(axis=1)
    played = sequences[action * tails.shape[0] + best, : replay.window]
    frames, step_reward, discount = play(
        replay, start_rows(start, row), played, replay.obstacle_inputs, gamma
    )
    return DoomBounds(
        doomed,
        bound,
        np.stack([rows[row], action], axis=1),
        frames,
        step_reward,
        discount,
    )


def start_rows(start: Situation, index: NDArray[np.int64]) -> Situation:
    """The situations `index` (P,) of `start`."""
    return Situation(*(np.asarray(field)[index] for field in start))


def play(
    replay: EpisodeReplay,
    start: Situation,
    actions: NDArray[np.int64],
    obstacle_inputs: bool,
    gamma: float,
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
    """Play action sequences (P, T) from `start` in the simulator (`sim.world.step`): the encoded
    frames (P, T, F), the discounted reward up to the first end (P,), and gamma ** T, or 0
    where the sequence ended (reached the target or collided) within the T steps."""
    config = replace(replay.config, max_episode_steps=10**7)
    count = actions.shape[0]
    zeros = np.zeros(count, dtype=np.int64)
    state = WorldState(*start, steps=zeros, seed=zeros, episode=zeros)
    frames, earned = [], np.zeros(count)
    running = np.ones(count, dtype=bool)
    for t in range(actions.shape[1]):
        state, observation, transition = world.step(config, state, actions[:, t])
        earned += running * gamma**t * transition.reward
        running &= ~transition.terminated
        parts = [
            encode_frame(observation.scan_m, observation.target_features(), replay.max_range_m)
        ]
        if obstacle_inputs:
            parts.append(observation.obstacle_features())
        frames.append(np.concatenate(parts, axis=-1))
    frames_array = np.stack(frames, axis=1).astype(np.float32)
    discount = np.where(running, gamma ** actions.shape[1], 0.0).astype(np.float32)
    return frames_array, earned.astype(np.float32), discount


class Situation(NamedTuple):
    """A look ahead's start (`contracts.lookahead.Situation`) from stored steps."""

    pose: NDArray[np.float64]
    velocity: NDArray[np.float64]
    target_xy: NDArray[np.float64]
    obstacle_xy: NDArray[np.float64]
    obstacle_velocity: NDArray[np.float64]


def choose_steps(
    replay: EpisodeReplay,
    batch_size: int,
    rng: np.random.Generator,
    priority_exponent: float = 0.0,
    priority_correction: float = 1.0,
) -> tuple[NDArray[np.int64], NDArray[np.float32] | None]:
    """Stored frames to leave (N,), uniformly or by priority, and the importance weights of a
    prioritized choice (None for a uniform one)."""
    stored = replay.transitions()
    if priority_exponent <= 0.0:
        return stored[rng.integers(0, stored.size, batch_size)], None
    chance = replay.priority[stored] ** priority_exponent
    chance /= chance.sum()
    picked = rng.choice(stored.size, batch_size, p=chance)
    raw = (stored.size * chance[picked]) ** -priority_correction
    return stored[picked], (raw / raw.max()).astype(np.float32)


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
    obstacles = replay.obstacles[frame_index] if replay.obstacle_inputs else None
    rows = np.flatnonzero(redraw)
    pose = replay.pose[frame_index[rows]]
    centres, velocities = draw_obstacle_paths(
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
    if obstacles is not None:
        obstacles[rows] = obstacle_features(pose, centres, velocities)
    m = replay.config.obstacles.count
    centres_now, velocities_now = np.zeros((now.size, m, 2)), np.zeros((now.size, m, 2))
    centres_now[rows] = centres[:, replay.window - 1]
    velocities_now[rows] = velocities[:, replay.window - 1]
    return Seen(scans, clearances, obstacles, (centres_now, velocities_now, redraw.copy()))


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
