"""benchmarks/accuracy.py dataset modes: the detector over a KITTI folder, and depth metrics."""

import dataclasses
import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from evaluation.harness import run_depth, run_detection
from evaluation.kitti_eval import evaluate_by_distance
from evaluation.labels import LabelArrays
from pipeline.calib import depth_crop, sparse_depth_map
from pipeline.errors import InputError
from pipeline.frame import load_frame
from pipeline.kitti import read_depth_png, read_labels, write_depth_png
from pipeline.provenance import code_version
from pipeline.render import NO_TRUTH_BGR
from simulation.run import RunConfig
from simulation.run import run as simulate
from tests.conftest import FRAMES, KITTI, lidar_only_models
from tests.test_bad_files import _object_folder

ACCURACY = Path(__file__).resolve().parents[1] / "benchmarks" / "accuracy.py"


def _accuracy(*args: str | Path, timeout: int = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(ACCURACY), *map(str, args), "--no-progress"],
                          capture_output=True, text=True, timeout=timeout, check=False)


def _frames_file(folder: Path, *frame_ids: str) -> Path:
    path = folder / "frames.txt"
    path.write_text("".join(f"{frame_id}\n" for frame_id in frame_ids))
    return path


def test_detection_run_then_evaluation_end_to_end(tiny_models, tmp_path):
    result = subprocess.run(
        [sys.executable, str(ACCURACY), "--data", str(KITTI), "--models", str(tiny_models),
         "--input", "lidar16+camera", "--score-threshold", "0.0", "--out", str(tmp_path / "run"),
         "--json", str(tmp_path / "ap.json"), "--no-progress"],
        capture_output=True, text=True, timeout=600, check=False,
    )
    assert result.returncode == 0, result.stderr
    for frame_id in FRAMES:
        lines = (tmp_path / "run" / "data" / f"{frame_id}.txt").read_text().splitlines()
        assert lines and all(len(line.split()) == 16 for line in lines)
    document = json.loads((tmp_path / "ap.json").read_text())
    for metric in ("bev", "3d", "bbox"):
        for iou in ("0.7", "0.5"):
            for interp in ("R40", "R11"):
                values = document["Car"][metric][iou][interp]
                assert len(values) == 3 and all(0 <= v <= 100 for v in values)
    assert "Car AP" in result.stdout


def test_detection_run_with_depth_from_files_and_distance_bands(tiny_models, tmp_path):
    """--depth-dir feeds PIXOR another depth source (here each frame's 64-line scan projected into the image),
    and the JSON says where the depth came from; --by-distance adds the bands."""
    depth_dir = tmp_path / "depth"
    depth_dir.mkdir()
    for frame_id in FRAMES:
        frame = load_frame(KITTI, frame_id)
        write_depth_png(depth_dir / f"{frame_id}.png", sparse_depth_map(frame.points, frame.calib, frame.image_hw))
    result = subprocess.run(
        [sys.executable, str(ACCURACY), "--data", str(KITTI), "--models", str(tiny_models),
         "--input", "lidar16+camera", "--depth-dir", str(depth_dir), "--by-distance", "0,30,80",
         "--score-threshold", "0.0", "--out", str(tmp_path / "run"), "--json", str(tmp_path / "ap.json"),
         "--plots", str(tmp_path / "plots"), "--no-progress"],
        capture_output=True, text=True, timeout=600, check=False,
    )
    assert result.returncode == 0, result.stderr
    assert f"depth from {depth_dir} instead of the depth network" in result.stdout
    # Where the JSON and each picture went, as the result-files mode says it.
    written = [line for line in result.stdout.splitlines() if line.startswith(("JSON: ", "plot: "))]
    assert written == [f"JSON: {tmp_path / 'ap.json'}",
                       *(f"plot: {tmp_path / 'plots' / f'pr_car_{d}.png'}" for d in ("easy", "moderate", "hard")),
                       f"plot: {tmp_path / 'plots' / 'ap_by_distance.png'}"]
    document = json.loads((tmp_path / "ap.json").read_text())
    assert document["depth_source"].startswith(str(depth_dir))
    assert [band["range_m"] for band in document["by_distance"]] == [[0, 30], [30, 80]]
    lidar_only = lidar_only_models(tiny_models, tmp_path / "lidar")  # a LiDAR-only model directory has no depth to replace
    with pytest.raises(InputError, match="--depth-dir: only the camera pipeline"):
        run_detection(KITTI, lidar_only, "lidar16", tmp_path / "x", depth_dir=depth_dir)


def test_a_skipped_frame_fails_the_evaluation_and_no_old_result_stands_in(tiny_models, tmp_path):
    """A frame whose scan is unusable is named, its cars count as missed, and the command exits 1; a result
    file left for it by an earlier run into the same folder is removed, not scored as this run's."""
    data = _object_folder(tmp_path / "kitti")
    (data / "velodyne" / "000006.bin").write_bytes(b"\0" * 1000)  # not a multiple of 16 bytes
    stale = tmp_path / "run" / "data" / "000006.txt"
    stale.parent.mkdir(parents=True)
    # A perfect old result: scored, it would lift the table.
    stale.write_text("".join(line + " 1.0\n" for line in (KITTI / "label_2" / "000006.txt").read_text().splitlines()))
    result = _accuracy("--data", data, "--models", tiny_models, "--input", "lidar16+camera", "--out", tmp_path / "run",
                       "--json", tmp_path / "ap.json")
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert f"{data / 'velodyne' / '000006.bin'}" in result.stderr and "(frame 000006 skipped; removed its result file" in result.stderr
    assert "1 frame(s) skipped (each named above with its reason): 000006; the table counts their cars as missed" in result.stderr
    assert not stale.exists() and "Car AP" in result.stdout
    # Counted without detections because the detector skipped it, not because of a flag the user never gave.
    assert "counted as frames without detections (frames the detector skipped)" in result.stdout, result.stdout
    assert "--missing-as-empty" not in result.stdout
    assert json.loads((tmp_path / "ap.json").read_text())["frames"] == 2


