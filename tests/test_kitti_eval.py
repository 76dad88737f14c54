"""KITTI object evaluation: hand-computed cases for every rule of the official protocol, the JSON
document, the command line end to end, and the shared real KITTI labels.

A property of the official devkit that the expected values below rely on: the k-th
score threshold is credited to the k-th recall sampling point (k/40) whatever the
recall actually reached there, so with fewer than 41 counted boxes even a perfect
detector scores below 100 (one box: R40 = 0, R11 = 100/11). Cases that should give
100 therefore replicate a frame 41 times.
"""

from __future__ import annotations

import dataclasses
import json
import math
import statistics
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from evaluation.depth_metrics import moderate_cars_in_view
from evaluation.kitti_eval import (
    DIFFICULTIES,
    BootstrapResult,
    available_metrics,
    bootstrap,
    bootstrap_interval,
    evaluate,
    recall_thresholds,
)
from evaluation.labels import LabelArrays
from evaluation.overlaps import bev_overlap, box3d_overlap, image_overlap
from evaluation.report import to_json
from pipeline.kitti import Object3D, read_labels, write_labels

REPO = Path(__file__).resolve().parents[1]
LABEL_DIR = REPO / "tests" / "data" / "kitti" / "training" / "label_2"


def obj(
    kind: str = "Car", x: float = 0.0, z: float = 20.0, ry: float = 0.0, left: float = 100.0, top: float = 150.0,
    height_px: float = 100.0, width_px: float = 100.0, truncated: float = 0.0, occluded: int = 0,
    score: float | None = None, h: float = 1.5, w: float = 1.6, l: float = 4.0, y: float = 1.6,
) -> Object3D:
    """A label line with a 2D box ``left, top, left + width_px, top + height_px``."""
    return Object3D(
        type=kind, truncated=truncated, occluded=occluded, alpha=0.0,
        bbox=(left, top, left + width_px, top + height_px), dimensions=(h, w, l), location=(x, y, z),
        rotation_y=ry, score=score,
    )


def dontcare(left: float, top: float, right: float, bottom: float) -> Object3D:
    return Object3D("DontCare", -1.0, -1, -10.0, (left, top, right, bottom), (-1.0, -1.0, -1.0),
                    (-1000.0, -1000.0, -1000.0), -10.0)


def frames(*objects_per_frame: list[Object3D]) -> list[LabelArrays]:
    return [LabelArrays.from_objects(objs) for objs in objects_per_frame]


def run_eval(gt: list[list[Object3D]], det: list[list[Object3D]], **kwargs):
    return evaluate(frames(*gt), frames(*det), **kwargs)


