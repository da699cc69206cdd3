"""`qnav keys` and `qnav serve`: the desktop side of policy delivery (docs/serve.md)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest

from qnav.contracts import delivery, wire
from qnav.contracts.daemon import free_port
from qnav.contracts.transport import ZenohSettings, open_session
from qnav.serve import PolicyServer, ServeSettings
from tests.conftest import PolicyFactory, with_metadata

ROOT = Path(__file__).resolve().parents[1]
QNAV = str(Path(sys.executable).parent / "qnav")


def _qnav(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [QNAV, *args], capture_output=True, text=True, timeout=120, check=False, cwd=ROOT
    )


@pytest.fixture
def keys(tmp_path: Path) -> Path:
    done = _qnav("keys", str(tmp_path / "keys"))
    assert done.returncode == 0, done.stderr
    return tmp_path / "keys"


def test_qnav_keys_writes_a_private_key_only_its_owner_reads_and_never_overwrites_by_accident(
    keys: Path,
) -> None:
    private, public = keys / delivery.PRIVATE_KEY_FILE, keys / delivery.PUBLIC_KEY_FILE
    assert private.stat().st_mode & 0o077 == 0
    assert b"PRIVATE KEY" in private.read_bytes() and b"PUBLIC KEY" in public.read_bytes()
    delivery.load_private_key(private, "--key")
    delivery.load_public_key(public, "policy.public_key")
    before = private.read_bytes()
    again = _qnav("keys", str(keys))
    assert again.returncode == 2 and "--force" in again.stderr
    assert private.read_bytes() == before
    assert _qnav("keys", str(keys), "--force").returncode == 0
    assert private.read_bytes() != before


def _server(sources: tuple[Path, ...], keys: Path) -> PolicyServer:
    settings = ServeSettings(sources=sources, private_key=keys / delivery.PRIVATE_KEY_FILE)
    return PolicyServer(settings, delivery.load_private_key(settings.private_key, "--key"))


def test_the_server_announces_its_best_tested_file_and_a_better_one_when_it_appears(
    tmp_path: Path, make_policy: PolicyFactory, keys: Path
) -> None:
    runs = tmp_path / "runs"
    for name in ("a", "b", "c"):
        (runs / name).mkdir(parents=True)
    with_metadata(
        make_policy(seed=0), runs / "a" / "policy.onnx", {"qnav.evaluation": {"success": 0.7}}
    )
    with_metadata(
        make_policy(seed=1), runs / "b" / "policy.onnx", {"qnav.evaluation": {"success": 0.9}}
    )
    (runs / "c" / "broken.onnx").write_bytes(b"not an onnx file")
    server = _server((runs,), keys)
    assert server.poll()
    assert server.current is not None
    assert server.current.path == runs / "b" / "policy.onnx"
    assert server.current.announcement.version.startswith("b-policy-")
    assert server.current.announcement.evaluation == {"success": 0.9}
    assert not server.poll()  # nothing changed: nothing to announce anew

    with_metadata(
        make_policy(seed=0), runs / "c" / "policy.onnx", {"qnav.evaluation": {"success": 0.95}}
    )
    assert server.poll()
    assert server.current.path == runs / "c" / "policy.onnx"
    # Every file held is served by version, the best and the others alike.
    for path in (runs / "a" / "policy.onnx", runs / "b" / "policy.onnx"):
        data = path.read_bytes()
        version = delivery.version_of(path.parent.name + "-policy", delivery.sha256_of(data))
        announcement = server._by_version[version].announcement
        chunks = [server.chunk(version, i) for i in range(announcement.chunks)]
        assert b"".join(c for c in chunks if c is not None) == data
        assert server.chunk(version, announcement.chunks) is None
    assert server.chunk("no-such-version", 0) is None


def test_qnav_serve_announces_signed_and_answers_chunks_over_zenoh(
    tmp_path: Path, make_policy: PolicyFactory, keys: Path
) -> None:
    policy = make_policy(seed=0)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server = subprocess.Popen(
        [QNAV, "serve", str(policy), "--key", str(keys / delivery.PRIVATE_KEY_FILE),
         "--listen", endpoint, "--announce-interval-s", "0.2", "--chunk-bytes", "8192"],
        cwd=ROOT, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    heard: list[bytes] = []
    arrived = threading.Event()

    def on_announcement(sample: Any) -> None:
        heard.append(sample.payload.to_bytes())
        arrived.set()

    try:
        with open_session(ZenohSettings(connect=(endpoint,))) as session:
            subscriber = session.declare_subscriber(
                wire.key(wire.POLICY_ANNOUNCEMENT), on_announcement
            )
            assert arrived.wait(60), "no announcement"
            announcement = delivery.decode_announcement(heard[0])
            public = delivery.load_public_key(keys / delivery.PUBLIC_KEY_FILE, "key")
            assert delivery.verify(public, announcement)
            assert announcement.sha256 == delivery.sha256_of(policy.read_bytes())
            assert announcement.chunks > 2
            chunks = []
            for index in range(announcement.chunks):
                replies = list(
                    session.get(delivery.chunk_key(announcement.version, index), timeout=5)
                )
                assert len(replies) == 1 and replies[0].ok is not None
                chunks.append(replies[0].ok.payload.to_bytes())
            assert b"".join(chunks) == policy.read_bytes()
            (wrong,) = list(session.get(delivery.chunk_key("nope-000000000000", 0), timeout=5))
            assert wrong.ok is None and b"no such policy chunk" in wrong.err.payload.to_bytes()
            subscriber.undeclare()
        server.send_signal(signal.SIGTERM)
        _, stderr = server.communicate(timeout=30)
        assert server.returncode == 0, stderr
    finally:
        if server.poll() is None:
            server.kill()
            server.wait()


def test_qnav_serve_refuses_a_missing_source_or_key_naming_it(tmp_path: Path, keys: Path) -> None:
    missing = _qnav(
        "serve", str(tmp_path / "nowhere"), "--key", str(keys / delivery.PRIVATE_KEY_FILE)
    )
    assert missing.returncode == 2 and "source" in missing.stderr and "nowhere" in missing.stderr
    shutil.copy(keys / delivery.PUBLIC_KEY_FILE, tmp_path / "public-as-private.pem")
    wrong = _qnav("serve", str(keys), "--key", str(tmp_path / "public-as-private.pem"),
                  "--connect", f"tcp/127.0.0.1:{free_port()}")  # fmt: skip
    assert wrong.returncode == 2 and "--key" in wrong.stderr
    assert "Traceback" not in wrong.stderr + missing.stderr


def test_a_refusal_names_its_verb_once(tmp_path: Path, keys: Path) -> None:
    # "qnav serve: qnav serve: source 'runs' does not exist" (issue 53).
    missing = _qnav("serve", "nowhere", "--key", str(keys / delivery.PRIVATE_KEY_FILE))
    assert missing.returncode == 2
    assert missing.stderr == "qnav serve: source 'nowhere' does not exist\n"
    again = _qnav("keys", str(keys))
    assert again.returncode == 2
    assert again.stderr.startswith("qnav keys: ") and again.stderr.count("qnav keys") == 1


def _run_folder(root: Path) -> Path:
    """A training run's folder as keep-best leaves it mid-training: settings and best.pt."""
    import torch

    from qnav.contracts.settings import to_toml
    from qnav.training.config import TrainSettings
    from qnav.training.run_folder import RunSettings
    from tests.conftest import policy_network

    run = root / "walls-inertia" / "recurrent-seed0"
    run.mkdir(parents=True)
    world, network = policy_network("walls-inertia", "recurrent", 64, 0)
    (run / "settings.toml").write_text(to_toml(RunSettings(world, TrainSettings(hidden_size=64))))
    torch.save({"online": network.state_dict(), "episodes": 10}, run / "best.pt")
    return run


