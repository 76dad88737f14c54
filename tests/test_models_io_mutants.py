"""Training data and weight I/O (models/data.py, cache_pseudo.py, checkpoint.py, start_weights.py,
onnx_weights.py): behaviours a mutation audit found no test pinning (session 45's audit of these modules).

Each test names the mutant it was seen to fail on. Real KITTI frames from tests/data and tiny hand-built
inputs; the tiny model directory is exported once per session (conftest's ``tiny_models``).
"""

from __future__ import annotations

import json
import re
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from models import build_depth_net, build_pixor
from models.data import (
    DepthDataset,
    DetectorDataset,
    car_boxes,
    depth_sample,
    detector_clouds,
)
from pipeline.beams import emulate_beams
from pipeline.calib import depth_crop
from pipeline.errors import InputError
from pipeline.frame import Frame, load_frame
from pipeline.kitti import Object3D, write_depth_png
from pipeline.preprocess import depth_inputs
from pipeline.presets import PRESETS, get_preset
from tests.conftest import KITTI

TINY = PRESETS["tiny"]


# --------------------------------------------------------------------------- models/data.py
def test_a_depth_sample_is_the_runtimes_own_network_input():
    """The module's promise: training sees exactly what the Detector feeds the depth net, channel for channel
    (mutant: the rgb planes reversed, BGR for RGB)."""
    frame = load_frame(KITTI, "000006")
    rgb, sparse, _ = DepthDataset(KITTI, ["000006"], TINY)[0]
    inputs = depth_inputs(frame.image, emulate_beams(frame.points, 16), frame.calib, TINY)
    assert torch.equal(rgb, torch.from_numpy(inputs.rgb[0]))
    assert torch.equal(sparse, torch.from_numpy(inputs.sparse_depth[0]))


def _item() -> tuple[np.ndarray, ...]:
    """A depth item as the cache holds it: uint8 rgb whose every plane differs left to right, sparse, target."""
    rng = np.random.default_rng(0)
    rgb = rng.integers(20, 200, (3, 6, 10), dtype=np.uint8)
    sparse = rng.uniform(1, 50, (1, 6, 10)).astype(np.float32)
    return rgb, sparse, sparse * 2


def test_the_mirrored_depth_sample_mirrors_the_image_with_its_depths():
    """A mirrored sample's image is the mirrored image, brightened: an affine map of it pixel by pixel, not of
    the unmirrored one (mutant: rgb left as it was while its depths were mirrored)."""
    rgb, sparse, _ = _item()
    flips = 0
    for epoch in range(8):
        got_rgb, got_sparse, _ = depth_sample(_item(), True, (0, epoch, 0))
        mirrored = torch.equal(got_sparse, torch.from_numpy(sparse[..., ::-1].copy()))
        source = (rgb[..., ::-1] if mirrored else rgb).astype(np.float64).ravel()
        fit = np.polyfit(source, got_rgb.numpy().astype(np.float64).ravel(), 1)  # clip never bites: 20..200
        np.testing.assert_allclose(np.polyval(fit, source), got_rgb.numpy().ravel(), atol=1e-3)
        flips += mirrored
    assert 0 < flips < 8


def _flips(key_of) -> list[bool]:
    sparse = _item()[1]
    return [not torch.equal(depth_sample(_item(), True, key_of(i))[1], torch.from_numpy(sparse)) for i in range(16)]


def test_augmentation_is_drawn_per_seed_and_per_frame():
    """--seed changes which samples are mirrored, and the frames of one epoch are mirrored independently
    (mutants: the seed or the frame index dropped from the generator's key)."""
    assert _flips(lambda i: (0, 3, i)) == _flips(lambda i: (0, 3, i))  # reproducible
    assert _flips(lambda i: (0, i, 5)) != _flips(lambda i: (1, i, 5))  # another seed: another pattern over epochs
    per_frame = _flips(lambda i: (0, 3, i))
    assert any(per_frame) and not all(per_frame)  # one epoch: some frames mirrored, others not


