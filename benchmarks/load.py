"""Load test of the detection service from another process on loopback, over capacity on purpose.

    python benchmarks/load.py --models DIR [--clients 8] [--duration 20 | --requests N] [--json OUT] [--plot OUT.png]
    python benchmarks/load.py --url http://127.0.0.1:8000 [...]

Without ``--url`` it starts ``python -m service`` itself on 127.0.0.1 (a free
port; ``--workers``, ``--queue-size``, ``--sessions``, ``--intra-op-threads``
passed on) and stops it at the end. ``--clients`` threads each send the same
real KITTI frame (tests/data/kitti/training) in a loop until ``--duration``
seconds or ``--requests`` requests in total; a client that gets a 503 waits
``--backoff-s`` before its next request. With more clients than the server's
workers + queue, some requests are refused with 503 by design.

Reports: throughput (answered 200 per second), p50/p99 latency of the 200s
and of everything, counts per status, the server's per-stage timings (from
the answers), and the server's resident memory (``process_resident_memory_bytes``
from /metrics) when ready, after 3 × clients warm-up requests sent at full
concurrency (every worker thread has run), and at the end.
"""

from __future__ import annotations

import argparse
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

import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[1]
KITTI = REPO / "tests" / "data" / "kitti" / "training"
DEFAULT_MODELS = REPO / "weights" / "edge"


@dataclass
class Sample:
    """One request: when it started (s since the run began), its latency (ms), status (or error name)."""

    start_s: float
    latency_ms: float
    status: str
    timings_ms: dict[str, float] | None = None


@dataclass
class LoadResult:
    """What a run measured."""

    url: str
    clients: int
    duration_s: float
    requests: int
    status_counts: dict[str, int]
    throughput_ok_per_s: float
    throughput_all_per_s: float
    latency_ms: dict[str, dict[str, float]]  # per status, and "all"
    stage_p50_ms: dict[str, float]
    rss_mb: dict[str, float]
    rss_series: list[tuple[float, float]]  # (s since the load began, MB), sampled every second
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


def server_rss_mb(url: str, headers: dict[str, str]) -> float:
    """The server's resident memory from its /metrics (MB)."""
    text = httpx.get(f"{url}/metrics", headers=headers, timeout=10).text
    match = re.search(r"^process_resident_memory_bytes ([0-9.e+]+)$", text, re.MULTILINE)
    if match is None:
        raise SystemExit(f"{url}/metrics has no process_resident_memory_bytes")
    return float(match.group(1)) / 1e6


def _percentiles(values: list[float]) -> dict[str, float]:
    if not values:
        return {"p50": float("nan"), "p99": float("nan"), "mean": float("nan"), "max": float("nan")}
    array = np.asarray(values)
    return {"p50": float(np.percentile(array, 50)), "p99": float(np.percentile(array, 99)),
            "mean": float(array.mean()), "max": float(array.max())}


class RequestBudget:
    """How many requests the clients may still send together (None: no limit); thread-safe."""

    def __init__(self, total: int | None) -> None:
        self._left = total
        self._lock = threading.Lock()

    def take(self) -> bool:
        with self._lock:
            if self._left is None:
                return True
            if self._left <= 0:
                return False
            self._left -= 1
            return True


def _client_loop(
    url: str, files: dict, params: dict, headers: dict, stop: threading.Event, budget: RequestBudget,
    backoff_s: float, origin: float, samples: list[Sample], lock: threading.Lock,
) -> None:
    with httpx.Client(timeout=120, headers=headers) as client:
        while not stop.is_set() and budget.take():
            tic = time.perf_counter()
            timings = None
            try:
                response = client.post(f"{url}/v1/detect", files=files, params=params)
                status = str(response.status_code)
                if response.status_code == 200:
                    timings = response.json()["timings_ms"]
            except httpx.HTTPError as exc:
                status = f"error:{type(exc).__name__}"
            toc = time.perf_counter()
            with lock:
                samples.append(Sample(tic - origin, (toc - tic) * 1e3, status, timings))
            if status == "503":
                stop.wait(backoff_s)


