"""Preset files (``--preset FILE.json``) through the commands that time, compare or redraw a preset: the
folders they export into, the preset they build a PyTorch twin of, how they compare a preset with a model
directory's, the weights they read back, and what they name and record (session 49's review)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from export.exporter import ExportConfig
from export.exporter import run as export
from models import build_network
from pipeline.presets import get_preset
from tests.conftest import KITTI

# A tiny preset of its own name with a taller grid: 8 height slices, so PIXOR reads 9 channels, tiny's 8.
TALL = {"base": "tiny", "name": "mycam_small", "bev": {"z_max": 1.5}}


def _preset_file(path: Path, config: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(config))
    return path


@pytest.fixture(scope="module")
def tall_models(tmp_path_factory) -> Path:
    """A model directory exported from the preset file TALL (initialised weights), once for this module."""
    folder = tmp_path_factory.mktemp("tall")
    out = folder / "m_cam"
    export(ExportConfig(preset=str(_preset_file(folder / "mycam.json", TALL)), out=out, parity=False))
    return out


def _jsonable(config: dict) -> dict:
    return json.loads(json.dumps(config))


# ----------------------------------------------------------------------------------------- network_latency
def test_network_latency_exports_each_preset_file_inside_its_scratch_folder_and_names_it(tmp_path, monkeypatch):
    """--preset /abs/near.json once ended in "--out …near.json: exists and is not a model directory", and
    ../p/x.json exported beside the scratch folder, where nothing removed it. Each preset is exported inside the
    scratch folder, which goes whole, and the table names the preset by its name and its file."""
    from benchmarks import network_latency

    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr("tempfile.tempdir", str(scratch))  # the command's TemporaryDirectory lands here
    absolute = _preset_file(tmp_path / "x" / "near.json", {"base": "tiny", "name": "mytiny"})
    _preset_file(tmp_path / "p" / "x.json", {"base": "tiny", "name": "other/../tiny"})
    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")
    before = torch.get_num_threads()
    try:
        rows = network_latency.run([str(absolute), "../p/x.json"], repeats=1, threads=1, progress=False, block=1)
    finally:
        torch.set_num_threads(before)
    assert [(row.preset, row.network) for row in rows] == [("mytiny", "depth"), ("mytiny", "pixor"),
                                                          ("other/../tiny", "depth"), ("other/../tiny", "pixor")]
    # Nothing exported beside the scratch folder, which was removed (torch keeps a compile cache in the temp folder).
    assert [path.name for path in scratch.iterdir() if not path.name.startswith("torchinductor")] == []
    assert absolute.is_file() and (tmp_path / "p" / "x.json").is_file()
    table = network_latency.format_table(rows)
    assert f"| mytiny ({absolute}) | pixor |" in table and "| other/../tiny (../p/x.json) | depth |" in table


def test_network_latency_refuses_a_bad_preset_file_in_one_line(tmp_path, capsys):
    from benchmarks.network_latency import main

    bad = _preset_file(tmp_path / "bad.json", {"base": "tiny", "name": "b", "bev": {"z_maxx": 1.5}})
    try:
        code = main(["--preset", str(bad), "--no-progress"])
    except SystemExit as stop:  # argparse's refusal, with its usage
        code = stop.code
    err = capsys.readouterr().err
    assert code == 2 and "usage:" not in err and err.count("\n") == 1, err
    assert err.startswith(f"error: argument --preset: preset file {bad}: bev.z_maxx is not a field of bev")


# ------------------------------------------------------------------------------------------------ latency
def test_torch_twin_of_a_preset_file_directory_is_built_from_its_manifest(tall_models, tmp_path):
    """An INT8 directory of a preset file's model, its FP32 source gone: the twin is exported with initialised
    weights for the directory's own preset (its manifest's preset_config), not looked up by a name that no
    registered preset has."""
    from benchmarks.latency import torch_twin
    from export.precision import convert_precision
    from pipeline.detector import Detector

    source = tmp_path / "fp32"
    shutil.copytree(tall_models, source)
    convert_precision(source, tmp_path / "int8", "int8", KITTI, calibration_frames=2)
    shutil.rmtree(source)
    detector = Detector(tmp_path / "int8", providers="cpu")
    networks, weights = torch_twin(detector, None)
    assert weights.startswith("initialised")
    assert set(networks) == {"depth", "pixor"}
    first = next(m for m in networks["pixor"].modules() if isinstance(m, torch.nn.Conv2d))
    assert first.in_channels == detector.preset.bev.channels == 9  # the file's grid, not tiny's 8 channels


def test_latency_compares_a_preset_with_the_directorys_by_its_configuration(tall_models, tmp_path, capsys):
    """A preset file that only shares the directory's preset name is another preset: refused before any timing,
    naming the first field that differs; the same preset from another file is the directory's."""
    from tests.test_latency import refused

    other = _preset_file(tmp_path / "samename_other.json", {**TALL, "decode": {"score_threshold": 0.3}})
    code, err = refused(capsys, "--models", str(tall_models), "--preset", str(other), "--frames", "1", "--warmup", "0")
    assert code == 2 and "Traceback" not in err, err
    error = [line for line in err.splitlines() if not line.startswith("warning: ")]  # the weights are initialised
    assert len(error) == 1 and error[0].startswith(f"error: --preset {other}: decode.score_threshold 0.3"), err
    assert "mycam_small" in error[0]

    from benchmarks.latency import check_models_preset
    from pipeline.errors import InputError
    from pipeline.model_files import load_manifest
    from pipeline.presets import preset_from_dict

    held = preset_from_dict(load_manifest(tall_models)["preset_config"])
    check_models_preset(str(_preset_file(tmp_path / "same.json", TALL)), held, tall_models)  # the same configuration
    with pytest.raises(InputError, match=r"decode\.score_threshold 0\.3, but .* holds 0\.5"):
        check_models_preset(str(other), held, tall_models)


