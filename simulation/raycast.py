"""Cast a grid of rays (camera pixels or LiDAR firings) into a scene, culling primitives per window.

A grid is an (H, W) array of rays sharing one origin. Each primitive is only
tested against the rectangular window of rays that can reach its bounding box
(screen-space rectangle for the camera, elevation rows × azimuth columns for
the LiDAR), which keeps a frame to a few million ray–primitive tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.calib import Calibration
from simulation.constants import MAX_RENDER_DISTANCE, NEAR_PLANE
from simulation.geometry import clip_box_to_near, intersect
from simulation.scene import Scene

SKY = -1  # primitive id of rays that hit nothing
GROUND = -2  # primitive id of ground hits

Window = tuple[slice, slice]


@dataclass
class CameraGrid:
    """Rays through the pixel centres of camera 2; ray parameter = projective depth.

    dirs: float64 (H, W, 3) in the LiDAR frame, origin: (3,) the camera centre.
    """

    calib: Calibration
    origin: np.ndarray
    dirs: np.ndarray

    @classmethod
    def build(cls, calib: Calibration, image_hw: tuple[int, int]) -> CameraGrid:
        """Rays of every pixel of an image of size ``image_hw`` (pixel centres at integer coordinates)."""
        h, w = image_hw
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        # image_to_velo is affine in depth: X(d) = C + d·D, so D = X(1) - X(0) exactly.
        at_zero = calib.image_to_velo(np.zeros(1), np.zeros(1), np.zeros(1))[0]
        ones = np.ones(h * w)
        dirs = calib.image_to_velo(u.ravel(), v.ravel(), ones) - at_zero
        return cls(calib, at_zero, dirs.reshape(h, w, 3))

    @property
    def shape(self) -> tuple[int, int]:
        return self.dirs.shape[:2]

    def windows(self, corners: np.ndarray) -> list[Window]:
        """Pixel window covering a convex hull of (K, 3) points, clipped to the near plane and image."""
        uv, depth = self.calib.velo_to_image(corners)
        if corners.shape[0] == 8:
            if (depth < NEAR_PLANE).all():
                return []
            if (depth < NEAR_PLANE).any():
                uv, depth = self.calib.velo_to_image(clip_box_to_near(corners, depth, NEAR_PLANE))
        else:
            keep = depth >= NEAR_PLANE
            uv = uv[keep]
            if uv.shape[0] == 0:
                return []
        h, w = self.shape
        c0 = max(int(np.floor(uv[:, 0].min())), 0)
        c1 = min(int(np.ceil(uv[:, 0].max())) + 1, w)
        r0 = max(int(np.floor(uv[:, 1].min())), 0)
        r1 = min(int(np.ceil(uv[:, 1].max())) + 1, h)
        if c0 >= c1 or r0 >= r1:
            return []
        return [(slice(r0, r1), slice(c0, c1))]


@dataclass
class LidarGrid:
    """Rays of one LiDAR revolution: rows = lasers (elevation descending), columns = firings.

    dirs: float64 (64, C, 3) unit vectors; elevation: (64,) radians of each laser;
    azimuth0: azimuth of column 0; step: azimuth step (radians).
    """

    origin: np.ndarray
    dirs: np.ndarray
    elevation: np.ndarray
    azimuth0: float
    step: float

    @property
    def shape(self) -> tuple[int, int]:
        return self.dirs.shape[:2]

    def windows(self, corners: np.ndarray) -> list[Window]:
        """Rows × columns that can reach the bounding box with these (8, 3) corners (split at the seam)."""
        cols = self.shape[1]
        rel = corners - self.origin
        centre = rel.mean(axis=0)
        radius_xy = float(np.max(np.hypot(rel[:, 0] - centre[0], rel[:, 1] - centre[1])))
        dist = float(np.hypot(centre[0], centre[1]))
        d_min = max(dist - radius_xy, 0.0)
        d_max = dist + radius_xy
        z_lo, z_hi = rel[:, 2].min(), rel[:, 2].max()
        # Elevation bounds over the whole box, not just its corners: nearest/farthest horizontal reach.
        lo = np.arctan2(z_lo, d_min if z_lo < 0 else d_max) if d_min > 0 or z_lo >= 0 else -np.pi / 2
        hi = np.arctan2(z_hi, d_min if z_hi > 0 else d_max) if d_min > 0 or z_hi <= 0 else np.pi / 2
        margin = np.radians(0.2)
        in_rows = np.nonzero((self.elevation >= lo - margin) & (self.elevation <= hi + margin))[0]
        if in_rows.size == 0:
            return []
        row_slice = slice(int(in_rows[0]), int(in_rows[-1]) + 1)
        if d_min <= 0:
            return [(row_slice, slice(0, cols))]
        az_c = np.arctan2(centre[1], centre[0])
        az = np.arctan2(rel[:, 1], rel[:, 0])
        offsets = (az - az_c + np.pi) % (2 * np.pi) - np.pi
        a0, a1 = az_c + offsets.min(), az_c + offsets.max()
        c0 = int(np.floor((a0 - self.azimuth0) / self.step)) - 2
        c1 = int(np.ceil((a1 - self.azimuth0) / self.step)) + 3
        if c1 - c0 >= cols:
            return [(row_slice, slice(0, cols))]
        c0, c1 = c0 % cols, c1 % cols
        if c0 < c1:
            return [(row_slice, slice(c0, c1))]
        return [(row_slice, slice(c0, cols)), (row_slice, slice(0, c1))]


@dataclass
class CastResult:
    """Per-ray nearest hit: t (H, W) float64 (inf = none), prim (H, W) int32 (SKY, GROUND or index).

    amodal: for each actor, (window, mask) of the rays that hit it ignoring occluders
    (only when requested).
    """

    t: np.ndarray
    prim: np.ndarray
    amodal: list[tuple[Window, np.ndarray] | None]


def cast(scene: Scene, grid: CameraGrid | LidarGrid, track_actors: bool = False) -> CastResult:
    """Nearest surface along every ray of the grid (ground, then each primitive in its window)."""
    h, w = grid.shape
    t_ground = scene.road.intersect(grid.origin, grid.dirs.reshape(-1, 3)).reshape(h, w)
    # The horizon: ground beyond the render distance reads as sky.
    ground_limit = MAX_RENDER_DISTANCE / np.linalg.norm(grid.dirs, axis=2)
    hit_ground = t_ground < ground_limit
    t = np.where(hit_ground, t_ground, np.inf)
    prim = np.where(hit_ground, GROUND, SKY).astype(np.int32)

    amodal: list[tuple[Window, np.ndarray] | None] = [None] * len(scene.actors)
    actor_windows: list[list[Window]] = []
    for actor in scene.actors:
        corners = np.concatenate([p.corners() for p in actor.primitives])
        hull = _box_of(corners)
        actor_windows.append(grid.windows(hull))
        if track_actors and isinstance(grid, CameraGrid) and actor_windows[-1]:
            win = actor_windows[-1][0]
            amodal[len(actor_windows) - 1] = (win, np.zeros((win[0].stop - win[0].start,
                                                             win[1].stop - win[1].start), bool))

    for index, p in enumerate(scene.primitives):
        if p.actor >= 0 and not actor_windows[p.actor]:
            continue  # the whole actor is out of view
        for win in grid.windows(p.corners()):
            dirs = grid.dirs[win]
            t_p = intersect(p, grid.origin, dirs.reshape(-1, 3)).reshape(dirs.shape[:2])
            t_win = t[win]
            closer = t_p < t_win
            t[win] = np.where(closer, t_p, t_win)
            prim[win][closer] = index
            if p.actor >= 0 and amodal[p.actor] is not None:
                (rows, cols), mask = amodal[p.actor]
                sub = mask[win[0].start - rows.start: win[0].stop - rows.start,
                           win[1].start - cols.start: win[1].stop - cols.start]
                sub |= np.isfinite(t_p)
    return CastResult(t=t, prim=prim, amodal=amodal)


def _box_of(points: np.ndarray) -> np.ndarray:
    """(8, 3) corners of the axis-aligned box around points (a convex hull the windows accept)."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    return np.array([[hi[k] if i >> k & 1 else lo[k] for k in range(3)] for i in range(8)])
