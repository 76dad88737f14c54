"""``python -m service``: run the detection service with uvicorn.

    python -m service [--models DIR] [--host 127.0.0.1] [--port 8000] [--workers N] [--provider cpu|cuda|tensorrt]

Every option is also an environment variable (``--queue-size`` ↔
``LOWRES3D_QUEUE_SIZE``); the command line wins; a ``LOWRES3D_*`` variable that
is no setting (a typo) gets a warning. The address is bound first (not yet
listened on), then the models are loaded and their sha256 checked: an address
in use, a missing or corrupted model file stops the start with one line naming
the option or the file (exit status 2), before any warm-up. SIGTERM and Ctrl-C
are handled from the first milliseconds, before the imports: one that comes
while the service starts or its models load stops the start there; once
serving, they stop accepting connections and let in-flight requests finish (up
to ``--shutdown-timeout-s``); those still running then are answered 503
``shutting_down`` (service/middleware.py). Ctrl-C then ends with one line
(``interrupted: …``) and exit status 130, SIGTERM by the signal itself.
Every line written, from the first to that last one, is in ``--log-format``
(text, or one JSON object per line: service/logs.py), refused settings included.
"""

from __future__ import annotations

import signal

_pending_signals: list[int] = []  # SIGTERM/SIGINT noted while nothing else handled them, first first


def _note_signal(signum: int, _frame: object) -> None:
    """Note a SIGTERM or SIGINT; main() acts on it at its next step (before the models load, or at exit)."""
    _pending_signals.append(signum)


def note_signals() -> None:
    """From now on a SIGTERM or SIGINT is noted rather than lost (the first process of a container ignores a
    signal it has no handler for) or turned into a KeyboardInterrupt traceback (Python's own SIGINT handler)."""
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, _note_signal)


if __name__ == "__main__":
    # First of all: the imports below take most of a second, and a stop sent meanwhile must not be lost.
    note_signals()

# The imports come after the handlers on purpose (see above).
import argparse
import difflib
import errno
import ipaddress
import logging
import os
import socket
import sys
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from pydantic import ValidationError

from pipeline.cli import INTERRUPTED_STATUS, HelpFormatter, examples, interrupted
from pipeline.errors import InputError
from pipeline.model_files import ModelFileError, default_models_hint
from service.logs import configure_logging, requested_log_format
from service.settings import ENV_PREFIX, Settings, option_name

if TYPE_CHECKING:
    import uvicorn
    from fastapi import FastAPI

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
    ("--device-ids", str, "IDS"),
    ("--intra-op-threads", int, "N"),
    ("--trt-cache-dir", Path, "DIR"),
    ("--request-timeout-s", float, "S"),
    ("--receive-timeout-s", float, "S"),
    ("--send-timeout-s", float, "S"),
    ("--max-connections", int, "N"),
    ("--max-body-bytes", int, "BYTES"),
    ("--max-points", int, "N"),
    ("--max-image-pixels", int, "N"),
    ("--token", str, "TOKEN"),
    ("--default-calib", Path, "FILE"),
    ("--mirror-tta", bool, None),
    ("--max-sensor-skew-ms", float, "MS"),
    ("--warmup-runs", int, "N"),
    ("--shutdown-timeout-s", float, "S"),
    ("--cors-origins", str, "ORIGINS"),
    ("--log-level", str, ["debug", "info", "warning", "error"]),
    ("--log-format", str, ["text", "json"]),
]


def build_parser() -> argparse.ArgumentParser:
    """The command line, generated from the Settings fields (help text and defaults included)."""
    parser = argparse.ArgumentParser(
        allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
        prog="python -m service",
        description="lowres3d detection service: FastAPI over the ONNX Runtime detector. Every option is also "
        f"an environment variable {ENV_PREFIX}<OPTION> (e.g. {ENV_PREFIX}QUEUE_SIZE); the command line wins.",
        epilog=examples("python -m service --models weights/edge --host 127.0.0.1 --port 8000 --workers 2"),
        formatter_class=HelpFormatter,
    )
    fields = Settings.model_fields
    for flag, kind, meta in _OPTIONS:
        name = flag[2:].replace("-", "_")
        info = fields[name]
        env = ENV_PREFIX + name.upper()
        default = info.default
        shown = ("on" if default else "off") if isinstance(default, bool) else default if default is not None else "none"
        # An unset option whose description says what it then means (the best provider, MODELS/trt_cache) has that
        # default only: "(default: GPU 0) (…; default none)" read as two.
        said = default is None and "default" in (info.description or "")
        help_text = f"{info.description} (env {env})" if said else f"{info.description} (env {env}; default {shown})"
        # Paths stay strings here: Settings refuses an empty one before making it a Path (Path("") is ".").
        kwargs: dict = {"type": str if kind is Path else kind, "default": argparse.SUPPRESS, "help": help_text}
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
        message = f"{error['msg'][:1].lower()}{error['msg'][1:]}"
        if not name:  # a check across settings: its message names the settings itself (option_name)
            lines.append(message)
            continue
        value = error["input"]
        # The token is never echoed (logs are read by others); an empty value has nothing to show.
        shown = name != "token" and not isinstance(value, dict) and str(value).strip()
        given = f" {value}" if shown else ""
        lines.append(f"{option_name(name)}{given}: {message}")
    return lines


