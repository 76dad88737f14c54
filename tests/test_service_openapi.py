"""The service as a client's writer in another language sees it: ``/openapi.json``, the error answers, CORS.

What a code generator (openapi-generator's typescript-fetch or cpp-restsdk) needs from the document: a type
for every body (a PNG as a binary string, else the generated method returns nothing), operation names a
person would write, the parts' content types, the bearer scheme, the request id; and what the client's error
handling needs from every answer: one JSON shape with a documented code and a message naming what was at
fault, also for a 404, a 405, an unparsable body and a request uvicorn cannot parse. In-process apps as in
test_service.py; a real uvicorn (on 127.0.0.1) only for what only the HTTP protocol layer answers.
"""

from __future__ import annotations

import json
import logging
import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any
from unittest.mock import patch

import cv2
import httpx
import numpy as np
import pytest
import uvicorn
from pydantic import ValidationError

from pipeline.render import PREDICTION_BGR, draw_key, key_rows
from service.__main__ import settings_errors, uvicorn_config
from service.app import create_app
from service.routes.detect import picture_title
from service.schemas import ERROR_CODES
from service.settings import Settings
from tests.test_service import AppClient, assert_error, client, frame, parts, service, tiny_models  # noqa: F401

DASHBOARD = "http://localhost:5173"


@pytest.fixture(scope="module")
def schema(client: AppClient) -> dict[str, Any]:  # noqa: F811
    """The document of the default configuration (a camera model, no token)."""
    response = client.get("/openapi.json")
    assert response.status_code == 200
    return response.json()


def _operations(schema: dict[str, Any]) -> Iterator[tuple[str, str, dict[str, Any]]]:
    for path, operations in schema["paths"].items():
        for method, operation in operations.items():
            yield path, method, operation


# --------------------------------------------------------------------------- the document
def test_every_answer_body_has_a_schema_a_generator_can_type(schema: dict[str, Any]) -> None:
    """A media type without a schema made openapi-generator's methods for the pictures and /metrics return
    void (typescript-fetch's VoidApiResponse): the PNG the client asked for was thrown away."""
    for path, method, operation in _operations(schema):
        for status, response in operation["responses"].items():
            for media_type, content in response.get("content", {}).items():
                assert content.get("schema"), f"{method} {path} {status} {media_type}"
    for picture in ("bev.png", "camera.png"):
        png = schema["paths"][f"/v1/detect/{picture}"]["post"]["responses"]["200"]["content"]["image/png"]["schema"]
        assert (png["type"], png["format"]) == ("string", "binary")
    assert schema["paths"]["/metrics"]["get"]["responses"]["200"]["content"]["text/plain"]["schema"]["type"] == "string"


def test_operations_are_named_after_their_functions(schema: dict[str, Any]) -> None:
    """A generated client's methods are named after the operation ids: ``detect``, not ``detect_v1_detect_post``
    (``detectV1DetectPost``); the multipart bodies' schemas follow (``Body_detect``)."""
    ids = {(method, path): operation["operationId"] for path, method, operation in _operations(schema)}
    assert ids == {
        ("post", "/v1/detect"): "detect", ("post", "/v1/detect/bev.png"): "detect_bev_png",
        ("post", "/v1/detect/camera.png"): "detect_camera_png", ("get", "/v1/model"): "model_info",
        ("get", "/healthz"): "healthz", ("get", "/readyz"): "readyz", ("get", "/v2/health/live"): "v2_live",
        ("get", "/v2/health/ready"): "v2_ready", ("get", "/metrics"): "metrics",
    }
    body = schema["paths"]["/v1/detect"]["post"]["requestBody"]["content"]["multipart/form-data"]["schema"]
    assert body["$ref"].endswith("/Body_detect")


def test_the_request_id_is_declared_on_every_operation_and_answer(
    schema: dict[str, Any], client: AppClient, frame: dict[str, bytes]  # noqa: F811
) -> None:
    """X-Request-ID: an optional header of every operation (a generated client gets a parameter for it) and a
    header of every answer it declares, and so of every answer the service gives."""
    for path, method, operation in _operations(schema):
        header = [p for p in operation["parameters"] if p["in"] == "header" and p["name"] == "X-Request-ID"]
        assert len(header) == 1 and header[0]["required"] is False, f"{method} {path}"
        for status, response in operation["responses"].items():
            assert response["headers"]["X-Request-ID"]["required"] is True, f"{method} {path} {status}"
    answers = [client.get("/healthz", headers={"X-Request-ID": "mine-1"}),
               client.post("/v1/detect", files=parts(frame, points=b"x" * 17), headers={"X-Request-ID": "mine-1"})]
    assert [(a.status_code, a.headers["x-request-id"]) for a in answers] == [(200, "mine-1"), (422, "mine-1")]


