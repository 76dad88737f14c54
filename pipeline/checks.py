"""Checks of what a caller hands the Detector in code: the image, the keyword options, an image size, and
whether the image fits its calibration. Each refusal is an InputError naming the argument; a file reader's
own checks (pipeline.kitti) come before these for inputs read from files. Then the warnings for a rig unlike the
training one, for a LiDAR failing at run time and for a camera and LiDAR captured apart in time (README, "Your
own vehicle" and "Sensor faults").
"""

from __future__ import annotations

import numbers
from enum import Enum
from typing import Any, NamedTuple

import numpy as np

from pipeline.beams import BEAM_COUNTS
from pipeline.calib import Calibration, affine_rows
from pipeline.errors import InputError


class WarningCode(str, Enum):
    """The stable, machine-readable name of each warning (``Detections.warning_codes``, the service's
    ``warning_codes`` and its ``lowres3d_frame_warnings_total{code}``): a warning's text carries the frame's
    figures and may be reworded, its code does not change. A str, so it compares and serialises as its value.

    Not enum.StrEnum, which is Python 3.11's: the Jetson image runs JetPack 6's Python 3.10."""

    def __str__(self) -> str:  # as StrEnum: the value, not "WarningCode.NAME" (also in f-strings, below)
        return self.value

    def __format__(self, format_spec: str) -> str:  # the value, as StrEnum formats it (Enum's own varies by Python)
        return str.__format__(self, format_spec)

    # A frame's (Detector.detect, the service's and the CLI's reading of the scan).
    CALIBRATION_MISFIT = "calibration_misfit"
    BEAMS_EMULATED = "beams_emulated"
    LINE_COUNT = "line_count"
    OUT_OF_RANGE = "out_of_range"
    THIN_SCAN = "thin_scan"
    BLOCKED_SECTOR = "blocked_sector"
    STUCK_RANGE = "stuck_range"
    BEAM_PATTERN = "beam_pattern"
    ROAD_LEVEL = "road_level"
    REFLECTANCE_SCALE = "reflectance_scale"
    CAMERA_VIEW = "camera_view"
    NONFINITE_DROPPED = "nonfinite_dropped"
    SENSOR_SKEW = "sensor_skew"
    # Loading a model directory's (Detector.load_warnings, the service's /v1/model).
    UNTRAINED_WEIGHTS = "untrained_weights"
    PROVIDER_FALLBACK = "provider_fallback"
    INT8_SATURATION = "int8_saturation"
    FP16_ON_CPU = "fp16_on_cpu"


# What each code means, for people (the service's schema and docs/service.md list them).
WARNING_MEANINGS: dict[WarningCode, str] = {
    WarningCode.CALIBRATION_MISFIT: "the calibration does not fit the frame: P2's principal point lies outside the "
    "middle half of the image (a resized or cropped image, or another camera's calibration), or (almost) none of "
    "the scan's returns ahead project into the image (Tr_velo_to_cam in another frame, direction or unit)",
    WarningCode.BEAMS_EMULATED: "the scan was thinned to fewer lines as asked (emulate_beams); not a fault",
    WarningCode.LINE_COUNT: "the scan's point count does not fit the line count the model was trained on",
    WarningCode.OUT_OF_RANGE: "almost no point lies in the detection range: points in another unit or frame",
    WarningCode.THIN_SCAN: "far fewer returns in the detection range than the training rig's: a dirty or wet "
    "window, fog, spray, lost packets (sensor fault)",
    WarningCode.BLOCKED_SECTOR: "a sector of azimuths ahead has no returns: a blocked or dirty window, lost "
    "packets (sensor fault)",
    WarningCode.STUCK_RANGE: "most returns lie at one range: a stuck or failing LiDAR (sensor fault; the boxes "
    "mean nothing)",
    WarningCode.BEAM_PATTERN: "the beams' elevations are not the training rig's (a VLP-16, a tilted sensor)",
    WarningCode.ROAD_LEVEL: "the road ahead lies far from the training rig's road level (a vehicle frame, another "
    "mounting height)",
    WarningCode.REFLECTANCE_SCALE: "the scan's reflectance is on another scale than the training scans'",
    WarningCode.CAMERA_VIEW: "the depth net's crop of the image lies below the cars ahead",
    WarningCode.NONFINITE_DROPPED: "scan rows with NaN or infinite values were dropped",
    WarningCode.SENSOR_SKEW: "the image and the scan were captured far apart in time (their stamps): on a moving "
    "vehicle the image shows the world from elsewhere, and moving cars elsewhere again",
    WarningCode.UNTRAINED_WEIGHTS: "a network was exported without trained weights: its outputs mean nothing",
    WarningCode.PROVIDER_FALLBACK: "the best execution provider offered did not load; the networks run on the next",
    WarningCode.INT8_SATURATION: "full-range INT8 weights on a CPU whose int8 kernels can saturate",
    WarningCode.FP16_ON_CPU: "FP16 networks run on the CPU provider, slower than FP32 there",
}
# The codes a frame can carry (the metric's label values), and those of loading a model directory.
LOAD_WARNING_CODES = (WarningCode.UNTRAINED_WEIGHTS, WarningCode.PROVIDER_FALLBACK, WarningCode.INT8_SATURATION,
                      WarningCode.FP16_ON_CPU)
