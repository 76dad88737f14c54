"""KITTI file formats on the real samples, and clear errors on bad files."""

import dataclasses
import gzip
import re
import struct
import warnings
import zlib

import cv2
import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.kitti import (
    PNG_SIGNATURE,
    Object3D,
    check_header_size,
    decode_depth_png,
    decode_image,
    format_label,
    image_header_hw,
    parse_calib,
    parse_labels,
    parse_velodyne,
    read_calib,
    read_depth_png,
    read_image,
    read_labels,
    read_raw_calib,
    read_velodyne,
    write_calib,
    write_depth_png,
    write_labels,
    write_velodyne,
)
from tests.conftest import FRAMES, KITTI

EXPECTED_POINTS = {"000000": 115384, "000001": 120268, "000003": 113110, "000004": 115976, "000006": 110089}
EXPECTED_IMAGE = {"000000": (370, 1224), "000001": (375, 1242), "000006": (374, 1238)}


@pytest.mark.parametrize("frame", FRAMES)
def test_real_scans_read_with_expected_counts(frame):
    scan = read_velodyne(KITTI / "velodyne" / f"{frame}.bin")
    assert scan.points.shape == (EXPECTED_POINTS[frame], 4)
    assert scan.points.dtype == np.float32
    assert scan.dropped_nonfinite == 0


def test_image_sizes_differ_per_frame():
    for frame, hw in EXPECTED_IMAGE.items():
        assert read_image(KITTI / "image_2" / f"{frame}.png").shape == (*hw, 3)


def test_image_size_from_png_header_and_jpeg_fallback(tmp_path):
    from pipeline.kitti import read_image, read_image_size, write_image

    for fid in ("000006", "000003"):  # 374 × 1238 and 375 × 1242
        path = KITTI / "image_2" / f"{fid}.png"
        assert read_image_size(path) == read_image(path).shape[:2]
    write_image(tmp_path / "x.jpg", np.zeros((7, 11, 3), np.uint8))
    assert read_image_size(tmp_path / "x.jpg") == (7, 11)
    with pytest.raises(InputError, match="missing.png"):
        read_image_size(tmp_path / "missing.png")


def test_velodyne_roundtrip_and_nonfinite_dropped(tmp_path):
    points = np.arange(40, dtype=np.float32).reshape(10, 4)
    points[3, 1] = np.nan
    points[7, 3] = np.inf
    write_velodyne(tmp_path / "x.bin", points)
    scan = read_velodyne(tmp_path / "x.bin")
    assert scan.dropped_nonfinite == 2
    assert np.isfinite(scan.points).all()
    np.testing.assert_array_equal(scan.points, np.delete(points, [3, 7], axis=0))
    # NaN, +inf and −inf in every column, some rows with several: exactly the rows with any are dropped.
    rng = np.random.default_rng(3)
    many = rng.normal(size=(1000, 4)).astype(np.float32)
    many.reshape(-1)[rng.choice(many.size, 60, replace=False)] = rng.choice([np.nan, np.inf, -np.inf], 60)
    write_velodyne(tmp_path / "many.bin", many)
    scan = read_velodyne(tmp_path / "many.bin")
    finite_rows = np.isfinite(many).all(axis=1)
    assert scan.dropped_nonfinite == np.count_nonzero(~finite_rows) > 50
    np.testing.assert_array_equal(scan.points, many[finite_rows])


def test_velodyne_bad_size_names_file(tmp_path):
    path = tmp_path / "broken.bin"
    path.write_bytes(b"\0" * 17)
    with pytest.raises(InputError, match=r"broken\.bin.*17 bytes.*multiple of 16"):
        read_velodyne(path)


def test_missing_scan_names_file(tmp_path):
    with pytest.raises(InputError, match="nope.bin"):
        read_velodyne(tmp_path / "nope.bin")


def test_calib_roundtrip(tmp_path):
    calib = read_calib(KITTI / "calib" / "000006.txt")
    assert calib.P2[0, 0] == pytest.approx(718.3351)
    write_calib(tmp_path / "c.txt", calib)
    again = read_calib(tmp_path / "c.txt")
    np.testing.assert_allclose(again.P2, calib.P2, rtol=1e-12)
    np.testing.assert_allclose(again.R0_rect, calib.R0_rect, rtol=1e-12)
    np.testing.assert_allclose(again.Tr_velo_to_cam, calib.Tr_velo_to_cam, rtol=1e-12)