def test_a_run_whose_every_frame_is_skipped_says_so(tmp_path, capfd):
    """With no frame left to score, the error says that every frame was skipped (each was named before), not
    that a result folder is missing."""
    data = _object_folder(tmp_path / "kitti", ("000006",))
    (data / "image_2" / "000006.png").write_bytes(b"\x89PNG\r\n")  # cut off after 6 bytes
    with pytest.raises(InputError, match=r"all 1 frame\(s\) skipped \(each named above with its reason\): "
                                         r"nothing to evaluate"):
        run_detection(data, ACCURACY.parents[1] / "weights" / "edge", "lidar16+camera", tmp_path / "run",
                      progress=False)
    named = capfd.readouterr().err
    assert f"{data / 'image_2' / '000006.png'}" in named and "(frame 000006 skipped" in named
    assert not (tmp_path / "run" / "data" / "000006.txt").exists()


def test_a_broken_first_scan_is_refused_as_broken_not_as_a_sensors_line_count(tmp_path):
    """The check that the first scan thins to 16 lines runs before any model: a scan that cannot be read is
    named once by its reader, not taken for a 16-line sensor's (no advice to give --emulate-beams 0)."""
    data = _object_folder(tmp_path / "kitti", ("000006",))
    scan = data / "velodyne" / "000006.bin"
    scan.write_bytes(b"\0" * 1000)  # not a multiple of 16 bytes
    with pytest.raises(InputError) as refused:
        run_detection(data, ACCURACY.parents[1] / "weights" / "edge-lidar16", "lidar16", tmp_path / "run",
                      progress=False)
    assert str(refused.value).startswith(f"{scan}: size 1000 bytes is not a multiple of 16")
    assert str(refused.value).count(str(scan)) == 1 and "--emulate-beams" not in str(refused.value)


def test_a_16_line_row_refuses_64_line_scans_taken_as_stored(tmp_path):
    """--emulate-beams 0 says the scans are a 16-line sensor's own: on KITTI's 64-line scans the 16-line rows are
    refused before any model runs (as training and the pseudo-depth cache refuse them), not scored on 64 lines
    with a warning a frame; the 64-line row takes the same scans as they are."""
    for model, input_mode in (("edge-lidar16", "lidar16"), ("edge", "lidar16+camera")):
        with pytest.raises(InputError, match=r"000003\.bin: the scan has 64 lines, and --emulate-beams 0 would "
                                             r"evaluate it as stored"):
            run_detection(KITTI, ACCURACY.parents[1] / "weights" / model, input_mode, tmp_path / input_mode,
                          frames=["000003"], beams=0, progress=False)
        assert not (tmp_path / input_mode).exists()
    run = run_detection(KITTI, ACCURACY.parents[1] / "weights" / "edge-lidar64", "lidar64", tmp_path / "lidar64",
                        frames=["000003"], beams=0, progress=False)
    assert (run.results / "000003.txt").is_file() and not run.skipped


def test_a_run_warns_of_its_own_score_threshold_only_when_it_cuts(tiny_models, tmp_path, caplog):
    """The detector's run knows its threshold: 0.05 (the default) gets no warning whatever the lowest score
    written, 0.5 (pipeline.detect's default) one line saying what it costs."""
    for threshold, warned in (("0.05", False), ("0.5", True)):
        result = _accuracy("--data", KITTI, "--models", tiny_models, "--input", "lidar16+camera", "--frames", "1",
                           "--score-threshold", threshold, "--out", tmp_path / threshold)
        assert result.returncode == 0, result.stderr
        assert ("--score-threshold 0.50 leaves out the low-score detections" in result.stderr) is warned
        assert "the lowest Car score" not in result.stderr

    # Its own results are judged by the threshold, not by their lowest score, even when that is high.
    import dataclasses
    import logging

    from benchmarks.accuracy import LabelEvalConfig, _warn_if_cut_at_a_score
    from evaluation.frames import load_label_dirs
    from pipeline.kitti import read_labels, write_labels

    results = tmp_path / "high"
    results.mkdir()
    for label in sorted((KITTI / "label_2").glob("*.txt")):
        cars = [o for o in read_labels(label) if o.type == "Car"]
        write_labels(results / label.name, [dataclasses.replace(o, score=0.9) for o in cars])
    labels = load_label_dirs(KITTI / "label_2", results)
    for detector, warned in (({"score_threshold": 0.05}, False), (None, True)):
        with caplog.at_level(logging.WARNING):
            caplog.clear()
            _warn_if_cut_at_a_score(labels, LabelEvalConfig(KITTI / "label_2", results, detector=detector))
        assert ("the lowest Car score" in caplog.text) is warned


