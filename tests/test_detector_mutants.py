"""What the mutation audit of pipeline/detector.py (the ONNX Runtime ``Detector``) found no test pinning.

Each test here was seen to fail on a mutant of the Detector's own code (a comparison's edge, a deleted check, a
dropped warning, a wrong unit, a stage thread close() did not stop, a frame that returned before its stage work)
and passes on the real code: the defaults and bounds of the scan's checks, the line-count and range warnings, the
load-time checks of the manifest and graphs, close() and its races, network_inputs' copies. They run the shipped
weights (weights/edge, edge-lidar16, edge-lidar64; copied into ``tmp_path`` where one must be altered) in real ONNX
Runtime on the real KITTI frame 000006 of tests/data.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto

from pipeline.beams import emulate_beams
from pipeline.bev import BevVoxelizer
from pipeline.detector import (
    FEWEST_POINTS_OF_64_LINES,
    MAX_POINTS,
    MOST_POINTS_OF_16_LINES,
    Cancellation,
    Detector,
    RunCancelled,
    resolve_providers,
    trained_lines,
)
from pipeline.errors import InputError
from pipeline.frame import Frame, load_frame
from pipeline.model_files import ModelFileError
from pipeline.postprocess import boxes_from_maps
from tests.conftest import KITTI
from tests.test_own_rig import _other_camera

WEIGHTS = Path(__file__).resolve().parents[1] / "weights"
GPU_BUILD = ["TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"]


def _copy(tmp_path: Path, name: str) -> Path:
    """A copy of a shipped model directory, to alter."""
    return Path(shutil.copytree(WEIGHTS / name, tmp_path / name))


def _edit_manifest(models: Path, edit: Callable[[dict], object]) -> None:
    """Rewrite the manifest of ``models`` through ``edit`` (the files it lists untouched)."""
    manifest = json.loads((models / "manifest.json").read_text())
    edit(manifest)
    (models / "manifest.json").write_text(json.dumps(manifest))


@pytest.fixture(scope="module")
def frame() -> Frame:
    return load_frame(KITTI, "000006")


@pytest.fixture(scope="module")
def lidar16(frame: Frame) -> np.ndarray:
    """KITTI 000006's scan thinned to the 16 lines the shipped models learned on."""
    return emulate_beams(frame.points, 16)


@pytest.fixture(scope="module")
def camera() -> Detector:
    return Detector(WEIGHTS / "edge")


@pytest.fixture(scope="module")
def lidar_only() -> Detector:
    return Detector(WEIGHTS / "edge-lidar16")


def test_the_trained_line_count_follows_the_recorded_thinning_only():
    """A 16-line PIXOR's manifest may record the lines its scans were thinned to (``--emulate-beams``): those
    count, a 16-line sensor's own scans (0) or a count it cannot thin to do not, and a 64-line PIXOR stays 64."""
    assert trained_lines({"input": "lidar16", "emulate_beams": 32}) == 32
    assert trained_lines({"input": "pseudo", "emulate_beams": 8}) == 8
    assert trained_lines({"input": "lidar16", "emulate_beams": 0}) == 16
    assert trained_lines({"input": "lidar16", "emulate_beams": 64}) == 16
    assert trained_lines({"input": "lidar64", "emulate_beams": 16}) == 64


def test_a_list_of_providers_still_ends_on_the_cpu():
    """A list is taken as given, but the CPU is appended as the last fallback when the list leaves it out."""
    assert resolve_providers(["cuda", "tensorrt"], GPU_BUILD) == [GPU_BUILD[1], GPU_BUILD[0], GPU_BUILD[2]]
    assert resolve_providers(["tensorrt"], GPU_BUILD[:1] + GPU_BUILD[2:]) == [GPU_BUILD[0], GPU_BUILD[2]]


def test_one_usable_cpu_runs_every_stage_in_turn():
    """By default a process with a single CPU gets no stage thread (a second thread would only take turns with
    the first); the CPUs counted are those of the affinity mask, which threads started from this one inherit."""
    allowed = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {min(allowed)})
    try:
        assert Detector(WEIGHTS / "edge-lidar16").stage_threads == 1
    finally:
        os.sched_setaffinity(0, allowed)


