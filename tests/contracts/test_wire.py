"""The direct CDR codecs of `contracts.wire` against rosbags, the reference they replace.

The hot-path messages (LaserScan and PoseStamped in, Twist and String out) skip rosbags'
generic serialiser. Whatever the payload, the direct path must give what rosbags gives: the
same bytes out, the same values in, and the same error for a payload that does not parse.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from contracts import cdr, wire

LASER_SCAN = "sensor_msgs/msg/LaserScan"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
FRAMES = ["", "a", "ab", "abc", "laser", "base_link", "map_frame_é"]
"""Frame ids of 0 to 12 bytes: every padding before the fields that follow the header."""


def _types() -> Any:
    return wire._typestore().types


def _header(stamp_s: float, frame_id: str) -> Any:
    sec = math.floor(stamp_s)
    nanosec = min(round((stamp_s - sec) * 1e9), 999_999_999)
    return _types()["std_msgs/msg/Header"](
        stamp=_types()["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
    )


def rosbags_scan_bytes(
    scan: wire.Scan, *, intensities: int = 0, little_endian: bool = True
) -> bytes:
    count = len(scan.ranges_m)
    message = _types()[LASER_SCAN](
        header=_header(scan.stamp_s, scan.frame_id),
        angle_min=scan.angle_min_rad,
        angle_max=scan.angle_min_rad + scan.angle_increment_rad * max(count - 1, 0),
        angle_increment=scan.angle_increment_rad,
        time_increment=0.0,
        scan_time=0.0,
        range_min=scan.range_min_m,
        range_max=scan.range_max_m,
        ranges=np.asarray(scan.ranges_m, dtype=np.float32),
        intensities=np.arange(intensities, dtype=np.float32),
    )
    store = wire._typestore()
    return bytes(store.serialize_cdr(message, LASER_SCAN, little_endian=little_endian))


def rosbags_scan(payload: bytes) -> wire.Scan:
    """The scan decoder before the direct path: rosbags, then the same checks."""
    message = wire.deserialize(payload, LASER_SCAN)
    ranges = np.asarray(message.ranges, dtype=np.float32)
    increment = float(message.angle_increment)
    if ranges.size == 0:
        raise wire.WireError("LaserScan has no ranges")
    if not math.isfinite(increment) or increment == 0.0 or not math.isfinite(message.angle_min):
        raise wire.WireError(f"LaserScan has an unusable angle_increment {increment}")
    header = message.header
    return wire.Scan(
        stamp_s=float(header.stamp.sec) + float(header.stamp.nanosec) * 1e-9,
        frame_id=str(header.frame_id),
        angle_min_rad=float(message.angle_min),
        angle_increment_rad=increment,
        range_min_m=float(message.range_min),
        range_max_m=float(message.range_max),
        ranges_m=ranges,
    )


def rosbags_pose_bytes(
    stamp_s: float,
    frame_id: str,
    position: tuple[float, float, float],
    orientation: tuple[float, float, float, float],
    *,
    little_endian: bool = True,
) -> bytes:
    types = _types()
    message = types[POSE_STAMPED](
        header=_header(stamp_s, frame_id),
        pose=types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](*position),
            orientation=types["geometry_msgs/msg/Quaternion"](*orientation),
        ),
    )
    store = wire._typestore()
    return bytes(store.serialize_cdr(message, POSE_STAMPED, little_endian=little_endian))


def rosbags_pose(payload: bytes) -> wire.Pose2D:
    """The pose decoder before the direct path."""
    message = wire.deserialize(payload, POSE_STAMPED)
    p, q = message.pose.position, message.pose.orientation
    if not all(math.isfinite(v) for v in (p.x, p.y, q.x, q.y, q.z, q.w)):
        raise wire.WireError("PoseStamped has NaN or infinite values")
    norm = math.sqrt(q.x**2 + q.y**2 + q.z**2 + q.w**2)
    if abs(norm - 1.0) > wire.QUATERNION_NORM_TOLERANCE:
        raise wire.WireError(f"PoseStamped's quaternion has norm {norm:.6g}, not 1")
    yaw = math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y**2 + q.z**2))
    header = message.header
    stamp_s = float(header.stamp.sec) + float(header.stamp.nanosec) * 1e-9
    return wire.Pose2D(stamp_s, str(header.frame_id), p.x, p.y, yaw)


def outcome(decode: Callable[[bytes], Any], payload: bytes) -> tuple[str, Any]:
    """("ok", the value's fields, exactly) or ("error", the message) of one decode."""
    try:
        value = decode(payload)
    except wire.WireError as error:
        return "error", str(error)
    return "ok", {name: _exact(field) for name, field in vars(value).items()}


def _exact(field: Any) -> Any:
    if isinstance(field, np.ndarray):
        assert field.dtype == np.float32
        return field.tobytes(), field.shape
    if isinstance(field, float):
        return field.hex()  # exact, and NaN equals NaN
    return field


def scans() -> list[wire.Scan]:
    """Scans of odd and even lengths, every frame-id padding, NaN and infinite readings."""
    rng = np.random.default_rng(7)
    result = []
    for i, count in enumerate([1, 2, 3, 7, 360, 719, 720, 1081]):
        ranges = rng.uniform(0.0, 40.0, count).astype(np.float32)
        ranges[rng.random(count) < 0.1] = np.nan
        ranges[rng.random(count) < 0.1] = np.inf
        ranges[rng.random(count) < 0.05] = -np.inf
        frame = FRAMES[i % len(FRAMES)]
        angle_min, increment = (-math.pi, 2 * math.pi / count) if i % 2 else (0.3, -0.01)
        stamp = 1e6 + i * 0.123456789
        result.append(wire.Scan(stamp, frame, angle_min, increment, 0.1, 30.0, ranges))
    return result


@pytest.mark.parametrize("scan", scans(), ids=lambda s: f"{len(s.ranges_m)}-{s.frame_id!r}")
def test_the_direct_scan_encoding_is_byte_for_byte_rosbags(scan: wire.Scan) -> None:
    assert wire.encode_scan_msg(scan) == rosbags_scan_bytes(scan)


@pytest.mark.parametrize("scan", scans(), ids=lambda s: f"{len(s.ranges_m)}-{s.frame_id!r}")
def test_the_direct_scan_decoder_reads_what_rosbags_reads(scan: wire.Scan) -> None:
    payloads = [
        rosbags_scan_bytes(scan),
        rosbags_scan_bytes(scan, intensities=5),
        rosbags_scan_bytes(scan, little_endian=False),  # not direct: rosbags reads it
        *(rosbags_scan_bytes(scan) + bytes(n) for n in (1, 3, 4, 9)),  # padding; too much
    ]
    for payload in payloads:
        assert outcome(wire.decode_scan_msg, payload) == outcome(rosbags_scan, payload)
    for payload in payloads[:2]:  # these take the direct path, not rosbags'
        wire._read_scan(cdr.Reader(payload))
    direct = wire.decode_scan_msg(payloads[0])
    np.testing.assert_array_equal(direct.ranges_m, scan.ranges_m)
    assert direct.frame_id == scan.frame_id


def test_the_direct_scan_decoder_refuses_whatever_rosbags_refuses() -> None:
    scan = wire.Scan(5.5, "laser", -1.0, 0.25, 0.1, 30.0, np.arange(1, 8, dtype=np.float32))
    payload = rosbags_scan_bytes(scan, intensities=2)
    broken = [payload[:cut] for cut in range(len(payload))]  # cut anywhere
    rng = np.random.default_rng(3)
    for _ in range(3000):  # random bytes changed (lengths, terminators, header, floats)
        mutated = bytearray(payload)
        for position in rng.integers(0, len(payload), rng.integers(1, 4)):
            mutated[position] = int(rng.integers(0, 256))
        broken.append(bytes(mutated))
    broken += [b"", b"\x00\x01", b"\x00\x02\x00\x00" + payload[4:], b"\xff" * 40]
    empty = wire.Scan(5.5, "laser", -1.0, 0.25, 0.1, 30.0, np.zeros(0, dtype=np.float32))
    zero = wire.Scan(5.5, "laser", -1.0, 0.0, 0.1, 30.0, np.ones(3, dtype=np.float32))
    broken += [rosbags_scan_bytes(empty), rosbags_scan_bytes(zero)]
    for payload in broken:
        assert outcome(wire.decode_scan_msg, payload) == outcome(rosbags_scan, payload)


POSES = [
    (12.25, frame, (1.5, -2.0, 0.3), (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)))
    for frame in FRAMES
    for yaw in (0.0, 1.0, -3.0)
] + [
    (1.0, "map", (math.nan, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)),
    (1.0, "map", (0.0, math.inf, 0.0), (0.0, 0.0, 0.0, 1.0)),
    (1.0, "map", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0)),
    (1.0, "map", (0.0, 0.0, math.nan), (0.1, 0.2, 0.3, 0.9)),  # z is not read
]


