"""Read an ONNX file's metadata and weights with numpy alone.

Boards without an onnxruntime wheel (32-bit ARM, like the paper's Odroid XU4) have no `onnx`
package either, so the numpy backend parses the file itself. An ONNX file is a protobuf
`ModelProto`; only a few of its fields matter here, and the protobuf wire format is simple:
each field is a varint key (field number << 3 | wire type) followed by a varint, a fixed 4 or
8 bytes, or a length-prefixed run of bytes (strings, packed arrays and nested messages).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from contracts.errors import PolicyFileError

# Field numbers from onnx.proto3.
_MODEL_GRAPH = 7
_MODEL_METADATA = 14
_GRAPH_INITIALIZER = 5
_ENTRY_KEY, _ENTRY_VALUE = 1, 2
_TENSOR_DIMS, _TENSOR_TYPE, _TENSOR_FLOATS, _TENSOR_NAME = 1, 2, 4, 8
_TENSOR_RAW, _TENSOR_LOCATION = 9, 14

_VARINT, _FIXED64, _BYTES, _FIXED32 = 0, 1, 2, 5

_DTYPES: dict[int, type[np.generic]] = {
    1: np.float32,
    6: np.int32,
    7: np.int64,
    11: np.float64,
}
"""TensorProto.DataType codes this reader decodes."""


@dataclass(frozen=True)
class OnnxContents:
    """What the numpy runtime needs from an ONNX file."""

    metadata: dict[str, str]
    """The model's metadata_props."""
    initializers: dict[str, NDArray[np.generic]]
    """The graph's weights by name."""


def read_onnx(path: Path) -> OnnxContents:
    """Metadata and initializers of the ONNX file at `path`."""
    data = memoryview(Path(path).read_bytes())
    metadata: dict[str, str] = {}
    initializers: dict[str, NDArray[np.generic]] = {}
    try:
        for number, _, value in _fields(data):
            if number == _MODEL_METADATA:
                entry = {n: bytes(_as_bytes(v)).decode() for n, _, v in _fields(_as_bytes(value))}
                metadata[entry.get(_ENTRY_KEY, "")] = entry.get(_ENTRY_VALUE, "")
            elif number == _MODEL_GRAPH:
                for graph_number, _, graph_value in _fields(_as_bytes(value)):
                    if graph_number == _GRAPH_INITIALIZER:
                        name, array = _tensor(_as_bytes(graph_value), path)
                        initializers[name] = array
    except (IndexError, ValueError, UnicodeDecodeError) as error:
        if isinstance(error, PolicyFileError):
            raise
        raise PolicyFileError(f"{path} is not a readable ONNX file ({error})") from None
    return OnnxContents(metadata=metadata, initializers=initializers)


def _fields(data: memoryview) -> Iterator[tuple[int, int, int | memoryview]]:
    """(field number, wire type, value) for each field of one message."""
    position = 0
    while position < len(data):
        key, position = _varint(data, position)
        number, wire = key >> 3, key & 7
        value: int | memoryview
        if wire == _VARINT:
            value, position = _varint(data, position)
        elif wire == _BYTES:
            length, position = _varint(data, position)
            if position + length > len(data):
                raise ValueError("a field runs past the end of the file")
            value, position = data[position : position + length], position + length
        elif wire == _FIXED64:
            value, position = int.from_bytes(data[position : position + 8], "little"), position + 8
        elif wire == _FIXED32:
            value, position = int.from_bytes(data[position : position + 4], "little"), position + 4
        else:
            raise ValueError(f"unsupported protobuf wire type {wire}")
        yield number, wire, value


def _varint(data: memoryview, position: int) -> tuple[int, int]:
    result = shift = 0
    while True:
        byte = data[position]
        position += 1
        result |= (byte & 0x7F) << shift
        if byte < 0x80:
            return result, position
        shift += 7
        if shift > 63:
            raise ValueError("malformed varint")


def _as_bytes(value: int | memoryview) -> memoryview:
    if isinstance(value, int):
        raise ValueError("expected a length-delimited field")
    return value


def _tensor(data: memoryview, path: Path) -> tuple[str, NDArray[np.generic]]:
    name, dims, dtype_code = "", [], 1
    raw: memoryview | None = None
    floats: list[float] = []
    for number, wire, value in _fields(data):
        if number == _TENSOR_NAME:
            name = bytes(_as_bytes(value)).decode()
        elif number == _TENSOR_DIMS:
            if wire == _BYTES:  # packed
                packed, position = _as_bytes(value), 0
                while position < len(packed):
                    dim, position = _varint(packed, position)
                    dims.append(dim)
            else:
                dims.append(int(value))
        elif number == _TENSOR_TYPE:
            dtype_code = int(value)
        elif number == _TENSOR_RAW:
            raw = _as_bytes(value)
        elif number == _TENSOR_FLOATS:
            if wire == _BYTES:
                floats.extend(np.frombuffer(_as_bytes(value), dtype="<f4").tolist())
            else:
                floats.append(float(np.uint32(value).view(np.float32)))  # type: ignore[arg-type]
        elif number == _TENSOR_LOCATION and value == 1:
            raise PolicyFileError(
                f"{path}: weight '{name}' is stored in a separate file; export with the weights "
                "inside (`qnav export` does)"
            )
    if dtype_code not in _DTYPES:
        raise PolicyFileError(
            f"{path}: weight '{name}' has unsupported ONNX data type {dtype_code}"
        )
    dtype = np.dtype(_DTYPES[dtype_code]).newbyteorder("<")
    array = np.frombuffer(raw, dtype=dtype) if raw is not None else np.asarray(floats, dtype=dtype)
    return name, array.reshape(dims).astype(dtype.newbyteorder("="), copy=True)
