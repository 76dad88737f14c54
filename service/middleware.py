"""Pure ASGI middleware, outermost first: request context, connection limit, token, body limit, admission.

:class:`RequestContextMiddleware` is the outermost layer: it gives each request
an id (``X-Request-ID``, echoed in every answer and error), counts and times
it (the method and route labels from fixed sets, so no client can grow the
metrics), writes one access line per request (logger ``service.access``: the
fields of :data:`service.logs.ACCESS_FIELDS`), and turns any unhandled
exception into a 500 that carries only the request id while the trace goes to
the log. A request whose client closed the connection before its answer is
counted (and logged) as 499. A request cancelled because uvicorn's graceful
shutdown (``--shutdown-timeout-s``) ran out is answered 503 ``shutting_down``
instead, when its answer has not begun, and the cancellation goes on
(:class:`CancelledRequestLogFilter` keeps uvicorn from logging it as a crash).

The layers inside answer before a byte of the body is read whenever they can:
:class:`ConnectionLimitMiddleware` answers 503 to a request service/protocol.py
found over the limit on requests in progress (``Settings.connection_limit``; probes and ``/metrics`` excepted);
:class:`AuthMiddleware` answers 401 on ``/v1/*`` without the token;
:class:`BodyLimitMiddleware` answers 413 on a Content-Length over the limit, else
counts body bytes as they arrive (so a chunked upload is cut off as soon as it
passes the limit), and answers 408 for a body not received within
``--receive-timeout-s``. While counting it also notes whether a multipart/form-data
body was empty or ended without its close delimiter
(``scope["state"]["multipart_body"]``), which the multipart parser does not
check: :func:`service.deps.require_multipart` answers 400 for those.
:class:`AdmissionMiddleware` takes the frame's place in the inference pool before
its upload is read, and answers 503 when there is none (or the models are not
ready), so the uploads held at once are bounded by workers + queue.

The 503s and the 401 given before the body is read close the connection, but only once the body has been
read and dropped (:func:`send_early_error`, a bounded lingering close): closing a socket with the upload unread
makes the kernel reset the connection, and a client that sends its whole body before it reads (httpx, most
libraries) would get a connection error instead of its answer.

With ``--cors-origins``, :class:`CORSMiddleware` is outermost of all: every answer a browser's script gets,
a 500 included, carries the CORS headers; it answers a preflight itself (no request id, not counted).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import re
import time
from collections.abc import Awaitable, Callable, MutableMapping
from dataclasses import dataclass, field
from typing import Any

from pydantic import SecretStr
from python_multipart.multipart import parse_options_header
from starlette.datastructures import Headers
from starlette.middleware.cors import CORSMiddleware as StarletteCORSMiddleware

from service.deps import UNAUTHORIZED_MESSAGE, WWW_AUTHENTICATE, not_ready_reason, token_accepted
from service.errors import error_bytes
from service.logs import REQUEST_ID, request_id_for
from service.metrics import Metrics
from service.pool import PoolClosed, PoolFull
from service.protocol import MALFORMED_BODY, METHODS, OVER_CONNECTION_LIMIT, peer_text
from service.runtime import Runtime

log = logging.getLogger(__name__)
access_log = logging.getLogger("service.access")

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

CLIENT_CLOSED = 499  # nginx's "client closed request": the client left before its answer
_ERROR_CODE_BYTES = 64 * 1024  # an error body read for its code in the log line (error bodies are small)
_SHOWN_PATH_CHARS = 200  # of a request's target in its access line: a client may send kilobytes of it
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


def _multipart_close(scope: Scope) -> bytes | None:
    """The close delimiter ``--BOUNDARY--`` of a multipart/form-data body, None for any other body.

    The boundary is read by the function Starlette's multipart parser reads it with (python-multipart's
    ``parse_options_header``, imported by Starlette 0.38 through its ``multipart`` alias: the same object), so the
    two cannot disagree: a regular expression of our own did on legal headers (``boundary=b ; charset=utf-8``,
    ``xboundary=a; boundary=b``) and refused whole bodies as cut off."""
    content_type = _header(scope, b"content-type") or ""
    if content_type.split(";", 1)[0].strip().lower() != "multipart/form-data":
        return None
    boundary = parse_options_header(content_type)[1].get(b"boundary")
    return b"--" + boundary + b"--" if boundary is not None else None


def _header(scope: Scope, name: bytes) -> str | None:
    for key, value in scope.get("headers", []):
        if key.lower() == name:
            return value.decode("latin-1")
    return None


def _has_body(scope: Scope) -> bool:
    """Whether the request announces a body (a Content-Length above 0, or chunked)."""
    length = _header(scope, b"content-length")
    return _header(scope, b"transfer-encoding") is not None or (length is not None and length.strip() not in ("", "0"))


def _close_if_body(scope: Scope) -> list[tuple[bytes, bytes]]:
    """``Connection: close`` for an answer given before the request's body was read: the server would
    otherwise read (and drop) all of it to keep the connection."""
    return [(b"connection", b"close")] if _has_body(scope) else []


def method_label(scope: Scope) -> str:
    """The request's method for metrics and the log: one of HTTP's methods, or "other" (a method token is any
    string a client likes, up to kilobytes: each would be a series of its own)."""
    method = scope.get("method", "")
    return method if method in METHODS else "other"


def _route_label(scope: Scope, route_paths: frozenset[str]) -> str:
    """The route of a request for metrics, also for one answered before routing (a 413 by the body limit);
    "unmatched" for paths no route serves, so a scan of random URLs cannot grow the label set."""
    route = getattr(scope.get("route"), "path", None)
    if route is None and scope.get("path") in route_paths:
        route = scope["path"]  # every route of the service is a fixed path, so the path is its template
    return route or "unmatched"


def request_target(scope: Scope) -> str:
    """The path and query the client sent, for its access line: as received (percent-escapes kept, so a
    ``%0A`` cannot start a line of its own), control characters escaped, at most 200 characters."""
    raw = scope.get("raw_path")
    path = raw.decode("ascii", "backslashreplace") if isinstance(raw, bytes) else str(scope.get("path", ""))
    query = scope.get("query_string", b"")
    if query:
        path += "?" + query.decode("ascii", "backslashreplace")
    path = _CONTROL.sub(lambda match: f"\\x{ord(match.group()):02x}", path)
    return path if len(path) <= _SHOWN_PATH_CHARS else path[:_SHOWN_PATH_CHARS] + "..."


def client_address(scope: Scope) -> str | None:
    """``host:port`` of the peer (``[::1]:port`` for IPv6), None when the server does not say."""
    return peer_text(scope.get("client"))


def access_level(status: int, quiet: bool) -> int:
    """The level of a request's access line: ERROR for a 500 (a bug), WARNING for the service's other 5xx
    (overloaded, not ready, shutting down, past its deadline), INFO for the rest (a client's mistake is not the
    service's error); DEBUG for the probes' and /metrics' (``quiet``: every few seconds from each scraper)."""
    if status == 500:
        return logging.ERROR
    if quiet:
        return logging.DEBUG
    return logging.WARNING if status >= 500 else logging.INFO


def warning_codes_of(state: MutableMapping[str, Any], header: str | None) -> list[str]:
    """The frame's warning codes: those the route noted (``state["warning_codes"]``), else X-Warning-Codes."""
    codes = state.get("warning_codes")
    if codes is None and header:
        with contextlib.suppress(ValueError):
            codes = json.loads(header)
    return [str(code) for code in codes] if isinstance(codes, list) else []


async def send_error(send: Send, status: int, code: str, message: str, request_id: str | None,
                     extra_headers: list[tuple[bytes, bytes]] | None = None, more_body: bool = False) -> None:
    """Answer an error from middleware (no Response object available); ``more_body``: an empty last part follows
    (the caller sends it)."""
    body = error_bytes(code, message, request_id)
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    await send({"type": "http.response.start", "status": status, "headers": headers + (extra_headers or [])})
    await send({"type": "http.response.body", "body": body, "more_body": more_body})


# How long an early error answer waits for the rest of the request's body (its lingering close) at most. A
# frame (3 MB) arrives in milliseconds on a LAN and in 2 s at 12 Mbit/s; a client slower than that is cut off
# (reset) as before, and a flood of refused uploads holds each connection at most this long.
LINGER_S = 2.0


@dataclass(frozen=True)
class Linger:
    """The bounds of an early answer's lingering close: at most ``max_bytes`` (the body limit) of the body read
    and dropped, for at most ``timeout_s``."""

    max_bytes: int
    timeout_s: float

    @classmethod
    def of(cls, max_body_bytes: int, receive_timeout_s: float) -> Linger:
        """LINGER_S, or ``--receive-timeout-s`` when shorter (no client is owed longer than that for its body)."""
        return cls(max_body_bytes, min(LINGER_S, receive_timeout_s))


def _client_sends_body(scope: Scope) -> bool:
    """Whether the client is sending a body: it announced one, and does not wait for ``100 Continue`` first (a
    client that does sends none once answered: uvicorn sends 100 only at a receive() before the answer)."""
    expect = _header(scope, b"expect")
    return _has_body(scope) and (expect is None or expect.strip().lower() != "100-continue")


async def _drop_body(receive: Receive, linger: Linger) -> None:
    """Read and drop the request's body until its end, the client's leaving, or ``linger``'s bounds: no more
    than one message of it is held at a time (uvicorn pauses reading once it holds 64 KiB)."""
    deadline = time.monotonic() + linger.timeout_s
    dropped = 0
    while dropped <= linger.max_bytes:
        try:
            message = await asyncio.wait_for(receive(), deadline - time.monotonic())
        except (TimeoutError, asyncio.TimeoutError):  # both: the builtin is not asyncio's on Python 3.10
            return
        if message["type"] != "http.request" or not message.get("more_body", False):
            return
        dropped += len(message.get("body", b""))


async def send_early_error(scope: Scope, receive: Receive, send: Send, linger: Linger, status: int, code: str,
                           message: str, extra_headers: list[tuple[bytes, bytes]]) -> None:
    """Answer an error before the request's body was read, then close the connection (``extra_headers`` should
    say ``Connection: close``) only once the body has been read and dropped, within ``linger``'s bounds.

    Closing the socket with the upload still unread in its buffer makes the kernel reset the connection, and
    a client that sends its whole body before it reads the answer then gets a connection error instead. The
    answer goes out first, so a client that reads as it sends (curl) has it at once; its last (empty) part
    waits for the body. A body past the bounds, or one the client waits to be invited for (``Expect:
    100-continue``), is not waited for: the connection closes at once, as it would without the body."""
    request_id = (scope.get("state") or {}).get("request_id")
    lingers = _client_sends_body(scope)
    await send_error(send, status, code, message, request_id, extra_headers, more_body=lingers)
    if lingers:
        await _drop_body(receive, linger)
        await send({"type": "http.response.body", "body": b"", "more_body": False})


class CancelledRequestLogFilter(logging.Filter):
    """Drops uvicorn's "Exception in ASGI application" record (with its traceback) for a cancelled request.

    uvicorn cancels the requests still running when its graceful shutdown times out, and logs each
    cancellation that leaves the app as a crash. RequestContextMiddleware has answered such a request and
    logged one line for it; the cancellation itself must still leave the app (asyncio's contract with the
    canceller). Add it to the ``uvicorn.error`` logger.
    """

    def filter(self, record: logging.LogRecord) -> bool:
        cancelled = record.exc_info is not None and isinstance(record.exc_info[1], asyncio.CancelledError)
        return not (cancelled and str(record.msg).startswith("Exception in ASGI application"))


class ClientNoiseLogFilter(logging.Filter):
    """Turns the library warnings any client can cause at will into DEBUG records.

    uvicorn warns once per malformed request ("Invalid HTTP request received.") and twice per ``Upgrade``
    request, python-multipart once per malformed body: a bad client could fill the log with them. The
    service answers each of these requests (uvicorn's 400, the service's own 400 with its one line), so at
    info level they are dropped; ``--log-level debug`` shows them. Add it to ``uvicorn.error`` and to
    python-multipart's logger (:func:`install_log_filters`).
    """

    _UVICORN = ("Invalid HTTP request received", "Unsupported upgrade request", "No supported WebSocket library")

    def filter(self, record: logging.LogRecord) -> bool:
        noise = record.name.startswith(("python_multipart", "multipart")) or (
            record.name == "uvicorn.error" and str(record.msg).startswith(self._UVICORN))
        if not noise or record.levelno < logging.WARNING:
            return True
        record.levelno, record.levelname = logging.DEBUG, "DEBUG"
        return logging.getLogger(record.name).isEnabledFor(logging.DEBUG)


class ShutdownGraceLogFilter(logging.Filter):
    """uvicorn's "Cancel N running task(s), timeout graceful shutdown exceeded" as a WARNING, not an ERROR: it is
    what ``--shutdown-timeout-s`` is for, and each request it cuts off is answered 503 with a line of its own.
    Add it to the ``uvicorn.error`` logger."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno == logging.ERROR and str(record.msg).startswith("Cancel %s running task(s)"):
            record.levelno, record.levelname = logging.WARNING, "WARNING"
        return True


def install_log_filters() -> None:
    """Attach the service's filters to uvicorn's and python-multipart's loggers (a logger's filters see only
    its own records, so each logger that writes them gets one)."""
    uvicorn_error = logging.getLogger("uvicorn.error")
    uvicorn_error.addFilter(CancelledRequestLogFilter())
    uvicorn_error.addFilter(ClientNoiseLogFilter())
    uvicorn_error.addFilter(ShutdownGraceLogFilter())
    # python-multipart's module logger; "multipart.multipart" before it was renamed (0.0.13).
    for name in ("python_multipart.multipart", "multipart.multipart"):
        logging.getLogger(name).addFilter(ClientNoiseLogFilter())


class RequestsInFlight:
    """How many HTTP requests :class:`RequestContextMiddleware` is handling.

    The lifespan's shutdown waits for them to end before the process does: the requests uvicorn cancels when
    the shutdown grace runs out answer their 503 as the event loop next runs them, which a process ending at
    once would not let them do (polled, not an asyncio.Event: an app may be served on more than one loop).
    """

    def __init__(self) -> None:
        self.count = 0

    async def drained(self, timeout_s: float) -> bool:
        """Wait until no request is in flight; False if some still are after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while self.count and time.monotonic() < deadline:
            await asyncio.sleep(0.01)
        return not self.count


