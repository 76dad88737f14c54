"""Prometheus metrics of one app instance (its own registry: several apps in one process do not mix).

Exposed at ``GET /metrics``: request counts by route, method and status (each label from a fixed set:
the service's routes or "unmatched", HTTP's methods or "other"; 499 for a client that left before its answer);
request latency per route; per-stage latency of the detector; inference queue
depth, in-flight frames and frames stopped on a worker; the warnings frames were answered with, by code
(one of pipeline.checks.FRAME_WARNING_CODES or "other"), and those the loaded models carry (LOAD_WARNING_CODES);
HTTP requests in flight; connections closed without an answer, by reason (CONNECTION_CLOSE_REASONS);
readiness; which model is loaded (``lowres3d_model_info``); and the process collector's memory and CPU
(``process_resident_memory_bytes``, Linux).
"""

from __future__ import annotations

from collections.abc import Iterable

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    Info,
    ProcessCollector,
    generate_latest,
)

from pipeline.checks import FRAME_WARNING_CODES, LOAD_WARNING_CODES

# The label of a warning code the service does not know (none is made today): the series stay bounded.
OTHER_WARNING_CODE = "other"

# Why service/protocol.py closed a connection without an answer: the reason label's values.
CONNECTION_CLOSE_REASONS = ("head_timeout", "send_timeout", "idle_evicted", "over_limit")

# Seconds: from a fast stage of a tiny model (~0.1 ms) to a paper-size frame on a CPU (~10 s).
LATENCY_BUCKETS = (0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)


class Metrics:
    """The service's metric families, registered in a private registry."""

    content_type = CONTENT_TYPE_LATEST

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        ProcessCollector(registry=self.registry)
        self.requests = Counter(
            "lowres3d_http_requests", "HTTP requests answered", ["route", "method", "status"], registry=self.registry
        )
        self.request_latency = Histogram(
            "lowres3d_http_request_duration_seconds", "HTTP request latency, first byte in to last byte out",
            ["route"], buckets=LATENCY_BUCKETS, registry=self.registry,
        )
        self.http_in_flight = Gauge(
            "lowres3d_http_requests_in_flight", "HTTP requests being handled", registry=self.registry
        )
        self.stage_latency = Histogram(
            "lowres3d_stage_duration_seconds",
            "latency of each detection stage (total = queue + parse + detector, + render on the picture routes)",
            ["stage"], buckets=LATENCY_BUCKETS, registry=self.registry,
        )
        self.queue_depth = Gauge(
            "lowres3d_inference_queue_depth", "frames admitted and waiting for a worker (their uploads still "
            "arriving included)", registry=self.registry
        )
        self.in_flight = Gauge(
            "lowres3d_inference_in_flight", "frames being processed by a worker", registry=self.registry
        )
        self.rejected = Counter(
            "lowres3d_inference_rejected", "frames refused or abandoned", ["reason"], registry=self.registry
        )
        self.stopped = Counter(
            "lowres3d_inference_stopped", "frames stopped on their worker after their deadline or their request's end",
            registry=self.registry,
        )
        self.frame_warnings = Counter(
            "lowres3d_frame_warnings", "warnings the answered frames carried, by code (a sensor fault, a rig unlike "
            "the training one, input dropped or adjusted)", ["code"], registry=self.registry
        )
        self._warning_codes = frozenset(FRAME_WARNING_CODES)
        for code in (*FRAME_WARNING_CODES, OTHER_WARNING_CODE):  # every series from the start, at 0: rate() has a base
            self.frame_warnings.labels(code=code)
        # A model loaded with a warning (untrained weights, a provider that fell back to the CPU …) answers every
        # frame as if it were fine: 1 per code the loaded session pairs carry, every code's series at 0 before.
        self.model_warnings = Gauge(
            "lowres3d_model_warnings", "1 for each warning code the loaded models carry (untrained weights, a "
            "provider that did not load, INT8 weights this CPU could saturate, FP16 on the CPU)", ["code"],
            registry=self.registry,
        )
        for code in LOAD_WARNING_CODES:
            self.model_warnings.labels(code=code).set(0)
        # Connections the protocol closed without an answer (service/protocol.py): the reasons are its fixed set,
        # every series at 0 from the start.
        self.connections_closed = Counter(
            "lowres3d_connections_closed", "connections closed by the service without an answer: head_timeout (sent "
            "nothing within --receive-timeout-s), send_timeout (read none of an answer within --send-timeout-s), "
            "idle_evicted (idle, closed to make room for a new one at --max-connections), over_limit (new, at the "
            "cap with none idle)", ["reason"], registry=self.registry,
        )
        for reason in CONNECTION_CLOSE_REASONS:
            self.connections_closed.labels(reason=reason)
        self.ready = Gauge("lowres3d_ready", "1 when models are loaded and warmed up", registry=self.registry)
        # Labels, one series: id (manifest.json's sha256), directory, preset, precision, format, weights,
        # training_data, two_stage, mirror_tta, providers, sha256_<file> (service/runtime.py sets them).
        self.model = Info("lowres3d_model", "the loaded model: id (sha256 of its manifest.json), directory, preset, "
                          "precision and each file's sha256", registry=self.registry)

    def observe_stages(self, timings_ms: dict[str, float]) -> None:
        """Record one frame's per-stage timings (milliseconds)."""
        for stage, ms in timings_ms.items():
            self.stage_latency.labels(stage=stage).observe(ms / 1000.0)

    def count_warnings(self, codes: Iterable[str]) -> None:
        """Count one frame's warning codes (an unknown one as OTHER_WARNING_CODE)."""
        for code in codes:
            self.frame_warnings.labels(code=code if code in self._warning_codes else OTHER_WARNING_CODE).inc()

    def set_model_warnings(self, codes: Iterable[str]) -> None:
        """The loaded models' warning codes: 1 for those given, 0 for the other known ones."""
        present = set(codes)
        for code in LOAD_WARNING_CODES:
            self.model_warnings.labels(code=code).set(1 if code in present else 0)

    def render(self) -> bytes:
        """The Prometheus text exposition of every metric."""
        return generate_latest(self.registry)
