"""Shared fixtures: the real KITTI samples copied from ../shared/data (see tests/data/README.md)."""

import json
import shutil
import signal
from collections.abc import Callable
from pathlib import Path

import pytest

DATA = Path(__file__).parent / "data"
KITTI = DATA / "kitti" / "training"
FRAMES = ["000000", "000001", "000003", "000004", "000006"]


def pytest_configure(config) -> None:
    """Ctrl-C tests need a SIGINT their commands can catch. A shell starts background jobs (`make test &`)
    with SIGINT ignored, and an ignored signal stays ignored through exec, so every command the tests start would
    ignore it too; Python's own handler here is reset to the default in each child instead."""
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(scope="session")
def kitti_dir() -> Path:
    return KITTI


@pytest.fixture(scope="session")
def depth_completion_dir() -> Path:
    return DATA / "depth_completion"


@pytest.fixture
def make_drive(depth_completion_dir: Path, tmp_path: Path) -> Callable[..., Path]:
    """Makes depth-completion drives in the flat layout (pipeline/depth_completion.py) under ``tmp_path``: copies of
    the real sample frame under the ids asked for, in ``date/NAME`` beside the drive's raw calibration files
    (``calib_cam_to_cam.txt``, ``calib_velo_to_cam.txt``, written from kitti/training/calib/000003.txt, the same
    recording day's), or with ``calib=False`` in ``nocalib/NAME`` without them."""
    from pipeline.kitti import read_calib

    def numbers(matrix) -> str:
        return " ".join(f"{v:.9e}" for v in matrix.ravel())

    calib = read_calib(KITTI / "calib" / "000003.txt")
    date = tmp_path / "date"
    date.mkdir()
    (date / "calib_cam_to_cam.txt").write_text(f"R_rect_00: {numbers(calib.R0_rect)}\nP_rect_02: {numbers(calib.P2)}\n")
    (date / "calib_velo_to_cam.txt").write_text(f"R: {numbers(calib.Tr_velo_to_cam[:, :3])}\n"
                                                f"T: {numbers(calib.Tr_velo_to_cam[:, 3])}\n")

    def make(name: str = "drive", frame_ids: tuple[str, ...] = ("0000000005",), calib: bool = True) -> Path:
        drive = (date if calib else tmp_path / "nocalib") / name
        for folder in ("image_02", "velodyne_raw", "groundtruth"):
            (drive / folder).mkdir(parents=True)
            for frame_id in frame_ids:
                shutil.copy(depth_completion_dir / folder / "0000000005.png", drive / folder / f"{frame_id}.png")
        return drive

    return make


@pytest.fixture(scope="session")
def tiny_models(tmp_path_factory) -> Path:
    """A tiny-preset model directory exported once per test session (initialised weights)."""
    from export.exporter import ExportConfig, run

    out = tmp_path_factory.mktemp("tiny_models")
    run(ExportConfig(preset="tiny", out=out, parity=False))
    return out


def lidar_only_models(tiny_models: Path, folder: Path) -> Path:
    """A LiDAR-only model directory in ``folder``: the tiny pixor.onnx with its manifest entry alone."""
    folder.mkdir()
    shutil.copy(tiny_models / "pixor.onnx", folder)
    manifest = json.loads((tiny_models / "manifest.json").read_text())
    del manifest["networks"]["depth"]
    manifest["files"] = {"pixor.onnx": manifest["files"]["pixor.onnx"]}
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder


def object_folder_with_depth(folder: Path, frame_id: str) -> Path:
    """A KITTI object folder at ``folder`` (copies of the bundled frames) whose ``depth_2/`` holds ``frame_id``'s
    64-line scan projected as its ground truth: what ``accuracy.py --depth`` reads, labels and all."""
    from pipeline.calib import sparse_depth_map
    from pipeline.frame import load_frame
    from pipeline.kitti import write_depth_png

    for sub in ("image_2", "velodyne", "calib", "label_2"):
        shutil.copytree(KITTI / sub, folder / sub)
    (folder / "depth_2").mkdir()
    frame = load_frame(KITTI, frame_id)
    write_depth_png(folder / "depth_2" / f"{frame_id}.png", sparse_depth_map(frame.points, frame.calib, frame.image_hw))
    return folder