@dataclass
class _Exchange:
    """One request as :class:`RequestContextMiddleware` sees it: its id and method label, and what its answer
    has been so far, noted by the ``receive`` and ``send`` the app is handed (:meth:`watched`,
    :meth:`stamped`)."""

    request_id: str
    method: str  # method_label's: one of HTTP's, or "other"
    status: int = 500
    started: bool = False  # the answer's start went to the server: no other answer can replace it
    client_gone: bool = False  # the server said the client disconnected before the answer began
    code: str | None = None  # an error answer's code, for the log line
    # The answer's, for the access line (X-Model-ID, X-Warning-Codes).
    headers: dict[bytes, bytes] = field(default_factory=dict)

    def watched(self, receive: Receive) -> Receive:
        """``receive``, noting a disconnect that comes before the answer began (the client left)."""
        async def receive_watched() -> Message:
            message = await receive()
            if message["type"] == "http.disconnect" and not self.started:
                self.client_gone = True
            return message

        return receive_watched

    def stamped(self, send: Send) -> Send:
        """``send``, noting the answer's status, headers and error code; its start carries X-Request-ID."""
        async def send_with_id(message: Message) -> None:
            if message["type"] == "http.response.start":
                self._note_start(message)
            elif self.status >= 400 and self.code is None and len(message.get("body", b"")) <= _ERROR_CODE_BYTES:
                self._note_code(message)
            await send(message)

        return send_with_id

    def _note_start(self, message: Message) -> None:
        """The answer begins: its status and the headers the access line reads noted, X-Request-ID added."""
        self.status = message["status"]
        self.started = True
        self.headers.update((bytes(key).lower(), bytes(value)) for key, value in message.get("headers", [])
                            if bytes(key).lower() in (b"x-model-id", b"x-warning-codes"))
        message["headers"] = [*message.get("headers", []), (b"x-request-id", self.request_id.encode())]

    def _note_code(self, message: Message) -> None:
        """An error answer's code, read from its body (when it is the service's JSON error)."""
        with contextlib.suppress(ValueError, TypeError, AttributeError, KeyError):
            self.code = str(json.loads(message.get("body", b""))["error"]["code"])

    def settle(self, scope: Scope) -> None:
        """The status and code as the client saw them, once the request has ended."""
        if self.client_gone and (scope.get("state") or {}).get(MALFORMED_BODY):
            # The protocol answered the body h11 could not read (service/protocol.py), then closed.
            self.status, self.code, self.client_gone = 400, "bad_request", False
        elif self.client_gone:  # whatever the app answered went nowhere
            self.status, self.code = CLIENT_CLOSED, None


