"""Reduced-precision model directories: FP16 for GPUs, INT8 (static, QDQ) for CPUs, fastest with VNNI.

    python -m export --preset P [--checkpoints DIR] --out DIR --precision fp16|int8
                     [--calibration-data DIR] [--calibration-frames N] [--reduce-range]

``--reduce-range`` quantizes the weights to 7 bits: on x86 CPUs without VNNI
ONNX Runtime sums pairs of uint8 × int8 products in 16 bits, which full 8-bit
weights can saturate (pipeline/cpu.py); with 7 bits the INT8 networks compute
the same on every CPU. The shipped ``weights/edge-int8`` is converted so.

FP16 converts weights and activations and keeps float32 inputs and outputs,
so the runtime feeds the same tensors. It first runs the FP32 graph on the
first frames and keeps in FP32 the nodes writing or reading a tensor FP16
cannot hold there (beyond ±65504, or a divisor below its normal range: the
edge depth net's prefill reciprocal is 1e6 where the map is empty), and it
fails when a tensor stored in FP16 would still overflow (export/fp16.py).
INT8 quantizes statically in QDQ format with unsigned 8-bit activations and
signed per-channel weights (on this AVX-512 VNNI CPU signed activations gave no
speed-up at all), calibrated on real frames run through the FP32 Detector:
each network sees exactly the tensors inference gives it (``Detector.network_inputs``), PIXOR the BEV with the
FP32 depth net's pseudo points. The depth net's ranges are the extremes over the
calibration frames, PIXOR's moving averages of the per-frame extremes. The
manifest records the precision, the calibration, the nodes FP16 keeps in FP32
and why, and each network's deviation from FP32 on the first calibration frames.
"""

from __future__ import annotations

import json
import logging
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import onnx
from tqdm import tqdm

from export.directory import check_destination, staged
from export.fp16 import (
    check_fp16_storage,
    drop_fp16_round_trips,
    fp16_ranges,
    fp16_unsafe_nodes,
    name_nodes,
    sort_topologically,
)
from export.manifest import graph_inputs, package_versions, write_manifest
from export.rewrite import (
    boundary_nodes,
    inputs_from_channel_pieces,
    inputs_from_channel_slices,
    merge_split_input_convs,
    pad_input_convs,
    quantize_before_pad,
    rewrite_transposed_convs,
)
from pipeline.beams import BEAM_COUNTS, lines_to_thin_to
from pipeline.cpu import describe as describe_cpu
from pipeline.detector import Detector
from pipeline.errors import InputError
from pipeline.frame import frame_ids, load_frame
from pipeline.graph_inputs import feeds_for
from pipeline.model_files import (
    PRECISIONS,
    ModelFileError,
    load_manifest,
    sha256_file,
    verify_sha256,
)
from pipeline.provenance import code_version

log = logging.getLogger(__name__)
REDUCE_RANGE_HELP = ("int8: weights in 7 bits, the same outputs on x86 CPUs without VNNI as with it (full 8-bit "
                     "weights can saturate ONNX Runtime's 16-bit sums of product pairs there: pipeline/cpu.py)")


DEVIATION_FRAMES = 8  # a converted network's deviation from fp32 is measured on the first frames' inputs
FEWEST_CALIBRATION_FRAMES = 100  # INT8 from fewer frames gets a warning: their ranges may clip real ones


def calibration_frame_ids(data: Path, frames: int) -> list[str]:
    """The first ``frames`` frame ids of the --calibration-data folder (InputError naming the flag when it has none)."""
    try:
        ids = frame_ids(data)
    except InputError as exc:
        raise InputError(f"--calibration-data {exc}") from None
    if not ids:
        raise InputError(f"--calibration-data {data}: no frames (velodyne/*.bin) to calibrate on")
    return ids[:frames]


