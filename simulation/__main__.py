"""CLI: ``python -m simulation --out DIR --frames N --seed S [--workers K]``."""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
from pathlib import Path

from pipeline.cli import interrupted, non_negative_int, positive_int
from simulation.run import RunConfig, run


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m simulation",
        description="Generate synthetic driving frames in the KITTI object layout: image_2/*.png, "
        "velodyne/*.bin (64-line), calib/*.txt, label_2/*.txt and depth_2/*.png (dense depth, "
        "metres × 256), plus ImageSets/<split>.txt. Frame i depends only on (seed, i).",
    )
    parser.add_argument("--out", type=Path, required=True, help="output folder (KITTI 'training/' equivalent)")
    parser.add_argument("--frames", type=positive_int, required=True, help="number of frames to write")
    parser.add_argument("--seed", type=non_negative_int, required=True, help="run seed; use disjoint seeds for train and val")
    parser.add_argument("--start", type=non_negative_int, default=0, help="first frame index / file id (default 0)")
    parser.add_argument("--workers", type=positive_int, default=1, help="worker processes (default 1)")
    parser.add_argument("--split", default="train", help="name of the ImageSets list file (default train)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        result = run(RunConfig(out=args.out, frames=args.frames, seed=args.seed, start=args.start,
                               workers=args.workers, split=args.split, progress=not args.no_progress))
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # each frame's files are whole (depth_2 last, renamed into place)
        return interrupted(f"the frames finished are in {args.out}; rerun the same command to resume")
    except OSError as exc:  # --out cannot be written (no permission, a full disk)
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"error: --out {args.out}: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    if not result.seconds_per_frame:
        print(f"all {len(result.ids)} frames were already in {result.out} ({result.list_file.name} rewritten)")
        return 0
    median = statistics.median(result.seconds_per_frame)
    print(f"wrote {len(result.seconds_per_frame)} of {len(result.ids)} frames to {result.out} "
          f"({result.list_file.name}); median {median:.2f} s/frame per worker")
    return 0


if __name__ == "__main__":
    sys.exit(main())
