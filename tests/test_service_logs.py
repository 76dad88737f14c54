"""The service's log as a log shipper reads it: ``python -m service`` as a real process on 127.0.0.1.

With ``--log-format json`` every line it writes, from the start to the exit (Ctrl-C, SIGTERM with a request
cut off, settings refused), is one JSON object with the stable fields; every request has exactly one access
line (method, path, route, status, duration, request id, client, model, warning codes) at a level that says
whose fault it was; uvicorn's lines follow the same format and level, and never duplicate the access line.
Each server gets a free port and a bounded start, and is stopped in teardown.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest

from service.logs import ACCESS_FIELDS, JsonFormatter, TextFormatter, utc_timestamp
from service.middleware import access_level, client_address, request_target
from tests.test_service import frame, parts  # noqa: F401 - fixtures
from tests.test_service import service as in_process_service
from tests.test_service_process import Server, _metric, _wait_for, running_service

REPO = Path(__file__).resolve().parents[1]
COMMON_FIELDS = ("timestamp", "level", "logger", "message", "request_id")
UTC_ISO = re.compile(r"^\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z$")
TOKEN = "fleet-secret-7f3a"


class Service(Server):
    """A running ``python -m service`` (tests/test_service_process.py's) read as a log shipper reads its output."""

    @property
    def output(self) -> Path:
        return self.log_path

    def lines(self) -> list[str]:
        return self.output.read_text(errors="replace").splitlines()

    def records(self) -> list[dict]:
        """Every line of the output as JSON: a line that is not one fails the test, naming it."""
        records = []
        for line in self.lines():
            try:
                records.append(json.loads(line))
            except ValueError:
                pytest.fail(f"not a JSON line: {line!r}")
        return records

    def access(self, request_id: str) -> list[dict]:
        return [r for r in self.records() if r["logger"] == "service.access" and r["request_id"] == request_id]


@contextmanager
def service(models: Path, output: Path, *args: str, env: dict[str, str] | None = None) -> Iterator[Service]:
    """Start the service with ``env`` added, wait until /readyz answers 200; stop it (SIGTERM, then SIGKILL)."""
    with running_service(models, output, *args, env=env) as server:
        yield Service(server.url, server.process, server.log_path)


def _hold_a_place(url: str, request_id: str) -> socket.socket:
    """A detection request whose head and first body bytes are sent, and no more: it holds its place in the
    inference pool (taken before the body is read) until the socket is closed."""
    host, port = url.removeprefix("http://").split(":")
    sock = socket.create_connection((host, int(port)), timeout=10)
    sock.sendall((f"POST /v1/detect HTTP/1.1\r\nHost: x\r\nX-Request-ID: {request_id}\r\nAuthorization: Bearer "
                  f"{TOKEN}\r\nContent-Type: multipart/form-data; boundary=bb\r\nContent-Length: 100000\r\n\r\n"
                  "--bb\r\n").encode())
    return sock


def _wait_for_its_place(running: Service) -> None:
    """Wait until a held request has its place in the pool: its head read and its place taken (a fixed pause
    could end first on a busy machine, and the next request would take the place, or the signal come first)."""
    _wait_for(lambda: _metric(running, "lowres3d_inference_queue_depth") == 1.0, "the held request took no place")


def _wait_for_line(running: Service, predicate: object, what: str, timeout_s: float = 10.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        found = [r for r in running.records() if predicate(r)]  # type: ignore[operator]
        if found:
            return found[0]
        time.sleep(0.05)
    pytest.fail(f"no line {what} within {timeout_s} s:\n" + "\n".join(running.lines()))


def _check_common(records: list[dict]) -> None:
    for record in records:
        assert set(COMMON_FIELDS) <= set(record), record
        assert UTC_ISO.match(record["timestamp"]), record
        assert record["level"] in ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"), record
        assert "\n" not in record["message"], record


# --------------------------------------------------------------------------- JSON, start to Ctrl-C
def test_json_log_has_one_access_line_per_request_and_every_line_parses(
    tiny_models: Path, frame: dict[str, bytes], tmp_path: Path  # noqa: F811
) -> None:
    with service(tiny_models, tmp_path / "service.log", "--log-format", "json", "--workers", "1", "--queue-size",
                 "0", env={"LOWRES3D_TOKEN": TOKEN}) as running:
        auth = {"Authorization": f"Bearer {TOKEN}"}
        with httpx.Client(base_url=running.url, timeout=30, headers=auth) as client:
            ok = client.post("/v1/detect", params={"format": "kitti", "emulate_beams": 16}, files=parts(frame),
                             headers={"X-Request-ID": "log-ok"})
            assert ok.status_code == 200 and json.loads(ok.headers["x-warning-codes"]) == ["beams_emulated"]
            plain = client.post("/v1/detect", params={"emulate_beams": 16}, files=parts(frame),
                                headers={"X-Request-ID": "log-json"})
            assert plain.json()["warning_codes"] == ["beams_emulated"]
            bad = client.post("/v1/detect", files=parts(frame, points=b"123"), headers={"X-Request-ID": "log-bad"})
            assert bad.status_code == 422
            assert client.get("/v1/nope%0Aforged", headers={"X-Request-ID": "log-404"}).status_code == 404
            assert client.get("/healthz", headers={"X-Request-ID": "log-probe"}).status_code == 200
            assert httpx.get(f"{running.url}/v1/model", headers={"X-Request-ID": "log-401"}).status_code == 401
            held = _hold_a_place(running.url, "log-gone")
            try:
                _wait_for_its_place(running)  # the only one (1 worker, no queue)
                busy = client.post("/v1/detect", files=parts(frame), headers={"X-Request-ID": "log-busy"})
                assert busy.status_code == 503 and busy.json()["error"]["code"] == "overloaded"
            finally:
                held.close()
            _wait_for_line(running, lambda r: r["request_id"] == "log-gone" and r["logger"] == "service.access",
                           "for the request whose client left")
            model_id = ok.headers["x-model-id"]  # which model answered
        running.process.send_signal(signal.SIGINT)
        assert running.process.wait(20) == 130

    records = running.records()
    _check_common(records)
    expected = {  # request id: (status, level, error code, route)
        "log-ok": (200, "INFO", None, "/v1/detect"),
        "log-json": (200, "INFO", None, "/v1/detect"),
        "log-bad": (422, "INFO", "invalid_input", "/v1/detect"),
        "log-404": (404, "INFO", "not_found", "unmatched"),
        "log-401": (401, "INFO", "unauthorized", "/v1/model"),
        "log-busy": (503, "WARNING", "overloaded", "/v1/detect"),
        "log-gone": (499, "INFO", None, "/v1/detect"),
    }
    for request_id, (status, level, code, route) in expected.items():
        (line,) = running.access(request_id)  # exactly one access line each
        assert set(ACCESS_FIELDS) <= set(line), line
        assert (line["status"], line["level"], line["error_code"], line["route"]) == (status, level, code, route)
        assert line["client"].startswith("127.0.0.1:") and line["duration_ms"] >= 0
        assert line["model_id"] == model_id
    ok = running.access("log-ok")[0]
    assert ok["method"] == "POST" and ok["path"] == "/v1/detect?format=kitti&emulate_beams=16"
    assert ok["warning_codes"] == ["beams_emulated"] and "warnings beams_emulated" in ok["message"]
    assert running.access("log-json")[0]["warning_codes"] == ["beams_emulated"]  # a JSON answer's codes too
    assert running.access("log-404")[0]["path"] == "/v1/nope%0Aforged"  # as sent: no line break forged
    assert running.access("log-probe") == []  # the probes' access lines are DEBUG
    assert "client disconnected" in running.access("log-gone")[0]["message"]
    # uvicorn's lines in the same format, its access log not beside ours; the start's warning a WARNING.
    assert {"uvicorn.error", "service.runtime", "service.access"} <= {r["logger"] for r in records}
    assert not [r for r in records if r["logger"] == "uvicorn.access"]
    assert any(r["level"] == "WARNING" and "untrained" in r["message"] for r in records)
    assert records[-1]["message"].startswith("interrupted: the service has stopped")
    # Nothing sensitive: the token never, the frame's bytes never.
    text = running.output.read_text()
    assert TOKEN not in text and "Bearer" not in text and "P2:" not in text


# --------------------------------------------------------------------------- answers the protocol gives itself
def _sent_raw(url: str, *parts: bytes, pause_s: float = 0.0) -> bytes:
    """Send ``parts`` on one connection (``pause_s`` between them); all the server sent until it closed."""
    host, port = url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=10) as sock:
        for i, part in enumerate(parts):
            if i:
                time.sleep(pause_s)
            sock.sendall(part)
        data = b""
        with contextlib.suppress(ConnectionResetError):
            while chunk := sock.recv(65536):
                data += chunk
    return data


def test_answers_given_before_the_app_have_one_access_line_and_a_count(tiny_models: Path, tmp_path: Path) -> None:
    """What h11 answers on its own has its access line and its count like every other request: a body h11
    cannot read (a malformed chunk) under the request's own id with its route (it used to be logged as a
    client that left, 499, under another id than the answer's), a head past --receive-timeout-s (408) and one
    HTTP does not allow (400) under the route ``unparsed``. A malformed chunk after an early answer has begun
    closes the connection with no traceback in the log (h11 cannot start a second answer)."""
    auth = f"Authorization: Bearer {TOKEN}\r\n".encode()
    chunked = (b"POST /v1/detect HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=bb\r\n"
               b"Transfer-Encoding: chunked\r\n")
    with service(tiny_models, tmp_path / "service.log", "--log-format", "json", "--receive-timeout-s", "0.5",
                 env={"LOWRES3D_TOKEN": TOKEN}) as running:
        malformed = _sent_raw(running.url, chunked + auth + b"X-Request-ID: log-chunk\r\n\r\n4\r\n--bb\r\nzz\r\n")
        late = _sent_raw(running.url, chunked + b"X-Request-ID: log-early\r\n\r\n4\r\n--bb\r\n", b"zz\r\n",
                         pause_s=0.2)  # no token: answered 401 at once, the malformed chunk while its body drains
        slow = _sent_raw(running.url, b"GET /healthz HTTP/1.1\r\nHost: x\r\n")
        garbage = _sent_raw(running.url, b"GET /healthz HTTP/1.1\r\nHost: x\r\nno colon here\r\n\r\n")
        counted = {status: _metric(running, f'lowres3d_http_requests_total{{method="{method}",route="unparsed",'
                                            f'status="{status}"}}') for method, status in (("GET", 408), ("GET", 400))}
    assert malformed.startswith(b"HTTP/1.1 400 ") and b"x-request-id: log-chunk" in malformed, malformed
    assert late.startswith(b"HTTP/1.1 401 "), late
    assert slow.startswith(b"HTTP/1.1 408 ") and garbage.startswith(b"HTTP/1.1 400 "), (slow, garbage)
    assert counted == {408: 1.0, 400: 1.0}
    records = running.records()
    _check_common(records)
    assert not [r for r in records if "exception" in r or r["level"] in ("ERROR", "CRITICAL")], records
    (chunk_line,) = running.access("log-chunk")
    assert (chunk_line["status"], chunk_line["error_code"], chunk_line["route"]) == (400, "bad_request", "/v1/detect")
    assert "answered 400 bad_request" in chunk_line["message"]
    (early_line,) = running.access("log-early")
    assert (early_line["status"], early_line["error_code"]) == (401, "unauthorized")
    unparsed = {r["status"]: r for r in records if r["logger"] == "service.access" and r["route"] == "unparsed"}
    assert set(unparsed) == {400, 408}, unparsed
    for status, answer in ((408, slow), (400, garbage)):
        line = unparsed[status]
        assert set(ACCESS_FIELDS) <= set(line) and line["client"].startswith("127.0.0.1:"), line
        assert f"x-request-id: {line['request_id']}".encode() in answer  # the answer's id is the line's
    assert unparsed[408]["method"] == "GET" and unparsed[408]["error_code"] == "request_timeout"
    assert 400 <= unparsed[408]["duration_ms"] < 5000, unparsed[408]  # from the connection's opening
    # h11 drops a refused head's bytes: the label is the head's own first word, kept as it arrived.
    assert unparsed[400]["method"] == "GET" and unparsed[400]["error_code"] == "bad_request"


# --------------------------------------------------------------------------- JSON, SIGTERM cutting a request off
def test_json_log_of_a_shutdown_that_cuts_a_request_off(tiny_models: Path, tmp_path: Path) -> None:
    """SIGTERM with a request whose upload never ends: uvicorn's grace runs out, the request is answered 503
    shutting_down; uvicorn's line about it is a WARNING (what --shutdown-timeout-s is for, not an error)."""
    with service(tiny_models, tmp_path / "service.log", "--log-format", "json", "--shutdown-timeout-s",
                 "0.3", env={"LOWRES3D_TOKEN": TOKEN}) as running:
        held = _hold_a_place(running.url, "log-cut")
        try:
            _wait_for_its_place(running)
            running.process.send_signal(signal.SIGTERM)
            assert running.process.wait(20) == -signal.SIGTERM
        finally:
            held.close()
    records = running.records()
    _check_common(records)
    (cut,) = running.access("log-cut")
    # The middleware's own line about it names the request in its field too (the request's context, not an extra).
    (said,) = [r for r in records if r["logger"] == "service.middleware" and "cut off by the shutdown" in r["message"]]
    assert said["request_id"] == "log-cut" and said["level"] == "WARNING"
    assert (cut["status"], cut["error_code"], cut["level"]) == (503, "shutting_down", "WARNING")
    assert not [r for r in records if r["level"] in ("ERROR", "CRITICAL")], records
    (grace,) = [r for r in records if r["message"].startswith("Cancel 1 running task(s)")]
    assert grace["level"] == "WARNING" and grace["logger"] == "uvicorn.error"
    assert records[-1]["message"].startswith("Finished server process")


# --------------------------------------------------------------------------- refused settings
def test_refused_settings_are_json_lines_when_json_was_asked_for() -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("LOWRES3D_")}
    env |= {"LOWRES3D_LOG_FORMAT": "json", "LOWRES3D_PORT": "99999", "LOWRES3D_TOKEN": " leaked-token "}
    done = subprocess.run([sys.executable, "-m", "service"], check=False, cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 2 and done.stdout == ""
    records = [json.loads(line) for line in done.stderr.splitlines()]
    _check_common(records)
    assert [r["level"] for r in records] == ["ERROR", "ERROR"]
    assert records[0]["message"].startswith("cannot start: --port (LOWRES3D_PORT) 99999: ")
    assert records[1]["message"].startswith("cannot start: --token (LOWRES3D_TOKEN): starts or ends with whitespace")
    assert "leaked-token" not in done.stderr
    # Without it, the one plain line of every command; a format that is none of the two is refused in it.
    env["LOWRES3D_LOG_FORMAT"] = "xml"
    done = subprocess.run([sys.executable, "-m", "service"], check=False, cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 2
    assert "python -m service: --log-format (LOWRES3D_LOG_FORMAT) xml: input should be 'text' or 'json'" in done.stderr


# --------------------------------------------------------------------------- text, levels
def test_text_log_at_debug_from_the_environment(
    tiny_models: Path, frame: dict[str, bytes], tmp_path: Path  # noqa: F811
) -> None:
    """LOWRES3D_LOG_LEVEL=debug: the probes' access lines appear (DEBUG), each request still has one line
    (uvicorn's own access log, which said the same without the request id, stays off); times are UTC."""
    with service(tiny_models, tmp_path / "service.log", env={"LOWRES3D_LOG_LEVEL": "debug"}) as running:
        with httpx.Client(base_url=running.url, timeout=30) as client:
            assert client.get("/healthz", headers={"X-Request-ID": "log-probe"}).status_code == 200
            assert client.post("/v1/detect", files=parts(frame), headers={"X-Request-ID": "log-ok"}).status_code == 200
        time.sleep(0.2)
    lines = running.lines()
    stamp = r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z"
    (probe,) = [line for line in lines if "log-probe" in line]
    assert re.match(rf"{stamp} DEBUG service\.access: request log-probe: GET /healthz answered 200 in \d+ ms "
                    r"\(client 127\.0\.0\.1:\d+\)$", probe), probe
    (ok,) = [line for line in lines if "log-ok" in line]
    assert re.match(rf"{stamp} INFO service\.access: request log-ok: POST /v1/detect answered 200 in \d+ ms "
                    r"\(client 127\.0\.0\.1:\d+; model [0-9a-f]{12}\)$", ok), ok
    assert not [line for line in lines if "uvicorn.access" in line]
    assert any(" DEBUG " in line for line in lines if "log-probe" not in line)  # the libraries' debug lines too


def test_log_level_warning_applies_to_uvicorn_too(tiny_models: Path, frame: dict[str, bytes],  # noqa: F811
                                                  tmp_path: Path) -> None:
    with service(tiny_models, tmp_path / "service.log", "--log-level", "warning", "--log-format", "json") as running:
        assert httpx.post(f"{running.url}/v1/detect", files=parts(frame, points=b"123"), timeout=30).status_code == 422
        running.process.send_signal(signal.SIGTERM)
        running.process.wait(20)
    records = running.records()
    assert records and {r["level"] for r in records} == {"WARNING"}, records  # the untrained weights' warning
    assert not [r for r in records if r["logger"].startswith("uvicorn")]


# --------------------------------------------------------------------------- units
def test_access_levels_say_whose_fault() -> None:
    assert access_level(200, quiet=False) == logging.INFO
    assert access_level(422, quiet=False) == logging.INFO  # the client's mistake
    assert access_level(499, quiet=False) == logging.INFO
    assert access_level(503, quiet=False) == access_level(504, quiet=False) == logging.WARNING
    assert access_level(500, quiet=False) == access_level(500, quiet=True) == logging.ERROR
    assert access_level(200, quiet=True) == access_level(503, quiet=True) == logging.DEBUG


def test_request_target_is_one_bounded_line() -> None:
    assert request_target({"raw_path": b"/v1/detect", "query_string": b"format=kitti"}) == "/v1/detect?format=kitti"
    # Without raw_path (an ASGI server that does not give it) the decoded path: its control characters escaped.
    assert request_target({"path": "/a\nb\x1b[31m", "query_string": b""}) == "/a\\x0ab\\x1b[31m"
    long = request_target({"raw_path": b"/" + b"p" * 5000, "query_string": b""})
    assert len(long) == 203 and long.endswith("...")
    longest = "/" + "p" * 199  # 200 characters: shown whole, no "..." for what was not cut
    assert request_target({"raw_path": longest.encode(), "query_string": b""}) == longest


def test_client_addresses_name_host_and_port_ipv6_in_brackets() -> None:
    """``[::1]:8000``, as in a URL: an IPv6 address's own colons would otherwise run into the port's."""
    assert client_address({"client": ("192.168.1.20", 51000)}) == "192.168.1.20:51000"
    assert client_address({"client": ("::1", 51000)}) == "[::1]:51000"
    assert client_address({"client": None}) is None and client_address({}) is None


def test_a_400_names_its_error_code_in_the_access_line(
    tiny_models: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Every refusal's code is in its access line (``error_code``), the lowest status of the 4xx too."""
    boundary = "lowres3dboundary"
    with in_process_service(tiny_models) as app_client, caplog.at_level(logging.INFO, logger="service.access"):
        response = app_client.post("/v1/detect", content=b"",
                                   headers={"content-type": f"multipart/form-data; boundary={boundary}"})
        assert response.status_code == 400, response.text
    (line,) = [r for r in caplog.records if r.name == "service.access" and getattr(r, "status", None) == 400]
    assert line.error_code == "bad_request" and " 400 bad_request " in line.getMessage()  # type: ignore[attr-defined]


def test_formatters_write_utc_and_one_line_per_record() -> None:
    try:
        raise RuntimeError("boom\nsecond line")
    except RuntimeError:
        record = logging.LogRecord("service.middleware", logging.ERROR, __file__, 1, "internal error on %s", ("x",),
                                   sys.exc_info())
    record.created = 0.0
    record.request_id = "r-1"
    event = json.loads(JsonFormatter().format(record))
    assert len(JsonFormatter().format(record).splitlines()) == 1
    assert event["timestamp"] == "1970-01-01T00:00:00.000Z" == utc_timestamp(0.0)
    assert (event["level"], event["logger"], event["message"], event["request_id"]) == (
        "ERROR", "service.middleware", "internal error on x", "r-1")
    assert "RuntimeError: boom" in event["exception"] and "Traceback" in event["exception"]
    assert TextFormatter().format(record).startswith("1970-01-01T00:00:00.000Z ERROR service.middleware: internal")
