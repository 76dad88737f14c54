"""Service behaviour a mutation audit of the middleware, protocol, app, runtime, deps and logs found unpinned
(session 43): each test here failed under a one-line change of the code it names, and passes on the code."""

from __future__ import annotations

import json
import logging
import shutil
import socket
import subprocess
import sys
import threading
import time
from collections.abc import AsyncIterator
from pathlib import Path

import anyio
import httpx
import numpy as np
import pytest

from pipeline.detector import Detector
from pipeline.model_files import ModelFileError
from service.app import create_app
from service.logs import REQUEST_ID, JsonFormatter, RequestIdFilter, requested_log_format
from service.metrics import Metrics
from service.runtime import load_runtime, loaded_identity
from service.settings import Settings
from tests.test_service import assert_error, frame, parts, service, tiny_models  # noqa: F401 - fixtures
from tests.test_service_openapi import served
from tests.test_service_process import REPO
from tests.test_service_readiness import _without_lifespan


def _multipart(frame: dict[str, bytes]) -> tuple[bytes, dict[str, str]]:  # noqa: F811
    """The frame's multipart body (its first 2000 points: a small upload) and its Content-Type."""
    request = httpx.Request("POST", "http://service/v1/detect", files=parts(frame, points=frame["points"][: 16 * 2000]))
    return request.read(), {"content-type": request.headers["content-type"]}


def _access(caplog: pytest.LogCaptureFixture, request_id: str) -> logging.LogRecord:
    """The one access line of ``request_id``."""
    (line,) = [r for r in caplog.records if r.name == "service.access" and getattr(r, "request_id", None) == request_id]
    return line


# --------------------------------------------------------------------------- the access line
def test_the_access_lines_duration_is_in_milliseconds(
    tiny_models: Path, frame: dict[str, bytes], caplog: pytest.LogCaptureFixture  # noqa: F811
) -> None:
    """A request whose body takes 0.4 s to arrive: its access line says at least 400 ms (``duration_ms`` and the
    sentence alike), and no more than the request took (a field in seconds would say 0.4)."""
    body, headers = _multipart(frame)

    async def slowly() -> AsyncIterator[bytes]:
        half = len(body) // 2
        for piece in (body[:half], body[half:]):
            await anyio.sleep(0.2)
            yield piece

    with service(tiny_models) as app_client, caplog.at_level(logging.INFO, logger="service.access"):
        tic = time.monotonic()
        response = app_client.post("/v1/detect", content=slowly(), headers={**headers, "X-Request-ID": "slow-1"})
        took_ms = (time.monotonic() - tic) * 1e3
        assert response.status_code == 200, response.text
    line = _access(caplog, "slow-1")
    assert 400 <= line.duration_ms <= took_ms, (line.duration_ms, took_ms)  # type: ignore[attr-defined]
    assert f" in {line.duration_ms:.0f} ms " in line.getMessage()  # type: ignore[attr-defined]



def test_a_500s_access_line_names_its_error_code(
    tiny_models: Path, frame: dict[str, bytes], caplog: pytest.LogCaptureFixture  # noqa: F811
) -> None:
    """A bug on the worker: the request context answers 500 itself, and its access line (an ERROR) names the
    code ``internal_error`` as every other refusal's does, so a log search by code finds it."""
    with service(tiny_models) as app_client:

        def broken(*args: object, **kwargs: object) -> None:
            raise RuntimeError("a bug")

        app_client.app.state.runtime.detector.detect = broken
        with caplog.at_level(logging.INFO, logger="service.access"):
            response = app_client.post("/v1/detect", files=parts(frame), headers={"X-Request-ID": "bug-1"})
        assert_error(response, 500, "internal_error")
    line = _access(caplog, "bug-1")
    assert (line.status, line.error_code, line.levelname) == (500, "internal_error", "ERROR")  # type: ignore[attr-defined]
    assert " 500 internal_error in " in line.getMessage()


