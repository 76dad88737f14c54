"""``GET /metrics``: Prometheus text exposition of the app's metrics (open, like the health probes)."""

from __future__ import annotations

import asyncio

from fastapi import APIRouter
from fastapi.responses import Response

from service.deps import MetricsDep
from service.routes.responses import error_responses

router = APIRouter(tags=["metrics"])


@router.get(
    "/metrics",
    summary="Prometheus metrics",
    response_class=Response,
    responses={200: {"description": "Prometheus text exposition format",
                     "content": {"text/plain": {"schema": {"type": "string"}}}},
               **error_responses(408, 500)},
)
async def metrics(metrics: MetricsDep) -> Response:
    """Request counts by route and status, latency histograms per route and per stage, queue depth,
    in-flight frames and requests, readiness, process memory (`process_resident_memory_bytes`)."""
    # On a worker thread: the text grows with the series, and the event loop must keep answering meanwhile.
    return Response(await asyncio.to_thread(metrics.render), media_type=metrics.content_type)
