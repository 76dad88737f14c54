"""A frame: what one detection runs on, loaded from a KITTI object layout folder or a KITTI raw drive."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.calib import Calibration
from pipeline.errors import InputError
from pipeline.kitti import (
    Object3D,
    read_calib,
    read_image,
    read_image_size,
    read_labels,
    read_raw_calib,
    read_text_file,
    read_velodyne,
)

# KITTI raw data: a drive folder (``2011_09_26_drive_0005_sync``) holds its frames as
# ``image_02/data/<10 digits>.png`` and ``velodyne_points/data/<10 digits>.bin``; the drive's one
# calibration lies in the date folder above it (``2011_09_26/calib_*.txt``).
DRIVE_IMAGES = Path("image_02") / "data"
DRIVE_SCANS = Path("velodyne_points") / "data"
RAW_CALIB_FILES = ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt")
KITTI_ID_DIGITS = 6  # an object folder's frame ids: 000000 … 007480


@dataclass
class Frame:
    """Camera image, LiDAR scan and calibration of one moment.

    image: uint8 RGB (H, W, 3), or None when loaded without pixels (then
    ``size_hw`` holds its size). points: float32 (N, 4) velodyne points.
    labels: ground truth when the dataset has it. dropped_nonfinite: points
    removed on load because a value was NaN or infinite.
    """

    frame_id: str
    image: np.ndarray | None
    points: np.ndarray
    calib: Calibration
    labels: list[Object3D] | None = None
    dropped_nonfinite: int = 0
    size_hw: tuple[int, int] | None = None

    @property
    def image_hw(self) -> tuple[int, int] | None:
        """(rows, columns) of the image, or ``size_hw`` without one (None when neither is known)."""
        if self.image is None:
            return self.size_hw
        return (int(self.image.shape[0]), int(self.image.shape[1]))


def read_split_file(path: str | Path) -> list[str]:
    """Frame ids, one per line (e.g. ``000123``), as in the ImageSets ``val.txt`` of Qian/Chen et al."""
    path = Path(path)
    text = read_text_file(path, "split file")
    ids: list[str] = []
    first_line: dict[str, int] = {}
    for line_no, line in enumerate(text.splitlines(), start=1):
        frame_id = line.strip()
        if not frame_id or frame_id.startswith("#"):  # blank lines and comments
            continue
        if len(frame_id.split()) > 1:
            raise InputError(f"{path}, line {line_no}: {frame_id[:40]!r} is not a frame id (one id per line)")
        if frame_id in first_line:  # it would count the frame twice in an evaluation or an epoch
            raise InputError(f"{path}, line {line_no}: frame {frame_id} listed twice (first on line "
                             f"{first_line[frame_id]})")
        first_line[frame_id] = line_no
        ids.append(frame_id)
    if not ids:
        raise InputError(f"{path}: split file lists no frame ids")
    return ids


def numbered_frame(data_dir: str | Path, frame: str) -> str:
    """``--frame`` as the id of a scan in ``data_dir``/velodyne: as given, or a plain number with the zeros KITTI
    names its frames with (``6`` → ``000006``), as ``pipeline.detect --frame`` takes it."""
    velodyne = Path(data_dir) / "velodyne"
    if frame.isdigit() and not (velodyne / f"{frame}.bin").is_file():
        padded = frame.zfill(KITTI_ID_DIGITS)
        if (velodyne / f"{padded}.bin").is_file():
            return padded
    return frame


def frame_ids(data_dir: str | Path, split_file: str | Path | None = None) -> list[str]:
    """Frame ids of a KITTI object folder: from a split file (one id per line) or the velodyne folder."""
    data_dir = Path(data_dir)
    if split_file is not None:
        return read_split_file(split_file)
    if not data_dir.exists():
        raise InputError(f"{data_dir}: no such folder")
    velodyne = data_dir / "velodyne"
    if not velodyne.is_dir():
        raise InputError(f"{data_dir}: not a KITTI object folder (no velodyne/ inside){_object_folder_hint(data_dir)}")
    return sorted(p.stem for p in velodyne.glob("*.bin"))


def _object_folder_hint(folder: Path) -> str:
    """For a --data folder without velodyne/: what it is instead, when it is a folder people pass by mistake."""
    if (folder / DRIVE_SCANS).is_dir():
        return "; it is a KITTI raw drive: give it with --drive"
    splits = [name for name in ("training", "testing") if (folder / name / "velodyne").is_dir()]
    if splits:
        return f"; give its {' or '.join(f'{name}/' for name in splits)} folder"
    if folder.name in ("velodyne", "image_2", "calib", "label_2"):
        return f"; give the folder that holds {folder.name}/: {folder.parent}"
    return ""


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")  # KITTI's PNG first; a camera recorder's JPEGs read as well


def frame_image_path(data_dir: str | Path, frame_id: str) -> Path:
    """``image_2/ID.png``, else the frame's JPEG (``.jpg``, ``.jpeg``) when only that exists, each suffix in
    lower or upper case; an InputError naming what was looked for when there is none."""
    folder = Path(data_dir) / "image_2"
    for suffix in IMAGE_SUFFIXES:
        for spelt in (suffix, suffix.upper()):  # cameras and Windows tools write .JPG (detect counts it an image)
            path = folder / f"{frame_id}{spelt}"
            if path.is_file():
                return path
    raise InputError(f"{folder / (frame_id + '.png')}: no image for frame {frame_id} (nor {frame_id}.jpg or "
                     f"{frame_id}.jpeg)")


def load_frame(data_dir: str | Path, frame_id: str, with_labels: bool = True, with_image: bool = True) -> Frame:
    """Load ``image_2/ID.png`` (or ``.jpg``), ``velodyne/ID.bin``, ``calib/ID.txt`` (and ``label_2/ID.txt`` if present).

    ``with_image=False`` reads only the image's size (LiDAR-side training samples need no pixels).
    """
    data_dir = Path(data_dir)
    scan = read_velodyne(data_dir / "velodyne" / f"{frame_id}.bin")
    label_path = data_dir / "label_2" / f"{frame_id}.txt"
    image_path = frame_image_path(data_dir, frame_id)
    return Frame(
        frame_id=frame_id,
        image=read_image(image_path) if with_image else None,
        size_hw=None if with_image else read_image_size(image_path),
        points=scan.points,
        calib=read_calib(data_dir / "calib" / f"{frame_id}.txt"),
        labels=read_labels(label_path) if with_labels and label_path.exists() else None,
        dropped_nonfinite=scan.dropped_nonfinite,
    )


def drive_frame_ids(drive: str | Path) -> list[str]:
    """Frame ids of a KITTI raw drive folder: the names of its ``velodyne_points/data/*.bin`` scans (the folder
    and its images checked, with a hint for the folders people pass by mistake)."""
    drive = Path(drive)
    if not drive.exists():
        raise InputError(f"{drive}: no such folder")
    scans = drive / DRIVE_SCANS
    if not scans.is_dir():
        drives = sorted(p.name for p in drive.glob("*_drive_*_sync") if (p / DRIVE_SCANS).is_dir())
        hint = f"; the drives in it: {', '.join(drives[:5])}{' …' if len(drives) > 5 else ''}" if drives else ""
        if (drive / "velodyne").is_dir():
            hint = "; it is a KITTI object folder: give it with --data"
        raise InputError(f"{drive}: not a KITTI raw drive folder (no {DRIVE_SCANS}/ inside){hint}")
    if not any(scans.glob("*.bin")) and any(scans.glob("*.txt")):
        raise InputError(f"{drive}: its scans are text files (KITTI's unsynced '_extract' download); use the "
                         "'_sync' drive, whose scans are .bin files")
    if not (drive / DRIVE_IMAGES).is_dir():
        raise InputError(f"{drive}: no {DRIVE_IMAGES}/ (the left colour camera's images) inside")
    return sorted(p.stem for p in scans.glob("*.bin"))


class CalibrationNotFound(InputError):
    """A drive's calibration files are in neither its folder nor the one above (they may be optional there)."""


def read_drive_calib(drive: str | Path) -> Calibration:
    """A raw drive's calibration, from ``calib_cam_to_cam.txt`` and ``calib_velo_to_cam.txt``, each looked for in
    the drive folder, then in the date folder above it (where KITTI's raw downloads put them): above the path
    as given (``..`` folded, links kept), then above the real folder it leads to."""
    given = Path(os.path.abspath(drive))
    real = given.resolve()
    folders = list(dict.fromkeys((given, given.parent, real, real.parent)))  # in order, each once
    paths = []
    for name in RAW_CALIB_FILES:
        found = next((folder / name for folder in folders if (folder / name).is_file()), None)
        if found is None:
            raise CalibrationNotFound(f"{given}: no {name} in it or in {given.parent}"
                             f"{f' (nor in {real} or {real.parent})' if real != given else ''}; KITTI raw keeps "
                             "the calibration files in the date folder above the drive")
        paths.append(found)
    return read_raw_calib(*paths)


def load_drive_frame(drive: str | Path, frame_id: str, calib: Calibration) -> Frame:
    """Load ``image_02/data/ID.png`` and ``velodyne_points/data/ID.bin`` of a raw drive (no labels)."""
    drive = Path(drive)
    scan = read_velodyne(drive / DRIVE_SCANS / f"{frame_id}.bin")
    return Frame(frame_id=frame_id, image=read_image(drive / DRIVE_IMAGES / f"{frame_id}.png"), points=scan.points,
                 calib=calib, dropped_nonfinite=scan.dropped_nonfinite)
