"""FP16 and INT8 model directories: conversion, manifest, and the runtime on a real frame."""

import json
import logging
import re

import numpy as np
import onnx
import pytest

from export.precision import calibration_feeds, convert_precision
from pipeline.cpu import int8_pairs_saturate
from pipeline.detector import Detector
from pipeline.errors import InputError
from pipeline.frame import load_frame
from pipeline.graph_inputs import feeds_for, session_feeds
from pipeline.model_files import ModelFileError, verify_sha256
from pipeline.provenance import code_version
from tests.conftest import KITTI

SHIPPED_EDGE = KITTI.parents[3] / "weights" / "edge"


@pytest.fixture(scope="module")
def frame():
    return load_frame(KITTI, "000006")


@pytest.mark.parametrize("precision", ["int8", "fp16"])
def test_reduced_precision_directory(tiny_models, tmp_path, frame, precision):
    out = tmp_path / precision
    manifest = convert_precision(tiny_models, out, precision, KITTI, calibration_frames=3)
    for name in ("depth.onnx", "pixor.onnx"):  # valid graphs, nodes in topological order (as export/lower.py checks)
        onnx.checker.check_model(str(out / name), full_check=True)
    assert manifest["precision"] == precision
    assert json.loads((out / "manifest.json").read_text())["precision"] == precision
    verify_sha256(out, manifest)
    info = manifest["precision_info"]
    if precision == "int8":  # calibrated on the first 3 frames; fp16 has no calibration, its deviation on 5
        assert info["calibration_frames"] == 3 and info["deviation_frames"] == 3
    else:
        assert "calibration_frames" not in info and info["deviation_frames"] == len(list((KITTI / "velodyne").iterdir()))
    fp32 = json.loads((tiny_models / "manifest.json").read_text())
    assert info["source"]["sha256"] == {file: entry["sha256"] for file, entry in fp32["files"].items()}
    # The FP32 export's parity check and lowering describe its files: they stay with the source's record.
    assert "parity" not in manifest and "export" not in manifest
    assert (info["source"]["parity"], info["source"]["export"]) == (fp32["parity"], fp32["export"])
    assert set(manifest["versions"]) == {"onnx", "onnxruntime", "numpy"}
    assert manifest["code"] == code_version() and info["source"]["code"] == fp32.get("code")
    assert set(info["deviation_from_fp32"]) == {"depth", "pixor"}
    if precision == "int8":
        assert info["calibration"] == {"depth": "min-max", "pixor": "min-max, moving average (0.01)"}
    pixor = onnx.load(str(out / "pixor.onnx"))
    ops = {node.op_type for node in pixor.graph.node}
    if precision == "int8":
        assert {"QuantizeLinear", "DequantizeLinear"} <= ops
        # Transposed convs were rewritten (and so quantized); the output heads stay fp32.
        depth = onnx.load(str(out / "depth.onnx"))
        assert "ConvTranspose" not in {node.op_type for node in depth.graph.node} | ops
        assert info["graph"]["depth"]["transposed_convs_rewritten"] == 4  # + 1 stride-1 one lowered at export
        heads = [n for n in pixor.graph.node if n.output[0] in ("score", "regression")]
        assert heads and all(n.op_type != "DequantizeLinear" for n in heads)
        weights = [i for i in pixor.graph.initializer if i.data_type == onnx.TensorProto.INT8]
        assert weights  # signed weights
        assert info["deviation_from_fp32"]["pixor"]["value"] < 0.05
    else:
        assert any(i.data_type == onnx.TensorProto.FLOAT16 for i in pixor.graph.initializer)
        assert info["deviation_from_fp32"]["depth"]["value"] < 1e-2
    # Inputs and outputs stay float32: the runtime feeds the same tensors.
    for value in list(pixor.graph.input) + list(pixor.graph.output):
        assert value.type.tensor_type.elem_type == onnx.TensorProto.FLOAT
    reference = Detector(tiny_models).detect(frame.image, frame.points, frame.calib, 0.0)
    reduced = Detector(out).detect(frame.image, frame.points, frame.calib, 0.0)
    assert reduced.boxes.shape[1] == 7 and np.isfinite(reduced.boxes).all()
    assert abs(len(reduced.scores) - len(reference.scores)) <= 0.2 * len(reference.scores) + 2