def test_calib_errors_name_key_and_line():
    text = (KITTI / "calib" / "000006.txt").read_text()
    without_r0 = "\n".join(line for line in text.splitlines() if not line.startswith("R0_rect"))
    with pytest.raises(InputError, match=r"calib\.txt: missing calibration key\(s\) R0_rect"):
        parse_calib(without_r0, "calib.txt")
    short = text.replace("P2: 7.183351000000e+02 ", "P2: ")
    with pytest.raises(InputError, match=r"line 3: P2 needs 12 numbers, got 11"):
        parse_calib(short, "calib.txt")
    with pytest.raises(InputError, match=r"line 5: R0_rect has a non-numeric value"):
        parse_calib(text.replace("R0_rect: 9.999478000000e-01", "R0_rect: abc"), "calib.txt")
    # Parsable but singular: back-projection could not invert it (the service answered 500 here).
    lines = text.splitlines()
    for key, numbers in (("P2", 12), ("R0_rect", 9), ("Tr_velo_to_cam", 12)):
        zeroed = "\n".join(f"{key}: " + " ".join(["0"] * numbers) if line.startswith(f"{key}:") else line
                           for line in lines)
        with pytest.raises(InputError, match=f"calib.txt: {key} is singular"):
            parse_calib(zeroed, "calib.txt")
    # A key given twice: which matrix is meant cannot be known (the last one used to win, silently).
    with pytest.raises(InputError, match=r"calib\.txt, line 8: P2 given twice \(first on line 3\)"):
        parse_calib(text.rstrip("\n") + "\nP2: 1 0 0 0 0 1 0 0 0 0 1 0\n", "calib.txt")
    with pytest.raises(InputError, match=r"line 8: P0 given twice \(first on line 1\)"):  # even keys not used
        parse_calib(text.rstrip("\n") + "\n" + lines[0] + "\n", "calib.txt")


def test_raw_drive_calibration_reads_as_the_object_calibration(tmp_path):
    """A drive's calib_cam_to_cam.txt and calib_velo_to_cam.txt (the depth-completion layout's calibration)
    give the same matrices as the object file they were written from; a key given twice is refused."""
    calib = read_calib(KITTI / "calib" / "000003.txt")
    numbers = (lambda a: " ".join(f"{v:.12e}" for v in np.ravel(a)))
    cam = tmp_path / "calib_cam_to_cam.txt"
    cam.write_text(f"calib_time: 09-Jan-2012 13:57:47\nR_rect_00: {numbers(calib.R0_rect)}\n"
                   f"P_rect_02: {numbers(calib.P2)}\n")
    velo = tmp_path / "calib_velo_to_cam.txt"
    velo.write_text(f"calib_time: 15-Mar-2012 11:37:16\nR: {numbers(calib.Tr_velo_to_cam[:, :3])}\n"
                    f"T: {numbers(calib.Tr_velo_to_cam[:, 3])}\ndelta_f: 0 0\ndelta_c: 0 0\n")
    raw = read_raw_calib(cam, velo)
    for key in ("P2", "R0_rect", "Tr_velo_to_cam"):
        np.testing.assert_allclose(getattr(raw, key), getattr(calib, key), rtol=1e-12)
    # A byte-order mark (a Windows editor's) is read past, as in object calibration files.
    cam.write_bytes(b"\xef\xbb\xbf" + cam.read_bytes())
    np.testing.assert_allclose(read_raw_calib(cam, velo).P2, calib.P2, rtol=1e-12)
    good = velo.read_text()
    velo.write_text(good + "T: 0 0 0\n")
    with pytest.raises(InputError, match=r"calib_velo_to_cam\.txt, line 6: T given twice \(first on line 3\)"):
        read_raw_calib(cam, velo)
    velo.write_text(good.replace(f"T: {numbers(calib.Tr_velo_to_cam[:, 3])}", "T: 1 2"))
    with pytest.raises(InputError, match=r"calib_velo_to_cam\.txt, line 3: T needs 3 numbers, got 2"):
        read_raw_calib(cam, velo)
    cam.write_text(cam.read_text(encoding="utf-8-sig").replace("P_rect_02: ", "P_rect_02: 1 2 3 4 5 6 7 8 9 10 11 #"))
    velo.write_text(good)
    with pytest.raises(InputError, match=r"calib_cam_to_cam\.txt, line 3: P_rect_02 has a non-numeric value"):
        read_raw_calib(cam, velo)


