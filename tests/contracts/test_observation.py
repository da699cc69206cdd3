import math

import numpy as np
import pytest
from numpy.typing import NDArray

from qnav.contracts.observation import (
    OBSTACLE_FEATURES,
    OBSTACLE_POSITION_SCALE_M,
    OBSTACLE_SLOT_FEATURES,
    OBSTACLE_SLOTS,
    OBSTACLE_SPEED_SCALE_M_S,
    FrameWindow,
    LidarSpec,
    encode_scan,
    encode_target,
    obstacle_features,
    target_features,
    target_features_of,
)


def test_beam_zero_points_along_heading_and_beams_advance_counter_clockwise() -> None:
    angles = LidarSpec(num_beams=720).beam_angles_rad()
    assert angles[0] == 0.0
    assert angles[180] == pytest.approx(math.pi / 2)
    assert angles[-1] < 2 * math.pi


def test_scan_encoding_maps_no_return_and_bad_values_into_unit_range() -> None:
    scan = np.array([np.inf, np.nan, -1.0, 0.0, 10.0, 25.0, -np.inf], dtype=np.float32)
    encoded = encode_scan(scan, max_range_m=20.0)
    np.testing.assert_allclose(encoded, [1.0, 1.0, 0.0, 0.0, 0.5, 1.0, 0.0])
    assert encoded.dtype == np.float32


