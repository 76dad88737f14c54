"""Run the detector on one frame, a KITTI-layout folder or a KITTI raw drive; write KITTI results and pictures.

    python -m pipeline.detect --models DIR --data DIR [--frame ID | --split-file F] --out DIR
    python -m pipeline.detect --models DIR --drive DATE/DATE_drive_NNNN_sync --out DIR [--video OUT.mp4]
    python -m pipeline.detect --models DIR --image F --points F --calib F --out DIR

Writes ``OUT/data/ID.txt`` (KITTI label_2 lines with scores, the format of
the official evaluation), ``OUT/bev/ID.png`` (the scan's returns grey over the
camera's pseudo points in magenta, the camera's field of view, predictions in
orange, dimmed outside that view, where the result file leaves them out, the
labelled cars dashed sky blue when labels exist, the frame's warning codes in
the key) and ``OUT/camera/ID.png`` (the camera image with the boxes of the
result file as wireframes); ``--video`` also puts the two
pictures, one above the other, in frame order into one MP4.

Each frame's warnings (``Detections.warnings``: sensor faults, a rig unlike the training one; not the thinning
``--emulate-beams`` asked for) go to ``OUT/warnings.txt``, one tab-separated line per frame and warning (frame id, code, message,
under a header line), which KITTI result files cannot hold; it is written only when a frame had one, and a
frame detected again has its earlier lines replaced. The terminal gets the first frame of each kind of
warning and, at the end, one line per code with its count of frames and their first ids, so that a fault
persisting over thousands of frames is a few lines there and every frame of it is on record in the file.

A raw drive (``--drive``) is read as KITTI's raw downloads lay it out:
``image_02/data/ID.png`` and ``velodyne_points/data/ID.bin`` in the drive
folder, ``calib_cam_to_cam.txt`` and ``calib_velo_to_cam.txt`` in the date
folder above it (or in the drive folder).

On a folder or a drive, a frame whose files cannot be used (a truncated scan, a broken
image or calibration) is reported with its file and skipped, and the run goes
on: one bad file in thousands costs that frame, not the rest of the run. The
command then exits 1 and lists the skipped frames; a ``--frame`` with no scan
is refused before any model is loaded, as is an id of a ``--split-file`` (ImageSets' ``val.txt``
or ``test.txt``) without one. On a whole folder, an image without its scan is a skipped frame too:
it has no result file, and KITTI's server refuses a submission with a file missing. A skipped
frame's result file and picture from an earlier run into the same folder are removed, so that
``OUT/data`` never passes an old result off as this run's.

Refused before any model loads: an ``--out`` or ``--video`` that would be written over what the run reads (an
object folder's KITTI folders, anything in a drive or the model directory, the files given; a new folder in
``--data`` is fine), and ``--emulate-beams N`` for scans that have few lines already (a 16-line sensor's:
give ``--emulate-beams 0``), which would otherwise skip every frame in turn.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.beams import BEAM_COUNTS, check_scan_thinnable
from pipeline.boxes import in_camera_view, labels_to_boxes
from pipeline.checks import WarningCode
from pipeline.cli import (
    HelpFormatter,
    add_no_progress,
    check_not_input,
    check_output,
    examples,
    frame_rate,
    probability,
    show_progress,
    sigterm_as_interrupt,
    skipped_summary,
    stopped,
    unwritable,
)
from pipeline.errors import InputError
from pipeline.frame import (
    DRIVE_SCANS,
    IMAGE_SUFFIXES,
    Frame,
    drive_frame_ids,
    frame_ids,
    load_drive_frame,
    load_frame,
    read_drive_calib,
    read_split_file,
)
from pipeline.kitti import (
    read_calib,
    read_image,
    read_image_depth_png,
    read_labels,
    read_velodyne,
    write_labels,
)
from pipeline.model_files import DEFAULT_MODELS, ModelFileError, default_models_hint
from pipeline.render import (
    VIDEO_FPS,
    FrameVideo,
    VideoError,
    camera_scale_in_stack,
    draw_label,
    render_bev,
    render_camera,
    split_scan_and_pseudo,
    stack_views,
    write_png,
)

if TYPE_CHECKING:  # the Detector (and ONNX Runtime) load only when a run starts, not for --help
    from pipeline.detector import Detections, Detector

log = logging.getLogger(__name__)


@dataclass
class DetectResult:
    """What a run wrote: frame ids, result files, pictures (BEV and camera view), and per-stage mean timings (ms)."""

    frame_ids: list[str]
    result_files: list[Path]
    pictures: list[Path]
    mean_timings_ms: dict[str, float]
    detection_count: int  # result lines written, over every frame
    skipped: dict[str, str] = field(default_factory=dict)  # frame id → why (folder runs go on past a bad frame)
    video_frames: int = 0  # frames in --video (0: no video written)
    warnings: list[tuple[str, str, str]] = field(default_factory=list)  # (frame id, code, message), as in WARNINGS_FILE


def _labels_for_picture(data: Path, fid: str) -> list | None:
    """The frame's ground truth for its picture, or None: labels are optional, so a broken label file
    costs the picture its labelled cars' boxes (with a warning), not the detections."""
    path = Path(data) / "label_2" / f"{fid}.txt"
    if not path.exists():
        return None
    try:
        return read_labels(path)
    except InputError as exc:
        log.warning("warning: %s (the picture has no ground truth)", exc)
        return None


