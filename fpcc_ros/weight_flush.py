"""Flush tiny float32 weights of a serialized ONNX model to zero, without the ``onnx`` package.

Why: a collapsed channel leaves weights around 1e-38 (denormal floats, below 1.2e-38) and many
just above, whose products with activations are denormal. Intel cores take a microcode assist
on every denormal operand: the shipped model's point2 MatMul ran at 3 GFLOP/s instead of ~100,
a 2048-point block 560 ms instead of 37 ms, with bit-identical outputs once the weights below
1e-20 were zero (issue 25). AMD cores pay little, so a benchmark there hides it.

The node must do this for any model a user brings, and its runtime has onnxruntime but not the
``onnx`` package, so this walks the protobuf wire format directly: an ONNX file is a
``ModelProto`` whose ``graph`` holds ``initializer`` tensors (and Constant nodes holding tensor
attributes, and subgraphs). A float tensor keeps its values in ``raw_data`` or a packed
``float_data``; zeroing a value changes no length, so the bytes are edited in place.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FLUSH_BELOW = 1e-20            # |w| below this becomes 0: far below any weight that matters
TINY = float(np.finfo(np.float32).tiny)
FLOAT = 1                       # TensorProto.DataType.FLOAT

# field numbers (onnx.proto3)
MODEL_GRAPH = 7
GRAPH_NODE, GRAPH_INITIALIZER = 1, 5
NODE_INPUT, NODE_OP_TYPE, NODE_ATTRIBUTE = 1, 4, 5
WEIGHT_OPS = {"MatMul": None, "FusedMatMul": None, "Gemm": 1, "Conv": 1}  # None: any input
ATTR_T, ATTR_G, ATTR_TENSORS, ATTR_GRAPHS = 5, 6, 10, 11
TENSOR_DIMS, TENSOR_DATA_TYPE, TENSOR_FLOAT_DATA, TENSOR_NAME = 1, 2, 4, 8
TENSOR_RAW_DATA, TENSOR_DATA_LOCATION = 9, 14
DEAD_BELOW = 1e-20             # a weight row whose largest |w| is under this: a dead channel


@dataclass(frozen=True)
class WeightFlush:
    """What a flush found: float32 weights in all, denormal ones, and all set to zero."""

    weights: int = 0
    denormal: int = 0
    flushed: int = 0

    def __add__(self, other: "WeightFlush") -> "WeightFlush":
        return WeightFlush(self.weights + other.weights, self.denormal + other.denormal,
                           self.flushed + other.flushed)


def flush_tiny_weights(model: bytes, below: float = FLUSH_BELOW) -> tuple[bytes, WeightFlush]:
    """``model`` with every float32 weight of magnitude under ``below`` (not zero) set to 0."""
    buf = bytearray(model)
    total = WeightFlush()
    for _, _, spans in _float_tensors(buf):
        for a, b in spans:
            values = np.frombuffer(buf, dtype="<f4", count=(b - a) // 4, offset=a)
            magnitude = np.abs(values)
            tiny = (values != 0) & (magnitude < below)
            total += WeightFlush(len(values), int(((values != 0) & (magnitude < TINY)).sum()),
                                 int(tiny.sum()))
            if tiny.any():
                buf[a:a + 4 * len(values)] = np.where(tiny, np.float32(0), values).astype("<f4").tobytes()
    return bytes(buf), total


def count_tiny_weights(model: bytes, below: float = FLUSH_BELOW) -> WeightFlush:
    """The same count without changing anything."""
    return flush_tiny_weights(model, below)[1]


def dead_channels(model: bytes) -> dict[str, tuple[int, int]]:
    """Weight matrix name -> (dead output channels, channels) for every 2-D float initializer
    with a dead channel, as ../shared/tools/model_health.py counts them: a channel is dead when
    every weight producing it is (nearly) zero, i.e. it outputs a constant. The output axis is
    the one with more dead lines (exporters lay matrices out either way)."""
    buf = bytearray(model)
    weights = _weight_inputs(buf)
    out = {}
    for name, dims, spans in _float_tensors(buf):
        if name not in weights or len(dims) != 2 or min(dims) < 8 or len(spans) != 1:
            continue
        a, b = spans[0]
        if (b - a) // 4 != dims[0] * dims[1]:
            continue
        w = np.abs(np.frombuffer(buf, dtype="<f4", count=dims[0] * dims[1], offset=a)).reshape(dims)
        rows, cols = int((w.max(axis=1) < DEAD_BELOW).sum()), int((w.max(axis=0) < DEAD_BELOW).sum())
        dead, n = (rows, dims[0]) if rows >= cols else (cols, dims[1])
        if dead:
            out[name] = (dead, n)
    return out


def _weight_inputs(buf: bytearray) -> set[str]:
    """Names the main graph's MatMul / Gemm / Conv nodes take as weights."""
    names: set[str] = set()
    for start, end in _fields_of(buf, 0, len(buf), MODEL_GRAPH):
        for a, b in _fields_of(buf, start, end, GRAPH_NODE):
            inputs, op = [], ""
            for field, wire, c, d in _walk(buf, a, b):
                if field == NODE_INPUT and wire == 2:
                    inputs.append(bytes(buf[c:d]).decode("utf-8", "replace"))
                elif field == NODE_OP_TYPE and wire == 2:
                    op = bytes(buf[c:d]).decode("utf-8", "replace")
            if op in WEIGHT_OPS:
                names.update(inputs if WEIGHT_OPS[op] is None else inputs[1:2])
    return names


