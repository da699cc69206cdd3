"""Wire messages and topic names shared by the controller, the bridge, the sim-car and recordings.

Everything on zenoh is a ROS 2 message in CDR, exactly as ROS 2 (and `zenoh-bridge-ros2dds`)
puts it on the wire, 4-byte encapsulation header included, so a ROS 2 system can feed and read
us through the bridge. Keys follow that bridge: the ROS topic name without its leading slash,
with an optional namespace prefix (`/scan` -> `scan`, or `car1/scan`).

The functions here turn payloads into small typed values of ours and back. Decoding never
returns a half-read message: a payload that does not parse raises `WireError`. rosbags
(de)serialises every message; the ones the controller handles per scan (LaserScan and
PoseStamped in, Twist and the status String out) go through `contracts.cdr` directly, which
gives the same bytes and values in a fraction of the time and leaves anything it does not take
plainly to rosbags.
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from contracts import cdr


class WireError(ValueError):
    """A payload is not a well-formed message of the expected type."""


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
)
"""Every topic of the project (what `qnav record` subscribes to)."""

PUBLISHERS: dict[str, tuple[Topic, ...]] = {
    "controller": (COMMAND, CONTROLLER_STATUS, ESTOP),
    "bridge": (VEHICLE_STATE, ESTOP),
    "sensors": (SCAN, POSE, ESTOP),
    "operator": (TARGET_POSE, TARGET_POINT, ESTOP, ESTOP_RELEASE, VEHICLE_REQUEST),
    "recorder": (),
}
"""Who may publish what, by certificate identity (config/zenoh-secure.json5's access control):
only the controller commands the car, only the bridge reports the vehicle, only the operator
sets targets, releases the stop or asks to arm; anyone known may press the stop."""


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
    """CDR bytes of a rosbags message object."""
    return bytes(_typestore().serialize_cdr(message, ros_type))


def deserialize(payload: bytes, ros_type: str) -> Any:
    """A rosbags message object from CDR bytes; `WireError` if they do not parse."""
    try:
        return _typestore().deserialize_cdr(bytes(payload), ros_type)
    except Exception as error:  # rosbags raises several types for truncated or odd input
        raise WireError(f"not a {ros_type}: {error}") from None


def _time(stamp_s: float) -> tuple[int, int]:
    sec = math.floor(stamp_s)
    return sec, min(round((stamp_s - sec) * 1e9), 999_999_999)


def _header(stamp_s: float, frame_id: str) -> Any:
    types = _typestore().types
    sec, nanosec = _time(stamp_s)
    return types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
    )


def _seconds(sec: int, nanosec: int) -> float:
    return float(sec) + float(nanosec) * 1e-9


def _stamp_s(header: Any) -> float:
    return _seconds(header.stamp.sec, header.stamp.nanosec)


def _read_header(reader: cdr.Reader) -> tuple[float, str]:
    """std_msgs/msg/Header: (stamp in seconds, frame_id)."""
    sec, nanosec = reader.unpack(cdr.TIME, 4)
    return _seconds(sec, nanosec), reader.string()


def _write_header(writer: cdr.Writer, stamp_s: float, frame_id: str) -> None:
    writer.pack(cdr.TIME, 4, *_time(stamp_s))
    writer.string(frame_id)


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


_SCAN_FLOATS = struct.Struct("<7f")
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
        0.0,  # time_increment
        0.0,  # scan_time
        scan.range_min_m,
        scan.range_max_m,
    )
    writer.float32_sequence(scan.ranges_m)
    writer.float32_sequence(np.zeros(0, dtype=np.float32))  # intensities
    return writer.payload()


def decode_scan_msg(payload: bytes) -> Scan:
    """A LaserScan; `WireError` if malformed, empty or with a zero or non-finite increment."""
    try:
        scan = _read_scan(cdr.Reader(payload))
    except cdr.NotDirectError:
        scan = _scan_of(deserialize(payload, SCAN.ros_type))
    if scan.ranges_m.size == 0:
        raise WireError("LaserScan has no ranges")
    increment = scan.angle_increment_rad
    if not math.isfinite(increment) or increment == 0.0 or not math.isfinite(scan.angle_min_rad):
        raise WireError(f"LaserScan has an unusable angle_increment {increment}")
    return scan


def _read_scan(reader: cdr.Reader) -> Scan:
    stamp_s, frame_id = _read_header(reader)
    angle_min, _, increment, _, _, range_min, range_max = reader.unpack(_SCAN_FLOATS, 4)
    ranges = reader.float32_sequence()
    reader.float32_sequence()  # intensities: unused, but they must be there
    reader.finish()
    return Scan(stamp_s, frame_id, angle_min, increment, range_min, range_max, ranges)


def _scan_of(message: Any) -> Scan:
    return Scan(
        stamp_s=_stamp_s(message.header),
        frame_id=str(message.header.frame_id),
        angle_min_rad=float(message.angle_min),
        angle_increment_rad=float(message.angle_increment),
        range_min_m=float(message.range_min),
        range_max_m=float(message.range_max),
        ranges_m=np.asarray(message.ranges, dtype=np.float32),
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


def encode_pose_msg(pose: Pose2D) -> bytes:
    """CDR of a PoseStamped with the yaw as a rotation about z."""
    types = _typestore().types
    message = types[POSE.ros_type](
        header=_header(pose.stamp_s, pose.frame_id),
        pose=types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](x=pose.x_m, y=pose.y_m, z=0.0),
            orientation=types["geometry_msgs/msg/Quaternion"](
                x=0.0, y=0.0, z=math.sin(pose.yaw_rad / 2), w=math.cos(pose.yaw_rad / 2)
            ),
        ),
    )
    return serialize(message, POSE.ros_type)


QUATERNION_NORM_TOLERANCE = 0.1
"""How far from 1 an orientation's norm may be (drivers round; a zero or garbled quaternion is
far off)."""

_POSE_FLOATS = struct.Struct("<7d")
"""geometry_msgs/msg/Pose: position x, y, z and orientation x, y, z, w."""


def decode_pose_msg(payload: bytes) -> Pose2D:
    """A PoseStamped as a planar pose; `WireError` if malformed or not finite."""
    try:
        reader = cdr.Reader(payload)
        stamp_s, frame_id = _read_header(reader)
        x, y, _, qx, qy, qz, qw = reader.unpack(_POSE_FLOATS, 8)
        reader.finish()
    except cdr.NotDirectError:
        message = deserialize(payload, POSE.ros_type)
        p, q = message.pose.position, message.pose.orientation
        stamp_s, frame_id = _stamp_s(message.header), str(message.header.frame_id)
        x, y, qx, qy, qz, qw = p.x, p.y, q.x, q.y, q.z, q.w
    if not all(math.isfinite(v) for v in (x, y, qx, qy, qz, qw)):
        raise WireError("PoseStamped has NaN or infinite values")
    norm = math.sqrt(qx**2 + qy**2 + qz**2 + qw**2)
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise WireError(f"PoseStamped's quaternion has norm {norm:.6g}, not 1")
    yaw = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy**2 + qz**2))
    return Pose2D(stamp_s, frame_id, x, y, yaw)


def encode_point_msg(point: Pose2D) -> bytes:
    """CDR of a PointStamped (the yaw is dropped)."""
    types = _typestore().types
    message = types[TARGET_POINT.ros_type](
        header=_header(point.stamp_s, point.frame_id),
        point=types["geometry_msgs/msg/Point"](x=point.x_m, y=point.y_m, z=0.0),
    )
    return serialize(message, TARGET_POINT.ros_type)


def decode_point_msg(payload: bytes) -> Pose2D:
    """A PointStamped as a planar point; `WireError` if malformed or not finite."""
    message = deserialize(payload, TARGET_POINT.ros_type)
    if not (math.isfinite(message.point.x) and math.isfinite(message.point.y)):
        raise WireError("PointStamped has NaN or infinite values")
    return Pose2D(
        _stamp_s(message.header), str(message.header.frame_id), message.point.x, message.point.y
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


_TWIST = struct.Struct("<6d")
"""geometry_msgs/msg/Twist: linear x, y, z and angular x, y, z."""


def encode_twist_msg(twist: Twist2D) -> bytes:
    """CDR of a Twist with only linear.x and angular.z set."""
    writer = cdr.Writer()
    writer.pack(_TWIST, 8, twist.linear_mps, 0.0, 0.0, 0.0, 0.0, twist.angular_radps)
    return writer.payload()


def decode_twist_msg(payload: bytes) -> Twist2D:
    """A Twist as a planar command; `WireError` if malformed or not finite.

    A Twist moves the car, so it is read strictly (`strict_reader`): little-endian CDR as ROS 2
    writes it, zero options, nothing after the six values but zero padding."""
    with strict_reader(payload, "Twist") as reader:
        linear, _, _, _, _, angular = reader.unpack(_TWIST, 8)
        reader.finish()
    if not (math.isfinite(linear) and math.isfinite(angular)):
        raise WireError("Twist has NaN or infinite values")
    return Twist2D(linear, angular)


@contextmanager
def strict_reader(payload: bytes, what: str) -> Iterator[cdr.Reader]:
    """A strict CDR reader (`contracts.cdr.Reader`) for an input that can move, arm or release
    the car: anything it does not take is a `WireError`, never handed to a lenient decoder."""
    try:
        yield cdr.Reader(payload, strict=True)
    except cdr.NotDirectError:
        raise WireError(
            f"{what} is not canonical little-endian CDR (header 00 01 00 00, exact length)"
        ) from None


def encode_bool_msg(value: bool) -> bytes:
    """CDR of a std_msgs/Bool."""
    return serialize(_typestore().types[ESTOP.ros_type](data=value), ESTOP.ros_type)


_BOOL = struct.Struct("<B")


def decode_bool_msg(payload: bytes) -> bool:
    """A std_msgs/Bool, strictly: the value byte exactly 0 or 1, zero options, nothing after it
    but zero padding; `WireError` otherwise (a stop release must never be read into a byte)."""
    with strict_reader(payload, "Bool") as reader:
        (value,) = reader.unpack(_BOOL, 1)
        reader.finish()
    if value not in (0, 1):
        raise WireError(f"Bool value byte is {value}, not 0 or 1")
    return bool(value == 1)


def encode_json_msg(value: dict[str, Any]) -> bytes:
    """A std_msgs/String carrying one JSON object (status and state messages)."""
    writer = cdr.Writer()
    writer.string(json.dumps(value, separators=(",", ":"), allow_nan=False))
    return writer.payload()


def decode_json_msg(payload: bytes) -> dict[str, Any]:
    """The JSON object inside a std_msgs/String; `WireError` if either is malformed.

    Requests (arm, mode) come this way, so the parse is strict: canonical CDR, no NaN or
    Infinity literals, no repeated keys."""
    with strict_reader(payload, "String") as reader:
        text = reader.string()
        reader.finish()
    try:
        value = json.loads(text, parse_constant=_refuse_constant, object_pairs_hook=_unique_keys)
    except (json.JSONDecodeError, ValueError) as error:
        raise WireError(f"String payload is not strict JSON: {error}") from None
    if not isinstance(value, dict):
        raise WireError("String payload is not a JSON object")
    return value


def _refuse_constant(name: str) -> Any:
    raise ValueError(f"{name} is not JSON")


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    keys = [key for key, _ in pairs]
    if len(set(keys)) != len(keys):
        raise ValueError(f"repeated keys in {keys}")
    return dict(pairs)