def drive(
    url: str, clients: int, duration_s: float | None, requests: int | None, files: dict, params: dict,
    headers: dict, backoff_s: float,
) -> tuple[list[Sample], float]:
    """Run the clients until the duration passes or the request budget is spent; samples and wall time."""
    stop = threading.Event()
    budget = RequestBudget(requests)
    samples: list[Sample] = []
    lock = threading.Lock()
    origin = time.perf_counter()
    threads = [
        threading.Thread(
            target=_client_loop,
            args=(url, files, params, headers, stop, budget, backoff_s, origin, samples, lock),
            daemon=True,
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


class RssSampler:
    """Reads the server's RSS from /metrics every ``period_s`` in a background thread."""

    def __init__(self, url: str, headers: dict[str, str], period_s: float = 1.0) -> None:
        self.url, self.headers, self.period_s = url, headers, period_s
        self.series: list[tuple[float, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def _loop(self) -> None:
        origin = time.perf_counter()
        while not self._stop.wait(self.period_s):
            try:
                self.series.append((round(time.perf_counter() - origin, 2), server_rss_mb(self.url, self.headers)))
            except httpx.HTTPError:
                pass  # a scrape lost under load is not a result

    def __enter__(self) -> Self:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


def summarise(samples: list[Sample], wall_s: float, url: str, clients: int, rss: dict[str, float],
              rss_series: list[tuple[float, float]], server: dict) -> LoadResult:
    ok = [s for s in samples if s.status == "200"]
    stages: dict[str, list[float]] = {}
    for sample in ok:
        for stage, ms in (sample.timings_ms or {}).items():
            stages.setdefault(stage, []).append(ms)
    return LoadResult(
        url=url, clients=clients, duration_s=round(wall_s, 2), requests=len(samples),
        status_counts=dict(sorted(Counter(s.status for s in samples).items())),
        throughput_ok_per_s=len(ok) / wall_s, throughput_all_per_s=len(samples) / wall_s,
        latency_ms={
            **{status: _percentiles([s.latency_ms for s in samples if s.status == status])
               for status in sorted({s.status for s in samples})},
            "all": _percentiles([s.latency_ms for s in samples]),
        },
        stage_p50_ms={stage: float(np.median(values)) for stage, values in stages.items()},
        rss_mb=rss, rss_series=rss_series, server=server,
        machine={"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
                 "cpus": os.cpu_count(), "python": platform.python_version()},
    )


def plot_histogram(samples: list[Sample], path: Path, title: str) -> None:
    """Latency histogram, 200s and 503s stacked, log-scaled x (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = {status: [s.latency_ms for s in samples if s.status == status] for status in sorted({s.status for s in samples})}
    all_ms = [s.latency_ms for s in samples]
    bins = np.geomspace(max(min(all_ms), 0.1), max(all_ms) * 1.05, 40)
    figure, axis = plt.subplots(figsize=(8, 4.5), dpi=100)
    axis.hist(list(groups.values()), bins=bins, stacked=True, label=[f"{k} ({len(v)})" for k, v in groups.items()])
    axis.set_xscale("log")
    axis.set_xlabel("latency (ms, client side)")
    axis.set_ylabel("requests")
    axis.set_title(title)
    axis.legend()
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)


def format_report(result: LoadResult) -> str:
    lines = [
        (f"service {result.url}: {result.server.get('preset')} models, {result.server.get('workers')} worker(s), "
         f"{result.server.get('sessions')} sessions, {result.server.get('intra_op_threads')} intra-op thread(s), "
         f"queue {result.server.get('queue_size')}, {result.server.get('providers')}"),
        f"machine: {result.machine['processor']}, {result.machine['cpus']} CPUs, {result.machine['platform']}",
        f"{result.clients} clients, {result.requests} requests in {result.duration_s} s",
        f"status counts: {result.status_counts}",
        (f"throughput: {result.throughput_ok_per_s:.2f} frames/s answered 200 "
         f"({result.throughput_all_per_s:.2f} requests/s in all)"),
        "latency ms (client side)   p50      p99      mean     max",
    ]
    for name, stats in result.latency_ms.items():
        lines.append(f"  {name:<24}" + "".join(f"{stats[k]:>9.1f}" for k in ("p50", "p99", "mean", "max")))
    if result.stage_p50_ms:
        lines.append("server stages p50 ms: " + ", ".join(f"{k} {v:.1f}" for k, v in result.stage_p50_ms.items()))
    rss = result.rss_mb
    lines.append(
        f"server RSS MB: ready {rss['ready']:.1f}, after {3 * result.clients} warm-up requests {rss['warm']:.1f}, "
        f"end {rss['end']:.1f} "
        f"(end − warm {rss['end'] - rss['warm']:+.1f})"
    )
    if result.rss_series:
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
    frame: str = "000006",
    emulate_beams: int | None = 16,
    token: str | None = None,
    backoff_s: float = 0.1,
    server_args: list[str] | None = None,
    plot: Path | None = None,
    log_path: Path = Path("outputs/load_service.log"),
) -> LoadResult:
    """Drive a service (started here when ``url`` is None) and measure it."""
    files = {
        "image": (f"{frame}.png", (KITTI / "image_2" / f"{frame}.png").read_bytes(), "image/png"),
        "points": (f"{frame}.bin", (KITTI / "velodyne" / f"{frame}.bin").read_bytes(), "application/octet-stream"),
        "calib": (f"{frame}.txt", (KITTI / "calib" / f"{frame}.txt").read_bytes(), "text/plain"),
    }
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
            "providers": sorted({p for ps in info["providers_in_use"].values() for p in ps}),
        }
        rss = {"ready": server_rss_mb(base, headers)}
        # Warm-up at full concurrency so every worker thread exists and has made its buffers.
        drive(base, clients, None, 3 * clients, files, params, headers, backoff_s)
        rss["warm"] = server_rss_mb(base, headers)
        with RssSampler(base, headers) as sampler:
            samples, wall = drive(base, clients, duration_s, requests, files, params, headers, backoff_s)
        rss["end"] = server_rss_mb(base, headers)
    result = summarise(samples, wall, base, clients, rss, sampler.series, server)
    if plot is not None and samples:
        plot.parent.mkdir(parents=True, exist_ok=True)
        plot_histogram(samples, plot, f"{clients} clients, {server['workers']} worker(s), queue {server['queue_size']}, "
                                      f"{server['preset']} models")
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python benchmarks/load.py",
        description="Load-test the lowres3d detection service on loopback (deliberately over capacity): "
        "throughput, p50/p99 latency, status counts, server memory before and after.",
    )
    parser.add_argument("--url", help="a running service (default: start one on 127.0.0.1 with --models)")
    parser.add_argument("--models", type=Path, default=DEFAULT_MODELS, help=f"model directory (default {DEFAULT_MODELS})")
    parser.add_argument("--clients", type=int, default=8, help="concurrent clients (default 8)")
    bound = parser.add_mutually_exclusive_group()
    bound.add_argument("--duration", type=float, help="seconds of load (default 20 unless --requests)")
    bound.add_argument("--requests", type=int, help="total requests instead of a duration")
    parser.add_argument("--frame", default="000006", help="KITTI frame of tests/data/kitti/training (default 000006)")
    parser.add_argument("--emulate-beams", type=int, default=16, help="server-side thinning of the 64-line scan (0: off)")
    parser.add_argument("--token", default=os.environ.get("LOWRES3D_TOKEN"), help="bearer token (default $LOWRES3D_TOKEN)")
    parser.add_argument("--backoff-s", type=float, default=0.1, help="a client's pause after a 503 (default 0.1)")
    parser.add_argument("--workers", type=int, help="started service: inference workers")
    parser.add_argument("--queue-size", type=int, help="started service: queue size")
    parser.add_argument("--sessions", choices=["shared", "per-worker"], help="started service: session mode")
    parser.add_argument("--intra-op-threads", type=int, help="started service: ONNX Runtime threads per session")
    parser.add_argument("--json", type=Path, help="write the result as JSON here")
    parser.add_argument("--plot", type=Path, help="write a latency histogram PNG here")
    args = parser.parse_args(argv)
    if args.clients < 1 or (args.requests is not None and args.requests < 1):
        parser.error("--clients and --requests must be at least 1")
    if (args.duration is not None and not args.duration > 0) or not args.backoff_s >= 0:
        parser.error("--duration must be a positive number of seconds and --backoff-s 0 or more")
    server_args: list[str] = []
    for flag in ("workers", "queue_size", "sessions", "intra_op_threads"):
        value = getattr(args, flag)
        if value is not None:
            server_args += [f"--{flag.replace('_', '-')}", str(value)]
    if args.url and server_args:
        parser.error("--workers/--queue-size/--sessions/--intra-op-threads apply only to a service started here")
    if args.url is None and not args.models.is_dir():
        parser.error(f"--models: {args.models} is not a directory (export one with `python -m export`)")
    duration = args.duration if args.duration is not None else (None if args.requests else 20.0)
    try:
        result = run(
            url=args.url, models=args.models, clients=args.clients, duration_s=duration, requests=args.requests,
            frame=args.frame, emulate_beams=args.emulate_beams or None, token=args.token, backoff_s=args.backoff_s,
            server_args=server_args, plot=args.plot,
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
