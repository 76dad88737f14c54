"""Training's up-front refusals and its saved state (models/run_checks.py), pinned where a mutation audit (session 45) found
no test that fails: each test calls the check directly on a tiny hand-built folder or state, no training run.
"""

import logging
import random
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from models import build_pixor
from models.devices import autocast, resolve_compile, resolve_device, run_layout, seed_everything
from models.run_checks import (
    check_cars,
    check_frames,
    check_pseudo_maps,
    check_resumable,
    check_thinnable_scans,
    load_state,
    restore_state,
    run_lock,
    stopped_at,
)
from models.train import TrainConfig
from pipeline.beams import emulate_beams
from pipeline.errors import InputError
from pipeline.kitti import read_image_size, read_velodyne, write_depth_png, write_velodyne
from pipeline.presets import get_preset
from tests.conftest import KITTI


def _object_folder(folder: Path, frames: tuple[str, ...]) -> Path:
    """A KITTI object folder of ``frames``: copies of the real samples' files (copies, so a test may break one)."""
    for sub, suffix in (("velodyne", ".bin"), ("image_2", ".png"), ("calib", ".txt"), ("label_2", ".txt")):
        (folder / sub).mkdir(parents=True)
        for fid in frames:
            shutil.copy(KITTI / sub / f"{fid}{suffix}", folder / sub / f"{fid}{suffix}")
    return folder


def _config(task: str, data: Path, **changes) -> TrainConfig:
    return TrainConfig(task=task, data=data, preset="tiny", out=data.parent / "run", **changes)


# ----------------------------------------------------------------------------------------------- the run folder's lock
def test_a_held_run_folder_is_refused_to_a_second_holder(tmp_path):
    """Two holders of one --out (each its own open folder, as two processes have): the second is refused in one
    line, and the folder is free again once the first lets go (mutant: a shared lock, which both would get)."""
    in_use = pytest.raises(InputError, match=r"--out: .* is in use by another training process")
    with run_lock(tmp_path), in_use, run_lock(tmp_path):
        pass
    with run_lock(tmp_path):
        pass


# ------------------------------------------------------------------------------------------------- the saved state
@pytest.mark.parametrize(("state", "says"), [
    ({"epoch": 1, "networks": {}}, "no optimizer, scheduler, best, history, torch_rng, numpy_rng, python_rng"),
    ({key: {} for key in ("networks", "optimizer", "scheduler", "best", "history", "torch_rng", "numpy_rng",
                          "python_rng")} | {"epoch": "3"}, "epoch '3'"),
])
def test_a_state_without_its_keys_or_with_a_text_epoch_is_not_a_checkpoint(tmp_path, state, says):
    """A dict torch reads back is a run's state only with every key --resume restores and a whole-number epoch
    (mutants: either check dropped, which left a KeyError or TypeError traceback for later)."""
    path = tmp_path / "state.pt"
    torch.save(state, path)
    with pytest.raises(InputError, match=r"state\.pt: not a training checkpoint") as caught:
        load_state(path)
    assert says in str(caught.value)


def test_a_saved_object_that_is_not_a_dict_is_named(tmp_path):
    """torch reads back a number: one line saying what it is (mutant: the check dropped, a TypeError traceback
    from looking keys up in an int)."""
    path = tmp_path / "state.pt"
    torch.save(7, path)
    with pytest.raises(InputError, match=r"state\.pt: not a training checkpoint \(a int, not a dict\)"):
        load_state(path)


def _restorable(networks: dict) -> tuple[torch.optim.Optimizer, torch.optim.lr_scheduler.StepLR]:
    optimizer = torch.optim.SGD([p for net in networks.values() for p in net.parameters()], lr=0.1)
    return optimizer, torch.optim.lr_scheduler.StepLR(optimizer, 1)


def test_a_state_without_the_runs_network_names_it(tmp_path):
    """A state holding a detector alone, restored into a depth run's networks: one line naming the network it
    lacks and those it has (mutant: the check dropped, a KeyError traceback)."""
    networks = {"depth": torch.nn.Linear(2, 2)}
    state = {"networks": {"pixor": {}}}
    with pytest.raises(InputError, match=r"state\.pt: holds no depth network \(it has pixor\)"):
        restore_state(state, tmp_path / "state.pt", networks, *_restorable(networks), "tiny")


