"""KITTI file formats: velodyne scans, object calibration, label_2 lines, depth PNGs.

The readers of what the service also receives have a twin that takes bytes or
text plus a ``source`` name (``parse_velodyne``, ``parse_calib``, ``parse_labels``,
``decode_image``, ``decode_depth_png``), so files on disk and HTTP uploads share
one validated code path. Errors
are :class:`~pipeline.errors.InputError` naming the source and the problem.
"""

from __future__ import annotations

import codecs
import math
import os
import re
import zlib
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline.calib import CALIBRATION_SHAPES, Calibration, check_calibration, homogeneous_block
from pipeline.errors import InputError

# The real KITTI frames a source checkout bundles (tests/data, CC BY-NC-SA 3.0): the demo's and check_models'
# default frame. An install from a wheel leaves them behind: each user checks the folder is there.
SAMPLE_DIR = Path(__file__).resolve().parents[1] / "tests" / "data" / "kitti" / "training"
POINT_BYTES = 16  # float32 x, y, z, reflectance
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"  # the first 8 bytes of every PNG file
JPEG_START, JPEG_SCAN, JPEG_END = b"\xff\xd8", b"\xff\xda", b"\xff\xd9"  # start of image, of a scan, end of image
IMAGE_TAIL_BYTES = 4096  # where check_image_file looks for an image's end
# The most pixels a camera image or depth map read from a file may have, by its header (an 8K frame has 33
# million): a corrupted size field would otherwise be taken at face value, and a 3 KB JPEG whose frame header
# says 30,000 × 30,000 decoded into 2.7 GB of grey in 14 s. (The service has its own, lower, --max-image-pixels.)
MAX_IMAGE_PIXELS = 1 << 26


# --------------------------------------------------------------------------- velodyne
@dataclass(frozen=True)
class Scan:
    """A LiDAR scan in the velodyne frame.

    points: float32 (N, 4) rows ``x, y, z, reflectance``, all finite, in file order
    (the order carries the ring structure that beam emulation relies on).
    dropped_nonfinite: rows removed because a value was NaN or infinite.
    source: where the scan came from (a file's path, or the upload's field name), for messages.
    """

    points: np.ndarray
    dropped_nonfinite: int = 0
    source: str = ""


# Printable ASCII and the whitespace of text lines: what no scan's first points are made of alone.
_TEXT_BYTES = bytes(range(0x20, 0x7F)) + b"\t\n\r"


def _looks_like_text(data: bytes) -> bool:
    """Whether a scan's first 64 bytes (4 points) are all text: an error page a download saved under the scan's
    name, or points written as text. A real scan's 16 float32 values all landing on printable bytes has a
    chance of about 1e-20 (each reflectance in [0, 1] has a byte 0x00 or above 0x7f in most values)."""
    head = bytes(data[:64])  # bytes of a bytearray or memoryview too: only bytes has translate's deletion
    return len(head) >= POINT_BYTES and not head.translate(None, _TEXT_BYTES)


# Files taken for scans by mistake, by their first bytes: read as float32 rows they fail a size or reflectance
# check whose hint (ring or time columns) sends the user the wrong way. Each signature read as a scan's first x
# is a value no LiDAR gives (PNG 52,817 m; a JPEG's start with an APPn, DQT, DHT or COM marker 2 km or more
# (not SOF0 or SOF2, which read as −8 and −128 m); a zip's or gzip's 1e-19 m or less; LAS 13,520 m), so a real
# scan is not taken for one of them.
NOT_SCAN_SIGNATURES: tuple[tuple[tuple[bytes, ...], str, str], ...] = (
    ((b"\x89PNG\r\n\x1a\n",), "a PNG image", " (a camera image or depth map given as the scan?)"),
    (tuple(b"\xff\xd8\xff" + bytes([m]) for m in (*range(0xE0, 0xF0), 0xDB, 0xC4, 0xFE)), "a JPEG image",
     " (a camera image given as the scan?)"),
    ((b"\x93NUMPY",), "a NumPy .npy file", ": np.load it, then write points.astype('<f4').tofile(path)"),
    ((b"PK\x03\x04",), "a zip archive", ": extract it first"),
    ((b"\x1f\x8b\x08",), "a gzip file", ": decompress it first"),
    ((b"LASF",), "a LAS point cloud", ": convert its x, y, z and intensity to float32 rows"),
)


