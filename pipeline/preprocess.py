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


def in_view(array: np.ndarray, preset: Preset, interpolation: int) -> np.ndarray:
    """An image or map of the whole camera image, cropped as the depth net sees it and resized to its input."""
    view = depth_crop(array.shape[:2], *preset.crop_hw).apply(array)
    height, width = preset.depth.input_hw
    if view.shape[:2] != (height, width):
        view = cv2.resize(view, (width, height), interpolation=interpolation)
    return view


def network_view(image: np.ndarray, calib: Calibration, preset: Preset) -> tuple[np.ndarray, Calibration]:
    """The depth net's view of a camera image: (H, W, 3) uint8 and its calibration."""
    return in_view(image, preset, cv2.INTER_AREA), view_calibration(image.shape[:2], calib, preset)


def view_calibration(image_hw: tuple[int, int], calib: Calibration, preset: Preset) -> Calibration:
    """The calibration of the depth net's view of an image of this size (:func:`network_view` without pixels)."""
    crop = depth_crop(image_hw, *preset.crop_hw)
    return scale_calibration(crop_calibration(calib, crop), preset.depth.input_scale)


def depth_inputs(image: np.ndarray, points: np.ndarray, calib: Calibration, preset: Preset) -> DepthInputs:
    """Everything ``depth.onnx`` needs for one frame."""
    view, view_calib = network_view(image, calib, preset)
    sparse = sparse_depth_map(points, view_calib, view.shape[:2])
    rgb = planar_float(view)
    return DepthInputs(rgb=rgb, sparse_depth=sparse[None, None], calib=view_calib)


def planar_float(view: np.ndarray) -> np.ndarray:
    """An (H, W, 3) uint8 image as the network's float32 (1, 3, H, W) input, raw 0–255.

    OpenCV splits the channels and each plane is cast in one pass: 91 µs for the edge view here, against
    155 µs for NumPy's cast of the strided (3, H, W) transpose.
    """
    planes = cv2.split(view)
    rgb = np.empty((1, len(planes), *view.shape[:2]), np.float32)
    for channel, plane in enumerate(planes):
        rgb[0, channel] = plane
    return rgb


def depth_view(depth: np.ndarray, preset: Preset) -> np.ndarray:
    """A dense depth map of the whole camera image (H, W, metres, 0 = none) in the depth net's view.

    Same crop as :func:`network_view`; resized by nearest neighbour, which keeps every depth a
    real one (no blend of a car and what is behind it across its outline).
    """
    return np.ascontiguousarray(in_view(depth, preset, cv2.INTER_NEAREST), dtype=np.float32)


def downscale_sparse_depth(sparse: np.ndarray, factor: int) -> np.ndarray:
    """Shrink a sparse depth map by an integer factor, nearest return per block (0 = none).

    A block of factor × factor pixels becomes one pixel whose centre is the
    block's centre, the same geometry as :func:`scale_calibration`.
    """
    if factor == 1:
        return sparse
    h, w = sparse.shape
    if h % factor or w % factor:
        raise ValueError(f"sparse depth {w}×{h} is not divisible by the factor {factor}")
    blocks = np.where(sparse > 0, sparse, np.inf).reshape(h // factor, factor, w // factor, factor)
    nearest = blocks.min(axis=(1, 3))
    return np.where(np.isfinite(nearest), nearest, 0).astype(np.float32)


def view_from_depth_png(image: np.ndarray, sparse: np.ndarray, preset: Preset) -> tuple[np.ndarray, np.ndarray]:
    """Depth-net inputs from a KITTI depth-completion frame (image + projected sparse depth PNG).

    Returns rgb float32 (1, 3, H, W) and sparse_depth float32 (1, 1, H, W) of the
    network's view: the same crop as object frames, the sparse map shrunk by
    nearest return (no calibration needed).
    """
    sparse_view = depth_crop(image.shape[:2], *preset.crop_hw).apply(sparse)  # the image's crop, as network_view
    if sparse_view.shape != tuple(preset.depth.input_hw):
        sparse_view = downscale_sparse_depth(sparse_view, round(1 / preset.depth.input_scale))
    rgb = planar_float(in_view(image, preset, cv2.INTER_AREA))
    return rgb, np.ascontiguousarray(sparse_view[None, None], dtype=np.float32)
