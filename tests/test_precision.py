"""FP16 and INT8 model directories: conversion, manifest, and the runtime on a real frame."""

import json

import numpy as np
import onnx
import pytest

from export.precision import convert_precision
from pipeline.detector import Detector
from pipeline.frame import load_frame
from pipeline.model_files import verify_sha256
from tests.conftest import KITTI


@pytest.fixture(scope="module")
def frame():
    return load_frame(KITTI, "000006")


@pytest.mark.parametrize("precision", ["int8", "fp16"])
def test_reduced_precision_directory(tiny_models, tmp_path, frame, precision):
    out = tmp_path / precision
    manifest = convert_precision(tiny_models, out, precision, KITTI, calibration_frames=3)
    assert manifest["precision"] == precision
    assert json.loads((out / "manifest.json").read_text())["precision"] == precision
    verify_sha256(out, manifest)
    info = manifest["precision_info"]
    assert info["calibration_frames"] == 3
    assert set(info["deviation_from_fp32"]) == {"depth", "pixor"}
    pixor = onnx.load(str(out / "pixor.onnx"))
    ops = {node.op_type for node in pixor.graph.node}
    if precision == "int8":
        assert {"QuantizeLinear", "DequantizeLinear"} <= ops
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


def test_unknown_precision(tiny_models, tmp_path):
    with pytest.raises(ValueError, match="--precision"):
        convert_precision(tiny_models, tmp_path / "x", "int4", KITTI)
