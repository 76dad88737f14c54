"""Export: ONNX files, parity with PyTorch for every preset, FLOPs from the graph, manifest and checksums.

Parity (a real KITTI frame + random inputs) runs here for ``tiny`` and ``edge``.
``paper`` is exported without the ONNX Runtime comparison (its depth net takes
seconds per run on 2 cores); its parity was run by hand, see docs/models.md.
"""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from onnx import TensorProto, helper

from export import run
from export.exporter import ExportConfig, ExportResult
from export.flops import count_flops
from export.inputs import kitti_inputs, random_inputs
from export.manifest import verify_model_dir
from export.parity import ParityError, cpu_session, depth_parity, require_parity
from models import build_depth_net, build_pixor
from models.checkpoint import save_checkpoint
from pipeline.graph_inputs import session_feeds, whole_inputs, whole_shapes
from pipeline.model_files import ModelFileError, sha256_file
from pipeline.presets import get_preset
from pipeline.provenance import code_version
from tests.conftest import KITTI


@pytest.fixture(scope="module")
def tiny_export(tmp_path_factory: pytest.TempPathFactory) -> ExportResult:
    return run(ExportConfig(preset="tiny", out=tmp_path_factory.mktemp("tiny")))


@pytest.fixture(scope="module")
def edge_export(tmp_path_factory: pytest.TempPathFactory) -> ExportResult:
    return run(ExportConfig(preset="edge", out=tmp_path_factory.mktemp("edge")))


@pytest.fixture(scope="module")
def paper_export(tmp_path_factory: pytest.TempPathFactory) -> ExportResult:
    return run(ExportConfig(preset="paper", out=tmp_path_factory.mktemp("paper"), parity=False))


def graph_io(path: Path) -> dict[str, tuple[int, ...]]:
    model = onnx.load(str(path))
    return {
        v.name: tuple(d.dim_value for d in v.type.tensor_type.shape.dim)
        for v in list(model.graph.input) + list(model.graph.output)
    }


# --------------------------------------------------------------------------- files and interfaces
@pytest.mark.parametrize("fixture", ["tiny_export", "edge_export", "paper_export"])
def test_onnx_interfaces_are_static_and_named(fixture: str, request: pytest.FixtureRequest) -> None:
    result: ExportResult = request.getfixturevalue(fixture)
    preset = get_preset(result.manifest["preset"])
    height, width = preset.depth.input_hw
    channels, ny, nx = preset.bev.shape
    assert graph_io(result.files["depth"]) == {
        "rgb": (1, 3, height, width), "sparse_depth": (1, 1, height, width), "depth": (1, 1, height, width)
    }
    pixor_io = graph_io(result.files["pixor"])
    # The BEV input read in channel pieces that tile it in order (export/rewrite.py, 8) past one NCHWc block.
    assert whole_shapes(pixor_io) == {
        "bev": (1, channels, ny, nx), "score": (1, 1, ny // 4, nx // 4), "regression": (1, 6, ny // 4, nx // 4)
    }
    assert len(whole_inputs(pixor_io).get("bev", [None])) == (1 if channels < 16 else 2)
    for path in result.files.values():
        model = onnx.load(str(path))
        onnx.checker.check_model(model, full_check=True)
        assert max(o.version for o in model.opset_import if o.domain in ("", "ai.onnx")) >= 17
        # BatchNorm is folded into the convolutions: a clean inference graph.
        assert "BatchNormalization" not in {n.op_type for n in model.graph.node}


# --------------------------------------------------------------------------- parity
@pytest.mark.parametrize("fixture", ["tiny_export", "edge_export"])
def test_parity_on_real_frame_and_random_inputs(fixture: str, request: pytest.FixtureRequest) -> None:
    result: ExportResult = request.getfixturevalue(fixture)
    checks = {(r.network, r.source.split()[0], r.metric) for r in result.parity}
    assert checks == {
        (network, source, metric)
        for source in ("KITTI", "random")
        for network, metric in [
            ("depth", "max relative error"),
            ("pixor", "score max absolute error"),
            ("pixor", "regression max absolute error"),
        ]
    }
    for r in result.parity:
        assert r.passed and r.error <= r.tolerance
        assert r.tolerance <= {"max relative error": 1e-3, "score max absolute error": 1e-4}.get(r.metric, 1.0)
    assert result.manifest["parity"]["checked"] is True


def test_parity_detects_a_model_that_differs(tiny_export: ExportResult) -> None:
    preset = get_preset("tiny")
    torch.manual_seed(0)  # the exporter's seed: same initial weights as depth.onnx
    model = build_depth_net(preset).eval()
    session = cpu_session(tiny_export.files["depth"])
    inputs = kitti_inputs(preset)
    require_parity([depth_parity(model, session, inputs)])  # identical weights pass
    with torch.no_grad():
        model.convtf.bias += 0.01  # +1 m on every pixel (×100 output scale)
    with pytest.raises(ParityError, match="depth on KITTI 000006: max relative error"):
        require_parity([depth_parity(model, session, inputs)])


def test_kitti_inputs_are_real_and_consistent() -> None:
    preset = get_preset("edge")
    inputs = kitti_inputs(preset)
    height, width = preset.depth.input_hw
    assert inputs.rgb.shape == (1, 3, height, width) and inputs.rgb.dtype == np.float32
    assert 0.0 <= inputs.rgb.min() and inputs.rgb.max() <= 255.0 and inputs.rgb.std() > 10.0
    valid = inputs.sparse_depth[inputs.sparse_depth > 0]
    assert valid.size > 0.01 * height * width  # a 64-line scan covers a few % of the half-size crop
    assert np.median(valid) > 1.0 and np.median(valid) < 80.0
    assert inputs.bev.shape == (1, *preset.bev.shape)
    assert set(np.unique(inputs.bev[0, :-1])) <= {0.0, 1.0} and inputs.bev[0, :-1].sum() > 1000


def test_random_inputs_look_like_real_ones() -> None:
    inputs = random_inputs(get_preset("tiny"), seed=3)
    density = (inputs.sparse_depth > 0).mean()
    assert 0.03 < density < 0.07
    occupied_cells = inputs.bev[0, :-1].max(axis=0) > 0
    assert np.all(inputs.bev[0, -1][~occupied_cells] == 0.0)


# --------------------------------------------------------------------------- FLOPs
def test_flop_counter_on_a_hand_built_graph() -> None:
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 4, 8, 8])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, None)
    z = helper.make_tensor_value_info("z", TensorProto.FLOAT, None)
    init = [
        helper.make_tensor("w_conv", TensorProto.FLOAT, [6, 2, 3, 3], np.zeros(108, np.float32)),
        helper.make_tensor("w_convt", TensorProto.FLOAT, [6, 5, 2, 2], np.zeros(120, np.float32)),
        helper.make_tensor("m", TensorProto.FLOAT, [16, 7], np.zeros(112, np.float32)),
        helper.make_tensor("g", TensorProto.FLOAT, [7, 3], np.zeros(21, np.float32)),
        helper.make_tensor("shape", TensorProto.INT64, [2], np.array([-1, 16], np.int64)),
    ]
    nodes = [
        # grouped conv, stride 2: output (1, 6, 4, 4), each output sums 2·3·3 products
        helper.make_node("Conv", ["x", "w_conv"], ["c"], group=2, strides=[2, 2], pads=[1, 1, 1, 1]),
        # transposed conv on (1, 6, 4, 4): every input element scatters into 5·2·2 outputs
        helper.make_node("ConvTranspose", ["c", "w_convt"], ["y"], strides=[2, 2]),
        helper.make_node("Reshape", ["c", "shape"], ["flat"]),  # (6, 16)
        helper.make_node("MatMul", ["flat", "m"], ["mm"]),  # (6, 16) @ (16, 7)
        helper.make_node("Gemm", ["mm", "g"], ["z"]),  # (6, 7) @ (7, 3)
    ]
    model = helper.make_model(helper.make_graph(nodes, "g", [x], [y, z], init), opset_imports=[helper.make_opsetid("", 17)])
    counted = count_flops(model)
    macs = {"Conv": 6 * 4 * 4 * 2 * 3 * 3, "ConvTranspose": 6 * 4 * 4 * 5 * 2 * 2, "MatMul": 6 * 7 * 16, "Gemm": 6 * 3 * 7}
    assert counted.by_op == {op: 2 * m for op, m in macs.items()}
    assert counted.total == 2 * sum(macs.values()) and counted.nodes == 4


