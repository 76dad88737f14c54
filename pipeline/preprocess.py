"""Network inputs from a frame: the depth-net crop of the image and the sparse depth it sees.

The depth network sees the KITTI depth-completion crop (bottom 352 rows,
centre 1216 columns), resized by the preset's ``input_scale``. Its sparse
depth input is the LiDAR scan projected straight into that resized view with
an exactly matching calibration, so no depth is ever interpolated.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.calib import Calibration, crop_calibration, depth_crop, sparse_depth_map
from pipeline.presets import Preset


@dataclass(frozen=True)
class DepthInputs:
    """rgb: float32 (1, 3, H, W) raw 0–255; sparse_depth: float32 (1, 1, H, W) metres, 0 = none;
    calib: the calibration of exactly this (H, W) view."""

    rgb: np.ndarray
    sparse_depth: np.ndarray
    calib: Calibration


def scale_calibration(calib: Calibration, scale: float) -> Calibration:
    """Calibration of an image resized by ``scale`` (area resampling).

    Pixel centres sit at integer coordinates, so a resized pixel u' covers
    original pixels around u = (u' + ½)/s − ½: u' = s·u + (s − 1)/2.
    """
    if scale == 1.0:
        return calib
    offset = (scale - 1.0) / 2.0
    resize = np.array([[scale, 0.0, offset], [0.0, scale, offset], [0.0, 0.0, 1.0]])
    return Calibration(P2=resize @ calib.P2, R0_rect=calib.R0_rect, Tr_velo_to_cam=calib.Tr_velo_to_cam)


def network_view(image: np.ndarray, calib: Calibration, preset: Preset) -> tuple[np.ndarray, Calibration]:
    """The depth net's view of a camera image: (H, W, 3) uint8 and its calibration."""
    crop = depth_crop(image.shape[:2], *preset.crop_hw)
    view = crop.apply(image)
    height, width = preset.depth.input_hw
    if view.shape[:2] != (height, width):
        view = cv2.resize(view, (width, height), interpolation=cv2.INTER_AREA)
    return view, scale_calibration(crop_calibration(calib, crop), preset.depth.input_scale)


def depth_inputs(image: np.ndarray, points: np.ndarray, calib: Calibration, preset: Preset) -> DepthInputs:
    """Everything ``depth.onnx`` needs for one frame."""
    view, view_calib = network_view(image, calib, preset)
    sparse = sparse_depth_map(points, view_calib, view.shape[:2])
    rgb = np.ascontiguousarray(view.transpose(2, 0, 1)[None], dtype=np.float32)
    return DepthInputs(rgb=rgb, sparse_depth=sparse[None, None], calib=view_calib)
