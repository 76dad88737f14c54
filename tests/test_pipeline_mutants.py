"""What the mutation audit of the runtime's remaining modules found no test pinning.

pipeline/detect.py (the detect command's flags, summary and per-frame errors), pipeline/checks.py (the checks of
what code hands the Detector, and the warnings' edges), pipeline/frame.py (loading frames), depth_completion.py,
onnx_wire.py, model_files.py, presets.py and cpu.py. Each test here was seen to fail on a mutant of that code (a
check deleted, an edge moved, a figure divided by the wrong count, a field named wrongly) and passes on the real
code; one pins a defect the audit found (a frame's image named ``000006.JPG`` was counted as its image, then not
read). The detect runs use the shipped LiDAR-only weights (weights/edge-lidar16: no torch) on the real KITTI
frames of tests/data.
"""

from __future__ import annotations

import itertools
import json
import logging
import re
import shutil
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from onnx import helper

from pipeline import cpu
from pipeline import detect as detect_module
from pipeline import detector as detector_module
from pipeline.beams import emulate_beams
from pipeline.calib import Calibration
from pipeline.checks import (
    STAMP_NS_MAX,
    beam_pattern_mismatch,
    blocked_sector_fault,
    calibration_mismatch,
    check_image,
    check_options,
    check_stamp,
    image_hw_of,
    road_level_mismatch,
    thin_scan_fault,
)
from pipeline.depth_completion import check_drive_folder, drive_calibration
from pipeline.depth_completion import drive_frame_ids as depth_drive_frame_ids
from pipeline.detect import frame_source, main, picture_title
from pipeline.errors import InputError
from pipeline.frame import drive_frame_ids, frame_image_path, load_drive_frame, load_frame, read_drive_calib
from pipeline.kitti import read_calib, write_image
from pipeline.model_files import DEFAULT_MODELS, ModelFileError, default_models_hint, load_manifest
from pipeline.onnx_wire import MAX_DEPTH, ExternalTensor, WireError, external_tensors
from pipeline.presets import (
    ABLATIONS,
    PRESETS,
    BevGrid,
    check_preset,
    get_preset,
    lidar_only,
    preset_from_dict,
    registered_preset,
)
from tests.conftest import KITTI
from tests.test_bad_files import _object_folder
from tests.test_detector import _raw_drive
from tests.test_onnx_wire import _length, external, model, weight

LIDAR16 = Path(__file__).resolve().parents[1] / "weights" / "edge-lidar16"


def _detect(capsys: pytest.CaptureFixture[str], *args: object) -> tuple[int, str, str]:
    """``python -m pipeline.detect`` (its main, in this process) with the LiDAR-only model: status, stdout, stderr."""
    status = main(["--models", str(LIDAR16), "--no-progress", "--emulate-beams", "16", *map(str, args)])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def _mean_total_ms(stdout: str) -> float:
    """The summary's mean total time per frame."""
    found = re.search(r"mean per frame: .*total ([0-9.]+) ms", stdout)
    assert found is not None, stdout
    return float(found.group(1))


# --------------------------------------------------------------------------- pipeline/detect.py


def test_a_depth_dir_for_a_lidar_only_model_is_refused_before_any_frame(tmp_path: Path, capsys) -> None:
    """Not every frame skipped in turn for a depth map the model cannot use: one line, status 2."""
    maps = tmp_path / "maps"
    maps.mkdir()
    status, _, err = _detect(capsys, "--data", KITTI, "--frame", "000006", "--depth-dir", maps, "--out",
                             tmp_path / "out")
    assert status == 2
    assert f"error: --depth-dir: {LIDAR16} is a LiDAR-only model directory; it uses no depth" in err
    assert not list((tmp_path / "out").rglob("*.txt"))


def test_frames_named_out_of_order_run_in_frame_order() -> None:
    """--frame ids (numbers or names) are run, written and filmed in frame order, whatever order they came in."""
    assert frame_source(KITTI, None, ["000006", "3", "000001"], None, None, None).ids == ["000001", "000003", "000006"]


def test_a_split_file_with_one_set_of_files_is_refused_naming_it(tmp_path: Path, capsys) -> None:
    """The flag the user gave is the one named: --split-file, not --frame."""
    split = tmp_path / "val.txt"
    split.write_text("000006\n")
    status, _, err = _detect(capsys, "--image", KITTI / "image_2" / "000006.png", "--points",
                             KITTI / "velodyne" / "000006.bin", "--calib", KITTI / "calib" / "000006.txt",
                             "--split-file", split, "--out", tmp_path / "out")
    assert status == 2
    assert err.startswith("error: --split-file chooses frames of --data DIR or --drive DIR; with --image/--points/"
                          "--calib there is one frame\n"), err


