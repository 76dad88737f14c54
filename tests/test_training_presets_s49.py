"""Preset files through training (session 49): a pseudo-depth cache of another view, an ONNX start of another
preset, the messages for a checkpoint of a preset file's, models.reproduce's refusal of a file, and the --preset
a resumed run records. Every run is the tiny preset (or a file on it) on one real KITTI frame for one epoch."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import cv2
import pytest

from models import build_pixor
from models.cache_pseudo import RECORD
from models.cache_pseudo import run as cache_pseudo
from models.checkpoint import load_checkpoint, load_network_weights, save_checkpoint
from models.data import cached_pseudo_depth
from models.train import main
from pipeline.errors import InputError
from pipeline.frame import load_frame
from pipeline.kitti import read_depth_png, write_depth_png
from pipeline.presets import get_preset
from tests.conftest import KITTI
from tests.test_train_cli import args, refused

FRAME = "000006"
TINY = get_preset("tiny")
# The tiny net's view of the camera at half scale instead of a quarter: the maps of a tiny export are 88 × 304.
HALFVIEW = {"base": "tiny", "name": "halfview", "depth": {"input_hw": [176, 608], "input_scale": 0.5}}


def _file(folder: Path, content: dict, name: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    path.write_text(json.dumps(content))
    return path


def _with_preset(argv: list[str], preset: str | Path) -> list[str]:
    argv = list(argv)
    argv[argv.index("--preset") + 1] = str(preset)
    return argv


@pytest.fixture(scope="module")
def one_frame(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("split") / "one.txt"
    path.write_text(f"{FRAME}\n")
    return path


@pytest.fixture(scope="module")
def tiny_cache(tiny_models: Path, one_frame: Path, tmp_path_factory) -> Path:
    """The tiny export's dense depth of frame 000006 (an 88 × 304 map), as models.cache_pseudo makes it."""
    out = tmp_path_factory.mktemp("pseudo") / "cache"
    assert cache_pseudo(KITTI, tiny_models, out, one_frame, progress=False) == 1
    return out


