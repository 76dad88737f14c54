"""The evaluation's pictures draw what the numbers are (session 48's review): precision against the curve's own
recall, not against the devkit's 41 sampling points; a warning where fewer than 41 cars make the devkit's AP
coarse; a palette colour-blind readers can tell apart, with curves lying on each other still seen; the compared
model beside this one; and the car-depth plot's title and axis saying what it shows."""

from __future__ import annotations

import itertools
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pytest

from evaluation.depth_metrics import CAR_BOX_MARGIN_M
from evaluation.kitti_eval import evaluate, evaluate_by_distance
from evaluation.report import (
    SERIES_COLOURS,
    by_distance_figure,
    pr_figure,
    series_colour,
    to_json,
)
from tests.test_evaluation_harness_mutants import _quarter_length_off
from tests.test_kitti_eval import frames, obj

REPO = Path(__file__).resolve().parents[1]


def _lines(fig) -> dict[str, object]:
    return {line.get_label(): line for line in fig.axes[0].get_lines()}


def test_one_car_found_exactly_is_drawn_at_recall_1_precision_1():
    """One car, one exact detection: every curve is the single point (recall 1, precision 1). The old plot put
    the devkit's 41-point row against k / 40, which fell to 0 at "recall 0.025". The legend keeps the devkit's
    AP (0.0: with one car its 40-point AP is 0) and says why it is coarse."""
    result = evaluate(frames([obj()]), frames([obj(score=0.99)]))
    fig = pr_figure(result, "moderate")
    try:
        lines = fig.axes[0].get_lines()
        assert len(lines) == 6
        for line in lines:
            assert list(line.get_xdata()) == [1.0] and list(line.get_ydata()) == [1.0], line.get_label()
            assert "AP$_{40}$ 0.0" in line.get_label()
        legend = fig.axes[0].get_legend().get_title().get_text()
        assert "n=1 car < 41" in legend.replace("\n", " ") and "1 car" in fig.axes[0].get_title()
    finally:
        plt.close(fig)


def test_the_pr_lines_are_the_curves_recall_and_interpolated_precision():
    """Five cars, three found (scores 0.9, 0.8, 0.6) and a false detection at 0.7: BEV @0.5 has its points at the
    JSON's recall 1/5, 2/5, 3/5, not past 3/5; precision 1, 1, 3/4 (interpolated: the best at that recall or
    above); the legend gives the devkit's AP_40 of that curve (its points after the first: 1/40 + 0.75/40
    = 4.375 %)."""
    truth = frames([obj(x=x) for x in (-12.0, -6.0, 0.0, 6.0, 12.0)])
    found = frames([obj(x=-12.0, score=0.9), obj(x=-6.0, score=0.8), obj(x=30.0, left=800.0, score=0.7),
                    obj(x=0.0, score=0.6)])
    result = evaluate(truth, found, metrics=("bev",))
    recall = to_json(result)["details"]["Car"]["bev"]["0.5"]["moderate"]["recall"]
    fig = pr_figure(result, "moderate")
    try:
        line = _lines(fig)["BEV @0.5 (AP$_{40}$ 4.4)"]
        np.testing.assert_allclose(line.get_xdata(), recall, rtol=0, atol=1e-12)
        np.testing.assert_allclose(line.get_xdata(), [0.2, 0.4, 0.6], rtol=0, atol=1e-12)
        np.testing.assert_allclose(line.get_ydata(), [1.0, 1.0, 0.75], rtol=0, atol=1e-12)
        assert result.ap("bev", 0.5, "moderate") == pytest.approx(4.375)
        assert fig.axes[0].get_xlabel().startswith("recall")
    finally:
        plt.close(fig)


