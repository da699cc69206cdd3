"""`qnav controller`: the decision logic of `controller.decision` between zenoh and the car.

The daemon is a thin shell around one `Controller`, guarded by one lock. Each zenoh callback
stamps its payload with the monotonic arrival time and hands it to the controller in zenoh's own
thread (no queue, no thread hand-off: the command of a scan leaves from the thread that received
the scan). The main thread keeps time:

- `trigger = "period"`: one decision per control period of the policy, on absolute monotonic
  deadlines t0 + n * period (as openpilot's Ratekeeper keeps them), on the newest inputs. A
  decision that ends past the next deadline is an overrun: the missed deadlines are counted
  (status `counters.overruns`) and skipped, not run back to back.
- `trigger = "scan"`: a decision as soon as a scan arrives, in the callback that received it;
  every period the main thread still checks the safety rules and publishes a stop if one
  applies, so the car stops when the scans stop.

SIGINT and SIGTERM end the loop; a stop command (status reason `shutdown`) is published before
the session is closed, and no decision is published after it.
"""

from __future__ import annotations

import gc
import logging
import tempfile
import textwrap
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from qnav.contracts import delivery, wire
from qnav.contracts.daemon import RateLimitedLog, stop_on_signals
from qnav.contracts.errors import PolicyFileError
from qnav.contracts.health import Heartbeat
from qnav.contracts.policy_file import PolicyContract
from qnav.contracts.settings import to_toml
from qnav.contracts.transport import StoppedError, open_session
from qnav.contracts.wire import Twist2D
from qnav.controller.config import DaemonConfig
from qnav.controller.decision import Controller, Input, Output, Reason
from qnav.controller.delivery import Candidate, PolicyFetcher
from qnav.controller.policy import PolicyRuntime
from qnav.controller.proximity import footprint_mismatch