class RequestContextMiddleware:
    """Request id, request metrics, one access line per request, a JSON 500 (trace logged, never returned) for
    unhandled errors, a JSON 503 for requests cancelled by the server's shutdown, and 499 in the metrics and
    the log for a request whose client left before its answer.

    ``model_id``: the id of the model served (None before it is loaded), on every access line. ``quiet_paths``:
    routes whose access lines are DEBUG (the probes, ``/metrics``), so that they do not fill the log."""

    def __init__(self, app: ASGIApp, metrics: Metrics, route_paths: frozenset[str] = frozenset(),
                 in_flight: RequestsInFlight | None = None, model_id: Callable[[], str | None] | None = None,
                 quiet_paths: frozenset[str] = frozenset()) -> None:
        self.app = app
        self.metrics = metrics
        self.route_paths = route_paths
        self.in_flight = in_flight or RequestsInFlight()
        self.model_id = model_id or (lambda: None)
        self.quiet_paths = quiet_paths

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """The request's phases: its id, the app with its answer watched, the answer of an unhandled error
        or of a shutdown's cut-off, then (however it ended) its metrics and its access line."""
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        request_id = request_id_for(_header(scope, b"x-request-id"))
        scope.setdefault("state", {})["request_id"] = request_id
        exchange = _Exchange(request_id, method_label(scope))
        context = REQUEST_ID.set(request_id)  # lines logged during this request on the loop name it
        self.metrics.http_in_flight.inc()
        self.in_flight.count += 1
        tic = time.perf_counter()
        try:
            await self.app(scope, exchange.watched(receive), exchange.stamped(send))
        except asyncio.CancelledError:
            await self._answer_cut_off(scope, send, exchange)
            raise
        except Exception:
            log.exception("internal error on %s %s (request id %s)", exchange.method,
                          _route_label(scope, self.route_paths), request_id)
            await self._answer_internal_error(send, exchange)
        finally:
            self._count_and_log(scope, exchange, tic)
            REQUEST_ID.reset(context)

    async def _answer_cut_off(self, scope: Scope, send: Send, exchange: _Exchange) -> None:
        """A request cancelled by the server's shutdown: answered 503 ``shutting_down`` unless its answer had
        begun; the caller lets the cancellation go on.

        uvicorn cancels the requests still running when --shutdown-timeout-s runs out (and answers a plain 500
        itself): answer in the service's format while the connection is still open, then let the cancellation
        go on. A frame already on a worker is stopped there; one still queued never runs."""
        request_id, method = exchange.request_id, exchange.method
        route = _route_label(scope, self.route_paths)
        if exchange.started:  # the client sees the connection close before the end of the body
            log.warning("request %s (%s %s) cut off by the shutdown during its answer", request_id, method,
                        route)
            return
        exchange.status, exchange.code = 503, "shutting_down"
        log.warning("request %s (%s %s) cut off by the shutdown: answered 503 shutting_down",
                    request_id, method, route)
        # Best effort: the client may be gone, and nothing may replace the cancellation (the caller's raise).
        with contextlib.suppress(Exception):
            await send_error(
                send, 503, "shutting_down",
                "the service shut down before this request finished; send it again (to another replica)",
                request_id, [(b"x-request-id", request_id.encode()), (b"retry-after", b"1"),
                             (b"connection", b"close")],
            )

    async def _answer_internal_error(self, send: Send, exchange: _Exchange) -> None:
        """An unhandled exception (its trace logged under the request id): a JSON 500 carrying only that id,
        when the answer has not begun."""
        request_id = exchange.request_id
        exchange.status, exchange.code = 500, "internal_error"
        if not exchange.started:
            await send_error(
                send, 500, "internal_error",
                f"internal error; the server log has the details under request id {request_id}", request_id,
                [(b"x-request-id", request_id.encode())],
            )

    def _count_and_log(self, scope: Scope, exchange: _Exchange, tic: float) -> None:
        """The request has ended (``tic``: when it began): out of the in-flight counts, then counted, timed
        and logged with the status its client saw."""
        self.metrics.http_in_flight.dec()
        self.in_flight.count -= 1
        elapsed_s = time.perf_counter() - tic
        label = _route_label(scope, self.route_paths)
        exchange.settle(scope)
        status = exchange.status
        self.metrics.requests.labels(route=label, method=exchange.method, status=str(status)).inc()
        self.metrics.request_latency.labels(route=label).observe(elapsed_s)
        level = access_level(status, scope.get("path") in self.quiet_paths)
        if access_log.isEnabledFor(level):
            self._log_access(level, scope, exchange.request_id, exchange.method, label, status, exchange.code,
                             exchange.client_gone, elapsed_s, exchange.headers)

    def _log_access(self, level: int, scope: Scope, request_id: str, method: str, route: str, status: int,
                    code: str | None, client_gone: bool, elapsed_s: float, headers: dict[bytes, bytes]) -> None:
        """The request's access line: a sentence for people, the fields (``extra``) for the JSON format."""
        client = client_address(scope)
        target = request_target(scope)
        header_model = headers.get(b"x-model-id")
        model_id = self.model_id() or (header_model.decode("latin-1") if header_model else None)
        header_codes = headers.get(b"x-warning-codes")
        warning_codes = warning_codes_of(scope.get("state") or {},
                                         header_codes.decode("latin-1") if header_codes else None)
        what = "client disconnected before its answer" if client_gone else "answered"
        details = [f"client {client or 'unknown'}"]
        if route == "unmatched":  # the route label says nothing of what was asked
            details.append(f"path {target}")
        if header_model:  # a model answered: which one (the JSON field has it on every line)
            details.append(f"model {header_model.decode('latin-1')[:12]}")
        if warning_codes:
            details.append(f"warnings {','.join(warning_codes)}")
        duration_ms = round(elapsed_s * 1e3, 1)  # one value for the field and the sentence (450.53 said 451 and 450.5)
        fields = {"request_id": request_id, "method": method, "path": target, "route": route, "status": status,
                  "error_code": code, "duration_ms": duration_ms, "client": client,
                  "model_id": model_id, "warning_codes": warning_codes}
        access_log.log(level, "request %s: %s %s %s %d%s in %.0f ms (%s)", request_id, method, route, what, status,
                       f" {code}" if code else "", duration_ms, "; ".join(details), extra=fields)


