"""The firmware bridge daemon: the I/O shell around `firmware_bridge.core.BridgeCore`.

Every decision (what MAVLink goes out for a command, a pose, a request or the time; arming and
mode; the failsafe's stops; link loss; the exit sequence) is the core's, which reads no clock
and opens no socket. This shell owns the rest: the zenoh session and its subscriptions, the
MAVLink port, the bridge thread and the clocks. It hands each input to the core with the time,
under one lock, and carries out the actions the core returns in their order (the sends under
the same lock, so the wire sees the decisions in order).

Three kinds of thread meet here. zenoh's callback threads hand commands to the core and send
its answer at once (the shortest path from the controller to the wire); the bridge thread
reads MAVLink, runs the core's clock (`BridgeCore.tick`: heartbeat, failsafe stops, requests,
link timeout), reopens the port and publishes the vehicle state; and the main thread waits for
SIGINT or SIGTERM, then shuts down in order: no more commands, stop sent, disarm (if
configured).

A payload that does not parse is counted and logged (rate-limited) and changes nothing: it is
not a command, so the failsafe treats it as silence.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

from qnav.contracts.daemon import RateLimitedLog, Service, stop_on_signals
from qnav.contracts.errors import ConfigError
from qnav.contracts.health import Heartbeat
from qnav.contracts.mavlink import key_file_is_private, load_signing_key
from qnav.contracts.transport import StoppedError, open_session
from qnav.contracts.wire import (
    COMMAND,
    POSE,
    STOP,
    VEHICLE_REQUEST,
    VEHICLE_STATE,
    Pose2D,
    decode_json_msg,
    decode_pose_msg,
    decode_twist_msg,
    encode_json_msg,
    encode_pose_msg,
    encode_twist_msg,
    key,
)
from qnav.firmware_bridge.core import Action, BridgeCore, Publish, Reopen, Send
from qnav.firmware_bridge.link import MavlinkLink, serial0_warning
from qnav.firmware_bridge.mapping import speed_scale
from qnav.firmware_bridge.settings import BridgeSettings

log = logging.getLogger("qnav.firmware_bridge")

Journal = Callable[[str, tuple[Any, ...], list[Action], list[bool]], None]
"""Told each call into the core: its name, inputs, the actions, whether each send went out."""

LOOP_MAX_WAIT_S = 0.1
"""The bridge thread looks at its clocks at least this often (requests from zenoh wait for it)."""


class Bridge(Service):
    """zenoh to MAVLink with a failsafe; `start()` it, `close()` it (or use `with`).

    `journal`, if given, is told every call into the core with its inputs, the actions and
    whether each send went out (`firmware_bridge.playback.Recorder` writes them down to replay)."""

    def __init__(
        self,
        settings: BridgeSettings,
        *,
        clock: Callable[[], float] = time.monotonic,
        journal: Journal | None = None,
    ) -> None:
        self.settings = settings
        self._clock = clock
        key_bytes = None
        if settings.signing.enabled:
            key_bytes = load_signing_key(settings.signing.key_file)
            if not key_file_is_private(settings.signing.key_file):
                log.warning(
                    "signing key file %s is readable by other users (chmod 600 it)",
                    settings.signing.key_file,
                )
            serial0 = serial0_warning(settings.mavlink.connection)
            if serial0 is not None:
                log.warning(
                    "SIGNING PROTECTS NOTHING HERE: %s, where ArduPilot accepts unsigned "
                    "packets from anyone (it treats it as the trusted USB link). Connect the "
                    "bridge to a telemetry port (SERIAL1/TELEM1...; SITL: tcp 5762) and keep "
                    "SERIAL0 for setting the key up (docs/bridge.md)",
                    serial0,
                )
        self.link = MavlinkLink(settings.mavlink, key_bytes)
        self.core = BridgeCore(settings)
        self._journal = journal
        self._lock = threading.Lock()
        """Held around every call into the core and the sends it decides."""
        self._rate_log = RateLimitedLog(log)
        self._session: Any = None
        self._state_publisher: Any = None
        self._subscribers: list[Any] = []
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()
        self.error: ConfigError | None = None
        """Why zenoh could not be joined (with `start(zenoh_in_background=True)`)."""
        self._heartbeat = Heartbeat.from_env("bridge")

    @property
    def counters(self) -> Counter[str]:
        """commands, stops, dropped (arrived while the link was down), malformed, rejected
        (unsigned or badly signed MAVLink), bad_data, poses, reconnects, requests, refused."""
        return self.core.counters

    # -- life cycle ---------------------------------------------------------------------------

    def start(self, zenoh_in_background: bool = False) -> None:
        """Open the MAVLink port, start the bridge thread (heartbeat, failsafe stops, vehicle
        state), then join zenoh and subscribe.

        With `zenoh_in_background` (the daemon) zenoh is joined by a helper thread, so the
        vehicle side runs and stops the car whether or not zenoh is reachable: no zenoh is no
        command. A failure to open the session is then kept in `error`."""
        try:
            self.link.open()
        except OSError as error:
            raise ConfigError(
                f"mavlink.connection {self.settings.mavlink.connection!r} cannot be opened: {error}"
            ) from None
        self._thread = threading.Thread(target=self._loop, name="bridge", daemon=True)
        self._thread.start()
        log.info(
            "bridge up: MAVLink %s (%s output%s), command timeout %.3f s",
            self.settings.mavlink.connection,
            self.settings.output.mode,
            ", signed" if self.link.signing else "",
            self.settings.failsafe.command_timeout_s,
        )
        warn_if_uncalibrated(self.settings)
        if zenoh_in_background:
            threading.Thread(target=self._join_zenoh, name="bridge-zenoh", daemon=True).start()
            return
        try:
            self._join_zenoh(raise_errors=True)
        except ConfigError:
            self.close()
            raise

    def _join_zenoh(self, raise_errors: bool = False) -> None:
        namespace = self.settings.zenoh.namespace
        # The first decodes build the ROS type store (about 0.3 s): here, not on the first
        # command, which would otherwise reach the vehicle that much late.
        decode_twist_msg(encode_twist_msg(STOP))
        decode_pose_msg(encode_pose_msg(Pose2D(0.0, "map", 0.0, 0.0, 0.0)))
        decode_json_msg(encode_json_msg({}))
        try:
            session = open_session(self.settings.zenoh, self._stopping)
        except StoppedError:
            return
        except ConfigError as error:
            if raise_errors:
                raise
            log.error("%s", error)
            self.error = error
            return
        with self._lock:
            if self.core.closed:  # closed while connecting
                session.close()
                return
            self._session = session
            self._state_publisher = session.declare_publisher(key(VEHICLE_STATE, namespace))
            self._subscribers.append(
                session.declare_subscriber(key(COMMAND, namespace), self._on_command)
            )
            self._subscribers.append(
                session.declare_subscriber(key(VEHICLE_REQUEST, namespace), self._on_request)
            )
            # Every output, not only guided: indoors the forwarded pose is the autopilot's only
            # position, without which its GCS failsafe (FS_ACTION 6) and the brake mode
            # (GUIDED) cannot brake and the car coasts (issue 20: 6.6 s, 2.4 m in SITL).
            if self.settings.vision.forward_pose:
                self._subscribers.append(
                    session.declare_subscriber(key(POSE, namespace), self._on_pose)
                )
        log.info("zenoh joined: commands from %s", key(COMMAND, namespace))

    def close(self) -> None:
        """Refuse further commands, send stop, then disarm (if configured), and close."""
        if self._thread is None:
            return
        self._feed(self.core.refuse_commands)
        for subscriber in self._subscribers:
            subscriber.undeclare()
        self._subscribers.clear()
        self._stopping.set()
        self._thread.join()
        self._thread = None
        self._feed(self.core.shutdown, self._clock())
        while True:  # the core's exit sequence: wait for rest, disarm until acknowledged
            self._feed(self.core.exit_step, self._clock())
            until_s = self.core.exit_wait_until_s
            if until_s is None:
                break
            for message in self.link.poll(max(until_s - self._clock(), 0.0)):
                self._feed(self.core.exit_message, message, self._clock(), time.time())
        self._feed(self.core.stopped, self._clock())
        if self._session is not None:
            self._session.close()
        self.link.close()
        self._heartbeat.close()
        log.info("bridge closed")

    # -- carrying out the core's decisions ----------------------------------------------------

    def _feed(self, decide: Callable[..., list[Action]], *inputs: Any) -> None:
        """Call the core, `decide(*inputs)`, and carry out its actions in their order: the sends
        under the lock with the call, so the wire sees decisions in order; reopening the port (a
        TCP connect may take seconds) and publishing the state after it."""
        with self._lock:
            actions = decide(*inputs)
            went_out = []
            for action in actions:
                if isinstance(action, Send):
                    ok = self.link.send(action.message, as_gcs=action.as_gcs)
                    self.core.sent(action, ok)
                    went_out.append(ok)
            if self._journal is not None:
                self._journal(decide.__name__, inputs, actions, went_out)
        for action in actions:
            if isinstance(action, Reopen):
                try:
                    self.link.open()
                    log.info("reopened %s", self.settings.mavlink.connection)
                except (OSError, ConfigError) as error:
                    self._rate_log.warning("reconnect", f"cannot reopen the link: {error}")
            elif isinstance(action, Publish):
                self._publish(action.state)

    def _publish(self, state: dict[str, Any]) -> None:
        if self._state_publisher is None:
            return  # zenoh not joined yet: nobody to tell
        try:
            self._state_publisher.put(encode_json_msg({"stamp_s": time.time(), **state}))
        except Exception as error:  # zenoh errors must not stop the failsafe loop
            self._rate_log.warning("state", f"could not publish the vehicle state: {error}")

    def state(self, now: float | None = None, bridge: str = "running") -> dict[str, Any]:
        """The vehicle state message as a dict (what goes out on qnav/vehicle_state)."""
        now = self._clock() if now is None else now
        with self._lock:
            return {"stamp_s": time.time(), **self.core.state(now, bridge)}

    # -- zenoh callbacks ----------------------------------------------------------------------

    def _on_command(self, sample: Any) -> None:
        now = self._clock()
        payload = sample.payload.to_bytes()
        self._feed(self.core.command, payload, now)

    def _on_pose(self, sample: Any) -> None:
        now, wall = self._clock(), time.time()
        payload = sample.payload.to_bytes()
        self._feed(self.core.pose, payload, now, wall)

    def _on_request(self, sample: Any) -> None:
        now = self._clock()
        payload = sample.payload.to_bytes()
        self._feed(self.core.request, payload, now)

    # -- the bridge thread --------------------------------------------------------------------

    def _loop(self) -> None:
        while not self._stopping.is_set():
            now = self._clock()
            with self._lock:
                wait = (
                    min(self.core.next_deadline(now, self.link.is_open), now + LOOP_MAX_WAIT_S)
                    - now
                )
            for message in self.link.poll(max(wait, 0.0)):
                try:
                    self._feed(self.core.mavlink, message, self._clock(), time.time())
                except Exception:  # one odd message must not end the failsafe loop
                    self._rate_log.warning("handler", f"MAVLink message {message} not handled")
                    log.debug("handler error", exc_info=True)
            try:
                self._feed(self.core.tick, self._clock(), time.time(), self.link.is_open)
            except Exception:
                log.exception("bridge loop error (continuing)")
            self._heartbeat.beat(link_up=self.core.link_up, armed=self.core.armed)


def warn_if_uncalibrated(settings: BridgeSettings) -> None:
    """Say so when the manual output drives on the assumed speed scale, not the car's."""
    output = settings.output
    if output.mode != "manual" or output.speed_at_full_throttle_mps is not None:
        return
    scale = speed_scale(output)
    log.warning(
        "output.speed_at_full_throttle_mps is not measured: driving as if full throttle were "
        "%g m/s (0.5 m/s is %.1f %% throttle); measure it with `qnav calibrate-car --config "
        "FILE --write`",
        scale,
        100 * 0.5 / scale,
    )


def serve(settings: BridgeSettings) -> None:
    """Run the bridge in this (main) thread until SIGINT or SIGTERM (`qnav bridge`)."""
    with stop_on_signals(logger=log) as stop:
        bridge = Bridge(settings)
        bridge.start(zenoh_in_background=True)
        try:
            while not stop.wait(0.1):
                if bridge.error is not None:
                    raise bridge.error
        finally:
            bridge.close()
