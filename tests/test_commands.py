"""The commands as one family: every one answers --help (with an example, on the runtime install too), spells a
shared flag alike, refuses a bad count or seed by the flag in one line before any work, and ends on Ctrl-C with
one ``interrupted: …`` line."""

import argparse
import importlib
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
           "models.reproduce", "models.cache_pseudo", "export", "export.lower", "export.precision",
           "export.golden", "requirements.lock", "models.onnx_weights", "pipeline.check_models", "models.curves"]
SCRIPTS = ["latency", "accuracy", "load", "frame_ops", "eval_speed", "sim_report", "network_latency", "peak",
           "op_profile", "depth_bound"]
# The commands of the README's table and the Makefile, which this family's checks hold to: all of them.
FAMILY = MODULES + SCRIPTS


def _command(name: str) -> list[str]:
    return [sys.executable, "-m", name] if name in MODULES else [sys.executable, str(REPO / "benchmarks" / f"{name}.py")]


def _prog(name: str) -> str:
    """How the README and the Makefile run the command, which its usage line and examples show."""
    if name in SCRIPTS:
        return f"python benchmarks/{name}.py"
    return "python requirements/lock.py" if name == "requirements.lock" else f"python -m {name}"


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
    if name in FAMILY:  # the usage line and an example run the command as the README does
        assert done.stdout.startswith(f"usage: {_prog(name)} "), done.stdout[:200]
        assert re.search(rf"^examples?:\n  {re.escape(_prog(name))} \S", done.stdout, re.MULTILINE), done.stdout


# What the runtime install (make demo: no torch, matplotlib or httpx) answers to --help: the usage, or for a
# command that needs a package it lacks one line saying what to install, exit status 2 as any usage error.
NEEDS_EXTRAS = {"models.train", "models.cache_pseudo", "models.reproduce", "export", "network_latency", "depth_bound",
                "load", "models.onnx_weights", "models.curves"}
RUNTIME = ("import runpy, sys; [sys.modules.__setitem__(m, None) for m in ('torch', 'matplotlib', 'httpx')]; "
           "sys.argv = ['x', '--help']; ")


@pytest.mark.parametrize("name", FAMILY)
def test_every_command_answers_help_on_the_runtime_install(name):
    run = (f"runpy.run_path({str(REPO / 'benchmarks' / f'{name}.py')!r}, run_name='__main__')" if name in SCRIPTS
           else f"runpy.run_module({name!r}, run_name='__main__', alter_sys=True)")
    done = subprocess.run([sys.executable, "-c", RUNTIME + run], capture_output=True, text=True, timeout=120,
                          check=False, cwd=REPO)
    if name not in NEEDS_EXTRAS:
        assert done.returncode == 0 and done.stdout.startswith("usage:"), done.stderr[-1000:]
        return
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr[-1000:]
    assert len(done.stderr.splitlines()) == 1 and done.stderr.startswith("error: ") and "make setup-dev" in done.stderr


class _Built(Exception):
    """Raised instead of parsing the command line: the command's parser is its argument."""


def _parser(name: str, monkeypatch: pytest.MonkeyPatch) -> argparse.ArgumentParser:
    """The parser a command's main builds (service's and accuracy's have builders of their own)."""
    if name == "service":
        from service.__main__ import build_parser

        return build_parser()
    module = importlib.import_module(f"benchmarks.{name}" if name in SCRIPTS else
                                     f"{name}.__main__" if name in ("simulation", "export") else name)

    def built(parser: argparse.ArgumentParser, *_: object, **__: object) -> None:
        raise _Built(parser)

    with monkeypatch.context() as patch:
        patch.setattr(argparse.ArgumentParser, "parse_args", built)
        with pytest.raises(_Built) as raised:
            module.main([])
    return raised.value.args[0]


# The family's spelling of each shared flag and what --help shows for its value.
SHARED_FLAGS = {"--models": {"DIR"}, "--data": {"DIR"}, "--out": {"DIR", "FILE"}, "--frame": {"ID"},
                "--frames": {"N", "LIST|N"}, "--split-file": {"F"}, "--preset": {"P"}, "--emulate-beams": {"N"},
                "--threads": {"N"}, "--repeats": {"N"}, "--json": {"FILE"}, "--plot": {"FILE"}, "--plots": {"DIR"},
                "--score-threshold": {"SCORE"}, "--seed": {None}, "--no-progress": {None}}
