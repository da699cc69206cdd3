"""A trace of guided output's stops in SITL: what the bridge sends, what the autopilot does.

Not collected with the other SITL tests (the file name does not start with `test_`): run it by
name, `-s` to see the trace (docs/bridge-testing.md, "Measured stops"):

    ARDUPILOT_SITL=... make test-sitl SITL_TESTS=tests/sitl/trace_stops.py SITL_ARGS=-s

The bridge reaches the autopilot through a relay that parses and timestamps every MAVLink
message passing (`RecordingRelay`); the observer adds the throttle output (SERVO_OUTPUT_RAW),
the speed controller's target (PID_TUNING, `GCS_PID_MASK 2`) and SITL's true velocity and yaw
(SIM_STATE) to the vehicle's own estimate (LOCAL_POSITION_NED, ATTITUDE). Three silences, then
a SIGTERM, each after the drive of `test_drive_and_every_stop`.
"""

from __future__ import annotations

import math
import signal
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from qnav.contracts.mavlink import mavutil, wrap_pi
from tests.firmware_bridge.rig import wait_until
from tests.sitl.harness import (
    OBSERVED,
    BridgeProcess,
    Observer,
    Sitl,
    Zenoh,
    measure_stop,
)
from tests.sitl.test_rover_sitl import OUTPUTS, _armed, _drive_and_check_motion

pytestmark = pytest.mark.sitl

TRACED = {"SERVO_OUTPUT_RAW": 36, "PID_TUNING": 194}
PID_TUNING_SPEED = 4
"""Rover reports its speed-to-throttle controller as PID_TUNING axis 4 (ACCZ)."""
STOP_FIELDS = ("coordinate_frame", "type_mask", "vx", "vy", "vz", "yaw", "yaw_rate")


class RecordingRelay:
    """A TCP relay between the bridge and the autopilot keeping (arrival time, message) of all
    the bridge sends."""

    def __init__(self, upstream_port: int) -> None:
        self.upstream_port = upstream_port
        self.sent: list[tuple[float, Any]] = []
        self._server = socket.create_server(("127.0.0.1", 0))
        self.port = int(self._server.getsockname()[1])
        self._sockets: list[socket.socket] = [self._server]
        threading.Thread(target=self._accept, name="relay", daemon=True).start()

    @property
    def connection(self) -> str:
        return f"tcp:127.0.0.1:{self.port}"

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self._server.accept()
            except OSError:
                return
            upstream = socket.create_connection(("127.0.0.1", self.upstream_port))
            self._sockets += [client, upstream]
            threading.Thread(target=self._pump, args=(client, upstream, True), daemon=True).start()
            threading.Thread(target=self._pump, args=(upstream, client, False), daemon=True).start()

    def _pump(self, source: socket.socket, sink: socket.socket, record: bool) -> None:
        parser = mavutil().mavlink.MAVLink(None)
        parser.robust_parsing = True
        while True:
            try:
                data = source.recv(65536)
                if not data:
                    return
                sink.sendall(data)
            except OSError:
                return
            if record:
                now = time.monotonic()
                self.sent += [(now, m) for m in parser.parse_buffer(data) or []]

    def stops(self, since_s: float, until_s: float) -> list[tuple[float, tuple[Any, ...]]]:
        """(time, fields) of the zero velocity targets sent in [since_s, until_s]."""
        return [
            (t, tuple(m.to_dict()[name] for name in STOP_FIELDS))
            for t, m in self.sent
            if since_s <= t <= until_s
            and m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"
            and m.vx == 0.0
        ]

    def close(self) -> None:
        for sock in self._sockets:
            sock.close()


