"""What the service holds while it runs: the Detector(s), the inference pool, the default calibration.

:func:`load_runtime` checks everything a start needs and fails with a message
naming the file: a missing model directory, a model file whose sha256 differs
from the manifest (:class:`pipeline.model_files.ModelFileError`), an
unavailable execution provider, an unreadable default calibration.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field

from pipeline.calib import Calibration
from pipeline.detector import Cancellation, Detector
from pipeline.kitti import read_calib
from pipeline.model_files import ModelFileError
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
        """Run the networks ``runs`` times and a frame on each worker, then mark the runtime ready (blocking).

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


def load_runtime(settings: Settings, metrics: Metrics) -> Runtime:
    """Load the model directory (sha256 checked) once, or once per worker, and build the pool.

    Raises ModelFileError for a missing or corrupted model directory and
    pipeline.errors.InputError for a bad provider or default calibration.
    """
    models = settings.models
    try:
        found = models.is_dir()
    except OSError as exc:  # a name too long, no permission on a parent folder
        raise ModelFileError(f"{models}: cannot open the model directory ({exc.strerror or exc})") from exc
    if not found:
        raise ModelFileError(
            f"{models}: model directory not found; pass --models DIR (or LOWRES3D_MODELS) pointing to a "
            "directory written by `python -m export`"
        )
    default_calib = read_calib(settings.default_calib) if settings.default_calib is not None else None
    count = settings.workers if settings.sessions == "per-worker" else 1
    log.info("loading %s (%d session set(s); with TensorRT, its first load builds the engines: minutes)", models, count)
    threads = settings.resolved_intra_op_threads()
    gpus = settings.gpu_ids()
    detectors = [
        Detector(models, providers=settings.provider, intra_op_threads=threads, trt_cache_dir=settings.trt_cache_dir,
                 mirror_tta=settings.mirror_tta, device_id=gpus[k % len(gpus)] if gpus else None)
        for k in range(count)
    ]
    detector = detectors[0]
    log.info(
        "loaded %s (preset %s, %s%s) with %s%s on %d worker(s), %s session(s), %d intra-op thread(s), queue %d",
        models, detector.preset.name, "two-stage" if detector.two_stage else "LiDAR-only",
        ", PIXOR with mirror TTA" if detector.mirror_tta else "", detector.providers_in_use,
        f" on GPU(s) {', '.join(str(d.device_id) for d in detectors)} (per session pair)" if gpus else "",
        settings.workers, settings.sessions, threads, settings.queue_size,
    )
    metrics.model.info({
        "preset": detector.preset.name,
        "two_stage": str(detector.two_stage).lower(),
        "mirror_tta": str(detector.mirror_tta).lower(),
        "providers": ",".join(sorted({p for ps in detector.providers_in_use.values() for p in ps})),
        **{f"sha256_{name.replace('.', '_')}": digest for name, digest in detector.sha256.items()},
    })
    metrics.set_model_warnings(code for d in detectors for code in d.load_warning_codes)
    pool = InferencePool(detectors, settings.workers, settings.queue_size, metrics)
    return Runtime(detectors=detectors, pool=pool, default_calib=default_calib)
