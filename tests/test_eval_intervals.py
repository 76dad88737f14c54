"""Bootstrap intervals at the edges a mutation test found unpinned: the BCa pole on the upper side, every draw
below the estimate, BC ignoring a jackknife, draws whose gap is negative, and the options the convenience
methods and the report's tables pass on (set, level, method).

Expected values come from the rules in ``bootstrap_interval``'s and ``BootstrapResult``'s docstrings (Efron's
BCa; the percentile interval is the central ``level`` of the draws; a share exists only where the upper set is
above the lower one), worked with ``statistics.NormalDist`` and ``np.percentile`` on small hand-made draws.
"""

from __future__ import annotations

import logging
import math
import statistics
from pathlib import Path

import numpy as np
import pytest

from evaluation.frames import first_frames, load_label_dirs
from evaluation.kitti_eval import BootstrapResult, bootstrap, bootstrap_interval, evaluate
from evaluation.overlaps import image_overlap
from evaluation.report import format_gap, format_spread, gap_json, gap_share, spread_json
from pipeline.kitti import write_labels
from tests.test_kitti_eval import frames, obj

NORMAL = statistics.NormalDist()


def test_bca_bound_past_the_pole_on_the_upper_side_is_the_largest_draw():
    """The mirror of the lower-side case: one jackknife value far below the rest (a ≈ +1/6), 90 % of the draws
    below the estimate (z0 ≈ 1.28) and a level of 1 − 10⁻⁹ (z ≈ +6.1) put the upper bound past the pole
    a (z0 + z) = 1; the bound is then the largest draw, not the wrapped-around formula's smallest."""
    draws = np.arange(100.0)
    jackknife = np.zeros(100)
    jackknife[0] = -1.0
    spread = jackknife.mean() - jackknife
    a = (spread**3).sum() / (6 * (spread**2).sum() ** 1.5)
    level = 1.0 - 1e-9
    z0, z_high = NORMAL.inv_cdf(0.90), NORMAL.inv_cdf((1 + level) / 2)
    assert a * (z0 + z_high) > 1.0  # the case this test is about
    bounds = bootstrap_interval(draws, 89.5, jackknife, level=level)
    assert bounds.acceleration == pytest.approx(a) and bounds.z0 == pytest.approx(z0)
    assert bounds.high == draws.max() and bounds.low < bounds.high


def test_bca_bound_exactly_at_the_pole_is_the_draws_edge():
    """At a (z0 + z) = 1 exactly the adjustment's denominator is 0: the bound is the draws' edge, the limit from
    either side of the pole, not a division by zero. A second jackknife outlier tunes a (bisection, then a scan of
    neighbouring floats) until the product is 1 in floating point, checked on the acceleration the interval reports."""
    draws = np.arange(100.0)
    level = 1.0 - 1e-7
    z_high = NORMAL.inv_cdf(50.0 * (1.0 + level) / 100.0)  # the upper tail as a share, computed as the code does

    def with_outliers(second: float) -> np.ndarray:
        jackknife = np.zeros(100)
        jackknife[0], jackknife[1] = -1.0, second
        return jackknife

    def past_pole(second: float) -> float:
        bounds = bootstrap_interval(draws, 89.5, with_outliers(second), level=level)
        return 1.0 - bounds.acceleration * (bounds.z0 + z_high)

    below, above = -0.5, 0.0  # the second outlier: a · (z0 + z) < 1 at −0.5, > 1 at 0
    assert past_pole(below) > 0.0 > past_pole(above)
    while True:
        middle = (below + above) / 2
        if middle in (below, above):
            break
        below, above = (middle, above) if past_pole(middle) > 0.0 else (below, middle)
    second = next(below + k * math.ulp(below) for k in range(-3000, 3000)
                  if past_pole(below + k * math.ulp(below)) == 0.0)
    bounds = bootstrap_interval(draws, 89.5, with_outliers(second), level=level)
    assert bounds.high == draws.max() and bounds.low < bounds.high