def run(
    models: Path,
    out: Path,
    data: Path | None = None,
    frames: list[str] | None = None,
    image: Path | None = None,
    points: Path | None = None,
    calib: Path | None = None,
    emulate_beams: int | None = None,
    score_threshold: float | None = None,
    provider: str | None = None,
    pictures: bool = True,
    progress: bool = True,
    depth_dir: Path | None = None,
    mirror_tta: bool = False,
    drive: Path | None = None,
    video: Path | None = None,
    video_fps: float = VIDEO_FPS,
    split_file: Path | None = None,
) -> DetectResult:
    """Detect on a folder (``data`` + optional ``frames`` or ``split_file``), a KITTI raw drive (``drive`` + the
    same) or one set of files; write the outputs.

    depth_dir: ``<id>.png`` dense depth maps of the camera image (KITTI depth PNGs) used instead of the
    depth network, named by frame id (by the scan's file name for one set of files). mirror_tta: PIXOR also
    on the mirrored BEV, maps averaged (:class:`pipeline.detector.Detector`). video: also the pictures (camera
    view above BEV) as one MP4 (needs ``pictures``), ``video_fps`` frames a second.

    An InputError before any model loads for an ``out`` or ``video`` over an input
    (:func:`check_outputs_not_inputs`) and for ``emulate_beams`` on scans thinned already
    (:func:`check_thinnable_first_scan`).
    """
    from pipeline.detector import Detector  # ONNX Runtime loads as a run starts, not for --help

    frames_of = frame_source(data, drive, frames, image, points, calib, split_file)  # before any model loads
    out = Path(out)
    inputs = {"--data": data, "--drive": drive, "--models": models, "--image": image, "--points": points,
              "--calib": calib, "--split-file": split_file, "--depth-dir": depth_dir}
    _check_before_models(out, video, frames_of, inputs, emulate_beams, pictures, depth_dir)
    movie = _probed_video(video, video_fps)
    detector = Detector(models, providers=provider, mirror_tta=mirror_tta)
    if depth_dir is not None and not detector.two_stage:
        raise InputError(f"--depth-dir: {models} is a LiDAR-only model directory; it uses no depth")
    _warn_of_earlier_outputs(out, frames_of.ids, pictures)
    result = _detect_and_finish_video(detector, frames_of, out, depth_dir, score_threshold, emulate_beams, pictures,
                                      progress, movie)
    if movie is not None:
        _warn_of_earlier_video(movie, video)
    return result


def _check_before_models(out: Path, video: Path | None, frames_of: FrameSource, inputs: dict[str, Path | None],
                         emulate_beams: int | None, pictures: bool, depth_dir: Path | None) -> None:
    """The InputErrors of :func:`run`'s arguments, before any model loads: outputs over inputs, scans thinned
    already, --video without pictures, a missing --depth-dir, --out folders that cannot be written."""
    check_outputs_not_inputs(out, video, frames_of.ids, inputs)
    if emulate_beams:
        check_thinnable_first_scan(frames_of, emulate_beams)
    if video is not None and not pictures:
        raise InputError("--video is made of the pictures: leave out --no-pictures")
    if depth_dir is not None and not Path(depth_dir).is_dir():  # else every frame would be skipped in turn
        raise InputError(f"--depth-dir {depth_dir}: directory not found")
    # The folders each frame writes into, before the models load (a file in the way used to be found only
    # after the first frame was detected).
    for folder in (out, out / "data", *((out / "bev", out / "camera") if pictures else ())):
        check_output(folder, "--out", directory=True)


def _probed_video(video: Path | None, video_fps: float) -> FrameVideo | None:
    """The --video being written (None without one), its folder tried first: a folder the video cannot be
    written into is refused before the models load."""
    if video is None:
        return None
    movie = FrameVideo(video, video_fps)
    movie.probe()
    return movie


def _detect_and_finish_video(detector: Detector, frames_of: FrameSource, out: Path, depth_dir: Path | None,
                             score_threshold: float | None, emulate_beams: int | None, pictures: bool,
                             progress: bool, movie: FrameVideo | None) -> DetectResult:
    """:func:`_detect_frames`, then the video put in place. On an error or Ctrl-C the exception carries, for
    :func:`main`, how many frames have their files (``frames_written``) and whether the video was written."""
    result: DetectResult | None = None
    try:
        result = _detect_frames(detector, frames_of, out, depth_dir, score_threshold, emulate_beams, pictures,
                                progress, movie)
        if movie is not None and movie.close():
            result.video_frames = movie.frames
    except BaseException as exc:  # an error or Ctrl-C: no cut-off video; one of an earlier run stays as it was
        if result is not None:  # stopped while the video was finished: every frame has its files (main says so)
            exc.frames_written = len(result.result_files)  # type: ignore[attr-defined]
        if movie is not None:
            movie.discard()
            # main reads it: an interrupt may come just after the video was put in place
            exc.video_written = movie.written  # type: ignore[attr-defined]
        raise
    return result


def _warn_of_earlier_video(movie: FrameVideo, video: Path | None) -> None:
    """A warning when the run wrote no video (no frame was detected) but an earlier run's is at its path."""
    if not movie.written and movie.path.is_file():
        log.warning("warning: --video %s: no frame was detected, so no video was written; the file there is an "
                    "earlier run's", video)


@dataclass
class FrameSource:
    """The frames of a run: their ids, how each is loaded, and where an error says it came from."""

    ids: list[str]
    load: Callable[[str], Frame]
    where: Callable[[str], str | dict[str, Path]]  # the folder and frame, or the files of one frame
    labels: Path | None = None  # a KITTI object folder: the pictures draw its label_2 ground truth
    single: bool = False  # one set of files: an unusable one is an error, not a skipped frame
    scan: Callable[[str], Path] | None = None  # a folder's or drive's frame → its scan file


