"""Cache the trained depth net's dense depth for every frame, for ``models.train detector --input pseudo``.

    python -m models.cache_pseudo --data DIR --models DIR --out PSEUDO_DIR [--split-file F]

Runs ``depth.onnx`` through the runtime Detector — exactly the depth maps
inference produces — on each frame's 16-line scan, and writes them as KITTI
depth PNGs (the network's view, metres × 256) named by frame id. Frames already
cached are skipped, so an interrupted run resumes.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tqdm import tqdm

from pipeline.beams import emulate_beams
from pipeline.detector import Detector
from pipeline.errors import InputError
from pipeline.frame import frame_ids, load_frame
from pipeline.kitti import write_depth_png
from pipeline.model_files import ModelFileError


def run(data: Path, models: Path, out: Path, split_file: Path | None = None, beams: int = 16,
        progress: bool = True, threads: int | None = None) -> int:
    """Write one depth PNG per frame into ``out``; returns how many were computed (not skipped).

    threads: ONNX Runtime's intra-op threads (None: one per core).
    """
    detector = Detector(models, intra_op_threads=threads)
    if not detector.two_stage:
        raise InputError(f"--models: {models} has no depth network")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    computed = 0
    for fid in tqdm(frame_ids(data, split_file), desc="pseudo depth", unit="frame", disable=not progress):
        target = out / f"{fid}.png"
        if target.exists():
            continue
        frame = load_frame(data, fid, with_labels=False)
        depth, _ = detector.dense_depth(frame.image, emulate_beams(frame.points, beams), frame.calib)
        write_depth_png(target.with_suffix(".tmp.png"), depth)
        target.with_suffix(".tmp.png").replace(target)
        computed += 1
    return computed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m models.cache_pseudo", description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="KITTI-layout folder")
    parser.add_argument("--models", type=Path, required=True, help="model directory with depth.onnx")
    parser.add_argument("--out", type=Path, required=True, help="folder for the depth PNGs")
    parser.add_argument("--split-file", type=Path, help="frame ids, one per line (default: all)")
    parser.add_argument("--beams", type=int, default=16, help="lines of the input scan (default 16)")
    args = parser.parse_args(argv)
    try:
        n = run(args.data, args.models, args.out, args.split_file, args.beams)
    except (InputError, ModelFileError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"cached {n} depth map(s) in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
