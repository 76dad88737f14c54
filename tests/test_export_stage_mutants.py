"""The export stage around the graph rewrites (export/flops.py, inputs.py, onnx_export.py, exporter.py, golden.py,
port_spec.py, precision.py), pinned where a mutation audit found the other tests blind.

Each test was written against a mutant those modules' other tests let through: a FLOP count that ignores the
batch or Gemm's transA, a golden array written in the wrong byte order, a TensorRT note off by one opset, an
INT8 conversion that quantizes the depth net's inputs, a manifest that keeps describing an input split the
quantized graph no longer has. Graphs are built by hand with onnx.helper or exported from a few-layer torch
module; the real conversions run on the shipped LiDAR-only and camera model directories, which convert in
seconds (the tiny preset's exports take longer than that).
"""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from onnx import TensorProto, helper, numpy_helper
from torch import nn

from export import golden, parity
from export.exporter import ExportConfig, ExportResult, _load_weights, normalisation, run
from export.flops import count_flops
from export.inputs import DEFAULT_FRAME, check_frame, kitti_inputs, random_inputs
from export.manifest import TensorSpec, graph_inputs
from export.onnx_export import NetworkIO, check_interface, export_onnx
from export.port_spec import graph_report, port_spec, tensorrt_notes
from export.precision import (
    DEVIATION_FRAMES,
    FEWEST_CALIBRATION_FRAMES,
    _Reader,
    calibration_feeds,
    convert_precision,
    deviation,
    to_int8,
)
from export.rewrite import boundary_nodes
from models import build_depth_net, build_pixor
from models.checkpoint import save_checkpoint
from pipeline.bev import voxelize_bev
from pipeline.detector import Detector
from pipeline.errors import InputError
from pipeline.frame import load_frame
from pipeline.model_files import ModelFileError
from pipeline.presets import get_preset
from tests.conftest import KITTI

WEIGHTS = KITTI.parents[3] / "weights"
LIDAR16 = WEIGHTS / "edge-lidar16"


def _value(name: str, shape: list[int] | None) -> onnx.ValueInfoProto:
    return helper.make_tensor_value_info(name, TensorProto.FLOAT, shape)


def _model(nodes: list[onnx.NodeProto], inputs: list[onnx.ValueInfoProto], outputs: list[onnx.ValueInfoProto],
           inits: list[onnx.TensorProto], opset: int = 18, domains: tuple[str, ...] = ()) -> onnx.ModelProto:
    opsets = [helper.make_opsetid("", opset)] + [helper.make_opsetid(d, 1) for d in domains]
    return helper.make_model(helper.make_graph(nodes, "g", inputs, outputs, inits), opset_imports=opsets, ir_version=8)


def _zeros(name: str, shape: tuple[int, ...]) -> onnx.TensorProto:
    return numpy_helper.from_array(np.zeros(shape, np.float32), name)


# --------------------------------------------------------------------------- FLOPs (export/flops.py)
def test_flops_count_every_image_of_a_batch_every_conv_and_gemms_transposed_operands() -> None:
    """A batch of 2 costs twice one image (Conv and ConvTranspose); two Convs add up under one op type; Gemm's
    shared dimension K comes from A's first axis under transA and its second otherwise, whatever transB says."""
    nodes = [
        # (2, 4, 8, 8) → (2, 6, 4, 4), grouped: each output sums 2·3·3 products
        helper.make_node("Conv", ["x", "w1"], ["c1"], group=2, strides=[2, 2], pads=[1, 1, 1, 1]),
        helper.make_node("Conv", ["c1", "w2"], ["c2"]),  # 1×1: each output sums 6 products
        helper.make_node("ConvTranspose", ["c2", "wt"], ["up"], strides=[2, 2]),  # each input into 5·2·2 outputs
        helper.make_node("Gemm", ["a", "b1"], ["g1"], transA=1),  # A (7, 3): (3, 7) @ (7, 5)
        helper.make_node("Gemm", ["a2", "b2"], ["g2"], transB=1),  # A (3, 7): (3, 7) @ (7, 5)
    ]
    inits = [_zeros("w1", (6, 2, 3, 3)), _zeros("w2", (6, 6, 1, 1)), _zeros("wt", (6, 5, 2, 2)),
             _zeros("b1", (7, 5)), _zeros("b2", (5, 7))]
    model = _model(nodes, [_value("x", [2, 4, 8, 8]), _value("a", [7, 3]), _value("a2", [3, 7])],
                   [_value("up", None), _value("g1", None), _value("g2", None)], inits)
    counted = count_flops(model)
    macs = {"Conv": 2 * 6 * 4 * 4 * 2 * 3 * 3 + 2 * 6 * 4 * 4 * 6, "ConvTranspose": 2 * 6 * 4 * 4 * 5 * 2 * 2,
            "Gemm": 2 * 3 * 5 * 7}
    assert counted.by_op == {op: 2 * m for op, m in macs.items()}
    assert counted.nodes == 5
    assert counted.gflops == pytest.approx(2 * sum(macs.values()) / 1e9)


