"""`qnav bench bridge`: how long a command takes through the bridge, and how soon it stops.

The bridge runs as a user runs it (`qnav bridge --config FILE`, its own process). This process
plays both neighbours on one thread: it publishes Twist commands on zenoh, and it is the
vehicle, a UDP socket on loopback that sends heartbeats and timestamps each MAVLink datagram
the moment `recvfrom` returns. So the latency is publish -> zenoh -> bridge (decode, map,
encode, sign if asked) -> UDP -> vehicle socket, in wall-clock time of one process.

The failsafe figure is the time from publishing the last command to the first stop message
arriving, to be compared with `failsafe.command_timeout_s` + 50 ms.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from qnav.contracts.daemon import free_port, stop_on_signals, stop_process
from qnav.contracts.errors import ConfigError
from qnav.contracts.mavlink import (
    MAV_AUTOPILOT_ARDUPILOTMEGA,
    MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
    MAV_MODE_FLAG_SAFETY_ARMED,
    MAV_STATE_ACTIVE,
    MAV_TYPE_GROUND_ROVER,
    ROVER_MODES,
    mavutil,
)
from qnav.contracts.settings import to_toml
from qnav.contracts.transport import ZenohSettings, open_session
from qnav.contracts.wire import COMMAND, STOP, VEHICLE_STATE, Twist2D, encode_twist_msg, key
from qnav.firmware_bridge import mapping
from qnav.firmware_bridge.settings import (
    BridgeSettings,
    FailsafeSettings,
    MavlinkSettings,
    OutputSettings,
    VehicleSettings,
)

VEHICLE_HEARTBEAT_S = 0.5
ECHO_KEY = "qnav/bench_echo"
COMMAND_GAP_S = 0.004
"""Pause between timed commands (the controller sends one per 0.2 s; this keeps the run short)."""


class _FakeAutopilot:
    """The vehicle end of the bench: one UDP socket, heartbeats out, datagrams timestamped."""

    def __init__(self, port: int, mode: int) -> None:
        self.socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.socket.bind(("127.0.0.1", port))
        self.parser: Any = mavutil().mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.parser.robust_parsing = True
        self.mode = mode
        self.peer: tuple[str, int] | None = None
        self._next_heartbeat_s = 0.0

    def heartbeat_if_due(self) -> None:
        now = time.monotonic()
        if self.peer is None or now < self._next_heartbeat_s:
            return
        self._next_heartbeat_s = now + VEHICLE_HEARTBEAT_S
        armed = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | MAV_MODE_FLAG_SAFETY_ARMED
        message = self.parser.heartbeat_encode(
            MAV_TYPE_GROUND_ROVER, MAV_AUTOPILOT_ARDUPILOTMEGA, armed, self.mode, MAV_STATE_ACTIVE
        )
        self.socket.sendto(message.pack(self.parser), self.peer)

    def receive(self, deadline_s: float) -> tuple[int, list[Any]]:
        """(arrival time in ns, messages of one datagram), or (0, []) at the deadline."""
        remaining = deadline_s - time.monotonic()
        if remaining <= 0:
            return 0, []
        self.socket.settimeout(min(remaining, VEHICLE_HEARTBEAT_S / 2))
        try:
            data, self.peer = self.socket.recvfrom(2048)
        except TimeoutError:
            return 0, []
        arrived_ns = time.perf_counter_ns()
        return arrived_ns, self.parser.parse_buffer(data) or []

    def wait_for(self, match: Callable[[Any], bool], timeout_s: float) -> int:
        """Arrival time (ns) of the first message that matches, heartbeating meanwhile."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.heartbeat_if_due()
            arrived_ns, messages = self.receive(deadline)
            if any(match(message) for message in messages):
                return arrived_ns
        raise TimeoutError("the bridge sent nothing that matched in time")


def _matcher(settings: BridgeSettings, twist: Twist2D) -> Callable[[Any], bool]:
    """Recognises the message the bridge sends for `twist`."""
    output = settings.output
    if output.mode == "guided":
        target = mapping.velocity_target(twist, output)

        def guided(message: Any) -> bool:
            return bool(
                message.get_type() == "SET_POSITION_TARGET_LOCAL_NED"
                and abs(message.vx - target.forward_mps) < 1e-4
                and abs(message.yaw_rate - target.yaw_rate_radps) < 1e-4
            )

        return guided
    pwm = mapping.rc_override(twist, output)

    def manual(message: Any) -> bool:
        return bool(
            message.get_type() == "RC_CHANNELS_OVERRIDE"
            and message.chan1_raw == pwm.steering_pwm_us
            and message.chan3_raw == pwm.throttle_pwm_us
        )

    return manual


