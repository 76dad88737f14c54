"""Error answers: every failure is JSON ``{"error": {"code", "message", "request_id"}}`` with its status.

Client mistakes (:class:`pipeline.errors.InputError`, validation errors, HTTP
errors) say what is wrong and name the field; internal errors answer only a
request id and the trace goes to the log (see :mod:`service.middleware`).
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping, Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.routing import APIRoute
from starlette.exceptions import HTTPException as StarletteHTTPException

from pipeline.errors import InputError

# The code of an HTTPException, by status, each one of the documented table (service.schemas.ERROR_CODES).
# Starlette and FastAPI raise 400 (a body they cannot parse), 404 and 405 here; not 403 (the bearer scheme has
# auto_error=False) nor 406 (nothing negotiates content). The other entries give the service's own statuses their
# codes; a status without one would be answered as http_<status>.
_HTTP_CODES = {
    400: "bad_request",
    401: "unauthorized",
    404: "not_found",
    405: "method_not_allowed",
    408: "request_timeout",
    413: "body_too_large",
    415: "unsupported_media_type",
    422: "invalid_input",
    500: "internal_error",
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


_SHOWN_CHARS = 200  # of a client's path or method echoed in a message: the log and the client need no more


def allowed_methods(request: Request, exc: StarletteHTTPException) -> list[str]:
    """The methods the routes at this request's path answer, for a 405's ``Allow``.

    From ``app.state.route_methods`` (service.app: every route is a fixed path), as the framework names only
    the first route it found: a probe served for GET and HEAD by two routes answered ``Allow: HEAD`` to a POST.
    """
    methods = getattr(request.app.state, "route_methods", {}).get(request.scope.get("path"))
    if methods:
        return sorted(methods)
    return [m.strip() for m in (exc.headers or {}).get("Allow", "").split(",") if m.strip()]


# Starlette's words for a multipart part without a filename, a form field, past its size limit (1 MiB; Starlette
# 0.38, FastAPI 0.112.2's, has none): raised while that part streams in, by a parser that does not say which part.
_OVERSIZED_FIELD = re.compile(r"Part exceeded maximum size of (\d+)KB")


def _part_names(request: Request) -> str:
    """The multipart parts the request's route takes (``image, points, calib``), as service.deps.check_parts
    names them."""
    route = request.scope.get("route")
    names = [field.alias for field in route.dependant.body_params] if isinstance(route, APIRoute) else []
    return ", ".join(names) or "image, points, calib"


def _oversized_field_message(request: Request, limit_kb: str) -> str:
    """What a client that sent a large file as a text field (no ``filename=``; ``filename*=`` alone, which
    multipart/form-data forbids, is none either) is told: every part of the service is a file."""
    return (f"request body: a part sent as a form field (without filename=) is larger than {limit_kb} KB; "
            f"send the parts {_part_names(request)} as files, each with a filename (curl -F points=@FILE)")


def _http_message(request: Request, exc: StarletteHTTPException, allow: list[str]) -> str:
    """What the framework's own HTTP errors say, naming what was at fault (Starlette says "Not Found")."""
    asked = f"{request.method[:_SHOWN_CHARS]} {request.url.path[:_SHOWN_CHARS]}"
    if exc.status_code == 404:
        return f"{asked}: no such route (the API is under /v1; /openapi.json lists every route)"
    if exc.status_code == 405:
        return f"{asked}: method not allowed; this route answers {', '.join(allow)}"
    if exc.status_code == 400:  # FastAPI and Starlette raise it only when the body cannot be parsed
        oversized = _OVERSIZED_FIELD.match(str(exc.detail))
        if oversized:
            return _oversized_field_message(request, oversized.group(1))
        return f"request body: not parsable as multipart/form-data ({exc.detail})"
    return str(exc.detail)


async def _http_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    code = _HTTP_CODES.get(exc.status_code, f"http_{exc.status_code}")
    headers = dict(exc.headers or {})
    allow = allowed_methods(request, exc) if exc.status_code == 405 else []
    if allow:
        headers["Allow"] = ", ".join(allow)
    return error_response(exc.status_code, code, _http_message(request, exc, allow), request, headers)


def install_error_handlers(app: FastAPI) -> None:
    """Route every known exception type to its JSON error answer."""
    app.add_exception_handler(ServiceError, _service_error)
    app.add_exception_handler(InputError, _input_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