def test_labels_read_and_roundtrip(tmp_path):
    objects = read_labels(KITTI / "label_2" / "000006.txt")
    assert [o.type for o in objects] == ["Car"] * 4 + ["DontCare"] * 2
    assert objects[0].dimensions == (1.48, 1.56, 3.62)
    assert objects[0].location == (-2.72, 0.82, 48.22)
    write_labels(tmp_path / "l.txt", objects)
    assert read_labels(tmp_path / "l.txt") == objects


def test_label_lines_are_stable_and_scores_roundtrip(tmp_path):
    objects = read_labels(KITTI / "label_2" / "000006.txt")
    for obj in objects:
        assert parse_labels(format_label(obj))[0] == obj
    obj = Object3D("Car", 0.0, 0, 0.1, (1, 2, 3, 4), (1.5, 1.6, 3.9), (1.0, 1.5, 20.0), -1.2, score=0.8765)
    write_labels(tmp_path / "r.txt", [obj])
    line = (tmp_path / "r.txt").read_text().split()
    assert len(line) == 16
    assert read_labels(tmp_path / "r.txt")[0].score == pytest.approx(0.8765)


def test_results_keep_a_tenth_of_a_millimetre_labels_keep_kittis_centimetre():
    """A result's box in 4 decimals (rounding to 1 cm flipped matches near IoU 0.7 and moved AP); a label
    line keeps KITTI's own 2."""
    box = Object3D("Car", 0.0, 0, 0.12345, (1, 2, 3, 4), (1.5432, 1.6, 3.9), (1.23456, 1.5, 20.06789), -1.23456)
    result = parse_labels(format_label(dataclasses.replace(box, score=0.5)))[0]
    assert result.location == (1.2346, 1.5, 20.0679) and result.rotation_y == -1.2346 and result.alpha == 0.1235
    assert result.dimensions == (1.5432, 1.6, 3.9)
    label = parse_labels(format_label(box))[0]
    assert label.location == (1.23, 1.5, 20.07) and label.rotation_y == -1.23 and label.dimensions[0] == 1.54


def test_label_wrong_field_count_names_line():
    text = "Car 0 0 0 1 2 3 4 1 1 1 1 1 1 0\nCar 0 0 0 1 2 3\n"
    with pytest.raises(InputError, match=r"labels\.txt, line 2: expected 15 fields \(16 with a score\), got 7"):
        parse_labels(text, "labels.txt")


def test_label_value_errors_name_line_and_field():
    good = "Car 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59"
    with pytest.raises(InputError, match=r"labels\.txt, line 3, field 9 \(height\): 'xx' is not a number"):
        parse_labels(f"{good}\n\n{good.replace(' 1.65 ', ' xx ')}\n", "labels.txt")
    with pytest.raises(InputError, match=r"line 1, field 14 \(z\): 'nan' is not finite"):
        parse_labels(good.replace(" 46.70 ", " nan "), "labels.txt")
    with pytest.raises(InputError, match=r"line 1, field 16 \(score\): '0\.9x' is not a number"):
        parse_labels(good + " 0.9x", "labels.txt")
    # Result files: each line needs its score, and the error names the line (blank lines counted).
    assert parse_labels(good, "gt.txt", needs_score=False)[0].score is None
    with pytest.raises(InputError, match=r"result\.txt, line 3: Car has 15 fields; a result line needs a 16th, the score"):
        parse_labels(f"{good} 0.5\n\n{good}\n", "result.txt", needs_score=True)