def check_scan_kind(data: bytes, source: str) -> None:
    """InputError naming ``source`` for a file that is plainly no scan (an image, an archive, text …): read as
    floats it would fail a size or reflectance check whose hint hides what the file is."""
    head = bytes(data[:8])
    for signatures, what, hint in NOT_SCAN_SIGNATURES:
        if head.startswith(signatures):
            raise InputError(f"{source}: {what}, not a KITTI scan of float32 rows x, y, z, reflectance{hint}")
    if _looks_like_text(data):
        raise InputError(f"{source}: holds text ({bytes(data[:40]).decode('ascii')!r}…), not a scan's float32 rows: a "
                         "download that saved an error page, or a scan written as text?")


def parse_velodyne(data: bytes, source: str = "<points>") -> Scan:
    """Decode a KITTI velodyne ``.bin`` payload; drop and count non-finite rows."""
    check_scan_kind(data, source)
    if len(data) % POINT_BYTES != 0:
        raise InputError(
            f"{source}: size {len(data)} bytes is not a multiple of {POINT_BYTES} "
            f"(a KITTI scan is float32 rows x, y, z, reflectance){wider_rows_hint(len(data))}"
        )
    points = np.frombuffer(data, dtype="<f4").reshape(-1, 4)
    finite = np.isfinite(points)
    if finite.all():  # the usual scan: no row needs its own test
        return Scan(points=points.copy(), dropped_nonfinite=0, source=source)
    # A row's four flags read as one 32-bit word are all True exactly when the word is 0x01010101 (in
    # either byte order): 0.1 ms for a 64-line scan, where .all(axis=1) over rows of four took 2 ms.
    finite_rows = finite.view(np.uint32)[:, 0] == 0x01010101
    return Scan(points=points[finite_rows], dropped_nonfinite=int(points.shape[0] - np.count_nonzero(finite_rows)),
                source=source)


def wider_rows_hint(size: int) -> str:
    """For a scan of ``size`` bytes that KITTI's 4 columns do not fit: which 5- or 6-column rows would (a driver's
    ring and time columns), with the way to keep the first four; "" when neither fits."""
    columns = [n for n in (5, 6) if size % (4 * n) == 0]
    if not columns:
        return ""
    n = columns[0]
    return (f"; it is a whole number of {' or '.join(map(str, columns))}-column rows: a scan with a ring or time "
            f"column? Keep x, y, z and the intensity: np.fromfile(path, np.float32).reshape(-1, {n})[:, :4]")


def read_velodyne(path: str | Path) -> Scan:
    """Read a KITTI velodyne ``.bin`` file."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read velodyne scan ({exc.strerror})") from exc
    return parse_velodyne(data, str(path))


def write_velodyne(path: str | Path, points: np.ndarray) -> None:
    """Write (N, 4) points as a KITTI velodyne ``.bin`` (little-endian float32)."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 4:
        raise InputError(f"{path}: points must have shape (N, 4), got {points.shape}")
    Path(path).write_bytes(np.ascontiguousarray(points, dtype="<f4").tobytes())


# --------------------------------------------------------------------------- text files
UTF16_BOMS = (codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)  # what Windows PowerShell's `>` starts its files with


