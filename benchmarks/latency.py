"""Latency and throughput of the whole pipeline, measured the way the paper measured its GPUs.

    python benchmarks/latency.py [--preset P | --models DIR] [--provider cpu|cuda|tensorrt]
                                 [--threads N [--worker-kind thread|process]] [--frames K] [--warmup W] [--json FILE] [--plot FILE.png]
                                 [--compare-torch [--checkpoints DIR]] [--baseline DIR] [--ops]
                                 [--score-threshold SCORE]

Single stream (the paper's per-frame latency, 25.4 ms on an RTX 2080Ti and
581.7 ms on a DRIVE PX2): one Detector using every core, per-stage and
end-to-end latency over real frames after warm-up. ``--threads N`` (the paper's
two-GPU mode, 3.4 fps on the PX2): N workers, each with its own sessions
pinned to its own share of the cores, run frames concurrently; aggregate fps
is compared with one worker on one share, in three alternating rounds of each.
A worker is a thread of this process by default; ``--worker-kind process`` gives
each its own process, which shares no interpreter lock with the others (the
NumPy stages between the networks hold it between calls).
Each network's achieved GFLOP/s is set against the machine's peak, measured in
the same run (benchmarks/peak.py); ``--ops`` also times each network operator by
operator with ONNX Runtime's profiler (benchmarks/op_profile.py), so the report
says whether the convolutions or the layout changes and other kernels between
them keep a network from the peak.
``--compare-torch`` runs the same Detector with PyTorch eager networks in blocks
of frames alternating with ONNX Runtime, and reports the median block's ratio and
the spread over the blocks (a spread over 1.3× is flagged: the machine's load
moved). ``--baseline DIR`` does the same with another model directory
(an INT8 directory against its FP32 source, say): on a shared machine, two
separate runs minutes apart differed by more than the precisions did.

End to end is ``Detector.detect`` on frames already in memory, from its input checks to the boxes (the
wait for the work beside the depth net included); reading and decoding the files and the line emulation are
not timed. ``fps`` is 1000 / the mean (``fps_wall`` the frames over the loop's wall time); each summary gives
its frame count and slowest frame (up to 101 frames a p99 lies between the two slowest), and the JSON's
``definitions`` say what each figure is.

What else moves the figures is in the report. The peak is measured before and
after the stream and the best reading counts (a reading taken while something
else ran reads low). Each throughput worker's share of its core is recorded and
a round where one got less than 95 % is flagged (its scaling measured the
neighbour too); ``scaling`` is per share of cores, ``vs_single_stream`` what N
workers give against one frame at a time on every core. ``--score-threshold``
sets every Detector's (the evaluation's 0.05 keeps 500 candidates for the NMS).

Without ``--models`` it times the shipped model, ``weights/edge`` (``weights/edge-int8``
with ``--precision int8``), as the README's figures were timed; ``--preset P`` (or
``--checkpoints``) exports P first (default: the shipped model's preset), with
initialised weights where no checkpoints are given (the networks' time does not
depend on the weights' values; the decoding's a little does). Scans are thinned to
the line count the model was trained on (16 for ``weights/edge``; a 64-line
model's are kept as stored) unless ``--emulate-beams`` says otherwise; each distinct
warning of the Detector (a scan unlike the model's, initialised weights) is
printed once. Ctrl-C stops the throughput workers (between frames, or inside a
network run) before the command ends.
"""

from __future__ import annotations

import argparse
import json
import logging
import multiprocessing
import os
import platform
import re
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from importlib import metadata
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.op_profile import GPU_PROFILER_HINT, profile_network
from benchmarks.op_profile import describe as describe_ops
from benchmarks.peak import PeakResult, measure_peak
from export.flops import count_flops
from pipeline.beams import BEAM_COUNTS, emulate_beams, lines_to_thin_to
from pipeline.cli import (
    HelpFormatter,
    check_figure,
    check_not_input,
    check_output,
    examples,
    gpu_ids,
    non_negative_int,
    positive_int,
    probability,
    quiet_interrupt,
    write_text_file,
)
from pipeline.cpu import core_shares, cpu_label, cpu_quota, usable_cpus
from pipeline.cpu import describe as describe_cpu
from pipeline.detector import Cancellation, Detector, RunCancelled
from pipeline.errors import TORCH_MISSING, InputError
from pipeline.frame import Frame, frame_ids, load_frame
from pipeline.model_files import DEFAULT_MODELS, ModelFileError, load_manifest, load_manifest_with_digest
from pipeline.presets import Preset, get_preset, is_preset_file, preset_fields
from pipeline.provenance import code_version

ROOT = Path(__file__).resolve().parents[1]
BUNDLED = ROOT / "tests" / "data" / "kitti" / "training"
# What runs without --models: the shipped model (the README's latency figures are of it), and its INT8 twin.
SHIPPED = DEFAULT_MODELS
SHIPPED_INT8 = SHIPPED.with_name("edge-int8")
DEFAULT_PRESET = "edge-split-near35"  # the shipped model's preset (weights/edge/manifest.json): --preset's default
PEAK_MATMUL = 4096  # the peak micro-benchmark's MatMul: N × N by N × N
# The stages that are network runs (pixor_mirror: PIXOR's second run, with --mirror-tta); the rest of a frame's
# time is "between the networks" (mirror_merge, the mirror's copies and averaging, too).
NETWORK_STAGES = ("depth_net", "pixor", "pixor_mirror")
PAPER = {"RTX 2080Ti": {"ms": 25.4, "fps": 39.8}, "DRIVE PX2": {"ms": 581.7, "fps_two_threads": 3.4}}


# ----------------------------------------------------------------------------- frames
def load_frames(data: Path, count: int, beams: int | None) -> list[Frame]:
    """The first ``count`` frames of a KITTI-layout folder (all of them when there are fewer; at least one), scans
    thinned to ``beams``. The timed runs cycle through them when they need more (run_stream, _frames_on)."""
    ids = frame_ids(data)
    if not ids:
        raise InputError(f"--data {data}: no frames (no .bin scans in {Path(data) / 'velodyne'})")
    frames = []
    for frame_id in ids[: max(1, min(count, len(ids)))]:
        frame = load_frame(data, frame_id, with_labels=False)
        if beams:
            frame.points = emulate_beams(frame.points, beams)
        frames.append(frame)
    return frames


def summarize(samples: list[float]) -> dict:
    """Mean, percentiles (numpy's linear interpolation between the sorted samples), the slowest and the count of
    ``samples``, none dropped: up to 101 samples p99 lies between the two slowest (:func:`tail_note`)."""
    s = np.asarray(samples)
    return {"mean": float(s.mean()), "p50": float(np.percentile(s, 50)), "p90": float(np.percentile(s, 90)),
            "p99": float(np.percentile(s, 99)), "max": float(s.max()), "n": int(s.size)}


def between_the_two_slowest(q: int, n: int) -> bool:
    """Whether numpy's linear ``q``-th percentile of ``n`` samples lies between the two slowest: its rank
    q/100 × (n − 1) in the sorted samples is n − 2 or more (p99 up to 101 samples, p90 up to 11)."""
    return q * (n - 1) >= 100 * (n - 2)


def tail_note(n: int) -> str:
    """What a p99 (and p90) of ``n`` samples rests on, for the printed report ("" from 102 samples on)."""
    if not between_the_two_slowest(99, n):
        return ""
    p90 = ", and p90 between the two slowest" if between_the_two_slowest(90, n) else ""
    return f"; with {n} frames p99 is an interpolation between the two slowest{p90}"


# What each figure of the report is, written into its JSON (``definitions``), so a reader setting one beside
# the paper's (25.4 ms, 3.4 fps) knows what it includes.
DEFINITIONS = {
    "end_to_end_ms": "per frame, Detector.detect on frames already in memory, from its input checks to the boxes: "
                     "crop and sparse depth, both networks, pseudo points, BEV, decoding and NMS, and the wait for "
                     "the work run beside the depth net; not reading or decoding the files, and not the line "
                     "emulation (scans thinned before timing, as a 16-line sensor sends them). Mean and percentiles "
                     "(numpy's linear interpolation) of n frames after the warm-up ones, none dropped; max the "
                     "slowest. Up to 101 frames p99 lies between the two slowest (numpy's rank 0.99 x (n - 1))",
    "fps": "1000 / end_to_end_ms.mean: the single stream, one frame at a time on every core",
    "fps_wall": "the single stream's frames / its wall time, the loop between frames included",
    "stages_ms": "each stage's time on the frame's path (ray_table with a stage thread: the wait for the work "
                 "beside the depth net), as end_to_end_ms",
    "overlapped_ms": "the work of the stage thread beside the depth net, on the frame's path only as waited for",
    "non_network_fraction": "(end_to_end_ms.mean - the networks' stages' means) / end_to_end_ms.mean",
    "non_network_fraction_fixed_calibration": "the same without the ray tables' builds on the frame's path (a "
                                              "vehicle's one calibration builds its table once)",
    "networks.gflops": "GFLOP a frame: 2 x the multiply-accumulates of the convolutions and matrix products, "
                       "counted from the ONNX graph before its lowering for the CPU (the manifest's flops), "
                       "x runs; graph_gflops: the same count on the graph that runs (its zero-padded channels, "
                       "an INT8 graph's sub-pixel convolutions)",
    "networks.ms": "the p50 of the network's stage (the sum over its runs)",
    "networks.peak_fraction": "gflops / ms over peak_gflops; matmul_peak_fraction over the MatMul's GFLOP/s",
    "peak_gflops": "ONNX Runtime fp32 on the CPU with the single stream's intra-op threads: the better of a "
                   "MatMul and a 256-channel 3x3 convolution, each the median of 5 runs after 1 untimed, read "
                   "before and after the stream, the higher reading counting",
    "throughput.fps": "the workers' frames / the wall time from their common start to the last one's end, "
                      "each worker after its own warm-up; the median over the rounds",
    "throughput.scaling": "throughput.fps / throughput.fps_one_worker (medians over the rounds; each round's "
                          "ratio in scaling_per_round)",
    "throughput.vs_single_stream": "throughput.fps / fps_wall",
    "throughput.cpu_ms_per_frame": "the CPU time a worker spent on a frame (its CPU time over its frames), with one "
                                   "worker and with all of them (medians over the runs), and all / one: with every "
                                   "worker at its full cores the scaling is workers / that ratio, and a ratio above 1 "
                                   "is cores slowing each other down (shared caches, memory, the host's clock), not "
                                   "workers waiting (the shares of their cores say that). null where a worker's CPU "
                                   "time is not measured (a thread worker of more than one core)",
    "speedup_vs_torch": "the median over the alternating blocks of PyTorch's time / ONNX Runtime's on the same "
                        "frames",
}


