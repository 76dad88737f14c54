"""Cache the trained depth net's dense depth for every frame, for ``models.train detector --input pseudo``.

    python -m models.cache_pseudo --data DIR --models DIR --out PSEUDO_DIR [--split-file F | --frames N]

Runs ``depth.onnx`` through the runtime Detector — exactly the depth maps
inference produces — on each frame's 16-line scan (the stored scan thinned
to ``--emulate-beams`` lines, 16 by default; 0 takes it as stored, as a
16-line sensor's own scans need), and writes them as KITTI
depth PNGs (the network's view, metres × 256) named by frame id. Frames already
cached are skipped, so an interrupted run resumes; ``cache.json`` records the
depth net's sha256 and the line count the maps were made with, and a run with another
depth net or another line count is refused instead of mixing its maps with those.
It also records each map's source files by their sizes: frame ids repeat across
data sets (every synthetic set and KITTI split starts at 000000), so a map of
another set's frame 000003, or of frames made again since, is refused by name
here and by ``models.train`` rather than taken for this frame's.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from tqdm import tqdm

from models.checkpoint import write_text_atomic
from pipeline.beams import BEAM_COUNTS, check_thinnable, emulate_beams
from pipeline.cli import (
    HelpFormatter,
    add_no_progress,
    check_not_input,
    check_output,
    examples,
    interrupted,
    list_or_count,
    show_progress,
    unwritable,
)
from pipeline.detector import Detector
from pipeline.errors import InputError, in_frame
from pipeline.frame import frame_ids, load_frame
from pipeline.kitti import write_depth_png
from pipeline.model_files import ModelFileError

# What a frame's map is made from: the files load_frame reads of every frame (models.run_checks checks them too).
FRAME_FILES = (("velodyne", ".bin"), ("image_2", ".png"), ("calib", ".txt"))
RECORD = "cache.json"


def source_sizes(data: Path, fid: str) -> list[int]:
    """The byte sizes of the files a frame's map is made from: what tells one data set's frame from another's
    of the same id without reading them (a scan's size is its point count)."""
    return [(data / folder / f"{fid}{ext}").stat().st_size for folder, ext in FRAME_FILES]


def _read_record(cache: Path) -> dict:
    """``cache``'s record ({} for a folder without one, or one that is not a JSON object)."""
    try:
        held = json.loads((cache / RECORD).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return held if isinstance(held, dict) else {}


def recorded_sources(cache: Path) -> dict[str, list[int]]:
    """The source sizes ``cache``'s record holds per frame ({} for a folder without one, or an older record)."""
    return _read_record(cache).get("frames", {})


def recorded_beams(cache: Path) -> int | None:
    """The --emulate-beams ``cache``'s maps were made with (0: the scans as stored; None: no record)."""
    beams = _read_record(cache).get("beams")
    return beams if isinstance(beams, int) else None


def recorded_view(cache: Path) -> dict | None:
    """The depth net's view ``cache``'s maps are in (crop_hw, input_scale, input_hw; None: an older record)."""
    view = _read_record(cache).get("view")
    return view if isinstance(view, dict) else None


def recorded_preset(cache: Path) -> str | None:
    """The preset of the model directory ``cache``'s maps were made with (None: no record)."""
    preset = _read_record(cache).get("preset")
    return preset if isinstance(preset, str) else None


def check_sources(cache: Path, flag: str, data: Path, data_flag: str, ids: list[str], hint: str = "") -> None:
    """InputError naming the first of ``ids`` whose cached map was made from other files than ``data``'s."""
    made_from = recorded_sources(cache)
    clash = [fid for fid in ids if fid in made_from and made_from[fid] != source_sizes(data, fid)]
    if clash:
        more = f"; {len(clash) - 1} more frame(s) too" if len(clash) > 1 else ""
        raise InputError(f"{flag} {cache}: its map of frame {clash[0]} was made from other files than frame "
                         f"{clash[0]} of {data_flag} {data} (another data set, or its frames made again){more}; "
                         f"cache {data_flag}'s frames into a folder of their own{hint}")


def run(data: Path, models: Path, out: Path, split_file: Path | None = None, beams: int = 16,
        progress: bool = True, threads: int | None = None, first: int | None = None) -> int:
    """Write one depth PNG per frame into ``out``; returns how many were computed (not skipped).

    Every input is checked before ``out`` is made or any map computed. beams: the lines each scan is thinned to
    (0: as stored, a 16-line sensor's own). threads: ONNX Runtime's intra-op threads (None: one per core).
    first: only the first N frames (of the split file, or in id order).
    """
    out = Path(out)
    check_output(out, "--out", directory=True)
    check_not_input(out, "--out", {"--data": data, "--models": models})
    ids = _frames(Path(data), split_file)[:first]
    if beams not in (0, *BEAM_COUNTS):  # argparse's choices, for library callers
        raise InputError(f"--emulate-beams: {beams} is not one of 0, {', '.join(map(str, BEAM_COUNTS))}")
    # A 16-line sensor's scans to thin, or 64-line ones as stored: one line naming the first, before any map.
    check_thinnable(Path(data), ids, beams, "cache the depth of")
    detector = Detector(models, intra_op_threads=threads, networks_used=("depth",))  # PIXOR is not run here
    if not detector.two_stage:
        raise InputError(f"--models: {models} has no depth network")
    out.mkdir(parents=True, exist_ok=True)
    depth_file = detector.manifest["networks"]["depth"]["file"]  # the maps depend on the depth net alone
    record = {"depth_sha256": detector.sha256[depth_file], "preset": detector.preset.name, "beams": beams}
    _check_record(out, record)
    # Recorded, not compared above (the depth net's sha256 decides it, and older records lack it): which view of the
    # image the maps are in, for models.train to check against its preset's (another view's calibration misplaces
    # every pseudo point).
    record["view"] = {"crop_hw": list(detector.preset.crop_hw), "input_scale": detector.preset.depth.input_scale,
                      "input_hw": list(detector.preset.depth.input_hw)}
    check_sources(out, "--out", Path(data), "--data", ids, hint=" (give another --out)")
    record["frames"] = made_from = recorded_sources(out)
    computed = 0
    for fid in tqdm(ids, desc="pseudo depth", unit="frame", disable=not progress):
        target = out / f"{fid}.png"
        sources = source_sizes(Path(data), fid)
        if target.exists() and made_from.get(fid) == sources:
            continue  # a map without its sources recorded (a run stopped between the two) is made again
        frame = load_frame(data, fid, with_labels=False)
        with in_frame(f"{data}, frame {fid}"):
            points = emulate_beams(frame.points, beams) if beams else frame.points
            depth, _ = detector.dense_depth(frame.image, points, frame.calib)
        partial = target.with_suffix(".tmp.png")
        try:  # written whole, then renamed: an interrupted run leaves no truncated map to skip next time
            write_depth_png(partial, depth)
            partial.replace(target)
        finally:
            partial.unlink(missing_ok=True)
        made_from[fid] = sources
        _write_record(out, record)
        computed += 1
    return computed


def _frames(data: Path, split_file: Path | None) -> list[str]:
    """The frame ids to cache, each with its scan, image and calibration in ``data`` (InputError naming the
    flag otherwise): a misspelt id fails before the first map, not after the ones before it."""
    if not (data / "velodyne").is_dir():
        raise InputError(f"--data {data}: not a KITTI object folder (no velodyne/ inside)")
    ids = frame_ids(data, split_file)
    if not ids:
        raise InputError(f"--data {data}: no frames (velodyne/*.bin)")
    held = {folder: {p.name for p in (data / folder).iterdir()} if (data / folder).is_dir() else set()
            for folder, _ in FRAME_FILES}
    lacking = {fid: [f"{folder}/{fid}{ext}" for folder, ext in FRAME_FILES if f"{fid}{ext}" not in held[folder]]
               for fid in ids}
    lacking = {fid: files for fid, files in lacking.items() if files}
    if lacking:
        fid, files = next(iter(lacking.items()))
        listed = f" (listed in --split-file {split_file})" if split_file is not None else ""
        more = f"; {len(lacking) - 1} more frame(s) are incomplete too" if len(lacking) > 1 else ""
        raise InputError(f"--data {data}: frame {fid}{listed} has no {', '.join(files)}{more}")
    return ids


def _check_record(out: Path, wanted: dict) -> None:
    """Refuse a cache folder whose maps came from another depth net or line count; record ours in it.

    A folder of PNGs without the record is refused too: its files would be skipped as maps already made and
    then certified by the record (a folder of camera images given as --out was), whatever made them.
    """
    record = out / RECORD
    if not record.exists():
        stray = next(out.glob("*.png"), None)
        if stray is not None:
            raise InputError(f"--out {out}: holds PNGs ({stray.name} among them) but no cache.json, so not maps this "
                             "command made; give a new or empty folder (a cache made before cache.json existed: "
                             "delete it and cache again)")
    if record.exists():
        try:
            held = json.loads(record.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise InputError(f"{record}: unreadable ({exc}); delete it or give another --out") from exc
        if not isinstance(held, dict) or {key: held.get(key) for key in wanted} != wanted:
            held = held if isinstance(held, dict) else {}
            raise InputError(f"--out {out}: holds depth maps of another depth net or line count ({record}: "
                             f"{held.get('preset')}, --emulate-beams {held.get('beams')}); give another --out")
        return
    _write_record(out, {**wanted, "frames": {}})


def _write_record(out: Path, record: dict) -> None:
    """Write the record whole, then rename it over the old one: a stopped run never leaves half a record."""
    write_text_atomic(out / RECORD, json.dumps(record, indent=1) + "\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
        prog="python -m models.cache_pseudo", description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter,
        epilog=examples("python -m models.cache_pseudo --data data/sim/train --models weights/edge "
                        "--out runs/edge/pseudo-train"))
    parser.add_argument("--data", type=Path, required=True, metavar="DIR", help="KITTI-layout folder")
    parser.add_argument("--models", type=Path, required=True, metavar="DIR", help="model directory with depth.onnx")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="folder for the depth PNGs")
    which = parser.add_mutually_exclusive_group()  # as benchmarks/accuracy.py's: the same frames either way
    which.add_argument("--split-file", dest="frames", type=list_or_count, metavar="F",
                       help="frame ids, one per line (default: all frames)")
    which.add_argument("--frames", dest="frames", type=list_or_count, metavar="LIST|N",
                       help="frame ids, one per line, as --split-file; or N: the first N frames in id order")
    parser.add_argument("--emulate-beams", "--beams", dest="beams", type=int, default=16, choices=(0, *BEAM_COUNTS),
                        metavar="N",
                        help="lines the 64-line scan is thinned to (default 16; 32, 8, 4); 0: the scans as stored "
                        "(a 16-line sensor's own), as models.train --emulate-beams 0")
    add_no_progress(parser)
    args = parser.parse_args(argv)
    try:
        split_file, first = (args.frames, None) if not isinstance(args.frames, int) else (None, args.frames)
        n = run(args.data, args.models, args.out, split_file, args.beams, first=first,
                progress=show_progress(args.no_progress))
    except (InputError, ModelFileError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a full disk or a folder removed while writing
        print(unwritable(args.out, exc), file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return interrupted(f"the maps already in {args.out} stay; rerun the same command to resume")
    print(f"cached {n} depth map(s) in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
