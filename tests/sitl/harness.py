"""ArduPilot Rover SITL, our real bridge process and a zenoh peer, wired as on the car.

`Sitl` runs the `ardurover` binary named by the ARDUPILOT_SITL environment variable (never
vendored; docs/bridge-testing.md, "Getting a SITL binary"), wiped (`-w`), with our parameter
files. Its SERIAL0 (TCP base port + 0, the "USB" port ArduPilot trusts unsigned) carries the
`Observer`: the test's own ground-truth reader of LOCAL_POSITION_NED, GLOBAL_POSITION_INT, ATTITUDE,
HEARTBEAT and STATUSTEXT, with system id 250 so the autopilot never takes it for its ground
station. The bridge drives SERIAL1 (TCP base port + 2), as a companion computer on a telemetry
port would. `make test-sitl` runs all of it inside a network namespace of its own (loopback
only), so nothing the autopilot serves is reachable from outside.
"""

from __future__ import annotations

import contextlib
import math
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from qnav.contracts.daemon import free_port
from qnav.contracts.mavlink import (
    MAV_MODE_FLAG_SAFETY_ARMED,
    drain,
    mode_name,
    open_connection,
    wrap_pi,
)
from qnav.contracts.transport import ZenohSettings, open_session
from qnav.contracts.wire import (
    COMMAND,
    POSE,
    VEHICLE_STATE,
    Pose2D,
    Twist2D,
    encode_pose_msg,
    encode_twist_msg,
    key,
)
from qnav.sitl import HOME, SITL_ENV, SitlProcess
from tests.firmware_bridge.rig import StateLog, keep_commanding, wait_until

ROOT = Path(__file__).resolve().parents[2]
OBSERVER_SYSTEM_ID = 250
MESSAGE_INTERVAL_US = 50_000
"""The observer asks for its messages at 20 Hz."""
MAV_CMD_SET_MESSAGE_INTERVAL = 511
OBSERVED = {
    "LOCAL_POSITION_NED": 32,
    "GLOBAL_POSITION_INT": 33,
    "ATTITUDE": 30,
    "SIMSTATE": 164,
    "SIM_STATE": 108,
    "EKF_STATUS_REPORT": 193,
}
"""SIMSTATE is SITL's true pose: the test's motion capture. SIM_STATE adds SITL's true velocity
(the car's own rest, beside the EKF's estimate of it). EKF_STATUS_REPORT: whether the EKF has an
absolute position (without one Rover's failsafe and GUIDED cannot brake)."""
EKF_POS_HORIZ_ABS = 16
"""EKF_STATUS_REPORT.flags: the EKF has a horizontal position relative to its origin."""
EKF_CONST_POS_MODE = 128
"""EKF_STATUS_REPORT.flags: the EKF holds a constant position (no aiding)."""
REST_SPEED_MPS = 0.05
"""Below this the vehicle is at rest."""


def sitl_binary() -> Path | None:
    """The ardurover binary from ARDUPILOT_SITL, or None when it is not set."""
    value = os.environ.get(SITL_ENV, "")
    return Path(value) if value else None


@dataclass
class Sample:
    """One telemetry message as the observer received it."""

    time_s: float
    """Host monotonic time of arrival."""
    type: str
    fields: dict[str, Any]


class Sitl(SitlProcess):
    """`qnav.sitl.SitlProcess` with what a test reports when the autopilot dies."""

    def start(self, timeout_s: float = 20.0) -> None:
        try:
            super().start(timeout_s)
        except RuntimeError as error:
            raise AssertionError(f"{error}: {self.log_tail()}") from None

    def process_died(self) -> bool:
        return self.process is not None and self.process.poll() is not None

    def log_tail(self, lines: int = 30) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return ""