def test_calibrating_on_few_frames_is_said_and_fp16_calibrates_nothing(tiny_models, caplog):
    """INT8 from fewer than 100 frames (the default 300 against the bundled five, or a small
    --calibration-frames) gets a warning saying what it got; FP16's deviation frames get none."""
    with caplog.at_level(logging.WARNING):
        feeds = calibration_feeds(tiny_models, KITTI, 300)
    assert len(feeds["pixor"]) == 5
    assert f"INT8 calibrated on 5 frame(s) of {KITTI}: ranges from so few frames may clip" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert len(calibration_feeds(tiny_models, KITTI, 2)["pixor"]) == 2
    assert "INT8 calibrated on 2 frame(s)" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        calibration_feeds(tiny_models, KITTI, 8, calibrating=False)
    assert "INT8" not in caplog.text


def test_unknown_precision(tiny_models, tmp_path):
    with pytest.raises(ValueError, match="--precision"):
        convert_precision(tiny_models, tmp_path / "x", "int4", KITTI)


def test_a_missing_model_directory_is_refused_in_one_line(tmp_path):
    import subprocess
    import sys

    result = subprocess.run(
        [sys.executable, "-m", "export.precision", "--models", str(tmp_path / "nowhere"), "--precision", "int8",
         "--calibration-data", str(KITTI), "--out", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert f"{tmp_path / 'nowhere'}: no such model directory" in result.stderr
    assert not (tmp_path / "out").exists()  # nothing written


def test_conversions_that_would_lose_or_break_something_are_refused(tiny_models, tmp_path):
    """Converting a converted directory, writing over --models, or over a folder that is not a model
    directory is refused with a one-line reason; a conversion that fails leaves an earlier --out intact."""
    import subprocess
    import sys

    from pipeline.model_files import ModelFileError

    int8 = tmp_path / "int8"
    convert_precision(tiny_models, int8, "int8", KITTI, calibration_frames=2)
    before = {p.name: p.read_bytes() for p in int8.iterdir()}
    # Quantizing the INT8 graphs again would write an invalid model: refused, naming the FP32 source.
    with pytest.raises(ModelFileError, match=f"holds int8 models; convert the FP32 directory it came from \\({tiny_models}"):
        convert_precision(int8, tmp_path / "again", "int8", KITTI, calibration_frames=2)
    assert not (tmp_path / "again").exists()
    # The FP32 source must stay: --out may not be --models.
    with pytest.raises(ModelFileError, match="is --models itself"):
        convert_precision(tiny_models, tiny_models, "fp16", KITTI, calibration_frames=2)
    verify_sha256(tiny_models, json.loads((tiny_models / "manifest.json").read_text()))
    # A folder that is not a model directory is never replaced.
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "keep.txt").write_text("mine")
    result = subprocess.run(
        [sys.executable, "-m", "export.precision", "--models", str(tiny_models), "--precision", "fp16",
         "--calibration-frames", "2", "--out", str(notes)],  # --calibration-data: the bundled frames by default
        capture_output=True, text=True, timeout=300, check=False,
    )
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "is not a model directory" in result.stderr and (notes / "keep.txt").read_text() == "mine"
    # A conversion that fails (no calibration frames here) leaves the earlier --out as it was.
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match=re.escape(f"--calibration-data {empty}: not a KITTI object folder")):
        convert_precision(tiny_models, int8, "int8", empty, calibration_frames=2)
    assert {p.name: p.read_bytes() for p in int8.iterdir()} == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no staging copy left behind


