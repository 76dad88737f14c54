"""Every warning carries a stable code an operator can alert on (pipeline.checks.WarningCode): in
``Detections.warning_codes`` beside the unchanged text, in the service's JSON ``warning_codes`` and
``X-Warning-Codes`` header, and counted in ``/metrics`` as ``lowres3d_frame_warnings_total{code}``.

Each warning is triggered on a real KITTI frame (tests/data) changed the way tests/test_sensor_faults.py and
tests/test_own_rig.py change it, run through the shipped models (weights/edge, weights/edge-lidar16) in ONNX
Runtime; the service runs the tiny exported models of tests/test_service.py in-process.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.beams import emulate_beams
from pipeline.calib import Calibration
from pipeline.checks import FRAME_WARNING_CODES, WarningCode
from pipeline.detector import Detections, Detector
from pipeline.frame import Frame, load_frame
from tests.conftest import KITTI
from tests.test_own_rig import _other_camera, _raised
from tests.test_service import FRAME, parts, service

WEIGHTS = Path(__file__).resolve().parents[1] / "weights"

# A frame as (image, points, calib), changed to trigger one warning.
Inputs = tuple[np.ndarray, np.ndarray, Calibration]


@pytest.fixture(scope="module")
def edge() -> Detector:
    return Detector(WEIGHTS / "edge")


@pytest.fixture(scope="module")
def kitti_frame() -> Frame:
    return load_frame(KITTI, "000006")


def _lidar16(f: Frame) -> np.ndarray:
    return emulate_beams(f.points, 16)


def _azimuth_deg(points: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan2(points[:, 1], points[:, 0]))


def _blocked(f: Frame) -> Inputs:
    points = _lidar16(f)
    return f.image, points[np.abs(_azimuth_deg(points)) > 10], f.calib


def _thin(f: Frame) -> Inputs:
    points = _lidar16(f)
    return f.image, points[np.random.default_rng(0).random(points.shape[0]) < 0.3], f.calib


def _stuck(f: Frame) -> Inputs:
    return f.image, np.zeros_like(_lidar16(f)), f.calib


def _dark(f: Frame) -> Inputs:
    points = _lidar16(f)
    points[:, 3] = 0.0
    return f.image, points, f.calib


def _millimetres(f: Frame) -> Inputs:
    points = _lidar16(f)
    points[:, :3] *= 1000.0
    return f.image, points, f.calib


def _doubled_image(f: Frame) -> Inputs:
    return cv2.resize(f.image, None, fx=2, fy=2), _lidar16(f), f.calib


def _big_camera(f: Frame) -> Inputs:
    image, calib = _other_camera(f.image, f.calib, 1920, 1080)
    return image, _lidar16(f), calib


def _vehicle_frame(f: Frame) -> Inputs:
    points, calib = _raised(_lidar16(f), f.calib, -1.73)
    return f.image, points, calib


# Each frame-path code the Detector makes, the change that triggers it, and how its warning's text begins (so the
# code is checked to sit at its own warning's index, not merely somewhere in the list).
TRIGGERS: dict[WarningCode, tuple[Callable[[Frame], Inputs], str]] = {
    WarningCode.BLOCKED_SECTOR: (_blocked, "points: no returns from azimuth -10° to 10°"),
    WarningCode.THIN_SCAN: (_thin, "points: only "),
    WarningCode.STUCK_RANGE: (_stuck, "points: 100% of the returns lie at one range"),
    WarningCode.BEAM_PATTERN: (lambda f: (f.image, emulate_beams(f.points, 16, mode="vlp16"), f.calib),
                               "points: the scan's beams are not those"),
    WarningCode.ROAD_LEVEL: (_vehicle_frame, "points: the road ahead lies far"),
    WarningCode.REFLECTANCE_SCALE: (_dark, "points: the scan's reflectance is on another scale"),
    WarningCode.CAMERA_VIEW: (_big_camera, "image: the depth net sees the bottom 352 rows"),
    WarningCode.CALIBRATION_MISFIT: (_doubled_image, "image and calib: P2's principal point"),
    WarningCode.LINE_COUNT: (lambda f: (f.image, f.points, f.calib), "points: as many as a 64-line scan"),
    WarningCode.OUT_OF_RANGE: (_millimetres, "points: almost none lie in the detection range"),
}


def _message_of(result: Detections, code: WarningCode) -> str:
    """The one warning with ``code``; the two lists have one entry per warning."""
    assert len(result.warning_codes) == len(result.warnings), (result.warning_codes, result.warnings)
    (index,) = [i for i, c in enumerate(result.warning_codes) if c == code]
    return result.warnings[index]


@pytest.mark.parametrize("code", list(TRIGGERS), ids=str)
def test_each_frame_warning_carries_its_code(edge, kitti_frame, code):
    """An operator alerts on the code, not the text (which holds the frame's figures): each warning the
    Detector makes on a changed frame has its own code at its own index, as a plain str."""
    change, start = TRIGGERS[code]
    result = edge.detect(*change(kitti_frame))
    message = _message_of(result, code)
    assert message.startswith(start), (code, result.warnings)
    assert json.dumps(result.warning_codes) == json.dumps([str(c) for c in result.warning_codes])


def test_a_clean_frame_has_no_codes_and_emulation_has_its_own(edge, kitti_frame):
    """The 16-line frame the model learned on carries no code; thinning a 64-line scan on request is coded
    ``beams_emulated`` (an operator filters it out), not ``line_count``."""
    clean = edge.detect(kitti_frame.image, _lidar16(kitti_frame), kitti_frame.calib)
    assert clean.warnings == [] and clean.warning_codes == []
    emulated = edge.detect(kitti_frame.image, kitti_frame.points, kitti_frame.calib, emulate_to_beams=16)
    assert emulated.warning_codes == [WarningCode.BEAMS_EMULATED]
    assert emulated.warnings[0].startswith("emulated 16 beams: kept")



def test_the_line_count_warnings_advice_is_each_entry_points_own_spelling(edge, kitti_frame):
    """The warning for a 64-line scan given to a 16-line model says how to thin it in each entry point; the
    Detector's keyword it names (it once said emulate_beams=16, the service's, which Detector.detect refuses
    with a TypeError) clears the warning when followed as written."""
    message = _message_of(edge.detect(kitti_frame.image, kitti_frame.points, kitti_frame.calib), WarningCode.LINE_COUNT)
    for spelling in ("--emulate-beams 16 to the commands", "emulate_beams=16 to the service",
                     "emulate_to_beams=16 to Detector.detect"):
        assert spelling in message, message
    followed = edge.detect(kitti_frame.image, kitti_frame.points, kitti_frame.calib, emulate_to_beams=16)
    assert WarningCode.LINE_COUNT not in followed.warning_codes

def test_codes_are_the_same_with_the_stage_thread_and_without(kitti_frame):
    """The rig's checks run beside the depth net on a second thread or in turn: the same codes either way."""
    image, points, calib = _blocked(kitti_frame)
    points = points.copy()
    points[:, 3] = 0.0  # a second rig warning, made on the same thread as the first
    codes = [Detector(WEIGHTS / "edge", stage_threads=n).detect(image, points, calib).warning_codes for n in (1, 2)]
    assert codes[0] == codes[1] == [WarningCode.BLOCKED_SECTOR, WarningCode.REFLECTANCE_SCALE]


