"""Health probes: ``/healthz`` and ``/readyz``, and the Open Inference Protocol's ``/v2/health/*``.

Liveness answers 200 while the process serves HTTP (to GET and HEAD); readiness answers 200
only once the models are loaded and warmed up (503 with ``Retry-After``
before), so an orchestrator sends traffic only to a replica that can take it.
"""

from __future__ import annotations

from fastapi import APIRouter
from pydantic import BaseModel

from service.deps import ReadyRuntimeDep
from service.routes.responses import error_responses
from service.schemas import Health

router = APIRouter(tags=["health"])


class LiveResponse(BaseModel):
    """Open Inference Protocol liveness."""

    live: bool


class ReadyResponse(BaseModel):
    """Open Inference Protocol readiness."""

    ready: bool


# Probes answer HEAD as well as GET: load balancers and uptime checkers often send HEAD. The HEAD
# routes stay out of the schema, which would otherwise list each probe twice.
# What any route may answer besides its own: a request not received in time, a bug.
_ANY_ROUTE = error_responses(408, 500)


@router.get("/healthz", summary="Liveness: the process answers HTTP", responses=_ANY_ROUTE)
@router.head("/healthz", include_in_schema=False)
async def healthz() -> Health:
    """Always 200 while the server runs."""
    return Health(status="ok")


@router.get("/readyz", summary="Readiness: models loaded and warmed up", responses=error_responses(408, 500, 503))
@router.head("/readyz", include_in_schema=False)
async def readyz(_: ReadyRuntimeDep) -> Health:
    """200 once the models are warmed up; 503 before."""
    return Health(status="ready", ready=True)


@router.get("/v2/health/live", summary="Open Inference Protocol liveness", responses=_ANY_ROUTE)
@router.head("/v2/health/live", include_in_schema=False)
async def v2_live() -> LiveResponse:
    """Always 200 while the server runs."""
    return LiveResponse(live=True)


@router.get("/v2/health/ready", summary="Open Inference Protocol readiness",
            responses=error_responses(408, 500, 503))
@router.head("/v2/health/ready", include_in_schema=False)
async def v2_ready(_: ReadyRuntimeDep) -> ReadyResponse:
    """200 once the models are warmed up; 503 before."""
    return ReadyResponse(ready=True)