def test_detector_mirroring_depends_on_the_seed():
    """DetectorDataset draws its mirror from (seed, epoch, frame) too (mutant: the seed dropped)."""
    patterns = []
    for seed in (0, 1):
        dataset = DetectorDataset(KITTI, ["000006"], TINY, "lidar64", augment=True, seed=seed)
        plain_points = dataset.cache.get(0, dataset._load)[1]
        pattern = []
        for epoch in range(12):
            dataset.epoch = epoch
            bev = dataset[0][0]
            pattern.append(not torch.equal(bev, torch.from_numpy(_plain_bev(plain_points))))
        patterns.append(pattern)
    assert patterns[0] != patterns[1]


def _plain_bev(points: np.ndarray) -> np.ndarray:
    from pipeline.bev import voxelize_bev

    return voxelize_bev(points, TINY.bev)


def test_samples_never_share_memory_with_the_cache():
    """Changing a sample's tensor in place (a transform, a loss written in place) leaves the next epoch's sample
    as it was (mutant: the sparse map handed out as a view of the cached array)."""
    dataset = DepthDataset(KITTI, ["000006"], TINY)
    first = dataset[0]
    for tensor in first:
        tensor.fill_(-1.0)
    again = dataset[0]
    assert all(float(t.min()) >= 0.0 for t in again)


def test_a_car_weight_below_one_weighs_the_cars_down():
    """--car-weight takes any positive number: 0.5 gives the cars' pixels half the weight, it does not drop the
    weights (mutant: the weight field only for weights above 1)."""
    sample = DepthDataset(KITTI, ["000006"], TINY, car_weight=0.5)[0]
    assert len(sample) == 4
    assert set(torch.unique(sample[3]).tolist()) == {0.5, 1.0}


def _label(kind: str, z: float) -> Object3D:
    """A car-sized label of class ``kind``, ``z`` metres ahead of the camera."""
    return Object3D(kind, 0.0, 0, 0.0, (500.0, 170.0, 600.0, 220.0), (1.5, 1.6, 3.9), (0.0, 1.6, z), 0.0)


def test_vans_are_not_cars():
    """The detector's targets are KITTI's Car class alone; a Van (its own class, ignored in the Car evaluation)
    is no positive (mutant: Car and Van)."""
    calib = load_frame(KITTI, "000006", with_image=False).calib
    frame = Frame("000006", None, np.zeros((0, 4), np.float32), calib, [_label("Car", 10.0), _label("Van", 20.0)],
                  size_hw=(375, 1242))
    boxes = car_boxes(frame)
    assert boxes.shape == (1, 7)
    assert boxes[0, 0] == pytest.approx(10.0 + 0.27, abs=0.1)  # the car's 10 m (the LiDAR sits 0.27 m behind)


def _frame_copy(folder: Path, fid: str = "000006") -> Path:
    """An object folder of one real frame, its files linked (a test replaces the ones it changes)."""
    for sub, suffix in (("velodyne", ".bin"), ("image_2", ".png"), ("calib", ".txt"), ("label_2", ".txt")):
        (folder / sub).mkdir(parents=True)
        (folder / sub / f"{fid}{suffix}").symlink_to(KITTI / sub / f"{fid}{suffix}")
    return folder


def test_a_car_is_a_car_whatever_the_case_of_its_class_as_the_evaluation_reads_it(tmp_path):
    """Labels writing "car" trained PIXOR on no positive (and --car-weight on no pixel) while the evaluation, which
    compares classes case-insensitively, scored the net on those cars (session 47's review); Van and Vehicle stay
    other classes."""
    calib = load_frame(KITTI, "000006", with_image=False).calib
    kinds = ("car", "CAR", "Car", "Van", "Vehicle")
    frame = Frame("000006", None, np.zeros((0, 4), np.float32), calib,
                  [_label(kind, 10.0 + 5 * i) for i, kind in enumerate(kinds)], size_hw=(375, 1242))
    assert car_boxes(frame)[:, 0] == pytest.approx([10.27, 15.27, 20.27], abs=0.1)
    data = _frame_copy(tmp_path / "data")
    labels = data / "label_2" / "000006.txt"
    labels.unlink()
    labels.write_text((KITTI / "label_2" / "000006.txt").read_text().replace("Car ", "car "))
    weights = DepthDataset(data, ["000006"], TINY, car_weight=5.0)[0][3]
    assert set(torch.unique(weights).tolist()) == {1.0, 5.0}


