"""Presets from JSON files (``--preset FILE.json``), the rules every preset is checked against
(``pipeline.presets.check_preset``), and export's way out when a checkpoint's preset is not registered here
(docs/models.md, "Adding a preset"). The export tests need torch."""

from __future__ import annotations

import json
import logging
import re
from dataclasses import replace
from pathlib import Path

import pytest

from export.__main__ import main as export_main
from export.exporter import _load_weights
from models import build_pixor
from models.checkpoint import save_checkpoint
from pipeline.presets import PRESETS, Preset, check_preset, get_preset

EDGE = PRESETS["edge"]
TINY = PRESETS["tiny"]
# The contributor's 0–100 m preset: edge's networks on a longer grid (500 columns of 0.2 m, 125 output cells).
HIGHWAY = {"base": "edge", "name": "highway", "bev": {"x_max": 100.0}}


def _file(folder: Path, content: object, name: str = "preset.json") -> Path:
    path = folder / name
    path.write_text(content if isinstance(content, str) else json.dumps(content), encoding="utf-8")
    return path


def test_a_preset_file_on_a_base_changes_only_the_fields_it_gives(tmp_path: Path) -> None:
    preset = get_preset(str(_file(tmp_path, HIGHWAY, "highway.json")))
    assert preset == replace(EDGE, name="highway", bev=replace(EDGE.bev, x_max=100.0))
    assert preset.bev.shape == (19, 400, 500)
    # The base may carry suffixes; a list becomes the tuple the dataclass holds.
    split = get_preset(str(_file(tmp_path, {"base": "edge-split-near35", "name": "s", "depth": {"prefill_kernel": [7, 3]}})))
    assert split.bev.split_pseudo and split.depth.max_depth == 35.0 and split.depth.prefill_kernel == (7, 3)


def test_a_whole_preset_file_is_the_preset_it_was_written_from(tmp_path: Path) -> None:
    """A manifest's preset_config (Preset.to_dict()) written to a file gives that preset back, tuples and all."""
    written = replace(get_preset("tiny-split-near35"), name="mine", crop_hw=(352, 1216))
    assert get_preset(str(_file(tmp_path, written.to_dict(), "MINE.JSON"))) == written
    # A registered preset's own configuration may be written out under its name.
    assert get_preset(str(_file(tmp_path, EDGE.to_dict()))) == EDGE