class ConnectionLimitMiddleware:
    """503 ``overloaded`` for a request service/protocol.py marked as over the limit on requests in progress, before
    its body is read; the probes and ``/metrics`` are answered still (an orchestrator must not take overload for
    death)."""

    def __init__(self, app: ASGIApp, open_paths: frozenset[str], linger: Linger) -> None:
        self.app = app
        self.open_paths = open_paths
        self.linger = linger

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        state = scope.get("state") or {}
        limit = state.get(OVER_CONNECTION_LIMIT)
        if scope["type"] != "http" or limit is None or scope.get("path") in self.open_paths:
            await self.app(scope, receive, send)
            return
        await send_early_error(scope, receive, send, self.linger, 503, "overloaded",
                               f"requests: more than the limit of {limit} in progress; retry later",
                               [(b"retry-after", b"1"), (b"connection", b"close")])


class AuthMiddleware:
    """401 on ``/v1/*`` without ``Authorization: Bearer <token>``, before the body is read (the route's own
    check would come after FastAPI has read and parsed the whole upload). Probes, metrics and the schema stay
    open."""

    def __init__(self, app: ASGIApp, token: SecretStr, linger: Linger) -> None:
        self.app = app
        self.token = token
        self.linger = linger

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        path = scope.get("path", "")
        protected = scope["type"] == "http" and (path == "/v1" or path.startswith("/v1/"))
        if protected and not token_accepted(self.token, _header(scope, b"authorization")):
            await send_early_error(scope, receive, send, self.linger, 401, "unauthorized", UNAUTHORIZED_MESSAGE,
                                   [(b"www-authenticate", WWW_AUTHENTICATE.encode()), *_close_if_body(scope)])
            return
        await self.app(scope, receive, send)