@pytest.mark.parametrize("network", ["depth", "pixor"])
def test_transposed_conv_rewrite_is_exact(tiny_models, network):
    """The sub-pixel (stride 2) and flipped-kernel (stride 1) forms give ONNX Runtime the same outputs."""
    import onnxruntime as ort

    from export.rewrite import boundary_nodes, rewrite_transposed_convs

    model = onnx.load(str(tiny_models / f"{network}.onnx"))
    rewritten, count = rewrite_transposed_convs(model)
    onnx.checker.check_model(rewritten)
    assert count == {"depth": 4, "pixor": 2}[network]  # the depth net's stride-1 one was lowered at export
    assert "ConvTranspose" not in {n.op_type for n in rewritten.graph.node}
    assert "DepthToSpace" in {n.op_type for n in rewritten.graph.node}
    sessions = [ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"])
                for m in (model, rewritten)]
    rng = np.random.default_rng(1)
    feeds = {i.name: (rng.random(i.shape) * 40).astype(np.float32) for i in sessions[0].get_inputs()}
    for a, b in zip(*(s.run(None, feeds) for s in sessions), strict=True):
        np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-5 * float(np.abs(a).max()))
    # The fp32 ends: input-side and output-side nodes up to the first and last conv.
    ends = boundary_nodes(rewritten)
    by_name = {n.name: n for n in rewritten.graph.node}
    # depth: the early-fusion conv (conv1_d and conv1_img merged at export) and convtf; pixor: stem and the merged
    # score and regression heads (export/rewrite.py, 9)
    assert sum(by_name[n].op_type == "Conv" for n in ends) == {"depth": 2, "pixor": 2}[network]
    assert set(boundary_nodes(rewritten, inputs=False)) < set(ends)
    # One conv deeper from the outputs: the depth net's last decoder stage (convt1, rewritten as a conv,
    # and its attention conv) joins the fp32 tail; PIXOR's header conv before the heads.
    deeper = boundary_nodes(rewritten, inputs=False, output_convs=2)
    assert set(boundary_nodes(rewritten, inputs=False)) < set(deeper)
    assert sum(by_name[n].op_type == "Conv" for n in deeper) > sum(
        by_name[n].op_type == "Conv" for n in boundary_nodes(rewritten, inputs=False))


def _three_convs() -> onnx.ModelProto:
    """x (1, 4, 8, 8) → Conv → Relu → Conv → Relu → Conv → y: a network small enough to read its scales."""
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(0)
    nodes, inits, name = [], [], "x"
    for i in range(3):
        w = numpy_helper.from_array(rng.normal(0, 0.3, (4, 4, 3, 3)).astype(np.float32), f"w{i}")
        inits.append(w)
        out = "y" if i == 2 else f"c{i}"
        nodes.append(helper.make_node("Conv", [name, f"w{i}"], [out], pads=[1, 1, 1, 1], name=f"conv{i}"))
        if i < 2:
            nodes.append(helper.make_node("Relu", [out], [f"r{i}"], name=f"relu{i}"))
            out = f"r{i}"
        name = out
    graph = helper.make_graph(nodes, "three_convs", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 4, 8, 8])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 4, 8, 8])], inits)
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])


def test_moving_average_calibration_is_not_stretched_by_one_outlying_frame(tmp_path):
    from export.precision import to_int8

    source = tmp_path / "fp32.onnx"
    onnx.save(_three_convs(), str(source))
    rng = np.random.default_rng(1)
    feeds = [{"x": rng.uniform(0, 1, (1, 4, 8, 8)).astype(np.float32)} for _ in range(10)]
    feeds[3]["x"] *= 50  # one frame far outside the others
    scales = {}
    for moving in (False, True):
        target = tmp_path / f"int8_{moving}.onnx"
        info = to_int8(source, target, feeds, inputs_fp32=False, moving_average=moving)
        assert info["calibration"] == ("min-max, moving average (0.01)" if moving else "min-max")
        model = onnx.load(str(target))
        initializers = {i.name: onnx.numpy_helper.to_array(i) for i in model.graph.initializer}
        (quantize,) = [n for n in model.graph.node if n.op_type == "QuantizeLinear" and n.input[0] == "x"]
        scales[moving] = float(initializers[quantize.input[1]])
    # Extremes over all frames: x spans 0–50, so one uint8 step is about 50/255. Averaged per-frame
    # extremes: (9 · 1 + 50) / 10 ≈ 5.9, a step about 5.9/255.
    assert scales[False] == pytest.approx(50 / 255, rel=0.05)
    assert scales[True] == pytest.approx(5.9 / 255, rel=0.1)


