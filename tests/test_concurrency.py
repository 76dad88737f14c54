"""One Detector under several threads: results equal to serial ones, stage threads that end with their callers,
and close() racing a frame (the tiny models, synthetic frames with calibrations of their own)."""

import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from pipeline.detector import Detections, Detector
from pipeline.frame import Frame, load_frame
from simulation.run import RunConfig, run

FRAMES = 4
STAGE_THREAD_PREFIX = "lowres3d-stages"
THREAD_END_S = 30.0  # generous: only a failing run waits this long


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> list[Frame]:
    """Synthetic validation frames, each with its own calibration (so each its own ray table)."""
    out = tmp_path_factory.mktemp("concurrency_frames")
    ids = run(RunConfig(out, frames=FRAMES, seed=2, split="val", progress=False)).ids
    loaded = [load_frame(out, frame_id) for frame_id in ids]
    assert len({frame.calib.P2.tobytes() for frame in loaded}) == FRAMES
    return loaded


def detect(detector: Detector, frame: Frame) -> Detections:
    return detector.detect(frame.image, frame.points, frame.calib, 0.0, emulate_to_beams=16)


def stage_threads() -> set[threading.Thread]:
    return {thread for thread in threading.enumerate() if thread.name.startswith(STAGE_THREAD_PREFIX)}


def test_frames_on_several_threads_equal_their_serial_results(tiny_models: Path, frames: list[Frame]) -> None:
    """Three threads run every frame twice, in shifted orders so that frames of different calibrations overlap:
    each result is the serial one exactly (the per-thread BEV, mirror and height buffers, the stage threads and
    the ray tables shared between threads mix nothing). Every box at score 0 is compared, so a stray voxel shows."""
    detector = Detector(tiny_models, stage_threads=2, mirror_tta=True)
    serial = [detect(detector, frame) for frame in frames]
    assert all(len(result.scores) > 0 for result in serial)
    jobs = [(start + k) % FRAMES for start in range(3) for k in range(2 * FRAMES)]
    with ThreadPoolExecutor(3) as callers:
        results = list(callers.map(lambda index: detect(detector, frames[index]), jobs))
    for index, result in zip(jobs, results):
        np.testing.assert_array_equal(result.boxes, serial[index].boxes)
        np.testing.assert_array_equal(result.scores, serial[index].scores)
        assert result.warning_codes == serial[index].warning_codes
    detector.close()


def test_short_lived_caller_threads_leave_no_stage_thread_behind(tiny_models: Path, frames: list[Frame]) -> None:
    """A thread that calls detect once and ends (a thread per request or per batch) takes its stage thread with
    it: a threading.local shuts nothing down, and each such caller left an idle thread for the Detector's life."""
    detector = Detector(tiny_models, stage_threads=2)
    before = stage_threads()
    for frame in frames * 2:
        caller = threading.Thread(target=detect, args=(detector, frame))
        caller.start()
        caller.join()
    left = stage_threads() - before
    deadline = time.monotonic() + THREAD_END_S
    for thread in left:  # woken as their executors go; they end at once, a busy machine aside
        thread.join(max(0.0, deadline - time.monotonic()))
    assert [thread.name for thread in left if thread.is_alive()] == []
    # A thread that stays keeps its stage thread until close().
    with ThreadPoolExecutor(1) as caller:
        caller.submit(detect, detector, frames[0]).result()
        (kept,) = stage_threads() - before
        detector.close()
        kept.join(THREAD_END_S)
        assert not kept.is_alive()


class HeldScan:
    """A scan handed over as an array-like (a message buffer): its first conversion waits until released."""

    def __init__(self, points: np.ndarray) -> None:
        self.points = points
        self.converting, self.release = threading.Event(), threading.Event()

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        if not self.converting.is_set():
            self.converting.set()
            self.release.wait(THREAD_END_S)
        return self.points if dtype is None else self.points.astype(dtype)


def test_close_during_a_frame_on_another_thread_says_the_detector_was_closed(tiny_models: Path,
                                                                            frames: list[Frame]) -> None:
    """close() from another thread (a node rebuilding its Detector) while a frame is under way on a thread that
    has its stage thread: the frame ends with the Detector's own message, not the executor's "cannot schedule
    new futures after shutdown"."""
    detector = Detector(tiny_models, stage_threads=2)
    frame = frames[0]
    scan = HeldScan(frame.points)

    def two_frames() -> None:
        detect(detector, frame)  # the thread's stage thread, made
        detector.detect(frame.image, scan, frame.calib, emulate_to_beams=16)

    with ThreadPoolExecutor(1) as caller:
        second = caller.submit(two_frames)
        assert scan.converting.wait(THREAD_END_S)  # the second frame is past the closed check, reading its scan
        detector.close()
        scan.release.set()
        with pytest.raises(RuntimeError, match=r"Detector\(.*\) was closed; make a new one"):
            second.result(THREAD_END_S)


def test_a_stopped_service_has_released_its_detectors(tiny_models: Path, frames: list[Frame]) -> None:
    """The lifespan's end closes every Detector (per-worker sessions here) once the pool has drained: their sessions
    and stage threads go then, not when the garbage collector reaches the app."""
    from service.app import create_app
    from service.settings import Settings
    from tests.test_service import AppClient

    before = stage_threads()
    app = create_app(Settings(models=tiny_models, sessions="per-worker", workers=2))
    with AppClient(app) as client:
        client.wait_ready()  # a warm-up frame on each worker (and its stage thread, with two intra-op threads)
        detectors = app.state.runtime.detectors
        assert len(detectors) == 2
    for detector in detectors:
        with pytest.raises(RuntimeError, match="was closed"):
            detect(detector, frames[0])
    left = stage_threads() - before
    for thread in left:
        thread.join(THREAD_END_S)
    assert [thread.name for thread in left if thread.is_alive()] == []
