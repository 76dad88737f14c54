"""The detection service as a real process: ``python -m service`` under uvicorn on 127.0.0.1.

Covers what only a real server shows: HTTP over a socket (chunked uploads,
Content-Length), the OpenAPI schema fuzzed by schemathesis, SIGTERM letting
in-flight requests finish (and answering those it cuts off, and ending a long
warm-up), and bad start configurations (a corrupted or unreadable model
directory, an address in use, empty or misspelt settings) stopping the start
with one line. Every server listens on a port it chose itself (--port 0: a port
picked free here and handed over could be taken meanwhile by another xdist
worker's server), has a bounded start-up time, and is killed in teardown.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import pytest
import schemathesis
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis.errors import Unsatisfiable
from schemathesis.generation import GenerationMode

from benchmarks.load import listening_port
from pipeline.beams import emulate_beams
from tests.test_service import assert_error, frame, parts, tiny_models  # noqa: F401 - fixtures

REPO = Path(__file__).resolve().parents[1]
START_TIMEOUT_S = 30.0


@dataclass
class Server:
    """A running ``python -m service`` process."""

    url: str
    process: subprocess.Popen
    log_path: Path

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")


def _stop(process: subprocess.Popen) -> None:
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(5)


@contextmanager
def running_service(models: Path, log_path: Path, *args: str, until: str = "/readyz",
                    env: dict[str, str] | None = None) -> Iterator[Server]:
    """Start the service on a port of its choosing (with ``env`` added to this environment's, its LOWRES3D_*
    variables left out), wait until ``until`` answers 200, stop it (SIGTERM, then SIGKILL) afterwards."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("LOWRES3D_")} | (env or {})
    with open(log_path, "w") as log_file:
        process = subprocess.Popen(
            [sys.executable, "-m", "service", "--models", str(models), "--port", "0", *args],
            cwd=REPO, env=env, stdout=log_file, stderr=subprocess.STDOUT,
        )
    server = Server("", process, log_path)
    try:
        deadline = time.monotonic() + START_TIMEOUT_S
        while True:
            if process.poll() is not None:
                pytest.fail(f"the service exited with {process.returncode} during start:\n{server.log()}")
            if not server.url and (port := listening_port(process.pid)) is not None:
                server.url = f"http://127.0.0.1:{port}"
            try:
                if server.url and httpx.get(f"{server.url}{until}", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                pytest.fail(f"the service was not ready within {START_TIMEOUT_S} s:\n{server.log()}")
            time.sleep(0.1)
        yield server
    finally:
        _stop(process)


@pytest.fixture(scope="module")
def server(tiny_models: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:  # noqa: F811
    """One server for the contract and fuzz tests; a 3 MB body limit (the frame is 2.5 MB)."""
    log_path = tmp_path_factory.mktemp("server") / "service.log"
    with running_service(tiny_models, log_path, "--max-body-bytes", "3000000") as running:
        yield running


# --------------------------------------------------------------------------- contract over a socket
def test_contract_over_http(server: Server, frame: dict[str, bytes]) -> None:  # noqa: F811
    with httpx.Client(base_url=server.url, timeout=30) as client:
        body = client.post("/v1/detect", params={"emulate_beams": 16}, files=parts(frame)).json()
        assert body["model"]["preset"] == "tiny" and "emulate_beams" in body["timings_ms"]
        kitti = client.post("/v1/detect", params={"format": "kitti", "score_threshold": 0}, files=parts(frame))
        assert kitti.status_code == 200 and len(kitti.text.splitlines()[0].split()) == 16
        png = client.post("/v1/detect/bev.png", files=parts(frame))
        assert png.status_code == 200 and png.content.startswith(b"\x89PNG")
        assert_error(client.post("/v1/detect", json={}), 415, "unsupported_media_type")
        assert_error(client.post("/v1/detect", files=parts(frame, points=b"1234")), 422, "invalid_input", "points")
        singular = re.sub(rb"P2:[^\n]*", b"P2: " + b" ".join([b"0"] * 12), frame["calib"])
        assert_error(client.post("/v1/detect", files=parts(frame, calib=singular)), 422, "invalid_input", "P2")
        thinned = emulate_beams(np.frombuffer(frame["points"], np.float32).reshape(-1, 4), 16).tobytes()
        assert_error(client.post("/v1/detect", params={"emulate_beams": 16}, files=parts(frame, points=thinned)),
                     422, "invalid_input", "16 rings, not 64")
        typo = client.post("/v1/detect?emulate_beam=16&foo=bar", files=parts(frame))
        assert_error(typo, 422, "invalid_input", "emulate_beam", "did you mean emulate_beams?", "foo")
        assert client.get("/v2/health/live").json() == {"live": True}
        info = client.get("/v1/model").json()
        assert info["providers_in_use"]["pixor"] == ["CPUExecutionProvider"]
        metrics = client.get("/metrics").text
        assert 'lowres3d_http_requests_total{method="POST",route="/v1/detect",status="200"} 2.0' in metrics
        assert re.search(r"^process_resident_memory_bytes \d", metrics, re.MULTILINE)


def test_body_limit_over_http(server: Server, frame: dict[str, bytes]) -> None:  # noqa: F811
    big = parts(frame, points=frame["points"] * 2)  # 4.3 MB
    with httpx.Client(base_url=server.url, timeout=30) as client:
        assert_error(client.post("/v1/detect", files=big), 413, "body_too_large", "3000000 bytes")
        boundary = "b0undary"
        head = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"points\"; filename=\"p.bin\"\r\n"
                "Content-Type: application/octet-stream\r\n\r\n").encode()

        def chunked() -> Iterator[bytes]:  # no Content-Length: Transfer-Encoding: chunked
            yield head
            for _ in range(64):
                yield b"\x00" * 65536

        response = client.post(
            "/v1/detect", content=chunked(), headers={"content-type": f"multipart/form-data; boundary={boundary}"}
        )
        assert_error(response, 413, "body_too_large")
    # The server is still healthy afterwards, and the 413s, answered before routing, count under their route.
    assert httpx.get(f"{server.url}/readyz", timeout=5).status_code == 200
    metrics = httpx.get(f"{server.url}/metrics", timeout=5).text
    assert 'lowres3d_http_requests_total{method="POST",route="/v1/detect",status="413"} 2.0' in metrics


def test_probes_answer_head_over_http(server: Server) -> None:
    """Load balancers and uptime checkers often probe with HEAD: same status as GET, no body."""
    for path in ("/healthz", "/readyz", "/v2/health/live", "/v2/health/ready"):
        response = httpx.head(f"{server.url}{path}", timeout=5)
        assert response.status_code == 200 and response.content == b"", path
    assert httpx.head(f"{server.url}/v1/detect", timeout=5).status_code == 405


def test_cut_off_upload_over_http(server: Server, frame: dict[str, bytes]) -> None:  # noqa: F811
    """A chunked upload whose close delimiter arrives split over chunks is whole; one that stops inside its
    last part (the calib) is a 400, not a silent loss of that part."""
    request = httpx.Request("POST", f"{server.url}/v1/detect", files=parts(frame))
    body, headers = request.read(), {"content-type": request.headers["content-type"]}

    def chunks(data: bytes) -> Iterator[bytes]:  # no Content-Length: Transfer-Encoding: chunked
        head = data[:-20]
        yield from (head[start : start + 65536] for start in range(0, len(head), 65536))
        yield from (data[-20:-9], data[-9:])  # the close delimiter (--boundary--\r\n) split over two chunks

    with httpx.Client(base_url=server.url, timeout=30) as client:
        whole = client.post("/v1/detect", content=chunks(body), headers=headers)
        assert whole.status_code == 200, whole.text
        cut = client.post("/v1/detect", content=chunks(body[:-60]), headers=headers)
        assert_error(cut, 400, "bad_request", "ended before its closing boundary")


def _raw_request(server: Server, head: str, body: bytes = b"") -> socket.socket:
    """A connection to the server that has sent ``head`` (CRLF line ends added) and ``body``, and no more."""
    host, port = server.url.removeprefix("http://").split(":")
    sock = socket.create_connection((host, int(port)), timeout=10)
    sock.sendall(head.replace("\n", "\r\n").encode("latin-1") + body)
    return sock


def _answer(sock: socket.socket, timeout_s: float, whole: bool = False) -> tuple[int | None, dict[str, str], bytes, bool]:
    """What the server sent on ``sock`` until it closed it (or, ``whole``, until an answer with a Content-Length
    was all in) or ``timeout_s`` passed: (status or None, headers, body, whether it closed the connection)."""
    sock.settimeout(timeout_s)
    data, closed = b"", False
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline and not (whole and _complete(data)):
            chunk = sock.recv(65536)
            if not chunk:
                closed = True
                break
            data += chunk
    except (TimeoutError, ConnectionResetError):
        pass
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    status = int(lines[0].split()[1]) if data else None
    headers = {name.lower(): value for name, _, value in (line.partition(": ") for line in lines[1:]) if value}
    return status, headers, body, closed


def _complete(data: bytes) -> bool:
    """Whether ``data`` holds an answer's whole head and all of the body its Content-Length announces."""
    head, found, body = data.partition(b"\r\n\r\n")
    length = re.search(rb"(?im)^content-length: *(\d+)", head)
    return bool(found and length and len(body) >= int(length.group(1)))


def test_request_log_names_each_refused_request_and_not_the_noise_clients_cause(
    server: Server, frame: dict[str, bytes]  # noqa: F811
) -> None:
    """At info level every answer that is not 2xx has one log line with its request id, status and error code;
    what any client can make the libraries warn about (a malformed request, an Upgrade, a malformed multipart
    body) is not in the log at all, where a bad client used to flood it."""
    with httpx.Client(base_url=server.url, timeout=30) as client:
        assert client.get("/no-such-route", headers={"X-Request-ID": "log-404"}).status_code == 404
        typo = client.post("/v1/detect?emulate_beam=16", files=parts(frame), headers={"X-Request-ID": "log-422"})
        assert typo.status_code == 422
        boundary = "b0undary"
        broken = client.post("/v1/detect", headers={"X-Request-ID": "log-400",
                                                    "content-type": f"multipart/form-data; boundary={boundary}"},
                             content=f"--{boundary}\r\nBad Header: x\r\n\r\ndata\r\n--{boundary}--\r\n".encode())
        assert broken.status_code == 400
        assert client.get("/healthz", headers={"X-Request-ID": "log-200"}).status_code == 200
    upgrade = ("GET /healthz HTTP/1.1\nHost: x\nConnection: Upgrade\nUpgrade: websocket\n"
               "Sec-WebSocket-Version: 13\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\n\n")
    for head in ("GARBAGE\n\n", upgrade):
        with _raw_request(server, head) as sock:
            assert _answer(sock, 5)[0] in (400, 200)
    # Each access line is written once its answer has gone out, maybe after the client has read it: wait for them.
    _wait_for(lambda: all(f"request log-{status}: " in server.log() for status in (404, 422, 400)),
              "an access line of log-404, log-422 or log-400 is missing")
    log = server.log()
    assert re.search(r"INFO service.access: request log-404: GET unmatched answered 404 not_found in \d+ ms", log)
    assert "request log-422: POST /v1/detect answered 422 invalid_input in " in log
    assert "request log-400: POST /v1/detect answered 400 bad_request in " in log
    assert "log-200" not in log  # a probe's access line is DEBUG
    for noise in ("Invalid HTTP request received", "Unsupported upgrade request", "WebSocket library",
                  "python_multipart", "Found invalid character"):
        assert noise not in log, noise


# --------------------------------------------------------------------------- a guarded server
GUARD_TOKEN = "guard-token"
RECEIVE_TIMEOUT_S = 2.0
AUTH = f"Authorization: Bearer {GUARD_TOKEN}\n"


@pytest.fixture(scope="module")
def guarded(tiny_models: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:  # noqa: F811
    """A server with a token, one worker and a queue of one (two places), and a receive timeout of 2 s: its
    connection limit is 1 + 1 + 16 = 18."""
    log_path = tmp_path_factory.mktemp("guarded") / "service.log"
    args = ("--workers", "1", "--queue-size", "1", "--receive-timeout-s", str(RECEIVE_TIMEOUT_S),
            "--token", GUARD_TOKEN, "--max-body-bytes", "40000000")
    with running_service(tiny_models, log_path, *args) as running:
        yield running


def _metric(server: Server, line_start: str) -> float:
    """The value of the first /metrics sample line starting with ``line_start`` (0 when there is none)."""
    for line in httpx.get(f"{server.url}/metrics", timeout=5).text.splitlines():
        if line.startswith(line_start):
            return float(line.rsplit(" ", 1)[1])
    return 0.0


def _wait_for(condition: object, what: str, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():  # type: ignore[operator]
        assert time.monotonic() < deadline, what
        time.sleep(0.01)


def test_a_stalled_request_head_is_answered_408_and_its_connection_closed(guarded: Server) -> None:
    """A client that sends half a request head, or nothing, no longer holds its connection for ever: after
    --receive-timeout-s the first is answered 408 request_timeout (JSON) and each is closed."""
    half = _raw_request(guarded, "POST /v1/detect HTTP/1.1\nHost: x\n")
    silent = _raw_request(guarded, "")
    tic = time.monotonic()
    with half, silent:
        status, headers, body, closed = _answer(half, RECEIVE_TIMEOUT_S + 5)
        took = time.monotonic() - tic
        assert (status, closed) == (408, True), (status, body)
        error = json.loads(body)["error"]
        assert error["code"] == "request_timeout" and "request head: not received within 2 s" in error["message"]
        assert headers["x-request-id"] == error["request_id"] and headers["connection"] == "close"
        assert RECEIVE_TIMEOUT_S - 0.2 < took < RECEIVE_TIMEOUT_S + 3, took
        assert _answer(silent, 3) == (None, {}, b"", True)  # nothing asked, nothing answered: closed
    assert (f"request {error['request_id']}: POST unparsed answered 408 request_timeout in " in guarded.log()
            and "its head not received within 2 s, --receive-timeout-s" in guarded.log())


STALLED_HEAD = ("POST /v1/detect HTTP/1.1\nHost: x\nContent-Type: multipart/form-data; boundary=b\n"
                f"Content-Length: 10000000\n{AUTH}\n")


def _hold_the_places(guarded: Server) -> list[socket.socket]:
    """Two uploads that stall after 1 kB of their 10 MB, holding both places of the guarded server's pool until
    --receive-timeout-s (the caller closes them)."""
    part = b'--b\r\nContent-Disposition: form-data; name="points"; filename="p.bin"\r\n\r\n' + b"\0" * 1000
    stalled = [_raw_request(guarded, STALLED_HEAD, part) for _ in range(2)]
    _wait_for(lambda: _metric(guarded, "lowres3d_inference_queue_depth") == 2.0, "the uploads took no place")
    return stalled


def test_the_pool_refuses_before_the_body_and_a_stalled_body_is_408(
    guarded: Server, frame: dict[str, bytes]  # noqa: F811
) -> None:
    """Each upload takes its place in the pool before its body is read: with both places held by uploads that
    stall, a third request is answered 503 overloaded without sending a byte of its 10 MB; the stalled ones
    are answered 408 after --receive-timeout-s and give their places back, and the next frame is answered."""
    stalled = _hold_the_places(guarded)
    try:
        with _raw_request(guarded, STALLED_HEAD) as third:
            status, headers, body, closed = _answer(third, 5)
        assert (status, closed) == (503, True), body
        assert json.loads(body)["error"]["code"] == "overloaded" and int(headers["retry-after"]) >= 1
        for sock in stalled:
            status, _, body, closed = _answer(sock, RECEIVE_TIMEOUT_S + 5)
            assert (status, closed) == (408, True), body
            assert "request body: not received within 2 s" in json.loads(body)["error"]["message"]
    finally:
        for sock in stalled:
            sock.close()
    _wait_for(lambda: _metric(guarded, "lowres3d_inference_queue_depth") == 0.0, "the places were not given back")
    response = httpx.post(f"{guarded.url}/v1/detect", files=parts(frame), timeout=30,
                          headers={"Authorization": f"Bearer {GUARD_TOKEN}"})
    assert response.status_code == 200, response.text


def test_without_the_token_the_answer_comes_before_the_body(guarded: Server) -> None:
    """A 30 MB upload without the token is answered 401 at once, not after the server has read and parsed it;
    the connection closes once the rest of the body has been waited for at most --receive-timeout-s (2 s)."""
    head = "POST /v1/detect HTTP/1.1\nHost: x\nContent-Type: multipart/form-data; boundary=b\nContent-Length: 30000000\n\n"
    tic = time.monotonic()
    with _raw_request(guarded, head, b"--b\r\n") as sock:
        status, headers, body, _ = _answer(sock, 5, whole=True)
        answered = time.monotonic() - tic
        closed = _answer(sock, RECEIVE_TIMEOUT_S + 3)[3]
        lingered = time.monotonic() - tic
    assert (status, closed) == (401, True), body
    assert answered < 1.0 and RECEIVE_TIMEOUT_S - 0.2 < lingered < RECEIVE_TIMEOUT_S + 1.5, (answered, lingered)
    assert json.loads(body)["error"]["code"] == "unauthorized"
    assert headers["www-authenticate"] == 'Bearer realm="lowres3d"'


async def _post_at_once(url: str, frame: dict[str, bytes], headers: list[dict[str, str]]) -> list[httpx.Response | str]:  # noqa: F811
    """POST the frame once per item of ``headers``, all at once, from an httpx.AsyncClient (which sends a whole
    request before it reads its answer): each answer, or the name of the transport error in its place."""
    async def post(client: httpx.AsyncClient, sent: dict[str, str]) -> httpx.Response | str:
        try:
            return await client.post("/v1/detect", files=parts(frame), headers=sent)
        except httpx.TransportError as exc:
            return type(exc).__name__

    async with httpx.AsyncClient(base_url=url, timeout=30, limits=httpx.Limits(max_connections=len(headers))) as client:
        return list(await asyncio.gather(*(post(client, sent) for sent in headers)))


def test_refused_uploads_sent_whole_get_their_answer_not_a_reset(
    guarded: Server, frame: dict[str, bytes]  # noqa: F811
) -> None:
    """A client that sends its whole upload before it reads gets the 503 overloaded (and the 401) answered
    before the body was read, not a connection reset: the server reads and drops the body before it closes
    the connection (closed with the upload unread, the kernel reset it, and httpx raised ReadError). Three
    bursts (a burst sometimes got all its answers before); the counts and access lines are the 503's and 401's."""
    counted = 'lowres3d_http_requests_total{method="POST",route="/v1/detect",status='
    before = {status: _metric(guarded, f'{counted}"{status}"}}') for status in (401, 503)}
    rejected = _metric(guarded, 'lowres3d_inference_rejected_total{reason="queue_full"}')
    token, wrong = f"Bearer {GUARD_TOKEN}", "Bearer wrong"
    bursts = [[{"Authorization": token if i < 6 else wrong, "X-Request-ID": f"whole-{burst}-{i}"} for i in range(8)]
              for burst in range(3)]
    stalled = _hold_the_places(guarded)
    try:
        answers = [asyncio.run(_post_at_once(guarded.url, frame, headers)) for headers in bursts]
    finally:
        for sock in stalled:
            sock.close()
    got = [answer if isinstance(answer, str) else answer.status_code for burst in answers for answer in burst]
    assert got == [503] * 6 + [401] * 2 + [503] * 6 + [401] * 2 + [503] * 6 + [401] * 2, got
    for headers, burst in zip(bursts, answers):
        for sent, answer in zip(headers, burst):
            assert isinstance(answer, httpx.Response)
            error = assert_error(answer, answer.status_code, "overloaded" if answer.status_code == 503 else "unauthorized")
            assert error["request_id"] == sent["X-Request-ID"] and answer.headers["connection"] == "close"
    assert _metric(guarded, f'{counted}"503"}}') == before[503] + 18
    assert _metric(guarded, f'{counted}"401"}}') == before[401] + 6
    assert _metric(guarded, 'lowres3d_inference_rejected_total{reason="queue_full"}') == rejected + 18
    _wait_for(lambda: "request whole-2-7: " in guarded.log(), "the last access line is missing")
    assert "request whole-0-0: POST /v1/detect answered 503 overloaded in " in guarded.log()
    assert "request whole-2-7: POST /v1/detect answered 401 unauthorized in " in guarded.log()
    _wait_for(lambda: _metric(guarded, "lowres3d_inference_queue_depth") == 0.0, "the places were not given back")


def test_a_refused_client_waiting_for_100_continue_is_answered_at_once(guarded: Server) -> None:
    """A client that sends ``Expect: 100-continue`` (curl, for a large upload) has not sent its body, and will
    not once answered: it gets its 401 (no ``100 Continue``) and its connection is closed at once, its body not
    waited for."""
    head = ("POST /v1/detect HTTP/1.1\nHost: x\nContent-Type: multipart/form-data; boundary=b\n"
            "Content-Length: 5000000\nExpect: 100-continue\n\n")
    tic = time.monotonic()
    with _raw_request(guarded, head) as sock:
        status, _, body, closed = _answer(sock, 5)
    assert (status, closed) == (401, True), body
    assert time.monotonic() - tic < 1.0  # not the lingering close's 2 s
    assert json.loads(body)["error"]["code"] == "unauthorized"


def test_requests_over_the_limit_are_refused_but_probes_answered(guarded: Server) -> None:
    """With as many requests in progress as the limit (workers + queue + 16 = 18; here uploads refused 401 whose
    bodies the service waits for, up to 2 s), a request is answered 503 overloaded before its body is read, and
    its connection closed; the probes and /metrics are still answered. Once they end, requests are served again.
    (Idle sockets do not count: tests/test_service_connections_s49.py.)"""
    upload = "POST /v1/detect HTTP/1.1\nHost: x\nContent-Type: multipart/form-data; boundary=b\n"
    held = [_raw_request(guarded, upload + "Content-Length: 5000000\n\n") for _ in range(18)]
    try:
        for sock in held:  # each refused at once, then lingering for the body never sent: in progress
            assert _answer(sock, 5, whole=True)[0] == 401
        with _raw_request(guarded, upload + AUTH + "Content-Length: 5000000\n\n") as sock:
            # The answer comes at once; the connection closes when the 5 MB never sent has been waited for (2 s),
            # and by then the held requests have ended: check the others first.
            status, headers, body, _ = _answer(sock, 5, whole=True)
            assert status == 503, body
            error = json.loads(body)["error"]
            assert error["code"] == "overloaded" and "requests: more than the limit of 18 in progress" in error["message"]
            assert headers["retry-after"] == "1"
            for path in ("/healthz", "/readyz", "/metrics"):
                assert httpx.get(f"{guarded.url}{path}", timeout=5).status_code == 200, path
            model = httpx.get(f"{guarded.url}/v1/model", timeout=5, headers={"Authorization": f"Bearer {GUARD_TOKEN}"})
            assert model.status_code == 503
            assert _answer(sock, RECEIVE_TIMEOUT_S + 3)[3], "the connection was not closed"
    finally:
        for sock in held:
            sock.close()
    _wait_for(lambda: httpx.get(f"{guarded.url}/v1/model", timeout=5,
                                headers={"Authorization": f"Bearer {GUARD_TOKEN}"}).status_code == 200,
              "requests were not served again")


def test_a_client_that_leaves_stops_its_frame_and_counts_499(guarded: Server, frame: dict[str, bytes]) -> None:  # noqa: F811
    """A client that closes its connection while its frame runs (thinning 880k points, half a second) stops
    the frame on its worker; the request is counted 499, not 200."""
    request = httpx.Request("POST", f"{guarded.url}/v1/detect?emulate_beams=16",
                            files=parts(frame, points=frame["points"] * 8))
    body = request.read()
    head = (f"POST /v1/detect?emulate_beams=16 HTTP/1.1\nHost: x\nContent-Type: {request.headers['content-type']}\n"
            f"Content-Length: {len(body)}\n{AUTH}X-Request-ID: leaves-1\n\n")
    counted = 'lowres3d_http_requests_total{method="POST",route="/v1/detect",status='
    stopped, answered = _metric(guarded, "lowres3d_inference_stopped_total"), _metric(guarded, counted + '"200"}')
    left = _metric(guarded, counted + '"499"}')  # other tests' clients may have left too
    with _raw_request(guarded, head, body):
        _wait_for(lambda: _metric(guarded, "lowres3d_inference_in_flight") == 1.0, "the frame did not start")
    _wait_for(lambda: _metric(guarded, "lowres3d_inference_stopped_total") == stopped + 1, "the frame was not stopped")
    _wait_for(lambda: _metric(guarded, "lowres3d_inference_in_flight") == 0.0, "the worker was not freed")
    assert _metric(guarded, counted + '"499"}') == left + 1
    assert _metric(guarded, counted + '"200"}') == answered
    log = guarded.log()
    assert "request leaves-1: POST /v1/detect client disconnected before its answer 499" in log
    assert "request leaves-1: its frame stopped on its worker" in log


# --------------------------------------------------------------------------- schemathesis
FUZZ_EXAMPLES = 12  # per operation and generation mode: 8 operations × 2 modes × 12 ≈ 200 requests


def test_openapi_fuzz_has_no_server_errors(server: Server) -> None:
    """Schema-generated requests, valid and invalid, never get a 5xx; answers match the schema (status
    codes, bodies, headers, content types), and schema-invalid requests are rejected."""
    api = schemathesis.openapi.from_url(f"{server.url}/openapi.json")
    operations = [result.ok() for result in api.get_all_operations()]
    assert {op.label for op in operations} >= {"POST /v1/detect", "POST /v1/detect/bev.png", "GET /readyz"}
    for operation in operations:
        for mode in (GenerationMode.POSITIVE, GenerationMode.NEGATIVE):

            @given(case=operation.as_strategy(generation_mode=mode))
            @settings(max_examples=FUZZ_EXAMPLES, deadline=None, database=None, derandomize=True,
                      phases=[Phase.explicit, Phase.generate], suppress_health_check=list(HealthCheck))
            def check(case: schemathesis.Case) -> None:
                # Every default check except positive_data_acceptance: a schema cannot say "a valid PNG",
                # so schema-valid random bytes rightly get a 4xx naming the part.
                case.call_and_validate(timeout=30, excluded_checks=[schemathesis.checks.positive_data_acceptance])

            try:
                check()
            except Unsatisfiable:
                # A route without parameters or body has no invalid request to generate.
                assert mode is GenerationMode.NEGATIVE, operation.label


# --------------------------------------------------------------------------- lifecycle
def test_sigterm_lets_in_flight_requests_finish(
    tiny_models: Path, frame: dict[str, bytes], tmp_path: Path  # noqa: F811
) -> None:
    heavy = parts(frame, points=frame["points"] * 6)  # 660k points: each frame takes a while on one worker
    with running_service(tiny_models, tmp_path / "service.log", "--workers", "1", "--queue-size", "4") as running:
        with ThreadPoolExecutor(3) as clients:
            futures = [clients.submit(httpx.post, f"{running.url}/v1/detect", files=heavy, timeout=60) for _ in range(3)]
            # A frame on the worker and every request in the service (its place in the pool, taken once its head
            # is read; or answered): a request still connecting when SIGTERM comes is not in flight, nor let in.
            def all_in() -> bool:
                waiting, on_a_worker = _pool_state(running)
                return on_a_worker == 1 and waiting + on_a_worker + sum(f.done() for f in futures) == len(futures)

            _wait_for(all_in, "the three frames did not get in flight", 20)
            running.process.send_signal(signal.SIGTERM)
            responses = [f.result() for f in futures]
        assert [r.status_code for r in responses] == [200, 200, 200], [r.text for r in responses]
        # uvicorn re-raises the captured SIGTERM after its graceful shutdown: the conventional status.
        assert running.process.wait(30) in (0, -signal.SIGTERM)
        log = running.log()
        assert "Shutting down" in log and "inference pool stopped" in log and "Application shutdown complete" in log
        with pytest.raises(httpx.TransportError):
            httpx.get(f"{running.url}/healthz", timeout=2)


def _log_time(log: str, text: str) -> float:
    """Seconds (since midnight, UTC) of the first log line holding ``text`` (the text format of service/logs.py)."""
    match = re.search(rf"^\d{{4}}-\d\d-\d\dT(\d+):(\d+):(\d+)\.(\d+)Z .*{re.escape(text)}", log, re.MULTILINE)
    assert match, f"no log line with {text!r}:\n{log}"
    hours, minutes, seconds, millis = (int(group) for group in match.groups())
    return hours * 3600 + minutes * 60 + seconds + millis / 1000


def _pool_state(server: Server) -> tuple[float, float]:
    """(frames waiting for a worker, frames on one), from the server's /metrics."""
    text = httpx.get(f"{server.url}/metrics", timeout=5).text
    return tuple(float(re.search(rf"^lowres3d_inference_{name} (\S+)$", text, re.MULTILINE).group(1))
                 for name in ("queue_depth", "in_flight"))  # type: ignore[return-value]


def test_requests_cut_off_by_the_shutdown_get_a_json_503(frame: dict[str, bytes], tmp_path: Path) -> None:  # noqa: F811
    """When --shutdown-timeout-s runs out uvicorn cancels the requests still running: each gets the service's 503
    shutting_down with its request id (not uvicorn's plain-text 500), the log a line each and no traceback; and
    the grace lasts the fraction of a second given (int(0.3) was none at all)."""
    # The shipped models with mirror TTA on one worker (0.15–0.3 s a frame here): twelve frames queue up for
    # seconds, far beyond the grace.
    args = ("--workers", "1", "--queue-size", "11", "--mirror-tta", "--shutdown-timeout-s", "0.3")
    with running_service(REPO / "weights" / "edge", tmp_path / "service.log", *args) as running:
        with ThreadPoolExecutor(12) as clients:
            futures = [clients.submit(httpx.post, f"{running.url}/v1/detect", params={"emulate_beams": 16},
                                      files=parts(frame), timeout=60, headers={"X-Request-ID": f"cut-{i}"})
                       for i in range(12)]
            deadline = time.monotonic() + 30
            while True:  # over a second of work waiting (more than the grace lets finish), and every upload in:
                waiting, on_a_worker = _pool_state(running)  # a request cut off in its upload can see a reset
                if waiting >= 8 and waiting + on_a_worker + sum(f.done() for f in futures) == len(futures):
                    break
                assert time.monotonic() < deadline, "the frames did not queue up"
                time.sleep(0.01)
            running.process.send_signal(signal.SIGTERM)
            responses = [f.result() for f in futures]
        assert running.process.wait(30) in (0, -signal.SIGTERM)
        log = running.log()
    statuses = [r.status_code for r in responses]
    assert set(statuses) <= {200, 503} and 503 in statuses, statuses
    for response in responses:
        if response.status_code == 503:
            error = assert_error(response, 503, "shutting_down", "shut down before this request finished")
            assert error["request_id"].startswith("cut-") and response.headers["retry-after"] == "1"
            assert f"request {error['request_id']} (POST /v1/detect) cut off by the shutdown" in log
    assert "Traceback" not in log and "Exception in ASGI application" not in log, log
    assert "inference pool stopped" in log
    assert _log_time(log, "Cancel ") - _log_time(log, "Shutting down") >= 0.3


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_stop_while_the_models_load_ends_the_start(tmp_path: Path, signum: int) -> None:
    """SIGTERM or Ctrl-C while the models load stop the start there, in one line: Python has no SIGTERM handler
    of its own, and a container's first process ignores a signal without one, so a stop then used to be lost."""
    log_path = tmp_path / "service.log"
    env = {k: v for k, v in os.environ.items() if not k.startswith("LOWRES3D_")}
    with open(log_path, "w") as log_file:  # two session sets of the shipped models: a load of a second or so
        process = subprocess.Popen(
            [sys.executable, "-m", "service", "--models", str(REPO / "weights" / "edge"), "--port", "0",
             "--workers", "2", "--sessions", "per-worker"],
            cwd=REPO, env=env, stdout=log_file, stderr=subprocess.STDOUT,
        )
    try:
        deadline = time.monotonic() + START_TIMEOUT_S
        while "service.runtime: loading" not in log_path.read_text():
            assert process.poll() is None and time.monotonic() < deadline, log_path.read_text()
            time.sleep(0.01)
        process.send_signal(signum)
        code = process.wait(30)
    finally:
        _stop(process)
    log = log_path.read_text()
    assert code == (130 if signum == signal.SIGINT else -signal.SIGTERM), log
    assert f"{signal.Signals(signum).name} before serving: stopped while loading the models; not started" in log
    assert "Uvicorn running" not in log and "Traceback" not in log


def test_ctrl_c_on_a_serving_service_ends_in_one_line_and_status_130(
    tiny_models: Path, tmp_path: Path  # noqa: F811
) -> None:
    """Ctrl-C on a ready service: the graceful shutdown, then one line saying so and exit status 130, as every
    command of the project promises; it used to end in a CancelledError → KeyboardInterrupt traceback (−2)."""
    with running_service(tiny_models, tmp_path / "service.log") as running:
        running.process.send_signal(signal.SIGINT)
        code = running.process.wait(30)
        log = running.log()
    assert code == 130, log
    assert log.strip().splitlines()[-1] == ("interrupted: the service has stopped; the requests in flight were let "
                                            "finish first (up to --shutdown-timeout-s)"), log
    assert "inference pool stopped" in log and "Traceback" not in log and "KeyboardInterrupt" not in log


def _catches(pid: int, signum: int) -> bool:
    """Whether process ``pid`` has a handler of its own for ``signum`` (Linux: SigCgt in /proc/PID/status)."""
    status = Path(f"/proc/{pid}/status").read_text()
    caught = int(re.search(r"^SigCgt:\s+([0-9a-f]+)$", status, re.MULTILINE).group(1), 16)  # type: ignore[union-attr]
    return bool(caught >> (signum - 1) & 1)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_sigterm_right_after_the_start_stops_it_even_as_a_containers_first_process(
    tiny_models: Path, tmp_path: Path  # noqa: F811
) -> None:
    """The first process of a container (no init) ignores a signal it has no handler for, as does a process
    started with SIGTERM ignored (how it is emulated here). The service's handler is in place before its imports
    (most of a second: a SIGTERM in them was lost, and the service went on to serve): before ONNX Runtime is
    even loaded. A SIGTERM then stops the start promptly, without serving."""
    log_path = tmp_path / "service.log"
    env = {k: v for k, v in os.environ.items() if not k.startswith("LOWRES3D_")}
    with open(log_path, "w") as log_file:
        process = subprocess.Popen(
            [sys.executable, "-m", "service", "--models", str(tiny_models), "--port", "0"],
            cwd=REPO, env=env, stdout=log_file, stderr=subprocess.STDOUT,
            preexec_fn=lambda: signal.signal(signal.SIGTERM, signal.SIG_IGN),  # noqa: PLW1509 - before exec
        )
    try:
        deadline = time.monotonic() + START_TIMEOUT_S
        while not _catches(process.pid, signal.SIGTERM):
            assert process.poll() is None and time.monotonic() < deadline, log_path.read_text()
            time.sleep(0.001)
        loaded = "onnxruntime" in Path(f"/proc/{process.pid}/maps").read_text()
        sent = time.monotonic()
        process.send_signal(signal.SIGTERM)
        code = process.wait(15)
        took = time.monotonic() - sent
    finally:
        _stop(process)
    log = log_path.read_text()
    assert not loaded, "SIGTERM was handled only once ONNX Runtime was loaded, late in the start"
    assert code == -signal.SIGTERM and took < 10, (code, took, log)
    assert "SIGTERM before serving: stopped while starting, before the models loaded; not started" in log, log
    assert "loading" not in log and "Uvicorn running" not in log and "Traceback" not in log


def test_sigterm_during_a_long_warm_up_stops_promptly(tmp_path: Path) -> None:
    """The warm-up stops at its next network node once the shutdown begins: a thousand runs of the shipped
    models (minutes) do not hold a SIGTERM up."""
    args = ("--workers", "1", "--warmup-runs", "1000", "--shutdown-timeout-s", "2")
    with running_service(REPO / "weights" / "edge", tmp_path / "service.log", *args, until="/healthz") as running:
        assert httpx.get(f"{running.url}/readyz", timeout=5).status_code == 503  # still warming up
        time.sleep(0.5)
        sent = time.monotonic()
        running.process.send_signal(signal.SIGTERM)
        try:
            code = running.process.wait(60)
        except subprocess.TimeoutExpired:
            pytest.fail(f"still running 60 s after SIGTERM:\n{running.log()}")
        took = time.monotonic() - sent
        log = running.log()
    assert code in (0, -signal.SIGTERM), log
    assert took < 10, f"{took:.1f} s to stop:\n{log}"
    assert "warm-up stopped: the service is shutting down" in log and ": ready" not in log
    assert "inference pool stopped" in log and "Traceback" not in log


def _start_fails(models: Path | None, *args: str, env: dict[str, str] | None = None) -> tuple[int, str]:
    """Run a start that must fail: its exit status and output. ``models`` None: no --models; --port 0 (any free
    port) unless ``args`` give one; ``env``: LOWRES3D_* variables (the test's own are left out)."""
    command = [sys.executable, "-m", "service", *(["--models", str(models)] if models is not None else []),
               *([] if "--port" in args else ["--port", "0"]), *args]
    environ = {k: v for k, v in os.environ.items() if not k.upper().startswith("LOWRES3D_")}
    result = subprocess.run(command, check=False, cwd=REPO, capture_output=True, text=True,
                            timeout=START_TIMEOUT_S, env=environ | (env or {}))
    return result.returncode, result.stdout + result.stderr


def test_corrupted_model_file_stops_the_start(tiny_models: Path, tmp_path: Path) -> None:  # noqa: F811
    corrupted = tmp_path / "models"
    shutil.copytree(tiny_models, corrupted)
    pixor = corrupted / "pixor.onnx"
    data = bytearray(pixor.read_bytes())
    data[len(data) // 2] ^= 0xFF
    pixor.write_bytes(bytes(data))
    code, output = _start_fails(corrupted)
    assert code == 2, output
    assert f"{pixor}: sha256 mismatch" in output and "re-export" in output
    assert "Traceback" not in output and "Uvicorn running" not in output


@pytest.mark.parametrize(
    ("args", "message"),
    [((), "model directory not found"),
     (("--workers", "0"), "--workers (LOWRES3D_WORKERS) 0: input should be greater than or equal to 1"),
     (("--port", "99999"), "--port (LOWRES3D_PORT) 99999: input should be less than or equal to 65535"),
     (("--provider", "tensorrt"), "tensorrt")],
    ids=["missing models", "bad setting", "bad port", "unavailable provider"],
)
def test_bad_start_configuration_exits_with_a_message(
    tiny_models: Path, tmp_path: Path, args: tuple[str, ...], message: str  # noqa: F811
) -> None:
    models = tmp_path / "nowhere" if not args else tiny_models
    code, output = _start_fails(models, *args)
    assert code == 2, output
    assert message in output and "Traceback" not in output


def test_without_models_outside_a_checkout_the_start_says_where_the_weights_are(tmp_path: Path) -> None:
    """After `pip install .` (not -e) the packages sit in site-packages and the default weights/edge beside
    them does not exist: the start names the way out instead of only "not found"."""
    site = tmp_path / "site-packages"
    for package in ("pipeline", "service"):
        shutil.copytree(REPO / package, site / package, ignore=shutil.ignore_patterns("__pycache__"))
    env = {k: v for k, v in os.environ.items() if not k.startswith("LOWRES3D_")} | {"PYTHONPATH": str(site)}
    result = subprocess.run([sys.executable, "-m", "service", "--port", "0"], check=False,
                            cwd=tmp_path, capture_output=True, text=True, timeout=START_TIMEOUT_S, env=env)
    assert result.returncode == 2, result.stderr
    assert f"{site / 'weights' / 'edge'}" in result.stderr and "exists only in a source checkout" in result.stderr
    assert "--models" in result.stderr and "LOWRES3D_MODELS" in result.stderr and "Traceback" not in result.stderr
    assert len(result.stderr.splitlines()) == 1, result.stderr  # the hint alone, not "not found" before it


@pytest.mark.parametrize("fault", ["a directory in its place", "a read error"])
def test_unreadable_model_file_stops_the_start_with_one_line(
    tiny_models: Path, tmp_path: Path, fault: str  # noqa: F811
) -> None:
    """The tests run as root, whom chmod 000 does not stop: a directory where the file should be, and a file
    whose reading fails for anyone (/proc/self/mem at offset 0, an address no process maps: EIO; the service
    and its tests run on Linux)."""
    models = tmp_path / "models"
    shutil.copytree(tiny_models, models)
    pixor = models / "pixor.onnx"
    pixor.unlink()
    if fault == "a directory in its place":
        pixor.mkdir()
        message = f"{pixor}: a directory, where the manifest lists a model file"
    else:
        pixor.symlink_to("/proc/self/mem")
        message = f"{pixor}: cannot read the model file (Input/output error)"
    code, output = _start_fails(models)
    assert code == 2, output
    assert message in output and "Traceback" not in output and "Uvicorn running" not in output
    assert [line for line in output.splitlines() if "ERROR" in line] == [output.strip().splitlines()[-1]]


@pytest.mark.parametrize(
    ("host", "message"),
    [("127.0.0.1", "--port {port} (LOWRES3D_PORT): address already in use on 127.0.0.1"),
     ("192.0.2.1", ("--host 192.0.2.1 (LOWRES3D_HOST): cannot assign requested address (not an address of "
                    "this machine)")),
     ("a..b", "--host a..b (LOWRES3D_HOST): cannot resolve it")],
    ids=["port in use", "address not here", "host name unusable"],
)
def test_an_unusable_address_stops_the_start_before_the_models_load(
    tiny_models: Path, host: str, message: str  # noqa: F811
) -> None:
    """One line naming --port or --host, exit status 2, and no model loaded or warmed up first. (192.0.2.1 is a
    documentation address no machine has; binding it sends nothing.)"""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        code, output = _start_fails(tiny_models, "--host", host, "--port", str(port))
    assert code == 2, output
    lines = output.strip().splitlines()
    assert len(lines) == 1 and f"ERROR service: cannot start: {message.format(port=port)}" in lines[0], output
    assert "Traceback" not in output and "loaded" not in output and "warm" not in output


@pytest.mark.parametrize(
    ("args", "env", "message"),
    [(("--token", ""), {}, "--token (LOWRES3D_TOKEN): empty; give a token"),
     ((), {"LOWRES3D_TOKEN": ""}, "--token (LOWRES3D_TOKEN): empty; give a token"),
     ((), {"LOWRES3D_MODELS": ""}, "--models (LOWRES3D_MODELS): empty; give a path"),
     ((), {"LOWRES3D_HOST": ""}, "--host (LOWRES3D_HOST): empty; give an address (an empty one would listen on")],
    ids=["--token ''", "LOWRES3D_TOKEN=", "LOWRES3D_MODELS=", "LOWRES3D_HOST="],
)
def test_an_empty_token_or_model_directory_is_refused_at_start(
    tiny_models: Path, args: tuple[str, ...], env: dict[str, str], message: str  # noqa: F811
) -> None:
    """An empty token would lock every /v1 route with 401; an empty model directory would be the current one; an
    empty host would listen on every interface (0.0.0.0 and ::)."""
    code, output = _start_fails(None if "LOWRES3D_MODELS" in env else tiny_models, *args, env=env)
    assert code == 2, output
    lines = output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"python -m service: {message}"), output


def test_a_misspelt_lowres3d_variable_is_named_at_start(tmp_path: Path) -> None:
    """pydantic-settings reads only its own variables: a typo gets a warning naming the closest setting."""
    code, output = _start_fails(tmp_path / "nowhere", env={"LOWRES3D_WORKER": "4"})
    assert code == 2, output  # no model directory: the start stops after the warning
    assert ("WARNING service: environment variable LOWRES3D_WORKER: not a setting, ignored "
            "(did you mean LOWRES3D_WORKERS?)") in output
