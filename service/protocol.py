"""uvicorn's HTTP/1.1 protocol (h11) with a deadline on a request's head and a limit on connections.

uvicorn waits for a request's head (its request line and headers) without end: a client that opens a
connection and sends half a header held it for ever. :func:`protocol_class` gives the protocol
``python -m service`` serves with: a head still incomplete ``--receive-timeout-s`` after the connection
opened (or after the previous answer on it) is answered 408 ``request_timeout`` and the connection closed
(one that sent nothing at all is closed without a word, as uvicorn's keep-alive timeout closes an idle one).
The body's own deadline is service.middleware.BodyLimitMiddleware's.

A request that arrives while more connections are open (or more requests in progress) than
:meth:`service.settings.Settings.connection_limit` is marked in ``scope["state"]`` (uvicorn's own
``limit_concurrency`` would answer it in plain text): service.middleware.ConnectionLimitMiddleware
answers it 503 ``overloaded`` in the service's format before its body is read, the probes and
``/metrics`` excepted.

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
import uuid
from typing import TYPE_CHECKING, Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from service.errors import error_bytes
from service.logs import request_id_for

if TYPE_CHECKING:
    from service.metrics import Metrics

access_log = logging.getLogger("service.access")

MALFORMED_REQUEST_MESSAGE = ("request: not valid HTTP/1.1 (a malformed request line or header, or a body framing h11 "
                             "cannot read); the connection is closed")
OVER_CONNECTION_LIMIT = "over_connection_limit"  # the scope["state"] key the protocol sets
_HEAD_START_BYTES = 16  # of a request head kept for its method label: the longest method, a space, and more
MALFORMED_BODY = "malformed_body"  # the scope["state"] key of a request whose body the protocol answered 400
UNPARSED_ROUTE = "unparsed"  # the route label of an answer given before the request's head was read
# The method label's values: HTTP's methods (RFC 9110, and PATCH); any other token a client sends is "other".
METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "DELETE", "CONNECT", "OPTIONS", "TRACE", "PATCH"})


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


def protocol_class(receive_timeout_s: float, connection_limit: int,
                   metrics: Metrics | None = None) -> type[H11Protocol]:
    """The h11 protocol with these limits, for ``uvicorn.Config(http=...)`` (uvicorn builds one per connection);
    ``metrics``: where the answers it gives itself are counted."""

    class ServiceH11Protocol(H11Protocol):
        """uvicorn's h11 protocol with a deadline on each request head and a mark for requests over the limit."""

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self._head_timer: asyncio.TimerHandle | None = None
            self._head_since = 0.0  # the loop's time the head now awaited became due (connection, or last answer)
            self._head_start = b""  # its first bytes, for the method label of an answer to it (h11 drops them)
            inner = self.app

            async def app(scope: Any, receive: Any, send: Any) -> None:
                # Counted as uvicorn counts for limit_concurrency: this connection and this request included.
                if len(self.connections) > connection_limit or len(self.tasks) > connection_limit:
                    scope.setdefault("state", {})[OVER_CONNECTION_LIMIT] = connection_limit
                await inner(scope, receive, send)

            self.app = app

        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            self._arm_head_deadline()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            self._arm_head_deadline()  # the next request's head on a kept-alive connection

        def data_received(self, data: bytes) -> None:
            if len(self._head_start) < _HEAD_START_BYTES and (self.cycle is None or self.cycle.response_complete):
                self._head_start += data[: _HEAD_START_BYTES - len(self._head_start)]
            super().data_received(data)

        def connection_lost(self, exc: Exception | None) -> None:
            self._cancel_head_deadline()
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
                client_id = next((value for key, value in cycle.scope["headers"] if key == b"x-request-id"), None)
                request_id = request_state.get("request_id") or request_id_for(
                    client_id.decode("latin-1") if client_id is not None else None)
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
            self.transport.close()

    return ServiceH11Protocol
