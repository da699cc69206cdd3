"""Handlers of `qnav record` and `qnav playback` (onboard verbs: no torch)."""

from __future__ import annotations

import argparse
import dataclasses
import logging
import re
import threading
from pathlib import Path
from typing import Any

from qnav.contracts.daemon import stop_on_signals
from qnav.contracts.errors import ConfigError
from qnav.contracts.settings import from_dict, load_toml, with_overrides
from qnav.contracts.transport import ZenohSettings
from qnav.controller.recording import (
    RecordedMessage,
    RecorderSettings,
    play,
    read_recordings,
    record,
)
from qnav.options import settings_from_args
from qnav.verbs.parser import Verbs, flag, repeated, settings_options, verb, zenoh_options


def _zenoh_overrides(args: argparse.Namespace) -> dict[str, Any]:
    overrides: dict[str, Any] = {}
    if args.connect is not None:
        overrides["connect"] = list(args.connect)
    if args.listen is not None:
        overrides["listen"] = list(args.listen)
    if args.namespace is not None:
        overrides["namespace"] = args.namespace
    return overrides


def recorder_settings(args: argparse.Namespace) -> RecorderSettings:
    """What `qnav record` runs with: its --config file, then --connect, --listen and
    --namespace, --out, and the options of the settings' other fields."""
    values = load_toml(args.config) if args.config else {}
    settings = from_dict(RecorderSettings, values)
    settings = dataclasses.replace(
        settings, zenoh=with_overrides(settings.zenoh, _zenoh_overrides(args))
    )
    if args.out is not None:
        settings = dataclasses.replace(settings, output_dir=str(args.out))
    return settings_from_args(settings, args)


def record_verb(args: argparse.Namespace) -> int:
    """Record the project's topics to MCAP until SIGINT/SIGTERM (or --duration-s)."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    settings = recorder_settings(args)
    with stop_on_signals() as stop:
        if args.duration_s:
            threading.Timer(args.duration_s, stop.set).start()
        writer = record(settings, stop, folder=args.folder)
    print(f"recorded {writer.messages} messages into {', '.join(map(str, writer.files)) or '-'}")
    return 0


def mcap_problem(path: Path) -> str | None:
    """Why `path` is not an MCAP file one may recover or play, or None. A recording starts with
    MCAP's magic bytes; a `.mcap` file shorter than them and holding their beginning (or
    nothing) is one its recorder was killed while opening."""
    from qnav.controller.recording import MCAP_MAGIC

    if not path.is_file():
        return f"{path}: no such file"
    with path.open("rb") as stream:
        start = stream.read(len(MCAP_MAGIC))
    if start == MCAP_MAGIC:
        return None
    if path.suffix == ".mcap" and MCAP_MAGIC.startswith(start):
        return None
    return f"{path} is not an MCAP file (it does not start with MCAP's magic bytes)"


def check_mcap(files: list[Path]) -> None:
    """ConfigError naming every one of `files` that is not an MCAP file (before any is used)."""
    problems = [problem for problem in map(mcap_problem, files) if problem is not None]
    if problems:
        raise ConfigError("; ".join(problems))


ROTATED = re.compile(r"^(?P<stem>.+)-\d{4}\.mcap$")
"""A file of a rotated recording, as `McapWriter` names them: `recording-0003.mcap`."""


def one_recording(files: list[Path]) -> bool:
    """Whether a folder's `*.mcap` files are one recording (what a rosbag2 metadata.yaml may
    describe): a single file, or the rotated files of one stem."""
    if len(files) <= 1:
        return True
    stems = {match["stem"] if (match := ROTATED.match(f.name)) else None for f in files}
    return len(stems) == 1 and None not in stems


def _metadata_refusal(folder: Path, given: list[Path]) -> str | None:
    """Why the folder's metadata.yaml must not be written, or None."""
    files = sorted(folder.glob("*.mcap"))
    if not set(given) <= set(files):
        return "a file given does not end in .mcap"
    if not one_recording(files):
        return f"its files are not one recording's ({', '.join(f.name for f in files)})"
    if any(mcap_problem(f) for f in files):
        return "it holds a .mcap file that is not MCAP"
    return None


def recover_verb(args: argparse.Namespace) -> int:
    """Rewrite every cut MCAP file of the given folders (or files) as a complete one, and write
    each folder's rosbag2 metadata.yaml when its files are one recording. Refuses (touching
    nothing) if any file is not MCAP."""
    from qnav.controller.recording import is_complete, recover, write_rosbag_metadata

    given: dict[Path, list[Path]] = {}
    for path in args.paths:
        files = sorted(path.glob("*.mcap")) if path.is_dir() else [path]
        if not files:
            raise ConfigError(f"{path}: no MCAP file there")
        check_mcap(files)
        for file in files:
            given.setdefault(file.parent, []).append(file)
    for file in (f for files in given.values() for f in files):
        if is_complete(file):
            print(f"{file}: complete")
        else:
            kept = recover(file)
            print(f"{file}: recovered {kept} messages (the cut original is {file}.cut)")
    for folder, files in given.items():
        refusal = _metadata_refusal(folder, files)
        if refusal is None:
            print(f"wrote {write_rosbag_metadata(folder)}")
        else:
            print(f"{folder}: no metadata.yaml written: {refusal}")
    return 0


