"""simulation/: generated frames are KITTI-shaped, self-consistent across sensors, labelled from the render."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from pipeline.beams import emulate_beams, recover_rings
from pipeline.boxes import labels_to_boxes, points_in_boxes
from pipeline.kitti import read_calib, read_depth_png, read_image, read_labels, read_velodyne
from simulation import RunConfig, generate_frame, run
from simulation.constants import BASE_P2, BASE_R0_RECT, BASE_TR_VELO_TO_CAM, IMAGE_HW, OCCLUSION_LEVELS
from simulation.labels import occlusion_level, visibility

SEED = 2024
FRAMES = 3
KITTI_TYPES = {"Car", "Van", "Pedestrian", "Cyclist", "DontCare"}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three frames written by the public run() (one worker)."""
    out = tmp_path_factory.mktemp("sim")
    run(RunConfig(out=out, frames=FRAMES, seed=SEED, progress=False))
    return out


@pytest.fixture(scope="module")
def frame():
    """Frame 0 in memory, with its scene and render."""
    return generate_frame(SEED, 0)


def _ids(dataset: Path) -> list[str]:
    return (dataset / "ImageSets" / "train.txt").read_text().split()


def test_files_read_back_through_pipeline_readers(dataset: Path) -> None:
    ids = _ids(dataset)
    assert ids == ["000000", "000001", "000002"]
    for name in ids:
        image = read_image(dataset / "image_2" / f"{name}.png")
        assert image.shape == (*IMAGE_HW, 3) and image.std() > 10
        scan = read_velodyne(dataset / "velodyne" / f"{name}.bin")
        assert scan.dropped_nonfinite == 0
        assert 90_000 <= scan.points.shape[0] <= 135_000
        assert 0.0 <= scan.points[:, 3].min() and scan.points[:, 3].max() < 1.0
        read_calib(dataset / "calib" / f"{name}.txt")
        objects = read_labels(dataset / "label_2" / f"{name}.txt")
        assert {o.type for o in objects} <= KITTI_TYPES
        assert any(o.type == "Car" for o in objects)
        depth = read_depth_png(dataset / "depth_2" / f"{name}.png")
        assert depth.shape == IMAGE_HW
        assert (depth > 0).mean() > 0.5  # dense: everything but the sky


def test_base_calibration_is_real_kitti(kitti_dir: Path) -> None:
    real = read_calib(kitti_dir / "calib" / "000003.txt")
    np.testing.assert_allclose(BASE_P2, real.P2)
    np.testing.assert_allclose(BASE_R0_RECT, real.R0_rect)
    np.testing.assert_allclose(BASE_TR_VELO_TO_CAM, real.Tr_velo_to_cam)


def test_calibration_varies_slightly_between_frames(dataset: Path) -> None:
    calibs = [read_calib(dataset / "calib" / f"{n}.txt") for n in _ids(dataset)]
    focal = [c.P2[0, 0] for c in calibs]
    assert len(set(focal)) == len(focal)
    assert all(abs(f - BASE_P2[0, 0]) < 15 for f in focal)
    for c in calibs:  # the LiDAR sits about 1.73 m up, the camera about 1.65 m: their offset stays KITTI's
        np.testing.assert_allclose(c.Tr_velo_to_cam[:, 3], BASE_TR_VELO_TO_CAM[:, 3], atol=0.05)


def test_car_lidar_points_project_inside_their_2d_boxes(dataset: Path) -> None:
    checked = 0
    for name in _ids(dataset):
        calib = read_calib(dataset / "calib" / f"{name}.txt")
        points = read_velodyne(dataset / "velodyne" / f"{name}.bin").points
        cars = [o for o in read_labels(dataset / "label_2" / f"{name}.txt") if o.type == "Car"]
        boxes = labels_to_boxes(cars, calib)
        inside = points_in_boxes(points, boxes)
        for k, car in enumerate(cars):
            on_car = points[inside[:, k] & (points[:, 2] > boxes[k, 2] - boxes[k, 5] / 2 + 0.15)]
            uv, depth = calib.velo_to_image(on_car[:, :3])
            in_image = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= IMAGE_HW[1] - 1) & (uv[:, 1] >= 0) & (
                uv[:, 1] <= IMAGE_HW[0] - 1)
            uv = uv[in_image]
            left, top, right, bottom = car.bbox
            tol = 1.0  # pixel rounding of the silhouette and the label's two decimals
            assert (uv[:, 0] >= left - tol).all() and (uv[:, 0] <= right + tol).all(), name
            assert (uv[:, 1] >= top - tol).all() and (uv[:, 1] <= bottom + tol).all(), name
            checked += int(uv.shape[0] > 0)
    assert checked >= 3


