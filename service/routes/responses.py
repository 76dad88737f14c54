"""OpenAPI ``responses=`` tables shared by the routes: each error status with the ErrorResponse body."""

from __future__ import annotations

from typing import Any

from service.schemas import ErrorResponse

_DESCRIPTIONS = {
    400: "the multipart body itself is malformed (boundary, part headers) and cannot be parsed",
    401: "a token is configured and the request has no valid `Authorization: Bearer` header",
    408: "the request body did not arrive within the receive timeout (the connection is closed)",
    413: "the request body is larger than the configured limit",
    415: "the body is not multipart/form-data, or the image is not PNG/JPEG",
    422: "an input is invalid; the message names the field or part",
    500: "internal error; the answer carries only a request id, the log has the trace",
    503: "the inference queue is full (refused before the body is read), too many connections are open, the models "
         "are not ready, or the service is shutting down (see Retry-After)",
    504: "the frame did not finish within the request timeout",
}

# The headers that come with a status, every time it is answered (service.deps, service.routes.detect,
# service.middleware).
_HEADERS: dict[int, dict[str, dict[str, Any]]] = {
    401: {"WWW-Authenticate": {
        "description": "the scheme to authenticate with: `Bearer realm=\"lowres3d\"`",
        "required": True, "schema": {"type": "string"},
    }},
    503: {"Retry-After": {
        "description": "seconds to wait before sending the request again (the queue ahead divided among the "
                       "workers when the queue is full; 1 otherwise)",
        "required": True, "schema": {"type": "integer", "minimum": 1},
    }},
}


def error_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """``{status: {"model": ErrorResponse, "description": ..., "headers": ...}}`` for FastAPI's ``responses=``."""
    return {
        status: {"model": ErrorResponse, "description": _DESCRIPTIONS[status],
                 **({"headers": _HEADERS[status]} if status in _HEADERS else {})}
        for status in statuses
    }