def ray_tables_on_path_ms(stream: StreamResult) -> float:
    """The mean time a frame's path spent building ray tables (pipeline/detector.py builds one per calibration).

    Run in turn, that is the ``ray_table`` stage. With a stage thread the table is built first of the work
    beside the depth net and the stage is the frame's wait for that work: of a wait W for work whose table
    took R, min(W, R) was the table's (without it the wait would have been max(0, W − R)); the rest of a
    wait is the voxelization and checks that outlasted the network, which a fixed calibration still waits for.
    """
    waited = stream.stages.get("ray_table", [])
    built = stream.overlapped.get("ray_table", [])
    if not waited:
        return 0.0
    if len(built) != len(waited):  # every frame of a stream runs the same way: beside or in turn
        return float(np.mean(waited))
    return float(np.mean(np.minimum(waited, built)))


def summarize_stages(stream: StreamResult) -> dict:
    """:func:`summarize` of each stage of a stream."""
    return {stage: summarize(v) for stage, v in stream.stages.items()}


def stream_figures(stream: StreamResult) -> dict:
    """The single stream's figures of the report, from its per-frame timings: ``end_to_end_ms``, ``fps`` (1000 /
    its mean), ``fps_wall`` (the frames over the loop's wall time), ``stages_ms``, ``overlapped_ms``, and the share
    of end to end outside the network stages (:data:`NETWORK_STAGES`), with and without the ray tables' builds
    (``non_network_fraction``, ``non_network_fraction_fixed_calibration``; :data:`DEFINITIONS`)."""
    end_to_end = summarize(stream.end_to_end)
    stages = summarize_stages(stream)
    mean = end_to_end["mean"]
    # Everything of a frame's wall time outside the network runs (the input checks too); stages run
    # beside a network count only for the time the frame waited for them.
    between = mean - sum(stages[s]["mean"] for s in NETWORK_STAGES if s in stages)
    # A calibration's ray table is built on its first frame only (pipeline/detector.py): what a vehicle,
    # with one calibration, spends between the networks is the rest. With a stage thread the ray_table stage
    # is the wait for all the work beside the depth net, of which only the table's part goes.
    rays = ray_tables_on_path_ms(stream)
    return {"end_to_end_ms": end_to_end, "fps": 1e3 / mean,
            "fps_wall": stream.frames / stream.wall_s,  # the inputs' checks and the loop between frames included
            "stages_ms": stages, "overlapped_ms": {stage: summarize(ms) for stage, ms in stream.overlapped.items()},
            "non_network_fraction": between / mean, "ray_tables_on_path_ms": rays,
            "non_network_fraction_fixed_calibration": (between - rays) / (mean - rays)}


def best_peak(readings: list[PeakResult]) -> PeakResult:
    """The best reading of each micro-benchmark over ``readings`` (before and after the stream): a reading taken
    while something else ran reads low, and the networks' share of the peak would rise with it."""
    return PeakResult(matmul_gflops=max(p.matmul_gflops for p in readings),
                      conv_gflops=max(p.conv_gflops for p in readings), threads=readings[0].threads)


def peak_warning(readings: list[PeakResult], size: int) -> str | None:
    """The warning when the peak's readings (before and after the stream) differ by more than a fifth; None when
    they agree, or for a MatMul smaller than the quoted one (it runs for milliseconds: its readings vary by
    themselves)."""
    best = best_peak(readings).peak_gflops
    if size < PEAK_MATMUL or min(p.peak_gflops for p in readings) >= 0.8 * best:
        return None
    return (f"peak: the readings before and after the stream differ ({readings[0].peak_gflops:.0f} and "
            f"{readings[-1].peak_gflops:.0f} GFLOP/s): the machine's speed moved during the run, and its "
            "figures with it; the higher reading counts")


def network_figures(stages_ms: dict, stages: tuple[str, ...], flops: float, graph_flops: float,
                    peak: PeakResult | None) -> dict:
    """One network's entry of the report's ``networks``.

    stages_ms: the stream's :func:`summarize_stages`; stages: the network's stages, one a run (PIXOR's second run
    with the mirror), those timed counting; flops, graph_flops: FLOPs of one run, counted on the graph before its
    lowering (the manifest's) and on the graph that runs. The time is the sum of the stages' p50, the achieved
    GFLOP/s the FLOPs over it, its shares those of ``peak``'s best micro-benchmark and of its MatMul (None when
    ``peak`` is None: the network ran on another provider than the CPU whose peak was measured).
    """
    runs = sum(stage in stages_ms for stage in stages)
    flops, graph_flops = flops * runs, graph_flops * runs
    ms = sum(stages_ms[stage]["p50"] for stage in stages if stage in stages_ms)
    achieved = flops / (ms / 1e3) / 1e9
    return {"gflops": flops / 1e9, "graph_gflops": graph_flops / 1e9, "runs": runs, "ms": ms,
            "achieved_gflops_per_s": achieved,
            "peak_fraction": achieved / peak.peak_gflops if peak is not None else None,
            "matmul_peak_fraction": achieved / peak.matmul_gflops if peak is not None else None}


# Per-block ratios further apart than this (max / min) say the machine's load moved during the comparison.
UNSTABLE_BLOCK_SPREAD = 1.3


def block_spread(ratios: list[float]) -> dict:
    """Median, min and max of the per-block ratios of :func:`run_paired`; ``unstable`` when they spread by more
    than :data:`UNSTABLE_BLOCK_SPREAD`."""
    return {"p50": float(np.median(ratios)), "min": float(min(ratios)), "max": float(max(ratios)),
            "blocks": len(ratios), "unstable": bool(max(ratios) > UNSTABLE_BLOCK_SPREAD * min(ratios))}


def unstable_warning(what: str, spread: dict) -> str:
    """The warning for a comparison whose blocks spread (:func:`block_spread`)."""
    return (f"{what}: the per-block ratios spread from {spread['min']:.2f}× to {spread['max']:.2f}× (more than "
            f"{UNSTABLE_BLOCK_SPREAD:g}×): the machine's load moved during the comparison; the median block, "
            f"{spread['p50']:.2f}×, is the figure, and a run on a quiet machine the one to quote")


class TorchMissing(Exception):
    """PyTorch is needed (an export, the PyTorch pipeline) and the runtime install has none."""


def require_torch(why: str) -> None:
    """Raise :class:`TorchMissing` (``why``: what needs it) when torch cannot be imported."""
    try:
        import torch  # noqa: F401
    except ModuleNotFoundError as exc:
        if exc.name != "torch":
            raise
        raise TorchMissing(why) from None


class Warnings:
    """Each distinct warning of the Detectors timed, in the order they came; said once on stderr when ``say``.

    The Detector warns per frame (a scan unlike the model's, with its point count) and each Detector at load
    (initialised weights), and a run builds many (every throughput round's workers): once each is enough.
    Warnings that differ only in their numbers are one warning; ``seen`` keeps the first of each.
    """

    def __init__(self, say: bool = True) -> None:
        self.seen: list[str] = []
        self.say = say
        self._kinds: set[str] = set()
        self._lock = threading.Lock()

    def add(self, messages: list[str]) -> None:
        for message in messages:
            kind = re.sub(r"\d+", "#", message)
            with self._lock:
                if kind in self._kinds:
                    continue
                self._kinds.add(kind)
                self.seen.append(message)
            if self.say:
                print(f"warning: {message}", file=sys.stderr)


class _LoadWarnings(logging.Filter):
    """Routes pipeline.detector's load warnings to a :class:`Warnings` (instead of one line per Detector)."""

    def __init__(self, warnings: Warnings) -> None:
        super().__init__()
        self.warnings = warnings

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno >= logging.WARNING:
            self.warnings.add([record.getMessage()])
            return False
        return True


# ----------------------------------------------------------------------------- torch eager twin
class TorchSession:
    """Stands in for an ONNX Runtime session: same ``run(outputs, feeds)`` call, PyTorch eager inside."""

    def __init__(self, module, input_names: list[str]) -> None:
        self.module, self.input_names = module, input_names

    def run(self, output_names, feeds):
        import torch

        with torch.inference_mode():
            outputs = self.module(*(torch.from_numpy(feeds[name]) for name in self.input_names))
        outputs = outputs if isinstance(outputs, tuple) else (outputs,)
        return [o.numpy() for o in outputs]


@contextmanager
def _checkpoints_refused() -> Iterator[None]:
    """The exporter's word on --checkpoints that do not fit (another preset's, none in the folder) as the
    command line's InputError: one line, exit 2, as ``python -m export`` says it."""
    try:
        yield
    except (ValueError, FileNotFoundError) as exc:
        message = str(exc)  # the exporter's own messages name the flag already
        raise InputError(message if message.startswith("--checkpoints") else f"--checkpoints: {message}") from exc


def torch_twin(detector: Detector, checkpoints: Path | None) -> tuple[dict, str]:
    """PyTorch eager networks of ``detector``'s model directory, and where their weights come from.

    From ``checkpoints`` where given; otherwise an FP32 directory's own weights (for an INT8 or FP16
    directory, those of the FP32 directory it was converted from), read back from the ONNX files
    (models/onnx_weights.py) and checked against ONNX Runtime on a real KITTI frame with the exporter's
    tolerances; the exporter's initialised weights when neither is there.
    """
    from export.exporter import ExportConfig
    from export.exporter import run as export

    names = tuple(detector.manifest["networks"])
    if checkpoints is None:
        source = detector if detector.manifest.get("precision", "fp32") == "fp32" else fp32_source(detector)
        if source is not None:
            origin = "" if source is detector else f" of the FP32 directory it was converted from, {source.model_dir}"
            return onnx_twin(source, names), f"the ONNX files' own{origin}, read back (models/onnx_weights.py)"
    # The directory's own preset (its manifest's preset_config), handed over whole: a preset file's name is
    # no registered preset's, and no file of it need be at hand.
    with tempfile.TemporaryDirectory(prefix="lowres3d-torch-") as scratch, _checkpoints_refused():
        networks = export(ExportConfig(preset=None, out=Path(scratch), parity=False, checkpoints=checkpoints,
                                       networks=names), detector.preset).networks
    return networks, str(checkpoints) if checkpoints else "initialised (as the exporter initialises them)"


def fp32_source(detector: Detector) -> Detector | None:
    """The FP32 directory a converted (INT8, FP16) directory came from, if it is still there unchanged."""
    source = detector.manifest.get("precision_info", {}).get("source", {})
    recorded, wanted = Path(source.get("directory", "")), source.get("sha256")
    for candidate in (recorded, detector.model_dir.parent / recorded.name):  # as written, or a sibling
        try:
            manifest = load_manifest(candidate)
        except ModelFileError:
            continue
        if wanted and {name: entry["sha256"] for name, entry in manifest["files"].items()} == wanted:
            return Detector(candidate, providers="cpu")
    return None


def onnx_twin(detector: Detector, names: tuple[str, ...]) -> dict:
    """The networks with the weights of the directory's FP32 ONNX files, each checked against ONNX Runtime."""
    from export.inputs import kitti_inputs
    from export.parity import ParityError, cpu_session, depth_parity, pixor_parity, require_parity
    from models import build_network
    from models.onnx_weights import load_onnx_weights

    inputs = kitti_inputs(detector.preset)
    networks, results = {}, []
    for name in names:
        path = detector.model_dir / detector.manifest["networks"][name]["file"]
        networks[name] = build_network(name, detector.preset).eval()
        try:
            load_onnx_weights(networks[name], path)
        except ValueError as exc:
            raise InputError(f"--compare-torch: {exc}") from exc
        check = depth_parity if name == "depth" else pixor_parity
        found = check(networks[name], cpu_session(path), inputs)
        results.extend(found if isinstance(found, list) else [found])
    try:
        require_parity(results)
    except ParityError as exc:
        raise InputError(f"--compare-torch: the PyTorch networks do not reproduce {detector.model_dir}: {exc}") from exc
    return networks


