"""Rolling a model out to a fleet: the bench check (python -m pipeline.check_models), the manifest's format
version, the model's identity as the service reports it, and a model directory swapped or half-copied.

Every model directory here is a copy of a small shipped one (weights/edge-lidar16 or edge-lidar64: PIXOR alone,
1.4 MB) in tmp_path, damaged on purpose; weights/ itself is only read."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import numpy_helper

from pipeline.check_models import CheckConfig, main, run
from pipeline.detector import Detector
from pipeline.model_files import (
    FORMAT,
    FORMAT_VERSION,
    ModelFileError,
    load_manifest,
    load_manifest_with_digest,
    model_identity,
    sha256_file,
)
from service.metrics import Metrics
from service.runtime import load_runtime, loaded_identity
from service.settings import Settings
from tests.conftest import KITTI
from tests.test_service import parts, service

REPO = Path(__file__).resolve().parents[1]
WEIGHTS = REPO / "weights"


def copy_models(name: str, folder: Path) -> Path:
    """A copy of the shipped model directory ``name`` at ``folder``."""
    shutil.copytree(WEIGHTS / name, folder)
    return folder


def edit_manifest(models: Path, change) -> None:
    """Rewrite ``models``' manifest with ``change(manifest)`` applied."""
    manifest = json.loads((models / "manifest.json").read_text())
    change(manifest)
    (models / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")


def manifest_sha256(models: Path) -> str:
    return hashlib.sha256((models / "manifest.json").read_bytes()).hexdigest()


@pytest.fixture
def models(tmp_path: Path) -> Path:
    return copy_models("edge-lidar16", tmp_path / "edge-lidar16")


def start_service(models: Path) -> subprocess.CompletedProcess:
    """``python -m service --models models`` on a free port, expected to stop before serving."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("LOWRES3D_")}
    return subprocess.run([sys.executable, "-m", "service", "--models", str(models), "--port", "0", "--provider", "cpu"],
                          cwd=REPO, capture_output=True, text=True, timeout=60, check=False, env=env)


# --------------------------------------------------------------------------- the bench check
def test_check_models_passes_a_whole_directory_and_gives_its_id(models: Path, tmp_path: Path, capsys) -> None:
    report_file = tmp_path / "out" / "check.json"
    assert main(["--models", str(models), "--provider", "cpu", "--json", str(report_file)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in out[:4]] == ["PASS"] * 4, out
    assert out[-1] == f"passed: {models} is fit to ship; model id {manifest_sha256(models)}"
    report = json.loads(report_file.read_text())
    assert report["passed"] is True and [c["status"] for c in report["checks"]] == ["pass"] * 4
    assert report["identity"]["id"] == manifest_sha256(models)
    assert report["identity"]["sha256"] == {"pixor.onnx": sha256_file(models / "pixor.onnx")}
    assert (report["identity"]["directory"], report["identity"]["precision"]) == ("edge-lidar16", "fp32")


def test_check_models_judges_the_manifests_descriptions_under_its_manifest_check(models: Path, capsys) -> None:
    """A bev_grid edited by hand failed only under the sessions' check, below a manifest check that had passed;
    one deleted passed without a word, though a port reads the grid there. Now the first fails the manifest
    check, naming the field, and the second passes it with a warning."""
    edit_manifest(models, lambda m: m["bev_grid"].update(x_max=100.0))
    assert main(["--models", str(models), "--provider", "cpu"]) == 1
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("FAIL manifest ") and "bev_grid.x_max is 100.0 where preset_config gives 70.4" in out[0]
    assert [line.split()[:2] for line in out[1:4]] == [["SKIP", "files"], ["SKIP", "sessions"], ["SKIP", "frame"]]
    edit_manifest(models, lambda m: m.pop("bev_grid"))
    assert main(["--models", str(models), "--provider", "cpu"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("PASS manifest ") and out[1].strip().startswith("warning: ")
    assert "no 'bev_grid' table: a runtime other than this one (a port) reads the grid" in out[1]


def test_check_models_fails_a_half_copied_directory_naming_the_file(models: Path, capsys) -> None:
    (models / "pixor.onnx").write_bytes((WEIGHTS / "edge-lidar16" / "pixor.onnx").read_bytes()[:300_000])
    assert main(["--models", str(models)]) == 1
    out = capsys.readouterr().out.splitlines()
    assert out[1].startswith(f"FAIL files    {models / 'pixor.onnx'}: sha256 mismatch: 300000 bytes, where the "
                             "manifest lists"), out
    assert "copy cut off or still in progress" in out[1]
    assert [line.split()[0] for line in out[2:4]] == ["SKIP", "SKIP"]
    assert out[-1] == f"failed: {models}: the files check; do not ship it"


def _poison(path: Path) -> None:
    """Make the network at ``path`` answer NaN: its largest weight tensor all NaN (the graph stays valid)."""
    model = onnx.load(str(path))
    largest = max((t for t in model.graph.initializer if t.data_type == onnx.TensorProto.FLOAT),
                  key=lambda t: np.prod(t.dims))
    array = numpy_helper.to_array(largest).copy()
    array[...] = np.nan
    largest.CopyFrom(numpy_helper.from_array(array, largest.name))
    onnx.save(model, str(path))


def test_check_models_fails_a_network_whose_outputs_are_nan(models: Path) -> None:
    """NaN scores are never above the threshold: the Detector answers "no car" without a word, the check fails."""
    _poison(models / "pixor.onnx")
    digest, size = sha256_file(models / "pixor.onnx"), (models / "pixor.onnx").stat().st_size
    edit_manifest(models, lambda m: m["files"].update({"pixor.onnx": {"sha256": digest, "bytes": size}}))
    frame_points = np.fromfile(KITTI / "velodyne" / "000006.bin", np.float32).reshape(-1, 4)
    with Detector(models, providers="cpu") as detector:
        assert len(detector.detect(None, frame_points, None).scores) == 0  # silently nothing
    report = run(CheckConfig(models=models, provider="cpu"))
    assert [c.status for c in report.checks] == ["pass", "pass", "pass", "fail"]
    assert report.checks[3].detail.startswith("pixor.onnx output score: ") and "NaN or infinite" in report.checks[3].detail


def test_check_models_fails_untrained_weights_unless_allowed(models: Path) -> None:
    edit_manifest(models, lambda m: m["networks"]["pixor"].update(weights="initialised (untrained)"))
    report = run(CheckConfig(models=models, provider="cpu"))
    assert report.checks[0].status == "fail" and "pixor: exported without trained weights" in report.checks[0].detail
    assert run(CheckConfig(models=models, provider="cpu", allow_untrained=True)).passed


@pytest.mark.parametrize(("args", "says"), [
    (["--models", "{tmp}/nope"], "error: --models {tmp}/nope: no such folder"),
    (["--models", "{models}", "--data", "{tmp}"], "{tmp}"),
    (["--models", "{models}", "--json", "{models}"], "error: --json {models}: is a directory"),
])
def test_check_models_bad_command_line_is_one_line_and_status_2(args, says, models: Path, tmp_path: Path,
                                                                capsys) -> None:
    fill = {"tmp": tmp_path, "models": models}
    assert main([arg.format(**fill) for arg in args]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and len(captured.err.splitlines()) == 1
    assert captured.err.startswith("error: ") and says.format(**fill) in captured.err


def test_check_models_refuses_a_json_over_what_it_reads_before_checking(models: Path, tmp_path: Path,
                                                                       capsys) -> None:
    """--json named as the model directory's manifest replaced it with the report (and said "passed"); named
    inside --data's frames, it would replace a calibration file. Refused in one line before any check, as
    benchmarks/accuracy.py and export.golden refuse it."""
    data = tmp_path / "kitti"
    for folder, suffix in (("image_2", ".png"), ("velodyne", ".bin"), ("calib", ".txt")):
        (data / folder).mkdir(parents=True)
        shutil.copy(KITTI / folder / f"000006{suffix}", data / folder)
    for json_file, read in ((models / "manifest.json", f"--models {models}"),
                            (data / "calib" / "000006.txt", f"--data {data}")):
        before = json_file.read_bytes()
        assert main(["--models", str(models), "--data", str(data), "--json", str(json_file)]) == 2
        captured = capsys.readouterr()
        assert captured.out == "", captured.out  # no check ran
        assert captured.err == (f"error: --json {json_file}: would be written over what {read} holds, which this "
                                "run reads; give a path outside it\n")
        assert json_file.read_bytes() == before


def test_check_models_provider_this_build_lacks_is_the_command_lines_fault(models: Path, capsys) -> None:
    import onnxruntime as ort

    # The locked install is onnxruntime's CPU build (requirements/constraints.txt): it offers neither GPU provider.
    offered = ort.get_available_providers()
    missing = [name for name, full in (("cuda", "CUDAExecutionProvider"), ("tensorrt", "TensorrtExecutionProvider"))
               if full not in offered]
    assert missing, f"this ONNX Runtime build offers every provider check_models takes: {offered}"
    assert main(["--models", str(models), "--provider", missing[0]]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: provider '{missing[0]}' (providers=, --provider): not available in this ONNX "
                          "Runtime build")
    assert err.endswith("\n") and len(err.splitlines()) == 1


def test_check_models_ctrl_c_is_one_line(models: Path, monkeypatch, capsys) -> None:
    import pipeline.check_models as command

    def interrupt(*_: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(command, "run", interrupt)
    assert command.main(["--models", str(models)]) == 130
    assert capsys.readouterr().err == "interrupted: nothing was written; the model directory is as it was\n"


def test_check_models_is_one_of_the_command_family() -> None:
    """What tests/test_commands.py asks of every command, for this one (its MODULES list does not name it yet)."""
    import tests.test_commands as family

    monkeypatch = pytest.MonkeyPatch()
    try:
        monkeypatch.setattr(family, "MODULES", [*family.MODULES, "pipeline.check_models"])
        monkeypatch.setattr(family, "FAMILY", [*family.FAMILY, "pipeline.check_models"])
        family.test_every_command_answers_help("pipeline.check_models")
        family.test_every_command_answers_help_on_the_runtime_install("pipeline.check_models")
        family.test_the_family_spells_each_shared_flag_alike("pipeline.check_models", monkeypatch)
    finally:
        monkeypatch.undo()


# --------------------------------------------------------------------------- the manifest's format version
def test_every_shipped_manifest_keeps_loading_with_its_format_and_identity() -> None:
    """The shipped manifests say lowres3d-models/1: a runtime raising FORMAT_VERSION must still read them."""
    for name in ("edge", "edge-int8", "edge-lidar16", "edge-lidar64"):
        manifest, digest = load_manifest_with_digest(WEIGHTS / name)
        identity = model_identity(WEIGHTS / name, manifest, digest)
        assert (manifest["format"], identity.format, identity.directory) == ("lowres3d-models/1", 1, name)
        assert identity.id == manifest_sha256(WEIGHTS / name) and identity.weights == "trained"
    assert FORMAT == f"lowres3d-models/{FORMAT_VERSION}"


def test_a_newer_format_is_refused_naming_both_versions(models: Path) -> None:
    edit_manifest(models, lambda m: m.update(format="lowres3d-models/2", a_field_from_the_future={"x": 1}))
    message = (f"{models / 'manifest.json'}: format lowres3d-models/2 is newer than this lowres3d reads "
               "(lowres3d-models/1); update lowres3d")
    with pytest.raises(ModelFileError, match=r"^" + message.replace("(", r"\(").replace(")", r"\)")):
        Detector(models)
    done = start_service(models)
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr[-2000:]
    assert f"ERROR service: cannot start: {message}" in done.stderr and "Uvicorn running" not in done.stderr


@pytest.mark.parametrize(("change", "says"), [
    ({"format": "lowres3d-models/0"}, "format lowres3d-models/0 is older than this lowres3d reads"),
    ({"format": "lowres3d-port/1"}, "format 'lowres3d-port/1' is not a lowres3d model manifest"),
    ({"format": 1}, "format 1 is not a lowres3d model manifest"),
    ({"precision": "bf16"}, "precision: 'bf16' is none of fp32, fp16, int8"),
])
def test_an_unreadable_format_or_field_is_refused(change: dict, says: str, models: Path) -> None:
    edit_manifest(models, lambda m: m.update(change))
    with pytest.raises(ModelFileError, match=says):
        load_manifest(models)


def test_fields_the_runtime_does_not_know_are_ignored_and_a_missing_format_is_version_1(models: Path) -> None:
    def older_and_newer(manifest: dict) -> None:
        del manifest["format"]
        manifest["something_added_later"] = [1, 2]

    edit_manifest(models, older_and_newer)
    with Detector(models, providers="cpu") as detector:
        assert detector.preset.name == "edge"


def test_a_network_file_without_a_sha256_is_refused(models: Path) -> None:
    """A network loaded from a file the 'files' table does not list would run unchecked."""
    shutil.copy(models / "pixor.onnx", models / "other.onnx")
    edit_manifest(models, lambda m: m["networks"]["pixor"].update(file="other.onnx"))
    with pytest.raises(ModelFileError, match=r"networks\.pixor\.file: 'other\.onnx' has no sha256 in 'files'"):
        Detector(models)
    edit_manifest(models, lambda m: m["files"].update({"../pixor.onnx": m["files"]["pixor.onnx"]}))
    with pytest.raises(ModelFileError, match=r"files\.\.\./pixor\.onnx: a file name in the model directory"):
        load_manifest(models)


# --------------------------------------------------------------------------- identity, swap, half copy
def test_the_service_says_which_model_it_runs_everywhere(tmp_path: Path, caplog) -> None:
    """/v1/model, each detection answer's body and headers, /metrics and the start's log line carry the same
    id (the manifest's sha256) and directory; a `current` link names the directory it points to."""
    target = copy_models("edge-lidar16", tmp_path / "edge-lidar16-v7")
    current = tmp_path / "current"
    current.symlink_to(target)
    frame = {"points": (KITTI / "velodyne" / "000006.bin").read_bytes(),
             "image": (KITTI / "image_2" / "000006.png").read_bytes(),
             "calib": (KITTI / "calib" / "000006.txt").read_bytes()}
    expected = {"id": manifest_sha256(target), "directory": "edge-lidar16-v7", "preset": "edge", "precision": "fp32"}
    headers = {"x-model-id": expected["id"], "x-model-directory": "edge-lidar16-v7", "x-model-preset": "edge",
               "x-model-precision": "fp32"}
    with caplog.at_level(logging.INFO, logger="service.runtime"), service(current, provider="cpu") as client:
        identity = client.get("/v1/model").json()["identity"]
        assert {k: identity[k] for k in expected} == expected
        assert identity["path"] == str(target) and identity["format"] == 1
        assert identity["training_data"] == {"pixor": "runs/s20/sim/train"}
        answer = client.post("/v1/detect", params={"emulate_beams": 16}, files=parts(frame))
        assert answer.status_code == 200, answer.text
        assert {k: answer.json()["model"][k] for k in expected} == expected
        for response in (answer, client.post("/v1/detect", params={"emulate_beams": 16, "format": "kitti"},
                                             files=parts(frame)),
                         client.post("/v1/detect/bev.png", params={"emulate_beams": 16}, files=parts(frame))):
            assert response.status_code == 200
            assert {k: response.headers.get(k) for k in headers} == headers
        info = next(line for line in client.get("/metrics").text.splitlines() if line.startswith("lowres3d_model_info{"))
        for label in (f'id="{expected["id"]}"', 'directory="edge-lidar16-v7"', 'precision="fp32"', 'format="1"',
                      'training_data="runs/s20/sim/train"'):
            assert label in info, info
    started = next(r.getMessage() for r in caplog.records if r.getMessage().startswith("loaded "))
    assert started.startswith(f"loaded {current} (→ {target}): model edge-lidar16-v7 (id {expected['id'][:12]}, ")


def test_a_swap_under_a_running_service_waits_for_the_restart(tmp_path: Path) -> None:
    """The sessions hold the networks: switching the link (or replacing the files) changes nothing until a
    restart, which then serves the new directory."""
    old, new = copy_models("edge-lidar16", tmp_path / "v1"), copy_models("edge-lidar64", tmp_path / "v2")
    current = tmp_path / "current"
    current.symlink_to(old)
    frame = {"points": (KITTI / "velodyne" / "000006.bin").read_bytes()}
    with service(current, provider="cpu") as client:
        before = client.post("/v1/detect", files={"points": ("f.bin", frame["points"])})
        staged = tmp_path / "current.new"
        staged.symlink_to(new)
        staged.replace(current)  # the atomic switch of a rollout
        shutil.rmtree(old)  # and even the old files gone
        after = client.post("/v1/detect", files={"points": ("f.bin", frame["points"])})
        assert after.status_code == 200 and after.headers["x-model-directory"] == "v1"
        assert after.json()["detections"] == before.json()["detections"]
    with service(current, provider="cpu") as client:
        assert client.get("/v1/model").json()["identity"]["id"] == manifest_sha256(new)


def test_a_half_copied_directory_is_refused_at_start_and_served_once_whole(tmp_path: Path) -> None:
    """A copy still running when the service (re)starts: the real process stops with one line naming the file,
    exit status 2; the same directory starts once the copy has finished."""
    models = tmp_path / "edge-lidar16"
    models.mkdir()
    source = WEIGHTS / "edge-lidar16"
    shutil.copy(source / "manifest.json", models)  # what `cp -r` and rsync may write first
    data = (source / "pixor.onnx").read_bytes()
    with open(models / "pixor.onnx", "wb") as copying:
        copying.write(data[: len(data) // 2])
        copying.flush()
        done = start_service(models)
        assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr[-2000:]
        line = next(line for line in done.stderr.splitlines() if "cannot start" in line)
        assert line.endswith(f"cannot start: {models / 'pixor.onnx'}: sha256 mismatch: {len(data) // 2} bytes, where "
                             f"the manifest lists {len(data)} (a copy cut off or still in progress, or another model's "
                             "file); copy the whole model directory again")
        assert "Uvicorn running" not in done.stderr
        copying.write(data[len(data) // 2:])
    with service(models, provider="cpu") as client:
        assert client.get("/v1/model").json()["identity"]["id"] == manifest_sha256(models)


def test_a_directory_changed_while_the_service_loads_is_refused(models: Path) -> None:
    """The manifest read again after the sessions are made: a copy that replaced it meanwhile stops the start."""
    detector = Detector(models, providers="cpu")
    try:
        assert loaded_identity(models, [detector]).id == manifest_sha256(models)
        edit_manifest(models, lambda m: m.update(weights="trained", note="a newer export copied in"))
        with pytest.raises(ModelFileError, match="the model directory changed while the service loaded it"):
            loaded_identity(models, [detector])
    finally:
        detector.close()


def test_per_worker_sessions_all_load_the_directory_the_link_named_at_the_start(tmp_path: Path) -> None:
    """--sessions per-worker loads the directory once per worker: a link switched meanwhile must not give two
    workers two models (the link is followed once)."""
    old, new = copy_models("edge-lidar16", tmp_path / "v1"), copy_models("edge-lidar64", tmp_path / "v2")
    current = tmp_path / "current"
    current.symlink_to(old)
    switched = threading.Event()
    real_init = Detector.__init__

    def switch_after_the_first(self, *args, **kwargs) -> None:  # the rollout's switch, between two workers' loads
        real_init(self, *args, **kwargs)
        if not switched.is_set():
            switched.set()
            staged = tmp_path / "current.new"
            staged.symlink_to(new)
            staged.replace(current)

    mp = pytest.MonkeyPatch()
    mp.setattr(Detector, "__init__", switch_after_the_first)
    try:
        runtime = load_runtime(Settings(models=current, provider="cpu", sessions="per-worker", workers=2), Metrics())
    finally:
        mp.undo()
    try:
        assert switched.is_set()
        assert {d.sha256["pixor.onnx"] for d in runtime.detectors} == {sha256_file(old / "pixor.onnx")}
        assert runtime.identity.directory == "v1"
    finally:
        runtime.pool.shutdown()
        for detector in runtime.detectors:
            detector.close()