def test_rings_recovered_and_16_line_emulation(dataset: Path) -> None:
    for name in _ids(dataset):
        points = read_velodyne(dataset / "velodyne" / f"{name}.bin").points
        rings = recover_rings(points)
        assert rings.method == "azimuth-wrap" and rings.n_rings == 64
        assert rings.elevation_deg.max() == pytest.approx(2.0, abs=0.3)
        assert rings.elevation_deg.min() == pytest.approx(-24.9, abs=0.3)
        kept = emulate_beams(points, beams=16)
        assert recover_rings(kept).n_rings == 16
        assert 0.22 <= kept.shape[0] / points.shape[0] <= 0.28


def test_dense_depth_agrees_with_lidar(dataset: Path) -> None:
    """Both sensors see one scene: LiDAR points land on the depth ground truth."""
    name = _ids(dataset)[0]
    calib = read_calib(dataset / "calib" / f"{name}.txt")
    points = read_velodyne(dataset / "velodyne" / f"{name}.bin").points
    depth = read_depth_png(dataset / "depth_2" / f"{name}.png")
    uv, d = calib.velo_to_image(points[:, :3])
    cols, rows = np.rint(uv[:, 0]), np.rint(uv[:, 1])
    ok = (d > 1) & (cols >= 0) & (cols < IMAGE_HW[1]) & (rows >= 0) & (rows < IMAGE_HW[0])
    gt = depth[rows[ok].astype(int), cols[ok].astype(int)]
    rel = np.abs(gt - d[ok]) / d[ok]
    assert ok.sum() > 10_000
    assert np.median(rel) < 0.01  # the rest: occlusion boundaries seen from two viewpoints


def test_occlusion_and_truncation_agree_with_render(frame) -> None:
    """Label levels follow the visible fraction measured independently from the written depth map."""
    calib, depth = frame.calib, frame.depth
    vis = visibility(frame.scene, frame.render, calib)
    labelled = [o for o in frame.objects if o.type != "DontCare"]
    boxes = labels_to_boxes(labelled, calib)
    assert len(labelled) >= 3
    for obj, box in zip(labelled, boxes):
        # Find the actor this label came from (same box centre).
        index = int(np.argmin([np.linalg.norm(a.box[:2] - box[:2]) for a in frame.scene.actors]))
        (rows, cols), mask = frame.render.cast.amodal[index]
        rr, cc = np.nonzero(mask)
        d = depth[rows][:, cols][rr, cc]
        pts = calib.image_to_velo(cc + cols.start, rr + rows.start, d)
        grown = box.copy()
        grown[3:6] += 0.05
        on_object = points_in_boxes(pts, grown[None])[:, 0] & (d > 0)
        visible = on_object.mean()
        near_threshold = np.min(np.abs(1 - visible - np.asarray(OCCLUSION_LEVELS))) < 0.02
        assert near_threshold or occlusion_level(1 - visible) == obj.occluded, (obj, visible)
        assert abs(vis[index].visible_pixels / vis[index].amodal_pixels - visible) < 0.02
        # Truncation: inside the image ⇔ box clear of the borders.
        left, _, right, bottom = obj.bbox
        touches = left <= 0.5 or right >= IMAGE_HW[1] - 1.5 or bottom >= IMAGE_HW[0] - 1.5
        if obj.truncated == 0.0:
            assert not (left <= 0.5 or right >= IMAGE_HW[1] - 1.5)
        if obj.truncated >= 0.1:
            assert touches


