"""3D boxes in the LiDAR frame and their KITTI label form.

A box array is float64 (N, 7): ``x, y, z, l, w, h, yaw`` — the box centre in
the velodyne frame, length along the heading, width, height, heading about z.
KITTI labels give the bottom centre in the rectified camera frame and
``rotation_y``; ``rotation_y = -yaw - π/2`` (camera y points down, LiDAR z up).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pipeline.calib import Calibration
from pipeline.iou import rect_corners
from pipeline.kitti import Object3D

BOX_FIELDS = ("x", "y", "z", "l", "w", "h", "yaw")


def wrap_angle(angle: np.ndarray | float) -> np.ndarray:
    """Wrap angles to [-π, π)."""
    return (np.asarray(angle, np.float64) + np.pi) % (2 * np.pi) - np.pi


def labels_to_boxes(objects: Sequence[Object3D], calib: Calibration) -> np.ndarray:
    """KITTI label objects → (N, 7) LiDAR-frame boxes (centre, l, w, h, yaw)."""
    if not objects:
        return np.zeros((0, 7))
    location = np.array([o.location for o in objects], np.float64)
    h, w, l = np.array([o.dimensions for o in objects], np.float64).T
    rotation_y = np.array([o.rotation_y for o in objects], np.float64)
    bottom = calib.rect_to_velo(location)
    centre = bottom + np.stack([np.zeros_like(h), np.zeros_like(h), h / 2], axis=1)
    return np.column_stack([centre, l, w, h, wrap_angle(-rotation_y - np.pi / 2)])


def box_corners_3d(boxes: np.ndarray) -> np.ndarray:
    """(N, 7) boxes → (N, 8, 3) corners: the 4 BEV corners at the bottom, then at the top."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    bev = bev_corners(boxes)  # (N, 4, 2)
    bottom = (boxes[:, 2] - boxes[:, 5] / 2)[:, None, None]
    top = (boxes[:, 2] + boxes[:, 5] / 2)[:, None, None]
    z = np.concatenate([np.repeat(bottom, 4, axis=1), np.repeat(top, 4, axis=1)], axis=1)
    return np.concatenate([np.concatenate([bev, bev], axis=1), z], axis=2)


def bev_corners(boxes: np.ndarray) -> np.ndarray:
    """(N, 7) boxes → (N, 4, 2) BEV corners (x, y), counter-clockwise from front-left."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    return rect_corners(boxes[:, [0, 1, 3, 4, 6]])


# A box's 12 edges between its corners as box_corners_3d orders them (bottom ring, top ring, uprights).
BOX_EDGES = ((0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7))
NEAR_PLANE_M = 0.1  # box edges are cut this far in front of the camera: nothing behind it projects


def segments_in_front(rect: np.ndarray, segments: tuple[tuple[int, int], ...] = BOX_EDGES,
                      near: float = NEAR_PLANE_M) -> tuple[np.ndarray, np.ndarray]:
    """Segments between the corners of boxes in the camera frame ((K, 8, 3), z forward), cut at the near plane.

    Returns each segment's two ends (K, S, 2, 3), an end behind the plane moved along the segment onto it,
    and (K, S) whether any of the segment lies in front of it. A car beside the vehicle reaches behind the
    camera: its edges are cut, not dropped, and the cut ends project towards the image's border on that side.
    """
    ends = rect[:, np.array(segments)]
    z, other = ends[..., 2], ends[..., ::-1, :]
    shown = np.asarray((z > near).any(axis=2))  # an array for any K (NumPy's stubs allow a scalar)
    with np.errstate(divide="ignore", invalid="ignore"):
        along = (near - z) / (other[..., 2] - z)  # where the segment crosses the near plane
        cut = np.where((z <= near)[..., None], ends + along[..., None] * (other - ends), ends)
    return cut, shown


def image_boxes(boxes: np.ndarray, calib: Calibration, image_hw: tuple[int, int]) -> np.ndarray:
    """2D boxes (left, top, right, bottom) of the projected 3D boxes, clipped to the image.

    A box reaching behind the camera is the box of its part in front (its edges cut at the near plane), which
    runs to the image's border on that side; one wholly behind covers the image.
    """
    rect = calib.velo_to_rect(box_corners_3d(boxes).reshape(-1, 3)).reshape(-1, 8, 3)
    ends, shown = segments_in_front(rect)
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = calib.rect_to_image(ends.reshape(-1, 3))[0].reshape(*ends.shape[:-1], 2)
    uv = np.where(shown[..., None, None], uv, np.nan).reshape(len(rect), -1, 2)
    h, w = image_hw
    # fmin/fmax skip the NaN ends; on a box wholly behind (all NaN) they give NaN without the RuntimeWarning
    # nanmin/nanmax raise there (a warnings.warn, which np.errstate does not silence).
    left = np.nan_to_num(np.fmin.reduce(uv[..., 0], axis=1), nan=0.0)
    right = np.nan_to_num(np.fmax.reduce(uv[..., 0], axis=1), nan=w - 1.0)
    top = np.nan_to_num(np.fmin.reduce(uv[..., 1], axis=1), nan=0.0)
    bottom = np.nan_to_num(np.fmax.reduce(uv[..., 1], axis=1), nan=h - 1.0)
    return np.column_stack([
        np.clip(left, 0, w - 1), np.clip(top, 0, h - 1), np.clip(right, 0, w - 1), np.clip(bottom, 0, h - 1)
    ])


def in_camera_view(boxes: np.ndarray, calib: Calibration, image_hw: tuple[int, int]) -> np.ndarray:
    """(N,) bool: the box centre lies in front of the camera and projects inside the image.

    KITTI labels only what the camera sees, so results outside its view would
    all count as false positives.
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    uv, depth = calib.velo_to_image(boxes[:, :3])
    h, w = image_hw
    with np.errstate(invalid="ignore"):
        return (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)


