"""OpenAPI ``responses=`` tables shared by the routes: each error status with the ErrorResponse body."""

from __future__ import annotations

from typing import Any

from service.schemas import ErrorResponse

_DESCRIPTIONS = {
    400: "the multipart body itself is malformed (boundary, part headers) and cannot be parsed",
    401: "a token is configured and the request has no valid `Authorization: Bearer` header",
    413: "the request body is larger than the configured limit",
    415: "the body is not multipart/form-data, or the image is not PNG/JPEG",
    422: "an input is invalid; the message names the field or part",
    500: "internal error; the answer carries only a request id, the log has the trace",
    503: "the inference queue is full, or models are not ready (see Retry-After)",
    504: "the frame did not finish within the request timeout",
}


def error_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """``{status: {"model": ErrorResponse, "description": ...}}`` for FastAPI's ``responses=``."""
    return {status: {"model": ErrorResponse, "description": _DESCRIPTIONS[status]} for status in statuses}
