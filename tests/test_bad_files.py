"""A messy KITTI copy: each damaged file gets one clear error naming the file (and line), never a traceback,
and costs its frame, not the run."""

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.frame import read_drive_calib, read_split_file
from pipeline.kitti import (
    decode_depth_png,
    parse_calib,
    parse_velodyne,
    read_calib,
    read_depth_png,
    read_labels,
    read_raw_calib,
    write_depth_png,
)
from tests.conftest import KITTI

ROOT = Path(__file__).resolve().parents[1]
PARTS = (("image_2", ".png"), ("velodyne", ".bin"), ("calib", ".txt"), ("label_2", ".txt"))

# KITTI raw's calib_cam_to_cam.txt, cut to the lines that matter here (drive 2011_09_26).
RAW_CAM_TO_CAM = """calib_time: 09-Jan-2012 13:57:47
corner_dist: 9.950000e-02
R_rect_00: 9.999239e-01 9.837760e-03 -7.445048e-03 -9.869795e-03 9.999421e-01 -4.278459e-03 7.402527e-03 4.351614e-03 9.999631e-01
P_rect_02: 7.215377e+02 0.000000e+00 6.095593e+02 4.485728e+01 0.000000e+00 7.215377e+02 1.728540e+02 2.163791e-01 0.000000e+00 0.000000e+00 1.000000e+00 2.745884e-03
"""


def _object_folder(root: Path, frames: tuple[str, ...] = ("000003", "000006")) -> Path:
    """A KITTI object folder in ``root`` holding copies of the real frames ``frames``."""
    for part, suffix in PARTS:
        (root / part).mkdir(parents=True)
        for fid in frames:
            shutil.copy(KITTI / part / f"{fid}{suffix}", root / part / f"{fid}{suffix}")
    return root


def _run(*args: object) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *map(str, args)], capture_output=True, text=True, timeout=300,
                          check=False, cwd=ROOT)


# --------------------------------------------------------------------------- depth PNGs
def test_an_empty_or_cut_off_depth_png_is_named_so(tmp_path, capfd):
    """An empty depth PNG made OpenCV assert (a cv2.error traceback that ended the whole run); a cut-off one
    was 'not a readable PNG', with libpng's complaint on stderr."""
    empty = tmp_path / "000003.png"
    empty.write_bytes(b"")
    with pytest.raises(InputError, match=rf"^{empty}: empty depth PNG$"):
        read_depth_png(empty)
    with pytest.raises(InputError, match=r"^upload: empty depth PNG$"):
        decode_depth_png(b"", "upload")
    whole = tmp_path / "whole.png"
    write_depth_png(whole, np.full((40, 60), 12.5))
    cut = tmp_path / "cut.png"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    capfd.readouterr()
    with pytest.raises(InputError, match=rf"^{cut}: PNG cut off before its end \(\d+ bytes, no IEND chunk\)$"):
        read_depth_png(cut)
    assert "libpng" not in capfd.readouterr().err


def test_detect_skips_the_frame_of_an_empty_depth_map_and_goes_on(tiny_models, tmp_path):
    """`detect --depth-dir` with one empty map: that frame is named and skipped, the other detected."""
    data = _object_folder(tmp_path / "kitti")
    depth = tmp_path / "depth"
    depth.mkdir()
    shutil.copy(ROOT / "tests" / "data" / "depth_completion" / "groundtruth" / "0000000005.png", depth / "000003.png")
    (depth / "000006.png").write_bytes(b"")  # a download that never started
    done = _run("-m", "pipeline.detect", "--models", tiny_models, "--data", data, "--depth-dir", depth,
                "--frame", "000003", "--frame", "000006", "--no-pictures", "--out", tmp_path / "out")
    assert "Traceback" not in done.stderr
    assert done.returncode == 1, done.stderr
    assert f"error: {depth / '000006.png'}: empty depth PNG (frame 000006 skipped)" in done.stderr
    assert "1 of 2 frame(s) skipped (each named above with its reason): 000006" in done.stderr
    assert sorted(p.name for p in (tmp_path / "out" / "data").iterdir()) == ["000003.txt"]


