"""Load test of the detection service from another process on loopback, over capacity on purpose.

    python benchmarks/load.py --models DIR [--clients 8] [--duration 20 | --requests N] [--json OUT] [--plot OUT.png]
    python benchmarks/load.py --url http://127.0.0.1:8000 [...]
    python benchmarks/load.py --url http://BOX:8000 --rate 10 --clients 4 --send-beams 16 [...]

Without ``--url`` it starts ``python -m service`` itself on 127.0.0.1 (a free
port; ``--workers``, ``--queue-size``, ``--sessions``, ``--intra-op-threads``,
``--mirror-tta`` passed on; its log to ``--log``) and stops it at the end. The
frames of a KITTI folder (``--data``, default tests/data/kitti/training;
``--frame`` for one) are sent in turn until ``--duration`` seconds or
``--requests`` requests in total.

Closed loop (the default): ``--clients`` threads each send their next request
when the previous one is answered; a client that gets a 503 waits
``--backoff-s`` first. With more clients than the server's workers + queue,
some requests are refused with 503 by design. A slower server thus gets fewer
requests. Open loop (``--rate HZ``): requests are due at fixed intervals, 1/HZ
apart in all (a sensor's frame rate), with at most ``--clients`` in flight; a
request due while all of them are busy is sent as soon as one frees and counted
late, and its latency, like every one's, runs from its due time, so waiting
shows; one still unsent when ``--duration`` ends is counted unsent.

The scans are sent as stored (KITTI's 64 lines) and thinned on the server
(``--emulate-beams``, default 16) unless ``--send-beams N`` thins them here,
once before the run, and sends N-line scans as an N-line sensor would.

``--bad-every N`` makes every Nth request a broken one (a truncated scan, a
cut-off PNG, a calibration without P2, a misspelt query parameter), which must
be answered 4xx, or 503 when the queue is full: the service takes a frame's
place before it reads the upload (so that a burst of uploads cannot hold more
memory than its queue), and checks the upload once it has one; never another 5xx.
Well-formed and broken requests each take the frames in turn.

Reports: throughput (answered 200 per second), p50/p99 latency (p90 too in the
JSON and the open loop) of the 200s and of everything, counts per status, the
server's per-stage timings (from the answers), the load generator's own CPU
time (it may share the server's cores), the server's resident memory
(``process_resident_memory_bytes`` from /metrics) when ready, after 3 × clients warm-up requests sent at full
concurrency (every worker thread has run), and at the end. For long runs
(soak tests) it also samples memory and open file descriptors every second,
fits the memory's trend (MB per hour, over the run after its first tenth) and
lists throughput, latency and memory per tenth of the run; ``--plot`` draws
the latency histogram beside latency and memory over time. The machine it names
is the load generator's: the server's too only when started here.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import platform
import queue
import re
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Self

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

try:
    import httpx
except ImportError:  # the runtime install (make setup) leaves the test tools out: exit status 2, as in latency.py
    from pipeline.cli import missing_extra

    raise missing_extra("error: benchmarks/load.py needs httpx, which the runtime install leaves out; install the "
                        "dev extras (make setup-dev) or .venv/bin/pip install 'httpx>=0.27'") from None

from pipeline.beams import BEAM_COUNTS, emulate_beams
from pipeline.cli import (
    HelpFormatter,
    check_figure,
    check_not_input,
    check_output,
    examples,
    non_negative_int,
    positive_float,
    positive_int,
    quiet_interrupt,
)
from pipeline.cpu import cpu_label, usable_cpus
from pipeline.cpu import describe as describe_cpu
from pipeline.errors import InputError
from pipeline.frame import frame_ids
from pipeline.kitti import POINT_BYTES, read_velodyne, write_velodyne
from pipeline.model_files import DEFAULT_MODELS
from pipeline.provenance import code_version

REPO = Path(__file__).resolve().parents[1]
KITTI = REPO / "tests" / "data" / "kitti" / "training"
# The broken requests of --bad-every, each made from a real frame; the service must answer each 4xx.
BROKEN_KINDS = ("points-truncated", "image-cut-off", "calib-without-P2", "query-misspelt")
DEFAULT_LOG = Path("outputs/load_service.log")  # relative to the working directory, as it always was


@dataclass
class Sample:
    """One request: when it started (s since the run began; in the open loop, when it was due), its latency (ms,
    in the open loop from its due time), status (or error name), which upload it was (a frame id, or one of
    BROKEN_KINDS) and the points it carried. Open loop only: how long after its due time it went out."""

    start_s: float
    latency_ms: float
    status: str
    upload: str = ""
    broken: bool = False
    timings_ms: dict[str, float] | None = None
    points: int = 0
    lag_ms: float = 0.0


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
    mode: str = "closed-loop"  # or "open-loop" (--rate)
    latency_from: str = "send"  # "schedule" in the open loop: each request's latency counts from its due time
    open_loop: dict = field(default_factory=dict)  # --rate: requested vs achieved rate, late and unsent requests
    thinning: dict = field(default_factory=dict)  # where the scans were thinned (client, server, none), points sent
    # The machine load.py runs on. It is the server's too only when load.py started the service
    # (client_shares_server_machine True); with --url the server's machine is not known here (None).
    client_machine: dict = field(default_factory=dict)
    code: dict = field(default_factory=code_version)  # the lowres3d code of load.py (and of a service it started)
    server_machine: dict | None = None
    client_shares_server_machine: bool | None = None
    client_cpu_s: float = 0.0  # the load generator's own CPU seconds (all its threads) over the measured run
    client_cpu_cores: float = 0.0  # client_cpu_s / the run's wall time: cores it kept busy on average
    service_log: str | None = None  # the started service's log (--log)


def listening_port(pid: int) -> int | None:
    """The IPv4 TCP port process ``pid`` listens on, None while it listens on none (Linux: the socket inodes of
    /proc/PID/fd looked up in /proc/PID/net/tcp). How a service started with --port 0 is found, whatever its
    log level or format: a port picked free here and passed on could be taken by another process meanwhile."""
    inodes = set()
    try:
        for fd in os.listdir(f"/proc/{pid}/fd"):
            with suppress(OSError):  # closed meanwhile
                link = os.readlink(f"/proc/{pid}/fd/{fd}")
                if link.startswith("socket:["):
                    inodes.add(link.removeprefix("socket:[").removesuffix("]"))
        table = Path(f"/proc/{pid}/net/tcp").read_text().splitlines()[1:]
    except OSError:  # the process has ended
        return None
    for row in table:  # sl local_address rem_address st ... inode: state 0A is LISTEN
        fields = row.split()
        if fields[3] == "0A" and fields[9] in inodes:
            return int(fields[1].rsplit(":", 1)[1], 16)
    return None


@contextmanager
def started_service(models: Path, server_args: list[str], log_path: Path, timeout_s: float = 60.0) -> Iterator[str]:
    """Run ``python -m service`` on a loopback port of its choosing until the block ends; yields its URL."""
    url = ""
    env = {k: v for k, v in os.environ.items() if not k.startswith("LOWRES3D_")}
    with open(log_path, "w") as log:
        process = subprocess.Popen(
            # Resolved here: the service runs in the checkout, and a relative --models names a folder under the
            # caller's working directory (where main checked it).
            [sys.executable, "-m", "service", "--models", str(Path(models).resolve()), "--port", "0",
             *server_args],
            cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT,
        )
    try:
        deadline = time.monotonic() + timeout_s
        while True:
            if process.poll() is not None:
                raise SystemExit(f"the service exited with {process.returncode}:\n{log_path.read_text()}")
            if not url and (port := listening_port(process.pid)) is not None:
                url = f"http://127.0.0.1:{port}"
            try:
                if url and httpx.get(f"{url}/readyz", timeout=1).status_code == 200:
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
    """p50, p90, p99, mean and max (NaN for none)."""
    if not values:
        return {key: float("nan") for key in ("p50", "p90", "p99", "mean", "max")}
    array = np.asarray(values)
    return {"p50": float(np.percentile(array, 50)), "p90": float(np.percentile(array, 90)),
            "p99": float(np.percentile(array, 99)), "mean": float(array.mean()), "max": float(array.max())}


@dataclass(frozen=True)
class Upload:
    """One request's body and query: a frame of the folder, or a broken one made from it."""

    name: str
    files: dict
    params: dict
    broken: bool = False

    @property
    def points(self) -> int:
        """Points in the scan sent (whole 16-byte rows)."""
        return len(self.files["points"][1]) // POINT_BYTES


