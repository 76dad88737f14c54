"""``python -m models.train``: bad input and bad resumes are refused in one line naming the file or flag
(exit 2) before anything is trained or written; a finished run resumed has nothing to do.

Every run here is the tiny preset on one real KITTI frame for one epoch.
"""

import json
import logging
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from models.train import TrainConfig, main, run
from pipeline.errors import InputError
from pipeline.presets import get_preset
from tests.conftest import KITTI

REPO = Path(__file__).resolve().parents[1]

FRAME = "000006"  # four labelled cars


@pytest.fixture(scope="module")
def one_frame(tmp_path_factory) -> Path:
    """A split file listing one frame of the KITTI samples."""
    path = tmp_path_factory.mktemp("split") / "one.txt"
    path.write_text(f"{FRAME}\n")
    return path


def args(task: str, out: Path, split: Path, *extra: str) -> list[str]:
    return [task, "--data", str(KITTI), "--train-split", str(split), "--val-split", str(split), "--preset", "tiny",
            "--out", str(out), "--epochs", "1", "--batch-size", "1", "--compile", "off", *extra]


def files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def refused(argv: list[str], capsys) -> str:
    """The one-line error of a run the command refuses with exit status 2."""
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err and err[-1].startswith("error: "), err
    return err[-1]


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory, one_frame) -> Path:
    """A tiny lidar16 detector run that trained its 1 epoch (tests copy it before touching it)."""
    out = tmp_path_factory.mktemp("runs") / "run"
    assert main(args("detector", out, one_frame, "--input", "lidar16")) == 0
    assert (out / "state.pt").is_file() and (out / "pixor.pt").is_file()
    return out


@pytest.fixture(scope="module")
def unlabelled(tmp_path_factory) -> Path:
    """A KITTI-layout folder of one frame without label_2/."""
    data = tmp_path_factory.mktemp("unlabelled")
    for folder, suffix in (("velodyne", ".bin"), ("image_2", ".png"), ("calib", ".txt")):
        (data / folder).mkdir()
        shutil.copy(KITTI / folder / f"{FRAME}{suffix}", data / folder)
    return data


@pytest.mark.parametrize(("task", "extra"), [
    ("detector", []),
    ("joint", ["--depth-checkpoint", "depth.pt", "--pixor-checkpoint", "pixor.pt"]),
    ("depth", ["--car-weight", "5"]),  # the car pixels come from the labels too
])
def test_runs_that_need_labels_refuse_a_folder_without_label_2(unlabelled, tmp_path, capsys, task, extra):
    out = tmp_path / "run"
    says = refused([task, "--data", str(unlabelled), "--preset", "tiny", "--out", str(out), "--epochs", "1", *extra],
                   capsys)
    assert f"--data {unlabelled}: no label_2/ folder" in says and f"a {task} run" in says
    assert not out.exists()


def test_depth_run_needs_no_labels_but_every_frame_file(unlabelled, tmp_path, capsys):
    """Depth targets come from the scan: no label_2/ is fine; a frame without its calibration is not."""
    broken = tmp_path / "data"
    shutil.copytree(unlabelled, broken)
    (broken / "calib" / f"{FRAME}.txt").unlink()
    says = refused(["depth", "--data", str(broken), "--preset", "tiny", "--out", str(tmp_path / "run")], capsys)
    assert says == f"error: --data {broken}: frame {FRAME} has no {broken / 'calib' / f'{FRAME}.txt'}"
    assert not (tmp_path / "run").exists()


def test_resume_without_a_run_to_continue_is_refused(tmp_path, capsys, one_frame):
    """--resume where --out is missing or holds no state.pt; the library's resume=True (models.reproduce
    reruns its stages with it) still starts a run that is not there yet."""
    missing = tmp_path / "missing"
    says = refused(args("detector", missing, one_frame, "--resume"), capsys)
    assert says == f"error: {missing}: nothing to resume (no state.pt); leave out --resume to start a new run"
    assert not missing.exists()
    empty = tmp_path / "empty"
    empty.mkdir()
    assert "nothing to resume (no state.pt)" in refused(args("detector", empty, one_frame, "--resume"), capsys)
    assert files(empty) == {}
    started = run(TrainConfig(task="detector", data=KITTI, train_split=one_frame, val_split=one_frame, preset="tiny",
                              out=empty, epochs=1, batch_size=1, compile="off", resume=True, progress=False))
    assert [h["epoch"] for h in started.history] == [1] and (empty / "state.pt").is_file()


