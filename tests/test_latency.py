"""benchmarks/latency.py end to end on the tiny preset: the report's keys and the plot (no timing targets)."""

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import cv2
import pytest

from pipeline.cpu import int8_pairs_saturate, speed_flags
from pipeline.provenance import code_version
from tests.conftest import lidar_only_models

LATENCY = Path(__file__).resolve().parents[1] / "benchmarks" / "latency.py"
QUICK_PEAK = ["--peak-size", "512"]  # the 4096² MatMul of the real peak takes 12 s a run; the keys are the same


def refused(capsys, *args: str) -> tuple[int, str]:
    """The command's exit status and stderr for a command line it refuses before any timing, run in this
    process: its real main (argparse, the checks, the decorator's handling), without a fresh interpreter's
    imports (one to three seconds each, fifteen times in this file). An exception main lets through fails the
    test here as a traceback would; every run that times frames still goes through a real subprocess."""
    from benchmarks.latency import main

    capsys.readouterr()
    try:
        code = main([*QUICK_PEAK, *args])
    except SystemExit as stop:  # argparse's refusals
        code = stop.code
    return code, capsys.readouterr().err


def test_latency_report_with_two_workers_and_torch(tmp_path):
    result = subprocess.run(
        [sys.executable, str(LATENCY), *QUICK_PEAK, "--preset", "tiny", "--frames", "4", "--warmup", "1", "--threads", "2",
         "--compare-torch", "--json", str(tmp_path / "lat.json"), "--plot", str(tmp_path / "lat.png")],
        capture_output=True, text=True, timeout=600, check=False,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads((tmp_path / "lat.json").read_text())
    assert set(report["end_to_end_ms"]) >= {"mean", "p50", "p90", "p99"}
    # Each summary says what it rests on: the count and the slowest frame; the JSON says what each figure is.
    end_to_end = report["end_to_end_ms"]
    assert end_to_end["n"] == 4 and end_to_end["p50"] <= end_to_end["p99"] <= end_to_end["max"]
    assert {"end_to_end_ms", "fps", "fps_wall", "networks.gflops", "networks.ms", "peak_gflops", "throughput.scaling",
            "throughput.vs_single_stream", "speedup_vs_torch"} <= set(report["definitions"])
    assert "not reading or decoding the files" in report["definitions"]["end_to_end_ms"]
    assert "1000 / mean" in result.stdout and "max" in result.stdout and "no file reading" in result.stdout
    assert "p99 is an interpolation between the two slowest" in result.stdout  # 4 frames: no tail to speak of
    assert {"governor", "load_average_start", "load_average_end"} <= set(report["machine"])
    assert report["fps"] > 0 and report["input"] == "16-line scan + camera" and report["beams"] == 16
    assert set(report["stages_ms"]) == {"prepare", "depth_net", "ray_table", "pseudo_points", "voxelize", "pixor", "decode"}
    assert all(set(s) >= {"mean", "p50", "p99"} for s in report["stages_ms"].values())
    assert 0 < report["non_network_fraction_fixed_calibration"] <= report["non_network_fraction"] < 1
    # The wall time outside the network runs; with a stage thread (two cores here) the rays and the scan's
    # half of the BEV were made beside the depth net.
    networks_ms = report["stages_ms"]["depth_net"]["mean"] + report["stages_ms"]["pixor"]["mean"]
    e2e = report["end_to_end_ms"]["mean"]
    assert abs(report["non_network_fraction"] - (e2e - networks_ms) / e2e) < 1e-9
    if report["machine"]["cores"] >= 2:
        assert report["stage_threads"] == 2
        assert set(report["overlapped_ms"]) == {"ray_table", "voxelize", "rig_checks"}
    t = report["throughput"]
    assert t["workers"] == 2 and t["mode"] == "thread" and t["fps"] > 0 and t["fps_one_worker"] > 0
    assert abs(t["scaling"] - t["fps"] / t["fps_one_worker"]) < 1e-9
    assert t["rounds"] == len(t["scaling_per_round"]) == 3 and all(r > 0 for r in t["scaling_per_round"])
    # Frames over wall time on both sides: the single stream's fps_wall, not 1000 / the mean of detect's times.
    assert abs(t["vs_single_stream"] - t["fps"] / report["fps_wall"]) < 1e-9
    # Every run's workers with the share of their one core they got; the lone worker takes each core in turn.
    assert [run["workers"] for run in t["runs"]] == [1, 2, 2, 1, 1, 2]
    # Each worker runs frames // workers frames (at least 2) of its own: 4 // 2 here.
    assert all(u["frames"] == 2 for run in t["runs"] for u in run["per_worker"])
    lone = [run["per_worker"][0]["cores"] for run in t["runs"] if run["workers"] == 1]
    assert len(lone) == 3 and all(len(c) == 1 for c in lone) and len({c[0] for c in lone}) == min(2, report["machine"]["cores"])
    for run in t["runs"]:
        assert [u["worker"] for u in run["per_worker"]] == list(range(run["workers"]))
        assert all(0 < u["cpu_share"] <= 1.05 and 0 < u["cpu_s"] <= 1.05 * u["wall_s"] for u in run["per_worker"])
    assert all(0 <= i < len(t["runs"]) for i in t["shared_runs"])
    for name in ("depth", "pixor"):
        n = report["networks"][name]
        assert n["gflops"] > 0 and n["ms"] > 0 and 0 < n["peak_fraction"] <= n["matmul_peak_fraction"]
    # The fixed calibration's share takes off the ray tables' builds on the frame's path, no more: with a stage
    # thread, at most what the tables took beside the depth net (the rest of the wait was the voxelization).
    rays = report["ray_tables_on_path_ms"]
    assert 0 <= rays <= report["stages_ms"]["ray_table"]["mean"] + 1e-9
    if report["stage_threads"] == 2:
        assert rays <= report["overlapped_ms"]["ray_table"]["mean"] + 1e-9
    between = report["non_network_fraction"] * e2e
    assert abs(report["non_network_fraction_fixed_calibration"] - (between - rays) / (e2e - rays)) < 1e-9
    assert report["peak_gflops"] > 1 and report["peak_detail"]["matmul_size"] == 512
    assert report["peak_gflops"] == max(report["peak_detail"]["matmul_512_gflops"], report["peak_detail"]["conv3x3_256_gflops"])
    readings = report["peak_detail"]["readings"]  # before and after the stream; the best of each kind counts
    assert len(readings) == 2 and report["peak_detail"]["matmul_512_gflops"] == max(r["matmul_gflops"] for r in readings)
    assert report["torch_end_to_end_ms"]["mean"] > 0 and report["speedup_vs_torch"] > 0
    # The median block's ratio is the headline; the means' ratio, which one disturbed block moves, is kept apart.
    assert report["speedup_vs_torch"] == report["speedup_vs_torch_blocks"]["p50"]
    assert report["speedup_vs_torch_of_means"] == (report["torch_end_to_end_ms"]["mean"]
                                                   / report["paired_end_to_end_ms"]["mean"])
    assert report["score_threshold"] == 0.5 and report["distinct_frames"] == 4 and report["fps_wall"] > 0
    assert report["torch_end_to_end_ms"]["n"] == report["paired_end_to_end_ms"]["n"] == report["frames"]
    assert set(report["paired_stages_ms"]) == set(report["torch_stages_ms"]) == set(report["stages_ms"])
    b = report["speedup_vs_torch_blocks"]
    assert b["blocks"] >= 1 and b["min"] <= b["p50"] <= b["max"]
    # 4 frames make one block of 4: its ratio is PyTorch's time over ONNX Runtime's, the means' ratio.
    assert b["blocks"] == 1 and abs(report["speedup_vs_torch"] / report["speedup_vs_torch_of_means"] - 1) < 1e-9
    nets = report["speedup_vs_torch_networks"]
    assert set(nets) == {"depth_net", "pixor"}
    for stage, ratio in nets.items():
        assert ratio == report["torch_stages_ms"][stage]["p50"] / report["paired_stages_ms"][stage]["p50"]
    assert report["torch_weights"] == "initialised, the same as the ONNX files'"
    import onnxruntime as ort

    assert report["machine"]["cores"] >= 1 and report["versions"]["onnxruntime"] == ort.__version__
    assert report["code"] == code_version()  # which code was timed (its git commit in a checkout)
    assert report["versions"]["onnxruntime_package"] == "onnxruntime"
    assert report["machine"]["int8_pair_sums_saturate"] == int8_pairs_saturate()
    assert report["machine"]["cpu_flags"] == speed_flags()
    picture = cv2.imread(str(tmp_path / "lat.png"))
    assert picture is not None and picture.shape[0] > 100


def test_latency_int8_and_precision_check(tmp_path, tiny_models, capsys):
    ok = subprocess.run(
        [sys.executable, str(LATENCY), *QUICK_PEAK, "--preset", "tiny", "--precision", "int8", "--frames", "2", "--warmup", "1",
         "--ops", "--stage-threads", "1", "--json", str(tmp_path / "q.json")],
        capture_output=True, text=True, timeout=600, check=False,
    )
    assert ok.returncode == 0, ok.stderr[-2000:]
    report = json.loads((tmp_path / "q.json").read_text())
    # Converted as the shipped weights/edge-int8 (export.precision --reduce-range): 7-bit weights, exact on CPUs
    # without VNNI, where the full 8-bit ones saturate (and the Detector says so).
    assert report["precision"] == "int8" and report["quantization"]["reduce_range"] is True
    assert "7-bit" in report["quantization"]["weights"] and "saturat" not in ok.stderr
    assert report["stage_threads"] == 1 and report["overlapped_ms"] == {}
    for name in ("depth", "pixor"):  # --ops: the quantized graph's own kernels, timed one by one
        ops = report["networks"][name]["ops"]
        assert "QLinearConv" in ops["by_op"] and ops["profiled_runs"] == 20
        assert 0 < ops["compute_ms"] < ops["kernels_ms"]
        assert abs(sum(entry["share"] for entry in ops["by_op"].values()) - 1) < 1e-9
        assert ops["compute_gflops_per_s"] == report["networks"][name]["gflops"] / (ops["compute_ms"] / 1e3)
        assert ops["run_ms"] > 0 and f"{name:6s} operators (median of 20 profiled runs of" in ok.stdout
    code, err = refused(capsys, "--models", str(tiny_models), "--precision", "int8", "--frames", "1")
    assert code == 2 and "error: --precision int8, but" in err
    code, err = refused(capsys, "--models", str(tiny_models), "--frames", "0")
    assert code == 2 and "argument --frames: must be at least 1, got 0" in err


def test_latency_baseline_runs_interleaved_and_bad_dir_is_refused(tmp_path, tiny_models, capsys):
    result = subprocess.run(
        [sys.executable, str(LATENCY), *QUICK_PEAK, "--models", str(tiny_models), "--baseline", str(tiny_models), "--frames", "8",
         "--warmup", "1", "--json", str(tmp_path / "b.json")],
        capture_output=True, text=True, timeout=600, check=False,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads((tmp_path / "b.json").read_text())
    # Which model was timed, as the service's X-Model-ID names it: the sha256 of its manifest.json.
    assert report["model_id"] == hashlib.sha256((tiny_models / "manifest.json").read_bytes()).hexdigest()
    # Each network's FLOPs: the manifest's (counted before the graph's lowering) and those of the graph that ran.
    from export.flops import count_flops

    manifest = json.loads((tiny_models / "manifest.json").read_text())
    for name, entry in manifest["networks"].items():
        n = report["networks"][name]
        assert n["gflops"] == entry["flops"] / 1e9
        assert n["graph_gflops"] == count_flops(tiny_models / entry["file"]).total / 1e9
    base = report["baseline"]
    assert base["precision"] == "fp32" and base["end_to_end_ms"]["n"] == base["paired_end_to_end_ms"]["n"] == 8
    assert set(base["stages_ms"]) == set(report["stages_ms"])
    b = report["speedup_vs_baseline_blocks"]
    assert b["blocks"] == 2 and b["min"] <= b["p50"] <= b["max"] and report["speedup_vs_baseline"] > 0
    # The baseline's time over the other's, both from the alternating blocks (not the single stream's).
    assert abs(report["speedup_vs_baseline_of_means"]
               - base["end_to_end_ms"]["mean"] / base["paired_end_to_end_ms"]["mean"]) < 1e-9
    assert "in alternating blocks" in result.stdout
    code, err = refused(capsys, "--models", str(tiny_models), "--baseline", str(tmp_path / "nowhere"), "--frames", "1",
                        "--warmup", "1")
    assert code == 2 and "nowhere" in err and "Traceback" not in err
    # A LiDAR-only baseline runs another pipeline on the frames: no speed-up of one over the other to report.
    lidar_only = lidar_only_models(tiny_models, tmp_path / "lidar")
    code, err = refused(capsys, "--models", str(tiny_models), "--baseline", str(lidar_only), "--frames", "1",
                        "--warmup", "1")
    assert code == 2 and "Traceback" not in err, err
    assert f"--baseline {lidar_only}: reads a " in err and "alone (LiDAR-only)" in err


def test_latency_throughput_with_worker_processes(tmp_path, tiny_models):
    result = subprocess.run(
        [sys.executable, str(LATENCY), *QUICK_PEAK, "--models", str(tiny_models), "--threads", "2", "--worker-kind", "process",
         "--frames", "4", "--warmup", "1", "--json", str(tmp_path / "p.json")],
        capture_output=True, text=True, timeout=600, check=False,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    t = json.loads((tmp_path / "p.json").read_text())["throughput"]
    assert t["mode"] == "process" and t["workers"] == 2 and t["fps"] > 0 and t["fps_one_worker"] > 0
    assert abs(t["scaling"] - t["fps"] / t["fps_one_worker"]) < 1e-9
    assert "2 process workers" in result.stdout


def test_latency_with_mirror_tta_times_pixors_second_run(tmp_path, tiny_models):
    """--mirror-tta: PIXOR's second run is a stage of its own, counted as network time, its FLOPs twice; the
    PyTorch pipeline and the throughput workers run it too."""
    result = subprocess.run(
        [sys.executable, str(LATENCY), *QUICK_PEAK, "--models", str(tiny_models), "--mirror-tta", "--frames", "4",
         "--warmup", "1", "--threads", "2", "--compare-torch", "--json", str(tmp_path / "m.json")],
        capture_output=True, text=True, timeout=600, check=False,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads((tmp_path / "m.json").read_text())
    manifest = json.loads((tiny_models / "manifest.json").read_text())
    assert report["mirror_tta"] is True and "PIXOR with mirror TTA" in result.stdout
    assert {"pixor_mirror", "mirror_merge"} <= set(report["stages_ms"]) & set(report["torch_stages_ms"])
    networks_ms = sum(report["stages_ms"][s]["mean"] for s in ("depth_net", "pixor", "pixor_mirror"))
    e2e = report["end_to_end_ms"]["mean"]
    assert abs(report["non_network_fraction"] - (e2e - networks_ms) / e2e) < 1e-9
    pixor = report["networks"]["pixor"]
    assert pixor["runs"] == 2 and abs(pixor["gflops"] - 2 * manifest["networks"]["pixor"]["flops"] / 1e9) < 1e-9
    assert pixor["ms"] == report["stages_ms"]["pixor"]["p50"] + report["stages_ms"]["pixor_mirror"]["p50"]
    assert report["networks"]["depth"]["runs"] == 1
    assert set(report["speedup_vs_torch_networks"]) == {"depth_net", "pixor", "pixor_mirror"}
    assert report["throughput"]["fps"] > 0


def test_a_worker_that_fails_is_reported_instead_of_waited_for(tmp_path, tiny_models):
    import os

    import pytest

    from benchmarks.latency import FrameSource, run_workers
    from pipeline.model_files import ModelFileError

    cores = sorted(os.sched_getaffinity(0))
    source = FrameSource(tmp_path / "nowhere", count=2, beams=16)  # a worker process's frames cannot load
    with pytest.raises(RuntimeError, match="worker [01]: .*nowhere"):
        run_workers(tiny_models, None, source, workers=2, per_worker=2, warmup=1, cores=cores, mode="process")
    # A thread's error is raised as it was: here the model directory is missing.
    with pytest.raises(ModelFileError, match="no-models"):
        run_workers(tmp_path / "no-models", None, [], workers=2, per_worker=2, warmup=1, cores=cores,
                    mode="thread")


def test_torch_twin_of_a_model_directory_is_built_for_its_own_preset(tmp_path, tiny_models, capsys):
    """--compare-torch with --models times PyTorch networks of the directory's preset (tiny here), not the
    default one's; a --preset that contradicts the directory is refused at once, in one line."""
    result = subprocess.run(
        [sys.executable, str(LATENCY), *QUICK_PEAK, "--models", str(tiny_models), "--compare-torch", "--frames", "2",
         "--warmup", "1", "--json", str(tmp_path / "t.json")],
        capture_output=True, text=True, timeout=600, check=False,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads((tmp_path / "t.json").read_text())
    assert report["preset"] == "tiny" and report["torch_end_to_end_ms"]["n"] == 2 and report["speedup_vs_torch"] > 0
    assert report["torch_weights"].startswith("the ONNX files' own")  # read back, checked against ONNX Runtime
    # An INT8 directory's twin reads the FP32 weights it was converted from.
    from export.precision import convert_precision
    from tests.conftest import KITTI

    convert_precision(tiny_models, tmp_path / "int8", "int8", KITTI, calibration_frames=2)
    result = subprocess.run(
        [sys.executable, str(LATENCY), *QUICK_PEAK, "--models", str(tmp_path / "int8"), "--compare-torch", "--frames", "2",
         "--warmup", "1", "--json", str(tmp_path / "q.json")],
        capture_output=True, text=True, timeout=600, check=False,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    weights = json.loads((tmp_path / "q.json").read_text())["torch_weights"]
    assert f"of the FP32 directory it was converted from, {tiny_models}" in weights
    code, err = refused(capsys, "--models", str(tiny_models), "--preset", "paper", "--compare-torch", "--frames", "1",
                        "--warmup", "1")
    assert code == 2 and "Traceback" not in err
    assert "--preset paper" in err and "holds tiny models" in err


def test_a_preset_file_is_exported_and_timed(tmp_path):
    """--preset FILE.json exports the file's preset and times it: the directory then holds the name inside
    the file, which is what --preset is compared with (the path itself once refused every preset file)."""
    preset_file = tmp_path / "narrow.json"
    preset_file.write_text(json.dumps({"base": "tiny", "name": "tiny-narrow", "decode": {"score_threshold": 0.4}}))
    result = subprocess.run(
        [sys.executable, str(LATENCY), *QUICK_PEAK, "--preset", str(preset_file), "--frames", "1", "--warmup", "0",
         "--json", str(tmp_path / "t.json")],
        capture_output=True, text=True, timeout=600, check=False,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads((tmp_path / "t.json").read_text())
    assert report["preset"] == "tiny-narrow"
    # The preset itself and its file are recorded: the name alone finds no registered preset.
    from pipeline.presets import get_preset

    assert report["preset_config"] == json.loads(json.dumps(get_preset(str(preset_file)).to_dict()))
    assert report["preset_config"]["decode"]["score_threshold"] == 0.4 and report["preset_file"] == str(preset_file)


def test_what_latency_could_not_use_or_write_is_refused_before_timing(tmp_path, tiny_models, capsys):
    """A misspelt preset, a folder without scans, and a --json or --plot that cannot be written: one line
    naming the flag, exit 2, before minutes of timing whose report would be lost."""
    (tmp_path / "empty" / "velodyne").mkdir(parents=True)
    (tmp_path / "a-file").write_text("")
    cases = {
        "--preset: unknown preset 'nonsense'": ["--preset", "nonsense"],
        "--data": ["--models", str(tiny_models), "--data", str(tmp_path / "empty")],
        "--json": ["--models", str(tiny_models), "--json", str(tmp_path)],
        "--plot": ["--models", str(tiny_models), "--plot", str(tmp_path / "a-file" / "p.png")],
    }
    for flag, args in cases.items():
        code, err = refused(capsys, *args, "--frames", "1", "--warmup", "0")
        assert code == 2 and f"error: {flag}" in err and "Traceback" not in err, err


def test_network_latency_alternates_in_blocks_each_after_an_untimed_run():
    """benchmarks.network_latency times each runtime in blocks, each block after one untimed run, so no
    timed run follows the other runtime's (whose threads may still be spinning)."""
    from tqdm import tqdm

    from benchmarks.network_latency import _time_alternating

    calls: list[str] = []
    with tqdm(disable=True) as bar:
        first, second = _time_alternating(lambda: calls.append("a"), lambda: calls.append("b"), 3, 2, bar)
    assert len(first) == len(second) == 3 and all(t >= 0 for t in first + second)
    # untimed + 2 timed of each, then untimed + the 1 left of each
    assert "".join(calls) == "aaabbbaabb"


def test_block_spread_flags_blocks_that_disagree():
    from benchmarks.latency import UNSTABLE_BLOCK_SPREAD, block_spread, unstable_warning

    steady = block_spread([1.58, 1.61, 1.60, 1.67])
    assert steady == {"p50": 1.605, "min": 1.58, "max": 1.67, "blocks": 4, "unstable": False}
    # One block disturbed by a neighbour (measured: 4.85 among 1.56-1.67): the median stays, the flag is raised.
    disturbed = block_spread([4.85, 1.58, 1.56, 1.61, 1.67, 1.61, 1.59, 1.60])
    assert disturbed["unstable"] and disturbed["p50"] == 1.605
    assert block_spread([1.0, UNSTABLE_BLOCK_SPREAD])["unstable"] is False
    text = unstable_warning("--compare-torch", disturbed)
    assert "1.56× to 4.85×" in text and "1.60×" in text


def test_the_score_threshold_reaches_every_detector_timed(tiny_models, monkeypatch):
    """--score-threshold goes to the single stream, both sides of the alternating blocks and the workers (the
    real Detector runs; a wrapper only records what each call was given)."""
    import os

    from benchmarks.latency import load_frames, run_paired, run_stream, run_workers
    from pipeline.detector import Detector
    from tests.conftest import KITTI

    given = []
    real = Detector.detect

    def recording(self, image, points, calib, score_threshold=None, *args, **kwargs):
        given.append(score_threshold)
        return real(self, image, points, calib, score_threshold, *args, **kwargs)

    monkeypatch.setattr(Detector, "detect", recording)
    frames = load_frames(KITTI, 2, 16)
    detector = Detector(tiny_models)
    run_stream(detector, frames, 2, 1, score_threshold=0.3)
    run_paired(detector, Detector(tiny_models), frames, 2, 1, block=1, score_threshold=0.3)
    usage = []
    run_workers(tiny_models, None, frames, 1, 2, 1, sorted(os.sched_getaffinity(0))[:1], score_threshold=0.3,
                usage=usage)
    assert len(given) > 10 and set(given) == {0.3}
    assert len(usage) == 1 and usage[0]["frames"] == 2 and 0 < usage[0]["cpu_share"] <= 1.05


def test_a_score_threshold_outside_0_1_is_refused_at_once(tiny_models, capsys):
    code, err = refused(capsys, "--models", str(tiny_models), "--score-threshold", "1.5")
    assert code == 2 and "--score-threshold" in err and "Traceback" not in err


def test_no_warm_up_on_a_gpu_provider_is_refused_before_anything_runs(tiny_models, capsys):
    """A GPU's first frames build its kernels (TensorRT's engine, for minutes): timed, they would be the mean."""
    code, err = refused(capsys, "--models", str(tiny_models), "--provider", "tensorrt", "--warmup", "0")
    assert code == 2 and "--warmup 0: with --provider tensorrt" in err
    assert "Traceback" not in err


def test_throughput_workers_take_the_gpus_in_turn(tiny_models, monkeypatch):
    """--device-ids: worker i's Detector is built for the i-th GPU, the single worker takes them in turn with the
    core shares, and the report says which. No GPU here: a subclass of the real Detector records the id it was
    given and loads on the CPU (the refusal of an id on the CPU is tested in test_detector.py)."""
    import os

    from benchmarks import latency
    from pipeline.detector import Detector
    from tests.conftest import KITTI

    given = []

    class RecordingGpu(Detector):
        def __init__(self, *args, device_id=None, **kwargs):
            given.append(device_id)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(latency, "Detector", RecordingGpu)
    frames = latency.load_frames(KITTI, 1, 16)
    cores = sorted(os.sched_getaffinity(0))[:2]
    report = latency.run_throughput(tiny_models, None, None, frames, 2, per_worker=1, warmup=0, cores=cores,
                                    rounds=2, device_ids=[3, 5])
    assert report["device_ids"] == [3, 5]
    # Rounds 1 N, N 1: one worker on GPU 3, two on 3 and 5, two again, then one on GPU 5 (with the second share).
    per_run = [sorted((u["worker"], u["device_id"]) for u in run["per_worker"]) for run in report["runs"]]
    assert per_run == [[(0, 3)], [(0, 3), (1, 5)], [(0, 3), (1, 5)], [(0, 5)]]
    assert sorted(given) == [3, 3, 3, 5, 5, 5]
    given.clear()
    assert latency.run_throughput(tiny_models, None, None, frames, 2, per_worker=1, warmup=0, cores=cores,
                                  rounds=1)["device_ids"] is None
    assert given == [None, None, None]


def test_gpu_ids_are_refused_without_a_gpu_provider_or_when_malformed(tiny_models, capsys):
    """--device-ids before minutes of timing: malformed or repeated ids by argparse, any without --provider
    cuda or tensorrt in one line (exit 2)."""
    for ids, message in (("0,1", "--device-ids 0,1: GPU ids need --provider cuda or tensorrt"),
                         ("0,x", "expected GPU ids from 0 separated by commas"), ("1,1", "a GPU id given twice"),
                         ("-1", "expected GPU ids from 0")):
        code, err = refused(capsys, "--models", str(tiny_models), f"--device-ids={ids}")
        assert code == 2 and message in err and "Traceback" not in err, ids


def test_summaries_keep_every_sample_and_say_what_a_p99_rests_on():
    """80 frames, the README's runs: numpy's p99 lies between the two slowest, so the report gives the slowest
    and the count beside it, and says so up to 101 frames (test_bench_latency.py: the boundaries)."""
    from benchmarks.latency import summarize, tail_note

    samples = [float(i) for i in range(1, 81)]  # 1 … 80 ms
    summary = summarize(samples)
    assert summary["n"] == 80 and summary["max"] == 80.0 and summary["mean"] == 40.5
    assert 79.0 < summary["p99"] < 80.0  # 79.21: an interpolation between the two slowest, not a tail
    assert "between the two slowest" in tail_note(80) and "p90" not in tail_note(80)
    assert "p90 between the two slowest" in tail_note(8) and tail_note(102) == ""


def test_the_fixed_calibration_takes_off_only_the_ray_tables_on_the_frames_path():
    """With a stage thread the ray_table stage is the frame's wait for all the work beside the depth net: a
    fast depth net (a GPU's, the tiny preset's) leaves the voxelization in that wait, and the share "without
    building ray tables" took it off too. Of a wait W for work whose table took R, min(W, R) is the table's."""
    from benchmarks.latency import StreamResult, ray_tables_on_path_ms

    beside = StreamResult(end_to_end=[10.0, 10.0, 10.0], stages={"ray_table": [5.0, 0.0, 0.3]}, wall_s=0.03,
                          frames=3, overlapped={"ray_table": [0.5, 0.6, 0.4], "voxelize": [6.0, 1.0, 1.0]})
    # frame 1 waited 5 ms, 0.5 of them the table's; frame 2 not at all; frame 3 0.3 ms, all of it the table's
    assert abs(ray_tables_on_path_ms(beside) - (0.5 + 0.0 + 0.3) / 3) < 1e-12
    in_turn = StreamResult(end_to_end=[10.0, 10.0], stages={"ray_table": [0.7, 0.02]}, wall_s=0.02, frames=2)
    assert abs(ray_tables_on_path_ms(in_turn) - 0.36) < 1e-12
    lidar_only = StreamResult(end_to_end=[5.0], stages={"pixor": [4.0]}, wall_s=0.005, frames=1)
    assert ray_tables_on_path_ms(lidar_only) == 0.0


def test_the_peak_runs_with_the_detectors_session_options(tiny_models):
    """The share of the peak compares like with like only if the micro-benchmarks' sessions are configured as
    the networks' are: the same threads, graph optimisation and thread-pool spinning."""
    from benchmarks.peak import _session, matmul_model
    from pipeline.detector import Detector

    peak = _session(matmul_model(64), 2).get_session_options()
    with Detector(tiny_models, providers="cpu", intra_op_threads=2) as detector:
        network = detector._sessions["pixor"].get_session_options()
        assert (peak.intra_op_num_threads, peak.inter_op_num_threads, peak.graph_optimization_level) == (
            network.intra_op_num_threads, network.inter_op_num_threads, network.graph_optimization_level)
        for key in ("session.intra_op.allow_spinning", "session.force_spinning_stop"):
            assert peak.get_session_config_entry(key) == network.get_session_config_entry(key) == "1", key


def test_network_latency_gives_both_runtimes_the_same_threads_and_reports_each_ones_own_runs(monkeypatch):
    """--threads 1 set PyTorch's threads alone: ONNX Runtime kept its default, one per core, and the table set
    one PyTorch thread against every core. The thread count is read back from the ONNX Runtime session.

    The networks run for real, their runs timed by a scripted clock: PyTorch's of 1, 2 and 6 ms give p50 2 and
    max 6, ONNX Runtime's of 1, 1 and 4 ms p50 1 and max 4 (a speed-up of 2); parameters and GFLOP are the
    networks' own."""
    from types import SimpleNamespace

    import torch

    from benchmarks import network_latency
    from models import build_network
    from pipeline.presets import get_preset
    from tests.test_benchmarks_mutants import ScriptedClock

    runs = {"torch": [1, 2, 6], "ort": [1, 1, 4]}  # ms, one block of three each
    clock = ScriptedClock([step for _network in ("depth", "pixor") for side in ("torch", "ort") for ms in runs[side]
                           for step in (0.0, ms / 1e3)])  # each timed run reads the clock at its start and its end
    monkeypatch.setattr(network_latency, "time", SimpleNamespace(perf_counter=clock.perf_counter))
    before = torch.get_num_threads()
    try:
        rows = network_latency.run(["tiny"], repeats=3, threads=1, progress=False, block=3)
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
    assert next(clock._steps, None) is None  # every scripted run was read, and no more
    assert [row.network for row in rows] == ["depth", "pixor"]
    for row in rows:
        assert row.threads == 1 and row.repeats == 3
        assert (row.torch_p50_ms, row.torch_max_ms, row.ort_p50_ms, row.ort_max_ms) == pytest.approx((2, 6, 1, 4))
        assert row.speedup == pytest.approx(2.0)
        assert row.parameters == sum(p.numel() for p in build_network(row.network, get_preset("tiny")).parameters())
        assert 0.01 < row.gflops < 1.0  # the README's 0.21 and 0.13 GFLOP, in GFLOP
