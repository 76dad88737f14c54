"""The detection service end to end in-process: real tiny ONNX models, a real KITTI frame, httpx over ASGI.

Each test talks HTTP to the FastAPI app (lifespan included) through
``httpx.ASGITransport``; the app loads a model directory exported with the
``tiny`` preset once per session. Real uvicorn processes are in
``test_service_process.py``.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import os
import re
import struct
import threading
import time
import typing
import zlib
from collections.abc import AsyncIterator, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Literal, Self
from unittest.mock import ANY

import anyio.from_thread
import cv2
import httpx
import numpy as np
import pytest

from pipeline.beams import emulate_beams
from pipeline.boxes import bev_corners, in_camera_view
from pipeline.detector import MAX_POINTS, Cancellation
from pipeline.kitti import parse_calib, parse_labels
from pipeline.presets import PRESETS
from pipeline.render import (
    PREDICTION_BGR,
    PSEUDO_BGR,
    draw_key,
    key_rows,
    render_bev,
)
from service.__main__ import _OPTIONS, settings_from_args
from service.app import create_app
from service.metrics import Metrics
from service.pool import InferencePool, PoolFull, PoolTimeout
from service.routes.detect import picture_title
from service.settings import Settings

KITTI = Path(__file__).parent / "data" / "kitti" / "training"
FRAME = "000006"
STAGES = {"queue_wait", "parse_inputs", "prepare", "depth_net", "ray_table", "pseudo_points", "voxelize", "pixor", "decode", "total"}


# --------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="session")
def tiny_models(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A model directory exported with the ``tiny`` preset (untrained weights), shared by the session."""
    out = tmp_path_factory.getbasetemp() / "service-tiny-models"
    if not (out / "manifest.json").is_file():
        from export.exporter import ExportConfig, run

        run(ExportConfig(preset="tiny", out=out, parity=False))
    return out


@pytest.fixture(scope="session")
def frame() -> dict[str, bytes]:
    """The raw files of KITTI frame 000006: PNG image, 64-line velodyne scan, calibration."""
    return {
        "image": (KITTI / "image_2" / f"{FRAME}.png").read_bytes(),
        "points": (KITTI / "velodyne" / f"{FRAME}.bin").read_bytes(),
        "calib": (KITTI / "calib" / f"{FRAME}.txt").read_bytes(),
    }


def parts(frame: dict[str, bytes], **replace: bytes | None) -> dict[str, tuple[str, bytes, str]]:
    """Multipart files for httpx; ``replace`` swaps a part's bytes, None leaves it out."""
    names = {"image": ("000006.png", "image/png"), "points": ("000006.bin", "application/octet-stream"),
             "calib": ("000006.txt", "text/plain")}
    files = {}
    for key, (filename, content_type) in names.items():
        data = replace.get(key, frame[key]) if key in replace else frame[key]
        if data is not None:
            files[key] = (filename, data, content_type)
    return files


