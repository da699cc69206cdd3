# Ad hoc measurement (2026-12-06, session 22): what placing a rotating lidar's beams one by one
# costs the tracker's update.
"""Median and p99 of one `ObstacleTracker.update` over an obstacles-inertia drive (go-to-target
with held random actions, 600 scans, one world): instantaneous scans placed from one pose, and a
10 Hz lidar's scans (each of 40 slices of beams cast from the car's and the obstacles' places at
its time, the turn ending at the pose) placed beam by beam (`beam_poses`), and the same placed from
one pose (a driver without time_increment).

Usage: tracker_timing.py
"""

from __future__ import annotations

import time

import numpy as np

from qnav.contracts.motion import move_obstacles
from qnav.controller.perception import ObstacleTracker, TrackerSettings, beam_poses, box_walls
from qnav.sim.config import scenario
from qnav.sim.evaluate import WanderingGoToTarget
from qnav.sim.geometry import cast_lidar
from qnav.sim.world import BatchedWorld, observe

TURN_S, SLICES = 0.1, 40


def main() -> None:
    world = scenario("obstacles-inertia")
    assert world.lidar is not None
    beams, period = world.lidar.num_beams, world.control_period_s
    radius = world.obstacles.radius_m
    batched = BatchedWorld(world, 1, seed=7)
    observation = observe(world, batched.state)
    driver = WanderingGoToTarget(1, 0.3, 7)
    frames = []
    previous = observation.pose[0].copy()
    for _ in range(600):
        state, pose = batched.state, observation.pose[0].copy()
        turned = np.angle(np.exp(1j * (pose[2] - previous[2])))
        rotating = np.empty(beams, dtype=np.float32)
        for k in range(SLICES):
            back_s = TURN_S * (1 - (k + 0.5) / SLICES)
            at = pose - back_s / period * np.array([*(pose[:2] - previous[:2]), turned])
            xy, _ = move_obstacles(
                state.obstacle_xy, -state.obstacle_velocity, radius, world.arena.size_m, back_s
            )
            part = slice(k * beams // SLICES, (k + 1) * beams // SLICES)
            rotating[part] = cast_lidar(at[None], world.lidar, world.arena, xy, radius)[0, part]
        frames.append((previous, pose, observation.scan_m[0].copy(), rotating))
        previous = pose
        observation = batched.step(driver(observation.target_features())).observation
    settings = TrackerSettings(obstacle_radius_m=radius)
    for placed in ("instantaneous, one pose", "10 Hz turn, beam by beam", "10 Hz turn, one pose"):
        tracker = ObstacleTracker(
            settings, box_walls(world.arena.size_m), world.lidar.beam_angles_rad()
        )
        spent_ms = []
        for k, (before, pose, scan, rotating) in enumerate(frames):
            now = k * period
            started = time.perf_counter()
            if placed.startswith("instantaneous"):
                tracker.update(now, scan, pose)
            elif placed.endswith("one pose"):  # time_increment missing: phantom walls
                tracker.update(now, rotating, pose)
            else:
                times_s = now - TURN_S + TURN_S / beams * np.arange(beams)
                poses = beam_poses(np.array([before, pose]), np.array([now - period, now]), times_s)
                tracker.update(now - TURN_S, rotating, poses, times_s)
            spent_ms.append((time.perf_counter() - started) * 1e3)
        print(
            f"{placed}: median {np.median(spent_ms):.2f} ms, p99 "
            f"{np.quantile(spent_ms, 0.99):.2f} ms over {len(spent_ms)} updates",
            flush=True,
        )


if __name__ == "__main__":
    main()