def frame_source(data: Path | None, drive: Path | None, frames: list[str] | None, image: Path | None,
                 points: Path | None, calib: Path | None, split_file: Path | None = None) -> FrameSource:
    """The frames a run detects on: a KITTI object folder (``data``), a raw drive (``drive``), each with
    optional ``frames`` ids or a ``split_file`` of them, or one set of files. The folder, the ids and a drive's
    calibration (or the one frame's files) are read and checked here, before any model loads."""
    files_given = image is not None or points is not None or calib is not None
    if (data is not None) + (drive is not None) + files_given > 1:
        raise InputError("give one of --data DIR, --drive DIR, or --image, --points and --calib, not two of them")
    chooser = "--split-file" if split_file is not None else "--frame"
    if (frames or split_file is not None) and data is None and drive is None:
        raise InputError(f"{chooser} chooses frames of --data DIR or --drive DIR; with --image/--points/--calib "
                         "there is one frame")
    if split_file is not None:
        if frames:
            raise InputError("give --frame ID or --split-file F, not both")
        frames = read_split_file(split_file)
    if data is not None:
        ids = _chosen_frames(frame_ids(data), frames, Path(data) / "velodyne", f"{data}: no frames", split_file)
        _check_frame_folders(Path(data))
        if not frames:  # every frame: one whose image has no scan would otherwise get no result file, unsaid
            ids = sorted({*ids, *_image_ids(Path(data))})
        return FrameSource(ids, lambda fid: load_frame(data, fid, with_labels=False),  # labels: read for pictures
                           lambda fid: f"{data}, frame {fid}", labels=Path(data),
                           scan=lambda fid: Path(data) / "velodyne" / f"{fid}.bin")
    if drive is not None:
        ids = _chosen_frames(drive_frame_ids(drive), frames, Path(drive) / DRIVE_SCANS, f"{drive}: no frames",
                             split_file)
        drive_calib = read_drive_calib(drive)
        return FrameSource(ids, lambda fid: load_drive_frame(drive, fid, drive_calib),
                           lambda fid: f"{drive}, frame {fid}",
                           scan=lambda fid: Path(drive) / DRIVE_SCANS / f"{fid}.bin")
    if image is not None and points is not None and calib is not None:
        scan = read_velodyne(points)
        frame = Frame(Path(points).stem, read_image(image), scan.points, read_calib(calib), None, scan.dropped_nonfinite)
        files = {"image": Path(image), "points": Path(points), "calib": Path(calib)}
        return FrameSource([frame.frame_id], lambda fid: frame, lambda fid: files, single=True)
    raise InputError("give --data DIR or --drive DIR (and optionally --frame), or all of --image, --points and "
                     "--calib")


# What a run writes in --out: each frame's file in each of these folders (a skipped frame's are removed instead,
# pictures included, with or without --no-pictures).
WRITTEN = {"data": ".txt", "bev": ".png", "camera": ".png"}
# Every frame's warnings, in --out: frame id, code, message, tab-separated (KITTI result files cannot hold them).
WARNINGS_FILE = "warnings.txt"
WARNINGS_HEADER = "frame_id\tcode\tmessage"


def check_outputs_not_inputs(out: Path, video: Path | None, ids: list[str], inputs: dict[str, Path | None]) -> None:
    """An InputError, before any model loads, for an --out or --video that would be written over what the run
    reads (``inputs``: flag → path, None when not given): :func:`pipeline.cli.check_not_input` for --out, the
    folders written in it and the video, so ``--out DRIVE/oxts`` no longer replaced a drive's GPS files; and
    an input file that is one of the files written or removed in --out (``--calib X/data/ID.txt --out X``).

    A raw drive (--drive) is an input whole, as --models is: besides the folders read, KITTI's drive holds
    image_00/01/03/, oxts/ and tracklets, none of which a run's files belong among; an object folder
    (--data) only its own folders (``--out K/results`` is a new folder beside them)."""
    written = [out, *(out / folder for folder in WRITTEN)]
    for folder in written:
        check_not_input(folder, "--out", inputs)
    if video is not None:
        check_not_input(video, "--video", inputs)
    names = set(ids)
    kinds = {(out / folder).resolve(): suffix for folder, suffix in WRITTEN.items()}
    record = (out / WARNINGS_FILE).resolve()
    for flag, source in inputs.items():
        if source is None or not Path(source).is_file():
            continue
        path = Path(source).resolve()
        if path == record:  # a --split-file kept beside the results: the run rewrites that file
            raise InputError(f"--out {out}: its {WARNINGS_FILE} would be written over {flag} {source}, which this "
                             "run reads; give an --out elsewhere")
        if kinds.get(path.parent) == path.suffix and path.stem in names:
            raise InputError(f"--out {out}: its {path.parent.name}/{path.name} would be written over {flag} {source}, "
                             "which this run reads; give an --out elsewhere")
    check_warnings_record(out / WARNINGS_FILE)


def check_warnings_record(record: Path) -> None:
    """An InputError, before any work, when ``record`` (OUT/warnings.txt) is there but is not a warnings file an
    earlier run wrote (a folder, or a file of other text): the run rewrites it as each frame is done, which would
    fail after the first frame's work (a folder) or lose what the file held."""
    if not (record.exists() or record.is_symlink()):
        return
    if record.is_file():
        with contextlib.suppress(OSError, UnicodeDecodeError), record.open(encoding="utf-8") as file:
            if file.readline().rstrip("\n") == WARNINGS_HEADER:
                return
        what = f"not a warnings file of pipeline.detect (its first line is not {WARNINGS_HEADER!r})"
    else:
        what = "not a file"
    raise InputError(f"--out {record.parent}: {record} is {what}; the run writes every frame's warnings there: move "
                     "it away or give another --out")