def test_weights_of_another_shape_name_the_first_mismatch(tmp_path):
    """Weights of another preset: the line names the mismatching tensor, not torch's heading "Error(s) in loading
    state_dict" (mutant: the heading taken as the reason)."""
    networks = {"depth": torch.nn.Linear(2, 2)}
    state = {"networks": {"depth": torch.nn.Linear(3, 2).state_dict()}}
    with pytest.raises(InputError, match=r"its depth weights do not fit --preset tiny \(size mismatch for weight"):
        restore_state(state, tmp_path / "state.pt", networks, *_restorable(networks), "tiny")


def test_an_optimizer_state_of_other_parameters_is_not_this_runs(tmp_path):
    """An optimizer state of two parameter tensors restored into a run that trains one: one line naming the state,
    not torch's ValueError traceback (mutant: ValueError not among the errors turned into that line)."""
    networks = {"depth": torch.nn.Linear(2, 2, bias=False)}
    other = torch.nn.Linear(2, 2)
    state = {"networks": {"depth": networks["depth"].state_dict()},
             "optimizer": torch.optim.SGD(other.parameters(), lr=0.1).state_dict()}
    with pytest.raises(InputError, match=r"state\.pt: not a training checkpoint of this run \(ValueError: "):
        restore_state(state, tmp_path / "state.pt", networks, *_restorable(networks), "tiny")


# --------------------------------------------------------------------------------------------------------- --resume
def test_an_older_joint_run_without_a_recorded_config_resumes_as_joint(tmp_path):
    """A state from before the configuration was recorded is told by its networks: depth and pixor together are a
    joint run, which resumes as one, and is refused as a detector run (mutant: both taken for a detector run)."""
    state = {"networks": {"depth": {}, "pixor": {}}}
    check_resumable(_config("joint", KITTI), state, tmp_path)
    with pytest.raises(InputError, match=r"task detector: .* was started as a joint run"):
        check_resumable(_config("detector", KITTI), state, tmp_path)


def test_train_only_resumes_whether_recorded_as_a_list_or_a_tuple(tmp_path):
    """--train-only recorded as a list (a library caller's run) and given as the command's tuple: the same modules,
    so the run resumes; other modules are refused (mutant: a list compared with a tuple as such, which refused
    "--train-only refine, but … was started with --train-only refine")."""
    state = {"networks": {"depth": {}}, "config": {"task": "depth", "train_only": ["refine"]}}
    check_resumable(_config("depth", KITTI, train_only=("refine",)), state, tmp_path)
    with pytest.raises(InputError, match=r"--train-only encoder, but .* was started with --train-only refine"):
        check_resumable(_config("depth", KITTI, train_only=("encoder",)), state, tmp_path)


@pytest.mark.parametrize(("flag", "key", "started", "resumed"), [
    ("--precision", "precision", "fp32", "bf16"), ("--device", "device", "cuda", "cpu"),
    ("--threads", "threads", 2, 1), ("--compile", "compile", "off", "on")])
def test_a_resume_computing_otherwise_is_warned_of_only_then(tmp_path, caplog, flag, key, started, resumed):
    """A setting that changes only how the sums run, as started: no warning; another: one warning naming both
    (mutants: the comparison inverted; --device left out of the compared settings)."""
    state = {"networks": {"depth": {}}, "config": {"task": "depth", key: started}}
    with caplog.at_level(logging.WARNING, logger="models.run_checks"):
        check_resumable(_config("depth", KITTI, **{key: started}), state, tmp_path)
        assert not caplog.records
        check_resumable(_config("depth", KITTI, **{key: resumed}), state, tmp_path)
    said = (f"{tmp_path}: resumed with {flag} {resumed}, started with {flag} {started}: the remaining epochs "
            "compute differently")
    assert [r.getMessage() for r in caplog.records] == [said]


def test_an_interrupted_run_with_an_unreadable_state_says_so_in_its_last_line(tmp_path):
    """Ctrl-C or SIGTERM in a run folder whose state.pt is not torch's: the command's last line says to start over
    elsewhere (mutant: the InputError escaped from the interrupt's handler)."""
    (tmp_path / "state.pt").write_text("garbage\n")
    assert stopped_at(tmp_path) == f"{tmp_path}: state.pt cannot be read back; start a new run in another folder"


# --------------------------------------------------------------------------------------------------- the frames' files
def test_every_frame_is_checked_not_only_the_first(tmp_path):
    """A broken scan of the second training frame is named before training (mutant: the first frame alone checked,
    which left the broken one to fail an epoch in)."""
    data = _object_folder(tmp_path / "data", ("000003", "000006"))
    scan = data / "velodyne" / "000006.bin"
    scan.write_bytes(scan.read_bytes()[:10])
    ids = ["000003", "000006"]
    with pytest.raises(InputError, match=rf"{scan}: size 10 bytes is not a whole number of 16-byte points"):
        check_frames(_config("detector", data), data, ids, data, ids)