def test_mirror_tta_reaches_the_detector_and_says_so(tiny_models, tmp_path):
    """--mirror-tta runs PIXOR on the mirrored BEV too: other result files than one pass, and the header says
    so; with result files alone (no model runs) the flag is refused."""
    runs = {}
    for name, extra in (("plain", []), ("mirror", ["--mirror-tta"])):
        result = _accuracy("--data", KITTI, "--models", tiny_models, "--input", "lidar16+camera", "--score-threshold",
                           "0.0", "--frames", "2", "--out", tmp_path / name, "--json", tmp_path / f"{name}.json", *extra)
        assert result.returncode == 0, result.stderr
        runs[name] = result.stdout
        # The JSON says what made its figures.
        assert json.loads((tmp_path / f"{name}.json").read_text())["run"] == {
            "gt_labels": str(KITTI / "label_2"), "pred_labels": str(tmp_path / name / "data"), "split_file": None,
            "first_frames": 2, "data": str(KITTI), "models": str(tiny_models), "input": "lidar16+camera",
            "model_id": hashlib.sha256((tiny_models / "manifest.json").read_bytes()).hexdigest(),
            "score_threshold": 0.0, "mirror_tta": name == "mirror", "provider": "best available",
            "code": code_version()}
    assert "PIXOR with mirror test-time augmentation" in runs["mirror"] and "test-time" not in runs["plain"]
    files = {name: sorted((tmp_path / name / "data").glob("*.txt")) for name in runs}
    assert [p.name for p in files["plain"]] == [p.name for p in files["mirror"]]
    assert [p.read_text() for p in files["plain"]] != [p.read_text() for p in files["mirror"]]
    refused = _accuracy("--gt-labels", KITTI / "label_2", "--pred-labels", tmp_path / "plain" / "data", "--mirror-tta")
    assert refused.returncode == 2 and "argument --mirror-tta: not allowed with argument --gt-labels" in refused.stderr
    # --frames N past the frames there says so; --seed without --bootstrap would seed nothing.
    more = _accuracy("--gt-labels", KITTI / "label_2", "--pred-labels", tmp_path / "plain" / "data", "--frames", "2",
                     "--json", tmp_path / "two.json")
    assert more.returncode == 0 and "--frames 2: only" not in more.stderr, more.stderr
    more = _accuracy("--data", KITTI, "--models", tiny_models, "--input", "lidar16+camera", "--frames", "9",
                     "--out", tmp_path / "nine")
    assert more.returncode == 0 and f"--frames 9: only {len(FRAMES)} frame(s) to evaluate; using them all" in more.stderr
    seed = _accuracy("--gt-labels", KITTI / "label_2", "--pred-labels", tmp_path / "plain" / "data", "--seed", "5")
    assert seed.returncode == 2 and "argument --seed: only with --bootstrap N" in seed.stderr


def test_detection_run_refuses_mismatched_models(tiny_models, tmp_path):
    with pytest.raises(InputError, match="does not fit --input lidar16"):
        run_detection(KITTI, tiny_models, "lidar16", tmp_path)
    with pytest.raises(InputError, match="--input"):
        run_detection(KITTI, tiny_models, "radar", tmp_path)
    # A LiDAR-only PIXOR on the other line count would be scored as the other row of the table.
    repo = Path(__file__).resolve().parents[1]
    for models, trained, asked in (("edge-lidar16", "lidar16", "lidar64"), ("edge-lidar64", "lidar64", "lidar16")):
        with pytest.raises(InputError, match=f"trained on --input {trained} scans .*not {asked}"):
            run_detection(KITTI, repo / "weights" / models, asked, tmp_path / "refused")
    assert not (tmp_path / "refused").exists()


def test_depth_metrics_on_real_depth_completion_frame(tiny_models, depth_completion_dir, tmp_path):
    outcome = run_depth(depth_completion_dir, tiny_models, progress=False, pictures=tmp_path / "pictures")
    gt = read_depth_png(depth_completion_dir / "groundtruth" / "0000000005.png")
    # One picture per frame: camera, prediction, ground truth and error, each at the ground truth's crop.
    picture = cv2.imread(str(tmp_path / "pictures" / "depth_0000000005.png"))
    crop = depth_crop(gt.shape).apply(gt)
    assert picture.shape == (4 * crop.shape[0], crop.shape[1], 3)
    error_panel = picture[3 * crop.shape[0]:]
    assert (error_panel[40:][crop[40:] == 0] == NO_TRUTH_BGR).all()  # grey where there is no ground truth
    assert outcome.mean.n_pixels == np.count_nonzero(depth_crop(gt.shape).apply(gt))
    assert outcome.layout == "depth-completion"
    m = outcome.mean
    assert np.isfinite([m.rmse_mm, m.mae_mm, m.irmse_per_km, m.imae_per_km]).all()
    assert m.rmse_mm >= m.mae_mm > 0
    # Another source's maps instead of the network: the raw 64-line projection, evaluated where it has a
    # depth (the pixels where both it and the ground truth have one).
    given = run_depth(depth_completion_dir, tiny_models, progress=False,
                      depth_dir=depth_completion_dir / "velodyne_raw")
    raw = depth_crop(gt.shape).apply(read_depth_png(depth_completion_dir / "velodyne_raw" / "0000000005.png"))
    assert given.mean.n_pixels == np.count_nonzero((raw > 0) & (crop > 0)) < m.n_pixels
    assert given.input.startswith(f"depth maps from {depth_completion_dir / 'velodyne_raw'}")
    assert 0 < given.mean.mae_mm < m.mae_mm  # the measured returns beat an untrained net