def check_thinnable_first_scan(frames_of: FrameSource, beams: int) -> None:
    """An InputError, before any model loads, when --emulate-beams ``beams`` is given for scans that cannot be
    thinned to it (a 16-line sensor's): every frame would otherwise be skipped in turn, with advice to mend
    files that are fine. As :func:`pipeline.beams.check_thinnable` (accuracy.py, models.train,
    models.cache_pseudo) one scan decides: the first that can be read and has points, so that a broken one
    stays its frame's skip, not the run's end; for a drive too (velodyne_points/data/)."""
    if frames_of.scan is None:  # one set of files: the Detector's error names the file
        return
    for fid in frames_of.ids:
        path = frames_of.scan(fid)
        try:
            points = read_velodyne(path).points
        except InputError:
            continue  # an unusable scan (or an image without one) is the frame loop's to skip and name
        if points.shape[0] == 0:
            continue
        check_scan_thinnable(path, points, beams, "detect on")
        return


# An object folder's folders besides velodyne/ (frame_ids checks that one) that every frame reads from.
FRAME_FOLDERS = {"image_2": "the camera images", "calib": "the calibrations"}


def _check_frame_folders(data: Path) -> None:
    """An InputError for an object folder without image_2/ or calib/: a wrong --data, said once before any model
    loads, rather than every frame skipped in turn with its own line."""
    for folder, holds in FRAME_FOLDERS.items():
        if not (data / folder).is_dir():
            raise InputError(f"{data}: no {folder}/ ({holds}) inside; a KITTI object folder holds image_2/, "
                             "velodyne/ and calib/")


def _warn_of_earlier_outputs(out: Path, ids: list[str], pictures: bool) -> None:
    """Warnings for what an earlier run left in ``out`` that this one will not replace: result files of frames
    it does not detect (another drive's or folder's, which an evaluation of the folder would read as this
    run's), and, with no pictures asked for, pictures that no longer match the results."""
    folder = out / "data"
    others = sorted({p.stem for p in folder.glob("*.txt")} - set(ids)) if folder.is_dir() else []
    if others:
        log.warning("warning: %s holds %d result file(s) of frames this run does not detect (from an earlier run?), "
                    "e.g. %s.txt", folder, len(others), others[0])
    stale = [out / kind for kind in ("bev", "camera") if not pictures and any((out / kind).glob("*.png"))]
    if stale:
        log.warning("warning: %s hold(s) pictures of an earlier run; this run writes none (--no-pictures), so they "
                    "will not match its results", " and ".join(map(str, stale)))


def _detect_frames(detector: Detector, frames_of: FrameSource, out: Path, depth_dir: Path | None,
                   score_threshold: float | None, emulate_beams: int | None, pictures: bool, progress: bool,
                   video: FrameVideo | None) -> DetectResult:
    """The frames in turn: detect, write the result file and the picture (and the video's frame); a folder's
    or drive's frame whose files are unusable is skipped and named."""
    from tqdm import tqdm

    results: list[Path] = []
    images: list[Path] = []
    totals: dict[str, float] = {}
    count = 0
    warned: set[str] = set()
    said: list[tuple[str, str, str]] = []  # every frame's warnings, in frame order
    skipped: dict[str, str] = {}
    ids = frames_of.ids
    record = out / WARNINGS_FILE
    _forget_warnings_of(record, set(ids))
    try:
        for fid in tqdm(ids, desc="detect", unit="frame", disable=not progress or len(ids) < 2):
            try:
                frame, detections = _load_and_detect(detector, frames_of, fid, depth_dir, score_threshold,
                                                     emulate_beams)
            except InputError as exc:
                if frames_of.single:  # one set of files: nothing else to do
                    raise
                skipped[fid] = _skip_frame(out, fid, exc)
                continue
            # Every frame's warnings are on record as it is detected (a run stopped midway keeps the frames done);
            # the terminal names only the first frame of each kind and, at the end, each code's count.
            mine = _warnings_to_record(frame.frame_id, detections)
            _say_new_kinds(fid, mine, warned)
            _record_warnings(record, mine)
            said += mine
            _add_timings(totals, detections.timings_ms)
            result, cars = _write_result_file(out, frame, detections)
            count += cars  # what the result files hold: the boxes the camera sees
            results.append(result)
            if pictures:
                images += _draw_pictures(out, detector, frame, detections, frames_of.labels, emulate_beams, mine,
                                         video, cars)
    except KeyboardInterrupt as exc:  # main says where the frames done are, or that there are none yet
        exc.frames_written = len(results)  # type: ignore[attr-defined]
        raise
    done = len(ids) - len(skipped)
    means = {stage: total / done for stage, total in totals.items()} if done else {}
    return DetectResult(list(ids), results, images, means, count, skipped, warnings=said)


