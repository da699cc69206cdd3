"""The daemon as a user runs it: `qnav controller --config FILE` in its own process, sensors from
another process, this process listening to its commands and status, all on a loopback port with
scouting off."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from qnav.contracts import wire
from qnav.contracts.health import HEALTH_FILE_ENV
from qnav.contracts.policy_file import PolicyContract
from qnav.contracts.settings import to_toml
from qnav.contracts.transport import ZenohSettings, open_session
from qnav.controller.config import ControllerSettings, DaemonConfig, SafetySettings
from qnav.controller.lookahead import LookaheadSettings
from qnav.controller.onnx_file import read_onnx
from qnav.controller.proximity import ProximitySettings
from tests.conftest import PolicyFactory

ROOT = Path(__file__).resolve().parents[2]
QNAV = str(Path(sys.executable).parent / "qnav")
LOOKAHEAD_OFF = LookaheadSettings(mode="off")
"""The policy alone, as these tests ran it before the shield became the default."""
OBSTACLES_POLICY = ROOT / "tests" / "data" / "stack" / "obstacles-inertia.onnx"


class Listener:
    """Commands and statuses from the daemon, in arrival order."""

    def __init__(self, endpoint: str, namespace: str = "") -> None:
        self.lock = threading.Lock()
        self.commands: list[wire.Twist2D] = []
        self.statuses: list[dict[str, Any]] = []
        self.session = open_session(ZenohSettings(connect=(endpoint,)))
        self.subscribers = [
            self.session.declare_subscriber(wire.key(wire.COMMAND, namespace), self._on_command),
            self.session.declare_subscriber(
                wire.key(wire.CONTROLLER_STATUS, namespace), self._on_status
            ),
        ]
        self.namespace = namespace

    def _on_command(self, sample: Any) -> None:
        with self.lock:
            self.commands.append(wire.decode_twist_msg(sample.payload.to_bytes()))

    def _on_status(self, sample: Any) -> None:
        with self.lock:
            self.statuses.append(wire.decode_json_msg(sample.payload.to_bytes()))

    def put(self, topic: wire.Topic | str, payload: bytes) -> None:
        self.session.put(wire.key(topic, self.namespace), payload)

    def last_status(self) -> dict[str, Any]:
        with self.lock:
            return self.statuses[-1]

    def mark(self) -> int:
        """A place in the status list to `wait_for` from."""
        with self.lock:
            return len(self.statuses)

    def wait_for(
        self,
        predicate: Callable[[dict[str, Any]], bool],
        timeout: float = 15.0,
        since: int | None = None,
    ) -> dict[str, Any]:
        """The first status from now (or from the mark `since`) that satisfies `predicate`."""
        start = self.mark() if since is None else since
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.lock:
                for status in self.statuses[start:]:
                    if predicate(status):
                        return status
                start = len(self.statuses)
            time.sleep(0.02)
        raise AssertionError(f"no such status within {timeout} s; last: {self.statuses[-1:]}")

    def wait_for_command(
        self, predicate: Callable[[wire.Twist2D], bool], timeout: float = 15.0
    ) -> wire.Twist2D:
        """The first command received that satisfies `predicate`, once it has come (commands and
        statuses are separate subscriptions: a status may arrive before the command it reports)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.lock:
                for command in self.commands:
                    if predicate(command):
                        return command
            time.sleep(0.02)
        raise AssertionError(f"no such command within {timeout} s; last: {self.commands[-1:]}")


def reason_is(*reasons: str) -> Callable[[dict[str, Any]], bool]:
    return lambda status: status["reason"] in reasons


def start_daemon(
    tmp_path: Path, config: DaemonConfig, processes: list[subprocess.Popen[Any]]
) -> subprocess.Popen[str]:
    """`qnav controller` as a user starts it, beating into tmp_path/health.json; added to
    `processes` (the fixture that kills what a failed test left running)."""
    path = tmp_path / "controller.toml"
    path.write_text(to_toml(config))
    daemon = subprocess.Popen(
        [QNAV, "controller", "--config", str(path)],
        cwd=ROOT,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, HEALTH_FILE_ENV: str(tmp_path / "health.json")},
    )
    processes.append(daemon)
    return daemon