# --------------------------------------------------------------------------- the token's reach
def test_the_token_guards_v1_and_everything_under_it_and_nothing_beside(tiny_models: Path) -> None:  # noqa: F811
    """``/v1`` and ``/v1/…`` are the API's: without the token they are answered 401 (whether a route exists there
    is not told); ``/v1x`` is no part of it and is answered 404 like any unknown path."""
    with service(tiny_models, token="s3cret-token") as app_client:
        for path in ("/v1", "/v1/", "/v1/nowhere"):
            assert_error(app_client.get(path), 401, "unauthorized")
        assert_error(app_client.get("/v1x"), 404, "not_found")
        assert_error(app_client.get("/v1", headers={"Authorization": "Bearer s3cret-token"}), 404, "not_found")


# --------------------------------------------------------------------------- the multipart close delimiter
def test_a_close_delimiter_split_across_chunks_at_any_byte_is_found(
    tiny_models: Path, frame: dict[str, bytes]  # noqa: F811
) -> None:
    """The body limit looks for ``CRLF--BOUNDARY--`` across the chunks a body arrives in: wherever the split
    falls inside it (down to its last byte alone in the second chunk), the body is whole and answered 200, not
    400 "ended before its closing boundary"."""
    body, headers = _multipart(frame)
    boundary = headers["content-type"].split("boundary=", 1)[1]
    needle = f"\r\n--{boundary}--".encode()
    start = body.rindex(needle)

    def in_two(split: int) -> AsyncIterator[bytes]:
        async def chunks() -> AsyncIterator[bytes]:
            yield body[:split]
            yield body[split:]
        return chunks()

    with service(tiny_models) as app_client:
        for split in range(start + 1, start + len(needle)):
            response = app_client.post("/v1/detect", content=in_two(split), headers=headers)
            assert response.status_code == 200, (split - start, response.text)


def test_a_body_that_is_its_close_delimiter_alone_is_whole_and_lacks_its_parts(tiny_models: Path) -> None:  # noqa: F811
    """``--BOUNDARY--`` at the very start of the body (a form of no parts) is a whole body: the answer names the
    missing part (422), not a cut-off upload (400)."""
    with service(tiny_models) as app_client:
        for body in (b"--bb--\r\n", b"--bb--"):
            response = app_client.post("/v1/detect", content=body,
                                       headers={"content-type": "multipart/form-data; boundary=bb"})
            assert_error(response, 422, "invalid_input", "points: Field required")


# --------------------------------------------------------------------------- admission
def test_only_a_detection_post_takes_a_place_in_the_pool(tiny_models: Path) -> None:  # noqa: F811
    """With the pool's one place taken, a GET on a detection route is still answered 405 (it would never run a
    frame), and a POST 503 overloaded; once the place is given back, the POST is read and judged."""
    with service(tiny_models, workers=1, queue_size=0) as app_client:
        held = app_client.app.state.runtime.pool.reserve()
        try:
            for path in ("/v1/detect", "/v1/detect/bev.png", "/v1/detect/camera.png"):
                assert_error(app_client.get(path), 405, "method_not_allowed")
            assert_error(app_client.post("/v1/detect", content=b""), 503, "overloaded")
        finally:
            held.release()
        assert_error(app_client.post("/v1/detect", content=b""), 415, "unsupported_media_type")


def test_a_frame_sent_after_the_pool_has_stopped_is_told_the_service_is_shutting_down(
    tiny_models: Path, frame: dict[str, bytes]  # noqa: F811
) -> None:
    """Between the pool's stop and the process's end a frame gets 503 shutting_down with Retry-After (another
    replica may take it), not "overloaded", which would say the same replica is worth retrying."""
    with service(tiny_models) as app_client:
        app_client.app.state.runtime.pool.shutdown()
        response = app_client.post("/v1/detect", files=parts(frame))
        assert_error(response, 503, "shutting_down", "shutting down")
        assert response.headers["retry-after"] == "1" and response.headers["connection"] == "close"


