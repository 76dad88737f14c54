"""KITTI depth-completion error metrics (Uhrig et al., 3DV 2017).

Per frame, over the pixels that have ground truth (depth > 0):

* RMSE, MAE of depth in millimetres;
* iRMSE, iMAE of inverse depth in 1/km (``1000 / depth_in_metres``).

The benchmark averages the per-frame values over frames (``mean_over_frames``).
Beside them, the median absolute error (mm) in ground-truth depth bands of
10 m up to 40 m, where cars are detected: RMSE and MAE are dominated by the
far background and by outlines, the median says how well surfaces land.

On object folders with labels (the synthetic scenes) :func:`car_depth_errors`
also measures each car's own pixels: inside its 2D box, with a true depth
within 3 m of the car's. That is the depth the camera pipeline's PIXOR sees
the car by, and the median over cars by the car's distance says where the
depth net loses cars. :func:`car_box_shares` says what PIXOR gets from
those pixels: the share whose back-projected point lands in the car's BEV
box. A smaller median error does not ensure a larger share: a far car is a
few pixels wide, most of them on its outline, and a correction blurred across
the outline moves them off the car (at 20–35 m the exact correction blurred as
the edge net blurs it has half the net's median error and the same share;
docs/measurements.md, session 23). A larger share does not ensure a better
camera row either: :func:`car_box_shares` also counts the other pixels of the
car's 2D box that land on it, which a source smearing the car's depth over
its surroundings also puts there (session 24).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from evaluation.kitti_eval import DIFFICULTIES, too_hard_for
from pipeline.calib import Calibration, CropWindow, depth_crop
from pipeline.errors import InputError
from pipeline.kitti import Object3D


@dataclass(frozen=True)
class DepthMetrics:
    """Errors of one frame (or the mean over frames); ``n_pixels`` evaluated pixels (summed over frames)."""

    rmse_mm: float
    mae_mm: float
    irmse_per_km: float
    imae_per_km: float
    n_pixels: int
    # Median |error| (mm) per ground-truth band "0-10" … "30-40" m; NaN where a frame has no such pixel.
    median_abs_mm_by_band: dict[str, float] = field(default_factory=dict)


DEPTH_BANDS_M: tuple[tuple[float, float], ...] = ((0, 10), (10, 20), (20, 30), (30, 40))


def _band_name(low: float, high: float) -> str:
    return f"{low:g}-{high:g}"


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
    bands = {}
    for low, high in DEPTH_BANDS_M:
        in_band = (g >= low) & (g < high)
        bands[_band_name(low, high)] = float(np.median(np.abs(err_mm[in_band]))) if in_band.any() else float("nan")
    return DepthMetrics(
        rmse_mm=float(np.sqrt(np.mean(err_mm**2))),
        mae_mm=float(np.mean(np.abs(err_mm))),
        irmse_per_km=float(np.sqrt(np.mean(inv_err_per_km**2))),
        imae_per_km=float(np.mean(np.abs(inv_err_per_km))),
        n_pixels=n,
        median_abs_mm_by_band=bands,
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
        median_abs_mm_by_band={
            band: _nanmean([f.median_abs_mm_by_band.get(band, float("nan")) for f in frames])
            for band in (_band_name(*b) for b in DEPTH_BANDS_M)
        },
    )


def _nanmean(values: list[float]) -> float:
    """Mean of the finite values; NaN when there are none (no frame had pixels in the band)."""
    finite = [v for v in values if np.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


CAR_BANDS_M: tuple[tuple[float, float], ...] = ((0, 20), (20, 35), (35, 50))
CAR_SURFACE_M = 3.0  # a pixel of the box belongs to the car when its true depth is this close to the car's


def car_depth_errors(prediction_m: np.ndarray, ground_truth_m: np.ndarray,
                     cars: Sequence[tuple[tuple[float, float, float, float], float]]) -> list[tuple[float, float]]:
    """(car depth z, median |error| in mm over the car's pixels) per car that has any.

    cars: (2D box (left, top, right, bottom) in the maps' pixels, depth z of the car's centre in metres).
    A car's pixels are those inside its box whose true depth lies within :data:`CAR_SURFACE_M` of z.
    """
    pred = np.asarray(prediction_m, np.float64)
    gt = np.asarray(ground_truth_m, np.float64)
    found = []
    for box, z in cars:  # a handful of cars per frame; the pixels are array slices
        window, on_car = car_surface(gt, box, z)
        if on_car.any():
            error = np.abs(pred[window][on_car] - gt[window][on_car])
            found.append((float(z), float(np.median(error)) * 1000.0))
    return found


def car_surface(ground_truth_m: np.ndarray, box: tuple[float, float, float, float], z: float
                ) -> tuple[tuple[slice, slice], np.ndarray]:
    """A car's pixels: the window of its 2D box (left, top, right, bottom, clipped to the map) and, in it,
    the pixels whose true depth lies within :data:`CAR_SURFACE_M` of the car's depth z.

    The window holds the pixels whose centres (at integers, as :func:`box_in_view` places them) lie inside the
    box, edges included: the simulator's box of 3 × 3 pixels, edges at centre ± 0.5, is those 9 pixels (until
    session 50 a ring of one pixel around them too: 25). A box narrower than a pixel holds no centre across
    that side; it keeps the one pixel its middle lies in. A box off the map gives an empty window."""
    height, width = ground_truth_m.shape
    left, top, right, bottom = box
    window = (_centres_inside(top, bottom, height), _centres_inside(left, right, width))
    truth = ground_truth_m[window]
    return window, (truth > 0) & (np.abs(truth - z) <= CAR_SURFACE_M)


def _centres_inside(low: float, high: float, size: int) -> slice:
    """The pixels 0 … size − 1 whose centres lie in [low, high]; without one, the pixel holding the middle."""
    first, last = int(np.ceil(low)), int(np.floor(high))
    if last < first:  # narrower than a pixel, between two centres
        first = last = int(np.floor((low + high) / 2 + 0.5))
    start = min(max(first, 0), size)
    return slice(start, max(min(last + 1, size), start))


CAR_BOX_MARGIN_M = 0.2  # a car pixel's point is on the car when it lies in the BEV box grown by this


@dataclass(frozen=True)
class CarInView:
    """A labelled car as the depth metrics see it, in the depth maps' pixels and the camera frame."""

    box: tuple[float, float, float, float]  # 2D box (left, top, right, bottom) in the maps' pixels
    z: float  # depth of the box centre (camera z, metres)
    footprint: tuple[float, float, float, float, float]  # BEV box: centre x, z, length, width, rotation_y