def _float_tensors(buf: bytearray):
    """(name, dims, value spans) of every float32 tensor stored in the model (initializers,
    Constant nodes' tensors, subgraphs); external data is skipped."""
    for start, end in _fields_of(buf, 0, len(buf), MODEL_GRAPH):
        yield from _graph_tensors(buf, start, end)


def _graph_tensors(buf: bytearray, start: int, end: int):
    for field, wire, a, b in _walk(buf, start, end):
        if wire != 2:
            continue
        if field == GRAPH_INITIALIZER:
            yield from _tensor(buf, a, b)
        elif field == GRAPH_NODE:
            for s, e in _fields_of(buf, a, b, NODE_ATTRIBUTE):
                for f, w, c, d in _walk(buf, s, e):
                    if w == 2 and f in (ATTR_T, ATTR_TENSORS):
                        yield from _tensor(buf, c, d)
                    elif w == 2 and f in (ATTR_G, ATTR_GRAPHS):
                        yield from _graph_tensors(buf, c, d)


def _tensor(buf: bytearray, start: int, end: int):
    data_type, external, name, dims, spans = 0, False, "", [], []
    for field, wire, a, b in _walk(buf, start, end):
        if field == TENSOR_DATA_TYPE and wire == 0:
            data_type = a
        elif field == TENSOR_DATA_LOCATION and wire == 0:
            external = a == 1
        elif field == TENSOR_NAME and wire == 2:
            name = bytes(buf[a:b]).decode("utf-8", "replace")
        elif field == TENSOR_DIMS and wire == 0:
            dims.append(a)
        elif field == TENSOR_DIMS and wire == 2:          # packed
            pos = a
            while pos < b:
                value, pos = _varint(buf, pos)
                dims.append(value)
        elif field == TENSOR_RAW_DATA and wire == 2:
            spans.append((a, b))
        elif field == TENSOR_FLOAT_DATA and wire in (2, 5):   # packed, or one value each
            spans.append((a, b))
    if data_type == FLOAT and not external:
        yield name, dims, spans


def _fields_of(buf: bytearray, start: int, end: int, wanted: int):
    """(start, end) of every length-delimited field ``wanted`` in a message."""
    for field, wire, a, b in _walk(buf, start, end):
        if field == wanted and wire == 2:
            yield a, b


def _walk(buf: bytearray, start: int, end: int):
    """(field, wire type, a, b) per field of the message in ``buf[start:end]``: for varints
    ``a`` is the value, for length-delimited and fixed-size fields ``buf[a:b]`` the payload."""
    pos = start
    while pos < end:
        key, pos = _varint(buf, pos)
        field, wire = key >> 3, key & 7
        if wire == 0:
            value, pos = _varint(buf, pos)
            yield field, wire, value, None
        elif wire == 2:
            length, pos = _varint(buf, pos)
            yield field, wire, pos, pos + length
            pos += length
        elif wire == 5:
            yield field, wire, pos, pos + 4
            pos += 4
        elif wire == 1:
            yield field, wire, pos, pos + 8
            pos += 8
        else:
            raise ValueError(f"not an ONNX model: protobuf wire type {wire} at byte {pos}")
    if pos != end:
        raise ValueError(f"not an ONNX model: a field runs past its message at byte {pos}")


def _varint(buf: bytearray, pos: int) -> tuple[int, int]:
    value, shift = 0, 0
    while True:
        if pos >= len(buf):
            raise ValueError("not an ONNX model: truncated varint")
        byte = buf[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            return value, pos
        shift += 7
