"""The pictures people read rather than the numbers: each says what it shows (a key, a title, a colour bar,
axes in metres), keeps its text inside it, and draws the same thing in the same colour in every tool."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.presets import PRESETS, get_preset
from pipeline.render import (
    GROUND_TRUTH_BGR,
    OUTSIDE_VIEW_BGR,
    PREDICTION_BGR,
    bev_key_rows,
    depth_colours,
    draw_colour_scale,
    draw_key,
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
    elsewhere); without it the corner stays as the points left it. The key is in a strip above the scene (on it,
    it hid what lay beyond 57 m on the left): the scene below is the picture without the key."""
    grid = PRESETS["tiny"].bev
    points = np.zeros((0, 4), np.float32)
    keyed = render_bev(points, grid, BOX, np.array([0.9]), BOX, title="frame 000006, model edge", legend=True)
    plain = render_bev(points, grid, BOX, np.array([0.9]), BOX)
    assert plain.shape == (704, 800, 3) and keyed.shape[1:] == plain.shape[1:] and keyed.shape[0] > 704
    np.testing.assert_array_equal(keyed[-704:], plain)
    corner = keyed[:80, :300]
    assert _has(corner, PREDICTION_BGR) and _has(corner, GROUND_TRUTH_BGR)
    assert not _has(plain[:80, :300], PREDICTION_BGR) and not _has(plain[:80, :300], GROUND_TRUTH_BGR)
    assert (corner > 200).all(axis=2).sum() > 200  # the white text of the title and the rows
    # Only ground truth drawn (the demo's core pictures): the key names only that.
    gt_only = render_bev(points, grid, gt_boxes=BOX, legend=True)[:80, :300]
    assert _has(gt_only, GROUND_TRUTH_BGR) and not _has(gt_only, PREDICTION_BGR)


def test_bev_ring_labels_sit_on_the_forward_axis_and_the_sensor_is_marked():
    """Each range ring's label sits just right of the forward axis, just above where the ring crosses it (the
    70 m ring, at the far edge, just below), so a box ahead reads against them; none at the picture's right edge,
    where they once sat level with cars 20 m nearer. The sensor is a white triangle at the bottom centre."""
    grid = PRESETS["tiny"].bev
    picture = render_bev(np.zeros((0, 4), np.float32), grid)
    centre, bottom = picture.shape[1] // 2, picture.shape[0]  # the sensor: y = 0, x = 0 at the bottom edge
    light = (picture > 150).all(axis=2)
    for metres in range(10, 80, 10):
        crossing = bottom - metres * 10
        rows = slice(crossing + 2, crossing + 20) if metres == 70 else slice(crossing - 16, crossing - 1)
        assert light[rows, centre + 3:centre + 40].sum() > 20, metres
    assert not light[:-20, centre + 60:].any() and not light[:-20, :centre - 2].any()  # off the axis: no label
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
            "models": "weights/edge", "preset": "edge-split-near35", "precision": "fp32",
            "input": "16-line scan + camera", "frames": 20,
            "warmup": 3, "machine": {"cpu": "AMD EPYC", "cpu_generation": "family 25 model 17", "cores": 2}}


def test_latency_plot_reads_top_down_as_the_report_and_keeps_its_p50s_inside():
    """The first stage on top (the printed report's order), each box's p50 and mean written beside it and inside
    the axes (the slowest one's was cut by the frame), each box's mean marked (the README quotes the end-to-end
    mean), the title naming the model directory, precision and input."""
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
        assert ax.get_title().startswith("lowres3d weights/edge: ")
        assert "fp32" in ax.get_title() and "16-line scan + camera" in ax.get_title()
        assert ax.get_xlabel().startswith("latency per frame (ms")
        p50s = [t for t in ax.texts if t.get_text().startswith("p50 ")]
        assert len(p50s) == len(names)
        # One mean marker a box, at the mean of that row's samples (rows 1.. top to bottom: the axis is inverted).
        report = _latency_report()["_samples"]
        data = [*report["stages"].values(), *report["overlapped"].values(), report["end_to_end"]]
        means = [ln for ln in ax.get_lines() if ln.get_marker() == "D"]
        assert len(means) == len(data) == len(names)
        for row, (line, values) in enumerate(zip(means, data, strict=True), start=1):
            assert line.get_ydata()[0] == row and line.get_xdata()[0] == pytest.approx(np.mean(values))
        for text, values in zip(p50s, data, strict=True):
            assert text.get_text() == f"p50 {np.median(values):.3g} · mean {np.mean(values):.3g} ms"
        frame, figure = ax.get_window_extent(), fig.get_window_extent()
        # Nothing cut: the figures beside the boxes inside the axes, the title and the x label inside the figure.
        cut = [t.get_text() for t in p50s if t.get_window_extent().x1 > frame.x1]
        cut += [t.get_text() for t in (ax.title, ax.xaxis.label)
                if t.get_window_extent().x0 < figure.x0 or t.get_window_extent().x1 > figure.x1]
        assert not cut, cut
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