def _commands(count: int) -> list[Twist2D]:
    """Distinct commands in turn (never STOP), so each message is matched to its command."""
    return [Twist2D(0.1 + 0.05 * (i % 9), 0.1 * ((i % 5) - 2) + 0.05) for i in range(count)]


@dataclass(frozen=True)
class BridgeBench:
    """What `measure` timed: commands through the bridge, its failsafe stops, and the floor."""

    output: str
    """The bridge's output mode (manual or guided)."""
    timeout_s: float
    """failsafe.command_timeout_s of the bridge measured."""
    latencies_ms: tuple[float, ...]
    """Each command's time from zenoh publish to its MAVLink message at the vehicle."""
    stops_ms: tuple[float, ...]
    """Each failsafe stop's time from the last command to the stop at the vehicle."""
    floor_ms: tuple[float, ...] = ()
    """Round trips through a bare zenoh-to-UDP echo process (empty: not measured)."""

    def report(self) -> dict[str, float]:
        """The figures as one JSON-friendly object."""
        report = {
            "p50_ms": round(float(np.percentile(self.latencies_ms, 50)), 4),
            "p99_ms": round(float(np.percentile(self.latencies_ms, 99)), 4),
            "failsafe_stop_ms": round(max(self.stops_ms), 2),
        }
        if self.floor_ms:
            report["baseline_p50_ms"] = round(float(np.percentile(self.floor_ms, 50)), 4)
            report["baseline_p99_ms"] = round(float(np.percentile(self.floor_ms, 99)), 4)
        return report

    def text(self) -> str:
        """The figures as lines for a person, beside their goals."""
        report = self.report()
        timeout_ms = self.timeout_s * 1000
        lines = [
            f"bridge ({self.output} output), {len(self.latencies_ms)} commands, "
            "zenoh -> MAVLink on UDP:",
            f"  latency p50 {report['p50_ms']:.3f} ms, p99 {report['p99_ms']:.3f} ms, "
            f"max {max(self.latencies_ms):.3f} ms (goal: p99 <= 2 ms)",
            f"  failsafe: first stop {', '.join(f'{s:.1f}' for s in self.stops_ms)} ms after the "
            f"last command (timeout {timeout_ms:.0f} ms; goal <= {timeout_ms + 50:.0f} ms)",
        ]
        if self.floor_ms:
            lines.append(
                f"  floor on this machine now (a bare zenoh subscriber echoing to UDP): "
                f"p50 {report['baseline_p50_ms']:.3f} ms, p99 {report['baseline_p99_ms']:.3f} ms"
            )
        return "\n".join(lines)


def measure(
    *,
    commands: int = 1000,
    stops: int = 5,
    output: Literal["manual", "guided"] = "manual",
    timeout_s: float = 0.5,
    baseline: bool = False,
) -> BridgeBench:
    """Time `commands` commands through a `qnav bridge` process and `stops` failsafe stops
    (its output mode and failsafe.command_timeout_s as given); with `baseline`, also a bare
    zenoh-to-UDP echo process."""
    if commands < 1 or stops < 1:
        raise ConfigError("--commands and --stops must each be at least 1")
    zenoh_port, mavlink_port = free_port(socket.SOCK_STREAM), free_port(socket.SOCK_DGRAM)
    settings = BridgeSettings(
        zenoh=ZenohSettings(connect=(f"tcp/127.0.0.1:{zenoh_port}",)),
        mavlink=MavlinkSettings(connection=f"udpout:127.0.0.1:{mavlink_port}"),
        output=OutputSettings(mode=output),
        failsafe=FailsafeSettings(command_timeout_s=timeout_s, disarm_on_exit=False),
        vehicle=VehicleSettings(set_mode_on_connect=False),
    )
    mode = ROVER_MODES["GUIDED" if output == "guided" else "MANUAL"]
    vehicle = _FakeAutopilot(mavlink_port, mode)
    with (
        tempfile.TemporaryDirectory() as folder,
        open_session(ZenohSettings(listen=(f"tcp/127.0.0.1:{zenoh_port}",), connect=())) as zenoh,
    ):
        config = Path(folder) / "bridge.toml"
        config.write_text(to_toml(settings))
        publisher = zenoh.declare_publisher(key(COMMAND))
        joined = threading.Event()
        states = zenoh.declare_subscriber(key(VEHICLE_STATE), lambda sample: joined.set())
        bridge = _spawn("qnav", "bridge", "--config", str(config), "--log-level", "warning")
        try:
            latencies_ms, stops_ms = _measure(
                settings,
                vehicle,
                publisher,
                joined,
                commands=commands,
                stops=stops,
                timeout_s=timeout_s,
            )
        finally:
            stop_process(bridge)
            states.undeclare()
        floor_ms: list[float] = []
        if baseline:
            echo = _spawn("qnav.firmware_bridge.bench", "echo", str(zenoh_port), str(mavlink_port))
            try:
                floor_ms = _measure_echo(commands, vehicle, zenoh.declare_publisher(ECHO_KEY))
            finally:
                stop_process(echo)
        vehicle.socket.close()
    return BridgeBench(output, timeout_s, tuple(latencies_ms), tuple(stops_ms), tuple(floor_ms))