# Old spellings, each still accepted as a hidden alias of the family's name for the same thing. pipeline.beams'
# --beams is that command's own subject (the lines to keep; 0, "as stored", is no choice there).
OLD_SPELLINGS = {"--beams": "--emulate-beams", "--kitti": "--data", "--sim": "--sim-data", "--figure": "--plot",
                 "--kitti-dir": "--data"}
# The commands that run over many frames (or runs) and draw progress bars.
LONG = {"pipeline.detect", "pipeline.beams", "simulation", "models.train", "models.reproduce", "models.cache_pseudo",
        "accuracy", "depth_bound", "network_latency", "sim_report"}


@pytest.mark.parametrize("name", FAMILY)
def test_the_family_spells_each_shared_flag_alike(name, monkeypatch):
    """Every command's parser: the same concept under the same flag, its value shown alike, a help line for each
    option, the old spellings kept working but out of --help, and --no-progress where bars are drawn."""
    from pipeline.cli import non_negative_int, shown_spellings

    parser = _parser(name, monkeypatch)
    assert parser.prog == _prog(name)
    assert parser.description
    text = parser.format_help()
    for action in parser._actions:
        assert action.help, (name, action.option_strings or action.dest)
        for flag in set(action.option_strings) & SHARED_FLAGS.keys():
            if (name, action.option_strings[0]) == ("pipeline.beams", "--beams"):
                continue  # its own subject, with the family's --emulate-beams a hidden alias (below)
            assert action.option_strings[0] == flag, (name, action.option_strings)
            assert action.metavar in SHARED_FLAGS[flag], (name, flag, action.metavar)
        if "--seed" in action.option_strings:
            assert action.type is non_negative_int, name  # a seed below 0 is refused by the flag, not by NumPy
        for hidden in set(action.option_strings) - set(shown_spellings(action)):
            assert not re.search(rf"(?<![\w-]){re.escape(hidden)}(?![\w-])", text), (name, hidden)
    for old, family in OLD_SPELLINGS.items():
        action = parser._option_string_actions.get(old)
        if action is not None and (name, old) != ("pipeline.beams", "--beams"):
            assert action.option_strings[0] == family, (name, old)  # the family's name, first, for the same thing
    assert ("--no-progress" in parser._option_string_actions) == (name in LONG), name


COUNTS = [("frame_ops", "--repeats"), ("eval_speed", "--frames"), ("sim_report", "--frames"),
          ("network_latency", "--repeats"), ("latency", "--frames"), ("simulation", "--frames"),
          ("export.precision", "--calibration-frames"), ("export", "--calibration-frames")]
SEEDS = [("eval_speed", []), ("accuracy", []), ("models.train", ["depth"]), ("sim_report", []), ("simulation", [])]
REFUSED = [*((name, [flag, "0"], f"argument {flag}: must be at least 1, got 0") for name, flag in COUNTS),
           *((name, [*args, "--seed", "-1"], "argument --seed: must be 0 or more, got -1") for name, args in SEEDS)]


@pytest.mark.parametrize(("name", "args", "says"), REFUSED, ids=[f"{r[0]} {' '.join(r[1])}" for r in REFUSED])
def test_counts_of_zero_and_seeds_below_zero_are_refused_by_the_flag(name, args, says):
    done = subprocess.run([*_command(name), *args], capture_output=True, text=True, timeout=120, check=False,
                          cwd=REPO)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert says in done.stderr


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
    assert len(result.stderr.splitlines()) == 1, result.stderr  # the hint alone, not "no such model directory" too


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


@pytest.mark.parametrize(("name", "flag"), [("latency", "--plot"), ("load", "--plot"), ("sim_report", "--plot")])
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


@pytest.mark.parametrize(("args", "says"), [
    (["--data", "{tmp}/nope"], "error: --data {tmp}/nope: not a folder"),
    (["--kitti", "{tmp}/nope"], "error: --kitti {tmp}/nope: not a folder"),  # an old script's spelling, named so
    (["--sim-data", "{tmp}/nope"], "error: --sim-data {tmp}/nope: not a folder"),
    (["--sim-data", str(KITTI), "--plot", "{tmp}/a.txt"], "error: --plot {tmp}/a.txt: give a file name ending in")])
