"""What the HTTP protocol layer (service/protocol.py) bounds on a real uvicorn on 127.0.0.1: requests in progress,
not idle sockets, count for the 503 ``overloaded`` limit; open sockets have a cap of their own; an answer the
client never reads is cut off at the send deadline; the connections closed without an answer are counted; a
request framed twice (Content-Length and chunked) ends its connection; and a malformed chunk's answer and access
line name one request id. Every connection count and wait here is small (tens of sockets, seconds)."""

from __future__ import annotations

import contextlib
import json
import logging
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from service.settings import Settings
from tests.test_service import tiny_models  # noqa: F401 - fixture
from tests.test_service_openapi import served

TOKEN = "s49-connections"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
RECEIVE_TIMEOUT_S = 3.0  # the head deadline; an early answer's lingering close is min(2 s, this)
SEND_TIMEOUT_S = 1.0
MAX_CONNECTIONS = 24
# --workers 1 --queue-size 2: 1 + 2 + 16 requests in progress at once.
LIMIT = 19
CLOSED = "lowres3d_connections_closed_total{{reason=\"{}\"}}"


@pytest.fixture(scope="module")
def server(tiny_models: Path) -> Iterator[tuple[str, tuple[str, int]]]:  # noqa: F811
    """The service with small limits, served as ``python -m service`` serves it: its URL and address."""
    settings = Settings(models=tiny_models, port=0, log_level="warning", workers=1, queue_size=2,
                        token=TOKEN, receive_timeout_s=RECEIVE_TIMEOUT_S, send_timeout_s=SEND_TIMEOUT_S,
                        max_connections=MAX_CONNECTIONS)
    assert (settings.connection_limit(), settings.socket_limit()) == (LIMIT, MAX_CONNECTIONS)
    with served(settings) as url:
        host, port = url.removeprefix("http://").split(":")
        yield url, (host, int(port))


def _metric(url: str, series: str) -> float:
    """A series' value on /metrics (0 when absent)."""
    for line in httpx.get(f"{url}/metrics", timeout=5).text.splitlines():
        if line.startswith(series + " "):
            return float(line.rsplit(" ", 1)[1])
    return 0.0