def test_every_draw_below_the_estimate_gives_the_percentile_interval_with_a_note():
    """Every draw below the value on all frames: the share below is 1, z0 = Φ⁻¹(1) = +∞, and no BCa interval can
    be read off the draws; the percentile one (central 95 %), saying so."""
    draws = np.arange(11.0)  # 0 … 10, all below 20
    bounds = bootstrap_interval(draws, 20.0, np.array([0.0, 1.0, 5.0]))
    assert bounds.method == "percentile" and bounds.z0 == math.inf and "every draw lies below" in bounds.note
    assert (bounds.low, bounds.high) == pytest.approx((0.25, 9.75))  # ranks 0.025 · 10 and 0.975 · 10
    assert bounds.draws == 11


def test_bc_leaves_the_jackknife_out_even_when_given_one():
    """``bc`` is BCa with a = 0: a skewed jackknife given alongside changes nothing, and without one there is
    nothing to note."""
    draws = np.arange(100.0)
    z0 = NORMAL.inv_cdf(0.30)  # 30 of the 100 draws below 29.5
    expected = np.percentile(draws, [100 * NORMAL.cdf(2 * z0 + NORMAL.inv_cdf(q)) for q in (0.025, 0.975)])
    bounds = bootstrap_interval(draws, 29.5, np.array([0.0, 0.0, 0.0, 1.0, 5.0]), method="bc")
    assert bounds.method == "bc" and bounds.acceleration == 0.0
    assert (bounds.low, bounds.high) == pytest.approx(tuple(expected))
    # BC asked for without a jackknife (--interval bc runs none) is no fallback from BCa: nothing to note.
    plain = bootstrap_interval(draws, 29.5, method="bc")
    assert (plain.low, plain.high, plain.method, plain.note) == (bounds.low, bounds.high, "bc", "")


def test_a_level_of_zero_is_refused_and_so_is_an_unknown_method_of_the_bootstrap():
    """An interval's level lies strictly between 0 and 1 (0 would be a single point of the draws); the
    bootstrap refuses a method it cannot give before it matches any frame."""
    with pytest.raises(ValueError, match="level"):
        bootstrap_interval(np.arange(10.0), 4.5, level=0.0)
    with pytest.raises(ValueError, match="method"):
        bootstrap(frames([obj()]), [frames([obj(score=0.9)])], resamples=1, method="basic")


def _three_sets(middle: np.ndarray, low: np.ndarray, high: np.ndarray, full: tuple[float, float, float],
                method: str = "bca", jackknife: np.ndarray | None = None) -> BootstrapResult:
    """A one-cell-per-difficulty result (BEV @0.7, the same values at every difficulty) of three sets."""
    ap = np.stack([middle, low, high])[:, :, None, None, None] * np.ones((1, 1, 1, 1, 3))
    whole = np.array(full)[:, None, None, None] * np.ones((3, 1, 1, 3))
    left_out = None if jackknife is None else jackknife[:, :, None, None, None] * np.ones((1, 1, 1, 1, 3))
    return BootstrapResult(metrics=("bev",), iou_thresholds=(0.7,), ap=ap, seed=0, full=whole, jackknife=left_out,
                           method=method)


