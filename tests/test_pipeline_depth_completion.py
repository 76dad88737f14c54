"""A depth-completion drive in the flat layout (pipeline/depth_completion.py): which folders make one, its frames,
and where its raw scans may lie."""

import random
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.calib import sparse_depth_map
from pipeline.depth_completion import (
    check_drive_folder,
    drive_calibration,
    drive_frame_ids,
    is_drive_folder,
    raw_scan_path,
    read_frame,
)
from pipeline.errors import InputError
from pipeline.frame import load_frame
from pipeline.kitti import read_depth_png, write_depth_png
from tests.conftest import KITTI


def test_a_drive_needs_both_velodyne_raw_and_groundtruth(tmp_path):
    """One of the two folders alone is no drive (a half-linked one is refused by name, not read as empty)."""
    for present in (("velodyne_raw",), ("groundtruth",), ("velodyne_raw", "groundtruth")):
        drive = tmp_path / "_".join(present)
        for name in present:
            (drive / name).mkdir(parents=True)
        assert is_drive_folder(drive) == (len(present) == 2)
        if len(present) == 1:
            with pytest.raises(InputError, match=rf"--data {drive}: not a depth-completion drive \(no velodyne_raw/"):
                check_drive_folder(drive)
    official = tmp_path / "train" / "2011_09_26_drive_0001_sync" / "proj_depth"
    (official / "velodyne_raw" / "image_02").mkdir(parents=True)
    with pytest.raises(InputError, match=r"proj_depth: KITTI's depth-completion layout, one drive at a time"):
        check_drive_folder(official)  # the proj_depth folder itself, given for the drive


def test_frames_are_the_ground_truth_pngs_in_order(make_drive):
    """A drive's frames are its groundtruth/ PNGs by name, in frame order whatever order the folder lists them in;
    other files there are not frames."""
    ids = [f"{i:010d}" for i in range(0, 60, 5)]
    shuffled = random.Random(4).sample(ids, len(ids))
    drive = make_drive(frame_ids=tuple(shuffled))
    (drive / "groundtruth" / "notes.txt").write_text("not a frame\n")
    assert drive_frame_ids(drive) == ids


def test_a_frame_without_thinning_is_its_files_as_given(make_drive, depth_completion_dir):
    """beams 0 or None: velodyne_raw as given (no calibration needed), ground truth from groundtruth/."""
    drive = make_drive(calib=False)
    for beams in (0, None):
        frame = read_frame(drive, "0000000005", None, beams)
        np.testing.assert_array_equal(frame.sparse,
                                      read_depth_png(depth_completion_dir / "velodyne_raw" / "0000000005.png"))
        np.testing.assert_array_equal(frame.ground_truth,
                                      read_depth_png(depth_completion_dir / "groundtruth" / "0000000005.png"))
    assert np.count_nonzero(frame.ground_truth) > 3 * np.count_nonzero(frame.sparse)  # the two maps, not one twice


def _drive_of_object_frame(drive: Path, frame_id: str, scans: str) -> str:
    """A drive of one real object frame (image, its scan projected as velodyne_raw and groundtruth, the raw
    calibration files) with the scan under ``scans`` (a folder inside the drive); returns the drive frame id."""
    frame = load_frame(KITTI, frame_id)
    name = f"0000{frame_id}"
    for folder in ("image_02", "velodyne_raw", "groundtruth", scans):
        (drive / folder).mkdir(parents=True, exist_ok=True)
    shutil.copy(KITTI / "image_2" / f"{frame_id}.png", drive / "image_02" / f"{name}.png")
    projected = sparse_depth_map(frame.points, frame.calib, frame.image_hw)
    write_depth_png(drive / "velodyne_raw" / f"{name}.png", projected)
    write_depth_png(drive / "groundtruth" / f"{name}.png", projected)
    frame.points.astype(np.float32).tofile(drive / scans / f"{name}.bin")

    def numbers(matrix: np.ndarray) -> str:
        return " ".join(f"{v:.9e}" for v in matrix.ravel())

    calib = frame.calib
    (drive / "calib_cam_to_cam.txt").write_text(f"R_rect_00: {numbers(calib.R0_rect)}\n"
                                                f"P_rect_02: {numbers(calib.P2)}\n")
    (drive / "calib_velo_to_cam.txt").write_text(f"R: {numbers(calib.Tr_velo_to_cam[:, :3])}\n"
                                                 f"T: {numbers(calib.Tr_velo_to_cam[:, 3])}\n")
    return name


def test_raw_scans_under_velodyne_points_data_as_kitti_raw_keeps_them_thin_the_same(tmp_path):
    """A drive whose velodyne_points/ is KITTI raw's own folder (scans in its data/) is thinned from them exactly as
    one with the scans linked straight into velodyne_points/."""
    flat, nested = tmp_path / "flat", tmp_path / "nested"
    name = _drive_of_object_frame(flat, "000003", "velodyne_points")
    _drive_of_object_frame(nested, "000003", "velodyne_points/data")
    assert raw_scan_path(nested, name) == nested / "velodyne_points" / "data" / f"{name}.bin"
    thinned = read_frame(nested, name, drive_calibration(nested)).sparse
    np.testing.assert_array_equal(thinned, read_frame(flat, name, drive_calibration(flat)).sparse)
    whole = read_depth_png(nested / "velodyne_raw" / f"{name}.png")
    assert 0.15 * np.count_nonzero(whole) < np.count_nonzero(thinned) < 0.4 * np.count_nonzero(whole)
