"""Training: data loaders on real frames, the differentiable BEV, a quick run, exact resume."""

import json
import logging
import shutil

import numpy as np
import pytest
import torch

from models.data import DepthCompletionDataset, DepthDataset, DetectorDataset
from models.soft_bev import soft_occupancy
from models.train import TrainConfig, run
from pipeline.beams import emulate_beams_on_depth_map
from pipeline.bev import voxelize_bev
from pipeline.frame import load_frame
from pipeline.kitti import read_calib, read_depth_png, read_velodyne
from pipeline.presets import PRESETS
from pipeline.provenance import code_version
from tests.conftest import KITTI


def test_depth_dataset_on_real_object_frames():
    preset = PRESETS["edge"]
    dataset = DepthDataset(KITTI, ["000006", "000003"], preset)
    rgb, sparse, target = dataset[0]
    assert rgb.shape == (3, 176, 608) and sparse.shape == target.shape == (1, 176, 608)
    # Without depth_2 the target is the full 64-line scan: about four times the 16-line input.
    ratio = int((target > 0).sum()) / int((sparse > 0).sum())
    assert 2.5 < ratio < 5.0


def test_depth_dataset_weights_the_labelled_cars_own_pixels(small_sim):
    """With car_weight, a 4th field weighs the car pixels (inside a labelled car's box, on its surface):
    they exist, lie on the cars' depths, and the mirrored sample mirrors them with the target."""
    from evaluation.depth_metrics import CAR_SURFACE_M

    preset = PRESETS["tiny"]
    ids = [p.stem for p in sorted((small_sim / "velodyne").glob("*.bin"))]
    plain = DepthDataset(small_sim, ids, preset)
    weighted = DepthDataset(small_sim, ids, preset, car_weight=10.0, augment=True)
    assert len(plain[0]) == 3
    found = 0
    for index in range(len(ids)):
        _, _, target, weight = weighted[index]
        assert set(torch.unique(weight).tolist()) <= {1.0, 10.0}
        cars = weight > 1
        found += int(cars.sum())
        assert (target[cars] > 0).all()
        unflipped = plain[index][2]
        mirrored = not torch.equal(target, unflipped)
        assert torch.equal(target, unflipped.flip(-1) if mirrored else unflipped)
        labels = load_frame(small_sim, ids[index]).labels
        depths = torch.tensor([o.location[2] for o in labels if o.type == "Car"])
        if cars.any():  # each weighted pixel is within the surface margin of some labelled car's depth
            assert ((target[cars][:, None] - depths[None]).abs() <= CAR_SURFACE_M + 1e-4).any(dim=1).all()
    assert found > 0


def test_detector_dataset_targets_and_mirror():
    preset = PRESETS["edge"]
    plain = DetectorDataset(KITTI, ["000006"], preset, "lidar64")
    bev, score, regression = plain[0]
    assert bev.shape == preset.bev.shape and score.shape == (1, 100, 88) and regression.shape == (6, 100, 88)
    assert int(score.sum()) > 10  # four cars
    mirrored = DetectorDataset(KITTI, ["000006"], preset, "lidar64", augment=True)
    flips = []
    for epoch in range(6):
        mirrored.epoch = epoch
        _m_bev, m_score, _ = mirrored[0]
        flips.append(torch.equal(m_score[0], torch.flip(score[0], dims=[0])))
        assert torch.equal(m_score, score) or flips[-1]
    assert any(flips) and not all(flips)  # the mirror is drawn per epoch


def test_detector_samples_without_pixels_equal_those_with(tmp_path):
    """Detector samples read only the image's size; pseudo points still land where the full frame puts them."""
    from models.data import detector_points
    from pipeline.kitti import write_depth_png

    preset = PRESETS["edge"]
    write_depth_png(tmp_path / "000006.png", np.full(preset.depth.input_hw, 12.5, np.float32))
    full, light = load_frame(KITTI, "000006"), load_frame(KITTI, "000006", with_image=False)
    assert light.image is None and light.image_hw == full.image_hw == (374, 1238)
    for mode in ("lidar64", "lidar16", "pseudo"):
        np.testing.assert_array_equal(detector_points(light, preset, mode, tmp_path),
                                      detector_points(full, preset, mode, tmp_path))


