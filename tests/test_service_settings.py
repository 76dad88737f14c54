"""The settings' bounds as an operator meets them through ``LOWRES3D_*`` variables: the documented edge values
start, the values just past them stop the start naming the variable, and a misspelt name gets its setting."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from service.__main__ import settings_errors, settings_from_args, unknown_env_warnings
from service.settings import Settings


@pytest.mark.parametrize(
    ("env", "field", "value"),
    [({"LOWRES3D_QUEUE_SIZE": "0"}, "queue_size", 0),  # no waiting: a frame is run or refused at once
     ({"LOWRES3D_WARMUP_RUNS": "0"}, "warmup_runs", 0),  # "0: none of it"
     ({"LOWRES3D_MAX_BODY_BYTES": "1024"}, "max_body_bytes", 1024),
     ({"LOWRES3D_INTRA_OP_THREADS": "3", "LOWRES3D_WORKERS": "1"}, "intra_op_threads", 3)],
    ids=["queue 0", "warm-up 0", "body 1 KiB", "intra-op threads"],
)
def test_the_edge_values_start(monkeypatch: pytest.MonkeyPatch, env: dict[str, str], field: str, value: int) -> None:
    for name, text in env.items():
        monkeypatch.setenv(name, text)
    settings = settings_from_args([])
    assert getattr(settings, field) == value


def test_intra_op_threads_given_win_over_the_share_of_the_cpus() -> None:
    """--intra-op-threads is used as given, whatever the CPUs and workers (the default divides the CPUs)."""
    assert Settings(intra_op_threads=3, workers=64).resolved_intra_op_threads() == 3
    assert Settings(intra_op_threads=1, workers=1).resolved_intra_op_threads() == 1


@pytest.mark.parametrize(
    ("env", "line"),
    [({"LOWRES3D_REQUEST_TIMEOUT_S": "0"}, ("--request-timeout-s (LOWRES3D_REQUEST_TIMEOUT_S) 0: input should be "
      "greater than 0")),
     ({"LOWRES3D_MAX_BODY_BYTES": "1023"}, ("--max-body-bytes (LOWRES3D_MAX_BODY_BYTES) 1023: input should be "
      "greater than or equal to 1024")),
     ({"LOWRES3D_TOKEN": "   "}, ("--token (LOWRES3D_TOKEN): empty; give a token, or leave both unset to serve /v1/* "
                                  "without one"))],
    ids=["no time at all", "body under 1 KiB", "blank token"],
)
def test_values_past_the_edge_stop_the_start_naming_the_variable(
    monkeypatch: pytest.MonkeyPatch, env: dict[str, str], line: str
) -> None:
    for name, text in env.items():
        monkeypatch.setenv(name, text)
    with pytest.raises(ValidationError) as caught:
        settings_from_args([])
    assert settings_errors(caught.value) == [line]


def test_a_setting_misspelt_in_code_is_refused() -> None:
    """Settings built by a program (a test, an embedding app) refuse a field they do not have, as the command
    line does, rather than run with the default."""
    with pytest.raises(ValidationError, match="worker"):
        Settings(worker=4)


def test_a_misspelt_variable_a_few_letters_off_gets_its_setting() -> None:
    """LOWRES3D_LOG_LVL is LOG_LEVEL two letters short: close enough to be named (difflib ratio 0.875)."""
    assert unknown_env_warnings({"LOWRES3D_LOG_LVL": "debug"}) == [
        "environment variable LOWRES3D_LOG_LVL: not a setting, ignored (did you mean LOWRES3D_LOG_LEVEL?)"]
