"""uvicorn's HTTP/1.1 protocol (h11) with deadlines on a request's head and on sending, and limits on connections.

uvicorn waits for a request's head (its request line and headers) without end: a client that opens a
connection and sends half a header held it for ever. :func:`protocol_class` gives the protocol
``python -m service`` serves with: a head still incomplete ``--receive-timeout-s`` after the connection
opened (or after the previous answer on it) is answered 408 ``request_timeout`` and the connection closed
(one that sent nothing at all is closed without a word, as uvicorn's keep-alive timeout closes an idle one).
The body's own deadline is service.middleware.BodyLimitMiddleware's.

A request that arrives while more requests are in progress (their heads received, their answers not all
sent) than :meth:`service.settings.Settings.connection_limit` is marked in ``scope["state"]`` (uvicorn's own
``limit_concurrency`` would answer it in plain text): service.middleware.ConnectionLimitMiddleware
answers it 503 ``overloaded`` in the service's format before its body is read, the probes and
``/metrics`` excepted. Connections that have sent nothing do not count there (a client opening sockets
would have locked every client out); open connections are bounded apart, by
:meth:`service.settings.Settings.socket_limit` (``--max-connections``, by default the open-file limit less a
reserve): a connection accepted beyond it closes the one idle the longest (no request in progress, nothing
left to send), so that idle sockets, a balancer's spares or a client holding sockets keep out neither new
clients nor the probes; only when none is idle is the new one closed at once, with a WARNING the first time
and then at most once a minute.

An answer whose sending stalls (the client takes none of it: neither the transport's buffer nor the socket's
send queue shrinks) for ``--send-timeout-s`` is cut off and its connection closed; a slow client that reads
some goes on, as with nginx's ``send_timeout``. Its access line, written when the answer was handed over, says
200: the count of cut answers is the metric's. The connections closed without an answer, at the head deadline,
the send deadline or the cap, are counted in ``lowres3d_connections_closed_total{reason}``, not logged one by
one (a client could flood the log).

A request framed twice, with a ``Content-Length`` and a ``Transfer-Encoding`` (read as chunked), is answered
as usual and its connection then closed (``Connection: close``), as RFC 9112 §6.1 asks: a proxy in front
may have read its body by the other header, and what follows on the connection cannot be trusted.

A request h11 cannot parse (a malformed request line or header) is answered 400 ``bad_request`` in the
service's JSON error shape with an ``X-Request-ID``, where uvicorn answers it in plain text. So is a body
whose framing h11 cannot read (a malformed chunk), under the request's own id; its access line is then the
middleware's, with that 400. The answers given before a request's head was read (that 400 and the 408) get
an access line of their own and are counted in ``lowres3d_http_requests`` under the route ``unparsed``:
every request the service answers has one line and one count.
"""

from __future__ import annotations

import asyncio
import logging
import struct
import uuid
from typing import TYPE_CHECKING, Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from service.errors import error_bytes
from service.logs import request_id_for

if TYPE_CHECKING:
    from service.metrics import Metrics

try:  # the socket's send queue (SIOCOUTQ is TIOCOUTQ's number): Linux, and Unix systems that share it
    import fcntl
    import termios

    _OUTQ: int | None = termios.TIOCOUTQ
except (ImportError, AttributeError):  # Windows, or a system without it: the transport's buffer alone
    _OUTQ = None

access_log = logging.getLogger("service.access")
log = logging.getLogger(__name__)

MALFORMED_REQUEST_MESSAGE = ("request: not valid HTTP/1.1 (a malformed request line or header, or a body framing h11 "
                             "cannot read); the connection is closed")
OVER_CONNECTION_LIMIT = "over_connection_limit"  # the scope["state"] key the protocol sets
_HEAD_START_BYTES = 16  # of a request head kept for its method label: the longest method, a space, and more
MALFORMED_BODY = "malformed_body"  # the scope["state"] key of a request whose body the protocol answered 400
UNPARSED_ROUTE = "unparsed"  # the route label of an answer given before the request's head was read
# The method label's values: HTTP's methods (RFC 9110, and PATCH); any other token a client sends is "other".
METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "DELETE", "CONNECT", "OPTIONS", "TRACE", "PATCH"})
OVER_SOCKET_LIMIT_WARNING_S = 60.0  # the least time between two warnings about connections closed at the cap


def head_method(head: bytes) -> str:
    """The method label of a request head not (or not wholly) parsed: its first token when that is one of HTTP's
    methods followed by a space, else "other"."""
    token, space, _ = head.partition(b" ")
    method = token.decode("latin-1")
    return method if space and method in METHODS else "other"