def test_a_lidar_only_model_codes_its_warnings_too(kitti_frame):
    """The LiDAR-only model runs the checks on its own path: a blocked sector and a thin scan are coded there."""
    lidar = Detector(WEIGHTS / "edge-lidar16")
    assert _message_of(lidar.detect(None, _blocked(kitti_frame)[1], None), WarningCode.BLOCKED_SECTOR)
    assert _message_of(lidar.detect(None, _thin(kitti_frame)[1], None), WarningCode.THIN_SCAN).startswith("points: only ")


def test_load_warnings_carry_their_codes(tiny_models, client_of):
    """Loading untrained weights is coded ``untrained_weights`` on the Detector and in ``/v1/model``."""
    detector = Detector(tiny_models)
    assert detector.load_warning_codes == [WarningCode.UNTRAINED_WEIGHTS]
    assert "untrained" in detector.load_warnings[0]
    info = client_of.get("/v1/model").json()
    assert info["warning_codes"] == ["untrained_weights"] and len(info["warnings"]) == 1
    # /metrics too, for an alert on a vehicle that loaded the wrong models: 1 for the code, 0 for the others.
    gauges = dict(re.findall(r'^lowres3d_model_warnings{code="(\w+)"} (\S+)$', client_of.get("/metrics").text,
                             re.MULTILINE))
    assert gauges == {"untrained_weights": "1.0", "provider_fallback": "0.0", "int8_saturation": "0.0",
                      "fp16_on_cpu": "0.0"}


