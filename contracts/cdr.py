"""Direct little-endian CDR for the fixed-shape messages on the controller's hot path.

rosbags' generic (de)serialiser builds a message object per payload, which costs tens of
microseconds per LaserScan or PoseStamped; these readers and writers go straight between the
bytes and our values with `struct` and `numpy.frombuffer`. They follow the same CDR rules as
rosbags (alignment counted from the end of the 4-byte encapsulation header, strings with a
NUL-terminated length prefix, at most 3 bytes of padding after the last field), and they take
only what they are sure of: a big-endian payload, or one that is not plainly well formed,
raises `NotDirectError`, and the caller then hands it to rosbags, which decodes it or says what is
wrong. So a payload decodes to the same values, or fails with the same error, either way
(`tests/contracts/test_wire.py` checks both against rosbags).
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np
from numpy.typing import NDArray

ENCAPSULATION_LE = b"\x00\x01\x00\x00"
"""CDR_LE representation identifier and empty options: what ROS 2 writes on little-endian
machines."""

TIME = struct.Struct("<iI")
"""builtin_interfaces/msg/Time: sec (int32), nanosec (uint32)."""

_U32 = struct.Struct("<I")

MAX_PADDING = 3
"""Bytes after the last field that rosbags still accepts (alignment padding)."""


class NotDirectError(Exception):
    """The direct reader does not take this payload: let rosbags decode it (or refuse it)."""


class Reader:
    """Sequential little-endian reads from one CDR payload."""

    __slots__ = ("data", "pos", "strict")

    def __init__(self, payload: bytes, *, strict: bool = False) -> None:
        data = bytes(payload)  # no copy for bytes; memoryviews and bytearrays become bytes
        # Only the representation identifier counts (rosbags ignores the options bytes too);
        # a strict reader wants the header ROS 2 writes, options zero.
        wanted = ENCAPSULATION_LE if strict else ENCAPSULATION_LE[:2]
        if len(data) < len(ENCAPSULATION_LE) or data[: len(wanted)] != wanted:
            raise NotDirectError
        self.strict = strict
        self.data = data
        self.pos = len(ENCAPSULATION_LE)

    def unpack(self, layout: struct.Struct, align: int) -> tuple[Any, ...]:
        """The next fields of `layout`, after padding to `align` bytes."""
        self._align(align)
        end = self.pos + layout.size
        if end > len(self.data):
            raise NotDirectError
        values = layout.unpack_from(self.data, self.pos)
        self.pos = end
        return values

    def string(self) -> str:
        """A string: uint32 length counting its NUL terminator, UTF-8 bytes, NUL."""
        (length,) = self.unpack(_U32, 4)
        end = self.pos + length
        if length < 1 or end > len(self.data) or self.data[end - 1] != 0:
            raise NotDirectError
        try:
            text = self.data[self.pos : end - 1].decode()
        except UnicodeDecodeError:
            raise NotDirectError from None
        self.pos = end
        return text

    def float32_sequence(self) -> NDArray[np.float32]:
        """A sequence<float32>, as a read-only view of the payload (no copy)."""
        (count,) = self.unpack(_U32, 4)
        end = self.pos + 4 * count
        if end > len(self.data):
            raise NotDirectError
        values = np.frombuffer(self.data, dtype="<f4", count=count, offset=self.pos)
        self.pos = end
        return np.asarray(values, dtype=np.float32)

    def finish(self) -> None:
        """The message ends here: only alignment padding may follow (zeros, for a strict
        reader)."""
        rest = self.data[self.pos :]
        if len(rest) > MAX_PADDING or (self.strict and rest.strip(b"\x00")):
            raise NotDirectError

    def _align(self, align: int) -> None:
        body = self.pos - len(ENCAPSULATION_LE)
        self.pos += -body % align


class Writer:
    """Little-endian CDR written field by field, as rosbags writes it (zero padding)."""

    __slots__ = ("out",)

    def __init__(self) -> None:
        self.out = bytearray(ENCAPSULATION_LE)

    def pack(self, layout: struct.Struct, align: int, *values: Any) -> None:
        """Fields of `layout`, after padding to `align` bytes."""
        self._align(align)
        self.out += layout.pack(*values)

    def string(self, text: str) -> None:
        """A string with its length prefix and NUL terminator."""
        encoded = text.encode()
        self.pack(_U32, 4, len(encoded) + 1)
        self.out += encoded
        self.out.append(0)

    def float32_sequence(self, values: NDArray[np.floating]) -> None:
        """A sequence<float32> (values rounded to float32)."""
        array = np.ascontiguousarray(values, dtype="<f4")
        self.pack(_U32, 4, array.size)
        self.out += array.tobytes()

    def payload(self) -> bytes:
        """The message's bytes."""
        return bytes(self.out)

    def _align(self, align: int) -> None:
        body = len(self.out) - len(ENCAPSULATION_LE)
        self.out += bytes(-body % align)