def test_a_warning_every_frame_shares_is_said_once(tmp_path: Path, capsys) -> None:
    """A warning of the same kind on every frame is one line for the run, named with its first frame."""
    data = _object_folder(tmp_path / "kitti")
    for fid in ("000003", "000006"):  # reflectance 0: another sensor's scale, warned on both frames
        scan = np.fromfile(data / "velodyne" / f"{fid}.bin", np.float32).reshape(-1, 4)
        scan[:, 3] = 0.0
        scan.tofile(data / "velodyne" / f"{fid}.bin")
    status, out, err = _detect(capsys, "--data", data, "--no-pictures", "--out", tmp_path / "out")
    assert status == 0 and "2 frame(s)" in out
    said = [line for line in err.splitlines() if "reflectance is on another scale" in line]
    assert len(said) == 1 and said[0].startswith("warning: 000003: points:"), err


def test_a_scan_of_nan_rows_only_is_named_so_and_skipped(tmp_path: Path, capsys) -> None:
    """A scan whose every row is NaN says so (not merely "no points"), and costs its frame alone."""
    data = _object_folder(tmp_path / "kitti")
    np.full((10, 4), np.nan, np.float32).tofile(data / "velodyne" / "000006.bin")
    status, out, err = _detect(capsys, "--data", data, "--no-pictures", "--out", tmp_path / "out")
    assert status == 1 and "1 frame(s)" in out
    assert f"error: {data}, frame 000006: points: none of the scan's 10 rows is finite (frame 000006 skipped)" in err


def test_the_mean_time_per_frame_counts_the_frames_detected_only(tmp_path: Path, capsys, monkeypatch) -> None:
    """Skipped frames took no detection time: the summary's mean is over the frames detected, not diluted by
    the skipped ones (here nine to one: a mean over all would be a tenth). The Detector's clock ticks 1 ms a
    read, so the one frame's time is the same in a run with the skipped frames and in one without them."""
    ticks = itertools.count()
    monkeypatch.setattr(detector_module, "time", SimpleNamespace(perf_counter=lambda: next(ticks) / 1e3))
    data = _object_folder(tmp_path / "kitti", ("000003",))
    for number in range(10, 19):  # nine cut-off scans, each a skipped frame
        (data / "velodyne" / f"0000{number}.bin").write_bytes(b"\0" * 10)
    status, out, err = _detect(capsys, "--data", data, "--no-pictures", "--out", tmp_path / "out")
    assert status == 1 and "9 of 10 frame(s) skipped" in err and "1 frame(s)" in out
    with_skipped = _mean_total_ms(out)
    alone = _object_folder(tmp_path / "alone", ("000003",))
    status, out, _ = _detect(capsys, "--data", alone, "--no-pictures", "--out", tmp_path / "alone-out")
    assert status == 0 and with_skipped == _mean_total_ms(out) >= 2, (with_skipped, out)


def test_a_video_name_that_is_a_folder_is_refused_before_anything_is_made(tmp_path: Path, capsys) -> None:
    (tmp_path / "film.mp4").mkdir()
    status, _, err = _detect(capsys, "--data", KITTI, "--frame", "000006", "--video", tmp_path / "film.mp4",
                             "--out", tmp_path / "out")
    assert status == 2 and f"error: --video {tmp_path / 'film.mp4'}: is a directory; give a file name" in err
    assert not (tmp_path / "out").exists()


def test_a_pictures_title_says_whether_the_scan_was_thinned() -> None:
    assert picture_title("000006", Path("weights/edge"), 16) == "frame 000006, model edge, scan thinned to 16 lines"
    assert picture_title("000006", Path("weights/edge"), 0) == "frame 000006, model edge"


def test_earlier_pictures_are_warned_of_only_when_this_run_writes_none(tmp_path: Path, capsys, caplog) -> None:
    """With pictures the run replaces its frames' own; without (--no-pictures) the earlier ones no longer match."""
    out = tmp_path / "out"
    (out / "bev").mkdir(parents=True)
    shutil.copy(KITTI / "image_2" / "000006.png", out / "bev" / "000006.png")
    stale = "pictures of an earlier run"
    with caplog.at_level(logging.WARNING, logger="pipeline.detect"):
        assert _detect(capsys, "--data", KITTI, "--frame", "000006", "--out", out)[0] == 0
    assert stale not in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="pipeline.detect"):
        assert _detect(capsys, "--data", KITTI, "--frame", "000006", "--no-pictures", "--out", out)[0] == 0
    assert f"{out / 'bev'} and {out / 'camera'} hold(s) {stale}" in caplog.text  # the first run's


