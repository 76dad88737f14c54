"""``/openapi.json`` as a client's code generator needs it: what FastAPI's generated document leaves out.

FastAPI describes the routes, their parameters and bodies; this adds what the middleware does on every route
(the ``X-Request-ID`` a client may send and every answer carries), declares the bearer scheme whether or not
this server has a token (a client generated from a server without one can still send it to one with one),
names the operations after their functions (``detect``, not ``detect_v1_detect_post``), and marks the
``image`` part required or not as the loaded model needs it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from fastapi import FastAPI
from fastapi.routing import APIRoute

REQUEST_ID = "X-Request-ID"
REQUEST_ID_RULE = "1–64 characters of `[A-Za-z0-9._-]`"
BEARER = "HTTPBearer"  # FastAPI's name for the scheme of service.deps's HTTPBearer

_REQUEST_ID_PARAMETER = {
    "name": REQUEST_ID, "in": "header", "required": False, "schema": {"type": "string"},
    "description": f"your own id for this request ({REQUEST_ID_RULE}), echoed in the answer's {REQUEST_ID} "
                   "and error body and named in the server log; any other value is replaced by one the server makes",
}
_REQUEST_ID_HEADER = {
    "required": True, "schema": {"type": "string"},
    "description": "this request's id: the client's own (when valid) or one the server made; every error body and "
                   "log line about the request carries it",
}


def operation_id(route: APIRoute) -> str:
    """The operation's id in the schema, and so a generated client's method name: the route function's name."""
    return route.name


def complete_schema(schema: dict[str, Any], bearer: dict[str, Any]) -> None:
    """Add to FastAPI's document (in place) what every route has: the request id, the optional bearer token."""
    schemes = schema.setdefault("components", {}).setdefault("securitySchemes", {})
    schemes.setdefault(BEARER, bearer)
    for path, operations in schema.get("paths", {}).items():
        for operation in operations.values():
            operation.setdefault("parameters", []).append(_REQUEST_ID_PARAMETER)
            for response in operation.get("responses", {}).values():
                response.setdefault("headers", {})[REQUEST_ID] = _REQUEST_ID_HEADER
            if path.startswith("/v1/") and "security" not in operation:
                # No token on this server: the token is optional ({} is "no authentication"), and a client
                # generated from this document can still send one.
                operation["security"] = [{}, {BEARER: []}]


def install_schema(app: FastAPI, bearer: dict[str, Any], camera_model: Callable[[], bool]) -> None:
    """Serve :func:`complete_schema`'s document, its ``image`` part required as ``camera_model()`` says.

    FastAPI generates the document once; the image's requirement is set each time it is served, as the models
    may load after the first request for it (the lifespan loads them).
    """
    generate = app.openapi

    def openapi() -> dict[str, Any]:
        first = app.openapi_schema is None
        schema = generate()
        if first:
            complete_schema(schema, bearer)
        camera = camera_model()
        for path, operations in schema.get("paths", {}).items():
            if not path.startswith("/v1/detect"):
                continue
            content = operations.get("post", {}).get("requestBody", {}).get("content", {})
            ref = content.get("multipart/form-data", {}).get("schema", {}).get("$ref", "")
            body = schema.get("components", {}).get("schemas", {}).get(ref.rsplit("/", 1)[-1])
            if body is not None and "image" in body.get("properties", {}):
                _set_image_required(body, camera)
        return schema

    app.openapi = openapi  # type: ignore[method-assign]


def _set_image_required(body: dict[str, Any], required: bool) -> None:
    """The ``image`` property of a multipart body schema: a required file, or an optional one (file or null)."""
    image = body["properties"]["image"]
    if "anyOf" in image:
        file_schema = next(branch for branch in image.pop("anyOf") if branch.get("type") != "null")
    else:
        file_schema = {key: image.pop(key) for key in list(image) if key not in ("title", "description")}
    names = [name for name in body.get("required", []) if name != "image"]
    if required:
        image.update(file_schema)
        body["required"] = ["image", *names]
    else:
        image["anyOf"] = [file_schema, {"type": "null"}]
        body["required"] = names
