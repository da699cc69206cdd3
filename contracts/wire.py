"""Wire messages and topic names shared by the controller, the bridge, the sim-car and recordings.

Everything on zenoh is a ROS 2 message in CDR, exactly as ROS 2 (and `zenoh-bridge-ros2dds`)
puts it on the wire, 4-byte encapsulation header included, so a ROS 2 system can feed and read
us through the bridge. Keys follow that bridge: the ROS topic name without its leading slash,
with an optional namespace prefix (`/scan` -> `scan`, or `car1/scan`).

The functions here turn payloads into small typed values of ours and back. Every decoder reads
with `contracts.cdr`'s strict reader (its docstring has the rules) and nothing else: a payload
that is not exactly one well-formed message of the type, with finite numbers, raises
`WireError`; there is no fallback to a more lenient decoder. rosbags is the reference the tests
check the bytes and values against, and still builds the messages nobody reads on a hot path.
JSON strings are parsed strictly too (`decode_json_msg`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from qnav.contracts import cdr

WireError = cdr.WireError
"""A payload is not a well-formed message (raised by the reader; imported from here)."""

MAX_FRAME_ID_BYTES = 256
"""Longest header frame_id taken (NUL included); a longer one is malformed."""

MAX_JSON_BYTES = 65_536
"""Longest JSON string message taken (NUL included); a longer one is malformed."""

QUATERNION_NORM_TOLERANCE = 0.1
"""How far from 1 a pose's orientation quaternion's norm may be (drivers round; a zero or
garbled quaternion is far off)."""


@dataclass(frozen=True)
class Topic:
    """One topic: its ROS name (without namespace) and message type."""

    name: str
    """ROS topic name without the leading slash."""
    ros_type: str
    """ROS 2 message type, e.g. sensor_msgs/msg/LaserScan."""


SCAN = Topic("scan", "sensor_msgs/msg/LaserScan")
POSE = Topic("pose", "geometry_msgs/msg/PoseStamped")
TARGET_POSE = Topic("goal_pose", "geometry_msgs/msg/PoseStamped")
TARGET_POINT = Topic("goal_point", "geometry_msgs/msg/PointStamped")
ESTOP = Topic("estop", "std_msgs/msg/Bool")
ESTOP_RELEASE = Topic("qnav/estop_release", "std_msgs/msg/Bool")
"""A Bool true here asks the controller to release its latched emergency stop."""
COMMAND = Topic("cmd_vel", "geometry_msgs/msg/Twist")
CONTROLLER_STATUS = Topic("qnav/controller_status", "std_msgs/msg/String")
VEHICLE_STATE = Topic("qnav/vehicle_state", "std_msgs/msg/String")
VEHICLE_REQUEST = Topic("qnav/vehicle_request", "std_msgs/msg/String")
POLICY_ANNOUNCEMENT = Topic("qnav/policy_announcement", "std_msgs/msg/String")
"""The policy `qnav serve` recommends (JSON, `contracts.delivery.Announcement`)."""

TOPICS = (
    SCAN,
    POSE,
    TARGET_POSE,
    TARGET_POINT,
    ESTOP,
    ESTOP_RELEASE,
    COMMAND,
    CONTROLLER_STATUS,
    VEHICLE_STATE,
    VEHICLE_REQUEST,
    POLICY_ANNOUNCEMENT,
)
"""Every topic of the project (what `qnav record` subscribes to)."""

PUBLISHERS: dict[str, tuple[Topic, ...]] = {
    "controller": (COMMAND, CONTROLLER_STATUS, ESTOP),
    "bridge": (VEHICLE_STATE, ESTOP),
    "sensors": (SCAN, POSE, ESTOP),
    "operator": (TARGET_POSE, TARGET_POINT, ESTOP, ESTOP_RELEASE, VEHICLE_REQUEST),
    "recorder": (),
    "server": (POLICY_ANNOUNCEMENT,),
}
"""Who may publish what, by certificate identity (config/zenoh-secure.json5's access control):
only the controller commands the car, only the bridge reports the vehicle, only the operator
sets targets, releases the stop or asks to arm, only the policy server (`qnav serve`) announces
policies; anyone known may press the stop."""


def key(topic: Topic | str, namespace: str = "") -> str:
    """The zenoh key of a topic: `name`, or `namespace/name` (slashes trimmed)."""
    name = topic.name if isinstance(topic, Topic) else topic.strip("/")
    prefix = namespace.strip("/")
    return f"{prefix}/{name}" if prefix else name


@cache
def _typestore() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def serialize(message: Any, ros_type: str) -> bytes:
    """CDR bytes of a rosbags message object (the reference the tests check ours against)."""
    return bytes(_typestore().serialize_cdr(message, ros_type))


def deserialize(payload: bytes, ros_type: str) -> Any:
    """A rosbags message object from CDR bytes; `WireError` if they do not parse. Lenient (it
    ignores the options bytes and what follows the message): never used to take an input."""
    try:
        return _typestore().deserialize_cdr(bytes(payload), ros_type)
    except Exception as error:  # rosbags raises several types for truncated or odd input
        raise WireError(f"not a {ros_type}: {error}") from None


def _time(stamp_s: float) -> tuple[int, int]:
    sec = math.floor(stamp_s)
    return sec, min(round((stamp_s - sec) * 1e9), 999_999_999)


def _seconds(sec: int, nanosec: int) -> float:
    return float(sec) + float(nanosec) * 1e-9


def _read_header(reader: cdr.Reader) -> tuple[float, str]:
    """std_msgs/msg/Header: (stamp in seconds, frame_id)."""
    sec, nanosec = reader.unpack(cdr.TIME, 4)
    if nanosec > 999_999_999:
        raise WireError(f"header stamp has nanosec {nanosec} (at most 999999999)")
    return _seconds(sec, nanosec), reader.string(MAX_FRAME_ID_BYTES)


def _write_header(writer: cdr.Writer, stamp_s: float, frame_id: str) -> None:
    writer.pack(cdr.TIME, 4, *_time(stamp_s))
    writer.string(frame_id)


def _finite(what: str, *values: float) -> None:
    if not all(math.isfinite(v) for v in values):
        raise WireError(f"{what} has NaN or infinite values")


@dataclass(frozen=True)
class Scan:
    """A planar lidar scan (sensor_msgs/msg/LaserScan), ranges in metres."""

    stamp_s: float
    """Acquisition time (header stamp), seconds."""
    frame_id: str
    """Frame of the lidar."""
    angle_min_rad: float
    """Angle of the first range, counter-clockwise from the lidar's x axis."""
    angle_increment_rad: float
    """Angle between consecutive ranges (negative for a clockwise scan)."""
    range_min_m: float
    """Readings below this are invalid."""
    range_max_m: float
    """Readings above this are no return."""
    ranges_m: NDArray[np.float32]
    """The readings."""
    time_increment_s: float = 0.0
    """Time between consecutive readings (a rotating lidar's; 0: all taken at the stamp)."""


_SCAN_FLOATS = cdr.Layout("7f")
"""LaserScan's angle_min, angle_max, angle_increment, time_increment, scan_time, range_min,
range_max."""


def encode_scan_msg(scan: Scan) -> bytes:
    """CDR of a LaserScan (the bytes rosbags writes; angle_max from the count, no intensities)."""
    count = len(scan.ranges_m)
    writer = cdr.Writer()
    _write_header(writer, scan.stamp_s, scan.frame_id)
    angle_max = scan.angle_min_rad + scan.angle_increment_rad * max(count - 1, 0)
    writer.pack(
        _SCAN_FLOATS,
        4,
        scan.angle_min_rad,
        angle_max,
        scan.angle_increment_rad,
        scan.time_increment_s,
        0.0,  # scan_time (the time between scans): not known here
        scan.range_min_m,
        scan.range_max_m,
    )
    writer.float32_sequence(scan.ranges_m)
    writer.float32_sequence(np.zeros(0, dtype=np.float32))  # intensities
    return writer.payload()


def decode_scan_msg(payload: bytes) -> Scan:
    """A LaserScan; `WireError` if malformed, empty, with a zero or non-finite angle increment,
    or with a negative or non-finite time increment.

    The readings may be anything (NaN and infinities have meanings, REP 117); whether the scan
    is plausible for the lidar is the controller's to judge (`[lidar]` settings).
    """
    reader = cdr.Reader(payload)
    stamp_s, frame_id = _read_header(reader)
    angle_min, _, increment, time_increment, _, range_min, range_max = reader.unpack(
        _SCAN_FLOATS, 4
    )
    ranges = reader.float32_sequence()
    reader.float32_sequence()  # intensities: unused, but they must be there
    reader.finish()
    if ranges.size == 0:
        raise WireError("LaserScan has no ranges")
    if not math.isfinite(increment) or increment == 0.0 or not math.isfinite(angle_min):
        raise WireError(f"LaserScan has an unusable angle_increment {increment}")
    if not (math.isfinite(time_increment) and time_increment >= 0.0):
        raise WireError(f"LaserScan has an unusable time_increment {time_increment}")
    return Scan(
        stamp_s, frame_id, angle_min, increment, range_min, range_max, ranges, time_increment
    )


@dataclass(frozen=True)
class Pose2D:
    """A planar pose from a PoseStamped (position and yaw), or a point from a PointStamped."""

    stamp_s: float
    """Header stamp, seconds."""
    frame_id: str
    """Frame the pose is expressed in."""
    x_m: float
    """Position x."""
    y_m: float
    """Position y."""
    yaw_rad: float = 0.0
    """Heading about z, counter-clockwise from x (0 for a point)."""


_POSE_FLOATS = cdr.Layout("7d")
"""geometry_msgs/msg/Pose: position x, y, z and orientation x, y, z, w."""

_POINT_FLOATS = cdr.Layout("3d")
"""geometry_msgs/msg/Point: x, y, z."""


def encode_pose_msg(pose: Pose2D) -> bytes:
    """CDR of a PoseStamped with the yaw as a rotation about z (the bytes rosbags writes)."""
    writer = cdr.Writer()
    _write_header(writer, pose.stamp_s, pose.frame_id)
    half = pose.yaw_rad / 2
    writer.pack(_POSE_FLOATS, 8, pose.x_m, pose.y_m, 0.0, 0.0, 0.0, math.sin(half), math.cos(half))
    return writer.payload()


def decode_pose_msg(payload: bytes) -> Pose2D:
    """A PoseStamped as a planar pose; `WireError` if malformed, not finite, or its quaternion
    is not a unit quaternion (within `QUATERNION_NORM_TOLERANCE`)."""
    reader = cdr.Reader(payload)
    stamp_s, frame_id = _read_header(reader)
    x, y, z, qx, qy, qz, qw = reader.unpack(_POSE_FLOATS, 8)
    reader.finish()
    _finite("PoseStamped", x, y, z, qx, qy, qz, qw)
    norm = math.sqrt(qx**2 + qy**2 + qz**2 + qw**2)
    if not abs(norm - 1.0) <= QUATERNION_NORM_TOLERANCE:
        raise WireError(f"PoseStamped has a quaternion of norm {norm:.6g}, not a unit quaternion")
    yaw = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy**2 + qz**2))
    return Pose2D(stamp_s, frame_id, x, y, yaw)


