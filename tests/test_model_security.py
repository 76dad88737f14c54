"""A model directory as untrusted input: it arrives over the air, and a compromised build server or a broken delivery
could hand a vehicle anything. The sha256 check proves only that the files match the manifest that came with them;
these tests pin what else the runtime refuses, each in one line naming the file (and field), never by hanging, eating
the memory or a traceback.

Every directory is a copy of weights/edge-lidar16 (PIXOR alone, 1.4 MB) in tmp_path, crafted with onnx and resealed
(its manifest's sha256 and size rewritten), as an attacker who controls the delivery would."""

from __future__ import annotations

import hashlib
import json
import os
import resource
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto

from pipeline import detector as detector_module
from pipeline.check_models import CheckConfig, run
from pipeline.detector import Detector
from pipeline.model_files import ModelFileError, load_manifest
from tests.test_onnx_wire import external

REPO = Path(__file__).resolve().parents[1]
SOURCE = REPO / "weights" / "edge-lidar16"


def copy(folder: Path) -> Path:
    shutil.copytree(SOURCE, folder)
    return folder


def reseal(models: Path, graph: onnx.ModelProto | None = None) -> None:
    """Write ``graph`` as pixor.onnx (when given) and list its true sha256 and size in the manifest."""
    if graph is not None:
        onnx.save(graph, str(models / "pixor.onnx"))
    data = (models / "pixor.onnx").read_bytes()
    manifest = json.loads((models / "manifest.json").read_text())
    manifest["files"]["pixor.onnx"] = {"sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}
    (models / "manifest.json").write_text(json.dumps(manifest))


def with_external_weight(models: Path, location: str) -> None:
    """pixor.onnx with its first initializer's data moved to ``location`` (ONNX external data), resealed."""
    graph = onnx.load(str(models / "pixor.onnx"))
    external(graph.graph.initializer[0], location)
    reseal(models, graph)


def check_line(models: Path) -> str:
    """The files and sessions checks' detail as check_models reports the first failure."""
    report = run(CheckConfig(models=models, provider="cpu"))
    assert not report.passed
    return next(check.detail for check in report.checks if check.status == "fail")


# --------------------------------------------------------------------------- external data
@pytest.mark.parametrize("where", ["beside the graph, unlisted", "../ out of the directory", "absolute",
                                   "a link beside the graph to a file outside"])
def test_a_graph_with_external_data_is_refused_wherever_the_data_is(where: str, tmp_path: Path) -> None:
    """Tensors in another file escape the sha256 check: a file beside the graph, listed nowhere, was loaded as
    PIXOR's weights (two vehicles with one model id could run two models; check_models called it "never loaded").
    ONNX Runtime refuses paths out of the directory itself; the graph bytes given to it now resolve none at all."""
    models = copy(tmp_path / "models")
    outside = tmp_path / "outside.bin"
    outside.write_bytes(np.full(2304, 0.5, np.float32).tobytes())
    if where == "beside the graph, unlisted":
        shutil.copy(outside, models / "weights.bin")
        location = "weights.bin"
    elif where == "../ out of the directory":
        location = "../outside.bin"
    elif where == "absolute":
        location = str(outside)
    else:
        (models / "weights.bin").symlink_to(outside)
        location = "weights.bin"
    with_external_weight(models, location)
    first = onnx.load(str(models / "pixor.onnx"), load_external_data=False).graph.initializer[0].name
    with pytest.raises(ModelFileError) as refused:
        Detector(models, providers="cpu")
    message = str(refused.value)
    assert message == (f"{models / 'pixor.onnx'}: the graph keeps tensors in another file (ONNX external data), "
                       "which no sha256 of the manifest covers; export it with its weights inside (1 tensor(s), "
                       f"the first '{first}' in '{location}')")
    assert check_line(models).startswith(f"{models / 'pixor.onnx'}: the graph keeps tensors in another file")


def test_graph_bytes_never_resolve_external_data_in_the_working_directory(tmp_path: Path, monkeypatch) -> None:
    """Given bytes, ONNX Runtime looks for external data in the working directory (the service's /app): pinned that
    the Detector's sessions look nowhere instead, even with the file right there. This is the second line of
    defence, so the first (the Detector reading the graph itself) is switched off here: as if it missed a tensor."""
    models = copy(tmp_path / "models")
    with_external_weight(models, "weights.bin")
    (tmp_path / "weights.bin").write_bytes(np.zeros(2304, np.float32).tobytes())
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(detector_module, "external_tensors", lambda graph: [])
    with pytest.raises(ModelFileError) as refused:
        Detector(models, providers="cpu")
    message = str(refused.value)
    assert message.startswith(f"{models / 'pixor.onnx'}: the graph keeps tensors in another file (ONNX external data), "
                              "which no sha256 of the manifest covers; export it with its weights inside (")
    assert "External data path" in message and "\n" not in message  # ONNX Runtime's refusal, in one line


def test_external_data_is_refused_before_any_provider_is_chosen(tmp_path: Path) -> None:
    """TensorRT is given the graph's path, from which every ONNX Runtime version reads a file beside it, and 1.21–1.23
    (the GPU and Jetson images) read one named by an absolute path: the graph is read and refused first, whatever
    the provider (TensorRT is not in this machine's build, which would be the error otherwise)."""
    models = copy(tmp_path / "models")
    (models / "weights.bin").write_bytes(np.full(2304, 0.5, np.float32).tobytes())
    with_external_weight(models, "weights.bin")
    with pytest.raises(ModelFileError, match=r"pixor\.onnx: the graph keeps tensors in another file .* in 'weights\.bin'"):
        Detector(models, providers="tensorrt")


def test_a_model_file_that_is_no_protobuf_is_refused_before_onnx_runtime(tmp_path: Path) -> None:
    """What the Detector cannot read it cannot vouch for: a listed, resealed file of text is refused in one line."""
    models = copy(tmp_path / "models")
    (models / "pixor.onnx").write_text("<html>502 Bad Gateway</html>\n")
    reseal(models)
    with pytest.raises(ModelFileError) as refused:
        Detector(models, providers="tensorrt")
    assert str(refused.value) == f"{models / 'pixor.onnx'}: not an ONNX graph (field 7 at byte 0 has wire type 4)"
    assert check_line(models) == str(refused.value)


# --------------------------------------------------------------------------- what ONNX Runtime is given
def test_the_session_runs_the_bytes_whose_sha256_was_checked(tmp_path: Path, monkeypatch) -> None:
    """The Detector read each file twice: once for its sha256, again by ONNX Runtime from its path. A file replaced
    between the two (a copy in progress, an attacker racing the check) ran unchecked; now ONNX Runtime gets the
    bytes that were checked, and the file on disk is never read again."""
    models = copy(tmp_path / "models")
    other = onnx.load(str(models / "pixor.onnx"))
    for weight in other.graph.initializer:  # the same graph, other weights: loads and runs, but another model
        array = onnx.numpy_helper.to_array(weight)
        if array.dtype == np.float32:  # not the int64 split sizes
            weight.CopyFrom(onnx.numpy_helper.from_array(np.full_like(array, 0.25), weight.name))
    swapped = other.SerializeToString()
    from pipeline import model_files

    real_check = model_files._check_digest

    def swap_after_the_check(path, entry, actual, size=None):  # the race, at its worst moment
        real_check(path, entry, actual, size)
        if Path(path).name == "pixor.onnx":
            Path(path).write_bytes(swapped)

    monkeypatch.setattr(model_files, "_check_digest", swap_after_the_check)
    detector = Detector(models, providers="cpu")
    try:
        bev = np.ones((1, *detector.preset.bev.shape), np.float32)
        score, _ = detector.run_pixor(bev)
    finally:
        detector.close()
    assert (models / "pixor.onnx").read_bytes() == swapped  # the swap did happen
    monkeypatch.undo()
    reference = Detector(SOURCE, providers="cpu")
    try:
        np.testing.assert_array_equal(score, reference.run_pixor(bev)[0])  # the checked weights ran
    finally:
        reference.close()


# --------------------------------------------------------------------------- what the files are
def _at_most_8_gib() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (8 << 30, 8 << 30))


