"""Makes the data of the bridge's playback tests (tests/firmware_bridge/test_playback.py).

    .venv/bin/python tests/data/make_bridge_playback.py          # record anew (about 30 s)
    .venv/bin/python tests/data/make_bridge_playback.py --refs   # references only

Recording: each scenario below runs the real daemon (`firmware_bridge.daemon.Bridge`, in this
process) between a real zenoh session and the MAVLink test vehicle (`simcar.mavlink_vehicle`) on
loopback, as tests/firmware_bridge/rig.py wires them, with a `firmware_bridge.playback.Recorder`
as its journal: every call into the core, with its inputs and the live core's actions, goes to
tests/data/bridge_playback/<scenario>.recording.jsonl.gz. A recording is what happened on this
machine at that time (timings vary run to run); the references are what the core makes of it.

References: `<scenario>.actions.jsonl`, what `firmware_bridge.playback.replay` gives for the
recording. With `--refs` only this step runs, on the recordings kept in the repo; it prints per
scenario how many calls' actions changed from the references it replaces (`make playback-refs`
then shows `git diff --stat`). Commit the new references when the change is meant.

The scenarios (manual output with RC override unless said; the rig's fast timings: 0.2 s
command timeout, 0.3 s link timeout):

- `drive_silence_exit`: armed on connect; drive; command silence (the failsafe's stops, the
  brake mode GUIDED); drive again (back to MANUAL); close, as on SIGTERM (stops, the brake
  mode, stops until the car is at rest, disarm until acknowledged).
- `malformed`: malformed commands, absurd commands while driving, a malformed and an absurd
  pose, a malformed request, an arm request with remote arming off, garbage on the MAVLink port;
  then a good command still drives.
- `estop`: drive, then the stop commands the controller publishes while its emergency stop is
  pressed (a zero Twist every 0.05 s), then silence.
- `heartbeat_loss`: drive; the vehicle goes silent both ways (link down, reconnect attempts,
  commands dropped); it comes back (stops until a fresh command); a fresh command drives.
- `link_loss`: over TCP; the vehicle process ends (the port closes: reopened every 0.15 s, in
  vain); a new one serves the port (link back; arming was asked once, so a request arms it).
- `guided`: guided output forwarding motion-capture poses (the EKF origin, GUIDED once a pose
  went out); velocity targets; silence (the zero target); close.
"""

from __future__ import annotations

import argparse
import gzip
import logging
import socket
import sys
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from qnav.contracts.daemon import free_port  # noqa: E402
from qnav.contracts.wire import COMMAND, POSE, Pose2D, Twist2D, encode_pose_msg, encode_twist_msg  # noqa: E402
from qnav.contracts.wire import key as wire_key  # noqa: E402
from qnav.firmware_bridge import playback  # noqa: E402
from qnav.firmware_bridge.daemon import Bridge  # noqa: E402
from qnav.simcar.mavlink_vehicle import MavlinkVehicle  # noqa: E402
from tests.firmware_bridge import rig as wiring  # noqa: E402
from tests.firmware_bridge.rig import wait_until  # noqa: E402

DATA = ROOT / "tests" / "data" / "bridge_playback"

QUIET_VEHICLE: dict[str, Any] = {
    "heartbeat_period_s": 0.1,
    "telemetry_period_s": 0.1,
    "require_position_for_guided": False,
}
"""Slower telemetry than the rig's (fewer messages to keep; still 3 heartbeats per timeout)."""
QUIET_BRIDGE: dict[str, Any] = {"vehicle": {"state_period_s": 0.25}}
"""A state every 0.25 s (and on every change) instead of the rig's 0.05 s."""


def _recording(name: str) -> Path:
    return DATA / f"{name}.recording.jsonl.gz"


def _record(
    name: str,
    scenario: Callable[[wiring.Rig], None],
    bridge: dict[str, Any] | None = None,
    vehicle: dict[str, Any] | None = None,
) -> None:
    """Run `scenario` on a rig whose bridge records into the scenario's recording."""
    with ExitStack() as stack:
        rig = wiring.start_rig(
            stack, start_bridge=False, vehicle={**QUIET_VEHICLE, **(vehicle or {})}
        )
        settings = wiring.bridge_settings(
            rig.zenoh_port, rig.mavlink_port, **{**QUIET_BRIDGE, **(bridge or {})}
        )
        out = stack.enter_context(gzip.open(_recording(name), "wt", compresslevel=9))
        rig.bridge = Bridge(settings, journal=playback.Recorder(out, settings))
        rig.bridge.start()
        try:
            scenario(rig)
        finally:
            rig.bridge.close()
    print(f"{name}: recorded {_recording(name).stat().st_size} bytes")


def drive_silence_exit(rig: wiring.Rig) -> None:
    rig.ready()
    rig.drive(0.8, 0.0, 0.5)
    wait_until(lambda: rig.vehicle.mode == "GUIDED", what="the brake mode after silence")
    time.sleep(0.3)
    rig.drive(0.8, 0.3, 0.5)
    wait_until(lambda: rig.vehicle.mode == "MANUAL", what="back to MANUAL")


