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

from qnav.contracts.errors import PolicyFileError
from qnav.contracts.policy_file import QUANTIZED_SUFFIXES, TRANSPOSED_SUFFIX

# Field numbers from onnx.proto3.
_MODEL_GRAPH = 7
_MODEL_METADATA = 14
_GRAPH_INITIALIZER = 5
_ENTRY_KEY, _ENTRY_VALUE = 1, 2
_TENSOR_DIMS, _TENSOR_TYPE, _TENSOR_FLOATS, _TENSOR_INTS, _TENSOR_NAME = 1, 2, 4, 5, 8
_TENSOR_RAW, _TENSOR_LOCATION = 9, 14

_VARINT, _FIXED64, _BYTES, _FIXED32 = 0, 1, 2, 5

_DTYPES: dict[int, type[np.generic]] = {
    1: np.float32,
    2: np.uint8,
    3: np.int8,
    6: np.int32,
    7: np.int64,
    11: np.float64,
}
"""TensorProto.DataType codes this reader decodes."""

_INT32_DATA_CODES = (2, 3, 6)
"""Codes whose values, when not raw, are in int32_data (float32's are in float_data)."""


@dataclass(frozen=True)
class OnnxContents:
    """What the numpy runtime needs from an ONNX file."""

    metadata: dict[str, str]
    """The model's metadata_props."""
    initializers: dict[str, NDArray[np.generic]]
    """The graph's weights by name."""


def read_onnx(path: Path) -> OnnxContents:
    """Metadata and initializers of the ONNX file at `path`."""
    return parse_onnx(Path(path).read_bytes(), path)


def parse_onnx(contents: bytes, path: Path | str) -> OnnxContents:
    """Metadata and initializers of an ONNX file's bytes (`path` names it in errors)."""
    data = memoryview(contents)
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


def float_weights(initializers: dict[str, NDArray[np.generic]]) -> dict[str, NDArray[np.float32]]:
    """The training network's parameters by name, in float32, from a file's initializers.

    float32 files store them as they are. int8 files store some as W_quantized, W_scale and
    W_zero_point, of the transpose (W_Transposed) of the parameter: these are dequantised,
    (W_quantized - W_zero_point) * W_scale column by column, and transposed back. Integer
    initializers that are not quantised weights (shape constants) are left out.
    """
    values, scales, zero_points = QUANTIZED_SUFFIXES
    weights: dict[str, NDArray[np.float32]] = {}
    for stored_name, stored in initializers.items():
        name, array = stored_name, stored
        if name.endswith((scales, zero_points)):
            continue
        if name.endswith(values):
            name = name.removesuffix(values)
            if name + scales not in initializers or name + zero_points not in initializers:
                raise PolicyFileError(f"int8 weight '{stored_name}' lacks its scale or zero point")
            offset = stored.astype(np.float32) - initializers[name + zero_points].astype(np.float32)
            array = offset * initializers[name + scales].astype(np.float32)
        elif not np.issubdtype(stored.dtype, np.floating):
            continue
        if name.endswith(TRANSPOSED_SUFFIX):
            name, array = name.removesuffix(TRANSPOSED_SUFFIX), array.T
        weights[name] = np.ascontiguousarray(array, dtype=np.float32)
    return weights


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


def _varints(wire: int, value: int | memoryview) -> list[int]:
    """A repeated varint field's values from one occurrence: packed or a single value."""
    if wire != _BYTES:
        return [int(value)]
    packed, position, result = _as_bytes(value), 0, []
    while position < len(packed):
        number, position = _varint(packed, position)
        result.append(number)
    return result


def _as_bytes(value: int | memoryview) -> memoryview:
    if isinstance(value, int):
        raise ValueError("expected a length-delimited field")
    return value


def _tensor(data: memoryview, path: Path | str) -> tuple[str, NDArray[np.generic]]:
    name, dims, dtype_code = "", [], 1
    raw: memoryview | None = None
    floats: list[float] = []
    ints: list[int] = []  # int32_data: int32, and the 8- and 16-bit types, as signed varints
    for number, wire, value in _fields(data):
        if number == _TENSOR_NAME:
            name = bytes(_as_bytes(value)).decode()
        elif number == _TENSOR_DIMS:
            dims.extend(_varints(wire, value))
        elif number == _TENSOR_INTS:
            ints.extend(v - (1 << 64) if v >= 1 << 63 else v for v in _varints(wire, value))
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
    if raw is not None:
        array = np.frombuffer(raw, dtype=dtype)
    else:
        array = np.asarray(ints if dtype_code in _INT32_DATA_CODES else floats, dtype=dtype)
    return name, array.reshape(dims).astype(dtype.newbyteorder("="), copy=True)
