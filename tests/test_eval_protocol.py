"""The devkit rules of evaluation.kitti_eval at their boundaries, where a mutation test found them unpinned.

Each expectation is reasoned from evaluate_object.cpp's rules (cleanData, getThresholds, computeStatistics,
the loader that decides which metrics to evaluate), not read off this code's output.
"""

from __future__ import annotations

import dataclasses
import math
import statistics

import numpy as np
import pytest

from evaluation.kitti_eval import (
    DIFFICULTIES,
    available_metrics,
    bootstrap,
    bootstrap_interval,
    evaluate,
    recall_thresholds,
)
from tests.test_kitti_eval import dontcare, frames, obj, run_eval


def test_a_recall_exactly_between_two_sampling_points_keeps_its_score():
    """getThresholds skips a score only when the next score's recall is *strictly* closer to the sampling point.
    52 cars, 7 true positives: after 5 kept scores the point is 5/40 = 6.5/52, exactly between recall 6/52 and
    7/52, so the sixth score is kept (a ``<=`` would skip it and move every later threshold)."""
    scores = 1.0 - np.arange(7) / 100
    np.testing.assert_array_equal(recall_thresholds(scores, 52), scores)
    # 45 cars, 14 found: the point 13/40 = 14.625/45 is exactly between 14/45 and 15/45 at the 14th score … which
    # is the last one, always kept; the tie that matters is the 13th: 12/40 = 13.5/45 between 13/45 and 14/45.
    scores = 1.0 - np.arange(14) / 100
    np.testing.assert_array_equal(recall_thresholds(scores, 45), scores)


def test_more_true_positives_than_cars_is_refused():
    """Recall cannot pass 1: more true positives than counted cars would give more than 41 thresholds."""
    with pytest.raises(RuntimeError, match="recall thresholds for 10 ground truth"):
        recall_thresholds(np.linspace(1.0, 0.0, 100), 10)


def test_which_metrics_a_detection_carries_at_the_field_boundaries():
    """The devkit's loader: 2D box when left >= 0 (a box at the image's left edge has left 0), BEV when x, z are
    not -1000 and w, l > 0, 3D when also y is not -1000 and h > 0."""
    def carried(**changes) -> tuple[str, ...]:
        detection = obj(score=0.5)
        return available_metrics(frames([dataclasses.replace(detection, **changes)]))

    assert carried(bbox=(0.0, 150.0, 100.0, 250.0)) == ("bbox", "bev", "3d")
    assert carried(dimensions=(1.5, 1.6, 0.0)) == ("bbox",)  # no length: no ground-plane box
    assert carried(dimensions=(1.5, 0.0, 4.0)) == ("bbox",)  # no width either
    assert carried(location=(0.0, -1000.0, 20.0)) == ("bbox", "bev")  # no height position: no 3D box
    assert carried(location=(-1000.0, 1.6, 20.0)) == ("bbox",)
    assert carried(location=(0.0, 1.6, -1000.0)) == ("bbox",)


@pytest.mark.parametrize(("truncated", "counted"), [(0.15, [1, 1, 1]), (0.30, [0, 1, 1]), (0.50, [0, 0, 1])])
def test_a_car_exactly_at_a_truncation_limit_is_counted(truncated: float, counted: list[int]):
    """cleanData ignores a box only when truncation is *above* the difficulty's limit (0.15, 0.30, 0.50)."""
    result = run_eval([[obj(truncated=truncated)]], [[obj(score=0.9)]], metrics=("bev",))
    assert [result.curve("bev", 0.7, d).n_ground_truth for d in DIFFICULTIES] == counted


