"""Malformed payloads for every message kind the daemons take: the generators behind the
property tests and `make fuzz` (issue 18 parts 2 and 7). Two generators, both seeded:

- `payloads(kind, count, seed)` (the fuzz suite's): random bytes, a valid message cut short, a
  valid message with a few bytes changed, another encapsulation header, garbage after the
  message, an absurd length field, non-finite or absurd values in a well-formed message, a
  message of another type, or (rarely) a 10 MB blob. A few are well-formed by chance;
  `enables_motion` tells the ones that could move, arm or release.
- `malformed(message, rng, count)` (the property tests'): payloads malformed by construction,
  never by chance, each named by how it was broken: truncations of minimal encodings, bytes
  after the message that are not zero padding, wrong encapsulation or option bytes, absurd
  string lengths and sequence counts, non-finite or absurd numbers, non-unit quaternions, scans
  no planar lidar sends, other message types, random bytes behind a broken header, oversized
  messages, loose JSON. A test still checks each one is refused, so a generator that made a
  valid one would fail loudly rather than pass quietly.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Iterator

import numpy as np

from qnav.contracts import cdr, wire

KINDS = ("scan", "pose", "bool", "twist", "json")
"""The message kinds on the daemons' subscribed keys."""

HUGE_BYTES = 10 * 1024 * 1024
"""Size of the rare oversized payload."""


def valid(kind: str, rng: np.random.Generator) -> bytes:
    """A well-formed message of `kind` (neutral where it could move or arm: a false Bool, a zero
    Twist, an empty request)."""
    if kind == "scan":
        count = int(rng.integers(50, 1500))
        ranges = rng.uniform(0.1, 12.0, count).astype(np.float32)
        scan = wire.Scan(1.0, "laser", -math.pi, 2 * math.pi / count, 0.05, 20.0, ranges)
        return wire.encode_scan_msg(scan)
    if kind == "pose":
        x, y = rng.uniform(0, 10, 2)
        return wire.encode_pose_msg(wire.Pose2D(1.0, "map", float(x), float(y), 0.3))
    if kind == "bool":
        return wire.encode_bool_msg(False)
    if kind == "twist":
        return wire.encode_twist_msg(wire.STOP)
    return wire.encode_json_msg({"mode": "HOLD"})


def _absurd_values(kind: str, rng: np.random.Generator) -> bytes:
    bad = float(rng.choice([math.nan, math.inf, -math.inf, 1e308, -9.1e150, 1e30]))
    if kind == "scan":  # float32 fields: the absurd values that fit
        bad = float(rng.choice([math.nan, math.inf, -math.inf, 1e30, -1e30]))
        ranges = np.full(720, 3.0, dtype=np.float32)
        fields = [0.0, 2 * math.pi / 720, 0.05, 20.0]
        fields[int(rng.integers(0, 4))] = bad
        angle_min, increment, range_min, range_max = fields
        return wire.encode_scan_msg(
            wire.Scan(1.0, "laser", angle_min, increment, range_min, range_max, ranges)
        )
    if kind == "pose":
        return wire.encode_pose_msg(wire.Pose2D(1.0, "map", bad, 1.0, 0.0))
    if kind == "twist":
        return wire.encode_twist_msg(wire.Twist2D(bad, float(rng.choice([0.0, bad]))))
    if kind == "bool":
        return b"\x00\x01\x00\x00" + bytes([int(rng.integers(2, 256))])
    text = rng.choice(
        ['{"arm": NaN}', '{"arm": 1}', '{"arm": "true"}', '{"arm": true, "arm": true}']
    )
    writer = cdr.Writer()
    writer.string(str(text))
    return writer.payload()


