"""simulation/ as a dataset tool: the folders third-party KITTI readers expect, whole files whatever stops a run,
and a stopped run resumed to the bytes of one that was not stopped."""

from __future__ import annotations

import errno
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

import simulation.frame
from pipeline.kitti import write_calib, write_depth_png, write_image, write_labels, write_velodyne
from simulation import RunConfig, generate_frame, run
from simulation.__main__ import main

RUN = sys.modules["simulation.run"]  # the package's `run` attribute is the function

SEED = 77
SUBS = (("image_2", ".png"), ("velodyne", ".bin"), ("calib", ".txt"), ("label_2", ".txt"), ("depth_2", ".png"))
CALIB_KEYS = ("P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo")
CALIB_VALUES = (12, 12, 12, 12, 9, 12, 12)
TYPES = {"Car", "Van", "Truck", "Pedestrian", "Person_sitting", "Cyclist", "Tram", "Misc"}
DONT_CARE = [-1.0, -1.0, -10.0, -1.0, -1.0, -1.0, -1000.0, -1000.0, -1000.0, -10.0]  # all but type and 2D box


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory):
    """Frames of SEED written file by file with pipeline.kitti's writers, as the simulator wrote them before its
    writes became atomic: the bytes every run must still produce. Made on first use, then kept."""
    folder = tmp_path_factory.mktemp("reference")
    for sub, _ in SUBS:
        (folder / sub).mkdir()

    def files(index: int) -> dict[str, bytes]:
        name = f"{index:06d}"
        if not (folder / "depth_2" / f"{name}.png").exists():
            frame = generate_frame(SEED, index)
            write_image(folder / "image_2" / f"{name}.png", frame.image)
            write_velodyne(folder / "velodyne" / f"{name}.bin", frame.points)
            write_calib(folder / "calib" / f"{name}.txt", frame.calib)
            write_labels(folder / "label_2" / f"{name}.txt", frame.objects)
            write_depth_png(folder / "depth_2" / f"{name}.png", frame.depth)
        return {f"{sub}/{name}{ext}": (folder / sub / f"{name}{ext}").read_bytes() for sub, ext in SUBS}

    return files


def written(folder: Path, index: int) -> dict[str, bytes]:
    """A frame's files in ``folder``, by path relative to it."""
    name = f"{index:06d}"
    return {f"{sub}/{name}{ext}": (folder / sub / f"{name}{ext}").read_bytes() for sub, ext in SUBS}


def hidden(folder: Path) -> list[Path]:
    """What a run left in ``folder`` besides KITTI's files: hidden names and unfinished parts."""
    return [p for p in folder.rglob("*") if p.name.startswith(".") or p.name.endswith(".part")]


def wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def check_kitti_frame(split_dir: Path, name: str) -> int:
    """Read frame ``name`` as OpenPCDet's KittiDataset and the devkit's readme do (by line position, single
    spaces, np.fromfile), assert KITTI's rules; returns the number of labelled objects checked."""
    image = cv2.imread(str(split_dir / "image_2" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
    assert image is not None and image.dtype == np.uint8 and image.shape == (375, 1242, 3)
    height, width = image.shape[:2]
    points = np.fromfile(split_dir / "velodyne" / f"{name}.bin", dtype=np.float32)
    assert points.size % 4 == 0
    points = points.reshape(-1, 4)
    assert np.isfinite(points).all() and points[:, 3].min() >= 0 and points[:, 3].max() <= 1

    lines = (split_dir / "calib" / f"{name}.txt").read_text().splitlines()
    assert [line.split(":")[0] for line in lines] == list(CALIB_KEYS)
    assert [len(line.split(" ")) - 1 for line in lines] == list(CALIB_VALUES)
    p2 = np.array(lines[2].split(" ")[1:], float).reshape(3, 4)
    r0 = np.array(lines[4].split(" ")[1:], float).reshape(3, 3)
    v2c = np.array(lines[5].split(" ")[1:], float).reshape(3, 4)

    rows = [line.split(" ") for line in (split_dir / "label_2" / f"{name}.txt").read_text().splitlines()]
    assert rows and all(len(row) == 15 for row in rows)
    kinds = [row[0] for row in rows]
    first_dont_care = kinds.index("DontCare") if "DontCare" in kinds else len(kinds)
    assert set(kinds[first_dont_care:]) <= {"DontCare"}  # OpenPCDet's infos index the objects before them
    checked = 0
    for row in rows:
        kind, values = row[0], [float(v) for v in row[1:]]
        left, top, right, bottom = values[3:7]
        if kind == "DontCare":
            assert values[:3] + values[7:] == DONT_CARE, row
            # Pixel edges of the visible pixels: at a border half a pixel outside (docs/simulation.md).
            assert -0.5 <= left < right <= width - 0.5 and -0.5 <= top < bottom <= height - 0.5, row
            continue
        assert kind in TYPES, row
        truncated, occluded, alpha = values[:3]
        h, w, l, x, y, z, rotation_y = values[7:]
        assert 0 <= truncated <= 1 and occluded in (0, 1, 2, 3), row
        assert -math.pi <= alpha <= math.pi and -math.pi <= rotation_y <= math.pi, row
        assert 0 <= left < right <= width - 1 and 0 <= top < bottom <= height - 1, row  # pixels, inside the image
        assert h > 0 and w > 0 and l > 0, row
        assert abs(wrap(rotation_y - math.atan2(x, z) - alpha)) < 0.02, row  # label values have two decimals
        if truncated > 0 or z < 5:
            continue
        # The 3D box (location = bottom centre in the rectified camera frame, h w l, rotation_y about camera y)
        # projects around the 2D box: had location been the centre, the projection would sit h/2 too low.
        c, s = math.cos(rotation_y), math.sin(rotation_y)
        corners = np.array([[dx * l / 2, -dy * h, dz * w / 2] for dx in (-1, 1) for dy in (0, 1) for dz in (-1, 1)])
        rect = corners @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]).T + [x, y, z]
        uvw = rect @ p2[:, :3].T + p2[:, 3]
        uv = uvw[:, :2] / uvw[:, 2:]
        # The 2D box is the silhouette, inside the projected box up to the label's 1 cm rounding and the tilt
        # between the LiDAR's z-aligned box and KITTI's y-aligned one (up to 5 px in 600 frames of data/sim).
        tol = 2.0 + 0.02 * (uv[:, 1].max() - uv[:, 1].min())
        assert uv[:, 0].min() - tol <= left and right <= uv[:, 0].max() + tol, row
        assert uv[:, 1].min() - tol <= top and bottom <= uv[:, 1].max() + tol, row
        checked += 1
    for rotation in (r0, v2c[:, :3]):  # rotations, as the devkit's transforms assume
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-6)
    return checked


def test_a_kitti_root_that_openpcdet_and_mmdetection3d_read(tmp_path: Path, reference) -> None:
    """ROOT/training/{image_2,velodyne,calib,label_2}/NNNNNN.* and ROOT/ImageSets/{train,val}.txt, as OpenPCDet's
    KittiDataset and mmdetection3d's KITTI converter read them (the lists used to go to ROOT/training/ImageSets,
    where neither looks); every file read back by their rules."""
    root = tmp_path / "kitti"
    run(RunConfig(out=root / "training", frames=2, seed=SEED, imagesets=root / "ImageSets", progress=False))
    run(RunConfig(out=root / "training", frames=1, seed=SEED, start=2, split="val", imagesets=root / "ImageSets",
                  progress=False))
    assert (root / "ImageSets" / "train.txt").read_text() == "000000\n000001\n"
    assert (root / "ImageSets" / "val.txt").read_text() == "000002\n"
    assert not (root / "training" / "ImageSets").exists()
    assert sorted(p.name for p in (root / "training").iterdir()) == sorted(sub for sub, _ in SUBS)
    assert sum(check_kitti_frame(root / "training", f"{i:06d}") for i in range(3)) >= 5
    assert hidden(root) == []
    for index in range(3):  # atomic writes, same bytes
        assert written(root / "training", index) == reference(index)
    (tmp_path / "file").write_text("")
    with pytest.raises(ValueError, match="--imagesets .*file: exists and is not a directory"):
        run(RunConfig(out=tmp_path / "other", frames=1, seed=SEED, imagesets=tmp_path / "file", progress=False))
    assert not (tmp_path / "other").exists()


