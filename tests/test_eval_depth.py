"""evaluation.depth_metrics at its boundaries, where a mutation test found them unpinned: band edges, the window
of a car's box, what a car's pixels are, the network's view of a label, and where a pixel's point lands."""

from __future__ import annotations

import math

import numpy as np
import pytest

from evaluation.depth_metrics import (
    CarInView,
    car_box_shares,
    car_depth_errors,
    car_errors_by_band,
    car_surface,
    depth_metrics,
    mean_over_frames,
    moderate_cars_in_view,
)
from pipeline.calib import Calibration
from pipeline.kitti import Object3D


def test_a_pixel_on_a_band_edge_belongs_to_the_band_above():
    """Bands are [low, high): a pixel whose true depth is exactly 10 m is in 10-20, not 0-10."""
    gt = np.array([[5.0, 10.0]])
    metrics = depth_metrics(gt + np.array([[0.1, 0.5]]), gt)
    assert metrics.median_abs_mm_by_band["0-10"] == pytest.approx(100.0)
    assert metrics.median_abs_mm_by_band["10-20"] == pytest.approx(500.0)


def test_a_band_is_averaged_over_the_frames_that_have_pixels_in_it():
    near_only = depth_metrics(np.array([[5.1]]), np.array([[5.0]]))
    both = depth_metrics(np.array([[5.3, 25.2]]), np.array([[5.0, 25.0]]))
    mean = mean_over_frames([near_only, both])
    assert mean.median_abs_mm_by_band["0-10"] == pytest.approx(200.0)  # (100 + 300) / 2
    assert mean.median_abs_mm_by_band["20-30"] == pytest.approx(200.0)  # the one frame that has it


def test_inverse_depth_errors_of_both_signs_do_not_cancel():
    gt = np.array([[10.0, 10.0]])
    metrics = depth_metrics(np.array([[8.0, 12.5]]), gt)  # 1000/8 − 100 = 25, 1000/12.5 − 100 = −20 (1/km)
    assert metrics.imae_per_km == pytest.approx(22.5) and metrics.irmse_per_km == pytest.approx(math.sqrt(512.5))


def test_a_cars_window_holds_its_boxs_last_row_and_column_and_is_clipped_to_the_map():
    truth = np.full((10, 12), 20.0)
    window, on_car = car_surface(truth, (2.0, 3.0, 5.0, 6.0), 20.0)
    assert window == (slice(3, 7), slice(2, 6)) and on_car.shape == (4, 4)  # rows 3 … 6, columns 2 … 5
    window, _ = car_surface(truth, (-2.5, -3.0, 4.2, 5.0), 20.0)
    assert window == (slice(0, 6), slice(0, 5))  # from the map's edge, up to the last centre inside, 4 (until s50 5)
    window, _ = car_surface(truth, (8.0, 7.0, 30.0, 25.0), 20.0)
    assert window == (slice(7, 10), slice(8, 12))


def test_a_cars_pixels_are_within_three_metres_of_its_depth_and_their_error_is_the_median():
    truth = np.array([[17.5, 22.5, 23.5, 20.0, 20.0, 0.0]])
    _, on_car = car_surface(truth, (0.0, 0.0, 5.0, 0.0), 20.0)
    assert on_car.tolist() == [[True, True, False, True, True, False]]
    prediction = truth + np.array([[0.1, 0.1, 5.0, 0.1, 0.9, 0.0]])
    # The four car pixels' errors: 100, 100, 100, 900 mm; the median, not the mean (300).
    assert car_depth_errors(prediction, truth, [((0.0, 0.0, 5.0, 0.0), 20.0)]) == [(20.0, pytest.approx(100.0))]


def test_a_car_on_a_band_edge_belongs_to_the_band_above():
    bands = car_errors_by_band([(20.0, 100.0), (35.0, 300.0)])
    assert (bands["0-20"]["cars"], bands["20-35"]["cars"], bands["35-50"]["cars"]) == (0, 1, 1)