def _files(folder: Path) -> dict[Path, bytes]:
    """Every file under ``folder`` with its bytes."""
    return {path: path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()}


def test_an_out_over_what_the_run_reads_is_refused_before_anything_is_written(tmp_path: Path, capsys) -> None:
    """``--out DRIVE/oxts`` replaced a drive's GPS/IMU files with result lines, ``--out K/label_2`` and a --video
    in K/calib were taken, and a result file could be written over the --calib it read: each is now refused in
    one line naming the input, before any model loads, with every input file as it was. A drive is an input
    whole (its oxts/ is read by no run, yet is no place for results); an object folder its KITTI folders only."""
    drive = _raw_drive(tmp_path / "raw", {"0000000000": "000006"})
    (drive / "oxts" / "data").mkdir(parents=True)
    (drive / "oxts" / "data" / "0000000000.txt").write_text("49.015 8.434 116.4 0.02 0.01 2.13 (GPS/IMU)\n")
    data = _object_folder(tmp_path / "kitti", ("000006",))
    one = tmp_path / "one"
    (one / "data").mkdir(parents=True)
    shutil.copy(KITTI / "calib" / "000006.txt", one / "data" / "000006.txt")  # what OUT/data/000006.txt would be
    models = tmp_path / "models"
    shutil.copytree(LIDAR16, models)
    before = {folder: _files(folder) for folder in (tmp_path / "raw", data, one, models)}
    single = ("--image", KITTI / "image_2" / "000006.png", "--points", KITTI / "velodyne" / "000006.bin")
    video, maps = data / "calib" / "v.mp4", tmp_path / "o" / "bev"
    for args, (flag, path), (source_flag, source) in (
        (("--drive", drive, "--out", drive / "oxts"), ("--out", drive / "oxts"), ("--drive", drive)),
        (("--drive", drive, "--out", drive / "image_02"), ("--out", drive / "image_02"), ("--drive", drive)),
        (("--drive", drive, "--out", drive / "results"), ("--out", drive / "results"), ("--drive", drive)),
        (("--data", data, "--out", data / "label_2"), ("--out", data / "label_2"), ("--data", data)),
        (("--data", data, "--out", data / "velodyne"), ("--out", data / "velodyne"), ("--data", data)),
        (("--data", data, "--video", video, "--out", tmp_path / "o"), ("--video", video), ("--data", data)),
        # A skipped frame's earlier picture OUT/bev/ID.png is removed: here the frame's depth map.
        (("--data", data, "--depth-dir", maps, "--out", tmp_path / "o"), ("--out", maps), ("--depth-dir", maps)),
        (("--data", data, "--models", models, "--out", models / "out"), ("--out", models / "out"), ("--models", models)),
    ):
        status, _, err = _detect(capsys, *args)
        assert status == 2 and err == (f"error: {flag} {path}: would be written over what {source_flag} {source} "
                                       "holds, which this run reads; give a path outside it\n"), (args, err)
    status, _, err = _detect(capsys, *single, "--calib", one / "data" / "000006.txt", "--out", one)
    assert status == 2 and err == (f"error: --out {one}: its data/000006.txt would be written over --calib "
                                   f"{one / 'data' / '000006.txt'}, which this run reads; give an --out elsewhere\n")
    assert {folder: _files(folder) for folder in before} == before
    assert not (tmp_path / "o").exists()
    # A new folder in an object folder, beside its KITTI folders, holds the results.
    status, out, _ = _detect(capsys, "--data", data, "--no-pictures", "--out", data / "results")
    assert status == 0 and (data / "results" / "data" / "000006.txt").is_file(), out


def _thinned(path: Path) -> None:
    """Thin the 64-line scan at ``path`` (a copy) to 16 lines, as a 16-line sensor writes its scans."""
    emulate_beams(np.fromfile(path, np.float32).reshape(-1, 4), 16).tofile(path)


