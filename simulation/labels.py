"""KITTI ``label_2`` objects from the render: 2D boxes, truncation, occlusion, DontCare.

- 2D box: the tight box around the object's silhouette as if nothing occluded it
  (its amodal mask in the render), pixel edges (centre ± 0.5), clipped as KITTI's boxes are
  to 0 … W − 1 and 0 … H − 1.
- truncated: fraction of the object's volume (sampled on a grid in its 3D box)
  that projects outside the image or behind the camera.
- occluded: from the visible fraction of the silhouette: level 0 / 1 / 2 below the
  OCCLUSION_LEVELS thresholds; beyond the last, or farther than
  LABEL_MAX_DISTANCE, or smaller than MIN_BOX_HEIGHT, the object becomes a
  DontCare region around its visible pixels (KITTI's annotators skipped those).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.boxes import wrap_angle
from pipeline.calib import Calibration
from pipeline.kitti import Object3D
from simulation.camera import Render
from simulation.constants import (
    LABEL_MAX_DISTANCE,
    MIN_BOX_HEIGHT,
    MIN_VISIBLE_PIXELS,
    NEAR_PLANE,
    OCCLUSION_LEVELS,
    TRUNCATION_SAMPLES,
)
from simulation.geometry import rotation_z
from simulation.scene import Actor, Scene


@dataclass(frozen=True)
class Visibility:
    """How an actor appears in the image.

    amodal_pixels / visible_pixels: silhouette pixels without / with occluders.
    amodal_box / visible_box: (left, top, right, bottom) pixel edges, None when empty.
    truncated: fraction of the box volume outside the image or behind the camera (:func:`truncation`).
    occluded_fraction: 1 - visible / amodal.
    """

    amodal_pixels: int
    visible_pixels: int
    amodal_box: tuple[float, float, float, float] | None
    visible_box: tuple[float, float, float, float] | None
    truncated: float

    @property
    def occluded_fraction(self) -> float:
        return 1.0 - self.visible_pixels / self.amodal_pixels if self.amodal_pixels else 1.0


def occlusion_level(occluded_fraction: float) -> int:
    """KITTI occlusion level 0, 1, 2 for a fraction; 3 when too occluded to label."""
    return int(np.searchsorted(np.asarray(OCCLUSION_LEVELS), occluded_fraction, side="right"))


def _mask_box(mask: np.ndarray, top: int, left: int) -> tuple[float, float, float, float] | None:
    """Pixel-edge box of a boolean mask placed at (top, left) in the image."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return None
    return (left + cols[0] - 0.5, top + rows[0] - 0.5, left + cols[-1] + 0.5, top + rows[-1] + 0.5)


def truncation(actor: Actor, calib: Calibration, image_hw: tuple[int, int]) -> float:
    """Fraction of the actor's box volume (grid samples) projecting outside the image or behind the camera."""
    n = TRUNCATION_SAMPLES
    g = (np.arange(n) + 0.5) / n - 0.5
    local = np.stack(np.meshgrid(g, g, g + 0.5, indexing="ij"), axis=-1).reshape(-1, 3) * np.array(actor.size)
    world = local @ rotation_z(actor.yaw).T + actor.bottom
    uv, depth = calib.velo_to_image(world)
    h, w = image_hw
    with np.errstate(invalid="ignore"):
        inside = (depth > NEAR_PLANE) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= w - 0.5) & (uv[:, 1] >= -0.5) & (
            uv[:, 1] <= h - 0.5)
    return float(1.0 - inside.mean())


def actor_map(scene: Scene, render: Render) -> np.ndarray:
    """(H, W) int32: index of the actor seen at each pixel, -1 for scenery, ground and sky."""
    owner = np.array([p.actor for p in scene.primitives] + [-1], np.int32)
    prim = render.cast.prim
    return owner[np.where(prim >= 0, prim, len(scene.primitives))]


def visibility(scene: Scene, render: Render, calib: Calibration) -> list[Visibility]:
    """Visibility of every actor in the render (see module doc)."""
    seen = actor_map(scene, render)
    image_hw = seen.shape
    out = []
    for index, actor in enumerate(scene.actors):
        entry = render.cast.amodal[index]
        if entry is None:
            out.append(Visibility(0, 0, None, None, truncation(actor, calib, image_hw)))
            continue
        (rows, cols), mask = entry
        visible = seen[rows, cols] == index
        out.append(Visibility(
            amodal_pixels=int(mask.sum()), visible_pixels=int(visible.sum()),
            amodal_box=_mask_box(mask, rows.start, cols.start), visible_box=_mask_box(visible, rows.start, cols.start),
            truncated=truncation(actor, calib, image_hw),
        ))
    return out


def dont_care(box: tuple[float, float, float, float]) -> Object3D:
    """A KITTI DontCare region."""
    return Object3D(type="DontCare", truncated=-1.0, occluded=-1, alpha=-10.0, bbox=box,
                    dimensions=(-1.0, -1.0, -1.0), location=(-1000.0, -1000.0, -1000.0), rotation_y=-10.0)


def label_objects(scene: Scene, render: Render, calib: Calibration) -> list[Object3D]:
    """The frame's ``label_2`` objects: labelled actors nearest first, then DontCare regions."""
    labelled: list[tuple[float, Object3D]] = []
    ignored: list[Object3D] = []
    for actor, vis in zip(scene.actors, visibility(scene, render, calib)):
        if vis.visible_pixels < MIN_VISIBLE_PIXELS or vis.amodal_box is None or vis.visible_box is None:
            continue
        level = occlusion_level(vis.occluded_fraction)
        box_height = vis.amodal_box[3] - vis.amodal_box[1]
        if actor.distance > LABEL_MAX_DISTANCE or level > 2 or box_height < MIN_BOX_HEIGHT:
            ignored.append(dont_care(vis.visible_box))
            continue
        l, w, h = actor.size
        location = calib.velo_to_rect(actor.bottom[None, :])[0]
        rot_y = float(wrap_angle(-actor.yaw - np.pi / 2))
        alpha = float(wrap_angle(rot_y - np.arctan2(location[0], location[2])))
        hh, ww = render.depth.shape
        left, top, right, bottom = vis.amodal_box
        bbox = (max(left, 0.0), max(top, 0.0), min(right, ww - 1.0), min(bottom, hh - 1.0))
        labelled.append((actor.distance, Object3D(
            type=actor.kind, truncated=round(vis.truncated, 2), occluded=level, alpha=alpha, bbox=bbox,
            dimensions=(h, w, l), location=tuple(float(v) for v in location), rotation_y=rot_y,
        )))
    labelled.sort(key=lambda item: item[0])
    return [obj for _, obj in labelled] + ignored
