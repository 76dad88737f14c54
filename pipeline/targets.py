"""PIXOR targets: boxes ↔ (score map, 6-channel regression map) on the output grid.

The output grid has the BEV grid's layout at 1/``stride`` resolution: row i,
column j is the cell centred at ``y_min + (i + ½)·s``, ``x_min + (j + ½)·s``
with ``s = cell · stride``. A cell is positive when its centre lies inside a
box (the box with the nearest centre wins where boxes overlap). Its regression
target is ``cos θ, sin θ, dx, dy, log w, log l`` (dx, dy from the cell centre
to the box centre), stored normalised as ``(t - mean) / std``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.presets import BevGrid, DecodeConfig

# Decoded log sizes are clipped to this before exp: sides from 0.05 to 20 m, wide around any car's (1.5–5 m).
# A cell's regression is unbounded and exp overflows past 709: an infinite box's rotated IoU with any box, its
# own copy included, comes out 0 (with NumPy warnings), so NMS would keep every one. export/port_spec.py
# publishes the same range for ports.
LOG_SIZE_CLIP = (-3.0, 3.0)


@dataclass(frozen=True)
class OutputGrid:
    """Geometry of the network's output maps."""

    x_min: float
    y_min: float
    step: float  # metres per output cell
    ny: int
    nx: int

    @classmethod
    def from_bev(cls, grid: BevGrid, stride: int) -> OutputGrid:
        return cls(grid.x_min, grid.y_min, grid.cell * stride, grid.ny // stride, grid.nx // stride)

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """(ny, nx) arrays of cell-centre x and y."""
        xs = self.x_min + (np.arange(self.nx) + 0.5) * self.step
        ys = self.y_min + (np.arange(self.ny) + 0.5) * self.step
        return np.meshgrid(xs, ys)


@dataclass(frozen=True)
class PixorTargets:
    """score: float32 (ny, nx) 1 on positive cells; regression: float32 (6, ny, nx) normalised."""

    score: np.ndarray
    regression: np.ndarray


def box_cells(boxes: np.ndarray, out: OutputGrid) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Output cells whose centre lies inside a box: (box index, row, col, squared distance to centre).

    Each box is tested only against the cells of its bounding square (one
    (K, W, W) block for all boxes), never against the whole map.
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    empty = np.zeros(0, np.int64)
    if boxes.shape[0] == 0:
        return empty, empty, empty, np.zeros(0)
    radius = 0.5 * np.hypot(boxes[:, 3], boxes[:, 4])
    window = int(np.ceil(2 * radius.max() / out.step)) + 2
    col0 = np.floor((boxes[:, 0] - radius - out.x_min) / out.step).astype(np.int64)
    row0 = np.floor((boxes[:, 1] - radius - out.y_min) / out.step).astype(np.int64)
    offsets = np.arange(window)
    rows = row0[:, None, None] + offsets[None, :, None]  # (K, W, 1)
    cols = col0[:, None, None] + offsets[None, None, :]  # (K, 1, W)
    rel_x = out.x_min + (cols + 0.5) * out.step - boxes[:, 0, None, None]
    rel_y = out.y_min + (rows + 0.5) * out.step - boxes[:, 1, None, None]
    cos, sin = np.cos(boxes[:, 6])[:, None, None], np.sin(boxes[:, 6])[:, None, None]
    along = rel_x * cos + rel_y * sin
    across = -rel_x * sin + rel_y * cos
    inside = (
        (np.abs(along) <= boxes[:, 3, None, None] / 2) & (np.abs(across) <= boxes[:, 4, None, None] / 2)
        & (rows >= 0) & (rows < out.ny) & (cols >= 0) & (cols < out.nx)
    )
    k, i, j = np.nonzero(inside)
    distance = rel_x[k, 0, j] ** 2 + rel_y[k, i, 0] ** 2
    return k, row0[k] + i, col0[k] + j, distance


def assign_cells(boxes: np.ndarray, out: OutputGrid) -> np.ndarray:
    """Index of the box owning each output cell, -1 for background: int64 (ny, nx).

    Where boxes overlap, the box with the nearest centre owns the cell.
    """
    owner = np.full((out.ny, out.nx), -1, dtype=np.int64)
    k, rows, cols, distance = box_cells(boxes, out)
    if k.size == 0:
        return owner
    flat = rows * out.nx + cols
    order = np.lexsort((distance, flat))  # per cell, nearest centre first
    flat, k = flat[order], k[order]
    first = np.ones(flat.size, dtype=bool)
    first[1:] = flat[1:] != flat[:-1]
    owner.reshape(-1)[flat[first]] = k[first]
    return owner


def encode_targets(boxes: np.ndarray, grid: BevGrid, stride: int, decode: DecodeConfig) -> PixorTargets:
    """(N, 7) LiDAR-frame boxes → PIXOR score and regression targets."""
    out = OutputGrid.from_bev(grid, stride)
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    owner = assign_cells(boxes, out)
    score = (owner >= 0).astype(np.float32)
    regression = np.zeros((6, out.ny, out.nx), dtype=np.float32)
    rows, cols = np.nonzero(owner >= 0)
    if rows.size:
        b = boxes[owner[rows, cols]]
        cx, cy = out.centres()
        raw = np.stack([
            np.cos(b[:, 6]), np.sin(b[:, 6]),
            b[:, 0] - cx[rows, cols], b[:, 1] - cy[rows, cols],
            np.log(b[:, 4]), np.log(b[:, 3]),
        ])
        mean = np.asarray(decode.reg_mean)[:, None]
        std = np.asarray(decode.reg_std)[:, None]
        regression[:, rows, cols] = (raw - mean) / std
    return PixorTargets(score=score, regression=regression)


def _highest(values: np.ndarray, count: int) -> np.ndarray:
    """Positions of the ``count`` highest ``values``, ascending; of equal values at the cut, the first ones.
    For ``count`` < ``values.size`` (:func:`decode_maps` calls it only past ``max_candidates``); none for 0.

    Not ``np.argpartition``'s selection: which of the equal values it keeps, and the order it returns them
    in, follow NumPy's sort kernels for the CPU (AVX-512 or not), and the same maps gave other boxes on an
    AVX2 machine than on an AVX-512 one (session 42)."""
    if count <= 0:  # a manifest's max_candidates of 0: no candidates, as np.argpartition's [:0] gave
        return np.zeros(0, np.intp)
    cut = np.partition(values, values.size - count)[values.size - count]  # the count-th highest value
    above = np.flatnonzero(values > cut)
    at_cut = np.flatnonzero(values == cut)[: count - above.size]
    return np.sort(np.concatenate([above, at_cut]))


def decode_maps(
    score: np.ndarray, regression: np.ndarray, grid: BevGrid, stride: int, decode: DecodeConfig,
    score_threshold: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Network maps → candidate BEV boxes ``[x, y, l, w, yaw]`` (K, 5) and scores (K,), best first.

    score: (ny, nx) probabilities; regression: (6, ny, nx) normalised targets.
    Keeps cells at or above the threshold, at most ``decode.max_candidates`` of them: the highest scores,
    and of equal scores at the cut the first cells in row-major order (:func:`_highest`).
    """
    # A Python float, compared with the float32 scores in float32 whatever the caller passed: an np.float64
    # threshold made NumPy 2 compare in float64 and drop a score equal to it in float32 that the CLI's and the
    # service's float threshold keeps.
    threshold = float(decode.score_threshold if score_threshold is None else score_threshold)
    out = OutputGrid.from_bev(grid, stride)
    flat_score = score.reshape(-1)
    candidates = np.flatnonzero(flat_score >= threshold)  # in cell order
    if candidates.size > decode.max_candidates:
        candidates = candidates[_highest(flat_score[candidates], decode.max_candidates)]
    # Equal scores (sigmoids saturate at 1.0f on confident cars) in cell order, which decides what NMS keeps.
    candidates = candidates[np.argsort(-flat_score[candidates], kind="stable")]
    rows, cols = np.divmod(candidates, out.nx)
    mean = np.asarray(decode.reg_mean, np.float64)[:, None]
    std = np.asarray(decode.reg_std, np.float64)[:, None]
    raw = regression.reshape(6, -1)[:, candidates].astype(np.float64) * std + mean
    cx = out.x_min + (cols + 0.5) * out.step
    cy = out.y_min + (rows + 0.5) * out.step
    boxes = np.column_stack([
        cx + raw[2], cy + raw[3], np.exp(np.clip(raw[5], *LOG_SIZE_CLIP)), np.exp(np.clip(raw[4], *LOG_SIZE_CLIP)),
        np.arctan2(raw[1], raw[0]),
    ])
    return boxes, flat_score[candidates].astype(np.float64)