def _input_conv_model(tmp_path):
    """A 19-channel input conv (split for the fp32 kernels, as PIXOR's BEV stem) and a head conv; binary inputs."""
    from onnx import TensorProto, helper, numpy_helper

    from export.rewrite import split_input_convs

    rng = np.random.default_rng(3)
    inits = [numpy_helper.from_array(rng.normal(0, 0.2, (16, 19, 3, 3)).astype(np.float32), "w"),
             numpy_helper.from_array(rng.normal(0, 0.1, 16).astype(np.float32), "b"),
             numpy_helper.from_array(rng.normal(0, 0.2, (4, 16, 3, 3)).astype(np.float32), "w2")]
    graph = helper.make_graph(
        [helper.make_node("Conv", ["x", "w", "b"], ["y"], name="stem", pads=[1, 1, 1, 1]),
         helper.make_node("Relu", ["y"], ["r"], name="relu"),
         helper.make_node("Conv", ["r", "w2"], ["out"], name="head", pads=[1, 1, 1, 1])],
        "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 19, 16, 16])],
        [helper.make_tensor_value_info("out", TensorProto.FLOAT, [1, 4, 16, 16])], inits)
    lowered, _ = split_input_convs(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)]))
    source = tmp_path / "fp32.onnx"
    onnx.save(lowered, str(source))
    feeds = [{"x": (rng.random((1, 19, 16, 16)) > 0.8).astype(np.float32)} for _ in range(10)]
    return source, feeds


def _largest_int8_weight(path) -> int:
    """The largest |value| among a quantized graph's int8 initializers (the weights)."""
    weights = [onnx.numpy_helper.to_array(i).astype(np.int32) for i in onnx.load(str(path)).graph.initializer
               if i.data_type == onnx.TensorProto.INT8]
    assert weights
    return max(int(np.abs(w).max()) for w in weights)


def _relative_deviation(source, target, feed) -> float:
    import onnxruntime as ort

    a, b = (ort.InferenceSession(str(p), providers=["CPUExecutionProvider"]).run(None, feed)[0] for p in (source, target))
    return float(np.abs(a - b).max() / np.abs(a).max())


def test_int8_input_conv_reads_the_whole_input_padded_in_uint8(tmp_path):
    """A 19-channel input conv, split for the fp32 kernels, is quantized whole: the input is quantized once
    and padded to 20 channels in uint8 with its zero point."""
    from export.precision import to_int8

    source, feeds = _input_conv_model(tmp_path)
    target = tmp_path / "int8.onnx"
    info = to_int8(source, target, feeds, inputs_fp32=False, output_convs=1)
    assert (info["input_convs_merged"], info["input_convs_padded"], info["pads_after_quantize"]) == (1, 1, 1)
    model = onnx.load(str(target))
    onnx.checker.check_model(model)
    assert "Slice" not in {n.op_type for n in model.graph.node}
    (quantize,) = [n for n in model.graph.node if "x" in n.input]
    (pad,) = [n for n in model.graph.node if quantize.output[0] in n.input]
    (dequantize,) = [n for n in model.graph.node if pad.output[0] in n.input]
    assert (quantize.op_type, pad.op_type, dequantize.op_type) == ("QuantizeLinear", "Pad", "DequantizeLinear")
    assert pad.input[2] == quantize.input[2]  # padded with the zero point


def test_reduced_range_int8_stays_close_to_fp32_on_any_cpu(tmp_path):
    """7-bit weights: every pair of uint8 × int8 products fits 16 bits, so the INT8 graph is what it says on any CPU."""
    from export.precision import to_int8

    source, feeds = _input_conv_model(tmp_path)
    target = tmp_path / "int8_7bit.onnx"
    to_int8(source, target, feeds, inputs_fp32=False, output_convs=1, reduce_range=True)
    assert _largest_int8_weight(target) <= 64
    assert max(_relative_deviation(source, target, feed) for feed in feeds[:3]) < 0.05


def test_full_range_int8_stays_close_to_fp32_only_where_pair_sums_do_not_saturate(tmp_path):
    """With VNNI (or off x86) full-range int8 weights stay as close to fp32 as 7-bit ones. On an x86 CPU
    without it ONNX Runtime adds pairs of uint8 × int8 products in 16 bits, which saturate: the same graph
    departs further from fp32 than its 7-bit twin, the reason for the shipped 7-bit weights and the
    Detector's warning (pipeline/cpu.py). On the AVX2 Zen 3 of session 42: 0.073 against 0.021."""
    from export.precision import to_int8

    source, feeds = _input_conv_model(tmp_path)
    full, seven = tmp_path / "int8.onnx", tmp_path / "int8_7bit.onnx"
    to_int8(source, full, feeds, inputs_fp32=False, output_convs=1)
    to_int8(source, seven, feeds, inputs_fp32=False, output_convs=1, reduce_range=True)
    deviation = {path: max(_relative_deviation(source, path, feed) for feed in feeds[:3]) for path in (full, seven)}
    if int8_pairs_saturate():
        assert deviation[full] > 2 * deviation[seven]
    else:
        assert deviation[full] < 0.05