class Observer:
    """The test's view of the autopilot over SERIAL0: telemetry, armed flag, mode, texts."""

    def __init__(self, connection: str) -> None:
        self.connection = connection
        self.samples: list[Sample] = []
        self.texts: list[str] = []
        self.armed: bool | None = None
        self.mode: str | None = None
        self.changes: list[tuple[float, bool, str]] = []
        """(time, armed, mode) at each change the heartbeats showed."""
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._send_lock = threading.Lock()
        self._next_request_s = 0.0
        self.conn: Any = wait_until(self._connect, 20.0, f"a connection to {connection}")
        self._thread = threading.Thread(target=self._loop, name="observer", daemon=True)
        self._thread.start()

    def _connect(self) -> Any:
        try:
            return open_connection(
                self.connection, baud_rate=115200, system_id=OBSERVER_SYSTEM_ID, component_id=1
            )
        except OSError:
            return None

    def _request_streams(self) -> None:
        with self._send_lock:
            for message_id in OBSERVED.values():
                self.conn.mav.command_long_send(
                    1, 1, MAV_CMD_SET_MESSAGE_INTERVAL, 0, message_id, MESSAGE_INTERVAL_US,
                    0, 0, 0, 0, 0,
                )  # fmt: skip

    def _loop(self) -> None:
        while not self._stopping.is_set():
            now = time.monotonic()
            if now >= self._next_request_s:  # again now and then: SITL may not hear the first
                self._request_streams()
                self._next_request_s = now + 2.0
            try:
                messages = drain(self.conn, 0.05)
            except (OSError, ConnectionError):
                time.sleep(0.05)
                continue
            now = time.monotonic()
            for message in messages:
                kind = message.get_type()
                if message.get_srcSystem() != 1 or message.get_srcComponent() != 1:
                    continue
                if kind in OBSERVED:
                    with self._lock:
                        self.samples.append(Sample(now, kind, message.to_dict()))
                elif kind == "HEARTBEAT":
                    armed = bool(message.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)
                    mode = mode_name(message.custom_mode)
                    if (armed, mode) != (self.armed, self.mode):
                        with self._lock:
                            self.changes.append((now, armed, mode))
                    self.armed, self.mode = armed, mode
                elif kind == "STATUSTEXT":
                    with self._lock:
                        self.texts.append(str(message.text))

    def close(self) -> None:
        self._stopping.set()
        self._thread.join(timeout=2)
        self.conn.close()

    def send(self, build: Callable[[Any], None]) -> None:
        """Send something over SERIAL0 (`build(conn.mav)` does the sending)."""
        with self._send_lock:
            build(self.conn.mav)

    def latest(self, kind: str) -> Sample | None:
        with self._lock:
            for sample in reversed(self.samples):
                if sample.type == kind:
                    return sample
        return None

    def since(self, kind: str, time_s: float) -> list[Sample]:
        with self._lock:
            return [s for s in self.samples if s.type == kind and s.time_s >= time_s]

    def position(self) -> tuple[float, float]:
        """(north m, east m) from the newest LOCAL_POSITION_NED."""
        sample = self.latest("LOCAL_POSITION_NED")
        assert sample is not None, "no LOCAL_POSITION_NED yet"
        return float(sample.fields["x"]), float(sample.fields["y"])

    def speed(self) -> float:
        """Ground speed (m/s) from the newest LOCAL_POSITION_NED."""
        sample = self.latest("LOCAL_POSITION_NED")
        if sample is None:
            return math.nan
        return math.hypot(sample.fields["vx"], sample.fields["vy"])

    def yaw_ned(self) -> float:
        sample = self.latest("ATTITUDE")
        assert sample is not None, "no ATTITUDE yet"
        return float(sample.fields["yaw"])


@dataclass
class StopMeasure:
    """How the vehicle came to rest after an event (a silence, a signal)."""

    speed_before_mps: float
    stop_time_s: float
    """From the event to the first LOCAL_POSITION_NED below REST_SPEED_MPS that stays there."""
    stop_distance_m: float
    """Distance travelled from the event to that moment (LOCAL_POSITION_NED)."""
    gps_distance_m: float
    """The same from GLOBAL_POSITION_INT."""
    rested: bool = field(default=True)
    true_stop_time_s: float = math.nan
    """From the event to the first of SITL's true velocities (SIM_STATE) below REST_SPEED_MPS
    that stays there: the car at rest, whatever the EKF estimates (NaN without SIM_STATE)."""
    ekf_error_mps: float = math.nan
    """How far the EKF's velocity (LOCAL_POSITION_NED) was from SITL's true one when the car came
    to rest: an EKF with this error reports rest only once it has shrunk below REST_SPEED_MPS."""


