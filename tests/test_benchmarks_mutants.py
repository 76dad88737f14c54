"""The benchmark tools' figures, keys, defaults and refusals that no earlier test pinned (session 46's mutation
audit of depth_bound, eval_speed, frame_ops, network_latency and sim_report).

Every assertion is on a computation (given inputs, or relations between a report's own figures), never on a
speed: where a figure is a time, a scripted clock stands in for ``time.perf_counter`` so that the median, the
percentiles and the units can be checked exactly.
"""

import dataclasses
import json
import re
import shutil
import warnings
from types import SimpleNamespace

import numpy as np
import pytest

from tests.conftest import KITTI
from tests.test_commands import _parser
from tests.test_depth_bound import REPO, _dataset


class ScriptedClock:
    """A perf_counter that moves only when told: ``advance(seconds)``, or on each read by the next step given."""

    def __init__(self, steps: list[float] | None = None) -> None:
        self.now = 0.0
        self._steps = iter(steps or [])

    def advance(self, seconds: float) -> None:
        self.now += seconds

    def perf_counter(self) -> float:
        self.now += next(self._steps, 0.0)
        return self.now


def _defaults(name: str, monkeypatch: pytest.MonkeyPatch) -> dict:
    """Each option's default in the parser the command's main builds."""
    return {action.dest: action.default for action in _parser(name, monkeypatch)._actions}


# ------------------------------------------------------------------------------------------------ depth_bound
def test_depth_bound_upsamples_block_corrections_bilinearly_with_half_pixel_centres():
    """A ramp of block corrections 0, 4, 8, 12 becomes a ramp across the pixels (as the network upsamples),
    not steps of whole blocks; the ends keep their block's value."""
    from benchmarks.depth_bound import bounded_depth

    filled = np.full((2, 8), 20.0, np.float32)
    truth = filled + np.repeat([0.0, 4.0, 8.0, 12.0], 2)[None].astype(np.float32)
    np.testing.assert_allclose(bounded_depth(filled, truth, 2, 0.9)[0], [20, 21, 23, 25, 27, 29, 31, 32], atol=1e-5)


def test_depth_bound_floors_the_corrected_depth_at_the_nets_minimum():
    from benchmarks.depth_bound import bounded_depth, closest_neighbour_depth

    filled = np.full((2, 2), 5.0, np.float32)
    truth = np.full((2, 2), 0.5, np.float32)  # nearer than the net's min_depth can say
    assert (bounded_depth(filled, truth, 1, 0.9) == np.float32(0.9)).all()
    assert (closest_neighbour_depth(filled, truth, 2, 0.9) == np.float32(0.9)).all()


def test_depth_bound_closest_averages_a_block_over_the_pixels_with_a_correction_only():
    """A block with one true depth among four pixels: its correction is that pixel's, not diluted by the three
    without truth; and a pixel picks among the image's blocks only, never a correction of 0 from outside it."""
    from benchmarks.depth_bound import closest_neighbour_depth

    filled = np.full((2, 4), 20.0, np.float32)
    truth = np.zeros_like(filled)
    truth[:, :2] = 20.0  # block 0: correction 0
    truth[0, 2] = 30.0  # block 1: one pixel, correction 10
    out = closest_neighbour_depth(filled, truth, 2, 0.9)
    assert out[0, 2] == 30.0 and (out[:, :2] == 20.0).all() and out[1, 3] == 20.0
    one_block = np.array([[30.0, 30.0], [30.0, 21.0]], np.float32)  # corrections 10, 10, 10, 1: mean 7.75
    assert (closest_neighbour_depth(np.full((2, 2), 20.0, np.float32), one_block, 2, 0.9) == 27.75).all()


@pytest.mark.parametrize("name", ["paper", "tiny"])
def test_depth_bound_full_image_maps_read_back_at_every_input_scale(name):
    """The existing check is on edge (scale 1/2); the paper view is the crop itself, the tiny one a quarter."""
    from benchmarks.depth_bound import to_full_image
    from pipeline.preprocess import depth_view
    from pipeline.presets import get_preset

    preset = get_preset(name)
    view = np.random.default_rng(0).uniform(1, 80, preset.depth.input_hw).astype(np.float32)
    assert np.array_equal(depth_view(to_full_image(view, (375, 1242), preset), preset), view)


