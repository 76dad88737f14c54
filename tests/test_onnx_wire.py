"""pipeline/onnx_wire.py: which tensors of an ONNX file keep their data in another file, read from the bytes without
onnx. Each graph here is built with onnx itself and serialized by protobuf, so the reader is held to the real
encoding; the shipped models are read whole, and onnx's own walk over a model's tensors is the reference."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper
from onnx.external_data_helper import _get_all_tensors, convert_model_to_external_data, uses_external_data

from pipeline.onnx_wire import (
    ENTRY_KEY,
    ENTRY_VALUE,
    EXTERNAL,
    MAX_DEPTH,
    MESSAGES,
    TENSOR_DATA_LOCATION,
    TENSOR_EXTERNAL_DATA,
    TENSOR_NAME,
    ExternalTensor,
    WireError,
    external_tensors,
)

REPO = Path(__file__).resolve().parents[1]
SHIPPED = sorted(REPO.glob("weights/*/*.onnx"))


def external(tensor: TensorProto, location: str) -> TensorProto:
    """``tensor`` with its data moved out to ``location``, as onnx.save_model(save_as_external_data=True) writes."""
    size = len(tensor.raw_data)
    tensor.ClearField("raw_data")
    tensor.data_location = TensorProto.EXTERNAL
    for key, value in (("location", location), ("offset", "0"), ("length", str(size))):
        entry = tensor.external_data.add()
        entry.key, entry.value = key, value
    return tensor


def weight(name: str) -> TensorProto:
    return numpy_helper.from_array(np.arange(6, dtype=np.float32).reshape(2, 3), name)


def model(nodes: list, initializers: list | None = None, functions: list | None = None,
          sparse: list | None = None) -> onnx.ModelProto:
    """A graph from x to y of ``nodes``, serialized as any exporter would."""
    graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [2, 3])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [2, 3])],
                              initializer=initializers or [], sparse_initializer=sparse or [])
    opsets = [helper.make_opsetid("", 17)] + ([helper.make_opsetid("local", 1)] if functions else [])
    return helper.make_model(graph, opset_imports=opsets, functions=functions or [])


def constant(output: str, tensor: TensorProto) -> onnx.NodeProto:
    return helper.make_node("Constant", [], [output], value=tensor)


def test_the_field_numbers_are_onnx_protos() -> None:
    """Every field number the reader follows is the one onnx's own generated classes carry, for the message
    the reader takes it to lead to."""
    protos = {"model": onnx.ModelProto, "training_info": onnx.TrainingInfoProto, "graph": onnx.GraphProto,
              "function": onnx.FunctionProto, "node": onnx.NodeProto, "attribute": onnx.AttributeProto,
              "sparse_tensor": onnx.SparseTensorProto, "tensor": onnx.TensorProto}
    assert set(MESSAGES) == set(protos) - {"tensor"}
    for kind, fields in MESSAGES.items():
        by_number = protos[kind].DESCRIPTOR.fields_by_number
        for number, inner in fields.items():
            assert by_number[number].message_type is protos[inner].DESCRIPTOR, (kind, number)
    tensor = onnx.TensorProto.DESCRIPTOR.fields_by_name
    assert (tensor["name"].number, tensor["external_data"].number, tensor["data_location"].number) == (
        TENSOR_NAME, TENSOR_EXTERNAL_DATA, TENSOR_DATA_LOCATION)
    entry = onnx.StringStringEntryProto.DESCRIPTOR.fields_by_name
    assert (entry["key"].number, entry["value"].number) == (ENTRY_KEY, ENTRY_VALUE)
    assert TensorProto.EXTERNAL == EXTERNAL


def test_every_field_that_holds_a_tensor_or_a_graph_is_followed() -> None:
    """The other way round: no field of these messages that holds a graph, a tensor or a message leading to one
    is left out (a new onnx release adding one would fail here, not pass a tensor by)."""
    leads = {onnx.GraphProto.DESCRIPTOR, onnx.TensorProto.DESCRIPTOR, onnx.SparseTensorProto.DESCRIPTOR,
             onnx.NodeProto.DESCRIPTOR, onnx.AttributeProto.DESCRIPTOR, onnx.FunctionProto.DESCRIPTOR,
             onnx.TrainingInfoProto.DESCRIPTOR}
    protos = {"model": onnx.ModelProto, "training_info": onnx.TrainingInfoProto, "graph": onnx.GraphProto,
              "function": onnx.FunctionProto, "node": onnx.NodeProto, "attribute": onnx.AttributeProto,
              "sparse_tensor": onnx.SparseTensorProto}
    for kind, proto in protos.items():
        holding = {f.number for f in proto.DESCRIPTOR.fields if f.message_type in leads}
        assert holding == set(MESSAGES[kind]), kind


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_the_shipped_graphs_keep_everything_inside(path: Path) -> None:
    assert external_tensors(path.read_bytes()) == []


@pytest.mark.parametrize("path", SHIPPED[:2], ids=lambda p: f"{p.parent.name}/{p.name}")
def test_a_shipped_graph_moved_out_whole_is_read_as_onnx_reads_it(path: Path) -> None:
    """Every tensor onnx moves out (initializers and attribute tensors, size threshold 0) is found, in order."""
    graph = onnx.load(str(path))
    convert_model_to_external_data(graph, all_tensors_to_one_file=True, location="weights.bin", size_threshold=0)
    expected = [t.name for t in _get_all_tensors(graph) if uses_external_data(t)]
    found = external_tensors(graph.SerializeToString())
    assert len(expected) > 50
    assert sorted(t.name for t in found) == sorted(expected)
    assert {t.location for t in found} == {"weights.bin"}


def test_an_initializer_kept_outside_is_found_with_its_location() -> None:
    inside, outside = weight("inside"), external(weight("outside"), "/etc/lowres3d/w.bin")
    graph = model([helper.make_node("Add", ["x", "outside"], ["y"])], initializers=[inside, outside])
    assert external_tensors(graph.SerializeToString()) == [ExternalTensor("outside", "/etc/lowres3d/w.bin")]


def test_tensors_are_given_in_the_files_order_with_their_last_location() -> None:
    """The error names the first; ONNX Runtime takes a repeated key's last value."""
    first, second = external(weight("first"), "a.bin"), external(weight("second"), "b.bin")
    second.external_data.add(key="location", value="c.bin")
    graph = model([helper.make_node("Add", ["x", "first"], ["y"])], initializers=[weight("inside"), first, second])
    assert external_tensors(graph.SerializeToString()) == [ExternalTensor("first", "a.bin"),
                                                          ExternalTensor("second", "c.bin")]


