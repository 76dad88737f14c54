"""benchmarks/latency.py as a command: Ctrl-C during the throughput rounds, the runtime install without torch,
what it times by default, LiDAR-only models and worker counts (real subprocesses, real ONNX Runtime)."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from pipeline.cpu import usable_cpus
from tests.conftest import KITTI

ROOT = Path(__file__).resolve().parents[1]
LATENCY = ROOT / "benchmarks" / "latency.py"
QUICK = ["--peak-size", "64"]
SHIPPED, LIDAR64 = ROOT / "weights" / "edge", ROOT / "weights" / "edge-lidar64"
# As the runtime install (make demo) has it: no torch to import.
WITHOUT_TORCH = ("import runpy, sys; sys.modules['torch'] = None; sys.argv = ['latency.py', *sys.argv[1:]]; "
                 f"runpy.run_path({str(LATENCY)!r}, run_name='__main__')")


# Run so that SIGINT raises KeyboardInterrupt as at a terminal: a child of a background job (a CI runner's, say)
# inherits SIGINT ignored, and Python then leaves it so.
AS_AT_A_TERMINAL = ("import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
                    f"sys.argv = ['latency.py', *sys.argv[1:]]; runpy.run_path({str(LATENCY)!r}, run_name='__main__')")


def test_ctrl_c_during_the_throughput_rounds_stops_the_worker_threads_and_exits_130(tmp_path, tiny_models):
    """The worker threads were daemons still inside InferenceSession.run when the interpreter ended: the
    process aborted (``terminate called without an active exception``, SIGABRT) after its ``interrupted``
    line. Now they are stopped and waited for, and the command exits 130."""
    log = tmp_path / "stderr.txt"  # a file, not a pipe: a pipe lets the command run ahead of the reader
    command = [sys.executable, "-c", AS_AT_A_TERMINAL, *QUICK, "--models", str(tiny_models), "--threads", "2", "--frames", "300",
               "--warmup", "1"]
    with open(log, "w") as stderr:
        process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=stderr, start_new_session=True)
    try:
        deadline = time.monotonic() + 300
        while "timing the throughput" not in log.read_text() and process.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.5)  # the workers loaded and running frames
        assert process.poll() is None, "the command ended before it could be interrupted: " + log.read_text()[-2000:]
        os.killpg(process.pid, signal.SIGINT)  # as a terminal's Ctrl-C
        code = process.wait(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
    err = log.read_text()
    assert code == 130, (code, err[-2000:])
    assert "terminate called" not in err and "Traceback" not in err, err[-2000:]
    assert err.count("interrupted:") == 1 and "interrupted: no report was written" in err


def test_without_torch_what_needs_it_is_refused_in_one_line(tiny_models):
    """The runtime install has no torch: exporting a preset and --compare-torch say so in one line, exit 2."""
    cases = {"--preset tiny is exported with PyTorch": ["--preset", "tiny"],
             "--compare-torch times the PyTorch networks": ["--models", str(tiny_models), "--compare-torch"]}
    for says, args in cases.items():
        done = subprocess.run([sys.executable, "-c", WITHOUT_TORCH, *QUICK, *args, "--frames", "1", "--warmup", "0"],
                              capture_output=True, text=True, timeout=300, check=False, cwd=ROOT)
        assert done.returncode == 2, done.stderr[-2000:]
        assert "Traceback" not in done.stderr and len(done.stderr.strip().splitlines()) == 1, done.stderr[-2000:]
        assert done.stderr.startswith("error: this command needs PyTorch") and says in done.stderr


def test_without_models_it_times_the_shipped_model_and_needs_no_torch(tmp_path):
    """The README's figures are of weights/edge (preset edge-split-near35); latency.py without --models timed
    a fresh export of preset edge (untrained, another grid) and needed torch for it."""
    done = subprocess.run([sys.executable, "-c", WITHOUT_TORCH, *QUICK, "--frames", "1", "--warmup", "0", "--json",
                           str(tmp_path / "r.json")], capture_output=True, text=True, timeout=300, check=False, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads((tmp_path / "r.json").read_text())
    manifest = json.loads((SHIPPED / "manifest.json").read_text())
    assert report["models"] == str(SHIPPED) and report["preset"] == manifest["preset"] == "edge-split-near35"
    assert report["weights"] == manifest["weights"] and report["input"] == "16-line scan + camera"


def test_a_64_line_lidar_only_model_is_labelled_and_timed_on_its_own_scans(tmp_path):
    """weights/edge-lidar64 was labelled "16-line scan + camera" and timed on 16-line scans, the Detector's
    warning about them dropped. Now its scans are kept as stored unless --beams says otherwise, and then the
    warning is said, once for all frames."""
    done = subprocess.run([sys.executable, str(LATENCY), *QUICK, "--models", str(LIDAR64), "--frames", "2", "--warmup",
                           "0", "--json", str(tmp_path / "own.json")], capture_output=True, text=True, timeout=300,
                          check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads((tmp_path / "own.json").read_text())
    assert report["input"] == "scan as stored, LiDAR only (PIXOR trained on lidar64)" and report["beams"] is None
    assert report["trained_on"] == "lidar64" and report["warnings"] == [] and "warning:" not in done.stderr
    thinned = subprocess.run([sys.executable, str(LATENCY), *QUICK, "--models", str(LIDAR64), "--beams", "16", "--frames",
                              "2", "--warmup", "1", "--json", str(tmp_path / "16.json")], capture_output=True, text=True,
                             timeout=300, check=False)
    assert thinned.returncode == 0, thinned.stderr[-2000:]
    report = json.loads((tmp_path / "16.json").read_text())
    assert report["input"] == "16-line scan, LiDAR only (PIXOR trained on lidar64)" and report["beams"] == 16
    says = "warning: points: fewer than a 64-line scan has, but the model was trained on 64-line scans"
    assert thinned.stderr.count(says) == 1, thinned.stderr[-2000:]  # three frames, each with its own point count
    assert len(report["warnings"]) == 1 and f"warning: {report['warnings'][0]}" in thinned.stderr


def test_more_throughput_workers_than_cores_are_refused(tiny_models):
    """The worker past the cores got an empty share, fell back to all of them and oversubscribed the others,
    while the report said one core a worker."""
    cores = usable_cpus()
    for kind in ("thread", "process"):
        done = subprocess.run([sys.executable, str(LATENCY), *QUICK, "--models", str(tiny_models), "--threads",
                               str(cores + 1), "--worker-kind", kind, "--frames", "1", "--warmup", "0"],
                              capture_output=True, text=True, timeout=120, check=False)
        assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr[-2000:]
        assert f"error: --threads {cores + 1}: {kind} workers are each pinned" in done.stderr
        assert f"may use {cores} core" in done.stderr and "timing" not in done.stderr  # before any timing


def test_help_says_what_threads_and_the_default_model_are():
    done = subprocess.run([sys.executable, str(LATENCY), "--help"], capture_output=True, text=True, timeout=60,
                          check=False, env={**os.environ, "COLUMNS": "2000"})  # no words broken across lines
    assert done.returncode == 0
    text = " ".join(done.stdout.split())
    assert "throughput workers" in text and "not ONNX Runtime's intra-op threads" in text
    assert "default: the shipped weights/edge" in text and "edge-split-near35" in text


def test_a_report_named_as_one_of_its_inputs_is_refused_before_any_timing(tmp_path, capsys):
    """latency.py's --json and --plot, and frame_ops.py's --json, were never compared with what the run reads:
    a report named as the model's manifest or a frame's calibration replaced it after minutes of timing. Refused
    in one line before anything is timed; the inputs are as they were."""
    import shutil

    from benchmarks.frame_ops import main as frame_ops
    from benchmarks.latency import main as latency

    models = shutil.copytree(SHIPPED.with_name("edge-lidar16"), tmp_path / "models")
    data = tmp_path / "kitti"
    shutil.copytree(KITTI / "calib", data / "calib")
    before = {p: p.read_bytes() for p in [*models.iterdir(), *(data / "calib").iterdir()]}
    cases = [(latency, ["--models", str(models), "--json", str(models / "manifest.json")], "--json", "--models", models),
             (latency, ["--models", str(models), "--data", str(data), "--plot", str(data / "calib" / "x.png")], "--plot",
              "--data", data),
             (frame_ops, ["--data", str(data), "--json", str(data / "calib" / "000006.txt")], "--json", "--data", data)]
    for main, args, flag, read, source in cases:
        assert main(args) == 2, args
        err = capsys.readouterr().err
        assert err.startswith(f"error: {flag} ") and f"would be written over what {read} {source.resolve()} holds" in err
        assert len(err.splitlines()) == 1, err
    assert {p: p.read_bytes() for p in before} == before