def test_depth_bound_refuses_a_factor_that_divides_one_side_only_before_writing(tmp_path, capsys):
    """The edge view is 608 × 176: 11 divides 176 but not 608."""
    from benchmarks.depth_bound import main

    data, out = _dataset(tmp_path / "data"), tmp_path / "out"
    code = main(["--data", str(data), "--models", str(REPO / "weights" / "edge"), "--factor", "11", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and "--factor 11: does not divide the network's view 608×176; use 1 or one of 2, 4, 8, 16" in err
    assert not out.exists()


def test_depth_bound_refuses_a_depth_net_without_a_fill(tmp_path, capsys):
    from benchmarks.depth_bound import main

    models = tmp_path / "models"
    models.mkdir()
    manifest = json.loads((REPO / "weights" / "edge" / "manifest.json").read_text())
    manifest["preset_config"]["depth"]["prefill_passes"] = 0
    (models / "manifest.json").write_text(json.dumps(manifest))
    out = tmp_path / "out"
    code = main(["--data", str(_dataset(tmp_path / "data")), "--models", str(models), "--out", str(out)])
    assert code == 2 and "no fill to correct (prefill_passes 0)" in capsys.readouterr().err and not out.exists()


def test_depth_bound_maps_are_the_fill_of_the_16_line_scan_plus_the_bound(tmp_path, capsys):
    """The written maps equal the module's own bound of the depth net's fill of the 16-line scan: bilinear by
    default, the closest oracle when asked; --frames keeps the first frames and the summary counts them."""
    import torch

    from benchmarks.depth_bound import bounded_depth, check_inputs, closest_neighbour_depth, main
    from models.depth_net import SparsePrefill
    from pipeline.beams import emulate_beams
    from pipeline.frame import load_frame
    from pipeline.kitti import read_depth_png
    from pipeline.preprocess import depth_inputs, depth_view

    data, models = _dataset(tmp_path / "data"), REPO / "weights" / "edge"
    for sub in ("image_2", "velodyne", "calib", "depth_2"):  # a second frame, after 000006, that --frames 1 leaves
        source = next((data / sub).iterdir())
        shutil.copy(source, source.with_stem("000007"))
    preset = check_inputs(data, models, 2)
    frame = load_frame(data, "000006")
    sparse = depth_inputs(frame.image, emulate_beams(frame.points, 16), frame.calib, preset).sparse_depth
    with torch.no_grad():
        filled = SparsePrefill(preset.depth.prefill_passes, preset.depth.prefill_kernel)(
            torch.from_numpy(sparse))[0, 0].numpy()
    truth = depth_view(read_depth_png(data / "depth_2" / "000006.png"), preset)
    for upsample, bound in (([], bounded_depth), (["--upsample", "closest"], closest_neighbour_depth)):
        out = tmp_path / f"out{len(upsample)}"
        code = main(["--data", str(data), "--models", str(models), "--factor", "2", *upsample, "--frames", "1",
                     "--cache", "--no-progress", "--out", str(out)])
        assert code == 0 and capsys.readouterr().out == f"wrote 1 maps to {out}\n"
        assert [p.name for p in out.iterdir()] == ["000006.png"]
        np.testing.assert_allclose(read_depth_png(out / "000006.png"), bound(filled, truth, 2, preset.depth.min_depth),
                                   atol=0.5 / 256 + 1e-6)
    full = tmp_path / "full"
    assert main(["--data", str(data), "--models", str(models), "--no-progress", "--out", str(full)]) == 0
    assert capsys.readouterr().out == f"wrote 2 maps to {full / 'depth_2'}\n"


def test_depth_bound_a_folder_it_cannot_make_is_one_line(tmp_path, capsys):
    """--out passes its check, but a file holds the depth_2/ name the maps go to: one line, no traceback."""
    from benchmarks.depth_bound import main

    out = tmp_path / "out"
    out.mkdir()
    (out / "depth_2").write_text("x")
    code = main(["--data", str(_dataset(tmp_path / "data")), "--models", str(REPO / "weights" / "edge"),
                 "--no-progress", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith(f"error: --out {out}: {out / 'depth_2'}") and err.count("\n") == 1, err


def test_depth_bound_defaults(monkeypatch):
    assert {k: v for k, v in _defaults("depth_bound", monkeypatch).items() if k in ("factor", "upsample", "cache")} == \
        {"factor": 1, "upsample": "bilinear", "cache": False}


# ------------------------------------------------------------------------------------------------- eval_speed
def test_eval_speed_writes_the_frames_it_reports_seeded(tmp_path):
    from benchmarks.eval_speed import write_random_label_sets

    gt_dir, det_dir = write_random_label_sets(tmp_path / "a", 3, seed=5)
    assert sorted(p.name for p in gt_dir.iterdir()) == sorted(p.name for p in det_dir.iterdir()) == \
        ["000000.txt", "000001.txt", "000002.txt"]
    same, _ = write_random_label_sets(tmp_path / "b", 3, seed=5)
    other, _ = write_random_label_sets(tmp_path / "c", 3, seed=6)
    texts = {d: [p.read_text() for p in sorted(d.iterdir())] for d in (gt_dir, det_dir, same, other)}
    assert texts[same] == texts[gt_dir] != texts[other]
    assert texts[det_dir] != texts[gt_dir]  # the detections are not the ground truth


def test_eval_speed_reports_median_min_and_max_in_seconds_of_each_run(tmp_path, monkeypatch, capsys):
    """Three runs of 1, 2 and 6 s (a scripted clock): the median is 2 s, not the mean of 3; --keep keeps the
    label sets the runs read."""
    from benchmarks import eval_speed

    clock = ScriptedClock([0, 1, 8, 2, 4, 6])  # start, end of each run
    monkeypatch.setattr(eval_speed, "time", SimpleNamespace(perf_counter=clock.perf_counter))
    keep = tmp_path / "keep"
    assert eval_speed.main(["--frames", "2", "--keep", str(keep)]) == 0
    last = capsys.readouterr().out.splitlines()[-1]
    assert last.startswith("2 frames, 3 runs (read files + evaluate ")
    assert "median 2.00 s, min 1.00 s, max 6.00 s on " in last
    assert sorted(p.name for p in (keep / "label_2").iterdir()) == ["000000.txt", "000001.txt"]


def test_eval_speed_defaults(monkeypatch):
    defaults = _defaults("eval_speed", monkeypatch)
    assert (defaults["frames"], defaults["repeats"], defaults["seed"]) == (3769, 3, 0)  # 3,769: the val split


# -------------------------------------------------------------------------------------------------- frame_ops
def test_frame_ops_times_in_ms_after_a_warm_up_median_p90_and_min(monkeypatch):
    """A slow first call is the untimed warm-up; nine calls of 1 ms and one of 11 ms give a median of 1 ms (a mean
    would say 2), a p90 of 2 ms (NumPy's linear percentile) and a min of 1 ms."""
    from benchmarks import frame_ops

    clock = ScriptedClock()
    durations = iter([0.1] + [0.001] * 9 + [0.011])
    monkeypatch.setattr(frame_ops, "time", SimpleNamespace(perf_counter=clock.perf_counter))
    result = frame_ops.timed(lambda: clock.advance(next(durations)), 10)
    assert next(durations, None) is None  # one warm-up call and ten timed ones
    assert result == pytest.approx({"p50": 1.0, "p90": 2.0, "min": 1.0})


def test_frame_ops_json_relates_its_figures_and_names_the_frame(tmp_path, capsys):
    """--data and --frame are the ones read; the speed-up is the reference's p50 over ours; the table prints p50
    then p90 of each step."""
    from benchmarks.frame_ops import main
    from pipeline.kitti import read_velodyne
    from pipeline.presets import get_preset

    data = tmp_path / "kitti"
    for sub, ext in (("image_2", ".png"), ("velodyne", ".bin"), ("calib", ".txt"), ("label_2", ".txt")):
        (data / sub).mkdir(parents=True)
        shutil.copy(KITTI / sub / f"000006{ext}", data / sub / f"000042{ext}")
    out = tmp_path / "frame_ops.json"
    assert main(["--data", str(data), "--frame", "000042", "--preset", "tiny", "--repeats", "2",
                 "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert (report["frame"], report["preset"], report["repeats"]) == ("000042", "tiny", 2)
    assert report["points_64"] == len(read_velodyne(data / "velodyne" / "000042.bin").points)
    assert report["pseudo_points"] == np.prod(get_preset("tiny").depth.input_hw)  # one point per view pixel
    steps = report["steps_ms"]
    speedup = steps["baseline: reference voxelize (64-line scan)"]["p50"] / steps["voxelize (64-line scan)"]["p50"]
    assert np.isfinite(speedup) and report["voxelize_speedup_vs_reference"] == pytest.approx(speedup)
    assert all(t["min"] <= t["p50"] <= t["p90"] for t in steps.values())
    printed = capsys.readouterr().out.splitlines()
    width = max(map(len, steps))
    assert all(f"{name:{width}s} {t['p50']:8.2f} {t['p90']:8.2f}" in printed for name, t in steps.items())


def test_frame_ops_defaults(monkeypatch):
    defaults = _defaults("frame_ops", monkeypatch)
    assert (defaults["frame"], defaults["preset"], defaults["repeats"], defaults["data"]) == \
        ("000006", "paper", 30, KITTI)


# -------------------------------------------------------------------------------------------- network_latency
def _row(**changes):
    from benchmarks.network_latency import LatencyRow

    row = LatencyRow(preset="paper", network="pixor", parameters=2_130_000, gflops=90.3, torch_p50_ms=880.0,
                     torch_max_ms=900.0, ort_p50_ms=248.0, ort_max_ms=260.0, repeats=10, threads=2)
    return dataclasses.replace(row, **changes)


def test_network_latency_table_reads_pytorch_then_onnx_runtime_and_the_speed_up_as_their_ratio():
    from benchmarks.network_latency import format_table

    assert _row().speedup == pytest.approx(880 / 248)  # > 1: ONNX Runtime faster
    assert format_table([_row()]).splitlines()[-1] == \
        "| paper | pixor | 2.13 M | 90.30 | 880.0 (900.0) | 248.0 (260.0) | 3.55× |"


def test_network_latency_times_each_runtime_in_ms(monkeypatch):
    from tqdm import tqdm

    from benchmarks import network_latency

    clock = ScriptedClock()
    monkeypatch.setattr(network_latency, "time", SimpleNamespace(perf_counter=clock.perf_counter))
    with tqdm(disable=True) as bar:
        first, second = network_latency._time_alternating(lambda: clock.advance(0.002), lambda: clock.advance(0.005),
                                                          3, 2, bar)
    assert first == pytest.approx([2.0] * 3) and second == pytest.approx([5.0] * 3)


def test_network_latency_defaults(monkeypatch):
    defaults = _defaults("network_latency", monkeypatch)
    assert (defaults["repeats"], defaults["block"], defaults["threads"], defaults["preset"]) == (5, 5, None, None)


# ------------------------------------------------------------------------------------------------- sim_report
def _exact_calibration():
    """Velodyne (x ahead, y left, z up) → camera (x right, y down, z ahead) by a permutation alone: a label's
    distance is then exactly its camera x and z."""
    from pipeline.calib import Calibration

    p2 = np.array([[721.5, 0, 609.6, 0], [0, 721.5, 172.9, 0], [0, 0, 1, 0]], np.float64)
    return Calibration(P2=p2, R0_rect=np.eye(3), Tr_velo_to_cam=np.array(
        [[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]], np.float64))


def _car(x: float, z: float, kind: str = "Car", dims: tuple[float, float, float] = (1.5, 1.6, 3.9)):
    from pipeline.kitti import Object3D

    return Object3D(kind, 0.0, 0, 0.0, (0.0, 0.0, 1.0, 1.0), dims, (x, 1.6, z), 0.0)


def test_sim_report_bins_cars_by_their_distance_in_the_ground_plane():
    """A car 25 m ahead and 20 m aside is 32 m away; one at 10 m opens the 10–20 bin; from 70 m on and vans are
    left out."""
    from benchmarks.sim_report import car_points_by_distance, load

    real = load(KITTI, 1)[0]
    frame = dataclasses.replace(real, calib=_exact_calibration(), objects=[
        _car(-20.0, 25.0), _car(0.0, 10.0), _car(0.0, 70.0), _car(0.0, 75.0), _car(0.0, 15.0, "Van")])
    bins = car_points_by_distance([frame])
    assert {lo: len(n64) for lo, (n64, _) in bins.items()} == {0: 0, 10: 1, 20: 0, 30: 1, 40: 0, 50: 0, 60: 0}


def test_sim_report_counts_each_cars_points_with_64_and_16_lines():
    from benchmarks.sim_report import car_points_by_distance, load
    from pipeline.beams import emulate_beams
    from pipeline.boxes import labels_to_boxes, points_in_boxes

    frame = next(f for f in load(KITTI) if f.name == "000006")
    cars = [o for o in frame.objects if o.type == "Car"]
    counts = [points_in_boxes(points, labels_to_boxes(cars, frame.calib)).sum(axis=0)
              for points in (frame.points, emulate_beams(frame.points, 16))]
    bins = car_points_by_distance([frame])
    assert sorted(n for n64, _ in bins.values() for n in n64) == sorted(counts[0].tolist())
    assert sorted(n for _, n16 in bins.values() for n in n16) == sorted(counts[1].tolist())
    assert (counts[1] <= counts[0]).all() and counts[1].sum() < counts[0].sum()


def test_sim_report_tables_give_medians_and_car_sizes_on_given_frames():
    from benchmarks.sim_report import _fmt, load, tables

    assert (_fmt([1, 2, 9]), _fmt([])) == ("2 (3)", "–")
    real = load(KITTI, 1)[0]
    sizes = [(1.5, 1.6, 3.8), (1.6, 1.7, 4.0), (2.0, 1.8, 4.5)]  # h, w, l
    # Cars beyond the bins (200 m): the sizes count them, the distance table does not; a van is no car.
    sim = [dataclasses.replace(real, objects=[_car(0.0, 200.0, dims=d) for d in sizes] +
                               [_car(0.0, 200.0, "Van", (2.4, 2.0, 5.5))])]
    sim += [dataclasses.replace(real, points=real.points[:n], objects=[]) for n in (10_000, 20_000)]
    text = tables(sim, [real])
    assert f"| simulated | 3 | 20,000 | 10,000 | {len(real.points):,} |" in text and len(real.points) > 20_000
    assert "| simulated | 3 | 1.70 ± 0.22 | 1.70 ± 0.08 | 4.10 ± 0.29 |" in text  # mean ± population std


def test_sim_report_sizes_of_no_car_are_dashes_without_warnings():
    """A folder whose frames label no car (000000: a pedestrian) printed "nan ± nan" after five NumPy warnings."""
    from benchmarks.sim_report import load, tables

    no_car = load(KITTI, 1)
    assert not any(o.type == "Car" for o in no_car[0].objects)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        text = tables(no_car, no_car)
    assert "| simulated | 0 | – | – | – |" in text and "| KITTI samples | 0 | – | – | – |" in text


def test_sim_report_columns_keep_64_lines_before_16():
    """Every car has at least as many points with 64 lines as with 16, so a row's 64-line median is never below
    its 16-line one, for the simulated columns as for KITTI's."""
    from benchmarks.sim_report import load, tables

    frames = load(KITTI)
    rows = [line.strip("|").split("|")[1:] for line in tables(frames[:3], frames[2:]).splitlines()
            if re.match(r"\| \d+–\d+ \|", line)]
    assert len(rows) == 7
    pairs = [(int(cells[i].split()[0]), int(cells[i + 1].split()[0])) for cells in rows for i in (0, 2)
             if cells[i].strip() != "–"]
    assert all(n64 >= n16 for n64, n16 in pairs) and sum(n64 > n16 for n64, n16 in pairs) >= 4


def test_sim_report_uses_frames_of_the_given_folder_and_draws_the_picture(tmp_path, monkeypatch):
    """--frames limits a given --sim-data folder too; the picture is written, simulated row first (its first
    frame), then the KITTI frame with the most cars."""
    pytest.importorskip("matplotlib")
    import cv2

    from benchmarks import sim_report

    drawn: list[list[str]] = []
    real_figure = sim_report.figure

    def recording(rows, path):
        drawn.append([title for title, _ in rows])
        real_figure(rows, path)

    monkeypatch.setattr(sim_report, "figure", recording)
    picture = tmp_path / "sim.png"
    text = sim_report.run(sim_report.ReportConfig(kitti=KITTI, sim=KITTI, frames=2, figure=picture))
    assert "| simulated | 2 |" in text and "| KITTI | 5 |" in text
    most = max(sim_report.load(KITTI), key=lambda f: sum(o.type == "Car" for o in f.objects)).name
    assert drawn == [["simulated 000000", f"KITTI {most}"]]
    image = cv2.imread(str(picture))
    assert image is not None and image.shape[0] > 100 and image.shape[1] > 100


def test_sim_report_generates_with_the_seed_given(monkeypatch):
    from benchmarks.sim_report import ReportConfig, run

    texts = [run(ReportConfig(kitti=KITTI, frames=1, seed=seed, progress=False)) for seed in (3, 4)]
    assert texts[0] != texts[1]
    defaults = _defaults("sim_report", monkeypatch)
    assert (defaults["frames"], defaults["seed"], defaults["sim"], defaults["figure"]) == (20, 1, None, None)
