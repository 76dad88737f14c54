"""The job graph's order check (mutation audit): a job may not come after itself."""

import functools

import pytest

from models.schedule import Job, run_jobs


def _result(threads: int | None) -> dict:
    return {"threads": threads}


def test_a_job_that_comes_after_itself_is_refused_before_anything_runs():
    """The graph is refused before any job runs, naming the job (on two lanes it would wait for itself forever)."""
    job = Job("depth", functools.partial(_result), after=("depth",))
    with pytest.raises(ValueError, match=r"job depth comes after \['depth'\]"):
        run_jobs([job], lanes=1, progress=False)