def test_a_constants_sparse_value_kept_outside_is_found() -> None:
    values = external(numpy_helper.from_array(np.ones(2, np.float32), "sparse_constant"), "k.bin")
    sparse = helper.make_sparse_tensor(values, numpy_helper.from_array(np.array([0, 4], np.int64), "at"), [2, 3])
    node = helper.make_node("Constant", [], ["k"], sparse_value=sparse)
    graph = model([node, helper.make_node("Add", ["x", "k"], ["y"])])
    assert external_tensors(graph.SerializeToString()) == [ExternalTensor("sparse_constant", "k.bin")]


def test_a_constant_in_a_subgraph_of_a_subgraph_is_found() -> None:
    """An If's branch holding a Loop-free If whose branch holds a Constant node: attributes' graphs are entered."""
    def branch(name: str, node: onnx.NodeProto) -> onnx.GraphProto:
        return helper.make_graph([node], name, [], [helper.make_tensor_value_info(node.output[0], TensorProto.FLOAT,
                                                                                   [2, 3])])
    deep = constant("c", external(weight("deep"), "deep.bin"))
    inner = helper.make_node("If", ["cond"], ["i"], then_branch=branch("t2", deep),
                             else_branch=branch("e2", constant("c2", weight("plain"))))
    outer = helper.make_node("If", ["cond"], ["y"], then_branch=branch("t1", inner),
                             else_branch=branch("e1", constant("c3", weight("plain2"))))
    cond = numpy_helper.from_array(np.array(True), "cond")
    graph = model([outer], initializers=[cond])
    assert external_tensors(graph.SerializeToString()) == [ExternalTensor("deep", "deep.bin")]


def test_a_constant_in_a_function_body_is_found() -> None:
    body = [constant("k", external(weight("in_function"), "f.bin")), helper.make_node("Add", ["a", "k"], ["b"])]
    function = helper.make_function("local", "AddK", ["a"], ["b"], body, [helper.make_opsetid("", 17)])
    graph = model([helper.make_node("AddK", ["x"], ["y"], domain="local")], functions=[function])
    assert external_tensors(graph.SerializeToString()) == [ExternalTensor("in_function", "f.bin")]


def test_a_functions_default_attribute_tensor_is_found() -> None:
    """A function's attribute defaults (IR 9) may be tensors, used wherever a call leaves the attribute out."""
    body = [helper.make_node("Constant", [], ["k"], value_float=1.0), helper.make_node("Add", ["a", "k"], ["b"])]
    default = helper.make_attribute("bias", external(weight("default"), "d.bin"))
    function = helper.make_function("local", "AddK", ["a"], ["b"], body, [helper.make_opsetid("", 17)],
                                    attribute_protos=[default])
    graph = model([helper.make_node("AddK", ["x"], ["y"], domain="local")], functions=[function])
    assert external_tensors(graph.SerializeToString()) == [ExternalTensor("default", "d.bin")]