@pytest.mark.parametrize(("change", "says"), [
    (["--input", "lidar64"], "--input lidar64, but {run} was started with --input lidar16"),
    (["--preset", "edge"], "--preset edge (preset 'edge'), but {run} was started with --preset tiny (preset 'tiny'"),
    (["--train-only", "score"], "--train-only score, but {run} was started with no --train-only"),
    (["task=depth"], "task depth: {run} was started as a detector run"),
    # The optimizer's saved state would override a new --lr while the checkpoints recorded it.
    (["--lr", "0.01"], "--lr 0.01, but {run} was started with --lr 0.001"),
    (["--seed", "99"], "--seed 99, but {run} was started with --seed 0"),
    (["--batch-size", "2"], "--batch-size 2, but {run} was started with --batch-size 1"),
    (["--freeze-bn", "--pixor-checkpoint", "START"], "--freeze-bn, but {run} was started with no --freeze-bn"),
])
def test_resume_refuses_another_task_input_or_preset(finished_run, tmp_path, capsys, one_frame, change, says):
    run_dir = tmp_path / "run"
    shutil.copytree(finished_run, run_dir)
    before = files(run_dir)
    task = change[0].split("=")[1] if change[0].startswith("task=") else "detector"
    change = [str(finished_run / "pixor.pt") if c == "START" else c for c in change]
    argv = args(task, run_dir, one_frame, "--resume", "--epochs", "2", *[c for c in change if "=" not in c])
    assert says.format(run=run_dir) in refused(argv, capsys)
    assert files(run_dir) == before



def test_resume_refuses_a_split_that_names_other_frames_now(tmp_path, capsys):
    """--resume compared the flags, not the frames they name: a split file edited between the two runs (or frames
    added to a folder read whole) trained the remaining epochs on other frames without a word."""
    split = tmp_path / "train.txt"
    split.write_text(f"{FRAME}\n")
    run_dir = tmp_path / "run"
    assert main(args("detector", run_dir, split)) == 0
    before = files(run_dir)
    split.write_text("000000\n000001\n")  # the same --train-split, other frames
    says = refused(args("detector", run_dir, split, "--resume", "--epochs", "2"), capsys)
    assert says == (f"error: --data / --train-split: {run_dir} was started on 1 training frame, and the same flags "
                    "now give 2 other frames (a split file edited, frames added or removed); resume on the frames it "
                    "started with, or start a new run")
    assert files(run_dir) == before
    split.write_text(f"{FRAME}\n")  # as it was: resumes
    assert main(args("detector", run_dir, split, "--resume", "--epochs", "2")) == 0

def test_resume_of_a_finished_run_has_nothing_to_do(finished_run, tmp_path, capsys, one_frame):
    run_dir = tmp_path / "run"
    shutil.copytree(finished_run, run_dir)
    before = files(run_dir)
    assert main(args("detector", run_dir, one_frame, "--resume")) == 0
    out = capsys.readouterr().out
    assert f"{run_dir}: already trained 1 of 1 epochs; nothing to do (raise --epochs to train more)" in out
    assert "nan" not in out
    assert files(run_dir) == before


def test_resume_trains_the_remaining_epochs_and_reports_their_loss(finished_run, tmp_path, capsys, one_frame):
    run_dir = tmp_path / "run"
    shutil.copytree(finished_run, run_dir)
    assert main(args("detector", run_dir, one_frame, "--resume", "--epochs", "2")) == 0
    summary = [line for line in capsys.readouterr().out.splitlines() if line.startswith(f"run {run_dir}: loss ")]
    first, last = (float(v) for v in summary[0].split(": loss ")[1].split(";")[0].split(" → "))
    assert math.isfinite(first) and math.isfinite(last) and first > 0
    log = (run_dir / "log.jsonl").read_text().splitlines()
    assert len(log) == 2 and '"epoch": 2' in log[1]


def test_resume_with_the_same_data_spelt_otherwise_and_a_log_line_past_the_state(
        finished_run, tmp_path, capsys, one_frame, monkeypatch):
    """A relative --data naming the same folder resumes; a log line written after the last state.pt
    (an interruption between the two) is not kept twice."""
    run_dir = tmp_path / "run"
    shutil.copytree(finished_run, run_dir)
    first = (run_dir / "log.jsonl").read_text()
    with open(run_dir / "log.jsonl", "a") as handle:  # epoch 2 logged, then interrupted before its state.pt
        handle.write(first.replace('"epoch": 1', '"epoch": 2'))
    monkeypatch.chdir(KITTI.parent)
    argv = args("detector", run_dir, one_frame, "--resume", "--epochs", "2")
    argv[argv.index("--data") + 1] = KITTI.name
    assert main(argv) == 0, capsys.readouterr().err
    epochs = [line.split('"epoch": ')[1].split(",")[0] for line in (run_dir / "log.jsonl").read_text().splitlines()]
    assert epochs == ["1", "2"]


def test_a_malformed_label_line_is_named_before_any_epoch(tmp_path, capsys, one_frame):
    data = tmp_path / "data"
    for folder in ("velodyne", "image_2", "calib", "label_2"):
        shutil.copytree(KITTI / folder, data / folder)
    (data / "label_2" / f"{FRAME}.txt").write_text("Car 0.00 0 -1.5 587 173 614 200 1.65 1.67 3.64 -0.65 x 46.7 -1.6\n")
    for task in ("detector", "depth"):  # the depth run validates on the labelled cars (car_in_box_*)
        argv = args(task, tmp_path / task, one_frame, *(["--input", "lidar16"] if task == "detector" else []))
        argv[argv.index("--data") + 1] = str(data)
        says = refused(argv, capsys)
        assert f"label_2/{FRAME}.txt, line 1" in says, says
        assert not (tmp_path / task).exists()