def calibration_feeds(model_dir: Path, data: Path, frames: int, progress: bool = False, beams: int | None = None,
                      calibrating: bool = True) -> dict[str, list[dict]]:
    """Inputs of each network on the first ``frames`` frames of ``data``, exactly as the FP32 Detector feeds them.

    beams: thin each scan to this many lines first; None: to the model's own line count (16 when its manifest
    does not say; as stored for a model trained on 64-line scans), as the pipeline's tools do with 64-line data;
    0: the scans as stored (a 16-line sensor's own recordings).
    calibrating: INT8 (warns when the frames are few); FP16 only measures its deviation on them."""
    detector = Detector(model_dir)
    if beams is None:  # a model trained with --emulate-beams 8 calibrates on 8-line scans
        beams = lines_to_thin_to(detector.trained_lines)
    ids = calibration_frame_ids(data, frames)
    if calibrating and len(ids) < FEWEST_CALIBRATION_FRAMES:
        log.warning("warning: INT8 calibrated on %d frame(s) of %s: ranges from so few frames may clip real ones; "
                    "give a few hundred frames of your data (--calibration-frames, default 300)", len(ids), data)
    feeds: dict[str, list[dict]] = {name: [] for name in ("depth", "pixor") if name in detector.manifest["networks"]}
    for fid in tqdm(ids, desc="calibration frames", unit="frame", disable=not progress):
        frame = load_frame(data, fid, with_labels=False)
        try:
            inputs = detector.network_inputs(frame.image, frame.points, frame.calib, emulate_to_beams=beams or None)
        except InputError as exc:
            hint = "; give --emulate-beams 0 to use the scans as stored" if beams else ""
            raise InputError(f"--calibration-data {data}, frame {fid}: {exc}{hint}") from None
        for name, feed in inputs.items():
            # The BEV as float16 halves the memory of a few hundred frames (its values are 0/1 and heights).
            feeds[name].append({k: v.astype(np.float16) if name == "pixor" else v for k, v in feed.items()})
    return feeds


class _Reader:
    """ONNX Runtime's CalibrationDataReader protocol over a list of feeds (BEV kept as float16 to save memory).

    ``set_range`` lets the strided min–max calibration walk the frames a few at a time.
    """

    def __init__(self, feeds: list[dict]) -> None:
        self._feeds = feeds
        self._iter: Iterator[dict] = iter(feeds)

    def __len__(self) -> int:
        return len(self._feeds)

    def set_range(self, start_index: int, end_index: int) -> None:
        self._iter = iter(self._feeds[start_index:end_index])

    def get_next(self) -> dict | None:
        feed = next(self._iter, None)
        return None if feed is None else {k: v.astype(np.float32) for k, v in feed.items()}


def to_fp16(source: Path, target: Path, feeds: list[dict]) -> dict:
    """FP16 weights and activations, float32 inputs and outputs; the nodes whose tensors FP16 cannot hold on
    ``feeds`` stay FP32 (export/fp16.py). Returns what was done.

    FP16RangeError when a tensor the result holds in float16 would still overflow on ``feeds``."""
    from onnxruntime.transformers.float16 import convert_float_to_float16

    model = onnx.load(str(source))
    name_nodes(model)  # the converter keeps nodes FP32 by name
    ranges = fp16_ranges(model, feeds)
    kept_fp32 = fp16_unsafe_nodes(model, ranges)
    # The converter edits the graph it is given: give it a copy, the FP32 graph names what each tensor holds.
    converted = convert_float_to_float16(onnx.ModelProto.FromString(model.SerializeToString()),
                                         keep_io_types=True, node_block_list=list(kept_fp32))
    round_trips = drop_fp16_round_trips(converted)
    sort_topologically(converted.graph)
    largest, value = check_fp16_storage(model, converted, ranges, str(source))
    onnx.save(converted, str(target))
    return {"fp32_nodes": kept_fp32, "fp16_round_trips_removed": round_trips,
            "largest_fp16_value": {"tensor": largest, "value": value}}


