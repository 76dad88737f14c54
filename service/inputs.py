"""Uploaded frame parts → validated arrays, or an error that names the part.

Two steps. :func:`check_upload` runs on the event loop before the frame takes a
place in the inference queue, so a request that can never succeed is answered
4xx even when the queue is full, never 503 "retry": it looks at sizes and
headers (empty or missing parts, a scan size that is not a multiple of 16 bytes,
too many points, an image that is not PNG/JPEG, has too many pixels or is
smaller than the crop, all read from its header before any decoding, and a PNG
cut off before its end) and parses the calibration (a few lines of text).
:func:`decode_frame` does the real decoding on an inference worker: a fault
found only there (a corrupt image body, a scan without finite points) is
answered 422 once the frame has a place, 503 like any frame while the queue is full.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

from pipeline.calib import SMALL_IMAGE_HINT, Calibration
from pipeline.errors import InputError
from pipeline.kitti import (
    PNG_SIGNATURE,
    POINT_BYTES,
    check_image_end,
    decode_image,
    parse_calib,
    parse_velodyne,
)
from service.errors import ServiceError
from service.schemas import NonFinitePolicy

JPEG_SIGNATURE = b"\xff\xd8\xff"
# JPEG start-of-frame markers (baseline, progressive, lossless, arithmetic); C4, C8, CC are not frames.
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_JPEG_NO_LENGTH = {0x01, *range(0xD0, 0xD9)}  # TEM, RST0-7, SOI
# A KITTI calib.txt is about 1 kB (a raw drive's cam_to_cam about 5 kB). The calibration is parsed on the
# event loop, so its size is bounded: a 30 MB "calibration" would hold every other request up.
MAX_CALIB_BYTES = 64 * 1024


@dataclass(frozen=True)
class FrameUpload:
    """The raw parts of one request: image bytes (None: not sent), scan bytes, calibration bytes (None: not
    sent; the server's default, if any, is used)."""

    image: bytes | None
    points: bytes
    calib: bytes | None


@dataclass
class DecodedFrame:
    """A frame ready for the Detector: uint8 RGB (H, W, 3), float32 (N, 4) finite points, calibration; image and
    calibration None when a LiDAR-only model answers from the scan alone."""

    image: np.ndarray | None
    points: np.ndarray
    calib: Calibration | None
    warnings: list[str] = field(default_factory=list)

    @property
    def image_hw(self) -> tuple[int, int] | None:
        return None if self.image is None else (int(self.image.shape[0]), int(self.image.shape[1]))


def _png_size(data: bytes) -> tuple[int, int]:
    if len(data) < 24 or data[12:16] != b"IHDR":
        raise InputError("image: corrupt PNG (no IHDR header)")
    width, height = struct.unpack(">II", data[16:24])
    return width, height


def _jpeg_size(data: bytes) -> tuple[int, int]:
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            break
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in _JPEG_NO_LENGTH:
            i += 2
            continue
        (length,) = struct.unpack(">H", data[i + 2 : i + 4])
        if marker in _JPEG_SOF:
            if i + 9 > len(data):
                break
            height, width = struct.unpack(">HH", data[i + 5 : i + 9])
            return width, height
        if marker == 0xDA or length < 2:  # start of scan before a frame header, or a broken segment
            break
        i += 2 + length
    raise InputError("image: corrupt JPEG (no frame header)")


def image_size(data: bytes) -> tuple[int, int]:
    """(width, height) from a PNG or JPEG header without decoding; 415 for other formats."""
    if not data:
        raise InputError("image: the part is empty (0 bytes)")
    if data.startswith(PNG_SIGNATURE):
        width, height = _png_size(data)
    elif data.startswith(JPEG_SIGNATURE):
        width, height = _jpeg_size(data)
    else:
        raise ServiceError(415, "unsupported_media_type", "image: expected a PNG or JPEG image")
    if width == 0 or height == 0:
        raise InputError(f"image: the header says {width}×{height} pixels")
    return width, height


def _check_image(data: bytes, max_image_pixels: int, crop_hw: tuple[int, int] | None) -> None:
    """The image checks that need no decoding: format, pixel count and crop from the header, a PNG's or JPEG's end."""
    width, height = image_size(data)
    if width * height > max_image_pixels:
        raise InputError(f"image: {width}×{height} pixels is more than the limit of {max_image_pixels} pixels")
    if crop_hw is not None and (height < crop_hw[0] or width < crop_hw[1]):
        crop_h, crop_w = crop_hw
        raise InputError(f"image: {width}×{height} pixels is smaller than the model's {crop_w}×{crop_h} crop"
                         f"{SMALL_IMAGE_HINT}")
    check_image_end(data, "image")  # as decode_image checks it, here before the queue


def _check_points(data: bytes, max_points: int) -> None:
    """The scan's byte size: not empty, whole 16-byte points, at most ``max_points`` of them."""
    if not data:
        raise InputError("points: the scan is empty (0 bytes)")
    if len(data) % POINT_BYTES:
        raise InputError(
            f"points: size {len(data)} bytes is not a multiple of {POINT_BYTES} "
            "(a KITTI scan is float32 rows x, y, z, reflectance)"
        )
    count = len(data) // POINT_BYTES
    if count > max_points:
        raise InputError(f"points: {count} points is more than the limit of {max_points}")


def check_upload(
    upload: FrameUpload, max_points: int, max_image_pixels: int, crop_hw: tuple[int, int] | None,
    default_calib: Calibration | None, camera_use: str | None,
) -> Calibration | None:
    """The checks before a frame takes a place in the queue; raises InputError (422) or ServiceError (415).

    crop_hw: the smallest image (height, width) the depth net accepts; None for a LiDAR-only model.
    camera_use: why this request needs the camera image and a calibration (a camera model; the boxes the camera
    sees), named in the error when one is missing; None when the scan alone answers it (a LiDAR-only model).
    Returns the calibration to use: the uploaded one, else the server's default, else None.
    """
    if upload.image is not None:
        _check_image(upload.image, max_image_pixels, crop_hw)
    elif camera_use is not None:
        raise InputError(f"image: required ({camera_use})")
    _check_points(upload.points, max_points)
    if upload.calib is not None:
        return decode_calib(upload.calib)
    if camera_use is not None and default_calib is None:
        raise InputError(f"calib: required ({camera_use}), and this server has no default calibration configured")
    return default_calib


def decode_calib(data: bytes) -> Calibration:
    """Uploaded KITTI calib text → Calibration; InputError naming ``calib`` for anything else.

    'utf-8-sig' drops a leading byte-order mark (Windows editors write one), as
    pipeline.kitti.read_calib does for files: it would stick to the first key, so
    a file with P2 first would read as missing P2.
    """
    if not data.strip():
        raise InputError("calib: the part is empty")
    if len(data) > MAX_CALIB_BYTES:
        raise InputError(f"calib: {len(data)} bytes is more than a KITTI calib.txt (about 1 kB) can be; "
                         f"at most {MAX_CALIB_BYTES} bytes are read")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise InputError("calib: not text (expected a KITTI calib.txt)") from None
    return parse_calib(text, "calib")


def decode_points(data: bytes, policy: NonFinitePolicy) -> tuple[np.ndarray, list[str]]:
    """Scan bytes → finite float32 (N, 4) points and warnings; rows with NaN/Inf dropped or rejected."""
    scan = parse_velodyne(data, "points")
    warnings: list[str] = []
    if scan.dropped_nonfinite:
        if policy is NonFinitePolicy.reject:
            raise InputError(
                f"points: {scan.dropped_nonfinite} rows have NaN or infinite values "
                "(nonfinite=reject; send nonfinite=drop to have them dropped)"
            )
        warnings.append(f"points: dropped {scan.dropped_nonfinite} rows with NaN or infinite values")
    if scan.points.shape[0] == 0:
        raise InputError("points: the scan has no finite points")
    return scan.points, warnings


def decode_frame(upload: FrameUpload, calib: Calibration | None, policy: NonFinitePolicy) -> DecodedFrame:
    """Decode the scan and the image, if sent (on a worker thread: PNG/JPEG decoding is the costly step).

    calib: what :func:`check_upload` returned."""
    points, warnings = decode_points(upload.points, policy)
    image = decode_image(upload.image, "image") if upload.image is not None else None
    return DecodedFrame(image=image, points=points, calib=calib, warnings=warnings)