def test_flop_counter_refuses_dynamic_shapes() -> None:
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, ["batch", 4, 8, 8])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, None)
    w = helper.make_tensor("w", TensorProto.FLOAT, [4, 4, 1, 1], np.zeros(16, np.float32))
    graph = helper.make_graph([helper.make_node("Conv", ["x", "w"], ["y"], name="c1")], "g", [x], [y], [w])
    with pytest.raises(ValueError, match="'c1'.*unknown"):
        count_flops(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]))


def test_edge_is_ten_times_cheaper_than_paper(edge_export: ExportResult, paper_export: ExportResult) -> None:
    for name in ("depth", "pixor"):
        paper = paper_export.manifest["networks"][name]["flops"]
        edge = edge_export.manifest["networks"][name]["flops"]
        # Counted before lowering: the zero weights of merged and padded convs are not work (the
        # depth net's merged early-fusion conv adds 0.1 % to a count of the written graph).
        assert paper <= count_flops(paper_export.files[name]).total <= 1.01 * paper
        assert paper >= 10 * edge, f"{name}: paper {paper / 1e9:.1f} GFLOP vs edge {edge / 1e9:.1f} GFLOP"
    # PIXOR at the paper grid is about 90 GFLOP (DESIGN.md), the depth net several hundred.
    assert 80e9 < paper_export.manifest["networks"]["pixor"]["flops"] < 100e9
    assert paper_export.manifest["networks"]["depth"]["flops"] > 300e9


def test_export_lowers_graphs_for_cpu_kernels(edge_export: ExportResult) -> None:
    """The edge export (parity-checked by its fixture) has no stride-1 ConvTranspose, one conv for the
    early fusion, no conv on the 19-channel BEV input itself (split at 16 channels, read as two graph
    inputs), no 12-channel conv outputs (padded to 16) and one conv for both output heads."""
    rewrites = edge_export.manifest["export"]["cpu_rewrites"]
    assert rewrites == {"depth": {"stride1_transposed_convs": 1, "merged_parallel_convs": 1, "split_input_convs": 0,
                                  "padded_narrow_convs": 0, "where_as_arithmetic": 6, "inputs_in_channel_pieces": 0,
                                  "merged_output_heads": 0},
                        "pixor": {"stride1_transposed_convs": 0, "merged_parallel_convs": 0, "split_input_convs": 1,
                                  "padded_narrow_convs": 4, "where_as_arithmetic": 0, "inputs_in_channel_pieces": 1,
                                  "merged_output_heads": 1}}
    depth = onnx.load(str(edge_export.files["depth"]))
    assert not [n for n in depth.graph.node if n.op_type == "Where"]  # the prefill's six, as arithmetic
    assert not any(n.name.startswith(("conv1_d", "conv1_img")) for n in depth.graph.initializer)  # merged
    strides = [list(a.ints) for n in depth.graph.node if n.op_type == "ConvTranspose"
               for a in n.attribute if a.name == "strides"]
    assert strides and all(s == [2, 2] for s in strides)
    pixor = onnx.load(str(edge_export.files["pixor"]))
    assert [i.name for i in pixor.graph.input] == ["bev[0:16]", "bev[16:19]"]
    assert [n.op_type for n in pixor.graph.node if {"bev[0:16]", "bev[16:19]"} & set(n.input)] == ["Conv", "Conv"]
    assert [n.op_type for n in pixor.graph.node][-2:] == ["Split", "Sigmoid"]  # score and boxes from one conv
    weights = {init.name: init.dims for init in pixor.graph.initializer}
    widths = {weights[n.input[1]][0] for n in pixor.graph.node if n.op_type == "Conv"}
    assert 12 not in widths and 16 in widths  # edge PIXOR's 12-wide first stage now runs 16 wide


def test_split_input_conv_is_exact() -> None:
    """A 19-channel input conv split at 16 gives ONNX Runtime the same output; 8 and 32 channels stay whole."""
    import onnxruntime as ort
    from onnx import numpy_helper

    from export.rewrite import split_input_convs

    rng = np.random.default_rng(0)

    def conv_graph(channels: int) -> onnx.ModelProto:
        weight = numpy_helper.from_array(rng.standard_normal((16, channels, 3, 3)).astype(np.float32), "w")
        bias = numpy_helper.from_array(rng.standard_normal(16).astype(np.float32), "b")
        graph = helper.make_graph(
            [helper.make_node("Conv", ["x", "w", "b"], ["y"], pads=[1, 1, 1, 1], kernel_shape=[3, 3], strides=[2, 2]),
             helper.make_node("Relu", ["y"], ["out"])], "g",
            [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, channels, 20, 24])],
            [helper.make_tensor_value_info("out", TensorProto.FLOAT, [1, 16, 10, 12])], [weight, bias])
        return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=8)

    for channels, expected in ((19, 1), (8, 0), (32, 0)):
        model = conv_graph(channels)
        split, count = split_input_convs(model)
        assert count == expected
        onnx.checker.check_model(split, full_check=True)
        x = {"x": rng.standard_normal((1, channels, 20, 24)).astype(np.float32)}
        a, b = (ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"]).run(None, x)[0]
                for m in (model, split))
        np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-5)
    assert [n.op_type for n in split_input_convs(conv_graph(19))[0].graph.node] == [
        "Slice", "Slice", "Conv", "Conv", "Add", "Relu"]