@pytest.mark.parametrize(("content", "says"), [
    ({**HIGHWAY, "bev": {"x_maxx": 100.0}}, r"bev\.x_maxx is not a field of bev \(did you mean 'x_max'\?\)"),
    ({**HIGHWAY, "bev": {"x_max": "100"}}, r'bev\.x_max is "100", not a value of type float'),
    ({**HIGHWAY, "depth": {"prefill_kernel": [5]}}, r"depth\.prefill_kernel is \[5\], not a value of type tuple\[int, int\]"),
    ({**HIGHWAY, "bev": {"split_pseudo": 1}}, r"bev\.split_pseudo is 1, not a value of type bool"),
    ({**HIGHWAY, "grid": {}}, r"unknown key 'grid'"),
    ({**HIGHWAY, "base": "motorway"}, r"base: unknown preset 'motorway'"),
    ({"base": "edge"}, r"'name' must be the preset's name"),
    ({"base": "edge", "name": "edge", "bev": {"x_max": 100.0}}, (r"name 'edge' is a registered preset's, whose "
                                                                 r"configuration differs; give this one a name of its own")),
    ({"name": "highway", "bev": {"x_max": 100.0}}, r"lacks crop_hw, depth, pixor, decode; give the whole preset"),
    ('{"base": "edge",\n "name": "x",}', r"not JSON \(line 2, column 14"),
    ([1, 2], r"holds a JSON list, not an object"),
    # The rules every preset is held to apply to a file's as to a registered one.
    ({**HIGHWAY, "bev": {"x_max": 100.1}}, r"preset 'highway': bev\.x_max 100\.1 at cell 0\.2 is 500\.5 cells"),
    # Numbers no preset holds: an OverflowError traceback in the grid's arithmetic (x_max 1e308) or a
    # RecursionError (deep nesting) before; NaN and Infinity are JSON's extensions.
    ({**HIGHWAY, "bev": {"x_max": 1e308}}, r"bev\.x_max is 1e\+308, not a value of type float"),
    ('{"base": "edge", "name": "x", "bev": {"x_max": Infinity}}', r"Infinity is not a number a preset holds"),
    ('{"base": "edge", "name": "x", "decode": {"nms_iou": NaN}}', r"NaN is not a number a preset holds"),
    ("[" * 100_000 + "]" * 100_000, r"nested too deep to be a preset"),
    # A key given twice: json kept the last, so the first x_max was dropped without a word.
    ('{"base": "edge", "name": "x", "bev": {"x_max": 80.0, "x_max": 70.4}}', r"key 'x_max' is given twice"),
    # Values the code would run with, wrongly, without a word (a threshold of 5, reg_mean broadcast from 1 value).
    ({**HIGHWAY, "decode": {"score_threshold": 5.0}}, r"decode\.score_threshold 5\.0 must lie in \[0, 1\]"),
    ({**HIGHWAY, "decode": {"reg_mean": [1.0]}}, r"decode\.reg_mean has 1 values: one per regression channel, 6"),
    ({**HIGHWAY, "decode": {"max_candidates": -1}}, r"decode\.max_candidates -1 must be at least 1"),
    ({**HIGHWAY, "crop_hw": [-352, 1216]}, r"crop_hw \[-352, 1216\] must be positive"),
    ({**HIGHWAY, "depth": {"refine_mode": "bogus"}}, r"depth\.refine_mode 'bogus' is none of add, convex"),
    # PIXOR's own rules, refused here where the file is read, not by a model build after it was accepted.
    ({**HIGHWAY, "pixor": {"output_stride": 16}}, r"pixor\.output_stride 16 is none of PIXOR's stage strides 2, 4, 8"),
    ({**HIGHWAY, "pixor": {"fpn_channels": [48, 48]}},
     r"pixor\.fpn_channels \[48, 48\] gives 2 widths, but an output stride of 4 has 3 FPN levels"),
    ({**HIGHWAY, "pixor": {"fpn_channels": 0}}, r"pixor\.fpn_channels 0 must be positive"),
])
def test_a_bad_preset_file_is_refused_naming_the_key(tmp_path: Path, content: object, says: str) -> None:
    path = _file(tmp_path, content)
    with pytest.raises(ValueError, match=f"^preset file {re.escape(str(path))}: .*{says}"):
        get_preset(str(path))


def test_a_missing_preset_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=f"^preset file {re.escape(str(tmp_path))}/highway.json: cannot be read"):
        get_preset(str(tmp_path / "highway.json"))


@pytest.mark.parametrize(("preset", "says"), [
    (replace(TINY, bev=replace(TINY.bev, x_max=70.0)),
     "bev.x_max 70.0 at cell 0.4 gives nx 175, not a multiple of the output stride 4: x_max 70.4 gives 176"),
    (replace(EDGE, bev=replace(EDGE.bev, y_min=-40.2)),
     "bev.y_max 40.0 at cell 0.2 with y_min -40.2 gives ny 401, not a multiple of the output stride 4: y_max 40.6 gives 404"),
    (replace(EDGE, bev=replace(EDGE.bev, x_max=70.3)),
     "bev.x_max 70.3 at cell 0.2 is 351.5 cells, not a whole number (rounded to nx 351, up to 70.2): x_max 70.4 gives 352"),
    (replace(EDGE, bev=replace(EDGE.bev, z_max=1.0)),
     ("bev.z_max 1.0 at z_cell 0.2 with z_min -2.5 is 17.5 slices, not a whole number (rounded to nz 18, up to 1.1): "
     "z_max 1.1 gives 18")),
    (replace(EDGE, depth=replace(EDGE.depth, input_hw=(176, 600))),
     ("depth.input_hw [176, 600] is not crop_hw [352, 1216] × input_scale 0.5 (the calibration is scaled by "
     "input_scale: the image would be stretched off the sparse depth and pseudo points): input_hw [176, 608]")),
    (replace(EDGE, depth=replace(EDGE.depth, prefill_kernel=(4, 3))),
     "depth.prefill_kernel [4, 3] must be odd on each side (a max-pool centred on its pixel): prefill_kernel [5, 3]"),
    (replace(EDGE, bev=replace(EDGE.bev, z_cell=0.0)), "bev.z_cell 0.0 must be positive"),
])
def test_check_preset_names_the_field_and_a_value_that_fits(preset: Preset, says: str) -> None:
    with pytest.raises(ValueError, match=f"^preset '{preset.name}': {re.escape(says)}$"):
        check_preset(preset)


