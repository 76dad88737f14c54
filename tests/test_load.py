"""benchmarks/load.py against a real service it starts on 127.0.0.1 (tiny models, a few requests)."""

import json
import socket
import subprocess
import sys
from pathlib import Path

import cv2

LOAD = Path(__file__).resolve().parents[1] / "benchmarks" / "load.py"


def test_load_test_drives_a_started_service_and_reports(tmp_path, tiny_models):
    # 12 requests over the folder's five frames, every second one broken (each kind at least once).
    result = subprocess.run(
        [sys.executable, str(LOAD), "--models", str(tiny_models), "--clients", "2", "--requests", "12",
         "--bad-every", "2", "--mirror-tta", "--json", str(tmp_path / "load.json"), "--plot", str(tmp_path / "load.png")],
        cwd=tmp_path, capture_output=True, text=True, timeout=300, check=False,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads((tmp_path / "load.json").read_text())
    assert report["url"].startswith("http://127.0.0.1:") and report["clients"] == 2
    assert report["requests"] == 12 and sum(report["status_counts"].values()) == 6
    assert report["status_counts"].get("200", 0) >= 1 and report["throughput_ok_per_s"] > 0
    assert report["frames_sent"] == 5  # the good requests went through every frame of tests/data/kitti/training
    broken = report["broken"]
    assert broken["sent"] == broken["answered_4xx"] == 6 and report["server_errors"] == 0
    assert set(broken["statuses"]) == {"points-truncated", "image-cut-off", "calib-without-P2", "query-misspelt"}
    assert "status counts of the real frames (the broken ones: below): {" in result.stdout
    assert "broken requests: 6 of 6 answered 4xx" in result.stdout
    assert len(report["windows"]) == 10 and report["trend"]["p50_ms_last_tenth"] > 0
    assert report["server"]["preset"] == "tiny"
    # --mirror-tta reached the started service: it says so, and its answers time PIXOR's second run.
    assert report["server"]["mirror_tta"] is True and "PIXOR with mirror TTA" in result.stdout
    assert {"pixor", "pixor_mirror", "mirror_merge"} <= set(report["stage_p50_ms"])
    assert report["latency_ms"]["all"]["p50"] > 0 and report["rss_mb"]["end"] > 0
    picture = cv2.imread(str(tmp_path / "load.png"))
    assert picture is not None and picture.shape[0] > 100


def test_every_frame_is_sent_intact_and_broken_whatever_bad_every():
    """--bad-every equal to the number of frames (or dividing it) used to break the same frame every time:
    that frame was never sent well-formed."""
    from benchmarks.load import BROKEN_KINDS, KITTI, RequestSource

    frames = sorted(path.stem for path in (KITTI / "velodyne").glob("*.bin"))
    assert len(frames) == 5
    for bad_every in (2, 5):
        source = RequestSource(KITTI, frames, {}, total=10 * len(frames) * bad_every, bad_every=bad_every)
        uploads = list(iter(source.take, None))
        intact = [u.name for u in uploads if not u.broken]
        broken = [(u.name, u.files["image"][0].removesuffix(".png")) for u in uploads if u.broken]
        assert len(broken) == len(uploads) // bad_every
        assert set(intact) == set(frames), bad_every
        assert intact[: 2 * len(frames)] == frames * 2  # the frames in turn
        assert {frame for _, frame in broken} == set(frames), bad_every
        assert {kind for kind, _ in broken} == set(BROKEN_KINDS)


def test_load_test_without_a_service_at_url_answers_one_line(tmp_path):
    with socket.socket() as sock:  # a loopback port nothing listens on
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    result = subprocess.run(
        [sys.executable, str(LOAD), "--url", f"http://127.0.0.1:{port}", "--requests", "2"],
        cwd=tmp_path, capture_output=True, text=True, timeout=120, check=False,
    )
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert f"--url http://127.0.0.1:{port}: cannot reach the service" in result.stderr


def test_load_test_refuses_a_frame_missing_from_data_before_starting_anything(tmp_path):
    result = subprocess.run(
        [sys.executable, str(LOAD), "--frame", "000002", "--requests", "2"],
        cwd=tmp_path, capture_output=True, text=True, timeout=120, check=False,
    )
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "frame 000002 has no image_2/000002.png" in result.stderr
    assert not (tmp_path / "outputs").exists()  # no service was started