# ----------------------------------------------------------------------------- overlaps
def test_box_against_itself_has_iou_exactly_one():
    rng = np.random.default_rng(0)
    objects = [
        obj(x=rng.uniform(-30, 30), z=rng.uniform(2, 70), ry=ry, l=rng.uniform(0.3, 12), w=rng.uniform(0.3, 3),
            h=rng.uniform(0.5, 4))
        for ry in [0.0, math.pi / 2, math.pi / 4, -math.pi, 1e-9, *rng.uniform(-math.pi, math.pi, 20)]
    ]
    boxes = LabelArrays.from_objects(objects)
    np.testing.assert_allclose(np.diag(bev_overlap(boxes, boxes)), 1.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.diag(box3d_overlap(boxes, boxes)), 1.0, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(np.diag(image_overlap(boxes.bbox, boxes.bbox)), 1.0)


def test_overlaps_follow_devkit_geometry():
    gt = LabelArrays.from_objects([obj(ry=0.3)])
    # Shifted by a quarter length along the heading: BEV IoU (l - l/4) / (l + l/4) = 0.6.
    # The devkit's heading in the (x, z) plane is (cos ry, -sin ry).
    shifted = LabelArrays.from_objects([obj(x=math.cos(0.3), z=20.0 - math.sin(0.3), ry=0.3)])
    assert bev_overlap(shifted, gt)[0, 0] == pytest.approx(0.6, abs=1e-12)
    # Same ground-plane box, half the height overlapping: 3D IoU = (V/2) / (3V/2) = 1/3.
    lifted = LabelArrays.from_objects([obj(ry=0.3, y=1.6 - 0.75)])
    assert box3d_overlap(lifted, gt)[0, 0] == pytest.approx(1 / 3, abs=1e-12)
    # 2D: no "+1 pixel"; "detection" criterion divides by the detection's own area.
    a, b = np.array([[0.0, 0.0, 10.0, 10.0]]), np.array([[5.0, 0.0, 25.0, 10.0]])
    assert image_overlap(a, b)[0, 0] == pytest.approx(50 / 250)
    assert image_overlap(a, b, criterion="detection")[0, 0] == pytest.approx(0.5)


# ----------------------------------------------------------------------------- thresholds
def test_recall_thresholds_sample_41_points():
    # Fewer counted boxes than sampling points: every true positive is a threshold.
    np.testing.assert_array_equal(recall_thresholds(np.array([0.2, 0.9, 0.5]), 3), [0.9, 0.5, 0.2])
    # 80 boxes: recall (i+1)/80 is kept when at least as close to k/40 as the next one,
    # i.e. at i = 0 and i = 2k - 1 for k = 1..40.
    scores = 1.0 - np.arange(80) / 100
    expected = scores[[0, *range(1, 80, 2)]]
    np.testing.assert_array_equal(recall_thresholds(scores, 80), expected)
    assert recall_thresholds(np.zeros(0), 5).size == 0


# ----------------------------------------------------------------------------- rules, by hand
def test_one_box_perfectly_detected():
    single = run_eval([[obj()]], [[obj(score=0.9)]], metrics=("bev",))
    curve = single.curve("bev", 0.7, "easy")
    assert (curve.n_ground_truth, curve.tp.tolist(), curve.fp.tolist(), curve.fn.tolist()) == (1, [1], [0], [0])
    # One threshold credited to recall point 0 only.
    assert curve.ap_r40 == 0.0 and curve.ap_r11 == pytest.approx(100 / 11)
    replicated = run_eval([[obj()]] * 41, [[obj(score=0.9)]] * 41)
    for metric in ("bbox", "bev", "3d"):
        for difficulty in DIFFICULTIES:
            assert replicated.ap(metric, 0.7, difficulty, "R40") == pytest.approx(100.0)
            assert replicated.ap(metric, 0.7, difficulty, "R11") == pytest.approx(100.0)


def test_miss_gives_no_threshold_and_zero_ap():
    far = obj(x=15.0, left=600.0, score=0.9)  # no overlap in the image or on the ground
    result = run_eval([[obj()]] * 41, [[far]] * 41)
    for curve in result.curves:
        assert curve.n_ground_truth == 41 and curve.thresholds.size == 0
        assert curve.ap_r40 == 0.0 and curve.ap_r11 == 0.0


def test_duplicate_is_one_true_positive_and_one_false_positive():
    car1, car2 = obj(), obj(x=8.0, left=400.0)
    # Duplicate of car1 shifted 0.2 m along its length and 5 px: IoU ≈ 0.9 in BEV, 3D and 2D.
    duplicate = obj(x=0.2, left=105.0, score=0.8)
    result = run_eval([[car1, car2]], [[obj(score=0.9), duplicate, obj(x=8.0, left=400.0, score=0.7)]])
    for metric in ("bbox", "bev", "3d"):
        curve = result.curve(metric, 0.7, "easy")
        np.testing.assert_array_equal(curve.thresholds, [0.9, 0.7])
        # @0.9: car1 found, car2 missed. @0.7: both found; the duplicate is left over.
        assert curve.tp.tolist() == [1, 2] and curve.fp.tolist() == [0, 1] and curve.fn.tolist() == [1, 0]
        np.testing.assert_allclose(curve.precision[:3], [1.0, 2 / 3, 0.0])
        assert curve.ap_r40 == pytest.approx(100 * (2 / 3) / 40)
        assert curve.ap_r11 == pytest.approx(100 / 11)


@pytest.mark.parametrize(("other_class", "expected_fp"), [("Van", 0), ("Truck", 1)])
def test_detection_on_a_van_is_ignored(other_class: str, expected_fp: int):
    gt = [obj(), obj(other_class, x=8.0, left=400.0)]
    det = [obj(score=0.9), obj(x=8.0, left=400.0, score=0.95)]
    result = run_eval([gt], [det])
    for curve in result.curves:
        assert curve.n_ground_truth == 1
        assert (curve.tp.tolist(), curve.fp.tolist()) == ([1], [expected_fp])


def test_dontcare_discounts_detections_only_in_the_2d_metric():
    gt = [obj(), dontcare(500.0, 150.0, 600.0, 260.0)]
    under_dontcare = obj(x=-10.0, left=510.0, width_px=80.0, score=0.95)  # ground position far from any car
    result = run_eval([gt], [[obj(score=0.9), under_dontcare]])
    for iou in (0.7, 0.5):
        assert result.curve("bbox", iou, "easy").fp.tolist() == [0]
        assert result.curve("bev", iou, "easy").fp.tolist() == [1]
        assert result.curve("3d", iou, "easy").fp.tolist() == [1]


def test_too_small_boxes_are_ignored():
    gt = [obj(), obj(x=8.0, left=400.0, height_px=20.0)]  # the second is below every minimum height
    det = [
        obj(score=0.9),
        obj(x=8.0, left=400.0, height_px=20.0, score=0.95),  # on the small car: absorbed, not a FP
        obj(x=-12.0, left=700.0, height_px=20.0, score=0.99),  # a tiny detection of nothing: ignored
    ]
    for curve in run_eval([gt], [det]).curves:
        assert curve.n_ground_truth == 1
        assert (curve.tp.tolist(), curve.fp.tolist(), curve.fn.tolist()) == ([1], [0], [0])


def test_height_limits_are_inclusive_for_ground_truth_and_exclusive_for_detections():
    # Ground truth exactly 40 px high is ignored for easy (height <= 40), counted for moderate.
    result = run_eval([[obj(height_px=40.0)]], [[obj(height_px=40.0, score=0.9)]], metrics=("bev",))
    assert result.curve("bev", 0.7, "easy").n_ground_truth == 0
    assert result.curve("bev", 0.7, "moderate").n_ground_truth == 1
    # A detection exactly 25 px high counts for moderate (only height < 25 is ignored).
    result = run_eval([[obj()]], [[obj(height_px=25.0, score=0.9)]], metrics=("bev",))
    assert result.curve("bev", 0.7, "moderate").tp.tolist() == [1]
    assert result.curve("bev", 0.7, "easy").thresholds.size == 0  # ignored for easy: not a true positive


@pytest.mark.parametrize(("kind", "height_px", "truncated", "occluded"),
                         [("Car", 24.0, 0.0, 0), ("Car", 25.0, 0.0, 0), ("car", 25.5, 0.0, 0), ("Car", 60.0, 0.0, 1),
                          ("Car", 60.0, 0.3, 0), ("Car", 60.0, 0.31, 0), ("Car", 60.0, 0.0, 2), ("Van", 60.0, 0.0, 0)])
def test_depth_metrics_moderate_cars_are_the_evaluators(kind: str, height_px: float, truncated: float, occluded: int):
    # The depth harness's per-car errors are reported for "KITTI-moderate cars": exactly the cars the evaluator
    # counts at moderate. The simulator's 2D boxes are whole pixels, so some of its cars are exactly 25 px high,
    # which the devkit ignores (height <= 25); the class name compares case-insensitively, as in the evaluator.
    label = obj(kind=kind, height_px=height_px, truncated=truncated, occluded=occluded)
    counted = run_eval([[label]], [[obj(score=0.9)]], metrics=("bev",)).curve("bev", 0.7, "moderate").n_ground_truth
    assert len(moderate_cars_in_view([label], (375, 1242), (352, 1216))) == counted

def test_small_detection_of_any_class_absorbs_a_car():
    # Frame 0: a car whose only detection is a Pedestrian-labelled detection on it. Frame 1: a
    # normally detected car providing the score threshold 0.5.
    def outcome(det_height_px: float) -> list[int]:
        result = run_eval(
            [[obj()], [obj()]],
            [[obj("Pedestrian", height_px=det_height_px, score=0.9)], [obj(score=0.5)]],
            metrics=("bev",),
        )
        curve = result.curve("bev", 0.7, "moderate")
        return [*curve.tp.tolist(), *curve.fp.tolist(), *curve.fn.tolist()]

    assert outcome(20.0) == [1, 0, 0]  # too small: ignored whatever its class, the car is not missed
    assert outcome(100.0) == [1, 0, 1]  # another class at full size plays no part: the car is missed


def test_counting_small_detections_is_a_diagnostic_outside_the_devkit(tmp_path: Path):
    """With small detections counted, a correct BEV box with a too-small 2D box is a true positive and a
    small detection of nothing a false positive; the command says the protocol is not the devkit's."""
    gt = [obj(), obj(x=8.0, left=400.0)]
    det = [obj(score=0.9), obj(x=8.0, left=400.0, height_px=20.0, score=0.95),
           obj(x=-12.0, left=700.0, height_px=20.0, score=0.99)]
    devkit = run_eval([gt], [det], metrics=("bev",)).curve("bev", 0.7, "moderate")
    counted = run_eval([gt], [det], metrics=("bev",), ignore_small_detections=False).curve("bev", 0.7, "moderate")
    assert (devkit.tp.tolist(), devkit.fp.tolist(), devkit.fn.tolist()) == ([1], [0], [0])
    # At the lowest score threshold: both cars found, and the tiny detection of nothing is a false positive.
    assert (counted.tp[-1], counted.fp[-1], counted.fn[-1]) == (2, 1, 0)

    for folder in ("gt", "pred"):
        (tmp_path / folder).mkdir()
    write_labels(tmp_path / "gt" / "000000.txt", gt)
    write_labels(tmp_path / "pred" / "000000.txt", det)
    out = _cli("--gt-labels", tmp_path / "gt", "--pred-labels", tmp_path / "pred", "--count-small-detections",
               "--json", tmp_path / "ap.json")
    assert out.returncode == 0, out.stderr
    assert "not the devkit protocol" in out.stdout
    assert json.loads((tmp_path / "ap.json").read_text())["small_detections"] == "counted (diagnostic)"


def test_a_distance_band_ignores_cars_and_detections_outside_it(tmp_path: Path):
    """In band [20, 40): the near car is neither found nor missed, a far detection of nothing is no false
    positive, and a car at 39 m detected at 40.2 m (across the edge) is neither a hit nor a miss."""
    along_z = math.pi / 2  # length along the camera's z axis
    gt = [obj(z=10.0), obj(x=8.0, z=30.0, left=400.0), obj(x=-8.0, z=39.0, ry=along_z, left=700.0)]
    det = [obj(z=10.0, score=0.9), obj(x=8.0, z=30.0, left=400.0, score=0.8),
           obj(x=20.0, z=50.0, left=900.0, score=0.95),  # far from everything: counted only without the band
           obj(x=-8.0, z=40.2, ry=along_z, left=700.0, score=0.85)]  # BEV IoU 0.54 with the 39 m car
    whole = run_eval([gt], [det], metrics=("bev",)).curve("bev", 0.5, "moderate")
    band = run_eval([gt], [det], metrics=("bev",), distance_range=(20.0, 40.0)).curve("bev", 0.5, "moderate")
    assert (whole.n_ground_truth, whole.tp[-1], whole.fp[-1], whole.fn[-1]) == (3, 3, 1, 0)
    assert (band.n_ground_truth, band.tp[-1], band.fp[-1], band.fn[-1]) == (2, 1, 0, 0)
    # Bands that tile the range count every car exactly once.
    counts = [run_eval([gt], [det], metrics=("bev",), distance_range=r).curve("bev", 0.5, "moderate").n_ground_truth
              for r in ((0.0, 20.0), (20.0, 35.0), (35.0, 80.0))]
    assert counts == [1, 1, 1]

    for folder in ("gt", "pred"):
        (tmp_path / folder).mkdir()
    write_labels(tmp_path / "gt" / "000000.txt", gt)
    write_labels(tmp_path / "pred" / "000000.txt", det)
    out = _cli("--gt-labels", tmp_path / "gt", "--pred-labels", tmp_path / "pred", "--by-distance", "0,20,35,80",
               "--json", tmp_path / "ap.json", "--plots", tmp_path / "plots")
    assert out.returncode == 0, out.stderr
    assert "by distance" in out.stdout and "20–35" in out.stdout
    bands = json.loads((tmp_path / "ap.json").read_text())["by_distance"]
    assert [b["range_m"] for b in bands] == [[0, 20], [20, 35], [35, 80]]
    assert [b["num_ground_truth"]["moderate"] for b in bands] == [1, 1, 1]
    assert (tmp_path / "plots" / "ap_by_distance.png").stat().st_size > 0

    for bad in ("20,10", "0", "0,a,5", "-5,10"):
        out = _cli("--gt-labels", tmp_path / "gt", "--pred-labels", tmp_path / "pred", "--by-distance", bad)
        assert out.returncode == 2 and "--by-distance" in out.stderr and "Traceback" not in out.stderr
    # A band without cars has no AP: "n/a" and null, not the protocol's 0 ("misses every car near").
    out = _cli("--gt-labels", tmp_path / "gt", "--pred-labels", tmp_path / "pred", "--by-distance", "0,5,20,80",
               "--json", tmp_path / "empty.json")
    assert out.returncode == 0, out.stderr
    row = next(line for line in out.stdout.splitlines() if line.strip().startswith("0–5"))
    assert row.split()[1] == "0" and "n/a" in row and "0.0" not in row
    empty = json.loads((tmp_path / "empty.json").read_text())["by_distance"][0]
    assert empty["num_ground_truth"]["moderate"] == 0 and empty["Car"]["bev"]["0.7"]["R40"][1] is None


def test_frame_bootstrap_intervals_and_paired_differences(tmp_path: Path):
    """41 frames of one car each: the perfect detector scores 100 on every draw; one that misses every other
    car is below it on every draw, so the paired difference's interval excludes 0; a set against itself
    differs by exactly 0; the same seed draws the same frames."""
    gt = [[obj()] for _ in range(41)]
    perfect = [[obj(score=0.9)] for _ in range(41)]
    half = [[obj(score=0.9)] if i % 2 else [] for i in range(41)]
    result = bootstrap(frames(*gt), [frames(*perfect), frames(*half), frames(*perfect)], resamples=30, seed=3,
                       metrics=("bev",))
    assert result.ap.shape == (3, 30, 1, 2, 3)
    assert result.interval("bev", 0.7, "moderate") == (100.0, 100.0)
    low, high = result.difference_interval("bev", 0.7, "moderate", 0, 1)
    assert 0 < low <= high < 100
    assert result.difference_interval("bev", 0.5, "hard", 0, 2) == (0.0, 0.0)
    again = bootstrap(frames(*gt), [frames(*half)], resamples=30, seed=3, metrics=("bev",))
    np.testing.assert_array_equal(again.ap[0], result.ap[1])
    other_seed = bootstrap(frames(*gt), [frames(*half)], resamples=30, seed=4, metrics=("bev",))
    assert not np.array_equal(other_seed.ap[0], result.ap[1])

    for folder, dets in (("gt", gt), ("a", perfect), ("b", half)):
        (tmp_path / folder).mkdir()
        for i, objects in enumerate(dets):
            write_labels(tmp_path / folder / f"{i:06d}.txt", objects)
    out = _cli("--gt-labels", tmp_path / "gt", "--pred-labels", tmp_path / "a", "--compare-pred-labels",
               tmp_path / "b", "--bootstrap", "10", "--json", tmp_path / "ap.json")
    assert out.returncode == 0, out.stderr
    assert "95% BCa interval over 10 bootstrap draws" in out.stdout and "paired" in out.stdout
    document = json.loads((tmp_path / "ap.json").read_text())
    assert document["bootstrap"]["draws"] == 10
    assert document["bootstrap"]["interval"]["bev"]["0.7"][1] == [100.0, 100.0]
    low, high = document["bootstrap"]["difference_interval"]["bev"]["0.7"][1]
    assert 0 < low <= high
    assert document["compared_with"]["bev"]["0.7"]["R40"][1] < 100
    out = _cli("--gt-labels", tmp_path / "gt", "--pred-labels", tmp_path / "a", "--compare-pred-labels", tmp_path / "b",
               "--by-distance", "0,30,80", "--json", tmp_path / "cmp.json", "--plots", tmp_path / "plots")
    assert out.returncode == 0 and "this − " in out.stdout and "bootstrap draws" not in out.stdout
    assert "by distance" in out.stdout and f"of {tmp_path / 'b'} by distance" in out.stdout
    compared = json.loads((tmp_path / "cmp.json").read_text())["compared_by_distance"]
    assert compared[0]["range_m"] == [0, 30] and compared[0]["Car"]["bev"]["0.7"]["R40"][1] < 100
    assert (tmp_path / "plots" / "ap_by_distance.png").stat().st_size > 0
    out = _cli("--gt-labels", tmp_path / "gt", "--pred-labels", tmp_path / "a", "--compare-pred-labels", tmp_path / "nowhere")
    assert out.returncode == 2 and f"--compare-pred-labels: {tmp_path / 'nowhere'}" in out.stderr
    out = _cli("--gt-labels", tmp_path / "gt", "--pred-labels", tmp_path / "a", "--bootstrap", "0")
    assert out.returncode == 2 and "--bootstrap" in out.stderr



def _random_scenes(n_frames: int, seed: int) -> tuple[list[list[Object3D]], ...]:
    """Ground truth and two detectors' results on ``n_frames`` frames with every case the matching meets: cars of
    each difficulty and too hard, a van, DontCare regions, misses, false positives, scores tied within and across
    frames (one decimal), frames without detections and frames without cars."""
    rng = np.random.default_rng(seed)
    gt: list[list[Object3D]] = []
    detectors: tuple[list[list[Object3D]], list[list[Object3D]]] = ([], [])
    for f in range(n_frames):
        n_cars = int(rng.integers(0, 5)) if f % 9 else 0
        cars = [{"x": rng.uniform(-15, 15), "z": rng.uniform(5, 60), "ry": rng.uniform(-3, 3),
                 "left": rng.uniform(0, 1000), "height_px": float(rng.choice([20.0, 30.0, 60.0])),
                 "occluded": int(rng.integers(0, 3)), "truncated": float(rng.choice([0.0, 0.2, 0.4]))}
                for _ in range(n_cars)]
        frame = [obj(**car) for car in cars]
        if f % 5 == 0:
            frame.append(obj(kind="Van", x=rng.uniform(-15, 15), z=rng.uniform(5, 60)))
        if f % 7 == 0:
            frame.append(dontcare(0, 0, 600, 400))
        gt.append(frame)
        for detections, jitter in zip(detectors, (0.2, 0.6)):
            found = [obj(**{**car, "x": car["x"] + rng.normal(0, jitter), "z": car["z"] + rng.normal(0, jitter)},
                         score=round(float(rng.uniform(0.05, 1.0)), 1)) for car in cars if rng.uniform() < 0.8]
            if rng.uniform() < 0.5:
                found.append(obj(x=rng.uniform(-15, 15), z=rng.uniform(5, 60), score=round(float(rng.uniform(0.05, 0.7)), 1)))
            detections.append(found if f % 6 else [])
    return (gt, *detectors)


def _ap_cells(result, metrics: tuple[str, ...], iou_thresholds=(0.7, 0.5)) -> np.ndarray:
    return np.array([[[result.ap(m, t, d) for d in DIFFICULTIES] for t in iou_thresholds] for m in metrics])


def test_bootstrap_scores_draws_all_frames_and_each_frame_left_out_as_evaluate_does():
    """The bootstrap matches each frame once and then scores any multiset of frames without matching: every
    draw, the full set and every leave-one-frame-out (jackknife) sample give exactly evaluate()'s AP."""
    gt, first, second = _random_scenes(30, seed=1)
    metrics = ("bbox", "bev", "3d")
    sets = [frames(*first), frames(*second)]
    truth = frames(*gt)
    result = bootstrap(truth, sets, resamples=3, seed=5, metrics=metrics)
    assert result.full.shape == (2, 3, 2, 3) and result.jackknife.shape == (2, 30, 3, 2, 3)
    rng = np.random.default_rng(5)  # the draws the bootstrap makes with seed 5
    for r in range(3):
        draw = rng.integers(0, 30, 30)
        for s, detections in enumerate(sets):
            drawn = evaluate([truth[i] for i in draw], [detections[i] for i in draw], metrics=metrics)
            np.testing.assert_array_equal(result.ap[s, r], _ap_cells(drawn, metrics))
    for s, detections in enumerate(sets):
        np.testing.assert_array_equal(result.full[s], _ap_cells(evaluate(truth, detections, metrics=metrics), metrics))
        for left_out in (0, 6, 9, 29):  # 0 and 6: no detections; 9: no cars
            rest = [i for i in range(30) if i != left_out]
            sample = evaluate([truth[i] for i in rest], [detections[i] for i in rest], metrics=metrics)
            np.testing.assert_array_equal(result.jackknife[s, left_out], _ap_cells(sample, metrics))
    assert bootstrap(truth, sets, resamples=3, seed=5, metrics=metrics, jackknife=False).jackknife is None


def test_bca_interval_by_hand():
    """BCa (Efron 1987): z0 = Φ⁻¹(share of draws below the estimate, ties half), a from the jackknife, bounds at
    the draws' percentiles Φ(z0 + (z0 + z_q) / (1 − a (z0 + z_q)))."""
    normal = statistics.NormalDist()
    draws = np.arange(100.0)
    jackknife = np.array([0.0, 0.0, 0.0, 1.0, 5.0])  # skewed: a ≠ 0
    spread = jackknife.mean() - jackknife
    a = (spread**3).sum() / (6 * ((spread**2).sum()) ** 1.5)
    z0 = normal.inv_cdf(0.30)  # 30 of the 100 draws below 29.5
    expected = np.percentile(draws, [100 * normal.cdf(z0 + (z0 + z) / (1 - a * (z0 + z)))
                                     for z in (normal.inv_cdf(0.025), normal.inv_cdf(0.975))])
    bounds = bootstrap_interval(draws, 29.5, jackknife)
    assert bounds.method == "bca" and bounds.z0 == pytest.approx(z0) and bounds.acceleration == pytest.approx(a)
    assert (bounds.low, bounds.high) == pytest.approx(tuple(expected)) and bounds.note == ""
    # The draws lean above the estimate: the interval moves down from the plain percentile one.
    percentile = bootstrap_interval(draws, 29.5, jackknife, method="percentile")
    assert (percentile.low, percentile.high) == pytest.approx((2.475, 96.525))
    assert bounds.low < percentile.low and bounds.high < percentile.high
    # Without a jackknife BCa falls back to BC (a = 0) and says so; ties count half.
    bc = bootstrap_interval(draws, 29.5)
    assert bc.method == "bc" and bc.acceleration == 0.0 and "no jackknife" in bc.note
    assert bootstrap_interval(np.array([1.0, 1.0, 2.0, 2.0]), 1.0).z0 == pytest.approx(normal.inv_cdf(0.25))
    with pytest.raises(ValueError, match="method"):
        bootstrap_interval(draws, 29.5, method="basic")


def test_bootstrap_intervals_of_every_statistic_and_their_degenerate_cases():
    """One AP, a paired difference and a gap share all get their BCa interval from the same draws, full-set values
    and jackknife values, the statistic taken set by set within each; degenerate cells give NaN with a note."""
    rng = np.random.default_rng(0)
    draws = np.stack([rng.normal(mean, 1.0, (50, 1, 1, 3)) for mean in (85.0, 83.0, 91.0)])
    full = np.array([84.5, 83.0, 91.0])[:, None, None, None] * np.ones((3, 1, 1, 3))
    jackknife = np.stack([rng.normal(mean, 0.1, (20, 1, 1, 3)) for mean in (84.5, 83.0, 91.0)])
    draws[:, :, 0, 0, 2] = 100.0  # hard: every draw of every set at 100 …
    full[:, 0, 0, 2] = 100.0
    draws[0, :, 0, 0, 0] = full[0, 0, 0, 0] + 1.0 + rng.uniform(size=50)  # easy: set 0's draws all above its value
    result = BootstrapResult(metrics=("bev",), iou_thresholds=(0.7,), ap=draws, seed=0, full=full, jackknife=jackknife)
    cell = ("bev", 0.7, "moderate")

    def values(statistic):
        return statistic(draws[:, :, 0, 0, 1]), float(statistic(full[:, 0, 0, 1])), statistic(jackknife[:, :, 0, 0, 1])

    assert result.ap_bounds(*cell, index=2) == bootstrap_interval(*values(lambda ap: ap[2]))
    difference = result.difference_bounds(*cell, first=0, second=1)
    assert difference == bootstrap_interval(*values(lambda ap: ap[0] - ap[1]))
    assert difference.estimate == pytest.approx(1.5) and difference.method == "bca" and difference.acceleration != 0
    assert result.difference_interval(*cell) == (difference.low, difference.high)
    share = result.gap_share_bounds(*cell)
    assert share == bootstrap_interval(*values(lambda ap: (ap[0] - ap[1]) / (ap[2] - ap[1])))
    assert result.gap_share_interval(*cell) == (share.low, share.high, 50)
    percentile = result.difference_bounds(*cell, method="percentile")
    assert (percentile.low, percentile.high) == pytest.approx(tuple(np.percentile(values(
        lambda ap: ap[0] - ap[1])[0], [2.5, 97.5])))
    # Every draw equal to the value on all frames (AP 100 everywhere): the interval is that value.
    assert result.interval("bev", 0.7, "hard") == (100.0, 100.0)
    assert result.difference_interval("bev", 0.7, "hard") == (0.0, 0.0)
    # Every draw above it: z0 is −inf and there is no BCa interval; the percentile one, saying so.
    above = result.ap_bounds("bev", 0.7, "easy")
    assert above.method == "percentile" and above.z0 == -math.inf and "every draw lies above" in above.note
    assert (above.low, above.high) == pytest.approx(tuple(np.percentile(draws[0, :, 0, 0, 0], [2.5, 97.5])))
    # No gap on all frames (hard: 100 − 100): no share, whatever the draws.
    low, high, _ = result.gap_share_interval("bev", 0.7, "hard")
    assert math.isnan(low) and math.isnan(high)
    assert "no gap on all frames" in result.gap_share_bounds("bev", 0.7, "hard").note


@pytest.mark.parametrize(
    ("truncated", "occluded", "counted"),
    [(0.0, 0, [1, 1, 1]), (0.2, 0, [0, 1, 1]), (0.4, 0, [0, 0, 1]), (0.6, 0, [0, 0, 0]),
     (0.0, 1, [0, 1, 1]), (0.0, 2, [0, 0, 1]), (0.0, 3, [0, 0, 0])],
)
def test_truncation_and_occlusion_set_the_difficulty(truncated: float, occluded: int, counted: list[int]):
    hard_car = obj(truncated=truncated, occluded=occluded)
    plain_car = obj(x=8.0, left=400.0)
    det = [obj(score=0.9), obj(x=8.0, left=400.0, score=0.8)]
    result = run_eval([[hard_car, plain_car]], [det], metrics=("bev",))
    for difficulty, is_counted in zip(DIFFICULTIES, counted):
        curve = result.curve("bev", 0.7, difficulty)
        assert curve.n_ground_truth == 1 + is_counted
        # Where the hard car is ignored its detection is absorbed, never a false positive.
        assert curve.fp[-1] == 0 and curve.tp[-1] == 1 + is_counted


def test_score_sorted_multi_frame_ap_by_hand():
    # 80 frames with one car each, detected exactly with scores 0.9, 0.895, ..., 0.505, and false
    # positives (far from the car) each scoring just below one of the true positives in FP_AFTER.
    tp_scores = 0.9 - 0.005 * np.arange(80)
    fp_after = np.array([0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 30, 31, 50, 70])
    gt = [[obj()] for _ in range(80)]
    det = [[obj(score=float(s))] for s in tp_scores]
    for p in fp_after:
        det[p].append(obj(x=-15.0, left=700.0, score=float(tp_scores[p] - 0.001)))
    result = run_eval(gt, det)
    # Thresholds are true positives i = 0 and i = 2k - 1 (see test_recall_thresholds_sample_41_points).
    kept = np.array([0, *range(1, 80, 2)])
    tp = kept + 1
    fp = (fp_after[None, :] < kept[:, None]).sum(axis=1)  # false positives scoring above true positive i
    raw = tp / (tp + fp)
    interpolated = np.maximum.accumulate(raw[::-1])[::-1]
    assert (interpolated > raw).sum() > 20  # the case exercises the max-over-later-points rule
    expected_r40 = 100 * interpolated[1:].sum() / 40
    expected_r11 = 100 * interpolated[::4].sum() / 11
    for curve in result.curves:
        np.testing.assert_allclose(curve.thresholds, tp_scores[kept])
        np.testing.assert_array_equal(curve.tp, tp)
        np.testing.assert_array_equal(curve.fp, fp)
        np.testing.assert_allclose(curve.precision, interpolated, rtol=0, atol=1e-15)
        assert curve.ap_r40 == pytest.approx(expected_r40, abs=1e-9)
        assert curve.ap_r11 == pytest.approx(expected_r11, abs=1e-9)


def test_metrics_follow_what_detections_carry():
    with_3d = frames([obj(score=0.5)])
    bev_only = frames([obj(score=0.5, h=-1.0, y=-1000.0)])
    no_image_box = frames([dataclasses.replace(obj(score=0.5), bbox=(-1.0, -1.0, -1.0, -1.0))])
    assert available_metrics(with_3d) == ("bbox", "bev", "3d")
    assert available_metrics(bev_only) == ("bbox", "bev")
    assert available_metrics(no_image_box) == ("bev", "3d")
    assert available_metrics(frames([obj("Pedestrian", score=0.5)])) == ()


def test_json_structure():
    result = run_eval([[obj()]] * 41, [[obj(score=0.9)]] * 41)
    document = json.loads(json.dumps(to_json(result)))
    assert set(document["Car"]) == {"bbox", "bev", "3d"}
    for metric in ("bbox", "bev", "3d"):
        assert set(document["Car"][metric]) == {"0.7", "0.5"}
        for iou in ("0.7", "0.5"):
            assert document["Car"][metric][iou]["R40"] == pytest.approx([100.0] * 3)
            assert document["Car"][metric][iou]["R11"] == pytest.approx([100.0] * 3)
            assert len(document["details"]["Car"][metric][iou]["moderate"]["precision_41"]) == 41
    assert document["frames"] == 41


# ----------------------------------------------------------------------------- real labels
def _real_frames() -> list[LabelArrays]:
    return [LabelArrays.from_objects(read_labels(p)) for p in sorted(LABEL_DIR.glob("*.txt"))]


def _as_detections(gt: LabelArrays, shift_along_heading: float = 0.0) -> LabelArrays:
    """Ground truth turned into detections (score 1), optionally moved along each box's heading."""
    ry = gt.rotation_y
    location = gt.location.copy()
    location[:, 0] += shift_along_heading * gt.dimensions[:, 2] * np.cos(ry)
    location[:, 2] -= shift_along_heading * gt.dimensions[:, 2] * np.sin(ry)
    return dataclasses.replace(gt, location=location, score=np.ones(len(gt)))


def test_real_labels_ground_truth_as_predictions():
    gt = _real_frames()
    result = evaluate(gt, [_as_detections(g) for g in gt])
    # Counted cars in the five frames: 3 easy (height > 40 px, unoccluded), 5 moderate and hard.
    for difficulty, n in zip(DIFFICULTIES, (3, 5, 5)):
        for curve in (c for c in result.curves if c.difficulty == difficulty):
            assert curve.n_ground_truth == n
            assert curve.fp.sum() == 0 and curve.tp[-1] == n and curve.fn[-1] == 0
            # n < 41 thresholds, all at precision 1: the devkit credits points 0 .. n-1.
            assert curve.ap_r40 == pytest.approx(100 * (n - 1) / 40)
            assert curve.ap_r11 == pytest.approx(100 * math.ceil(n / 4) / 11)
    replicated = evaluate(gt * 14, [_as_detections(g) for g in gt] * 14)  # 42 easy cars ≥ 41
    assert all(c.ap_r40 == pytest.approx(100.0) and c.ap_r11 == pytest.approx(100.0) for c in replicated.curves)


def test_real_labels_perturbed_predictions():
    gt = _real_frames() * 14
    exact = evaluate(gt, [_as_detections(g) for g in gt])
    # A quarter length along the heading: ground-plane and 3D IoU 0.6 (heights unchanged), 2D box unchanged.
    moved = evaluate(gt, [_as_detections(g, 0.25) for g in gt])
    for curve in moved.curves:
        reference = exact.curve(curve.metric, curve.iou_threshold, curve.difficulty)
        if curve.metric == "bbox" or curve.iou_threshold == 0.5:
            assert curve.ap_r40 == pytest.approx(reference.ap_r40) and curve.ap_r11 == pytest.approx(100.0)
        else:
            assert curve.ap_r40 == 0.0 and curve.ap_r11 == 0.0


# ----------------------------------------------------------------------------- command line
def _cli(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / "accuracy.py"), *map(str, args), "--no-progress"],
        check=False, capture_output=True, text=True, timeout=120,
    )