FRAME_WARNING_CODES = tuple(code for code in WarningCode if code not in LOAD_WARNING_CODES)


class CodedWarning(NamedTuple):
    """A warning with its code, as the Detector's checks pair them."""

    code: WarningCode
    message: str


def coded(*found: tuple[WarningCode, str | None]) -> list[CodedWarning]:
    """The warnings among ``(code, message or None)`` pairs, in order (a check's None: nothing to say)."""
    return [CodedWarning(code, message) for code, message in found if message]


# P2's principal point lies near the middle of the image it describes (KITTI: (600–610, 170–190) in 1224–1242 ×
# 370–376); outside the middle half, the image is most likely resized or cropped after calibrating, or the
# calibration another camera's, and the scan projects into the wrong pixels.
PRINCIPAL_POINT_SPAN = (0.25, 0.75)


def image_hw_of(image_hw: object) -> tuple[int, int]:
    """(rows, columns) from an image size or shape (its first two values), else an InputError naming ``image_hw``."""
    try:
        size: tuple[Any, ...] = tuple(image_hw)  # type: ignore[arg-type]  # TypeError: not a sequence
    except TypeError:
        size = ()
    if len(size) not in (2, 3) or not all(not isinstance(v, bool) and isinstance(v, numbers.Integral) and int(v) > 0
                                          for v in size):
        raise InputError(f"image_hw: expected (rows, columns) or an image's shape (rows, columns, 3), got {image_hw!r}")
    return int(size[0]), int(size[1])


def image_hints(image: np.ndarray) -> list[str]:
    """How to turn a refused image into uint8 RGB, where that can be said (an error path: it may scan the pixels)."""
    hints = []
    if image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 1):
        hints.append("one channel (grayscale), but the depth net reads colour")
    elif image.ndim == 3 and image.shape[2] == 4:
        hints.append("4 channels: drop the alpha channel, image[..., :3] (cv2.COLOR_BGRA2RGB for OpenCV's BGRA)")
    elif image.ndim != 3:
        hints.append(f"a {image.ndim}-D array, not an image's (H, W, 3)")
    if image.dtype == np.uint16:
        hints.append("16-bit: scale it to 8 bits, (image // 257).astype(np.uint8) for the full 0–65535 range "
                     "(image >> 4 for 12-bit data)")
    elif image.dtype.kind == "f":
        finite = image[np.isfinite(image)]
        if finite.size == 0:
            hints.append("no finite pixel value")
        elif finite.max() <= 1.0 and finite.min() >= 0.0:
            hints.append("values 0–1: convert with (image * 255).round().astype(np.uint8)")
        else:
            hints.append("floats: convert 0–255 values with image.clip(0, 255).round().astype(np.uint8)")
    elif image.dtype.kind in "iu" and image.dtype != np.uint8:
        hints.append("convert 0–255 values with image.astype(np.uint8)")
    return hints


