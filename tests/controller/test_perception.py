"""The onboard obstacle tracker: each pure step, then the whole tracker on the simulator's scans."""

import math

import numpy as np
import pytest

from qnav.contracts.errors import ConfigError
from qnav.contracts.observation import LidarSpec
from qnav.controller.perception import (
    ObstacleTracker,
    StaticGrid,
    TrackerSettings,
    bounce_mirrors,
    box_walls,
    clusters,
    ego_velocity,
    fit_velocity,
    off_the_walls,
    scan_points,
    wall_noise,
)
from qnav.controller.shapes import arc_of, fit_arc

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


@pytest.mark.parametrize("radius", [0.05, 0.2, 0.45])
def test_the_arc_fit_finds_the_centre_and_radius_of_a_seen_arc(radius: float) -> None:
    points = _arc((3.0, 1.0), radius, (0.5, -0.5))
    centre, found, rms = fit_arc(points, np.array([0.5, -0.5]))
    np.testing.assert_allclose(centre, [3.0, 1.0], atol=1e-9)
    assert found == pytest.approx(radius, abs=1e-9) and rms < 1e-9


def test_the_arc_fit_stays_within_centimetres_under_centimetre_range_noise() -> None:
    chance = np.random.default_rng(0)
    sensor = np.array([0.0, 0.0])
    errors = []
    for _ in range(200):
        points = _arc((2.5, 0.7), 0.2, (0.0, 0.0))
        direction = points / np.linalg.norm(points, axis=1, keepdims=True)
        noisy = points + direction * chance.normal(0.0, 0.01, size=(len(points), 1))
        arc = arc_of(noisy, sensor, 0.01, 0.6)
        if arc is not None:
            errors.append(np.linalg.norm(arc[0] - [2.5, 0.7]))
    assert len(errors) > 150 and np.median(errors) < 0.03


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
    # Touching in the scan (one run of neighbouring returns), they are cut where the range peaks
    # between them: each centre and radius exact.
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
        nearest = min(found, key=lambda shape: float(np.linalg.norm(shape.centre - centre)))
        np.testing.assert_allclose(nearest.centre, centre, atol=1e-6)
        assert nearest.radius_m == pytest.approx(0.2, abs=1e-6)