# --------------------------------------------------------------------------- the HTTP protocol's head deadline
def _read_answer(sock: socket.socket) -> tuple[int, dict[str, str], bytes]:
    """One answer read off a kept-alive connection: (status, headers, body), by its Content-Length."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(65536)
        assert chunk, f"the connection closed before an answer: {data!r}"
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    status, *lines = head.decode("latin-1").split("\r\n")
    headers = {name.lower(): value for name, _, value in (line.partition(": ") for line in lines)}
    while len(body) < int(headers["content-length"]):
        chunk = sock.recv(65536)
        assert chunk, "the connection closed during an answer"
        body += chunk
    return int(status.split()[1]), headers, body


def _until_closed(sock: socket.socket, timeout_s: float) -> tuple[bytes, bool]:
    """What the server sends until it closes the connection (True) or ``timeout_s`` passes (False)."""
    sock.settimeout(timeout_s)
    data = b""
    try:
        while chunk := sock.recv(65536):
            data += chunk
    except TimeoutError:
        return data, False
    return data, True


def test_a_kept_alive_connection_gets_the_head_deadline_again_after_each_answer(tiny_models: Path) -> None:  # noqa: F811
    """After an answer on a kept-alive connection the next request's head has --receive-timeout-s again: half a
    head is answered 408 and the connection closed, not held until the client gives up."""
    settings = Settings(models=tiny_models, port=0, log_level="warning", receive_timeout_s=0.5)
    with served(settings) as url:
        host, port = url.removeprefix("http://").split(":")
        with socket.create_connection((host, int(port)), timeout=10) as sock:
            sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
            assert _read_answer(sock)[0] == 200
            tic = time.monotonic()  # the deadline runs from the answer
            sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n")
            data, closed = _until_closed(sock, 5)
            took = time.monotonic() - tic
    assert closed and data.startswith(b"HTTP/1.1 408 "), data
    assert b'"code": "request_timeout"' in data and 0.4 < took < 3, took


def test_a_pipelined_request_still_being_answered_keeps_its_connection(
    tiny_models: Path, frame: dict[str, bytes]  # noqa: F811
) -> None:
    """Two requests sent at once: the second, a frame that takes longer than --receive-timeout-s to answer, has
    its head already in, so the deadline armed after the first answer does not close its connection."""
    request = httpx.Request("POST", "http://x/v1/detect?emulate_beams=16", files=parts(frame, points=frame["points"] * 8))
    body = request.read()
    second = (f"POST /v1/detect?emulate_beams=16 HTTP/1.1\r\nHost: x\r\nContent-Type: "
              f"{request.headers['content-type']}\r\nContent-Length: {len(body)}\r\n\r\n").encode() + body
    settings = Settings(models=tiny_models, port=0, log_level="warning", receive_timeout_s=0.2)
    with served(settings) as url:
        host, port = url.removeprefix("http://").split(":")
        with socket.create_connection((host, int(port)), timeout=30) as sock:
            sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n" + second)
            assert _read_answer(sock)[0] == 200
            tic = time.monotonic()
            status, _, answer = _read_answer(sock)
            took = time.monotonic() - tic
    assert status == 200, answer
    assert took > 0.2, took  # it did outlast the deadline (else this test could not fail)


# --------------------------------------------------------------------------- the lifespan's shutdown
def test_the_stop_says_not_ready_and_releases_the_sessions(tiny_models: Path) -> None:  # noqa: F811
    """Once the app has stopped, its ready gauge says 0 (a last scrape must not report a stopped replica
    ready), and the Detectors have released their sessions: a frame run on them is refused as closed."""
    with service(tiny_models) as app_client:
        runtime, metrics = app_client.app.state.runtime, app_client.app.state.metrics
        assert "lowres3d_ready 1.0" in metrics.render().decode()
        assert runtime.detector.providers_in_use  # the sessions, while it serves
    assert "lowres3d_ready 0.0" in metrics.render().decode()
    assert runtime.detector.providers_in_use == {}
    with pytest.raises(RuntimeError, match="was closed"):
        runtime.detector.detect(None, np.zeros((10, 4), np.float32), None)


# --------------------------------------------------------------------------- the connection limit
def test_a_request_on_the_last_place_the_limit_allows_is_served(tiny_models: Path) -> None:  # noqa: F811
    """With 1 worker and no queue the limit is 1 + 0 + 16 = 17 requests in progress: with 16 held, a request is
    served (the 17th); with 17 held, the next is answered 503 overloaded. The held ones are uploads refused 401
    whose bodies the service waits for (a lingering close of up to 2 s): requests in progress, not idle sockets,
    which no longer count (service/protocol.py)."""
    token = "limit-token"
    settings = Settings(models=tiny_models, port=0, log_level="warning", workers=1, queue_size=0, token=token)
    limit = settings.connection_limit()
    assert limit == 17
    head = (b"POST /v1/detect HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\n"
            b"Content-Length: 1000000\r\n\r\n")
    auth = {"Authorization": f"Bearer {token}"}
    with served(settings) as url:
        host, port = url.removeprefix("http://").split(":")

        def upload_held() -> socket.socket:
            """A request in progress: its 401 answered at once, its body (never sent) waited for."""
            sock = socket.create_connection((host, int(port)), timeout=10)
            sock.sendall(head)
            assert _read_answer(sock)[0] == 401
            return sock

        held = [upload_held() for _ in range(limit - 1)]
        try:  # all within the 2 s the held requests linger
            model = httpx.get(f"{url}/v1/model", headers=auth, timeout=5)
            assert model.status_code == 200, model.text
            held.append(upload_held())
            assert_error(httpx.get(f"{url}/v1/model", headers=auth, timeout=5), 503, "overloaded",
                         f"the limit of {limit} in progress")
        finally:
            for sock in held:
                sock.close()


# --------------------------------------------------------------------------- the token's comparison
def test_only_the_whole_token_is_accepted(tiny_models: Path) -> None:  # noqa: F811
    """A prefix of the token, a single character of it or the token with a character changed is refused 401,
    before routing and at the route alike; the token itself is accepted."""
    token = "s3cret-token"
    with service(tiny_models, token=token) as app_client:
        for guess in (token[:-1], token[:1], token[:-1] + "X", token.upper()):
            assert_error(app_client.get("/v1/model", headers={"Authorization": f"Bearer {guess}"}), 401,
                         "unauthorized")
        assert app_client.get("/v1/model", headers={"Authorization": f"Bearer {token}"}).status_code == 200


# --------------------------------------------------------------------------- the log's format
def test_a_json_line_is_ascii_whatever_the_message_holds() -> None:
    """A message with characters beyond ASCII (a path, a client's text) is written escaped: every byte of the line
    is ASCII, so no shipper's encoding setting can garble it, and it parses back to the message."""
    message = "model directory /srv/modèles/voiture→edge ✓"
    record = logging.LogRecord("service.runtime", logging.INFO, __file__, 1, message, None, None)
    line = JsonFormatter().format(record)
    assert line.isascii(), line
    assert json.loads(line)["message"] == message


def test_a_libraries_python_warning_becomes_a_line_in_the_chosen_format() -> None:
    """After configure_logging, a library's ``warnings.warn`` is a record like any other (logger ``py.warnings``),
    one JSON line, not the two lines of plain text Python writes by default."""
    code = ("import warnings\nfrom service.logs import configure_logging\nconfigure_logging('info', 'json')\n"
            "warnings.warn('a library is unhappy', RuntimeWarning)\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60,
                          check=True)
    (line,) = done.stderr.splitlines()
    record = json.loads(line)
    assert record["logger"] == "py.warnings" and record["level"] == "WARNING", record
    assert "RuntimeWarning: a library is unhappy" in record["message"], record


def test_the_stop_lets_a_request_still_in_flight_answer_first(
    tiny_models: Path, frame: dict[str, bytes], caplog: pytest.LogCaptureFixture  # noqa: F811
) -> None:
    """A stop while an upload is still arriving: once the pool has stopped, the shutdown waits (up to 2 s) for the
    request to answer, here 503 shutting_down as its body ends, before it closes the models; nothing is left
    "still unanswered"."""
    body, headers = _multipart(frame)

    async def slowly() -> AsyncIterator[bytes]:
        yield body[:100]
        await anyio.sleep(0.5)
        yield body[100:]

    answers: list[httpx.Response] = []
    with caplog.at_level(logging.WARNING, logger="service.app"):
        with service(tiny_models) as app_client:
            sender = threading.Thread(target=lambda: answers.append(
                app_client.post("/v1/detect", content=slowly(), headers=headers)))
            sender.start()
            pool = app_client.app.state.runtime.pool
            deadline = time.monotonic() + 10
            while pool.depth == (0, 0):  # its place taken: the request is in flight
                assert time.monotonic() < deadline
                time.sleep(0.01)
        answered_by_the_stop = bool(answers)
        sender.join(10)
    assert answered_by_the_stop, answers
    assert_error(answers[0], 503, "shutting_down")
    assert not [r for r in caplog.records if "still unanswered" in r.getMessage()]


def test_a_record_keeps_its_own_request_id_else_takes_the_requests() -> None:
    """A worker thread logs with ``extra={"request_id": ...}`` (the context of the request is the event loop's):
    that id is kept even while another request is being handled; a record without one takes the request's."""
    request_id_filter = RequestIdFilter()
    own = logging.LogRecord("service.pool", logging.INFO, __file__, 1, "frame stopped", None, None)
    own.request_id = "from-the-worker"
    plain = logging.LogRecord("service.routes", logging.INFO, __file__, 1, "a line", None, None)
    token = REQUEST_ID.set("on-the-loop")
    try:
        assert request_id_filter.filter(own) and request_id_filter.filter(plain)
    finally:
        REQUEST_ID.reset(token)
    assert (own.request_id, plain.request_id) == ("from-the-worker", "on-the-loop")  # type: ignore[attr-defined]
    outside = logging.LogRecord("service.app", logging.INFO, __file__, 1, "no request", None, None)
    assert request_id_filter.filter(outside) and outside.request_id is None  # type: ignore[attr-defined]


# --------------------------------------------------------------------------- loading the models
def test_a_file_given_as_the_model_directory_is_named_as_no_directory(tiny_models: Path, tmp_path: Path) -> None:  # noqa: F811
    """``--models`` naming a file (the manifest itself, say) stops the start with the model directory's own
    message and the way to fix it, not an error about a file inside it."""
    with pytest.raises(ModelFileError, match="model directory not found; pass --models DIR"):
        load_runtime(Settings(models=tiny_models / "manifest.json"), Metrics())



def test_a_model_directory_without_links_is_named_as_given(
    tiny_models: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture  # noqa: F811
) -> None:
    """``--models NAME`` relative and free of links: the start's lines name it as given, with no "(→ …)" that
    would say a link was followed, and the Detector loads it under that name."""
    assert tiny_models.resolve() == tiny_models  # no link on the way here (else the arrow would be right)
    monkeypatch.chdir(tiny_models.parent)
    with caplog.at_level(logging.INFO, logger="service.runtime"):
        runtime = load_runtime(Settings(models=Path(tiny_models.name)), Metrics())
    try:
        assert runtime.detector.model_dir == Path(tiny_models.name)
        (loading,) = [r.getMessage() for r in caplog.records if r.getMessage().startswith("loading ")]
        assert loading.startswith(f"loading {tiny_models.name} (1 session set(s)"), loading
    finally:
        runtime.close()


def test_sessions_loaded_from_two_versions_of_the_manifest_are_refused(tiny_models: Path, tmp_path: Path) -> None:  # noqa: F811
    """Per-worker sessions, the manifest replaced between the first worker's load and the second's: the workers
    would serve two models under one identity, so the start is refused (one Detector differing is enough)."""
    models = Path(shutil.copytree(tiny_models, tmp_path / "models"))
    first = Detector(models, providers="cpu")
    manifest = json.loads((models / "manifest.json").read_text())
    (models / "manifest.json").write_text(json.dumps({**manifest, "note": "a newer export copied in"}))
    second = Detector(models, providers="cpu")
    try:
        with pytest.raises(ModelFileError, match="the model directory changed while the service loaded it"):
            loaded_identity(models, [first, second])
    finally:
        first.close()
        second.close()


def test_a_network_file_replaced_after_the_sessions_loaded_it_is_refused(tiny_models: Path, tmp_path: Path) -> None:  # noqa: F811
    """A network file rewritten after the Detector read it (the manifest left alone): the directory no longer holds
    what the sessions run, so its identity is refused naming the file."""
    models = Path(shutil.copytree(tiny_models, tmp_path / "models"))
    detector = Detector(models, providers="cpu")
    try:
        with (models / "pixor.onnx").open("ab") as network:
            network.write(b"\0")
        with pytest.raises(ModelFileError, match="pixor.onnx"):
            loaded_identity(models, [detector])
    finally:
        detector.close()


def test_the_loaded_models_warning_codes_are_in_the_metrics(tiny_models: Path) -> None:  # noqa: F811
    """The tiny models carry untrained weights: /metrics says so (``lowres3d_model_warnings`` 1 for that code, 0 for
    the others), so a fleet's dashboard sees a replica serving a model that means nothing."""
    with service(tiny_models) as app_client:
        text = app_client.get("/metrics").text
    assert 'lowres3d_model_warnings{code="untrained_weights"} 1.0' in text
    assert 'lowres3d_model_warnings{code="provider_fallback"} 0.0' in text


def test_before_the_models_load_the_schema_asks_for_the_image(tiny_models: Path) -> None:  # noqa: F811
    """Until the model is loaded the schema assumes a camera model (every shipped one is): the image is a required
    part of /v1/detect, as it is once the tiny camera model has loaded."""
    app = create_app(Settings(models=tiny_models))
    schema = _without_lifespan(app, "GET", "/openapi.json").json()
    ref = schema["paths"]["/v1/detect"]["post"]["requestBody"]["content"]["multipart/form-data"]["schema"]["$ref"]
    assert schema["components"]["schemas"][ref.rsplit("/", 1)[1]]["required"] == ["image", "points"]


def test_the_log_format_for_refused_settings_is_read_as_the_settings_read_it() -> None:
    """The environment variable's name in any case (pydantic-settings reads ``lowres3d_log_format`` too), the
    value in any case and padded; the command line wins; anything else is text."""
    assert requested_log_format({}, {"lowres3d_log_format": " JSON "}) == "json"
    assert requested_log_format({"log_format": "text"}, {"LOWRES3D_LOG_FORMAT": "json"}) == "text"
    assert requested_log_format({}, {"LOWRES3D_LOG_FORMAT": "xml"}) == requested_log_format({}, {}) == "text"


def test_a_records_stored_traceback_is_written_when_its_exception_is_gone() -> None:
    """A record that carries its traceback as text only (``exc_text``: formatted once already, the exception itself
    dropped, as a record sent from another process is) still has it in the JSON line's ``exception``."""
    record = logging.LogRecord("service.pool", logging.ERROR, __file__, 1, "worker failed", None, None)
    record.exc_text = "Traceback (most recent call last):\nRuntimeError: boom"
    event = json.loads(JsonFormatter().format(record))
    assert event["exception"] == record.exc_text and event["message"] == "worker failed"
