"""``python -m export [--preset P|FILE.json] [--checkpoints DIR] --out DIR``: write depth.onnx, pixor.onnx, manifest.json."""

from __future__ import annotations

import argparse
import logging
import os
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

from pipeline.cli import (  # first: the standard library alone, so that Ctrl-C below is told in one line
    HelpFormatter,
    check_not_inside,
    ctrl_c_held_while_loading,
    examples,
    interrupted,
    missing_extra,
    non_negative_int,
    positive_int,
    show_progress,
    unwritable,
)
from pipeline.errors import TORCH_MISSING

# Ctrl-C while the imports below load (NumPy, ONNX, ONNX Runtime, PyTorch: the command's first second or two) ends
# the command in one line once they are done, as in models/__init__.py (which this cannot import before PyTorch).
with ctrl_c_held_while_loading(__name__ == "__main__"):  # an importer's Ctrl-C stays theirs
    try:
        from export.directory import check_destination
        from export.exporter import ExportConfig, checkpoint_preset, export_preset, run
        from export.inputs import DEFAULT_FRAME, DEFAULT_KITTI_DIR
        from export.parity import ParityError
        from export.precision import REDUCE_RANGE_HELP, calibration_frame_ids
        from pipeline.model_files import ModelFileError
        from pipeline.presets import ABLATIONS, PRESETS, get_preset, is_preset_file
    except ModuleNotFoundError as exc:
        if exc.name != "torch":
            raise
        raise missing_extra(TORCH_MISSING) from exc  # one error line, exit status 2


def parse_args(argv: list[str] | None = None) -> tuple[ExportConfig, argparse.Namespace]:
    parser = argparse.ArgumentParser(
        allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
        prog="python -m export",
        description="Export a preset's depth-completion net and PIXOR to ONNX, check ONNX Runtime against "
        "PyTorch on a real KITTI frame and random inputs, and write manifest.json.",
        epilog=examples("python -m export --preset edge-split-near35 --checkpoints runs/edge/joint --out weights/own",
                        "python -m export --checkpoints runs/edge/joint --precision int8 "
                        "--calibration-data data/sim/val --out weights/own-int8"),
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--preset", metavar="P", help=f"model preset: {', '.join(sorted(PRESETS))}, optionally with "
                        f"suffixes {', '.join(ABLATIONS)} (the shipped camera model: edge-split-near35), or a preset "
                        "file FILE.json (docs/models.md, \"Adding a preset\"); default with --checkpoints: the preset "
                        "they were trained with (PIXOR's)")
    parser.add_argument("--out", required=True, type=Path, metavar="DIR",
                        help="output model directory: new, empty, or a model directory to replace (only once the new "
                        "one is written and checked)")
    parser.add_argument(
        "--checkpoints", type=Path, default=None, metavar="DIR",
        help="directory with depth.pt and/or pixor.pt (models/checkpoint.py); default: initialised, untrained weights",
    )
    # Defaults of None: a flag given with --no-parity (or a calibration flag with fp32) is refused, not ignored.
    parser.add_argument("--data", "--kitti-dir", dest="kitti_dir", type=Path, default=None, metavar="DIR",
                        help="KITTI training folder of the parity frame (default: the bundled tests/data/kitti/training)")
    parser.add_argument("--frame", default=None, metavar="ID", help=f"KITTI frame id for the parity check (default {DEFAULT_FRAME})")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="seed for initial weights and random parity inputs (default 0)")
    parser.add_argument("--no-parity", action="store_true", help="skip the ONNX Runtime vs PyTorch check")
    parser.add_argument("--precision", choices=["fp32", "fp16", "int8"], default="fp32",
                        help="fp32 (default); fp16 for GPUs; int8 static QDQ quantization for CPUs")
    parser.add_argument("--calibration-data", type=Path, default=None, metavar="DIR",
                        help="fp16/int8: KITTI-layout folder whose frames calibrate int8 and measure the deviation "
                        "from fp32 (default: the bundled KITTI frames)")
    parser.add_argument("--calibration-frames", type=positive_int, default=None, metavar="N",
                        help="fp16/int8: frames of --calibration-data used (default 300)")
    parser.add_argument("--reduce-range", action="store_true", help=REDUCE_RANGE_HELP)
    parser.add_argument("--networks", nargs="+", default=["depth", "pixor"], choices=["depth", "pixor"],
                        help="networks to export (default both; 'pixor' alone for a LiDAR-only detector)")
    args = parser.parse_args(argv)
    _refuse_contradictions(parser, args)
    if args.preset is None and args.checkpoints is None:
        parser.error("--preset: needed without --checkpoints (with them, export takes the preset they were trained "
                     "with)")
    if args.preset is not None:
        try:
            get_preset(args.preset)
        except ValueError as exc:
            if is_preset_file(args.preset):  # the file's fault, in one line: argparse's usage says nothing of it
                print(f"error: --preset: {exc}", file=sys.stderr)
                raise SystemExit(2) from None
            parser.error(f"--preset: {exc}{_trained_with(args.preset, args.checkpoints, tuple(args.networks))}")
    return ExportConfig(
        preset=args.preset, out=args.out, checkpoints=args.checkpoints, kitti_dir=args.kitti_dir or DEFAULT_KITTI_DIR,
        frame=args.frame or DEFAULT_FRAME, seed=args.seed, parity=not args.no_parity, progress=show_progress(False),
        networks=tuple(dict.fromkeys(args.networks)),
    ), args