# --------------------------------------------------------------------------- text files from Windows and elsewhere
def test_a_byte_order_mark_is_read_past_in_labels_and_split_files(tmp_path):
    """Notepad's UTF-8 byte-order mark (with CRLF line ends) used to make a label or split file unreadable
    ('ascii' codec can't decode byte 0xef in position 0); the calibration reader already dropped it."""
    label = tmp_path / "000001.txt"
    label.write_bytes(b"\xef\xbb\xbf" + (KITTI / "label_2" / "000001.txt").read_bytes().replace(b"\n", b"\r\n"))
    assert read_labels(label) == read_labels(KITTI / "label_2" / "000001.txt")
    split = tmp_path / "val.txt"
    split.write_bytes(b"\xef\xbb\xbf000001\r\n000003\r\n")
    assert read_split_file(split) == ["000001", "000003"]


def test_utf16_and_non_ascii_bytes_name_the_file_and_line(tmp_path):
    """PowerShell's `>` writes UTF-16, and a stray Latin-1 byte is not ASCII: each named with its line, not the
    codec's 'position N' of the whole file."""
    split = tmp_path / "val.txt"
    split.write_bytes("000001\r\n000003\r\n".encode("utf-16"))
    with pytest.raises(InputError, match=rf"^{split}: UTF-16 text \(as Windows PowerShell's '>' writes it\); save "
                                         "the split file as ASCII text$"):
        read_split_file(split)
    label = tmp_path / "000001.txt"
    lines = (KITTI / "label_2" / "000001.txt").read_bytes().splitlines(keepends=True)
    label.write_bytes(b"".join(lines[:2]) + lines[2].replace(b"Cyclist", b"Cycl\xefst") + b"".join(lines[3:]))
    with pytest.raises(InputError, match=rf"^{label}, line 3: byte 0xef is not ASCII text; save the labels as "
                                         "ASCII"):
        read_labels(label)
    calib = tmp_path / "calib.txt"
    keys = (KITTI / "calib" / "000001.txt").read_bytes().split(b"\n")[:7]  # P0 … Tr_imu_to_velo
    calib.write_bytes(b"\n".join(keys) + b"\ncalib_time: 09-J\xe4n-2012\n")  # a German locale's date
    with pytest.raises(InputError, match=rf"^{calib}, line 8: byte 0xe4 is not UTF-8 text"):
        read_calib(calib)


def test_a_missing_file_says_why_once(tmp_path):
    """The reason without the errno and the path said a second time ('[Errno 2] No such file …: '<path>'')."""
    missing = tmp_path / "calib" / "000001.txt"
    with pytest.raises(InputError) as caught:
        read_calib(missing)
    assert str(caught.value) == f"{missing}: cannot read calibration (No such file or directory)"
    with pytest.raises(InputError) as caught:
        read_split_file(tmp_path)
    assert str(caught.value) == f"{tmp_path}: cannot read split file (Is a directory)"


