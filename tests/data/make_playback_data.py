"""Makes the data of the playback tests (tests/controller/test_playback.py) in tests/data/playback.

    .venv/bin/python tests/data/make_playback_data.py          # everything (10-20 min, 2 cores)
    .venv/bin/python tests/data/make_playback_data.py --refs   # references only (playback-refs)

Everything, in order:

1. A small trained policy: `qnav train --scenario walls-increment --episodes 64
   --train-set train.hidden_size=64` (a recurrent network, a few minutes on 2 cores), exported
   with `qnav export RUN -o tests/data/playback/policy.onnx --eval-episodes 50`.
   `--reuse-policy` keeps the policy file already there. (The file kept in the repo was
   exported in the qnav-policy/1 layout, then re-exported in /2 from its own weights with
   `qnav export tests/data/playback/policy.onnx -o tests/data/playback/policy.onnx`, which
   keeps its metadata and notes it in `qnav.reexported_from`; the references did not change.
   A file of an older layout must be re-exported that way before `--reuse-policy` or
   `--refs`.)
2. A clean sim-in-the-loop recording: `qnav stack --policy policy.onnx --episodes 2` (the sim-car,
   the controller with `trigger = "scan"`, the bridge and the recorder as separate processes).
   `--stack DIR` reuses the output folder of an earlier `qnav stack` run instead.
3. One episode of it (the first success that drives long enough, else the first episode, cut to
   at most `MAX_DRIVE_S` of driving), from a little before its target was published, written as
   `clean.mcap`: the controller's inputs and the original run's `/cmd_vel` and
   `/qnav/controller_status`.
4. Recordings derived from the clean one with `McapWriter`, carrying the inputs only (the
   recorded outputs were the clean run's and would contradict the fault):
   - `stale_pose.mcap`: no pose for `POSE_GAP_S` (5 control periods) from 30 % into the drive;
   - `bad_scan.mcap`: every scan re-encoded with NaN, +inf, -inf and negative readings in
     places (seeded), and `DEAD_SCANS` scans in a row that are NaN throughout (refused);
   - `other_lidar.mcap`: every scan re-encoded as a 360-reading LaserScan over [-pi, pi)
     (counter-clockwise, range_min 0.05 m, frame `laser360`), read off the 720-beam scan;
   - `estop.mcap`: the emergency stop pressed at 30 % of the drive, a release request while it
     is still pressed (refused), the button out (false) after 1 s, and a release 0.4 s later;
   - `lost_target.mcap`: every target message removed.
5. The references: `<name>.decisions.jsonl`, the rows `controller.playback.play_into_controller`
   gives for each recording with the policy above and default controller settings (those of
   `qnav stack`). With `--refs` only this step runs; it prints, per recording, how many rows
   changed from the references it replaces (`make playback-refs` then shows `git diff --stat`).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
import tempfile
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from qnav.contracts import wire  # noqa: E402
from qnav.controller.playback import (  # noqa: E402
    differences,
    play_into_controller,
    read_rows,
    write_rows,
)
from qnav.controller.policy import PolicyRuntime  # noqa: E402
from qnav.controller.recording import McapWriter, RecordedMessage, read_recording  # noqa: E402

DATA = ROOT / "tests" / "data" / "playback"
POLICY = DATA / "policy.onnx"

INPUTS = ("/scan", "/pose", "/goal_pose", "/estop", "/qnav/estop_release")
OUTPUTS = ("/cmd_vel", "/qnav/controller_status")
LEAD_S = 0.5
"""Recorded time kept before the episode's target was published."""
MIN_DRIVE_S = 6.0
"""An episode used must drive at least this long (room for the faults)."""
MAX_DRIVE_S = 14.0
"""At most this much driving is kept (the files stay small)."""
FAULT_AT = 0.3
"""Faults start this far into the drive (fraction of its duration)."""
POSE_GAP_S = 1.0
"""Poses missing in stale_pose (5 control periods of walls-increment)."""
DEAD_SCANS = 5
"""Scans in a row that are NaN throughout in bad_scan."""
MS = 1_000_000


def qnav(*args: str) -> None:
    """Run `qnav ARGS` with this interpreter, failing loudly."""
    print("$ qnav " + " ".join(args), flush=True)
    subprocess.run([sys.executable, "-m", "qnav", *args], cwd=ROOT, check=True)


def make_policy(scratch: Path) -> None:
    """Step 1: train and export the small recurrent policy."""
    run = scratch / "run"
    qnav(
        "train",
        "--scenario", "walls-increment",
        "--episodes", "64",
        "--train-set", "train.hidden_size=64",
        "--run-dir", str(run),
        "--quiet",
    )  # fmt: skip
    qnav("export", str(run), "-o", str(POLICY), "--eval-episodes", "50", "--quiet")


