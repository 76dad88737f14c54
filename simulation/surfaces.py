"""Surface properties at hit points: normals, camera colour (with procedural texture), LiDAR albedo.

Shared by the camera and the LiDAR so both sensors see the same road markings,
facades and foliage.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simulation.constants import LANE_WIDTH
from simulation.geometry import Texture, mat_rows, surface_normals
from simulation.road import Road, Zone
from simulation.scene import Scene

MARKING_WIDTH = 0.14
DASH_PERIOD, DASH_ON = 12.0, 4.0  # German-style lane dashes: 4 m painted every 12 m
ASPHALT = np.array([0.21, 0.21, 0.22])
SIDEWALK = np.array([0.50, 0.49, 0.47])
GRASS = np.array([0.20, 0.33, 0.12])
PAVING = np.array([0.45, 0.42, 0.38])
MARKING = np.array([0.85, 0.85, 0.82])
WINDOW = np.array([0.12, 0.15, 0.2])


def cell_noise(points: np.ndarray, scale: float, salt: int = 0) -> np.ndarray:
    """Deterministic white noise in [0, 1) per cubic cell of size ``scale`` (integer hash, no RNG)."""
    cells = np.floor(points / scale).astype(np.int64)
    h = (cells[:, 0] * 73856093) ^ (cells[:, 1] * 19349663) ^ (cells[:, 2] * 83492791) ^ (salt * 2654435761)
    h = (h ^ (h >> 13)) * 1274126177
    h = h ^ (h >> 16)
    return (h & 0xFFFF).astype(np.float64) / 65536.0


@dataclass
class SurfaceSample:
    """Per-hit arrays: normal (M, 3) unit, colour (M, 3) linear RGB, albedo (M,), extra range noise (M,),
    texture (M,) Texture values (ground is PLAIN)."""

    normal: np.ndarray
    colour: np.ndarray
    albedo: np.ndarray
    range_noise: np.ndarray
    texture: np.ndarray


def _markings(road: Road, along: np.ndarray, lateral: np.ndarray) -> np.ndarray:
    """True where a lane line is painted: dashed between lanes, solid at the centre and road edges."""
    dashed = np.mod(along, DASH_PERIOD) < DASH_ON
    paint = np.zeros(along.shape, bool)
    for k in range(1, road.lanes_left):
        paint |= (np.abs(lateral - k * LANE_WIDTH) < MARKING_WIDTH / 2) & dashed
    for k in range(1, road.lanes_right):
        paint |= (np.abs(lateral + k * LANE_WIDTH) < MARKING_WIDTH / 2) & dashed
    centre_solid = road.lanes_left + road.lanes_right >= 4
    paint |= (np.abs(lateral) < MARKING_WIDTH / 2) & (dashed | centre_solid)
    for edge in (road.lanes_left * LANE_WIDTH - 0.3 * (not road.parking_left),
                 -road.lanes_right * LANE_WIDTH + 0.3 * (not road.parking_right)):
        paint |= np.abs(lateral - edge) < MARKING_WIDTH / 2
    return paint


def ground_surface(road: Road, points: np.ndarray) -> SurfaceSample:
    """Appearance of ground hits (M, 3): asphalt with markings, tiled sidewalk, curb, grass or paving."""
    x, y = points[:, 0], points[:, 1]
    lateral = road.lateral(x, y)
    zone = road.zone(lateral)
    fine = cell_noise(points, 0.07, 1)
    coarse = cell_noise(points, 1.3, 2)
    colour = np.empty_like(points)
    albedo = np.empty(points.shape[0])
    on_road = zone == Zone.ROAD
    colour[on_road] = ASPHALT * (0.8 + 0.3 * fine[on_road, None] + 0.15 * coarse[on_road, None])
    albedo[on_road] = 0.22 + 0.06 * fine[on_road]
    paint = on_road & _markings(road, x, lateral)
    colour[paint] = MARKING * (0.9 + 0.1 * fine[paint, None])
    albedo[paint] = 0.6

    walk = zone == Zone.SIDEWALK
    seam = (np.mod(x, 0.6) < 0.03) | (np.mod(lateral, 0.6) < 0.03)
    colour[walk] = SIDEWALK * (0.9 + 0.15 * fine[walk, None]) * np.where(seam[walk], 0.75, 1.0)[:, None]
    albedo[walk] = 0.32
    beyond = np.maximum(lateral - road.left_edge, road.right_edge - lateral)
    curb = walk & (beyond < 0.15)
    colour[curb] = SIDEWALK * 1.25

    verge = zone == Zone.VERGE
    base = GRASS if road.verge_grass else PAVING
    colour[verge] = base * (0.7 + 0.5 * fine[verge, None]) * (0.85 + 0.3 * coarse[verge, None])
    albedo[verge] = 0.45 if road.verge_grass else 0.3

    grad_x = road.slope + 2.0 * road.bend_v * x
    normal = np.column_stack([-grad_x, np.full_like(x, -road.cross_slope), np.ones_like(x)])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return SurfaceSample(normal, colour, albedo, np.zeros_like(albedo), np.zeros(len(x), np.int8))


def _facade(colour: np.ndarray, local: np.ndarray, local_normal: np.ndarray, half: np.ndarray,
            points: np.ndarray) -> np.ndarray:
    """Walls with rows of windows (per-window brightness), roofs plain."""
    u = np.where(np.abs(local_normal[:, 0]) > 0.5, local[:, 1], local[:, 0])
    z = local[:, 2] + half[2] - 1.0  # height above the (sunk) ground line
    wall = np.abs(local_normal[:, 2]) < 0.5
    in_window = wall & (np.mod(u, 3.0) > 0.7) & (np.mod(u, 3.0) < 2.3) & (np.mod(z, 3.2) > 0.9) & (z > 0.5)
    window_id = np.column_stack([np.floor(u / 3.0), np.floor(z / 3.2), np.zeros_like(u)])
    shade = 0.5 + cell_noise(window_id, 1.0, 3)
    out = colour * (0.88 + 0.18 * cell_noise(points, 0.25, 4))[:, None]
    out[in_window] = WINDOW * shade[in_window, None] * 1.6
    return out


def primitive_surface(scene: Scene, prim: np.ndarray, points: np.ndarray) -> SurfaceSample:
    """Appearance of hits on primitives: ``prim`` (M,) primitive indices, ``points`` (M, 3) world hits."""
    m = points.shape[0]
    normal = np.zeros((m, 3))
    colour = np.zeros((m, 3))
    albedo = np.zeros(m)
    noise = np.zeros(m)
    texture = np.zeros(m, np.int8)
    order = np.argsort(prim, kind="stable")
    ids, starts = np.unique(prim[order], return_index=True)
    ends = np.append(starts[1:], m)
    for pid, s, e in zip(ids, starts, ends):  # loop over primitives, vectorized over their hits
        sel = order[s:e]
        p = scene.primitives[int(pid)]
        n, local = surface_normals(p, points[sel])
        mat = p.material
        c = np.broadcast_to(np.asarray(mat.colour), (sel.size, 3)).copy()
        if mat.texture == Texture.FACADE:
            c = _facade(c, local, mat_rows(n, p.rotation), p.half, points[sel])
        elif mat.texture == Texture.FOLIAGE:
            c *= ((0.5 + 0.9 * cell_noise(points[sel], 0.12, 5)) * (0.8 + 0.4 * cell_noise(points[sel], 0.7, 6)))[:, None]
        elif mat.texture in (Texture.PLAIN, Texture.PAINT):
            c *= (0.94 + 0.08 * cell_noise(points[sel], 0.1, 7))[:, None]
        normal[sel], colour[sel] = n, c
        albedo[sel], noise[sel], texture[sel] = mat.albedo, mat.range_noise, int(mat.texture)
    return SurfaceSample(normal, colour, albedo, noise, texture)


def surface(scene: Scene, prim: np.ndarray, points: np.ndarray, ground_id: int) -> SurfaceSample:
    """Appearance of any hits: ground where ``prim == ground_id``, primitives elsewhere (no sky)."""
    on_ground = prim == ground_id
    g = ground_surface(scene.road, points[on_ground])
    o = primitive_surface(scene, prim[~on_ground], points[~on_ground])
    out = SurfaceSample(*(np.empty((prim.size,) + a.shape[1:], a.dtype) for a in (
        g.normal, g.colour, g.albedo, g.range_noise, g.texture)))
    for name in ("normal", "colour", "albedo", "range_noise", "texture"):
        getattr(out, name)[on_ground] = getattr(g, name)
        getattr(out, name)[~on_ground] = getattr(o, name)
    return out
