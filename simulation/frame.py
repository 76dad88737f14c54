"""One synthetic frame: generate it from (seed, index) and write it in the KITTI object layout.

Layout under the output folder (KITTI's ``training/`` folder plus dense depth):
``image_2/NNNNNN.png``, ``velodyne/NNNNNN.bin``, ``calib/NNNNNN.txt``,
``label_2/NNNNNN.txt`` and ``depth_2/NNNNNN.png`` (KITTI depth PNG: uint16,
metres × 256, 0 = sky or beyond MAX_DEPTH_GT).

A frame's files appear whole or not at all: they are written into a hidden
scratch folder under the output folder, then renamed into place, depth_2 last.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline.calib import Calibration
from pipeline.kitti import Object3D, write_calib, write_depth_png, write_labels, write_velodyne
from simulation.camera import Render, render, sample_calibration
from simulation.labels import label_objects
from simulation.layout import generate_scene
from simulation.lidar import scan
from simulation.scene import Scene

SUBDIRS = ("image_2", "velodyne", "calib", "label_2", "depth_2")
# A frame's files, in the order they are put in place: depth_2 last, so a frame with its depth map is whole.
FRAME_FILES = (("image_2", ".png"), ("velodyne", ".bin"), ("calib", ".txt"), ("label_2", ".txt"), ("depth_2", ".png"))
SCRATCH_PREFIX = ".partial-"  # + frame id + "-": hidden, so KITTI readers and globs of the sub-folders skip it


@dataclass
class Frame:
    """Everything generated for one frame; ``scene`` and ``render`` are written to no file: they are kept for
    callers of :func:`generate_frame` that check the labels against the scene (the tests; docs/simulation.md).

    points: float32 (N, 4) ring-ordered scan. image: uint8 (375, 1242, 3) RGB.
    depth: float32 (375, 1242) metres, 0 = none.
    """

    index: int
    calib: Calibration
    points: np.ndarray
    image: np.ndarray
    depth: np.ndarray
    objects: list[Object3D]
    scene: Scene
    render: Render


def frame_rngs(seed: int, index: int) -> dict[str, np.random.Generator]:
    """Independent generators for each part of frame ``index`` of run ``seed``.

    Derived from (seed, index) alone, so a frame does not depend on which worker
    made it or how many frames came before; separate streams keep, e.g., the
    scene unchanged when the LiDAR model's use of randomness changes.
    """
    children = np.random.SeedSequence([seed, index]).spawn(4)
    return {name: np.random.default_rng(ss) for name, ss in zip(("scene", "calib", "lidar", "camera"), children)}


def generate_frame(seed: int, index: int) -> Frame:
    """Generate frame ``index`` of the run with seed ``seed``."""
    rngs = frame_rngs(seed, index)
    scene = generate_scene(rngs["scene"])
    calib = sample_calibration(rngs["calib"])
    points = scan(scene, rngs["lidar"])
    shot = render(scene, calib, rngs["camera"])
    objects = label_objects(scene, shot, calib)
    return Frame(index, calib, points, shot.image, shot.depth, objects, scene, shot)


def frame_name(index: int) -> str:
    """KITTI's six-digit frame id."""
    return f"{index:06d}"


def scratch_prefix(index: int) -> str:
    """Name prefix of the scratch folders in which frame ``index`` is written before its files are put in place."""
    return f"{SCRATCH_PREFIX}{frame_name(index)}-"


def _write_png(path: Path, rgb: np.ndarray) -> None:
    """The camera image as PNG: the bytes of cv2.imwrite (pipeline.kitti.write_image), but written with Python's
    own file calls, so that a full disk raises OSError (ENOSPC) instead of imwrite's bare False."""
    encoded, png = cv2.imencode(".png", cv2.cvtColor(np.asarray(rgb, np.uint8), cv2.COLOR_RGB2BGR))
    if not encoded:
        raise ValueError(f"{path}: could not encode the image as PNG")
    path.write_bytes(png.tobytes())


def write_frame(out: Path, frame: Frame) -> None:
    """Write a frame's five files under ``out`` (sub-folders must exist), each whole or not at all.

    All five are written into a scratch folder in ``out`` (same file system, so the renames are atomic) and then
    renamed into place, depth_2 last: a run killed or out of disk space mid-frame leaves no cut-off file that a
    reader would take for a finished one (a cut-off scan of whole rows reads as a valid, shorter scan).
    """
    name = frame_name(frame.index)
    scratch = Path(tempfile.mkdtemp(prefix=scratch_prefix(frame.index), dir=out))
    try:
        for sub in SUBDIRS:
            (scratch / sub).mkdir()
        _write_png(scratch / "image_2" / f"{name}.png", frame.image)
        write_velodyne(scratch / "velodyne" / f"{name}.bin", frame.points)
        write_calib(scratch / "calib" / f"{name}.txt", frame.calib)
        write_labels(scratch / "label_2" / f"{name}.txt", frame.objects)
        write_depth_png(scratch / "depth_2" / f"{name}.png", frame.depth)
        for sub, ext in FRAME_FILES:
            os.replace(scratch / sub / f"{name}{ext}", out / sub / f"{name}{ext}")
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