def test_labels_follow_kitti_rules(dataset: Path) -> None:
    for name in _ids(dataset):
        calib = read_calib(dataset / "calib" / f"{name}.txt")
        objects = read_labels(dataset / "label_2" / f"{name}.txt")
        real = [o for o in objects if o.type != "DontCare"]
        assert objects[len(real):] == [o for o in objects if o.type == "DontCare"]  # DontCare last
        for o in real:
            assert o.occluded in (0, 1, 2) and 0.0 <= o.truncated <= 1.0
            assert np.hypot(*labels_to_boxes([o], calib)[0, :2]) <= 75.5
            assert -np.pi <= o.alpha <= np.pi
        for o in (o for o in real if o.type == "Car"):
            h, w, l = o.dimensions
            assert h > 1.2 and h < 1.9 and w > 1.3 and w < 1.9 and l > 2.9 and l < 4.8


def test_same_seed_same_bytes_any_workers_different_seed_differs(dataset: Path, tmp_path: Path) -> None:
    again = tmp_path / "again"
    run(RunConfig(out=again, frames=2, seed=SEED, start=1, workers=2, progress=False))
    for sub, ext in (("image_2", "png"), ("velodyne", "bin"), ("calib", "txt"), ("label_2", "txt"),
                     ("depth_2", "png")):
        for name in ("000001", "000002"):
            assert (again / sub / f"{name}.{ext}").read_bytes() == (dataset / sub / f"{name}.{ext}").read_bytes()
    other = generate_frame(SEED + 1, 1)
    mine = read_velodyne(dataset / "velodyne" / "000001.bin").points
    assert other.points.shape != mine.shape or not np.array_equal(other.points, mine)
    assert not np.array_equal(other.image, read_image(dataset / "image_2" / "000001.png"))


