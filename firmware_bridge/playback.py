"""The bridge's process replay: a recorded run's inputs fed into a fresh `BridgeCore`.

As the controller's `controller.playback` (and openpilot's process replay), a change to the
bridge's decisions shows as a change in rows kept in the repo. A recording holds every call the
daemon made into its core during a real run (`Bridge(journal=Recorder(...))`): the zenoh payloads
(commands, poses, requests) as received, the MAVLink messages as read from the port (their bytes;
BAD_DATA as its bytes and reason), the clock's ticks, and the exit sequence; each with the
monotonic time (and wall time) the daemon handed in, which sends the port refused, and the
actions the live core returned. `replay` hands the same inputs, in the same order, to a fresh core
built from the recording's settings and returns its actions as rows. No zenoh, no socket, no
thread, no clock: the same recording gives the same rows.

Recording (JSON lines): the first line is `{"settings": {...}}` (the bridge's settings as a
dict); then one line per call: `event` (the core's method: command, pose, request, mavlink, tick,
refuse_commands, shutdown, exit_step, exit_message, stopped), `args` (its inputs: numbers and
booleans as they are, bytes as {"hex": ...}, a MAVLink message as {"mavlink": hex} or
{"bad_data": hex, "reason": ...}), `unsent` (indices, among the call's sends, of those the port
refused; absent when all went out), and `out` (the live core's actions as rows).

Rows (an action each): {"send": MAVLink type, "gcs": sent with the ground station's id,
"fields": the message's fields, "counts": the counter a sent one adds to (or absent)}, {"reopen":
true}, or {"state": the vehicle state published, less its wall-clock stamp}. Floats are rounded
to 6 decimals. References (JSON lines) hold, for each call that produced actions, {"i": the
call's index in the recording, "event", "t": its time, "out": rows}.
"""

from __future__ import annotations

import dataclasses
import gzip
import json
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO, Any

from qnav.contracts.mavlink import mavutil
from qnav.contracts.settings import from_dict
from qnav.firmware_bridge.core import Action, BridgeCore, Publish, Reopen, Send
from qnav.firmware_bridge.settings import BridgeSettings

Row = dict[str, Any]
"""One action, or one call of a recording or a reference, as plain JSON values."""

DECIMALS = 6
"""Floats in rows are rounded to this many decimals."""

EVENTS = frozenset(
    {
        "command",
        "pose",
        "request",
        "mavlink",
        "tick",
        "refuse_commands",
        "shutdown",
        "exit_step",
        "exit_message",
        "stopped",
    }
)
"""The core's methods a recording may call (everything the daemon hands the core)."""


class Recorder:
    """A journal for `Bridge(journal=...)` writing a recording to an open text file."""

    def __init__(self, out: IO[str], settings: BridgeSettings) -> None:
        self._out = out
        self._lock = threading.Lock()
        self._write({"settings": dataclasses.asdict(settings)})

    def __call__(
        self, event: str, inputs: tuple[Any, ...], actions: list[Action], went_out: list[bool]
    ) -> None:
        row: Row = {"event": event, "args": [_encode_input(value) for value in inputs]}
        unsent = [index for index, ok in enumerate(went_out) if not ok]
        if unsent:
            row["unsent"] = unsent
        row["out"] = [action_row(action) for action in actions]
        self._write(row)

    def _write(self, row: Row) -> None:
        with self._lock:
            self._out.write(json.dumps(row, allow_nan=False) + "\n")
            self._out.flush()


def read_recording(path: Path) -> tuple[BridgeSettings, list[Row]]:
    """The settings and the calls of a recording (gzip-compressed if its name ends in .gz)."""
    text = gzip.decompress(path.read_bytes()).decode() if path.suffix == ".gz" else path.read_text()
    lines = [json.loads(line) for line in text.splitlines() if line.strip()]
    if not lines or "settings" not in lines[0]:
        raise ValueError(f"{path}: not a bridge recording (no settings line first)")
    return from_dict(BridgeSettings, lines[0]["settings"]), lines[1:]


def replay(settings: BridgeSettings, calls: Iterable[Row]) -> list[Row]:
    """The references a fresh core gives for these calls (module docstring: the rows)."""
    core = BridgeCore(settings)
    parser = _parser()
    references: list[Row] = []
    for index, call in enumerate(calls):
        event = call["event"]
        if event not in EVENTS:
            raise ValueError(f"call {index}: {event!r} is not one of the core's inputs")
        actions: list[Action] = getattr(core, event)(*call_inputs(call, parser))
        unsent = set(call.get("unsent", ()))
        sends = [action for action in actions if isinstance(action, Send)]
        for position, send in enumerate(sends):
            core.sent(send, position not in unsent)
        if actions:
            references.append(
                {
                    "i": index,
                    "event": event,
                    "t": call_time(call),
                    "out": [action_row(action) for action in actions],
                }
            )
    return references


