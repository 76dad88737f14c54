"""Overlap matrices between detections and ground truth, in the official devkit's conventions.

All functions take detections first and return (D, G) float64 matrices.

* 2D: axis-aligned image boxes, no "+1 pixel" (the 2017+ devkit dropped it).
* BEV: rotated rectangles in the camera frame's ground plane ``(x, z)``. The devkit
  rotates the corner offsets ``(±l/2, ±w/2)`` by ``[[cos ry, sin ry], [-sin ry, cos ry]]``,
  i.e. by the angle ``-ry``: the rows handed to the exact rotated IoU are
  ``[x, z, l, w, -ry]``.
* 3D: BEV intersection area times the vertical overlap; camera y points down and a
  box spans ``[y - h, y]``.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from evaluation.labels import LabelArrays
from pipeline.iou import rotated_intersection_matrix, rotated_iou_matrix


def image_overlap(
    det_boxes: np.ndarray, gt_boxes: np.ndarray, criterion: Literal["union", "detection"] = "union"
) -> np.ndarray:
    """Overlap of 2D boxes (D, 4) and (G, 4) ``left, top, right, bottom`` → (D, G).

    ``union``: intersection over union. ``detection``: intersection over the
    detection's own area (how the devkit measures a detection inside a DontCare
    region). Pairs that do not intersect give 0 without dividing, as in the devkit,
    so a zero-area detection never produces NaN.
    """
    det = np.asarray(det_boxes, np.float64).reshape(-1, 4)
    gt = np.asarray(gt_boxes, np.float64).reshape(-1, 4)
    width = np.minimum(det[:, None, 2], gt[None, :, 2]) - np.maximum(det[:, None, 0], gt[None, :, 0])
    height = np.minimum(det[:, None, 3], gt[None, :, 3]) - np.maximum(det[:, None, 1], gt[None, :, 1])
    intersects = (width > 0) & (height > 0)
    inter = np.where(intersects, width * height, 0.0)
    det_area = ((det[:, 2] - det[:, 0]) * (det[:, 3] - det[:, 1]))[:, None]
    if criterion == "union":
        gt_area = ((gt[:, 2] - gt[:, 0]) * (gt[:, 3] - gt[:, 1]))[None, :]
        denominator = det_area + gt_area - inter
    elif criterion == "detection":
        denominator = np.broadcast_to(det_area, inter.shape)
    else:
        raise ValueError(f"criterion must be 'union' or 'detection', got {criterion!r}")
    out = np.zeros_like(inter)
    np.divide(inter, denominator, out=out, where=intersects)
    return out


def bev_rows(labels: LabelArrays) -> np.ndarray:
    """(N, 5) ``[x, z, l, w, -rotation_y]`` ground-plane rectangles of KITTI camera-frame boxes."""
    return np.column_stack(
        [labels.location[:, 0], labels.location[:, 2], labels.dimensions[:, 2], labels.dimensions[:, 1],
         -labels.rotation_y]
    )


def bev_overlap(det: LabelArrays, gt: LabelArrays) -> np.ndarray:
    """(D, G) exact rotated IoU in the camera ground plane (a box against itself gives 1)."""
    return rotated_iou_matrix(bev_rows(det), bev_rows(gt))


def box3d_overlap(det: LabelArrays, gt: LabelArrays) -> np.ndarray:
    """(D, G) 3D IoU: ground-plane intersection × vertical overlap over the union of volumes."""
    area = rotated_intersection_matrix(bev_rows(det), bev_rows(gt))
    det_bottom, gt_bottom = det.location[:, 1][:, None], gt.location[:, 1][None, :]
    det_top = det_bottom - det.dimensions[:, 0][:, None]
    gt_top = gt_bottom - gt.dimensions[:, 0][None, :]
    vertical = np.maximum(0.0, np.minimum(det_bottom, gt_bottom) - np.maximum(det_top, gt_top))
    inter = area * vertical
    det_volume = np.prod(det.dimensions, axis=1)[:, None]
    gt_volume = np.prod(gt.dimensions, axis=1)[None, :]
    union = det_volume + gt_volume - inter
    out = np.zeros_like(inter)
    np.divide(inter, union, out=out, where=(inter > 0) & (union > 0))
    return out