def test_split_detector_samples_keep_the_pseudo_points_apart(tmp_path):
    """--preset …-split --input pseudo: the sample's first channels are the 16-line scan's own BEV, the
    rest the pseudo points' occupancy, mirrored with the scan; the shared grid's sample is their union."""
    from models.data import detector_clouds
    from pipeline.beams import emulate_beams
    from pipeline.kitti import write_depth_png
    from pipeline.presets import get_preset

    preset = PRESETS["edge"]
    split = get_preset("edge-split")
    nz = preset.bev.nz
    write_depth_png(tmp_path / "000006.png", np.full(preset.depth.input_hw, 12.5, np.float32))
    lidar16 = voxelize_bev(emulate_beams(load_frame(KITTI, "000006").points, 16), preset.bev)
    shared = DetectorDataset(KITTI, ["000006"], preset, "pseudo", pseudo_dir=tmp_path)[0][0].numpy()
    bev = DetectorDataset(KITTI, ["000006"], split, "pseudo", pseudo_dir=tmp_path)[0][0].numpy()
    assert bev.shape == split.bev.shape
    np.testing.assert_array_equal(bev[:nz + 1], lidar16)
    np.testing.assert_array_equal(np.maximum(bev[:nz], bev[nz + 1:]), shared[:nz])
    assert bev[nz + 1:].sum() > 0 and lidar16[:nz].sum() > 0
    # The mirror flips the pseudo points with the scan.
    pseudo, real = detector_clouds(load_frame(KITTI, "000006", with_image=False), split, "pseudo", tmp_path)
    mirror = np.array([1, -1, 1, 1], np.float32)
    mirrored = DetectorDataset(KITTI, ["000006"], split, "pseudo", pseudo_dir=tmp_path, augment=True)
    samples = []
    for epoch in range(6):
        mirrored.epoch = epoch
        samples.append(mirrored[0][0].numpy())
    flipped = [b for b in samples if not np.array_equal(b, bev)]
    assert flipped and len(flipped) < len(samples)
    np.testing.assert_array_equal(flipped[0][:nz + 1], voxelize_bev(real * mirror, preset.bev))
    np.testing.assert_array_equal(flipped[0][nz + 1:], voxelize_bev(pseudo * mirror, preset.bev)[:nz])


def test_split_pixor_starts_as_the_lidar_only_pixor_it_is_loaded_from(tmp_path):
    """A split PIXOR loaded from a LiDAR-only checkpoint of the same grid gives that checkpoint's outputs
    whatever its pseudo channels hold: their weights start at zero."""
    from models import build_pixor
    from models.checkpoint import save_checkpoint
    from models.start_weights import load_start_weights
    from pipeline.presets import get_preset

    lidar = build_pixor(PRESETS["tiny"]).eval()
    torch.manual_seed(0)
    for module in lidar.modules():  # statistics that are not the identity, so a mistake would show
        if isinstance(module, torch.nn.BatchNorm2d):
            module.running_mean.uniform_(-0.2, 0.2)
            module.running_var.uniform_(0.5, 2.0)
    path = save_checkpoint(tmp_path / "pixor.pt", PRESETS["tiny"], {"pixor": lidar}, {})
    split_preset = get_preset("tiny-split")
    split = build_pixor(split_preset).eval()
    load_start_weights(split, "pixor", path, split_preset)
    grid = split_preset.bev
    bev = torch.rand((1, *grid.shape)) < 0.05
    bev = bev.float()
    with torch.no_grad():
        for a, b in zip(split(bev), lidar(bev[:, :grid.lidar_channels]), strict=True):
            torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert not split.stem[0][0].weight[:, grid.lidar_channels:].any()


def test_depth_completion_layout_emulates_16_lines(depth_completion_dir):
    calib = read_calib(KITTI / "calib" / "000003.txt")  # same recording day's calibration as the drive
    raw = read_depth_png(depth_completion_dir / "velodyne_raw" / "0000000005.png")
    thinned = emulate_beams_on_depth_map(raw, calib, 16)
    kept = np.count_nonzero(thinned) / np.count_nonzero(raw)
    assert 0.2 < kept < 0.3
    assert np.all((thinned == 0) | (thinned == raw))
    dataset = DepthCompletionDataset(depth_completion_dir, ["0000000005"], PRESETS["edge"], calib)
    rgb, sparse, target = dataset[0]
    assert rgb.shape == (3, 176, 608) and sparse.shape == target.shape == (1, 176, 608)
    assert 0 < int((sparse > 0).sum()) < int((target > 0).sum())


