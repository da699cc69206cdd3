"""Malformed payloads of every message we take, by construction, for property and fuzz tests.

    for kind, payload in malformed("pose", np.random.default_rng(0), 500):
        ...  # every payload is refused: by the decoder, or by the consumer's plausibility rules

Each generator yields (kind, payload) pairs; `kind` names how the payload was broken (for the
failure message and the counts a fuzz run prints). Every payload is malformed by construction,
never by chance: truncations of minimal encodings, bytes after the message that are not zero
padding, wrong encapsulation or option bytes, absurd length prefixes, non-finite or absurd
numbers, other message types, random bytes behind a broken header, oversized messages, loose
JSON. A test still checks each one is refused, so a generator that made a valid one would fail
loudly rather than pass quietly.

`MESSAGES` are the message kinds: scan (LaserScan), pose (PoseStamped), point (PointStamped),
bool (std_msgs/Bool), twist (Twist) and json (a String holding a JSON vehicle request).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import numpy as np

from contracts import cdr, wire

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


def valid(message: str, rng: Generator) -> bytes:
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
            n: int = count, increment: float = inc, low: float = 0.1, high: float = 30.0
        ) -> bytes:
            values = ranges[:n] if n <= count else np.full(n, 3.0, dtype=np.float32)
            return wire.encode_scan_msg(wire.Scan(1.0, "laser", 0.0, increment, low, high, values))

        yield "scan-range-min-nonfinite", scan(low=pick)
        yield "scan-range-max-nonfinite", scan(high=pick)
        yield "scan-range-min-above-max", scan(low=40.0, high=float(rng.uniform(0.0, 40.0)))
        yield "scan-range-min-negative", scan(low=-float(rng.uniform(0.01, 10.0)))
        yield "scan-one-reading", scan(n=1, increment=float(rng.uniform(0.001, 0.1)))
        yield "scan-few-readings", scan(n=int(rng.integers(0, 50)), increment=0.2)
        yield "scan-narrow", scan(n=100, increment=float(rng.uniform(0.001, 0.03)))
        yield "scan-increment-nonfinite", scan(increment=pick)
        yield "scan-increment-zero", scan(increment=0.0)
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
        lambda: iter([("other-type", valid(others[int(rng.integers(0, len(others)))], rng))]),
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
    payload = valid(message, rng)
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
        yield "oversized", valid(message, np.random.default_rng(0)) + bytes(max_bytes)
