"""Pseudo point cloud: a dense depth map back-projected into the LiDAR frame.

Pseudo points carry reflectance 0: the camera measures none, and 0 keeps the
BEV reflectance channel meaning "mean reflectance of real returns, diluted by
pseudo points", the same at training and at inference. When the real 16-line
points are merged in they keep their measured reflectance.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.calib import Calibration
from pipeline.presets import BevGrid


def pixel_rays(calib: Calibration, height: int, width: int, stride: int = 1,
               scale: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel rays in the LiDAR frame: point(u, v, d) = d · ray[v, u] + origin, exactly.

    Back-projection is affine in depth: X_rect = d·K⁻¹[u, v, 1]ᵀ − K⁻¹t with
    P2 = [K | t], then X_velo = A·X_rect + b. Returns float32 rays
    (3, H/stride, W/stride) and the float64 origin (3,). scale multiplies each
    axis (x, y, z) of both before the one rounding (the BEV's bin units: 1 / cell).
    """
    k_inv = np.linalg.inv(calib.P2[:, :3])
    to_velo = calib.rect_to_velo_matrix
    factor = np.asarray(scale, np.float64)
    direction = factor[:, None] * (to_velo[:3, :3] @ k_inv)  # columns: d/du, d/dv, constant
    origin = factor * (to_velo[:3, 3] - to_velo[:3, :3] @ (k_inv @ calib.P2[:, 3]))
    u = np.arange(0, width, stride, dtype=np.float64)
    v = np.arange(0, height, stride, dtype=np.float64)
    # ray = d/du·u + d/dv·v + constant, per axis: an outer sum of a column term and a row term that
    # holds the constant, in float64 and rounded once to float32 as it is written. A frame with a new
    # calibration pays this (synthetic frames all have their own), so it is one full-size pass per axis
    # (two passes, the outer sum and then the constant, took 0.42 ms against 0.34; equal on 3.2 million rays).
    rays = np.empty((3, v.size, u.size), dtype=np.float32)
    for axis in range(3):
        np.add((direction[axis, 1] * v)[:, None], direction[axis, 0] * u + direction[axis, 2], out=rays[axis],
               casting="same_kind")
    return rays, origin


@dataclass(frozen=True)
class RayTable:
    """Rays of every (strided) pixel of one view, flattened: point = d · rays[:, i] + origin."""

    rays: np.ndarray  # float32 (3, H·W / stride²)
    origin: np.ndarray  # float32 (3,)
    shape: tuple[int, int]  # (H, W) of the depth map the table is for (before striding)
    stride: int


_TABLES: OrderedDict[tuple, RayTable] = OrderedDict()
_TABLES_MAX = 16  # a deployment sees one or a few calibrations; KITTI one per drive
# One Detector serves several threads (each with a stage thread that builds the tables beside the depth net),
# and every Detector of a process shares this cache: it is changed under a lock, as calib's _PASSED is.
_TABLES_LOCK = threading.Lock()


def _cached(key: tuple, build: Callable[[], RayTable]) -> RayTable:
    """The table under key, built on first use (least recently built dropped past _TABLES_MAX)."""
    table = _TABLES.get(key)
    if table is None:
        table = build()  # outside the lock: a racing thread may build the same table, equal, harmless
        with _TABLES_LOCK:  # two threads trimming at once could pop one entry too many, or from an empty dict
            _TABLES[key] = table
            while len(_TABLES) > _TABLES_MAX:
                _TABLES.popitem(last=False)
    return table


def _calibration_key(calib: Calibration, height: int, width: int, stride: int) -> tuple:
    return (calib.P2.tobytes(), calib.R0_rect.tobytes(), calib.Tr_velo_to_cam.tobytes(), height, width, stride)


def ray_table(calib: Calibration, height: int, width: int, stride: int = 1) -> RayTable:
    """:func:`pixel_rays` of a view, cached by calibration (a frame's rays cost more than using them)."""
    def build() -> RayTable:
        rays, origin = pixel_rays(calib, height, width, stride)
        return RayTable(np.ascontiguousarray(rays.reshape(3, -1)), origin.astype(np.float32), (height, width), stride)

    return _cached(("rays", *_calibration_key(calib, height, width, stride)), build)


