"""The firmware bridge daemon: Twist commands from zenoh out to the autopilot over MAVLink.

Three kinds of thread meet here. zenoh's callback threads decode commands and send them at
once (the shortest path from the controller to the wire); one bridge thread reads MAVLink,
sends the heartbeat, runs the failsafe clock (`CommandGate`), reconnects and publishes the
vehicle state; and the main thread waits for SIGINT or SIGTERM, then shuts down in order:
no more commands, stop sent, disarm (if configured).

A payload that does not parse is counted and logged (rate-limited) and changes nothing: it is
not a command, so the failsafe treats it as silence.
"""

from __future__ import annotations

import argparse
import logging
import math
import signal
import threading
import time
from collections import Counter
from collections.abc import Callable
from types import FrameType, TracebackType
from typing import Any

from contracts.errors import ConfigError
from contracts.health import Heartbeat
from contracts.mavlink import (
    MAV_AUTOPILOT_INVALID,
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_SET_MODE,
    MAV_FRAME_BODY_NED,
    MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
    MAV_MODE_FLAG_SAFETY_ARMED,
    MAV_STATE_ACTIVE,
    MAV_TYPE_GCS,
    MAV_TYPE_ONBOARD_CONTROLLER,
    RC_IGNORE,
    ROVER_MODES,
    TYPE_MASK_VELOCITY_YAW_RATE,
    key_file_is_private,
    load_signing_key,
    mode_name,
    mode_number,
    ned_to_enu,
)
from contracts.settings import parse_assignments, to_toml, with_overrides
from contracts.transport import StoppedError, open_session
from contracts.wire import (
    COMMAND,
    POSE,
    STOP,
    VEHICLE_REQUEST,
    VEHICLE_STATE,
    Pose2D,
    Twist2D,
    WireError,
    decode_json_msg,
    decode_pose_msg,
    decode_twist_msg,
    encode_json_msg,
    encode_pose_msg,
    encode_twist_msg,
    key,
)
from firmware_bridge import mapping
from firmware_bridge.failsafe import CommandGate
from firmware_bridge.link import MavlinkLink, serial0_warning
from firmware_bridge.settings import BridgeSettings, load_settings

log = logging.getLogger("firmware_bridge")

LOOP_MAX_WAIT_S = 0.1
"""The bridge thread looks at its clocks at least this often (requests from zenoh wait for it)."""
MODE_SETTLE_S = 1.5
"""A requested mode counts as taken once the heartbeats showed it this long: Rover may undo a
mode right after boot (INITIAL_MODE, the RC mode switch's first reading; seen in SITL), and the
bridge asks again then."""
EXIT_ACK_WAIT_S = 0.2
"""On shutdown, how long to wait for the disarm to be acknowledged before sending it again."""


class RateLimitedLog:
    """Warnings that may repeat fast (malformed payloads), at most one per key and period."""

    def __init__(self, logger: logging.Logger, period_s: float = 5.0) -> None:
        self._logger = logger
        self._period_s = period_s
        self._last_s: dict[str, float] = {}
        self._suppressed: Counter[str] = Counter()
        self._lock = threading.Lock()

    def warning(self, what: str, message: str, *args: object) -> None:
        """Log `message` unless `what` was logged within the period (then count it)."""
        now = time.monotonic()
        with self._lock:
            if now - self._last_s.get(what, -math.inf) < self._period_s:
                self._suppressed[what] += 1
                return
            self._last_s[what] = now
            suppressed, self._suppressed[what] = self._suppressed[what], 0
        suffix = f" ({suppressed} more since the last report)" if suppressed else ""
        self._logger.warning(message + suffix, *args)