def test_the_score_threshold_given_replaces_the_models_default(lidar_only: Detector, lidar16: np.ndarray):
    """Boxes below the caller's threshold are dropped and those above it kept, whatever the model's default."""
    default = lidar_only.preset.decode.score_threshold
    low = lidar_only.detect(None, lidar16, None, score_threshold=0.05)
    usual = lidar_only.detect(None, lidar16, None)
    assert (low.scores >= 0.05).all() and (usual.scores >= default).all()
    assert len(low.scores) > len(usual.scores) and (low.scores < default).any()
    assert len(lidar_only.detect(None, lidar16, None, score_threshold=1.0).scores) == 0


def test_a_lidar_only_frame_is_decoded_as_a_bev_without_pseudo_points(lidar_only: Detector, lidar16: np.ndarray):
    """A LiDAR-only model's boxes are its PIXOR maps decoded with the real points' box bottoms (the camera
    pipeline's pseudo points place them half a slice higher): detect equals its public pieces run by hand."""
    voxelizer = BevVoxelizer(lidar_only.preset.bev)
    voxelizer.add_points(lidar16)
    bev = voxelizer.add_pseudo(None)
    score, regression = lidar_only.run_pixor(bev[None])
    boxes, scores = boxes_from_maps(score[0, 0], regression[0], voxelizer.height_occupancy, lidar_only.preset, 0.3,
                                    with_pseudo=False, mark=voxelizer.height_mark)
    result = lidar_only.detect(None, lidar16, None, score_threshold=0.3)
    assert len(scores) >= 3
    np.testing.assert_allclose(result.boxes, boxes, atol=1e-6)
    np.testing.assert_allclose(result.scores, scores, atol=1e-6)


def test_network_stages_are_timed_in_milliseconds(camera: Detector, frame: Frame, lidar16: np.ndarray):
    """timings_ms are milliseconds: each network takes a good share of the frame's ``total``, which is at most
    the wall-clock time of the call (a stage timed in seconds would be a thousandth of it)."""
    tic = time.perf_counter()
    result = camera.detect(frame.image, lidar16, frame.calib)
    wall_ms = (time.perf_counter() - tic) * 1e3
    timings = result.timings_ms
    assert timings["total"] <= wall_ms
    assert timings["depth_net"] >= 0.1 * timings["total"] and timings["pixor"] >= 0.1 * timings["total"]


def test_only_the_camera_models_own_networks_are_warned_of_as_untrained(tmp_path: Path):
    """An untrained network is named at load when the caller runs it: the depth net alone for a depth-only
    user (its outputs are depth maps), both when both are untrained ("have")."""
    models = _copy(tmp_path, "edge")
    _edit_manifest(models, lambda m: m["networks"]["pixor"].update(weights="initialised"))
    assert Detector(models, networks_used=("depth",)).load_warnings == []
    (warning,) = Detector(models).load_warnings
    assert "pixor has initialised (untrained) weights: the detections mean nothing" in warning
    _edit_manifest(models, lambda m: m["networks"]["depth"].update(weights="initialised"))
    (warning,) = Detector(models, networks_used=("depth",)).load_warnings
    assert "depth has initialised (untrained) weights: the depth maps mean nothing" in warning
    both = Detector(models)
    assert both.load_warning_codes == ["untrained_weights"]
    assert "depth and pixor have initialised (untrained) weights: the detections" in both.load_warnings[0]


def test_an_fp16_directory_on_the_cpu_is_warned_of(tmp_path: Path):
    """FP16 networks on the CPU provider run slower than FP32 there: named at load, with the networks."""
    models = _copy(tmp_path, "edge-lidar16")
    _edit_manifest(models, lambda m: m.update(precision="fp16"))
    detector = Detector(models)
    assert detector.load_warning_codes == ["fp16_on_cpu"]
    assert "FP16 networks (pixor) run on the CPU provider" in detector.load_warnings[0]
    assert Detector(WEIGHTS / "edge-lidar16").load_warnings == []


@pytest.mark.parametrize(("column", "value"), [(0, 1e6), (1, -1e6), (3, float(np.float32(1 + 5e-7)))])
def test_a_scan_at_the_limits_of_its_checks_is_taken(camera: Detector, column: int, value: float):
    """A coordinate of exactly ±1e6 m and a reflectance a float32 rounding above 1 pass the scan's checks: the
    frame goes on to the next check, the camera model's want of an image."""
    points = np.full((1000, 4), 0.5, np.float32)
    points[0, column] = value
    with pytest.raises(InputError, match="^image and calib"):
        camera.detect(None, points, None)


