"""The inference pool as a client meets it: how long a 503 says to wait, and which refusals need no worker.

The real pool (service/pool.py) with the real tiny models, its jobs real callables that take a known time;
the app in-process over ASGI as ``test_service.py`` does.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import anyio
import pytest

from pipeline.detector import Cancellation, Detector
from service.metrics import Metrics
from service.pool import InferencePool, Reservation
from tests.test_service import AppClient, assert_error, frame, parts, service, tiny_models  # noqa: F401 - fixtures


@pytest.fixture
def pool(tiny_models: Path) -> Iterator[InferencePool]:  # noqa: F811
    """Two workers, ten places in the queue."""
    pool = InferencePool([Detector(tiny_models)], workers=2, queue_size=10, metrics=Metrics())
    yield pool
    pool.shutdown()


def _timed_job(seconds: float, taken: list[float]) -> Callable[[Detector, Cancellation], None]:
    """A job that sleeps ``seconds`` and records how long it took (the pool's own measure is a hair longer)."""

    def job(_detector: Detector, _cancel: Cancellation) -> None:
        tic = time.perf_counter()
        time.sleep(seconds)
        taken.append(time.perf_counter() - tic)

    return job


def test_retry_after_is_the_queue_ahead_divided_among_the_workers(pool: InferencePool) -> None:
    """Retry-After (docs: "the queue ahead divided among the workers") = ceil(mean job time × frames admitted /
    workers), the mean a moving average (4/5 the old, 1/5 the newest), and at least 1 s, also before any job
    has run. The number of places taken is chosen so that the estimate lies between two whole seconds."""
    assert pool.retry_after_s() == 1  # nothing measured yet: not 0, which would mean "retry at once"
    taken: list[float] = []

    async def two_jobs() -> None:
        await pool.run(_timed_job(0.5, taken), timeout_s=30)
        await pool.run(_timed_job(0.0, taken), timeout_s=30)

    anyio.run(two_jobs)
    mean = 0.8 * taken[0] + 0.2 * taken[1]
    # At least 2 s, so that neither "the last job alone" (~0 s) nor 1 s can pass for it, and not near a whole second.
    places = next(n for n in range(1, pool.capacity + 1)
                  if mean * n / pool.workers >= 1.25 and 0.25 <= (mean * n / pool.workers) % 1 <= 0.75)
    reservations = [pool.reserve() for _ in range(places)]
    try:
        assert pool.retry_after_s() == math.ceil(mean * places / pool.workers)
    finally:
        for reservation in reservations:
            reservation.release()
    assert pool.depth == (0, 0)


def test_a_full_queue_answers_the_pools_own_retry_after(tiny_models: Path, frame: dict[str, bytes]) -> None:  # noqa: F811
    """The 503 of a full pool carries the pool's estimate, not a fixed second."""
    with service(tiny_models, workers=1, queue_size=20) as app_client:
        pool = app_client.app.state.runtime.pool
        app_client.portal.call(pool.run, _timed_job(0.2, []), 30)  # a job time to go by
        reservations: list[Reservation] = [pool.reserve() for _ in range(pool.capacity)]
        try:
            expected = pool.retry_after_s()
            assert expected >= 2, expected  # 21 frames ahead of one worker: more than the 1 s floor
            response = app_client.post("/v1/detect", files=parts(frame))
            assert_error(response, 503, "overloaded", "inference queue: full (21 frames admitted)")
            assert response.headers["retry-after"] == str(expected)
        finally:
            for reservation in reservations:
                reservation.release()


def test_a_frame_that_can_never_succeed_is_refused_without_waiting_for_a_worker(
    tiny_models: Path, frame: dict[str, bytes]  # noqa: F811
) -> None:
    """The checks that need no decoding run on the event loop: with the only worker busy, a scan whose size is no
    whole number of points is answered 422 at once, not after a wait for the worker (here: its deadline, 504)."""
    with service(tiny_models, workers=1, queue_size=1, request_timeout_s=2) as app_client:
        pool = app_client.app.state.runtime.pool
        release = threading.Event()
        held = app_client.portal.start_task_soon(pool.run, lambda _d, _c: release.wait(30), 60)
        try:
            deadline = time.monotonic() + 10
            while pool.depth != (0, 1):  # the worker is busy, the queue's place free
                assert time.monotonic() < deadline
                time.sleep(0.01)
            response = app_client.post("/v1/detect", files=parts(frame, points=frame["points"][:-6]))
            assert_error(response, 422, "invalid_input", "points", "multiple of 16")
            assert not release.is_set() and pool.depth == (0, 1)  # the worker was never free meanwhile
        finally:
            release.set()
            held.result(30)