@pytest.mark.parametrize(("breakage", "says"), [
    ("calib", f"calib/{FRAME}.txt: missing calibration key(s) Tr_velo_to_cam"),
    ("velodyne", f"velodyne/{FRAME}.bin: size 1001 bytes is not a whole number of 16-byte points"),
    ("empty velodyne", f"velodyne/{FRAME}.bin: size 0 bytes"),
    ("image", f"image_2/{FRAME}.png: PNG cut off before its end"),
    ("not an image", f"image_2/{FRAME}.png: not a PNG or JPEG image"),
])
def test_a_broken_frame_file_is_named_before_any_epoch(tmp_path, capsys, one_frame, breakage, says):
    """A calibration without a key, a scan of no whole points, an image cut off: refused before --out is made,
    for every task (the datasets would meet them only when their batch comes, maybe most of an epoch in)."""
    data = tmp_path / "data"
    for folder in ("velodyne", "image_2", "calib", "label_2"):
        shutil.copytree(KITTI / folder, data / folder)
    calib, scan, image = data / "calib" / f"{FRAME}.txt", data / "velodyne" / f"{FRAME}.bin", data / "image_2" / f"{FRAME}.png"
    if breakage == "calib":
        calib.write_text("".join(line for line in calib.read_text().splitlines(True) if not line.startswith("Tr_velo")))
    elif breakage == "velodyne":
        scan.write_bytes(scan.read_bytes()[:1001])
    elif breakage == "empty velodyne":
        scan.write_bytes(b"")
    elif breakage == "image":
        image.write_bytes(image.read_bytes()[:2000])
    else:
        image.write_bytes(b"GIF89a" + bytes(100))
    for task in ("detector", "depth"):
        argv = args(task, tmp_path / task, one_frame, *(["--input", "lidar16"] if task == "detector" else []))
        argv[argv.index("--data") + 1] = str(data)
        said = refused(argv, capsys)
        assert says in said, said
        assert not (tmp_path / task).exists()


def test_ctrl_c_says_what_was_kept(tmp_path, capsys, one_frame, monkeypatch):
    from models import train

    def interrupted(config):
        raise KeyboardInterrupt

    monkeypatch.setattr(train, "run", interrupted)
    assert main(args("detector", tmp_path / "run", one_frame)) == 130
    assert f"interrupted: {tmp_path / 'run'} has no finished epoch yet; nothing to resume" in capsys.readouterr().err


def test_out_that_is_a_file_is_refused(tmp_path, capsys, one_frame):
    path = tmp_path / "notes.txt"
    path.write_text("kept\n")
    assert refused(args("detector", path, one_frame), capsys) == f"error: --out: {path} is a file, not a run folder"
    under = path / "run"
    assert refused(args("detector", under, one_frame), capsys) == f"error: --out: cannot create {under}: {path} is a file"
    assert path.read_text() == "kept\n"


def test_checkpoints_without_a_run_are_never_replaced(finished_run, tmp_path, capsys, one_frame):
    """A folder of checkpoints with no state.pt (models.onnx_weights writes them): a new run there would replace
    one and leave the other beside it. models.onnx_weights itself never writes over a run's checkpoints."""
    from models.onnx_weights import main as onnx_weights

    folder = tmp_path / "converted"
    folder.mkdir()
    shutil.copy(finished_run / "pixor.pt", folder)
    before = files(folder)
    says = refused(args("detector", folder, one_frame, "--input", "lidar16"), capsys)
    assert says == f"error: --out: {folder} already holds pixor.pt but no state.pt (not a run to resume); give a new folder"
    run_copy = tmp_path / "run"
    shutil.copytree(finished_run, run_copy)
    kept = files(run_copy)
    assert onnx_weights(["--models", str(REPO / "weights" / "edge-lidar16"), "--out", str(run_copy)]) == 2
    assert f"--out {run_copy}: already holds pixor.pt and state.pt; give a new folder" in capsys.readouterr().err
    assert files(run_copy) == kept and files(folder) == before


@pytest.mark.parametrize(("task", "extra", "says"), [
    ("depth", ["--pixor-checkpoint", "pixor.pt"], "--pixor-checkpoint: not used by a depth run"),
    ("depth", ["--input", "lidar64"], "--input: not used by a depth run"),
    ("joint", ["--input", "pseudo", "--depth-checkpoint", "d.pt", "--pixor-checkpoint", "p.pt"],
     "--input: not used by a joint run"),
    ("detector", ["--depth-checkpoint", "depth.pt"], "--depth-checkpoint: not used by a detector run"),
    ("detector", ["--depth-loss", "l1"], "--depth-loss: not used by a detector run"),
    ("detector", ["--car-weight", "5"], "--car-weight: not used by a detector run"),
    ("detector", ["--pseudo-dir", "maps"], "--pseudo-dir: not used by a detector run (read by detector runs with --input"),
    ("depth", ["--val-pseudo-dir", "maps"], "--val-pseudo-dir: not used by a depth run"),
    ("depth", ["--freeze-bn"], "--freeze-bn: not used by a depth run (it keeps the batch norms of the weights"),
    ("detector", ["--lr-gamma", "0.1"], "--lr-gamma: not used by a detector run (a detector run halves its rate"),
    ("detector", ["--lr-step", "3"], "--lr-step: not used by a detector run"),
    ("detector", ["--resnet18", "r.pth"], "--resnet18: not used by a detector run (it starts a depth run's encoder"),
    ("depth", ["--resnet18", "r.pth", "--depth-checkpoint", "d.pt"],
     "--resnet18: not used by a depth run (--depth-checkpoint gives every weight"),
])
def test_a_setting_the_task_does_not_use_is_refused(tmp_path, capsys, one_frame, task, extra, says):
    """Silently ignored, it would leave the user believing the run used it."""
    out = tmp_path / "run"
    assert refused(args(task, out, one_frame, *extra), capsys).startswith(f"error: {says}")
    assert not out.exists()


