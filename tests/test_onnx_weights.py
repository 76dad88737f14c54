"""ONNX weights back into the PyTorch networks (models/onnx_weights.py): the shipped files and a round trip."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from export.inputs import kitti_inputs, random_inputs
from export.onnx_export import depth_io, export_onnx
from export.parity import cpu_session, depth_parity, pixor_parity
from models import build_network
from models.onnx_weights import load_onnx_weights
from pipeline.presets import get_preset, preset_from_dict

WEIGHTS = Path(__file__).resolve().parents[1] / "weights"


@pytest.mark.parametrize(("directory", "network"), [("edge", "depth"), ("edge", "pixor"), ("edge-lidar64", "pixor")])
def test_shipped_onnx_weights_reproduce_onnx_runtime_in_pytorch(directory, network):
    """Every rewrite of the shipped graphs (folded batch norms, the merged early fusion, the split and padded
    PIXOR convs, the stride-1 transposed conv) is undone: PyTorch eager then agrees with ONNX Runtime on a
    real KITTI frame within the exporter's own parity tolerances."""
    path = WEIGHTS / directory / f"{network}.onnx"
    manifest = json.loads((path.parent / "manifest.json").read_text())
    preset = preset_from_dict(manifest["preset_config"])  # the preset these files were exported with
    net = build_network(network, preset).eval()
    load_onnx_weights(net, path)
    check = depth_parity if network == "depth" else pixor_parity
    results = check(net, cpu_session(path), kitti_inputs(preset))
    for result in results if isinstance(results, list) else [results]:
        assert result.passed, f"{result.metric} {result.error:.3g} > {result.tolerance:.3g}"


@pytest.mark.parametrize("preset_name", ["tiny-refine", "tiny-convex"])
def test_round_trip_of_trained_looking_weights(tmp_path, preset_name):
    """Weights with non-trivial batch-norm statistics and biases, exported and read back, give the network
    the outputs the original gives (PyTorch against PyTorch: the folding is undone, not approximated).
    With the full-resolution head (either mode), so its convs round-trip too; the convex one is also
    exported with the exporter's ONNX Runtime parity checks on."""
    from export.exporter import ExportConfig, run
    from models.checkpoint import save_checkpoint

    preset = get_preset(preset_name)
    torch.manual_seed(3)
    originals = {}
    for name in ("depth", "pixor"):
        net = build_network(name, preset)
        with torch.no_grad():
            for module in net.modules():
                if isinstance(module, torch.nn.BatchNorm2d):
                    module.weight.uniform_(0.5, 1.5)
                    module.bias.uniform_(-0.2, 0.2)
                    module.running_mean.uniform_(-0.3, 0.3)
                    module.running_var.uniform_(0.5, 2.0)
                elif isinstance(module, torch.nn.Conv2d | torch.nn.ConvTranspose2d) and module.bias is not None:
                    module.bias.uniform_(-0.1, 0.1)
            if name == "depth":  # the full-resolution head starts at zero: give it a say
                head = net.refine.head if preset.depth.refine_mode == "convex" else net.refine
                head.out.weight.normal_(std=0.05 if head is net.refine else 1.0)
        originals[name] = net.eval()
        save_checkpoint(tmp_path / "runs" / f"{name}.pt", preset, {name: net}, {"note": "test"})
    out = tmp_path / "models"
    run(ExportConfig(preset=preset_name, out=out, checkpoints=tmp_path / "runs", parity=preset_name == "tiny-convex"))
    inputs = random_inputs(preset, seed=4)
    for name, original in originals.items():
        twin = build_network(name, preset).eval()
        load_onnx_weights(twin, out / f"{name}.onnx")
        feeds = [torch.from_numpy(v) for v in inputs.feeds(name).values()]
        with torch.inference_mode():
            expected, got = original(*feeds), twin(*feeds)
        for a, b in zip(expected if isinstance(expected, tuple) else (expected,),
                        got if isinstance(got, tuple) else (got,), strict=True):
            np.testing.assert_allclose(b.numpy(), a.numpy(), rtol=1e-4, atol=1e-4)


def test_a_graph_of_another_network_is_refused():
    net = build_network("depth", get_preset("edge"))
    with pytest.raises(ValueError, match="no weights|shape|could belong to"):
        load_onnx_weights(net, WEIGHTS / "edge" / "pixor.onnx")


def test_an_int8_graph_is_refused_as_such():
    """A quantized graph holds no trained fp32 weights to read back: the error says so, not "another network"."""
    net = build_network("depth", get_preset("edge"))
    with pytest.raises(ValueError, match="INT8 .*give the FP32 model directory"):
        load_onnx_weights(net, WEIGHTS / "edge-int8" / "depth.onnx")


