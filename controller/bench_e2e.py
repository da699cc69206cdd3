"""`qnav bench controller`: end-to-end latency of the daemon, in three processes on loopback.

1. The daemon, started as a user starts it (`qnav controller --config FILE`), with
   `trigger = "scan"` so that a decision follows each scan's arrival, listening on a loopback
   port with scouting off.
2. A publisher process: a target, then at the chosen rate a pose and a 720-reading LaserScan
   over [-pi, pi) (so the resampling is timed too), each scan stamped with the monotonic clock
   just before it is encoded and published.
3. This process: subscribes to the command and the status. Every command is followed by its
   status, which names the scan the decision used (`scan_stamp_s`); the latency of a scan is
   the command's arrival (monotonic, taken in the zenoh callback) minus that stamp. Linux's
   monotonic clock is shared by all processes of the machine.

So one figure covers: encoding the scan, zenoh to the daemon, decoding, resampling, the
policy's step (onnxruntime, one thread), the look ahead when one is asked for (the tracker's
update and the forecast), the proximity stop, encoding the Twist, zenoh to the receiver. The
daemon's numpy and onnxruntime run one thread each; `cpu` pins it to that core. With a look
ahead the publisher replays a drive through the simulated room (a `Drive`: the poses, targets
and scans of a car among moving obstacles, written by `qnav bench controller`), so the tracker
and the forecast work on what they would meet; without, one pose and random ranges. It is
reported beside its three parts, from the status (`time_s` is the scan's arrival in the
daemon's callback, `loop.decide_ms` the time from there to the command's publication): inbound
(stamp -> the daemon's callback), the daemon's own share, and outbound (publication -> the
receiver's callback).
"""

from __future__ import annotations

import math
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from qnav.contracts import wire
from qnav.contracts.daemon import free_port
from qnav.contracts.errors import ConfigError
from qnav.contracts.settings import to_toml
from qnav.contracts.transport import ZenohSettings, open_session
from qnav.controller.config import ControllerSettings, DaemonConfig, SafetySettings
from qnav.controller.lookahead import LookaheadSettings