def box_in_view(bbox: Sequence[float], crop: CropWindow, scale: float = 1.0) -> tuple[float, float, float, float]:
    """A 2D box (left, top, right, bottom) of the camera image in the pixels of its depth crop ``crop`` resized
    by ``scale`` (the network's view), pixel centres at integers: x' = s·(x − crop) + (s − 1)/2, as
    :func:`pipeline.preprocess.scale_calibration` maps them. The one mapping the evaluation and the trainer's
    car weights (models.data.car_pixels) share, so that both count the same pixels."""
    offset = (scale - 1.0) / 2.0
    left, top, right, bottom = (scale * (edge - shift) + offset for edge, shift in
                                zip(bbox, (crop.left, crop.top, crop.left, crop.top), strict=True))
    return left, top, right, bottom


def moderate_cars_in_view(labels: Sequence[Object3D] | None, image_hw: tuple[int, int], crop_hw: tuple[int, int],
                          scale: float = 1.0) -> list[CarInView]:
    """The KITTI-moderate cars among a frame's labels (2D box over 25 px high, occlusion ≤ 1, truncation ≤ 0.3:
    those the evaluator counts at moderate), their 2D boxes in the pixels of the image's depth crop
    (``crop_hw``) resized by ``scale`` (the network's view)."""
    crop = depth_crop(image_hw, *crop_hw)
    moderate = DIFFICULTIES.index("moderate")
    cars = []
    for label in labels or []:
        _, top, _, bottom = label.bbox
        # The evaluator's own rule, so that these are the cars its moderate AP counts: a car exactly 25 px high
        # is not one (the simulator's boxes are whole pixels: 32 such cars in data/sim/val besides its 1,520).
        if label.type.lower() == "car" and not too_hard_for(label.occluded, label.truncated, bottom - top)[moderate, 0]:
            box = box_in_view(label.bbox, crop, scale)
            x, _, z = label.location
            length, width = label.dimensions[2], label.dimensions[1]
            cars.append(CarInView(box=box, z=z, footprint=(x, z, length, width, label.rotation_y)))
    return cars