def test_a_share_leaves_out_draws_and_jackknife_samples_where_the_upper_set_is_below_the_lower():
    """A share exists only where high is above low: 4 of the 10 draws have high below low (a negative gap) and
    give no share; the percentile interval is over the other 6, and BCa's acceleration over the jackknife samples
    with a positive gap only."""
    middle = np.array([50.0, 55.0, 60.0, 65.0, 70.0, 75.0, 50.0, 50.0, 50.0, 50.0])
    low = np.full(10, 40.0)
    high = np.array([90.0, 90.0, 90.0, 90.0, 90.0, 90.0, 30.0, 20.0, 35.0, 39.0])
    result = _three_sets(middle, low, high, (60.0, 40.0, 90.0), method="percentile")
    shares = (middle[:6] - 40.0) / 50.0  # 0.2 … 0.7
    low_bound, high_bound, used = result.gap_share_interval("bev", 0.7, "moderate")
    assert used == 6
    assert (low_bound, high_bound) == pytest.approx(tuple(np.percentile(shares, [2.5, 97.5])))
    # The jackknife: samples 0 … 3 have a gap; 4 and 5 have high below low and must not enter the acceleration.
    jackknife = np.array([[55.0, 56.0, 58.0, 70.0, 80.0, 10.0], [40.0] * 6, [90.0, 90.0, 90.0, 90.0, 30.0, 20.0]])
    left_out_shares = (jackknife[0, :4] - 40.0) / 50.0
    spread = left_out_shares.mean() - left_out_shares
    a = (spread**3).sum() / (6 * (spread**2).sum() ** 1.5)
    with_jackknife = _three_sets(middle, low, high, (60.0, 40.0, 90.0), jackknife=jackknife)
    assert with_jackknife.gap_share_bounds("bev", 0.7, "moderate").acceleration == pytest.approx(a)


def test_the_convenience_methods_pass_the_set_level_and_method_on():
    """interval, difference_interval and gap_share_interval give the interval of the set, level and method asked
    for: the percentile interval at level 0.8 is the draws' 10th and 90th percentiles."""
    first = np.arange(0.0, 101.0, 10.0)  # 11 draws: 0, 10, … 100
    second = np.zeros(11)
    third = first * 2.0
    result = _three_sets(first, second, third, (40.0, 0.0, 100.0))  # BCa (the default) would differ: z0 ≠ 0
    assert result.interval("bev", 0.7, "moderate", index=2, level=0.8, method="percentile") == pytest.approx(
        (20.0, 180.0))
    assert result.difference_interval("bev", 0.7, "moderate", 2, 0, level=0.8, method="percentile") == pytest.approx(
        (10.0, 90.0))
    # Share of the gap from set 1 (0) up to set 2 (2 × set 0's draw): 1/2 on every draw with a gap (10 of 11).
    low, high, used = result.gap_share_interval("bev", 0.7, "moderate", level=0.8, method="percentile")
    assert (low, high, used) == pytest.approx((0.5, 0.5, 10))
    spread = _three_sets(first, second, second + 1.0, (50.0, 0.0, 1.0), method="percentile")
    assert spread.gap_share_interval("bev", 0.7, "moderate", level=0.8) == pytest.approx((10.0, 90.0, 11))


def _forty_one(detected: bool) -> list:
    """AP 100 (every car found) or 0 (none) on 41 frames of one car each (41 counted cars reach every R40 point)."""
    return frames(*([obj(score=0.9)] if detected else [] for _ in range(41)))


def test_the_report_gives_this_minus_other_and_the_intervals_at_the_level_asked():
    """format_spread and spread_json: the difference row is this − other (100 − 0 = +100) and every interval is
    at the level passed (0.8: the draws' 10th and 90th percentiles), not the default 95 %."""
    truth = frames(*([obj()] for _ in range(41)))
    this, other = evaluate(truth, _forty_one(True), metrics=("bev",)), evaluate(truth, _forty_one(False),
                                                                                metrics=("bev",))
    draws = np.arange(0.0, 101.0, 10.0)
    ap = np.stack([draws, np.zeros(11)])[:, :, None, None, None] * np.ones((1, 1, 1, 2, 3))
    spread = BootstrapResult(metrics=("bev",), iou_thresholds=(0.7, 0.5), ap=ap, seed=0,
                             full=np.stack([np.full((1, 2, 3), 100.0), np.zeros((1, 2, 3))]), method="percentile")
    text = format_spread(this, spread, other, "other", level=0.8)
    assert "80% percentile interval over 11 bootstrap draws" in text
    rows = text.splitlines()
    difference = rows[rows.index("this − other (paired: the same draws for both)") + 1]
    assert "easy +100.0 [ 10.0,  90.0]" in difference
    assert "easy  100.0 [ 10.0,  90.0]" in rows[1]
    document = spread_json(this, spread, other, level=0.8)
    assert document["interval"]["bev"]["0.7"][1] == pytest.approx([10.0, 90.0])
    assert document["difference"]["bev"]["0.7"][1] == 100.0
    assert document["difference_interval"]["bev"]["0.7"][1] == pytest.approx([10.0, 90.0])


