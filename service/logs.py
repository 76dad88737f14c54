"""The service's log: one event per line, as text (the default) or as JSON (``--log-format json``).

Both formats stamp each line with its time in UTC, ISO-8601 with milliseconds
(``2026-12-06T18:33:04.468Z``): a fleet's vehicles run in several time zones, and a
log backend sorts their lines together. The JSON format writes one object per line
with stable field names, for a log shipper (Fluent Bit, Vector, Promtail) to parse
without a pattern:

- every line: ``timestamp``, ``level``, ``logger``, ``message``, ``request_id``
  (the request the line is about, null outside a request), and ``exception`` (the
  traceback, one string) when the line has one;
- the access line of each request (logger ``service.access``, written by
  :class:`service.middleware.RequestContextMiddleware`): :data:`ACCESS_FIELDS`.

Nothing here imports FastAPI or uvicorn: ``python -m service`` configures the
log before those imports, so that a bad setting is reported in the chosen format.
"""

from __future__ import annotations

import contextvars
import json
import logging
import re
import sys
import uuid
from collections.abc import Mapping
from datetime import datetime, timezone
from typing import Any, TextIO

from service.settings import ENV_PREFIX

LOG_FORMATS = ("text", "json")
# The request being handled in the current task (set by RequestContextMiddleware): lines logged while it runs
# on the event loop name it without each call passing it. Worker threads pass it in ``extra`` themselves.
REQUEST_ID: contextvars.ContextVar[str | None] = contextvars.ContextVar("lowres3d_request_id", default=None)
# The fields of an access line beyond the common ones, in this order in the JSON object.
ACCESS_FIELDS = ("method", "path", "route", "status", "error_code", "duration_ms", "client", "model_id",
                 "warning_codes")
TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
_SAFE_REQUEST_ID = re.compile(r"^[A-Za-z0-9._-]{1,64}$")


def request_id_for(incoming: str | None) -> str:
    """A request's id: the client's own (its X-Request-ID) when it is safe to log and echo, else a new one."""
    return incoming if incoming and _SAFE_REQUEST_ID.match(incoming) else uuid.uuid4().hex


def utc_timestamp(created: float) -> str:
    """A record's time as UTC ISO-8601 with milliseconds and a ``Z``: ``2026-12-06T18:33:04.468Z``."""
    return datetime.fromtimestamp(created, timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


class RequestIdFilter(logging.Filter):
    """Gives every record a ``request_id``: its own (``extra=``), else the request being handled, else None.
    A handler's filter: it sees the records of every logger, uvicorn's and the libraries' too."""

    def filter(self, record: logging.LogRecord) -> bool:
        if getattr(record, "request_id", None) is None:
            record.request_id = REQUEST_ID.get()
        return True


class TextFormatter(logging.Formatter):
    """``2026-12-06T18:33:04.468Z INFO service.access: request …``: the project's text line, in UTC."""

    def __init__(self) -> None:
        super().__init__(TEXT_FORMAT)

    def formatTime(self, record: logging.LogRecord, datefmt: str | None = None) -> str:
        return utc_timestamp(record.created)


class JsonFormatter(logging.Formatter):
    """One JSON object per record, on one line (a traceback included, as the ``exception`` string); ASCII only,
    so no shipper's encoding setting can garble it."""

    def format(self, record: logging.LogRecord) -> str:
        event: dict[str, Any] = {
            "timestamp": utc_timestamp(record.created),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
            "request_id": getattr(record, "request_id", None),
        }
        for name in ACCESS_FIELDS:
            if hasattr(record, name):
                event[name] = getattr(record, name)
        if record.exc_info:
            event["exception"] = self.formatException(record.exc_info)
        elif record.exc_text:
            event["exception"] = record.exc_text
        if record.stack_info:
            event["stack"] = self.formatStack(record.stack_info)
        return json.dumps(event, default=str)


def make_formatter(log_format: str) -> logging.Formatter:
    """The formatter of ``--log-format``: ``text`` or ``json``."""
    return JsonFormatter() if log_format == "json" else TextFormatter()


def configure_logging(level: str, log_format: str, stream: TextIO | None = None) -> None:
    """Send every logger's records at ``level`` and above to ``stream`` (stderr) in ``log_format``.

    As :func:`logging.basicConfig`, it does nothing to a root logger that has handlers already (a test's
    capture). Python's warnings (a library's ``RuntimeWarning``) become records too: ``warnings`` would write
    them as two lines of plain text, past the format.
    """
    handler = logging.StreamHandler(stream if stream is not None else sys.stderr)
    handler.setFormatter(make_formatter(log_format))
    handler.addFilter(RequestIdFilter())
    logging.basicConfig(level=level.upper(), handlers=[handler])
    logging.captureWarnings(True)


def requested_log_format(options: Mapping[str, Any], environ: Mapping[str, str]) -> str:
    """The log format asked for on the command line (``options``) or in ``LOWRES3D_LOG_FORMAT``, read leniently
    for the lines that say why the settings were refused (before there are Settings); ``text`` when unclear."""
    value = options.get("log_format")
    if value is None:
        value = next((v for k, v in environ.items() if k.upper() == f"{ENV_PREFIX}LOG_FORMAT"), None)
    value = str(value).strip().lower() if value is not None else "text"
    return value if value in LOG_FORMATS else "text"
