"""Checks of what a caller hands the Detector in code: the image, the keyword options, an image size, and
whether the image fits its calibration. Each refusal is an InputError naming the argument; a file reader's
own checks (pipeline.kitti) come before these for inputs read from files.
"""

from __future__ import annotations

import numbers

import numpy as np

from pipeline.beams import BEAM_COUNTS
from pipeline.calib import Calibration
from pipeline.errors import InputError

# P2's principal point lies near the middle of the image it describes (KITTI: (600–610, 170–190) in 1224–1242 ×
# 370–376); outside the middle half, the image is most likely resized or cropped after calibrating, or the
# calibration another camera's, and the scan projects into the wrong pixels.
PRINCIPAL_POINT_SPAN = (0.25, 0.75)


def image_hw_of(image_hw: object) -> tuple[int, int]:
    """(rows, columns) from an image size or shape (its first two values), else an InputError naming ``image_hw``."""
    try:
        size = tuple(image_hw)  # type: ignore[arg-type]
    except TypeError:
        size = ()
    if len(size) not in (2, 3) or not all(isinstance(v, numbers.Integral) and not isinstance(v, bool) and v > 0
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
        and 0.0 <= score_threshold <= 1.0  # NaN fails too
    ):
        raise InputError(f"score_threshold: a probability in [0, 1] (None: the model's default), got {score_threshold!r}")
    if emulate_to_beams is not None and not (
        isinstance(emulate_to_beams, numbers.Integral) and not isinstance(emulate_to_beams, bool)
        and emulate_to_beams in (0, *BEAM_COUNTS)
    ):
        raise InputError(f"emulate_to_beams: one of {', '.join(map(str, BEAM_COUNTS))} lines (None: the scan as given), "
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
