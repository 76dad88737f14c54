"""Service configuration: one ``Settings`` object, read from ``LOWRES3D_*`` environment variables.

Every command-line option of ``python -m service`` is a field here and an
environment variable (``--queue-size`` ↔ ``LOWRES3D_QUEUE_SIZE``); the command
line wins over the environment, the environment over the defaults. Nothing is
read at import time: build ``Settings()`` in ``main`` (or a test) and pass it to
:func:`service.app.create_app`.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_core import PydanticCustomError
from pydantic_settings import BaseSettings, SettingsConfigDict

from pipeline.checks import MAX_SENSOR_SKEW_MS
from pipeline.cli import gpu_ids
from pipeline.cpu import usable_cpus
from pipeline.detector import MAX_POINTS
from pipeline.kitti import MAX_IMAGE_PIXELS
from pipeline.model_files import DEFAULT_MODELS

ENV_PREFIX = "LOWRES3D_"
# Requests in progress beyond workers + queue: the probes, a metrics scrape, /v1/model, and clients being told 503.
CONNECTION_HEADROOM = 16
# File descriptors the process keeps for itself beside its connections (model files, logs, pipes, the event
# loop's): the default cap on open connections is the open-file limit less these, so accept() never runs out.
FD_RESERVE = 64
# The default cap where the open-file limit is not known (Windows) or unlimited.
DEFAULT_SOCKET_LIMIT = 4096
# An origin as a browser sends it in the Origin header: scheme://host[:port], no path, no trailing slash.
_ORIGIN = re.compile(r"^https?://[^/\s?#]+$")


def option_name(field: str) -> str:
    """A setting named both ways a user can give it: ``--max-connections (LOWRES3D_MAX_CONNECTIONS)``."""
    return f"--{field.replace('_', '-')} ({ENV_PREFIX}{field.upper()})"


def open_file_limit() -> int | None:
    """The process's open-file limit (the soft ``ulimit -n``); None where unknown (Windows) or unlimited."""
    try:
        import resource
    except ImportError:
        return None
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    return None if soft == resource.RLIM_INFINITY else soft