# --------------------------------------------------------------------------- parity inputs (export/inputs.py)
def test_random_inputs_have_the_stated_ranges_and_follow_their_seed() -> None:
    """RGB spans 0–255 raw (normalised inside depth.onnx), depths 1–80 m, and the seed both chooses the
    values and is named in the source the parity results report."""
    preset = get_preset("tiny")
    inputs = random_inputs(preset, seed=4)
    assert inputs.source == "random (seed 4)"
    assert inputs.rgb.min() >= 0.0 and inputs.rgb.max() <= 255.0 and inputs.rgb.max() > 250.0
    depths = inputs.sparse_depth[inputs.sparse_depth > 0]
    assert depths.min() >= 1.0 and depths.max() <= 80.0 and depths.min() < 1.5
    assert not np.array_equal(random_inputs(preset, seed=5).rgb, inputs.rgb)
    assert np.array_equal(random_inputs(preset, seed=4).bev, inputs.bev)
    depth, pixor = inputs.feeds("depth"), inputs.feeds("pixor")
    assert depth.keys() == {"rgb", "sparse_depth"} and depth["rgb"] is inputs.rgb
    assert pixor.keys() == {"bev"} and pixor["bev"] is inputs.bev
    assert kitti_inputs(preset).source == f"KITTI {DEFAULT_FRAME}"


@pytest.mark.parametrize("left_out", ["image_2/000006.png", "velodyne/000006.bin", "calib/000006.txt"])
def test_a_parity_frame_missing_any_of_its_three_files_is_refused_by_name(tmp_path: Path, left_out: str) -> None:
    for sub in ("image_2", "velodyne", "calib"):
        (tmp_path / sub).mkdir()
        for file in (KITTI / sub).glob("000006.*"):
            (tmp_path / sub / file.name).symlink_to(file)
    (tmp_path / left_out).unlink()
    with pytest.raises(InputError, match=rf"^--frame 000006: not in --data {tmp_path} \(no {left_out}\)$"):
        check_frame(tmp_path, "000006")