class Bridge:
    """zenoh to MAVLink with a failsafe; `start()` it, `close()` it (or use `with`)."""

    def __init__(
        self, settings: BridgeSettings, *, clock: Callable[[], float] = time.monotonic
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
        self._gate = CommandGate(
            settings.failsafe.command_timeout_s, settings.failsafe.stop_period_s
        )
        self._lock = threading.Lock()
        self._rate_log = RateLimitedLog(log)
        self.counters: Counter[str] = Counter()
        """commands, stops, dropped (arrived while the link was down), malformed, rejected
        (unsigned or badly signed MAVLink), bad_data, poses, reconnects, requests."""
        self._guided = settings.output.mode == "guided"
        self._stop_message = self._command_message(STOP)
        self._as_gcs = not self._guided
        # Vehicle state, written by the bridge thread, read under the lock.
        self._link_up = False
        self._ever_up = False
        self._last_heartbeat_s = -math.inf
        self._armed: bool | None = None
        self._custom_mode: int | None = None
        self._position_ned: tuple[float, float, float] | None = None
        self._speed_mps: float | None = None
        """Ground speed from the newest LOCAL_POSITION_NED (None before the first)."""
        self._speed_s = -math.inf
        self._velocity_ned: tuple[float, float] | None = None
        self._yaw_rate_ned: float | None = None
        self._braking = False
        """True from a stop that switched to `failsafe.brake_mode` until the next command."""
        self._brake_mode = (
            mode_number(settings.failsafe.brake_mode) if settings.failsafe.brake_mode else None
        )
        self._yaw_ned: float | None = None
        self._battery: dict[str, float] | None = None
        self._last_ack: dict[str, Any] | None = None
        # Requests (arm, mode) the bridge keeps sending until the heartbeat shows them.
        self._want_mode: int | None = None
        self._want_armed: bool | None = None
        self._request_attempts = 0
        self._mode_since_s = -math.inf
        self._origin_confirmed = False
        """True once the vehicle reported GPS_GLOBAL_ORIGIN (its EKF has an origin)."""
        self._request_since_s = -math.inf
        self._request_status: str | None = None
        self._vehicle_text: str | None = None
        self._next_request_s = -math.inf
        self._pose_since_link_up = False
        self._waiting_for_pose_logged = False
        self._next_heartbeat_s = -math.inf
        self._next_state_s = -math.inf
        self._next_reconnect_s = -math.inf
        self._state_dirty = True
        self._session: Any = None
        self._state_publisher: Any = None
        self._subscribers: list[Any] = []
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()
        self.error: ConfigError | None = None
        """Why zenoh could not be joined (with `start(zenoh_in_background=True)`)."""
        self._heartbeat = Heartbeat.from_env("bridge")

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
            if self._gate.closed:  # closed while connecting
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
        with self._lock:
            self._gate.close()
        for subscriber in self._subscribers:
            subscriber.undeclare()
        self._subscribers.clear()
        self._stopping.set()
        self._thread.join()
        self._thread = None
        failsafe = self.settings.failsafe
        for _ in range(failsafe.stop_repeats_on_exit):
            self._send_stop(self._clock())
        log.info("sent stop %d times on exit", failsafe.stop_repeats_on_exit)
        if self._brake_mode is not None and self._link_up:
            self._send_command_long(
                MAV_CMD_DO_SET_MODE, MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, self._brake_mode
            )
            log.info("exit: switching to %s to brake", mode_name(self._brake_mode))
        if failsafe.disarm_on_exit:
            self._wait_for_rest()
            self._disarm_on_exit()
        self._publish_state(self._clock(), bridge="stopped")
        if self._session is not None:
            self._session.close()
        self.link.close()
        self._heartbeat.close()
        log.info("bridge closed")

    def __enter__(self) -> Bridge:
        self.start()
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        trace: TracebackType | None,
    ) -> None:
        self.close()

    # -- what goes on the wire ----------------------------------------------------------------

    def _command_message(self, twist: Twist2D) -> Any:
        """The MAVLink message that carries `twist` in the configured output mode."""
        output, target = self.settings.output, self.settings.mavlink
        encoder = self.link.encoder
        if output.mode == "guided":
            velocity = mapping.velocity_target(twist, output)
            return encoder.set_position_target_local_ned_encode(
                0,
                target.vehicle_system_id,
                target.vehicle_component_id,
                MAV_FRAME_BODY_NED,
                TYPE_MASK_VELOCITY_YAW_RATE,
                0.0,
                0.0,
                0.0,
                velocity.forward_mps,
                0.0,
                0.0,
                0.0,
                0.0,
                0.0,
                0.0,
                velocity.yaw_rate_radps,
            )
        if output.manual_message == "manual_control":
            axes = mapping.manual_control(twist, output)
            return encoder.manual_control_encode(target.vehicle_system_id, 0, axes.y, axes.z, 0, 0)
        pwm = mapping.rc_override(twist, output)
        return encoder.rc_channels_override_encode(
            target.vehicle_system_id,
            target.vehicle_component_id,
            pwm.steering_pwm_us,
            RC_IGNORE,
            pwm.throttle_pwm_us,
            *([RC_IGNORE] * 5),
        )

    def _send_stop(self, now_s: float) -> None:
        with self._lock:
            if self.link.send(self._stop_message, as_gcs=self._as_gcs):
                self.counters["stops"] += 1
            self._gate.stop_sent(now_s)

    def _brake(self, now: float) -> None:
        """A moving car was just stopped: switch to the braking mode, if one is set."""
        if self._brake_mode is None or self._brake_mode == self.settings.rover_mode:
            return
        with self._lock:
            self._braking = True
            self._want_mode = self._brake_mode
            self._request_since_s = now
            self._request_attempts = 0
            self._next_request_s = -math.inf
        log.info("stopped: switching to %s to brake", mode_name(self._brake_mode))

    def _send_command_long(self, command: int, *params: float) -> None:
        target = self.settings.mavlink
        padded = (list(params) + [0.0] * 7)[:7]
        self.link.send(
            self.link.encoder.command_long_encode(
                target.vehicle_system_id, target.vehicle_component_id, command, 0, *padded
            )
        )

    def _send_heartbeat(self) -> None:
        encoder = self.link.encoder
        self.link.send(
            encoder.heartbeat_encode(
                MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE
            )
        )
        if self.settings.mavlink.gcs_heartbeat:
            self.link.send(
                encoder.heartbeat_encode(
                    MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE
                ),
                as_gcs=True,
            )

    def _send_origin(self) -> None:
        vision = self.settings.vision
        lat, lon, alt = mapping.origin_e7(
            vision.origin_lat_deg, vision.origin_lon_deg, vision.origin_alt_m
        )
        self.link.send(
            self.link.encoder.set_gps_global_origin_encode(
                self.settings.mavlink.vehicle_system_id, lat, lon, alt, int(time.time() * 1e6)
            )
        )
        log.debug("EKF origin sent (%.6f, %.6f, %.1f m)", *_origin(self.settings))

    # -- zenoh callbacks ----------------------------------------------------------------------

    def _on_command(self, sample: Any) -> None:
        now = self._clock()
        try:
            twist = decode_twist_msg(sample.payload.to_bytes())
        except WireError as error:
            self._malformed("command", error)
            return
        absurd = mapping.implausible(
            twist, self.settings.output, self.settings.failsafe.implausible_factor
        )
        if absurd is not None:
            # Nobody meant this: count it, and stop rather than keep the last command.
            self._malformed("command", ValueError(absurd))
            with self._lock:
                self.link.send(self._stop_message, as_gcs=self._as_gcs)
            return
        message = self._command_message(twist)
        with self._lock:
            if not self._gate.accept_command(now):
                self.counters["dropped"] += 1
                return
            if self._braking:
                # Back to the output's mode at once: the command below takes effect with it.
                self._braking = False
                self._want_mode = self.settings.rover_mode
                self._request_since_s = now
                self._request_attempts = 0
                self._next_request_s = now + self.settings.vehicle.request_retry_s
                self._send_command_long(
                    MAV_CMD_DO_SET_MODE, MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, self._want_mode
                )
            if self.link.send(message, as_gcs=self._as_gcs):
                self.counters["commands"] += 1

    def _on_pose(self, sample: Any) -> None:
        try:
            pose = decode_pose_msg(sample.payload.to_bytes())
        except WireError as error:
            self._malformed("pose", error)
            return
        problem = mapping.pose_problem(pose, self.settings.vision.max_position_m)
        if problem is not None:  # finite, so the decoder took it, but no place anyone measured
            self._malformed("pose", ValueError(problem))
            return
        if not self._link_up:
            return
        ned = mapping.vision_pose(pose)
        usec = int((pose.stamp_s if pose.stamp_s > 0 else time.time()) * 1e6)
        self.link.send(
            self.link.encoder.vision_position_estimate_encode(
                usec, ned.north_m, ned.east_m, ned.down_m, 0.0, 0.0, ned.yaw_rad
            )
        )
        self._pose_since_link_up = True
        self.counters["poses"] += 1

    def _on_request(self, sample: Any) -> None:
        try:
            request = decode_json_msg(sample.payload.to_bytes())
            arm, mode = _parse_request(request)
        except (WireError, ValueError) as error:
            self._malformed("request", error)
            return
        if arm is True and not self.settings.vehicle.remote_arming:
            with self._lock:
                self.counters["refused"] += 1
            self._rate_log.warning(
                "remote arming", "refused an arm request: vehicle.remote_arming is off"
            )
            return
        log.info("request: %s", request)
        with self._lock:
            if arm is not None:
                self._want_armed = arm
            if mode is not None:
                self._want_mode = mode
            self._request_attempts = 0
            self._request_since_s = self._clock()
            self._next_request_s = -math.inf
            self.counters["requests"] += 1

    def _malformed(self, what: str, error: Exception) -> None:
        with self._lock:
            self.counters["malformed"] += 1
        self._rate_log.warning(f"malformed {what}", "ignored a malformed %s: %s", what, error)

    # -- the bridge thread --------------------------------------------------------------------

    def _loop(self) -> None:
        while not self._stopping.is_set():
            now = self._clock()
            wait = min(self._next_deadline(now), now + LOOP_MAX_WAIT_S) - now
            for message in self.link.poll(max(wait, 0.0)):
                try:
                    self._on_mavlink(message, self._clock())
                except Exception:  # one odd message must not end the failsafe loop
                    self._rate_log.warning("handler", "MAVLink message %s not handled", message)
                    log.debug("handler error", exc_info=True)
            try:
                self._duties(self._clock())
            except Exception:
                log.exception("bridge loop error (continuing)")
            self._heartbeat.beat(link_up=self._link_up, armed=self._armed)

    def _next_deadline(self, now: float) -> float:
        """When the bridge thread must next act, whatever arrives before."""
        with self._lock:
            deadlines = [self._gate.next_check_s(now), self._next_heartbeat_s, self._next_state_s]
            if self._want_mode is not None or self._want_armed is not None:
                deadlines.append(self._next_request_s)
        if self._link_up:
            deadlines.append(self._last_heartbeat_s + self.settings.mavlink.link_timeout_s)
        else:
            deadlines.append(self._next_reconnect_s)
        return min(deadlines)

    def _duties(self, now: float) -> None:
        with self._lock:
            was_driving = self._gate.was_driving
            stop_due = self._gate.stop_due(now)
        if stop_due:
            self._send_stop(now)
            if was_driving:
                self._brake(now)
        if now >= self._next_heartbeat_s:
            self._send_heartbeat()
            self._next_heartbeat_s = now + self.settings.mavlink.heartbeat_period_s
        self._watch_link(now)
        self._send_requests(now)
        if self._state_dirty or now >= self._next_state_s:
            self._publish_state(now)

    def _watch_link(self, now: float) -> None:
        mavlink = self.settings.mavlink
        if self._link_up and now - self._last_heartbeat_s > mavlink.link_timeout_s:
            with self._lock:
                self._gate.set_link(False)
                self._link_up = False
            self._state_dirty = True
            self._next_reconnect_s = now + mavlink.reconnect_period_s
            log.warning(
                "vehicle link down: no heartbeat for %g s; stopping, reconnecting every %g s",
                mavlink.link_timeout_s,
                mavlink.reconnect_period_s,
            )
        reconnect = self._ever_up or not self.link.is_open
        if not self._link_up and reconnect and now >= self._next_reconnect_s:
            self._next_reconnect_s = now + mavlink.reconnect_period_s
            self.counters["reconnects"] += 1
            try:
                self.link.open()
                log.info("reopened %s", mavlink.connection)
            except (OSError, ConfigError) as error:
                self._rate_log.warning("reconnect", "cannot reopen the link: %s", error)

    def _link_came_up(self, now: float) -> None:
        with self._lock:
            self._gate.set_link(True)
            self._link_up = True
            self._origin_confirmed = False  # a rebooted autopilot lost it
            self._pose_since_link_up = False
            if not self._ever_up:
                vehicle = self.settings.vehicle
                if vehicle.set_mode_on_connect:
                    self._want_mode = self.settings.rover_mode
                if vehicle.arm_on_connect:
                    self._want_armed = True
                self._request_attempts = 0
                self._request_since_s = now
                self._next_request_s = -math.inf
        self._ever_up = True
        self._state_dirty = True
        log.info(
            "vehicle link up (system %d); stop until a fresh command",
            self.settings.mavlink.vehicle_system_id,
        )
        if self._guided:
            self._send_origin()

    def _send_requests(self, now: float) -> None:
        if not self._link_up or now < self._next_request_s:
            return
        vehicle = self.settings.vehicle
        self._next_request_s = now + vehicle.request_retry_s
        # GUIDED needs a position estimate: ask for it only once a pose went to the autopilot.
        forward_pose = self.settings.vision.forward_pose
        needs_pose = self._guided and forward_pose
        # The EKF origin: in guided output from the link's start (as the mode waits on it); in
        # a manual output only once a pose went out, so a car on GPS without a motion-capture
        # publisher never gets an origin from the bridge.
        wants_origin = needs_pose or (forward_pose and self._pose_since_link_up)
        if (
            wants_origin
            and not self._origin_confirmed
            and self._custom_mode not in (None, ROVER_MODES["INITIALISING"])
        ):
            # An origin sent while the EKF still starts is dropped ("AHRS: waiting for home"
            # in SITL): again until the vehicle reports GPS_GLOBAL_ORIGIN.
            self._send_origin()
        with self._lock:
            mode_held = self._want_mode is not None and self._custom_mode == self._want_mode
            if mode_held and now - self._mode_since_s >= MODE_SETTLE_S:
                self._want_mode = None
            if self._want_armed is not None and self._armed == self._want_armed:
                self._want_armed = None
            want_mode, want_armed = self._want_mode, self._want_armed
            if mode_held:
                want_mode = None  # there now: watch that it holds, without asking again
            if want_mode == ROVER_MODES["GUIDED"] and needs_pose and not self._pose_since_link_up:
                if not self._waiting_for_pose_logged:
                    log.info("waiting for a motion-capture pose before asking for GUIDED")
                    self._waiting_for_pose_logged = True
                want_mode = None
            if self._custom_mode == ROVER_MODES["INITIALISING"]:
                # Rover ends its boot by switching to INITIAL_MODE: a mode taken before that
                # is undone (seen in SITL), so ask only once the vehicle is up.
                if want_mode is not None or want_armed is not None:
                    self._set_request_status("waiting for the vehicle to initialise")
                return
            if want_mode is None and want_armed is None:
                if (self._request_status or "").startswith(("asking", "waiting")):
                    self._set_request_status(None)  # done (a give-up stays reported)
                return
            waited_s = now - self._request_since_s
            if 0 < vehicle.request_timeout_s <= waited_s:
                self._want_mode = self._want_armed = None
                self._set_request_status(
                    f"gave up on {_describe(want_mode, want_armed)} after "
                    f"{self._request_attempts} tries in {waited_s:.1f} s"
                )
                log.warning(
                    "vehicle did not take %s in %.1f s (%d tries; vehicle.request_timeout_s); "
                    "giving up",
                    _describe(want_mode, want_armed),
                    waited_s,
                    self._request_attempts,
                )
                return
            self._request_attempts += 1
            self._set_request_status(
                f"asking for {_describe(want_mode, want_armed)} "
                f"(try {self._request_attempts}, {waited_s:.1f} s)"
            )
        if want_mode is not None:
            self._send_command_long(
                MAV_CMD_DO_SET_MODE, MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, want_mode
            )
        if want_armed is not None:
            self._send_command_long(MAV_CMD_COMPONENT_ARM_DISARM, 1.0 if want_armed else 0.0)
        log.info("asked the vehicle for %s", _describe(want_mode, want_armed))

    def _set_request_status(self, status: str | None) -> None:
        """What the bridge is asking of the vehicle (called under the lock)."""
        if status != self._request_status:
            self._request_status = status
            self._state_dirty = True

    def _on_mavlink(self, message: Any, now: float) -> None:
        kind = message.get_type()
        if kind == "BAD_DATA":
            reason = str(getattr(message, "reason", ""))
            counter = "rejected" if "signature" in reason.lower() else "bad_data"
            with self._lock:
                self.counters[counter] += 1
            self._rate_log.warning(counter, "refused a MAVLink packet: %s", reason)
            return
        target = self.settings.mavlink
        if message.get_srcSystem() != target.vehicle_system_id:
            return
        if kind == "HEARTBEAT":
            if (
                message.get_srcComponent() != target.vehicle_component_id
                or message.autopilot == MAV_AUTOPILOT_INVALID
            ):
                return
            armed = bool(message.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)
            self._last_heartbeat_s = now
            if not self._link_up:
                self._link_came_up(now)
            with self._lock:
                if armed != self._armed or message.custom_mode != self._custom_mode:
                    log.info(
                        "vehicle %s in %s",
                        "armed" if armed else "disarmed",
                        mode_name(message.custom_mode),
                    )
                    self._state_dirty = True
                if int(message.custom_mode) != self._custom_mode:
                    self._mode_since_s = now
                self._armed, self._custom_mode = armed, int(message.custom_mode)
                # Done is done: a request met once is not sent again after a reconnect. A mode
                # must hold for MODE_SETTLE_S first (`_send_requests`).
                if self._want_armed == armed:
                    self._want_armed = None
        elif kind == "LOCAL_POSITION_NED":
            with self._lock:
                self._position_ned = (float(message.x), float(message.y), float(message.z))
                self._speed_mps = math.hypot(float(message.vx), float(message.vy))
                self._speed_s = now
                self._velocity_ned = (float(message.vx), float(message.vy))
        elif kind == "GPS_GLOBAL_ORIGIN":
            if not self._origin_confirmed:
                log.info("vehicle has its EKF origin")
            self._origin_confirmed = True
        elif kind == "ATTITUDE":
            with self._lock:
                self._yaw_ned = float(message.yaw)
                self._yaw_rate_ned = float(message.yawspeed)
        elif kind == "SYS_STATUS":
            battery: dict[str, float] = {}
            if message.voltage_battery != 0xFFFF:
                battery["voltage_v"] = message.voltage_battery / 1000.0
            if message.current_battery != -1:
                battery["current_a"] = message.current_battery / 100.0
            if message.battery_remaining != -1:
                battery["remaining_pct"] = float(message.battery_remaining)
            with self._lock:
                self._battery = battery or None
        elif kind == "COMMAND_ACK":
            with self._lock:
                self._last_ack = {"command": int(message.command), "result": int(message.result)}
            log.info("vehicle answered command %d with result %d", message.command, message.result)
        elif kind == "STATUSTEXT":
            text = str(message.text)
            log.info("vehicle says: %s", text)
            with self._lock:
                self._vehicle_text = text  # arming refusals say why: users see it in the state
            self._state_dirty = True

    # -- state on zenoh -----------------------------------------------------------------------

    def state(self, now: float | None = None, bridge: str = "running") -> dict[str, Any]:
        """The vehicle state message as a dict (what goes out on qnav/vehicle_state)."""
        now = self._clock() if now is None else now
        with self._lock:
            position = None
            if self._position_ned is not None:
                yaw_ned = self._yaw_ned if self._yaw_ned is not None else math.pi / 2
                x, y, yaw = ned_to_enu(self._position_ned[0], self._position_ned[1], yaw_ned)
                position = {"x_m": x, "y_m": y, "z_m": -self._position_ned[2]}
                if self._yaw_ned is not None:
                    position["yaw_rad"] = yaw
            return {
                "stamp_s": time.time(),
                "bridge": bridge,
                "link_up": self._link_up,
                "armed": self._armed,
                "mode": None if self._custom_mode is None else mode_name(self._custom_mode),
                "output": self.settings.output.mode,
                "driving": self._gate.driving(now),
                "position": position,
                "velocity": _velocity(self._velocity_ned, self._yaw_ned, self._yaw_rate_ned),
                "battery": self._battery,
                "last_ack": self._last_ack,
                "request": self._request_status,
                "vehicle_text": self._vehicle_text,
                "counters": dict(self.counters),
            }

    def _publish_state(self, now: float, bridge: str = "running") -> None:
        self._state_dirty = False
        self._next_state_s = now + self.settings.vehicle.state_period_s
        if self._state_publisher is None:
            return  # zenoh not joined yet: nobody to tell
        try:
            self._state_publisher.put(encode_json_msg(self.state(now, bridge)))
        except Exception as error:  # zenoh errors must not stop the failsafe loop
            self._rate_log.warning("state", "could not publish the vehicle state: %s", error)

    def _wait_for_rest(self) -> None:
        """Keep stopping until the vehicle reports rest (or `rest_timeout_s`): a car disarmed
        while moving loses its brakes and coasts. Without speed reports there is nothing to
        wait for."""
        failsafe = self.settings.failsafe
        start = self._clock()
        deadline = start + failsafe.rest_timeout_s
        next_stop = start + failsafe.stop_period_s
        while self._link_up and self._speed_mps is not None:
            now = self._clock()
            fresh = now - self._speed_s < 1.0
            if fresh and self._speed_mps < failsafe.rest_speed_mps:
                log.info("exit: vehicle at rest after %.2f s", now - start)
                return
            if now >= deadline:
                log.warning(
                    "exit: vehicle not reported at rest within %g s (failsafe.rest_timeout_s)",
                    failsafe.rest_timeout_s,
                )
                return
            if now >= next_stop:
                self._send_stop(now)
                next_stop = now + failsafe.stop_period_s
            for message in self.link.poll(min(deadline, next_stop) - now):
                try:
                    self._on_mavlink(message, self._clock())
                except Exception:
                    log.debug("handler error", exc_info=True)

    def _disarm_on_exit(self) -> None:
        """Send disarm until acknowledged (or a few tries), reading replies here. With the link
        down nobody would answer: one disarm is sent, and the bridge does not wait."""
        if not self._link_up:
            self._send_command_long(MAV_CMD_COMPONENT_ARM_DISARM, 0.0)
            log.warning("disarm on exit: sent once; the vehicle's link is down")
            return
        for _ in range(3):
            self._send_command_long(MAV_CMD_COMPONENT_ARM_DISARM, 0.0)
            deadline = self._clock() + EXIT_ACK_WAIT_S
            while self._clock() < deadline:
                for message in self.link.poll(deadline - self._clock()):
                    if (
                        message.get_type() == "COMMAND_ACK"
                        and message.command == MAV_CMD_COMPONENT_ARM_DISARM
                    ):
                        log.info("disarm on exit: vehicle answered %d", message.result)
                        return
        log.warning("disarm on exit: no answer from the vehicle")


