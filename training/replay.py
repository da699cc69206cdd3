"""Replay of raw episodes, sampled as windows with re-drawn targets.

The replay keeps what the robot experienced, never the target: poses, encoded scans, the exact
clearance and the actions. A target is chosen when a transition is sampled, and the target
features, reward and termination are recomputed from the stored poses by the simulator's own
pure functions (`sim.task`), so one stored step teaches about every target.

Windows never cross an episode start: frames before the first are copies of the first, the
same padding `contracts.observation.FrameWindow` applies when acting.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import numpy as np
from numpy.typing import NDArray

from contracts.observation import distance_scale_m, encode_scan, encode_target, target_features
from sim.config import WorldConfig
from sim.task import Outcome, outcome, reward
from sim.world import targets_around

_LOCAL_CANDIDATES = 64
"""Candidates per local target (as in the simulator's spawn)."""

Relabel = Literal["paper", "local", "hindsight", "none"]
"""How a sampled transition gets its target: a fresh uniform one in the arena (the paper), a
fresh one drawn as the simulator spawns targets around the robot's pose at that step (local),
a position the robot reached later in the same episode (hindsight), or the episode's own."""


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
        self.first = np.zeros(capacity_frames, dtype=np.int64)
        self.last = np.zeros(capacity_frames, dtype=np.int64)
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
        self.action[self.size : self.size + frames - 1] = episode.action
        self.own_target[span] = episode.target_xy
        self.first[span] = self.size
        self.last[span] = self.size + frames - 1
        self._transitions.append(np.arange(self.size, self.size + frames - 1))
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
    ) -> Batch:
        """Uniformly random transitions, each with its own target drawn by `relabel`."""
        if not self._transition_index.size:
            self._transition_index = np.concatenate(self._transitions)
        now = self._transition_index[rng.integers(0, self._transition_index.size, batch_size)]
        return self.transitions_at(now, self._targets(now, rng, relabel), n_step, gamma)

    def transitions_at(
        self,
        now: NDArray[np.int64],
        target: NDArray[np.float64],
        n_step: int = 1,
        gamma: float = 0.97,
    ) -> Batch:
        """The transitions leaving frames `now`, with the given targets (N, 2).

        With n_step > 1 the reward is the discounted sum of up to n rewards for the sampled
        target, stopping early where the target is reached, a collision happens or the stored
        episode ends; the bootstrap window ends where it stopped.
        """
        k = self.window
        offsets = np.arange(-k + 1, n_step + 1)
        frame_index = np.maximum(now[:, None] + offsets, self.first[now][:, None])
        # Frames past the episode's end are never bootstrapped from; repeat its last frame.
        frame_index = np.minimum(frame_index, self.last[now][:, None])
        features = target_features(self.pose[frame_index], target[:, None, :])
        encoded_target = encode_target(features, self.max_range_m)
        frames = (
            np.concatenate([self.scan[frame_index], encoded_target], axis=-1)
            if self.num_beams
            else encoded_target
        )
        radius = self.config.robot_radius_m
        ahead = frame_index[:, k:]  # frames t+1 .. t+n
        distance = features[:, k:, 0]
        step_outcome = outcome(distance, self.clearance[ahead], radius)
        step_reward = reward(distance, self.clearance[ahead], radius, self.config.reward)
        # Steps taken: up to n, the first terminal step, or the episode's last frame.
        available = np.minimum(self.last[now] - now, n_step)
        ends = (step_outcome != Outcome.RUNNING) | (np.arange(1, n_step + 1) >= available[:, None])
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