def refuse_settings(exc: ValidationError, log_format: str) -> int:
    """Say why the settings were refused, one line each, and return exit status 2: ``python -m service: …`` as
    text, or as JSON records when the JSON log was asked for (a log shipper parses every line of the start)."""
    if log_format == "json":
        configure_logging("error", "json")
        for line in settings_errors(exc):
            log.error("cannot start: %s", line)
    else:
        for line in settings_errors(exc):
            print(f"python -m service: {line}", file=sys.stderr)
    return 2


def interrupted_line(leaves: str, log_format: str) -> int:
    """Ctrl-C's one line (``interrupted: …``) and its exit status, 130; a record in the JSON log, as the lines
    before it."""
    if log_format != "json":
        return interrupted(leaves)
    log.info("interrupted: %s", leaves)
    return INTERRUPTED_STATUS


def unknown_env_warnings(environ: Mapping[str, str]) -> list[str]:
    """One line per ``LOWRES3D_*`` variable that is no setting, with the closest setting's name or the list.

    pydantic-settings reads only the variables of its fields, so a misspelt one (``LOWRES3D_WORKER=4``) would
    be ignored without a word. Names are compared in upper case: the settings read them case-insensitively.
    """
    fields = [name.upper() for name in Settings.model_fields]
    lines = []
    for name in sorted(environ):
        upper = name.upper()
        if not upper.startswith(ENV_PREFIX) or upper.removeprefix(ENV_PREFIX) in fields:
            continue
        # Compared without the prefix, which every name shares and would make any two look alike.
        close = difflib.get_close_matches(upper.removeprefix(ENV_PREFIX), fields, n=1, cutoff=0.6)
        hint = (f"did you mean {ENV_PREFIX}{close[0]}?" if close
                else f"the settings are {', '.join(ENV_PREFIX + field for field in fields)}")
        lines.append(f"environment variable {name}: not a setting, ignored ({hint})")
    return lines


def exposure_warning(addresses: list[str], port: int, token_set: bool) -> str | None:
    """A warning when the service listens on an address other machines reach and no token guards ``/v1/*``
    (the container's default: ``LOWRES3D_HOST=0.0.0.0``, no token), else None. ``addresses``: where the
    sockets are bound (an IPv6 zone, ``%eth0``, is ignored)."""
    exposed = [address for address in addresses
               if not ipaddress.ip_address(address.split("%", 1)[0]).is_loopback]
    if token_set or not exposed:
        return None
    return (f"listening on {', '.join(exposed)} port {port} without a token: any client that reaches it can send "
            f"frames to /v1/detect and read /v1/model; set {ENV_PREFIX}TOKEN (clients then send Authorization: "
            "Bearer …), or listen on 127.0.0.1")


class AddressError(Exception):
    """The address to listen on cannot be had; the message names --host or --port."""


def _address_error(host: str, port: int, exc: OSError) -> AddressError:
    """One line naming the option at fault in a failed bind."""
    reason = (exc.strerror or str(exc)).lower()
    if exc.errno == errno.EADDRINUSE:
        return AddressError(f"--port {port} ({ENV_PREFIX}PORT): {reason} on {host} (another process listens "
                            "there; choose another port, or 0 for any free one)")
    if exc.errno == errno.EACCES and 0 < port < 1024:
        return AddressError(f"--port {port} ({ENV_PREFIX}PORT): {reason} (ports below 1024 need privileges)")
    if exc.errno == errno.EADDRNOTAVAIL:
        return AddressError(f"--host {host} ({ENV_PREFIX}HOST): {reason} (not an address of this machine)")
    return AddressError(f"--host {host} --port {port}: cannot listen there ({reason})")


