"""The onboard obstacle tracker: each pure step, then the whole tracker on the simulator's scans."""

import math

import numpy as np
import pytest

from qnav.contracts.errors import ConfigError
from qnav.contracts.observation import LidarSpec
from qnav.controller.perception import (
    ObstacleTracker,
    TrackerSettings,
    bounce_mirrors,
    box_walls,
    clusters,
    ego_velocity,
    fit_circle,
    fit_velocity,
    off_the_walls,
    one_wide_pieces,
    scan_points,
)

BEAMS = LidarSpec().beam_angles_rad()


def _arc(centre: tuple[float, float], radius_m: float, sensor: tuple[float, float]) -> np.ndarray:
    """Points of the near side of a circle as a lidar at `sensor` sees it."""
    offset = np.subtract(centre, sensor)
    bearing = math.atan2(offset[1], offset[0])
    half = math.asin(radius_m / float(np.linalg.norm(offset)))
    angles = np.linspace(bearing - 0.9 * half, bearing + 0.9 * half, 12)
    d = float(np.linalg.norm(offset))
    # Ray-circle intersection along each angle.
    u = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    along = u @ offset
    t = along - np.sqrt(np.maximum(along**2 - (d**2 - radius_m**2), 0.0))
    return np.asarray(np.array(sensor) + t[:, None] * u)


def test_the_circle_fit_finds_the_centre_of_a_seen_arc() -> None:
    points = _arc((3.0, 1.0), 0.2, (0.5, -0.5))
    assert np.allclose(fit_circle(points, np.array([0.5, -0.5]), 0.2), [3.0, 1.0], atol=1e-6)


def test_the_circle_fit_stays_within_centimetres_under_centimetre_range_noise() -> None:
    chance = np.random.default_rng(0)
    sensor = np.array([0.0, 0.0])
    errors = []
    for _ in range(200):
        points = _arc((2.5, 0.7), 0.2, (0.0, 0.0))
        direction = points / np.linalg.norm(points, axis=1, keepdims=True)
        noisy = points + direction * chance.normal(0.0, 0.01, size=(len(points), 1))
        errors.append(np.linalg.norm(fit_circle(noisy, sensor, 0.2) - [2.5, 0.7]))
    assert np.median(errors) < 0.02


def test_returns_on_the_walls_are_dropped_and_the_rest_kept() -> None:
    walls = box_walls(10.0)
    points = np.array([[0.05, 5.0], [5.0, 9.95], [5.0, 5.0], [np.nan, np.nan], [0.3, 5.0]])
    assert off_the_walls(points, walls, 0.1).tolist() == [False, False, True, False, True]


def test_clusters_split_at_gaps_and_join_across_the_scan_seam() -> None:
    points = np.array([[1.0, 0.0], [1.0, 0.05], [3.0, 0.0], [3.0, 0.05], [5.0, 5.0], [1.0, -0.05]])
    keep = np.array([True, True, True, True, False, True])
    runs = clusters(points, keep, 0.3)
    assert sorted(r.tolist() for r in runs) == [[2, 3], [5, 0, 1]]


def test_velocity_is_the_slope_of_the_latest_straight_stretch() -> None:
    times = np.arange(5, dtype=np.float64) * 0.2
    straight = np.stack([1.0 + 0.5 * times, 2.0 - 0.25 * times], axis=1)
    assert np.allclose(fit_velocity(times, straight, 0.01), [0.5, -0.25])
    # A bounce off a wall at the fourth centre: only the stretch after it counts.
    bounced = straight.copy()
    bounced[3:, 0] = bounced[2, 0] - 0.5 * (times[3:] - times[2])
    assert np.allclose(fit_velocity(times, bounced, 0.01), [-0.5, -0.25])
    assert np.allclose(fit_velocity(times[:1], straight[:1], 0.01), [0.0, 0.0])


def test_ego_velocity_reads_speed_and_turn_from_two_poses() -> None:
    before = np.array([1.0, 1.0, 0.5])
    after = np.array([1.0 + 0.1 * math.cos(0.55), 1.0 + 0.1 * math.sin(0.55), 0.6])
    speed, turn = ego_velocity(before, after, 0.2)
    assert speed == pytest.approx(0.5, abs=1e-9)
    assert turn == pytest.approx(0.5, abs=1e-9)


def test_a_tracker_follows_a_crossing_cylinder_to_its_velocity() -> None:
    tracker = ObstacleTracker(TrackerSettings(), box_walls(10.0), BEAMS)
    pose = np.array([5.0, 2.0, 0.3])
    velocity = np.array([-0.6, 0.4])
    for frame in range(6):
        centre = np.array([6.0, 5.0]) + velocity * 0.2 * frame
        tracks = tracker.update(0.2 * frame, _scan_of(centre, pose), pose)
    assert len(tracks.xy_m) == 1
    assert np.allclose(tracks.xy_m[0], centre, atol=1e-3)
    assert np.allclose(tracks.velocity_mps[0], velocity, atol=1e-3)