def measure_stop(observer: Observer, event_s: float, timeout_s: float) -> StopMeasure:
    """Wait until the vehicle has stayed below REST_SPEED_MPS for 0.5 s (or `timeout_s`), by
    its own estimate (LOCAL_POSITION_NED) and, where SITL reports it, by its true velocity."""
    deadline = event_s + timeout_s
    while time.monotonic() < deadline:
        if _rested_for(observer.since("LOCAL_POSITION_NED", event_s), ("vx", "vy"), 0.5):
            truth = observer.since("SIM_STATE", event_s)
            if not truth or _rested_for(truth, ("vn", "ve"), 0.5):
                break
        time.sleep(0.05)
    samples = observer.since("LOCAL_POSITION_NED", event_s - 0.3)
    before = [s for s in samples if s.time_s <= event_s]
    after = [s for s in samples if s.time_s > event_s]
    assert before and after, "no LOCAL_POSITION_NED around the event"
    start = before[-1]
    rest = _rest_index(after)
    end = after[rest] if rest is not None else after[-1]
    distance = math.hypot(end.fields["x"] - start.fields["x"], end.fields["y"] - start.fields["y"])
    gps = observer.since("GLOBAL_POSITION_INT", event_s - 0.3)
    gps_distance = math.nan
    gps_before = [s for s in gps if s.time_s <= event_s]
    gps_after = [s for s in gps if s.time_s > event_s and s.time_s <= end.time_s + 0.06]
    if gps_before and gps_after:
        gps_distance = _ground_distance_m(gps_before[-1].fields, gps_after[-1].fields)
    truth = [s for s in observer.since("SIM_STATE", event_s) if s.time_s <= after[-1].time_s]
    true_rest = _rest_index(truth, ("vn", "ve"))
    true_stop_s = ekf_error = math.nan
    if true_rest is not None:
        true_stop_s = truth[true_rest].time_s - event_s
        ekf_error = _ekf_error_mps(after, truth[true_rest])
    return StopMeasure(
        speed_before_mps=math.hypot(start.fields["vx"], start.fields["vy"]),
        stop_time_s=end.time_s - event_s,
        stop_distance_m=distance,
        gps_distance_m=gps_distance,
        rested=rest is not None,
        true_stop_time_s=true_stop_s,
        ekf_error_mps=ekf_error,
    )


def _rest_index(samples: list[Sample], velocity: tuple[str, str] = ("vx", "vy")) -> int | None:
    """Index of the first sample from which every later one is at rest (`velocity`: the north
    and east fields)."""
    index = None
    for i, sample in enumerate(samples):
        if math.hypot(sample.fields[velocity[0]], sample.fields[velocity[1]]) < REST_SPEED_MPS:
            if index is None:
                index = i
        else:
            index = None
    return index


def _rested_for(samples: list[Sample], velocity: tuple[str, str], duration_s: float) -> bool:
    """True when the samples end with at least `duration_s` at rest."""
    rest = _rest_index(samples, velocity)
    return rest is not None and samples[-1].time_s - samples[rest].time_s >= duration_s


def _ekf_error_mps(estimates: list[Sample], truth: Sample) -> float:
    """|EKF velocity - true velocity| at `truth`'s moment (the estimate nearest in time)."""
    nearest = min(estimates, key=lambda s: abs(s.time_s - truth.time_s))
    return math.hypot(
        nearest.fields["vx"] - truth.fields["vn"], nearest.fields["vy"] - truth.fields["ve"]
    )


def _ground_distance_m(a: dict[str, Any], b: dict[str, Any]) -> float:
    """Flat-earth distance between two GLOBAL_POSITION_INT fixes (metres apart)."""
    lat = math.radians(a["lat"] * 1e-7)
    north = (b["lat"] - a["lat"]) * 1e-7 * 111_319.5
    east = (b["lon"] - a["lon"]) * 1e-7 * 111_319.5 * math.cos(lat)
    return math.hypot(north, east)


def true_pose(simstate: dict[str, Any], home: tuple[float, float]) -> tuple[float, float, float]:
    """SITL's true pose as motion capture gives it: (x east m, y north m, yaw rad
    counter-clockwise from x) around `home` (lat, lon degrees)."""
    north = (simstate["lat"] * 1e-7 - home[0]) * 111_319.5
    east = (simstate["lng"] * 1e-7 - home[1]) * 111_319.5 * math.cos(math.radians(home[0]))
    return east, north, wrap_pi(math.pi / 2 - simstate["yaw"])