# --------------------------------------------------------------------------- calibration and label layouts
def test_a_calibration_of_another_kitti_layout_says_which(tmp_path):
    """A raw drive's calib_cam_to_cam.txt copied into calib/, an object calib given as a drive's, and a tracking
    calib (keys without colons) used to be only 'missing P2, R0_rect, Tr_velo_to_cam' or 'expected KEY:'."""
    raw = tmp_path / "calib" / "000001.txt"
    raw.parent.mkdir()
    raw.write_text(RAW_CAM_TO_CAM)
    with pytest.raises(InputError, match=rf"^{raw}: missing calibration key\(s\) P2, R0_rect, Tr_velo_to_cam; the "
                                         r"file is KITTI raw's calib_cam_to_cam.txt \(P_rect_02, R_rect_00\), not a "
                                         r"KITTI object calib/ID.txt .*: a raw drive's calib_cam_to_cam.txt and "
                                         r"calib_velo_to_cam.txt make one calibration together \(P2 = P_rect_02, "
                                         r"R0_rect = R_rect_00, Tr_velo_to_cam = \[R \| T\]\); the commands read a "
                                         r"drive with --drive$"):
        read_calib(raw)
    # The two raw files joined into one: the first repeated key is refused, and the layout is said with it.
    raw.write_text(RAW_CAM_TO_CAM + "calib_time: 15-Mar-2012 11:37:16\nR: 1 0 0 0 1 0 0 0 1\nT: 0 0 0\n")
    with pytest.raises(InputError, match=r"line 5: calib_time given twice \(first on line 1\); the file is KITTI "
                                         "raw's calib_cam_to_cam.txt"):
        read_calib(raw)
    tracking = tmp_path / "tracking.txt"
    tracking.write_text((KITTI / "calib" / "000001.txt").read_text().replace("R0_rect:", "R_rect")
                        .replace("Tr_velo_to_cam:", "Tr_velo_cam").replace("Tr_imu_to_velo:", "Tr_imu_velo"))
    with pytest.raises(InputError, match=r"tracking.txt, line 5: expected 'KEY: numbers', got 'R_rect .*'; the file "
                                         r"is a KITTI tracking calib \(R_rect, Tr_velo_cam, without colons\).*"
                                         "'R0_rect:' and 'Tr_velo_to_cam:'"):
        read_calib(tracking)
    drive = tmp_path / "2011_09_26" / "2011_09_26_drive_0001_sync"
    drive.mkdir(parents=True)
    shutil.copy(KITTI / "calib" / "000001.txt", drive.parent / "calib_cam_to_cam.txt")
    (drive.parent / "calib_velo_to_cam.txt").write_text("R: 1 0 0 0 1 0 0 0 1\nT: 0 0 0\n")
    with pytest.raises(InputError, match=r"calib_cam_to_cam.txt: missing calibration key\(s\) P_rect_02, R_rect_00; "
                                         "the file is a KITTI object calib/ID.txt .*: an object folder's frames are "
                                         "read with --data"):
        read_drive_calib(drive)
    # A drive's two raw files given the wrong way round (the service and the commands' --drive alike): not the
    # advice to read the drive with --drive, which is what is being done.
    velo = drive.parent / "calib_velo_to_cam.txt"
    with pytest.raises(InputError, match=rf"^{velo}: missing calibration key\(s\) P_rect_02, R_rect_00; the file is "
                                         r"KITTI raw's calib_velo_to_cam.txt \(R, T\): are the drive's "
                                         r"calib_cam_to_cam.txt and calib_velo_to_cam.txt swapped or misnamed\?$"):
        read_raw_calib(velo, drive.parent / "calib_cam_to_cam.txt")
    # The hint is for a file of another layout: an object calib that lost R0_rect is only missing it.
    text = "\n".join(line for line in (KITTI / "calib" / "000001.txt").read_text().splitlines()
                     if not line.startswith("R0_rect"))
    with pytest.raises(InputError, match=r"^calib.txt: missing calibration key\(s\) R0_rect$"):
        parse_calib(text, "calib.txt")


def test_a_tracking_label_line_is_recognised(tmp_path):
    """KITTI tracking labels put the frame and track id before the type: 17 fields, said so."""
    label = tmp_path / "000001.txt"
    label.write_text("".join(f"7 {track} {line}\n" for track, line in
                             enumerate((KITTI / "label_2" / "000001.txt").read_text().splitlines())))
    with pytest.raises(InputError, match=rf"^{label}, line 1: expected 15 fields \(16 with a score\), got 17 \(a "
                                         r"KITTI tracking label line\? Frame 7, track 0 come before the type 'Truck'"):
        read_labels(label)


# --------------------------------------------------------------------------- scans
def test_a_scan_that_is_an_error_page_is_named_so():
    """An HTML page saved under the scan's name, padded here to whole 16-byte rows, used to read as garbage
    points (refused later for their 'reflectance', which hid what the file was)."""
    page = b"<!DOCTYPE html><html><head><title>404 Not Found</title></head><body>Not Found</body></html>\n"
    page += b" " * (-len(page) % 16)
    with pytest.raises(InputError, match=r"^velodyne/000001.bin: holds text \('<!DOCTYPE html><html><head><title>404 "
                                         r"No'…\), not a scan's float32 rows: a download that saved an error page"):
        parse_velodyne(page, "velodyne/000001.bin")
    # Not a scan of 17 bytes of text either: the text is said before the size.
    with pytest.raises(InputError, match="holds text"):
        parse_velodyne(b"Not Found\r\n12345678", "x.bin")