# ------------------------------------------------------------------------------------------- onnx_weights
def test_onnx_weights_refuse_to_cut_away_weights_that_are_not_padding(tall_models, tiny_models):
    """The taller grid's PIXOR (9 input channels) into tiny's (8): cutting its first conv to tiny's shape would
    drop real weights (the reflectance's) and put a height slice's on tiny's reflectance. The exporter's zero
    padding is still cut away: tiny's own graph, whose narrow convs are padded, loads."""
    from models.onnx_weights import load_onnx_weights

    path = tall_models / "pixor.onnx"
    with pytest.raises(ValueError) as refused:
        load_onnx_weights(build_network("pixor", get_preset("tiny")).eval(), path)
    message = str(refused.value)
    assert "\n" not in message and str(path) in message
    # Its stem has 9 input channels (its output channels padded to the exporter's block), tiny's 8.
    assert "stem.0.0.weight has shape (" in message and ", 9, 3, 3), the network's is (8, 8, 3, 3)" in message, message
    net = build_network("pixor", get_preset("tiny")).eval()
    load_onnx_weights(net, tiny_models / "pixor.onnx")
    assert all(np.isfinite(p.detach().numpy()).all() for p in net.parameters())


# ------------------------------------------------------------------------------------------------- curves
def test_curves_title_a_run_by_its_presets_name_not_the_file_it_was_given_as(tmp_path):
    """A run started with --preset FILE.json: redrawing its picture names the preset as models.train did."""
    from models.curves import draw, read_log, recorded_info
    from models.run_checks import STATE_KEYS

    preset_file = _preset_file(tmp_path / "x.json", {"base": "tiny", "name": "mytiny"})
    preset = get_preset(str(preset_file))
    history = [{"epoch": 1, "train_loss": 3.0, "lr": 1e-4, "val_loss": 2.0, "rmse_mm": 900.0, "mae_mm": 400.0}]
    (tmp_path / "log.jsonl").write_text(json.dumps(history[0]) + "\n")
    state = {key: {} for key in STATE_KEYS}
    state.update(epoch=1, config={"task": "depth", "preset": str(preset_file), "preset_config": preset.to_dict()})
    torch.save(state, tmp_path / "state.pt")
    info = recorded_info(tmp_path, read_log(tmp_path / "log.jsonl"))
    assert info.preset == "mytiny"
    figure = draw(history, info, tmp_path)
    assert "preset mytiny ·" in figure._suptitle.get_text()


# ----------------------------------------------------------------------------------------------- frame_ops
def test_frame_ops_names_the_preset_and_records_its_configuration_and_file(tmp_path, capsys):
    from benchmarks.frame_ops import main

    preset_file = _preset_file(tmp_path / "x.json", {"base": "tiny", "name": "mytiny"})
    assert main(["--preset", str(preset_file), "--repeats", "1", "--json", str(tmp_path / "f.json")]) == 0
    assert ", preset mytiny, " in capsys.readouterr().out
    report = json.loads((tmp_path / "f.json").read_text())
    assert report["preset"] == "mytiny" and report["preset_file"] == str(preset_file)
    assert report["preset_config"] == _jsonable(get_preset(str(preset_file)).to_dict())
    assert main(["--preset", "tiny", "--repeats", "1", "--json", str(tmp_path / "t.json")]) == 0
    report = json.loads((tmp_path / "t.json").read_text())
    assert report["preset"] == "tiny" and report["preset_file"] is None
    assert report["preset_config"] == _jsonable(get_preset("tiny").to_dict())
