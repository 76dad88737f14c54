"""One drive of KITTI depth completion, in the flat layout the evaluation and training read.

A drive folder holds ``image_02/``, ``velodyne_raw/`` and ``groundtruth/`` PNGs named by frame
(``0000000005.png``), the drive's raw-data calibration (``calib_cam_to_cam.txt`` and
``calib_velo_to_cam.txt``) in it or in the folder above, and optionally its raw 64-line scans in
``velodyne_points/`` (``0000000005.bin``, or under ``velodyne_points/data/`` as KITTI raw keeps them).
With the scans the 16-line input is exact (the scan's rings thinned in scan order); without them each
pixel's beam is read from its elevation angle, an approximation (:mod:`pipeline.beams`).

KITTI distributes depth completion as ``train/<drive>/proj_depth/{velodyne_raw,groundtruth}/image_02/``
with the images in the raw drives; :data:`FLAT_LAYOUT_HINT` says how to link one drive into this layout.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.beams import emulate_beams_on_depth_map
from pipeline.calib import Calibration
from pipeline.errors import InputError
from pipeline.frame import CalibrationNotFound, read_drive_calib
from pipeline.kitti import read_depth_png, read_image, read_velodyne

FLAT_LAYOUT_HINT = (
    "link one drive into the flat layout: mkdir DRIVE && ln -s $PWD/train/DRIVE/proj_depth/velodyne_raw/image_02 "
    "DRIVE/velodyne_raw && ln -s $PWD/train/DRIVE/proj_depth/groundtruth/image_02 DRIVE/groundtruth && ln -s "
    "RAW/DATE/DRIVE/image_02/data DRIVE/image_02 && ln -s RAW/DATE/DRIVE/velodyne_points/data DRIVE/velodyne_points "
    "&& ln -s RAW/DATE/calib_*.txt DRIVE/"
)


@dataclass(frozen=True)
class DepthCompletionFrame:
    """image: uint8 RGB (H, W, 3); sparse: the scan's depth map thinned to the requested lines (metres, 0 =
    none); ground_truth: KITTI's semi-dense depth (metres, 0 = none); all of one (H, W)."""

    image: np.ndarray
    sparse: np.ndarray
    ground_truth: np.ndarray


def is_drive_folder(folder: Path) -> bool:
    """Whether ``folder`` is a depth-completion drive in the flat layout."""
    return (Path(folder) / "velodyne_raw").is_dir() and (Path(folder) / "groundtruth").is_dir()


def flat_layout_hint(folder: Path) -> str:
    """:data:`FLAT_LAYOUT_HINT` with the drive's own paths where ``folder`` gives them (a drive's folder in KITTI's
    ``train/`` or ``val/``, its ``proj_depth/``, or the folder holding ``train/``: its first drive as the example);
    the raw data's folder, which KITTI's depth download does not hold, stays RAW."""
    folder = Path(folder).absolute()
    if folder.name == "proj_depth":
        folder = folder.parent
    if not (folder / "proj_depth").is_dir():
        folder = next(iter(sorted((folder / "train").glob("*/proj_depth"))), Path()).parent
    if not (folder / "proj_depth").is_dir():
        return FLAT_LAYOUT_HINT
    name, date = folder.name, folder.name[:10]  # 2011_09_26_drive_0001_sync was recorded on 2011_09_26
    return (f"link one drive into the flat layout: mkdir {name} && ln -s {folder}/proj_depth/velodyne_raw/image_02 "
            f"{name}/velodyne_raw && ln -s {folder}/proj_depth/groundtruth/image_02 {name}/groundtruth && ln -s "
            f"RAW/{date}/{name}/image_02/data {name}/image_02 && ln -s RAW/{date}/{name}/velodyne_points/data "
            f"{name}/velodyne_points && ln -s RAW/{date}/calib_*.txt {name}/ (RAW: where KITTI's raw data is)")


def refuse_kitti_layout(folder: Path, flag: str = "--data") -> None:
    """An InputError with the way to link one drive into the flat layout when ``folder`` is in KITTI's own."""
    folder = Path(folder)
    if (folder / "proj_depth").is_dir() or folder.name == "proj_depth" or (folder / "train").is_dir():
        raise InputError(f"{flag} {folder}: KITTI's depth-completion layout, one drive at a time in the flat one: "
                         f"{flat_layout_hint(folder)}")


