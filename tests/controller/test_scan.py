"""Resampling any LaserScan to the policy's beams (controller.scan)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from numpy.typing import NDArray

from qnav.contracts.wire import Scan
from qnav.controller.scan import ScanRules, beam_index, resample_scan

TWO_PI = 2 * math.pi
POLICY_BEAMS = 720


def make_scan(
    count: int,
    angle_min: float,
    ranges: NDArray[np.floating],
    clockwise: bool = False,
    *,
    range_min: float = 0.1,
    range_max: float = 30.0,
    field_of_view: float = TWO_PI,
) -> Scan:
    increment = field_of_view / count * (-1 if clockwise else 1)
    return Scan(
        0.0, "laser", angle_min, increment, range_min, range_max, np.asarray(ranges, np.float32)
    )


def reading_angles(scan: Scan, mount_yaw: float = 0.0) -> NDArray[np.float64]:
    count = len(scan.ranges_m)
    index = np.arange(count, dtype=np.float64)
    angles: NDArray[np.float64] = mount_yaw + scan.angle_min_rad + index * scan.angle_increment_rad
    return angles


def reference(scan: Scan, beams: int, mount_yaw: float = 0.0) -> NDArray[np.float64]:
    """The documented rule by brute force: each beam reads the minimum of the readings whose
    sectors overlap its own by more than a thousandth of the narrower sector."""
    angles = reading_angles(scan, mount_yaw)
    width = abs(scan.angle_increment_rad)
    beam_width = TWO_PI / beams
    centres = np.arange(beams) * beam_width
    gap = np.abs(np.mod(angles[None, :] - centres[:, None] + math.pi, TWO_PI) - math.pi)
    overlap = (width + beam_width) / 2 - gap
    overlaps = overlap > 1e-3 * min(width, beam_width)
    values = np.where(overlaps, np.asarray(scan.ranges_m, np.float64)[None, :], np.inf)
    minimum: NDArray[np.float64] = values.min(axis=1)
    return minimum


def obstacle_scan(count: int, angle_min: float, bearing: float, clockwise: bool = False) -> Scan:
    """10 m everywhere except a 2 m obstacle within 0.05 rad of `bearing` (lidar frame)."""
    scan = make_scan(count, angle_min, np.zeros(count), clockwise)
    angles = reading_angles(scan)
    near = np.abs(np.mod(angles - bearing + math.pi, TWO_PI) - math.pi) < 0.05
    return make_scan(count, angle_min, np.where(near, 2.0, 10.0), clockwise)


LAYOUTS = [(count, start) for count in (360, 720, 1080) for start in (-math.pi, 0.0)]


@pytest.mark.parametrize(("count", "angle_min"), LAYOUTS)
def test_every_scan_layout_follows_the_documented_min_over_overlapping_sectors_rule(
    count: int, angle_min: float
) -> None:
    ranges = np.random.default_rng(count).uniform(0.2, 20.0, count)
    for clockwise in (False, True):
        for yaw in (0.0, 0.3, -math.pi / 2):
            scan = make_scan(count, angle_min, ranges, clockwise)
            got = resample_scan(scan, ScanRules(POLICY_BEAMS, mount_yaw_rad=yaw)).ranges_m
            np.testing.assert_allclose(got, reference(scan, POLICY_BEAMS, yaw), rtol=1e-6)


@pytest.mark.parametrize(("count", "angle_min"), LAYOUTS)
@pytest.mark.parametrize("clockwise", [False, True])
def test_an_obstacle_appears_at_its_bearing_whatever_the_scan_layout(
    count: int, angle_min: float, clockwise: bool
) -> None:
    for bearing in (0.0, 1.0, math.pi, -2.0):
        scan = obstacle_scan(count, angle_min, bearing, clockwise)
        beams = resample_scan(scan, ScanRules(POLICY_BEAMS)).ranges_m
        angles = np.arange(POLICY_BEAMS) * TWO_PI / POLICY_BEAMS
        gap = np.abs(np.mod(angles - bearing + math.pi, TWO_PI) - math.pi)
        assert np.all(beams[gap < 0.04] == 2.0)  # the obstacle, on every beam that sees it
        assert np.all(beams[gap > 0.08] == 10.0)  # nothing else moves
        assert beams[int(np.argmin(gap))] == 2.0


def test_a_scan_in_the_policys_own_layout_passes_unchanged() -> None:
    ranges = np.random.default_rng(0).uniform(0.2, 20.0, POLICY_BEAMS)
    scan = make_scan(POLICY_BEAMS, 0.0, ranges)
    got = resample_scan(scan, ScanRules(POLICY_BEAMS)).ranges_m
    np.testing.assert_array_equal(got, ranges.astype(np.float32))


def test_a_scan_over_minus_pi_to_pi_is_rotated_by_half_a_turn() -> None:
    ranges = np.arange(1, POLICY_BEAMS + 1, dtype=np.float64)
    scan = make_scan(POLICY_BEAMS, -math.pi, ranges, range_max=1e4)
    got = resample_scan(scan, ScanRules(POLICY_BEAMS)).ranges_m
    np.testing.assert_array_equal(got, np.roll(ranges, POLICY_BEAMS // 2))


def test_a_lidar_mounted_backwards_sees_ahead_what_its_own_frame_calls_behind() -> None:
    scan = obstacle_scan(720, -math.pi, bearing=math.pi)
    beams = resample_scan(scan, ScanRules(POLICY_BEAMS, mount_yaw_rad=math.pi)).ranges_m
    assert beams[0] == 2.0
    assert beams[POLICY_BEAMS // 2] == 10.0


def test_a_coarser_scan_gives_each_beam_between_two_readings_the_nearer_of_them() -> None:
    ranges = np.random.default_rng(1).uniform(0.2, 20.0, 360)
    beams = resample_scan(make_scan(360, 0.0, ranges), ScanRules(POLICY_BEAMS)).ranges_m
    np.testing.assert_allclose(beams[0::2], ranges, rtol=1e-6)
    np.testing.assert_allclose(beams[1::2], np.minimum(ranges, np.roll(ranges, -1)), rtol=1e-6)


def test_a_single_short_reading_of_a_finer_scan_is_never_lost() -> None:
    for index in range(0, 1080, 7):
        ranges = np.full(1080, 10.0)
        ranges[index] = 0.7
        beams = resample_scan(make_scan(1080, -math.pi, ranges), ScanRules(POLICY_BEAMS)).ranges_m
        assert beams.min() == pytest.approx(0.7)


def test_readings_outside_the_range_limits_follow_rep_117() -> None:
    ranges = np.array([math.inf, 50.0, -math.inf, math.nan, 0.0, 0.05, 5.0, 5.0])
    scan = make_scan(8, 0.0, ranges, range_min=0.1, range_max=30.0)
    rules = ScanRules(8, uncovered_range_m=99.0)
    invalid = resample_scan(scan, rules)
    # no return, no return, too close, NaN (uncovered), below range_min (invalid -> uncovered)
    np.testing.assert_array_equal(
        invalid.ranges_m, [math.inf, math.inf, 0.0, 99.0, 99.0, 99.0, 5.0, 5.0]
    )
    assert invalid.invalid_fraction == pytest.approx(3 / 8)
    no_return = resample_scan(scan, ScanRules(8, below_range_min="no_return"))
    np.testing.assert_array_equal(no_return.ranges_m[4:6], [math.inf, math.inf])
    assert no_return.invalid_fraction == pytest.approx(1 / 8)
    obstacle = resample_scan(scan, ScanRules(8, below_range_min="obstacle"))
    np.testing.assert_array_equal(obstacle.ranges_m[4:6], [0.0, 0.0])


def test_beams_outside_a_partial_field_of_view_read_the_uncovered_value() -> None:
    fov = math.radians(270)
    scan = make_scan(810, -fov / 2, np.full(810, 4.0), field_of_view=fov)
    angles = np.arange(POLICY_BEAMS) * TWO_PI / POLICY_BEAMS
    behind = np.abs(np.mod(angles, TWO_PI) - math.pi) < math.radians(44)
    ahead = np.abs(np.mod(angles + math.pi, TWO_PI) - math.pi) < math.radians(134)
    for uncovered in (math.inf, 0.0):
        beams = resample_scan(scan, ScanRules(POLICY_BEAMS, uncovered_range_m=uncovered)).ranges_m
        assert np.all(beams[behind] == uncovered)
        assert np.all(beams[ahead] == 4.0)


def masked_resample(scan: Scan, rules: ScanRules) -> tuple[NDArray[np.float32], float]:
    """The resampling as first written, with explicit validity masks: the reference of the
    NaN-marking one in `controller.scan`, which must give the same values. (Only the sign of a
    zero may differ, where a +0 and a -0 reading tie for a beam's minimum: the two minima
    break the tie differently, and nothing downstream tells the zeros apart.)"""
    r = np.asarray(scan.ranges_m, dtype=np.float64)
    finite = np.isfinite(r)
    out = r.copy()
    out[np.isposinf(r) | (finite & (r > scan.range_max_m))] = np.inf
    out[np.isneginf(r)] = 0.0
    valid = ~np.isnan(r)
    below = finite & (r < scan.range_min_m)
    if rules.below_range_min == "invalid":
        valid &= ~below
    elif rules.below_range_min == "no_return":
        out[below] = np.inf
    else:
        out[below] = 0.0
    count = len(r)
    index = beam_index(
        count, scan.angle_min_rad, scan.angle_increment_rad, rules.num_beams, rules.mount_yaw_rad
    )
    padded = np.concatenate([np.where(valid, out, np.inf), [np.inf, rules.uncovered_range_m]])
    covered = np.concatenate([valid, [False, True]])
    beams = padded[index].min(axis=1)
    beams = np.where(covered[index].any(axis=1), beams, rules.uncovered_range_m)
    return beams.astype(np.float32), 1.0 - float(valid.mean())


@pytest.mark.parametrize(("count", "angle_min"), [*LAYOUTS, (7, 0.1), (811, -2.0)])
def test_resampling_gives_the_values_of_the_masked_reference_for_any_readings(
    count: int, angle_min: float
) -> None:
    rng = np.random.default_rng(count)
    limits = [(0.1, 30.0), (0.0, math.inf), (0.5, 0.2), (math.nan, math.nan)]
    for trial in range(12):
        specials = rng.choice([np.nan, np.inf, -np.inf, 0.0, -0.0], count)
        ranges = np.where(rng.random(count) < 0.3, specials, rng.uniform(-1.0, 40.0, count))
        range_min, range_max = limits[trial % len(limits)]
        fov = TWO_PI if trial % 3 else math.radians(200)
        scan = make_scan(
            count,
            angle_min,
            ranges,
            clockwise=trial % 2 == 1,
            range_min=range_min,
            range_max=range_max,
            field_of_view=fov,
        )
        for below in ("invalid", "no_return", "obstacle"):
            for uncovered in (math.inf, 0.0, 7.3):
                rules = ScanRules(
                    POLICY_BEAMS,
                    mount_yaw_rad=0.3 * trial,
                    below_range_min=below,
                    uncovered_range_m=uncovered,
                )
                got = resample_scan(scan, rules)
                beams, invalid_fraction = masked_resample(scan, rules)
                assert got.ranges_m.dtype == np.float32
                np.testing.assert_array_equal(got.ranges_m, beams)
                assert got.invalid_fraction == invalid_fraction


def test_each_beam_of_a_rotating_scan_carries_the_time_of_its_first_reading() -> None:
    """LaserScan's time_increment times the readings; a beam's delay after the stamp is its
    first overlapping reading's (the seam's beam overlaps the last reading and the first, a turn
    apart: the first)."""
    rules = ScanRules(num_beams=POLICY_BEAMS)
    dt = 0.1 / 720
    own = make_scan(POLICY_BEAMS, 0.0, np.full(POLICY_BEAMS, 3.0))
    timed = replace(own, time_increment_s=dt)
    delays = resample_scan(timed, rules).delays_s
    assert delays is not None
    np.testing.assert_allclose(delays, dt * np.arange(POLICY_BEAMS))
    coarse = make_scan(360, 0.0, np.full(360, 3.0))  # each reading covers 1 degree, two beams
    timed = replace(coarse, time_increment_s=dt)
    delays = resample_scan(timed, rules).delays_s
    assert delays is not None
    expected = dt * (np.arange(POLICY_BEAMS) // 2)  # beam 2i: reading i; beam 2i+1: i and i+1
    expected[-1] = 0.0  # the seam's beam: readings 359 and 0
    np.testing.assert_allclose(delays, expected)
    assert resample_scan(coarse, rules).delays_s is None  # no time_increment: all at the stamp
