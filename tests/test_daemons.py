"""Every daemon ends within a second of SIGTERM or SIGINT, whatever the state of zenoh.

Real processes (`qnav controller`, `qnav record`, `qnav bridge`) as a user starts them, on
loopback with scouting off, in three states: no router reachable yet (the endpoint is a closed
port), connected to a router, and after the router was killed. The router is a listening zenoh
peer in its own process, so the test can kill it. The bridge drives the test vehicle over real
UDP: it must send heartbeats and neutral output with no zenoh at all, and neutral on its way out.
"""

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

from contracts import wire
from contracts.settings import to_toml
from contracts.transport import ZenohSettings, open_session
from controller.config import ControllerSettings, DaemonConfig
from firmware_bridge.bench import free_port
from sim.mavlink_vehicle import MavlinkVehicle
from tests.conftest import PolicyFactory
from tests.firmware_bridge.rig import bridge_settings, vehicle_settings, wait_until

ROOT = Path(__file__).resolve().parents[1]
EXIT_LIMIT_S = 1.0
"""The goal of issue 18: a daemon ends within a second of the signal, in every state."""
NEUTRAL = (1500, 1500)
ROUTER = (
    "import sys, time\n"
    "from contracts.transport import ZenohSettings, open_session\n"
    "session = open_session(ZenohSettings(listen=(sys.argv[1],), connect=()))\n"
    "print('ready', flush=True)\n"
    "time.sleep(3600)\n"
)
STATES = ["no-router", "connected", "router-lost"]


