"""Settings of the firmware bridge: one TOML file with a section per concern.

`qnav bridge --config FILE` reads them; `config/bridge.toml` is a commented example and
`qnav bridge --print-config` prints every setting with its default.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from qnav.contracts.errors import ConfigError
from qnav.contracts.mavlink import (
    AUTOPILOT_COMPONENT_ID,
    COMPANION_COMPONENT_ID,
    GCS_SYSTEM_ID,
    ROVER_MODES,
    mode_number,
)
from qnav.contracts.settings import check_range, from_dict, load_toml
from qnav.contracts.transport import ZenohSettings

CONNECTION_PREFIXES = ("udpin:", "udpout:", "udpbcast:", "udp:", "tcp:", "tcpin:", "/dev/", "COM")
UNCALIBRATED_SPEED_AT_FULL_THROTTLE_MPS = 20.0
"""The speed at full throttle the bridge assumes until the car's is measured: a fast hobby car's
(72 km/h; ArduPilot's SITL rover, SIM_Rover, is as fast), so a car that is not faster drives no
faster than asked, and a slow car creeps or, inside its RC dead zone, stands still."""


@dataclass(frozen=True)
class MavlinkSettings:
    """The MAVLink link to the autopilot and the ids used on it."""

    SECTION = "mavlink"

    connection: str = "udpin:127.0.0.1:14550"
    """pymavlink connection string: udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, or a
    serial device such as /dev/ttyAMA0 (with `baud_rate`)."""
    baud_rate: int = 115200
    """Serial baud rate (serial devices only; ArduPilot's SERIALn_BAUD)."""
    vehicle_system_id: int = 1
    """The autopilot's system id (its SYSID_THISMAV / MAV_SYSID)."""
    vehicle_component_id: int = AUTOPILOT_COMPONENT_ID
    """The autopilot's component id."""
    gcs_system_id: int = GCS_SYSTEM_ID
    """System id of RC overrides and MANUAL_CONTROL; must equal the autopilot's MAV_GCS_SYSID
    (SYSID_MYGCS before ArduPilot 4.7), or Rover ignores them."""
    companion_component_id: int = COMPANION_COMPONENT_ID
    """Component id of the bridge's heartbeat and other messages (191: onboard computer)."""
    heartbeat_period_s: float = 1.0
    """Period of the bridge's companion heartbeat."""
    gcs_heartbeat: bool = True
    """Also send a ground-station heartbeat from `gcs_system_id`, so the autopilot's GCS
    failsafe (FS_GCS_ENABLE) stops the car if the bridge dies."""
    link_timeout_s: float = 2.5
    """The link is down when no vehicle heartbeat arrived for this long (ArduPilot sends 1 Hz)."""
    reconnect_period_s: float = 2.0
    """While the link is down, reopen the connection this often."""

    def __post_init__(self) -> None:
        if not self.connection.startswith(CONNECTION_PREFIXES) and ":" in self.connection:
            raise ConfigError(
                f"mavlink.connection = {self.connection!r} is not a connection string: use "
                "udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT or a serial device path"
            )
        if not self.connection:
            raise ConfigError("mavlink.connection is empty")
        check_range(self, "baud_rate", self.baud_rate, 1200, 12_000_000)
        for name in ("vehicle_system_id", "gcs_system_id"):
            check_range(self, name, getattr(self, name), 1, 255)
        for name in ("vehicle_component_id", "companion_component_id"):
            check_range(self, name, getattr(self, name), 1, 255)
        check_range(self, "heartbeat_period_s", self.heartbeat_period_s, 0.01, 10.0)
        check_range(self, "link_timeout_s", self.link_timeout_s, 0.05, 60.0)
        check_range(self, "reconnect_period_s", self.reconnect_period_s, 0.01, 600.0)


@dataclass(frozen=True)
class OutputSettings:
    """How a Twist becomes a MAVLink message the rover acts on."""

    SECTION = "output"

    mode: Literal["manual", "guided"] = "manual"
    """manual: RC overrides or MANUAL_CONTROL in Rover's MANUAL mode (no position estimate
    needed); guided: SET_POSITION_TARGET_LOCAL_NED velocity and yaw rate in GUIDED mode (the
    motion-capture pose is forwarded as the position estimate)."""
    manual_message: Literal["rc_override", "manual_control"] = "rc_override"
    """manual mode: RC_CHANNELS_OVERRIDE (ch1 steering, ch3 throttle) or MANUAL_CONTROL."""
    speed_at_full_throttle_mps: float | None = None
    """manual mode: the forward speed that maps to full throttle, as measured on the car (`qnav
    calibrate-car --config FILE --write` writes it); none (not measured): the bridge drives as if
    it were 20 m/s (UNCALIBRATED_SPEED_AT_FULL_THROTTLE_MPS), so 0.5 m/s is 2.5 % throttle."""
    turn_rate_at_full_steering_radps: float = 1.0
    """manual mode: the turn rate that maps to full steering (measure it on the car)."""
    steering_reversed: bool = False
    """manual mode: flip the steering direction (a car whose servo turns the other way)."""
    throttle_reversed: bool = False
    """manual mode: flip the throttle direction."""
    steering_pwm_min_us: int = 1100
    """Steering PWM for full left (RC1_MIN); never sent below it."""
    steering_pwm_trim_us: int = 1500
    """Steering PWM for straight ahead (RC1_TRIM)."""
    steering_pwm_max_us: int = 1900
    """Steering PWM for full right (RC1_MAX); never sent above it."""
    throttle_pwm_min_us: int = 1100
    """Throttle PWM for full reverse (RC3_MIN); never sent below it. Raise it to forbid reverse."""
    throttle_pwm_trim_us: int = 1500
    """Throttle PWM for stop (RC3_TRIM)."""
    throttle_pwm_max_us: int = 1900
    """Throttle PWM for full forward (RC3_MAX); lower it to cap the speed (RC overrides only:
    MANUAL_CONTROL carries no PWM; `max_throttle_fraction` caps both)."""
    max_throttle_fraction: float = 1.0
    """manual mode: the largest throttle sent, as a fraction of full travel, forward and
    reverse, in both messages (RC_CHANNELS_OVERRIDE and MANUAL_CONTROL); e.g. 0.4 indoors.
    With `throttle_pwm_min_us` = trim, reverse is forbidden in both too."""
    guided_max_speed_mps: float = 1.0
    """guided mode: forward speed targets are clipped to this magnitude."""
    guided_max_turn_rate_radps: float = 1.0
    """guided mode: yaw-rate targets are clipped to this magnitude."""

    def __post_init__(self) -> None:
        if self.mode not in ("manual", "guided"):
            raise ConfigError(f"output.mode = {self.mode!r} is not one of manual, guided")
        if self.manual_message not in ("rc_override", "manual_control"):
            raise ConfigError(
                f"output.manual_message = {self.manual_message!r} is not one of "
                "rc_override, manual_control"
            )
        for name in ("speed_at_full_throttle_mps", "turn_rate_at_full_steering_radps"):
            if getattr(self, name) is not None:
                check_range(self, name, getattr(self, name), 0.0, 100.0, exclusive_low=True)
        for name in ("guided_max_speed_mps", "guided_max_turn_rate_radps"):
            check_range(self, name, getattr(self, name), 0.0, 100.0)
        check_range(
            self, "max_throttle_fraction", self.max_throttle_fraction, 0.0, 1.0, exclusive_low=True
        )
        for channel in ("steering", "throttle"):
            low = getattr(self, f"{channel}_pwm_min_us")
            trim = getattr(self, f"{channel}_pwm_trim_us")
            high = getattr(self, f"{channel}_pwm_max_us")
            check_range(self, f"{channel}_pwm_min_us", low, 800, 2200)
            check_range(
                self,
                f"{channel}_pwm_trim_us",
                trim,
                low,
                2200,
                why=f"trim must be at least {channel}_pwm_min_us",
            )
            check_range(
                self,
                f"{channel}_pwm_max_us",
                high,
                trim,
                2200,
                why=f"max must be at least {channel}_pwm_trim_us",
            )


@dataclass(frozen=True)
class FailsafeSettings:
    """The bridge's own failsafe: it stops the car whatever the controller does."""

    SECTION = "failsafe"

    command_timeout_s: float = 0.5
    """A command older than this is stale: the bridge sends stop instead."""
    stop_period_s: float = 0.1
    """While commands are stale or absent, stop is sent again at this period."""
    stop_repeats_on_exit: int = 3
    """On SIGINT or SIGTERM, stop is sent this many times (UDP may drop one)."""
    disarm_on_exit: bool = True
    """On SIGINT or SIGTERM, disarm after sending stop, once the vehicle reports it is at rest
    (`rest_speed_mps`; or it stopped slowing down, `rest_timeout_s`; or `brake_timeout_s`
    passed): disarming a moving car removes its brakes."""
    brake_mode: str = "GUIDED"
    """A Rover mode that brakes, switched to when the bridge stops a moving car (command
    silence, exit) and left for the output's mode on the next fresh command. GUIDED (default)
    brakes to a stop; it needs a position estimate (GPS or the motion-capture pose), and
    without one Rover refuses it and the car coasts on neutral. Empty: stay in the output's
    mode, where a manual stop is neutral sticks, on which Rover coasts (SITL: 5-7 s from 1 m/s;
    GUIDED's zero velocity target brakes by itself)."""
    rest_speed_mps: float = 0.05
    """The vehicle is at rest when its LOCAL_POSITION_NED speed is below this."""
    rest_timeout_s: float = 5.0
    """On exit, disarm the vehicle anyway once its speed reports have not fallen by
    `rest_speed_mps` for this long: stops and the brake mode are not slowing it (or something
    else drives it), and disarming then loses nothing."""
    brake_timeout_s: float = 30.0
    """On exit, disarm after this long at the most, even if the vehicle is still slowing down."""
    implausible_factor: float = 10.0
    """A command beyond this many times the output's full scale (speed or turn rate) is not
    one anyone meant: it is refused as malformed and the car is stopped; closer overshoot is
    clipped."""

    def __post_init__(self) -> None:
        check_range(self, "implausible_factor", self.implausible_factor, 1.0, 1e6)
        check_range(self, "command_timeout_s", self.command_timeout_s, 0.01, 10.0)
        check_range(self, "stop_period_s", self.stop_period_s, 0.005, 2.0)
        check_range(self, "stop_repeats_on_exit", self.stop_repeats_on_exit, 1, 100)
        if self.brake_mode:
            try:
                mode_number(self.brake_mode)
            except ValueError as error:
                raise ConfigError(f"failsafe.brake_mode: {error}") from None
        check_range(self, "rest_speed_mps", self.rest_speed_mps, 0.0, 10.0, exclusive_low=True)
        check_range(self, "rest_timeout_s", self.rest_timeout_s, 0.0, 600.0)
        check_range(
            self,
            "brake_timeout_s",
            self.brake_timeout_s,
            self.rest_timeout_s,
            3600.0,
            why="at least rest_timeout_s",
        )


@dataclass(frozen=True)
class VehicleSettings:
    """What the bridge asks of the vehicle, and how often it reports the vehicle's state."""

    SECTION = "vehicle"

    arm_on_connect: bool = False
    """Arm when the link first comes up (later arming: a request on qnav/vehicle_request)."""
    set_mode_on_connect: bool = True
    """Switch to the output mode's Rover mode (MANUAL or GUIDED) when the link first comes up."""
    remote_arming: bool = False
    """Take arm requests from zenoh (qnav/vehicle_request); off, anyone on the network could
    arm the car, so only arm_on_connect, the RC or a ground station arm it (disarm and mode
    requests are always taken)."""
    state_period_s: float = 0.2
    """Period of the vehicle state message on zenoh (also sent at once on any change)."""
    request_retry_s: float = 0.5
    """An arm or mode request not yet shown by the vehicle's heartbeat is sent again this often
    (each refusal's text goes out on the vehicle state topic)."""
    request_timeout_s: float = 120.0
    """Give up on an arm or mode request after this long (0: never). An autopilot refuses to
    arm until its pre-arm checks pass, which takes tens of seconds after it boots."""

    def __post_init__(self) -> None:
        check_range(self, "state_period_s", self.state_period_s, 0.01, 60.0)
        check_range(self, "request_retry_s", self.request_retry_s, 0.01, 60.0)
        check_range(self, "request_timeout_s", self.request_timeout_s, 0.0, 86400.0)


@dataclass(frozen=True)
class VisionSettings:
    """The motion-capture pose forwarded to the autopilot as its position, in every output mode."""

    SECTION = "vision"

    forward_pose: bool = True
    """Every output: send each pose from zenoh as VISION_POSITION_ESTIMATE (EK3_SRC1_POSXY=6)."""
    origin_lat_deg: float = -35.363261
    """Latitude of the EKF origin set once with SET_GPS_GLOBAL_ORIGIN (any place will do)."""
    origin_lon_deg: float = 149.165230
    """Longitude of the EKF origin."""
    origin_alt_m: float = 584.0
    """Altitude of the EKF origin above mean sea level."""
    max_position_m: float = 10_000.0
    """A pose farther than this from the origin on either axis is refused as malformed and not
    forwarded (a finite 1e308 is still no place a motion-capture system measured)."""

    def __post_init__(self) -> None:
        check_range(self, "origin_lat_deg", self.origin_lat_deg, -90.0, 90.0)
        check_range(self, "origin_lon_deg", self.origin_lon_deg, -180.0, 180.0)
        check_range(self, "origin_alt_m", self.origin_alt_m, -1000.0, 10000.0)
        check_range(self, "max_position_m", self.max_position_m, 1.0, 1e7)


@dataclass(frozen=True)
class SigningSettings:
    """MAVLink 2 signing: outgoing messages signed, unsigned incoming messages rejected."""

    SECTION = "signing"

    enabled: bool = False
    """Sign every message and accept only correctly signed ones."""
    key_file: str = ""
    """File with the 32-byte key: 64 hex digits, 32 raw bytes, or a passphrase (its SHA-256,
    as MAVProxy's `signing setup`). The same key must be set on the autopilot."""

    def __post_init__(self) -> None:
        if self.enabled and not self.key_file:
            raise ConfigError("signing.key_file is empty but signing.enabled is true")
        if self.enabled and not Path(self.key_file).is_file():
            raise ConfigError(f"signing.key_file {self.key_file!r} does not exist")


@dataclass(frozen=True)
class BridgeSettings:
    """Everything `qnav bridge` needs."""

    SECTION = ""

    zenoh: ZenohSettings = field(default_factory=ZenohSettings)
    """How the bridge joins zenoh."""
    mavlink: MavlinkSettings = field(default_factory=MavlinkSettings)
    """The link to the autopilot."""
    output: OutputSettings = field(default_factory=OutputSettings)
    """Twist to MAVLink."""
    failsafe: FailsafeSettings = field(default_factory=FailsafeSettings)
    """When and how the bridge stops the car."""
    vehicle: VehicleSettings = field(default_factory=VehicleSettings)
    """Arming, mode and state reports."""
    vision: VisionSettings = field(default_factory=VisionSettings)
    """Motion-capture pose forwarding (every output mode)."""
    signing: SigningSettings = field(default_factory=SigningSettings)
    """MAVLink 2 signing."""

    @property
    def rover_mode(self) -> int:
        """The Rover mode the output mode needs."""
        return ROVER_MODES["GUIDED" if self.output.mode == "guided" else "MANUAL"]


def load_settings(path: Path | None) -> BridgeSettings:
    """Bridge settings from a TOML file (defaults without one)."""
    if path is None:
        return BridgeSettings()
    return from_dict(BridgeSettings, load_toml(path))
