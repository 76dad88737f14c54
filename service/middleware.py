"""Pure ASGI middleware: request ids, metrics and the last-resort 500; the request body limit (413).

:class:`RequestContextMiddleware` is the outermost layer: it gives each request
an id (``X-Request-ID``, echoed in every answer and error), counts and times
it, and turns any unhandled exception into a 500 that carries only the request
id while the trace goes to the log. A request cancelled because uvicorn's
graceful shutdown (``--shutdown-timeout-s``) ran out is answered 503
``shutting_down`` instead, when its answer has not begun, and the cancellation goes
on (:class:`CancelledRequestLogFilter` keeps uvicorn from logging it as a crash).
:class:`BodyLimitMiddleware` counts body
bytes as they arrive, so a client that sends no Content-Length (chunked) is
cut off as soon as it passes the limit, and answers 413 itself. While counting it
also notes whether a multipart body ended with its close delimiter
(``scope["state"]["multipart_complete"]``), which the multipart parser does not
check: :func:`service.deps.require_multipart` answers 400 for a cut-off upload.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
import time
import uuid
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from service.errors import error_bytes
from service.metrics import Metrics

log = logging.getLogger(__name__)

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

_SAFE_REQUEST_ID = re.compile(r"^[A-Za-z0-9._-]{1,64}$")
_BOUNDARY = re.compile(r'boundary="?([^";]+)"?', re.IGNORECASE)
_TAIL_BYTES = 4096  # room for the close delimiter plus any CRLF/epilogue a client adds after it


def _multipart_close(scope: Scope) -> bytes | None:
    """The close delimiter ``--BOUNDARY--`` of a multipart/form-data body, None for any other body."""
    content_type = _header(scope, b"content-type") or ""
    if content_type.split(";", 1)[0].strip().lower() != "multipart/form-data":
        return None
    match = _BOUNDARY.search(content_type)
    return b"--" + match.group(1).encode("latin-1") + b"--" if match else None


def _header(scope: Scope, name: bytes) -> str | None:
    for key, value in scope.get("headers", []):
        if key.lower() == name:
            return value.decode("latin-1")
    return None


def _route_label(scope: Scope, route_paths: frozenset[str]) -> str:
    """The route of a request for metrics, also for one answered before routing (a 413 by the body limit);
    "unmatched" for paths no route serves, so a scan of random URLs cannot grow the label set."""
    route = getattr(scope.get("route"), "path", None)
    if route is None and scope.get("path") in route_paths:
        route = scope["path"]  # every route of the service is a fixed path, so the path is its template
    return route or "unmatched"


async def send_error(send: Send, status: int, code: str, message: str, request_id: str | None,
                     extra_headers: list[tuple[bytes, bytes]] | None = None) -> None:
    """Answer an error from middleware (no Response object available)."""
    body = error_bytes(code, message, request_id)
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    await send({"type": "http.response.start", "status": status, "headers": headers + (extra_headers or [])})
    await send({"type": "http.response.body", "body": body})


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


class RequestContextMiddleware:
    """Request id, request metrics, a JSON 500 (trace logged, never returned) for unhandled errors, and a JSON
    503 for requests cancelled by the server's shutdown."""

    def __init__(self, app: ASGIApp, metrics: Metrics, route_paths: frozenset[str] = frozenset(),
                 in_flight: RequestsInFlight | None = None) -> None:
        self.app = app
        self.metrics = metrics
        self.route_paths = route_paths
        self.in_flight = in_flight or RequestsInFlight()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        incoming = _header(scope, b"x-request-id")
        request_id = incoming if incoming and _SAFE_REQUEST_ID.match(incoming) else uuid.uuid4().hex
        scope.setdefault("state", {})["request_id"] = request_id
        status = 500
        started = False

        async def send_with_id(message: Message) -> None:
            nonlocal status, started
            if message["type"] == "http.response.start":
                status = message["status"]
                started = True
                message["headers"] = [*message.get("headers", []), (b"x-request-id", request_id.encode())]
            await send(message)

        self.metrics.http_in_flight.inc()
        self.in_flight.count += 1
        tic = time.perf_counter()
        try:
            await self.app(scope, receive, send_with_id)
        except asyncio.CancelledError:
            # uvicorn cancels the requests still running when --shutdown-timeout-s runs out (and answers a plain
            # 500 itself): answer in the service's format while the connection is still open, then let the
            # cancellation go on. A frame already on a worker is stopped there; one still queued never runs.
            if not started:
                status = 503
                log.warning("request %s (%s %s) cut off by the shutdown: answered 503 shutting_down",
                            request_id, scope.get("method"), scope.get("path"))
                # Best effort: the client may be gone, and nothing may replace the cancellation below.
                with contextlib.suppress(Exception):
                    await send_error(
                        send, 503, "shutting_down",
                        "the service shut down before this request finished; send it again (to another replica)",
                        request_id, [(b"x-request-id", request_id.encode()), (b"retry-after", b"1"),
                                     (b"connection", b"close")],
                    )
            else:  # the answer had begun: the client sees the connection close before the end of the body
                log.warning("request %s (%s %s) cut off by the shutdown during its answer",
                            request_id, scope.get("method"), scope.get("path"))
            raise
        except Exception:
            log.exception("internal error on %s %s (request id %s)", scope.get("method"), scope.get("path"), request_id)
            status = 500
            if not started:
                await send_error(
                    send, 500, "internal_error",
                    f"internal error; the server log has the details under request id {request_id}", request_id,
                    [(b"x-request-id", request_id.encode())],
                )
        finally:
            self.metrics.http_in_flight.dec()
            self.in_flight.count -= 1
            label = _route_label(scope, self.route_paths)
            self.metrics.requests.labels(route=label, method=scope.get("method", ""), status=str(status)).inc()
            self.metrics.request_latency.labels(route=label).observe(time.perf_counter() - tic)


