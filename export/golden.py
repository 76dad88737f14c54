"""Golden inputs and outputs of every stage on one real frame, for a port to another runtime to test itself.

examples:
  python -m export.golden --models weights/edge --out /tmp/golden
  python -m export.golden --models weights/edge-lidar16 --spec-only --out /tmp/spec

Writes into --out (a folder outside the repository: the files are generated, about 30 MB):

- ``port.json``: the port spec of the model directory (export/port_spec.py: every constant and rule of the
  NumPy stages), where it came from (the manifest's ``port`` section, or computed from its preset for a
  manifest written before exports had one), and each ONNX graph as a port meets it (inputs, outputs, opset,
  operators, what TensorRT's parser refuses);
- one ``.npy`` file per array (little-endian, C order) and ``golden.json``: each array's file, dtype, shape
  and the byte offset of its data in the file (a reader without a .npy parser reads the bytes there), each
  stage's inputs and outputs, and the tolerance a port should meet on it.

Check each stage on the golden input of that stage, not on the port's own output of the stage before: a depth
difference of 1e-6 relative already moves pseudo points into other BEV voxels (docs/models.md, "Porting to
another runtime"). The golden boxes are checked against pipeline.detector.Detector on the same frame before
anything is written. Runs on the runtime install: ONNX Runtime and the pipeline, no torch.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import onnxruntime as ort

from export.inputs import DEFAULT_FRAME, DEFAULT_KITTI_DIR, check_frame
from export.port_spec import graph_report, port_spec_of
from pipeline.beams import BEAM_COUNTS, emulate_beams, lines_to_thin_to
from pipeline.bev import BevVoxelizer, PseudoBins, pseudo_bins
from pipeline.cli import check_not_input, check_output, interrupted, probability
from pipeline.detector import Detections, Detector, session_options, trained_lines
from pipeline.errors import InputError
from pipeline.frame import Frame, load_frame
from pipeline.graph_inputs import feeds_for
from pipeline.iou import rotated_nms
from pipeline.kitti import format_label
from pipeline.model_files import DEFAULT_MODELS, ModelFileError, load_manifest, verify_sha256
from pipeline.postprocess import estimate_heights
from pipeline.preprocess import depth_inputs, network_view
from pipeline.presets import Preset
from pipeline.pseudo import depth_jumps, depth_to_points
from pipeline.targets import decode_maps

GOLDEN_FORMAT = "lowres3d-golden/1"
INDEX_NAME, SPEC_NAME = "golden.json", "port.json"
RESULT_LINES_NAME = "result_lines.txt"  # the frame's KITTI result lines, as pipeline.detect writes them
# The export's parity tolerances (export/parity.py): what ONNX Runtime on the CPU met against PyTorch.
DEPTH_RTOL = 1e-3
SCORE_ATOL = 1e-4
REGRESSION_ATOL = 1e-3  # × max(1, max |golden regression|)


class GoldenMismatch(RuntimeError):
    """The stages computed here disagree with the Detector's own run: the golden files would mislead a port."""


@dataclass
class ArrayWriter:
    """Writes arrays as .npy into ``out`` and keeps the index a reader without NumPy needs."""

    out: Path
    arrays: dict[str, dict] = field(default_factory=dict)

    def save(self, name: str, array: np.ndarray, description: str) -> np.ndarray:
        """Write ``name``.npy (booleans as uint8 0/1, little-endian, C order); returns the array as written."""
        array = np.ascontiguousarray(array)
        if array.dtype == np.bool_:
            array = array.astype(np.uint8)
        array = array.astype(array.dtype.newbyteorder("<"), copy=False)
        path = self.out / f"{name}.npy"
        np.save(path, array, allow_pickle=False)
        self.arrays[name] = {"file": path.name, "dtype": array.dtype.str, "shape": list(array.shape),
                             "data_offset": path.stat().st_size - array.nbytes, "bytes": int(array.nbytes),
                             "description": description}
        return array


@dataclass
class Golden:
    """What :func:`write_golden` wrote: the index (golden.json) and the port spec (port.json)."""

    index: dict
    spec: dict


