"""An HDL-64E-like scanner: 64 lasers × 2000 firings per revolution, ray-cast into the scene.

Returns are lost beyond the range a target's brightness allows (range grows with
the square root of reflectivity × incidence cosine), at grazing incidence and at
random; ranges get Gaussian noise (more on foliage and glass). Points are
written like KITTI's: ring after ring (lasers top to bottom), azimuth
``atan2(y, x)`` increasing through each ring from -180° to +180°, so every ring
ends in exactly one azimuth wrap and ring recovery finds 64 rings.
"""

from __future__ import annotations

import numpy as np

from simulation.constants import (
    HDL64_ELEVATIONS_DEG,
    LIDAR_AZIMUTH_JITTER_DEG,
    LIDAR_COLUMNS,
    LIDAR_DROPOUT,
    LIDAR_ELEVATION_JITTER_DEG,
    LIDAR_GRAZING_COS,
    LIDAR_MAX_RANGE,
    LIDAR_MIN_RANGE,
    LIDAR_RANGE_NOISE,
    LIDAR_REFERENCE_ALBEDO,
)
from simulation.raycast import GROUND, SKY, LidarGrid, cast
from simulation.scene import Scene
from simulation.surfaces import surface

# One physical sensor for every frame: its per-laser calibration residuals come from a fixed seed.
_SENSOR_SEED = 64


def sensor_elevations() -> np.ndarray:
    """(64,) laser elevations in radians, top laser first, with this sensor's small residuals."""
    residual = np.random.default_rng(_SENSOR_SEED).normal(0, LIDAR_ELEVATION_JITTER_DEG, HDL64_ELEVATIONS_DEG.size)
    return np.radians(HDL64_ELEVATIONS_DEG + residual)


def build_grid(rng: np.random.Generator) -> LidarGrid:
    """The rays of one revolution; firing times jitter a little in azimuth from frame to frame."""
    elevation = sensor_elevations()
    step = 2 * np.pi / LIDAR_COLUMNS
    azimuth0 = -np.pi + step / 2
    jitter = rng.normal(0, np.radians(LIDAR_AZIMUTH_JITTER_DEG), (elevation.size, LIDAR_COLUMNS))
    azimuth = azimuth0 + step * np.arange(LIDAR_COLUMNS)[None, :] + np.clip(jitter, -step / 3, step / 3)
    ce = np.cos(elevation)[:, None]
    dirs = np.stack([ce * np.cos(azimuth), ce * np.sin(azimuth),
                     np.broadcast_to(np.sin(elevation)[:, None], azimuth.shape)], axis=-1)
    return LidarGrid(origin=np.zeros(3), dirs=dirs, elevation=elevation, azimuth0=azimuth0, step=step)


def scan(scene: Scene, rng: np.random.Generator) -> np.ndarray:
    """One KITTI-style scan of the scene: float32 (N, 4) ``x, y, z, reflectance`` in ring order."""
    grid = build_grid(rng)
    result = cast(scene, grid)
    t, prim = result.t.ravel(), result.prim.ravel()
    dirs = grid.dirs.reshape(-1, 3)
    candidate = np.flatnonzero((prim != SKY) & (t >= LIDAR_MIN_RANGE) & (t <= LIDAR_MAX_RANGE))
    t, prim, dirs = t[candidate], prim[candidate], dirs[candidate]
    hits = dirs * t[:, None]
    surf = surface(scene, prim, hits, GROUND)
    cos_inc = np.abs(np.einsum("ij,ij->i", surf.normal, dirs))
    # Detection range scales with sqrt(reflected power): dark or oblique targets vanish sooner.
    # Diffuse surfaces still scatter some light back at oblique incidence, hence the 0.3 floor.
    power = surf.albedo * (0.3 + 0.7 * cos_inc) / LIDAR_REFERENCE_ALBEDO
    reach = LIDAR_MAX_RANGE * np.sqrt(np.clip(power, 0, 1))
    keep = (t <= reach) & (rng.random(t.size) >= LIDAR_DROPOUT)
    keep &= (cos_inc >= LIDAR_GRAZING_COS) | (rng.random(t.size) < 0.2)
    sigma = LIDAR_RANGE_NOISE + surf.range_noise
    measured = t + rng.normal(0, 1, t.size) * sigma
    reflectance = surf.albedo * (0.35 + 0.65 * cos_inc) + rng.normal(0, 0.03, t.size)
    reflectance = np.round(np.clip(reflectance, 0.0, 0.99), 2)  # KITTI stores two decimals
    points = np.column_stack([dirs * measured[:, None], reflectance])[keep]
    # candidate indices are row-major over (laser, firing): already ring after ring, azimuth ascending.
    return points.astype(np.float32)
