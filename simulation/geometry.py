"""Scene primitives (oriented boxes, cylinders, ellipsoids) and their vectorized ray intersections.

A primitive lives in its own local frame: ``world = centre + rotation @ local``.
Rays are given in the world (LiDAR) frame as one origin and an (M, 3) array of
directions that need not be unit length; the returned ``t`` is in units of the
direction, so camera rays built with unit projective depth return depth directly.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

_EPS = 1e-6
# The 8 corners of the unit cube [-1, 1]³; corner i has bit k set ⇔ coordinate k is +1.
UNIT_CORNERS = np.array([[(i >> k & 1) * 2.0 - 1.0 for k in range(3)] for i in range(8)])
# The 12 cube edges as corner index pairs (corners that differ in exactly one bit).
CUBE_EDGES = np.array([(i, i | 1 << k) for i in range(8) for k in range(3) if not i >> k & 1])


class Shape(IntEnum):
    """Primitive kinds. Cylinders have their axis along local z."""

    BOX = 0
    CYLINDER = 1
    ELLIPSOID = 2


class Texture(IntEnum):
    """How the camera colours a surface (LiDAR ignores textures)."""

    PLAIN = 0
    PAINT = 1  # glossy car paint
    GLASS = 2
    FACADE = 3  # a building wall with rows of windows
    FOLIAGE = 4
    LIGHT = 5  # lamps and signs: bright, hardly shaded


@dataclass(frozen=True)
class Material:
    """Surface appearance: linear RGB colour for the camera, albedo and extra noise for the LiDAR."""

    colour: tuple[float, float, float]
    texture: Texture = Texture.PLAIN
    albedo: float = 0.3  # LiDAR reflectivity at normal incidence, 0…1
    range_noise: float = 0.0  # extra range noise (leaves, glass), metres


@dataclass(frozen=True)
class Primitive:
    """One solid: shape, pose (centre (3,), rotation (3, 3) local→world), half-extents (3,).

    Box: half sizes along local x, y, z. Cylinder: (radius, radius, half-length along z).
    Ellipsoid: semi-axes. ``actor`` is the index of the labelled object it belongs to, -1 for scenery.
    """

    shape: Shape
    centre: np.ndarray
    rotation: np.ndarray
    half: np.ndarray
    material: Material
    actor: int = -1

    def corners(self) -> np.ndarray:
        """(8, 3) world corners of the primitive's oriented bounding box (corner order of UNIT_CORNERS)."""
        return (UNIT_CORNERS * self.half) @ self.rotation.T + self.centre


def rotation_z(yaw: float) -> np.ndarray:
    """Rotation about z by ``yaw`` (counter-clockwise seen from above)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_x(angle: float) -> np.ndarray:
    """Rotation about x by ``angle``."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rotation_y(angle: float) -> np.ndarray:
    """Rotation about y by ``angle``."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def mat_rows(vectors: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """``vectors @ matrix`` for (M, 3) × (3, 3) without BLAS (keeps worker processes single-threaded)."""
    return vectors[:, 0:1] * matrix[0] + vectors[:, 1:2] * matrix[1] + vectors[:, 2:3] * matrix[2]


def _to_local(prim: Primitive, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray origin (3,) and directions (M, 3) in the primitive's frame."""
    return (origin - prim.centre) @ prim.rotation, mat_rows(dirs, prim.rotation)


def _safe(d: np.ndarray) -> np.ndarray:
    """Replace zero direction components so slab divisions stay finite-signed."""
    return np.where(np.abs(d) < 1e-12, 1e-12, d)


def intersect(prim: Primitive, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Entry distance of each ray into the primitive: (M,) float64, ``inf`` where it misses."""
    o, d = _to_local(prim, origin, dirs)
    h = prim.half
    if prim.shape == Shape.BOX:
        inv = 1.0 / _safe(d)
        t1 = (-h - o) * inv
        t2 = (h - o) * inv
        t_near = np.minimum(t1, t2).max(axis=1)
        t_far = np.maximum(t1, t2).min(axis=1)
        hit = (t_near <= t_far) & (t_near > _EPS)
        return np.where(hit, t_near, np.inf)
    if prim.shape == Shape.ELLIPSOID:
        o, d = o / h, d / h
        a = np.einsum("ij,ij->i", d, d)
        b = 2.0 * (d @ o)
        c = float(o @ o) - 1.0
        disc = b * b - 4.0 * a * c
        with np.errstate(invalid="ignore"):
            t = (-b - np.sqrt(disc)) / (2.0 * a)
        return np.where((disc >= 0) & (t > _EPS), t, np.inf)
    # Cylinder along local z: the side (a circle in x, y) or the cap the ray enters first.
    r, half_len = h[0], h[2]
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = 2.0 * (o[0] * d[:, 0] + o[1] * d[:, 1])
    c = o[0] ** 2 + o[1] ** 2 - r * r
    disc = b * b - 4.0 * a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        t_side = (-b - np.sqrt(disc)) / (2.0 * a)
    z_side = o[2] + t_side * d[:, 2]
    side_ok = (disc >= 0) & (t_side > _EPS) & (np.abs(z_side) <= half_len)
    dz = _safe(d[:, 2])
    t_cap = (-np.sign(dz) * half_len - o[2]) / dz
    x_cap = o[0] + t_cap * d[:, 0]
    y_cap = o[1] + t_cap * d[:, 1]
    cap_ok = (t_cap > _EPS) & (x_cap**2 + y_cap**2 <= r * r)
    return np.minimum(np.where(side_ok, t_side, np.inf), np.where(cap_ok, t_cap, np.inf))


def surface_normals(prim: Primitive, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit world normals (M, 3) and local coordinates (M, 3) of points on the primitive's surface."""
    local = mat_rows(points - prim.centre, prim.rotation)
    h = prim.half
    if prim.shape == Shape.BOX:
        q = np.abs(local) / h
        axis = np.argmax(q, axis=1)
        n = np.zeros_like(local)
        rows = np.arange(local.shape[0])
        n[rows, axis] = np.sign(local[rows, axis])
    elif prim.shape == Shape.ELLIPSOID:
        n = local / (h * h)
    else:
        radial = np.hypot(local[:, 0], local[:, 1])
        on_cap = np.abs(np.abs(local[:, 2]) - h[2]) < np.abs(radial - h[0])
        n = np.where(on_cap[:, None], np.column_stack([0 * radial, 0 * radial, np.sign(local[:, 2])]),
                     np.column_stack([local[:, 0], local[:, 1], 0 * radial]))
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return mat_rows(n, prim.rotation.T), local


def clip_box_to_near(corners: np.ndarray, depth: np.ndarray, near: float) -> np.ndarray:
    """Points whose convex hull is the part of a box with ``depth >= near``: kept corners + edge crossings.

    corners (8, 3) in UNIT_CORNERS order, depth (8,) along the viewing axis; returns (K, 3), K ≥ 0.
    """
    a, b = corners[CUBE_EDGES[:, 0]], corners[CUBE_EDGES[:, 1]]
    da, db = depth[CUBE_EDGES[:, 0]], depth[CUBE_EDGES[:, 1]]
    crosses = (da - near) * (db - near) < 0
    f = (near - da[crosses]) / (db[crosses] - da[crosses])
    crossings = a[crosses] + f[:, None] * (b[crosses] - a[crosses])
    return np.concatenate([corners[depth >= near], crossings])
