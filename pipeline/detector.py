"""The ONNX Runtime two-stage detector: image + sparse scan + calibration → 3D car boxes.

Stages (each timed): ``emulate_beams`` (only when asked to thin a 64-line scan) →
``prepare`` (depth-net view and sparse depth) → ``depth_net`` (depth.onnx) →
``ray_table`` (the view's rays in BEV bins, once per calibration) →
``pseudo_points`` (back-projection, straight to BEV bins) → ``voxelize`` (BEV
tensor of pseudo + real points) → ``pixor`` (pixor.onnx; with mirror TTA also
``pixor_mirror`` and ``mirror_merge``) → ``decode`` (candidates, rotated NMS, z and
h; heights skip the pseudo points smeared across depth edges). A model directory
whose manifest lists no depth network is a LiDAR-only PIXOR: it skips the
stages from ``prepare`` to ``pseudo_points``.

With two or more cores for a frame (``stage_threads``), the work that needs
no depth runs on a second thread while the depth net runs: the calibration's
rays, the real points' half of the voxelization and the frame's sensor and rig
checks (:meth:`Detector.frame_checks`). Those stages are then
timed as the frame waited for them (about nothing), and what they took on
their thread is in ``Detections.overlapped_ms``.

One Detector may be called from several threads at once: ONNX Runtime
sessions are thread-safe and each thread gets its own BEV buffer (and stage thread).
Another thread may stop a frame it no longer wants (its deadline passed, the
service is shutting down) through a :class:`Cancellation`.
"""

from __future__ import annotations

import ctypes
import logging
import threading
import time
import weakref
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import onnxruntime as ort

from pipeline.beams import BEAM_COUNTS, emulate_beams
from pipeline.bev import BevVoxelizer, PseudoBins, pseudo_bins
from pipeline.boxes import BoxRecord, box_records, boxes_to_objects, in_camera_view
from pipeline.calib import KITTI_CALIBRATION, KITTI_IMAGE_HW, Calibration, check_calibration
from pipeline.checks import (
    CodedWarning,
    WarningCode,
    beam_pattern_mismatch,
    blocked_sector_fault,
    byte_order_hint,
    calibration_mismatch,
    check_image,
    check_options,
    coded,
    image_hw_of,
    reflectance_mismatch,
    road_level_mismatch,
    scan_misses_image,
    stuck_range_fault,
    thin_scan_fault,
    view_mismatch,
)
from pipeline.cpu import int8_pairs_saturate, usable_cpus
from pipeline.errors import InputError
from pipeline.graph_inputs import session_feeds, whole_shapes
from pipeline.kitti import Object3D
from pipeline.model_files import (
    ModelFileError,
    check_descriptions,
    load_manifest,
    read_verified,
    verify_sha256,
)
from pipeline.onnx_wire import WireError, external_tensors
from pipeline.postprocess import boxes_from_maps
from pipeline.preprocess import DepthInputs, depth_inputs, depth_view, view_calibration
from pipeline.presets import Preset, preset_from_dict
from pipeline.pseudo import bin_rays, depth_to_points, merge_points

log = logging.getLogger(__name__)

PROVIDER_PREFERENCE = ("TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider")
PROVIDER_ALIASES = {
    "tensorrt": "TensorrtExecutionProvider",
    "cuda": "CUDAExecutionProvider",
    "cpu": "CPUExecutionProvider",
}
GPU_PROVIDERS = ("TensorrtExecutionProvider", "CUDAExecutionProvider")  # those that take a device_id
MAX_POINTS = 2_000_000  # far beyond any real scan; protects memory from absurd inputs
# A KITTI HDL-64E scan holds about 120,000 points (the shared frames: 104,000–123,000) and its 16-line
# emulation a quarter of that, as a VLP-16's does: a count past these says the scan is not what the
# model was trained on.
SCAN_LINES_BY_INPUT = {"lidar16": 16, "pseudo": 16, "lidar64": 64}
MOST_POINTS_OF_16_LINES = 80_000
FEWEST_POINTS_OF_64_LINES = 50_000
# On KITTI about 40 % of a scan lies in the BEV grid in front of the car; a scan with almost none there
# is in other units (millimetres) or another frame, and would give no boxes without saying why.
FEWEST_IN_GRID_SHARE = 0.01
# PIXOR's regression targets (pipeline/targets.py: cos yaw, sin yaw, dx, dy, log w, log l) whose sign a
# left-right mirror of the BEV flips.
MIRRORED_TARGETS = [1, 3]
REFLECTANCE_SLACK = 1e-6  # float32 rounding of a reflectance of exactly 1 written by another tool
# The largest coordinate a scan may hold, in metres: a LiDAR's returns lie within a few hundred (a scan in
# millimetres, 1,000 times that, is still taken and gets the out-of-range warning). Beyond it a value is
# garbage, and the float32 stages (squared ranges, projections) would overflow on it: a float64 1e300 even
# became infinite in the cast to float32.
MAX_COORDINATE = 1e6
# Where ONNX Runtime looks for a graph's external data (tensors kept in another file) when the graph is given as bytes:
# by default the working directory, where no sha256 covers anything. A path under /dev/null can hold no file, so a
# graph that names one is refused, as is one naming a path outside it (ONNX Runtime's own check, from 1.24). That is
# the second line of defence; the first, refuse_external_data, reads the graph before and refuses it on every version.
NO_EXTERNAL_DATA = "/dev/null/lowres3d-loads-no-external-data"
# What each network's graph must give, by output name (float32, of the preset's shapes: Detector._check_shapes).
NETWORK_OUTPUTS = {"depth": ("depth",), "pixor": ("score", "regression")}


def refuse_external_data(path: Path, graph: bytes) -> None:
    """ModelFileError when the ONNX graph ``graph`` (the bytes of ``path``) keeps a tensor in another file, which no
    sha256 of the manifest covers, or is no protobuf message at all. Checked here, on the bytes, for every ONNX
    Runtime version and provider: see pipeline/onnx_wire.py for the versions and the TensorRT path that would load
    such a file."""
    try:
        external = external_tensors(graph)
    except WireError as exc:
        raise ModelFileError(f"{path}: not an ONNX graph ({exc})") from exc
    if external:
        first = external[0]
        where = f"'{first.location}'" if first.location else "a file it does not name"
        raise ModelFileError(f"{path}: the graph keeps tensors in another file (ONNX external data), which no sha256 "
                             f"of the manifest covers; export it with its weights inside ({len(external)} tensor(s), "
                             f"the first '{first.name}' in {where})")


def trained_lines(training: dict[str, object]) -> int | None:
    """The line count of the scans a PIXOR learned from, by its manifest's training record: 64 for ``lidar64``;
    for ``lidar16`` and ``pseudo`` the lines ``models.train --emulate-beams`` thinned them to, 16 when it took
    them as stored (0: a 16-line sensor's own scans) or did not record it (runs before the flag); None without
    a recorded input."""
    given = training.get("input")
    lines = SCAN_LINES_BY_INPUT.get(given) if isinstance(given, str) else None  # a list would not even hash
    emulated = training.get("emulate_beams")
    if lines == 16 and isinstance(emulated, int) and not isinstance(emulated, bool) and emulated in BEAM_COUNTS:
        return emulated
    return lines


class RunCancelled(Exception):
    """The frame was cancelled (:meth:`Cancellation.cancel`) before or during one of its network runs."""


class Cancellation:
    """Stops one frame's detection from another thread.

    ONNX Runtime checks its run options' terminate flag between the nodes of a graph, so a network run
    already under way ends within about one node's time rather than running to its end; a run not yet
    started does not start. The NumPy stages are not interrupted: those between the networks take a few
    milliseconds, the beam emulation before them up to about 0.5 s for a million-point scan, after which
    the flag is checked. One per frame: the flag stays set.
    """

    def __init__(self) -> None:
        self.run_options = ort.RunOptions()
        self._cancelled = threading.Event()

    def cancel(self) -> None:
        """Stop the frame at its next network node; safe from any thread, and more than once."""
        self._cancelled.set()
        self.run_options.terminate = True

    @property
    def cancelled(self) -> bool:
        return self._cancelled.is_set()