def bind_listeners(host: str, port: int) -> list[socket.socket]:
    """Bind, without listening yet, the sockets uvicorn would open for ``host:port``: AddressError if it cannot.

    Bound as asyncio's create_server binds them (every address the host resolves to, SO_REUSEADDR, IPv6
    sockets IPv6-only, an address family the machine lacks skipped), so uvicorn serves as it would on its
    own; but an address in use is found before the models load and warm up, not after. Until uvicorn
    listens on them, connections are refused.
    """
    try:
        # The host as given: None ("" too) would mean every interface, which Settings refuses to take silently.
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (OSError, UnicodeError) as exc:  # UnicodeError: a name IDNA cannot encode (an empty label: "a..b")
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise AddressError(f"--host {host} ({ENV_PREFIX}HOST): cannot resolve it ({reason})") from None
    sockets: list[socket.socket] = []
    missing: OSError | None = None
    for family, kind, proto, _, address in dict.fromkeys(infos):
        sock = socket.socket(family, kind, proto)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if family == socket.AF_INET6:
                sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
            sock.bind(address)
        except OSError as exc:
            sock.close()
            if exc.errno == errno.EADDRNOTAVAIL:  # as asyncio: the family is not enabled here (bpo-30945)
                missing = exc
                continue
            for bound in sockets:
                bound.close()
            raise _address_error(host, port, exc) from None
        sockets.append(sock)
    if not sockets:
        raise _address_error(host, port, missing or OSError(errno.EADDRNOTAVAIL, os.strerror(errno.EADDRNOTAVAIL)))
    return sockets


class StoppedBeforeServing(BaseException):
    """SIGTERM or SIGINT came before uvicorn took the signals over. A BaseException, as KeyboardInterrupt is:
    the model loading's own ``except Exception`` (a graph ONNX Runtime cannot load) must not take it."""

    def __init__(self, signum: int, during: str = "loading the models") -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum
        self.during = during  # what the start was doing, for the log line


@contextmanager
def stop_on_signals_until_serving() -> Iterator[None]:
    """Until uvicorn installs its own handlers, SIGTERM and SIGINT raise :class:`StoppedBeforeServing`; one
    noted since the start (:func:`note_signals`) raises it on entry.

    Python has no SIGTERM handler of its own, and the first process of a container (no init) ignores a
    signal it has no handler for: a ``docker stop`` or a rollout while the models loaded (TensorRT builds its
    engines then, minutes on a Jetson) was lost, and the service went on to serve until it was killed.
    """
    def stop(signum: int, _frame: object) -> None:
        raise StoppedBeforeServing(signum)

    previous = {signum: signal.signal(signum, stop) for signum in (signal.SIGTERM, signal.SIGINT)}
    try:
        if _pending_signals:  # noted during the imports or the bind: the models are not even loaded
            raise StoppedBeforeServing(_pending_signals.pop(0), "starting, before the models loaded")
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def ended_by_signal(signum: int) -> int:
    """End the process as the signal would have, after the clean-up: by the signal itself (uvicorn does so
    after a shutdown too), or, where it is ignored (the first process of a container), 128 + its number."""
    signal.signal(signum, signal.SIG_DFL)
    signal.raise_signal(signum)
    return 128 + signum


def stopped_before_serving(signum: int) -> int:
    """The exit status of a start stopped by ``signum``: 130 for SIGINT (Ctrl-C), else :func:`ended_by_signal`."""
    return 130 if signum == signal.SIGINT else ended_by_signal(signum)


def uvicorn_config(settings: Settings, app: FastAPI) -> uvicorn.Config:
    """uvicorn's configuration for the service."""
    import uvicorn

    from service.protocol import protocol_class

    return uvicorn.Config(
        app,
        host=settings.host,
        port=settings.port,
        # h11 with a deadline on each request's head and on sending, the limit on requests in progress and the
        # cap on open connections (service/protocol.py); what it answers or closes itself is counted with the app's.
        http=protocol_class(settings.receive_timeout_s, settings.connection_limit(), getattr(app.state, "metrics", None),
                            socket_limit=settings.socket_limit(), send_timeout_s=settings.send_timeout_s),
        ws="none",  # no WebSocket route: an Upgrade request is answered as plain HTTP
        log_level=settings.log_level,  # uvicorn's loggers: the same level as the service's
        # A float: uvicorn waits in asyncio.timeout(), which takes fractions (int() made 0.9 s no grace at all).
        timeout_graceful_shutdown=settings.shutdown_timeout_s,  # type: ignore[arg-type]  # annotated int there
        access_log=False,  # the service writes its own access line per request (service/middleware.py)
        server_header=False,
        log_config=None,  # keep the logging configured in main() (its format; uvicorn's would colour a terminal)
    )


