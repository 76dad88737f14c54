"""``python -m models.cache_pseudo``: the depth maps it caches, and how it answers a user's mistakes."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from models.cache_pseudo import main, recorded_sources, run
from pipeline.kitti import read_depth_png


def _kitti_copy(kitti_dir: Path, target: Path, frames: int) -> Path:
    """A KITTI folder of ``frames`` frames, each a symlink to the real frame 000006 (no copies of the data)."""
    for folder, ext in (("velodyne", ".bin"), ("image_2", ".png"), ("calib", ".txt")):
        (target / folder).mkdir(parents=True)
        for i in range(frames):
            (target / folder / f"{i:06d}{ext}").symlink_to(kitti_dir / folder / f"000006{ext}")
    return target


def _main(args: list[str], capsys: pytest.CaptureFixture) -> tuple[int, str]:
    try:
        code = main(args)
    except SystemExit as stop:  # argparse
        code = stop.code
    return code, capsys.readouterr().err


def test_caches_every_frame_and_resumes(tiny_models: Path, kitti_dir: Path, tmp_path: Path) -> None:
    """Each map is the depth net's dense depth of the frame's 64-line scan thinned to 16 lines, as the runtime's
    Detector computes it (to the PNG's 1/256 m steps)."""
    from pipeline.beams import emulate_beams
    from pipeline.detector import Detector
    from pipeline.frame import load_frame

    out = tmp_path / "pseudo"
    assert run(kitti_dir, tiny_models, out, progress=False) == 5
    frame = load_frame(kitti_dir, "000006", with_labels=False)
    expected, _ = Detector(tiny_models).dense_depth(frame.image, emulate_beams(frame.points, 16), frame.calib)
    cached = read_depth_png(out / "000006.png")
    assert cached.shape == expected.shape and cached.max() > 0
    np.testing.assert_allclose(cached, expected, rtol=0, atol=1 / 512 + 1e-6)
    assert run(kitti_dir, tiny_models, out, progress=False) == 0  # all cached: nothing recomputed


def test_frames_n_caches_the_first_frames(tiny_models: Path, kitti_dir: Path, tmp_path: Path,
                                          capsys: pytest.CaptureFixture) -> None:
    """--frames N as in the other commands: the first N frames in id order (--split-file is the same flag)."""
    out = tmp_path / "pseudo"
    code, err = _main(["--data", str(kitti_dir), "--models", str(tiny_models), "--out", str(out), "--frames", "2"],
                      capsys)
    assert code == 0, err
    assert sorted(p.name for p in out.glob("*.png")) == ["000000.png", "000001.png"]


def test_bad_inputs_get_one_line_before_anything_is_written(tiny_models: Path, kitti_dir: Path, tmp_path: Path,
                                                           capsys: pytest.CaptureFixture) -> None:
    """An --out that is (or sits under) a file, a --data without frames, a split file naming a frame
    --data lacks: exit 2 and one line naming the flag, before any map is computed or --out is made."""
    a_file = tmp_path / "notes.txt"
    a_file.write_text("mine")
    (tmp_path / "empty" / "velodyne").mkdir(parents=True)
    split = tmp_path / "split.txt"
    split.write_text("000006\n999999\n")
    out = tmp_path / "out"
    cases = [
        (["--data", str(kitti_dir), "--out", str(a_file)], f"--out {a_file}: exists and is not a directory"),
        (["--data", str(kitti_dir), "--out", f"{a_file}/pseudo"], f"{a_file} is a file, not a directory"),
        (["--data", str(tmp_path / "kitt"), "--out", str(out)], f"--data {tmp_path / 'kitt'}: not a KITTI object"),
        (["--data", str(tmp_path / "empty"), "--out", str(out)], "no frames (velodyne/*.bin)"),
        (["--data", str(kitti_dir), "--out", str(out), "--split-file", str(split)],
         f"frame 999999 (listed in --split-file {split}) has no velodyne/999999.bin"),
    ]
    # A folder of other PNGs (camera images) would have been skipped as maps made and certified by cache.json.
    images = tmp_path / "images"
    images.mkdir()
    (images / "000006.png").write_bytes((kitti_dir / "image_2" / "000006.png").read_bytes())
    cases += [
        (["--data", str(kitti_dir), "--out", str(images)],
         f"--out {images}: holds PNGs (000006.png among them) but no cache.json"),
        (["--data", str(kitti_dir), "--out", str(kitti_dir / "image_2")],
         f"--out {kitti_dir / 'image_2'}: would be written over what --data"),
    ]
    for args, says in cases:
        code, err = _main(["--models", str(tiny_models), *args], capsys)
        assert code == 2 and says in err and len(err.strip().splitlines()) == 1, (args, err)
        assert "Traceback" not in err
    assert not out.exists() and a_file.read_text() == "mine"
    assert sorted(p.name for p in images.iterdir()) == ["000006.png"]  # no cache.json written into it


def test_ctrl_c_keeps_the_finished_maps_and_the_rerun_resumes(tiny_models: Path, kitti_dir: Path,
                                                            tmp_path: Path) -> None:
    frames = 120  # symlinks; the tiny net maps about 20 a second here, so seconds remain to interrupt
    data = _kitti_copy(kitti_dir, tmp_path / "data", frames)
    out = tmp_path / "pseudo"
    command = [sys.executable, "-m", "models.cache_pseudo", "--data", str(data), "--models", str(tiny_models),
               "--out", str(out)]
    log = tmp_path / "stderr.txt"  # a file, not a pipe: a pipe lets the command run ahead of the reader
    with open(log, "w") as stderr:
        process = subprocess.Popen(command, stderr=stderr, stdout=subprocess.DEVNULL, text=True)

    def finished_maps() -> int:  # not the .tmp.png being written
        return sum(1 for p in out.glob("*.png") if p.name.count(".") == 1)

    # Wait on the maps themselves: tqdm redraws at most every 0.1 s, so a count like "2/120" may never be printed.
    deadline = time.monotonic() + 120
    while finished_maps() < 2 and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert process.poll() is None, "the command ended before it could be interrupted"
    process.send_signal(signal.SIGINT)
    code = process.wait(timeout=120)
    err = log.read_text()
    assert code == 130, err[-2000:]
    assert "interrupted" in err and "rerun the same command to resume" in err and "Traceback" not in err
    maps = sorted(p.name for p in out.glob("*.png"))
    assert 2 <= len(maps) < frames and all(name.count(".") == 1 for name in maps)  # no half-written .tmp.png
    for name in maps:
        assert read_depth_png(out / name).max() > 0
    # A map written but not yet recorded when the interrupt came (the run stops between the two) is made again.
    recorded = set(recorded_sources(out))
    assert recorded <= {name.removesuffix(".png") for name in maps} and len(recorded) >= len(maps) - 1
    assert run(data, tiny_models, out, progress=False) == frames - len(recorded)


def test_a_depth_only_export_is_not_warned_of_for_its_unused_pixor(tiny_models: Path, kitti_dir: Path, tmp_path: Path,
                                                                   caplog: pytest.LogCaptureFixture) -> None:
    """Caching runs the depth net alone: a model directory whose depth net is trained and whose PIXOR is not
    (``python -m export --checkpoints`` of a depth run's folder) gets no warning about PIXOR here, while the
    Detector that detect and the service load still warns of it; an untrained depth net is still warned of."""
    import json
    import logging
    import shutil

    from pipeline.detector import Detector

    models = tmp_path / "depth_only"
    shutil.copytree(tiny_models, models)
    manifest = json.loads((models / "manifest.json").read_text())  # as export writes a depth.pt-only folder's
    manifest["networks"]["depth"].update(weights="trained", training={"checkpoint": "depth.pt"})
    manifest["weights"] = "partially trained: depth trained, pixor initialised (untrained)"
    (models / "manifest.json").write_text(json.dumps(manifest))
    with caplog.at_level(logging.WARNING, logger="pipeline.detector"):
        assert run(kitti_dir, models, tmp_path / "pseudo", progress=False, first=1) == 1
        assert not [r for r in caplog.records if "initialised (untrained)" in r.getMessage()]
        assert Detector(models).load_warnings == [(f"{models}: pixor has initialised (untrained) weights: the "
                                                   "detections mean nothing; export trained checkpoints "
                                                   "(python -m export --checkpoints DIR)")]
        caplog.clear()
        assert run(kitti_dir, tiny_models, tmp_path / "untrained", progress=False, first=1) == 1
    assert [r.getMessage() for r in caplog.records] == [(f"{tiny_models}: depth has initialised (untrained) weights: "
                                                         "the depth maps mean nothing; export trained checkpoints "
                                                         "(python -m export --checkpoints DIR)")]
