"""Speed of the non-network steps of a frame, on a real 64-line KITTI scan and a full pseudo cloud.

    python benchmarks/frame_ops.py [--frame 000006] [--repeats 30] [--json OUT]

Steps timed: ring recovery + 16-line emulation, sparse depth at the depth-net
view, pseudo point cloud from a dense 1216×352 depth map (428k points), BEV
voxelization of the 64-line scan and of the pseudo cloud, decoding + rotated
NMS. Side by side in the same run: the straightforward voxelization of PIXOR's
public reference (vectorized range filter, then a Python loop over the points),
re-implemented here only as the baseline.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.beams import emulate_beams
from pipeline.bev import BevVoxelizer, pseudo_bins
from pipeline.boxes import labels_to_boxes
from pipeline.cli import (
    HelpFormatter,
    check_not_input,
    check_output,
    examples,
    positive_int,
    quiet_interrupt,
    write_text_file,
)
from pipeline.cpu import describe as describe_cpu
from pipeline.errors import InputError
from pipeline.frame import load_frame
from pipeline.postprocess import boxes_from_maps
from pipeline.preprocess import depth_inputs, network_view
from pipeline.presets import get_preset, is_preset_file
from pipeline.pseudo import depth_to_points, merge_points, pseudo_xyz
from pipeline.targets import encode_targets

KITTI = Path(__file__).resolve().parents[1] / "tests" / "data" / "kitti" / "training"


def reference_voxelize(points: np.ndarray, grid) -> np.ndarray:
    """Baseline: PIXOR reference style — range filter, then one Python iteration per point."""
    keep = (
        (points[:, 0] >= grid.x_min) & (points[:, 0] < grid.x_max)
        & (points[:, 1] >= grid.y_min) & (points[:, 1] < grid.y_max)
        & (points[:, 2] >= grid.z_min) & (points[:, 2] < grid.z_max)
    )
    velo = points[keep]
    out = np.zeros((grid.ny, grid.nx, grid.channels), dtype=np.float32)
    counts = np.zeros((grid.ny, grid.nx))
    for i in range(velo.shape[0]):
        row = int((velo[i, 1] - grid.y_min) / grid.cell)
        col = int((velo[i, 0] - grid.x_min) / grid.cell)
        level = int((velo[i, 2] - grid.z_min) / grid.z_cell)
        out[row, col, level] = 1
        out[row, col, -1] += velo[i, 3]
        counts[row, col] += 1
    out[:, :, -1] = np.divide(out[:, :, -1], counts, out=np.zeros_like(counts, dtype=np.float32), where=counts != 0)
    return out


def timed(fn, repeats: int) -> dict:
    """Median, p90 and min of ``repeats`` calls (ms), after one warm-up call."""
    fn()
    samples = []
    for _ in range(repeats):
        tic = time.perf_counter()
        fn()
        samples.append((time.perf_counter() - tic) * 1e3)
    samples = np.array(samples)
    return {"p50": float(np.median(samples)), "p90": float(np.percentile(samples, 90)), "min": float(samples.min())}


def run(frame_id: str = "000006", repeats: int = 30, preset_name: str = "paper", data: Path = KITTI) -> dict:
    """Time every non-network step on frame ``frame_id`` of ``data`` (a KITTI-layout folder with labels, whose
    cars give the targets) under ``preset_name`` (a name or a preset file); returns {step: {p50, p90, min}} plus
    the baseline ratio, and the preset: its name, its configuration and the file it was read from (or None)."""
    preset = get_preset(preset_name)
    frame = load_frame(data, frame_id)
    lidar16 = emulate_beams(frame.points, 16)
    # A dense depth map of the depth-net view: nearest-neighbour fill of the 64-line sparse depth stands in
    # for the network's output, so the pseudo cloud has the real geometry and the full 428k-point size.
    _, view_calib = network_view(frame.image, frame.calib, preset)
    sparse = depth_inputs(frame.image, frame.points, frame.calib, preset).sparse_depth[0, 0]
    import cv2

    filled = cv2.dilate(sparse, np.ones((9, 9), np.uint8))
    dense = np.where(filled > 0, filled, 40.0).astype(np.float32)
    pseudo = depth_to_points(dense, view_calib, 0.0, 1e9)
    cloud = merge_points(pseudo, lidar16)
    voxelize = BevVoxelizer(preset.bev)
    gt = labels_to_boxes([o for o in frame.labels if o.type == "Car"], frame.calib)
    targets = encode_targets(gt, preset.bev, preset.pixor.output_stride, preset.decode)
    # Score map as a trained network gives it: high on the cars, noisy low background.
    rng = np.random.default_rng(0)
    score = np.clip(0.9 * targets.score + rng.uniform(0, 0.45, targets.score.shape), 0, 1).astype(np.float32)
    bev_pseudo = voxelize(cloud).copy()
    # The Detector's limits: depth range, stride, and no pseudo points above pseudo_max_height (sky, trees).
    limits = preset.pseudo_limits
    bins = pseudo_bins(dense, view_calib, preset.bev, *limits)

    steps = {
        "emulate_16_beams (64-line scan)": lambda: emulate_beams(frame.points, 16),
        "prepare: crop + sparse depth (16-line)": lambda: depth_inputs(frame.image, lidar16, frame.calib, preset),
        f"pseudo_points ({dense.shape[1]}x{dense.shape[0]} depth map to BEV bins), as the Detector runs it":
            lambda: pseudo_bins(dense, view_calib, preset.bev, *limits),
        "voxelize (64-line scan)": lambda: voxelize(frame.points),
        f"voxelize (16-line scan + {bins.occupancy.size} pseudo points), as the Detector runs it": lambda: voxelize(
            lidar16, bins),
        "for comparison: pseudo x, y, z arrays, then voxelize them with the 16-line scan": lambda: voxelize(
            lidar16, pseudo_xyz(dense, view_calib, *limits)),
        "for comparison: pseudo (N, 4) cloud + merge, then voxelize the merged cloud": lambda: voxelize(merge_points(
            depth_to_points(dense, view_calib, *limits), lidar16)),
        "decode + NMS + heights": lambda: boxes_from_maps(score, targets.regression, bev_pseudo, preset, 0.5),
    }
    results = {name: timed(fn, repeats) for name, fn in steps.items()}
    baseline = timed(lambda: reference_voxelize(frame.points, preset.bev), max(3, repeats // 6))
    results["baseline: reference voxelize (64-line scan)"] = baseline
    ours = results["voxelize (64-line scan)"]["p50"]
    return {
        "frame": frame_id, "preset": preset.name, "preset_config": preset.to_dict(),
        "preset_file": preset_name if is_preset_file(preset_name) else None, "points_64": int(frame.points.shape[0]),
        "pseudo_points": int(pseudo.shape[0]), "repeats": repeats,
        "machine": {**describe_cpu(), "system": platform.platform()},
        "steps_ms": results, "voxelize_speedup_vs_reference": baseline["p50"] / ours,
    }


@quiet_interrupt("no report was written (--json is written at the end)")
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
                                     prog="python benchmarks/frame_ops.py", description=__doc__.split("\n\n")[0],
                                     epilog=examples("python benchmarks/frame_ops.py --repeats 30 --json "
                                                     "outputs/frame_ops.json"),
                                     formatter_class=HelpFormatter)
    parser.add_argument("--data", type=Path, default=KITTI, metavar="DIR",
                        help="KITTI-layout folder with label_2 (default: the bundled real frames)")
    parser.add_argument("--frame", default="000006", metavar="ID", help="frame id in --data (default 000006)")
    parser.add_argument("--preset", default="paper", metavar="P",
                        help="preset whose grid and crop are used (default paper)")
    parser.add_argument("--repeats", type=positive_int, default=30, metavar="N",
                        help="timed calls per step (default 30)")
    parser.add_argument("--json", type=Path, metavar="FILE", help="write the figures as JSON")
    args = parser.parse_args(argv)
    try:
        get_preset(args.preset)
    except ValueError as exc:  # get_preset's list of the valid names, or what is wrong in a preset file
        if is_preset_file(args.preset):  # the file's fault, in one line: argparse's usage says nothing of it
            print(f"error: argument --preset: {exc}", file=sys.stderr)
            return 2
        parser.error(f"argument --preset: {exc}")
    try:
        if args.json is not None:
            check_output(args.json, "--json")
            check_not_input(args.json, "--json", {"--data": args.data})
        report = run(args.frame, args.repeats, args.preset, args.data)
    except InputError as exc:  # a frame --data lacks, an output that cannot be written
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"frame {report['frame']} ({report['points_64']} points), preset {report['preset']}, "
          f"pseudo cloud {report['pseudo_points']} points, {report['repeats']} repeats")
    width = max(len(name) for name in report["steps_ms"])
    print(f"{'step':{width}s} {'p50 ms':>8s} {'p90 ms':>8s}")
    for name, t in report["steps_ms"].items():
        print(f"{name:{width}s} {t['p50']:8.2f} {t['p90']:8.2f}")
    print(f"voxelization speed-up over the reference loop: {report['voxelize_speedup_vs_reference']:.0f}×")
    if args.json:
        write_text_file(args.json, json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