def test_emulate_beams_on_scans_thinned_already_is_refused_before_any_frame(tmp_path: Path, capsys) -> None:
    """--emulate-beams 16 on a 16-line sensor's folder or drive skipped every frame in turn, advising to mend
    files that are fine (exit 1): now one line, exit 2, before any model loads, naming the first scan that
    reads (a cut-off one before it stays its frame's skip) and the flag to give, as accuracy.py does."""
    data = _object_folder(tmp_path / "kitti")
    for scan in (data / "velodyne").glob("*.bin"):
        _thinned(scan)
    (data / "velodyne" / "000002.bin").write_bytes(b"\0" * 10)  # sorts first, and cannot be read
    drive = _raw_drive(tmp_path / "raw", {"0000000000": "000006", "0000000001": "000003"})
    for scan in (drive / "velodyne_points" / "data").glob("*.bin"):
        _thinned(scan)
    thinned = "points: the scan has 16 rings, not 64: it is thinned already (emulate beams on 64-line scans only)"
    for source, scan in (("--data", data / "velodyne" / "000003.bin"),
                         ("--drive", drive / "velodyne_points" / "data" / "0000000000.bin")):
        status, out, err = _detect(capsys, source, scan.parents[1 if source == "--data" else 2], "--out",
                                   tmp_path / "out")
        assert (status, out) == (2, "")
        assert err == (f"error: {scan}: {thinned}; to detect on scans of a 16-line sensor as they are, give "
                       "--emulate-beams 0\n")
        assert not (tmp_path / "out").exists()


def test_a_run_stopped_before_its_first_frame_says_it_wrote_nothing(tmp_path: Path, capsys, monkeypatch) -> None:
    """Ctrl-C during the first frame said "the frames detected so far have their files in OUT", of an OUT that
    did not exist. The interrupt is raised where the Detector works, as Ctrl-C's KeyboardInterrupt is: in the
    first frame the line says nothing was written; in the second, that the first frame's files are there."""
    detect = detector_module.Detector.detect

    def interrupted_in_frame(number: int) -> Callable[..., object]:
        """Detector.detect, with Ctrl-C in the ``number``-th frame (from 0)."""
        calls = itertools.count()

        def interrupted(self, *args, **kwargs):
            if next(calls) == number:
                raise KeyboardInterrupt
            return detect(self, *args, **kwargs)
        return interrupted

    for frames_done in (0, 1):
        monkeypatch.setattr(detector_module.Detector, "detect", interrupted_in_frame(frames_done))
        out = tmp_path / f"out{frames_done}"
        status, _, err = _detect(capsys, "--data", KITTI, "--frame", "3", "--frame", "6", "--out", out)
        assert status == 130
        if frames_done:
            assert err.endswith(f"interrupted: the frames detected so far have their files in {out}\n"), err
            assert [p.name for p in (out / "data").iterdir()] == ["000003.txt"]
        else:
            assert err.endswith(f"interrupted: no frame was detected yet, so this run wrote nothing in {out}\n"), err
            assert not out.exists()
    # Stopped while the summary is printed: the run is over, every frame's files are there.
    monkeypatch.undo()

    def interrupted_report(*args: object) -> int:
        raise KeyboardInterrupt

    monkeypatch.setattr(detect_module, "_report", interrupted_report)
    status, _, err = _detect(capsys, "--data", KITTI, "--frame", "6", "--out", tmp_path / "done")
    assert status == 130 and err.endswith(f"have their files in {tmp_path / 'done'}\n"), err


# --------------------------------------------------------------------------- pipeline/checks.py


def test_an_image_size_that_is_no_images_is_refused_naming_image_hw() -> None:
    assert image_hw_of((375, 1242, 3)) == (375, 1242)
    for size in ((0, 1242), (375, 0, 3), (375,), (1, 375, 1242, 3)):  # a batch's shape is no image's
        with pytest.raises(InputError, match=r"^image_hw: expected \(rows, columns\)"):
            image_hw_of(size)


def test_a_bool_is_no_score_threshold_and_zero_lines_is_the_scan_as_given() -> None:
    """True would pass for the threshold 1.0 (no box at all); emulate_to_beams=0 is the CLI's --emulate-beams 0."""
    with pytest.raises(InputError, match=r"^score_threshold: a probability in \[0, 1\].*got True"):
        check_options(True, None)
    check_options(0.0, 0)
    check_options(1.0, 16)


def test_the_principal_points_column_is_checked_against_the_images_width() -> None:
    """cx = 200 lies in a 1242-column image's left quarter (though above a quarter of its 375 rows): warned."""
    calib = read_calib(KITTI / "calib" / "000006.txt")
    assert calibration_mismatch((375, 1242), calib) is None
    p2 = calib.P2.copy()
    p2[0, 2] = 200.0
    warning = calibration_mismatch((375, 1242), Calibration(P2=p2, R0_rect=calib.R0_rect,
                                                           Tr_velo_to_cam=calib.Tr_velo_to_cam))
    assert warning is not None and "principal point (200.0, " in warning and "(x 310.5…931.5, " in warning


@pytest.fixture(scope="module")
def scan6() -> np.ndarray:
    """KITTI 000006's 64-line scan."""
    return load_frame(KITTI, "000006").points