def test_depth_completion_scan_is_thinned_to_16_lines_with_the_drives_calibration(
        tiny_models, depth_completion_dir, tmp_path, monkeypatch, caplog):
    """The paper measures depth from 16 lines: a depth-completion folder with its drive's raw calibration files
    has velodyne_raw thinned through them before the net; without them it goes in whole, with a warning."""
    from pipeline.detector import Detector
    from pipeline.kitti import read_calib

    seen: list[int] = []
    real = Detector.run_depth_net

    def counting(self, rgb, sparse_depth):  # the real net, its sparse input's returns counted
        seen.append(int(np.count_nonzero(sparse_depth)))
        return real(self, rgb, sparse_depth)

    monkeypatch.setattr(Detector, "run_depth_net", counting)
    whole = run_depth(depth_completion_dir, tiny_models, progress=False)
    assert whole.input == "velodyne_raw as given (projected 64-line scan)"
    assert "not thinned to 16 as the model was trained" in caplog.text
    data = tmp_path / "drive"
    shutil.copytree(depth_completion_dir, data)
    calib = read_calib(KITTI / "calib" / "000001.txt")  # drive 2011_09_26's, as the frame's

    def numbers(matrix: np.ndarray) -> str:
        return " ".join(f"{v:.9e}" for v in matrix.ravel())

    (tmp_path / "calib_cam_to_cam.txt").write_text(f"R_rect_00: {numbers(calib.R0_rect)}\nP_rect_02: {numbers(calib.P2)}\n")
    (tmp_path / "calib_velo_to_cam.txt").write_text(f"R: {numbers(calib.Tr_velo_to_cam[:, :3])}\n"
                                                    f"T: {numbers(calib.Tr_velo_to_cam[:, 3])}\n")
    thinned = run_depth(data, tiny_models, progress=False)
    assert thinned.input == "16-line emulated on velodyne_raw by each pixel's elevation (approximate)"
    assert "no velodyne_points/ with the drive's raw scans" in caplog.text
    assert 0.15 * seen[0] < seen[1] < 0.4 * seen[0]  # about a quarter of the returns
    assert thinned.mean.n_pixels == whole.mean.n_pixels and thinned.mean.mae_mm != whole.mean.mae_mm


def _drive_from_object_frame(frame_id: str, drive: Path) -> np.ndarray:
    """A depth-completion drive folder made of a real object frame: its image, its whole scan projected as
    velodyne_raw and as ground truth, the scan itself in velodyne_points/ and the raw calibration files.
    Returns the scan."""
    frame = load_frame(KITTI, frame_id)
    name = f"0000{frame_id}"  # a drive frame's 10 digits
    for folder in ("image_02", "velodyne_raw", "groundtruth", "velodyne_points"):
        (drive / folder).mkdir(parents=True)
    shutil.copy(KITTI / "image_2" / f"{frame_id}.png", drive / "image_02" / f"{name}.png")
    projected = sparse_depth_map(frame.points, frame.calib, frame.image_hw)
    write_depth_png(drive / "velodyne_raw" / f"{name}.png", projected)
    write_depth_png(drive / "groundtruth" / f"{name}.png", projected)
    frame.points.astype(np.float32).tofile(drive / "velodyne_points" / f"{name}.bin")

    def numbers(matrix: np.ndarray) -> str:
        return " ".join(f"{v:.9e}" for v in matrix.ravel())

    calib = frame.calib
    (drive / "calib_cam_to_cam.txt").write_text(f"R_rect_00: {numbers(calib.R0_rect)}\nP_rect_02: {numbers(calib.P2)}\n")
    (drive / "calib_velo_to_cam.txt").write_text(f"R: {numbers(calib.Tr_velo_to_cam[:, :3])}\n"
                                                 f"T: {numbers(calib.Tr_velo_to_cam[:, 3])}\n")
    return frame.points


def test_depth_completion_with_raw_scans_thins_them_in_scan_order(tiny_models, tmp_path, monkeypatch, caplog):
    """With the drive's raw scans in velodyne_points/, the net's sparse input is velodyne_raw on exactly the 16
    rings a scan-order thinning keeps (no warning); a velodyne_raw of another size than its image is refused,
    naming both files; KITTI's own layout gets the way to link a drive."""
    from pipeline.beams import emulate_beams
    from pipeline.depth_completion import drive_calibration, read_frame
    from pipeline.detector import Detector
    from pipeline.preprocess import view_from_depth_png

    drive = tmp_path / "drive"
    points = _drive_from_object_frame("000003", drive)
    seen: list[np.ndarray] = []
    real = Detector.run_depth_net

    def recording(self, rgb, sparse_depth):  # the real net, its sparse input kept
        seen.append(sparse_depth.copy())
        return real(self, rgb, sparse_depth)

    monkeypatch.setattr(Detector, "run_depth_net", recording)
    outcome = run_depth(drive, tiny_models, progress=False)
    assert outcome.input.startswith("16-line, the raw scans (velodyne_points/) thinned in scan order")
    assert "velodyne_points" not in caplog.text
    frame = load_frame(KITTI, "000003")
    true16 = sparse_depth_map(emulate_beams(points, 16), frame.calib, frame.image_hw)
    sparse = read_frame(drive, "0000000003", drive_calibration(drive)).sparse
    assert np.count_nonzero((sparse > 0) & (true16 == 0)) == 0  # only pixels of the 16 kept rings ...
    assert np.count_nonzero(sparse) >= 0.99 * np.count_nonzero(true16)  # ... and nearly all of them
    np.testing.assert_allclose(sparse[sparse > 0], true16[sparse > 0], atol=1 / 256)  # the PNG's 1/256 m steps
    _, expected = view_from_depth_png(frame.image, sparse, Detector(tiny_models).preset)
    np.testing.assert_array_equal(seen[0], expected)  # what the net was given

    (drive / "velodyne_points" / "0000000003.bin").rename(drive / "0000000003.bin")
    with pytest.raises(InputError, match=r"velodyne_points: no raw scan of frame 0000000003 \(0000000003.bin\)"):
        run_depth(drive, tiny_models, progress=False)
    (drive / "0000000003.bin").rename(drive / "velodyne_points" / "0000000003.bin")
    smaller = read_depth_png(drive / "velodyne_raw" / "0000000003.png")[:-5, :-16]
    write_depth_png(drive / "velodyne_raw" / "0000000003.png", smaller)
    with pytest.raises(InputError, match=r"velodyne_raw/0000000003.png: a 1226×370 depth map for the 1242×375 "
                                         r"image .*image_02/0000000003.png"):
        run_depth(drive, tiny_models, progress=False)
    official = tmp_path / "train" / "2011_09_26_drive_0001_sync"
    (official / "proj_depth" / "velodyne_raw" / "image_02").mkdir(parents=True)
    with pytest.raises(InputError, match="KITTI's depth-completion layout, one drive at a time in the flat one: "
                                         "link one drive"):
        run_depth(official, tiny_models, progress=False)


