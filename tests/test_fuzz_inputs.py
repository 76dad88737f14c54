"""Seeded fuzzing of every reader of user input in the frame path, and of Detector.detect's in-memory inputs.

A corrupted file or buffer must give the project's error (an InputError naming the file, or the argument), never
another exception type, a NumPy warning, a hang or an allocation taken from a size field at face value. Each case
is generated from ``np.random.default_rng((SEED, reader, case))`` and its failure message names the reader, the
case number and the mutation, so ``pytest -k`` on the reader and the printed case reproduce it. Bounded: a few
hundred small cases per reader (the whole module takes well under a minute on two cores).

The named regression tests at the end keep the inputs the fuzzing found mishandled, one each.
"""

from __future__ import annotations

import math
import re
import struct
import warnings
import zlib
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.calib import KITTI_CALIBRATION, KITTI_IMAGE_HW, Calibration, check_calibration, sparse_depth_map
from pipeline.detector import Detections, Detector
from pipeline.errors import InputError
from pipeline.frame import Frame, load_frame, read_split_file
from pipeline.kitti import (
    MAX_IMAGE_PIXELS,
    Object3D,
    Scan,
    check_image_file,
    format_calib,
    format_label,
    parse_velodyne,
    read_calib,
    read_depth_png,
    read_image,
    read_image_depth_png,
    read_image_size,
    read_labels,
    read_raw_calib,
    read_velodyne,
    write_depth_png,
)
from tests.conftest import KITTI, lidar_only_models

SEED = 20_260_518
# Values a corrupted or hand-edited text number becomes: float overflow and underflow, signed zero, the
# non-finite spellings float() accepts, and spellings it accepts that look like no number (underscores, hex).
EXTREME_NUMBERS = ("1e308", "-1e308", "1e309", "-1e400", "1e-320", "-0.0", "0", "nan", "-nan", "inf", "-Infinity",
                   "1_0", "0x10", "1e", ".", "-", "+", "1e+308e", "4294967296", "9" * 400, "٣", "1,5")
# Characters that split lines or fields in Python's str.splitlines/str.split but not in KITTI's own tools.
# A 16-line scan's worth of real points, spread over all azimuths: what a calibration read must project.
SCAN_SAMPLE = np.fromfile(KITTI / "velodyne" / "000006.bin", np.float32).reshape(-1, 4)[::4]
ODD_CHARACTERS = ("\x00", "\x0b", "\x0c", "\x1c", "\x85", "\u2028", "\ufeff", "é", "\t", "\r", ":", "\n", " ")