def test_depth_completion_samples_are_depth_samples_of_the_drives_frames(make_drive):
    """A drive's samples come as DepthDataset's do (uint8 view pixels cached, inputs = 2, mirrored with the
    input when augmented): the 16 lines thinned through the drive's own calibration, KITTI's ground truth as the
    target in the network's view. Without a calibration thinning is refused by name, not an AttributeError."""
    from pipeline.depth_completion import drive_calibration, read_frame
    from pipeline.errors import InputError
    from pipeline.preprocess import depth_view, view_from_depth_png

    preset = PRESETS["tiny"]
    drive = make_drive(frame_ids=("0000000005", "0000000006"))
    calib = drive_calibration(drive)
    plain = DepthCompletionDataset(drive, ["0000000005", "0000000006"], preset, calib)
    assert DepthCompletionDataset.inputs == 2
    rgb, sparse, target = plain[0]
    frame = read_frame(drive, "0000000005", calib, 16)
    view_rgb, view_sparse = view_from_depth_png(frame.image, frame.sparse, preset)
    assert torch.equal(rgb, torch.from_numpy(view_rgb[0])) and torch.equal(sparse, torch.from_numpy(view_sparse[0]))
    assert torch.equal(target, torch.from_numpy(depth_view(frame.ground_truth, preset)[None]))
    assert 0 < int((sparse > 0).sum()) < int((target > 0).sum())
    assert plain.cache.items[0][0].dtype == np.uint8
    augmented = DepthCompletionDataset(drive, plain.frame_ids, preset, calib, augment=True)
    mirrored = []
    for epoch in range(6):  # the mirror is drawn per epoch and frame
        augmented.epoch = epoch
        rgb_a, sparse_a, target_a = augmented[0]
        flipped = torch.equal(sparse_a, sparse.flip(-1))
        assert flipped or torch.equal(sparse_a, sparse)
        assert torch.equal(target_a, target.flip(-1) if flipped else target) and not torch.equal(rgb_a, rgb)
        mirrored.append(flipped)
    assert any(mirrored) and not all(mirrored)
    with pytest.raises(InputError, match=r"thinning its scans to 16 lines needs the drive's calibration"):
        DepthCompletionDataset(drive, ["0000000005"], preset, None)[0]
    whole = DepthCompletionDataset(drive, ["0000000005"], preset, None, beams=None)[0][1]  # as given: no calibration
    assert int((whole > 0).sum()) > 2 * int((sparse > 0).sum())


def test_soft_occupancy_forward_is_the_hard_grid_and_has_gradient():
    grid = PRESETS["edge"].bev
    points = read_velodyne(KITTI / "velodyne" / "000006.bin").points
    xyz = torch.tensor(points[:, :3], requires_grad=True)
    occupancy = soft_occupancy(xyz, grid)
    np.testing.assert_array_equal(occupancy.detach().numpy(), voxelize_bev(points, grid)[:-1])
    (occupancy * torch.rand_like(occupancy)).sum().backward()
    inside = (points[:, 0] > 1) & (points[:, 0] < 69) & (np.abs(points[:, 1]) < 39) & (points[:, 2] > -2.3) & (points[:, 2] < 0.9)
    assert torch.count_nonzero(xyz.grad[torch.from_numpy(inside)].abs().sum(dim=1)) > 0.9 * inside.sum()
    assert torch.count_nonzero(xyz.grad[torch.from_numpy(points[:, 0] < -5)]) == 0


@pytest.fixture(scope="module")
def small_sim(tmp_path_factory):
    from simulation.run import RunConfig
    from simulation.run import run as simulate

    out = tmp_path_factory.mktemp("sim")
    simulate(RunConfig(out=out, frames=3, seed=11, workers=1, progress=False))
    return out


def test_joint_bev_on_a_split_grid_is_the_hard_grid_with_gradient_in_the_pseudo_channels_only():
    """Joint fine-tuning on a -split preset: the forward BEV is the voxelizer's (scan channels, then the
    pseudo points' own), and only the pseudo channels pass a gradient back to the depth map."""
    from models.joint import joint_bev
    from pipeline.beams import emulate_beams
    from pipeline.preprocess import network_view
    from pipeline.presets import get_preset
    from pipeline.pseudo import pixel_rays, pseudo_xyz

    preset = get_preset("tiny-split")
    frame = load_frame(KITTI, "000006")
    lidar16 = emulate_beams(frame.points, 16)
    _, view_calib = network_view(frame.image, frame.calib, preset)
    h, w = preset.depth.input_hw
    depth_map = np.repeat(np.linspace(40, 4, h, dtype=np.float32)[:, None], w, axis=1)
    rays, origin = pixel_rays(view_calib, h, w, preset.decode.pseudo_stride)
    depth = torch.from_numpy(depth_map)[None].requires_grad_(True)
    bev = joint_bev(depth, torch.from_numpy(rays), torch.from_numpy(origin.astype(np.float32)), lidar16, preset)
    limits = (preset.depth.min_depth, preset.depth.max_depth, preset.decode.pseudo_stride,
              preset.decode.pseudo_max_height)
    expected = voxelize_bev(lidar16, preset.bev, pseudo=pseudo_xyz(depth_map, view_calib, *limits))
    nz = preset.bev.nz
    assert bev.shape == preset.bev.shape
    np.testing.assert_array_equal(bev[:nz + 1].detach().numpy(), expected[:nz + 1])
    # Pseudo bins: float32 back-projection here, float64 rays in pseudo_xyz; a point on a bin edge may differ.
    assert np.mean(bev[nz + 1:].detach().numpy() != expected[nz + 1:]) < 1e-4
    bev[:nz + 1].sum().backward(retain_graph=True)
    assert depth.grad is None or not depth.grad.any()
    bev[nz + 1:].sum().backward()
    assert depth.grad is not None and depth.grad.abs().sum() > 0


