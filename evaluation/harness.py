"""Accuracy runs: the detector over a KITTI-layout dataset, and depth completion against ground truth.

Detection inputs (the paper's table rows):
``lidar64`` — PIXOR on the scan as stored; ``lidar16`` — PIXOR on the scan
thinned to 16 lines; ``lidar16+camera`` — the two-stage pipeline on the
16-line scan and the image. Each needs a model directory trained for it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from evaluation import DEFAULT_SCORE_THRESHOLD
from evaluation.depth_metrics import (
    DepthMetrics,
    car_box_shares,
    car_depth_errors,
    depth_metrics,
    mean_over_frames,
    moderate_cars_in_view,
)
from evaluation.frames import first_frames
from pipeline.beams import check_thinnable, emulate_beams
from pipeline.calib import Calibration, depth_crop
from pipeline.depth_completion import (
    DepthCompletionFrame,
    check_drive_folder,
    drive_calibration,
    drive_frame_ids,
    has_raw_scans,
    is_drive_folder,
    read_frame,
)
from pipeline.detector import Detector
from pipeline.errors import InputError, in_frame
from pipeline.frame import Frame, frame_ids, load_frame
from pipeline.kitti import read_image_depth_png
from pipeline.model_files import load_manifest
from pipeline.preprocess import depth_view, view_calibration, view_from_depth_png
from pipeline.presets import Preset
from pipeline.render import render_depth_panel, write_png

log = logging.getLogger(__name__)

INPUTS = {"lidar64": None, "lidar16": 16, "lidar16+camera": 16}




@dataclass(frozen=True)
class DetectionRun:
    """Where a detection run wrote its result files, and the frames it skipped (id → why)."""

    results: Path
    skipped: dict[str, str] = field(default_factory=dict)


def run_detection(data: Path, models: Path, input_mode: str, out: Path, frames: list[str] | None = None,
                  provider: str | None = None, progress: bool = True,
                  score_threshold: float = DEFAULT_SCORE_THRESHOLD, depth_dir: Path | None = None,
                  mirror_tta: bool = False, beams: int | None = None) -> DetectionRun:
    """Detect on every frame and write KITTI result files.

    beams: the line count the scans are thinned to; None: the input row's (16 for the lidar16 rows, the scans as
    stored for lidar64), 0: the scans as stored (a 16-line sensor's own scans, which cannot be thinned again;
    64-line ones are refused for the 16-line rows).

    A frame whose files are unusable is skipped (named on stderr) and has no result file, not even one
    from an earlier run into ``out``: the evaluation counts its cars as missed, and the caller says so.
    depth_dir: dense depth PNGs used instead of the depth network (``pipeline.detect --depth-dir``).
    mirror_tta: PIXOR also on the mirrored BEV (``pipeline.detect --mirror-tta``).
    """
    from pipeline.detect import run as detect

    if input_mode not in INPUTS:
        raise InputError(f"--input: {input_mode!r} is not one of {', '.join(INPUTS)}")
    # The manifest says the directory's kind and what its PIXOR learned from; pipeline.detect loads (and
    # checks) the models once, below.
    networks = load_manifest(models).get("networks", {})
    two_stage = "depth" in networks
    wants_camera = input_mode == "lidar16+camera"
    if two_stage != wants_camera:
        kind = "two-stage (depth.onnx + pixor.onnx)" if two_stage else "LiDAR-only (pixor.onnx)"
        raise InputError(f"--models: {models} is a {kind} model directory, which does not fit --input {input_mode}")
    trained_on = ((networks.get("pixor") or {}).get("training") or {}).get("input")
    if not two_stage and trained_on in ("lidar16", "lidar64") and trained_on != input_mode:
        # It would run, and be scored as the other row of the table (a 64-line PIXOR on 16-line scans).
        raise InputError(f"--models: {models}'s PIXOR was trained on --input {trained_on} scans (its manifest), "
                         f"not {input_mode}: give --input {trained_on}, or the model directory trained for {input_mode}")
    if depth_dir is not None and not wants_camera:
        raise InputError(f"--depth-dir: only the camera pipeline uses depth (--input lidar16+camera, not {input_mode})")
    emulate = INPUTS[input_mode] if beams is None else (beams or None)
    if emulate or INPUTS[input_mode]:  # a 16-line row's scans as stored (beams 0) must not be 64-line ones
        check_thinnable(data, frames, emulate or 0)
    result = detect(models, out, data=data, frames=frames, emulate_beams=emulate, provider=provider,
                    pictures=False, progress=progress, score_threshold=score_threshold, depth_dir=depth_dir,
                    mirror_tta=mirror_tta)
    if result.skipped and not result.result_files:
        # Else the evaluation's last line would be a missing result folder, after every frame was named.
        raise InputError(f"--data {data}: all {len(result.skipped)} frame(s) skipped (each named above with its "
                         "reason): nothing to evaluate")
    return DetectionRun(out / "data" if result.result_files else out, result.skipped)


@dataclass(frozen=True)
class DepthRun:
    """Mean metrics over frames, per-frame metrics, and what the input was."""

    mean: DepthMetrics
    per_frame: dict[str, DepthMetrics]
    layout: str
    input: str
    # Object folders with labels: (car depth z, median |error| mm on its pixels) of every moderate car.
    car_errors: list[tuple[float, float]] = field(default_factory=list)
    # And (car depth z, share of its pixels whose point lands in its BEV box), in the network's view,
    # and (car depth z, share of the other pixels of its 2D box that land there too).
    car_in_box: list[tuple[float, float]] = field(default_factory=list)
    car_stray: list[tuple[float, float]] = field(default_factory=list)


def _crop_ground_truth(gt: np.ndarray, preset) -> np.ndarray:
    return depth_crop(gt.shape, *preset.crop_hw).apply(gt)


def _to_crop_resolution(prediction: np.ndarray, crop_hw: tuple[int, int]) -> np.ndarray:
    """Bilinear resize of the network's view back to the crop (pixel centres aligned, as cv2 does)."""
    if prediction.shape == tuple(crop_hw):
        return prediction
    return cv2.resize(prediction, (crop_hw[1], crop_hw[0]), interpolation=cv2.INTER_LINEAR)


