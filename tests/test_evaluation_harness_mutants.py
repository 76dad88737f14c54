"""The evaluation modules around the devkit (frames, labels, overlaps, report, harness) where a mutation test (session 45) found
behaviour no test pinned: which frames an error names, a ground-truth box's signed height, 2D overlaps of
zero-area boxes, the paper's table (its column and row order, R40 against R11, IoU 0.5 against 0.7), the JSON's
per-threshold details, the precision-recall plot, and the accuracy harness's refusals.

Expected AP figures are worked by hand from the devkit's rules: with n < 41 counted cars all found at precision
1, the k-th score threshold is credited to recall point k, so R40 = 100 (n - 1) / 40 and R11 = 100 ceil(n / 4) / 11
(tests/test_kitti_eval.py's docstring); a car moved a quarter of its length along its heading overlaps its
ground truth by 3/5 = 0.6 on the ground and in 3D, a hit at IoU 0.5 and a miss at 0.7, its 2D box unchanged.
"""

from __future__ import annotations

import json
import logging
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from evaluation.frames import load_label_dirs
from evaluation.harness import _to_crop_resolution, run_depth, run_detection
from evaluation.kitti_eval import KittiEvalResult, bootstrap, evaluate, evaluate_by_distance
from evaluation.labels import LabelArrays
from evaluation.overlaps import image_overlap
from evaluation.report import (
    by_distance_figure,
    distance_json,
    format_difference,
    format_distance_table,
    format_table,
    gap_json,
    plot_pr_curves,
    pr_figure,
    spread_json,
    to_json,
)
from pipeline.beams import emulate_beams
from pipeline.calib import sparse_depth_map
from pipeline.errors import InputError
from pipeline.frame import load_frame
from pipeline.kitti import read_labels, read_velodyne, write_depth_png
from tests.conftest import KITTI
from tests.test_eval_frames import _folders
from tests.test_kitti_eval import frames, obj

REPO = Path(__file__).resolve().parents[1]
EDGE = REPO / "weights" / "edge"  # a two-stage model directory: its depth network runs a frame in about 0.1 s


# ----------------------------------------------------------------------------- evaluation.frames


def test_result_files_of_other_frames_are_counted_and_the_first_named(tmp_path: Path):
    """Seven frames, and results for two frames that are not among them: the error lists the first three frames
    and the count (``a, b, c, … 7481 frames``), and says how many result files the folder holds, naming the
    first in id order."""
    gt, results = _folders(tmp_path, [f"{i:06d}" for i in range(7)], ["000011", "000010"])
    with pytest.raises(InputError) as caught:
        load_label_dirs(gt, results)
    assert str(caught.value) == (f"{results}: no result file matches a frame of {gt} (000000, 000001, 000002, … 7 "
                                 "frames); it holds 2 *.txt file(s), e.g. 000010.txt")


def test_the_frame_named_for_missing_results_is_the_first_in_id_order(tmp_path: Path):
    gt, results = _folders(tmp_path, ["000003", "000000", "000002", "000001"], ["000000", "000002"])
    with pytest.raises(InputError, match=r"2 of 4 frames have no result file, e\.g\. 000001\.txt;"):
        load_label_dirs(gt, results)


# ----------------------------------------------------------------------------- evaluation.labels
def test_a_ground_truth_box_upside_down_has_a_negative_height_and_is_not_counted():
    """The devkit's cleanData takes a ground-truth box's height as ``y2 - y1``, signed: a box whose bottom lies
    above its top is below every minimum height, so its car counts at no difficulty."""
    upside_down = obj(left=100.0, top=250.0, height_px=-100.0)  # top 250, bottom 150
    assert LabelArrays.from_objects([upside_down]).box_height.tolist() == [-100.0]
    result = evaluate(frames([upside_down]), frames([obj(score=0.9)]), metrics=("bev",))
    assert [result.curve("bev", 0.7, d).n_ground_truth for d in ("easy", "moderate", "hard")] == [0, 0, 0]