def _load_and_detect(detector: Detector, frames_of: FrameSource, fid: str, depth_dir: Path | None,
                     score_threshold: float | None, emulate_beams: int | None) -> tuple[Frame, Detections]:
    """Frame ``fid`` loaded and detected on (:func:`_detect_frame`), with a warning for the scan's rows dropped
    as not finite; an InputError names the file or frame that cannot be used."""
    frame = frames_of.load(fid)
    detections = _detect_frame(detector, frame, frames_of.where(fid), depth_dir, score_threshold, emulate_beams)
    if frame.dropped_nonfinite:  # as the service says it, so a broken driver does not go unnoticed
        detections.add_warning(WarningCode.NONFINITE_DROPPED, "points: dropped rows with NaN or infinite "
                               f"values ({frame.dropped_nonfinite} rows)")
    return frame, detections


def _skip_frame(out: Path, fid: str, exc: InputError) -> str:
    """Skip a folder's or drive's unusable frame: remove its earlier run's outputs, say so on stderr (above the
    progress bar); why it was skipped."""
    from tqdm import tqdm

    removed = _remove_earlier_outputs(out, fid)
    also = f"; removed its {' and '.join(removed)} from an earlier run" if removed else ""
    tqdm.write(f"error: {exc} (frame {fid} skipped{also})", file=sys.stderr)
    return str(exc)


def _warnings_to_record(frame_id: str, detections: Detections) -> list[tuple[str, str, str]]:
    """The frame's warnings (frame id, code, message) but the thinning the run's own --emulate-beams asked for
    (a line on every frame, saying what the command line says)."""
    return [(frame_id, str(code), warning)
            for warning, code in zip(detections.warnings, detections.warning_codes, strict=True)
            if code != WarningCode.BEAMS_EMULATED]


def _say_new_kinds(fid: str, warnings: list[tuple[str, str, str]], warned: set[str]) -> None:
    """Print on stderr each of the frame's warnings of a kind not said yet, adding its kind to ``warned``."""
    from tqdm import tqdm

    for _, _, warning in warnings:
        kind = warning.rsplit(" (", 1)[0]  # each kind once (the trailing "(…)" holds the frame's figures)
        if kind not in warned:
            warned.add(kind)
            tqdm.write(f"warning: {fid}: {warning}", file=sys.stderr)  # above the progress bar, not in it


def _add_timings(totals: dict[str, float], timings_ms: dict[str, float]) -> None:
    """Add a frame's per-stage timings (ms) to the run's ``totals``."""
    for stage, ms in timings_ms.items():
        totals[stage] = totals.get(stage, 0.0) + ms


def _write_result_file(out: Path, frame: Frame, detections: Detections) -> tuple[Path, int]:
    """Write the frame's KITTI result file in ``out/data``: its path and its count of lines (the boxes the camera
    sees)."""
    (out / "data").mkdir(parents=True, exist_ok=True)
    result = out / "data" / f"{frame.frame_id}.txt"
    # Every source loads the image (so its size), and _detect_frame keeps the points PIXOR saw.
    assert frame.image is not None and frame.image_hw is not None and detections.points is not None
    objects = detections.to_objects(frame.calib, frame.image_hw)
    write_labels(result, objects)
    return result, len(objects)


def _draw_pictures(out: Path, detector: Detector, frame: Frame, detections: Detections, labels: Path | None,
                   emulate_beams: int | None, warnings: list[tuple[str, str, str]], video: FrameVideo | None,
                   cars: int) -> list[Path]:
    """Draw the frame's BEV and camera pictures (the labelled cars of ``labels``' folder too) and write them in
    ``out``: their paths; add the frame to ``video``, captioned with its ``cars`` in view."""
    assert frame.image is not None and frame.image_hw is not None  # as _write_result_file checked
    gt = _ground_truth(labels, frame)
    title = picture_title(frame.frame_id, detector.model_dir, emulate_beams)
    # The sensor faults and mismatches named on stderr, by code (the thinning asked for is in the title).
    faults = [code for _, code, _ in warnings]
    bev = _render_bev(detector, frame, detections, gt, title, faults)
    seen = in_camera_view(detections.boxes, frame.calib, frame.image_hw)  # the result file's boxes
    camera = render_camera(frame.image, frame.calib, detections.boxes[seen], detections.scores[seen], gt,
                           title=title, legend=True, warnings=faults)
    written = _write_pictures(out, frame.frame_id, {"bev": bev, "camera": camera})
    if video is not None:  # the camera view drawn again at the video's size, so its scores stay readable
        small = render_camera(frame.image, frame.calib, detections.boxes[seen], detections.scores[seen], gt,
                              scale=camera_scale_in_stack(frame.image_hw, bev), legend=True, warnings=faults)
        video.add(_captioned(stack_views(small, bev), frame.frame_id, cars))
    return written


def _ground_truth(labels: Path | None, frame: Frame) -> np.ndarray | None:
    """The labelled cars of the frame in an object folder (``labels``), as boxes for its pictures; None when
    there are none (no folder, no label file, a broken one, no object)."""
    objects = _labels_for_picture(labels, frame.frame_id) if labels is not None else None
    if not objects:
        return None
    return labels_to_boxes([o for o in objects if o.type == "Car"], frame.calib)


def _render_bev(detector: Detector, frame: Frame, detections: Detections, gt: np.ndarray | None, title: str,
                faults: list[str]) -> np.ndarray:
    """The BEV picture: the points PIXOR saw (the scan's and the camera's pseudo points apart), the camera's
    view, the boxes and scores, the labelled cars ``gt`` and the frame's warning codes in the key."""
    assert detections.points is not None and frame.image_hw is not None  # as _write_result_file checked
    scan, pseudo = split_scan_and_pseudo(detections.points, detections.pseudo_count)
    return render_bev(scan, detector.preset.bev, detections.boxes, detections.scores, gt, title=title,
                      legend=True, pseudo=pseudo, view=(frame.calib, frame.image_hw), warnings=faults)


