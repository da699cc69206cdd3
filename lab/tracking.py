"""The onboard obstacle tracker (`controller.perception`) measured against the simulator's truth,
and the oracle planner driven by what it perceives instead of the true state.

`qnav lab probe --tracker` prints the tracker's errors in the same terms as the perception probe
(`qnav lab probe --perception`), so the two perceivers sit in one table; `qnav eval --agent oracle
--tracker` runs the planner on the tracker's estimate under the test protocol.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from qnav.contracts.errors import ConfigError
from qnav.contracts.motion import InertiaDynamics
from qnav.controller.perception import (
    ObstacleTracker,
    TrackerSettings,
    Tracks,
    box_walls,
    own_velocity,
)
from qnav.lab.oracle import PERCEIVED, run_oracle
from qnav.sim.config import WorldConfig
from qnav.sim.evaluate import EvalResult, EvalSettings, WanderingGoToTarget
from qnav.sim.world import BatchedWorld, Observation, WorldState
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
    return Tracks(tracks.xy_m[order], tracks.velocity_mps[order])


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


@dataclass(frozen=True)
class TrackerCheckSettings:
    """The drive the tracker is judged on (`qnav lab probe --tracker`), as the perception
    probe's."""

    SECTION = "tracker_check"

    samples: int = 4_000
    """States judged (each with the nearest obstacle within `max_distance_m`)."""
    max_distance_m: float = 4.0
    """States whose nearest obstacle is farther than this are skipped."""
    explore_share: float = 0.3
    """Share of steps where a held random action replaces go-to-target's."""
    warmup_frames: int = 5
    """Frames of an episode before its states are judged (the policy's window)."""
    seed: int = 1005
    """Seed of the layouts (the perception probe's held-out layouts)."""
    range_noise_m: float = 0.0
    """Gaussian noise (one standard deviation) added to each range the tracker reads: the
    simulator's lidar is exact, a real one is not."""


class TrackerErrors(NamedTuple):
    """Absolute errors of the tracker over the judged states, by `PERCEIVED` name."""

    median: dict[str, float]
    """Median absolute error of each quantity, in its unit."""
    p90: dict[str, float]
    """90th percentile."""
    missed_share: float
    """Share of judged states where the tracker had no track within 1 m of the nearest
    obstacle (its error then counts against the nearest track, or the robot itself)."""
    samples: int
    """States judged."""
    update_ms: tuple[float, float]
    """Median and 99th percentile wall time of one tracker update (one scan), milliseconds."""


def measure_tracker(
    world: WorldConfig,
    tracker: TrackerSettings | None = None,
    check: TrackerCheckSettings | None = None,
    progress: bool = False,
) -> TrackerErrors:
    """Drive go-to-target with held random actions (the perception probe's drive) and compare
    the tracker's nearest obstacle (position and velocity in the robot's frame) and the robot's
    own speed and turn rate with the truth."""
    if not world.obstacles.count:
        raise ConfigError(f"scenario {world.name!r} has no moving obstacles to track")
    tracker = tracker or TrackerSettings()
    check = check or TrackerCheckSettings()
    worlds = 200
    batched = BatchedWorld(world, worlds, seed=check.seed)
    observation = batched.reset(check.seed)
    trackers = WorldTrackers(world, tracker, check.range_noise_m, check.seed)
    driver = WanderingGoToTarget(worlds, check.explore_share, check.seed)
    errors: list[F64] = []
    missed = 0
    bar = tqdm(total=check.samples, desc="tracker", unit="state", disable=not progress)
    while len(errors) < check.samples:
        state = batched.state
        perceived = trackers.perceive_state(state, observation)
        for row in np.flatnonzero(state.steps >= check.warmup_frames - 1).tolist():
            true = _nearest_in_robot_frame(state, state, row)
            if true[4] > check.max_distance_m:
                continue
            estimate = _nearest_in_robot_frame(perceived, state, row)
            missed += int(_closest_track_m(perceived, state, row) > 1.0)
            errors.append(
                np.abs(
                    np.concatenate(
                        [estimate[:4] - true[:4], perceived.velocity[row] - state.velocity[row]]
                    )
                )
            )
            bar.update(int(len(errors) <= check.samples))
        observation = batched.step(driver(observation.target_features())).observation
    bar.close()
    table = np.array(errors[: check.samples])
    median = dict(zip(PERCEIVED, np.median(table, axis=0).tolist(), strict=True))
    p90 = dict(zip(PERCEIVED, np.percentile(table, 90, axis=0).tolist(), strict=True))
    update_ms = np.percentile(np.array(trackers.update_s) * 1e3, [50, 99])
    return TrackerErrors(
        median, p90, missed / len(errors), len(table), (float(update_ms[0]), float(update_ms[1]))
    )


def _nearest_in_robot_frame(view: WorldState, truth: WorldState, row: int) -> F64:
    """(5,) the nearest obstacle of `view` in the true robot's frame: ahead, left, forward
    velocity, leftward velocity, distance."""
    pose = truth.pose[row]
    offset = view.obstacle_xy[row] - pose[:2]
    nearest = int(np.argmin(np.linalg.norm(offset, axis=1)))
    cos, sin = np.cos(pose[2]), np.sin(pose[2])
    rotate = np.array([[cos, sin], [-sin, cos]])
    return np.concatenate(
        [
            rotate @ offset[nearest],
            rotate @ view.obstacle_velocity[row, nearest],
            [np.linalg.norm(offset[nearest])],
        ]
    )


def _closest_track_m(perceived: WorldState, truth: WorldState, row: int) -> float:
    offset = truth.obstacle_xy[row] - truth.pose[row, :2]
    nearest = truth.obstacle_xy[row, int(np.argmin(np.linalg.norm(offset, axis=1)))]
    return float(np.min(np.linalg.norm(perceived.obstacle_xy[row] - nearest, axis=1)))