def test_a_depth_target_of_another_size_or_missing_beside_other_maps_is_refused_by_name(tmp_path):
    """A depth_2 map twice its image's size was cropped by its own shape: the target of another part of the scene
    (session 47's review); one missing where depth_2/ holds maps trained on the scan instead. Each is an error
    naming the map (training checks both up front, models.run_checks; this is the loader's own guard)."""
    data = _frame_copy(tmp_path / "data")
    (data / "depth_2").mkdir()
    dense = data / "depth_2" / "000006.png"
    write_depth_png(dense, np.full((748, 2476), 9.0))
    with pytest.raises(InputError) as caught:
        DepthDataset(data, ["000006"], TINY)[0]
    assert str(caught.value) == f"{dense}: a 2476×748 depth map for a 1238×374 image; it must cover the whole image"
    dense.unlink()
    with pytest.raises(InputError, match=rf"^{re.escape(str(dense))}: cannot read depth PNG"):
        DepthDataset(data, ["000006"], TINY)[0]
    write_depth_png(dense, np.full((374, 1238), 9.0))
    assert torch.unique(DepthDataset(data, ["000006"], TINY)[0][2]).tolist() == [9.0]  # the map's, in the view


def test_an_unknown_input_is_refused_by_name():
    """A typo'd --input (library callers pass no argparse choices) is named, not read as ``pseudo`` (mutant: the
    check deleted, which asked for --pseudo-dir instead)."""
    frame = load_frame(KITTI, "000006", with_image=False)
    with pytest.raises(InputError, match=r"^--input: 'lidar32' is not one of lidar64, lidar16, pseudo$"):
        detector_clouds(frame, TINY, "lidar32", None)


def test_pseudo_points_fall_back_into_the_crop_of_the_image_they_came_from(tmp_path):
    """A cached map is in the depth net's view (the crop, scaled): its points, projected with the frame's own
    calibration, land in the crop window at the map's depth and span its width (mutant: the full image's
    calibration used for the view's pixels, which puts them in the image's top-left corner)."""
    frame = load_frame(KITTI, "000006", with_image=False)
    write_depth_png(tmp_path / "000006.png", np.full(TINY.depth.input_hw, 12.5, np.float32))
    pseudo, _ = detector_clouds(frame, TINY, "pseudo", tmp_path)
    assert len(pseudo) > np.prod(TINY.depth.input_hw) // 2  # most pixels: the ones below the height cut
    uv, depth = frame.calib.velo_to_image(pseudo[:, :3])
    crop = depth_crop(frame.image_hw, *TINY.crop_hw)
    np.testing.assert_allclose(depth, 12.5, atol=0.01)
    assert uv[:, 0].min() >= crop.left - 1 and uv[:, 0].max() <= crop.left + crop.width + 1
    assert uv[:, 1].min() >= crop.top - 1 and uv[:, 1].max() <= crop.top + crop.height + 1
    assert uv[:, 0].max() - uv[:, 0].min() > 0.95 * crop.width


# --------------------------------------------------------------------------- models/cache_pseudo.py
def _pseudo_folder(folder: Path, record: object, frames: tuple[str, ...] = ("000006",)) -> Path:
    """A cache folder as models.cache_pseudo leaves it: a map per frame (constant 12.5 m) and ``record``."""
    folder.mkdir()
    for fid in frames:
        write_depth_png(folder / f"{fid}.png", np.full(TINY.depth.input_hw, 12.5, np.float32))
    (folder / "cache.json").write_text(json.dumps(record))
    return folder


