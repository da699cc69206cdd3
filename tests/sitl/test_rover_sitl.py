"""The bridge against ArduPilot Rover SITL: arming, motion, turning, every stop and fault.

Real parts only: the `ardurover` binary (ARDUPILOT_SITL), `qnav bridge` as a process, a zenoh
peer on loopback. Motion and stops are measured from the autopilot's own LOCAL_POSITION_NED
(and GLOBAL_POSITION_INT), read by an observer on SERIAL0. `pytest -s` prints each stop's
figures (docs/bridge.md's table comes from them).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import pytest

from contracts.mavlink import wrap_pi
from tests.sitl.harness import (
    BridgeProcess,
    Observer,
    Sitl,
    StopMeasure,
    Zenoh,
    measure_stop,
    wait_until,
)

pytestmark = pytest.mark.sitl

StartSitl = Callable[..., tuple[Sitl, Observer]]
StartBridge = Callable[..., BridgeProcess]

BOOT_TIMEOUT_S = 120.0
"""SITL's EKF needs GPS and a settled IMU before it may arm: tens of seconds after boot."""
DRIVE_SPEED_MPS = 1.0
"""The toy car's top speed in the paper's use (the policy's largest forward command)."""


def _report(what: str, measure: StopMeasure) -> None:
    print(
        f"\n[sitl] {what}: from {measure.speed_before_mps:.2f} m/s, at rest after "
        f"{measure.stop_time_s:.2f} s, {measure.stop_distance_m:.2f} m "
        f"(GLOBAL_POSITION_INT: {measure.gps_distance_m:.2f} m)"
    )


def _armed_and_ready(zenoh: Zenoh, observer: Observer) -> None:
    wait_until(
        lambda: zenoh.state().get("armed") and observer.armed,
        BOOT_TIMEOUT_S,
        "the bridge to arm the rover",
    )


def _drive_to_speed(zenoh: Zenoh, observer: Observer, linear_mps: float, seconds: float) -> float:
    """Drive straight for `seconds`; the time of the last command."""
    return zenoh.drive(linear_mps, 0.0, seconds)


@pytest.mark.parametrize("output", ["rc_override", "manual_control", "guided"])
def test_arms_drives_forward_turns_left_and_stops_on_silence(
    output: str, start_sitl: StartSitl, start_bridge: StartBridge, zenoh: Zenoh
) -> None:
    sitl, observer = start_sitl()
    settings = (
        ['output.mode="guided"']
        if output == "guided"
        else ['output.mode="manual"', f'output.manual_message="{output}"']
    )
    bridge = start_bridge(sitl.serial1, *settings)
    _armed_and_ready(zenoh, observer)
    wait_until(lambda: observer.latest("LOCAL_POSITION_NED"), 30, "LOCAL_POSITION_NED")
    north0, east0 = observer.position()
    yaw0 = observer.yaw_ned()
    _drive_to_speed(zenoh, observer, DRIVE_SPEED_MPS, 4.0)
    north1, east1 = observer.position()
    travelled = (north1 - north0) * math.cos(yaw0) + (east1 - east0) * math.sin(yaw0)
    assert travelled > 1.0, f"moved {travelled:.2f} m forward in 4 s"
    # angular.z > 0 turns counter-clockwise seen from above: the NED yaw decreases.
    yaw1 = observer.yaw_ned()
    last = zenoh.drive(DRIVE_SPEED_MPS, 0.5, 3.0)
    turned = wrap_pi(observer.yaw_ned() - yaw1)
    assert turned < -0.3, f"NED yaw changed by {turned:.2f} rad on a left turn"
    measure = measure_stop(observer, last, timeout_s=30.0)
    _report(f"silence, {output}", measure)
    assert measure.rested
    assert bridge.process.poll() is None
