"""Cache the trained depth net's dense depth for every frame, for ``models.train detector --input pseudo``.

    python -m models.cache_pseudo --data DIR --models DIR --out PSEUDO_DIR [--split-file F]

Runs ``depth.onnx`` through the runtime Detector — exactly the depth maps
inference produces — on each frame's 16-line scan, and writes them as KITTI
depth PNGs (the network's view, metres × 256) named by frame id. Frames already
cached are skipped, so an interrupted run resumes; ``cache.json`` records the
depth net's sha256 and the line count the maps were made with, and a run with another
depth net or another line count is refused instead of mixing its maps with those.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from tqdm import tqdm

from pipeline.beams import BEAM_COUNTS, emulate_beams
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
    depth_file = detector.manifest["networks"]["depth"]["file"]  # the maps depend on the depth net alone
    _check_record(out, {"depth_sha256": detector.sha256[depth_file], "preset": detector.preset.name, "beams": beams})
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


def _check_record(out: Path, wanted: dict) -> None:
    """Refuse a cache folder whose maps came from another depth net or line count; record ours in it.

    A folder from before the record existed is taken as it is (and recorded): its maps cannot be checked.
    """
    record = out / "cache.json"
    if record.exists():
        try:
            held = json.loads(record.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise InputError(f"{record}: unreadable ({exc}); delete it or give another --out") from exc
        if held != wanted:
            raise InputError(f"--out {out}: holds depth maps of another depth net or line count ({record}: "
                             f"{held.get('preset')}, {held.get('beams')} lines); give another --out")
        return
    record.write_text(json.dumps(wanted, indent=2) + "\n", encoding="utf-8")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m models.cache_pseudo", description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="KITTI-layout folder")
    parser.add_argument("--models", type=Path, required=True, help="model directory with depth.onnx")
    parser.add_argument("--out", type=Path, required=True, help="folder for the depth PNGs")
    parser.add_argument("--split-file", type=Path, help="frame ids, one per line (default: all)")
    parser.add_argument("--beams", type=int, default=16, choices=BEAM_COUNTS, metavar="N",
                        help="lines the 64-line scan is thinned to (default 16; 32, 8, 4)")
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