def test_results_with_low_scores_get_no_warning_of_a_cut(tmp_path: Path):
    gt_dir, pred_dir = tmp_path / "gt", tmp_path / "pred"
    gt_dir.mkdir()
    pred_dir.mkdir()
    for i in range(3):
        write_labels(gt_dir / f"{i:06d}.txt", [obj()])
        write_labels(pred_dir / f"{i:06d}.txt", [obj(score=0.9), obj(x=8.0, score=0.06)])
    out = _cli("--gt-labels", gt_dir, "--pred-labels", pred_dir)
    assert out.returncode == 0 and "BEV" in out.stdout, out.stderr
    assert "lowest Car score" not in out.stderr and "no result file" not in out.stdout


def test_cli_end_to_end(tmp_path: Path):
    gt_dir, pred_dir = tmp_path / "gt", tmp_path / "pred"
    gt_dir.mkdir()
    pred_dir.mkdir()
    for i in range(42):
        write_labels(gt_dir / f"{i:06d}.txt", [obj(), dontcare(500, 150, 600, 260)])
        if i < 41:  # frame 41 has no result file: its car is missed
            write_labels(pred_dir / f"{i:06d}.txt", [obj(score=0.9)])
    write_labels(pred_dir / "000099.txt", [obj(score=0.9)])  # a frame the ground truth does not have
    # As the devkit: a frame without a result file is refused, naming it, and nothing is written.
    refused = _cli("--gt-labels", gt_dir, "--pred-labels", pred_dir, "--json", tmp_path / "ap.json")
    assert refused.returncode == 2 and "Traceback" not in refused.stderr
    assert "1 of 42 frames have no result file, e.g. 000041.txt" in refused.stderr and "--missing-as-empty" in \
        refused.stderr
    assert not (tmp_path / "ap.json").exists()
    out = _cli("--gt-labels", gt_dir, "--pred-labels", pred_dir, "--json", tmp_path / "ap.json",
               "--plots", tmp_path / "plots", "--missing-as-empty")
    assert out.returncode == 0, out.stderr
    assert "BEV" in out.stdout and "R40" in out.stdout and "R11" in out.stdout
    assert "no result file" in out.stderr  # the missing frame is reported, and the table says so
    assert out.stdout.startswith("1 of 42 frames have no result file, counted as frames without detections")
    # No score under 0.1: as if written with a threshold (pipeline.detect's 0.5), which lowers AP: said once.
    assert out.stderr.count(f"the lowest Car score in {pred_dir} is 0.90: if these results were written with a "
                            "score threshold") == 1
    assert f"1 result file(s) in {pred_dir} have no ground truth in {gt_dir} and are not scored, e.g. 000099.txt" \
        in out.stderr
    document = json.loads((tmp_path / "ap.json").read_text())
    assert document["missing_predictions"] == ["000041"]
    # 42 cars, 41 found with precision 1. getThresholds skips the 31st true positive (recall
    # 31/42 is farther from 30/40 than 32/42 is), so 40 thresholds (points 0..39): R40 = 39/40, R11 = 10/11.
    assert document["Car"]["bev"]["0.7"]["R40"] == pytest.approx([97.5] * 3)
    assert document["Car"]["bev"]["0.7"]["R11"] == pytest.approx([1000 / 11] * 3)
    assert document["details"]["Car"]["bev"]["0.7"]["easy"]["fn"][-1] == 1
    assert sorted(p.name for p in (tmp_path / "plots").glob("*.png")) == [
        "pr_car_easy.png", "pr_car_hard.png", "pr_car_moderate.png"]

    split = tmp_path / "split.txt"
    split.write_text("000000\n000001\n")
    out = _cli("--gt-labels", gt_dir, "--pred-labels", pred_dir, "--split-file", split, "--json", tmp_path / "s.json")
    assert out.returncode == 0, out.stderr
    assert json.loads((tmp_path / "s.json").read_text())["frames"] == 2