def test_merge_and_pad_input_convs_are_exact() -> None:
    """For INT8: a split input conv merges back whole, then reads its 19-channel input padded to 20: the
    same outputs; skipped, aligned or inner convs stay as they are."""
    import onnxruntime as ort
    from onnx import numpy_helper

    from export.rewrite import merge_split_input_convs, pad_input_convs, split_input_convs

    rng = np.random.default_rng(2)

    def input_conv(channels: int) -> onnx.ModelProto:
        inits = [numpy_helper.from_array(rng.standard_normal((16, channels, 3, 3)).astype(np.float32), "w"),
                 numpy_helper.from_array(rng.standard_normal(16).astype(np.float32), "b"),
                 numpy_helper.from_array(rng.standard_normal((8, 16, 3, 3)).astype(np.float32), "w2")]
        graph = helper.make_graph(
            [helper.make_node("Conv", ["x", "w", "b"], ["y"], name="stem", pads=[1, 1, 1, 1], kernel_shape=[3, 3]),
             helper.make_node("Relu", ["y"], ["r"], name="relu"),
             helper.make_node("Conv", ["r", "w2"], ["out"], name="inner", pads=[1, 1, 1, 1], kernel_shape=[3, 3])],
            "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, channels, 12, 10])],
            [helper.make_tensor_value_info("out", TensorProto.FLOAT, [1, 8, 12, 10])], inits)
        return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=8)

    def run(model: onnx.ModelProto, x: np.ndarray) -> np.ndarray:
        onnx.checker.check_model(model, full_check=True)
        return ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"]).run(None, {"x": x})[0]

    model = input_conv(19)
    x = rng.standard_normal((1, 19, 12, 10)).astype(np.float32)
    split, _ = split_input_convs(model)
    merged, count = merge_split_input_convs(split)
    assert count == 1 and [n.op_type for n in merged.graph.node] == ["Conv", "Relu", "Conv"]
    assert merge_split_input_convs(split, skip=frozenset({"stem_a"}))[1] == 0
    padded, count = pad_input_convs(merged)
    assert count == 1 and [n.op_type for n in padded.graph.node] == ["Pad", "Conv", "Relu", "Conv"]
    assert padded.graph.node[0].input[0] == "x"
    reference = run(model, x)
    for rewritten in (merged, padded):
        # Float summation order only: the scale of the outputs (hundreds) times a few float32 steps.
        np.testing.assert_allclose(run(rewritten, x), reference, rtol=1e-5, atol=1e-6 * float(np.abs(reference).max()))
    assert pad_input_convs(merged, skip=frozenset({"stem"}))[1] == 0
    assert pad_input_convs(input_conv(20))[1] == 0  # already a multiple of 4; the inner conv never reads an input


def _stem_graph(channels: int, extra_reader: bool = False) -> onnx.ModelProto:
    """x (1, C, 12, 10) → 3×3 Conv named "stem" → Relu → out; with ``extra_reader`` x is also summed to a second output."""
    from onnx import numpy_helper

    rng = np.random.default_rng(channels)
    inits = [numpy_helper.from_array(rng.standard_normal((16, channels, 3, 3)).astype(np.float32), "w"),
             numpy_helper.from_array(rng.standard_normal(16).astype(np.float32), "b")]
    nodes = [helper.make_node("Conv", ["x", "w", "b"], ["y"], name="stem", pads=[1, 1, 1, 1], kernel_shape=[3, 3]),
             helper.make_node("Relu", ["y"], ["out"], name="relu")]
    outputs = [helper.make_tensor_value_info("out", TensorProto.FLOAT, [1, 16, 12, 10])]
    if extra_reader:
        nodes.append(helper.make_node("ReduceSum", ["x"], ["total"], name="sum", keepdims=0))
        outputs.append(helper.make_tensor_value_info("total", TensorProto.FLOAT, []))
    graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, channels, 12, 10])],
                              outputs, inits)
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=8)


def test_channel_slices_become_graph_inputs_fed_as_views_and_join_back() -> None:
    """A split 19-channel input conv reads two graph inputs x[0:16] and x[16:19]: ONNX Runtime gives the same
    output when they are fed as views of one array (no copy); for INT8 the pieces join back into x and the
    conv merges whole again. Inputs with another reader, or slices that do not tile them, stay as they are."""
    import onnxruntime as ort

    from export.rewrite import (
        inputs_from_channel_pieces,
        inputs_from_channel_slices,
        merge_split_input_convs,
        split_input_convs,
    )

    def run(model: onnx.ModelProto, arrays: dict[str, np.ndarray]) -> list[np.ndarray]:
        onnx.checker.check_model(model, full_check=True)
        session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
        return session.run(None, session_feeds([i.name for i in session.get_inputs()], arrays))

    model = _stem_graph(19)
    x = np.random.default_rng(3).standard_normal((1, 19, 12, 10)).astype(np.float32)
    split, _ = split_input_convs(model)
    pieces, count = inputs_from_channel_slices(split)
    assert count == 1 and [i.name for i in pieces.graph.input] == ["x[0:16]", "x[16:19]"]
    assert [n.op_type for n in pieces.graph.node] == ["Conv", "Conv", "Add", "Relu"]
    assert [[d.dim_value for d in i.type.tensor_type.shape.dim] for i in pieces.graph.input] == [[1, 16, 12, 10],
                                                                                              [1, 3, 12, 10]]
    feeds = session_feeds(["x[0:16]", "x[16:19]"], {"x": x})
    assert all(np.shares_memory(v, x) and v.flags.c_contiguous for v in feeds.values())
    reference = run(model, {"x": x})[0]
    np.testing.assert_allclose(run(pieces, {"x": x})[0], reference, rtol=1e-5, atol=1e-5)
    assert inputs_from_channel_slices(pieces)[1] == 0  # nothing left to rewrite

    joined, count = inputs_from_channel_pieces(pieces)
    assert count == 1 and [i.name for i in joined.graph.input] == ["x"]
    merged, count = merge_split_input_convs(joined)
    assert count == 1 and [n.op_type for n in merged.graph.node] == ["Conv", "Relu"]
    np.testing.assert_allclose(run(merged, {"x": x})[0], reference, rtol=1e-5, atol=1e-5)

    assert inputs_from_channel_slices(split_input_convs(_stem_graph(19, extra_reader=True))[0])[1] == 0
    gapped = onnx.ModelProto.FromString(split.SerializeToString())  # the second slice starts one channel late
    bound = next(init for init in gapped.graph.initializer if init.name == "stem_c1")
    slice_b = next(n for n in gapped.graph.node if n.name == "stem_slice_b")
    gapped.graph.initializer.append(helper.make_tensor("late", TensorProto.INT64, [1], [17]))
    slice_b.input[1] = "late"
    assert bound.name == "stem_c1" and inputs_from_channel_slices(gapped)[1] == 0
    with pytest.raises(KeyError, match="y\\[0:16\\]"):
        session_feeds(["y[0:16]"], {"x": x})