def test_two_cylinders_side_by_side_are_two_detections_not_one() -> None:
    # Touching in the scan (one run of neighbouring returns), they are cut where the two circle
    # fits leave the least residual: each centre to a millimetre.
    pose = np.array([5.0, 2.0, 0.0])
    left, right = np.array([4.8, 5.0]), np.array([5.15, 5.25])  # the right one half behind
    ranges = np.minimum(_scan_of(left, pose), _scan_of(right, pose))
    tracker = ObstacleTracker(TrackerSettings(), box_walls(10.0), BEAMS)
    points = scan_points(ranges, pose, BEAMS)
    runs = clusters(points, off_the_walls(points, tracker.walls, 0.1), 0.3)
    assert len(runs) == 1, "the two arcs make one run: the case to split"
    found = tracker.detect(ranges, pose)
    assert len(found) == 2
    for centre in (left, right):
        assert np.min(np.linalg.norm(found - centre, axis=1)) < 1e-3


def test_a_long_unknown_object_becomes_a_chain_of_obstacle_wide_pieces() -> None:
    # A 3 m cabinet face 3 m ahead, which the room's walls do not explain: cut in one pass into
    # pieces one obstacle (0.4 m) wide, each a detection within a radius behind the face, so the
    # forecast keeps the car off all of it (the best-cut search would be quadratic in its
    # length: up to 0.2 s a scan, docs/controller.md).
    pose = np.array([5.0, 2.0, math.pi / 2])
    ranges = _scan_of(None, pose).astype(np.float64)
    angle = pose[2] + BEAMS
    with np.errstate(divide="ignore", invalid="ignore"):
        along = 3.0 / np.sin(angle)  # the face y = 5 m, from x = 3.5 to 6.5 m
    x = pose[0] + along * np.cos(angle)
    face = (along > 0) & (np.abs(x - 5.0) <= 1.5)
    ranges[face] = np.minimum(ranges[face], along[face])
    tracker = ObstacleTracker(TrackerSettings(), box_walls(10.0), BEAMS)
    found = tracker.detect(ranges.astype(np.float32), pose)
    assert 7 <= len(found) <= 9  # 3 m in pieces of at most 0.4 m
    assert np.all((found[:, 1] >= 5.0) & (found[:, 1] <= 5.2 + 1e-6))
    assert found[:, 0].min() < 3.5 + 0.4 and found[:, 0].max() > 6.5 - 0.4  # end to end


def test_obstacle_wide_pieces_are_consecutive_and_each_within_the_width() -> None:
    points = np.stack([np.linspace(0.0, 3.0, 61), np.zeros(61)], axis=1)  # 5 cm apart
    run = np.arange(100, 161)
    pieces = one_wide_pieces(run, np.concatenate([np.zeros((100, 2)), points]), 0.42)
    np.testing.assert_array_equal(np.concatenate(pieces), run)
    assert [len(piece) for piece in pieces] == [9] * 6 + [7]  # 0.42 m holds 9 points 5 cm apart


def test_a_lost_track_coasts_then_goes() -> None:
    settings = TrackerSettings(coast_frames=2)
    tracker = ObstacleTracker(settings, box_walls(10.0), BEAMS)
    pose = np.array([5.0, 2.0, 0.0])
    tracker.update(0.0, _scan_of(np.array([6.0, 5.0]), pose), pose)
    empty = _scan_of(None, pose)
    assert len(tracker.update(0.2, empty, pose).xy_m) == 1
    assert len(tracker.update(0.4, empty, pose).xy_m) == 1
    assert len(tracker.update(0.6, empty, pose).xy_m) == 0


def test_a_wrong_tracker_setting_names_itself() -> None:
    with pytest.raises(ConfigError, match="velocity_frames"):
        TrackerSettings(velocity_frames=1)


def _scan_of(centre: np.ndarray | None, pose: np.ndarray) -> np.ndarray:
    """A 720-beam scan of the 10 m box with one cylinder of radius 0.2 m, by ray casting."""
    angle = pose[2] + BEAMS
    u = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        tx = np.where(u[:, 0] > 0, (10.0 - pose[0]) / u[:, 0], -pose[0] / u[:, 0])
        ty = np.where(u[:, 1] > 0, (10.0 - pose[1]) / u[:, 1], -pose[1] / u[:, 1])
    ranges = np.minimum(np.where(tx > 0, tx, np.inf), np.where(ty > 0, ty, np.inf))
    if centre is not None:
        offset = centre - pose[:2]
        along = u @ offset
        disc = along**2 - (offset @ offset - 0.2**2)
        hit = (disc >= 0) & (along > 0)
        ranges = np.where(hit, np.minimum(ranges, along - np.sqrt(np.maximum(disc, 0))), ranges)
    assert np.all(np.isfinite(scan_points(ranges, pose, BEAMS)))
    return ranges.astype(np.float32)


def test_a_bounce_off_a_wall_is_unfolded_so_the_velocity_is_right_at_once() -> None:
    # An obstacle of radius 0.2 m moving at (-1.5, 0.5) m/s bounces off the wall x = 0 between
    # the fourth and fifth centres: reflected in x = 0.2, the last centre continues the line.
    times = np.arange(5, dtype=np.float64) * 0.2
    x = 1.25 - 1.5 * times
    x[4] = 2 * 0.2 - x[4]
    centres = np.stack([x, 3.0 + 0.5 * times], axis=1)
    mirrors = bounce_mirrors(box_walls(10.0), 0.2)
    assert np.allclose(fit_velocity(times, centres, 0.01, mirrors), [1.5, 0.5])
    # Without the mirrors only the last two centres are straight, and they mix both legs.
    assert not np.allclose(fit_velocity(times, centres, 0.01), [1.5, 0.5], atol=0.1)
