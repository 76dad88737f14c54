"""What a training run checks before it trains or writes anything (``--out``, the frames and their labels,
the cached depth maps of ``--input pseudo``), and the run's saved state (``RUN_DIR/state.pt``): reading it
back, checking that ``--resume`` continues the run it was started as, and restoring it. (Whether each flag
applies to the task is checked next to the flags, in models.train.check_flags_apply.)
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import random
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

try:
    import fcntl
except ImportError:  # Windows: no advisory locks; a run folder is then not guarded against a second process
    fcntl = None

import numpy as np
import torch

from models.cache_pseudo import (
    FRAME_FILES,
    RECORD,
    check_sources,
    recorded_beams,
    recorded_preset,
    recorded_view,
)
from models.checkpoint import save_atomic
from models.data import CAR_CLASS, is_car
from pipeline.beams import check_thinnable, emulate_beams
from pipeline.depth_completion import check_map_size, drive_calibration, is_drive_folder, raw_scan_path
from pipeline.errors import InputError
from pipeline.kitti import (
    PNG_SIGNATURE,
    POINT_BYTES,
    check_image_file,
    read_calib,
    read_image_size,
    read_labels,
    read_velodyne,
)
from pipeline.presets import preset_fields

if TYPE_CHECKING:
    from models.train import TrainConfig, TrainResult
    from pipeline.presets import Preset

log = logging.getLogger(__name__)
STATE_FILE = "state.pt"
STATE_KEYS = ("networks", "optimizer", "scheduler", "epoch", "best", "history", "torch_rng", "numpy_rng",
              "python_rng")
# Settings a run's state has recorded only since they existed, with the value every run had before.
RECORDED_SINCE = {"emulate_beams": 16}
FRAME_PATTERNS = tuple(f"{sub}/{{}}{ext}" for sub, ext in FRAME_FILES)  # what load_frame reads of every frame
# … and what pipeline.depth_completion.read_frame reads of a drive's (its raw scans are optional)
DRIVE_FILES = ("image_02/{}.png", "velodyne_raw/{}.png", "groundtruth/{}.png")


def check_out(out: Path) -> None:
    """``--out`` is a folder, or a path where one can be made (no file in its place or above it)."""
    if out.exists() and not out.is_dir():
        raise InputError(f"--out: {out} is a file, not a run folder")
    existing = next((parent for parent in out.parents if parent.exists()), None)
    if existing is not None and not existing.is_dir():
        raise InputError(f"--out: cannot create {out}: {existing} is a file")


@contextlib.contextmanager
def run_lock(out: Path) -> Iterator[None]:
    """Hold the run folder ``out`` (an existing directory) for this process while it trains: a second process
    given the same --out (the command started twice, a rerun while the earlier one still winds down) is refused
    instead of both writing its state. The lock is on the folder itself, so it adds no file to it, and the
    system drops it when the process ends, however it ends (SIGKILL included)."""
    if fcntl is None:
        yield
        return
    handle = os.open(out, os.O_RDONLY)
    try:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise InputError(f"--out: {out} is in use by another training process; wait for it to end (or stop "
                             "it), then rerun") from None
        except OSError as exc:  # NFS takes an exclusive lock only on a file open for writing (EBADF); Lustre
            # without -o flock has none (ENOSYS): the run trains unguarded there, as on Windows, rather than not at all
            log.warning("%s: the file system locks no folder (%s): not guarded against a second process given the "
                        "same --out", out, exc.strerror or exc)
        yield
    finally:
        os.close(handle)  # closing the last descriptor releases the lock


def save_state(state_path: Path, networks: dict[str, torch.nn.Module], optimizer, scheduler, epoch: int,
               best: float, history: list[dict], config: dict) -> None:
    """Write the run's state after ``epoch`` epochs (0: before the first), whole or not at all (save_atomic):
    everything ``--resume`` needs to continue as if never stopped."""
    save_atomic({"networks": {name: net.state_dict() for name, net in networks.items()},
                 "optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(),
                 "epoch": epoch, "best": best, "history": history, "config": config,
                 "torch_rng": torch.get_rng_state(), "numpy_rng": np.random.get_state(),
                 "python_rng": random.getstate()}, state_path)


def stopped_at(out: Path) -> str:
    """What an interrupted run in ``out`` keeps and how to go on (the command's last line)."""
    state_path = out / STATE_FILE
    if not state_path.is_file():
        return f"{out} has no finished epoch yet; nothing to resume"
    try:
        state = load_state(state_path)
    except InputError:
        return f"{out}: {STATE_FILE} cannot be read back; start a new run in another folder"
    done = state["epoch"]
    if done == 0:
        return f"{out} has no finished epoch yet; rerun with --resume to start it again"
    return (f"{out} keeps epoch {done} ({STATE_FILE}); rerun with --resume "
            f"to continue from epoch {done + 1}")


def load_state(state_path: Path) -> dict:
    """The training state a run folder holds (written before the first epoch and at the end of each); InputError
    if it is not one."""
    try:
        state = torch.load(state_path, map_location="cpu", weights_only=False)
    except Exception as exc:  # torch raises pickle, zip, value and runtime errors for files that are not its own
        raise InputError(f"{state_path}: not a training checkpoint (torch.load cannot read it: "
                         f"{type(exc).__name__})") from exc
    if not isinstance(state, dict):
        raise InputError(f"{state_path}: not a training checkpoint (a {type(state).__name__}, not a dict)")
    missing = [key for key in STATE_KEYS if key not in state]
    if missing:
        raise InputError(f"{state_path}: not a training checkpoint (no {', '.join(missing)})")
    if not isinstance(state["epoch"], int) or not isinstance(state["networks"], dict):
        raise InputError(f"{state_path}: not a training checkpoint (epoch {state['epoch']!r})")
    return state


def _flag_text(flag: str, value) -> str:
    if isinstance(value, (list, tuple)):
        value = ",".join(value)
    if value is True:
        return flag
    return f"no {flag}" if value is None or value is False or value == "" else f"{flag} {value}"


def check_resumable(config: TrainConfig, state: dict, out: Path, preset: Preset | None = None) -> None:
    """The resumed run is the one started in ``out``: the same task and flags; only --epochs may change.

    The state records the configuration it was started with; a state without one (an older run) is
    compared by the networks it holds. ``preset``: the one --preset gives now, compared field by field with the
    preset the run recorded (a preset file may be spelt from another folder, or edited since); without it, or for
    a run that recorded none, --preset is compared as written.
    """
    recorded = state.get("config") if isinstance(state.get("config"), dict) else {}
    held = {("depth",): "depth", ("pixor",): "detector", ("depth", "pixor"): "joint"}
    task = recorded.get("task") or held.get(tuple(sorted(state["networks"])), config.task)
    if task != config.task:
        raise InputError(f"task {config.task}: {out} was started as a {task} run "
                         f"(resume it with python -m models.train {task} … --resume)")
    compared = [("--preset", "preset"), ("--train-only", "train_only")]
    started_preset = recorded.get("preset_config") if preset is not None else None
    if isinstance(started_preset, dict):  # the preset itself is compared, not how --preset spells it
        if started_preset.get("name") != preset.name:  # another preset (a registered name, or a file renamed)
            raise InputError(f"{_flag_text('--preset', config.preset)} (preset {preset.name!r}), but {out} was "
                             f"started with {_flag_text('--preset', recorded.get('preset'))} (preset "
                             f"{started_preset.get('name')!r}; resume with the same flags; only --epochs may change)")
        check_same_preset(preset, started_preset, config.preset, out)
        compared = compared[1:]
    if config.task == "detector":
        compared.insert(1, ("--input", "input_mode"))
    # Everything else that decides what the remaining epochs train on and how (--epochs may grow):
    # resumed with other values, the run would silently stop being the one its log and checkpoints describe
    # (the optimizer's saved learning rate would even override --lr, while the metadata recorded --lr).
    compared += [("--data", "data"), ("--val-data", "val_data"), ("--train-split", "train_split"),
                 ("--val-split", "val_split"), ("--max-train-frames", "max_train_frames"),
                 ("--max-val-frames", "max_val_frames"), ("--batch-size", "batch_size"), ("--lr", "lr"),
                 ("--lr-step", "lr_step"), ("--lr-gamma", "lr_gamma"), ("--resnet18", "resnet18"),
                 ("--seed", "seed"), ("--depth-loss", "depth_loss"), ("--car-weight", "car_weight"),
                 ("--freeze-bn", "freeze_bn"), ("--quick", "quick"), ("--pseudo-dir", "pseudo_dir"),
                 ("--val-pseudo-dir", "val_pseudo_dir"), ("--depth-checkpoint", "depth_checkpoint"),
                 ("--pixor-checkpoint", "pixor_checkpoint"), ("--emulate-beams", "emulate_beams")]
    for flag, key in compared:
        if key not in recorded and key not in RECORDED_SINCE:
            continue
        wanted, started = getattr(config, key), recorded.get(key, RECORDED_SINCE.get(key))
        if isinstance(wanted, (list, tuple)) or isinstance(started, (list, tuple)):
            wanted, started = tuple(wanted or ()), tuple(started or ())
        elif key.endswith(("data", "split", "dir", "checkpoint", "resnet18")):  # the same file, however it is spelt
            wanted, started = (None if v is None else str(Path(v).resolve()) for v in (wanted, started))
        if wanted != started:
            raise InputError(f"{_flag_text(flag, wanted)}, but {out} was started with {_flag_text(flag, started)}"
                             f" (resume with the same flags; only --epochs may change)")
    # Not refused, but the float sums run in another order: the remaining epochs do not match the uninterrupted run's.
    for flag, key in (("--precision", "precision"), ("--device", "device"), ("--threads", "threads"),
                      ("--compile", "compile")):
        if key in recorded and recorded[key] != getattr(config, key):
            log.warning("%s: resumed with %s, started with %s: the remaining epochs compute differently", out,
                        _flag_text(flag, getattr(config, key)), _flag_text(flag, recorded[key]))


def check_same_preset(preset: Preset, started: dict, given: str, out: Path) -> None:
    """An InputError naming the first field in which ``preset`` (--preset ``given`` now) differs from the preset
    ``started`` (its ``to_dict()``) that the run in ``out`` recorded: its remaining epochs would train another grid
    or network under the first epochs' log and checkpoints."""
    now, then = preset_fields(preset.to_dict()), preset_fields(started)
    for name, value in now.items():
        if name in then and then[name] != value:  # a field the run's record lacks (added since) is not compared
            raise InputError(f"--preset {given}: {name} {value!r}, but {out} was started with {then[name]!r} "
                             f"(preset {started.get('name')!r}; resume with the preset it was started with, "
                             "unchanged; only --epochs may change)")


def frame_fingerprints(train_ids: list[str], val_ids: list[str]) -> dict[str, str | int]:
    """What a run's state records of the frames it trains and validates on: their counts and the sha256 of each
    id list in its order (which, with the seed, decides every batch), for :func:`check_same_frames`."""
    def digest(ids: list[str]) -> str:
        return hashlib.sha256("\n".join(ids).encode()).hexdigest()

    return {"train_frames": len(train_ids), "train_frames_sha256": digest(train_ids),
            "val_frames": len(val_ids), "val_frames_sha256": digest(val_ids)}


def check_same_frames(state: dict, out: Path, train_ids: list[str], val_ids: list[str]) -> None:
    """A resumed run reads the frames it was started on: the same flags can name others (a split file edited,
    frames added to a folder read whole), and the remaining epochs would silently train on them. Refused in one
    line; a state from before the record is not compared."""
    recorded = state.get("config") if isinstance(state.get("config"), dict) else {}
    now = frame_fingerprints(train_ids, val_ids)
    for kind, flags in (("train", "--data / --train-split"), ("val", "--val-data / --val-split")):
        started = recorded.get(f"{kind}_frames_sha256")
        if started is not None and started != now[f"{kind}_frames_sha256"]:
            name = "training" if kind == "train" else "validation"
            raise InputError(f"{flags}: {out} was started on {_frames(recorded.get(f'{kind}_frames', 0), name)}, "
                             f"and the same flags now give {_frames(int(now[f'{kind}_frames']), 'other')} (a split "
                             "file edited, frames added or removed); resume on the frames it started with, or start "
                             "a new run")


def restore_state(state: dict, state_path: Path, networks: dict[str, torch.nn.Module], optimizer, scheduler,
                  preset_name: str) -> None:
    """Weights, optimizer, schedule and random generators from a run's state (exact resume)."""
    for name, net in networks.items():
        if name not in state["networks"]:
            raise InputError(f"{state_path}: holds no {name} network (it has {', '.join(state['networks']) or 'none'})")
        try:
            net.load_state_dict(state["networks"][name])
        except RuntimeError as exc:
            lines = [line.strip() for line in str(exc).splitlines() if line.strip()]  # the first mismatch
            raise InputError(f"{state_path}: its {name} weights do not fit --preset {preset_name} "
                             f"({lines[min(1, len(lines) - 1)] if lines else type(exc).__name__})") from None
    try:
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        torch.set_rng_state(state["torch_rng"])
        np.random.set_state(state["numpy_rng"])
        random.setstate(state["python_rng"])
    except (ValueError, KeyError, TypeError, RuntimeError) as exc:
        raise InputError(f"{state_path}: not a training checkpoint of this run "
                         f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from None


def already_trained(result: TrainResult) -> str:
    """The command's answer to a resumed run that has nothing left to train."""
    done, epochs = result.epochs_before, result.epochs
    trained = f"{done} of {done} epochs" if done == epochs else f"{done} epochs, --epochs asks for {epochs}"
    return f"{result.run_dir}: already trained {trained}; nothing to do (raise --epochs to train more)"


def _missing(folder: Path, pattern: str, ids: list[str]) -> tuple[str, Path, str] | None:
    """The first of ``ids`` whose ``folder/pattern`` file is missing, that file, and how many more are
    missing ("" if none); None if none is."""
    missing = [fid for fid in ids if not (folder / pattern.format(fid)).is_file()]
    if not missing:
        return None
    return missing[0], folder / pattern.format(missing[0]), f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""


def _check_scan_size(scan: Path) -> None:
    """A scan file of whole points, none empty (InputError naming it): a cut-off file fails now, not an epoch in."""
    size = scan.stat().st_size
    if size == 0 or size % POINT_BYTES:
        raise InputError(f"{scan}: size {size} bytes is not a whole number of {POINT_BYTES}-byte points "
                         "(a KITTI scan is float32 rows x, y, z, reflectance)")


def _check_frame_files(folder: Path, fid: str) -> None:
    """A frame's files as far as they can be checked without decoding them: the calibration's keys, a scan
    of whole points, an image that starts and ends as a PNG or JPEG (InputError naming the file)."""
    read_calib(folder / "calib" / f"{fid}.txt")
    _check_scan_size(folder / "velodyne" / f"{fid}.bin")
    check_image_file(folder / "image_2" / f"{fid}.png")


def _check_drive_files(folder: Path, flag: str, ids: list[str], beams: int | None) -> None:
    """A depth-completion drive's frames as far as they can be checked without decoding them (their three PNGs
    whole and of one size, raw scans of whole points) and, when its scans are thinned, its calibration."""
    if beams and drive_calibration(folder) is None:  # an unreadable file is an InputError naming it
        raise InputError(f"{flag} {folder}: no drive calibration (calib_cam_to_cam.txt and calib_velo_to_cam.txt, "
                         f"in it or in {folder.parent}); a depth run thins the drive's scans to {beams} lines "
                         "through it")
    for fid in ids:
        paths = [folder / pattern.format(fid) for pattern in DRIVE_FILES]
        for path in paths:
            check_image_file(path)
        sizes = [read_image_size(path) for path in paths]
        for path, size in zip(paths[1:], sizes[1:], strict=True):
            check_map_size(path, size, paths[0], sizes[0])
        scan = raw_scan_path(folder, fid)
        if scan is not None:
            _check_scan_size(scan)


def _check_depth_maps(folder: Path, flag: str, ids: list[str]) -> None:
    """A folder's ``depth_2/`` targets, when it has that folder: a map of every frame (a frame without one would
    silently learn from its scan instead, mixing two kinds of target), each a PNG of its image's size (the crop is
    taken from the map's own shape: another size trains on another part of the scene). Sizes from the PNG headers
    alone; InputError naming the first frame without a map and how many more, or the first map of another size."""
    dense = folder / "depth_2"
    if not dense.is_dir():
        return  # no dense ground truth: every frame's target is its scan, as documented
    missing = _missing(folder, "depth_2/{}.png", ids)
    if missing is not None:
        frame, path, more = missing
        raise InputError(f"{flag} {folder}: frame {frame}{more} has no depth map ({path}) although depth_2/ holds "
                         "the others' targets; give every frame its map, or remove depth_2/ to train on the scans")
    for fid in ids:
        path, image = dense / f"{fid}.png", folder / "image_2" / f"{fid}.png"
        check_image_file(path)  # whole, not cut off
        with open(path, "rb") as handle:
            if handle.read(len(PNG_SIGNATURE)) != PNG_SIGNATURE:
                raise InputError(f"{path}: not a PNG (a KITTI depth map is a 16-bit PNG)")
        map_hw, image_hw = read_image_size(path), read_image_size(image)
        if map_hw != image_hw:
            raise InputError(f"{path}: a {map_hw[1]}×{map_hw[0]} depth map for the {image_hw[1]}×{image_hw[0]} image "
                             f"{image}; it must cover the whole image, pixel for pixel")


def check_frames(config: TrainConfig, train_dir: Path, train_ids: list[str], val_dir: Path,
                 val_ids: list[str], beams: int | None = 16) -> None:
    """Every frame file the run reads is there, before it trains: each frame's scan, image and calibration;
    its labels (``label_2/``) for the detector and joint tasks, whose targets and AP come from them. Depth
    runs need no labels (the target is ``depth_2/ID.png`` when present, else the frame's stored scan, unthinned:
    64 lines on KITTI, a 16-line sensor's own under ``--emulate-beams 0``)
    unless ``--car-weight`` weighs the labelled cars' pixels. A folder with ``depth_2/`` must hold the map of
    every frame whose depth target the run reads (a depth run's, a joint run's training frames), of its image's
    size (:func:`_check_depth_maps`).

    A depth-completion drive (:func:`pipeline.depth_completion.is_drive_folder`) has each frame's
    ``image_02``, ``velodyne_raw`` and ``groundtruth`` PNGs checked instead, and its calibration, which
    thinning its scans to ``beams`` lines (training's 16) needs; it has no labels to train ``--car-weight`` on."""
    labels = config.task in ("detector", "joint") or config.car_weight != 1.0
    needs = f"a {config.task} run" + (" with --car-weight" if config.task == "depth" else "")
    val_flag = "--val-data" if config.val_data is not None else "--data"
    for folder, ids, flag, split in ((train_dir, train_ids, "--data", ("--train-split", config.train_split)),
                                     (val_dir, val_ids, val_flag, ("--val-split", config.val_split))):
        drive = is_drive_folder(folder)
        # --car-weight weighs the training frames' loss alone: a drive may still validate such a run
        if drive and labels and (config.task != "depth" or ids is train_ids):
            raise InputError(f"{flag} {folder}: a depth-completion drive, which has no labelled cars; {needs} needs "
                             "the ground-truth boxes of an object folder (label_2/)")
        for pattern in DRIVE_FILES if drive else FRAME_PATTERNS:
            missing = _missing(folder, pattern, ids)
            if missing is None:
                continue
            frame, path, more = missing
            if split[1] is not None:  # the ids come from a split file: name it
                raise InputError(f"{split[0]} {split[1]}: frame {frame}{more} is not in {folder} (no {path})")
            raise InputError(f"{flag} {folder}: frame {frame}{more} has no {path}")
        if drive:
            _check_drive_files(folder, flag, ids, beams)
            continue
        for fid in ids:  # what a file's size and ends tell, so that a broken one fails now, not an epoch in
            _check_frame_files(folder, fid)
        if config.task == "depth" or (config.task == "joint" and ids is train_ids):  # joint validates PIXOR alone
            _check_depth_maps(folder, flag, ids)
        if labels:
            if not (folder / "label_2").is_dir():
                raise InputError(f"{flag} {folder}: no label_2/ folder; {needs} needs the ground-truth boxes "
                                 f"(label_2/ID.txt of every frame)")
            missing = _missing(folder, "label_2/{}.txt", ids)
            if missing is not None:
                frame, path, more = missing
                raise InputError(f"{flag} {folder}: frame {frame}{more} has no ground truth ({path}); {needs} "
                                 f"needs the labels of every frame")
        if labels or ids is val_ids:  # depth validation reads the labels that are there (car_in_box_*)
            for fid in ids:  # InputError naming the file and line of a malformed one
                if (folder / "label_2" / f"{fid}.txt").is_file():
                    read_labels(folder / "label_2" / f"{fid}.txt")


def label_classes(folder: Path, ids: list[str]) -> tuple[Counter, bool]:
    """Whether the ``label_2`` files of ``ids`` in ``folder`` label a Car (:func:`models.data.is_car`), and the
    classes they name with their counts: of every file when none does (each read once, a few hundred bytes),
    else of those read up to the first with a Car (usually the first file alone)."""
    classes: Counter = Counter()
    for fid in ids:
        labels = read_labels(folder / "label_2" / f"{fid}.txt")
        classes.update(label.type for label in labels)
        if any(is_car(label) for label in labels):
            return classes, True
    return classes, False


def check_cars(config: TrainConfig, train_dir: Path, train_ids: list[str], val_dir: Path, val_ids: list[str]) -> None:
    """A detector or joint run's training frames (those it trains on, after --max-train-frames) label at least one
    Car, or it would train PIXOR on no positive, to a low loss and an AP of 0, without a word: refused in one line
    naming the folder and the classes its labels hold. Validation frames without a Car give an AP of 0 whatever
    the net learns (and the best epoch is picked by AP): said in that line, or warned of when training has cars.
    A depth run with ``--car-weight`` whose training frames label no Car is refused too: the weight would weigh
    nothing."""
    if config.task == "depth" and config.car_weight != 1.0:
        # --car-weight weighs the labelled cars' pixels: with no Car it weighs nothing, and the run is the plain one.
        classes, cars = label_classes(train_dir, train_ids)
        if not cars:
            found = _classes_text(classes)
            raise InputError(f"--car-weight {config.car_weight:g}: no {CAR_CLASS} in the label_2 files of the "
                             f"{_frames(len(train_ids), 'training')} of --data {train_dir} (classes found: {found}), "
                             "so it would weigh nothing")
        return
    if config.task not in ("detector", "joint"):
        return
    val_flag = "--val-data" if config.val_data is not None else "--data"
    _, val_cars = label_classes(val_dir, val_ids)
    classes, cars = label_classes(train_dir, train_ids)
    if not cars:
        found = _classes_text(classes)
        val_frames = (f"its {_frames(len(val_ids), 'validation')}" if val_dir.resolve() == train_dir.resolve()
                      else f"the {_frames(len(val_ids), 'validation')} of {val_flag} {val_dir}")
        also = "" if val_cars else f"; {val_frames} label none either (AP would be 0)"
        raise InputError(f"--data {train_dir}: no {CAR_CLASS} in the label_2 files of its "
                         f"{_frames(len(train_ids), 'training')} (classes found: {found}); the detector learns "
                         f"KITTI's {CAR_CLASS} class{also}")
    if not val_cars:
        log.warning("%s %s: no %s in the label_2 files of its %s: their AP is 0 whatever the detector learns, "
                    "and the run's best epoch (picked by AP) means nothing", val_flag, val_dir, CAR_CLASS,
                    _frames(len(val_ids), "validation"))


def _classes_text(classes: Counter) -> str:
    """"Vehicle 40, Pedestrian 3": the classes labels name, most frequent first."""
    return ", ".join(f"{kind} {count}" for kind, count in classes.most_common()) or "none: the files are empty"


def _frames(count: int, kind: str) -> str:
    """"1 training frame", "8 training frames"."""
    return f"{count} {kind} frame{'' if count == 1 else 's'}"


def thins_scans(config: TrainConfig) -> bool:
    """Whether the run reads "16-line" scans, thinned as --emulate-beams says: all but a detector's lidar64."""
    return not (config.task == "detector" and config.input_mode == "lidar64")


def emulated_lines(config: TrainConfig) -> int | None:
    """The lines the run thins its scans to; None when it reads them as stored (--emulate-beams 0, --input lidar64)."""
    return (config.emulate_beams or None) if thins_scans(config) else None


def check_thinnable_scans(config: TrainConfig, train_dir: Path, train_ids: list[str], val_dir: Path,
                          val_ids: list[str]) -> None:
    """The first training and validation scans thin to --emulate-beams lines: a 16-line sensor's scans, left at
    the default 16, are refused now in one line naming the scan and the flag (--emulate-beams 0), not by the
    first batch's emulate_beams error without a file name. With --emulate-beams 0 they must not have 64 lines,
    or the run would learn from 64 as if from 16 and its manifest say 16. A drive's maps are thinned through its
    calibration, which read_frame checks. ``--input lidar64`` reads the scans as stored: they must have 64 lines
    (:func:`check_64_lines`)."""
    for folder, first in dict.fromkeys(((train_dir, train_ids[0]), (val_dir, val_ids[0]))):  # each pair once
        if is_drive_folder(folder):
            continue
        if thins_scans(config):
            check_thinnable(folder, [first], config.emulate_beams, "train on")
        else:
            check_64_lines(folder / "velodyne" / f"{first}.bin")


def check_64_lines(scan: Path) -> None:
    """``--input lidar64``: the scan has 64 lines, as :func:`pipeline.beams.emulate_beams` judges a scan it can thin
    (the test every other input's check makes, :func:`pipeline.beams.check_thinnable`). A 16-line sensor's scans would
    train a "lidar64" PIXOR, and its exported manifest would claim 64 lines: refused in one line naming the scan."""
    points = read_velodyne(scan).points  # an unreadable scan is named by its reader, as such
    try:
        emulate_beams(points, 16)
    except InputError as exc:  # its reason, without the advice that suits thinning: "the scan has 16 rings, …"
        reason = str(exc).removeprefix("points: ").split(" (emulate beams")[0]
        raise InputError(f"{scan}: --input lidar64 trains on 64-line scans as stored, but {reason}; "
                         "for a 16-line sensor's scans give --input lidar16 --emulate-beams 0") from None


def check_pseudo_maps(config: TrainConfig, train_ids: list[str], val_ids: list[str],
                      preset: Preset | None = None) -> None:
    """``--input pseudo``: the cached dense depth map of every frame the run trains and validates on, made from
    the run's scans and (given ``preset``) in its depth net's view."""
    if config.task == "detector" and config.input_mode == "pseudo":
        if config.pseudo_dir is None:
            raise InputError("--input pseudo needs the cached dense depth maps (--pseudo-dir; "
                             "python -m models.cache_pseudo makes them)")
        val_pseudo = ("--val-pseudo-dir", config.val_pseudo_dir) if config.val_pseudo_dir else ("--pseudo-dir",
                                                                                                config.pseudo_dir)
        val_data = ("--val-data", config.val_data) if config.val_data is not None else ("--data", config.data)
        # One folder for both suits splits of one --data; with another --val-data, the same ids are other frames.
        hint = " and give it as --val-pseudo-dir" if config.val_pseudo_dir is None else ""
        for (flag, folder), ids, (data_flag, data), also in (
                (("--pseudo-dir", config.pseudo_dir), train_ids, ("--data", config.data), ""),
                (val_pseudo, val_ids, val_data, hint)):
            missing = _missing(Path(folder), "{}.png", ids)
            if missing is not None:
                frame, path, more = missing
                raise InputError(f"{flag} {folder}: no cached depth map of frame {frame}{more} ({path})")
            check_sources(Path(folder), flag, Path(data), data_flag, ids, also)
            made_with = recorded_beams(Path(folder))
            if made_with is not None and made_with != config.emulate_beams:  # the depth of other scans than the run's
                raise InputError(f"{flag} {folder}: its maps were made with --emulate-beams {made_with} (cache.json), "
                                 f"this run thins its scans with --emulate-beams {config.emulate_beams}; cache them "
                                 f"with python -m models.cache_pseudo --emulate-beams {config.emulate_beams}")
            if preset is not None:
                check_pseudo_view(Path(folder), flag, ids[0] if ids else None, preset)


def _view_text(crop_hw: object, input_scale: object, input_hw: object) -> str:
    """A depth net's view as a message gives it: ``crop [352, 1216] × 0.25 = 88×304``."""
    hw = list(input_hw) if isinstance(input_hw, (list, tuple)) else input_hw
    shape = f"{hw[0]}×{hw[1]}" if isinstance(hw, list) and len(hw) == 2 else repr(hw)
    return f"crop {list(crop_hw) if isinstance(crop_hw, (list, tuple)) else crop_hw!r} × {input_scale} = {shape}"


def check_pseudo_view(folder: Path, flag: str, first_id: str | None, preset: Preset) -> None:
    """InputError when ``folder``'s maps are in another view of the image than ``preset``'s depth net sees: the
    run would place each pixel's depth with its own view's calibration (a quarter-scale cache read at half scale
    put the points at azimuths −0.7…39° instead of −40…39°). The view ``cache.json`` records (since session 49),
    else the first map's shape."""
    wanted = {"crop_hw": list(preset.crop_hw), "input_scale": preset.depth.input_scale,
              "input_hw": list(preset.depth.input_hw)}
    made = recorded_view(folder)
    if made is not None:
        made = {key: list(v) if isinstance(v, (list, tuple)) else v for key, v in made.items()}
        if all(made.get(key) == value for key, value in wanted.items()):
            return
        theirs = _view_text(made.get("crop_hw"), made.get("input_scale"), made.get("input_hw"))
        where = f"{folder / RECORD}"
    else:
        if first_id is None:
            return
        path = folder / f"{first_id}.png"
        hw = list(read_image_size(path))
        if hw == wanted["input_hw"]:
            return
        theirs, where = f"{hw[0]}×{hw[1]}", str(path)
    made_with = recorded_preset(folder)
    by = f", made with preset {made_with!r}" if made_with else ""
    raise InputError(f"{flag} {folder}: its maps are in the view {theirs} ({where}{by}); preset {preset.name!r} "
                     f"sees {_view_text(**wanted)}, so every pseudo point would be misplaced: cache them again with "
                     "python -m models.cache_pseudo from a --models directory of this preset")
