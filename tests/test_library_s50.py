"""lowres3d used as a library from a node of one's own (README, "In your own code"): a LiDAR→camera transform in
the wrong frame, direction or unit is warned of, and the refusals a node meets first say what to do.

Real KITTI frames (tests/data) through the shipped ``weights/edge`` in ONNX Runtime; the wrong transforms are
those a node builds by mistake from its tf tree: into the camera's body frame, the inverse, millimetres.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from pipeline.beams import emulate_beams
from pipeline.calib import Calibration
from pipeline.checks import WarningCode
from pipeline.detector import Detections, Detector, resolve_providers
from pipeline.errors import InputError
from pipeline.frame import Frame, load_frame
from tests.conftest import KITTI

WEIGHTS = Path(__file__).resolve().parents[1] / "weights"
FRAMES = ("000000", "000001", "000003", "000004", "000006")
# Optical frame (x right, y down, z forward) → the camera body's (x forward, y left, z up), as tf names them.
OPTICAL_TO_BODY = np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]], float)


def _homogeneous(calib: Calibration) -> np.ndarray:
    return np.vstack([calib.Tr_velo_to_cam, [0.0, 0.0, 0.0, 1.0]])


def _millimetres(transform: np.ndarray) -> np.ndarray:
    scaled = transform.copy()
    scaled[:3, 3] *= 1000.0
    return scaled


WRONG_TRANSFORMS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "camera body frame": lambda t: OPTICAL_TO_BODY @ t,
    "inverted (camera to LiDAR)": np.linalg.inv,
    "translation in millimetres": _millimetres,
}


@pytest.fixture(scope="module")
def edge() -> Iterator[Detector]:
    with Detector(WEIGHTS / "edge") as detector:
        yield detector


@pytest.fixture(scope="module")
def frames() -> dict[str, Frame]:
    return {frame_id: load_frame(KITTI, frame_id) for frame_id in FRAMES}


def _misfits(result: Detections) -> list[str]:
    return [w for w, code in zip(result.warnings, result.warning_codes) if code == WarningCode.CALIBRATION_MISFIT]


@pytest.mark.parametrize("wrong", list(WRONG_TRANSFORMS))
@pytest.mark.parametrize("stage_threads", [1, 2])
def test_a_transform_in_the_wrong_frame_direction_or_unit_is_warned_of(frames, wrong: str, stage_threads: int):
    """Each mistake put (almost) none of 000006's returns ahead into the image, changed the boxes (3 → 4) and was
    warned of only as beams_emulated: now ``calibration_misfit`` says what to check, on either thread layout."""
    frame = frames["000006"]
    calib = Calibration.from_matrices(frame.calib.P2, frame.calib.R0_rect,
                                      WRONG_TRANSFORMS[wrong](_homogeneous(frame.calib)))
    with Detector(WEIGHTS / "edge", stage_threads=stage_threads) as detector:
        result = detector.detect(frame.image, frame.points, calib, emulate_to_beams=16)
    (warning,) = _misfits(result)
    assert warning.startswith("calib: ") and "of the scan's returns ahead project into the image" in warning
    for what in ("LiDAR → camera", "optical frame (x right, y down, z forward", "metres"):
        assert what in warning, (what, warning)


@pytest.mark.parametrize("frame_id", FRAMES)
def test_correct_frames_get_no_calibration_warning(edge: Detector, frames, frame_id: str):
    """The five KITTI frames, as 64 lines thinned to 16 and as a forward-only sensor would give them (only the
    returns the camera sees), carry no calibration warning: 53 % of their returns ahead or more land in the image."""
    frame = frames[frame_id]
    lidar16 = emulate_beams(frame.points, 16)
    assert _misfits(edge.detect(frame.image, lidar16, frame.calib)) == []
    uv, depth = frame.calib.velo_to_image(lidar16)
    height, width = frame.image.shape[:2]
    seen = (depth > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] < width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] < height - 1)
    assert 0 < np.count_nonzero(seen) < seen.size  # a 360° scan: some of its returns in view, not all
    assert _misfits(edge.detect(frame.image, lidar16[seen], frame.calib)) == []


def test_a_provider_is_named_as_both_its_callers_give_it():
    """Detector(..., providers="gpu") said "--provider: gpu is not available": a library caller gave providers=."""
    with pytest.raises(InputError) as raised:
        resolve_providers("gpu")
    assert str(raised.value).startswith("provider 'gpu' (providers=, --provider): not available in this ONNX "
                                        "Runtime build (available: ")


def test_nan_rows_are_refused_with_a_hint_that_works(edge: Detector, frames):
    """The hint named pipeline.kitti.parse_velodyne, which takes a file's bytes; the one-liner given now is run as
    it stands on the refused scan, which then detects."""
    frame = frames["000006"]
    points = emulate_beams(frame.points, 16)
    points[10, 0], points[20, 2] = np.nan, np.inf
    with pytest.raises(InputError) as raised:
        edge.detect(frame.image, points, frame.calib)
    message = str(raised.value)
    hint = "points[np.isfinite(points).all(axis=1)]"
    assert message.startswith("points: NaN or infinite values") and message.endswith(hint)
    kept = eval(hint, {"np": np, "points": points})  # the message's own code, as a user pastes it
    assert kept.shape[0] == points.shape[0] - 2
    assert edge.detect(frame.image, kept, frame.calib).boxes.shape[1] == 7


def test_a_ring_column_is_refused_with_the_slice_that_keeps_four(edge: Detector, frames):
    """An (N, 5) cloud with a ring column got the shape alone; now the message gives ``points[:, :4]``, which the
    Detector then takes."""
    frame = frames["000006"]
    lidar16 = emulate_beams(frame.points, 16)
    ring = np.random.default_rng(0).integers(0, 16, (lidar16.shape[0], 1)).astype(np.float32)
    with_ring = np.hstack([lidar16, ring])
    with pytest.raises(InputError) as raised:
        edge.detect(frame.image, with_ring, frame.calib)
    message = str(raised.value)
    assert message.startswith(f"points: expected shape (N, 4) x, y, z, reflectance; got {with_ring.shape}")
    assert message.endswith("points[:, :4]")
    assert np.array_equal(edge.detect(frame.image, with_ring[:, :4], frame.calib).boxes,
                          edge.detect(frame.image, lidar16, frame.calib).boxes)


def test_sessions_run_without_onnx_runtimes_fallback_even_where_it_ignores_enable_fallback(monkeypatch) -> None:
    """ONNX Runtime 1.22 (the GPU image's pin) sets the run-time fallback on in ``InferenceSession.__init__``
    whatever ``enable_fallback`` says, so a failed GPU run would rebuild the session on the CPU for good. That
    version cannot be installed beside this one: its ``__init__``'s behaviour is stood in for by turning the flag
    back on after the real one, and the Detector's sessions must still have it off."""
    import onnxruntime as ort

    real_init = ort.InferenceSession.__init__

    def as_in_1_22(self, *args, **kwargs) -> None:
        real_init(self, *args, **kwargs)
        self._enable_fallback = True

    monkeypatch.setattr(ort.InferenceSession, "__init__", as_in_1_22)
    with Detector(WEIGHTS / "edge", providers="cpu") as detector:
        assert detector._sessions and not any(s._enable_fallback for s in detector._sessions.values())