def check_image(image: object) -> np.ndarray:
    """``image`` if it is the uint8 RGB (H, W, 3) array the depth net reads, else an InputError naming ``image``,
    what it is and, where it can be said, how to convert it (ONNX Runtime and OpenCV would fail on it with
    their own errors, or a float or 16-bit image would run on wrong pixel values)."""
    if isinstance(image, np.ndarray) and image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3:
        return image  # the usual frame: nothing else looked at
    try:
        array = np.asarray(image)
    except (TypeError, ValueError):  # ragged nested lists
        raise InputError(f"image: expected a uint8 RGB (H, W, 3) array, got a {type(image).__name__} of "
                         "rows of different lengths") from None
    if array.dtype == np.uint8 and array.ndim == 3 and array.shape[2] == 3:
        return array
    hints = "".join(f"; {hint}" for hint in image_hints(array)) if array.dtype.kind in "biuf" else ""
    raise InputError(f"image: expected uint8 RGB (H, W, 3), got {array.dtype} {array.shape}{hints}")


def check_options(score_threshold: object, emulate_to_beams: object) -> None:
    """InputError naming ``score_threshold`` (None or a probability in [0, 1], as the CLI's) or
    ``emulate_to_beams`` (None or 0: the scan as given, else one of BEAM_COUNTS)."""
    if score_threshold is not None and not (
        isinstance(score_threshold, numbers.Real) and not isinstance(score_threshold, bool)
        and 0.0 <= float(score_threshold) <= 1.0  # NaN fails too
    ):
        raise InputError(f"score_threshold: a probability in [0, 1] (None: the model's default), got {score_threshold!r}")
    if emulate_to_beams is not None and not (
        isinstance(emulate_to_beams, numbers.Integral) and not isinstance(emulate_to_beams, bool)
        and emulate_to_beams in (0, *BEAM_COUNTS)
    ):
        raise InputError(f"emulate_to_beams: one of {', '.join(map(str, BEAM_COUNTS))} lines (None or 0: the scan as given), "
                         f"got {emulate_to_beams!r}")


def calibration_mismatch(image_hw: tuple[int, int], calib: Calibration) -> str | None:
    """A warning when P2's principal point lies outside the middle half of the image (PRINCIPAL_POINT_SPAN)."""
    height, width = image_hw
    cx, cy = float(calib.P2[0, 2]), float(calib.P2[1, 2])
    low, high = PRINCIPAL_POINT_SPAN
    if low * width <= cx <= high * width and low * height <= cy <= high * height:
        return None
    return (f"image and calib: P2's principal point ({cx:.1f}, {cy:.1f}) lies outside the middle half of the "
            f"{width}×{height} image (x {low * width:g}…{high * width:g}, y {low * height:g}…{high * height:g}): "
            "is the image resized or cropped, or the calibration another camera's? The scan would project into "
            "the wrong pixels")


# The share of the scan's returns ahead (x beyond AHEAD_M; every SCAN_VIEW_SAMPLE-th point) that project into the
# image: 53.8–76.4 % on the five KITTI frames of tests/data (64 lines, and thinned to 16), 52.7–73.0 % on four
# synthetic ones (python -m simulation --frames 4 --seed 5), 67 % for 000006 framed by a 1920×1080 camera, 71 % for
# the Detector's warm-up road, 100 % for a forward-only sensor (a scan of the points the camera sees alone). A
# LiDAR→camera transform into the camera's body frame (x forward, z up) instead of its optical frame, its inverse
# (camera→LiDAR: a tf lookup the wrong way round) or one with its translation in millimetres gave 0–1.0 % on the
# same scans, and changed the boxes without a word (000006: 3 → 4, a car lost and two made up). The inverse still
# puts 9 % of a whole scan into the image, returns beside the car: hence the returns ahead, where a camera looks.
AHEAD_M = 5.0  # metres; nearer returns are mostly the vehicle's own body and the ground below the camera's view
SCAN_VIEW_SAMPLE = 8
FEWEST_IN_IMAGE_SHARE = 0.1  # 5× below the lowest correct scan's share, 10× above the highest wrong transform's
FEWEST_AHEAD = 50  # sampled returns ahead below which the scan says nothing of the calibration