# ------------------------------------------------------------------------------------ 1. a cache of another view
def test_a_pseudo_cache_of_another_view_is_refused_before_training(tiny_cache: Path, one_frame: Path, tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """A cache of the tiny export read by a run whose depth view is twice as large trained without a word, its
    pseudo points placed with the half-scale calibration (azimuths −0.7…39° instead of −40…39°)."""
    halfview = _file(tmp_path, HALFVIEW, "halfview.json")
    argv = _with_preset(args("detector", tmp_path / "run", one_frame, "--input", "pseudo", "--pseudo-dir",
                             str(tiny_cache), "--no-progress"), halfview)
    says = refused(argv, capsys)
    assert says.startswith(f"error: --pseudo-dir {tiny_cache}: its maps are in the view crop [352, 1216] × 0.25 = "
                           f"88×304 ({tiny_cache / RECORD}, made with preset 'tiny'); preset 'halfview' sees crop "
                           "[352, 1216] × 0.5 = 176×608"), says
    assert "cache them again with python -m models.cache_pseudo" in says
    assert not (tmp_path / "run").exists()
    record = json.loads((tiny_cache / RECORD).read_text())
    assert record["view"] == {"crop_hw": [352, 1216], "input_scale": 0.25, "input_hw": [88, 304]}
    # A training cache in the run's view (the map enlarged, as a half-view model's would be) beside a validation
    # cache in another: the flag of the one refused is named.
    good = tmp_path / "good"
    shutil.copytree(tiny_cache, good)
    depth = read_depth_png(good / f"{FRAME}.png")
    write_depth_png(good / f"{FRAME}.png", cv2.resize(depth, (608, 176), interpolation=cv2.INTER_NEAREST))
    (good / RECORD).write_text(json.dumps({**record, "view": {"crop_hw": [352, 1216], "input_scale": 0.5,
                                                             "input_hw": [176, 608]}}))
    says = refused([*_with_preset(argv, halfview)[:-3], "--pseudo-dir", str(good), "--val-pseudo-dir",
                    str(tiny_cache), "--no-progress"], capsys)
    assert says.startswith(f"error: --val-pseudo-dir {tiny_cache}: its maps are in the view crop [352, 1216] × 0.25 "
                           "= 88×304"), says


def test_an_older_pseudo_cache_is_checked_by_its_first_maps_shape(tiny_cache: Path, one_frame: Path, tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """A record from before the view was recorded (session 48's): the first map's shape is compared; under the
    preset it was made with, the cache still trains."""
    older = tmp_path / "older"
    shutil.copytree(tiny_cache, older)
    record = json.loads((older / RECORD).read_text())
    record.pop("view", None)
    (older / RECORD).write_text(json.dumps(record))
    argv = args("detector", tmp_path / "run", one_frame, "--input", "pseudo", "--val-pseudo-dir", str(older),
                "--pseudo-dir", str(older), "--no-progress")
    says = refused(_with_preset(argv, _file(tmp_path, HALFVIEW, "halfview.json")), capsys)
    assert says.startswith(f"error: --pseudo-dir {older}: its maps are in the view 88×304 ({older / f'{FRAME}.png'}, "
                           "made with preset 'tiny'); preset 'halfview' sees crop [352, 1216] × 0.5 = 176×608"), says
    assert main(argv) == 0


def test_a_cached_map_of_another_shape_is_refused_by_the_loader(tiny_cache: Path) -> None:
    """The loader read any map and placed it with the preset's view calibration."""
    frame = load_frame(KITTI, FRAME, with_labels=False)
    halfview = get_preset(str(_file(tiny_cache.parent / "presets", HALFVIEW, "halfview.json")))
    with pytest.raises(InputError, match=r"000006\.png: a cached 88×304 map, not the 176×608 view of preset "
                                         r"'halfview'"):
        cached_pseudo_depth(tiny_cache, frame, halfview)
    depth, _ = cached_pseudo_depth(tiny_cache, frame, TINY)
    assert depth.shape == (88, 304)


# ------------------------------------------------------------------------------------ 2. an ONNX start's preset
def test_an_onnx_start_of_another_grid_is_refused_as_its_checkpoint_is(tiny_models: Path, one_frame: Path,
                                                                       tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """pixor.onnx of a tiny export started a run on a 51.2 m grid without a word (PIXOR's weights have the same
    shapes on any grid); its checkpoint was refused. Now both say the same, from the manifest's preset_config."""
    mytiny = _file(tmp_path, {"base": "tiny", "name": "mytiny", "bev": {"x_max": 51.2}}, "mytiny.json")
    pt = save_checkpoint(tmp_path / "det" / "pixor.pt", TINY, {"pixor": build_pixor(TINY)}, {"epochs": 1})
    said = {}
    for start in (pt, tiny_models / "pixor.onnx"):
        argv = _with_preset(args("detector", tmp_path / start.suffix, one_frame, "--input", "lidar16",
                                 "--pixor-checkpoint", str(start), "--no-progress"), mytiny)
        said[start.suffix] = refused(argv, capsys).replace(str(start), "START")
        assert not (tmp_path / start.suffix).exists()
    assert said[".onnx"] == said[".pt"]
    assert said[".onnx"] == ("error: START: trained with preset 'tiny' whose bev configuration differs from the "
                             "requested preset 'mytiny'; give --preset tiny with it, or a checkpoint trained with mytiny")


def test_an_onnx_depth_start_of_another_crop_is_refused(tiny_models: Path, one_frame: Path, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    cropped = _file(tmp_path, {"base": "tiny", "name": "lowcrop", "crop_hw": [320, 1216],
                               "depth": {"input_hw": [80, 304]}}, "lowcrop.json")
    argv = _with_preset(args("depth", tmp_path / "run", one_frame, "--depth-checkpoint",
                             str(tiny_models / "depth.onnx"), "--no-progress"), cropped)
    says = refused(argv, capsys)
    assert says == (f"error: {tiny_models / 'depth.onnx'}: trained with preset 'tiny' whose depth, crop_hw "
                    "configuration differs from the requested preset 'lowcrop'; give --preset tiny with it, or a "
                    "checkpoint trained with lowcrop")


# ------------------------------------------------------------------------------------ 3. a preset file's checkpoint
def test_a_checkpoint_of_an_edited_preset_file_sends_the_user_back_to_the_file(one_frame: Path, tmp_path: Path,
                                                                               capsys: pytest.CaptureFixture[str]) -> None:
    """The file edited since (same name, x_max 51.2 → 76.8) was told "as an earlier lowres3d defined it … export it
    with the lowres3d it was trained with", and another preset "give --preset mytiny", which --preset does not
    know."""
    trained = get_preset(str(_file(tmp_path / "then", {"base": "tiny", "name": "mytiny", "bev": {"x_max": 51.2}},
                                   "mytiny.json")))
    pt = save_checkpoint(tmp_path / "det" / "pixor.pt", trained, {"pixor": build_pixor(trained)}, {"epochs": 1})
    edited = _file(tmp_path, {"base": "tiny", "name": "mytiny", "bev": {"x_max": 76.8}}, "mytiny.json")
    argv = _with_preset(args("detector", tmp_path / "run", one_frame, "--input", "lidar16", "--pixor-checkpoint",
                             str(pt), "--no-progress"), edited)
    says = refused(argv, capsys)
    assert says.startswith(f"error: {pt}: trained with preset 'mytiny', not a registered one (a preset file's), whose "
                           "preset_config differs from preset 'mytiny' given (bev.x_max 51.2 in the checkpoint, 76.8 "
                           "in 'mytiny'): give the preset file it was trained with (its preset_config, written to a "
                           ".json file as it stands, is one"), says
    assert "earlier lowres3d" not in says
    says = refused(_with_preset(argv, "tiny"), capsys)
    assert "give --preset mytiny" not in says and "(bev.x_max 51.2 in the checkpoint, 70.4 in 'tiny')" in says, says
    # The registered presets' wording stays.
    with pytest.raises(ValueError, match="give --preset tiny with it, or a checkpoint trained with mytiny"):
        tiny_pt = save_checkpoint(tmp_path / "tiny" / "pixor.pt", TINY, {"pixor": build_pixor(TINY)}, {})
        load_network_weights(build_pixor(trained), load_checkpoint(tiny_pt), "pixor", trained)


def test_a_pseudo_range_of_a_preset_file_sends_the_user_to_the_file(tmp_path: Path) -> None:
    near = replace(TINY, name="mynear", depth=replace(TINY.depth, max_depth=35.0))
    pt = save_checkpoint(tmp_path / "det" / "pixor.pt", near, {"pixor": build_pixor(near)},
                         {"task": "detector", "input": "pseudo"})
    with pytest.raises(ValueError) as refusal:
        load_network_weights(build_pixor(TINY), load_checkpoint(pt), "pixor", TINY)
    says = str(refusal.value)
    assert "points it never saw: give the preset file it was trained with (its preset_config" in says, says
    assert "--preset mynear" not in says


# ------------------------------------------------------------------------------------ 4. models.reproduce
def test_reproduce_refuses_a_preset_file_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from models.reproduce import main as reproduce

    preset_file = _file(tmp_path, {"base": "tiny", "name": "mytiny", "bev": {"x_max": 51.2}}, "mytiny.json")
    with pytest.raises(SystemExit) as stop:
        reproduce(["--out", str(tmp_path / "run"), "--data", str(tmp_path / "data"), "--preset", str(preset_file)])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and "usage:" not in err and err.count("\n") == 1, err
    assert err.startswith(f"error: --preset {preset_file}: the recipe takes a registered preset's name, not a preset "
                          "file"), err
    assert not (tmp_path / "run").exists()


# ------------------------------------------------------------------------------------ 5. a resumed run's --preset
def test_a_resume_keeps_the_preset_spelling_the_run_was_started_with(one_frame: Path, tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """Resumed with a copy of its preset file, the state recorded the copy's path: a later refusal said the run
    was "started with --preset …override_copy.json"."""
    content = {"base": "tiny", "name": "override", "bev": {"x_max": 51.2}}
    first = _file(tmp_path, content, "override.json")
    argv = _with_preset(args("detector", tmp_path / "run", one_frame, "--input", "lidar16", "--no-progress"), first)
    assert main(argv) == 0
    copy = _file(tmp_path / "elsewhere", content, "override_copy.json")
    argv[argv.index("--epochs") + 1] = "2"
    assert main([*_with_preset(argv, copy), "--resume"]) == 0
    other = _file(tmp_path, {**content, "name": "other"}, "other.json")
    argv[argv.index("--epochs") + 1] = "3"
    says = refused([*_with_preset(argv, other), "--resume"], capsys)
    assert f"but {tmp_path / 'run'} was started with --preset {first} (preset 'override'" in says, says


REPO = Path(__file__).resolve().parents[1]


def test_a_split_camera_pixor_starts_from_the_shipped_lidar_only_onnx() -> None:
    """docs/models.md's camera PIXOR starts from the 16-line PIXOR: the shipped pixor.onnx takes its BEV in
    channel pieces (bev[0:16], bev[16:19]), whose sum is the LiDAR grid's, so the split net is widened from it
    (its pseudo channels at zero) instead of being refused as another preset's."""
    import torch

    from models.onnx_weights import load_onnx_weights
    from models.start_weights import load_start_weights
    from pipeline.presets import lidar_only

    preset = get_preset("edge-split-near35")
    net = build_pixor(preset)
    load_start_weights(net, "pixor", REPO / "weights" / "edge-lidar16" / "pixor.onnx", preset)
    lidar = build_pixor(lidar_only(preset))
    load_onnx_weights(lidar, REPO / "weights" / "edge-lidar16" / "pixor.onnx")
    first, lidar_first = net.stem[0][0].weight, lidar.stem[0][0].weight
    channels = lidar_first.shape[1]
    assert torch.equal(first[:, :channels], lidar_first) and not first[:, channels:].any()


def test_a_train_only_start_compares_the_networks_section_but_the_added_head() -> None:
    """--train-only refine on an exported depth net may add the refine head (its fields differ from the
    export's), but not read the image in another view: that is still refused."""
    import torch

    from models import build_network
    from models.onnx_weights import load_onnx_weights
    from models.start_weights import load_start_weights

    onnx = REPO / "weights" / "edge" / "depth.onnx"
    refine = get_preset("edge-refine")
    net = build_network("depth", refine)
    initial = {key: value.clone() for key, value in net.state_dict().items()}
    load_start_weights(net, "depth", onnx, refine, train_only=("refine",))
    # The export's weights went in: every tensor outside the added head is what the graph holds (read into a second
    # net), and the encoder's convolutions are no longer their initialisation; the refine head kept its own.
    exported = build_network("depth", refine)
    assert load_onnx_weights(exported, onnx, optional=("refine",)) == ("refine",)
    loaded, read = net.state_dict(), exported.state_dict()
    outside = [key for key in loaded if not key.startswith("refine.")]
    assert [key for key in outside if not torch.equal(loaded[key], read[key])] == []
    # (Convolutions only: the graph's batch norms come folded in, so theirs are read back as the identity.)
    encoder = [key for key in outside if key.startswith(("conv1_d.", "layer")) and loaded[key].dim() == 4]
    assert encoder and not any(torch.equal(loaded[key], initial[key]) for key in encoder)
    head = [key for key in loaded if key.startswith("refine.")]
    assert head and all(torch.equal(loaded[key], initial[key]) for key in head)
    quarter = replace(refine, name="quarter-refine",
                      depth=replace(refine.depth, input_scale=0.25, input_hw=(88, 304)))
    with pytest.raises(ValueError, match="whose depth configuration differs from the requested preset 'quarter-refine'"):
        load_start_weights(build_network("depth", quarter), "depth", onnx, quarter, train_only=("refine",))