def call_inputs(call: Row, parser: Any = None) -> list[Any]:
    """The inputs of a recorded call as the core takes them (bytes, MAVLink messages, times)."""
    parser = _parser() if parser is None else parser
    return [_decode_input(value, parser) for value in call["args"]]


def live_references(calls: Iterable[Row]) -> list[Row]:
    """What the live core decided in the recorded run, in the references' shape."""
    return [
        {"i": index, "event": call["event"], "t": call_time(call), "out": call["out"]}
        for index, call in enumerate(calls)
        if call.get("out")
    ]


def action_row(action: Action) -> Row:
    """One action as a row."""
    if isinstance(action, Send):
        fields = {
            name: _rounded(value)
            for name, value in action.message.to_dict().items()
            if name != "mavpackettype"
        }
        row: Row = {"send": action.message.get_type(), "gcs": action.as_gcs, "fields": fields}
        if action.counter is not None:
            row["counts"] = action.counter
        return row
    if isinstance(action, Reopen):
        return {"reopen": True}
    if isinstance(action, Publish):
        return {"state": _rounded(action.state)}
    raise TypeError(f"not an action: {action!r}")


def differences(expected: list[Row], actual: list[Row], most: int = 20) -> list[str]:
    """How `actual` references differ from `expected`, one line per call (empty: the same), at
    most `most` lines."""
    want = {row["i"]: row for row in expected}
    got = {row["i"]: row for row in actual}
    lines = []
    for index in sorted(want.keys() | got.keys()):
        before, after = want.get(index), got.get(index)
        if before == after:
            continue
        row = before or after or {}
        where = f"call {index} ({row.get('event')} at {row.get('t')})"
        lines.append(f"{where}: {_brief(before)} -> {_brief(after)}")
        if len(lines) == most:
            break
    return lines


def sends(references: Iterable[Row]) -> Iterator[tuple[Row, Row]]:
    """(call, send row) for every send in references or a recording's calls, in order."""
    for call in references:
        for row in call["out"]:
            if "send" in row:
                yield call, row


def write_rows(path: Path, rows: list[Row]) -> None:
    """Rows as JSON lines (the references)."""
    path.write_text("".join(json.dumps(row, allow_nan=False) + "\n" for row in rows))


def read_rows(path: Path) -> list[Row]:
    """Rows from JSON lines."""
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def call_time(call: Row) -> float | None:
    """The monotonic time a recorded call was handed (None for one without a time)."""
    args = call["args"]
    times = [value for value in args if isinstance(value, float)]
    return times[0] if times else None


def _brief(row: Row | None) -> str:
    if row is None:
        return "nothing"
    kinds = []
    for action in row["out"]:
        kinds.append(action.get("send") or ("reopen" if "reopen" in action else "state"))
    return "[" + ", ".join(kinds) + "]"


def _rounded(value: Any) -> Any:
    if isinstance(value, float):
        return round(value, DECIMALS)
    if isinstance(value, dict):
        return {name: _rounded(item) for name, item in value.items()}
    if isinstance(value, list | tuple):
        return [_rounded(item) for item in value]
    return value


def _encode_input(value: Any) -> Any:
    if isinstance(value, bool | int | float | str) or value is None:
        return value
    if isinstance(value, bytes | bytearray | memoryview):
        return {"hex": bytes(value).hex()}
    if value.get_type() == "BAD_DATA":
        return {"bad_data": bytes(value.data).hex(), "reason": str(value.reason)}
    return {"mavlink": bytes(value.get_msgbuf()).hex()}


def _decode_input(value: Any, parser: Any) -> Any:
    if not isinstance(value, dict):
        return value
    if "hex" in value:
        return bytes.fromhex(value["hex"])
    if "bad_data" in value:
        data = bytearray.fromhex(value["bad_data"])
        return mavutil().mavlink.MAVLink_bad_data(data, value["reason"])
    return parser.decode(bytearray.fromhex(value["mavlink"]))


def _parser() -> Any:
    """A MAVLink 2 decoder of recorded packets (signatures are not checked: the live bridge
    did, and a refused packet was recorded as BAD_DATA)."""
    parser = mavutil().mavlink.MAVLink(None)
    parser.robust_parsing = True
    return parser