def torch_detector(models_dir: Path, networks: dict, stage_threads: int | None = None,
                   mirror_tta: bool = False) -> Detector:
    """The same Detector with its sessions swapped for the PyTorch modules (same weights)."""
    detector = Detector(models_dir, providers="cpu", stage_threads=stage_threads, mirror_tta=mirror_tta)
    inputs = {"depth": ["rgb", "sparse_depth"], "pixor": ["bev"]}
    detector._sessions = {name: TorchSession(networks[name].eval(), inputs[name]) for name in detector._sessions}
    detector._input_names = {name: inputs[name] for name in detector._sessions}  # whole tensors, as PyTorch takes them
    return detector


# ----------------------------------------------------------------------------- runs
@dataclass
class StreamResult:
    end_to_end: list[float]
    stages: dict[str, list[float]]
    wall_s: float
    frames: int
    overlapped: dict[str, list[float]] = field(default_factory=dict)  # stages run beside a network


def run_stream(detector: Detector, frames: list[Frame], count: int, warmup: int,
               warnings: Warnings | None = None, score_threshold: float | None = None) -> StreamResult:
    """Frames one after the other (cycling), after ``warmup`` untimed frames; the Detector's warnings of each
    frame go to ``warnings``. score_threshold: as :meth:`Detector.detect`'s (None: the model's)."""
    for i in range(warmup):
        f = frames[i % len(frames)]
        result = detector.detect(f.image, f.points, f.calib, score_threshold)
        if warnings is not None:
            warnings.add(result.warnings)
    stages: dict[str, list[float]] = {}
    overlapped: dict[str, list[float]] = {}
    totals = []
    tic = time.perf_counter()
    for i in range(count):
        f = frames[i % len(frames)]
        result = detector.detect(f.image, f.points, f.calib, score_threshold)
        if warnings is not None:
            warnings.add(result.warnings)
        totals.append(result.timings_ms["total"])
        for stage, ms in result.timings_ms.items():
            if stage != "total":
                stages.setdefault(stage, []).append(ms)
        for stage, ms in result.overlapped_ms.items():
            overlapped.setdefault(stage, []).append(ms)
    return StreamResult(totals, stages, time.perf_counter() - tic, count, overlapped)


