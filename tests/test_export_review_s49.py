"""Session 49's review of export/: the precision CLI's --emulate-beams, golden's map descriptions at the preset's
output stride, and a conversion of a directory whose manifest names its own file names."""

import json
import shutil

import pytest

from export.exporter import ExportConfig, run
from export.golden import write_golden
from export.precision import convert_precision, main
from tests.conftest import KITTI


def test_the_precision_cli_refuses_a_line_count_it_cannot_thin_to_naming_the_flag(tmp_path, capsys):
    """12 is refused by argparse, naming --emulate-beams, before any model is read: --models does not even exist,
    and without the choice it was that missing folder the error named (and 12 only after the Detector loaded)."""
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exited:
        main(["--models", str(tmp_path / "no-models"), "--precision", "fp16", "--out", str(out),
              "--emulate-beams", "12"])
    assert exited.value.code == 2
    err = capsys.readouterr().err
    assert "--emulate-beams" in err and "invalid choice: 12" in err
    assert "no-models" not in err and not out.exists()


def test_a_library_caller_giving_such_a_line_count_is_refused_before_the_model_loads(tmp_path):
    """convert_precision(beams=12) is refused as the CLI's choices refuse it, naming --emulate-beams; it was
    refused only after the Detector had loaded, as frame 000000's fault, with the hint to give 0."""
    from pipeline.errors import InputError

    with pytest.raises(InputError, match=r"^--emulate-beams: 12 is not one of 0, 32, 16, 8, 4$"):
        convert_precision(tmp_path / "no-models", tmp_path / "out", "fp16", KITTI, beams=12)


def test_golden_describes_pixor_maps_at_the_presets_output_stride(tmp_path):
    """A preset with output stride 2: the score and regression maps are the grid / 2, and golden.json says so."""
    preset = tmp_path / "stride2.json"
    preset.write_text(json.dumps({"base": "tiny", "name": "tiny-stride2", "pixor": {"output_stride": 2}}))
    models = tmp_path / "models"
    run(ExportConfig(preset=str(preset), out=models, parity=False, networks=("pixor",)))
    arrays = write_golden(models, tmp_path / "golden", KITTI).index["arrays"]
    ny, nx = arrays["bev"]["shape"][2:]
    for name in ("score", "regression"):
        assert arrays[name]["shape"][2:] == [ny // 2, nx // 2]
        assert "ny/2, nx/2" in arrays[name]["description"], arrays[name]["description"]


def test_a_conversion_reads_the_files_its_manifest_names(tiny_models, tmp_path):
    """The runtime loads each network from the file its manifest names (networks.NAME.file); so does the conversion,
    its deviation from fp32 included (it opened depth.onnx and pixor.onnx whatever the manifest said)."""
    source = tmp_path / "renamed"
    source.mkdir()
    manifest = json.loads((tiny_models / "manifest.json").read_text())
    for name, entry in manifest["networks"].items():
        renamed = f"{name}-v2.onnx"
        shutil.copy(tiny_models / entry["file"], source / renamed)
        manifest["files"][renamed] = manifest["files"].pop(entry["file"])
        entry["file"] = renamed
    (source / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    out = tmp_path / "fp16"
    converted = convert_precision(source, out, "fp16", KITTI)
    assert sorted(p.name for p in out.iterdir()) == ["depth-v2.onnx", "manifest.json", "pixor-v2.onnx"]
    deviation = converted["precision_info"]["deviation_from_fp32"]
    assert set(deviation) == {"depth", "pixor"}
    assert 0 < deviation["depth"]["value"] < 1e-2 and deviation["pixor"]["value"] < 1e-2