def test_sim_report_takes_the_family_flags_and_names_them_as_given(args, says, tmp_path):
    done = subprocess.run([*_command("sim_report"), *(arg.format(tmp=tmp_path) for arg in args)], capture_output=True,
                          text=True, timeout=120, check=False, cwd=REPO)
    assert done.returncode == 2 and done.stderr.startswith(says.format(tmp=tmp_path)), done.stderr
    assert len(done.stderr.splitlines()) == 1


def _broken_copy(folder: Path) -> Path:
    """A KITTI folder of the bundled frames whose scans 000000 and 000001 are cut off."""
    for sub in ("image_2", "velodyne", "calib"):
        shutil.copytree(KITTI / sub, folder / sub)
    for fid in ("000000", "000001"):
        (folder / "velodyne" / f"{fid}.bin").write_bytes(b"abc")
    return folder


@pytest.mark.parametrize("name", ["pipeline.beams", "pipeline.detect"])
def test_a_run_into_a_pipe_writes_its_lines_clean(name, tmp_path):
    """A script reads stderr line by line: in a pipe there is no progress bar, whose carriage returns and the
    blanks tqdm.write cleared it with came between the named frames, read as blank lines."""
    data = _broken_copy(tmp_path / "kitti")
    args = ([str(data / "velodyne"), str(tmp_path / "v16")] if name == "pipeline.beams" else
            ["--data", str(data), "--emulate-beams", "16", "--no-pictures", "--out", str(tmp_path / "out")])
    done = subprocess.run([*_command(name), *args], capture_output=True, text=True, timeout=300, check=False,
                          cwd=REPO)
    assert done.returncode == 1, done.stderr[-2000:]
    lines = done.stderr.splitlines()  # splits at a carriage return too, as a log viewer does
    assert "\r" not in done.stderr and all(line.startswith("error: ") for line in lines), lines
    assert sum("size 3 bytes" in line for line in lines) == 2 and "2 of 5" in lines[2], lines


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
    ("models.onnx_weights", ["--models", "weights/edge", "--out", "{tmp}/ckpt"], "checkpoints_from_model_dir",
     "--out holds what was written before it"),
    ("pipeline.check_models", ["--models", "weights/edge-lidar16"], "run", "the model directory is as it was"),
    ("pipeline.demo", [], "argparse", "the pictures and result files written so far stay in --out"),
    ("requirements.lock", [], "argparse", "--out is as it was"),
    *[(name, [], "argparse", "") for name in SCRIPTS],
]


@pytest.mark.parametrize(("name", "args", "where", "says"), INTERRUPTIONS, ids=[i[0] for i in INTERRUPTIONS])
def test_ctrl_c_ends_a_command_with_one_line(name, args, where, says, tmp_path, monkeypatch, capsys):
    """Ctrl-C (a KeyboardInterrupt wherever it comes) ends each command with exit status 130 and one line that
    says what it leaves, not a traceback."""
    import argparse
    import importlib

    module = importlib.import_module(f"benchmarks.{name}" if name in SCRIPTS else
                                     f"{name}.__main__" if name in ("simulation", "export") else name)
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


# Installed in the command's own process before it starts (a sitecustomize on PYTHONPATH): a real SIGINT sent to
# itself when the module $CTRL_C_AT is first imported, $CTRL_C_TIMES times, as a Ctrl-C landing at that moment.
CTRL_C_AT_IMPORT = """import os, signal, sys


class CtrlCAt:
    def find_spec(self, name, path=None, target=None):
        if name == os.environ["CTRL_C_AT"]:
            for _ in range(int(os.environ["CTRL_C_TIMES"])):
                os.kill(os.getpid(), signal.SIGINT)
        return None


sys.meta_path.insert(0, CtrlCAt())
"""