def malformed(rig: wiring.Rig) -> None:
    rig.ready()
    for payload in (b"", b"\x00\x01\x00\x00garbage", b"\xff" * 60):
        rig.publish(wire_key(COMMAND), payload)
    wait_until(lambda: rig.counters().get("malformed") == 3, what="malformed commands")
    rig.drive(0.8, 0.0, 0.3)
    for linear, angular in ((0.0, -9.1e150), (1e308, 1e308), (20.0, 0.0)):
        rig.publish(wire_key(COMMAND), encode_twist_msg(Twist2D(linear, angular)))
    wait_until(lambda: rig.counters().get("malformed") == 6, what="absurd commands")
    rig.publish(wire_key(POSE), b"\x00\x01\x00\x00not a pose")
    rig.publish(wire_key(POSE), encode_pose_msg(Pose2D(time.time(), "map", 1e308, 0.0, 0.0)))
    rig.request({"arm": "yes"})
    rig.request({"arm": True})  # vehicle.remote_arming is off
    wait_until(lambda: rig.counters().get("malformed") == 9, what="bad pose and request")
    wait_until(lambda: rig.counters().get("refused") == 1, what="the refused arm request")
    rig.send_garbage()
    wait_until(lambda: rig.counters().get("bad_data", 0) >= 2, what="garbage counted")
    rig.drive(0.8, 0.0, 0.3)
    time.sleep(0.3)


def estop(rig: wiring.Rig) -> None:
    rig.ready()
    rig.drive(0.8, 0.0, 0.5)
    rig.drive(0.0, 0.0, 0.5)  # the controller's stop commands while its e-stop is pressed
    time.sleep(0.5)


def heartbeat_loss(rig: wiring.Rig) -> None:
    rig.ready()
    rig.drive(0.8, 0.0, 0.3)
    rig.vehicle.set_link_enabled(False)
    wait_until(lambda: rig.state().get("link_up") is False, what="link reported down")
    wait_until(lambda: rig.counters().get("reconnects", 0) >= 1, what="a reconnection attempt")
    dropped = rig.counters().get("dropped", 0)
    rig.drive(0.8, 0.0, 0.2)
    wait_until(lambda: rig.counters().get("dropped", 0) >= dropped + 4, what="commands dropped")
    rig.vehicle.set_link_enabled(True)
    wait_until(lambda: rig.state().get("link_up") is True, what="link reported up again")
    time.sleep(0.3)
    rig.drive(0.8, 0.0, 0.3)


def link_loss(rig: wiring.Rig) -> None:
    """Drives the TCP rig `_record_link_loss` built."""
    rig.ready()
    rig.drive(0.8, 0.0, 0.3)
    rig.vehicle.stop()
    wait_until(lambda: rig.state().get("link_up") is False, what="link down")
    wait_until(lambda: rig.counters().get("reconnects", 0) >= 2, what="reopened in vain")


def _record_link_loss() -> None:
    port = free_port(socket.SOCK_STREAM)
    serve = {"connection": f"tcpin:127.0.0.1:{port}", **QUIET_VEHICLE}
    bridge = {
        "mavlink": {"connection": f"tcp:127.0.0.1:{port}"},
        "vehicle": {"remote_arming": True, "state_period_s": 0.25},
    }
    with ExitStack() as stack:
        rig = wiring.start_rig(stack, start_bridge=False)
        rig.vehicle = stack.enter_context(MavlinkVehicle(wiring.vehicle_settings(0, **serve)))
        settings = wiring.bridge_settings(rig.zenoh_port, 0, **bridge)
        out = stack.enter_context(gzip.open(_recording("link_loss"), "wt", compresslevel=9))
        rig.bridge = Bridge(settings, journal=playback.Recorder(out, settings))
        rig.bridge.start()
        try:
            link_loss(rig)
            rig.vehicle = stack.enter_context(MavlinkVehicle(wiring.vehicle_settings(0, **serve)))
            wait_until(lambda: rig.state().get("link_up") is True, what="link back over TCP")
            time.sleep(0.3)
            rig.request({"arm": True})
            wait_until(lambda: rig.vehicle.armed, what="armed on request")
            rig.drive(0.8, 0.0, 0.3)
        finally:
            rig.bridge.close()
    print(f"link_loss: recorded {_recording('link_loss').stat().st_size} bytes")


def guided(rig: wiring.Rig) -> None:
    wait_until(lambda: rig.state().get("link_up"), what="link up")
    for _ in range(10):
        rig.publish_pose()
        time.sleep(0.1)
    wait_until(lambda: rig.state().get("armed") and rig.vehicle.mode == "GUIDED", what="GUIDED")
    end = time.monotonic() + 0.5
    while time.monotonic() < end:
        rig.command(0.8, 0.2)
        rig.publish_pose()
        time.sleep(0.05)
    for _ in range(5):
        rig.publish_pose()
        time.sleep(0.1)


SCENARIOS = ["drive_silence_exit", "malformed", "estop", "heartbeat_loss", "link_loss", "guided"]


def record_all() -> None:
    DATA.mkdir(parents=True, exist_ok=True)
    _record("drive_silence_exit", drive_silence_exit)
    _record("malformed", malformed)
    _record("estop", estop)
    _record("heartbeat_loss", heartbeat_loss)
    _record_link_loss()
    _record("guided", guided, bridge={"output": {"mode": "guided"}})


def write_references() -> None:
    for name in SCENARIOS:
        settings, calls = playback.read_recording(_recording(name))
        rows = playback.replay(settings, calls)
        path = DATA / f"{name}.actions.jsonl"
        old = playback.read_rows(path) if path.exists() else []
        changed = playback.differences(old, rows, most=len(old) + len(rows) + 1)
        playback.write_rows(path, rows)
        print(f"{name}: {len(rows)} calls with actions, {len(changed)} changed")


def main() -> None:
    logging.getLogger("qnav.firmware_bridge").setLevel(logging.ERROR)  # the faults are on purpose
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--refs", action="store_true", help="only regenerate the references")
    args = parser.parse_args()
    if not args.refs:
        record_all()
    write_references()


if __name__ == "__main__":
    main()
