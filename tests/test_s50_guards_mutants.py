"""Session 50's mutation audit of the guards it added: tests for what the review's own tests left unpinned.

The calibration check's thresholds and image edges on scans built to land on chosen pixels, a car's window at
the rounding and map edges, check_models on scans whose ring count sits at the edges of its window,
check_image_file's end marker per format, a video's even sides, a check across the service's settings named as a
user gives them, and accuracy's compared folder checked before any result is read. No data/sim; KITTI 000006 of
tests/data and weights/edge-lidar16 where a frame or a model runs."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from pydantic import ValidationError

from benchmarks.accuracy import main as accuracy
from evaluation.depth_metrics import car_surface
from pipeline.beams import recover_rings
from pipeline.calib import Calibration
from pipeline.check_models import main as check_models
from pipeline.checks import SCAN_VIEW_SAMPLE, scan_misses_image
from pipeline.errors import InputError
from pipeline.kitti import IMAGE_TAIL_BYTES, JPEG_END, check_image_file, read_velodyne, write_velodyne
from pipeline.render import FrameVideo
from service.__main__ import settings_errors
from service.settings import Settings
from tests.conftest import KITTI
from tests.test_pipeline_review_s50 import FRAME, jpeg, vehicle_frame  # noqa: F401 - jpeg: a fixture
from tests.test_rollout import WEIGHTS, copy_models, edit_manifest

# --------------------------------------------------------------------------- scan_misses_image
# A camera 100 × 60 pixels, focal length 50, looking along the LiDAR's x axis (x forward, y left, z up → the
# optical frame's x right, y down, z forward): a return at depth x lands on pixel (cx − 50 y / x, cy − 50 z / x).
HEIGHT, WIDTH, FOCAL = 60, 100, 50.0
CALIB = Calibration.from_matrices([[FOCAL, 0, WIDTH / 2, 0], [0, FOCAL, HEIGHT / 2, 0], [0, 0, 1, 0]], np.eye(3),
                                  [[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]])
CENTRE, FAR_LEFT = (WIDTH / 2, HEIGHT / 2), (-1000.0, HEIGHT / 2)  # in the image; ahead but far outside it


def scan(*groups: tuple[int, tuple[float, float], float]) -> np.ndarray:
    """A scan whose sampled returns (every SCAN_VIEW_SAMPLE-th) are ``count`` returns at depth ``x`` on pixel
    ``(u, v)`` for each (count, (u, v), x) of ``groups``; the points between the sampled ones repeat them."""
    rows = []
    for count, (u, v), x in groups:
        rows += [[x, -(u - WIDTH / 2) * x / FOCAL, -(v - HEIGHT / 2) * x / FOCAL, 0.5]] * count
    return np.repeat(np.array(rows, np.float32), SCAN_VIEW_SAMPLE, axis=0)


def misses(points: np.ndarray) -> str | None:
    return scan_misses_image(points, CALIB, (HEIGHT, WIDTH))


def test_a_tenth_of_the_returns_ahead_in_the_image_is_enough_and_fewer_is_warned_of() -> None:
    assert misses(scan((10, CENTRE, 10.0), (90, FAR_LEFT, 10.0))) is None
    warning = misses(scan((9, CENTRE, 10.0), (91, FAR_LEFT, 10.0)))
    assert warning is not None and warning.startswith("calib: 9.0% of the scan's returns ahead project into")


@pytest.mark.parametrize("pixel", [(-0.4, 30.0), (WIDTH - 0.6, 30.0), (50.0, -0.4), (50.0, HEIGHT - 0.6)])
def test_a_return_on_the_images_edge_pixels_is_in_it(pixel: tuple[float, float]) -> None:
    """The image spans −0.5 … side − 0.5 on each axis (pixel centres at integers), width across, height down."""
    assert misses(scan((10, pixel, 10.0), (90, FAR_LEFT, 10.0))) is None


@pytest.mark.parametrize("pixel", [(-0.6, 30.0), (WIDTH - 0.4, 30.0), (50.0, -0.6), (50.0, HEIGHT - 0.4)])
def test_a_return_just_off_the_image_is_not_in_it(pixel: tuple[float, float]) -> None:
    """Nine in ten inside: the one return just past an edge would make the tenth that silences the warning."""
    assert misses(scan((9, CENTRE, 10.0), (1, pixel, 10.0), (90, FAR_LEFT, 10.0))) is not None


def test_too_few_returns_ahead_say_nothing_and_the_near_ones_do_not_count() -> None:
    """50 sampled returns beyond 5 m decide (pipeline.checks' FEWEST_AHEAD and AHEAD_M); 49 say nothing."""
    assert misses(scan((50, FAR_LEFT, 10.0))) is not None
    assert misses(scan((49, FAR_LEFT, 10.0))) is None
    # Returns at 5 m or nearer, in the image, are not ahead: neither in the share nor in the floor.
    assert misses(scan((50, FAR_LEFT, 10.0), (500, CENTRE, 5.0))) is not None
    assert misses(scan((49, FAR_LEFT, 10.0), (500, CENTRE, 5.0))) is None


# --------------------------------------------------------------------------- car_surface's window
def test_a_narrow_box_keeps_the_pixel_its_middle_rounds_to() -> None:
    """Middles 6.75 and 3.6 lie in pixels 7 and 4 (centres at integers, pixel 7 spans 6.5 … 7.5)."""
    truth = np.full((10, 12), 20.0)
    window, on_car = car_surface(truth, (6.6, 3.3, 6.9, 3.9), 20.0)
    assert window == (slice(4, 5), slice(7, 8)) and on_car.sum() == 1


def test_a_box_over_the_maps_edge_keeps_the_pixels_on_the_map() -> None:
    truth = np.full((10, 12), 20.0)
    window, on_car = car_surface(truth, (-3.0, 8.2, 1.0, 14.0), 20.0)
    assert window == (slice(9, 10), slice(0, 2)) and on_car.sum() == 2


# --------------------------------------------------------------------------- check_models' scan window
def _vehicle(folder: Path, edit, lines: int = 16) -> Path:
    """vehicle_frame's folder of ``lines`` with its scan rewritten by ``edit``."""
    data = vehicle_frame(folder, lines)
    path = data / "velodyne" / f"{FRAME}.bin"
    write_velodyne(path, edit(read_velodyne(path).points))
    return data


def _check(data: Path) -> int:
    return check_models(["--models", str(WEIGHTS / "edge-lidar16"), "--provider", "cpu", "--data", str(data),
                         "--frame", FRAME])


def test_a_16_line_scan_starting_mid_ring_runs_as_stored(tmp_path: Path, capsys) -> None:
    """A driver that starts its scan mid-rotation cuts the first ring in two at the wrap: 17 segments, still the
    model's 16 lines."""
    def mid_ring(points: np.ndarray) -> np.ndarray:
        azimuth = np.arctan2(points[:, 1], points[:, 0])
        first_ring = int(np.argmax(np.abs(np.diff(azimuth)) > np.pi)) + 1
        rolled = np.roll(points, -(first_ring // 2), axis=0)
        assert recover_rings(rolled).n_rings == 17
        return rolled

    assert _check(_vehicle(tmp_path / "vehicle", mid_ring)) == 0
    assert "(scan as stored: 16 lines already, the model's own): " in capsys.readouterr().out


@pytest.mark.parametrize("what", ["32 lines", "16 lines out of order"])
def test_a_scan_of_other_lines_or_no_ring_order_is_refused(tmp_path: Path, capsys, what: str) -> None:
    """A 32-line scan is not the 16-line model's input; nor is a 16-line one whose order tells no rings (its line
    count then a guess from elevations)."""
    if what == "32 lines":
        data = vehicle_frame(tmp_path / "vehicle", 32)
    else:
        data = _vehicle(tmp_path / "vehicle", lambda p: p[np.random.default_rng(0).permutation(len(p))])
    assert _check(data) == 2
    assert capsys.readouterr().err.strip().endswith("give --emulate-beams 0")


def test_a_32_line_model_runs_a_32_line_scan_as_stored_and_refuses_a_24_line_one(tmp_path: Path, capsys) -> None:
    """The window is the model's lines (or one more): a 24-line scan, ring-ordered, is not a 32-line model's input
    (recover_rings reads a scan's order as rings from 16 segments up, so only a model of more lines meets this edge)."""
    models = copy_models("edge-lidar16", tmp_path / "models")
    edit_manifest(models, lambda m: m["networks"]["pixor"]["training"].update({"emulate_beams": 32}))
    argv = ["--models", str(models), "--provider", "cpu", "--frame", FRAME, "--data"]
    assert check_models([*argv, str(vehicle_frame(tmp_path / "v32", 32))]) == 0
    assert "(scan as stored: 32 lines already, the model's own): " in capsys.readouterr().out

    def first_24_rings(points: np.ndarray) -> np.ndarray:
        rings = recover_rings(points)
        assert rings.n_rings == 32 and rings.method == "azimuth-wrap"
        return points[rings.ring < 24]

    data = _vehicle(tmp_path / "v24", first_24_rings, 32)
    assert recover_rings(read_velodyne(data / "velodyne" / f"{FRAME}.bin").points).n_rings == 24
    assert check_models([*argv, str(data)]) == 2
    assert capsys.readouterr().err.strip().endswith("give --emulate-beams 0")


# --------------------------------------------------------------------------- check_image_file's end marker
def test_a_cut_off_jpeg_whose_last_bytes_hold_a_pngs_end_is_still_cut_off(tmp_path: Path, jpeg: bytes) -> None:  # noqa: F811
    """Its own end marker decides whether the tail alone may: a JPEG's scan data may hold any bytes, "IEND" too."""
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(jpeg[: len(jpeg) // 2] + b"IEND" + bytes(8))
    with pytest.raises(InputError, match="JPEG cut off before its end"):
        check_image_file(cut)


def test_a_png_with_bytes_after_its_end_passes_whatever_they_hold(tmp_path: Path) -> None:
    """Appended bytes beyond the tail read, a JPEG's end marker among them: the PNG's IEND is looked for in all."""
    path = tmp_path / "padded.png"
    path.write_bytes((KITTI / "image_2" / f"{FRAME}.png").read_bytes() + bytes(3 * IMAGE_TAIL_BYTES) + JPEG_END)
    check_image_file(path)


# --------------------------------------------------------------------------- FrameVideo's even sides
@pytest.mark.parametrize(("height", "width"), [(76, 101), (75, 100)])
def test_a_video_evens_each_odd_side_alone(tmp_path: Path, height: int, width: int) -> None:
    """One side odd, the other even: the odd one gets its black row or column, the even one is left alone (the
    session's test had both sides odd)."""
    picture = np.zeros((height, width, 3), np.uint8)
    picture[-4:], picture[:, -4:] = 255, 255  # bands along the bottom and right edges, wider than a pixel
    video = FrameVideo(tmp_path / "odd.mp4", fps=5)
    for _ in range(2):
        video.add(picture)
    assert video.close()
    capture = cv2.VideoCapture(str(tmp_path / "odd.mp4"))
    size = (capture.get(cv2.CAP_PROP_FRAME_WIDTH), capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
    assert size == (width + width % 2, height + height % 2)
    ok, frame = capture.read()
    assert ok and frame[height - 3, 10:-10].mean() > 200 and frame[10:-10, width - 3].mean() > 200


# --------------------------------------------------------------------------- the service's settings, named
def test_a_check_across_settings_is_given_as_its_message_names_it() -> None:
    """A check across settings has no field of its own: its message, which names each setting both ways a user
    gives it, is the whole line (no "settings: " or empty flag before it)."""
    with pytest.raises(ValidationError) as refused:
        Settings(models=WEIGHTS / "edge", device_ids="0", provider="cpu")
    (line,) = settings_errors(refused.value)
    assert line == "--device-ids (LOWRES3D_DEVICE_IDS) 0 with --provider cpu: GPU ids are for cuda or tensorrt"


# --------------------------------------------------------------------------- accuracy's compared folders
def test_a_missing_compared_folder_is_named_before_any_result_file_is_read(tmp_path: Path, capsys) -> None:
    """Label mode checks --compare-pred-labels before it reads the results: a missing folder is the one error,
    not found after a whole evaluation (here the broken result file it would have read first)."""
    (tmp_path / "pred").mkdir()
    (tmp_path / "pred" / f"{FRAME}.txt").write_text("Car 0 0\n")  # a line of 3 fields: refused when read
    absent = tmp_path / "absent"
    assert accuracy(["--gt-labels", str(KITTI / "label_2"), "--pred-labels", str(tmp_path / "pred"),
                     "--compare-pred-labels", str(absent)]) == 2
    assert capsys.readouterr().err.strip() == (f"error: --compare-pred-labels: {absent}: prediction label directory "
                                               "not found")