def run_depth(data: Path, models: Path, frames: list[str] | None = None, beams: int | None = 16,
              provider: str | None = None, progress: bool = True, pictures: Path | None = None,
              depth_dir: Path | None = None, first: int | None = None) -> DepthRun:
    """Depth completion metrics on the KITTI crop, at full resolution.

    Layouts: a KITTI depth-completion drive (``image_02/``, ``velodyne_raw/``,
    ``groundtruth/`` PNGs; :mod:`pipeline.depth_completion`), whose projected 64-line
    scan is thinned to ``beams`` lines through the drive's calibration
    (``calib_cam_to_cam.txt`` and ``calib_velo_to_cam.txt`` in the folder or the one
    above it): exactly with the raw scans in ``velodyne_points/``, else by each pixel's
    elevation (with a warning), and used as given without a calibration, with a warning; or a
    KITTI object folder with dense ground truth in ``depth_2/`` (the synthetic
    scenes), whose scan is thinned to ``beams`` lines first. pictures: a folder
    for one PNG per frame (``depth_<id>.png``: camera, prediction, ground truth, error).
    first: only the first N of the frames.
    """
    data = Path(data)
    layout = _depth_layout(data)
    detector = _depth_detector(models, provider)
    if pictures is not None:
        Path(pictures).mkdir(parents=True, exist_ok=True)
    job = _DepthJob(data, detector, depth_dir, pictures, _depth_source(models, depth_dir), progress)
    if layout == "depth-completion":
        used, figures = _depth_on_drive(job, frames, first, beams)
    else:
        used, figures = _depth_on_object_folder(job, frames, first, beams)
    if not figures.per_frame:
        raise InputError(f"--data: {data} has no frames to evaluate")
    if depth_dir is not None:
        used = f"depth maps from {depth_dir}, not the depth network; their pixels without depth left out"
    return DepthRun(mean=mean_over_frames(list(figures.per_frame.values())), per_frame=figures.per_frame,
                    layout=layout, input=used, car_errors=figures.car_errors, car_in_box=figures.car_in_box,
                    car_stray=figures.car_stray)


@dataclass(frozen=True)
class _DepthJob:
    """What every frame of a depth run shares: its folder, the detector, where the depth comes from, the pictures."""

    data: Path
    detector: Detector
    depth_dir: Path | None  # given depth maps evaluated instead of the depth network's
    pictures: Path | None  # a folder for one PNG per frame, or None for none
    source: str  # the depth's source, in the pictures' titles
    progress: bool

    @property
    def preset(self) -> Preset:
        """The model directory's preset: its crop and the depth net's view."""
        return self.detector.preset

    def picture(self, fid: str, image: np.ndarray, prediction: np.ndarray, ground_truth: np.ndarray) -> None:
        """``depth_<fid>.png`` (camera, prediction, ground truth, error) when pictures are asked for."""
        if self.pictures is not None:
            crop = depth_crop(image.shape[:2], *self.preset.crop_hw).apply(image)
            # Shown to 80 m whatever range the preset's pseudo points keep (35 m for the shipped model), so the
            # far ground truth is not clipped to the colour of the range's end.
            panel = render_depth_panel(crop, prediction, ground_truth, title=f"frame {fid}, {self.source}")
            write_png(Path(self.pictures) / f"depth_{fid}.png", panel)


