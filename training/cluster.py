"""Ray as the study's engine (`--engine ray`): each training run is one Ray task.

A thin shell over `training.study`: the plan, the skip of finished runs, the `qnav train`
arguments of a run, its result record and the progress lines are the study's own, the same as
the local runner's. What is here: joining a cluster (or starting a local Ray instance), sizing
each task by its torch threads, retrying a run whose worker died (it resumes from its run
folder's checkpoint), and, when workers share no disk with the driver, carrying a run's files
back to the driver as it goes.

Ray is an optional extra (`pip install '.[cluster]'`) and is imported only inside functions, so
`import training.study` and this module work without it.
"""

from __future__ import annotations

import os
import socket
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

from qnav.contracts.errors import ConfigError
from qnav.training.study import Command, Outcome, RunSpec, StudySettings, execute

RAY_MISSING = (
    "--engine ray needs Ray, an optional extra: pip install '.[cluster]' "
    "(or run without --engine ray: the local runner needs nothing more)"
)
DEFAULT_GCS_PORT = 6379
"""The port `ray start --head` listens on unless told otherwise."""
DEFAULT_CLIENT_PORT = 10001
"""The Ray Client port of a ray:// address."""
RESUMABLE_FIRST = ("checkpoint.pt", "settings.toml")
"""Sent before the rest of a run folder: a checkpoint never refers to rounds not sent with it."""


@dataclass(frozen=True)
class ClusterSettings:
    """Where and how a study runs on Ray."""

    address: str | None = None
    """A running cluster's head as host:port (ray:// for Ray Client); None: a local instance."""
    local_cpus: int | None = None
    """CPUs of the local instance (None: this machine's cores); unused with an address."""
    object_store_mb: int = 128
    """Object store of the local instance, in MiB (run files pass through it)."""
    artifacts: bool = False
    """Workers share no disk with the driver: runs train in a scratch folder on their node and
    their files (checkpoint as it goes, results, policy, progress) come back to the driver."""
    scratch_dir: str | None = None
    """Workers' folder for runs with `artifacts` (None: the node's temporary folder)."""
    sync_every_s: float = 10.0
    """How often a worker sends a run's changed files to the driver, with `artifacts`."""
    max_retries: int = 3
    """Times a run whose worker died is started again (it resumes from its checkpoint)."""
    connect_timeout_s: float = 15.0
    """How long to wait for the head at `address` to answer before giving up, in seconds."""

    def __post_init__(self) -> None:
        if self.local_cpus is not None and self.local_cpus < 1:
            raise ConfigError(f"--local-cpus = {self.local_cpus}: give at least 1")
        if self.object_store_mb < 64:
            raise ConfigError(f"object_store_mb = {self.object_store_mb}: Ray needs at least 64")
        if self.sync_every_s <= 0:
            raise ConfigError(f"--sync-every-s = {self.sync_every_s}: must be positive")
        if self.max_retries < 0:
            raise ConfigError(f"--max-retries = {self.max_retries}: must be at least 0")
        if self.connect_timeout_s <= 0:
            raise ConfigError(f"--connect-timeout-s = {self.connect_timeout_s}: must be positive")


def parse_address(address: str) -> tuple[str, int] | None:
    """`host:port` or `ray://host[:port]` -> (host, port); `auto` (the cluster this node is part
    of, found by Ray itself) -> None; anything else names --address."""
    if address == "auto":
        return None
    rest, port = address, DEFAULT_GCS_PORT
    if address.startswith("ray://"):
        rest, port = address.removeprefix("ray://"), DEFAULT_CLIENT_PORT
    host, colon, port_text = rest.rpartition(":")
    if not colon:
        host, port_text = rest, str(port)
    try:
        number = int(port_text)
    except ValueError:
        number = 0
    if not host or "/" in host or not 0 < number < 65536:
        raise ConfigError(
            f"--address = {address!r}: expected HOST:PORT (the head's `ray start --head --port`), "
            "ray://HOST:PORT or auto"
        )
    return host.strip("[]"), number


def check_reachable(address: str, timeout_s: float) -> None:
    """Wait until the head at `address` accepts a connection, at most `timeout_s`; if it never
    does, say so, naming --address (before any run starts: Ray's own wait is minutes long)."""
    target = parse_address(address)
    if target is None:
        return
    deadline = time.monotonic() + timeout_s
    while True:
        remaining = deadline - time.monotonic()
        try:
            with socket.create_connection(target, timeout=max(0.1, min(2.0, remaining))):
                return
        except OSError as error:
            if time.monotonic() + 0.5 >= deadline:
                raise ConfigError(
                    f"--address {address}: no Ray head answers at {target[0]}:{target[1]} "
                    f"within {timeout_s:g} s ({error}); no run was started"
                ) from None
        time.sleep(0.5)


