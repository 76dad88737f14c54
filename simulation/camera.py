"""Camera 2: a per-frame KITTI-like calibration, and the rendered image with its dense depth.

The image is ray-cast through ``P2 · R0_rect · Tr_velo_to_cam`` itself, so the
calibration written beside it is exact by construction. Shading: Lambert sun +
ambient, ground shadows cast by cars, buildings and trees, specular paint and
glass, sky gradient with clouds, distance haze, lens blur and sensor noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.calib import Calibration
from simulation.constants import (
    BASE_P2,
    BASE_R0_RECT,
    BASE_TR_VELO_TO_CAM,
    CALIB_FOCAL_SIGMA,
    CALIB_PRINCIPAL_SIGMA,
    CALIB_ROTATION_SIGMA_DEG,
    CALIB_TRANSLATION_SIGMA,
    IMAGE_BLUR_SIGMA,
    IMAGE_HW,
    IMAGE_NOISE_SIGMA,
    MAX_DEPTH_GT,
)
from simulation.geometry import Texture, rotation_x, rotation_y, rotation_z
from simulation.raycast import GROUND, SKY, CameraGrid, CastResult, cast
from simulation.scene import Lighting, Scene
from simulation.surfaces import surface


def sample_calibration(rng: np.random.Generator) -> Calibration:
    """The base KITTI calibration with focal length, principal point and extrinsics jittered slightly."""
    k_base = BASE_P2[:, :3]
    baseline = np.linalg.solve(k_base, BASE_P2[:, 3])  # camera 2's offset from the reference camera
    k = k_base.copy()
    focal = rng.normal(0, CALIB_FOCAL_SIGMA)
    k[0, 0] += focal
    k[1, 1] += focal
    k[0, 2] += rng.normal(0, CALIB_PRINCIPAL_SIGMA)
    k[1, 2] += rng.normal(0, CALIB_PRINCIPAL_SIGMA)
    p2 = np.column_stack([k, k @ baseline])

    def small_rotation() -> np.ndarray:
        a, b, c = np.radians(rng.normal(0, CALIB_ROTATION_SIGMA_DEG, 3))
        return rotation_x(a) @ rotation_y(b) @ rotation_z(c)

    r0 = small_rotation() @ BASE_R0_RECT
    tr = BASE_TR_VELO_TO_CAM.copy()
    tr[:, :3] = small_rotation() @ tr[:, :3]
    tr[:, 3] += rng.normal(0, CALIB_TRANSLATION_SIGMA, 3)
    return Calibration(P2=p2, R0_rect=r0, Tr_velo_to_cam=tr)


@dataclass
class Render:
    """A camera render: image uint8 (H, W, 3) RGB, depth float32 (H, W) metres (0 = none), the cast."""

    image: np.ndarray
    depth: np.ndarray
    cast: CastResult
    grid: CameraGrid


def _sky(lighting: Lighting, dirs: np.ndarray) -> np.ndarray:
    """Sky colour for (M, 3) view directions: horizon-to-zenith gradient with soft clouds."""
    unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    up = np.clip(unit[:, 2], 0, 1)
    mix = np.clip(up * 4, 0, 1)[:, None] ** 0.6
    colour = lighting.sky_horizon * (1 - mix) + lighting.sky_zenith * mix
    # Clouds: smooth bands from a few sines of the direction, bright where positive.
    az = np.arctan2(unit[:, 1], unit[:, 0])
    cloud = np.sin(az * 9 + up * 20) + 0.7 * np.sin(az * 23 - up * 31 + 1.3) + 0.5 * np.sin(up * 57 + az * 4)
    cover = np.clip((cloud - 0.9) / 1.5, 0, 1)[:, None] * np.clip(up * 8, 0, 1)[:, None]
    return colour * (1 - cover) + np.array([0.92, 0.92, 0.94]) * cover


def _ground_shadow(scene: Scene, grid: CameraGrid, result: CastResult, points: np.ndarray) -> np.ndarray:
    """(H, W) float 1 = sunlit, 0.35 = in a caster's shadow (ground pixels only)."""
    h, w = grid.shape
    shade = np.ones((h, w))
    sun = scene.lighting.sun
    if sun[2] <= 0.05 or scene.shadow_casters.shape[0] == 0:
        return shade
    for corners in scene.shadow_casters:  # loop over objects, vectorized over pixels
        z_ground = float(scene.road.base_height(corners[:, 0].mean(), corners[:, 1].mean()))
        drop = np.maximum(corners[:, 2] - z_ground, 0.0) / sun[2]
        shadow = corners[:, :2] - drop[:, None] * sun[:2]
        hull = _convex_hull(np.concatenate([shadow, corners[:, :2]]))
        lo, hi = hull.min(axis=0), hull.max(axis=0)
        box = np.array([[hi[0] if i & 1 else lo[0], hi[1] if i & 2 else lo[1],
                         z_ground + (0.5 if i & 4 else -0.5)] for i in range(8)])
        for rows, cols in grid.windows(box):
            is_ground = result.prim[rows, cols] == GROUND
            if not is_ground.any():
                continue
            p = points[rows, cols][is_ground][:, :2]
            inside = np.ones(p.shape[0], bool)
            edges = np.roll(hull, -1, axis=0) - hull
            for (ex, ey), (vx, vy) in zip(edges, hull):  # ≤ 16 hull edges
                inside &= ex * (p[:, 1] - vy) - ey * (p[:, 0] - vx) >= 0
            sub = shade[rows, cols]
            sub[is_ground] = np.where(inside, 0.35, sub[is_ground])
            shade[rows, cols] = sub
    return shade