def test_target_to_the_left_has_positive_sine_and_ahead_has_cosine_one() -> None:
    pose = np.array([[1.0, 1.0, math.pi / 2], [0.0, 0.0, 0.0]])
    target = np.array([[0.0, 1.0], [3.0, 0.0]])
    features = target_features(pose, target)
    np.testing.assert_allclose(features[0], [1.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(features[1], [3.0, 0.0, 1.0], atol=1e-12)


def test_target_at_the_robot_gives_zero_distance_and_finite_bearing() -> None:
    features = target_features(np.array([2.0, 2.0, 0.3]), np.array([2.0, 2.0]))
    np.testing.assert_array_equal(features, [0.0, 0.0, 1.0])


def test_target_encoding_scales_distance_like_the_lidar() -> None:
    encoded = encode_target(np.array([10.0, 0.6, 0.8]), max_range_m=20.0)
    np.testing.assert_allclose(encoded, [0.5, 0.6, 0.8], rtol=1e-6)


def test_a_window_starts_as_copies_of_its_first_frame_and_then_slides_oldest_first() -> None:
    window = FrameWindow(num_streams=2, frame_size=1, length=3)
    first = window.advance(np.array([[1.0], [10.0]], dtype=np.float32)).copy()
    np.testing.assert_array_equal(first[:, :, 0], [[1, 1, 1], [10, 10, 10]])
    window.advance(np.array([[2.0], [20.0]], dtype=np.float32))
    slid = window.advance(np.array([[3.0], [30.0]], dtype=np.float32))
    np.testing.assert_array_equal(slid[:, :, 0], [[1, 2, 3], [10, 20, 30]])


def test_restarting_one_stream_never_mixes_its_old_episode_into_the_new_window() -> None:
    window = FrameWindow(num_streams=2, frame_size=1, length=3)
    for value in (1.0, 2.0, 3.0):
        window.advance(np.array([[value], [value]], dtype=np.float32))
    window.restart(np.array([1]))
    after = window.advance(np.array([[4.0], [7.0]], dtype=np.float32))
    np.testing.assert_array_equal(after[:, :, 0], [[2, 3, 4], [7, 7, 7]])


def test_scan_encoding_gives_the_bits_of_nan_to_num_then_clip() -> None:
    rng = np.random.default_rng(0)
    specials = np.array(
        [np.nan, -np.nan, np.inf, -np.inf, 0.0, -0.0, 20.0, 19.999998, 20.000002, 1e-45, -1e-45],
        dtype=np.float32,
    )
    any_bits = rng.integers(0, 2**32, 200_000, dtype=np.uint64).astype(np.uint32)
    scans: list[NDArray[np.floating]] = [
        specials,
        np.tile(specials, (3, 70)),  # long enough for the vectorised loops
        any_bits.view(np.float32),
        rng.uniform(-5.0, 30.0, (4, 720)),  # float64 in
    ]
    for max_range in (20.0, 7.3, 0.1):
        for scan in scans:
            as_f32 = np.asarray(scan, dtype=np.float32)
            clipped = np.nan_to_num(as_f32, nan=max_range, posinf=max_range)
            reference = np.clip(clipped, 0.0, max_range) / np.float32(max_range)
            encoded = encode_scan(scan, max_range)
            assert encoded.dtype == np.float32
            np.testing.assert_array_equal(encoded.view(np.uint32), reference.view(np.uint32))


def test_one_targets_features_in_floats_are_exactly_the_array_versions() -> None:
    rng = np.random.default_rng(1)
    poses = np.concatenate(
        [rng.uniform(-50.0, 50.0, (2000, 2)), rng.uniform(-10.0, 10.0, (2000, 1))], axis=1
    )
    targets = np.where(rng.random((2000, 1)) < 0.1, poses[:, :2], rng.uniform(-50, 50, (2000, 2)))
    expected = target_features(poses, targets)
    for pose, target, row in zip(poses, targets, expected, strict=True):
        got = target_features_of(*pose.tolist(), *target.tolist())
        assert got == tuple(row.tolist())


def test_a_window_advances_as_per_stream_starts_and_pushes_would() -> None:
    rng = np.random.default_rng(2)
    streams, length = 4, 3
    window = FrameWindow(num_streams=streams, frame_size=2, length=length)
    expected = np.zeros((streams, length, 2), dtype=np.float32)
    fresh = np.ones(streams, dtype=bool)
    for step in range(60):
        restart = [np.array([], dtype=np.intp), np.arange(streams), rng.choice(streams, 2)]
        chosen = restart[step % 3] if step % 5 else restart[0]
        window.restart(chosen)
        fresh[chosen] = True
        frames = rng.random((streams, 2)).astype(np.float32)
        for stream in range(streams):  # one stream at a time, as the rule reads
            if fresh[stream]:
                expected[stream] = frames[stream]
            else:
                expected[stream] = np.roll(expected[stream], -1, axis=0)
                expected[stream, -1] = frames[stream]
        fresh[:] = False
        np.testing.assert_array_equal(window.advance(frames), expected)


def test_obstacles_are_given_nearest_first_in_the_robots_frame() -> None:
    # Robot at (1, 1) facing +y: +y is ahead, -x is to its left.
    pose = np.array([1.0, 1.0, math.pi / 2])
    xy = np.array([[1.0, 4.0], [0.0, 1.0]])  # 3 m ahead; 1 m to the left
    velocity = np.array([[0.0, -0.5], [0.3, 0.0]])  # coming towards it; moving to its right
    slots = obstacle_features(pose, xy, velocity).reshape(OBSTACLE_SLOTS, OBSTACLE_SLOT_FEATURES)
    position, speed = OBSTACLE_POSITION_SCALE_M, OBSTACLE_SPEED_SCALE_M_S
    np.testing.assert_allclose(
        slots[0], [1.0, 0.0, 1.0 / position, 0.0, -0.3 / speed], atol=1e-6
    )  # the nearer one first
    np.testing.assert_allclose(slots[1], [1.0, 3.0 / position, 0.0, -0.5 / speed, 0.0], atol=1e-6)


def test_missing_obstacles_leave_empty_slots_and_extra_ones_are_dropped_farthest_first() -> None:
    pose = np.zeros((2, 3))
    none = obstacle_features(pose, np.zeros((2, 0, 2)), np.zeros((2, 0, 2)))
    assert none.shape == (2, OBSTACLE_FEATURES) and not none.any()
    many = OBSTACLE_SLOTS + 2
    xy = np.stack([np.arange(many, 0, -1.0), np.zeros(many)], axis=-1)  # farthest first
    kept = obstacle_features(np.zeros(3), xy, np.zeros_like(xy)).reshape(OBSTACLE_SLOTS, -1)
    np.testing.assert_allclose(
        kept[:, 1], np.arange(1.0, OBSTACLE_SLOTS + 1) / OBSTACLE_POSITION_SCALE_M
    )