def test_a_start_file_that_is_not_onnx_is_named(tmp_path, capsys, one_frame):
    garbage = tmp_path / "pixor.onnx"
    garbage.write_text("hello\n")
    says = refused(args("detector", tmp_path / "run", one_frame, "--input", "lidar16", "--pixor-checkpoint", str(garbage)),
                   capsys)
    assert says.startswith(f"error: {garbage}: not a readable ONNX model (DecodeError")
    assert not (tmp_path / "run").exists()


def test_an_exported_start_network_of_another_kind_or_preset_is_named(tmp_path, capsys, one_frame):
    """The manifest beside an exported .onnx says which network and preset it is: a message a user can act on,
    not only the weight that did not fit."""
    edge = REPO / "weights" / "edge"
    says = refused(args("depth", tmp_path / "a", one_frame, "--depth-checkpoint", str(edge / "pixor.onnx")), capsys)
    assert says == f"error: --depth-checkpoint: {edge / 'pixor.onnx'} is the pixor network of {edge}, not the depth one"
    # Another preset's export is refused by its manifest's preset_config, before its weights are read, in the words
    # a .pt checkpoint of that preset gets.
    says = refused(args("depth", tmp_path / "b", one_frame, "--depth-checkpoint", str(edge / "depth.onnx")), capsys)
    assert says == (f"error: {edge / 'depth.onnx'}: trained with preset 'edge-split-near35' whose depth configuration "
                    "differs from the requested preset 'tiny'; give --preset edge-split-near35 with it, or a checkpoint "
                    "trained with tiny")


def test_a_run_folder_as_start_checkpoint_points_to_the_file_in_it(finished_run, tmp_path, capsys, one_frame):
    says = refused(args("detector", tmp_path / "run", one_frame, "--pixor-checkpoint", str(finished_run)), capsys)
    assert says == f"error: --pixor-checkpoint: {finished_run} is a folder: give the checkpoint in it, {finished_run / 'pixor.pt'}"