def main(argv: list[str] | None = None) -> int:
    """Parse options, bind the address, load and check the models, serve until SIGTERM/SIGINT; the exit status."""
    note_signals()  # (again: for a caller other than python -m service)
    # Every module the service runs is imported here, before the settings: before logging is configured (it
    # captures warnings) and before the model loading's signal handlers (a stop during the imports is noted).
    from service.app import create_app
    from service.memory import limit_malloc_arenas
    from service.metrics import Metrics
    from service.runtime import load_runtime

    try:
        settings = settings_from_args(argv)
    except ValidationError as exc:  # the options again (a usage error would have exited above): the log format
        return refuse_settings(exc, requested_log_format(vars(build_parser().parse_args(argv)), os.environ))
    _start_logging(settings)
    try:
        sockets = bind_listeners(settings.host, settings.port)
    except AddressError as exc:
        log.error("cannot start: %s", exc)
        return 2
    _warn_if_exposed(sockets, settings.token is not None)
    limit_malloc_arenas()  # before the worker threads exist (service/memory.py: the memory of a long run)
    metrics = Metrics()
    try:
        with stop_on_signals_until_serving():
            runtime = load_runtime(settings, metrics)
            server = _server(uvicorn_config(settings, create_app(settings, runtime=runtime, metrics=metrics)))
    except (ModelFileError, InputError) as exc:
        _close_all(sockets)
        return _refuse_models(exc, settings.models)
    except StoppedBeforeServing as stopped:
        _close_all(sockets)
        return _start_stopped(stopped, settings.log_format)
    server.run(sockets=sockets)  # uvicorn's own signal handlers from here on
    return _exit_status(server, settings.log_format)


def _start_logging(settings: Settings) -> None:
    """The log as the settings ask, the service's filters on the libraries' loggers, then a warning for each
    ``LOWRES3D_*`` variable that is no setting."""
    from service.middleware import install_log_filters  # imported already (service.app imports it)

    configure_logging(settings.log_level, settings.log_format)
    install_log_filters()  # no traceback for a cancelled request; what clients cause at will at DEBUG
    for line in unknown_env_warnings(os.environ):
        log.warning(line)


def _warn_if_exposed(sockets: list[socket.socket], token_set: bool) -> None:
    """A warning when the bound sockets reach other machines and no token guards ``/v1/*``
    (:func:`exposure_warning`)."""
    if warning := exposure_warning([sock.getsockname()[0] for sock in sockets], sockets[0].getsockname()[1],
                                   token_set):
        log.warning(warning)


def _close_all(sockets: list[socket.socket]) -> None:
    """Close the bound sockets of a start that stops before serving."""
    for sock in sockets:
        sock.close()


def _refuse_models(exc: ModelFileError | InputError, models: Path) -> int:
    """Say why the model directory cannot be served, one line, and return exit status 2."""
    hint = default_models_hint(models)
    if hint and str(models) in str(exc):  # the default's absence itself: one line with the way out
        log.error("cannot start: %s (or LOWRES3D_MODELS)", hint)
    else:
        log.error("cannot start: %s", exc)
    return 2


def _start_stopped(stopped: StoppedBeforeServing, log_format: str) -> int:
    """Say that a SIGTERM or SIGINT stopped the start; the exit status (:func:`stopped_before_serving`)."""
    said = f"{stopped} before serving: stopped while {stopped.during}; not started"
    if stopped.signum == signal.SIGINT:  # Ctrl-C: one line and 130, as every command of the project
        return interrupted_line(said, log_format)
    log.info("%s", said)
    return stopped_before_serving(stopped.signum)


def _server(config: uvicorn.Config) -> uvicorn.Server:
    """uvicorn's server for ``config``: it serves on the sockets main() bound, and acts on a signal noted
    before it took the signals over."""
    import uvicorn

    class Server(uvicorn.Server):
        """uvicorn's server on the sockets bound here; it logs where it listens, as uvicorn does for a host and
        port (given sockets, uvicorn leaves that line to the code that bound them)."""

        async def startup(self, sockets: list[socket.socket] | None = None) -> None:
            await super().startup(sockets=sockets)
            if not self.started:
                return
            for sock in sockets or []:
                address, bound_port = sock.getsockname()[:2]
                shown = f"[{address}]" if sock.family == socket.AF_INET6 else address
                logging.getLogger("uvicorn.error").info("Uvicorn running on http://%s:%d (Press CTRL+C to quit)",
                                                        shown, bound_port)

        async def on_tick(self, counter: int) -> bool:
            # A signal noted between the models' load and uvicorn's own handlers: uvicorn's shutdown, as if
            # uvicorn had caught it (it re-raises it at the end, noted again for main()).
            while _pending_signals:
                self.handle_exit(_pending_signals.pop(0), None)
            return await super().on_tick(counter)

    return Server(config)


def _exit_status(server: uvicorn.Server, log_format: str) -> int:
    """The exit status once uvicorn has stopped: Ctrl-C's line and 130, the end by the signal that stopped it,
    else 0, or 3 when it never started."""
    # uvicorn re-raises the signal that stopped it once its handlers are gone: noted here, ended on here.
    if _pending_signals:
        signum = _pending_signals[0]
        if signum == signal.SIGINT:  # Ctrl-C: one line and 130, as every command of the project
            return interrupted_line("the service has stopped; the requests in flight were let finish first "
                                    "(up to --shutdown-timeout-s)", log_format)
        return ended_by_signal(signum)
    return 0 if server.started else 3


if __name__ == "__main__":
    sys.exit(main())