@pytest.mark.parametrize("which", ["manifest.json", "pixor.onnx"])
@pytest.mark.parametrize("fault", ["a named pipe", "a link to /dev/zero"])
def test_a_pipe_or_device_in_a_files_place_is_refused_at_once(which: str, fault: str, tmp_path: Path) -> None:
    """A named pipe as manifest.json hung the load for ever; a link to /dev/zero read until the memory ran out
    (MemoryError traceback, or the kernel killing the service). A model file so was "missing"."""
    models = copy(tmp_path / "models")
    (models / which).unlink()
    if fault == "a named pipe":
        os.mkfifo(models / which)
    else:
        (models / which).symlink_to("/dev/zero")
    kind = "a named pipe" if fault == "a named pipe" else "a device"
    what = "manifest" if which == "manifest.json" else "model file"
    code = ("from pipeline.detector import Detector\nfrom pipeline.model_files import ModelFileError\n"
            f"try:\n    Detector({str(models)!r}, providers='cpu')\nexcept ModelFileError as exc:\n    print(exc)\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60,
                          check=False, preexec_fn=_at_most_8_gib)  # without the fix: a MemoryError, not the box's RAM
    assert done.stdout == f"{models / which}: {kind}, where the model directory needs the {what} as a regular file\n", \
        done.stderr[-2000:]