def _absurd_length(payload: bytes, rng: np.random.Generator) -> bytes:
    """A uint32 length field (the first one after the header, or a random aligned one) set to
    something no message holds."""
    if len(payload) < 12:
        return payload + struct.pack("<I", 0xFFFFFFFF)
    offset = 4 + 4 * int(rng.integers(0, (len(payload) - 8) // 4))
    huge = int(rng.choice([0xFFFFFFFF, 0x7FFFFFFF, 10**9]))
    return payload[:offset] + struct.pack("<I", huge) + payload[offset + 4 :]


MUTATIONS: tuple[Callable[[str, bytes, np.random.Generator], bytes], ...] = (
    lambda kind, p, rng: rng.integers(0, 256, int(rng.integers(0, 300)), dtype=np.uint8).tobytes(),
    lambda kind, p, rng: p[: int(rng.integers(0, max(len(p), 1)))],
    lambda kind, p, rng: _flip(p, rng),
    lambda kind, p, rng: rng.integers(0, 256, 4, dtype=np.uint8).tobytes() + p[4:],
    lambda kind, p, rng: (
        p + rng.integers(1, 256, int(rng.integers(1, 64)), dtype=np.uint8).tobytes()
    ),
    lambda kind, p, rng: _absurd_length(p, rng),
    lambda kind, p, rng: _absurd_values(kind, rng),
    lambda kind, p, rng: valid(str(rng.choice([k for k in KINDS if k != kind])), rng),
)


def _garbage(rng: np.random.Generator) -> bytes:
    return rng.integers(1, 256, int(rng.integers(1, 64)), dtype=np.uint8).tobytes()


def _flip(payload: bytes, rng: np.random.Generator) -> bytes:
    data = bytearray(payload)
    for _ in range(int(rng.integers(1, 5))):
        if data:
            data[int(rng.integers(0, len(data)))] = int(rng.integers(0, 256))
    return bytes(data)


def payloads(kind: str, count: int, seed: int = 0) -> Iterator[bytes]:
    """`count` mutated payloads of `kind` (one in 2000 is a 10 MB blob)."""
    rng = np.random.default_rng([seed, KINDS.index(kind)])
    for i in range(count):
        if i % 2000 == 1999:
            yield bytes(HUGE_BYTES)
            continue
        mutate = MUTATIONS[int(rng.integers(0, len(MUTATIONS)))]
        yield mutate(kind, valid(kind, rng), rng)


def enables_motion(kind: str, payload: bytes) -> bool:
    """Whether the payload is a well-formed message that may move, arm or release: a true Bool,
    a non-zero Twist, a request to arm. Fuzzing skips these (they are not malformed)."""
    try:
        if kind == "bool":
            return wire.decode_bool_msg(payload)
        if kind == "twist":
            return wire.decode_twist_msg(payload) != wire.STOP
        if kind == "json":
            return wire.decode_json_msg(payload).get("arm") is not False
    except wire.WireError:
        return False
    return False


# ---- malformed by construction (the property tests) ----------------------------------

MESSAGES = ("scan", "pose", "point", "bool", "twist", "json")

CANONICAL_BOOLS = {
    bytes([0, order, 0, 0, value]) + padding
    for order in (0, 1)
    for value in (0, 1)
    for padding in (b"", b"\x00\x00\x00")
} | {bytes([0, order, 0, 3, value, 0, 0, 0]) for order in (0, 1) for value in (0, 1)}
"""Every well-formed std_msgs/Bool, written out: anything else on a Bool key is malformed."""

CANONICAL_TRUE = {payload for payload in CANONICAL_BOOLS if payload[4] == 1}
"""The only payloads that may release an emergency stop."""

TWIST_BYTES = 52
"""A Twist's size: the header and six doubles (a PointStamped with a 10-byte frame id, too)."""

Generator = np.random.Generator


def well_formed(message: str, rng: Generator) -> bytes:
    """One well-formed payload of `message` (minimal encoding: no padding after it)."""
    frame = ["", "map", "laser", "base_link"][int(rng.integers(0, 4))]
    if message == "scan":
        count = int(rng.integers(360, 1081))
        ranges = rng.uniform(0.2, 20.0, count).astype(np.float32)
        scan = wire.Scan(1.5, frame, -math.pi, 2 * math.pi / count, 0.1, 30.0, ranges)
        return wire.encode_scan_msg(scan)
    x, y, yaw = (float(v) for v in rng.uniform(-50.0, 50.0, 3))
    if message == "pose":
        return wire.encode_pose_msg(wire.Pose2D(2.0, frame, x, y, yaw))
    if message == "point":
        return wire.encode_point_msg(wire.Pose2D(2.0, frame, x, y))
    if message == "bool":
        return wire.encode_bool_msg(bool(rng.integers(0, 2)))
    if message == "twist":
        return wire.encode_twist_msg(wire.Twist2D(x / 100, y / 100))
    if message == "json":
        return wire.encode_json_msg({"arm": bool(rng.integers(0, 2)), "mode": "GUIDED"})
    raise ValueError(f"no message kind {message!r}; one of {MESSAGES}")


def _string_payload(raw: bytes, length: int | None = None) -> bytes:
    writer = cdr.Writer()
    writer.pack(cdr.Layout("I"), 4, len(raw) if length is None else length)
    writer.out += raw
    return writer.payload()


def _structured(message: str, rng: Generator) -> Iterator[tuple[str, bytes]]:
    """Well-formed CDR carrying values our rules refuse (non-finite, absurd, implausible)."""
    bad = [math.nan, math.inf, -math.inf]
    pick = bad[int(rng.integers(0, 3))]
    absurd = float(rng.choice([1e308, -1e308, 9.1e150, -3e38, 1e6]))
    if message == "scan":
        count = int(rng.integers(360, 721))
        ranges = np.full(count, 3.0, dtype=np.float32)
        inc = 2 * math.pi / count

        def scan(
            n: int = count,
            increment: float = inc,
            low: float = 0.1,
            high: float = 30.0,
            start: float = 0.0,
        ) -> bytes:
            values = ranges[:n] if n <= count else np.full(n, 3.0, dtype=np.float32)
            return wire.encode_scan_msg(
                wire.Scan(1.0, "laser", start, increment, low, high, values)
            )

        yield "scan-range-min-nonfinite", scan(low=pick)
        yield "scan-range-max-nonfinite", scan(high=pick)
        yield "scan-range-min-above-max", scan(low=40.0, high=float(rng.uniform(0.0, 40.0)))
        yield "scan-range-min-negative", scan(low=-float(rng.uniform(0.01, 10.0)))
        yield "scan-one-reading", scan(n=1, increment=float(rng.uniform(0.001, 0.1)))
        yield "scan-few-readings", scan(n=int(rng.integers(0, 50)), increment=0.2)
        yield "scan-narrow", scan(n=100, increment=float(rng.uniform(0.001, 0.03)))
        yield "scan-increment-nonfinite", scan(increment=pick)
        yield "scan-increment-zero", scan(increment=0.0)
        yield "scan-angle-min-absurd", scan(start=float(rng.choice([1e30, -1e30, 1e7, -13.0])))
        yield "scan-increment-absurd", scan(increment=float(rng.choice([1e6, -1e5, 4.0])))
        all_nan = wire.Scan(1.0, "laser", 0.0, inc, 0.1, 30.0, np.full(count, np.nan, np.float32))
        yield "scan-all-invalid", wire.encode_scan_msg(all_nan)
    elif message in ("pose", "point"):
        fields = 7 if message == "pose" else 3
        values = [1.0, 2.0, 0.0, 0.0, 0.0, 0.0, 1.0][:fields]
        index = int(rng.integers(0, fields))
        for kind, value in (("nonfinite", pick), ("absurd", absurd)):
            broken = list(values)
            broken[index if kind == "nonfinite" else int(rng.integers(0, 2))] = value
            writer = cdr.Writer()
            writer.pack(cdr.TIME, 4, 1, 0)
            writer.string("map")
            writer.pack(cdr.Layout(f"{fields}d"), 8, *broken)
            yield f"{message}-{kind}", writer.payload()
        if message == "pose":
            scale = float(rng.choice([0.0, 0.5, 0.85, 1.15, 2.0, 1e10]))
            q = rng.normal(size=4)
            q = q / np.linalg.norm(q) * scale
            writer = cdr.Writer()
            writer.pack(cdr.TIME, 4, 1, 0)
            writer.string("map")
            writer.pack(cdr.Layout("7d"), 8, 1.0, 2.0, 0.0, *(float(v) for v in q))
            yield "pose-quaternion-not-unit", writer.payload()
        writer = cdr.Writer()
        writer.pack(cdr.TIME, 4, 1, int(rng.integers(1_000_000_000, 2**32)))
        writer.string("map")
        writer.pack(cdr.Layout(f"{fields}d"), 8, *values)
        yield f"{message}-nanosec-overflow", writer.payload()
    elif message == "bool":
        yield "bool-byte", bytes([0, 1, 0, 0, int(rng.integers(2, 256))])
        yield "bool-byte-padded", bytes([0, 1, 0, 0, int(rng.integers(2, 256)), 0, 0, 0])
    elif message == "twist":
        values = [0.0] * 6
        values[int(rng.integers(0, 6))] = pick
        writer = cdr.Writer()
        writer.pack(cdr.Layout("6d"), 8, *values)
        yield "twist-nonfinite", writer.payload()
        yield "twist-absurd", wire.encode_twist_msg(wire.Twist2D(absurd, 0.0))
        yield "twist-absurd-turn", wire.encode_twist_msg(wire.Twist2D(0.0, absurd))
    elif message == "json":
        texts = [
            '{"arm": NaN}',
            '{"arm": true, "arm": false}',
            '{"arm": 1}',
            '{"arm": "true"}',
            '{"arm": null}',
            '{"arm": [true]}',
            '{"mode": 3.0}',
            '{"mode": "WARP"}',
            '{"arm": true, "speed": 5}',
            '{"mode": true}',
            '{"arm": Infinity}',
            "[true]",
            "true",
            '"arm"',
            '{"arm": tru',
            "[" * 50_000 + "]" * 50_000,
        ]
        yield (
            "json-loose",
            _string_payload(texts[int(rng.integers(0, len(texts)))].encode() + b"\0"),
        )
        yield "json-not-utf8", _string_payload(b'{"arm": "\xff\xfe"}\x00')
        yield "json-inner-nul", _string_payload(b'{"arm": true}\x00{"arm": false}\x00')
        yield "json-oversized", _string_payload(b'{"x": "' + b"a" * 70_000 + b'"}\x00')


def malformed(
    message: str, rng: Generator, count: int, max_bytes: int = 1 << 20
) -> Iterator[tuple[str, bytes]]:
    """`count` malformed payloads of `message` (module docstring), the largest `max_bytes`."""
    others = [m for m in MESSAGES if m != message and {m, message} != {"pose", "point"}]
    makers: list[Callable[[], Iterator[tuple[str, bytes]]]] = [
        lambda: _structured(message, rng),
        lambda: _framing(message, rng),
        lambda: iter([("other-type", well_formed(others[int(rng.integers(0, len(others)))], rng))]),
        lambda: iter([("random", _random(rng))]),
    ]
    yield from _many(message, makers, rng, count)
    if max_bytes >= 1 << 20:
        yield from _oversized(message, max_bytes)


def _many(
    message: str,
    makers: list[Callable[[], Iterator[tuple[str, bytes]]]],
    rng: Generator,
    count: int,
) -> Iterator[tuple[str, bytes]]:
    made = 0
    while made < count:
        for kind, payload in makers[int(rng.integers(0, len(makers)))]():
            if message == "bool" and payload in CANONICAL_BOOLS:
                continue  # a random payload that happens to be a Bool is no malformed one
            if message == "twist" and kind == "other-type" and len(payload) == TWIST_BYTES:
                continue  # CDR has no type tags: any 48-byte body reads as six doubles
            yield kind, payload
            made += 1
            if made == count:
                return


def _random(rng: Generator) -> bytes:
    """Random bytes behind a broken header (wrong representation or options)."""
    body = rng.integers(0, 256, int(rng.integers(0, 300)), dtype=np.uint8).tobytes()
    if rng.random() < 0.5:
        kind = bytes([int(rng.integers(1, 256)), int(rng.integers(0, 256))])  # not 00 0x
        return kind + rng.integers(0, 256, 2, dtype=np.uint8).tobytes() + body
    return bytes([0, int(rng.integers(2, 256))]) + bytes(2) + body  # 00 02.. is not CDR


def _framing(message: str, rng: Generator) -> Iterator[tuple[str, bytes]]:
    """A valid payload broken in its framing: cut, extended, re-headed, re-counted."""
    payload = well_formed(message, rng)
    yield "truncated", payload[: int(rng.integers(0, len(payload)))]
    tail = rng.integers(0, 256, int(rng.integers(1, 64)), dtype=np.uint8).tobytes()
    if not any(tail):
        tail += b"\x01"
    yield "trailing-garbage", payload + tail
    yield "trailing-zeros", payload + bytes(int(rng.integers(4, 64)))
    options = bytes([int(rng.integers(1, 256)), int(rng.integers(0, 256))])
    yield "options-byte", payload[:2] + options + payload[4:]
    yield "options-padding-missing", payload[:3] + bytes([int(rng.integers(1, 4))]) + payload[4:]
    yield "encapsulation", bytes([0, int(rng.integers(2, 256))]) + payload[2:]
    if message != "twist":  # six byte-swapped doubles may well be a valid Twist
        yield "big-endian-header-on-little-endian-body", b"\x00\x00" + payload[2:]
    if message in ("scan", "pose", "point"):  # a header: frame_id's length prefix at byte 12
        absurd = int(rng.choice([0, len(payload), 2**31, 2**32 - 1, int(rng.integers(1, 2**32))]))
        if absurd != int.from_bytes(payload[12:16], "little"):
            yield "string-length", payload[:12] + absurd.to_bytes(4, "little") + payload[16:]
        frame_end = 16 + int.from_bytes(payload[12:16], "little")
        unterminated = bytearray(payload)
        unterminated[frame_end - 1] = int(rng.integers(1, 256))
        yield "string-unterminated", bytes(unterminated)
    if message == "scan":  # the ranges' count: right after the seven floats
        frame_end = 16 + int.from_bytes(payload[12:16], "little")
        at = frame_end + (-(frame_end - 4) % 4) + 28
        count = int.from_bytes(payload[at : at + 4], "little")
        absurd = int(rng.choice([count + 1, 2**31, 2**32 - 1, count + int(rng.integers(2, 10**6))]))
        yield "sequence-count", payload[:at] + absurd.to_bytes(4, "little") + payload[at + 4 :]
    if message == "json":
        yield "string-length", payload[:4] + (2**32 - 1).to_bytes(4, "little") + payload[8:]


def _oversized(message: str, max_bytes: int) -> Iterator[tuple[str, bytes]]:
    """A message of about `max_bytes` (a scan with that many bytes of readings, a string of
    that length, or a valid message followed by that many zero bytes)."""
    if message == "scan":
        count = max_bytes // 4
        scan = wire.Scan(1.0, "laser", 0.0, 1e-6, 0.1, 30.0, np.full(count, 3.0, np.float32))
        yield "oversized", wire.encode_scan_msg(scan)
    elif message == "json":
        yield "oversized", _string_payload(b'{"x": "' + b"a" * max_bytes + b'"}\x00')
    else:
        yield "oversized", well_formed(message, np.random.default_rng(0)) + bytes(max_bytes)