@pytest.mark.parametrize(("name", "at", "times"), [
    ("models.train", "torch", 1),  # models/__init__.py's `from torch import nn`
    ("models.train", "torch", 2),  # a second Ctrl-C: at once
    ("models.onnx_weights", "onnx", 1),  # its own imports, after PyTorch's
    ("export", "torch", 1),  # export/__main__.py's imports
])
def test_ctrl_c_while_a_torch_command_loads_ends_in_one_line(name, at, times, tmp_path):
    """Ctrl-C in a torch command's first second or so, while PyTorch and ONNX load, printed a traceback ending in
    KeyboardInterrupt and the process died by SIGINT; now it ends as a later Ctrl-C does: one line, status 130."""
    (tmp_path / "sitecustomize.py").write_text(CTRL_C_AT_IMPORT)
    path = os.pathsep.join(filter(None, [str(tmp_path), os.environ.get("PYTHONPATH")]))
    done = subprocess.run([sys.executable, "-m", name, "--help"], capture_output=True, text=True, timeout=120,
                          check=False, cwd=REPO,
                          env={**os.environ, "PYTHONPATH": path, "CTRL_C_AT": at, "CTRL_C_TIMES": str(times)})
    assert done.returncode == 130, (done.returncode, done.stderr[-2000:])
    assert done.stderr == ("interrupted: while the command was loading PyTorch and ONNX, before it began; nothing "
                           "was written\n"), done.stderr[-2000:]
    assert done.stdout == ""  # it stopped there: not even its --help


def test_ctrl_c_while_the_service_starts_ends_as_in_every_command():
    """Ctrl-C while the service loads its models (here: at once) ends with one ``interrupted: …`` line and 130,
    as once it serves; it was a log line of its own form."""
    code = ("import signal, sys\nimport service.runtime as runtime\nimport service.__main__ as service\n"
            "def ctrl_c(*_, **__):\n    raise service.StoppedBeforeServing(signal.SIGINT)\n"
            "runtime.load_runtime = ctrl_c\nsys.exit(service.main(['--port', '0']))")
    env = {k: v for k, v in os.environ.items() if not k.startswith("LOWRES3D_")}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False,
                          cwd=REPO, env=env)
    assert done.returncode == 130, done.stderr[-2000:]
    assert done.stderr.count("SIGINT before serving") == 1 and "Traceback" not in done.stderr, done.stderr
    assert done.stderr.splitlines()[-1] == ("interrupted: SIGINT before serving: stopped while loading the models; "
                                            "not started")


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


@pytest.mark.parametrize(("failure", "says"), [("missing", "error: torch is not installed: run make setup-dev first"),
                                               ("unreadable", "error: --out {tmp}/none.txt: No such file")])
def test_the_lock_says_what_the_environment_lacks_with_status_2(failure, says, tmp_path, monkeypatch, capsys):
    """Exit status 1 is --check's "the versions differ"; a package missing here or a lock file that cannot be
    read is a usage error, 2, as in every command."""
    from importlib.metadata import PackageNotFoundError

    from requirements import lock

    def torch_missing(_: object) -> dict[str, str]:
        raise PackageNotFoundError("torch")

    if failure == "missing":
        monkeypatch.setattr(lock, "installed_closure", torch_missing)
    assert lock.main(["--check", "--out", str(tmp_path / "none.txt")]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(says.format(tmp=tmp_path)), err


def test_lower_outside_a_checkout_asks_for_a_frame(tmp_path):
    """An installed wheel leaves tests/data behind: export.lower takes its check frame from --data then."""
    site = tmp_path / "site-packages"
    for package in ("pipeline", "export"):
        shutil.copytree(REPO / package, site / package, ignore=shutil.ignore_patterns("__pycache__"))
    command = [sys.executable, "-m", "export.lower", "--models", str(REPO / "weights" / "edge")]
    env = {**os.environ, "PYTHONPATH": str(site)}
    refused = subprocess.run([*command, "--out", str(tmp_path / "a")], cwd=tmp_path, env=env, capture_output=True,
                             text=True, timeout=120, check=False)
    assert refused.returncode == 2 and "Traceback" not in refused.stderr
    assert "exist only in a source checkout; give a KITTI object folder with --data DIR" in refused.stderr
    done = subprocess.run([*command, "--out", str(tmp_path / "b"), "--data", str(KITTI)], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "b" / "manifest.json").is_file()
