"""What the service holds while it runs: the Detector(s), the inference pool, the default calibration, and the
identity of the model it serves.

:func:`load_runtime` checks everything a start needs and fails with a message
naming the file: a missing model directory, a model file whose sha256 differs
from the manifest (:class:`pipeline.model_files.ModelFileError`), a directory
that changed while it loaded (a copy in progress), an unavailable execution
provider, an unreadable default calibration.

The sessions hold the networks in memory: files replaced under a running service
change nothing until it restarts. The model directory is followed through its
symbolic links once, at the start: every worker loads the same directory even when a
``current`` link is switched meanwhile, and /v1/model names the directory it points to.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.calib import Calibration
from pipeline.detector import Cancellation, Detector
from pipeline.kitti import read_calib
from pipeline.model_files import (
    ModelFileError,
    ModelIdentity,
    load_manifest_with_digest,
    model_identity,
    verify_sha256,
)
from service.metrics import Metrics
from service.pool import InferencePool
from service.settings import Settings

log = logging.getLogger(__name__)


@dataclass
class Runtime:
    """The loaded models and the pool that runs them; ``ready`` is set once warmed up."""

    detectors: list[Detector]
    pool: InferencePool
    default_calib: Calibration | None
    identity: ModelIdentity
    ready: threading.Event = field(default_factory=threading.Event)
    stopping: Cancellation = field(default_factory=Cancellation)  # cancelled on shutdown: the warm-up ends early
    warm_up_error: str | None = None

    @property
    def detector(self) -> Detector:
        """The first Detector (all of them load the same model directory)."""
        return self.detectors[0]

    @property
    def crop_hw(self) -> tuple[int, int] | None:
        """Smallest image (height, width) the depth net accepts; None for a LiDAR-only model."""
        detector = self.detector
        return tuple(detector.preset.crop_hw) if detector.two_stage else None  # type: ignore[return-value]

    def warm_up(self, runs: int) -> None:
        """Run the networks ``runs`` times and a frame on each worker (``runs`` 0: neither), then mark the runtime
        ready (blocking).

        Ends at the next network node once ``stopping`` is cancelled, so a SIGTERM during a long warm-up
        (many ``--warmup-runs``, TensorRT) does not wait for all of it."""
        try:
            finished = self.pool.warm_up(runs, self.stopping)
        except Exception as exc:  # an execution provider failing at first run: stay not ready, say why
            self.warm_up_error = f"warm-up failed: {exc}"
            log.exception("warm-up failed; /readyz stays 503")
            return
        if not finished:
            log.info("warm-up stopped: the service is shutting down")
            return
        self.ready.set()
        log.info("warmed up (%d run(s) per session): ready", runs)

    def close(self) -> None:
        """Stop the pool (its running and waiting jobs end first) and release every Detector's sessions and stage
        threads at once; safe twice. Without it they went only when the garbage collector reached the app: a
        process that starts the service again (a test suite, a supervisor in-process) kept every stopped one's."""
        self.pool.shutdown()
        for detector in self.detectors:
            detector.close()


def load_runtime(settings: Settings, metrics: Metrics) -> Runtime:
    """Load the model directory (sha256 checked) once, or once per worker, and build the pool.

    Raises ModelFileError for a missing or corrupted model directory, or one that changed while it loaded,
    and pipeline.errors.InputError for a bad provider or default calibration.
    """
    models = settings.models
    directory = model_directory(models)
    default_calib = read_calib(settings.default_calib) if settings.default_calib is not None else None
    count = settings.workers if settings.sessions == "per-worker" else 1
    shown = str(models) if directory == models else f"{models} (→ {directory})"
    log.info("loading %s (%d session set(s); with TensorRT, its first load builds the engines: minutes)", shown, count)
    threads = settings.resolved_intra_op_threads()
    gpus = settings.gpu_ids()
    detectors = [
        Detector(directory, providers=settings.provider, intra_op_threads=threads, trt_cache_dir=settings.trt_cache_dir,
                 mirror_tta=settings.mirror_tta, device_id=gpus[k % len(gpus)] if gpus else None)
        for k in range(count)
    ]
    detector = detectors[0]
    identity = loaded_identity(directory, detectors)
    log.info(
        "loaded %s: %s, %s%s, with %s%s on %d worker(s), %s session(s), %d intra-op thread(s), queue %d",
        shown, identity.summary(), "two-stage" if detector.two_stage else "LiDAR-only",
        ", PIXOR with mirror TTA" if detector.mirror_tta else "", detector.providers_in_use,
        f" on GPU(s) {', '.join(str(d.device_id) for d in detectors)} (per session pair)" if gpus else "",
        settings.workers, settings.sessions, threads, settings.queue_size,
    )
    metrics.model.info({
        "id": identity.id,
        "directory": identity.directory,
        "preset": identity.preset,
        "precision": identity.precision,
        "format": str(identity.format),
        "weights": identity.weights,
        "training_data": ",".join(sorted({d for d in identity.training_data.values() if d})) or "unrecorded",
        "two_stage": str(detector.two_stage).lower(),
        "mirror_tta": str(detector.mirror_tta).lower(),
        "providers": ",".join(sorted({p for ps in detector.providers_in_use.values() for p in ps})),
        **{f"sha256_{name.replace('.', '_')}": digest for name, digest in identity.sha256.items()},
    })
    metrics.set_model_warnings(code for d in detectors for code in d.load_warning_codes)
    pool = InferencePool(detectors, settings.workers, settings.queue_size, metrics)
    return Runtime(detectors=detectors, pool=pool, default_calib=default_calib, identity=identity)


def model_directory(models: Path) -> Path:
    """``--models`` with its symbolic links followed, as given when it has none (read once: a rollout switching a
    link while the service starts cannot give two workers two models); ModelFileError when it is no directory."""
    try:
        resolved = models.resolve()
        directory = models if resolved == models.absolute() else resolved
        found = directory.is_dir()
    except (OSError, RuntimeError) as exc:  # a name too long, no permission on a parent folder, a link loop
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        raise ModelFileError(f"{models}: cannot open the model directory ({reason})") from exc
    if not found:
        raise ModelFileError(
            f"{models}: model directory not found; pass --models DIR (or LOWRES3D_MODELS) pointing to a "
            "directory written by `python -m export`"
        )
    return directory


def loaded_identity(directory: Path, detectors: list[Detector]) -> ModelIdentity:
    """The identity of the model the sessions hold, after checking that the directory still holds it: a copy
    into the directory while the service started (its manifest replaced between the workers' loads, or a file)
    is refused rather than served under an identity the directory no longer has. (The CPU and CUDA sessions run
    the very bytes each Detector checked; TensorRT's, loaded by path, were checked again by the Detector.)"""
    manifest, digest = load_manifest_with_digest(directory)
    if any(d.manifest != manifest for d in detectors):
        raise ModelFileError(f"{directory}: the model directory changed while the service loaded it (a copy in "
                             "progress?); copy a model into a new directory, then point --models at it")
    verify_sha256(directory, manifest)
    return model_identity(directory, manifest, digest)
