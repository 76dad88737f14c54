"""Run a small graph of training jobs on N lanes, each job in its own process with its share of the cores.

Two PyTorch trainings side by side with one thread each get through more work
on this 2-core machine than the same two one after the other with two
threads each: intra-op threading of these small convolutions scales well
below 2×. Measured here on 160-frame runs of two epochs (whole processes), a
depth run and a PIXOR run took 45.6 s in turn and 35.0 s side by side (1.30×).

With one lane every job runs in this process, in order, with all threads and
its own progress bars. With more, each job is a fresh spawned process (its
sample cache is freed when it ends), a job starts when the jobs it comes after
are done, earlier jobs in the list first, and one bar counts the units the
caller reports (epochs written to the runs' logs). A failing job stops the
others; every job resumes from its last checkpoint when the caller reruns. A
job whose parent is gone (killed with SIGKILL, which cannot be passed on) ends
within a second instead of training on beside the rerun's own job.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import queue
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass

from tqdm import tqdm

from pipeline.errors import InputError

log = logging.getLogger(__name__)
_POLL_SECONDS = 5.0
_PARENT_POLL_SECONDS = 1.0
ORPHAN_STATUS = 143  # a job ended because its parent is gone: as if SIGTERM had ended it
_USER_ERRORS = (InputError, FileNotFoundError, ValueError)


@dataclass(frozen=True)
class Job:
    """One unit of work: ``run(threads)`` returns a picklable result (a module-level function or partial)."""

    name: str
    run: Callable[[int | None], dict]
    after: tuple[str, ...] = ()


class JobFailed(RuntimeError):
    """A job raised; ``user_error`` when it was bad input (the message names it), not a crash."""

    def __init__(self, name: str, message: str, user_error: bool) -> None:
        super().__init__(f"{name}: {message}")
        self.user_error = user_error


def cores() -> int:
    """CPU cores this process may use."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def run_jobs(jobs: list[Job], lanes: int, units: Callable[[], int] | None = None, total_units: int = 0,
             on_done: Callable[[str, dict], None] | None = None, progress: bool = True,
             ) -> tuple[dict[str, dict], dict[str, dict]]:
    """Run every job once its ``after`` jobs are done. See the module docstring.

    Returns {name: result} and the timeline {name: {"start_s", "end_s"}}, seconds from the call.
    """
    names = [job.name for job in jobs]
    for job in jobs:
        unknown = [n for n in job.after if n not in names or names.index(n) >= names.index(job.name)]
        if unknown:
            raise ValueError(f"job {job.name} comes after {unknown}, which are not earlier jobs")
    started, timeline = time.perf_counter(), {}

    def finished(name: str, start: float, result: dict) -> None:
        timeline[name] = {"start_s": round(start - started, 1), "end_s": round(time.perf_counter() - started, 1)}
        if on_done:
            on_done(name, result)

    if lanes <= 1:
        results = {}
        for job in jobs:
            start = time.perf_counter()
            results[job.name] = job.run(None)
            finished(job.name, start, results[job.name])
        return results, timeline
    threads = max(1, cores() // lanes)
    return _run_in_processes(jobs, lanes, threads, units, total_units, finished, progress), timeline


def _end_with_parent(parent: int) -> None:
    """End this process once ``parent`` is no longer its parent (a thread polls for it): its files are written
    whole or not at all, so ending it at any moment loses at most the epoch under way."""
    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(_PARENT_POLL_SECONDS)
        os._exit(ORPHAN_STATUS)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def _child(job: Job, threads: int, results: mp.Queue, parent: int) -> None:
    _end_with_parent(parent)
    logging.basicConfig(level=logging.INFO, format=f"%(asctime)s [{job.name}] %(message)s")
    try:
        results.put((job.name, None, job.run(threads)))
    except KeyboardInterrupt:
        # Ctrl-C reaches every process of the terminal's group: the parent says it once, without a traceback
        # per lane. Exit status 130 tells it, should the signal have reached this lane alone.
        raise SystemExit(130) from None
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which stops the other lanes
        user_error = isinstance(exc, _USER_ERRORS)
        if not user_error:
            traceback.print_exc()
        results.put((job.name, (str(exc) if user_error else f"{type(exc).__name__}: {exc}", user_error), None))


def _run_in_processes(jobs: list[Job], lanes: int, threads: int, units: Callable[[], int] | None, total_units: int,
                      finished: Callable[[str, float, dict], None], progress: bool) -> dict[str, dict]:
    context = mp.get_context("spawn")  # no torch or ONNX Runtime thread state inherited from this process
    messages = context.Queue()
    pending, running, results, starts = list(jobs), {}, {}, {}
    bar = tqdm(total=total_units or None, desc="training", unit="epoch", disable=not progress)
    try:
        while pending or running:
            for job in [j for j in pending if all(n in results for n in j.after)][: lanes - len(running)]:
                process = context.Process(target=_child, args=(job, threads, messages, os.getpid()), name=job.name)
                process.start()
                running[job.name], starts[job.name] = process, time.perf_counter()
                pending.remove(job)
                log.info("started %s (%d thread%s)", job.name, threads, "" if threads == 1 else "s")
            bar.set_postfix_str(", ".join(running))
            try:
                name, error, result = messages.get(timeout=_POLL_SECONDS)
            except queue.Empty:
                crashed = [n for n, p in running.items() if p.exitcode not in (None, 0)]
                if crashed:
                    raise JobFailed(crashed[0], f"its process died (exit code {running[crashed[0]].exitcode})",
                                    user_error=False)
                if units:
                    bar.update(units() - bar.n)
                continue
            running.pop(name).join()
            if error:
                raise JobFailed(name, *error)
            results[name] = result
            finished(name, starts[name], result)
            if units:
                bar.update(units() - bar.n)
    finally:
        for process in running.values():  # on failure or Ctrl-C: the others resume from their checkpoints
            process.terminate()
            process.join()
        bar.close()
    return results
