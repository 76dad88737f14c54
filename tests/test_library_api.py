"""The Detector as a ROS 2 node embeds it: teardown, calibration from matrices, inputs from messages, named
boxes, several callback threads, and the annotations a type checker reads (weights/edge, the KITTI samples)."""

import subprocess
import sys
import tomllib
from concurrent.futures import ThreadPoolExecutor
from importlib.resources import files
from pathlib import Path

import numpy as np
import pytest

from pipeline.beams import emulate_beams
from pipeline.calib import Calibration
from pipeline.detector import Detector
from pipeline.errors import InputError
from pipeline.frame import Frame, load_frame
from tests.conftest import FRAMES, KITTI

ROOT = Path(__file__).resolve().parents[1]
EDGE = ROOT / "weights" / "edge"


@pytest.fixture(scope="module")
def detector():
    with Detector(EDGE) as detector:
        yield detector


@pytest.fixture(scope="module")
def frames() -> dict[str, Frame]:
    return {frame_id: load_frame(KITTI, frame_id) for frame_id in FRAMES}


def lidar16(frame: Frame) -> np.ndarray:
    return emulate_beams(frame.points, 16)


# Run in a fresh interpreter: in the test process, the threads of other tests' Detectors end whenever the
# garbage collector reaches them, and would move the count between the two readings. Threads are told apart by
# their ids: a thread that was joined is still listed in /proc for a moment while the kernel ends it (the first
# Detector's in the "before" reading, the second's right after close(); seen under load), so the script waits,
# boundedly, for the second Detector's threads to leave the list rather than reading it once.
CLOSE_SCRIPT = """
import os, sys, time
from concurrent.futures import ThreadPoolExecutor
from pipeline.beams import emulate_beams
from pipeline.detector import Detector
from pipeline.frame import load_frame

def thread_ids():
    return set(os.listdir("/proc/self/task"))  # every thread of this process, ONNX Runtime's pools too

frame = load_frame(sys.argv[1], "000006")
points = emulate_beams(frame.points, 16)
with ThreadPoolExecutor(1) as callbacks:  # the node's executor thread, which outlives the Detector
    # A first Detector's frame starts what stays with the process whatever the Detector does (OpenCV's worker
    # pool, say): listed before, so that the second Detector's own threads are what close() must end.
    with Detector(sys.argv[2], stage_threads=2) as first:
        callbacks.submit(first.detect, frame.image, points, frame.calib).result()
    before = thread_ids()
    detector = Detector(sys.argv[2], stage_threads=2)
    callbacks.submit(detector.detect, frame.image, points, frame.calib).result()
    started = thread_ids() - before
    detector.close()
    # The detector and the callback thread holding its stage thread are still referenced here: only close()
    # can end these threads, so a wait of a few seconds cannot pass for a thread close() left running.
    deadline = time.monotonic() + 10
    while thread_ids() - before and time.monotonic() < deadline:
        time.sleep(0.01)
    print(len(started), len(thread_ids() - before))
"""


def test_close_stops_every_thread_the_detector_started_while_the_node_still_holds_it(frames):
    """A node rebuilding its Detector on a parameter change: the sessions' pools and the stage threads made for
    its callback thread go at close(), not whenever the last reference does; a frame after it says so."""
    done = subprocess.run([sys.executable, "-c", CLOSE_SCRIPT, str(KITTI), str(EDGE)], capture_output=True, text=True,
                          timeout=120, check=False, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-2000:]
    started, left = map(int, done.stdout.split())
    assert started > 0  # the stage thread at least
    assert left == 0
    frame = frames["000006"]
    detector = Detector(EDGE, stage_threads=2)
    detector.close()
    detector.close()  # twice is harmless
    with pytest.raises(RuntimeError, match="was closed"):
        detector.detect(frame.image, lidar16(frame), frame.calib)
    with Detector(EDGE) as scoped:
        scoped.detect(frame.image, lidar16(frame), frame.calib)
    with pytest.raises(RuntimeError, match="was closed"):
        scoped.detect(frame.image, lidar16(frame), frame.calib)


def test_a_calibration_from_camera_info_and_tf_matrices_equals_the_files(detector, frames):
    """CameraInfo's flat p (12) and r (9) and a TF 4×4 give the file's calibration, and the same boxes."""
    frame = frames["000006"]
    calib = frame.calib
    transform = np.eye(4)
    transform[:3] = calib.Tr_velo_to_cam
    made = Calibration.from_matrices(tuple(calib.P2.ravel()), tuple(calib.R0_rect.ravel()), transform)
    for key in ("P2", "R0_rect", "Tr_velo_to_cam"):
        np.testing.assert_array_equal(getattr(made, key), getattr(calib, key))
    transform[0, 3] += 1.0  # copied: the caller's buffer changing later changes nothing
    np.testing.assert_array_equal(made.Tr_velo_to_cam, calib.Tr_velo_to_cam)
    rotation = np.eye(4)
    rotation[:3, :3] = calib.R0_rect
    np.testing.assert_array_equal(Calibration.from_matrices(calib.P2, rotation, calib.Tr_velo_to_cam).R0_rect,
                                  calib.R0_rect)
    expected = detector.detect(frame.image, lidar16(frame), calib)
    np.testing.assert_array_equal(detector.detect(frame.image, lidar16(frame), made).boxes, expected.boxes)