def test_corrupt_state_is_named_without_a_traceback(finished_run, tmp_path, one_frame):
    run_dir = tmp_path / "run"
    shutil.copytree(finished_run, run_dir)
    (run_dir / "state.pt").write_text("garbage\n")
    done = subprocess.run([sys.executable, "-m", "models.train", *args("detector", run_dir, one_frame, "--resume")],
                          capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert done.stderr.strip().splitlines()[-1].startswith(f"error: {run_dir / 'state.pt'}: not a training checkpoint (")
    assert (run_dir / "state.pt").read_text() == "garbage\n"


def test_unknown_preset_names_the_flag(tmp_path, capsys, one_frame):
    argv = args("detector", tmp_path / "run", one_frame)
    argv[argv.index("tiny")] = "nonsense"
    assert refused(argv, capsys).startswith("error: --preset: unknown preset 'nonsense'; choose one of ")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("flag", ["--train-split", "--val-split"])
def test_split_listing_a_missing_frame_is_refused_before_training(tmp_path, capsys, one_frame, flag):
    """Every listed id is checked, also those past --max-*-frames."""
    split = tmp_path / "split.txt"
    split.write_text(f"{FRAME}\n999999\n999998\n")
    argv = args("detector", tmp_path / "run", one_frame, "--max-train-frames", "1", "--max-val-frames", "1")
    argv[argv.index(flag) + 1] = str(split)
    says = refused(argv, capsys)
    assert says == (f"error: {flag} {split}: frame 999999 (and 1 more) is not in {KITTI} "
                    f"(no {KITTI / 'velodyne' / '999999.bin'})")
    assert not (tmp_path / "run").exists()


def test_failed_runs_leave_no_out_folder_and_keep_an_existing_one(tmp_path, capsys, one_frame):
    """--out is made after every check, the start weights' included; a folder already there is left as it was."""
    out = tmp_path / "deep" / "run"
    says = refused(args("detector", out, one_frame, "--pixor-checkpoint", str(tmp_path / "none.pt")), capsys)
    assert "--pixor-checkpoint" in says
    assert not (tmp_path / "deep").exists()
    kept = tmp_path / "kept"
    kept.mkdir()
    (kept / "notes.txt").write_text("mine\n")
    assert "--preset" in refused(args("detector", kept, one_frame, "--preset", "nonsense"), capsys)
    assert files(kept) == {"notes.txt": b"mine\n"}


def _readme_train_commands() -> list[list[str]]:
    """Every ``python -m models.train`` command of the README, continuation lines joined and each ``for``
    loop's variable expanded (the real-KITTI recipe has one)."""
    import shlex

    text = (REPO / "README.md").read_text(encoding="utf-8").replace("\\\n", " ")
    commands, loop = [], None
    for line in text.splitlines():
        line = line.split(" # ")[0].strip()
        if line.startswith("for ") and line.endswith("; do"):
            name, values = line[4:-4].split(" in ")
            loop = (name.strip(), values.split())
        elif line == "done":
            loop = None
        elif line.startswith("python -m models.train "):
            for value in loop[1] if loop else [None]:
                expanded = line.replace(f"${loop[0]}", value) if loop else line
                commands.append(shlex.split(expanded)[3:])
    return commands


def test_the_readme_training_commands_take_their_flags(monkeypatch, capsys):
    """Each README training command parses, and its flags all apply to its task: the real-KITTI recipe once
    gave --pseudo-dir to the 64- and 16-line runs, which models.train refuses."""
    from models import train

    commands = _readme_train_commands()
    assert len(commands) >= 5 and any("pseudo" in c for c in commands)

    class Checked(Exception):
        pass

    def flags_only(config: TrainConfig) -> None:
        train.check_flags_apply(config)
        raise Checked

    monkeypatch.setattr(train, "run", flags_only)
    for argv in commands:
        with pytest.raises(Checked):
            main(argv)
        assert capsys.readouterr().err == "", argv


# ----------------------------------------------------------------------------- KITTI depth completion
DRIVE_RUN = ["--preset", "tiny", "--epochs", "1", "--batch-size", "1", "--compile", "off"]


def test_depth_run_trains_and_validates_on_depth_completion_drives(make_drive, tmp_path, caplog):
    """``models.train depth --data DRIVE --val-data DRIVE2``: trained on the drive's frames (16 lines thinned through
    its calibration in the date folder above), validated on the other's ground truth; split files list a drive's
    frame ids. The figures are RMSE and MAE over the ground truth's pixels in the view (a drive has no labels)."""
    from models.checkpoint import load_checkpoint
    from pipeline.kitti import read_depth_png
    from pipeline.preprocess import depth_view
    from pipeline.presets import get_preset

    drive = make_drive("train", ("0000000005", "0000000006"))
    other = make_drive("val", ("0000000007",))
    out = tmp_path / "run"
    assert main(["depth", "--data", str(drive), "--val-data", str(other), "--out", str(out), *DRIVE_RUN]) == 0
    record = json.loads((out / "log.jsonl").read_text().splitlines()[-1])
    truth = depth_view(read_depth_png(other / "groundtruth" / "0000000007.png"), get_preset("tiny"))
    assert record["pixels"] == np.count_nonzero(truth) > 0
    assert math.isfinite(record["rmse_mm"]) and math.isfinite(record["train_loss"])
    assert not [key for key in record if key.startswith("car_")]
    metadata = load_checkpoint(out / "depth.pt").metadata
    assert (metadata["data"], metadata["train_frames"], metadata["val_frames"]) == (str(drive), 2, 1)
    train, val = tmp_path / "train.txt", tmp_path / "val.txt"
    train.write_text("0000000005\n")
    val.write_text("0000000006\n")
    with caplog.at_level(logging.WARNING, logger="models.train"):
        assert main(["depth", "--data", str(drive), "--train-split", str(train), "--val-split", str(val),
                     "--out", str(tmp_path / "split_run"), *DRIVE_RUN]) == 0
    assert not [r for r in caplog.records if r.name == "models.train"]  # distinct frames: nothing to warn of
    metadata = load_checkpoint(tmp_path / "split_run" / "depth.pt").metadata
    assert (metadata["train_frames"], metadata["val_frames"]) == (1, 1)
    # Object frames trained with --car-weight (their labels) may be validated on a drive, which has none.
    one = tmp_path / "one.txt"
    one.write_text(f"{FRAME}\n")
    assert main(["depth", "--data", str(KITTI), "--train-split", str(one), "--val-data", str(other), "--car-weight",
                 "5", "--out", str(tmp_path / "mixed"), *DRIVE_RUN]) == 0
    assert json.loads((tmp_path / "mixed" / "log.jsonl").read_text())["pixels"] == record["pixels"]



def test_the_flat_layout_hint_is_written_out_for_the_drive_given(tmp_path):
    """Given KITTI's depth-completion folder (holding train/), a drive's proj_depth/ or the drive itself, the
    hint's ln -s commands name that drive's own folders (the first drive of train/ for the whole folder), the
    raw data's folder the only placeholder; a folder with no drive in it keeps the template."""
    from pipeline.depth_completion import FLAT_LAYOUT_HINT, flat_layout_hint

    drives = [tmp_path / "train" / name for name in ("2011_09_28_drive_0002_sync", "2011_09_26_drive_0001_sync")]
    for drive in drives:
        (drive / "proj_depth" / "groundtruth" / "image_02").mkdir(parents=True)
    first = drives[1]
    for given in (tmp_path, first, first / "proj_depth"):
        hint = flat_layout_hint(given)
        assert f"ln -s {first}/proj_depth/groundtruth/image_02 {first.name}/groundtruth" in hint, hint
        assert f"RAW/2011_09_26/{first.name}/velodyne_points/data" in hint and "DRIVE" not in hint, hint
    assert flat_layout_hint(tmp_path / "elsewhere") == FLAT_LAYOUT_HINT

@pytest.mark.parametrize("case", ["kitti layout", "neither", "no calibration", "missing scan", "split frame",
                                  "smaller ground truth", "broken image", "detector", "car weight"])
def test_a_drive_a_run_cannot_train_on_is_refused_by_name(make_drive, tmp_path, capsys, case):
    """KITTI's own layout gets the way to link a drive; a drive without its calibration (training thins its scans
    to 16 lines through it), a frame without a file, of maps of another size, or a broken PNG, a task needing
    labels: each one line naming the folder or file, before --out is made."""
    from pipeline.kitti import read_depth_png, write_depth_png

    drive = make_drive("drive", ("0000000005", "0000000006"), calib=case != "no calibration")
    data, task, extra = drive, "depth", []
    frame = "0000000006"
    if case == "kitti layout":  # train/DRIVE/proj_depth/{velodyne_raw,groundtruth}/image_02/ as KITTI ships it
        data = tmp_path / "train" / "2011_09_26_drive_0001_sync"
        for name in ("velodyne_raw", "groundtruth"):
            (data / "proj_depth" / name / "image_02").mkdir(parents=True)
        name = "2011_09_26_drive_0001_sync"  # the hint is written out for this drive, only the raw data's folder left
        says = (f"--data {data}: KITTI's depth-completion layout, one drive at a time in the flat one: link one drive "
                f"into the flat layout: mkdir {name} && ln -s {data}/proj_depth/velodyne_raw/image_02 {name}/"
                f"velodyne_raw && ln -s {data}/proj_depth/groundtruth/image_02 {name}/groundtruth && ln -s "
                f"RAW/2011_09_26/{name}/image_02/data {name}/image_02 && ln -s RAW/2011_09_26/{name}/velodyne_points/"
                f"data {name}/velodyne_points && ln -s RAW/2011_09_26/calib_*.txt {name}/ (RAW: where KITTI's raw "
                "data is)")
    elif case == "neither":
        data = drive / "image_02"
        says = (f"--data {data}: not a KITTI object folder (no velodyne/ inside) nor a depth-completion drive "
                "(no velodyne_raw/ and groundtruth/ inside)")
    elif case == "no calibration":
        says = (f"--data {drive}: no drive calibration (calib_cam_to_cam.txt and calib_velo_to_cam.txt, in it or in "
                f"{drive.parent}); a depth run thins the drive's scans to 16 lines through it")
    elif case == "missing scan":
        (drive / "velodyne_raw" / f"{frame}.png").unlink()
        says = f"--data {drive}: frame {frame} has no {drive / 'velodyne_raw' / f'{frame}.png'}"
    elif case == "split frame":
        split = tmp_path / "val.txt"
        split.write_text("0000000009\n")
        extra = ["--val-split", str(split)]
        says = f"--val-split {split}: frame 0000000009 is not in {drive} (no {drive / 'image_02' / '0000000009.png'})"
    elif case == "smaller ground truth":
        truth = drive / "groundtruth" / f"{frame}.png"
        write_depth_png(truth, read_depth_png(truth)[::2, ::2])
        says = (f"{truth}: a 621×188 depth map for the 1242×375 image {drive / 'image_02' / f'{frame}.png'}; they "
                "must be the same size")
    elif case == "broken image":
        image = drive / "image_02" / f"{frame}.png"
        image.write_bytes(image.read_bytes()[:2000])
        says = f"{image}: PNG cut off before its end"
    elif case == "detector":
        task = "detector"
        says = (f"--data {drive}: a depth-completion drive (velodyne_raw/, groundtruth/), which only a depth run "
                "trains on; a detector run needs a KITTI object folder (velodyne/, label_2/)")
    else:
        extra = ["--car-weight", "5"]
        says = (f"--data {drive}: a depth-completion drive, which has no labelled cars; a depth run with --car-weight "
                "needs the ground-truth boxes of an object folder (label_2/)")
    out = tmp_path / "run"
    said = refused([task, "--data", str(data), "--out", str(out), *DRIVE_RUN, *extra], capsys)
    assert said.startswith(f"error: {says}"), said
    assert not out.exists()


# ----------------------------------------------------------------------------- validation frames among the training ones
def _object_folder(folder: Path, frames: tuple[str, ...]) -> Path:
    """A KITTI object folder of ``frames``, each file a link to the real sample's."""
    for sub, suffix in (("velodyne", ".bin"), ("image_2", ".png"), ("calib", ".txt"), ("label_2", ".txt")):
        (folder / sub).mkdir(parents=True)
        for fid in frames:
            (folder / sub / f"{fid}{suffix}").symlink_to(KITTI / sub / f"{fid}{suffix}")
    return folder


def _warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == "models.train" and r.levelno == logging.WARNING]


