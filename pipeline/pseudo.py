"""Pseudo point cloud: a dense depth map back-projected into the LiDAR frame.

Pseudo points carry reflectance 0: the camera measures none, and 0 keeps the
BEV reflectance channel meaning "mean reflectance of real returns, diluted by
pseudo points", the same at training and at inference. When the real 16-line
points are merged in they keep their measured reflectance.
"""

from __future__ import annotations

import numpy as np

from pipeline.calib import Calibration


def pixel_rays(calib: Calibration, height: int, width: int, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel rays in the LiDAR frame: point(u, v, d) = d · ray[v, u] + origin, exactly.

    Back-projection is affine in depth: X_rect = d·K⁻¹[u, v, 1]ᵀ − K⁻¹t with
    P2 = [K | t], then X_velo = A·X_rect + b. Returns float32 rays
    (3, H/stride, W/stride) and the float64 origin (3,).
    """
    k_inv = np.linalg.inv(calib.P2[:, :3])
    to_velo = calib.rect_to_velo_matrix
    direction = to_velo[:3, :3] @ k_inv  # columns: d/du, d/dv, constant
    origin = to_velo[:3, 3] - to_velo[:3, :3] @ (k_inv @ calib.P2[:, 3])
    u = np.arange(0, width, stride, dtype=np.float64)
    v = np.arange(0, height, stride, dtype=np.float64)
    rays = (
        direction[:, 0, None, None] * u[None, None, :]
        + direction[:, 1, None, None] * v[None, :, None]
        + direction[:, 2, None, None]
    )
    return rays.astype(np.float32), origin


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
    sub = np.asarray(depth, np.float32)[::stride, ::stride]
    rays, origin = pixel_rays(calib, depth.shape[0], depth.shape[1], stride)
    valid = (sub >= min_depth) & (sub <= max_depth)
    if max_height is not None:
        # z = d·ray_z + origin_z ≤ max_height, tested before any point is built.
        valid &= sub * rays[2] + np.float32(origin[2]) <= max_height
    index = np.flatnonzero(valid)
    d = sub.reshape(-1)[index]
    points = np.zeros((index.size, 4), dtype=np.float32)
    for axis in range(3):  # three coordinates, each one vectorized multiply-add
        points[:, axis] = d * rays[axis].reshape(-1)[index] + np.float32(origin[axis])
    return points


def merge_points(pseudo: np.ndarray, lidar: np.ndarray) -> np.ndarray:
    """Pseudo points followed by the real LiDAR points (both (N, 4) float32)."""
    return np.concatenate([pseudo.astype(np.float32, copy=False), lidar.astype(np.float32, copy=False)])