def test_depth_png_roundtrip_and_real_frame(tmp_path, depth_completion_dir):
    gt = read_depth_png(depth_completion_dir / "groundtruth" / "0000000005.png")
    assert gt.shape == (375, 1242)
    assert 0.15 < np.count_nonzero(gt) / gt.size < 0.25  # 19.5 % filled (README)
    assert gt.max() < 100
    write_depth_png(tmp_path / "d.png", gt)
    np.testing.assert_array_equal(read_depth_png(tmp_path / "d.png"), gt)
    # Written beside and renamed (a killed run leaves no cut-off map): no partial file stays, the bytes are
    # OpenCV's PNG as cv2.imwrite writes them, and a second write replaces the first.
    assert [p.name for p in tmp_path.iterdir()] == ["d.png"]
    import cv2

    cv2.imwrite(str(tmp_path / "e.png"), np.rint(gt * 256).astype(np.uint16))
    assert (tmp_path / "d.png").read_bytes() == (tmp_path / "e.png").read_bytes()
    write_depth_png(tmp_path / "d.png", gt * 0.5)
    np.testing.assert_array_equal(read_depth_png(tmp_path / "d.png"), np.rint(gt * 0.5 * 256) / 256)


def test_depth_png_rejects_8bit(tmp_path):
    import cv2

    cv2.imwrite(str(tmp_path / "rgb.png"), np.zeros((4, 4), np.uint8))
    with pytest.raises(InputError, match="uint16"):
        decode_depth_png((tmp_path / "rgb.png").read_bytes(), "rgb.png")


def test_parse_velodyne_copies_buffer():
    data = np.ones((3, 4), np.float32).tobytes()
    scan = parse_velodyne(data)
    scan.points[0, 0] = 5  # writable, not a view of immutable bytes
    assert scan.points.shape == (3, 4)


def test_a_png_cut_off_is_named_so_and_libpng_stays_quiet(capfd):
    from pipeline.kitti import decode_image

    data = (KITTI / "image_2" / "000006.png").read_bytes()
    assert decode_image(data, "image").shape == (374, 1238, 3)
    # Bytes after the IEND chunk (padding some tools and transports add) are ignored, as libpng does.
    assert decode_image(data + bytes(16), "image").shape == (374, 1238, 3)
    with pytest.raises(InputError, match=r"image: PNG cut off before its end \(\d+ bytes, no IEND chunk\)"):
        decode_image(data[: len(data) // 2], "image")
    assert "libpng" not in capfd.readouterr().err  # refused before OpenCV's decoder complains on stderr
    with pytest.raises(InputError, match="not a readable PNG or JPEG"):  # whole length, but garbled inside
        decode_image(data[:100] + bytes(len(data) - 112) + data[-12:], "image")


@pytest.mark.parametrize("progressive", [False, True])
def test_a_jpeg_cut_off_is_named_so(progressive):
    """A JPEG that stops before its end-of-image marker is refused by name, whatever the OpenCV build's
    libjpeg would make of it (some decode the missing rows as grey without an error)."""
    from pipeline.kitti import decode_image

    bgr = cv2.imread(str(KITTI / "image_2" / "000006.png"))
    data = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_PROGRESSIVE, int(progressive)])[1].tobytes()
    assert decode_image(data, "image").shape == (374, 1238, 3)
    assert decode_image(data + bytes(16), "image").shape == (374, 1238, 3)  # bytes after the end are ignored
    for kept in (0.5, 0.99):  # in the first scan, and in the last one
        with pytest.raises(InputError, match=r"image: JPEG cut off before its end \(\d+ bytes, no end-of-image"):
            decode_image(data[: int(len(data) * kept)], "image")
    with pytest.raises(InputError, match="not a readable PNG or JPEG"):  # cut off before its first scan
        decode_image(data[:200], "image")


def test_split_files_name_the_line_at_fault(tmp_path):
    from pipeline.frame import frame_ids, read_split_file

    split = tmp_path / "val.txt"
    split.write_text("# frames for the night run\n000001\n\n  000003  \n")
    assert read_split_file(split) == ["000001", "000003"]  # comments, blank lines and padding are not ids
    split.write_text("000001\n000003 000004\n")
    with pytest.raises(InputError, match=r"val\.txt, line 2: '000003 000004' is not a frame id \(one id per line\)"):
        read_split_file(split)
    split.write_text("000001\n000003\n000001\n")  # would count 000001 twice
    with pytest.raises(InputError, match=r"val\.txt, line 3: frame 000001 listed twice \(first on line 1\)"):
        read_split_file(split)
    with pytest.raises(InputError, match=r"nowhere: no such folder"):
        frame_ids(tmp_path / "nowhere")
    with pytest.raises(InputError, match=r"not a KITTI object folder \(no velodyne/ inside\)"):
        frame_ids(tmp_path)



