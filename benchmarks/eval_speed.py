"""Time the KITTI evaluator on random KITTI-like label sets (default: 3,769 frames, the val split's size).

    python benchmarks/eval_speed.py [--frames 3769] [--repeats 3] [--seed 0] [--keep DIR]

Writes random ground truth (Car, Van, Pedestrian, DontCare with varied
truncation, occlusion and image heights) and noisy detections (misses,
duplicates, false positives, other classes, tiny boxes) as KITTI files, then
times what ``benchmarks/accuracy.py`` does (reading the files + evaluation) and
reports the median. ``--keep DIR`` leaves the files in ``DIR/label_2`` and
``DIR/results`` (e.g. to feed another evaluator).
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from evaluation.frames import load_label_dirs
from evaluation.kitti_eval import KittiEvalResult, evaluate
from evaluation.report import format_table
from pipeline.cli import (
    HelpFormatter,
    check_output,
    examples,
    non_negative_int,
    positive_int,
    quiet_interrupt,
)
from pipeline.cpu import cpu_label
from pipeline.errors import InputError
from pipeline.kitti import Object3D, write_labels

FOCAL_PX = 721.5  # KITTI P2 focal length: sets realistic 2D box heights from 3D sizes
CENTRE_U, CENTRE_V = 609.6, 172.9
IMAGE_W, IMAGE_H = 1242.0, 375.0
SIZES = {"Car": (1.52, 1.63, 3.88), "Van": (2.2, 1.9, 5.1), "Pedestrian": (1.76, 0.66, 0.84)}


def _project_box(h: float, w: float, l: float, x: float, y: float, z: float, ry: float) -> tuple[float, ...]:
    """2D box (left, top, right, bottom) of a 3D box seen by a KITTI-like camera, clipped to the image."""
    c, s = math.cos(ry), math.sin(ry)
    us, vs = [], []
    for dx in (l / 2, -l / 2):
        for dz in (w / 2, -w / 2):
            for dy in (0.0, -h):
                px, pz = x + c * dx + s * dz, z - s * dx + c * dz
                pz = max(pz, 0.5)
                us.append(CENTRE_U + FOCAL_PX * px / pz)
                vs.append(CENTRE_V + FOCAL_PX * (y + dy) / pz)
    return (
        min(max(min(us), 0.0), IMAGE_W - 1), min(max(min(vs), 0.0), IMAGE_H - 1),
        min(max(max(us), 0.0), IMAGE_W - 1), min(max(max(vs), 0.0), IMAGE_H - 1),
    )


def _random_object(rng: np.random.Generator, kind: str) -> Object3D:
    h0, w0, l0 = SIZES[kind]
    h, w, l = h0 * rng.uniform(0.9, 1.1), w0 * rng.uniform(0.9, 1.1), l0 * rng.uniform(0.85, 1.15)
    z = rng.uniform(4.0, 70.0)
    x = rng.uniform(-0.6, 0.6) * z
    y = rng.normal(1.65, 0.15)
    ry = rng.uniform(-math.pi, math.pi)
    return Object3D(
        type=kind, truncated=float(rng.choice([0.0, 0.0, 0.0, 0.1, 0.2, 0.4, 0.7])),
        occluded=int(rng.choice([0, 0, 1, 1, 2, 3])), alpha=ry, bbox=_project_box(h, w, l, x, y, z, ry),
        dimensions=(h, w, l), location=(x, y, z), rotation_y=ry,
    )


def _jitter(rng: np.random.Generator, obj: Object3D, score: float, kind: str | None = None) -> Object3D:
    """A detection of ``obj``: noisy position, size, heading and 2D box."""
    h, w, l = (d * rng.normal(1.0, 0.05) for d in obj.dimensions)
    x, y, z = (v + rng.normal(0.0, s) for v, s in zip(obj.location, (0.12, 0.08, 0.25)))
    ry = obj.rotation_y + rng.normal(0.0, 0.05)
    bbox = tuple(b + rng.normal(0.0, 3.0) for b in obj.bbox)
    return Object3D(
        type=kind or obj.type, truncated=-1.0, occluded=-1, alpha=obj.alpha, bbox=bbox,
        dimensions=(abs(h), abs(w), abs(l)), location=(x, y, z), rotation_y=ry, score=score,
    )


def random_frame(rng: np.random.Generator) -> tuple[list[Object3D], list[Object3D]]:
    """One frame of ground truth and detections."""
    gt: list[Object3D] = []
    for kind, mean in (("Car", 4.0), ("Van", 0.6), ("Pedestrian", 1.0)):
        gt += [_random_object(rng, kind) for _ in range(rng.poisson(mean))]
    for _ in range(rng.poisson(1.5)):
        u, v = rng.uniform(0, IMAGE_W - 80), rng.uniform(120, 220)
        gt.append(Object3D("DontCare", -1.0, -1, -10.0, (u, v, u + rng.uniform(10, 80), v + rng.uniform(8, 60)),
                           (-1.0, -1.0, -1.0), (-1000.0, -1000.0, -1000.0), -10.0))
    det: list[Object3D] = []
    for obj in gt:
        if obj.type == "DontCare":
            if rng.random() < 0.3:  # a detection inside a DontCare region
                u0, v0, u1, v1 = obj.bbox
                det.append(Object3D("Car", -1.0, -1, 0.0, (u0 + 1, v0 + 1, u1 - 1, max(v1 - 1, v0 + 30)),
                                    (1.5, 1.6, 3.9), (rng.uniform(-20, 20), 1.6, rng.uniform(10, 60)),
                                    rng.uniform(-3, 3), score=rng.uniform(0.0, 0.9)))
            continue
        if obj.type == "Pedestrian":
            if rng.random() < 0.5:
                det.append(_jitter(rng, obj, rng.uniform(0.0, 1.0)))
            continue
        if rng.random() < 0.85:
            det.append(_jitter(rng, obj, rng.uniform(0.2, 1.0), "Car"))
            if rng.random() < 0.15:  # duplicate
                det.append(_jitter(rng, obj, rng.uniform(0.0, 0.8), "Car"))
    for _ in range(rng.poisson(2.0)):  # false positives, some far away and tiny in the image
        fake = _random_object(rng, "Car")
        det.append(_jitter(rng, fake, rng.uniform(0.0, 0.7), "Car"))
    return gt, det


def write_random_label_sets(out_dir: Path, n_frames: int, seed: int) -> tuple[Path, Path]:
    """Write ``out_dir/label_2/%06d.txt`` and ``out_dir/results/%06d.txt``; return both directories."""
    rng = np.random.default_rng(seed)
    gt_dir, det_dir = out_dir / "label_2", out_dir / "results"
    gt_dir.mkdir(parents=True, exist_ok=True)
    det_dir.mkdir(parents=True, exist_ok=True)
    for i in range(n_frames):
        gt, det = random_frame(rng)
        write_labels(gt_dir / f"{i:06d}.txt", gt)
        write_labels(det_dir / f"{i:06d}.txt", det)
    return gt_dir, det_dir


@quiet_interrupt("no timing was reported (--keep's label sets written so far stay)")
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
                                     prog="python benchmarks/eval_speed.py", description=__doc__.split("\n\n")[0],
                                     epilog=examples("python benchmarks/eval_speed.py --frames 3769 --repeats 3"),
                                     formatter_class=HelpFormatter)
    parser.add_argument("--frames", type=positive_int, default=3769, metavar="N",
                        help="frames to generate (default 3769)")
    parser.add_argument("--repeats", type=positive_int, default=3, metavar="N",
                        help="timed runs; the median is reported (default 3)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="seed of the random label sets (default 0)")
    parser.add_argument("--keep", type=Path, metavar="DIR",
                        help="write the label sets here and keep them (a new or empty folder)")
    args = parser.parse_args(argv)
    if args.keep is not None:
        try:
            check_output(args.keep, "--keep", directory=True)
            # Random labels over a folder's own would destroy them, and an earlier, larger set's files would
            # be evaluated too while the report says --frames.
            if args.keep.is_dir() and next(args.keep.iterdir(), None) is not None:
                raise InputError(f"--keep {args.keep}: not empty; give a new or empty folder")
        except InputError as exc:
            parser.error(str(exc))
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        gt_dir, det_dir = write_random_label_sets(root, args.frames, args.seed)
        times = []
        result: KittiEvalResult | None = None
        for _ in range(args.repeats):
            start = time.perf_counter()
            labels = load_label_dirs(gt_dir, det_dir)
            result = evaluate(labels.ground_truth, labels.detections)
            times.append(time.perf_counter() - start)
    assert result is not None
    print(format_table(result))
    print(
        f"{args.frames} frames, {args.repeats} runs (read files + evaluate {len(result.metrics)} metrics "
        f"x {len(result.iou_thresholds)} IoU x 3 difficulties): median {statistics.median(times):.2f} s, "
        f"min {min(times):.2f} s, max {max(times):.2f} s on {cpu_label()}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
