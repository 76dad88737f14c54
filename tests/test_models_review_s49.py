"""Session 49's review of models/: ResNet-18 files without batch counters, the trainer's car pixels against the
depth evaluation's, the joint task's refused flags, and the evaluation folders' names."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from evaluation.depth_metrics import car_surface, moderate_cars_in_view
from models import build_depth_net
from models.data import car_pixels, depth_target
from models.depth_net import load_resnet18_encoder
from pipeline.frame import load_frame
from pipeline.presets import get_preset
from tests.conftest import KITTI
from tests.test_models import torchvision_resnet18_state


# --------------------------------------------------------------------------- ResNet-18 files without counters
def test_a_resnet18_file_without_batch_counters_loads_its_weights_and_keeps_the_nets_counters(tmp_path: Path) -> None:
    """``num_batches_tracked`` are batch-norm counters, not weights, and torchvision's published files may lack
    them: such a file loads every tensor it has (before: refused, 'checkpoint lacks 19 encoder tensors')."""
    state = {name: tensor for name, tensor in torchvision_resnet18_state().items()
             if not name.endswith("num_batches_tracked")}
    path = tmp_path / "resnet18-no-counters.pth"
    torch.save(state, path)
    model = build_depth_net(get_preset("paper"))
    counters = {name: tensor.clone() for name, tensor in model.state_dict().items()
                if name.startswith("layer") and name.endswith("num_batches_tracked")}
    assert len(counters) == 19  # the 19 counters of layer1–layer4's batch norms
    loaded = load_resnet18_encoder(model, path)
    ours = model.state_dict()
    assert sorted(loaded) == sorted(name for name in state if name.startswith("layer"))
    assert all(torch.equal(ours[name], state[name]) for name in loaded)
    assert all(torch.equal(ours[name], counter) for name, counter in counters.items())


# --------------------------------------------------------------------------- car pixels as the evaluation counts them
def test_car_pixels_are_the_depth_evaluations_car_pixels_at_the_edge_scale() -> None:
    """On KITTI 000006 (three moderate cars) in the edge preset's view (scale 0.5), the trainer's car pixels are
    exactly the union of the evaluation's (each moderate car's box in the view, on its surface); before, the
    trainer mapped the boxes without the half-pixel offset (s − 1)/2 and 28 pixels on the box edges differed."""
    preset = get_preset("edge")
    assert preset.depth.input_scale != 1.0  # the offset matters only on a resized view
    frame = load_frame(KITTI, "000006")
    moderate = [label for label in frame.labels
                if moderate_cars_in_view([label], frame.image_hw, preset.crop_hw, preset.depth.input_scale)]
    assert len(moderate) == 3
    frame = replace(frame, labels=moderate)  # car_pixels weighs every car; the evaluation counts moderate ones
    target = depth_target(KITTI, frame, preset)
    expected = np.zeros(target.shape, bool)
    for car in moderate_cars_in_view(frame.labels, frame.image_hw, preset.crop_hw, preset.depth.input_scale):
        window, on_car = car_surface(target, car.box, car.z)
        expected[window] |= on_car
    assert expected.sum() > 500
    np.testing.assert_array_equal(car_pixels(frame, target, preset), expected)


# --------------------------------------------------------------------------- joint runs: flags they would ignore
@pytest.mark.parametrize(("extra", "says"), [
    (["--compile", "on"], "error: --compile: not used by a joint run ("),
    (["--workers", "2"], "error: --workers: not used by a joint run ("),
])
def test_a_joint_run_refuses_compile_and_workers_it_would_ignore(tmp_path, capsys, extra, says) -> None:
    """A joint run computes its soft BEV per frame (no fixed shapes to compile for) and loads its frames in the
    training loop itself: --compile on and --workers N were accepted and silently ignored. One line naming the
    flag, exit status 2, nothing written."""
    from models.train import main

    split = tmp_path / "one.txt"
    split.write_text("000006\n")
    out = tmp_path / "run"
    argv = ["joint", "--data", str(KITTI), "--train-split", str(split), "--val-split", str(split), "--preset", "tiny",
            "--out", str(out), "--epochs", "1", "--batch-size", "1", "--depth-checkpoint", "d.pt",
            "--pixor-checkpoint", "p.pt", *extra]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(says), err
    assert not out.exists()


# --------------------------------------------------------------------------- the recipe's evaluation folders
def test_the_recipes_evaluation_folders_have_clean_names() -> None:
    """Each row of the recipe's table (tests/test_reproduce.py checks these are its rows) gets its own folder under
    OUT/eval without spaces, ``+`` or parentheses; the joint row's came out as ``lidar16_camera_(joint``
    (strip("()") removed only the closing parenthesis)."""
    from models.reproduce import eval_folder

    rows = ("lidar64", "lidar16", "lidar16+camera", "lidar16+camera (joint)")
    folders = [eval_folder(row) for row in rows]
    assert folders == ["lidar64", "lidar16", "lidar16_camera", "lidar16_camera_joint"]
