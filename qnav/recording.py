"""Handlers of `qnav record` and `qnav playback` (onboard verbs: no torch)."""

from __future__ import annotations

import argparse
import dataclasses
import logging
import signal
import threading
from typing import Any

from contracts.settings import from_dict, load_toml, with_overrides
from contracts.transport import ZenohSettings
from controller.recording import RecorderSettings, play, read_recordings, record


def _zenoh_overrides(args: argparse.Namespace) -> dict[str, Any]:
    overrides: dict[str, Any] = {}
    if args.connect is not None:
        overrides["connect"] = list(args.connect)
    if args.listen is not None:
        overrides["listen"] = list(args.listen)
    if args.namespace is not None:
        overrides["namespace"] = args.namespace
    return overrides


def _stop_on_signals() -> threading.Event:
    stop = threading.Event()
    for number in (signal.SIGINT, signal.SIGTERM):
        signal.signal(number, lambda *_: stop.set())
    return stop


def record_verb(args: argparse.Namespace) -> int:
    """Record the project's topics to MCAP until SIGINT/SIGTERM (or --duration-s)."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    values = load_toml(args.config) if args.config else {}
    settings = from_dict(RecorderSettings, values)
    settings = dataclasses.replace(
        settings, zenoh=with_overrides(settings.zenoh, _zenoh_overrides(args))
    )
    if args.out is not None:
        settings = dataclasses.replace(settings, output_dir=str(args.out))
    stop = _stop_on_signals()
    if args.duration_s:
        threading.Timer(args.duration_s, stop.set).start()
    writer = record(settings, stop, folder=args.folder)
    print(f"recorded {writer.messages} messages into {', '.join(map(str, writer.files)) or '-'}")
    return 0


def playback_verb(args: argparse.Namespace) -> int:
    """Publish recordings back onto zenoh at their recorded timing."""
    files = sorted(p for f in args.files for p in (sorted(f.glob("*.mcap")) if f.is_dir() else [f]))
    messages = list(read_recordings(files))
    settings = with_overrides(ZenohSettings(), _zenoh_overrides(args))
    count = play(messages, settings, speed=args.speed, stop=_stop_on_signals())
    print(f"published {count} of {len(messages)} messages from {len(files)} file(s)")
    return 0
