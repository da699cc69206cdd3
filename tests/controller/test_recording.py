"""Recordings: MCAP with the ROS 2 profile, payloads byte for byte, readable after a SIGKILL."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from qnav.contracts import wire
from qnav.contracts.daemon import free_port
from qnav.contracts.health import HEALTH_FILE_ENV, check_health
from qnav.contracts.transport import ZenohSettings, open_session
from qnav.controller.recording import McapWriter, Rotation, play, read_recording, read_recordings


def _scan(i: int) -> bytes:
    ranges = np.full(720, 1.0 + i, dtype=np.float32)
    return wire.encode_scan_msg(
        wire.Scan(i * 0.1, "laser", 0.0, 2 * math.pi / 720, 0.1, 20.0, ranges)
    )


def _pose(i: int) -> bytes:
    return wire.encode_pose_msg(wire.Pose2D(i * 0.1, "map", float(i), 2.0, 0.3))


def _write(folder: Path, count: int, rotation: Rotation | None = None) -> McapWriter:
    with McapWriter(folder, rotation=rotation) as writer:
        for i in range(count):
            writer.write("/scan", wire.SCAN.ros_type, _scan(i), 1_000_000_000 + i * 50_000_000)
            writer.write("/pose", wire.POSE.ros_type, _pose(i), 1_000_000_000 + i * 50_000_000 + 1)
    return writer


def test_a_recording_uses_the_ros2_profile_and_keeps_payloads_byte_for_byte(
    tmp_path: Path,
) -> None:
    writer = _write(tmp_path, 10)
    (path,) = writer.files
    with path.open("rb") as stream:
        reader = make_reader(stream)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == 20
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        assert {s.name for s in summary.schemas.values()} == {
            wire.SCAN.ros_type,
            wire.POSE.ros_type,
        }
    messages = list(read_recording(path))
    assert [m.payload for m in messages if m.topic == "/scan"] == [_scan(i) for i in range(10)]
    assert wire.decode_pose_msg(messages[1].payload).x_m == 0.0


def test_a_recording_cut_anywhere_reads_up_to_its_last_complete_message(tmp_path: Path) -> None:
    (path,) = _write(tmp_path, 20).files
    data = path.read_bytes()
    counts = []
    for cut in range(0, len(data), len(data) // 37):
        truncated = tmp_path / "cut.mcap"
        truncated.write_bytes(data[:cut])
        messages = list(read_recording(truncated))
        expected = [m.payload for m in read_recording(path)][: len(messages)]
        assert [m.payload for m in messages] == expected
        counts.append(len(messages))
    assert counts == sorted(counts) and counts[-1] >= 38


def test_rotation_by_size_splits_into_files_that_are_each_complete(tmp_path: Path) -> None:
    writer = _write(tmp_path, 40, Rotation(max_bytes=20_000))
    assert len(writer.files) > 2
    for path in writer.files:
        with path.open("rb") as stream:
            assert make_reader(stream).get_summary() is not None
    assert [m.payload for m in read_recordings(writer.files)] == [
        p for i in range(40) for p in (_scan(i), _pose(i))
    ]


def test_a_recorder_killed_with_sigkill_keeps_every_message_it_received(tmp_path: Path) -> None:
    port = free_port()
    folder = tmp_path / "rec"
    health = tmp_path / "health.json"
    recorder = subprocess.Popen(
        [sys.executable, "-m", "qnav", "record", "--folder", str(folder),
         "--listen", f"tcp/127.0.0.1:{port}", "--connect", f"tcp/127.0.0.1:{port}"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, HEALTH_FILE_ENV: str(health)},
    )  # fmt: skip
    sent = 0
    try:
        settings = ZenohSettings(connect=(f"tcp/127.0.0.1:{port}",))
        with open_session(settings) as session:
            # Publish until the recorder is subscribed and has written some messages.
            deadline = time.monotonic() + 30
            files: list[Path] = []
            while time.monotonic() < deadline:
                session.put(wire.key(wire.SCAN), _scan(sent))
                sent += 1
                time.sleep(0.01)
                files = sorted(folder.glob("*.mcap"))
                if files and sent > 30 and len(list(read_recording(files[0]))) >= 20:
                    break
            else:
                pytest.fail("the recorder wrote nothing within 30 s")
            for _ in range(20):
                session.put(wire.key(wire.SCAN), _scan(sent))
                sent += 1
            # Wait (on a loaded machine, seconds) until the last one is in the file.
            last = _scan(sent - 1)
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                if any(m.payload == last for m in read_recording(files[0])):
                    break
                time.sleep(0.05)
            assert check_health(health, max_age_s=3.0)[0], "the recording loop beats"
            os.kill(recorder.pid, signal.SIGKILL)
            recorder.wait(10)
            # A killed recorder cannot remove its file: its beat goes stale.
            healthy, explanation = check_health(health, max_age_s=3.0, now_s=time.monotonic() + 4)
            assert not healthy and "recorder" in explanation
    finally:
        if recorder.poll() is None:
            recorder.kill()
    payloads = [m.payload for m in read_recording(files[0])]
    # The first samples may predate the subscription; after that none is missing.
    first = next(i for i in range(sent) if _scan(i) == payloads[0])
    assert payloads == [_scan(i) for i in range(first, sent)]
    # After `qnav recover`, other people's readers read every one of them too.
    mended = subprocess.run(
        [sys.executable, "-m", "qnav", "recover", str(folder)],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert mended.returncode == 0, mended.stderr
    with files[0].open("rb") as stream:
        theirs = [bytes(m.data) for _, _, m in make_reader(stream).iter_messages()]
    assert theirs == payloads
    from rosbags.highlevel import AnyReader

    with AnyReader([folder]) as reader:
        assert [bytes(raw) for _, _, raw in reader.messages()] == payloads


def test_playback_publishes_the_recorded_bytes_in_order_at_the_recorded_pace(
    tmp_path: Path,
) -> None:
    writer = _write(tmp_path, 10)  # 0.45 s of recording
    messages = list(read_recordings(writer.files))
    port = free_port()
    received: list[bytes] = []
    listen = ZenohSettings(listen=(f"tcp/127.0.0.1:{port}",), connect=())
    with open_session(listen) as session:
        done = threading.Event()

        def on_sample(sample: object) -> None:
            received.append(bytes(sample.payload.to_bytes()))  # type: ignore[attr-defined]
            if len(received) == len(messages):
                done.set()

        subscriber = session.declare_subscriber("**", on_sample)
        time.sleep(0.2)
        started = time.monotonic()
        played = play(messages, ZenohSettings(connect=(f"tcp/127.0.0.1:{port}",)), speed=3.0)
        elapsed = time.monotonic() - started
        assert done.wait(10)
        subscriber.undeclare()
    assert played == 20
    assert received == [m.payload for m in messages]
    assert elapsed >= 0.45 / 3.0