def _write_pictures(out: Path, frame_id: str, pictures: dict[str, np.ndarray]) -> list[Path]:
    """Write each picture as ``out/KIND/ID.png`` (``pictures``: kind → picture); the paths, in that order."""
    paths = []
    for kind, picture in pictures.items():
        (out / kind).mkdir(parents=True, exist_ok=True)
        path = out / kind / f"{frame_id}.png"
        write_png(path, picture)
        paths.append(path)
    return paths


def _forget_warnings_of(record: Path, ids: set[str]) -> None:
    """Drop the lines of ``ids`` (this run's frames) from an earlier run's warnings file, as their result files
    are written again or removed; the file goes when no line is left. Other frames' lines stay with their
    result files."""
    if not record.is_file():
        return
    # Its header was checked (check_warnings_record); a byte past it that is not UTF-8 is kept as U+FFFD, not a
    # traceback. Replaced whole (a temporary file, then a rename): a run stopped here leaves the old file or the new.
    kept = [line for line in record.read_text(encoding="utf-8", errors="replace").splitlines()[1:]
            if line and line.split("\t", 1)[0] not in ids]
    if kept:
        temporary = record.with_name(f".{record.name}.tmp")
        temporary.write_text("\n".join([WARNINGS_HEADER, *kept]) + "\n", encoding="utf-8")
        os.replace(temporary, record)
    else:
        record.unlink()


def _record_warnings(record: Path, warnings: list[tuple[str, str, str]]) -> None:
    """Append one frame's warnings to the warnings file (its header first when new); nothing when none."""
    if not warnings:
        return
    record.parent.mkdir(parents=True, exist_ok=True)
    new = not record.is_file()
    with record.open("a", encoding="utf-8") as file:
        if new:
            file.write(WARNINGS_HEADER + "\n")
        for row in warnings:  # a tab or line break inside a message would split its line
            file.write("\t".join(" ".join(part.split()) for part in row) + "\n")


def warnings_summary(warnings: list[tuple[str, str, str]], frames: int, shown: int = 5) -> list[str]:
    """One line per warning code of a run (``warnings``: frame id, code, message, as the warnings file holds them):
    ``line_count on 2 of 5 frames (000000, 000006)``, the first ``shown`` frame ids, then how many more."""
    by_code: dict[str, list[str]] = {}
    for fid, code, _ in warnings:
        named = by_code.setdefault(code, [])
        if fid not in named:
            named.append(fid)
    lines = []
    for code, ids in by_code.items():
        more = f", and {len(ids) - shown} more" if len(ids) > shown else ""
        lines.append(f"{code} on {len(ids)} of {frames} frame{'' if frames == 1 else 's'} "
                     f"({', '.join(ids[:shown])}{more})")
    return lines


def picture_title(frame_id: str, models: Path, emulate_beams: int | None) -> str:
    """What a picture shows, for its key: the frame, the model directory and whether its scan was thinned."""
    thinned = f", scan thinned to {emulate_beams} lines" if emulate_beams else ""
    return f"frame {frame_id}, model {Path(models).name}{thinned}"


def _captioned(picture: np.ndarray, frame_id: str, cars: int) -> np.ndarray:
    """The video's frame: the picture with its frame id and the count of cars in the camera's view (those of
    the result file) in the corner; in a video the frames pass by. ``picture`` is a fresh stack_views array."""
    return draw_label(picture, f"{frame_id}  {cars} car{'' if cars == 1 else 's'} in view")


def _remove_earlier_outputs(out: Path, fid: str) -> list[str]:
    """Remove a skipped frame's result file and picture left in ``out`` by an earlier run; what was removed.

    An evaluation reads every result file in ``OUT/data``: an old one would be scored as this run's.
    """
    removed = []
    for kind, path in (("result file", out / "data" / f"{fid}.txt"), ("picture", out / "bev" / f"{fid}.png"),
                       ("camera picture", out / "camera" / f"{fid}.png")):
        if path.is_file():
            path.unlink()
            removed.append(f"{kind} {path}")
    return removed


def _image_ids(data: Path) -> set[str]:
    """The frame ids of an object folder's images (``image_2/ID.png``, or a JPEG)."""
    folder = data / "image_2"
    return {p.stem for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES} if folder.is_dir() else set()


def _chosen_frames(scans: list[str], frames: list[str] | None, scan_dir: Path, none: str,
                   split_file: Path | None = None) -> list[str]:
    """The ids to run on, in order: every scan of a folder or drive (``scans``, from ``scan_dir``), or the
    --frame ids (those of ``split_file`` when given), each of which must have a scan. A plain number stands
    for the scan it names with its zeros (``5`` → ``000005`` in an object folder, ``0000000005`` in a drive)."""
    if not frames:
        if not scans:
            raise InputError(f"{none} (no .bin scans in {scan_dir})")
        return scans
    present = set(scans)
    width = next((len(fid) for fid in scans if fid.isdigit()), 0)  # KITTI names every frame with one width
    frames = [fid.zfill(width) if fid not in present and fid.isdigit() else fid for fid in frames]
    repeated = sorted({fid for fid in frames if frames.count(fid) > 1})
    if repeated:  # its result file would be written twice, its picture filmed twice
        raise InputError(f"--frame {repeated[0]} given twice")
    # A misspelt id is a mistake in the command, not a bad file: refuse it rather than skip it.
    unknown = [fid for fid in frames if fid not in present]
    if unknown:
        scan = scan_dir / (unknown[0] + ".bin")
        if split_file is not None:  # a frame of test.txt without its scan: its result file could not be made
            more = f" (and {len(unknown) - 1} more of its frames without one)" if len(unknown) > 1 else ""
            raise InputError(f"--split-file {split_file}: frame {unknown[0]} has no scan {scan}{more}")
        more = f" (and {len(unknown) - 1} more --frame without one)" if len(unknown) > 1 else ""
        raise InputError(f"--frame {unknown[0]}: no scan {scan}{more}")
    return sorted(frames)