def test_the_load_plots_p50_line_is_the_median_of_each_run_of_200s_in_send_order():
    """The p50 line was per tenth of the run's time, and a short run's tenths without an answer broke it into
    lone markers. Now each of its ten points is the median of a run of n // 10 consecutive 200s in send order
    (the runs spread evenly from the first 200 to the last when n is not a multiple of 10), at the middle of
    their send times; other statuses and broken requests are left out, whatever order the samples come in; a
    run of fewer than ten 200s draws one joined point per answer. (tests/test_bench_load.py pins the first and
    last points against the printed tenths on 30 answers in order; not the points between, the spreading, the
    order or the short run.)"""
    pytest.importorskip("matplotlib")
    import matplotlib.pyplot as plt

    sys.path.insert(0, str(REPO))
    from benchmarks.load import LoadResult, Sample, load_figure

    def p50_line(samples: list) -> tuple[list[float], list[float], str]:
        result = LoadResult(url="", clients=1, duration_s=12.0, requests=len(samples), status_counts={},
                            throughput_ok_per_s=1.0, throughput_all_per_s=1.0, latency_ms={}, stage_p50_ms={},
                            rss_mb={}, rss_series=[])
        fig = load_figure(samples, result, "test")
        try:
            (line,) = [ln for ln in fig.axes[1].get_lines() if ln.get_label().startswith("p50 ")]
            return list(line.get_xdata()), list(line.get_ydata()), line.get_linestyle()
        finally:
            plt.close(fig)

    # 23 answers, the k-th sent at 0.5 k s taking k² ms: runs of 2, starting at these 200s (21 / 9 apart, rounded).
    answers = [Sample(start_s=0.5 * k, latency_ms=float(k * k), status="200") for k in range(23)]
    others = [Sample(start_s=0.5 * k + 0.1, latency_ms=9000.0, status="503") for k in range(0, 23, 4)]
    others += [Sample(start_s=0.5 * k + 0.2, latency_ms=1.0, status="200", broken=True) for k in range(1, 23, 5)]
    shuffled = [(answers + others)[i] for i in np.random.default_rng(0).permutation(len(answers) + len(others))]
    xs, ys, style = p50_line(shuffled)
    firsts = [0, 2, 5, 7, 9, 12, 14, 16, 19, 21]
    assert ys == [(k * k + (k + 1) ** 2) / 2 for k in firsts] and style == "-"
    assert xs == pytest.approx([0.5 * k + 0.25 for k in firsts])
    short = [Sample(start_s=t, latency_ms=150.0 + t, status="200") for t in (0.45, 0.05, 0.25)]
    xs, ys, style = p50_line(short)
    assert xs == [0.05, 0.25, 0.45] and ys == [150.05, 150.25, 150.45] and style == "-"


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
    its BEV pictures carry the key: which scan, and the labelled cars' colour."""
    from pipeline.demo import run_core

    summary = run_core("000006", tmp_path)
    paths = [Path(p) for p in summary["pictures"]]
    assert [p.name for p in paths] == ["000006_bev_64.png", "000006_bev_16.png", "000006_sparse_depth_16.png"]
    bev = cv2.imread(str(paths[1]))
    assert _has(bev[:80, :300], GROUND_TRUTH_BGR) and (bev[:20, :300] == 255).all(axis=2).sum() > 50


# ----------------------------------------------------------------------------- session 48: the BEV and camera review


def _deuteranope(bgr: np.ndarray) -> np.ndarray:
    """sRGB 0–255 of BGR colours as a deuteranope sees them (Machado, Oliveira and Fernandes 2009, severity 1)."""
    machado = np.array([[0.367322, 0.860646, -0.227968], [0.280085, 0.672501, 0.047413],
                        [-0.011820, 0.042940, 0.968881]])
    rgb = np.asarray(bgr, float)[..., ::-1] / 255
    linear = np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4)
    seen = np.clip(linear @ machado.T, 0, 1)
    return np.where(seen <= 0.0031308, seen * 12.92, 1.055 * seen ** (1 / 2.4) - 0.055) * 255


