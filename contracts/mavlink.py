"""MAVLink conventions shared by the firmware bridge and the test vehicle in `sim/`.

One definition of what both ends of the MAVLink link must agree on: ArduPilot Rover's mode
numbers, the ids a companion computer uses, the SET_POSITION_TARGET type masks, the frame
conversion between our planar frame and MAVLink's NED frame, and how a signing key file reads.

Our frame is the ROS one (x, y in the floor plane, z up, yaw counter-clockwise from x); MAVLink
local frames are NED (x north, y east, z down, yaw clockwise from north). The conversion is the
one MAVROS uses: x_ned = y, y_ned = x, yaw_ned = pi/2 - yaw.

pymavlink is imported only by `mavutil()`, so importing this module costs nothing.
"""

from __future__ import annotations

import hashlib
import math
import os
import re
import time
from pathlib import Path
from typing import Any

from qnav.contracts.errors import ConfigError

ROVER_MODES: dict[str, int] = {
    "MANUAL": 0,
    "ACRO": 1,
    "STEERING": 3,
    "HOLD": 4,
    "LOITER": 5,
    "FOLLOW": 6,
    "SIMPLE": 7,
    "DOCK": 8,
    "CIRCLE": 9,
    "AUTO": 10,
    "RTL": 11,
    "SMART_RTL": 12,
    "GUIDED": 15,
    "INITIALISING": 16,
}
"""ArduPilot Rover's flight modes as HEARTBEAT.custom_mode numbers."""

MODE_NAMES: dict[int, str] = {number: name for name, number in ROVER_MODES.items()}
"""Rover custom_mode number -> mode name."""

GCS_SYSTEM_ID = 255
"""Rover accepts RC overrides and MANUAL_CONTROL only from this id (MAV_GCS_SYSID/SYSID_MYGCS)."""
COMPANION_COMPONENT_ID = 191
"""MAV_COMP_ID_ONBOARD_COMPUTER: the component id of a companion computer."""
AUTOPILOT_COMPONENT_ID = 1
"""MAV_COMP_ID_AUTOPILOT1."""

MAV_TYPE_GCS = 6
MAV_TYPE_GROUND_ROVER = 10
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_INVALID = 8
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_STATE_STANDBY = 3
MAV_STATE_ACTIVE = 4
MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_BODY_NED = 8
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_RESULT_ACCEPTED = 0
MAV_RESULT_DENIED = 2
MAV_RESULT_UNSUPPORTED = 3
MAV_RESULT_FAILED = 4

RC_IGNORE = 65535
"""RC_CHANNELS_OVERRIDE: leave this channel to the radio (UINT16_MAX)."""

TYPE_MASK_VELOCITY = 0x0DC7
"""SET_POSITION_TARGET_*: velocity only (position, acceleration, yaw and yaw rate ignored)."""
TYPE_MASK_VELOCITY_YAW_RATE = 0x05C7
"""SET_POSITION_TARGET_*: velocity and yaw rate (position, acceleration and yaw ignored)."""


def enu_to_ned(x_m: float, y_m: float, yaw_rad: float) -> tuple[float, float, float]:
    """Our planar pose (x, y, yaw counter-clockwise) as NED (north, east, yaw clockwise)."""
    return y_m, x_m, wrap_pi(math.pi / 2 - yaw_rad)


def ned_to_enu(north_m: float, east_m: float, yaw_rad: float) -> tuple[float, float, float]:
    """A NED pose as our planar pose (the inverse of `enu_to_ned`)."""
    return east_m, north_m, wrap_pi(math.pi / 2 - yaw_rad)


def wrap_pi(angle_rad: float) -> float:
    """An angle wrapped to [-pi, pi)."""
    return (angle_rad + math.pi) % (2 * math.pi) - math.pi


def mode_number(mode: str | int) -> int:
    """A Rover mode given by name (any case) or number, as its custom_mode number."""
    if isinstance(mode, int) and not isinstance(mode, bool):
        if mode in MODE_NAMES:
            return mode
    elif isinstance(mode, str) and mode.upper() in ROVER_MODES:
        return ROVER_MODES[mode.upper()]
    raise ValueError(f"unknown Rover mode {mode!r}: choose one of {', '.join(ROVER_MODES)}")