def _trained_with(name: str, checkpoints: Path | None, networks: tuple[str, ...]) -> str:
    """A hint when an unknown ``--preset`` is the one ``--checkpoints`` were trained with: the checkpoint holds that
    preset's configuration, which export takes when --preset is left out."""
    if checkpoints is None:
        return ""
    try:
        preset, path = checkpoint_preset(ExportConfig(preset=None, out=Path(), checkpoints=checkpoints, networks=networks))
    except (ValueError, OSError):  # no checkpoints there: --checkpoints' own error comes later
        return ""
    return (f"; {path} was trained with preset {name!r}: leave --preset out, and export takes that checkpoint's own "
            "(its preset_config)") if preset.name == name else ""


def _refuse_contradictions(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Flags that would be silently ignored are refused (argparse's exit 2), and the defaults filled in."""
    if args.reduce_range and args.precision != "int8":
        parser.error(f"--reduce-range: applies to --precision int8 only, not {args.precision}")
    if args.no_parity:
        given = [flag for flag, value in (("--data", args.kitti_dir), ("--frame", args.frame)) if value is not None]
        if given:
            parser.error(f"{' and '.join(given)}: only used by the parity check, which --no-parity skips")
    if args.precision == "fp32":
        given = [flag for flag, value in (("--calibration-data", args.calibration_data),
                                          ("--calibration-frames", args.calibration_frames)) if value is not None]
        if given:
            parser.error(f"{' and '.join(given)}: only used by --precision fp16 or int8, not fp32")
    if "pixor" not in args.networks:
        parser.error("--networks: every model directory has pixor; choose 'depth pixor' or 'pixor'")
    args.calibration_data = args.calibration_data or DEFAULT_KITTI_DIR
    args.calibration_frames = args.calibration_frames or 300


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    for chatty in ("onnx_ir", "onnxscript"):  # torch.onnx's passes log each rewrite at INFO: ~20 lines an export
        logging.getLogger(chatty).setLevel(logging.WARNING)
    config, args = parse_args(argv)
    try:
        return export(config, args)
    except (ValueError, FileNotFoundError, ModelFileError) as exc:  # checkpoints, calibration data, --out
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except ParityError as exc:  # nothing is written to --out; the numbers say why
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:  # a full disk or a vanished folder while writing: --out is as it was
        print(unwritable(config.out, exc), file=sys.stderr)
        return 2
    except BaseException as exc:
        if not _interrupted(exc):
            raise
        return interrupted(f"--out {config.out} is as it was (nothing written)")


def _interrupted(exc: BaseException | None) -> bool:
    """Whether ``exc`` is Ctrl-C, or an error raised while handling it: torch.onnx.export turns a
    KeyboardInterrupt during tracing into a TorchExportError that asks for a bug report."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def export(config: ExportConfig, args: argparse.Namespace) -> int:
    """Export (and convert) as ``args`` asks; prints what was written."""
    # --out is replaced whole once the new model is written: --out M --data M/kitti deleted the frames.
    check_not_inside(config.out, "--out", {
        "--checkpoints": config.checkpoints, "--data": config.kitti_dir if config.parity else None,
        "--calibration-data": args.calibration_data if args.precision != "fp32" else None})
    if args.precision == "fp32":
        result = run(config)
        manifest = result.manifest
    else:
        from export.precision import convert_precision

        # Checked before the fp32 export, which takes minutes, rather than by the conversion after it.
        preset = export_preset(config)
        check_destination(config.out, preset.name, args.precision)
        calibration_frame_ids(args.calibration_data, 1)  # a folder without frames: refused now
        with tempfile.TemporaryDirectory(prefix="lowres3d-fp32-") as fp32_dir:
            result = run(replace(config, out=Path(fp32_dir)), preset)
            # The FP32 directory is temporary: record what made it, not a folder that is gone after this.
            preset_flag = f" --preset {config.preset}" if config.preset is not None else ""
            made_by = (f"not kept: python -m export{preset_flag} --networks {' '.join(config.networks)}"
                       + (f" --checkpoints {config.checkpoints}" if config.checkpoints else " (initialised)"))
            manifest = convert_precision(Path(fp32_dir), config.out, args.precision, args.calibration_data,
                                         args.calibration_frames, progress=show_progress(False), reduce_range=args.reduce_range,
                                         source=made_by)
        result = replace(result, directory=config.out, manifest=manifest)
        print(f"{args.precision}: deviation from fp32 {manifest['precision_info']['deviation_from_fp32']}")
    print(f"wrote {result.directory} (preset {manifest['preset']}, weights: {manifest['weights']})")
    for entry in manifest["networks"].values():
        print(f"  {entry['file']}: {entry['parameters']:,} parameters, {entry['flops'] / 1e9:.2f} GFLOP")
    for r in result.parity:
        print(f"  parity {r.network} {r.source}: {r.metric} {r.error:.2e} (≤ {r.tolerance:.2e})")
    return 0


if __name__ == "__main__":
    status = main()
    if status == 130:
        # Ctrl-C was handled and reported, but when it lands inside torch.onnx.export CPython can still hold
        # it as unhandled and, at exit, kill the process with SIGINT (exit -2, 1 run in 5 here) instead of
        # exiting 130. Nothing is left to clean up by then: leave at once with the status that was reported.
        sys.stderr.flush()
        os._exit(status)
    sys.exit(status)
