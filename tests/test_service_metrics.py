"""The values in ``/metrics``, not only the names: what a dashboard graphs and alerts on over hours of service.

A fresh app in-process over ASGI (as ``test_service.py``), with the real tiny models and KITTI frame 000006, so
that every count is known; the pool's gauges read while a real job holds the only worker.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from pathlib import Path

import pytest

from service.metrics import OTHER_WARNING_CODE, Metrics
from tests.test_service import AppClient, assert_error, frame, parts, service, tiny_models  # noqa: F401 - fixtures


def _value(text: str, series: str) -> float:
    """The value of one series (name and labels exactly as exposed) in a Prometheus text exposition."""
    match = re.search(rf"^{re.escape(series)} (\S+)$", text, re.MULTILINE)
    assert match is not None, f"{series} not in /metrics"
    return float(match.group(1))


def _wait_depth(client: AppClient, depth: tuple[int, int]) -> None:
    pool = client.app.state.runtime.pool
    deadline = time.monotonic() + 10
    while pool.depth != depth:
        assert time.monotonic() < deadline, pool.depth
        time.sleep(0.01)


def test_request_counts_latencies_and_in_flight_add_up(tiny_models: Path, frame: dict[str, bytes]) -> None:  # noqa: F811
    """Three frames: three latency observations under their route, the per-stage histograms in seconds (the
    frames' own ``total`` in milliseconds / 1000), and no request left "in flight" but the scrape itself."""
    with service(tiny_models) as app_client:
        totals_ms = []
        for _ in range(3):
            response = app_client.post("/v1/detect", files=parts(frame))
            assert response.status_code == 200, response.text
            totals_ms.append(response.json()["timings_ms"]["total"])
        assert_error(app_client.post("/v1/detect", files=parts(frame, points=b"\x00" * 100)), 422, "invalid_input")
        text = app_client.get("/metrics").text
        route = 'route="/v1/detect"'
        assert _value(text, f'lowres3d_http_requests_total{{method="POST",{route},status="200"}}') == 3
        assert _value(text, f"lowres3d_http_request_duration_seconds_count{{{route}}}") == 4  # the 422 too
        assert _value(text, "lowres3d_http_requests_in_flight") == 1  # this scrape; every answered request left
        assert _value(text, 'lowres3d_stage_duration_seconds_count{stage="total"}') == 3
        assert _value(text, 'lowres3d_stage_duration_seconds_sum{stage="total"}') == pytest.approx(
            sum(totals_ms) / 1e3, abs=1e-5)  # the answers round to a microsecond
        assert _value(text, "lowres3d_inference_queue_depth") == 0 and _value(text, "lowres3d_inference_in_flight") == 0


def test_the_pool_gauges_while_a_frame_runs_and_one_waits(tiny_models: Path) -> None:  # noqa: F811
    """One frame on the only worker, one more place taken in the queue: in flight 1, waiting 1; then both 0."""
    with service(tiny_models, workers=1, queue_size=2) as app_client:
        pool = app_client.app.state.runtime.pool
        release = threading.Event()
        held = app_client.portal.start_task_soon(pool.run, lambda _d, _c: release.wait(30), 60)
        waiting = None
        try:
            _wait_depth(app_client, (0, 1))
            text = app_client.get("/metrics").text
            assert _value(text, "lowres3d_inference_in_flight") == 1
            assert _value(text, "lowres3d_inference_queue_depth") == 0  # running is not waiting
            waiting = pool.reserve()  # a frame whose upload is still arriving
            text = app_client.get("/metrics").text
            assert _value(text, "lowres3d_inference_in_flight") == 1
            assert _value(text, "lowres3d_inference_queue_depth") == 1
        finally:
            if waiting is not None:
                waiting.release()
            release.set()
            held.result(30)
        _wait_depth(app_client, (0, 0))
        text = app_client.get("/metrics").text
        assert _value(text, "lowres3d_inference_in_flight") == 0 and _value(text, "lowres3d_inference_queue_depth") == 0


def test_a_frame_past_its_deadline_is_counted_as_rejected_for_timeout(
    tiny_models: Path, frame: dict[str, bytes]  # noqa: F811
) -> None:
    """A 504 is counted in ``lowres3d_inference_rejected{reason="timeout"}`` (a full queue under queue_full)."""
    with service(tiny_models, workers=1, queue_size=1, request_timeout_s=0.2) as app_client:
        pool = app_client.app.state.runtime.pool
        release = threading.Event()
        held = app_client.portal.start_task_soon(pool.run, lambda _d, _c: release.wait(30), 60)
        try:
            _wait_depth(app_client, (0, 1))
            assert_error(app_client.post("/v1/detect", files=parts(frame)), 504, "timeout", "0.2 s")
        finally:
            release.set()
            held.result(30)
        text = app_client.get("/metrics").text
        assert _value(text, 'lowres3d_inference_rejected_total{reason="timeout"}') == 1
        assert 'reason="queue_full"' not in text


def test_warning_codes_are_counted_from_zero_and_an_unknown_one_as_other() -> None:
    """Every known code's series is there at 0 before any frame (rate() needs a start), and a code the metrics do
    not know adds to ``other``, not a series of its own."""
    metrics = Metrics()
    text = metrics.render().decode()
    assert _value(text, 'lowres3d_frame_warnings_total{code="nonfinite_dropped"}') == 0
    assert _value(text, f'lowres3d_frame_warnings_total{{code="{OTHER_WARNING_CODE}"}}') == 0
    metrics.count_warnings(["nonfinite_dropped", "no_such_code", "nonfinite_dropped"])
    text = metrics.render().decode()
    assert _value(text, 'lowres3d_frame_warnings_total{code="nonfinite_dropped"}') == 2
    assert _value(text, f'lowres3d_frame_warnings_total{{code="{OTHER_WARNING_CODE}"}}') == 1
    assert "no_such_code" not in text


def test_a_stop_after_answered_requests_waits_for_none_of_them(
    tiny_models: Path, frame: dict[str, bytes], caplog: pytest.LogCaptureFixture  # noqa: F811
) -> None:
    """The shutdown waits (up to 2 s) for requests still in flight to answer: every request answered, a refused
    one too, has left the count, so the stop neither waits nor warns of requests "still unanswered"."""
    with caplog.at_level(logging.WARNING, logger="service.app"):
        with service(tiny_models) as app_client:
            assert app_client.post("/v1/detect", files=parts(frame)).status_code == 200
            assert_error(app_client.post("/v1/detect", files=parts(frame, points=b"")), 422, "invalid_input")
            assert app_client.get("/healthz").status_code == 200
            stopping = time.monotonic()
        assert time.monotonic() - stopping < 1.5
    assert not [r for r in caplog.records if "still unanswered" in r.getMessage()]
