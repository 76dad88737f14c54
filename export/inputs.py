"""Network inputs for the parity check: a real KITTI frame and realistic random inputs (NumPy only).

Real inputs go through the runtime's own preprocessing
(:func:`pipeline.preprocess.depth_inputs`: the KITTI depth-completion crop, a
resize by ``input_scale`` with cv2.INTER_AREA, the sparse depth projected with
the matching calibration) and :func:`pipeline.bev.voxelize_bev` of the frame's
full 64-line scan.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.bev import voxelize_bev
from pipeline.errors import InputError
from pipeline.kitti import read_calib, read_image, read_velodyne
from pipeline.preprocess import depth_inputs
from pipeline.presets import Preset

DEFAULT_KITTI_DIR = Path(__file__).resolve().parents[1] / "tests" / "data" / "kitti" / "training"
DEFAULT_FRAME = "000006"


@dataclass
class NetworkInputs:
    """One set of inputs for both networks.

    rgb: float32 (1, 3, H, W) raw 0–255; sparse_depth: float32 (1, 1, H, W) metres (0 = none);
    bev: float32 (1, C, ny, nx). ``source`` says where they came from.
    """

    rgb: np.ndarray
    sparse_depth: np.ndarray
    bev: np.ndarray
    source: str

    def feeds(self, network: str) -> dict[str, np.ndarray]:
        """The ONNX feeds of ``network`` ("depth" or "pixor")."""
        return {"rgb": self.rgb, "sparse_depth": self.sparse_depth} if network == "depth" else {"bev": self.bev}


def check_frame(kitti_dir: str | Path, frame: str) -> None:
    """Refuse a parity frame that is not in ``kitti_dir`` before any export work (InputError naming the flags)."""
    kitti_dir = Path(kitti_dir)
    if not kitti_dir.is_dir():
        raise InputError(f"--data {kitti_dir}: not a folder (a KITTI object training folder with image_2/, "
                         "velodyne/, calib/)")
    needed = (f"image_2/{frame}.png", f"velodyne/{frame}.bin", f"calib/{frame}.txt")
    missing = [name for name in needed if not (kitti_dir / name).is_file()]
    if missing:
        raise InputError(f"--frame {frame}: not in --data {kitti_dir} (no {', '.join(missing)})")


def kitti_inputs(preset: Preset, kitti_dir: str | Path = DEFAULT_KITTI_DIR, frame: str = DEFAULT_FRAME) -> NetworkInputs:
    """Inputs built from a real KITTI object frame (image_2, velodyne, calib)."""
    kitti_dir = Path(kitti_dir)
    image = read_image(kitti_dir / "image_2" / f"{frame}.png")
    points = read_velodyne(kitti_dir / "velodyne" / f"{frame}.bin").points
    calib = read_calib(kitti_dir / "calib" / f"{frame}.txt")

    depth = depth_inputs(image, points, calib, preset)  # the runtime's own preprocessing
    bev = voxelize_bev(points, preset.bev)
    return NetworkInputs(
        rgb=depth.rgb,
        sparse_depth=depth.sparse_depth.astype(np.float32),
        bev=bev[None].astype(np.float32),
        source=f"KITTI {frame}",
    )


def random_inputs(preset: Preset, seed: int = 0, depth_density: float = 0.05, occupancy: float = 0.02) -> NetworkInputs:
    """Random but realistic inputs: uniform RGB, ~5 % of pixels with 1–80 m depth, sparse BEV occupancy.

    Laid out as the voxelizer's output (pipeline.presets.BevGrid): nz occupancy channels, then a random
    reflectance in the cells they occupy (0 elsewhere), then on a ``split_pseudo`` grid the pseudo points'
    own nz occupancy channels.
    """
    rng = np.random.default_rng(seed)
    height, width = preset.depth.input_hw
    rgb = rng.uniform(0.0, 255.0, (1, 3, height, width)).astype(np.float32)
    has_depth = rng.random((1, 1, height, width)) < depth_density
    sparse = np.where(has_depth, rng.uniform(1.0, 80.0, has_depth.shape), 0.0).astype(np.float32)
    grid = preset.bev
    _, ny, nx = grid.shape
    occupied = (rng.random((grid.nz, ny, nx)) < occupancy).astype(np.float32)
    reflectance = occupied.max(axis=0) * rng.uniform(0.0, 1.0, (ny, nx)).astype(np.float32)
    layers = [occupied, reflectance[None]]
    if grid.split_pseudo:
        layers.append((rng.random((grid.nz, ny, nx)) < occupancy).astype(np.float32))
    bev = np.concatenate(layers, axis=0)[None].astype(np.float32)
    return NetworkInputs(rgb=rgb, sparse_depth=sparse, bev=bev, source=f"random (seed {seed})")