def test_an_export_without_the_refine_head_starts_a_network_with_it(tmp_path):
    """A depth net exported before the full-resolution head existed, loaded with the head optional: the
    head keeps its zero-initialised output, so the network computes what the ONNX file does; asked for
    everything, the loader names what the graph lacks."""
    preset = get_preset("tiny-refine")
    torch.manual_seed(5)
    older = build_network("depth", get_preset("tiny")).eval()
    path = tmp_path / "depth.onnx"
    inputs = random_inputs(preset, seed=6)
    export_onnx(older, depth_io(preset.depth.input_hw), path)
    net = build_network("depth", preset).eval()
    with pytest.raises(ValueError, match="refine"):
        load_onnx_weights(net, path)
    assert load_onnx_weights(net, path, optional=("refine",)) == ("refine",)
    assert torch.count_nonzero(net.refine.out.weight) == 0
    result = depth_parity(net, cpu_session(path), inputs)
    assert result.passed, f"{result.metric} {result.error:.3g} > {result.tolerance:.3g}"
    # A graph that has the head: the head is loaded, optional or not.
    with torch.no_grad():
        net.refine.out.weight.normal_(std=0.05)
    export_onnx(net, depth_io(preset.depth.input_hw), path)
    twin = build_network("depth", preset).eval()
    assert load_onnx_weights(twin, path, optional=("refine",)) == ()
    assert torch.equal(twin.refine.out.weight, net.refine.out.weight)


def test_a_model_directory_back_to_checkpoints(tiny_models, tmp_path, capsys):
    """python -m models.onnx_weights: checkpoints of a model directory that carry its preset and
    training record and compute what its ONNX files do."""
    from models.checkpoint import load_checkpoint, load_network_weights
    from models.onnx_weights import main

    assert main(["--models", str(tiny_models), "--out", str(tmp_path / "ckpt")]) == 0
    preset = get_preset("tiny")
    inputs = random_inputs(preset, seed=7)
    for name, check in (("depth", depth_parity), ("pixor", pixor_parity)):
        checkpoint = load_checkpoint(tmp_path / "ckpt" / f"{name}.pt")
        assert checkpoint.metadata["from_onnx"].endswith(f"{name}.onnx")
        net = build_network(name, preset)
        load_network_weights(net, checkpoint, name, preset)
        results = check(net.eval(), cpu_session(tiny_models / f"{name}.onnx"), inputs)
        for result in results if isinstance(results, list) else [results]:
            assert result.passed, f"{result.metric} {result.error:.3g} > {result.tolerance:.3g}"
    assert main(["--models", str(tmp_path / "nothing"), "--out", str(tmp_path / "x")]) == 2
    (tmp_path / "a-file").write_text("")
    assert main(["--models", str(tiny_models), "--out", str(tmp_path / "a-file")]) == 2
    assert "--out" in capsys.readouterr().err
    damaged = tmp_path / "damaged"  # a cut-off copy: named by the manifest's sha256, not a protobuf trace
    shutil.copytree(tiny_models, damaged)
    (damaged / "pixor.onnx").write_bytes((tiny_models / "pixor.onnx").read_bytes()[:1000])
    assert main(["--models", str(damaged), "--out", str(tmp_path / "y")]) == 2
    assert f"{damaged / 'pixor.onnx'}: sha256 mismatch" in capsys.readouterr().err
    listless = tmp_path / "listless"  # a manifest without its networks table: named, not "--models: 'networks'"
    shutil.copytree(tiny_models, listless)
    manifest = json.loads((listless / "manifest.json").read_text())
    del manifest["networks"]
    (listless / "manifest.json").write_text(json.dumps(manifest))
    assert main(["--models", str(listless), "--out", str(tmp_path / "z")]) == 2
    assert f"{listless / 'manifest.json'}: manifest has no 'networks' table" in capsys.readouterr().err


def test_an_out_that_cannot_take_the_checkpoints_is_named_as_out(tmp_path, capsys):
    """An --out holding checkpoints was reported as "error: --models: --out …": the flag at fault is --out alone.
    An --out inside --models is refused too (its checkpoints would land in the model directory it reads)."""
    from models.onnx_weights import main

    held = tmp_path / "run"
    held.mkdir()
    (held / "pixor.pt").write_bytes(b"a training run's own")
    assert main(["--models", str(WEIGHTS / "edge-lidar16"), "--out", str(held)]) == 2
    assert capsys.readouterr().err == f"error: --out {held}: already holds pixor.pt; give a new folder\n"
    assert (held / "pixor.pt").read_bytes() == b"a training run's own"
    models = shutil.copytree(WEIGHTS / "edge-lidar16", tmp_path / "models")
    assert main(["--models", str(models), "--out", str(models / "ckpt")]) == 2
    assert capsys.readouterr().err == (f"error: --out {models / 'ckpt'}: would be written over what --models {models} "
                                       "holds, which this run reads; give a path outside it\n")
    assert not (models / "ckpt").exists()


def test_a_file_that_is_not_onnx_is_named(tmp_path):
    from models.onnx_weights import read_onnx

    garbage = tmp_path / "pixor.onnx"
    garbage.write_text("hello\n")
    with pytest.raises(ValueError, match=r"pixor\.onnx: not a readable ONNX model \(DecodeError"):
        read_onnx(garbage)
