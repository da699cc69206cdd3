"""The MAVLink test vehicle follows ArduPilot Rover's rules, over real UDP on loopback."""

from __future__ import annotations

import math
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from qnav.contracts.daemon import free_port
from qnav.contracts.mavlink import (
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_SET_MODE,
    MAV_FRAME_BODY_NED,
    MAV_MODE_FLAG_SAFETY_ARMED,
    MAV_RESULT_ACCEPTED,
    MAV_RESULT_FAILED,
    ROVER_MODES,
    TYPE_MASK_VELOCITY,
    TYPE_MASK_VELOCITY_YAW_RATE,
    open_connection,
)
from qnav.contracts.motion import step_velocity_lag
from qnav.contracts.settings import with_overrides
from qnav.simcar.car import drive
from qnav.simcar.mavlink_vehicle import MavlinkVehicle, MavlinkVehicleSettings

IGNORE = 65535


class Station:
    """A ground station (or a rogue sender) on a pymavlink connection to the vehicle."""

    def __init__(self, port: int, system_id: int = 255, key: bytes | None = None) -> None:
        self.conn: Any = open_connection(
            f"udpout:127.0.0.1:{port}",
            baud_rate=115200,
            system_id=system_id,
            component_id=190,
            signing_key=key,
        )
        self.mav: Any = self.conn.mav

    def wait(
        self, kind: str, condition: Callable[[Any], bool] = bool, timeout_s: float = 3.0
    ) -> Any:
        """The next message of a type that meets `condition`, heartbeating meanwhile."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.mav.heartbeat_send(6, 8, 0, 0, 4)
            message = self.conn.recv_match(type=kind, blocking=True, timeout=0.05)
            if message is not None and condition(message):
                return message
        raise AssertionError(f"no {kind} in {timeout_s} s")

    def command(self, command: int, *params: float) -> Any:
        """Send a COMMAND_LONG; its COMMAND_ACK."""
        padded = (list(params) + [0.0] * 7)[:7]
        self.mav.command_long_send(1, 1, command, 0, *padded)
        return self.wait("COMMAND_ACK", lambda ack: ack.command == command)

    def override(self, steering_pwm: int, throttle_pwm: int) -> None:
        self.mav.rc_channels_override_send(
            1, 1, steering_pwm, IGNORE, throttle_pwm, *([IGNORE] * 5)
        )

    def give_position(self, vehicle: MavlinkVehicle) -> None:
        """Set the EKF origin and send the vehicle's own pose as a vision estimate."""
        self.mav.set_gps_global_origin_send(1, -353632610, 1491652300, 584000)
        self.wait("GPS_GLOBAL_ORIGIN")
        self.vision(vehicle)

    def vision(self, vehicle: MavlinkVehicle) -> None:
        x, y, _ = vehicle.pose()
        self.mav.vision_position_estimate_send(int(time.time() * 1e6), y, x, 0.0, 0.0, 0.0, 0.0)


@pytest.fixture
def rig() -> Iterator[Callable[..., tuple[MavlinkVehicle, Station]]]:
    """`rig(**vehicle_settings)` -> a running vehicle and a ground station talking to it."""
    opened: list[tuple[MavlinkVehicle, Station]] = []

    def make(
        station_id: int = 255, key: bytes | None = None, **fields: Any
    ) -> tuple[MavlinkVehicle, Station]:
        port = free_port(socket.SOCK_DGRAM)
        values = {
            "connection": f"udpin:127.0.0.1:{port}",
            "heartbeat_period_s": 0.05,
            "telemetry_period_s": 0.05,
            "dynamics": {"linear_time_constant_s": 0.1, "angular_time_constant_s": 0.1},
            **fields,
        }
        vehicle = MavlinkVehicle(with_overrides(MavlinkVehicleSettings(), values))
        vehicle.start()
        station = Station(port, station_id, key)
        opened.append((vehicle, station))
        return vehicle, station

    yield make
    for vehicle, station in opened:
        station.conn.close()
        vehicle.stop()


def _armed(heartbeat: Any) -> bool:
    return bool(heartbeat.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)


