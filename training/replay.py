"""Replay storage: the raw episodes collected, read back as windows of transitions.

The replay keeps what the robot experienced, never the target: poses, encoded scans, the exact
clearance and the actions. A target is chosen when a transition is sampled, and the target
features, reward and termination are recomputed from the stored poses by the simulator's own
pure functions (`sim.task`), so one stored step teaches about every target. Which stored steps
a batch holds, and which target and which obstacles each sees, are the sampling strategies of
`training.sampling`, beside this storage.

Windows never cross an episode start: frames before the first are copies of the first, the
same padding `contracts.observation.FrameWindow` applies when acting.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.motion import Outcome, outcome
from qnav.contracts.observation import (
    distance_scale_m,
    encode_scan,
    encode_target,
    target_features,
)
from qnav.sim.config import WorldConfig
from qnav.sim.geometry import cast_lidar, clearance
from qnav.sim.task import reward
from qnav.training.episode_log import Episode


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


class Seen(NamedTuple):
    """What the frames of sampled windows (N, k + n) saw: the stored episode's, or re-drawn."""

    scans: NDArray[np.float32]
    """(N, k + n, B) encoded scans."""
    clearances: NDArray[np.float64]
    """(N, k + n) exact clearances."""


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
        # What each stored step would have seen without the episode's obstacles, so that
        # fresh ones can be put in when a transition is sampled (`training.sampling`).
        self.has_obstacles = config.obstacles.count > 0
        self.walls_scan = np.zeros(
            (capacity_frames if self.has_obstacles else 0, self.num_beams), dtype=np.float32
        )
        self.walls_clearance = np.zeros(capacity_frames if self.has_obstacles else 0)
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
        self.first[span] = self.size
        self.last[span] = self.size + frames - 1
        self._transitions.append(np.arange(self.size, self.size + frames - 1))
        self._transition_index = np.zeros(0, dtype=np.int64)
        self.size += frames
        self.episodes += 1

    def transitions(self) -> NDArray[np.int64]:
        """The stored frames a transition leaves (every frame but each episode's last)."""
        if not self._transition_index.size:
            self._transition_index = np.concatenate(self._transitions)
        return self._transition_index

    def window_index(self, now: NDArray[np.int64], n_step: int) -> NDArray[np.int64]:
        """Stored frames (N, k + n) of the windows of the transitions leaving frames `now`: the
        k frames up to s_t and the n after it, clamped to the episode's first and last."""
        offsets = np.arange(-self.window + 1, n_step + 1)
        frame_index = np.maximum(now[:, None] + offsets, self.first[now][:, None])
        # Frames past the episode's end are never bootstrapped from; repeat its last frame.
        return np.asarray(np.minimum(frame_index, self.last[now][:, None]), dtype=np.int64)

    def windows(self, now: NDArray[np.int64]) -> NDArray[np.float32]:
        """(N, k, F) the network's input windows ending at frames `now`, for each episode's own
        target (what the robot saw when it acted there)."""
        frame_index = self.window_index(now, 0)
        features = target_features(self.pose[frame_index], self.own_target[now][:, None, :])
        parts = [self.scan[frame_index]] if self.num_beams else []
        parts.append(encode_target(features, self.max_range_m))
        return np.concatenate(parts, axis=-1).astype(np.float32, copy=False)

    def transitions_at(
        self,
        now: NDArray[np.int64],
        target: NDArray[np.float64],
        n_step: int = 1,
        gamma: float = 0.97,
        *,
        seen: Seen | None = None,
    ) -> Batch:
        """The transitions leaving frames `now`, with the given targets (N, 2).

        With n_step > 1 the reward is the discounted sum of up to n rewards for the sampled
        target, stopping early where the target is reached, a collision happens or the stored
        episode ends; the bootstrap window ends where it stopped. `seen` replaces the stored
        encoded scans (N, k + n, B) and clearances (N, k + n) of the windows (`window_index`),
        e.g. with re-drawn obstacles (`training.sampling`).
        """
        k = self.window
        frame_index = self.window_index(now, n_step)
        if seen is None:
            seen = Seen(self.scan[frame_index], self.clearance[frame_index])
        scans, clearances = seen.scans, seen.clearances
        features = target_features(self.pose[frame_index], target[:, None, :])
        parts = [scans] if self.num_beams else []
        parts.append(encode_target(features, self.max_range_m))
        frames = np.concatenate(parts, axis=-1)
        radius = self.config.robot_radius_m
        ahead = clearances[:, k:]  # frames t+1 .. t+n
        distance = features[:, k:, 0]
        reach = self.config.reach_m
        step_outcome = outcome(distance, ahead, radius, reach)
        step_reward = reward(distance, ahead, radius, self.config.reward, reach)
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