def test_a_road_far_below_the_training_rigs_is_warned_about_as_one_above(scan6: np.ndarray) -> None:
    """A LiDAR mounted a metre higher than KITTI's sees the road a metre lower: as wrong as a vehicle frame's."""
    assert road_level_mismatch(scan6, -1.73) is None
    lower = scan6.copy()
    lower[:, 2] -= 1.0
    warning = road_level_mismatch(lower, -1.73)
    assert warning is not None and warning.endswith("(road at -2.68 m)")


def test_a_road_strip_of_a_few_returns_gives_no_verdict(scan6: np.ndarray) -> None:
    """Under FEWEST_ROAD_RETURNS returns 3–12 m ahead (here 100 points, about 25 in the every-4th sample, 3 m up: a
    truck's side right ahead, say) say nothing of the road's level."""
    x, y = scan6[:, 0], scan6[:, 1]
    strip = (np.abs(x - 7.5) < 4.5) & (np.abs(y) < 3.0)
    raised = np.concatenate([scan6[~strip], scan6[strip][:100] + np.float32([0.0, 0.0, 3.0, 0.0])])
    assert road_level_mismatch(raised, -1.73) is None


def test_a_few_hundred_far_returns_are_enough_to_tell_the_beam_pattern() -> None:
    """500 sampled returns (4,000 points) all level with the sensor, 10 m off: none below -17°, warned."""
    ring = np.linspace(-np.pi, np.pi, 4000, endpoint=False)
    level = np.column_stack([10 * np.cos(ring), 10 * np.sin(ring), np.zeros(4000), np.full(4000, 0.2)])
    warning = beam_pattern_mismatch(level.astype(np.float32))
    assert warning is not None and warning.endswith("(0% below, 0% above)")


@pytest.fixture(scope="module")
def lidar16(scan6: np.ndarray) -> np.ndarray:
    """KITTI 000006's scan thinned to 16 lines, as the shipped models learned on."""
    return emulate_beams(scan6, 16)


def test_a_sector_of_exactly_two_empty_degrees_is_named_with_its_width(lidar16: np.ndarray) -> None:
    """The shortest block the check catches (SECTOR_RUN degrees) is named with its azimuths and its width."""
    assert blocked_sector_fault(lidar16) is None
    azimuth = np.degrees(np.arctan2(lidar16[:, 1], lidar16[:, 0]))
    blocked = lidar16[~((azimuth >= 10.0) & (azimuth < 12.0) & (lidar16[:, 0] > 0))]
    warning = blocked_sector_fault(blocked)
    assert warning is not None and "no returns from azimuth 10° to 12°" in warning
    assert "(2° empty in all, a degree's median 80 returns)" in warning


def test_a_scan_too_thin_to_tell_a_sector_is_not_called_blocked(lidar16: np.ndarray) -> None:
    """With a twentieth of its returns left, empty degrees are chance, not a blocked window: the thin-scan warning
    is the one to give, not a blocked sector somewhere."""
    thin = lidar16[np.random.default_rng(0).random(len(lidar16)) < 0.05]
    assert blocked_sector_fault(thin) is None


def test_the_thin_scan_warning_starts_below_its_bound() -> None:
    """A 16-line scan with FEWEST_IN_GRID_PER_LINE × 16 = 7,200 returns in the grid passes; one fewer is warned."""
    assert thin_scan_fault(7200, 16) is None
    warning = thin_scan_fault(7199, 16)
    assert warning is not None and "only 7199 returns" in warning and "puts 10,880 or more" in warning
    assert warning.endswith("(fewer than 7,200)")
    assert thin_scan_fault(0, None) is None  # a line count the model does not know: nothing to compare with


def test_the_edges_of_a_stamp_are_taken() -> None:
    """0 (a clock's start) and int64's largest value are capture times; the schema's bounds say the same."""
    assert check_stamp(0, "image_stamp_ns") == 0
    assert check_stamp(STAMP_NS_MAX, "points_stamp_ns") == 2**63 - 1
    with pytest.raises(InputError, match=r"^points_stamp_ns: 9223372036854775808 is more than int64 holds"):
        check_stamp(STAMP_NS_MAX + 1, "points_stamp_ns")


def test_a_float_image_with_negative_values_is_not_called_a_0_to_1_image() -> None:
    """Only an image whose every finite value lies in 0…1 gets the ×255 hint: a -1…1 one would come out wrong."""
    with pytest.raises(InputError) as caught:
        check_image(np.full((4, 4, 3), -0.5, np.float32))
    assert str(caught.value) == ("image: expected uint8 RGB (H, W, 3), got float32 (4, 4, 3); floats: convert 0–255 "
                                 "values with image.clip(0, 255).round().astype(np.uint8)")
    with pytest.raises(InputError, match="; values 0–1: convert with"):
        check_image(np.full((4, 4, 3), 0.5, np.float32))