class Process:
    """A started daemon and its output lines (read by a thread, so pipes never fill)."""

    def __init__(self, args: list[str]) -> None:
        self.popen = subprocess.Popen(
            [sys.executable, "-m", "qnav", *args],
            cwd=ROOT,
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

    def wait_for_line(self, text: str, timeout_s: float = 60.0) -> None:
        wait_until(
            lambda: text in self.output() or self.popen.poll() is not None,
            timeout_s,
            f"{text!r} in the output",
        )
        assert text in self.output(), self.output()

    def stop(self, number: signal.Signals, what: str) -> float:
        """Send the signal; the seconds until the process ended (polled, 20 s at most)."""
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

    def kill(self) -> None:
        if self.popen.poll() is None:
            self.popen.kill()
            self.popen.wait()


@pytest.fixture
def processes() -> Iterator[list[Process]]:
    """Processes a failed test leaves behind are killed."""
    started: list[Process] = []
    yield started
    for process in started:
        process.kill()


def start_router(endpoint: str, processes: list[Process]) -> subprocess.Popen[str]:
    router = subprocess.Popen(
        [sys.executable, "-c", ROUTER, endpoint], cwd=ROOT, stdout=subprocess.PIPE, text=True
    )
    assert router.stdout is not None and router.stdout.readline().strip() == "ready"
    holder = Process.__new__(Process)  # killed with the others if the test fails
    holder.popen = router
    processes.append(holder)
    return router


class Observer:
    """A client of the router that counts the samples of one key."""

    def __init__(self, endpoint: str, topic: wire.Topic) -> None:
        self.session = open_session(ZenohSettings(connect=(endpoint,)))
        self.samples: list[bytes] = []
        self.subscriber = self.session.declare_subscriber(wire.key(topic), self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        self.samples.append(bytes(sample.payload.to_bytes()))

    def close(self) -> None:
        self.subscriber.undeclare()
        self.session.close()


def _bring_to(
    state: str, endpoint: str, router: subprocess.Popen[str] | None, topic: wire.Topic | None
) -> None:
    """Wait until the daemon's `topic` comes through the router (none: the caller waited),
    and for router-lost, kill the router then."""
    if state == "no-router":
        return
    assert router is not None
    if topic is not None:
        observer = Observer(endpoint, topic)
        try:
            wait_until(lambda: observer.samples, 60, f"{topic} from the daemon via the router")
        finally:
            observer.close()
    if state == "router-lost":
        router.kill()
        router.wait()
        time.sleep(0.5)  # the daemon's session notices the closed connection


def _endpoint_and_router(
    state: str, processes: list[Process]
) -> tuple[str, subprocess.Popen[str] | None]:
    endpoint = f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    router = None if state == "no-router" else start_router(endpoint, processes)
    return endpoint, router


@pytest.mark.parametrize("state", STATES)
@pytest.mark.parametrize("number", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_controller_stops_within_a_second(
    state: str,
    number: signal.Signals,
    tmp_path: Path,
    make_policy: PolicyFactory,
    processes: list[Process],
) -> None:
    endpoint, router = _endpoint_and_router(state, processes)
    config = DaemonConfig(
        controller=ControllerSettings(policy=str(make_policy("walls-inertia"))),
        zenoh=ZenohSettings(connect=(endpoint,)),
    )
    path = tmp_path / "controller.toml"
    path.write_text(to_toml(config))
    controller = Process(["controller", "--config", str(path)])
    processes.append(controller)
    controller.wait_for_line("zenoh: connecting to")
    _bring_to(state, endpoint, router, wire.CONTROLLER_STATUS)
    if state == "no-router":
        time.sleep(0.3)  # well inside the wait for the router
    elapsed = controller.stop(number, f"controller, {state}")
    assert controller.popen.returncode == 0, controller.output()
    assert "Traceback" not in controller.output()
    assert elapsed <= EXIT_LIMIT_S, controller.output()


@pytest.mark.parametrize("state", STATES)
def test_recorder_stops_within_a_second(
    state: str, tmp_path: Path, processes: list[Process]
) -> None:
    endpoint, router = _endpoint_and_router(state, processes)
    recorder = Process(["record", "--connect", endpoint, "--out", str(tmp_path)])
    processes.append(recorder)
    recorder.wait_for_line("zenoh: connecting to")
    if state != "no-router":
        recorder.wait_for_line("recording ")
    _bring_to(state, endpoint, router, None)
    if state == "no-router":
        time.sleep(0.3)
    elapsed = recorder.stop(signal.SIGTERM, f"recorder, {state}")
    assert recorder.popen.returncode == 0, recorder.output()
    assert "recorded 0 messages" in recorder.output() or state != "no-router"
    assert elapsed <= EXIT_LIMIT_S, recorder.output()


def _overrides(vehicle: MavlinkVehicle, since_s: float) -> list[tuple[int, int]]:
    return [
        (r.fields["chan1_raw"], r.fields["chan3_raw"])
        for r in vehicle.received("RC_CHANNELS_OVERRIDE")
        if r.time_s >= since_s
    ]


@pytest.mark.parametrize("state", STATES)
@pytest.mark.parametrize("number", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_bridge_stops_within_a_second_and_sends_neutral_first(
    state: str, number: signal.Signals, tmp_path: Path, processes: list[Process]
) -> None:
    endpoint, router = _endpoint_and_router(state, processes)
    mavlink_port = free_port(socket.SOCK_DGRAM)
    with MavlinkVehicle(vehicle_settings(mavlink_port)) as vehicle:
        settings = bridge_settings(
            0,
            mavlink_port,
            zenoh={"connect": [endpoint]},
            # Periodic stops far apart, so the ones sent on the way out stand out.
            failsafe={"stop_period_s": 2.0},
        )
        path = tmp_path / "bridge.toml"
        path.write_text(to_toml(settings))
        bridge = Process(["bridge", "--config", str(path)])
        processes.append(bridge)
        # With or without zenoh, the vehicle side runs: heartbeats, link up, armed, neutral.
        wait_until(lambda: vehicle.armed, 60, "the bridge to arm the vehicle")
        assert {(r.src_system, r.src_component) for r in vehicle.received("HEARTBEAT")} >= {
            (1, 191)
        }
        assert set(_overrides(vehicle, -1.0)) == {NEUTRAL}
        _bring_to(state, endpoint, router, wire.VEHICLE_STATE)
        sent = time.monotonic()
        elapsed = bridge.stop(number, f"bridge, {state}")
        out = _overrides(vehicle, sent)
        disarms = [
            r
            for r in vehicle.received("COMMAND_LONG")
            if r.time_s >= sent and r.fields["command"] == 400 and r.fields["param1"] == 0.0
        ]
    assert bridge.popen.returncode == 0, bridge.output()
    assert "Traceback" not in bridge.output()
    assert len(out) >= 3 and set(out) == {NEUTRAL}, out
    assert disarms, "disarmed on the way out"
    assert elapsed <= EXIT_LIMIT_S, bridge.output()


def test_bridge_without_zenoh_heartbeats_and_holds_neutral(
    tmp_path: Path, processes: list[Process]
) -> None:
    mavlink_port = free_port(socket.SOCK_DGRAM)
    closed = f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    with MavlinkVehicle(vehicle_settings(mavlink_port)) as vehicle:
        settings = bridge_settings(0, mavlink_port, zenoh={"connect": [closed]})
        path = tmp_path / "bridge.toml"
        path.write_text(to_toml(settings))
        bridge = Process(["bridge", "--config", str(path)])
        processes.append(bridge)
        wait_until(lambda: len(_overrides(vehicle, -1.0)) >= 10, 60, "neutral output")
        heartbeats = {
            (r.src_system, r.src_component, r.fields["type"]) for r in vehicle.received("HEARTBEAT")
        }
        assert heartbeats == {(1, 191, 18), (255, 191, 6)}
        assert set(_overrides(vehicle, -1.0)) == {NEUTRAL}
        assert vehicle.armed and vehicle.mode == "MANUAL"  # link up, requests done
        assert vehicle.velocity()[0] == 0.0
        bridge.stop(signal.SIGTERM, "bridge, no zenoh")
    assert bridge.popen.returncode == 0, bridge.output()
