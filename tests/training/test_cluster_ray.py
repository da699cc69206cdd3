"""Studies on Ray (`make test-cluster`): a local instance with two workers, a worker killed
mid-run, and a two-node cluster on this one machine. Real Ray, real training runs (tiny ones)."""

from __future__ import annotations

import json
import os
import re
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

ray = pytest.importorskip(
    "ray", reason="Ray is not installed: `make test-cluster` installs the [cluster] extra"
)

from qnav.cli import main  # noqa: E402
from qnav.contracts.daemon import free_port  # noqa: E402
from qnav.training.bench_cluster import SMALL_RUN  # noqa: E402
from qnav.training.cluster import ClusterSettings, RayEngine  # noqa: E402
from qnav.training.study import RunSpec, StudySettings, run_progress, run_study  # noqa: E402

pytestmark = pytest.mark.cluster

TINY = ("train.episodes=16", *SMALL_RUN)
"""The smallest runs worth the name: two rounds of 8 episodes, an 8-episode test."""
SPECS = [RunSpec("walls-inertia", "recurrent", seed) for seed in (0, 1)]
RAY_BIN = Path(sys.executable).with_name("ray")


def _comparable(value: Any) -> Any:
    """A result record less what differs between two identical runs: times, the commit."""
    if isinstance(value, dict):
        return {
            k: _comparable(v) for k, v in value.items() if not k.endswith("_s") and k != "commit"
        }
    return value


def _progress_rows(run_dir: Path, keep_times: bool = False) -> list[dict[str, str]]:
    """progress.csv's rows, less the wall times unless `keep_times`."""
    lines = (run_dir / "progress.csv").read_text().splitlines()
    header = lines[0].split(",")
    return [
        {k: v for k, v in zip(header, line.split(","), strict=True) if keep_times or k != "wall_s"}
        for line in lines[1:]
    ]


def _weights(run_dir: Path) -> dict[str, Any]:
    import torch

    saved = torch.load(run_dir / "model.pt", weights_only=False)
    state = saved["online"]
    return {k: v for k, v in state.items() if hasattr(v, "shape")}


def _assert_same_runs(
    ours: tuple[Path, Path], reference: tuple[Path, Path], specs: list[RunSpec]
) -> None:
    """Same result records (less times), same progress (less times), same trained weights."""
    import torch

    for spec in specs:
        mine = json.loads((ours[1] / f"{spec.name}.json").read_text())
        theirs = json.loads((reference[1] / f"{spec.name}.json").read_text())
        assert _comparable(mine) == _comparable(theirs), spec.name
        assert _progress_rows(ours[0] / spec.name) == _progress_rows(reference[0] / spec.name)
        a, b = _weights(ours[0] / spec.name), _weights(reference[0] / spec.name)
        assert a.keys() == b.keys() and a
        assert all(torch.equal(a[k], b[k]) for k in a), spec.name


