"""Load test of the detection service from another process on loopback, over capacity on purpose.

    python benchmarks/load.py --models DIR [--clients 8] [--duration 20 | --requests N] [--json OUT] [--plot OUT.png]
    python benchmarks/load.py --url http://127.0.0.1:8000 [...]

Without ``--url`` it starts ``python -m service`` itself on 127.0.0.1 (a free
port; ``--workers``, ``--queue-size``, ``--sessions``, ``--intra-op-threads``,
``--mirror-tta`` passed on) and stops it at the end. ``--clients`` threads send the frames of
a KITTI folder (``--data``, default tests/data/kitti/training; ``--frame`` for
one) in turn until ``--duration`` seconds or ``--requests`` requests in total;
a client that gets a 503 waits ``--backoff-s`` before its next request. With
more clients than the server's workers + queue, some requests are refused with
503 by design. ``--bad-every N`` makes every Nth request a broken one (a
truncated scan, a cut-off PNG, a calibration without P2, a misspelt query
parameter), which must be answered 4xx, never 5xx: the service checks each of
them before the frame takes a place in its queue, so not even a full queue
answers them 503. Well-formed and broken requests each take the frames in turn.

Reports: throughput (answered 200 per second), p50/p99 latency of the 200s
and of everything, counts per status, the server's per-stage timings (from
the answers), and the server's resident memory (``process_resident_memory_bytes``
from /metrics) when ready, after 3 × clients warm-up requests sent at full
concurrency (every worker thread has run), and at the end. For long runs
(soak tests) it also samples memory and open file descriptors every second,
fits the memory's trend (MB per hour, over the run after its first tenth) and
lists throughput, latency and memory per tenth of the run; ``--plot`` draws
the latency histogram beside latency and memory over time.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import re
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Self

import numpy as np

try:
    import httpx
except ImportError:  # the runtime install (make setup) leaves the test tools out
    sys.exit("error: benchmarks/load.py needs httpx, which the runtime install leaves out; install the dev extras "
             "(make setup-dev) or .venv/bin/pip install 'httpx>=0.27'")

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.cli import (
    check_figure,
    check_output,
    non_negative_int,
    positive_float,
    positive_int,
    quiet_interrupt,
)
from pipeline.cpu import cpu_label
from pipeline.cpu import describe as describe_cpu
from pipeline.errors import InputError
from pipeline.frame import frame_ids

REPO = Path(__file__).resolve().parents[1]
KITTI = REPO / "tests" / "data" / "kitti" / "training"
DEFAULT_MODELS = REPO / "weights" / "edge"
# The broken requests of --bad-every, each made from a real frame; the service must answer each 4xx.
BROKEN_KINDS = ("points-truncated", "image-cut-off", "calib-without-P2", "query-misspelt")


@dataclass
class Sample:
    """One request: when it started (s since the run began), its latency (ms), status (or error name), and
    which upload it was (a frame id, or one of BROKEN_KINDS)."""

    start_s: float
    latency_ms: float
    status: str
    upload: str = ""
    broken: bool = False
    timings_ms: dict[str, float] | None = None


@dataclass
class LoadResult:
    """What a run measured."""

    url: str
    clients: int
    duration_s: float
    requests: int
    status_counts: dict[str, int]  # the well-formed requests' statuses
    throughput_ok_per_s: float
    throughput_all_per_s: float
    latency_ms: dict[str, dict[str, float]]  # per status, and "all"
    stage_p50_ms: dict[str, float]
    rss_mb: dict[str, float]
    rss_series: list[tuple[float, float]]  # (s since the load began, MB), sampled every second
    fds_series: list[tuple[float, float]] = field(default_factory=list)  # (s, the server's open file descriptors)
    frames_sent: int = 0  # distinct frames among the well-formed requests
    broken: dict = field(default_factory=dict)  # --bad-every: sent, statuses, answered_4xx
    server_errors: int = 0  # 5xx answers and transport errors, well-formed or not: each one is a defect
    trend: dict = field(default_factory=dict)  # memory slope, file descriptors, latency first vs last tenth
    windows: list[dict] = field(default_factory=list)  # per tenth of the run: throughput, p50, memory
    server: dict = field(default_factory=dict)
    machine: dict = field(default_factory=dict)


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@contextmanager
def started_service(models: Path, server_args: list[str], log_path: Path, timeout_s: float = 60.0) -> Iterator[str]:
    """Run ``python -m service`` on a free loopback port until the block ends; yields its URL."""
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    env = {k: v for k, v in os.environ.items() if not k.startswith("LOWRES3D_")}
    with open(log_path, "w") as log:
        process = subprocess.Popen(
            [sys.executable, "-m", "service", "--models", str(models), "--port", str(port), *server_args],
            cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT,
        )
    try:
        deadline = time.monotonic() + timeout_s
        while True:
            if process.poll() is not None:
                raise SystemExit(f"the service exited with {process.returncode}:\n{log_path.read_text()}")
            try:
                if httpx.get(f"{url}/readyz", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                raise SystemExit(f"the service was not ready within {timeout_s} s:\n{log_path.read_text()}")
            time.sleep(0.1)
        yield url
    finally:
        process.terminate()
        try:
            process.wait(30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(5)




def server_gauges(url: str, headers: dict[str, str]) -> dict[str, float]:
    """The server's resident memory (MB) and open file descriptors from its /metrics."""
    text = httpx.get(f"{url}/metrics", headers=headers, timeout=10).text
    values = {}
    for name, metric, scale in (("rss_mb", "process_resident_memory_bytes", 1e-6), ("fds", "process_open_fds", 1.0)):
        match = re.search(rf"^{metric} ([0-9.e+]+)$", text, re.MULTILINE)
        if match is None:
            raise SystemExit(f"{url}/metrics has no {metric}")
        values[name] = float(match.group(1)) * scale
    return values