def test_the_gap_report_gives_the_share_interval_in_percent_at_the_level_asked():
    """format_gap and gap_json (sets: this, low, high): low 0 and high 100 on every draw, this 0, 10, … 100, so
    the share is this / 100 and its 80 % percentile interval is [0.1, 0.9] (10 % and 90 % in the table). A high
    set below the low one has no share (None), whatever the sign of this − low."""
    truth = frames(*([obj()] for _ in range(41)))
    found, missed = evaluate(truth, _forty_one(True), metrics=("bev",)), evaluate(truth, _forty_one(False),
                                                                                  metrics=("bev",))
    draws = np.arange(0.0, 101.0, 10.0)
    ap = np.stack([draws, np.zeros(11), np.full(11, 100.0)])[:, :, None, None, None] * np.ones((1, 1, 1, 2, 3))
    full = np.array([100.0, 0.0, 100.0])[:, None, None, None] * np.ones((3, 1, 2, 3))
    spread = BootstrapResult(metrics=("bev",), iou_thresholds=(0.7, 0.5), ap=ap, seed=0, full=full,
                             method="percentile")
    text = format_gap(found, missed, found, "low", "high", spread, level=0.8)
    assert "with its 80% percentile interval" in text
    assert "easy  100 % [  10,   90]" in text.splitlines()[1]
    document = gap_json(found, missed, found, spread, level=0.8)
    assert document["share"]["bev"]["0.7"][1] == 1.0
    assert document["interval"]["bev"]["0.7"][1] == pytest.approx([0.1, 0.9])
    assert document["draws_used"]["bev"]["0.7"][1] == 11
    assert gap_share(missed, found, missed, "bev", 0.7, "moderate") is None  # high 0 below low 100


# ----------------------------------------------------------------------------- frame lists (evaluation.frames)
def test_frames_n_warns_only_when_there_are_fewer_frames(caplog: pytest.LogCaptureFixture):
    """--frames N with exactly N frames takes them all and has nothing to warn of; with fewer it says so."""
    with caplog.at_level(logging.WARNING, logger="evaluation.frames"):
        assert first_frames(["a", "b"], 2) == ["a", "b"]
    assert not caplog.records
    with caplog.at_level(logging.WARNING, logger="evaluation.frames"):
        assert first_frames(["a"], 2) == ["a"]
    assert "--frames 2: only 1 frame(s) to evaluate" in caplog.text


def test_result_files_outside_a_split_are_not_warned_of(tmp_path: Path, caplog: pytest.LogCaptureFixture):
    """With frame ids (a split) the other result files are left out on purpose: no "not scored" warning; without
    them, every ground-truth file is a frame and a result file without one is named."""
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    gt.mkdir()
    pred.mkdir()
    for frame_id in ("000000", "000001"):
        write_labels(gt / f"{frame_id}.txt", [obj()])
    for frame_id in ("000000", "000001", "000099"):
        write_labels(pred / f"{frame_id}.txt", [obj(score=0.9)])
    with caplog.at_level(logging.WARNING, logger="evaluation.frames"):
        assert load_label_dirs(gt, pred, ["000000"]).frame_ids == ("000000",)
    assert "not scored" not in caplog.text
    with caplog.at_level(logging.WARNING, logger="evaluation.frames"):
        load_label_dirs(gt, pred)
    assert "1 result file(s)" in caplog.text and "000099.txt" in caplog.text