def boxes_to_objects(
    boxes: np.ndarray,
    calib: Calibration,
    image_hw: tuple[int, int],
    scores: np.ndarray | None = None,
    label: str = "Car",
) -> list[Object3D]:
    """LiDAR-frame boxes → KITTI label objects (result format with scores when given).

    The 2D box is the projection of the 3D box clipped to the image; truncation
    and occlusion are unknown for detections and written as 0 (KITTI results
    ignore them).
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    if boxes.shape[0] == 0:
        return []
    bottom = boxes[:, :3] - np.column_stack([np.zeros((len(boxes), 2)), boxes[:, 5] / 2])
    location = calib.velo_to_rect(bottom)
    rotation_y = wrap_angle(-boxes[:, 6] - np.pi / 2)
    alpha = wrap_angle(rotation_y - np.arctan2(location[:, 0], location[:, 2]))
    bbox = image_boxes(boxes, calib, image_hw)
    return [
        Object3D(
            type=label, truncated=0.0, occluded=0, alpha=float(alpha[i]),
            bbox=(float(bbox[i, 0]), float(bbox[i, 1]), float(bbox[i, 2]), float(bbox[i, 3])),
            dimensions=(float(boxes[i, 5]), float(boxes[i, 4]), float(boxes[i, 3])),
            location=(float(location[i, 0]), float(location[i, 1]), float(location[i, 2])),
            rotation_y=float(rotation_y[i]),
            score=None if scores is None else float(scores[i]),
        )
        for i in range(boxes.shape[0])
    ]


def points_in_boxes(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(N, ≥3) points × (M, 7) boxes → (N, M) bool: point inside the box (boundary included).

    For tests and small sets; the frame path uses raster look-ups instead.
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    rel = np.asarray(points[:, :3], np.float64)[:, None, :] - boxes[None, :, :3]
    cos, sin = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    along = rel[..., 0] * cos + rel[..., 1] * sin
    across = -rel[..., 0] * sin + rel[..., 1] * cos
    return (
        (np.abs(along) <= boxes[:, 3] / 2)
        & (np.abs(across) <= boxes[:, 4] / 2)
        & (np.abs(rel[..., 2]) <= boxes[:, 5] / 2)
    )


@dataclass(frozen=True)
class BoxRecord:
    """One box by name, in the LiDAR frame (x forward, y left, z up, metres): the centre (z is the box's middle,
    not its bottom), the size along, across and up its heading, and the heading ``yaw`` about +z from +x,
    counter-clockwise, in radians."""

    x: float
    y: float
    z: float
    length: float
    width: float
    height: float
    yaw: float
    score: float
    label: str = "Car"

    @property
    def quaternion_xyzw(self) -> tuple[float, float, float, float]:
        """The heading as a unit quaternion (x, y, z, w): a rotation by ``yaw`` about +z, as ROS's
        ``geometry_msgs/Quaternion`` takes it (the box's size then goes x: length, y: width, z: height)."""
        return (0.0, 0.0, float(np.sin(self.yaw / 2)), float(np.cos(self.yaw / 2)))


def box_records(boxes: np.ndarray, scores: np.ndarray, label: str = "Car") -> list[BoxRecord]:
    """(K, 7) boxes and their (K,) scores → one :class:`BoxRecord` each, in the same order."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    scores = np.asarray(scores, np.float64).reshape(-1)
    if len(scores) != len(boxes):
        raise ValueError(f"{len(boxes)} boxes but {len(scores)} scores")
    return [BoxRecord(x, y, z, length, width, height, yaw, score, label)  # tolist(): Python floats
            for (x, y, z, length, width, height, yaw), score in zip(boxes.tolist(), scores.tolist(), strict=True)]
