"""benchmarks/accuracy.py's label-file mode called in-process: options reach every evaluation it makes."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from benchmarks.accuracy import LabelEvalConfig, distance_edges, run
from pipeline.kitti import write_labels
from tests.test_kitti_eval import obj


def _folder(path: Path, objects: list) -> Path:
    path.mkdir()
    write_labels(path / "000000.txt", objects)
    return path


def test_counting_small_detections_reaches_the_compared_model_and_the_distance_bands(tmp_path: Path):
    """The car's only detection is 20 px high: ignored by the devkit's rule (the car is neither found nor
    missed: no AP), counted with --count-small-detections (one car found: R11 = 100/11). The option holds for
    this model, the compared one and every distance band alike."""
    gt = _folder(tmp_path / "gt", [obj()])
    small = [obj(height_px=20.0, score=0.9)]
    config = LabelEvalConfig(gt_labels=gt, pred_labels=_folder(tmp_path / "a", small), progress=False,
                             compare_pred_labels=_folder(tmp_path / "b", small), distance_edges=(0.0, 80.0),
                             json_path=tmp_path / "ap.json")
    for counted, expected in ((False, 0.0), (True, 100 / 11)):
        outcome = run(LabelEvalConfig(**{**config.__dict__, "ignore_small_detections": not counted}))
        document = json.loads((tmp_path / "ap.json").read_text())
        assert outcome.result.ap("bev", 0.7, "moderate", "R11") == pytest.approx(expected)
        assert document["compared_with"]["bev"]["0.7"]["R11"][1] == pytest.approx(expected)
        assert outcome.by_distance[(0.0, 80.0)].ap("bev", 0.7, "moderate", "R11") == pytest.approx(expected)


@pytest.mark.parametrize("text", ["0,20,20", "20,10", "-5,10", "0"])
def test_distance_edges_must_increase_from_zero(text: str):
    with pytest.raises(argparse.ArgumentTypeError):
        distance_edges(text)
    assert distance_edges("0,20,35.5") == (0.0, 20.0, 35.5)


def test_the_bootstrap_scores_only_the_metrics_both_models_carry(tmp_path: Path):
    """A compared model whose result lines have no 3D box (h and y unset) has no 3D AP: the paired bootstrap
    covers BEV alone, not a 3D difference against a column of zeros."""
    gt = _folder(tmp_path / "gt", [obj()])
    outcome = run(LabelEvalConfig(gt_labels=gt, pred_labels=_folder(tmp_path / "a", [obj(score=0.9)]), progress=False,
                                  compare_pred_labels=_folder(tmp_path / "b", [obj(score=0.9, h=-1.0, y=-1000.0)]),
                                  bootstrap=2))
    assert outcome.result.metrics == ("bbox", "bev", "3d") and outcome.spread.metrics == ("bev",)


def test_the_pr_plots_of_a_comparison_draw_both_models(tmp_path: Path, monkeypatch):
    """--compare-pred-labels with --plots: the PR plots showed only this model; they now get the compared
    model's evaluation and both folders' names (its distance plot had them already)."""
    from benchmarks import accuracy

    given = []
    real = accuracy.plot_pr_curves
    monkeypatch.setattr(accuracy, "plot_pr_curves", lambda *args: (given.append(args), real(*args))[1])
    gt = _folder(tmp_path / "gt", [obj(), obj(x=8.0, left=400.0)])
    both = _folder(tmp_path / "both", [obj(score=0.9), obj(x=8.0, left=400.0, score=0.8)])
    one = _folder(tmp_path / "one", [obj(score=0.9)])
    outcome = run(LabelEvalConfig(gt_labels=gt, pred_labels=both, compare_pred_labels=one, progress=False,
                                  plots_dir=tmp_path / "plots"))
    (result, _, _, other, names), = given
    assert result is outcome.result and names == ("both", "one")
    assert other.ap("bev", 0.7, "moderate") == 0.0 < result.ap("bev", 0.7, "moderate")  # one car of two: no R40 AP
    assert other.curve("bev", 0.7, "moderate").recall.tolist() == [0.5]
