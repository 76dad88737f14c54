"""Retraining on a 16-line sensor's own scans: ``--emulate-beams 0`` of ``models.train`` and ``models.cache_pseudo``.

Every training path used to thin the stored scans to 16 lines itself, and pipeline.beams.emulate_beams refuses a
scan that has 16 lines already, so a labelled folder of a VLP-16's scans could not be trained on at all. Each run
here is the tiny preset on one or two real KITTI frames (or their 16-line copies) for one epoch.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from models.cache_pseudo import main as cache_main
from models.train import main
from pipeline.beams import emulate_beams
from pipeline.frame import load_frame
from pipeline.kitti import read_depth_png, read_velodyne, write_velodyne
from pipeline.presets import get_preset
from tests.conftest import KITTI

FRAMES = ("000006", "000003")
RUN = ["--preset", "tiny", "--epochs", "1", "--batch-size", "1", "--compile", "off"]


def _error(argv: list[str], capsys, command=main) -> str:
    """The one-line error of a command that refuses with exit status 2."""
    assert command(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    return err[0]


def _log(run_dir: Path) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "log.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def sensor16(tmp_path_factory) -> Path:
    """A labelled KITTI-layout folder of a 16-line sensor: two real frames, their scans thinned to 16 lines once
    and written back as the sensor would have stored them (images, calibrations and labels linked)."""
    folder = tmp_path_factory.mktemp("own_sensor") / "training"
    for name in ("velodyne", "image_2", "calib", "label_2"):
        (folder / name).mkdir(parents=True)
    for fid in FRAMES:
        scan = read_velodyne(KITTI / "velodyne" / f"{fid}.bin").points
        write_velodyne(folder / "velodyne" / f"{fid}.bin", emulate_beams(scan, 16))
        for name, ext in (("image_2", ".png"), ("calib", ".txt"), ("label_2", ".txt")):
            (folder / name / f"{fid}{ext}").symlink_to(KITTI / name / f"{fid}{ext}")
    return folder


def _train(task: str, data: Path, out: Path, *extra: str) -> list[str]:
    return [task, "--data", str(data), *RUN, "--out", str(out), *extra]


@pytest.fixture(scope="module")
def own_detector(sensor16, tmp_path_factory) -> Path:
    """A tiny lidar16 PIXOR trained one epoch on the 16-line sensor's own scans."""
    out = tmp_path_factory.mktemp("runs") / "pixor"
    assert main(_train("detector", sensor16, out, "--input", "lidar16", "--emulate-beams", "0")) == 0
    return out


@pytest.fixture(scope="module")
def own_depth(sensor16, tmp_path_factory) -> Path:
    """A tiny depth net trained one epoch on the 16-line sensor's own scans."""
    out = tmp_path_factory.mktemp("runs") / "depth"
    assert main(_train("depth", sensor16, out, "--emulate-beams", "0")) == 0
    return out


def test_a_detector_trains_on_a_16_line_sensors_own_scans(own_detector):
    """Trained and validated on the scans as stored; the run's state and checkpoint record the flag."""
    (record,) = _log(own_detector)
    assert math.isfinite(record["train_loss"]) and math.isfinite(record["val_loss"])
    state = torch.load(own_detector / "state.pt", map_location="cpu", weights_only=False)
    assert state["config"]["emulate_beams"] == 0
    checkpoint = torch.load(own_detector / "pixor.pt", map_location="cpu", weights_only=False)
    assert checkpoint["metadata"]["emulate_beams"] == 0 and checkpoint["metadata"]["input"] == "lidar16"


def test_a_depth_net_trains_on_a_16_line_sensors_own_scans(own_depth):
    (record,) = _log(own_depth)
    assert math.isfinite(record["train_loss"]) and math.isfinite(record["val_loss"]) and record["pixels"] > 0
    checkpoint = torch.load(own_depth / "depth.pt", map_location="cpu", weights_only=False)
    assert checkpoint["metadata"]["emulate_beams"] == 0


@pytest.mark.parametrize(("task", "extra"), [("detector", ["--input", "lidar16"]), ("detector", ["--input", "pseudo",
                                             "--pseudo-dir", "maps"]), ("depth", [])])
def test_without_the_flag_one_line_names_the_scan_and_the_flag(sensor16, tmp_path, capsys, task, extra):
    """Left at 16 on scans thinned already: refused before any training, naming the first scan, not a traceback
    or an emulate_beams error without a file name an epoch in."""
    out = tmp_path / "run"
    says = _error(_train(task, sensor16, out, *extra), capsys)
    assert says == (f"error: {sensor16 / 'velodyne' / '000003.bin'}: points: the scan has 16 rings, not 64: it is "
                    "thinned already (emulate beams on 64-line scans only); to train on scans of a 16-line sensor "
                    "as they are, give --emulate-beams 0")
    assert not out.exists()


