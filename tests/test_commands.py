"""Every command answers --help, and a count of zero is refused by the flag, in one line, before any work."""

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
KITTI = REPO / "tests" / "data" / "kitti" / "training"
MODULES = ["pipeline.detect", "pipeline.beams", "pipeline.demo", "service", "simulation", "models.train",
           "models.reproduce", "models.cache_pseudo", "export", "export.lower", "export.precision"]
SCRIPTS = ["latency", "accuracy", "load", "frame_ops", "eval_speed", "sim_report", "network_latency", "peak",
           "op_profile", "depth_bound"]


def _command(name: str) -> list[str]:
    return [sys.executable, "-m", name] if name in MODULES else [sys.executable, str(REPO / "benchmarks" / f"{name}.py")]


@pytest.mark.parametrize("name", MODULES + SCRIPTS)
def test_every_command_answers_help(name):
    done = subprocess.run([*_command(name), "--help"], capture_output=True, text=True, timeout=120, check=False,
                          cwd=REPO)
    assert done.returncode == 0, done.stderr[-1000:]
    assert done.stdout.startswith("usage:") and "--help" in done.stdout
    # The module docstrings that become the help are plain text to a user: no Sphinx roles.
    assert not re.search(r":(data|func|class|meth|attr|mod):`", done.stdout), done.stdout
    if name == "models.train":
        from models.devices import COMPILE_MIN_STEPS

        assert f"at least {COMPILE_MIN_STEPS} steps" in done.stdout  # the docstring's number is the constant's


@pytest.mark.parametrize(("name", "flag"), [("frame_ops", "--repeats"), ("eval_speed", "--frames"),
                                            ("sim_report", "--frames"), ("network_latency", "--repeats"),
                                            ("latency", "--frames"), ("simulation", "--frames"),
                                            ("export.precision", "--calibration-frames"),
                                            ("export", "--calibration-frames")])
def test_counts_of_zero_are_refused_by_the_flag(name, flag):
    done = subprocess.run([*_command(name), flag, "0"], capture_output=True, text=True, timeout=120, check=False,
                          cwd=REPO)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert f"argument {flag}: must be at least 1, got 0" in done.stderr


@pytest.mark.parametrize("name", ["pipeline.detect", "accuracy"])
def test_a_score_threshold_outside_0_1_is_refused(name):
    done = subprocess.run([*_command(name), "--score-threshold", "2"], capture_output=True, text=True, timeout=120,
                          check=False, cwd=REPO)
    assert done.returncode == 2 and "argument --score-threshold: must be between 0 and 1, got 2" in done.stderr


def test_detect_outside_a_checkout_says_where_the_default_weights_are(tmp_path):
    """After `pip install .` (not -e) weights/edge is not beside the installed package: the error says so."""
    site = tmp_path / "site-packages"
    shutil.copytree(REPO / "pipeline", site / "pipeline", ignore=shutil.ignore_patterns("__pycache__"))
    result = subprocess.run(
        [sys.executable, "-m", "pipeline.detect", "--data", str(KITTI), "--frame", "000006", "--out", str(tmp_path / "o")],
        cwd=tmp_path, capture_output=True, text=True, timeout=120, check=False,
        env={**os.environ, "PYTHONPATH": str(site)},
    )
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert f"the default --models {site / 'weights' / 'edge'} exists only in a source checkout" in result.stderr


def test_the_demo_outside_a_checkout_says_it_needs_one(tmp_path):
    """The demo's bundled frames (tests/data) are not installed by `pip install .`: one line says so."""
    site = tmp_path / "site-packages"
    shutil.copytree(REPO / "pipeline", site / "pipeline", ignore=shutil.ignore_patterns("__pycache__"))
    result = subprocess.run([sys.executable, "-m", "pipeline.demo", "--out", str(tmp_path / "o")], cwd=tmp_path,
                            capture_output=True, text=True, timeout=120, check=False,
                            env={**os.environ, "PYTHONPATH": str(site)})
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "exist only in a source checkout" in result.stderr and not (tmp_path / "o").exists()


def test_a_picture_without_matplotlib_is_refused_before_the_run(tmp_path, monkeypatch):
    """The runtime install has no matplotlib: a --plot is refused up front, not after minutes of timing."""
    import importlib.util

    from pipeline.cli import check_figure
    from pipeline.errors import InputError

    check_figure(tmp_path / "a.png", "--plot")
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "matplotlib" else real(name, *a))
    with pytest.raises(InputError, match="--plot: drawing needs matplotlib"):
        check_figure(tmp_path / "a.png", "--plot")


@pytest.mark.parametrize(("name", "flag"), [("latency", "--plot"), ("load", "--plot"), ("sim_report", "--figure")])
def test_a_picture_name_matplotlib_cannot_write_is_refused_before_the_run(name, flag, tmp_path):
    done = subprocess.run([*_command(name), flag, str(tmp_path / "latency.txt")], capture_output=True, text=True,
                          timeout=120, check=False, cwd=REPO)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert f"{flag} {tmp_path / 'latency.txt'}: give a file name ending in .png" in done.stderr


@pytest.mark.parametrize(("args", "words"), [(["--frame", "999999"], "999999"), (["--preset", "nope"], "unknown preset"),
                                             (["--json", "{file}/x.json"], "--json"),
                                             (["--data", "{file}", "--frame", "000000"], "a-file")])