# --------------------------------------------------------------------------- commands
def test_detect_refuses_a_folder_without_calib_in_one_line(tiny_models, tmp_path):
    """A --data folder without calib/ (a wrong folder, or a download not unpacked) used to skip every frame in turn,
    a line each; now one line, before any model loads."""
    data = _object_folder(tmp_path / "kitti")
    shutil.rmtree(data / "calib")
    done = _run("-m", "pipeline.detect", "--models", tiny_models, "--data", data, "--no-pictures",
                "--out", tmp_path / "out")
    assert done.returncode == 2, done.stderr
    assert done.stderr == (f"error: {data}: no calib/ (the calibrations) inside; a KITTI object folder holds "
                           "image_2/, velodyne/ and calib/\n")
    assert not (tmp_path / "out" / "data").exists()


def test_accuracy_reads_the_ground_truth_before_the_detector_runs(tiny_models, tmp_path):
    """A label file with a field missing was found only after the detector had been over every frame: the run
    ended without its table. Now it is refused first, named with its line, and nothing is detected."""
    data = _object_folder(tmp_path / "kitti")
    label = data / "label_2" / "000006.txt"
    label.write_text("".join(" ".join(line.split()[:-1]) + "\n" for line in label.read_text().splitlines()))
    done = _run(ROOT / "benchmarks" / "accuracy.py", "--data", data, "--models", tiny_models,
                "--input", "lidar16+camera", "--out", tmp_path / "run", "--no-progress")
    assert "Traceback" not in done.stderr
    assert done.returncode == 2, done.stderr
    assert done.stderr.splitlines()[-1] == (
        f"error: {label}, line 1: expected 15 fields (16 with a score), got 14; mend the ground truth, or give "
        "--split-file or --frames to leave frame 000006 out")
    assert not (tmp_path / "run").exists()  # the detector never ran
    # Leaving the frame out with --frames 1 (000003 only) runs, as the message says.
    done = _run(ROOT / "benchmarks" / "accuracy.py", "--data", data, "--models", tiny_models,
                "--input", "lidar16+camera", "--out", tmp_path / "run", "--no-progress", "--frames", "1")
    assert done.returncode == 0, done.stderr
    assert "Car AP" in done.stdout


# --------------------------------------------------------------------------- the frame in a per-frame error
def test_cache_pseudo_names_the_frame_the_detector_refused(tiny_models, tmp_path):
    """The Detector names only the field ("image: …"); over thousands of frames the run must say which one."""
    import cv2

    from models.cache_pseudo import run as cache_pseudo

    data = _object_folder(tmp_path / "kitti")
    small = data / "image_2" / "000006.png"
    cv2.imwrite(str(small), cv2.imread(str(small))[::2, ::2])
    with pytest.raises(InputError, match=rf"^{data}, frame 000006: image: "):
        cache_pseudo(data, tiny_models, tmp_path / "maps", progress=False)
    assert (tmp_path / "maps" / "000003.png").is_file()  # the frames before it are kept


def test_accuracy_depth_refuses_a_ground_truth_map_of_another_size(tiny_models, tmp_path):
    """A depth_2 map not of the image's size was cropped as if it were, and then reported as the image's fault."""
    from evaluation.harness import run_depth
    from simulation.run import RunConfig
    from simulation.run import run as simulate

    data = tmp_path / "sim"
    simulate(RunConfig(out=data, frames=1, seed=2, split="val", progress=False))
    truth = data / "depth_2" / "000000.png"
    write_depth_png(truth, read_depth_png(truth)[::2, ::2])
    with pytest.raises(InputError, match=rf"^{truth}: a 621×188 depth map for a 1242×375 image; it must cover"):
        run_depth(data, tiny_models, progress=False)