def _drive(station: Station, steering_pwm: int, throttle_pwm: int, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        station.override(steering_pwm, throttle_pwm)
        time.sleep(0.05)


def test_heartbeat_says_rover_disarmed_in_manual_at_boot(rig: Callable[..., Any]) -> None:
    _, station = rig()
    heartbeat = station.wait("HEARTBEAT")
    assert (heartbeat.type, heartbeat.autopilot) == (10, 3)  # ground rover, ArduPilot
    assert heartbeat.custom_mode == ROVER_MODES["MANUAL"] and not _armed(heartbeat)


def test_arm_and_disarm_are_acknowledged_and_shown_in_the_heartbeat(
    rig: Callable[..., Any],
) -> None:
    vehicle, station = rig()
    assert station.command(MAV_CMD_COMPONENT_ARM_DISARM, 1.0).result == MAV_RESULT_ACCEPTED
    station.wait("HEARTBEAT", _armed)
    assert station.command(MAV_CMD_COMPONENT_ARM_DISARM, 0.0).result == MAV_RESULT_ACCEPTED
    station.wait("HEARTBEAT", lambda heartbeat: not _armed(heartbeat))
    assert not vehicle.armed


def test_mode_changes_show_in_custom_mode(rig: Callable[..., Any]) -> None:
    _, station = rig()
    for mode in ("HOLD", "MANUAL"):
        ack = station.command(MAV_CMD_DO_SET_MODE, 1, ROVER_MODES[mode])
        assert ack.result == MAV_RESULT_ACCEPTED
        station.wait("HEARTBEAT", lambda heartbeat, m=mode: heartbeat.custom_mode == ROVER_MODES[m])


def test_rc_override_moves_the_armed_car_forward_and_left(rig: Callable[..., Any]) -> None:
    vehicle, station = rig()
    station.command(MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    _drive(station, 1500, 1900, 0.4)
    x, y, yaw = vehicle.pose()
    assert x > 0.1 and abs(y) < 1e-6 and abs(yaw) < 1e-6
    _drive(station, 1100, 1500, 0.4)  # below-trim steering is a left turn
    assert vehicle.pose()[2] > 0.1


def test_with_external_physics_the_car_moves_only_by_advance_exactly_as_the_simulator_does(
    rig: Callable[..., Any],
) -> None:
    # The sim-car's lockstep: the override is taken over MAVLink, but the car stays put until
    # advance() moves it one control period, as `step_velocity_lag` moves the simulator's robot.
    vehicle, station = rig(external_physics=True)
    station.command(MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    station.wait("HEARTBEAT", _armed)
    station.override(1500, 1700)  # half throttle
    params = vehicle.settings.dynamics
    half = 0.5 * params.max_speed_mps
    assert vehicle.wait_for_targets(half, 0.0, 0.01, timeout_s=3.0)
    assert not vehicle.wait_for_targets(2 * half, 0.0, 0.01, timeout_s=0.1)
    time.sleep(0.2)
    assert vehicle.pose() == (0.0, 0.0, 0.0), "it moved with the clock"
    vehicle.advance(0.2)
    expected, _ = step_velocity_lag(
        np.zeros((1, 3)), np.zeros((1, 2)), np.array([half]), np.array([0.0]), params=params,
        period_s=0.2,
    )  # fmt: skip
    assert vehicle.pose() == pytest.approx(tuple(expected[0]), abs=1e-12)
    with pytest.raises(RuntimeError, match="external_physics"):
        rig()[0].advance(0.2)


def test_the_path_of_a_lockstep_period_passes_its_physics_steps_to_where_advance_took_the_car(
    rig: Callable[..., Any],
) -> None:
    # A rotating lidar needs the path within a period (`simcar.car.drive`); the car
    # must still move exactly as one `advance` moves it.
    vehicle, station = rig(external_physics=True)
    station.command(MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    station.wait("HEARTBEAT", _armed)
    station.override(1700, 1800)  # forward and turning right
    params = vehicle.settings.dynamics
    speed, rate = 0.75 * params.max_speed_mps, -0.5 * params.max_turn_rate_radps
    assert vehicle.wait_for_targets(speed, rate, 0.01, timeout_s=3.0)
    pose, velocity = np.zeros((1, 3)), np.zeros((1, 2))
    for _ in range(3):
        times_s, path = drive(vehicle, 0.2)
        np.testing.assert_allclose(times_s, [-0.2, -0.15, -0.1, -0.05, 0.0], atol=1e-15)
        for k, time_s in enumerate(times_s):
            passed, _ = step_velocity_lag(
                pose, velocity, np.array([speed]), np.array([rate]), params=params,
                period_s=0.2 + time_s,
            )  # fmt: skip
            np.testing.assert_allclose(path[0, k], passed[0], atol=1e-12)
        pose, velocity = step_velocity_lag(
            pose, velocity, np.array([speed]), np.array([rate]), params=params, period_s=0.2
        )
        assert vehicle.pose() == tuple(pose[0]) == tuple(path[0, -1])  # to the last bit


def test_rc_override_does_nothing_while_disarmed(rig: Callable[..., Any]) -> None:
    vehicle, station = rig()
    _drive(station, 1500, 1900, 0.3)
    assert vehicle.pose() == (0.0, 0.0, 0.0)


def test_rc_override_is_ignored_unless_from_the_ground_station_id(
    rig: Callable[..., Any],
) -> None:
    vehicle, station = rig(station_id=42)
    station.command(MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    _drive(station, 1500, 1900, 0.3)
    station.mav.manual_control_send(1, 0, 0, 1000, 0, 0)
    time.sleep(0.1)
    assert vehicle.armed and vehicle.pose() == (0.0, 0.0, 0.0)
    assert vehicle.counters["ignored_override"] >= 3


def test_manual_control_z_is_throttle_and_y_is_steering(rig: Callable[..., Any]) -> None:
    vehicle, station = rig()
    station.command(MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    end = time.monotonic() + 0.3
    while time.monotonic() < end:
        station.mav.manual_control_send(1, 0, -1000, 0, 0, 0)  # full left, no throttle
        time.sleep(0.05)
    x, y, yaw = vehicle.pose()
    assert yaw > 0.05 and math.hypot(x, y) < 1e-6


def _poll(condition: Callable[[], bool], what: str, timeout_s: float = 10.0) -> None:
    """Wait until `condition` holds (a loaded machine may take a while), or fail."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.01)


def test_rc_override_expires_after_the_override_timeout(rig: Callable[..., Any]) -> None:
    vehicle, station = rig(rc_override_timeout_s=0.2)
    station.command(MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    station.override(1500, 1900)
    _poll(lambda: vehicle.velocity()[0] > 0.1, "the override to drive the car")
    _poll(lambda: abs(vehicle.velocity()[0]) < 0.01, "the override to expire and the car stop")


def test_guided_is_refused_without_a_position_and_taken_with_one(
    rig: Callable[..., Any],
) -> None:
    vehicle, station = rig()
    ack = station.command(MAV_CMD_DO_SET_MODE, 1, ROVER_MODES["GUIDED"])
    assert ack.result == MAV_RESULT_FAILED and vehicle.mode == "MANUAL"
    station.give_position(vehicle)
    ack = station.command(MAV_CMD_DO_SET_MODE, 1, ROVER_MODES["GUIDED"])
    assert ack.result == MAV_RESULT_ACCEPTED and vehicle.mode == "GUIDED"


def test_guided_falls_back_to_hold_when_the_position_is_lost(rig: Callable[..., Any]) -> None:
    vehicle, station = rig(position_timeout_s=0.2)
    station.give_position(vehicle)
    station.command(MAV_CMD_DO_SET_MODE, 1, ROVER_MODES["GUIDED"])
    station.wait("HEARTBEAT", lambda heartbeat: heartbeat.custom_mode == ROVER_MODES["HOLD"])


def _guided_target(station: Station, forward_mps: float, yaw_rate_radps: float, mask: int) -> None:
    station.mav.set_position_target_local_ned_send(
        0, 1, 1, MAV_FRAME_BODY_NED, mask, 0, 0, 0, forward_mps, 0, 0, 0, 0, 0, 0, yaw_rate_radps
    )


def test_guided_velocity_and_yaw_rate_drive_the_car_until_the_guided_timeout(
    rig: Callable[..., Any],
) -> None:
    vehicle, station = rig(guided_timeout_s=0.3, position_timeout_s=5.0)
    station.give_position(vehicle)
    station.command(MAV_CMD_DO_SET_MODE, 1, ROVER_MODES["GUIDED"])
    station.command(MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    # Negative NED yaw rate: counter-clockwise from above, a left turn.

    def driving() -> bool:
        _guided_target(station, 0.4, -0.4, TYPE_MASK_VELOCITY_YAW_RATE)  # kept fresh
        speed, rate = vehicle.velocity()
        return bool(speed > 0.3 and rate > 0.3)

    _poll(driving, "the guided target to drive and turn the car")
    # No more targets: after the guided timeout the car stops.
    _poll(lambda: max(map(abs, vehicle.velocity())) < 0.02, "the guided timeout to stop the car")


def test_guided_velocity_without_yaw_rate_steers_towards_the_vector(
    rig: Callable[..., Any],
) -> None:
    vehicle, station = rig(position_timeout_s=5.0)
    station.give_position(vehicle)
    station.command(MAV_CMD_DO_SET_MODE, 1, ROVER_MODES["GUIDED"])
    station.command(MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    # Body frame, straight to the right: the car turns clockwise.
    station.mav.set_position_target_local_ned_send(
        0, 1, 1, MAV_FRAME_BODY_NED, TYPE_MASK_VELOCITY, 0, 0, 0, 0.0, 0.3, 0, 0, 0, 0, 0, 0
    )
    time.sleep(0.3)
    assert vehicle.pose()[2] < -0.03


def test_guided_targets_are_ignored_outside_guided(rig: Callable[..., Any]) -> None:
    vehicle, station = rig()
    station.command(MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    _guided_target(station, 0.4, 0.0, TYPE_MASK_VELOCITY_YAW_RATE)
    time.sleep(0.2)
    assert vehicle.pose() == (0.0, 0.0, 0.0)


def test_reports_its_pose_as_local_position_ned_and_attitude(rig: Callable[..., Any]) -> None:
    _, station = rig(x_m=2.0, y_m=-1.0, yaw_rad=math.pi / 2)
    position = station.wait("LOCAL_POSITION_NED")
    attitude = station.wait("ATTITUDE")
    assert (position.x, position.y) == pytest.approx((-1.0, 2.0))  # north = y, east = x
    assert attitude.yaw == pytest.approx(0.0, abs=1e-6)  # facing our +y is facing north


def test_signing_vehicle_refuses_unsigned_commands_and_takes_signed_ones(
    rig: Callable[..., Any], tmp_path: Path
) -> None:
    key = bytes(range(32))
    key_file = tmp_path / "key"
    key_file.write_bytes(key)
    vehicle, unsigned = rig(signing_key_file=str(key_file))
    unsigned.mav.command_long_send(1, 1, MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    deadline = time.monotonic() + 3
    while vehicle.counters["rejected"] == 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert vehicle.counters["rejected"] >= 1 and not vehicle.armed
    signed = Station(int(vehicle.settings.connection.rsplit(":", 1)[1]), key=key)
    try:
        assert signed.command(MAV_CMD_COMPONENT_ARM_DISARM, 1.0).result == MAV_RESULT_ACCEPTED
        heartbeat = signed.wait("HEARTBEAT", _armed)
        assert heartbeat.get_signed()
    finally:
        signed.conn.close()


def test_vehicle_runs_as_a_process_and_exits_on_sigterm() -> None:
    port = free_port(socket.SOCK_DGRAM)
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "qnav",
            "fake-vehicle",
            "--connection",
            f"udpin:127.0.0.1:{port}",
            "--set",
            "heartbeat_period_s=0.05",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    station = Station(port)
    try:
        heartbeat = station.wait("HEARTBEAT", timeout_s=20)
        assert heartbeat.type == 10
        process.send_signal(signal.SIGTERM)
        output, _ = process.communicate(timeout=20)
    finally:
        station.conn.close()
        if process.poll() is None:
            process.kill()
    assert process.returncode == 0, output
