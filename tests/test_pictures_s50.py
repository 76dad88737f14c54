"""Session 50's review of the pictures: the BEV key covered the scene beyond 57 m; the depth panel's error row
drew "no ground truth" in zero error's black; a score sat on a labelled car; a one-epoch run's curves hid its
learning rate and validation loss and read its epoch axis in tenths; the simulation report's BEV title ran into
its colour bar and the command named no plot; an empty precision-recall chart said nothing."""

from __future__ import annotations

from pathlib import Path

import cv2
import matplotlib.pyplot as plt
import numpy as np
import pytest

from benchmarks import sim_report
from evaluation.kitti_eval import evaluate
from evaluation.report import pr_figure
from pipeline.presets import PRESETS
from pipeline.render import bev_key_rows, error_colours, key_box, render_bev, render_depth_panel
from tests.conftest import KITTI
from tests.test_kitti_eval import frames, obj

GRID = PRESETS["tiny"].bev  # x 0–70.4 m, y −40–40 m: 704 × 800 pixels at the pictures' 0.1 m
SCENE_H = 704
NO_POINTS = np.zeros((0, 4), np.float32)
# The service's title, the longest the reviewer saw: its key's box was about 497 × 130 pixels.
SERVICE_TITLE = "model 6b5d7996d5cd (edge), preset edge-split-near35, scan thinned to 16 lines"


def test_the_bev_key_covers_no_part_of_the_scene():
    """With the service's key, a detection 60.8 m ahead on the left, the 60 and 70 m ring labels and points
    there lay under the key's black box. Now the key has a strip of its own above the scene: the scene below it
    is pixel for pixel the picture without a key (points, rings, their labels, boxes, scores), at 0.1 m a pixel,
    and the key's box ends above it. A frame with warnings and one without keep one size (a video's frames)."""
    far_left = np.array([[60.8, 12.0, -0.9, 4.0, 1.7, 1.5, 0.0]])
    points = np.repeat(np.array([[65.0, 15.0, -1.0, 0.0], [55.0, 20.0, -1.0, 0.0]], np.float32), 30, axis=0)
    keyed = render_bev(points, GRID, far_left, np.array([0.8]), title=SERVICE_TITLE, legend=True, pseudo=points,
                       warnings=[])
    plain = render_bev(points, GRID, far_left, np.array([0.8]), pseudo=points)
    assert plain.shape == (SCENE_H, 800, 3) and keyed.shape[1:] == plain.shape[1:]
    strip = keyed.shape[0] - SCENE_H
    np.testing.assert_array_equal(keyed[strip:], plain)
    rows = bev_key_rows(SERVICE_TITLE, True, False, True)
    assert key_box(800, rows)[3] < strip
    warned = render_bev(points, GRID, far_left, np.array([0.8]), title=SERVICE_TITLE, legend=True, pseudo=points,
                        warnings=["thin_scan"])
    assert warned.shape == keyed.shape


def test_the_error_row_tells_no_ground_truth_from_zero_error():
    """A pixel without ground truth is a neutral grey in the error row; a pixel with ground truth and no error
    keeps the bar's first colour (black-purple), not that grey."""
    height, width = 120, 400
    truth = np.full((height, width), 30.0, np.float32)
    truth[:, 300:] = 0.0  # no ground truth, whatever the prediction
    prediction = truth.copy()
    prediction[:, 300:] = 50.0
    error = render_depth_panel(np.zeros((height, width, 3), np.uint8), prediction, truth)[3 * height + 40:]
    none, zero = error[:, 350].astype(int), error[:, 150].astype(int)
    assert (none == none[:, :1]).all() and (60 < none).all() and (none < 200).all()  # grey: b = g = r, mid
    np.testing.assert_array_equal(zero, np.broadcast_to(error_colours()[0], zero.shape))
    assert np.abs(zero - none).sum(axis=1).min() > 150


def test_a_score_keeps_off_a_labelled_car():
    """KITTI 000006's 0.53 sat on a labelled car's box: a score whose first spot lies on a labelled car moves."""
    found = np.array([[30.0, 3.0, -0.9, 4.0, 1.7, 1.5, 0.0]])
    labelled = np.array([[33.5, 2.0, -0.9, 4.0, 1.7, 1.5, 0.0]])  # across where the score first goes
    text = (render_bev(NO_POINTS, GRID, found, np.array([0.53]), labelled)
            != render_bev(NO_POINTS, GRID, found, None, labelled)).any(axis=2)
    x, y, _, length, width = labelled[0, :5]
    rows = slice(round((GRID.x_max - x - length / 2) / 0.1), round((GRID.x_max - x + length / 2) / 0.1) + 1)
    cols = slice(round((GRID.y_max - y - width / 2) / 0.1), round((GRID.y_max - y + width / 2) / 0.1) + 1)
    assert text.sum() > 30 and not text[rows, cols].any()


