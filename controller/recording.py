"""Recordings: the project's zenoh traffic written to MCAP, and read back.

Files use MCAP's `ros2` profile: one `ros2msg` schema per message type (the type's full
definition, as rosbag2 writes it) and `cdr` message encoding, with each payload stored exactly as
it came off the wire. Foxglove and rosbag2's MCAP storage open them.

Messages are written in log-time order: the recorder stamps each one under the writer's lock,
never earlier than the one before, so readers that need order without a chunk index (rosbags'
`AnyReader`) take the files as they are. A recording folder is also a rosbag2 bag: a
`metadata.yaml` (rosbag2 format version 8, MCAP storage) lists its files and topics, written
when the recording ends (and by `recover`).

Nothing is lost to a crash: messages are written without chunking and flushed to the operating
system after each one, so a recorder killed with SIGKILL leaves a file holding every message up
to its last complete record. `read_recording` (and so `qnav playback`) reads such a file as it
is; other readers need its summary and footer, which `recover` (`qnav recover`) writes, keeping
the cut original as `NAME.mcap.cut`. Files rotate by size or duration; each is complete and
self-describing on its own.
"""

from __future__ import annotations

import json
import logging
import struct
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import IO, Any, NamedTuple

from qnav.contracts.daemon import RateLimitedLog
from qnav.contracts.errors import ConfigError
from qnav.contracts.health import Heartbeat
from qnav.contracts.transport import StoppedError, ZenohSettings, open_session
from qnav.contracts.wire import TOPICS, Topic, key

log = logging.getLogger(__name__)

PROFILE = "ros2"
SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"


class RecordedMessage(NamedTuple):
    """One message of a recording."""

    topic: str
    """ROS topic name with its leading slash, as rosbag2 names channels (e.g. /scan)."""
    ros_type: str
    """Message type (e.g. sensor_msgs/msg/LaserScan)."""
    log_time_ns: int
    """When the recorder received it (wall clock, ns since the epoch)."""
    payload: bytes
    """The CDR bytes as they came off the wire."""


@cache
def message_definition(ros_type: str) -> bytes:
    """The `ros2msg` schema text of a type, with its dependencies, as rosbag2 stores it."""
    from rosbags.typesys import Stores, get_typestore

    text, _ = get_typestore(Stores.ROS2_HUMBLE).generate_msgdef(ros_type, ros_version=2)
    return text.encode()


def topic_of(ros_topic_name: str) -> Topic | None:
    """The project topic with this name (with or without the leading slash)."""
    name = ros_topic_name.lstrip("/")
    return next((t for t in TOPICS if t.name == name), None)


@dataclass(frozen=True)
class Rotation:
    """When a recording moves on to a new file."""

    SECTION = "rotation"

    max_bytes: int = 256 * 1024 * 1024
    """Start a new file once the current one holds this many bytes (0: never)."""
    max_duration_s: float = 0.0
    """Start a new file after this many seconds (0: never)."""