def run_paired(first: Detector, second: Detector, frames: list[Frame], count: int, warmup: int,
               block: int = 4, warnings: Warnings | None = None,
               score_threshold: float | None = None) -> tuple[StreamResult, StreamResult, list[float]]:
    """Two detectors on the same frames in alternating blocks, A B B A A B …, so a change of load on a
    shared machine slows both alike; returns both streams and each pair of blocks' time ratio second/first.

    Run one after the other, three ONNX Runtime / PyTorch ratios measured here within an hour were 2.32,
    1.76 and 1.38: the load of the machine moved between the two halves, not the code. Each block starts
    with one untimed frame: after the other runtime's block its idle threads may still spin on the cores
    (PyTorch's OpenMP pool, for up to a few hundred milliseconds), and that cost fell on the first frame.
    """
    runs = ([], []), ([], [])  # per detector: (end-to-end ms, stage dicts)
    detectors = (first, second)
    for detector in detectors:
        for i in range(warmup):
            f = frames[i % len(frames)]
            result = detector.detect(f.image, f.points, f.calib, score_threshold)
            if warnings is not None:
                warnings.add(result.warnings)
    ratios = []
    blocks = max(1, -(-count // block))
    for b in range(blocks):
        order = (0, 1) if b % 2 == 0 else (1, 0)
        spent = [0.0, 0.0]
        for which in order:
            f = frames[(b * block) % len(frames)]
            detectors[which].detect(f.image, f.points, f.calib, score_threshold)  # untimed: the other's threads go idle
            for i in range(b * block, min((b + 1) * block, count)):
                f = frames[i % len(frames)]
                result = detectors[which].detect(f.image, f.points, f.calib, score_threshold)
                if warnings is not None:
                    warnings.add(result.warnings)
                runs[which][0].append(result.timings_ms["total"])
                runs[which][1].append(result.timings_ms)
                spent[which] += result.timings_ms["total"]
        ratios.append(spent[1] / spent[0])
    streams = []
    for totals, timings in runs:
        stages = {stage: [t[stage] for t in timings] for stage in timings[0] if stage != "total"}
        streams.append(StreamResult(totals, stages, sum(totals) / 1e3, len(totals)))
    return streams[0], streams[1], ratios


@dataclass(frozen=True)
class FrameSource:
    """Where the benchmark's frames come from, so a worker process can load its own copy."""

    data: Path
    count: int
    beams: int | None

    def load(self) -> list[Frame]:
        return load_frames(self.data, self.count, self.beams)


def _frames_on(detector: Detector, frames: list[Frame], count: int, offset: int, cancel: Cancellation | None = None,
               warnings: Warnings | None = None, score_threshold: float | None = None) -> bool:
    """``count`` frames from ``offset`` on; False when ``cancel`` stopped them (between frames, or inside a
    network run: ONNX Runtime's terminate flag)."""
    for i in range(count):
        if cancel is not None and cancel.cancelled:
            return False
        f = frames[(i + offset) % len(frames)]
        try:
            result = detector.detect(f.image, f.points, f.calib, score_threshold, cancel=cancel)
        except RunCancelled:
            return False
        if warnings is not None:
            warnings.add(result.warnings)
    return True


def _worker(index: int, models: Path, provider: str | None, frames: list[Frame] | FrameSource, per_worker: int,
            warmup: int, mine: list[int], start, done, errors, mirror_tta: bool = False,
            cancel: Cancellation | None = None, warnings: Warnings | None = None,
            score_threshold: float | None = None, usage=None, device_id: int | None = None) -> None:
    """One throughput worker, a thread or a process: pin itself, load, warm up, wait for the start, run.

    device_id: the GPU its sessions run on (None: the provider's default, GPU 0).

    usage (a list for a thread, a queue for a process): gets the worker's :class:`_CpuClock` reading after its frames.

    A thread gets the frames, a list for its errors, a :class:`Cancellation` by which the caller stops it
    (Ctrl-C: a thread still inside ONNX Runtime when the interpreter ends aborts the process) and the run's
    :class:`Warnings`; a process gets a :class:`FrameSource` (it loads its own copy) and a queue, which
    carries the errors as text, and is stopped by its parent (it leaves Ctrl-C to the parent, and its
    Detector's warnings too: the parent's said them).
    """
    def fail(exc: Exception) -> None:
        if isinstance(errors, list):
            errors.append(exc)  # re-raised as it is in the main thread
        else:
            errors.put(f"worker {index}: {type(exc).__name__}: {exc}")

    process = isinstance(frames, FrameSource)
    if process:
        logging.getLogger("pipeline.detector").setLevel(logging.ERROR)
    try:
        try:
            os.sched_setaffinity(0, mine)  # this thread or process only; ORT threads created below inherit it
            if process:
                frames = frames.load()
            detector = Detector(models, providers=provider, intra_op_threads=len(mine), verify=False,
                                mirror_tta=mirror_tta, device_id=device_id)
            if not _frames_on(detector, frames, warmup, index, cancel, warnings, score_threshold):
                start.abort()
                return
        except Exception as exc:  # noqa: BLE001 — reported to the caller of run_workers
            fail(exc)
            start.abort()
            return
        try:
            start.wait()
        except threading.BrokenBarrierError:  # another worker failed, or the run was stopped: nothing to time
            return
        clock = _CpuClock(process, len(mine))
        try:
            if not _frames_on(detector, frames, per_worker, index, cancel, warnings, score_threshold):
                return
        except Exception as exc:  # noqa: BLE001 — reported to the caller of run_workers
            fail(exc)
        if usage is not None:
            entry = {"worker": index, "cores": list(mine), "device_id": device_id, "frames": per_worker,
                     **clock.read()}
            if isinstance(usage, list):
                usage.append(entry)
            else:
                usage.put(entry)
        done.wait()
    except threading.BrokenBarrierError:  # stopped while the others finished
        return
    except KeyboardInterrupt:  # a process's Ctrl-C (the terminal's goes to the whole group): the parent says it
        if not process:
            raise


class _CpuClock:
    """A throughput worker's wall time and the CPU time it got, from its start.

    ``cpu_share`` is that CPU time over the wall time of its cores: under 1 when the worker could not run,
    because another process ran on its cores (a shared machine) or, for thread workers, another worker
    held Python's interpreter lock; no latency figure shows either by itself. A process counts
    all its threads; a thread only itself, which is all its work when it has one core (ONNX Runtime then
    runs the networks on the calling thread and the Detector its stages in turn), so a thread with more
    cores gets no share.
    """

    def __init__(self, process: bool, cores: int) -> None:
        self.process, self.cores = process, cores
        self.wall, self.cpu = time.perf_counter(), self._cpu()

    def _cpu(self) -> float:
        return time.process_time() if self.process else time.thread_time()

    def read(self) -> dict:
        wall, cpu = time.perf_counter() - self.wall, self._cpu() - self.cpu
        measurable = self.process or self.cores == 1
        return {"wall_s": wall, "cpu_s": cpu if measurable else None,
                "cpu_share": cpu / (wall * self.cores) if measurable and wall > 0 else None}


# A worker that got less of its cores than this was sharing them: its round's scaling is not the hardware's.
FULL_CORE_SHARE = 0.95


def check_workers(workers: int, mode: str = "thread", cores: int | None = None) -> None:
    """Refuse more throughput workers than usable cores: each is pinned to a share of its own, and a worker
    past the cores would get none (it used to fall back to all of them, oversubscribing the others)."""
    cores = usable_cpus() if cores is None else cores
    if workers > cores:
        raise InputError(f"--threads {workers}: {mode} workers are each pinned to cores of their own, and this "
                         f"process may use {cores} core{'s' if cores != 1 else ''}; give --threads {cores} or fewer")


def run_workers(models: Path, provider: str | None, frames: list[Frame] | FrameSource, workers: int,
                per_worker: int, warmup: int, cores: list[int], mode: str = "thread", mirror_tta: bool = False,
                warnings: Warnings | None = None, score_threshold: float | None = None,
                usage: list | None = None, device_ids: list[int] | None = None, clock: dict | None = None) -> float:
    """Aggregate fps of ``workers`` workers, each pinned to its share of ``cores`` with its own sessions: their
    frames over the wall time from their common start to the last one's end, which ``clock`` gets (``wall_s``).

    device_ids: the GPUs the workers' sessions run on, worker i on ``device_ids[i % len(device_ids)]`` (None:
    every worker on the provider's default, GPU 0).

    usage: gets one dict per worker, by worker: its cores, wall time, CPU time and the share of its cores it
    got (:class:`_CpuClock`).

    mode ``thread``: threads of this process (as the paper ran its PX2's two GPUs), sharing Python's
    interpreter lock between NumPy calls. ``process``: one process each (spawned), sharing nothing;
    ``frames`` must then be a :class:`FrameSource`, from which each loads its own copy before the
    clock starts (a thread given one does the same). mirror_tta: as :class:`pipeline.detector.Detector`'s.
    More workers than cores are refused (:func:`check_workers`). Ctrl-C (KeyboardInterrupt) stops the
    workers and waits for them before it goes on up: thread workers end between frames or inside a
    network run, worker processes are terminated.
    """
    check_workers(workers, mode, len(cores))
    shares = core_shares(cores, workers)  # whole physical cores each: no worker on another's SMT siblings
    devices = [None if not device_ids else device_ids[i % len(device_ids)] for i in range(workers)]
    cancels: list[Cancellation | None] = [None] * workers
    if mode == "thread":
        start, done, errors = threading.Barrier(workers + 1), threading.Barrier(workers + 1), []
        cancels = [Cancellation() for _ in range(workers)]
        reported: list = []
        pool = [threading.Thread(target=_worker, daemon=True,
                                 args=(i, models, provider, frames, per_worker, warmup, shares[i], start, done, errors,
                                       mirror_tta, cancels[i], warnings, score_threshold, reported, devices[i]))
                for i in range(workers)]
    elif mode == "process":
        if not isinstance(frames, FrameSource):
            raise ValueError("process workers load their own frames: pass a FrameSource")
        context = multiprocessing.get_context("spawn")  # no forked copy of this process's ORT thread pools
        start, done, errors = context.Barrier(workers + 1), context.Barrier(workers + 1), context.Queue()
        reported = context.Queue()
        pool = [context.Process(target=_worker, daemon=True,
                                args=(i, models, provider, frames, per_worker, warmup, shares[i], start, done, errors,
                                      mirror_tta, None, None, score_threshold, reported, devices[i]))
                for i in range(workers)]
    else:
        raise ValueError(f"workers mode {mode!r}: expected 'thread' or 'process'")
    try:
        for worker in pool:
            worker.start()
        try:
            start.wait()
            tic = time.perf_counter()
            done.wait()
            wall = time.perf_counter() - tic
        except threading.BrokenBarrierError:
            wall = None  # a worker failed before the clock started; its error is raised below
        for worker in pool:
            worker.join()
    except KeyboardInterrupt:
        _stop(pool, cancels, start, done)
        raise
    failures = list(errors) if mode == "thread" else [errors.get() for _ in range(errors.qsize())]
    if failures or wall is None:
        failure = failures[0] if failures else "a worker stopped before the clock started"
        raise failure if isinstance(failure, Exception) else RuntimeError(failure)
    if usage is not None:
        entries = reported if isinstance(reported, list) else [reported.get() for _ in range(workers)]
        usage.extend(sorted(entries, key=lambda entry: entry["worker"]))
    if clock is not None:
        clock["wall_s"] = wall
    return workers * per_worker / wall


def _stop(pool: list, cancels: list[Cancellation | None], start, done) -> None:
    """Stop the workers of :func:`run_workers` and wait for them: a daemon thread still inside ONNX Runtime
    when the interpreter ends takes the process down with ``terminate called without an active exception``."""
    for cancel in cancels:
        if cancel is not None:
            cancel.cancel()  # ends the network run under way, and the frames after it
    start.abort()  # workers waiting for the start or for the others to finish go home
    done.abort()
    for worker in pool:
        if isinstance(worker, multiprocessing.process.BaseProcess) and worker.is_alive():
            worker.terminate()
    for worker in pool:
        while True:
            try:
                if worker.ident is not None:  # started
                    worker.join()
                break
            except KeyboardInterrupt:  # Ctrl-C again: the workers are ending already; still wait for them
                continue


def run_throughput(models: Path, provider: str | None, source: FrameSource, frames: list[Frame], workers: int,
                   per_worker: int, warmup: int, cores: list[int], rounds: int = 3, mode: str = "thread",
                   mirror_tta: bool = False, warnings: Warnings | None = None,
                   score_threshold: float | None = None, device_ids: list[int] | None = None) -> dict:
    """One worker on its share of the cores and ``workers`` workers on all of them, in alternating rounds
    (1 N N 1 1 N), so a change of load on a shared machine touches both; medians over the rounds.

    device_ids: the GPUs, worker i on ``device_ids[i % len(device_ids)]`` (:func:`run_workers`); the single
    worker takes them in turn with the core shares.

    ``scaling`` is per share of cores: N workers on N shares against one worker on one share. The single
    worker takes each share in turn (round r the r-th), so a neighbour busy on one core does not touch
    only the N-worker runs. Each run's workers, frames, wall time and fps (their quotient) and the share of
    their cores each worker got are kept (``runs``); a run where a worker got less than :data:`FULL_CORE_SHARE`
    is named in ``shared_runs`` and said in ``warnings``: its fps measured the neighbour as well.
    """
    check_workers(workers, mode, len(cores))
    shares = core_shares(cores, workers)
    one, many, runs, shared = [], [], [], []
    for r in range(rounds):
        for n in ((1, workers) if r % 2 == 0 else (workers, 1)):
            usage: list[dict] = []
            clock: dict = {}
            devices = device_ids
            if device_ids and n == 1:
                devices = [device_ids[r % workers % len(device_ids)]]  # the GPU worker r % workers would have
            fps = run_workers(models, provider, source if mode == "process" else frames, n, per_worker, warmup,
                              shares[r % workers] if n == 1 else [cpu for mine in shares for cpu in mine], mode,
                              mirror_tta, warnings, score_threshold, usage, devices, clock)
            (one if n == 1 else many).append(fps)
            runs.append({"round": r, "workers": n, "frames": n * per_worker, "wall_s": clock["wall_s"], "fps": fps,
                         "per_worker": usage})
            got = [u["cpu_share"] for u in usage if u["cpu_share"] is not None]
            if got and min(got) < FULL_CORE_SHARE:
                shared.append(len(runs) - 1)
                if warnings is not None:
                    lock = " or waited for Python's interpreter lock" if mode == "thread" and n > 1 else ""
                    warnings.add([(f"throughput round {r + 1}, {n} worker{'s' if n > 1 else ''}: a worker got "
                                   f"{100 * min(got):.0f} % of its cores (something else ran on them{lock}): that "
                                   "round's scaling is not the hardware's alone")])
    fps_one, fps_many = float(np.median(one)), float(np.median(many))
    return {"workers": workers, "mode": mode, "fps": fps_many, "fps_one_worker": fps_one,
            "scaling": fps_many / fps_one, "cores_per_worker": len(shares[0]), "rounds": rounds,
            "device_ids": None if not device_ids else [device_ids[i % len(device_ids)] for i in range(workers)],
            "scaling_per_round": [m / o for m, o in zip(many, one, strict=True)],
            "cpu_ms_per_frame": cpu_per_frame(runs), "runs": runs, "shared_runs": shared}


def cpu_per_frame(runs: list[dict]) -> dict | None:
    """The CPU time a frame took with one worker and with all of them (ms; medians over the runs of each) and
    their ratio (``DEFINITIONS["throughput.cpu_ms_per_frame"]``): what tells a scaling short of the workers'
    count by cores that slow each other from one by workers that wait. None where a worker's CPU time is not
    measured (:class:`_CpuClock`)."""
    one, many = [], []
    for run in runs:
        cpu = [u["cpu_s"] for u in run["per_worker"]]
        if not cpu or any(c is None for c in cpu):
            return None
        (one if run["workers"] == 1 else many).append(1e3 * sum(cpu) / run["frames"])
    if not one or not many:
        return None
    alone, together = float(np.median(one)), float(np.median(many))
    return {"one_worker": alone, "all_workers": together, "ratio": together / alone}


def _reads(detector: Detector) -> str:
    """What a model directory's pipeline reads, for a refusal: "reads a 16-line scan + camera"."""
    lines = f"{detector.trained_lines}-line scan" if detector.trained_lines else "scan"
    return f"reads a {lines} + camera" if detector.two_stage else f"reads a {lines} alone (LiDAR-only)"


def profile_operators(detector: Detector, frame: Frame, threads: int, matmul_gflops: float) -> dict:
    """Each network's time per operator type (benchmarks/op_profile.py), for the report's ``networks``."""
    profiles = {}
    for name, feeds in detector.network_inputs(frame.image, frame.points, frame.calib).items():
        entry = detector.manifest["networks"][name]
        providers = detector.providers_in_use[name]
        try:
            profile = profile_network(detector.model_dir / entry["file"], providers, threads, feeds)
        except ValueError as exc:
            raise InputError(f"--ops: {exc}") from None
        profiles[name] = profile.to_dict(entry["flops"] / 1e9, matmul_gflops)
    return profiles


def versions() -> dict:
    """Versions of the packages timed; ONNX Runtime's from the module, as its GPU and Jetson builds are packages
    of other names (``onnxruntime_package`` says which)."""
    import onnxruntime as ort

    out = {"onnxruntime": ort.__version__, "onnxruntime_package": None}
    for package in ("onnxruntime", "onnxruntime-gpu", "onnxruntime-openvino", "onnxruntime-directml"):
        try:
            metadata.version(package)
        except metadata.PackageNotFoundError:
            continue
        out["onnxruntime_package"] = package
        break
    for name in ("numpy", "opencv-python-headless", "torch"):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_WAIT_POLICY", "GOMP_SPINCOUNT")


def governor(cpu: int = 0) -> str | None:
    """The CPU frequency governor of ``cpu`` (``performance``, ``powersave``, …); None where the kernel shows none
    (a virtual machine often has no cpufreq)."""
    try:
        return Path(f"/sys/devices/system/cpu/cpu{cpu}/cpufreq/scaling_governor").read_text().strip() or None
    except OSError:
        return None


def load_average() -> list[float] | None:
    """The 1, 5 and 15-minute load averages (None off Unix): what else the machine was running."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except (AttributeError, OSError):
        return None


def machine() -> dict:
    # INT8 speed (and exactness) hangs on VNNI, fp32 on AVX-512 and FMA: say which this box has.
    cpus = sorted(os.sched_getaffinity(0))
    return {**describe_cpu(), "cores": usable_cpus(), "affinity_cpus": len(cpus),
            "cpu_quota": cpu_quota(), "governor": governor(cpus[0]),
            # At the start; load_average_end is added when the run ends. On a shared machine the figures move
            # with it (docs/measurements.md quotes it by hand).
            "load_average_start": load_average(), "system": platform.platform(),
            "python": platform.python_version(),
            # Thread counts set for NumPy's BLAS and OpenMP runtimes move the figures (docs/measurements.md, session 35).
            "thread_environment": {name: os.environ[name] for name in THREAD_VARIABLES if name in os.environ}}


# ----------------------------------------------------------------------------- main job
def run(preset: str | None = None, models: Path | None = None, provider: str | None = None, threads: int = 1,
        frames: int = 20, warmup: int = 3, data: Path = BUNDLED, beams: int | None = None,
        compare_torch: bool = False, checkpoints: Path | None = None, progress: bool = True,
        precision: str | None = None, baseline: Path | None = None, worker_kind: str = "thread",
        peak_size: int = PEAK_MATMUL, ops: bool = False, stage_threads: int | None = None,
        mirror_tta: bool = False, score_threshold: float | None = None,
        device_ids: list[int] | None = None) -> dict:
    """Measure everything; returns the JSON-able report (``warnings``: each distinct warning of the Detectors,
    said once on stderr as it came where ``progress``, with a line as each measurement starts).

    models: the model directory; None: :data:`SHIPPED` (:data:`SHIPPED_INT8` for ``precision`` int8) when
    neither ``preset`` nor ``checkpoints`` is given and it is there, else ``preset`` (default
    :data:`DEFAULT_PRESET`) exported with ``checkpoints`` or initialised weights (PyTorch:
    :class:`TorchMissing` without it). With ``models`` ``preset`` may only name the directory's own preset.
    precision: with ``models`` it must match the directory's (a check); without, the FP32 directory is
    converted (calibrated on the benchmark frames; INT8 with 7-bit weights, as the shipped one).
    beams: the line count to thin scans to; None: the model's own (its manifest's
    ``networks.pixor.training.input``: a 64-line model's scans are kept as stored, others thinned to 16);
    0: as stored.
    threads: throughput workers (1: none), at most one per usable core (InputError).
    peak_size: the MatMul's size in the peak micro-benchmark (12 s at 4096 here; the figures quoted use 4096).
    ops: also profile each network operator by operator (``networks[name]["ops"]``).
    stage_threads: the single-stream Detectors' (:class:`pipeline.detector.Detector`; None: its default,
    2 on two or more cores); throughput workers of one core each run their stages in turn.
    mirror_tta: PIXOR also on the mirrored BEV in every Detector timed (PyTorch's and the baseline's too), timed
    as the stage ``pixor_mirror`` (its copies and averaging as ``mirror_merge``); PIXOR's FLOPs and time per
    frame count both runs.
    score_threshold: every Detector's, as :meth:`Detector.detect`'s (None: the model's, 0.5 for the shipped
    ones); the decoding's time grows with the candidates it keeps (at 0.05, the evaluation's, about 9 ms
    a frame against 1 ms).
    device_ids: GPUs (CUDA or TensorRT): the single stream runs on the first, throughput worker i on
    ``device_ids[i % len(device_ids)]``, as the paper ran its PX2's two GPUs as two threads (None: all on GPU 0).
    """
    if threads > 1:  # before anything is exported or timed
        check_workers(threads, worker_kind, usable_cpus())
    warnings = Warnings(say=progress)
    said_once = _LoadWarnings(warnings)
    logger = logging.getLogger("pipeline.detector")
    logger.addFilter(said_once)
    try:
        report = _run(preset, models, provider, threads, frames, warmup, data, beams, compare_torch, checkpoints,
                      progress, precision, baseline, worker_kind, peak_size, ops, stage_threads, mirror_tta, warnings,
                      score_threshold, device_ids)
    finally:
        logger.removeFilter(said_once)
    report["warnings"] = list(warnings.seen)
    return report


def _named_preset(given: str) -> Preset:
    """The preset ``given`` names (a registered name or a preset file); an InputError with get_preset's word (the
    valid names, or the file's fault) otherwise. Only this call's ValueError is the command line's: one from
    anywhere else in a run is a defect, and keeps its traceback."""
    try:
        return get_preset(given)
    except ValueError as exc:
        raise InputError(f"--preset: {exc}") from exc


def check_models_preset(given: str, held: Preset, models: Path) -> None:
    """InputError unless --preset ``given`` (a name or a preset file) is the preset ``held`` of the model directory
    ``models``: another preset's name, or else the first field whose value differs (a preset file may reuse the
    name with another configuration)."""
    wanted = _named_preset(given)
    if wanted.name != held.name:
        raise InputError(f"--preset {given}: {models} holds {held.name} models (leave --preset out with --models)")
    now, then = preset_fields(wanted.to_dict()), preset_fields(held.to_dict())
    for name, value in now.items():
        if then.get(name) != value:
            raise InputError(f"--preset {given}: {name} {value!r}, but {models} holds {then.get(name)!r} (preset "
                             f"{held.name!r}, another configuration under the same name; leave --preset out with "
                             "--models)")


def _step(progress: bool, what: str) -> None:
    """A line on stderr as a measurement starts (``what`` it times), where ``progress``."""
    if progress:
        print(f"timing {what} …", file=sys.stderr, flush=True)


def _run(preset: str | None, models: Path | None, provider: str | None, threads: int, frames: int, warmup: int,
         data: Path, beams: int | None, compare_torch: bool, checkpoints: Path | None, progress: bool,
         precision: str | None, baseline: Path | None, worker_kind: str, peak_size: int, ops: bool,
         stage_threads: int | None, mirror_tta: bool, warnings: Warnings,
         score_threshold: float | None = None, device_ids: list[int] | None = None) -> dict:
    """:func:`run`'s measurements: the model directory, its Detectors and the frames first (a bad input is
    refused before minutes of timing), then each measurement in turn, into the report."""
    cores = sorted(os.sched_getaffinity(0))[: usable_cpus()]  # a container's CPU quota bounds them too
    if compare_torch:
        require_torch("--compare-torch times the PyTorch networks")
    chosen = _models_to_time(preset, models, checkpoints, precision, data, frames)
    detector, other = _load_detectors(chosen.path, baseline, provider, cores, stage_threads, mirror_tta, device_ids)
    _check_detector(detector, chosen.path, precision, preset, ops)
    twin = _pytorch_networks(detector, chosen, checkpoints) if compare_torch else None
    beams = _beams_for(detector, beams)
    source = FrameSource(data, max(frames, warmup), beams)
    pool = source.load()
    report = _report_head(preset, chosen.described, detector, device_ids, frames, len(pool), warmup,
                          score_threshold, beams, data, mirror_tta)
    on_cpu = all(p[0] == "CPUExecutionProvider" for p in detector.providers_in_use.values())

    peaks = [_read_peak(progress, "before", len(cores), peak_size)]
    _step(progress, f"the single stream: {frames} frames after {warmup} warm-up, {report['input']}")
    stream = run_stream(detector, pool, frames, warmup, warnings, score_threshold)
    report.update(stream_figures(stream))
    report["stage_threads"] = detector.stage_threads
    peaks.append(_read_peak(progress, "after", len(cores), peak_size))
    # Measured before and after the stream, the best of each kind counts: a reading taken while something
    # else ran reads low (here 88–190 GFLOP/s for the MatMul in seven runs on a shared machine), and the
    # networks' share of the peak would rise with it.
    peak = best_peak(peaks)
    report.update(_peak_figures(peak, peaks, peak_size, warnings))
    report["networks"] = _networks(detector, report["stages_ms"], peak, on_cpu, report["precision"], warnings)
    if ops:
        _add_operator_profiles(report["networks"], detector, pool[0], len(cores), peak.matmul_gflops)

    report["throughput"] = None  # without --threads: no throughput run (the key is there for other tools)
    _warn_unused_gpus(device_ids, threads, on_cpu, warnings)
    if threads > 1:
        report["throughput"] = _throughput(chosen.path, provider, source, pool, threads, frames, warmup, cores,
                                           worker_kind, mirror_tta, warnings, score_threshold, device_ids,
                                           report["fps_wall"], progress)
    if twin is not None:
        report.update(_torch_comparison(detector, chosen.path, twin, pool, frames, warmup, len(cores), stage_threads,
                                        mirror_tta, warnings, score_threshold, progress))
    if other is not None:
        report.update(_baseline_comparison(detector, other, baseline, pool, frames, warmup, warnings,
                                           score_threshold, progress))
    report["machine"]["load_average_end"] = load_average()
    report["definitions"] = DEFINITIONS
    report["_samples"] = {"end_to_end": stream.end_to_end, "stages": stream.stages, "overlapped": stream.overlapped}
    if chosen.scratch is not None:
        chosen.scratch.cleanup()
    return report


@dataclass
class _ModelsToTime:
    """The model directory a run times, what the report calls it, and what came with an export."""

    path: Path
    described: str
    scratch: tempfile.TemporaryDirectory[str] | None = None  # holds an export or a conversion; removed at the end
    torch_networks: dict | None = None  # an export's PyTorch modules, for --compare-torch
    torch_weights: str = ""


def _models_to_time(preset: str | None, models: Path | None, checkpoints: Path | None, precision: str | None,
                    data: Path, frames: int) -> _ModelsToTime:
    """The model directory :func:`run` times (its ``models``), converted to ``precision`` where that is asked."""
    chosen, convert = _choose_models(preset, models, checkpoints, precision)
    if convert and precision is not None:
        chosen = _convert_models(chosen, precision, data, frames)
    return chosen


def _choose_models(preset: str | None, models: Path | None, checkpoints: Path | None,
                   precision: str | None) -> tuple[_ModelsToTime, bool]:
    """The model directory before any conversion, and whether to convert it to ``precision``: the shipped one
    (its INT8 twin for int8, where it is there) when neither a directory, a preset nor checkpoints are given,
    else the preset exported, else ``models`` as given (its precision checked, never converted)."""
    shipped = models is None and preset is None and checkpoints is None and (SHIPPED / "manifest.json").is_file()
    if shipped:
        shipped_int8 = precision == "int8" and (SHIPPED_INT8 / "manifest.json").is_file()
        path = SHIPPED_INT8 if shipped_int8 else SHIPPED
        return _ModelsToTime(path, str(path)), precision not in (None, "fp32") and not shipped_int8
    if models is None:
        return _export_preset(preset, checkpoints), precision not in (None, "fp32")
    return _ModelsToTime(models, str(models)), False


def _export_preset(preset: str | None, checkpoints: Path | None) -> _ModelsToTime:
    """``preset`` (default :data:`DEFAULT_PRESET`) exported into a scratch directory, with ``checkpoints`` or
    initialised weights (PyTorch: :class:`TorchMissing` without it)."""
    require_torch(f"--preset {preset or DEFAULT_PRESET} is exported with PyTorch first (without --preset and "
                  "--checkpoints the shipped weights/edge is timed, which needs none)")
    from export.exporter import ExportConfig
    from export.exporter import run as export

    scratch = tempfile.TemporaryDirectory(prefix="lowres3d-latency-")
    models = Path(scratch.name) / "fp32"  # a reduced precision is converted beside it, not inside it
    with _checkpoints_refused():
        result = export(ExportConfig(preset=preset or DEFAULT_PRESET, out=models, parity=False,
                                     checkpoints=checkpoints))
    return _ModelsToTime(models, f"exported ({checkpoints})" if checkpoints else "exported (initialised weights)",
                         scratch, torch_networks=result.networks,  # the exported modules: the same weights on both sides
                         torch_weights=str(checkpoints) if checkpoints else "initialised, the same as the ONNX files'")


def _convert_models(chosen: _ModelsToTime, precision: str, data: Path, frames: int) -> _ModelsToTime:
    """``chosen`` converted to ``precision`` beside it in the scratch directory, calibrated on the benchmark's
    frames."""
    from export.precision import convert_precision

    scratch = chosen.scratch
    if scratch is None:
        scratch = tempfile.TemporaryDirectory(prefix="lowres3d-latency-")
    reduced = Path(scratch.name) / precision
    # INT8 as the shipped weights/edge-int8 is made (python -m export.precision --reduce-range): 7-bit
    # weights, the same outputs on every x86 CPU; full 8-bit ones saturate on CPUs without VNNI (pipeline/cpu.py).
    convert_precision(chosen.path, reduced, precision, data, calibration_frames=min(frames, 20),
                      reduce_range=precision == "int8")
    return replace(chosen, path=reduced, described=f"{chosen.described}, converted to {precision}", scratch=scratch)


def _load_detectors(models: Path, baseline: Path | None, provider: str | None, cores: list[int],
                    stage_threads: int | None, mirror_tta: bool,
                    device_ids: list[int] | None) -> tuple[Detector, Detector | None]:
    """The single stream's Detector on every core and the first GPU, and the baseline's beside it (None without
    ``baseline``); a baseline that reads another input than ``models`` is refused."""
    first_gpu = device_ids[0] if device_ids else None
    detector = Detector(models, providers=provider, intra_op_threads=len(cores), stage_threads=stage_threads,
                        mirror_tta=mirror_tta, device_id=first_gpu)
    # Loaded now, so a bad directory is refused before minutes of timing.
    other = None if baseline is None else Detector(baseline, providers=provider, intra_op_threads=len(cores),
                                                   stage_threads=stage_threads, mirror_tta=mirror_tta,
                                                   device_id=first_gpu)
    if other is not None and (other.two_stage, other.trained_lines) != (detector.two_stage, detector.trained_lines):
        # The same frames would be another pipeline's input (and thinned for --models alone): no speed-up to say.
        raise InputError(f"--baseline {baseline}: {_reads(other)}, and {models} {_reads(detector)}: give a baseline "
                         "of the same input (its FP32 source, say)")
    return detector, other


def _check_detector(detector: Detector, models: Path, precision: str | None, preset: str | None, ops: bool) -> None:
    """InputError, before any timing, where the loaded model directory is not the ``precision`` or ``preset``
    asked for, or ``ops`` asks for operator times of a provider other than the CPU's."""
    actual = detector.manifest.get("precision", "fp32")
    if precision and actual != precision:
        raise InputError(f"--precision {precision}, but {models} holds {actual} models")
    if preset:
        check_models_preset(preset, detector.preset, models)
    if ops and any(p[0] != "CPUExecutionProvider" for p in detector.providers_in_use.values()):
        # Refused before minutes of timing: on CUDA the profiler's kernel times are the launches', not the GPU's
        # work; TensorRT runs each graph as one engine, with no operators to time.
        raise InputError(f"--ops: ONNX Runtime's profiler times the operators of the CPU provider only (on a GPU "
                         f"its kernel times are the launches'; TensorRT runs an engine of its own); {GPU_PROFILER_HINT}")