@pytest.mark.parametrize("pose", POSES)
def test_the_direct_pose_decoder_reads_and_refuses_what_rosbags_does(pose: Any) -> None:
    stamp, frame, position, orientation = pose
    payload = rosbags_pose_bytes(stamp, frame, position, orientation)
    payloads = [
        payload,
        rosbags_pose_bytes(stamp, frame, position, orientation, little_endian=False),
        payload + bytes(3),
        payload + bytes(4),
        *(payload[:cut] for cut in range(0, len(payload), 3)),
    ]
    for candidate in payloads:
        assert outcome(wire.decode_pose_msg, candidate) == outcome(rosbags_pose, candidate)


def test_the_direct_twist_and_status_encodings_are_byte_for_byte_rosbags() -> None:
    store, types = wire._typestore(), _types()
    for linear, angular in [(0.0, 0.0), (0.5, -0.5), (-1.25, 3.0e-7)]:
        vector = types["geometry_msgs/msg/Vector3"]
        message = types["geometry_msgs/msg/Twist"](
            linear=vector(x=linear, y=0.0, z=0.0), angular=vector(x=0.0, y=0.0, z=angular)
        )
        expected = bytes(store.serialize_cdr(message, "geometry_msgs/msg/Twist"))
        assert wire.encode_twist_msg(wire.Twist2D(linear, angular)) == expected
    values: list[dict[str, Any]] = [{}, {"a": 1}, {"reason": "policy", "q": [0.1, -2.5], "x": None}]
    for value in values:
        text = json.dumps(value, separators=(",", ":"), allow_nan=False)
        string = types["std_msgs/msg/String"](data=text)
        assert wire.encode_json_msg(value) == bytes(
            store.serialize_cdr(string, "std_msgs/msg/String")
        )
        assert wire.decode_json_msg(wire.encode_json_msg(value)) == value