# --------------------------------------------------------------------------- mutations
def mutate_bytes(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    """One random corruption of a binary file: cut, bits flipped, bytes overwritten, inserted, deleted,
    a span repeated, junk appended; half the time within the first 64 bytes, where the headers and sizes lie."""
    size = len(data)
    head = bool(rng.integers(2)) and size > 0
    where = int(rng.integers(0, min(size, 64) if head else max(size, 1)))
    span = int(rng.integers(1, 17))
    noise = rng.integers(0, 256, span, dtype=np.uint8).tobytes()
    kind = int(rng.integers(7))
    if kind == 0:
        return data[:where], f"cut at {where}"
    if kind == 1:
        out = bytearray(data)
        flips = rng.integers(0, min(size, 64) if head else size, int(rng.integers(1, 9))) if size else []
        for position in flips:
            out[position] ^= 1 << int(rng.integers(8))
        return bytes(out), f"bits flipped at {sorted(int(p) for p in flips)}"
    if kind == 2:
        return data[:where] + noise + data[where + span:], f"{span} bytes overwritten at {where}"
    if kind == 3:
        return data[:where] + noise + data[where:], f"{span} bytes inserted at {where}"
    if kind == 4:
        return data[:where] + data[where + span:], f"{span} bytes deleted at {where}"
    if kind == 5:
        return data[:where + span] + data[where:], f"bytes {where}…{where + span} repeated"
    return data + noise * int(rng.integers(1, 5)), "junk appended"


HEADER_SIZES = (0, 1, 255, 256, 30_000, 65_535, 1 << 31, (1 << 32) - 1)


def with_header_size(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    """A PNG's or JPEG's header size fields set to extreme values, the PNG's CRC made right again half the time
    (a damaged size a checksum does not catch: what the decoder would allocate), else :func:`mutate_bytes`."""
    rows, columns = (int(v) for v in rng.choice(HEADER_SIZES, 2))
    if data.startswith(b"\x89PNG") and rng.integers(2):
        fields = b"IHDR" + (columns % (1 << 32)).to_bytes(4, "big") + (rows % (1 << 32)).to_bytes(4, "big") + data[24:29]
        crc = zlib.crc32(fields) if rng.integers(2) else zlib.crc32(fields) ^ 1
        return data[:12] + fields + crc.to_bytes(4, "big") + data[33:], f"IHDR says {columns}×{rows} (CRC {crc:#x})"
    frame = data.find(b"\xff\xc0") if data.startswith(b"\xff\xd8") else -1
    if frame < 0:
        frame = data.find(b"\xff\xc2") if data.startswith(b"\xff\xd8") else -1
    if frame >= 0 and rng.integers(2):
        size = struct.pack(">HH", rows % (1 << 16), columns % (1 << 16))
        return data[: frame + 5] + size + data[frame + 9 :], f"frame header says {columns % (1 << 16)}×{rows % (1 << 16)}"
    return mutate_bytes(data, rng)


def mutate_text(text: str, rng: np.random.Generator) -> tuple[bytes, str]:
    """One to three random corruptions of a text file's lines and fields, returned encoded (UTF-8; a random
    byte sometimes breaks that): numbers made extreme, fields swapped, dropped or repeated, lines swapped or
    repeated many times (kept small in bytes), odd characters inserted, a line cut, line endings changed."""
    lines = text.splitlines()
    done = []
    raw_edit = None
    for _ in range(int(rng.integers(1, 4))):
        if not lines:
            lines = [""]
        row = int(rng.integers(len(lines)))
        fields = lines[row].split(" ")
        kind = int(rng.integers(11))
        if kind == 0:
            column = int(rng.integers(len(fields)))
            fields[column] = EXTREME_NUMBERS[int(rng.integers(len(EXTREME_NUMBERS)))]
            done.append(f"line {row + 1} field {column + 1} := {fields[column]!r}")
        elif kind == 1 and len(fields) > 1:
            a, b = rng.choice(len(fields), 2, replace=False)
            fields[a], fields[b] = fields[b], fields[a]
            done.append(f"line {row + 1} fields {a + 1}, {b + 1} swapped")
        elif kind == 2:
            column = int(rng.integers(len(fields)))
            del fields[column]
            done.append(f"line {row + 1} field {column + 1} dropped")
        elif kind == 3:
            column = int(rng.integers(len(fields)))
            fields.insert(column, fields[column])
            done.append(f"line {row + 1} field {column + 1} repeated")
        elif kind == 4 and len(lines) > 1:
            other = int(rng.integers(len(lines)))
            lines[row], lines[other] = lines[other], lines[row]
            done.append(f"lines {row + 1}, {other + 1} swapped")
        elif kind == 5:
            copies = int(rng.integers(2, 2000))
            lines[row:row + 1] = [lines[row]] * copies
            done.append(f"line {row + 1} repeated {copies} times")
            continue
        elif kind == 6:
            char = ODD_CHARACTERS[int(rng.integers(len(ODD_CHARACTERS)))]
            at = int(rng.integers(len(lines[row]) + 1))
            lines[row] = lines[row][:at] + char + lines[row][at:]
            done.append(f"line {row + 1} {char!r} inserted at {at}")
            continue
        elif kind == 7:
            at = int(rng.integers(len(lines[row]) + 1))
            lines[row] = lines[row][:at]
            done.append(f"line {row + 1} cut at {at}")
            continue
        elif kind == 8:
            lines.insert(row, " ".join(["1"] * int(rng.integers(1, 5000))))
            done.append(f"a long line of ones before line {row + 1}")
            continue
        elif kind == 9:
            raw_edit = int(rng.integers(3))
            done.append(("byte inserted", "CRLF endings", "CR endings")[raw_edit])
            continue
        else:
            lines = lines[:row]
            done.append(f"cut before line {row + 1}")
            continue
        lines[row] = " ".join(fields)
    data = ("\n".join(lines) + "\n").encode("utf-8")
    if raw_edit == 0:
        at = int(rng.integers(len(data) + 1))
        data = data[:at] + bytes([int(rng.integers(256))]) + data[at:]
    elif raw_edit == 1:
        data = data.replace(b"\n", b"\r\n")
    elif raw_edit == 2:
        data = data.replace(b"\n", b"\r")
    return data, "; ".join(done)


# --------------------------------------------------------------------------- the assertion
def call_reader(read: Callable[[], object], names: str, case: str) -> object | None:
    """``read()``'s value, or None when it raised an InputError whose message names ``names`` (the file or
    argument); any other exception, and any warning (NumPy's overflow and invalid-value ones), fail with ``case``."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a warning raised becomes an exception of its own type: a failure below
        try:
            return read()
        except InputError as exc:
            assert names in str(exc), f"{case}: the InputError does not name {names}: {exc}"
            assert "\n" not in str(exc).strip(), f"{case}: not one line: {exc!r}"
            return None
        except Exception as exc:  # noqa: BLE001 (the point: any other type is the defect)
            pytest.fail(f"{case}: {type(exc).__name__} leaked instead of an InputError: {exc}")


def fuzz_file(name: str, base: bytes, read: Callable[[Path], object], check: Callable[[object, str], None],
              tmp_path: Path, cases: int, text: bool, suffix: str = ".txt") -> None:
    """Write ``cases`` corruptions of ``base`` to one file and assert :func:`call_reader` of ``read`` on each,
    ``check`` on each value returned. Images (by ``suffix``) get extreme header sizes in a third of the cases."""
    path = tmp_path / f"fuzzed{suffix}"
    for case_no in range(cases):
        rng = np.random.default_rng((SEED, zlib.crc32(name.encode()), case_no))
        if text:
            data, how = mutate_text(base.decode("utf-8"), rng)
        elif suffix in (".png", ".jpg") and rng.integers(3) == 0:
            data, how = with_header_size(base, rng)
        else:
            data, how = mutate_bytes(base, rng)
        path.write_bytes(data)
        case = f"{name}, seed {SEED}, case {case_no} ({how})"
        value = call_reader(lambda: read(path), str(path), case)
        if value is not None:
            check(value, case)


# --------------------------------------------------------------------------- what each reader must return
def check_scan(scan: object, case: str) -> None:
    assert isinstance(scan, Scan), case
    assert scan.points.dtype == np.float32 and scan.points.ndim == 2 and scan.points.shape[1] == 4, case
    assert np.isfinite(scan.points).all() and scan.dropped_nonfinite >= 0, case


def check_calib(calib: object, case: str) -> None:
    assert isinstance(calib, Calibration), case
    for matrix, shape in ((calib.P2, (3, 4)), (calib.R0_rect, (3, 3)), (calib.Tr_velo_to_cam, (3, 4))):
        assert matrix.dtype == np.float64 and matrix.shape == shape and np.isfinite(matrix).all(), case
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # what the pipeline does with it first, without overflow
        sparse_depth_map(SCAN_SAMPLE, calib, KITTI_IMAGE_HW)
        assert np.isfinite(calib.image_to_velo(np.array([0.0, 600.0]), np.array([0.0, 180.0]), np.array([1.0, 80.0]))).all(), case


def check_labels(objects: object, case: str) -> None:
    assert isinstance(objects, list), case
    for obj in objects:
        assert isinstance(obj, Object3D), case
        numbers = (obj.truncated, obj.occluded, obj.alpha, *obj.bbox, *obj.dimensions, *obj.location, obj.rotation_y)
        assert all(math.isfinite(v) for v in numbers), case
        format_label(obj)  # a label read can be written back


def check_rgb(image: object, case: str) -> None:
    assert isinstance(image, np.ndarray) and image.dtype == np.uint8, case
    assert image.ndim == 3 and image.shape[2] == 3 and min(image.shape[:2]) > 0, case


def check_depth(depth: object, case: str) -> None:
    assert isinstance(depth, np.ndarray) and depth.dtype == np.float32 and depth.ndim == 2, case
    assert np.isfinite(depth).all() and (depth >= 0).all(), case


def check_size(size: object, case: str) -> None:
    assert isinstance(size, tuple) and len(size) == 2 and all(isinstance(v, int) and v > 0 for v in size), case
    assert size[0] * size[1] <= MAX_IMAGE_PIXELS, case


# --------------------------------------------------------------------------- inputs to corrupt
def small_image(encoding: str, params: tuple[int, ...] = ()) -> bytes:
    """A 32×48 colour picture encoded as ``encoding`` (".png", ".jpg"): small, so corruptions hit its headers."""
    rows, columns = np.mgrid[0:32, 0:48]
    image = np.stack([rows * 8, columns * 5, (rows * columns) % 256], axis=-1).astype(np.uint8)
    return cv2.imencode(encoding, image, list(params))[1].tobytes()


def small_depth_png(tmp_path: Path) -> bytes:
    path = tmp_path / "depth.png"
    write_depth_png(path, np.linspace(0.0, 80.0, 24 * 40).reshape(24, 40))
    return path.read_bytes()


RAW_CAM_TO_CAM = "calib_time: 09-Jan-2012 13:57:47\nR_rect_00: {r0}\nP_rect_02: {p2}\n"
RAW_VELO_TO_CAM = "calib_time: 15-Mar-2012 11:37:16\nR: {r}\nT: {t}\n"


def numbers(matrix: np.ndarray) -> str:
    return " ".join(f"{v:.6e}" for v in np.ravel(matrix))


# --------------------------------------------------------------------------- the readers, fuzzed
def test_fuzz_read_velodyne(tmp_path):
    base = (KITTI / "velodyne" / "000006.bin").read_bytes()[: 16 * 500]
    fuzz_file("read_velodyne", base, read_velodyne, check_scan, tmp_path, 300, text=False, suffix=".bin")


def test_fuzz_read_calib(tmp_path):
    base = (KITTI / "calib" / "000003.txt").read_bytes()
    fuzz_file("read_calib", base, read_calib, check_calib, tmp_path, 400, text=True)


def test_fuzz_read_calib_binary_corruption(tmp_path):
    base = format_calib(KITTI_CALIBRATION).encode()
    fuzz_file("read_calib/bytes", base, read_calib, check_calib, tmp_path, 200, text=False)


@pytest.mark.parametrize("which", ["cam_to_cam", "velo_to_cam"])
def test_fuzz_read_raw_calib(tmp_path, which):
    calib = KITTI_CALIBRATION
    texts = {"cam_to_cam": RAW_CAM_TO_CAM.format(r0=numbers(calib.R0_rect), p2=numbers(calib.P2)),
             "velo_to_cam": RAW_VELO_TO_CAM.format(r=numbers(calib.Tr_velo_to_cam[:, :3]),
                                                   t=numbers(calib.Tr_velo_to_cam[:, 3]))}
    other = "velo_to_cam" if which == "cam_to_cam" else "cam_to_cam"
    kept = tmp_path / f"calib_{other}.txt"
    kept.write_text(texts[other])

    def read(path: Path) -> Calibration:
        return read_raw_calib(path, kept) if which == "cam_to_cam" else read_raw_calib(kept, path)

    fuzz_file(f"read_raw_calib/{which}", texts[which].encode(), read, check_calib, tmp_path, 200, text=True)


@pytest.mark.parametrize("needs_score", [False, True])
def test_fuzz_read_labels(tmp_path, needs_score):
    if needs_score:
        objects = read_labels(KITTI / "label_2" / "000006.txt")
        base = "".join(format_label(Object3D(**{**vars(o), "score": 0.5})) + "\n" for o in objects).encode()
    else:
        base = (KITTI / "label_2" / "000006.txt").read_bytes()
    fuzz_file(f"read_labels/score={needs_score}", base, lambda p: read_labels(p, needs_score), check_labels,
              tmp_path, 300, text=True)


def test_fuzz_read_split_file(tmp_path):
    base = b"000000\n000001\n# a comment\n000003\n\n000004\n000006\n"

    def check(ids: object, case: str) -> None:
        assert isinstance(ids, list) and ids and all(isinstance(i, str) and i and " " not in i for i in ids), case

    fuzz_file("read_split_file", base, read_split_file, check, tmp_path, 200, text=True)


@pytest.mark.parametrize(("kind", "suffix", "params"), [
    ("png", ".png", ()),
    ("jpeg", ".jpg", ()),
    ("progressive-jpeg", ".jpg", (cv2.IMWRITE_JPEG_PROGRESSIVE, 1)),
])
def test_fuzz_read_image(tmp_path, capfd, kind, suffix, params):
    base = small_image(suffix, params)
    fuzz_file(f"read_image/{kind}", base, read_image, check_rgb, tmp_path, 250, text=False, suffix=suffix)
    fuzz_file(f"read_image_size/{kind}", base, read_image_size, check_size, tmp_path, 100, text=False, suffix=suffix)
    fuzz_file(f"check_image_file/{kind}", base, check_image_file, lambda value, case: None, tmp_path, 100,
              text=False, suffix=suffix)
    capfd.readouterr()  # libpng and libjpeg say what they think of the corrupted files on stderr


def test_fuzz_read_image_real_frame(tmp_path, capfd):
    """Corruptions of a real KITTI image (IDAT chunks of 8 KB, not one): fewer cases, each decodes 460,000 pixels."""
    base = (KITTI / "image_2" / "000006.png").read_bytes()
    fuzz_file("read_image/kitti", base, read_image, check_rgb, tmp_path, 30, text=False, suffix=".png")
    capfd.readouterr()


def test_fuzz_read_depth_png(tmp_path, capfd):
    base = small_depth_png(tmp_path)
    fuzz_file("read_depth_png", base, read_depth_png, check_depth, tmp_path, 250, text=False, suffix=".png")

    def whole_image(path: Path) -> np.ndarray:
        return read_image_depth_png(path, (24, 40))

    fuzz_file("read_image_depth_png", base, whole_image, check_depth, tmp_path, 100, text=False, suffix=".png")
    capfd.readouterr()


def test_fuzz_load_frame(tmp_path, capfd):
    """A KITTI folder of frame 000006 (its scan cut to 2,000 points, its image to 48 × 160) with one of its four
    files corrupted per case: the Frame, or an InputError naming that file."""
    parts = {"velodyne": ".bin", "calib": ".txt", "label_2": ".txt", "image_2": ".png"}
    originals = {"velodyne": (KITTI / "velodyne" / "000006.bin").read_bytes()[: 16 * 2000],
                 "calib": (KITTI / "calib" / "000006.txt").read_bytes(),
                 "label_2": (KITTI / "label_2" / "000006.txt").read_bytes(),
                 "image_2": cv2.imencode(".png", read_image(KITTI / "image_2" / "000006.png")[-48:, :160])[1].tobytes()}
    for part, suffix in parts.items():
        (tmp_path / part).mkdir()
        (tmp_path / part / f"000006{suffix}").write_bytes(originals[part])
    for case_no in range(80):
        rng = np.random.default_rng((SEED, zlib.crc32(b"load_frame"), case_no))
        part = list(parts)[case_no % len(parts)]
        path = tmp_path / part / f"000006{parts[part]}"
        text = parts[part] == ".txt" and bool(rng.integers(2))
        data, how = mutate_text(originals[part].decode(), rng) if text else mutate_bytes(originals[part], rng)
        path.write_bytes(data)
        frame = call_reader(lambda: load_frame(tmp_path, "000006"), str(path),
                            f"load_frame, seed {SEED}, case {case_no} ({part}: {how})")
        if frame is not None:
            assert isinstance(frame, Frame) and frame.image is not None and frame.points.dtype == np.float32
        path.write_bytes(originals[part])
    capfd.readouterr()


# --------------------------------------------------------------------------- Detector.detect's in-memory inputs
@pytest.fixture(scope="module")
def detectors(tiny_models, tmp_path_factory) -> dict[str, Detector]:
    """The tiny camera model and its LiDAR-only PIXOR, one stage thread each (the fuzz's warnings stay on the
    calling thread, where the test catches them)."""
    lidar = lidar_only_models(tiny_models, tmp_path_factory.mktemp("fuzz") / "lidar")
    return {"camera": Detector(tiny_models, stage_threads=1), "lidar": Detector(lidar, stage_threads=1)}


@pytest.fixture(scope="module")
def kitti_frame() -> Frame:
    frame = load_frame(KITTI, "000006")
    frame.points = frame.points[::4].copy()  # about 27,500 points: a 16-line scan's count, a quarter of the time
    return frame


# dtypes a caller's buffer may come in: those detect() takes, and those it must refuse by name.
POINT_DTYPES = ("<f4", ">f4", "<f8", ">f8", "f2", "longdouble", "<i4", ">i8", "u8", "u1", "?", "c8", "O", "U8")
ODD_VALUES = (np.nan, np.inf, -np.inf, -0.0, 1e308, -1e308, 3e38, 1e20, 1e-45, 2.0**64, 1e4000)
POINT_LAYOUTS = ("contiguous", "Fortran", "strided", "reversed", "read-only", "flat", "(N, 4, 1)", "3 columns",
                 "5 columns", "0-d", "a list of 50 rows")


def fuzzed_points(points: np.ndarray, rng: np.random.Generator) -> tuple[object, str]:
    """The scan in a random dtype, row count, memory layout or container, with odd values planted in a few rows."""
    how = []
    rows = points[: int(rng.choice([0, 1, 2, 500, points.shape[0], points.shape[0]]))].astype(np.float64)
    if rows.size and rng.integers(2):
        for _ in range(int(rng.integers(1, 4))):
            value = ODD_VALUES[int(rng.integers(len(ODD_VALUES)))]
            at = (int(rng.integers(rows.shape[0])), int(rng.integers(4)))
            rows[at] = value
            how.append(f"{value!r} at {at}")
    dtype = POINT_DTYPES[int(rng.integers(len(POINT_DTYPES)))] if rng.integers(2) else "<f4"
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the casts of odd values to small dtypes make the input, not the defect
        array = rows.astype(np.longdouble) if dtype == "longdouble" else rows.astype(dtype)
    if dtype == "longdouble" and rows.size and rng.integers(2):
        array[int(rng.integers(rows.shape[0])), 0] = np.longdouble("1e4000")  # finite in long double only
        how.append("1e4000 (long double) in x")
    layout = int(rng.integers(len(POINT_LAYOUTS))) if rng.integers(2) else 0
    how = "; ".join([f"{array.shape[0]} rows of {dtype}", *how, POINT_LAYOUTS[layout]])
    variants = {
        1: lambda: np.asfortranarray(array),
        2: lambda: np.repeat(array, 2, axis=1)[:, ::2],  # strided columns, as a cloud[:, :4] view of wider rows
        3: lambda: array[::-1],
        4: lambda: np.frombuffer(array.tobytes(), array.dtype).reshape(array.shape) if dtype not in "OU8" else array,
        5: lambda: array.reshape(-1),
        6: lambda: array[..., None],
        7: lambda: array[:, :3],
        8: lambda: np.hstack([array, array[:, :1]]),
        9: lambda: array[0, 0] if array.size else np.float32(1.0),
        10: lambda: array.tolist()[:50],
    }
    return variants.get(layout, lambda: array)(), how


IMAGE_VARIANTS = {
    "mirrored view": lambda image: image[:, ::-1],
    "Fortran": np.asfortranarray,
    "read-only": lambda image: np.frombuffer(image.tobytes(), np.uint8).reshape(image.shape),
    "float32": lambda image: image.astype(np.float32),
    "uint16": lambda image: image.astype(np.uint16) * 257,
    "2 channels": lambda image: image[..., :2],
    "4 channels": lambda image: np.dstack([image, image[..., :1]]),
    "no rows": lambda image: image[:0],
    "100 rows": lambda image: image[:100],
    "object": lambda image: image.astype(object),
    "a nested list": lambda image: image[:2, :2].tolist(),
    "a 0-d array": lambda image: np.uint8(7),
}


def fuzzed_image(image: np.ndarray, rng: np.random.Generator) -> tuple[object, str]:
    """The image in another dtype, shape, layout or container."""
    how = list(IMAGE_VARIANTS)[int(rng.integers(len(IMAGE_VARIANTS)))]
    return IMAGE_VARIANTS[how](image), how


def fuzzed_calib(calib: Calibration, rng: np.random.Generator) -> tuple[object, str]:
    """The calibration with a matrix scaled to the float range's ends, cast, perturbed or replaced."""
    kind = int(rng.integers(7))
    key = ("P2", "R0_rect", "Tr_velo_to_cam")[int(rng.integers(3))]
    matrix = np.array(getattr(calib, key))
    if kind == 0:
        factor = float(rng.choice([1e300, 1e-300, 1e30, 1e-30, 1e154, 1e-154]))
        changed, how = matrix * factor, f"{key} × {factor:g}"
    elif kind == 1:
        dtype = str(rng.choice(["float32", "float16", "longdouble", "int64", ">f8", "complex128", "bool", "object"]))
        changed, how = matrix.astype(dtype), f"{key} as {dtype}"
    elif kind == 2:
        at = (int(rng.integers(matrix.shape[0])), int(rng.integers(matrix.shape[1])))
        value = float(rng.choice([np.nan, np.inf, 1e308, -1e308, 1e-308, 0.0, 1e200]))
        matrix[at] = value
        changed, how = matrix, f"{key}{list(at)} := {value!r}"
    elif kind == 3:
        changed, how = matrix.T.copy(), f"{key} transposed"
    elif kind == 4:
        changed, how = matrix.tolist(), f"{key} as a list"
    elif kind == 5:
        return None, "no calibration"
    else:
        return {"P2": calib.P2}, "a dict"
    return Calibration(**{**vars(calib), key: changed}), how


def fuzzed_depth(image_hw: tuple[int, int], rng: np.random.Generator) -> tuple[object, str]:
    """A caller's dense depth map in an odd dtype or shape, or with odd values."""
    kind = int(rng.integers(5))
    depth = np.full(image_hw, 20.0)
    if kind < 2:
        dtype = str(rng.choice(["float32", "float16", "longdouble", "int64", "uint16", "complex64", "bool", "object"]))
        return depth.astype(dtype), f"depth as {dtype}"
    if kind == 2:
        value = float(rng.choice([np.nan, np.inf, -1.0, 1e300, 3e38, -0.0, 1e-320]))
        depth[int(rng.integers(image_hw[0])), int(rng.integers(image_hw[1]))] = value
        return depth, f"a depth := {value!r}"
    if kind == 3:
        return depth[:, :-1], "depth one column short"
    return [[1.0, 2.0], [3.0]], "depth a ragged list"


GOOD_THRESHOLDS = (None, 0.0, 1.0, 0.5, np.float32(0.3))
ODD_THRESHOLDS = (-0.1, 1.5, float("nan"), True, "0.5", np.array(0.5))
GOOD_BEAMS = (None, 0, 16, 32, np.int64(8))
ODD_BEAMS = (64, 15, -16, 16.0, True, "16")


def fuzzed_options(rng: np.random.Generator) -> tuple[dict[str, object], str]:
    """score_threshold and emulate_to_beams: values to take, or one of them to refuse."""
    options = {"score_threshold": GOOD_THRESHOLDS[int(rng.integers(len(GOOD_THRESHOLDS)))],
               "emulate_to_beams": GOOD_BEAMS[int(rng.integers(len(GOOD_BEAMS)))]}
    if rng.integers(2):
        key, odd = (("score_threshold", ODD_THRESHOLDS), ("emulate_to_beams", ODD_BEAMS))[int(rng.integers(2))]
        options[key] = odd[int(rng.integers(len(odd)))]
    return options, ", ".join(f"{k} {v!r}" for k, v in options.items())


def fuzzed_frame(frame: Frame, camera: bool, rng: np.random.Generator) -> tuple[dict[str, object], str]:
    """detect()'s arguments with one or two of its inputs fuzzed (more would mostly stop at the first refused),
    the points most often; the others as the frame has them."""
    args: dict[str, object] = {"image": frame.image, "points": frame.points, "calib": frame.calib}
    inputs = ["points", "points", "points", "image", "calib", "options"] + (["depth"] if camera else [])
    how = []
    for which in sorted(set(rng.choice(inputs, int(rng.integers(1, 3))))):
        if which == "points":
            args["points"], said = fuzzed_points(frame.points, rng)
        elif which == "image":
            args["image"], said = fuzzed_image(frame.image, rng)
        elif which == "calib":
            args["calib"], said = fuzzed_calib(frame.calib, rng)
        elif which == "depth":
            args["depth"], said = fuzzed_depth(frame.image.shape[:2], rng)
        else:
            options, said = fuzzed_options(rng)
            args.update(options)
        how.append(f"{which}: {said}")
    return args, "; ".join(how)


def test_fuzz_detect(detectors, kitti_frame):
    """Five dozen frames with fuzzed points, image, calibration, depth or options, on the camera model and the
    LiDAR-only one: Detections of the documented shapes, or an InputError."""
    for case_no in range(60):
        rng = np.random.default_rng((SEED, zlib.crc32(b"detect"), case_no))
        name = ("camera", "lidar")[case_no % 2]
        args, how = fuzzed_frame(kitti_frame, name == "camera", rng)
        case = f"detect on the {name} model, seed {SEED}, case {case_no} ({how})"
        result = call_reader(lambda detector=detectors[name], args=args: detector.detect(**args), "", case)
        if result is not None:
            assert isinstance(result, Detections), case
            assert result.boxes.dtype == np.float64 and result.boxes.shape == (result.scores.shape[0], 7), case
            assert np.isfinite(result.boxes).all() and np.isfinite(result.scores).all(), case
            assert len(result.warnings) == len(result.warning_codes), case


# --------------------------------------------------------------------------- what the fuzzing found, kept
def jpeg_claiming(rows: int, columns: int) -> bytes:
    """The small JPEG with its frame header's size changed (its data still that of 32 × 48 pixels)."""
    data = small_image(".jpg")
    frame = data.index(b"\xff\xc0")
    return data[: frame + 5] + struct.pack(">HH", rows, columns) + data[frame + 9 :]


def png_claiming(rows: int, columns: int, crc_right: bool = True) -> bytes:
    """The small PNG with its IHDR size changed, its CRC made to fit (or not)."""
    data = small_image(".png")
    fields = b"IHDR" + struct.pack(">II", columns, rows) + data[24:29]
    crc = zlib.crc32(fields) ^ (0 if crc_right else 1)
    return data[:12] + fields + struct.pack(">I", crc) + data[33:]


def test_an_image_whose_header_claims_a_huge_size_is_refused_before_decoding(tmp_path, capfd):
    """A 3 KB JPEG whose frame header said 30,000 × 30,000 decoded into 2.7 GB of grey in 14 s (libjpeg fills
    the rows its data lacks; 9,000 × 9,000 here, 240 MB had the check gone); a PNG's IHDR past OpenCV's own limit
    raised its cv2.error (fuzz cases read_image/png 159, read_depth_png 117). Refused by the header, before
    OpenCV allocates anything."""
    path = tmp_path / "000006.jpg"
    path.write_bytes(jpeg_claiming(9_000, 9_000))
    with pytest.raises(InputError, match=rf"{path}: its header says 9000×9000 pixels, more than the limit"):
        read_image(path)
    path = tmp_path / "000006.png"
    path.write_bytes(png_claiming(65_535, 30_000))
    with pytest.raises(InputError, match=rf"{path}: its header says 30000×65535 pixels, more than the limit"):
        read_image(path)
    with pytest.raises(InputError, match=rf"{path}: its header says 30000×65535 pixels, more than the limit"):
        read_depth_png(path)
    path = tmp_path / "000006.jpg"  # the header is looked for among at most 1,000 segments or fill bytes
    path.write_bytes(b"\xff\xd8" + b"\xff" * 100_000 + jpeg_claiming(9_000, 9_000)[2:])
    with pytest.raises(InputError, match=rf"{path}: not a readable JPEG \(no frame header in its first 1000"):
        read_image(path)
    path = tmp_path / "000006.png"
    for rows, columns in ((0, 48), (32, 0)):  # libpng says so on stderr; OpenCV answered None, now we say why
        path.write_bytes(png_claiming(rows, columns))
        with pytest.raises(InputError, match=rf"{path}: its header says {columns}×{rows} pixels, no pixels"):
            read_image(path)
    capfd.readouterr()


def test_read_image_size_believes_no_damaged_png_header(tmp_path):
    """read_image_size took a PNG's IHDR at face value: 4 bytes inserted into it (fuzz case read_image_size/png 11)
    gave a width of 1.2 billion, a header with the width 0 a size of 0. Now its CRC is checked and its size bounded."""
    path = tmp_path / "x.png"
    data = small_image(".png")
    path.write_bytes(data[:16] + b"\x49\x48\x44\x52" + data[16:])
    with pytest.raises(InputError, match=rf"{path}: PNG header damaged \(its IHDR chunk is missing, cut off or fails"):
        read_image_size(path)
    path.write_bytes(png_claiming(32, 4096, crc_right=False))
    with pytest.raises(InputError, match=rf"{path}: PNG header damaged"):
        read_image_size(path)
    path.write_bytes(png_claiming(0, 48))
    with pytest.raises(InputError, match=rf"{path}: its header says 48×0 pixels, no pixels"):
        read_image_size(path)
    path.write_bytes(data)
    assert read_image_size(path) == (32, 48)


def test_only_png_and_jpeg_are_decoded(tmp_path):
    """decode_image said "a PNG or JPEG" but handed any bytes to OpenCV, which decodes a dozen other formats
    (BMP, TIFF, PPM …) whose size fields no header check here reads; check_image_file and the service refuse them."""
    image = cv2.imdecode(np.frombuffer(small_image(".png"), np.uint8), cv2.IMREAD_COLOR)
    for suffix in (".bmp", ".ppm", ".tiff"):
        path = tmp_path / f"x{suffix}"
        cv2.imwrite(str(path), image)
        with pytest.raises(InputError, match=rf"{path}: not a readable PNG or JPEG image"):
            read_image(path)
    cv2.imwrite(str(tmp_path / "depth.tiff"), np.ones((8, 8), np.uint16))
    with pytest.raises(InputError, match=r"depth.tiff: not a PNG \(a KITTI depth map is a 16-bit PNG\)"):
        read_depth_png(tmp_path / "depth.tiff")


@pytest.mark.parametrize(("row", "dtype", "shown"), [
    ((1e300, 0.0, 0.0, 0.5), np.float64, "1e+300"),  # finite in float64, infinite in the cast to float32
    ((0.0, 3e38, 0.0, 0.5), np.float32, "3e+38"),  # overflowed the projection's products
    ((0, 0, 2**64 - 1, 0), np.uint64, "18446744073709551615"),  # a driver's -1 in an unsigned field
    ((np.longdouble("1e4000"), 0.0, 0.0, 0.5), np.longdouble, "1e+4000"),  # printed in full, not as float's inf
])
def test_detect_refuses_a_coordinate_beyond_any_lidars_range(detectors, kitti_frame, row, dtype, shown):
    """Such a value passed the finiteness test and overflowed later (RuntimeWarnings, then infinities in the
    float32 stages); now it is named. Fuzz cases detect 69, 109, 149, 214."""
    points = np.vstack([np.abs(kitti_frame.points).astype(dtype), np.array([row], dtype)])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match=rf"points: a coordinate of {re.escape(shown)} m, beyond any LiDAR's"):
            detectors["lidar"].detect(None, points, None)


def test_detect_takes_float16_points_and_millimetres_still(detectors, kitti_frame):
    """The bound's own comparison overflowed for float16 points (fuzz case detect 310, a RuntimeWarning); a scan in
    millimetres lies within it, and gets the out-of-range warning as before."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert isinstance(detectors["lidar"].detect(None, kitti_frame.points.astype(np.float16), None), Detections)
        millimetres = kitti_frame.points * np.array([1000.0, 1000.0, 1000.0, 1.0], np.float32)
        assert "out_of_range" in detectors["lidar"].detect(None, millimetres, None).warning_codes


@pytest.mark.parametrize(("depth", "message"), [
    ([[1.0, 2.0], [3.0]], r"depth: expected an \(H, W\) array of metres, got a list of rows of different lengths"),
    ("complex64", r"depth: expected real depths in metres, got complex64 values"),
    ("bool", r"depth: expected real depths in metres, got bool values"),
    (1e300, r"depth: expected finite depths in metres \(float32's range\)"),
])
def test_detect_refuses_a_depth_map_it_cannot_resize(detectors, kitti_frame, depth, message):
    """A ragged list raised NumPy's ValueError, a complex map OpenCV's error from resize, 1e300 overflowed in the
    cast to float32 (fuzz cases detect 8, 28, 56)."""
    hw = kitti_frame.image.shape[:2]
    if isinstance(depth, str):
        depth = np.ones(hw, depth)
    elif isinstance(depth, float):
        depth = np.full(hw, depth)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match=message):
            detectors["camera"].detect(kitti_frame.image, kitti_frame.points, kitti_frame.calib, depth=depth)


def test_detect_takes_a_depth_map_of_any_real_dtype(detectors, kitti_frame):
    """OpenCV's resize takes neither int64 nor long double: the map is cast to float32 first."""
    for dtype in (np.int64, np.longdouble, np.float16):
        depth = np.full(kitti_frame.image.shape[:2], 20, dtype)
        result = detectors["camera"].detect(kitti_frame.image, kitti_frame.points, kitti_frame.calib, depth=depth)
        assert isinstance(result, Detections)


@pytest.mark.parametrize(("key", "factor"), [("P2", 1e300), ("Tr_velo_to_cam", 1e30), ("R0_rect", 1e-300),
                                              ("P2", 1e-30)])
def test_a_calibration_scaled_beyond_any_rig_is_refused(key, factor):
    """Finite and of full rank, so it passed, and the projections overflowed (fuzz case detect 90: R0_rect ×
    1e-300); now a value's magnitude and each block's smallest singular value are bounded."""
    calib = Calibration(**{**vars(KITTI_CALIBRATION), key: getattr(KITTI_CALIBRATION, key) * factor})
    expected = "is singular" if factor < 1 else "has a value of magnitude"
    with pytest.raises(InputError, match=rf"calib: {key} {expected}"):
        check_calibration(calib)


def test_a_calibration_in_long_double_is_checked_as_float64():
    """np.linalg has no long double: check_calibration raised its TypeError (fuzz case detect 0). Matrices of
    another real dtype are copied to float64, as the Calibration's docstring has them."""
    calib = Calibration(**{key: np.asarray(value, np.longdouble) for key, value in vars(KITTI_CALIBRATION).items()})
    checked = check_calibration(calib)
    assert all(matrix.dtype == np.float64 for matrix in vars(checked).values())
    np.testing.assert_array_equal(checked.P2, KITTI_CALIBRATION.P2)
    assert check_calibration(KITTI_CALIBRATION) is KITTI_CALIBRATION  # float64 already: as it was
    beyond = Calibration(**{**vars(calib), "P2": calib.P2 * np.longdouble("1e4000")})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match=r"calib: P2 has a non-finite value"):
            check_calibration(beyond)


@pytest.mark.parametrize(("value", "described"), [
    ([10**400] * 12, "a list"),  # OverflowError from the cast
    (np.full(12, 1 + 1j), "a complex128 array"),  # ComplexWarning, and the imaginary part dropped
    (np.array(["2020-01-01"] * 12, "M8[D]"), "a datetime64[D] array"),  # taken as days since 1970
    (np.array(["721.5"] * 12), "a <U5 array"),  # strings of digits, parsed
])
def test_from_matrices_takes_real_numbers_only(value, described):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match=rf"calib: P2: expected a 3×4 matrix of numbers, got {re.escape(described)}"):
            Calibration.from_matrices(value, KITTI_CALIBRATION.R0_rect, KITTI_CALIBRATION.Tr_velo_to_cam)


def test_parse_velodyne_takes_a_memoryview():
    """A message's buffer as a memoryview raised AttributeError in the text test (bytes.translate)."""
    points = np.arange(32, dtype="<f4").reshape(8, 4) / 32
    np.testing.assert_array_equal(parse_velodyne(memoryview(points.tobytes())).points, points)
    with pytest.raises(InputError, match="<points>: holds text"):
        parse_velodyne(memoryview(b"<html><body>404 Not Found</body></html>" * 4))