def test_quick_depth_and_detector_runs_reduce_the_loss(small_sim, tmp_path):
    depth = run(TrainConfig(task="depth", data=small_sim, preset="tiny", out=tmp_path / "depth", quick=True,
                            epochs=3, lr=1e-3, progress=False))
    assert depth.last_loss < depth.first_loss
    assert (tmp_path / "depth" / "depth.pt").exists() and (tmp_path / "depth" / "log.jsonl").exists()
    assert {"rmse_mm", "mae_mm", "val_loss"} <= set(depth.history[-1])
    # The labelled validation frames also say where the cars' pixels land (only bands that have cars).
    shares = {k: v for k, v in depth.history[-1].items() if k.startswith("car_in_box_")}
    assert shares and set(shares) <= {"car_in_box_0-20", "car_in_box_20-35", "car_in_box_35-50"}
    assert all(0.0 <= v <= 1.0 for v in shares.values())
    strays = {k: v for k, v in depth.history[-1].items() if k.startswith("car_stray_")}
    assert strays and {k.replace("stray", "in_box") for k in strays} <= set(shares)
    assert all(0.0 <= v <= 1.0 for v in strays.values())
    detector = run(TrainConfig(task="detector", data=small_sim, preset="tiny", out=tmp_path / "det", quick=True,
                               epochs=3, progress=False))
    assert detector.last_loss < detector.first_loss
    assert "bev_ap_0.7_moderate" in detector.history[-1]


def test_resume_is_exact(small_sim, tmp_path):
    common = {"task": "detector", "data": small_sim, "preset": "tiny", "epochs": 2, "batch_size": 2,
              "progress": False, "max_train_frames": 3, "max_val_frames": 1}
    straight = run(TrainConfig(out=tmp_path / "straight", **common))
    run(TrainConfig(out=tmp_path / "interrupted", **{**common, "epochs": 1}))
    resumed = run(TrainConfig(out=tmp_path / "interrupted", resume=True, **common))
    a = torch.load(tmp_path / "straight" / "state.pt", weights_only=False)["networks"]["pixor"]
    b = torch.load(tmp_path / "interrupted" / "state.pt", weights_only=False)["networks"]["pixor"]
    for key in a:
        assert torch.equal(a[key], b[key]), key
    for key in ("train_loss", "val_loss", "lr"):
        assert [h[key] for h in straight.history] == [h[key] for h in resumed.history], key


def test_train_only_trains_the_refine_head_from_exported_weights_and_keeps_the_rest(small_sim, tmp_path,
                                                                                    tiny_models):
    """--preset tiny-refine --depth-checkpoint depth.onnx --train-only refine, from a tiny export that has no
    head: the head's weights and its own batch-norm statistics move; every other weight and statistic is
    still the exported one."""
    from models import build_depth_net
    from models.checkpoint import load_checkpoint
    from models.onnx_weights import load_onnx_weights
    from pipeline.presets import get_preset

    start = tiny_models / "depth.onnx"
    result = run(TrainConfig(task="depth", data=small_sim, preset="tiny-refine", out=tmp_path / "r", quick=True,
                             epochs=2, lr=1e-2, depth_loss="l1", depth_checkpoint=start, train_only=("refine",),
                             progress=False))
    exported = build_depth_net(get_preset("tiny-refine"))
    assert load_onnx_weights(exported, start, optional=("refine",)) == ("refine",)
    trained = torch.load(tmp_path / "r" / "state.pt", weights_only=False)["networks"]["depth"]
    moved = [k for k, v in exported.state_dict().items() if not torch.equal(v, trained[k])]
    # Only the head moved (its out conv starts at zero and its batch norms at 0 / 1 in both builds).
    assert moved and all(k.startswith("refine.") for k in moved), moved
    assert any(k.startswith("refine.out.") for k in moved) and any(k.endswith("running_mean") for k in moved)
    metadata = load_checkpoint(result.checkpoints["depth"]).metadata
    recipe = metadata["recipe"]
    assert recipe["train_only"] == ["refine"] and recipe["depth_start"] == str(start)
    assert metadata["code"] == code_version()  # which code trained it (into the manifest's training record)


