"""Every daemon and long-running verb stops within a second of SIGTERM and SIGINT, even before
zenoh is reachable, and the bridge keeps the car stopped without zenoh (issue 18 part 4, issue
53). Real processes, real sockets.

The states: no router reachable (the endpoint is a closed port), connected through a hub, and
after the hub was killed; SIGTERM and SIGINT. `pytest -s` prints each measured exit time."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from qnav.contracts import wire
from qnav.contracts.daemon import free_port, stop_process
from qnav.contracts.mavlink import MAV_CMD_COMPONENT_ARM_DISARM
from qnav.contracts.transport import ZenohSettings, open_session
from qnav.simcar.mavlink_vehicle import MavlinkVehicle
from tests.firmware_bridge.rig import vehicle_settings, wait_until

POLICY = Path(__file__).parent / "data" / "playback" / "policy.onnx"
EXIT_LIMIT_S = 1.0
"""The goal: a daemon is gone within this long of SIGTERM, in any state."""


def _nobody_listening() -> str:
    """A loopback endpoint where nothing listens (the port was free a moment ago)."""
    return f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"


def _daemon(args: list[str], log: Path) -> subprocess.Popen[bytes]:
    with log.open("wb") as out:
        return subprocess.Popen([sys.executable, "-m", "qnav", *args], stdout=out, stderr=out)


def _stop(process: subprocess.Popen[bytes]) -> float:
    """Send SIGTERM; seconds until the process is gone (it is killed after 10 s)."""
    sent = time.monotonic()
    if not stop_process(process, timeout_s=10.0):
        return float("inf")
    return time.monotonic() - sent


@pytest.fixture
def vehicle() -> Iterator[MavlinkVehicle]:
    with MavlinkVehicle(vehicle_settings(free_port(socket.SOCK_DGRAM))) as car:
        yield car


def _arguments(daemon: str, endpoint: str, tmp_path: Path, vehicle_port: int) -> list[str]:
    if daemon == "controller":
        return [
            "controller", "--policy", str(POLICY), "--set", f'zenoh.connect=["{endpoint}"]',
            "--set", 'lookahead.mode="off"',
        ]  # fmt: skip
    if daemon == "record":
        return ["record", "--connect", endpoint, "--out", str(tmp_path / "recordings")]
    return [
        "bridge",
        "--set", f'zenoh.connect=["{endpoint}"]',
        "--set", "zenoh.listen=[]",
        "--set", f'mavlink.connection="udpout:127.0.0.1:{vehicle_port}"',
    ]  # fmt: skip


@pytest.mark.parametrize("daemon", ["controller", "record", "bridge"])
def test_a_daemon_waiting_for_zenoh_stops_within_a_second_of_sigterm(
    daemon: str, tmp_path: Path, vehicle: MavlinkVehicle, processes: list[subprocess.Popen[Any]]
) -> None:
    log = tmp_path / f"{daemon}.log"
    port = int(vehicle.settings.connection.rsplit(":", 1)[1])
    process = _daemon(_arguments(daemon, _nobody_listening(), tmp_path, port), log)
    processes.append(process)
    wait_until(
        lambda: b"waiting until something listens" in log.read_bytes(),
        timeout_s=60,
        what=f"{daemon} to start connecting",
    )
    time.sleep(0.3)  # well inside zenoh's wait
    elapsed = _stop(process)
    print(f"{daemon}: exited {elapsed:.3f} s after SIGTERM")
    assert process.returncode == 0, log.read_text()
    assert elapsed <= EXIT_LIMIT_S


def test_the_bridge_keeps_the_car_stopped_without_zenoh(
    tmp_path: Path, vehicle: MavlinkVehicle, processes: list[subprocess.Popen[Any]]
) -> None:
    port = int(vehicle.settings.connection.rsplit(":", 1)[1])
    log = tmp_path / "bridge.log"
    process = _daemon(_arguments("bridge", _nobody_listening(), tmp_path, port), log)
    processes.append(process)
    wait_until(
        lambda: len(vehicle.received("RC_CHANNELS_OVERRIDE")) >= 3,
        timeout_s=60,
        what="neutral overrides from a bridge without zenoh",
    )
    assert vehicle.received("HEARTBEAT")
    overrides = vehicle.received("RC_CHANNELS_OVERRIDE")
    assert all((r.fields["chan1_raw"], r.fields["chan3_raw"]) == (1500, 1500) for r in overrides)
    elapsed = _stop(process)
    assert process.returncode == 0, log.read_text()
    assert elapsed <= EXIT_LIMIT_S


# -- every state: waiting, connected, router lost; SIGTERM and SIGINT ---------------------------

STATES = ["no-router", "connected", "router-lost"]
ROUTER = (
    "import sys, time\n"
    "from contracts.transport import ZenohSettings, open_session\n"
    "session = open_session(ZenohSettings(listen=(sys.argv[1],), connect=()))\n"
    "print('ready', flush=True)\n"
    "time.sleep(3600)\n"
)
"""A zenoh hub in a process of its own (a listening peer routes for its clients), to kill."""
NEUTRAL = (1500, 1500)


class _Daemon:
    """A started daemon whose output a thread reads (so the pipe never fills)."""

    def __init__(self, args: list[str]) -> None:
        self.popen = subprocess.Popen(
            [sys.executable, "-m", "qnav", *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.popen.stdout is not None
        for line in self.popen.stdout:
            self.lines.append(line)

    def output(self) -> str:
        return "".join(self.lines)

    def wait_for_line(self, text: str) -> None:
        wait_until(lambda: text in self.output() or self.popen.poll() is not None, 60, repr(text))
        assert text in self.output(), self.output()

    def stop(self, number: signal.Signals, what: str) -> float:
        """Send the signal; seconds until the process ended (polled, 20 s at most)."""
        assert self.popen.poll() is None, self.output()
        sent = time.monotonic()
        self.popen.send_signal(number)
        deadline = sent + 20.0
        while self.popen.poll() is None and time.monotonic() < deadline:
            time.sleep(0.005)
        elapsed = time.monotonic() - sent
        print(f"{what}: {number.name} -> exit in {elapsed:.3f} s (rc {self.popen.poll()})")
        self._reader.join(5)
        return elapsed


def _router(state: str, processes: list[subprocess.Popen[Any]]) -> tuple[str, Any]:
    """An endpoint, and (unless no-router) a hub process listening there."""
    endpoint = _nobody_listening()
    if state == "no-router":
        return endpoint, None
    router = subprocess.Popen([sys.executable, "-c", ROUTER, endpoint], stdout=subprocess.PIPE)
    processes.append(router)
    assert router.stdout is not None and router.stdout.readline().strip() == b"ready"
    return endpoint, router


def _bring_to(state: str, endpoint: str, router: Any, topic: wire.Topic | None) -> None:
    """Wait until the daemon's `topic` comes through the hub (None: the caller has waited);
    for router-lost, then kill the hub."""
    if state == "no-router":
        time.sleep(0.3)  # well inside the wait for the router
        return
    if topic is not None:
        with open_session(ZenohSettings(connect=(endpoint,))) as session:
            samples: list[bytes] = []
            subscriber = session.declare_subscriber(
                wire.key(topic), lambda sample: samples.append(sample.payload.to_bytes())
            )
            wait_until(lambda: samples, 60, f"{topic.name} through the hub")
            subscriber.undeclare()
    if state == "router-lost":
        router.kill()
        router.wait()
        time.sleep(0.5)  # the daemon's session sees its connection close


@pytest.mark.parametrize("state", STATES)
@pytest.mark.parametrize("number", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_the_controller_stops_within_a_second_in_every_state(
    state: str, number: signal.Signals, processes: list[subprocess.Popen[Any]]
) -> None:
    endpoint, router = _router(state, processes)
    controller = _Daemon(_arguments("controller", endpoint, Path(), 0))
    processes.append(controller.popen)
    controller.wait_for_line("waiting until something listens")
    _bring_to(state, endpoint, router, wire.CONTROLLER_STATUS)
    elapsed = controller.stop(number, f"controller, {state}")
    assert controller.popen.returncode == 0, controller.output()
    assert "Traceback" not in controller.output()
    assert elapsed <= EXIT_LIMIT_S, controller.output()


@pytest.mark.parametrize("state", STATES)
def test_the_recorder_stops_within_a_second_in_every_state(
    state: str, tmp_path: Path, processes: list[subprocess.Popen[Any]]
) -> None:
    endpoint, router = _router(state, processes)
    recorder = _Daemon(_arguments("record", endpoint, tmp_path, 0))
    processes.append(recorder.popen)
    recorder.wait_for_line("waiting until something listens")
    if state != "no-router":
        recorder.wait_for_line("recording ")  # its session is open
    _bring_to(state, endpoint, router, None)
    elapsed = recorder.stop(signal.SIGTERM, f"recorder, {state}")
    assert recorder.popen.returncode == 0, recorder.output()
    assert "Traceback" not in recorder.output()
    assert elapsed <= EXIT_LIMIT_S, recorder.output()


def _overrides(vehicle: MavlinkVehicle, since_s: float) -> list[tuple[int, int]]:
    return [
        (r.fields["chan1_raw"], r.fields["chan3_raw"])
        for r in vehicle.received("RC_CHANNELS_OVERRIDE")
        if r.time_s >= since_s
    ]


@pytest.mark.parametrize("state", STATES)
@pytest.mark.parametrize("number", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_the_bridge_sends_neutral_and_disarms_then_stops_within_a_second_in_every_state(
    state: str,
    number: signal.Signals,
    vehicle: MavlinkVehicle,
    processes: list[subprocess.Popen[Any]],
) -> None:
    endpoint, router = _router(state, processes)
    port = int(vehicle.settings.connection.rsplit(":", 1)[1])
    bridge = _Daemon(
        [
            *_arguments("bridge", endpoint, Path(), port),
            "--set", "vehicle.arm_on_connect=true",
            # Periodic stops far apart, so the ones sent on the way out stand out.
            "--set", "failsafe.stop_period_s=2.0",
        ]
    )  # fmt: skip
    processes.append(bridge.popen)
    # With or without zenoh, the vehicle side runs: link up, armed, neutral only.
    wait_until(lambda: vehicle.armed, 60, "the bridge to arm the vehicle")
    assert set(_overrides(vehicle, -1.0)) == {NEUTRAL}
    _bring_to(state, endpoint, router, wire.VEHICLE_STATE)
    sent = time.monotonic()
    elapsed = bridge.stop(number, f"bridge, {state}")
    out = _overrides(vehicle, sent)
    disarms = [
        r
        for r in vehicle.received("COMMAND_LONG")
        if r.time_s >= sent
        and r.fields["command"] == MAV_CMD_COMPONENT_ARM_DISARM
        and r.fields["param1"] == 0.0
    ]
    assert bridge.popen.returncode == 0, bridge.output()
    assert "Traceback" not in bridge.output()
    assert len(out) >= 3 and set(out) == {NEUTRAL}, out  # its stops on the way out
    assert disarms and not vehicle.armed
    assert elapsed <= EXIT_LIMIT_S, bridge.output()


# -- the other long-running verbs: every state, SIGTERM and SIGINT (issue 53) -----------------


POSE_TYPE = "geometry_msgs/msg/PoseStamped"


def _pose_recording(folder: Path, seconds: float = 120.0) -> Path:
    """A recording of motion-capture poses at 10 Hz, long enough never to end in a test."""
    from qnav.controller.recording import McapWriter

    with McapWriter(folder) as writer:
        for index in range(int(seconds * 10)):
            pose = wire.Pose2D(index * 0.1, "map", 0.0, 0.0, 0.0)
            writer.write("/pose", POSE_TYPE, wire.encode_pose_msg(pose), index * 100_000_000)
    return writer.files[0]


def _serve_key(folder: Path) -> Path:
    from qnav.contracts.delivery import generate_key_pair

    path = folder / "private.pem"
    path.write_bytes(generate_key_pair()[0])
    return path


def _verb(verb: str, endpoint: str, tmp_path: Path) -> tuple[list[str], str | wire.Topic, int]:
    """The verb's arguments, the sign that it joined zenoh (a line it prints, or a topic it
    publishes), and its exit status after a signal."""
    if verb == "serve":
        (tmp_path / "policies").mkdir()
        args = ["serve", str(tmp_path / "policies"), "--key", str(_serve_key(tmp_path))]
        return [*args, "--connect", endpoint], "serving ", 0
    if verb == "playback":
        recording = _pose_recording(tmp_path / "recording")
        return ["playback", str(recording), "--connect", endpoint], wire.POSE, 0
    if verb == "sim-car":
        vehicle = f"udpout:127.0.0.1:{free_port(socket.SOCK_DGRAM)}"
        args = ["sim-car", "--connect", endpoint, "--vehicle-connection", vehicle]
        return args, "waiting for the car to be armed", 0
    # calibrate-car: stopped before its fit, it measured nothing: exit 1, as when aborted.
    args = ["calibrate-car", "--set", f'zenoh.connect=["{endpoint}"]', "--set", "zenoh.listen=[]"]
    return args, "waiting up to", 1


@pytest.mark.parametrize("state", STATES)
@pytest.mark.parametrize("number", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
@pytest.mark.parametrize("verb", ["serve", "playback", "sim-car", "calibrate-car"])
def test_every_zenoh_verb_stops_within_a_second_of_either_signal_in_every_state(
    verb: str,
    state: str,
    number: signal.Signals,
    tmp_path: Path,
    processes: list[subprocess.Popen[Any]],
) -> None:
    # Waiting for zenoh, playback and sim-car ignored both signals, calibrate-car SIGINT; serve
    # printed a StoppedError traceback.
    endpoint, router = _router(state, processes)
    args, joined, code = _verb(verb, endpoint, tmp_path)
    daemon = _Daemon(args)
    processes.append(daemon.popen)
    daemon.wait_for_line("waiting until something listens")
    if isinstance(joined, str):
        if state != "no-router":
            daemon.wait_for_line(joined)
        _bring_to(state, endpoint, router, None)
    else:
        _bring_to(state, endpoint, router, joined)
    elapsed = daemon.stop(number, f"{verb}, {state}")
    assert daemon.popen.returncode == code, daemon.output()
    assert "Traceback" not in daemon.output()
    assert elapsed <= EXIT_LIMIT_S, daemon.output()


@pytest.mark.parametrize("state", STATES)
def test_the_recorder_stops_within_a_second_of_sigint_in_every_state(
    state: str, tmp_path: Path, processes: list[subprocess.Popen[Any]]
) -> None:
    endpoint, router = _router(state, processes)
    recorder = _Daemon(_arguments("record", endpoint, tmp_path, 0))
    processes.append(recorder.popen)
    recorder.wait_for_line("waiting until something listens")
    if state != "no-router":
        recorder.wait_for_line("recording ")
    _bring_to(state, endpoint, router, None)
    elapsed = recorder.stop(signal.SIGINT, f"recorder, {state}")
    assert recorder.popen.returncode == 0, recorder.output()
    assert "Traceback" not in recorder.output()
    assert elapsed <= EXIT_LIMIT_S, recorder.output()


@pytest.mark.parametrize("number", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_the_fake_vehicle_stops_within_a_second_of_either_signal(
    number: signal.Signals, processes: list[subprocess.Popen[Any]]
) -> None:
    port = free_port(socket.SOCK_DGRAM)
    vehicle = _Daemon(["fake-vehicle", "--connection", f"udpout:127.0.0.1:{port}"])
    processes.append(vehicle.popen)
    vehicle.wait_for_line("serving")
    elapsed = vehicle.stop(number, "fake-vehicle")
    assert vehicle.popen.returncode == 0, vehicle.output()
    assert "Traceback" not in vehicle.output()
    assert elapsed <= EXIT_LIMIT_S, vehicle.output()
