"""The oracle planner driven by what the onboard obstacle tracker (`controller.perception`)
perceives instead of the true state: `qnav eval --agent oracle --tracker` runs it under the test
protocol.
"""

from __future__ import annotations

import time

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.errors import ConfigError
from qnav.contracts.motion import InertiaDynamics
from qnav.controller.perception import (
    ObstacleTracker,
    TrackerSettings,
    Tracks,
    box_walls,
    own_velocity,
)
from qnav.lab.oracle import run_oracle
from qnav.sim.config import WorldConfig
from qnav.sim.evaluate import EvalResult, EvalSettings
from qnav.sim.world import Observation, WorldState
from qnav.tracking import lidar_of, noisy

F64 = NDArray[np.float64]

FAR_AWAY_M = 1e4
"""Where a missing obstacle is put in the planner's state: out of every rollout's reach."""


def new_tracker(world: WorldConfig, settings: TrackerSettings) -> ObstacleTracker:
    """A tracker for `world`'s room: its walls are known, as a car's room is (an opening in
    them returns nothing, so the whole box serves)."""
    beams = lidar_of(world).beam_angles_rad()
    return ObstacleTracker(settings, box_walls(world.arena.size_m), beams)


class WorldTrackers:
    """A tracker and the last pose for each running episode, keyed by (seed, episode).

    It sees only what a car sees (the observation: scan, motion-capture pose, target) plus the
    keys and step count of each episode, and builds the state a planner needs from them.
    """

    def __init__(
        self,
        world: WorldConfig,
        settings: TrackerSettings,
        range_noise_m: float = 0.0,
        seed: int = 0,
    ) -> None:
        self.world = world
        self.settings = settings
        self.range_noise_m = range_noise_m
        self._noise = np.random.default_rng([seed, 31])
        self._trackers: dict[tuple[int, int], ObstacleTracker] = {}
        self.update_s: list[float] = []
        """Wall time of each tracker update (one scan of one world), in seconds."""
        self._poses: dict[tuple[int, int], list[F64]] = {}

    def perceive(
        self,
        observation: Observation,
        seed: NDArray[np.int64],
        episode: NDArray[np.int64],
        steps: NDArray[np.int64],
    ) -> WorldState:
        """The state as the tracker and the poses see it: the obstacles are the tracks, nearest
        first (padded far away to the world's count), the robot's velocity comes from its last
        three poses: the mean over the last period, extrapolated by half the change since the
        period before (zero under increment dynamics, which have none)."""
        if observation.scan_m is None:
            raise ConfigError(f"scenario {self.world.name!r} has no lidar to track obstacles with")
        period = self.world.control_period_s
        worlds, count = observation.pose.shape[0], self.world.obstacles.count
        scans = noisy(observation.scan_m, self.range_noise_m, self._noise)
        xy = np.full((worlds, count, 2), FAR_AWAY_M)
        velocity = np.zeros((worlds, count, 2))
        own = np.zeros((worlds, 2))
        live = set()
        for row in range(worlds):
            key = (int(seed[row]), int(episode[row]))
            live.add(key)
            if key not in self._trackers:
                self._trackers[key] = new_tracker(self.world, self.settings)
            pose = observation.pose[row]
            started = time.perf_counter()
            tracks = self._trackers[key].update(float(steps[row]) * period, scans[row], pose)
            self.update_s.append(time.perf_counter() - started)
            nearest = _nearest_first(tracks, pose[:2], count)
            xy[row, : len(nearest.xy_m)] = nearest.xy_m
            velocity[row, : len(nearest.xy_m)] = nearest.velocity_mps
            poses = [*self._poses.get(key, [])[-2:], pose.copy()]
            if isinstance(self.world.dynamics, InertiaDynamics):
                own[row] = own_velocity(np.array(poses), np.full(len(poses) - 1, period))
            self._poses[key] = poses
        for key in set(self._trackers) - live:
            del self._trackers[key]
            self._poses.pop(key, None)
        return WorldState(
            pose=observation.pose,
            velocity=own,
            target_xy=observation.target_xy,
            obstacle_xy=xy,
            obstacle_velocity=velocity,
            steps=steps,
            seed=seed,
            episode=episode,
        )

    def perceive_state(self, state: WorldState, observation: Observation) -> WorldState:
        """`perceive` with the keys of a simulated state (nothing else of it is read)."""
        return self.perceive(observation, state.seed, state.episode, state.steps)


def _nearest_first(tracks: Tracks, robot_xy: F64, count: int) -> Tracks:
    order = np.argsort(np.linalg.norm(tracks.xy_m - robot_xy, axis=1))[:count]
    return Tracks(tracks.xy_m[order], tracks.velocity_mps[order], tracks.radius_m[order])


def run_perceiving_oracle(
    config: WorldConfig,
    settings: EvalSettings,
    tracker: TrackerSettings,
    *,
    range_noise_m: float = 0.0,
    progress: bool = False,
) -> EvalResult:
    """The test protocol's episodes driven by the planner on the tracker's estimate of the
    state (the walls and the target it knows, as a car indoors does)."""
    trackers = WorldTrackers(config, tracker, range_noise_m, settings.seed)
    return run_oracle(config, settings, perceive=trackers.perceive_state, progress=progress)