def test_an_unknown_preset_says_where_presets_are_defined() -> None:
    with pytest.raises(ValueError, match=r"unknown preset 'highway'; choose one of paper, edge, tiny, .*registered in "
                                         r"pipeline/presets\.py, or a preset file: a path ending in \.json"):
        get_preset("highway")


@pytest.fixture
def unregistered_run(tmp_path: Path) -> tuple[Path, Preset]:
    """A PIXOR checkpoint trained (initialised here) with a preset registered nowhere: tiny to 100.8 m (252 columns of 0.4 m)."""
    preset = replace(TINY, name="tinyway", bev=replace(TINY.bev, x_max=100.8))
    save_checkpoint(tmp_path / "run" / "pixor.pt", preset, {"pixor": build_pixor(preset)}, {"epochs": 1})
    return tmp_path / "run", preset


def test_export_takes_the_checkpoints_preset_when_given_none(unregistered_run: tuple[Path, Preset], tmp_path: Path,
                                                            capsys: pytest.CaptureFixture) -> None:
    run_dir, preset = unregistered_run
    common = ["--checkpoints", str(run_dir), "--networks", "pixor", "--no-parity"]
    assert export_main([*common, "--out", str(tmp_path / "own")]) == 0
    manifest = json.loads((tmp_path / "own" / "manifest.json").read_text())
    assert manifest["preset"] == "tinyway" and manifest["preset_config"] == json.loads(json.dumps(preset.to_dict()))
    # The same preset given as a file (a partial one on tiny) is the one the checkpoint's weights load under.
    file = get_preset(str(_file(tmp_path, {"base": "tiny", "name": "tinyway", "bev": {"x_max": 100.8}}, "tinyway.json")))
    assert file == preset
    assert _load_weights({"pixor": run_dir / "pixor.pt"}, file, {"pixor": build_pixor(file)})["pixor"]["epochs"] == 1
    with pytest.raises(SystemExit):  # nothing to take a preset from
        export_main(["--out", str(tmp_path / "none"), "--no-parity"])
    assert "--preset: needed without --checkpoints" in capsys.readouterr().err


def test_export_under_another_preset_names_the_way_out(unregistered_run: tuple[Path, Preset], tmp_path: Path,
                                                      capsys: pytest.CaptureFixture) -> None:
    """Not "give --preset tinyway", which is no preset here (the circle the contributor went round)."""
    run_dir, _ = unregistered_run
    common = ["--checkpoints", str(run_dir), "--networks", "pixor", "--no-parity", "--out", str(tmp_path / "out")]
    assert export_main([*common, "--preset", "tiny"]) == 2
    err = capsys.readouterr().err
    assert ("trained with preset 'tinyway', which is not registered here (it is the checkpoint's own preset_config), "
            "and its weights do not fit preset 'tiny' (bev.x_max 100.8 in the checkpoint, 70.4 in 'tiny'): leave "
            "--preset out, and export takes the checkpoints' own preset") in err
    with pytest.raises(SystemExit):
        export_main([*common, "--preset", "tinyway"])
    err = capsys.readouterr().err
    assert "unknown preset 'tinyway'" in err and (f"{run_dir / 'pixor.pt'} was trained with preset 'tinyway': leave "
                                                  "--preset out") in err
    assert not (tmp_path / "out").exists()