def _box_scan(pose: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """The 10 m box's scan with a polygon (its corners in order) added."""
    ranges = _scan_of(None, pose).astype(np.float64)
    angle = pose[2] + BEAMS
    d = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    for start, end in zip(corners, np.roll(corners, -1, axis=0), strict=True):
        e = end - start
        w = start - pose[:2]
        with np.errstate(divide="ignore", invalid="ignore"):
            inverse = 1.0 / (d[:, 0] * e[1] - d[:, 1] * e[0])
            t = (w[0] * e[1] - w[1] * e[0]) * inverse
            u = (w[0] * d[:, 1] - w[1] * d[:, 0]) * inverse
        hit = np.isfinite(inverse) & (t > 0) & (u >= 0) & (u <= 1)
        ranges = np.where(hit, np.minimum(ranges, t), ranges)
    return ranges.astype(np.float32)


def test_a_box_seen_corner_on_is_one_object_round_its_middle_as_wide_as_it() -> None:
    pose = np.array([5.0, 2.0, 0.0])
    centre, half = np.array([5.2, 5.0]), 0.3  # a 0.6 m square turned 45 degrees
    corners = centre + half * np.sqrt(2) * np.array([[0, -1], [1, 0], [0, 1], [-1, 0]])
    tracker = ObstacleTracker(TrackerSettings(), box_walls(10.0), BEAMS)
    found = tracker.detect(_box_scan(pose, corners), pose)
    assert len(found) == 1
    assert np.linalg.norm(found[0].centre - centre) < 0.15
    # The circle round the found centre holds the seen corner and both side corners.
    reach = np.linalg.norm(corners[[0, 1, 3]] - found[0].centre, axis=1)
    assert (reach <= found[0].radius_m + 0.1).all()


def test_a_persons_two_legs_with_the_wall_seen_between_them_are_one_object() -> None:
    pose = np.array([5.0, 2.0, math.pi / 2])
    legs = (np.array([4.875, 5.0]), np.array([5.125, 5.0]))
    ranges = np.minimum(_scan_of_radius(legs[0], pose, 0.06), _scan_of_radius(legs[1], pose, 0.06))
    tracker = ObstacleTracker(TrackerSettings(), box_walls(10.0), BEAMS)
    found = tracker.detect(ranges, pose)
    assert len(found) == 1
    assert np.linalg.norm(found[0].centre - np.array([5.0, 5.0])) < 0.1
    assert 0.15 <= found[0].radius_m <= 0.3


def test_a_long_unknown_object_becomes_pieces_that_stand_still_as_the_car_drives_by() -> None:
    # A 3 m cabinet face 3 m ahead, which the room's walls do not explain: pieces on a grid
    # fixed in the room, each within a piece of the face, end to end; and as the car drives
    # along it, no piece's track moves (a static wall got 0.23 m/s before, issue 53).
    tracker = ObstacleTracker(TrackerSettings(), box_walls(10.0), BEAMS)
    face = np.array([[3.5, 5.0], [6.5, 5.0], [6.5, 5.3], [3.5, 5.3]])
    for frame in range(8):
        pose = np.array([4.0 + 0.1 * frame, 2.0, math.pi / 2])
        found = tracker.detect(_box_scan(pose, face), pose)
        tracks = tracker.update(0.2 * frame, _box_scan(pose, face), pose)
    centres = np.array([shape.centre for shape in found])
    assert len(found) >= 3
    assert np.all((centres[:, 1] >= 5.0 - 1e-6) & (centres[:, 1] <= 5.3))
    assert centres[:, 0].min() < 3.5 + 1.0 and centres[:, 0].max() > 6.5 - 1.0
    gaps = np.linalg.norm(centres[:, None] - tracks.xy_m[None], axis=2)
    assert gaps.min(axis=1).max() < 0.05  # every piece tracked
    assert np.abs(tracks.velocity_mps).max() == 0.0


def test_a_thin_pole_far_away_is_tracked_once_seen_twice_and_a_stray_return_is_not() -> None:
    tracker = ObstacleTracker(TrackerSettings(), box_walls(10.0), BEAMS)
    pose = np.array([5.0, 1.0, math.pi / 2])
    pole = _scan_of_radius(np.array([5.0, 5.0]), pose, 0.015)  # 3 cm wide, 4 m away
    assert np.sum(pole != _scan_of(None, pose)) == 1  # one return
    assert len(tracker.update(0.0, pole, pose).xy_m) == 0  # once: maybe a stray return
    tracks = tracker.update(0.2, pole, pose)
    assert len(tracks.xy_m) == 1 and np.linalg.norm(tracks.xy_m[0] - [5.0, 5.0]) < 0.03
    stray = _scan_of(None, pose)
    stray[300] = 3.0
    fresh = ObstacleTracker(TrackerSettings(), box_walls(10.0), BEAMS)
    fresh.update(0.0, stray, pose)
    assert len(fresh.update(0.2, _scan_of(None, pose), pose).xy_m) == 0


def test_ten_centimetres_of_range_noise_on_the_walls_makes_no_obstacle_of_them() -> None:
    chance = np.random.default_rng(4)
    tracker = ObstacleTracker(TrackerSettings(), box_walls(10.0), BEAMS)
    pose = np.array([5.0, 4.0, 0.3])
    for frame in range(10):
        ranges = _scan_of(np.array([6.0, 6.0]), pose) + chance.normal(0.0, 0.1, len(BEAMS))
        tracks = tracker.update(0.2 * frame, ranges.astype(np.float32), pose)
    assert tracker.noise_m == pytest.approx(0.1, rel=0.2)
    moving = np.linalg.norm(tracks.velocity_mps, axis=1) > 0
    assert moving.sum() == 0  # the cylinder stands still; so do the walls' stray returns
    assert np.linalg.norm(tracks.xy_m - [6.0, 6.0], axis=1).min() < 0.1


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
    return _scan_of_radius(centre, pose, 0.2)


def _scan_of_radius(centre: np.ndarray | None, pose: np.ndarray, radius: float) -> np.ndarray:
    """A 720-beam scan of the 10 m box with one cylinder of `radius`, by ray casting."""
    angle = pose[2] + BEAMS
    u = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        tx = np.where(u[:, 0] > 0, (10.0 - pose[0]) / u[:, 0], -pose[0] / u[:, 0])
        ty = np.where(u[:, 1] > 0, (10.0 - pose[1]) / u[:, 1], -pose[1] / u[:, 1])
    ranges = np.minimum(np.where(tx > 0, tx, np.inf), np.where(ty > 0, ty, np.inf))
    if centre is not None:
        offset = centre - pose[:2]
        along = u @ offset
        disc = along**2 - (offset @ offset - radius**2)
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


def _scan_of_poles(poles: np.ndarray, mover: np.ndarray | None, pose: np.ndarray) -> np.ndarray:
    """The 10 m box's scan with poles of radius 0.075 m (P, 2) and a mover of 0.2 m."""
    ranges = _scan_of(mover, pose)
    for pole in poles:
        ranges = np.minimum(ranges, _scan_of_radius(pole, pose, 0.075))
    return ranges


def test_a_mover_passing_standing_clutter_keeps_its_own_track_and_velocity() -> None:
    # A row of thin poles (BARN's clutter: 0.075 m radius on a 0.15 m grid) and an obstacle of
    # 0.2 m passing 5 cm beside it at 1 m/s: their returns make one run of beams. Once the
    # poles have stood in view long enough (`StaticGrid`), their returns are clustered apart.
    poles = np.stack([4.0 + 0.15 * np.arange(8), np.full(8, 6.0)], axis=1)
    pose = np.array([5.0, 2.0, 0.0])
    tracker = ObstacleTracker(TrackerSettings(), box_walls(10.0), BEAMS)
    for frame in range(10):
        tracker.update(0.2 * frame, _scan_of_poles(poles, None, pose), pose)
    velocity = np.array([1.0, 0.0])
    for frame in range(6):
        mover = np.array([3.8, 5.675]) + velocity * 0.2 * frame
        tracks = tracker.update(2.0 + 0.2 * frame, _scan_of_poles(poles, mover, pose), pose)
    moving = np.flatnonzero(np.linalg.norm(tracks.velocity_mps, axis=1) > 0)
    assert len(moving) == 1
    np.testing.assert_allclose(tracks.xy_m[moving[0]], mover, atol=0.02)
    np.testing.assert_allclose(tracks.velocity_mps[moving[0]], velocity, atol=0.05)


def test_returns_hit_again_and_again_in_the_rooms_frame_are_of_what_stands() -> None:
    grid = StaticGrid(box_walls(10.0))
    points = np.array([[3.0, 3.0], [7.0, 7.0]])
    keep = np.array([True, True])
    for _ in range(9):  # the first point in every scan; the second in one
        assert not grid.standing(points, keep).any()
        grid.add(points, np.array([True, False]))
    grid.add(points, keep)
    assert grid.standing(points, keep).tolist() == [True, False]


def test_clutter_along_a_wall_is_not_taken_for_the_walls_range_noise() -> None:
    # Poles 0.15 m inside the wall y = 10, seen from close by, hide most of it; their returns
    # lie within `NOISE_NEAR_WALL_M` of it. The noise is read from the returns beyond the walls,
    # where only a noisy wall's fall.
    poles = np.stack([2.0 + 0.15 * np.arange(30), np.full(30, 9.85)], axis=1)
    pose = np.array([4.2, 9.3, 0.0])
    north = box_walls(10.0)[2:3]
    points = scan_points(_scan_of_poles(poles, None, pose), pose, BEAMS)
    assert (wall_noise(points, north) or 0.0) > 0.05  # the poles taken for noise
    assert (wall_noise(points, north, pose[:2]) or 0.0) < 1e-6
    chance = np.random.default_rng(5)
    ranges = _scan_of_poles(poles, None, pose) + chance.normal(0.0, 0.05, len(BEAMS))
    noisy = scan_points(ranges.astype(np.float32), pose, BEAMS)
    assert wall_noise(noisy, box_walls(10.0), pose[:2]) == pytest.approx(0.05, rel=0.25)
