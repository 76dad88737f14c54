"""``python -m models.train``'s epoch loop and ``models.reproduce``'s recipe (mutation audit, session 46): the
recipe's defaults, each epoch's data order and augmentation, the detector's rate on a plateau, the best-epoch
choice across a resume, the log's lines; the reproduce recipe's job order, its flags, its stage reruns, its
epoch count and its table.

Every run here is the tiny preset on one to five real KITTI frames, one optimizer step an epoch; the runs
whose assertions follow the training's course compute in fp32, the same on every CPU.
"""

from pathlib import Path

import pytest
import torch

from models import build_depth_net, build_pixor
from models.checkpoint import load_checkpoint, save_checkpoint
from models.data import DepthDataset, DetectorDataset
from models.devices import CPU
from models.train import TrainConfig, depth_dataset, main, recipe, run
from models.validation import validate_depth
from pipeline.presets import get_preset
from tests.conftest import KITTI
from tests.test_own_sensor_training import _log as logged
from tests.test_train_cli import args, refused


def split_file(folder: Path, *frames: str) -> Path:
    """A split file listing ``frames`` of the KITTI samples."""
    path = folder / f"split{len(frames)}.txt"
    path.write_text("".join(f"{fid}\n" for fid in frames))
    return path


def test_an_unset_count_or_rate_is_the_documented_recipes_and_quick_shrinks_it(tmp_path):
    """README: PIXOR's 30 epochs at batch 8 and lr 1e-3, joint fine-tuning's 3 epochs at lr 1e-5 (the depth
    recipe is test_paper_fidelity's); --quick keeps at most 3 epochs, batch 2, 4 training and 2 validation
    frames, and what is given stays as given."""
    def filled(task: str, **given) -> tuple:
        config = recipe(TrainConfig(task=task, data=KITTI, preset="tiny", out=tmp_path, **given))
        return config.epochs, config.batch_size, config.lr, config.max_train_frames, config.max_val_frames

    assert filled("detector") == (30, 8, 1e-3, None, None)
    assert filled("joint")[0::2] == (3, 1e-5, None)
    assert filled("detector", epochs=2, batch_size=3, lr=0.5) == (2, 3, 0.5, None, None)
    assert filled("detector", quick=True) == (3, 2, 1e-3, 4, 2)
    assert filled("depth", quick=True, epochs=1, batch_size=1, max_train_frames=9, max_val_frames=7) == (
        1, 1, 1e-4, 9, 7)


def test_the_best_epoch_is_chosen_by_the_mean_of_both_moderate_bev_aps():
    """Detector and joint runs keep the epoch of the best mean of BEV AP at IoU 0.7 and 0.5 (moderate): where the
    two disagree the mean decides, either way (mutants: one of the two alone)."""
    from models.train import selection_criterion

    def ap(at_07: float, at_05: float) -> dict:
        return {"val_loss": 1.0, "bev_ap_0.7_moderate": at_07, "bev_ap_0.5_moderate": at_05}

    for task in ("detector", "joint"):
        assert selection_criterion(task, ap(49.0, 80.0)) < selection_criterion(task, ap(50.0, 60.0))
        assert selection_criterion(task, ap(60.0, 80.0)) < selection_criterion(task, ap(40.0, 90.0))


@pytest.mark.parametrize(("extra", "says"), [
    (["--car-weight", "5", "--depth-checkpoint", "d.pt", "--pixor-checkpoint", "p.pt"],
     "--car-weight: not used by a joint run (it weights the depth loss of a depth run)"),
    (["--depth-checkpoint", "d.pt"], "joint: pass the trained --depth-checkpoint and --pixor-checkpoint to fine-tune"),
])
def test_a_joint_run_refuses_a_car_weight_and_needs_both_checkpoints(tmp_path, capsys, extra, says):
    """--car-weight weights a depth run's loss only; a joint run without one of its two trained networks would
    fine-tune a PIXOR (or depth net) from its initialisation."""
    out = tmp_path / "run"
    assert refused(args("joint", out, split_file(tmp_path, "000006"), *extra), capsys) == f"error: {says}"
    assert not out.exists()


