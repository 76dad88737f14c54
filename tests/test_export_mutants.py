"""The export stage's graph rewrites (export/rewrite.py, export/lower.py, export/fp16.py), pinned edge by edge.

Each test here was written against a mutant of those modules that the other export tests let through
(a mutation audit of the export stage): a dropped attribute check, an off-by-one in the channel padding, a swapped
phase table, a guard removed. The rewrites change trained graphs, so a wrong one silently changes what runs
on a vehicle; every test compares ONNX Runtime's outputs of the rewritten graph with the original's, or the
exact graph structure a rewrite must leave (what it must not touch). The graphs are built by hand with
onnx.helper and are a few KiB each, so the whole file runs in seconds; export.lower runs on a copy of the
shipped LiDAR-only PIXOR directory.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper, numpy_helper

from export import fp16, rewrite
from export.lower import run as lower_run
from pipeline.model_files import ModelFileError, sha256_file
from tests.conftest import KITTI

LIDAR16 = KITTI.parents[3] / "weights" / "edge-lidar16"
CONV3 = {"kernel_shape": [3, 3], "pads": [1, 1, 1, 1]}


def _init(name: str, array: np.ndarray) -> onnx.TensorProto:
    return numpy_helper.from_array(array, name)


def _random(name: str, shape: tuple[int, ...], seed: int = 0) -> onnx.TensorProto:
    """A float32 initializer with distinct values (no symmetry a swapped axis could hide behind)."""
    return _init(name, np.random.default_rng(seed).standard_normal(shape).astype(np.float32))


def _value(name: str, shape: list[int] | None, elem: int = TensorProto.FLOAT) -> onnx.ValueInfoProto:
    return helper.make_tensor_value_info(name, elem, shape)


def _model(nodes: list[onnx.NodeProto], inputs: list[onnx.ValueInfoProto], outputs: list[onnx.ValueInfoProto],
           inits: list[onnx.TensorProto], opset: int = 18) -> onnx.ModelProto:
    graph = helper.make_graph(nodes, "g", inputs, outputs, inits)
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)], ir_version=8)


def _run(model: onnx.ModelProto, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
    """ONNX Runtime's outputs of a checked graph."""
    onnx.checker.check_model(model, full_check=True)
    session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    return session.run(None, feeds)


def _same_outputs(before: onnx.ModelProto, after: onnx.ModelProto, feeds: dict[str, np.ndarray],
                  tolerance: float = 1e-5) -> None:
    for a, b in zip(_run(before, feeds), _run(after, feeds), strict=True):
        assert a.shape == b.shape
        np.testing.assert_allclose(b, a, rtol=tolerance, atol=tolerance * max(1.0, float(np.abs(a).max())))


def _ops(model: onnx.ModelProto) -> list[str]:
    return [node.op_type for node in model.graph.node]