def test_the_multipart_parts_say_their_content_types(schema: dict[str, Any]) -> None:
    """FastAPI calls every file part application/octet-stream; the encoding says what a client sends in each."""
    for route in ("/v1/detect", "/v1/detect/bev.png", "/v1/detect/camera.png"):
        multipart = schema["paths"][route]["post"]["requestBody"]["content"]["multipart/form-data"]
        encoding = {part: value["contentType"] for part, value in multipart["encoding"].items()}
        assert encoding == {"image": "image/png, image/jpeg", "points": "application/octet-stream",
                            "calib": "text/plain"}, route
        body = schema["components"]["schemas"][multipart["schema"]["$ref"].rsplit("/", 1)[1]]
        assert set(encoding) == set(body["properties"])  # one entry per part, none the route does not take


def test_the_bearer_scheme_is_declared_also_without_a_token(schema: dict[str, Any], tiny_models: Path) -> None:  # noqa: F811
    """A client generated from a server without a token can send one to a server with one: the scheme is
    always declared, optional ({} = none) without a token and required with one; the probes never ask."""
    bearer = schema["components"]["securitySchemes"]["HTTPBearer"]
    assert (bearer["type"], bearer["scheme"]) == ("http", "bearer")
    for path, method, operation in _operations(schema):
        expected = [{}, {"HTTPBearer": []}] if path.startswith("/v1/") else None
        assert operation.get("security") == expected, f"{method} {path}"
    with service(tiny_models, token="t0ken") as guarded:
        detect = guarded.get("/openapi.json").json()["paths"]["/v1/detect"]["post"]
        assert detect["security"] == [{"HTTPBearer": []}]


def test_each_error_status_shows_every_code_it_carries(schema: dict[str, Any]) -> None:
    """Each declared error answer is the ErrorResponse, with an example of each code of its status; the
    request id is always there (a C++ client need not make it optional)."""
    for path, method, operation in _operations(schema):
        for status, response in operation["responses"].items():
            if int(status) < 400:
                continue
            content = response["content"]["application/json"]
            assert content["schema"]["$ref"].endswith("/ErrorResponse"), f"{method} {path} {status}"
            examples = {name: example["value"]["error"] for name, example in content["examples"].items()}
            assert sorted(examples) == sorted(ERROR_CODES[int(status)]), f"{method} {path} {status}"
            assert all(error["code"] == name and error["message"] for name, error in examples.items())
    detail = schema["components"]["schemas"]["ErrorDetail"]
    assert detail["required"] == ["code", "message", "request_id"]
    assert detail["properties"]["request_id"] == {**detail["properties"]["request_id"], "type": "string"}
    assert "503: overloaded, not_ready, shutting_down" in detail["properties"]["code"]["description"]


def test_every_box_field_says_its_unit_and_the_frame_is_named(schema: dict[str, Any]) -> None:
    """A box is read in the KITTI velodyne frame, in metres and radians, z its centre: each field says so."""
    box = schema["components"]["schemas"]["Box"]
    assert "velodyne" in box["description"]
    for name, field in box["properties"].items():
        assert ("radians" if name == "yaw" else "metres") in field["description"], name
    assert "centre" in box["properties"]["z"]["description"]
    corners = schema["components"]["schemas"]["Detection"]["properties"]["bev_corners"]["description"]
    assert "metres" in corners and "LiDAR frame" in corners


# --------------------------------------------------------------------------- error answers
def test_a_405_names_every_method_of_the_route(client: AppClient) -> None:  # noqa: F811
    """A probe is served by a GET and a HEAD route: a POST to it was told ``Allow: HEAD`` alone."""
    response = client.post("/healthz")
    assert_error(response, 405, "method_not_allowed", "POST /healthz", "GET, HEAD")
    assert response.headers["allow"] == "GET, HEAD"
    response = client.request("DELETE", "/v1/detect")
    assert_error(response, 405, "method_not_allowed", "DELETE /v1/detect", "POST")
    assert response.headers["allow"] == "POST"