def scan_misses_image(points: np.ndarray, calib: Calibration, image_hw: tuple[int, int]) -> str | None:
    """A warning when (almost) none of the scan's returns ahead of the LiDAR project into the image: the
    LiDAR→camera transform is in another frame, direction or unit, and the depth net gets no sparse depth (or
    another scene's) and the pseudo points land elsewhere. Every SCAN_VIEW_SAMPLE-th point (about 40 µs for a
    16-line scan)."""
    # Homogeneous pixels: a return lies in the image when u/d and v/d do, d > 0. Every sampled point is projected
    # and the count taken over those ahead: cheaper than picking them out first.
    sample = points[::SCAN_VIEW_SAMPLE]
    u, v, depth = affine_rows(calib.velo_to_pixels_f32, sample[:, :3].T)
    ahead = sample[:, 0] > AHEAD_M
    count = int(np.count_nonzero(ahead))
    if count < FEWEST_AHEAD:
        return None
    height, width = image_hw
    inside = (ahead & (depth > 0.1) & (u >= -0.5 * depth) & (u < (width - 0.5) * depth)
              & (v >= -0.5 * depth) & (v < (height - 0.5) * depth))
    share = float(np.count_nonzero(inside)) / count
    if share >= FEWEST_IN_IMAGE_SHARE:
        return None
    return (f"calib: {share:.1%} of the scan's returns ahead project into the image, where a camera looking forward "
            f"sees half or more of them: is Tr_velo_to_cam the LiDAR → camera transform (not camera → LiDAR), into "
            "the camera's optical frame (x right, y down, z forward; not the camera body's x forward, z up), in "
            "metres? The depth net gets no LiDAR depth and the boxes change (README, 'In your own code')")


# --------------------------------------------------------------------------- a rig unlike the training one
# The models learned on 16-line scans made of every 4th ring of KITTI's HDL-64E (+2° … −24.9°) and their
# 64-line originals. Measured on the scans at hand (returns beyond 3 m, every 8th): 14–33 % lie below −17° on
# the five real KITTI frames and 1,300 synthetic ones, with 16 lines or 64; none of their returns' 99th
# percentile reaches +4°. A VLP-16 (±15°) has no beam below −15° and 7 above +1°.
LOW_BEAM_DEG, HIGH_BEAM_DEG = -17.0, 4.0
FEWEST_LOW_BEAM_SHARE = 0.05  # of the returns below LOW_BEAM_DEG (training scans: 0.14 and more)
MOST_HIGH_BEAM_SHARE = 0.05  # of the returns above HIGH_BEAM_DEG (training scans: under 0.01)
# The road's height in the LiDAR frame, read as the 25th percentile of the returns' z in a strip 3–12 m ahead
# (|y| < 3 m): -1.74 … -1.67 m on the KITTI frames (a LiDAR 1.73 m above the road), -2.04 … -1.54 m on
# the 300 synthetic validation scenes, whose sensor height and pitch vary as the training scenes' do.
ROAD_STRIP = (3.0, 12.0, 3.0)  # x from, x to, |y| under (metres)
ROAD_QUANTILE = 25
ROAD_LEVEL_SLACK = 0.45  # metres from the preset's ground_z beyond which the road is not where training had it
FEWEST_ROAD_RETURNS = 30


def beam_pattern_mismatch(points: np.ndarray) -> str | None:
    """A warning when a scan's beams do not span the elevations the models were trained on: none of its returns
    low (below LOW_BEAM_DEG) or many high (above HIGH_BEAM_DEG), as a VLP-16's ±15° gives. Every 8th point
    is enough for shares of a few per cent (about 85 µs for a 16-line scan)."""
    sample = points[::8, :3]
    horizontal = np.hypot(sample[:, 0], sample[:, 1])
    far = horizontal > 3.0  # the vehicle's own body and the sensor's blind zone say nothing of the beams
    if np.count_nonzero(far) < 100:
        return None
    elevation = np.degrees(np.arctan2(sample[far, 2], horizontal[far]))
    low = float(np.mean(elevation < LOW_BEAM_DEG))
    high = float(np.mean(elevation > HIGH_BEAM_DEG))
    if low >= FEWEST_LOW_BEAM_SHARE and high <= MOST_HIGH_BEAM_SHARE:
        return None
    return (f"points: the scan's beams are not those the models were trained on (every 4th ring of KITTI's "
            "HDL-64E, +2° … −24.9°: 14 % or more of the returns below −17°, none above +4°); a VLP-16's ±15° or "
            "a tilted sensor gives lines the networks never saw, and fewer or worse boxes: compare on your own "
            "labelled frames (benchmarks/accuracy.py) or retrain on your sensor's pattern (README, 'Your own "
            f"vehicle') ({low:.0%} below, {high:.0%} above)")