# ----------------------------------------------------------------------------- evaluation.overlaps
def test_a_zero_height_detection_on_a_region_overlaps_it_by_zero():
    """boxoverlap divides only when the intersection is wider *and* higher than 0: a detection of no height
    inside a DontCare region covers none of it, with no 0 / 0 (the zero-width case is in test_eval_intervals)."""
    flat = np.array([[10.0, 20.0, 30.0, 20.0]])
    region = np.array([[0.0, 0.0, 50.0, 50.0]])
    with np.errstate(all="raise"):
        assert image_overlap(flat, region, "detection").tolist() == [[0.0]]
        assert image_overlap(flat, region).tolist() == [[0.0]]


def test_an_unknown_overlap_criterion_is_refused():
    a = np.array([[0.0, 0.0, 10.0, 10.0]])
    with pytest.raises(ValueError, match="criterion must be 'union' or 'detection', got 'area'"):
        image_overlap(a, a, criterion="area")  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- evaluation.report
def _quarter_length_off() -> KittiEvalResult:
    """Nine frames of one car each, its detection a quarter length ahead (ground and 3D IoU 0.6, 2D IoU 1). The
    cars of frames 0–4 are partly occluded (1: moderate and hard, not easy), those of 5–8 largely (2: hard only).

    Hand-worked AP, every car found at precision 1: easy counts no car, 0; moderate n = 5, R40 4/40 = 10.00 and
    R11 2/11 = 18.18; hard n = 9, R40 8/40 = 20.00 and R11 3/11 = 27.27 — at IoU 0.5 in every metric and at 0.7
    in 2D only (BEV and 3D miss every car at 0.7).
    """
    return evaluate(*_quarter_length_off_frames())


def _quarter_length_off_frames() -> tuple[list[LabelArrays], list[LabelArrays]]:
    """The ground truth and detections of :func:`_quarter_length_off`; every car 20 m ahead."""
    occlusion = [1] * 5 + [2] * 4
    truth = frames(*([obj(occluded=o)] for o in occlusion))
    found = frames(*([obj(x=1.0, score=0.9 - 0.01 * i)] for i in range(len(occlusion))))
    return truth, found


HIT = {"R40": [0.0, 10.0, 20.0], "R11": [0.0, round(200 / 11, 2), round(300 / 11, 2)]}
MISS = {"R40": [0.0] * 3, "R11": [0.0] * 3}


def test_the_table_lists_bev_3d_2d_iou_0_5_then_0_7_easy_moderate_hard_r40_then_r11():
    """The paper's table: a block per metric (BEV, 3D, 2D box), each column group an overlap threshold (0.5 before
    0.7) of easy, moderate, hard, the R40 row above the R11 row, AP in percent to two decimals."""
    lines = format_table(_quarter_length_off()).splitlines()
    assert lines[0] == "Car AP (%), 9 frames"
    blocks = [lines[1:4], lines[4:7], lines[7:10]]
    assert len(lines) == 10
    expected = {"BEV": (HIT, MISS), "3D": (HIT, MISS), "2D bbox": (HIT, HIT)}
    assert [block[0].split("|")[0].strip() for block in blocks] == list(expected)
    for block in blocks:
        title, *groups = block[0].split("|")
        assert [g.split() for g in groups] == [["IoU", "0.5", "easy", "mod.", "hard"],
                                               ["IoU", "0.7", "easy", "mod.", "hard"]]
        assert [row.split("|")[0].strip() for row in block[1:]] == ["R40", "R11"]
        at_05, at_07 = expected[title.strip()]
        for row in block[1:]:
            points, *cells = row.split("|")
            assert [[float(v) for v in cell.split()] for cell in cells] == [at_05[points.strip()],
                                                                             at_07[points.strip()]]