def _pytorch_networks(detector: Detector, chosen: _ModelsToTime, checkpoints: Path | None) -> tuple[dict, str]:
    """``--compare-torch``'s PyTorch networks and where their weights come from: an export's own modules, else
    the model directory's twin (:func:`torch_twin`)."""
    if chosen.torch_networks is not None:
        return chosen.torch_networks, chosen.torch_weights
    # The PyTorch twin of a model directory is built for that directory's preset and networks, before
    # any timing, so a mismatch is refused at once instead of after minutes of measurements.
    return torch_twin(detector, checkpoints)


def _beams_for(detector: Detector, beams: int | None) -> int | None:
    """The line count to thin scans to (None: as stored): ``beams`` as given (0: as stored), or by default the
    model's own."""
    if beams is None:  # the model's own: a 64-line model's scans as they are (KITTI's have 64), else its lines (16)
        beams = lines_to_thin_to(detector.trained_lines) or None
    return beams or None


def _report_head(preset: str | None, described: str, detector: Detector, device_ids: list[int] | None,
                 frames: int, distinct: int, warmup: int, score_threshold: float | None, beams: int | None,
                 data: Path, mirror_tta: bool) -> dict:
    """The report's first part: what was timed (model, code, input, frames, settings) and on what machine."""
    trained_on = (detector.manifest["networks"]["pixor"].get("training") or {}).get("input")
    scan = f"{beams}-line scan" if beams else "scan as stored"
    info = detector.manifest.get("precision_info") or {}
    return {"preset": detector.preset.name, "models": described,
            # The preset itself: a preset file's name alone would not find it again.
            "preset_config": detector.preset.to_dict(),
            "preset_file": preset if preset and is_preset_file(preset) else None,
            # Which model and which code were timed: the service's X-Model-ID, and the git commit.
            "model_id": load_manifest_with_digest(detector.model_dir)[1], "code": code_version(),
            "weights": detector.manifest.get("weights"), "provider": detector.providers_in_use,
            "device_ids": device_ids,
            "precision": detector.manifest.get("precision", "fp32"),
            "quantization": {key: info[key] for key in ("weights", "reduce_range") if key in info},
            "frames": frames, "distinct_frames": distinct, "warmup": warmup,
            "score_threshold": detector.preset.decode.score_threshold if score_threshold is None
            else score_threshold,
            "input": f"{scan} + camera" if detector.two_stage else
                     f"{scan}, LiDAR only (PIXOR trained on {trained_on or 'an input not recorded'})",
            "beams": beams, "trained_on": trained_on,
            "data": str(data), "mirror_tta": mirror_tta, "machine": machine(), "versions": versions(),
            "paper": PAPER}