def road_level_mismatch(points: np.ndarray, ground_z: float) -> str | None:
    """A warning when the road in front lies far from ``ground_z`` (the preset's road level in the LiDAR frame):
    points in a vehicle frame (z = 0 on the road) or a sensor mounted much higher or lower than in training
    fill other height slices of the BEV than the networks learned, and lose most cars without an error.
    (A road 0.45 m off lost a sixth of the cars' AP on 80 synthetic frames, one at z = 0 three quarters.)"""
    x_from, x_to, half_width = ROAD_STRIP
    # Every 4th point: a 16-line scan still has a few hundred returns in the strip (about 50 µs, not 240).
    sample = points[::4]
    centre, half_length = (x_from + x_to) / 2, (x_to - x_from) / 2
    ahead = sample[(np.abs(sample[:, 0] - centre) < half_length) & (np.abs(sample[:, 1]) < half_width), 2]
    if ahead.size < FEWEST_ROAD_RETURNS:
        return None
    rank = ahead.size * ROAD_QUANTILE // 100  # np.partition: a tenth of np.percentile's 0.1 ms of overhead
    road = float(np.partition(ahead, rank)[rank])
    if abs(road - ground_z) <= ROAD_LEVEL_SLACK:
        return None
    return (f"points: the road ahead lies far from where the models were trained to find it in the velodyne frame, "
            f"at about {ground_z:g} m (a LiDAR {-ground_z:g} m above the road); are the points in a vehicle "
            "frame, or the sensor mounted higher or lower? Shift the points' z and Tr_velo_to_cam by the "
            f"difference (README, 'Your own vehicle') (road at {road:.2f} m)")


def view_mismatch(image_hw: tuple[int, int], view_calib: Calibration, view_hw: tuple[int, int], ground_z: float,
                  car_height: float, max_depth: float) -> str | None:
    """A warning when the depth net's view (its crop of the image) misses cars ahead within the pseudo points'
    reach (``max_depth``): the middle of a car straight ahead projects above the view's top row from some
    distance on. KITTI's crop holds the horizon about 150 rows below its top; the bottom 352 rows of a
    1080-row image often lie wholly below it, and then only the road near the car gets pseudo points."""
    distances = np.arange(2.0, max_depth + 1.0, 1.0)
    middles = np.column_stack([distances, np.zeros_like(distances), np.full_like(distances, ground_z + car_height / 2)])
    uv, depth = view_calib.velo_to_image(middles)
    above = (uv[:, 1] < 0) & (depth > 0)
    if not above.any():
        return None
    start = float(distances[np.argmax(above)])
    height, width = image_hw
    return (f"image: the depth net sees the bottom {view_hw[0]} rows, centre {view_hw[1]} columns of this "
            f"{width}×{height} image (its training crop), which lies below the cars ahead from some distance on: "
            f"they get no pseudo points (the model's reach is {max_depth:g} m) and the camera adds little; crop or "
            "resize the image (and P2 with it) so the horizon lies in the crop's upper half as in KITTI "
            f"(README, 'Your own vehicle') (cars beyond {start:.0f} m unseen)")


# PIXOR reads the mean reflectance of each BEV cell as a channel of its own: the training scans' mean
# reflectance lies in 0.14–0.28 (300 + 1,000 synthetic scenes and the five KITTI frames, 16 lines or 64).
# The same 80 synthetic frames with reflectance 0 lost 14 points of BEV AP at IoU 0.7 moderate (85.5 → 71.7).
REFLECTANCE_MEAN_RANGE = (0.07, 0.5)  # half the lowest training scan's, about twice the highest


def reflectance_mismatch(points: np.ndarray) -> str | None:
    """A warning when a scan's mean reflectance (every 8th point's) lies far from the training scans': a sensor
    whose intensities, even divided to [0, 1], are on another scale than KITTI's calibrated reflectance."""
    mean = float(points[::8, 3].mean())
    low, high = REFLECTANCE_MEAN_RANGE
    if low <= mean <= high:
        return None
    return (f"points: the scan's reflectance is on another scale than the training scans' (mean 0.14–0.28 on KITTI's "
            "0–1 reflectance): PIXOR reads it as a BEV channel, and cars are lost without an error; rescale your "
            f"sensor's intensities so their mean over a scan lies near 0.2 (README, 'Your own vehicle') (mean {mean:.3f})")