def test_the_json_details_give_each_thresholds_counts_in_the_devkits_order():
    """One frame, two cars: car A found at 0.9, a detection far from both at 0.8, car B found at 0.7. The score
    thresholds are the true positives' scores, highest first: at 0.9 tp 1, fp 0, fn 1 (recall 1/2, precision 1);
    at 0.7 tp 2, fp 1, fn 0 (recall 1, precision 2/3). The 41-point precision is 1 and 2/3 at the first two
    recall points, then 0."""
    truth = frames([obj(), obj(x=8.0, left=400.0)])
    found = frames([obj(score=0.9), obj(x=-15.0, left=700.0, score=0.8), obj(x=8.0, left=400.0, score=0.7)])
    details = to_json(evaluate(truth, found, metrics=("bev",)))["details"]["Car"]["bev"]["0.7"]["easy"]
    assert details["num_ground_truth"] == 2
    assert details["score_thresholds"] == [0.9, 0.7]
    assert (details["tp"], details["fp"], details["fn"]) == ([1, 2], [0, 1], [1, 0])
    assert details["recall"] == [0.5, 1.0]
    assert details["precision_41"] == pytest.approx([1.0, 2 / 3] + [0.0] * 39, abs=1e-12)


def test_the_pr_figure_draws_the_difficultys_precision_over_its_real_recall():
    """Hard, BEV @0.5: nine cars, all found at precision 1: the curve's points are its real recalls 1/9 … 9/9, each
    at precision 1 (session 48: it plotted the devkit's 41 precision samples against k / 40, which is recall only
    from 40 cars up, and so fell to 0 at "recall" 0.225); the legend keeps the devkit's R40 AP (20.0); nothing
    is drawn for a metric that found no car; recall is the x axis from 0, precision the y axis."""
    import matplotlib.pyplot as plt

    fig = pr_figure(_quarter_length_off(), "hard")
    try:
        ax = fig.axes[0]
        assert "hard" in ax.get_title() and "9 cars" in ax.get_title()
        assert ax.get_xlabel().startswith("recall") and ax.get_ylabel().startswith("precision")
        assert ax.get_xlim()[0] == 0.0 and ax.get_xlim()[1] >= 1.0 and ax.get_ylim()[0] == 0.0 and ax.get_ylim()[1] >= 1.0
        lines = {line.get_label(): line for line in ax.get_lines()}
        hit = lines["BEV @0.5 (AP$_{40}$ 20.0)"]
        np.testing.assert_allclose(hit.get_xdata(), np.arange(1, 10) / 9, rtol=0, atol=1e-15)
        assert list(hit.get_ydata()) == [1.0] * 9
        assert list(lines["BEV @0.7 (AP$_{40}$ 0.0)"].get_ydata()) == []
    finally:
        plt.close(fig)


def test_each_pr_png_draws_its_own_difficulty(tmp_path: Path):
    """Easy (no counted car, every curve at 0), moderate (five cars) and hard (nine): three different pictures."""
    paths = plot_pr_curves(_quarter_length_off(), tmp_path)
    assert [p.name for p in paths] == ["pr_car_easy.png", "pr_car_moderate.png", "pr_car_hard.png"]
    pictures = [cv2.imread(str(p)) for p in paths]
    for i in range(3):
        for j in range(i + 1, 3):
            a, b = pictures[i], pictures[j]
            assert a.shape != b.shape or not np.array_equal(a, b), (paths[i].name, paths[j].name)


def _bands(found: bool = True) -> dict[tuple[float, float], KittiEvalResult]:
    """:func:`_quarter_length_off` in the bands 0–30 m (every car) and 30–60 m (none); or its cars all missed."""
    truth, detections = _quarter_length_off_frames()
    if not found:
        detections = frames(*([] for _ in truth))
    return evaluate_by_distance(truth, detections, edges=(0.0, 30.0, 60.0), metrics=("bev",))