def run_stack(scratch: Path) -> Path:
    """Step 2: two episodes of the full stack; returns its output folder."""
    out = scratch / "stack"
    qnav("stack", "--policy", str(POLICY), "--episodes", "2", "--out", str(out))
    return out


def clean_episode(stack: Path) -> list[RecordedMessage]:
    """Step 3: one episode's inputs and recorded outputs."""
    files = sorted((stack / "recording").glob("*.mcap"))
    messages = sorted(
        (m for f in files for m in read_recording(f) if m.topic in INPUTS + OUTPUTS),
        key=lambda m: m.log_time_ns,
    )
    outcomes = [json.loads(line)["outcome"] for line in (stack / "episodes.jsonl").open()]
    goals = [m.log_time_ns for m in messages if m.topic == "/goal_pose"]
    spans = [(g, goals[i + 1] if i + 1 < len(goals) else None) for i, g in enumerate(goals)]
    if not spans:
        raise SystemExit(f"no target in the recording of {stack}")

    def drive_s(span: tuple[int, int | None]) -> float:
        start, end = span
        scans = [m.log_time_ns for m in messages if m.topic == "/scan" and m.log_time_ns > start]
        scans = [t for t in scans if end is None or t < end]
        return (scans[-1] - scans[0]) * 1e-9 if len(scans) > 1 else 0.0

    # The recorder joins last: the first targets may have been published before it listened,
    # so the targets recorded are those of the last episodes.
    outcomes = outcomes[len(outcomes) - len(spans) :] if len(spans) <= len(outcomes) else []
    chosen = next(
        (
            i
            for i, span in enumerate(spans)
            if i < len(outcomes) and outcomes[i] == "success" and drive_s(span) >= MIN_DRIVE_S
        ),
        0,
    )
    start, end = spans[chosen]
    outcome = outcomes[chosen] if chosen < len(outcomes) else "unknown outcome"
    print(f"recorded episode {chosen + 1} of {len(spans)} with a target ({outcome}) kept")
    scans = [m.log_time_ns for m in messages if m.topic == "/scan" and m.log_time_ns > start]
    cut = scans[0] + int(MAX_DRIVE_S * 1e9) if scans else start
    stop = min(cut, end) if end is not None else cut
    first = start - int(LEAD_S * 1e9)
    return [m for m in messages if first <= m.log_time_ns < stop]


def write(name: str, messages: list[RecordedMessage]) -> Path:
    """One recording as tests/data/playback/<name>.mcap."""
    with tempfile.TemporaryDirectory() as folder:
        with McapWriter(Path(folder), stem=name) as writer:
            for m in sorted(messages, key=lambda m: m.log_time_ns):
                writer.write(m.topic, m.ros_type, m.payload, m.log_time_ns)
        (path,) = writer.files
        target = DATA / f"{name}.mcap"
        shutil.move(path, target)
    print(f"wrote {target.relative_to(ROOT)} ({target.stat().st_size / 1e3:.0f} kB)")
    return target


def drive_window(messages: list[RecordedMessage]) -> tuple[int, int]:
    """Log times of the first and the last scan after the target (the drive)."""
    goal = next(m.log_time_ns for m in messages if m.topic == "/goal_pose")
    scans = [m.log_time_ns for m in messages if m.topic == "/scan" and m.log_time_ns > goal]
    return scans[0], scans[-1]


def fault_time(messages: list[RecordedMessage]) -> int:
    """When the faults start: `FAULT_AT` into the drive."""
    first, last = drive_window(messages)
    return first + int(FAULT_AT * (last - first))


def rescan(
    messages: list[RecordedMessage], change: Callable[[int, wire.Scan], wire.Scan]
) -> list[RecordedMessage]:
    """Every scan decoded, changed by `change(index, scan)` and re-encoded."""
    out, index = [], 0
    for message in messages:
        if message.topic == "/scan":
            scan = change(index, wire.decode_scan_msg(message.payload))
            out.append(message._replace(payload=wire.encode_scan_msg(scan)))
            index += 1
        else:
            out.append(message)
    return out


def stale_pose(messages: list[RecordedMessage]) -> list[RecordedMessage]:
    """Poses dropped for `POSE_GAP_S` from the fault time."""
    start = fault_time(messages)
    end = start + int(POSE_GAP_S * 1e9)
    return [m for m in messages if not (m.topic == "/pose" and start <= m.log_time_ns < end)]