def model_facts(models: Path, manifest: dict) -> dict:
    """The model directory a port runs, as golden.json and port.json record it."""
    networks = manifest["networks"]
    return {
        "directory": str(models),
        "preset": manifest["preset"],
        "precision": manifest.get("precision", "fp32"),
        "sha256": {file: entry["sha256"] for file, entry in manifest["files"].items()},
        "two_stage": "depth" in networks,
        "scan_lines": trained_lines(networks["pixor"].get("training") or {}),
        "graph_inputs": {name: entry.get("graph_inputs") for name, entry in networks.items()},
    }


def spec_document(models: Path, manifest: dict) -> dict:
    """port.json: the port spec, where it came from, the model and its graphs."""
    spec, source = port_spec_of(manifest)
    graphs = {name: graph_report(models / entry["file"]) for name, entry in manifest["networks"].items()}
    return {**spec, "spec_source": source, "models": model_facts(models, manifest), "graphs": graphs}


def default_beams(manifest: dict) -> int:
    """The line count the bundled 64-line scans are thinned to: the model's own (0, as stored, for 64 lines; 16,
    the recipe's, when the manifest does not say), as every tool that feeds a model its own frames chooses."""
    return lines_to_thin_to(trained_lines(manifest["networks"]["pixor"].get("training") or {}))


def _sessions(models: Path, manifest: dict) -> dict[str, ort.InferenceSession]:
    """CPU sessions with the Detector's own options (the golden outputs are the runtime's)."""
    return {name: ort.InferenceSession(str(models / entry["file"]), session_options(),
                                       providers=["CPUExecutionProvider"])
            for name, entry in manifest["networks"].items()}


def write_golden(models: Path, out: Path, data: Path = DEFAULT_KITTI_DIR, frame_id: str = DEFAULT_FRAME,
                 beams: int | None = None, score_threshold: float | None = None) -> Golden:
    """Run one frame stage by stage, check the boxes against the Detector's, write everything into ``out``."""
    manifest = load_manifest(models)
    verify_sha256(models, manifest)
    check_frame(data, frame_id)
    beams = default_beams(manifest) if beams is None else beams
    detector = Detector(models, providers="cpu")
    preset = detector.preset
    threshold = preset.decode.score_threshold if score_threshold is None else score_threshold
    frame = load_frame(data, frame_id, with_labels=False)
    points = emulate_beams(frame.points, beams) if beams else frame.points

    out.mkdir(parents=True, exist_ok=True)
    # An index left from an earlier run must not describe these arrays, nor its lines pass for this frame's.
    for stale in (INDEX_NAME, SPEC_NAME, RESULT_LINES_NAME):
        (out / stale).unlink(missing_ok=True)
    writer = ArrayWriter(out)
    stages = _run_stages(writer, _sessions(models, manifest), preset, frame, points, detector.two_stage, threshold)
    result = _check_against_detector(detector, writer, frame, beams, threshold)
    # The frame's KITTI result lines, as pipeline.detect writes them: a port's last stage, checked to the character.
    lines = [format_label(obj) for obj in result.to_objects(frame.calib, frame.image_hw)]
    (out / RESULT_LINES_NAME).write_text("".join(f"{line}\n" for line in lines), encoding="utf-8")

    spec = spec_document(models, manifest)
    index = {
        "format": GOLDEN_FORMAT,
        "models": spec["models"],
        "frame": {"data": str(data), "frame": frame_id, "emulate_beams": beams, "score_threshold": threshold,
                  "points_in_file": int(frame.points.shape[0]), "points": int(points.shape[0])},
        "calibration": _calibration(frame, preset, detector.two_stage),
        "arrays": writer.arrays,
        "stages": stages,
        "end_to_end": {
            "compare": "boxes, not maps: chained stages move pseudo points into other voxels and PIXOR's maps "
                       "with them (docs/models.md, 'Porting to another runtime')",
            "tolerance": {"bev_iou_min": 0.9, "score_atol": 0.05,
                          "except": "golden boxes scoring within 0.05 of the score threshold may be missing, "
                                    "and a port's boxes there may be extra"},
        },
        "result_lines": {"file": RESULT_LINES_NAME, "lines": len(lines), "image_hw": list(frame.image_hw),
                         "rule": "port.json kitti_results (docs/models.md, 'The result lines'), on the golden boxes "
                                 "and scores with the full image's calibration",
                         "compare": "exact, character for character"},
        "checked": "boxes and scores equal to pipeline.detector.Detector.detect on the same frame and scan; "
                   "rgb, sparse_depth and bev equal to what it feeds the networks; result lines those "
                   "pipeline.detect writes",
    }
    (out / SPEC_NAME).write_text(json.dumps(spec, indent=2) + "\n", encoding="utf-8")
    (out / INDEX_NAME).write_text(json.dumps(index, indent=2) + "\n", encoding="utf-8")  # last: the run is whole
    return Golden(index=index, spec=spec)


