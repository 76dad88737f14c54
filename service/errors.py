"""Error answers: every failure is JSON ``{"error": {"code", "message", "request_id"}}`` with its status.

Client mistakes (:class:`pipeline.errors.InputError`, validation errors, HTTP
errors) say what is wrong and name the field; internal errors answer only a
request id and the trace goes to the log (see :mod:`service.middleware`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from pipeline.errors import InputError

_HTTP_CODES = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    406: "not_acceptable",
    408: "request_timeout",
    413: "body_too_large",
    415: "unsupported_media_type",
    422: "invalid_input",
    500: "internal_error",
    503: "unavailable",
    504: "timeout",
}


class ServiceError(Exception):
    """An error answer: HTTP status, a stable machine-readable code, a message naming the field."""

    def __init__(self, status: int, code: str, message: str, headers: Mapping[str, str] | None = None) -> None:
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message
        self.headers = dict(headers or {})


def request_id_of(scope: Mapping[str, Any]) -> str | None:
    """The id :class:`service.middleware.RequestContextMiddleware` gave this request."""
    state = scope.get("state") or {}
    return state.get("request_id")


def error_payload(code: str, message: str, request_id: str | None) -> dict[str, Any]:
    """The JSON body of every error answer."""
    return {"error": {"code": code, "message": message, "request_id": request_id}}


def error_bytes(code: str, message: str, request_id: str | None) -> bytes:
    """:func:`error_payload` encoded, for middleware that answers without a Response object."""
    return json.dumps(error_payload(code, message, request_id)).encode()


def error_response(
    status: int, code: str, message: str, request: Request, headers: Mapping[str, str] | None = None
) -> JSONResponse:
    """A JSONResponse carrying :func:`error_payload`."""
    return JSONResponse(
        error_payload(code, message, request_id_of(request.scope)), status_code=status, headers=dict(headers or {})
    )


def _field_name(loc: Sequence[Any]) -> str:
    """``("body", "image")`` → ``image``; ``("query", "score_threshold")`` → ``score_threshold``."""
    parts = [str(p) for p in loc if p not in ("body", "query", "path", "header", "cookie")]
    return ".".join(parts) or "request"


def validation_message(errors: Sequence[Mapping[str, Any]]) -> str:
    """One line per problem, each starting with the field it is about."""
    return "; ".join(f"{_field_name(e.get('loc', ()))}: {e.get('msg', 'invalid')}" for e in errors)


async def _service_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, ServiceError)
    return error_response(exc.status, exc.code, exc.message, request, exc.headers)


async def _input_error(request: Request, exc: Exception) -> JSONResponse:
    return error_response(422, "invalid_input", str(exc), request)


async def _validation_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    return error_response(422, "invalid_input", validation_message(exc.errors()), request)


async def _http_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    code = _HTTP_CODES.get(exc.status_code, f"http_{exc.status_code}")
    return error_response(exc.status_code, code, str(exc.detail), request, exc.headers)


def install_error_handlers(app: FastAPI) -> None:
    """Route every known exception type to its JSON error answer."""
    app.add_exception_handler(ServiceError, _service_error)
    app.add_exception_handler(InputError, _input_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