def car_box_shares(prediction_m: np.ndarray, ground_truth_m: np.ndarray, cars: Sequence[CarInView],
                   calib: Calibration) -> tuple[list[tuple[float, float]], list[tuple[float, float]]]:
    """Where each car's box pixels land in BEV: two lists of (car depth z, share).

    On the car: the share of the car's own pixels (:func:`car_surface`'s) whose point, back-projected with
    its predicted depth through ``calib`` (the calibration of exactly these maps), lies in the labelled
    footprint grown by :data:`CAR_BOX_MARGIN_M` on every side; with the true depth nearly all land in it.
    Stray: the share of the other pixels of the car's 2D box (a true depth off the car's surface: the road,
    what is behind it) that land there too. A depth source that smears the car's depth over its
    surroundings (the 16-line fill, say) puts many of both on the car, which widens and heightens the car
    PIXOR sees. A pixel without depth lands at the camera, outside every car. Cars without pixels of their
    own are left out of both lists, cars whose box has no other pixel out of the second.
    """
    pred = np.asarray(prediction_m, np.float64)
    gt = np.asarray(ground_truth_m, np.float64)
    # X_rect = d·K⁻¹[u, v, 1]ᵀ − K⁻¹t with P2 = [K | t]: only x and z matter in BEV.
    k_inv = np.linalg.inv(calib.P2[:, :3])
    offset = k_inv @ calib.P2[:, 3]

    def lands_in_box(window: tuple[slice, slice], pixels: np.ndarray, car: CarInView) -> np.ndarray:
        rows, cols = np.nonzero(pixels)
        v = rows + window[0].start
        u = cols + window[1].start
        d = pred[window][pixels]
        x = d * (k_inv[0, 0] * u + k_inv[0, 1] * v + k_inv[0, 2]) - offset[0]
        z = d * (k_inv[2, 0] * u + k_inv[2, 1] * v + k_inv[2, 2]) - offset[2]
        centre_x, centre_z, length, width, rotation_y = car.footprint
        dx, dz = x - centre_x, z - centre_z
        # KITTI's rotation_y turns the box's length axis from the camera's x towards −z.
        along = np.cos(rotation_y) * dx - np.sin(rotation_y) * dz
        across = np.sin(rotation_y) * dx + np.cos(rotation_y) * dz
        return (np.abs(along) <= length / 2 + CAR_BOX_MARGIN_M) & (np.abs(across) <= width / 2 + CAR_BOX_MARGIN_M)

    on_car_shares, stray_shares = [], []
    for car in cars:  # a handful of cars per frame; each car's pixels are one vectorized pass
        window, on_car = car_surface(gt, car.box, car.z)
        if not on_car.any():
            continue
        on_car_shares.append((float(car.z), float(lands_in_box(window, on_car, car).mean())))
        off_car = (gt[window] > 0) & ~on_car
        if off_car.any():
            stray_shares.append((float(car.z), float(lands_in_box(window, off_car, car).mean())))
    return on_car_shares, stray_shares


def car_shares_by_band(shares: Sequence[tuple[float, float]]) -> dict[str, dict[str, float]]:
    """Mean over cars of a :func:`car_box_shares` share, and the number of cars, per :data:`CAR_BANDS_M` band."""
    return _per_car_band(shares, "mean_share", np.mean)


def car_errors_by_band(errors: Sequence[tuple[float, float]]) -> dict[str, dict[str, float]]:
    """Median over cars of their median |error| (mm), and the number of cars, per :data:`CAR_BANDS_M` band."""
    return _per_car_band(errors, "median_mm", np.median)


def _per_car_band(per_car: Sequence[tuple[float, float]], name: str, reduce) -> dict[str, dict[str, float]]:
    """``{band: {name: reduce(the values of the band's cars) or NaN, "cars": n}}`` of (car depth, value) pairs."""
    out = {}
    for low, high in CAR_BANDS_M:
        values = [value for z, value in per_car if low <= z < high]
        out[_band_name(low, high)] = {name: float(reduce(values)) if values else float("nan"), "cars": len(values)}
    return out