def test_joint_fine_tuning_on_a_16_line_sensors_own_scans(sensor16, own_depth, own_detector, tmp_path):
    out = tmp_path / "joint"
    argv = _train("joint", sensor16, out, "--emulate-beams", "0", "--max-train-frames", "1", "--max-val-frames", "1",
                  "--depth-checkpoint", str(own_depth / "depth.pt"),
                  "--pixor-checkpoint", str(own_detector / "pixor.pt"))
    assert main(argv) == 0
    (record,) = _log(out)
    assert math.isfinite(record["train_loss"]) and math.isfinite(record["val_loss"])


def test_the_flag_reaches_the_datasets():
    """On a 64-line folder the samples are those of the scan as stored with 0, of its 16-line thinning with 16."""
    from models.data import DetectorDataset
    from models.train import depth_dataset
    from pipeline.preprocess import depth_inputs

    preset = get_preset("tiny")
    frame = load_frame(KITTI, "000006")
    for beams, points in ((0, frame.points), (16, emulate_beams(frame.points, 16))):
        _, scan, _ = DetectorDataset(KITTI, ["000006"], preset, "lidar16", beams=beams)._load(0)
        np.testing.assert_array_equal(scan, points)
        _, sparse, _ = depth_dataset(KITTI, ["000006"], preset, beams=beams)._load(0)
        np.testing.assert_array_equal(sparse, depth_inputs(frame.image, points, frame.calib, preset).sparse_depth[0])


def test_resume_keeps_the_flag_and_refuses_another_value(own_detector, sensor16, tmp_path, capsys):
    run_dir = tmp_path / "run"
    shutil.copytree(own_detector, run_dir)
    before = {p.name: p.read_bytes() for p in run_dir.iterdir()}
    says = _error(_train("detector", sensor16, run_dir, "--input", "lidar16", "--resume", "--epochs", "2"), capsys)
    assert f"--emulate-beams 16, but {run_dir} was started with --emulate-beams 0" in says
    assert {p.name: p.read_bytes() for p in run_dir.iterdir()} == before
    argv = _train("detector", sensor16, run_dir, "--input", "lidar16", "--emulate-beams", "0", "--resume", "--epochs", "2")
    assert main(argv) == 0
    assert [r["epoch"] for r in _log(run_dir)] == [1, 2]


def test_resume_of_a_run_from_before_the_flag_counts_it_as_16(tmp_path, capsys):
    """A state without the setting was made when every run thinned to 16: resumed with 0 it is refused."""
    split = tmp_path / "one.txt"
    split.write_text("000006\n")
    run_dir = tmp_path / "run"
    argv = _train("detector", KITTI, run_dir, "--train-split", str(split), "--val-split", str(split))
    assert main(argv) == 0
    state = torch.load(run_dir / "state.pt", map_location="cpu", weights_only=False)
    assert state["config"].pop("emulate_beams") == 16
    torch.save(state, run_dir / "state.pt")
    capsys.readouterr()  # the first run's progress bars
    says = _error([*argv, "--resume", "--epochs", "2", "--emulate-beams", "0"], capsys)
    assert f"--emulate-beams 0, but {run_dir} was started with --emulate-beams 16" in says


def test_lidar64_runs_refuse_the_flag(tmp_path, capsys):
    """--input lidar64 reads the scans as stored: a line count given to it would be silently ignored."""
    says = _error(_train("detector", KITTI, tmp_path / "run", "--input", "lidar64", "--emulate-beams", "8"), capsys)
    assert says.startswith("error: --emulate-beams: not used by a detector run (--input lidar64 reads the scans")