def test_a_library_run_of_unknown_settings_or_without_training_frames_is_refused_before_its_folder(tmp_path):
    """models.train.run (the recipe's and a script's way in, without argparse's choices) refuses a task, an input
    mode or a line count it does not know, and a training folder without a frame, before --out is made
    (mutants: the checks left out, the run failing later with a state.pt written, or with a traceback)."""
    from pipeline.errors import InputError

    common = {"task": "detector", "preset": "tiny", "out": tmp_path / "run", "epochs": 1, "val_data": KITTI,
              "val_split": split_file(tmp_path, "000006"), "compile": "off", "progress": False}
    with pytest.raises(InputError, match="--input: 'lidar32' is not one of lidar64, lidar16, pseudo"):
        run(TrainConfig(data=KITTI, input_mode="lidar32", **common))
    with pytest.raises(InputError, match="--emulate-beams: 12 is not one of 0, "):
        run(TrainConfig(data=KITTI, emulate_beams=12, **common))
    with pytest.raises(InputError, match="task: 'segment' is not one of depth, detector, joint"):
        run(TrainConfig(data=KITTI, **{**common, "task": "segment"}))
    empty = tmp_path / "empty"
    for folder in ("velodyne", "image_2", "calib", "label_2"):
        (empty / folder).mkdir(parents=True)
    with pytest.raises(InputError, match=f"--data: no frames to train on in {empty} "):
        run(TrainConfig(data=empty, **common))
    assert not (tmp_path / "run").exists()


def test_each_epoch_draws_its_own_data_order_and_augmentation_and_keeps_its_rate_while_validation_improves(
        tmp_path, monkeypatch):
    """The docstring's promise behind exact resume: the epoch's order comes from the seed and the epoch number,
    and the dataset's augmentation (on, outside --quick) from the epoch; --max-train-frames 4 of a split of 5
    trains the first 4 (mutants: one order for every epoch; the dataset left at epoch 0; no augmentation; a
    frame more). The real dataset serves every sample; the test only notes which it was asked for. The
    detector's validation loss falls every epoch here, so its rate stays (mutant: the plateau scheduler fed the
    loss's sign flipped halved it after epoch 3)."""
    served: list[tuple[int, int, bool]] = []
    getitem = DetectorDataset.__getitem__

    def noted(self, index):
        served.append((self.epoch, index, self.augment))
        return getitem(self, index)

    monkeypatch.setattr(DetectorDataset, "__getitem__", noted)
    split = split_file(tmp_path, "000000", "000001", "000003", "000006", "000004")
    out = tmp_path / "run"
    run(TrainConfig(task="detector", data=KITTI, train_split=split, val_split=split_file(tmp_path, "000006"),
                    preset="tiny", out=out, epochs=4, batch_size=4, max_train_frames=4, compile="off",
                    precision="fp32", progress=False))
    assert [(epoch, augment) for epoch, _, augment in served] == [(e, True) for e in range(4) for _ in range(4)]
    orders = [tuple(index for _, index, _ in served[i:i + 4]) for i in range(0, 16, 4)]
    assert all(sorted(order) == [0, 1, 2, 3] for order in orders) and len(set(orders)) > 1, orders
    log = logged(out)
    losses = [record["val_loss"] for record in log]
    assert losses == sorted(losses, reverse=True)  # falling: else the rate below could rightly halve
    assert [record["lr"] for record in log] == [1e-3] * 4


def test_the_detectors_rate_halves_after_two_epochs_without_a_better_validation_loss(tmp_path):
    """PIXOR's recipe: lr halved when the validation loss stops falling (patience 1: two epochs without a
    better loss). Weights that hardly move (lr 1e-6, batch norms frozen) leave the loss flat, so epochs 2 and 3
    bring no improvement and epoch 4 trains at half the rate (mutants: a tenth; patience 0). One frame with
    --batch-size 2 still makes a batch each epoch (mutant: the short last batch dropped, then no batch at all)."""
    start = tmp_path / "pixor.pt"
    torch.manual_seed(0)
    save_checkpoint(start, get_preset("tiny"), {"pixor": build_pixor(get_preset("tiny"))}, {})
    out = tmp_path / "run"
    assert main([*args("detector", out, split_file(tmp_path, "000006"), "--epochs", "4", "--lr", "1e-6",
                       "--pixor-checkpoint", str(start), "--freeze-bn", "--precision", "fp32", "--no-progress"),
                 "--batch-size", "2"]) == 0
    assert [record["lr"] for record in logged(out)] == [1e-6, 1e-6, 1e-6, 5e-7]