def import_ray() -> Any:
    """The ray module, or an error saying to install the extra."""
    try:
        import ray
    except ImportError:
        raise ConfigError(RAY_MISSING) from None
    return ray


# Run files carried between a worker and the driver (workers that share no disk).


def changed_files(run_dir: Path, seen: dict[str, tuple[int, int]]) -> dict[str, bytes]:
    """The files of `run_dir` new or changed since `seen` (relative POSIX path -> content),
    checkpoint and settings first; `seen` is updated. Half-written files (`*.partial*`, every
    writer renames a finished file into place) are left for later."""
    if not run_dir.is_dir():
        return {}
    paths = sorted(p for p in run_dir.rglob("*") if p.is_file() and ".partial" not in p.name)
    paths.sort(key=lambda p: p.name not in RESUMABLE_FIRST or p.parent != run_dir)
    files: dict[str, bytes] = {}
    for path in paths:
        try:
            stat = path.stat()
            stamp = (stat.st_size, stat.st_mtime_ns)
            relative = path.relative_to(run_dir).as_posix()
            if seen.get(relative) == stamp:
                continue
            files[relative] = path.read_bytes()
        except FileNotFoundError:  # replaced meanwhile: the next call sends the new one
            continue
        seen[relative] = stamp
    return files


def write_files(run_dir: Path, files: dict[str, bytes]) -> None:
    """Write carried files into `run_dir`, each whole then renamed into place; a path that
    would leave the folder is refused."""
    for relative, content in files.items():
        parts = PurePosixPath(relative).parts
        if not parts or PurePosixPath(relative).is_absolute() or ".." in parts:
            raise ValueError(f"run file {relative!r} is outside its run folder")
        path = run_dir.joinpath(*parts)
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_name(f".{path.name}.partial")
        partial.write_bytes(content)
        partial.replace(path)


class RunStore:
    """The driver's copy of each run folder, kept by a Ray actor on the driver's node."""

    def __init__(self, run_root: str) -> None:
        self.run_root = Path(run_root)

    def put(self, name: str, files: dict[str, bytes]) -> int:
        write_files(self.run_root / name, files)
        return len(files)

    def get(self, name: str) -> dict[str, bytes]:
        return changed_files(self.run_root / name, {})


def train_task(
    command: Command,
    spec: RunSpec,
    run_dir: str,
    study: StudySettings,
    *,
    store: Any,
    scratch_dir: str | None,
    sync_every_s: float,
) -> tuple[dict[str, Any], str]:
    """One run on a Ray worker: (its result record, the node that ran it). With a store, it
    trains in a scratch folder of its node, first filled from the driver's copy (a retry on
    another node resumes from the last checkpoint sent), and sends changed files as it goes."""
    import ray

    node = str(ray.get_runtime_context().get_node_id())
    if store is None:
        return execute(spec, Path(run_dir), study, command), node
    local = Path(scratch_dir or tempfile.gettempdir()) / "qnav-runs" / node[:12] / spec.name
    if not (local / "checkpoint.pt").exists():
        write_files(local, ray.get(store.get.remote(spec.name)))
    seen: dict[str, tuple[int, int]] = {}
    stop = threading.Event()

    def send() -> None:
        files = changed_files(local, seen)
        if files:
            ray.get(store.put.remote(spec.name, files))

    def keep_sending() -> None:
        while not stop.wait(sync_every_s):
            send()

    sender = threading.Thread(target=keep_sending, name="qnav-run-sync", daemon=True)
    sender.start()
    try:
        result = execute(spec, local, study, command)
    finally:
        stop.set()
        sender.join()
    send()  # the finished run: results, policy, progress, the final checkpoint
    return result, node