def frame_upload(data: Path, frame: str, params: dict, scans: Path | None = None) -> Upload:
    """The image, scan and calibration of one KITTI frame, as the service's multipart fields; the scan from
    ``scans`` (a folder of FRAME.bin) when given, else from ``data``/velodyne."""
    scan = (scans if scans is not None else data / "velodyne") / f"{frame}.bin"
    files = {
        "image": (f"{frame}.png", (data / "image_2" / f"{frame}.png").read_bytes(), "image/png"),
        "points": (f"{frame}.bin", scan.read_bytes(), "application/octet-stream"),
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

    def __init__(self, data: Path, frames: list[str], params: dict, total: int | None, bad_every: int = 0,
                 scans: Path | None = None) -> None:
        self.data, self.frames, self.params = data, frames, params
        self.bad_every, self.scans = bad_every, scans
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
        good = frame_upload(self.data, self.frames[turn % len(self.frames)], self.params, self.scans)
        if broken:
            return broken_upload(good, BROKEN_KINDS[turn % len(BROKEN_KINDS)])
        return good


def _post(client: httpx.Client, url: str, upload: Upload) -> tuple[str, dict[str, float] | None]:
    """Send one request: its status (or the transport error's name) and, for a 200, the server's stage timings."""
    try:
        response = client.post(f"{url}/v1/detect", files=upload.files, params=upload.params)
    except httpx.HTTPError as exc:
        return f"error:{type(exc).__name__}", None
    return str(response.status_code), response.json()["timings_ms"] if response.status_code == 200 else None


def _client_loop(
    url: str, source: RequestSource, headers: dict, stop: threading.Event, backoff_s: float, origin: float,
    samples: list[Sample], lock: threading.Lock,
) -> None:
    """One closed-loop client: the next request when the previous one is answered (after a 503, ``backoff_s``)."""
    with httpx.Client(timeout=120, headers=headers) as client:
        while not stop.is_set() and (upload := source.take()) is not None:
            tic = time.perf_counter()
            status, timings = _post(client, url, upload)
            toc = time.perf_counter()
            with lock:
                samples.append(Sample(tic - origin, (toc - tic) * 1e3, status, upload.name, upload.broken, timings,
                                      upload.points))
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


@dataclass
class Schedule:
    """What the open loop's dispatcher did: requests due in the run, sent, sent late (every slot busy at their
    due time), never sent (still waiting for a slot when the run ended), and the sending window (s)."""

    due: int = 0
    sent: int = 0
    late: int = 0
    unsent: int = 0
    window_s: float = 0.0


# An open-loop request handed to a sender: the upload, when it was due and when it went out (perf_counter s).
_Job = tuple[Upload, float, float]


def drive_open_loop(
    url: str, rate_hz: float, max_in_flight: int, duration_s: float | None, source: RequestSource, headers: dict,
) -> tuple[list[Sample], float, Schedule]:
    """Send a request every 1/``rate_hz`` s, whatever the answers, with at most ``max_in_flight`` unanswered, until
    ``duration_s`` has passed or the source is spent; samples (latency from each request's due time), wall time,
    and the schedule kept.

    A request due while every slot is busy goes out as soon as one frees (counted late), and the later ones wait
    behind it: a sensor that queues its frames, so the latency from the due time shows the queueing (measured
    from the send, it would hide it, as a closed loop does). One still waiting when ``duration_s`` ends is counted
    unsent, as are the later ones due before the end."""
    slots = threading.Semaphore(max_in_flight)
    jobs: queue.Queue[_Job | None] = queue.Queue()
    samples: list[Sample] = []
    origin = time.perf_counter()
    senders = _start_senders(url, headers, max_in_flight, jobs, slots, origin, samples)
    deadline = origin + duration_s if duration_s is not None else None
    schedule, last_sent = _dispatch(source, rate_hz, origin, deadline, slots, jobs)
    _stop_senders(jobs, senders)
    wall = time.perf_counter() - origin
    schedule.window_s = _sending_window(schedule.due, rate_hz, duration_s, last_sent - origin)
    return samples, wall, schedule


def _start_senders(url: str, headers: dict, count: int, jobs: queue.Queue[_Job | None], slots: threading.Semaphore,
                   origin: float, samples: list[Sample]) -> list[threading.Thread]:
    """Start ``count`` sender threads, each posting the jobs it takes and adding their samples to ``samples``."""
    lock = threading.Lock()
    threads = [
        threading.Thread(target=_sender_loop, args=(url, headers, jobs, slots, origin, samples, lock), daemon=True)
        for _ in range(count)
    ]
    for thread in threads:
        thread.start()
    return threads


def _sender_loop(url: str, headers: dict, jobs: queue.Queue[_Job | None], slots: threading.Semaphore, origin: float,
                 samples: list[Sample], lock: threading.Lock) -> None:
    """One open-loop sender: posts each job it takes until it takes None, then frees the job's slot."""
    with httpx.Client(timeout=120, headers=headers) as client:
        while (job := jobs.get()) is not None:
            upload, due, sent = job
            try:
                status, timings = _post(client, url, upload)
                toc = time.perf_counter()
                with lock:
                    samples.append(Sample(due - origin, (toc - due) * 1e3, status, upload.name, upload.broken,
                                          timings, upload.points, (sent - due) * 1e3))
            finally:
                slots.release()  # after the sample, so a finished run has every sample; always, or the run hangs


def _stop_senders(jobs: queue.Queue[_Job | None], threads: list[threading.Thread]) -> None:
    """Tell every sender to stop once the jobs before are sent, and wait for them: then every sample is in."""
    for _ in threads:
        jobs.put(None)
    for thread in threads:
        thread.join()


def _dispatch(source: RequestSource, rate_hz: float, origin: float, deadline: float | None,
              slots: threading.Semaphore, jobs: queue.Queue[_Job | None]) -> tuple[Schedule, float]:
    """Hand each request to a sender at its due time, every 1/``rate_hz`` s from ``origin`` until ``deadline``
    (None: until the source is spent); the schedule kept (its window aside) and when the last request went out."""
    end = deadline if deadline is not None else math.inf
    schedule = Schedule()
    waited_until = -math.inf  # when the dispatcher last got a slot it had to wait for
    last_sent = origin
    index = 0
    while (due := origin + index / rate_hz) < end:
        upload = source.take()  # read before its due time: the file read is not the request's latency
        if upload is None:
            return schedule, last_sent  # spent (--requests): every request went out, none is left unsent
        schedule.due += 1
        index += 1
        _sleep_until(due)
        late, waited_until = _take_slot(slots, due, waited_until, deadline)
        if late is None:
            schedule.unsent += 1  # the run ended with every slot still busy
            break
        last_sent = time.perf_counter()
        schedule.sent += 1
        schedule.late += late
        jobs.put((upload, due, last_sent))
    if deadline is not None:
        # Requests due before the end that the dispatcher never reached: counted, not silently left out.
        unreached = _due_before(end, origin, index, rate_hz)
        schedule.due += unreached
        schedule.unsent += unreached
    return schedule, last_sent


def _sleep_until(moment: float) -> None:
    """Wait until ``moment`` (perf_counter s); at once if it has passed."""
    now = time.perf_counter()
    if now < moment:
        time.sleep(moment - now)


def _take_slot(slots: threading.Semaphore, due: float, waited_until: float,
               deadline: float | None) -> tuple[bool | None, float]:
    """Take a free sender for a request due at ``due``, waiting for one until ``deadline`` (None: as long as it
    takes): whether the request goes out late (None: no sender freed in time), and when the dispatcher last got a
    slot it had to wait for."""
    if slots.acquire(blocking=False):
        # Behind schedule only because the dispatcher was still waiting for a slot at this one's due time.
        return due < waited_until, waited_until
    left = max(0.0, deadline - time.perf_counter()) if deadline is not None else None  # None: as long as it takes
    if not slots.acquire(timeout=left):
        return None, waited_until
    return True, time.perf_counter()


def _due_before(end: float, origin: float, index: int, rate_hz: float) -> int:
    """How many requests from the ``index``th on fall due before ``end``."""
    count = 0
    while origin + (index + count) / rate_hz < end:
        count += 1
    return count


def _sending_window(due: int, rate_hz: float, duration_s: float | None, last_sent_s: float) -> float:
    """The seconds the rates are taken over: the run's duration (a --requests run: its ``due`` requests' schedule),
    or up to one interval after the last send (``last_sent_s``, s since the run began) when that is later."""
    scheduled_window = duration_s if duration_s is not None else due / rate_hz
    # Late sends can stretch a --requests run past its schedule: the rate achieved is then over the longer window.
    return max(scheduled_window, last_sent_s + 1 / rate_hz)


def thin_scans(data: Path, frames: list[str], beams: int, folder: Path) -> None:
    """Write each frame's scan thinned to ``beams`` lines into ``folder`` as FRAME.bin (what an N-line sensor
    sends); a scan that cannot be thinned (thinned already, empty, truncated) is an InputError naming
    --send-beams."""
    for frame in frames:
        path = data / "velodyne" / f"{frame}.bin"
        try:
            points = emulate_beams(read_velodyne(path).points, beams)
        except InputError as exc:
            reason = str(exc).removeprefix(f"{path}: ").removeprefix("points: ")
            raise InputError(f"--send-beams {beams}: {path}: {reason}") from None
        write_velodyne(folder / f"{frame}.bin", points)


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


def this_machine() -> dict:
    """The machine this process runs on, for a report. ``cpus``: those this process may use (its affinity and a
    container's CPU quota: the client's share of a machine is what bounds it); ``cpus_online``: the machine's."""
    return {**describe_cpu(), "platform": platform.platform(), "cpus": usable_cpus(), "cpus_online": os.cpu_count(),
            "python": platform.python_version()}


@dataclass
class RunContext:
    """What a run was, besides its samples: the mode, where the scans were thinned, who ran where, and what the
    load generator itself cost."""

    url: str
    clients: int
    server: dict
    thinning: dict
    started_here: bool
    client_cpu_s: float
    rate_hz: float | None = None
    schedule: Schedule | None = None
    service_log: str | None = None


def summarise(samples: list[Sample], wall_s: float, rss: dict[str, float], gauges: GaugeSampler | None,
              context: RunContext) -> LoadResult:
    """The figures of a run from its samples."""
    good = [s for s in samples if not s.broken]
    broken = [s for s in samples if s.broken]
    ok = [s for s in good if s.status == "200"]
    stage_p50_ms = _stage_p50s(ok)
    rss_series = gauges.rss if gauges else []
    fds_series = gauges.fds if gauges else []
    windows = per_window(samples, rss_series, wall_s)
    thinning = _thinning_done(context.thinning, good, ok)
    open_loop = _open_loop_figures(samples, good, ok, context)
    machine = this_machine()
    return LoadResult(
        url=context.url, clients=context.clients, duration_s=round(wall_s, 2), requests=len(samples),
        status_counts=_status_counts(good),
        throughput_ok_per_s=len(ok) / wall_s, throughput_all_per_s=len(samples) / wall_s,
        latency_ms=_latency_by_status(good),
        stage_p50_ms=stage_p50_ms,
        rss_mb=rss, rss_series=rss_series, fds_series=fds_series,
        frames_sent=len({s.upload for s in good}),
        broken=_broken_figures(broken),
        server_errors=_server_errors(samples),
        trend=_trend(ok, rss_series, fds_series, wall_s),
        windows=windows, server=context.server,
        mode="open-loop" if open_loop else "closed-loop",
        latency_from="schedule" if open_loop else "send",
        open_loop=open_loop, thinning=thinning,
        client_machine=machine,
        server_machine=machine if context.started_here else None,
        client_shares_server_machine=True if context.started_here else None,
        client_cpu_s=round(context.client_cpu_s, 3),
        client_cpu_cores=context.client_cpu_s / wall_s if wall_s > 0 else float("nan"),
        service_log=context.service_log,
    )


def _stage_p50s(ok: list[Sample]) -> dict[str, float]:
    """The server's p50 of each stage it timed, over the answered requests (stages in the order first seen)."""
    stages: dict[str, list[float]] = {}
    for sample in ok:
        for stage, ms in (sample.timings_ms or {}).items():
            stages.setdefault(stage, []).append(ms)
    return {stage: float(np.median(values)) for stage, values in stages.items()}


def _thinning_done(planned: dict, good: list[Sample], ok: list[Sample]) -> dict:
    """Where the scans were to be thinned (``planned``), with the points the well-formed requests carried and how
    many answers the server thinned."""
    # What the server did with the scans, from its own answers: it times an emulate_beams stage only when it thins.
    return {**planned,
            "points_sent_mean": float(np.mean([s.points for s in good])) if good else float("nan"),
            "server_thinned_answers": sum("emulate_beams" in (s.timings_ms or {}) for s in ok)}


def _open_loop_figures(samples: list[Sample], good: list[Sample], ok: list[Sample], context: RunContext) -> dict:
    """The open loop's rates (over its schedule's window), its schedule's counts and the send lag; empty for a
    closed loop."""
    if context.rate_hz is None or context.schedule is None:
        return {}
    schedule = context.schedule
    return {
        "requested_rate_hz": context.rate_hz,
        "achieved_rate_hz": schedule.sent / schedule.window_s if schedule.window_s > 0 else float("nan"),
        "ok_rate_hz": len(ok) / schedule.window_s if schedule.window_s > 0 else float("nan"),
        "max_in_flight": context.clients,
        "window_s": round(schedule.window_s, 3),
        "due": schedule.due, "sent": schedule.sent, "late_sends": schedule.late, "unsent": schedule.unsent,
        "send_lag_ms": _percentiles([s.lag_ms for s in samples]),
        # The same requests timed from when they went out: the difference is the wait for a slot.
        "latency_from_send_ms": _percentiles([s.latency_ms - s.lag_ms for s in good]),
    }


def _status_counts(samples: list[Sample]) -> dict[str, int]:
    """How many of ``samples`` got each status, by status."""
    return dict(sorted(Counter(s.status for s in samples).items()))


def _latency_by_status(good: list[Sample]) -> dict[str, dict[str, float]]:
    """The well-formed requests' latency percentiles per status, then of them all ("all")."""
    return {
        **{status: _percentiles([s.latency_ms for s in good if s.status == status])
           for status in sorted({s.status for s in good})},
        "all": _percentiles([s.latency_ms for s in good]),
    }


def _broken_figures(broken: list[Sample]) -> dict:
    """The broken requests sent, their statuses per kind (the kinds sent, in BROKEN_KINDS' order) and how many were
    answered 4xx."""
    return {
        "sent": len(broken),
        "statuses": {kind: dict(sorted(Counter(s.status for s in broken if s.upload == kind).items()))
                     for kind in BROKEN_KINDS if any(s.upload == kind for s in broken)},
        "answered_4xx": sum(s.status.startswith("4") for s in broken),
    }


def _server_errors(samples: list[Sample]) -> int:
    """The 5xx answers other than 503 and the transport errors, well-formed requests or not."""
    return sum((s.status.startswith("5") and s.status != "503") or s.status.startswith("error") for s in samples)


def _trend(ok: list[Sample], rss_series: list[tuple[float, float]], fds_series: list[tuple[float, float]],
           wall_s: float) -> dict:
    """How the run changed over time: the memory's slope, the open file descriptors (first, last, most) and the
    p50 of the first and last tenth of the 200s in send order."""
    tenth = max(1, len(ok) // 10)
    by_start = sorted(ok, key=lambda s: s.start_s)
    return {
        "rss_mb_per_hour": memory_trend(rss_series, wall_s),
        "fds_first": fds_series[0][1] if fds_series else None,
        "fds_last": fds_series[-1][1] if fds_series else None,
        "fds_max": max((n for _, n in fds_series), default=None),
        "p50_ms_first_tenth": float(np.median([s.latency_ms for s in by_start[:tenth]])) if ok else None,
        "p50_ms_last_tenth": float(np.median([s.latency_ms for s in by_start[-tenth:]])) if ok else None,
    }


def status_colour(key: str) -> str:
    """The histogram's colour of a status (``bad …``: a broken request's), the same in every run whatever
    other statuses it has: the 200s blue as the latency line beside them, refusals orange, broken requests
    rightly refused green, server errors red."""
    if key.startswith("bad "):
        return "tab:olive" if key == "bad 503" else "tab:green"
    if key == "200":
        return "tab:blue"
    if key == "503":
        return "tab:orange"
    if key == "408":
        return "tab:purple"
    if key.startswith("4"):
        return "tab:brown"
    return "tab:red"  # another 5xx, or a broken connection ("error …")


def tenths_of_the_200s(start_s: np.ndarray, latency_ms: np.ndarray) -> list[tuple[float, float]]:
    """(middle of its send times, p50) of ten runs of ``n // 10`` consecutive 200s in send order (``start_s``
    sorted), spaced evenly from the first to the last: the first and last are the report's first and last
    tenth (``trend``), and with n a multiple of 10 they are its ten tenths. Fewer than 10: one per answer."""
    n = len(start_s)
    size = max(1, n // 10)
    firsts = np.unique(np.rint(np.linspace(0, n - size, 10)).astype(int)).tolist()
    return [(float((start_s[i] + start_s[i + size - 1]) / 2), float(np.median(latency_ms[i:i + size])))
            for i in firsts]


def _mark_percentiles(histogram, latency_ms: list[float]) -> None:
    """The 200s' p50 and p99 (the report's, numpy's linear interpolation) as lines across the histogram, each
    named at its top."""
    stats = _percentiles(latency_ms)
    for key, style in (("p50", "--"), ("p99", ":")):
        histogram.axvline(stats[key], color="black", linestyle=style, linewidth=1.2)
        # Upright beside its line: two labels side by side overlapped where p50 and p99 are close.
        histogram.text(stats[key], 0.98, f" 200s' {key} {stats[key]:.0f} ms", transform=histogram.get_xaxis_transform(),
                       rotation=90, ha="left", va="top", fontsize=8,
                       bbox={"facecolor": "white", "edgecolor": "none", "alpha": 0.7, "pad": 1})


# Tick values on a log axis, coarse to fine: the coarsest that puts two or more in view is taken.
LOG_TICK_STEPS = ((1.0,), (1.0, 2.0, 5.0), (1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0),
                  (1.0, 1.2, 1.4, 1.6, 1.8, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5, 5.0, 6.0, 7.0, 8.0, 9.0))


def log_ticks(low: float, high: float) -> list[float]:
    """Tick values between ``low`` and ``high`` (> 0) for a log axis: powers of ten when two or more lie
    between, else the coarsest finer steps that give two or more (latencies of 160-380 ms: 200, 300), else
    two round values within the range (:func:`_round_ends`)."""
    decades = range(math.floor(math.log10(low)), math.ceil(math.log10(high)) + 1)
    for steps in LOG_TICK_STEPS:
        ticks = [step * 10.0 ** k for k in decades for step in steps if low <= step * 10.0 ** k <= high]
        if len(ticks) >= 2:
            return ticks
    return _round_ends(low, high)


def _round_ends(low: float, high: float) -> list[float]:
    """The first and the last value within ``low``…``high`` (> 0) at the fewest significant digits that part
    them. The ends rounded as they were fell outside the axis: one request of 152 ms had ticks at 150 and 160 and
    an axis without a number."""
    for digits in range(2, 16):
        unit = 10.0 ** (math.floor(math.log10(high)) - digits + 1)
        first, last = math.ceil(low / unit) * unit, math.floor(high / unit) * unit
        if first < last:  # formatted so that 0.1 + 0.005 reads 0.105, not 0.10500000000000001
            return [float(f"{first:.{digits}g}"), float(f"{last:.{digits}g}")]
    return [low, high]  # equal ends: no two values part them


def label_log_axis(axis, low: float, high: float) -> None:
    """Labelled ticks from :func:`log_ticks` on a log axis spanning ``low``…``high``, as plain numbers. With
    matplotlib's own, only powers of ten were labelled (the minor labels, which overlap, blanked): latencies
    all within one decade had no label at all."""
    from matplotlib import ticker

    axis.set_major_locator(ticker.FixedLocator(log_ticks(low, high)))
    axis.set_major_formatter(ticker.FuncFormatter(lambda value, _: f"{value:g}"))
    axis.set_minor_formatter(ticker.NullFormatter())


def load_figure(samples: list[Sample], result: LoadResult, title: str):
    """The figure of :func:`plot_load` (not saved)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labelled = [(f"bad {s.status}" if s.broken else s.status, s) for s in samples]
    groups = {key: [s.latency_ms for k, s in labelled if k == key] for key in sorted({k for k, _ in labelled})}
    all_ms = [s.latency_ms for s in samples]
    bins = np.geomspace(max(min(all_ms), 0.1), max(all_ms) * 1.05, 40)
    figure, (histogram, timeline) = plt.subplots(1, 2, figsize=(13, 4.5), dpi=100)
    histogram.hist(list(groups.values()), bins=bins, stacked=True, color=[status_colour(k) for k in groups],
                   label=[f"{k} ({len(v)})" for k, v in groups.items()])
    histogram.set_xscale("log")
    label_log_axis(histogram.xaxis, float(bins[0]), float(bins[-1]))
    histogram.set_xlabel("latency (ms, client side, from the due time)" if result.latency_from == "schedule"
                         else "latency (ms, client side)")
    histogram.set_ylabel("requests")
    histogram.yaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))  # counts, not 17.5 requests
    histogram.legend(title="status (requests)", fontsize=8, title_fontsize=8)

    # In send order, as summarise's first and last tenth (a stable sort: ties keep the samples' order).
    ok = sorted((s for s in samples if s.status == "200" and not s.broken), key=lambda s: s.start_s)
    if ok:
        _mark_percentiles(histogram, [s.latency_ms for s in ok])
        start = np.asarray([s.start_s for s in ok])
        ms = np.asarray([s.latency_ms for s in ok])
        # Faint enough that thousands do not hide the p50 line, large enough that a short run's few are seen.
        timeline.plot(start, ms, ".", markersize=3, alpha=0.5, color="tab:blue", label="a 200's latency")
        tenths = tenths_of_the_200s(start, ms)
        size = max(1, len(ok) // 10)
        # Black over the blue dots (in blue, p50 points that fell among them vanished), white-filled markers.
        timeline.plot([t for t, _ in tenths], [p50 for _, p50 in tenths], "-D", color="black", markersize=5,
                      markerfacecolor="white", linewidth=1.5, zorder=3,
                      label=f"p50 of each tenth of the 200s ({size} each, in send order)")
    timeline.set_xlabel("seconds into the load (due time)" if result.latency_from == "schedule"
                        else "seconds into the load")
    timeline.set_ylabel("latency (ms)", color="tab:blue")
    timeline.legend(loc="upper left", fontsize=8)
    if result.rss_series:
        memory = timeline.twinx()
        seconds, mb = np.asarray(result.rss_series).T
        memory.plot(seconds, mb, color="tab:red", linewidth=1)
        memory.set_ylabel("server RSS (MB)", color="tab:red")
        low, high = float(mb.min()), float(mb.max())
        memory.set_ylim(low - max(10.0, 0.1 * low), high + max(10.0, 0.1 * high))
    figure.suptitle(title)
    figure.tight_layout()
    return figure


def plot_load(samples: list[Sample], result: LoadResult, path: Path, title: str) -> None:
    """Left: latency histogram per status, log-scaled x. Right: each answered frame's latency and the
    server's memory over the run (a picture file)."""
    import matplotlib.pyplot as plt

    figure = load_figure(samples, result, title)
    figure.savefig(path)
    plt.close(figure)


def _machine_line(result: LoadResult) -> str:
    """Whose machine the report describes: always the load generator's; the server's only when started here."""
    machine = result.client_machine
    where = ("the server's too: load.py started it here, so the two share these CPUs"
             if result.client_shares_server_machine
             else "where load.py runs; the server's machine is not known here")
    return f"client machine: {cpu_label(machine)}, {machine['cpus']} CPUs, {machine['platform']} ({where})"


def _thinning_line(result: LoadResult) -> str:
    """Which side thinned the scans, and how many points each request carried."""
    thinning = result.thinning
    sent = f"{thinning['points_sent_mean']:,.0f} points a scan"
    if thinning["where"] == "client":
        return (f"scans: thinned to {thinning['beams']} lines here before the run (--send-beams {thinning['beams']}): "
                f"{sent} sent, of {thinning['points_stored_mean']:,.0f} stored; the server not asked to thin "
                f"(it thinned {thinning['server_thinned_answers']} answers)")
    if thinning["where"] == "server":
        return (f"scans: sent as stored ({sent}), thinned to {thinning['beams']} lines by the server "
                f"(emulate_beams={thinning['beams']}; --send-beams N thins them here instead)")
    return f"scans: sent as stored ({sent}), not thinned"


def _load_lines(result: LoadResult) -> list[str]:
    """The load's shape: closed-loop clients, or the open loop's schedule and how well it was kept."""
    if result.mode != "open-loop":
        return [(f"{result.clients} clients, {result.requests} requests in {result.duration_s} s, "
                 f"{result.frames_sent} distinct frame(s)")]
    loop = result.open_loop
    lag = loop["send_lag_ms"]
    return [
        (f"open loop: {loop['requested_rate_hz']:g} Hz requested, {loop['achieved_rate_hz']:.2f} Hz sent "
         f"over {loop['window_s']:.2f} s, at most {loop['max_in_flight']} in flight; {loop['due']} due, "
         f"{loop['sent']} sent, {loop['late_sends']} of them late (every slot busy at their due time), "
         f"{loop['unsent']} never sent (still waiting when the run ended); {result.frames_sent} distinct frame(s), "
         f"last answer at {result.duration_s} s"),
        f"send lag ms (due time → sent): p50 {lag['p50']:.1f}, p99 {lag['p99']:.1f}, max {lag['max']:.1f}",
    ]


def format_report(result: LoadResult) -> str:
    """The printed report."""
    lines = [
        (f"service {result.url}: {result.server.get('preset')} models, {result.server.get('workers')} worker(s), "
         f"{result.server.get('sessions')} sessions, {result.server.get('intra_op_threads')} intra-op thread(s), "
         f"queue {result.server.get('queue_size')}, {result.server.get('providers')}"
         f"{', PIXOR with mirror TTA' if result.server.get('mirror_tta') else ''}"),
        _machine_line(result),
        _thinning_line(result),
        *_load_lines(result),
        (f"status counts of the real frames (the broken ones: below): {result.status_counts}" if result.broken.get("sent")
         else f"status counts: {result.status_counts}"),
        (f"throughput: {result.throughput_ok_per_s:.2f} frames/s answered 200 "
         f"({result.throughput_all_per_s:.2f} requests/s in all)"),
    ]
    if result.mode == "open-loop":
        columns = ("p50", "p90", "p99", "mean", "max")
        lines.append("latency ms from the due time   p50      p90      p99      mean     max")
        rows = {**result.latency_ms, "all, from the send": result.open_loop["latency_from_send_ms"]}
    else:
        columns = ("p50", "p99", "mean", "max")
        lines.append("latency ms (client side)   p50      p99      mean     max")
        rows = result.latency_ms
    for name, stats in rows.items():
        lines.append(f"  {name:<24}" + "".join(f"{stats[k]:>9.1f}" for k in columns))
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
    cpus = result.client_machine.get("cpus") or 1
    lines.append(
        f"load generator CPU: {result.client_cpu_s:.2f} s over the {result.duration_s} s run "
        f"({result.client_cpu_cores:.2f} of a core on average, {100 * result.client_cpu_cores / cpus:.0f} % of the "
        f"client machine's {cpus} CPUs{', which the server shares' if result.client_shares_server_machine else ''})")
    if result.service_log:
        lines.append(f"service log: {result.service_log}")
    return "\n".join(lines)


def thinning_plan(send_beams: int, emulate_beams: int | None) -> tuple[int, int]:
    """(lines the client thins to, lines the server is asked to thin to), 0 for none. ``emulate_beams`` None: the
    server thins to 16 unless the client thins (a thinned scan is refused by the server's thinning); asking both
    to thin is an InputError."""
    if send_beams and emulate_beams:
        raise InputError(f"--send-beams {send_beams} thins the scans here and --emulate-beams {emulate_beams} would "
                         "ask the server to thin them again (it refuses a thinned scan): give one of the two")
    if emulate_beams is None:
        emulate_beams = 0 if send_beams else 16
    return send_beams, emulate_beams


def stored_points_mean(data: Path, frames: list[str]) -> float:
    """Mean points per stored scan of the frames, from the files' sizes."""
    return float(np.mean([(data / "velodyne" / f"{frame}.bin").stat().st_size // POINT_BYTES for frame in frames]))


def run(
    url: str | None = None,
    models: Path = DEFAULT_MODELS,
    clients: int = 8,
    duration_s: float | None = 20.0,
    requests: int | None = None,
    data: Path = KITTI,
    frames: list[str] | None = None,
    emulate_beams: int | None = None,
    bad_every: int = 0,
    token: str | None = None,
    backoff_s: float = 0.1,
    server_args: list[str] | None = None,
    plot: Path | None = None,
    log_path: Path = DEFAULT_LOG,
    rate_hz: float | None = None,
    send_beams: int = 0,
) -> LoadResult:
    """Drive a service (started here when ``url`` is None) and measure it: closed-loop ``clients``, or with
    ``rate_hz`` an open loop with at most ``clients`` requests in flight. ``send_beams``: thin the scans here
    first (0: as stored); ``emulate_beams``: ask the server to (see :func:`thinning_plan`)."""
    frames = frames or frame_ids(data)
    send_beams, emulate_beams = thinning_plan(send_beams, emulate_beams)
    params = {"emulate_beams": emulate_beams} if emulate_beams else {}
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    thinning = _thinning_planned(data, frames, send_beams, emulate_beams)
    # The thinned scans go to a temporary folder, read per request as the stored ones are: a folder of hundreds
    # of frames is not held in memory. Thinned before the service starts, so a scan that cannot be thinned
    # stops the run before anything runs.
    with tempfile.TemporaryDirectory(prefix="load-scans-") as scratch:
        scans = _thinned_here(data, frames, send_beams, Path(scratch))
        with _target(url, models, server_args or [], log_path) as base:
            server = _server_info(base, headers)
            warm_up = RequestSource(data, frames, params, 3 * clients, scans=scans)
            rss = _memory_ready_and_warm(base, clients, warm_up, headers, backoff_s)
            measured_requests = RequestSource(data, frames, params, requests, bad_every, scans)
            measured = _measure(base, clients, rate_hz, duration_s, measured_requests, headers, backoff_s)
            rss["end"] = server_rss_mb(base, headers)
    context = RunContext(url=base, clients=clients, server=server, thinning=thinning, started_here=url is None,
                         client_cpu_s=measured.client_cpu_s, rate_hz=rate_hz, schedule=measured.schedule,
                         service_log=str(log_path) if url is None else None)
    result = summarise(measured.samples, measured.wall_s, rss, measured.gauges, context)
    if plot is not None and measured.samples:
        plot.parent.mkdir(parents=True, exist_ok=True)
        plot_load(measured.samples, result, plot,
                  _plot_title(rate_hz, clients, server, len(measured.samples), measured.wall_s))
    return result


def _thinning_planned(data: Path, frames: list[str], send_beams: int, emulate_beams: int) -> dict:
    """Where the scans are to be thinned (client, server or none), to how many lines, and the points stored."""
    where = "client" if send_beams else "server" if emulate_beams else "none"
    return {"where": where, "beams": send_beams or emulate_beams or None, "send_beams": send_beams,
            "emulate_beams": emulate_beams, "points_stored_mean": stored_points_mean(data, frames)}


def _thinned_here(data: Path, frames: list[str], send_beams: int, scratch: Path) -> Path | None:
    """The folder of the scans thinned here to ``send_beams`` lines (written into ``scratch``); None when they
    are sent as stored (``send_beams`` 0)."""
    if not send_beams:
        return None
    thin_scans(data, frames, send_beams, scratch)
    return scratch


@contextmanager
def _target(url: str | None, models: Path, server_args: list[str], log_path: Path) -> Iterator[str]:
    """The service's base URL: ``url`` (without a trailing slash), else one started here for the block's length."""
    if url is not None:
        yield url.rstrip("/")
    else:
        log_path.parent.mkdir(parents=True, exist_ok=True)
        with started_service(models, server_args, log_path) as started:
            yield started


def _server_info(base: str, headers: dict[str, str]) -> dict:
    """What the service says it runs (/v1/model): the model's id (its manifest's sha256, the X-Model-ID of each
    answer), preset, workers, sessions, queue, threads, TTA and providers."""
    info = httpx.get(f"{base}/v1/model", headers=headers, timeout=10).json()
    return {
        "model_id": info["identity"]["id"],
        "preset": info["preset"], "workers": info["workers"], "sessions": info["sessions"],
        "queue_size": info["queue_size"], "intra_op_threads": info.get("intra_op_threads"),
        "mirror_tta": info.get("mirror_tta", False),
        "providers": sorted({p for ps in info["providers_in_use"].values() for p in ps}),
    }


def _memory_ready_and_warm(base: str, clients: int, source: RequestSource, headers: dict[str, str],
                           backoff_s: float) -> dict[str, float]:
    """The server's resident memory (MB) when ready, and after ``source``'s requests (not measured)."""
    rss = {"ready": server_rss_mb(base, headers)}
    # Warm-up at full concurrency so every worker thread exists and has made its buffers.
    drive(base, clients, None, source, headers, backoff_s)
    rss["warm"] = server_rss_mb(base, headers)
    return rss


@dataclass
class _Measured:
    """The measured part of a run: its samples and wall time, the open loop's schedule (None: closed loop), the
    server's gauges over it and the load generator's CPU seconds."""

    samples: list[Sample]
    wall_s: float
    schedule: Schedule | None
    gauges: GaugeSampler
    client_cpu_s: float


def _measure(base: str, clients: int, rate_hz: float | None, duration_s: float | None, source: RequestSource,
             headers: dict[str, str], backoff_s: float) -> _Measured:
    """Drive the load (closed loop, or open at ``rate_hz``) with ``source``'s requests, sampling the server's
    gauges and timing this process's CPU meanwhile."""
    schedule = None
    # CPU of this process alone (every thread, the gauge scrapes too; not a service started here, a child):
    # on a shared box, what the load generator took from the server.
    cpu_start = time.process_time()
    with GaugeSampler(base, headers) as gauges:
        if rate_hz is None:
            samples, wall = drive(base, clients, duration_s, source, headers, backoff_s)
        else:
            samples, wall, schedule = drive_open_loop(base, rate_hz, clients, duration_s, source, headers)
    return _Measured(samples, wall, schedule, gauges, time.process_time() - cpu_start)


def _plot_title(rate_hz: float | None, clients: int, server: dict, requests: int, wall_s: float) -> str:
    """The plot's title: the load, the service's workers, queue and models, and the requests sent."""
    load = (f"{rate_hz:g} Hz open loop, at most {clients} in flight" if rate_hz is not None
            else f"{clients} clients")
    return (f"{load}, {server['workers']} worker(s), queue {server['queue_size']}, {server['preset']} models: "
            f"{requests} requests in {wall_s:.0f} s")


def check_frames(data: Path, frames: list[str]) -> None:
    """Every frame must have its image, scan and calibration: an error names the first file missing."""
    for frame in frames:
        for folder, suffix in (("image_2", ".png"), ("velodyne", ".bin"), ("calib", ".txt")):
            if not (data / folder / f"{frame}{suffix}").is_file():
                raise InputError(f"--data {data}: frame {frame} has no {folder}/{frame}{suffix}")


def check_outputs(args: argparse.Namespace, log: Path) -> None:
    """--json, --plot and (a service started here) its log, before the load, so that a bad path does not lose
    the report: each writable, and none over what the run reads (a --json named as the served manifest replaced
    it; a --log there would empty it before the service read it). With --url, --models is not read."""
    started = args.url is None
    inputs = {"--models": args.models if started else None, "--data": args.data}
    if args.json is not None:
        check_output(args.json, "--json")
    if args.plot is not None:
        check_figure(args.plot, "--plot")
    if started:
        check_output(log, "--log")
    for path, flag in ((args.json, "--json"), (args.plot, "--plot"), (log if started else None, "--log")):
        if path is not None:
            check_not_input(path, flag, inputs)


@quiet_interrupt("no report was written (--json and --plot come at the end); a service it started is stopped")
def main(argv: list[str] | None = None) -> int:
    """The command line: check every flag and input before anything starts, run the load, report."""
    parser = _parser()
    args = parser.parse_args(argv)
    send_beams, emulate_beams = _checked_load_flags(parser, args)
    server_args = _server_args(args)
    _check_service_flags(parser, args, server_args)
    frames, log = _checked_inputs(parser, args)
    try:
        result = run(
            url=args.url, models=args.models, clients=args.clients, duration_s=_duration_s(args),
            requests=args.requests, data=args.data, frames=frames, emulate_beams=emulate_beams,
            bad_every=args.bad_every, token=args.token, backoff_s=0.1 if args.backoff_s is None else args.backoff_s,
            server_args=server_args, plot=args.plot, log_path=log, rate_hz=args.rate, send_beams=send_beams,
        )
    except InputError as exc:  # a scan --send-beams cannot thin (a thinned one already); nothing was started
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except httpx.TransportError as exc:  # nothing listening at --url, or it went away before the load began
        where = f"--url {args.url}" if args.url else "the service started here"
        print(f"error: {where}: cannot reach the service ({exc}); start it first (python -m service) "
              "or leave --url out to start one here", file=sys.stderr)
        return 2
    _write_report(result, args.json, args.plot)
    return 0


def _parser() -> argparse.ArgumentParser:
    """The command line's flags, in --help's order."""
    parser = argparse.ArgumentParser(
        allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
        prog="python benchmarks/load.py",
        description="Load-test the lowres3d detection service on loopback (deliberately over capacity) or at --url: "
        "throughput, p50/p99 latency, status counts, server memory and file descriptors over the run "
        "(a soak test when long), broken requests mixed in on request. Closed loop by default (each client sends "
        "when answered); --rate HZ for an open loop at a sensor's rate. The machine it reports is the client's "
        "(the load generator's, with its own CPU time): the server's too only when it started the service.",
        epilog=examples("python benchmarks/load.py --duration 20 --json outputs/load.json --plot outputs/load.png",
                        "python benchmarks/load.py --url http://127.0.0.1:8000 --rate 10 --duration 600 "
                        "--bad-every 50"),
        formatter_class=HelpFormatter,
    )
    _add_load_arguments(parser)
    _add_request_arguments(parser)
    _add_started_service_arguments(parser)
    _add_output_arguments(parser)
    return parser


def _add_load_arguments(parser: argparse.ArgumentParser) -> None:
    """Which service, and how much load: clients or a rate, for a duration or a number of requests."""
    parser.add_argument("--url", help="a running service (default: start one on 127.0.0.1 with --models)")
    parser.add_argument("--models", type=Path, default=DEFAULT_MODELS, metavar="DIR",
                        help=f"model directory (default {DEFAULT_MODELS})")
    parser.add_argument("--clients", type=positive_int, default=8, metavar="N",
                        help="concurrent clients (default 8); with --rate, the most requests in flight at once")
    parser.add_argument("--rate", type=positive_float, metavar="HZ",
                        help="open loop: a request due every 1/HZ s in all, whatever the answers (a 10 Hz sensor: 10), "
                        "at most --clients in flight; one due while all are busy goes out late, and latency counts "
                        "from the due time (default: closed loop)")
    bound = parser.add_mutually_exclusive_group()
    bound.add_argument("--duration", type=positive_float, metavar="S",
                       help="seconds of load (default 20 unless --requests)")
    bound.add_argument("--requests", type=positive_int, metavar="N", help="total requests instead of a duration")


def _add_request_arguments(parser: argparse.ArgumentParser) -> None:
    """What each request sends (frames, thinning, broken ones, token) and a closed-loop client's backoff."""
    parser.add_argument("--data", type=Path, default=KITTI, metavar="DIR",
                        help="KITTI object folder whose frames are sent in turn (default tests/data/kitti/training)")
    parser.add_argument("--frame", metavar="ID", help="send only this frame of --data")
    parser.add_argument("--emulate-beams", "--beams", type=int, choices=(0, *BEAM_COUNTS), metavar="N",
                        help="ask the server to thin the 64-line scan to N lines (emulate_beams=N: 32, 16, 8 or 4; "
                        "default 16, or 0 with --send-beams; 0: off)")
    parser.add_argument("--send-beams", type=int, choices=(0, *BEAM_COUNTS), default=0, metavar="N",
                        help="thin the scans to N lines (32, 16, 8 or 4) here, once before the run, and send those, "
                        "as an N-line sensor would, without asking the server to thin (default 0: as stored)")
    parser.add_argument("--bad-every", type=non_negative_int, default=0, metavar="N",
                        help="make every Nth request a broken one, which must be answered 4xx (503 when the queue is full) "
                        "(default 0: none)")
    parser.add_argument("--token", default=os.environ.get("LOWRES3D_TOKEN"), metavar="TOKEN",
                        help="bearer token (default $LOWRES3D_TOKEN)")
    parser.add_argument("--backoff-s", type=float, metavar="S",
                        help="closed loop: a client's pause after a 503 (default 0.1)")


def _add_started_service_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags passed on to a service started here."""
    parser.add_argument("--workers", type=int, metavar="N", help="started service: inference workers")
    parser.add_argument("--queue-size", type=int, metavar="N", help="started service: queue size")
    parser.add_argument("--sessions", choices=["shared", "per-worker"], help="started service: session mode")
    parser.add_argument("--intra-op-threads", type=int, metavar="N",
                        help="started service: ONNX Runtime threads per session")
    parser.add_argument("--mirror-tta", action="store_true",
                        help="started service: PIXOR also on the mirrored BEV (python -m service --mirror-tta)")


def _add_output_arguments(parser: argparse.ArgumentParser) -> None:
    """Where the JSON, the picture and a started service's log go."""
    parser.add_argument("--json", type=Path, metavar="FILE", help="write the result as JSON here")
    parser.add_argument("--plot", type=Path, metavar="FILE",
                        help="write a picture here (.png, .jpg, .pdf or .svg; needs matplotlib): latency histogram, "
                        "latency and memory over time")
    parser.add_argument("--log", type=Path, metavar="FILE",
                        help=f"started service: write its log here (default {DEFAULT_LOG}, under the working directory)")


def _checked_load_flags(parser: argparse.ArgumentParser, args: argparse.Namespace) -> tuple[int, int]:
    """--backoff-s checked against the loop, and the thinning plan: (lines thinned here, lines the server is asked
    to thin to). A bad combination is a usage error."""
    if args.backoff_s is not None and args.rate is not None:
        parser.error("--backoff-s applies to the closed loop only: with --rate each request goes at its due time")
    if args.backoff_s is not None and not args.backoff_s >= 0:
        parser.error("--backoff-s must be 0 or more")
    try:
        return thinning_plan(args.send_beams, args.emulate_beams)
    except InputError as exc:
        parser.error(str(exc))


def _server_args(args: argparse.Namespace) -> list[str]:
    """The started service's own flags among ours, as ``python -m service`` spells them."""
    server_args: list[str] = []
    for flag in ("workers", "queue_size", "sessions", "intra_op_threads"):
        value = getattr(args, flag)
        if value is not None:
            server_args += [f"--{flag.replace('_', '-')}", str(value)]
    if args.mirror_tta:
        server_args.append("--mirror-tta")
    return server_args


def _check_service_flags(parser: argparse.ArgumentParser, args: argparse.Namespace, server_args: list[str]) -> None:
    """A started service's flags are refused with --url; without it, --models must be a directory."""
    if args.url and server_args:
        parser.error("--workers/--queue-size/--sessions/--intra-op-threads/--mirror-tta apply only to a service "
                     "started here")
    if args.url and args.log is not None:
        parser.error("--log applies only to a service started here (the one at --url logs where it was started)")
    if args.url is None and not args.models.is_dir():
        parser.error(f"--models: {args.models} is not a directory (export one with `python -m export`)")


def _checked_inputs(parser: argparse.ArgumentParser, args: argparse.Namespace) -> tuple[list[str], Path]:
    """The frames to send (each with its three files) and the started service's log path, with the outputs
    checked: a usage error before anything starts."""
    try:
        if not (args.data / "velodyne").is_dir():
            raise InputError(f"--data {args.data}: not a KITTI object folder (no velodyne/ inside)")
        frames = [args.frame] if args.frame else frame_ids(args.data)
        if not frames:
            raise InputError(f"--data {args.data}: no frames in its velodyne/")
        check_frames(args.data, frames)
        log = DEFAULT_LOG if args.log is None else args.log
        check_outputs(args, log)
        return frames, log
    except InputError as exc:
        parser.error(str(exc))


def _duration_s(args: argparse.Namespace) -> float | None:
    """--duration, else 20 s unless --requests bounds the run instead (None)."""
    return args.duration if args.duration is not None else (None if args.requests else 20.0)


def _write_report(result: LoadResult, json_path: Path | None, plot: Path | None) -> None:
    """Print the report, write the JSON, and name each file written (the plot was drawn by :func:`run`)."""
    print(format_report(result))
    if json_path:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(asdict(result), indent=2))
        print(f"wrote {json_path}")
    if plot:
        print(f"wrote {plot}")


if __name__ == "__main__":
    sys.exit(main())