def _calibration(frame: Frame, preset: Preset, two_stage: bool) -> dict:
    """The frame's calibration (float64 as JSON numbers) and, for a camera model, that of the depth net's view."""
    calib = {"P2": frame.calib.P2.tolist(), "R0_rect": frame.calib.R0_rect.tolist(),
             "Tr_velo_to_cam": frame.calib.Tr_velo_to_cam.tolist()}
    if two_stage:
        calib["view_P2"] = network_view(frame.image, frame.calib, preset)[1].P2.tolist()
        calib["image_hw"] = list(frame.image.shape[:2])
    return calib


def _run_stages(writer: ArrayWriter, sessions: dict[str, ort.InferenceSession], preset: Preset, frame: Frame,
                points: np.ndarray, two_stage: bool, threshold: float) -> list[dict]:
    """Each stage as the Detector runs it, its arrays written; returns the stages' index entries."""
    writer.save("points", points, "float32 (N, 4) x, y, z, reflectance: the scan every stage reads (thinned as "
                "frame.emulate_beams says)")
    stages, pseudo = _camera_stages(writer, sessions, preset, frame, points) if two_stage else ([], None)
    voxelizer = BevVoxelizer(preset.bev)
    bev = writer.save("bev", voxelizer(points, pseudo)[None], "float32 (1, C, ny, nx): pixor.onnx input bev (its "
                      "graph inputs bev[lo:hi] are channel ranges of it)")
    height = writer.save("height_occupancy", voxelizer.height_voxels(),
                         "uint8 (nz, ny, nx) 1 where a voxel counts for box heights")
    stages.append({"stage": "voxelize", "inputs": ["points"] + (["pseudo_points", "depth_jumps"] if two_stage else []),
                   "outputs": ["bev", "height_occupancy"],
                   "tolerance": {"bev": {"real_point_channels": "exact (occupancy and reflectance to 1e-6)",
                                         "pseudo_voxels_differing_max_share": 1e-3},
                                 "height_occupancy": {"voxels_differing_max_share": 1e-3}},
                   "note": "pseudo points within float32 rounding of a bin edge may land in the next voxel"})
    score, regression = sessions["pixor"].run(["score", "regression"], feeds_for(sessions["pixor"], {"bev": bev}))
    maps = f"ny/{preset.pixor.output_stride}, nx/{preset.pixor.output_stride}"  # the grid at PIXOR's output stride
    writer.save("score", score, f"float32 (1, 1, {maps}): pixor.onnx output score")
    writer.save("regression", regression, f"float32 (1, 6, {maps}): pixor.onnx output regression (normalised)")
    stages.append({"stage": "pixor", "inputs": ["bev"], "outputs": ["score", "regression"],
                   "tolerance": {"score": {"atol": SCORE_ATOL},
                                 "regression": {"atol": REGRESSION_ATOL * max(1.0, float(np.abs(regression).max())),
                                                "formula": f"{REGRESSION_ATOL} * max(1, max |golden regression|)"}}})
    stages.append(_decode_stage(writer, preset, score[0, 0], regression[0], height, two_stage, threshold))
    return stages