def test_the_best_epochs_weights_are_kept_across_a_resume_and_the_log_holds_every_epoch(tmp_path, capsys,
                                                                                           monkeypatch):
    """depth.pt holds the epoch of the lowest validation loss, not the last one, also when the run was stopped
    after that epoch and resumed (the state carries the best figure); log.jsonl has one line per epoch with the
    epoch, its loss, the rate it trained at, its seconds and its validation metrics. At lr 0.01 on one frame the
    validation loss of this run is lowest after epoch 1 (mutants: every epoch saved; the best not carried).
    It trains on augmented frames and validates on the 16-line scans it trains on, unaugmented; the recipe's
    decay is recorded, halved every 5 epochs; Adam runs without weight decay; --threads is taken, and
    --no-progress leaves out the bars the run otherwise draws."""
    augmented: set[bool] = set()
    getitem = DepthDataset.__getitem__

    def noted(self, index):
        augmented.add(self.augment)
        return getitem(self, index)

    monkeypatch.setattr(DepthDataset, "__getitem__", noted)
    split = split_file(tmp_path, "000006")
    out = tmp_path / "run"
    common = args("depth", out, split, "--lr", "0.01", "--threads", "1", "--precision", "fp32")
    threads = torch.get_num_threads()
    try:
        assert main([*common, "--epochs", "1"]) == 0
        assert torch.get_num_threads() == 1
        assert "depth epoch 1/1" in capsys.readouterr().err  # the bar, drawn into a log too
        assert main([*common, "--epochs", "3", "--resume", "--no-progress"]) == 0
        assert "depth epoch" not in capsys.readouterr().err
    finally:
        torch.set_num_threads(threads)
    assert augmented == {True, False}  # the training frames augmented (outside --quick), the validation ones not
    log = logged(out)
    assert [record["epoch"] for record in log] == [1, 2, 3]
    for record in log:
        assert {"train_loss", "lr", "seconds", "val_loss", "rmse_mm", "mae_mm"} <= set(record)
        assert record["seconds"] >= 0 and record["lr"] == 0.01  # seconds of 0.1: a tiny epoch may show 0.0
    losses = [record["val_loss"] for record in log]
    best = losses.index(min(losses)) + 1
    assert best < 3  # else the test could not tell the best epoch from the last
    kept = load_checkpoint(out / "depth.pt")
    assert kept.metadata["epoch"] == best and kept.metadata["metrics"]["val_loss"] == min(losses)
    assert kept.metadata["recipe"]["lr_decay"] == {"every_epochs": 5, "factor": 0.5}
    # Validated on the scans thinned to 16 lines as trained, not as stored (mutant: the 64-line ones).
    net = build_depth_net(get_preset("tiny"))
    net.load_state_dict(kept.state_dicts["depth"])
    for beams, alike in ((16, True), (None, False)):
        frames = depth_dataset(KITTI, ["000006"], get_preset("tiny"), beams=beams)
        assert (validate_depth(net, frames, CPU)["val_loss"] == pytest.approx(min(losses), rel=1e-5)) == alike
    state = torch.load(out / "state.pt", weights_only=False)
    assert state["epoch"] == 3 and state["best"] == min(losses) and state["history"] == log
    assert state["optimizer"]["param_groups"][0]["weight_decay"] == 0