class McapWriter:
    """Writes messages to `<stem>-<index>.mcap` files in a folder, rotating as told.

    Thread-safe: zenoh delivers samples on its own threads.
    """

    def __init__(
        self, folder: Path, stem: str = "recording", rotation: Rotation | None = None
    ) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.stem = stem
        self.rotation = rotation or Rotation()
        self.files: list[Path] = []
        self.messages = 0
        self._lock = threading.Lock()
        self._writer: Any = None
        self._stream: IO[bytes] | None = None
        self._channels: dict[tuple[str, str], int] = {}
        self._opened_at = 0.0
        self._last_log_time_ns = 0

    def write(
        self, topic: str, ros_type: str, payload: bytes, log_time_ns: int | None = None
    ) -> None:
        """Append one message (topic with its leading slash) and flush it to the OS.

        Without `log_time_ns` the message is stamped now, under the writer's lock and never
        earlier than the previous one, so a file's messages are in log-time order whichever
        thread delivers them."""
        with self._lock:
            if log_time_ns is None:
                log_time_ns = max(time.time_ns(), self._last_log_time_ns)
            self._last_log_time_ns = max(self._last_log_time_ns, log_time_ns)
            if self._writer is None or self._due_for_rotation():
                self._open_next()
            channel = self._channels.get((topic, ros_type))
            if channel is None:
                schema = self._writer.register_schema(
                    ros_type, SCHEMA_ENCODING, message_definition(ros_type)
                )
                channel = self._writer.register_channel(topic, MESSAGE_ENCODING, schema)
                self._channels[(topic, ros_type)] = channel
            self._writer.add_message(
                channel,
                log_time=log_time_ns,
                data=payload,
                publish_time=log_time_ns,
                sequence=self.messages,
            )
            assert self._stream is not None
            self._stream.flush()
            self.messages += 1

    def close(self) -> None:
        """Finish the current file (summary and footer) and write the folder's rosbag2
        metadata.yaml; safe to call twice."""
        with self._lock:
            self._finish()
            if self.files:
                write_rosbag_metadata(self.folder)

    def __enter__(self) -> McapWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _due_for_rotation(self) -> bool:
        assert self._stream is not None
        rotation = self.rotation
        too_big = rotation.max_bytes > 0 and self._stream.tell() >= rotation.max_bytes
        too_old = (
            rotation.max_duration_s > 0
            and time.monotonic() - self._opened_at >= rotation.max_duration_s
        )
        return too_big or too_old

    def _open_next(self) -> None:
        from mcap.writer import Writer

        self._finish()
        path = self.folder / f"{self.stem}-{len(self.files):04d}.mcap"
        self._stream = path.open("wb")
        # No chunks: every record reaches the file as soon as it is written.
        self._writer = Writer(self._stream, use_chunking=False)
        self._writer.start(profile=PROFILE, library="qnav")
        self._channels = {}
        self._opened_at = time.monotonic()
        self.files.append(path)
        log.info("recording to %s", path)

    def _finish(self) -> None:
        if self._writer is not None:
            self._writer.finish()
            self._writer = None
        if self._stream is not None:
            self._stream.close()
            self._stream = None


def read_recording(path: Path) -> Iterator[RecordedMessage]:
    """Messages of one MCAP file in file order, up to its last complete record.

    A file cut short (a recorder killed mid-write) ends quietly after its last whole message.
    """
    from mcap.exceptions import McapError
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader

    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, str]] = {}
    with Path(path).open("rb") as stream:
        records = StreamReader(stream, skip_magic=False).records
        while True:
            try:
                record = next(records)
            except StopIteration:
                return
            except (McapError, EOFError, ValueError, OSError, struct.error) as error:
                log.info("%s ends in an incomplete record (%s); read up to it", path, error)
                return
            if isinstance(record, Schema):
                schemas[record.id] = record.name
            elif isinstance(record, Channel):
                channels[record.id] = (record.topic, schemas.get(record.schema_id, ""))
            elif isinstance(record, Message) and record.channel_id in channels:
                topic, ros_type = channels[record.channel_id]
                yield RecordedMessage(topic, ros_type, record.log_time, bytes(record.data))


MCAP_MAGIC = b"\x89MCAP0\r\n"
"""The bytes a complete MCAP file starts and ends with."""


def is_complete(path: Path) -> bool:
    """The file ends with MCAP's footer magic and its summary reads (it was closed properly)."""
    from mcap.reader import make_reader

    path = Path(path)
    with path.open("rb") as stream:
        if path.stat().st_size < 2 * len(MCAP_MAGIC):
            return False
        stream.seek(-len(MCAP_MAGIC), 2)
        if stream.read() != MCAP_MAGIC:
            return False
        stream.seek(0)
        try:
            return make_reader(stream).get_summary() is not None
        except Exception:  # a damaged summary is as bad as none
            return False