def test_cli_reports_bad_input_without_traceback(tmp_path: Path):
    gt_dir, pred_dir = tmp_path / "gt", tmp_path / "pred"
    gt_dir.mkdir()
    pred_dir.mkdir()
    write_labels(gt_dir / "000000.txt", [obj()])
    (pred_dir / "000000.txt").write_text("Car 0 0 0 1 2 3\n")
    out = _cli("--gt-labels", gt_dir, "--pred-labels", pred_dir)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert f"{pred_dir / '000000.txt'}, line 1" in out.stderr

    out = _cli("--gt-labels", tmp_path / "nowhere", "--pred-labels", pred_dir)
    assert out.returncode == 2 and str(tmp_path / "nowhere") in out.stderr and "Traceback" not in out.stderr
    out = _cli("--gt-labels", gt_dir / "000000.txt", "--pred-labels", pred_dir)  # a file, not the folder
    assert out.returncode == 2 and f"{gt_dir / '000000.txt'}: not a directory (the ground-truth label folder" in out.stderr
    write_labels(pred_dir / "000000.txt", [obj()])  # 15 fields: a ground-truth line, not a result line
    out = _cli("--gt-labels", gt_dir, "--pred-labels", pred_dir)
    assert out.returncode == 2 and f"{pred_dir / '000000.txt'}, line 1: Car has 15 fields; a result line needs" in out.stderr

    split = tmp_path / "split.txt"
    split.write_text("000007\n")
    out = _cli("--gt-labels", gt_dir, "--pred-labels", pred_dir, "--split-file", split)
    assert out.returncode == 2 and str(gt_dir / "000007.txt") in out.stderr