@dataclass
class Detections:
    """Boxes of one frame.

    boxes: float64 (K, 7) ``x, y, z, l, w, h, yaw`` in the LiDAR frame (x forward, y left, z up, metres):
    x, y, z the box's centre (z its middle, not its bottom: a KITTI label's location is the bottom), l along
    the heading, w across it, h up; yaw the heading in radians about +z from +x, counter-clockwise (0: along
    x, π/2: along y), in (−π, π]. :meth:`as_records` gives them by name with a quaternion. scores (K,),
    best first. timings_ms: per stage and ``total``, as the frame spent them
    one after the other. overlapped_ms: stages run on the stage thread while a
    network ran (not part of ``total``'s sum). warnings: what was dropped or
    adjusted on the way. warning_codes: each warning's stable code
    (pipeline.checks.WarningCode), same length and order, for alerting.
    points: None unless :meth:`Detector.detect` was asked to ``keep_points``; then float32 (M, 4) ``x, y, z,
    reflectance`` in the LiDAR frame, the cloud PIXOR saw: the camera's pseudo points first, then the scan's.
    pseudo_count: how many of ``points`` are pseudo points (0 without ``keep_points`` or for a LiDAR-only model).
    """

    boxes: np.ndarray
    scores: np.ndarray
    label: str = "Car"
    timings_ms: dict[str, float] = field(default_factory=dict)
    overlapped_ms: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    warning_codes: list[str] = field(default_factory=list)
    points: np.ndarray | None = field(default=None, repr=False)  # the points PIXOR saw (keep_points; for pictures)
    pseudo_count: int = 0  # how many of ``points`` are the camera's pseudo points, which come first (0: none kept)

    def add_warning(self, code: WarningCode, message: str) -> None:
        """Append a warning and its code (the two lists stay parallel)."""
        self.warnings.append(message)
        self.warning_codes.append(code)

    def to_objects(self, calib: Calibration, image_hw: tuple[int, ...]) -> list[Object3D]:
        """KITTI result objects (label_2 format with score; :func:`pipeline.kitti.format_label` writes one as a
        line) of the boxes the camera sees. image_hw: (rows, columns), or an image's ``shape``."""
        calib = check_calibration(calib, "calib")
        image_hw = image_hw_of(image_hw)
        seen = in_camera_view(self.boxes, calib, image_hw)
        return boxes_to_objects(self.boxes[seen], calib, image_hw, self.scores[seen], self.label)

    def as_records(self) -> list[BoxRecord]:
        """Each box by name, best first: centre, size, yaw, its quaternion and score (e.g. one
        ``vision_msgs/Detection3D`` each, in the LiDAR's frame)."""
        return box_records(self.boxes, self.scores, self.label)


@dataclass
class _CameraStage:
    """What the camera stage of :meth:`Detector.detect` hands on: the pseudo points in their BEV bins, the depth
    map and its view's calibration (for ``keep_points``), whether the stage thread has written the real points
    into the BEV already, what its stages took there, and the frame checks' warnings."""

    pseudo: PseudoBins
    dense: np.ndarray  # (H, W) metres in the depth net's view
    view_calib: Calibration
    points_voxelized: bool  # by the stage thread, beside the depth net
    overlapped: dict[str, float]
    warnings: list[CodedWarning]


def resolve_providers(requested: str | Sequence[str] | None = None, available: list[str] | None = None) -> list[str]:
    """Execution providers to use, best first: TensorRT → CUDA → CPU, those this ONNX Runtime build offers.

    ``requested`` may be short names (cpu, cuda, tensorrt) or ONNX Runtime names. One name of the chain
    starts the chain there (``tensorrt``: TensorRT, then CUDA for the operators TensorRT does not take, then
    CPU); a list is used as given. CPU is always appended as the last fallback. ``available``: the build's
    providers (default: this one's).
    """
    available = ort.get_available_providers() if available is None else available
    if requested:
        names = [requested] if isinstance(requested, str) else list(requested)
        chosen = []
        for name in names:
            full = PROVIDER_ALIASES.get(name.lower(), name)
            if full not in available:
                # Named as both callers give it: Detector's providers= argument and the commands' --provider.
                raise InputError(
                    f"provider {name!r} (providers=, --provider): not available in this ONNX Runtime build "
                    f"(available: {', '.join(available)})"
                )
            chosen.append(full)
        if len(chosen) == 1 and chosen[0] in PROVIDER_PREFERENCE:
            below = PROVIDER_PREFERENCE[PROVIDER_PREFERENCE.index(chosen[0]) + 1:]
            chosen += [p for p in below if p in available]
    else:
        chosen = [p for p in PROVIDER_PREFERENCE if p in available]
    if "CPUExecutionProvider" not in chosen:
        chosen.append("CPUExecutionProvider")
    return chosen


def provider_fallbacks(wanted: str, in_use: dict[str, list[str]]) -> dict[str, str]:
    """The networks whose session does not run on ``wanted`` first, with the provider it does run on.

    ONNX Runtime drops a provider whose libraries fail to load (CUDA or TensorRT missing, no GPU visible
    in a container) with a log line only, and runs the session on what is left."""
    return {name: providers[0] for name, providers in in_use.items() if providers and providers[0] != wanted}


def tensorrt_version() -> int | None:
    """The TensorRT library's version number as the library gives it (10.9.0 → 100900), None without one.

    Read from libnvinfer itself (``getInferLibVersion``), as ONNX Runtime's provider loads it: no Python
    package of TensorRT is needed, and the number is that of the library the engines are built with."""
    for name in ("libnvinfer.so.10", "libnvinfer.so.8", "libnvinfer.so"):
        try:
            library = ctypes.CDLL(name)
        except OSError:
            continue
        return int(library.getInferLibVersion())
    return None


def tensorrt_options(manifest: dict, cache_root: Path) -> dict:
    """ONNX Runtime's TensorRT provider options for a model directory with this manifest.

    Building TensorRT engines takes minutes, so they are cached (a volume in the container), in a folder
    of their own per model: named by the ONNX files' sha256s, since ONNX Runtime does not notice new
    weights under an old file name and would run the stale engine; and by the versions of ONNX Runtime
    and of the TensorRT library, since ONNX Runtime's engine names tell TensorRT releases apart by major
    and minor version only, and an engine from another patch release fails to deserialize (an image
    rebuilt with a new TENSORRT_VERSION, or a JetPack update, over a kept volume). An FP16 directory asks
    TensorRT for FP16 kernels too (its builder flag), which its fp16 tensors alone do not choose."""
    files = manifest.get("files", {})
    key = "-".join(files[name]["sha256"][:12] for name in sorted(files))
    versions = f"ort{ort.__version__}-trt{tensorrt_version() or 'none'}"
    cache = (Path(cache_root)
             / f"{manifest.get('preset', 'model')}-{manifest.get('precision', 'fp32')}-{key}-{versions}")
    try:
        cache.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"--trt-cache-dir {cache_root}: cannot create the TensorRT engine cache "
                         f"({exc.strerror or exc})") from exc
    return {"trt_engine_cache_enable": True, "trt_engine_cache_path": str(cache),
            "trt_timing_cache_enable": True, "trt_timing_cache_path": str(cache),
            "trt_fp16_enable": manifest.get("precision") == "fp16"}


def session_providers(providers: list[str], device_id: int | None = None,
                      trt_options: dict | None = None) -> list[str | tuple[str, dict]]:
    """The ``providers`` argument of an ONNX Runtime session: each provider's name, with its options where
    it has any (TensorRT's cache, a GPU's ``device_id``).

    device_id: the GPU the session runs on (None: the provider's default, GPU 0), given to TensorRT and CUDA
    alike, so that TensorRT's fallback to CUDA stays on the same GPU. An InputError when none of the providers
    runs on a GPU: a device id would be ignored without a word.
    """
    if device_id is not None:
        if device_id < 0:
            raise InputError(f"device id {device_id}: GPU ids count from 0")
        if not any(p in GPU_PROVIDERS for p in providers):
            raise InputError(f"device id {device_id}: the sessions run on {', '.join(providers)}; device ids are "
                             "for the GPU providers (--provider cuda or tensorrt)")
    entries: list[str | tuple[str, dict]] = []
    for provider in providers:
        options = dict(trt_options or {}) if provider == "TensorrtExecutionProvider" else {}
        if device_id is not None and provider in GPU_PROVIDERS:
            options["device_id"] = device_id
        entries.append((provider, options) if options else provider)
    return entries