@pytest.fixture(scope="module")
def local_study(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The tiny study on the local runner (no Ray): the reference every engine must equal."""
    root = tmp_path_factory.mktemp("local")
    run_study(SPECS, root / "runs", results_root=root / "results", jobs=2, threads=1, common=TINY)
    assert len(list((root / "results").glob("*.json"))) == len(SPECS)
    return root / "runs", root / "results"


def _engine_factory(
    runs: Path, settings: ClusterSettings, engines: list[RayEngine]
) -> Callable[[StudySettings], RayEngine]:
    def make(study: StudySettings) -> RayEngine:
        engines.append(RayEngine(runs, study, settings, main))
        return engines[-1]

    return make


def test_a_local_ray_instance_with_two_workers_writes_the_local_runners_results(
    tmp_path: Path, local_study: tuple[Path, Path]
) -> None:
    engines: list[RayEngine] = []
    runs, results = tmp_path / "runs", tmp_path / "results"
    finished = run_study(
        SPECS, runs, results_root=results, threads=1, common=TINY,
        engine=_engine_factory(runs, ClusterSettings(local_cpus=2), engines),
    )  # fmt: skip
    assert sorted(finished, key=SPECS.index) == SPECS  # in whichever order they ended
    assert not ray.is_initialized()  # the local instance is stopped with the study
    _assert_same_runs((runs, results), local_study, SPECS)
    assert set(engines[0].ran_on) == {s.name for s in SPECS}
    # Started again, it skips both finished runs and starts no engine.
    again = _engine_factory(runs, ClusterSettings(local_cpus=2), engines)
    assert run_study(SPECS, runs, results_root=results, common=TINY, engine=again) == []
    assert len(engines) == 1


def test_runs_larger_than_any_node_are_refused_by_name_before_they_start(tmp_path: Path) -> None:
    from qnav.contracts.errors import ConfigError

    with pytest.raises(ConfigError, match="--threads = 2: no node of the cluster has that many"):
        run_study(
            SPECS, tmp_path / "runs", results_root=tmp_path / "results", threads=2, common=TINY,
            engine=_engine_factory(tmp_path / "runs", ClusterSettings(local_cpus=1), []),
        )  # fmt: skip
    assert not ray.is_initialized()
    assert not (tmp_path / "runs").exists()


def _descendants(root: int) -> list[int]:
    """Our own child processes, all generations (Ray's workers are the raylet's children)."""
    parents: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            parents[int(entry.name)] = int(fields[1])
    found, frontier = [], [root]
    while frontier:
        parent = frontier.pop()
        children = [p for p, pp in parents.items() if pp == parent]
        found += children
        frontier += children
    return found


def _worker_running(name: str) -> int | None:
    """The pid of our Ray worker whose process title names the run `name`, if any."""
    for pid in _descendants(os.getpid()):
        try:
            title = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ")
        except OSError:
            continue
        if title.startswith(b"ray::") and name.encode() in title:
            return pid
    return None


@pytest.mark.parametrize("artifacts", [False, True], ids=["shared-disk", "artifacts"])
def test_a_run_whose_worker_is_killed_mid_run_is_retried_and_resumes(
    tmp_path: Path, artifacts: bool
) -> None:
    """SIGKILL to the worker training a run, once it has checkpointed at least two rounds: Ray
    retries the task and the run resumes from its checkpoint (with --artifacts, from the copy
    that came back to the driver: the worker's scratch folder is deleted after the kill)."""
    victim = RunSpec("walls-inertia", "recurrent", 0, overrides=("train.episodes=64",))
    specs = [victim, SPECS[1]]
    runs, results, scratch = tmp_path / "runs", tmp_path / "results", tmp_path / "scratch"
    killed: dict[str, Any] = {}

    def kill_mid_run() -> None:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            progress = run_progress(runs / victim.name)
            pid = _worker_running(victim.name)
            if progress and 16 <= progress[0] < progress[1] and pid:
                rows = _progress_rows(runs / victim.name, keep_times=True)
                os.kill(pid, signal.SIGKILL)
                for folder in scratch.glob(f"qnav-runs/*/{victim.name}"):
                    shutil.rmtree(folder)
                killed.update(pid=pid, rows=rows)
                return
            time.sleep(0.02)

    killer = threading.Thread(target=kill_mid_run, daemon=True)
    killer.start()
    settings = ClusterSettings(
        local_cpus=2, max_retries=2, artifacts=artifacts, scratch_dir=str(scratch), sync_every_s=0.5
    )
    finished = run_study(
        specs, runs, results_root=results, threads=1, common=TINY,
        engine=_engine_factory(runs, settings, []),
    )  # fmt: skip
    killer.join(timeout=5)
    assert killed, "the run finished before its worker could be killed mid-run"
    assert set(finished) == set(specs)
    assert json.loads((results / f"{victim.name}.json").read_text())["episodes"] == 64
    rows = _progress_rows(runs / victim.name, keep_times=True)
    assert [int(r["episodes"]) for r in rows] == list(range(8, 65, 8))
    # Resumed, not started over: the rounds checkpointed before the kill keep their recorded
    # wall times (a run started afresh measures new ones). The last row seen may be one round
    # ahead of the checkpoint it resumed from.
    assert len(killed["rows"]) >= 2
    assert rows[: len(killed["rows"]) - 1] == killed["rows"][:-1]


@pytest.fixture
def two_nodes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """A head and a second node on this machine (1 CPU each, resources node_a and node_b),
    each `ray start --block` in a process group of its own, ended by that group's id. The
    cluster's token is this test's own (in the environment of the nodes and the driver), not
    whatever ~/.ray/auth_token holds."""
    port = free_port()
    common = ["--num-cpus=1", "--object-store-memory=100000000", "--block", "--disable-usage-stats"]
    token = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(32)}
    for name, value in token.items():
        monkeypatch.setenv(name, value)
    env = os.environ | {"RAY_USAGE_STATS_ENABLED": "0"}
    nodes: list[subprocess.Popen[bytes]] = []
    logs = [(tmp_path / f"node{i}.log").open("wb") for i in range(2)]
    try:
        nodes.append(subprocess.Popen(
            [str(RAY_BIN), "start", "--head", f"--port={port}", "--node-ip-address=127.0.0.1",
             "--include-dashboard=false", '--resources={"node_a": 1}', *common],
            stdout=logs[0], stderr=subprocess.STDOUT, start_new_session=True, env=env,
        ))  # fmt: skip
        deadline = time.monotonic() + 120
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                assert time.monotonic() < deadline, (tmp_path / "node0.log").read_text()
                assert nodes[0].poll() is None, (tmp_path / "node0.log").read_text()
                time.sleep(0.5)
        nodes.append(subprocess.Popen(
            [str(RAY_BIN), "start", f"--address=127.0.0.1:{port}", "--node-ip-address=127.0.0.1",
             '--resources={"node_b": 1}', *common],
            stdout=logs[1], stderr=subprocess.STDOUT, start_new_session=True, env=env,
        ))  # fmt: skip
        while "Ray runtime started" not in (tmp_path / "node1.log").read_text():
            assert time.monotonic() < deadline, (tmp_path / "node1.log").read_text()
            assert nodes[1].poll() is None, (tmp_path / "node1.log").read_text()
            time.sleep(0.5)
        yield f"127.0.0.1:{port}"
    finally:
        for node in reversed(nodes):
            _end_group(node)
        for log in logs:
            log.close()


def _end_group(process: subprocess.Popen[bytes]) -> None:
    """SIGTERM to the node's own process group (ray start stops what it started), SIGKILL what
    is left after a while."""
    for sig, wait_s in ((signal.SIGTERM, 30), (signal.SIGKILL, 10)):
        try:
            os.killpg(process.pid, sig)
        except ProcessLookupError:
            return
        try:
            process.wait(timeout=wait_s)
            time.sleep(1)
        except subprocess.TimeoutExpired:
            continue


def test_a_two_node_cluster_on_this_machine_runs_the_study_across_both_nodes(
    tmp_path: Path, two_nodes: str, local_study: tuple[Path, Path]
) -> None:
    """`qnav sweep --engine ray --address` (a process of its own, as a user runs it), workers
    sharing no disk with the driver (--artifacts): one run on each node, the driver's folders
    filled, the same results as the local runner's."""
    runs, results = tmp_path / "driver" / "runs", tmp_path / "driver" / "results"
    tiny = [arg for setting in TINY for arg in ("--set", setting)]
    done = subprocess.run(
        [sys.executable, "-m", "qnav", "sweep", "--seeds", "0,1", "--threads", "1", *tiny,
         "--engine", "ray", "--address", two_nodes, "--artifacts",
         "--scratch-dir", str(tmp_path / "scratch"), "--runs-dir", str(runs),
         "--results-dir", str(results)],
        check=False, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    nodes = dict(re.findall(r"^ray: node (\w+) at \S+ \d+ CPUs, (node_[ab])$", done.stdout, re.M))
    assert sorted(nodes.values()) == ["node_a", "node_b"], done.stdout
    ran_on = dict(re.findall(r"^\s+(\S+) ran on node (\w+)$", done.stdout, re.M))
    assert sorted(nodes[node] for node in ran_on.values()) == ["node_a", "node_b"], done.stdout
    assert sorted(ran_on) == sorted(s.name for s in SPECS)
    for spec in SPECS:
        for name in ("results.json", "model.pt", "progress.csv", "checkpoint.pt", "settings.toml"):
            assert (runs / spec.name / name).exists(), (spec.name, name)
    # Each run trained in its node's scratch folder, not in the driver's.
    assert len(list((tmp_path / "scratch" / "qnav-runs").glob("*/*"))) == len(SPECS)
    _assert_same_runs((runs, results), local_study, SPECS)