def test_maps_of_the_stored_scans_are_refused_for_a_16_line_run(tmp_path, capsys):
    """Maps cached with --emulate-beams 0 are the depth of the scans as stored; a detector run thinning to 16
    lines is refused them by name, before it trains (mutant: a recorded 0 read as "no record")."""
    from models.cache_pseudo import source_sizes
    from models.train import main

    maps = _pseudo_folder(tmp_path / "pseudo", {"beams": 0, "frames": {"000006": source_sizes(KITTI, "000006")}})
    split = tmp_path / "one.txt"
    split.write_text("000006\n")
    out = tmp_path / "run"
    code = main(["detector", "--data", str(KITTI), "--train-split", str(split), "--val-split", str(split),
                 "--preset", "tiny", "--out", str(out), "--epochs", "1", "--input", "pseudo", "--pseudo-dir", str(maps)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err[-1] == (f"error: --pseudo-dir {maps}: its maps were made with --emulate-beams 0 "
                                     "(cache.json), this run thins its scans with --emulate-beams 16; cache them with "
                                     "python -m models.cache_pseudo --emulate-beams 16")
    assert not out.exists()


def test_a_record_that_is_no_json_object_counts_as_none(tmp_path):
    """cache.json holding a JSON list (hand-edited, or another tool's) is read as no record: no frame is claimed
    for other sources (mutant: the list handed on, an AttributeError trace)."""
    from models.cache_pseudo import check_sources, recorded_beams, recorded_sources

    folder = _pseudo_folder(tmp_path / "pseudo", [1, 2, 3])
    assert recorded_sources(folder) == {} and recorded_beams(folder) is None
    check_sources(folder, "--pseudo-dir", KITTI, "--data", ["000006"])  # nothing to refuse


def test_the_count_of_further_clashing_frames_is_exact(tmp_path):
    """Two frames cached from other files: the first is named and "1 more" counted (mutant: the count shown
    only past two clashes)."""
    from models.cache_pseudo import check_sources

    other = {"000003": [1, 2, 3], "000006": [4, 5, 6]}
    folder = _pseudo_folder(tmp_path / "pseudo", {"beams": 16, "frames": other}, tuple(other))
    with pytest.raises(InputError) as refused:
        check_sources(folder, "--pseudo-dir", KITTI, "--data", ["000003", "000006"])
    assert str(refused.value).startswith(f"--pseudo-dir {folder}: its map of frame 000003 was made from other files "
                                         f"than frame 000003 of --data {KITTI} (another data set, or its frames made "
                                         "again); 1 more frame(s) too; cache --data's frames")
    with pytest.raises(InputError) as refused:
        check_sources(folder, "--pseudo-dir", KITTI, "--data", ["000006"])
    assert "more frame(s)" not in str(refused.value)


def test_an_incomplete_frame_is_named_alone_or_with_the_count_of_others(tmp_path):
    """The one-line refusal of frames --data lacks files of: exact, with "N more" only when there are more
    (mutant: "0 more frame(s) are incomplete too" after a single one). Checked before any model is read."""
    from models.cache_pseudo import run

    split = tmp_path / "split.txt"
    for listed, more in (("000006\n999999\n", ""), ("999998\n000006\n999999\n", "; 1 more frame(s) are incomplete too")):
        split.write_text(listed)
        first = listed.split()[0] if listed.startswith("9") else "999999"
        with pytest.raises(InputError) as refused:
            run(KITTI, tmp_path / "no-models", tmp_path / "out", split_file=split, progress=False)
        assert str(refused.value) == (f"--data {KITTI}: frame {first} (listed in --split-file {split}) has no "
                                      f"velodyne/{first}.bin, image_2/{first}.png, calib/{first}.txt{more}")
    assert not (tmp_path / "out").exists()


def test_maps_follow_the_line_count_asked_and_unrecorded_maps_are_made_again(tiny_models, tmp_path):
    """--emulate-beams 32 caches the depth of the 32-line scan; a map whose sources the record lacks (a run
    stopped between writing it and recording it) is made again, not taken as done (mutants: the scan always
    thinned to 16 lines; a map skipped because its file exists)."""
    from models.cache_pseudo import RECORD, recorded_beams, recorded_sources, run
    from pipeline.detector import Detector
    from pipeline.kitti import read_depth_png

    split = tmp_path / "one.txt"
    split.write_text("000006\n")
    out = tmp_path / "pseudo"
    assert run(KITTI, tiny_models, out, split_file=split, beams=32, progress=False) == 1
    frame = load_frame(KITTI, "000006", with_labels=False)
    detector = Detector(tiny_models, networks_used=("depth",))
    expected = {lines: detector.dense_depth(frame.image, emulate_beams(frame.points, lines), frame.calib)[0]
                for lines in (16, 32)}
    assert np.abs(expected[32] - expected[16]).max() > 0.1  # the line count shows in the map
    np.testing.assert_allclose(read_depth_png(out / "000006.png"), expected[32], rtol=0, atol=1 / 512 + 1e-6)
    assert recorded_beams(out) == 32 and list(recorded_sources(out)) == ["000006"]

    record = json.loads((out / RECORD).read_text())
    record["frames"] = {}
    (out / RECORD).write_text(json.dumps(record))
    assert run(KITTI, tiny_models, out, split_file=split, beams=32, progress=False) == 1
    assert list(recorded_sources(out)) == ["000006"]


def test_a_cache_folder_carries_its_record_before_its_first_map(tiny_models, tmp_path):
    """The record is written before any map: a run killed right after its first map leaves a folder a rerun
    resumes, not "PNGs but no cache.json" it must refuse. Staged with a first frame the Detector refuses (an image
    of half the size): the folder then holds the record and nothing else (mutant: the record first written
    after the first map)."""
    import cv2

    from models.cache_pseudo import run

    data = tmp_path / "data"
    for folder, ext in (("velodyne", ".bin"), ("image_2", ".png"), ("calib", ".txt")):
        (data / folder).mkdir(parents=True)
        (data / folder / f"000000{ext}").symlink_to(KITTI / folder / f"000006{ext}")
    half = data / "image_2" / "000000.png"
    half.unlink()
    cv2.imwrite(str(half), cv2.imread(str(KITTI / "image_2" / "000006.png"))[::2, ::2])
    out = tmp_path / "pseudo"
    with pytest.raises(InputError, match="frame 000000: image: "):
        run(data, tiny_models, out, progress=False)
    assert sorted(p.name for p in out.iterdir()) == ["cache.json"]
    record = json.loads((out / "cache.json").read_text())
    assert record["beams"] == 16 and record["preset"] == "tiny" and record["frames"] == {}


# --------------------------------------------------------------------------- models/checkpoint.py
def test_what_is_not_a_checkpoint_file_is_named_as_such(tmp_path):
    """A folder is "not found" as a checkpoint file; a torch file of another program (a dict without the format
    field) is "not a lowres3d checkpoint", not a KeyError (mutants: is_file → exists; the format check dropped)."""
    from models.checkpoint import load_checkpoint

    (tmp_path / "run").mkdir()
    with pytest.raises(FileNotFoundError, match=r"run: checkpoint not found$"):
        load_checkpoint(tmp_path / "run")
    torch.save({"preset": "tiny", "state_dict": {}}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match=r"other\.pt: not a lowres3d checkpoint \(expected format"):
        load_checkpoint(tmp_path / "other.pt")


def test_weights_are_refused_for_another_crop_or_another_meaning_of_their_outputs(tmp_path):
    """A depth net's weights depend on the crop it saw, a PIXOR's on what its regression channels mean (the
    decode section's normalisation): a preset changed there is refused by field (mutants: crop_hw, decode
    dropped from the sections compared)."""
    from models.checkpoint import load_checkpoint, load_network_weights, save_checkpoint

    path = save_checkpoint(tmp_path / "both.pt", TINY, {"depth": build_depth_net(TINY), "pixor": build_pixor(TINY)}, {})
    checkpoint = load_checkpoint(path)
    cropped = replace(TINY, crop_hw=(320, 1216))
    with pytest.raises(ValueError, match=r"as an earlier lowres3d defined it \(crop_hw\)"):
        load_network_weights(build_depth_net(cropped), checkpoint, "depth", cropped)
    means = replace(TINY, decode=replace(TINY.decode, reg_mean=(0.0, 0.0, 0.0, 0.0, 0.6, 1.4)))
    with pytest.raises(ValueError, match=r"decode\.reg_mean: \[0\.0, 0\.0, 0\.0, 0\.0, 0\.49, 1\.36\] then"):
        load_network_weights(build_pixor(means), checkpoint, "pixor", means)


def test_a_state_dict_missing_a_weight_is_refused(tmp_path):
    """A checkpoint whose state dict lacks a weight the network has never loads partly (mutant: strict=False,
    which left that weight at its initialisation)."""
    from models.checkpoint import load_checkpoint, load_network_weights, save_checkpoint

    checkpoint = load_checkpoint(save_checkpoint(tmp_path / "pixor.pt", TINY, {"pixor": build_pixor(TINY)}, {}))
    dropped = next(iter(checkpoint.state_dicts["pixor"]))
    del checkpoint.state_dicts["pixor"][dropped]
    with pytest.raises(RuntimeError, match=rf"Missing key\(s\).*{dropped}"):
        load_network_weights(build_pixor(TINY), checkpoint, "pixor", TINY)


def test_a_partial_preset_record_is_compared_by_the_sections_it_has(tmp_path):
    """A checkpoint whose preset record is not a whole preset of this version (a PIXOR's, without the depth
    section) still loads where the sections its network depends on agree, and is refused where they differ
    (mutant: the unreadable record raised instead of compared)."""
    from models.checkpoint import load_checkpoint, load_network_weights, save_checkpoint

    checkpoint = load_checkpoint(save_checkpoint(tmp_path / "pixor.pt", TINY, {"pixor": build_pixor(TINY)}, {}))
    del checkpoint.preset_config["depth"]
    load_network_weights(build_pixor(TINY), checkpoint, "pixor", TINY)
    wider = replace(TINY, bev=replace(TINY.bev, x_max=80.0))
    with pytest.raises(ValueError, match=r"bev\.x_max"):
        load_network_weights(build_pixor(wider), checkpoint, "pixor", wider)


# --------------------------------------------------------------------------- models/start_weights.py
def test_a_start_file_that_does_not_exist_is_named_by_its_flag(tmp_path):
    """--pixor-checkpoint with a misspelt path: one line naming the flag (mutant: the check dropped, which left
    the checkpoint reader's FileNotFoundError without the flag)."""
    from models.start_weights import load_start_weights

    missing = tmp_path / "pixr.pt"
    with pytest.raises(InputError, match=rf"^--pixor-checkpoint: {missing} does not exist$"):
        load_start_weights(build_pixor(TINY), "pixor", missing, TINY)


def test_a_lone_exported_file_starts_a_run(tiny_models, tmp_path):
    """An exported depth.onnx copied away from its manifest still starts a run: with no manifest there is no
    other network it could claim to be (mutant: "no manifest" read as "another network")."""
    from models.onnx_weights import load_onnx_weights
    from models.start_weights import load_start_weights

    lone = tmp_path / "depth.onnx"
    shutil.copy(tiny_models / "depth.onnx", lone)
    net, twin = build_depth_net(TINY), build_depth_net(TINY)
    load_start_weights(net, "depth", lone, TINY)
    load_onnx_weights(twin, tiny_models / "depth.onnx")
    for key, value in twin.state_dict().items():
        assert torch.equal(net.state_dict()[key], value), key


def test_a_split_pixor_starts_from_a_lidar_only_onnx_file(tiny_models):
    """An exported LiDAR-only pixor.onnx starts a split-grid PIXOR as exactly that network, its pseudo channels
    at zero, as a checkpoint does (mutant: the channel count read from the batch axis of the graph's input)."""
    from models.onnx_weights import load_onnx_weights
    from models.start_weights import load_start_weights

    split_preset = get_preset("tiny-split")
    split = build_pixor(split_preset).eval()
    load_start_weights(split, "pixor", tiny_models / "pixor.onnx", split_preset)
    lidar = build_pixor(TINY).eval()
    load_onnx_weights(lidar, tiny_models / "pixor.onnx")
    grid = split_preset.bev
    torch.manual_seed(0)
    bev = (torch.rand((1, *grid.shape)) < 0.05).float()
    with torch.no_grad():
        for a, b in zip(split(bev), lidar(bev[:, :grid.lidar_channels]), strict=True):
            torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_the_start_training_record_is_the_networks_own(tmp_path):
    """From an exported file, the run's record of how its start was trained is the manifest's entry for that
    network, and nothing for a manifest that is not JSON (mutants: the manifest's top level read; a JSON error
    raised)."""
    from models.start_weights import start_training_metadata

    (tmp_path / "depth.onnx").write_bytes(b"")  # only the manifest beside it is read
    manifest = {"training": {"epochs": 99}, "networks": {"depth": {"file": "depth.onnx", "training": {"epochs": 3}},
                                                          "pixor": {"file": "pixor.onnx", "training": {"epochs": 7}}}}
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    assert start_training_metadata(tmp_path / "depth.onnx", "depth") == {"epochs": 3}
    (tmp_path / "manifest.json").write_text("{")
    assert start_training_metadata(tmp_path / "depth.onnx", "depth") is None


def test_a_split_checkpoint_with_a_partial_preset_record_starts_a_split_run(tmp_path):
    """A split PIXOR's checkpoint whose preset record is not a whole preset of this version: reading its channel
    count fails, so it is no LiDAR-only PIXOR to widen, and it loads as itself by the sections it has (mutant: that
    failure raised, refusing a checkpoint the loader takes)."""
    from models.checkpoint import save_checkpoint
    from models.start_weights import load_start_weights

    split_preset = get_preset("tiny-split")
    torch.manual_seed(1)
    saved = build_pixor(split_preset)
    path = save_checkpoint(tmp_path / "pixor.pt", split_preset, {"pixor": saved}, {})
    payload = torch.load(path, weights_only=True)
    del payload["preset_config"]["depth"]
    torch.save(payload, path)
    net = build_pixor(split_preset)
    load_start_weights(net, "pixor", path, split_preset)
    for key, value in saved.state_dict().items():
        assert torch.equal(net.state_dict()[key], value), key


# --------------------------------------------------------------------------- models/onnx_weights.py
def test_a_folded_batch_norm_comes_back_as_an_exact_identity_plus_its_bias(tiny_models):
    """Each batch norm torch.onnx folded into its conv is read back as x ↦ x + bias to float32 precision, so the
    PyTorch twin computes the graph's numbers, not numbers scaled by 1/sqrt(1 + eps) (mutant: running_var 1,
    a 5e-6 relative error, well inside the parity tolerance)."""
    from models.onnx_weights import load_onnx_weights

    net = build_pixor(TINY).eval()
    load_onnx_weights(net, tiny_models / "pixor.onnx")
    norms = [m for m in net.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    assert norms
    for bn in norms:
        x = torch.linspace(-1000.0, 1000.0, 64).repeat(1, bn.num_features, 1, 1).reshape(1, bn.num_features, 8, 8)
        with torch.no_grad():
            torch.testing.assert_close(bn(x), x + bn.bias.view(1, -1, 1, 1), rtol=2e-7, atol=1e-4)


def test_a_weight_the_graph_lacks_is_named_and_a_missing_file_is_not_called_foreign(tiny_models, tmp_path):
    """A network holding a parameter the exported graph has no weight for is refused by ValueError naming it
    (what start_weights and the CLI answer in one line), not torch's RuntimeError from the strict load; a file
    that is not there is an OSError, not "not a readable ONNX model" (mutants: the check of unset weights dropped;
    OSError folded into the ValueError)."""
    from models.onnx_weights import load_onnx_weights, read_onnx

    net = build_pixor(TINY)
    net.register_parameter("gain", torch.nn.Parameter(torch.ones(1)))  # a weight added since the export
    with pytest.raises(ValueError, match=r"pixor\.onnx: no weights for gain$"):
        load_onnx_weights(net, tiny_models / "pixor.onnx")
    with pytest.raises(FileNotFoundError):
        read_onnx(tmp_path / "pixor.onnx")


def test_a_batch_norm_the_graph_keeps_unfolded_keeps_its_statistics(tmp_path):
    """A graph whose batch norm follows its conv unfolded (an export with the optimizer off keeps
    ``bn1.running_mean`` and friends) gives the twin those statistics: it computes what ONNX Runtime does
    (mutant: every conv's batch norm taken as folded, its statistics overwritten by the identity's)."""
    import onnx
    import onnxruntime as ort
    from onnx import helper, numpy_helper

    from models.onnx_weights import load_onnx_weights

    class ConvNorm(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.conv1 = torch.nn.Conv2d(2, 3, 3, padding=1, bias=False)
            self.bn1 = torch.nn.BatchNorm2d(3)

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return self.bn1(self.conv1(x))

    rng = np.random.default_rng(0)
    values = {"conv1.weight": rng.normal(size=(3, 2, 3, 3)), "bn1.weight": rng.uniform(0.5, 1.5, 3),
              "bn1.bias": rng.uniform(-1, 1, 3), "bn1.running_mean": rng.uniform(-1, 1, 3),
              "bn1.running_var": rng.uniform(0.5, 2.0, 3)}
    graph = helper.make_graph(
        [helper.make_node("Conv", ["x", "conv1.weight"], ["c"], name="/conv1/Conv", pads=[1, 1, 1, 1]),
         helper.make_node("BatchNormalization", ["c", *list(values)[1:]], ["y"], name="/bn1/BatchNormalization",
                          epsilon=1e-5)],
        "convnorm", [helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [1, 2, 5, 5])],
        [helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [1, 3, 5, 5])],
        [numpy_helper.from_array(v.astype(np.float32), name) for name, v in values.items()])
    path = tmp_path / "convnorm.onnx"
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), path)
    net = ConvNorm().eval()
    load_onnx_weights(net, path)
    x = rng.normal(size=(1, 2, 5, 5)).astype(np.float32)
    expected = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"x": x})[0]
    with torch.no_grad():
        np.testing.assert_allclose(net(torch.from_numpy(x)).numpy(), expected, rtol=1e-5, atol=1e-5)


# --------------------------------------------------------------------------- the run's state (models/run_checks.py)
def test_a_resumed_run_keeps_its_learning_rate_schedule(tmp_path):
    """--lr-step 2 stopped after epoch 1 and resumed: epoch 3 still trains at a tenth of the rate, as the
    uninterrupted run does (mutant: the scheduler's state not restored, which restarted the step count)."""
    from models.train import main

    split = tmp_path / "one.txt"
    split.write_text("000006\n")
    out = tmp_path / "run"
    common = ["depth", "--data", str(KITTI), "--train-split", str(split), "--val-split", str(split), "--preset", "tiny",
              "--out", str(out), "--batch-size", "1", "--compile", "off", "--lr", "0.001", "--lr-step", "2",
              "--lr-gamma", "0.1", "--no-progress"]
    assert main([*common, "--epochs", "1"]) == 0
    assert main([*common, "--epochs", "3", "--resume"]) == 0
    rates = [json.loads(line)["lr"] for line in (out / "log.jsonl").read_text().splitlines()]
    assert rates == pytest.approx([1e-3, 1e-3, 1e-4])
