"""The fuzz suite (issue 18 part 7): malformed payloads on every subscribed key of the real
controller and bridge processes, over loopback zenoh.

`make fuzz` sends 10,000 payloads per controller key and 2,000 per bridge key
(`QNAV_FUZZ_PAYLOADS`, `QNAV_FUZZ_BRIDGE_PAYLOADS`); the default suite sends a seeded slice of
150 per key. Payloads come from `tests.contracts.malformed`; the few that are well-formed and
would move, arm or release (a mutated Bool that reads true, say) are skipped, since they are not
malformed. The checks: the daemon lives, its memory stays bounded, no payload produced a
non-neutral command, a release or an arm, and afterwards it answers valid input.
"""

from __future__ import annotations

import json
import math
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from qnav.contracts import delivery, wire
from qnav.contracts.daemon import free_port, stop_process
from qnav.contracts.transport import ZenohSettings, open_session
from qnav.simcar.mavlink_vehicle import MavlinkVehicle
from tests.contracts.malformed import enables_motion, payloads
from tests.firmware_bridge.rig import vehicle_settings, wait_until

POLICY = Path(__file__).parents[1] / "data" / "playback" / "policy.onnx"
CONTROLLER_PAYLOADS = int(os.environ.get("QNAV_FUZZ_PAYLOADS", "150"))
BRIDGE_PAYLOADS = int(os.environ.get("QNAV_FUZZ_BRIDGE_PAYLOADS", "150"))
RSS_GROWTH_LIMIT_MB = 150.0
"""How much a daemon's resident memory may grow over a fuzz run (the 10 MB payloads pass
through zenoh's buffers; a leak per payload would show as hundreds of MB)."""

CONTROLLER_KEYS = {
    wire.SCAN: "scan",
    wire.POSE: "pose",
    wire.TARGET_POSE: "pose",
    wire.ESTOP: "bool",
    wire.ESTOP_RELEASE: "bool",
    wire.POLICY_ANNOUNCEMENT: "json",
}
"""Every key the controller reads, policy announcements included (`policy.source = "server"`)."""
BRIDGE_KEYS = {wire.COMMAND: "twist", wire.VEHICLE_REQUEST: "json", wire.POSE: "pose"}


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return math.nan


@pytest.fixture
def hub() -> Iterator[tuple[Any, str]]:
    endpoint = f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    with open_session(ZenohSettings(listen=(endpoint,), connect=())) as session:
        yield session, endpoint


def _fuzz(session: Any, keys: dict[wire.Topic, str], count: int) -> dict[str, int]:
    """Put `count` malformed payloads on each key; returns how many were sent per key."""
    sent = {}
    for topic, kind in keys.items():
        publisher = session.declare_publisher(wire.key(topic))
        sent[topic.name] = 0
        for i, payload in enumerate(payloads(kind, count, seed=len(sent))):
            if enables_motion(kind, payload):
                continue
            publisher.put(payload)
            sent[topic.name] += 1
            if i % 200 == 199:
                time.sleep(0.02)  # let the daemon keep up, as a real flood would be paced
        publisher.undeclare()
    return sent


@dataclass(frozen=True)
class Flood:
    """One fuzz run against a live daemon."""

    sent: dict[str, int]
    """Payloads sent, per topic name."""
    rss_mb: tuple[float, float]
    """The daemon's resident memory before and after, in MB."""
    started_s: float
    """When the run began (time.monotonic)."""

    def usage(self) -> dict[str, Any]:
        """The report's memory and duration fields."""
        return {
            "rss_mb": [round(mb, 1) for mb in self.rss_mb],
            "seconds": round(time.monotonic() - self.started_s, 1),
        }


def _flood(
    process: subprocess.Popen[bytes], session: Any, keys: dict[wire.Topic, str], count: int
) -> Flood:
    """`_fuzz` a running daemon: it must live through it (and a second more for the backlog)
    with its memory bounded."""
    rss_before = _rss_mb(process.pid)
    started = time.monotonic()
    sent = _fuzz(session, keys, count)
    time.sleep(1.0)
    assert process.poll() is None, "the daemon died"
    rss_after = _rss_mb(process.pid)
    assert rss_after - rss_before < RSS_GROWTH_LIMIT_MB
    return Flood(sent, (rss_before, rss_after), started)


def _valid_scan() -> bytes:
    ranges = np.full(720, 6.0, dtype=np.float32)
    return wire.encode_scan_msg(
        wire.Scan(0.0, "laser", -math.pi, 2 * math.pi / 720, 0.05, 20.0, ranges)
    )


