"""The job scheduler of the reproduce recipe: lanes side by side, dependencies, threads, failures."""

import json
import os
import time
from functools import partial
from pathlib import Path

import pytest

from models.schedule import Job, JobFailed, cores, run_jobs
from pipeline.errors import InputError


def _record(folder: Path, name: str, seconds: float, threads: int | None) -> dict:
    """A job that writes when it started and ended (seconds on the monotonic clock) and its threads."""
    start = time.monotonic()
    time.sleep(seconds)
    record = {"start": start, "end": time.monotonic(), "threads": threads, "pid": os.getpid()}
    (folder / f"{name}.json").write_text(json.dumps(record))
    return record


def _fail(kind: str, threads: int | None) -> dict:
    if kind == "input":
        raise InputError("--data: /nowhere has no velodyne/ folder")
    if kind == "exit":
        os._exit(3)
    if kind == "interrupt":  # what Ctrl-C raises in a lane
        raise KeyboardInterrupt
    raise ZeroDivisionError("a bug")


def _jobs(folder: Path) -> list[Job]:
    return [
        Job("a", partial(_record, folder, "a", 1.0)),
        Job("b", partial(_record, folder, "b", 1.0)),
        Job("c", partial(_record, folder, "c", 0.1), after=("a",)),
    ]


def _meet(folder: Path, name: str, other: str, threads: int | None) -> dict:
    """A job that says it has started, then waits (up to a minute) for ``other`` to say so too: both see each
    other only if they run at the same time, however long each process takes to start."""
    (folder / f"{name}.started").touch()
    deadline = time.monotonic() + 60
    while not (folder / f"{other}.started").exists() and time.monotonic() < deadline:
        time.sleep(0.01)
    return {"met": (folder / f"{other}.started").exists(), "end": time.monotonic(), "threads": threads,
            "pid": os.getpid()}


def test_two_lanes_run_independent_jobs_side_by_side_and_dependents_after(tmp_path):
    jobs = [Job("a", partial(_meet, tmp_path, "a", "b")), Job("b", partial(_meet, tmp_path, "b", "a")),
            Job("c", partial(_record, tmp_path, "c", 0.1), after=("a",))]
    results, timeline = run_jobs(jobs, lanes=2, progress=False)
    a, b, c = (results[n] for n in "abc")
    assert a["met"] and b["met"]  # a and b ran side by side
    assert c["start"] >= a["end"]  # c waited for a
    assert len({a["pid"], b["pid"], c["pid"], os.getpid()}) == 4  # a fresh process per job
    assert {a["threads"], b["threads"], c["threads"]} == {max(1, cores() // 2)}
    assert set(timeline) == {"a", "b", "c"} and timeline["c"]["start_s"] >= timeline["a"]["end_s"]


def test_one_lane_runs_in_order_in_this_process_with_all_threads(tmp_path):
    finished = []
    results, _ = run_jobs(_jobs(tmp_path), lanes=1, on_done=lambda name, _: finished.append(name), progress=False)
    assert finished == ["a", "b", "c"]
    assert all(r["pid"] == os.getpid() and r["threads"] is None for r in results.values())
    assert results["b"]["start"] >= results["a"]["end"]


@pytest.mark.parametrize("kind, user_error, text", [
    ("input", True, "x: --data: /nowhere has no velodyne/ folder"),
    ("bug", False, "x: ZeroDivisionError: a bug"),
    ("exit", False, "x: its process died (exit code 3)"),
    ("interrupt", False, "x: its process died (exit code 130)"),
])
def test_a_failing_job_names_itself_and_stops_the_other_lane(tmp_path, kind, user_error, text, capfd):
    jobs = [Job("slow", partial(_record, tmp_path, "slow", 60.0)), Job("x", partial(_fail, kind))]
    with pytest.raises(JobFailed) as failure:
        run_jobs(jobs, lanes=2, progress=False)
    assert str(failure.value) == text and failure.value.user_error is user_error
    if kind in ("input", "interrupt"):  # no traceback from the lane: the parent's one line says it all
        assert "Traceback" not in capfd.readouterr().err
    assert not (tmp_path / "slow.json").exists()  # terminated, not waited for


def test_a_job_may_only_come_after_earlier_jobs(tmp_path):
    jobs = [Job("c", partial(_record, tmp_path, "c", 0.0), after=("a",)), Job("a", partial(_record, tmp_path, "a", 0.0))]
    with pytest.raises(ValueError, match="job c comes after"):
        run_jobs(jobs, lanes=2, progress=False)