# ----------------------------------------------------------------------------------- 1. transposed convs
def _transposed(c_in: int = 3, c_out: int = 5, bias: str | None = "b", weight_input: bool = False,
                bias_input: bool = False, **attrs) -> onnx.ModelProto:
    """x (1, c_in, 6, 7) → ConvTranspose (3×3 kernel, ``attrs``) → y, with its output shape inferred."""
    group = attrs.get("group", 1)
    inits, inputs = [], [_value("x", [1, c_in, 6, 7])]
    weight = _random("w", (c_in, c_out // group, 3, 3), seed=1)
    (inputs.append(_value("w", list(weight.dims))) if weight_input else inits.append(weight))
    names = ["x", "w"]
    if bias is not None:
        names.append(bias)
        if bias:
            b = _random(bias, (c_out,), seed=2)
            (inputs.append(_value(bias, [c_out])) if bias_input else inits.append(b))
    node = helper.make_node("ConvTranspose", names, ["y"], name="up", kernel_shape=[3, 3], **attrs)
    model = _model([node], inputs, [_value("y", None)], inits)
    inferred = onnx.shape_inference.infer_shapes(model)
    model.graph.output[0].CopyFrom(inferred.graph.output[0])
    return model


def _feeds(model: onnx.ModelProto, seed: int = 3) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {v.name: rng.standard_normal([d.dim_value for d in v.type.tensor_type.shape.dim]).astype(np.float32)
            for v in model.graph.input}


@pytest.mark.parametrize("subpixel", [True, False])
@pytest.mark.parametrize(("strides", "output_padding"), [([1, 1], [0, 0]), ([2, 2], [1, 1])])
@pytest.mark.parametrize("bias", ["b", None, ""])
def test_transposed_convs_become_convs_with_the_same_outputs(subpixel, strides, output_padding, bias):
    """3 → 5 channels on a 6 × 7 map (no square or channel symmetry to hide a swapped axis), with a bias or
    without one (no third input, or ONNX's "" for an omitted one): the stride-1 form as a flipped conv, the
    stride-2 one (with ``subpixel``) as
    a 2×2 conv and DepthToSpace; ONNX Runtime gives the same outputs, and the old weights are gone."""
    model = _transposed(bias=bias, strides=strides, pads=[1, 1, 1, 1], output_padding=output_padding)
    rewritten, count = rewrite.rewrite_transposed_convs(model, subpixel=subpixel)
    expected = 1 if strides == [1, 1] or subpixel else 0
    assert count == expected
    if expected:
        assert _ops(rewritten) == (["Conv"] if strides == [1, 1] else ["Conv", "DepthToSpace"])
        assert "w" not in {init.name for init in rewritten.graph.initializer}
    else:
        assert _ops(rewritten) == ["ConvTranspose"]
    _same_outputs(model, rewritten, _feeds(model))


@pytest.mark.parametrize("attrs", [
    {"group": 5, "strides": [1, 1]},  # 5 → 5 channels, one per group
    {"dilations": [2, 2], "strides": [1, 1]},
    {"auto_pad": "SAME_UPPER", "strides": [1, 1]},
    {"pads": [0, 0, 0, 0], "strides": [1, 1]},
    {"pads": [1, 1, 1, 1], "strides": [2, 2]},  # no output padding: (2i − 1) rows, not the sub-pixel form's 2i
    {"pads": [1, 1, 1, 1], "strides": [1, 1], "weight_input": True},
    {"pads": [1, 1, 1, 1], "strides": [1, 1], "bias_input": True},
], ids=["group", "dilations", "auto_pad", "no_pads", "no_output_padding", "weight_input", "bias_input"])
def test_transposed_convs_of_other_forms_stay(attrs):
    """A ConvTranspose the rewrite has no exact form for stays as it is (and ONNX Runtime still runs it)."""
    attrs = {"pads": [1, 1, 1, 1], **attrs} if "auto_pad" not in attrs else attrs
    c = 5 if attrs.get("group") else 3
    model = _transposed(c_in=c, **attrs)
    rewritten, count = rewrite.rewrite_transposed_convs(model)
    assert count == 0 and _ops(rewritten) == ["ConvTranspose"]
    _same_outputs(model, rewritten, _feeds(model))


# ----------------------------------------------------------------------------------- 2. and 7. input convs
def _input_conv(channels: int, group: int = 1, out: int = 16) -> onnx.ModelProto:
    """x (1, channels, 8, 6) → Conv "stem" (3×3, stride 2, ``group``) → y."""
    inits = [_random("w", (out, channels // group, 3, 3)), _random("b", (out,), seed=1)]
    node = helper.make_node("Conv", ["x", "w", "b"], ["y"], name="stem", group=group, strides=[2, 2], **CONV3)
    return _model([node], [_value("x", [1, channels, 8, 6])], [_value("y", [1, out, 4, 3])], inits)


def test_grouped_input_convs_are_neither_split_nor_padded():
    """A grouped conv's weights hold C/group input channels: slicing or padding the input by them would mix the
    groups, so a 38-channel group-2 conv (19 per group) is left whole and unpadded."""
    model = _input_conv(38, group=2)
    for lowered, count in (rewrite.split_input_convs(model), rewrite.pad_input_convs(model)):
        assert count == 0 and _ops(lowered) == ["Conv"]
    assert rewrite.pad_input_convs(_input_conv(6, group=2, out=4))[1] == 0  # 3 per group, 6 in all


@pytest.mark.parametrize(("channels", "padded_to"), [(17, 20), (18, 20), (19, 20), (21, 24)])
def test_input_convs_are_padded_to_the_next_multiple_of_four_with_zero_channels(channels, padded_to):
    """The Pad adds exactly the missing channels after the last one, as constant zeros (quantize_before_pad moves
    only constant Pads), and the weights get as many zero input channels: the same outputs."""
    model = _input_conv(channels)
    padded, count = rewrite.pad_input_convs(model)
    assert count == 1 and _ops(padded) == ["Pad", "Conv"]
    pad = padded.graph.node[0]
    inits = {init.name: numpy_helper.to_array(init) for init in padded.graph.initializer}
    assert inits[pad.input[1]].tolist() == [0, 0, 0, 0, 0, padded_to - channels, 0, 0]
    assert {a.name: helper.get_attribute_value(a) for a in pad.attribute} == {"mode": b"constant"}
    weight = inits[padded.graph.node[1].input[1]]
    assert weight.shape == (16, padded_to, 3, 3) and not weight[:, channels:].any()
    _same_outputs(model, padded, _feeds(model))


def test_merging_a_split_input_conv_back_checks_the_group_it_merges():
    """A skipped Add (or Slice) keeps its group apart, and an Add that no longer sums the two convs is no split
    conv: merging it would drop what it adds."""
    model = _input_conv(19)
    split, _ = rewrite.split_input_convs(model)
    for skipped in ("stem_sum", "stem_slice_b"):
        assert rewrite.merge_split_input_convs(split, skip=frozenset({skipped}))[1] == 0
    tampered = onnx.ModelProto.FromString(split.SerializeToString())
    add = next(n for n in tampered.graph.node if n.name == "stem_sum")
    add.input[1] = "stem_ya"  # 2·(first conv): the second conv's output is no longer added
    merged, count = rewrite.merge_split_input_convs(tampered)
    assert count == 0
    _same_outputs(tampered, merged, _feeds(model))


# ----------------------------------------------------------------------------------- quantize_before_pad
def _pad_quantize(pad_inputs: tuple[str, ...] = ("x", "pads"), zero_point: bool = True,
                  per_channel: bool = False, extra_reader: bool = False, reader: str = "QuantizeLinear"
                  ) -> onnx.ModelProto:
    """x (1, 3, 5, 7) → Pad (one channel after) → QuantizeLinear (scale 0.02, zero point 37) → DequantizeLinear."""
    scale = np.full(4, 0.02, np.float32) if per_channel else np.array(0.02, np.float32)
    zp = np.full(4, 37, np.uint8) if per_channel else np.array(37, np.uint8)
    inits = [_init("pads", np.array([0, 0, 0, 0, 0, 1, 0, 0], np.int64)), _init("s", scale), _init("z", zp),
             _init("fill", np.array(1.5, np.float32))]
    qz = ["xp", "s", "z"] if zero_point else ["xp", "s"]
    axis = {"axis": 1} if per_channel else {}
    nodes = [helper.make_node("Pad", list(pad_inputs), ["xp"], name="pad", mode="constant")]
    outputs = [_value("out", [1, 4, 5, 7])]
    if reader == "QuantizeLinear":
        nodes += [helper.make_node("QuantizeLinear", qz, ["q"], name="q", **axis),
                  helper.make_node("DequantizeLinear", ["q", *qz[1:]], ["out"], name="dq", **axis)]
    else:
        nodes.append(helper.make_node(reader, ["xp"], ["out"], name="other"))
    if extra_reader:
        nodes.append(helper.make_node("Relu", ["xp"], ["relu"], name="relu"))
        outputs.append(_value("relu", [1, 4, 5, 7]))
    return _model(nodes, [_value("x", [1, 3, 5, 7])], outputs, inits)


@pytest.mark.parametrize("case", ["pad_value", "second_reader", "per_channel", "not_quantized"])
def test_pads_that_cannot_move_behind_their_quantize_stay(case):
    """A Pad with its own pad value (1.5 is not q(0)), one read by something besides its QuantizeLinear, one
    before a per-channel QuantizeLinear, or one read by another op stays where it is."""
    model = {"pad_value": lambda: _pad_quantize(pad_inputs=("x", "pads", "fill")),
             "second_reader": lambda: _pad_quantize(extra_reader=True),
             "per_channel": lambda: _pad_quantize(per_channel=True),
             "not_quantized": lambda: _pad_quantize(reader="Relu")}[case]()
    moved, count = rewrite.quantize_before_pad(model)
    assert count == 0 and _ops(moved) == _ops(model)
    x = {"x": np.random.default_rng(0).uniform(-0.7, 4.0, (1, 3, 5, 7)).astype(np.float32)}
    for a, b in zip(_run(model, x), _run(moved, x), strict=True):
        np.testing.assert_array_equal(b, a)


def test_a_pad_before_a_quantize_without_zero_point_moves_and_pads_with_zero():
    """QuantizeLinear's zero point is optional (default uint8 0): the moved Pad pads with 0 then, exactly
    q(0). quantize_before_pad used to fail on such a graph with an IndexError."""
    model = _pad_quantize(zero_point=False)
    moved, count = rewrite.quantize_before_pad(model)
    assert count == 1 and _ops(moved) == ["QuantizeLinear", "Pad", "DequantizeLinear"]
    x = {"x": np.random.default_rng(1).uniform(0, 4.0, (1, 3, 5, 7)).astype(np.float32)}
    np.testing.assert_array_equal(_run(moved, x)[0], _run(model, x)[0])


# ----------------------------------------------------------------------------------- 3. narrow convs
def _narrow(first: int = 8, activation: str | None = "Relu", first_output: bool = False,
            activation_output: bool = False, shared_weight: bool = False, group: int = 1) -> onnx.ModelProto:
    """x (1, 8, 6, 5) → Conv (``first`` outputs) → ``activation`` → Conv (4 outputs) → out."""
    inits = [_random("w1", (first, 8 // group, 3, 3)), _random("b1", (first,), seed=1),
             _random("w2", (4, first, 3, 3), seed=2)]
    nodes = [helper.make_node("Conv", ["x", "w1", "b1"], ["a"], name="narrow", group=group, **CONV3)]
    data = "a"
    if activation:
        nodes.append(helper.make_node(activation, ["a"], ["act"], name="act"))
        data = "act"
    nodes.append(helper.make_node("Conv", [data, "w2"], ["out"], name="reader", **CONV3))
    outputs = [_value("out", [1, 4, 6, 5])]
    if first_output:
        outputs.append(_value("a", [1, first, 6, 5]))
    if activation_output:
        outputs.append(_value("act", [1, first, 6, 5]))
    if shared_weight:  # a second narrow conv with the same weights and bias, read by its own conv
        inits.append(_random("w3", (4, first, 3, 3), seed=3))
        nodes += [helper.make_node("Conv", ["x", "w1", "b1"], ["a2"], name="twin", **CONV3),
                  helper.make_node("Conv", ["a2", "w3"], ["out2"], name="reader2", **CONV3)]
        outputs.append(_value("out2", [1, 4, 6, 5]))
    return _model(nodes, [_value("x", [1, 8, 6, 5])], outputs, inits)


@pytest.mark.parametrize("case", ["block_wide", "sigmoid", "activation_output", "conv_output", "shared_weight",
                                  "grouped"])
def test_narrow_convs_are_padded_only_where_nothing_sees_the_zero_channels(case):
    """A 16-wide conv needs nothing; a Sigmoid turns zero channels into 0.5; a graph output (the conv's or its
    activation's) would change shape; weights shared with another conv cannot grow for one alone; a grouped
    conv's output channels belong to groups. Each stays as it is, with the same outputs."""
    model = {"block_wide": lambda: _narrow(first=16), "sigmoid": lambda: _narrow(activation="Sigmoid"),
             "activation_output": lambda: _narrow(activation_output=True),
             "conv_output": lambda: _narrow(activation=None, first_output=True),
             "shared_weight": lambda: _narrow(shared_weight=True), "grouped": lambda: _narrow(group=2)}[case]()
    padded, count = rewrite.pad_narrow_convs(model)
    assert count == 0
    assert ({i.name: tuple(i.dims) for i in padded.graph.initializer}
            == {i.name: tuple(i.dims) for i in model.graph.initializer})
    _same_outputs(model, padded, _feeds(model))


def test_a_narrow_conv_read_through_a_relu_is_padded_to_the_block():
    model = _narrow()
    padded, count = rewrite.pad_narrow_convs(model)
    dims = {i.name: tuple(i.dims) for i in padded.graph.initializer}
    assert count == 1 and dims == {"w1": (16, 8, 3, 3), "b1": (16,), "w2": (4, 16, 3, 3)}
    _same_outputs(model, padded, _feeds(model))


# ----------------------------------------------------------------------------------- 5. Where as arithmetic
def _where(branch: str, minimum: float = 1e-3, elem: int = TensorProto.FLOAT) -> onnx.ModelProto:
    """Where(x > 0, ``branch``, 0) on x (1, 1, 4, 5): ``branch`` is "reciprocal" (1/clip(x, minimum)), "div"
    (x / y), "max" (max(x, 1/x)), or "int" (int64 constants on both sides)."""
    shape = [1, 1, 4, 5]
    inits = [_init("zero", np.array(0, np.float32)), _init("low", np.array(minimum, np.float32)),
             _init("zeros", np.zeros(shape, np.float32))]
    nodes = [helper.make_node("Greater", ["x", "zero"], ["measured"])]
    inputs = [_value("x", shape)]
    if branch == "reciprocal":
        nodes += [helper.make_node("Clip", ["x", "low"], ["c"]), helper.make_node("Reciprocal", ["c"], ["a"])]
    elif branch == "div":
        nodes.append(helper.make_node("Div", ["x", "y"], ["a"]))
        inputs.append(_value("y", shape))
    elif branch == "max":
        nodes += [helper.make_node("Reciprocal", ["x"], ["r"]), helper.make_node("Max", ["x", "r"], ["a"])]
    if branch == "int":
        inits += [_init("ones_i", np.ones(shape, np.int64)), _init("zeros_i", np.zeros(shape, np.int64))]
        nodes.append(helper.make_node("Where", ["measured", "ones_i", "zeros_i"], ["out"]))
        return _model(nodes, inputs, [_value("out", shape, TensorProto.INT64)], inits)
    nodes.append(helper.make_node("Where", ["measured", "a", "zeros"], ["out"]))
    return _model(nodes, inputs, [_value("out", shape, elem)], inits)


@pytest.mark.parametrize(("branch", "minimum"), [("reciprocal", 0.0), ("reciprocal", -1.0), ("reciprocal", 1e-45),
                                                 ("div", 1e-3),
                                                 ("max", 1e-3), ("int", 1e-3)])
def test_where_stays_where_a_branch_may_be_infinite_or_is_not_float(branch, minimum):
    """1/clip(x, 0), 1/clip(x, −1) and 1/clip(x, 1e-45) are ∞ at x = 0 (the last: 1e45 is beyond float32), x/y and
    max(x, 1/x) may be ∞, and an int64 Where has no float arithmetic form: each Where stays, so ∞·0 never
    makes a NaN. The 1e-45 one used to be rewritten: NaN where x = 0."""
    model = _where(branch, minimum)
    rewritten, count = rewrite.where_as_arithmetic(model)
    assert count == 0 and _ops(rewritten) == _ops(model)
    x = np.array([0, 1, 2, 0, 3] * 4, np.float32).reshape(1, 1, 4, 5)
    feeds = {"x": x, "y": np.where(x > 0, 0.0, 1.0).astype(np.float32)} if branch == "div" else {"x": x}
    out = _run(rewritten, feeds)[0]
    assert not np.isnan(out.astype(np.float64)).any()


def test_where_over_a_clipped_reciprocal_is_rewritten_exactly():
    model = _where("reciprocal", 1e-3)
    rewritten, count = rewrite.where_as_arithmetic(model)
    assert count == 1 and "Where" not in _ops(rewritten)
    x = {"x": np.array([0, 1, 2, 0, 3] * 4, np.float32).reshape(1, 1, 4, 5)}
    np.testing.assert_array_equal(_run(rewritten, x)[0], _run(model, x)[0])


# ----------------------------------------------------------------------------------- 6. parallel convs
def _parallel(axis: int = 1, relu_reader: bool = False, conv_reader: bool = False, group: int = 1
              ) -> onnx.ModelProto:
    """Concat(Relu(Conv(d)), Relu(Conv(i)), ``axis``) with 4 output channels each, on (1, 4, 6, 5) inputs."""
    inits = [_random("wd", (4, 4 // group, 3, 3)), _random("wi", (4, 4 // group, 3, 3), seed=1)]
    nodes = [helper.make_node("Conv", ["d", "wd"], ["cd"], group=group, **CONV3),
             helper.make_node("Relu", ["cd"], ["rd"]),
             helper.make_node("Conv", ["i", "wi"], ["ci"], group=group, **CONV3),
             helper.make_node("Relu", ["ci"], ["ri"]),
             helper.make_node("Concat", ["rd", "ri"], ["fused"], axis=axis)]
    shape = [2, 4, 6, 5] if axis == 0 else [1, 8, 6, 5]
    outputs = [_value("fused", shape)]
    for flag, tensor in ((relu_reader, "rd"), (conv_reader, "cd")):
        if flag:  # read by one more node whose output is a graph output
            nodes.append(helper.make_node("Sigmoid", [tensor], [f"{tensor}_other"]))
            outputs.append(_value(f"{tensor}_other", [1, 4, 6, 5]))
    return _model(nodes, [_value("d", [1, 4, 6, 5]), _value("i", [1, 4, 6, 5])], outputs, inits)


@pytest.mark.parametrize("case", ["batch_axis", "relu_read_elsewhere", "conv_read_elsewhere", "grouped"])
def test_parallel_convs_merge_only_when_nothing_else_needs_them_apart(case):
    """A Concat along the batch, a branch's Relu or Conv output read by another node, and grouped convs (whose
    block-diagonal form is not one group) keep their branches; the outputs are the same."""
    model = {"batch_axis": lambda: _parallel(axis=0), "relu_read_elsewhere": lambda: _parallel(relu_reader=True),
             "conv_read_elsewhere": lambda: _parallel(conv_reader=True),
             "grouped": lambda: _parallel(group=2)}[case]()
    merged, count = rewrite.merge_parallel_convs(model)
    assert count == 0 and _ops(merged) == _ops(model)
    _same_outputs(model, merged, _feeds(model))


# ----------------------------------------------------------------------------------- 8. channel pieces
def _sliced(bounds: list[tuple[int, int, int, int]], channels: int = 6) -> onnx.ModelProto:
    """x (1, channels, 6, 6) read only by Slices (start, end, axis, step), each a graph output."""
    inits, nodes, outputs = [], [], []
    for k, (lo, hi, axis, step) in enumerate(bounds):
        names = [f"s{k}_{p}" for p in ("lo", "hi", "axis", "step")]
        inits += [_init(n, np.array([v], np.int64)) for n, v in zip(names, (lo, hi, axis, step), strict=True)]
        nodes += [helper.make_node("Slice", ["x", *names], [f"piece{k}"]),
                  helper.make_node("Relu", [f"piece{k}"], [f"out{k}"])]
        outputs.append(_value(f"out{k}", None))
    return _model(nodes, [_value("x", [1, channels, 6, 6])], outputs, inits)


@pytest.mark.parametrize("bounds", [
    [(0, 2, 2, 1), (2, 6, 2, 1)],  # along the rows, not the channels
    [(0, 4, 1, 2), (4, 6, 1, 1)],  # every second channel
    [(0, 4, 1, 1)],  # channels 4 and 5 read by nobody: the pieces would not make x
], ids=["rows", "step", "short"])
def test_slices_become_graph_inputs_only_when_they_are_contiguous_channel_ranges_covering_the_input(bounds):
    model = _sliced(bounds)
    pieces, count = rewrite.inputs_from_channel_slices(model)
    assert count == 0 and [i.name for i in pieces.graph.input] == ["x"]


def test_channel_pieces_join_back_only_when_they_tile_the_input():
    """Inputs x[0:16] and x[17:19] leave channel 16 out: they stay two inputs."""
    inputs = [_value("x[0:16]", [1, 16, 4, 4]), _value("x[17:19]", [1, 2, 4, 4])]
    nodes = [helper.make_node("Relu", ["x[0:16]"], ["a"]), helper.make_node("Relu", ["x[17:19]"], ["b"])]
    model = _model(nodes, inputs, [_value("a", [1, 16, 4, 4]), _value("b", [1, 2, 4, 4])], [])
    joined, count = rewrite.inputs_from_channel_pieces(model)
    assert count == 0 and [i.name for i in joined.graph.input] == ["x[0:16]", "x[17:19]"]


# ----------------------------------------------------------------------------------- 9. output heads
def _heads(second_pads: list[int], head_also_read: bool = False, sigmoid_also_read: bool = False
           ) -> onnx.ModelProto:
    """Features f (1, 4, 6, 5) → score head (Conv → Sigmoid → output) and box head (Conv → output)."""
    inits = [_random("ws", (1, 4, 3, 3)), _random("wr", (6, 4, 3, 3), seed=1)]
    nodes = [helper.make_node("Conv", ["f", "ws"], ["s"], name="score_conv", **CONV3),
             helper.make_node("Sigmoid", ["s"], ["score"], name="sigmoid"),
             helper.make_node("Conv", ["f", "wr"], ["boxes"], name="box_conv", kernel_shape=[3, 3], pads=second_pads)]
    out_hw = [6, 5] if second_pads == [1, 1, 1, 1] else [4, 3]
    outputs = [_value("score", [1, 1, 6, 5]), _value("boxes", [1, 6, *out_hw])]
    for flag, tensor in ((head_also_read, "boxes"), (sigmoid_also_read, "score")):
        if flag:
            nodes.append(helper.make_node("Relu", [tensor], [f"{tensor}_relu"]))
            outputs.append(_value(f"{tensor}_relu", [1, 6 if tensor == "boxes" else 1, 6, 5]))
    return _model(nodes, [_value("f", [1, 4, 6, 5])], outputs, inits)


@pytest.mark.parametrize("case", ["other_pads", "head_read_elsewhere", "sigmoid_read_elsewhere"])
def test_output_heads_merge_only_when_alike_and_only_read_as_outputs(case):
    """Heads with other padding produce other shapes; a head (or its Sigmoid) also read inside the graph is
    no output head. Each stays a conv of its own, with the same outputs."""
    model = {"other_pads": lambda: _heads([0, 0, 0, 0]), "head_read_elsewhere": lambda: _heads(
        [1, 1, 1, 1], head_also_read=True), "sigmoid_read_elsewhere": lambda: _heads(
        [1, 1, 1, 1], sigmoid_also_read=True)}[case]()
    merged, count = rewrite.merge_output_heads(model)
    assert count == 0 and _ops(merged) == _ops(model)
    _same_outputs(model, merged, _feeds(model))


# ----------------------------------------------------------------------------------- 4. boundary nodes
def test_boundary_nodes_do_not_start_at_weights_listed_as_graph_inputs():
    """Older ONNX files list initializers among the graph inputs too; the fp32 ends must not start from them
    (every conv reads a weight: all of them would stay fp32)."""
    inits = [_random(f"w{k}", (4, 4, 3, 3), seed=k) for k in range(4)]
    nodes, data = [], "x"
    for k in range(4):
        nodes += [helper.make_node("Conv", [data, f"w{k}"], [f"c{k}"], name=f"conv{k}", **CONV3),
                  helper.make_node("Relu", [f"c{k}"], [f"r{k}"], name=f"relu{k}")]
        data = f"r{k}"
    model = _model(nodes, [_value("x", [1, 4, 6, 6])], [_value("r3", [1, 4, 6, 6])], inits)
    expected = ["conv0", "conv3", "relu3"]
    assert rewrite.boundary_nodes(model) == expected
    model.graph.input.extend(_value(init.name, list(init.dims)) for init in inits)
    assert rewrite.boundary_nodes(model) == expected


# ----------------------------------------------------------------------------------- export.lower
def _copy_lidar16(tmp_path: Path, edit_manifest=None, edit_graph=None) -> Path:
    """A copy of the shipped LiDAR-only PIXOR directory, its manifest and graph edited (sha256s kept valid)."""
    models = tmp_path / "models"
    shutil.copytree(LIDAR16, models)
    manifest = json.loads((models / "manifest.json").read_text())
    if edit_graph is not None:
        path = models / "pixor.onnx"
        onnx.save(edit_graph(onnx.load(str(path))), str(path))
        manifest["files"]["pixor.onnx"] = {"sha256": sha256_file(path), "bytes": path.stat().st_size}
    if edit_manifest is not None:
        edit_manifest(manifest)
    (models / "manifest.json").write_text(json.dumps(manifest, indent=2))
    return models


def _as_exported_before_the_split(model: onnx.ModelProto) -> onnx.ModelProto:
    """The PIXOR graph as an exporter without rewrites 2 and 8 wrote it: one 19-channel input conv on ``bev``."""
    return rewrite.merge_split_input_convs(rewrite.inputs_from_channel_pieces(model)[0])[0]


def test_lower_splits_an_old_graph_and_records_its_inputs_and_rewrites(tmp_path):
    """An old PIXOR (one 19-channel stem on ``bev``) lowered into a new folder reads the BEV in pieces again; the
    manifest lists those inputs and adds this run's rewrites to those recorded at export; the largest difference
    it reports is the largest over both check inputs, within the tolerance."""
    from export.inputs import kitti_inputs, random_inputs
    from pipeline.graph_inputs import feeds_for
    from pipeline.presets import preset_from_dict

    def stale(manifest: dict) -> None:
        manifest["networks"]["pixor"]["graph_inputs"] = [{"name": "bev", "shape": [1, 19, 400, 352]}]

    old = _copy_lidar16(tmp_path, stale, _as_exported_before_the_split)
    recorded = json.loads((old / "manifest.json").read_text())["export"]["cpu_rewrites"]["pixor"]
    result = lower_run(old, tmp_path / "new")
    assert result.written and result.rewrites["pixor"]["split_input_convs"] == 1
    assert result.rewrites["pixor"]["inputs_in_channel_pieces"] == 1
    manifest = json.loads((tmp_path / "new" / "manifest.json").read_text())
    assert [i["name"] for i in manifest["networks"]["pixor"]["graph_inputs"]] == ["bev[0:16]", "bev[16:19]"]
    totals = manifest["export"]["cpu_rewrites"]["pixor"]
    assert totals == {k: v + result.rewrites["pixor"][k] for k, v in recorded.items()}
    assert totals["split_input_convs"] == 2

    preset = preset_from_dict(manifest["preset_config"])
    sessions = [ort.InferenceSession(str(d / "pixor.onnx"), providers=["CPUExecutionProvider"])
                for d in (old, tmp_path / "new")]
    worst = [max(float(np.abs(a - b).max()) for a, b in zip(*(s.run(None, feeds_for(s, sample.feeds("pixor")))
                                                            for s in sessions), strict=True))
             for sample in (kitti_inputs(preset, KITTI), random_inputs(preset, seed=1))]
    assert result.max_abs_difference["pixor"] == max(worst) <= 1e-5


def test_lower_in_place_rewrites_a_manifest_whose_graph_inputs_are_stale(tmp_path):
    """Nothing left to rewrite in the graph, but the manifest's graph_inputs do not describe it: lowering in
    place writes the manifest again rather than leaving it as it was."""
    def stale(manifest: dict) -> None:
        manifest["networks"]["pixor"]["graph_inputs"] = [{"name": "bev", "shape": [1, 19, 400, 352]}]

    models = _copy_lidar16(tmp_path, stale)
    result = lower_run(models)
    assert result.written and not any(result.rewrites["pixor"].values())
    inputs = json.loads((models / "manifest.json").read_text())["networks"]["pixor"]["graph_inputs"]
    assert [i["name"] for i in inputs] == ["bev[0:16]", "bev[16:19]"]


def test_lower_refuses_a_reduced_precision_or_altered_directory(tmp_path):
    """Only an intact FP32 directory is lowered: one whose manifest says int8, or whose file no longer
    matches its sha256, is refused naming the file."""
    int8 = _copy_lidar16(tmp_path / "a", lambda m: m.update(precision="int8"))
    with pytest.raises(ModelFileError, match="precision int8; lower the FP32 directory"):
        lower_run(int8)
    altered = _copy_lidar16(tmp_path / "b", lambda m: m["files"]["pixor.onnx"].update(sha256="0" * 64))
    with pytest.raises(ModelFileError, match="pixor.onnx"):
        lower_run(altered, tmp_path / "out")
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------------- export/fp16.py
def test_fp16_range_counts_what_float16_cannot_hold_at_its_exact_edges():
    """65504 and 65519 (rounded down to 65504) fit, 65520 is stored as ∞; 2⁻¹⁴ is FP16's smallest normal, 3e-5
    (a subnormal) and 1e-8 (stored as 0) are not; zeros are neither small nor the smallest value."""
    tiny = np.float32(fp16.FP16_SMALLEST_NORMAL)
    values = fp16.Fp16Range()
    values.add(np.array([0, 65504, 65519, -65520, 1e6, tiny, 3e-5, -1e-8, 0], np.float32))
    assert (values.overflow, values.subnormal) == (2, 2)
    assert values.largest == 1e6 and values.smallest == pytest.approx(1e-8)
    fits = fp16.Fp16Range()
    fits.add(np.array([0, tiny, 1, 65504], np.float32))
    assert (fits.overflow, fits.subnormal, fits.smallest) == (0, 0, tiny)
    small = fp16.Fp16Range()
    small.add(np.array([1e-7, 1.0], np.float32))  # harmless unless divided by
    assert small.trouble() is None and "Div_0 divides by it" in small.trouble("Div_0")


def test_fp16_unsafe_nodes_are_the_writer_and_readers_and_the_divisor_is_the_second_input():
    """Tiny values in a numerator are harmless; in b of a / b they keep the Div and every other reader of b FP32.
    A node reading a tensor twice (Mul(b, b)) says so once."""
    nodes = [helper.make_node("Div", ["a", "b"], ["q"], name="div"),
             helper.make_node("Mul", ["b", "b"], ["bb"], name="square")]
    model = _model(nodes, [_value("a", [4]), _value("b", [4])], [_value("q", [4]), _value("bb", [4])], [])
    small, plain = np.array([1e-7, 1, 2, 3], np.float32), np.array([1, 1, 2, 3], np.float32)
    assert fp16.fp16_unsafe_nodes(model, fp16.fp16_ranges(model, [{"a": small, "b": plain}])) == {}
    unsafe = fp16.fp16_unsafe_nodes(model, fp16.fp16_ranges(model, [{"a": plain, "b": small}]))
    assert unsafe.keys() == {"div", "square"}
    assert unsafe["square"].count("reads b:") == 1 and "and div divides by it" in unsafe["square"]


def test_name_nodes_gives_unique_names_past_taken_ones():
    nodes = [helper.make_node("Relu", ["x"], ["a"]), helper.make_node("Relu", ["a"], ["b"], name="Relu_0"),
             helper.make_node("Relu", ["b"], ["c"], name="Relu_0_1")]
    model = _model(nodes, [_value("x", [2])], [_value("c", [2])], [])
    assert fp16.name_nodes(model) == 1
    assert [n.name for n in model.graph.node] == ["Relu_0_2", "Relu_0", "Relu_0_1"]


def _casts(chain: list[int], source_type: int = TensorProto.FLOAT) -> onnx.ModelProto:
    """x → Cast(to=t) for t in ``chain`` → Relu → y (float)."""
    nodes, data = [], "x"
    for k, to in enumerate(chain):
        nodes.append(helper.make_node("Cast", [data], [f"c{k}"], name=f"cast{k}", to=to))
        data = f"c{k}"
    nodes.append(helper.make_node("Relu", [data], ["y"], name="relu"))
    return _model(nodes, [_value("x", [4], source_type)], [_value("y", [4])], [])


def test_round_trips_through_fp16_are_dropped_and_nothing_else():
    """float → fp16 → float twice over: Relu reads x itself. float → int32 → float truncates, and
    double → fp16 → float changes the type: both stay."""
    f32, f16 = TensorProto.FLOAT, TensorProto.FLOAT16
    twice = _casts([f16, f32, f16, f32])
    assert fp16.drop_fp16_round_trips(twice) == 2
    assert _ops(twice) == ["Relu"] and twice.graph.node[0].input[0] == "x"
    for model in (_casts([TensorProto.INT32, f32]), _casts([f16, f32], source_type=TensorProto.DOUBLE)):
        before = _ops(model)
        assert fp16.drop_fp16_round_trips(model) == 0 and _ops(model) == before
    x = {"x": np.array([-1.5, 0.4, 2.7, 1e5], np.float32)}
    kept = _casts([TensorProto.INT32, f32])
    fp16.drop_fp16_round_trips(kept)
    np.testing.assert_array_equal(_run(kept, x)[0], [0, 0, 2, 1e5])


def test_sort_topologically_keeps_valid_order_and_refuses_cycles():
    """Nodes already in order keep it; Casts appended at the end move to just after their producers, the earliest
    ready node first; a cycle is an error rather than a graph with nodes missing."""
    nodes = [helper.make_node("Relu", ["x"], ["a"], name="n0"), helper.make_node("Neg", ["x"], ["b"], name="n1"),
             helper.make_node("Add", ["a2", "b2"], ["y"], name="n2"),
             helper.make_node("Identity", ["b"], ["b2"], name="late_b"),
             helper.make_node("Identity", ["a"], ["a2"], name="late_a")]
    graph = helper.make_graph(nodes, "g", [_value("x", [2])], [_value("y", [2])])
    fp16.sort_topologically(graph)
    assert [n.name for n in graph.node] == ["n0", "n1", "late_b", "late_a", "n2"]
    ordered = [n.name for n in graph.node]
    fp16.sort_topologically(graph)
    assert [n.name for n in graph.node] == ordered
    loop = helper.make_graph([helper.make_node("Relu", ["b"], ["a"], name="p"),
                              helper.make_node("Relu", ["a"], ["b"], name="q")], "loop", [], [_value("b", [2])])
    with pytest.raises(ValueError, match="'loop': its nodes form a cycle"):
        fp16.sort_topologically(loop)


def test_check_fp16_storage_names_a_tensor_no_frame_measured():
    """A float16 tensor of the converted graph with no measured FP32 values is an error naming it, not a
    KeyError: the check cannot vouch for it."""
    source = _model([helper.make_node("Relu", ["x"], ["y"], name="relu")], [_value("x", [2])], [_value("y", [2])],
                    [])
    converted = _model([helper.make_node("Relu", ["x"], ["y"], name="relu")], [_value("x", [2], TensorProto.FLOAT16)],
                       [_value("y", [2], TensorProto.FLOAT16)], [])
    measured = fp16.Fp16Range()
    measured.add(np.array([1.0, 2.0], np.float32))
    assert fp16.check_fp16_storage(source, converted, {"x": measured, "y": measured}) == ("x", 2.0)
    with pytest.raises(fp16.FP16RangeError, match="y \\(written by relu\\): no FP32 tensor 'y' was measured"):
        fp16.check_fp16_storage(source, converted, {"x": measured}, "net")