def _read_peak(progress: bool, when: str, threads: int, size: int) -> PeakResult:
    """One reading of the CPU's peak (benchmarks/peak.py), ``when`` ("before", "after") the stream."""
    _step(progress, f"the peak ({size}² MatMul, 3×3 conv), {when} the stream")
    return measure_peak(threads, matmul_n=size)


def _peak_figures(peak: PeakResult, readings: list[PeakResult], size: int, warnings: Warnings) -> dict:
    """The report's ``peak_gflops`` and ``peak_detail``: the best ``peak`` of the ``readings``; a warning where
    the readings differ (:func:`peak_warning`)."""
    figures = {"peak_gflops": peak.peak_gflops,
               "peak_detail": {f"matmul_{size}_gflops": peak.matmul_gflops, "matmul_size": size,
                               "conv3x3_256_gflops": peak.conv_gflops, "threads": peak.threads,
                               "readings": [{"matmul_gflops": p.matmul_gflops, "conv3x3_256_gflops": p.conv_gflops}
                                            for p in readings],
                               "provider": "CPUExecutionProvider"}}
    if (moved := peak_warning(readings, size)) is not None:
        warnings.add([moved])
    return figures


def _networks(detector: Detector, stages_ms: dict, peak: PeakResult, on_cpu: bool, precision: str,
              warnings: Warnings) -> dict:
    """The report's ``networks``: each network timed, its FLOPs, time and share of the peak
    (:func:`network_figures`); a warning where an fp32 network ran above the peak."""
    networks = {}
    for name, stages in (("depth", ("depth_net",)), ("pixor", ("pixor", "pixor_mirror"))):
        if name in detector.manifest["networks"] and stages[0] in stages_ms:
            entry = detector.manifest["networks"][name]
            # The manifest counts the graph before its lowering for the CPU (zero-padded channels are no work);
            # the graph that runs multiplies a little more (an INT8 one's sub-pixel convolutions more still).
            # The peak is the CPU's: against a GPU's network time a share of it would mean nothing.
            networks[name] = network_figures(stages_ms, stages, entry["flops"],
                                             count_flops(detector.model_dir / entry["file"]).total,
                                             peak if on_cpu else None)
            achieved = networks[name]["achieved_gflops_per_s"]
            # The peak is fp32's: an INT8 network may run above it (VNNI does four multiply-adds where fp32 does one).
            if on_cpu and precision == "fp32" and achieved > peak.peak_gflops:
                warnings.add([(f"{name}: {achieved:.0f} GFLOP/s, above the measured peak ({peak.peak_gflops:.0f}): "
                              "the peak read low (the machine was busy while it ran?); its share is not a figure")])
    return networks


def _add_operator_profiles(networks: dict, detector: Detector, frame: Frame, threads: int,
                           matmul_gflops: float) -> None:
    """``--ops``: each network's time per operator type into its entry of ``networks`` (``ops``)."""
    for name, profile in profile_operators(detector, frame, threads, matmul_gflops).items():
        if name in networks:
            networks[name]["ops"] = profile


def _warn_unused_gpus(device_ids: list[int] | None, threads: int, on_cpu: bool, warnings: Warnings) -> None:
    """Warnings for GPU ids no worker uses, and for throughput workers that share a GPU."""
    gpus = sorted(set(device_ids or [0]))
    if device_ids and len(device_ids) > threads:
        unused = ", ".join(map(str, device_ids[threads:]))
        warnings.add([(f"--device-ids {','.join(map(str, device_ids))}: GPU {unused} not used (--threads {threads}: "
                      f"the single stream runs on GPU {device_ids[0]}, throughput worker i on the i-th id)")])
    if threads > 1 and not on_cpu and len(gpus) < threads:
        shared_gpus = "GPU 0" if not device_ids else f"GPU{'s' if len(gpus) > 1 else ''} {', '.join(map(str, gpus))}"
        warnings.add([(f"--threads {threads}: the workers share {shared_gpus}, so on a box with more GPUs the "
                      "throughput is not the box's; give each its own with --device-ids (0,1 on two GPUs)")])


