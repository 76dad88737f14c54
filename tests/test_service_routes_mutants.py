"""What the routes answer that a mutation audit of service/routes, service/openapi.py and service/memory.py found
unpinned (session 46): each test here failed under a one-line change of the code it names, and passes on the code.

In-process apps over ASGI with the real tiny models and KITTI frame 000006, as in test_service.py.
"""

from __future__ import annotations

import json
import time
from collections.abc import AsyncIterator
from pathlib import Path

import cv2
import numpy as np
from prometheus_client import CONTENT_TYPE_LATEST

from pipeline.boxes import in_camera_view
from pipeline.kitti import parse_calib
from pipeline.render import bev_key_rows, draw_key
from service.app import create_app
from service.routes.detect import picture_title
from tests.test_service import AppClient, assert_error, client, frame, parts, service, tiny_models  # noqa: F401
from tests.test_service_metrics import _value
from tests.test_service_mutants import _multipart
from tests.test_service_readiness import _held_runtime

RENDER_COUNT = 'lowres3d_stage_duration_seconds_count{stage="render"}'


def _picture(content: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(content, np.uint8), cv2.IMREAD_COLOR)


def test_the_bev_picture_has_its_key_in_the_top_left_corner(client: AppClient, frame: dict[str, bytes]) -> None:  # noqa: F811
    """bev.png's key (routes.detect: render_bev(legend=True)): pixel for pixel the one draw_key makes with
    bev_key_rows, in the top-left corner (the camera picture's, top right, is pinned in test_service_openapi):
    titled with the model (picture_title), the detections counted in the camera's view and outside it (as
    format=kitti keeps them), the scan's and the camera's points and the camera's view named."""
    params = {"score_threshold": 0.0}
    response = client.post("/v1/detect/bev.png", params=params, files=parts(frame))
    assert response.status_code == 200, response.text
    picture = _picture(response.content)
    detections = client.post("/v1/detect", params=params, files=parts(frame)).json()["detections"]
    boxes = np.array([[d["box"][k] for k in ("x", "y", "z", "l", "w", "h", "yaw")] for d in detections])
    seen = in_camera_view(boxes, parse_calib(frame["calib"].decode(), "calib"), _picture(frame["image"]).shape[:2])
    split = (int(seen.sum()), int((~seen).sum()))
    assert split[0] > 0 and split[1] > 0  # both kinds counted
    title = picture_title(client.app.state.runtime.identity, None)
    # In its own strip above the scene: nothing is drawn over it (boxes were, and its black box hid the scene
    # beyond 57 m on the left), so it is draw_key's, pixel for pixel.
    expected = np.zeros_like(picture)
    left, top, right, bottom = draw_key(expected, bev_key_rows(title, True, False, True, True, [], split))
    assert (left, top) == (0, 0)
    np.testing.assert_array_equal(picture[top:bottom + 1, left:right + 1], expected[top:bottom + 1, left:right + 1])


def test_stage_timings_are_in_milliseconds(client: AppClient, frame: dict[str, bytes]) -> None:  # noqa: F811
    """``parse_inputs`` includes decoding the PNG, so it is not far below what decoding it takes here (a twentieth,
    room for a busy machine; a figure in seconds would be a thousandth); ``total`` is no more than the request
    took as the client timed it (both in milliseconds)."""
    decode_ms = []
    for _ in range(3):
        tic = time.perf_counter()
        _picture(frame["image"])
        decode_ms.append((time.perf_counter() - tic) * 1e3)
    tic = time.perf_counter()
    response = client.post("/v1/detect", files=parts(frame))
    took_ms = (time.perf_counter() - tic) * 1e3
    assert response.status_code == 200, response.text
    timings = response.json()["timings_ms"]
    assert timings["parse_inputs"] >= 0.05 * min(decode_ms), (timings, decode_ms)
    assert timings["parse_inputs"] <= timings["total"] <= took_ms, (timings, took_ms)


def test_drawing_a_picture_is_timed_as_the_render_stage(client: AppClient, frame: dict[str, bytes]) -> None:  # noqa: F811
    """Each picture answered adds one ``render`` observation to the stage histograms; a JSON answer none."""
    before = _value(client.get("/metrics").text, RENDER_COUNT) if RENDER_COUNT in client.get("/metrics").text else 0.0
    assert client.post("/v1/detect", files=parts(frame)).status_code == 200
    for route in ("/v1/detect/bev.png", "/v1/detect/camera.png"):
        assert client.post(route, files=parts(frame)).status_code == 200
    assert _value(client.get("/metrics").text, RENDER_COUNT) == before + 2


