"""What a real lidar and motion capture add (`sim.sensor`): the lidar's own readings resampled as
the controller resamples them, range noise, dropouts, a blocked sector, a noisy and late pose."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from qnav.contracts.motion import wrap_angle
from qnav.contracts.wire import Scan
from qnav.controller.scan import ScanRules, resample_scan
from qnav.sim.config import SensorConfig, WorldConfig, changed_world, scenario
from qnav.sim.sensor import sensed_scans, step_keys
from qnav.sim.world import observe, reset, robot_path, step

WORLD = scenario("obstacles-inertia")


def _with(*assignments: str) -> WorldConfig:
    return changed_world(WORLD, None, list(assignments))


def test_360_readings_reach_the_policy_as_the_controllers_resampling_gives_them() -> None:
    random = np.random.default_rng(1)
    readings = random.uniform(0.3, 8.0, (4, 360)).astype(np.float32)
    readings[:, random.integers(0, 360, 40)] = np.inf
    keys = step_keys(np.arange(4), np.zeros(4, np.int64), np.zeros(4, np.int64))
    beams = sensed_scans(SensorConfig(lidar_readings=360), 720, readings, keys)
    for row in range(4):
        scan = Scan(0.0, "", 0.0, 2 * math.pi / 360, 0.0, 20.0, readings[row])
        expected = resample_scan(scan, ScanRules(num_beams=720)).ranges_m
        np.testing.assert_array_equal(beams[row], expected)


def test_a_world_with_360_readings_reads_its_readings_and_between_them_the_nearer() -> None:
    fine = reset(WORLD, np.full(8, 3), np.arange(8))
    exact = observe(WORLD, fine).scan_m
    coarse = observe(_with("sensor.lidar_readings=360"), fine).scan_m
    assert exact is not None and coarse is not None
    readings = exact[:, ::2]  # the 720-beam lidar's even beams are the 360 readings' directions
    np.testing.assert_array_equal(coarse[:, ::2], readings)
    np.testing.assert_array_equal(coarse[:, 1::2], np.minimum(readings, np.roll(readings, -1, 1)))


def test_range_noise_and_dropouts_have_the_set_spread_and_share() -> None:
    world = _with("sensor.range_noise_m=0.05", "sensor.dropout=0.1")
    state = reset(world, np.full(64, 3), np.arange(64))
    exact = observe(WORLD, state).scan_m
    noisy = observe(world, state).scan_m
    assert exact is not None and noisy is not None
    returned = np.isfinite(exact)
    dropped = returned & np.isinf(noisy)
    assert dropped.sum() / returned.sum() == pytest.approx(0.1, abs=0.01)
    kept = returned & np.isfinite(noisy)
    error = noisy[kept] - exact[kept]
    assert error.std() == pytest.approx(0.05, rel=0.05)
    assert abs(error.mean()) < 0.002


def test_noise_changes_from_step_to_step_and_is_the_same_for_the_same_episode() -> None:
    world = _with("sensor.range_noise_m=0.05")
    state = reset(world, np.array([3, 3]), np.array([0, 0]))
    first = observe(world, state).scan_m
    assert first is not None
    np.testing.assert_array_equal(first[0], first[1])
    later = observe(world, state._replace(steps=state.steps + 1)).scan_m
    assert later is not None and not np.array_equal(first, later)


def test_the_blocked_sector_reads_no_return_exactly_there() -> None:
    world = _with("sensor.blocked_width_rad=1.5707963267948966")
    state = reset(world, np.full(16, 3), np.arange(16))
    scan = observe(world, state).scan_m
    exact = observe(WORLD, state).scan_m
    assert scan is not None and exact is not None
    angles = WORLD.lidar.beam_angles_rad() if WORLD.lidar else np.zeros(0)
    behind = np.abs(wrap_angle(angles - math.pi)) <= math.pi / 4
    assert np.isinf(scan[:, behind]).all()
    np.testing.assert_array_equal(scan[:, ~behind], exact[:, ~behind])


def test_a_late_pose_is_where_the_turning_car_was_that_long_before() -> None:
    world = _with("sensor.pose_latency_s=0.1")
    state = reset(world, np.full(4, 3), np.arange(4))
    action = np.array([1, 1, 2, 0])
    for _ in range(4):
        before = state
        state, observation, _ = step(world, state, action)
    times, poses = robot_path(world, before, action)
    then = poses[:, np.argmin(np.abs(times + 0.1))]
    np.testing.assert_allclose(observation.pose[:, :2], then[:, :2], atol=1e-12)
    np.testing.assert_allclose(wrap_angle(observation.pose[:, 2] - then[:, 2]), 0.0, atol=1e-12)
    assert np.abs(wrap_angle(observation.pose[:2, 2] - state.pose[:2, 2])).min() > 0.01


def test_pose_noise_has_the_set_spread() -> None:
    world = replace(WORLD, sensor=SensorConfig(pose_noise_m=0.01, pose_noise_rad=0.02))
    state = reset(world, np.full(3000, 3), np.arange(3000))
    error = observe(world, state).pose - state.pose
    assert error[:, :2].std() == pytest.approx(0.01, rel=0.05)
    assert wrap_angle(error[:, 2]).std() == pytest.approx(0.02, rel=0.05)
