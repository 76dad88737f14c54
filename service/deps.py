"""FastAPI dependencies: settings, runtime and metrics of the app, bearer-token auth, multipart check,
unknown query parameters.

Use them as ``Annotated`` types in route signatures (``settings: SettingsDep``).
"""

from __future__ import annotations

import difflib
import hmac
from typing import Annotated, Any

from fastapi import Depends, Request
from fastapi.dependencies.models import Dependant
from fastapi.routing import APIRoute
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from fastapi.security.utils import get_authorization_scheme_param
from pydantic import SecretStr

from service.errors import ServiceError, request_id_of
from service.metrics import Metrics
from service.runtime import Runtime
from service.settings import Settings

_bearer = HTTPBearer(
    auto_error=False,
    description="Required on /v1/* when the server has a token configured (LOWRES3D_TOKEN).",
)


def bearer_scheme() -> dict[str, Any]:
    """The bearer scheme as the OpenAPI document declares it (``components.securitySchemes``)."""
    return _bearer.model.model_dump(mode="json", by_alias=True, exclude_none=True)


def get_settings(request: Request) -> Settings:
    """The Settings the app was created with."""
    return request.app.state.settings


def get_metrics(request: Request) -> Metrics:
    """The app's metrics."""
    return request.app.state.metrics


def not_ready_reason(runtime: Runtime | None) -> str | None:
    """Why the runtime cannot take a frame yet (the message of the 503 ``not_ready``); None once it can."""
    if runtime is None:
        return "models are still loading"
    if not runtime.ready.is_set():
        return runtime.warm_up_error or "models are warming up"
    return None


def get_runtime(request: Request) -> Runtime:
    """The loaded runtime; 503 while it is still loading."""
    runtime: Runtime | None = getattr(request.app.state, "runtime", None)
    if runtime is None:
        raise ServiceError(503, "not_ready", "models are still loading", {"Retry-After": "1"})
    return runtime


def get_ready_runtime(runtime: Annotated[Runtime, Depends(get_runtime)]) -> Runtime:
    """The runtime once warmed up; 503 before."""
    reason = not_ready_reason(runtime)
    if reason is not None:
        raise ServiceError(503, "not_ready", reason, {"Retry-After": "1"})
    return runtime


def get_request_id(request: Request) -> str:
    """The id given to this request by service.middleware.RequestContextMiddleware."""
    return request_id_of(request.scope) or ""


SettingsDep = Annotated[Settings, Depends(get_settings)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]
RuntimeDep = Annotated[Runtime, Depends(get_runtime)]
ReadyRuntimeDep = Annotated[Runtime, Depends(get_ready_runtime)]
RequestIdDep = Annotated[str, Depends(get_request_id)]


UNAUTHORIZED_MESSAGE = "Authorization: a valid bearer token is required"
WWW_AUTHENTICATE = 'Bearer realm="lowres3d"'


def token_accepted(token: SecretStr, authorization: str | None) -> bool:
    """Whether an ``Authorization`` header value is ``Bearer <token>`` (the scheme in any case, as HTTPBearer
    reads it). The comparison is constant-time (hmac.compare_digest) so response timing does not reveal how
    much of a guess was right."""
    scheme, credentials = get_authorization_scheme_param(authorization)
    given = credentials.encode() if scheme.lower() == "bearer" else b""
    return bool(given) and hmac.compare_digest(given, token.get_secret_value().encode())