# --------------------------------------------------------------------------- pipeline/frame.py


def test_a_frames_png_is_read_before_its_jpeg(tmp_path: Path) -> None:
    """KITTI's PNG first: a camera recorder's JPEG of the same frame beside it is not what gets read."""
    data = _object_folder(tmp_path / "kitti", ("000006",))
    write_image(data / "image_2" / "000006.jpg", np.zeros((20, 30, 3), np.uint8))
    assert frame_image_path(data, "000006") == data / "image_2" / "000006.png"
    assert load_frame(data, "000006").image_hw == (374, 1238)  # the PNG's size, not the 20×30 JPEG's


def test_a_frames_image_with_an_upper_case_suffix_is_read(tmp_path: Path, capsys) -> None:
    """Cameras and Windows tools write 000006.JPG: the detect command counted it as the frame's image, then
    skipped the frame with "no image for frame 000006 (nor 000006.jpg or 000006.jpeg)"."""
    data = _object_folder(tmp_path / "kitti", ("000006",))
    (data / "image_2" / "000006.png").rename(data / "image_2" / "000006.PNG")
    assert frame_image_path(data, "000006") == data / "image_2" / "000006.PNG"
    status, out, err = _detect(capsys, "--data", data, "--no-pictures", "--out", tmp_path / "out")
    assert status == 0 and "1 frame(s)" in out and "error" not in err, err

def test_a_drive_of_text_scans_is_named_as_kittis_unsynced_download(tmp_path: Path) -> None:
    drive = tmp_path / "2011_09_26" / "2011_09_26_drive_0005_extract"
    (drive / "image_02" / "data").mkdir(parents=True)
    (drive / "velodyne_points" / "data").mkdir(parents=True)
    (drive / "velodyne_points" / "data" / "0000000000.txt").write_text("1.0 2.0 -1.5 0.3\n")
    with pytest.raises(InputError, match=r"its scans are text files \(KITTI's unsynced '_extract' download\); use "
                                         r"the '_sync' drive"):
        drive_frame_ids(drive)


def test_a_drives_own_calibration_files_come_before_the_date_folders(make_drive) -> None:
    """Each file is looked for in the drive folder first: a drive that carries its own is not read with the date
    folder's (here a broken one)."""
    drive = make_drive()
    for name in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt"):
        shutil.copy(drive.parent / name, drive / name)
    (drive.parent / "calib_cam_to_cam.txt").write_text("P_rect_02: 1 2 3\n")
    calib = read_drive_calib(drive)
    np.testing.assert_allclose(calib.P2, read_calib(KITTI / "calib" / "000003.txt").P2)


def test_a_drive_frame_counts_the_rows_it_dropped(tmp_path: Path) -> None:
    """As a folder's frame does: the detect command warns of them on a drive too."""
    drive = tmp_path / "2011_09_26_drive_0005_sync"
    (drive / "image_02" / "data").mkdir(parents=True)
    (drive / "velodyne_points" / "data").mkdir(parents=True)
    shutil.copy(KITTI / "image_2" / "000006.png", drive / "image_02" / "data" / "0000000000.png")
    scan = np.fromfile(KITTI / "velodyne" / "000006.bin", np.float32).reshape(-1, 4)
    scan[:7, 2] = np.inf
    scan.tofile(drive / "velodyne_points" / "data" / "0000000000.bin")
    frame = load_drive_frame(drive, "0000000000", read_calib(KITTI / "calib" / "000006.txt"))
    assert frame.dropped_nonfinite == 7 and len(frame.points) == len(scan) - 7


# --------------------------------------------------------------------------- pipeline/depth_completion.py


def test_a_drives_frames_are_those_with_ground_truth(make_drive) -> None:
    """A scan's depth map without its ground truth is no frame to evaluate or train on."""
    drive = make_drive(frame_ids=("0000000005", "0000000010"))
    (drive / "groundtruth" / "0000000010.png").unlink()
    assert depth_drive_frame_ids(drive) == ["0000000005"]


def test_a_drives_unreadable_calibration_file_is_named_not_taken_for_none(make_drive) -> None:
    """A calibration file that is there but broken is an error naming it, not "needs the drive's calibration"."""
    drive = make_drive()
    (drive.parent / "calib_velo_to_cam.txt").write_text("R: 1 2 3\n")
    with pytest.raises(InputError) as caught:
        drive_calibration(drive)
    assert str(caught.value) == f"{drive.parent / 'calib_velo_to_cam.txt'}, line 1: R needs 9 numbers, got 3"



