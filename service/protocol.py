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
service's JSON error shape with an ``X-Request-ID``, where uvicorn answers it in plain text.
"""

from __future__ import annotations

import asyncio
import logging
import uuid
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from service.errors import error_bytes

log = logging.getLogger(__name__)

MALFORMED_REQUEST_MESSAGE = ("request: not valid HTTP/1.1 (a malformed request line or header, or a body framing h11 "
                             "cannot read); the connection is closed")
OVER_CONNECTION_LIMIT = "over_connection_limit"  # the scope["state"] key the protocol sets


def protocol_class(receive_timeout_s: float, connection_limit: int) -> type[H11Protocol]:
    """The h11 protocol with these limits, for ``uvicorn.Config(http=...)`` (uvicorn builds one per connection)."""

    class ServiceH11Protocol(H11Protocol):
        """uvicorn's h11 protocol with a deadline on each request head and a mark for requests over the limit."""

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self._head_timer: asyncio.TimerHandle | None = None
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

        def connection_lost(self, exc: Exception | None) -> None:
            self._cancel_head_deadline()
            super().connection_lost(exc)

        def send_400_response(self, msg: str) -> None:
            """uvicorn's answer to a request h11 cannot parse, in the service's error shape (uvicorn's is plain
            text, which a client's error handling would not parse)."""
            request_id = uuid.uuid4().hex
            body = error_bytes("bad_request", MALFORMED_REQUEST_MESSAGE, request_id)
            headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                       (b"x-request-id", request_id.encode()), (b"connection", b"close")]
            for event in (h11.Response(status_code=400, headers=headers, reason=b"Bad Request"), h11.Data(data=body),
                          h11.EndOfMessage()):
                self.transport.write(self.conn.send(event))
            self.transport.close()

        def _cancel_head_deadline(self) -> None:
            if self._head_timer is not None:
                self._head_timer.cancel()
                self._head_timer = None

        def _arm_head_deadline(self) -> None:
            self._cancel_head_deadline()
            if not self.transport.is_closing():
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
                client = f"{self.client[0]}:{self.client[1]}" if self.client else "a client"
                log.info("request %s: its head from %s was not received within %g s: answered 408, connection "
                         "closed", request_id, client, receive_timeout_s, extra={"request_id": request_id})
            self.transport.close()

    return ServiceH11Protocol
