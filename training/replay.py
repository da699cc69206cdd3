"""Replay of raw episodes, sampled as windows with re-drawn targets.

The replay keeps what the robot experienced, never the target: poses, encoded scans, the exact
clearance and the actions. A target is chosen when a transition is sampled, and the target
features, reward and termination are recomputed from the stored poses by the simulator's own
pure functions (`sim.task`), so one stored step teaches about every target.

Windows never cross an episode start: frames before the first are copies of the first, the
same padding `contracts.observation.FrameWindow` applies when acting.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np
from numpy.typing import NDArray

from contracts.actions import Action
from contracts.motion import Outcome, move_obstacles, outcome
from contracts.observation import distance_scale_m, encode_scan, encode_target, target_features
from sim.config import WorldConfig
from sim.geometry import add_circles_to_scan, cast_lidar, clearance
from sim.task import reward
from sim.world import obstacle_speeds, targets_around

_LOCAL_CANDIDATES = 64
"""Candidates per local target (as in the simulator's spawn)."""
_OBSTACLE_CANDIDATES = 8
"""Candidate paths per re-drawn obstacle; the first that never touches the robot before the
sampled step is used (each is accepted with probability about 0.9, so all 8 fail with
probability about 1e-8)."""
_SPEED_CANDIDATES = 8
"""Box-Muller candidates per re-drawn obstacle speed; each lies in the speed range with
probability about 0.9."""

Relabel = Literal["paper", "local", "hindsight", "none"]
"""How a sampled transition gets its target: a fresh uniform one in the arena (the paper), a
fresh one drawn as the simulator spawns targets around the robot's pose at that step (local),
a position the robot reached later in the same episode (hindsight), or the episode's own."""


@dataclass(frozen=True)
class ObstacleRedraw:
    """How sampled transitions get fresh obstacles in place of their episode's own."""

    probability: float = 1.0
    """Chance that a sampled transition sees fresh obstacles."""
    near_probability: float = 0.0
    """Chance that a fresh obstacle starts within `near_radius_m` of the robot instead of
    anywhere in the arena, so that more samples show an obstacle that matters."""
    near_radius_m: float = 3.0
    """Radius of the disc around the robot that near obstacles start in."""
    bootstrap_within_m: float = 0.0
    """An n-step return stops, and bootstraps, at the first step where a fresh obstacle's surface
    is this close to the robot (0: never). The stored actions never saw that obstacle, so they
    must not stand in for the greedy ones while it matters."""


class Episode(NamedTuple):
    """One finished episode, as collected."""

    pose: NDArray[np.float64]
    """(T + 1, 3) poses from the first observation to the last."""
    scan_m: NDArray[np.float32] | None
    """(T + 1, B) raw ranges in metres, or None without a lidar."""
    clearance_m: NDArray[np.float64]
    """(T + 1,) distance to the nearest surface at each observation."""
    action: NDArray[np.int64]
    """(T,) actions taken."""
    target_xy: NDArray[np.float64]
    """(2,) the episode's own target."""
    outcome: int
    """How it ended (sim.task.Outcome; RUNNING = truncated)."""
    demonstrated: bool = False
    """Driven by a demonstrator that knew the obstacles' future (`TrainSettings.
    demonstration_episodes`), not by the agent."""


class Batch(NamedTuple):
    """Sampled transitions as windows over k + n consecutive frames of one episode."""

    frames: NDArray[np.float32]
    """(N, k + n, F) encoded frames; s_t is [:, :k], the bootstrap state [:, m : m + k]."""
    action: NDArray[np.int64]
    """(N,) action taken at s_t."""
    reward: NDArray[np.float32]
    """(N,) discounted reward of the m steps taken, recomputed for the sampled target."""
    terminal: NDArray[np.bool_]
    """(N,) the m-th step ends the episode for the sampled target (success or collision)."""
    steps: NDArray[np.int64]
    """(N,) m: steps taken before bootstrapping (1 <= m <= n)."""
    discount: NDArray[np.float32]
    """(N,) gamma ** m, the bootstrap's discount."""
    demonstrated: NDArray[np.bool_] | None = None
    """(N,) the transition is a demonstration's, with its own target and obstacles (None:
    none is)."""
    stored: NDArray[np.int64] | None = None
    """(N,) the stored frames the transitions leave (set by `EpisodeReplay.sample`), for
    `EpisodeReplay.reprioritise`."""
    weight: NDArray[np.float32] | None = None
    """(N,) importance weights of a prioritized sample (None: uniform, all 1)."""


class EpisodeReplay:
    """All frames of all episodes in flat arrays, with per-frame episode bounds."""

    def __init__(self, config: WorldConfig, capacity_frames: int, window: int) -> None:
        self.config = config
        self.window = window
        self.num_beams = config.lidar.num_beams if config.lidar else 0
        self.max_range_m = distance_scale_m(config.lidar)
        self.pose = np.zeros((capacity_frames, 3))
        self.scan = np.zeros((capacity_frames, self.num_beams), dtype=np.float32)
        self.clearance = np.zeros(capacity_frames)
        self.action = np.zeros(capacity_frames, dtype=np.int64)
        self.own_target = np.zeros((capacity_frames, 2))
        self.demonstrated = np.zeros(capacity_frames, dtype=bool)
        # What each stored step would have seen without the episode's obstacles, so that
        # fresh ones can be put in when a transition is sampled (`redraw_obstacles`).
        self.has_obstacles = config.obstacles.count > 0
        self.walls_scan = np.zeros(
            (capacity_frames if self.has_obstacles else 0, self.num_beams), dtype=np.float32
        )
        self.walls_clearance = np.zeros(capacity_frames if self.has_obstacles else 0)
        self.first = np.zeros(capacity_frames, dtype=np.int64)
        self.last = np.zeros(capacity_frames, dtype=np.int64)
        # Proportional priorities (Schaul et al. 2016): a stored step's last |TD error|, the
        # largest one seen for steps never sampled yet.
        self.priority = np.zeros(capacity_frames)
        self._max_priority = 1.0
        self.size = 0
        self.episodes = 0
        self._transitions: list[NDArray[np.int64]] = []
        self._transition_index = np.zeros(0, dtype=np.int64)

    def add(self, episode: Episode) -> None:
        """Store one episode (its scans encoded once, here)."""
        frames = episode.pose.shape[0]
        if self.size + frames > self.pose.shape[0]:
            raise ValueError(
                f"replay is full: {self.size} + {frames} frames exceed its capacity "
                f"{self.pose.shape[0]}"
            )
        span = slice(self.size, self.size + frames)
        self.pose[span] = episode.pose
        if episode.scan_m is not None:
            self.scan[span] = encode_scan(episode.scan_m, self.max_range_m)
        self.clearance[span] = episode.clearance_m
        if self.has_obstacles:
            no_obstacles = np.zeros((frames, 0, 2))
            if self.config.lidar is not None:
                self.walls_scan[span] = encode_scan(
                    cast_lidar(episode.pose, self.config.lidar, self.config.arena, no_obstacles, 0),
                    self.max_range_m,
                )
            self.walls_clearance[span] = clearance(
                episode.pose[:, :2], self.config.arena, no_obstacles, 0.0
            )
        self.action[self.size : self.size + frames - 1] = episode.action
        self.own_target[span] = episode.target_xy
        self.demonstrated[span] = episode.demonstrated
        self.first[span] = self.size
        self.last[span] = self.size + frames - 1
        self._transitions.append(np.arange(self.size, self.size + frames - 1))
        self.priority[self.size : self.size + frames - 1] = self._max_priority
        self._transition_index = np.zeros(0, dtype=np.int64)
        self.size += frames
        self.episodes += 1

    def sample(
        self,
        batch_size: int,
        rng: np.random.Generator,
        relabel: Relabel,
        n_step: int = 1,
        gamma: float = 0.97,
        *,
        mirror_probability: float = 0.0,
        obstacles: ObstacleRedraw | None = None,
        priority_exponent: float = 0.0,
        priority_correction: float = 1.0,
    ) -> Batch:
        """Random transitions, each with its own target drawn by `relabel`, fresh obstacles as
        `obstacles` says (none by default), and each seen in a mirror (`mirror_batch`) with
        probability `mirror_probability`.

        Transitions are drawn uniformly, or with `priority_exponent` > 0 in proportion to their
        priority to that power, with importance weights (N p)^-`priority_correction` scaled to
        at most 1 in `Batch.weight`. A demonstration's transitions keep their episode's target
        and obstacles: its actions answer those, and the learner's margin loss holds them to
        it."""
        if not self._transition_index.size:
            self._transition_index = np.concatenate(self._transitions)
        stored = self._transition_index
        weight = None
        if priority_exponent > 0.0:
            chance = self.priority[stored] ** priority_exponent
            chance /= chance.sum()
            picked = rng.choice(stored.size, batch_size, p=chance)
            raw = (stored.size * chance[picked]) ** -priority_correction
            weight = (raw / raw.max()).astype(np.float32)
            now = stored[picked]
        else:
            now = stored[rng.integers(0, stored.size, batch_size)]
        demonstrated = self.demonstrated[now]
        redraw = None
        if obstacles is not None and self.has_obstacles:
            redraw = (rng.random(batch_size) < obstacles.probability) & ~demonstrated
        targets = self._targets(now, rng, relabel)
        targets[demonstrated] = self.own_target[now[demonstrated]]
        batch = self.transitions_at(
            now,
            targets,
            n_step,
            gamma,
            redraw=redraw,
            rng=rng,
            obstacles=obstacles,
        )
        if demonstrated.any():
            batch = batch._replace(demonstrated=demonstrated)
        if mirror_probability > 0.0:
            batch = mirror_batch(batch, rng.random(batch_size) < mirror_probability, self.num_beams)
        return batch._replace(stored=now, weight=weight)

    def reprioritise(self, index: NDArray[np.int64], td_error: NDArray[np.floating]) -> None:
        """Set the sampled steps' priorities to their new |TD error| (plus a floor, so that no
        step is never drawn again)."""
        priority = np.abs(td_error) + 1e-3
        self.priority[index] = priority
        self._max_priority = max(self._max_priority, float(priority.max()))

    def transitions_at(
        self,
        now: NDArray[np.int64],
        target: NDArray[np.float64],
        n_step: int = 1,
        gamma: float = 0.97,
        *,
        redraw: NDArray[np.bool_] | None = None,
        rng: np.random.Generator | None = None,
        obstacles: ObstacleRedraw | None = None,
    ) -> Batch:
        """The transitions leaving frames `now`, with the given targets (N, 2).

        With n_step > 1 the reward is the discounted sum of up to n rewards for the sampled
        target, stopping early where the target is reached, a collision happens or the stored
        episode ends (or, with fresh obstacles, where one comes within
        `obstacles.bootstrap_within_m`); the bootstrap window ends where it stopped. Transitions
        marked in `redraw`
        see fresh obstacles drawn with `rng` as `obstacles` says, instead of the episode's own.
        """
        k = self.window
        offsets = np.arange(-k + 1, n_step + 1)
        frame_index = np.maximum(now[:, None] + offsets, self.first[now][:, None])
        # Frames past the episode's end are never bootstrapped from; repeat its last frame.
        frame_index = np.minimum(frame_index, self.last[now][:, None])
        scans, clearances = self.scan[frame_index], self.clearance[frame_index]
        # Distance from the robot to the nearest fresh obstacle (inf where none was drawn).
        fresh_gap = np.full(clearances.shape, np.inf)
        if redraw is not None and redraw.any():
            if rng is None:
                raise ValueError("re-drawing obstacles needs a random generator")
            rows = np.flatnonzero(redraw)
            scans[rows], clearances[rows], fresh_gap[rows] = redraw_obstacles(
                self.config,
                self.pose[frame_index[rows]],
                np.diff(frame_index[rows], axis=1) > 0,
                self.walls_scan[frame_index[rows]],
                self.walls_clearance[frame_index[rows]],
                history=k,
                rng=rng,
                law=obstacles or ObstacleRedraw(),
            )
        features = target_features(self.pose[frame_index], target[:, None, :])
        encoded_target = encode_target(features, self.max_range_m)
        frames = (
            np.concatenate([scans, encoded_target], axis=-1) if self.num_beams else encoded_target
        )
        radius = self.config.robot_radius_m
        ahead = clearances[:, k:]  # frames t+1 .. t+n
        distance = features[:, k:, 0]
        step_outcome = outcome(distance, ahead, radius)
        step_reward = reward(distance, ahead, radius, self.config.reward)
        # Steps taken: up to n, the first terminal step, or the episode's last frame.
        available = np.minimum(self.last[now] - now, n_step)
        ends = (step_outcome != Outcome.RUNNING) | (np.arange(1, n_step + 1) >= available[:, None])
        if obstacles is not None and obstacles.bootstrap_within_m > 0.0:
            ends |= fresh_gap[:, k:] < obstacles.bootstrap_within_m
        steps = np.argmax(ends, axis=1) + 1
        taken = np.arange(1, n_step + 1) <= steps[:, None]
        discounts = gamma ** np.arange(n_step)
        returns = (step_reward * discounts * taken).sum(axis=1)
        terminal = step_outcome[np.arange(now.size), steps - 1] != Outcome.RUNNING
        return Batch(
            frames=frames.astype(np.float32, copy=False),
            action=self.action[now],
            reward=returns.astype(np.float32),
            terminal=terminal,
            steps=steps,
            discount=(gamma**steps).astype(np.float32),
        )

    def _targets(
        self, now: NDArray[np.int64], rng: np.random.Generator, relabel: Relabel
    ) -> NDArray[np.float64]:
        if relabel == "none":
            return self.own_target[now]
        if relabel == "hindsight":
            # A position reached after this step, in the same episode ("future" strategy).
            later = rng.integers(now + 1, self.last[now] + 1)
            return self.pose[later, :2]
        low = self.config.spawn.wall_margin_m
        high = self.config.arena.size_m - low
        if relabel == "local":
            draws = rng.random((now.size, _LOCAL_CANDIDATES, 2))
            return targets_around(self.config, self.pose[now, :2], draws)
        return rng.uniform(low, high, size=(now.size, 2))


def redraw_obstacles(
    config: WorldConfig,
    pose: NDArray[np.float64],
    moving: NDArray[np.bool_],
    walls_scan: NDArray[np.float32],
    walls_clearance: NDArray[np.float64],
    *,
    history: int,
    rng: np.random.Generator,
    law: ObstacleRedraw,
) -> tuple[NDArray[np.float32], NDArray[np.float64], NDArray[np.float64]]:
    """Encoded scans (N, T, B), clearances (N, T) and the fresh obstacles' own clearances (N, T)
    along stored robot paths (N, T, 3), with fresh obstacles (`draw_obstacle_paths`) in place of
    the episode's own.

    The obstacles never react to the robot, so its stored path is as possible among any other
    obstacles as among those it met: like the paper's re-drawn targets, a fresh set per sample
    lets one stored step teach about many layouts. `walls_scan` and `walls_clearance` are what
    the stored poses see without obstacles.
    """
    centres = draw_obstacle_paths(config, pose, moving, history=history, rng=rng, law=law)
    return view_with_obstacles(config, pose, centres, walls_scan, walls_clearance)


def draw_obstacle_paths(
    config: WorldConfig,
    pose: NDArray[np.float64],
    moving: NDArray[np.bool_],
    *,
    history: int,
    rng: np.random.Generator,
    law: ObstacleRedraw | None = None,
) -> NDArray[np.float64]:
    """Fresh obstacle centres (N, T, M, 2) along robot paths (N, T, 3).

    Each obstacle starts at a uniform position in the arena (or, with `law.near_probability`,
    in the disc of `law.near_radius_m` around the robot's first pose, clipped to the arena)
    with a uniform heading and the simulator's speed law, and moves by the simulator's own
    `move_obstacles`, one control period per step where `moving` (N, T - 1) is true (frames
    repeated at an episode's start or end stand still). It stays clear of the robot over the
    first `history` frames (up to the sampled step, which the episode survived): of
    `_OBSTACLE_CANDIDATES` paths, the first that does is used.
    """
    n, frames = pose.shape[:2]
    obstacles = config.obstacles
    m, radius, size = obstacles.count, obstacles.radius_m, config.arena.size_m
    shape = (n, m, _OBSTACLE_CANDIDATES)
    xy = radius + (size - 2 * radius) * rng.random((*shape, 2))
    law = law or ObstacleRedraw()
    if law.near_probability > 0.0:
        # Where an obstacle starts changes only how often a state is sampled, never its value:
        # the state (five obstacles in view) fixes what happens next whatever placed them.
        near = rng.random((n, m, 1, 1)) < law.near_probability
        reach = law.near_radius_m * np.sqrt(rng.random(shape))
        angle = 2 * np.pi * rng.random(shape)
        around = pose[:, 0, None, None, :2] + reach[..., None] * np.stack(
            [np.cos(angle), np.sin(angle)], axis=-1
        )
        xy = np.where(near, np.clip(around, radius, size - radius), xy)
    heading = 2 * np.pi * rng.random(shape)
    # One speed per obstacle, shared by its candidate paths (each candidate still moves at a
    # speed from the simulator's law; only one of them is kept).
    speed = obstacle_speeds(config, rng.random((n, m, 1, _SPEED_CANDIDATES, 2)))
    velocity = np.stack([np.cos(heading), np.sin(heading)], axis=-1) * speed[..., None]
    path = [xy]
    for step in range(frames - 1):
        if step + 1 == history:
            xy, velocity, path = _first_clear_candidate(config, pose, xy, velocity, path)
        moved, turned = move_obstacles(xy, velocity, radius, size, config.control_period_s)
        advance = moving[:, step, None, None, None]
        xy, velocity = np.where(advance, moved, xy), np.where(advance, turned, velocity)
        path.append(xy)
    if len(path) <= history:
        _, _, path = _first_clear_candidate(config, pose, xy, velocity, path)
    return np.stack(path, axis=1)[:, :, :, 0]


def _first_clear_candidate(
    config: WorldConfig,
    pose: NDArray[np.float64],
    xy: NDArray[np.float64],
    velocity: NDArray[np.float64],
    path: list[NDArray[np.float64]],
) -> tuple[NDArray[np.float64], NDArray[np.float64], list[NDArray[np.float64]]]:
    """Keep, of each obstacle's candidates (N, M, C, 2), the first whose path so far stays clear
    of the robot (else the first): its position, velocity and path, with C = 1."""
    history = len(path)
    centres = np.stack(path, axis=1)  # (N, history, M, C, 2)
    gap = np.linalg.norm(centres - pose[:, :history, None, None, :2], axis=-1)
    clear = (gap - config.obstacles.radius_m >= config.robot_radius_m).all(axis=1)  # (N, M, C)
    index = np.argmax(clear, axis=2)[:, :, None, None]

    def keep(array: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.take_along_axis(array, index, axis=2)

    return keep(xy), keep(velocity), [keep(frame) for frame in path]


def view_with_obstacles(
    config: WorldConfig,
    pose: NDArray[np.float64],
    centres: NDArray[np.float64],
    walls_scan: NDArray[np.float32],
    walls_clearance: NDArray[np.float64],
) -> tuple[NDArray[np.float32], NDArray[np.float64], NDArray[np.float64]]:
    """Encoded scans (N, T, B), clearances (N, T) and the obstacles' own clearances (N, T) from
    poses (N, T, 3) among obstacles (N, T, M, 2), given what the poses see without them."""
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
    return scans, np.minimum(walls_clearance, gap), gap


_MIRRORED_ACTION = np.array([Action.FORWARD, Action.RIGHT, Action.LEFT], dtype=np.int64)
"""Each action's mirror image: forward stays forward, left and right swap."""


def mirror_batch(batch: Batch, mirrored: NDArray[np.bool_], num_beams: int) -> Batch:
    """The chosen transitions as seen in a mirror through the robot's heading axis.

    The world's physics is symmetric under that reflection: a beam at angle theta reads what
    the beam at -theta read (beam i takes beam (B - i) mod B), the target's bearing changes
    sign (sin phi -> -sin phi, distance and cos phi unchanged), left and right turns swap, and
    distances, hence reward and termination, are unchanged. Every mirrored transition is one
    the robot could have experienced, so the replay holds twice the experience.
    """
    if not mirrored.any():
        return batch
    frames = batch.frames.copy()
    chosen = frames[mirrored]
    if num_beams:
        chosen[..., :num_beams] = chosen[..., (-np.arange(num_beams)) % num_beams]
    chosen[..., num_beams + 1] *= -1.0  # sin of the target's bearing
    frames[mirrored] = chosen
    action = np.where(mirrored, _MIRRORED_ACTION[batch.action], batch.action)
    return batch._replace(frames=frames, action=action)