@pytest.mark.parametrize("outside", ["sparse_values", "sparse_indices"])
def test_a_sparse_initializers_tensors_kept_outside_are_found(outside: str) -> None:
    """onnx's own walk leaves sparse initializers out; ONNX Runtime reads their tensors from a file all the same."""
    values = numpy_helper.from_array(np.ones(2, np.float32), "sparse_values")
    indices = numpy_helper.from_array(np.array([0, 4], np.int64), "sparse_indices")
    external(values if outside == "sparse_values" else indices, "s.bin")
    sparse = helper.make_sparse_tensor(values, indices, [2, 3])
    graph = model([helper.make_node("Add", ["x", "sparse_values"], ["y"])], sparse=[sparse])
    assert external_tensors(graph.SerializeToString()) == [ExternalTensor(outside, "s.bin")]


@pytest.mark.parametrize("half", ["entries alone", "data_location alone"])
def test_half_of_an_external_tensor_is_refused_too(half: str) -> None:
    """ONNX Runtime reads a file for data_location = EXTERNAL; entries without it are no exporter's output."""
    tensor = external(weight("w"), "w.bin")
    if half == "entries alone":
        tensor.ClearField("data_location")
        expected = ExternalTensor("w", "w.bin")
    else:
        tensor.ClearField("external_data")
        expected = ExternalTensor("w", "")
    graph = model([helper.make_node("Add", ["x", "w"], ["y"])], initializers=[tensor])
    assert external_tensors(graph.SerializeToString()) == [expected]


def test_unknown_fields_of_every_wire_type_are_skipped() -> None:
    """A newer exporter's fields (here a varint, a fixed64, a fixed32 and a nested group, appended to the graph's
    bytes) parse with protobuf, and the external tensor after them is still found."""
    graph = model([helper.make_node("Add", ["x", "w"], ["y"])], initializers=[external(weight("w"), "w.bin")])
    unknown = bytes([0xF8, 0x06, 0x2A,  # field 111, varint 42
                     0xF9, 0x06]) + bytes(8) + bytes([0xFD, 0x06]) + bytes(4) + bytes(  # 111 fixed64, fixed32
        [0xFB, 0x06, 0x83, 0x07, 0x08, 0x01, 0x84, 0x07, 0xFC, 0x06])  # group 111 { group 112 { field 1: 1 } }
    data = unknown + graph.SerializeToString()
    assert onnx.load_from_string(data).graph.initializer[0].name == "w"  # protobuf itself accepts these bytes
    assert external_tensors(data) == [ExternalTensor("w", "w.bin")]


@pytest.mark.parametrize(("bytes_", "says"), [
    (b"\x3a\xff\xff\xff\xff\x0f", "past the end of its message"),  # graph field of 4 GB in a 6-byte file
    (b"\x3a\x05\x2a\x01", "field 7 at byte 0 is 5 bytes long, past the end"),
    (b"\x3a", "runs past its message"),  # a key without its length
    (b"\x08\xff\xff", "the varint at byte 1 runs past its message"),  # a varint cut off
    (b"\x08" + b"\x80" * 10 + b"\x00", "longer than 10 bytes"),
    (b"\x0f", "wire type 7"),
    (b"\x0c", "wire type 4"),  # a group's end without its start
    (b"\x0b\x10\x01", "not closed"),
    (b"\x0b\x14", "field 2 at byte 1 has wire type 4 inside group field 1"),  # group 1 closed as group 2
    (b"\x09\x00\x00", "field 1 at byte 0 runs past the end"),  # a fixed64 of 2 bytes
    (b"Protobuf? No, a text file", "wire type"),
])
def test_bytes_that_are_no_protobuf_are_refused(bytes_: bytes, says: str) -> None:
    with pytest.raises(WireError, match=says):
        external_tensors(bytes_)


def test_graphs_nested_deeper_than_protobuf_allows_are_refused_without_recursion() -> None:
    """Subgraphs nested 200 deep (protobuf's own parser stops at 100): refused in one line, no RecursionError."""
    data = b""
    for _ in range(200):  # graph { node { attribute { g { ... } } } }: each level three messages deep
        attribute = b"\x32" + _length(len(data)) + data  # AttributeProto.g = 6
        node = b"\x2a" + _length(len(attribute)) + attribute  # NodeProto.attribute = 5
        data = b"\x0a" + _length(len(node)) + node  # GraphProto.node = 1
    top = b"\x3a" + _length(len(data)) + data  # ModelProto.graph = 7
    with pytest.raises(WireError, match=f"deeper than {MAX_DEPTH}"):
        external_tensors(top)


def _length(size: int) -> bytes:
    """``size`` as a protobuf varint."""
    out = bytearray()
    while True:
        out.append((size & 0x7F) | (0x80 if size > 0x7F else 0))
        size >>= 7
        if not size:
            return bytes(out)