class MotionCapture:
    """Publishes SITL's true pose on zenoh's `pose` key at `rate_hz`, as a mocap system."""

    def __init__(self, zenoh: Zenoh, observer: Observer, rate_hz: float = 30.0) -> None:
        self._zenoh, self._observer, self._period_s = zenoh, observer, 1.0 / rate_hz
        self._stopping = threading.Event()
        self.published = 0
        home = HOME.split(",")
        self._home = (float(home[0]), float(home[1]))
        self._publisher = zenoh.session.declare_publisher(key(POSE))
        self._thread = threading.Thread(target=self._loop, name="mocap", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._stopping.wait(self._period_s):
            sample = self._observer.latest("SIMSTATE")
            if sample is None:
                continue
            x, y, yaw = true_pose(sample.fields, self._home)
            self._publisher.put(encode_pose_msg(Pose2D(time.time(), "map", x, y, yaw)))
            self.published += 1

    def close(self) -> None:
        self._stopping.set()
        self._thread.join(timeout=2)
        self._publisher.undeclare()


class Zenoh:
    """The test's zenoh peer: the bridge connects to it; commands out, vehicle states in."""

    def __init__(self) -> None:
        self.port = free_port(socket.SOCK_STREAM)
        self.session: Any = open_session(
            ZenohSettings(listen=(f"tcp/127.0.0.1:{self.port}",), connect=())
        )
        self.heard = StateLog()
        self._subscriber = self.session.declare_subscriber(key(VEHICLE_STATE), self.heard.on_sample)
        self._publisher = self.session.declare_publisher(key(COMMAND))

    def state(self) -> dict[str, Any]:
        return self.heard.newest()

    def command(self, linear_mps: float, angular_radps: float) -> None:
        self._publisher.put(encode_twist_msg(Twist2D(linear_mps, angular_radps)))

    def drive(self, linear_mps: float, angular_radps: float, seconds: float) -> float:
        """A command every 0.1 s (the controller's rate is 5-10 Hz); the last one's time."""
        return keep_commanding(self.command, linear_mps, angular_radps, seconds, period_s=0.1)

    def close(self) -> None:
        self._subscriber.undeclare()
        self.session.close()


class BridgeProcess:
    """`qnav bridge` as its own process, as a user runs it."""

    def __init__(self, config: Path, log_path: Path, assignments: list[str]) -> None:
        self.log_path = log_path
        args = [sys.executable, "-m", "qnav", "bridge", "--config", str(config)]
        for assignment in assignments:
            args += ["--set", assignment]
        with log_path.open("wb") as out:
            self.process = subprocess.Popen(args, stdout=out, stderr=subprocess.STDOUT)

    def signal(self, number: int) -> float:
        """Send a signal; its time."""
        sent = time.monotonic()
        self.process.send_signal(number)
        return sent

    def wait(self, timeout_s: float = 10.0) -> int:
        return self.process.wait(timeout=timeout_s)

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait()


class LinkCutter:
    """A TCP relay between the bridge and the autopilot that can go silent, as a radio link
    out of range: after `cut()` no byte passes either way and both sockets stay open (no FIN,
    no reset), so neither end learns of it except by silence. A bridge that reconnects while
    cut is accepted and hears nothing."""

    def __init__(self, upstream_port: int) -> None:
        self.upstream_port = upstream_port
        self._server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._server.bind(("127.0.0.1", 0))
        self._server.listen(4)
        self.port = int(self._server.getsockname()[1])
        self._cut = threading.Event()
        self._stopping = threading.Event()
        self._sockets: list[socket.socket] = []
        threading.Thread(target=self._accept, name="link-accept", daemon=True).start()

    @property
    def connection(self) -> str:
        """The bridge's mavlink.connection."""
        return f"tcp:127.0.0.1:{self.port}"

    def cut(self) -> float:
        """Stop passing bytes, both ways; its time."""
        self._cut.set()
        return time.monotonic()

    def _accept(self) -> None:
        while not self._stopping.is_set():
            try:
                client, _ = self._server.accept()
            except OSError:
                return
            self._sockets.append(client)
            if self._cut.is_set():
                threading.Thread(target=self._pump, args=(client, None), daemon=True).start()
                continue
            upstream = socket.create_connection(("127.0.0.1", self.upstream_port))
            self._sockets.append(upstream)
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    def _pump(self, source: socket.socket, sink: socket.socket | None) -> None:
        while not self._stopping.is_set():
            try:
                data = source.recv(65536)
            except OSError:
                return
            if not data:
                return
            if sink is not None and not self._cut.is_set():
                try:
                    sink.sendall(data)
                except OSError:
                    return

    def close(self) -> None:
        self._stopping.set()
        self._server.close()
        for sock in self._sockets:
            with contextlib.suppress(OSError):
                sock.close()