def recover(path: Path) -> int:
    """Rewrite a cut MCAP file (a recorder killed mid-write) as a complete one holding every
    complete message, in place; the original is kept beside it as `NAME.mcap.cut`. Returns the
    messages kept. Run `write_rosbag_metadata` on the folder afterwards."""
    path = Path(path)
    messages = list(read_recording(path))
    partial = path.with_name(path.name + ".recovering")
    with partial.open("wb") as stream:
        from mcap.writer import Writer

        writer = Writer(stream)
        writer.start(profile=PROFILE, library="qnav recover")
        channels: dict[tuple[str, str], int] = {}
        for index, message in enumerate(messages):
            channel = channels.get((message.topic, message.ros_type))
            if channel is None:
                schema = writer.register_schema(
                    message.ros_type, SCHEMA_ENCODING, message_definition(message.ros_type)
                )
                channel = writer.register_channel(message.topic, MESSAGE_ENCODING, schema)
                channels[(message.topic, message.ros_type)] = channel
            writer.add_message(
                channel,
                log_time=message.log_time_ns,
                data=message.payload,
                publish_time=message.log_time_ns,
                sequence=index,
            )
        writer.finish()  # type: ignore[no-untyped-call]
    path.replace(path.with_name(path.name + ".cut"))
    partial.replace(path)
    return len(messages)


def write_rosbag_metadata(folder: Path) -> Path:
    """The folder's `metadata.yaml` as rosbag2 writes it for MCAP storage (format version 8),
    from its `*.mcap` files, so `rosbags.rosbag2.Reader(folder)` and `ros2 bag info` open it."""
    folder = Path(folder)
    files = sorted(folder.glob("*.mcap"))
    per_file: list[dict[str, Any]] = []
    topics: dict[str, dict[str, Any]] = {}
    for path in files:
        messages = list(read_recording(path))
        times = [m.log_time_ns for m in messages]
        per_file.append(
            {
                "path": path.name,
                "starting_time": {"nanoseconds_since_epoch": min(times, default=0)},
                "duration": {"nanoseconds": (max(times) - min(times)) if times else 0},
                "message_count": len(messages),
            }
        )
        for message in messages:
            entry = topics.setdefault(message.topic, {"type": message.ros_type, "count": 0})
            entry["count"] += 1
    starts = [f["starting_time"]["nanoseconds_since_epoch"] for f in per_file if f["message_count"]]
    ends = [
        f["starting_time"]["nanoseconds_since_epoch"] + f["duration"]["nanoseconds"]
        for f in per_file
        if f["message_count"]
    ]
    start = min(starts, default=0)
    info = {
        "version": 8,
        "storage_identifier": "mcap",
        "duration": {"nanoseconds": (max(ends) - start) if ends else 0},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": sum(f["message_count"] for f in per_file),
        "topics_with_message_count": [
            {
                "topic_metadata": {
                    "name": name,
                    "type": entry["type"],
                    "serialization_format": MESSAGE_ENCODING,
                    "offered_qos_profiles": "",
                    "type_description_hash": "",
                },
                "message_count": entry["count"],
            }
            for name, entry in sorted(topics.items())
        ],
        "compression_format": "",
        "compression_mode": "",
        "relative_file_paths": [path.name for path in files],
        "files": per_file,
        "custom_data": {},
        "ros_distro": "",
    }
    target = folder / "metadata.yaml"
    partial = folder / "metadata.yaml.partial"
    # JSON is YAML (1.2, flow style): every YAML reader takes it, with no YAML library here.
    partial.write_text(json.dumps({"rosbag2_bagfile_information": info}, indent=2) + "\n")
    partial.replace(target)
    return target


def read_recordings(paths: list[Path]) -> Iterator[RecordedMessage]:
    """Messages of several files (a rotated recording), in order of log time."""
    messages = [m for path in paths for m in read_recording(path)]
    yield from sorted(messages, key=lambda m: m.log_time_ns)