def test_freeze_bn_fine_tunes_exported_weights_and_keeps_their_statistics(small_sim, tmp_path, tiny_models, caplog):
    """--pixor-checkpoint pixor.onnx --freeze-bn: every weight may move, the (folded, identity) batch-norm
    statistics do not, and a run without the flag does move them, with a warning that says so; both say what
    they loaded."""
    from models import build_pixor
    from models.onnx_weights import load_onnx_weights

    exported = build_pixor(PRESETS["tiny"])
    load_onnx_weights(exported, tiny_models / "pixor.onnx")
    before = exported.state_dict()
    common = {"task": "detector", "data": small_sim, "preset": "tiny", "quick": True, "epochs": 1, "lr": 1e-3,
              "pixor_checkpoint": tiny_models / "pixor.onnx", "progress": False}
    for frozen in (True, False):
        caplog.clear()
        with caplog.at_level(logging.INFO):
            run(TrainConfig(out=tmp_path / str(frozen), freeze_bn=frozen, **common))
        assert f"loaded pixor weights from {tiny_models / 'pixor.onnx'}" in caplog.messages
        warned = [m for m in caplog.messages if "batch norms are folded into its convolutions; without --freeze-bn" in m]
        assert len(warned) == (0 if frozen else 1), caplog.messages
        after = torch.load(tmp_path / str(frozen) / "state.pt", weights_only=False)["networks"]["pixor"]
        statistics = [k for k in before if k.endswith(("running_mean", "running_var"))]
        moved = [k for k in statistics if not torch.equal(before[k], after[k])]
        assert (moved == []) == frozen, moved
        assert any(not torch.equal(before[k], after[k]) for k in before if k.endswith(".weight"))


def test_train_only_refuses_a_submodule_the_network_lacks(small_sim, tmp_path):
    from pipeline.errors import InputError

    with pytest.raises(InputError, match="no submodule 'decoder'"):
        run(TrainConfig(task="depth", data=small_sim, preset="tiny", out=tmp_path / "r", quick=True, epochs=1,
                        train_only=("decoder",), progress=False))


def test_refuses_to_overwrite_a_run(small_sim, tmp_path):
    from pipeline.errors import InputError

    config = {"task": "depth", "data": small_sim, "preset": "tiny", "out": tmp_path / "r", "quick": True,
              "epochs": 1, "progress": False}
    run(TrainConfig(**config))
    with pytest.raises(InputError, match="pass --resume"):
        run(TrainConfig(**config))


@pytest.mark.parametrize(("flag", "value", "says"), [
    ("--epochs", "0", "must be at least 1, got 0"),  # 0 used to fall through to the recipe's 30 epochs
    ("--batch-size", "0", "must be at least 1, got 0"),
    ("--lr", "0", "must be a positive number"),
    ("--workers=-1", None, "must be 0 or more"),
])
def test_command_refuses_counts_and_rates_that_are_not_positive(tmp_path, capsys, flag, value, says):
    from models.train import main

    with pytest.raises(SystemExit) as stop:
        main(["detector", "--data", str(KITTI), "--preset", "tiny", "--out", str(tmp_path / "r"),
              *([flag] if value is None else [flag, value])])
    assert stop.value.code == 2 and not (tmp_path / "r").exists()
    assert f"argument {flag.split('=')[0]}: {says}" in capsys.readouterr().err


def test_pseudo_detector_validates_on_the_validation_depth_maps(small_sim, tmp_path, tiny_models):
    from models.cache_pseudo import run as cache_pseudo

    train_pseudo, val_pseudo = tmp_path / "pseudo_train", tmp_path / "pseudo_val"
    cache_pseudo(small_sim, tiny_models, val_pseudo, progress=False)
    cache_pseudo(small_sim, tiny_models, train_pseudo, progress=False)
    (train_pseudo / "000002.png").unlink()  # only the validation folder has frame 000002
    result = run(TrainConfig(task="detector", data=small_sim, preset="tiny", out=tmp_path / "run", input_mode="pseudo",
                             pseudo_dir=train_pseudo, val_pseudo_dir=val_pseudo, epochs=1, batch_size=2,
                             max_train_frames=2, progress=False))
    assert result.history[0]["val_loss"] > 0