def test_a_car_on_a_band_edge_belongs_to_the_band_above():
    """Bands are [low, high): a car (and its detection) at exactly 20 m is in [20, 40), not in [0, 20)."""
    gt, det = [[obj(z=20.0)]], [[obj(z=20.0, score=0.9)]]
    near = run_eval(gt, det, metrics=("bev",), distance_range=(0.0, 20.0)).curve("bev", 0.7, "moderate")
    far = run_eval(gt, det, metrics=("bev",), distance_range=(20.0, 40.0)).curve("bev", 0.7, "moderate")
    assert (near.n_ground_truth, near.tp.tolist(), near.fp.tolist()) == (0, [], [])
    assert (far.n_ground_truth, far.tp.tolist(), far.fp.tolist()) == (1, [1], [0])
    # A detection of nothing at exactly 20 m (scoring above the one true positive): a false positive in [20, 40)
    # only, ignored in [0, 20).
    stray = obj(x=-12.0, z=20.0, left=700.0, score=0.99)
    for band, car_z, fp in (((20.0, 40.0), 30.0, [1]), ((0.0, 20.0), 10.0, [0])):
        curve = run_eval([[obj(x=8.0, z=car_z, left=400.0)]], [[obj(x=8.0, z=car_z, left=400.0, score=0.95), stray]],
                         metrics=("bev",), distance_range=band).curve("bev", 0.7, "moderate")
        assert (curve.tp.tolist(), curve.fp.tolist()) == ([1], fp)


def test_evaluate_is_unchanged_by_frame_order_and_box_order():
    """The protocol pools frames and matches each frame's boxes by score and overlap, not by file order (no ties
    here): shuffling frames, and the boxes within each, leaves every curve as it was."""
    rng = np.random.default_rng(7)
    gt, det = [], []
    for f in range(12):
        cars = [obj(x=float(x), z=float(z), left=float(left)) for x, z, left in
                zip(rng.uniform(-12, 12, 3), rng.uniform(8, 50, 3), rng.uniform(0, 1000, 3), strict=True)]
        gt.append(cars)
        det.append([dataclasses.replace(c, location=(c.location[0] + float(rng.normal(0, 0.3)), c.location[1],
                                                     c.location[2] + float(rng.normal(0, 0.3))),
                                        score=float(0.3 + 0.05 * f + 0.01 * i)) for i, c in enumerate(cars)]
                   + [obj(x=float(rng.uniform(-12, 12)), z=float(rng.uniform(8, 50)), score=float(0.21 + 0.005 * f))])
    reference = run_eval(gt, det)
    order = rng.permutation(12)
    shuffled = evaluate(frames(*[gt[i][::-1] for i in order]), frames(*[det[i][::-1] for i in order]))
    for a, b in zip(reference.curves, shuffled.curves, strict=True):
        np.testing.assert_array_equal(a.thresholds, b.thresholds)
        assert (a.tp.tolist(), a.fp.tolist(), a.fn.tolist()) == (b.tp.tolist(), b.fp.tolist(), b.fn.tolist())


def test_dontcare_coverage_is_the_share_of_the_detections_own_box():
    """computeStatistics discounts a false positive in the 2D metric when a DontCare region covers more than the
    overlap threshold of the *detection's* area (boxoverlap criterion 0), not their IoU: a box well inside a
    large region is discounted, one 60 % inside only at the 0.5 threshold, one 50 % inside at neither."""
    # 600 × 400 px: IoU with a 100 × 100 box inside is 0.04. The small region first: every region counts.
    gt = [obj(), dontcare(0.0, 0.0, 50.0, 50.0), dontcare(400.0, 100.0, 1000.0, 500.0)]
    inside = obj(x=-10.0, left=500.0, score=0.95)
    partly = obj(x=-14.0, left=940.0, score=0.95)  # x 940 … 1040: 60 of its 100 columns in the region
    half = obj(x=-14.0, left=950.0, score=0.95)  # exactly half: not more than 0.5
    for stray, fp_at in ((inside, {0.7: 0, 0.5: 0}), (partly, {0.7: 1, 0.5: 0}), (half, {0.7: 1, 0.5: 1})):
        result = run_eval([gt], [[obj(score=0.9), stray]])
        for iou, fp in fp_at.items():
            assert result.curve("bbox", iou, "easy").fp.tolist() == [fp]
            assert result.curve("bev", iou, "easy").fp.tolist() == [1]


