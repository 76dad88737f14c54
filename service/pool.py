"""A bounded inference pool: worker threads off the event loop, a counted queue, a deadline per job.

At most ``workers`` frames run at once and at most ``queue_size`` more wait;
a job that finds the pool full is refused at once (:class:`PoolFull`, the
service answers 503 with ``Retry-After``), so a burst never becomes an
unbounded backlog. A job that misses its deadline raises :class:`PoolTimeout`
(504); if it is still waiting it never starts, if it is already running it is
told to stop (its :class:`~pipeline.detector.Cancellation`: ONNX Runtime ends
the network run at its next node) and keeps its slot until it has, so the
bound on concurrent work always holds. A request cancelled while its job runs
(the service's shutdown grace ran out, or its client left) stops its job the same way.

A request takes its place with :meth:`InferencePool.reserve` before its upload is read
(service.middleware.AdmissionMiddleware), so that a full pool refuses it before a byte of
the body is held: the uploads held at once are bounded by ``workers + queue_size``.

Sessions: ``detectors`` holds either one Detector shared by every worker
(ONNX Runtime sessions are thread-safe) or one per worker thread.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Generic, TypeVar

from pipeline.detector import Cancellation, Detector, RunCancelled
from service.metrics import Metrics

log = logging.getLogger(__name__)

T = TypeVar("T")

# The warm-up frames meet at a barrier, one per worker thread; a thread that never comes is a bug, not a wait.
WARM_UP_BARRIER_S = 60.0


class PoolFull(Exception):
    """Every worker is busy and the queue is full."""

    def __init__(self, retry_after_s: int) -> None:
        super().__init__(f"the inference queue is full; retry in {retry_after_s} s")
        self.retry_after_s = retry_after_s


class PoolTimeout(Exception):
    """The job did not finish before its deadline."""


class PoolClosed(Exception):
    """The pool is shutting down and takes no new jobs."""


class Reservation:
    """A place in the pool taken before the frame is known (its upload still to be read).

    :meth:`InferencePool.run` hands it to the frame's job, whose end frees it; a request that ends before
    (a 4xx, a client gone, a deadline) frees it with :meth:`release`.
    """

    def __init__(self, pool: InferencePool) -> None:
        self._pool = pool
        self._held = True  # False once released or handed to a job

    def take(self) -> None:
        """Hand the place to a job (its end frees it); RuntimeError if it was already given up."""
        if not self._held:
            raise RuntimeError("the pool reservation was already released or used")
        self._held = False

    def release(self) -> None:
        """Give the place back unless a job took it; safe to call more than once."""
        if self._held:
            self._held = False
            self._pool._release(None)


@dataclass(frozen=True)
class JobResult(Generic[T]):
    """What a job returned, and how long it waited for a worker (ms)."""

    value: T
    queue_wait_ms: float


class InferencePool:
    """Runs ``job(detector, cancel)`` callables on worker threads with admission control.

    A job passes ``cancel`` to :meth:`Detector.detect`, so that a frame past its deadline stops.
    """

    def __init__(self, detectors: Sequence[Detector], workers: int, queue_size: int, metrics: Metrics) -> None:
        if not detectors:
            raise ValueError("detectors: at least one Detector is needed")
        if len(detectors) not in (1, workers):
            raise ValueError(f"detectors: give 1 (shared) or {workers} (one per worker), got {len(detectors)}")
        self.detectors = list(detectors)
        self.workers = workers
        self.queue_size = queue_size
        self.capacity = workers + queue_size
        self._metrics = metrics
        self._lock = threading.Lock()
        self._admitted = 0  # waiting + running
        self._running = 0
        self._mean_job_s = 0.0  # exponential moving average of job durations
        self._next_detector = itertools.count()
        self._local = threading.local()
        self._executor = ThreadPoolExecutor(
            max_workers=workers, thread_name_prefix="lowres3d-infer", initializer=self._init_thread
        )
        self._closed = False

    # ------------------------------------------------------------------ worker side
    def _init_thread(self) -> None:
        index = next(self._next_detector) % len(self.detectors)
        self._local.detector = self.detectors[index]

    def _update_gauges(self) -> None:
        self._metrics.queue_depth.set(self._admitted - self._running)
        self._metrics.in_flight.set(self._running)

    def _run(self, job: Callable[[Detector, Cancellation], T], cancel: Cancellation,
             admitted_at: float, request_id: str | None) -> JobResult[T]:
        started = time.perf_counter()
        with self._lock:
            self._running += 1
            self._update_gauges()
        try:
            return JobResult(job(self._local.detector, cancel), (started - admitted_at) * 1e3)
        except RunCancelled as exc:
            self._metrics.stopped.inc()
            # The request id ties this line to the request's own (its 504, its client gone, the shutdown's 503).
            log.info("request %s: its frame stopped on its worker after %.0f ms, nobody waiting for it any more "
                     "(deadline passed, client gone or shutdown): %s",
                     request_id or "-", (time.perf_counter() - started) * 1e3, exc, extra={"request_id": request_id})
            raise
        finally:
            elapsed = time.perf_counter() - started
            with self._lock:
                self._running -= 1
                self._mean_job_s = elapsed if self._mean_job_s == 0 else 0.8 * self._mean_job_s + 0.2 * elapsed
                self._update_gauges()

    def _release(self, _: Future | None) -> None:
        with self._lock:
            self._admitted -= 1
            self._update_gauges()

    # ------------------------------------------------------------------ event-loop side
    @property
    def depth(self) -> tuple[int, int]:
        """(waiting, running) right now."""
        with self._lock:
            return self._admitted - self._running, self._running

    def retry_after_s(self) -> int:
        """Seconds until a slot is likely free: the queue ahead divided among the workers."""
        with self._lock:
            estimate = self._mean_job_s * self._admitted / self.workers
        return max(1, math.ceil(estimate))

    def _admit(self) -> None:
        """Take a place: PoolClosed when shutting down, PoolFull (counted) when every place is taken."""
        with self._lock:
            if self._closed:
                raise PoolClosed("the service is shutting down")
            full = self._admitted >= self.capacity
            if not full:
                self._admitted += 1
                self._update_gauges()
        if full:
            self._metrics.rejected.labels(reason="queue_full").inc()
            raise PoolFull(self.retry_after_s())

    def reserve(self) -> Reservation:
        """A place for a frame whose upload is still to be read: PoolFull or PoolClosed at once when there is none."""
        self._admit()
        return Reservation(self)

    async def run(self, job: Callable[[Detector, Cancellation], T], timeout_s: float,
                  reservation: Reservation | None = None, request_id: str | None = None) -> JobResult[T]:
        """Run ``job`` on a worker; PoolFull at once when over capacity, PoolTimeout after ``timeout_s``
        (the job stopped: it never starts, or its frame is cancelled).

        reservation: the place :meth:`reserve` took for this frame (no admission then); request_id: names
        the request in the log line of a frame stopped on its worker."""
        if reservation is None:
            self._admit()
        else:
            reservation.take()
        cancel = Cancellation()
        try:
            future = self._executor.submit(self._run, job, cancel, time.perf_counter(), request_id)
        except RuntimeError:  # the executor was shut down between the check and the submit
            self._release(None)
            raise PoolClosed("the service is shutting down") from None
        future.add_done_callback(self._release)
        try:
            return await asyncio.wait_for(asyncio.wrap_future(future), timeout_s)
        # Both names: on Python 3.10 (the Jetson image) asyncio.wait_for raises asyncio.TimeoutError, a class of
        # its own there (the builtin only from 3.11 on); catching the builtin alone made a deadline a 500.
        except (TimeoutError, asyncio.TimeoutError):
            self._stop(future, cancel)
            self._metrics.rejected.labels(reason="timeout").inc()
            raise PoolTimeout(f"the frame took longer than {timeout_s:g} s") from None
        except asyncio.CancelledError:  # the request was cancelled: nobody waits for the frame any more
            self._stop(future, cancel)
            raise

    @staticmethod
    def _stop(future: Future, cancel: Cancellation) -> None:
        """A job nobody waits for: drop it while it waits, stop its frame if it runs."""
        if not future.cancel():  # succeeds only while the job is still waiting
            cancel.cancel()

    def warm_up(self, runs: int, stop: Cancellation | None = None) -> bool:
        """Run every distinct Detector's networks ``runs`` times, then one frame on each worker thread.

        Blocking; call it off the event loop. The frames wait for each other at a barrier, so each one
        starts a worker thread of its own and makes that thread's buffers (Detector.warm_up_thread).
        ``stop`` (cancelled when the service shuts down) ends it at the next network node; False when it did.
        ``runs`` 0: no network run and no frame, True at once.
        """
        if runs == 0:
            return True
        stop = stop or Cancellation()
        try:
            for _ in range(runs):
                for detector in self.detectors:
                    detector.warm_up(1, stop)
            barrier = threading.Barrier(self.workers)

            def on_a_worker() -> None:
                barrier.wait(timeout=WARM_UP_BARRIER_S)
                self._local.detector.warm_up_thread(stop)

            for future in [self._executor.submit(on_a_worker) for _ in range(self.workers)]:
                future.result()
        except RunCancelled:
            return False
        return True

    def shutdown(self) -> None:
        """Refuse new jobs, let running and waiting ones finish, stop the threads."""
        with self._lock:
            self._closed = True
        self._executor.shutdown(wait=True)