def test_kittis_depth_completion_root_gets_the_way_to_link_one_drive(tmp_path: Path) -> None:
    """The folder KITTI's download unpacks (train/, val/) given as --data: how to link a drive, not "no drive"."""
    (tmp_path / "train" / "2011_09_26_drive_0001_sync").mkdir(parents=True)
    with pytest.raises(InputError, match=rf"^--data {tmp_path}: KITTI's depth-completion layout, one drive at a "
                                         r"time in the flat one: link one drive into the flat layout: mkdir DRIVE"):
        check_drive_folder(tmp_path)


# --------------------------------------------------------------------------- pipeline/onnx_wire.py


def test_a_graph_with_a_negative_attribute_is_read_whole() -> None:
    """axis=-1 is a 10-byte varint on the wire (protobuf's longest): read past, and the tensor after it found."""
    concat = helper.make_node("Concat", ["x", "w"], ["y"], axis=-1)
    data = model([concat], initializers=[external(weight("w"), "w.bin")]).SerializeToString()
    assert b"\xff\xff\xff\xff\xff\xff\xff\xff\xff\x01" in data
    assert external_tensors(data) == [ExternalTensor("w", "w.bin")]


def test_a_field_one_byte_longer_than_its_message_is_refused() -> None:
    with pytest.raises(WireError, match="field 7 at byte 0 is 3 bytes long, past the end of its message"):
        external_tensors(b"\x3a\x03\x2a\x01")


def test_a_fixed32_field_one_byte_short_is_refused() -> None:
    with pytest.raises(WireError, match="field 1 at byte 0 runs past the end of its message"):
        external_tensors(b"\x0d\x00\x00\x00")


def _nested(deepest: int) -> bytes:
    """A model whose messages nest ``deepest`` levels below it: graph, node, attribute, graph (its g), node, …"""
    data = b""
    for depth in range(deepest, 0, -1):  # from the innermost message out
        kind = depth % 3  # 1: a graph (the model's, or an attribute's g), 2: a node, 0: an attribute
        tag = (b"\x3a" if depth == 1 else b"\x32") if kind == 1 else (b"\x0a" if kind == 2 else b"\x2a")
        data = tag + _length(len(data)) + data
    return data


def test_messages_nest_at_most_max_depth_levels_below_the_model() -> None:
    """protobuf's own bound (onnx.load_from_string reads 100 levels and refuses 101): the same here."""
    assert external_tensors(_nested(MAX_DEPTH)) == []
    with pytest.raises(WireError, match=f"messages nest deeper than {MAX_DEPTH}"):
        external_tensors(_nested(MAX_DEPTH + 1))


def test_groups_nest_at_most_max_depth_deep() -> None:
    """Unknown group fields (field 1, opened and closed n times) are skipped to protobuf's bound, as onnx reads
    them: 100 deep read past, 101 refused."""
    assert external_tensors(b"\x0b" * MAX_DEPTH + b"\x0c" * MAX_DEPTH) == []
    with pytest.raises(WireError, match=f"groups nest deeper than {MAX_DEPTH}"):
        external_tensors(b"\x0b" * (MAX_DEPTH + 1) + b"\x0c" * (MAX_DEPTH + 1))


# --------------------------------------------------------------------------- pipeline/model_files.py


def _manifest_with(tmp_path: Path, edit: Callable[[dict], object]) -> Path:
    """A model directory holding the shipped LiDAR-only manifest changed by ``edit`` (manifest checks only)."""
    manifest = json.loads((LIDAR16 / "manifest.json").read_text())
    edit(manifest)
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    return tmp_path


def test_a_recorded_line_count_of_true_is_refused_naming_the_field(tmp_path: Path) -> None:
    """True is an int to Python (1 line): as a training record's emulate_beams it is a broken manifest."""
    models = _manifest_with(tmp_path, lambda m: m["networks"]["pixor"].setdefault("training", {}).update(
        emulate_beams=True))
    with pytest.raises(ModelFileError, match=r"networks\.pixor\.training\.emulate_beams: expected a whole number "
                                             r"of lines \(0: as stored\), got True"):
        load_manifest(models)


def test_a_recorded_input_that_is_not_a_name_is_refused_naming_the_field(tmp_path: Path) -> None:
    """A list there made the Detector fail with a TypeError traceback at load."""
    models = _manifest_with(tmp_path, lambda m: m["networks"]["pixor"].setdefault("training", {}).update(
        input=["pseudo"]))
    with pytest.raises(ModelFileError, match=r"networks\.pixor\.training\.input: expected the name of the input "
                                             r"\(such as \"pseudo\"\), got \['pseudo'\]"):
        load_manifest(models)


