"""`qnav certs` refuses what it cannot do cleanly: a target that is a file, a folder it cannot
create, or certificates already there (issue 53: each was a Python traceback, or an overwrite).
The real `qnav certs` process, running openssl."""

from __future__ import annotations

import subprocess
from pathlib import Path

from tests.command import run_qnav


def _refused(result: subprocess.CompletedProcess[str], *words: str) -> None:
    """Exit status 2, one line on stderr holding `words`, no traceback."""
    stderr = result.stderr
    assert result.returncode == 2, stderr
    assert "Traceback" not in stderr
    assert len(stderr.strip().splitlines()) == 1, stderr
    assert stderr.startswith("qnav certs: ")
    for word in words:
        assert word in stderr, stderr


def test_certs_into_an_existing_file_is_refused_and_the_file_left_alone(tmp_path: Path) -> None:
    target = tmp_path / "policy.onnx"
    target.write_bytes(b"not a folder")
    _refused(run_qnav("certs", str(target), "--names", "hub"), str(target), "not a folder")
    assert target.read_bytes() == b"not a folder"


def test_certs_into_a_folder_it_cannot_create_is_refused(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("a file where a folder would go")
    target = blocker / "certs"
    _refused(run_qnav("certs", str(target), "--names", "hub"), str(target))
    assert blocker.read_text() == "a file where a folder would go"


def test_certs_never_overwrite_a_ca_unless_forced(tmp_path: Path) -> None:
    folder = tmp_path / "certs"
    made = run_qnav("certs", str(folder), "--names", "hub")
    assert made.returncode == 0, made.stderr
    written = {path.name: path.read_bytes() for path in folder.iterdir()}
    assert "ca-key.pem" in written and "hub.pem" in written
    _refused(run_qnav("certs", str(folder), "--names", "hub"), "ca-key.pem", "--force")
    assert {path.name: path.read_bytes() for path in folder.iterdir()} == written
    forced = run_qnav("certs", str(folder), "--names", "hub", "--force")
    assert forced.returncode == 0, forced.stderr
    assert (folder / "ca-key.pem").read_bytes() != written["ca-key.pem"]