def _drawn_colour(picture: np.ndarray, blank: np.ndarray) -> np.ndarray:
    """The commonest colour among the pixels ``picture`` changed from ``blank``: the lines' own colour."""
    colours, counts = np.unique(picture[_changed_mask(picture, blank)], axis=0, return_counts=True)
    return colours[np.argmax(counts)]


def _changed_mask(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return (a != b).any(axis=2)


def test_labelled_cars_and_detections_read_apart_without_red_green_and_by_line_style():
    """A deuteranope saw the red ground truth and green detections as two yellows (76 apart in simulated sRGB);
    the drawn colours now stay far apart, and the labelled cars are dashed (many pieces) where a detection is one
    solid outline, in the BEV, in the camera picture and in the key's samples."""
    grid = PRESETS["tiny"].bev
    points = np.zeros((0, 4), np.float32)
    blank = render_bev(points, grid)
    truth, found = render_bev(points, grid, gt_boxes=BOX), render_bev(points, grid, BOX)
    truth_colour, found_colour = _drawn_colour(truth, blank), _drawn_colour(found, blank)
    assert np.linalg.norm(_deuteranope(truth_colour) - _deuteranope(found_colour)) > 150
    pieces = [cv2.connectedComponents((pic == colour).all(axis=2).astype(np.uint8))[0] - 1
              for pic, colour in ((truth, truth_colour), (found, found_colour))]
    assert pieces[0] >= 8 and pieces[1] <= 2, pieces
    key = render_bev(points, grid, BOX, None, BOX, legend=True)[:60, :40]  # the rows' samples
    swatch = (key == truth_colour).all(axis=2).astype(np.uint8)
    assert cv2.connectedComponents(swatch)[0] - 1 >= 2  # a dashed sample: the line as the picture draws it


def test_camera_labelled_cars_are_dashed_in_their_own_colour(frame):
    """The camera picture draws the labelled cars as the BEV does: dashed, in a colour far from the detections'
    for a deuteranope too."""
    ahead = np.array([[15.0, 2.0, -0.9, 4.0, 1.7, 1.5, 0.3]])
    black = np.zeros_like(frame.image)
    blank = render_camera(black, frame.calib)
    truth, found = render_camera(black, frame.calib, gt_boxes=ahead), render_camera(black, frame.calib, ahead)
    truth_colour, found_colour = _drawn_colour(truth, blank), _drawn_colour(found, blank)
    assert np.linalg.norm(_deuteranope(truth_colour) - _deuteranope(found_colour)) > 150
    assert (cv2.connectedComponents((truth == truth_colour).all(axis=2).astype(np.uint8))[0] - 1
            > 3 * (cv2.connectedComponents((found == found_colour).all(axis=2).astype(np.uint8))[0] - 1))


def _points_in_cells(cells: list[tuple[int, int]], per_cell: int = 30) -> np.ndarray:
    """Points the tiny grid's BEV picture (0.1 m a pixel, x 0–70.4 m up, y 40 to −40 m across) puts in each
    (row, column)."""
    grid = PRESETS["tiny"].bev
    rows, cols = np.array(cells, float).T
    xyz = np.stack([grid.x_max - (rows + 0.5) * 0.1, grid.y_max - (cols + 0.5) * 0.1, np.full_like(rows, -1.0),
                    np.zeros_like(rows)], axis=1)
    return np.repeat(xyz, per_cell, axis=0).astype(np.float32)


def test_bev_draws_the_scans_returns_over_the_pseudo_points_in_another_colour_and_keys_both():
    """A sector the LiDAR lost but the camera's pseudo points fill no longer looks like a full scan: pseudo points
    alone are coloured, the scan's returns grey to white and drawn over them, and the key names both."""
    grid = PRESETS["tiny"].bev
    scan, both, camera_only = (300, 200), (300, 600), (500, 400)
    picture = render_bev(_points_in_cells([scan, both]), grid, pseudo=_points_in_cells([both, camera_only]))
    for cell in (scan, both):  # the scan's: grey, on top of the pseudo points
        assert picture[cell][0] == picture[cell][1] == picture[cell][2] > 200, cell
    pseudo = picture[camera_only].astype(int)
    assert pseudo.max() > 100 and pseudo.max() - pseudo.min() > 80  # a colour, not a grey
    keyed = render_bev(_points_in_cells([scan]), grid, pseudo=_points_in_cells([camera_only]), legend=True)
    plain = render_bev(_points_in_cells([scan]), grid, legend=True)
    key = keyed[:120, :300]
    assert (key == picture[camera_only]).all(axis=2).any() and not (plain[:120, :300] == picture[camera_only]).all(axis=2).any()
    assert (keyed[:120, :300] > 200).all(axis=2).sum() > (plain[:120, :300] > 200).all(axis=2).sum() + 100


def test_bev_key_names_the_frames_warning_codes():
    """A frame's sensor faults reach its picture: their codes are a row of the key, as bev_key_rows gives it."""
    grid = PRESETS["tiny"].bev
    points = np.zeros((0, 4), np.float32)
    faulty = render_bev(points, grid, BOX, np.array([0.9]), title="frame 000006", legend=True,
                        warnings=["blocked_sector", "thin_scan"])
    clean = render_bev(points, grid, BOX, np.array([0.9]), title="frame 000006", legend=True)
    rows = bev_key_rows("frame 000006", True, False, warnings=["blocked_sector", "thin_scan"])
    assert any("blocked_sector, thin_scan" in row[0] for row in rows)
    expected = np.zeros_like(faulty)
    left, top, right, bottom = draw_key(expected, rows)
    np.testing.assert_array_equal(faulty[top:bottom + 1, left:right + 1], expected[top:bottom + 1, left:right + 1])
    assert bottom > draw_key(np.zeros_like(clean), bev_key_rows("frame 000006", True, False))[3]


def test_bev_dims_detections_outside_the_camera_view_draws_the_view_and_counts_both(frame):
    """The BEV drew every box in full while the result file keeps those the camera sees: the camera's field of
    view is drawn, a box behind it dimmed (not the detections' colour), and the key says how many of each."""
    grid = PRESETS["tiny"].bev
    points = np.zeros((0, 4), np.float32)
    ahead, beside = [20.0, 0.0, -0.9, 4.0, 1.7, 1.5, 0.0], [3.0, 15.0, -0.9, 4.0, 1.7, 1.5, 0.0]
    boxes = np.array([ahead, beside])
    view = (frame.calib, frame.image_hw)
    picture = render_bev(points, grid, boxes, np.array([0.9, 0.8]), view=view)
    alone = render_bev(points, grid, boxes[:1], np.array([0.9]), view=view)
    dimmed = _changed_mask(picture, alone)  # what the box beside adds
    assert dimmed.sum() > 50 and not (picture[dimmed] == PREDICTION_BGR).all(axis=1).any()
    assert (alone == PREDICTION_BGR).all(axis=2).sum() > 50  # the box the camera sees: full colour
    # The view's edges: lines from the sensor out to about 40° either side of ahead, 30 m out.
    fov = _changed_mask(render_bev(points, grid, view=view), render_bev(points, grid))
    for side in (-1, 1):
        bearing = np.radians(40.0) * side
        row, col = round(704 - 300 * np.cos(bearing)), round(400 - 300 * np.sin(bearing))
        assert fov[row - 3:row + 4, col - 12:col + 13].any(), side
    keyed = render_bev(points, grid, boxes, np.array([0.9, 0.8]), view=view, legend=True)
    rows = bev_key_rows(None, True, False, view=True, split=(1, 1))
    assert rows[0][0].startswith("detection (score): 1 in view (written), 1 outside")
    expected = np.zeros_like(keyed)
    left, top, right, bottom = draw_key(expected, rows)
    np.testing.assert_array_equal(keyed[top:bottom + 1, left:right + 1], expected[top:bottom + 1, left:right + 1])


def test_scores_keep_off_the_sensor_and_off_each_other(frame):
    """KITTI 000003's BEV printed 0.70 over the sensor's triangle; a synthetic camera view hid 0.87 under 0.69.
    A score that would cover the sensor or an earlier score moves."""
    grid = PRESETS["tiny"].bev
    points = np.zeros((0, 4), np.float32)
    backing = np.array([[1.5, 2.0, -0.9, 4.0, 1.7, 1.5, np.pi]])  # beside the sensor, its front behind it
    text = _changed_mask(render_bev(points, grid, backing, np.array([0.7])), render_bev(points, grid, backing))
    assert text.sum() > 50 and not text[686:704, 392:409].any()  # the triangle's rows and columns
    white = np.full_like(frame.image, 255)
    close = np.array([[15.0, 2.0, -0.9, 4.0, 1.7, 1.5, 0.3], [15.5, 2.2, -0.9, 4.0, 1.7, 1.5, 0.3]])
    scored = render_camera(white, frame.calib, close, np.array([0.87, 0.69]))
    labels = _changed_mask(scored, render_camera(white, frame.calib, close))  # each a dark box with its text
    assert cv2.connectedComponents(labels.astype(np.uint8))[0] - 1 == 2  # two apart, neither on the other


def test_detect_pictures_split_the_scan_from_pseudo_points_name_faults_and_count_boxes_outside_view(tmp_path):
    """pipeline.detect on KITTI 000003 and on 000006 with azimuth 0–20° blanked (a blocked sensor window), the
    shipped model: the blanked wedge holds the camera's pseudo points alone, coloured, the scan's returns grey
    elsewhere; 000006's pictures name blocked_sector in their keys; 000003's BEV counts its boxes as the result
    file holds them (in view) and the one the camera does not see, drawn dimmed."""
    from pipeline.detect import main, picture_title
    from pipeline.kitti import read_velodyne
    from pipeline.render import key_rows

    data = tmp_path / "data"
    for sub in ("image_2", "calib", "label_2", "velodyne"):
        (data / sub).mkdir(parents=True)
        for fid in ("000003", "000006"):
            name = f"{fid}.{'png' if sub == 'image_2' else 'bin' if sub == 'velodyne' else 'txt'}"
            if sub != "velodyne" or fid == "000003":
                (data / sub / name).write_bytes((KITTI / sub / name).read_bytes())
    scan = read_velodyne(KITTI / "velodyne" / "000006.bin").points
    azimuth = np.degrees(np.arctan2(scan[:, 1], scan[:, 0]))
    scan[~((azimuth >= 0) & (azimuth <= 20))].astype("<f4").tofile(data / "velodyne" / "000006.bin")
    out = tmp_path / "out"
    assert main(["--models", str(REPO / "weights" / "edge"), "--data", str(data), "--emulate-beams", "16",
                 "--out", str(out)]) == 0
    bev6 = cv2.imread(str(out / "bev" / "000006.png")).astype(int)
    scene6 = bev6[-704:]  # below the key's strip
    blank = render_bev(np.zeros((0, 4), np.float32), get_preset("edge").bev)  # the rings and their labels
    grey = (scene6[..., 0] == scene6[..., 1]) & (scene6[..., 1] == scene6[..., 2]) & (scene6 != blank).any(axis=2)
    coloured = scene6.max(axis=2) - scene6.min(axis=2) > 15
    rows, cols = np.mgrid[:704, :800]
    x, y = (704 - rows) * 0.1, (400 - cols) * 0.1  # the edge preset's grid at the picture's 0.1 m
    bearing = np.degrees(np.arctan2(y, x))
    wedge = (bearing > 3) & (bearing < 17) & (np.hypot(x, y) > 6) & (np.hypot(x, y) < 30)
    mirror = (bearing < -3) & (bearing > -17) & (np.hypot(x, y) > 6) & (np.hypot(x, y) < 30)
    assert coloured[wedge].sum() > 1000 and grey[wedge].sum() < 20  # no grey scan returns in the blocked wedge
    assert grey[mirror].sum() > 200  # the scan's returns where the sensor saw
    faults = ["blocked_sector"]
    title = picture_title("000006", REPO / "weights" / "edge", 16)
    assert _key_of(cv2.imread(str(out / "camera" / "000006.png")), key_rows(title, True, True, faults), "top-right")
    in_view = len((out / "data" / "000006.txt").read_text().splitlines())
    assert _outside_in_key(bev6.astype(np.uint8), title, in_view, faults) is not None
    # 000003: one box in its result file, one the camera does not see (behind it, beside the sensor), dimmed.
    bev3 = cv2.imread(str(out / "bev" / "000003.png"))
    in_view = len((out / "data" / "000003.txt").read_text().splitlines())
    outside = _outside_in_key(bev3, picture_title("000003", REPO / "weights" / "edge", 16), in_view, [])
    assert in_view == 1 and outside == 1
    drawn = bev3.copy()
    left, top, right, bottom = draw_key(np.zeros_like(bev3), bev_key_rows(
        picture_title("000003", REPO / "weights" / "edge", 16), True, True, True, True, [], (1, 1)))
    drawn[top:bottom + 1, left:right + 1] = 0  # the key's samples aside: the boxes themselves
    assert (drawn == OUTSIDE_VIEW_BGR).all(axis=2).sum() > 20 and (drawn == PREDICTION_BGR).all(axis=2).sum() > 20


def _key_of(picture: np.ndarray, rows: list, corner: str = "top-left") -> bool:
    """Whether ``picture`` carries exactly the key :func:`draw_key` draws of ``rows``."""
    expected = np.zeros_like(picture)
    left, top, right, bottom = draw_key(expected, rows, corner)
    return bool((picture[top:bottom + 1, left:right + 1] == expected[top:bottom + 1, left:right + 1]).all())


def _outside_in_key(bev: np.ndarray, title: str, in_view: int, warnings: list[str]) -> int | None:
    """How many boxes outside the camera's view the key of a detect BEV picture (scan, pseudo points, the view)
    says, with ``in_view`` in view; None when no count up to 20 gives its key."""
    for outside in range(21):
        if _key_of(bev, bev_key_rows(title, True, True, True, True, warnings, (in_view, outside))):
            return outside
    return None


def test_service_pictures_are_titled_with_the_model_its_preset_and_the_thinning():
    """bev.png and camera.png had no title: their key now says which model drew them (its id's first 12 hex
    digits, as X-Model-ID begins, and its directory), its preset and the lines the scan was thinned to; the
    frame's warning codes but the thinning asked for join the key."""
    from pipeline.checks import CodedWarning
    from pipeline.detector import Detections
    from pipeline.model_files import load_manifest_with_digest, model_identity
    from service.routes.detect import _picture_warnings, picture_title

    directory = REPO / "weights" / "edge"
    identity = model_identity(directory, *load_manifest_with_digest(directory))
    title = picture_title(identity, 16)
    assert title.startswith(f"model {identity.id[:12]} ({identity.directory})")
    assert f"preset {identity.preset}" in title and "16 lines" in title and "lines" not in picture_title(identity, None)
    detections = Detections(np.zeros((0, 7)), np.zeros(0), warning_codes=["beams_emulated", "blocked_sector"])
    codes = _picture_warnings([CodedWarning("sensor_skew", "capture times apart")], ["nonfinite_dropped"], detections)
    assert codes == ["sensor_skew", "nonfinite_dropped", "blocked_sector"]


def test_demo_sparse_depth_picture_names_its_frame(tmp_path):
    """The demo's sparse-depth picture said which view it is but not which frame: its camera label now starts
    with the frame id, as its BEV pictures' titles do."""
    from pipeline.demo import run_core, sparse_depth_picture

    rgb, sparse = np.zeros((1, 3, 100, 500), np.float32), np.zeros((1, 1, 100, 500), np.float32)
    named, unnamed = sparse_depth_picture(rgb, sparse, frame_id="000006"), sparse_depth_picture(rgb, sparse)
    white = [(p[:24] == 255).all(axis=2) for p in (named, unnamed)]
    assert np.flatnonzero(white[0].any(axis=0)).max() > np.flatnonzero(white[1].any(axis=0)).max() + 50
    np.testing.assert_array_equal(named[30:], unnamed[30:])  # the label alone differs
    written = cv2.imread(run_core("000006", tmp_path)["pictures"][2])
    label = (written[:24] == 255).all(axis=2)
    assert np.flatnonzero(label.any(axis=0)).max() == np.flatnonzero(white[0].any(axis=0)).max()


def test_sim_report_bev_names_what_it_draws_cars_and_vans():
    """The simulation report's BEV draws labelled Cars and Vans: its title says both (detect's pictures draw
    Cars alone and say "labelled cars"), one outline each, none for other classes."""
    pytest.importorskip("matplotlib")
    import matplotlib.pyplot as plt

    sys.path.insert(0, str(REPO))
    from benchmarks.sim_report import figure_of, load

    frame = load(KITTI, 1)[0]
    car = dataclasses.replace(frame.objects[0], type="Car")  # 000000 holds a pedestrian: moved into a car
    objects = [car, dataclasses.replace(car, type="Van", location=(car.location[0] + 4, *car.location[1:])),
               dataclasses.replace(car, type="Pedestrian", location=(car.location[0] - 4, *car.location[1:]))]
    fig = figure_of([("KITTI", dataclasses.replace(frame, objects=objects))])
    try:
        bev = next(ax for ax in fig.axes if ax.get_xlabel() == "right of the sensor (m)")
        assert "labelled cars and vans" in bev.get_title()
        assert len(bev.get_lines()) == 2
        assert ("labelled cars", GROUND_TRUTH_BGR, "dashed") in bev_key_rows(None, False, True)
    finally:
        plt.close("all")
