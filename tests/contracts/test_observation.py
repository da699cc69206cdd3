import math

import numpy as np
import pytest

from contracts.observation import (
    FrameWindow,
    LidarSpec,
    encode_scan,
    encode_target,
    target_features,
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