class BodyLimitMiddleware:
    """413 for bodies over ``max_bytes``: by Content-Length up front, else by counting received bytes.

    Also records whether a multipart/form-data body arrived whole (its close delimiter at the end)."""

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    def _message(self) -> str:
        return f"request body: larger than the limit of {self.max_bytes} bytes"

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        request_id = (scope.get("state") or {}).get("request_id")
        connection_close = [(b"connection", b"close")]
        declared = _header(scope, b"content-length")
        if declared is not None and declared.strip().isdigit() and int(declared) > self.max_bytes:
            await send_error(send, 413, "body_too_large", self._message(), request_id, connection_close)
            return

        received = 0
        exceeded = False
        app_started = False
        # python-multipart (and so Starlette) silently drops a part that the body ends in the middle of
        # (its finalize() does not check for the close delimiter): a cut-off upload would lose its last
        # part, and with --default-calib a lost calib would silently become the server's. Keep the tail
        # of the body and record whether the close delimiter arrived (service.deps.require_multipart).
        close = _multipart_close(scope)
        tail = b""

        async def counting_receive() -> Message:
            nonlocal received, exceeded, tail
            if exceeded:
                return {"type": "http.disconnect"}
            message = await receive()
            if message["type"] == "http.request":
                chunk = message.get("body", b"")
                received += len(chunk)
                if received > self.max_bytes:
                    exceeded = True  # the app sees a client disconnect and stops reading
                    return {"type": "http.disconnect"}
                if close is not None:
                    tail = (tail + chunk)[-_TAIL_BYTES:]
                    if not message.get("more_body", False):
                        complete = tail.startswith(close) or (b"\r\n" + close) in tail
                        scope.setdefault("state", {})["multipart_complete"] = complete
            return message

        async def guarded_send(message: Message) -> None:
            nonlocal app_started
            if exceeded and not app_started:
                return  # the app's answer to the "disconnect" is replaced by the 413 below
            if message["type"] == "http.response.start":
                app_started = True
            await send(message)

        try:
            await self.app(scope, counting_receive, guarded_send)
        except Exception:
            if not exceeded or app_started:
                raise
        if exceeded and not app_started:
            await send_error(send, 413, "body_too_large", self._message(), request_id, connection_close)
