"""`qnav controller`: the decision logic of `controller.decision` between zenoh and the car.

The daemon is a thin shell. Zenoh callbacks stamp each payload with its monotonic arrival time
and queue it; the main thread takes the queue in order, hands each payload to the `Controller`,
and publishes the controller's command and status:

- `trigger = "period"`: one decision per control period of the policy, on absolute monotonic
  deadlines t0 + n * period (as openpilot's Ratekeeper keeps them). A decision that ends past the
  next deadline is an overrun: the missed deadlines are counted (status `counters.overruns`)
  and skipped, not run back to back.
- `trigger = "scan"`: a decision as soon as a scan arrives (several queued scans: one decision
  on the newest); every period the safety rules are still checked, and a stop is published if
  one applies, so the car stops when the scans stop.

SIGINT and SIGTERM end the loop; a stop command (status reason `shutdown`) is published before
the session is closed.
"""

from __future__ import annotations

import argparse
import gc
import logging
import queue
import signal
import sys
import textwrap
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from types import FrameType
from typing import Any

from contracts import wire
from contracts.health import Heartbeat
from contracts.settings import to_toml
from contracts.transport import open_session
from contracts.wire import Twist2D
from controller.config import DaemonConfig, load_config
from controller.decision import Controller, Input, Output, Reason
from controller.policy import PolicyRuntime

log = logging.getLogger("qnav.controller")

_Item = tuple[Input, bytes, float] | None
"""A queued payload (input, bytes, monotonic arrival time), or None to wake the loop."""


class BoundedLog:
    """Warnings of one kind at most once per interval; the ones held back are counted."""

    def __init__(self, logger: logging.Logger, interval_s: float) -> None:
        self.logger = logger
        self.interval_s = interval_s
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}

    def warning(self, kind: str, message: str, now: float) -> bool:
        """Log `message` unless one of this kind was logged less than an interval ago."""
        last = self._last.get(kind)
        if last is not None and now - last < self.interval_s:
            self._held[kind] = self._held.get(kind, 0) + 1
            return False
        held = self._held.pop(kind, 0)
        suffix = f" ({held} more since the last warning)" if held else ""
        self.logger.warning("%s%s", message, suffix)
        self._last[kind] = now
        return True