class BodyLimitMiddleware:
    """413 for bodies over ``max_bytes``: by Content-Length up front, else by counting received bytes; 408 for a
    body not received within ``receive_timeout_s`` of its head's arrival (when the request reaches this layer;
    the head's own deadline is service/protocol.py's).

    Also records whether a multipart/form-data body was empty, or arrived without its close delimiter."""

    def __init__(self, app: ASGIApp, max_bytes: int, receive_timeout_s: float = 30.0) -> None:
        self.app = app
        self.max_bytes = max_bytes
        self.receive_timeout_s = receive_timeout_s

    def _too_large(self) -> tuple[int, str, str]:
        return 413, "body_too_large", f"request body: larger than the limit of {self.max_bytes} bytes"

    def _too_slow(self) -> tuple[int, str, str]:
        return 408, "request_timeout", (f"request body: not received within {self.receive_timeout_s:g} s "
                                        "(--receive-timeout-s); the connection is closed")

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """The body's phases: its declared length checked, then the app run on a body counted and timed as it
        arrives (:class:`_BodyWatch`), its answer replaced by the 413 or 408 when the body was refused."""
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        request_id = (scope.get("state") or {}).get("request_id")
        connection_close = [(b"connection", b"close")]
        if self._declared_too_large(scope):
            await send_error(send, 413, *self._too_large()[1:], request_id, connection_close)
            return
        body = _BodyWatch(self, scope, receive, send)
        try:
            await self.app(scope, body.receive, body.send)
        except Exception:
            if body.refusal is None or body.app_started:
                raise
        if body.refusal is not None and not body.app_started:
            await send_error(send, body.refusal[0], *body.refusal[1:], request_id, connection_close)

    def _declared_too_large(self, scope: Scope) -> bool:
        """Whether the request's Content-Length is over the limit (refused before its body is read)."""
        declared = _header(scope, b"content-length")
        return declared is not None and declared.strip().isdigit() and int(declared) > self.max_bytes


