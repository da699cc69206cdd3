"""A recording fed straight into the controller's decision step, on the recording's own clock.

This is the controller's process replay (as openpilot's): the inputs of a recorded run go into a
fresh `controller.decision.Controller`, and what it decides comes back as rows, so a change to
the controller, the scan rules or the policy runtime shows as a change in the rows of recordings
kept in the repo (`tests/controller/test_playback.py`, docs/recordings.md). No zenoh, no
threads, no wall clock: the same recording and policy file give the same rows.

The rule (the daemon's `controller.trigger = "scan"`, as `qnav stack` runs it):

- The clock: a message's time is its log time in seconds from the recording's first message
  (of any topic), t = (log_time_ns - first_log_time_ns) / 1e9; the controller is handed it as
  the message's arrival time.
- Inputs: messages on the scan, pose, target (`/goal_pose`, or `/goal_point` with
  `safety.target_kind = "point"`), emergency-stop and release topics (names from
  `TopicSettings`, without namespace, as `qnav record` names channels) are handed to
  `Controller.receive` in order of log time (file order among equal times). Every other topic,
  the recorded `/cmd_vel` and `/qnav/controller_status` included, is what the original run
  produced and is not fed in.
- Decisions: right after each scan the controller accepted, `decide(t)` at the scan's time
  (trigger `scan`). A refused scan (malformed, too many invalid readings) triggers nothing, as
  in the daemon; the previous scan then ages.
- Safety checks: on a grid of control periods from the first message, at n * period for
  n = 0, 1, ... up to the last message's time, `check(t)` runs the safety rules alone and a stop
  that applies is a row (trigger `period`), so stale inputs stop the car even when scans stop.
  Messages at a tick's time are taken before the tick. Times are compared in integer
  nanoseconds, so the order of events never depends on rounding.

Unlike the daemon, no decision is ever late or folded: each scan gets its own decision, at its
own time. `trigger = "period"` (the daemon's default, and the only one for a lidar-less policy)
decides at every tick instead, with the newest inputs.

Each row is one JSON object: `time_s` (6 decimals), `trigger` (`scan` or `period`), `reason`
(`controller.decision.Reason`), `action` (`forward`/`left`/`right`, or null when a rule
stopped the car), `command` ({`linear_mps`, `angular_radps`}), `q_values` (5 decimals, or
null) and `scan_stamp_s` (header stamp of the scan in use, or null).
"""

from __future__ import annotations

import json
import math
from collections import Counter
from collections.abc import Iterable
from pathlib import Path
from typing import Any, Literal

from qnav.contracts import wire
from qnav.contracts.errors import ConfigError
from qnav.controller.config import LidarSettings, SafetySettings, TopicSettings
from qnav.controller.decision import Controller, Input, Output, Reason
from qnav.controller.policy import PolicyRuntime
from qnav.controller.recording import RecordedMessage

Row = dict[str, Any]
"""One output of the controller, as plain JSON values (module docstring: the fields)."""

Trigger = Literal["scan", "period"]

Q_DECIMALS = 5
"""Q values in rows are rounded to this many decimals."""
TIME_DECIMALS = 6
"""Times in rows are rounded to this many decimals (microseconds)."""


def input_topics(
    topics: TopicSettings | None = None, safety: SafetySettings | None = None
) -> dict[str, Input]:
    """Recorded channel names (with their leading slash) of the controller's inputs."""
    topics = topics or TopicSettings()
    safety = safety or SafetySettings()
    target = topics.target or (
        wire.TARGET_POSE.name if safety.target_kind == "pose" else wire.TARGET_POINT.name
    )
    names = {
        Input.SCAN: topics.scan,
        Input.POSE: topics.pose,
        Input.TARGET: target,
        Input.ESTOP: topics.estop,
        Input.ESTOP_RELEASE: topics.estop_release,
    }
    return {"/" + name.strip("/"): source for source, name in names.items()}


def play_into_controller(
    messages: Iterable[RecordedMessage],
    policy: PolicyRuntime | Path,
    *,
    safety: SafetySettings | None = None,
    lidar: LidarSettings | None = None,
    topics: TopicSettings | None = None,
    trigger: Trigger = "scan",
) -> list[Row]:
    """The rows a fresh controller outputs for these messages (module docstring: the rule).

    `policy` is a policy file or a runtime; a runtime's window is restarted first, so earlier
    use of it changes nothing.
    """
    runtime = policy if isinstance(policy, PolicyRuntime) else PolicyRuntime(policy)
    runtime.reset()
    controller = Controller(runtime, safety, lidar)
    if trigger == "scan" and not controller.uses_scan:
        raise ConfigError(
            "trigger = 'scan' needs a policy that reads a lidar; use trigger = 'period'"
        )
    inputs = input_topics(topics, controller.safety)
    ordered = sorted(messages, key=lambda m: m.log_time_ns)
    if not ordered:
        return []
    first_ns = ordered[0].log_time_ns
    period_ns = round(controller.period_s * 1e9)
    rows: list[Row] = []
    tick = 0

    def run_ticks_before(time_ns: int) -> None:
        """Ticks strictly before `time_ns` (messages at a tick's time go first)."""
        nonlocal tick
        while tick * period_ns < time_ns:
            now = tick * period_ns * 1e-9
            if trigger == "period":
                rows.append(row(controller.decide(now), "period"))
            else:
                output = controller.check(now)
                if output is not None:
                    rows.append(row(output, "period"))
            tick += 1

    for message in ordered:
        source = inputs.get(message.topic)
        if source is None:
            continue
        time_ns = message.log_time_ns - first_ns
        run_ticks_before(time_ns)
        now = time_ns * 1e-9
        refused = controller.receive(source, message.payload, now)
        if trigger == "scan" and source is Input.SCAN and refused is None:
            rows.append(row(controller.decide(now), "scan"))
    run_ticks_before(ordered[-1].log_time_ns - first_ns + 1)
    return rows