def test_the_seed_draws_the_initial_weights(tmp_path):
    """--seed seeds the initial weights too, not only the order and augmentation: on one frame without
    augmentation (--quick) two seeds train apart, the same seed twice alike (mutant: the weights drawn from
    seed 0 whatever --seed says)."""
    split = split_file(tmp_path, "000006")
    trained = {}
    for name, seed in (("a", "0"), ("b", "0"), ("c", "1")):
        assert main(args("depth", tmp_path / name, split, "--quick", "--seed", seed, "--no-progress")) == 0
        trained[name] = torch.load(tmp_path / name / "state.pt", weights_only=False)["networks"]["depth"]
    weights = [key for key in trained["a"] if key.endswith("conv1.weight")]
    assert weights and all(torch.equal(trained["a"][key], trained["b"][key]) for key in weights)
    assert not any(torch.equal(trained["a"][key], trained["c"][key]) for key in weights)
    assert load_checkpoint(tmp_path / "c" / "depth.pt").metadata["recipe"]["seed"] == 1  # into the manifest


def test_a_joint_run_validates_the_camera_pipeline_it_fine_tunes(tmp_path):
    """A joint epoch's validation figures, which pick its best epoch, are those of PIXOR on the depth net's
    pseudo points with the scan, as the kept checkpoints compute them, not of PIXOR on the scan alone (mutant:
    the depth net left out of the joint run's validation)."""
    from models.validation import validate_detector

    preset = get_preset("tiny")
    torch.manual_seed(0)
    for name, net in (("depth", build_depth_net(preset)), ("pixor", build_pixor(preset))):
        save_checkpoint(tmp_path / f"start_{name}.pt", preset, {name: net}, {})
    out = tmp_path / "joint"
    assert main(args("joint", out, split_file(tmp_path, "000006"), "--depth-checkpoint",
                     str(tmp_path / "start_depth.pt"), "--pixor-checkpoint", str(tmp_path / "start_pixor.pt"),
                     "--no-progress")) == 0
    nets = {"depth": build_depth_net(preset), "pixor": build_pixor(preset)}
    for name, net in nets.items():
        net.load_state_dict(load_checkpoint(out / f"{name}.pt").state_dicts[name])
    (record,) = logged(out)
    camera = validate_detector(nets["pixor"], preset, KITTI, ["000006"], "lidar16", None, nets["depth"])
    scan_alone = validate_detector(nets["pixor"], preset, KITTI, ["000006"], "lidar16", None)
    assert record["val_loss"] == pytest.approx(camera["val_loss"], rel=1e-5)
    assert scan_alone["val_loss"] != pytest.approx(camera["val_loss"], rel=1e-3)
    # What the checkpoints (and so the exported manifest's training record) say its PIXOR read: pseudo points.
    assert {load_checkpoint(out / f"{name}.pt").metadata["input"] for name in nets} == {"pseudo"}


def test_a_joint_epoch_logs_the_mean_frame_loss_of_its_batches(tmp_path):
    """A joint run logs the mean loss over the frames of a batch, as the depth and detector runs log theirs
    (mutant: the batch's frame losses summed). Its one batch of 2 frames starts from the saved weights, so the
    epoch's loss is the mean of the frames' losses computed here from those weights."""
    from models.train import joint_step

    preset = get_preset("tiny")
    torch.manual_seed(0)
    starts = {"depth": build_depth_net(preset), "pixor": build_pixor(preset)}
    for name, net in starts.items():
        save_checkpoint(tmp_path / f"start_{name}.pt", preset, {name: net}, {})
    frames = ["000003", "000006"]
    out = tmp_path / "joint"
    assert main([*args("joint", out, split_file(tmp_path, *frames), "--depth-checkpoint",
                       str(tmp_path / "start_depth.pt"), "--pixor-checkpoint", str(tmp_path / "start_pixor.pt"),
                       "--precision", "fp32", "--max-val-frames", "1", "--no-progress"), "--batch-size", "2"]) == 0
    nets = {name: net.train() for name, net in starts.items()}  # as trained: batch norms on the frame's own
    expected = sum(joint_step(nets, preset, KITTI, fid).item() for fid in frames) / len(frames)
    assert logged(out)[0]["train_loss"] == pytest.approx(expected, rel=1e-4)