def _detect_frame(detector: Detector, frame: Frame, source: str | dict[str, Path], depth_dir: Path | None,
                  score_threshold: float | None, emulate_beams: int | None) -> Detections:
    """Detect on one loaded frame (with its --depth-dir map); an InputError names the file, or source:
    the folder and frame, or for one set of files the file of the field the Detector names."""
    depth = None
    if depth_dir is not None:
        assert frame.image is not None  # every frame source loads the image
        depth = read_image_depth_png(Path(depth_dir) / f"{frame.frame_id}.png", frame.image.shape[:2])
    if frame.points.shape[0] == 0 and frame.dropped_nonfinite:
        raise InputError(f"{_where(source, 'points')}: points: none of the scan's {frame.dropped_nonfinite} rows is finite")
    try:
        detections = detector.detect(frame.image, frame.points, frame.calib, score_threshold, emulate_beams,
                                     keep_points=True, depth=depth)
    except InputError as exc:  # the Detector names the field ("image: …"); say which frame or file it was
        raise InputError(f"{_where(source, str(exc).partition(':')[0])}: {exc}") from exc
    return detections


def _where(source: str | dict[str, Path], field: str) -> str:
    """The folder and frame, or the file that holds ``field`` (the scan's when no file is named by it)."""
    return source if isinstance(source, str) else str(source.get(field, source["points"]))


def main(argv: list[str] | None = None) -> int:
    """The ``python -m pipeline.detect`` command: its exit status."""
    parser = _parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.video_fps is not None and args.video is None:
        parser.error("--video-fps sets the frame rate of --video: give --video FILE.mp4 too")
    try:
        # SIGTERM (a supervisor stopping the run) ends it as Ctrl-C does, so the partial video is removed.
        with sigterm_as_interrupt():
            return _run_and_report(args)
    except KeyboardInterrupt as exc:  # Ctrl-C or SIGTERM: the frames done keep their files
        return stopped(exc, _left_when_stopped(args, exc))


def _parser() -> argparse.ArgumentParser:
    """The command's arguments, in the order --help lists them: the inputs, how to detect, the outputs."""
    parser = argparse.ArgumentParser(
        allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
        prog="python -m pipeline.detect",
        description="Detect cars with a lowres3d model directory on KITTI-layout frames or a KITTI raw drive; "
        "write KITTI result lines (label_2 format + score) to OUT/data, BEV pictures to OUT/bev and the camera "
        "view with the boxes to OUT/camera.",
        epilog=examples("python -m pipeline.detect --data data/kitti/training --split-file "
                        "data/kitti/ImageSets/val.txt --emulate-beams 16 --score-threshold 0.05 --out outputs/val",
                        "python -m pipeline.detect --image F.png --points F.bin --calib F.txt --out outputs/one"),
        formatter_class=HelpFormatter,
    )
    _add_input_arguments(parser)
    _add_detection_arguments(parser)
    _add_output_arguments(parser)
    return parser


def _add_input_arguments(parser: argparse.ArgumentParser) -> None:
    """The model directory and the frames: a folder, a raw drive (either with chosen frames) or one set of files."""
    parser.add_argument("--models", type=Path, default=DEFAULT_MODELS, metavar="DIR",
                        help=f"model directory (default {DEFAULT_MODELS})")
    parser.add_argument("--data", type=Path, metavar="DIR",
                        help="KITTI object folder with image_2/, velodyne/, calib/ (label_2/ optional)")
    parser.add_argument("--drive", type=Path, metavar="DIR",
                        help="KITTI raw drive folder (DATE_drive_NNNN_sync) with image_02/data/ and "
                        "velodyne_points/data/; its calib_cam_to_cam.txt and calib_velo_to_cam.txt in the date "
                        "folder above it (or in it)")
    parser.add_argument("--frame", action="append", dest="frames", metavar="ID",
                        help="frame id of --data or --drive, or its number (5 for 000005; repeatable; default all)")
    parser.add_argument("--split-file", type=Path, metavar="F",
                        help="the frame ids of --data or --drive to run on, one per line (ImageSets' val.txt or "
                        "test.txt); each must have a scan")
    parser.add_argument("--image", type=Path, metavar="F", help="camera image (PNG/JPEG), with --points and --calib")
    parser.add_argument("--points", type=Path, metavar="F", help="velodyne .bin scan")
    parser.add_argument("--calib", type=Path, metavar="F", help="KITTI calib .txt")


