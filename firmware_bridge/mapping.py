"""Pure mappings from a Twist (and a pose) to the numbers MAVLink messages carry.

No I/O here: the link sends what these return. Signs follow the conventions both ends share
(`contracts.mavlink`): a Twist turns counter-clockwise for positive angular speed; RC steering
above trim, MANUAL_CONTROL y > 0 and a NED yaw rate > 0 all turn right (clockwise from above).
"""

from __future__ import annotations

import math
from typing import NamedTuple

from qnav.contracts.mavlink import enu_to_ned
from qnav.contracts.wire import Pose2D, Twist2D
from qnav.firmware_bridge.settings import UNCALIBRATED_SPEED_AT_FULL_THROTTLE_MPS, OutputSettings


class Sticks(NamedTuple):
    """Steering and throttle as fractions of full travel, each in [-1, 1]."""

    steering: float
    """+1 full right, -1 full left."""
    throttle: float
    """+1 full forward, -1 full reverse."""


class RcOverride(NamedTuple):
    """PWM of RC_CHANNELS_OVERRIDE's two channels Rover reads in MANUAL mode."""

    steering_pwm_us: int
    """Channel 1."""
    throttle_pwm_us: int
    """Channel 3."""


class ManualControl(NamedTuple):
    """MANUAL_CONTROL's two axes Rover reads: -1000..1000, 0 = centre/stop."""

    y: int
    """Steering (positive: right)."""
    z: int
    """Throttle (positive: forward)."""


class VelocityTarget(NamedTuple):
    """SET_POSITION_TARGET_LOCAL_NED's body-frame velocity and NED yaw rate."""

    forward_mps: float
    """vx in MAV_FRAME_BODY_NED (Rover drives backwards when negative)."""
    yaw_rate_radps: float
    """Clockwise positive, as NED."""


class VisionPose(NamedTuple):
    """VISION_POSITION_ESTIMATE's position and attitude, NED."""

    north_m: float
    east_m: float
    down_m: float
    yaw_rad: float


def _clip(value: float, limit: float) -> float:
    """`value` clipped to [-limit, limit]; a non-finite value is neutral (0), never a limit."""
    if not math.isfinite(value):
        return 0.0
    return max(-limit, min(limit, value))


def _finite(twist: Twist2D) -> bool:
    return math.isfinite(twist.linear_mps) and math.isfinite(twist.angular_radps)


def pose_problem(pose: Pose2D, max_position_m: float) -> str | None:
    """Why a motion-capture pose must not go to the autopilot as its position, or None."""
    values = (pose.x_m, pose.y_m, pose.yaw_rad)
    if not all(math.isfinite(value) for value in values):
        return f"non-finite pose {values}"
    if max(abs(pose.x_m), abs(pose.y_m)) > max_position_m:
        return f"position ({pose.x_m:g}, {pose.y_m:g}) m is beyond {max_position_m:g} m"
    return None


def speed_scale(output: OutputSettings) -> float:
    """The speed full throttle stands for: the car's as measured, or while it is not (an
    uncalibrated car is not a fast car) a fast car's."""
    measured = output.speed_at_full_throttle_mps
    return UNCALIBRATED_SPEED_AT_FULL_THROTTLE_MPS if measured is None else measured


def full_scale(output: OutputSettings) -> tuple[float, float]:
    """The speed (m/s) and turn rate (rad/s) that the output mode maps to its limits."""
    if output.mode == "guided":
        return output.guided_max_speed_mps, output.guided_max_turn_rate_radps
    return speed_scale(output), output.turn_rate_at_full_steering_radps


def implausible(twist: Twist2D, output: OutputSettings, factor: float) -> str | None:
    """Why a command is too far beyond the output's full scale to be meant, or None."""
    speed, turn_rate = full_scale(output)
    for name, value, scale, unit in (
        ("linear.x", twist.linear_mps, speed, "m/s"),
        ("angular.z", twist.angular_radps, turn_rate, "rad/s"),
    ):
        if not math.isfinite(value) or abs(value) > factor * max(scale, 1e-9):
            return f"{name} = {value} {unit} is beyond {factor} x the full scale {scale} {unit}"
    return None


def sticks(twist: Twist2D, output: OutputSettings) -> Sticks:
    """Fractions of full steering and throttle for a Twist, clipped to [-1, 1].

    A Twist with a non-finite part is no command at all: both sticks centre (the finite part
    must not steer or drive on its own).
    """
    if not _finite(twist):
        return Sticks(0.0, 0.0)
    steering = -twist.angular_radps / output.turn_rate_at_full_steering_radps
    throttle = twist.linear_mps / speed_scale(output)
    if output.steering_reversed:
        steering = -steering
    if output.throttle_reversed:
        throttle = -throttle
    # The throttle cap and a forbidden reverse hold whatever message carries the sticks
    # (MANUAL_CONTROL has no PWM for the PWM limits to clip).
    throttle = _clip(throttle, output.max_throttle_fraction)
    if output.throttle_pwm_min_us == output.throttle_pwm_trim_us:
        throttle = max(0.0, throttle)
    # `+ 0.0` turns -0.0 into 0.0 so a stop maps exactly to trim.
    return Sticks(_clip(steering, 1.0) + 0.0, throttle + 0.0)


def fraction_to_pwm(fraction: float, low_us: int, trim_us: int, high_us: int) -> int:
    """PWM for a fraction of travel in [-1, 1]: trim at 0, each end of the range at +-1."""
    fraction = _clip(fraction, 1.0)
    span = (high_us - trim_us) if fraction >= 0 else (trim_us - low_us)
    return max(low_us, min(high_us, round(trim_us + fraction * span)))


def rc_override(twist: Twist2D, output: OutputSettings) -> RcOverride:
    """The steering and throttle PWM for a Twist, within the configured limits."""
    steering, throttle = sticks(twist, output)
    return RcOverride(
        fraction_to_pwm(
            steering,
            output.steering_pwm_min_us,
            output.steering_pwm_trim_us,
            output.steering_pwm_max_us,
        ),
        fraction_to_pwm(
            throttle,
            output.throttle_pwm_min_us,
            output.throttle_pwm_trim_us,
            output.throttle_pwm_max_us,
        ),
    )


def manual_control(twist: Twist2D, output: OutputSettings) -> ManualControl:
    """MANUAL_CONTROL axes for a Twist (the autopilot applies its own RC calibration)."""
    steering, throttle = sticks(twist, output)
    return ManualControl(round(steering * 1000), round(throttle * 1000))


def velocity_target(twist: Twist2D, output: OutputSettings) -> VelocityTarget:
    """Guided velocity and yaw rate for a Twist, clipped to the configured maxima (a Twist with
    a non-finite part: zero for both)."""
    if not _finite(twist):
        return VelocityTarget(0.0, 0.0)
    forward = _clip(twist.linear_mps, output.guided_max_speed_mps)
    yaw_rate = _clip(-twist.angular_radps, output.guided_max_turn_rate_radps)
    return VelocityTarget(forward + 0.0, yaw_rate + 0.0)


def vision_pose(pose: Pose2D) -> VisionPose:
    """A motion-capture pose in our frame as the NED pose the autopilot expects."""
    north, east, yaw = enu_to_ned(pose.x_m, pose.y_m, pose.yaw_rad)
    return VisionPose(north, east, 0.0, yaw)


def origin_e7(lat_deg: float, lon_deg: float, alt_m: float) -> tuple[int, int, int]:
    """SET_GPS_GLOBAL_ORIGIN's integer fields: degrees * 1e7 and millimetres."""
    return round(lat_deg * 1e7), round(lon_deg * 1e7), round(alt_m * 1000)