def test_depth_metrics_on_object_folder_with_dense_ground_truth(tiny_models, tmp_path):
    data = tmp_path / "data"
    for sub in ("image_2", "velodyne", "calib", "label_2"):
        shutil.copytree(KITTI / sub, data / sub)
    (data / "depth_2").mkdir()
    for frame_id in FRAMES:
        frame = load_frame(KITTI, frame_id)
        write_depth_png(data / "depth_2" / f"{frame_id}.png", sparse_depth_map(frame.points, frame.calib, frame.image_hw))
    outcome = run_depth(data, tiny_models, frames=["000006", "000003"], progress=False)
    assert set(outcome.per_frame) == {"000006", "000003"} and outcome.input == "16-line emulated scan"
    assert outcome.mean.rmse_mm > 0
    # With labels, the errors on the moderate cars' own pixels (the 64-line returns on them, here).
    assert outcome.car_errors and all(z > 0 and mm >= 0 for z, mm in outcome.car_errors)
    # And where their points land, in the network's view: one share per car with pixels there.
    assert outcome.car_in_box and all(0.0 <= share <= 1.0 for _, share in outcome.car_in_box)
    assert {z for z, _ in outcome.car_in_box} <= {z for z, _ in outcome.car_errors}
    # Another source's maps in place of the network: the ground truth itself scores no error.
    given = run_depth(data, tiny_models, frames=["000006"], progress=False, depth_dir=data / "depth_2")
    assert given.input.startswith(f"depth maps from {data / 'depth_2'}, not the depth network")
    assert given.mean.rmse_mm == 0.0 and all(mm == 0.0 for _, mm in given.car_errors)
    # Most of the 64-line returns on a car land in its box (a few dozen returns per car in the half-size
    # view: the ground beside a car inside its 2D box counts against it).
    assert given.car_in_box and np.mean([share for _, share in given.car_in_box]) > 0.6
    # And the returns of a car's 2D box that see something else stay off it.
    assert given.car_stray and all(share <= 0.05 for _, share in given.car_stray)
    assert outcome.car_stray and all(0.0 <= share <= 1.0 for _, share in outcome.car_stray)
    # The command prints both per distance band and writes them to its JSON.
    result = _accuracy("--depth", "--data", data, "--models", tiny_models, "--frames",
                       _frames_file(tmp_path, "000006"), "--json", tmp_path / "depth.json", "--plots", tmp_path / "p")
    assert result.returncode == 0, result.stderr
    assert "share of those pixels whose point lands in the car's BEV box" in result.stdout
    picture = cv2.imread(str(tmp_path / "p" / "car_depth.png"))  # each car's error and share against distance
    assert picture is not None and picture.shape[1] > picture.shape[0] > 200
    document = json.loads((tmp_path / "depth.json").read_text())["depth"]
    assert "share of the other pixels of each car's 2D box" in result.stdout
    assert set(document["car_points_in_box_by_band"]) == set(document["car_median_abs_mm_by_band"]) == set(
        document["car_stray_points_in_box_by_band"]) == {"0-20", "20-35", "35-50"}
    assert sum(band["cars"] for band in document["car_points_in_box_by_band"].values()) >= 1
    # Frame 000003's one car is 13 m away: the farther bands say so, not "nan".
    near = _accuracy("--depth", "--data", data, "--models", tiny_models, "--frames", _frames_file(tmp_path, "000003"))
    assert near.returncode == 0, near.stderr
    assert near.stdout.count("20-35 m no cars") == near.stdout.count("35-50 m no cars") == 3
    assert "nan" not in near.stdout.split("on the pixels of moderate cars")[1]


def test_depth_mode_names_the_missing_layout(tiny_models, tmp_path):
    result = subprocess.run(
        [sys.executable, str(ACCURACY), "--depth", "--data", str(tmp_path), "--models", str(tiny_models)],
        capture_output=True, text=True, timeout=300, check=False,
    )
    assert result.returncode == 2 and "depth_2/" in result.stderr and "Traceback" not in result.stderr