def row(output: Output, trigger: Trigger) -> Row:
    """One output as a row."""
    status = output.status
    q_values = status.q_values
    return {
        "time_s": round(status.time_s, TIME_DECIMALS),
        "trigger": trigger,
        "reason": status.reason.value,
        "action": None if status.action is None else status.action.name.lower(),
        "command": {
            "linear_mps": output.command.linear_mps,
            "angular_radps": output.command.angular_radps,
        },
        "q_values": None if q_values is None else [round(q, Q_DECIMALS) for q in q_values],
        "scan_stamp_s": status.scan_stamp_s,
    }


def summary(rows: list[Row]) -> dict[str, int]:
    """Rows by reason, the policy's split by action (`policy:forward`, ...), most first."""
    counts: Counter[str] = Counter(r["reason"] for r in rows)
    counts.update(f"policy:{r['action']}" for r in rows if r["reason"] == Reason.POLICY.value)
    return dict(counts.most_common())


def recorded_statuses(messages: Iterable[RecordedMessage]) -> list[dict[str, Any]]:
    """The status objects the original run's controller published (malformed ones skipped)."""
    statuses = []
    name = "/" + wire.CONTROLLER_STATUS.name
    for message in messages:
        if message.topic == name:
            try:
                statuses.append(wire.decode_json_msg(message.payload))
            except wire.WireError:
                continue
    return statuses


def agreement_with_recorded(rows: list[Row], statuses: list[dict[str, Any]]) -> tuple[int, int]:
    """Of the original run's policy decisions whose scan the playback also decided on (matched
    by the scan's header stamp), how many chose the same action: (same, matched)."""
    played = {
        r["scan_stamp_s"]: r["action"]
        for r in rows
        if r["trigger"] == "scan" and r["reason"] == Reason.POLICY.value
    }
    same = matched = 0
    for status in statuses:
        stamp = status.get("scan_stamp_s")
        if status.get("reason") != Reason.POLICY.value or stamp not in played:
            continue
        matched += 1
        same += played[stamp] == status.get("action")
    return same, matched


def differences(expected: list[Row], actual: list[Row], q_tolerance: float = 1e-4) -> list[str]:
    """How `actual` rows differ from `expected` ones, one line per difference, in time order
    (empty: the same). Rows are matched by time and trigger; matched rows must have every field
    equal except the Q values, which may differ by up to `q_tolerance`."""
    want = {_key(r): r for r in expected}
    got = {_key(r): r for r in actual}
    lines: list[tuple[tuple[float, str], str]] = []
    for key in sorted(want.keys() | got.keys()):
        where = f"at {key[0]} s ({key[1]})"
        if key not in got:
            lines.append((key, f"{where}: {_brief(want[key])} is gone"))
        elif key not in want:
            lines.append((key, f"{where}: {_brief(got[key])} is new"))
        else:
            fields = _differing_fields(want[key], got[key], q_tolerance)
            if fields:
                change = f"{_brief(want[key])} -> {_brief(got[key])}"
                lines.append((key, f"{where}: {change} ({', '.join(fields)} differ)"))
    if len(want) != len(expected) or len(got) != len(actual):
        lines.append(((math.inf, ""), "rows with the same time and trigger"))
    return [line for _, line in lines]


def _key(row: Row) -> tuple[float, str]:
    return (float(row.get("time_s", math.nan)), str(row.get("trigger")))


def _differing_fields(want: Row, got: Row, q_tolerance: float) -> list[str]:
    fields = [
        key
        for key in sorted(want.keys() | got.keys())
        if key != "q_values" and want.get(key) != got.get(key)
    ]
    q_want, q_got = want.get("q_values"), got.get("q_values")
    if q_want is None or q_got is None:
        same_q = q_want is None and q_got is None
    else:
        same_q = len(q_want) == len(q_got) and all(
            abs(a - b) <= q_tolerance for a, b in zip(q_want, q_got, strict=True)
        )
    return fields if same_q else [*fields, "q_values"]


def _brief(row: Row) -> str:
    action = row.get("action")
    return f"{row.get('reason')}{'' if action is None else ':' + str(action)}"


def write_rows(path: Path, rows: list[Row]) -> None:
    """Rows as JSON lines (the reference files of the playback tests)."""
    path.write_text("".join(json.dumps(r, allow_nan=False) + "\n" for r in rows))


def read_rows(path: Path) -> list[Row]:
    """Rows from JSON lines."""
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
