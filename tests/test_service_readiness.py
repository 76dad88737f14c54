"""Readiness as an orchestrator and a client see it: every 503 ``not_ready`` says when to retry
(``Retry-After: 1``), before the models are loaded, while they warm up, and after a failed warm-up, which
``/readyz`` names instead of "warming up" for ever."""

from __future__ import annotations

import threading
from pathlib import Path

import anyio
import httpx
import pytest
from fastapi import FastAPI

from pipeline.detector import Cancellation
from service.app import create_app
from service.metrics import Metrics
from service.runtime import Runtime, load_runtime
from service.settings import Settings
from tests.test_service import AppClient, assert_error, frame, parts, tiny_models  # noqa: F401 - fixtures

PROBES = ("/readyz", "/v2/health/ready")


def assert_not_ready(response: httpx.Response, *words: str) -> None:
    """503 not_ready with the retry hint a load balancer or client reads."""
    assert_error(response, 503, "not_ready", *words)
    assert response.headers["retry-after"] == "1", response.headers


def _without_lifespan(app: FastAPI, method: str, url: str, **kwargs: object) -> httpx.Response:
    """One request to ``app`` whose lifespan has not run: no runtime loaded yet."""
    async def send() -> httpx.Response:
        transport = httpx.ASGITransport(app=app, raise_app_exceptions=False)
        async with httpx.AsyncClient(transport=transport, base_url="http://service") as client:
            return await client.request(method, url, **kwargs)
    return anyio.run(send)


def test_before_the_models_are_loaded_every_route_that_needs_them_says_retry(
    tiny_models: Path, frame: dict[str, bytes]  # noqa: F811
) -> None:
    """An app whose lifespan has not run (no runtime yet: a server started with the lifespan off, or a request
    that slips in before it): the probes, /v1/model and a frame are 503 with Retry-After, never a 500."""
    app = create_app(Settings(models=tiny_models))
    assert _without_lifespan(app, "GET", "/healthz").status_code == 200  # alive all the same
    for route in (*PROBES, "/v1/model"):
        assert_not_ready(_without_lifespan(app, "GET", route), "models are still loading")
    assert_not_ready(_without_lifespan(app, "POST", "/v1/detect", files=parts(frame)), "models are still loading")


def _held_runtime(models: Path, warm_up_error: Exception | None) -> tuple[Settings, Metrics, Runtime, threading.Event]:
    """A loaded runtime whose warm-up waits for the returned event, then raises ``warm_up_error`` (if any)."""
    settings = Settings(models=models)
    metrics = Metrics()
    runtime = load_runtime(settings, metrics)
    gate = threading.Event()
    original = runtime.detector.warm_up

    def held_warm_up(runs: int = 1, cancel: Cancellation | None = None) -> None:
        gate.wait(10)
        if warm_up_error is not None:
            raise warm_up_error
        original(runs, cancel)

    runtime.detector.warm_up = held_warm_up
    return settings, metrics, runtime, gate


def test_while_warming_up_every_503_carries_retry_after(
    tiny_models: Path, frame: dict[str, bytes]  # noqa: F811
) -> None:
    settings, metrics, runtime, gate = _held_runtime(tiny_models, None)
    with AppClient(create_app(settings, runtime=runtime, metrics=metrics)) as app_client:
        try:
            for route in PROBES:
                assert_not_ready(app_client.get(route), "warming up")
            assert_not_ready(app_client.post("/v1/detect", files=parts(frame)), "warming up")
        finally:
            gate.set()
        app_client.wait_ready()


def test_a_failed_warm_up_is_named_by_readiness_and_stays_not_ready(
    tiny_models: Path, frame: dict[str, bytes], caplog: pytest.LogCaptureFixture  # noqa: F811
) -> None:
    """An execution provider failing at its first run: /readyz says so (not "warming up" for ever), the frames
    are refused with the same reason, and the service never turns ready."""
    settings, metrics, runtime, gate = _held_runtime(tiny_models, RuntimeError("the provider fell over"))
    with AppClient(create_app(settings, runtime=runtime, metrics=metrics)) as app_client:
        gate.set()
        for _ in range(200):  # the warm-up thread records the failure; polled, not timed
            if runtime.warm_up_error is not None:
                break
            threading.Event().wait(0.05)
        for route in PROBES:
            assert_not_ready(app_client.get(route), "warm-up failed: the provider fell over")
        assert_not_ready(app_client.post("/v1/detect", files=parts(frame)), "warm-up failed: the provider fell over")
        assert "lowres3d_ready 0.0" in app_client.get("/metrics").text
    assert "warm-up failed; /readyz stays 503" in caplog.text