def test_a_validation_folder_lacking_a_file_is_named_by_its_flag(tmp_path):
    """A frame of --val-data without its calibration: the line names --val-data, where the folder came from
    (mutant: named --data, the training folder's flag)."""
    train = _object_folder(tmp_path / "train", ("000006",))
    val = _object_folder(tmp_path / "val", ("000003",))
    (val / "calib" / "000003.txt").unlink()
    with pytest.raises(InputError) as caught:
        check_frames(_config("detector", train, val_data=val), train, ["000006"], val, ["000003"])
    assert str(caught.value) == f"--val-data {val}: frame 000003 has no {val / 'calib' / '000003.txt'}"


def test_a_drives_raw_scan_of_broken_points_is_named(make_drive):
    """A drive's optional raw 64-line scan (velodyne_points/) cut mid-point is named before training (mutant: its
    size not checked)."""
    drive = make_drive("drive", ("0000000005",))
    scan = drive / "velodyne_points" / "0000000005.bin"
    scan.parent.mkdir()
    scan.write_bytes(bytes(20))
    with pytest.raises(InputError, match=rf"{scan}: size 20 bytes is not a whole number of 16-byte points"):
        check_frames(_config("depth", drive), drive, ["0000000005"], drive, ["0000000005"])


def test_the_validation_folders_first_scan_is_checked_for_thinning_too(tmp_path):
    """64-line training scans and a 16-line sensor's validation scans, left at --emulate-beams 16: refused in one
    line naming the validation scan and the flag (mutant: the training folder's scan alone checked)."""
    val = tmp_path / "val"
    (val / "velodyne").mkdir(parents=True)
    scan = val / "velodyne" / "000003.bin"
    write_velodyne(scan, emulate_beams(read_velodyne(KITTI / "velodyne" / "000003.bin").points, 16))
    config = _config("detector", KITTI, val_data=val)
    with pytest.raises(InputError, match=rf"{scan}: .*--emulate-beams 0"):
        check_thinnable_scans(config, KITTI, ["000006"], val, ["000003"])


def test_pseudo_input_without_its_maps_folder_says_how_to_make_them(tmp_path):
    """--input pseudo without --pseudo-dir: one line naming the flag and the command that caches the maps
    (mutant: the check dropped, a TypeError traceback from Path(None))."""
    with pytest.raises(InputError, match=r"--input pseudo needs the cached dense depth maps \(--pseudo-dir; "):
        check_pseudo_maps(_config("detector", KITTI, input_mode="pseudo"), ["000006"], ["000006"])


def test_the_validation_frames_need_their_own_cached_maps(tmp_path):
    """--input pseudo validating on frame 000003 from a cache of 000006 alone: the missing map is named before
    training (mutant: the validation folder checked for the training frames' maps)."""
    maps = tmp_path / "pseudo"
    maps.mkdir()
    write_depth_png(maps / "000006.png", torch.full(get_preset("tiny").depth.input_hw, 12.5).numpy())
    config = _config("detector", KITTI, input_mode="pseudo", pseudo_dir=maps)
    with pytest.raises(InputError, match=rf"--pseudo-dir {maps}: no cached depth map of frame 000003"):
        check_pseudo_maps(config, ["000006"], ["000003"])


# ------------------------------------------------------------------- what a run learns from: cars, depth maps, lines
def _relabel(folder: Path, fid: str, car_as: str) -> None:
    """A frame's labels (a copy's) with their Car class written ``car_as``."""
    path = folder / "label_2" / f"{fid}.txt"
    path.write_text("".join(line.replace("Car ", f"{car_as} ", 1) + "\n" for line in path.read_text().splitlines()))