# ----------------------------------------------------------------------------- 2D overlap (evaluation.overlaps)
def test_boxes_that_only_touch_do_not_overlap_even_a_zero_area_detection():
    """The devkit's boxoverlap divides only when the intersection's width and height are both above 0: a
    zero-width detection lying on a DontCare region's area has overlap 0 with it, not 0 / 0, and two boxes that
    share an edge overlap 0."""
    zero_width = np.array([[10.0, 10.0, 10.0, 20.0]])
    region = np.array([[0.0, 0.0, 50.0, 50.0]])
    with np.errstate(all="raise"):  # no division may happen at all
        assert image_overlap(zero_width, region, "detection").tolist() == [[0.0]]
        assert image_overlap(np.array([[50.0, 0.0, 80.0, 50.0]]), region).tolist() == [[0.0]]


# ----------------------------------------------------------------------------- draws by frame id
def _varied_frames(tmp_path: Path) -> tuple[Path, Path, list[str]]:
    """12 frames of one car each in label folders: found at scores that differ frame to frame, missed, or
    found beside a false positive, so that which frames a draw takes moves every AP."""
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    gt.mkdir()
    pred.mkdir()
    ids = [f"{i:06d}" for i in range(12)]
    for i, frame_id in enumerate(ids):
        write_labels(gt / f"{frame_id}.txt", [obj()])
        found = [obj(score=0.3 + 0.05 * i)] if i % 3 else []
        if i % 4 == 1:
            found.append(obj(x=10.0, score=0.95 - 0.02 * i))
        write_labels(pred / f"{frame_id}.txt", found)
    return gt, pred, ids


def test_the_draws_do_not_depend_on_the_order_the_frames_are_listed_in(tmp_path: Path):
    """The same frames listed in two orders (a split file's lines reversed, or shuffled) give the same draws,
    jackknife and intervals for a seed: the draws go to the frames by id, in the bootstrap itself, so
    accuracy.py's --split-file order changes nothing. Ids listed in order (the default listing of the runs
    published) draw what they drew before ids were taken, when draws went to the frames as listed."""
    from benchmarks.accuracy import LabelEvalConfig, run

    gt, pred, ids = _varied_frames(tmp_path)
    listings = {"sorted": ids, "reversed": ids[::-1], "shuffled": [ids[i] for i in (5, 0, 11, 3, 8, 1, 10, 2, 7, 4, 9, 6)]}
    spreads = {}
    for name, listed in listings.items():
        split = tmp_path / f"{name}.txt"
        split.write_text("\n".join(listed) + "\n")
        outcome = run(LabelEvalConfig(gt_labels=gt, pred_labels=pred, split_file=split, progress=False, bootstrap=40,
                                      seed=3))
        assert outcome.spread is not None
        spreads[name] = outcome.spread
    first = spreads["sorted"]
    assert np.ptp(first.ap[0, :, 0, 0, 1]) > 10  # the draws differ from one another: their order could matter
    for name in ("reversed", "shuffled"):
        np.testing.assert_array_equal(spreads[name].ap, first.ap, err_msg=name)
        np.testing.assert_array_equal(spreads[name].jackknife, first.jackknife, err_msg=name)
        for metric in first.metrics:
            for difficulty in ("easy", "moderate", "hard"):
                assert spreads[name].interval(metric, 0.5, difficulty) == first.interval(metric, 0.5, difficulty)
    # The sorted listing's draws are those made over the frames as listed, without ids.
    truth = load_label_dirs(gt, pred)
    as_listed = bootstrap(truth.ground_truth, [truth.detections], resamples=40, seed=3, metrics=first.metrics)
    np.testing.assert_array_equal(as_listed.ap, first.ap)
    np.testing.assert_array_equal(as_listed.jackknife, first.jackknife)
    with pytest.raises(ValueError, match="frame_ids: 11 ids for 12 frames"):
        bootstrap(truth.ground_truth, [truth.detections], resamples=1, frame_ids=ids[1:])