def _throughput(models: Path, provider: str | None, source: FrameSource, pool: list[Frame], threads: int,
                frames: int, warmup: int, cores: list[int], worker_kind: str, mirror_tta: bool, warnings: Warnings,
                score_threshold: float | None, device_ids: list[int] | None, fps_wall: float,
                progress: bool) -> dict:
    """The report's ``throughput``: 1 and ``threads`` workers in alternating rounds (:func:`run_throughput`),
    and the workers' fps against the single stream's ``fps_wall``."""
    _step(progress, f"the throughput: 1 and {threads} {worker_kind} workers in 3 alternating rounds")
    throughput = run_throughput(models, provider, source, pool, threads, max(frames // threads, 2),
                                warmup, cores, mode=worker_kind, mirror_tta=mirror_tta, warnings=warnings,
                                score_threshold=score_threshold, device_ids=device_ids)
    # The workers' fps against the single stream's, which had every core too: what the box gains by
    # running frames side by side rather than one frame on all cores.
    # Frames over wall time on both sides (report["fps"] is 1000 / the mean of detect's own times).
    throughput["vs_single_stream"] = throughput["fps"] / fps_wall
    return throughput


def _torch_comparison(detector: Detector, models: Path, twin: tuple[dict, str], pool: list[Frame], frames: int,
                      warmup: int, threads: int, stage_threads: int | None, mirror_tta: bool, warnings: Warnings, score_threshold: float | None, progress: bool) -> dict:
    """``--compare-torch``: the report's ``torch_*``, ``paired_*`` and ``speedup_vs_torch*`` entries, from the
    PyTorch eager ``twin`` (its networks, where their weights come from) and ``detector`` in alternating blocks
    (:func:`run_paired`)."""
    import torch

    torch_networks, torch_weights = twin

    _step(progress, "PyTorch eager against ONNX Runtime in alternating blocks")
    torch.set_num_threads(threads)
    paired, eager, ratios = run_paired(detector, torch_detector(models, torch_networks, stage_threads, mirror_tta), pool,
                                       frames, warmup, warnings=warnings, score_threshold=score_threshold)
    figures: dict = {"torch_end_to_end_ms": summarize(eager.end_to_end), "torch_stages_ms": summarize_stages(eager)}
    # Against the ONNX Runtime frames interleaved with the PyTorch ones, not the stream above.
    figures["paired_end_to_end_ms"] = summarize(paired.end_to_end)
    figures["paired_stages_ms"] = summarize_stages(paired)
    # The median block's ratio: one block disturbed by a neighbour (PyTorch's threads suffer it far more than
    # ONNX Runtime's) moves the means' ratio, here once 2.60× against 1.60× for the median block.
    figures["speedup_vs_torch_blocks"] = block_spread(ratios)
    figures["speedup_vs_torch"] = figures["speedup_vs_torch_blocks"]["p50"]
    figures["speedup_vs_torch_of_means"] = (figures["torch_end_to_end_ms"]["mean"]
                                            / figures["paired_end_to_end_ms"]["mean"])
    if figures["speedup_vs_torch_blocks"]["unstable"]:
        warnings.add([unstable_warning("--compare-torch", figures["speedup_vs_torch_blocks"])])
    # The networks alone do not depend on the weights' values; the stages between them do (candidates to
    # decode, pseudo points to bin), so where the twin has initialised weights only these compare like with like.
    figures["speedup_vs_torch_networks"] = {
        stage: figures["torch_stages_ms"][stage]["p50"] / figures["paired_stages_ms"][stage]["p50"]
        for stage in NETWORK_STAGES if stage in figures["paired_stages_ms"]}
    figures["torch_weights"] = torch_weights
    return figures


def _baseline_comparison(detector: Detector, other: Detector, baseline: Path | None, pool: list[Frame], frames: int,
                         warmup: int, warnings: Warnings, score_threshold: float | None, progress: bool) -> dict:
    """``--baseline``: the report's ``baseline`` and ``speedup_vs_baseline*`` entries, from ``other`` (the
    baseline's Detector) and ``detector`` in alternating blocks (:func:`run_paired`)."""
    _step(progress, f"the baseline {baseline} against it in alternating blocks")
    paired, base, ratios = run_paired(detector, other, pool, frames, warmup, warnings=warnings,
                                      score_threshold=score_threshold)
    figures: dict = {"baseline": {"models": str(baseline), "precision": other.manifest.get("precision", "fp32"),
                                  "end_to_end_ms": summarize(base.end_to_end),
                                  "stages_ms": summarize_stages(base),
                                  "paired_end_to_end_ms": summarize(paired.end_to_end),
                                  "paired_stages_ms": summarize_stages(paired)},
                     "speedup_vs_baseline_blocks": block_spread(ratios)}
    figures["speedup_vs_baseline"] = figures["speedup_vs_baseline_blocks"]["p50"]  # as speedup_vs_torch
    figures["speedup_vs_baseline_of_means"] = float(np.mean(base.end_to_end) / np.mean(paired.end_to_end))
    if figures["speedup_vs_baseline_blocks"]["unstable"]:
        warnings.add([unstable_warning("--baseline", figures["speedup_vs_baseline_blocks"])])
    return figures


def latency_figure(report: dict):
    """The figure of :func:`plot` (not saved): a box plot per stage, read top to bottom in the printed
    report's order, end to end last, each box's mean marked and its p50 and mean written beside it; the title
    names the model directory, its preset, precision and input, the frames and the machine."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    samples = report["_samples"]
    # Each stage as the frame spent it; work made on the stage thread beside the depth net after it, apart.
    beside = samples.get("overlapped", {})
    names = list(samples["stages"]) + [f"{n} (beside depth net)" for n in beside] + ["end to end"]
    data = list(samples["stages"].values()) + list(beside.values()) + [samples["end_to_end"]]
    fig, ax = plt.subplots(figsize=(8, 4 + 0.3 * len(beside)))
    # The mean drawn too: the README and the printed report quote the end-to-end mean (fps = 1000 / mean).
    ax.boxplot(data, orientation="horizontal", tick_labels=names, showfliers=True, showmeans=True,
               meanprops={"marker": "D", "markersize": 4, "markerfacecolor": "black", "markeredgecolor": "black"})
    ax.invert_yaxis()  # the first stage on top, as the printed report lists them
    ax.set_xscale("log")
    ax.set_xlabel("latency per frame (ms, log scale)\nbox p25–p75, line p50, ◆ mean, whiskers to 1.5 × the box's "
                  "width, circles beyond", fontsize=8)
    right = max(float(np.max(d)) for d in data if len(d))
    ax.set_xlim(right=right * 40)  # room for the figures beside the slowest boxes (log axis: 1.6 decades)
    for row, values in enumerate(data, start=1):
        if len(values):
            ax.annotate(f"p50 {np.median(values):.3g} · mean {np.mean(values):.3g} ms", (float(np.max(values)), row),
                        xytext=(6, 0), textcoords="offset points", va="center", fontsize=7)
    machine = report["machine"]
    tta = ", mirror TTA" if report.get("mirror_tta") else ""
    ax.set_title(f"lowres3d {report['models']}: latency per stage\n{report['preset']} ({report['precision']}{tta}), "
                 f"{report['input']}\n{report['frames']} frames after {report['warmup']} warm-up, "
                 f"{cpu_label(machine)}, {machine['cores']} cores", fontsize=9)
    fig.tight_layout()
    return fig


def plot(report: dict, path: Path) -> None:
    """Latency distribution per stage (box plots), end to end last, as a picture file."""
    import matplotlib.pyplot as plt

    fig = latency_figure(report)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _governor_and_load(described: dict) -> str:
    """"; governor performance; load average 0.9 → 2.1" from :func:`machine`'s dict (what is known of it)."""
    text = f"; governor {described['governor']}" if described.get("governor") else ""
    start, end = described.get("load_average_start"), described.get("load_average_end")
    if start and end:
        text += f"; load average {start[0]:.1f} at the start, {end[0]:.1f} at the end"
    return text


def print_report(report: dict) -> None:
    """The report on stdout: what was timed, the single stream, the peak and the networks, then the throughput
    and the comparisons that ran."""
    _print_stream(report)
    _print_peak_and_networks(report)
    if report.get("throughput"):
        _print_throughput(report["throughput"])
    if "speedup_vs_torch" in report:
        _print_torch_comparison(report)
    if "speedup_vs_baseline" in report:
        _print_baseline_comparison(report)


def _print_stream(report: dict) -> None:
    """What was timed on what machine, and the single stream: end to end, each stage, the time between the
    networks and the work beside the depth net."""
    e = report["end_to_end_ms"]
    tta = ", PIXOR with mirror TTA (two runs a frame)" if report.get("mirror_tta") else ""
    distinct = (f" ({report['distinct_frames']} distinct, cycled)" if report["distinct_frames"] < report["frames"]
                else "")
    print(f"{report['models']}: preset {report['preset']}{tta}, {report['precision']}, {report['input']}; "
          f"{report['frames']} frames{distinct} after {report['warmup']} warm-up, score threshold "
          f"{report['score_threshold']:g}, "
          f"{cpu_label(report['machine'])} ({report['machine']['cores']} cores; {' '.join(report['machine']['cpu_flags'])}"
          f"{_governor_and_load(report['machine'])}), {report['provider']}")
    # Up to 101 frames p99 is an interpolation between the two slowest (tail_note): say how many there were.
    print(f"end to end (Detector.detect on frames in memory: no file reading, decoding or line emulation): mean "
          f"{e['mean']:.1f} ms, p50 {e['p50']:.1f}, p90 {e['p90']:.1f}, p99 {e['p99']:.1f}, max {e['max']:.1f} (of "
          f"{e['n']} frames{tail_note(e['n'])}) → {report['fps']:.2f} fps (1000 / mean; {report['fps_wall']:.2f} "
          "frames over the loop's wall time)")
    for stage, s in report["stages_ms"].items():
        print(f"  {stage:14s} mean {s['mean']:8.2f}  p50 {s['p50']:8.2f}  p99 {s['p99']:8.2f} ms")
    between = f"between the networks: {100 * report['non_network_fraction']:.1f} % of end to end"
    if report["ray_tables_on_path_ms"] > 0.05:
        between += (f" ({100 * report['non_network_fraction_fixed_calibration']:.1f} % without building ray tables,"
                    " which a fixed calibration does once: these frames do not share one)")
    print(between)
    if report.get("overlapped_ms"):
        beside = ", ".join(f"{stage} {s['p50']:.2f} ms" for stage, s in report["overlapped_ms"].items())
        print(f"  on the stage thread beside the depth net (p50; on the frame's path only as waited for): {beside}")


def _print_peak_and_networks(report: dict) -> None:
    """The CPU's peak and each network's FLOPs, time and share of it (``--ops``: its operators too)."""
    size = report["peak_detail"]["matmul_size"]
    readings = ", ".join(f"{r['matmul_gflops']:.0f} / {r['conv3x3_256_gflops']:.0f}"
                         for r in report["peak_detail"]["readings"])
    print(f"peak on the CPU (best of the {size}² MatMul {report['peak_detail'][f'matmul_{size}_gflops']:.0f} and 3×3 conv "
          f"{report['peak_detail']['conv3x3_256_gflops']:.0f} GFLOP/s, the best of the readings before and after the "
          f"stream: {readings}): {report['peak_gflops']:.0f} GFLOP/s")
    for name, n in report["networks"].items():
        flops = f"2 × {n['gflops'] / 2:.2f}" if n["runs"] == 2 else f"{n['gflops']:.2f}"
        share = ("no share of the CPU's peak (the networks ran on another provider)" if n["peak_fraction"] is None
                 else f"{100 * n['peak_fraction']:.0f} % of peak ({100 * n['matmul_peak_fraction']:.0f} % of the MatMul's)")
        graph = (f" (the graph that runs, lowered, multiplies {n['graph_gflops']:.2f})"
                 if abs(n["graph_gflops"] - n["gflops"]) > 0.005 * n["gflops"] else "")
        print(f"  {name:6s} {flops} GFLOP{graph} in {n['ms']:.1f} ms (p50) = {n['achieved_gflops_per_s']:.0f} GFLOP/s, "
              f"{share}")
    for name, n in report["networks"].items():
        if "ops" in n:
            print(describe_ops(name, n["ops"]))


def _print_throughput(t: dict) -> None:
    """The throughput workers against one worker and against the single stream (the report's ``throughput``)."""
    per_round = ", ".join(f"{r:.2f}" for r in t["scaling_per_round"])
    shares = [u["cpu_share"] for run in t["runs"] for u in run["per_worker"] if u["cpu_share"] is not None]
    got = f"; the workers got {100 * min(shares):.0f}–{100 * max(shares):.0f} % of their cores" if shares else ""
    print(f"{t['workers']} {t['mode']} workers, {t['cores_per_worker']} core(s) each: {t['fps']:.2f} fps vs one "
          f"worker on one share {t['fps_one_worker']:.2f} fps → scaling {t['scaling']:.2f}× (medians of "
          f"{t['rounds']} alternating rounds; per round {per_round}{got}); against the single stream on every "
          f"core {t['vs_single_stream']:.2f}×")
    cpu = t.get("cpu_ms_per_frame")
    if cpu:
        print(f"  a frame's CPU time: {cpu['one_worker']:.1f} ms with one worker, {cpu['all_workers']:.1f} ms with "
              f"{t['workers']} ({cpu['ratio']:.2f}×; with the workers on their full cores, scaling ≈ "
              f"{t['workers']} / that: above 1, the cores slowed each other down)")


def _print_torch_comparison(report: dict) -> None:
    """``--compare-torch``: PyTorch eager against ONNX Runtime, end to end and the networks alone."""
    b = report["speedup_vs_torch_blocks"]
    print(f"PyTorch eager: mean {report['torch_end_to_end_ms']['mean']:.1f} ms vs ONNX Runtime "
          f"{report['paired_end_to_end_ms']['mean']:.1f} ms in alternating blocks → ONNX Runtime "
          f"{report['speedup_vs_torch']:.2f}× faster (the median block; {b['min']:.2f}–{b['max']:.2f}× over "
          f"{b['blocks']} blocks; the means' ratio {report['speedup_vs_torch_of_means']:.2f}×)")
    nets = ", ".join(f"{stage} {report['torch_stages_ms'][stage]['p50']:.1f} vs "
                     f"{report['paired_stages_ms'][stage]['p50']:.1f} ms ({ratio:.2f}×)"
                     for stage, ratio in report["speedup_vs_torch_networks"].items())
    print(f"  networks alone (p50): {nets}; PyTorch weights: {report['torch_weights']}")


def _print_baseline_comparison(report: dict) -> None:
    """``--baseline``: the baseline directory against the one timed, end to end and each network."""
    base, b = report["baseline"], report["speedup_vs_baseline_blocks"]
    nets = "".join(f", {stage} {base['stages_ms'][stage]['p50']:.1f} → {base['paired_stages_ms'][stage]['p50']:.1f} ms"
                   for stage in NETWORK_STAGES if stage in base["stages_ms"])
    print(f"baseline {base['models']} ({base['precision']}): mean {base['end_to_end_ms']['mean']:.1f} ms vs "
          f"{base['paired_end_to_end_ms']['mean']:.1f} ms in alternating blocks → "
          f"{report['speedup_vs_baseline']:.2f}× faster (the median block; {b['min']:.2f}–{b['max']:.2f}× over "
          f"{b['blocks']} blocks; the means' ratio {report['speedup_vs_baseline_of_means']:.2f}×){nets} (p50)")


@quiet_interrupt("no report was written (--json and --plot are written at the end)")
def main(argv: list[str] | None = None) -> int:
    """The command: check the arguments, measure, print the report, write --json and --plot; 2 on an error."""
    args = _parser().parse_args(argv)
    try:
        _check_args(args)
        report = run(args.preset, args.models, args.provider, args.threads, args.frames, args.warmup, args.data,
                     args.beams, args.compare_torch, args.checkpoints, precision=args.precision,
                     baseline=args.baseline, worker_kind=args.worker_kind, peak_size=args.peak_size, ops=args.ops,
                     stage_threads=args.stage_threads, mirror_tta=args.mirror_tta,
                     score_threshold=args.score_threshold, device_ids=args.device_ids)
    except (InputError, ModelFileError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except TorchMissing as exc:  # the runtime install: one line, as the other commands that need torch
        print(f"{TORCH_MISSING}; {exc}", file=sys.stderr)
        return 2
    print_report(report)
    try:  # the JSON first: it is the report; a picture that fails must not lose it
        if args.json:
            write_text_file(args.json, json.dumps({k: v for k, v in report.items() if k != "_samples"}, indent=2))
        if args.plot:
            plot(report, args.plot)
            print(f"plot: {args.plot}")
    except OSError as exc:
        print(f"error: cannot write {exc.filename or ''} ({exc.strerror or exc})", file=sys.stderr)
        return 2
    return 0


def _parser() -> argparse.ArgumentParser:
    """The command's arguments (its --help)."""
    epilog = __doc__.split("\n\n", 1)[1] + "\n" + examples(
        "python benchmarks/latency.py --threads 2 --json outputs/latency.json --plot outputs/latency.png")
    parser = argparse.ArgumentParser(allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
                                     prog="python benchmarks/latency.py", description=__doc__.split("\n\n")[0],
                                     formatter_class=HelpFormatter, epilog=epilog)
    parser.add_argument("--preset", metavar="P", help=f"export this preset (with initialised weights, or --checkpoints) and time it "
                                          f"instead of the shipped model (default {DEFAULT_PRESET}, the shipped "
                                          "model's; needs PyTorch); with --models it must be the directory's")
    parser.add_argument("--models", type=Path, metavar="DIR",
                        help=f"model directory (default: the shipped {SHIPPED.relative_to(ROOT)}, as the README's "
                             f"figures were timed, or {SHIPPED_INT8.relative_to(ROOT)} with --precision int8; "
                             "--preset or --checkpoints export instead)")
    parser.add_argument("--provider", choices=["cpu", "cuda", "tensorrt"], help="execution provider (default: best)")
    parser.add_argument("--precision", choices=["fp32", "fp16", "int8"],
                        help="with --models: check the directory is this precision; without: the shipped INT8 "
                             "directory for int8, else convert (INT8 with 7-bit weights, as the shipped one)")
    parser.add_argument("--threads", type=positive_int, default=1, metavar="N",
                        help="throughput workers (default 1: no throughput run): N detectors, each pinned to its own "
                             "share of the cores, at most one per usable core; not ONNX Runtime's intra-op threads "
                             "(--threads of op_profile.py and peak.py), which here are a worker's share of the cores")
    parser.add_argument("--device-ids", type=gpu_ids, metavar="IDS",
                        help="GPUs for --provider cuda or tensorrt, e.g. 0,1: the single stream runs on the first, "
                        "throughput worker i on the i-th (in turn when fewer), as the paper ran the PX2's two GPUs "
                        "as two threads (default: every worker on GPU 0)")
    # Not --workers: every other command (service, load test, training, simulation) counts with that name.
    parser.add_argument("--worker-kind", choices=["thread", "process"], default="thread",
                        help="what a throughput worker is: a thread of this process (default, as the paper ran "
                             "two GPUs) or a process of its own (no interpreter lock shared)")
    parser.add_argument("--frames", type=positive_int, default=20, metavar="N", help="timed frames (default 20)")
    parser.add_argument("--warmup", type=non_negative_int, default=3, metavar="N",
                        help="untimed warm-up frames (default 3)")
    parser.add_argument("--data", type=Path, default=BUNDLED, metavar="DIR",
                        help="KITTI-layout folder (default: the bundled frames)")
    # --beams: its old spelling, kept for scripts (a hidden alias).
    parser.add_argument("--emulate-beams", "--beams", dest="beams", type=int, choices=(0, *BEAM_COUNTS), metavar="N",
                        help="thin scans to N lines before timing (16, 32, 8, 4; 0: keep as stored); default: the "
                        "model's own line count (16; a 64-line LiDAR-only model's scans kept as stored)")
    parser.add_argument("--compare-torch", action="store_true", help="also time the PyTorch eager pipeline, in blocks alternating with ONNX Runtime")
    parser.add_argument("--checkpoints", type=Path, metavar="DIR",
                        help="checkpoints for --compare-torch with trained --models")
    parser.add_argument("--baseline", type=Path, metavar="DIR",
                        help="another model directory to time in blocks alternating with --models, for the ratio")
    parser.add_argument("--peak-size", type=positive_int, default=PEAK_MATMUL, metavar="N",
                        help=f"size of the MatMul in the peak micro-benchmark (default {PEAK_MATMUL}, as every "
                        "figure quoted; a smaller one takes less than a second and reads lower)")
    parser.add_argument("--ops", action="store_true",
                        help="also time each network operator by operator with ONNX Runtime's profiler "
                        "(20 runs on a real frame's inputs): where its time goes, and the convolutions' own GFLOP/s")
    parser.add_argument("--stage-threads", type=int, choices=(1, 2),
                        help="the single stream's threads for the stages between the networks: 2 runs those that "
                        "need no depth beside the depth net, 1 runs all in turn (default: 2 on two or more cores)")
    parser.add_argument("--mirror-tta", action="store_true",
                        help="PIXOR also on the BEV mirrored left to right, maps averaged, as pipeline.detect "
                        "--mirror-tta and the service's --mirror-tta: PIXOR's time twice over")
    parser.add_argument("--score-threshold", type=probability, metavar="SCORE",
                        help="keep detections from this score, in every Detector timed (default: the model's, 0.5 "
                        "for the shipped ones; the evaluation's 0.05 keeps 500 candidates for NMS: a slower decoding)")
    parser.add_argument("--json", type=Path, metavar="FILE", help="write the report as JSON")
    parser.add_argument("--plot", type=Path, metavar="FILE", help="write the latency distribution per stage (box plots, log-scaled ms) as a picture: .png, .jpg, .pdf or .svg by the name (needs matplotlib)")
    return parser


def _check_args(args: argparse.Namespace) -> None:
    """InputError (ValueError for a misspelt preset) for arguments refused before anything is exported or timed."""
    # Checked first: a report that cannot be written is lost after minutes of timing.
    if args.json is not None:
        check_output(args.json, "--json")
    if args.plot is not None:
        check_figure(args.plot, "--plot")
    read = {"--models": args.models or (SHIPPED if args.preset is None else None), "--baseline": args.baseline, "--checkpoints": args.checkpoints,
            "--data": args.data}
    for path, flag in ((args.json, "--json"), (args.plot, "--plot")):
        if path is not None:  # a report named as a manifest or a frame's file would replace it
            check_not_input(path, flag, read)
    if args.models is None and args.preset is not None:
        _named_preset(args.preset)  # the exporter's word on a misspelt preset, before anything is exported
    if args.device_ids and args.provider not in ("cuda", "tensorrt"):
        # Refused before minutes of timing; without --provider the best available might be the CPU anyway.
        raise InputError(f"--device-ids {','.join(map(str, args.device_ids))}: GPU ids need --provider cuda "
                         "or tensorrt")
    if args.provider in ("cuda", "tensorrt") and args.warmup == 0:
        # A GPU's first run builds its kernels (TensorRT its engine, for minutes): timed, it is the mean.
        raise InputError(f"--warmup 0: with --provider {args.provider} the first frames build the GPU's kernels "
                         "(TensorRT's engine takes minutes); give --warmup 1 or more")


if __name__ == "__main__":
    sys.exit(main())