@dataclass
class _DepthFigures:
    """What the frames measured so far: metrics per frame, and the moderate cars' figures (DepthRun's fields)."""

    per_frame: dict[str, DepthMetrics] = field(default_factory=dict)
    car_errors: list[tuple[float, float]] = field(default_factory=list)
    car_in_box: list[tuple[float, float]] = field(default_factory=list)
    car_stray: list[tuple[float, float]] = field(default_factory=list)


def _depth_layout(data: Path) -> str:
    """``data``'s layout, ``depth-completion`` or ``object + depth_2``; an InputError for neither."""
    if is_drive_folder(data):
        return "depth-completion"
    if (data / "depth_2").is_dir():
        return "object + depth_2"
    if (data / "proj_depth").is_dir() or data.name == "proj_depth":
        check_drive_folder(data)  # KITTI's own layout: how to link a drive into the flat one (raises: not a flat drive)
    raise InputError(
        f"--data: {data} has neither groundtruth/ + velodyne_raw/ (KITTI depth completion) "
        "nor depth_2/ (dense ground truth of an object folder)"
    )


def _depth_detector(models: Path, provider: str | None) -> Detector:
    """The model directory's detector; an InputError for a LiDAR-only one, which has no depth network."""
    detector = Detector(models, providers=provider)
    if not detector.two_stage:
        raise InputError(f"--models {models}: a LiDAR-only model directory has no depth network")
    return detector


def _depth_source(models: Path, depth_dir: Path | None) -> str:
    """Where the evaluated depth comes from, for the pictures' titles."""
    return f"depth from {Path(depth_dir).name}" if depth_dir is not None else f"model {Path(models).name}"


def _depth_on_drive(job: _DepthJob, frames: list[str] | None, first: int | None,
                    beams: int | None) -> tuple[str, _DepthFigures]:
    """What the input is, and the figures of every frame of a depth-completion drive."""
    drive_calib, used = _drive_input(job.data, beams)
    beams_used = beams if drive_calib is not None else None
    ids = first_frames(frames or drive_frame_ids(job.data), first)
    figures = _DepthFigures()
    for fid in tqdm(ids, desc="depth", unit="frame", disable=not job.progress):
        dc_frame = read_frame(job.data, fid, drive_calib, beams_used)
        crop_gt = _crop_ground_truth(dc_frame.ground_truth, job.preset)
        prediction = _drive_prediction(job, fid, dc_frame, crop_gt.shape)
        figures.per_frame[fid] = depth_metrics(prediction, crop_gt, _given_pixels(prediction, job.depth_dir))
        job.picture(fid, dc_frame.image, prediction, crop_gt)
    return used, figures


def _drive_input(data: Path, beams: int | None) -> tuple[Calibration | None, str]:
    """The drive's calibration (None without one, or with beams 0: velodyne_raw as given) and what the input
    is; a warning when the scan cannot be thinned exactly."""
    drive_calib = drive_calibration(data) if beams else None
    if drive_calib is None:
        used = "velodyne_raw as given (projected 64-line scan)"
        if beams:  # the paper's figures, and the model's training, are on 16 lines
            log.warning("--data %s: no calib_cam_to_cam.txt and calib_velo_to_cam.txt in it or above it, "
                        "so velodyne_raw goes in with all 64 lines, not thinned to %d as the model was trained "
                        "and the paper measured: put the drive's calibration files there to thin it", data, beams)
    elif has_raw_scans(data):
        used = f"{beams}-line, the raw scans (velodyne_points/) thinned in scan order and matched to velodyne_raw"
    else:
        used = f"{beams}-line emulated on velodyne_raw by each pixel's elevation (approximate)"
        # Measured on the shared KITTI scans: a third of the kept pixels are on other rings (pipeline/beams.py).
        log.warning("--data %s: no velodyne_points/ with the drive's raw scans, so each pixel's beam is read "
                    "from its elevation: the %d-line input has the density of %d lines but not their whole "
                    "lines (about two kept pixels in three on the right rings); link the raw drive's "
                    "velodyne_points/data there for an exact thinning", data, beams, beams)
    return drive_calib, used