def _at_most_1_5_gib() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (3 << 29, 3 << 29))


def test_a_model_loads_in_less_memory_than_the_file_size_bound(tmp_path: Path) -> None:
    """Reading a 1.4 MB graph asked for a buffer of the whole bound up front (read(2 GiB + 1)): under an address-space
    limit (ulimit -v, a 32-bit board, strict overcommit) every model failed to load with a MemoryError traceback."""
    code = (f"from pipeline.detector import Detector\nDetector({str(SOURCE)!r}, providers='cpu').close()\n"
            "print('loaded')\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60,
                          check=False, preexec_fn=_at_most_1_5_gib)  # loading takes about 0.7 GiB of address space
    assert done.stdout == "loaded\n", done.stderr[-2000:]


def test_a_link_to_a_checked_file_outside_the_directory_still_loads(tmp_path: Path) -> None:
    """Files linked rather than copied (tests/test_typing.py does so) stay a model: their bytes are what is checked."""
    models = tmp_path / "models"
    models.mkdir()
    shutil.copy(SOURCE / "manifest.json", models)
    (models / "pixor.onnx").symlink_to(SOURCE / "pixor.onnx")
    Detector(models, providers="cpu").close()


# --------------------------------------------------------------------------- the manifest's size and shape
@pytest.mark.parametrize(("text", "says"), [
    ("[" * 100_000 + "]" * 100_000, "unreadable manifest (lists and tables nested too deep to parse)"),
    ('{"a": ' * 200 + "1" + "}" * 200, "unreadable manifest (lists and tables nested more than 64 deep)"),
    ('{"files": ' + "1" * 5000 + "}", "unreadable manifest (Exceeds the limit (4300 digits)"),
    ('{"pad": "' + "a" * (9 << 20) + '"}', "more than 8 MiB, far more than any manifest this lowres3d reads"),
], ids=["100,000 brackets", "200 tables deep", "a 5,000-digit number", "9 MiB"])
def test_a_manifest_too_deep_or_too_big_is_one_line(text: str, says: str, tmp_path: Path) -> None:
    """100,000 nested brackets made Python's JSON parser raise RecursionError, a 5,000-digit number a ValueError:
    tracebacks out of the service and check_models. A gigabyte of JSON was read and parsed whole."""
    models = copy(tmp_path / "models")
    (models / "manifest.json").write_text(text)
    with pytest.raises(ModelFileError) as refused:
        load_manifest(models)
    assert str(refused.value).startswith(f"{models / 'manifest.json'}: {says}")
    assert check_line(models).startswith(f"{models / 'manifest.json'}: {says}")


def test_check_models_names_a_few_bad_files_then_counts_the_rest(tmp_path: Path) -> None:
    """A manifest listing 20,000 missing files made a FAIL line of 20,000 messages (over a megabyte)."""
    models = copy(tmp_path / "models")
    manifest = json.loads((models / "manifest.json").read_text())
    manifest["files"].update({f"f{k}.bin": {"sha256": "0" * 64} for k in range(20_000)})
    (models / "manifest.json").write_text(json.dumps(manifest))
    detail = check_line(models)
    assert detail.endswith("; and 19995 more") and len(detail) < 1000
    assert detail.startswith(f"{models / 'f0.bin'}: model file listed in the manifest is missing; ")


