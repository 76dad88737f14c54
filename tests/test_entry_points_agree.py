"""Every way of running lowres3d on a frame gives the same answer, run after run.

The entry points: the library (``Detector.detect`` + ``format_label``), the CLI (``pipeline.detect``),
``benchmarks/accuracy.py``'s result files, ``pipeline.demo`` and the service over loopback (JSON boxes and
``format=kitti``), for the same score threshold and the same scan lines. The settings that must change no
number: ONNX Runtime's intra-op threads and the stage threads (fp32 and INT8; with ONNX Runtime 1.32 the
networks' outputs were bit-identical from 1 to 8 threads), the service's workers and
per-worker sessions, a scan thinned beforehand by ``pipeline.beams`` against ``--emulate-beams``, and PNG against
JPEG decoding (a JPEG's own pixels differ from the PNG's, and so do its boxes: that is the codec, not the path).

On the shipped ``weights/edge`` (and ``edge-int8``, ``edge-lidar64``), real KITTI frames of tests/data and one
synthetic frame with a calibration of its own.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest

from pipeline.detector import Detections, Detector
from pipeline.frame import load_frame
from pipeline.kitti import format_label, read_calib, read_image
from tests.conftest import KITTI
from tests.test_service_process import running_service

REPO = Path(__file__).resolve().parents[1]
WEIGHTS = REPO / "weights"
EDGE = WEIGHTS / "edge"
# Low enough that each frame writes 50-70 lines (the default 0.5 writes 1-6): more boxes to disagree on.
LOW_SCORE = 0.05
KITTI_FRAMES = ["000003", "000006"]
BOX_FIELDS = ("x", "y", "z", "l", "w", "h", "yaw")


@pytest.fixture(scope="module")
def sim_data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A KITTI-layout folder with one synthetic validation frame (000000; its own calibration, 1224 columns)."""
    from simulation.run import RunConfig, run

    out = tmp_path_factory.mktemp("sim")
    run(RunConfig(out, frames=1, seed=2, start=0, split="val", progress=False))
    return out


def library(models: Path, data: Path, frame_id: str, threshold: float | None, beams: int | None,
            **options: object) -> tuple[str, Detections]:
    """The README's library use on one frame: the KITTI result file's text and the detections."""
    frame = load_frame(data, frame_id, with_labels=False)
    with Detector(models, **options) as detector:
        result = detector.detect(frame.image, frame.points, frame.calib, threshold, beams)
    return "".join(format_label(o) + "\n" for o in result.to_objects(frame.calib, frame.image.shape)), result


def cli(models: Path, data: Path, out: Path, frame_ids: list[str], *flags: str) -> dict[str, bytes]:
    """``python -m pipeline.detect`` (its main, in this process) on frames of ``data``: each result file's bytes."""
    from pipeline.detect import main

    argv = ["--models", str(models), "--data", str(data), "--out", str(out), "--no-pictures", "--no-progress"]
    assert main([*argv, *(a for fid in frame_ids for a in ("--frame", fid)), *flags]) == 0
    return {fid: (out / "data" / f"{fid}.txt").read_bytes() for fid in frame_ids}


def test_the_cli_writes_the_librarys_lines_byte_for_byte_twice(sim_data: Path, tmp_path: Path) -> None:
    """(a) and (b): two CLI runs write the same bytes, and they are the library's lines, with the library run
    on one intra-op thread and no stage thread, the CLI on the defaults (a pool per core, a stage thread)."""
    for data, frame_ids in ((KITTI, KITTI_FRAMES), (sim_data, ["000000"])):
        flags = ("--emulate-beams", "16", "--score-threshold", str(LOW_SCORE))
        first = cli(EDGE, data, tmp_path / data.name / "1", frame_ids, *flags)
        second = cli(EDGE, data, tmp_path / data.name / "2", frame_ids, *flags)
        assert first == second
        for fid in frame_ids:
            lines, _ = library(EDGE, data, fid, LOW_SCORE, 16, intra_op_threads=1, stage_threads=1)
            assert lines.count("\n") >= 40, lines  # a frame with many boxes, not an empty agreement
            assert first[fid] == lines.encode("ascii"), (data, fid)