@dataclass(frozen=True)
class RecorderSettings:
    """What `qnav record` subscribes to and where it writes."""

    SECTION = ""

    zenoh: ZenohSettings = field(default_factory=ZenohSettings)
    """How to join the zenoh network."""
    rotation: Rotation = field(default_factory=Rotation)
    """When to start a new file."""
    output_dir: str = "recordings"
    """Folder for the MCAP files (one subfolder per recording, named by its start time)."""
    topics: tuple[str, ...] = tuple(t.name for t in TOPICS)
    """Topic names to record (default: all of the project's)."""

    def __post_init__(self) -> None:
        unknown = [name for name in self.topics if topic_of(name) is None]
        if unknown:
            known = ", ".join(t.name for t in TOPICS)
            raise ConfigError(f"topics: unknown {unknown}; the project's topics are {known}")


def record(
    settings: RecorderSettings, stop: threading.Event, folder: Path | None = None
) -> McapWriter:
    """Record until `stop` is set; returns the (closed) writer, whose `files` lists the output."""
    folder = folder or Path(settings.output_dir) / time.strftime("%Y%m%d-%H%M%S")
    writer = McapWriter(folder, rotation=settings.rotation)
    topics = [t for t in TOPICS if t.name in settings.topics]
    errors = 0
    bounded = RateLimitedLog(log)

    def subscriber(topic: Topic) -> Any:
        def on_sample(sample: Any) -> None:
            nonlocal errors
            try:
                writer.write("/" + topic.name, topic.ros_type, bytes(sample.payload.to_bytes()))
            except Exception:  # a full disk must not kill zenoh's thread silently
                errors += 1
                bounded.warning(
                    topic.name,
                    f"cannot write a {topic.name} message ({errors} failures in all)",
                    exc_info=True,
                )

        return on_sample

    try:
        opened = open_session(settings.zenoh, stop)
    except StoppedError:
        log.info("stopped before zenoh connected: nothing recorded")
        writer.close()
        return writer
    with opened as session:
        subscribers = [
            session.declare_subscriber(key(t, settings.zenoh.namespace), subscriber(t))
            for t in topics
        ]
        log.info("recording %s into %s", ", ".join(t.name for t in topics), writer.folder)
        heartbeat = Heartbeat.from_env("recorder")
        while True:
            heartbeat.beat(messages=writer.messages, write_errors=errors)
            if stop.wait(heartbeat.every_s):
                break
        heartbeat.close()
        for handle in subscribers:
            handle.undeclare()
    writer.close()
    return writer


def play(
    messages: list[RecordedMessage],
    settings: ZenohSettings,
    speed: float = 1.0,
    stop: threading.Event | None = None,
    settle_s: float = 0.5,
) -> int:
    """Publish recorded messages on zenoh at their recorded timing (scaled by `speed`).

    Payloads go out byte for byte as recorded. Publishers are declared first and given
    `settle_s` to meet their subscribers, so the first messages are not lost. Returns the
    number published. `stop` ends it at any time, the wait for zenoh included.
    """
    if speed <= 0:
        raise ConfigError(f"speed = {speed} must be > 0")
    stop = stop or threading.Event()
    if not messages:
        return 0
    published = 0
    try:
        session = open_session(settings, stop)
    except StoppedError:
        return 0  # stopped while waiting for zenoh
    with session:
        names = dict.fromkeys(m.topic.lstrip("/") for m in messages)
        publishers = {
            name: session.declare_publisher(key(name, settings.namespace)) for name in names
        }
        stop.wait(settle_s)
        first_ns, start = messages[0].log_time_ns, time.monotonic()
        for message in messages:
            due = start + (message.log_time_ns - first_ns) * 1e-9 / speed
            if stop.wait(max(0.0, due - time.monotonic())):
                break
            publishers[message.topic.lstrip("/")].put(message.payload)
            published += 1
        for publisher in publishers.values():
            publisher.undeclare()
    return published