def _camera_stages(writer: ArrayWriter, sessions: dict[str, ort.InferenceSession], preset: Preset, frame: Frame,
                   points: np.ndarray) -> tuple[list[dict], PseudoBins]:
    """prepare, depth_net and pseudo_points; returns their index entries and the pseudo points' BEV bins."""
    save = writer.save
    save("image", frame.image, "uint8 (rows, columns, 3) RGB camera image")
    inputs = depth_inputs(frame.image, points, frame.calib, preset)
    save("view_image", network_view(frame.image, frame.calib, preset)[0],
         "uint8 (H, W, 3) RGB: the crop resized, before the float conversion")
    save("rgb", inputs.rgb, "float32 (1, 3, H, W): depth.onnx input rgb")
    save("sparse_depth", inputs.sparse_depth, "float32 (1, 1, H, W) metres, 0 = none: depth.onnx input sparse_depth")
    (depth,) = sessions["depth"].run(["depth"], feeds_for(sessions["depth"], {"rgb": inputs.rgb,
                                                                            "sparse_depth": inputs.sparse_depth}))
    save("depth", depth, "float32 (1, 1, H, W) metres: depth.onnx output depth")
    dense, limits = depth[0, 0], preset.pseudo_limits
    save("pseudo_points", depth_to_points(dense, inputs.calib, *limits),
         "float32 (M, 4) x, y, z, 0: the pseudo points, pixels in row-major order")
    save("depth_jumps", depth_jumps(dense, preset.decode.height_max_jump),
         "uint8 (H, W) 1 where the pixel lies on a depth jump (left out of the height occupancy)")
    stages = [
        {"stage": "prepare", "inputs": ["image", "points"], "outputs": ["view_image", "rgb", "sparse_depth"],
         "tolerance": {"view_image": "exact with OpenCV INTER_AREA (image.resize.uint8_equivalent)",
                       "rgb": "exact", "sparse_depth": {"nonzero_pixels": "the same", "rtol": 1e-6}}},
        {"stage": "depth_net", "inputs": ["rgb", "sparse_depth"], "outputs": ["depth"],
         "tolerance": {"depth": {"rtol": DEPTH_RTOL}},
         "note": "the export's parity tolerance; an FP16 engine is looser: compare its boxes"},
        {"stage": "pseudo_points", "inputs": ["depth"], "outputs": ["pseudo_points", "depth_jumps"],
         "calibration": "view_P2, R0_rect, Tr_velo_to_cam",
         "tolerance": {"pseudo_points": {"count": "the same", "atol_m": 1e-4}, "depth_jumps": "exact (float32 comparison)"}},
    ]
    # The BEV reads the pseudo points as the Detector does: straight from the depth map to their bins.
    return stages, pseudo_bins(dense, inputs.calib, preset.bev, *limits, max_jump=preset.decode.height_max_jump)


def _decode_stage(writer: ArrayWriter, preset: Preset, score: np.ndarray, regression: np.ndarray,
                  height: np.ndarray, two_stage: bool, threshold: float) -> dict:
    """Candidates, NMS and heights as pipeline.postprocess.boxes_from_maps runs them, each step written."""
    decode = preset.decode
    candidates, scores = decode_maps(score, regression, preset.bev, preset.pixor.output_stride, decode, threshold)
    writer.save("candidates", candidates, "float64 (K, 5) x, y, l, w, yaw before NMS, best score first")
    writer.save("candidate_scores", scores, "float64 (K,) their scores")
    kept = writer.save("kept", rotated_nms(candidates, scores, decode.nms_iou, decode.max_detections),
                       "int64 (D,) indices of the candidates NMS keeps, in order")
    bev_boxes = candidates[kept]
    z, h = estimate_heights(bev_boxes, height, preset, with_pseudo=two_stage)
    writer.save("boxes", np.column_stack([bev_boxes[:, :2], z, bev_boxes[:, 2:4], h, bev_boxes[:, 4]]).reshape(-1, 7),
                "float64 (D, 7) x, y, z, l, w, h, yaw in the LiDAR frame")
    writer.save("scores", scores[kept], "float64 (D,) their scores")
    return {"stage": "decode", "inputs": ["score", "regression", "height_occupancy"],
            "outputs": ["candidates", "candidate_scores", "kept", "boxes", "scores"],
            "tolerance": {"candidates": {"atol": 1e-6}, "kept": "exact", "boxes": {"atol": 1e-6}, "scores": {"atol": 0.0}}}