@pytest.mark.parametrize(("model", "mirror_tta"), [("edge", False), ("edge", True), ("edge-int8", False)])
def test_thread_counts_change_no_result_line(model: str, mirror_tta: bool) -> None:
    """(c) and (d): intra-op threads 1, 2 and 3 and stage threads 1 and 2 give the same KITTI lines and boxes
    (measured bit-identical; below the printed 1e-4 is what must hold), INT8 and mirror TTA included."""
    settings = [(1, 1), (2, 2), (3, 2), (2, 1)]
    for fid in KITTI_FRAMES:
        runs = [library(WEIGHTS / model, KITTI, fid, LOW_SCORE, 16, intra_op_threads=threads, stage_threads=stage,
                        mirror_tta=mirror_tta) for threads, stage in settings]
        lines, first = runs[0]
        assert lines.count("\n") >= 5, lines
        for (threads, stage), (other_lines, other) in zip(settings[1:], runs[1:], strict=True):
            where = f"{model} {fid}: {threads} intra-op thread(s), {stage} stage thread(s)"
            assert other_lines == lines, where
            assert other.boxes.shape == first.boxes.shape, where  # the boxes outside the camera's view too
            np.testing.assert_allclose(other.boxes, first.boxes, rtol=0, atol=1e-6, err_msg=where)
            np.testing.assert_allclose(other.scores, first.scores, rtol=0, atol=1e-6, err_msg=where)


def test_accuracy_writes_the_clis_result_files(tmp_path: Path) -> None:
    """(b): benchmarks/accuracy.py --input lidar16+camera (its scans thinned to 16 lines, score 0.05 by default)
    writes the files pipeline.detect writes with --emulate-beams 16 --score-threshold 0.05."""
    run = subprocess.run(
        [sys.executable, "benchmarks/accuracy.py", "--data", str(KITTI), "--models", str(EDGE), "--input",
         "lidar16+camera", "--frames", "2", "--out", str(tmp_path / "accuracy"), "--no-progress"],
        cwd=REPO, capture_output=True, text=True, timeout=120, check=False,
    )
    assert run.returncode == 0, run.stderr
    written = {p.stem: p.read_bytes() for p in (tmp_path / "accuracy" / "data").glob("*.txt")}
    first_two = sorted(p.stem for p in (KITTI / "label_2").glob("*.txt"))[:2]
    assert sorted(written) == first_two
    assert written == cli(EDGE, KITTI, tmp_path / "cli", first_two, "--emulate-beams", "16", "--score-threshold",
                          str(LOW_SCORE))


def test_a_scan_thinned_by_pipeline_beams_gives_the_emulated_scans_lines(sim_data: Path, tmp_path: Path) -> None:
    """(b): `python -m pipeline.beams --beams 16` then --emulate-beams 0 writes what --emulate-beams 16 writes on
    the 64-line scans."""
    from pipeline.beams import main as thin

    for data, fid in ((KITTI, "000006"), (sim_data, "000000")):
        thinned = tmp_path / data.name
        for folder, suffix in (("image_2", "png"), ("calib", "txt")):
            (thinned / folder).mkdir(parents=True)
            shutil.copy(data / folder / f"{fid}.{suffix}", thinned / folder)
        (tmp_path / "src").mkdir(exist_ok=True)
        shutil.copy(data / "velodyne" / f"{fid}.bin", tmp_path / "src" / f"{fid}.bin")
        assert thin(["--beams", "16", "--no-progress", str(tmp_path / "src"), str(thinned / "velodyne")]) == 0
        (tmp_path / "src" / f"{fid}.bin").unlink()
        flags = ("--score-threshold", str(LOW_SCORE))
        as_stored = cli(EDGE, thinned, tmp_path / "out" / data.name / "0", [fid], "--emulate-beams", "0", *flags)
        emulated = cli(EDGE, data, tmp_path / "out" / data.name / "16", [fid], "--emulate-beams", "16", *flags)
        assert as_stored == emulated, (data, fid)


@pytest.mark.parametrize(("model", "cli_flags"), [("edge", ("--emulate-beams", "16")), ("edge-lidar64", ())])
def test_the_demo_writes_what_the_cli_writes_for_the_models_own_scan(model: str, cli_flags: tuple[str, ...],
                                                                     tmp_path: Path) -> None:
    """(b): the demo thins the 64-line frame to the lines its model was trained on, as pipeline.detect is told
    to: 16 for the camera model; none for a 64-line PIXOR (it once thinned every model's scan to 16 lines, and a
    64-line model found 1 car of the CLI's 4)."""
    from pipeline.demo import run as demo

    summary = demo(WEIGHTS / model, "000006", tmp_path / "demo")
    written = (tmp_path / "demo" / "data" / "000006.txt").read_bytes()
    assert written == cli(WEIGHTS / model, KITTI, tmp_path / "cli", ["000006"], *cli_flags)["000006"]
    assert summary["detections_in_camera_view"] == written.decode("ascii").splitlines()
    assert ("thinned to 16 lines" if cli_flags else "as stored") in summary["mode"]


