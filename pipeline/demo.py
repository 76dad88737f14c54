"""The Quickstart's main job: run lowres3d end to end on a bundled real KITTI frame.

With a model directory (the shipped ``weights/edge`` by default) it runs the
detector on the frame's scan thinned to the lines the model was trained on (16
for the shipped camera model; a 64-line model takes it as stored), as
``pipeline.detect --emulate-beams`` would, and writes the KITTI result file, the
BEV picture and the camera view. With ``--core`` (or
when the default directory is missing) it runs the frame-processing core alone
— 16-line emulation, the depth-net view and its sparse depth, the BEV tensor —
and writes pictures of each step.

    python -m pipeline.demo [--models DIR | --core] [--frame 000006] [--out outputs/demo]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from pipeline.beams import emulate_beams, lines_to_thin_to, recover_rings
from pipeline.bev import voxelize_bev
from pipeline.boxes import labels_to_boxes
from pipeline.cli import HelpFormatter, examples, quiet_interrupt, unwritable
from pipeline.errors import InputError
from pipeline.frame import load_frame
from pipeline.kitti import SAMPLE_DIR
from pipeline.model_files import DEFAULT_MODELS, ModelFileError, load_manifest
from pipeline.preprocess import depth_inputs
from pipeline.presets import get_preset
from pipeline.render import depth_colours, draw_colour_scale, draw_label, render_bev, render_depth, write_png


def sparse_depth_picture(rgb: np.ndarray, sparse_depth: np.ndarray, max_depth: float = 80.0,
                         frame_id: str | None = None) -> np.ndarray:
    """The depth net's view of the camera above the sparse depth it gets from the 16-line scan (each return
    grown to 3 × 3 pixels to be seen), each labelled (the camera's label with ``frame_id``: which frame it is),
    the depth with its colour bar."""
    view = cv2.cvtColor(rgb[0].transpose(1, 2, 0).astype(np.uint8), cv2.COLOR_RGB2BGR)
    sparse = render_depth(cv2.dilate(sparse_depth[0, 0], np.ones((3, 3), np.uint8)), max_depth)
    draw_colour_scale(sparse, depth_colours(max_depth), 0.0, max_depth, "m", length=120)
    which = f"KITTI {frame_id}: " if frame_id else ""
    return np.vstack([draw_label(view, f"{which}camera, the depth net's view"),
                      draw_label(sparse, "sparse depth, 16 lines (black: none)")])


def run_core(frame_id: str, out: Path, preset_name: str = "edge") -> dict:
    """Frame-processing core on one real frame; returns a summary and writes pictures into ``out``."""
    preset = get_preset(preset_name)
    frame = load_frame(SAMPLE_DIR, frame_id)
    assert frame.image is not None  # loaded with its image (with_image=True)
    tic = time.perf_counter()
    rings = recover_rings(frame.points)
    lidar16 = emulate_beams(frame.points, 16)
    inputs = depth_inputs(frame.image, lidar16, frame.calib, preset)
    bev64 = voxelize_bev(frame.points, preset.bev)
    bev16 = voxelize_bev(lidar16, preset.bev)
    elapsed = (time.perf_counter() - tic) * 1e3
    cars = labels_to_boxes([o for o in (frame.labels or []) if o.type == "Car"], frame.calib)
    out.mkdir(parents=True, exist_ok=True)
    pictures = []
    for lines, points in ((64, frame.points), (16, lidar16)):
        title = f"KITTI {frame_id}: {'the 64-line scan' if lines == 64 else 'the scan thinned to 16 lines'}"
        pictures.append(out / f"{frame_id}_bev_{lines}.png")
        write_png(pictures[-1], render_bev(points, preset.bev, gt_boxes=cars, title=title, legend=True))
    pictures.append(out / f"{frame_id}_sparse_depth_16.png")
    write_png(pictures[-1], sparse_depth_picture(inputs.rgb, inputs.sparse_depth, frame_id=frame_id))
    return {
        "frame": frame_id, "mode": "core (no model directory)", "points_64": int(frame.points.shape[0]),
        "rings_found": rings.n_rings, "points_16": int(lidar16.shape[0]),
        "kept_fraction": round(lidar16.shape[0] / frame.points.shape[0], 4),
        "sparse_depth_pixels": int(np.count_nonzero(inputs.sparse_depth)),
        "occupied_voxels_64": int(np.count_nonzero(bev64[:-1])), "occupied_voxels_16": int(np.count_nonzero(bev16[:-1])),
        "labelled_cars": len(cars), "core_ms": round(elapsed, 1), "pictures": [str(p) for p in pictures],
    }


def scan_lines(models: Path) -> int | None:
    """The lines the bundled 64-line scan is thinned to for ``models``: those its PIXOR was trained on (16 when
    its manifest does not say), None for a 64-line model, which takes the scan as stored. As check_models,
    latency.py and INT8 calibration choose them (pipeline.beams.lines_to_thin_to): a fixed 16 gave a 64-line
    model a quarter of its points (1 car on 000006 where pipeline.detect and accuracy.py --input lidar64 find 4)."""
    from pipeline.detector import trained_lines

    pixor = (load_manifest(models).get("networks") or {}).get("pixor") or {}
    return lines_to_thin_to(trained_lines(pixor.get("training") or {})) or None


def run(models: Path | None, frame_id: str, out: Path) -> dict:
    """The detector of the model directory ``models`` on the bundled frame; None: the core alone."""
    if models is None:
        return run_core(frame_id, out)
    from pipeline.detect import run as detect

    lines = scan_lines(models)
    result = detect(models, out, data=SAMPLE_DIR, frames=[frame_id], emulate_beams=lines, progress=False)
    scan = f"64-line scan thinned to {lines} lines" if lines else "64-line scan as stored (a 64-line model)"
    return {
        "frame": frame_id, "mode": f"detector ({models}), {scan}",
        "detections_in_camera_view": result.result_files[0].read_text().splitlines(),
        "results": [str(p) for p in result.result_files], "pictures": [str(p) for p in result.pictures],
        "timings_ms": {k: round(v, 1) for k, v in result.mean_timings_ms.items()},
    }


def _models(args: argparse.Namespace) -> Path | None:
    """The model directory to run, None for the core alone: a --models that is not a model directory is an
    error (a mistyped path would otherwise run the core and exit 0, its summary's "mode" the only sign)."""
    if args.core:
        return None
    if args.models is None:  # the shipped weights, else the core (a checkout without them)
        if (DEFAULT_MODELS / "manifest.json").is_file():
            return DEFAULT_MODELS
        print(f"no model directory at {DEFAULT_MODELS}: running the frame-processing core alone", file=sys.stderr)
        return None
    if not (args.models / "manifest.json").is_file():
        raise InputError(f"--models {args.models}: no manifest.json, so not a model directory (python -m export "
                         "writes one); --core runs the frame-processing core alone")
    return args.models


@quiet_interrupt("the pictures and result files written so far stay in --out")
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
                                     prog="python -m pipeline.demo", description=__doc__.split("\n\n")[0],
                                     epilog=examples("python -m pipeline.demo --frame 000003 --out outputs/demo"),
                                     formatter_class=HelpFormatter)
    which = parser.add_mutually_exclusive_group()
    which.add_argument("--models", type=Path, metavar="DIR", help=f"model directory (default {DEFAULT_MODELS})")
    which.add_argument("--core", action="store_true",
                       help="run the frame-processing core alone, without a model (pictures of each step)")
    parser.add_argument("--frame", default="000006", metavar="ID",
                        help="bundled KITTI frame: 000000, 000001, 000003, 000004, 000006 (default 000006)")
    parser.add_argument("--out", type=Path, default=Path("outputs/demo"), metavar="DIR",
                        help="output folder (default outputs/demo): the KITTI result file in OUT/data, the PNG pictures "
                        "in OUT/bev and OUT/camera (with --core: OUT/<frame>_*.png of each step)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if not SAMPLE_DIR.is_dir():  # `pip install .` (not -e) leaves tests/data and weights/ behind
        print(f"error: the demo's bundled KITTI frames ({SAMPLE_DIR}) exist only in a source checkout (make demo, "
              "or pip install -e .); for your own frames use python -m pipeline.detect --models DIR", file=sys.stderr)
        return 2
    try:
        summary = run(_models(args), args.frame, args.out)
    except (InputError, ModelFileError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # an --out that cannot be written (a file in the way, no permission, a full disk)
        print(unwritable(args.out, exc), file=sys.stderr)
        return 2
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