def test_validation_frames_that_are_trained_on_are_warned_of(tmp_path, caplog):
    """--val-split without --train-split trains on every frame, the validation ones too; a --train-split that
    overlaps --val-split (or --val-data the same folder): one warning naming how many and one of them. The run
    goes on (nothing is refused); other folders' frames of the same ids are other frames."""
    from models.train import split_ids

    data = _object_folder(tmp_path / "data", ("000003", "000006"))
    val, train, apart = tmp_path / "val.txt", tmp_path / "train.txt", tmp_path / "apart.txt"
    val.write_text("000006\n")
    train.write_text("000003\n000006\n")
    apart.write_text("000003\n")
    tail = "their validation figures flatter the net; give a --train-split without them"
    with caplog.at_level(logging.WARNING, logger="models.train"):
        assert main(["detector", "--data", str(data), "--val-split", str(val), "--out", str(tmp_path / "run"),
                     *DRIVE_RUN]) == 0
    assert _warnings(caplog) == [(f"--val-split {val}: 1 of its 1 validation frames (000006 among them) are training "
                                  f"frames too (every frame of --data {data}, for want of --train-split): {tail}")]

    def warned(**flags) -> list[str]:
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="models.train"):
            split_ids(TrainConfig(task="detector", data=data, preset="tiny", out=tmp_path / "unused", **flags))
        return _warnings(caplog)

    assert warned(train_split=train, val_split=val) == [
        (f"--val-split {val}: 1 of its 1 validation frames (000006 among them) are training frames too "
         f"(--train-split {train}): {tail}")]
    same = tmp_path / "data" / ".." / "data"  # the same folder spelt otherwise
    assert warned(train_split=val, val_data=same) == [
        (f"--val-data {same} (every frame): 1 of its 2 validation frames (000006 among them) are training frames "
         f"too (--train-split {val}): {tail}")]
    assert warned(train_split=apart, val_split=val) == []
    other = _object_folder(tmp_path / "other", ("000003", "000006"))
    assert warned(val_data=other) == []
    assert warned() == ["no --val-data or --val-split: validating on the training frames"]  # as before, alone