def test_the_pr_figure_draws_the_compared_model_dashed_and_named():
    """With another model on the same frames, each series twice: this model's solid, the other's dashed, each
    legend entry naming its model and its own AP, the other's line through its own recall."""
    this = _quarter_length_off()
    truth = frames(*([obj(occluded=o)] for o in [1] * 5 + [2] * 4))
    other = evaluate(truth, frames(*([obj(score=0.9 - 0.01 * i)] if i < 3 else [] for i in range(9))))
    fig = pr_figure(this, "hard", other=other, names=("shifted", "exact"))
    try:
        lines = _lines(fig)
        assert len(lines) == 12
        mine = lines["BEV @0.7 (shifted, AP$_{40}$ 0.0)"]
        theirs = lines["BEV @0.7 (exact, AP$_{40}$ 5.0)"]
        assert mine.get_linestyle() == "-" and theirs.get_linestyle() == "--"
        assert mine.get_color() == theirs.get_color() == series_colour("bev", 0.7)
        np.testing.assert_allclose(theirs.get_xdata(), other.curve("bev", 0.7, "hard").recall, rtol=0, atol=1e-12)
        np.testing.assert_allclose(theirs.get_xdata(), [1 / 9, 2 / 9, 3 / 9], rtol=0, atol=1e-12)
    finally:
        plt.close(fig)


# Machado, Oliveira and Fernandes (2009), severity 1, on linear RGB: how a deuteranope and a protanope see a colour.
DEUTERANOPIA = np.array([[0.367322, 0.860646, -0.227968], [0.280085, 0.672501, 0.047413],
                         [-0.011820, 0.042940, 0.968881]])
PROTANOPIA = np.array([[0.152286, 1.052583, -0.204868], [0.114503, 0.786281, 0.099216],
                       [-0.003882, -0.048116, 1.051998]])


def _lab(colour: str, vision: np.ndarray) -> np.ndarray:
    """CIELAB (D65) of a matplotlib colour as seen with ``vision``."""
    from matplotlib.colors import to_rgb

    srgb = np.asarray(to_rgb(colour))
    linear = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    seen = np.clip(vision @ linear, 0, 1)
    xyz = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]]) @ seen
    f = np.cbrt(np.maximum(xyz / np.array([0.95047, 1.0, 1.08883]), 1e-9))
    return np.array([116 * f[1] - 16, 500 * (f[0] - f[1]), 200 * (f[1] - f[2])])


@pytest.mark.parametrize("vision", [DEUTERANOPIA, PROTANOPIA], ids=["deutan", "protan"])
def test_no_two_series_colours_look_alike_to_colour_blind_readers(vision: np.ndarray):
    """3D @0.7 and 2D @0.7 (tab:red, tab:green), 3D @0.5 and 2D @0.5 (tab:orange, tab:olive) were 7 CIELAB units
    apart under deuteranopia: one colour. Every pair is now at least 15 apart (a clearly seen difference)."""
    close = [(a, b, round(float(np.linalg.norm(_lab(SERIES_COLOURS[a], vision) - _lab(SERIES_COLOURS[b], vision)))))
             for a, b in itertools.combinations(SERIES_COLOURS, 2)]
    assert [c for c in close if c[2] < 15] == []


def _pixels_near(picture: np.ndarray, colour: str, tolerance: float = 20.0) -> int:
    from matplotlib.colors import to_rgb

    rgb = np.asarray(to_rgb(colour)) * 255
    return int((np.linalg.norm(picture[..., :3].astype(float) - rgb, axis=2) < tolerance).sum())


def test_curves_lying_on_each_other_all_stay_visible():
    """Hard: every car found at IoU 0.5 in BEV, 3D and 2D, and at 0.7 in 2D: four identical curves. Drawn one
    over the other at one width, only the last (2D @0.7) was seen; now each shows inside the axes."""
    fig = pr_figure(_quarter_length_off(), "hard")
    try:
        fig.canvas.draw()
        box = fig.axes[0].get_window_extent()
        picture = np.asarray(fig.canvas.buffer_rgba())
        height = picture.shape[0]
        axes = picture[int(height - box.y1) + 1:int(height - box.y0) - 1, int(box.x0) + 1:int(box.x1) - 1]
        for series in (("bev", 0.5), ("3d", 0.5), ("bbox", 0.5), ("bbox", 0.7)):
            assert _pixels_near(axes, series_colour(*series)) > 30, series
    finally:
        plt.close(fig)