def test_the_distance_table_counts_moderate_cars_and_leaves_an_empty_band_without_ap():
    """At moderate, R40: the near band holds the five moderate cars, BEV AP 10.0 at 0.5 and 0.0 at 0.7; the far
    band holds none, so it has no AP (n/a), not a 0 that reads as every car missed."""
    lines = format_distance_table(_bands()).splitlines()
    assert [cell.strip() for cell in lines[1].split("|")] == ["band (m)    cars", "BEV 0.5", "BEV 0.7"]
    rows = [[cell.split() for cell in line.split("|")] for line in lines[2:]]
    assert rows == [[["0–30", "5"], ["10.0"], ["0.0"]], [["30–60", "0"], ["n/a"], ["n/a"]]]


def test_the_distance_json_counts_each_difficulty_and_gives_r11_and_null_where_no_car_counts():
    document = distance_json(_bands())
    json.dumps(document, allow_nan=False)  # no NaN: strict JSON readers refuse it
    near, far = document
    assert near["range_m"] == [0.0, 30.0] and near["num_ground_truth"] == {"easy": 0, "moderate": 5, "hard": 9}
    hit = near["Car"]["bev"]["0.5"]
    assert hit["R40"] == [None, 10.0, 20.0] and hit["R11"][0] is None
    assert hit["R11"][1:] == pytest.approx([200 / 11, 300 / 11], rel=1e-12)
    assert near["Car"]["bev"]["0.7"] == {"R40": [None, 0.0, 0.0], "R11": [None, 0.0, 0.0]}
    assert far["num_ground_truth"] == {"easy": 0, "moderate": 0, "hard": 0}
    assert far["Car"]["bev"]["0.5"] == {"R40": [None] * 3, "R11": [None] * 3}


def test_the_distance_plot_draws_the_other_models_own_ap():
    """Beside this model's AP by band, the other's (which finds nothing: 0 in the near band, none in the far)."""
    import matplotlib.pyplot as plt

    fig = by_distance_figure(_bands(), _bands(found=False), names=("this", "blind"))
    try:
        lines = {line.get_label(): list(line.get_ydata()) for line in fig.axes[0].get_lines()}
        np.testing.assert_array_equal(lines["BEV @0.5 (this)"], [10.0, np.nan])
        np.testing.assert_array_equal(lines["BEV @0.5 (blind)"], [0.0, np.nan])
    finally:
        plt.close(fig)


def test_the_difference_table_is_this_minus_other_in_the_metrics_both_have():
    """This (every metric) against a model that found nothing, scored in BEV only: only BEV rows, +AP of this."""
    truth, _ = _quarter_length_off_frames()
    other = evaluate(truth, frames(*([] for _ in truth)), metrics=("bev",))
    lines = format_difference(_quarter_length_off(), other, "blind").splitlines()
    assert lines[0] == "Car AP (%, R40): this − blind"
    assert [line.split() for line in lines[1:]] == [
        ["BEV", "@0.5", "easy", "+0.0", "moderate", "+10.0", "hard", "+20.0"],
        ["BEV", "@0.7", "easy", "+0.0", "moderate", "+0.0", "hard", "+0.0"]]


def test_the_gap_share_covers_bev_and_3d():
    """The middle model finds every car, as the high one; the low one none: it closes the whole gap, 1, in BEV and
    in 3D (the paper's columns; not in 2D)."""
    truth = frames(*([obj()] for _ in range(41)))
    every = evaluate(truth, frames(*([obj(score=0.9)] for _ in range(41))))
    none = evaluate(truth, frames(*([] for _ in range(41))))
    ones = {"0.7": [1.0] * 3, "0.5": [1.0] * 3}
    assert gap_json(every, none, every) == {"share": {"bev": ones, "3d": ones}}