def test_the_rate_decays_after_every_lr_step_epochs_not_one_sooner_or_later(tmp_path):
    """--lr-step 2: epochs 1 and 2 train at the rate given, 3 at a tenth of it; the log gives each epoch the rate
    it trained at."""
    split = tmp_path / "one.txt"
    split.write_text(f"{FRAME}\n")
    out = tmp_path / "run"
    assert main(args("depth", out, split, "--epochs", "3", "--lr", "0.001", "--lr-step", "2", "--lr-gamma",
                     "0.1", "--no-progress")) == 0
    rates = [json.loads(line)["lr"] for line in (out / "log.jsonl").read_text().splitlines()]
    assert rates == pytest.approx([1e-3, 1e-3, 1e-4])


def test_depth_rate_decays_by_the_given_factor_every_given_epochs(tmp_path, one_frame):
    """--lr-step and --lr-gamma: the paper's "decayed every 5 epochs" has no factor; Ma et al.'s code divides by 10.
    The log's rate per epoch follows the schedule asked for, and the recipe records it."""
    out = tmp_path / "run"
    assert main(args("depth", out, one_frame, "--epochs", "3", "--lr", "0.001", "--lr-step", "1", "--lr-gamma",
                     "0.1", "--no-progress")) == 0
    rates = [json.loads(line)["lr"] for line in (out / "log.jsonl").read_text().splitlines()]
    assert rates == pytest.approx([1e-3, 1e-4, 1e-5])  # each epoch's own rate: the first runs at --lr
    recipe = torch.load(out / "depth.pt", map_location="cpu", weights_only=False)["metadata"]["recipe"]
    assert recipe["lr_decay"] == {"every_epochs": 1, "factor": 0.1}
    resumed_otherwise = args("depth", out, one_frame, "--epochs", "4", "--lr", "0.001", "--lr-step", "1", "--resume")
    assert main(resumed_otherwise) == 2  # the rest of the run would decay by another factor than its log says


def test_resnet18_weights_start_the_paper_encoder_and_unusable_files_are_named(tmp_path, one_frame, capsys):
    """--resnet18: torchvision's ImageNet ResNet-18 as the paper preset's encoder (start_networks, as a run
    builds them); a file that is not one, or a preset of other widths, is one line naming the flag and file."""
    from models.train import start_networks
    from tests.test_models import torchvision_resnet18_state

    state = torchvision_resnet18_state()
    path = tmp_path / "resnet18.pth"
    torch.save(state, path)
    config = TrainConfig(task="depth", data=KITTI, preset="paper", out=tmp_path / "unused", resnet18=path)
    depth = start_networks(config, get_preset("paper"))["depth"].state_dict()
    assert all(torch.equal(depth[name], tensor) for name, tensor in state.items() if name.startswith("layer"))
    resumed = start_networks(config, get_preset("paper"), resumed=True)["depth"].state_dict()
    assert not torch.equal(resumed["layer1.0.conv1.weight"], state["layer1.0.conv1.weight"])

    says = refused(args("depth", tmp_path / "edge", one_frame, "--resnet18", str(path)), capsys)
    assert says.startswith(f"error: --resnet18: {path}: layer1.0.conv1.weight has")
    garbage = tmp_path / "notes.pth"
    garbage.write_text("not a checkpoint")
    says = refused(args("depth", tmp_path / "garbage", one_frame, "--resnet18", str(garbage)), capsys)
    assert says.startswith(f"error: --resnet18: {garbage}: not a PyTorch state dict")
    says = refused(args("depth", tmp_path / "missing", one_frame, "--resnet18", str(tmp_path / "nowhere.pth")), capsys)
    assert says == f"error: --resnet18: {tmp_path / 'nowhere.pth'} does not exist"