def mode_name(number: int) -> str:
    """The name of a Rover custom_mode number (`MODE_<n>` for numbers Rover does not define)."""
    return MODE_NAMES.get(number, f"MODE_{number}")


SIGNING_KEY_BYTES = 32


def load_signing_key(path: Path | str) -> bytes:
    """The 32-byte MAVLink 2 signing key in a key file.

    The file holds 64 hexadecimal digits, or exactly 32 raw bytes, or else a passphrase whose
    SHA-256 is the key (what MAVProxy's `signing setup PASSPHRASE` and Mission Planner do).
    Errors name the file, never its content: the key must not reach a log.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as error:
        raise ConfigError(f"signing key file {path}: cannot read it ({error.strerror})") from None
    text = raw.strip()
    if re.fullmatch(rb"[0-9a-fA-F]{64}", text):
        return bytes.fromhex(text.decode("ascii"))
    if len(raw) == SIGNING_KEY_BYTES:
        return raw
    if not text:
        raise ConfigError(f"signing key file {path} is empty")
    return hashlib.sha256(text).digest()


def key_file_is_private(path: Path | str) -> bool:
    """False when group or others may read the key file (worth a warning, as ssh gives)."""
    return os.stat(path).st_mode & 0o077 == 0


def mavutil() -> Any:
    """pymavlink's `mavutil`, speaking MAVLink 2 with the ardupilotmega dialect.

    pymavlink picks its wire protocol from the MAVLINK20 environment variable when a dialect
    is loaded; signing needs MAVLink 2, so it is set before the dialect is (re)loaded.
    """
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil as module

    if module.current_dialect != "ardupilotmega" or module.mavlink.WIRE_PROTOCOL_VERSION != "2.0":
        module.set_dialect("ardupilotmega")
    return module


SIGNING_EPOCH_S = 1420070400
"""MAVLink 2 signing timestamps count 10-microsecond units from 2015-01-01 00:00 UTC."""


def signing_timestamp_now() -> int:
    """The current signing timestamp (10 us units since the signing epoch)."""
    return int(max(time.time() - SIGNING_EPOCH_S, 0.0) * 100_000)


def open_connection(
    connection: str,
    *,
    baud_rate: int,
    system_id: int,
    component_id: int,
    signing_key: bytes | None = None,
    signing_timestamp: int = 0,
) -> Any:
    """An open pymavlink connection (MAVLink 2) for a connection string, signing if given a key.

    With a key, every outgoing message is signed and incoming messages without a valid
    signature are refused by the parser (they come out as BAD_DATA). `signing_timestamp` lets
    a reopened link continue after the last timestamp it sent, as replay protection requires.
    A malformed connection string raises ConfigError; a port that cannot be opened, OSError.
    """
    module = mavutil()
    try:
        conn = module.mavlink_connection(
            connection,
            baud=baud_rate,
            source_system=system_id,
            source_component=component_id,
            autoreconnect=False,
            retries=0,
        )
    except ValueError as error:
        raise ConfigError(f"MAVLink connection {connection!r} is malformed: {error}") from None
    except ImportError as error:
        raise ConfigError(f"MAVLink connection {connection!r} needs {error.name}") from None
    if hasattr(conn, "handle_eof"):
        # pymavlink's TCP link prints and carries on when the peer goes; say so instead, so
        # the owner can reopen (and its loop does not spin on a dead socket).
        def closed() -> None:
            raise ConnectionResetError(f"{connection} was closed by the other end")

        conn.handle_eof = conn.handle_disconnect = closed
    if signing_key is not None:
        conn.setup_signing(
            signing_key,
            sign_outgoing=True,
            allow_unsigned_callback=None,
            initial_timestamp=max(signing_timestamp_now(), signing_timestamp + 1),
        )
    return conn


def drain(conn: Any, timeout_s: float, limit: int = 256) -> list[Any]:
    """Messages that arrive on `conn` within `timeout_s` (those already queued at once).

    BAD_DATA messages (garbage, bad CRC, refused signatures) are returned too, for counting.
    A stream connection closed by the other end raises ConnectionResetError.
    """
    messages: list[Any] = []
    if timeout_s > 0:
        conn.select(timeout_s)
    while len(messages) < limit:
        message = conn.recv_msg()
        if message is None:
            break
        messages.append(message)
    return messages