def test_moderate_cars_in_the_networks_view():
    """A label's 2D box in the depth crop's pixels (crop of a 375 × 1242 image to 352 × 1216: 23 rows off the
    top, 13 columns off the left) resized by 0.5 with pixel centres at integers (x' = 0.5 x − 0.25); the BEV
    footprint is (x, z, length, width, rotation_y) from the label's (h, w, l)."""
    label = Object3D(type="Car", truncated=0.0, occluded=0, alpha=0.0, bbox=(113.0, 123.0, 213.0, 223.0),
                     dimensions=(1.5, 1.6, 4.2), location=(1.0, 1.6, 20.0), rotation_y=0.3)
    (car,) = moderate_cars_in_view([label], (375, 1242), (352, 1216), scale=0.5)
    assert car.box == pytest.approx((49.75, 49.75, 99.75, 99.75))
    assert car.z == 20.0 and car.footprint == (1.0, 20.0, 4.2, 1.6, 0.3)
    (full,) = moderate_cars_in_view([label], (375, 1242), (352, 1216))
    assert full.box == pytest.approx((100.0, 100.0, 200.0, 200.0))


# A camera 0.5 m to the right of the rectified frame's origin (P2 = K [I | (-0.5, 0, 0)]): f 1000 px, centre
# (600, 200). A pixel (u, v) at depth d is the point x = d (u − 600) / 1000 + 0.5, z = d.
CALIB = Calibration(P2=np.array([[1000.0, 0.0, 600.0, -500.0], [0.0, 1000.0, 200.0, 0.0], [0.0, 0.0, 1.0, 0.0]]),
                    R0_rect=np.eye(3), Tr_velo_to_cam=np.eye(3, 4))


def _share_on_car(along: float, across: float, rotation_y: float) -> float:
    """The on-car share of one pixel whose point lies ``along`` / ``across`` the footprint's axes from its centre
    (a 4 m × 1.6 m car)."""
    u, v, depth = 700, 150, 20.0
    truth = np.zeros((300, 800))
    truth[v, u] = depth
    x, z = depth * (u - 600) / 1000 + 0.5, depth
    # KITTI's rotation_y turns the length axis from x towards −z: length axis (cos, −sin), width axis (sin, cos).
    centre_x = x - along * math.cos(rotation_y) - across * math.sin(rotation_y)
    centre_z = z + along * math.sin(rotation_y) - across * math.cos(rotation_y)
    car = CarInView(box=(u - 2, v - 2, u + 2, v + 2), z=depth, footprint=(centre_x, centre_z, 4.0, 1.6, rotation_y))
    (on_car,), _ = car_box_shares(truth, truth, [car], CALIB)
    return on_car[1]


@pytest.mark.parametrize("rotation_y", [0.0, 0.5, -2.0])
def test_a_point_lands_on_the_car_within_its_footprint_grown_by_the_margin(rotation_y: float):
    """Half the length is 2.0 m and half the width 0.8 m, each grown by 0.2 m."""
    assert _share_on_car(2.1, 0.0, rotation_y) == 1.0 and _share_on_car(2.3, 0.0, rotation_y) == 0.0
    assert _share_on_car(-2.1, 0.5, rotation_y) == 1.0 and _share_on_car(0.0, -1.1, rotation_y) == 0.0
    assert _share_on_car(0.0, 0.95, rotation_y) == 1.0


def test_pixels_without_true_depth_are_not_stray():
    """The stray share is over the box's other pixels *with* a true depth: one without truth is no pixel at all."""
    truth = np.zeros((300, 800))
    truth[150, 700] = 20.0
    prediction = truth.copy()
    prediction[151, 700] = 20.0  # predicted on the car, but the truth has nothing there
    x = 20.0 * 100 / 1000 + 0.5
    car = CarInView(box=(698, 148, 702, 152), z=20.0, footprint=(x, 20.0, 4.0, 1.6, 0.0))
    on_car, stray = car_box_shares(prediction, truth, [car], CALIB)
    assert on_car == [(20.0, 1.0)] and stray == []
