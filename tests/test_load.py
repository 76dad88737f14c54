"""benchmarks/load.py against a real service it starts on 127.0.0.1 (tiny models, a few requests)."""

import hashlib
import json
import shutil
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.beams import emulate_beams
from pipeline.cpu import usable_cpus
from pipeline.kitti import read_velodyne, write_velodyne

LOAD = Path(__file__).resolve().parents[1] / "benchmarks" / "load.py"


@pytest.fixture(scope="module")
def running_service(tiny_models, tmp_path_factory) -> Iterator[str]:
    """The real service on a free 127.0.0.1 port, started by the test itself (not by load.py), for --url runs."""
    from benchmarks.load import started_service

    with started_service(tiny_models, [], tmp_path_factory.mktemp("service") / "service.log") as url:
        yield url


def load(args: list[str], cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess:
    """Run benchmarks/load.py with ``args`` in ``cwd``."""
    return subprocess.run([sys.executable, str(LOAD), *args], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout, check=False)


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
    # docs/models.md: the JSON names the model it drove, by its manifest's sha256 (the service's X-Model-ID).
    assert report["server"]["model_id"] == hashlib.sha256((tiny_models / "manifest.json").read_bytes()).hexdigest()
    # --mirror-tta reached the started service: it says so, and its answers time PIXOR's second run.
    assert report["server"]["mirror_tta"] is True and "PIXOR with mirror TTA" in result.stdout
    assert {"pixor", "pixor_mirror", "mirror_merge"} <= set(report["stage_p50_ms"])
    assert report["latency_ms"]["all"]["p50"] > 0 and report["rss_mb"]["end"] > 0
    picture = cv2.imread(str(tmp_path / "load.png"))
    assert picture is not None and picture.shape[0] > 100
    # The default is unchanged: a closed loop, 64-line scans sent as stored and thinned by the server, which times
    # that stage in every answer.
    assert report["mode"] == "closed-loop" and report["latency_from"] == "send" and report["open_loop"] == {}
    thinning = report["thinning"]
    assert thinning["where"] == "server" and thinning["emulate_beams"] == 16 and thinning["send_beams"] == 0
    assert thinning["server_thinned_answers"] == report["status_counts"]["200"] and "emulate_beams" in report["stage_p50_ms"]
    assert thinning["points_sent_mean"] > 100_000  # KITTI's 64-line scans
    # load.py started the service here: the machine it names is the server's too, and it says so.
    assert report["client_shares_server_machine"] is True and report["server_machine"] == report["client_machine"]
    assert "load.py started it here, so the two share these CPUs" in result.stdout
    assert report["client_cpu_s"] > 0 and "load generator CPU: " in result.stdout
    assert (tmp_path / "outputs" / "load_service.log").is_file()  # the default --log, under the working directory


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
    with socket.socket() as sock:  # a loopback port nothing listens on: held, so no other test's server takes it
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


@pytest.mark.parametrize(("flag", "where", "read"), [
    ("--json", "models/manifest.json", "--models"),  # replaced the manifest with the report
    ("--log", "models/manifest.json", "--models"),  # emptied it before the started service read it
    ("--plot", "models/load.png", "--models"),
    ("--json", "data/velodyne/load.json", "--data"),
])
def test_load_test_refuses_an_output_over_what_it_reads_before_starting_anything(flag, where, read, tmp_path,
                                                                                kitti_dir, capsys, monkeypatch):
    from benchmarks.load import main

    monkeypatch.chdir(tmp_path)  # where the started service's default log would go
    models = shutil.copytree(Path(__file__).resolve().parents[1] / "weights" / "edge-lidar16", tmp_path / "models")
    data = tmp_path / "data"
    for folder, suffix in (("image_2", ".png"), ("velodyne", ".bin"), ("calib", ".txt")):
        (data / folder).mkdir(parents=True)
        shutil.copy(kitti_dir / folder / f"000006{suffix}", data / folder)
    before = {path: path.read_bytes() for folder in (models, data) for path in folder.rglob("*") if path.is_file()}
    out = tmp_path / where
    with pytest.raises(SystemExit) as stopped:  # a short run if it is not refused, as it was
        main(["--models", str(models), "--data", str(data), "--requests", "1", "--clients", "1", flag, str(out)])
    assert stopped.value.code == 2
    captured = capsys.readouterr()
    source = models if read == "--models" else data
    assert captured.err.splitlines()[-1] == (f"python benchmarks/load.py: error: {flag} {out}: would be written over "
                                             f"what {read} {source} holds, which this run reads; give a path "
                                             "outside it")
    assert captured.out == "" and not (tmp_path / "outputs").exists()  # no service was started
    after = {path: path.read_bytes() for folder in (models, data) for path in folder.rglob("*") if path.is_file()}
    assert after == before


def test_url_names_the_client_machine_and_the_load_generators_cpu(tmp_path, running_service):
    """With --url the server may run on another box: the machine described is the client's, never the server's."""
    result = load(["--url", running_service, "--clients", "1", "--requests", "2", "--json", str(tmp_path / "r.json")],
                  tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads((tmp_path / "r.json").read_text())
    assert "machine" not in report and report["client_machine"]["cpus"] >= 1
    # The CPUs the client may use (affinity, a container's quota), beside the machine's.
    assert report["client_machine"]["cpus"] == usable_cpus() <= report["client_machine"]["cpus_online"]
    assert report["server_machine"] is None and report["client_shares_server_machine"] is None
    lines = result.stdout.splitlines()
    assert not any(line.startswith("machine:") for line in lines)
    assert any(line.startswith("client machine: ") and "the server's machine is not known here" in line for line in lines)
    # The load generator's own CPU time over the run, and its share of a core.
    assert report["client_cpu_s"] > 0 and 0 < report["client_cpu_cores"] <= report["client_machine"]["cpus"]
    assert "load generator CPU: " in result.stdout and "which the server shares" not in result.stdout
    assert report["service_log"] is None and not (tmp_path / "outputs").exists()  # nothing started, nothing logged


def test_open_loop_sends_on_schedule_whatever_the_answers(tmp_path, running_service):
    # 3 requests due at 0, 0.5 and 1.0 s, two slots: a closed loop would be done in a fraction of a second.
    result = load(["--url", running_service, "--rate", "2", "--clients", "2", "--requests", "3",
                   "--json", str(tmp_path / "r.json")], tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["mode"] == "open-loop" and report["latency_from"] == "schedule"
    loop = report["open_loop"]
    assert loop["requested_rate_hz"] == 2 and loop["max_in_flight"] == 2
    assert loop["due"] == loop["sent"] == report["requests"] == 3 and loop["unsent"] == 0
    assert report["duration_s"] >= 1.0  # the last request was not sent before its due time
    # Sent on time: two slots free at every due time, so none late, each out within 0.2 s of its due time,
    # and the rate achieved over the schedule's window close to the one asked for.
    assert loop["late_sends"] == 0 and loop["send_lag_ms"]["max"] < 200
    assert abs(loop["achieved_rate_hz"] - loop["requested_rate_hz"]) < 0.25
    latency = report["latency_ms"]["200"]
    assert 0 < latency["p50"] <= latency["p90"] <= latency["p99"]
    assert "open loop: 2 Hz requested" in result.stdout and "latency ms from the due time" in result.stdout


def test_open_loop_counts_late_and_unsent_requests_when_the_slots_are_busy(tmp_path, running_service):
    # A request due every 10 ms with one slot: each takes longer than that, so most wait for the slot or never go.
    result = load(["--url", running_service, "--rate", "100", "--clients", "1", "--duration", "1",
                   "--json", str(tmp_path / "r.json")], tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads((tmp_path / "r.json").read_text())
    loop = report["open_loop"]
    assert loop["due"] == 100 and loop["sent"] + loop["unsent"] == loop["due"]  # none skipped without a count
    assert loop["late_sends"] >= 1 and loop["unsent"] >= 1 and loop["late_sends"] <= loop["sent"] == report["requests"]
    assert sum(report["status_counts"].values()) == loop["sent"]
    assert loop["achieved_rate_hz"] < 100
    # Timed from the due time, the wait for the slot shows; timed from the send, it would not.
    assert loop["send_lag_ms"]["max"] > 10
    assert report["latency_ms"]["all"]["p99"] > loop["latency_from_send_ms"]["p99"]
    assert f"{loop['late_sends']} of them late" in result.stdout and f"{loop['unsent']} never sent" in result.stdout


def test_send_beams_thins_on_the_client_and_the_server_does_not(tmp_path, running_service, kitti_dir):
    result = load(["--url", running_service, "--send-beams", "16", "--clients", "2", "--requests", "4",
                   "--json", str(tmp_path / "r.json")], tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads((tmp_path / "r.json").read_text())
    thinning = report["thinning"]
    assert thinning["where"] == "client" and thinning["send_beams"] == 16 and thinning["emulate_beams"] == 0
    # The scans sent are pipeline.beams' 16-line ones of the first four frames, a quarter of what is stored.
    frames = sorted(path.stem for path in (kitti_dir / "velodyne").glob("*.bin"))[:4]
    expected = np.mean([len(emulate_beams(read_velodyne(kitti_dir / "velodyne" / f"{f}.bin").points, 16)) for f in frames])
    assert thinning["points_sent_mean"] == pytest.approx(expected)
    assert thinning["points_sent_mean"] < 0.4 * thinning["points_stored_mean"]
    # The server was not asked to thin: every answer is a 200 without the emulate_beams stage.
    assert report["status_counts"] == {"200": 4} and thinning["server_thinned_answers"] == 0
    assert "emulate_beams" not in report["stage_p50_ms"]
    assert "thinned to 16 lines here before the run (--send-beams 16)" in result.stdout


def test_send_beams_refuses_thinned_scans_and_a_second_thinning_in_one_line(tmp_path, kitti_dir):
    data = tmp_path / "thinned"
    for folder in ("image_2", "calib", "velodyne"):
        (data / folder).mkdir(parents=True)
    shutil.copy(kitti_dir / "image_2" / "000000.png", data / "image_2")
    shutil.copy(kitti_dir / "calib" / "000000.txt", data / "calib")
    write_velodyne(data / "velodyne" / "000000.bin",
                   emulate_beams(read_velodyne(kitti_dir / "velodyne" / "000000.bin").points, 16))
    result = load(["--data", str(data), "--send-beams", "16", "--requests", "2"], tmp_path)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    scan = data / "velodyne" / "000000.bin"
    assert result.stderr.strip().splitlines() == [
        (f"error: --send-beams 16: {scan}: the scan has 16 rings, not 64: it is thinned already "
         "(emulate beams on 64-line scans only)")]
    assert not (tmp_path / "outputs").exists()  # refused before a service was started
    both = load(["--send-beams", "16", "--emulate-beams", "16", "--requests", "2"], tmp_path)
    assert both.returncode == 2 and "Traceback" not in both.stderr
    assert "error: --send-beams 16 thins the scans here and --emulate-beams 16 would ask the server" in both.stderr
    # A line count the service cannot thin to would only come back as 422s, request after request.
    odd = load(["--emulate-beams", "5", "--requests", "2"], tmp_path)
    assert odd.returncode == 2 and "--emulate-beams/--beams: invalid choice: 5" in odd.stderr


def test_log_puts_the_started_services_log_where_asked(tmp_path, tiny_models):
    work = tmp_path / "work"
    work.mkdir()
    log = tmp_path / "logs" / "service.log"
    result = load(["--models", str(tiny_models), "--clients", "1", "--requests", "2", "--log", str(log),
                   "--json", str(tmp_path / "r.json")], work)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "uvicorn" in log.read_text() and not (work / "outputs").exists()
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["service_log"] == str(log) and f"service log: {log}" in result.stdout
    refused = load(["--url", "http://127.0.0.1:9", "--log", str(log)], work)
    assert refused.returncode == 2 and "--log applies only to a service started here" in refused.stderr


def test_load_help_names_the_new_flags(tmp_path):
    result = load(["--help"], tmp_path)
    assert result.returncode == 0
    for flag in ("--rate HZ", "--send-beams N", "--log FILE"):
        assert flag in result.stdout