def _post(url: str, image: bytes, data: Path, fid: str, query: dict[str, object]) -> httpx.Response:
    files = {"image": image, "points": (data / "velodyne" / f"{fid}.bin").read_bytes(),
             "calib": (data / "calib" / f"{fid}.txt").read_bytes()}
    answer = httpx.post(f"{url}/v1/detect", params=query, files=files, timeout=60)
    assert answer.status_code == 200, answer.text
    return answer


def test_the_service_answers_the_librarys_boxes_and_the_clis_lines(sim_data: Path, tmp_path: Path) -> None:
    """(b) over loopback, on two workers with a session pair each (one intra-op thread): the JSON boxes and scores
    are the library's to the last bit of the float, the same boxes through to_objects and format_label are the
    format=kitti answer, and that is the CLI's result file: at score 0.05 on a KITTI frame, a synthetic frame and
    the KITTI frame as JPEG, and with neither side given a score threshold (the same default)."""
    jpeg_data = tmp_path / "jpeg"
    for folder in ("image_2", "velodyne", "calib"):
        (jpeg_data / folder).mkdir(parents=True)
    for folder, suffix in (("velodyne", "bin"), ("calib", "txt")):
        shutil.copy(KITTI / folder / f"000006.{suffix}", jpeg_data / folder)
    ok, jpeg = cv2.imencode(".jpg", cv2.imread(str(KITTI / "image_2" / "000006.png")), [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    (jpeg_data / "image_2" / "000006.jpg").write_bytes(jpeg.tobytes())
    cases = [(KITTI, "000006", LOW_SCORE), (sim_data, "000000", LOW_SCORE), (jpeg_data, "000006", LOW_SCORE),
             (KITTI, "000006", None)]
    with running_service(EDGE, tmp_path / "service.log", "--workers", "2", "--sessions", "per-worker") as server:
        for case, (data, fid, threshold) in enumerate(cases):
            where = f"{data.name} {fid}, score threshold {threshold}"
            image = next(p for p in sorted((data / "image_2").iterdir()) if p.stem == fid)
            query: dict[str, object] = {"emulate_beams": 16}
            if threshold is not None:
                query["score_threshold"] = threshold
            answer = _post(server.url, image.read_bytes(), data, fid, query).json()
            kitti = _post(server.url, image.read_bytes(), data, fid, {**query, "format": "kitti"}).text
            lines, result = library(EDGE, data, fid, threshold, 16)
            boxes = np.array([[d["box"][k] for k in BOX_FIELDS] for d in answer["detections"]]).reshape(-1, 7)
            scores = np.array([d["score"] for d in answer["detections"]])
            assert np.array_equal(boxes, result.boxes) and np.array_equal(scores, result.scores), where
            calib = read_calib(data / "calib" / f"{fid}.txt")
            image_hw = read_image(image).shape
            from_json = Detections(boxes, scores).to_objects(calib, image_hw)
            assert "".join(format_label(o) + "\n" for o in from_json) == kitti == lines, where
            flags = ("--emulate-beams", "16", *(("--score-threshold", str(threshold)) if threshold is not None else ()))
            written = cli(EDGE, data, tmp_path / f"cli-{case}", [fid], *flags)[fid]
            assert written == kitti.encode("ascii"), where


def test_a_numpy_threshold_keeps_what_the_same_float_keeps() -> None:
    """A library caller's np.float64 threshold keeps the boxes the CLI's and the service's float keeps."""
    frame = load_frame(KITTI, "000006", with_labels=False)
    with Detector(EDGE) as detector:
        score = np.float32(detector.detect(frame.image, frame.points, frame.calib, LOW_SCORE, 16).scores[2])
        threshold = float(score) + float(np.spacing(score)) * 0.4  # above the score, equal to it in float32
        kept = [len(detector.detect(frame.image, frame.points, frame.calib, t, 16).scores)
                for t in (threshold, np.float64(threshold))]
    assert kept[0] == kept[1] == 3