def _check_against_detector(detector: Detector, writer: ArrayWriter, frame: Frame, beams: int,
                            threshold: float) -> Detections:
    """GoldenMismatch unless the written arrays are what the Detector feeds its networks and gives as boxes; the
    Detector's result."""
    def written(name: str) -> np.ndarray:
        return np.load(writer.out / writer.arrays[name]["file"])

    image, calib = (frame.image, frame.calib) if detector.two_stage else (None, None)
    fed = detector.network_inputs(image, frame.points, calib, emulate_to_beams=beams or None)
    for network, arrays in fed.items():
        for name, array in arrays.items():
            if not np.array_equal(written(name), array):
                raise GoldenMismatch(f"{name}: differs from what the Detector feeds {network}.onnx")
    result = detector.detect(image, frame.points, calib, score_threshold=threshold, emulate_to_beams=beams or None)
    boxes, scores = written("boxes"), written("scores")
    if boxes.shape != result.boxes.shape or not np.allclose(boxes, result.boxes, rtol=0, atol=1e-9) \
            or not np.array_equal(scores, result.scores):
        raise GoldenMismatch(f"boxes: {len(boxes)} written, the Detector gives {len(result.boxes)} "
                             "(or they differ): the stages here no longer follow pipeline/detector.py")
    return result


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
                                     prog="python -m export.golden", description=__doc__.split("\n\n")[0],
                                     epilog=__doc__.split("\n\n", 1)[1],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", type=Path, default=DEFAULT_MODELS, metavar="DIR", help=f"model directory (default {DEFAULT_MODELS})")
    parser.add_argument("--data", type=Path, default=None, metavar="DIR",
                        help="KITTI object folder with image_2/, velodyne/, calib/ (default: the bundled "
                        "tests/data/kitti/training)")
    parser.add_argument("--frame", default=None, metavar="ID", help=f"frame id of --data (default {DEFAULT_FRAME})")
    parser.add_argument("--emulate-beams", type=int, metavar="N", choices=(0, *BEAM_COUNTS), default=None,
                        help="thin the 64-line scan to N lines first (default: the model's own line count, 16 for "
                        "the shipped camera model; 0: the scan as stored, as a 16-line sensor's own)")
    parser.add_argument("--score-threshold", type=probability, default=None, metavar="SCORE",
                        help="the decode's threshold (default: the model's, 0.5 for the shipped ones; 0.05 gives "
                        "NMS hundreds of candidates to agree on)")
    parser.add_argument("--spec-only", action="store_true",
                        help="write port.json alone (the constants and graphs), no frame")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR",
                        help="output folder for port.json, golden.json and the .npy files (outside the repository)")
    args = parser.parse_args(argv)
    if args.spec_only:
        given = [flag for flag, value in (("--data", args.data), ("--frame", args.frame),
                                          ("--emulate-beams", args.emulate_beams),
                                          ("--score-threshold", args.score_threshold)) if value is not None]
        if given:
            parser.error(f"{' and '.join(given)}: only used for the golden frame, which --spec-only skips")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    data = args.data or DEFAULT_KITTI_DIR
    try:
        check_output(args.out, "--out", directory=True)
        check_not_input(args.out, "--out", {"--models": args.models, "--data": data})
        if args.spec_only:
            manifest = load_manifest(args.models)
            verify_sha256(args.models, manifest)
            args.out.mkdir(parents=True, exist_ok=True)
            spec = spec_document(args.models, manifest)
            (args.out / SPEC_NAME).write_text(json.dumps(spec, indent=2) + "\n", encoding="utf-8")
            print(f"wrote {args.out / SPEC_NAME} (port spec {spec['spec_source']})")
            return 0
        golden = write_golden(args.models, args.out, data, args.frame or DEFAULT_FRAME, args.emulate_beams,
                              args.score_threshold)
    except (InputError, ModelFileError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except GoldenMismatch as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"error: --out {args.out}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return interrupted(f"{args.out} holds no {INDEX_NAME}: run again for a whole golden set")
    arrays = golden.index["arrays"]
    megabytes = sum(a["bytes"] for a in arrays.values()) / 1e6
    print(f"wrote {len(arrays)} arrays ({megabytes:.1f} MB), {INDEX_NAME} and {SPEC_NAME} to {args.out} "
          f"(port spec {golden.spec['spec_source']}); {len(np.load(args.out / arrays['boxes']['file']))} boxes, "
          "equal to the Detector's")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
