"""Read the initializer tensors of an ONNX file without the ``onnx`` package.

The runtime needs the KSNN weights (for the analytic Jacobian and the hidden-space inverse solve) but may only
depend on numpy and onnxruntime, which does not expose initializer values. An ONNX file is a protobuf
``ModelProto``; this module walks its wire format just far enough to find ``graph.initializer`` entries and
decode their ``dims``, ``data_type`` and ``raw_data`` (or packed typed data) into numpy arrays.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from models.errors import SpecError

#: ONNX TensorProto.DataType → numpy dtype (the types an exported KSNN can hold).
_DTYPES: dict[int, np.dtype] = {
    1: np.dtype("<f4"),
    2: np.dtype("u1"),
    3: np.dtype("i1"),
    6: np.dtype("<i4"),
    7: np.dtype("<i8"),
    10: np.dtype("<f2"),
    11: np.dtype("<f8"),
}

# Field numbers from onnx.proto3.
_MODEL_GRAPH = 7
_MODEL_METADATA = 14
_GRAPH_INITIALIZER = 5
_GRAPH_INPUT, _GRAPH_OUTPUT = 11, 12
_VALUE_INFO_NAME = 1
_ENTRY_KEY, _ENTRY_VALUE = 1, 2
_TENSOR_DIMS, _TENSOR_TYPE, _TENSOR_FLOAT, _TENSOR_INT32 = 1, 2, 4, 5
_TENSOR_INT64, _TENSOR_NAME, _TENSOR_RAW, _TENSOR_DOUBLE = 7, 8, 9, 10
_TENSOR_EXTERNAL, _TENSOR_LOCATION = 13, 14


def _varint(buf: memoryview, pos: int) -> tuple[int, int]:
    result = 0
    shift = 0
    while True:
        b = buf[pos]
        pos += 1
        result |= (b & 0x7F) << shift
        if b < 0x80:
            return result, pos
        shift += 7


def _fields(buf: memoryview):
    """Yield (field_number, wire_type, value) where value is an int or a memoryview slice."""
    pos = 0
    end = len(buf)
    while pos < end:
        key, pos = _varint(buf, pos)
        field, wire = key >> 3, key & 7
        if wire == 0:
            value, pos = _varint(buf, pos)
        elif wire == 1:
            value, pos = buf[pos:pos + 8], pos + 8
        elif wire == 2:
            n, pos = _varint(buf, pos)
            value, pos = buf[pos:pos + n], pos + n
        elif wire == 5:
            value, pos = buf[pos:pos + 4], pos + 4
        else:
            raise ValueError(f"unsupported protobuf wire type {wire}")
        yield field, wire, value


def _packed_varints(buf: memoryview) -> list[int]:
    out = []
    pos = 0
    while pos < len(buf):
        v, pos = _varint(buf, pos)
        out.append(v)
    return out


def _tensor(buf: memoryview, source: str) -> tuple[str, np.ndarray]:
    dims: list[int] = []
    dtype_code = 0
    name = ""
    raw: memoryview | None = None
    typed: list[memoryview] = []
    for field, wire, value in _fields(buf):
        if field == _TENSOR_DIMS:
            dims.extend(_packed_varints(value) if wire == 2 else [value])
        elif field == _TENSOR_TYPE:
            dtype_code = value
        elif field == _TENSOR_NAME:
            name = bytes(value).decode("utf-8")
        elif field == _TENSOR_RAW:
            raw = value
        elif field in (_TENSOR_FLOAT, _TENSOR_DOUBLE, _TENSOR_INT32, _TENSOR_INT64) and wire == 2:
            typed.append(value)
        elif field == _TENSOR_EXTERNAL or (field == _TENSOR_LOCATION and value == 1):
            raise SpecError(source, f"initializer {name or '?'}", "external tensor data is not supported")
    if dtype_code not in _DTYPES:
        raise SpecError(source, f"initializer {name}", "unsupported tensor data type", dtype_code)
    dtype = _DTYPES[dtype_code]
    count = int(np.prod(dims)) if dims else 1
    if raw is not None:
        arr = np.frombuffer(bytes(raw), dtype=dtype)
    elif typed:
        blob = b"".join(bytes(t) for t in typed)
        if dtype_code in (1, 11):
            arr = np.frombuffer(blob, dtype=dtype)
        else:  # int32/int64/uint8/int8 stored as packed varints
            arr = np.array(_packed_varints(memoryview(blob)), dtype=np.int64).astype(dtype)
    else:
        arr = np.zeros(count, dtype=dtype)
    if arr.size != count:
        raise SpecError(source, f"initializer {name}", f"holds {arr.size} values, dims {dims} need {count}")
    return name, arr.reshape(dims)


def read_initializers(path: str | Path, names: set[str] | None = None) -> dict[str, np.ndarray]:
    """Return the graph initializers of the ONNX file at ``path`` (only ``names`` if given) as numpy arrays."""
    source = str(path)
    data = memoryview(Path(path).read_bytes())
    out: dict[str, np.ndarray] = {}
    try:
        for field, wire, graph in _fields(data):
            if field != _MODEL_GRAPH or wire != 2:
                continue
            for gfield, gwire, tensor in _fields(graph):
                if gfield != _GRAPH_INITIALIZER or gwire != 2:
                    continue
                name, arr = _tensor(tensor, source)
                if names is None or name in names:
                    out[name] = arr
    except (IndexError, ValueError) as exc:
        raise SpecError(source, "graph", f"not a readable ONNX model: {exc}") from exc
    return out


def read_model_info(path: str | Path) -> tuple[tuple[str, ...], tuple[str, ...], dict[str, str]]:
    """The graph's input names, output names and the model's metadata (``metadata_props``) of the ONNX file at
    ``path``, read without onnxruntime (what :class:`models.predictor.SkinPredictor` checks before it needs a
    session). A file that is not a readable ONNX model raises :class:`SpecError`."""
    source = str(path)
    data = memoryview(Path(path).read_bytes())
    inputs: list[str] = []
    outputs: list[str] = []
    meta: dict[str, str] = {}
    graphs = 0

    def name_of(value_info: memoryview) -> str:
        for f, w, v in _fields(value_info):
            if f == _VALUE_INFO_NAME and w == 2:
                return bytes(v).decode("utf-8")
        return ""

    try:
        for field, wire, value in _fields(data):
            if field == _MODEL_GRAPH and wire == 2:
                graphs += 1
                for gfield, gwire, item in _fields(value):
                    if gwire == 2 and gfield in (_GRAPH_INPUT, _GRAPH_OUTPUT):
                        (inputs if gfield == _GRAPH_INPUT else outputs).append(name_of(item))
            elif field == _MODEL_METADATA and wire == 2:
                entry = {f: bytes(v).decode("utf-8") for f, w, v in _fields(value) if w == 2}
                meta[entry.get(_ENTRY_KEY, "")] = entry.get(_ENTRY_VALUE, "")
    except (IndexError, ValueError) as exc:  # UnicodeDecodeError is a ValueError
        raise SpecError(source, "graph", f"not a readable ONNX model: {exc}") from exc
    if graphs != 1:
        raise SpecError(source, "graph", f"not a readable ONNX model: {graphs} graphs")
    return tuple(inputs), tuple(outputs), meta
