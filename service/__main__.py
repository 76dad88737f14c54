"""``python -m service``: run the detection service with uvicorn.

    python -m service [--models DIR] [--host 127.0.0.1] [--port 8000] [--workers N] [--provider cpu|cuda|tensorrt]

Every option is also an environment variable (``--queue-size`` ↔
``LOWRES3D_QUEUE_SIZE``); the command line wins. The models are loaded and
their sha256 checked before the port is bound: a missing or corrupted model
file stops the start with a message naming it (exit status 2). SIGTERM or
Ctrl-C stop accepting connections and let in-flight requests finish (up to
``--shutdown-timeout-s``).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from pydantic import ValidationError

from pipeline.errors import InputError
from pipeline.model_files import ModelFileError, default_models_hint
from service.settings import ENV_PREFIX, Settings

log = logging.getLogger("service")

# (flag, type, metavar or choices; a bool is a --flag/--no-flag pair); the Settings field is the flag without dashes, '-' → '_'.
_OPTIONS: list[tuple[str, type, object]] = [
    ("--models", Path, "DIR"),
    ("--host", str, "ADDR"),
    ("--port", int, "PORT"),
    ("--workers", int, "N"),
    ("--queue-size", int, "N"),
    ("--sessions", str, ["shared", "per-worker"]),
    ("--provider", str, ["cpu", "cuda", "tensorrt"]),
    ("--intra-op-threads", int, "N"),
    ("--trt-cache-dir", Path, "DIR"),
    ("--request-timeout-s", float, "S"),
    ("--max-body-bytes", int, "BYTES"),
    ("--max-points", int, "N"),
    ("--max-image-pixels", int, "N"),
    ("--token", str, "TOKEN"),
    ("--default-calib", Path, "FILE"),
    ("--mirror-tta", bool, None),
    ("--warmup-runs", int, "N"),
    ("--shutdown-timeout-s", float, "S"),
    ("--log-level", str, ["debug", "info", "warning", "error"]),
]


def build_parser() -> argparse.ArgumentParser:
    """The command line, generated from the Settings fields (help text and defaults included)."""
    parser = argparse.ArgumentParser(
        prog="python -m service",
        description="lowres3d detection service: FastAPI over the ONNX Runtime detector. Every option is also "
        f"an environment variable {ENV_PREFIX}<OPTION> (e.g. {ENV_PREFIX}QUEUE_SIZE); the command line wins.",
    )
    fields = Settings.model_fields
    for flag, kind, meta in _OPTIONS:
        name = flag[2:].replace("-", "_")
        info = fields[name]
        env = ENV_PREFIX + name.upper()
        default = info.default
        shown = ("on" if default else "off") if isinstance(default, bool) else default if default is not None else "none"
        help_text = f"{info.description} (env {env}; default {shown})"
        kwargs: dict = {"type": kind, "default": argparse.SUPPRESS, "help": help_text}
        if kind is bool:  # --mirror-tta / --no-mirror-tta
            kwargs = {"action": argparse.BooleanOptionalAction, "default": argparse.SUPPRESS, "help": help_text}
        elif isinstance(meta, list):
            kwargs["choices"] = meta
        else:
            kwargs["metavar"] = meta
        parser.add_argument(flag, **kwargs)
    return parser


def settings_from_args(argv: list[str] | None = None) -> Settings:
    """Settings from the environment, overridden by the options given on the command line."""
    args = build_parser().parse_args(argv)
    return Settings(**vars(args))


def settings_errors(exc: ValidationError) -> list[str]:
    """One line per invalid setting, named as the user gives it: ``--port (LOWRES3D_PORT) 99999: …``."""
    lines = []
    for error in exc.errors():
        name = str(error["loc"][0]) if error["loc"] else ""
        named = f"--{name.replace('_', '-')} ({ENV_PREFIX}{name.upper()})" if name else "settings"
        given = f" {error['input']}" if name and not isinstance(error["input"], dict) else ""
        lines.append(f"{named}{given}: {error['msg'][:1].lower()}{error['msg'][1:]}")
    return lines


def main(argv: list[str] | None = None) -> int:
    """Parse options, load and check the models, serve until SIGTERM/SIGINT; the exit status."""
    import uvicorn

    from service.app import create_app
    from service.memory import limit_malloc_arenas
    from service.metrics import Metrics
    from service.runtime import load_runtime

    try:
        settings = settings_from_args(argv)
    except ValidationError as exc:
        for line in settings_errors(exc):
            print(f"python -m service: {line}", file=sys.stderr)
        return 2
    logging.basicConfig(level=settings.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    limit_malloc_arenas()  # before the worker threads exist (service/memory.py: the memory of a long run)
    metrics = Metrics()
    try:
        runtime = load_runtime(settings, metrics)
    except (ModelFileError, InputError) as exc:
        log.error("cannot start: %s", exc)
        if hint := default_models_hint(settings.models):
            log.error("%s (or LOWRES3D_MODELS)", hint)
        return 2
    app = create_app(settings, runtime=runtime, metrics=metrics)
    config = uvicorn.Config(
        app,
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        timeout_graceful_shutdown=int(settings.shutdown_timeout_s),
        access_log=settings.log_level == "debug",
        server_header=False,
        log_config=None,  # keep the logging configured above
    )
    server = uvicorn.Server(config)
    server.run()
    return 0 if server.started else 3


if __name__ == "__main__":
    sys.exit(main())
