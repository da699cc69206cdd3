"""Wire messages and topic names shared by the controller, the bridge, the sim-car and recordings.

Everything on zenoh is a ROS 2 message in CDR, exactly as ROS 2 (and `zenoh-bridge-ros2dds`)
puts it on the wire, 4-byte encapsulation header included, so a ROS 2 system can feed and read
us through the bridge. Keys follow that bridge: the ROS topic name without its leading slash,
with an optional namespace prefix (`/scan` -> `scan`, or `car1/scan`).

The functions here turn payloads into small typed values of ours and back. Decoding never
returns a half-read message: a payload that does not parse raises `WireError`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
from numpy.typing import NDArray


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


def _header(stamp_s: float, frame_id: str) -> Any:
    types = _typestore().types
    sec = math.floor(stamp_s)
    nanosec = min(round((stamp_s - sec) * 1e9), 999_999_999)
    return types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
    )


def _stamp_s(header: Any) -> float:
    return float(header.stamp.sec) + float(header.stamp.nanosec) * 1e-9


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


def encode_scan_msg(scan: Scan) -> bytes:
    """CDR of a LaserScan."""
    count = len(scan.ranges_m)
    message = _typestore().types[SCAN.ros_type](
        header=_header(scan.stamp_s, scan.frame_id),
        angle_min=scan.angle_min_rad,
        angle_max=scan.angle_min_rad + scan.angle_increment_rad * max(count - 1, 0),
        angle_increment=scan.angle_increment_rad,
        time_increment=0.0,
        scan_time=0.0,
        range_min=scan.range_min_m,
        range_max=scan.range_max_m,
        ranges=np.asarray(scan.ranges_m, dtype=np.float32),
        intensities=np.zeros(0, dtype=np.float32),
    )
    return serialize(message, SCAN.ros_type)


def decode_scan_msg(payload: bytes) -> Scan:
    """A LaserScan; `WireError` if malformed, empty or with a zero or non-finite increment."""
    message = deserialize(payload, SCAN.ros_type)
    ranges = np.asarray(message.ranges, dtype=np.float32)
    increment = float(message.angle_increment)
    if ranges.size == 0:
        raise WireError("LaserScan has no ranges")
    if not math.isfinite(increment) or increment == 0.0 or not math.isfinite(message.angle_min):
        raise WireError(f"LaserScan has an unusable angle_increment {increment}")
    return Scan(
        stamp_s=_stamp_s(message.header),
        frame_id=str(message.header.frame_id),
        angle_min_rad=float(message.angle_min),
        angle_increment_rad=increment,
        range_min_m=float(message.range_min),
        range_max_m=float(message.range_max),
        ranges_m=ranges,
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


def decode_pose_msg(payload: bytes) -> Pose2D:
    """A PoseStamped as a planar pose; `WireError` if malformed or not finite."""
    message = deserialize(payload, POSE.ros_type)
    p, q = message.pose.position, message.pose.orientation
    values = (p.x, p.y, q.x, q.y, q.z, q.w)
    if not all(math.isfinite(v) for v in values):
        raise WireError("PoseStamped has NaN or infinite values")
    norm = math.sqrt(q.x**2 + q.y**2 + q.z**2 + q.w**2)
    if norm < 1e-6:
        raise WireError("PoseStamped has a zero quaternion")
    yaw = math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y**2 + q.z**2))
    return Pose2D(_stamp_s(message.header), str(message.header.frame_id), p.x, p.y, yaw)


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


def encode_twist_msg(twist: Twist2D) -> bytes:
    """CDR of a Twist with only linear.x and angular.z set."""
    types = _typestore().types
    vector = types["geometry_msgs/msg/Vector3"]
    message = types[COMMAND.ros_type](
        linear=vector(x=twist.linear_mps, y=0.0, z=0.0),
        angular=vector(x=0.0, y=0.0, z=twist.angular_radps),
    )
    return serialize(message, COMMAND.ros_type)


def decode_twist_msg(payload: bytes) -> Twist2D:
    """A Twist as a planar command; `WireError` if malformed or not finite."""
    message = deserialize(payload, COMMAND.ros_type)
    linear, angular = float(message.linear.x), float(message.angular.z)
    if not (math.isfinite(linear) and math.isfinite(angular)):
        raise WireError("Twist has NaN or infinite values")
    return Twist2D(linear, angular)


def encode_bool_msg(value: bool) -> bytes:
    """CDR of a std_msgs/Bool."""
    return serialize(_typestore().types[ESTOP.ros_type](data=value), ESTOP.ros_type)


def decode_bool_msg(payload: bytes) -> bool:
    """A std_msgs/Bool; `WireError` if malformed."""
    return bool(deserialize(payload, ESTOP.ros_type).data)


def encode_json_msg(value: dict[str, Any]) -> bytes:
    """A std_msgs/String carrying one JSON object (status and state messages)."""
    text = json.dumps(value, separators=(",", ":"), allow_nan=False)
    return serialize(_typestore().types["std_msgs/msg/String"](data=text), "std_msgs/msg/String")


def decode_json_msg(payload: bytes) -> dict[str, Any]:
    """The JSON object inside a std_msgs/String; `WireError` if either is malformed."""
    text = deserialize(payload, "std_msgs/msg/String").data
    try:
        value = json.loads(text)
    except json.JSONDecodeError as error:
        raise WireError(f"String payload is not JSON: {error}") from None
    if not isinstance(value, dict):
        raise WireError("String payload is not a JSON object")
    return value