def _convex_hull(points: np.ndarray) -> np.ndarray:
    """Counter-clockwise convex hull of a few 2D points (monotone chain)."""
    pts = sorted(map(tuple, np.round(points, 6)))
    if len(pts) < 3:
        return np.array(pts)

    def half(seq: list) -> list:
        out: list = []
        for p in seq:
            while len(out) >= 2 and ((out[-1][0] - out[-2][0]) * (p[1] - out[-2][1])
                                     - (out[-1][1] - out[-2][1]) * (p[0] - out[-2][0])) <= 0:
                out.pop()
            out.append(p)
        return out

    lower, upper = half(pts), half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1])


def render(scene: Scene, calib: Calibration, rng: np.random.Generator) -> Render:
    """Render the image and its dense depth ground truth (projective depth of camera 2)."""
    grid = CameraGrid.build(calib, IMAGE_HW)
    result = cast(scene, grid, track_actors=True)
    h, w = grid.shape
    dirs = grid.dirs.reshape(-1, 3)
    t, prim = result.t.ravel(), result.prim.ravel()
    hit = prim != SKY
    points = grid.origin + dirs * np.where(hit, t, 0.0)[:, None]
    light = scene.lighting
    colour = np.empty((h * w, 3))
    colour[~hit] = _sky(light, dirs[~hit])

    idx = np.flatnonzero(hit)
    surf = surface(scene, prim[idx], points[idx], GROUND)
    view = dirs[idx] / np.linalg.norm(dirs[idx], axis=1, keepdims=True)
    normal = surf.normal * np.where(np.einsum("ij,ij->i", surf.normal, view) > 0, -1.0, 1.0)[:, None]
    shadow = _ground_shadow(scene, grid, result, points.reshape(h, w, 3)).ravel()[idx]
    lambert = np.clip((normal * light.sun).sum(axis=1), 0, None) * shadow
    shaded = surf.colour * (light.ambient + (1 - light.ambient) * lambert)[:, None]
    glossy = (surf.texture == Texture.PAINT) | (surf.texture == Texture.GLASS)
    half_vec = light.sun - view
    half_vec /= np.linalg.norm(half_vec, axis=1, keepdims=True)
    spec = np.clip(np.einsum("ij,ij->i", normal, half_vec), 0, 1) ** 40 * shadow
    shaded += (glossy * 0.6 * spec)[:, None]
    glass = surf.texture == Texture.GLASS
    if glass.any():  # glass mirrors the sky, more at grazing angles (Fresnel-like)
        mirrored = view[glass] - 2 * np.einsum("ij,ij->i", view[glass], normal[glass])[:, None] * normal[glass]
        fresnel = 0.15 + 0.6 * (1 - np.abs(np.einsum("ij,ij->i", view[glass], normal[glass]))) ** 3
        shaded[glass] += fresnel[:, None] * _sky(light, mirrored) * 0.6
    lamp = surf.texture == Texture.LIGHT
    shaded[lamp] = surf.colour[lamp] * (0.7 + 0.3 * lambert[lamp, None])
    haze = 1 - np.exp(-t[idx] / 700.0)
    colour[idx] = shaded * (1 - haze[:, None]) + light.sky_horizon * haze[:, None]

    # Camera response: exposure, gamma, lens blur, vignetting, sensor noise.
    linear = np.clip(colour.reshape(h, w, 3) * light.exposure, 0, 1)
    image = linear ** (1 / 2.2) * 255
    image = cv2.GaussianBlur(image.astype(np.float32), (0, 0), IMAGE_BLUR_SIGMA)
    yy, xx = np.mgrid[0:h, 0:w]
    vignette = 1 - 0.25 * (((xx - w / 2) / (w / 2)) ** 2 * 0.6 + ((yy - h / 2) / (h / 2)) ** 2 * 0.2)
    image = image * vignette[..., None] + rng.normal(0, IMAGE_NOISE_SIGMA, image.shape)
    image = np.clip(np.rint(image), 0, 255).astype(np.uint8)

    depth = np.where(hit & (t <= MAX_DEPTH_GT), t, 0.0).reshape(h, w).astype(np.float32)
    return Render(image=image, depth=depth, cast=result, grid=grid)
