"""The reproduce recipe's --quick variant: every stage end to end on a few synthetic frames (smoke test)."""

import json
import subprocess
import sys

from pipeline.detector import Detector
from pipeline.presets import get_preset


def test_quick_reproduce_runs_every_stage_and_losses_fall(tmp_path):
    out = tmp_path / "run"
    # The recipe's default two lanes: each training stage in a spawned process, as a user's run has them (one lane
    # would save about 40 CPU seconds of imports, and leave that path to the stand-in jobs of test_schedule.py).
    result = subprocess.run(
        [sys.executable, "-m", "models.reproduce", "--quick", "--out", str(out), "--data", str(tmp_path / "sim"),
         "--sim-workers", "1"],
        capture_output=True, text=True, timeout=900, check=False,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    report = json.loads((out / "table.json").read_text())
    for name in ("depth", "depth_no_gam", "pixor_lidar64", "pixor_lidar16", "pixor_pseudo"):
        stage = report["stages"][name]
        assert stage["last_loss"] < stage["first_loss"], (name, stage)
    assert set(report["bev_ap"]) == {"lidar64", "lidar16", "lidar16+camera", "lidar16+camera (joint)"}
    assert set(report["ap_3d"]) == set(report["bev_ap"])
    for row in (*report["bev_ap"].values(), *report["ap_3d"].values()):
        assert all(0 <= v <= 100 for iou in ("0.5", "0.7") for v in row[iou]["R40"])
    assert set(report["depth"]) == {"with GAMs", "without GAMs"}
    assert set(report["bev_by_distance"]) == set(report["bev_ap"])
    assert [band["range_m"] for band in report["bev_by_distance"]["lidar16"]] == [[0, 20], [20, 35], [35, 80]]
    for intervals in report["bev_difference_interval_95"].values():  # camera − lidar16, lidar64 − camera
        assert all(-100 <= low <= high <= 100 for iou in ("0.5", "0.7") for low, high in intervals[iou])
    table_md = (out / "table.md").read_text()
    assert table_md.startswith("Preset tiny-split-near35; budget: train_frames ")  # the table says which run it is
    assert "| lidar16+camera |" in table_md and "| BEV AP |" in table_md and "| 3D AP |" in table_md
    assert "by distance" in table_md and "| camera - lidar16 |" in table_md
    # The depth nets' moderate cars: median error and share of their pixels on the car, per band.
    for depth in report["depth"].values():
        shares = depth["car_points_in_box_by_band"]
        assert set(shares) == set(depth["car_median_abs_mm_by_band"]) == set(
            depth["car_stray_points_in_box_by_band"]) == {"0-20", "20-35", "35-50"}
        assert sum(band["cars"] for band in shares.values()) > 0
    assert "| depth net, moderate cars' own pixels |" in table_md and "/ rest of its box on it |" in table_md
    # The shipped-style directories load in the runtime, each of the right kind.
    weights = out / "weights"
    product = Detector(weights / "tiny")  # the recipe's preset: split pseudo channels, pseudo points up to 35 m
    assert product.two_stage and product.preset.name == "tiny-split-near35"
    assert product.preset.bev.split_pseudo and product.preset.depth.max_depth == 35.0
    assert not Detector(weights / "tiny-lidar16").two_stage
    manifest = json.loads((weights / "tiny" / "manifest.json").read_text())
    assert manifest["weights"] == "trained"
    # The product is the better camera pipeline at IoU 0.7, moderate: joint fine-tuning's on a tie.
    moderate = {name: report["bev_ap"][name]["0.7"]["R40"][1] for name in ("lidar16+camera", "lidar16+camera (joint)")}
    joint_better = moderate["lidar16+camera (joint)"] >= moderate["lidar16+camera"]
    assert report["shipped_from"] == ("joint fine-tuning" if joint_better else "before joint fine-tuning")
    assert manifest["networks"]["depth"]["training"]["task"] == ("joint" if joint_better else "depth")


def test_the_training_jobs_can_be_sent_to_a_spawned_lane(tmp_path):
    """With two or more lanes (the recipe's default) each training job runs in a spawned process, which gets it
    pickled: every job of the recipe, with the config it closes over, must survive the trip and still name the
    recipe's stage function (a lambda or a local function here would fail only in a multi-lane run)."""
    import pickle

    from models.reproduce import QUICK, ReproduceConfig, run_stage, training_jobs

    config = ReproduceConfig(out=tmp_path / "run", data=tmp_path / "sim", quick=True)
    jobs = training_jobs(config)
    copies = pickle.loads(pickle.dumps(jobs))
    assert [job.name for job in copies] == [job.name for job in jobs] and len(jobs) == 8
    for job, sent in zip(jobs, copies, strict=True):
        assert sent.after == job.after and sent.run.func is run_stage
        assert sent.run.args == (config, job.name) and sent.run.args[0].budget == QUICK


def test_ablation_presets():
    preset = get_preset("edge-no-gam")
    assert preset.name == "edge-no-gam" and not preset.depth.use_gam and preset.depth.use_aspp
    assert preset.bev == get_preset("edge").bev
    assert not get_preset("paper-no-aspp").depth.use_aspp
    # Suffixes stack, so the recipe's no-GAM ablation exists for a preset with the refine head too.
    stacked = get_preset("edge-refine-no-gam")
    assert stacked.name == "edge-refine-no-gam" and stacked.depth.refine_channels == 8 and not stacked.depth.use_gam
    assert get_preset("edge").depth.refine_channels == 0 and get_preset("edge") is get_preset("edge")
    # -split changes the BEV, not the depth net; lidar_only gives back the grid a LiDAR-only PIXOR reads.
    from pipeline.presets import lidar_only

    split = get_preset("edge-split-no-gam")
    assert split.bev.split_pseudo and split.bev.channels == 2 * split.bev.nz + 1 == 37 and not split.depth.use_gam
    assert lidar_only(get_preset("edge-split")) == get_preset("edge") and lidar_only(split).bev.channels == 19
    # -near35 keeps the pseudo points up to 35 m; it changes no network, and the LiDAR rows do without it.
    near = get_preset("edge-split-near35")
    assert near.depth.max_depth == 35.0 and near.bev.split_pseudo and near.pseudo_limits[1] == 35.0
    assert lidar_only(near) == get_preset("edge") and lidar_only(get_preset("edge-near35")) == get_preset("edge")
    import pytest

    with pytest.raises(ValueError, match="unknown preset 'edge-nogam'"):
        get_preset("edge-nogam")
    with pytest.raises(ValueError, match="preset 'edge-no-gam-split-no-gam': no-gam given twice"):
        get_preset("edge-no-gam-split-no-gam")  # built twice over, it would pass for edge-split-no-gam


def test_split_recipe_trains_lidar_pixors_on_the_plain_grid():
    """--preset edge-split: the camera PIXOR reads the split grid, the LiDAR-only PIXORs the same grid without
    the pseudo channels (and their directories are named after it); --quick keeps the suffix on tiny."""
    from models.reproduce import ReproduceConfig

    config = ReproduceConfig(preset="edge-split")
    assert config.lidar_preset == "edge" and get_preset(config.preset).bev.split_pseudo
    quick = ReproduceConfig(preset="edge-split", quick=True)
    assert (quick.preset, quick.lidar_preset) == ("tiny-split", "tiny")
    near = ReproduceConfig(preset="edge-split-near35", quick=True)
    assert (near.preset, near.lidar_preset) == ("tiny-split-near35", "tiny")
    assert ReproduceConfig(preset="edge-split-near35").lidar_preset == "edge"
    assert ReproduceConfig(quick=True).preset == "tiny-split-near35" and ReproduceConfig(quick=True).lidar_preset == "tiny" and ReproduceConfig(preset="paper").lidar_preset == "paper"


def test_worker_and_lane_counts_must_be_positive(tmp_path, capsys):
    import pytest

    from models.reproduce import main

    for flag, says in (("--sim-workers", "must be at least 1, got 0"), ("--lanes", "must be at least 1, got 0"),
                       ("--car-weight", "must be a positive number")):
        with pytest.raises(SystemExit) as stop:
            main(["--out", str(tmp_path / "run"), "--data", str(tmp_path / "data"), flag, "0"])
        assert stop.value.code == 2 and f"argument {flag}: {says}" in capsys.readouterr().err
    # A misspelt preset is refused before any simulation, with or without --quick.
    for quick in ([], ["--quick"]):
        with pytest.raises(SystemExit) as stop:
            main(["--out", str(tmp_path / "run"), "--data", str(tmp_path / "data"), "--preset", "edge-splitt", *quick])
        assert stop.value.code == 2 and "argument --preset: unknown preset 'edge-splitt'" in capsys.readouterr().err
    # A preset without GAMs: the recipe's ablation would train it "with" and "without" them alike.
    with pytest.raises(SystemExit) as stop:
        main(["--out", str(tmp_path / "run"), "--data", str(tmp_path / "data"), "--preset", "edge-split-no-gam"])
    assert stop.value.code == 2 and "argument --preset: edge-split-no-gam has no GAMs" in capsys.readouterr().err
    # A preset file (models.train and export take one): the recipe's stages add suffixes to a registered name, so
    # a file would fail an hour in, at its first ablation; refused up front, even a valid one.
    preset_file = tmp_path / "highway.json"
    preset_file.write_text('{"base": "edge", "name": "highway", "bev": {"x_max": 100.0}}')
    with pytest.raises(SystemExit) as stop:
        main(["--out", str(tmp_path / "run"), "--data", str(tmp_path / "data"), "--preset", str(preset_file)])
    assert stop.value.code == 2 and "the recipe takes a registered preset's name, not a preset file" in \
        capsys.readouterr().err
    assert not (tmp_path / "run").exists() and not (tmp_path / "data").exists()


def test_paths_are_checked_before_any_work(tmp_path, capsys):
    """An --out, --data or --weights that cannot be written, a shipped directory's place holding something
    else, or --weights with --quick (which never ships): exit 2 and one line, before anything is simulated."""
    import pytest

    from models.reproduce import main

    a_file = tmp_path / "notes.txt"
    a_file.write_text("mine")
    (tmp_path / "weights" / "edge-lidar16").mkdir(parents=True)
    (tmp_path / "weights" / "edge-lidar16" / "keep.txt").write_text("mine")
    data, out = str(tmp_path / "data"), str(tmp_path / "run")
    cases = [
        (["--out", str(a_file), "--data", data, "--quick"], f"--out {a_file}: exists and is not a directory"),
        (["--out", out, "--data", f"{a_file}/sim", "--quick"], f"--data {a_file}/sim: {a_file} is a file"),
        (["--out", out, "--data", data, "--weights", str(a_file)], f"--weights {a_file}: exists and is not a directory"),
        (["--out", out, "--data", data, "--weights", str(tmp_path / "weights")],
         "edge-lidar16: exists and is not a model directory"),
    ]
    for args, says in cases:
        assert main(args) == 2
        err = capsys.readouterr().err
        assert says in err and len(err.strip().splitlines()) == 1, (args, err)
    with pytest.raises(SystemExit) as stop:
        main(["--out", out, "--data", data, "--quick", "--weights", str(tmp_path / "weights")])
    assert stop.value.code == 2 and "argument --weights: --quick writes" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt", "weights"]
    assert (tmp_path / "weights" / "edge-lidar16" / "keep.txt").read_text() == "mine"


def test_a_failed_export_or_ship_keeps_the_model_directory_there(tiny_models, tmp_path):
    """The recipe's exports replace a directory only once the new one is complete, and shipping swaps
    each directory in whole: a bad checkpoint leaves the earlier directory as it was."""
    import shutil

    import pytest

    from export.manifest import verify_model_dir
    from models.reproduce import ReproduceConfig, _export, _ship, shipped_directories

    config = ReproduceConfig(out=tmp_path / "run", quick=True)
    target = tmp_path / "run" / "models" / "lidar64"
    shutil.copytree(tiny_models, target)
    broken = tmp_path / "checkpoints"
    broken.mkdir()
    (broken / "pixor.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="not a lowres3d checkpoint"):
        _export(config, broken, target, ("pixor",), "tiny")
    assert verify_model_dir(target)["preset"] == "tiny"
    shipped = _ship(config, dict.fromkeys(("product", "lidar64", "lidar16"), target))
    assert shipped == {name: str(path) for name, path in shipped_directories(config).items()}
    assert all(verify_model_dir(path)["preset"] == "tiny" for path in shipped.values())