log = logging.getLogger("qnav.controller")


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

    def __init__(
        self,
        config: DaemonConfig,
        controller: Controller,
        policy_sha256: str = "",
        public_key: Any = None,
    ) -> None:
        self.config = config
        self.controller = controller
        self.policy_sha256 = policy_sha256
        """Hash of the running policy's file (a server's announcement of it is ignored)."""
        self.public_key = public_key
        """The server's public key (with policy.source = "server")."""
        self.fetcher: PolicyFetcher | None = None
        """Takes delivered policies (while `run` has a session, with policy.source = "server")."""
        self._candidate: Candidate | None = None
        """A verified policy waiting for the car to stop (under the lock)."""
        self.period_s = controller.period_s
        self.decide_on_scan = config.controller.trigger == "scan"
        self.stopping = threading.Event()
        self.bounded = RateLimitedLog(log, config.controller.log_interval_s)
        self._lock = threading.Lock()
        """Held by whoever talks to the controller or publishes (zenoh's threads, the loop)."""
        self._closed = False
        """Set (under the lock) once the shutdown stop is published: nothing follows it."""
        self._last_reason: Reason | None = None
        self._last_logged: tuple[Reason, bool] | None = None
        """The reason last logged, and whether the car was stopped."""
        self._late_s = 0.0
        self._command: Any = None
        """The command publisher (while `run` has a session)."""
        self._status: Any = None
        """The status publisher (while `run` has a session)."""
        self._sent_s = 0.0
        """When the last command was published."""
        self._scratch: tempfile.TemporaryDirectory[str] | None = None
        """The temporary policy cache (policy.cache_dir unset)."""
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
        self.announcement_key = wire.key(topics.policy_announcement, namespace)

    def request_stop(self) -> None:
        """End the loop (safe from a signal handler or another thread)."""
        self.stopping.set()

    def run(self) -> None:
        """Join zenoh, decide until asked to stop, publish a stop, close the session."""
        import zenoh

        # First calls are slow (the ROS type store is built, onnxruntime plans its graph): make
        # them before the first deadline.
        self.controller.warm_up()
        wire.decode_twist_msg(wire.encode_twist_msg(wire.STOP))
        wire.decode_json_msg(wire.encode_json_msg({}))
        try:
            session = open_session(self.config.zenoh, self.stopping)
        except StoppedError:
            log.info("stopped before zenoh connected: no command was ever published")
            self.heartbeat.close()
            return
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
            # What the imports, the policy and zenoh left is several ms of objects for a full
            # collection to walk: freeze it, so that collections walk only what the daemon
            # allocates from now on.
            gc.collect()
            gc.freeze()
            subscribers = [
                session.declare_subscriber(
                    key, zenoh.handlers.Callback(self._on_sample(source), indirect=False)
                )
                for source, key in self.keys.items()
            ]
            if self.config.policy.source == "server":
                subscribers.append(self._start_fetcher(session))
            log.info(
                "listening on %s; commands to %s, status to %s",
                ", ".join(f"{s.value}={k}" for s, k in self.keys.items()),
                self.command_key,
                self.status_key,
            )
            try:
                self._loop()
            finally:
                with self._lock:
                    self._closed = True
                    now = time.monotonic()
                    self._publish_status(self.controller.shutdown(now, self._send), now)
                log.info("stop command published; closing the zenoh session")
                if self.fetcher is not None:
                    self.fetcher.stop()
                for subscriber in subscribers:
                    subscriber.undeclare()
                self._command.undeclare()
                self._status.undeclare()
        finally:
            session.close()
            self.heartbeat.close()
            if self._scratch is not None:
                self._scratch.cleanup()

    def _start_fetcher(self, session: Any) -> Any:
        """Start taking the policies a server announces; returns the announcement subscriber."""
        import zenoh

        settings = self.config.policy
        if settings.cache_dir:
            cache = Path(settings.cache_dir)
        else:
            self._scratch = tempfile.TemporaryDirectory(prefix="qnav-policies-")
            cache = Path(self._scratch.name)
        self.fetcher = PolicyFetcher(
            settings,
            public_key=self.public_key,
            cache_dir=cache,
            backend=self.config.controller.backend,
            running=self._running,
            offer=self._offer,
            warn=lambda kind, message: self.bounded.warning(kind, message, time.monotonic()),
        )
        fetcher = self.fetcher
        subscriber = session.declare_subscriber(
            self.announcement_key,
            zenoh.handlers.Callback(
                lambda sample: fetcher.on_payload(sample.payload.to_bytes()), indirect=False
            ),
        )
        fetcher.start(session, self.config.zenoh.namespace)
        log.info("taking policies announced on %s (cache %s)", self.announcement_key, cache)
        return subscriber

    def _running(self) -> tuple[PolicyContract, str]:
        with self._lock:
            return self.controller.runtime.contract, self.policy_sha256

    def _offer(self, candidate: Candidate) -> None:
        with self._lock:
            self._candidate = candidate

    def _swap_if_at_rest(self, now: float) -> None:
        """Swap a waiting policy in if the car is stopped (under the lock, between decisions)."""
        candidate = self._candidate
        if candidate is None or self.fetcher is None or not self.controller.at_rest(now):
            return
        self._candidate = None
        previous = self.controller.policy_version
        try:
            self.controller.swap_policy(candidate.runtime, candidate.version)
        except PolicyFileError as error:
            self.fetcher.refused(candidate.version, str(error))
            return
        self.policy_sha256 = candidate.sha256
        self.fetcher.swapped(candidate.version)
        log.info("policy %s swapped in (was %s) while stopped", candidate.version, previous)

    def _send(self, command: Twist2D) -> None:
        """Publish a command the moment the controller decides it (its status comes after)."""
        payload = wire.encode_twist_msg(command)
        # Stamped as it is handed to zenoh: stamped after `put` returned, a listener on a loaded
        # machine could hold the command before the stamp (a negative outbound time).
        self._sent_s = time.monotonic()
        self._command.put(payload)

    def _publish_status(self, output: Output, started: float) -> None:
        """Publish the status of the output whose command `_send` published."""
        report = output.status.to_dict()
        report["loop"] = {
            "trigger": self.config.controller.trigger,
            "period_s": self.period_s,
            "decide_ms": round((self._sent_s - started) * 1e3, 3),
            "late_ms": round(self._late_s * 1e3, 3),
        }
        if self.fetcher is not None:
            report["delivery"] = self.fetcher.report()
        self._status.put(wire.encode_json_msg(report))
        self._note_reason(output)

    def _on_sample(self, source: Input) -> Callable[[Any], None]:
        """The zenoh callback of one input: take the payload, and decide on a scan."""
        decides = source is Input.SCAN and self.decide_on_scan

        def on_sample(sample: Any) -> None:
            arrived = time.monotonic()
            payload = sample.payload.to_bytes()
            with self._lock:
                if self._closed:
                    return
                error = self.controller.receive(source, payload, arrived)
                if error is not None:
                    self.bounded.warning(
                        source.value, f"{source.value} refused: {error}", time.monotonic()
                    )
                elif decides and not self.stopping.is_set():
                    self._publish_status(self.controller.decide(arrived, self._send), arrived)

        return on_sample

    def _loop(self) -> None:
        rate = Ratekeeper(self.period_s, time.monotonic())
        while not self.stopping.wait(max(0.0, rate.deadline - time.monotonic())):
            started = time.monotonic()
            self._late_s = started - rate.deadline
            with self._lock:
                self._swap_if_at_rest(started)
                if self.decide_on_scan:
                    output = self.controller.check(started, self._send)
                    if output is not None:
                        self._publish_status(output, started)
                else:
                    self._publish_status(self.controller.decide(started, self._send), started)
            self.heartbeat.beat(reason=self._last_reason.value if self._last_reason else None)
            now = time.monotonic()
            missed = rate.advance(now)
            if missed:
                with self._lock:
                    self.controller.note_overruns(missed)
                    self.bounded.warning(
                        "overrun",
                        f"overrun: a decision ended {(now - started) * 1e3:.1f} ms after it "
                        f"began ({self._late_s * 1e3:.1f} ms late); skipped {missed} control "
                        "period(s)",
                        now,
                    )

    def _note_reason(self, output: Output) -> None:
        """Log why the car does what it does whenever that changes (a proximity stop's turn and
        its stop are two)."""
        reason, action = output.status.reason, output.status.action
        logged = (reason, action is None)
        if logged != self._last_logged:
            if reason is Reason.POLICY:
                log.info("driving: the policy decides")
            elif reason is Reason.PROXIMITY:
                log.warning(
                    "proximity: the safety field forbids the chosen action; %s",
                    "stopped" if action is None else f"turning {action.name.lower()} instead",
                )
            else:
                log.info("stopped: %s", reason.value)
            self._last_logged = logged
        self._last_reason = reason