def to_int8(source: Path, target: Path, feeds: list[dict], inputs_fp32: bool = True, output_convs: int = 1,
            moving_average: bool = False, reduce_range: bool = False) -> dict:
    """Static QDQ quantization: uint8 activations, int8 per-channel weights, min–max calibration.

    reduce_range: weights in −64…64 (255 · 64 · 2 < 2¹⁵), for x86 CPUs without VNNI, where ONNX Runtime adds pairs
    of uint8 × int8 products in 16 bits and full-range weights saturate them (pipeline/cpu.py).

    moving_average: each tensor's range is a moving average of the per-frame extremes (ONNX Runtime's
    ``CalibMovingAverage``, constant 0.01, as PyTorch's ``MovingAverageMinMaxObserver``) instead of the
    extremes over all frames, so a few outlying frames do not stretch the 256 steps.

    Transposed convs are rewritten as convs first so they are quantized too, quantized convs on a graph input
    read it whole and padded to a multiple of four channels (export/rewrite.py, 7), and the nodes
    between the last conv and the outputs (and with ``inputs_fp32`` between the inputs and the
    first conv) stay fp32 (export/rewrite.py says why). Min–max runs in strides of a few frames: ONNX
    Runtime's histogram calibrators keep every intermediate tensor of every calibration frame
    in memory (300 frames of the edge depth net exceeded 24 GB here). Returns what was done.
    """
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    with tempfile.TemporaryDirectory() as scratch:
        rewritten_path, prepared = Path(scratch) / "rewritten.onnx", Path(scratch) / "prepared.onnx"
        rewritten, count = rewrite_transposed_convs(onnx.load(str(source)))
        # Quantized input convs read whole, padded inputs (export/rewrite.py, 7); fp32 ones keep their split.
        # The quantizer calibrates on whole inputs: an input read in channel pieces (8) becomes one again.
        rewritten, _ = inputs_from_channel_pieces(rewritten)
        kept_fp32 = frozenset(boundary_nodes(rewritten, inputs=inputs_fp32, output_convs=output_convs))
        rewritten, merged = merge_split_input_convs(rewritten, skip=kept_fp32)
        rewritten, padded = pad_input_convs(rewritten, skip=kept_fp32)
        onnx.save(rewritten, str(rewritten_path))
        quant_pre_process(str(rewritten_path), str(prepared), skip_symbolic_shape=True)
        # The channel Pads stay out of the quantizer's hands (it would run them on dequantized floats between
        # two more Q/DQ pairs); quantize_before_pad then moves each behind its input's QuantizeLinear.
        prepared_model = onnx.load(str(prepared))
        pads = [node.name for node in prepared_model.graph.node if node.op_type == "Pad" and node.name.endswith("_pad")]
        kept_fp32 = boundary_nodes(prepared_model, inputs=inputs_fp32, output_convs=output_convs) + pads
        quantize_static(
            str(prepared), str(target), _Reader(feeds), quant_format=QuantFormat.QDQ,
            activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, per_channel=True, reduce_range=reduce_range,
            calibrate_method=CalibrationMethod.MinMax, nodes_to_exclude=kept_fp32,
            # ONNX Runtime wants the stride to divide the frame count: the largest divisor up to 10.
            extra_options={"CalibStridedMinMax": max(d for d in range(1, 11) if len(feeds) % d == 0),
                           "CalibMovingAverage": moving_average},
        )
        quantized, moved = quantize_before_pad(onnx.load(str(target)))
        # An input conv kept fp32 keeps its split: its input goes back to channel pieces (8).
        quantized, pieces = inputs_from_channel_slices(quantized)
        if moved or pieces:
            onnx.save(quantized, str(target))
    return {"transposed_convs_rewritten": count, "input_convs_merged": merged, "input_convs_padded": padded,
            "pads_after_quantize": moved,
            "fp32_nodes": kept_fp32,
            "calibration": "min-max, moving average (0.01)" if moving_average else "min-max"}