# --------------------------------------------------------------------------- torch → ONNX (export/onnx_export.py)
class _ConvBn(nn.Module):
    """A conv, a batch norm with running statistics of its own and a dropout: train mode would change all but
    the conv."""

    def __init__(self) -> None:
        super().__init__()
        self.conv = nn.Conv2d(3, 4, 3, padding=1)
        self.bn = nn.BatchNorm2d(4)
        self.drop = nn.Dropout(0.5)
        with torch.no_grad():
            self.bn.running_mean.copy_(torch.tensor([0.5, -1.0, 2.0, 0.1]))
            self.bn.running_var.copy_(torch.tensor([4.0, 0.25, 1.0, 9.0]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.drop(self.bn(self.conv(x)))


def _small_io(output_shape: tuple[int, ...] = (1, 4, 8, 8)) -> NetworkIO:
    return NetworkIO(inputs=[TensorSpec("x", (1, 3, 8, 8))], outputs=[TensorSpec("y", output_shape)])


def test_export_onnx_traces_in_eval_mode_inline_at_opset_18_and_restores_the_exporters_log(tmp_path: Path) -> None:
    """A module handed over in train mode is exported (and left) in eval mode, its weights inside the one .onnx
    file the manifest's sha256 covers, at the opset the port notes assume; the exporter's registry log,
    quieted while tracing, gets its level back."""
    torch.manual_seed(0)
    module = _ConvBn().train()
    registry = logging.getLogger("torch.onnx._internal.exporter._registration")
    registry.setLevel(logging.INFO)
    try:
        exported = export_onnx(module, _small_io(), tmp_path / "small.onnx", lower=False)
        assert registry.level == logging.INFO
    finally:
        registry.setLevel(logging.NOTSET)
    assert not module.training
    assert sorted(p.name for p in tmp_path.iterdir()) == ["small.onnx"]
    model = onnx.load(str(exported.path), load_external_data=False)
    assert all(i.data_location != TensorProto.EXTERNAL for i in model.graph.initializer)
    assert {o.version for o in model.opset_import if o.domain in ("", "ai.onnx")} == {18}
    x = np.random.default_rng(0).normal(0, 1, (1, 3, 8, 8)).astype(np.float32)
    (y,) = ort.InferenceSession(str(exported.path), providers=["CPUExecutionProvider"]).run(None, {"x": x})
    with torch.no_grad():
        expected = module.eval()(torch.from_numpy(x)).numpy()
    np.testing.assert_allclose(y, expected, rtol=1e-5, atol=1e-5)
    assert exported.flops.total == 2 * 4 * 8 * 8 * 3 * 3 * 3


def test_export_onnx_refuses_a_network_whose_output_differs_from_the_declared(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"ONNX outputs \{'y': \(1, 4, 8, 8\)\} differ from the declared"):
        export_onnx(_ConvBn(), _small_io((1, 4, 4, 4)), tmp_path / "small.onnx", lower=False)


def test_check_interface_compares_shapes_of_inputs_and_outputs() -> None:
    model = _model([helper.make_node("Relu", ["x"], ["y"])], [_value("x", [1, 3, 8, 8])], [_value("y", [1, 3, 8, 8])], [])
    io = NetworkIO(inputs=[TensorSpec("x", (1, 3, 8, 8))], outputs=[TensorSpec("y", (1, 3, 8, 8))])
    check_interface(model, io, "relu.onnx")
    wrong_output = NetworkIO(inputs=io.inputs, outputs=[TensorSpec("y", (1, 3, 8, 9))])
    with pytest.raises(ValueError, match=r"^relu\.onnx: ONNX outputs .* differ from the declared \{'y': \(1, 3, 8, 9\)\}"):
        check_interface(model, wrong_output, "relu.onnx")
    wrong_input = NetworkIO(inputs=[TensorSpec("x", (1, 4, 8, 8))], outputs=io.outputs)
    with pytest.raises(ValueError, match=r"^relu\.onnx: ONNX inputs .* differ from the declared \{'x': \(1, 4, 8, 8\)\}"):
        check_interface(model, wrong_input, "relu.onnx")


# --------------------------------------------------------------------------- the exporter (export/exporter.py)
def test_the_manifest_normalisation_carries_the_presets_own_constants() -> None:
    preset = get_preset("edge")
    record = normalisation(preset)
    assert (record["min_depth"], record["max_depth"]) == (preset.depth.min_depth, preset.depth.max_depth)
    assert record["input_scale"] == preset.depth.input_scale and record["crop_hw"] == list(preset.crop_hw)
    assert record["regression_mean"] == list(preset.decode.reg_mean)
    assert record["regression_std"] == list(preset.decode.reg_std)


def test_loading_only_some_checkpoints_warns_about_the_others(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    preset = get_preset("tiny")
    path = save_checkpoint(tmp_path / "runs" / "pixor.pt", preset, {"pixor": build_pixor(preset)}, {"epochs": 3})
    with caplog.at_level(logging.WARNING, logger="export.exporter"):
        training = _load_weights({"pixor": path}, preset, {"depth": build_depth_net(preset), "pixor": build_pixor(preset)})
    assert training == {"depth": None, "pixor": {"checkpoint": "pixor.pt", "epochs": 3}}
    assert f"no checkpoint for depth in {tmp_path / 'runs'}: exporting initialised weights" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="export.exporter"):
        _load_weights({}, preset, {"pixor": build_pixor(preset)})  # no --checkpoints: initialised on purpose
    assert caplog.text == ""


def test_an_export_without_pixor_is_refused_before_anything_is_written(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="^--networks: depth; choose 'depth pixor' or 'pixor'$"):
        run(ExportConfig(preset="tiny", out=tmp_path / "out", networks=("depth",)))
    assert list(tmp_path.iterdir()) == []


@pytest.fixture(scope="module")
def trained_lidar_only(tmp_path_factory: pytest.TempPathFactory) -> tuple[ExportResult, Path]:
    """A tiny LiDAR-only directory of a trained PIXOR, exported with seed 2 and the parity check; its checkpoints."""
    base = tmp_path_factory.mktemp("lidar_only")
    preset = get_preset("tiny")
    torch.manual_seed(7)
    save_checkpoint(base / "runs" / "pixor.pt", preset, {"pixor": build_pixor(preset)}, {"epochs": 4})
    result = run(ExportConfig(preset="tiny", out=base / "models", checkpoints=base / "runs", networks=("pixor",), seed=2))
    return result, base / "runs"


def test_the_parity_check_and_the_manifest_follow_the_seed(trained_lidar_only: tuple[ExportResult, Path]) -> None:
    result, _ = trained_lidar_only
    assert {r.source for r in result.parity} == {f"KITTI {DEFAULT_FRAME}", "random (seed 2)"}
    manifest = json.loads(result.manifest_path.read_text())
    assert manifest["export"]["torch_seed"] == 2 and manifest["parity"]["checked"] is True
    assert manifest["networks"]["pixor"]["weights"] == "trained"


def test_a_camera_export_without_checkpoints_keeps_a_trained_lidar_only_directory(
        trained_lidar_only: tuple[ExportResult, Path], tmp_path: Path) -> None:
    """`python -m export --preset tiny --out DIR` (both networks, a forgotten --checkpoints) over a trained
    LiDAR-only directory would replace its PIXOR with initialised weights: refused as over a camera one. Its
    own export again, without the parity check, is allowed and records that the check did not run."""
    result, runs = trained_lidar_only
    out = tmp_path / "models"
    shutil.copytree(result.directory, out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    with pytest.raises(ModelFileError, match="holds trained pixor weights, which this export would replace"):
        run(ExportConfig(preset="tiny", out=out, parity=False))
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    again = run(ExportConfig(preset="tiny", out=out, checkpoints=runs, networks=("pixor",), parity=False))
    assert again.manifest["parity"] == {"checked": False, "results": []}
    assert again.manifest["networks"]["pixor"]["weights"] == "trained"


# --------------------------------------------------------------------------- graph reports (export/port_spec.py)
def _notes(opset: int, nodes: list[onnx.NodeProto] | None = None, inits: list[onnx.TensorProto] | None = None,
           domains: tuple[str, ...] = ()) -> list[str]:
    nodes = nodes or [helper.make_node("Relu", ["x"], ["y"])]
    return tensorrt_notes(_model(nodes, [_value("x", [1, 2])], [_value("y", [1, 2])], inits or [], opset, domains))


def test_tensorrt_notes_at_the_opset_limits_and_for_each_kind_of_refusal() -> None:
    assert _notes(17) == []  # what TensorRT 8.5/8.6 parse
    for opset in (18, 20):  # TensorRT 10 parses up to 20
        (note,) = _notes(opset)
        assert note.startswith(f"opset {opset}: TensorRT 10 parses it")
    (note,) = _notes(21)
    assert note == "opset 21: above 20, what TensorRT 10.0 parses"
    (note,) = _notes(17, [helper.make_node("Unique", ["x"], ["y"])])
    assert note == "operators TensorRT's ONNX parser does not import: Unique"
    (note,) = _notes(17, [helper.make_node("Gelu", ["x"], ["y"], domain="com.microsoft")], domains=("com.microsoft",))
    assert note == "operators of custom domains (com.microsoft): not parsed by TensorRT"
    # int8 with zero point 0 is what TensorRT takes; a non-zero int8 zero point is not
    scale = numpy_helper.from_array(np.array(0.1, np.float32), "s")
    quantize = [helper.make_node("QuantizeLinear", ["x", "s", "z"], ["q"]), helper.make_node("DequantizeLinear", ["q", "s", "z"], ["y"])]
    assert _notes(17, quantize, [scale, numpy_helper.from_array(np.array(0, np.int8), "z")]) == []
    (note,) = _notes(17, quantize, [scale, numpy_helper.from_array(np.array(3, np.int8), "z")])
    assert note.startswith("quantization: 0 of 2 Quantize/DequantizeLinear nodes are not int8") and "2 have non-zero" in note


@pytest.mark.parametrize("name", ["edge", "edge-split-near35"])  # pseudo points sharing channels, or their own
def test_spec_channel_ranges_tile_the_bev_as_the_voxelizer_fills_it(name: str) -> None:
    """A port slices the BEV by these ranges: in order they cover every channel once, and only the reflectance
    range holds values other than 0 and 1."""
    preset = get_preset(name)
    ranges = port_spec(preset)["bev"]["channel_ranges"]
    pieces = [ranges["occupancy"], ranges["reflectance"]] + ([ranges["pseudo_occupancy"]] if preset.bev.split_pseudo else [])
    assert [lo for lo, _ in pieces] == [0] + [hi for _, hi in pieces[:-1]] and pieces[-1][1] == preset.bev.channels
    rng = np.random.default_rng(8)
    grid = preset.bev
    xyz = np.column_stack([rng.uniform(grid.x_min, grid.x_max, 5000), rng.uniform(grid.y_min, grid.y_max, 5000),
                           rng.uniform(grid.z_min, grid.z_max, 5000)])
    points = np.column_stack([xyz, rng.uniform(0.05, 0.95, 5000)]).astype(np.float32)
    bev = voxelize_bev(points, grid, pseudo=tuple(xyz[:2000].astype(np.float32).T))
    low, high = ranges["reflectance"]
    assert set(np.unique(np.delete(bev, np.arange(low, high), axis=0))) == {0.0, 1.0}
    assert ((bev[low:high] > 0) & (bev[low:high] < 1)).sum() > 1000


def test_graph_report_leaves_out_initializers_listed_as_inputs(tmp_path: Path) -> None:
    """An older exporter lists each weight among the graph inputs too; a port feeds only the real ones."""
    weight = numpy_helper.from_array(np.ones((1, 2), np.float32), "w")
    model = _model([helper.make_node("Add", ["x", "w"], ["y"])], [_value("x", [1, 2]), _value("w", [1, 2])],
                   [_value("y", [1, 2])], [weight])
    onnx.save(model, str(tmp_path / "add.onnx"))
    report = graph_report(tmp_path / "add.onnx")
    assert report["inputs"] == [{"name": "x", "dtype": "float32", "shape": [1, 2]}]
    assert report["static_shapes"] and report["opset"] == 18


# --------------------------------------------------------------------------- golden files (export/golden.py)
def test_array_writer_stores_booleans_as_bytes_and_every_array_little_endian(tmp_path: Path) -> None:
    """golden.json promises readers without a .npy parser little-endian data at data_offset, booleans as 0/1."""
    writer = golden.ArrayWriter(tmp_path)
    writer.save("mask", np.array([[True, False, True]]), "a mask")
    big = (np.arange(6).reshape(2, 3) + 0.5).astype(">f4")
    assert big.dtype.byteorder == ">"
    writer.save("big", big, "big-endian on the way in")
    assert writer.arrays["mask"]["dtype"] == "|u1" and writer.arrays["big"]["dtype"] == "<f4"
    for name, expected in (("mask", np.array([[1, 0, 1]], np.uint8)), ("big", big)):
        entry = writer.arrays[name]
        raw = (tmp_path / entry["file"]).read_bytes()[entry["data_offset"]:]
        assert len(raw) == entry["bytes"]
        np.testing.assert_array_equal(np.frombuffer(raw, entry["dtype"]).reshape(entry["shape"]), expected)


@pytest.fixture(scope="module")
def lidar_golden(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The 16-line PIXOR's golden set on the bundled 64-line scan as stored (--emulate-beams 0), threshold 0.3."""
    out = tmp_path_factory.mktemp("golden")
    golden.write_golden(LIDAR16, out, KITTI, "000006", beams=0, score_threshold=0.3)
    return out


def test_golden_frame_records_the_scan_and_threshold_asked_for(lidar_golden: Path) -> None:
    index = json.loads((lidar_golden / "golden.json").read_text())
    frame = index["frame"]
    assert frame["emulate_beams"] == 0 and frame["score_threshold"] == 0.3
    assert frame["points"] == frame["points_in_file"] == index["arrays"]["points"]["shape"][0]
    scores = np.load(lidar_golden / "candidate_scores.npy")
    assert scores.min() >= 0.3


def test_golden_tolerances_are_the_exports_parity_tolerances(lidar_golden: Path) -> None:
    """golden.json asks a port for what ONNX Runtime met against PyTorch (export/parity.py)."""
    index = json.loads((lidar_golden / "golden.json").read_text())
    tolerance = next(s for s in index["stages"] if s["stage"] == "pixor")["tolerance"]
    regression = np.load(lidar_golden / "regression.npy")
    assert tolerance["score"]["atol"] == parity.SCORE_MAX_ABSOLUTE
    scale = max(1.0, float(np.abs(regression).max()))
    assert tolerance["regression"]["atol"] == pytest.approx(parity.REGRESSION_RELATIVE_TO_SCALE * scale, rel=1e-12)
    assert golden.DEPTH_RTOL == parity.DEPTH_MAX_RELATIVE


@pytest.mark.parametrize(("name", "says"), [("bev", "bev: differs from what the Detector feeds pixor.onnx"),
                                            ("boxes", "boxes: "), ("scores", "boxes: ")])
def test_golden_arrays_that_differ_from_the_detectors_are_refused(lidar_golden: Path, tmp_path: Path, name: str,
                                                                  says: str) -> None:
    shutil.copytree(lidar_golden, tmp_path, dirs_exist_ok=True)
    index = json.loads((tmp_path / "golden.json").read_text())
    writer = golden.ArrayWriter(tmp_path, index["arrays"])
    array = np.load(tmp_path / f"{name}.npy")
    assert array.size
    array.flat[0] += 1e-6 if name != "bev" else 1.0
    np.save(tmp_path / f"{name}.npy", array)
    detector = Detector(LIDAR16, providers="cpu")
    frame = load_frame(KITTI, "000006", with_labels=False)
    with pytest.raises(golden.GoldenMismatch, match=says):
        golden._check_against_detector(detector, writer, frame, 0, 0.3)


def test_a_failed_golden_run_leaves_no_index_of_an_earlier_one(tmp_path: Path) -> None:
    """An index left from an earlier run must not describe the arrays of one that stopped half-way."""
    for stale in ("golden.json", "port.json"):
        (tmp_path / stale).write_text("{}")
    (tmp_path / "points.npy").mkdir()  # the first array cannot be written
    with pytest.raises(OSError):
        golden.write_golden(LIDAR16, tmp_path, KITTI, "000006")
    assert not (tmp_path / "golden.json").exists() and not (tmp_path / "port.json").exists()


def test_spec_only_refuses_a_model_directory_whose_files_changed(tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture) -> None:
    models = tmp_path / "models"
    shutil.copytree(LIDAR16, models)
    data = bytearray((models / "pixor.onnx").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (models / "pixor.onnx").write_bytes(bytes(data))
    code = golden.main(["--models", str(models), "--spec-only", "--out", str(tmp_path / "spec")])
    err = capsys.readouterr().err
    assert code == 2 and "pixor.onnx: sha256 mismatch" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "spec" / "port.json").exists()


def test_golden_refuses_a_frame_not_in_data_in_one_line_before_writing(tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture) -> None:
    code = golden.main(["--models", str(LIDAR16), "--frame", "999999", "--out", str(tmp_path / "golden")])
    err = capsys.readouterr().err
    assert code == 2 and err.strip() == f"error: --frame 999999: not in --data {KITTI} (no image_2/999999.png, " \
        "velodyne/999999.bin, calib/999999.txt)"
    assert not (tmp_path / "golden").exists()


# --------------------------------------------------------------------------- reduced precision (export/precision.py)
def test_the_calibration_reader_walks_the_range_it_is_given() -> None:
    """Strided min–max calls set_range(start, end) and reads exactly those frames, as float32."""
    frames = [{"x": np.full((1, 2), i, np.float16)} for i in range(6)]
    reader = _Reader(frames)
    assert len(reader) == 6
    reader.set_range(2, 4)
    seen = [reader.get_next() for _ in range(3)]
    assert seen[2] is None
    assert [float(f["x"][0, 0]) for f in seen[:2]] == [2.0, 3.0] and all(f["x"].dtype == np.float32 for f in seen[:2])


def _scaled(path: Path, factor: float, offset: float) -> None:
    """A graph y = x · factor + offset."""
    inits = [numpy_helper.from_array(np.array(factor, np.float32), "f"), numpy_helper.from_array(np.array(offset, np.float32), "o")]
    nodes = [helper.make_node("Mul", ["x", "f"], ["m"]), helper.make_node("Add", ["m", "o"], ["y"])]
    onnx.save(_model(nodes, [_value("x", [1, 4])], [_value("y", [1, 4])], inits), str(path))


def test_deviation_is_relative_to_at_least_one_metre_for_depth_absolute_for_scores_on_the_first_frames(
        tmp_path: Path) -> None:
    for folder, factor, offset in (("fp32", 1.0, 0.0), ("low", 1.01, 0.0)):
        (tmp_path / folder).mkdir()
        _scaled(tmp_path / folder / "depth.onnx", factor, offset)
    _scaled(tmp_path / "fp32" / "pixor.onnx", 1.0, 0.0)
    _scaled(tmp_path / "low" / "pixor.onnx", 1.0, 0.25)
    # 0.5 m on the first eight frames: 1 % of 0.5 m against one metre; the ninth (100 m, 1 %) is not read.
    frames = [{"x": np.full((1, 4), 0.5 if i < 8 else 100.0, np.float32)} for i in range(9)]
    report = deviation(tmp_path / "fp32", tmp_path / "low", {"depth": frames, "pixor": frames[:2]})
    assert report["depth"] == {"metric": "max relative error (depth)", "value": pytest.approx(0.005, rel=1e-4)}
    assert report["pixor"] == {"metric": "max absolute score error", "value": pytest.approx(0.25, rel=1e-5)}


def test_int8_activations_are_unsigned_and_weights_signed_per_channel(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    inits = [numpy_helper.from_array(rng.normal(0, 0.3, (5, 3, 3, 3)).astype(np.float32), "w1"),
             numpy_helper.from_array(rng.normal(0, 0.3, (2, 5, 3, 3)).astype(np.float32), "w2")]
    nodes = [helper.make_node("Conv", ["x", "w1"], ["c"], name="c1", pads=[1, 1, 1, 1]),
             helper.make_node("Relu", ["c"], ["r"], name="relu"),
             helper.make_node("Conv", ["r", "w2"], ["y"], name="c2", pads=[1, 1, 1, 1])]
    source, target = tmp_path / "fp32.onnx", tmp_path / "int8.onnx"
    onnx.save(_model(nodes, [_value("x", [1, 3, 8, 8])], [_value("y", [1, 2, 8, 8])], inits), str(source))
    feeds = [{"x": rng.uniform(0, 1, (1, 3, 8, 8)).astype(np.float32)} for _ in range(4)]
    to_int8(source, target, feeds, inputs_fp32=False, output_convs=1)
    model = onnx.load(str(target))
    stored = {i.name: i for i in model.graph.initializer}
    (quantize,) = [n for n in model.graph.node if n.op_type == "QuantizeLinear" and n.input[0] == "x"]
    assert stored[quantize.input[2]].data_type == TensorProto.UINT8
    (conv,) = [n for n in model.graph.node if n.op_type == "Conv" and n.name.startswith("c1")]
    (weights,) = [n for n in model.graph.node if n.output[0] == conv.input[1]]
    assert weights.op_type == "DequantizeLinear" and stored[weights.input[0]].data_type == TensorProto.INT8
    assert numpy_helper.to_array(stored[weights.input[1]]).shape == (5,)  # one scale per output channel


def _frames(folder: Path, count: int) -> Path:
    """A KITTI-layout folder of ``count`` frames: the bundled ones in turn, as symbolic links."""
    names = sorted(p.stem for p in (KITTI / "velodyne").glob("*.bin"))
    for sub, suffix in (("image_2", ".png"), ("velodyne", ".bin"), ("calib", ".txt")):
        (folder / sub).mkdir(parents=True)
        for i in range(count):
            (folder / sub / f"{i:06d}{suffix}").symlink_to(KITTI / sub / f"{names[i % len(names)]}{suffix}")
    return folder


@pytest.fixture(scope="module")
def edge_int8(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    """The shipped camera model converted to INT8 on one frame."""
    out = tmp_path_factory.mktemp("int8") / "int8"
    return out, convert_precision(WEIGHTS / "edge", out, "int8", KITTI, calibration_frames=1)


def test_int8_conversion_keeps_the_depth_nets_inputs_and_last_stage_fp32(edge_int8: tuple[Path, dict]) -> None:
    """The depth net's inputs (0–255, 0–85 m) are not quantized as they come, and its last two conv levels
    stay fp32; PIXOR's 0/1 BEV is."""
    out, _ = edge_int8
    depth = onnx.load(str(out / "depth.onnx"))
    read_raw = [n.name for n in depth.graph.node if n.op_type == "QuantizeLinear" and n.input[0] in ("rgb", "sparse_depth")]
    assert read_raw == []
    stored = {i.name for i in depth.graph.initializer}
    last = [n for n in depth.graph.node if n.op_type == "Conv"
            and n.name in set(boundary_nodes(depth, inputs=False, output_convs=2))]
    assert len(last) >= 2 and all(n.input[1] in stored for n in last), [n.name for n in last]
    pixor = onnx.load(str(out / "pixor.onnx"))
    assert any(n.op_type == "QuantizeLinear" and n.input[0] == "bev" for n in pixor.graph.node)


def test_int8_manifest_describes_the_graph_inputs_it_has(edge_int8: tuple[Path, dict]) -> None:
    """INT8 reads the split grid's 37 BEV channels whole again (the FP32 graph reads them in two pieces): the
    manifest a port feeds by says so."""
    out, _ = edge_int8
    fp32 = json.loads((WEIGHTS / "edge" / "manifest.json").read_text())
    assert len(fp32["networks"]["pixor"]["graph_inputs"]) == 2
    written = json.loads((out / "manifest.json").read_text())
    for name in ("depth", "pixor"):
        assert written["networks"][name]["graph_inputs"] == graph_inputs(out / f"{name}.onnx")
    assert written["networks"]["pixor"]["graph_inputs"] == [{"name": "bev", "shape": [1, 37, 400, 352]}]


def test_int8_deviation_is_measured_on_the_first_frames_of_more(trained_lidar_only: tuple[ExportResult, Path],
                                                                tmp_path: Path) -> None:
    """One frame more than DEVIATION_FRAMES calibrates it; the deviation from FP32 is measured on DEVIATION_FRAMES."""
    result, _ = trained_lidar_only
    data = _frames(tmp_path / "data", DEVIATION_FRAMES + 1)
    info = convert_precision(result.directory, tmp_path / "int8", "int8", data,
                             calibration_frames=DEVIATION_FRAMES + 1)["precision_info"]
    assert (info["calibration_frames"], info["deviation_frames"]) == (DEVIATION_FRAMES + 1, DEVIATION_FRAMES)


def test_a_hundred_calibration_frames_are_enough_to_say_nothing(trained_lidar_only: tuple[ExportResult, Path],
                                                                tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """The warning is for fewer than FEWEST_CALIBRATION_FRAMES (100) frames: at 100 the INT8 ranges stand."""
    result, _ = trained_lidar_only
    data = _frames(tmp_path, FEWEST_CALIBRATION_FRAMES)
    with caplog.at_level(logging.WARNING, logger="export.precision"):
        feeds = calibration_feeds(result.directory, data, 300)
    assert len(feeds["pixor"]) == FEWEST_CALIBRATION_FRAMES and "INT8 calibrated on" not in caplog.text