# A scan whose float32 values are read in the other byte order than written (a big-endian exporter's file read as
# KITTI's little-endian .bin): mostly reflectance far outside [0, 1] and coordinates of 1e30 m, which the Detector
# refuses. Read the other way round, a real scan is plausible again: finite, reflectance in [0, 1], every
# coordinate within this many metres (KITTI's scans reach about 120 m).
BYTE_SWAP_MAX_RANGE_M = 1000.0


def byte_order_hint(points: np.ndarray) -> str:
    """For a scan refused for its values: a hint when its float32 rows, byte-swapped, are a plausible scan (the
    file's floats are big-endian); "" otherwise. Only called on the refusal's path, so its copy costs a frame
    nothing."""
    if points.dtype != np.float32 or points.size == 0:
        return ""
    with np.errstate(invalid="ignore", over="ignore"):
        swapped = points.byteswap()
        if not np.isfinite(swapped).all():
            return ""
        reflectance, extent = swapped[:, 3], float(np.abs(swapped[:, :3]).max())
        plausible = reflectance.min() >= 0.0 and reflectance.max() <= 1.0 and 0.0 < extent <= BYTE_SWAP_MAX_RANGE_M
    if not plausible:
        return ""
    return ("the file's floats look big-endian: read in the other byte order they are a plausible scan; convert "
            "it with np.fromfile(path, '>f4').astype('<f4').reshape(-1, 4)")


# --------------------------------------------------------------------------- a sensor failing at run time
# Faults of a working rig (README, "Sensor faults"), measured on the first 80 synthetic validation frames (BEV AP
# at IoU 0.7 moderate: 85.5 with the camera, 83.7 LiDAR-only) with each fault applied to their 16-line scans. Only
# the LiDAR's faults change the boxes much: a black, white, frozen, mirrored or half-covered image cost at most
# 1.2 AP (the camera model falls back to about the LiDAR's own), Tr_velo_to_cam turned by up to 5° 1.3 (the scan
# projects into wrong pixels and its depths come back out through the same calibration), rain-like returns
# within 4 m 1.8, duplicated points nothing. These checks are for the faults that cost more.

# Returns in the front half (x > 0, the detection range's azimuths) per 1° of azimuth, every 4th point: the
# fuller of any two neighbouring degrees holds 0.45 or more of the median degree's on the five KITTI frames and
# 300 synthetic ones (16 lines; the median degree 15 returns or more), as the lower beams reach the ground all
# round. A window blocked over 5° ahead lost 12 AP, over 10° 25; its degrees hold nothing. Two degrees under a
# tenth of the median catch every 3° block at random azimuths on 51 of those scans.
SECTOR_SAMPLE = 4
SECTOR_DEG = 1
SECTOR_RUN = 2  # neighbouring degrees, all nearly empty
FEWEST_SECTOR_SHARE = 0.1  # of the median degree's returns
FEWEST_SECTOR_MEDIAN = 8  # returns in the median degree below which the scan is too thin to tell (thin_scan_fault)
# The share of returns within STUCK_BAND of the median range (every 16th point, whose share is off by 0.02 at
# most): 0.03–0.14 on the same clean scans; a sensor that reports one range (or all zeros) for every beam puts
# them all there and gives no box at all.
STUCK_SAMPLE = 16
STUCK_BAND = 0.25  # metres either side of the median range
MOST_AT_ONE_RANGE = 0.5
# Returns in the BEV grid per line of the scans a model learned on: 10,942–15,981 for 16 lines (684–999 a line)
# on the same clean scans. Random returns dropped (a dirty window, fog, spray, lost packets) cost, for the
# camera model and the LiDAR's: 70 % kept 1.5 and 3.7 AP, 50 % kept 4.8 and 9.3, 30 % 13 and 16, 10 % 46 and 44.
THINNEST_IN_GRID_PER_LINE = 680  # of the clean scans, rounded down
FEWEST_IN_GRID_PER_LINE = 450  # 7,200 for 16 lines: 1.5× below the thinnest clean scan, about half a scan's


