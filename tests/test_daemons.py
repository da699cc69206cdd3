"""Every daemon stops within a second of SIGTERM, even before zenoh is reachable, and the bridge
keeps the car stopped without zenoh (issue 18 part 4). Real processes, real sockets."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from firmware_bridge.bench import free_port
from sim.mavlink_vehicle import MavlinkVehicle
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
    process.send_signal(signal.SIGTERM)
    try:
        process.wait(timeout=10)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
        return float("inf")
    return time.monotonic() - sent


@pytest.fixture
def vehicle() -> Iterator[MavlinkVehicle]:
    with MavlinkVehicle(vehicle_settings(free_port(socket.SOCK_DGRAM))) as car:
        yield car


def _arguments(daemon: str, endpoint: str, tmp_path: Path, vehicle_port: int) -> list[str]:
    if daemon == "controller":
        return ["controller", "--policy", str(POLICY), "--set", f'zenoh.connect=["{endpoint}"]']
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
    daemon: str, tmp_path: Path, vehicle: MavlinkVehicle
) -> None:
    log = tmp_path / f"{daemon}.log"
    port = int(vehicle.settings.connection.rsplit(":", 1)[1])
    process = _daemon(_arguments(daemon, _nobody_listening(), tmp_path, port), log)
    try:
        wait_until(
            lambda: b"waiting until something listens" in log.read_bytes(),
            timeout_s=60,
            what=f"{daemon} to start connecting",
        )
        time.sleep(0.3)  # well inside zenoh's wait
        elapsed = _stop(process)
    finally:
        if process.poll() is None:
            process.kill()
    print(f"{daemon}: exited {elapsed:.3f} s after SIGTERM")
    assert process.returncode == 0, log.read_text()
    assert elapsed <= EXIT_LIMIT_S


def test_the_bridge_keeps_the_car_stopped_without_zenoh(
    tmp_path: Path, vehicle: MavlinkVehicle
) -> None:
    port = int(vehicle.settings.connection.rsplit(":", 1)[1])
    log = tmp_path / "bridge.log"
    process = _daemon(_arguments("bridge", _nobody_listening(), tmp_path, port), log)
    try:
        wait_until(
            lambda: len(vehicle.received("RC_CHANNELS_OVERRIDE")) >= 3,
            timeout_s=60,
            what="neutral overrides from a bridge without zenoh",
        )
        assert vehicle.received("HEARTBEAT")
        overrides = vehicle.received("RC_CHANNELS_OVERRIDE")
        assert all(
            (r.fields["chan1_raw"], r.fields["chan3_raw"]) == (1500, 1500) for r in overrides
        )
        elapsed = _stop(process)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 0, log.read_text()
    assert elapsed <= EXIT_LIMIT_S