def bin_rays(calib: Calibration, height: int, width: int, stride: int, grid: BevGrid) -> RayTable:
    """The rays of :func:`ray_table` in the BEV's bin units: bin coordinate = d · rays[:, i] + origin.

    origin here is ``(origin − (x_min, y_min, z_min)) / cell`` per axis; built
    from the calibration in float64 and rounded once, cached like the rays.
    """
    def build() -> RayTable:
        scale = (1 / grid.cell, 1 / grid.cell, 1 / grid.z_cell)
        rays, origin = pixel_rays(calib, height, width, stride, scale)
        low = np.array([grid.x_min, grid.y_min, grid.z_min]) * np.asarray(scale)
        return RayTable(np.ascontiguousarray(rays.reshape(3, -1)), (origin - low).astype(np.float32),
                        (height, width), stride)

    return _cached(("bins", grid, *_calibration_key(calib, height, width, stride)), build)


def pseudo_xyz(
    depth: np.ndarray,
    calib: Calibration,
    min_depth: float,
    max_depth: float,
    stride: int = 1,
    max_height: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Back-project an (H, W) depth map (metres, camera 2 projective depth) → float32 x, y, z arrays.

    calib: the calibration of this exact depth map (cropped and scaled as the
    map is). stride keeps every k-th row and column. Pixels outside
    [min_depth, max_depth] are dropped, and with max_height points higher than
    that above the LiDAR (sky, tree tops: no cars up there). The depths have
    no defaults: the preset's ``pseudo_limits`` give them (its models were
    trained on what those keep). Three separate
    arrays, not an (N, 3) block: the voxelizer reads them column by column.
    """
    table = ray_table(calib, depth.shape[0], depth.shape[1], stride)
    d = np.asarray(depth, np.float32)[::stride, ::stride].reshape(-1)
    valid = (d >= min_depth) & (d <= max_depth)
    if max_height is not None:
        # z = d·ray_z + origin_z ≤ max_height, tested before any point is built.
        valid &= d * table.rays[2] + table.origin[2] <= max_height
    index = np.flatnonzero(valid)
    d = d[index]
    return tuple(d * table.rays[axis][index] + table.origin[axis] for axis in range(3))


_CROSS = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))


def depth_jumps(depth: np.ndarray, max_jump: float) -> np.ndarray:
    """Pixels of an (H, W) depth map whose depth differs from a 4-neighbour's by more than max_jump × their own.

    These are the pixels on either side of a depth edge, and the pixels a
    completion network smears across it: back-projected, they float between a
    car and what is behind it. The largest difference to a neighbour is the
    larger of (3×3 cross maximum − d) and (d − cross minimum); borders compare
    only with neighbours inside the map.
    """
    d = np.asarray(depth, np.float32)
    with np.errstate(invalid="ignore", over="ignore"):  # inf − inf and NaN are not jumps (and not depths)
        above: np.ndarray = cv2.dilate(d, _CROSS)
        above -= d
        below = d - cv2.erode(d, _CROSS)
        np.maximum(above, below, out=above)
        return above > np.float32(max_jump) * d


def depth_to_points(
    depth: np.ndarray,
    calib: Calibration,
    min_depth: float,
    max_depth: float,
    stride: int = 1,
    max_height: float | None = None,
) -> np.ndarray:
    """:func:`pseudo_xyz` as float32 (N, 4) points with reflectance 0."""
    return xyz_to_points(*pseudo_xyz(depth, calib, min_depth, max_depth, stride, max_height))


def xyz_to_points(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Coordinate arrays → float32 (N, 4) points with reflectance 0 (the camera measures none)."""
    points = np.zeros((x.size, 4), dtype=np.float32)
    points[:, 0], points[:, 1], points[:, 2] = x, y, z
    return points


def merge_points(pseudo: np.ndarray, lidar: np.ndarray) -> np.ndarray:
    """Pseudo points followed by the real LiDAR points (both (N, 4) float32)."""
    return np.concatenate([pseudo.astype(np.float32, copy=False), lidar.astype(np.float32, copy=False)])