def _wait_for(condition: object, what: str, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():  # type: ignore[operator]
        assert time.monotonic() < deadline, what
        time.sleep(0.05)


@contextlib.contextmanager
def _idle(address: tuple[str, int], count: int) -> Iterator[list[socket.socket]]:
    """``count`` connections that send nothing, taken in by the server (a moment for uvicorn to accept them)."""
    socks: list[socket.socket] = []
    try:
        for _ in range(count):
            socks.append(socket.create_connection(address, timeout=5))
        time.sleep(0.3)
        yield socks
    finally:
        for sock in socks:
            sock.close()
        time.sleep(0.2)  # the server sees them go


def _closed_by_server(sock: socket.socket, timeout_s: float) -> bool:
    """Whether the server closes (or resets) ``sock`` within ``timeout_s``, whatever it sent before."""
    sock.settimeout(timeout_s)
    try:
        while sock.recv(65536):
            pass
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False
    return True


def _answers(data: bytes) -> list[tuple[int, dict[str, str], bytes]]:
    """The answers (status, headers, body) in what a connection received, by their Content-Length."""
    answers = []
    while data:
        head, _, rest = data.partition(b"\r\n\r\n")
        status, *lines = head.decode("latin-1").split("\r\n")
        headers = {name.lower(): value for name, _, value in (line.partition(": ") for line in lines)}
        length = int(headers.get("content-length", "0"))
        answers.append((int(status.split()[1]), headers, rest[:length]))
        data = rest[length:]
    return answers


def _all_received(address: tuple[str, int], request: bytes, timeout_s: float = 10.0) -> bytes:
    """Send ``request`` as is; all the server sent until it closed the connection."""
    with socket.create_connection(address, timeout=timeout_s) as sock:
        sock.sendall(request)
        data = b""
        with contextlib.suppress(ConnectionResetError):
            while chunk := sock.recv(65536):
                data += chunk
    return data


# --------------------------------------------------------------------------- the limit counts requests, not sockets
def test_idle_connections_up_to_the_limit_do_not_lock_out_a_request(server: tuple[str, tuple[str, int]]) -> None:
    """19 connections that send nothing used to fill the limit: every /v1 request, with the right token, was
    answered 503 overloaded until they hit the head deadline. They hold no request, so they no longer count."""
    url, address = server
    with _idle(address, LIMIT):
        model = httpx.get(f"{url}/v1/model", headers=AUTH, timeout=5)
        assert model.status_code == 200, model.text


def test_requests_in_progress_over_the_limit_are_still_refused(server: tuple[str, tuple[str, int]]) -> None:
    """19 requests in progress (uploads refused 401 whose bodies the service waits for, up to 2 s) fill the
    limit: the next /v1 request is answered 503 overloaded, the probes still 200."""
    url, address = server
    head = (b"POST /v1/detect HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\n"
            b"Content-Length: 1000000\r\n\r\n")
    socks = [socket.create_connection(address, timeout=5) for _ in range(LIMIT)]
    try:
        for sock in socks:
            sock.sendall(head)
        for sock in socks:  # each answered at once, and lingering for the body never sent
            assert sock.recv(65536).startswith(b"HTTP/1.1 401 ")
        response = httpx.get(f"{url}/v1/model", headers=AUTH, timeout=5)
        assert response.status_code == 503, response.text[:300]
        error = response.json()["error"]
        assert error["code"] == "overloaded" and f"the limit of {LIMIT}" in error["message"], error
        assert httpx.get(f"{url}/healthz", timeout=5).status_code == 200
    finally:
        for sock in socks:
            sock.close()
    _wait_for(lambda: httpx.get(f"{url}/v1/model", headers=AUTH, timeout=5).status_code == 200,
              "requests were not served again", 5)


# --------------------------------------------------------------------------- the socket cap
def test_at_the_socket_cap_a_new_connection_closes_the_one_idle_longest(server: tuple[str, tuple[str, int]],
                                                                         caplog: pytest.LogCaptureFixture) -> None:
    """With --max-connections idle connections open (a client holding sockets, a balancer's spares), a new one
    is served, a probe included: the connection idle the longest is closed to make room (idle_evicted), without
    a WARNING, and the others stay open."""
    url, address = server
    before = _metric(url, CLOSED.format("idle_evicted"))
    with caplog.at_level(logging.WARNING, logger="service.protocol"), _idle(address, MAX_CONNECTIONS) as idle:
        with socket.create_connection(address, timeout=5) as probe:
            probe.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
            assert probe.recv(65536).startswith(b"HTTP/1.1 200 "), "a probe at the cap was not answered"
        assert _closed_by_server(idle[0], 2.0), "the connection idle the longest was kept open"
        assert not _closed_by_server(idle[-1], 0.3), "a later idle connection was closed as well"
    assert _metric(url, CLOSED.format("idle_evicted")) == before + 1
    assert not [r for r in caplog.records if r.name == "service.protocol"]


def test_at_the_socket_cap_with_none_idle_a_new_connection_is_closed(server: tuple[str, tuple[str, int]],
                                                                    caplog: pytest.LogCaptureFixture) -> None:
    """With --max-connections connections each with a request in progress (uploads answered early whose bodies
    the service waits for, up to 2 s), none is idle: a new connection is closed at once (no descriptor held),
    counted under over_limit, and said in one WARNING; once they end, connections are served again."""
    url, address = server
    head = (b"POST /v1/detect HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\n"
            b"Content-Length: 1000000\r\n\r\n")
    before = _metric(url, CLOSED.format("over_limit"))
    socks = [socket.create_connection(address, timeout=5) for _ in range(MAX_CONNECTIONS)]
    try:
        with caplog.at_level(logging.WARNING, logger="service.protocol"):
            for sock in socks:
                sock.sendall(head)
            for sock in socks:  # each answered at once (401, or 503 past the limit), then lingering: in progress
                assert sock.recv(65536).startswith((b"HTTP/1.1 401 ", b"HTTP/1.1 503 "))
            for _ in range(2):
                with socket.create_connection(address, timeout=5) as extra:
                    extra.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
                    assert _closed_by_server(extra, 1.0), "a connection over the cap was kept open"
    finally:
        for sock in socks:
            sock.close()
    assert _metric(url, CLOSED.format("over_limit")) == before + 2
    warnings = [r.getMessage() for r in caplog.records if r.name == "service.protocol"]
    assert len(warnings) == 1 and f"{MAX_CONNECTIONS} open, the cap (--max-connections), none idle" in warnings[0], \
        warnings
    _wait_for(lambda: httpx.get(f"{url}/v1/model", headers=AUTH, timeout=5).status_code == 200,
              "requests were not served again", 5)


# --------------------------------------------------------------------------- deadlines
def test_a_client_that_never_reads_is_closed_at_the_send_deadline(server: tuple[str, tuple[str, int]]) -> None:
    """Pipelined requests for /openapi.json on a connection that reads none of their answers: once the socket
    buffers are full the answers wait in the server, and after --send-timeout-s without progress the
    connection is cut (it used to stay open with megabytes queued), counted under send_timeout."""
    url, address = server
    size = len(httpx.get(f"{url}/openapi.json", timeout=5).content)
    count = min(400, 12 * 1024 * 1024 // size + 1)  # over the kernel's buffers (4 MiB to send, at most)
    before = _metric(url, CLOSED.format("send_timeout"))
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # before connecting: a small window
    sock.settimeout(5)
    with sock:
        sock.connect(address)
        sock.sendall(b"GET /openapi.json HTTP/1.1\r\nHost: x\r\n\r\n" * count)
        tic = time.monotonic()
        _wait_for(lambda: _metric(url, CLOSED.format("send_timeout")) == before + 1,
                  "the stalled connection was not closed", SEND_TIMEOUT_S + 8)
        assert time.monotonic() - tic >= SEND_TIMEOUT_S - 0.2
        received = 0
        with contextlib.suppress(ConnectionResetError):
            while chunk := sock.recv(65536):
                received += len(chunk)
        assert received < count * size  # cut off: not every answer came
    assert httpx.get(f"{url}/v1/model", headers=AUTH, timeout=5).status_code == 200


def test_a_client_that_reads_slowly_is_not_cut_off(server: tuple[str, tuple[str, int]]) -> None:
    """A client taking its answers at about 160 kB/s, far slower than the server sends: over 4 s (four send
    deadlines) it is not cut off, since the socket's send queue shows its progress even while the transport's
    own buffer waits for the kernel to take more (judged by that buffer alone, it was cut within a deadline)."""
    url, address = server
    size = len(httpx.get(f"{url}/openapi.json", timeout=5).content)
    count = min(400, 12 * 1024 * 1024 // size + 1)
    before = _metric(url, CLOSED.format("send_timeout"))
    with socket.create_connection(address, timeout=5) as sock:
        sock.sendall(b"GET /openapi.json HTTP/1.1\r\nHost: x\r\n\r\n" * count)
        received, end = 0, time.monotonic() + 4 * SEND_TIMEOUT_S
        while time.monotonic() < end:
            chunk = sock.recv(16 * 1024)
            assert chunk, f"cut off after {received} bytes"
            received += len(chunk)
            time.sleep(0.1)
        assert received < count * size  # still answers to come: the deadline was in play throughout
    assert _metric(url, CLOSED.format("send_timeout")) == before


def test_a_connection_that_sends_nothing_is_counted_when_closed(server: tuple[str, tuple[str, int]]) -> None:
    """A connection that sends nothing is closed at the head deadline without an answer or a log line, and
    counted under head_timeout."""
    url, address = server
    before = _metric(url, CLOSED.format("head_timeout"))
    with socket.create_connection(address, timeout=5) as sock:
        assert _closed_by_server(sock, RECEIVE_TIMEOUT_S + 3)
    _wait_for(lambda: _metric(url, CLOSED.format("head_timeout")) == before + 1, "not counted", 2)


# --------------------------------------------------------------------------- framing
def test_a_request_framed_twice_closes_its_connection(server: tuple[str, tuple[str, int]]) -> None:
    """Content-Length and Transfer-Encoding: chunked on one request (RFC 9112 §6.1): it is answered, with
    Connection: close, and the request pipelined after it is not served."""
    _, address = server
    auth = f"Authorization: Bearer {TOKEN}\r\n".encode()
    request = (b"POST /v1/detect HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\n"
               b"Content-Length: 4\r\nTransfer-Encoding: chunked\r\n" + auth + b"\r\n0\r\n\r\n"
               b"GET /v1/model HTTP/1.1\r\nHost: x\r\n" + auth + b"\r\n")
    answers = _answers(_all_received(address, request))
    assert len(answers) == 1, [status for status, _, _ in answers]
    status, headers, _ = answers[0]
    assert status == 400 and headers["connection"] == "close", (status, headers)


# --------------------------------------------------------------------------- one id per request
@pytest.mark.parametrize("size", [b"ffffffffffffffffffffffff", b"-1"], ids=["huge", "negative"])
@pytest.mark.parametrize("client_id", [None, "s49-chunk", "not safe!"], ids=["none", "client's", "unsafe"])
def test_a_malformed_chunk_has_one_request_id(server: tuple[str, tuple[str, int]], caplog: pytest.LogCaptureFixture,
                                              size: bytes, client_id: str | None) -> None:
    """A chunk size h11 cannot read, sent with the head: the answer's X-Request-ID, its body's id and the
    access line name the same id (the client's when safe to echo, else one made for it)."""
    _, address = server
    header = f"X-Request-ID: {client_id}\r\n".encode() if client_id else b""
    request = (b"POST /v1/detect HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\n"
               b"Transfer-Encoding: chunked\r\nAuthorization: Bearer " + TOKEN.encode() + b"\r\n" + header
               + b"\r\n" + size + b"\r\n--b\r\n")
    with caplog.at_level(logging.INFO, logger="service.access"):
        (answer,) = _answers(_all_received(address, request))
        status, headers, body = answer
        assert status == 400, body
        request_id = headers["x-request-id"]
        assert json.loads(body)["error"]["request_id"] == request_id
        if client_id == "s49-chunk":
            assert request_id == client_id
        _wait_for(lambda: any(r.name == "service.access" for r in caplog.records), "no access line", 5)
    lines = [r for r in caplog.records if r.name == "service.access"]
    assert [(r.request_id, r.status) for r in lines] == [(request_id, 400)], [r.getMessage() for r in lines]


# --------------------------------------------------------------------------- the settings
def test_the_socket_cap_lies_between_the_requests_admitted_and_the_open_file_limit(tiny_models: Path) -> None:  # noqa: F811
    """A cap at or under the limit on requests in progress would cut clients off where they should be told 503,
    and one over the open-file limit (less the process's own 64) makes accept() fail with a traceback per try:
    both refused at start, in one line naming the option. Unset, it is the open-file limit less 64, at most 4096:
    measured in a child whose limit is 100."""
    import subprocess
    import sys

    from pydantic import ValidationError

    from service.__main__ import settings_errors

    assert Settings(models=tiny_models, workers=1, queue_size=2, max_connections=LIMIT + 1).socket_limit() == LIMIT + 1
    with pytest.raises(ValidationError) as refused:
        Settings(models=tiny_models, workers=1, queue_size=2, max_connections=LIMIT)
    (line,) = settings_errors(refused.value)
    assert f"--max-connections (LOWRES3D_MAX_CONNECTIONS) {LIMIT}: at most {LIMIT} requests are admitted at once" in line, line
    child = ("import resource, sys\n"
             "resource.setrlimit(resource.RLIMIT_NOFILE, (100, resource.getrlimit(resource.RLIMIT_NOFILE)[1]))\n"
             "from pydantic import ValidationError\n"
             "from service.settings import Settings\n"
             f"print(Settings(models={str(tiny_models)!r}, workers=1, queue_size=2).socket_limit())\n"
             "try:\n"
             f"    Settings(models={str(tiny_models)!r}, workers=1, queue_size=2, max_connections=37)\n"
             "except ValidationError as exc:\n"
             "    print(exc.errors()[0]['msg'])\n")
    done = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, timeout=120, check=True,
                          cwd=Path(__file__).resolve().parents[1])
    default, message = done.stdout.splitlines()
    assert default == "36"
    assert "--max-connections (LOWRES3D_MAX_CONNECTIONS) 37: the open-file limit (ulimit -n) is 100" in message and "at most 36" in message