def test_cache_pseudo_caches_the_depth_of_the_stored_scan(sensor16, tiny_models, tmp_path, capsys):
    """--emulate-beams 0: each map is the depth net's of the scan as stored; left at 16 on a 16-line sensor's
    scans, one line names the first and the flag, before any map is written."""
    from pipeline.detector import Detector

    out = tmp_path / "pseudo"
    says = _error(["--data", str(sensor16), "--models", str(tiny_models), "--out", str(out)], capsys, cache_main)
    assert says == (f"error: {sensor16 / 'velodyne' / '000003.bin'}: points: the scan has 16 rings, not 64: it is "
                    "thinned already (emulate beams on 64-line scans only); to cache the depth of scans of a 16-line "
                    "sensor as they are, give --emulate-beams 0")
    assert not out.exists()
    argv = ["--data", str(sensor16), "--models", str(tiny_models), "--out", str(out), "--emulate-beams", "0"]
    assert cache_main(argv) == 0, capsys.readouterr().err
    frame = load_frame(sensor16, "000006", with_labels=False)
    expected, _ = Detector(tiny_models).dense_depth(frame.image, frame.points, frame.calib)
    np.testing.assert_allclose(read_depth_png(out / "000006.png"), expected, rtol=0, atol=1 / 512 + 1e-6)
    assert json.loads((out / "cache.json").read_text())["beams"] == 0
    # On a 64-line folder 0 would cache the depth of all 64 lines as a 16-line sensor's: refused by name.
    full = tmp_path / "full"
    capsys.readouterr()  # the run's progress bars
    says = _error(["--data", str(KITTI), "--models", str(tiny_models), "--out", str(full), "--frames", "1",
                   "--emulate-beams", "0"], capsys, cache_main)
    assert says == (f"error: {KITTI / 'velodyne' / '000000.bin'}: the scan has 64 lines, and --emulate-beams 0 would "
                    "cache the depth of it as stored, as a 16-line sensor's; give --emulate-beams 16 to thin such "
                    "scans")
    assert not full.exists()


@pytest.mark.parametrize(("task", "extra"), [("detector", ["--input", "lidar16"]), ("depth", [])])
def test_the_flag_refuses_64_line_scans(tmp_path, capsys, task, extra):
    """--emulate-beams 0 on a 64-line folder would train on 64 lines while the manifest says 16 (the detector's
    line-count warnings then point the wrong way): refused before any training, naming the first scan."""
    out = tmp_path / "run"
    says = _error(_train(task, KITTI, out, "--emulate-beams", "0", *extra), capsys)
    first = min(p.stem for p in (KITTI / "velodyne").glob("*.bin"))
    assert says.startswith(f"error: {KITTI / 'velodyne' / f'{first}.bin'}: the scan has 64 lines, and "
                           "--emulate-beams 0 would train on it as stored")
    assert not out.exists()


def test_a_pseudo_run_trains_on_maps_cached_with_its_own_line_count(sensor16, tiny_models, tmp_path, capsys):
    """detector --input pseudo on the sensor's own scans, from maps cached with --emulate-beams 0; maps cached from
    other scans than the run's (another --emulate-beams) are refused by name."""
    from models.cache_pseudo import run as cache_pseudo

    maps = tmp_path / "pseudo"
    cache_pseudo(sensor16, tiny_models, maps, beams=0, progress=False)
    out = tmp_path / "run"
    assert main(_train("detector", sensor16, out, "--input", "pseudo", "--pseudo-dir", str(maps),
                       "--emulate-beams", "0")) == 0
    assert math.isfinite(_log(out)[0]["train_loss"])
    capsys.readouterr()  # the run's progress bars
    split = tmp_path / "one.txt"
    split.write_text("000006\n")
    kitti_maps = tmp_path / "kitti_pseudo"
    cache_pseudo(KITTI, tiny_models, kitti_maps, split_file=split, progress=False)  # 16 lines
    says = _error(_train("detector", KITTI, tmp_path / "other", "--train-split", str(split), "--val-split", str(split),
                         "--input", "pseudo", "--pseudo-dir", str(kitti_maps), "--emulate-beams", "8"), capsys)
    assert f"--pseudo-dir {kitti_maps}: its maps were made with --emulate-beams 16 (cache.json)" in says


def test_the_exported_manifest_keeps_the_line_count(own_detector, tmp_path):
    """A model trained on a sensor's own 16-line scans is a 16-line model; one trained on scans thinned to 8 lines
    an 8-line one (the Detector's trained_lines, which the benchmarks thin their scans to)."""
    from export.exporter import ExportConfig
    from export.exporter import run as export
    from pipeline.detector import Detector, trained_lines

    out = tmp_path / "model"
    export(ExportConfig(preset="tiny", out=out, checkpoints=own_detector, parity=False, networks=("pixor",)))
    training = json.loads((out / "manifest.json").read_text())["networks"]["pixor"]["training"]
    assert training["emulate_beams"] == 0 and training["input"] == "lidar16"
    assert Detector(out).trained_lines == 16
    assert trained_lines({"input": "lidar16", "emulate_beams": 8}) == 8
    assert trained_lines({"input": "pseudo"}) == 16 and trained_lines({"input": "lidar64", "emulate_beams": 16}) == 64