def test_the_folders_people_give_by_mistake_are_named_with_the_right_one(tmp_path):
    """--data given the KITTI root, the velodyne/ folder itself or a raw drive, --drive given an object folder, and
    --models given the folder above the model directories: each error says which folder or flag was meant."""
    from pipeline.frame import drive_frame_ids, frame_ids
    from pipeline.model_files import ModelFileError, load_manifest_with_digest

    root = KITTI.parent
    with pytest.raises(InputError, match=rf"^{root}: not a KITTI object folder .*; give its training/ folder$"):
        frame_ids(root)
    with pytest.raises(InputError, match=rf"; give the folder that holds velodyne/: {KITTI}$"):
        frame_ids(KITTI / "velodyne")
    drive = tmp_path / "2011_09_26_drive_0005_sync"
    (drive / "velodyne_points" / "data").mkdir(parents=True)
    with pytest.raises(InputError, match=r"no velodyne/ inside\); it is a KITTI raw drive: give it with --drive$"):
        frame_ids(drive)
    with pytest.raises(InputError, match=r"no velodyne_points/data/ inside\); it is a KITTI object folder: give it "
                                         r"with --data$"):
        drive_frame_ids(KITTI)
    for name in ("edge", "edge-int8"):
        (tmp_path / "weights" / name).mkdir(parents=True)
        (tmp_path / "weights" / name / "manifest.json").write_text("{}")
    with pytest.raises(ModelFileError, match=r"no manifest; the model directories in .*weights: edge, edge-int8: "
                                             r"give one of them$"):
        load_manifest_with_digest(tmp_path / "weights")

# --------------------------------------------------------------------------- pinned by mutation testing
def test_a_label_line_written_back_is_kittis_own_text():
    """Every field of a label keeps KITTI's precision through read and write: the line comes back character for
    character (truncation and the 2D box in hundredths, occlusion an integer), and DontCare's -1/-10/-1000 stay."""
    lines = ["Car 0.37 2 -1.57 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59",
             "DontCare -1.00 -1 -10.00 603.36 169.62 631.06 186.56 -1.00 -1.00 -1.00 -1000.00 -1000.00 -1000.00 -10.00"]
    objects = parse_labels("\n".join(lines), "labels.txt")
    assert [format_label(obj) for obj in objects] == lines
    assert objects[0].truncated == 0.37 and objects[0].occluded == 2 and type(objects[0].occluded) is int
    assert type(objects[1].occluded) is int


def test_a_label_with_a_field_that_is_not_a_number_is_refused_before_the_file_is_touched(tmp_path):
    """Written as "nan", such a line would be refused by every KITTI reader (ours too): write_labels names the
    fields and leaves an existing file as it was."""
    import dataclasses

    from pipeline.kitti import write_labels

    car = parse_labels("Car 0.00 0 -1.57 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59",
                       "labels.txt")[0]
    path = tmp_path / "000001.txt"
    path.write_text("kept\n")
    for broken, named in ((dataclasses.replace(car, location=(np.nan, 1.71, 46.7)), "x"),
                          (dataclasses.replace(car, rotation_y=np.inf, score=np.nan), "rotation_y, score")):
        with pytest.raises(InputError, match=f"Car object: {named} not a finite number"):
            write_labels(path, [car, broken])
        assert path.read_text() == "kept\n"
    write_labels(path, [dataclasses.replace(car, score=0.5)])
    assert parse_labels(path.read_text(), "results.txt")[0].score == 0.5


def test_calibration_is_written_with_kittis_keys_in_kittis_order_and_read_without_tr_imu_to_velo(tmp_path):
    """write_calib writes the seven keys of a KITTI object calib file in its order (other tools look them up);
    a file without Tr_imu_to_velo (which the pipeline does not use) reads the same."""
    source = KITTI / "calib" / "000006.txt"
    keys = [line.split(":")[0] for line in source.read_text().splitlines() if line.strip()]
    calib = read_calib(source)
    write_calib(tmp_path / "c.txt", calib)
    assert [line.split(":")[0] for line in (tmp_path / "c.txt").read_text().splitlines()] == keys
    without = "\n".join(line for line in source.read_text().splitlines() if not line.startswith("Tr_imu_to_velo"))
    again = parse_calib(without, "calib.txt")
    for key in ("P2", "R0_rect", "Tr_velo_to_cam"):
        np.testing.assert_array_equal(getattr(again, key), getattr(calib, key))