def _velocity(
    velocity_ned: tuple[float, float] | None, yaw_ned: float | None, yaw_rate_ned: float | None
) -> dict[str, float] | None:
    """The vehicle's own velocity in our terms: forward speed along its heading (m/s, negative
    backwards) and turn rate (rad/s, counter-clockwise), from LOCAL_POSITION_NED and ATTITUDE."""
    if velocity_ned is None or yaw_ned is None or yaw_rate_ned is None:
        return None
    north, east = velocity_ned
    forward = north * math.cos(yaw_ned) + east * math.sin(yaw_ned)
    return {
        "forward_mps": forward,
        "speed_mps": math.hypot(north, east),
        "turn_rate_radps": -yaw_rate_ned,
    }


def _parse_request(request: dict[str, Any]) -> tuple[bool | None, int | None]:
    """(arm, mode) from a vehicle request such as {"arm": true, "mode": "GUIDED"}."""
    unknown = set(request) - {"arm", "mode"}
    if unknown or not request:
        raise ValueError(f"a request has keys arm and/or mode, got {sorted(request)}")
    arm = request.get("arm")
    if arm is not None and not isinstance(arm, bool):
        raise ValueError(f"arm must be true or false, got {arm!r}")
    mode = request.get("mode")
    return arm, None if mode is None else mode_number(mode)


def _describe(mode: int | None, armed: bool | None) -> str:
    parts = [] if mode is None else [f"mode {mode_name(mode)}"]
    parts += [] if armed is None else ["arm" if armed else "disarm"]
    return " and ".join(parts)


def _origin(settings: BridgeSettings) -> tuple[float, float, float]:
    vision = settings.vision
    return vision.origin_lat_deg, vision.origin_lon_deg, vision.origin_alt_m


def run(args: argparse.Namespace) -> int:
    """`qnav bridge`: run until SIGINT or SIGTERM."""
    settings = load_settings(args.config)
    if args.assignments:
        settings = with_overrides(settings, parse_assignments(args.assignments))
    if args.print_config:
        print(to_toml(settings), end="")
        return 0
    logging.basicConfig(
        level=getattr(logging, args.log_level.upper()),
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
    )
    stop = threading.Event()

    def on_signal(number: int, frame: FrameType | None) -> None:
        log.info("%s: stopping", signal.Signals(number).name)
        stop.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    bridge = Bridge(settings)
    try:
        bridge.start(zenoh_in_background=True)
        try:
            while not stop.wait(0.1):
                if bridge.error is not None:
                    raise bridge.error
        finally:
            bridge.close()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