class Settings(BaseSettings):
    """Everything the detection service needs to start; validated when built."""

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, extra="forbid", frozen=True)

    models: Path = Field(DEFAULT_MODELS, description="model directory (manifest.json, depth.onnx, pixor.onnx)")
    host: str = Field("127.0.0.1", description="address to listen on (0.0.0.0 exposes the service to the network)")
    port: int = Field(8000, ge=0, le=65535, description="TCP port (0 = any free port)")
    workers: int = Field(2, ge=1, le=64, description="inference threads: frames processed at the same time")
    queue_size: int = Field(4, ge=0, le=1024, description="frames allowed to wait for a worker; beyond: 503")
    sessions: Literal["shared", "per-worker"] = Field(
        "shared", description="one ONNX Runtime session pair for all workers, or one per worker"
    )
    provider: Literal["cpu", "cuda", "tensorrt"] | None = Field(
        None, description="execution provider (default: the best available, TensorRT → CUDA → CPU)"
    )
    # Text as given (0,1), not a list: the environment variable then reads as the option does, with no JSON.
    device_ids: str | None = Field(
        None, description="GPUs for cuda or tensorrt, e.g. 0,1: with --sessions per-worker, worker i's sessions run "
        "on the i-th (in turn when fewer); shared sessions take one id (default: GPU 0)"
    )
    intra_op_threads: int | None = Field(
        None, ge=1, le=256,
        description="ONNX Runtime intra-op threads per session (default: usable CPUs // workers, at least 1)",
    )
    trt_cache_dir: Path | None = Field(
        None, description="TensorRT engine cache (a volume in the container; default: MODELS/trt_cache)"
    )
    request_timeout_s: float = Field(30.0, gt=0, le=3600, description="per-request deadline, queue wait included; beyond: 504")
    receive_timeout_s: float = Field(
        30.0, gt=0, le=3600, description="how long a client may take to send a request's head, and then its body; "
        "beyond: 408 and the connection closed"
    )
    send_timeout_s: float = Field(
        30.0, gt=0, le=3600, description="how long sending an answer may stall (the client reading none of it, the "
        "server's buffer full) before the connection is closed"
    )
    max_connections: int | None = Field(
        None, ge=2, le=1_000_000, description="open connections at most, idle ones included; one beyond closes the "
        "connection idle the longest, or is closed itself when none is idle (default: the open-file limit, ulimit -n, "
        f"less {FD_RESERVE}, at most {DEFAULT_SOCKET_LIMIT})"
    )
    max_body_bytes: int = Field(32 * 1024 * 1024, ge=1024, description="largest request body; beyond: 413")
    max_points: int = Field(1_000_000, ge=1, le=MAX_POINTS, description="most points a scan may have; beyond: 422")
    max_image_pixels: int = Field(
        16 * 1024 * 1024, ge=1, description="most pixels an uploaded image may have (checked before decoding; at "
        f"most {MAX_IMAGE_PIXELS:,}, the decoder's own limit)"
    )
    token: SecretStr | None = Field(
        None, description="bearer token required on /v1/* when set (prefer the environment variable over --token)"
    )
    default_calib: Path | None = Field(
        None, description="KITTI calib.txt used when a request sends none (a fixed camera–LiDAR rig)"
    )
    mirror_tta: bool = Field(
        False, description="also run PIXOR on the BEV mirrored left to right and average the maps: more boxes right "
        "to IoU 0.7, PIXOR's time twice over (docs/models.md)"
    )
    max_sensor_skew_ms: float = Field(
        MAX_SENSOR_SKEW_MS, gt=0, allow_inf_nan=False, description="how far apart in time the image and the scan may be "
        "captured (their stamps, image_stamp_ns and points_stamp_ns) before a frame is answered with the warning "
        "sensor_skew (milliseconds)"
    )
    warmup_runs: int = Field(
        1, ge=0, le=1000, description="network runs on zero inputs before /readyz says ready, then one frame on each "
        "worker thread to make its buffers (0: none of it)"
    )
    # 25 s: under Kubernetes' default kill grace of 30 s, so the requests left are answered before the kill.
    shutdown_timeout_s: float = Field(
        25.0, gt=0, description="on SIGTERM, how long in-flight requests may take to finish (seconds, fractions "
        "too); those still running then are answered 503. Keep it below the orchestrator's kill grace"
    )
    # Text as given (a comma-separated list), as device_ids: the environment variable reads as the option does.
    cors_origins: str | None = Field(
        None, description="browser origins allowed to call the service and read its answers (CORS), comma-separated, "
        "e.g. http://localhost:5173 for a dashboard served there; * for any (default: none, CORS off)"
    )
    log_level: Literal["debug", "info", "warning", "error"] = Field(
        "info", description="the lowest level logged, by the service, uvicorn and the libraries alike; debug adds "
        "the probes' and /metrics' access lines"
    )
    log_format: Literal["text", "json"] = Field(
        "text", description="text lines, or one JSON object per line for a log shipper (timestamp, level, logger, "
        "message, request_id; docs/service.md)"
    )

    @field_validator("models", "trt_cache_dir", "default_calib", mode="before")
    @classmethod
    def _path_not_empty(cls, value: object) -> object:
        """Refuse an empty path: ``LOWRES3D_MODELS=`` left blank would become Path(""), the current directory."""
        if isinstance(value, str) and not value.strip():
            raise PydanticCustomError("empty_path", "empty; give a path (an empty one would be the current directory)")
        return value

    @field_validator("max_image_pixels")
    @classmethod
    def _image_pixels_decodable(cls, value: int) -> int:
        """Refuse a limit above the decoder's (pipeline.kitti.MAX_IMAGE_PIXELS): an image between the two would
        pass the check before the queue, wait for a worker, then be refused there as a damaged header."""
        if value > MAX_IMAGE_PIXELS:
            raise PydanticCustomError(
                "max_image_pixels_high", f"more than {MAX_IMAGE_PIXELS:,}, the most pixels the decoder takes "
                "(pipeline.kitti.MAX_IMAGE_PIXELS); give at most that")
        return value

    @field_validator("host", mode="before")
    @classmethod
    def _host_not_empty(cls, value: object) -> object:
        """Refuse an empty host: ``LOWRES3D_HOST=`` left blank would listen on every interface (0.0.0.0 and ::)."""
        if isinstance(value, str) and not value.strip():
            raise PydanticCustomError(
                "empty_host", "empty; give an address (an empty one would listen on every interface: give "
                "0.0.0.0 for that)"
            )
        return value

    @field_validator("device_ids", mode="before")
    @classmethod
    def _device_ids_listed(cls, value: object) -> object:
        """``0,1`` → ``"0,1"``, checked (ids from 0, none twice); also a list from code."""
        if value is None:
            return None
        text = ",".join(map(str, value)) if isinstance(value, list | tuple) else str(value)
        try:
            return ",".join(map(str, gpu_ids(text)))
        except argparse.ArgumentTypeError as exc:
            raise PydanticCustomError("device_ids", str(exc)) from None

    @field_validator("cors_origins", mode="before")
    @classmethod
    def _cors_origins_listed(cls, value: object) -> object:
        """``http://a:5173, https://b`` → ``"http://a:5173,https://b"``, each an origin as browsers send it."""
        if value is None:
            return None
        origins = [origin.strip() for origin in str(value).split(",")]
        if not any(origins):
            raise PydanticCustomError("empty_cors", "empty; give origins (http://host:port), or leave it unset for "
                                      "no CORS")
        for origin in origins:
            if origin != "*" and not _ORIGIN.match(origin):
                raise PydanticCustomError(
                    "cors_origin", f"{origin!r} is no origin: give scheme://host[:port] as the browser's address bar "
                    "shows it, without a path or a trailing slash (or * for any)")
        return ",".join(origins)

    @model_validator(mode="after")
    def _device_ids_usable(self) -> Settings:
        """Device ids only where they can be used: a GPU provider (or the best available, checked at load) and,
        for several GPUs, a session pair per worker."""
        ids = self.gpu_ids()
        given = f"{option_name('device_ids')} {self.device_ids}"
        if ids and self.provider == "cpu":
            raise PydanticCustomError("device_ids_cpu", f"{given} with --provider cpu: GPU ids are for cuda or "
                                      "tensorrt")
        if ids and len(ids) > 1 and self.sessions == "shared":
            raise PydanticCustomError("device_ids_shared", f"{given}: several GPUs need --sessions per-worker "
                                      "(shared sessions run on one GPU)")
        if ids and len(ids) > self.workers:  # a GPU no worker would use, unsaid
            raise PydanticCustomError("device_ids_unused", f"{given}: {len(ids)} GPUs for {self.workers} worker(s); "
                                      f"give each worker one (--workers {len(ids)})")
        return self

    @model_validator(mode="after")
    def _sockets_above_requests(self) -> Settings:
        """Room on the socket cap for every request the admission limit lets in, and one more to be told 503
        (below it, a client over the limit would see its connection closed without an answer); and within the
        open-file limit, where accept() fails instead, with a traceback in the log for every try."""
        if self.max_connections is None:
            return self
        if self.max_connections <= self.connection_limit():
            raise PydanticCustomError(
                "max_connections_low", f"{option_name('max_connections')} {self.max_connections}: at most "
                f"{self.connection_limit()} requests are admitted at once (workers + queue size + "
                f"{CONNECTION_HEADROOM}); give more connections than that, or leave it unset")
        files = open_file_limit()
        if files is not None and self.max_connections > files - FD_RESERVE:
            raise PydanticCustomError(
                "max_connections_high", f"{option_name('max_connections')} {self.max_connections}: the open-file limit "
                f"(ulimit -n) "
                f"is {files}, and the process keeps {FD_RESERVE} of them for itself; give at most "
                f"{files - FD_RESERVE}, or raise the limit")
        return self

    def gpu_ids(self) -> list[int] | None:
        """``device_ids`` as numbers (None: not given)."""
        return None if self.device_ids is None else [int(part) for part in self.device_ids.split(",")]

    @field_validator("token")
    @classmethod
    def _token_usable(cls, token: SecretStr | None) -> SecretStr | None:
        """Refuse a token no request can send: it would lock every /v1 route with 401 (``LOWRES3D_TOKEN=``)."""
        if token is None:
            return None
        value = token.get_secret_value()
        if not value.strip():
            raise PydanticCustomError(
                "empty_token", "empty; give a token, or leave both unset to serve /v1/* without one"
            )
        if value != value.strip():  # HTTP drops the whitespace around a header value: it could never match
            raise PydanticCustomError(
                "token_whitespace", "starts or ends with whitespace, which an Authorization header cannot carry"
            )
        return token

    def cors_origin_list(self) -> list[str]:
        """The origins CORS allows (empty: CORS off)."""
        return self.cors_origins.split(",") if self.cors_origins else []

    def connection_limit(self) -> int:
        """Requests in progress at once (their heads received, their answers not yet sent): the pool's places
        plus headroom for probes; a request beyond is answered 503 before its body is read (service/protocol.py).
        Connections that have sent no request do not count: :meth:`socket_limit` bounds those."""
        return self.workers + self.queue_size + CONNECTION_HEADROOM

    def socket_limit(self) -> int:
        """Open connections at once, idle ones included: ``max_connections``, or the open-file limit less
        FD_RESERVE (at most DEFAULT_SOCKET_LIMIT), and always more than the connection limit; a connection beyond
        closes the one idle the longest, or is closed itself (service/protocol.py)."""
        if self.max_connections is not None:
            return self.max_connections
        files = open_file_limit()
        room = DEFAULT_SOCKET_LIMIT if files is None else min(files - FD_RESERVE, DEFAULT_SOCKET_LIMIT)
        return max(room, self.connection_limit() + 1)

    def resolved_intra_op_threads(self) -> int:
        """The configured intra-op threads, or the usable CPUs divided among the workers (docs/service.md)."""
        if self.intra_op_threads is not None:
            return self.intra_op_threads
        return max(1, usable_cpus() // self.workers)