def test_a_one_epoch_runs_curves_show_its_rate_and_validation_loss_on_whole_epochs():
    """One epoch: the learning rate has a marker (its dashed line had no length), the validation loss is drawn
    above the best epoch's line, and the epoch axis reads whole epochs (it read 0.5, 0.6, … 1.5)."""
    # models/ needs torch: the lowest-versions run leaves this test out.
    from models.curves import RunInfo, draw

    history = [{"epoch": 1, "train_loss": 2.95, "val_loss": 2.89, "lr": 1e-3, "bev_ap_0.7_moderate": 0.0,
                "bev_ap_0.5_moderate": 0.0}]
    figure = draw(history, RunInfo("detector", "tiny"), Path("run"))
    figure.draw_without_rendering()
    lines = {line.get_gid(): line for ax in figure.axes for line in ax.get_lines()}
    rate = lines["lr"]
    assert rate.get_marker() not in ("", " ", "None", None) and rate.get_markersize() > 0
    best = [line for line in figure.axes[0].get_lines() if line.get_gid() == "best"]
    assert best and lines["val_loss"].get_zorder() > best[0].get_zorder()
    low, high = figure.axes[1].get_xlim()
    shown = [tick for tick in figure.axes[1].get_xticks() if low <= tick <= high]
    assert shown and all(float(tick).is_integer() for tick in shown)


def test_the_simulation_reports_bev_title_clears_its_colour_bar_and_the_command_names_its_plot(tmp_path, capsys):
    """The BEV panel's title ran into its colour bar's top tick label and the panel was 260 of 1920 pixels wide;
    the command wrote the plot without a line naming it, as accuracy.py and latency.py print one."""
    frame = sim_report.load(KITTI, 1)[0]
    figure = sim_report.figure_of([("simulated " + frame.name, frame), ("KITTI " + frame.name, frame)])
    try:
        figure.set_dpi(80)  # as figure() saves it
        renderer = figure.canvas.get_renderer()
        figure.canvas.draw()
        bars = [ax for ax in figure.axes if ax.get_label() == "<colorbar>" and ax.get_ylabel()]  # the BEVs' own
        for bev, bar in zip(figure.axes[2:6:3], bars, strict=True):
            title = bev.title.get_window_extent(renderer)
            ticks = [label for label in bar.get_yticklabels() if label.get_text()]
            assert ticks and not any(title.overlaps(label.get_window_extent(renderer)) for label in ticks)
            assert bev.get_window_extent(renderer).width > figure.bbox.width / 5
    finally:
        plt.close(figure)
    out = tmp_path / "sim_vs_kitti.png"
    assert sim_report.main(["--sim-data", str(KITTI), "--frames", "1", "--plot", str(out)]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert out.is_file() and f"plot: {out}" in printed


@pytest.mark.parametrize(("truth", "found", "says"), [([], [obj(score=0.9)], "no cars labelled"),
                                                     ([obj()], [], "no detections")])
def test_an_empty_precision_recall_chart_says_why(truth, found, says):
    """No car labelled, or no detection on one: the chart says so where its curves would be, with no legend of
    "AP 0.0" beside an empty axis; a chart with a curve has its legend and no such note."""
    figure = pr_figure(evaluate(frames(truth), frames(found)), "moderate")
    drawn = pr_figure(evaluate(frames([obj()]), frames([obj(score=0.9)])), "moderate")
    try:
        ax = figure.axes[0]
        assert not any(len(line.get_xdata()) for line in ax.get_lines())
        assert any(says in text.get_text() for text in ax.texts) and ax.get_legend() is None
        assert not drawn.axes[0].texts and drawn.axes[0].get_legend() is not None
    finally:
        plt.close(figure)
        plt.close(drawn)


def test_no_ground_truth_grey_is_not_an_error_colour():
    """The grey sits apart from every colour the error bar uses, so it cannot be read as an error."""
    bar = error_colours().astype(int)
    height, width = 60, 200
    truth = np.zeros((height, width), np.float32)
    grey = render_depth_panel(np.zeros((height, width, 3), np.uint8), truth, truth)[3 * height + 40, 100].astype(int)
    assert np.abs(bar - grey).sum(axis=1).min() > 100


def test_a_video_of_odd_sized_pictures_keeps_their_last_row_and_column(tmp_path: Path) -> None:
    """MPEG-4's writer drops an odd last row or column (the BEV picture with its key strip is 877 rows): the
    video is one pixel larger instead, a black row and column added, and the picture's bright last rows show."""
    from pipeline.render import FrameVideo

    picture = np.zeros((75, 101, 3), np.uint8)
    picture[-4:] = 255  # a band along the bottom edge, wide enough to survive the codec's blocks
    video = FrameVideo(tmp_path / "odd.mp4", fps=5)
    for _ in range(2):
        video.add(picture)
    assert video.close()
    capture = cv2.VideoCapture(str(tmp_path / "odd.mp4"))
    assert (capture.get(cv2.CAP_PROP_FRAME_WIDTH), capture.get(cv2.CAP_PROP_FRAME_HEIGHT)) == (102, 76)
    ok, frame = capture.read()
    assert ok and frame[-4:-2, 10:-10].mean() > 200 and frame[30:40, 30:70].mean() < 30