@pytest.mark.parametrize("task", ["detector", "joint"])
def test_a_run_whose_training_labels_hold_no_car_is_refused_naming_the_classes(tmp_path, task):
    """Labels calling the cars "Vehicle": the detector would train on no positive, to a low loss and AP 0, without a
    word (session 47's review: exit 0). Refused in one line naming the folder, the classes found and, when the
    validation frames hold no Car either, that too."""
    data = _object_folder(tmp_path / "data", ("000003", "000006"))
    for fid in ("000003", "000006"):
        _relabel(data, fid, "Vehicle")
    with pytest.raises(InputError) as caught:
        check_cars(_config(task, data), data, ["000003", "000006"], data, ["000003"])
    assert str(caught.value) == (f"--data {data}: no Car in the label_2 files of its 2 training frames (classes "
                                 "found: Vehicle 5, DontCare 4); the detector learns KITTI's Car class; its 1 "
                                 "validation frame label none either (AP would be 0)")
    with pytest.raises(InputError, match=r"training frames \(classes found: Vehicle 5, DontCare 4\); the detector "
                                         r"learns KITTI's Car class$"):  # validated on KITTI's own cars
        check_cars(_config(task, data, val_data=KITTI), data, ["000003", "000006"], KITTI, ["000006"])
    check_cars(_config("depth", data), data, ["000003"], data, ["000003"])  # depth targets come from no label
    # A depth run weighing the cars' pixels (--car-weight) with no car to weigh: refused as well.
    with pytest.raises(InputError, match=rf"^--car-weight 10: no Car in the label_2 files of the 1 training frame of "
                                         rf"--data {data} \(classes found: DontCare 2, Vehicle 1\), so it would weigh "
                                         r"nothing$"):
        check_cars(_config("depth", data, car_weight=10.0), data, ["000003"], data, ["000003"])


def test_cars_are_counted_whatever_the_case_of_their_class_and_validation_without_one_is_warned_of(tmp_path, caplog):
    """"car" is a Car, as the evaluation reads it (case-insensitively): accepted. Training cars and validation
    frames without one (000000: a pedestrian): a warning that their AP says nothing, no refusal."""
    data = _object_folder(tmp_path / "data", ("000000", "000006"))
    _relabel(data, "000006", "car")
    with caplog.at_level(logging.WARNING, logger="models.run_checks"):
        check_cars(_config("detector", data), data, ["000006"], data, ["000006"])
        assert caplog.messages == []
        check_cars(_config("detector", data), data, ["000006"], data, ["000000"])
    assert caplog.messages == [(f"--data {data}: no Car in the label_2 files of its 1 validation frame: their AP is 0 "
                                "whatever the detector learns, and the run's best epoch (picked by AP) means nothing")]


def _depth_maps(data: Path, ids: tuple[str, ...]) -> None:
    """``depth_2/`` maps of ``ids``, each of its image's size."""
    (data / "depth_2").mkdir()
    for fid in ids:
        write_depth_png(data / "depth_2" / f"{fid}.png", np.full(read_image_size(data / "image_2" / f"{fid}.png"), 9.0))


@pytest.mark.parametrize(("task", "wh"), [("depth", (2484, 750)), ("depth", (1216, 352)), ("joint", (621, 187))])
def test_a_depth_map_of_another_size_than_its_image_is_named_before_training(tmp_path, task, wh):
    """depth_2 maps twice, a crop of, or half the image's size: the crop is taken from the map's own shape, so the run
    trained on another part of the scene, or failed an epoch in blaming the image (session 47's review). Refused
    up front naming the map and the image it must match; maps of their own images' sizes (000003's is 1242×375,
    000006's 1238×374) pass."""
    data = _object_folder(tmp_path / "data", ("000003", "000006"))
    _depth_maps(data, ("000003", "000006"))
    ids = ["000003", "000006"]
    check_frames(_config(task, data), data, ids, data, ids)
    bad = data / "depth_2" / "000003.png"
    write_depth_png(bad, np.full(wh[::-1], 9.0))
    with pytest.raises(InputError) as caught:
        check_frames(_config(task, data), data, ids, data, ids)
    assert str(caught.value) == (f"{bad}: a {wh[0]}×{wh[1]} depth map for the 1242×375 image "
                                 f"{data / 'image_2' / '000003.png'}; it must cover the whole image, pixel for pixel")
    check_frames(_config("detector", data), data, ids, data, ids)  # a detector reads no depth map