def peer_text(client: tuple[str, int] | list | None) -> str | None:
    """``host:port`` of a peer (``[::1]:port`` for IPv6), None when the server does not say."""
    if not client:
        return None
    host, port = client[0], client[1]
    return f"[{host}]:{port}" if ":" in str(host) else f"{host}:{port}"


def log_head_answer(metrics: Metrics | None, request_id: str, status: int, code: str, method: str,
                    client: str | None, waited_s: float, why: str) -> None:
    """The access line and the count of an answer given before a request's head was read, with the fields of
    service.middleware's access lines (no path or model: none was read or reached)."""
    duration_ms = round(waited_s * 1e3, 1)
    if metrics is not None:
        metrics.requests.labels(route=UNPARSED_ROUTE, method=method, status=str(status)).inc()
        metrics.request_latency.labels(route=UNPARSED_ROUTE).observe(waited_s)
    fields: dict[str, object] = {
        "request_id": request_id, "method": method, "path": None, "route": UNPARSED_ROUTE, "status": status,
        "error_code": code, "duration_ms": duration_ms, "client": client, "model_id": None, "warning_codes": [],
    }
    access_log.info("request %s: %s %s answered %d %s in %.0f ms (client %s; %s)", request_id, method,
                    UNPARSED_ROUTE, status, code, duration_ms, client or "unknown", why, extra=fields)


def count_closed(metrics: Metrics | None, reason: str) -> None:
    """Count a connection closed without an answer (one of service.metrics.CONNECTION_CLOSE_REASONS)."""
    if metrics is not None:
        metrics.connections_closed.labels(reason=reason).inc()


def framed_twice(headers: list[tuple[bytes, bytes]]) -> bool:
    """Whether a request head (uvicorn's lower-cased headers) carries both a Content-Length and a
    Transfer-Encoding: h11 reads the body as chunked, a proxy in front may have read it by its length."""
    names = {name for name, _ in headers}
    return b"content-length" in names and b"transfer-encoding" in names


def closing_send(send: Any) -> Any:
    """``send`` with ``Connection: close`` added to the answer's head (unless it says so already)."""

    async def send_closing(message: Any) -> None:
        if message["type"] == "http.response.start":
            headers = list(message.get("headers", []))
            if not any(bytes(name).lower() == b"connection" and bytes(value).lower() == b"close"
                       for name, value in headers):
                message = {**message, "headers": [*headers, (b"connection", b"close")]}
        await send(message)

    return send_closing


def unsent_bytes(transport: asyncio.BaseTransport) -> int:
    """Bytes of the answers not yet taken by the client: those in the transport's buffer and, on Linux, those in
    the socket's send queue (SIOCOUTQ: sent and not acknowledged, or not sent). The kernel's queue alone shows a
    slow reader's progress: the transport hands it more only once much of a large send buffer is free."""
    size = transport.get_write_buffer_size() if isinstance(transport, asyncio.WriteTransport) else 0
    sock = transport.get_extra_info("socket")
    if _OUTQ is None or sock is None:
        return size
    try:
        return size + struct.unpack("i", fcntl.ioctl(sock.fileno(), _OUTQ, b"\0" * 4))[0]
    except (OSError, ValueError):  # a socket closed meanwhile, or one the ioctl does not apply to
        return size


class SocketLimitWarning:
    """The WARNING about new connections closed at the socket cap with no idle one to close in their place: the
    first, then at most one a minute with how many since (a line per connection would let a client flood the
    log)."""

    def __init__(self, socket_limit: int) -> None:
        self.socket_limit = socket_limit
        self.last: float | None = None  # the loop's time of the last line
        self.unsaid = 0  # new connections closed since that line

    def closed_one(self, now: float) -> None:
        """One more new connection closed at the cap; a line when the first, or a minute after the last."""
        self.unsaid += 1
        if self.last is not None and now - self.last < OVER_SOCKET_LIMIT_WARNING_S:
            return
        since = "" if self.last is None else f" ({self.unsaid} since the last such line, {now - self.last:.0f} s ago)"
        log.warning("connections: %d open, the cap (--max-connections), none idle: a new connection was closed at "
                    "once%s; lowres3d_connections_closed_total{reason=\"over_limit\"} counts them",
                    self.socket_limit, since)
        self.last, self.unsaid = now, 0