def gpu_session_error(path: Path, provider: str, device_id: int | None, trt_options: dict | None,
                      exc: Exception) -> str:
    """The message for a session that a GPU provider failed to create, with what to check."""
    where = f"{provider} on GPU {device_id if device_id is not None else 0}"
    checks = [f"does this box have a GPU {device_id}?" if device_id is not None else "is the GPU visible (nvidia-smi)?"]
    if trt_options:  # an engine built by another TensorRT fails to deserialize
        checks.append(f"after a TensorRT or driver change, remove the engine cache {trt_options['trt_engine_cache_path']}")
    return f"{path}: ONNX Runtime could not create its session with {where} ({exc}); {'; '.join(checks)}"


def session_options(intra_op_threads: int | None = None) -> ort.SessionOptions:
    """The ONNX Runtime session options every Detector session runs with (and the benchmarks time).

    intra_op_threads: the session's thread pool size (None: ONNX Runtime's default, one per core).
    """
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    # The pool threads spin-wait for work. Inside a run that saves waking them for each operator;
    # after a run, two sessions run one after the other with NumPy stages between them, and a
    # spinning idle pool steals the cores from the stage that is working (measured here: an edge
    # frame took 69 ms instead of 43 with spinning throughout). So the threads spin within a run and
    # stop when it ends: against no spinning at all, an edge frame went 38.1 → 36.5 ms (80 frames, the
    # same code with either setting, two runs each).
    options.add_session_config_entry("session.intra_op.allow_spinning", "1")
    options.add_session_config_entry("session.force_spinning_stop", "1")
    if intra_op_threads:
        options.intra_op_num_threads = intra_op_threads
        options.inter_op_num_threads = 1
    return options


