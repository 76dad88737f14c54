"""Pseudo point cloud: a dense depth map back-projected into the LiDAR frame.

Pseudo points carry reflectance 0: the camera measures none, and 0 keeps the
BEV reflectance channel meaning "mean reflectance of real returns, diluted by
pseudo points", the same at training and at inference. When the real 16-line
points are merged in they keep their measured reflectance.
"""

from __future__ import annotations

import numpy as np

from pipeline.calib import Calibration


def depth_to_points(
    depth: np.ndarray,
    calib: Calibration,
    min_depth: float = 0.9,
    max_depth: float = 80.0,
    stride: int = 1,
    max_height: float | None = None,
) -> np.ndarray:
    """Back-project an (H, W) depth map (metres, camera 2 projective depth) → float32 (N, 4) points.

    calib: the calibration of this exact depth map (cropped and scaled as the
    map is). stride keeps every k-th row and column. Pixels outside
    [min_depth, max_depth] are dropped, and with max_height points higher than
    that above the LiDAR (sky, tree tops: no cars up there).
    """
    depth = np.asarray(depth)
    sub = depth[::stride, ::stride]
    rows, cols = np.nonzero((sub >= min_depth) & (sub <= max_depth))
    d = sub[rows, cols]
    xyz = calib.image_to_velo(cols * stride, rows * stride, d)
    if max_height is not None:
        xyz = xyz[xyz[:, 2] <= max_height]
    points = np.zeros((xyz.shape[0], 4), dtype=np.float32)
    points[:, :3] = xyz
    return points


def merge_points(pseudo: np.ndarray, lidar: np.ndarray) -> np.ndarray:
    """Pseudo points followed by the real LiDAR points (both (N, 4) float32)."""
    return np.concatenate([pseudo.astype(np.float32, copy=False), lidar.astype(np.float32, copy=False)])