def test_pseudo_cache_is_not_mixed_across_depth_nets_or_line_counts(small_sim, tmp_path, tiny_models):
    """A cache folder resumes with the depth net and line count that made it; others are refused."""
    from export.precision import convert_precision
    from models.cache_pseudo import run as cache_pseudo
    from pipeline.errors import InputError

    cache = tmp_path / "pseudo"
    assert cache_pseudo(small_sim, tiny_models, cache, progress=False) > 0
    assert cache_pseudo(small_sim, tiny_models, cache, progress=False) == 0  # resumed: nothing left to do
    with pytest.raises(InputError, match="another depth net or line count"):
        cache_pseudo(small_sim, tiny_models, cache, beams=8, progress=False)
    convert_precision(tiny_models, tmp_path / "int8", "int8", KITTI, calibration_frames=2)
    with pytest.raises(InputError, match="another depth net or line count"):
        cache_pseudo(small_sim, tmp_path / "int8", cache, progress=False)


def test_pseudo_maps_of_another_data_set_are_refused_by_frame(small_sim, tmp_path, tiny_models):
    """Frame ids repeat across data sets: a cache of one set's maps is refused for another set's frames of the
    same ids, by cache_pseudo (nothing made or overwritten) and by a training run whose --val-data would read
    them through the default --val-pseudo-dir, before its --out is made."""
    from models.cache_pseudo import run as cache_pseudo
    from pipeline.errors import InputError
    from simulation.run import RunConfig
    from simulation.run import run as simulate

    other = tmp_path / "other"
    simulate(RunConfig(out=other, frames=3, seed=12, workers=1, progress=False))
    cache = tmp_path / "pseudo"
    assert cache_pseudo(small_sim, tiny_models, cache, progress=False) == 3
    maps = {path.name: path.read_bytes() for path in cache.iterdir()}
    with pytest.raises(InputError, match=rf"--out {cache}: its map of frame 000000 was made from other files than "
                                         rf"frame 000000 of --data {other} .*; 2 more frame\(s\) too"):
        cache_pseudo(other, tiny_models, cache, progress=False)
    assert {path.name: path.read_bytes() for path in cache.iterdir()} == maps
    assert cache_pseudo(small_sim, tiny_models, cache, progress=False) == 0  # its own frames: all there

    config = {"task": "detector", "data": small_sim, "val_data": other, "preset": "tiny", "out": tmp_path / "run",
              "input_mode": "pseudo", "pseudo_dir": cache, "epochs": 1, "batch_size": 2, "progress": False}
    with pytest.raises(InputError, match=rf"--pseudo-dir {cache}: its map of frame 000000 .* of --val-data {other} .*"
                                         "give it as --val-pseudo-dir"):
        run(TrainConfig(**config))
    assert not (tmp_path / "run").exists()
    own = tmp_path / "pseudo_other"
    assert cache_pseudo(other, tiny_models, own, progress=False) == 3
    assert run(TrainConfig(**config, val_pseudo_dir=own)).history[0]["val_loss"] > 0

    # Frames made again since their maps were cached are other frames too.
    (small_sim / "calib" / "000001.txt").write_text((small_sim / "calib" / "000001.txt").read_text() + "\n")
    try:
        with pytest.raises(InputError, match=rf"--pseudo-dir {cache}: its map of frame 000001 .* of --data"):
            run(TrainConfig(**{**config, "out": tmp_path / "run2"}, val_pseudo_dir=own))
    finally:
        calib = small_sim / "calib" / "000001.txt"
        calib.write_text(calib.read_text()[:-1])


def test_detector_checkpoints_are_selected_by_ap_not_loss():
    from models.train import selection_criterion

    epoch1 = {"val_loss": 1.50, "bev_ap_0.7_moderate": 31.6, "bev_ap_0.5_moderate": 74.1}
    epoch2 = {"val_loss": 1.54, "bev_ap_0.7_moderate": 55.3, "bev_ap_0.5_moderate": 80.0}
    assert selection_criterion("detector", epoch2) < selection_criterion("detector", epoch1)
    assert selection_criterion("joint", epoch2) < selection_criterion("joint", epoch1)
    assert selection_criterion("depth", {"val_loss": 1.0}) < selection_criterion("depth", {"val_loss": 2.0})