# ----------------------------------------------------------------------------- models.reproduce
def test_each_training_job_comes_after_the_jobs_whose_files_it_reads(tmp_path):
    """On two lanes a job starts as soon as the jobs it names are done: the pseudo PIXOR reads the cached maps
    (which need the depth net) and the 16-line branch, joint fine-tuning the depth net and the pseudo PIXOR,
    and the 16-line PIXOR's second leg trains on in the folder of its first (mutants: each dependency dropped)."""
    from models.reproduce import ReproduceConfig, training_jobs

    jobs = {job.name: job for job in training_jobs(ReproduceConfig(out=tmp_path, quick=True))}

    def before(name: str) -> set[str]:
        found: set[str] = set()
        for earlier in jobs[name].after:
            found |= {earlier} | before(earlier)
        return found

    assert {"depth", "cache_pseudo", "pixor_lidar16_branch"} <= before("pixor_pseudo")
    assert {"depth", "pixor_pseudo"} <= before("joint")
    assert "pixor_lidar16_branch" in before("pixor_lidar16")
    assert before("depth") == before("depth_no_gam") == before("pixor_lidar64") == set()


def test_quick_ships_into_out_and_bars_are_drawn_on_one_lane_only(tmp_path):
    """--quick never writes the shipped weights (its directories go to OUT/weights); a stage draws its own
    progress bars only when it runs alone (side by side they would overwrite each other)."""
    from models.reproduce import ReproduceConfig, _bars, shipped_directories

    quick = ReproduceConfig(out=tmp_path / "run", quick=True)
    assert quick.weights == tmp_path / "run" / "weights"
    assert shipped_directories(quick)["product"] == tmp_path / "run" / "weights" / "tiny"
    assert ReproduceConfig(out=tmp_path / "run").weights == Path("weights")
    assert [_bars(ReproduceConfig(lanes=lanes)) for lanes in (1, 2)] == [True, False]
    assert not _bars(ReproduceConfig(lanes=1, progress=False))


def test_the_recipe_counts_its_epochs_as_the_readme_gives_them(tmp_path):
    """README: 10 depth epochs (and as many for the no-GAM ablation), 12 per PIXOR with the camera one branching
    off after 6 and training 6, 1 joint epoch: 51 epochs the progress counts up to, read from the runs' logs
    (blank lines are no epochs)."""
    from models.reproduce import Budget, _epochs_logged, _epochs_planned

    assert _epochs_planned(Budget()) == 10 + 10 + 12 + 12 + 6 + 1
    for name, lines in (("depth", 3), ("pixor_pseudo", 2), ("joint", 1)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "log.jsonl").write_text('{"epoch": 1}\n' * lines + "\n")
    assert _epochs_logged(tmp_path) == 6


def test_the_16_line_pixor_branches_its_copy_then_resumes_to_the_whole_budget(tmp_path):
    """The camera PIXOR's start is a copy of the 16-line PIXOR's best weights after pseudo_branch_epochs (not
    its live pixor.pt, which trains on); the second leg resumes that run folder (not refused as one holding a
    run already) to the budget's epochs, validates on the budget's few frames, and reports the first and last
    loss of the whole run. A branch point the run has trained past is refused, not copied."""
    from models.reproduce import ReproduceConfig, run_stage

    data = tmp_path / "sim"
    data.mkdir()
    for split in ("train", "val"):
        (data / split).symlink_to(KITTI, target_is_directory=True)
    config = ReproduceConfig(out=tmp_path / "run", data=data, quick=True, progress=False)
    b, folder = config.budget, tmp_path / "run" / "pixor_lidar16"
    branch = run_stage(config, "pixor_lidar16_branch")
    assert Path(branch["branch"]) == folder / f"pixor_epoch{b.pseudo_branch_epochs}.pt"
    copied = (folder / "pixor.pt").read_bytes()
    assert Path(branch["branch"]).read_bytes() == copied
    whole = run_stage(config, "pixor_lidar16")
    assert [record["epoch"] for record in whole["history"]] == list(range(1, b.detector_epochs + 1))
    assert whole["first_loss"] == whole["history"][0]["train_loss"]
    assert whole["last_loss"] == whole["history"][-1]["train_loss"]
    assert Path(branch["branch"]).read_bytes() == copied  # the branch stays what it was
    kept = load_checkpoint(folder / "pixor.pt").metadata
    assert (kept["train_frames"], kept["val_frames"]) == (5, b.val_frames_during_training)
    Path(branch["branch"]).unlink()
    with pytest.raises(RuntimeError, match="past the branch point"):
        run_stage(config, "pixor_lidar16_branch")


