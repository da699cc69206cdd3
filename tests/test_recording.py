"""`qnav recover` and `qnav playback` take only MCAP files: anything else is refused and left as it
was, and a folder's metadata.yaml describes one recording, never others beside it (issue 53:
`qnav recover policy.onnx` replaced the file with an empty MCAP, wrote a metadata.yaml over
the folder's other recordings and exited 0; `qnav playback` of random bytes said "0 messages").
The real `qnav` process on real files."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from qnav.controller.recording import McapWriter, is_complete, read_recording
from tests.command import run_qnav

DATA = Path(__file__).parent / "data"
POLICY = DATA / "playback" / "policy.onnx"


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {path.name: path.read_bytes() for path in sorted(folder.iterdir())}


def _refused(result: subprocess.CompletedProcess[str], verb: str, *words: str) -> None:
    assert result.returncode == 2, result.stdout + result.stderr
    assert "Traceback" not in result.stderr
    assert result.stderr.startswith(f"qnav {verb}: "), result.stderr
    for word in words:
        assert word in result.stderr, result.stderr


def _recording(folder: Path, messages: int = 20) -> Path:
    """A recording's folder holding one complete file of `messages` poses, 0.1 s apart."""
    with McapWriter(folder) as writer:
        for index in range(messages):
            writer.write("/pose", "geometry_msgs/msg/PoseStamped", b"\0" * 8, index * 100_000_000)
    (path,) = writer.files
    return path


@pytest.fixture
def not_mcap(tmp_path: Path) -> list[Path]:
    """A folder with a recording and three files that are not MCAP, one named as if it were."""
    folder = tmp_path / "mixed"
    _recording(folder)
    (folder / "metadata.yaml").unlink()
    shutil.copy(POLICY, folder / "policy.onnx")
    (folder / "noise.bin").write_bytes(np.random.default_rng(0).bytes(5000))
    (folder / "noise.mcap").write_bytes(np.random.default_rng(1).bytes(5000))
    return [folder / "policy.onnx", folder / "noise.bin", folder / "noise.mcap"]


def test_recover_refuses_a_file_that_is_not_mcap_and_touches_nothing(
    not_mcap: list[Path],
) -> None:
    folder = not_mcap[0].parent
    before = _snapshot(folder)
    for path in not_mcap:
        _refused(run_qnav("recover", str(path)), "recover", str(path), "not an MCAP file")
        assert _snapshot(folder) == before  # no .cut, no rewrite, no metadata.yaml
    # A folder with one such file among its recordings: refused before any file is touched.
    _refused(run_qnav("recover", str(folder)), "recover", "noise.mcap", "not an MCAP file")
    assert _snapshot(folder) == before


def test_recover_in_a_folder_of_unrelated_recordings_writes_no_metadata_for_them(
    tmp_path: Path,
) -> None:
    folder = tmp_path / "playback"
    shutil.copytree(DATA / "playback", folder)
    path = folder / "clean.mcap"
    path.write_bytes(path.read_bytes()[:60_000])  # cut, as SIGKILL leaves it
    before = _snapshot(folder)
    result = run_qnav("recover", str(path))
    assert result.returncode == 0, result.stderr
    assert is_complete(path) and (folder / "clean.mcap.cut").read_bytes() == before["clean.mcap"]
    assert not (folder / "metadata.yaml").exists()  # six recordings are not one bag
    assert "no metadata.yaml" in result.stdout
    unchanged = _snapshot(folder)
    assert {k: v for k, v in unchanged.items() if k not in ("clean.mcap", "clean.mcap.cut")} == {
        k: v for k, v in before.items() if k != "clean.mcap"
    }
    result = run_qnav("recover", str(folder))
    assert result.returncode == 0, result.stderr
    assert not (folder / "metadata.yaml").exists()


def test_recover_describes_a_rotated_recording_in_its_folder(tmp_path: Path) -> None:
    first = _recording(tmp_path / "run")
    second = first.with_name("recording-0001.mcap")
    data = first.read_bytes()
    second.write_bytes(data[: len(data) // 2])
    (tmp_path / "run" / "metadata.yaml").unlink()
    result = run_qnav("recover", str(second))
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "run" / "metadata.yaml").exists()
    assert is_complete(second)


def test_playback_refuses_a_file_that_is_not_mcap(not_mcap: list[Path]) -> None:
    for path in not_mcap:
        result = run_qnav("playback", str(path), "--connect", "tcp/127.0.0.1:9")
        _refused(result, "playback", str(path), "not an MCAP file")
        assert "messages" not in result.stdout
    into = run_qnav("playback", str(not_mcap[0]), "--into-controller", "--policy", str(POLICY))
    _refused(into, "playback", "not an MCAP file")


def test_playback_still_reads_a_cut_recording(tmp_path: Path) -> None:
    path = _recording(tmp_path / "run")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    kept = len(list(read_recording(path)))
    assert 0 < kept < 20
    result = run_qnav("playback", str(path), "--into-controller", "--policy", str(POLICY))
    assert result.returncode == 0, result.stderr
    assert f"{kept} messages" in result.stdout


def test_record_takes_each_recorder_setting_as_an_option_over_its_file(tmp_path: Path) -> None:
    from qnav.cli import build_parser
    from qnav.contracts.errors import ConfigError
    from qnav.controller.recording import Rotation
    from qnav.recording import recorder_settings

    config = tmp_path / "recorder.toml"
    config.write_text("[rotation]\nmax_duration_s = 60.0\n")
    argv = ["record", "--config", str(config), "--rotation-max-bytes", "1000", "--topics", "scan"]
    settings = recorder_settings(build_parser().parse_args([*argv, "--out", str(tmp_path)]))
    assert settings.rotation == Rotation(max_bytes=1000, max_duration_s=60.0)
    assert settings.topics == ("scan",) and settings.output_dir == str(tmp_path)
    with pytest.raises(ConfigError, match="topics"):
        recorder_settings(build_parser().parse_args(["record", "--topics", "nothing"]))