def test_resuming_needs_the_same_seed_and_extending_keeps_the_list(dataset: Path, tmp_path: Path) -> None:
    """A folder is resumed or extended only with the seed that wrote it (frames already there are not
    regenerated, so another seed would mix two data sets), and the split list keeps every id it had."""
    import shutil
    import subprocess
    import sys

    folder = tmp_path / "sim"
    shutil.copytree(dataset, folder)
    with pytest.raises(ValueError, match=f"frame 000000 there is not the one seed {SEED + 1} makes"):
        run(RunConfig(out=folder, frames=FRAMES + 1, seed=SEED + 1, progress=False))
    assert not (folder / "velodyne" / f"{FRAMES:06d}.bin").exists()  # refused before writing anything
    run(RunConfig(out=folder, frames=1, seed=SEED, start=FRAMES, progress=False))  # one more frame
    assert _ids(folder) == [f"{i:06d}" for i in range(FRAMES + 1)]
    done = subprocess.run([sys.executable, "-m", "simulation", "--out", str(folder), "--frames", "2", "--seed",
                           str(SEED), "--no-progress"], capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0 and "all 2 frames were already in" in done.stdout, done.stderr
    assert _ids(folder) == [f"{i:06d}" for i in range(FRAMES + 1)]
    # Frames added elsewhere in the folder (--start) with another seed: the folder's own frames are checked too.
    with pytest.raises(ValueError, match=f"frame 000000 there is not the one seed {SEED + 1} makes"):
        run(RunConfig(out=folder, frames=1, seed=SEED + 1, start=FRAMES + 5, progress=False))
    assert not (folder / "velodyne" / f"{FRAMES + 5:06d}.bin").exists()


def test_ctrl_c_stops_every_worker_with_one_line_and_keeps_whole_frames(tmp_path: Path) -> None:
    """Ctrl-C reaches the whole process group: the workers leave it to the parent, which says it once (no
    traceback from any process) and exits 130; every frame on disk is whole, and the rerun resumes."""
    import signal
    import subprocess
    import sys
    import time

    out, frames = tmp_path / "sim", 40
    command = [sys.executable, "-m", "simulation", "--out", str(out), "--frames", str(frames), "--seed", str(SEED),
               "--workers", "2", "--no-progress"]
    log = tmp_path / "stderr.txt"
    with open(log, "w") as stderr:  # the workers' own stderr included
        process = subprocess.Popen(command, stderr=stderr, stdout=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + 120
    while len(list((out / "depth_2").glob("*.png"))) < 2 and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert process.poll() is None, "the run ended before it could be interrupted"
    os.killpg(process.pid, signal.SIGINT)  # as a terminal's Ctrl-C: the parent and its workers
    code = process.wait(timeout=120)
    err = log.read_text()
    assert code == 130 and "Traceback" not in err, err[-2000:]
    assert err.count("interrupted:") == 1
    assert f"interrupted: the frames finished are in {out}; rerun the same command to resume" in err
    finished = sorted(p.stem for p in (out / "depth_2").glob("*.png") if p.name.count(".") == 1)
    assert 2 <= len(finished) < frames
    assert _ids(out) == finished  # the finished frames are listed, usable as they are
    for name in finished:  # each frame whose depth map is there has all its files
        assert all((out / sub / f"{name}{ext}").is_file() for sub, ext in (
            ("image_2", ".png"), ("velodyne", ".bin"), ("calib", ".txt"), ("label_2", ".txt")))
    upto = int(finished[-1]) + 2  # one frame past the last finished
    resumed = run(RunConfig(out=out, frames=upto, seed=SEED, progress=False))
    assert len(resumed.seconds_per_frame) == upto - len(finished)  # only the frames not finished before


def test_a_folder_of_real_kitti_frames_is_never_written_over(kitti_dir: Path, tmp_path: Path) -> None:
    """KITTI's folders have every file of a frame but depth_2, so each frame counted as not made yet and was
    overwritten with a synthetic one; now the run is refused and the files stay as they were."""
    import shutil
    import subprocess
    import sys

    folder = tmp_path / "kitti"
    shutil.copytree(kitti_dir, folder)
    before = {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}
    folders = sorted(p for p in folder.rglob("*") if p.is_dir())
    done = subprocess.run([sys.executable, "-m", "simulation", "--out", str(folder), "--frames", "1", "--seed",
                           str(SEED), "--no-progress"], capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert (f"{folder}: frame 000000 there is not the one seed {SEED} makes ({folder / 'calib' / '000000.txt'} "
            "differs)") in done.stderr
    assert {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()} == before
    assert sorted(p for p in folder.rglob("*") if p.is_dir()) == folders  # no empty depth_2/ left in it either


def test_a_frame_cut_off_by_a_killed_run_is_made_again(dataset: Path, tmp_path: Path) -> None:
    """A run killed while writing leaves a frame's first files, the last one cut short: that frame is this
    seed's, so the rerun makes it whole."""
    folder = tmp_path / "sim"
    for sub, ext in (("image_2", "png"), ("velodyne", "bin")):
        (folder / sub).mkdir(parents=True)
        data = (dataset / sub / f"000000.{ext}").read_bytes()
        (folder / sub / f"000000.{ext}").write_bytes(data if sub == "image_2" else data[: len(data) // 3])
    result = run(RunConfig(out=folder, frames=1, seed=SEED, progress=False))
    assert len(result.seconds_per_frame) == 1
    for sub, ext in (("image_2", "png"), ("velodyne", "bin"), ("calib", "txt"), ("label_2", "txt"), ("depth_2", "png")):
        assert (folder / sub / f"000000.{ext}").read_bytes() == (dataset / sub / f"000000.{ext}").read_bytes()
    other = tmp_path / "other"
    (other / "velodyne").mkdir(parents=True)
    (other / "velodyne" / "000000.bin").write_bytes(b"\0" * 64)  # not what the seed writes
    with pytest.raises(ValueError, match="velodyne/000000.bin differs"):
        run(RunConfig(out=other, frames=1, seed=SEED, progress=False))


def test_bad_run_options_are_refused_before_any_folder_is_made(tmp_path: Path) -> None:
    """A negative seed, a split name that is a path, and an --out that is a file: one line each, nothing written."""
    with pytest.raises(ValueError, match="--seed: must be 0 or more"):
        run(RunConfig(out=tmp_path / "a", frames=1, seed=-1, progress=False))
    with pytest.raises(ValueError, match="--split: '../evil' names a list file"):
        run(RunConfig(out=tmp_path / "b", frames=1, seed=1, split="../evil", progress=False))
    (tmp_path / "c").write_text("")
    with pytest.raises(ValueError, match="exists and is not a directory"):
        run(RunConfig(out=tmp_path / "c", frames=1, seed=1, progress=False))
    with pytest.raises(ValueError, match=r"--start 999999 --frames 2: frame ids end at 999999 \(KITTI's six digits\)"):
        run(RunConfig(out=tmp_path / "d", frames=2, seed=1, start=999_999, progress=False))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c"]