def read_text_file(path: str | Path, what: str, encoding: str = "ascii") -> str:
    """The text of a KITTI text file, ``what`` naming it in errors ("labels", "calibration", "split file").

    A UTF-8 byte-order mark, which Windows editors write, is dropped (it would stick to the first field); a
    UTF-16 file and a byte ``encoding`` cannot hold are InputErrors naming the file and the line, rather than
    the codec's "position 0" of the whole file."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read {what} ({exc.strerror or exc})") from exc
    if data.startswith(UTF16_BOMS):
        raise InputError(f"{path}: UTF-16 text (as Windows PowerShell's '>' writes it); save the {what} as "
                         f"{encoding.upper()} text")
    data = data.removeprefix(codecs.BOM_UTF8)
    try:
        return data.decode(encoding)
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise InputError(f"{path}, line {line}: byte 0x{data[exc.start]:02x} is not {encoding.upper()} text; save "
                         f"the {what} as {encoding.upper()}, as KITTI's own files are") from None


# --------------------------------------------------------------------------- calibration
# A number as KITTI's files (7.215377e+02) and other tools write it: ASCII digits, a sign, a point, an exponent;
# or NaN and infinity, named as non-finite below. Python's float() also reads "٧٢١", "７２１" and "7_2_1" as 721,
# which no other reader of the file would.
_CALIB_NUMBER = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|[+-]?(?:nan|inf|infinity)",
                           re.IGNORECASE)


def _calib_number(text: str) -> float:
    """One number of a calibration line; ValueError naming it unless it is an ASCII decimal number."""
    if not _CALIB_NUMBER.fullmatch(text):
        raise ValueError(f"{text[:30]!r}; expected ASCII decimal numbers such as 7.215377e+02")
    return float(text)


def _calib_values(text: str, source: object, shapes: dict[str, tuple[int, int]],
                  every_line_a_key: bool = True) -> dict[str, np.ndarray]:
    """The ``shapes`` keys of a calibration text's ``KEY: numbers`` lines, each checked with its line (numbers,
    their count, finite) and reshaped; a key given twice is refused, the other keys are skipped. A line without
    a colon is an error where ``every_line_a_key`` (object files), else skipped (raw files)."""
    values: dict[str, np.ndarray] = {}
    seen: dict[str, int] = {}  # key → the line it was first given on
    for line_no, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        key = key.strip()
        if not sep:
            if every_line_a_key:
                hint = _layout_hint({*seen, line.split()[0]}, shapes)
                raise InputError(f"{source}, line {line_no}: expected 'KEY: numbers', got {line[:60]!r}{hint}")
            continue
        if key in seen:
            _refuse_repeated_key(key, line_no, seen, source, _layout_hint(seen, shapes))
        seen[key] = line_no
        if key not in shapes:
            continue  # keys not needed: P0, P1, P3, Tr_imu_to_velo; the raw files' other cameras, calib_time …
        try:
            numbers = np.array([_calib_number(v) for v in rest.split()], dtype=np.float64)
        except ValueError as exc:
            raise InputError(f"{source}, line {line_no}: {key} has a non-numeric value ({exc})") from exc
        shape = shapes[key]
        if not np.isfinite(numbers).all():
            raise InputError(f"{source}, line {line_no}: {key} has a non-finite value")
        if numbers.size == 16 and key in HOMOGENEOUS_KEYS:
            values[key] = homogeneous_block(numbers.reshape(4, 4), shape, f"{source}, line {line_no}: {key}")
            continue
        if numbers.size != shape[0] * shape[1]:
            also = " (or 16: the 4×4 homogeneous form)" if key in HOMOGENEOUS_KEYS else ""
            raise InputError(
                f"{source}, line {line_no}: {key} needs {shape[0] * shape[1]} numbers{also}, got {numbers.size}"
            )
        values[key] = numbers.reshape(shape)
    missing = [k for k in shapes if k not in values]
    if missing:
        raise InputError(f"{source}: missing calibration key(s) {', '.join(missing)}{_layout_hint(seen, shapes)}")
    return values


RAW_CALIB_ADVICE = ("a raw drive's calib_cam_to_cam.txt and calib_velo_to_cam.txt make one calibration together "
                    "(P2 = P_rect_02, R0_rect = R_rect_00, Tr_velo_to_cam = [R | T]); the commands read a drive "
                    "with --drive")
# The keys that tell KITTI's calibration layouts apart, each with what to do with a file of it where another
# layout is read: a raw drive's calib_cam_to_cam.txt copied into an object folder's calib/ is otherwise only
# "missing P2, R0_rect, Tr_velo_to_cam".
CALIB_LAYOUTS = (
    (("P2", "R0_rect", "Tr_velo_to_cam"), "a KITTI object calib/ID.txt (P2, R0_rect, Tr_velo_to_cam)",
     "an object folder's frames are read with --data"),
    (("P_rect_02", "R_rect_00"), "KITTI raw's calib_cam_to_cam.txt (P_rect_02, R_rect_00)", RAW_CALIB_ADVICE),
    (("R", "T"), "KITTI raw's calib_velo_to_cam.txt (R, T)", RAW_CALIB_ADVICE),
    (("R_rect", "Tr_velo_cam"), "a KITTI tracking calib (R_rect, Tr_velo_cam, without colons)",
     "write them as the object layout's 'R0_rect:' and 'Tr_velo_to_cam:'"),
)


def _layout_hint(keys: Iterable[str], shapes: dict[str, tuple[int, int]]) -> str:
    """For an error in a calibration file: '; the file is <its layout>, not <the one read>: <what to do>' when
    ``keys`` (those read so far) are another KITTI layout's than ``shapes``'; "" otherwise. Error paths only."""
    keys = set(keys)
    wanted, raw_wanted = next(((desc, advice == RAW_CALIB_ADVICE) for names, desc, advice in CALIB_LAYOUTS
                               if set(names) <= set(shapes)), ("", False))
    for names, desc, advice in CALIB_LAYOUTS:
        if desc != wanted and keys & (set(names) - set(shapes)):  # P2 alone is no sign: tracking files have it
            if advice == RAW_CALIB_ADVICE and raw_wanted:  # one raw file where the other is read: a drive's pair
                return (f"; the file is {desc}: are the drive's calib_cam_to_cam.txt and calib_velo_to_cam.txt "
                        "swapped or misnamed?")
            return f"; the file is {desc}, not {wanted}: {advice}"
    return ""


# Calibration tools other than KITTI's often write the rigid transforms as 4×4 homogeneous matrices.
HOMOGENEOUS_KEYS = ("R0_rect", "Tr_velo_to_cam")


def parse_calib(text: str, source: str = "<calib>") -> Calibration:
    """Parse a KITTI object ``calib/*.txt`` (keys P2, R0_rect, Tr_velo_to_cam are required; others are skipped).

    R0_rect and Tr_velo_to_cam may also be given as 4×4 homogeneous matrices (16 numbers, last row 0 0 0 1)."""
    values = _calib_values(text, source, CALIBRATION_SHAPES)
    return check_calibration(Calibration(P2=values["P2"], R0_rect=values["R0_rect"],
                                         Tr_velo_to_cam=values["Tr_velo_to_cam"]), source)


def _refuse_repeated_key(key: str, line_no: int, seen: dict[str, int], source: object, hint: str = "") -> None:
    """Refuse ``key`` given again on ``line_no`` (``seen``: where each key was first given): which of the two
    values is meant cannot be known, and taking either silently projects every point with a matrix the file
    may not mean. ``hint``: the file's layout, when it is not the one read (two raw files joined into one)."""
    raise InputError(f"{source}, line {line_no}: {key} given twice (first on line {seen[key]}){hint}")


def _calib_text(path: Path) -> str:
    """A calibration file's text (its byte-order mark dropped); UTF-8, not ASCII, as the raw files'
    ``calib_time`` may be written in another locale's month names."""
    return read_text_file(path, "calibration", "utf-8")


def read_calib(path: str | Path) -> Calibration:
    """Read a KITTI object calibration file."""
    path = Path(path)
    return parse_calib(_calib_text(path), str(path))


# What a drive's calibration needs of each raw file: key → shape.
_CAM_TO_CAM_KEYS = {"P_rect_02": (3, 4), "R_rect_00": (3, 3)}  # calib_cam_to_cam.txt: the left colour camera
_VELO_TO_CAM_KEYS = {"R": (3, 3), "T": (3, 1)}  # calib_velo_to_cam.txt: the LiDAR's rotation and translation


def read_raw_calib(cam_to_cam: str | Path, velo_to_cam: str | Path) -> Calibration:
    """Calibration from KITTI raw-data files (``calib_cam_to_cam.txt``, ``calib_velo_to_cam.txt``),
    as the raw drives and the depth-completion drives need: P2 = P_rect_02, R0_rect = R_rect_00,
    Tr_velo_to_cam = [R | T]."""
    cam_to_cam, velo_to_cam = Path(cam_to_cam), Path(velo_to_cam)
    cam = _calib_values(_calib_text(cam_to_cam), cam_to_cam, _CAM_TO_CAM_KEYS, every_line_a_key=False)
    velo = _calib_values(_calib_text(velo_to_cam), velo_to_cam, _VELO_TO_CAM_KEYS, every_line_a_key=False)
    return check_calibration(Calibration(P2=cam["P_rect_02"], R0_rect=cam["R_rect_00"],
                                         Tr_velo_to_cam=np.hstack([velo["R"], velo["T"]])),
                             f"{cam_to_cam} and {velo_to_cam}")


def format_calib(calib: Calibration) -> str:
    """KITTI calib text for ``calib``: P0/P1/P3 written as copies of P2 and Tr_imu_to_velo as the identity, so
    that other tools find every key (one camera, no IMU: placeholders, not a stereo rig)."""

    def row(name: str, m: np.ndarray) -> str:
        return f"{name}: " + " ".join(f"{v:.12e}" for v in np.asarray(m, dtype=np.float64).ravel())

    return "\n".join(
        [
            row("P0", calib.P2), row("P1", calib.P2), row("P2", calib.P2), row("P3", calib.P2),
            row("R0_rect", calib.R0_rect), row("Tr_velo_to_cam", calib.Tr_velo_to_cam),
            row("Tr_imu_to_velo", np.hstack([np.eye(3), np.zeros((3, 1))])),
        ]
    ) + "\n"


def write_calib(path: str | Path, calib: Calibration) -> None:
    """Write a KITTI object calibration file."""
    Path(path).write_text(format_calib(calib), encoding="ascii")


# --------------------------------------------------------------------------- labels
@dataclass
class Object3D:
    """One KITTI ``label_2`` line (15 fields, or 16 with a score in result files).

    bbox: 2D box (left, top, right, bottom) in image pixels.
    dimensions: h, w, l in metres. location: x, y, z of the bottom centre in the
    rectified camera frame. rotation_y: yaw around the camera's y axis.
    """

    type: str
    truncated: float
    occluded: int
    alpha: float
    bbox: tuple[float, float, float, float]
    dimensions: tuple[float, float, float]
    location: tuple[float, float, float]
    rotation_y: float
    score: float | None = None


# The fields of a label_2 line after the type, as the KITTI devkit's readme names them (16th: a result's score).
LABEL_FIELDS = ("truncated", "occluded", "alpha", "bbox left", "bbox top", "bbox right", "bbox bottom",
                "height", "width", "length", "x", "y", "z", "rotation_y", "score")


def _label_number(text: str, position: int, source: str, line_no: int) -> float:
    """Field ``position`` (1-based, the type is field 1) of a label line as a finite float, or an InputError naming it."""
    where = f"{source}, line {line_no}, field {position} ({LABEL_FIELDS[position - 2]})"
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"{where}: {text[:30]!r} is not a number") from None
    if not math.isfinite(value):
        raise InputError(f"{where}: {text!r} is not finite")
    return value


def _tracking_hint(fields: list[str]) -> str:
    """For a line of the wrong length: the hint that it is a KITTI tracking label, whose lines start with the
    frame number and track id (-1 for DontCare) before the object's 15 or 16 fields; "" otherwise."""
    if len(fields) in (17, 18) and fields[0].isdigit() and fields[1].lstrip("-").isdigit():
        return (f" (a KITTI tracking label line? Frame {fields[0]}, track {fields[1]} come before the type "
                f"{fields[2]!r}: the object layout keeps the fields from the type on, one file per frame)")
    return ""


def parse_labels(text: str, source: str = "<labels>", needs_score: bool = False) -> list[Object3D]:
    """Parse KITTI label lines; 15 fields (ground truth) or 16 (result with score).

    needs_score: every line must have the 16th field (result files, which the evaluation ranks by score).
    """
    objects: list[Object3D] = []
    for line_no, line in enumerate(text.splitlines(), start=1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) not in (15, 16):
            raise InputError(
                f"{source}, line {line_no}: expected 15 fields (16 with a score), got {len(fields)}"
                f"{_tracking_hint(fields)}"
            )
        if needs_score and len(fields) == 15:
            raise InputError(f"{source}, line {line_no}: {fields[0]} has 15 fields; a result line needs a 16th, the score")
        v = [_label_number(x, position, source, line_no) for position, x in enumerate(fields[1:], start=2)]
        objects.append(
            Object3D(
                type=fields[0], truncated=v[0], occluded=int(v[1]), alpha=v[2],
                bbox=(v[3], v[4], v[5], v[6]), dimensions=(v[7], v[8], v[9]),
                location=(v[10], v[11], v[12]), rotation_y=v[13],
                score=v[14] if len(v) == 15 else None,
            )
        )
    return objects


RESULT_DECIMALS = 4  # of a result line's alpha, size, location and rotation (format_label)


def read_labels(path: str | Path, needs_score: bool = False) -> list[Object3D]:
    """Read a KITTI ``label_2`` (or result) file; needs_score as :func:`parse_labels`."""
    path = Path(path)
    text = read_text_file(path, "labels")
    return parse_labels(text, str(path), needs_score)


def format_label(obj: Object3D) -> str:
    """One KITTI label line; with a score when ``obj.score`` is set (result format).

    Labels keep KITTI's two decimals. Results get four, as other detectors' result files do: at 1 cm a
    rounded location moves a box's IoU by up to about 0.01 and so flips matches that lie that close to 0.7,
    which moved BEV AP by up to 3 points on 30 frames against the unrounded boxes (docs/evaluation.md)."""
    places = 2 if obj.score is None else RESULT_DECIMALS
    values = (obj.truncated, obj.occluded, obj.alpha, *obj.bbox, *obj.dimensions, *obj.location, obj.rotation_y,
              *(() if obj.score is None else (obj.score,)))
    bad = [name for name, value in zip(LABEL_FIELDS, values) if not math.isfinite(value)]
    if bad:  # written as "nan", the line would be refused by every KITTI reader, ours included
        raise InputError(f"{obj.type} object: {', '.join(bad)} not a finite number; KITTI label lines hold numbers only")
    h, w, l = obj.dimensions
    x, y, z = obj.location
    parts = [
        obj.type, f"{obj.truncated:.2f}", f"{int(obj.occluded)}", f"{obj.alpha:.{places}f}",
        *(f"{b:.2f}" for b in obj.bbox),
        *(f"{v:.{places}f}" for v in (h, w, l, x, y, z, obj.rotation_y)),
    ]
    if obj.score is not None:
        parts.append(f"{obj.score:.4f}")
    return " ".join(parts)


def write_labels(path: str | Path, objects: Iterable[Object3D]) -> None:
    """Write KITTI label lines (an empty file for no objects, as KITTI results expect); an object with a field
    that is not a finite number is refused (InputError) before the file is touched. The file appears whole or
    not at all: written beside it and renamed over it, so Ctrl-C mid-write neither leaves an empty result a
    reader takes for "no cars" nor cuts an earlier run's file."""
    _write_whole(Path(path), "".join(format_label(o) + "\n" for o in objects).encode("ascii"))


def _write_whole(path: Path, data: bytes) -> None:
    """``data`` as the file ``path``, whole or not at all: written beside it (``.part``) and renamed over it,
    the partial file removed when the write stops (Ctrl-C, a full disk)."""
    partial = path.with_name(path.name + ".part")
    try:
        partial.write_bytes(data)
        os.replace(partial, path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise


# --------------------------------------------------------------------------- images and depth
DEPTH_SCALE = 256.0  # KITTI depth PNG: uint16, metres × 256, 0 = no measurement


def decode_depth_png(data: bytes, source: str = "<depth>") -> np.ndarray:
    """Decode a KITTI depth PNG into float32 metres (0 where there is no measurement)."""
    if not data:  # OpenCV asserts on an empty buffer: a traceback, not a skipped frame
        raise InputError(f"{source}: empty depth PNG")
    if bytes(data[:8]) != PNG_SIGNATURE:  # OpenCV would decode any format it knows (TIFF, EXR …)
        raise InputError(f"{source}: not a PNG (a KITTI depth map is a 16-bit PNG)")
    check_header_size(data, source)
    check_image_end(data, source)  # a cut-off map: named so, and libpng kept quiet
    raw = _imdecode(data, cv2.IMREAD_UNCHANGED, source)
    if raw is None:
        raise InputError(f"{source}: not a readable PNG")
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise InputError(f"{source}: a depth PNG must be single-channel uint16, got {raw.dtype} {raw.shape}")
    return raw.astype(np.float32) / DEPTH_SCALE


def read_depth_png(path: str | Path) -> np.ndarray:
    """Read a KITTI depth PNG into float32 metres."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read depth PNG ({exc.strerror})") from exc
    return decode_depth_png(data, str(path))


def read_image_depth_png(path: str | Path, image_hw: tuple[int, int]) -> np.ndarray:
    """A dense depth PNG of a whole camera image (float32 metres), refused when its size is not the image's."""
    depth = read_depth_png(path)
    if depth.shape != tuple(image_hw):
        raise InputError(f"{path}: a {depth.shape[1]}×{depth.shape[0]} depth map for a "
                         f"{image_hw[1]}×{image_hw[0]} image; it must cover the whole image")
    return depth


def write_depth_png(path: str | Path, depth_m: np.ndarray) -> None:
    """Write float metres as a KITTI depth PNG (rounded to 1/256 m, clipped to the uint16 range).

    The file appears whole or not at all (written beside it, then renamed): a run killed while writing
    leaves no cut-off map that a resumed run (the simulator writes depth_2 last, and counts a frame done
    when it is there) or a reader would take for a finished one.
    """
    path = Path(path)
    depth = np.nan_to_num(np.asarray(depth_m, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    raw = np.clip(np.rint(depth * DEPTH_SCALE), 0, 65535).astype(np.uint16)
    encoded, png = cv2.imencode(".png", raw)
    if not encoded:
        raise InputError(f"{path}: could not encode the depth map as PNG")
    _write_whole(path, png.tobytes())


def check_image_end(data: bytes, source: str) -> None:
    """InputError when ``data`` is a PNG or JPEG that stops before its end: an upload or copy cut off.

    A PNG must hold its closing IEND chunk, a JPEG its end-of-image marker after its last scan's start.
    Checked here rather than left to the decoder: libpng complains on stderr, and the libjpeg of some
    OpenCV builds (4.x) decodes a cut-off JPEG's missing rows as grey without an error. (Both searched
    from the end, not only in the last bytes: bytes after the end, which some tools and transports
    append, are ignored by the decoders and must not read as a cut-off file. A JPEG's scan data cannot
    hold either marker: a 0xFF byte there is always followed by 0x00 or a restart marker.)
    """
    if data.startswith(PNG_SIGNATURE) and data.rfind(b"IEND") == -1:
        raise InputError(f"{source}: PNG cut off before its end ({len(data)} bytes, no IEND chunk)")
    if data.startswith(JPEG_START) and data.rfind(JPEG_END) < data.rfind(JPEG_SCAN):
        raise InputError(f"{source}: JPEG cut off before its end ({len(data)} bytes, no end-of-image marker "
                         "after its last scan)")


# JPEG markers: SOF0–SOF15 (a frame header, whose height and width follow its length and precision) but DHT,
# JPG and DAC, which share their range; and those without a length field (TEM, RST0–7, SOI).
JPEG_FRAME_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
JPEG_BARE_MARKERS = frozenset({0x01, *range(0xD0, 0xD9)})
# Segments (and fill bytes) walked to a JPEG's frame header: a camera's has a few, with an ICC profile and EXIF
# a few dozen. A walk one byte at a time through megabytes of fill bytes would take seconds.
MOST_JPEG_HEADER_STEPS = 1000


def _jpeg_header_hw(data: bytes, source: str) -> tuple[int, int] | None:
    """(rows, columns) from a JPEG's frame header, found by walking its segments; None without one before
    the first scan (the decoder then refuses the file). An InputError naming ``source`` when it is not within
    MOST_JPEG_HEADER_STEPS steps (each moves on by at least one byte): its size could not be checked."""
    at = 2
    for _ in range(MOST_JPEG_HEADER_STEPS):
        if at + 4 > len(data) or data[at] != 0xFF:
            return None
        marker = data[at + 1]
        if marker == 0xFF or marker in JPEG_BARE_MARKERS:  # a fill byte, or a marker without a length
            at += 1 if marker == 0xFF else 2
            continue
        length = int.from_bytes(data[at + 2 : at + 4], "big")
        if marker in JPEG_FRAME_MARKERS and at + 9 <= len(data):
            return int.from_bytes(data[at + 5 : at + 7], "big"), int.from_bytes(data[at + 7 : at + 9], "big")
        if marker == 0xDA or length < 2:  # a scan before any frame header, or a broken segment
            return None
        at += 2 + length
    raise InputError(f"{source}: not a readable JPEG (no frame header in its first {MOST_JPEG_HEADER_STEPS} "
                     "segments)")


# The PNG standard's bit depths for each colour type (section 11.2.2); libpng refuses any other IHDR.
PNG_BIT_DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}
PNG_COLOUR_TYPES = {0: "greyscale", 2: "truecolour", 3: "indexed-colour", 4: "greyscale with alpha",
                    6: "truecolour with alpha"}


def check_png_fields(ihdr_fields: bytes, source: str) -> None:
    """InputError naming ``source`` and the field for an IHDR (its 13 bytes of fields) that the PNG standard
    does not allow: a bit depth its colour type cannot have, an unknown colour type, compression, filter or
    interlace method. Checked here, not left to libpng, which refuses them too but writes two or three lines
    to stderr for each, outside the service's log and a batch run's report."""
    depth, colour, compression, filtering, interlace = ihdr_fields[8:13]
    if colour not in PNG_BIT_DEPTHS:
        raise InputError(f"{source}: PNG header names colour type {colour}, which PNG does not have "
                         "(0, 2, 3, 4 or 6)")
    if depth not in PNG_BIT_DEPTHS[colour]:
        allowed = ", ".join(map(str, PNG_BIT_DEPTHS[colour]))
        raise InputError(f"{source}: PNG header gives {PNG_COLOUR_TYPES[colour]} (colour type {colour}) a bit depth "
                         f"of {depth}, which PNG does not allow ({allowed})")
    for field, value, allowed_values in (("compression", compression, (0,)), ("filter", filtering, (0,)),
                                         ("interlace", interlace, (0, 1))):
        if value not in allowed_values:
            raise InputError(f"{source}: PNG header names {field} method {value}, which PNG does not have "
                             f"({' or '.join(map(str, allowed_values))})")


def image_header_hw(data: bytes, source: str) -> tuple[int, int] | None:
    """(rows, columns) as a PNG's IHDR chunk or a JPEG's frame header gives them, without decoding; None for
    a JPEG without a frame header and for other formats. An InputError naming ``source`` for a PNG header
    that is cut off or fails its CRC (a damaged size must not be believed), or whose fields PNG does not allow."""
    if data[:8] == PNG_SIGNATURE:
        ihdr = bytes(data[12:33])  # chunk type, 13 bytes of fields, CRC
        if len(ihdr) < 21 or ihdr[:4] != b"IHDR" or zlib.crc32(ihdr[:17]) != int.from_bytes(ihdr[17:], "big"):
            raise InputError(f"{source}: PNG header damaged (its IHDR chunk is missing, cut off or fails its CRC)")
        check_png_fields(ihdr[4:17], source)
        return int.from_bytes(ihdr[8:12], "big"), int.from_bytes(ihdr[4:8], "big")
    if data[:2] == JPEG_START:
        return _jpeg_header_hw(data, source)
    return None


def check_header_size(data: bytes, source: str) -> tuple[int, int] | None:
    """:func:`image_header_hw`, refused with an InputError naming ``source`` when a side is 0 or the pixels are
    more than MAX_IMAGE_PIXELS: checked before decoding, which would allocate what the header says."""
    hw = image_header_hw(data, source)
    if hw is None:
        return None
    rows, columns = hw
    if rows == 0 or columns == 0 or rows * columns > MAX_IMAGE_PIXELS:
        limit = "no pixels" if rows == 0 or columns == 0 else f"more than the limit of {MAX_IMAGE_PIXELS:,}"
        raise InputError(f"{source}: its header says {columns}×{rows} pixels, {limit}: a damaged header?")
    return hw


def check_image_file(path: str | Path) -> None:
    """InputError for an image file that is empty, neither PNG nor JPEG, or cut off before its end: what its
    first and last bytes tell without decoding it, or all its bytes when the last hold no end marker (a training
    run checks every frame's so before it starts)."""
    path = Path(path)
    try:
        with open(path, "rb") as handle:
            head = handle.read(24)
            size = handle.seek(0, 2)
            handle.seek(max(size - IMAGE_TAIL_BYTES, len(head)))
            tail = handle.read()
    except OSError as exc:
        raise InputError(f"{path}: cannot read image ({exc.strerror})") from exc
    if not head:
        raise InputError(f"{path}: empty image")
    if not head.startswith((PNG_SIGNATURE, JPEG_START)):
        raise InputError(f"{path}: not a PNG or JPEG image")
    # With its end marker in the tail, the tail decides as the whole file would (any earlier scan starts before
    # it). Without it the file is cut off, or ends further back (bytes appended after its end): read_image's rule
    # on all of it then. (The tail alone passed a cut-off JPEG, whose one scan marker lies near its start.)
    end = b"IEND" if head.startswith(PNG_SIGNATURE) else JPEG_END
    check_image_end(head + tail if end in tail else path.read_bytes(), str(path))


def _imdecode(data: bytes, flags: int, source: str) -> np.ndarray | None:
    """cv2.imdecode, None when it cannot decode ``data``; its own errors (its pixel limit, which the header check
    here keeps below, and the asserts of its decoders) an InputError naming ``source`` rather than a cv2.error."""
    try:
        return cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    except cv2.error as exc:
        raise InputError(f"{source}: not a readable image (OpenCV refused it: {getattr(exc, 'err', '') or exc})") from None


def decode_image(data: bytes, source: str = "<image>") -> np.ndarray:
    """Decode a PNG or JPEG into uint8 RGB (H, W, 3), its pixels as stored (an EXIF orientation is not applied)."""
    if not data:
        raise InputError(f"{source}: empty image")
    if not bytes(data[:8]).startswith((PNG_SIGNATURE, JPEG_START)):  # OpenCV decodes any format it knows
        raise InputError(f"{source}: not a readable PNG or JPEG image")
    check_header_size(data, source)
    check_image_end(data, source)
    # The pixels as the sensor stored them: IMREAD_COLOR alone turns a JPEG by its EXIF Orientation tag, and
    # the calibration's P2 describes the stored pixels, not a turned picture.
    bgr = _imdecode(data, cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION, source)
    if bgr is None:
        raise InputError(f"{source}: not a readable PNG or JPEG image")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def read_image(path: str | Path) -> np.ndarray:
    """Read a camera image as uint8 RGB (H, W, 3)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read image ({exc.strerror})") from exc
    return decode_image(data, str(path))


def read_image_size(path: str | Path) -> tuple[int, int]:
    """(height, width) of a camera image; for PNG from its header alone (training loaders that only
    need the size skip decoding a million pixels), otherwise by decoding it."""
    path = Path(path)
    try:
        with open(path, "rb") as handle:
            header = handle.read(33)  # the signature, the IHDR chunk's length, type, fields and CRC
    except OSError as exc:
        raise InputError(f"{path}: cannot read image ({exc.strerror})") from exc
    if header[:8] == PNG_SIGNATURE:
        size = check_header_size(header, str(path))
        if size is not None:
            return size
    return read_image(path).shape[:2]


def write_image(path: str | Path, rgb: np.ndarray) -> None:
    """Write a uint8 RGB image (PNG or JPEG by extension)."""
    if not cv2.imwrite(str(path), cv2.cvtColor(np.asarray(rgb, np.uint8), cv2.COLOR_RGB2BGR)):
        raise InputError(f"{path}: could not write image")