def test_cli_refuses_result_files_matching_no_frame(tmp_path: Path):
    """Result files named for other frames (here 999999.txt) are the wrong folder or naming, not a detector
    that found nothing: an error naming both folders, not a header without rows."""
    pred_dir = tmp_path / "pred"
    pred_dir.mkdir()
    write_labels(pred_dir / "999999.txt", [obj(score=0.9)])
    out = _cli("--gt-labels", LABEL_DIR, "--pred-labels", pred_dir, "--json", tmp_path / "ap.json")
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert f"{pred_dir}: no result file matches a frame of {LABEL_DIR} (000000, 000001, 000003, 000004, 000006)" \
        in out.stderr and "999999.txt" in out.stderr
    assert out.stdout == "" and not (tmp_path / "ap.json").exists()


def test_no_detections_score_zero_in_every_column(tmp_path: Path):
    """Empty result files (a detector that found nothing): every metric is evaluated and every AP is 0,
    in the same JSON structure as a run with detections."""
    pred_dir = tmp_path / "pred"
    pred_dir.mkdir()
    for gt_file in LABEL_DIR.glob("*.txt"):
        (pred_dir / gt_file.name).write_text("")
    out = _cli("--gt-labels", LABEL_DIR, "--pred-labels", pred_dir, "--json", tmp_path / "ap.json")
    assert out.returncode == 0, out.stderr
    assert "every AP is 0" in out.stderr
    rows = [line for line in out.stdout.splitlines() if line.lstrip().startswith(("R40", "R11"))]
    assert len(rows) == 6 and all(cell == "0.00" for row in rows for cell in row.split() if "." in cell)
    document = json.loads((tmp_path / "ap.json").read_text())
    assert document["metrics"] == ["bbox", "bev", "3d"] and document["missing_predictions"] == []
    for metric in ("bbox", "bev", "3d"):
        assert set(document["Car"][metric]) == {"0.7", "0.5"}
        for iou in ("0.7", "0.5"):
            assert document["Car"][metric][iou] == {"R40": [0.0] * 3, "R11": [0.0] * 3}
            moderate = document["details"]["Car"][metric][iou]["moderate"]
            # Counted cars of the five frames: 5 moderate, all missed; no score threshold, precision 0.
            assert moderate["num_ground_truth"] == 5 and moderate["score_thresholds"] == []
            assert moderate["precision_41"] == [0.0] * 41