def server_rss_mb(url: str, headers: dict[str, str]) -> float:
    """The server's resident memory from its /metrics (MB)."""
    return server_gauges(url, headers)["rss_mb"]


def _percentiles(values: list[float]) -> dict[str, float]:
    if not values:
        return {"p50": float("nan"), "p99": float("nan"), "mean": float("nan"), "max": float("nan")}
    array = np.asarray(values)
    return {"p50": float(np.percentile(array, 50)), "p99": float(np.percentile(array, 99)),
            "mean": float(array.mean()), "max": float(array.max())}


@dataclass(frozen=True)
class Upload:
    """One request's body and query: a frame of the folder, or a broken one made from it."""

    name: str
    files: dict
    params: dict
    broken: bool = False


def frame_upload(data: Path, frame: str, params: dict) -> Upload:
    """The image, scan and calibration of one KITTI frame, as the service's multipart fields."""
    files = {
        "image": (f"{frame}.png", (data / "image_2" / f"{frame}.png").read_bytes(), "image/png"),
        "points": (f"{frame}.bin", (data / "velodyne" / f"{frame}.bin").read_bytes(), "application/octet-stream"),
        "calib": (f"{frame}.txt", (data / "calib" / f"{frame}.txt").read_bytes(), "text/plain"),
    }
    return Upload(frame, files, params)