class _MultipartEnd:
    """Whether a multipart/form-data body ends with its close delimiter, sought in its chunks as they pass.

    python-multipart (and so Starlette) silently drops a part that the body ends in the middle of
    (its finalize() does not check for the close delimiter): a cut-off upload would lose its last
    part, and with --default-calib a lost calib would silently become the server's. Look for the close
    delimiter (CRLF--BOUNDARY--) in the whole stream: a boundary never occurs inside a part, so its first
    occurrence is the end, and anything after it (an epilogue, RFC 2046) is harmless."""

    def __init__(self, close: bytes) -> None:
        self.needle = b"\r\n" + close
        # As if a CRLF came before the body: a close delimiter at its very start counts too.
        self.carry = b"\r\n"
        self.closed = False

    def feed(self, chunk: bytes) -> None:
        """Look at the body's next chunk (after the end of the one before, where the delimiter may begin)."""
        if self.closed:
            return
        window = self.carry + chunk
        self.closed = self.needle in window
        self.carry = window[-(len(self.needle) - 1):]

    def ending(self, received: int) -> str:
        """How the body of ``received`` bytes ended, for ``scope["state"]["multipart_body"]``."""
        return "empty" if received == 0 else "whole" if self.closed else "cut_off"


class _BodyWatch:
    """One request's body as :class:`BodyLimitMiddleware` lets the app read it: counted against the limit, on
    a deadline, a multipart body's ending noted; and the app's answer, held back once the body is refused.

    :meth:`receive` and :meth:`send` are what the app is handed in place of the server's."""

    def __init__(self, limits: BodyLimitMiddleware, scope: Scope, receive: Receive, send: Send) -> None:
        self.limits = limits
        self.scope = scope
        self.server_receive = receive
        self.server_send = send
        self.received = 0
        self.body_done = False
        self.refusal: tuple[int, str, str] | None = None  # the 413 or 408 that replaces the app's answer
        self.app_started = False
        self.deadline = time.monotonic() + limits.receive_timeout_s
        close = _multipart_close(scope)
        self.multipart = _MultipartEnd(close) if close is not None else None

    async def receive(self) -> Message:
        """The server's next message, or a disconnect once the body is refused (too slow, or too large)."""
        if self.refusal is not None:
            return {"type": "http.disconnect"}
        if self.body_done:  # after the body only the end of the connection can come: no deadline
            return await self.server_receive()
        try:
            message = await asyncio.wait_for(self.server_receive(),
                                             max(0.0, self.deadline - time.monotonic()))
        # Both names: asyncio.TimeoutError is no builtin TimeoutError on Python 3.10 (the Jetson image).
        except (TimeoutError, asyncio.TimeoutError):
            self.refusal = self.limits._too_slow()  # the app sees a client disconnect and stops reading
            return {"type": "http.disconnect"}
        if message["type"] == "http.request":
            return self._counted(message)
        return message

    def _counted(self, message: Message) -> Message:
        """A part of the body, counted (a disconnect in its place once past the limit); at its end, a
        multipart body's ending noted in the scope's state."""
        chunk = message.get("body", b"")
        self.received += len(chunk)
        if self.received > self.limits.max_bytes:
            self.refusal = self.limits._too_large()
            return {"type": "http.disconnect"}
        if self.multipart is not None:
            self.multipart.feed(chunk)
        if not message.get("more_body", False):
            self.body_done = True
            if self.multipart is not None:
                self.scope.setdefault("state", {})["multipart_body"] = self.multipart.ending(self.received)
        return message

    async def send(self, message: Message) -> None:
        """The app's message to the server; none once the body is refused before the app's answer began."""
        if self.refusal is not None and not self.app_started:
            return  # the app's answer to the "disconnect" is replaced by the 413 or 408 (BodyLimitMiddleware)
        if message["type"] == "http.response.start":
            self.app_started = True
        await self.server_send(message)