def encode_point_msg(point: Pose2D) -> bytes:
    """CDR of a PointStamped (the yaw is dropped)."""
    writer = cdr.Writer()
    _write_header(writer, point.stamp_s, point.frame_id)
    writer.pack(_POINT_FLOATS, 8, point.x_m, point.y_m, 0.0)
    return writer.payload()


def decode_point_msg(payload: bytes) -> Pose2D:
    """A PointStamped as a planar point; `WireError` if malformed or not finite."""
    reader = cdr.Reader(payload)
    stamp_s, frame_id = _read_header(reader)
    x, y, z = reader.unpack(_POINT_FLOATS, 8)
    reader.finish()
    _finite("PointStamped", x, y, z)
    return Pose2D(stamp_s, frame_id, x, y)


def check_position(
    what: str, pose: Pose2D, max_position_m: float, setting: str = "max_position_m"
) -> None:
    """`WireError` unless the pose (or point) is finite and within `max_position_m` of the
    frame's origin (a position beyond it is no place the car can be); the error names
    `setting`."""
    _finite(what, pose.x_m, pose.y_m, pose.yaw_rad)
    if math.hypot(pose.x_m, pose.y_m) > max_position_m:
        raise WireError(
            f"{what} at ({pose.x_m:.6g}, {pose.y_m:.6g}) m is beyond {setting} = {max_position_m}"
        )