def blocked_sector_fault(points: np.ndarray) -> str | None:
    """A warning when a sector of the azimuths ahead has (almost) no returns: SECTOR_RUN neighbouring degrees
    with under FEWEST_SECTOR_SHARE of the median degree's (every SECTOR_SAMPLE-th point; about 55 µs)."""
    sample = points[::SECTOR_SAMPLE]
    x = sample[:, 0]
    front = x > 0.0
    azimuth = np.arctan2(sample[front, 1], x[front])  # (−π/2, π/2): left is positive
    degrees = 180 // SECTOR_DEG
    bins = np.minimum(((np.degrees(azimuth) + 90.0) / SECTOR_DEG).astype(np.intp), degrees - 1)
    counts = np.bincount(bins, minlength=degrees)
    median = float(np.partition(counts, degrees // 2)[degrees // 2])
    if median < FEWEST_SECTOR_MEDIAN:
        return None
    empty = counts < FEWEST_SECTOR_SHARE * median
    if not (empty[:-1] & empty[1:]).any():  # the usual frame: no two neighbouring degrees empty
        return None
    edges = np.flatnonzero(np.diff(np.concatenate([[0], empty.astype(np.int8), [0]])))
    starts, ends = edges[::2], edges[1::2]
    runs = ends - starts >= SECTOR_RUN
    widest = int(np.argmax(np.where(runs, ends - starts, 0)))
    left, right = (int(starts[widest]) * SECTOR_DEG - 90, int(ends[widest]) * SECTOR_DEG - 90)
    blocked = int(((ends - starts) * runs).sum()) * SECTOR_DEG
    return (f"points: no returns from azimuth {left}° to {right}° (0° straight ahead, left positive), where the "
            "lower beams always reach the ground: a blocked or dirty sensor window, or lost packets? Cars in that "
            f"sector are not detected ({blocked}° empty in all, a degree's median {median * SECTOR_SAMPLE:.0f} returns)")


def stuck_range_fault(points: np.ndarray) -> str | None:
    """A warning when most returns lie at one range from the sensor (every STUCK_SAMPLE-th point): a sensor
    reporting a constant or zero range, whose scan has no road, no beams and no cars to find (about 20 µs)."""
    sample = points[::STUCK_SAMPLE]
    x, y, z = sample[:, 0], sample[:, 1], sample[:, 2]
    squared = x * x + y * y + z * z  # squared ranges against a squared band: no square root per point
    middle = squared.size // 2
    median = float(np.sqrt(np.partition(squared, middle)[middle]))
    low, high = max(median - STUCK_BAND, 0.0) ** 2, (median + STUCK_BAND) ** 2
    share = float(np.count_nonzero((squared >= low) & (squared < high))) / squared.size
    if share <= MOST_AT_ONE_RANGE:
        return None
    return (f"points: {share:.0%} of the returns lie at one range, {median:.1f} m from the sensor (a scan has 14 % "
            "at most there): a stuck or failing LiDAR, or a driver sending placeholder points; the frame's boxes "
            "mean nothing")


def thin_scan_fault(in_grid: int, lines: int | None) -> str | None:
    """A warning when far fewer returns lie in the BEV grid than a scan of ``lines`` lines puts there
    (FEWEST_IN_GRID_PER_LINE each; the voxelizer's count, so free): returns lost at random."""
    if lines is None or in_grid >= FEWEST_IN_GRID_PER_LINE * lines:
        return None
    return (f"points: only {in_grid} returns lie in the detection range, where a {lines}-line scan of the training "
            f"rig puts {THINNEST_IN_GRID_PER_LINE * lines:,} or more: a dirty or wet window, fog, spray, lost packets, or a "
            f"sensor with fewer lines? Cars are missed (half the returns lost cost 5–9 AP) "
            f"(fewer than {FEWEST_IN_GRID_PER_LINE * lines:,})")


# --------------------------------------------------------------------------- sensors not synchronised
# A capture time ("stamp") is an integer count of nanoseconds on a clock both sensors share: since the Unix
# epoch for ROS (sec * 1_000_000_000 + nanosec, exact) and Python's time.time_ns(), or any other common clock.
# Integers, not float seconds: a client matches answers to its frames by the stamps echoed back, which
# must compare equal. KITTI triggers the camera as the LiDAR sweeps past its view; an unsynchronised rig pairs
# frames itself, and at 20 m/s a 50 ms gap moves the world 1 m between the image and the scan.
# Measured (the first 80 synthetic val frames, weights/edge, BEV AP at IoU 0.7 moderate 85.5): the
# camera placed 0.2, 0.4, 1 m ahead of the scan's pose, 1 m behind, and 2 m ahead gave 85.8, 85.3, 86.2, 85.9,
# 84.7: the boxes follow the scan's geometry, and the depth net's pseudo points come back out through the same
# calibration. Not measured: cars that move themselves, which the image shows elsewhere than the scan does.
# What a skew does move is everything drawn in the image: format=kitti's 2D boxes and camera.png.
STAMP_NS_MAX = 2**63 - 1  # int64: ROS's time and the JSON schema's format
# 0.4 m at 20 m/s (72 km/h), a fifth of a 10 Hz LiDAR's sweep: a rig that triggers its camera from the LiDAR, as
# KITTI's, stays within a few milliseconds, a 30 Hz camera paired by nearest stamp within 17 ms; a free-running
# 10 Hz one paired so is up to 50 ms off.
MAX_SENSOR_SKEW_MS = 20.0
# Stamps further apart than this are not one frame's: two clocks (one since boot, one since the epoch) or units.
UNRELATED_SKEW_S = 1.0


STAMP_FORMS = "(from ROS: sec * 1000000000 + nanosec; from seconds: round(seconds * 1e9); Python: time.time_ns())"


def stamp_problem(stamp: object) -> str | None:
    """What is wrong with ``stamp`` as a capture time in integer nanoseconds (0 … int64's largest); None: nothing.
    A float, seconds most likely, is refused rather than rounded: one representation, compared exactly."""
    if isinstance(stamp, numbers.Integral) and not isinstance(stamp, bool):
        if int(stamp) < 0:
            return (f"{stamp} is negative; a capture time counts nanoseconds since the epoch (or on another clock "
                    "both sensors share), 0 or later")
        if int(stamp) > STAMP_NS_MAX:
            return f"{stamp} is more than int64 holds ({STAMP_NS_MAX}): nanoseconds, not a finer unit?"
        return None
    if isinstance(stamp, numbers.Real) and not isinstance(stamp, bool):
        return f"expected an integer count of nanoseconds, got {stamp!r} {STAMP_FORMS}"
    shown = repr(stamp[:40]) if isinstance(stamp, str) else f"a {type(stamp).__name__}"
    return f"expected an integer count of nanoseconds, got {shown} {STAMP_FORMS}"


def check_stamp(stamp: object, name: str) -> int:
    """``stamp`` as an int if it is a capture time in integer nanoseconds, else an InputError naming ``name``."""
    problem = stamp_problem(stamp)
    if problem is not None:
        raise InputError(f"{name}: {problem}")
    return int(stamp)  # type: ignore[call-overload]  # an Integral: stamp_problem said so


def sensor_skew(image_stamp_ns: int, points_stamp_ns: int, max_skew_ms: float = MAX_SENSOR_SKEW_MS) -> str | None:
    """A warning when the image and the scan were captured more than ``max_skew_ms`` apart (stamps as
    :func:`check_stamp` accepts them): on a moving vehicle the image shows the world from elsewhere than the
    scan, the cars that move elsewhere again, and what is drawn in the image is off by the motion."""
    skew_ns = image_stamp_ns - points_stamp_ns  # Python ints: exact
    if abs(skew_ns) <= max_skew_ms * 1e6:
        return None
    skew_ms = skew_ns / 1e6
    order = "after" if skew_ns > 0 else "before"
    if abs(skew_ns) > UNRELATED_SKEW_S * 1e9:
        return (f"image and points: the image's stamp is {abs(skew_ms) / 1e3:,.3f} s {order} the scan's: not one "
                "frame's capture times. Are they on two clocks (one since boot, one since the epoch) or in "
                f"different units (both nanoseconds)? ({skew_ms:+.1f} ms)")
    return (f"image and points: the image was captured {abs(skew_ms):.1f} ms {order} the scan (more than "
            f"{max_skew_ms:g} ms apart): on a moving vehicle it shows the world from elsewhere (1 m at 20 m/s in "
            "50 ms) and moving cars elsewhere again; the boxes are the scan's, at its time, and boxes drawn in the "
            "image are off by the motion. Pair each scan with the image nearest the moment it swept the camera's "
            f"view (README, 'Your own vehicle') ({skew_ms:+.1f} ms)")