def deviation(fp32_dir: Path, reduced_dir: Path, feeds: dict[str, list[dict]],
              files: dict[str, str] | None = None) -> dict:
    """Max deviation of each reduced network from FP32 on the first frames' inputs (for INT8: frames it was
    calibrated on, so a check that the conversion worked, not a measure of accuracy: benchmarks/accuracy.py).

    files: each network's file name in both directories, as the manifest's ``networks.NAME.file`` names it
    (default: the exporter's, ``NAME.onnx``)."""
    import onnxruntime as ort

    report = {}
    for name, samples in feeds.items():
        file = (files or {}).get(name, f"{name}.onnx")
        ref = ort.InferenceSession(str(fp32_dir / file), providers=["CPUExecutionProvider"])
        low = ort.InferenceSession(str(reduced_dir / file), providers=["CPUExecutionProvider"])
        errors = []
        for feed in samples[:DEVIATION_FRAMES]:
            feed = {k: v.astype(np.float32) for k, v in feed.items()}
            a, b = ref.run(None, feeds_for(ref, feed))[0], low.run(None, feeds_for(low, feed))[0]
            errors.append(float(np.max(np.abs(a - b) / np.maximum(np.abs(a), 1.0))) if name == "depth"
                          else float(np.max(np.abs(a - b))))
        report[name] = {"metric": "max relative error (depth)" if name == "depth" else "max absolute score error",
                        "value": max(errors)}
    return report


def convert_precision(fp32_dir: Path, out: Path, precision: str, calibration_data: Path,
                      calibration_frames: int = 300, progress: bool = False, reduce_range: bool = False,
                      source: str | None = None, beams: int | None = None) -> dict:
    """Write ``out`` as a copy of the FP32 directory ``fp32_dir`` at ``precision``; returns the manifest.

    reduce_range: INT8 weights in 7 bits, the same outputs on every x86 CPU (:func:`to_int8`). source: what the
    manifest records as the FP32 source (default ``fp32_dir``; say what made it when that is a temporary
    folder). beams: how the calibration scans are thinned (:func:`calibration_feeds`). FP16 reads only the
    first DEVIATION_FRAMES frames, for its deviation from fp32.
    """
    if precision not in PRECISIONS:
        raise ValueError(f"--precision: {precision!r} is not one of {', '.join(PRECISIONS)}")
    if reduce_range and precision != "int8":
        raise ValueError(f"--reduce-range: applies to --precision int8 only, not {precision}")
    if beams not in (None, 0, *BEAM_COUNTS):  # argparse's choices, for library callers: before any model loads
        raise InputError(f"--emulate-beams: {beams} is not one of 0, {', '.join(map(str, BEAM_COUNTS))}")
    fp32_dir, out = Path(fp32_dir), Path(out)
    manifest = load_manifest(fp32_dir)  # ModelFileError naming the file when it is missing or broken
    verify_sha256(fp32_dir, manifest)
    held = manifest.get("precision", "fp32")
    if held != "fp32":  # quantizing a quantized graph again gives an invalid model
        came_from = manifest.get("precision_info", {}).get("source", {}).get("directory")
        raise ModelFileError(f"--models {fp32_dir}: holds {held} models; convert the FP32 directory"
                             + (f" it came from ({came_from})" if came_from else "") + " instead")
    if precision == "fp32":
        if out.resolve() != fp32_dir.resolve():
            check_destination(out, manifest.get("preset"), "fp32")
            with staged(out, source=fp32_dir):
                pass
        return manifest
    if out.resolve() == fp32_dir.resolve():
        raise ModelFileError(f"--out {out}: is --models itself; the FP32 source must stay (its manifest records "
                             "where a converted directory came from): give a new folder")
    check_destination(out, manifest.get("preset"), precision)
    source_files = dict(manifest["files"])
    int8 = precision == "int8"
    feeds = calibration_feeds(fp32_dir, calibration_data, calibration_frames if int8 else DEVIATION_FRAMES,
                              progress, beams, calibrating=int8)
    with staged(out, source=fp32_dir) as staging:
        _convert(fp32_dir, staging, manifest, source_files, feeds, precision, calibration_data, reduce_range,
                 source)
    return manifest