class AppClient:
    """A synchronous httpx client for an ASGI app: runs the app's lifespan and the requests on one
    event loop in a background thread (an anyio blocking portal), so tests can also send requests
    from several threads at once."""

    def __init__(self, app: Any) -> None:
        self.app = app

    def __enter__(self) -> Self:
        self._portal_cm = anyio.from_thread.start_blocking_portal()
        self.portal = self._portal_cm.__enter__()
        self._lifespan = self.app.router.lifespan_context(self.app)
        self.portal.call(self._lifespan.__aenter__)
        transport = httpx.ASGITransport(app=self.app, raise_app_exceptions=False)
        self._client = httpx.AsyncClient(transport=transport, base_url="http://service", timeout=60)
        return self

    def request(self, method: str, url: str, **kwargs: Any) -> httpx.Response:
        return self.portal.call(functools.partial(self._client.request, method, url, **kwargs))

    def get(self, url: str, **kwargs: Any) -> httpx.Response:
        return self.request("GET", url, **kwargs)

    def post(self, url: str, **kwargs: Any) -> httpx.Response:
        return self.request("POST", url, **kwargs)

    def wait_ready(self, timeout_s: float = 20.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.get("/readyz").status_code == 200:
                return
            time.sleep(0.02)
        raise TimeoutError("the app did not become ready")

    def __exit__(self, *exc: object) -> None:
        self.portal.call(self._client.aclose)
        self.portal.call(self._lifespan.__aexit__, None, None, None)
        self._portal_cm.__exit__(None, None, None)


@contextmanager
def service(models: Path, **overrides: Any) -> Iterator[AppClient]:
    """A ready app on ``models`` with Settings overrides."""
    with AppClient(create_app(Settings(models=models, **overrides))) as client:
        client.wait_ready()
        yield client


@pytest.fixture(scope="module")
def client(tiny_models: Path) -> Iterator[AppClient]:
    """The default configuration: 2 workers, shared session, no token, no default calibration."""
    with service(tiny_models) as app_client:
        yield app_client


def assert_error(response: httpx.Response, status: int, code: str, *words: str) -> dict:
    """The response is the JSON error shape with this status and code; its message mentions ``words``."""
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/json")
    error = response.json()["error"]
    assert error["code"] == code, error
    for word in words:
        assert word in error["message"], error
    assert error["request_id"] == response.headers["x-request-id"]
    return error


# --------------------------------------------------------------------------- the contract
def test_detect_json_contract(client: AppClient, frame: dict[str, bytes], tiny_models: Path) -> None:
    response = client.post("/v1/detect", params={"score_threshold": 0.0}, files=parts(frame))
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["request_id"] == response.headers["x-request-id"]
    manifest = json.loads((tiny_models / "manifest.json").read_text())
    assert body["model"]["preset"] == "tiny"
    assert body["model"]["sha256"] == {name: entry["sha256"] for name, entry in manifest["files"].items()}
    assert body["model"]["sha256"]["pixor.onnx"] == hashlib.sha256((tiny_models / "pixor.onnx").read_bytes()).hexdigest()
    assert STAGES <= set(body["timings_ms"])
    detector_ms = sum(v for k, v in body["timings_ms"].items() if k != "total")
    assert body["timings_ms"]["total"] >= detector_ms * 0.99
    assert body["warnings"] == []
    # score 0 keeps every NMS survivor of the untrained tiny PIXOR: boxes to check the geometry on.
    assert body["detections"]
    scores = [d["score"] for d in body["detections"]]
    assert scores == sorted(scores, reverse=True)
    for detection in body["detections"]:
        assert detection["label"] == "Car"
        box = detection["box"]
        as_array = np.array([[box[k] for k in ("x", "y", "z", "l", "w", "h", "yaw")]])
        assert np.isfinite(as_array).all() and box["l"] > 0 and box["w"] > 0 and box["h"] > 0
        np.testing.assert_allclose(detection["bev_corners"], bev_corners(as_array)[0], atol=1e-9)


def test_detect_default_threshold_and_beam_emulation(frame: dict[str, bytes]) -> None:
    """Without ``score_threshold`` the model's own (its manifest's preset: 0.5) decides. The shipped 16-line PIXOR,
    read only, since the tiny models' untrained scores never reach 0.5 and an empty answer would pass any default."""
    models = Path(__file__).resolve().parents[1] / "weights" / "edge-lidar16"
    default = json.loads((models / "manifest.json").read_text())["preset_config"]["decode"]["score_threshold"]
    with service(models) as app_client:
        response = app_client.post("/v1/detect", params={"emulate_beams": 16}, files=parts(frame))
        assert response.status_code == 200, response.text
        body = response.json()
        lower = app_client.post("/v1/detect", params={"emulate_beams": 16, "score_threshold": default / 2},
                                files=parts(frame)).json()["detections"]
    assert "emulate_beams" in body["timings_ms"]
    kept = [w for w in body["warnings"] if w.startswith("emulated 16 beams: kept")]
    assert len(kept) == 1 and int(kept[0].split()[4]) < len(frame["points"]) // 16, kept  # points were dropped
    scores = [d["score"] for d in body["detections"]]
    assert scores and min(scores) >= default, scores
    assert len(lower) > len(scores)  # the default did cut: a lower threshold keeps more boxes
    assert min(d["score"] for d in lower) < default


def test_detect_kitti_lines_match_json(client: AppClient, frame: dict[str, bytes]) -> None:
    params = {"score_threshold": 0.0}
    as_json = client.post("/v1/detect", params=params, files=parts(frame)).json()
    response = client.post("/v1/detect", params={**params, "format": "kitti"}, files=parts(frame))
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/plain")
    objects = parse_labels(response.text, "response")
    # KITTI results hold the boxes the camera sees, in the JSON answer's order.
    boxes = np.array([[d["box"][k] for k in ("x", "y", "z", "l", "w", "h", "yaw")] for d in as_json["detections"]])
    seen = in_camera_view(boxes, parse_calib(frame["calib"].decode(), "calib"), (375, 1242))
    expected = [d for d, keep in zip(as_json["detections"], seen, strict=True) if keep]
    assert 0 < len(objects) == len(expected) < len(boxes)
    # A label_2 file's lines, each ended: answers appended to one file stay one object a line.
    assert response.text.endswith("\n") and response.text.count("\n") == len(objects)
    # Which model answered, as on the JSON answer (the body has no room for it).
    model = as_json["model"]
    assert (response.headers["x-model-id"], response.headers["x-model-preset"], response.headers["x-model-precision"]) \
        == (model["id"], model["preset"], model["precision"])
    for obj, detection in zip(objects, expected, strict=True):
        assert obj.type == "Car"
        assert obj.score == pytest.approx(detection["score"], abs=1e-4)
        assert obj.dimensions == pytest.approx((detection["box"]["h"], detection["box"]["w"], detection["box"]["l"]), abs=0.01)


def test_bev_png(client: AppClient, frame: dict[str, bytes]) -> None:
    response = client.post("/v1/detect/bev.png", params={"score_threshold": 0.0}, files=parts(frame))
    assert response.status_code == 200
    assert response.headers["content-type"] == "image/png"
    picture = cv2.imdecode(np.frombuffer(response.content, np.uint8), cv2.IMREAD_COLOR)
    # The tiny grid's scene (x 0–70.4 m up, y −40–40 m across, 0.1 m pixels: 704 × 800) under the key's strip.
    assert picture.shape[1:] == (800, 3) and picture.shape[0] > 704
    assert (picture == PREDICTION_BGR).all(axis=2).any()  # predicted boxes drawn in orange


def test_bev_png_draws_the_scan_over_the_pseudo_points_and_the_cameras_view(client: AppClient,
                                                                          frame: dict[str, bytes]) -> None:
    """bev.png drew the scan and the camera's pseudo points in one grey and no camera view; now as pipeline.detect
    draws its BEV: each pixel of the scan thinned to 16 lines grey, magenta where pseudo points alone fall, and
    the lines of the camera's view from the frame's calibration."""
    response = client.post("/v1/detect/bev.png", params={"emulate_beams": 16}, files=parts(frame))
    assert response.status_code == 200, response.text
    picture = cv2.imdecode(np.frombuffer(response.content, np.uint8), cv2.IMREAD_COLOR).astype(int)
    grid = PRESETS["tiny"].bev
    calib = parse_calib(frame["calib"].decode(), "calib")
    view = (calib, cv2.imdecode(np.frombuffer(frame["image"], np.uint8), cv2.IMREAD_COLOR).shape[:2])
    blank = render_bev(np.zeros((0, 4), np.float32), grid).astype(int)  # the rings, their labels, the sensor
    alone = render_bev(np.zeros((0, 4), np.float32), grid, view=view).astype(int)  # and the view
    picture = picture[-blank.shape[0]:]  # the scene, below the key's strip
    free = (alone == 0).all(axis=2)
    # The scan's returns: grey (on top of the pseudo points) in every pixel they fall in.
    scan = emulate_beams(np.frombuffer(frame["points"], "<f4").reshape(-1, 4), 16)
    rows = np.floor((grid.x_max - scan[:, 0]) / 0.1).astype(int)
    cols = np.floor((grid.y_max - scan[:, 1]) / 0.1).astype(int)
    inside = (rows >= 0) & (rows < picture.shape[0]) & (cols >= 0) & (cols < picture.shape[1])
    returns = np.zeros(picture.shape[:2], bool)
    returns[rows[inside], cols[inside]] = True
    returns &= free
    grey = (picture[..., 0] == picture[..., 1]) & (picture[..., 1] == picture[..., 2]) & (picture[..., 0] > 0)
    assert returns.sum() > 2000 and grey[returns].all()
    # The pseudo points: magenta (blue and red equal, green lower), never where a return is.
    magenta = (picture[..., 0] == picture[..., 2]) & (picture[..., 0] > picture[..., 1] + 20) & free
    assert magenta.sum() > 1000 and not (magenta & returns).any()
    shade = picture[magenta] / np.array(PSEUDO_BGR)  # the pseudo colour times the density's shade
    assert (np.abs(shade - shade[:, :1]) * np.array(PSEUDO_BGR) <= 1).all() and shade.max() <= 1
    # The camera's view: its lines' bright core (anti-aliased, off the rings) drawn as on an empty picture, but
    # where a point lies under an edge pixel.
    core = (alone != blank).any(axis=2) & (blank == 0).all(axis=2) & (alone >= 100).all(axis=2)
    assert core.sum() > 500 and (picture[core] == alone[core]).all(axis=1).mean() > 0.9


def test_camera_png_draws_the_boxes_of_the_kitti_answer(client: AppClient, frame: dict[str, bytes]) -> None:
    """camera.png: the uploaded image with the boxes format=kitti answers (those the camera sees) as wireframes:
    each box's projected 2D extent (the KITTI line's bbox) holds the detections' orange, and no orange is outside
    them but the key's swatch (top right, as pipeline.render draws it, titled with the model) and the scores (above
    a box, up to three label heights when the first spot is taken, or under it)."""
    params = {"score_threshold": 0.0}
    response = client.post("/v1/detect/camera.png", params=params, files=parts(frame))
    assert response.status_code == 200 and response.headers["content-type"] == "image/png"
    picture = cv2.imdecode(np.frombuffer(response.content, np.uint8), cv2.IMREAD_COLOR)
    image = cv2.imdecode(np.frombuffer(frame["image"], np.uint8), cv2.IMREAD_COLOR)
    assert picture.shape == image.shape
    objects = parse_labels(client.post("/v1/detect", params={**params, "format": "kitti"}, files=parts(frame)).text,
                           "response")
    orange = (picture == PREDICTION_BGR).all(axis=2) & ~(image == PREDICTION_BGR).all(axis=2)
    assert objects and orange.any()
    # The key: where draw_key puts the service's rows (its title first) on a picture of this size; its swatch is
    # the one orange allowed outside the boxes.
    title = picture_title(client.app.state.runtime.identity, None)
    left, top, right, bottom = draw_key(np.zeros_like(picture), key_rows(title, True, False), corner="top-right")
    key = np.zeros_like(orange)
    key[top:bottom + 1, left:right + 1] = True
    covered = key.copy()
    # A score's label: above its box, moved up by one or two label heights (8 px apart) or right by its width
    # when another label or the key is there, else under the box (pipeline.render.render_camera).
    (text_w, text_h), _ = cv2.getTextSize("0.00", cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
    above, below, beside = 4 + 2 * (text_h + 8) + text_h + 3, text_h + 9, 2 * text_w + 14
    for obj in objects:
        left, top, right, bottom = (round(v) for v in obj.bbox)
        assert orange[top:bottom + 1, left:right + 1].any()
        covered[max(top - above, 0):bottom + below, max(left - 3, 0):max(right + 45, left + beside)] = True
    assert not (orange & ~covered).any()


def test_jpeg_image_accepted(client: AppClient, frame: dict[str, bytes]) -> None:
    bgr = cv2.imdecode(np.frombuffer(frame["image"], np.uint8), cv2.IMREAD_COLOR)
    jpeg = cv2.imencode(".jpg", bgr)[1].tobytes()
    response = client.post("/v1/detect", files=parts(frame, image=jpeg))
    assert response.status_code == 200, response.text


def _with_exif_orientation(jpeg: bytes, orientation: int) -> bytes:
    """The JPEG with an EXIF APP1 segment right after its start marker holding one tag, Orientation (0x0112)."""
    entry = struct.pack(">HHIHH", 0x0112, 3, 1, orientation, 0)  # tag, SHORT, one value, the value, padding
    tiff = b"MM\x00\x2a" + struct.pack(">I", 8) + struct.pack(">H", 1) + entry + struct.pack(">I", 0)
    app1 = b"\xff\xe1" + struct.pack(">H", 2 + 6 + len(tiff)) + b"Exif\x00\x00" + tiff
    assert jpeg.startswith(b"\xff\xd8")
    return jpeg[:2] + app1 + jpeg[2:]


@pytest.mark.parametrize("orientation", [3, 6])
def test_jpeg_exif_orientation_is_not_applied(orientation: int) -> None:
    """The calibration describes the pixels as the sensor stored them: a JPEG's EXIF Orientation (3: turned
    half-way, 6: a quarter) must not turn them, or every projection would miss."""
    from pipeline.kitti import decode_image

    picture = np.zeros((48, 64, 3), np.uint8)
    picture[:16, :24] = (255, 0, 0)  # a corner mark that any turn moves
    jpeg = cv2.imencode(".jpg", picture)[1].tobytes()
    tagged = _with_exif_orientation(jpeg, orientation)
    def turned(data: bytes) -> np.ndarray:
        return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)

    assert not np.array_equal(turned(tagged), turned(jpeg))  # the tag is one OpenCV reads: the test can fail
    np.testing.assert_array_equal(decode_image(tagged, "image"), decode_image(jpeg, "image"))


def test_jpeg_with_exif_orientation_detects_as_without(client: AppClient, frame: dict[str, bytes]) -> None:
    bgr = cv2.imdecode(np.frombuffer(frame["image"], np.uint8), cv2.IMREAD_COLOR)
    jpeg = cv2.imencode(".jpg", bgr)[1].tobytes()
    params = {"score_threshold": 0.0}
    plain = client.post("/v1/detect", params=params, files=parts(frame, image=jpeg))
    tagged = client.post("/v1/detect", params=params, files=parts(frame, image=_with_exif_orientation(jpeg, 6)))
    assert plain.status_code == tagged.status_code == 200, tagged.text
    assert tagged.json()["detections"] == plain.json()["detections"]


def test_nonfinite_points_dropped_with_warning(client: AppClient, frame: dict[str, bytes]) -> None:
    points = np.frombuffer(frame["points"], "<f4").reshape(-1, 4).copy()
    points[:5, 0] = np.nan
    points[5:7, 2] = np.inf
    response = client.post("/v1/detect", files=parts(frame, points=points.tobytes()))
    assert response.status_code == 200, response.text
    assert "points: dropped 7 rows with NaN or infinite values" in response.json()["warnings"]
    rejected = client.post("/v1/detect", params={"nonfinite": "reject"}, files=parts(frame, points=points.tobytes()))
    assert_error(rejected, 422, "invalid_input", "points", "7 rows", "NaN")
    assert "send nonfinite=drop" in rejected.json()["error"]["message"]


def test_a_big_endian_scan_is_named_as_such(client: AppClient, frame: dict[str, bytes]) -> None:
    """A scan of big-endian floats: some of its rows read as NaN, the rest as garbage. Either policy's 422 says
    what the file is and how to convert it, rather than to drop the NaN rows or that the rows are misread."""
    points = np.frombuffer(frame["points"], "<f4").reshape(-1, 4)
    big_endian = points.astype(">f4").tobytes()
    for policy in ("reject", "drop"):
        response = client.post("/v1/detect", params={"nonfinite": policy}, files=parts(frame, points=big_endian))
        assert_error(response, 422, "invalid_input", "points", "the file's floats look big-endian",
                     "np.fromfile(path, '>f4')")
        assert "nonfinite=drop" not in response.json()["error"]["message"]


def test_default_calibration(tiny_models: Path, frame: dict[str, bytes]) -> None:
    with service(tiny_models, default_calib=KITTI / "calib" / f"{FRAME}.txt") as app_client:
        response = app_client.post("/v1/detect", files=parts(frame, calib=None))
        assert response.status_code == 200, response.text
        assert app_client.get("/v1/model").json()["default_calib"] is True


BOM = b"\xef\xbb\xbf"  # the UTF-8 byte-order mark some editors (Notepad) put in front of a text file


def _bom_calib(calib: bytes) -> bytes:
    """The calibration cut to the keys the detector needs, P2 first, behind a UTF-8 byte-order mark: the
    layout where a BOM left in the text hides the first key (\\ufeffP2), which plain 'utf-8' misread as no P2."""
    needed = [line for line in calib.splitlines() if line.split(b":")[0] in (b"P2", b"R0_rect", b"Tr_velo_to_cam")]
    assert needed[0].startswith(b"P2:")
    return BOM + b"\n".join(needed) + b"\n"


def test_calib_with_byte_order_mark_accepted(client: AppClient, frame: dict[str, bytes]) -> None:
    params = {"score_threshold": 0.0}
    plain = client.post("/v1/detect", params=params, files=parts(frame)).json()
    response = client.post("/v1/detect", params=params, files=parts(frame, calib=_bom_calib(frame["calib"])))
    assert response.status_code == 200, response.text
    assert response.json()["detections"] == plain["detections"]  # the same calibration was read


def test_default_calibration_with_byte_order_mark(tiny_models: Path, frame: dict[str, bytes], tmp_path: Path) -> None:
    path = tmp_path / "calib_bom.txt"
    path.write_bytes(_bom_calib(frame["calib"]))
    with service(tiny_models, default_calib=path) as app_client:
        response = app_client.post("/v1/detect", files=parts(frame, calib=None))
        assert response.status_code == 200, response.text


# --------------------------------------------------------------------------- bad inputs
def _jpeg(png: bytes) -> bytes:
    """The same picture as a JPEG."""
    return cv2.imencode(".jpg", cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR))[1].tobytes()


