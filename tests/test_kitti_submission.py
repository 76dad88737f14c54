"""Result files for KITTI's test server: the devkit's format line by line, one file per frame, and a run that
cannot give every frame its file says so (the server refuses a submission with a file missing)."""

import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.kitti import read_image_size, read_labels
from simulation.run import RunConfig
from simulation.run import run as simulate

ROOT = Path(__file__).resolve().parent.parent
KITTI = ROOT / "tests" / "data" / "kitti" / "training"
MODELS = ROOT / "weights" / "edge"


def _copy_frame(source: Path, fid: str, testing: Path, new: str) -> None:
    """Frame ``fid`` of ``source`` as frame ``new`` of ``testing`` (image, scan and calibration; no labels)."""
    for part, suffix in (("image_2", ".png"), ("velodyne", ".bin"), ("calib", ".txt")):
        (testing / part).mkdir(parents=True, exist_ok=True)
        shutil.copy(source / part / f"{fid}{suffix}", testing / part / f"{new}{suffix}")


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> Path:
    """Frames 0, 3 and 9 of the synthetic validation set (seed 2, as data/sim/val: a frame depends only on the
    seed and its index), made here since data/ is not in the repository."""
    out = tmp_path_factory.mktemp("sim")
    for index in (0, 3, 9):
        simulate(RunConfig(out=out, frames=1, seed=2, start=index, split="val", progress=False))
    return out


@pytest.fixture(scope="module")
def testing(sim, tmp_path_factory) -> Path:
    """A KITTI ``testing/`` folder (no label_2): a real frame, a synthetic one whose nearest car reaches out of the
    image on the right, one whose scan has points behind the vehicle alone (no car at the default threshold), one
    with a broken image, and one whose scan is missing (an incomplete download)."""
    testing = tmp_path_factory.mktemp("kitti") / "testing"
    _copy_frame(KITTI, "000006", testing, "000000")
    _copy_frame(sim, "000000", testing, "000001")
    _copy_frame(sim, "000009", testing, "000002")
    scan = np.fromfile(testing / "velodyne" / "000002.bin", np.float32).reshape(-1, 4)
    scan[scan[:, 0] < -5].tofile(testing / "velodyne" / "000002.bin")
    _copy_frame(sim, "000003", testing, "000003")
    (testing / "image_2" / "000003.png").write_bytes(b"not an image")
    _copy_frame(KITTI, "000003", testing, "000004")
    (testing / "velodyne" / "000004.bin").unlink()
    return testing


def _detect(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pipeline.detect", "--models", str(MODELS), "--emulate-beams", "16",
                           "--no-pictures", *args], capture_output=True, text=True, timeout=300, check=False, cwd=ROOT)


@pytest.fixture(scope="module")
def run(testing, tmp_path_factory) -> tuple[subprocess.CompletedProcess, Path]:
    out = tmp_path_factory.mktemp("results")
    return _detect("--data", str(testing), "--out", str(out)), out


def test_every_result_line_is_in_the_devkits_format(run, testing):
    """16 values (type … rotation_y, score), Car alone, alpha = rotation_y − atan2(x, z) in [−π, π], the 2D box in
    the image's pixels, sizes positive, the box in front of the camera; a frame without a car has an empty file."""
    done, out = run
    assert "Traceback" not in done.stderr
    lines = 0
    for fid in ("000000", "000001", "000002"):
        h, w = read_image_size(testing / "image_2" / f"{fid}.png")
        for row in (out / "data" / f"{fid}.txt").read_text().splitlines():
            fields = row.split()
            assert len(fields) == 16 and fields[0] == "Car", row
            values = map(float, fields[1:])
            _, _, alpha, left, top, right, bottom, height, width, length, x, _, z, rotation_y, score = values
            assert -math.pi <= alpha <= math.pi and -math.pi <= rotation_y <= math.pi
            assert abs(math.remainder(alpha - (rotation_y - math.atan2(x, z)), 2 * math.pi)) < 2e-4, row
            assert 0 <= left < right <= w - 1 and 0 <= top < bottom <= h - 1, row
            assert min(height, width, length) > 0 and z > 0 and 0.5 <= score <= 1, row
            lines += 1
    assert lines > 0 and (out / "data" / "000002.txt").read_text() == ""
    # The synthetic car that reaches out of the image on the right (x 3.41 m, z 8.55 m in its label) is found, its
    # 2D box clipped at the image's last column.
    cars = read_labels(out / "data" / "000001.txt", needs_score=True)
    assert any(abs(o.location[0] - 3.4) < 0.5 and abs(o.location[2] - 8.55) < 1 for o in cars)


def test_a_frame_whose_scan_is_missing_is_named_not_left_out_in_silence(run):
    """An image without its scan (a download that lost a file) gave no result file, no word and exit status 0: a
    test-split submission made of it would be refused by the server for the missing file."""
    done, out = run
    assert done.returncode == 1
    assert "velodyne/000004.bin" in done.stderr and "frame 000004 skipped" in done.stderr
    assert "2 of 5 frame(s) skipped" in done.stderr and "000003, 000004" in done.stderr
    assert sorted(p.stem for p in (out / "data").glob("*.txt")) == ["000000", "000001", "000002"]


def test_skipped_frames_say_the_result_folder_is_not_a_whole_submission(run):
    done, out = run
    assert (f"{out / 'data'} has no result file for the 2 skipped frame(s): KITTI's evaluation server refuses a "
            "submission with a file missing") in done.stderr


def test_a_split_file_chooses_the_frames_and_refuses_an_id_without_a_scan(testing, tmp_path):
    """--split-file takes ImageSets/val.txt or test.txt; an id in it without a scan is refused before any model
    loads, so that a run over test.txt either gives every frame its file or says which cannot have one."""
    split = tmp_path / "val.txt"
    split.write_text("000002\n000000\n")
    done = _detect("--data", str(testing), "--split-file", str(split), "--out", str(tmp_path / "out"))
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in (tmp_path / "out" / "data").iterdir()) == ["000000.txt", "000002.txt"]
    split.write_text("000000\n000004\n")
    refused = _detect("--data", str(testing), "--split-file", str(split), "--out", str(tmp_path / "refused"))
    assert refused.returncode == 2 and "Traceback" not in refused.stderr
    assert f"--split-file {split}: frame 000004 has no scan {testing / 'velodyne' / '000004.bin'}" in refused.stderr
    assert not (tmp_path / "refused").exists()
    both = _detect("--data", str(testing), "--split-file", str(split), "--frame", "0", "--out", str(tmp_path / "x"))
    assert both.returncode == 2 and "not both" in both.stderr


def test_the_projects_evaluator_reads_the_result_files(run, sim, tmp_path):
    """benchmarks/accuracy.py, the devkit's protocol, takes the files as they are (the frames with one)."""
    _, out = run
    gt = tmp_path / "label_2"
    gt.mkdir()
    shutil.copy(KITTI / "label_2" / "000006.txt", gt / "000000.txt")
    shutil.copy(sim / "label_2" / "000000.txt", gt / "000001.txt")
    (gt / "000002.txt").write_text("")
    done = subprocess.run([sys.executable, "benchmarks/accuracy.py", "--gt-labels", str(gt), "--pred-labels",
                           str(out / "data"), "--no-progress"], capture_output=True, text=True, timeout=120,
                          check=False, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    assert "Car AP (%), 3 frames" in done.stdout
