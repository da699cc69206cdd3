"""A small car that speaks MAVLink the way ArduPilot Rover does, for tests and sim-in-the-loop.

It follows the Rover behaviour the bridge relies on (docs/bridge-testing.md lists it):

- HEARTBEAT as a ground rover (type 10, autopilot 3) with the mode in custom_mode (MANUAL 0,
  HOLD 4, GUIDED 15), armed in base_mode; LOCAL_POSITION_NED, ATTITUDE and SYS_STATUS.
- Arming and mode changes by COMMAND_LONG (MAV_CMD_COMPONENT_ARM_DISARM 400, DO_SET_MODE 176)
  or SET_MODE, each answered with COMMAND_ACK. GUIDED is refused without a position estimate
  (an EKF origin and a fresh VISION_POSITION_ESTIMATE), and a GUIDED vehicle that loses its
  estimate falls back to HOLD, as Rover's EKF failsafe does.
- MANUAL: RC_CHANNELS_OVERRIDE (ch1 steering, ch3 throttle) and MANUAL_CONTROL (y steering,
  z throttle) are taken only from the ground-station system id and expire after
  `rc_override_timeout_s` (RC_OVERRIDE_TIME); with no override the car has no radio: neutral.
- GUIDED: SET_POSITION_TARGET_LOCAL_NED velocity targets (with or without yaw rate) expire
  after `guided_timeout_s` (Rover: 3 s).
- MAVLink 2 signing with a key: outgoing signed, unsigned or badly signed incoming refused.

How it moves: a throttle fraction (or a guided speed) sets the steady forward speed, steering
(or a guided yaw rate) the steady turn rate, full travel being `dynamics.max_speed_mps` and
`dynamics.max_turn_rate_radps`; the velocities follow the simulator's first-order lags
(`sim.dynamics.step_velocity_lag`, the inertia model), so the car turns in place as a
skid-steered rover does. Disarmed, HOLD and any other mode command zero. The pose it reports
is its true simulated pose (it plays a perfect EKF), in our frame converted to NED.

Use it as a class (`with MavlinkVehicle(settings) as car: car.pose()`), or as a process:
`qnav fake-vehicle` (it sends to udpout:127.0.0.1:14550, where `qnav bridge` listens by
default).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from qnav.contracts.daemon import Service, stop_on_signals
from qnav.contracts.errors import ConfigError
from qnav.contracts.mavlink import (
    GCS_SYSTEM_ID,
    MAV_AUTOPILOT_ARDUPILOTMEGA,
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_SET_MODE,
    MAV_FRAME_BODY_NED,
    MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
    MAV_MODE_FLAG_SAFETY_ARMED,
    MAV_RESULT_ACCEPTED,
    MAV_RESULT_DENIED,
    MAV_RESULT_FAILED,
    MAV_RESULT_UNSUPPORTED,
    MAV_STATE_ACTIVE,
    MAV_STATE_STANDBY,
    MAV_TYPE_GROUND_ROVER,
    MODE_NAMES,
    ROVER_MODES,
    drain,
    enu_to_ned,
    load_signing_key,
    mode_name,
    mode_number,
    open_connection,
    wrap_pi,
)
from qnav.contracts.motion import InertiaDynamics, step_velocity_lag
from qnav.contracts.settings import (
    check_range,
    from_dict,
    load_toml,
    parse_assignments,
    with_overrides,
)

log = logging.getLogger("qnav.simcar.mavlink_vehicle")

POS_IGNORE = 0x7
VEL_IGNORE = 0x38
YAW_IGNORE = 0x400
YAW_RATE_IGNORE = 0x800
NOT_READY = b"Arm: System not initialised"
"""What Rover says when asked to arm before its sensors are up (AP_Arming)."""
MAV_SEVERITY_CRITICAL = 2
HEADING_GAIN_PER_S = 2.0
"""Turn rate per radian of heading error when a guided target gives velocity without yaw rate."""


@dataclass(frozen=True)
class MavlinkVehicleSettings:
    """The test vehicle: its link, its ids, its Rover parameters and how it moves."""

    SECTION = ""

    connection: str = "udpout:127.0.0.1:14550"
    """pymavlink connection string of the vehicle: udpout sends to a bridge that listens there
    (as ArduPilot SITL's --out; the default pairs with `qnav bridge`'s default udpin), udpin
    serves a port and answers whoever sends."""
    baud_rate: int = 115200
    """Serial baud rate (serial devices only)."""
    system_id: int = 1
    """SYSID_THISMAV / MAV_SYSID."""
    component_id: int = 1
    """The autopilot's component id."""
    gcs_system_id: int = GCS_SYSTEM_ID
    """MAV_GCS_SYSID (SYSID_MYGCS): RC overrides and MANUAL_CONTROL from other ids are ignored."""
    initial_mode: str = "MANUAL"
    """Mode at boot (Rover's INITIAL_MODE default: MANUAL)."""
    heartbeat_period_s: float = 1.0
    """Period of HEARTBEAT (and SYS_STATUS)."""
    telemetry_period_s: float = 0.1
    """Period of LOCAL_POSITION_NED and ATTITUDE."""
    physics_period_s: float = 0.02
    """Time step of the motion."""
    rc_override_timeout_s: float = 3.0
    """RC_OVERRIDE_TIME: an override (or MANUAL_CONTROL) older than this is dropped."""
    guided_timeout_s: float = 3.0
    """A guided velocity target older than this is dropped (Rover: 3 s)."""
    require_position_for_guided: bool = True
    """GUIDED needs an EKF origin and a fresh vision position estimate, as on a real Rover."""
    position_timeout_s: float = 1.0
    """A vision position estimate older than this no longer counts as a position."""
    initialising_s: float = 0.0
    """The vehicle reports mode INITIALISING for this long after boot, then switches to
    `initial_mode`, undoing any mode taken meanwhile, as Rover does at the end of its boot."""
    arming_delay_s: float = 0.0
    """Arming is refused for this long after boot, with Rover's STATUSTEXT "Arm: System not
    initialised", as an autopilot whose sensors and EKF are still starting (a cold start)."""
    x_m: float = 0.0
    """Start position x, our frame (x_ned = y, y_ned = x)."""
    y_m: float = 0.0
    """Start position y."""
    yaw_rad: float = 0.0
    """Start heading, counter-clockwise from x."""
    battery_voltage_v: float = 12.6
    """Battery voltage reported in SYS_STATUS."""
    signing_key_file: str = ""
    """MAVLink 2 signing key file (empty: no signing); see docs/bridge.md for its format."""
    dynamics: InertiaDynamics = field(default_factory=InertiaDynamics)
    """Full-travel speeds and time constants of the motion."""
    external_physics: bool = False
    """The car moves only when `advance(duration_s)` is called (the sim-car's lockstep: one
    control period once that period's command has arrived), not with the clock; messages,
    heartbeats and telemetry keep real time. False: it moves in real time."""

    def __post_init__(self) -> None:
        check_range(self, "system_id", self.system_id, 1, 255)
        check_range(self, "component_id", self.component_id, 1, 255)
        check_range(self, "gcs_system_id", self.gcs_system_id, 1, 255)
        try:
            mode_number(self.initial_mode)
        except ValueError as error:
            raise ConfigError(f"initial_mode: {error}") from None
        for name in ("heartbeat_period_s", "telemetry_period_s", "physics_period_s"):
            check_range(self, name, getattr(self, name), 0.001, 10.0)
        for name in ("rc_override_timeout_s", "guided_timeout_s", "position_timeout_s"):
            check_range(self, name, getattr(self, name), 0.01, 60.0)
        check_range(self, "arming_delay_s", self.arming_delay_s, 0.0, 600.0)
        check_range(self, "initialising_s", self.initialising_s, 0.0, 600.0)
        if self.signing_key_file and not Path(self.signing_key_file).is_file():
            raise ConfigError(f"signing_key_file {self.signing_key_file!r} does not exist")


