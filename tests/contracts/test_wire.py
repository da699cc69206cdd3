"""The strict CDR codecs of `contracts.wire` against rosbags, the reference ROS 2 serialiser.

What we write is byte for byte what rosbags writes; a well-formed message (either byte order)
reads as the values rosbags reads; whatever rosbags refuses we refuse too; and beyond that we
refuse what rosbags lets through (option bytes, bytes after the message, bool bytes other than
0 and 1, unterminated or oversized strings, non-unit quaternions, non-finite numbers, loose
JSON), because those payloads can release a stop or move the car.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from qnav.contracts import cdr, wire

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
        time_increment=scan.time_increment_s,
        scan_time=0.0,
        range_min=scan.range_min_m,
        range_max=scan.range_max_m,
        ranges=np.asarray(scan.ranges_m, dtype=np.float32),
        intensities=np.arange(intensities, dtype=np.float32),
    )
    store = wire._typestore()
    return bytes(store.serialize_cdr(message, LASER_SCAN, little_endian=little_endian))


def rosbags_scan(payload: bytes) -> wire.Scan:
    """The scan rosbags reads, with the same checks."""
    message = wire.deserialize(payload, LASER_SCAN)
    ranges = np.asarray(message.ranges, dtype=np.float32)
    increment = float(message.angle_increment)
    if ranges.size == 0:
        raise wire.WireError("LaserScan has no ranges")
    if not math.isfinite(increment) or increment == 0.0 or not math.isfinite(message.angle_min):
        raise wire.WireError(f"LaserScan has an unusable angle_increment {increment}")
    time_increment = float(message.time_increment)
    if not (math.isfinite(time_increment) and time_increment >= 0.0):
        raise wire.WireError(f"LaserScan has an unusable time_increment {time_increment}")
    header = message.header
    return wire.Scan(
        stamp_s=float(header.stamp.sec) + float(header.stamp.nanosec) * 1e-9,
        frame_id=str(header.frame_id),
        angle_min_rad=float(message.angle_min),
        angle_increment_rad=increment,
        range_min_m=float(message.range_min),
        range_max_m=float(message.range_max),
        ranges_m=ranges,
        time_increment_s=time_increment,
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
    """The pose rosbags reads, with the same checks."""
    message = wire.deserialize(payload, POSE_STAMPED)
    p, q = message.pose.position, message.pose.orientation
    if not all(math.isfinite(v) for v in (p.x, p.y, p.z, q.x, q.y, q.z, q.w)):
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
        turn_s = 0.1 if i % 3 else 0.0  # a rotating lidar's 10 Hz turn, or all at the stamp
        result.append(
            wire.Scan(stamp, frame, angle_min, increment, 0.1, 30.0, ranges, turn_s / count)
        )
    return result


def same(decode: Callable[[bytes], Any], reference: Callable[[bytes], Any], payload: bytes) -> None:
    """Both decode `payload` to the same values, or both refuse it."""
    ours, theirs = outcome(decode, payload), outcome(reference, payload)
    assert ours[0] == theirs[0], (payload.hex(), ours, theirs)
    if ours[0] == "ok":
        assert ours == theirs


def refused_if_rosbags_refuses(
    decode: Callable[[bytes], Any], reference: Callable[[bytes], Any], payload: bytes
) -> None:
    """Stricter, never looser: what rosbags refuses we refuse; what we take rosbags reads
    to the same values."""
    ours, theirs = outcome(decode, payload), outcome(reference, payload)
    if theirs[0] == "error":
        assert ours[0] == "error", (payload.hex(), ours)
    if ours[0] == "ok":
        assert ours == theirs, payload.hex()


@pytest.mark.parametrize("scan", scans(), ids=lambda s: f"{len(s.ranges_m)}-{s.frame_id!r}")
def test_the_scan_encoding_is_byte_for_byte_rosbags(scan: wire.Scan) -> None:
    assert wire.encode_scan_msg(scan) == rosbags_scan_bytes(scan)


@pytest.mark.parametrize("scan", scans(), ids=lambda s: f"{len(s.ranges_m)}-{s.frame_id!r}")
def test_the_scan_decoder_reads_what_rosbags_reads_in_either_byte_order(scan: wire.Scan) -> None:
    payloads = [
        rosbags_scan_bytes(scan),
        rosbags_scan_bytes(scan, intensities=5),
        rosbags_scan_bytes(scan, little_endian=False),
        rosbags_scan_bytes(scan, intensities=3, little_endian=False),
    ]
    for payload in payloads:
        same(wire.decode_scan_msg, rosbags_scan, payload)
        assert outcome(wire.decode_scan_msg, payload)[0] == "ok"
    direct = wire.decode_scan_msg(payloads[0])
    np.testing.assert_array_equal(direct.ranges_m, scan.ranges_m)
    assert direct.frame_id == scan.frame_id
    swapped = wire.decode_scan_msg(payloads[2])
    assert swapped.ranges_m.dtype == np.float32
    np.testing.assert_array_equal(swapped.ranges_m, scan.ranges_m)


def test_the_scan_decoder_refuses_whatever_rosbags_refuses_and_more() -> None:
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
    for time_increment in (-1e-4, math.nan, math.inf):  # a time that runs back, or none
        timed = wire.Scan(5.5, "laser", -1.0, 0.25, 0.1, 30.0, np.ones(3, np.float32), 0.0)
        timed = dataclasses.replace(timed, time_increment_s=time_increment)
        broken.append(rosbags_scan_bytes(timed))
        assert outcome(wire.decode_scan_msg, broken[-1])[0] == "error"
    for candidate in broken:
        refused_if_rosbags_refuses(wire.decode_scan_msg, rosbags_scan, candidate)
    # Rosbags reads these; they are not one well-formed LaserScan.
    stricter = [
        payload + bytes(1),  # the body already ends on 4 bytes: nothing may follow
        payload + bytes(3),
        payload[:2] + b"\x01\x00" + payload[4:],  # option bytes
        payload[:3] + b"\x02" + payload[4:],  # padding announced, none there
    ]
    for candidate in stricter:
        assert outcome(rosbags_scan, candidate)[0] == "ok"
        assert outcome(wire.decode_scan_msg, candidate)[0] == "error", candidate.hex()
    assert outcome(wire.decode_scan_msg, payload + bytes(4))[0] == "error"


POSES = [
    (12.25, frame, (1.5, -2.0, 0.3), (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)))
    for frame in FRAMES
    for yaw in (0.0, 1.0, -3.0)
] + [
    (1.0, "map", (math.nan, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)),
    (1.0, "map", (0.0, math.inf, 0.0), (0.0, 0.0, 0.0, 1.0)),
    (1.0, "map", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0)),
    (1.0, "map", (0.0, 0.0, math.nan), (0.0, 0.0, 0.0, 1.0)),  # z is not used, but NaN
    (1.0, "map", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 2.0)),  # not a unit quaternion
    (1.0, "map", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.05)),  # within the tolerance
    (1.0, "map", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.85)),  # not
]


@pytest.mark.parametrize("pose", POSES)
def test_the_pose_decoder_reads_and_refuses_what_rosbags_does(pose: Any) -> None:
    stamp, frame, position, orientation = pose
    payload = rosbags_pose_bytes(stamp, frame, position, orientation)
    same(wire.decode_pose_msg, rosbags_pose, payload)
    same(
        wire.decode_pose_msg,
        rosbags_pose,
        rosbags_pose_bytes(stamp, frame, position, orientation, little_endian=False),
    )
    for candidate in [payload + bytes(3), payload + bytes(4)]:  # the body ends on 8 bytes
        assert outcome(wire.decode_pose_msg, candidate)[0] == "error"
    for candidate in (payload[:cut] for cut in range(0, len(payload), 3)):
        assert outcome(wire.decode_pose_msg, candidate)[0] == "error"


def test_the_pose_point_bool_twist_and_string_encodings_are_byte_for_byte_rosbags() -> None:
    store, types = wire._typestore(), _types()
    for linear, angular in [(0.0, 0.0), (0.5, -0.5), (-1.25, 3.0e-7)]:
        vector = types["geometry_msgs/msg/Vector3"]
        message = types["geometry_msgs/msg/Twist"](
            linear=vector(x=linear, y=0.0, z=0.0), angular=vector(x=0.0, y=0.0, z=angular)
        )
        expected = bytes(store.serialize_cdr(message, "geometry_msgs/msg/Twist"))
        assert wire.encode_twist_msg(wire.Twist2D(linear, angular)) == expected
        assert wire.decode_twist_msg(expected) == wire.Twist2D(linear, angular)
    values: list[dict[str, Any]] = [{}, {"a": 1}, {"reason": "policy", "q": [0.1, -2.5], "x": None}]
    for value in values:
        text = json.dumps(value, separators=(",", ":"), allow_nan=False)
        string = types["std_msgs/msg/String"](data=text)
        assert wire.encode_json_msg(value) == bytes(
            store.serialize_cdr(string, "std_msgs/msg/String")
        )
        assert wire.decode_json_msg(wire.encode_json_msg(value)) == value
    for flag in (False, True):
        message = types["std_msgs/msg/Bool"](data=flag)
        assert wire.encode_bool_msg(flag) == bytes(
            store.serialize_cdr(message, "std_msgs/msg/Bool")
        )
    for frame in FRAMES:
        for yaw in (0.0, 1.0, -3.0):
            pose = wire.Pose2D(12.25, frame, 1.5, -2.0, yaw)
            orientation = (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
            assert wire.encode_pose_msg(pose) == rosbags_pose_bytes(
                12.25, frame, (1.5, -2.0, 0.0), orientation
            )
        point = types["geometry_msgs/msg/PointStamped"](
            header=_header(3.5, frame), point=types["geometry_msgs/msg/Point"](x=4.0, y=-1.0, z=0.0)
        )
        expected = bytes(store.serialize_cdr(point, "geometry_msgs/msg/PointStamped"))
        assert wire.encode_point_msg(wire.Pose2D(3.5, frame, 4.0, -1.0)) == expected
        assert wire.decode_point_msg(expected) == wire.Pose2D(3.5, frame, 4.0, -1.0)


BOOLS = {
    # The canonical forms: rosbags' (no padding), padded to 4 bytes with the options saying
    # so (Cyclone DDS), padded with zero options, and big-endian.
    "0001000001": True,
    "0001000000": False,
    "0001000301000000": True,
    "0001000300000000": False,
    "0001000001000000": True,
    "0000000001": True,
    "0000000300000000": False,
}
MALFORMED_BOOLS = [
    # issue 18: each of these released the stop.
    "0001000002",
    "00010000ff",
    "0001000080000000",
    "0001000001deadbe",
    "0001ffff01",
    # and their kind
    "",
    "0001",
    "00010000",
    "0001000001000000000000",  # more than padding
    "00010000010000",  # padding that does not end on 4 bytes
    "0001000201000000",  # options announce 2 padding bytes, 3 follow
    "0001000301",  # options announce padding, none follows
    "0001010001",  # first option byte
    "0002000001",  # PL_CDR_BE
    "0003000001",  # PL_CDR_LE
    "0100000001",
    "0001000101000000",
    "00010000010100",
]


def test_only_a_canonical_bool_decodes() -> None:
    for payload, value in BOOLS.items():
        assert wire.decode_bool_msg(bytes.fromhex(payload)) is value, payload
    for payload in MALFORMED_BOOLS:
        with pytest.raises(wire.WireError):
            wire.decode_bool_msg(bytes.fromhex(payload))
    for byte in range(2, 256):
        with pytest.raises(wire.WireError, match="neither 0 nor 1"):
            wire.decode_bool_msg(bytes([0, 1, 0, 0, byte]))


def test_strings_must_be_terminated_utf8_without_nul_and_bounded() -> None:
    def with_frame(raw: bytes, length: int | None = None) -> bytes:
        """A PoseStamped whose frame_id is these raw bytes behind this length prefix."""
        writer = cdr.Writer()
        writer.pack(cdr.TIME, 4, 1, 0)
        writer.pack(cdr.Layout("I"), 4, len(raw) if length is None else length)
        writer.out += raw
        writer.pack(cdr.Layout("7d"), 8, 1.0, 2.0, 0.0, 0.0, 0.0, 0.0, 1.0)
        return writer.payload()

    assert wire.decode_pose_msg(with_frame(b"map\x00")).frame_id == "map"
    for raw, why in [
        (b"map_", "NUL-terminated"),
        (b"m\x00p\x00", "NUL before"),
        (b"\xff\xfe\x00", "UTF-8"),
        (b"", "length 0"),
    ]:
        with pytest.raises(wire.WireError, match=why):
            wire.decode_pose_msg(with_frame(raw))
    long_frame = b"f" * wire.MAX_FRAME_ID_BYTES + b"\x00"
    with pytest.raises(wire.WireError, match="length"):
        wire.decode_pose_msg(with_frame(long_frame))
    with pytest.raises(wire.WireError, match="length"):
        wire.decode_pose_msg(with_frame(b"map\x00", length=0xFFFFFFFF))
    text = json.dumps({"x": "a" * wire.MAX_JSON_BYTES})
    writer = cdr.Writer()
    writer.string(text)
    with pytest.raises(wire.WireError, match="length"):
        wire.decode_json_msg(writer.payload())


def test_a_header_stamp_with_a_second_or_more_of_nanoseconds_is_malformed() -> None:
    payload = bytearray(wire.encode_pose_msg(wire.Pose2D(1.0, "map", 1.0, 2.0)))
    payload[8:12] = (1_000_000_000).to_bytes(4, "little")
    with pytest.raises(wire.WireError, match="nanosec"):
        wire.decode_pose_msg(bytes(payload))


def test_a_twist_with_any_non_finite_number_is_malformed() -> None:
    for index in range(6):
        for bad in (math.nan, math.inf, -math.inf):
            values = [0.0] * 6
            values[index] = bad
            writer = cdr.Writer()
            writer.pack(cdr.Layout("6d"), 8, *values)
            with pytest.raises(wire.WireError, match="NaN or infinite"):
                wire.decode_twist_msg(writer.payload())
    assert wire.decode_twist_msg(wire.encode_twist_msg(wire.Twist2D(0.5, -0.25))) == wire.Twist2D(
        0.5, -0.25
    )


def test_a_point_with_a_non_finite_number_is_malformed() -> None:
    for x, y in [(math.nan, 0.0), (0.0, math.inf)]:
        with pytest.raises(wire.WireError):
            wire.decode_point_msg(wire.encode_point_msg(wire.Pose2D(0.0, "map", x, y)))


def test_a_position_beyond_the_bound_is_malformed() -> None:
    wire.check_position("pose", wire.Pose2D(0.0, "map", 600.0, -800.0), 1000.0)  # 1000 m away
    for x, y in [(1000.5, 0.0), (710.0, -710.0), (0.0, -1e308), (math.nan, 0.0)]:
        with pytest.raises(wire.WireError):
            wire.check_position("pose", wire.Pose2D(0.0, "map", x, y), 1000.0)


@pytest.mark.parametrize(
    "text",
    [
        '{"arm": NaN}',
        '{"x": Infinity}',
        '{"x": -Infinity}',
        '{"arm": true, "arm": false}',
        '{"a": {"b": 1, "b": 2}}',
        "[1]",
        '"arm"',
        "{",
        "[" * 100_000 + "]" * 100_000,
    ],
)
def test_loose_json_is_malformed(text: str) -> None:
    writer = cdr.Writer()
    writer.string(text)
    with pytest.raises(wire.WireError):
        wire.decode_json_msg(writer.payload())
