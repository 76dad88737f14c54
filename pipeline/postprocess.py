"""From PIXOR's maps to 3D boxes: decode, rotated NMS, then z and h from the BEV occupancy.

PIXOR regresses only the BEV box. Each box's vertical extent is read from the
BEV occupancy: the occupied height slices of the grid cells under the box,
between robust low and high quantiles. The box's bottom is in the low slice
(its lower edge, or its centre with pseudo points); its height is the measured
extent averaged with the mean car height, weighted by how much occupied volume
was seen (a car seen by a few returns keeps about the mean height). No pass
over the points is needed. Boxes with too little occupancy sit on the road at
the preset's ground level with the mean KITTI car height. The camera pipeline
reads a grid without the pseudo points smeared across depth edges
(:class:`pipeline.bev.BevVoxelizer`, ``height_occupancy``). docs/models.md
("Box heights") gives the measurements.
"""

from __future__ import annotations

import numpy as np

from pipeline.iou import rotated_nms
from pipeline.presets import Preset
from pipeline.targets import OutputGrid, box_cells, decode_maps

_HEIGHT_RANGE = (1.2, 2.4)  # metres: cars and vans, not tree tops or kerbs
_LOW_Q, _HIGH_Q = 0.05, 0.95


def estimate_heights(bev_boxes: np.ndarray, bev: np.ndarray, preset: Preset,
                     with_pseudo: bool = False, mark: float = 1) -> tuple[np.ndarray, np.ndarray]:
    """Centre z and height h of each BEV box ``[x, y, l, w, yaw]`` from the (≥nz, ny, nx) BEV occupancy.

    with_pseudo: the occupancy holds pseudo points (the camera pipeline), which places bottoms differently.
    mark: the value of an occupied voxel (a BEV tensor: 1; :class:`pipeline.bev.BevVoxelizer`'s height
    grid: its ``height_mark``).
    """
    decode, grid = preset.decode, preset.bev
    stride = preset.pixor.output_stride
    n = bev_boxes.shape[0]
    h = np.full(n, decode.car_height)
    z = np.full(n, decode.ground_z + decode.car_height / 2)
    if n == 0:
        return z, h
    out = OutputGrid.from_bev(grid, stride)
    boxes7 = np.column_stack([bev_boxes[:, :2], np.zeros(n), bev_boxes[:, 2:4], np.ones(n), bev_boxes[:, 4]])
    k, rows, cols, _ = box_cells(boxes7, out)
    if k.size == 0:
        return z, h
    # The stride × stride block of BEV cells under each output cell, as flat cell indices, every height
    # slice, each with the box it lies under.
    block = (np.arange(stride)[:, None] * grid.nx + np.arange(stride)).reshape(-1)
    cells = ((rows * (stride * grid.nx) + cols * stride)[:, None] + block).reshape(-1)
    owner = np.repeat(k, block.size)
    slices, occupied = np.nonzero(np.take(bev[: grid.nz].reshape(grid.nz, -1), cells, axis=1) == mark)
    # Occupied voxels per box and height slice, counted. Not as a product with a one-hot matrix of the
    # cells' boxes: that goes through OpenBLAS, whose worker thread then spins for about 0.1 s on the
    # cores ONNX Runtime needs next (at a score threshold of 0.05 the next frame's depth net took 76 ms
    # instead of 44: docs/measurements.md, session 35).
    histogram = np.bincount(owner[occupied] * grid.nz + slices, minlength=n * grid.nz).reshape(n, grid.nz)
    total = histogram.sum(axis=1)
    cumulative = np.cumsum(histogram, axis=1)
    low = np.argmax(cumulative >= _LOW_Q * total[:, None], axis=1)
    high = np.argmax(cumulative >= _HIGH_Q * total[:, None], axis=1)
    # The high quantile already trims the roof: the top is the high slice's upper edge.
    in_slice = decode.bottom_in_slice_with_pseudo if with_pseudo else decode.bottom_in_slice
    bottom = grid.z_min + (low + in_slice) * grid.z_cell
    top = grid.z_min + (high + 1) * grid.z_cell
    enough = total >= decode.min_occupied_for_height
    measured = np.clip(top - bottom, *_HEIGHT_RANGE)
    # Car heights spread little (KITTI: 1.53 ± 0.14 m) while a sparse view measures them badly:
    # weigh the measurement by the occupied volume seen against height_prior_volume.
    seen = total * (grid.cell * grid.cell * grid.z_cell)
    measured = (seen * measured + decode.height_prior_volume * decode.car_height) / (seen + decode.height_prior_volume)
    h = np.where(enough, measured, h)
    z = np.where(enough, bottom + h / 2, z)
    return z, h


def boxes_from_maps(
    score: np.ndarray, regression: np.ndarray, bev: np.ndarray, preset: Preset,
    score_threshold: float | None = None, with_pseudo: bool = False, mark: float = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """PIXOR maps (ny/s, nx/s) and (6, ny/s, nx/s), s the preset's output stride (4 in every preset), plus the BEV
    occupancy → (K, 7) LiDAR boxes and (K,) scores, best first.

    bev: the BEV input, or any (≥nz, ny, nx) occupancy of the same grid (the heights read only that).
    with_pseudo: it holds pseudo points; mark: the value of its occupied voxels (:func:`estimate_heights`).
    """
    candidates, scores = decode_maps(
        score, regression, preset.bev, preset.pixor.output_stride, preset.decode, score_threshold
    )
    keep = rotated_nms(candidates, scores, preset.decode.nms_iou, preset.decode.max_detections)
    bev_boxes, scores = candidates[keep], scores[keep]
    z, h = estimate_heights(bev_boxes, bev, preset, with_pseudo, mark)
    boxes = np.column_stack([bev_boxes[:, 0], bev_boxes[:, 1], z, bev_boxes[:, 2], bev_boxes[:, 3], h, bev_boxes[:, 4]])
    return boxes.reshape(-1, 7), scores