_ONE_THREAD = {name: "1" for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
WARMUP_S = 1.0
"""Scans published before the timed ones, to let connections and caches settle."""


def daemon_config(
    policy: Path, endpoint: str, lookahead: LookaheadSettings | None = None
) -> DaemonConfig:
    """The daemon's settings for the bench: decide on scan arrival, listen on `endpoint`, with
    `lookahead` (None: off) and the default proximity stop."""
    return DaemonConfig(
        controller=ControllerSettings(policy=str(policy), trigger="scan", log_level="error"),
        safety=SafetySettings(scan_timeout_s=1.0, pose_timeout_s=1.0),
        zenoh=ZenohSettings(listen=(endpoint,), connect=()),
        lookahead=lookahead or LookaheadSettings(mode="off"),
    )


class Drive(NamedTuple):
    """What the publisher replays, one row per scan (`save` / `load` as .npz)."""

    poses: NDArray[np.float64]
    """(T, 3) the car's x, y, heading."""
    targets: NDArray[np.float64]
    """(T, 2) its target."""
    scans: NDArray[np.float32]
    """(T, B) the policy's beams, beam j at j * 2 pi / B (the bench sends them over [-pi, pi))."""

    def save(self, path: Path) -> None:
        """Write the drive to `path` (.npz)."""
        np.savez(path, poses=self.poses, targets=self.targets, scans=self.scans)

    @staticmethod
    def load(path: Path) -> Drive:
        """A drive `save` wrote."""
        with np.load(path) as data:
            return Drive(data["poses"], data["targets"], data["scans"])


def standing_drive(beams: int) -> Drive:
    """One pose and target, 16 scans of random ranges (the bench without a look ahead)."""
    ranges = np.random.default_rng(0).uniform(0.3, 8.0, size=(16, beams)).astype(np.float32)
    return Drive(np.tile([1.0, 1.0, 0.3], (16, 1)), np.tile([8.0, 8.0], (16, 1)), ranges)


def publish(endpoint: str, rate_hz: float, count: int, drive: Drive) -> float:
    """Publish the drive's target, then `count` (pose, scan) pairs of it at `rate_hz` (warm-up
    first; the drive starts over when it runs out), each scan over [-pi, pi).

    Returns the stamp of the first timed scan."""
    beams = drive.scans.shape[1]
    half = beams // 2  # beam j of the drive is reading j - B/2 of a scan starting at -pi
    session = open_session(ZenohSettings(connect=(endpoint,)))
    import zenoh

    try:
        options: dict[str, Any] = {
            "congestion_control": zenoh.CongestionControl.BLOCK,
            "express": True,
        }
        scan_pub = session.declare_publisher(wire.key(wire.SCAN), **options)
        pose_pub = session.declare_publisher(wire.key(wire.POSE), **options)
        target_pub = session.declare_publisher(wire.key(wire.TARGET_POSE), **options)
        period = 1.0 / rate_hz
        warmup = max(3, math.ceil(WARMUP_S * rate_hz))
        first_timed = math.nan
        deadline = time.monotonic() + 0.2
        for i in range(warmup + count):
            time.sleep(max(0.0, deadline - time.monotonic()))
            deadline += period
            row = i % len(drive.poses)
            tx, ty = drive.targets[row]
            if (
                i % max(1, round(rate_hz / 2)) == 0
                or row == 0
                or (drive.targets[row - 1] != (tx, ty)).any()
            ):
                target_pub.put(wire.encode_pose_msg(wire.Pose2D(0.0, "map", tx, ty)))
            now = time.monotonic()
            x, y, yaw = drive.poses[row]
            pose_pub.put(wire.encode_pose_msg(wire.Pose2D(now, "map", x, y, yaw)))
            stamp = time.monotonic()
            ranges = np.roll(drive.scans[row], half)
            scan = wire.Scan(stamp, "laser", -math.pi, 2 * math.pi / beams, 0.1, 30.0, ranges)
            scan_pub.put(wire.encode_scan_msg(scan))
            if i == warmup:
                first_timed = stamp
        time.sleep(0.3)
        return first_timed
    finally:
        session.close()


class Receiver:
    """Commands and statuses in arrival order, stamped in the zenoh callback."""

    def __init__(self, endpoint: str) -> None:
        import zenoh

        self.lock = threading.Lock()
        self.events: list[tuple[str, float, bytes]] = []
        self.session = open_session(ZenohSettings(connect=(endpoint,)))
        self.subscribers = [
            self.session.declare_subscriber(
                wire.key(topic), zenoh.handlers.Callback(self._on(kind), indirect=False)
            )
            for kind, topic in (("command", wire.COMMAND), ("status", wire.CONTROLLER_STATUS))
        ]

    def _on(self, kind: str) -> Any:
        def on_sample(sample: Any) -> None:
            arrived = time.monotonic()
            with self.lock:
                self.events.append((kind, arrived, sample.payload.to_bytes()))

        return on_sample

    def take(self) -> list[tuple[str, float, bytes]]:
        """Events so far (and forget them)."""
        with self.lock:
            events, self.events = self.events, []
        return events

    def close(self) -> None:
        """Close the session."""
        self.session.close()


class Latencies(NamedTuple):
    """Per policy decision, in ms: the whole path and its three parts."""

    end_to_end: list[float]
    """Scan stamped by the publisher -> command in the receiver's callback."""
    inbound: list[float]
    """Scan stamped -> scan in the daemon's callback (encoding, zenoh, the daemon's wake-up)."""
    daemon: list[float]
    """Scan in the daemon's callback -> command put started (decode, decide, encode)."""
    outbound: list[float]
    """Command put started -> command in the receiver's callback (the put, zenoh, wake-up)."""


def latencies(events: list[tuple[str, float, bytes]], since: float) -> Latencies:
    """The latencies of each policy decision on a scan stamped at or after `since` (all
    processes read the same monotonic clock)."""
    found = Latencies([], [], [], [])
    last_command: float | None = None
    seen: set[float] = set()
    for kind, arrived, payload in events:
        if kind == "command":
            last_command = arrived
            continue
        status = wire.decode_json_msg(payload)
        stamp = status.get("scan_stamp_s")
        decided = status["reason"] in ("policy", "proximity")  # the policy stepped on the scan
        if not decided or stamp is None or stamp < since or stamp in seen:
            continue
        if last_command is None:
            continue
        seen.add(stamp)
        decide_ms = float(status["loop"]["decide_ms"])
        found.end_to_end.append((last_command - stamp) * 1e3)
        found.inbound.append((status["time_s"] - stamp) * 1e3)
        found.daemon.append(decide_ms)
        found.outbound.append((last_command - status["time_s"]) * 1e3 - decide_ms)
    return found


def run(
    policy: Path,
    rates: list[float],
    seconds: float,
    *,
    lookahead: LookaheadSettings | None = None,
    drive: Path | None = None,
    cpu: int | None = None,
) -> dict[str, Any]:
    """Start the daemon (with `lookahead`, None: off; pinned to core `cpu`, None: not pinned),
    time each rate, stop the daemon; the report as a dict. The publisher replays `drive` (a
    `Drive` file), or without one a standing car's random scans."""
    from qnav.controller.policy import PolicyRuntime

    beams = PolicyRuntime(policy, backend="numpy").contract.num_beams
    if not beams:
        raise ValueError("the bench needs a policy that reads a lidar")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = os.environ | _ONE_THREAD
    results = []
    if cpu is not None and cpu not in _cpus():
        raise ConfigError(f"--cpu {cpu}: this process may run on cores {sorted(_cpus())}")
    with tempfile.TemporaryDirectory() as scratch:
        config = Path(scratch) / "controller.toml"
        config.write_text(to_toml(daemon_config(policy.resolve(), endpoint, lookahead)))
        if drive is None:
            drive = Path(scratch) / "drive.npz"
            standing_drive(beams).save(drive)
        daemon = subprocess.Popen(
            [sys.executable, "-m", "qnav", "controller", "--config", str(config)],
            env=env,
        )
        if cpu is not None:
            _pin(daemon.pid, cpu)  # before it starts its threads, which inherit the core
        receiver = Receiver(endpoint)
        try:
            _wait_for_status(receiver, daemon)
            for rate in rates:
                count = max(10, round(seconds * rate))
                receiver.take()
                done = subprocess.run(
                    [
                        sys.executable,
                        "-m",
                        "qnav.controller.bench_e2e",
                        endpoint,
                        str(rate),
                        str(count),
                        str(drive),
                    ],
                    env=env,
                    capture_output=True,
                    text=True,
                    check=True,
                )
                since = float(done.stdout.strip())
                results.append(_summary(rate, count, latencies(receiver.take(), since)))
        finally:
            daemon.terminate()
            daemon.wait(timeout=30)
            receiver.close()
    return {
        "measured": "scan publish (publisher process) -> command arrival (receiver process), "
        "loopback, daemon with trigger = scan",
        "policy": str(policy),
        "lookahead": "off" if lookahead is None else lookahead.mode,
        "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "daemon_cpu": cpu,
        "results": results,
    }


def _cpus() -> set[int]:
    """The cores this process may run on."""
    return os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else {0}


def _pin(pid: int, cpu: int) -> None:
    """Run process `pid` on core `cpu` alone."""
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(pid, {cpu})


def _wait_for_status(receiver: Receiver, daemon: subprocess.Popen[bytes]) -> None:
    deadline = time.monotonic() + 60.0
    while time.monotonic() < deadline:
        if daemon.poll() is not None:
            raise RuntimeError(f"the controller daemon exited with {daemon.returncode}")
        if any(kind == "status" for kind, _, _ in receiver.take()):
            return
        time.sleep(0.05)
    raise RuntimeError("no status from the controller daemon within 60 s")


def _summary(rate: float, scans: int, found: Latencies) -> dict[str, Any]:
    def stat(values: list[float], q: float) -> float:
        return round(float(np.percentile(values, q)), 3) if values else math.nan

    summary: dict[str, Any] = {
        "rate_hz": rate,
        "p50_ms": stat(found.end_to_end, 50),
        "p99_ms": stat(found.end_to_end, 99),
        "max_ms": round(max(found.end_to_end), 3) if found.end_to_end else math.nan,
        "scans": scans,
        "commands": len(found.end_to_end),
    }
    for part in ("inbound", "daemon", "outbound"):
        values = getattr(found, part)
        summary |= {f"{part}_p50_ms": stat(values, 50), f"{part}_p99_ms": stat(values, 99)}
    return summary


def format_report(report: dict[str, Any]) -> str:
    """A table of the rates' latencies."""
    lines = [
        f"end to end: {report['measured']}",
        f"policy {report['policy']}, look ahead {report['lookahead']}, daemon "
        + ("not pinned" if report["daemon_cpu"] is None else f"on core {report['daemon_cpu']}")
        + f" of {report['cpus']}",
        f"{'rate Hz':>8} {'p50 ms':>8} {'p99 ms':>8} {'max ms':>8} {'commands':>9}   "
        "p50 / p99 ms of: in (publisher -> daemon), daemon, out (daemon -> receiver)",
    ]
    for r in report["results"]:
        parts = "   ".join(
            f"{part} {r[f'{part}_p50_ms']:.3f} / {r[f'{part}_p99_ms']:.3f}"
            for part in ("inbound", "daemon", "outbound")
        )
        lines.append(
            f"{r['rate_hz']:>8g} {r['p50_ms']:>8.3f} {r['p99_ms']:>8.3f} {r['max_ms']:>8.3f} "
            f"{r['commands']:>4}/{r['scans']:<4}   {parts}"
        )
    goal = 3 if report["lookahead"] == "off" else 15
    lines.append(f"goal: p99 <= {goal} ms")
    return "\n".join(lines)


if __name__ == "__main__":
    # The publisher process `run` starts: endpoint, rate, count, drive (no user types these).
    endpoint, rate, count, drive = sys.argv[1:]
    print(publish(endpoint, float(rate), int(count), Drive.load(Path(drive))))