def test_merge_output_heads_is_exact_and_only_on_heads() -> None:
    """Two convs on the same features, one through a Sigmoid to an output and one straight to an output,
    become one conv and a Split: the same outputs. A conv on those features that feeds another conv, or a
    head with other settings, stays apart."""
    import onnxruntime as ort
    from onnx import numpy_helper

    from export.rewrite import merge_output_heads

    rng = np.random.default_rng(4)

    def weight(name: str, shape: tuple[int, ...]) -> onnx.TensorProto:
        return numpy_helper.from_array(rng.standard_normal(shape).astype(np.float32), name)

    inits = [weight("wf", (8, 4, 3, 3)), weight("ws", (1, 8, 3, 3)), weight("bs", (1,)), weight("wr", (6, 8, 3, 3)),
             weight("br", (6,)), weight("wt", (4, 8, 1, 1)), weight("wu", (2, 4, 3, 3)), weight("wv", (3, 8, 1, 1))]
    conv3 = {"pads": [1, 1, 1, 1], "kernel_shape": [3, 3]}
    nodes = [helper.make_node("Conv", ["x", "wf"], ["f"], name="features", **conv3),
             helper.make_node("Relu", ["f"], ["r"], name="relu"),
             helper.make_node("Conv", ["r", "ws", "bs"], ["s"], name="score_conv", **conv3),
             helper.make_node("Sigmoid", ["s"], ["score"], name="sigmoid"),
             helper.make_node("Conv", ["r", "wr", "br"], ["regression"], name="regression_conv", **conv3),
             helper.make_node("Conv", ["r", "wt"], ["t"], name="inner", kernel_shape=[1, 1]),
             helper.make_node("Conv", ["t", "wu"], ["other"], name="after_inner", **conv3),
             helper.make_node("Conv", ["r", "wv"], ["pointwise"], name="pointwise_head", kernel_shape=[1, 1])]
    shapes = {"score": 1, "regression": 6, "other": 2, "pointwise": 3}
    graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 4, 10, 12])],
                              [helper.make_tensor_value_info(n, TensorProto.FLOAT, [1, c, 10, 12]) for n, c in shapes.items()],
                              inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=8)
    merged, count = merge_output_heads(model)
    onnx.checker.check_model(merged, full_check=True)
    assert count == 1  # score and regression; the pointwise head has another kernel, "inner" feeds a conv
    ops = [n.op_type for n in merged.graph.node]
    assert ops.count("Conv") == 5 and ops.count("Split") == 1
    x = {"x": rng.standard_normal((1, 4, 10, 12)).astype(np.float32)}
    before, after = (ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"]).run(list(shapes), x)
                     for m in (model, merged))
    for name, a, b in zip(shapes, before, after):
        np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-5, err_msg=name)
    assert merge_output_heads(merged)[1] == 0


def test_pad_narrow_convs_is_exact_and_only_where_safe() -> None:
    """8-channel convs read only by convs (through a Relu) are padded to 16; one whose output is added
    to something else, or is a graph output, is left alone. ONNX Runtime gives the same outputs."""
    import onnxruntime as ort
    from onnx import numpy_helper

    from export.rewrite import pad_narrow_convs

    rng = np.random.default_rng(0)

    def weight(name: str, shape: tuple[int, ...]) -> onnx.TensorProto:
        return numpy_helper.from_array(rng.standard_normal(shape).astype(np.float32), name)

    nodes = [
        helper.make_node("Conv", ["x", "w1", "b1"], ["a"], kernel_shape=[1, 1]),  # 8 out → Relu → Conv: padded
        helper.make_node("Relu", ["a"], ["a_relu"]),
        helper.make_node("Conv", ["a_relu", "w2", "b2"], ["c"], kernel_shape=[3, 3], pads=[1, 1, 1, 1]),  # 8 out → Add
        helper.make_node("Add", ["c", "x8"], ["d"]),
        helper.make_node("Conv", ["d", "w3"], ["out"], kernel_shape=[1, 1]),  # 4 out, a graph output
    ]
    inits = [weight("w1", (8, 16, 1, 1)), weight("b1", (8,)), weight("w2", (8, 8, 3, 3)), weight("b2", (8,)),
             weight("w3", (4, 8, 1, 1))]
    graph = helper.make_graph(
        nodes, "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 16, 12, 10]),
         helper.make_tensor_value_info("x8", TensorProto.FLOAT, [1, 8, 12, 10])],
        [helper.make_tensor_value_info("out", TensorProto.FLOAT, [1, 4, 12, 10])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=8)
    padded, count = pad_narrow_convs(model)
    assert count == 1
    onnx.checker.check_model(padded, full_check=True)
    dims = {init.name: tuple(init.dims) for init in padded.graph.initializer}
    assert dims["w1"] == (16, 16, 1, 1) and dims["b1"] == (16,) and dims["w2"] == (8, 16, 3, 3)
    assert dims["w3"] == (4, 8, 1, 1)
    feeds = {"x": rng.standard_normal((1, 16, 12, 10)).astype(np.float32),
             "x8": rng.standard_normal((1, 8, 12, 10)).astype(np.float32)}
    a, b = (ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"]).run(None, feeds)[0]
            for m in (model, padded))
    np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-5)


def test_where_as_arithmetic_is_exact_and_only_on_finite_branches() -> None:
    """The prefill's pattern (Where over a clipped reciprocal and a max-pool of it) becomes arithmetic with
    ONNX Runtime giving the same values; a Where whose branch may be infinite (1/x unclipped) stays."""
    import onnxruntime as ort
    from onnx import numpy_helper

    from export.rewrite import where_as_arithmetic

    zero = numpy_helper.from_array(np.zeros((1, 1, 8, 12), np.float32), "zeros")
    scalars = [numpy_helper.from_array(np.array(v, np.float32), n) for n, v in (("zero", 0.0), ("eps", 1e-3))]
    nodes = [
        helper.make_node("Greater", ["x", "zero"], ["measured"]),
        helper.make_node("Clip", ["x", "eps"], ["clipped"]),
        helper.make_node("Reciprocal", ["clipped"], ["inverse"]),
        helper.make_node("Where", ["measured", "inverse", "zeros"], ["filled0"]),  # finite branches: rewritten
        helper.make_node("MaxPool", ["filled0"], ["pooled"], kernel_shape=[3, 3], pads=[1, 1, 1, 1]),
        helper.make_node("Greater", ["filled0", "zero"], ["kept"]),
        helper.make_node("Where", ["kept", "filled0", "pooled"], ["filled"]),  # finite branches: rewritten
        helper.make_node("Reciprocal", ["x"], ["raw_inverse"]),  # 1/0 = inf where x is 0
        helper.make_node("Where", ["measured", "raw_inverse", "zeros"], ["unsafe"]),  # may be inf: kept
    ]
    shape = [1, 1, 8, 12]
    graph = helper.make_graph(
        nodes, "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, shape)],
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, shape) for n in ("filled", "unsafe")], [zero, *scalars])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=8)
    rewritten, count = where_as_arithmetic(model)
    assert count == 2
    onnx.checker.check_model(rewritten, full_check=True)
    assert [n.output[0] for n in rewritten.graph.node if n.op_type == "Where"] == ["unsafe"]
    rng = np.random.default_rng(3)
    x = np.where(rng.random(shape) < 0.3, rng.uniform(1, 80, shape), 0).astype(np.float32)
    a, b = (ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"]).run(None, {"x": x})
            for m in (model, rewritten))
    for before, after in zip(a, b, strict=True):
        np.testing.assert_array_equal(after, before)
    assert np.isinf(a[1]).sum() == 0 and (a[0] > 0).mean() > 0.5  # the fill spread; 1/x stayed masked