def test_a_detection_must_overlap_by_more_than_the_threshold():
    """A 2D box covering half of a car's box has IoU exactly 0.5: no match at 0.5 (the devkit needs overlap > 0.5),
    so with a second, exactly detected car providing the threshold the half box is a false positive and the car
    a miss."""
    half = dataclasses.replace(obj(score=0.95), bbox=(100.0, 150.0, 200.0, 200.0))  # top half of 100 × 100
    result = run_eval([[obj(), obj(left=400.0, x=8.0)]], [[half, obj(left=400.0, x=8.0, score=0.9)]],
                      metrics=("bbox",))
    curve = result.curve("bbox", 0.5, "moderate")
    assert (curve.tp.tolist(), curve.fp.tolist(), curve.fn.tolist()) == ([1], [1], [1])


def test_bev_overlap_ignores_height_and_3d_overlap_does_not():
    """A detection with the car's footprint but 0.75 m too high (h 1.5 m): BEV IoU 1, 3D IoU 0.75 / 2.25 = 1/3."""
    raised = obj(y=1.6 - 0.75, score=0.9)
    result = run_eval([[obj()]], [[raised]], metrics=("bev", "3d"))
    for iou in (0.7, 0.5):
        assert (result.curve("bev", iou, "easy").tp.tolist(), result.curve("3d", iou, "easy").tp.tolist()) == ([1], [])


def test_thresholds_come_from_the_best_score_and_precision_from_the_best_overlap():
    """First pass: a car takes the highest-scoring detection over the threshold, whose score becomes the recall
    threshold. Second pass: among the counted candidates above the score threshold, the largest overlap.

    2D boxes 100 × 100 px at y 150 … 250: car 1 at x 100, car 2 at x 130. Detection B (score 0.6) is car 1
    exactly (IoU 1 with car 1, 70/130 = 0.54 with car 2); A (score 0.9) at x 115 has IoU 85/115 = 0.74 with
    both. A second frame's car, found with score 0.5, gives the second threshold."""
    def box(left: float, score: float | None = None):
        return obj(left=left, score=score)

    gt = [[box(100.0), box(130.0)], [box(100.0)]]
    det = [[box(115.0, 0.9), box(100.0, 0.6)], [box(100.0, 0.5)]]
    curve = run_eval(gt, det, metrics=("bbox",)).curve("bbox", 0.7, "moderate")
    # First pass: car 1 takes A (0.9 beats 0.6), car 2 has only A, taken: B is no true positive; frame 2: 0.5.
    np.testing.assert_array_equal(curve.thresholds, [0.9, 0.5])
    # At 0.9 only A takes part: car 1 takes it, car 2 is missed. At 0.5 car 1 takes B (overlap 1), which leaves A
    # for car 2: three true positives (taking A by its score would leave car 2 without a match: B is under 0.7).
    assert (curve.tp.tolist(), curve.fp.tolist(), curve.fn.tolist()) == ([1, 3], [0, 0], [2, 0])


def test_a_car_found_only_by_an_ignored_detection_leaves_the_other_detections_alone():
    """A car whose only candidate is a too-small (ignored) detection absorbs that one; a counted detection of
    nothing listed before it stays a false positive."""
    stray = obj(x=-12.0, left=700.0, score=0.97)
    small = obj(height_px=20.0, score=0.95)  # on car 1 in BEV, under every minimum height
    result = run_eval([[obj(), obj(x=8.0, left=400.0)]], [[stray, small, obj(x=8.0, left=400.0, score=0.9)]],
                      metrics=("bev",))
    curve = result.curve("bev", 0.7, "moderate")
    assert (curve.tp.tolist(), curve.fp.tolist(), curve.fn.tolist()) == ([1], [1], [0])


def test_cars_of_frames_without_detections_are_missed():
    """A frame with no detection at all still counts its cars: missed at every threshold (recall 1/2 here)."""
    curve = run_eval([[obj()], [obj()]], [[obj(score=0.9)], []], metrics=("bev",)).curve("bev", 0.7, "moderate")
    assert (curve.n_ground_truth, curve.tp.tolist(), curve.fn.tolist()) == (2, [1], [1])
    np.testing.assert_array_equal(curve.recall, [0.5])


def test_evaluate_refuses_what_it_cannot_score():
    """Mismatched frame counts, a detection without a score and an unknown metric are errors, not a table."""
    with pytest.raises(ValueError, match="1 ground-truth frames but 2 detection frames"):
        run_eval([[obj()]], [[obj(score=0.9)], []])
    with pytest.raises(ValueError, match="frame 0: detections need a score"):
        run_eval([[obj()]], [[obj()]])
    with pytest.raises(ValueError, match="unknown metric"):
        run_eval([[obj()]], [[obj(score=0.9)]], metrics=("bev", "aos"))