def test_the_command_hands_its_flags_to_the_recipe_and_a_job_with_bad_input_exits_2(tmp_path, monkeypatch, capsys):
    """--car-weight reaches the depth stages' budget, --lanes and --sim-workers the run (the recipe itself is
    played by a stand-in that notes its config: the real one trains for hours); a job that failed on bad input
    exits 2, a crashed one 1, each in one line saying to rerun."""
    from models import reproduce
    from models.schedule import JobFailed

    seen = []

    def stand_in(config):
        seen.append(config)
        raise failure

    monkeypatch.setattr(reproduce, "run", stand_in)
    argv = ["--out", str(tmp_path / "run"), "--data", str(tmp_path / "sim"), "--car-weight", "3", "--lanes", "1",
            "--sim-workers", "1", "--quick"]
    for failure, status in ((JobFailed("depth", "bad frame", user_error=True), 2),
                            (JobFailed("depth", "crashed", user_error=False), 1)):
        assert reproduce.main(argv) == status
        assert capsys.readouterr().err.strip().splitlines()[-1] == f"error: {failure}; rerun the same command to resume"
    config = seen[0]
    assert (config.budget.depth_car_weight, config.lanes, config.sim_workers) == (3.0, 1, 1)
    assert config.quick and config.preset == "tiny-split-near35" and config.budget.depth_frames == 6


def _result_files(folder: Path, frames: list[str], kept: bool) -> Path:
    """KITTI result files of ``frames``: every ground-truth car found with score 1 (``kept``), or none."""
    folder.mkdir()
    for fid in frames:
        lines = [line + " 1.0" for line in (KITTI / "label_2" / f"{fid}.txt").read_text().splitlines()
                 if kept and line.startswith("Car ")]
        (folder / f"{fid}.txt").write_text("".join(f"{line}\n" for line in lines))
    return folder


def test_the_table_orders_its_columns_and_its_intervals_are_of_the_named_differences(tmp_path):
    """table.md's columns are IoU 0.5 easy / mod. / hard, then IoU 0.7; the bootstrap intervals are of
    camera − 16-line and 64-line − camera: a camera row that finds every car and a 16-line row that finds none
    give a positive first difference (mutant: the pair swapped, a negative one)."""
    from evaluation.frames import load_label_dirs
    from models.reproduce import ReproduceConfig, _how_sure, format_table

    frames = ["000000", "000001", "000003", "000004", "000006"]
    rows = {"lidar16": False, "lidar64": True, "lidar16+camera (joint)": True}
    labels = {row: load_label_dirs(KITTI / "label_2", _result_files(tmp_path / row.replace(" ", "_"), frames, kept))
              for row, kept in rows.items()}
    config = ReproduceConfig(out=tmp_path, quick=True)
    sure = _how_sure(config, labels)
    low, high = sure["bev_difference_interval_95"]["camera - lidar16"]["0.7"][1]
    assert 0 < low <= high
    assert sure["bev_difference_interval_95"]["lidar64 - camera"]["0.7"][1] == [0.0, 0.0]
    ap = {"0.5": {"R40": [1.0, 2.0, 3.0]}, "0.7": {"R40": [4.0, 5.0, 6.0]}}
    depth = {"rmse_mm": 1.0, "mae_mm": 1.0, "irmse_per_km": 1.0, "imae_per_km": 1.0}
    table = format_table({"bev_ap": {"lidar16": ap}, "depth": {"with GAMs": depth}})
    assert "| lidar16 | 1.0 | 2.0 | 3.0 | 4.0 | 5.0 | 6.0 |" in table.splitlines()