class AdmissionMiddleware:
    """Takes a frame's place in the inference pool before its upload is read (``scope["state"]["reservation"]``,
    handed to the pool by the route), and gives it back when the request ends.

    Without a place (every worker busy and the queue full, the service shutting down) or before the models are
    ready, the request is answered 503 at once, with Retry-After and the connection closed, so no more uploads
    than the pool has places are held at once. Only the detection routes (``detect_paths``) take a place.
    """

    def __init__(self, app: ASGIApp, runtime: Callable[[], Runtime | None], detect_paths: frozenset[str],
                 linger: Linger) -> None:
        self.app = app
        self.runtime = runtime
        self.detect_paths = detect_paths
        self.linger = linger

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope.get("method") != "POST" or scope.get("path") not in self.detect_paths:
            await self.app(scope, receive, send)
            return
        state = scope.setdefault("state", {})
        close = [(b"connection", b"close")]
        runtime = self.runtime()
        reason = not_ready_reason(runtime)
        if reason is not None:
            await send_early_error(scope, receive, send, self.linger, 503, "not_ready", reason,
                                   [(b"retry-after", b"1"), *close])
            return
        assert runtime is not None  # not_ready_reason said so
        pool = runtime.pool
        try:
            reservation = pool.reserve()
        except PoolFull as exc:
            await send_early_error(scope, receive, send, self.linger, 503, "overloaded",
                                   f"inference queue: full ({pool.capacity} frames admitted); retry later",
                                   [(b"retry-after", str(exc.retry_after_s).encode()), *close])
            return
        except PoolClosed:
            await send_early_error(scope, receive, send, self.linger, 503, "shutting_down",
                                   "the service is shutting down", [(b"retry-after", b"1"), *close])
            return
        state["reservation"] = reservation
        try:
            await self.app(scope, receive, send)
        finally:
            reservation.release()  # a no-op when the frame's job took the place over