def test_no_malformed_payload_moves_or_releases_the_controller(
    hub: tuple[Any, str], tmp_path: Path
) -> None:
    session, endpoint = hub
    commands: list[wire.Twist2D] = []
    statuses: list[dict[str, Any]] = []
    lock = threading.Lock()

    def on_command(sample: Any) -> None:
        with lock:
            commands.append(wire.decode_twist_msg(bytes(sample.payload.to_bytes())))

    def on_status(sample: Any) -> None:
        with lock:
            statuses.append(wire.decode_json_msg(bytes(sample.payload.to_bytes())))

    subscribers = [
        session.declare_subscriber(wire.key(wire.COMMAND), on_command),
        session.declare_subscriber(wire.key(wire.CONTROLLER_STATUS), on_status),
    ]
    log = (tmp_path / "controller.log").open("wb")
    public_key = tmp_path / "policy.pub"
    public_key.write_bytes(delivery.generate_key_pair()[1])
    process = subprocess.Popen(
        [sys.executable, "-m", "qnav", "controller", "--policy", str(POLICY),
         "--set", f'zenoh.connect=["{endpoint}"]', "--set", "safety.estop_start_latched=true",
         "--set", 'policy.source="server"', "--set", f'policy.public_key="{public_key}"',
         "--set", 'lookahead.mode="off"'],
        stdout=log, stderr=log,
    )  # fmt: skip
    try:
        wait_until(lambda: len(statuses) > 3, timeout_s=60, what="controller statuses")
        flood = _flood(process, session, CONTROLLER_KEYS, CONTROLLER_PAYLOADS)
        with lock:
            during = list(commands)
            latched = [s["estop"]["latched"] for s in statuses]
            last = statuses[-1]
        assert during and all(c == wire.STOP for c in during)
        assert all(latched), "a malformed payload released the stop"
        malformed = last["counters"]["malformed"] | {
            wire.POLICY_ANNOUNCEMENT.name: last["delivery"]["malformed"]
        }
        assert last["counters"]["policy_swaps"] == 0 and last["delivery"]["pending"] is None
        # It still answers valid input: button out, release, inputs -> the policy drives.
        moved_from = len(during)
        publish = {
            topic: session.declare_publisher(wire.key(topic))
            for topic in (wire.ESTOP, wire.ESTOP_RELEASE, wire.SCAN, wire.POSE, wire.TARGET_POSE)
        }
        publish[wire.ESTOP].put(wire.encode_bool_msg(False))
        time.sleep(0.2)
        publish[wire.ESTOP_RELEASE].put(wire.encode_bool_msg(True))
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            publish[wire.SCAN].put(_valid_scan())
            publish[wire.POSE].put(wire.encode_pose_msg(wire.Pose2D(0.0, "", 3.0, 3.0, 0.0)))
            publish[wire.TARGET_POSE].put(wire.encode_pose_msg(wire.Pose2D(0.0, "", 7.0, 7.0)))
            with lock:
                if any(c != wire.STOP for c in commands[moved_from:]):
                    break
            time.sleep(0.1)
        else:
            pytest.fail("the controller never drove on valid input after the fuzz")
        report = {
            "daemon": "controller",
            "payloads_sent": flood.sent,
            "counted_malformed": malformed,
            "commands_during_fuzz": len(during),
            "non_stop_commands_during_fuzz": 0,
            **flood.usage(),
        }
        print(json.dumps(report))
        assert sum(malformed.values()) >= 0.5 * sum(flood.sent.values())
    finally:
        for subscriber in subscribers:
            subscriber.undeclare()
        stop_process(process)
        log.close()


def test_no_malformed_payload_moves_or_arms_through_the_bridge(
    hub: tuple[Any, str], tmp_path: Path
) -> None:
    session, endpoint = hub
    port = free_port(socket.SOCK_DGRAM)
    with MavlinkVehicle(vehicle_settings(port)) as vehicle:
        log = (tmp_path / "bridge.log").open("wb")
        process = subprocess.Popen(
            [sys.executable, "-m", "qnav", "bridge",
             "--set", f'zenoh.connect=["{endpoint}"]', "--set", "zenoh.listen=[]",
             "--set", f'mavlink.connection="udpout:127.0.0.1:{port}"',
             "--set", "failsafe.stop_period_s=0.05"],
            stdout=log, stderr=log,
        )  # fmt: skip
        try:
            wait_until(
                lambda: len(vehicle.received("RC_CHANNELS_OVERRIDE")) > 3,
                timeout_s=60,
                what="the bridge's neutral overrides",
            )
            time.sleep(1.0)  # zenoh joined
            flood = _flood(process, session, BRIDGE_KEYS, BRIDGE_PAYLOADS)
            overrides = vehicle.received("RC_CHANNELS_OVERRIDE")
            pwm = {(r.fields["chan1_raw"], r.fields["chan3_raw"]) for r in overrides}
            assert pwm == {(1500, 1500)}, "a malformed payload moved the car"
            assert not vehicle.armed, "a malformed payload armed the car"
            # It still answers valid input.
            command = session.declare_publisher(wire.key(wire.COMMAND))
            seen = len(overrides)

            def drove() -> bool:
                command.put(wire.encode_twist_msg(wire.Twist2D(0.5, 0.0)))
                time.sleep(0.05)
                later = vehicle.received("RC_CHANNELS_OVERRIDE")[seen:]
                return any(r.fields["chan3_raw"] > 1500 for r in later)

            wait_until(drove, timeout_s=10, what="a valid command after the fuzz")
            print(
                json.dumps(
                    {
                        "daemon": "bridge",
                        "payloads_sent": flood.sent,
                        "overrides_during_fuzz": len(overrides),
                        "non_neutral_overrides_during_fuzz": 0,
                        "armed": False,
                        **flood.usage(),
                    }
                )
            )
        finally:
            stop_process(process)
            log.close()