def build(config: DaemonConfig) -> Daemon:
    """A daemon for `config`: the policy loaded and checked, ready to `run`."""
    path = config.policy_path()
    public_key = None
    if config.policy.source == "server":
        public_key = delivery.load_public_key(config.policy.public_key_path(), "policy.public_key")
    runtime = PolicyRuntime(path, backend=config.controller.backend)
    contract = runtime.contract
    sha = delivery.sha256_of(path.read_bytes())
    version = delivery.version_of(path.stem, sha)
    log.info(
        "policy %s (%s): %s, %s, window %d, %s, period %.3f s",
        path,
        version,
        contract.model_kind,
        contract.scenario,
        contract.window_length,
        f"{contract.num_beams} beams" if contract.num_beams else "no lidar",
        contract.control_period_s,
    )
    controller = Controller(
        runtime,
        config.safety,
        config.lidar,
        policy_version=version,
        lookahead=config.lookahead,
        tracker=config.tracker,
        proximity=config.proximity,
    )
    if not controller.uses_scan and config.proximity.enabled:
        log.info("proximity stop: none (the policy reads no lidar)")
    elif config.proximity.enabled and contract.motion:
        _, robot_radius_m = contract.motion_model(str(path))
        mismatch = footprint_mismatch(config.proximity.footprint_m, robot_radius_m)
        if mismatch:
            log.warning(mismatch)
    return Daemon(config, controller, sha, public_key)


def serve(daemon: Daemon) -> None:
    """Run `daemon` in this (main) thread until SIGINT or SIGTERM."""
    with stop_on_signals(daemon.stopping, log):
        daemon.run()


def commented_config(config: DaemonConfig | None = None) -> str:
    """Every setting with its meaning, as a TOML file: the defaults (`config/controller.toml`),
    or `config`'s values (what `--print-config` shows after --config, --set and --policy)."""
    config = DaemonConfig() if config is None else config
    shown = (
        "the defaults"
        if config == DaemonConfig()
        else "this command's (its --config, --set and --policy)"
    )
    header = (
        "# Settings of `qnav controller --config FILE` (docs/controller.md).\n"
        f"# Every key is optional except controller.policy; the values shown are {shown}.\n"
        "# Written by `qnav controller --print-config`.\n\n"
    )
    lines = []
    for line in to_toml(config).splitlines():
        if line.startswith("# "):
            lines += textwrap.wrap(line[2:], 97, initial_indent="# ", subsequent_indent="# ")
        else:
            lines.append(line)
    return header + "\n".join(lines) + "\n"