@dataclass(frozen=True)
class Twist2D:
    """A planar velocity command (geometry_msgs/msg/Twist: linear.x and angular.z)."""

    linear_mps: float
    """Forward speed."""
    angular_radps: float
    """Turn rate, counter-clockwise positive."""


STOP = Twist2D(0.0, 0.0)
"""The command that stops the car."""


_TWIST = cdr.Layout("6d")
"""geometry_msgs/msg/Twist: linear x, y, z and angular x, y, z."""


def encode_twist_msg(twist: Twist2D) -> bytes:
    """CDR of a Twist with only linear.x and angular.z set."""
    writer = cdr.Writer()
    writer.pack(_TWIST, 8, twist.linear_mps, 0.0, 0.0, 0.0, 0.0, twist.angular_radps)
    return writer.payload()


def decode_twist_msg(payload: bytes) -> Twist2D:
    """A Twist as a planar command; `WireError` if malformed or any of its six numbers is not
    finite (the four we do not use included: a NaN anywhere is no command anyone meant)."""
    reader = cdr.Reader(payload)
    values = reader.unpack(_TWIST, 8)
    reader.finish()
    _finite("Twist", *values)
    return Twist2D(values[0], values[5])


def encode_bool_msg(value: bool) -> bytes:
    """CDR of a std_msgs/Bool (the bytes rosbags writes: no padding)."""
    writer = cdr.Writer()
    writer.boolean(value)
    return writer.payload()