def test_quantize_before_pad_is_exact():
    """Padding the uint8 tensor with the zero point equals quantizing the zero-padded floats."""
    import onnxruntime as ort
    from onnx import TensorProto, helper, numpy_helper

    from export.rewrite import quantize_before_pad

    inits = [numpy_helper.from_array(np.array([0, 0, 0, 0, 0, 1, 0, 0], np.int64), "pads"),
             numpy_helper.from_array(np.array(0.02, np.float32), "s"), numpy_helper.from_array(np.array(37, np.uint8), "z")]
    graph = helper.make_graph(
        [helper.make_node("Pad", ["x", "pads"], ["xp"], name="pad", mode="constant"),
         helper.make_node("QuantizeLinear", ["xp", "s", "z"], ["q"], name="q"),
         helper.make_node("DequantizeLinear", ["q", "s", "z"], ["out"], name="dq")],
        "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, 5, 7])],
        [helper.make_tensor_value_info("out", TensorProto.FLOAT, [1, 4, 5, 7])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    moved, count = quantize_before_pad(model)
    assert count == 1 and [n.op_type for n in moved.graph.node] == ["QuantizeLinear", "Pad", "DequantizeLinear"]
    onnx.checker.check_model(moved, full_check=True)
    x = {"x": np.random.default_rng(0).uniform(-0.7, 4.0, (1, 3, 5, 7)).astype(np.float32)}
    a, b = (ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"]).run(None, x)[0]
            for m in (model, moved))
    np.testing.assert_array_equal(b, a)
    assert b[0, 3].max() == 0.0  # the padded channel is zero after dequantization
    # A Pad read by more than its QuantizeLinear stays where it is.
    graph.output.append(helper.make_tensor_value_info("xp", TensorProto.FLOAT, [1, 4, 5, 7]))
    assert quantize_before_pad(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)]))[1] == 0


def test_reduce_range_is_recorded_and_quiets_the_saturation_warning(tiny_models, tmp_path, frame, monkeypatch):
    """--reduce-range gives 7-bit weights and says so in the manifest; a full-range INT8 directory loaded on an
    x86 CPU without VNNI gets a warning (in the log and in Detector.load_warnings), a 7-bit one does not."""
    import shutil

    import pipeline.detector

    out = tmp_path / "int8-7bit"
    manifest = convert_precision(tiny_models, out, "int8", KITTI, calibration_frames=3, reduce_range=True)
    info = manifest["precision_info"]
    assert info["reduce_range"] is True and info["weights"] == "int8 per channel, 7-bit range"
    assert info["deviation_measured_on"]["int8_pair_sums_saturate"] == int8_pairs_saturate()  # this CPU
    for name in ("depth.onnx", "pixor.onnx"):
        assert _largest_int8_weight(out / name) <= 64

    full = tmp_path / "int8-full"
    shutil.copytree(out, full)
    edited = json.loads((full / "manifest.json").read_text())
    edited["precision_info"]["reduce_range"] = False
    (full / "manifest.json").write_text(json.dumps(edited))

    def about_precision(detector: Detector) -> list[str]:  # the tiny models also say they are untrained
        return [w for w in detector.load_warnings if "untrained" not in w]

    monkeypatch.setattr(pipeline.detector, "int8_pairs_saturate", lambda: True)  # as on an AVX2-only CPU
    assert about_precision(Detector(out)) == []
    warned = Detector(full)
    assert len(about_precision(warned)) == 1 and "--reduce-range" in about_precision(warned)[0]
    assert warned.detect(frame.image, frame.points, frame.calib, 0.0).boxes.shape[1] == 7  # it still runs
    monkeypatch.setattr(pipeline.detector, "int8_pairs_saturate", lambda: False)  # as with VNNI
    assert about_precision(Detector(full)) == []
    assert about_precision(Detector(tiny_models)) == []  # fp32: nothing to say


