"""Uploaded frame parts → validated arrays, or an error that names the part.

Two steps. :func:`check_upload` runs on the event loop before the frame's job is
handed to the inference pool (its place there was taken before its upload was
read, service.middleware.AdmissionMiddleware), so a request that can never succeed
is answered 4xx at once, not after a wait for a worker: it looks at sizes and
headers (empty or missing parts, a scan size that is not a multiple of 16 bytes,
too many points, an image that is not PNG/JPEG, has too many pixels or is
smaller than the crop, all read from its header before any decoding, a PNG
cut off before its end, a JPEG of more scans than any camera writes) and parses
the calibration (a few lines of text), and the capture times sent with the frame
(:func:`stamp_query`, :func:`stamp_warnings`).
:func:`decode_frame` does the real decoding on an inference worker: a fault
found only there (a corrupt image body, a PNG whose image data inflates past its
size, a scan without finite points) is answered 422 once the frame has a place,
503 like any frame while the queue is full.

The image checks bound what decoding one upload can cost, as the pixel limit bounds its memory: the
decoders' time grows with a JPEG's scans and with a PNG's compressed data, not only with its pixels
(:func:`_check_jpeg_scans`, :func:`png_for_decoding`).
"""

from __future__ import annotations

import re
import struct
import zlib
from dataclasses import dataclass, field

import numpy as np
from pydantic_core import PydanticCustomError

from pipeline.calib import SMALL_IMAGE_HINT, Calibration
from pipeline.checks import (
    STAMP_NS_MAX,
    CodedWarning,
    WarningCode,
    byte_order_hint,
    coded,
    sensor_skew,
    stamp_problem,
)
from pipeline.errors import InputError
from pipeline.kitti import (
    _CALIB_NUMBER,
    JPEG_SCAN,
    PNG_SIGNATURE,
    POINT_BYTES,
    check_image_end,
    check_scan_kind,
    decode_image,
    image_header_hw,
    parse_calib,
    parse_velodyne,
    wider_rows_hint,
)
from service.errors import ServiceError
from service.schemas import NonFinitePolicy

JPEG_SIGNATURE = b"\xff\xd8\xff"
# A KITTI calib.txt is about 1 kB (a raw drive's cam_to_cam about 5 kB). The calibration is parsed on the
# event loop, so its size is bounded: a 30 MB "calibration" would hold every other request up.
MAX_CALIB_BYTES = 64 * 1024
# Each scan of a progressive JPEG is a pass over every block of the image, and an almost empty one takes 12 bytes:
# a crafted JPEG of a million scans held a worker for tens of seconds past any deadline (libjpeg-turbo's
# LJT-01-003; decoding cannot be interrupted). Cameras write 1 scan (baseline), progressive encoders about 10.
MAX_JPEG_SCANS = 100
# The chunks whose bytes make a PNG's pixels; OpenCV ignores the others (text, colour profiles, animation frames).
PNG_PIXEL_CHUNKS = frozenset({b"IHDR", b"PLTE", b"tRNS", b"IDAT", b"IEND"})
# A large PNG has a few thousand IDAT chunks; the walk over them is Python, so their number is bounded.
MAX_PNG_CHUNKS = 100_000
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # colour type → samples per pixel
_ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))
_INFLATE_STEP = 1 << 16  # bytes inflated at a time while counting a PNG's image data
PNG_IEND_CHUNK = b"\x00\x00\x00\x00IEND\xaeB`\x82"  # length 0, type, CRC


@dataclass(frozen=True)
class FrameUpload:
    """The raw parts of one request: image bytes (None: not sent), scan bytes, calibration bytes (None: not
    sent; the server's default, if any, is used)."""

    image: bytes | None
    points: bytes
    calib: bytes | None


@dataclass(frozen=True)
class FrameStamps:
    """The capture times sent with a frame (integer nanoseconds on a clock both sensors share; None: not sent)."""

    image_ns: int | None = None
    points_ns: int | None = None

    @property
    def sent(self) -> bool:
        return self.image_ns is not None or self.points_ns is not None

    @property
    def skew_ms(self) -> float | None:
        """image_ns - points_ns in milliseconds (positive: the image after the scan); None unless both were sent."""
        if self.image_ns is None or self.points_ns is None:
            return None
        return (self.image_ns - self.points_ns) / 1e6


_DECIMAL_INTEGER = re.compile(r"[+-]?[0-9]+")
_INT64_DIGITS = len(str(STAMP_NS_MAX))


