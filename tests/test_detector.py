"""The ONNX Runtime Detector and `python -m pipeline.detect` on a real KITTI frame (tiny preset)."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.beams import emulate_beams
from pipeline.calib import Calibration
from pipeline.detector import (
    Cancellation,
    Detector,
    RunCancelled,
    provider_fallbacks,
    resolve_providers,
    session_options,
    session_providers,
)
from pipeline.errors import InputError
from pipeline.frame import load_frame
from pipeline.kitti import format_label, read_labels
from pipeline.model_files import ModelFileError, sha256_file
from pipeline.presets import PRESETS, preset_from_dict
from pipeline.render import GROUND_TRUTH_BGR, PREDICTION_BGR, split_scan_and_pseudo
from tests.conftest import FRAMES, KITTI, lidar_only_models

STAGES = {"prepare", "depth_net", "ray_table", "pseudo_points", "voxelize", "pixor", "decode", "total"}


@pytest.fixture(scope="module")
def detector(tiny_models):
    return Detector(tiny_models)


@pytest.fixture(scope="module")
def frame():
    return load_frame(KITTI, "000006")


def test_ray_table_is_built_once_per_calibration(detector, frame):
    """The pseudo points' rays are built on a calibration's first frame (timed as ``ray_table``) and reused
    after; a frame with another calibration builds its own."""
    from pipeline import pseudo

    lidar16 = emulate_beams(frame.points, 16)
    pseudo._TABLES.clear()
    detector.detect(frame.image, lidar16, frame.calib)
    (built,) = pseudo._TABLES.values()
    detector.detect(frame.image, lidar16, frame.calib)
    (again,) = pseudo._TABLES.values()
    assert again is built  # not built again
    moved = Calibration(P2=frame.calib.P2 + np.array([[0, 0, 1.0, 0], [0, 0, 0, 0], [0, 0, 0, 0]]),
                        R0_rect=frame.calib.R0_rect, Tr_velo_to_cam=frame.calib.Tr_velo_to_cam)
    detector.detect(frame.image, lidar16, moved)
    assert len(pseudo._TABLES) == 2


def test_detects_on_real_frame_with_wellformed_boxes(detector, frame):
    lidar16 = emulate_beams(frame.points, 16)
    result = detector.detect(frame.image, lidar16, frame.calib, score_threshold=0.0, keep_points=True)
    assert set(result.timings_ms) == STAGES
    assert all(np.isfinite(v) and v >= 0 for v in result.timings_ms.values())
    assert result.timings_ms["total"] >= sum(v for k, v in result.timings_ms.items() if k != "total") * 0.99
    assert result.boxes.shape == (len(result.scores), 7) and len(result.scores) > 0
    assert np.all(np.diff(result.scores) <= 0)  # best first
    assert np.isfinite(result.boxes).all()
    assert (result.boxes[:, 3:6] > 0).all()
    grid = detector.preset.bev
    assert (result.boxes[:, 0] > grid.x_min - 5).all() and (result.boxes[:, 0] < grid.x_max + 5).all()
    # Kept boxes do not overlap beyond the NMS threshold.
    from pipeline.iou import rotated_iou_matrix

    iou = rotated_iou_matrix(result.boxes[:, [0, 1, 3, 4, 6]], result.boxes[:, [0, 1, 3, 4, 6]])
    assert (iou[~np.eye(len(iou), dtype=bool)] <= detector.preset.decode.nms_iou + 1e-9).all()
    # The cloud PIXOR saw is the pseudo cloud plus the 16 real lines.
    assert result.points.shape[0] > lidar16.shape[0]
    assert detector.detect(frame.image, lidar16, frame.calib).points is None  # only on request
    objects = result.to_objects(frame.calib, frame.image_hw)
    assert all(o.type == "Car" and o.score is not None for o in objects)
    assert len(objects) <= len(result.scores)


def test_emulation_on_request_equals_emulating_first(detector, frame):
    a = detector.detect(frame.image, frame.points, frame.calib, 0.0, emulate_to_beams=16)
    b = detector.detect(frame.image, emulate_beams(frame.points, 16), frame.calib, 0.0)
    np.testing.assert_array_equal(a.boxes, b.boxes)
    assert "emulate_beams" in a.timings_ms and a.warnings


def test_threads_give_the_same_answer(detector, frame):
    lidar16 = emulate_beams(frame.points, 16)
    reference = detector.detect(frame.image, lidar16, frame.calib, 0.0)
    with ThreadPoolExecutor(2) as pool:
        results = list(pool.map(lambda _: detector.detect(frame.image, lidar16, frame.calib, 0.0), range(4)))
    for r in results:
        np.testing.assert_allclose(r.boxes, reference.boxes, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("stage_threads", [1, 2])
def test_a_cancelled_frame_stops_in_onnx_runtime_and_leaves_the_thread_sound(tiny_models, frame, stage_threads,
                                                                             monkeypatch):
    """A Cancellation set before or during a frame stops it with RunCancelled: ONNX Runtime itself ends the run
    on its terminate flag (the error it raised is the context). The thread's next frame is as a fresh one's."""
    lidar16 = emulate_beams(frame.points, 16)
    detector = Detector(tiny_models, stage_threads=stage_threads)
    detector.detect(frame.image, lidar16, frame.calib, 0.0)

    cancel = Cancellation()
    cancel.cancel()
    with pytest.raises(RunCancelled, match="depth network run") as stopped:
        detector.detect(frame.image, lidar16[::2], frame.calib, 0.0, cancel=cancel)
    assert "terminate flag" in str(stopped.value.__context__)  # ONNX Runtime's own refusal, not a check of ours

    # Cancelled by another thread while the frame runs: with a stage thread, from the work beside the depth
    # net; without one, between the depth net and PIXOR.
    during = Cancellation()
    with monkeypatch.context() as patch:
        if stage_threads == 2:
            beside = detector._without_depth
            patch.setattr(detector, "_without_depth", lambda *args: (during.cancel(), beside(*args))[1])
            network = "(depth|pixor)"  # the depth net's run, unless it was over before that thread came to run
        else:
            add_pseudo = detector._voxelizer().add_pseudo
            patch.setattr(detector._voxelizer(), "add_pseudo", lambda *args: (during.cancel(), add_pseudo(*args))[1])
            network = "pixor"
        with pytest.raises(RunCancelled, match=f"{network} network run"):
            detector.detect(frame.image, lidar16[::3], frame.calib, 0.0, cancel=during)

    fresh = Detector(tiny_models, stage_threads=stage_threads)
    again, expected = (d.detect(frame.image, lidar16[::5], frame.calib, 0.0) for d in (detector, fresh))
    np.testing.assert_array_equal(again.boxes, expected.boxes)
    np.testing.assert_array_equal(detector._voxelizer()._out, fresh._voxelizer()._out)  # no cell of a stopped frame


def test_stage_thread_changes_nothing_but_the_timings(tiny_models, frame, tmp_path):
    """With a stage thread the calibration's rays, the real points' half of the BEV and the rig's checks are made
    beside the depth net (``overlapped_ms``) and the boxes and warnings are those of the stages in turn, frame
    after frame, on the shared grid and the split one; LiDAR-only models have nothing to overlap."""
    from export.exporter import ExportConfig, run

    run(ExportConfig(preset="tiny-split", out=tmp_path / "split", parity=False))
    lidar16 = emulate_beams(frame.points, 16)
    dark = np.column_stack([lidar16[:, :3], np.zeros(len(lidar16), np.float32)])  # a rig check's warning
    scans = [lidar16, lidar16[::3], frame.points[::4], dark]
    for models in (tiny_models, tmp_path / "split"):
        in_turn, beside = Detector(models, stage_threads=1), Detector(models, stage_threads=2)
        assert (in_turn.stage_threads, beside.stage_threads) == (1, 2)
        for points in scans:
            a = in_turn.detect(frame.image, points, frame.calib, 0.0)
            b = beside.detect(frame.image, points, frame.calib, 0.0)
            np.testing.assert_array_equal(a.boxes, b.boxes)
            np.testing.assert_array_equal(a.scores, b.scores)
            np.testing.assert_array_equal(in_turn._voxelizer()._out, beside._voxelizer()._out)
            assert a.overlapped_ms == {} and set(b.overlapped_ms) == {"ray_table", "voxelize", "rig_checks"}
            assert a.warnings == b.warnings  # the rig's checks, beside the depth net or in turn
            assert any("reflectance is on another scale" in w for w in b.warnings) == (points is dark)
            assert set(b.timings_ms) == STAGES
            assert b.timings_ms["total"] >= sum(v for k, v in b.timings_ms.items() if k != "total") * 0.99
    # One thread per worker (the service's default on two cores, the throughput workers): stages in turn.
    assert Detector(tiny_models, intra_op_threads=1).stage_threads == 1
    with pytest.raises(InputError, match="stage_threads"):
        Detector(tiny_models, stage_threads=3)


def test_bad_inputs_are_input_errors(detector, frame):
    with pytest.raises(InputError, match="no points"):
        detector.detect(frame.image, np.zeros((0, 4), np.float32), frame.calib)
    with pytest.raises(InputError, match="shape"):
        detector.detect(frame.image, np.zeros((10, 3), np.float32), frame.calib)
    bad = frame.points.copy()
    bad[0, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        detector.detect(frame.image, bad, frame.calib)
    with pytest.raises(InputError, match="smaller than the model's"):
        detector.detect(frame.image[:200], frame.points, frame.calib)
    with pytest.raises(InputError, match="image and calib"):
        detector.detect(None, frame.points, frame.calib)


def test_reflectance_off_kittis_scale_is_refused(detector, frame):
    """0–255 intensities (a VLP-16 driver's) would read as bright returns everywhere: refused, naming the column."""
    intensities = frame.points.copy()
    intensities[:, 3] = np.round(intensities[:, 3] * 255)
    with pytest.raises(InputError, match=r"points: reflectance \(the 4th column\) must lie in \[0, 1\].*255"):
        detector.detect(frame.image, intensities, frame.calib)
    negative = frame.points.copy()
    negative[0, 3] = -0.5
    with pytest.raises(InputError, match="reflectance"):
        detector.detect(frame.image, negative, frame.calib)
    edge = frame.points.copy()
    edge[:, 3] = np.where(edge[:, 3] > 0.5, 1.0, 0.0)  # the ends of the scale are fine
    assert detector.detect(frame.image, edge, frame.calib).boxes.shape[1] == 7


def test_a_scan_in_millimetres_is_warned_about(detector, frame):
    """A driver sending millimetres puts the scan far outside the detection range: no boxes, and a warning that
    says why, which a scan in metres never gets."""
    assert not any("detection range" in w for w in detector.detect(frame.image, frame.points, frame.calib).warnings)
    millimetres = frame.points.copy()
    millimetres[:, :3] *= 1000
    warnings = detector.detect(frame.image, millimetres, frame.calib).warnings
    in_grid = [w for w in warnings if w.startswith("points: almost none lie in the detection range, x 0…")]
    assert len(in_grid) == 1 and in_grid[0].endswith(f"of {frame.points.shape[0]} points)")


def _grey(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


@pytest.mark.parametrize(("make", "given", "hint"), [
    (lambda im: _grey(im), r"uint8 \(374, 1238\)", "one channel"),
    (lambda im: _grey(im)[..., None], r"uint8 \(374, 1238, 1\)", "one channel"),
    (lambda im: cv2.cvtColor(im, cv2.COLOR_RGB2BGRA), r"uint8 \(374, 1238, 4\)", r"drop the alpha channel"),
    (lambda im: im.ravel(), r"uint8 \(1389036,\)", "1-D array"),
    (lambda im: im.astype(np.int64), r"int64 \(374, 1238, 3\)", r"image\.astype\(np\.uint8\)"),
    (lambda im: im.astype(np.float16), r"float16 \(374, 1238, 3\)", "clip"),
    (lambda im: im > 127, r"bool \(374, 1238, 3\)", ""),
    (lambda im: im.astype(np.float32) / 255, r"float32 \(374, 1238, 3\)", r"values 0–1: convert with \(image \* 255\)"),
    (lambda im: im.astype(np.uint16) * 257, r"uint16 \(374, 1238, 3\)", r"16-bit: .*\(image // 257\)\.astype"),
    (lambda im: np.full(im.shape, np.nan, np.float32), r"float32 \(374, 1238, 3\)", "no finite pixel value"),
])
def test_an_image_that_is_not_uint8_rgb_is_refused_saying_what_it_is(detector, frame, make, given, hint):
    """Grey, 4-channel, flat, float, 16-bit or boolean images used to fail inside ONNX Runtime or OpenCV, or to
    run on wrong pixel values (0–1 floats, uint16, NaN gave boxes): refused, naming what was given and, where
    it can be said, how to convert it."""
    lidar16 = emulate_beams(frame.points, 16)
    with pytest.raises(InputError, match=rf"^image: expected uint8 RGB \(H, W, 3\), got {given}.*{hint}"):
        detector.detect(make(frame.image), lidar16, frame.calib, 0.0)


def test_an_image_the_calibration_does_not_fit_is_warned_about(detector, frame):
    """An image resized after calibrating puts P2's principal point outside its middle: the scan projects into
    the wrong pixels. A warning, not an error (exotic cameras exist); KITTI's own frames get none."""
    lidar16 = emulate_beams(frame.points, 16)
    doubled = cv2.resize(frame.image, None, fx=2, fy=2, interpolation=cv2.INTER_LINEAR)
    result = detector.detect(doubled, lidar16, frame.calib, 0.0)
    assert len(result.scores) > 0  # still detected
    (warning,) = [w for w in result.warnings if w.startswith("image and calib")]
    assert warning.startswith("image and calib: P2's principal point (600.4, 181.5) lies outside the middle half "
                              "of the 2476×748 image (x 619…1857, y 187…561)")
    for frame_id in FRAMES:  # 1224–1242 × 370–376 pixels, principal points (600–610, 170–190)
        kitti = load_frame(KITTI, frame_id)
        warnings = detector.detect(kitti.image, emulate_beams(kitti.points, 16), kitti.calib, 0.0).warnings
        assert not [w for w in warnings if w.startswith("image and calib")], (frame_id, warnings)


def _calibration(calib: Calibration, **replace) -> Calibration:
    matrices = {"P2": calib.P2.copy(), "R0_rect": calib.R0_rect.copy(), "Tr_velo_to_cam": calib.Tr_velo_to_cam.copy()}
    return Calibration(**{**matrices, **replace})


def test_a_calibration_built_in_code_is_checked_as_a_file_is(detector, frame):
    """A NaN gave boxes that vanished in to_objects, a zero matrix a LinAlgError, a 3×3 P2 a matmul error, a
    dict an AttributeError: each is an InputError naming calib and the matrix, with parse_calib's checks."""
    lidar16 = emulate_beams(frame.points, 16)
    calib = frame.calib
    cases = [
        (_calibration(calib, P2=calib.P2 * np.nan), r"calib: P2 has a non-finite value"),
        (_calibration(calib, R0_rect=np.full((3, 3), np.inf)), r"calib: R0_rect has a non-finite value"),
        (_calibration(calib, P2=np.zeros((3, 4))), r"calib: P2 is singular"),
        (_calibration(calib, Tr_velo_to_cam=np.zeros((3, 4))), r"calib: Tr_velo_to_cam is singular"),
        (_calibration(calib, P2=calib.P2[:, :3]), r"calib: P2 must be a 3×4 array .*got a float64 array of shape \(3, 3\)"),
        (_calibration(calib, R0_rect=calib.R0_rect.tolist()), r"calib: R0_rect must be a 3×3 array .*got a list"),
        (_calibration(calib, Tr_velo_to_cam=calib.Tr_velo_to_cam.astype(str)), r"calib: Tr_velo_to_cam must be"),
        ({"P2": calib.P2, "R0_rect": calib.R0_rect, "Tr_velo_to_cam": calib.Tr_velo_to_cam},
         r"calib: expected a pipeline\.calib\.Calibration .*got a dict"),
    ]
    for bad, message in cases:
        with pytest.raises(InputError, match=f"^{message}"):
            detector.detect(frame.image, lidar16, bad, 0.0)
    # Checked on every frame: a matrix changed in place after its first frame is seen.
    mine = _calibration(calib)
    detector.detect(frame.image, lidar16, mine, 0.0)
    mine.P2[1, 1] = np.nan
    with pytest.raises(InputError, match="^calib: P2 has a non-finite value"):
        detector.detect(frame.image, lidar16, mine, 0.0)


@pytest.mark.parametrize("dtype", [str, object, np.complex64, bool])
def test_points_that_are_not_real_numbers_are_refused(detector, frame, dtype):
    """Strings and objects failed in np.isfinite with a TypeError, complex points ran (a ComplexWarning, then
    boxes) and booleans were taken for coordinates."""
    points = emulate_beams(frame.points, 16).astype(dtype)
    with pytest.raises(InputError, match=r"^points: expected real numbers .*got (<U\d+|object|complex64|bool) values"):
        detector.detect(frame.image, points, frame.calib, 0.0)


@pytest.mark.parametrize(("options", "message"), [
    ({"emulate_to_beams": "16"}, r"emulate_to_beams: one of 32, 16, 8, 4 lines .*got '16'"),
    ({"emulate_to_beams": 12}, r"emulate_to_beams: one of 32, 16, 8, 4 lines .*got 12"),
    ({"emulate_to_beams": 16.0}, r"emulate_to_beams: .*got 16\.0"),
    ({"emulate_to_beams": True}, r"emulate_to_beams: .*got True"),
    ({"score_threshold": "0.5"}, r"score_threshold: a probability in \[0, 1\] .*got '0\.5'"),
    ({"score_threshold": float("nan")}, r"score_threshold: a probability in \[0, 1\] .*got nan"),
    ({"score_threshold": 1.5}, r"score_threshold: a probability in \[0, 1\] .*got 1\.5"),
    ({"score_threshold": -0.1}, r"score_threshold: .*got -0\.1"),
])
def test_bad_keyword_arguments_are_input_errors_naming_them(detector, frame, options, message):
    """A string beam count raised a TypeError and a string threshold a UFuncTypeError; a NaN threshold gave no
    boxes without a word."""
    with pytest.raises(InputError, match=f"^{message}"):
        detector.detect(frame.image, frame.points, frame.calib, **options)


def test_keyword_arguments_may_be_numpy_numbers(detector, frame):
    """What a caller reads from a NumPy array or a config: NumPy integers and floats are numbers like any other."""
    a = detector.detect(frame.image, frame.points, frame.calib, np.float32(0.25), emulate_to_beams=np.int64(16))
    b = detector.detect(frame.image, frame.points, frame.calib, 0.25, emulate_to_beams=16)
    np.testing.assert_array_equal(a.boxes, b.boxes)


def test_to_objects_takes_the_images_shape(detector, frame):
    """README: ``to_objects(calib, image.shape)`` gives the KITTI objects that format_label writes as lines; a
    size of another length is refused naming image_hw."""
    result = detector.detect(frame.image, emulate_beams(frame.points, 16), frame.calib, 0.0)
    by_size = [format_label(o) for o in result.to_objects(frame.calib, frame.image_hw)]
    assert by_size and [format_label(o) for o in result.to_objects(frame.calib, frame.image.shape)] == by_size
    for bad in [(375,), (1, 375, 1242, 3), 375, (375.0, 1242.0)]:
        with pytest.raises(InputError, match=r"^image_hw: expected \(rows, columns\) or an image's shape"):
            result.to_objects(frame.calib, bad)


def _sorted_boxes(boxes: np.ndarray) -> np.ndarray:
    return boxes[np.lexsort(np.round(boxes[:, :2], 3).T[::-1])]


def test_mirror_tta_averages_the_maps_so_a_mirrored_scene_gives_mirrored_boxes(tiny_models, tmp_path, frame):
    """With mirror_tta the maps of a left-right mirrored BEV are exactly the mirror of the maps (the average of
    the same two runs), so the boxes of the mirrored scan are the boxes mirrored: y and yaw change sign. One
    PIXOR pass alone has no such symmetry, which is what makes the average worth its second run."""
    lidar = lidar_only_models(tiny_models, tmp_path / "lidar")
    grid = PRESETS["tiny"].bev
    points = frame.points.copy()
    # Each y at its cell's centre, so that y → −y lands every point in the mirrored cell: a point on a cell
    # boundary would fall to one side both ways, and the BEVs would differ by a voxel or two.
    points[:, 1] = (np.floor((points[:, 1] - grid.y_min) / grid.cell) + 0.5) * grid.cell + grid.y_min
    mirrored = points.copy()
    mirrored[:, 1] *= -1
    flip = np.array([1, -1, 1, 1, 1, 1, -1])

    def boxes(detector: Detector, scan: np.ndarray) -> np.ndarray:
        return detector.detect(None, scan, None, score_threshold=0.0).boxes

    tta = Detector(lidar, mirror_tta=True)
    assert tta.mirror_tta and not Detector(lidar).mirror_tta
    straight, mirror = boxes(tta, points), boxes(tta, mirrored)
    assert len(straight) > 3 and len(mirror) == len(straight)
    np.testing.assert_allclose(_sorted_boxes(mirror * flip), _sorted_boxes(straight), atol=1e-4)
    plain = Detector(lidar)
    one, other = boxes(plain, points), boxes(plain, mirrored)
    assert len(one) != len(other) or not np.allclose(_sorted_boxes(other * flip), _sorted_boxes(one), atol=1e-4)


def _edited_manifest(tiny_models, tmp_path, edit) -> Path:
    """A copy of the tiny model directory whose manifest went through ``edit`` (its ONNX files untouched)."""
    copy = tmp_path / "edited"
    shutil.copytree(tiny_models, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    edit(manifest)
    (copy / "manifest.json").write_text(json.dumps(manifest))
    return copy


@pytest.mark.parametrize(("edit", "message"), [
    (lambda m: m["networks"]["pixor"].pop("file"), r"networks\.pixor: expected a table with its \"file\""),
    (lambda m: m.update(networks="pixor.onnx"), "networks: expected a table of networks"),
    (lambda m: m["files"]["depth.onnx"].update(sha256=12), r"files\.depth\.onnx: expected"),
    (lambda m: m["networks"]["pixor"].update(training="yes"), r"networks\.pixor\.training: expected a table"),
    (lambda m: m["preset_config"]["bev"].update(cell=0.2), r"preset_config gives pixor input 'bev' the shape"),
    (lambda m: m["preset_config"]["depth"].update(input_hw=[100, 100]), r"depth input 'rgb' the shape \[1, 3, 100, 100\]"),
    (lambda m: m["preset_config"]["bev"].update(cell=0), "preset_config: not a usable grid"),
    (lambda m: m["preset_config"].update(crop_hw=[352]), "preset_config: not a usable grid"),
    # The descriptions other runtimes read must say what runs (a hand edit of one changed nothing here).
    (lambda m: m["bev_grid"].update(x_max=100.0), r"bev_grid\.x_max is 100\.0 where preset_config gives 70\.4"),
    (lambda m: m["normalisation"].update(max_depth=50.0), r"normalisation\.max_depth is 50\.0 where preset_config"),
    (lambda m: m.update(bev_grid=[0, 70.4]), r"bev_grid: expected a table"),
    # A grid moved 10 m back keeps the graphs' shapes: only the description still says where it was.
    (lambda m: m["preset_config"]["bev"].update(x_min=-10.0, x_max=60.4),
     r"bev_grid\.x_min is 0\.0 where preset_config gives -10\.0: this runtime runs preset_config, which bev_grid"),
])
def test_a_broken_manifest_is_refused_at_load_naming_the_field(tiny_models, tmp_path, edit, message):
    broken = _edited_manifest(tiny_models, tmp_path, edit)
    with pytest.raises(ModelFileError, match=message) as caught:
        Detector(broken)
    assert str(broken / "manifest.json") in str(caught.value)


def test_a_given_depth_map_replaces_the_depth_network(detector, frame, tiny_models, tmp_path):
    """A constant 12 m depth map of the whole image puts every pseudo point 12 m in front of the camera."""
    lidar16 = emulate_beams(frame.points, 16)
    depth = np.full(frame.image.shape[:2], 12.0, np.float32)
    result = detector.detect(frame.image, lidar16, frame.calib, 0.0, keep_points=True, depth=depth)
    assert "depth_net" not in result.timings_ms and "prepare" in result.timings_ms
    pseudo = result.points[: len(result.points) - len(lidar16)]  # pseudo points first, then the real ones
    assert len(pseudo) > 1000
    # Depth is camera 2's; the rectified frame is camera 0's, a few millimetres behind along z (P2[2, 3]).
    np.testing.assert_allclose(frame.calib.velo_to_rect(pseudo[:, :3])[:, 2], 12.0, atol=0.005)
    network = detector.detect(frame.image, lidar16, frame.calib, 0.0, keep_points=True)
    assert not np.allclose(frame.calib.velo_to_rect(network.points[:1000, :3])[:, 2], 12.0)

    with pytest.raises(InputError, match="whole image"):
        detector.detect(frame.image, lidar16, frame.calib, depth=depth[:-1])
    with pytest.raises(InputError, match="finite depths"):
        detector.detect(frame.image, lidar16, frame.calib, depth=-depth)

    # The command reads <id>.png from --depth-dir, and names a missing one.
    from pipeline.kitti import write_depth_png

    depth_dir = tmp_path / "depth"
    depth_dir.mkdir()
    write_depth_png(depth_dir / "000006.png", depth)
    command = [sys.executable, "-m", "pipeline.detect", "--models", str(tiny_models), "--data", str(KITTI),
               "--emulate-beams", "16", "--depth-dir", str(depth_dir), "--no-pictures"]
    done = subprocess.run([*command, "--frame", "000006", "--out", str(tmp_path / "a")],
                          capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "a" / "data" / "000006.txt").exists()
    missing = subprocess.run([*command, "--frame", "000003", "--out", str(tmp_path / "b")],
                             capture_output=True, text=True, timeout=300, check=False)
    assert missing.returncode == 1 and str(depth_dir / "000003.png") in missing.stderr
    assert "1 of 1 frame(s) skipped" in missing.stderr and "Traceback" not in missing.stderr


def test_manifest_preset_is_the_code_preset(tiny_models, detector):
    manifest = json.loads((tiny_models / "manifest.json").read_text())
    assert preset_from_dict(manifest["preset_config"]) == PRESETS["tiny"]
    assert detector.preset == PRESETS["tiny"]
    assert list(manifest["bev_grid"]["shape"]) == list(PRESETS["tiny"].bev.shape)


def test_split_model_directory_runs_with_its_own_grid(tmp_path, frame):
    """A ``-split`` export (pseudo points in BEV channels of their own): the manifest carries the grid, the
    Detector builds that BEV and returns well-formed boxes. Without the parity check (10 s of CI): the
    edge-split exports by hand passed it (4e-6)."""
    from export.exporter import ExportConfig, run
    from pipeline.bev import voxelize_bev
    from pipeline.presets import get_preset, lidar_only

    run(ExportConfig(preset="tiny-split", out=tmp_path / "split", parity=False))
    manifest = json.loads((tmp_path / "split" / "manifest.json").read_text())
    preset = get_preset("tiny-split")
    assert preset_from_dict(manifest["preset_config"]) == preset
    assert list(manifest["bev_grid"]["shape"]) == [2 * preset.bev.nz + 1, preset.bev.ny, preset.bev.nx]
    detector = Detector(tmp_path / "split")
    assert detector.preset.bev.split_pseudo
    lidar16 = emulate_beams(frame.points, 16)
    result = detector.detect(frame.image, lidar16, frame.calib, score_threshold=0.0)
    assert set(result.timings_ms) == STAGES and len(result.boxes) > 0
    assert np.isfinite(result.boxes).all() and ((result.scores >= 0) & (result.scores <= 1)).all()
    # The BEV PIXOR read (the calling thread's reused buffer): the scan's own channels, then pseudo points.
    bev = detector._voxelizer()._out
    nz = preset.bev.nz
    np.testing.assert_array_equal(bev[:nz + 1], voxelize_bev(lidar16, lidar_only(preset).bev))
    assert np.count_nonzero(bev[nz + 1:]) > 0 and np.count_nonzero(bev[:nz]) > 0


def test_corrupted_model_file_is_refused(tiny_models, tmp_path):
    broken = tmp_path / "models"
    shutil.copytree(tiny_models, broken)
    data = bytearray((broken / "pixor.onnx").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (broken / "pixor.onnx").write_bytes(bytes(data))
    with pytest.raises(ModelFileError, match=r"pixor\.onnx: sha256 mismatch"):
        Detector(broken)
    (broken / "pixor.onnx").unlink()
    with pytest.raises(ModelFileError, match=r"pixor\.onnx: model file listed in the manifest is missing"):
        Detector(broken)
    with pytest.raises(ModelFileError, match="no manifest"):
        Detector(tmp_path)
    with pytest.raises(ModelFileError, match=r"nowhere: no such model directory \(one holds manifest\.json"):
        Detector(tmp_path / "nowhere")
    (tmp_path / "pixor.onnx").write_bytes(b"")  # a model file given where its directory is meant
    with pytest.raises(ModelFileError, match=r"pixor\.onnx: a file, not a model directory"):
        Detector(tmp_path / "pixor.onnx")


def test_lidar_only_model_directory(tiny_models, tmp_path, frame):
    lidar_only = tmp_path / "lidar"
    lidar_only.mkdir()
    shutil.copy(tiny_models / "pixor.onnx", lidar_only)
    manifest = json.loads((tiny_models / "manifest.json").read_text())
    del manifest["networks"]["depth"]
    manifest["files"] = {"pixor.onnx": {"sha256": sha256_file(lidar_only / "pixor.onnx")}}
    (lidar_only / "manifest.json").write_text(json.dumps(manifest))
    detector = Detector(lidar_only)
    assert not detector.two_stage
    result = detector.detect(None, frame.points, None, 0.0, keep_points=True)
    assert set(result.timings_ms) == {"voxelize", "pixor", "decode", "total"}
    assert result.points.shape == frame.points.shape
    with pytest.raises(InputError, match="no depth network"):
        detector.detect(frame.image, frame.points, frame.calib, depth=np.ones(frame.image.shape[:2], np.float32))


def test_provider_resolution():
    assert resolve_providers("cpu") == ["CPUExecutionProvider"]
    assert resolve_providers(None)[-1] == "CPUExecutionProvider"
    with pytest.raises(InputError, match="not available"):
        resolve_providers("tensorrt")


def test_a_gpu_device_id_goes_to_every_gpu_provider_and_only_there():
    """TensorRT and its CUDA fallback get the same GPU (TensorRT's cache options kept); the CPU takes none."""
    gpu = ["TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"]
    cache = {"trt_engine_cache_enable": True}
    assert session_providers(gpu) == gpu
    assert session_providers(gpu, None, cache) == [("TensorrtExecutionProvider", cache), *gpu[1:]]
    assert session_providers(gpu, 1, cache) == [
        ("TensorrtExecutionProvider", {"trt_engine_cache_enable": True, "device_id": 1}),
        ("CUDAExecutionProvider", {"device_id": 1}), "CPUExecutionProvider"]
    assert cache == {"trt_engine_cache_enable": True}  # the caller's options are not written into
    assert session_providers(gpu[1:], 0) == [("CUDAExecutionProvider", {"device_id": 0}), "CPUExecutionProvider"]
    with pytest.raises(InputError, match="device id 0: the sessions run on CPUExecutionProvider"):
        session_providers(gpu[2:], 0)
    with pytest.raises(InputError, match="count from 0"):
        session_providers(gpu, -1)


def test_sessions_never_fall_back_to_other_devices_behind_the_callers_back(tiny_models):
    """ONNX Runtime's Python layer retries a session whose GPU provider failed on CUDA and the CPU without the
    provider options (the device id, TensorRT's cache), and rebuilds one whose GPU run failed: both are off.
    (No GPU here: the sessions' own flag is what can be read; the message a GPU failure gets is checked below.)"""
    from pipeline.detector import gpu_session_error

    detector = Detector(tiny_models, providers="cpu")
    assert [session._enable_fallback for session in detector._sessions.values()] == [False, False]
    error = RuntimeError("[ONNXRuntimeError] : 1 : FAIL : Invalid device ID 1")
    assert gpu_session_error(Path("m/depth.onnx"), "CUDAExecutionProvider", 1, None, error) == (
        "m/depth.onnx: ONNX Runtime could not create its session with CUDAExecutionProvider on GPU 1 "
        "([ONNXRuntimeError] : 1 : FAIL : Invalid device ID 1); does this box have a GPU 1?")
    text = gpu_session_error(Path("m/pixor.onnx"), "TensorrtExecutionProvider", None,
                             {"trt_engine_cache_path": "/var/cache/x"}, RuntimeError("could not deserialize engine"))
    assert "TensorrtExecutionProvider on GPU 0" in text and "remove the engine cache /var/cache/x" in text


def test_a_device_id_on_the_cpu_provider_is_refused(tiny_models):
    """A GPU id on a CPU-only build would be ignored without a word: refused, naming the id."""
    with pytest.raises(InputError, match="device id 1: .*--provider cuda or tensorrt"):
        Detector(tiny_models, providers="cpu", device_id=1)
    assert Detector(tiny_models, providers="cpu").device_id is None


def test_provider_chain_of_a_gpu_build_keeps_cuda_behind_tensorrt():
    """onnxruntime-gpu's list: TensorRT hands the operators it cannot take to CUDA, not to the CPU."""
    gpu = ["TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"]
    assert resolve_providers(None, gpu) == gpu
    assert resolve_providers("tensorrt", gpu) == gpu
    assert resolve_providers("cuda", gpu) == gpu[1:]
    assert resolve_providers("cpu", gpu) == gpu[2:]
    assert resolve_providers(["tensorrt", "cpu"], gpu) == [gpu[0], gpu[2]]  # a list is taken as given
    assert resolve_providers(None, ["CUDAExecutionProvider", "CPUExecutionProvider"]) == gpu[1:]


def test_a_provider_that_did_not_load_is_found():
    """ONNX Runtime drops a provider whose libraries fail to load and runs on the rest: the Detector compares
    each session's providers with the one it asked for (an error when named, a warning otherwise)."""
    assert provider_fallbacks("CUDAExecutionProvider", {"depth": ["CPUExecutionProvider"],
                                                        "pixor": ["CUDAExecutionProvider", "CPUExecutionProvider"]}) \
        == {"depth": "CPUExecutionProvider"}
    assert provider_fallbacks("CPUExecutionProvider", {"pixor": ["CPUExecutionProvider"]}) == {}


def test_detector_on_the_cpu_provider_has_no_fallback_warning(tiny_models):
    detector = Detector(tiny_models, providers="cpu")
    assert set(detector.providers_in_use) == {"depth", "pixor"}
    assert not any("did not load" in w for w in detector.load_warnings)


def test_a_network_exported_without_trained_weights_is_named_at_load(tiny_models, tmp_path, caplog):
    """An export given only depth.pt (say) ships an initialised PIXOR, which runs and finds nothing real."""
    mixed = tmp_path / "mixed"
    shutil.copytree(tiny_models, mixed)
    manifest = json.loads((mixed / "manifest.json").read_text())
    manifest["networks"]["depth"]["weights"] = "trained"
    (mixed / "manifest.json").write_text(json.dumps(manifest))
    with caplog.at_level("WARNING"):
        (warning,) = Detector(mixed).load_warnings
    assert warning.startswith(f"{mixed}: pixor has initialised (untrained) weights") and warning in caplog.text
    manifest["networks"]["pixor"]["weights"] = "trained"
    (mixed / "manifest.json").write_text(json.dumps(manifest))
    assert Detector(mixed).load_warnings == []


def test_session_threads_stop_spinning_after_each_run():
    """Spinning pool threads after a run took the cores from the NumPy stages (69 ms instead of 43 ms an
    edge frame): sessions may spin within a run only."""
    options = session_options(2)
    assert options.get_session_config_entry("session.intra_op.allow_spinning") == "1"
    assert options.get_session_config_entry("session.force_spinning_stop") == "1"
    assert options.intra_op_num_threads == 2 and options.inter_op_num_threads == 1
    assert session_options().intra_op_num_threads == 0  # ONNX Runtime's default


def test_detect_command_on_bundled_frames(tiny_models, tmp_path):
    out = tmp_path / "out"
    result = subprocess.run(
        [sys.executable, "-m", "pipeline.detect", "--models", str(tiny_models), "--data", str(KITTI),
         "--frame", "000006", "--frame", "000003", "--emulate-beams", "16", "--score-threshold", "0.0",
         "--out", str(out)],
        capture_output=True, text=True, timeout=300, check=False,
    )
    assert result.returncode == 0, result.stderr
    written = sum(len(read_labels(out / "data" / f"{f}.txt")) for f in ("000006", "000003"))
    assert f"2 frame(s), {written} detection(s)" in result.stdout  # what the files hold, not boxes out of view
    for frame_id in ("000006", "000003"):
        objects = read_labels(out / "data" / f"{frame_id}.txt")
        assert all(o.score is not None for o in objects)
        picture = cv2.imread(str(out / "bev" / f"{frame_id}.png"))
        assert picture is not None and picture.shape[2] == 3
        assert (picture == GROUND_TRUTH_BGR).all(axis=2).any()  # the labelled cars drawn (dashed sky blue)
        camera = cv2.imread(str(out / "camera" / f"{frame_id}.png"))  # the image with the boxes as wireframes
        image = cv2.imread(str(KITTI / "image_2" / f"{frame_id}.png"))
        assert camera.shape == image.shape and (camera == GROUND_TRUTH_BGR).all(axis=2).any()
        assert (camera == PREDICTION_BGR).all(axis=2).any() and not (image == PREDICTION_BGR).all(axis=2).any()
    single = subprocess.run(
        [sys.executable, "-m", "pipeline.detect", "--models", str(tiny_models),
         "--image", str(KITTI / "image_2" / "000006.png"), "--points", str(KITTI / "velodyne" / "000006.bin"),
         "--calib", str(KITTI / "calib" / "000006.txt"), "--out", str(tmp_path / "single"), "--no-pictures"],
        capture_output=True, text=True, timeout=300, check=False,
    )
    assert single.returncode == 0, single.stderr
    assert (tmp_path / "single" / "data" / "000006.txt").exists()
    (tmp_path / "empty").mkdir()  # a folder with no model in it (beside --out: one inside it would be refused)
    missing = subprocess.run(
        [sys.executable, "-m", "pipeline.detect", "--models", str(tmp_path / "empty"), "--data", str(KITTI), "--out",
         str(tmp_path / "x")],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert missing.returncode == 2 and "no manifest" in missing.stderr and "Traceback" not in missing.stderr
    # A line count a 64-line scan cannot be thinned to is refused before any model is loaded.
    odd = subprocess.run(
        [sys.executable, "-m", "pipeline.detect", "--models", str(tiny_models), "--data", str(KITTI),
         "--emulate-beams", "7", "--out", str(tmp_path / "odd")],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert odd.returncode == 2 and "--emulate-beams: invalid choice: 7" in odd.stderr and not (tmp_path / "odd").exists()
    (tmp_path / "a-file").write_text("")
    blocked = subprocess.run(
        [sys.executable, "-m", "pipeline.detect", "--models", str(tiny_models), "--data", str(KITTI), "--frame",
         "000006", "--out", str(tmp_path / "a-file" / "out")],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert blocked.returncode == 2 and "Traceback" not in blocked.stderr
    assert f"--out {tmp_path / 'a-file' / 'out'}: {tmp_path / 'a-file'} is a file, not a directory" in blocked.stderr
    # The two ways to name frames do not mix: neither may be silently ignored.
    one_frame = ["--image", str(KITTI / "image_2" / "000006.png"), "--points", str(KITTI / "velodyne" / "000006.bin"),
                 "--calib", str(KITTI / "calib" / "000006.txt")]
    for extra, words in ((["--data", str(KITTI)], "not two of them"), (["--frame", "000003"], "--frame chooses frames of --data")):
        mixed = subprocess.run(
            [sys.executable, "-m", "pipeline.detect", "--models", str(tiny_models), *one_frame, *extra,
             "--out", str(tmp_path / "mixed")], capture_output=True, text=True, timeout=120, check=False,
        )
        assert mixed.returncode == 2 and words in mixed.stderr and "Traceback" not in mixed.stderr
        assert not (tmp_path / "mixed").exists()


def test_detect_command_on_awkward_folders(tiny_models, tmp_path):
    """An empty folder is an error, not a success; a broken label file costs the picture its ground truth
    (with a warning), not the detections; rows with NaN are dropped with a warning, as the service does."""
    empty = tmp_path / "empty"
    (empty / "velodyne").mkdir(parents=True)
    done = subprocess.run([sys.executable, "-m", "pipeline.detect", "--models", str(tiny_models), "--data", str(empty),
                           "--out", str(tmp_path / "o1")], capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 2 and "no frames" in done.stderr and "Traceback" not in done.stderr
    data = tmp_path / "kitti"
    for part, name in (("image_2", "000006.png"), ("calib", "000006.txt"), ("label_2", "000006.txt")):
        (data / part).mkdir(parents=True)
        (data / part / name).write_bytes((KITTI / part / name).read_bytes())
    (data / "label_2" / "000006.txt").write_text("Car 1 2 3\n")
    (data / "velodyne").mkdir()
    points = emulate_beams(load_frame(KITTI, "000006").points, 16)
    points[:7, 0] = np.nan
    points.tofile(data / "velodyne" / "000006.bin")
    done = subprocess.run([sys.executable, "-m", "pipeline.detect", "--models", str(tiny_models), "--data", str(data),
                           "--score-threshold", "0.0", "--out", str(tmp_path / "o2")],
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert "label_2/000006.txt, line 1" in done.stderr and "no ground truth" in done.stderr
    assert "dropped rows with NaN or infinite values (7 rows)" in done.stderr
    assert (tmp_path / "o2" / "data" / "000006.txt").exists() and (tmp_path / "o2" / "bev" / "000006.png").exists()
    # --emulate-beams 0 keeps a 16-line sensor's scans as stored, as in accuracy.py, latency.py and load.py.
    done = subprocess.run([sys.executable, "-m", "pipeline.detect", "--models", str(tiny_models), "--data", str(data),
                           "--score-threshold", "0.0", "--emulate-beams", "0", "--no-pictures",
                           "--out", str(tmp_path / "o0")], capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    kept = (tmp_path / "o0" / "data" / "000006.txt").read_text()
    assert kept and kept == (tmp_path / "o2" / "data" / "000006.txt").read_text()
    # A scan the Detector refuses is named by its frame.
    (data / "velodyne" / "000006.bin").write_bytes(np.zeros((0, 4), np.float32).tobytes())
    done = subprocess.run([sys.executable, "-m", "pipeline.detect", "--models", str(tiny_models), "--data", str(data),
                           "--out", str(tmp_path / "o3")], capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 1 and f"{data}, frame 000006: points: the scan has no points" in done.stderr


def test_detect_command_goes_on_past_a_broken_frame(tiny_models, tmp_path):
    """One unusable file in a folder costs its frame, named with the file, not the rest of the run; a --frame
    without a scan is a mistake in the command, refused before any model is loaded."""
    data = tmp_path / "kitti"
    for part in ("image_2", "velodyne", "calib"):
        (data / part).mkdir(parents=True)
        for fid in ("000003", "000006"):
            suffix = {"image_2": ".png", "velodyne": ".bin", "calib": ".txt"}[part]
            (data / part / f"{fid}{suffix}").write_bytes((KITTI / part / f"{fid}{suffix}").read_bytes())
    (data / "image_2" / "000002.png").write_bytes(b"not an image")  # sorts first: the run must go on past it
    (data / "calib" / "000002.txt").write_bytes((KITTI / "calib" / "000003.txt").read_bytes())
    np.zeros((10, 4), np.float32).tofile(data / "velodyne" / "000002.bin")
    (data / "calib" / "000006.txt").write_text("P2: 1 2 3\n")
    old = {tmp_path / "out" / "data" / "000002.txt": "Car 0 0 0 1 1 2 2 1 1 1 1 1 1 0 0.9\n",
           tmp_path / "out" / "bev" / "000002.png": "not this run's picture"}
    for path, text in old.items():  # an earlier run's outputs for a frame this run skips
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    done = subprocess.run([sys.executable, "-m", "pipeline.detect", "--models", str(tiny_models), "--data", str(data),
                           "--emulate-beams", "16", "--no-pictures", "--out", str(tmp_path / "out")],
                          capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 1 and "Traceback" not in done.stderr
    assert (f"{data / 'image_2' / '000002.png'}: not a readable PNG or JPEG image (frame 000002 skipped; removed its "
            f"result file {tmp_path / 'out' / 'data' / '000002.txt'} and picture ") in done.stderr
    assert not any(path.exists() for path in old)
    assert f"{data / 'calib' / '000006.txt'}" in done.stderr
    assert "2 of 3 frame(s) skipped (each named above with its reason): 000002, 000006" in done.stderr
    assert sorted(p.name for p in (tmp_path / "out" / "data").iterdir()) == ["000003.txt"]
    assert "1 frame(s)" in done.stdout
    # Unknown ids: refused whatever the model directory holds (here none), and nothing is written.
    typo = subprocess.run([sys.executable, "-m", "pipeline.detect", "--models", str(tmp_path / "no-models"),
                           "--data", str(data), "--frame", "000003", "--frame", "3a", "--frame", "000007",
                           "--out", str(tmp_path / "typo")], capture_output=True, text=True, timeout=120, check=False)
    assert typo.returncode == 2 and "Traceback" not in typo.stderr
    assert f"--frame 3a: no scan {data / 'velodyne' / '3a.bin'} (and 1 more --frame without one)" in typo.stderr
    assert not (tmp_path / "typo").exists()
    # A --depth-dir that is not there: one line before any model loads, not every frame skipped in turn.
    nowhere = subprocess.run([sys.executable, "-m", "pipeline.detect", "--models", str(tmp_path / "no-models"),
                              "--data", str(data), "--depth-dir", str(tmp_path / "maps"), "--out", str(tmp_path / "d")],
                             capture_output=True, text=True, timeout=120, check=False)
    assert nowhere.returncode == 2 and f"error: --depth-dir {tmp_path / 'maps'}: directory not found" in nowhere.stderr


def _raw_drive(tmp_path: Path, frames: dict[str, str]) -> Path:
    """A KITTI raw drive as the raw downloads lay it out, made of bundled object frames (new id → object id), with
    the date folder's two calibration files written from frame 000006's calibration."""
    from pipeline.kitti import read_calib

    drive = tmp_path / "2011_09_26" / "2011_09_26_drive_0005_sync"
    (drive / "image_02" / "data").mkdir(parents=True)
    (drive / "velodyne_points" / "data").mkdir(parents=True)
    for new, old in frames.items():
        shutil.copy(KITTI / "image_2" / f"{old}.png", drive / "image_02" / "data" / f"{new}.png")
        shutil.copy(KITTI / "velodyne" / f"{old}.bin", drive / "velodyne_points" / "data" / f"{new}.bin")
    calib = read_calib(KITTI / "calib" / "000006.txt")
    numbers = (lambda a: " ".join(f"{v:.12e}" for v in np.ravel(a)))
    (drive.parent / "calib_cam_to_cam.txt").write_text(
        f"calib_time: 09-Jan-2012 13:57:47\nR_rect_00: {numbers(calib.R0_rect)}\nP_rect_02: {numbers(calib.P2)}\n")
    (drive.parent / "calib_velo_to_cam.txt").write_text(
        f"calib_time: 15-Mar-2012 11:37:16\nR: {numbers(calib.Tr_velo_to_cam[:, :3])}\n"
        f"T: {numbers(calib.Tr_velo_to_cam[:, 3])}\n")
    return drive


def test_detect_command_on_a_raw_drive_with_a_video(tiny_models, tmp_path):
    """--drive reads a KITTI raw drive (frames in image_02/data and velodyne_points/data, the calibration in the
    date folder): each frame's results equal those of the same files as an object frame, a broken scan is
    skipped as in a folder, and --video holds the pictures of the frames detected, in order."""
    drive = _raw_drive(tmp_path, {"0000000000": "000006", "0000000001": "000006", "0000000002": "000006"})
    (drive / "velodyne_points" / "data" / "0000000001.bin").write_bytes(b"\0" * 10)  # cut off mid-point
    command = [sys.executable, "-m", "pipeline.detect", "--models", str(tiny_models), "--emulate-beams", "16",
               "--score-threshold", "0.0"]
    done = subprocess.run([*command, "--drive", str(drive), "--video", str(tmp_path / "bev.mp4"), "--video-fps", "5",
                           "--out", str(tmp_path / "out")], capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 1, done.stderr
    assert f"{drive / 'velodyne_points' / 'data' / '0000000001.bin'}" in done.stderr and "Traceback" not in done.stderr
    assert sorted(p.name for p in (tmp_path / "out" / "data").iterdir()) == ["0000000000.txt", "0000000002.txt"]
    assert f"video: {tmp_path / 'bev.mp4'} (2 frames at 5 a second)" in done.stdout
    as_object = subprocess.run([*command, "--data", str(KITTI), "--frame", "000006", "--no-pictures",
                                "--out", str(tmp_path / "object")], capture_output=True, text=True, timeout=300,
                               check=False)
    assert as_object.returncode == 0, as_object.stderr
    expected = (tmp_path / "object" / "data" / "000006.txt").read_text()
    assert expected and (tmp_path / "out" / "data" / "0000000000.txt").read_text() == expected
    video = cv2.VideoCapture(str(tmp_path / "bev.mp4"))
    bev = cv2.imread(str(tmp_path / "out" / "bev" / "0000000000.png"))
    camera = cv2.imread(str(tmp_path / "out" / "camera" / "0000000000.png"))
    assert video.get(cv2.CAP_PROP_FRAME_COUNT) == 2 and video.get(cv2.CAP_PROP_FPS) == 5
    # Each video frame: the camera view scaled to the BEV picture's width, above the BEV picture (an odd height
    # padded to an even one, as MPEG-4 needs).
    stacked_height = bev.shape[0] + round(camera.shape[0] * bev.shape[1] / camera.shape[1])
    stacked_height += stacked_height % 2
    assert (video.get(cv2.CAP_PROP_FRAME_WIDTH), video.get(cv2.CAP_PROP_FRAME_HEIGHT)) == (bev.shape[1], stacked_height)
    assert not list(tmp_path.glob(".*partial*"))

    # Into the same --out again, one frame and no pictures: what the earlier run left that this one will not
    # replace is named (the other frame's result file, the pictures).
    again = subprocess.run([*command, "--drive", str(drive), "--frame", "0", "--no-pictures", "--out",
                            str(tmp_path / "out")], capture_output=True, text=True, timeout=300, check=False)
    assert again.returncode == 0, again.stderr
    assert f"{tmp_path / 'out' / 'data'} holds 1 result file(s) of frames this run does not detect" in again.stderr
    assert f"{tmp_path / 'out' / 'bev'} and {tmp_path / 'out' / 'camera'} hold(s) pictures of an earlier run" \
        in again.stderr

    # The drive named as "." from inside it, its frame as a plain number; the calibration in the date folder.
    here = subprocess.run([*command, "--drive", ".", "--frame", "2", "--no-pictures", "--out", str(tmp_path / "here")],
                          cwd=drive, capture_output=True, text=True, timeout=300, check=False)
    assert here.returncode == 0, here.stderr
    assert (tmp_path / "here" / "data" / "0000000002.txt").read_text() == expected

    # Every frame skipped: no video; the earlier one under that name is kept, and said to be an earlier run's.
    broken = _raw_drive(tmp_path / "broken", {"0000000000": "000006"})
    (broken / "velodyne_points" / "data" / "0000000000.bin").write_bytes(b"\0" * 10)
    (tmp_path / "old.mp4").write_bytes(b"an earlier run's video")
    none = subprocess.run([*command, "--drive", str(broken), "--video", str(tmp_path / "old.mp4"),
                           "--out", str(tmp_path / "none")], capture_output=True, text=True, timeout=300, check=False)
    assert none.returncode == 1 and (tmp_path / "old.mp4").read_bytes() == b"an earlier run's video"
    assert (f"--video {tmp_path / 'old.mp4'}: no frame was detected, so no video was written; the file there is an "
            "earlier run's") in none.stderr

    # A drive reached through a symbolic link, its calibration in the date folder the user named (the link's
    # parent), not above the real folder; the object folder's frame given as a plain number.
    linked = tmp_path / "links" / "2011_09_26"
    linked.mkdir(parents=True)
    for name in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt"):
        shutil.copy(drive.parent / name, linked / name)
    real = tmp_path / "real" / drive.name
    shutil.copytree(drive, real)
    (linked / "drive").symlink_to(real)
    via_link = subprocess.run([*command, "--drive", str(linked / "drive"), "--frame", "0", "--no-pictures",
                               "--out", str(tmp_path / "link")], capture_output=True, text=True, timeout=300,
                              check=False)
    assert via_link.returncode == 0, via_link.stderr
    assert (tmp_path / "link" / "data" / "0000000000.txt").read_text() == expected
    numbered = subprocess.run([*command, "--data", str(KITTI), "--frame", "6", "--no-pictures", "--out",
                               str(tmp_path / "numbered")], capture_output=True, text=True, timeout=300, check=False)
    assert numbered.returncode == 0 and (tmp_path / "numbered" / "data" / "000006.txt").read_text() == expected

    # Refused before any model loads (there is none here): no calibration, not a drive, a wrong video name.
    (tmp_path / "2011_09_26" / "2011_09_26_drive_0009_sync" / "velodyne_points" / "data").mkdir(parents=True)
    shutil.rmtree(broken / "image_02")
    (drive.parent / "calib_velo_to_cam.txt").unlink()
    (tmp_path / "a-file").write_text("")
    for args, message in (
        (["--drive", str(drive)], f"{drive}: no calib_velo_to_cam.txt in it or in {drive.parent}"),
        (["--data", str(KITTI), "--video", str(tmp_path / "a-file" / "v.mp4")],
         f"--video {tmp_path / 'a-file' / 'v.mp4'}: cannot create files in {tmp_path / 'a-file'}"),
        (["--drive", str(tmp_path)], f"{tmp_path}: not a KITTI raw drive folder (no velodyne_points/data/ inside)"),
        (["--data", str(KITTI), "--video", str(tmp_path / "bev.avi")],
         f"--video {tmp_path / 'bev.avi'}: give a file name ending in .mp4"),
        (["--data", str(KITTI), "--video", str(tmp_path / "v.mp4"), "--no-pictures"],
         "--video is made of the pictures"),
        (["--data", str(KITTI), "--drive", str(drive)], "give one of --data DIR, --drive DIR"),
        (["--drive", str(drive.parent)], "the drives in it: 2011_09_26_drive_0005_sync, 2011_09_26_drive_0009_sync"),
        (["--drive", str(broken)], f"{broken}: no image_02/data/ (the left colour camera's images) inside"),
        (["--drive", str(drive), "--frame", "0", "--frame", "0000000000"], "--frame 0000000000 given twice"),
        (["--data", str(KITTI), "--video", str(tmp_path / "v.mp4"), "--video-fps", "0"],
         "--video-fps: must be from 0.1 to 1000 frames a second, got 0"),
        (["--data", str(KITTI), "--video-fps", "5"], "--video-fps sets the frame rate of --video"),
        (["--data", str(KITTI), "--out", str(tmp_path / "a-file")],
         f"--out {tmp_path / 'a-file'}: exists and is not a directory"),  # the last --out is the one taken
    ):
        refused = subprocess.run([sys.executable, "-m", "pipeline.detect", "--models", str(tmp_path / "no-models"),
                                  "--out", str(tmp_path / "refused"), *args], capture_output=True, text=True,
                                 timeout=120, check=False)
        assert refused.returncode == 2 and message in refused.stderr, (args, refused.stderr)
        assert "Traceback" not in refused.stderr and not (tmp_path / "refused").exists()


def test_a_stopped_run_says_so_and_leaves_no_partial_video(tiny_models, tmp_path):
    """SIGTERM (as a supervisor stops a run; Ctrl-C is the same, exit 130) mid-drive: one line saying what is
    kept, exit 143, the frames done keep their files, no hidden partial video, the earlier video kept."""
    drive = _raw_drive(tmp_path, {"0000000000": "000006"})
    for index in range(1, 400):  # a long drive of the same frame, linked rather than copied
        for folder, suffix in (("image_02", ".png"), ("velodyne_points", ".bin")):
            (drive / folder / "data" / f"{index:010d}{suffix}").symlink_to(drive / folder / "data" / f"0000000000{suffix}")
    (tmp_path / "run.mp4").write_bytes(b"an earlier run's video")
    run = subprocess.Popen([sys.executable, "-m", "pipeline.detect", "--models", str(tiny_models), "--drive",
                            str(drive), "--video", str(tmp_path / "run.mp4"), "--out", str(tmp_path / "out")],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not (tmp_path / "out" / "data" / "0000000001.txt").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    run.send_signal(signal.SIGTERM)
    _, stderr = run.communicate(timeout=120)
    assert run.returncode == 128 + signal.SIGTERM, stderr[-2000:]
    assert f"terminated: the frames detected so far have their files in {tmp_path / 'out'}; no video was written " \
           "(the earlier one is kept)" in stderr and "Traceback" not in stderr
    assert (tmp_path / "run.mp4").read_bytes() == b"an earlier run's video" and not list(tmp_path.glob(".*partial*"))
    done = len(list((tmp_path / "out" / "data").glob("*.txt")))
    assert 2 <= done < 400


def test_a_video_that_fails_half_way_leaves_nothing_under_its_name(tmp_path):
    """A video is written to a hidden file of this process and renamed at the end: discarded, it leaves the
    earlier video under the name as it was. A picture of another size is fitted into the first one's."""
    from pipeline.render import FrameVideo, fit_into

    path = tmp_path / "bev.mp4"
    path.write_bytes(b"an earlier video")
    video = FrameVideo(path)
    video.add(np.zeros((64, 48, 3), np.uint8))
    video.add(np.full((64, 40, 3), 200, np.uint8))  # an image of another size above the BEV
    assert video.frames == 2 and [p.name for p in tmp_path.glob(".bev.*.partial.mp4")] == [
        f".bev.{os.getpid()}.partial.mp4"]
    video.discard()
    assert path.read_bytes() == b"an earlier video" and sorted(p.name for p in tmp_path.iterdir()) == ["bev.mp4"]
    assert FrameVideo(tmp_path / "none.mp4").close() is False and not (tmp_path / "none.mp4").exists()
    # Fitted: scaled to fit, centred on black, the first size kept.
    fitted = fit_into(np.full((20, 40, 3), 255, np.uint8), (40, 40))
    assert fitted.shape == (40, 40, 3) and fitted[10:30].min() == 255 and fitted[:10].max() == fitted[30:].max() == 0


def test_a_picture_that_cannot_be_written_is_an_error_naming_it(tiny_models, tmp_path):
    """cv2.imwrite only answers False: the command must not claim pictures it did not write."""
    blocked = tmp_path / "out" / "bev" / "000006.png"
    blocked.mkdir(parents=True)  # a directory where the picture goes
    done = subprocess.run([sys.executable, "-m", "pipeline.detect", "--models", str(tiny_models),
                           "--image", str(KITTI / "image_2" / "000006.png"), "--points", str(KITTI / "velodyne" / "000006.bin"),
                           "--calib", str(KITTI / "calib" / "000006.txt"), "--out", str(tmp_path / "out")],
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 2 and "Traceback" not in done.stderr and "pictures:" not in done.stdout
    assert f"error: --out {tmp_path / 'out'}: {blocked}: could not write the PNG" in done.stderr


def test_one_set_of_files_names_the_file_of_the_field_at_fault(tiny_models, tmp_path):
    """With --image/--points/--calib, an image the model cannot use is blamed on the image file, not the scan."""
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((50, 50, 3), np.uint8))
    done = subprocess.run([sys.executable, "-m", "pipeline.detect", "--models", str(tiny_models), "--image", str(small),
                           "--points", str(KITTI / "velodyne" / "000006.bin"), "--calib", str(KITTI / "calib" / "000006.txt"),
                           "--out", str(tmp_path / "out")], capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert f"error: {small}: image: 50×50 pixels is smaller than" in done.stderr and "000006.bin" not in done.stderr


def test_pictures_survive_boxes_far_off_the_grid():
    """A box no pixel can hold (a broken scan can make one) is left out of the picture, not an OpenCV error."""
    from pipeline.render import render_bev

    grid = PRESETS["tiny"].bev
    boxes = np.array([[1e25, 3, 0, 4, 1.7, 1.5, 0.3], [10, 0, -1, 4, 1.7, 1.5, 0.3], [np.nan, 0, 0, 4, 1.7, 1.5, 0]])
    picture = render_bev(np.zeros((3, 4), np.float32), grid, boxes, np.array([1.0, 0.9, 0.5]), boxes)
    drawn = (picture == PREDICTION_BGR).all(axis=2)
    assert drawn.any() and picture.shape[:2] == (round((grid.x_max - grid.x_min) / 0.1), round((grid.y_max - grid.y_min) / 0.1))


def test_camera_picture_draws_each_box_where_its_corners_project(frame):
    """The wireframe's corners are the 3D corners projected through the calibration; a box reaching behind the
    camera (a car beside it) is cut at the near plane, not dropped; a box wholly behind it, far off or not
    finite is left out, not an OpenCV error."""
    from pipeline.boxes import box_corners_3d
    from pipeline.render import render_camera

    ahead = np.array([[15, 2, -0.9, 4, 1.7, 1.5, 0.3]])
    away = np.array([[-10, 0, -0.9, 4, 1.7, 1.5, 0.0], [1e25, 3, 0, 4, 1.7, 1.5, 0.3], [np.nan, 0, 0, 4, 1.7, 1.5, 0]])
    beside = np.array([[1.0, -3.0, -0.9, 4.5, 1.8, 1.5, 0.0]])  # from 1.25 m behind the LiDAR to 3.25 m ahead
    orange = (lambda boxes: (render_camera(frame.image, frame.calib, boxes, np.full(len(boxes), 0.9))
                             == PREDICTION_BGR).all(axis=2))
    picture = render_camera(frame.image, frame.calib, np.vstack([ahead, away]), np.array([0.9, 0.8, 0.7, 0.6]))
    assert picture.shape == frame.image.shape and picture.dtype == np.uint8
    np.testing.assert_array_equal((picture == PREDICTION_BGR).all(axis=2), orange(ahead))  # the others: nothing
    drawn = orange(ahead)
    uv, _ = frame.calib.velo_to_image(box_corners_3d(ahead).reshape(-1, 3))
    for u, v in np.rint(uv).astype(int):  # every corner of the box in view is drawn on
        assert drawn[max(v - 1, 0):v + 2, max(u - 1, 0):u + 2].any()
    left, top = uv.min(axis=0)
    right, bottom = uv.max(axis=0)
    rows, cols = np.nonzero(drawn)  # nothing orange outside the box (its score label sits just above it)
    assert rows.min() >= top - 20 and rows.max() <= bottom + 2 and cols.min() >= left - 2 and cols.max() <= right + 40
    corners_z = frame.calib.velo_to_rect(box_corners_3d(beside).reshape(-1, 3))[:, 2]
    assert (corners_z < 0).any() and (corners_z > 0).any()  # the car beside reaches behind the camera
    side = orange(beside)
    assert side.sum() > 500 and np.nonzero(side)[1].min() > frame.image.shape[1] // 2  # drawn, on the right (y < 0)


def test_camera_picture_drawn_at_a_scale_keeps_its_lines_and_scores_in_pixels(frame):
    """A video's camera view is drawn after the image is scaled: the corners land at their projections times
    the scale, and the score label is as many pixels tall as in the full-size picture."""
    from pipeline.boxes import box_corners_3d
    from pipeline.render import render_camera

    ahead = np.array([[15, 2, -0.9, 4, 1.7, 1.5, 0.3]])
    black = np.zeros_like(frame.image)
    uv, _ = frame.calib.velo_to_image(box_corners_3d(ahead).reshape(-1, 3))
    label_rows = {}
    for scale in (1.0, 0.5):
        picture = render_camera(black, frame.calib, ahead, np.array([0.9]), scale=scale)
        assert picture.shape[:2] == (round(black.shape[0] * scale), round(black.shape[1] * scale))
        drawn = (picture == PREDICTION_BGR).all(axis=2)
        for u, v in np.rint(uv * scale).astype(int):  # each corner, where it projects in the scaled picture
            assert drawn[max(v - 1, 0):v + 2, max(u - 1, 0):u + 2].any()
        rows = np.nonzero(drawn.any(axis=1))[0]
        label_rows[scale] = int((rows < uv[:, 1].min() * scale - 1).sum())  # orange rows above the box: the label
    assert label_rows[1.0] >= 8 and abs(label_rows[0.5] - label_rows[1.0]) <= 1


def test_depth_colours_keep_far_depth_apart_from_no_depth():
    """The depth pictures colour 35 m and 70 m apart, and the farthest depth stays visibly apart from black
    (no depth): the accuracy harness's panels once clipped at the preset's 35 m, where the colour map's end
    is nearly black."""
    from pipeline.render import render_depth

    colours = render_depth(np.array([[0.0, 10.0, 35.0, 70.0, 500.0]]))[0].astype(int)
    assert (colours[0] == 0).all()
    assert all(colour.max() >= 120 for colour in colours[1:])  # bright enough not to read as black
    assert np.abs(colours[2] - colours[3]).sum() > 100 and np.abs(colours[1] - colours[2]).sum() > 100


def test_runtime_never_imports_torch_or_onnx():
    """The service container carries neither: torch is for training, the onnx package for export and the
    benchmarks' peak micro-benchmark (requirements/service-*.txt leave it out)."""
    code = (
        "import sys; sys.modules['torch'] = None; sys.modules['onnx'] = None\n"
        "import pipeline.detector, pipeline.detect, pipeline.demo, pipeline.beams, pipeline.bev\n"
        "import service.app, service.__main__\n"
        "loaded = [m for m in sys.modules if sys.modules[m] is not None]\n"
        "assert not [m for m in loaded if m.split('.')[0] in ('torch', 'onnx')], loaded\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 0, result.stderr


def test_tensorrt_engines_are_cached_per_model_and_fp16_asks_for_fp16(tmp_path):
    """ONNX Runtime's TensorRT provider would run a cached engine of old weights under the same file name:
    each model's engines get a folder named by its files' sha256s. An FP16 directory sets the FP16 flag."""
    import copy
    import json

    import onnxruntime

    from pipeline.detector import tensorrt_options

    fp32 = json.loads((Path(__file__).resolve().parents[1] / "weights" / "edge" / "manifest.json").read_text())
    options = tensorrt_options(fp32, tmp_path / "cache")
    cache = Path(options["trt_engine_cache_path"])
    assert cache.is_dir() and cache.parent == tmp_path / "cache" and options["trt_timing_cache_path"] == str(cache)
    assert cache.name.startswith("edge-split-near35-fp32-") and options["trt_fp16_enable"] is False
    # Another ONNX Runtime or TensorRT release builds its own engines (no TensorRT library here).
    assert cache.name.endswith(f"-ort{onnxruntime.__version__}-trtnone")
    retrained = copy.deepcopy(fp32)
    retrained["files"]["pixor.onnx"]["sha256"] = "0" * 64
    assert tensorrt_options(retrained, tmp_path / "cache")["trt_engine_cache_path"] != str(cache)
    fp16 = {**fp32, "precision": "fp16"}
    assert tensorrt_options(fp16, tmp_path / "cache")["trt_fp16_enable"] is True
    (tmp_path / "file").write_text("not a folder")
    with pytest.raises(InputError, match="--trt-cache-dir .*file: cannot create the TensorRT engine cache"):
        tensorrt_options(fp32, tmp_path / "file")


def test_the_points_kept_for_pictures_say_how_many_are_the_cameras(detector, frame):
    """Detections.pseudo_count: the pictures split the scan from the pseudo points by it (they thinned the scan a
    second time and compared, about 9 ms a picture, and drew everything in the scan's grey when that missed)."""
    lidar16 = emulate_beams(frame.points, 16)
    result = detector.detect(frame.image, lidar16, frame.calib, keep_points=True)
    assert 1000 < result.pseudo_count < len(result.points)
    np.testing.assert_array_equal(result.points[result.pseudo_count:], lidar16)
    scan, pseudo = split_scan_and_pseudo(result.points, result.pseudo_count)
    assert scan.shape == lidar16.shape and pseudo is not None and len(pseudo) == result.pseudo_count
    lidar_only = Detector(Path(__file__).resolve().parents[1] / "weights" / "edge-lidar16").detect(None, lidar16, None, keep_points=True)
    assert lidar_only.pseudo_count == 0 and split_scan_and_pseudo(lidar_only.points, 0)[1] is None
    np.testing.assert_array_equal(lidar_only.points, lidar16)
