import math

import numpy as np
import pytest

from qnav.contracts.observation import LidarSpec
from qnav.sim.config import WorldConfig, scenario
from qnav.sim.geometry import cast_lidar, cast_rotating_lidar, clearance
from qnav.sim.world import reset
from tests.sim.reference_lidar import reference_scan


def _scan(config: WorldConfig, pose: np.ndarray, obstacles: np.ndarray) -> np.ndarray:
    assert config.lidar is not None
    return cast_lidar(pose, config.lidar, config.arena, obstacles, config.obstacles.radius_m)


@pytest.mark.parametrize("name", ["walls-inertia", "obstacles-inertia", "obstacles-increment"])
def test_lidar_matches_a_ray_by_ray_reference_exactly(name: str) -> None:
    config = scenario(name)
    state = reset(config, np.arange(4) + 7, np.zeros(4, np.int64))
    scans = _scan(config, state.pose, state.obstacle_xy)
    for world in range(4):
        expected = reference_scan(config, state.pose[world], state.obstacle_xy[world])
        np.testing.assert_array_equal(np.isinf(scans[world]), np.isinf(expected))
        finite = np.isfinite(expected)
        np.testing.assert_allclose(scans[world][finite], expected[finite], atol=1e-4)


def test_each_beam_of_a_rotating_lidar_is_that_beam_of_the_scan_from_its_own_pose() -> None:
    config = scenario("obstacles-inertia")
    assert config.lidar is not None
    state = reset(config, np.array([3]), np.array([0]))
    beams = config.lidar.num_beams
    # The car turns and drives, the obstacles drift: a different pose and layout for each beam.
    share = np.linspace(0.0, 1.0, beams)[:, None]
    poses = state.pose + share * np.array([[0.3, -0.2, 1.5]])
    obstacles = state.obstacle_xy + share[:, None] * np.array([0.4, 0.1])
    radius = config.obstacles.radius_m
    scan = cast_rotating_lidar(poses, config.lidar, config.arena, obstacles, radius)
    for beam in (0, 100, 359, 719):
        whole = _scan(config, poses[beam : beam + 1], obstacles[beam : beam + 1])
        assert scan[beam] == whole[0, beam]
    still = cast_rotating_lidar(
        np.repeat(state.pose, beams, axis=0),
        config.lidar,
        config.arena,
        np.repeat(state.obstacle_xy, beams, axis=0),
        radius,
    )
    np.testing.assert_array_equal(still, _scan(config, state.pose, state.obstacle_xy)[0])


def test_rays_leave_through_an_opening_and_read_no_return() -> None:
    config = scenario("walls-inertia")
    # Facing the south opening (centre x = 3.0) from straight above it.
    pose = np.array([[3.0, 2.0, -math.pi / 2]])
    scan = _scan(config, pose, np.zeros((1, 0, 2)))[0]
    assert np.isinf(scan[0])
    # A quarter turn left of south is east, where the wall is solid at y = 2, 7 m away.
    assert scan[180] == pytest.approx(7.0, abs=1e-5)
    assert scan[360] == pytest.approx(8.0, abs=1e-5)  # behind: the north wall


def test_readings_beyond_max_range_are_no_return() -> None:
    config = scenario("walls-inertia", lidar=LidarSpec(720, 2.0))
    scan = _scan(config, np.array([[5.0, 5.0, 0.0]]), np.zeros((1, 0, 2)))
    assert np.isinf(scan).all()


def test_sensor_inside_an_obstacle_reads_zero_everywhere() -> None:
    config = scenario("obstacles-inertia")
    scan = _scan(config, np.array([[5.0, 5.0, 0.3]]), np.array([[[5.1, 5.0]]]))
    assert (scan == 0).all()


def test_clearance_equals_the_nearest_reading_of_a_dense_scan() -> None:
    config = scenario("obstacles-inertia")
    state = reset(config, np.arange(16), np.zeros(16, np.int64))
    scans = _scan(config, state.pose, state.obstacle_xy)
    exact = clearance(state.pose[:, :2], config.arena, state.obstacle_xy, config.obstacles.radius_m)
    # The scan's minimum can only over-estimate, by at most the gap between two beams.
    assert (scans.min(axis=1) >= exact - 1e-4).all()
    np.testing.assert_allclose(scans.min(axis=1), exact, rtol=1e-3)


def test_clearance_sees_the_jamb_of_an_opening() -> None:
    config = scenario("walls-inertia")
    # Straight above the south opening (x in [2.6, 3.4]): the nearest solid point is a jamb.
    gap = clearance(np.array([[3.0, 0.3]]), config.arena, np.zeros((1, 0, 2)), 0.4)
    assert gap[0] == pytest.approx(math.hypot(0.4, 0.3))