# What a dashboard's script may send and read across origins, beyond CORS's safelisted headers.
CORS_METHODS = ("GET", "HEAD", "POST")
CORS_REQUEST_HEADERS = ("Authorization", "X-Request-ID")
CORS_EXPOSED_HEADERS = ("X-Request-ID", "X-Warnings", "X-Warning-Codes", "X-Model-ID", "X-Model-Directory",
                        "X-Model-Preset", "X-Model-Precision", "X-Image-Stamp-Ns", "X-Points-Stamp-Ns", "Retry-After",
                        "WWW-Authenticate")


class CORSMiddleware(StarletteCORSMiddleware):
    """Starlette's CORS for the ``--cors-origins``, the methods and headers of the service; a refused preflight is
    answered in the service's error shape (Starlette answers it in plain text)."""

    def __init__(self, app: ASGIApp, origins: list[str]) -> None:
        super().__init__(app, allow_origins=origins, allow_methods=CORS_METHODS, allow_headers=CORS_REQUEST_HEADERS,
                         expose_headers=CORS_EXPOSED_HEADERS)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":  # the lifespan: it has no headers
            await self.app(scope, receive, send)
            return
        headers = Headers(scope=scope)
        preflight = (scope["method"] == "OPTIONS" and "origin" in headers
                     and "access-control-request-method" in headers)
        if not preflight:
            await super().__call__(scope, receive, send)
            return
        response = self.preflight_response(request_headers=headers)
        if response.status_code == 200:
            await response(scope, receive, send)
            return
        request_id = request_id_for(headers.get("x-request-id"))
        # Starlette's text: "Disallowed CORS origin, method, headers" (those at fault).
        failures = bytes(response.body).decode().removeprefix("Disallowed CORS ").split(", ")
        kept = [(key, value) for key, value in response.raw_headers if key not in (b"content-type", b"content-length")]
        await send_error(send, 400, "bad_request", self._refusal(headers, failures), request_id,
                         [*kept, (b"x-request-id", request_id.encode())])

    def _refusal(self, headers: Headers, failures: list[str]) -> str:
        """Why the preflight was refused, each clause naming its header and what the service allows."""
        clauses = {
            "origin": f"Origin: {headers['origin'][:200]} is not one of --cors-origins",
            "method": f"Access-Control-Request-Method: {headers['access-control-request-method'][:20]} is not one "
                      f"of {', '.join(CORS_METHODS)}",
            "headers": "Access-Control-Request-Headers: only "
                       f"{', '.join(CORS_REQUEST_HEADERS)} and the CORS-safelisted headers may be sent",
            "private-network": "Access-Control-Request-Private-Network: not allowed",
        }
        return "CORS preflight refused: " + "; ".join(clauses.get(failure, failure) for failure in failures)