def decode_bool_msg(payload: bytes) -> bool:
    """A std_msgs/Bool; `WireError` unless it is exactly one: a value byte of 0 or 1 and
    nothing after it but zero padding (`contracts.cdr`). Releasing a stop hangs on this."""
    reader = cdr.Reader(payload)
    value = reader.boolean()
    reader.finish()
    return value


def encode_json_msg(value: dict[str, Any]) -> bytes:
    """A std_msgs/String carrying one JSON object (status and state messages)."""
    writer = cdr.Writer()
    writer.string(json.dumps(value, separators=(",", ":"), allow_nan=False))
    return writer.payload()


def _no_constant(name: str) -> Any:
    raise WireError(f"JSON holds {name}, which is not JSON")


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    result: dict[str, Any] = {}
    for name, field in pairs:
        if name in result:
            raise WireError(f"JSON object has the key {name!r} twice")
        result[name] = field
    return result


def decode_json_msg(payload: bytes) -> dict[str, Any]:
    """The JSON object inside a std_msgs/String; `WireError` if either is malformed.

    Strict JSON: NaN, Infinity and -Infinity are refused, and so is an object with a key twice
    (which of the two counts differs between parsers); the string is at most `MAX_JSON_BYTES`.
    """
    reader = cdr.Reader(payload)
    text = reader.string(MAX_JSON_BYTES)
    reader.finish()
    try:
        value = json.loads(text, parse_constant=_no_constant, object_pairs_hook=_no_duplicates)
    except json.JSONDecodeError as error:
        raise WireError(f"String payload is not JSON: {error}") from None
    except RecursionError:
        raise WireError("String payload nests JSON too deeply") from None
    if not isinstance(value, dict):
        raise WireError("String payload is not a JSON object")
    return value
