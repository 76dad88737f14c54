"""Which tensors of an ONNX file keep their data in another file (ONNX external data), read from the file's bytes
with the standard library alone, before ONNX Runtime is given them.

Why not leave it to ONNX Runtime: the Detector tells it to look for external data nowhere, and ONNX Runtime 1.24
and later refuse such a graph. But 1.21–1.23 (the GPU image's onnxruntime-gpu 1.22, the Jetson's 1.23, every
Python 3.10 install) still load a tensor whose file is named by an absolute path, and TensorRT is given the graph's
path, from which any version resolves a file beside it. No sha256 in the manifest covers such a file, so a checked
graph could run weights nobody checked. Reading the graph here refuses it on every version and provider.

Only protobuf's wire format is parsed (varints and length-delimited fields; onnx.proto gives the field numbers),
and only the messages that can hold a tensor are entered; everything else, the weights' bytes included, is skipped
by its length. A file that does not parse is refused too: what is not read cannot be vouched for.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import NamedTuple

# Wire types (protobuf encoding): varint, 64-bit, length-delimited, group start, group end, 32-bit.
VARINT, FIXED64, LENGTH, GROUP_START, GROUP_END, FIXED32 = 0, 1, 2, 3, 4, 5
# onnx.proto's field numbers, per message, of the fields that lead to a TensorProto.
MODEL_FIELDS = {7: "graph", 20: "training_info", 25: "function"}
TRAINING_INFO_FIELDS = {1: "graph", 2: "graph"}  # initialization, algorithm
GRAPH_FIELDS = {1: "node", 5: "tensor", 15: "sparse_tensor"}  # node, initializer, sparse_initializer
FUNCTION_FIELDS = {7: "node", 11: "attribute"}  # node, attribute_proto (default attribute values)
NODE_FIELDS = {5: "attribute"}
ATTRIBUTE_FIELDS = {5: "tensor", 6: "graph", 10: "tensor", 11: "graph", 22: "sparse_tensor", 23: "sparse_tensor"}
SPARSE_TENSOR_FIELDS = {1: "tensor", 2: "tensor"}  # values, indices
MESSAGES = {"model": MODEL_FIELDS, "training_info": TRAINING_INFO_FIELDS, "graph": GRAPH_FIELDS,
            "function": FUNCTION_FIELDS, "node": NODE_FIELDS, "attribute": ATTRIBUTE_FIELDS,
            "sparse_tensor": SPARSE_TENSOR_FIELDS}
TENSOR_NAME, TENSOR_EXTERNAL_DATA, TENSOR_DATA_LOCATION = 8, 13, 14
ENTRY_KEY, ENTRY_VALUE = 1, 2  # StringStringEntryProto
EXTERNAL = 1  # TensorProto.DataLocation.EXTERNAL
# How deep messages may nest: protobuf's own parser stops at 100 (its default recursion limit), so ONNX Runtime
# refuses a deeper file anyway; here the walk is a loop, and the bound keeps its stack small.
MAX_DEPTH = 100


class WireError(ValueError):
    """The bytes are not a protobuf message (a field runs past its end, an unknown wire type, too deep)."""


@dataclass(frozen=True)
class ExternalTensor:
    """A tensor whose data is kept in another file: its name and the ``location`` it names ('' when none)."""

    name: str
    location: str


class Field(NamedTuple):
    """One field of a message: its number and wire type, a varint's ``value``, a length-delimited field's bytes
    as the span ``data[start:end]``."""

    number: int
    wire: int
    value: int = 0
    start: int = 0
    end: int = 0


def _varint(data: bytes, pos: int, end: int) -> tuple[int, int]:
    """The varint at ``pos`` and the position after it."""
    value = shift = 0
    start = pos
    while pos < end:
        if shift >= 70:  # protobuf's varints take at most 10 bytes
            raise WireError(f"the varint at byte {start} is longer than 10 bytes")
        byte = data[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            return value, pos
        shift += 7
    raise WireError(f"the varint at byte {start} runs past its message")


def _fields(data: bytes, start: int, end: int) -> Iterator[Field]:
    """Each varint and length-delimited field of the message in ``data[start:end]``; the other wire types are
    skipped."""
    pos = start
    while pos < end:
        at = pos
        key, pos = _varint(data, pos, end)
        number, wire = key >> 3, key & 7
        if wire == VARINT:
            value, pos = _varint(data, pos, end)
            yield Field(number, wire, value=value)
        elif wire == LENGTH:
            size, pos = _varint(data, pos, end)
            if size > end - pos:
                raise WireError(f"field {number} at byte {at} is {size} bytes long, past the end of its message")
            yield Field(number, wire, start=pos, end=pos + size)
            pos += size
        elif wire in (FIXED64, FIXED32):
            pos += 8 if wire == FIXED64 else 4
            if pos > end:
                raise WireError(f"field {number} at byte {at} runs past the end of its message")
        elif wire == GROUP_START:
            pos = _skip_group(data, pos, end, number)
        else:  # a group's end without its start, or the unused wire types 6 and 7
            raise WireError(f"field {number} at byte {at} has wire type {wire}")


def _skip_group(data: bytes, pos: int, end: int, number: int) -> int:
    """The position after the (deprecated, but valid) group field ``number`` whose contents start at ``pos``."""
    open_groups = [number]
    while open_groups:
        if pos >= end:
            raise WireError(f"group field {number} is not closed")
        at = pos
        key, pos = _varint(data, pos, end)
        inner, wire = key >> 3, key & 7
        if wire == VARINT:
            _, pos = _varint(data, pos, end)
        elif wire == LENGTH:
            size, pos = _varint(data, pos, end)
            pos += size
        elif wire in (FIXED64, FIXED32):
            pos += 8 if wire == FIXED64 else 4
        elif wire == GROUP_START:
            open_groups.append(inner)
        elif wire == GROUP_END and inner == open_groups[-1]:
            open_groups.pop()
        else:
            raise WireError(f"field {inner} at byte {at} has wire type {wire} inside group field {number}")
        if len(open_groups) > MAX_DEPTH:
            raise WireError(f"groups nest deeper than {MAX_DEPTH}")
    if pos > end:
        raise WireError(f"group field {number} runs past the end of its message")
    return pos


def _external(data: bytes, start: int, end: int) -> ExternalTensor | None:
    """The TensorProto in ``data[start:end]`` as an ExternalTensor when it keeps its data in another file."""
    name, location, external = "", "", False
    for field in _fields(data, start, end):
        if field.number == TENSOR_NAME and field.wire == LENGTH:
            name = data[field.start:field.end].decode("utf-8", "replace")
        elif field.number == TENSOR_DATA_LOCATION and field.wire == VARINT:
            external = external or field.value == EXTERNAL
        elif field.number == TENSOR_EXTERNAL_DATA and field.wire == LENGTH:
            # Entries without data_location = EXTERNAL are ignored by ONNX Runtime, but no exporter writes them
            # for a tensor it keeps inside: refused as well.
            external = True
            entry = {item.number: data[item.start:item.end].decode("utf-8", "replace")
                     for item in _fields(data, field.start, field.end) if item.wire == LENGTH}
            if entry.get(ENTRY_KEY) == "location":  # the last one, as ONNX Runtime reads the entries
                location = entry.get(ENTRY_VALUE, "")
    return ExternalTensor(name, location) if external else None


def external_tensors(data: bytes) -> list[ExternalTensor]:
    """Every tensor of the ONNX model ``data`` (a serialized ModelProto) that keeps its data in another file:
    initializers, sparse ones, Constant nodes' and other attributes' tensors, in subgraphs and functions too.

    Raises WireError when ``data`` is not a protobuf message."""
    found: list[ExternalTensor] = []
    stack = [("model", 0, len(data), 0)]  # (message kind, start, end, depth)
    while stack:
        kind, start, end, depth = stack.pop()
        if kind == "tensor":
            tensor = _external(data, start, end)
            if tensor is not None:
                found.append(tensor)
            continue
        fields = MESSAGES[kind]
        inside = [(fields[field.number], field.start, field.end, depth + 1)
                  for field in _fields(data, start, end) if field.number in fields and field.wire == LENGTH]
        if inside and depth + 1 > MAX_DEPTH:
            raise WireError(f"messages nest deeper than {MAX_DEPTH}")
        stack.extend(reversed(inside))  # popped in the file's order
    return found