class Ratekeeper:
    """Absolute monotonic deadlines start + n * period (openpilot's Ratekeeper keeps time so).

    Deadlines never drift with the work done at each; a tick whose work ends past the next
    deadline is an overrun, and the deadlines it missed are skipped, not run back to back (a
    burst of decisions on the same inputs would only crowd the policy's window).
    """

    def __init__(self, period_s: float, start_s: float) -> None:
        self.period_s = period_s
        self.start_s = start_s
        self.index = 0

    @property
    def deadline(self) -> float:
        """The next deadline."""
        return self.start_s + self.index * self.period_s

    def advance(self, now: float) -> int:
        """After the work of the current deadline, ending at `now`: move to the next deadline
        still ahead and return how many were missed (0 when on time)."""
        self.index += 1
        behind = now - self.deadline
        if behind < 0:
            return 0
        missed = int(behind // self.period_s) + 1
        self.index += missed
        return missed


class Daemon:
    """The controller on a zenoh session."""

    def __init__(self, config: DaemonConfig, controller: Controller) -> None:
        self.config = config
        self.controller = controller
        self.period_s = controller.period_s
        self.inbox: queue.SimpleQueue[_Item] = queue.SimpleQueue()
        self.stopping = threading.Event()
        self.bounded = BoundedLog(log, config.controller.log_interval_s)
        self._last_reason: Reason | None = None
        self._late_s = 0.0
        self._command: Any = None
        """The command publisher (while `run` has a session)."""
        self._status: Any = None
        """The status publisher (while `run` has a session)."""
        self._sent_s = 0.0
        """When the last command was published."""
        self.heartbeat = Heartbeat.from_env("controller")
        namespace = config.zenoh.namespace
        topics = config.topics
        self.keys: dict[Input, str] = {
            Input.POSE: wire.key(topics.pose, namespace),
            Input.TARGET: wire.key(config.target_topic(), namespace),
            Input.ESTOP: wire.key(topics.estop, namespace),
            Input.ESTOP_RELEASE: wire.key(topics.estop_release, namespace),
        }
        if controller.uses_scan:
            self.keys[Input.SCAN] = wire.key(topics.scan, namespace)
        self.command_key = wire.key(topics.command, namespace)
        self.status_key = wire.key(topics.status, namespace)

    def request_stop(self) -> None:
        """End the loop (safe from a signal handler or another thread)."""
        self.stopping.set()
        self.inbox.put(None)

    def run(self) -> None:
        """Join zenoh, decide until asked to stop, publish a stop, close the session."""
        import zenoh

        # First calls are slow (the ROS type store is built, onnxruntime plans its graph): make
        # them before the first deadline.
        self.controller.warm_up()
        wire.decode_twist_msg(wire.encode_twist_msg(wire.STOP))
        wire.decode_json_msg(wire.encode_json_msg({}))
        session = open_session(self.config.zenoh)
        try:
            self._command = session.declare_publisher(
                self.command_key,
                congestion_control=zenoh.CongestionControl.BLOCK,
                priority=zenoh.Priority.REAL_TIME,
                express=True,
            )
            self._status = session.declare_publisher(
                self.status_key, congestion_control=zenoh.CongestionControl.DROP, express=True
            )
            subscribers = [
                session.declare_subscriber(
                    key, zenoh.handlers.Callback(self._enqueue(source), indirect=False)
                )
                for source, key in self.keys.items()
            ]
            log.info(
                "listening on %s; commands to %s, status to %s",
                ", ".join(f"{s.value}={k}" for s, k in self.keys.items()),
                self.command_key,
                self.status_key,
            )

            # What the imports, the policy and zenoh left is several ms of objects for a full
            # collection to walk: freeze it, so that collections in the loop walk only what
            # the loop allocates.
            gc.collect()
            gc.freeze()
            try:
                self._loop()
            finally:
                now = time.monotonic()
                self._publish_status(self.controller.shutdown(now, self._send), now)
                log.info("stop command published; closing the zenoh session")
                for subscriber in subscribers:
                    subscriber.undeclare()
                self._command.undeclare()
                self._status.undeclare()
        finally:
            session.close()
            self.heartbeat.close()

    def _send(self, command: Twist2D) -> None:
        """Publish a command the moment the controller decides it (its status comes after)."""
        self._command.put(wire.encode_twist_msg(command))
        self._sent_s = time.monotonic()

    def _publish_status(self, output: Output, started: float) -> None:
        """Publish the status of the output whose command `_send` published."""
        report = output.status.to_dict()
        report["loop"] = {
            "trigger": self.config.controller.trigger,
            "period_s": self.period_s,
            "decide_ms": round((self._sent_s - started) * 1e3, 3),
            "late_ms": round(self._late_s * 1e3, 3),
        }
        self._status.put(wire.encode_json_msg(report))
        self._note_reason(output)

    def _enqueue(self, source: Input) -> Callable[[Any], None]:
        inbox = self.inbox

        def on_sample(sample: Any) -> None:
            inbox.put((source, sample.payload.to_bytes(), time.monotonic()))

        return on_sample

    def _loop(self) -> None:
        on_scan = self.config.controller.trigger == "scan"
        rate = Ratekeeper(self.period_s, time.monotonic())
        while not self.stopping.is_set():
            remaining = rate.deadline - time.monotonic()
            if remaining > 0:
                try:
                    item = self.inbox.get(timeout=remaining)
                except queue.Empty:
                    continue
                scans = self._take(item)
                if on_scan and scans and not self.stopping.is_set():
                    started = time.monotonic()
                    self._publish_status(self.controller.decide(started, self._send), started)
                continue
            # A deadline: take what has arrived, then decide (or check) on the newest inputs.
            started = time.monotonic()
            self._late_s = started - rate.deadline
            self._take(None)
            if self.stopping.is_set():
                break
            if on_scan:
                output = self.controller.check(started, self._send)
                if output is not None:
                    self._publish_status(output, started)
            else:
                self._publish_status(self.controller.decide(started, self._send), started)
            self.heartbeat.beat(reason=self._last_reason.value if self._last_reason else None)
            now = time.monotonic()
            missed = rate.advance(now)
            if missed:
                self.controller.note_overruns(missed)
                self.bounded.warning(
                    "overrun",
                    f"overrun: a decision ended {(now - started) * 1e3:.1f} ms after it began "
                    f"({self._late_s * 1e3:.1f} ms late); skipped {missed} control period(s)",
                    now,
                )

    def _take(self, first: _Item) -> int:
        """Hand `first` and everything queued to the controller; returns the scans taken."""
        scans = 0
        item = first
        while True:
            if item is not None:
                source, payload, arrived = item
                error = self.controller.receive(source, payload, arrived)
                if error is not None:
                    self.bounded.warning(
                        source.value, f"{source.value} refused: {error}", time.monotonic()
                    )
                elif source is Input.SCAN:
                    scans += 1
            try:
                item = self.inbox.get_nowait()
            except queue.Empty:
                return scans

    def _note_reason(self, output: Output) -> None:
        reason = output.status.reason
        if reason is not self._last_reason:
            if reason is Reason.POLICY:
                log.info("driving: the policy decides")
            else:
                log.info("stopped: %s", reason.value)
            self._last_reason = reason


def build(config: DaemonConfig) -> Daemon:
    """A daemon for `config`: the policy loaded and checked, ready to `run`."""
    path = config.policy_path()
    runtime = PolicyRuntime(path, backend=config.controller.backend)
    contract = runtime.contract
    log.info(
        "policy %s: %s, %s, window %d, %s, period %.3f s",
        path,
        contract.model_kind,
        contract.scenario,
        contract.window_length,
        f"{contract.num_beams} beams" if contract.num_beams else "no lidar",
        contract.control_period_s,
    )
    return Daemon(config, Controller(runtime, config.safety, config.lidar))


def serve(daemon: Daemon) -> None:
    """Run `daemon` in this (main) thread until SIGINT or SIGTERM."""

    def on_signal(number: int, frame: FrameType | None) -> None:
        log.info("%s: stopping", signal.Signals(number).name)
        daemon.request_stop()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        daemon.run()
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)