def test_a_scan_of_exactly_the_most_points_taken_is_taken(camera: Detector):
    """MAX_POINTS is the most a scan may hold, itself included."""
    points = np.zeros((MAX_POINTS + 1, 4), np.float32)
    with pytest.raises(InputError, match="^image and calib"):
        camera.detect(None, points[:MAX_POINTS], None)
    with pytest.raises(InputError, match="more than the limit"):
        camera.detect(None, points, None)


def test_the_line_count_warning_starts_past_its_bounds(lidar_only: Detector, frame: Frame, lidar16: np.ndarray):
    """A 16-line model warns of a scan of more than MOST_POINTS_OF_16_LINES points, a 64-line one of fewer than
    FEWEST_POINTS_OF_64_LINES; a scan of exactly that many is not warned of."""
    many = np.concatenate([lidar16] * 3)
    codes = [lidar_only.detect(None, many[:n], None).warning_codes for n in (MOST_POINTS_OF_16_LINES,
                                                                            MOST_POINTS_OF_16_LINES + 1)]
    assert ["line_count" in c for c in codes] == [False, True]
    lidar64 = Detector(WEIGHTS / "edge-lidar64")
    codes = [lidar64.detect(None, frame.points[:n], None).warning_codes for n in (FEWEST_POINTS_OF_64_LINES,
                                                                                 FEWEST_POINTS_OF_64_LINES - 1)]
    assert ["line_count" in c for c in codes] == [False, True]
    # A 16-line scan to the 64-line model: named for its line count alone, not also as a thin scan.
    assert lidar64.detect(None, lidar16, None).warning_codes == ["line_count"]


@pytest.mark.parametrize(("inside", "warned"), [(0, True), (1, False), (5, False)])
def test_a_scan_is_out_of_range_below_one_percent_in_the_grid(lidar_only: Detector, inside: int, warned: bool):
    """Of a 100-point scan, none in the grid is out of range; one (exactly 1 %) or five are not."""
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-30, -5, 100), rng.uniform(-20, 20, 100), rng.uniform(-1.5, 0, 100),
                              np.full(100, 0.3)]).astype(np.float32)
    points[:inside, 0] *= -1  # ahead of the car, in the grid
    assert ("out_of_range" in lidar_only.detect(None, points, None).warning_codes) == warned


def test_a_frame_cancelled_during_its_beam_emulation_stops_after_it(camera: Detector, frame: Frame):
    """The emulation is not interrupted; a frame cancelled by then stops right after it, before the depth net's
    inputs are even made."""
    cancel = Cancellation()
    cancel.cancel()
    with pytest.raises(RunCancelled, match="during its beam emulation"):
        camera.detect(frame.image, frame.points, frame.calib, emulate_to_beams=16, cancel=cancel)


def test_a_closed_detector_says_so_before_looking_at_the_frame():
    """After close() every frame is refused as such, even one that would have failed its own checks."""
    detector = Detector(WEIGHTS / "edge-lidar16")
    detector.close()
    with pytest.raises(RuntimeError, match="was closed; make a new one"):
        detector.detect(None, np.zeros((0, 4), np.float32), None)


def test_network_inputs_are_copies_of_the_first_run_of_each_network(lidar16: np.ndarray):
    """network_inputs records what detect feeds each network once (with mirror TTA, not the mirrored BEV of
    PIXOR's second run) and as copies, which later frames (reusing the voxelizer's buffer) leave alone."""
    plain = Detector(WEIGHTS / "edge-lidar16", stage_threads=1)
    mirrored = Detector(WEIGHTS / "edge-lidar16", stage_threads=1, mirror_tta=True)
    bev = plain.network_inputs(None, lidar16, None)["pixor"]["bev"]
    np.testing.assert_array_equal(mirrored.network_inputs(None, lidar16, None)["pixor"]["bev"], bev)
    kept = bev.copy()
    plain.detect(None, lidar16[::2], None)
    np.testing.assert_array_equal(bev, kept)


def test_a_given_depth_map_is_checked(camera: Detector, frame: Frame, lidar16: np.ndarray):
    """A caller's depth map must cover the whole image with real, finite, non-negative metres."""
    whole = np.full(frame.image.shape[:2], 10.0, np.float32)
    for depth, message in ((whole[:-1], "it must cover the whole image"), (whole.astype(complex), "complex"),
                           (-whole, "finite depths in metres")):
        with pytest.raises(InputError, match=message):
            camera.detect(frame.image, lidar16, frame.calib, depth=depth)