# --------------------------------------------------------------------------- the service
@pytest.fixture(scope="module")
def client_of(tiny_models):
    """A service of its own (conftest's tiny models), so its /metrics count this module's frames alone."""
    with service(tiny_models) as app_client:
        yield app_client


@pytest.fixture(scope="module")
def frame() -> dict[str, bytes]:
    """The raw files of the service tests' KITTI frame: PNG image, 64-line scan, calibration."""
    return {part: (KITTI / folder / f"{FRAME}{suffix}").read_bytes()
            for part, folder, suffix in (("image", "image_2", ".png"), ("points", "velodyne", ".bin"),
                                         ("calib", "calib", ".txt"))}


def _blocked_scan(raw: bytes) -> bytes:
    points = np.frombuffer(raw, "<f4").reshape(-1, 4)
    return points[np.abs(_azimuth_deg(points)) > 10].tobytes()


def _counted(client, code: str) -> float:
    match = re.search(rf'^lowres3d_frame_warnings_total{{code="{code}"}} (\S+)$', client.get("/metrics").text, re.MULTILINE)
    assert match, f"no lowres3d_frame_warnings_total series for {code}"
    return float(match.group(1))


def test_the_json_answer_and_the_headers_carry_the_codes(client_of, frame):
    """The service's own warning (non-finite rows dropped) and the Detector's come with their codes, in the JSON
    answer beside ``warnings`` and in ``X-Warning-Codes`` beside ``X-Warnings``, in the same order."""
    points = np.frombuffer(frame["points"], "<f4").reshape(-1, 4).copy()
    points[:3, 0] = np.nan
    params = {"emulate_beams": 16, "score_threshold": 0.0}
    body = client_of.post("/v1/detect", params=params, files=parts(frame, points=points.tobytes())).json()
    assert body["warning_codes"][:2] == ["nonfinite_dropped", "beams_emulated"], body
    assert len(body["warning_codes"]) == len(body["warnings"])
    assert body["warnings"][0] == "points: dropped 3 rows with NaN or infinite values"
    for route, extra in (("/v1/detect", {"format": "kitti"}), ("/v1/detect/bev.png", {}), ("/v1/detect/camera.png", {})):
        response = client_of.post(route, params={**params, **extra}, files=parts(frame, points=points.tobytes()))
        assert response.status_code == 200, response.text
        assert json.loads(response.headers["x-warning-codes"]) == body["warning_codes"]
        assert json.loads(response.headers["x-warnings"]) == body["warnings"]
    thinned = np.frombuffer(frame["points"], "<f4").reshape(-1, 4)[::8].tobytes()  # no warning at all
    quiet = client_of.post("/v1/detect", params={"format": "kitti"}, files=parts(frame, points=thinned))
    assert quiet.status_code == 200 and "x-warning-codes" not in quiet.headers


def test_metrics_count_each_code_per_frame(client_of, frame):
    """``lowres3d_frame_warnings_total{code}`` has a series at 0 for every frame code from the start (a rate has a
    base) and counts each frame's codes, whichever route answered it; nothing else grows the label's values."""
    before = {code: _counted(client_of, code) for code in FRAME_WARNING_CODES}
    blocked = parts(frame, points=_blocked_scan(frame["points"]))
    for route, extra in (("/v1/detect", {}), ("/v1/detect", {"format": "kitti"}), ("/v1/detect/bev.png", {})):
        response = client_of.post(route, params=extra, files=blocked)
        assert response.status_code == 200, response.text
        codes = response.json()["warning_codes"] if extra == {} and route == "/v1/detect" else \
            json.loads(response.headers["x-warning-codes"])
        assert "blocked_sector" in codes, (route, extra, codes)
    assert _counted(client_of, "blocked_sector") == before["blocked_sector"] + 3
    text = client_of.get("/metrics").text
    labels = set(re.findall(r'^lowres3d_frame_warnings_total\{code="([^"]+)"\}', text, re.MULTILINE))
    assert labels == {*map(str, FRAME_WARNING_CODES), "other"}