def test_a_run_is_due_for_export_while_its_keep_best_weights_are_newer_than_its_file(
    tmp_path: Path,
) -> None:
    from qnav.serve import runs_to_export

    run = _run_folder(tmp_path / "runs")
    (tmp_path / "runs" / "loose.onnx").write_bytes(b"")  # files beside runs are no runs
    assert runs_to_export((tmp_path / "runs",)) == [run]
    assert runs_to_export((run,)) == [run]  # a run folder named itself
    (run / "policy.onnx").write_bytes(b"exported")
    later = (run / "best.pt").stat().st_mtime_ns + 10**9
    os.utime(run / "policy.onnx", ns=(later, later))
    assert runs_to_export((tmp_path / "runs",)) == []
    os.utime(run / "best.pt", ns=(later + 10**9, later + 10**9))  # keep-best saved a new best
    assert runs_to_export((tmp_path / "runs",)) == [run]
    os.utime(run / "policy.onnx", ns=(later + 2 * 10**9, later + 2 * 10**9))
    (run / "model.pt").write_bytes(b"")  # the run finished: model.pt is what ships
    os.utime(run / "model.pt", ns=(later + 3 * 10**9, later + 3 * 10**9))
    assert runs_to_export((tmp_path / "runs",)) == [run]


@pytest.mark.slow
def test_the_server_exports_a_runs_keep_best_weights_tests_them_and_announces_the_file(
    tmp_path: Path, keys: Path
) -> None:
    from qnav.serve import runs_to_export

    run = _run_folder(tmp_path / "runs")

    settings = ServeSettings(
        sources=(tmp_path / "runs",),
        private_key=keys / delivery.PRIVATE_KEY_FILE,
        export_runs=10,
    )
    server = PolicyServer(settings, delivery.load_private_key(settings.private_key, "--key"))
    assert server.poll()
    assert server.current is not None and server.current.path == run / "policy.onnx"
    announced = server.current.announcement
    assert announced.evaluation["episodes"] == 10
    assert announced.contract.training_run == str(run)
    assert announced.version.startswith("recurrent-seed0-policy-")
    assert not (run / "policy.onnx.partial").exists()
    assert runs_to_export((tmp_path / "runs",)) == []  # up to date: no export at the next poll
    assert not server.poll()

    # A new best during training (keep-best rewrote best.pt): the run is exported again.
    later = (run / "policy.onnx").stat().st_mtime_ns + 10**9
    os.utime(run / "best.pt", ns=(later, later))
    assert runs_to_export((tmp_path / "runs",)) == [run]


def test_a_rewritten_file_is_served_anew_and_only_the_last_superseded_versions_are_kept(
    tmp_path: Path, make_policy: PolicyFactory, keys: Path
) -> None:
    from qnav.serve import KEEP_SUPERSEDED

    path = tmp_path / "policy.onnx"
    server = _server((tmp_path,), keys)
    versions = []
    for rewrite in range(KEEP_SUPERSEDED + 2):
        success = 0.5 + rewrite / 100
        with_metadata(make_policy(seed=0), path, {"qnav.evaluation": {"success": success}})
        os.utime(path, ns=(10**18 + rewrite * 10**9, 10**18 + rewrite * 10**9))
        assert server.poll()
        assert server.current is not None
        versions.append(server.current.announcement.version)
    assert len(set(versions)) == len(versions)
    served = [v for v in versions if server.chunk(v, 0) is not None]
    assert served == versions[-(KEEP_SUPERSEDED + 1) :]