def _chunk(kind: bytes, data: bytes) -> bytes:
    """A PNG chunk: length, type, data, CRC (right: a damaged chunk is refused as such)."""
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _png_header(width: int, height: int, bit_depth: int = 8, colour_type: int = 2) -> bytes:
    """A PNG's signature and IHDR chunk (8-bit truecolour unless said)."""
    fields = struct.pack(">IIBBBBB", width, height, bit_depth, colour_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", fields)


BAD_PARTS = {
    "empty image": ({"image": b""}, 422, "invalid_input", ("image", "empty")),
    "corrupt png": ({"image": _png_header(1242, 375) + b"\x00" * 500}, 422, "invalid_input", ("image", "PNG cut off")),
    "no IHDR": ({"image": b"\x89PNG\r\n\x1a\n" + b"\x00" * 40}, 422, "invalid_input", ("image", "IHDR")),
    # Fields PNG does not allow: refused by name before libpng, which writes stderr lines past the log for them.
    "png bit depth": ({"image": _png_header(1242, 375, bit_depth=3) + b"\x00" * 500}, 422, "invalid_input",
                      ("image", "truecolour (colour type 2) a bit depth of 3", "(8, 16)")),
    "png colour type": ({"image": _png_header(1242, 375, colour_type=5) + b"\x00" * 500}, 422, "invalid_input",
                        ("image", "colour type 5")),
    "gif image": ({"image": b"GIF89a" + b"\x00" * 100}, 415, "unsupported_media_type", ("image", "PNG or JPEG")),
    # Fill bytes walked one at a time (up to the body limit: 32 MB of Python steps) until a bounded walk.
    "jpeg of fill bytes": ({"image": b"\xff\xd8" + b"\xff" * 100_000}, 422, "invalid_input",
                           ("image", "no frame header in its first 1000 segments")),
    "text image": ({"image": b"hello"}, 415, "unsupported_media_type", ("image",)),
    "decompression bomb": ({"image": _png_header(60000, 60000)}, 422, "invalid_input", ("image", "limit")),
    "scan size": ({"points": b"\x00" * 100}, 422, "invalid_input", ("points", "100 bytes", "multiple of 16")),
    # A camera image sent as the scan: named for what it is, whatever its size (KITTI's 000006.png is 16-aligned).
    "image as points": ({"points": _png_header(8, 8) + b"\x00" * 7}, 422, "invalid_input",
                        ("points: a PNG image, not a KITTI scan",)),
    "zero points": ({"points": b""}, 422, "invalid_input", ("points", "empty")),
    "all nan": ({"points": np.full((10, 4), np.nan, np.float32).tobytes()}, 422, "invalid_input", ("points", "no finite")),
    "calib missing keys": ({"calib": b"P2: 1 0 0 0 0 1 0 0 0 0 1 0\n"}, 422, "invalid_input", ("calib", "R0_rect")),
    "calib malformed": ({"calib": b"P2: 1 2 three\nR0_rect: 1\n"}, 422, "invalid_input", ("calib", "line 1", "non-numeric")),
    "calib short row": ({"calib": b"P2: 1 2 3\n"}, 422, "invalid_input", ("calib", "P2 needs 12 numbers")),
    "calib no colon": ({"calib": b"garbage line\n"}, 422, "invalid_input", ("calib", "KEY: numbers")),
    "calib binary": ({"calib": b"\xff\xfe\x00\x81"}, 422, "invalid_input", ("calib", "not text")),
    "calib empty": ({"calib": b"  \n"}, 422, "invalid_input", ("calib", "empty")),
    "calib too big": ({"calib": b"P2: " + b"0 " * 40000}, 422, "invalid_input", ("calib", "80004 bytes", "65536")),
    "missing points": ({"points": None}, 422, "invalid_input", ("points", "required")),
    "missing image": ({"image": None}, 422, "invalid_input", ("image", "required")),
    "missing calib, no default": ({"calib": None}, 422, "invalid_input", ("calib", "default")),
}


@pytest.mark.parametrize("case", list(BAD_PARTS), ids=list(BAD_PARTS))
def test_bad_parts_answer_4xx_naming_the_part(client: AppClient, frame: dict[str, bytes], case: str) -> None:
    replace, status, code, words = BAD_PARTS[case]
    response = client.post("/v1/detect", files=parts(frame, **replace))
    assert_error(response, status, code, *words)


def test_image_smaller_than_crop(client: AppClient, frame: dict[str, bytes]) -> None:
    small = cv2.imencode(".png", np.zeros((200, 600, 3), np.uint8))[1].tobytes()
    response = client.post("/v1/detect", files=parts(frame, image=small))
    assert_error(response, 422, "invalid_input", "image", "600×200", "1216×352")


def test_too_many_points(tiny_models: Path, frame: dict[str, bytes]) -> None:
    with service(tiny_models, max_points=1000) as app_client:
        response = app_client.post("/v1/detect", files=parts(frame))
        assert_error(response, 422, "invalid_input", "points", "110089 points", "limit of 1000")


@pytest.mark.parametrize(
    ("params", "field"),
    [({"score_threshold": 2}, "score_threshold"), ({"score_threshold": "high"}, "score_threshold"),
     ({"emulate_beams": 15}, "emulate_beams"), ({"format": "xml"}, "format"), ({"nonfinite": "keep"}, "nonfinite")],
)
def test_bad_query_names_the_field(client: AppClient, frame: dict[str, bytes], params: dict, field: str) -> None:
    error = assert_error(client.post("/v1/detect", params=params, files=parts(frame)), 422, "invalid_input", field)
    assert error["message"].startswith(f"{field}: "), error  # the parameter as sent, not where FastAPI found it


@pytest.mark.parametrize("value", ["nan", "NaN", "inf", "-inf"])
def test_non_finite_score_threshold_names_the_field(client: AppClient, frame: dict[str, bytes], value: str) -> None:
    response = client.post("/v1/detect", params={"score_threshold": value}, files=parts(frame))
    error = assert_error(response, 422, "invalid_input", "score_threshold", "finite number")
    assert "less than" not in error["message"]  # not the range check's misleading answer


@pytest.mark.parametrize(
    ("route", "params", "words", "accepted"),
    [("/v1/detect", {"emulate_beam": 16, "foo": "bar"},
      ("emulate_beam: unknown query parameter (did you mean emulate_beams?)", "foo: unknown query parameter;"),
      "format, score_threshold, emulate_beams, nonfinite, image_stamp_ns, points_stamp_ns"),
     ("/v1/detect/bev.png", {"format": "kitti"}, ("format: unknown query parameter",),
      "score_threshold, emulate_beams, nonfinite, image_stamp_ns, points_stamp_ns")],
    ids=["detect typo", "bev.png has no format"],
)
def test_unknown_query_parameter_is_422_naming_it(
    client: AppClient, frame: dict[str, bytes], route: str, params: dict, words: tuple[str, ...], accepted: str
) -> None:
    error = assert_error(client.post(route, params=params, files=parts(frame)), 422, "invalid_input", *words)
    assert error["message"].endswith(f"accepted query parameters: {accepted}")


def test_query_check_leaves_open_routes_alone(client: AppClient) -> None:
    """Routes that take no query options keep ignoring a query (cache-busting probes, scrapers)."""
    for route in ("/healthz", "/readyz", "/v2/health/live", "/v2/health/ready", "/metrics", "/docs", "/openapi.json"):
        assert client.get(route, params={"foo": "bar", "_": "1"}).status_code == 200, route


@pytest.mark.parametrize(
    ("kwargs", "shown"),
    [({"json": {"image": "x"}}, "application/json"), ({"content": b"raw", "headers": {"content-type": "image/png"}}, "image/png"),
     ({"data": {"image": "x"}}, "application/x-www-form-urlencoded"), ({}, "none")],
)
def test_non_multipart_body_is_415(client: AppClient, kwargs: dict, shown: str) -> None:
    for route in ("/v1/detect", "/v1/detect/bev.png", "/v1/detect/camera.png"):
        assert_error(client.post(route, **kwargs), 415, "unsupported_media_type", "multipart/form-data", shown)


def test_malformed_multipart_is_400_not_500(client: AppClient) -> None:
    """A body that claims multipart but has no parsable part (found by the OpenAPI fuzzer) is documented."""
    boundary = "0d37f771f3609e9baf6be26654101f5f"
    response = client.post("/v1/detect", content=f"--{boundary}\r\nTrue--{boundary}--\r\n".encode(),
                           headers={"content-type": f"multipart/form-data; boundary={boundary}"})
    assert_error(response, 400, "bad_request", "multipart")
    assert "400" in client.get("/openapi.json").json()["paths"]["/v1/detect"]["post"]["responses"]


def _multipart_body(frame: dict[str, bytes], calib: bytes) -> tuple[bytes, dict[str, str]]:
    """The bytes and Content-Type of the multipart body httpx sends for the frame with this calib part."""
    request = httpx.Request("POST", "http://service/v1/detect", files=parts(frame, calib=calib))
    return request.read(), {"content-type": request.headers["content-type"]}


def test_cut_off_multipart_body_is_400_not_the_default_calibration(tiny_models: Path, frame: dict[str, bytes]) -> None:
    """The multipart parser drops a last part the body ends inside of; with a default calibration
    that part (calib, last) would silently become the server's own."""
    other_calib = (KITTI / "calib" / "000001.txt").read_bytes()
    body, headers = _multipart_body(frame, other_calib)
    with service(tiny_models, default_calib=KITTI / "calib" / f"{FRAME}.txt") as app_client:
        params = {"score_threshold": 0.0}
        whole = app_client.post("/v1/detect", params=params, content=body, headers=headers)
        assert whole.status_code == 200, whole.text
        default = app_client.post("/v1/detect", params=params, files=parts(frame, calib=None)).json()
        assert whole.json()["detections"] != default["detections"]  # the sent calibration was used
        # An epilogue after the close delimiter is allowed (RFC 2046) and changes nothing.
        padded = app_client.post("/v1/detect", params=params, content=body + b"\r\n\r\n", headers=headers)
        assert padded.json()["detections"] == whole.json()["detections"]
        for cut in (body[:-100], body[: len(body) // 2]):  # inside calib; inside points
            response = app_client.post("/v1/detect", params=params, content=cut, headers=headers)
            assert_error(response, 400, "bad_request", "ended before its closing boundary")
        assert app_client.post("/v1/detect", params=params, content=body, headers=headers).json() == {
            **whole.json(), "request_id": ANY, "timings_ms": ANY}


def test_an_epilogue_after_the_close_delimiter_is_harmless_and_an_empty_body_says_so(
    client: AppClient, frame: dict[str, bytes]
) -> None:
    """RFC 2046 allows an epilogue after the close delimiter, of any length: the frame is answered as without
    it, also when the delimiter arrives split over chunks. An empty body is named as such, not as a cut-off
    upload."""
    body, headers = _multipart_body(frame, frame["calib"])
    params = {"score_threshold": 0.0}
    whole = client.post("/v1/detect", params=params, content=body, headers=headers)
    assert whole.status_code == 200, whole.text
    epilogue = b"\r\n" + b"an epilogue, ignored by every reader\r\n" * 400  # 15 kB

    async def split() -> AsyncIterator[bytes]:  # the close delimiter (--boundary--\r\n) over three chunks
        yield body[:-12]
        yield body[-12:-5]
        yield body[-5:] + epilogue[:1000]
        yield epilogue[1000:]

    for content in (body + epilogue, split()):
        padded = client.post("/v1/detect", params=params, content=content, headers=headers)
        assert padded.status_code == 200, padded.text
        assert padded.json()["detections"] == whole.json()["detections"]
    empty = assert_error(client.post("/v1/detect", content=b"", headers=headers), 400, "bad_request",
                         "request body: empty (0 bytes)", "image, points")
    assert "closing boundary" not in empty["message"]
    assert_error(client.post("/v1/detect", content=body[:-100], headers=headers), 400, "bad_request",
                 "ended before its closing boundary")


@pytest.mark.parametrize(
    ("send", "words"),
    [({"files": {"calibration": ("c.txt", b"P2: 1", "text/plain")}}, ("calibration: unknown part (did you mean calib?)",
                                                                        "accepted parts: image, points, calib")),
     ({"files": [("image", ("a.png", b"x", "image/png"))]}, ("image: sent 2 times",)),
     ({"data": {"calib": "P2: 1"}}, ("calib: sent as a text field", "-F calib=@FILE"))],
    ids=["misspelt part", "repeated part", "text field"],
)
def test_unknown_repeated_or_text_parts_are_422_naming_them(
    client: AppClient, frame: dict[str, bytes], send: dict, words: tuple[str, ...]
) -> None:
    files = parts(frame, calib=None) if "calib" in str(send) else parts(frame)
    extra = send.get("files", {})
    files = list(files.items()) + (list(extra.items()) if isinstance(extra, dict) else extra)
    for route in ("/v1/detect", "/v1/detect/bev.png", "/v1/detect/camera.png"):
        response = client.post(route, files=files, data=send.get("data"))
        assert_error(response, 422, "invalid_input", *words)


def test_repeated_query_parameter_is_422(client: AppClient, frame: dict[str, bytes]) -> None:
    response = client.post("/v1/detect?emulate_beams=16&emulate_beams=8", files=parts(frame))
    assert_error(response, 422, "invalid_input", "emulate_beams: given more than once")



def test_emulate_beams_0_takes_the_scan_as_sent(client: AppClient, frame: dict[str, bytes]) -> None:
    """emulate_beams=0, the commands' --emulate-beams 0, was a 422 ('Input should be 4, 8, 16 or 32'): it answers
    as leaving the parameter out does, the scan not thinned (no emulate_beams stage, no beams_emulated warning)."""
    sent = client.post("/v1/detect", params={"emulate_beams": 0}, files=parts(frame))
    plain = client.post("/v1/detect", files=parts(frame))
    assert sent.status_code == plain.status_code == 200, sent.text
    assert sent.json()["detections"] == plain.json()["detections"]
    assert "emulate_beams" not in sent.json()["timings_ms"] and "beams_emulated" not in sent.json()["warning_codes"]
    thinned = client.post("/v1/detect", params={"emulate_beams": 16}, files=parts(frame)).json()
    assert "emulate_beams" in thinned["timings_ms"] and "beams_emulated" in thinned["warning_codes"]

def test_warnings_travel_in_a_header_where_the_body_has_no_room(client: AppClient, frame: dict[str, bytes]) -> None:
    params = {"emulate_beams": 16, "score_threshold": 0.0}
    warnings = client.post("/v1/detect", params=params, files=parts(frame)).json()["warnings"]
    assert any("emulated 16 beams" in warning for warning in warnings)
    for route, extra in (("/v1/detect", {"format": "kitti"}), ("/v1/detect/bev.png", {}), ("/v1/detect/camera.png", {})):
        response = client.post(route, params={**params, **extra}, files=parts(frame))
        assert response.status_code == 200, response.text
        assert json.loads(response.headers["x-warnings"]) == warnings
    thinned = np.frombuffer(frame["points"], "<f4").reshape(-1, 4)[::8].tobytes()  # no line-count warning
    quiet = client.post("/v1/detect", params={"format": "kitti"}, files=parts(frame, points=thinned))
    assert quiet.status_code == 200 and "x-warnings" not in quiet.headers


def test_an_image_the_calibration_does_not_fit_gets_the_detectors_warning(client: AppClient, frame: dict[str, bytes]) -> None:
    """A camera image resized after calibrating is answered (a warning, not an error), and the client is told
    that the calibration's principal point does not fit the image; the frame as recorded gets no warning."""
    image = cv2.imdecode(np.frombuffer(frame["image"], np.uint8), cv2.IMREAD_COLOR)
    doubled = cv2.imencode(".png", cv2.resize(image, None, fx=2, fy=2))[1].tobytes()
    params = {"score_threshold": 0.0}
    response = client.post("/v1/detect", params=params, files=parts(frame, image=doubled))
    assert response.status_code == 200, response.text
    (warning,) = [w for w in response.json()["warnings"] if w.startswith("image and calib")]
    assert "P2's principal point (600.4, 181.5) lies outside the middle half of the 2476×748 image" in warning
    kitti = client.post("/v1/detect", params={**params, "format": "kitti"}, files=parts(frame, image=doubled))
    assert kitti.status_code == 200 and warning in json.loads(kitti.headers["x-warnings"])
    assert client.post("/v1/detect", params=params, files=parts(frame)).json()["warnings"] == []


def test_oversized_body_is_413_with_and_without_content_length(tiny_models: Path, frame: dict[str, bytes]) -> None:
    limit = 1024 * 1024  # above the image (749 kB), below image + scan (2.5 MB)
    with service(tiny_models, max_body_bytes=limit) as app_client:
        declared = app_client.post("/v1/detect", files=parts(frame))
        assert_error(declared, 413, "body_too_large", f"{limit} bytes")
        assert declared.headers["connection"] == "close"

        boundary = "lowres3dboundary"

        async def chunks() -> AsyncIterator[bytes]:  # a well-formed multipart start, then 2 MiB of scan: chunked
            yield (f"--{boundary}\r\nContent-Disposition: form-data; name=\"points\"; filename=\"a.bin\"\r\n"
                   "Content-Type: application/octet-stream\r\n\r\n").encode()
            for _ in range(128):
                yield b"\x00" * 16384

        streamed = app_client.post(
            "/v1/detect", content=chunks(), headers={"content-type": f"multipart/form-data; boundary={boundary}"}
        )
        assert_error(streamed, 413, "body_too_large")
        # Answered before routing, yet counted under the route asked for, not "unmatched".
        counted = app_client.get("/metrics").text
        assert 'lowres3d_http_requests_total{method="POST",route="/v1/detect",status="413"} 2.0' in counted
        # Under the limit, the same app still answers normally.
        small = app_client.post("/v1/detect", files=parts(frame, points=frame["points"][: 16 * 1000]))
        assert small.status_code == 200, small.text


def test_unknown_route_and_method_are_json(client: AppClient) -> None:
    assert_error(client.get("/v1/nothing"), 404, "not_found")
    assert_error(client.get("/v1/detect"), 405, "method_not_allowed")


# --------------------------------------------------------------------------- auth
def test_bearer_token(tiny_models: Path, frame: dict[str, bytes]) -> None:
    with service(tiny_models, token="s3cret-token") as app_client:
        for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": "Basic czNjcmV0LXRva2Vu"},
                        {"Authorization": "Bearer s3cret-token-longer"}):
            response = app_client.post("/v1/detect", files=parts(frame), headers=headers)
            assert_error(response, 401, "unauthorized", "bearer token")
            assert response.headers["www-authenticate"].startswith("Bearer")
            assert_error(app_client.get("/v1/model", headers=headers), 401, "unauthorized")
        good = {"Authorization": "Bearer s3cret-token"}
        assert app_client.post("/v1/detect", files=parts(frame), headers=good).status_code == 200
        assert app_client.get("/v1/model", headers={"Authorization": "bearer s3cret-token"}).status_code == 200
        assert app_client.get("/v1/model", headers=good).status_code == 200
        security = app_client.get("/openapi.json").json()["paths"]["/v1/detect"]["post"]["security"]
        assert security == [{"HTTPBearer": []}]
        # Probes and metrics stay open for orchestrators and scrapers.
        for route in ("/healthz", "/readyz", "/v2/health/live", "/v2/health/ready", "/metrics"):
            assert app_client.get(route).status_code == 200


def test_the_token_is_checked_before_the_upload_is_read(tiny_models: Path, frame: dict[str, bytes]) -> None:
    """Without the token a detection request is answered 401 before its body is read (test_service_process.py
    sees the answer come first over a socket), and the connection closed once the rest of the upload has been
    read and dropped, up to the body limit (a client that sends all before it reads would otherwise get a
    connection reset): an unauthenticated client cannot make the service parse or hold uploads. With the
    token, the same upload is read and answered."""
    body, headers = _multipart_body(frame, frame["calib"])
    with service(tiny_models, token="s3cret-token") as app_client:
        for route in ("/v1/detect", "/v1/detect/bev.png", "/v1/detect/camera.png"):
            for authorization in ({}, {"Authorization": "Bearer wrong"}):
                upload = CountedUpload(body)
                response = app_client.post(route, content=upload, headers={**headers, **authorization})
                assert_error(response, 401, "unauthorized", "Authorization: a valid bearer token is required")
                assert upload.pulled == len(body), route  # read to its end, and dropped unparsed
                assert response.headers["www-authenticate"] == 'Bearer realm="lowres3d"'
                assert response.headers["connection"] == "close"
        upload = CountedUpload(body)
        answered = app_client.post("/v1/detect", content=upload,
                                   headers={**headers, "Authorization": "Bearer s3cret-token"})
        assert answered.status_code == 200 and upload.pulled == len(body)
        # Refused before routing, and still counted under the route asked for.
        assert 'lowres3d_http_requests_total{method="POST",route="/v1/detect",status="401"} 2.0' in (
            app_client.get("/metrics").text)
        # Nothing to read and drop: a request without a body (none, or Content-Length: 0) keeps its connection.
        for bodiless in (app_client.get("/v1/model"), app_client.post("/v1/detect", content=b"", headers=headers)):
            assert_error(bodiless, 401, "unauthorized")
            assert "connection" not in bodiless.headers, bodiless.request.headers
        limit = app_client.app.state.settings.max_body_bytes
        endless = CountedUpload(b"\0" * (limit + 8 * 2**20), chunk=2**20)
        assert_error(app_client.post("/v1/detect", content=endless, headers=headers), 401, "unauthorized")
        assert limit < endless.pulled <= limit + 2**20  # dropped up to the body limit, not to its end


# --------------------------------------------------------------------------- load and faults
def test_queue_full_answers_503_with_retry_after(tiny_models: Path, frame: dict[str, bytes]) -> None:
    # A 64-line scan tiled ×4 (440k points) keeps each frame busy long enough for the burst to overflow.
    heavy = parts(frame, points=frame["points"] * 4)
    with service(tiny_models, workers=1, queue_size=1) as app_client:
        with ThreadPoolExecutor(8) as burst:
            responses = list(burst.map(lambda _: app_client.post("/v1/detect", files=heavy), range(8)))
        statuses = sorted(r.status_code for r in responses)
        assert set(statuses) == {200, 503}, statuses
        assert statuses.count(200) >= 2  # the running frame and the queued one
        for response in responses:
            if response.status_code == 503:
                assert_error(response, 503, "overloaded", "queue")
                assert int(response.headers["retry-after"]) >= 1
        metrics = app_client.get("/metrics").text
        rejected = statuses.count(503)
        assert f'lowres3d_inference_rejected_total{{reason="queue_full"}} {float(rejected)}' in metrics
        assert f'lowres3d_http_requests_total{{method="POST",route="/v1/detect",status="503"}} {float(rejected)}' in metrics
        assert "lowres3d_inference_queue_depth 0.0" in metrics


def _without_p2(calib: bytes) -> bytes:
    return b"\n".join(line for line in calib.splitlines() if not line.startswith(b"P2:"))


class CountedUpload:
    """A request body for httpx that records how many of its bytes the server has pulled."""

    def __init__(self, body: bytes, chunk: int = 65536) -> None:
        self.body, self.chunk, self.pulled = body, chunk, 0

    async def __aiter__(self) -> AsyncIterator[bytes]:
        for start in range(0, len(self.body), self.chunk):
            piece = self.body[start : start + self.chunk]
            self.pulled += len(piece)
            yield piece


def test_a_full_pool_refuses_a_frame_before_reading_its_upload(tiny_models: Path, frame: dict[str, bytes]) -> None:
    """The frame's place is taken before its upload is read: with every place taken a request is answered 503
    overloaded (Retry-After, connection closed) before its body is read (then read and dropped before the
    close), so no more uploads than workers + queue are held at once (a broken one too: it cannot be told apart
    unread). Once there is room, the
    checks that need no decoding still answer a broken frame 422 before it waits for a worker."""
    body, headers = _multipart_body(frame, frame["calib"])
    with service(tiny_models, workers=1, queue_size=0) as app_client:
        pool = app_client.app.state.runtime.pool
        release = threading.Event()
        held = app_client.portal.start_task_soon(pool.run, lambda _d, _c: release.wait(30), 60)
        try:
            deadline = time.monotonic() + 10
            while pool.depth != (0, 1):  # the only place is taken
                assert time.monotonic() < deadline
                time.sleep(0.01)
            upload = CountedUpload(body)
            response = app_client.post("/v1/detect", content=upload, headers=headers)
            assert_error(response, 503, "overloaded", "inference queue: full (1 frames admitted)")
            assert upload.pulled == len(body)  # read to its end and dropped, the place not taken
            assert int(response.headers["retry-after"]) >= 1 and response.headers["connection"] == "close"
            assert_error(app_client.post("/v1/detect", files=parts(frame, calib=None)), 503, "overloaded")
        finally:
            release.set()
            held.result(30)
        broken = {
            "calib": ({"calib": None}, ("calib: required", "no default calibration")),
            "calib without P2": ({"calib": _without_p2(frame["calib"])}, ("calib", "P2")),
            "cut-off PNG": ({"image": frame["image"][: len(frame["image"]) // 2]}, ("image", "PNG cut off")),
            "cut-off JPEG": ({"image": _jpeg(frame["image"])[:-5000]}, ("image", "JPEG cut off")),
            "scan size": ({"points": frame["points"][:-6]}, ("points", "multiple of 16")),
            "empty image": ({"image": b""}, ("image", "empty")),
            "missing image": ({"image": None}, ("image: required",)),
        }
        for case, (replace, words) in broken.items():
            response = app_client.post("/v1/detect", files=parts(frame, **replace))
            assert response.status_code == 422, (case, response.text)
            assert_error(response, 422, "invalid_input", *words)
        upload = CountedUpload(body)
        assert app_client.post("/v1/detect", content=upload, headers=headers).status_code == 200
        assert upload.pulled == len(body)
        metrics = app_client.get("/metrics").text
        assert "lowres3d_inference_queue_depth 0.0" in metrics and "lowres3d_inference_in_flight 0.0" in metrics
        assert pool.depth == (0, 0)  # every place given back: the refused, the broken and the answered


def test_pool_deadline_is_a_timeout_with_python_310s_timeout_class(
    tiny_models: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """On Python 3.10 (the Jetson image) asyncio.wait_for raises asyncio.TimeoutError, a class of its own there;
    stood in for here by a class that is no builtin TimeoutError. A deadline must still be PoolTimeout (504)."""
    import asyncio
    import types

    import service.pool as pool_module
    from pipeline.detector import Detector

    class Py310TimeoutError(Exception):
        """asyncio.exceptions.TimeoutError of Python 3.10: not a subclass of the builtin TimeoutError."""

    async def wait_for(awaitable: Any, timeout: float) -> Any:
        try:
            return await asyncio.wait_for(awaitable, timeout)
        except TimeoutError:
            raise Py310TimeoutError from None

    monkeypatch.setattr(pool_module, "asyncio", types.SimpleNamespace(
        wait_for=wait_for, wrap_future=asyncio.wrap_future, TimeoutError=Py310TimeoutError))
    pool = InferencePool([Detector(tiny_models)], workers=1, queue_size=0, metrics=Metrics())

    async def late() -> None:
        await pool.run(lambda _d, _c: time.sleep(0.5), timeout_s=0.05)

    try:
        with pytest.raises(PoolTimeout):
            anyio.run(late)
    finally:
        pool.shutdown()


def test_pool_admission_is_bounded_and_deadlines_cancel_waiting_jobs(tiny_models: Path) -> None:
    from pipeline.detector import Detector

    metrics = Metrics()
    pool = InferencePool([Detector(tiny_models)], workers=1, queue_size=1, metrics=metrics)
    release = threading.Event()
    started = threading.Event()
    ran: list[str] = []

    def blocking(detector: Detector, _: Cancellation) -> str:
        started.set()
        release.wait(10)
        ran.append("blocking")
        return detector.preset.name

    def quick(_d: Detector, _c: Cancellation) -> str:
        ran.append("quick")
        return "quick"

    async def scenario() -> None:
        async with anyio.create_task_group() as group:
            results: dict[str, Any] = {}

            async def first() -> None:
                results["first"] = await pool.run(blocking, timeout_s=10)

            group.start_soon(first)
            await anyio.to_thread.run_sync(started.wait, 5)
            assert pool.depth == (0, 1)
            with pytest.raises(PoolTimeout):  # queued behind the blocked job, misses its deadline, is cancelled
                await pool.run(quick, timeout_s=0.05)
            assert pool.depth == (0, 1)  # the cancelled job gave its slot back

            async def second() -> None:
                results["second"] = await pool.run(quick, timeout_s=10)

            group.start_soon(second)
            await anyio.sleep(0.05)
            assert pool.depth == (1, 1)
            with pytest.raises(PoolFull) as full:
                await pool.run(quick, timeout_s=10)
            assert full.value.retry_after_s >= 1
            release.set()
        assert results["first"].value == "tiny" and results["second"].value == "quick"
        assert results["second"].queue_wait_ms > 0

    anyio.run(scenario)
    assert ran == ["blocking", "quick"]  # the timed-out job never ran
    assert pool.depth == (0, 0)
    pool.shutdown()


def test_a_frame_nobody_waits_for_stops_on_its_worker(tiny_models: Path, frame: dict[str, bytes]) -> None:
    """Past its deadline, or when its request is cancelled (the shutdown grace ran out), a running frame is
    stopped at its next network node and gives its worker back; counted in lowres3d_inference_stopped."""
    from pipeline.detector import Detector

    calib = parse_calib(frame["calib"].decode())
    image = cv2.cvtColor(cv2.imdecode(np.frombuffer(frame["image"], np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    points = np.frombuffer(frame["points"], np.float32).reshape(-1, 4)
    metrics = Metrics()
    pool = InferencePool([Detector(tiny_models)], workers=1, queue_size=0, metrics=metrics)
    started, finished = threading.Event(), []

    def late_frame(detector: Detector, cancel: Cancellation) -> None:
        started.set()
        time.sleep(0.5)  # the frame is still on its worker when nobody waits for it any more
        detector.detect(image, points, calib, cancel=cancel)
        finished.append(True)

    def stopped() -> float:
        return metrics.registry.get_sample_value("lowres3d_inference_stopped_total")

    def worker_free() -> None:
        deadline = time.monotonic() + 10
        while pool.depth != (0, 0):
            assert time.monotonic() < deadline
            time.sleep(0.01)

    async def past_its_deadline() -> None:
        await pool.run(late_frame, timeout_s=0.2)

    async def request_cancelled() -> None:
        async with anyio.create_task_group() as group:
            group.start_soon(pool.run, late_frame, 30)
            await anyio.to_thread.run_sync(started.wait, 5)
            group.cancel_scope.cancel()

    try:
        with pytest.raises(PoolTimeout):
            anyio.run(past_its_deadline)
        worker_free()
        assert (finished, stopped()) == ([], 1.0)
        started.clear()
        anyio.run(request_cancelled)
        worker_free()
        assert (finished, stopped()) == ([], 2.0)

        async def on_time() -> Any:
            return await pool.run(lambda d, c: d.detect(image, points, calib, cancel=c), timeout_s=30)

        assert anyio.run(on_time).value.boxes.shape[1] == 7  # the worker goes on with the next frame
    finally:
        pool.shutdown()


def test_request_timeout_is_504(tiny_models: Path, frame: dict[str, bytes]) -> None:
    with service(tiny_models, request_timeout_s=0.001) as app_client:
        assert_error(app_client.post("/v1/detect", files=parts(frame)), 504, "timeout", "0.001 s")
        assert 'lowres3d_inference_rejected_total{reason="timeout"} 1.0' in app_client.get("/metrics").text


def _scan_slow_to_thin(points: bytes, at_least_s: float) -> bytes:
    """Copies of a scan (eight at first: 880k points of KITTI 000006), more of them up to the service's most
    points while thinning them to 16 lines here takes under ``at_least_s`` (the best of two runs), so that a
    faster CPU than this one still spends that long in the beam emulation."""
    scan = np.frombuffer(points, np.float32).reshape(-1, 4)
    for copies in (8, 12, 16, MAX_POINTS // len(scan)):
        cloud = np.tile(scan, (copies, 1))
        took = []
        for _ in range(2):
            tic = time.perf_counter()
            emulate_beams(cloud, 16)
            took.append(time.perf_counter() - tic)
        if min(took) >= at_least_s:
            break
    return cloud.tobytes()


def test_a_frame_past_its_deadline_stops_after_its_beam_emulation_and_the_log_names_its_request(
    tiny_models: Path, frame: dict[str, bytes], caplog: pytest.LogCaptureFixture
) -> None:
    """Thinning a scan of 880k points to 16 lines takes about half a second of NumPy that cannot be
    interrupted: a frame whose deadline passes meanwhile stops right after it (not at the depth net, a stage
    later). Both log lines of the request name its id: the 504's, and the worker's about the frame it stopped."""
    big = _scan_slow_to_thin(frame["points"], at_least_s=0.5)  # the 0.2 s deadline passes during the thinning
    with service(tiny_models, workers=1, request_timeout_s=0.2, max_points=MAX_POINTS,
                 max_body_bytes=64 * 1024 * 1024) as app_client:
        with caplog.at_level(logging.INFO, logger="service"):
            response = app_client.post("/v1/detect", params={"emulate_beams": 16}, files=parts(frame, points=big),
                                       headers={"X-Request-ID": "late-1"})
            assert_error(response, 504, "timeout", "0.2 s")
            pool = app_client.app.state.runtime.pool
            deadline = time.monotonic() + 20
            while pool.depth != (0, 0):  # the frame keeps its worker until it has stopped
                assert time.monotonic() < deadline
                time.sleep(0.01)
        assert 'lowres3d_inference_stopped_total 1.0' in app_client.get("/metrics").text
    lines = [record.getMessage() for record in caplog.records]
    assert any(line.startswith("request late-1: POST /v1/detect answered 504 timeout in ") for line in lines), lines
    (stopped,) = [line for line in lines if line.startswith("request late-1: its frame stopped on its worker")]
    assert stopped.endswith("the frame was cancelled during its beam emulation; stopped after it"), stopped


def test_metric_labels_take_no_value_from_the_client(client: AppClient) -> None:
    """A method token is whatever a client sends (kilobytes of it): each used to be a series of its own in
    /metrics, which grew without end. The method label is one of HTTP's methods or "other", the route label
    a route of the service or "unmatched"."""
    methods_sent = [f"M{i:04d}" + "X" * 4000 for i in range(20)]
    for method in methods_sent:
        assert client.request(method, "/healthz").status_code == 405
    path_sent = "/" + "p" * 5000
    assert client.get(path_sent).status_code == 404
    assert client.request("PATCH", "/healthz").status_code == 405
    text = client.get("/metrics").text
    assert not any(method[:100] in text for method in methods_sent) and path_sent[:100] not in text
    series = [line for line in text.splitlines() if line.startswith("lowres3d_http_requests_total{")]
    other = [float(line.rsplit(" ", 1)[1]) for line in series if 'method="other"' in line]
    assert sum(other) == 20.0, series
    assert any('method="PATCH"' in line for line in series)
    methods = {re.search(r'method="([^"]*)"', line).group(1) for line in series}  # type: ignore[union-attr]
    assert methods <= {"GET", "HEAD", "POST", "PUT", "DELETE", "CONNECT", "OPTIONS", "TRACE", "PATCH", "other"}


def test_internal_error_answers_only_a_request_id(
    tiny_models: Path, frame: dict[str, bytes], caplog: pytest.LogCaptureFixture
) -> None:
    with service(tiny_models) as app_client:
        runtime = app_client.app.state.runtime

        def broken(*args: Any, **kwargs: Any) -> None:
            raise RuntimeError("secret detail /srv/models/internal.onnx")

        runtime.detector.detect = broken  # a fault inside the worker, as a bug or a provider crash would raise
        with caplog.at_level(logging.ERROR, logger="service.middleware"):
            response = app_client.post("/v1/detect", files=parts(frame), headers={"X-Request-ID": "req-42"})
        error = assert_error(response, 500, "internal_error", "req-42")
        assert "secret" not in response.text and "/srv" not in response.text and "Traceback" not in response.text
        assert error["request_id"] == "req-42"
        logged = "\n".join(r.getMessage() + (r.exc_text or "") for r in caplog.records)
        assert "req-42" in logged and "secret detail" in logged and "RuntimeError" in logged
        # The service keeps answering after the fault.
        assert app_client.get("/healthz").status_code == 200


def test_a_request_cancelled_by_the_shutdown_is_answered_503_and_stays_cancelled() -> None:
    """What uvicorn does when --shutdown-timeout-s runs out: cancel the request's task. The middleware answers
    the service's 503 shutting_down (with the request id) and lets the cancellation go on; the log filter then
    keeps uvicorn's "Exception in ASGI application" traceback for it out of the log, and only for it."""
    import asyncio

    from service.middleware import CancelledRequestLogFilter, RequestContextMiddleware

    sent: list[dict] = []
    metrics = Metrics()

    async def never_answers(scope: Any, receive: Any, send: Any) -> None:
        await asyncio.Event().wait()

    async def send(message: dict) -> None:
        sent.append(message)

    async def receive() -> dict:
        return {"type": "http.request", "body": b"", "more_body": False}

    async def scenario() -> None:
        scope = {"type": "http", "method": "POST", "path": "/v1/detect", "headers": [(b"x-request-id", b"cut-1")]}
        task = asyncio.ensure_future(RequestContextMiddleware(never_answers, metrics)(scope, receive, send))
        await asyncio.sleep(0.01)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    asyncio.run(scenario())
    start, body = sent
    assert start["status"] == 503
    headers = dict(start["headers"])
    assert headers[b"x-request-id"] == b"cut-1" and headers[b"retry-after"] == b"1"
    assert headers[b"content-type"] == b"application/json"
    assert json.loads(body["body"])["error"] == {
        "code": "shutting_down", "request_id": "cut-1",
        "message": "the service shut down before this request finished; send it again (to another replica)"}
    assert 'lowres3d_http_requests_total{method="POST",route="unmatched",status="503"} 1.0' in metrics.render().decode()

    def record(exc: BaseException) -> logging.LogRecord:
        return logging.LogRecord("uvicorn.error", logging.ERROR, __file__, 1, "Exception in ASGI application\n",
                                 None, (type(exc), exc, None))

    log_filter = CancelledRequestLogFilter()
    assert not log_filter.filter(record(asyncio.CancelledError()))
    assert log_filter.filter(record(RuntimeError("a bug")))  # a real crash keeps its traceback


def test_unsafe_request_ids_are_replaced(client: AppClient) -> None:
    assert client.get("/healthz", headers={"X-Request-ID": "abc-123"}).headers["x-request-id"] == "abc-123"
    replaced = client.get("/healthz", headers={"X-Request-ID": "bad id\twith spaces"}).headers["x-request-id"]
    assert replaced != "bad id\twith spaces" and len(replaced) == 32
    # At most 64 characters are kept as sent (a UUID with its dashes is 36): one more and a new id is given.
    longest = "r" * 64
    assert client.get("/healthz", headers={"X-Request-ID": longest}).headers["x-request-id"] == longest
    replaced = client.get("/healthz", headers={"X-Request-ID": longest + "r"}).headers["x-request-id"]
    assert re.fullmatch(r"[0-9a-f]{32}", replaced), replaced


# --------------------------------------------------------------------------- health, model, metrics
def test_health_routes(client: AppClient) -> None:
    assert client.get("/healthz").json() == {"status": "ok", "ready": None}
    assert client.get("/readyz").json() == {"status": "ready", "ready": True}
    assert client.get("/v2/health/live").json() == {"live": True}
    assert client.get("/v2/health/ready").json() == {"ready": True}
    for path in ("/healthz", "/readyz", "/v2/health/live", "/v2/health/ready"):
        head = client.request("HEAD", path)
        assert head.status_code == 200 and head.content == b"", path


def test_warm_up_runs_a_frame_on_every_worker_thread(tiny_models: Path, frame: dict[str, bytes]) -> None:
    """After the warm-up each worker thread holds its BEV buffers (the mirror's too)."""
    from pipeline.detector import Detector

    detector = Detector(tiny_models, mirror_tta=True)
    calib = parse_calib(frame["calib"].decode())
    image = cv2.cvtColor(cv2.imdecode(np.frombuffer(frame["image"], np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    points = np.frombuffer(frame["points"], np.float32).reshape(-1, 4)
    met = threading.Barrier(2)

    def buffers(d: Detector, _: Cancellation) -> tuple[int, bool]:
        met.wait(10)  # two probes at once: one on each worker thread
        voxelizer = getattr(d._local, "voxelizer", None)
        made = voxelizer is not None and voxelizer._mirror is not None
        d.detect(image, points, calib, emulate_to_beams=16)
        return threading.get_ident(), made

    async def probe(pool: InferencePool) -> list[tuple[int, bool]]:
        results: list[tuple[int, bool]] = []

        async def one() -> None:
            results.append((await pool.run(buffers, timeout_s=30)).value)

        async with anyio.create_task_group() as group:
            group.start_soon(one)
            group.start_soon(one)
        return results

    cold = InferencePool([detector], workers=2, queue_size=0, metrics=Metrics())
    cold.warm_up(0)  # no warm-up: nothing made before the first frames
    assert [made for _, made in anyio.run(probe, cold)] == [False, False]
    cold.shutdown()

    warm = InferencePool([Detector(tiny_models, mirror_tta=True)], workers=2, queue_size=0, metrics=Metrics())
    warm.warm_up(1)
    results = anyio.run(probe, warm)
    warm.shutdown()
    assert len({thread for thread, _ in results}) == 2
    assert [made for _, made in results] == [True, True]


def test_not_ready_until_warmed_up(tiny_models: Path, frame: dict[str, bytes]) -> None:
    from service.metrics import Metrics as MetricsClass
    from service.runtime import load_runtime

    settings = Settings(models=tiny_models)
    metrics = MetricsClass()
    runtime = load_runtime(settings, metrics)
    gate = threading.Event()
    original = runtime.detector.warm_up

    def slow_warm_up(runs: int = 1, cancel: Cancellation | None = None) -> None:  # held until the test has probed
        gate.wait(10)
        original(runs, cancel)

    runtime.detector.warm_up = slow_warm_up
    with AppClient(create_app(settings, runtime=runtime, metrics=metrics)) as app_client:
        assert app_client.get("/healthz").status_code == 200
        for route in ("/readyz", "/v2/health/ready"):
            assert_error(app_client.get(route), 503, "not_ready", "warming up")
        assert_error(app_client.post("/v1/detect", files=parts(frame)), 503, "not_ready")
        assert "lowres3d_ready 0.0" in app_client.get("/metrics").text
        gate.set()
        app_client.wait_ready()
        assert "lowres3d_ready 1.0" in app_client.get("/metrics").text


def test_model_info(client: AppClient, tiny_models: Path) -> None:
    info = client.get("/v1/model").json()
    assert info["preset"] == "tiny" and info["two_stage"] is True
    assert info["providers_in_use"] == {"depth": ["CPUExecutionProvider"], "pixor": ["CPUExecutionProvider"]}
    assert info["manifest"] == json.loads((tiny_models / "manifest.json").read_text())
    assert (info["workers"], info["sessions"], info["queue_size"]) == (2, "shared", 4)
    assert info["intra_op_threads"] == max(1, len(os.sched_getaffinity(0)) // 2)
    assert info["crop_hw"] == [352, 1216]
    # The tiny models are untrained (and fp32: nothing this CPU could run inexactly).
    untrained = (f"{tiny_models}: depth and pixor have initialised (untrained) weights: the detections mean "
                 "nothing; export trained checkpoints (python -m export --checkpoints DIR)")
    assert info["warnings"] == [untrained]
    # One shared session pair, on the CPU, with the load's warnings.
    assert info["session_pairs"] == [{"device_id": None, "providers_in_use": info["providers_in_use"],
                                      "warnings": [untrained]}]


def test_lidar_only_model_needs_the_scan_alone(tiny_models: Path, frame: dict[str, bytes], tmp_path: Path) -> None:
    """A LiDAR-only model answers from points alone (boxes in the LiDAR frame); only the answers about the camera
    (format=kitti, camera.png) need the image and a calibration. Its /v1/model has no crop, and the schema
    agrees: image is optional there, required for a camera model."""
    from tests.conftest import lidar_only_models

    models = lidar_only_models(tiny_models, tmp_path / "lidar")
    params = {"score_threshold": 0.0}
    with service(models) as app_client:
        info = app_client.get("/v1/model").json()
        assert info["two_stage"] is False and info["crop_hw"] is None
        alone = app_client.post("/v1/detect", params=params, files=parts(frame, image=None, calib=None))
        assert alone.status_code == 200, alone.text
        assert alone.json()["detections"] and "depth_net" not in alone.json()["timings_ms"]
        whole = app_client.post("/v1/detect", params=params, files=parts(frame))
        assert whole.json()["detections"] == alone.json()["detections"]  # the image changes nothing here
        bev = app_client.post("/v1/detect/bev.png", params=params, files=parts(frame, image=None, calib=None))
        assert bev.status_code == 200 and bev.content.startswith(b"\x89PNG")

        kitti = {**params, "format": "kitti"}
        assert_error(app_client.post("/v1/detect", params=kitti, files=parts(frame, calib=None)),
                     422, "invalid_input", "calib: required", "format=kitti", "no default calibration")
        assert_error(app_client.post("/v1/detect", params=kitti, files=parts(frame, image=None)),
                     422, "invalid_input", "image: required", "format=kitti")
        lines = app_client.post("/v1/detect", params=kitti, files=parts(frame))
        assert lines.status_code == 200 and lines.text.startswith("Car ")
        assert_error(app_client.post("/v1/detect/camera.png", params=params, files=parts(frame, image=None)),
                     422, "invalid_input", "image: required", "camera picture")
        camera = app_client.post("/v1/detect/camera.png", params=params, files=parts(frame))
        assert camera.status_code == 200 and camera.content.startswith(b"\x89PNG")
        assert_error(app_client.post("/v1/detect", files=parts(frame, points=b"\x00" * 100)), 422, "invalid_input",
                     "points", "multiple of 16")

        schema = app_client.get("/openapi.json").json()
        assert schema["components"]["schemas"]["ModelInfo"]["properties"]["crop_hw"]["anyOf"][1] == {"type": "null"}
        for route in ("/v1/detect", "/v1/detect/bev.png", "/v1/detect/camera.png"):
            ref = schema["paths"][route]["post"]["requestBody"]["content"]["multipart/form-data"]["schema"]["$ref"]
            body = schema["components"]["schemas"][ref.rsplit("/", 1)[1]]
            assert body["required"] == ["points"], route
            assert {"type": "null"} in body["properties"]["image"]["anyOf"]


def test_metrics_exposition(client: AppClient, frame: dict[str, bytes]) -> None:
    assert client.post("/v1/detect", files=parts(frame)).status_code == 200
    assert client.get("/no-such-route-7f3a").status_code == 404
    assert client.get("/openapi.json").status_code == 200
    response = client.get("/metrics")
    assert response.status_code == 200 and response.headers["content-type"].startswith("text/plain")
    text = response.text
    assert 'lowres3d_http_requests_total{method="POST",route="/v1/detect",status="200"}' in text
    for stage in ("depth_net", "pixor", "voxelize", "queue_wait", "total"):
        assert f'lowres3d_stage_duration_seconds_count{{stage="{stage}"}}' in text
    for family in ("lowres3d_inference_queue_depth", "lowres3d_inference_in_flight", "lowres3d_http_requests_in_flight",
                   "process_resident_memory_bytes", 'lowres3d_model_info{'):
        assert family in text
    # A path no route matches is counted under one label, never its own: clients cannot grow the series.
    assert 'lowres3d_http_requests_total{method="GET",route="unmatched",status="404"}' in text
    assert 'lowres3d_http_requests_total{method="GET",route="/openapi.json",status="200"}' in text  # FastAPI's own
    assert "no-such-route-7f3a" not in text


# --------------------------------------------------------------------------- OpenAPI and settings
def test_openapi_documents_the_contract(client: AppClient) -> None:
    schema = client.get("/openapi.json").json()
    detect = schema["paths"]["/v1/detect"]["post"]
    assert set(detect["responses"]) >= {"200", "401", "413", "415", "422", "503", "504"}
    assert detect["responses"]["503"]["content"]["application/json"]["schema"]["$ref"].endswith("/ErrorResponse")
    assert "text/plain" in detect["responses"]["200"]["content"]
    body_ref = detect["requestBody"]["content"]["multipart/form-data"]["schema"]["$ref"].rsplit("/", 1)[1]
    body = schema["components"]["schemas"][body_ref]
    assert set(body["required"]) == {"image", "points"} and "calib" in body["properties"]
    params = {p["name"]: p for p in detect["parameters"] if p["in"] == "query"}
    assert set(params) == {"score_threshold", "emulate_beams", "nonfinite", "format", "image_stamp_ns", "points_stamp_ns"}
    assert params["score_threshold"]["schema"]["anyOf"][0]["maximum"] == 1.0
    assert schema["components"]["schemas"]["DetectResponse"]["examples"]
    assert schema["components"]["schemas"]["ErrorResponse"]["examples"]
    for picture in ("bev.png", "camera.png"):
        assert "image/png" in schema["paths"][f"/v1/detect/{picture}"]["post"]["responses"]["200"]["content"]
    assert detect["security"] == [{}, {"HTTPBearer": []}]  # no token configured: optional
    # The headers that come with a status are declared with it, on every route that declares the status.
    for path, method in (("/v1/detect", "post"), ("/v1/detect/bev.png", "post"), ("/v1/model", "get"),
                         ("/readyz", "get"), ("/v2/health/ready", "get")):
        responses = schema["paths"][path][method]["responses"]
        assert responses["503"]["headers"]["Retry-After"]["required"] is True, path
        if "401" in responses:
            assert responses["401"]["headers"]["WWW-Authenticate"]["required"] is True, path
    assert "401" in detect["responses"] and "401" in schema["paths"]["/v1/model"]["get"]["responses"]
    for path in ("/healthz", "/readyz", "/v1/model", "/metrics", "/v2/health/live", "/v2/health/ready"):
        assert path in schema["paths"]


def test_the_beam_counts_the_api_takes_are_the_pipelines() -> None:
    """emulate_beams's values in the HTTP API are pipeline.beams.BEAM_COUNTS, which the Python API checks, and 0
    for the scan as sent, as the commands' --emulate-beams 0."""
    from pipeline.beams import BEAM_COUNTS
    from service.schemas import BeamCount

    assert sorted(BeamCount) == [0, *sorted(BEAM_COUNTS)]


def test_every_setting_is_a_cli_option_and_an_env_var(monkeypatch: pytest.MonkeyPatch, tiny_models: Path) -> None:
    assert {flag[2:].replace("-", "_") for flag, _, _ in _OPTIONS} == set(Settings.model_fields)
    for flag, _, choices in _OPTIONS:  # a choice the command line lists by hand is the setting's own Literal
        if isinstance(choices, list):
            annotation = Settings.model_fields[flag[2:].replace("-", "_")].annotation
            union = (annotation,) if typing.get_origin(annotation) is Literal else typing.get_args(annotation)
            literal = next(arg for arg in union if typing.get_origin(arg) is Literal)
            assert choices == list(typing.get_args(literal)), flag
    monkeypatch.setenv("LOWRES3D_QUEUE_SIZE", "7")
    monkeypatch.setenv("LOWRES3D_WORKERS", "3")
    monkeypatch.setenv("LOWRES3D_MODELS", str(tiny_models))
    settings = settings_from_args(["--workers", "1", "--sessions", "per-worker", "--token", "tok-XYZ"])
    assert (settings.queue_size, settings.workers, settings.sessions, settings.models) == (7, 1, "per-worker", tiny_models)
    assert settings.token is not None and settings.token.get_secret_value() == "tok-XYZ"
    assert "tok-XYZ" not in repr(settings)
    assert Settings().models == tiny_models
    monkeypatch.delenv("LOWRES3D_MODELS")
    assert Settings().models == Path(__file__).resolve().parents[1] / "weights" / "edge"


@pytest.mark.parametrize(
    ("argv", "env", "line"),
    [(["--token", ""], {}, "--token (LOWRES3D_TOKEN): empty; give a token"),
     ([], {"LOWRES3D_TOKEN": ""}, "--token (LOWRES3D_TOKEN): empty; give a token"),
     ([], {"LOWRES3D_TOKEN": " s3cret "}, "--token (LOWRES3D_TOKEN): starts or ends with whitespace"),
     (["--models", ""], {}, "--models (LOWRES3D_MODELS): empty; give a path"),
     ([], {"LOWRES3D_MODELS": ""}, "--models (LOWRES3D_MODELS): empty; give a path"),
     ([], {"LOWRES3D_DEFAULT_CALIB": " "}, "--default-calib (LOWRES3D_DEFAULT_CALIB): empty; give a path"),
     (["--host", ""], {}, ("--host (LOWRES3D_HOST): empty; give an address (an empty one would listen on every "
                           "interface")),
     ([], {"LOWRES3D_HOST": " "}, "--host (LOWRES3D_HOST): empty; give an address")],
    ids=["empty --token", "empty LOWRES3D_TOKEN", "token with spaces", "empty --models", "empty LOWRES3D_MODELS",
         "blank LOWRES3D_DEFAULT_CALIB", "empty --host", "blank LOWRES3D_HOST"],
)
def test_settings_refuse_an_empty_token_or_path(
    monkeypatch: pytest.MonkeyPatch, argv: list[str], env: dict[str, str], line: str
) -> None:
    """An empty token would lock every /v1 route with 401; an empty path would be the current directory; an
    empty host would listen on every interface (0.0.0.0 and ::)."""
    from pydantic import ValidationError

    from service.__main__ import settings_errors

    for name, value in env.items():
        monkeypatch.setenv(name, value)
    with pytest.raises(ValidationError) as caught:
        settings_from_args(argv)
    lines = settings_errors(caught.value)
    assert len(lines) == 1 and lines[0].startswith(line), lines
    assert "s3cret" not in lines[0]  # a token is never echoed


def test_gpu_ids_from_the_command_line_or_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """--device-ids 0,1 (LOWRES3D_DEVICE_IDS=0,1: the same text, no JSON) for per-worker sessions; refused, naming
    the option, where it could not be used: malformed, on the CPU provider, or several GPUs for shared sessions."""
    from pydantic import ValidationError

    from service.__main__ import settings_errors

    assert settings_from_args(["--device-ids", "0, 1", "--sessions", "per-worker"]).gpu_ids() == [0, 1]
    assert settings_from_args(["--device-ids", "1"]).gpu_ids() == [1]  # shared sessions: one GPU
    assert settings_from_args([]).gpu_ids() is None
    monkeypatch.setenv("LOWRES3D_DEVICE_IDS", "1,0")
    assert settings_from_args(["--sessions", "per-worker", "--provider", "cuda"]).gpu_ids() == [1, 0]
    for argv, line in (([], "--device-ids (LOWRES3D_DEVICE_IDS) 1,0: several GPUs need --sessions per-worker"),
                       (["--device-ids", "0", "--provider", "cpu"], ("--device-ids (LOWRES3D_DEVICE_IDS) 0 with --provider cpu: GPU ids are "
                        "for cuda or tensorrt")),
                       (["--device-ids", "0,0"], "--device-ids (LOWRES3D_DEVICE_IDS) 0,0: a GPU id given twice"),
                       (["--workers", "1", "--sessions", "per-worker"], "--device-ids (LOWRES3D_DEVICE_IDS) 1,0: 2 GPUs for 1 worker(s)"),
                       (["--device-ids", "gpu0"], "--device-ids (LOWRES3D_DEVICE_IDS) gpu0: expected GPU ids from 0")):
        with pytest.raises(ValidationError) as caught:
            settings_from_args(argv)
        assert any(line in error for error in settings_errors(caught.value)), (argv, settings_errors(caught.value))


def test_unknown_lowres3d_variables_are_named_with_the_closest_setting() -> None:
    from service.__main__ import unknown_env_warnings

    environ = {"LOWRES3D_WORKER": "4", "lowres3d_queue_sise": "2", "LOWRES3D_ZZZ": "1", "LOWRES3D_WORKERS": "2",
               "lowres3d_port": "9000", "PATH": "/bin"}
    lines = unknown_env_warnings(environ)
    assert lines[:2] == [
        "environment variable LOWRES3D_WORKER: not a setting, ignored (did you mean LOWRES3D_WORKERS?)",
        "environment variable LOWRES3D_ZZZ: not a setting, ignored (the settings are LOWRES3D_MODELS, LOWRES3D_HOST, "
        + ", ".join(f"LOWRES3D_{name.upper()}" for name in list(Settings.model_fields)[2:]) + ")",
    ]
    # Read case-insensitively, like the settings.
    assert lines[2:] == ["environment variable lowres3d_queue_sise: not a setting, ignored (did you mean "
                         + "LOWRES3D_QUEUE_SIZE?)"]


def test_uvicorn_waits_the_fraction_of_a_second_given(tiny_models: Path) -> None:
    """--shutdown-timeout-s 0.9 is 0.9 s of grace, not int(0.9) = none (uvicorn waits in asyncio.timeout)."""
    from service.__main__ import uvicorn_config

    settings = Settings(models=tiny_models, shutdown_timeout_s=0.9)
    assert uvicorn_config(settings, create_app(settings)).timeout_graceful_shutdown == 0.9


def test_mirror_tta_setting_reaches_the_detector(tiny_models: Path, client: AppClient, frame: dict[str, bytes],
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """--mirror-tta (LOWRES3D_MIRROR_TTA) makes the service's PIXOR run on the mirrored BEV too: its boxes
    are those of a Detector built with mirror_tta, not those of the plain service."""
    from pipeline.detector import Detector
    from pipeline.kitti import read_calib, read_image, read_velodyne

    monkeypatch.setenv("LOWRES3D_MIRROR_TTA", "true")
    assert settings_from_args([]).mirror_tta is True
    assert settings_from_args(["--no-mirror-tta"]).mirror_tta is False  # the command line wins
    monkeypatch.delenv("LOWRES3D_MIRROR_TTA")
    assert settings_from_args([]).mirror_tta is False and settings_from_args(["--mirror-tta"]).mirror_tta is True
    assert client.get("/v1/model").json()["mirror_tta"] is False

    params = {"score_threshold": 0.0}
    plain = client.post("/v1/detect", params=params, files=parts(frame)).json()["detections"]
    direct = Detector(tiny_models, mirror_tta=True).detect(
        read_image(KITTI / "image_2" / f"{FRAME}.png"), read_velodyne(KITTI / "velodyne" / f"{FRAME}.bin").points,
        read_calib(KITTI / "calib" / f"{FRAME}.txt"), score_threshold=0.0)
    with service(tiny_models, mirror_tta=True) as app_client:
        assert app_client.get("/v1/model").json()["mirror_tta"] is True
        assert 'mirror_tta="true"' in app_client.get("/metrics").text
        body = app_client.post("/v1/detect", params=params, files=parts(frame)).json()
        mirrored = body["detections"]
        assert "pixor_mirror" in body["timings_ms"]  # PIXOR's second run, timed as a stage of its own
        assert 'lowres3d_stage_duration_seconds_count{stage="pixor_mirror"}' in app_client.get("/metrics").text
    assert len(mirrored) == len(direct.scores) > 0
    np.testing.assert_allclose([d["score"] for d in mirrored], direct.scores, atol=1e-5)
    np.testing.assert_allclose([[d["box"][k] for k in ("x", "y", "z", "l", "w", "h", "yaw")] for d in mirrored],
                               direct.boxes, atol=1e-4)
    assert [d["score"] for d in mirrored] != [d["score"] for d in plain]


def test_per_worker_sessions(tiny_models: Path, frame: dict[str, bytes]) -> None:
    with service(tiny_models, workers=2, sessions="per-worker") as app_client:
        runtime = app_client.app.state.runtime
        assert len(runtime.detectors) == 2 and runtime.detectors[0] is not runtime.detectors[1]
        pairs = app_client.get("/v1/model").json()["session_pairs"]
        assert [(pair["device_id"], pair["providers_in_use"]["pixor"]) for pair in pairs] == [
            (None, ["CPUExecutionProvider"])] * 2  # each worker's own pair, each said
        with ThreadPoolExecutor(2) as burst:
            responses = list(burst.map(lambda _: app_client.post("/v1/detect", files=parts(frame)), range(4)))
        assert [r.status_code for r in responses] == [200] * 4