def _convert(fp32_dir: Path, out: Path, manifest: dict, source_files: dict, feeds: dict, precision: str,
             calibration_data: Path, reduce_range: bool = False, source: str | None = None) -> None:
    """Convert the networks of the copy ``out`` in place and write its manifest (see :func:`convert_precision`)."""
    graph_info: dict[str, dict] = {}
    for name, frames in feeds.items():
        path = out / manifest["networks"][name]["file"]
        if precision == "fp16":
            graph_info[name] = to_fp16(fp32_dir / path.name, path, frames)
        else:
            # The depth net's inputs span 0–255 and 0–85 m; PIXOR's BEV is 0/1 occupancy: uint8 holds it.
            # The depth net's last decoder stage stays fp32 too (output_convs 2): with the prefill its output
            # is a correction of centimetres to the filled map, and uint8 decoder features put 0.19 m of
            # median error at 0–10 m where fp32 has 0.08 m (BEV AP at IoU 0.7 moderate 77.3 vs 82.6).
            # The depth net's ranges are the extremes over the calibration frames (averaged, its median
            # error at 0–10 m grew from 122 to 140 mm); PIXOR's are moving averages of the per-frame
            # extremes. Calibrated on the BEV the Detector feeds it (session 34), the camera PIXOR on the
            # split grid lost 0.5 BEV AP at IoU 0.7 moderate so (85.8 → 85.3 on the 300 validation frames)
            # and 1.7 with the extremes (84.1). Until then calibration voxelized the merged cloud, which
            # leaves the split grid's pseudo channels empty; on those inputs the extremes had lost 1.1 and
            # the averages 3.4 (docs/measurements.md, sessions 25 and 34).
            graph_info[name] = to_int8(fp32_dir / path.name, path, frames, inputs_fp32=name == "depth",
                                       output_convs=2 if name == "depth" else 1, moving_average=name == "pixor",
                                       reduce_range=reduce_range)
        # What is written must be a valid graph (the FP16 converter once left its Casts out of order).
        onnx.checker.check_model(str(path), full_check=True)
        manifest["files"][path.name] = {"sha256": sha256_file(path), "bytes": path.stat().st_size}
        manifest["networks"][name]["graph_inputs"] = graph_inputs(path)  # INT8 reads the BEV whole again
    manifest["precision"] = precision
    # The FP32 export's parity check, CPU lowering and package versions describe the source's files, not these:
    # they move under precision_info.source, and this conversion's versions take their place.
    fp32_records = {"parity": manifest.pop("parity", None), "versions": manifest.get("versions"),
                    "code": manifest.get("code"), "export": manifest.pop("export", None)}
    manifest["versions"] = package_versions(("onnx", "onnxruntime", "numpy"))
    manifest["code"] = code_version()
    manifest["precision_info"] = {
        # Which FP32 files this directory was converted from (their manifest's sha256s), and what that export said.
        "source": {"directory": source or str(fp32_dir),
                   "sha256": {name: entry["sha256"] for name, entry in source_files.items()}, **fp32_records},
        **({"calibration_data": str(calibration_data), "calibration_frames": len(next(iter(feeds.values()))),
            "activations": "uint8", "weights": "int8 per channel" + (", 7-bit range" if reduce_range else ""),
            "reduce_range": reduce_range, "format": "QDQ",
            "calibration": {name: info["calibration"] for name, info in graph_info.items()},
            "graph": graph_info} if precision == "int8"
           # fp32_nodes: what FP16 cannot hold on the deviation frames stays FP32, each node with why.
           else {"io": "float32 (keep_io_types)", "graph": graph_info}),
        "deviation_from_fp32": deviation(fp32_dir, out, feeds,
                                         {name: manifest["networks"][name]["file"] for name in feeds}),
        "deviation_data": str(calibration_data),
        "deviation_frames": min(DEVIATION_FRAMES, len(next(iter(feeds.values())))),
        # Full-range INT8 computes differently on CPUs whose pair sums saturate: where was it measured?
        "deviation_measured_on": describe_cpu(),
    }
    write_manifest(out, manifest)
    verify_sha256(out, manifest)