def main(args: argparse.Namespace) -> int:
    """Handler of `qnav controller`."""
    if args.example_config:
        sys.stdout.write(example_config())
        return 0
    config = load_config(args.config, args.assignments)
    if args.policy is not None:
        config = replace(config, controller=replace(config.controller, policy=str(args.policy)))
    logging.basicConfig(
        level=config.controller.log_level.upper(),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    serve(build(config))
    return 0


def example_config() -> str:
    """Every setting with its meaning, as a TOML file (`config/controller.toml`)."""
    header = (
        "# Settings of `qnav controller --config FILE` (docs/controller.md).\n"
        "# Every key is optional except controller.policy; the values shown are the defaults.\n"
        "# Written by `qnav controller --example-config`.\n\n"
    )
    lines = []
    for line in to_toml(DaemonConfig()).splitlines():
        if line.startswith("# "):
            lines += textwrap.wrap(line[2:], 97, initial_indent="# ", subsequent_indent="# ")
        else:
            lines.append(line)
    return header + "\n".join(lines) + "\n"


if __name__ == "__main__":  # pragma: no cover - `qnav controller` is the entry point
    parser = argparse.ArgumentParser()
    parser.add_argument("--config", type=Path)
    parser.add_argument("--policy", type=Path)
    parser.add_argument("--set", dest="assignments", action="append", default=[])
    parser.add_argument("--example-config", action="store_true")
    sys.exit(main(parser.parse_args()))