def test_a_manifest_without_a_pixor_is_refused_naming_it(tmp_path: Path):
    """Every model directory runs a PIXOR: a manifest listing none is a model-file error naming manifest.json,
    not a KeyError from deep inside the loading."""
    models = _copy(tmp_path, "edge")
    _edit_manifest(models, lambda m: m["networks"].pop("pixor"))
    with pytest.raises(ModelFileError, match=r"manifest\.json: no 'pixor' network listed"):
        Detector(models)


def test_verify_false_reads_the_files_without_checking_any(tmp_path: Path):
    """``verify=False`` (for a directory being written, say) skips every sha256 of the manifest, the networks'
    and the other files' alike; the default checks both."""
    models = _copy(tmp_path, "edge-lidar16")
    (models / "notes.txt").write_text("notes\n")
    _edit_manifest(models, lambda m: m["files"].update({"notes.txt": {"sha256": "0" * 64}}))
    with pytest.raises(ModelFileError, match="notes.txt"):
        Detector(models)
    Detector(models, verify=False)
    _edit_manifest(models, lambda m: (m["files"].pop("notes.txt"), m["files"]["pixor.onnx"].update(sha256="0" * 64)))
    with pytest.raises(ModelFileError, match="pixor.onnx"):
        Detector(models)
    Detector(models, verify=False)


def _stage_threads() -> set[threading.Thread]:
    return {thread for thread in threading.enumerate() if thread.name.startswith("lowres3d-stages")}


def test_close_returns_once_the_stage_work_in_flight_has_ended(frame: Frame, lidar16: np.ndarray, monkeypatch):
    """close() on another thread while a frame's stage work runs beside the depth net waits for that work and
    stops the thread: when it returns no stage thread of the Detector is left, and the frame ends with the
    Detector's own message."""
    detector = Detector(WEIGHTS / "edge", stage_threads=2)
    beside, started = detector._without_depth, threading.Event()

    def slow(*args):  # the stage thread's work, held long enough for close() to come in the middle of it
        started.set()
        time.sleep(0.3)
        return beside(*args)

    monkeypatch.setattr(detector, "_without_depth", slow)
    before = _stage_threads()
    with ThreadPoolExecutor(1) as caller:
        frame_run = caller.submit(detector.detect, frame.image, lidar16, frame.calib)
        assert started.wait(10)
        ours = _stage_threads() - before
        detector.close()
        assert len(ours) == 1 and not any(thread.is_alive() for thread in ours)
        with pytest.raises(RuntimeError, match="was closed; make a new one"):
            frame_run.result(10)


def test_a_closed_detector_runs_no_network_and_a_with_block_closes_it(lidar16: np.ndarray):
    """After close() (here at the end of a ``with`` block) the sessions are gone: the networks' own entry
    points refuse to run as detect does."""
    with Detector(WEIGHTS / "edge-lidar16") as detector:
        bev = detector.network_inputs(None, lidar16, None)["pixor"]["bev"]
        detector.run_pixor(bev)
    for run in (lambda: detector.run_pixor(bev), detector.warm_up, lambda: detector.detect(None, lidar16, None)):
        with pytest.raises(RuntimeError, match="was closed; make a new one"):
            run()


def test_a_frame_stopped_in_its_depth_net_returns_after_its_stage_work(frame: Frame, lidar16: np.ndarray,
                                                                       monkeypatch):
    """A frame that ends in its depth net's run (cancelled here) first waits for its half on the stage thread: a
    caller that goes on, or retries, finds no work of the old frame still writing the thread's BEV buffer."""
    detector = Detector(WEIGHTS / "edge", stage_threads=2)
    beside, finished = detector._without_depth, threading.Event()

    def slow(*args):  # the stage thread's work, still running when the depth net refuses the cancelled frame
        time.sleep(0.3)
        result = beside(*args)
        finished.set()
        return result

    monkeypatch.setattr(detector, "_without_depth", slow)
    cancel = Cancellation()
    cancel.cancel()
    with pytest.raises(RunCancelled, match="depth network run"):
        detector.detect(frame.image, lidar16, frame.calib, cancel=cancel)
    assert finished.is_set()


class _HeldScan:
    """A scan handed over as an array-like whose conversion (inside detect's checks) waits until released."""

    def __init__(self, points: np.ndarray) -> None:
        self.points, self.converting, self.release = points, threading.Event(), threading.Event()

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        self.converting.set()
        self.release.wait(10)
        return self.points


