"""Shared fixtures: the real KITTI samples copied from ../shared/data (see tests/data/README.md)."""

import json
import shutil
import signal
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
