"""The FastAPI application: :func:`create_app` wires settings, runtime, routes, middleware and errors.

Start-up (the lifespan): load the model directory (sha256 checked; a bad file
stops the start), start the inference pool, then warm the networks up in the
background; ``/readyz`` answers 503 until that is done. Shutdown: after the
server has let in-flight requests finish, the pool drains and stops, and the
Detectors release their sessions and stage threads.
"""

from __future__ import annotations

import asyncio
import functools
import logging
from collections.abc import AsyncIterator, Callable, Iterable
from contextlib import AbstractAsyncContextManager, asynccontextmanager
from typing import Any

from fastapi import APIRouter, Depends, FastAPI
from starlette.routing import BaseRoute

from service.deps import bearer_scheme, require_token
from service.errors import install_error_handlers
from service.metrics import Metrics
from service.middleware import (
    AdmissionMiddleware,
    AuthMiddleware,
    BodyLimitMiddleware,
    ConnectionLimitMiddleware,
    CORSMiddleware,
    Linger,
    RequestContextMiddleware,
    RequestsInFlight,
)
from service.openapi import install_schema, operation_id
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
back in the LiDAR frame (KITTI's velodyne frame: x forward, y left, z up; metres, radians).

Every error is JSON `{"error": {"code", "message", "request_id"}}`: `code` is stable, the
message names the field at fault. Every answer carries `X-Request-ID` (send your own to
correlate). A full queue answers 503 with `Retry-After` (the service sheds load with 503).
"""


def create_app(settings: Settings, runtime: Runtime | None = None, metrics: Metrics | None = None) -> FastAPI:
    """Build the app. ``runtime``: models already loaded (``python -m service`` loads them before
    uvicorn starts, so a bad model directory fails fast); None loads them in the lifespan."""
    metrics = metrics or Metrics()
    in_flight = RequestsInFlight()
    app = FastAPI(
        title="lowres3d detection service",
        version="0.1.0",
        description=DESCRIPTION,
        lifespan=_lifespan(settings, runtime, metrics, in_flight),
        generate_unique_id_function=operation_id,
    )
    app.state.settings = settings
    app.state.metrics = metrics
    app.state.runtime = None
    install_error_handlers(app)
    _include_routes(app, settings)
    _add_middleware(app, settings, metrics, in_flight)
    install_schema(app, bearer_scheme(), functools.partial(_camera_model, app))
    return app


def _lifespan(settings: Settings, runtime: Runtime | None, metrics: Metrics,
              in_flight: RequestsInFlight) -> Callable[[FastAPI], AbstractAsyncContextManager[None]]:
    """The app's lifespan: at start-up the models (``runtime``, or loaded now), then their warm-up in the
    background; at shutdown the warm-up stopped, the pool drained, the cut-off requests' answers let out, and
    the models closed last."""

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
            # Last, once nothing answers from the models any more (/v1/model reads their sessions' providers).
            await asyncio.to_thread(loaded.close)

    return lifespan


_PROTECTED_ROUTERS = (detect.router, model.router)  # /v1/*: behind the token, when one is set
_OPEN_ROUTERS = (health.router, metrics_route.router)  # the probes and /metrics


def _include_routes(app: FastAPI, settings: Settings) -> None:
    """The service's routes (the protected ones with the token's dependency when a token is set), and each
    route path's methods in ``app.state.route_methods``."""
    # /v1/* needs the bearer token when one is configured (and only then does the schema declare it):
    # AuthMiddleware checks it before the body is read, the dependency declares it in the schema (and checks
    # again); probes and metrics stay open for orchestrators and scrapers.
    auth = [Depends(require_token)] if settings.token is not None else []
    for router in _PROTECTED_ROUTERS:
        app.include_router(router, dependencies=auth)
    for router in _OPEN_ROUTERS:
        app.include_router(router)
    app.state.route_methods = route_methods(_routes_of(*_PROTECTED_ROUTERS, *_OPEN_ROUTERS)
                                            + list(app.routes))


def _add_middleware(app: FastAPI, settings: Settings, metrics: Metrics, in_flight: RequestsInFlight) -> None:
    """The middleware stack, added innermost first (Starlette wraps in reverse: added last, outermost)."""
    # Every route is a fixed path: the metrics label requests answered before routing (413s) by it, and
    # those to FastAPI's own routes (/openapi.json, /docs, /redoc), which do not name their route in the scope.
    route_paths = frozenset(paths_of(_routes_of(*_PROTECTED_ROUTERS, *_OPEN_ROUTERS))
                            + paths_of(app.routes))  # FastAPI's own
    open_paths = frozenset(paths_of(_routes_of(*_OPEN_ROUTERS)))
    detect_paths = frozenset(paths_of(detect.router.routes))
    # Added last = outermost. The request context wraps everything (but CORS, when configured: a 500 must carry
    # its headers too, or a browser's script cannot read it), so that every answer is counted and carries an id;
    # inside it, each layer answers before the body is read when it can: the connection limit (503), the
    # token (401), a declared size over the limit (413), no place in the pool (503). The pool's place is taken
    # last, for a request nothing else refused.
    # Those early answers read and drop the body the client sends anyway before they close the connection.
    linger = Linger.of(settings.max_body_bytes, settings.receive_timeout_s)
    app.add_middleware(AdmissionMiddleware, runtime=lambda: app.state.runtime, detect_paths=detect_paths,
                       linger=linger)
    app.add_middleware(BodyLimitMiddleware, max_bytes=settings.max_body_bytes,
                       receive_timeout_s=settings.receive_timeout_s)
    if settings.token is not None:
        app.add_middleware(AuthMiddleware, token=settings.token, linger=linger)
    app.add_middleware(ConnectionLimitMiddleware, open_paths=open_paths, linger=linger)
    app.add_middleware(RequestContextMiddleware, metrics=metrics, route_paths=route_paths, in_flight=in_flight,
                       model_id=lambda: served_model_id(app), quiet_paths=open_paths)
    if settings.cors_origins:  # off by default: only a dashboard in a browser on another origin needs it
        app.add_middleware(CORSMiddleware, origins=settings.cors_origin_list())


def _routes_of(*routers: APIRouter) -> list[BaseRoute]:
    """The routes of ``routers``, in order."""
    return [route for router in routers for route in router.routes]


def _camera_model(app: FastAPI) -> bool:
    """Whether the model needs the image; True before it loads (the shipped models are camera models)."""
    loaded: Runtime | None = app.state.runtime
    return loaded is None or loaded.detector.two_stage


def served_model_id(app: FastAPI) -> str | None:
    """The id of the model the app serves (its manifest's sha256), None before it is loaded."""
    loaded: Runtime | None = app.state.runtime
    return loaded.identity.id if loaded is not None else None


def paths_of(routes: Iterable[object]) -> list[str]:
    """The paths of ``routes`` (Starlette types a router's routes as BaseRoute, which need not have one)."""
    return [path for route in routes if isinstance(path := getattr(route, "path", None), str)]


def route_methods(routes: list[Any]) -> dict[str, frozenset[str]]:
    """Each route path with the methods all its routes answer (a probe's GET and HEAD are two routes)."""
    methods: dict[str, set[str]] = {}
    for route in routes:
        path, answered = getattr(route, "path", None), getattr(route, "methods", None)
        if isinstance(path, str) and answered:
            methods.setdefault(path, set()).update(answered)
    return {path: frozenset(answered) for path, answered in methods.items()}
