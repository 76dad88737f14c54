"""An integrator's own vehicle: a 16-line sensor, another camera, calibration from other tools, other files.

Each frame is a real KITTI frame (tests/data) turned into what such a rig records: its image resized and framed
as another camera's, its scan thinned to a VLP-16's beams, raised or lowered, its intensities on another scale,
written with extra columns; and it runs through the shipped model (weights/edge) in ONNX Runtime, the CLI and
benchmarks/accuracy.py. Inputs the models were not trained on are answered with a warning naming what differs,
inputs that cannot be read with an error naming the file, the line or the field, and what to do.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.beams import emulate_beams
from pipeline.calib import Calibration
from pipeline.detector import Detector
from pipeline.errors import InputError
from pipeline.frame import Frame, load_frame
from pipeline.kitti import format_calib, parse_calib, parse_velodyne, read_calib, write_image
from tests.conftest import KITTI

ROOT = Path(__file__).resolve().parents[1]
EDGE = ROOT / "weights" / "edge"
ACCURACY = ROOT / "benchmarks" / "accuracy.py"


@pytest.fixture(scope="module")
def detector() -> Detector:
    return Detector(EDGE)


@pytest.fixture(scope="module")
def frame() -> Frame:
    return load_frame(KITTI, "000006")


def _warnings(detector: Detector, image: np.ndarray, points: np.ndarray, calib: Calibration) -> list[str]:
    return detector.detect(image, points, calib).warnings


def _raised(points: np.ndarray, calib: Calibration, metres: float) -> tuple[np.ndarray, Calibration]:
    """The scan of a LiDAR ``metres`` higher on the same vehicle (z lower by that), and its Tr_velo_to_cam, so
    that every point still projects into the same pixel."""
    moved = points.copy()
    moved[:, 2] -= metres
    tr = calib.Tr_velo_to_cam.copy()
    tr[:, 3] += tr[:, :3] @ np.array([0.0, 0.0, metres])
    return moved, Calibration(P2=calib.P2, R0_rect=calib.R0_rect, Tr_velo_to_cam=tr)


def _other_camera(image: np.ndarray, calib: Calibration, width: int, height: int) -> tuple[np.ndarray, Calibration]:
    """The frame as a ``width``×``height`` camera would frame it: the image scaled to that width (P2 exactly with
    it) and placed with the horizon (P2's principal point) at the middle row, as a camera mounted level has it."""
    scale = width / image.shape[1]
    rows = round(image.shape[0] * scale)
    resized = cv2.resize(image, (width, rows), interpolation=cv2.INTER_LINEAR)
    offset = (scale - 1) / 2
    p2 = np.array([[scale, 0, offset], [0, scale, offset], [0, 0, 1]]) @ calib.P2
    top = int(np.clip(round(height / 2 - p2[1, 2]), 0, height - rows))
    canvas = np.full((height, width, 3), 40, np.uint8)
    canvas[top:top + rows] = resized
    p2 = np.array([[1, 0, 0], [0, 1, top], [0, 0, 1.0]]) @ p2
    return canvas, Calibration(P2=p2, R0_rect=calib.R0_rect, Tr_velo_to_cam=calib.Tr_velo_to_cam)


# --------------------------------------------------------------------------- a scan unlike the training ones
def test_a_vlp16_beam_pattern_is_warned_about(detector, frame):
    """A VLP-16's beams (−15° … +15°, here the 9 inside the HDL-64E's field) are not the every-4th-ring subset the
    models learned on: it ran without a word and lost 5.5 BEV AP (IoU 0.7 moderate, 80 synthetic frames)."""
    vlp16 = emulate_beams(frame.points, 16, mode="vlp16")
    (warning,) = [w for w in _warnings(detector, frame.image, vlp16, frame.calib) if "beams are not" in w]
    assert warning.startswith("points: the scan's beams are not those the models were trained on")
    assert warning.endswith("(0% below, 0% above)")
    trained_like = emulate_beams(frame.points, 16)
    assert not [w for w in _warnings(detector, frame.image, trained_like, frame.calib) if "beams" in w]


def test_points_in_a_vehicle_frame_are_warned_about(detector, frame):
    """Points whose z is 0 on the road (a vehicle frame) filled other height slices than the networks learned
    and lost three quarters of the AP without a word; a VLP-16 mounted 1.9 m high, as the synthetic training
    scenes' varying sensor heights cover, gets no warning."""
    lidar16 = emulate_beams(frame.points, 16)
    on_road, calib = _raised(lidar16, frame.calib, -1.73)
    warnings = _warnings(detector, frame.image, on_road, calib)
    (warning,) = [w for w in warnings if w.startswith("points: the road ahead")]
    assert "Shift the points' z and Tr_velo_to_cam" in warning and warning.endswith("(road at 0.05 m)")
    higher, calib = _raised(lidar16, frame.calib, 0.17)
    assert _warnings(detector, frame.image, higher, calib) == []


def test_intensities_on_another_scale_are_warned_about(detector, frame):
    """A sensor without reflectance, or whose intensities divided by 255 are far darker than KITTI's: PIXOR reads
    reflectance as a channel (all zero: 85.5 → 71.7 BEV AP), so the scan is answered with a warning."""
    lidar16 = emulate_beams(frame.points, 16)
    dark = lidar16.copy()
    dark[:, 3] = 0.0
    (warning,) = [w for w in _warnings(detector, frame.image, dark, frame.calib) if "reflectance" in w]
    assert warning.startswith("points: the scan's reflectance is on another scale") and warning.endswith("(mean 0.000)")
    assert not [w for w in _warnings(detector, frame.image, lidar16, frame.calib) if "reflectance" in w]


def test_a_16_line_scan_out_of_ring_order_is_not_thinned_again(frame):
    """A VLP-16 driver writes its points in firing order (the azimuth sweeps once, the lasers interleaved): no
    wraps to count rings by, so emulate_beams(…, 16) clustered its elevations into 64 and kept a fifth of the
    points, about 4 lines, without a word. A 64-line scan in that order is still thinned."""
    def firing_order(points: np.ndarray) -> np.ndarray:
        return points[np.argsort(-np.arctan2(points[:, 1], points[:, 0]), kind="stable")]

    with pytest.raises(InputError, match=r"^points: the scan's returns lie on beams far apart .* it has 16 lines or so "
                                         r"already, such as a VLP-16's"):
        emulate_beams(firing_order(emulate_beams(frame.points, 16)), 16)
    with pytest.raises(InputError, match="beams far apart"):
        emulate_beams(firing_order(emulate_beams(frame.points, 16, mode="vlp16")), 16)
    kept = emulate_beams(firing_order(frame.points), 16)
    assert 0.2 < kept.shape[0] / frame.points.shape[0] < 0.3


# --------------------------------------------------------------------------- another camera
def test_a_camera_whose_crop_misses_the_cars_ahead_is_warned_about(detector, frame):
    """The depth net reads the bottom 352 rows, centre 1216 columns of any image. Of a level 1920×1080 camera
    that crop lies below every car farther than a few metres: the camera's share of the boxes was lost (BEV AP
    that of the LiDAR alone on 80 synthetic frames) without a word. A 1280×720 one keeps the cars in the crop."""
    lidar16 = emulate_beams(frame.points, 16)
    image, calib = _other_camera(frame.image, frame.calib, 1920, 1080)
    (warning,) = [w for w in _warnings(detector, image, lidar16, calib) if w.startswith("image: the depth net sees")]
    assert "bottom 352 rows, centre 1216 columns of this 1920×1080 image" in warning
    assert warning.endswith("(cars beyond 6 m unseen)")
    image, calib = _other_camera(frame.image, frame.calib, 1280, 720)
    assert _warnings(detector, image, lidar16, calib) == []


def test_the_readmes_reframing_of_a_camera_clears_the_warning(detector, frame):
    """README "Your own vehicle": its snippet, run as it stands on the 1920×1080 frame, gives an image framed as
    KITTI's camera (375 rows, KITTI's focal length, the horizon 173 rows down) with its calibration: no warning."""
    snippet = re.search(r"### Your own vehicle.*?```python\n(.*?)```", (ROOT / "README.md").read_text(), re.DOTALL)
    assert snippet is not None, "README.md has no 'Your own vehicle' Python block"
    lidar16 = emulate_beams(frame.points, 16)
    big_image, big_calib = _other_camera(frame.image, frame.calib, 1920, 1080)
    namespace = {"image": big_image, "calib": big_calib}
    exec(snippet.group(1), namespace)  # noqa: S102 - the README's own code
    image, calib, scale, top = (namespace[name] for name in ("image", "calib", "scale", "top"))
    assert image.shape[0] == 375 and image.shape[1] >= 1216
    np.testing.assert_allclose(calib.P2[:2, :3], [[721.5, 0, calib.P2[0, 2]], [0, 721.5, 173]], atol=1.0)
    # A point of the scan lands on the pixel the resize and the cut move its 1920×1080 pixel to (centres aligned).
    point = lidar16[lidar16[:, 0] > 10][:1, :3]
    (u, v), (big_u, big_v) = calib.velo_to_image(point)[0][0], big_calib.velo_to_image(point)[0][0]
    np.testing.assert_allclose([u, v], [scale * big_u + (scale - 1) / 2, scale * big_v + (scale - 1) / 2 - top],
                               atol=1e-6)
    assert _warnings(detector, image, lidar16, calib) == []


def test_an_image_smaller_than_the_crop_says_what_to_do(detector, frame):
    """A 960×540 camera cannot fill the 1216×352 crop: the error says to upscale the image and P2 with it."""
    image, calib = _other_camera(frame.image, frame.calib, 960, 540)
    with pytest.raises(InputError, match=r"^image: 960×540 pixels is smaller than the model's 1216×352 crop; upscale "
                                         r"the image until it covers the crop and P2 with it"):
        detector.detect(image, emulate_beams(frame.points, 16), calib)


# --------------------------------------------------------------------------- files written by other tools
def _calib_lines(calib: Calibration, homogeneous: bool) -> list[str]:
    def row(name: str, m: np.ndarray) -> str:
        return f"{name}: " + " ".join(f"{v:.12e}" for v in np.asarray(m, np.float64).ravel())

    r0, tr = calib.R0_rect, calib.Tr_velo_to_cam
    if homogeneous:
        r0 = np.pad(r0, ((0, 1), (0, 1)))
        r0[3, 3] = 1.0
        tr = np.vstack([tr, [0.0, 0.0, 0.0, 1.0]])
    return [row("P2", calib.P2), row("R0_rect", r0), row("Tr_velo_to_cam", tr), "image_size: 1280 720"]


def test_a_calibration_with_4x4_transforms_and_p2_alone_is_read():
    """Calibration tools write R0_rect and Tr_velo_to_cam as 4×4 homogeneous matrices: 'needs 12 numbers, got 16'
    refused them. They are read as their 3×4 / 3×3 blocks; a 4×4 that is not homogeneous is refused, naming its
    line and what to give."""
    kitti = read_calib(KITTI / "calib" / "000006.txt")
    calib = parse_calib("\n".join(_calib_lines(kitti, homogeneous=True)) + "\n", "rig.txt")
    for key in ("P2", "R0_rect", "Tr_velo_to_cam"):
        np.testing.assert_allclose(getattr(calib, key), getattr(kitti, key), rtol=1e-12)
    lines = _calib_lines(kitti, homogeneous=True)
    lines[2] = lines[2].rsplit(" ", 4)[0] + " 0 0 1 1"  # a projective last row
    with pytest.raises(InputError, match=r"^rig.txt, line 3: Tr_velo_to_cam: a 4×4 matrix, but not a "
                                         r"homogeneous one \(last row 0 0 0 1\); give the 3×4 block, 12 numbers$"):
        parse_calib("\n".join(lines), "rig.txt")
    with pytest.raises(InputError, match=r"line 3: Tr_velo_to_cam needs 12 numbers \(or 16: the 4×4 homogeneous "
                                         r"form\), got 9"):
        parse_calib("\n".join([*_calib_lines(kitti, False)[:2], "Tr_velo_to_cam: " + " ".join(["1"] * 9)]), "rig.txt")


def _rig_folder(folder: Path, frame_ids: tuple[str, ...], suffix: str = ".png") -> Path:
    """A KITTI-layout folder of the rig: 16-line scans as its sensor writes them (thinned already), images in
    ``suffix``'s format, calibration with P2 alone and 4×4 transforms, the frames' labels."""
    for name in ("image_2", "velodyne", "calib", "label_2"):
        (folder / name).mkdir(parents=True, exist_ok=True)
    for fid in frame_ids:
        kitti = load_frame(KITTI, fid)
        write_image(folder / "image_2" / f"{fid}{suffix}", kitti.image)
        emulate_beams(kitti.points, 16).astype("<f4").tofile(folder / "velodyne" / f"{fid}.bin")
        (folder / "calib" / f"{fid}.txt").write_text("\n".join(_calib_lines(kitti.calib, homogeneous=True)) + "\n")
        shutil.copy(KITTI / "label_2" / f"{fid}.txt", folder / "label_2" / f"{fid}.txt")
    return folder


def test_detect_reads_a_rigs_folder_of_jpegs(tmp_path):
    """A recorder's JPEGs in image_2/: 'image_2/ID.png: cannot read image (No such file)' skipped every frame.
    The frame's JPEG is read when there is no PNG; with neither, the error names what was looked for."""
    data = _rig_folder(tmp_path / "rig", ("000006",), suffix=".jpg")
    done = subprocess.run([sys.executable, "-m", "pipeline.detect", "--models", str(EDGE), "--data", str(data),
                           "--out", str(tmp_path / "out"), "--no-pictures"], capture_output=True, text=True,
                          cwd=ROOT, timeout=300, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    assert (tmp_path / "out" / "data" / "000006.txt").is_file() and "1 frame(s)" in done.stdout
    (data / "image_2" / "000006.jpg").unlink()
    with pytest.raises(InputError, match=r"image_2/000006.png: no image for frame 000006 \(nor 000006.jpg or "
                                         r"000006.jpeg\)"):
        load_frame(data, "000006")


def test_a_scan_with_ring_and_time_columns_is_named_as_such(detector, frame):
    """A driver's scan of 6 float32 columns (x, y, z, intensity, ring, time): refused for its size, or, when its
    size happened to be a multiple of 16, read as shifted rows whose 'reflectance' then failed with 'divide
    0–255 intensities by 255', the wrong fix. Both errors now say what the rows are and how to keep four."""
    lidar16 = emulate_beams(frame.points, 16)  # 27,599 points: 24 × 27,599 bytes is not a multiple of 16
    extra = np.column_stack([lidar16, np.arange(len(lidar16)) % 16, np.linspace(0, 0.1, len(lidar16))])
    with pytest.raises(InputError, match=r"^scan.bin: size 662376 bytes is not a multiple of 16 .*; it is a whole "
                                         r"number of 6-column rows: a scan with a ring or time column\? Keep x, y, z "
                                         r"and the intensity: np.fromfile\(path, np.float32\).reshape\(-1, 6\)\[:, :4\]$"):
        parse_velodyne(extra.astype("<f4").tobytes(), "scan.bin")
    even = parse_velodyne(extra[:-1].astype("<f4").tobytes(), "scan.bin").points  # a multiple of 16 bytes
    with pytest.raises(InputError, match=r"^points: reflectance .* \(no sensor's intensities: are the scan's rows 4 "
                                         r"float32 values\? A scan with a ring or time column"):
        detector.detect(frame.image, even, frame.calib)
    intensities = lidar16.copy()
    intensities[:, 3] = np.round(intensities[:, 3] * 255)
    with pytest.raises(InputError, match=r"\(divide 0–255 intensities by 255\)$"):
        detector.detect(frame.image, intensities, frame.calib)



def test_a_big_endian_scan_is_named_as_such(detector, frame):
    """A scan written as big-endian float32 (some exporters' and Java tools' default) and read as KITTI's
    little-endian .bin: its values are garbage in every column, and the errors blamed a ring or time column or
    said 'garbage values'. Read the other way round they are the scan, which the error now says, with the fix;
    a scan that is garbage either way keeps the old hint."""
    lidar16 = emulate_beams(frame.points, 16)
    swapped = parse_velodyne(lidar16.astype(">f4").tobytes(), "scan.bin").points  # rows that read as NaN dropped
    fix = r"the file's floats look big-endian: read in the other byte order they are a plausible scan; convert it " \
          r"with np.fromfile\(path, '>f4'\).astype\('<f4'\).reshape\(-1, 4\)"
    with pytest.raises(InputError, match=rf"^points: reflectance \(the 4th column\) must lie in \[0, 1\].* \({fix}\)$"):
        detector.detect(frame.image, swapped, frame.calib)
    no_reflectance = np.column_stack([lidar16[:, :3], np.zeros(len(lidar16), np.float32)])
    swapped = parse_velodyne(no_reflectance.astype(">f4").tobytes(), "scan.bin").points  # reflectance 0 either way
    with pytest.raises(InputError, match=rf"^points: a coordinate of .* m, beyond any LiDAR's range .*: {fix}$"):
        detector.detect(frame.image, swapped, frame.calib)
    garbage = lidar16.copy()
    garbage[::7, 0] = 3e30  # misread either way round
    with pytest.raises(InputError, match=r"beyond any LiDAR's range .*: garbage values, or rows misread\?$"):
        detector.detect(frame.image, garbage, frame.calib)

# --------------------------------------------------------------------------- evaluating on the rig's own frames
def test_accuracy_evaluates_a_16_line_sensors_own_scans(tmp_path):
    """benchmarks/accuracy.py --input lidar16+camera thinned every scan to 16 lines: a 16-line sensor's own scans
    were each skipped ('thinned already') and the table counted every car missed, with no flag to keep them.
    Now one error before any model runs says to give --emulate-beams 0, which evaluates them as stored."""
    data = _rig_folder(tmp_path / "rig", ("000004", "000006"))
    args = [sys.executable, str(ACCURACY), "--data", str(data), "--models", str(EDGE), "--input", "lidar16+camera",
            "--out", str(tmp_path / "out"), "--no-progress"]
    refused = subprocess.run(args, capture_output=True, text=True, cwd=ROOT, timeout=300, check=False)
    assert refused.returncode == 2, refused.stderr[-2000:]
    assert refused.stderr.strip() == (f"error: {data / 'velodyne' / '000004.bin'}: points: the scan has 16 rings, not "
                                      "64: it is thinned already (emulate beams on 64-line scans only); to evaluate "
                                      "scans of a 16-line sensor as they are, give --emulate-beams 0")
    done = subprocess.run([*args, "--emulate-beams", "0"], capture_output=True, text=True, cwd=ROOT, timeout=300,
                          check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "skipped" not in done.stderr and "lidar16+camera on" in done.stdout and "BEV" in done.stdout
    assert sorted(p.name for p in (tmp_path / "out" / "data").glob("*.txt")) == ["000004.txt", "000006.txt"]
    # The rig's calibration (P2 alone, 4×4 transforms) was read as KITTI's.
    assert format_calib(read_calib(data / "calib" / "000006.txt")) == format_calib(read_calib(KITTI / "calib" / "000006.txt"))