def test_a_frame_admitted_before_the_stop_is_told_to_retry_elsewhere(tiny_models: Path, frame: dict[str, bytes]) -> None:  # noqa: F811
    """The pool stops while an admitted frame's upload is still arriving: the route (not the admission, which
    let it in) answers 503 shutting_down, and with Retry-After as every 503 (routes.detect's PoolClosed)."""
    body, headers = _multipart(frame)

    with service(tiny_models) as app_client:
        pool = app_client.app.state.runtime.pool

        async def stop_midway() -> AsyncIterator[bytes]:
            yield body[: len(body) // 2]
            pool.shutdown()  # no frame runs: returns at once
            yield body[len(body) // 2:]

        response = app_client.post("/v1/detect", content=stop_midway(), headers=headers)
        assert_error(response, 503, "shutting_down", "shutting down")
        assert response.headers["retry-after"] == "1"


def test_metrics_say_the_version_of_the_text_format_they_are_in(client: AppClient) -> None:  # noqa: F811
    """A scraper picks its parser by the Content-Type: the answer names the text format's version that
    prometheus_client's generate_latest writes (a bare text/plain leaves the scraper to guess)."""
    content_type = client.get("/metrics").headers["content-type"]
    assert content_type == CONTENT_TYPE_LATEST and "version=" in content_type, content_type


def test_the_document_is_the_same_each_time_it_is_served(client: AppClient) -> None:  # noqa: F811
    """openapi.install_schema completes FastAPI's document once: a second fetch declares X-Request-ID once too."""
    first = client.get("/openapi.json").json()
    assert client.get("/openapi.json").json() == first
    parameters = first["paths"]["/healthz"]["get"]["parameters"]
    assert [p["name"] for p in parameters] == ["X-Request-ID"]


def test_the_model_is_described_while_it_warms_up(tiny_models: Path) -> None:  # noqa: F811
    """/v1/model needs the models loaded, not warmed up: an operator sees which model a replica that is not ready
    yet runs (while /readyz says 503)."""
    settings, metrics, runtime, gate = _held_runtime(tiny_models, None)
    with AppClient(create_app(settings, runtime=runtime, metrics=metrics)) as app_client:
        try:
            assert app_client.get("/readyz").status_code == 503
            info = app_client.get("/v1/model")
            assert info.status_code == 200, info.text
            assert info.json()["identity"]["id"] == runtime.identity.id
        finally:
            gate.set()
        app_client.wait_ready()


def test_every_operation_documents_a_receive_timeout_and_an_internal_error(client: AppClient) -> None:  # noqa: F811
    """408 and 500 can answer any request (the middleware's): every operation declares both, /metrics too."""
    schema = client.get("/openapi.json").json()
    for path, operations in schema["paths"].items():
        for method, operation in operations.items():
            assert {"408", "500"} <= set(operation["responses"]), f"{method} {path}"


def test_each_warning_comes_with_its_own_code(client: AppClient, frame: dict[str, bytes]) -> None:  # noqa: F811
    """A frame warned while decoding (rows with NaN dropped) and by the Detector (beams emulated): the i-th code
    is the i-th warning's, in the JSON answer and in X-Warnings / X-Warning-Codes alike."""
    points = np.frombuffer(frame["points"], "<f4").reshape(-1, 4).copy()
    points[:3, 0] = np.nan
    files = parts(frame, points=points.tobytes())
    body = client.post("/v1/detect", params={"emulate_beams": 16}, files=files).json()
    pairs = dict(zip(body["warning_codes"], body["warnings"], strict=True))
    assert pairs["nonfinite_dropped"].startswith("points: dropped 3 rows"), pairs
    assert pairs["beams_emulated"].startswith("emulated 16 beams"), pairs
    lines = client.post("/v1/detect", params={"emulate_beams": 16, "format": "kitti"}, files=files)
    assert list(zip(json.loads(lines.headers["x-warning-codes"]), json.loads(lines.headers["x-warnings"]),
                    strict=True)) == list(pairs.items())