def test_split_file_chooses_the_frames_of_a_detection_run(tiny_models, tmp_path):
    """--split-file (the same flag as --frames) restricts the detector's frames, not only the evaluation's."""
    split = _frames_file(tmp_path, "000003")
    result = _accuracy("--data", KITTI, "--models", tiny_models, "--input", "lidar16+camera", "--split-file", split,
                       "--score-threshold", "0.0", "--out", tmp_path / "run", "--json", tmp_path / "ap.json")
    assert result.returncode == 0, result.stderr
    assert sorted(p.name for p in (tmp_path / "run" / "data").iterdir()) == ["000003.txt"]
    assert json.loads((tmp_path / "ap.json").read_text())["frames"] == 1 and "(1 frames" in result.stdout


def test_frames_count_takes_the_first_frames_in_every_mode(tiny_models, tmp_path):
    """--frames N (digits naming no file) is a count, as in the other commands: the first N frames by id."""
    first_two = sorted(p.stem for p in (KITTI / "label_2").glob("*.txt"))[:2]
    result = _accuracy("--data", KITTI, "--models", tiny_models, "--input", "lidar16+camera", "--frames", "2",
                       "--score-threshold", "0.0", "--out", tmp_path / "run", "--json", tmp_path / "ap.json")
    assert result.returncode == 0, result.stderr
    assert sorted(p.stem for p in (tmp_path / "run" / "data").iterdir()) == first_two
    assert json.loads((tmp_path / "ap.json").read_text())["frames"] == 2
    # The result files evaluated on their own, the first one of them.
    result = _accuracy("--gt-labels", KITTI / "label_2", "--pred-labels", tmp_path / "run" / "data", "--frames", "1",
                       "--json", tmp_path / "one.json")
    assert result.returncode == 0, result.stderr
    assert json.loads((tmp_path / "one.json").read_text())["frames"] == 1
    # Depth completion on an object folder with dense ground truth.
    data = tmp_path / "data"
    for sub in ("image_2", "velodyne", "calib"):
        shutil.copytree(KITTI / sub, data / sub)
    (data / "depth_2").mkdir()
    for frame_id in FRAMES:
        frame = load_frame(KITTI, frame_id)
        write_depth_png(data / "depth_2" / f"{frame_id}.png", sparse_depth_map(frame.points, frame.calib, frame.image_hw))
    result = _accuracy("--depth", "--data", data, "--models", tiny_models, "--frames", "1")
    assert result.returncode == 0, result.stderr
    assert "depth completion on 1 frame(s)" in result.stdout
    # 0 is no count, and a name that is not a file is still read as a list (and refused as missing).
    zero = _accuracy("--gt-labels", KITTI / "label_2", "--pred-labels", tmp_path / "run" / "data", "--frames", "0")
    assert zero.returncode == 2 and "--frames" in zero.stderr and "Traceback" not in zero.stderr
    missing = _accuracy("--gt-labels", KITTI / "label_2", "--pred-labels", tmp_path / "run" / "data",
                        "--frames", tmp_path / "no-such-list.txt")
    assert missing.returncode == 2 and "no-such-list.txt" in missing.stderr and "Traceback" not in missing.stderr


def test_flags_of_another_mode_are_refused(tiny_models, tmp_path):
    """A flag the chosen mode would ignore is an argparse error naming it and the mode's flag (exit 2)."""
    for args, message in [
        (("--data", KITTI, "--models", tiny_models, "--input", "lidar16", "--gt-labels", KITTI / "label_2"),
         "argument --gt-labels: not allowed with argument --data"),
        (("--depth", "--data", KITTI, "--models", tiny_models, "--by-distance", "0,30,80"),
         "argument --by-distance: not allowed with argument --depth"),
        (("--gt-labels", KITTI / "label_2", "--pred-labels", tmp_path, "--input", "lidar16"),
         "argument --input: not allowed with argument --gt-labels"),
    ]:
        result = _accuracy(*args, "--out", tmp_path / "run") if "--input" in args else _accuracy(*args)
        assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
        assert f"error: {message}" in result.stderr and result.stdout == ""
    assert not (tmp_path / "run").exists()


def test_dataset_modes_check_output_paths_before_any_work(tiny_models, tmp_path):
    a_file = tmp_path / "a_file"
    a_file.write_text("kept\n")
    frames = _frames_file(tmp_path, "000000")
    result = _accuracy("--data", KITTI, "--models", tiny_models, "--input", "lidar16+camera", "--frames", frames,
                       "--out", a_file)
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert f"error: --out {a_file}: exists and is not a directory" in result.stderr
    result = _accuracy("--data", KITTI, "--models", tiny_models, "--input", "lidar16+camera", "--frames", frames,
                       "--out", tmp_path / "run", "--json", a_file / "ap.json")
    assert result.returncode == 2 and f"error: --json {a_file / 'ap.json'}: {a_file} is a file" in result.stderr
    assert not (tmp_path / "run").exists()  # refused before the detector wrote a result file
    data = tmp_path / "data"
    (data / "depth_2").mkdir(parents=True)
    result = _accuracy("--depth", "--data", data, "--models", tiny_models, "--json", a_file / "d.json")
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert f"error: --json {a_file / 'd.json'}: {a_file} is a file" in result.stderr
    assert result.stdout == "" and a_file.read_text() == "kept\n"  # no metrics computed, nothing overwritten


