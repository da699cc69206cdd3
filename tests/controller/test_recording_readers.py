"""Recordings that other people's readers read: rosbags' AnyReader and rosbag2 Reader, and
mcap's own `make_reader`, on complete recordings and on killed ones after `qnav recover`."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import Reader as Rosbag2Reader

from qnav.contracts import wire
from qnav.controller.recording import (
    McapWriter,
    is_complete,
    read_recording,
    recover,
    write_rosbag_metadata,
)
from tests.command import run_qnav
from tests.controller.test_recording import _pose, _scan


def _mcap_messages(path: Path) -> list[tuple[str, int, bytes]]:
    with path.open("rb") as stream:
        return [
            (channel.topic, message.log_time, bytes(message.data))
            for _, channel, message in make_reader(stream).iter_messages(log_time_order=False)
        ]


def _rosbags_messages(folder: Path) -> list[tuple[str, int, bytes]]:
    with AnyReader([folder]) as reader:
        return [
            (connection.topic, timestamp, bytes(raw))
            for connection, timestamp, raw in reader.messages()
        ]


def _write_from_threads(folder: Path, per_thread: int = 60) -> McapWriter:
    """Two threads (scans, poses) write at once, each message stamped by the writer."""
    writer = McapWriter(folder)

    def scans() -> None:
        for i in range(per_thread):
            writer.write("/scan", wire.SCAN.ros_type, _scan(i))

    def poses() -> None:
        for i in range(per_thread):
            writer.write("/pose", wire.POSE.ros_type, _pose(i))

    threads = [threading.Thread(target=scans), threading.Thread(target=poses)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    writer.close()
    return writer


def test_both_readers_read_every_message_of_a_recording_in_log_time_order(
    tmp_path: Path,
) -> None:
    writer = _write_from_threads(tmp_path)
    (path,) = writer.files
    ours = [(m.topic, m.log_time_ns, m.payload) for m in read_recording(path)]
    assert len(ours) == 120
    times = [t for _, t, _ in ours]
    assert times == sorted(times)  # file order is log-time order
    assert _mcap_messages(path) == ours
    assert _rosbags_messages(tmp_path) == ours
    with Rosbag2Reader(tmp_path) as bag:
        assert bag.message_count == 120
        assert {c.topic: c.msgcount for c in bag.connections} == {"/pose": 60, "/scan": 60}


def test_a_killed_recording_is_whole_again_for_both_readers_after_recover(
    tmp_path: Path,
) -> None:
    (complete,) = _write_from_threads(tmp_path / "whole").files
    data = complete.read_bytes()
    everything = [(m.topic, m.log_time_ns, m.payload) for m in read_recording(complete)]
    rng = np.random.default_rng(5)
    for trial, cut in enumerate(sorted(rng.integers(200, len(data) - 100, 6))):
        folder = tmp_path / f"cut{trial}"
        folder.mkdir()
        path = folder / "recording-0000.mcap"
        path.write_bytes(data[:cut])  # what SIGKILL leaves: no summary, maybe half a record
        assert not is_complete(path)
        kept = recover(path)
        write_rosbag_metadata(folder)
        assert is_complete(path) and (folder / "recording-0000.mcap.cut").exists()
        # Every complete message before the cut, and nothing else, for every reader.
        assert kept == len(list(read_recording(folder / "recording-0000.mcap.cut")))
        assert _mcap_messages(path) == everything[:kept]
        assert _rosbags_messages(folder) == everything[:kept]


def test_qnav_recover_mends_a_folder_and_leaves_complete_files_alone(tmp_path: Path) -> None:
    (path,) = _write_from_threads(tmp_path).files
    untouched = path.read_bytes()
    result = run_qnav("recover", str(tmp_path))
    assert result.returncode == 0, result.stderr
    assert "complete" in result.stdout and path.read_bytes() == untouched
    path.write_bytes(untouched[: len(untouched) // 2])
    result = run_qnav("recover", str(path))
    assert result.returncode == 0, result.stderr
    assert "recovered" in result.stdout and is_complete(path)
    assert len(_rosbags_messages(tmp_path)) == len(_mcap_messages(path)) > 0
