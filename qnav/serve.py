"""`qnav serve` and `qnav keys`: the desktop side of policy delivery (contracts.delivery).

`qnav serve SOURCE...` holds every exported policy file it finds in its sources (an .onnx file,
or a folder searched for them: a run folder, or a folder of run folders), polls them for new or
rewritten files, and

- answers `get(POLICY_FILE/VERSION/INDEX)` with that chunk of that version's file, for every
  version it has held since it started;
- announces the best file it holds (highest test success in the file's own evaluation, then the
  newest) on `POLICY_ANNOUNCEMENT` whenever the best changes, and again every
  `announce_interval_s`, signed with the desktop's private key.

A file that is not a readable qnav policy (half written, an older format, someone else's ONNX)
is skipped with one warning until it changes. The bytes served are the bytes hashed: a file
rewritten after it was read is read again as a new version, never served half old, half new.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from qnav.contracts import delivery, wire
from qnav.contracts.daemon import stop_on_signals
from qnav.contracts.errors import ConfigError, PolicyFileError
from qnav.contracts.policy_file import PolicyContract
from qnav.contracts.transport import StoppedError, ZenohSettings, open_session
from qnav.controller.onnx_file import parse_onnx
from qnav.options import add_print_config, config_text, settings_from_args
from qnav.verbs.parser import Verbs, flag, settings_options, verb, zenoh_options

log = logging.getLogger("qnav.serve")


@dataclass(frozen=True)
class ServeSettings:
    """What `qnav serve` serves and how."""

    sources: tuple[Path, ...]
    """Policy files (.onnx) and folders searched for them (run folders, or their parents)."""
    private_key: Path
    """The Ed25519 private key (PEM) announcements are signed with (`qnav keys`)."""
    zenoh: ZenohSettings = field(default_factory=ZenohSettings)
    """How to join the zenoh network (the car's hub, or listen for it)."""
    poll_s: float = 2.0
    """Seconds between looks at the sources for new or changed files."""
    announce_interval_s: float = 2.0
    """The current announcement is put again this often, for cars that join late."""
    chunk_bytes: int = delivery.DEFAULT_CHUNK_BYTES
    """Size of the chunks files are served in."""
    export_runs: int = 0
    """Episodes of the test protocol for exporting training runs found in the sources (0: do
    not export, serve only the .onnx files there). A run folder whose keep-best weights
    (model.pt when finished, else best.pt) are newer than its policy.onnx is exported to
    it, tested, and then served like any file."""

    def __post_init__(self) -> None:
        if not self.sources:
            raise ConfigError("name at least one policy file or folder (SOURCE)")
        for source in self.sources:
            if not source.exists():
                raise ConfigError(f"source {str(source)!r} does not exist")
        if not 0.01 <= self.poll_s <= 3600:
            raise ConfigError(f"--poll-s = {self.poll_s} is out of range: allowed [0.01, 3600]")
        if not 0.01 <= self.announce_interval_s <= 3600:
            raise ConfigError(
                f"--announce-interval-s = {self.announce_interval_s} is out of range: "
                "allowed [0.01, 3600]"
            )
        if not 0 <= self.export_runs <= 100_000:
            raise ConfigError(
                f"--export-runs = {self.export_runs} is out of range: allowed [0, 100000]"
            )
        if not 1024 <= self.chunk_bytes <= delivery.MAX_CHUNK_BYTES:
            raise ConfigError(
                f"--chunk-bytes = {self.chunk_bytes} is out of range: allowed "
                f"[1024, {delivery.MAX_CHUNK_BYTES}]"
            )


@dataclass(frozen=True)
class Held:
    """One policy file as read: its bytes, contract and signed announcement."""

    path: Path
    """Where it was read from."""
    stamp: tuple[int, int]
    """(mtime in ns, size) when read: a change means read it again."""
    data: bytes
    """The file's bytes (what is served and hashed)."""
    announcement: delivery.Announcement
    """Its signed announcement."""

    @property
    def rank(self) -> tuple[float, int]:
        """Better first by test success (a file without one ranks last), then the newest."""
        return (self.announcement.evaluation.get("success", -1.0), self.stamp[0])


KEEP_SUPERSEDED = 4
"""Versions still served after their file was rewritten (a car may be in the middle of one)."""


def find_policy_files(sources: tuple[Path, ...]) -> list[Path]:
    """Every .onnx file named in or found under the sources, sorted."""
    found: set[Path] = set()
    for source in sources:
        if source.is_file():
            found.add(source)
        elif source.is_dir():
            found.update(p for p in source.rglob("*.onnx") if p.is_file())
    return sorted(found)


EXPORTED_NAME = "policy.onnx"
"""What a run's export is called inside its folder (`--export-runs`)."""


def runs_to_export(sources: tuple[Path, ...]) -> list[Path]:
    """Run folders under the sources whose keep-best weights are newer than their export."""
    runs = {
        settings.parent
        for source in sources
        if source.is_dir()
        for settings in [source / "settings.toml", *source.rglob("*/settings.toml")]
        if settings.is_file()
    }
    stale = []
    for run in sorted(runs):
        weights = best_weights(run)
        exported = run / EXPORTED_NAME
        if weights is not None and (
            not exported.exists() or exported.stat().st_mtime_ns < weights.stat().st_mtime_ns
        ):
            stale.append(run)
    return stale


def best_weights(run: Path) -> Path | None:
    """The run's weights to ship: model.pt once finished (keep-best applied), else best.pt
    (the best validation so far), else None."""
    return next((run / n for n in ("model.pt", "best.pt") if (run / n).is_file()), None)


def export_best(run: Path, episodes: int) -> Path:
    """Export the run's keep-best weights to RUN/policy.onnx and test the file (`episodes`
    of the test protocol); the file appears only once whole and tested (needs qnav[train])."""
    from qnav.training.export import export_run

    weights = best_weights(run)
    if weights is None:
        raise ConfigError(f"{run} has neither model.pt nor best.pt to export")
    partial = run / (EXPORTED_NAME + ".partial")
    export_run(run, partial, eval_episodes=episodes, progress=False, weights=weights)
    partial.replace(run / EXPORTED_NAME)
    return run / EXPORTED_NAME


def contract_of(data: bytes, name: str) -> PolicyContract:
    """The contract in a policy file's bytes; `PolicyFileError` if it holds none."""
    return PolicyContract.from_metadata(parse_onnx(data, name).metadata, name)


def best(held: list[Held]) -> Held | None:
    """The file to announce (`Held.rank`)."""
    return max(held, key=lambda h: h.rank, default=None)


class PolicyServer:
    """The server's state and its zenoh side; `poll` and `announce` are called by `run`'s loop
    (or a test), the queryable answers from zenoh's threads."""

    def __init__(self, settings: ServeSettings, private_key: Any) -> None:
        self.settings = settings
        self.private_key = private_key
        self.namespace = settings.zenoh.namespace
        self._lock = threading.Lock()
        self._by_path: dict[Path, Held] = {}
        self._by_version: dict[str, Held] = {}
        self._skipped: dict[Path, tuple[int, int]] = {}
        self._export_failed: dict[Path, int] = {}
        """Runs whose export failed, with the weights' mtime then (tried again once they change)."""
        self.current: Held | None = None
        self.announcements = 0
        """Announcements put so far."""
        self.chunks_served = 0
        """Chunk queries answered with data."""

    def poll(self) -> bool:
        """Export runs with new best weights (`export_runs`), read new and changed files;
        returns whether the best file changed."""
        if self.settings.export_runs:
            for run in runs_to_export(self.settings.sources):
                self._export(run)
        for path in find_policy_files(self.settings.sources):
            try:
                info = path.stat()
            except OSError:
                continue  # removed since it was listed
            stamp = (info.st_mtime_ns, info.st_size)
            known = self._by_path.get(path)
            if (known is not None and known.stamp == stamp) or self._skipped.get(path) == stamp:
                continue
            try:
                data = path.read_bytes()
                contract = contract_of(data, str(path))
            except (OSError, PolicyFileError) as error:
                self._skipped[path] = stamp
                log.warning("skipping %s: %s", path, error)
                continue
            self._skipped.pop(path, None)
            name = path.parent.name + "-" + path.stem if path.stem == "policy" else path.stem
            announcement = delivery.make_announcement(
                data, name, contract, self.private_key, self.settings.chunk_bytes
            )
            held = Held(path, stamp, data, announcement)
            with self._lock:
                self._by_path[path] = held
                self._by_version.pop(announcement.version, None)
                self._by_version[announcement.version] = held  # the newest read last
                self._forget_superseded()
            log.info(
                "holding %s from %s (success %s)",
                announcement.version,
                path,
                announcement.evaluation.get("success", "not tested"),
            )
        chosen = best(list(self._by_path.values()))
        changed = chosen is not None and (
            self.current is None or chosen.announcement.version != self.current.announcement.version
        )
        self.current = chosen
        return changed

    def _export(self, run: Path) -> None:
        weights = best_weights(run)
        stamp = weights.stat().st_mtime_ns if weights is not None else 0
        if self._export_failed.get(run) == stamp:
            return
        log.info("exporting %s (its keep-best weights are newer than its export)", run)
        try:
            export_best(run, self.settings.export_runs)
        except Exception as error:  # a run's files may be mid-write: tried again once changed
            self._export_failed[run] = stamp
            log.warning("cannot export %s: %s", run, error)
        else:
            self._export_failed.pop(run, None)

    def _forget_superseded(self) -> None:
        """Keep the versions of the files as they are now and the `KEEP_SUPERSEDED` last read
        before them (a car may be fetching one); forget older ones (their bytes are in memory)."""
        current = {held.announcement.version for held in self._by_path.values()}
        superseded = [v for v in self._by_version if v not in current]
        for version in superseded[: max(0, len(superseded) - KEEP_SUPERSEDED)]:
            del self._by_version[version]

    def chunk(self, version: str, index: int) -> bytes | None:
        """Chunk `index` of `version`, or None if there is no such chunk."""
        with self._lock:
            held = self._by_version.get(version)
        if held is None or index >= held.announcement.chunks:
            return None
        size = held.announcement.chunk_bytes
        return held.data[index * size : (index + 1) * size]

    def on_query(self, query: Any) -> None:
        """Answer one chunk query (zenoh's thread)."""
        parsed = delivery.parse_chunk_key(str(query.key_expr), self.namespace)
        data = None if parsed is None else self.chunk(*parsed)
        if data is None:
            query.reply_err(f"no such policy chunk: {query.key_expr}".encode())
            return
        query.reply(query.key_expr, data)
        with self._lock:
            self.chunks_served += 1

    def announcement_payload(self) -> bytes | None:
        """The payload announcing the current best file (None: none held)."""
        if self.current is None:
            return None
        return delivery.encode_announcement(self.current.announcement)


def run(settings: ServeSettings, stop: threading.Event) -> None:
    """Serve until `stop` is set."""
    import zenoh

    server = PolicyServer(settings, delivery.load_private_key(settings.private_key, "--key"))
    try:
        session = open_session(settings.zenoh, stop)
    except StoppedError:
        return  # stopped while waiting for zenoh: nothing was served
    with session:
        queryable = session.declare_queryable(
            wire.key(delivery.POLICY_FILE, server.namespace) + "/**", server.on_query
        )
        announcer = session.declare_publisher(
            wire.key(delivery.POLICY_ANNOUNCEMENT, server.namespace),
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        log.info(
            "serving %s; announcing on %s",
            ", ".join(str(s) for s in settings.sources),
            wire.key(delivery.POLICY_ANNOUNCEMENT, server.namespace),
        )
        next_poll = next_announcement = time.monotonic()
        while not stop.is_set():
            now = time.monotonic()
            if now >= next_poll:
                next_poll = now + settings.poll_s
                if server.poll() and server.current is not None:
                    log.info("announcing %s", server.current.announcement.version)
                    next_announcement = now
            if now >= next_announcement:
                next_announcement = now + settings.announce_interval_s
                payload = server.announcement_payload()
                if payload is not None:
                    announcer.put(payload)
                    server.announcements += 1
            stop.wait(max(0.0, min(next_poll, next_announcement) - time.monotonic()))
        announcer.undeclare()
        queryable.undeclare()


def serve_verb(args: argparse.Namespace) -> int:
    """Handler of `qnav serve`."""
    logging.basicConfig(
        level=logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    zenoh_settings = ZenohSettings(
        listen=tuple(args.listen or ()),
        connect=tuple(args.connect or (() if args.listen else ZenohSettings().connect)),
        namespace=args.namespace or "",
        config_file=str(args.zenoh_config or ""),
    )
    settings = settings_from_args(
        ServeSettings(sources=tuple(args.sources), private_key=args.key, zenoh=zenoh_settings),
        args,
    )
    if args.print_config:
        print(config_text(settings), end="")
        return 0
    with stop_on_signals(logger=log) as stop:
        run(settings, stop)
    return 0


def keys_verb(args: argparse.Namespace) -> int:
    """Handler of `qnav keys`: an Ed25519 key pair for signing policies."""
    folder: Path = args.folder
    private_path = folder / delivery.PRIVATE_KEY_FILE
    public_path = folder / delivery.PUBLIC_KEY_FILE
    if (private_path.exists() or public_path.exists()) and not args.force:
        raise ConfigError(
            f"{private_path} or {public_path} exists; --force replaces them (every car "
            "then needs the new public key)"
        )
    folder.mkdir(parents=True, exist_ok=True)
    private, public = delivery.generate_key_pair()
    # Created with owner-only permissions, never readable by others even for a moment.
    descriptor = os.open(private_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(descriptor, "wb") as handle:
        handle.write(private)
    private_path.chmod(0o600)
    public_path.write_bytes(public)
    print(f"wrote {private_path} (keep it on the desktop: it signs policies)")
    print(f"wrote {public_path} (copy it to the car: [policy] public_key)")
    return 0


def add_verbs(verbs: Verbs) -> None:
    """`qnav keys` and `qnav serve`: their options."""
    _add_keys(verbs)
    _add_serve(verbs)


def _add_keys(verbs: Verbs) -> None:
    """`qnav keys FOLDER`."""
    parser = verb(
        verbs,
        keys_verb,
        "keys",
        help="an Ed25519 key pair that signs the policies qnav serve delivers",
    )
    parser.add_argument("folder", type=Path, help="where to write the key pair (e.g. keys/)")
    flag(parser, "--force", "replace an existing key pair")


def _add_serve(verbs: Verbs) -> None:
    """`qnav serve SOURCE... --key FILE`."""
    parser = verb(
        verbs,
        serve_verb,
        "serve",
        help="serve exported policies to cars over zenoh, announcing the best (docs/serve.md)",
    )
    parser.add_argument(
        "sources",
        nargs="+",
        type=Path,
        metavar="SOURCE",
        help="policy files (.onnx), or folders searched for them (run folders, runs/)",
    )
    parser.add_argument(
        "--key",
        type=Path,
        required=True,
        metavar="FILE",
        help="the Ed25519 private key that signs announcements (qnav keys DIR)",
    )
    settings_options(
        parser,
        "qnav.serve:ServeSettings",
        "serving",
        skip=("sources", "private_key", "zenoh"),
    )
    parser.add_argument(
        "--zenoh-config",
        type=Path,
        metavar="FILE",
        help="a zenoh JSON5 configuration (TLS, access control: qnav certs writes "
        "zenoh-server.json5)",
    )
    zenoh_options(parser)
    add_print_config(parser)
