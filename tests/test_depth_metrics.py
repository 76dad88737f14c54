"""Depth-completion metrics: synthetic cases with known answers and the shared real KITTI frame."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from evaluation.depth_metrics import (
    CarInView,
    DepthMetrics,
    car_box_shares,
    car_depth_errors,
    car_errors_by_band,
    car_shares_by_band,
    car_surface,
    depth_metrics,
    mean_over_frames,
)
from pipeline.calib import sparse_depth_map
from pipeline.errors import InputError
from pipeline.frame import load_frame
from pipeline.kitti import read_depth_png
from tests.conftest import KITTI

FRAME = Path(__file__).resolve().parent / "data" / "depth_completion"


def test_constant_offset():
    gt = np.zeros((4, 5))
    gt[1, 1:4] = [10.0, 20.0, 40.0]
    pred = np.full(gt.shape, 7.0)
    pred[gt > 0] = gt[gt > 0] + 0.1  # 100 mm too far everywhere
    m = depth_metrics(pred, gt)
    assert m.n_pixels == 3
    assert m.rmse_mm == pytest.approx(100.0) and m.mae_mm == pytest.approx(100.0)
    inverse = [1000 / (d + 0.1) - 1000 / d for d in (10.0, 20.0, 40.0)]  # 1/km
    assert m.imae_per_km == pytest.approx(np.mean(np.abs(inverse)))
    assert m.irmse_per_km == pytest.approx(math.sqrt(np.mean(np.square(inverse))))


def test_real_frame_velodyne_against_groundtruth():
    gt = read_depth_png(FRAME / "groundtruth" / "0000000005.png")
    sparse = read_depth_png(FRAME / "velodyne_raw" / "0000000005.png")
    both = (gt > 0) & (sparse > 0)
    full = depth_metrics(sparse, gt, valid_mask=sparse > 0)
    assert full.n_pixels == int(both.sum()) > 1000

    # A few pixels by hand, with scalar arithmetic.
    rows, cols = np.nonzero(both)
    picks = list(zip(rows[:: len(rows) // 6][:6].tolist(), cols[:: len(rows) // 6][:6].tolist()))
    mask = np.zeros_like(both)
    errors_mm, inverse_errors = [], []
    for r, c in picks:
        mask[r, c] = True
        p, g = float(sparse[r, c]), float(gt[r, c])
        errors_mm.append((p - g) * 1000.0)
        inverse_errors.append(1.0 / (p / 1000.0) - 1.0 / (g / 1000.0))
    few = depth_metrics(sparse, gt, valid_mask=mask)
    assert few.n_pixels == len(picks)
    assert few.rmse_mm == pytest.approx(math.sqrt(sum(e * e for e in errors_mm) / len(picks)))
    assert few.mae_mm == pytest.approx(sum(abs(e) for e in errors_mm) / len(picks))
    assert few.irmse_per_km == pytest.approx(math.sqrt(sum(e * e for e in inverse_errors) / len(picks)))
    assert few.imae_per_km == pytest.approx(sum(abs(e) for e in inverse_errors) / len(picks))

    # The raw scan agrees with the accumulated ground truth to within a few metres RMS
    # (outliers at occlusion edges), far better than a constant guess.
    assert 0 < full.mae_mm < full.rmse_mm < 5000
    constant = depth_metrics(np.full(gt.shape, float(np.median(gt[gt > 0]))), gt, valid_mask=sparse > 0)
    assert constant.mae_mm > 5 * full.mae_mm


def test_median_error_per_depth_band():
    gt = np.array([[5.0, 8.0, 9.0, 15.0, 35.0, 60.0]])
    pred = gt + np.array([[0.1, -0.3, 0.2, 2.0, -1.0, 9.0]])
    m = depth_metrics(pred, gt)
    assert m.median_abs_mm_by_band["0-10"] == pytest.approx(200.0)  # median of 100, 300, 200 mm
    assert m.median_abs_mm_by_band["10-20"] == pytest.approx(2000.0)
    assert math.isnan(m.median_abs_mm_by_band["20-30"])  # no pixel there; 60 m is past every band
    assert m.median_abs_mm_by_band["30-40"] == pytest.approx(1000.0)
    other = depth_metrics(gt + 0.4, gt)
    mean = mean_over_frames([m, other])
    assert mean.median_abs_mm_by_band["20-30"] != mean.median_abs_mm_by_band["20-30"]  # NaN in both frames
    assert mean.median_abs_mm_by_band["0-10"] == pytest.approx(300.0)  # (200 + 400) / 2


def test_mean_is_over_frames():
    a = DepthMetrics(1000.0, 500.0, 4.0, 2.0, 10)
    b = DepthMetrics(3000.0, 700.0, 6.0, 4.0, 30)
    m = mean_over_frames([a, b])
    assert (m.rmse_mm, m.mae_mm, m.irmse_per_km, m.imae_per_km, m.n_pixels) == (2000.0, 600.0, 5.0, 3.0, 40)


def test_errors_name_the_problem():
    gt = np.zeros((2, 2))
    with pytest.raises(InputError, match="no pixel has ground truth"):
        depth_metrics(np.ones((2, 2)), gt)
    gt[0, 0] = 5.0
    with pytest.raises(InputError, match="shape"):
        depth_metrics(np.ones((3, 2)), gt)
    with pytest.raises(InputError, match="not positive finite"):
        depth_metrics(np.zeros((2, 2)), gt)
    with pytest.raises(InputError, match="no frames"):
        mean_over_frames([])


def test_car_pixels_are_the_box_pixels_on_the_car_surface():
    """Inside a car's box only the pixels whose true depth is within 3 m of the car's count: the road
    and the wall behind it, also inside the box, do not."""
    gt = np.full((20, 30), 60.0)  # a wall far behind
    gt[10:20, :] = 8.0  # road in front
    gt[5:15, 10:20] = 25.0  # the car's surface, 25 m away
    gt[0, 0] = 0.0  # a pixel without ground truth
    pred = gt.copy()
    pred[5:15, 10:20] += 0.5  # 500 mm too far on the car
    pred[:5] += 9.0  # and far off on the wall (inside the box too)
    cars = [((8.0, 2.0, 21.0, 17.0), 26.0), ((25.0, 0.0, 29.0, 3.0), 45.0)]  # the second box holds no surface
    assert car_depth_errors(pred, gt, cars) == [(26.0, pytest.approx(500.0))]
    errors = [(10.0, 100.0), (12.0, 300.0), (40.0, 900.0)]
    bands = car_errors_by_band(errors)
    assert bands["0-20"] == {"median_mm": 200.0, "cars": 2} and bands["35-50"] == {"median_mm": 900.0, "cars": 1}
    assert bands["20-35"]["cars"] == 0 and math.isnan(bands["20-35"]["median_mm"])


def _cars_in_full_image(frame) -> list[CarInView]:
    return [CarInView(box=label.bbox, z=label.location[2],
                      footprint=(label.location[0], label.location[2], label.dimensions[2], label.dimensions[1],
                                 label.rotation_y))
            for label in frame.labels if label.type == "Car"]


@pytest.mark.parametrize("frame_id", ["000004", "000006"])
def test_car_points_land_in_their_boxes_with_the_true_depth_and_leave_them_when_nearer(frame_id):
    """On the shared real frames (cars at 20–51 m, seen from behind and from the side), the 64-line
    returns on each labelled car land in its BEV box; moved towards the camera they leave it (the
    visible faces are the box's near faces), and 5 m farther they are past it."""
    frame = load_frame(KITTI, frame_id)
    truth = sparse_depth_map(frame.points, frame.calib, frame.image_hw)
    cars = _cars_in_full_image(frame)
    on_truth, _ = car_box_shares(truth, truth, cars, frame.calib)
    assert [z for z, _ in on_truth] == [car.z for car in cars]
    assert all(share >= 0.75 for _, share in on_truth) and np.mean([s for _, s in on_truth]) >= 0.85
    nearer, _ = car_box_shares(np.where(truth > 0, truth - 1.5, 0), truth, cars, frame.calib)
    assert np.mean([s for _, s in nearer]) <= 0.25
    farther, _ = car_box_shares(np.where(truth > 0, truth + 5.0, 0), truth, cars, frame.calib)
    assert all(share == 0.0 for _, share in farther)


@pytest.mark.parametrize("frame_id", ["000004", "000006"])
def test_the_other_pixels_of_a_cars_box_stay_off_it_with_the_true_depth_and_not_when_smeared(frame_id):
    """The 64-line returns of each car's 2D box that are not on the car (road, what is behind it) land off
    the car; given the car's own depth, as a fill that smears a car over its surroundings gives them,
    many of them land on it."""
    frame = load_frame(KITTI, frame_id)
    truth = sparse_depth_map(frame.points, frame.calib, frame.image_hw)
    cars = _cars_in_full_image(frame)
    _, stray = car_box_shares(truth, truth, cars, frame.calib)
    assert stray and all(share <= 0.02 for _, share in stray)
    smeared = truth.copy()
    for car in cars:  # every return of the box at the car's depth (along its own ray)
        window, _ = car_surface(truth, car.box, car.z)
        smeared[window] = np.where(truth[window] > 0, car.z, 0.0)
    _, on_smear = car_box_shares(smeared, truth, cars, frame.calib)
    assert [z for z, _ in on_smear] == [z for z, _ in stray]
    assert np.mean([share for _, share in on_smear]) >= 0.25
    # Nothing predicted there: no point lands anywhere near a car.
    assert all(share == 0.0 for _, share in car_box_shares(np.zeros_like(truth), truth, cars, frame.calib)[1])


def test_car_shares_by_band_average_the_cars_of_each_band():
    bands = car_shares_by_band([(10.0, 0.5), (15.0, 1.0), (40.0, 0.25)])
    assert bands["0-20"] == {"mean_share": 0.75, "cars": 2} and bands["35-50"] == {"mean_share": 0.25, "cars": 1}
    assert bands["20-35"]["cars"] == 0 and math.isnan(bands["20-35"]["mean_share"])