def _print_trace(observer: Observer, relay: RecordingRelay, event_s: float, end_s: float) -> None:
    """The vehicle's mode changes and the bridge's messages (each change), then every 0.1 s:
    the EKF's and the true speed."""
    for t, armed, mode in list(observer.changes):
        if event_s - 0.7 <= t <= end_s:
            print(f"  {t - event_s:+.2f} s  vehicle {'armed' if armed else 'disarmed'} in {mode}")
    previous = None
    for t, m in relay.sent:
        kind = m.get_type()
        if not event_s - 0.7 <= t <= end_s or kind in ("HEARTBEAT", "VISION_POSITION_ESTIMATE"):
            continue
        fields = {k: v for k, v in m.to_dict().items() if k in (*STOP_FIELDS, "command")}
        if (kind, fields) != previous:
            print(f"  {t - event_s:+.2f} s  bridge sends {kind} {fields}")
        previous = (kind, fields)
    latest: dict[str, dict[str, Any]] = {}
    next_line_s = event_s - 0.2
    for sample in list(observer.samples):
        if sample.type != "PID_TUNING" or sample.fields["axis"] == PID_TUNING_SPEED:
            latest[sample.type] = sample.fields
        if sample.type != "LOCAL_POSITION_NED" or not next_line_s <= sample.time_s <= end_s:
            continue
        next_line_s = sample.time_s + 0.09
        if not {"ATTITUDE", "SIM_STATE", "SERVO_OUTPUT_RAW", "PID_TUNING"} <= latest.keys():
            continue
        ekf, yaw, true = sample.fields, latest["ATTITUDE"]["yaw"], latest["SIM_STATE"]
        forward = ekf["vx"] * math.cos(yaw) + ekf["vy"] * math.sin(yaw)
        lateral = -ekf["vx"] * math.sin(yaw) + ekf["vy"] * math.cos(yaw)
        true_forward = true["vn"] * math.cos(true["yaw"]) + true["ve"] * math.sin(true["yaw"])
        true_lateral = -true["vn"] * math.sin(true["yaw"]) + true["ve"] * math.cos(true["yaw"])
        print(
            f"  {sample.time_s - event_s:+.2f} s  EKF speed {math.hypot(ekf['vx'], ekf['vy']):.3f}"
            f" (forward {forward:+.3f}, sideways {lateral:+.3f})  true speed "
            f"{math.hypot(true['vn'], true['ve']):.3f} (forward {true_forward:+.3f}, sideways "
            f"{true_lateral:+.3f})  EKF yaw error "
            f"{math.degrees(wrap_pi(yaw - true['yaw'])):+.2f} deg, velocity error "
            f"{math.hypot(ekf['vx'] - true['vn'], ekf['vy'] - true['ve']):.3f}  throttle "
            f"{latest['SERVO_OUTPUT_RAW']['servo3_raw']} us, speed target "
            f"{latest['PID_TUNING']['desired']:+.2f}"
        )


def test_trace_guided_stops(
    monkeypatch: pytest.MonkeyPatch,  # first: undone only after the observer has stopped
    start_sitl: Callable[..., tuple[Sitl, Observer]],
    start_bridge: Callable[..., BridgeProcess],
    zenoh: Zenoh,
    tmp_path: Path,
) -> None:
    for name, message_id in TRACED.items():
        monkeypatch.setitem(OBSERVED, name, message_id)
    pid = tmp_path / "pid.parm"
    pid.write_text("GCS_PID_MASK 2\n")
    sitl, observer = start_sitl([pid])
    relay = RecordingRelay(sitl.base_port + 2)
    try:
        bridge = start_bridge(relay.connection, *OUTPUTS["guided"])
        _armed(zenoh, observer)
        wait_until(lambda: any("is using GPS" in t for t in observer.texts), 150, "GPS")
        wait_until(lambda: observer.mode == "GUIDED", 150, "GUIDED")
        stops: list[tuple[Any, ...]] = []
        for number in range(3):
            last = _drive_and_check_motion(zenoh, observer)
            measure = measure_stop(observer, last, timeout_s=30.0)
            end = last + measure.stop_time_s + 0.3
            print(f"\n[trace] silence {number + 1}, from the last command: {measure}")
            _print_trace(observer, relay, last, end)
            stops += [fields for _, fields in relay.stops(last + 0.05, end)]
        _drive_and_check_motion(zenoh, observer)
        sent = bridge.signal(signal.SIGTERM)
        measure = measure_stop(observer, sent, timeout_s=30.0)
        end = sent + measure.stop_time_s + 0.3
        print(f"\n[trace] SIGTERM: {measure}")
        _print_trace(observer, relay, sent, end)
        on_exit = [fields for _, fields in relay.stops(sent, end)]
        assert bridge.wait(timeout_s=15.0) == 0
        # The stop after silence and on exit: one and the same message.
        assert on_exit and stops and set(stops) == set(on_exit)
    finally:
        relay.close()