def test_a_frame_without_its_depth_map_beside_others_with_one_is_refused(tmp_path):
    """depth_2/ with the maps of some frames: the others trained silently on their scans, two kinds of target mixed
    (session 47's review). Refused naming the first frame without one and how many more; without depth_2/ at all
    every target is the scan, as documented; a joint run's validation frames need none (it validates PIXOR)."""
    ids = ["000000", "000003", "000006"]
    data = _object_folder(tmp_path / "data", tuple(ids))
    check_frames(_config("depth", data), data, ids, data, ids)
    _depth_maps(data, ("000003",))
    with pytest.raises(InputError) as caught:
        check_frames(_config("depth", data), data, ids, data, ["000003"])
    assert str(caught.value) == (f"--data {data}: frame 000000 (and 1 more) has no depth map "
                                 f"({data / 'depth_2' / '000000.png'}) although depth_2/ holds the others' targets; "
                                 "give every frame its map, or remove depth_2/ to train on the scans")
    check_frames(_config("joint", data), data, ["000003"], data, ids)
    with pytest.raises(InputError, match=r"frame 000006 has no depth map"):
        check_frames(_config("depth", data, val_data=data), data, ["000003"], data, ["000006"])


def test_lidar64_refuses_a_16_line_sensors_scans_in_either_folder(tmp_path):
    """--input lidar64 on 16-line scans trained silently and recorded lidar64, so the exported model claimed 64
    lines (session 47's review). The first training and validation scans are judged as emulate_beams judges them
    and refused in one line naming the scan and the flags that fit; KITTI's 64-line scans pass."""
    data = _object_folder(tmp_path / "data", ("000006",))
    scan = data / "velodyne" / "000006.bin"
    write_velodyne(scan, emulate_beams(read_velodyne(scan).points, 16))
    says = (f"{scan}: --input lidar64 trains on 64-line scans as stored, but the scan has 16 rings, not 64: it is "
            "thinned already; for a 16-line sensor's scans give --input lidar16 --emulate-beams 0")
    with pytest.raises(InputError) as caught:
        check_thinnable_scans(_config("detector", data, input_mode="lidar64"), data, ["000006"], KITTI, ["000006"])
    assert str(caught.value) == says
    with pytest.raises(InputError) as caught:
        check_thinnable_scans(_config("detector", KITTI, input_mode="lidar64", val_data=data), KITTI, ["000003"], data,
                              ["000006"])
    assert str(caught.value) == says
    check_thinnable_scans(_config("detector", KITTI, input_mode="lidar64"), KITTI, ["000003"], KITTI, ["000006"])


# ------------------------------------------------------------------------------------------------- models/devices.py
def test_fp32_runs_compute_in_fp32():
    """--precision fp32 (or a CPU without bf16): the forward pass stays fp32 (mutant: autocast always on)."""
    layer = torch.nn.Linear(4, 4)
    with autocast("fp32"):
        assert layer(torch.ones(1, 4)).dtype == torch.float32
    with autocast("bf16"):
        assert layer(torch.ones(1, 4)).dtype == torch.bfloat16


def test_a_torch_device_training_does_not_support_is_refused():
    """"meta" is a torch device (no data: every result is empty) and "mps" one this code never tried: refused as
    unsupported instead of training on them (mutant: only unknown device names refused)."""
    for device in ("meta", "mps"):
        with pytest.raises(InputError, match=rf"--device: '{device}': only cpu and cuda are supported"):
            resolve_device(device)


def test_compile_on_without_a_compiler_is_refused_not_ignored(tmp_path, monkeypatch):
    """--compile on where Inductor finds no C++ compiler (none on the PATH): one line saying to install one or pass
    --compile off (mutant: silently trained eager, as if --compile auto)."""
    monkeypatch.setenv("PATH", str(tmp_path))  # an empty folder: no c++, g++ or clang++ on it
    assert not resolve_compile("auto", "detector", 10**6)
    with pytest.raises(InputError, match=r"--compile on: torch\.compile on the CPU needs a C\+\+ compiler"):
        resolve_compile("on", "detector", 1)


def test_the_tiny_preset_trains_in_the_plain_layout():
    """tiny's 8-channel 1x1 stride-2 shortcut corrupts the heap in oneDNN's channels-last backward: its networks
    train contiguous, edge's channels-last (mutant: channels-last whatever the networks)."""
    assert run_layout({"pixor": build_pixor(get_preset("tiny"))}) == torch.contiguous_format
    assert run_layout({"pixor": build_pixor(get_preset("edge"))}) == torch.channels_last


def test_seeds_apart_by_2_to_the_31_draw_other_numbers():
    """--seed 2**31 and --seed 0 are two runs, numpy's draws included (numpy takes seeds below 2**32; mutant: the
    seed folded below 2**31, which made the two the same); the same seed draws the same in all three generators."""
    def draws(seed: int) -> tuple:
        seed_everything(seed)
        return random.random(), float(np.random.random()), float(torch.rand(1))

    assert draws(2**31) == draws(2**31)
    assert draws(2**31)[1] != draws(0)[1]