def test_a_band_with_few_cars_is_marked_and_counts_one_car_as_1_car():
    """0–20 m: one car, found exactly (the devkit's AP 0); 20–80 m: 41 cars; 80–100 m: none. Only the first band
    is hatched and carries its AP_40 ceiling (0.0); its tick says "1 car", not "1 cars"."""
    truth = frames([obj(z=10.0)], *([obj(z=30.0)] for _ in range(41)))
    found = frames([obj(z=10.0, score=0.9)], *([obj(z=30.0, score=0.9 - 0.001 * i)] for i in range(41)))
    bands = evaluate_by_distance(truth, found, edges=(0.0, 20.0, 80.0, 100.0), metrics=("bev",))
    fig = by_distance_figure(bands)
    try:
        ax = fig.axes[0]
        ticks = [label.get_text() for label in ax.get_xticklabels()]
        assert ticks == ["0–20\n1 car", "20–80\n41 cars", "80–100\n0 cars"]
        hatched = [p for p in ax.patches if p.get_hatch()]
        assert len(hatched) == 1
        extent = hatched[0].get_path().transformed(hatched[0].get_patch_transform()).get_extents()
        assert -0.5 < extent.x0 < extent.x1 < 0.5  # over the first band's tick (at 0) alone
        notes = [t.get_text() for t in ax.texts]
        assert notes == ["n=1 < 41:\nAP$_{40}$ ≤ 0.0"]
        np.testing.assert_array_equal(_lines(fig)["BEV @0.7"].get_ydata(), [0.0, 100.0, np.nan])
    finally:
        plt.close(fig)


def test_the_car_depth_figure_says_its_cars_and_the_grown_box():
    """Its title counts the cars drawn (the printed text's bands count them too), its right axis says the box is
    grown by the margin the harness uses, as the printed line does."""
    # Imported here: it is new, and the other tests stand without it.
    from evaluation.report import car_depth_figure

    fig = car_depth_figure([(10.0, 100.0), (30.0, 400.0)], [(10.0, 0.9), (30.0, 0.7)],
                           "depth on the moderate cars, 1 frame\nweights/edge on data")
    try:
        assert fig._suptitle.get_text() == "depth on the moderate cars, 1 frame, 2 cars\nweights/edge on data"
        assert f"BEV box grown by {CAR_BOX_MARGIN_M:g} m" in fig.axes[1].get_ylabel().replace("\n", " ")
    finally:
        plt.close(fig)


def test_the_depth_runs_car_plot_names_model_data_and_frames(tmp_path: Path, monkeypatch):
    """``accuracy.py --depth --plots``: the car-depth plot's title named only the input; it names the model
    directory, the data folder and the frame count (the shipped edge model on frame 000006, no torch)."""
    from benchmarks import accuracy
    from tests.conftest import object_folder_with_depth

    data = object_folder_with_depth(tmp_path / "data", "000006")
    (tmp_path / "frames.txt").write_text("000006\n")
    calls = []
    real = accuracy.plot_car_depth
    monkeypatch.setattr(accuracy, "plot_car_depth", lambda *args: (calls.append(args), real(*args))[1])
    edge = REPO / "weights" / "edge"
    code = accuracy.main(["--depth", "--data", str(data), "--models", str(edge), "--frames",
                          str(tmp_path / "frames.txt"), "--plots", str(tmp_path / "plots"), "--no-progress"])
    assert code == 0
    (errors, _, path, title, *margin), = calls
    assert title == f"depth on the moderate cars, 1 frame\n{edge} (16-line emulated scan) on {data}"
    assert margin == [CAR_BOX_MARGIN_M] and errors and path.is_file()