def test_a_frame_that_outlives_close_starts_no_stage_thread(frame: Frame, lidar16: np.ndarray):
    """A thread's first frame, past detect's own closed check when close() comes, is refused where it would make
    its stage thread: none is started after close(), to idle for as long as the calling thread lives."""
    detector = Detector(WEIGHTS / "edge", stage_threads=2)
    scan = _HeldScan(lidar16)
    before = _stage_threads()
    with ThreadPoolExecutor(1) as caller:  # the caller thread stays alive until the end of the block
        frame_run = caller.submit(detector.detect, frame.image, scan, frame.calib)
        assert scan.converting.wait(10)
        detector.close()
        scan.release.set()
        with pytest.raises(RuntimeError, match="was closed; make a new one"):
            frame_run.result(10)
        assert _stage_threads() - before == set()


@pytest.mark.parametrize("edit", [lambda p: p.update(crop_hw=[0, 1216]), lambda p: p["bev"].update(x_max=0.0)])
def test_a_preset_of_an_empty_crop_or_grid_is_refused_at_load(tmp_path: Path, edit: Callable[[dict], object]):
    """A crop or BEV grid of no rows or columns (the crop is in no graph's shapes) is refused at load, not at the
    first frame."""
    models = _copy(tmp_path, "edge")
    _edit_manifest(models, lambda m: edit(m["preset_config"]))
    with pytest.raises(ModelFileError, match=r"manifest\.json: preset_config: empty BEV grid"):
        Detector(models)


def test_the_rig_checks_look_at_the_camera_view_only_with_both_its_halves(camera: Detector, frame: Frame,
                                                                          lidar16: np.ndarray):
    """frame_checks (public: a node may run them on a frame it does not detect in) checks the camera's view
    only given both the image's size and the view's calibration; with either alone, the scan's checks only."""
    view = camera.dense_depth(frame.image, lidar16, frame.calib)[1]
    scan_only = camera.frame_checks(lidar16)
    assert camera.frame_checks(lidar16, image_hw=frame.image.shape[:2]) == scan_only
    assert camera.frame_checks(lidar16, view_calib=view) == scan_only


def test_a_graph_input_of_another_type_is_refused_at_load(tmp_path: Path):
    """A PIXOR that reads its BEV in float16 loads in ONNX Runtime and fails at the first frame, fed float32:
    refused at load, naming the input and its type."""
    models = _copy(tmp_path, "edge-lidar16")
    graph = onnx.load(str(models / "pixor.onnx"))
    first = graph.graph.input[0]
    for node in graph.graph.node:  # its consumers read a float32 cast of the float16 input
        node.input[:] = [f"{first.name}/f32" if name == first.name else name for name in node.input]
    graph.graph.node.insert(0, onnx.helper.make_node("Cast", [first.name], [f"{first.name}/f32"], to=TensorProto.FLOAT))
    first.type.tensor_type.elem_type = TensorProto.FLOAT16
    onnx.save(graph, str(models / "pixor.onnx"))
    data = (models / "pixor.onnx").read_bytes()
    _edit_manifest(models, lambda m: m["files"].update({"pixor.onnx": {"sha256": hashlib.sha256(data).hexdigest(),
                                                                       "bytes": len(data)}}))
    with pytest.raises(ModelFileError, match=rf"pixor\.onnx: input '{re.escape(first.name)}' is a tensor\(float16\), "
                                             r"where the runtime feeds tensor\(float\)"):
        Detector(models)


def test_a_stuck_scan_still_gets_the_camera_views_warning(camera: Detector, frame: Frame, lidar16: np.ndarray):
    """A scan stuck at one range skips the scan's rig checks, which would misname it, but not the camera's:
    a 1920×1080 camera whose depth-net crop lies below the cars is still named."""
    image, calib = _other_camera(frame.image, frame.calib, 1920, 1080)
    stuck = lidar16.copy()
    stuck[:, :3] *= 10.0 / np.linalg.norm(stuck[:, :3], axis=1, keepdims=True)
    assert camera.detect(image, stuck, calib).warning_codes == ["stuck_range", "camera_view"]


def test_a_lidar_only_model_refuses_to_run_a_depth_net(lidar_only: Detector, frame: Frame, lidar16: np.ndarray):
    """Depth completion alone asked of a LiDAR-only model directory: an InputError saying it has no depth network."""
    with pytest.raises(InputError, match="has no depth network"):
        lidar_only.dense_depth(frame.image, lidar16, frame.calib)