def require_token(
    settings: SettingsDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> None:
    """401 unless the request carries ``Authorization: Bearer <token>`` (when a token is configured).

    service.middleware.AuthMiddleware checks the same before the body is read; this dependency declares the
    scheme in the OpenAPI schema and checks again for an app served without that middleware.
    """
    if settings.token is None:
        return
    header = f"{credentials.scheme} {credentials.credentials}" if credentials is not None else None
    if not token_accepted(settings.token, header):
        raise ServiceError(401, "unauthorized", UNAUTHORIZED_MESSAGE, {"WWW-Authenticate": WWW_AUTHENTICATE})


def require_multipart(request: Request) -> None:
    """415 unless the body is multipart/form-data; 400 when it ended before its close delimiter."""
    content_type = request.headers.get("content-type", "")
    if content_type.split(";", 1)[0].strip().lower() != "multipart/form-data":
        shown = content_type.split(";", 1)[0].strip() or "none"
        raise ServiceError(
            415, "unsupported_media_type",
            f"Content-Type: expected multipart/form-data with parts image, points (and calib), got {shown}",
        )
    # Recorded by service.middleware.BodyLimitMiddleware as the body arrived.
    body = (request.scope.get("state") or {}).get("multipart_body")
    if body == "empty":
        raise ServiceError(
            400, "bad_request",
            "request body: empty (0 bytes); send multipart/form-data with the parts image, points (and calib)",
        )
    if body == "cut_off":
        raise ServiceError(
            400, "bad_request",
            "request body: the multipart body ended before its closing boundary (a cut-off upload?); "
            "its last part is incomplete",
        )


async def check_parts(request: Request) -> None:
    """422 for a multipart part the route does not declare, a part sent twice, or a text field where a file
    is expected: FastAPI would ignore the first (``-F calibration=@…`` would silently run on the server's
    default calibration), keep the last of the second, and answer the third with a Python type name."""
    route = request.scope.get("route")
    if not isinstance(route, APIRoute):
        return
    accepted = [field.alias for field in route.dependant.body_params]
    form = await request.form()  # parsed and cached by FastAPI before the dependencies run
    names = [name for name, _ in form.multi_items()]
    problems = []
    for name in dict.fromkeys(names):
        if name not in accepted:
            problems.append(unknown_clause(name, accepted, "part"))
        elif names.count(name) > 1:
            problems.append(f"{name}: sent {names.count(name)} times; send each part once")
        elif isinstance(form[name], str):
            problems.append(f"{name}: sent as a text field; send it as a file (curl -F {name}=@FILE)")
    if problems:
        raise ServiceError(422, "invalid_input", "; ".join(problems) + f"; accepted parts: {', '.join(accepted)}")


def declared_query_params(dependant: Dependant) -> list[str]:
    """The query parameter names (aliases) a route declares, its own and then its dependencies' (the
    order of the OpenAPI schema)."""
    names = [field.alias for field in dependant.query_params]
    for sub in dependant.dependencies:
        names += [name for name in declared_query_params(sub) if name not in names]
    return names


def unknown_clause(name: str, accepted: list[str], what: str) -> str:
    """``"<name>: unknown <what> (did you mean <closest>?)"``, the hint only when an accepted name is close."""
    close = difflib.get_close_matches(name, accepted, n=1, cutoff=0.6)
    hint = f" (did you mean {close[0]}?)" if close else ""
    return f"{name or repr(name)}: unknown {what}{hint}"  # '' for "?=1", not a bare colon


def unknown_query_message(unknown: list[str], accepted: list[str]) -> str:
    """One clause per unknown parameter (with the closest accepted name when there is one), then the accepted ones."""
    clauses = [unknown_clause(name, accepted, "query parameter") for name in unknown]
    return "; ".join(clauses) + f"; accepted query parameters: {', '.join(accepted) or 'none'}"


def reject_unknown_query(request: Request) -> None:
    """422 naming any query parameter the route does not declare.

    FastAPI ignores undeclared parameters, so a typo (``emulate_beam=16``) would
    silently run with the default (no ``emulate_beams``: the scan as sent, not thinned); the accepted names
    come from the route's own declarations, so they cannot drift from the schema.
    """
    route = request.scope.get("route")
    if not isinstance(route, APIRoute):
        return
    accepted = declared_query_params(route.dependant)
    unknown = list(dict.fromkeys(name for name in request.query_params if name not in accepted))
    if unknown:
        raise ServiceError(422, "invalid_input", unknown_query_message(unknown, accepted))
    # A repeated name would silently run with its last value (?emulate_beams=16&emulate_beams=8 → 8 beams).
    repeated = [name for name in dict.fromkeys(request.query_params) if len(request.query_params.getlist(name)) > 1]
    if repeated:
        raise ServiceError(422, "invalid_input", "; ".join(f"{name}: given more than once" for name in repeated))