def main(argv: list[str] | None = None) -> int:
    """``python -m export.precision --models DIR --precision int8 --out DIR``: convert an existing directory."""
    import argparse
    import sys

    from export.inputs import DEFAULT_KITTI_DIR
    from pipeline.cli import (
        HelpFormatter,
        check_not_inside,
        examples,
        interrupted,
        positive_int,
        show_progress,
    )

    parser = argparse.ArgumentParser(
        allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
        prog="python -m export.precision", description="Convert an FP32 model directory to FP16 or INT8 (QDQ).",
        epilog=examples("python -m export.precision --models weights/edge --precision int8 --calibration-data "
                        "data/sim/val --out weights/own-int8"),
        formatter_class=HelpFormatter)
    parser.add_argument("--models", type=Path, required=True, metavar="DIR",
                        help="FP32 model directory (manifest.json + ONNX files)")
    parser.add_argument("--precision", choices=["fp16", "int8"], required=True,
                        help="fp16 for GPUs (I/O stays float32); int8 static QDQ quantization for CPUs")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="output model directory")
    parser.add_argument("--calibration-data", type=Path, default=DEFAULT_KITTI_DIR, metavar="DIR",
                        help="KITTI-layout folder: INT8 calibrates on its frames, and both precisions measure their "
                        "deviation from fp32 there (default: the bundled real KITTI frames, as python -m export; "
                        "give a few hundred frames of your data for INT8)")
    parser.add_argument("--calibration-frames", type=positive_int, default=300, metavar="N",
                        help="int8: the first N frames calibrate it (default 300; fewer than 100 get a warning); fp16 "
                        f"reads only the first {DEVIATION_FRAMES}, for its deviation from fp32")
    parser.add_argument("--reduce-range", action="store_true", help=REDUCE_RANGE_HELP)
    # argparse's choices: a count a 64-line scan cannot thin to is refused here, naming the flag, not at frame one.
    parser.add_argument("--emulate-beams", "--beams", dest="beams", type=int, choices=(0, *BEAM_COUNTS), metavar="N",
                        help=f"thin the calibration scans to N lines first ({', '.join(map(str, BEAM_COUNTS))}; "
                        "default: the model's own line count, 16 when its manifest does not say, the scans as "
                        "stored for a model trained on 64-line scans; 0: the scans as stored, e.g. a 16-line "
                        "sensor's own recordings)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        # --out is replaced whole once the converted model is written: not with its inputs in it.
        check_not_inside(args.out, "--out", {"--models": args.models, "--calibration-data": args.calibration_data})
        manifest = convert_precision(args.models, args.out, args.precision, args.calibration_data,
                                     args.calibration_frames, progress=show_progress(False), reduce_range=args.reduce_range,
                                     beams=args.beams)
    except (InputError, ModelFileError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # an unwritable or full --out: the source and any earlier --out are untouched
        print(f"error: {exc.filename or args.out}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # the staging folder is removed; --out is swapped in only at the end
        return interrupted(f"--out {args.out} is as it was (nothing written)")
    print(f"wrote {args.out} ({args.precision}); deviation from fp32: "
          f"{json.dumps(manifest['precision_info']['deviation_from_fp32'])}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