def test_a_calibration_of_full_float64_precision_is_written_without_loss(tmp_path):
    """A calibration computed rather than read (a simulator's, a rig's) keeps 12 significant digits in its file:
    the real files' 7 digits would hide a writer that rounds."""
    from pipeline.calib import Calibration

    calib = read_calib(KITTI / "calib" / "000006.txt")
    angle = 0.0123456789012345
    c, s = np.cos(angle), np.sin(angle)
    exact = Calibration(P2=calib.P2 * (1 + 1.23456789e-9), R0_rect=np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
                        Tr_velo_to_cam=calib.Tr_velo_to_cam + 1.23456789e-9)
    write_calib(tmp_path / "c.txt", exact)
    again = read_calib(tmp_path / "c.txt")
    for key in ("P2", "R0_rect", "Tr_velo_to_cam"):
        np.testing.assert_allclose(getattr(again, key), getattr(exact, key), rtol=1e-11, atol=1e-15)


def test_calibration_numbers_are_checked_with_their_file_and_line():
    """A NaN or infinity is named with the file, line and key (not only the matrix, after parsing); 16 numbers are
    the homogeneous form of R0_rect and Tr_velo_to_cam only: a P2 of 16 is refused, not cut to its first rows."""
    lines = (KITTI / "calib" / "000006.txt").read_text().splitlines()

    def replaced(key: str, numbers: str) -> str:
        return "\n".join(f"{key}: {numbers}" if line.startswith(f"{key}:") else line for line in lines)

    for key, at, value in (("P2", 3, "nan"), ("R0_rect", 5, "inf"), ("Tr_velo_to_cam", 6, "-inf")):
        numbers = lines[at - 1].split(":")[1].split()
        numbers[1] = value
        with pytest.raises(InputError, match=rf"^calib\.txt, line {at}: {key} has a non-finite value$"):
            parse_calib(replaced(key, " ".join(numbers)), "calib.txt")
    p2_4x4 = " ".join(lines[2].split(":")[1].split() + ["0", "0", "0", "1"])
    with pytest.raises(InputError, match=r"^calib\.txt, line 3: P2 needs 12 numbers, got 16$"):
        parse_calib(replaced("P2", p2_4x4), "calib.txt")
    r0_4x4 = np.eye(4)
    r0_4x4[:3, :3] = read_calib(KITTI / "calib" / "000006.txt").R0_rect
    calib = parse_calib(replaced("R0_rect", " ".join(f"{v:.12e}" for v in r0_4x4.ravel())), "calib.txt")
    np.testing.assert_array_equal(calib.R0_rect, r0_4x4[:3, :3])