def test_a_404_and_an_unparsable_body_name_what_was_at_fault(client: AppClient) -> None:  # noqa: F811
    """Starlette says "Not Found" and "Invalid multipart data."; the service's messages start with the field."""
    assert_error(client.get("/v1/detections"), 404, "not_found", "GET /v1/detections: no such route", "/openapi.json")
    for content_type in ("multipart/form-data", "multipart/form-data; boundary=x"):
        response = client.post("/v1/detect", headers={"content-type": content_type}, content=b"garbage")
        error = assert_error(response, 400, "bad_request")
        assert error["message"].startswith("request body: "), error


@contextmanager
def served(settings: Settings) -> Iterator[str]:
    """The service as ``python -m service`` serves it (uvicorn with service/protocol.py, the lifespan over ASGI)
    in a thread, on 127.0.0.1 and a free port; its base URL once /readyz answers 200."""
    app = create_app(settings)
    server = uvicorn.Server(uvicorn_config(settings, app))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 30
        while not (server.started and server.servers):
            assert thread.is_alive() and time.monotonic() < deadline, "uvicorn did not start"
            time.sleep(0.02)
        url = f"http://127.0.0.1:{server.servers[0].sockets[0].getsockname()[1]}"
        while httpx.get(f"{url}/readyz", timeout=5).status_code != 200:
            assert time.monotonic() < deadline, "the service did not become ready (its lifespan did not run?)"
            time.sleep(0.05)
        yield url
    finally:
        server.should_exit = True
        thread.join(30)


@pytest.fixture(scope="module")
def served_default(tiny_models: Path) -> Iterator[tuple[str, int]]:  # noqa: F811
    """The default service over a socket: what the HTTP protocol answers itself comes before any app."""
    with served(Settings(models=tiny_models, port=0, log_level="warning")) as url:
        host, port = url.removeprefix("http://").split(":")
        yield host, int(port)


def _raw_answer(address: tuple[str, int], request: bytes) -> tuple[str, dict[str, str], bytes]:
    """Send ``request`` as is; the status line, headers and body the server sent before closing."""
    with socket.create_connection(address, timeout=5) as sock:
        sock.sendall(request)
        data = b""
        while chunk := sock.recv(65536):
            data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    status, *lines = head.decode("latin-1").split("\r\n")
    return status, {name.lower(): value for name, _, value in (line.partition(": ") for line in lines)}, body


@pytest.mark.parametrize("request_bytes", [b"GARBAGE\r\n\r\n", b"GET / HTTP/1.1\r\n\r\n",
                                           b"GET / HTTP/1.1\r\nHost: x\r\nContent-Length: abc\r\n\r\n"],
                         ids=["no request line", "no Host", "bad Content-Length"])
def test_a_request_http_cannot_parse_is_answered_in_the_error_shape(
    served_default: tuple[str, int], request_bytes: bytes
) -> None:
    """uvicorn answers such a request in plain text ("Invalid HTTP request received."); the service's clients
    parse one shape, so the protocol answers JSON with an id and closes the connection."""
    status, headers, body = _raw_answer(served_default, request_bytes)
    assert status.startswith("HTTP/1.1 400"), status
    assert headers["content-type"] == "application/json" and headers["connection"] == "close"
    error = json.loads(body)["error"]
    assert error["code"] == "bad_request" and error["message"].startswith("request: not valid HTTP/1.1")
    assert error["request_id"] == headers["x-request-id"]