def test_a_manifest_without_its_networks_table_is_named_so_without_torch(tmp_path: Path) -> None:
    """Named, not a KeyError later (test_onnx_weights.py sees it through a tool that needs torch)."""
    with pytest.raises(ModelFileError, match=r"manifest\.json: manifest has no 'networks' table$"):
        load_manifest(_manifest_with(tmp_path, lambda m: m.pop("networks")))


def test_the_default_models_hint_is_only_for_an_install_without_them(tmp_path: Path, capsys) -> None:
    """In a checkout (weights/edge there) an error with the default --models gets no "only in a source
    checkout" line: it would send the user after the wrong cause."""
    assert DEFAULT_MODELS.is_dir() and default_models_hint(DEFAULT_MODELS) is None
    status = main(["--data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert status == 2 and err == f"error: {tmp_path / 'nowhere'}: no such folder\n"


# --------------------------------------------------------------------------- pipeline/presets.py


def test_a_preset_suffix_given_twice_is_refused() -> None:
    """edge-no-gam-no-gam would otherwise pass for a preset of its own name (a manifest, a report's row)."""
    with pytest.raises(ValueError, match="^preset 'edge-no-gam-no-gam': no-gam given twice$"):
        get_preset("edge-no-gam-no-gam")


def test_the_lidar_rows_preset_of_the_shipped_camera_model_is_edge() -> None:
    """edge-split-near35 without its pseudo points' channels and range: the LiDAR rows' edge, max_depth and all."""
    assert lidar_only(get_preset("edge-split-near35")) == PRESETS["edge"]


def test_a_manifest_preset_with_a_field_this_version_lacks_is_a_value_error() -> None:
    """A newer exporter's preset field: one ValueError naming the mismatch (the Detector's load says it in one
    line), not a TypeError from a dataclass."""
    config = PRESETS["tiny"].to_dict()
    config["depth"]["new_field"] = 1
    with pytest.raises(ValueError, match=r"does not match this version of lowres3d .*'new_field'"):
        preset_from_dict(config)


@pytest.mark.parametrize("name", sorted(PRESETS) + [f"{base}{suffix}" for base in sorted(PRESETS) for suffix in ABLATIONS])
def test_each_presets_grid_and_depth_input_fit_its_networks(name: str) -> None:
    """Every registered preset and ablation keeps the rules check_preset holds a preset to (its docstring; a
    file's preset is held to them too, tests/test_preset_files.py): a whole number of PIXOR's output cells, of
    height slices, the depth input the crop scaled by input_scale, an odd prefill kernel."""
    check_preset(registered_preset(name))


def test_a_grid_range_a_hair_under_whole_cells_in_floats_keeps_its_last_cell() -> None:
    """30.4 / 0.1 is 303.99999999999994 in floats: the grid still has 304 columns, not 303 (0.1 m short)."""
    assert BevGrid(x_max=30.4, cell=0.1).nx == 304


# --------------------------------------------------------------------------- pipeline/cpu.py


def test_a_cpu_quota_is_rounded_to_the_nearest_whole_cpu(tmp_path: Path, monkeypatch) -> None:
    """1.5 CPUs of quota on an 8-CPU host: two threads' worth, not one (the host's mask is the kernel's answer
    on the 8-CPU machine this stands for)."""
    (tmp_path / "cpu.max").write_text("150000 100000\n")
    monkeypatch.setattr(cpu, "CGROUP", tmp_path)
    monkeypatch.setattr(cpu.os, "sched_getaffinity", lambda pid: set(range(8)))
    assert cpu.usable_cpus() == 2
    (tmp_path / "cpu.max").write_text("140000 100000\n")
    assert cpu.usable_cpus() == 1


def test_int8_pair_sums_never_saturate_off_x86(monkeypatch) -> None:
    """An Arm CPU (the Jetson's) has no VNNI flag and no VPMADDUBSW either: its int8 dot products do not saturate."""
    monkeypatch.setattr(cpu.platform, "machine", lambda: "aarch64")
    assert not cpu.is_x86() and not cpu.int8_pairs_saturate(frozenset({"asimd", "asimddp"}))


def test_a_reports_cpu_label_names_the_generation_only_when_recorded() -> None:
    """A report from before the generation was recorded (or off x86) heads with the model name alone."""
    assert cpu.cpu_label({"cpu": "AMD EPYC", "cpu_generation": "family 25 model 17"}) == "AMD EPYC, family 25 model 17"
    assert cpu.cpu_label({"cpu": "AMD EPYC", "cpu_generation": None}) == "AMD EPYC"
    assert cpu.cpu_label({"cpu": "AMD EPYC"}) == "AMD EPYC"