def test_a_full_disk_mid_frame_leaves_no_cut_off_file_and_lists_the_frames_finished(
        tmp_path: Path, reference, monkeypatch: pytest.MonkeyPatch) -> None:
    """The disk fills while frame 1's scan is written: that frame has no file at all (a cut-off scan of whole
    rows used to stay, readable as a shorter scan, beside its image), frame 0 is listed, and the rerun makes
    frame 1 to the bytes of an uninterrupted run."""
    write_velodyne = simulation.frame.write_velodyne

    def disk_full(path: Path, points: np.ndarray) -> None:
        if Path(path).name != "000001.bin":
            return write_velodyne(path, points)
        Path(path).write_bytes(points[: points.shape[0] // 2].astype("<f4").tobytes())  # whole rows, then full
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(simulation.frame, "write_velodyne", disk_full)
    out = tmp_path / "sim"
    with pytest.raises(OSError, match="No space left on device"):
        run(RunConfig(out=out, frames=2, seed=SEED, progress=False))
    assert [p.relative_to(out).as_posix() for p in sorted(out.rglob("000001.*"))] == []
    assert hidden(out) == []
    assert (out / "ImageSets" / "train.txt").read_text() == "000000\n"
    monkeypatch.undo()
    resumed = run(RunConfig(out=out, frames=2, seed=SEED, progress=False))
    assert len(resumed.seconds_per_frame) == 1
    assert written(out, 0) == reference(0) and written(out, 1) == reference(1)


def test_sigterm_stops_like_ctrl_c_and_the_rerun_matches_an_uninterrupted_run(tmp_path: Path, reference) -> None:
    """`timeout` and a CI job's cancel send SIGTERM to the command: it used to die at once (status -15, no split
    list). Now it finishes the frames being made, lists them, says so in one line and exits 143; the rerun
    resumes, and every frame has the bytes it would have had."""
    out = tmp_path / "sim"
    command = [sys.executable, "-m", "simulation", "--out", str(out), "--frames", "12", "--seed", str(SEED),
               "--workers", "2", "--no-progress"]
    log = tmp_path / "stderr.txt"
    with open(log, "w") as stderr:
        process = subprocess.Popen(command, stderr=stderr, stdout=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + 120
    while not list((out / "depth_2").glob("*.png")) and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert process.poll() is None, "the run ended before it could be stopped"
    process.send_signal(signal.SIGTERM)  # to the parent alone, as `timeout` does
    code = process.wait(timeout=120)
    err = log.read_text()
    assert code == 143 and "Traceback" not in err, err[-2000:]
    assert err.count(f"terminated: the frames finished are in {out}; rerun the same command to resume") == 1
    finished = sorted(p.stem for p in (out / "depth_2").glob("*.png"))  # one at least: waited for above
    assert (out / "ImageSets" / "train.txt").read_text().split() == finished
    assert hidden(out) == []
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:  # the workers end with their parent
        try:
            os.killpg(process.pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        pytest.fail("worker processes outlived the stopped run")
    upto = len(finished) + 1
    resumed = run(RunConfig(out=out, frames=upto, seed=SEED, workers=2, progress=False))
    assert len(resumed.seconds_per_frame) == upto - len(finished)
    for index in range(upto):
        assert written(out, index) == reference(index), index


_make = RUN._make


def _killed_on_frame_one(seed: int, index: int, out: Path) -> float:
    """A worker's job that dies on frame 1 as under the OOM killer (module level: the pool pickles it by name)."""
    if index == 1:
        os._exit(137)
    return _make(seed, index, out)


def test_a_worker_killed_mid_run_ends_it_with_one_line(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture) -> None:
    """A worker killed outright (the OOM killer, `kill -9`) used to end the run in a BrokenProcessPool traceback;
    now one line says so, and the frames finished are listed for the rerun."""
    monkeypatch.setattr(RUN, "_make", _killed_on_frame_one)  # the forked workers inherit it
    out = tmp_path / "sim"
    code = main(["--out", str(out), "--frames", "2", "--seed", str(SEED), "--workers", "2", "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    says = (f"error: a worker process ended abruptly (killed, or out of memory?); the frames finished are in {out}; "
            "rerun the same command to resume")
    assert code == 2 and err == [says], err
    assert (out / "ImageSets" / "train.txt").read_text() == "000000\n"
    assert not list(out.rglob("000001.*")) and hidden(out) == []
