"""Session 50's review of pipeline/: check_models on a 16-line vehicle's own frame, check_image_file on a JPEG cut
off after its scan marker, and the order of the regression channels a preset's reg_mean is refused with.

The model directories are copies of weights/edge-lidar16 (PIXOR alone, 1.4 MB) in tmp_path; the frames are KITTI
000006 of tests/data, its scan thinned with pipeline.beams as a 16-line (or 8-line) vehicle records it."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import cv2
import pytest

from pipeline.beams import emulate_beams
from pipeline.check_models import CheckConfig, main, run
from pipeline.errors import InputError
from pipeline.kitti import (
    IMAGE_TAIL_BYTES,
    JPEG_SCAN,
    check_image_file,
    read_image,
    read_velodyne,
    write_velodyne,
)
from pipeline.presets import PRESETS, check_preset
from tests.conftest import KITTI
from tests.test_rollout import WEIGHTS, _poison, copy_models, edit_manifest, sha256_file

FRAME = "000006"


def vehicle_frame(folder: Path, lines: int) -> Path:
    """A KITTI-layout folder holding frame 000006 with its scan thinned to ``lines``, as such a vehicle records it."""
    for name in ("image_2", "calib", "velodyne"):
        (folder / name).mkdir(parents=True)
    for name, ext in (("image_2", ".png"), ("calib", ".txt")):
        (folder / name / f"{FRAME}{ext}").symlink_to(KITTI / name / f"{FRAME}{ext}")
    scan = read_velodyne(KITTI / "velodyne" / f"{FRAME}.bin").points
    write_velodyne(folder / "velodyne" / f"{FRAME}.bin", emulate_beams(scan, lines))
    return folder


# --------------------------------------------------------------------------- check_models on a vehicle's frame
def test_check_models_passes_a_16_line_model_on_a_16_line_vehicles_own_frame(tmp_path: Path, capsys) -> None:
    """docs/deploy.md's rollout runs the check on one of the vehicle's own frames: a 16-line scan, which the check
    tried to thin to 16 lines again and failed the model for ("the frame did not run", exit 1, "do not ship it").
    It runs as stored: the vehicle's real input."""
    data = vehicle_frame(tmp_path / "vehicle", 16)
    assert main(["--models", str(WEIGHTS / "edge-lidar16"), "--provider", "cpu", "--data", str(data),
                 "--frame", FRAME]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[3].startswith(f"PASS frame    frame {FRAME} (scan as stored: 16 lines already, the model's own): "), out
    assert out[-1].startswith("passed: ")


def test_check_models_still_fails_a_nan_model_on_a_16_line_frame(tmp_path: Path) -> None:
    """A 16-line frame run as stored is still a real test of the model: a PIXOR whose weights went NaN fails."""
    models = copy_models("edge-lidar16", tmp_path / "models")
    _poison(models / "pixor.onnx")
    digest, size = sha256_file(models / "pixor.onnx"), (models / "pixor.onnx").stat().st_size
    edit_manifest(models, lambda m: m["files"].update({"pixor.onnx": {"sha256": digest, "bytes": size}}))
    report = run(CheckConfig(models=models, provider="cpu", data=vehicle_frame(tmp_path / "vehicle", 16), frame=FRAME))
    assert [c.status for c in report.checks] == ["pass", "pass", "pass", "fail"]
    assert report.checks[3].detail.startswith("pixor.onnx output score: "), report.checks[3].detail


@pytest.mark.parametrize(("lines", "extra"), [(8, []), (16, ["--emulate-beams", "16"])])
def test_check_models_refuses_a_frame_it_cannot_read_as_asked_naming_the_scan(tmp_path: Path, capsys, lines: int,
                                                                              extra: list[str]) -> None:
    """An 8-line scan for a 16-line model, or a 16-line scan with --emulate-beams 16: no fault of the model, so
    no FAIL and no "do not ship it", but the command line's error (exit 2) naming the scan and the way out."""
    data = vehicle_frame(tmp_path / "vehicle", lines)
    argv = ["--models", str(WEIGHTS / "edge-lidar16"), "--provider", "cpu", "--data", str(data), "--frame", FRAME]
    assert main(argv + extra) == 2
    captured = capsys.readouterr()
    assert "do not ship" not in captured.out
    err = captured.err.strip()
    assert "\n" not in err and err.startswith(f"error: {data / 'velodyne' / f'{FRAME}.bin'}: points: the scan"), err
    assert err.endswith("give --emulate-beams 0")
    assert main(argv + ["--emulate-beams", "0"]) == 0  # the way out it names
    assert "(scan as stored): " in capsys.readouterr().out


# --------------------------------------------------------------------------- a cut-off JPEG
@pytest.fixture(scope="module")
def jpeg() -> bytes:
    """KITTI 000006's image as a baseline JPEG (OpenCV's encoder: one scan, its marker near the start)."""
    ok, encoded = cv2.imencode(".jpg", cv2.imread(str(KITTI / "image_2" / f"{FRAME}.png")))
    assert ok
    return encoded.tobytes()


def test_check_image_file_refuses_a_jpeg_cut_off_in_its_scan_as_read_image_does(tmp_path: Path, jpeg: bytes) -> None:
    """check_image_file looked for the scan marker in the first 24 and last 4096 bytes only: a baseline JPEG cut
    in half (scan marker at byte 609) passed it, while read_image refused it. models/run_checks.py relies on it."""
    assert 0 < jpeg.find(JPEG_SCAN) < len(jpeg) // 2 - IMAGE_TAIL_BYTES  # neither in the head nor in the tail read
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(jpeg[: len(jpeg) // 2])
    with pytest.raises(InputError) as from_reader:
        read_image(cut)
    with pytest.raises(InputError, match=f"^{re.escape(str(from_reader.value))}$"):
        check_image_file(cut)


@pytest.mark.parametrize("padding", [0, 16, 3 * IMAGE_TAIL_BYTES])
def test_check_image_file_passes_a_whole_jpeg_with_or_without_bytes_after_its_end(tmp_path: Path, jpeg: bytes,
                                                                                   padding: int) -> None:
    """Bytes after the end marker (which decoders ignore), even more than the tail read, are no cut-off file."""
    path = tmp_path / "whole.jpg"
    path.write_bytes(jpeg + bytes(padding))
    check_image_file(path)
    assert read_image(path).shape == (374, 1238, 3)  # and it decodes whole


# --------------------------------------------------------------------------- a preset's reg_mean
def test_a_reg_mean_of_five_values_is_refused_naming_the_channels_in_their_order() -> None:
    """The message named the channels dx, dy, cos, sin, log l, log w; targets.encode_targets writes cos θ, sin θ,
    dx, dy, log w, log l, and a reg_mean written in the message's order would normalise each by another's mean."""
    edge = PRESETS["edge"]
    with pytest.raises(ValueError, match=re.escape("decode.reg_mean has 5 values: one per regression channel, 6 "
                                                   "(cos θ, sin θ, dx, dy, log w, log l)")):
        check_preset(replace(edge, decode=replace(edge.decode, reg_mean=(0.0, 0.0, 0.0, 0.0, 0.49))))


def test_check_models_names_the_warnings_of_a_frame_unlike_the_models_training(tmp_path: Path) -> None:
    """A 64-line model on a 16-line vehicle's frame runs it as stored and passes (the files are sound), but the
    frame line names the Detector's warnings, so whoever rolls the model out sees it does not fit the sensor; the
    model's own frame names none."""
    data = vehicle_frame(tmp_path / "vehicle", 16)
    unlike = run(CheckConfig(models=WEIGHTS / "edge-lidar64", provider="cpu", data=data, frame=FRAME))
    assert [c.status for c in unlike.checks] == ["pass"] * 4
    assert re.search(r"; the frame's warnings: .*line_count", unlike.checks[3].detail), unlike.checks[3].detail
    own = run(CheckConfig(models=WEIGHTS / "edge-lidar16", provider="cpu", data=data, frame=FRAME))
    assert "warnings" not in own.checks[3].detail, own.checks[3].detail