def test_depth_png_values_are_kittis_metres_times_256_and_0_is_no_depth(tmp_path):
    """Read: uint16 / 256 m, 0 staying 0 (no measurement). Written: what is no depth (NaN, ±inf, negative) is 0,
    not a wrapped uint16 (-1 m was 255 m), and beyond 65535/256 m it is the largest value, without warnings."""
    raw = np.array([[0, 1, 256, 65535]], np.uint16)
    cv2.imwrite(str(tmp_path / "k.png"), raw)
    np.testing.assert_array_equal(read_depth_png(tmp_path / "k.png"), [[0.0, 1 / 256, 1.0, 65535 / 256]])
    depth = np.array([[np.nan, np.inf, -np.inf, -1.0, -0.001, 0.0, 12.5, 300.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_depth_png(tmp_path / "d.png", depth)
    stored = cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(stored, [[0, 0, 0, 0, 0, 0, 3200, 65535]])


def test_a_depth_png_of_three_16_bit_channels_is_refused(tmp_path):
    cv2.imwrite(str(tmp_path / "rgb16.png"), np.full((4, 5, 3), 256, np.uint16))
    with pytest.raises(InputError, match=r"rgb16\.png: a depth PNG must be single-channel uint16, got uint16 "
                                         r"\(4, 5, 3\)"):
        read_depth_png(tmp_path / "rgb16.png")


def test_images_are_read_as_rgb(tmp_path):
    """A red pixel stored by OpenCV (which writes BGR) is read as red, (255, 0, 0), from a PNG and a JPEG."""
    bgr = np.zeros((8, 8, 3), np.uint8)
    bgr[..., 2] = 255
    for suffix in (".png", ".jpg"):
        cv2.imwrite(str(tmp_path / f"red{suffix}"), bgr)
        rgb = read_image(tmp_path / f"red{suffix}")
        assert rgb[..., 0].min() >= 250 and rgb[..., 1:].max() <= 5, suffix


def _png_header(rows: int, columns: int) -> bytes:
    """A PNG's signature and IHDR chunk (16-bit grey) with its CRC: all a header check reads."""
    fields = b"IHDR" + struct.pack(">IIBBBBB", columns, rows, 16, 0, 0, 0, 0)
    return PNG_SIGNATURE + struct.pack(">I", 13) + fields + struct.pack(">I", zlib.crc32(fields))


def _jpeg_with_tables_first(rgb: np.ndarray) -> bytes:
    """``rgb`` as a JPEG whose Huffman tables (DHT) come before its frame header (SOF0), as some encoders
    write them; OpenCV puts them after."""
    data = cv2.imencode(".jpg", rgb)[1].tobytes()
    at, segments = 2, []
    while data[at + 1] != 0xDA:  # up to the scan
        length = int.from_bytes(data[at + 2 : at + 4], "big")
        segments.append(data[at : at + 2 + length])
        at += 2 + length
    ordered = sorted(segments, key=lambda s: 0 if s[1] == 0xC4 else 1)  # stable: the rest keep their order
    assert ordered != segments
    return data[:2] + b"".join(ordered) + data[at:]


def test_image_headers_give_rows_then_columns():
    """(rows, columns) from a PNG's IHDR and a JPEG's frame header, wherever its tables lie; a frame header within
    the pixel limit passes, one pixel row past it is refused; a cut-off frame header gives none."""
    rgb = np.zeros((7, 11, 3), np.uint8)
    for data in (cv2.imencode(".png", rgb)[1].tobytes(), cv2.imencode(".jpg", rgb)[1].tobytes(),
                 _jpeg_with_tables_first(rgb)):
        assert image_header_hw(data, "image") == (7, 11)
    assert decode_image(_jpeg_with_tables_first(rgb), "image").shape == (7, 11, 3)  # a valid JPEG
    jpeg = cv2.imencode(".jpg", rgb)[1].tobytes()
    frame = jpeg.index(b"\xff\xc0")
    assert image_header_hw(jpeg[: frame + 8], "image") is None  # a frame header cut off: no size from half of it
    side = 1 << 13  # 8192² = MAX_IMAGE_PIXELS
    assert check_header_size(_png_header(side, side), "image") == (side, side)
    with pytest.raises(InputError, match=r"image: its header says 8192×8193 pixels, more than the limit"):
        check_header_size(_png_header(side + 1, side), "image")



def _png_with_fields(png: bytes, **fields: int) -> bytes:
    """``png`` with IHDR fields (bit_depth, colour_type, compression, filter, interlace) changed, CRC made again:
    a header libpng parses and then refuses."""
    offsets = {"bit_depth": 24, "colour_type": 25, "compression": 26, "filter": 27, "interlace": 28}
    data = bytearray(png)
    for name, value in fields.items():
        data[offsets[name]] = value
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])))
    return bytes(data)


@pytest.mark.parametrize(("fields", "words"), [
    ({"bit_depth": 3}, "gives truecolour (colour type 2) a bit depth of 3, which PNG does not allow (8, 16)"),
    ({"colour_type": 3, "bit_depth": 16}, "indexed-colour (colour type 3) a bit depth of 16"),
    ({"colour_type": 5}, "colour type 5, which PNG does not have"),
    ({"compression": 1}, "compression method 1"),
    ({"filter": 1}, "filter method 1"),
    ({"interlace": 2}, "interlace method 2, which PNG does not have (0 or 1)"),
])
def test_png_headers_png_does_not_allow_are_named_before_libpng_sees_them(tmp_path, capfd, fields, words):
    """An image whose IHDR has a valid CRC but fields PNG does not allow: one error naming the file and the field,
    and nothing from libpng on stderr (it writes two or three lines for each such file, past any log)."""
    path = tmp_path / "000000.png"
    path.write_bytes(_png_with_fields(cv2.imencode(".png", np.zeros((4, 5, 3), np.uint8))[1].tobytes(), **fields))
    with pytest.raises(InputError) as raised:
        read_image(path)
    assert str(raised.value).startswith(f"{path}: PNG header ") and words in str(raised.value)
    assert capfd.readouterr().err == ""