def test_frame_ops_bad_input_is_one_line(args, words, tmp_path):
    (tmp_path / "a-file").write_text("")
    args = [arg.replace("{file}", str(tmp_path / "a-file")) for arg in args]
    done = subprocess.run([*_command("frame_ops"), *args, "--repeats", "1"], capture_output=True, text=True,
                          timeout=120, check=False, cwd=REPO)
    assert done.returncode == 2 and "Traceback" not in done.stderr and words in done.stderr


def test_network_latency_takes_preset_names_with_suffixes():
    """--preset goes through get_preset, as every other command's: the shipped edge-split-near35 is one."""
    from benchmarks.network_latency import _preset_name

    assert _preset_name("edge-split-near35") == "edge-split-near35"
    done = subprocess.run([*_command("network_latency"), "--preset", "edge-splitt"], capture_output=True, text=True,
                          timeout=120, check=False, cwd=REPO)
    assert done.returncode == 2 and "argument --preset: unknown preset 'edge-splitt'" in done.stderr


def test_eval_speed_refuses_a_keep_folder_it_cannot_write(tmp_path):
    (tmp_path / "a-file").write_text("")
    done = subprocess.run([*_command("eval_speed"), "--frames", "2", "--keep", str(tmp_path / "a-file")],
                          capture_output=True, text=True, timeout=120, check=False, cwd=REPO)
    assert done.returncode == 2 and "Traceback" not in done.stderr and "--keep" in done.stderr
    labels = tmp_path / "kitti" / "label_2"
    labels.mkdir(parents=True)
    (labels / "000000.txt").write_text("Car 0 0 0 1 2 3 4 1 1 1 1 1 1 0\n")  # someone's real labels
    done = subprocess.run([*_command("eval_speed"), "--frames", "2", "--keep", str(tmp_path / "kitti")],
                          capture_output=True, text=True, timeout=120, check=False, cwd=REPO)
    assert done.returncode == 2 and "--keep" in done.stderr and "not empty" in done.stderr
    assert (labels / "000000.txt").read_text() == "Car 0 0 0 1 2 3 4 1 1 1 1 1 1 0\n"


def _stop(*_: object, **__: object) -> None:
    raise KeyboardInterrupt


# (command, its arguments, the function Ctrl-C is raised in: a name in the command's module, or the argument
# parser for the commands that write their outputs only at the end, and what the line says is left).
INTERRUPTIONS = [
    ("simulation", ["--out", "{tmp}/sim", "--frames", "1", "--seed", "1"], "run",
     "the frames finished are in {tmp}/sim; rerun the same command to resume"),
    ("pipeline.beams", [str(KITTI / "velodyne"), "{tmp}/v16"], "convert_folder", "the scans written so far stay in"),
    ("export.precision", ["--models", "weights/edge", "--precision", "int8", "--out", "{tmp}/int8"],
     "convert_precision", "--out {tmp}/int8 is as it was (nothing written)"),
    ("export.lower", ["--models", "weights/edge", "--out", "{tmp}/low"], "run", "{tmp}/low is as it was"),
    ("pipeline.demo", [], "argparse", "the pictures and result files written so far stay in --out"),
    *[(name, [], "argparse", "") for name in SCRIPTS],
]


@pytest.mark.parametrize(("name", "args", "where", "says"), INTERRUPTIONS, ids=[i[0] for i in INTERRUPTIONS])
def test_ctrl_c_ends_a_command_with_one_line(name, args, where, says, tmp_path, monkeypatch, capsys):
    """Ctrl-C (a KeyboardInterrupt wherever it comes) ends each command with exit status 130 and one line that
    says what it leaves, not a traceback."""
    import argparse
    import importlib

    module = importlib.import_module(f"benchmarks.{name}" if name in SCRIPTS else
                                     f"{name}.__main__" if name == "simulation" else name)
    if where == "argparse":
        monkeypatch.setattr(argparse.ArgumentParser, "parse_args", _stop)
    else:
        monkeypatch.setattr(module, where, _stop)
    monkeypatch.chdir(REPO)
    try:
        code = module.main([arg.format(tmp=tmp_path) for arg in args])
    except KeyboardInterrupt:
        pytest.fail(f"{name}: Ctrl-C escaped its main as a traceback")
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 130 and len(err) == 1 and err[0].startswith("interrupted: "), err
    assert says.format(tmp=tmp_path) in err[0]


def test_the_demo_refuses_a_models_folder_that_is_not_one(tmp_path, capsys):
    """A mistyped --models ran the core alone and exited 0, its summary's "mode" the only sign; --core asks for
    the core by name."""
    from pipeline.demo import main

    typo = tmp_path / "weigths" / "edge"
    assert main(["--models", str(typo), "--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err == (f"error: --models {typo}: no manifest.json, so not a model directory (python "
                                       "-m export writes one); --core runs the frame-processing core alone\n")
    assert not (tmp_path / "o").exists()
    assert main(["--core", "--frame", "000003", "--out", str(tmp_path / "o")]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["mode"] == "core (no model directory)"
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == [
        "000003_bev_16.png", "000003_bev_64.png", "000003_sparse_depth_16.png"]
