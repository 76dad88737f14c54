"""OpenAPI ``responses=`` tables shared by the routes: each error status with the ErrorResponse body, the
headers that come with it and an example of each code it carries."""

from __future__ import annotations

from typing import Any

from service.schemas import ERROR_CODES, ErrorResponse

_DESCRIPTIONS = {
    400: "the multipart body itself is malformed (boundary, part headers) and cannot be parsed, is empty or cut off",
    401: "a token is configured and the request has no valid `Authorization: Bearer` header",
    408: "the request's head or body did not arrive within the receive timeout (the connection is closed)",
    413: "the request body is larger than the configured limit",
    415: "the body is not multipart/form-data, or the image is not PNG/JPEG",
    422: "an input is invalid; the message names the field or part",
    500: "internal error; the answer carries only a request id, the log has the trace",
    503: "the inference queue is full (refused before the body is read), too many requests are in progress, the models "
         "are not ready, or the service is shutting down (see Retry-After)",
    504: "the frame did not finish within the request timeout",
}

# One message per code, as the service words it, for the examples a client's developer reads.
_EXAMPLE_MESSAGES = {
    "bad_request": "request body: the multipart body ended before its closing boundary (a cut-off upload?); its last "
                   "part is incomplete",
    "unauthorized": "Authorization: a valid bearer token is required",
    "request_timeout": "request body: not received within 30 s (--receive-timeout-s); the connection is closed",
    "body_too_large": "request body: larger than the limit of 33554432 bytes",
    "unsupported_media_type": "Content-Type: expected multipart/form-data with parts image, points (and calib), got "
                              "application/json",
    "invalid_input": "emulate_beams: Input should be 0, 4, 8, 16 or 32",
    "internal_error": "internal error; the server log has the details under request id 5f0c8e7a9b2d4c1e8f3a6b7c9d0e1f2a",
    "overloaded": "inference queue: full (6 frames admitted); retry later",
    "not_ready": "models are warming up",
    "shutting_down": "the service is shutting down",
    "timeout": "request: the frame took longer than 30 s",
}
_EXAMPLE_ID = "5f0c8e7a9b2d4c1e8f3a6b7c9d0e1f2a"

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


def _examples(status: int) -> dict[str, dict[str, Any]]:
    """An example body for each code ``status`` carries, keyed by the code."""
    return {code: {"summary": code, "value": {"error": {"code": code, "message": _EXAMPLE_MESSAGES[code],
                                                        "request_id": _EXAMPLE_ID}}}
            for code in ERROR_CODES[status]}


def error_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """``{status: {"model": ErrorResponse, "description": ..., ...}}`` for FastAPI's ``responses=``."""
    return {
        status: {"model": ErrorResponse, "description": _DESCRIPTIONS[status],
                 "content": {"application/json": {"examples": _examples(status)}},
                 **({"headers": _HEADERS[status]} if status in _HEADERS else {})}
        for status in statuses
    }