def test_merge_parallel_convs_is_exact_and_only_where_alike() -> None:
    """The early-fusion pattern (two Relu(Conv) branches, concatenated) becomes one conv with the same
    ONNX Runtime outputs; branches with different dilations, or read elsewhere, stay."""
    import onnxruntime as ort
    from onnx import numpy_helper

    from export.rewrite import merge_parallel_convs

    rng = np.random.default_rng(7)
    weights = {"wd": (8, 2), "wi": (16, 3), "wa": (4, 3), "wb": (4, 3)}
    inits = [numpy_helper.from_array(rng.standard_normal((o, c, 3, 3)).astype(np.float32), n)
             for n, (o, c) in weights.items()]
    inits += [numpy_helper.from_array(rng.standard_normal(o).astype(np.float32), f"{n}_b")
              for n, (o, _) in weights.items()]
    conv = {"kernel_shape": [3, 3], "strides": [2, 2], "pads": [1, 1, 1, 1]}
    nodes = [
        helper.make_node("Conv", ["d", "wd", "wd_b"], ["cd"], **conv),
        helper.make_node("Relu", ["cd"], ["rd"]),
        helper.make_node("Conv", ["i", "wi", "wi_b"], ["ci"], **conv),
        helper.make_node("Relu", ["ci"], ["ri"]),
        helper.make_node("Concat", ["rd", "ri"], ["fused"], axis=1),  # merged
        helper.make_node("Conv", ["i", "wa", "wa_b"], ["ca"], kernel_shape=[3, 3], pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["ca"], ["ra"]),
        helper.make_node("Conv", ["i", "wb", "wb_b"], ["cb"], kernel_shape=[3, 3], pads=[2, 2, 2, 2], dilations=[2, 2]),
        helper.make_node("Relu", ["cb"], ["rb"]),
        helper.make_node("Concat", ["ra", "rb"], ["aspp"], axis=1),  # different dilations: kept
    ]
    inputs = [helper.make_tensor_value_info("d", TensorProto.FLOAT, [1, 2, 16, 20]),
              helper.make_tensor_value_info("i", TensorProto.FLOAT, [1, 3, 16, 20])]
    outputs = [helper.make_tensor_value_info("fused", TensorProto.FLOAT, [1, 24, 8, 10]),
               helper.make_tensor_value_info("aspp", TensorProto.FLOAT, [1, 8, 16, 20])]
    model = helper.make_model(helper.make_graph(nodes, "g", inputs, outputs, inits),
                              opset_imports=[helper.make_opsetid("", 18)], ir_version=8)
    merged, count = merge_parallel_convs(model)
    assert count == 1
    onnx.checker.check_model(merged, full_check=True)
    assert sum(n.op_type == "Conv" for n in merged.graph.node) == 3
    feeds = {"d": rng.uniform(0, 80, (1, 2, 16, 20)).astype(np.float32),
             "i": rng.uniform(-2, 2, (1, 3, 16, 20)).astype(np.float32)}
    a, b = (ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"]).run(None, feeds)
            for m in (model, merged))
    for before, after in zip(a, b, strict=True):
        np.testing.assert_allclose(after, before, rtol=1e-5, atol=1e-5)
    # A branch whose activation is also read elsewhere cannot be folded away.
    extra = helper.make_tensor_value_info("rd", TensorProto.FLOAT, [1, 8, 8, 10])
    model.graph.output.append(extra)
    assert merge_parallel_convs(model)[1] == 0


def test_lower_command_upgrades_an_old_directory_and_is_idempotent(tiny_export: ExportResult, tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture) -> None:
    """A directory exported before the lowering (the depth net's Where ops, a stride-1 ConvTranspose) gets
    the lowered graphs, the same outputs and a manifest whose sha256s the Detector accepts."""
    from export.lower import main as lower_main
    from export.lower import run as lower_run
    from export.onnx_export import depth_io, export_onnx
    from pipeline.detector import Detector

    old = tmp_path / "old"
    shutil.copytree(tiny_export.directory, old)
    preset = get_preset("tiny")
    export_onnx(tiny_export.networks["depth"], depth_io(preset.depth.input_hw), old / "depth.onnx", lower=False)
    manifest = json.loads((old / "manifest.json").read_text())
    manifest["files"]["depth.onnx"]["sha256"] = sha256_file(old / "depth.onnx")
    manifest["export"]["cpu_rewrites"]["depth"] = {}  # as an exporter without the lowering wrote it
    (old / "manifest.json").write_text(json.dumps(manifest))
    assert [n for n in onnx.load(str(old / "depth.onnx")).graph.node if n.op_type == "Where"]

    result = lower_run(old, tmp_path / "new")
    assert result.rewrites["depth"]["where_as_arithmetic"] == 4  # tiny's two prefill passes
    assert result.rewrites["depth"]["stride1_transposed_convs"] == 1
    assert not any(result.rewrites["pixor"].values()) and max(result.max_abs_difference.values()) <= 1e-5
    lowered = onnx.load(str(tmp_path / "new" / "depth.onnx"))
    assert not [n for n in lowered.graph.node if n.op_type in ("Where",)]
    inputs = kitti_inputs(preset)
    feeds = {"rgb": inputs.rgb, "sparse_depth": inputs.sparse_depth}
    before = cpu_session(old / "depth.onnx").run(None, feeds)[0]
    after = cpu_session(tmp_path / "new" / "depth.onnx").run(None, feeds)[0]
    np.testing.assert_allclose(after, before, rtol=1e-5, atol=1e-5)
    Detector(tmp_path / "new")  # sha256s verified
    counts = json.loads((tmp_path / "new" / "manifest.json").read_text())["export"]["cpu_rewrites"]["depth"]
    assert counts == result.rewrites["depth"]

    again = tmp_path / "new" / "depth.onnx"
    digest = sha256_file(again)
    assert lower_main(["--models", str(tmp_path / "new")]) == 0  # in place: nothing left to rewrite
    assert sha256_file(again) == digest
    assert capsys.readouterr().out.splitlines()[-1] == f"unchanged: {tmp_path / 'new'} (already lowered)"

    other = tmp_path / "notes"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    assert lower_main(["--models", str(old), "--out", str(other)]) == 2  # not a model directory: refused
    assert [p.name for p in other.iterdir()] == ["keep.txt"]
    assert lower_main(["--models", str(old), "--out", str(tmp_path / "new")]) == 0  # a model directory: replaced
    assert sha256_file(again) == digest and not list(tmp_path.glob(".new.*"))  # no staging copies left

    (old / "pixor.onnx").write_bytes(b"broken")
    assert lower_main(["--models", str(old), "--out", str(tmp_path / "x")]) == 2  # refused, with a message