def protocol_class(receive_timeout_s: float, connection_limit: int, metrics: Metrics | None = None,
                   socket_limit: int | None = None, send_timeout_s: float | None = None) -> type[H11Protocol]:
    """The h11 protocol with these limits, for ``uvicorn.Config(http=...)`` (uvicorn builds one per connection);
    ``metrics``: where the answers it gives itself, and the connections it closes, are counted.
    ``socket_limit``: open connections at most (None: none); ``send_timeout_s``: how long sending may stall
    (None: ``receive_timeout_s``)."""
    send_timeout = receive_timeout_s if send_timeout_s is None else send_timeout_s
    over_limit_warning = SocketLimitWarning(socket_limit or 0)  # shared by the connections, as the limit is

    class ServiceH11Protocol(H11Protocol):
        """uvicorn's h11 protocol with deadlines on each request head and on sending, a mark for requests over
        the limit, and a cap on open connections."""

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self._head_timer: asyncio.TimerHandle | None = None
            self._head_since = 0.0  # the loop's time the head now awaited became due (connection, or last answer)
            self._head_start = b""  # its first bytes, for the method label of an answer to it (h11 drops them)
            self._send_timer: asyncio.TimerHandle | None = None
            self._send_left = 0  # bytes waiting to be sent when the send deadline was last armed
            inner = self.app

            async def app(scope: Any, receive: Any, send: Any) -> None:
                if scope["type"] == "http" and framed_twice(scope["headers"]):
                    cycle = self.cycle  # this request's: h11 holds a pipelined head until its answer is sent
                    if cycle is not None and cycle.scope is scope:
                        cycle.keep_alive = False  # uvicorn closes the connection once the answer is sent
                    send = closing_send(send)
                # Requests in progress, this one included (uvicorn's tasks: one per request until answered).
                if len(self.tasks) > connection_limit:
                    scope.setdefault("state", {})[OVER_CONNECTION_LIMIT] = connection_limit
                await inner(scope, receive, send)

            self.app = app

        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            if socket_limit is not None and len(self.connections) > socket_limit:
                # Room is made by closing the connection idle the longest (a balancer's spare, a client between
                # requests, or one that never sent a byte), so that neither idle sockets nor a client holding
                # them keep new clients and the probes out; with none idle, the new one is closed at once.
                idle = [c for c in self.connections
                        if c is not self and isinstance(c, ServiceH11Protocol) and c.waiting_for_head()]
                if idle:
                    min(idle, key=lambda c: c._head_since).transport.close()
                    count_closed(metrics, "idle_evicted")
                else:
                    transport.close()  # nothing read or written: closed at once, its descriptor freed
                    count_closed(metrics, "over_limit")
                    over_limit_warning.closed_one(self.loop.time())
                    return
            # Any byte left waiting to be sent pauses writing, which arms the send deadline: with asyncio's
            # high-water mark (64 KiB) the rest of an answer under it, left after a close, would wait for ever.
            transport.set_write_buffer_limits(high=0)
            self._arm_head_deadline()

        def waiting_for_head(self) -> bool:
            """Whether the connection is idle: open, no request being answered, nothing left to send."""
            return (not self.transport.is_closing() and (self.cycle is None or self.cycle.response_complete)
                    and self._send_timer is None and self.transport.get_write_buffer_size() == 0)

        def pause_writing(self) -> None:
            super().pause_writing()
            self._arm_send_deadline()

        def resume_writing(self) -> None:
            self._cancel_send_deadline()
            super().resume_writing()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            self._arm_head_deadline()  # the next request's head on a kept-alive connection

        def data_received(self, data: bytes) -> None:
            if len(self._head_start) < _HEAD_START_BYTES and (self.cycle is None or self.cycle.response_complete):
                self._head_start += data[: _HEAD_START_BYTES - len(self._head_start)]
            super().data_received(data)

        def connection_lost(self, exc: Exception | None) -> None:
            self._cancel_head_deadline()
            self._cancel_send_deadline()
            super().connection_lost(exc)

        def send_400_response(self, msg: str) -> None:
            """uvicorn's answer to a request h11 cannot parse, in the service's error shape (uvicorn's is plain
            text, which a client's error handling would not parse). A malformed body of a request being handled
            is answered under that request's id, or, when its answer has begun (an early error reading the rest
            of the body), the connection is closed after what was sent."""
            cycle = self.cycle
            request_state = None
            if cycle is not None and not cycle.response_complete:  # the body of a request the app is handling
                if cycle.response_started:  # h11 cannot start another answer: end the connection here (the
                    self.transport.close()  # access line keeps the answer that had begun)
                    return
                request_state = cycle.scope.setdefault("state", {})
                request_state[MALFORMED_BODY] = True  # its access line: this 400, not a client that left
            if request_state is None:
                request_id = uuid.uuid4().hex
            else:  # the id the middleware gives the request, which may not have run yet (the body came with the head)
                request_id = request_state.get("request_id") or self._request_id_ahead(cycle.scope)
            body = error_bytes("bad_request", MALFORMED_REQUEST_MESSAGE, request_id)
            headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                       (b"x-request-id", request_id.encode()), (b"connection", b"close")]
            for event in (h11.Response(status_code=400, headers=headers, reason=b"Bad Request"), h11.Data(data=body),
                          h11.EndOfMessage()):
                self.transport.write(self.conn.send(event))
            self.transport.close()
            if request_state is None:  # a head: no request reached the app, so no middleware logs it
                log_head_answer(metrics, request_id, 400, "bad_request", head_method(self._head_start),
                                peer_text(self.client), self.loop.time() - self._head_since,
                                "a request line or header HTTP/1.1 does not allow")

        @staticmethod
        def _request_id_ahead(scope: Any) -> str:
            """The id of a request the middleware has not seen yet, made here and left where it will take it: in
            the state, and as the request's X-Request-ID when the client sent none, or one not safe to echo (the
            middleware makes its own from that header: the answer's id and the access line's would differ)."""
            client_id = next((value for key, value in scope["headers"] if key == b"x-request-id"), None)
            request_id = request_id_for(client_id.decode("latin-1") if client_id is not None else None)
            scope.setdefault("state", {})["request_id"] = request_id
            if client_id is None or client_id.decode("latin-1") != request_id:
                scope["headers"] = [*((key, value) for key, value in scope["headers"] if key != b"x-request-id"),
                                    (b"x-request-id", request_id.encode())]
            return request_id

        def _cancel_send_deadline(self) -> None:
            if self._send_timer is not None:
                self._send_timer.cancel()
                self._send_timer = None

        def _arm_send_deadline(self) -> None:
            self._cancel_send_deadline()
            self._send_left = unsent_bytes(self.transport)
            self._send_timer = self.loop.call_later(send_timeout, self._send_overdue)

        def _send_overdue(self) -> None:
            self._send_timer = None
            if unsent_bytes(self.transport) < self._send_left:
                self._arm_send_deadline()  # the client reads, slowly: its answer goes on
                return
            # Not close(): it would wait for the buffer to drain, which it never does. uvicorn then sees the
            # client gone; the request's task, waiting to send, ends.
            self.transport.abort()
            count_closed(metrics, "send_timeout")

        def _cancel_head_deadline(self) -> None:
            if self._head_timer is not None:
                self._head_timer.cancel()
                self._head_timer = None

        def _arm_head_deadline(self) -> None:
            self._cancel_head_deadline()
            if not self.transport.is_closing():
                self._head_since = self.loop.time()
                self._head_start = b""
                # The cycle now on: a head that arrives in time starts a new one.
                self._head_timer = self.loop.call_later(receive_timeout_s, self._head_overdue, self.cycle)

        def _head_overdue(self, cycle: object) -> None:
            self._head_timer = None
            if self.transport.is_closing() or self.cycle is not cycle:
                return  # closed already, or a request's head came in time
            if self.cycle is not None and not self.cycle.response_complete:
                return  # a request still being answered (a pipelined head waits behind it)
            pending, _ = self.conn.trailing_data
            if pending:  # part of a head: say why the connection closes
                request_id = uuid.uuid4().hex
                message = (f"request head: not received within {receive_timeout_s:g} s (--receive-timeout-s); "
                           "the connection is closed")
                body = error_bytes("request_timeout", message, request_id)
                head = (f"HTTP/1.1 408 Request Timeout\r\ncontent-type: application/json\r\n"
                        f"content-length: {len(body)}\r\nx-request-id: {request_id}\r\nconnection: close\r\n\r\n")
                self.transport.write(head.encode("latin-1") + body)
                log_head_answer(metrics, request_id, 408, "request_timeout", head_method(self._head_start),
                                peer_text(self.client), self.loop.time() - self._head_since,
                                f"its head not received within {receive_timeout_s:g} s, --receive-timeout-s")
            else:  # nothing sent: no answer, and no line (a client could open connections by the thousand)
                count_closed(metrics, "head_timeout")
            self.transport.close()

    return ServiceH11Protocol