def _measure(
    settings: BridgeSettings,
    vehicle: _FakeAutopilot,
    publisher: Any,
    joined: threading.Event,
    *,
    commands: int,
    stops: int,
    timeout_s: float,
) -> tuple[list[float], list[float]]:
    stop = _matcher(settings, STOP)
    # The vehicle side runs before zenoh is joined (stops flow without it): wait for both.
    vehicle.wait_for(lambda message: message.get_type() == "HEARTBEAT", 30.0)
    vehicle.wait_for(stop, 10.0)
    deadline = time.monotonic() + 30.0
    while not joined.is_set():  # its first vehicle state: the bridge's session is up
        if time.monotonic() > deadline:
            raise TimeoutError("the bridge did not join zenoh in time")
        vehicle.heartbeat_if_due()
        vehicle.receive(time.monotonic() + 0.05)
    time.sleep(0.2)  # let zenoh finish declaring the bridge's subscriber to us
    latencies_ms: list[float] = []
    warmup = 20
    for i, twist in enumerate(_commands(commands + warmup)):
        vehicle.heartbeat_if_due()
        payload = encode_twist_msg(twist)
        sent_ns = time.perf_counter_ns()
        publisher.put(payload)
        arrived_ns = vehicle.wait_for(_matcher(settings, twist), 2.0)
        if i >= warmup:
            latencies_ms.append((arrived_ns - sent_ns) / 1e6)
        time.sleep(COMMAND_GAP_S)
    stops_ms: list[float] = []
    for twist in _commands(stops):
        sent_ns = time.perf_counter_ns()
        publisher.put(encode_twist_msg(twist))
        vehicle.wait_for(_matcher(settings, twist), 2.0)
        arrived_ns = vehicle.wait_for(stop, timeout_s + 2.0)
        stops_ms.append((arrived_ns - sent_ns) / 1e6)
    return latencies_ms, stops_ms


def _measure_echo(count: int, vehicle: _FakeAutopilot, publisher: Any) -> list[float]:
    """Round trips through a process that only echoes each zenoh sample to the UDP socket."""
    deadline = time.monotonic() + 30.0
    vehicle.socket.settimeout(0.2)
    while True:  # the echo process answers once its subscriber is declared
        if time.monotonic() > deadline:
            raise TimeoutError("the echo process did not answer")
        publisher.put(b"hello")
        try:
            if vehicle.socket.recvfrom(2048)[0] == b"hello":
                break
        except TimeoutError:
            continue
    time.sleep(0.2)
    latencies_ms = []
    for i in range(count):
        payload = i.to_bytes(4, "little") * 13  # the size of a Twist in CDR
        sent_ns = time.perf_counter_ns()
        publisher.put(payload)
        vehicle.socket.settimeout(2.0)
        while vehicle.socket.recvfrom(2048)[0] != payload:
            pass
        latencies_ms.append((time.perf_counter_ns() - sent_ns) / 1e6)
        time.sleep(COMMAND_GAP_S)
    return latencies_ms


def _spawn(module: str, *args: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", module, *args], env={**os.environ, "PYTHONUNBUFFERED": "1"}
    )


def _echo(zenoh_port: int, udp_port: int) -> None:
    """The baseline's other end: each sample on ECHO_KEY goes back as one UDP datagram."""
    out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    destination = ("127.0.0.1", udp_port)
    with (
        stop_on_signals() as stop,
        open_session(ZenohSettings(connect=(f"tcp/127.0.0.1:{zenoh_port}",))) as session,
    ):
        session.declare_subscriber(
            ECHO_KEY, lambda sample: out.sendto(sample.payload.to_bytes(), destination)
        )
        stop.wait()


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "echo":
        _echo(int(sys.argv[2]), int(sys.argv[3]))