@pytest.mark.parametrize(("given", "message"), [
    ({"P2": np.eye(3)}, r"calib: P2: expected a 3×4 matrix .*got a float64 array of shape \(3, 3\)"),
    ({"P2": np.eye(4)}, r"calib: P2: expected a 3×4 matrix"),  # a projection has no homogeneous form
    ({"R0_rect": np.ones((4, 4))}, r"calib: R0_rect: a 4×4 matrix, but not a homogeneous one"),
    ({"Tr_velo_to_cam": np.ones((4, 4))}, r"calib: Tr_velo_to_cam: a 4×4 matrix, but not a homogeneous one"),
    ({"Tr_velo_to_cam": [["a"] * 4] * 3}, r"calib: Tr_velo_to_cam: expected a 3×4 matrix of numbers, got a list"),
    ({"R0_rect": np.zeros((3, 3))}, r"calib: R0_rect is singular"),
    ({"P2": np.full((3, 4), np.nan)}, r"calib: P2 has a non-finite value"),
])
def test_a_calibration_from_bad_matrices_names_the_one_at_fault(frames, given, message):
    calib = frames["000006"].calib
    matrices = {"P2": calib.P2, "R0_rect": calib.R0_rect, "Tr_velo_to_cam": calib.Tr_velo_to_cam, **given}
    with pytest.raises(InputError, match=f"^{message}"):
        Calibration.from_matrices(**matrices)


def test_records_name_each_box_with_a_quaternion_about_z(detector, frames):
    frame = frames["000006"]
    result = detector.detect(frame.image, lidar16(frame), frame.calib, score_threshold=0.05)
    records = result.as_records()
    assert len(records) == len(result.boxes) > 0
    for record, box, score in zip(records, result.boxes, result.scores, strict=True):
        assert (record.x, record.y, record.z, record.length, record.width, record.height, record.yaw) == tuple(box)
        assert record.score == score and record.label == "Car"
        qx, qy, qz, qw = record.quaternion_xyzw
        assert qx == qy == 0.0 and qz**2 + qw**2 == pytest.approx(1.0)
        # The quaternion turns +x onto the heading: (1 − 2qz², 2qz·qw) = (cos yaw, sin yaw).
        np.testing.assert_allclose([1 - 2 * qz**2, 2 * qz * qw], [np.cos(record.yaw), np.sin(record.yaw)], atol=1e-12)


def test_a_cloud_as_a_message_gives_it_is_taken_or_refused_by_name(detector, frames):
    """A PointCloud2 read as float64, strided (x y z intensity ring rows) and read-only, with the camera's
    BGR8 turned to RGB by a view: the same boxes. Three columns: an InputError saying what is missing."""
    frame = frames["000006"]
    points = lidar16(frame)
    expected = detector.detect(frame.image, points, frame.calib)
    rows = np.zeros((len(points), 5))
    rows[:, :4] = points
    message_points = rows[:, :4]
    message_points.setflags(write=False)
    bgr = np.ascontiguousarray(frame.image[..., ::-1])
    bgr.setflags(write=False)
    result = detector.detect(bgr[..., ::-1], message_points, frame.calib)
    np.testing.assert_allclose(result.boxes, expected.boxes, atol=1e-4)
    with pytest.raises(InputError, match=r"^points: .*got \(\d+, 3\), no reflectance column"):
        detector.detect(frame.image, points[:, :3], frame.calib)


def test_two_callback_threads_get_each_frames_serial_boxes(detector, frames):
    """Two threads each run every frame (in opposite orders, so that different frames overlap): each frame's
    boxes are those of a serial run, so no buffer of one frame leaks into another's."""
    inputs = {frame_id: (frame.image, lidar16(frame), frame.calib) for frame_id, frame in frames.items()}
    serial = {frame_id: detector.detect(*args, score_threshold=0.05) for frame_id, args in inputs.items()}
    orders = [list(inputs) * 2, list(reversed(inputs)) * 2]

    def run(order: list[str]) -> list[tuple[str, np.ndarray]]:
        return [(frame_id, detector.detect(*inputs[frame_id], score_threshold=0.05).boxes) for frame_id in order]

    with ThreadPoolExecutor(2) as pool:
        results = [pair for part in pool.map(run, orders) for pair in part]
    assert len(results) == 4 * len(inputs)
    for frame_id, boxes in results:
        assert boxes.shape == serial[frame_id].boxes.shape, frame_id
        np.testing.assert_allclose(boxes, serial[frame_id].boxes, rtol=1e-5, atol=1e-5, err_msg=frame_id)


def test_the_package_ships_its_type_marker():
    """PEP 561: without py.typed in the wheel a node's mypy or pyright treats pipeline as untyped."""
    assert files("pipeline").joinpath("py.typed").is_file()
    package_data = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    assert "py.typed" in package_data["pipeline"]