def test_cli_frames_and_split_file_are_one_flag(tmp_path: Path):
    pred_dir = tmp_path / "pred"
    pred_dir.mkdir()
    for gt_file in LABEL_DIR.glob("*.txt"):
        write_labels(pred_dir / gt_file.name, [obj(score=0.9)])
    split = tmp_path / "split.txt"
    split.write_text("000000\n000003\n")
    out = _cli("--gt-labels", LABEL_DIR, "--pred-labels", pred_dir, "--frames", split, "--json", tmp_path / "f.json")
    assert out.returncode == 0, out.stderr
    assert json.loads((tmp_path / "f.json").read_text())["frames"] == 2 and "2 frames" in out.stdout
    out = _cli("--gt-labels", LABEL_DIR, "--pred-labels", pred_dir, "--frames", split, "--split-file", split)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "argument --frames: not allowed with argument --split-file" in out.stderr


def test_cli_checks_output_paths_before_any_work(tmp_path: Path):
    pred_dir = tmp_path / "pred"
    pred_dir.mkdir()
    write_labels(pred_dir / "000000.txt", [obj(score=0.9)])
    a_file = tmp_path / "a_file"
    a_file.write_text("kept\n")
    json_path = tmp_path / "ap.json"
    for flag, path, problem in [
        ("--plots", a_file, "exists and is not a directory"),
        ("--json", a_file / "x.json", f"{a_file} is a file, not a directory"),
        ("--json", tmp_path, "is a directory"),
    ]:
        args = ("--json", json_path, "--plots", path) if flag == "--plots" else (flag, path)
        out = _cli("--gt-labels", LABEL_DIR, "--pred-labels", pred_dir, *args)
        assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
        assert f"error: {flag} {path}: {problem}" in out.stderr
        assert out.stdout == "" and not json_path.exists()  # refused before the evaluation wrote anything
    assert a_file.read_text() == "kept\n"


