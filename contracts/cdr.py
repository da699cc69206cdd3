"""A strict CDR reader and writer for the ROS 2 messages we take and send.

Every payload on the safety path (scans, poses, targets, the emergency stop and its release,
motor commands, JSON strings) is read here and nowhere else: there is no fallback to a more
lenient decoder, so what this reader refuses is refused. The rules (OMG CDR as ROS 2 uses it,
XCDR1 "plain" encoding):

- A 4-byte encapsulation header: representation identifier `00 01` (CDR_LE) or `00 00`
  (CDR_BE), then two option bytes. The first option byte is 0; the second is 0 or the number
  of padding bytes at the end of the message (DDS-XTypes 1.3, 7.6.3.1.2: Cyclone DDS, and so
  zenoh-bridge-ros2dds's DDS side, writes the count there; rosbags and Fast DDS write 0).
  Any other header is malformed.
- Fields aligned to their size (at most 8), counted from the end of the header.
- A string is a uint32 length counting its NUL terminator, that many bytes of UTF-8 with no NUL
  before the terminator, and the NUL; its length is bounded by the caller.
- A sequence is a uint32 count and that many elements, which must all be in the payload.
- After the last field only alignment padding may follow: at most 3 zero bytes that end the
  message on a 4-byte boundary, and exactly as many as the options byte says when it says any.
- A bool is one byte, exactly 0 or 1.

Decoding raises `WireError` with the reason, never returns a half-read message, and never reads
beyond the payload. Big-endian payloads are read too (the same rules, numbers byte-swapped).
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np
from numpy.typing import NDArray

ENCAPSULATION_LE = b"\x00\x01\x00\x00"
"""CDR_LE representation identifier and empty options: what we write (and ROS 2 on
little-endian machines)."""

_CDR_LE = b"\x00\x01"
_CDR_BE = b"\x00\x00"

MAX_PADDING = 3
"""Zero bytes after the last field that may pad a message to a 4-byte boundary."""

MAX_STRING_BYTES = 65_536
"""Longest string read when the caller gives no tighter bound (NUL included)."""


class WireError(ValueError):
    """A payload is not a well-formed message of the expected type."""


class Layout:
    """Fixed fields read or written together: one `struct` format (no byte-order prefix) for
    both byte orders."""

    __slots__ = ("be", "le", "size")

    def __init__(self, fields: str) -> None:
        self.le = struct.Struct("<" + fields)
        self.be = struct.Struct(">" + fields)
        self.size = self.le.size


TIME = Layout("iI")
"""builtin_interfaces/msg/Time: sec (int32), nanosec (uint32)."""

_U32 = Layout("I")
_U8 = Layout("B")


class Reader:
    """Sequential reads from one CDR payload, refusing anything not plainly well formed."""

    __slots__ = ("data", "little", "padding", "pos")

    def __init__(self, payload: bytes) -> None:
        data = bytes(payload)  # no copy for bytes; memoryviews and bytearrays become bytes
        if len(data) < 4:
            raise WireError(f"{len(data)} bytes: shorter than the CDR encapsulation header")
        kind, options = data[:2], data[2:4]
        if kind == _CDR_LE:
            self.little = True
        elif kind == _CDR_BE:
            self.little = False
        else:
            raise WireError(f"encapsulation {kind.hex()} is neither CDR_LE 0001 nor CDR_BE 0000")
        if options[0] != 0 or options[1] > MAX_PADDING:
            raise WireError(f"encapsulation options {options.hex()} are not 0000 to 0003")
        self.padding = options[1]
        self.data = data
        self.pos = 4

    def unpack(self, layout: Layout, align: int) -> tuple[Any, ...]:
        """The next fields of `layout`, after padding to `align` bytes."""
        self._align(align)
        end = self.pos + layout.size
        if end > len(self.data):
            raise WireError(f"truncated: {len(self.data)} bytes, a field ends at byte {end}")
        values = (layout.le if self.little else layout.be).unpack_from(self.data, self.pos)
        self.pos = end
        return values

    def boolean(self) -> bool:
        """A bool: one byte, exactly 0 or 1."""
        (value,) = self.unpack(_U8, 1)
        if value > 1:
            raise WireError(f"bool byte is {value:#04x}, neither 0 nor 1")
        return bool(value == 1)

    def string(self, max_bytes: int = MAX_STRING_BYTES) -> str:
        """A string: uint32 length counting its NUL terminator (at most `max_bytes`), UTF-8
        bytes without NUL, the NUL."""
        (length,) = self.unpack(_U32, 4)
        if length < 1 or length > max_bytes:
            raise WireError(f"string length {length} is not in [1, {max_bytes}]")
        end = self.pos + length
        if end > len(self.data):
            raise WireError(f"truncated: a string of {length} bytes ends past the payload")
        if self.data[end - 1] != 0:
            raise WireError("string is not NUL-terminated")
        raw = self.data[self.pos : end - 1]
        if 0 in raw:
            raise WireError("string holds a NUL before its end")
        try:
            text = raw.decode()
        except UnicodeDecodeError:
            raise WireError("string is not UTF-8") from None
        self.pos = end
        return text

    def float32_sequence(self) -> NDArray[np.float32]:
        """A sequence<float32> (a read-only view of the payload when little-endian)."""
        (count,) = self.unpack(_U32, 4)
        end = self.pos + 4 * count
        if end > len(self.data):
            raise WireError(f"truncated: a sequence of {count} float32 ends past the payload")
        dtype = "<f4" if self.little else ">f4"
        values = np.frombuffer(self.data, dtype=dtype, count=count, offset=self.pos)
        self.pos = end
        return np.asarray(values, dtype=np.float32)

    def finish(self) -> None:
        """The message ends here: only zero alignment padding may follow (module docstring)."""
        trailing = self.data[self.pos :]
        if not trailing:
            if self.padding:
                raise WireError(f"options announce {self.padding} padding bytes; none follow")
            return
        if len(trailing) > MAX_PADDING or (len(self.data) - 4) % 4 or any(trailing):
            raise WireError(f"{len(trailing)} bytes after the message that are not its padding")
        if self.padding and self.padding != len(trailing):
            raise WireError(
                f"options announce {self.padding} padding bytes; {len(trailing)} follow"
            )

    def _align(self, align: int) -> None:
        self.pos += -(self.pos - 4) % align


class Writer:
    """Little-endian CDR written field by field, as rosbags writes it (zero padding)."""

    __slots__ = ("out",)

    def __init__(self) -> None:
        self.out = bytearray(ENCAPSULATION_LE)

    def pack(self, layout: Layout, align: int, *values: Any) -> None:
        """Fields of `layout`, after padding to `align` bytes."""
        self._align(align)
        self.out += layout.le.pack(*values)

    def boolean(self, value: bool) -> None:
        """A bool byte."""
        self.out.append(1 if value else 0)

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
        self.out += bytes(-(len(self.out) - 4) % align)
