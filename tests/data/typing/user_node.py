"""A user's typed code against lowres3d's public API, as README.md's "In your own code" and "Your own vehicle" use it.

tests/test_typing.py checks it with ``mypy --strict`` (the library read as an installed package is: its own
errors silenced, its annotations taken as the truth) and runs it on weights/edge and a KITTI sample, so what it
passes the library is what the library takes. An annotation that is wrong for what a function takes or gives (a
missing None, a parameter typed narrower than what it accepts) fails the check.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from pipeline.beams import emulate_beams
from pipeline.boxes import BoxRecord, labels_to_boxes
from pipeline.calib import Calibration
from pipeline.checks import WarningCode, check_stamp, coded, sensor_skew
from pipeline.detector import Detections, Detector
from pipeline.errors import InputError
from pipeline.frame import Frame, load_frame
from pipeline.kitti import (
    Object3D,
    Scan,
    format_label,
    read_calib,
    read_image,
    read_labels,
    read_velodyne,
    write_labels,
)
from pipeline.preprocess import scale_calibration


def detect_file(detector: Detector, frame: str) -> Detections:
    """README's example: one KITTI frame's files, its 64-line scan thinned to 16 lines."""
    image: npt.NDArray[np.uint8] = read_image(frame.format("image_2", "png"))
    scan: Scan = read_velodyne(frame.format("velodyne", "bin"))
    calib: Calibration = read_calib(frame.format("calib", "txt"))
    result = detector.detect(image, scan.points, calib, emulate_to_beams=16)
    for (x, y, _z, _length, _width, _height, yaw), score in zip(result.boxes, result.scores):
        print(f"car {score:.2f}: x {x:.1f} m, y {y:.1f} m, yaw {yaw:.2f} rad")
    total: float = result.timings_ms["total"]
    print(f"{total:.0f} ms", result.warnings, result.warning_codes)
    lines: list[str] = [format_label(o) for o in result.to_objects(calib, image.shape)]
    print("\n".join(lines))
    return result


def keep_confident(objects: Sequence[Object3D], path: Path, calib: Calibration) -> npt.NDArray[np.float64]:
    """A result file of the confident boxes alone, read back as LiDAR-frame boxes (a generator and a tuple are
    as good as lists to the library)."""
    write_labels(path, (o for o in objects if o.score is not None and o.score > 0.5))
    return labels_to_boxes(tuple(read_labels(path)), calib)


def to_message(record: BoxRecord) -> tuple[tuple[float, float, float], tuple[float, ...], tuple[float, float, float]]:
    """A vision_msgs/Detection3D's centre, orientation and size from one record."""
    return (record.x, record.y, record.z), record.quaternion_xyzw, (record.length, record.width, record.height)


def calibration_from_camera_info(p: Sequence[float], r: Sequence[float],
                                 lidar_to_optical: npt.NDArray[np.float64]) -> Calibration | None:
    """CameraInfo.p (12 numbers) and .r (9) with the TF transform; None (the node logs why) when unusable."""
    try:
        return Calibration.from_matrices(list(p), list(r), lidar_to_optical)
    except InputError as refused:
        print(refused)
        return None


def reframed(image: npt.NDArray[np.uint8], calib: Calibration) -> tuple[npt.NDArray[np.uint8], Calibration]:
    """README's "a camera framed otherwise", the calibration following each step."""
    scale = max(721.5 / float(calib.P2[0, 0]), 1216 / image.shape[1])
    resized = np.asarray(cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA), np.uint8)
    calib = scale_calibration(calib, scale)
    top = max(0, min(round(float(calib.P2[1, 2])) - 173, resized.shape[0] - 375))
    return resized[top:top + 375], calib.shifted(0, top)


def stamps_apart(image_sec: int, image_nanosec: int, scan_ns: object) -> list[str]:
    """The capture-time check a library user makes, as README's "Your own vehicle" shows it."""
    image_ns = image_sec * 1_000_000_000 + image_nanosec
    warnings = coded((WarningCode.SENSOR_SKEW, sensor_skew(image_ns, check_stamp(scan_ns, "scan_ns"))))
    return [f"{warning.code}: {warning.message}" for warning in warnings]


def node(models: Path, data: Path, out: Path) -> list[BoxRecord]:
    """A ROS 2 node's life on one KITTI frame: a Detector sized to its share of the cores, the frame from files,
    from a loaded Frame (a driver's float64 rows, read-only) and reframed, then closed. Returns the boxes."""
    with Detector(models, intra_op_threads=2, stage_threads=1) as detector:
        result = detect_file(detector, str(data / "{}" / "000006.{}"))
        records = result.as_records()
        print([to_message(record) for record in records])
        frame: Frame = load_frame(data, "000006")
        if frame.image is None:
            raise SystemExit("loaded without its image")
        points: npt.NDArray[np.float32] = emulate_beams(frame.points, 16)
        rows = np.hstack([points, np.zeros((len(points), 1), np.float32)]).astype(np.float64)
        read_only = rows[:, :4]
        read_only.flags.writeable = False
        again = detector.detect(frame.image, read_only, frame.calib, score_threshold=0.5, keep_points=True)
        seen: npt.NDArray[np.float32] | None = again.points
        print(None if seen is None else seen.shape, detector.trained_lines, detector.load_warnings)
        print(keep_confident(again.to_objects(frame.calib, frame.image.shape), out / "000006.txt", frame.calib))
        image, calib = reframed(frame.image, frame.calib)
        print(detector.detect(image, points, calib).scores)
    calib_again = calibration_from_camera_info(frame.calib.P2.ravel().tolist(), frame.calib.R0_rect.ravel().tolist(),
                                               frame.calib.Tr_velo_to_cam)
    print(calib_again, stamps_apart(1718000000, 50_000_000, 1718000000_000_000_000))
    standalone = Detector(models, providers=("CPUExecutionProvider",), mirror_tta=True)
    try:
        print(standalone.sha256, standalone.providers_in_use)
    finally:
        standalone.close()
    return records