def test_outputs_over_the_inputs_are_refused(tiny_models, tmp_path):
    """--json named as a ground-truth file used to replace it with JSON; --plots or --out inside an input
    folder would write among what the run reads. A new folder inside --data stays allowed."""
    data = tmp_path / "kitti"
    shutil.copytree(KITTI, data)
    labels = data / "label_2"
    before = {p.name: p.read_bytes() for p in labels.iterdir()}
    for args, flag, path, source in (
        (["--gt-labels", labels, "--pred-labels", labels, "--json", labels / "000006.txt"], "--json",
         labels / "000006.txt", "--gt-labels"),
        (["--gt-labels", labels, "--pred-labels", labels, "--plots", labels / "plots"], "--plots", labels / "plots",
         "--gt-labels"),
        (["--data", data, "--models", tiny_models, "--input", "lidar16+camera", "--out", data / "calib"], "--out",
         data / "calib", "--data"),
        (["--data", data, "--models", tiny_models, "--input", "lidar16+camera", "--json",
          tiny_models / "manifest.json"], "--json", tiny_models / "manifest.json", "--models"),
    ):
        result = _accuracy(*args)
        assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
        assert f"error: {flag} {path}: would be written over what {source} " in result.stderr, result.stderr
    assert {p.name: p.read_bytes() for p in labels.iterdir()} == before
    scored = tmp_path / "scored"  # the ground truth as results with score 1
    scored.mkdir()
    for label in labels.iterdir():
        scored.joinpath(label.name).write_text("".join(f"{line} 1\n" for line in label.read_text().splitlines()))
    result = _accuracy("--gt-labels", labels, "--pred-labels", scored, "--json", data / "ap.json")
    assert result.returncode == 0 and json.loads((data / "ap.json").read_text()), result.stderr


def test_depth_mode_refuses_a_lidar_only_model_directory(tiny_models, tmp_path):
    lidar_only = lidar_only_models(tiny_models, tmp_path / "lidar")
    data = tmp_path / "data"
    (data / "depth_2").mkdir(parents=True)
    result = _accuracy("--depth", "--data", data, "--models", lidar_only)
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert f"error: --models {lidar_only}: a LiDAR-only model directory has no depth network" in result.stderr


def test_detection_run_checks_label_2_before_detecting(tiny_models, tmp_path):
    data = tmp_path / "data"
    for sub in ("image_2", "velodyne", "calib"):
        shutil.copytree(KITTI / sub, data / sub)
    result = _accuracy("--data", data, "--models", tiny_models, "--input", "lidar16+camera",
                       "--frames", _frames_file(tmp_path, "000000"), "--out", tmp_path / "run")
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert f"error: --data {data}: no label_2/" in result.stderr
    assert not (tmp_path / "run").exists()  # no frame was detected

    def refused_before_detecting(message: str) -> None:
        result = _accuracy("--data", data, "--models", tiny_models, "--input", "lidar16+camera", "--out",
                           tmp_path / "run")
        assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
        assert f"error: --data {data}: {message}; give --split-file or --frames to leave it out" in result.stderr
        assert not (tmp_path / "run").exists()

    # One frame's label file lost: run over every scan, its cars would vanish from the table.
    shutil.copytree(KITTI / "label_2", data / "label_2")
    (data / "label_2" / "000003.txt").unlink()
    refused_before_detecting("frame 000003 has no ground truth (label_2/000003.txt), so its cars could not be scored")
    # And the other way: a label file whose scan is lost would count its cars as missed.
    shutil.copy(KITTI / "label_2" / "000003.txt", data / "label_2")
    (data / "velodyne" / "000004.bin").unlink()
    refused_before_detecting("label_2/000004.txt has no scan (velodyne/000004.bin), so its cars would count as missed")


def test_depth_mode_with_depth_dir_names_a_missing_folder_or_a_map_of_another_size(tiny_models, tmp_path):
    data = tmp_path / "data"
    for sub in ("image_2", "velodyne", "calib", "label_2"):
        shutil.copytree(KITTI / sub, data / sub)
    (data / "depth_2").mkdir()
    image_hw = load_frame(KITTI, "000006").image_hw
    write_depth_png(data / "depth_2" / "000006.png", np.full(image_hw, 20.0))
    frames = _frames_file(tmp_path, "000006")
    result = _accuracy("--depth", "--data", data, "--models", tiny_models, "--frames", frames,
                       "--depth-dir", tmp_path / "nowhere")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert f"error: --depth-dir {tmp_path / 'nowhere'}: directory not found" in result.stderr
    (tmp_path / "small").mkdir()
    write_depth_png(tmp_path / "small" / "000006.png", np.full((10, 20), 20.0))
    result = _accuracy("--depth", "--data", data, "--models", tiny_models, "--frames", frames,
                       "--depth-dir", tmp_path / "small")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert (f"{tmp_path / 'small' / '000006.png'}: a 20×10 depth map for a {image_hw[1]}×{image_hw[0]} image; "
            "it must cover the whole image") in result.stderr


def test_a_detection_runs_plots_name_the_model_input_and_data(tiny_models, tmp_path, monkeypatch, capsys):
    """The PR curves and the distance plot of a detection run carry what was run in their titles (the result
    folder's name alone says nothing of the model)."""
    import inspect

    from benchmarks import accuracy

    sources = []

    def recording(real):
        """The real plot function, recording the ``source`` it was given."""
        def plot(*args, **kwargs):
            sources.append(inspect.signature(real).bind(*args, **kwargs).arguments.get("source"))
            return real(*args, **kwargs)
        return plot

    monkeypatch.setattr(accuracy, "plot_pr_curves", recording(accuracy.plot_pr_curves))
    monkeypatch.setattr(accuracy, "plot_by_distance", recording(accuracy.plot_by_distance))
    code = accuracy.main(["--data", str(KITTI), "--models", str(tiny_models), "--input", "lidar16+camera",
                          "--score-threshold", "0.0", "--frames", "2", "--by-distance", "0,80",
                          "--out", str(tmp_path / "run"), "--plots", str(tmp_path / "plots"), "--no-progress"])
    assert code == 0, capsys.readouterr().err
    assert sources == [f"{tiny_models} (lidar16+camera) on {KITTI}"] * 2