def test_every_png_colour_type_and_bit_depth_png_allows_passes_the_header_check():
    """The standard's 15 combinations all give their size (greyscale 1–16 bits, indexed 1–8, the rest 8 and 16),
    interlaced or not; each one step outside its colour type's depths is refused."""
    allowed = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}
    png = cv2.imencode(".png", np.zeros((4, 5), np.uint8))[1].tobytes()
    for colour, depths in allowed.items():
        for depth in depths:
            for interlace in (0, 1):
                data = _png_with_fields(png, colour_type=colour, bit_depth=depth, interlace=interlace)
                assert image_header_hw(data, "image") == (4, 5), (colour, depth, interlace)
        for depth in {1, 2, 4, 8, 16, 32} - set(depths):
            with pytest.raises(InputError, match=rf"colour type {colour}\) a bit depth of {depth},"):
                image_header_hw(_png_with_fields(png, colour_type=colour, bit_depth=depth), "image")
    # Real encoders' files: 8- and 16-bit grey and colour, with alpha, decode as before.
    for pixels in (np.zeros((4, 5), np.uint16), np.zeros((4, 5, 3), np.uint16), np.zeros((4, 5, 4), np.uint8)):
        assert decode_image(cv2.imencode(".png", pixels)[1].tobytes(), "image").shape == (4, 5, 3)


def test_files_of_other_kinds_given_as_scans_are_named(tmp_path):
    """KITTI's own image_2/000006.png is a multiple of 16 bytes: read as a scan it failed the Detector's
    reflectance check with a hint about ring or time columns. An image, a NumPy .npy, a zip, a gzip or a LAS file
    is named for what it is; each real scan (and a scan whose first x reads as a JPEG's first bytes with a
    frame marker, -8 m) is read as before."""
    image = KITTI / "image_2" / "000006.png"
    assert image.stat().st_size % 16 == 0
    with pytest.raises(InputError, match=rf"^{re.escape(str(image))}: a PNG image, not a KITTI scan .* depth map"):
        read_velodyne(image)
    npy = tmp_path / "scan.npy"
    np.save(npy, np.zeros((4, 4), np.float32))
    kinds = {"a JPEG image": cv2.imencode(".jpg", np.zeros((8, 8, 3), np.uint8))[1].tobytes(),
             "a NumPy .npy file": npy.read_bytes(), "a zip archive": b"PK\x03\x04" + bytes(60),
             "a gzip file": gzip.compress(bytes(64)), "a LAS point cloud": b"LASF" + bytes(60)}
    for what, data in kinds.items():
        with pytest.raises(InputError, match=rf"^scan\.bin: {what}, not a KITTI scan"):
            parse_velodyne(data, "scan.bin")
    for fid in FRAMES:
        assert len(read_velodyne(KITTI / "velodyne" / f"{fid}.bin").points) > 100_000
    sof0 = np.frombuffer(b"\xff\xd8\xff\xc0" + bytes(12), "<f4").copy()  # x = -8.0 m: a point, not a JPEG
    assert parse_velodyne(sof0.tobytes(), "scan.bin").points[0, 0] == pytest.approx(-7.99, abs=0.01)

def test_scans_of_one_point_of_text_or_three_columns_are_refused(tmp_path):
    """A 16-byte text file (one point's size) is named as text, not read as a point; points of 3 columns are
    refused by the writer, which would otherwise write a file that reads as other rows."""
    with pytest.raises(InputError, match=r"scan\.bin: holds text \('abcdefghijklmnop'…\)"):
        parse_velodyne(b"abcdefghijklmnop", "scan.bin")
    with pytest.raises(InputError, match=r"x\.bin: points must have shape \(N, 4\), got \(8, 3\)"):
        write_velodyne(tmp_path / "x.bin", np.zeros((8, 3), np.float32))
    assert not (tmp_path / "x.bin").exists()
