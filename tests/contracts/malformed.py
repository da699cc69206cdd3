"""Malformed payloads for every message kind the daemons take: the generator behind the
property tests and `make fuzz` (issue 18 part 7).

Each payload is one of: random bytes, a valid message cut short, a valid message with a few
bytes changed, another encapsulation header, garbage after the message, an absurd length field,
non-finite or absurd values in a well-formed message, a message of another type, or (rarely)
a 10 MB blob. Seeded: the same seed gives the same payloads.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Iterator

import numpy as np

from contracts import cdr, wire

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