# ----------------------------------------------------------------------------- evaluation.harness
def _object_folder_with_a_16_line_scan(folder: Path) -> Path:
    """KITTI frame 000003 with its scan already thinned to 16 lines (a 16-line sensor's own scan)."""
    for part, suffix in (("image_2", ".png"), ("calib", ".txt"), ("label_2", ".txt")):
        (folder / part).mkdir(parents=True)
        shutil.copy(KITTI / part / f"000003{suffix}", folder / part)
    (folder / "velodyne").mkdir()
    points = read_velodyne(KITTI / "velodyne" / "000003.bin").points
    emulate_beams(points, 16).astype(np.float32).tofile(folder / "velodyne" / "000003.bin")
    return folder


@pytest.mark.parametrize(("models", "input_mode"), [("edge-lidar16", "lidar16"), ("edge", "lidar16+camera")])
def test_the_16_line_rows_refuse_scans_that_have_16_lines_already(tmp_path: Path, models: str, input_mode: str):
    """The lidar16 rows thin 64-line scans to 16; a scan with 16 lines already would lose three rings in four
    (or fail frame by frame), so the run is refused before the detector loads, naming the scan."""
    data = _object_folder_with_a_16_line_scan(tmp_path / "kitti")
    with pytest.raises(InputError, match=re.escape(f"{data / 'velodyne' / '000003.bin'}: points: the scan has 16 "
                                                   "rings, not 64")):
        run_detection(data, REPO / "weights" / models, input_mode, tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()


def test_a_detection_run_names_an_unknown_input_and_a_lidar_only_directory_for_the_camera_row(tmp_path: Path):
    with pytest.raises(InputError, match=r"^--input: 'radar' is not one of lidar64, lidar16, lidar16\+camera$"):
        run_detection(KITTI, REPO / "weights" / "edge", "radar", tmp_path / "out")
    with pytest.raises(InputError, match=r"is a LiDAR-only \(pixor\.onnx\) model directory, which does not fit "
                                         r"--input lidar16\+camera"):
        run_detection(KITTI, REPO / "weights" / "edge-lidar16", "lidar16+camera", tmp_path / "out")


def test_a_detection_run_keeps_low_scores_by_default(tmp_path: Path):
    """AP integrates over the whole precision-recall curve, so a run keeps detections down to 0.05 unless told,
    not pipeline.detect's 0.5 (which cuts the curve's tail and lowers AP): the 16-line PIXOR on frame 000003
    writes boxes scored under 0.5."""
    run = run_detection(KITTI, REPO / "weights" / "edge-lidar16", "lidar16", tmp_path / "out", frames=["000003"],
                        progress=False)
    scores = [o.score for o in read_labels(run.results / "000003.txt", needs_score=True)]
    assert scores and min(scores) < 0.5 and min(scores) >= 0.05


def test_the_network_depth_is_resized_to_the_crop_bilinearly_with_pixel_centres_aligned():
    """Two columns 0 and 2 to four: output centres x = 0.5 … 3.5 sit at source x = (x + 0.5) / 2 - 0.5 = -0.25,
    0.25, 0.75, 1.25, clamped to the edge pixels: 0, 0.5, 1.5, 2 (nearest would give 0, 0, 2, 2)."""
    wide = _to_crop_resolution(np.array([[0.0, 2.0], [0.0, 2.0]], np.float32), (2, 4))
    np.testing.assert_allclose(wide, [[0.0, 0.5, 1.5, 2.0]] * 2, rtol=0, atol=1e-6)


def _object_folder_with_dense_depth(folder: Path) -> Path:
    """KITTI frame 000006 with its 64-line scan projected as the dense ground truth (depth_2/), no labels."""
    for part in ("image_2", "velodyne", "calib"):
        (folder / part).mkdir(parents=True)
    for part, suffix in (("image_2", ".png"), ("velodyne", ".bin"), ("calib", ".txt")):
        shutil.copy(KITTI / part / f"000006{suffix}", folder / part)
    frame = load_frame(KITTI, "000006")
    (folder / "depth_2").mkdir()
    write_depth_png(folder / "depth_2" / "000006.png", sparse_depth_map(frame.points, frame.calib, frame.image_hw))
    return folder


def test_depth_on_an_object_folder_thins_the_scan_to_the_lines_asked(tmp_path: Path):
    """beams 16: the network sees a 16-line scan; None: the scan as stored. Other inputs, other depth maps."""
    data = _object_folder_with_dense_depth(tmp_path / "kitti")
    thinned = run_depth(data, EDGE, progress=False, beams=16)
    whole = run_depth(data, EDGE, progress=False, beams=None)
    assert (thinned.input, whole.input) == ("16-line emulated scan", "scan as stored")
    assert thinned.mean.n_pixels == whole.mean.n_pixels and thinned.mean.mae_mm != whole.mean.mae_mm
    with pytest.raises(InputError, match=f"^--data: {re.escape(str(data))} has no frames to evaluate$"):
        run_depth(data, EDGE, progress=False, first=0)


def test_a_drive_with_its_calibration_goes_in_whole_without_beams_and_first_takes_the_first(make_drive, caplog):
    """beams None: velodyne_raw as given, whatever calibration lies beside the drive (nothing to thin, nothing to
    warn of); first 1 of two frames: the first by id."""
    drive = make_drive(frame_ids=("0000000005", "0000000007"))
    with caplog.at_level(logging.WARNING):
        whole = run_depth(drive, EDGE, progress=False, beams=None)
    assert whole.input == "velodyne_raw as given (projected 64-line scan)" and not caplog.records
    assert sorted(whole.per_frame) == ["0000000005", "0000000007"]
    first = run_depth(drive, EDGE, progress=False, beams=None, first=1)
    assert list(first.per_frame) == ["0000000005"]


# ----------------------------------------------------------------------------- evaluation.kitti_eval, lines no test reached
def test_unknown_interpolation_and_curve_are_refused_by_name():
    result = evaluate(frames([obj()]), frames([obj(score=0.9)]), metrics=("bev",))
    with pytest.raises(ValueError, match="points must be 'R40' or 'R11', got 'R20'"):
        result.ap("bev", 0.7, "moderate", "R20")  # type: ignore[arg-type]
    with pytest.raises(KeyError, match=r"no curve for 3d @ 0\.7 moderate; metrics: \('bev',\)"):
        result.curve("3d", 0.7, "moderate")


def test_cars_whose_fields_carry_no_box_leave_nothing_to_evaluate_and_say_so(caplog: pytest.LogCaptureFixture):
    """The devkit evaluates a metric only when some detection carries its fields: a car detection without a 2D box
    (left -1) or a ground-plane box (x, z -1000) leaves none, which is said, not silently an empty table."""
    blank = obj(score=0.9, left=-1.0, x=-1000.0, z=-1000.0)
    with caplog.at_level(logging.WARNING, logger="evaluation.kitti_eval"):
        result = evaluate(frames([obj()]), frames([blank]))
    assert result.metrics == () and result.curves == ()
    assert "no Car detection carries a 2D box or a ground-plane box: nothing to evaluate" in caplog.text


def test_a_set_without_a_single_detection_scores_zero_on_every_draw():
    """A compared model that found nothing (every result file empty) misses every car in every draw: AP 0, beside a
    set that finds all 41 cars (AP 100 on all frames). The JSON counts the draws (5), not the sets (2)."""
    truth = frames(*([obj()] for _ in range(41)))
    nothing = frames(*([] for _ in range(41)))
    everything = frames(*([obj(score=0.9)] for _ in range(41)))
    spread = bootstrap(truth, [nothing, everything], resamples=5, metrics=("bev",), jackknife=False)
    assert spread.ap.shape == (2, 5, 1, 2, 3)
    assert (spread.ap[0] == 0.0).all() and (spread.full[0] == 0.0).all()
    assert spread.full[1].tolist() == [[[100.0] * 3] * 2]
    assert spread_json(evaluate(truth, nothing, metrics=("bev",)), spread)["draws"] == 5
