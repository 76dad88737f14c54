"""KITTI depth-completion error metrics (Uhrig et al., 3DV 2017).

Per frame, over the pixels that have ground truth (depth > 0):

* RMSE, MAE of depth in millimetres;
* iRMSE, iMAE of inverse depth in 1/km (``1000 / depth_in_metres``).

The benchmark averages the per-frame values over frames (``mean_over_frames``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pipeline.errors import InputError


@dataclass(frozen=True)
class DepthMetrics:
    """Errors of one frame (or the mean over frames); ``n_pixels`` evaluated pixels (summed over frames)."""

    rmse_mm: float
    mae_mm: float
    irmse_per_km: float
    imae_per_km: float
    n_pixels: int


def depth_metrics(
    prediction_m: np.ndarray, ground_truth_m: np.ndarray, valid_mask: np.ndarray | None = None
) -> DepthMetrics:
    """Errors of a depth map (metres) against ground truth (metres, 0 = none), same shape (H, W).

    valid_mask: optional (H, W) bool restricting the evaluated pixels further
    (e.g. to where a sparse input exists). The prediction must be positive and
    finite wherever it is evaluated: inverse depth is undefined otherwise.
    """
    pred = np.asarray(prediction_m, np.float64)
    gt = np.asarray(ground_truth_m, np.float64)
    if pred.shape != gt.shape:
        raise InputError(f"prediction shape {pred.shape} differs from ground truth shape {gt.shape}")
    evaluated = np.isfinite(gt) & (gt > 0)
    if valid_mask is not None:
        mask = np.asarray(valid_mask, bool)
        if mask.shape != gt.shape:
            raise InputError(f"valid_mask shape {mask.shape} differs from ground truth shape {gt.shape}")
        evaluated &= mask
    n = int(np.count_nonzero(evaluated))
    if n == 0:
        raise InputError("no pixel has ground truth (depth > 0) to evaluate")
    p, g = pred[evaluated], gt[evaluated]
    bad = ~np.isfinite(p) | (p <= 0)
    if bad.any():
        raise InputError(f"prediction: {int(bad.sum())} evaluated pixels are not positive finite depths")
    err_mm = (p - g) * 1000.0
    inv_err_per_km = 1000.0 / p - 1000.0 / g
    return DepthMetrics(
        rmse_mm=float(np.sqrt(np.mean(err_mm**2))),
        mae_mm=float(np.mean(np.abs(err_mm))),
        irmse_per_km=float(np.sqrt(np.mean(inv_err_per_km**2))),
        imae_per_km=float(np.mean(np.abs(inv_err_per_km))),
        n_pixels=n,
    )


def mean_over_frames(frames: Sequence[DepthMetrics]) -> DepthMetrics:
    """The benchmark's figure: each metric averaged over frames (not over pooled pixels)."""
    if not frames:
        raise InputError("no frames to average")
    return DepthMetrics(
        rmse_mm=float(np.mean([f.rmse_mm for f in frames])),
        mae_mm=float(np.mean([f.mae_mm for f in frames])),
        irmse_per_km=float(np.mean([f.irmse_per_km for f in frames])),
        imae_per_km=float(np.mean([f.imae_per_km for f in frames])),
        n_pixels=int(sum(f.n_pixels for f in frames)),
    )
