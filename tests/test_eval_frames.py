"""evaluation.frames: which frames an evaluation reads and what it refuses, called directly (no subprocess)."""

from __future__ import annotations

from pathlib import Path

import pytest

from evaluation.frames import check_ground_truth, first_frames, ground_truth_frames, load_label_dirs
from pipeline.errors import InputError
from pipeline.kitti import write_labels
from tests.test_kitti_eval import obj


def _folders(tmp_path: Path, gt_ids: tuple[str, ...], result_ids: tuple[str, ...], score: float | None = 0.9
             ) -> tuple[Path, Path]:
    gt, results = tmp_path / "gt", tmp_path / "results"
    gt.mkdir()
    results.mkdir()
    for frame_id in gt_ids:
        write_labels(gt / f"{frame_id}.txt", [obj()])
    for frame_id in result_ids:
        write_labels(results / f"{frame_id}.txt", [obj(score=score)])
    return gt, results


def test_frames_are_read_in_id_order_and_first_frames_takes_the_first(tmp_path: Path):
    gt, results = _folders(tmp_path, ("000007", "000002", "000005"), ("000007", "000002", "000005"))
    labels = load_label_dirs(gt, results)
    assert labels.frame_ids == ("000002", "000005", "000007") and len(labels.detections) == 3
    assert first_frames(ground_truth_frames(gt), 2) == ["000002", "000005"]
    assert first_frames(["a", "b"], 5) == ["a", "b"] and first_frames(["a", "b"], None) == ["a", "b"]


def test_a_missing_result_file_is_refused_unless_counted_as_empty(tmp_path: Path):
    """As the devkit: a frame without a result file is an error; --missing-as-empty counts it as no detections."""
    gt, results = _folders(tmp_path, ("000000", "000001"), ("000000",))
    with pytest.raises(InputError, match=r"1 of 2 frames have no result file, e\.g\. 000001\.txt"):
        load_label_dirs(gt, results)
    labels = load_label_dirs(gt, results, missing_as_empty=True)
    assert labels.missing_predictions == ("000001",) and len(labels.detections[1]) == 0 and len(labels.detections[0]) == 1


def test_no_result_file_for_any_frame_is_refused_even_as_empty(tmp_path: Path):
    gt, results = _folders(tmp_path, ("000000",), ("000009",))
    with pytest.raises(InputError, match="no result file matches a frame"):
        load_label_dirs(gt, results, missing_as_empty=True)


def test_a_result_line_without_a_score_is_refused(tmp_path: Path):
    gt, results = _folders(tmp_path, ("000000",), ("000000",), score=None)
    with pytest.raises(InputError, match="000000.txt"):
        load_label_dirs(gt, results)


def test_the_ground_truth_folder_must_hold_the_frames(tmp_path: Path):
    gt, results = _folders(tmp_path, ("000000",), ("000000",))
    with pytest.raises(InputError, match="ground-truth label file not found for frame 000003"):
        load_label_dirs(gt, results, ["000000", "000003"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no ground-truth label files"):
        ground_truth_frames(tmp_path / "empty")
    with pytest.raises(InputError, match="not a directory"):
        load_label_dirs(gt, gt / "000000.txt")
    (gt / "000001.txt").write_text("Car 0 0\n")
    with pytest.raises(InputError, match="000001.txt"):
        check_ground_truth(gt, ["000000", "000001"])
