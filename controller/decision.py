"""The controller's decision logic, without any I/O: inputs in, a command and a status out.

`Controller` is what the daemon runs between zenoh and the car, and what playback of a recording
and the sim-in-the-loop stack run the same way. It holds the newest input of each kind with the
monotonic time it arrived, and the policy's k-frame window; it reads no clock, opens no socket
and writes no log: callers pass the time and do the I/O.

    controller = Controller(PolicyRuntime("policy.onnx"), SafetySettings(), LidarSettings())
    controller.receive(Input.SCAN, cdr_bytes, now)      # raw payloads, as they come off the wire
    controller.on_pose(Pose2D(...), now)                  # or values already decoded
    output = controller.decide(now)                       # once per control period
    publish(output.command, output.status.to_dict())
    output = controller.decide(now, send)                 # or: send(command) before the status

Safety rules, checked in this order by `decide` (the first that applies names the stop in
`status.reason`; every stop also restarts the policy's window, so a resumed run starts a fresh
episode, while the look ahead's obstacle tracker, if any, goes on taking every scan through the
stop):

1. `estop_latched`: an emergency stop was pressed (Bool true on the estop topic, or any
   malformed payload there: someone tried to press it), and has not been released on purpose:
   a release request (a canonical Bool true on the release topic) is honoured only while the
   last estop message is a well-formed false (the button is out); one that comes while the
   button is still pressed is refused and counted.
2. `no_scan` / `scan_stale`: the policy reads a lidar and no scan has arrived, or the newest
   arrived longer than the scan timeout ago (default two control periods).
3. `no_pose` / `pose_stale`: the same for the motion-capture pose.
4. `no_target`: no target yet.
5. `frame_mismatch`: the pose and the target name different frames.
6. `target_reached`: the car is within the tolerance of the target; it stays stopped until a
   different target arrives.
7. `policy_input_error`: the policy refused the observation (not expected after the checks
   above, but it never moves the car).

Otherwise the policy decides (`policy`), the look ahead may overrule it, and the command is the
action's velocity from the policy file's contract, unless the proximity stop's safety field
(`controller.proximity`) forbids that action: then the best allowed action, a turn in place, or
a stop when none is allowed (`proximity`; the policy's window goes on, as it decided).

A malformed payload (not exactly one well-formed message, NaN, wrong frame, a pose beyond
`safety.max_position_m` or with a non-unit quaternion, a scan that is no plausible scan of a
planar lidar: range_min/range_max not finite and ordered, fewer than `lidar.min_readings`
readings, less than `lidar.min_field_of_view_rad`, an absurd angle_min or increment, too many
invalid readings) is counted and its error returned; it never replaces the last good input, so
it can only make the car stop (through the timeouts, or the emergency stop), never move.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from qnav.contracts import delivery, wire
from qnav.contracts.actions import Action
from qnav.contracts.errors import PolicyFileError, PolicyInputError
from qnav.contracts.lookahead import shielded_actions
from qnav.contracts.observation import target_features_of
from qnav.contracts.wire import STOP, Pose2D, Scan, Twist2D, WireError
from qnav.controller.config import LidarSettings, SafetySettings
from qnav.controller.lookahead import Lookahead, LookaheadSettings, beam_angles
from qnav.controller.perception import TrackerSettings
from qnav.controller.policy import PolicyRuntime
from qnav.controller.proximity import (
    CLEAR,
    Blocked,
    ProximitySettings,
    allowed_actions,
    blocked_parts,
    field_ranges,
    guarded_action,
)
from qnav.controller.scan import ScanRules, resample_scan

MAX_SCAN_READINGS = 100_000
"""Scans with more readings are refused (no planar lidar has as many)."""

MAX_ANGLE_MIN_RAD = 2 * math.pi
"""Scans starting farther from 0 either way are refused (drivers start in [-pi, 2 pi))."""

TARGET_MOVED_M = 1e-3
"""A target this far from the current one is a different target (new episode)."""

POSE_JUMPED_M = 0.5
"""A pose this far from the last one is a new start (the car was carried or placed, or a new
episode begins at the same target): the policy's window restarts. A car at 0.5 m/s covers this
in a second; the newest poses come far more often."""


class Input(StrEnum):
    """The inputs the controller listens to."""

    SCAN = "scan"
    POSE = "pose"
    TARGET = "target"
    ESTOP = "estop"
    ESTOP_RELEASE = "estop_release"


class Reason(StrEnum):
    """Why the command is what it is (`status.reason`)."""

    POLICY = "policy"
    ESTOP_LATCHED = "estop_latched"
    NO_SCAN = "no_scan"
    SCAN_STALE = "scan_stale"
    NO_POSE = "no_pose"
    POSE_STALE = "pose_stale"
    NO_TARGET = "no_target"
    FRAME_MISMATCH = "frame_mismatch"
    TARGET_REACHED = "target_reached"
    POLICY_INPUT_ERROR = "policy_input_error"
    SHUTDOWN = "shutdown"
    PROXIMITY = "proximity"


AT_REST = frozenset({Reason.NO_TARGET, Reason.TARGET_REACHED, Reason.ESTOP_LATCHED})
"""The stops during which a delivered policy may be swapped in: no episode is under way."""


@dataclass
class Counters:
    """Running totals reported in every status."""

    received: dict[str, int] = field(default_factory=lambda: {i.value: 0 for i in Input})
    """Payloads received per input (malformed ones included)."""
    malformed: dict[str, int] = field(default_factory=lambda: {i.value: 0 for i in Input})
    """Payloads refused per input."""
    decisions: int = 0
    """Outputs produced (policy decisions and stops)."""
    policy_steps: int = 0
    """Decisions taken by the policy."""
    stops: int = 0
    """Outputs that stopped the car."""
    overruns: int = 0
    """Control periods missed because a decision ran past the next deadline (set by the loop)."""
    estop_presses: int = 0
    """Emergency-stop messages that pressed it."""
    releases_refused: int = 0
    """Release requests refused because the emergency stop was still pressed."""
    policy_swaps: int = 0
    """Policies swapped in while running (`Controller.swap_policy`)."""
    overruled: int = 0
    """Policy decisions the look ahead changed (`lookahead.mode` shield or plan)."""
    proximity: int = 0
    """Decisions the proximity stop changed (to a safe turn, or a stop)."""

    def to_dict(self) -> dict[str, Any]:
        """As plain JSON values."""
        return {
            "received": dict(self.received),
            "malformed": dict(self.malformed),
            "decisions": self.decisions,
            "policy_steps": self.policy_steps,
            "stops": self.stops,
            "overruns": self.overruns,
            "estop_presses": self.estop_presses,
            "releases_refused": self.releases_refused,
            "policy_swaps": self.policy_swaps,
            "overruled": self.overruled,
            "proximity": self.proximity,
        }


@dataclass(frozen=True)
class Status:
    """What the controller decided and why, with the state of its inputs."""

    time_s: float
    """Monotonic time of the decision (the caller's clock)."""
    sequence: int
    """Number of this output, from 1."""
    reason: Reason
    """Why the command is what it is."""
    command: Twist2D
    """The command sent."""
    action: Action | None
    """The policy's action (None when stopped by a rule)."""
    q_values: tuple[float, ...] | None
    """The policy's Q values, indexed by action (None when stopped by a rule)."""
    scan_stamp_s: float | None
    """Header stamp of the scan used (None without one)."""
    target_distance_m: float | None
    """Distance from the pose to the target (None without both)."""
    ages_s: dict[str, float | None]
    """Seconds since each input last arrived well-formed (None: never)."""
    estop_latched: bool
    """Whether the emergency stop is latched."""
    estop_pressed: bool | None
    """The last emergency-stop message (None: none yet)."""
    counters: dict[str, Any]
    """A copy of the running totals."""
    policy_version: str = ""
    """Version of the policy that decides (or would decide): `Controller.policy_version`."""
    risks: tuple[float, ...] | None = None
    """With `lookahead.mode = "shield"`: each action's share of forecast continuations
    that collide, indexed by action (None otherwise, or when stopped by a rule)."""

    def to_dict(self) -> dict[str, Any]:
        """As one JSON object (the status message)."""
        return {
            "time_s": self.time_s,
            "sequence": self.sequence,
            "reason": self.reason.value,
            "command": {
                "linear_mps": self.command.linear_mps,
                "angular_radps": self.command.angular_radps,
            },
            "action": None if self.action is None else self.action.name.lower(),
            "q_values": None if self.q_values is None else list(self.q_values),
            "scan_stamp_s": self.scan_stamp_s,
            "target_distance_m": self.target_distance_m,
            "ages_s": dict(self.ages_s),
            "estop": {"latched": self.estop_latched, "pressed": self.estop_pressed},
            "counters": self.counters,
            "policy_version": self.policy_version,
            "risks": None if self.risks is None else list(self.risks),
        }


class Output(NamedTuple):
    """One decision: the command to publish and the status that explains it."""

    command: Twist2D
    """The motor command."""
    status: Status
    """Why."""


CommandSink = Callable[[Twist2D], None]
"""Takes a command the moment it is decided, before its status is written (the daemon publishes
it there, so that writing the status adds nothing to the command's latency)."""


@dataclass
class _Latest:
    """The newest well-formed value of one input and when it arrived."""

    value: Any = None
    arrived_s: float | None = None

    def age(self, now: float) -> float | None:
        return None if self.arrived_s is None else max(0.0, now - self.arrived_s)


class Controller:
    """Newest inputs + monotonic time -> command and status (module docstring: the rules)."""

    def __init__(
        self,
        runtime: PolicyRuntime,
        safety: SafetySettings | None = None,
        lidar: LidarSettings | None = None,
        policy_version: str = "",
        *,
        lookahead: LookaheadSettings | None = None,
        tracker: TrackerSettings | None = None,
        proximity: ProximitySettings | None = None,
    ) -> None:
        """`lookahead` and `proximity`: the look ahead and the proximity stop; None leaves
        each out (the daemon passes its settings, whose defaults run both: the shield and the
        default safety field)."""
        self.runtime = runtime
        self.policy_version = policy_version or delivery.version_of_file(runtime.path)
        """Reported in every status (by default the file's own: `version_of_file`)."""
        self.safety = safety or SafetySettings()
        self.lidar = lidar or LidarSettings()
        contract = runtime.contract
        self.period_s = contract.control_period_s
        self.scan_timeout_s = self.safety.scan_timeout_s or 2 * self.period_s
        self.pose_timeout_s = self.safety.pose_timeout_s or 2 * self.period_s
        self.uses_scan = contract.num_beams > 0
        self.scan_rules = ScanRules(
            num_beams=max(contract.num_beams, 1),
            mount_yaw_rad=self.lidar.mount_yaw_rad,
            below_range_min=self.lidar.below_range_min,
            uncovered_range_m=self.lidar.uncovered_range_m,
        )
        self.commands = tuple(Twist2D(a.linear_mps, a.angular_radps) for a in contract.actions)
        self.proximity = proximity or ProximitySettings(enabled=False)
        self._linear_mps = np.array([a.linear_mps for a in contract.actions])
        self._blocked: Blocked = CLEAR
        """Which parts of the proximity stop's field the newest scan holds a reading in."""
        self.counters = Counters()
        self._latest = {i: _Latest() for i in Input}
        self._scan: NDArray[np.float32] | None = None
        self._scan_stamp_s: float | None = None
        self._scan_delays_s: NDArray[np.float64] | None = None
        """When each of the newest scan's beams was taken after its stamp (None: at it)."""
        self.estop_latched = self.safety.estop_start_latched
        self.estop_pressed: bool | None = None
        self.target_reached = False
        self._sequence = 0
        self._window_fresh = True
        self._last_reason: Reason | None = None
        self.lookahead_settings = lookahead or LookaheadSettings(mode="off")
        self.tracker_settings = tracker or TrackerSettings()
        self.lookahead = self._new_lookahead(runtime, self.tracker_settings)
        """The look ahead that may overrule the policy (None with `lookahead.mode = "off"`)."""

    # ---- inputs -------------------------------------------------------------------------

    def receive(self, source: Input, payload: bytes, now: float) -> str | None:
        """Decode one payload as it came off the wire and take it in.

        Returns None, or why the payload was refused (it is then counted as malformed and the
        previous input of its kind stays in force).
        """
        self.counters.received[source.value] += 1
        try:
            if source is Input.SCAN:
                self._take_scan(wire.decode_scan_msg(payload), now)
            elif source is Input.POSE:
                self._take_pose(wire.decode_pose_msg(payload), now)
            elif source is Input.TARGET:
                decode = (
                    wire.decode_pose_msg
                    if self.safety.target_kind == "pose"
                    else wire.decode_point_msg
                )
                self._take_target(decode(payload), now)
            elif source is Input.ESTOP:
                self._take_estop(wire.decode_bool_msg(payload), now)
            else:
                return self._take_release(wire.decode_bool_msg(payload), now)
        except Exception as error:  # whatever a payload does, it is only ever refused
            self.counters.malformed[source.value] += 1
            why = str(error) if isinstance(error, WireError) else f"{type(error).__name__}: {error}"
            if source is Input.ESTOP:
                self._press_malformed()
                return f"{why} (taken as a press: the emergency stop is latched)"
            return why
        return None

    def on_scan(self, scan: Scan, now: float) -> str | None:
        """Take a decoded scan; returns why it was refused, if it was."""
        return self._checked(Input.SCAN, lambda: self._take_scan(scan, now))

    def on_pose(self, pose: Pose2D, now: float) -> str | None:
        """Take a decoded motion-capture pose; returns why it was refused, if it was."""
        return self._checked(Input.POSE, lambda: self._take_pose(pose, now))

    def on_target(self, target: Pose2D, now: float) -> str | None:
        """Take a decoded target (its yaw is ignored); returns why it was refused, if it was."""
        return self._checked(Input.TARGET, lambda: self._take_target(target, now))

    def on_estop(self, pressed: bool, now: float) -> None:
        """Take an emergency-stop message: true presses (and latches) it."""
        self.counters.received[Input.ESTOP.value] += 1
        self._take_estop(pressed, now)

    def request_release(self, now: float) -> str | None:
        """Ask to release a latched emergency stop; returns why it was refused, if it was."""
        self.counters.received[Input.ESTOP_RELEASE.value] += 1
        return self._take_release(True, now)

    def _checked(self, source: Input, take: Callable[[], None]) -> str | None:
        self.counters.received[source.value] += 1
        try:
            take()
        except WireError as error:
            self.counters.malformed[source.value] += 1
            return str(error)
        return None

    def _take_scan(self, scan: Scan, now: float) -> None:
        if self.lidar.frame_id and scan.frame_id != self.lidar.frame_id:
            raise WireError(
                f"scan in frame {scan.frame_id!r}; lidar.frame_id is {self.lidar.frame_id!r}"
            )
        if not self.uses_scan:
            return  # the lidar-less policy has no use for it
        count, increment = len(scan.ranges_m), abs(scan.angle_increment_rad)
        if count < self.lidar.min_readings:
            raise WireError(
                f"scan of {count} readings (fewer than lidar.min_readings = "
                f"{self.lidar.min_readings})"
            )
        if not (
            math.isfinite(scan.range_min_m)
            and math.isfinite(scan.range_max_m)
            and 0.0 <= scan.range_min_m < scan.range_max_m
        ):
            raise WireError(
                f"scan range_min {scan.range_min_m} / range_max {scan.range_max_m} are not "
                "finite with 0 <= range_min < range_max"
            )
        if count > MAX_SCAN_READINGS or increment > math.pi or count * increment > 4 * math.pi:
            raise WireError(
                f"scan of {count} readings {increment:.4g} rad apart is not a planar scan of at "
                f"most two turns and {MAX_SCAN_READINGS} readings"
            )
        if abs(scan.angle_min_rad) > MAX_ANGLE_MIN_RAD:
            # Finite but absurd (1e30): every reading's angle rounds to one, and the resampled
            # scan would read as open space all round.
            raise WireError(
                f"scan angle_min {scan.angle_min_rad:.4g} rad is not a planar scan's start angle "
                f"(at most {MAX_ANGLE_MIN_RAD:.4g} rad either way)"
            )
        if count * increment < self.lidar.min_field_of_view_rad:
            raise WireError(
                f"scan covers {count * increment:.4g} rad (less than lidar.min_field_of_view_rad "
                f"= {self.lidar.min_field_of_view_rad:.4g})"
            )
        turn_s = scan.time_increment_s * (count - 1)
        if turn_s > self.scan_timeout_s:
            raise WireError(
                f"scan's readings span {turn_s:.4g} s (time_increment {scan.time_increment_s:.4g}"
                f" s), longer than safety.scan_timeout_s = {self.scan_timeout_s:.4g} s"
            )
        resampled = resample_scan(scan, self.scan_rules)
        if resampled.invalid_fraction > self.lidar.max_invalid_fraction:
            raise WireError(
                f"scan has {resampled.invalid_fraction:.0%} invalid readings (more than "
                f"lidar.max_invalid_fraction = {self.lidar.max_invalid_fraction})"
            )
        self._scan, self._scan_stamp_s = resampled.ranges_m, scan.stamp_s
        self._scan_delays_s = resampled.delays_s
        self._blocked = self._field(scan)
        self._mark(Input.SCAN, None, now)
        self._track(now)

    def _field(self, scan: Scan) -> Blocked:
        """Which parts of the proximity stop's field `scan` holds a reading in (CLEAR when the
        stop is off)."""
        settings = self.proximity
        if not settings.enabled:
            return CLEAR
        count = len(scan.ranges_m)
        angles = (
            self.lidar.mount_yaw_rad
            + scan.angle_min_rad
            + scan.angle_increment_rad * np.arange(count, dtype=np.float64)
        )
        ranges = field_ranges(
            scan.ranges_m,
            scan.range_min_m,
            scan.range_max_m,
            below_min_is_no_return=self.lidar.below_range_min == "no_return",
        )
        return blocked_parts(angles, ranges, settings.footprint_m, settings.travel_m)

    def _track(self, now: float) -> None:
        """Give the look ahead the newest scan and pose, driving or not (a car at rest keeps
        tracking: `controller.lookahead`), if the pose is fresh enough to place the scan in the
        room (a scan already tracked is not tracked again)."""
        pose: Pose2D | None = self._latest[Input.POSE].value
        age = self._latest[Input.POSE].age(now)
        if self.lookahead is None or pose is None or age is None or age > self.pose_timeout_s:
            return
        assert self._scan is not None and self._scan_stamp_s is not None  # just taken
        xy_yaw = np.array([pose.x_m, pose.y_m, pose.yaw_rad])
        self.lookahead.observe(
            pose.stamp_s, xy_yaw, self._scan_stamp_s, self._scan, self._scan_delays_s
        )

    def _check_frame(self, what: str, value: Pose2D) -> None:
        wire.check_position(what, value, self.safety.max_position_m, "safety.max_position_m")
        wanted = self.safety.frame_id
        if wanted and value.frame_id != wanted:
            raise WireError(f"{what} in frame {value.frame_id!r}; safety.frame_id is {wanted!r}")

    def _take_pose(self, pose: Pose2D, now: float) -> None:
        self._check_frame("pose", pose)
        last = self._latest[Input.POSE].value
        if last is not None and math.hypot(pose.x_m - last.x_m, pose.y_m - last.y_m) > (
            POSE_JUMPED_M
        ):
            self._restart_window()
        self._mark(Input.POSE, pose, now)

    def _take_target(self, target: Pose2D, now: float) -> None:
        self._check_frame("target", target)
        current = self._latest[Input.TARGET].value
        if (
            current is None
            or math.hypot(target.x_m - current.x_m, target.y_m - current.y_m) > TARGET_MOVED_M
            or target.frame_id != current.frame_id
        ):
            self.target_reached = False
            self._restart_window()
        self._mark(Input.TARGET, target, now)

    def _take_estop(self, pressed: bool, now: float) -> None:
        self.estop_pressed = pressed
        if pressed:
            self.estop_latched = True
            self.counters.estop_presses += 1
        self._mark(Input.ESTOP, pressed, now)

    def _press_malformed(self) -> None:
        """A malformed message on the estop topic is someone pressing the stop with a broken
        sender: press and latch it, and hold it pressed until a well-formed false says the
        button is out (its age stays that of the last well-formed message)."""
        self.estop_pressed = True
        self.estop_latched = True
        self.counters.estop_presses += 1

    def _take_release(self, request: bool, now: float) -> str | None:
        if not request:
            return None
        if self.estop_pressed:
            self.counters.releases_refused += 1
            return "the emergency stop is still pressed (send false on the estop topic first)"
        self.estop_latched = False
        self._mark(Input.ESTOP_RELEASE, True, now)
        return None

    def _mark(self, source: Input, value: Any, now: float) -> None:
        latest = self._latest[source]
        latest.value, latest.arrived_s = value, now

    # ---- decisions ----------------------------------------------------------------------

    def decide(self, now: float, send: CommandSink | None = None) -> Output:
        """One decision at monotonic time `now`: a stop by the first rule that applies, or the
        policy's action on the newest inputs (which pushes one frame into its window), as the
        look ahead and the proximity stop leave it.

        `send`, when given, gets the command as soon as it is known, before the status is
        written; the status is the same either way.
        """
        reason = self._stop_reason(now)
        if reason is not None:
            return self._stop(now, reason, send)
        pose: Pose2D = self._latest[Input.POSE].value
        target: Pose2D = self._latest[Input.TARGET].value
        features = target_features_of(pose.x_m, pose.y_m, pose.yaw_rad, target.x_m, target.y_m)
        try:
            decision = self.runtime.step(self._scan if self.uses_scan else None, np.array(features))
        except PolicyInputError:
            return self._stop(now, Reason.POLICY_INPUT_ERROR, send)
        self._window_fresh = False
        self.counters.policy_steps += 1
        action, risks = decision.action, None
        if self.lookahead is not None:
            self._track(now)  # the newest pose (rules 2-3 held: it and the scan are fresh)
            action, risks = self._look_ahead(decision.action, decision.q_values, target)
            self.counters.overruled += int(action != decision.action)
        q_values = tuple(decision.q_values.tolist())
        guarded = self._guard(action, decision.q_values, risks)
        reason = Reason.POLICY if guarded == action else Reason.PROXIMITY
        if reason is Reason.PROXIMITY:
            self.counters.proximity += 1
            self.counters.stops += int(guarded is None)  # nothing may move (the window goes on)
        command = STOP if guarded is None else self.commands[guarded]
        return self._output(now, reason, command, guarded, q_values, send=send, risks=risks)

    def _look_ahead(
        self, chosen: Action, q_values: NDArray[np.float32], target: Pose2D
    ) -> tuple[Action, tuple[float, ...] | None]:
        """The look ahead's action in its mode, and the risks the status reports."""
        assert self.lookahead is not None
        target_xy = np.array([target.x_m, target.y_m])
        mode = self.lookahead_settings.mode
        if mode == "plan":
            return Action(self.lookahead.plan(target_xy)), None
        shares = self.lookahead.risks(target_xy)
        overrule_share = self.lookahead_settings.overrule_share
        safest = shielded_actions(
            q_values[None], shares[None], overrule_share, np.array([int(chosen)])
        )
        return Action(int(safest[0])), tuple(shares.tolist())

    def _guard(
        self, action: Action, q_values: NDArray[np.float32], risks: tuple[float, ...] | None
    ) -> Action | None:
        """`action` unless the proximity stop's field forbids it: then the best allowed action
        (with the shield's risks, the shield's rule among them), or None for a stop."""
        if not self.uses_scan or self._blocked == CLEAR:
            return action
        allowed = allowed_actions(self._linear_mps, self._blocked)
        shield = self.lookahead_settings.mode == "shield" and risks is not None
        guarded = guarded_action(
            int(action),
            allowed,
            q_values,
            np.array(risks) if shield else None,
            self.lookahead_settings.overrule_share,
        )
        return None if guarded is None else Action(guarded)

    def warm_up(self) -> None:
        """Run the policy once on a neutral observation (first runs are slow) and restart its
        window; changes nothing else."""
        scan = np.full(self.runtime.contract.num_beams, np.inf) if self.uses_scan else None
        self.runtime.step(scan, np.array([1.0, 0.0, 1.0]))
        self.runtime.reset()
        self._window_fresh = True

    def check(self, now: float, send: CommandSink | None = None) -> Output | None:
        """The safety rules alone (no policy step): a stop if one applies, else None.

        With `trigger = "scan"` the daemon decides on scan arrival and calls this every period,
        so the car still stops when the scans stop coming. `send` as for `decide`.
        """
        reason = self._stop_reason(now)
        return None if reason is None else self._stop(now, reason, send)

    def shutdown(self, now: float, send: CommandSink | None = None) -> Output:
        """The last output before the process exits: a stop (`send` as for `decide`)."""
        return self._stop(now, Reason.SHUTDOWN, send)

    def at_rest(self, now: float) -> bool:
        """Whether a policy may be swapped in now: the last output stopped the car for no
        target, a reached target or a latched emergency stop, and the rules still say so (so the
        car was told to stop, and no episode is under way)."""
        return self._last_reason in AT_REST and self._stop_reason(now) in AT_REST

    def swap_policy(self, runtime: PolicyRuntime, version: str) -> None:
        """Run `runtime` from the next decision on (call between two decisions, `at_rest`).

        The new policy must keep what the loop and the car were set up for (beams, actions,
        control period): `PolicyFileError` otherwise, and the old one stays."""
        have, offered = self.runtime.contract, runtime.contract
        if (offered.num_beams, offered.control_period_s, offered.actions) != (
            have.num_beams,
            have.control_period_s,
            have.actions,
        ):
            raise PolicyFileError(
                f"policy {version} does not keep the running policy's beams, control period and "
                "actions"
            )
        lookahead = self._new_lookahead(runtime, self.tracker_settings)
        self.runtime = runtime
        self.lookahead = lookahead
        self.policy_version = version
        self.runtime.reset()
        self._window_fresh = True
        self.counters.policy_swaps += 1

    def note_overruns(self, missed: int) -> None:
        """Count control periods the loop missed (reported in status)."""
        self.counters.overruns += missed

    def _stop_reason(self, now: float) -> Reason | None:
        if self.estop_latched:
            return Reason.ESTOP_LATCHED
        if self.uses_scan:
            age = self._latest[Input.SCAN].age(now)
            if age is None:
                return Reason.NO_SCAN
            if age > self.scan_timeout_s:
                return Reason.SCAN_STALE
        age = self._latest[Input.POSE].age(now)
        if age is None:
            return Reason.NO_POSE
        if age > self.pose_timeout_s:
            return Reason.POSE_STALE
        pose: Pose2D = self._latest[Input.POSE].value
        target: Pose2D | None = self._latest[Input.TARGET].value
        if target is None:
            return Reason.NO_TARGET
        if pose.frame_id and target.frame_id and pose.frame_id != target.frame_id:
            return Reason.FRAME_MISMATCH
        distance = math.hypot(target.x_m - pose.x_m, target.y_m - pose.y_m)
        if self.target_reached or distance <= self.safety.target_tolerance_m:
            self.target_reached = True
            return Reason.TARGET_REACHED
        return None

    def _distance(self) -> float | None:
        pose: Pose2D | None = self._latest[Input.POSE].value
        target: Pose2D | None = self._latest[Input.TARGET].value
        if pose is None or target is None:
            return None
        return math.hypot(target.x_m - pose.x_m, target.y_m - pose.y_m)

    def _restart_window(self) -> None:
        """Restart the policy's window (the look ahead keeps its tracks: `_track`)."""
        if not self._window_fresh:
            self.runtime.reset()
            self._window_fresh = True

    def _new_lookahead(self, runtime: PolicyRuntime, tracker: TrackerSettings) -> Lookahead | None:
        """The look ahead for `runtime`'s policy, or None with `lookahead.mode = "off"`."""
        if self.lookahead_settings.mode == "off":
            return None
        contract = runtime.contract
        if not self.uses_scan:
            raise PolicyFileError(
                f"lookahead.mode = {self.lookahead_settings.mode!r} tracks obstacles in the "
                f'lidar: {runtime.path} reads no scan (set lookahead.mode = "off" for a policy '
                "without a lidar)"
            )
        dynamics, robot_radius_m = contract.motion_model(str(runtime.path))
        return Lookahead(
            self.lookahead_settings,
            tracker,
            dynamics=dynamics,
            robot_radius_m=robot_radius_m,
            control_period_s=contract.control_period_s,
            beam_angles_rad=beam_angles(contract.num_beams),
            max_scan_gap_s=self.scan_timeout_s,
        )

    def _stop(self, now: float, reason: Reason, send: CommandSink | None) -> Output:
        self._restart_window()
        self.counters.stops += 1
        return self._output(now, reason, STOP, None, None, send=send)

    def _output(
        self,
        now: float,
        reason: Reason,
        command: Twist2D,
        action: Action | None,
        q_values: tuple[float, ...] | None,
        *,
        send: CommandSink | None,
        risks: tuple[float, ...] | None = None,
    ) -> Output:
        self._sequence += 1
        self._last_reason = reason
        self.counters.decisions += 1
        if send is not None:
            send(command)  # nothing the status reads changes in between
        status = Status(
            time_s=now,
            sequence=self._sequence,
            reason=reason,
            command=command,
            action=action,
            q_values=q_values,
            scan_stamp_s=self._scan_stamp_s if self.uses_scan else None,
            target_distance_m=self._distance(),
            ages_s={i.value: self._latest[i].age(now) for i in Input},
            estop_latched=self.estop_latched,
            estop_pressed=self.estop_pressed,
            counters=self.counters.to_dict(),
            policy_version=self.policy_version,
            risks=risks,
        )
        return Output(command, status)
