"""CLI: ``python -m simulation --out DIR --frames N --seed S [--workers K]``."""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

from pipeline.cli import (
    HelpFormatter,
    add_no_progress,
    examples,
    non_negative_int,
    positive_int,
    sigterm_as_interrupt,
    stopped,
)
from simulation.run import RunConfig, run


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
        prog="python -m simulation",
        description="Generate synthetic driving frames in the KITTI object layout: image_2/*.png, "
        "velodyne/*.bin (64-line), calib/*.txt, label_2/*.txt and depth_2/*.png (dense depth, "
        "metres × 256), plus ImageSets/<split>.txt. Frame i depends only on (seed, i). Each file appears "
        "whole or not at all; rerun the same command to resume a stopped run.",
        epilog=examples("python -m simulation --out data/sim/train --frames 3000 --seed 1 --workers 2",
                        "python -m simulation --out data/sim/val --frames 300 --seed 2 --split val --workers 2"),
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--out", type=Path, required=True, metavar="DIR",
                        help="output folder (KITTI 'training/' equivalent)")
    parser.add_argument("--frames", type=positive_int, required=True, metavar="N", help="number of frames to write")
    parser.add_argument("--seed", type=non_negative_int, required=True,
                        help="run seed; use disjoint seeds (or disjoint --start ranges) for train and val")
    parser.add_argument("--start", type=non_negative_int, default=0, metavar="N",
                        help="first frame index / file id (default 0)")
    parser.add_argument("--workers", type=positive_int, default=1, metavar="N", help="worker processes (default 1)")
    parser.add_argument("--split", default="train", help="name of the ImageSets list file (default train)")
    parser.add_argument("--imagesets", type=Path, default=None, metavar="DIR",
                        help="folder of the split list (default OUT/ImageSets); with --out ROOT/training or "
                        "ROOT/testing give ROOT/ImageSets, where OpenPCDet and mmdetection3d read it")
    # Drawn into a log too (not show_progress): a run of thousands of frames goes on for hours in the background.
    add_no_progress(parser, "hide the progress bar (drawn into a log too: a long run in the background shows its "
                    "progress there)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    resume = f"the frames finished are in {args.out}; rerun the same command to resume"
    try:
        with sigterm_as_interrupt():  # a build server's stop (`timeout`, `kill`, a CI job's cancel)
            result = run(RunConfig(out=args.out, frames=args.frames, seed=args.seed, start=args.start,
                                   workers=args.workers, split=args.split, progress=not args.no_progress,
                                   imagesets=args.imagesets))
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:  # each frame's files are whole (renamed into place, depth_2 last)
        return stopped(exc, resume)
    except BrokenProcessPool:  # the OOM killer or a `kill -9` took a worker: its frame is not on disk
        print(f"error: a worker process ended abruptly (killed, or out of memory?); {resume}", file=sys.stderr)
        return 2
    except OSError as exc:  # --out cannot be written (no permission, a full disk)
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"error: --out {args.out}: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    if not result.seconds_per_frame:
        print(f"all {len(result.ids)} frames were already in {result.out} ({result.list_file} rewritten)")
        return 0
    median = statistics.median(result.seconds_per_frame)
    print(f"wrote {len(result.seconds_per_frame)} of {len(result.ids)} frames to {result.out} "
          f"({result.list_file}); median {median:.2f} s/frame per worker")
    return 0


if __name__ == "__main__":
    sys.exit(main())