def test_precision_and_layout_choices():
    from models import build_depth_net, build_pixor
    from models.devices import autocast, channels_last_safe, resolve_precision
    from pipeline.errors import InputError

    assert resolve_precision("auto") in ("bf16", "fp32")
    with pytest.raises(InputError, match="--precision"):
        resolve_precision("fp16")
    # tiny has the 8-channel 1x1 stride-2 shortcut that oneDNN's channels-last backward corrupts; edge has none.
    assert not channels_last_safe({"pixor": build_pixor(PRESETS["tiny"])})
    assert channels_last_safe({"pixor": build_pixor(PRESETS["edge"]), "depth": build_depth_net(PRESETS["edge"])})
    # bf16 autocast stays close to fp32 on the edge PIXOR (what the training loop runs).
    torch.manual_seed(0)
    pixor = build_pixor(PRESETS["edge"]).eval().to(memory_format=torch.channels_last)
    bev = (torch.rand(1, *PRESETS["edge"].bev.shape) > 0.97).float().contiguous(memory_format=torch.channels_last)
    with torch.no_grad():
        reference, _ = pixor.forward_logits(bev)
        with autocast("bf16"):
            low, _ = pixor.forward_logits(bev)
    assert low.dtype == torch.bfloat16
    assert torch.allclose(low.float(), reference, atol=0.05 * float(reference.abs().max()))


def test_device_choice_is_checked():
    from models.devices import resolve_device
    from pipeline.errors import InputError

    assert resolve_device("cpu").type == "cpu"
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(InputError, match="--device"):
        resolve_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(InputError, match="sees no CUDA GPU"):
            resolve_device("cuda")


# Run in a fresh interpreter (the thresholds are the process's own), with models/allocator.py loaded by path so
# that torch, whose import allocates on its own, stays out. glibc's mallinfo2 reports the bytes held in mmapped
# blocks (hblkhd) and in the heap (arena): a 64 MB buffer is mmapped, and the heap trimmed once it is freed, unless
# the thresholds are raised above it.
_MALLOC_THRESHOLDS = r"""
import ctypes, importlib.util, sys
class MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                     "fsmblks", "uordblks", "fordblks", "keepcost")]
libc = ctypes.CDLL("libc.so.6")
libc.mallinfo2.restype = MallInfo2
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
applied = None
if sys.argv[2] == "keep":
    spec = importlib.util.spec_from_file_location("allocator", sys.argv[1])
    allocator = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(allocator)
    applied = allocator.keep_freed_memory()
before = libc.mallinfo2()
buffer = libc.malloc(64 << 20)
ctypes.memset(buffer, 1, 64 << 20)
held = libc.mallinfo2()
libc.free(buffer)
after = libc.mallinfo2()
print(applied, held.hblkhd - before.hblkhd, held.arena - before.arena, held.arena - after.arena)
"""