# --------------------------------------------------------------------------- the graph's outputs
def _rename_output(graph: onnx.ModelProto, names: dict[str, str]) -> onnx.ModelProto:
    for node in graph.graph.node:
        for k, name in enumerate(node.output):
            node.output[k] = names.get(name, name)
    for output in graph.graph.output:
        output.name = names.get(output.name, output.name)
    return graph


@pytest.mark.parametrize("change", ["outputs swapped", "output renamed", "output in float64"])
def test_a_graph_whose_outputs_differ_is_refused_at_load(change: str, tmp_path: Path) -> None:
    """A PIXOR whose outputs had other names, shapes or types loaded, and failed at the first frame (a ValueError
    or ONNX Runtime's InvalidArgument, in the service after it had started and said it was warming up)."""
    models = copy(tmp_path / "models")
    graph = onnx.load(str(models / "pixor.onnx"))
    pixor = models / "pixor.onnx"
    if change == "outputs swapped":
        _rename_output(graph, {"score": "regression", "regression": "score"})
        says = (f"{models / 'manifest.json'}: preset_config gives pixor output 'score' the shape [1, 1, 100, 88], but "
                f"{pixor} gives [1, 6, 100, 88]")
    elif change == "output renamed":
        _rename_output(graph, {"score": "probability"})
        says = f"{pixor}: no output 'score' (a pixor network gives score, regression; this graph: probability, regression)"
    else:
        _rename_output(graph, {"score": "score32"})
        graph.graph.node.append(onnx.helper.make_node("Cast", ["score32"], ["score"], to=TensorProto.DOUBLE))
        graph.graph.output[0].name = "score"
        graph.graph.output[0].type.tensor_type.elem_type = TensorProto.DOUBLE
        says = f"{pixor}: output 'score' is a tensor(double), where the runtime reads tensor(float)"
    reseal(models, graph)
    with pytest.raises(ModelFileError) as refused:
        Detector(models, providers="cpu")
    assert str(refused.value) == says
    assert check_line(models) == says


# --------------------------------------------------------------------------- what ONNX Runtime itself refuses
@pytest.mark.parametrize(("change", "says"), [
    ("custom domain", "is not a registered function/op"),
    ("opset 999", "ValidateOpsetForDomain"),
    ("10 GB initializer declared", "exceeds the 2147483648 byte limit"),
    ("EPContext reading a file", "EPContext node generated by 'TensorrtExecutionProvider' is not compatible"),
])
def test_onnx_runtime_refuses_hostile_graphs_in_one_line(change: str, says: str, tmp_path: Path) -> None:
    """Pinned: ONNX Runtime itself refuses an operator of an unknown domain, an opset from the future, an initializer
    declared far bigger than its data, and an EPContext node (com.microsoft) naming an engine file to read."""
    models = copy(tmp_path / "models")
    graph = onnx.load(str(models / "pixor.onnx"))
    if change == "custom domain":
        graph.graph.node[0].domain = "evil.ops"
        graph.opset_import.append(onnx.helper.make_opsetid("evil.ops", 1))
    elif change == "opset 999":
        graph.opset_import[0].version = 999
    elif change == "10 GB initializer declared":
        weight = graph.graph.initializer[0]
        weight.dims[-1] = 3 * 100_000_000
    else:
        node = onnx.helper.make_node("EPContext", [i.name for i in graph.graph.input], [o.name for o in graph.graph.output],
                                     domain="com.microsoft", embed_mode=0, ep_cache_context="../../../../etc/passwd",
                                     source="TensorrtExecutionProvider", main_context=1)
        del graph.graph.node[:]
        del graph.graph.initializer[:]
        graph.graph.node.append(node)
        graph.opset_import.append(onnx.helper.make_opsetid("com.microsoft", 1))
    reseal(models, graph)
    with pytest.raises(ModelFileError) as refused:
        Detector(models, providers="cpu")
    message = str(refused.value)
    assert message.startswith(f"{models / 'pixor.onnx'}: ONNX Runtime cannot load it (") and says in message
    assert "\n" not in message