def stamp_query(value: object) -> object:
    """A stamp query parameter's text → int, or a 422 saying what the stamp must be (pydantic names the parameter).

    Only decimal digits: ``int()`` would also take ``1_000`` and surrounding spaces, pydantic ``1.0``; a float
    (seconds most likely) or ``nan`` is refused with how to make nanoseconds of it, as for the Python API."""
    if not isinstance(value, str):
        return value  # from code, not a query: pydantic's own checks
    number: object = value
    if _DECIMAL_INTEGER.fullmatch(value):
        digits = value.lstrip("+-").lstrip("0")
        if len(digits) > _INT64_DIGITS:  # int() of thousands of digits is slow, then refused
            raise PydanticCustomError("stamp_ns", f"{len(digits)} digits is more than int64 holds: nanoseconds, not a "
                                      "finer unit?")
        # Without the leading zeros: int() refuses a string of over 4,300 characters, zeros and all, with a
        # message about sys.set_int_max_str_digits.
        number = -int(digits or "0") if value.startswith("-") else int(digits or "0")
    # A decimal number as a calibration's are read: said as a float (seconds most likely); not '1_000' or ' 5'.
    elif _CALIB_NUMBER.fullmatch(value):
        number = float(value)
    problem = stamp_problem(number)
    if problem is not None:
        raise PydanticCustomError("stamp_ns", problem.replace("{", "{{").replace("}", "}}"))
    return number


def check_stamps(stamps: FrameStamps, upload: FrameUpload) -> None:
    """InputError for an image stamp without an image: the client pairs its frames itself, and one without its
    image is not the frame it thinks it sent."""
    if stamps.image_ns is not None and upload.image is None:
        raise InputError("image_stamp_ns: sent without an image part; send the image it stamps, or leave the stamp out")


def stamp_warnings(stamps: FrameStamps, max_skew_ms: float, camera_use: str | None) -> list[CodedWarning]:
    """The ``sensor_skew`` warning when both stamps were sent, the image is used (``camera_use``: why, as
    :func:`check_upload` takes it; None: the scan alone answers) and they lie more than ``max_skew_ms`` apart."""
    if stamps.image_ns is None or stamps.points_ns is None or camera_use is None:
        return []
    return coded((WarningCode.SENSOR_SKEW, sensor_skew(stamps.image_ns, stamps.points_ns, max_skew_ms)))


@dataclass
class DecodedFrame:
    """A frame ready for the Detector: uint8 RGB (H, W, 3), float32 (N, 4) finite points, calibration; image and
    calibration None when a LiDAR-only model answers from the scan alone."""

    image: np.ndarray | None
    points: np.ndarray
    calib: Calibration | None
    warnings: list[str] = field(default_factory=list)
    warning_codes: list[str] = field(default_factory=list)  # parallel to warnings (pipeline.checks.WarningCode)

    @property
    def image_hw(self) -> tuple[int, int] | None:
        return None if self.image is None else (int(self.image.shape[0]), int(self.image.shape[1]))


def upload_image_hw(data: bytes) -> tuple[int, int]:
    """(height, width), as :func:`pipeline.kitti.image_header_hw`, from a PNG or JPEG header without decoding;
    415 for other formats."""
    if not data:
        raise InputError("image: the part is empty (0 bytes)")
    if not data.startswith((PNG_SIGNATURE, JPEG_SIGNATURE)):
        raise ServiceError(415, "unsupported_media_type", "image: expected a PNG or JPEG image")
    # The readers' header walk: a PNG's IHDR with its CRC checked, a JPEG's segments in a bounded number of steps.
    hw = image_header_hw(data, "image")
    if hw is None:  # a PNG always has its IHDR (or was refused): a JPEG without a frame header before its scan
        raise InputError("image: corrupt JPEG (no frame header)")
    height, width = hw
    if width == 0 or height == 0:
        raise InputError(f"image: the header says {width}×{height} pixels")
    return height, width


def _check_image(data: bytes, max_image_pixels: int, crop_hw: tuple[int, int] | None) -> None:
    """The image checks that need no decoding: format, pixel count and crop from the header, a PNG's or JPEG's end."""
    height, width = upload_image_hw(data)
    if width * height > max_image_pixels:
        raise InputError(f"image: {width}×{height} pixels is more than the limit of {max_image_pixels} pixels")
    if crop_hw is not None and (height < crop_hw[0] or width < crop_hw[1]):
        crop_h, crop_w = crop_hw
        raise InputError(f"image: {width}×{height} pixels is smaller than the model's {crop_w}×{crop_h} crop"
                         f"{SMALL_IMAGE_HINT}")
    check_image_end(data, "image")  # as decode_image checks it, here before the queue
    if data.startswith(JPEG_SIGNATURE):
        _check_jpeg_scans(data)