# ----------------------------------------------------------------------------- bootstrap and its intervals
def test_bootstrap_scores_only_the_metrics_every_set_carries_and_refuses_bad_calls():
    """Default metrics: those every detection set supports (a set with ground-plane boxes only has no 3D AP)."""
    gt = frames([obj()])
    with_3d, bev_only = frames([obj(score=0.9)]), frames([obj(score=0.9, h=-1.0, y=-1000.0)])
    assert bootstrap(gt, [with_3d, bev_only], resamples=1).metrics == ("bbox", "bev")
    with pytest.raises(ValueError, match="resamples must be at least 1"):
        bootstrap(gt, [with_3d], resamples=0)
    with pytest.raises(ValueError, match="detection set 1: 2 frames, ground truth 1"):
        bootstrap(gt, [with_3d, with_3d * 2], resamples=1)
    with pytest.raises(ValueError, match="level"):
        bootstrap_interval(np.arange(10.0), 4.5, level=1.0)


def test_bca_bound_past_the_pole_of_the_adjustment_is_the_draws_edge():
    """Φ(z0 + (z0 + z) / (1 − a (z0 + z))) has a pole where a (z0 + z) = 1: past it the formula wraps around to
    the other end of the draws. A jackknife with one outlier (a ≈ −1/6) and a level of 1 − 10⁻⁹ (z ≈ −6.1) with
    10 % of the draws below the estimate put the lower bound past it: the bound is then the smallest draw."""
    normal = statistics.NormalDist()
    draws = np.arange(100.0)
    jackknife = np.zeros(100)
    jackknife[0] = 1.0
    spread = jackknife.mean() - jackknife
    a = (spread**3).sum() / (6 * (spread**2).sum() ** 1.5)
    level = 1.0 - 1e-9
    z0, z_low, z_high = normal.inv_cdf(0.10), normal.inv_cdf((1 - level) / 2), normal.inv_cdf((1 + level) / 2)
    # Past the pole, the formula taken as it stands would put the lower bound near the top of the draws.
    wrapped_low = np.percentile(draws, 100 * normal.cdf(z0 + (z0 + z_low) / (1 - a * (z0 + z_low))))
    bounds = bootstrap_interval(draws, 9.5, jackknife, level=level)
    assert bounds.acceleration == pytest.approx(a) and bounds.z0 == pytest.approx(z0)
    assert bounds.low == draws.min() < bounds.high < wrapped_low
    share = normal.cdf(z0 + (z0 + z_high) / (1 - a * (z0 + z_high)))
    assert bounds.high == pytest.approx(np.percentile(draws, 100 * share))


def test_bca_leaves_out_values_that_do_not_exist():
    """A share has no value on a draw or jackknife sample without a gap (NaN): those are left out of the
    percentiles and of the acceleration; equal jackknife values give acceleration 0 (BC), not 0 / 0."""
    draws = np.arange(100.0)
    jackknife = np.array([0.0, 0.0, 0.0, 1.0, 5.0])
    reference = bootstrap_interval(draws, 29.5, jackknife)
    with_gaps = bootstrap_interval(np.concatenate([draws, [np.nan] * 7]), 29.5,
                                   np.concatenate([jackknife, [np.nan, np.nan]]))
    assert (with_gaps.low, with_gaps.high, with_gaps.acceleration) == (reference.low, reference.high,
                                                                     reference.acceleration)
    assert with_gaps.draws == 100
    flat = bootstrap_interval(draws, 29.5, np.full(5, 3.0))
    assert flat.acceleration == 0.0 and flat.method == "bca"
    assert (flat.low, flat.high) == (bootstrap_interval(draws, 29.5).low, bootstrap_interval(draws, 29.5).high)
    nothing = bootstrap_interval(draws, float("nan"), jackknife)
    assert math.isnan(nothing.low) and math.isnan(nothing.high) and "no value on all frames" in nothing.note