def test_cli_help():
    out = _cli("--help")
    assert out.returncode == 0 and "--gt-labels" in out.stdout and "--split-file" in out.stdout
    text = " ".join(out.stdout.split())
    assert "the same as --frames" in text and "A flag of another mode is refused, not ignored" in text


def test_gap_share_between_a_weaker_and_a_stronger_model(tmp_path: Path):
    """--gap-to-pred-labels: the share of the gap from --compare-pred-labels up to it that --pred-labels closes
    (the paper's camera row between its 16- and 64-line rows), with its interval over the same bootstrap draws."""
    gt = [[obj()] for _ in range(41)]
    sets = {"gt": gt,
            "high": [[obj(score=0.9)] for _ in range(41)],  # every car
            "low": [[obj(score=0.9)] if i % 2 else [] for i in range(41)],  # every other car
            "middle": [[obj(score=0.9)] if i % 4 else [] for i in range(41)]}  # three in four
    for folder, dets in sets.items():
        (tmp_path / folder).mkdir()
        for i, objects in enumerate(dets):
            write_labels(tmp_path / folder / f"{i:06d}.txt", objects)
    out = _cli("--gt-labels", tmp_path / "gt", "--pred-labels", tmp_path / "middle", "--compare-pred-labels",
               tmp_path / "low", "--gap-to-pred-labels", tmp_path / "high", "--bootstrap", "20", "--json",
               tmp_path / "gap.json")
    assert out.returncode == 0, out.stderr
    assert "share of the gap from" in out.stdout
    document = json.loads((tmp_path / "gap.json").read_text())
    ap = {name: table["bev"]["0.7"]["R40"][1] for name, table in
          (("middle", document["Car"]), ("low", document["compared_with"]), ("high", document["gap_to"]))}
    assert ap["low"] < ap["middle"] < ap["high"]
    share = document["gap_share"]["share"]["bev"]["0.7"][1]
    assert share == (ap["middle"] - ap["low"]) / (ap["high"] - ap["low"]) and 0.3 < share < 0.7
    low, high = document["gap_share"]["interval"]["bev"]["0.7"][1]
    assert low <= share <= high and document["gap_share"]["draws_used"]["bev"]["0.7"][1] == 20
    alone = _cli("--gt-labels", tmp_path / "gt", "--pred-labels", tmp_path / "middle", "--gap-to-pred-labels",
                 tmp_path / "high")
    assert alone.returncode == 2 and "--gap-to-pred-labels: give --compare-pred-labels too" in alone.stderr