def _add_detection_arguments(parser: argparse.ArgumentParser) -> None:
    """How each frame is detected: the scan's thinning, the score threshold, the provider, the depth source."""
    parser.add_argument("--emulate-beams", type=int, metavar="N", choices=(0, *BEAM_COUNTS),
                        help=f"thin a 64-line scan to N lines first ({', '.join(map(str, BEAM_COUNTS))}; 0, the "
                        "default: the scans as stored, as a 16-line sensor's own; the flag of accuracy.py and "
                        "latency.py)")
    parser.add_argument("--score-threshold", type=probability, metavar="SCORE",
                        help="minimum score (default: the model's, 0.5 for the shipped ones); for result files "
                        "to evaluate give 0.05: AP needs the low-score detections")
    parser.add_argument("--provider", choices=["cpu", "cuda", "tensorrt"], help="execution provider (default: best available)")
    parser.add_argument("--depth-dir", type=Path, metavar="DIR",
                        help="dense depth PNGs of the camera image (KITTI depth format, <id>.png) used instead of "
                        "the depth network: another depth source, or depth_2/ ground truth for an upper bound")
    parser.add_argument("--mirror-tta", action="store_true",
                        help="also run PIXOR on the BEV mirrored left to right and average the maps: PIXOR's time "
                        "twice over for boxes more often right to IoU 0.7 (docs/models.md)")


def _add_output_arguments(parser: argparse.ArgumentParser) -> None:
    """What is written: the pictures, the video, the output folder, the progress bar."""
    parser.add_argument("--no-pictures", action="store_true", help="skip the BEV and camera-view PNGs")
    parser.add_argument("--video", type=Path, metavar="FILE.mp4",
                        help="also put the pictures (camera view above BEV), in frame order and captioned, into "
                        "one MP4 (MPEG-4 Part 2: VLC, ffmpeg and most players, not web browsers)")
    parser.add_argument("--video-fps", type=frame_rate, default=None, metavar="FPS",
                        help=f"frames a second of --video, 0.1 to 1000 (default {VIDEO_FPS:g}: KITTI's LiDAR rate)")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR",
                        help="output folder (outside what the run reads; a new folder in --data will do)")
    add_no_progress(parser)


def _left_when_stopped(args: argparse.Namespace, exc: KeyboardInterrupt) -> str:
    """What a run stopped by Ctrl-C or SIGTERM leaves: the frames done (``exc.frames_written``) and the video
    (``exc.video_written``), for :func:`pipeline.cli.stopped`'s line."""
    if args.video is None:
        video = ""
    elif getattr(exc, "video_written", False):
        video = f"; the video {args.video} was written"
    else:
        video = f"; no video was written{' (the earlier one is kept)' if args.video.is_file() else ''}"
    if getattr(exc, "frames_written", 0):
        kept = f"the frames detected so far have their files in {args.out}"
    else:  # stopped before any frame's result file was written: --out may not even exist yet
        kept = f"no frame was detected yet, so this run wrote nothing in {args.out}"
    return f"{kept}{video}"


def _run_and_report(args: argparse.Namespace) -> int:
    """The run of :func:`main`'s arguments and its summary; the exit status (errors reported in one line)."""
    try:
        if args.video is not None:  # checked before the run (run() also tries its folder): lost after it
            if args.video.suffix.lower() != ".mp4":
                raise InputError(f"--video {args.video}: give a file name ending in .mp4")
            if args.video.is_dir():
                raise InputError(f"--video {args.video}: is a directory; give a file name")
        result = run(
            args.models, args.out, args.data, args.frames, args.image, args.points, args.calib,
            args.emulate_beams, args.score_threshold, args.provider, not args.no_pictures,
            depth_dir=args.depth_dir, mirror_tta=args.mirror_tta, drive=args.drive, video=args.video,
            video_fps=args.video_fps or VIDEO_FPS, split_file=args.split_file,
            progress=show_progress(args.no_progress),
        )
    except (InputError, ModelFileError) as exc:
        hint = default_models_hint(args.models)  # the default's absence itself: one line with the way out
        print(f"error: {hint if hint and str(args.models) in str(exc) else exc}", file=sys.stderr)
        return 2
    except VideoError as exc:
        print(f"error: --video {args.video}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # an --out that cannot be written (a file in the way, no permission, a full disk)
        print(unwritable(args.out, exc), file=sys.stderr)
        return 2
    try:
        return _report(args, result)
    except KeyboardInterrupt as exc:  # the run is over: main says its files are there, not that none were written
        exc.frames_written = len(result.result_files)  # type: ignore[attr-defined]
        raise


def _report(args: argparse.Namespace, result: DetectResult) -> int:
    """The summary of a finished run on stdout (its skipped frames on stderr); the exit status."""
    stages = ", ".join(f"{k} {v:.1f} ms" for k, v in result.mean_timings_ms.items())
    done = len(result.frame_ids) - len(result.skipped)
    print(f"{done} frame(s), {result.detection_count} detection(s) → {args.out}/data")
    if stages:
        print(f"mean per frame: {stages}")
    if result.pictures:
        print(f"pictures: {args.out}/bev/ (BEV) and {args.out}/camera/ (camera view)")
    if result.video_frames:
        frames = result.video_frames
        print(f"video: {args.video} ({frames} frame{'' if frames == 1 else 's'} at {args.video_fps or VIDEO_FPS:g} "
              "a second)")
    for line in warnings_summary(result.warnings, done):
        print(f"warning: {line}", file=sys.stderr)
    if result.warnings:
        print(f"warnings of each frame: {args.out / WARNINGS_FILE}")
    if result.skipped:
        print(f"error: {skipped_summary(list(result.skipped), 'frame', len(result.frame_ids))}", file=sys.stderr)
        if args.data is not None:  # the folder is a KITTI object split: its result files are what gets zipped
            print(f"error: {args.out / 'data'} has no result file for the {len(result.skipped)} skipped frame(s): "
                  "KITTI's evaluation server refuses a submission with a file missing, as benchmarks/accuracy.py "
                  "does without --missing-as-empty; mend their files and run them again (--frame ID)", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