def test_reduce_range_needs_int8(tiny_models, tmp_path):
    with pytest.raises(ValueError, match="--reduce-range"):
        convert_precision(tiny_models, tmp_path / "x", "fp16", KITTI, reduce_range=True)
    assert not (tmp_path / "x").exists()


def test_fp16_on_the_cpu_provider_is_flagged(tiny_models, tmp_path, frame):
    """FP16 is a GPU precision: a directory of it that ends up on the CPU provider says so at load, and runs."""
    out = tmp_path / "fp16"
    convert_precision(tiny_models, out, "fp16", KITTI, calibration_frames=2)
    detector = Detector(out, providers="cpu")
    untrained, warning = detector.load_warnings  # the tiny models are untrained
    assert "initialised (untrained) weights" in untrained
    assert "FP16 networks (depth, pixor) run on the CPU provider" in warning
    assert detector.detect(frame.image, frame.points, frame.calib, 0.0).boxes.shape[1] == 7


class _Recording:
    """An ONNX Runtime session stand-in that keeps the feeds of each run and passes them on."""

    def __init__(self, session) -> None:
        self.session, self.feeds = session, []

    def run(self, outputs, feeds, *args):
        self.feeds.append({name: array.copy() for name, array in feeds.items()})
        return self.session.run(outputs, feeds, *args)


def test_calibration_sees_what_the_detector_feeds_pixor(frame):
    """INT8 calibrates on the BEV the runtime gives PIXOR: on the shipped split grid the pseudo points fill
    channels of their own (a BEV voxelized from the merged cloud, as calibration did until session 34, left
    them empty and put the pseudo points among the LiDAR heights)."""
    detector = Detector(SHIPPED_EDGE)
    recording = detector._sessions["pixor"] = _Recording(detector._sessions["pixor"])
    detector.detect(frame.image, frame.points, frame.calib, emulate_to_beams=16)
    (fed,) = recording.feeds
    (bev,) = calibration_feeds(SHIPPED_EDGE, KITTI, 5)["pixor"][-1:]  # 000006 is the fifth bundled frame
    assert bev["bev"].dtype == np.float16
    expected = session_feeds(fed.keys(), {"bev": bev["bev"].astype(np.float32)})
    assert fed.keys() == expected.keys()
    for name in fed:
        np.testing.assert_allclose(fed[name], expected[name], atol=2e-3)  # float16 storage
    grid = detector.preset.bev
    assert grid.split_pseudo
    occupied = (bev["bev"][0, grid.lidar_channels:] > 0).sum()  # channels nz + 1 … 2·nz: the pseudo points'
    assert occupied > 1000


def test_calibration_of_a_16_line_recording_keeps_its_scans(tmp_path):
    """--beams 0 calibrates on scans as stored; thinning a 16-line scan again is refused naming the frame."""
    import shutil

    from pipeline.beams import emulate_beams
    from pipeline.kitti import read_velodyne, write_velodyne

    data = tmp_path / "data"
    for sub in ("image_2", "calib"):
        shutil.copytree(KITTI / sub, data / sub)
    (data / "velodyne").mkdir()
    for scan in sorted((KITTI / "velodyne").glob("*.bin"))[:2]:
        write_velodyne(data / "velodyne" / scan.name, emulate_beams(read_velodyne(scan).points, 16))
    with pytest.raises(InputError, match=r"frame 000000: .*thinned already.*give --emulate-beams 0"):
        calibration_feeds(SHIPPED_EDGE, data, 2)
    feeds = calibration_feeds(SHIPPED_EDGE, data, 2, beams=0)
    assert len(feeds["pixor"]) == len(feeds["depth"]) == 2
    (tmp_path / "empty" / "velodyne").mkdir(parents=True)  # a KITTI folder with no frames: one line, no traceback
    with pytest.raises(InputError, match="--calibration-data .*empty: no frames"):
        calibration_feeds(SHIPPED_EDGE, tmp_path / "empty", 2)