# --------------------------------------------------------------------------- manifest and checksums
def test_manifest_contents(tiny_export: ExportResult, tmp_path: Path) -> None:
    from export.onnx_export import depth_io, export_onnx, pixor_io

    manifest = json.loads(tiny_export.manifest_path.read_text())
    preset = get_preset("tiny")
    assert manifest["preset"] == "tiny"
    assert manifest["preset_config"] == json.loads(json.dumps(preset.to_dict()))
    assert manifest["weights"] == "initialised (untrained)"
    assert manifest["bev_grid"]["shape"] == list(preset.bev.shape)
    # tiny's 8-channel BEV is below one NCHWc block: read whole, as declared
    assert manifest["networks"]["pixor"]["graph_inputs"] == [{"name": "bev", "shape": [1, *preset.bev.shape]}]
    assert manifest["normalisation"]["rgb_mean"] == pytest.approx([123.675, 116.28, 103.53])
    assert manifest["normalisation"]["rgb_std"] == pytest.approx([58.395, 57.12, 57.375])
    assert set(manifest["versions"]) >= {"torch", "onnx", "onnxruntime"}
    assert manifest["code"] == code_version()  # the checkout's commit: which code exported the files
    for name, file in (("depth", "depth.onnx"), ("pixor", "pixor.onnx")):
        entry = manifest["networks"][name]
        assert entry["file"] == file and entry["weights"] == "initialised (untrained)"
        # FLOPs of the network as traced: the zero channels lowering pads in (tiny PIXOR) are not work.
        io = depth_io(preset.depth.input_hw) if name == "depth" else pixor_io(preset.bev.shape, preset.pixor.output_stride)
        traced = export_onnx(tiny_export.networks[name], io, tmp_path / file, lower=False)
        assert entry["flops"] == count_flops(traced.path).total > 0
        if name == "pixor":
            assert count_flops(tiny_export.directory / file).total > entry["flops"]
        assert entry["parameters"] == sum(p.numel() for p in (build_depth_net if name == "depth" else build_pixor)(preset).parameters())
        assert manifest["files"][file]["sha256"] == sha256_file(tiny_export.directory / file)
    assert [i["name"] for i in manifest["networks"]["depth"]["inputs"]] == ["rgb", "sparse_depth"]
    assert [o["name"] for o in manifest["networks"]["pixor"]["outputs"]] == ["score", "regression"]