def test_training_takes_a_preset_file_and_its_first_line_names_the_files_grid(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """``models.train --preset FILE.json`` trains under the file's preset, and its first line gives that grid (a
    line built by looking the preset's name up again refused the run: "unknown preset 'tinyway'")."""
    from models.train import main
    from tests.test_train_cli import args

    split = tmp_path / "one.txt"
    split.write_text("000006\n")
    preset_file = tmp_path / "tinyway.json"
    preset_file.write_text(json.dumps({"base": "tiny", "name": "tinyway", "bev": {"x_max": 100.8}}))
    argv = args("detector", tmp_path / "run", split, "--input", "lidar16")
    argv[argv.index("--preset") + 1] = str(preset_file)
    with caplog.at_level(logging.INFO, logger="models.train"):
        assert main(argv) == 0
    (line,) = [r.getMessage() for r in caplog.records if r.getMessage().startswith("detector: preset ")]
    assert line.startswith("detector: preset tinyway, BEV grid 7 × 200 × 252 (nz × ny × nx), x 0…100.8 m"), line


def test_a_resumed_run_compares_the_preset_itself_not_its_file_name(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--resume compared --preset as written: the same file spelt from another folder was refused, and a file
    edited since (or another file of the same name) trained the remaining epochs on another grid. Now the
    preset the run recorded is compared field by field."""
    from models.train import main
    from tests.test_train_cli import args, refused

    split = tmp_path / "one.txt"
    split.write_text("000006\n")
    first = _file(tmp_path, {"base": "tiny", "name": "tinyway", "bev": {"x_max": 100.8}}, "tinyway.json")
    argv = args("detector", tmp_path / "run", split, "--input", "lidar16")
    argv[argv.index("--preset") + 1] = str(first)
    assert main(argv) == 0
    # The same preset in a file of another name and folder: the run resumes.
    (tmp_path / "copy").mkdir()
    same = _file(tmp_path / "copy", json.loads(first.read_text()), "same.json")
    argv[argv.index("--preset") + 1] = str(same)
    argv[argv.index("--epochs") + 1] = "2"
    assert main([*argv, "--resume"]) == 0
    # The first file edited since: refused, naming the field, before any epoch.
    first.write_text(json.dumps({"base": "tiny", "name": "tinyway", "bev": {"x_max": 80.0}}))
    argv[argv.index("--preset") + 1] = str(first)
    argv[argv.index("--epochs") + 1] = "3"
    says = refused([*argv, "--resume"], capsys)
    assert says.startswith(f"error: --preset {first}: bev.x_max 80.0, but {tmp_path / 'run'} was started with 100.8 "
                           "(preset 'tinyway'"), says
    # Edited and renamed at the same path: another preset, refused as such (the file's name alone had passed).
    first.write_text(json.dumps({"base": "tiny", "name": "mine2", "bev": {"x_max": 80.0}}))
    says = refused([*argv, "--resume"], capsys)
    assert f"error: --preset {first} (preset 'mine2'), but {tmp_path / 'run'} was started with --preset " in says, says
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert [entry["epoch"] for entry in log] == [1, 2]


def test_a_bad_preset_file_is_one_error_line_in_export(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """export printed argparse's whole usage above a preset file's fault (7 lines, where models.train says one)."""
    bad = _file(tmp_path, {"base": "edge", "name": "hw", "bev": {"x_maxx": 100.0}}, "hw.json")
    with pytest.raises(SystemExit) as stop:
        export_main(["--preset", str(bad), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and err.count("\n") == 1, err
    assert err.startswith(f"error: --preset: preset file {bad}: bev.x_maxx is not a field of bev (did you mean 'x_max'?)")
    assert not (tmp_path / "out").exists()