def test_a_conversion_copies_the_model_files_alone_and_not_into_its_source(tiny_models, tmp_path):
    """What else lies in --models (a TensorRT engine cache of the fp32 graphs, notes) is not carried into
    --out, and an --out inside --models, whose next copy would carry it along, is refused."""
    import shutil

    source = tmp_path / "fp32"
    shutil.copytree(tiny_models, source)
    (source / "trt_cache").mkdir()
    (source / "trt_cache" / "engine.bin").write_bytes(b"an fp32 engine")
    out = tmp_path / "fp16"
    convert_precision(source, out, "fp16", KITTI, calibration_frames=2)
    assert sorted(p.name for p in out.iterdir()) == ["depth.onnx", "manifest.json", "pixor.onnx"]
    with pytest.raises(ModelFileError, match=r"lies inside the model directory"):
        convert_precision(source, source / "fp16", "fp16", KITTI, calibration_frames=2)
    assert not (source / "fp16").exists() and (source / "trt_cache" / "engine.bin").exists()


@pytest.fixture(scope="module", params=["tiny", "edge"])
def fp16_directory(request, tmp_path_factory):
    """(FP32 directory, its FP16 conversion): the tiny models and the shipped edge weights (converted elsewhere)."""
    fp32 = request.getfixturevalue("tiny_models") if request.param == "tiny" else SHIPPED_EDGE
    out = tmp_path_factory.mktemp(f"fp16-{request.param}") / "fp16"
    convert_precision(fp32, out, "fp16", KITTI)
    return fp32, out


def _elem_types(model: onnx.ModelProto) -> dict[str, int]:
    graph = onnx.shape_inference.infer_shapes(model).graph
    types = {v.name: v.type.tensor_type.elem_type for v in [*graph.value_info, *graph.input, *graph.output]}
    return types | {init.name: init.data_type for init in graph.initializer}


def test_no_tensor_held_in_fp16_overflows_on_real_frames(fp16_directory):
    """Every tensor the FP16 graphs hold in float16 stays within ±65504 on the bundled frames. ONNX Runtime's CPU
    provider runs most FP16 nodes in FP32, but a tensor asked for as an output it stores as float16, as a GPU
    does. The edge depth net's prefill reciprocal, 1e6 where the prefilled map is empty, was one: ±inf, and
    inf · 0 = NaN in GPU FP16 arithmetic, over the whole depth map."""
    import onnxruntime as ort

    fp32, out = fp16_directory
    for name, samples in calibration_feeds(fp32, KITTI, 5, calibrating=False).items():
        model = onnx.load(str(out / f"{name}.onnx"))
        types = _elem_types(model)
        held = [t for node in model.graph.node for t in node.output if types.get(t) == onnx.TensorProto.FLOAT16]
        assert len(held) > 50  # FP16 it is
        model.graph.output.extend(onnx.helper.make_tensor_value_info(t, onnx.TensorProto.FLOAT16, None) for t in held)
        session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
        for feed in samples:
            values = session.run(held, feeds_for(session, {k: v.astype(np.float32) for k, v in feed.items()}))
            beyond = {t: float(np.abs(v.astype(np.float32)).max()) for t, v in zip(held, values, strict=True)
                      if not (np.abs(v) <= 65504).all()}  # NaN fails too
            assert not beyond, f"{name}: float16 tensors beyond ±65504 or NaN: {beyond}"


def test_fp16_keeps_the_prefill_reciprocal_in_fp32(fp16_directory):
    """The depth net's second prefill reciprocal, 1/clip(x, 1e-6) of the prefilled inverse depth, its divisor's
    Clip and its reader stay FP32 and read each other's FP32 tensors; the manifest says why. The first one,
    of measured depths clipped at 1 mm (at most 1000), stays FP16: the values decide, not the op type."""
    _, out = fp16_directory
    model = onnx.load(str(out / "depth.onnx"))
    types, nodes = _elem_types(model), {node.name: node for node in model.graph.node}
    reciprocal = nodes["node_reciprocal_1"]
    assert types[reciprocal.input[0]] == types[reciprocal.output[0]] == onnx.TensorProto.FLOAT
    assert types[nodes["node_reciprocal"].output[0]] == onnx.TensorProto.FLOAT16
    # No Cast to FP16 and back between them: the 1e6 never passes through float16.
    clip = next(node for node in model.graph.node if reciprocal.input[0] in node.output)
    (reader,) = [node for node in model.graph.node if reciprocal.output[0] in node.input]
    assert (clip.name, reader.op_type) == ("node_clamp_1", "Mul")
    info = json.loads((out / "manifest.json").read_text())["precision_info"]["graph"]
    kept = info["depth"]["fp32_nodes"]
    assert kept.keys() == {clip.name, reciprocal.name, reader.name}
    assert "writes reciprocal_1: " in kept["node_reciprocal_1"]
    assert "values beyond FP16's ±65504 (|x| up to 1e+06)" in kept["node_reciprocal_1"]
    assert "(|x| down to 1e-06), and node_reciprocal_1 divides by it" in kept["node_clamp_1"]
    assert info["pixor"]["fp32_nodes"] == {}
    assert all(0 < network["largest_fp16_value"]["value"] <= 65504 for network in info.values())


