"""Twist to RC PWM, MANUAL_CONTROL axes and guided targets; poses to NED."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from qnav.contracts.mavlink import enu_to_ned, ned_to_enu
from qnav.contracts.wire import STOP, Pose2D, Twist2D
from qnav.firmware_bridge import mapping
from qnav.firmware_bridge.settings import OutputSettings

OUT = OutputSettings(speed_at_full_throttle_mps=1.0)
"""A car measured at 1 m/s at full throttle: 0.5 m/s is half throttle."""


def test_stop_maps_to_trim_on_both_channels() -> None:
    assert mapping.rc_override(STOP, OUT) == (1500, 1500)
    assert mapping.manual_control(STOP, OUT) == (0, 0)
    assert mapping.velocity_target(STOP, OUT) == (0.0, 0.0)


def test_forward_raises_throttle_and_keeps_steering_centred() -> None:
    pwm = mapping.rc_override(Twist2D(0.5, 0.0), OUT)
    assert pwm.throttle_pwm_us == 1700 and pwm.steering_pwm_us == 1500


def test_left_turn_steers_below_trim_and_right_above() -> None:
    assert mapping.rc_override(Twist2D(0.0, 0.5), OUT).steering_pwm_us == 1300
    assert mapping.rc_override(Twist2D(0.0, -0.5), OUT).steering_pwm_us == 1700
    assert mapping.manual_control(Twist2D(0.0, 0.5), OUT).y == -500


def test_pwm_never_leaves_the_configured_limits() -> None:
    out = replace(OUT, throttle_pwm_min_us=1500, throttle_pwm_max_us=1650)
    for linear in (-100.0, -1.0, 0.3, 1.0, 100.0):
        for angular in (-100.0, 0.0, 100.0):
            pwm = mapping.rc_override(Twist2D(linear, angular), out)
            assert 1500 <= pwm.throttle_pwm_us <= 1650
            assert 1100 <= pwm.steering_pwm_us <= 1900
    assert mapping.rc_override(Twist2D(-1.0, 0.0), out).throttle_pwm_us == 1500  # no reverse


def test_an_unmeasured_speed_scale_is_a_fast_cars() -> None:
    # With the shipped settings 0.5 m/s was half throttle: 6.5 m/s on SITL's rover (issue 53).
    unmeasured = OutputSettings()
    assert unmeasured.speed_at_full_throttle_mps is None
    forward = Twist2D(0.5, 0.0)
    assert mapping.sticks(forward, unmeasured).throttle == pytest.approx(0.5 / 20.0)
    assert mapping.rc_override(forward, unmeasured).throttle_pwm_us == 1510
    assert mapping.manual_control(forward, unmeasured).z == 25
    assert mapping.full_scale(unmeasured)[0] == 20.0
    assert mapping.sticks(forward, OUT).throttle == 0.5


def test_scales_set_what_full_travel_means() -> None:
    out = OutputSettings(speed_at_full_throttle_mps=0.5, turn_rate_at_full_steering_radps=2.0)
    assert mapping.sticks(Twist2D(0.25, 1.0), out) == (-0.5, 0.5)


def test_reversed_channels_flip_their_direction() -> None:
    out = replace(OUT, steering_reversed=True, throttle_reversed=True)
    assert mapping.rc_override(Twist2D(0.5, 0.5), out) == (1700, 1300)


def test_asymmetric_pwm_range_reaches_each_end_at_full_travel() -> None:
    assert mapping.fraction_to_pwm(1.0, 1000, 1450, 2000) == 2000
    assert mapping.fraction_to_pwm(-1.0, 1000, 1450, 2000) == 1000
    assert mapping.fraction_to_pwm(0.5, 1000, 1450, 2000) == 1725


def test_guided_target_turns_counter_clockwise_as_negative_ned_yaw_rate_and_clips() -> None:
    out = OutputSettings(guided_max_speed_mps=0.4, guided_max_turn_rate_radps=0.3)
    target = mapping.velocity_target(Twist2D(1.0, 1.0), out)
    assert target == (0.4, -0.3)


def test_pose_to_ned_and_back_is_the_identity() -> None:
    for x, y, yaw in [(1.0, 2.0, 0.3), (-3.0, 0.5, -2.9), (0.0, 0.0, math.pi / 2)]:
        back = ned_to_enu(*enu_to_ned(x, y, yaw))
        assert back == pytest.approx((x, y, yaw))


def test_facing_our_y_axis_is_facing_north() -> None:
    vision = mapping.vision_pose(Pose2D(0.0, "map", 1.0, 2.0, math.pi / 2))
    assert (vision.north_m, vision.east_m) == (2.0, 1.0)
    assert vision.yaw_rad == pytest.approx(0.0)


def test_origin_is_in_degrees_e7_and_millimetres() -> None:
    assert mapping.origin_e7(-35.363261, 149.16523, 584.0) == (-353632610, 1491652300, 584000)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_a_non_finite_value_maps_to_neutral_in_every_output(bad: float) -> None:
    for twist in (Twist2D(bad, 0.0), Twist2D(0.0, bad), Twist2D(bad, bad)):
        assert mapping.rc_override(twist, OUT) == (1500, 1500)
        assert mapping.manual_control(twist, OUT) == (0, 0)
        assert mapping.velocity_target(twist, OUT) == (0.0, 0.0)


def test_commands_far_beyond_full_scale_are_implausible_and_overshoot_is_not() -> None:
    assert mapping.implausible(Twist2D(1.5, -2.0), OUT, 10.0) is None  # clipped, not refused
    assert mapping.implausible(Twist2D(9.9, 0.0), OUT, 10.0) is None
    for twist in (Twist2D(10.1, 0.0), Twist2D(0.0, -9.1e150), Twist2D(1e308, 1e308)):
        assert "beyond 10.0 x" in (mapping.implausible(twist, OUT, 10.0) or "")
    guided = OutputSettings(mode="guided", guided_max_speed_mps=0.5)
    assert mapping.implausible(Twist2D(5.5, 0.0), guided, 10.0) is not None


@pytest.mark.parametrize(
    "twist",
    [Twist2D(math.nan, 0.5), Twist2D(0.5, math.inf), Twist2D(-math.inf, -0.7)],
    ids=str,
)
def test_a_twist_with_one_non_finite_part_is_no_command_at_all(twist: Twist2D) -> None:
    # The finite part alone must not steer or drive: the sender is broken.
    assert mapping.sticks(twist, OUT) == (0.0, 0.0)
    assert mapping.rc_override(twist, OUT) == (1500, 1500)
    assert mapping.manual_control(twist, OUT) == (0, 0)
    assert mapping.velocity_target(twist, OUT) == (0.0, 0.0)


def test_a_non_finite_fraction_is_trim_not_a_limit() -> None:
    for fraction in (math.nan, math.inf, -math.inf):
        assert mapping.fraction_to_pwm(fraction, 1100, 1500, 1900) == 1500


def test_absurd_poses_are_refused() -> None:
    assert mapping.pose_problem(Pose2D(0.0, "map", 3.0, -4.0, 1.0), 100.0) is None
    assert mapping.pose_problem(Pose2D(0.0, "map", 1e308, 0.0, 0.0), 100.0) is not None
    assert mapping.pose_problem(Pose2D(0.0, "map", 0.0, -100.5, 0.0), 100.0) is not None
    assert mapping.pose_problem(Pose2D(0.0, "map", math.nan, 0.0, 0.0), 100.0) is not None


def test_the_throttle_cap_and_no_reverse_hold_in_both_manual_messages() -> None:
    # MANUAL_CONTROL carries no PWM: the PWM limits alone never capped it (issue 20).
    out = replace(OUT, max_throttle_fraction=0.4, throttle_pwm_min_us=1500)
    for linear in (-5.0, -1.0, 0.5, 1.0, 5.0):
        z = mapping.manual_control(Twist2D(linear, 0.0), out).z
        pwm = mapping.rc_override(Twist2D(linear, 0.0), out).throttle_pwm_us
        assert 0 <= z <= 400
        assert 1500 <= pwm <= 1500 + 0.4 * 400
        assert z == round((pwm - 1500) / 400 * 1000)
    assert mapping.manual_control(Twist2D(1.0, 0.0), out).z == 400
