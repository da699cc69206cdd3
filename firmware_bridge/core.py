"""The bridge's decisions without I/O: zenoh payloads, MAVLink messages and time in, actions out.

`BridgeCore` is everything the bridge decides: what MAVLink goes out for a command, a pose or
a vehicle request; arming and mode requests and their retries; the failsafe's stops after
command silence (`CommandGate`) and the brake mode; the link coming up and going down on the
autopilot's heartbeat, and when to reopen the port; malformed payloads and refused packets
counted and logged, never sent; the vehicle state reported on zenoh; and the exit sequence
(stops, brake mode, wait for rest, disarm until acknowledged).

It reads no clock and opens no socket, like the controller's `controller.decision.Controller`:
every call takes the monotonic time `now_s` (and the wall time `wall_s` where a MAVLink field
carries one), and returns the actions for the shell to carry out in order. The shell
(`firmware_bridge.daemon.Bridge`) owns zenoh, the MAVLink port and the thread, calls the core
under one lock and sends what it returns under the same lock, so the wire sees the decisions in
their order. The same inputs give the same actions: `firmware_bridge.playback` replays recorded
inputs through a fresh core and compares the actions with references kept in the repo.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import dataclass
from typing import Any

from qnav.contracts.daemon import RateLimitedLog
from qnav.contracts.mavlink import (
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
    mavutil,
    mode_name,
    mode_number,
    ned_to_enu,
)
from qnav.contracts.wire import (
    STOP,
    Twist2D,
    WireError,
    decode_json_msg,
    decode_pose_msg,
    decode_twist_msg,
)
from qnav.firmware_bridge import mapping
from qnav.firmware_bridge.failsafe import CommandGate
from qnav.firmware_bridge.settings import BridgeSettings

log = logging.getLogger("qnav.firmware_bridge")

MODE_SETTLE_S = 1.5
"""A requested mode counts as taken once the heartbeats showed it this long: Rover may undo a
mode right after boot (INITIAL_MODE, the RC mode switch's first reading; seen in SITL), and the
bridge asks again then."""
EXIT_ACK_WAIT_S = 0.2
"""On shutdown, how long to wait for the disarm to be acknowledged before sending it again."""
EXIT_DISARM_TRIES = 3
"""On shutdown, how many disarms are sent without an acknowledgement before giving up."""
SPEED_FRESH_S = 1.0
"""On shutdown, a speed report older than this does not show the vehicle at rest."""


@dataclass(frozen=True)
class Send:
    """Send `message` to the autopilot."""

    message: Any
    """A pymavlink message object (built by the core's encoder; packed by the link)."""
    as_gcs: bool = False
    """Send with the ground station's system id (RC override, MANUAL_CONTROL) instead of the
    companion computer's."""
    counter: str | None = None
    """The counter to add one to if the send succeeded (`BridgeCore.sent`)."""


@dataclass(frozen=True)
class Reopen:
    """Reopen the MAVLink port (counted in `reconnects` already)."""


@dataclass(frozen=True)
class Publish:
    """Publish the vehicle state on zenoh (the shell adds the wall-clock `stamp_s`)."""

    state: dict[str, Any]
    """`BridgeCore.state` at the time of the decision."""


Action = Send | Reopen | Publish


class BridgeCore:
    """Every decision of the bridge; no clock, no socket, no thread (module docstring)."""

    def __init__(self, settings: BridgeSettings) -> None:
        self.settings = settings
        self.encoder: Any = mavutil().mavlink.MAVLink(None)
        """Builds the message objects of `Send` (building sends nothing)."""
        self.gate = CommandGate(
            settings.failsafe.command_timeout_s, settings.failsafe.stop_period_s
        )
        self.rate_log = RateLimitedLog(log)
        self.counters: Counter[str] = Counter()
        """commands, stops, dropped (arrived while the link was down), malformed, rejected
        (unsigned or badly signed MAVLink), bad_data, poses, reconnects, requests, refused."""
        self._guided = settings.output.mode == "guided"
        self._as_gcs = not self._guided
        self._stop_message = self._command_message(STOP)
        self._brake_mode = (
            mode_number(settings.failsafe.brake_mode) if settings.failsafe.brake_mode else None
        )
        # What the vehicle reported.
        self.link_up = False
        self._ever_up = False
        self._last_heartbeat_s = -math.inf
        self.armed: bool | None = None
        self._custom_mode: int | None = None
        self._position_ned: tuple[float, float, float] | None = None
        self._speed_mps: float | None = None
        """Ground speed from the newest LOCAL_POSITION_NED (None before the first)."""
        self._speed_s = -math.inf
        self._velocity_ned: tuple[float, float] | None = None
        self._yaw_ned: float | None = None
        self._yaw_rate_ned: float | None = None
        self._battery: dict[str, float] | None = None
        self._last_ack: dict[str, Any] | None = None
        self._vehicle_text: str | None = None
        self._origin_confirmed = False
        """True once the vehicle reported GPS_GLOBAL_ORIGIN (its EKF has an origin)."""
        # What the bridge asks of the vehicle (arm, mode), again until the heartbeat shows it.
        self._braking = False
        """True from a stop that switched to `failsafe.brake_mode` until the next command."""
        self._moving_command = False
        """Whether the last command forwarded asked for motion (a zero one after it brakes)."""
        self._want_mode: int | None = None
        self._want_armed: bool | None = None
        self._request_attempts = 0
        self._request_since_s = -math.inf
        self._request_status: str | None = None
        self._next_request_s = -math.inf
        self._mode_since_s = -math.inf
        self._pose_since_link_up = False
        self._waiting_for_pose_logged = False
        # The bridge's own clocks.
        self._next_heartbeat_s = -math.inf
        self._next_state_s = -math.inf
        self._next_reconnect_s = -math.inf
        self._state_dirty = True
        # The exit sequence (`shutdown`, then `exit_step` until `exit_wait_until_s` is None).
        self._exit_phase = "running"
        self._rest_start_s = 0.0
        self._rest_deadline_s = 0.0
        """When the exit stops waiting for rest: `rest_timeout_s` after the car last slowed."""
        self._brake_deadline_s = 0.0
        self._slowest_mps = math.inf
        """The lowest fresh speed reported since the exit began (braking is progress on it)."""
        self._next_exit_stop_s = 0.0
        self._disarm_tries = 0
        self._disarm_deadline_s = -math.inf
        self.exit_wait_until_s: float | None = None
        """After `exit_step`: read the port until then before the next step (None: done)."""

    @property
    def closed(self) -> bool:
        """True once `refuse_commands` (or `shutdown`) ran: no command goes out any more."""
        return self.gate.closed

    def sent(self, action: Send, ok: bool) -> None:
        """The shell sent `action` (`ok`: the port took it): count it if it went out."""
        if ok and action.counter is not None:
            self.counters[action.counter] += 1

    # -- zenoh in -----------------------------------------------------------------------------

    def command(self, payload: bytes, now_s: float) -> list[Action]:
        """A Twist command arrived: the output message if the failsafe lets it through."""
        try:
            twist = decode_twist_msg(payload)
        except WireError as error:
            self._malformed("command", error, now_s)
            return []
        absurd = mapping.implausible(
            twist, self.settings.output, self.settings.failsafe.implausible_factor
        )
        if absurd is not None:
            # Nobody meant this: count it, and stop rather than keep the last command.
            self._malformed("command", ValueError(absurd), now_s)
            return [Send(self._stop_message, self._as_gcs)]
        message = self._command_message(twist)
        if not self.gate.accept_command(now_s):
            self.counters["dropped"] += 1
            return []
        actions: list[Action] = []
        moving = twist.linear_mps != 0.0 or twist.angular_radps != 0.0
        if not moving and self._moving_command:
            # The controller stopped a car it was driving (an emergency stop, a stale input, a
            # reached target): brake as for silence. Its stops keep coming every period, so
            # silence never would, and on neutral sticks Rover coasts.
            self._brake(now_s)
        elif moving and self._braking:
            # Back to the output's mode at once: the command below takes effect with it.
            self._braking = False
            self._want_mode = self.settings.rover_mode
            self._request_since_s = now_s
            self._request_attempts = 0
            self._next_request_s = now_s + self.settings.vehicle.request_retry_s
            actions.append(self._set_mode(self._want_mode))
        self._moving_command = moving
        actions.append(Send(message, self._as_gcs, "commands"))
        return actions

    def pose(self, payload: bytes, now_s: float, wall_s: float) -> list[Action]:
        """A motion-capture pose arrived: forwarded as VISION_POSITION_ESTIMATE while the link
        is up (stamped with the pose's own time, or `wall_s` when it has none)."""
        try:
            pose = decode_pose_msg(payload)
        except WireError as error:
            self._malformed("pose", error, now_s)
            return []
        problem = mapping.pose_problem(pose, self.settings.vision.max_position_m)
        if problem is not None:  # finite, so the decoder took it, but no place anyone measured
            self._malformed("pose", ValueError(problem), now_s)
            return []
        if not self.link_up:
            return []
        ned = mapping.vision_pose(pose)
        usec = int((pose.stamp_s if pose.stamp_s > 0 else wall_s) * 1e6)
        self._pose_since_link_up = True
        message = self.encoder.vision_position_estimate_encode(
            usec, ned.north_m, ned.east_m, ned.down_m, 0.0, 0.0, ned.yaw_rad
        )
        return [Send(message, counter="poses")]

    def request(self, payload: bytes, now_s: float) -> list[Action]:
        """A vehicle request ({"arm": true, "mode": "GUIDED"}) arrived: remembered, and asked
        of the vehicle by `tick` until its heartbeat shows it."""
        try:
            request = decode_json_msg(payload)
            arm, mode = parse_request(request)
        except (WireError, ValueError) as error:
            self._malformed("request", error, now_s)
            return []
        if arm is True and not self.settings.vehicle.remote_arming:
            self.counters["refused"] += 1
            self.rate_log.warning(
                "remote arming", "refused an arm request: vehicle.remote_arming is off", now_s
            )
            return []
        log.info("request: %s", request)
        if arm is not None:
            self._want_armed = arm
        if mode is not None:
            self._want_mode = mode
        self._request_attempts = 0
        self._request_since_s = now_s
        self._next_request_s = -math.inf
        self.counters["requests"] += 1
        return []

    def _malformed(self, what: str, error: Exception, now_s: float) -> None:
        self.counters["malformed"] += 1
        self.rate_log.warning(f"malformed {what}", f"ignored a malformed {what}: {error}", now_s)

    # -- MAVLink in ---------------------------------------------------------------------------

    def mavlink(self, message: Any, now_s: float, wall_s: float) -> list[Action]:
        """A MAVLink message (or BAD_DATA) arrived from the port."""
        kind = message.get_type()
        if kind == "BAD_DATA":
            reason = str(getattr(message, "reason", ""))
            counter = "rejected" if "signature" in reason.lower() else "bad_data"
            self.counters[counter] += 1
            self.rate_log.warning(counter, f"refused a MAVLink packet: {reason}", now_s)
            return []
        target = self.settings.mavlink
        if message.get_srcSystem() != target.vehicle_system_id:
            return []
        actions: list[Action] = []
        if kind == "HEARTBEAT":
            if (
                message.get_srcComponent() != target.vehicle_component_id
                or message.autopilot == MAV_AUTOPILOT_INVALID
            ):
                return []
            armed = bool(message.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)
            self._last_heartbeat_s = now_s
            if not self.link_up:
                actions += self._link_came_up(now_s, wall_s)
            if armed != self.armed or message.custom_mode != self._custom_mode:
                log.info(
                    "vehicle %s in %s",
                    "armed" if armed else "disarmed",
                    mode_name(message.custom_mode),
                )
                self._state_dirty = True
            if int(message.custom_mode) != self._custom_mode:
                self._mode_since_s = now_s
            self.armed, self._custom_mode = armed, int(message.custom_mode)
            # Done is done: a request met once is not sent again after a reconnect. A mode
            # must hold for MODE_SETTLE_S first (`_requests`).
            if self._want_armed == armed:
                self._want_armed = None
        elif kind == "LOCAL_POSITION_NED":
            self._position_ned = (float(message.x), float(message.y), float(message.z))
            self._speed_mps = math.hypot(float(message.vx), float(message.vy))
            self._speed_s = now_s
            self._velocity_ned = (float(message.vx), float(message.vy))
        elif kind == "GPS_GLOBAL_ORIGIN":
            if not self._origin_confirmed:
                log.info("vehicle has its EKF origin")
            self._origin_confirmed = True
        elif kind == "ATTITUDE":
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
            self._battery = battery or None
        elif kind == "COMMAND_ACK":
            self._last_ack = {"command": int(message.command), "result": int(message.result)}
            log.info("vehicle answered command %d with result %d", message.command, message.result)
        elif kind == "STATUSTEXT":
            text = str(message.text)
            log.info("vehicle says: %s", text)
            self._vehicle_text = text  # arming refusals say why: users see it in the state
            self._state_dirty = True
        return actions

    def _link_came_up(self, now_s: float, wall_s: float) -> list[Action]:
        self.gate.set_link(True)
        self.link_up = True
        self._origin_confirmed = False  # a rebooted autopilot lost it
        self._pose_since_link_up = False
        if not self._ever_up:
            vehicle = self.settings.vehicle
            if vehicle.set_mode_on_connect:
                self._want_mode = self.settings.rover_mode
            if vehicle.arm_on_connect:
                self._want_armed = True
            self._request_attempts = 0
            self._request_since_s = now_s
            self._next_request_s = -math.inf
        self._ever_up = True
        self._state_dirty = True
        log.info(
            "vehicle link up (system %d); stop until a fresh command",
            self.settings.mavlink.vehicle_system_id,
        )
        return [self._origin(wall_s)] if self._guided else []

    # -- the clock ----------------------------------------------------------------------------

    def next_deadline(self, now_s: float, link_open: bool) -> float:
        """When `tick` must next run, whatever arrives before (`link_open`: is the port open)."""
        deadlines = [self.gate.next_check_s(now_s), self._next_heartbeat_s, self._next_state_s]
        if self._want_mode is not None or self._want_armed is not None:
            deadlines.append(self._next_request_s)
        if self.link_up:
            deadlines.append(self._last_heartbeat_s + self.settings.mavlink.link_timeout_s)
        elif self._reconnects(link_open):
            deadlines.append(self._next_reconnect_s)
        # else: an open port waiting for the first heartbeat has nothing to reopen (before
        # this the loop spun without sleeping until the autopilot's first heartbeat).
        return min(deadlines)

    def tick(self, now_s: float, wall_s: float, link_open: bool) -> list[Action]:
        """The bridge's own duties at `now_s`: the failsafe's stop, the heartbeat, the link's
        timeout and reopening (`link_open`: is the port open now), arm and mode requests, the
        vehicle state."""
        actions: list[Action] = []
        was_driving = self.gate.was_driving
        if self.gate.stop_due(now_s):
            actions.append(self._stop(now_s))
            if was_driving:
                self._brake(now_s)
        if now_s >= self._next_heartbeat_s:
            actions += self._heartbeats()
            self._next_heartbeat_s = now_s + self.settings.mavlink.heartbeat_period_s
        actions += self._watch_link(now_s, link_open)
        actions += self._requests(now_s, wall_s)
        if self._state_dirty or now_s >= self._next_state_s:
            actions.append(self.publish(now_s))
        return actions

    def publish(self, now_s: float, bridge: str = "running") -> Publish:
        """The vehicle state to publish now (and the next one due a period later)."""
        self._state_dirty = False
        self._next_state_s = now_s + self.settings.vehicle.state_period_s
        return Publish(self.state(now_s, bridge))

    def _stop(self, now_s: float) -> Send:
        self.gate.stop_sent(now_s)
        self._moving_command = False
        return Send(self._stop_message, self._as_gcs, "stops")

    def _brake(self, now_s: float) -> None:
        """A moving car was just stopped: switch to the braking mode, if one is set."""
        if self._brake_mode is None or self._brake_mode == self.settings.rover_mode:
            return
        self._braking = True
        self._want_mode = self._brake_mode
        self._request_since_s = now_s
        self._request_attempts = 0
        self._next_request_s = -math.inf
        log.info("stopped: switching to %s to brake", mode_name(self._brake_mode))

    def _watch_link(self, now_s: float, link_open: bool) -> list[Action]:
        mavlink = self.settings.mavlink
        if self.link_up and now_s - self._last_heartbeat_s > mavlink.link_timeout_s:
            self.gate.set_link(False)
            self.link_up = False
            self._state_dirty = True
            self._next_reconnect_s = now_s + mavlink.reconnect_period_s
            log.warning(
                "vehicle link down: no heartbeat for %g s; stopping, reconnecting every %g s",
                mavlink.link_timeout_s,
                mavlink.reconnect_period_s,
            )
        if not self.link_up and self._reconnects(link_open) and now_s >= self._next_reconnect_s:
            self._next_reconnect_s = now_s + mavlink.reconnect_period_s
            self.counters["reconnects"] += 1
            return [Reopen()]
        return []

    def _reconnects(self, link_open: bool) -> bool:
        """Reopen the port while the link is down? After a link loss, or when it is closed (a
        port open since the start waits for the first heartbeat as it is)."""
        return self._ever_up or not link_open

    def _requests(self, now_s: float, wall_s: float) -> list[Action]:
        """Origin, mode and arming requests due now (again every `vehicle.request_retry_s`
        until the vehicle shows them, or `vehicle.request_timeout_s`)."""
        if not self.link_up or now_s < self._next_request_s:
            return []
        vehicle = self.settings.vehicle
        self._next_request_s = now_s + vehicle.request_retry_s
        actions: list[Action] = []
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
            actions.append(self._origin(wall_s))
        mode_held = self._want_mode is not None and self._custom_mode == self._want_mode
        if mode_held and now_s - self._mode_since_s >= MODE_SETTLE_S:
            self._want_mode = None
        if self._want_armed is not None and self.armed == self._want_armed:
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
            # Rover ends its boot by switching to INITIAL_MODE: a mode taken before that is
            # undone (seen in SITL), so ask only once the vehicle is up.
            if want_mode is not None or want_armed is not None:
                self._set_request_status("waiting for the vehicle to initialise")
            return actions
        if want_mode is None and want_armed is None:
            if (self._request_status or "").startswith(("asking", "waiting")):
                self._set_request_status(None)  # done (a give-up stays reported)
            return actions
        waited_s = now_s - self._request_since_s
        if 0 < vehicle.request_timeout_s <= waited_s:
            self._want_mode = self._want_armed = None
            self._set_request_status(
                f"gave up on {describe(want_mode, want_armed)} after "
                f"{self._request_attempts} tries in {waited_s:.1f} s"
            )
            log.warning(
                "vehicle did not take %s in %.1f s (%d tries; vehicle.request_timeout_s); "
                "giving up",
                describe(want_mode, want_armed),
                waited_s,
                self._request_attempts,
            )
            return actions
        self._request_attempts += 1
        self._set_request_status(
            f"asking for {describe(want_mode, want_armed)} "
            f"(try {self._request_attempts}, {waited_s:.1f} s)"
        )
        if want_mode is not None:
            actions.append(self._set_mode(want_mode))
        if want_armed is not None:
            actions.append(self._command_long(MAV_CMD_COMPONENT_ARM_DISARM, float(want_armed)))
        log.info("asked the vehicle for %s", describe(want_mode, want_armed))
        return actions

    def _set_request_status(self, status: str | None) -> None:
        """What the bridge is asking of the vehicle (shown in the state)."""
        if status != self._request_status:
            self._request_status = status
            self._state_dirty = True

    # -- the exit sequence --------------------------------------------------------------------

    def refuse_commands(self) -> list[Action]:
        """The first step of closing: no command goes out from now on (`shutdown` follows)."""
        self.gate.close()
        return []

    def shutdown(self, now_s: float) -> list[Action]:
        """SIGTERM, SIGINT or `close()`: refuse every later command, send stop
        `failsafe.stop_repeats_on_exit` times, switch to the brake mode (if set and the link is
        up); then `exit_step` waits for rest and disarms (with `failsafe.disarm_on_exit`)."""
        self.gate.close()
        failsafe = self.settings.failsafe
        actions: list[Action] = [self._stop(now_s) for _ in range(failsafe.stop_repeats_on_exit)]
        log.info("sent stop %d times on exit", failsafe.stop_repeats_on_exit)
        if self._brake_mode is not None and self.link_up:
            actions.append(self._set_mode(self._brake_mode))
            log.info("exit: switching to %s to brake", mode_name(self._brake_mode))
        if failsafe.disarm_on_exit:
            self._exit_phase = "rest"
            self._rest_start_s = now_s
            self._rest_deadline_s = now_s + failsafe.rest_timeout_s
            self._brake_deadline_s = now_s + failsafe.brake_timeout_s
            self._slowest_mps = math.inf
            self._next_exit_stop_s = now_s + failsafe.stop_period_s
        else:
            self._exit_phase = "done"
        return actions

    def exit_step(self, now_s: float) -> list[Action]:
        """The exit sequence at `now_s`; then read the port until `exit_wait_until_s`, handing
        each message to `exit_message`, and step again (the sequence is over when it is None).

        First keep stopping until the vehicle reports rest: a car disarmed while moving loses its
        brakes and coasts. The wait goes on as long as the car keeps slowing down, up to
        `failsafe.brake_timeout_s`; once its speed has not fallen for `failsafe.rest_timeout_s`
        the brakes are doing nothing and disarming loses nothing (without speed reports there
        is nothing to wait for). Then disarm, again until acknowledged (three tries); with the
        link down nobody would answer: one disarm is sent, and the bridge does not wait."""
        self.exit_wait_until_s = None
        if self._exit_phase == "rest":
            actions, until_s = self._rest_step(now_s)
            if until_s is not None:
                self.exit_wait_until_s = until_s
                return actions
            self._exit_phase = "disarm"
            if not self.link_up:
                log.warning("disarm on exit: sent once; the vehicle's link is down")
                self._exit_phase = "done"
                return [self._command_long(MAV_CMD_COMPONENT_ARM_DISARM, 0.0)]
        if self._exit_phase != "disarm":
            return []
        if now_s < self._disarm_deadline_s:
            self.exit_wait_until_s = self._disarm_deadline_s
            return []
        if self._disarm_tries == EXIT_DISARM_TRIES:
            log.warning("disarm on exit: no answer from the vehicle")
            self._exit_phase = "done"
            return []
        self._disarm_tries += 1
        self._disarm_deadline_s = self.exit_wait_until_s = now_s + EXIT_ACK_WAIT_S
        return [self._command_long(MAV_CMD_COMPONENT_ARM_DISARM, 0.0)]

    def stopped(self, now_s: float) -> list[Action]:
        """The last vehicle state, once the exit sequence is over (`bridge` is "stopped")."""
        return [self.publish(now_s, bridge="stopped")]

    def _rest_step(self, now_s: float) -> tuple[list[Action], float | None]:
        failsafe = self.settings.failsafe
        if not self.link_up or self._speed_mps is None:
            return [], None
        fresh = now_s - self._speed_s < SPEED_FRESH_S
        if fresh and self._speed_mps < failsafe.rest_speed_mps:
            log.info("exit: vehicle at rest after %.2f s", now_s - self._rest_start_s)
            return [], None
        if fresh and self._speed_mps <= self._slowest_mps - failsafe.rest_speed_mps:
            # Still slowing down: the brakes work, so keep them on (a car disarmed moving coasts).
            self._slowest_mps = self._speed_mps
            self._rest_deadline_s = min(now_s + failsafe.rest_timeout_s, self._brake_deadline_s)
        if now_s >= self._rest_deadline_s:
            log.warning(
                "exit: disarming a car %s at %.2f m/s: %s",
                "still" if fresh else "last reported",
                self._speed_mps,
                f"not at rest within {failsafe.brake_timeout_s:g} s (failsafe.brake_timeout_s)"
                if now_s >= self._brake_deadline_s
                else f"not slowing for {failsafe.rest_timeout_s:g} s (failsafe.rest_timeout_s)",
            )
            return [], None
        actions: list[Action] = []
        if now_s >= self._next_exit_stop_s:
            actions.append(self._stop(now_s))
            self._next_exit_stop_s = now_s + failsafe.stop_period_s
        if now_s >= self._next_heartbeat_s:
            # Still the ground station while it brakes: silence would trip the autopilot's GCS
            # failsafe, whose mode (FS_ACTION: Hold coasts, Loiter may drive back to where it
            # began) would take the car from the brake mode before it is at rest.
            actions += self._heartbeats()
            self._next_heartbeat_s = now_s + self.settings.mavlink.heartbeat_period_s
        return actions, min(self._rest_deadline_s, self._next_exit_stop_s, self._next_heartbeat_s)

    def exit_message(self, message: Any, now_s: float, wall_s: float) -> list[Action]:
        """A MAVLink message read during the exit sequence: while waiting for rest it is handled
        as any (speed reports end the wait); while disarming only the disarm's acknowledgement
        counts (and ends the sequence)."""
        if self._exit_phase == "rest":
            try:
                return self.mavlink(message, now_s, wall_s)
            except Exception:  # the car must still be stopped and disarmed
                log.debug("handler error", exc_info=True)
                return []
        if (
            self._exit_phase == "disarm"
            and message.get_type() == "COMMAND_ACK"
            and message.command == MAV_CMD_COMPONENT_ARM_DISARM
        ):
            log.info("disarm on exit: vehicle answered %d", message.result)
            self._exit_phase = "done"
        return []

    # -- what goes on the wire ----------------------------------------------------------------

    def _command_message(self, twist: Twist2D) -> Any:
        """The MAVLink message that carries `twist` in the configured output mode."""
        output, target = self.settings.output, self.settings.mavlink
        encoder = self.encoder
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

    def _command_long(self, command: int, *params: float) -> Send:
        target = self.settings.mavlink
        padded = (list(params) + [0.0] * 7)[:7]
        return Send(
            self.encoder.command_long_encode(
                target.vehicle_system_id, target.vehicle_component_id, command, 0, *padded
            )
        )

    def _set_mode(self, mode: int) -> Send:
        return self._command_long(MAV_CMD_DO_SET_MODE, MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode)

    def _heartbeats(self) -> list[Action]:
        """As the companion computer, and (with `mavlink.gcs_heartbeat`) as the ground station
        whose silence trips the autopilot's own GCS failsafe."""
        encoder = self.encoder
        actions: list[Action] = [
            Send(
                encoder.heartbeat_encode(
                    MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE
                )
            )
        ]
        if self.settings.mavlink.gcs_heartbeat:
            message = encoder.heartbeat_encode(
                MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE
            )
            actions.append(Send(message, as_gcs=True))
        return actions

    def _origin(self, wall_s: float) -> Send:
        """The EKF origin (`vision.origin_*`), stamped with the wall time."""
        vision = self.settings.vision
        lat, lon, alt = mapping.origin_e7(
            vision.origin_lat_deg, vision.origin_lon_deg, vision.origin_alt_m
        )
        log.debug(
            "EKF origin sent (%.6f, %.6f, %.1f m)",
            vision.origin_lat_deg,
            vision.origin_lon_deg,
            vision.origin_alt_m,
        )
        return Send(
            self.encoder.set_gps_global_origin_encode(
                self.settings.mavlink.vehicle_system_id, lat, lon, alt, int(wall_s * 1e6)
            )
        )

    # -- state on zenoh -----------------------------------------------------------------------

    def state(self, now_s: float, bridge: str = "running") -> dict[str, Any]:
        """The vehicle state message as a dict (what goes out on qnav/vehicle_state, less the
        wall-clock `stamp_s` the shell adds)."""
        position = None
        if self._position_ned is not None:
            yaw_ned = self._yaw_ned if self._yaw_ned is not None else math.pi / 2
            x, y, yaw = ned_to_enu(self._position_ned[0], self._position_ned[1], yaw_ned)
            position = {"x_m": x, "y_m": y, "z_m": -self._position_ned[2]}
            if self._yaw_ned is not None:
                position["yaw_rad"] = yaw
        return {
            "bridge": bridge,
            "link_up": self.link_up,
            "armed": self.armed,
            "mode": None if self._custom_mode is None else mode_name(self._custom_mode),
            "output": self.settings.output.mode,
            "driving": self.gate.driving(now_s),
            "position": position,
            "velocity": velocity(self._velocity_ned, self._yaw_ned, self._yaw_rate_ned),
            "battery": self._battery,
            "last_ack": self._last_ack,
            "request": self._request_status,
            "vehicle_text": self._vehicle_text,
            "counters": dict(self.counters),
        }


def velocity(
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


def parse_request(request: dict[str, Any]) -> tuple[bool | None, int | None]:
    """(arm, mode) from a vehicle request such as {"arm": true, "mode": "GUIDED"}."""
    unknown = set(request) - {"arm", "mode"}
    if unknown or not request:
        raise ValueError(f"a request has keys arm and/or mode, got {sorted(request)}")
    arm = request.get("arm")
    if arm is not None and not isinstance(arm, bool):
        raise ValueError(f"arm must be true or false, got {arm!r}")
    mode = request.get("mode")
    return arm, None if mode is None else mode_number(mode)


def describe(mode: int | None, armed: bool | None) -> str:
    """ "mode GUIDED and arm", for logs and the state's `request`."""
    parts = [] if mode is None else [f"mode {mode_name(mode)}"]
    parts += [] if armed is None else ["arm" if armed else "disarm"]
    return " and ".join(parts)
