"""One synthetic frame: generate it from (seed, index) and write it in the KITTI object layout.

Layout under the output folder (KITTI's ``training/`` folder plus dense depth):
``image_2/NNNNNN.png``, ``velodyne/NNNNNN.bin``, ``calib/NNNNNN.txt``,
``label_2/NNNNNN.txt`` and ``depth_2/NNNNNN.png`` (KITTI depth PNG: uint16,
metres × 256, 0 = sky or beyond MAX_DEPTH_GT).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.calib import Calibration
from pipeline.kitti import Object3D, write_calib, write_depth_png, write_image, write_labels, write_velodyne
from simulation.camera import Render, render, sample_calibration
from simulation.labels import label_objects
from simulation.layout import generate_scene
from simulation.lidar import scan
from simulation.scene import Scene

SUBDIRS = ("image_2", "velodyne", "calib", "label_2", "depth_2")


@dataclass
class Frame:
    """Everything generated for one frame; ``scene`` and ``render`` are kept for tests and reports.

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


def write_frame(out: Path, frame: Frame) -> None:
    """Write a frame's five files under ``out`` (sub-folders must exist)."""
    name = frame_name(frame.index)
    write_image(out / "image_2" / f"{name}.png", frame.image)
    write_velodyne(out / "velodyne" / f"{name}.bin", frame.points)
    write_calib(out / "calib" / f"{name}.txt", frame.calib)
    write_labels(out / "label_2" / f"{name}.txt", frame.objects)
    write_depth_png(out / "depth_2" / f"{name}.png", frame.depth)