def test_a_new_run_refuses_a_folder_another_process_started_meanwhile(tmp_path, one_frame, capsys, monkeypatch):
    """Two new runs given one --out that does not exist yet: whichever takes the folder's lock second finds the
    other's state.pt and stops, instead of writing an epoch-0 state over it. The other process is played by the
    lock itself: it finishes a run into the folder just before this one's lock is taken."""
    from models import train

    out = tmp_path / "run"
    taken = train.run_lock
    played: list[Path] = []

    def after_another_run(folder):
        if not played:  # the first lock this run takes: the other process's whole run comes just before it
            played.append(folder)
            assert main(args("detector", tmp_path / "other", one_frame, "--input", "lidar16")) == 0
            for name in ("state.pt", "pixor.pt", "log.jsonl", "curves.png"):
                shutil.copy(tmp_path / "other" / name, folder / name)
        return taken(folder)

    monkeypatch.setattr(train, "run_lock", after_another_run)
    says = refused(args("detector", out, one_frame, "--input", "lidar16"), capsys)
    assert played == [out]
    assert says == (f"error: --out: {out} was started by another training process meanwhile (state.pt); give a new "
                    "folder, or --resume it once that process has ended")
    assert files(out) == files(tmp_path / "other")  # the other run's files, as it left them


def test_a_run_started_from_resnet18_weights_resumes_with_the_same_file(tmp_path):
    """--resnet18 is a file, compared on --resume as the other files are (the state records it as text): the
    same file, however it is spelt, resumes; another is refused."""
    from models.run_checks import check_resumable

    weights = tmp_path / "resnet18.pth"
    state = {"config": {"task": "depth", "resnet18": str(weights)}, "networks": {"depth": {}}}
    spelt_otherwise = tmp_path / "." / "resnet18.pth"
    check_resumable(TrainConfig(task="depth", data=KITTI, preset="paper", out=tmp_path, resnet18=spelt_otherwise), state, tmp_path)
    other = TrainConfig(task="depth", data=KITTI, preset="paper", out=tmp_path, resnet18=tmp_path / "other.pth")
    with pytest.raises(InputError, match=r"--resnet18 .*other\.pth, but .* was started with --resnet18"):
        check_resumable(other, state, tmp_path)


# ----------------------------------------------------------------------------- what the run would learn from
def _replace(path: Path, data: bytes) -> None:
    """Write ``data`` in place of a linked sample file (the link goes, the sample stays)."""
    path.unlink()
    path.write_bytes(data)


def _no_cars(data: Path) -> str:
    _replace(data / "label_2" / f"{FRAME}.txt",
             (KITTI / "label_2" / f"{FRAME}.txt").read_bytes().replace(b"Car ", b"Vehicle "))
    return f"--data {data}: no Car in the label_2 files of its 1 training frame (classes found: Vehicle 4, DontCare 2)"


def _doubled_depth_map(data: Path) -> str:
    from pipeline.kitti import write_depth_png

    (data / "depth_2").mkdir()
    write_depth_png(data / "depth_2" / f"{FRAME}.png", np.full((748, 2476), 9.0))
    return f"{data / 'depth_2' / f'{FRAME}.png'}: a 2476×748 depth map for the 1238×374 image"


def _scans_of_16_lines(data: Path) -> str:
    from pipeline.beams import emulate_beams
    from pipeline.kitti import read_velodyne, write_velodyne

    scan = data / "velodyne" / f"{FRAME}.bin"
    points = read_velodyne(scan).points
    scan.unlink()
    write_velodyne(scan, emulate_beams(points, 16))
    return f"{scan}: --input lidar64 trains on 64-line scans as stored, but the scan has 16 rings"


@pytest.mark.parametrize(("task", "extra", "breakage"), [
    ("detector", [], _no_cars),
    ("depth", [], _doubled_depth_map),
    ("detector", ["--input", "lidar64"], _scans_of_16_lines),
], ids=["no-car-labelled", "depth-map-of-another-size", "lidar64-on-16-lines"])
def test_data_the_run_would_silently_learn_wrong_from_is_refused_before_it_starts(tmp_path, capsys, task, extra,
                                                                                    breakage):
    """Session 47's review: labels naming no Car (the detector trained on no positive: exit 0, AP 0), a depth map
    twice its image's size (the target of another part of the scene), --input lidar64 on a 16-line sensor's scans
    (a model recorded as 64-line). Each is one line naming what is wrong (exit 2), and no --out is made."""
    data = _object_folder(tmp_path / "data", (FRAME,))
    says = breakage(data)
    out = tmp_path / "run"
    said = refused([task, "--data", str(data), "--out", str(out), *DRIVE_RUN, *extra], capsys)
    assert said.startswith(f"error: {says}"), said
    assert not out.exists()