def test_corrupted_model_file_is_refused(tiny_export: ExportResult, tmp_path: Path) -> None:
    copy = tmp_path / "models"
    shutil.copytree(tiny_export.directory, copy)
    assert verify_model_dir(copy)["preset"] == "tiny"
    data = bytearray((copy / "pixor.onnx").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (copy / "pixor.onnx").write_bytes(bytes(data))
    with pytest.raises(ModelFileError, match=r"pixor\.onnx: sha256 mismatch"):
        verify_model_dir(copy)
    (copy / "pixor.onnx").unlink()
    with pytest.raises(ModelFileError, match=r"pixor\.onnx: model file listed in the manifest is missing"):
        verify_model_dir(copy)
    (copy / "manifest.json").unlink()
    with pytest.raises(ModelFileError, match="no manifest"):
        verify_model_dir(copy)


def test_export_with_checkpoints_records_training(tmp_path: Path) -> None:
    preset = get_preset("tiny")
    torch.manual_seed(5)
    depth, pixor = build_depth_net(preset), build_pixor(preset)
    with torch.no_grad():
        pixor.score.bias.fill_(-1.0)  # weights the exporter's seed would never produce
    save_checkpoint(tmp_path / "ckpt" / "depth.pt", preset, {"depth": depth}, {"epochs": 10, "val_rmse_m": 1.59})
    save_checkpoint(tmp_path / "ckpt" / "pixor.pt", preset, {"pixor": pixor}, {"epochs": 30})
    result = run(ExportConfig(preset="tiny", out=tmp_path / "out", checkpoints=tmp_path / "ckpt"))
    manifest = result.manifest
    assert manifest["weights"] == "trained"
    assert manifest["networks"]["depth"]["training"] == {"checkpoint": "depth.pt", "epochs": 10, "val_rmse_m": 1.59}
    assert manifest["networks"]["pixor"]["training"]["epochs"] == 30
    bev = random_inputs(preset).bev
    (score,) = cpu_session(result.files["pixor"]).run(["score"], {"bev": bev})
    with torch.no_grad():
        expected = pixor.eval()(torch.from_numpy(bev))[0].numpy()
    np.testing.assert_allclose(score, expected, atol=1e-5)
    # Exported again without the pixor checkpoint (a forgotten or misspelt --checkpoints): the trained
    # directory is not replaced by initialised weights.
    before = {p.name: p.read_bytes() for p in result.directory.iterdir()}
    (tmp_path / "ckpt" / "pixor.pt").unlink()
    for checkpoints in (None, tmp_path / "ckpt"):
        with pytest.raises(ModelFileError, match="holds trained .*pixor weights, which this export would replace"):
            run(ExportConfig(preset="tiny", out=result.directory, checkpoints=checkpoints, parity=False))
    assert {p.name: p.read_bytes() for p in result.directory.iterdir()} == before
    # A LiDAR-only export (--networks pixor) over the camera directory would delete its trained depth net.
    save_checkpoint(tmp_path / "ckpt" / "pixor.pt", preset, {"pixor": pixor}, {"epochs": 30})
    with pytest.raises(ModelFileError, match="holds a trained depth network, which this export .*would delete"):
        run(ExportConfig(preset="tiny", out=result.directory, checkpoints=tmp_path / "ckpt", networks=("pixor",),
                         parity=False))
    assert {p.name: p.read_bytes() for p in result.directory.iterdir()} == before


def test_export_refuses_empty_checkpoint_dir(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="expected depth.pt and/or pixor.pt"):
        run(ExportConfig(preset="tiny", out=tmp_path / "out", checkpoints=tmp_path / "empty"))


# --------------------------------------------------------------------------- commands and imports
def test_cli_help() -> None:
    done = subprocess.run([sys.executable, "-m", "export", "--help"], capture_output=True, text=True, check=True)
    assert "--preset" in done.stdout and "--checkpoints" in done.stdout and "--out" in done.stdout


@pytest.mark.parametrize(("extra", "says"), [
    (["--preset", "edge-large"], "--preset: unknown preset 'edge-large'"),
    (["--preset", "tiny", "--checkpoints", "{tmp}/no-runs"], "no-runs: checkpoint directory not found"),
])
def test_cli_bad_preset_or_checkpoints_answer_one_line(tmp_path: Path, extra: list[str], says: str) -> None:
    args = [a.replace("{tmp}", str(tmp_path)) for a in extra]
    done = subprocess.run([sys.executable, "-m", "export", *args, "--out", str(tmp_path / "out"), "--no-parity"],
                          capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert says.replace("{tmp}", str(tmp_path)) in done.stderr


def test_runtime_side_modules_do_not_import_torch() -> None:
    code = (
        "import sys, export, export.flops, export.manifest, export.inputs, pipeline.model_files; "
        "assert 'torch' not in sys.modules, 'torch imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("module", ["export", "models.train", "models.reproduce"])
def test_commands_without_torch_say_what_to_install(module: str) -> None:
    """With the runtime install alone (no torch), the torch commands answer one line, not a traceback;
    export.lower, which needs no torch, still works."""
    hide_torch = "import runpy, sys; sys.modules['torch'] = None; sys.argv = ['x', '--help']; "
    result = subprocess.run([sys.executable, "-c", hide_torch + f"runpy.run_module({module!r}, run_name='__main__')"],
                            capture_output=True, text=True, check=False)
    assert result.returncode != 0
    assert "make setup-dev" in result.stderr and "Traceback" not in result.stderr
    bound = subprocess.run([sys.executable, "-c", hide_torch + "runpy.run_path('benchmarks/depth_bound.py', run_name='__main__')"],
                           capture_output=True, text=True, check=False, cwd=Path(__file__).resolve().parents[1])
    assert bound.returncode != 0 and "make setup-dev" in bound.stderr and "Traceback" not in bound.stderr
    lower = subprocess.run([sys.executable, "-c", hide_torch + "runpy.run_module('export.lower', run_name='__main__')"],
                           capture_output=True, text=True, check=False)
    assert lower.returncode == 0 and "--models" in lower.stdout


def test_a_failed_export_leaves_the_earlier_model_directory_as_it_was(tmp_path: Path) -> None:
    """The export writes into a staging folder: when it fails (here on a checkpoint torch cannot read),
    the model directory already at --out keeps its files and still verifies; a folder that is not a
    model directory is never written into."""
    from export.manifest import verify_model_dir
    from pipeline.model_files import ModelFileError

    out = tmp_path / "models"
    run(ExportConfig(preset="tiny", out=out, parity=False))
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    broken = tmp_path / "runs"
    broken.mkdir()
    (broken / "pixor.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="pixor.pt: not a lowres3d checkpoint"):
        run(ExportConfig(preset="tiny", out=out, parity=False, checkpoints=broken))
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    verify_model_dir(out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["models", "runs"]  # no staging folder left
    with pytest.raises(ModelFileError, match="is not a model directory"):
        run(ExportConfig(preset="tiny", out=broken, parity=False))
    assert sorted(p.name for p in broken.iterdir()) == ["pixor.pt"]


@pytest.mark.parametrize("name", ["edge", "edge-split-near35"])
def test_random_inputs_are_laid_out_as_the_voxelizers_output(name: str) -> None:
    """Occupancy in the height channels (and, on a split grid, the pseudo points' own after the reflectance),
    the reflectance in channel nz, only where the real returns' channels are occupied."""
    grid = get_preset(name).bev
    bev = random_inputs(get_preset(name)).bev[0]
    assert bev.shape == grid.shape
    occupancy = np.delete(bev, grid.nz, axis=0)
    assert set(np.unique(occupancy)) == {0.0, 1.0}
    reflectance = bev[grid.nz]
    assert 0.0 < reflectance.max() < 1.0 and len(np.unique(reflectance)) > 100
    np.testing.assert_array_equal(reflectance > 0, bev[: grid.nz].max(axis=0) > 0)


def test_a_model_directory_of_another_preset_or_precision_is_not_replaced(tmp_path: Path) -> None:
    """--out over a model directory replaces it with a new export of the same model; one of another preset
    or precision is refused untouched (a typo, such as the shipped weights/edge given as --out)."""
    from export.lower import run as lower_run
    from export.precision import convert_precision

    out = tmp_path / "models"
    run(ExportConfig(preset="tiny", out=out, parity=False))
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    with pytest.raises(ModelFileError, match=rf"--out {out}: holds a model of preset tiny \(fp32\); this writes preset "
                                             rf"tiny-split \(fp32\): give a new folder, or remove {out} first"):
        run(ExportConfig(preset="tiny-split", out=out, parity=False))
    int8 = tmp_path / "int8"
    convert_precision(out, int8, "int8", KITTI, calibration_frames=1)
    with pytest.raises(ModelFileError, match=r"holds a model of preset tiny \(int8\); this writes preset tiny \(fp16\)"):
        convert_precision(out, int8, "fp16", KITTI, calibration_frames=1)
    with pytest.raises(ModelFileError, match=r"holds a model of preset tiny \(int8\); this writes preset tiny \(fp32\)"):
        lower_run(out, int8)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    run(ExportConfig(preset="tiny", out=out, parity=False, seed=1))  # the same model exported again: replaced
    assert {p.name: p.read_bytes() for p in out.iterdir()} != before


# --------------------------------------------------------------------------- the command's inputs, checked first
def _export_main(args: list[str], capsys: pytest.CaptureFixture) -> tuple[int, str]:
    """``python -m export`` in this process: (exit status, stderr)."""
    from export.__main__ import main

    try:
        code = main(args)
    except SystemExit as stop:  # argparse
        code = stop.code
    return code, capsys.readouterr().err


def test_cli_refuses_bad_inputs_in_one_line_before_exporting(tmp_path: Path, capsys: pytest.CaptureFixture,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """Each mistake gets exit 2 and one line naming the flag, at once rather than after the export's
    minutes (a tiny export takes over 10 s here): no network is exported before it, and nothing is written."""
    import export.exporter

    def exported(*args: object, **kwargs: object) -> None:
        raise AssertionError("a network was exported before the mistake was refused")

    monkeypatch.setattr(export.exporter, "export_onnx", exported)
    a_file = tmp_path / "notes.txt"
    a_file.write_text("mine")
    only_depth = tmp_path / "only_depth"
    preset = get_preset("tiny")
    save_checkpoint(only_depth / "depth.pt", preset, {"depth": build_depth_net(preset)}, {})
    out = str(tmp_path / "out")
    cases = [
        (["--out", f"{a_file}/models"], f"--out {a_file}/models: {a_file} is a file, not a directory"),
        (["--out", out, "--frame", "999999"], "--frame 999999: not in --data"),
        (["--out", out, "--kitti-dir", str(tmp_path / "kitt")], f"--data {tmp_path / 'kitt'}: not a folder"),  # alias
        (["--out", out, "--data", str(tmp_path / "kitt")], f"--data {tmp_path / 'kitt'}: not a folder"),
        (["--out", out, "--checkpoints", str(only_depth / "depth.pt")], "depth.pt: is a file; give the folder"),
        (["--out", out, "--checkpoints", str(only_depth), "--networks", "pixor"],
         "holds depth.pt but no checkpoint of --networks pixor"),
        (["--out", out, "--precision", "int8", "--calibration-data", str(tmp_path / "cal")],
         f"--calibration-data {tmp_path / 'cal'}: no such folder"),
        (["--out", str(a_file), "--precision", "fp16"], f"--out {a_file}: exists and is not a model directory"),
    ]
    for args, says in cases:
        code, err = _export_main(["--preset", "tiny", *args], capsys)
        assert code == 2 and says in err and len(err.strip().splitlines()) == 1, (args, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt", "only_depth"]


def test_cli_refuses_an_out_that_holds_what_it_reads(tmp_path: Path, capsys: pytest.CaptureFixture,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """--out is replaced as a whole once the new model is written: ``--out M --data M/kitti`` deleted the frames
    it had read, ``--checkpoints M/run`` a training run's checkpoints. Refused before any network is exported."""
    import export.exporter

    def exported(*args: object, **kwargs: object) -> None:
        raise AssertionError("a network was exported before the mistake was refused")

    monkeypatch.setattr(export.exporter, "export_onnx", exported)
    models = shutil.copytree(Path(__file__).resolve().parents[1] / "weights" / "edge-lidar16", tmp_path / "models")
    frames = models / "kitti"
    for folder, suffix in (("image_2", ".png"), ("velodyne", ".bin"), ("calib", ".txt")):
        (frames / folder).mkdir(parents=True)
        shutil.copy(KITTI / folder / f"000006{suffix}", frames / folder)
    preset = get_preset("edge")
    for run_dir in (models / "run", tmp_path / "run"):  # trained weights: the model at --out is not lost to initialised
        save_checkpoint(run_dir / "pixor.pt", preset, {"pixor": build_pixor(preset)}, {})
    before = {path: path.read_bytes() for path in models.rglob("*") if path.is_file()}
    for flag, source, rest in (("--data", frames, ["--frame", "000006", "--checkpoints", str(tmp_path / "run")]),
                               ("--checkpoints", models / "run", ["--no-parity"])):
        code, err = _export_main(["--preset", "edge", "--networks", "pixor", "--out", str(models), flag, str(source),
                                  *rest], capsys)
        assert code == 2, err
        assert err == (f"error: --out {models}: replacing it would delete {flag} {source}, which this run reads; "
                       "give another --out, one that does not hold it\n")
    assert {path: path.read_bytes() for path in models.rglob("*") if path.is_file()} == before
    # export.lower and export.precision replace their --out whole too: refused alike, before any work.
    from export.lower import main as lower
    from export.precision import main as precision

    other = shutil.copytree(models, tmp_path / "other", ignore=shutil.ignore_patterns("kitti", "run"))
    for main, args, flag in ((lower, ["--models", str(other), "--out", str(models), "--data", str(frames)], "--data"),
                             (precision, ["--models", str(other), "--precision", "int8", "--out", str(models),
                                          "--calibration-data", str(frames)], "--calibration-data")):
        assert main(args) == 2
        assert capsys.readouterr().err == (f"error: --out {models}: replacing it would delete {flag} {frames}, which "
                                           "this run reads; give another --out, one that does not hold it\n")
    assert {path: path.read_bytes() for path in models.rglob("*") if path.is_file()} == before


def test_a_reduced_precision_export_records_what_made_its_fp32_networks(tmp_path: Path,
                                                                         capsys: pytest.CaptureFixture) -> None:
    """The FP32 directory of `python -m export --precision …` is temporary: the manifest names the command,
    not a folder that is gone (which a later conversion's refusal would send the user to)."""
    out = tmp_path / "fp16"
    code, err = _export_main(["--preset", "tiny", "--out", str(out), "--no-parity", "--precision", "fp16"], capsys)
    assert code == 0, err
    source = json.loads((out / "manifest.json").read_text())["precision_info"]["source"]["directory"]
    assert source == "not kept: python -m export --preset tiny --networks depth pixor (initialised)"


@pytest.mark.parametrize(("extra", "says"), [
    (["--no-parity", "--frame", "000001"], "--frame: only used by the parity check, which --no-parity skips"),
    (["--no-parity", "--data", "x"], "--data: only used by the parity check"),
    (["--calibration-frames", "10"], "--calibration-frames: only used by --precision fp16 or int8, not fp32"),
    (["--networks", "depth"], "--networks: every model directory has pixor"),
])
def test_cli_refuses_flags_it_would_ignore(tmp_path: Path, capsys: pytest.CaptureFixture, extra: list[str],
                                          says: str) -> None:
    code, err = _export_main(["--preset", "tiny", "--out", str(tmp_path / "out"), *extra], capsys)
    assert code == 2 and says in err and not (tmp_path / "out").exists()


def test_ctrl_c_during_export_leaves_out_as_it_was(tiny_export: ExportResult, tmp_path: Path) -> None:
    """Ctrl-C while torch traces the network (which turns it into a TorchExportError asking for a bug
    report) ends with one line and exit 130; the model directory at --out keeps its files."""
    out = tmp_path / "models"
    shutil.copytree(tiny_export.directory, out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    log = tmp_path.parent / f"{tmp_path.name}.stderr"  # a file, not a pipe: a pipe lets the export run ahead
    with open(log, "w") as stderr:
        process = subprocess.Popen([sys.executable, "-m", "export", "--preset", "tiny", "--out", str(out), "--seed",
                                    "3"], stderr=stderr, stdout=subprocess.DEVNULL, text=True)
    deadline = time.monotonic() + 120
    while "exporting depth.onnx" not in log.read_text() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert process.poll() is None, "the export ended before it could be interrupted"
    process.send_signal(signal.SIGINT)
    code = process.wait(timeout=120)
    err = log.read_text()
    assert code == 130, err[-2000:]
    assert "interrupted" in err and "Traceback" not in err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["models"]  # no staging folder left