def bad_scan(messages: list[RecordedMessage]) -> list[RecordedMessage]:
    """NaN, +inf, -inf and negative readings in every scan; a stretch of all-NaN scans."""
    rng = np.random.default_rng(7)
    start = fault_time(messages)
    scan_times = [m.log_time_ns for m in messages if m.topic == "/scan"]
    dead_from = next(i for i, t in enumerate(scan_times) if t >= start)
    dead = range(dead_from, dead_from + DEAD_SCANS)

    def change(index: int, scan: wire.Scan) -> wire.Scan:
        ranges = scan.ranges_m.astype(np.float32).copy()
        if index in dead:
            ranges[:] = np.nan
        else:
            draw = rng.random(ranges.shape[0])
            ranges[draw < 0.10] = np.nan
            ranges[(draw >= 0.10) & (draw < 0.20)] = np.inf
            ranges[(draw >= 0.20) & (draw < 0.25)] = -0.5
            ranges[(draw >= 0.25) & (draw < 0.26)] = -np.inf
        return wire.Scan(
            scan.stamp_s,
            scan.frame_id,
            scan.angle_min_rad,
            scan.angle_increment_rad,
            scan.range_min_m,
            scan.range_max_m,
            ranges,
        )

    return rescan(messages, change)


def other_lidar(messages: list[RecordedMessage]) -> list[RecordedMessage]:
    """Each 720-beam scan over [0, 2 pi) read as a 360-reading scan over [-pi, pi)."""
    readings = 360

    def change(index: int, scan: wire.Scan) -> wire.Scan:
        beams = scan.ranges_m.shape[0]
        step = 2 * math.pi / readings
        angles = -math.pi + step * np.arange(readings)
        source = np.round(np.mod(angles, 2 * math.pi) / (2 * math.pi / beams)).astype(int) % beams
        return wire.Scan(
            scan.stamp_s, "laser360", -math.pi, step, 0.05, scan.range_max_m, scan.ranges_m[source]
        )

    return rescan(messages, change)


def estop(messages: list[RecordedMessage]) -> list[RecordedMessage]:
    """Pressed, a refused release, the button out, released."""
    press = fault_time(messages) + MS  # a millisecond after a scan, never at the same time
    events = [
        ("/estop", True, press),
        ("/qnav/estop_release", True, press + 500 * MS),
        ("/estop", False, press + 1000 * MS),
        ("/qnav/estop_release", True, press + 1400 * MS),
    ]
    added = [
        RecordedMessage(topic, wire.ESTOP.ros_type, time_ns, wire.encode_bool_msg(value))
        for topic, value, time_ns in events
    ]
    return sorted([*messages, *added], key=lambda m: m.log_time_ns)


def lost_target(messages: list[RecordedMessage]) -> list[RecordedMessage]:
    """No target message at all."""
    return [m for m in messages if m.topic != "/goal_pose"]


FAULTS: dict[str, Callable[[list[RecordedMessage]], list[RecordedMessage]]] = {
    "stale_pose": stale_pose,
    "bad_scan": bad_scan,
    "other_lidar": other_lidar,
    "estop": estop,
    "lost_target": lost_target,
}


def make_recordings(stack: Path) -> None:
    """Steps 3 and 4."""
    clean = clean_episode(stack)
    write("clean", clean)
    inputs = [m for m in clean if m.topic in INPUTS]
    for name, fault in FAULTS.items():
        write(name, fault(inputs))


def make_references() -> int:
    """Step 5: rows of every recording; prints what changed. Returns the rows changed."""
    runtime = PolicyRuntime(POLICY)
    changed_total = 0
    for path in sorted(DATA.glob("*.mcap")):
        reference = path.with_suffix(".decisions.jsonl")
        old = read_rows(reference) if reference.exists() else None
        rows = play_into_controller(list(read_recording(path)), runtime)
        write_rows(reference, rows)
        changes = [] if old is None else differences(old, rows)
        changed_total += len(rows) if old is None else len(changes)
        counts = ", ".join(f"{k} {v}" for k, v in Counter(r["reason"] for r in rows).items())
        verdict = "new" if old is None else f"{len(changes)} changed" if changes else "unchanged"
        print(f"{path.stem:<12} {len(rows):4d} rows ({counts}): {verdict}")
        for line in changes[:10]:
            print(f"    {line}")
        if len(changes) > 10:
            print(f"    ... and {len(changes) - 10} more")
    return changed_total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--refs", action="store_true", help="only regenerate the references")
    parser.add_argument("--reuse-policy", action="store_true", help="keep policy.onnx")
    parser.add_argument(
        "--stack", type=Path, help="output folder of an earlier `qnav stack` (keeps policy.onnx)"
    )
    args = parser.parse_args()
    DATA.mkdir(parents=True, exist_ok=True)
    if not args.refs:
        with tempfile.TemporaryDirectory(prefix="qnav-playback-") as folder:
            scratch = Path(folder)
            if not ((args.reuse_policy or args.stack) and POLICY.exists()):
                make_policy(scratch)
            make_recordings(args.stack or run_stack(scratch))
    changed = make_references()
    print(f"{changed} reference rows changed" if changed else "references unchanged")


if __name__ == "__main__":
    main()