def broken_upload(good: Upload, kind: str) -> Upload:
    """A request a client gets wrong, made from a good one: the service must answer it 4xx."""
    files, params = dict(good.files), dict(good.params)
    name, data, mime = files[{"points-truncated": "points", "image-cut-off": "image"}.get(kind, "calib")]
    if kind == "points-truncated":  # not a whole number of 16-byte points
        files["points"] = (name, data[:-6], mime)
    elif kind == "image-cut-off":  # a PNG whose transfer stopped half-way
        files["image"] = (name, data[: len(data) // 2], mime)
    elif kind == "calib-without-P2":
        kept = [line for line in data.decode("utf-8-sig").splitlines() if not line.startswith("P2:")]
        files["calib"] = (name, "\n".join(kept).encode(), mime)
    elif kind == "query-misspelt":
        params = {"emulate_beam": 16}
    else:
        raise ValueError(f"unknown broken request {kind!r}; one of {BROKEN_KINDS}")
    return Upload(kind, files, params, broken=True)


class RequestSource:
    """What each request sends, shared by the clients: the frames in turn, with every ``bad_every``th request
    a broken one (0: none); stops after ``total`` requests (None: no limit). Thread-safe.

    The well-formed and the broken requests each go through the frames in turn on a count of their own: on one
    shared count, a ``bad_every`` dividing the number of frames (5 with the five bundled ones) broke the same
    frames every time, and those were never sent intact."""

    def __init__(self, data: Path, frames: list[str], params: dict, total: int | None, bad_every: int = 0) -> None:
        self.data, self.frames, self.params = data, frames, params
        self.bad_every = bad_every
        self._left = total
        self._count = 0
        self._turns = {False: 0, True: 0}  # requests sent so far: well-formed, broken
        self._lock = threading.Lock()

    def take(self) -> Upload | None:
        with self._lock:
            if self._left is not None:
                if self._left <= 0:
                    return None
                self._left -= 1
            index = self._count
            self._count += 1
            broken = bool(self.bad_every) and (index + 1) % self.bad_every == 0
            turn = self._turns[broken]
            self._turns[broken] += 1
        # Read per request (the page cache holds them): a folder of hundreds of frames is not held in memory.
        good = frame_upload(self.data, self.frames[turn % len(self.frames)], self.params)
        if broken:
            return broken_upload(good, BROKEN_KINDS[turn % len(BROKEN_KINDS)])
        return good


def _client_loop(
    url: str, source: RequestSource, headers: dict, stop: threading.Event, backoff_s: float, origin: float,
    samples: list[Sample], lock: threading.Lock,
) -> None:
    with httpx.Client(timeout=120, headers=headers) as client:
        while not stop.is_set() and (upload := source.take()) is not None:
            tic = time.perf_counter()
            timings = None
            try:
                response = client.post(f"{url}/v1/detect", files=upload.files, params=upload.params)
                status = str(response.status_code)
                if response.status_code == 200:
                    timings = response.json()["timings_ms"]
            except httpx.HTTPError as exc:
                status = f"error:{type(exc).__name__}"
            toc = time.perf_counter()
            with lock:
                samples.append(Sample(tic - origin, (toc - tic) * 1e3, status, upload.name, upload.broken, timings))
            if status == "503":
                stop.wait(backoff_s)


def drive(
    url: str, clients: int, duration_s: float | None, source: RequestSource, headers: dict, backoff_s: float,
) -> tuple[list[Sample], float]:
    """Run the clients until the duration passes or the source is spent; samples and wall time."""
    stop = threading.Event()
    samples: list[Sample] = []
    lock = threading.Lock()
    origin = time.perf_counter()
    threads = [
        threading.Thread(
            target=_client_loop, args=(url, source, headers, stop, backoff_s, origin, samples, lock), daemon=True,
        )
        for _ in range(clients)
    ]
    for thread in threads:
        thread.start()
    if duration_s is not None:
        stop.wait(duration_s)
        stop.set()
    for thread in threads:
        thread.join()
    return samples, time.perf_counter() - origin


class GaugeSampler:
    """Reads the server's memory and open file descriptors from /metrics every ``period_s`` in a background
    thread."""

    def __init__(self, url: str, headers: dict[str, str], period_s: float = 1.0) -> None:
        self.url, self.headers, self.period_s = url, headers, period_s
        self.rss: list[tuple[float, float]] = []
        self.fds: list[tuple[float, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def _loop(self) -> None:
        origin = time.perf_counter()
        while not self._stop.wait(self.period_s):
            try:
                gauges = server_gauges(self.url, self.headers)
            except httpx.HTTPError:
                continue  # a scrape lost under load is not a result
            now = round(time.perf_counter() - origin, 2)
            self.rss.append((now, gauges["rss_mb"]))
            self.fds.append((now, gauges["fds"]))

    def __enter__(self) -> Self:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


def memory_trend(rss_series: list[tuple[float, float]], wall_s: float) -> float | None:
    """The memory's slope in MB per hour, fitted over the run after its first tenth (while buffers and caches
    settle); None for fewer than 10 samples there."""
    series = np.asarray([(t, mb) for t, mb in rss_series if t >= 0.1 * wall_s], dtype=np.float64)
    if len(series) < 10 or np.ptp(series[:, 0]) <= 0:
        return None
    slope_per_s = np.polyfit(series[:, 0], series[:, 1], 1)[0]
    return float(slope_per_s * 3600.0)


def per_window(samples: list[Sample], rss_series: list[tuple[float, float]], wall_s: float,
               count: int = 10) -> list[dict]:
    """Throughput, p50 latency of the 200s and median memory in each of ``count`` equal parts of the run."""
    edges = np.linspace(0.0, wall_s, count + 1)
    ok = [s for s in samples if s.status == "200" and not s.broken]
    ok_start = np.asarray([s.start_s for s in ok])
    ok_ms = np.asarray([s.latency_ms for s in ok])
    rss = np.asarray(rss_series, dtype=np.float64).reshape(-1, 2)
    windows = []
    for begin, end in itertools.pairwise(edges):
        inside = (ok_start >= begin) & (ok_start < end)
        memory = rss[(rss[:, 0] >= begin) & (rss[:, 0] < end), 1]
        windows.append({
            "start_s": round(float(begin), 1), "end_s": round(float(end), 1),
            "ok_per_s": float(inside.sum() / (end - begin)) if end > begin else float("nan"),
            "p50_ms": float(np.median(ok_ms[inside])) if inside.any() else float("nan"),
            "rss_mb": float(np.median(memory)) if len(memory) else float("nan"),
        })
    return windows


def summarise(samples: list[Sample], wall_s: float, url: str, clients: int, rss: dict[str, float],
              gauges: GaugeSampler | None, server: dict) -> LoadResult:
    good = [s for s in samples if not s.broken]
    broken = [s for s in samples if s.broken]
    ok = [s for s in good if s.status == "200"]
    stages: dict[str, list[float]] = {}
    for sample in ok:
        for stage, ms in (sample.timings_ms or {}).items():
            stages.setdefault(stage, []).append(ms)
    rss_series = gauges.rss if gauges else []
    fds_series = gauges.fds if gauges else []
    windows = per_window(samples, rss_series, wall_s)
    tenth = max(1, len(ok) // 10)
    by_start = sorted(ok, key=lambda s: s.start_s)
    return LoadResult(
        url=url, clients=clients, duration_s=round(wall_s, 2), requests=len(samples),
        status_counts=dict(sorted(Counter(s.status for s in good).items())),
        throughput_ok_per_s=len(ok) / wall_s, throughput_all_per_s=len(samples) / wall_s,
        latency_ms={
            **{status: _percentiles([s.latency_ms for s in good if s.status == status])
               for status in sorted({s.status for s in good})},
            "all": _percentiles([s.latency_ms for s in good]),
        },
        stage_p50_ms={stage: float(np.median(values)) for stage, values in stages.items()},
        rss_mb=rss, rss_series=rss_series, fds_series=fds_series,
        frames_sent=len({s.upload for s in good}),
        broken={
            "sent": len(broken),
            "statuses": {kind: dict(sorted(Counter(s.status for s in broken if s.upload == kind).items()))
                         for kind in BROKEN_KINDS if any(s.upload == kind for s in broken)},
            "answered_4xx": sum(s.status.startswith("4") for s in broken),
        },
        server_errors=sum((s.status.startswith("5") and s.status != "503") or s.status.startswith("error")
                          for s in samples),
        trend={
            "rss_mb_per_hour": memory_trend(rss_series, wall_s),
            "fds_first": fds_series[0][1] if fds_series else None,
            "fds_last": fds_series[-1][1] if fds_series else None,
            "fds_max": max((n for _, n in fds_series), default=None),
            "p50_ms_first_tenth": float(np.median([s.latency_ms for s in by_start[:tenth]])) if ok else None,
            "p50_ms_last_tenth": float(np.median([s.latency_ms for s in by_start[-tenth:]])) if ok else None,
        },
        windows=windows, server=server,
        machine={**describe_cpu(), "platform": platform.platform(), "cpus": os.cpu_count(),
                 "python": platform.python_version()},
    )


def plot_load(samples: list[Sample], result: LoadResult, path: Path, title: str) -> None:
    """Left: latency histogram per status, log-scaled x. Right: each answered frame's latency and the
    server's memory over the run (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labelled = [(f"bad {s.status}" if s.broken else s.status, s) for s in samples]
    groups = {key: [s.latency_ms for k, s in labelled if k == key] for key in sorted({k for k, _ in labelled})}
    all_ms = [s.latency_ms for s in samples]
    bins = np.geomspace(max(min(all_ms), 0.1), max(all_ms) * 1.05, 40)
    figure, (histogram, timeline) = plt.subplots(1, 2, figsize=(13, 4.5), dpi=100)
    histogram.hist(list(groups.values()), bins=bins, stacked=True,
                   label=[f"{k} ({len(v)})" for k, v in groups.items()])
    histogram.set_xscale("log")
    histogram.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())  # minor labels overlap on a log axis
    histogram.set_xlabel("latency (ms, client side)")
    histogram.set_ylabel("requests")
    histogram.legend()

    ok = sorted((s.start_s, s.latency_ms) for s in samples if s.status == "200" and not s.broken)
    if ok:
        start, ms = np.asarray(ok).T
        timeline.plot(start, ms, ".", markersize=2, alpha=0.3, color="tab:blue", label="a 200's latency")
        windows = result.windows
        timeline.plot([(w["start_s"] + w["end_s"]) / 2 for w in windows], [w["p50_ms"] for w in windows],
                      "-o", color="tab:blue", label="p50 per tenth of the run")
    timeline.set_xlabel("seconds into the load")
    timeline.set_ylabel("latency (ms)", color="tab:blue")
    timeline.legend(loc="upper left")
    if result.rss_series:
        memory = timeline.twinx()
        seconds, mb = np.asarray(result.rss_series).T
        memory.plot(seconds, mb, color="tab:red", linewidth=1)
        memory.set_ylabel("server RSS (MB)", color="tab:red")
        low, high = float(mb.min()), float(mb.max())
        memory.set_ylim(low - max(10.0, 0.1 * low), high + max(10.0, 0.1 * high))
    figure.suptitle(title)
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)


def format_report(result: LoadResult) -> str:
    lines = [
        (f"service {result.url}: {result.server.get('preset')} models, {result.server.get('workers')} worker(s), "
         f"{result.server.get('sessions')} sessions, {result.server.get('intra_op_threads')} intra-op thread(s), "
         f"queue {result.server.get('queue_size')}, {result.server.get('providers')}"
         f"{', PIXOR with mirror TTA' if result.server.get('mirror_tta') else ''}"),
        f"machine: {cpu_label(result.machine)}, {result.machine['cpus']} CPUs, {result.machine['platform']}",
        (f"{result.clients} clients, {result.requests} requests in {result.duration_s} s, "
         f"{result.frames_sent} distinct frame(s)"),
        (f"status counts of the real frames (the broken ones: below): {result.status_counts}" if result.broken.get("sent")
         else f"status counts: {result.status_counts}"),
        (f"throughput: {result.throughput_ok_per_s:.2f} frames/s answered 200 "
         f"({result.throughput_all_per_s:.2f} requests/s in all)"),
        "latency ms (client side)   p50      p99      mean     max",
    ]
    for name, stats in result.latency_ms.items():
        lines.append(f"  {name:<24}" + "".join(f"{stats[k]:>9.1f}" for k in ("p50", "p99", "mean", "max")))
    if result.broken.get("sent"):
        lines.append(f"broken requests: {result.broken['answered_4xx']} of {result.broken['sent']} answered 4xx; "
                     + "; ".join(f"{kind} {statuses}" for kind, statuses in result.broken["statuses"].items()))
    lines.append(f"server errors (5xx other than 503, broken connections): {result.server_errors}")
    if result.stage_p50_ms:
        lines.append("server stages p50 ms: " + ", ".join(f"{k} {v:.1f}" for k, v in result.stage_p50_ms.items()))
    rss = result.rss_mb
    lines.append(
        f"server RSS MB: ready {rss['ready']:.1f}, after {3 * result.clients} warm-up requests {rss['warm']:.1f}, "
        f"end {rss['end']:.1f} "
        f"(end − warm {rss['end'] - rss['warm']:+.1f})"
    )
    trend = result.trend
    if trend.get("rss_mb_per_hour") is not None:
        lines.append(f"server RSS trend after the first tenth: {trend['rss_mb_per_hour']:+.1f} MB per hour")
    if trend.get("fds_first") is not None:
        lines.append(f"server open file descriptors: first {trend['fds_first']:.0f}, last {trend['fds_last']:.0f}, "
                     f"max {trend['fds_max']:.0f}")
    if trend.get("p50_ms_first_tenth") is not None:
        lines.append(f"p50 of the 200s: first tenth of the run {trend['p50_ms_first_tenth']:.1f} ms, "
                     f"last tenth {trend['p50_ms_last_tenth']:.1f} ms")
    if result.windows and result.duration_s >= 60:
        lines.append("per tenth of the run      200s/s   p50 ms   RSS MB")
        for window in result.windows:
            lines.append(f"  {window['start_s']:>7.0f}–{window['end_s']:<7.0f} s  {window['ok_per_s']:>8.2f}"
                         f"{window['p50_ms']:>9.1f}{window['rss_mb']:>9.1f}")
    elif result.rss_series:
        series = result.rss_series
        picks = [series[min(len(series) - 1, int(q * len(series)))] for q in (0.0, 0.25, 0.5, 0.75)] + [series[-1]]
        lines.append("server RSS MB during the load: " + ", ".join(f"{t:.0f} s {mb:.1f}" for t, mb in picks))
    return "\n".join(lines)


def run(
    url: str | None = None,
    models: Path = DEFAULT_MODELS,
    clients: int = 8,
    duration_s: float | None = 20.0,
    requests: int | None = None,
    data: Path = KITTI,
    frames: list[str] | None = None,
    emulate_beams: int | None = 16,
    bad_every: int = 0,
    token: str | None = None,
    backoff_s: float = 0.1,
    server_args: list[str] | None = None,
    plot: Path | None = None,
    log_path: Path = Path("outputs/load_service.log"),
) -> LoadResult:
    """Drive a service (started here when ``url`` is None) and measure it."""
    frames = frames or frame_ids(data)
    params = {"emulate_beams": emulate_beams} if emulate_beams else {}
    headers = {"Authorization": f"Bearer {token}"} if token else {}

    @contextmanager
    def target() -> Iterator[str]:
        if url is not None:
            yield url.rstrip("/")
        else:
            log_path.parent.mkdir(parents=True, exist_ok=True)
            with started_service(models, server_args or [], log_path) as started:
                yield started

    with target() as base:
        info = httpx.get(f"{base}/v1/model", headers=headers, timeout=10).json()
        server = {
            "preset": info["preset"], "workers": info["workers"], "sessions": info["sessions"],
            "queue_size": info["queue_size"], "intra_op_threads": info.get("intra_op_threads"),
            "mirror_tta": info.get("mirror_tta", False),
            "providers": sorted({p for ps in info["providers_in_use"].values() for p in ps}),
        }
        rss = {"ready": server_rss_mb(base, headers)}
        # Warm-up at full concurrency so every worker thread exists and has made its buffers.
        drive(base, clients, None, RequestSource(data, frames, params, 3 * clients), headers, backoff_s)
        rss["warm"] = server_rss_mb(base, headers)
        with GaugeSampler(base, headers) as gauges:
            source = RequestSource(data, frames, params, requests, bad_every)
            samples, wall = drive(base, clients, duration_s, source, headers, backoff_s)
        rss["end"] = server_rss_mb(base, headers)
    result = summarise(samples, wall, base, clients, rss, gauges, server)
    if plot is not None and samples:
        plot.parent.mkdir(parents=True, exist_ok=True)
        plot_load(samples, result, plot, f"{clients} clients, {server['workers']} worker(s), "
                                         f"queue {server['queue_size']}, {server['preset']} models")
    return result


def check_frames(data: Path, frames: list[str]) -> None:
    """Every frame must have its image, scan and calibration: an error names the first file missing."""
    for frame in frames:
        for folder, suffix in (("image_2", ".png"), ("velodyne", ".bin"), ("calib", ".txt")):
            if not (data / folder / f"{frame}{suffix}").is_file():
                raise InputError(f"--data {data}: frame {frame} has no {folder}/{frame}{suffix}")


@quiet_interrupt("no report was written (--json and --plot come at the end); a service it started is stopped")
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python benchmarks/load.py",
        description="Load-test the lowres3d detection service on loopback (deliberately over capacity): "
        "throughput, p50/p99 latency, status counts, server memory and file descriptors over the run "
        "(a soak test when long), broken requests mixed in on request.",
    )
    parser.add_argument("--url", help="a running service (default: start one on 127.0.0.1 with --models)")
    parser.add_argument("--models", type=Path, default=DEFAULT_MODELS, help=f"model directory (default {DEFAULT_MODELS})")
    parser.add_argument("--clients", type=positive_int, default=8, help="concurrent clients (default 8)")
    bound = parser.add_mutually_exclusive_group()
    bound.add_argument("--duration", type=positive_float, help="seconds of load (default 20 unless --requests)")
    bound.add_argument("--requests", type=positive_int, help="total requests instead of a duration")
    parser.add_argument("--data", type=Path, default=KITTI,
                        help="KITTI object folder whose frames are sent in turn (default tests/data/kitti/training)")
    parser.add_argument("--frame", metavar="ID", help="send only this frame of --data")
    parser.add_argument("--emulate-beams", "--beams", type=non_negative_int, default=16, metavar="N",
                        help="server-side thinning of the 64-line scan (default 16; 0: off)")
    parser.add_argument("--bad-every", type=non_negative_int, default=0, metavar="N",
                        help="make every Nth request a broken one, which must be answered 4xx (default 0: none)")
    parser.add_argument("--token", default=os.environ.get("LOWRES3D_TOKEN"), help="bearer token (default $LOWRES3D_TOKEN)")
    parser.add_argument("--backoff-s", type=float, default=0.1, help="a client's pause after a 503 (default 0.1)")
    parser.add_argument("--workers", type=int, help="started service: inference workers")
    parser.add_argument("--queue-size", type=int, help="started service: queue size")
    parser.add_argument("--sessions", choices=["shared", "per-worker"], help="started service: session mode")
    parser.add_argument("--intra-op-threads", type=int, help="started service: ONNX Runtime threads per session")
    parser.add_argument("--mirror-tta", action="store_true",
                        help="started service: PIXOR also on the mirrored BEV (python -m service --mirror-tta)")
    parser.add_argument("--json", type=Path, help="write the result as JSON here")
    parser.add_argument("--plot", type=Path, help="write a PNG here: latency histogram, latency and memory over time")
    args = parser.parse_args(argv)
    if not args.backoff_s >= 0:
        parser.error("--backoff-s must be 0 or more")
    server_args: list[str] = []
    for flag in ("workers", "queue_size", "sessions", "intra_op_threads"):
        value = getattr(args, flag)
        if value is not None:
            server_args += [f"--{flag.replace('_', '-')}", str(value)]
    if args.mirror_tta:
        server_args.append("--mirror-tta")
    if args.url and server_args:
        parser.error("--workers/--queue-size/--sessions/--intra-op-threads/--mirror-tta apply only to a service "
                     "started here")
    if args.url is None and not args.models.is_dir():
        parser.error(f"--models: {args.models} is not a directory (export one with `python -m export`)")
    try:
        if not (args.data / "velodyne").is_dir():
            raise InputError(f"--data {args.data}: not a KITTI object folder (no velodyne/ inside)")
        frames = [args.frame] if args.frame else frame_ids(args.data)
        if not frames:
            raise InputError(f"--data {args.data}: no frames in its velodyne/")
        check_frames(args.data, frames)
        # Before the load, so a bad path does not lose its report.
        if args.json is not None:
            check_output(args.json, "--json")
        if args.plot is not None:
            check_figure(args.plot, "--plot")
    except InputError as exc:
        parser.error(str(exc))
    duration = args.duration if args.duration is not None else (None if args.requests else 20.0)
    try:
        result = run(
            url=args.url, models=args.models, clients=args.clients, duration_s=duration, requests=args.requests,
            data=args.data, frames=frames, emulate_beams=args.emulate_beams or None, bad_every=args.bad_every,
            token=args.token, backoff_s=args.backoff_s, server_args=server_args, plot=args.plot,
        )
    except httpx.TransportError as exc:  # nothing listening at --url, or it went away before the load began
        where = f"--url {args.url}" if args.url else "the service started here"
        print(f"error: {where}: cannot reach the service ({exc}); start it first (python -m service) "
              "or leave --url out to start one here", file=sys.stderr)
        return 2
    print(format_report(result))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(asdict(result), indent=2))
        print(f"wrote {args.json}")
    if args.plot:
        print(f"wrote {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