def test_a_conversion_that_would_overflow_fp16_fails_naming_the_node(tiny_models, tmp_path, monkeypatch):
    """Should a graph hold in FP16 a tensor that FP16 cannot hold (here: nothing kept FP32 on the tiny depth net),
    the conversion stops with an error naming the node and writes nothing."""
    import export.precision
    from export.fp16 import FP16RangeError

    monkeypatch.setattr(export.precision, "fp16_unsafe_nodes", lambda model, ranges: {})
    out = tmp_path / "fp16"
    with pytest.raises(FP16RangeError, match=r"depth\.onnx: FP16 cannot hold .* node node_reciprocal_1 writes "
                       r"reciprocal_1 in FP16: \d+ values beyond FP16's ±65504 \(\|x\| up to 1e\+06\)"):
        convert_precision(tiny_models, out, "fp16", KITTI, calibration_frames=2)
    assert not out.exists()


def test_what_fp16_cannot_hold_stays_fp32_from_node_to_node_and_to_the_output(tmp_path):
    """r = 1/clip(x, 1e-6) (1e6 where x = 0), a graph output also read by a Mul, beside an FP16 Relu branch.
    The nodes writing or reading r, and the Clip whose output r divides by, stay FP32, unnamed ones too; between
    them and to the output r stays FP32 (the converter's Casts to FP16 and back are gone), exact as in FP32."""
    import onnxruntime as ort
    from onnx import TensorProto, helper, numpy_helper

    from export.precision import to_fp16

    value = helper.make_tensor_value_info
    graph = helper.make_graph(
        [helper.make_node("Clip", ["x", "low"], ["c"]), helper.make_node("Reciprocal", ["c"], ["r"], name="inverse"),
         helper.make_node("Mul", ["r", "x"], ["rx"], name="masked"), helper.make_node("Relu", ["x"], ["z"], name="relu")],
        "g", [value("x", TensorProto.FLOAT, [1, 1, 4, 4])],
        [value(name, TensorProto.FLOAT, [1, 1, 4, 4]) for name in ("r", "rx", "z")],
        [numpy_helper.from_array(np.array(1e-6, np.float32), "low")])
    source, target = tmp_path / "fp32.onnx", tmp_path / "fp16.onnx"
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)]), str(source))
    steps = np.arange(16, dtype=np.float32).reshape(1, 1, 4, 4)
    x = np.where(steps % 3 == 0, 0.0, steps * 0.5).astype(np.float32)  # zeros: r = 1e6 there
    info = to_fp16(source, target, [{"x": x}])
    assert info["fp32_nodes"].keys() == {"Clip_0", "inverse", "masked"}
    assert info["fp16_round_trips_removed"] >= 3  # x into Clip and Mul, r into Mul and to the output
    model = onnx.load(str(target))
    onnx.checker.check_model(model, full_check=True)
    types = _elem_types(model)
    assert {types[t] for n in model.graph.node if n.name in info["fp32_nodes"] for t in [*n.input, *n.output]} == {
        TensorProto.FLOAT}
    assert types[next(n for n in model.graph.node if n.name == "relu").output[0]] == TensorProto.FLOAT16
    expected, converted = (ort.InferenceSession(str(p), providers=["CPUExecutionProvider"]).run(None, {"x": x})
                           for p in (source, target))
    for a, b in zip(expected, converted[:2], strict=False):  # r and rx: exact; z went through FP16
        np.testing.assert_array_equal(b, a)
    assert expected[0].max() == np.float32(1e6)
