"""Session 50 review of evaluation/ and benchmarks/accuracy.py: strict JSON from --depth, a car's pixels are those
whose centres lie in its box, the bootstrap refuses unscored detections, and label mode refuses --emulate-beams."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from benchmarks.accuracy import main as accuracy
from evaluation.depth_metrics import car_surface
from evaluation.kitti_eval import bootstrap, evaluate
from evaluation.labels import LabelArrays
from pipeline.kitti import write_labels
from tests.conftest import KITTI, object_folder_with_depth
from tests.test_kitti_eval import obj


def _refuse_constant(name: str) -> float:
    raise ValueError(f"not JSON: {name}")


def test_depth_json_parses_strictly_with_null_for_bands_without_cars(tiny_models, tmp_path: Path, capsys) -> None:
    """Frame 000003's one moderate car is 13 m away: the 20–35 and 35–50 m bands have no car. Their figures were
    written as NaN, which no strict JSON parser reads; they are null now."""
    data = object_folder_with_depth(tmp_path / "data", "000003")
    frames = tmp_path / "frames.txt"
    frames.write_text("000003\n")
    out = tmp_path / "depth.json"
    code = accuracy(["--depth", "--data", str(data), "--models", str(tiny_models), "--frames", str(frames),
                     "--json", str(out), "--no-progress"])
    assert code == 0, capsys.readouterr().err
    depth = json.loads(out.read_text(), parse_constant=_refuse_constant)["depth"]
    for key, name in (("car_median_abs_mm_by_band", "median_mm"), ("car_points_in_box_by_band", "mean_share")):
        assert depth[key]["0-20"]["cars"] == 1 and depth[key]["0-20"][name] is not None
        assert depth[key]["35-50"] == {name: None, "cars": 0}


def test_a_three_pixel_box_holds_the_nine_pixels_whose_centres_lie_in_it() -> None:
    """The simulator writes a box of pixels 2…4 × 3…5 as its edges, centre ± 0.5: (1.5, 2.5, 4.5, 5.5). The window
    was floor(top) … ceil(bottom) inclusive, 5 × 5 = 25 pixels with a ring around the box."""
    truth = np.full((10, 12), 20.0)
    window, on_car = car_surface(truth, (1.5, 2.5, 4.5, 5.5), 20.0)
    assert window == (slice(3, 6), slice(2, 5)) and on_car.sum() == 9


def test_a_box_narrower_than_a_pixel_keeps_the_pixel_its_middle_lies_in_and_one_off_the_map_none() -> None:
    truth = np.full((10, 12), 20.0)
    window, on_car = car_surface(truth, (6.1, 3.2, 6.4, 3.8), 20.0)  # between centres 6 and 7, 3 and 4
    assert window == (slice(4, 5), slice(6, 7)) and on_car.sum() == 1
    # Left of and above the map: no pixel (a stop below 0 made the window most of the map).
    window, on_car = car_surface(truth, (-6.0, -5.0, -2.5, -2.5), 20.0)
    assert on_car.size == 0
    window, on_car = car_surface(truth, (13.0, 11.0, 20.0, 15.0), 20.0)  # right of and below it
    assert on_car.size == 0


def test_bootstrap_refuses_detections_without_a_score_as_evaluate_does() -> None:
    """Unscored detections gave every bootstrap AP 0 without a word, where evaluate refuses them."""
    truth = [LabelArrays.from_objects([obj()]) for _ in range(3)]
    unscored = [LabelArrays.from_objects([obj(score=float("nan"))]) for _ in range(3)]
    with pytest.raises(ValueError, match="frame 0: detections need a score"):
        evaluate(truth, unscored)
    scored = [LabelArrays.from_objects([obj(score=0.9)]) for _ in range(3)]
    with pytest.raises(ValueError, match=r"detection set 1, frame 0: detections need a score \(16th label field\)"):
        bootstrap(truth, [scored, unscored], resamples=5)


@pytest.mark.parametrize("flag", [
    ["--emulate-beams", "16"], ["--emulate-beams", "0"], ["--models", "m"], ["--provider", "cpu"],
    ["--input", "lidar16"], ["--out", "o"], ["--score-threshold", "0.3"], ["--mirror-tta"], ["--depth-dir", "d"],
])
def test_label_mode_refuses_every_flag_of_a_model_run_besides_data(tmp_path: Path, capsys, flag: list[str]) -> None:
    """Result files are evaluated as they are: a flag that only a model run reads is refused, not ignored
    (--emulate-beams was taken and ignored, against docs/evaluation.md). --data itself chooses the other mode."""
    labels = tmp_path / "labels"
    labels.mkdir()
    write_labels(labels / "000000.txt", [obj()])
    with pytest.raises(SystemExit) as usage:
        accuracy(["--gt-labels", str(labels), "--pred-labels", str(labels), *flag])
    assert usage.value.code == 2
    assert f"argument {flag[0]}: not allowed with argument --gt-labels" in capsys.readouterr().err


def test_a_missing_gap_folder_is_refused_before_the_detector_runs(tiny_models, tmp_path: Path, capsys) -> None:
    """--gap-to-pred-labels was checked only by the evaluation after the detector had been over every frame."""
    compare = tmp_path / "compare"
    compare.mkdir()
    out = tmp_path / "run"
    code = accuracy(["--data", str(KITTI), "--models", str(tiny_models), "--input", "lidar16+camera", "--frames", "1",
                     "--out", str(out), "--compare-pred-labels", str(compare),
                     "--gap-to-pred-labels", str(tmp_path / "absent"), "--no-progress"])
    assert code == 2
    assert f"--gap-to-pred-labels: {tmp_path / 'absent'}: prediction label directory not found" in (
        capsys.readouterr().err)
    assert not list(out.glob("data/*.txt"))


def test_the_detector_may_not_write_over_the_gap_folder(tiny_models, tmp_path: Path, capsys) -> None:
    """--out's result folder was checked against --compare-pred-labels alone: the stronger model's results given
    as --gap-to-pred-labels were overwritten by this run's, and the gap measured against itself."""
    compare, out = tmp_path / "compare", tmp_path / "run"
    compare.mkdir()
    (compare / "000000.txt").write_text("")
    (out / "data").mkdir(parents=True)
    stronger = out / "data" / "000000.txt"
    stronger.write_text("")
    code = accuracy(["--data", str(KITTI), "--models", str(tiny_models), "--input", "lidar16+camera", "--frames", "1",
                     "--out", str(out), "--compare-pred-labels", str(compare),
                     "--gap-to-pred-labels", str(out / "data"), "--no-progress"])
    assert code == 2 and "would overwrite the results of --gap-to-pred-labels" in capsys.readouterr().err
    assert stronger.read_text() == ""