class Received(NamedTuple):
    """One message the vehicle received and accepted as MAVLink (kept for tests)."""

    time_s: float
    """Monotonic time of arrival."""
    type: str
    """Message type, e.g. RC_CHANNELS_OVERRIDE."""
    src_system: int
    src_component: int
    signed: bool
    fields: dict[str, Any]


class _Override(NamedTuple):
    steering: float
    throttle: float
    time_s: float


class _GuidedTarget(NamedTuple):
    vx: float
    vy: float
    yaw_rate: float
    type_mask: int
    frame: int
    time_s: float


def pwm_to_fraction(
    pwm_us: int, low_us: int = 1100, trim_us: int = 1500, high_us: int = 1900
) -> float:
    """The fraction of travel in [-1, 1] an RC PWM stands for (Rover's RCn_MIN/TRIM/MAX)."""
    if pwm_us >= trim_us:
        return min(1.0, (pwm_us - trim_us) / (high_us - trim_us))
    return max(-1.0, (pwm_us - trim_us) / (trim_us - low_us))


class MavlinkVehicle(Service):
    """The car: `start()` runs its loop in a thread, `stop()` ends it; `pose()` reads it."""

    def __init__(
        self, settings: MavlinkVehicleSettings, *, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.settings = settings
        self._clock = clock
        self._key = (
            load_signing_key(settings.signing_key_file) if settings.signing_key_file else None
        )
        self._lock = threading.Lock()
        self._pose = np.array([[settings.x_m, settings.y_m, settings.yaw_rad]], dtype=np.float64)
        self._velocity = np.zeros((1, 2), dtype=np.float64)
        self._armed = False
        self._initialising = settings.initialising_s > 0
        self._mode = (
            ROVER_MODES["INITIALISING"]
            if self._initialising
            else mode_number(settings.initial_mode)
        )
        self._override: _Override | None = None
        self._guided: _GuidedTarget | None = None
        self._origin: tuple[int, int, int] | None = None
        self._last_vision_s = -math.inf
        self._link_enabled = True
        self._received: deque[Received] = deque(maxlen=20_000)
        self.counters: Counter[str] = Counter()
        """rejected (bad signature), bad_data, ignored_override (not from the GCS id)."""
        self._conn: Any = None
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()
        self._boot_s = clock()
        self._handled = threading.Condition()
        """Notified after each batch of messages is handled (`wait_for_targets` waits on it)."""

    # -- life cycle ---------------------------------------------------------------------------

    def start(self) -> None:
        """Open the connection and start the vehicle's thread."""
        self._conn = open_connection(
            self.settings.connection,
            baud_rate=self.settings.baud_rate,
            system_id=self.settings.system_id,
            component_id=self.settings.component_id,
            signing_key=self._key,
        )
        self._stopping.clear()
        self._thread = threading.Thread(target=self._loop, name="mavlink-vehicle", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop the thread and close the connection (also `stop()`)."""
        self._stopping.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    stop = close

    # -- what tests and other processes read --------------------------------------------------

    def pose(self) -> tuple[float, float, float]:
        """(x m, y m, yaw rad) in our frame (yaw counter-clockwise from x)."""
        with self._lock:
            x, y, yaw = self._pose[0]
        return float(x), float(y), float(yaw)

    def velocity(self) -> tuple[float, float]:
        """(forward m/s, turn rate rad/s, counter-clockwise)."""
        with self._lock:
            speed, rate = self._velocity[0]
        return float(speed), float(rate)

    @property
    def armed(self) -> bool:
        """True while armed."""
        return self._armed

    @property
    def mode(self) -> str:
        """The current Rover mode's name."""
        return mode_name(self._mode)

    def set_link_enabled(self, enabled: bool) -> None:
        """Cut (False) or restore the radio: while cut, nothing is sent or taken in."""
        self._link_enabled = enabled

    def received(self, kind: str | Sequence[str] | None = None) -> list[Received]:
        """Accepted messages so far, oldest first, optionally of some types only."""
        kinds = {kind} if isinstance(kind, str) else set(kind or ())
        with self._lock:
            return [r for r in self._received if not kinds or r.type in kinds]

    def set_pose(self, x_m: float, y_m: float, yaw_rad: float) -> None:
        """Place the car (velocities zeroed), e.g. at the start of a sim-in-the-loop episode."""
        with self._lock:
            self._pose[0] = (x_m, y_m, yaw_rad)
            self._velocity[:] = 0.0

    def targets(self) -> tuple[float, float]:
        """The (forward m/s, counter-clockwise rad/s) the car is commanded now, under its mode
        and inputs (what its velocities approach)."""
        return self._targets(self._clock())

    def wait_for_targets(
        self, speed_mps: float, rate_radps: float, tolerance: float, timeout_s: float
    ) -> bool:
        """Wait until the commanded velocities are within `tolerance` of these (a command has
        reached the car over MAVLink); False if not within `timeout_s`."""

        def reached() -> bool:
            speed, rate = self.targets()
            return abs(speed - speed_mps) <= tolerance and abs(rate - rate_radps) <= tolerance

        with self._handled:
            return self._handled.wait_for(reached, timeout_s)

    def advance(self, duration_s: float) -> None:
        """Move the car `duration_s` under its current command (with `external_physics`)."""
        if not self.settings.external_physics:
            raise RuntimeError("advance() needs external_physics = true: this car moves itself")
        self._move(*self.targets(), duration_s)

    # -- the loop -----------------------------------------------------------------------------

    def _loop(self) -> None:
        settings = self.settings
        now = self._clock()
        next_physics = now + settings.physics_period_s
        next_heartbeat = now
        next_telemetry = now
        while not self._stopping.is_set():
            now = self._clock()
            wait = max(0.0, min(next_physics, next_heartbeat, next_telemetry) - now)
            try:
                messages = drain(self._conn, wait)
            except Exception:  # a malformed packet must not stop the car's clock
                log.debug("receive error", exc_info=True)
                messages = []
            if self._link_enabled and messages:
                for message in messages:
                    self._handle(message, self._clock())
                with self._handled:
                    self._handled.notify_all()
            now = self._clock()
            # Absolute deadlines: a late tick is followed by a short one, not by drift.
            while now >= next_physics:
                self._step(settings.physics_period_s, next_physics)
                next_physics += settings.physics_period_s
            if now >= next_heartbeat:
                self._send_heartbeat()
                next_heartbeat = now + settings.heartbeat_period_s
            if now >= next_telemetry:
                self._send_telemetry(now)
                next_telemetry = now + settings.telemetry_period_s

    def _step(self, period_s: float, now: float) -> None:
        if self._initialising and now - self._boot_s >= self.settings.initialising_s:
            self._initialising = False
            self._mode = mode_number(self.settings.initial_mode)
        speed, rate = self._targets(now)
        if not self.settings.external_physics:  # else the sim-car moves it (`advance`)
            self._move(speed, rate, period_s)

    def _move(self, speed_mps: float, rate_radps: float, period_s: float) -> None:
        """The simulator's own lagged motion towards the commanded speed and turn rate."""
        with self._lock:
            self._pose, self._velocity = step_velocity_lag(
                self._pose,
                self._velocity,
                np.array([speed_mps]),
                np.array([rate_radps]),
                params=self.settings.dynamics,
                period_s=period_s,
            )

    def _position_ok(self, now: float) -> bool:
        return (
            self._origin is not None
            and now - self._last_vision_s <= self.settings.position_timeout_s
        )

    def _targets(self, now: float) -> tuple[float, float]:
        """Commanded (forward m/s, counter-clockwise rad/s) under the current mode and inputs."""
        settings, dynamics = self.settings, self.settings.dynamics
        if self._mode == ROVER_MODES["GUIDED"] and not self._guided_allowed(now):
            self._mode = ROVER_MODES["HOLD"]
            log.warning("position estimate lost: GUIDED -> HOLD")
        if not self._armed:
            return 0.0, 0.0
        if self._mode == ROVER_MODES["MANUAL"]:
            override = self._override
            if override is None or now - override.time_s > settings.rc_override_timeout_s:
                return 0.0, 0.0
            return (
                override.throttle * dynamics.max_speed_mps,
                -override.steering * dynamics.max_turn_rate_radps,
            )
        if self._mode == ROVER_MODES["GUIDED"]:
            target = self._guided
            if target is None or now - target.time_s > settings.guided_timeout_s:
                return 0.0, 0.0
            return self._guided_velocity(target)
        return 0.0, 0.0

    def _guided_velocity(self, target: _GuidedTarget) -> tuple[float, float]:
        """Rover's reading of a velocity target: speed is the vector's length, signed by vx."""
        dynamics = self.settings.dynamics
        speed = math.hypot(target.vx, target.vy) * (-1.0 if target.vx < 0 else 1.0)
        speed = max(-dynamics.max_speed_mps, min(dynamics.max_speed_mps, speed))
        limit = dynamics.max_turn_rate_radps
        if not target.type_mask & YAW_RATE_IGNORE:
            return speed, max(-limit, min(limit, -target.yaw_rate))
        # Velocity only: steer towards the vector's direction.
        heading_ned = math.atan2(target.vy, target.vx)
        _, _, yaw_ned = enu_to_ned(*self.pose())
        if target.frame == MAV_FRAME_BODY_NED:
            heading_ned += yaw_ned
        error = wrap_pi(heading_ned - yaw_ned)
        return abs(speed), max(-limit, min(limit, -HEADING_GAIN_PER_S * error))

    # -- incoming -----------------------------------------------------------------------------

    def _handle(self, message: Any, now: float) -> None:
        kind = message.get_type()
        if kind == "BAD_DATA":
            reason = str(getattr(message, "reason", ""))
            self.counters["rejected" if "signature" in reason.lower() else "bad_data"] += 1
            return
        src = message.get_srcSystem()
        with self._lock:
            self._received.append(
                Received(
                    now,
                    kind,
                    src,
                    message.get_srcComponent(),
                    bool(getattr(message, "_signed", False)),
                    message.to_dict(),
                )
            )
        own = self.settings.system_id
        if kind == "RC_CHANNELS_OVERRIDE" and message.target_system in (0, own):
            if src != self.settings.gcs_system_id:
                self.counters["ignored_override"] += 1
                return
            self._take_override(message.chan1_raw, message.chan3_raw, now)
        elif kind == "MANUAL_CONTROL" and message.target in (0, own):
            if src != self.settings.gcs_system_id:
                self.counters["ignored_override"] += 1
                return
            self._override = _Override(_axis(message.y), _axis(message.z), now)
        elif kind == "SET_POSITION_TARGET_LOCAL_NED" and message.target_system in (0, own):
            if self._mode == ROVER_MODES["GUIDED"]:
                self._guided = _GuidedTarget(
                    message.vx,
                    message.vy,
                    message.yaw_rate,
                    message.type_mask,
                    message.coordinate_frame,
                    now,
                )
        elif kind == "VISION_POSITION_ESTIMATE":
            self._last_vision_s = now
        elif kind == "SET_GPS_GLOBAL_ORIGIN" and message.target_system in (0, own):
            self._origin = (message.latitude, message.longitude, message.altitude)
            self._send(
                self._conn.mav.gps_global_origin_encode(
                    message.latitude, message.longitude, message.altitude
                )
            )
        elif kind == "COMMAND_LONG" and message.target_system in (0, own):
            self._command(message, now)
        elif kind == "SET_MODE" and message.target_system in (0, own):
            self._set_mode(int(message.custom_mode), now)

    def _take_override(self, steering_pwm: int, throttle_pwm: int, now: float) -> None:
        previous = self._override
        steering = previous.steering if previous else 0.0
        throttle = previous.throttle if previous else 0.0
        # 0 releases a channel back to the (absent) radio; UINT16_MAX leaves it as it was.
        if steering_pwm == 0:
            steering = 0.0
        elif steering_pwm != 65535:
            steering = pwm_to_fraction(steering_pwm)
        if throttle_pwm == 0:
            throttle = 0.0
        elif throttle_pwm != 65535:
            throttle = pwm_to_fraction(throttle_pwm)
        self._override = _Override(steering, throttle, now)

    def _command(self, message: Any, now: float) -> None:
        command = int(message.command)
        if command == MAV_CMD_COMPONENT_ARM_DISARM:
            arm = message.param1 >= 0.5
            if arm and now - self._boot_s < self.settings.arming_delay_s:
                result = MAV_RESULT_FAILED
                self._send(self._conn.mav.statustext_encode(MAV_SEVERITY_CRITICAL, NOT_READY))
            elif arm and self._mode == ROVER_MODES["GUIDED"] and not self._guided_allowed(now):
                result = MAV_RESULT_FAILED
            else:
                result = MAV_RESULT_ACCEPTED
                if arm != self._armed:
                    self._armed = arm
                    self._override = None
                    self._guided = None
                    log.info("%s", "armed" if arm else "disarmed")
        elif command == MAV_CMD_DO_SET_MODE:
            result = self._set_mode(int(message.param2), now)
        else:
            result = MAV_RESULT_UNSUPPORTED
        self._send(
            self._conn.mav.command_ack_encode(
                command, result, 0, 0, message.get_srcSystem(), message.get_srcComponent()
            )
        )

    def _guided_allowed(self, now: float) -> bool:
        return not self.settings.require_position_for_guided or self._position_ok(now)

    def _set_mode(self, mode: int, now: float) -> int:
        if mode not in MODE_NAMES:
            return MAV_RESULT_DENIED
        if mode == ROVER_MODES["GUIDED"] and not self._guided_allowed(now):
            log.info("mode change to GUIDED refused: no position estimate")
            return MAV_RESULT_FAILED
        if mode != self._mode:
            log.info("mode %s -> %s", mode_name(self._mode), mode_name(mode))
            self._mode = mode
            self._guided = None
        return MAV_RESULT_ACCEPTED

    # -- outgoing -----------------------------------------------------------------------------

    def _send(self, message: Any) -> None:
        if not self._link_enabled or self._conn is None:
            return
        try:
            self._conn.mav.send(message)
        except OSError:
            log.debug("send failed", exc_info=True)

    def _send_heartbeat(self) -> None:
        mav = self._conn.mav
        base_mode = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (
            MAV_MODE_FLAG_SAFETY_ARMED if self._armed else 0
        )
        status = MAV_STATE_ACTIVE if self._armed else MAV_STATE_STANDBY
        self._send(
            mav.heartbeat_encode(
                MAV_TYPE_GROUND_ROVER, MAV_AUTOPILOT_ARDUPILOTMEGA, base_mode, self._mode, status
            )
        )
        voltage_mv = round(self.settings.battery_voltage_v * 1000)
        self._send(mav.sys_status_encode(0, 0, 0, 0, voltage_mv, -1, -1, 0, 0, 0, 0, 0, 0))

    def _send_telemetry(self, now: float) -> None:
        mav = self._conn.mav
        x, y, yaw = self.pose()
        speed, rate = self.velocity()
        north, east, yaw_ned = enu_to_ned(x, y, yaw)
        v_north, v_east = speed * math.sin(yaw), speed * math.cos(yaw)
        boot_ms = int((now - self._boot_s) * 1000) & 0xFFFFFFFF
        self._send(mav.local_position_ned_encode(boot_ms, north, east, 0.0, v_north, v_east, 0.0))
        self._send(mav.attitude_encode(boot_ms, 0.0, 0.0, yaw_ned, 0.0, 0.0, -rate))


def _axis(value: int) -> float:
    """A MANUAL_CONTROL axis (-1000..1000, INT16_MAX: unused) as a fraction."""
    if value == 32767:
        return 0.0
    return max(-1.0, min(1.0, value / 1000.0))


def load_vehicle_settings(
    path: Path | None, assignments: list[str] | None = None
) -> MavlinkVehicleSettings:
    """Vehicle settings from a TOML file and `field=value` overrides (defaults without)."""
    settings = (
        MavlinkVehicleSettings()
        if path is None
        else from_dict(MavlinkVehicleSettings, load_toml(path))
    )
    if assignments:
        settings = with_overrides(settings, parse_assignments(assignments))
    return settings


def serve(settings: MavlinkVehicleSettings, pose_period_s: float = 1.0) -> None:
    """`qnav fake-vehicle`: run the vehicle until SIGINT or SIGTERM, logging its pose every
    `pose_period_s` (0: never)."""
    with stop_on_signals() as stop, MavlinkVehicle(settings) as vehicle:
        log.info("vehicle %d serving %s", settings.system_id, settings.connection)
        period = pose_period_s if pose_period_s > 0 else 3600.0
        while not stop.wait(period):
            x, y, yaw = vehicle.pose()
            log.info(
                "%s %s pose x %.3f y %.3f yaw %.3f",
                vehicle.mode,
                "armed" if vehicle.armed else "disarmed",
                x,
                y,
                yaw,
            )
