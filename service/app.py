"""The FastAPI application: :func:`create_app` wires settings, runtime, routes, middleware and errors.

Start-up (the lifespan): load the model directory (sha256 checked; a bad file
stops the start), start the inference pool, then warm the networks up in the
background; ``/readyz`` answers 503 until that is done. Shutdown: after the
server has let in-flight requests finish, the pool drains and stops.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import Depends, FastAPI

from service.deps import require_token
from service.errors import install_error_handlers
from service.metrics import Metrics
from service.middleware import (
    AdmissionMiddleware,
    AuthMiddleware,
    BodyLimitMiddleware,
    ConnectionLimitMiddleware,
    RequestContextMiddleware,
    RequestsInFlight,
)
from service.routes import detect, health, model
from service.routes import metrics as metrics_route
from service.runtime import Runtime, load_runtime
from service.settings import Settings

log = logging.getLogger(__name__)

# How long the shutdown waits, after the pool has stopped, for cut-off requests to send their 503s (they take
# milliseconds).
SHUTDOWN_ANSWERS_S = 2.0

DESCRIPTION = """\
3D car detection from a 16-line LiDAR scan plus a camera image (depth completion →
pseudo point cloud → BEV → PIXOR), on ONNX Runtime.

Send a frame as multipart/form-data to `POST /v1/detect`: `image` (PNG/JPEG), `points`
(KITTI velodyne `.bin`) and `calib` (KITTI `calib.txt`, optional when the server has a
default). A LiDAR-only model (`two_stage` false in `GET /v1/model`) needs `points` alone,
and the image and a calibration only for `format=kitti` and the camera picture. Boxes come
back in the LiDAR frame (x forward, y left, z up).

Every error is JSON `{"error": {"code", "message", "request_id"}}`; the message names the
field at fault. A full queue answers 503 with `Retry-After`.
"""


def create_app(settings: Settings, runtime: Runtime | None = None, metrics: Metrics | None = None) -> FastAPI:
    """Build the app. ``runtime``: models already loaded (``python -m service`` loads them before
    uvicorn starts, so a bad model directory fails fast); None loads them in the lifespan."""
    metrics = metrics or Metrics()
    in_flight = RequestsInFlight()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        loaded = runtime if runtime is not None else await asyncio.to_thread(load_runtime, settings, metrics)
        app.state.runtime = loaded
        warm_up = asyncio.create_task(asyncio.to_thread(loaded.warm_up, settings.warmup_runs))
        warm_up.add_done_callback(lambda _: metrics.ready.set(1 if loaded.ready.is_set() else 0))
        try:
            yield
        finally:
            loaded.stopping.cancel()  # a warm-up still running stops at its next network node
            await warm_up
            metrics.ready.set(0)
            await asyncio.to_thread(loaded.pool.shutdown)
            log.info("inference pool stopped")
            # Requests uvicorn cut off at the end of the grace answer 503 when the loop next runs them: let them.
            if not await in_flight.drained(SHUTDOWN_ANSWERS_S):
                log.warning("%d request(s) still unanswered at exit", in_flight.count)

    app = FastAPI(
        title="lowres3d detection service",
        version="0.1.0",
        description=DESCRIPTION,
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.metrics = metrics
    app.state.runtime = None
    install_error_handlers(app)
    # /v1/* needs the bearer token when one is configured (and only then does the schema declare it):
    # AuthMiddleware checks it before the body is read, the dependency declares it in the schema (and checks
    # again); probes and metrics stay open for orchestrators and scrapers.
    auth = [Depends(require_token)] if settings.token is not None else []
    protected, open_to_all = (detect.router, model.router), (health.router, metrics_route.router)
    for router in protected:
        app.include_router(router, dependencies=auth)
    for router in open_to_all:
        app.include_router(router)
    # Every route is a fixed path: the metrics label requests answered before routing (413s) by it, and
    # those to FastAPI's own routes (/openapi.json, /docs, /redoc), which do not name their route in the scope.
    route_paths = frozenset(
        [route.path for router in (*protected, *open_to_all) for route in router.routes]
        + [path for route in app.routes if isinstance(path := getattr(route, "path", None), str)]  # FastAPI's own
    )
    open_paths = frozenset(route.path for router in open_to_all for route in router.routes)
    detect_paths = frozenset(route.path for route in detect.router.routes)
    # Added last = outermost. The request context wraps everything, so that every answer is counted and carries
    # an id; inside it, each layer answers before the body is read when it can: the connection limit (503), the
    # token (401), a declared size over the limit (413), no place in the pool (503). The pool's place is taken
    # last, for a request nothing else refused.
    app.add_middleware(AdmissionMiddleware, runtime=lambda: app.state.runtime, detect_paths=detect_paths)
    app.add_middleware(BodyLimitMiddleware, max_bytes=settings.max_body_bytes,
                       receive_timeout_s=settings.receive_timeout_s)
    if settings.token is not None:
        app.add_middleware(AuthMiddleware, token=settings.token)
    app.add_middleware(ConnectionLimitMiddleware, open_paths=open_paths)
    app.add_middleware(RequestContextMiddleware, metrics=metrics, route_paths=route_paths, in_flight=in_flight)
    _schema_follows_the_model(app)
    return app


def _schema_follows_the_model(app: FastAPI) -> None:
    """Make ``/openapi.json`` mark the detection routes' ``image`` part required for a camera model.

    The routes declare it optional, as a LiDAR-only model takes a frame without it, so the schema (generated
    once by FastAPI, and before the models load when the lifespan loads them) is adjusted to the loaded model
    each time it is served: required unless the model is LiDAR-only.
    """
    generate = app.openapi

    def openapi() -> dict[str, Any]:
        schema = generate()
        runtime: Runtime | None = app.state.runtime
        camera = runtime is None or runtime.detector.two_stage  # the shipped models are camera models
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