class Detector:
    """Loads a model directory (checking its sha256s) and detects cars in frames.

    Threads: each ONNX Runtime session has a pool of ``intra_op_threads`` − 1 threads (default one per core;
    they spin only inside a run), and with ``stage_threads`` 2 each thread that calls :meth:`detect` gets one
    stage thread, which ends when that thread does. :meth:`close` (or ``with Detector(...) as detector:``)
    releases the sessions and stops the stage threads at once, rather than when the last reference goes.

    What a caller catches (each a subclass of the built-in named, with a one-line message naming the file, field or
    argument at fault; anything else is a bug, not the input's fault):

    - ``pipeline.errors.InputError`` (a ValueError): a frame or option it cannot use (:meth:`detect`'s image,
      points, calib, score_threshold …), a provider this ONNX Runtime build lacks, a GPU session that cannot be made.
    - ``pipeline.model_files.ModelFileError`` (a RuntimeError), from the constructor: a model directory that is
      missing, incomplete, altered (a sha256 mismatch) or unusable (a graph ONNX Runtime cannot load).
    - ``RuntimeError`` from :meth:`detect` (and the networks' runs) after :meth:`close`: "Detector(…) was closed;
      make a new one".
    - :class:`RunCancelled` from a frame stopped through its :class:`Cancellation`.
    """

    def __init__(
        self,
        model_dir: str | Path,
        providers: str | Sequence[str] | None = None,
        intra_op_threads: int | None = None,
        verify: bool = True,
        trt_cache_dir: str | Path | None = None,
        stage_threads: int | None = None,
        mirror_tta: bool = False,
        device_id: int | None = None,
        networks_used: tuple[str, ...] = ("depth", "pixor"),
    ) -> None:
        """stage_threads: 2 runs the stages that need no depth beside the depth net, 1 runs every stage in
        turn; None: 2 when the networks may use two or more threads (``intra_op_threads`` not 1) and the
        process two or more CPUs. A worker given one core gains nothing from a second thread.

        mirror_tta: run PIXOR a second time on the BEV mirrored left to right and average the two maps
        (test-time augmentation): PIXOR's time twice over for BEV boxes that are more often right to
        IoU 0.7 (docs/models.md has the figures). Off by default: the paper's pipeline runs it once.

        device_id: the GPU both sessions run on, for CUDA and TensorRT (None: GPU 0); an InputError on the CPU
        provider. One Detector per GPU runs frames on several GPUs side by side (the service's per-worker
        sessions, latency.py's throughput workers).

        networks_used: the networks the caller runs, whose untrained weights are warned of (``models.cache_pseudo``
        runs the depth net alone; a depth-only export's initialised PIXOR is no concern of it)."""
        self.mirror_tta = bool(mirror_tta)
        self.networks_used = tuple(networks_used)
        self.model_dir = Path(model_dir)
        self.manifest = load_manifest(self.model_dir)
        graphs = self._read_graphs(verify)
        self.preset: Preset = self._manifest_preset()

        self.providers = resolve_providers(providers)
        self.device_id = device_id
        trt_options = None
        if "TensorrtExecutionProvider" in self.providers:
            trt_options = tensorrt_options(self.manifest, Path(trt_cache_dir or self.model_dir / "trt_cache"))
        entries = session_providers(self.providers, device_id, trt_options)
        options = session_options(intra_op_threads)
        networks = self._listed_networks()
        self.two_stage = "depth" in networks
        self._sessions = self._open_sessions(graphs, entries, options, trt_options, verify)

        # Input names as each graph has them: a lowered PIXOR reads its BEV in channel pieces.
        self._input_names = {name: [i.name for i in session.get_inputs()] for name, session in self._sessions.items()}
        self._check_shapes()
        # After the shapes: an edited preset_config that no longer fits the graphs is named as such first.
        check_descriptions(self.manifest, self.preset.described(), self.model_dir / "manifest.json")

        self._local = threading.local()
        self._closing = threading.Lock()  # guards the stage threads' set against close() on another thread
        # Held weakly: the only strong reference to a stage thread's executor is its calling thread's local state,
        # which goes when that thread ends; the executor is then collected, and its thread, woken by that, exits.
        # (A threading.local shuts nothing down itself: every short-lived caller, such as a thread per request,
        # left an idle stage thread behind for the Detector's life.) close() stops those still held.
        self._stage_executors: weakref.WeakSet[ThreadPoolExecutor] = weakref.WeakSet()
        self._closed = False
        self.stage_threads = self._stage_thread_count(stage_threads, intra_op_threads)

        loaded = self._load_checks(explicit=bool(providers))
        self.load_warnings: list[str] = [w.message for w in loaded]
        self.load_warning_codes: list[str] = [w.code for w in loaded]  # parallel to load_warnings
        for warning in self.load_warnings:
            log.warning(warning)
        self.trained_lines: int | None = trained_lines(networks["pixor"].get("training") or {})  # None: not recorded

    def _manifest_preset(self) -> Preset:
        """The preset the manifest carries (``preset_config``), or a ModelFileError naming the manifest."""
        try:
            return preset_from_dict(self.manifest["preset_config"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelFileError(f"{self.model_dir / 'manifest.json'}: {exc}") from exc

    def _listed_networks(self) -> dict:
        """The manifest's networks by name; a ModelFileError when it lists no PIXOR."""
        networks = self.manifest.get("networks", {})
        if "pixor" not in networks:
            raise ModelFileError(f"{self.model_dir / 'manifest.json'}: no 'pixor' network listed")
        return networks

    def _open_sessions(self, graphs: dict[str, bytes], entries: list[str | tuple[str, dict]],
                       options: ort.SessionOptions, trt_options: dict | None,
                       verify: bool) -> dict[str, ort.InferenceSession]:
        """An ONNX Runtime session for each network of the directory, by name; a ModelFileError for a graph ONNX
        Runtime cannot load, an InputError for a GPU session it cannot create."""
        networks = self.manifest["networks"]
        # CPU and CUDA get the very bytes whose sha256 was checked: no second read of a file that a copy may have
        # replaced since, and no external data (the check covers only the listed files). TensorRT gets the path,
        # as before: its engine cache is named after the model file (untested here from bytes), and the file is
        # checked again once the session holds it.
        by_path = "TensorrtExecutionProvider" in self.providers
        if not by_path:
            options.add_session_config_entry("session.model_external_initializers_file_folder_path", NO_EXTERNAL_DATA)
        sessions: dict[str, ort.InferenceSession] = {}
        for name in ("depth", "pixor") if self.two_stage else ("pixor",):
            path = self.model_dir / networks[name]["file"]
            model = str(path) if by_path else graphs[networks[name]["file"]]  # every network's file is in graphs
            sessions[name] = self._open_session(path, model, entries, options, trt_options)
        if by_path and verify:  # the file ONNX Runtime read by its path, checked again now that the session holds it
            verify_sha256(self.model_dir, {"files": {f: self.manifest["files"][f] for f in graphs}})
        return sessions

    def _open_session(self, path: Path, model: str | bytes, entries: list[str | tuple[str, dict]],
                      options: ort.SessionOptions, trt_options: dict | None) -> ort.InferenceSession:
        """One network's session on ``model`` (the graph's bytes, or with TensorRT its path), the errors named."""
        try:
            # No fallback: on an error ONNX Runtime's Python layer would retry on CUDA and the CPU without
            # the provider options (the device id, TensorRT's cache): a worker given GPU 1 would run on
            # GPU 0, a failing GPU session on the CPU, with a printout only; later, a run that fails on the
            # GPU would rebuild the session there for good. A GPU that fails says so instead.
            session = ort.InferenceSession(model, options, providers=entries, enable_fallback=0)
            # ONNX Runtime 1.22 and older (the GPU image's) drop enable_fallback=0 in __init__ and turn the
            # run-time fallback on again: turned off here too. A session they created on other providers
            # than asked for shows in providers_in_use (the provider_fallback warning).
            session.disable_fallback()
            return session
        except Exception as exc:  # ORT raises its own exception types for unreadable graphs
            reason = " ".join(str(exc).split())  # one line: some of ONNX Runtime's messages span several
            # ONNX Runtime's words when it will not read a tensor's file: refuse_external_data missed one.
            if "External data path" in reason:
                raise ModelFileError(f"{path}: the graph keeps tensors in another file (ONNX external data), "
                                     "which no sha256 of the manifest covers; export it with its weights inside "
                                     f"({reason})") from exc
            gpu = next((p for p in self.providers if p in GPU_PROVIDERS), None)
            if gpu is not None:  # the file's sha256 was checked: the likelier cause is the GPU side
                raise InputError(gpu_session_error(path, gpu, self.device_id, trt_options, exc)) from exc
            raise ModelFileError(f"{path}: ONNX Runtime cannot load it ({reason})") from exc

    @staticmethod
    def _stage_thread_count(stage_threads: int | None, intra_op_threads: int | None) -> int:
        """``stage_threads`` checked (1 or 2, else an InputError); None: 2 when the networks may use two or more
        threads and the process two or more CPUs."""
        if stage_threads is None:
            stage_threads = 2 if intra_op_threads != 1 and usable_cpus() >= 2 else 1
        if stage_threads not in (1, 2):
            raise InputError(f"stage_threads: 1 or 2, not {stage_threads}")
        return stage_threads

    def _load_checks(self, explicit: bool) -> list[CodedWarning]:
        """About the weights and the precision on this machine, logged once at load (and shown by the
        service's /v1/model); an InputError when a provider asked for by name (``explicit``) did not load."""
        fallback = self._check_provider_loaded(explicit=explicit)
        return coded((WarningCode.UNTRAINED_WEIGHTS, self._untrained()), (WarningCode.PROVIDER_FALLBACK, fallback),
                     (WarningCode.INT8_SATURATION, self._saturating_int8()),
                     (WarningCode.FP16_ON_CPU, self._fp16_on_cpu()))

    def _read_graphs(self, verify: bool) -> dict[str, bytes]:
        """The bytes of the networks' files, by file name, each read once and (``verify``) checked against its
        sha256; the manifest's other files checked too. Every file in the manifest's order, as verify_sha256 did."""
        networks = self.manifest.get("networks", {})
        wanted = {networks[name]["file"] for name in ("depth", "pixor") if name in networks}
        graphs: dict[str, bytes] = {}
        for file, entry in self.manifest["files"].items():
            if file in wanted:
                graphs[file] = read_verified(self.model_dir, self.manifest, file, check=verify)
                refuse_external_data(self.model_dir / file, graphs[file])
            elif verify:
                verify_sha256(self.model_dir, {"files": {file: entry}})
        return graphs

    def _check_shapes(self) -> None:
        """The manifest's preset gives the input shapes the graphs were exported with (a hand-edited preset
        would otherwise fail at the first frame, inside ONNX Runtime), and the outputs the runtime reads: each
        network's by name, float32, of the preset's shapes (a graph that gives another shape or type, or names its
        outputs otherwise, loaded and failed at the first frame: in the service, after it had started)."""
        manifest = self.model_dir / "manifest.json"
        try:
            bev = (1, *self.preset.bev.shape)
            height, width = self.preset.depth.input_hw
            crop_h, crop_w = self.preset.crop_hw
            stride = self.preset.pixor.output_stride
            maps = (self.preset.bev.ny // stride, self.preset.bev.nx // stride)
        except (ArithmeticError, TypeError, ValueError) as exc:
            raise ModelFileError(f"{manifest}: preset_config: not a usable grid or input size ({exc})") from exc
        if min(bev) <= 0 or min(height, width, crop_h, crop_w) <= 0:
            raise ModelFileError(f"{manifest}: preset_config: empty BEV grid {bev[1:]} or input "
                                 f"{height}×{width} / crop {crop_h}×{crop_w}")
        files = {name: entry["file"] for name, entry in self.manifest["networks"].items()}
        expected = {"pixor": {"bev": bev}, "depth": {"rgb": (1, 3, height, width), "sparse_depth": (1, 1, height, width)}}
        for name, session in self._sessions.items():
            path = self.model_dir / files[name]
            try:  # a graph may read an input in channel pieces that tile it (export/rewrite.py, 8)
                shapes = whole_shapes({i.name: tuple(i.shape) for i in session.get_inputs()})
            except ValueError as exc:
                raise ModelFileError(f"{path}: {exc}") from exc
            for input_name, shape in shapes.items():
                want = expected[name].get(input_name)
                if want is None:
                    raise ModelFileError(f"{path}: unknown input '{input_name}' (a {name} network takes "
                                         f"{', '.join(expected[name])})")
                if shape != want:
                    raise ModelFileError(f"{manifest}: preset_config gives {name} input '{input_name}' the "
                                         f"shape {list(want)}, but {path} expects {list(shape)}")
            for graph_input in session.get_inputs():
                if graph_input.type != "tensor(float)":
                    raise ModelFileError(f"{path}: input '{graph_input.name}' is a {graph_input.type}, where the "
                                         "runtime feeds tensor(float)")
            given = {output.name: output for output in session.get_outputs()}
            outputs = {"depth": (1, 1, height, width), "score": (1, 1, *maps), "regression": (1, 6, *maps)}
            for output_name in NETWORK_OUTPUTS[name]:
                output = given.get(output_name)
                if output is None:
                    raise ModelFileError(f"{path}: no output '{output_name}' (a {name} network gives "
                                         f"{', '.join(NETWORK_OUTPUTS[name])}; this graph: {', '.join(given)})")
                if output.type != "tensor(float)":
                    raise ModelFileError(f"{path}: output '{output_name}' is a {output.type}, where the runtime "
                                         "reads tensor(float)")
                if tuple(output.shape) != outputs[output_name]:
                    raise ModelFileError(f"{manifest}: preset_config gives {name} output '{output_name}' the shape "
                                         f"{list(outputs[output_name])}, but {path} gives {list(output.shape)}")

    def _check_provider_loaded(self, explicit: bool) -> str | None:
        """A provider asked for by name must really run the networks: otherwise an InputError naming
        ``--provider``. When it was only the best one offered, a warning (the networks run on the next)."""
        wanted = self.providers[0]
        fallen = provider_fallbacks(wanted, self.providers_in_use)
        if not fallen:
            return None
        where = ", ".join(f"{name} on {provider}" for name, provider in fallen.items())
        message = (f"{wanted} is offered by this ONNX Runtime build but did not load ({where}): its libraries "
                   "or the GPU are missing (in a container: --gpus all or --runtime nvidia; docs/deploy.md)")
        if explicit:
            raise InputError(f"--provider: {message}")
        return message

    def _untrained(self) -> str | None:
        """A warning when a network was exported without trained weights (``python -m export`` without its
        checkpoint, as for latency measurements): it runs, and its boxes mean nothing."""
        untrained = [name for name, entry in self.manifest["networks"].items()
                     if entry.get("weights") != "trained" and name in self.networks_used]
        if not untrained:
            return None
        outputs = "detections" if "pixor" in self.networks_used else "depth maps"
        return (f"{self.model_dir}: {' and '.join(untrained)} {'has' if len(untrained) == 1 else 'have'} initialised "
                f"(untrained) weights: the {outputs} mean nothing; export trained checkpoints "
                "(python -m export --checkpoints DIR)")

    def _saturating_int8(self) -> str | None:
        """A warning when full-range INT8 weights run on a CPU whose int8 kernels saturate (pipeline/cpu.py)."""
        info = self.manifest.get("precision_info") or {}
        if self.manifest.get("precision") != "int8" or info.get("reduce_range") or not int8_pairs_saturate():
            return None
        return (f"{self.model_dir}: INT8 weights in the full 8-bit range on an x86 CPU without VNNI, where ONNX "
                "Runtime's uint8 × int8 sums can saturate and change the outputs; convert with "
                "`python -m export.precision --reduce-range` for this CPU")

    def _fp16_on_cpu(self) -> str | None:
        """A warning when an FP16 directory ended up on the CPU provider (a GPU precision: slower than fp32 there)."""
        if self.manifest.get("precision") != "fp16":
            return None
        on_cpu = sorted(name for name, providers in self.providers_in_use.items() if providers[0] == "CPUExecutionProvider")
        if not on_cpu:
            return None
        # Measured on an AMD EPYC Zen 3 (session 14): the edge FP16 pair ran 1.32× slower than fp32.
        return (f"{self.model_dir}: FP16 networks ({', '.join(on_cpu)}) run on the CPU provider, where ONNX Runtime "
                "is slower in FP16 than in FP32; FP16 is for GPUs (use the FP32 or INT8 directory on a CPU)")

    # ------------------------------------------------------------------ info
    @property
    def providers_in_use(self) -> dict[str, list[str]]:
        """The providers each session actually runs on (after ONNX Runtime's own fallback)."""
        return {name: session.get_providers() for name, session in self._sessions.items()}

    @property
    def sha256(self) -> dict[str, str]:
        return {name: entry["sha256"] for name, entry in self.manifest["files"].items()}

    def _voxelizer(self) -> BevVoxelizer:
        voxelizer = getattr(self._local, "voxelizer", None)
        if voxelizer is None:
            voxelizer = self._local.voxelizer = BevVoxelizer(self.preset.bev, prefault=True)
        return voxelizer

    def _stage_thread(self) -> ThreadPoolExecutor:
        """The calling thread's stage thread (one each, like the BEV buffer its work writes; both go when the
        calling thread ends)."""
        executor = getattr(self._local, "stage_thread", None)
        if executor is None:
            with self._closing:  # close() must see every stage thread, made on whichever thread called detect
                self._check_open()
                executor = ThreadPoolExecutor(1, thread_name_prefix="lowres3d-stages")
                self._stage_executors.add(executor)
            self._local.stage_thread = executor
        return executor

    def _beside(self, voxelizer: BevVoxelizer, points: np.ndarray, view_calib: Calibration,
                image_hw: tuple[int, int], calib: Calibration) -> Future:
        """:meth:`_without_depth` submitted to the calling thread's stage thread."""
        executor = self._stage_thread()
        try:
            return executor.submit(self._without_depth, voxelizer, points, view_calib, image_hw, calib)
        except RuntimeError:
            # close() on another thread since this frame began has shut the executor down: say that, not the
            # executor's "cannot schedule new futures after shutdown".
            if self._closed:
                raise self._closed_error() from None
            raise

    # ------------------------------------------------------------------ lifecycle
    def close(self) -> None:
        """Release the ONNX Runtime sessions (and their thread pools) and stop every stage thread; safe to
        call twice. For a node that rebuilds its Detector (a parameter change): without it they go only when
        the last reference to the Detector does. Call it after the frames in flight: their stage work ends
        first, a later network run raises RuntimeError, as :meth:`detect` does from then on."""
        with self._closing:
            self._closed = True
            executors, self._stage_executors = list(self._stage_executors), weakref.WeakSet()
            self._sessions = {}  # a run in flight holds its own reference to its session
        for executor in executors:
            executor.shutdown(wait=True)

    def __enter__(self) -> Detector:  # noqa: PYI034 (typing.Self is Python 3.11; the Jetson image runs 3.10)
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def _check_open(self) -> None:
        if self._closed:
            raise self._closed_error()

    def _closed_error(self) -> RuntimeError:
        return RuntimeError(f"Detector({str(self.model_dir)!r}) was closed; make a new one")

    def _ray_table(self, view_calib: Calibration) -> None:
        """The view's rays in BEV bin units, built on a calibration's first frame and cached (pipeline/pseudo.py)."""
        height, width = self.preset.depth.input_hw  # the depth map's size, given or from the net
        bin_rays(view_calib, height, width, self.preset.pseudo_limits[2], self.preset.bev)

    def rig_mismatches(self, points: np.ndarray, image_hw: tuple[int, int] | None = None,
                       view_calib: Calibration | None = None) -> list[CodedWarning]:
        """Warnings, with their codes, for a rig unlike the training one (README, "Your own vehicle"): the scan's
        beams' elevations, the road's height and the reflectance's scale, and with ``view_calib`` (the camera
        pipeline) a depth-net crop that lies below the cars ahead. Such a frame still gets boxes, fewer and worse."""
        decode = self.preset.decode
        return coded((WarningCode.BEAM_PATTERN, beam_pattern_mismatch(points)),
                     (WarningCode.ROAD_LEVEL, road_level_mismatch(points, decode.ground_z)),
                     (WarningCode.REFLECTANCE_SCALE, reflectance_mismatch(points)),
                     (WarningCode.CAMERA_VIEW, self._view_mismatch(image_hw, view_calib)))

    def _view_mismatch(self, image_hw: tuple[int, int] | None, view_calib: Calibration | None) -> str | None:
        """:func:`view_mismatch` for the camera pipeline (None without a view)."""
        if view_calib is None or image_hw is None:
            return None
        decode = self.preset.decode
        return view_mismatch(image_hw, view_calib, self.preset.crop_hw, decode.ground_z, decode.car_height,
                             self.preset.depth.max_depth)

    def frame_checks(self, points: np.ndarray, image_hw: tuple[int, int] | None = None,
                     view_calib: Calibration | None = None, calib: Calibration | None = None) -> list[CodedWarning]:
        """The warnings, with their codes, :meth:`detect` gives a frame from its scan and view (all but the
        voxelizer's counts): with ``calib`` and ``image_hw`` (the camera pipeline), a scan whose returns ahead
        (almost) all miss the image (a LiDAR→camera transform in another frame, direction or unit); a LiDAR
        failing at run time (README, "Sensor faults": a scan stuck at one range, a blocked sector), then the rig's
        mismatches (:meth:`rig_mismatches`). On the stage thread where there is one."""
        stuck = stuck_range_fault(points)
        if stuck:  # a scan at one range has no beams, road or reflectance to compare: the rig's checks would misname it
            return coded((WarningCode.STUCK_RANGE, stuck),
                         (WarningCode.CAMERA_VIEW, self._view_mismatch(image_hw, view_calib)))
        misses = scan_misses_image(points, calib, image_hw) if calib is not None and image_hw is not None else None
        return [*coded((WarningCode.CALIBRATION_MISFIT, misses),
                       (WarningCode.BLOCKED_SECTOR, blocked_sector_fault(points))),
                *self.rig_mismatches(points, image_hw, view_calib)]

    def _without_depth(self, voxelizer: BevVoxelizer, points: np.ndarray, view_calib: Calibration,
                       image_hw: tuple[int, int], calib: Calibration) -> tuple[dict[str, float], list[CodedWarning]]:
        """The stages of a frame that need no depth: the view's rays (built once per calibration), the real
        points' half of the voxelization and :meth:`frame_checks` (timed as ``rig_checks``). Returns what each took,
        and the checks' warnings."""
        timings = {}
        tic = time.perf_counter()
        self._ray_table(view_calib)
        timings["ray_table"] = (time.perf_counter() - tic) * 1e3
        tic = time.perf_counter()
        voxelizer.add_points(points)
        timings["voxelize"] = (time.perf_counter() - tic) * 1e3
        tic = time.perf_counter()
        warnings = self.frame_checks(points, image_hw, view_calib, calib)
        timings["rig_checks"] = (time.perf_counter() - tic) * 1e3
        return timings, warnings

    # ------------------------------------------------------------------ stages
    def dense_depth(self, image: np.ndarray, points: np.ndarray, calib: Calibration) -> tuple[np.ndarray, Calibration]:
        """Depth completion alone: (H, W) metres in the network's view, and that view's calibration."""
        image, calib = check_image(image), check_calibration(calib, "calib")
        inputs = depth_inputs(image, points, calib, self.preset)
        return self.run_depth_net(inputs.rgb, inputs.sparse_depth), inputs.calib

    def run_depth_net(self, rgb: np.ndarray, sparse_depth: np.ndarray) -> np.ndarray:
        """depth.onnx on prepared inputs (1, 3, H, W) and (1, 1, H, W) → (H, W) metres."""
        if not self.two_stage:
            raise InputError("models: this model directory has no depth network (LiDAR-only PIXOR)")
        (depth,) = self._run("depth", ["depth"], {"rgb": rgb, "sparse_depth": sparse_depth})
        return depth[0, 0]

    def run_pixor(self, bev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """pixor.onnx on a whole BEV tensor (1, C, H, W) → its raw maps: score (1, 1, h, w) in [0, 1] and the
        normalised regression (1, 6, h, w), before any decoding."""
        score, regression = self._run("pixor", ["score", "regression"], {"bev": bev})
        return score, regression

    def network_inputs(self, image: np.ndarray | None, points: np.ndarray, calib: Calibration | None,
                       emulate_to_beams: int | None = None) -> dict[str, dict[str, np.ndarray]]:
        """Each network's whole input tensors for one frame: copies of exactly what :meth:`detect` feeds it.

        For what needs the real distribution, such as INT8 calibration and operator profiles: on the split
        grid the pseudo points fill BEV channels of their own, which a BEV voxelized from the merged cloud
        leaves empty."""
        self._local.recorded = {}
        try:
            self.detect(image, points, calib, emulate_to_beams=emulate_to_beams)
            return self._local.recorded
        finally:
            self._local.recorded = None

    def _run(self, network: str, outputs: list[str], arrays: dict[str, np.ndarray],
             cancel: Cancellation | None = None) -> list[np.ndarray]:
        """One network on whole input tensors, fed as the graph takes them (pipeline/graph_inputs.py).

        RunCancelled when ``cancel`` stops it (ONNX Runtime's own error for it is a generic failure)."""
        recorded = getattr(self._local, "recorded", None)
        if recorded is not None:  # network_inputs: copies, as the voxelizer reuses its buffer; mirror TTA's 2nd run not
            recorded.setdefault(network, {name: np.array(array, copy=True) for name, array in arrays.items()})
        feeds = session_feeds(self._input_names[network], arrays)
        session = self._sessions.get(network)
        if session is None:  # every network of the directory is loaded: only close() removes them
            raise self._closed_error()
        if cancel is None:
            return session.run(outputs, feeds)
        try:
            return session.run(outputs, feeds, cancel.run_options)
        except Exception:
            if cancel.cancelled:
                raise RunCancelled(f"the frame was cancelled in or before its {network} network run") from None
            raise

    def detect(
        self,
        image: np.ndarray | None,
        points: np.ndarray,
        calib: Calibration | None,
        score_threshold: float | None = None,
        emulate_to_beams: int | None = None,
        keep_points: bool = False,
        depth: np.ndarray | None = None,
        cancel: Cancellation | None = None,
    ) -> Detections:
        """Detect cars in one frame.

        image: uint8 RGB (H, W, 3), required for a two-stage model. points:
        (N, 4) ``x, y, z, reflectance`` in the LiDAR frame, finite, reflectance in [0, 1]; any real dtype
        (float64, integers: cast to float32), strided or read-only arrays taken as they are. calib: required for
        a two-stage model; a warning (``calibration_misfit``) when its principal point does not fit the image's
        size, or when (almost) none of the scan's returns ahead project into the image. score_threshold: in
        [0, 1] (None: the model's default).
        emulate_to_beams: thin a 64-line scan to 32, 16, 8 or 4 lines first (None or 0: the scan as given).
        keep_points: also return the point cloud PIXOR saw (pseudo + real),
        for pictures; otherwise the pseudo points go from the depth map
        straight to their BEV bins and are never built. depth: a dense depth
        map of the whole image (H, W, metres, 0 = none) from another source
        (stereo, or ground truth for an upper bound), used instead of the
        depth network; a two-stage model only. cancel: another thread's way
        to stop the frame (RunCancelled).
        """
        timings: dict[str, float] = {}
        warnings: list[CodedWarning] = []  # split into Detections' two parallel lists at the end
        start = time.perf_counter()  # ``total`` counts from here, the checks of the inputs included
        image, points, calib = self._checked_frame(image, points, calib, score_threshold, emulate_to_beams)
        if image is not None and calib is not None:
            warnings += coded((WarningCode.CALIBRATION_MISFIT, calibration_mismatch(image.shape[:2], calib)))
        if emulate_to_beams:  # None or 0: the scan as given
            points, emulated = self._emulate_beams(points, emulate_to_beams, timings, cancel)
            warnings.append(emulated)
        mismatch = self._line_count_mismatch(points.shape[0])
        warnings += coded((WarningCode.LINE_COUNT, mismatch))

        voxelizer = self._voxelizer()
        camera: _CameraStage | None = None  # a LiDAR-only model's: no pseudo points
        if self.two_stage:
            camera = self._camera_stage(image, points, calib, depth, voxelizer, timings, cancel)
            warnings += camera.warnings
        elif depth is not None:
            raise InputError("depth: this model has no depth network to replace (a LiDAR-only model directory)")
        else:
            warnings += self.frame_checks(points)

        bev = self._voxelize(voxelizer, points, camera, timings)
        warnings += self._grid_warnings(voxelizer, points.shape[0], mismatch)
        score, regression = self._pixor(voxelizer, bev, timings, cancel)
        boxes, scores = self._decode(score, regression, voxelizer, score_threshold, camera is not None, timings)
        timings["total"] = (time.perf_counter() - start) * 1e3
        cloud, made = self._kept_points(points, camera) if keep_points else (None, 0)
        return Detections(boxes=boxes, scores=scores, timings_ms=timings,
                          overlapped_ms={} if camera is None else camera.overlapped,
                          warnings=[w.message for w in warnings], warning_codes=[w.code for w in warnings], points=cloud,
                          pseudo_count=made)

    def _checked_frame(self, image: np.ndarray | None, points: np.ndarray, calib: Calibration | None,
                       score_threshold: float | None, emulate_to_beams: int | None,
                       ) -> tuple[np.ndarray | None, np.ndarray, Calibration | None]:
        """:meth:`detect`'s arguments checked (an InputError naming the one at fault; RuntimeError after
        :meth:`close`): the image, the scan as float32 and the calibration as the stages take them."""
        self._check_open()
        check_options(score_threshold, emulate_to_beams)
        points = self._check_points(points)
        if image is not None:
            image = check_image(image)
        if calib is not None:
            calib = check_calibration(calib, "calib")
        return image, points, calib

    def _emulate_beams(self, points: np.ndarray, lines: int, timings: dict[str, float],
                       cancel: Cancellation | None) -> tuple[np.ndarray, CodedWarning]:
        """A 64-line scan thinned to ``lines`` lines (``emulate_beams``) and the warning that says so;
        RunCancelled when the frame was cancelled meanwhile."""
        tic = time.perf_counter()
        before = points.shape[0]
        points = emulate_beams(points, lines)
        timings["emulate_beams"] = (time.perf_counter() - tic) * 1e3
        emulated = CodedWarning(WarningCode.BEAMS_EMULATED,
                                f"emulated {lines} beams: kept {points.shape[0]} of {before} points")
        # The emulation is NumPy, not interrupted (about 0.5 s for a scan of a million points): a frame
        # cancelled meanwhile stops here rather than going on to the depth net's inputs.
        if cancel is not None and cancel.cancelled:
            raise RunCancelled("the frame was cancelled during its beam emulation; stopped after it")
        return points, emulated

    def _camera_stage(self, image: np.ndarray | None, points: np.ndarray, calib: Calibration | None,
                      depth: np.ndarray | None, voxelizer: BevVoxelizer, timings: dict[str, float],
                      cancel: Cancellation | None) -> _CameraStage:
        """A two-stage model's pseudo points: the depth net's inputs (or the given depth map), the depth net
        with the work that needs no depth beside it on the stage thread (or in turn, before it), then the
        pseudo points' BEV bins."""
        if image is None or calib is None:
            raise InputError("image and calib: this model needs a camera image and a calibration")
        prepared, view_calib = self._prepare(image, points, calib, depth, timings)
        # With a second core, the stages that need no depth run beside the depth net, which has room for
        # them (an edge frame's path 1.6 ms shorter on two cores: docs/measurements.md, session 28), and
        # so do the rig's checks (about 0.2 ms, off the frame's path there).
        beside: Future | None = None
        warnings: list[CodedWarning] = []
        if self.stage_threads > 1:
            beside = self._beside(voxelizer, points, view_calib, image.shape[:2], calib)
        else:
            warnings = self.frame_checks(points, image.shape[:2], view_calib, calib)
        dense = self._depth_map(prepared, beside, timings, cancel)
        overlapped, rig_warnings = self._join_beside(beside, view_calib, timings)
        pseudo = self._pseudo_points(dense, view_calib, timings)
        return _CameraStage(pseudo=pseudo, dense=dense, view_calib=view_calib, points_voxelized=beside is not None,
                            overlapped=overlapped, warnings=warnings + rig_warnings)

    def _prepare(self, image: np.ndarray, points: np.ndarray, calib: Calibration, depth: np.ndarray | None,
                 timings: dict[str, float]) -> tuple[DepthInputs | np.ndarray, Calibration]:
        """The depth net's inputs, or with ``depth`` the given map checked and in the net's view (``prepare``),
        and that view's calibration."""
        tic = time.perf_counter()
        prepared: DepthInputs | np.ndarray
        if depth is None:
            prepared = depth_inputs(image, points, calib, self.preset)
            view_calib = prepared.calib
        else:
            prepared, view_calib = self._given_depth(depth, image, calib)
        timings["prepare"] = (time.perf_counter() - tic) * 1e3
        return prepared, view_calib

    def _depth_map(self, prepared: DepthInputs | np.ndarray, beside: Future | None, timings: dict[str, float],
                   cancel: Cancellation | None) -> np.ndarray:
        """The (H, W) depth in the net's view: the depth net's on its inputs (``depth_net``), or a given map as it is.
        When the net raises, the work ``beside`` it on the stage thread is waited for first."""
        if not isinstance(prepared, DepthInputs):  # a given depth map: no network to run
            return prepared
        tic = time.perf_counter()
        try:
            (dense,) = self._run("depth", ["depth"], {"rgb": prepared.rgb, "sparse_depth": prepared.sparse_depth},
                                 cancel)
        except BaseException:
            if beside is not None:  # the frame ends here: its half on the stage thread ends first
                wait([beside])
            raise
        dense = dense[0, 0]
        timings["depth_net"] = (time.perf_counter() - tic) * 1e3
        return dense

    def _join_beside(self, beside: Future | None, view_calib: Calibration,
                     timings: dict[str, float]) -> tuple[dict[str, float], list[CodedWarning]]:
        """The ``ray_table`` stage: the wait for the stage thread's work (what each of its stages took there, and
        the frame checks' warnings), or without one the view's rays built here."""
        overlapped: dict[str, float] = {}
        rig_warnings: list[CodedWarning] = []
        # The view's rays in BEV bin units are built on a calibration's first frame and cached. Timed
        # apart: a vehicle, with one calibration, builds them once; every synthetic frame has its own.
        tic = time.perf_counter()
        if beside is not None:
            overlapped, rig_warnings = beside.result()  # the wait for them is the stage's time on the frame's path
        else:
            self._ray_table(view_calib)
        timings["ray_table"] = (time.perf_counter() - tic) * 1e3
        return overlapped, rig_warnings

    def _pseudo_points(self, dense: np.ndarray, view_calib: Calibration, timings: dict[str, float]) -> PseudoBins:
        """The depth map back-projected straight to the BEV bins of its points (``pseudo_points``)."""
        limits = self.preset.pseudo_limits
        tic = time.perf_counter()
        pseudo = pseudo_bins(dense, view_calib, self.preset.bev, *limits, max_jump=self.preset.decode.height_max_jump)
        timings["pseudo_points"] = (time.perf_counter() - tic) * 1e3
        return pseudo

    def _voxelize(self, voxelizer: BevVoxelizer, points: np.ndarray, camera: _CameraStage | None,
                  timings: dict[str, float]) -> np.ndarray:
        """The BEV tensor of the real and the pseudo points (``voxelize``); the real points' half is done when
        the stage thread did it beside the depth net."""
        tic = time.perf_counter()
        if camera is None or not camera.points_voxelized:
            voxelizer.add_points(points)
        bev = voxelizer.add_pseudo(None if camera is None else camera.pseudo)
        timings["voxelize"] = (time.perf_counter() - tic) * 1e3
        return bev

    def _grid_warnings(self, voxelizer: BevVoxelizer, count: int, line_mismatch: str | None) -> list[CodedWarning]:
        """From the voxelizer's count of the scan's ``count`` points in the grid: a scan (almost) all outside the
        detection range, else one too thin for the model (unless its line count was named already)."""
        if voxelizer.points_in_grid < FEWEST_IN_GRID_SHARE * count:
            grid = self.preset.bev
            return [CodedWarning(WarningCode.OUT_OF_RANGE,
                f"points: almost none lie in the detection range, x {grid.x_min:g}…{grid.x_max:g} m forward, "
                f"y {grid.y_min:g}…{grid.y_max:g} m, z {grid.z_min:g}…{grid.z_max:g} m in the velodyne frame: "
                f"are they in metres, in that frame? ({voxelizer.points_in_grid} of {count} points)")]
        if not line_mismatch:  # the voxelizer's count, so free; a scan of fewer lines than trained is named above
            return coded((WarningCode.THIN_SCAN, thin_scan_fault(voxelizer.points_in_grid, self.trained_lines)))
        return []

    def _pixor(self, voxelizer: BevVoxelizer, bev: np.ndarray, timings: dict[str, float],
               cancel: Cancellation | None) -> tuple[np.ndarray, np.ndarray]:
        """PIXOR's score and regression maps of the BEV (``pixor``), with mirror TTA averaged with the mirror's."""
        tic = time.perf_counter()
        score, regression = self._run("pixor", ["score", "regression"], {"bev": bev[None]}, cancel)
        timings["pixor"] = (time.perf_counter() - tic) * 1e3
        if self.mirror_tta:
            score, regression = self._with_mirror(voxelizer, score, regression, timings, cancel)
        return score, regression

    def _decode(self, score: np.ndarray, regression: np.ndarray, voxelizer: BevVoxelizer,
                score_threshold: float | None, with_pseudo: bool,
                timings: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
        """The boxes and their scores from PIXOR's maps (``decode``), heights from the voxelizer's occupancy."""
        tic = time.perf_counter()
        boxes, scores = boxes_from_maps(score[0, 0], regression[0], voxelizer.height_occupancy, self.preset,
                                        score_threshold, with_pseudo=with_pseudo, mark=voxelizer.height_mark)
        timings["decode"] = (time.perf_counter() - tic) * 1e3
        return boxes, scores

    def _kept_points(self, points: np.ndarray, camera: _CameraStage | None) -> tuple[np.ndarray, int]:
        """``keep_points``: the cloud PIXOR saw, the camera's pseudo points first, and how many of them there are."""
        if camera is None:
            return points, 0
        camera_points = depth_to_points(camera.dense, camera.view_calib, *self.preset.pseudo_limits)
        return merge_points(camera_points, points), camera_points.shape[0]

    def _with_mirror(self, voxelizer: BevVoxelizer, score: np.ndarray, regression: np.ndarray,
                     timings: dict[str, float], cancel: Cancellation | None = None) -> tuple[np.ndarray, np.ndarray]:
        """PIXOR's maps averaged with those of the BEV mirrored left to right (y → −y), mirrored back.

        The grid is symmetric in y, so mirroring flips the rows; in the mirror a box's sin(yaw) and its
        offset dy change sign, which is undone on the de-normalised targets before averaging. The second
        run is timed as ``pixor_mirror``, the mirrored BEV and the averaging as ``mirror_merge`` (NumPy, not a
        network).
        """
        tic = time.perf_counter()
        mirrored = voxelizer.mirrored()
        merge_ms = (time.perf_counter() - tic) * 1e3
        tic = time.perf_counter()
        score_m, regression_m = self._run("pixor", ["score", "regression"], {"bev": mirrored[None]}, cancel)
        timings["pixor_mirror"] = (time.perf_counter() - tic) * 1e3
        tic = time.perf_counter()
        decode = self.preset.decode
        mean = np.asarray(decode.reg_mean, np.float32)[:, None, None]
        std = np.asarray(decode.reg_std, np.float32)[:, None, None]
        raw = regression_m[0, :, ::-1] * std + mean
        raw[MIRRORED_TARGETS] *= -1
        averaged = (score + score_m[:, :, ::-1]) / 2, (regression + ((raw - mean) / std)[None]) / 2
        timings["mirror_merge"] = merge_ms + (time.perf_counter() - tic) * 1e3
        return averaged

    def _given_depth(self, depth: np.ndarray, image: np.ndarray, calib: Calibration) -> tuple[np.ndarray, Calibration]:
        """A caller's dense depth map of the whole image, checked, in the depth net's view, and that view's calibration."""
        try:
            depth = np.asarray(depth)
        except (TypeError, ValueError):  # ragged nested lists
            raise InputError(f"depth: expected an (H, W) array of metres, got a {type(depth).__name__} of rows of "
                             "different lengths") from None
        if depth.shape != image.shape[:2]:
            raise InputError(f"depth: a {depth.shape} map for a {image.shape[:2]} image; it must cover the whole image")
        if depth.dtype.kind not in "fiu":  # OpenCV's resize takes none of complex, bool, object, long double
            raise InputError(f"depth: expected real depths in metres, got {depth.dtype} values")
        with np.errstate(over="ignore"):  # a float64 beyond float32's range becomes infinite: refused below
            metres = depth.astype(np.float32)
        if not np.isfinite(metres).all() or (metres < 0).any():
            raise InputError("depth: expected finite depths in metres (float32's range), 0 where there is none")
        return depth_view(metres, self.preset), view_calibration(image.shape[:2], calib, self.preset)

    def _line_count_mismatch(self, count: int) -> str | None:
        """A warning when a scan's point count is far from that of the line count the model was trained on."""
        if self.trained_lines == 16 and count > MOST_POINTS_OF_16_LINES:
            return ("points: as many as a 64-line scan, but the model was trained on 16-line scans; thin it first "
                    f"(--emulate-beams 16 to the commands, emulate_beams=16 to the service, emulate_to_beams=16 to "
                    f"Detector.detect) ({count} points)")
        if self.trained_lines == 64 and count < FEWEST_POINTS_OF_64_LINES:
            return f"points: fewer than a 64-line scan has, but the model was trained on 64-line scans ({count} points)"
        return None

    def _check_points(self, points: np.ndarray) -> np.ndarray:
        """The scan as finite float32 (N, 4) points on KITTI's reflectance scale, else an InputError naming ``points``."""
        try:
            points = np.asarray(points)
        except (TypeError, ValueError):  # ragged nested lists
            raise InputError(f"points: expected an (N, 4) array of x, y, z, reflectance, got a {type(points).__name__} "
                             "of rows of different lengths") from None
        if points.dtype.kind not in "fiu":  # np.isfinite fails on strings, drops a complex part, passes booleans
            raise InputError(f"points: expected real numbers (float32 x, y, z, reflectance), got {points.dtype} values")
        if points.ndim == 2 and points.shape[1] == 3:  # a driver's cloud without an intensity field
            raise InputError(f"points: expected shape (N, 4) x, y, z, reflectance; got {points.shape}, no "
                             "reflectance column: add the sensor's intensities scaled to [0, 1] (README, 'Your own "
                             "vehicle'; all zero runs, with a warning and fewer boxes)")
        if points.ndim == 2 and points.shape[1] > 4:  # a driver's cloud with a ring, time or other field after them
            raise InputError(f"points: expected shape (N, 4) x, y, z, reflectance; got {points.shape}: keep the "
                             "first four columns if they are x, y, z and the intensity (scaled to [0, 1]): "
                             "points[:, :4]")
        if points.ndim != 2 or points.shape[1] != 4:
            raise InputError(f"points: expected shape (N, 4) x, y, z, reflectance; got {points.shape}")
        if points.shape[0] == 0:
            raise InputError("points: the scan has no points")
        if points.shape[0] > MAX_POINTS:
            raise InputError(f"points: {points.shape[0]} points is more than the limit of {MAX_POINTS}")
        # The extremes of all values, in their own dtype: as fast as np.isfinite(points).all(), and a NaN (it
        # propagates) or an infinity among them is found as well; then they bound the coordinates.
        lowest, highest = points.min(), points.max()
        if not (np.isfinite(lowest) and np.isfinite(highest)):
            # Refused, not dropped: an array is the caller's own (a file's or the service's scan decoding drops such
            # rows and warns, nonfinite_dropped); the caller decides whether a frame with them is worth detecting.
            raise InputError("points: NaN or infinite values; drop those rows first: "
                             "points = points[np.isfinite(points).all(axis=1)]")
        # The BEV averages reflectance into a channel PIXOR learned on KITTI's [0, 1] scale: a driver's
        # 0–255 intensities would read as a wall of bright returns (about 100 made-up cars at score 1).
        low, high = float(points[:, 3].min()), float(points[:, 3].max())
        if low < 0.0 or high > 1.0 + REFLECTANCE_SLACK:
            swapped = byte_order_hint(points)
            if swapped:  # garbage in every column, plausible the other way round: a big-endian file
                hint = swapped
            elif low < 0.0 or high > 65535.0:  # no intensity scale: the rows are misread (5 or 6 values each?)
                hint = ("no sensor's intensities: are the scan's rows 4 float32 values? A scan with a ring or time "
                        "column (5 or 6 values a row) reads as shifted rows; keep x, y, z and the intensity: "
                        "np.fromfile(path, np.float32).reshape(-1, 5)[:, :4]")
            elif high > 255.0:
                hint = "divide the intensities by their full scale, 65535 for 16-bit ones"
            else:
                hint = "divide 0–255 intensities by 255"
            raise InputError(f"points: reflectance (the 4th column) must lie in [0, 1], KITTI's scale; this scan's "
                             f"lies in [{low:.4g}, {high:.4g}] ({hint})")
        # Compared as Python floats (a float16 would overflow taking the bound; a long double beyond float64's range
        # becomes infinite), printed in the points' own dtype (such a long double in full, not as inf).
        if float(lowest) < -MAX_COORDINATE or float(highest) > MAX_COORDINATE:  # the reflectance is in [0, 1]
            extreme = lowest if float(lowest) < -MAX_COORDINATE else highest
            shown = np.format_float_scientific(extreme, 3, trim="-") if points.dtype.kind == "f" else str(extreme)
            swapped = byte_order_hint(points)
            raise InputError(f"points: a coordinate of {shown} m, beyond any LiDAR's range (at most "
                             f"{MAX_COORDINATE:g} m in magnitude is taken): "
                             + (swapped or "garbage values, or rows misread?"))
        return points.astype(np.float32, copy=False)

    def warm_up(self, runs: int = 1, cancel: Cancellation | None = None) -> None:
        """Run the networks on zero inputs so the first real request is not slow (RunCancelled when
        ``cancel`` stops it)."""
        for _ in range(runs):
            if self.two_stage:
                h, w = self.preset.depth.input_hw
                self._run("depth", ["depth"], {"rgb": np.zeros((1, 3, h, w), np.float32),
                                               "sparse_depth": np.zeros((1, 1, h, w), np.float32)}, cancel)
            self._run("pixor", ["score", "regression"], {"bev": np.zeros((1, *self.preset.bev.shape), np.float32)},
                      cancel)

    def warm_up_thread(self, cancel: Cancellation | None = None) -> None:
        """Run one whole frame on the calling thread, so that its first real frame is not slow either.

        Each thread that calls :meth:`detect` keeps its own BEV buffers (the mirror's too) and its stage
        thread, made on its first frame. The frame is a flat road ahead and a black image under KITTI's
        usual calibration. (The view's rays are cached per calibration and image size, which a default
        calibration does not give, so a vehicle's first frame still builds its own: about 1 ms.)
        """
        grid = self.preset.bev
        x, y = np.meshgrid(np.arange(max(grid.x_min, 2.0), grid.x_max, 0.5, dtype=np.float32),
                           np.arange(grid.y_min, grid.y_max, 0.5, dtype=np.float32))
        road = np.stack([x.ravel(), y.ravel(), np.full(x.size, self.preset.decode.ground_z, np.float32),
                         np.full(x.size, 0.3, np.float32)], axis=1)
        image = np.zeros((*KITTI_IMAGE_HW, 3), np.uint8)
        self.detect(image, road, KITTI_CALIBRATION, cancel=cancel)