def check_drive_folder(folder: Path, flag: str = "--data") -> None:
    """An InputError unless ``folder`` is a drive in the flat layout; KITTI's own layout gets the way to link it."""
    if is_drive_folder(folder):
        return
    refuse_kitti_layout(folder, flag)
    raise InputError(f"{flag} {folder}: not a depth-completion drive (no velodyne_raw/ and groundtruth/ inside)")


def check_map_size(path: Path, map_hw: tuple[int, int], image_path: Path, image_hw: tuple[int, int]) -> None:
    """An InputError naming both files when a depth map's (H, W) is not its image's."""
    if tuple(map_hw) != tuple(image_hw):
        raise InputError(f"{path}: a {map_hw[1]}×{map_hw[0]} depth map for the {image_hw[1]}×{image_hw[0]} image "
                         f"{image_path}; they must be the same size")


def drive_frame_ids(folder: Path) -> list[str]:
    """The frames of a drive folder: those with ground truth."""
    return sorted(path.stem for path in (Path(folder) / "groundtruth").glob("*.png"))


def drive_calibration(folder: Path) -> Calibration | None:
    """The drive's calibration (its raw-data files in the folder or the one above, as ``pipeline.detect --drive``
    looks for them), or None when they are not there; an InputError naming a file that is there but unreadable."""
    try:
        return read_drive_calib(Path(folder))
    except CalibrationNotFound:
        return None


def raw_scan_path(folder: Path, frame_id: str) -> Path | None:
    """The frame's raw 64-line scan in ``velodyne_points/`` (or ``velodyne_points/data/``), or None."""
    for path in (Path(folder) / "velodyne_points" / f"{frame_id}.bin",
                 Path(folder) / "velodyne_points" / "data" / f"{frame_id}.bin"):
        if path.is_file():
            return path
    return None


def has_raw_scans(folder: Path) -> bool:
    """Whether the drive folder has a ``velodyne_points/`` folder of raw scans."""
    return (Path(folder) / "velodyne_points").is_dir()


def read_frame(folder: Path, frame_id: str, calib: Calibration | None, beams: int | None = 16) -> DepthCompletionFrame:
    """One frame of a drive folder, its scan thinned to ``beams`` lines (None or 0: as given, all 64).

    Thinning needs ``calib``; with the frame's raw scan in ``velodyne_points/`` it is exact, otherwise each
    pixel's beam comes from its elevation angle (a drive with ``velodyne_points/`` must have every frame's
    scan). Maps whose size differs from the image's are refused, naming both files.
    """
    folder = Path(folder)
    image_path = folder / "image_02" / f"{frame_id}.png"
    image = read_image(image_path)
    maps = {}
    for name in ("velodyne_raw", "groundtruth"):
        path = folder / name / f"{frame_id}.png"
        depth = read_depth_png(path)
        check_map_size(path, depth.shape, image_path, image.shape[:2])
        maps[name] = depth
    sparse = maps["velodyne_raw"]
    if beams:
        if calib is None:
            raise InputError(f"{folder}: thinning its scans to {beams} lines needs the drive's calibration "
                             "(calib_cam_to_cam.txt and calib_velo_to_cam.txt in it or the folder above)")
        scan_path = raw_scan_path(folder, frame_id)
        if scan_path is None and has_raw_scans(folder):  # one frame approximate among exact ones, unsaid: refused
            raise InputError(f"{folder / 'velodyne_points'}: no raw scan of frame {frame_id} ({frame_id}.bin), "
                             "while the drive's other frames are thinned from theirs")
        scan = read_velodyne(scan_path).points if scan_path is not None else None
        sparse = emulate_beams_on_depth_map(sparse, calib, beams, scan=scan,
                                            source=f"{folder / 'velodyne_raw' / f'{frame_id}.png'} and {scan_path}")
    return DepthCompletionFrame(image=image, sparse=sparse, ground_truth=maps["groundtruth"])