def test_cli_bootstrap_intervals_are_bca_by_default_and_percentile_on_request(tmp_path: Path):
    """The table and the JSON give BCa intervals and say so, the JSON with the percentile ones beside them;
    --interval percentile gives those; a share without a gap is null with a note, and the JSON has no NaN."""
    gt, first, second = _random_scenes(40, seed=2)
    for folder, dets in (("gt", gt), ("a", first), ("b", second), ("b_again", second)):
        (tmp_path / folder).mkdir()
        for i, objects in enumerate(dets):
            write_labels(tmp_path / folder / f"{i:06d}.txt", objects)
    common = ("--gt-labels", tmp_path / "gt", "--pred-labels", tmp_path / "a", "--compare-pred-labels", tmp_path / "b",
              "--gap-to-pred-labels", tmp_path / "b_again", "--bootstrap", "30")
    out = _cli(*common, "--json", tmp_path / "bca.json")
    assert out.returncode == 0, out.stderr
    assert "intervals: BCa, bias-corrected and accelerated" in out.stdout
    assert "BEV @0.7 moderate, share of the gap: no gap on all frames" in out.stdout

    def strict(text: str):
        return json.loads(text, parse_constant=lambda name: pytest.fail(f"{name} in the JSON"))

    bca = strict((tmp_path / "bca.json").read_text())
    assert bca["bootstrap"]["method"] == "bca" and bca["gap_share"]["method"] == "bca"
    assert bca["gap_share"]["interval"]["bev"]["0.7"][1] is None
    assert any("share of the gap: no gap on all frames" in note for note in bca["bootstrap"]["notes"])
    out = _cli(*common, "--interval", "percentile", "--json", tmp_path / "percentile.json")
    assert out.returncode == 0 and "intervals: percentile" in out.stdout, out.stderr
    percentile = strict((tmp_path / "percentile.json").read_text())
    assert percentile["bootstrap"]["method"] == "percentile"
    for key in ("interval", "difference_interval"):
        assert percentile["bootstrap"][key] == bca["bootstrap"]["percentile"][key]
        assert percentile["bootstrap"][key] != bca["bootstrap"][key]
    assert percentile["gap_share"]["interval"] == bca["gap_share"]["percentile_interval"]
    refused = _cli("--gt-labels", tmp_path / "gt", "--pred-labels", tmp_path / "a", "--interval", "bca")
    assert refused.returncode == 2 and "argument --interval: only with --bootstrap N" in refused.stderr
    help_text = " ".join(_cli("--help").stdout.split())
    assert "which bootstrap interval (default bca)" in help_text and "(Efron 1987)" in help_text