def test_depth_pictures_name_their_frame_and_model(tiny_models, tmp_path, monkeypatch):
    """Each depth_<id>.png says in its picture which frame and which model (or which maps) it shows."""
    from evaluation import harness

    titles = []
    real = harness.render_depth_panel
    monkeypatch.setattr(harness, "render_depth_panel",
                        lambda *args, **kwargs: (titles.append(kwargs.get("title")), real(*args, **kwargs))[1])
    data = tmp_path / "data"
    for sub in ("image_2", "velodyne", "calib"):
        shutil.copytree(KITTI / sub, data / sub)
    (data / "depth_2").mkdir()
    frame = load_frame(KITTI, "000006")
    write_depth_png(data / "depth_2" / "000006.png", sparse_depth_map(frame.points, frame.calib, frame.image_hw))
    run_depth(data, tiny_models, frames=["000006"], progress=False, pictures=tmp_path / "p")
    run_depth(data, tiny_models, frames=["000006"], progress=False, pictures=tmp_path / "q", depth_dir=data / "depth_2")
    assert titles == [f"frame 000006, model {tiny_models.name}", "frame 000006, depth from depth_2"]
    assert cv2.imread(str(tmp_path / "p" / "depth_000006.png")) is not None


def test_depth_runs_cars_are_those_the_evaluation_counts_at_moderate(tiny_models, tmp_path):
    # Synthetic validation frame 3 (seed 2) holds a car exactly 25 px high at 39 m, which the devkit ignores
    # (height <= 25): the per-car depth figures must be of the same cars the moderate AP counts, band by band.
    data = tmp_path / "sim"
    simulate(RunConfig(data, frames=1, seed=2, start=3, split="val", progress=False))
    labels = read_labels(data / "label_2" / "000003.txt")
    assert any(o.type == "Car" and o.bbox[3] - o.bbox[1] == 25.0 and o.occluded <= 1 for o in labels)
    depth = run_depth(data, tiny_models, progress=False)
    truth = [LabelArrays.from_objects(labels)]
    detections = [LabelArrays.from_objects([dataclasses.replace(o, score=1.0) for o in labels if o.type == "Car"])]
    bands = evaluate_by_distance(truth, detections, edges=(0.0, 20.0, 35.0, 50.0), metrics=("bev",))
    for (low, high), result in bands.items():
        counted = result.curve("bev", 0.7, "moderate").n_ground_truth
        assert sum(low <= z < high for z, _ in depth.car_errors) == counted, (low, high)


def test_depth_mode_evaluates_a_16_line_sensors_own_scans(tiny_models, tmp_path):
    """--depth thinned every scan to 16 lines, and a folder of a 16-line sensor's scans failed on its first frame
    ('it is thinned already') while --emulate-beams 0 was refused with --depth as a flag for boxes. The first
    scan now decides up front, naming the flag, and --emulate-beams 0 evaluates the scans as stored."""
    from pipeline.beams import emulate_beams
    from pipeline.kitti import read_velodyne, write_depth_png, write_velodyne

    data = tmp_path / "own"
    for sub in ("image_2", "calib"):
        shutil.copytree(KITTI / sub, data / sub)
    (data / "velodyne").mkdir()
    (data / "depth_2").mkdir()
    for fid in ("000006",):
        write_velodyne(data / "velodyne" / f"{fid}.bin", emulate_beams(read_velodyne(KITTI / "velodyne" / f"{fid}.bin").points, 16))
        rows, columns = cv2.imread(str(KITTI / "image_2" / f"{fid}.png")).shape[:2]
        write_depth_png(data / "depth_2" / f"{fid}.png", np.full((rows, columns), 20.0, np.float32))
    frames = _frames_file(tmp_path, "000006")
    refused = _accuracy("--depth", "--data", data, "--models", tiny_models, "--frames", frames)
    assert refused.returncode == 2 and "Traceback" not in refused.stderr, refused.stderr
    assert (f"error: {data / 'velodyne' / '000006.bin'}: points: the scan has" in refused.stderr
            and "give --emulate-beams 0" in refused.stderr), refused.stderr
    stored = _accuracy("--depth", "--data", data, "--models", tiny_models, "--frames", frames, "--emulate-beams", "0")
    assert stored.returncode == 0, stored.stderr
    assert "depth completion on 1 frame(s)" in stored.stdout and "input: scan as stored" in stored.stdout


def test_the_default_run_folder_is_the_models_own(tiny_models, tmp_path):
    """Without --out every model's run went to outputs/accuracy/INPUT: evaluating a second model replaced the
    first's result files without a word. Each model directory now has a folder of its own there."""
    frames = _frames_file(tmp_path, "000006")
    for name in ("first", "second"):
        models = shutil.copytree(tiny_models, tmp_path / "models" / name)
        done = subprocess.run([sys.executable, str(ACCURACY), "--data", str(KITTI), "--models", str(models), "--input",
                               "lidar16+camera", "--frames", str(frames), "--no-progress"],
                              capture_output=True, text=True, timeout=300, check=False, cwd=tmp_path)
        assert done.returncode == 0, done.stderr[-2000:]
    for name in ("first", "second"):
        assert (tmp_path / "outputs" / "accuracy" / name / "lidar16_camera" / "data" / "000006.txt").is_file(), name