def _check_jpeg_scans(data: bytes) -> None:
    """InputError for a JPEG of more than :data:`MAX_JPEG_SCANS` scans. Counting the start-of-scan markers misses
    none, as entropy-coded data never holds the bytes FF DA (an FF there is followed by 00 or a restart marker);
    metadata may add a few (an EXIF thumbnail's own scans), far from the limit."""
    scans = data.count(JPEG_SCAN)
    if scans > MAX_JPEG_SCANS:
        raise InputError(f"image: a JPEG of {scans} scans is more than the limit of {MAX_JPEG_SCANS} (a camera's "
                         "JPEG has 1, a progressive one about 10)")


def _png_image_bytes(ihdr: bytes) -> int:
    """The bytes a PNG's image data inflates to, from its IHDR fields: each row (of each Adam7 pass when
    interlaced) a filter byte and its packed samples. An unknown colour type (the header check refuses it
    before this) counts 4 samples."""
    width, height, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", ihdr)
    bits = _PNG_CHANNELS.get(colour, 4) * depth
    passes = _ADAM7 if interlace else ((0, 0, 1, 1),)
    total = 0
    for x0, y0, dx, dy in passes:
        columns, rows = (width - x0 + dx - 1) // dx, (height - y0 + dy - 1) // dy
        if columns > 0 and rows > 0:
            total += rows * (1 + (columns * bits + 7) // 8)
    return total


def _inflate_at_most(parts: list[memoryview], limit: int) -> bytes:
    """The zlib stream split over ``parts``, inflated; InputError when it inflates to more than ``limit`` bytes
    (found a step past ``limit`` at most, so the cost is bounded by the image's own size) or is not zlib."""
    inflater = zlib.decompressobj()
    pieces: list[bytes] = []
    total = 0
    try:
        for part in parts:
            # In slices: the input a step leaves is copied (unconsumed_tail), so it is kept small.
            for start in range(0, len(part), _INFLATE_STEP):
                rest: bytes | memoryview = part[start : start + _INFLATE_STEP]
                while rest and not inflater.eof:
                    pieces.append(inflater.decompress(rest, _INFLATE_STEP))
                    total += len(pieces[-1])
                    if total > limit:
                        raise InputError("image: the PNG's image data inflates to more than its header's size "
                                         "(a decompression bomb?)")
                    rest = inflater.unconsumed_tail
        pieces.append(inflater.flush())  # what a last step left in zlib (input exhausted: little)
    except zlib.error as exc:
        raise InputError(f"image: not a readable PNG image (its image data: {exc})") from None
    if total + len(pieces[-1]) > limit:
        raise InputError("image: the PNG's image data inflates to more than its header's size (a decompression bomb?)")
    return b"".join(pieces)


def _stored_idat_chunk(raw: bytes) -> list[bytes | memoryview]:
    """An IDAT chunk (length, type, data, CRC: as pieces to join) holding ``raw`` as a zlib stream of stored
    blocks: inflating it is a copy, so the decoder does not inflate the image data a second time."""
    view, step = memoryview(raw), 0xFFFF  # a stored block holds at most 65,535 bytes
    data: list[bytes | memoryview] = [b"\x78\x01"]  # zlib header: deflate, 32 kB window, no dictionary
    for start in range(0, max(len(raw), 1), step):
        block = view[start : start + step]
        last = start + step >= len(raw)
        data += [struct.pack("<BHH", last, len(block), len(block) ^ 0xFFFF), block]
    data.append(struct.pack(">I", zlib.adler32(raw)))
    crc = zlib.crc32(b"IDAT")
    for piece in data:
        crc = zlib.crc32(piece, crc)
    return [struct.pack(">I", sum(len(piece) for piece in data)), b"IDAT", *data, struct.pack(">I", crc)]


def png_for_decoding(data: bytes) -> bytes:
    """The PNG ``data`` with only the chunks that make its pixels (:data:`PNG_PIXEL_CHUNKS`); InputError for one
    whose image data inflates to more than its IHDR's size, or that is not a sequence of chunks up to IEND.

    libpng inflates every byte of IDAT data, also what comes after the last row (a megabyte of zlib holds a
    gigabyte of zeros: seconds of a worker, which decoding cannot be stopped in), and inflates the compressed
    ancillary chunks (zTXt, iTXt, iCCP) too. It also writes a line to stderr, past the service's log filters,
    for every ancillary chunk it finds fault with: thousands of tiny bad chunks made as many log lines from one
    upload. OpenCV's pixels do not depend on those chunks, so they are dropped here. Bytes after IEND are ignored,
    as decoders do. The image data, inflated here to count it, goes to the decoder in stored (uncompressed)
    blocks, so it is inflated once: a KITTI image's decoding took 9.4 ms as sent, 10.7 ms with this (an
    inflation only to count took 6.7 ms more).
    """
    if data[12:16] != b"IHDR" or int.from_bytes(data[8:12], "big") != 13:
        raise InputError("image: corrupt PNG (no IHDR header)")
    view = memoryview(data)
    kept: list[bytes | memoryview] = [view[:8]]  # the signature, IHDR and PLTE / tRNS: the chunks before the data
    idat: list[memoryview] = []
    transparency = False
    pos = len(PNG_SIGNATURE)
    for _ in range(MAX_PNG_CHUNKS):
        if pos + 12 > len(data):
            raise InputError("image: not a readable PNG image (it ends inside a chunk, before IEND)")
        length = int.from_bytes(data[pos : pos + 4], "big")
        kind = data[pos + 4 : pos + 8]
        end = pos + 12 + length
        if end > len(data):
            raise InputError(f"image: not a readable PNG image (a chunk of {length} bytes runs past its end)")
        if kind == b"IDAT":
            idat.append(view[pos + 8 : end - 4])
        elif kind in PNG_PIXEL_CHUNKS:
            # tRNS once, before the image data: libpng warns of each duplicate or misplaced one, as of others.
            if kind != b"IEND" and not (kind == b"tRNS" and (transparency or idat)):
                kept.append(view[pos:end])
            transparency = transparency or kind == b"tRNS"
        elif not kind[0] & 0x20:  # a critical chunk (upper-case first letter) no decoder may skip
            raise InputError(f"image: not a readable PNG image (unknown critical chunk "
                             f"{kind.decode('ascii', 'backslashreplace')!r})")
        pos = end
        if kind == b"IEND":
            break
    else:
        raise InputError(f"image: a PNG of more than {MAX_PNG_CHUNKS} chunks is more than any encoder writes")
    raw = _inflate_at_most(idat, _png_image_bytes(data[16:29]))
    return b"".join([*kept, *_stored_idat_chunk(raw), PNG_IEND_CHUNK])


def _check_points(data: bytes, max_points: int) -> None:
    """The scan's byte size: not empty, whole 16-byte points, at most ``max_points`` of them."""
    if not data:
        raise InputError("points: the scan is empty (0 bytes)")
    check_scan_kind(data, "points")  # an image or archive sent as the scan, named before its size is
    if len(data) % POINT_BYTES:
        raise InputError(
            f"points: size {len(data)} bytes is not a multiple of {POINT_BYTES} "
            f"(a KITTI scan is float32 rows x, y, z, reflectance){wider_rows_hint(len(data))}"
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


def decode_points(data: bytes, policy: NonFinitePolicy) -> tuple[np.ndarray, list[CodedWarning]]:
    """Scan bytes → finite float32 (N, 4) points and warnings with their codes; rows with NaN/Inf dropped or
    rejected."""
    scan = parse_velodyne(data, "points")
    warnings: list[CodedWarning] = []
    if scan.dropped_nonfinite:
        if policy is NonFinitePolicy.reject:
            # A big-endian scan read as KITTI's little-endian floats has such rows too: say so rather than
            # suggest dropping them (the rest would be refused for their values next).
            swapped = byte_order_hint(np.frombuffer(data, "<f4").reshape(-1, 4))
            raise InputError(
                f"points: {scan.dropped_nonfinite} rows have NaN or infinite values "
                + (f"({swapped})" if swapped else "(nonfinite=reject; send nonfinite=drop to have them dropped)")
            )
        warnings.append(CodedWarning(WarningCode.NONFINITE_DROPPED,
                                     f"points: dropped {scan.dropped_nonfinite} rows with NaN or infinite values"))
    if scan.points.shape[0] == 0:
        raise InputError("points: the scan has no finite points")
    return scan.points, warnings


def decode_frame(upload: FrameUpload, calib: Calibration | None, policy: NonFinitePolicy) -> DecodedFrame:
    """Decode the scan and the image, if sent (on a worker thread: PNG/JPEG decoding is the costly step).

    calib: what :func:`check_upload` returned."""
    points, warnings = decode_points(upload.points, policy)
    image = None
    if upload.image is not None:
        data = png_for_decoding(upload.image) if upload.image.startswith(PNG_SIGNATURE) else upload.image
        image = decode_image(data, "image")
    return DecodedFrame(image=image, points=points, calib=calib, warnings=[w.message for w in warnings],
                        warning_codes=[w.code for w in warnings])
