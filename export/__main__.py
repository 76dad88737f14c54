"""``python -m export --preset P [--checkpoints DIR] --out DIR``: write depth.onnx, pixor.onnx, manifest.json."""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

from export.inputs import DEFAULT_FRAME, DEFAULT_KITTI_DIR
from export.precision import REDUCE_RANGE_HELP
from pipeline.cli import positive_int
from pipeline.errors import TORCH_MISSING
from pipeline.model_files import ModelFileError
from pipeline.presets import PRESETS, get_preset

try:
    from export.exporter import ExportConfig, run
    from export.parity import ParityError
except ModuleNotFoundError as exc:
    if exc.name != "torch":
        raise
    raise SystemExit(TORCH_MISSING) from exc


def parse_args(argv: list[str] | None = None) -> tuple[ExportConfig, argparse.Namespace]:
    parser = argparse.ArgumentParser(
        prog="python -m export",
        description="Export a preset's depth-completion net and PIXOR to ONNX, check ONNX Runtime against "
        "PyTorch on a real KITTI frame and random inputs, and write manifest.json.",
    )
    parser.add_argument("--preset", required=True, help=f"model preset: {', '.join(sorted(PRESETS))}, optionally with -no-gam, -no-aspp, -refine or -split")
    parser.add_argument("--out", required=True, type=Path, help="output model directory")
    parser.add_argument(
        "--checkpoints", type=Path, default=None,
        help="directory with depth.pt and/or pixor.pt (models/checkpoint.py); default: initialised, untrained weights",
    )
    parser.add_argument("--kitti-dir", type=Path, default=DEFAULT_KITTI_DIR, help="KITTI training dir for the parity frame")
    parser.add_argument("--frame", default=DEFAULT_FRAME, help="KITTI frame id for the parity check")
    parser.add_argument("--seed", type=int, default=0, help="seed for initial weights and random parity inputs")
    parser.add_argument("--no-parity", action="store_true", help="skip the ONNX Runtime vs PyTorch check")
    parser.add_argument("--precision", choices=["fp32", "fp16", "int8"], default="fp32",
                        help="fp32 (default); fp16 for GPUs; int8 static QDQ quantization for CPUs")
    parser.add_argument("--calibration-data", type=Path, default=DEFAULT_KITTI_DIR,
                        help="KITTI-layout folder whose frames calibrate int8 (default: the bundled KITTI frames)")
    parser.add_argument("--calibration-frames", type=positive_int, default=300, help="frames used for calibration (default 300)")
    parser.add_argument("--reduce-range", action="store_true", help=REDUCE_RANGE_HELP)
    parser.add_argument("--networks", nargs="+", default=["depth", "pixor"], choices=["depth", "pixor"],
                        help="networks to export (default both; 'pixor' alone for a LiDAR-only detector)")
    args = parser.parse_args(argv)
    if args.reduce_range and args.precision != "int8":
        parser.error(f"--reduce-range: applies to --precision int8 only, not {args.precision}")
    try:
        get_preset(args.preset)
    except ValueError as exc:
        parser.error(f"--preset: {exc}")
    return ExportConfig(
        preset=args.preset, out=args.out, checkpoints=args.checkpoints, kitti_dir=args.kitti_dir,
        frame=args.frame, seed=args.seed, parity=not args.no_parity, progress=True, networks=tuple(args.networks),
    ), args


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    config, args = parse_args(argv)
    try:
        return export(config, args)
    except (ValueError, FileNotFoundError, ModelFileError) as exc:  # checkpoints, calibration data, --out
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except ParityError as exc:  # nothing is written to --out; the numbers say why
        print(f"error: {exc}", file=sys.stderr)
        return 1


def export(config: ExportConfig, args: argparse.Namespace) -> int:
    """Export (and convert) as ``args`` asks; prints what was written."""
    if args.precision == "fp32":
        result = run(config)
        manifest = result.manifest
    else:
        from export.precision import convert_precision

        with tempfile.TemporaryDirectory(prefix="lowres3d-fp32-") as fp32_dir:
            result = run(replace(config, out=Path(fp32_dir)))
            manifest = convert_precision(Path(fp32_dir), config.out, args.precision, args.calibration_data,
                                         args.calibration_frames, progress=True, reduce_range=args.reduce_range)
        result = replace(result, directory=config.out, manifest=manifest)
        print(f"{args.precision}: deviation from fp32 {manifest['precision_info']['deviation_from_fp32']}")
    print(f"wrote {result.directory} (preset {manifest['preset']}, weights: {manifest['weights']})")
    for entry in manifest["networks"].values():
        print(f"  {entry['file']}: {entry['parameters']:,} parameters, {entry['flops'] / 1e9:.2f} GFLOP")
    for r in result.parity:
        print(f"  parity {r.network} {r.source}: {r.metric} {r.error:.2e} (≤ {r.tolerance:.0e})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