def test_training_keeps_freed_memory_on_glibc():
    """models.train fixes glibc's mmap/trim thresholds (a PIXOR epoch 16 % shorter here); elsewhere a no-op.
    With them a 64 MB buffer comes from the heap, not a fresh mmap, and freeing it leaves the heap as large."""
    import platform
    import subprocess
    import sys
    from pathlib import Path

    if not (platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"):
        from models.allocator import keep_freed_memory

        assert keep_freed_memory() is False
        return
    allocator = Path(__file__).resolve().parents[1] / "models" / "allocator.py"

    def buffer_accounting(mode: str) -> tuple[str, int, int, int]:
        done = subprocess.run([sys.executable, "-c", _MALLOC_THRESHOLDS, str(allocator), mode], capture_output=True,
                              text=True, timeout=60, check=True)
        applied, mmapped, heap_grew, trimmed = done.stdout.split()
        return applied, int(mmapped), int(heap_grew), int(trimmed)

    size = 64 << 20
    applied, mmapped, heap_grew, trimmed = buffer_accounting("keep")
    assert applied == "True"
    assert mmapped < size <= heap_grew  # served from the heap
    assert trimmed < size // 2  # and kept there once freed
    # Without the thresholds the same buffer is mmapped and unmapped: the test can fail.
    applied, mmapped, heap_grew, _ = buffer_accounting("plain")
    assert applied == "None" and mmapped >= size and heap_grew < size


def test_sample_cache_gives_the_samples_a_fresh_load_gives():
    """Datasets keep each frame's pre-augmentation sample in memory: every epoch's augmented tensors equal
    those of a dataset that loads the frame again, the cache stays intact, and the byte budget holds."""
    from models.data import DepthDataset, SampleCache

    preset = PRESETS["edge"]
    ids = ["000006", "000001"]
    datasets = {
        "depth": (DepthDataset(KITTI, ids, preset, augment=True), DepthDataset(KITTI, ids, preset, augment=True,
                                                                              cache=SampleCache(max_bytes=0))),
        "detector": (DetectorDataset(KITTI, ids, preset, "lidar16", augment=True),
                     DetectorDataset(KITTI, ids, preset, "lidar16", augment=True, cache=SampleCache(max_bytes=0))),
    }
    for name, (cached, fresh) in datasets.items():
        for epoch in range(4):  # the mirror and brightness draws differ per epoch
            cached.epoch = fresh.epoch = epoch
            for index in range(len(ids)):
                for a, b in zip(cached[index], fresh[index], strict=True):
                    assert torch.equal(a, b), (name, epoch, index)
        assert len(cached.cache.items) == 2 and not fresh.cache.items, name
        assert cached.cache.nbytes == sum(a.nbytes for item in cached.cache.items.values() for a in item)
    rgb = datasets["depth"][0].cache.items[0][0]
    assert rgb.dtype == np.uint8  # the view's pixels, exact, a quarter of float32's memory
    budget = SampleCache(max_bytes=datasets["depth"][0].cache.nbytes // 2 + 1)  # room for one of the two
    one = DepthDataset(KITTI, ids, preset, cache=budget)
    one[0], one[1]
    assert list(budget.items) == [0] and budget.nbytes <= budget.max_bytes


def test_compile_choice():
    from models.devices import COMPILE_MIN_STEPS, resolve_compile
    from pipeline.errors import InputError

    assert not resolve_compile("off", "detector", 10**6)
    assert not resolve_compile("auto", "joint", 10**6)  # joint stays eager
    assert not resolve_compile("auto", "detector", COMPILE_MIN_STEPS - 1)  # a smoke test does not pay a minute
    if shutil.which("c++") or shutil.which("g++") or shutil.which("clang++"):
        assert resolve_compile("auto", "depth", COMPILE_MIN_STEPS)
        assert resolve_compile("on", "detector", 1)
    with pytest.raises(InputError, match="--compile"):
        resolve_compile("sometimes", "detector", 1)


@pytest.mark.skipif(not (shutil.which("c++") or shutil.which("g++")), reason="torch.compile on the CPU needs a C++ compiler")
def test_compiled_training_computes_what_eager_training_does(small_sim, tmp_path):
    """The same detector run, compiled and eager: the same losses up to float rounding, and the checkpoint
    of the compiled run is the module's own state (no wrapper prefixes), so export reads it as always."""
    from models.checkpoint import load_checkpoint

    common = {"task": "detector", "data": small_sim, "preset": "tiny", "epochs": 2, "batch_size": 2,
              "progress": False, "max_train_frames": 4, "max_val_frames": 1, "precision": "fp32"}
    eager = run(TrainConfig(out=tmp_path / "eager", compile="off", **common))
    compiled = run(TrainConfig(out=tmp_path / "compiled", compile="on", **common))
    for a, b in zip(eager.history, compiled.history):
        assert b["train_loss"] == pytest.approx(a["train_loss"], rel=1e-4)
        assert b["val_loss"] == pytest.approx(a["val_loss"], rel=1e-4)
    log = [json.loads(line) for line in (tmp_path / "compiled" / "log.jsonl").read_text().splitlines()]
    assert [entry["epoch"] for entry in log] == [1, 2]
    state = load_checkpoint(compiled.checkpoints["pixor"])
    eager_state = load_checkpoint(eager.checkpoints["pixor"])
    assert state.metadata["recipe"]["compiled"] and not eager_state.metadata["recipe"]["compiled"]
    assert set(state.state_dicts["pixor"]) == set(eager_state.state_dicts["pixor"])


def test_batches_come_in_the_training_layout_with_the_values_of_a_plain_stack(small_sim):
    """The loader builds the network inputs of a batch straight in channels-last; targets stay as stacked."""
    from torch.utils.data import default_collate

    from models.train import loader
    from pipeline.frame import frame_ids

    dataset = DetectorDataset(small_sim, frame_ids(small_sim), PRESETS["tiny"], "lidar16")
    (bev, score, regression), = list(loader(dataset, 3, False, 0, 0, inputs=dataset.inputs, layout=torch.channels_last))
    plain = default_collate([dataset[i] for i in range(3)])
    assert bev.is_contiguous(memory_format=torch.channels_last) and bev.stride(1) == 1
    assert score.is_contiguous() and regression.is_contiguous() and regression.stride(1) != 1
    for got, expected in zip((bev, score, regression), plain):
        assert torch.equal(got, expected)