# --------------------------------------------------------------------------- CORS
def test_cors_is_off_by_default_and_serves_the_configured_origins(
    client: AppClient, tiny_models: Path, frame: dict[str, bytes], caplog: pytest.LogCaptureFixture  # noqa: F811
) -> None:
    """A dashboard in a browser on another origin can call the service only with ``--cors-origins``: its
    preflight passes, and every answer its script reads (a 500 included) carries the CORS headers and exposes
    the request id, warnings and Retry-After; a preflight from another origin is refused in the error shape.
    Served by uvicorn as ``python -m service`` serves it: the CORS layer must let the lifespan through."""
    preflight = {"Origin": DASHBOARD, "Access-Control-Request-Method": "POST",
                 "Access-Control-Request-Headers": "authorization, x-request-id"}
    off = client.request("OPTIONS", "/v1/detect", headers=preflight)
    assert_error(off, 405, "method_not_allowed")
    assert "access-control-allow-origin" not in off.headers
    assert "access-control-allow-origin" not in client.get("/healthz", headers={"Origin": DASHBOARD}).headers

    settings = Settings(models=tiny_models, port=0, log_level="warning",
                        cors_origins=f"{DASHBOARD}, https://ops.example:8443")
    with served(settings) as url, httpx.Client(base_url=url, timeout=30) as browser:
        allowed = browser.options("/v1/detect", headers=preflight)
        assert allowed.status_code == 200, allowed.text
        assert allowed.headers["access-control-allow-origin"] == DASHBOARD
        assert {"authorization", "x-request-id"} <= {
            h.strip().lower() for h in allowed.headers["access-control-allow-headers"].split(",")}
        origin = {"Origin": DASHBOARD}
        answers = [browser.post("/v1/detect", files=parts(frame), headers=origin),
                   browser.post("/v1/detect", files=parts(frame, points=b"x" * 17), headers=origin),
                   browser.get("/nowhere", headers=origin)]
        # A bug on the worker: the 500 comes from the request context, the outermost layer but CORS.
        with (caplog.at_level(logging.CRITICAL, logger="service.middleware"),
              patch("pipeline.detector.Detector.detect", side_effect=ZeroDivisionError)):
            answers.append(browser.post("/v1/detect", files=parts(frame), headers=origin))
        assert [a.status_code for a in answers] == [200, 422, 404, 500]
        for answer in answers:
            assert answer.headers["access-control-allow-origin"] == DASHBOARD, answer.status_code
            exposed = {h.strip().lower() for h in answer.headers["access-control-expose-headers"].split(",")}
            assert {"x-request-id", "x-warnings", "x-warning-codes", "retry-after"} <= exposed
        refused = browser.options("/v1/detect", headers={**preflight, "Origin": "http://elsewhere"})
        assert_error(refused, 400, "bad_request", "CORS preflight", "Origin: http://elsewhere", "--cors-origins")
        assert "access-control-allow-origin" not in refused.headers


@pytest.mark.parametrize(("value", "words"), [("localhost:5173", "'localhost:5173' is no origin"),
                                              ("http://dash/", "'http://dash/' is no origin"),
                                              (" , ", "empty; give origins")])
def test_a_cors_origin_that_is_no_origin_stops_the_start_naming_the_option(value: str, words: str) -> None:
    """A browser sends ``Origin: http://host:port``: a value with a path or without a scheme would never match,
    and CORS would stay off without a word."""
    with pytest.raises(ValidationError) as raised:
        Settings(cors_origins=value)
    [line] = settings_errors(raised.value)
    assert line.startswith("--cors-origins (LOWRES3D_CORS_ORIGINS)") and words in line, line
    assert Settings(cors_origins=" * ").cors_origin_list() == ["*"]


# --------------------------------------------------------------------------- the camera picture
def test_the_camera_picture_has_a_key_as_the_bev_picture_has(client: AppClient, frame: dict[str, bytes]) -> None:  # noqa: F811
    """camera.png's key in the top-right corner, drawn by pipeline.render.draw_key with the rows of
    pipeline.render.key_rows, titled with the model (service.routes.detect.picture_title): a black box holding the
    orange swatch of the detections and white text."""
    response = client.post("/v1/detect/camera.png", params={"score_threshold": 0.0}, files=parts(frame))
    assert response.status_code == 200
    picture = cv2.imdecode(np.frombuffer(response.content, np.uint8), cv2.IMREAD_COLOR)
    image = cv2.imdecode(np.frombuffer(frame["image"], np.uint8), cv2.IMREAD_COLOR)
    expected = image.copy()
    title = picture_title(client.app.state.runtime.identity, None)
    left, top, right, bottom = draw_key(expected, key_rows(title, True, False), corner="top-right")
    assert (top, right) == (0, picture.shape[1])  # the top-right corner
    key, drawn = picture[top:bottom, left:right], expected[top:bottom, left:right]
    assert (key == PREDICTION_BGR).all(axis=2).any()  # the detections' swatch
    assert (key.min(axis=2) > 128).sum() > 50  # its text: white, anti-aliased
    # Pixel for pixel the key draw_key makes (boxes are drawn first: one under the key is covered by it).
    assert np.array_equal(key, drawn)