def _drive_prediction(job: _DepthJob, fid: str, dc_frame: DepthCompletionFrame,
                      crop_hw: tuple[int, int]) -> np.ndarray:
    """The drive frame's depth on the crop: the network's from its image and sparse map, or the given map's."""
    if job.depth_dir is None:
        with in_frame(f"{job.data}, frame {fid}"):
            rgb, sparse_view = view_from_depth_png(dc_frame.image, dc_frame.sparse, job.preset)
            return _to_crop_resolution(job.detector.run_depth_net(rgb, sparse_view), crop_hw)
    given = read_image_depth_png(job.depth_dir / f"{fid}.png", dc_frame.image.shape[:2])
    return _crop_ground_truth(given, job.preset)


def _depth_on_object_folder(job: _DepthJob, frames: list[str] | None, first: int | None,
                            beams: int | None) -> tuple[str, _DepthFigures]:
    """What the input is, and the figures of every frame of an object folder with ``depth_2/`` (and, with
    ``label_2/``, of its moderate cars)."""
    used = f"{beams}-line emulated scan" if beams else "scan as stored"
    ids = first_frames(frames or frame_ids(job.data), first)
    if beams:  # a 16-line sensor's scans cannot be thinned: one line saying --emulate-beams 0, up front
        check_thinnable(job.data, ids, beams)
    labelled = (job.data / "label_2").is_dir()
    figures = _DepthFigures()
    for fid in tqdm(ids, desc="depth", unit="frame", disable=not job.progress):
        frame = load_frame(job.data, fid, with_labels=labelled)
        with in_frame(f"{job.data}, frame {fid}"):
            points = emulate_beams(frame.points, beams) if beams else frame.points
        gt = read_image_depth_png(job.data / "depth_2" / f"{fid}.png", frame.image_hw)
        crop_gt = _crop_ground_truth(gt, job.preset)
        prediction, view_depth, view_calib = _object_prediction(job, fid, frame, points, crop_gt.shape)
        figures.per_frame[fid] = depth_metrics(prediction, crop_gt, _given_pixels(prediction, job.depth_dir))
        if labelled:
            errors, on_car, stray = _car_figures(frame, job.preset, prediction, crop_gt, gt, view_depth, view_calib)
            figures.car_errors.extend(errors)
            figures.car_in_box.extend(on_car)
            figures.car_stray.extend(stray)
        job.picture(fid, frame.image, prediction, crop_gt)
    return used, figures


def _object_prediction(job: _DepthJob, fid: str, frame: Frame, points: np.ndarray,
                       crop_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, Calibration]:
    """The frame's depth on the crop, and the depth net's view of it with that view's calibration (what the
    pipeline's points come from): the network's from the image and scan, or the given map's."""
    if job.depth_dir is None:
        with in_frame(f"{job.data}, frame {fid}"):
            view_depth, view_calib = job.detector.dense_depth(frame.image, points, frame.calib)
        return _to_crop_resolution(view_depth, crop_hw), view_depth, view_calib
    # The pipeline's view of a given map, as `detect --depth-dir` makes it.
    given = read_image_depth_png(job.depth_dir / f"{fid}.png", frame.image_hw)
    view_depth = depth_view(given, job.preset)
    view_calib = view_calibration(frame.image_hw, frame.calib, job.preset)
    return _crop_ground_truth(given, job.preset), view_depth, view_calib


def _car_figures(frame: Frame, preset: Preset, prediction: np.ndarray, crop_gt: np.ndarray, gt: np.ndarray,
                 view_depth: np.ndarray, view_calib: Calibration
                 ) -> tuple[list[tuple[float, float]], list[tuple[float, float]], list[tuple[float, float]]]:
    """The frame's moderate cars: (z, median |error| mm) on the crop, and (z, share) of their pixels landing in
    their BEV box and of the other pixels of their 2D box landing there too, in the depth net's view."""
    cars = moderate_cars_in_view(frame.labels, frame.image_hw, preset.crop_hw)
    errors = car_depth_errors(prediction, crop_gt, [(car.box, car.z) for car in cars])
    # Where the pipeline's points come from: the view's own map, the truth resized as the
    # pipeline resizes a given depth map (nearest: no blend across outlines).
    in_view = moderate_cars_in_view(frame.labels, frame.image_hw, preset.crop_hw, preset.depth.input_scale)
    view_truth = depth_view(gt, preset)
    on_car, stray = car_box_shares(view_depth, view_truth, in_view, view_calib)
    return errors, on_car, stray


def _given_pixels(prediction: np.ndarray, depth_dir: Path | None) -> np.ndarray | None:
    """The pixels a given map has a depth for (None for the network's maps, which cover every pixel)."""
    return None if depth_dir is None else prediction > 0