def stop_sends_stop(daemon: subprocess.Popen[str], number: int, listener: Listener) -> str:
    """Send `number` (SIGTERM, SIGINT) to the running daemon: it must exit cleanly with a stop
    published on the way out (status reason `shutdown`) as its last command; its stderr."""
    before = listener.mark()
    daemon.send_signal(number)
    _, stderr = daemon.communicate(timeout=20)
    assert daemon.returncode == 0, stderr
    listener.wait_for(reason_is("shutdown"), timeout=5, since=before)
    # The daemon has exited, so whatever command is last once delivery settles was its last.
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:
        with listener.lock:
            if listener.commands[-1] == wire.STOP:
                break
        time.sleep(0.02)
    with listener.lock:
        assert listener.commands[-1] == wire.STOP
    return stderr


def qnav_health(path: Path) -> subprocess.CompletedProcess[str]:
    """`qnav health --file path`, as a container's HEALTHCHECK runs it."""
    return subprocess.run(
        [QNAV, "health", "--file", str(path)], capture_output=True, text=True, check=False
    )


def start_feeder(
    processes: list[subprocess.Popen[Any]], endpoint: str, *options: str
) -> subprocess.Popen[str]:
    """The sensors (`tests.controller.feeder`), once they say they are ready; added to
    `processes`."""
    feeder = subprocess.Popen(
        [sys.executable, "-m", "tests.controller.feeder", endpoint, *options],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    processes.append(feeder)
    assert feeder.stdout is not None
    assert feeder.stdout.readline().strip() == "ready"
    return feeder


def action_commands(policy: Path) -> set[tuple[float, float]]:
    contract = PolicyContract.from_metadata(read_onnx(policy).metadata, str(policy))
    return {(a.linear_mps, a.angular_radps) for a in contract.actions}


def test_the_daemon_drives_stops_on_stale_and_bad_inputs_and_estop_and_stops_the_car_on_sigterm(
    tmp_path: Path,
    endpoint: str,
    make_policy: PolicyFactory,
    processes: list[subprocess.Popen[str]],
) -> None:
    policy = make_policy("walls-inertia")
    config = DaemonConfig(
        controller=ControllerSettings(policy=str(policy)),
        safety=SafetySettings(frame_id="map"),
        zenoh=ZenohSettings(listen=(endpoint,), connect=()),
        lookahead=LOOKAHEAD_OFF,
    )
    daemon = start_daemon(tmp_path, config, processes)
    listener = Listener(endpoint)
    try:
        first = listener.wait_for(lambda s: True, timeout=30)
        assert first["reason"] == "no_scan"
        assert listener.wait_for_command(lambda command: True) == wire.STOP  # the first of all

        feeder = start_feeder(processes, endpoint)
        assert feeder.stdin is not None
        driving = listener.wait_for(reason_is("policy"))
        assert driving["action"] in ("forward", "left", "right")
        assert len(driving["q_values"]) == 3
        actions = action_commands(policy)
        listener.wait_for_command(lambda c: (c.linear_mps, c.angular_radps) in actions)
        health = qnav_health(tmp_path / "health.json")
        assert health.returncode == 0 and "controller" in health.stdout, health.stdout

        # Malformed payloads are counted and change nothing.
        listener.put(wire.SCAN, b"\x00\x01\x00\x00garbage")
        listener.put(wire.POSE, wire.encode_pose_msg(wire.Pose2D(0.0, "map", float("nan"), 1.0)))
        listener.put(wire.POSE, wire.encode_pose_msg(wire.Pose2D(0.0, "odom", 1.0, 1.0)))
        counted = listener.wait_for(
            lambda s: (
                s["counters"]["malformed"]["scan"] >= 1 and s["counters"]["malformed"]["pose"] >= 2
            )
        )
        assert counted["reason"] == "policy"
        assert daemon.poll() is None

        # Scans stop coming: the car stops; they come back: it drives.
        feeder.stdin.write("scan off\n")
        feeder.stdin.flush()
        stale = listener.wait_for(reason_is("scan_stale"))
        assert stale["command"] == {"linear_mps": 0.0, "angular_radps": 0.0}
        assert stale["ages_s"]["scan"] > 0.4
        feeder.stdin.write("scan on\n")
        feeder.stdin.flush()
        listener.wait_for(reason_is("policy"))

        # The emergency stop latches until released on purpose.
        listener.put(wire.ESTOP, wire.encode_bool_msg(True))
        listener.wait_for(reason_is("estop_latched"))
        listener.put(wire.ESTOP_RELEASE, wire.encode_bool_msg(True))  # still pressed: refused
        listener.wait_for(lambda s: s["counters"]["releases_refused"] == 1)
        listener.put(wire.ESTOP, wire.encode_bool_msg(False))
        released_too_soon = listener.wait_for(lambda s: s["estop"]["pressed"] is False)
        assert released_too_soon["reason"] == "estop_latched"
        listener.put(wire.ESTOP_RELEASE, wire.encode_bool_msg(True))
        listener.wait_for(reason_is("policy"))

        # A malformed stop message presses the stop; a malformed release releases nothing.
        listener.put(wire.ESTOP, bytes.fromhex("0001000002"))
        pressed = listener.wait_for(reason_is("estop_latched"))
        assert pressed["counters"]["malformed"]["estop"] == 1
        assert pressed["estop"] == {"latched": True, "pressed": True}
        listener.put(wire.ESTOP, wire.encode_bool_msg(False))
        listener.wait_for(lambda s: s["estop"]["pressed"] is False)
        listener.put(wire.ESTOP_RELEASE, bytes.fromhex("0001000001deadbe"))
        refused = listener.wait_for(lambda s: s["counters"]["malformed"]["estop_release"] == 1)
        assert refused["reason"] == "estop_latched"
        listener.put(wire.ESTOP_RELEASE, wire.encode_bool_msg(True))
        listener.wait_for(reason_is("policy"))

        # SIGTERM while driving: a stop goes out before the process ends.
        stderr = stop_sends_stop(daemon, signal.SIGTERM, listener)
        assert "scan refused" in stderr and "pose refused" in stderr
        stopped = qnav_health(tmp_path / "health.json")
        assert stopped.returncode == 1, "a stopped daemon is unhealthy"
    finally:
        listener.session.close()


def test_the_lidarless_daemon_drives_on_pose_and_point_target_and_stops_the_car_on_sigint(
    tmp_path: Path,
    endpoint: str,
    make_policy: PolicyFactory,
    processes: list[subprocess.Popen[str]],
) -> None:
    policy = make_policy("toycar-inertia")
    config = DaemonConfig(
        controller=ControllerSettings(policy=str(policy)),
        safety=SafetySettings(target_kind="point"),
        zenoh=ZenohSettings(listen=(endpoint,), connect=(), namespace="car1"),
        lookahead=LOOKAHEAD_OFF,
    )
    daemon = start_daemon(tmp_path, config, processes)
    listener = Listener(endpoint, namespace="car1")
    try:
        assert listener.wait_for(lambda s: True, timeout=30)["reason"] == "no_pose"
        options = ("--namespace", "car1", "--beams", "0", "--target", "point")
        start_feeder(processes, endpoint, *options)
        driving = listener.wait_for(reason_is("policy"))
        assert driving["scan_stamp_s"] is None
        assert driving["target_distance_m"] == pytest.approx(7.0 * 2**0.5)

        stop_sends_stop(daemon, signal.SIGINT, listener)
    finally:
        listener.session.close()


def test_the_scan_triggered_daemon_stops_the_car_when_scans_stop_coming(
    tmp_path: Path,
    endpoint: str,
    make_policy: PolicyFactory,
    processes: list[subprocess.Popen[str]],
) -> None:
    """With `trigger = "scan"` decisions ride on scans; when they stop, only the main loop's
    periodic check of the safety rules can publish the stop."""
    policy = make_policy("walls-inertia")
    config = DaemonConfig(
        controller=ControllerSettings(policy=str(policy), trigger="scan"),
        zenoh=ZenohSettings(listen=(endpoint,), connect=()),
        lookahead=LOOKAHEAD_OFF,
    )
    daemon = start_daemon(tmp_path, config, processes)
    listener = Listener(endpoint)
    try:
        listener.wait_for(lambda s: True, timeout=30)
        feeder = start_feeder(processes, endpoint)
        assert feeder.stdin is not None
        driving = listener.wait_for(reason_is("policy"))
        assert driving["loop"]["trigger"] == "scan"
        feeder.stdin.write("scan off\n")
        feeder.stdin.flush()
        stale = listener.wait_for(reason_is("scan_stale"))
        assert stale["command"] == {"linear_mps": 0.0, "angular_radps": 0.0}
        assert stale["q_values"] is None
        # It keeps publishing the stop every period while the scans stay away.
        more = listener.mark()
        listener.wait_for(reason_is("scan_stale"), since=more + 1)
        with listener.lock:
            assert listener.commands[-1] == wire.STOP
        daemon.send_signal(signal.SIGTERM)
        _, stderr = daemon.communicate(timeout=20)
        assert daemon.returncode == 0, stderr
    finally:
        listener.session.close()


def test_the_daemon_with_the_shield_on_the_numpy_backend_reports_each_actions_risk(
    tmp_path: Path,
    endpoint: str,
    make_policy: PolicyFactory,
    processes: list[subprocess.Popen[str]],
) -> None:
    """`lookahead.mode = "shield"` on the numpy backend (a board without onnxruntime): every
    policy decision carries the forecast's risks, and the daemon still stops on SIGTERM."""
    config = DaemonConfig(
        controller=ControllerSettings(
            policy=str(make_policy("obstacles-inertia")), trigger="scan", backend="numpy"
        ),
        zenoh=ZenohSettings(listen=(endpoint,), connect=()),
        lookahead=LookaheadSettings(mode="shield", room_size_m=10.0),
    )
    daemon = start_daemon(tmp_path, config, processes)
    listener = Listener(endpoint)
    try:
        listener.wait_for(lambda s: True, timeout=30)
        start_feeder(processes, endpoint)
        first = listener.wait_for(reason_is("policy"))
        later = listener.wait_for(reason_is("policy"), since=listener.mark() + 3)
        for status in (first, later):
            risks = status["risks"]
            assert len(risks) == 3 and all(0.0 <= risk <= 1.0 for risk in risks), status
        assert "overruled" in later["counters"]
        stop_sends_stop(daemon, signal.SIGTERM, listener)
    finally:
        listener.session.close()


def test_the_shipped_daemon_stops_at_a_wall_and_on_an_all_neg_inf_scan_and_says_why(
    tmp_path: Path, endpoint: str, processes: list[subprocess.Popen[str]]
) -> None:
    """The shipped settings (the shield, the proximity stop), the room the feeder's car is in:
    whatever the policy and the shield chose, a wall 0.1 m ahead and a scan of -inf stop the car,
    and the stop is counted in the status and logged."""
    config = DaemonConfig(
        controller=ControllerSettings(policy=str(OBSTACLES_POLICY)),
        zenoh=ZenohSettings(listen=(endpoint,), connect=()),
        lookahead=LookaheadSettings(room_size_m=10.0),
    )
    assert config.lookahead.mode == "shield" and config.proximity == ProximitySettings()
    daemon = start_daemon(tmp_path, config, processes)
    listener = Listener(endpoint)
    try:
        listener.wait_for(lambda s: True, timeout=30)
        feeder = start_feeder(processes, endpoint)
        assert feeder.stdin is not None
        driving = listener.wait_for(reason_is("policy"))
        assert driving["risks"] is not None and driving["counters"]["proximity"] == 0
        for ranges in ("wall", "neginf"):
            feeder.stdin.write(f"ranges {ranges}\n")
            feeder.stdin.flush()
            stopped = listener.wait_for(reason_is("proximity"))
            assert stopped["command"] == {"linear_mps": 0.0, "angular_radps": 0.0}
            assert stopped["action"] is None and stopped["q_values"] is not None
            counted = stopped["counters"]["proximity"]
            assert counted >= 1 and stopped["counters"]["stops"] >= counted
            feeder.stdin.write("ranges random\n")
            feeder.stdin.flush()
            again = listener.wait_for(reason_is("policy"))
            assert again["counters"]["proximity"] >= counted
        stderr = stop_sends_stop(daemon, signal.SIGTERM, listener)
        assert stderr.count("proximity: the safety field forbids the chosen action; stopped") == 2
    finally:
        listener.session.close()
