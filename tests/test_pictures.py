"""The pictures people read rather than the numbers: each says what it shows (a key, a title, a colour bar,
axes in metres), keeps its text inside it, and draws the same thing in the same colour in every tool."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.presets import PRESETS
from pipeline.render import (
    GROUND_TRUTH_BGR,
    PREDICTION_BGR,
    depth_colours,
    draw_colour_scale,
    error_colours,
    fit_text,
    render_bev,
    render_camera,
    render_depth,
    render_depth_panel,
)

REPO = Path(__file__).resolve().parents[1]
KITTI = REPO / "tests" / "data" / "kitti" / "training"
@pytest.fixture(scope="module")
def frame():
    from pipeline.frame import load_frame

    return load_frame(KITTI, "000006")


BOX = np.array([[20.0, 5.0, -0.9, 4.0, 1.7, 1.5, 0.3]])  # a car 20 m ahead, 5 m to the left


def _has(picture: np.ndarray, bgr: tuple[int, int, int]) -> bool:
    return bool((picture == bgr).all(axis=2).any())


def test_bev_key_says_what_the_colours_are_and_which_way_is_ahead():
    """With legend=True the top-left corner holds the title and a line of each colour drawn (the boxes are
    elsewhere); without it the corner stays as the points left it."""
    grid = PRESETS["tiny"].bev
    points = np.zeros((0, 4), np.float32)
    keyed = render_bev(points, grid, BOX, np.array([0.9]), BOX, title="frame 000006, model edge", legend=True)
    plain = render_bev(points, grid, BOX, np.array([0.9]), BOX)
    assert keyed.shape == plain.shape == (704, 800, 3)  # the key is drawn on the picture, not beside it
    corner = keyed[:80, :300]
    assert _has(corner, PREDICTION_BGR) and _has(corner, GROUND_TRUTH_BGR)
    assert not _has(plain[:80, :300], PREDICTION_BGR) and not _has(plain[:80, :300], GROUND_TRUTH_BGR)
    assert (corner > 200).all(axis=2).sum() > 200  # the white text of the title and the rows
    # Only ground truth drawn (the demo's core pictures): the key names only that.
    gt_only = render_bev(points, grid, gt_boxes=BOX, legend=True)[:80, :300]
    assert _has(gt_only, GROUND_TRUTH_BGR) and not _has(gt_only, PREDICTION_BGR)


def test_bev_ring_labels_stay_off_the_lane_ahead_and_the_sensor_is_marked():
    """The range rings' labels once sat straight ahead of the sensor, under the boxes of the cars in its lane;
    they now sit where each ring leaves the picture. The sensor is a white triangle at the bottom centre."""
    grid = PRESETS["tiny"].bev
    picture = render_bev(np.zeros((0, 4), np.float32), grid)
    centre = picture.shape[1] // 2
    lane = picture[:-20, centre - 30:centre + 30]  # 3 m either side of straight ahead, above the sensor
    assert lane.max() <= 70  # the rings' grey alone, no label text
    labels = picture[-20:, centre + 60:]  # the bottom edge to the right: 10 m, 20 m, 30 m
    assert (labels > 150).all(axis=2).sum() > 50
    sensor = picture[-16:, centre - 8:centre + 9]
    assert (sensor == 255).all(axis=2).sum() > 30


def test_long_titles_are_cut_to_the_picture():
    long = "frame 000006, model " + "x" * 300
    cut = fit_text(long, 400)
    assert cut.endswith("...") and cv2.getTextSize(cut, cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)[0][0] <= 400
    assert fit_text("short", 400) == "short"


def test_camera_key_sits_top_right_and_only_when_asked(frame):
    """The camera view's key is in the top-right corner, clear of a video's caption at the top left."""
    ahead = np.array([[15, 2, -0.9, 4, 1.7, 1.5, 0.3]])
    black = np.zeros_like(frame.image)
    keyed = render_camera(black, frame.calib, ahead, np.array([0.9]), ahead, title="frame 000006", legend=True)
    plain = render_camera(black, frame.calib, ahead, np.array([0.9]), ahead)
    width = keyed.shape[1]
    corner = keyed[:70, width - 260:]
    assert _has(corner, PREDICTION_BGR) and _has(corner, GROUND_TRUTH_BGR)
    assert not _has(plain[:70, width - 260:], PREDICTION_BGR)
    assert not (keyed[:70, :200] > 0).any()  # the top-left corner is left for the caption


def test_depth_panel_maps_carry_their_colour_bars():
    """Each depth map of the accuracy harness's panel has a colour bar from 0 m (warm) to 80 m (blue) in its
    top-right corner, the error map its own 0–5 m bar; the panel keeps its size."""
    height, width = 120, 600
    truth = np.full((height, width), 30.0, np.float32)
    panel = render_depth_panel(np.zeros((height, width, 3), np.uint8), truth, truth)
    assert panel.shape == (4 * height, width, 3)
    near, far = depth_colours()[0], depth_colours()[-1]
    for row in (1, 2):  # prediction and ground truth
        corner = panel[row * height:row * height + 24, width // 2:]
        assert (corner == near).all(axis=2).any() and (corner == far).all(axis=2).any()
    error_corner = panel[3 * height:3 * height + 24, width // 2:]
    assert (error_corner == error_colours()[-1]).all(axis=2).any()
    assert not (panel[:24, width // 2:] == far).all(axis=2).any()  # the camera row has none


def test_depth_panel_title_goes_into_the_camera_rows_label_only():
    """A title (the frame and the model) lengthens the camera row's label; the maps' rows stay as they were."""
    height, width = 120, 600
    truth = np.full((height, width), 30.0, np.float32)
    camera = np.zeros((height, width, 3), np.uint8)
    plain = render_depth_panel(camera, truth, truth)
    titled = render_depth_panel(camera, truth, truth, title="frame 000006, model edge")
    np.testing.assert_array_equal(titled[height:], plain[height:])
    drawn = [np.flatnonzero((panel[:height] > 0).any(axis=(0, 2))).max() for panel in (plain, titled)]
    assert drawn[1] > drawn[0] + 50  # the label reaches further right


def test_colour_bar_runs_from_low_to_high_as_the_depth_picture_colours():
    picture = np.zeros((40, 400, 3), np.uint8)
    left, top, right, bottom = draw_colour_scale(picture, depth_colours(80.0), 0.0, 80.0, "m")
    assert bottom - top >= 8  # tall enough to see
    bar = picture[top, left:right]
    np.testing.assert_array_equal(bar[0], render_depth(np.array([[1e-3]]))[0, 0])  # near: warm
    np.testing.assert_array_equal(bar[-1], render_depth(np.array([[80.0]]))[0, 0])  # far: blue
    assert right <= picture.shape[1]


def test_demo_sparse_depth_picture_is_labelled_with_its_scale():
    from pipeline.demo import sparse_depth_picture

    rgb = np.zeros((1, 3, 100, 500), np.float32)
    sparse = np.zeros((1, 1, 100, 500), np.float32)
    sparse[0, 0, 60, 100] = 40.0
    picture = sparse_depth_picture(rgb, sparse)
    assert picture.shape == (200, 500, 3)
    lower_right = picture[100:124, 250:]
    assert (lower_right == depth_colours()[-1]).all(axis=2).any()
    assert (picture[:24, :200] == 255).all(axis=2).sum() > 20 and (picture[100:124, :200] == 255).all(axis=2).sum() > 20


# ----------------------------------------------------------------------------- matplotlib figures (dev extras)


def _evaluation():
    from evaluation.kitti_eval import evaluate
    from evaluation.labels import LabelArrays
    from pipeline.kitti import read_labels

    gt = [LabelArrays.from_objects(read_labels(p)) for p in sorted((KITTI / "label_2").glob("*.txt"))]
    shifted = []
    for g in gt:  # moved 0.3 box lengths along their heading: some overlaps pass 0.5, fewer 0.7
        location = g.location.copy()
        location[:, 0] += 0.3 * g.dimensions[:, 2] * np.cos(g.rotation_y)
        shifted.append(dataclasses.replace(g, location=location, score=np.linspace(1, 0.5, len(g))))
    return evaluate(gt, shifted)


def test_pr_and_distance_plots_draw_each_metric_in_one_colour():
    """BEV @0.7 was blue in the PR curves and orange in AP by distance (matplotlib's colour cycle in each
    plot's order); now each (metric, threshold) keeps its colour, and the titles say how many frames."""
    pytest.importorskip("matplotlib")
    import matplotlib.pyplot as plt

    from evaluation.report import by_distance_figure, pr_figure, series_colour

    result = _evaluation()
    pr = pr_figure(result, "moderate", source="weights/edge on tests/data/kitti")
    by_distance = by_distance_figure({(0.0, 20.0): result, (20.0, 80.0): result})
    try:
        colours = {}
        for fig in (pr, by_distance):
            ax = fig.axes[0]
            assert f"{result.n_frames} frames" in ax.get_title()
            for line in ax.get_lines():
                name = line.get_label().split(" (")[0]  # "BEV @0.7"
                colours.setdefault(name, set()).add(line.get_color())
        assert "weights/edge on tests/data/kitti" in pr.axes[0].get_title()
        assert all(len(c) == 1 for c in colours.values()), colours
        assert colours["BEV @0.7"] == {series_colour("bev", 0.7)} != colours["BEV @0.5"]
        assert len({next(iter(c)) for c in colours.values()}) == len(colours)  # no two series share one
        legend = [t.get_text() for t in pr.axes[0].get_legend().get_texts()]
        assert legend[0].startswith("BEV @0.5") and legend[-1].startswith("2D bbox @0.7")  # the table's order
    finally:
        plt.close("all")


def _latency_report() -> dict:
    rng = np.random.default_rng(0)
    stages = {name: list(rng.uniform(low, 2 * low, 20)) for name, low in
              (("prepare", 1.0), ("depth_net", 40.0), ("ray_table", 0.02), ("pixor", 30.0), ("decode", 0.9))}
    return {"_samples": {"stages": stages, "overlapped": {"voxelize": list(rng.uniform(1, 2, 20))},
                         "end_to_end": list(rng.uniform(80, 300, 20))},
            "preset": "edge-split-near35", "precision": "fp32", "input": "16-line scan + camera", "frames": 20,
            "warmup": 3, "machine": {"cpu": "AMD EPYC", "cpu_generation": "family 25 model 17", "cores": 2}}


def test_latency_plot_reads_top_down_as_the_report_and_keeps_its_p50s_inside():
    """The first stage on top (the printed report's order), each box's p50 written beside it and inside the
    axes (the slowest one's was cut by the frame), the title naming precision and input."""
    pytest.importorskip("matplotlib")
    import matplotlib.pyplot as plt

    sys.path.insert(0, str(REPO))
    from benchmarks.latency import latency_figure

    fig = latency_figure(_latency_report())
    try:
        ax = fig.axes[0]
        fig.canvas.draw()
        ticks = sorted(ax.get_yticklabels(), key=lambda t: -t.get_window_extent().y0)  # top to bottom on screen
        names = [t.get_text() for t in ticks]
        assert names[0] == "prepare" and names[-1] == "end to end"
        assert "fp32" in ax.get_title() and "16-line scan + camera" in ax.get_title()
        assert ax.get_xlabel().startswith("latency per frame (ms")
        p50s = [t for t in ax.texts if t.get_text().startswith("p50 ")]
        assert len(p50s) == len(names)
        frame = ax.get_window_extent()
        assert all(t.get_window_extent().x1 <= frame.x1 for t in p50s)
    finally:
        plt.close("all")


def test_load_plot_gives_each_status_one_colour_in_every_run():
    """A status's colour depended on which others the run had (sorted order in matplotlib's cycle): "bad 422"
    was orange without 503s and green with them."""
    pytest.importorskip("matplotlib")
    import matplotlib.colors as mcolors
    import matplotlib.pyplot as plt

    sys.path.insert(0, str(REPO))
    from benchmarks.load import LoadResult, Sample, load_figure, status_colour

    assert status_colour("200") == "tab:blue" and status_colour("503") == "tab:orange"
    assert status_colour("bad 422") == status_colour("bad 400") != status_colour("503")
    assert status_colour("500") == status_colour("error ConnectError") == "tab:red"
    for statuses in (["200", "bad 422"], ["200", "503", "bad 422"]):
        samples = [Sample(start_s=i * 0.1, latency_ms=10.0 + i, status=s.removeprefix("bad "),
                          broken=s.startswith("bad ")) for i, s in enumerate(statuses * 5)]
        result = LoadResult(url="", clients=1, duration_s=1.0, requests=len(samples), status_counts={},
                            throughput_ok_per_s=1.0, throughput_all_per_s=1.0, latency_ms={}, stage_p50_ms={},
                            rss_mb={}, rss_series=[])
        fig = load_figure(samples, result, "test")
        try:
            legend = fig.axes[0].get_legend()
            for text, handle in zip(legend.get_texts(), legend.legend_handles, strict=True):
                status = text.get_text().rsplit(" (", 1)[0]
                assert mcolors.same_color(handle.get_facecolor(), status_colour(status)), status
            assert all(float(t).is_integer() for t in fig.axes[0].get_yticks())  # counts of requests
        finally:
            plt.close("all")



def test_the_load_plots_p50_line_joins_over_tenths_without_an_answer():
    """A short run leaves tenths of the load without an answer, whose p50 is NaN: the line the legend draws
    broke into lone markers. It joins the tenths that have one."""
    pytest.importorskip("matplotlib")
    import matplotlib.pyplot as plt

    sys.path.insert(0, str(REPO))
    from benchmarks.load import LoadResult, Sample, load_figure

    samples = [Sample(start_s=t, latency_ms=150.0 + t, status="200") for t in (0.05, 0.25, 0.45)]
    windows = [{"start_s": i / 10, "end_s": (i + 1) / 10, "p50_ms": 150.0 + i if i % 2 == 0 else float("nan")}
               for i in range(6)]
    result = LoadResult(url="", clients=1, duration_s=0.6, requests=3, status_counts={}, throughput_ok_per_s=5.0,
                        throughput_all_per_s=5.0, latency_ms={}, stage_p50_ms={}, rss_mb={}, rss_series=[],
                        windows=windows)
    fig = load_figure(samples, result, "test")
    try:
        (line,) = [ln for ln in fig.axes[1].get_lines() if ln.get_label() == "p50 per tenth of the run"]
        assert list(line.get_ydata()) == [150.0, 152.0, 154.0] and line.get_linestyle() == "-"
    finally:
        plt.close("all")

def test_sim_report_figure_has_colour_bars_and_bev_axes_in_metres():
    """The projected LiDAR is coloured as the depth pictures of the other tools (near warm), with a colour bar;
    the BEV has axes in metres and its height colour bar."""
    pytest.importorskip("matplotlib")
    import matplotlib.pyplot as plt

    sys.path.insert(0, str(REPO))
    from benchmarks.sim_report import depth_colour_map, figure_of, load

    frame = load(KITTI, 1)[0]
    fig = figure_of([("KITTI " + frame.name, frame)])
    try:
        labels = [ax.get_xlabel() + "|" + ax.get_ylabel() for ax in fig.axes]
        assert any(label.startswith("depth (m)") for label in labels)  # the horizontal bar under the projection
        assert any("height z (m)" in label for label in labels)
        assert "right of the sensor (m)|ahead of the sensor (m)" in labels
        near = np.array(depth_colour_map()(0.0)[:3]) * 255
        np.testing.assert_allclose(near, render_depth(np.array([[1e-3]]))[0, 0][::-1], atol=1)
    finally:
        plt.close("all")


def test_demo_core_names_its_pictures_and_keys_them(tmp_path):
    """Without a model directory the demo lists each picture it wrote (it once printed the folder alone), and
    its BEV pictures carry the key: which scan, and the ground truth in red."""
    from pipeline.demo import run_core

    summary = run_core("000006", tmp_path)
    paths = [Path(p) for p in summary["pictures"]]
    assert [p.name for p in paths] == ["000006_bev_64.png", "000006_bev_16.png", "000006_sparse_depth_16.png"]
    bev = cv2.imread(str(paths[1]))
    assert _has(bev[:80, :300], GROUND_TRUTH_BGR) and (bev[:20, :300] == 255).all(axis=2).sum() > 50