@dataclass
class RayEngine:
    """Runs a study's runs as Ray tasks (the study's `Engine`)."""

    run_root: Path
    study: StudySettings
    settings: ClusterSettings
    command: Command
    """The `qnav` command line in process (`qnav.cli.main`), which each task runs `train` with."""
    ray: Any = None
    task: Any = None
    store: Any = None
    running: dict[Any, RunSpec] = field(default_factory=dict)
    ran_on: dict[str, str] = field(default_factory=dict)
    """Run name -> the id of the node that ran it."""
    nodes: dict[str, dict[str, float]] = field(default_factory=dict)
    """Node id -> its resources, as the cluster had them when the engine closed."""

    def __post_init__(self) -> None:
        self.run_root = self.run_root.resolve()
        if self.settings.address:
            check_reachable(self.settings.address, self.settings.connect_timeout_s)
        self.ray = ray = import_ray()
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        if self.settings.address:
            try:
                ray.init(address=self.settings.address, log_to_driver=False)
            except (ConnectionError, RuntimeError, ray.exceptions.RayError) as error:
                raise ConfigError(
                    f"--address {self.settings.address}: could not join the cluster "
                    f"({_first_line(error)}; a head started with token authentication needs "
                    "its token here too, docs/cluster.md); no run was started"
                ) from None
        else:
            ray.init(
                address="local",  # a new instance, never a cluster found on this machine
                num_cpus=self.settings.local_cpus,
                object_store_memory=self.settings.object_store_mb * 2**20,
                include_dashboard=False,
                log_to_driver=False,
            )
        # The task's name (the run's) is its worker's process title while it runs.
        self.task = ray.remote(train_task)
        if self.settings.artifacts:
            from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

            here = ray.get_runtime_context().get_node_id()
            self.store = (
                ray.remote(num_cpus=0)(RunStore)
                .options(scheduling_strategy=NodeAffinitySchedulingStrategy(here, soft=False))
                .remote(str(self.run_root))
            )
        alive = [n for n in ray.nodes() if n["Alive"]]
        largest = max((n["Resources"].get("CPU", 0) for n in alive), default=0)
        if self.study.threads > largest:
            ray.shutdown()
            raise ConfigError(
                f"--threads = {self.study.threads}: no node of the cluster has that many CPUs "
                f"(the most: {largest:g}); a run would never start"
            )
        print(
            f"ray: {len(alive)} node(s), {ray.cluster_resources().get('CPU', 0):g} CPUs; "
            f"each run asks for {self.study.threads}",
            flush=True,
        )
        for node in alive:
            print(f"ray: {describe_node(node)}", flush=True)

    def capacity(self) -> int:
        cpus = float(self.ray.cluster_resources().get("CPU", 0))
        return max(1, int(cpus) // self.study.threads)

    def run_dir(self, spec: RunSpec) -> Path:
        return self.run_root / spec.name

    def start(self, spec: RunSpec) -> None:
        task = self.task.options(
            num_cpus=self.study.threads, max_retries=self.settings.max_retries, name=spec.name
        )
        ref = task.remote(
            self.command,
            spec,
            str(self.run_dir(spec)),
            self.study,
            store=self.store,
            scratch_dir=self.settings.scratch_dir,
            sync_every_s=self.settings.sync_every_s,
        )
        self.running[ref] = spec

    def ended(self) -> list[Outcome]:
        if not self.running:
            return []
        ready, _ = self.ray.wait(list(self.running), num_returns=len(self.running), timeout=0)
        ended: list[Outcome] = []
        for ref in ready:
            spec = self.running.pop(ref)
            try:
                result, node = self.ray.get(ref)
            except self.ray.exceptions.RayError as error:
                ended.append((spec, _first_line(error)))
                continue
            self.ran_on[spec.name] = node
            print(f"       {spec.name} ran on node {node[:12]}", flush=True)
            ended.append((spec, result))
        return ended

    def close(self) -> None:
        if self.ray is None or not self.ray.is_initialized():
            return
        self.nodes = {n["NodeID"]: dict(n["Resources"]) for n in self.ray.nodes() if n["Alive"]}
        self.ray.shutdown()  # stops a local instance; leaves a cluster running


BUILT_IN_RESOURCES = ("CPU", "GPU", "memory", "object_store_memory")


def describe_node(node: dict[str, Any]) -> str:
    """`node 1a2b3c4d5e6f at 10.0.0.2: 2 CPUs, gpu_box` (its id, address, CPUs and the custom
    resources it was started with)."""
    resources: dict[str, float] = node.get("Resources", {})
    custom = sorted(
        name
        for name in resources
        if name not in BUILT_IN_RESOURCES and not name.startswith(("node:", "accelerator_type"))
    )
    return (
        f"node {node['NodeID'][:12]} at {node.get('NodeManagerAddress', '?')}: "
        f"{resources.get('CPU', 0):g} CPUs" + "".join(f", {name}" for name in custom)
    )


def _first_line(error: BaseException) -> str:
    """The last line of a task's error that says something (Ray's own are long tracebacks)."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    return lines[-1] if lines else type(error).__name__