def playback_verb(args: argparse.Namespace) -> int:
    """Publish recordings back onto zenoh at their recorded timing, or (--into-controller) feed
    them into the controller's decision step on a simulated clock."""
    files = sorted(p for f in args.files for p in (sorted(f.glob("*.mcap")) if f.is_dir() else [f]))
    missing = [str(f) for f in files if not f.is_file()]
    if missing or not files:
        raise ConfigError(
            f"no such recording: {', '.join(missing) or ' '.join(map(str, args.files))}"
        )
    check_mcap(files)
    messages = list(read_recordings(files))
    if args.into_controller:
        return _into_controller(args, messages, len(files))
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    settings = with_overrides(ZenohSettings(), _zenoh_overrides(args))
    with stop_on_signals() as stop:
        count = play(messages, settings, speed=args.speed, stop=stop)
    print(f"published {count} of {len(messages)} messages from {len(files)} file(s)")
    return 0


def _into_controller(args: argparse.Namespace, messages: list[RecordedMessage], files: int) -> int:
    """`qnav playback --into-controller`: the controller's rows, as a summary or JSON lines."""
    import json

    from qnav.controller.config import load_config
    from qnav.controller.playback import (
        agreement_with_recorded,
        play_into_controller,
        recorded_statuses,
        summary,
    )
    from qnav.controller.policy import PolicyRuntime

    config = load_config(args.config, args.assignments)
    policy = args.policy or (config.policy_path() if config.controller.policy else None)
    if policy is None:
        raise ConfigError("--into-controller needs --policy FILE.onnx (or controller.policy)")
    runtime = PolicyRuntime(policy, backend=config.controller.backend)
    rows = play_into_controller(
        messages,
        runtime,
        safety=config.safety,
        lidar=config.lidar,
        topics=config.topics,
        trigger=args.trigger or ("scan" if runtime.contract.num_beams else "period"),
    )
    if args.json:
        for row in rows:
            print(json.dumps(row, allow_nan=False))
        return 0
    span_s = (messages[-1].log_time_ns - messages[0].log_time_ns) * 1e-9 if messages else 0.0
    print(
        f"{len(messages)} messages from {files} file(s) over {span_s:.1f} s into the controller "
        f"({policy}): {len(rows)} outputs"
    )
    counts = summary(rows)
    actions = ", ".join(f"{k.split(':')[1]} {v}" for k, v in counts.items() if ":" in k)
    for reason, count in counts.items():
        if ":" not in reason:
            print(f"  {reason:<16} {count:5d}" + (f"  ({actions})" if reason == "policy" else ""))
    statuses = recorded_statuses(messages)
    if statuses:
        same, matched = agreement_with_recorded(rows, statuses)
        print(
            f"recorded run: {len(statuses)} statuses; on the {matched} scans both decided by "
            f"the policy, the same action {same} times"
        )
    return 0


def add_verbs(verbs: Verbs) -> None:
    """`qnav record`, `qnav recover` and `qnav playback`: their options."""
    _add_record(verbs)
    _add_recover(verbs)
    _add_playback(verbs)


def _add_record(verbs: Verbs) -> None:
    """`qnav record`."""
    parser = verb(
        verbs,
        record_verb,
        "record",
        help="record the project's zenoh topics to MCAP (ROS 2 profile, CDR)",
    )
    parser.add_argument("--config", type=Path, metavar="FILE", help="recorder TOML file")
    settings_options(
        parser,
        "qnav.controller.recording:RecorderSettings",
        "recorder settings (each over the --config file)",
        skip=("zenoh", "output_dir"),
    )
    parser.add_argument("--out", type=Path, help="output folder (default recordings/)")
    parser.add_argument(
        "--folder", type=Path, help="write into exactly this folder (no timestamped subfolder)"
    )
    parser.add_argument(
        "--duration-s", type=float, default=0.0, help="stop after this long (0: at SIGINT)"
    )
    zenoh_options(parser)


def _add_recover(verbs: Verbs) -> None:
    """`qnav recover PATH...`."""
    parser = verb(
        verbs,
        recover_verb,
        "recover",
        help="make a killed recording whole: every complete message, indexed, with metadata.yaml",
    )
    parser.add_argument(
        "paths", nargs="+", type=Path, help="recording folders or .mcap files (cut or not)"
    )


def _add_playback(verbs: Verbs) -> None:
    """`qnav playback FILE...`, onto zenoh or into the controller."""
    parser = verb(
        verbs,
        playback_verb,
        "playback",
        help="publish MCAP recordings back onto zenoh at their recorded timing, or feed them "
        "into the controller's decision step (--into-controller)",
    )
    parser.add_argument("files", type=Path, nargs="+", help="MCAP files or folders of them")
    parser.add_argument("--speed", type=float, default=1.0, help="time factor (2: twice as fast)")
    zenoh_options(parser)
    replay = parser.add_argument_group(
        "into the controller",
        "no zenoh: the recording's inputs through a fresh controller, on "
        "the recording's clock (docs/recordings.md)",
    )
    flag(
        replay,
        "--into-controller",
        "feed the recording into the controller's decision step and report its decisions",
    )
    replay.add_argument("--policy", type=Path, metavar="FILE.onnx", help="policy file")
    replay.add_argument(
        "--config", type=Path, metavar="FILE", help="controller TOML (safety, lidar, topics)"
    )
    repeated(
        replay,
        "--set",
        "assignments",
        "SECTION.FIELD=VALUE",
        "change one controller setting, e.g. --set safety.pose_timeout_s=1.0",
    )
    replay.add_argument(
        "--trigger",
        choices=["scan", "period"],
        help="decide on each scan (default, as `qnav stack` runs the daemon) or every period",
    )
    flag(replay, "--json", "print the decisions as JSON lines")
