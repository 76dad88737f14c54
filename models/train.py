"""Training: ``python -m models.train depth|detector|joint --data DIR --preset P --out RUN_DIR [--resume] …``

* depth — the paper's recipe by default: batch 4, Adam lr 1e-4 decayed every 5
  epochs (the paper gives no factor: halved here, ``--lr-gamma``; Ma et al.'s code
  divides by 10), 10 epochs, MSE on pixels with ground truth; input = 16-line sparse
  depth + image. ``--data`` / ``--val-data`` may also be KITTI depth-completion
  drives in the flat layout of pipeline/depth_completion.py (``image_02/``,
  ``velodyne_raw/``, ``groundtruth/``, the drive's calibration in it or above;
  split files list its frame ids): 16 lines thinned through that calibration,
  KITTI's semi-dense ground truth as the target.
* detector — PIXOR from scratch: Adam, batch 8, lr 1e-3 halved when the
  validation loss stops falling; ``--input lidar64|lidar16|pseudo``.
* joint — both networks fine-tuned together through a differentiable BEV
  occupancy (models/soft_bev.py); starts from the two trained checkpoints.

``--emulate-beams N`` (32, 16, 8, 4; default 16) is the line count every
"16-line" scan of the run is thinned to from the stored one: the depth net's
input, PIXOR's ``lidar16`` and ``pseudo`` scans, the joint task's, in training
and validation alike; ``--emulate-beams 0`` takes the scans as stored, a 16-line
sensor's own (they cannot be thinned again: left at 16 on such scans, the run is
refused before it starts, naming the first scan). It is recorded in the run's
state and checkpoints, so ``--resume`` keeps it and export carries it.

``--depth-checkpoint`` / ``--pixor-checkpoint`` also start a depth or detector
run from trained weights: a checkpoint, or the ``depth.onnx`` / ``pixor.onnx``
of an exported model directory (its batch norms come folded into the
convolutions, so train such weights with ``--train-only`` or ``--freeze-bn``). ``--train-only
refine`` trains only that submodule (here the depth net's full-resolution head,
which an older export lacks and which then starts from its initialisation);
every other weight and batch-norm statistic stays as loaded.

Each epoch: a progress bar, validation metrics (depth RMSE/MAE; detector loss
and KITTI BEV AP), the best weights as ``RUN_DIR/depth.pt`` / ``pixor.pt`` in
the checkpoint format ``python -m export --checkpoints RUN_DIR`` reads, the full
training state in ``RUN_DIR/state.pt`` (also written before the first epoch;
exact resume with ``--resume``: weights, optimizer, schedule, RNG, the epoch's
data order comes from the seed and the epoch number) and one JSON line in
``RUN_DIR/log.jsonl``. Each file is written whole or not at all, so a run killed
at any moment resumes; SIGTERM stops it as Ctrl-C does, saying which epoch it
keeps; a second process given the same RUN_DIR is refused while one trains there.

Arithmetic: bf16 autocast with channels-last tensors where the CPU supports it
(``--precision auto``, the default; ``fp32`` to turn it off). Weights, optimizer
state and losses stay fp32, so checkpoints and exported models are the same
either way.

Compilation: the training forward pass of the depth and detector tasks runs
through ``torch.compile`` (``--compile auto``, the default, when the run has
at least 200 steps (``COMPILE_MIN_STEPS``) and, on the CPU, a C++ compiler is on
the PATH; ``on``, ``off``). Compiling takes about a minute per network and
process; Inductor fuses batch norm's backward pass with its neighbours, which
eager PyTorch runs as separate memory-bound passes (44 % of an eager edge PIXOR
step here). Validation and the joint task stay eager (a joint run refuses
``--compile on``). Compiled and eager steps
compute the same function; their floating-point results differ in the last
bits (fused reductions), so losses agree to a few decimals, not to the digit.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import logging
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader
from tqdm import tqdm

from models import build_depth_net, build_pixor
from models.allocator import keep_freed_memory
from models.checkpoint import CHECKPOINT_FILES, save_checkpoint, write_text_atomic
from models.curves import RunInfo, after_epoch, run_description
from models.data import (
    DETECTOR_INPUTS,
    DepthCompletionDataset,
    DepthDataset,
    DetectorDataset,
    car_boxes,
    depth_target,
    frame_points,
)
from models.depth_net import load_resnet18_encoder
from models.devices import (
    COMPILE_MIN_STEPS,
    COMPILED_TASKS,
    CPU,
    autocast,
    resolve_compile,
    resolve_device,
    resolve_precision,
    run_layout,
    seed_everything,
)
from models.joint import joint_bev
from models.losses import DEPTH_LOSSES, pixor_loss
from models.run_checks import (
    STATE_FILE,
    already_trained,
    check_cars,
    check_frames,
    check_out,
    check_pseudo_maps,
    check_resumable,
    check_same_frames,
    check_thinnable_scans,
    emulated_lines,
    frame_fingerprints,
    load_state,
    restore_state,
    run_lock,
    save_state,
    stopped_at,
    thins_scans,
)
from models.start_weights import (
    freeze_batch_norms,
    freeze_except,
    load_start_weights,
    start_training_metadata,
)
from models.validation import validate_depth, validate_detector
from pipeline.beams import BEAM_COUNTS
from pipeline.cli import (
    HelpFormatter,
    add_no_progress,
    examples,
    non_negative_int,
    positive_float,
    positive_int,
    sigterm_as_interrupt,
    stopped,
)
from pipeline.depth_completion import (
    drive_calibration,
    drive_frame_ids,
    is_drive_folder,
    refuse_kitti_layout,
)
from pipeline.errors import InputError
from pipeline.frame import frame_ids, load_frame
from pipeline.preprocess import depth_inputs
from pipeline.presets import Preset, get_preset
from pipeline.provenance import code_version
from pipeline.pseudo import pixel_rays
from pipeline.targets import encode_targets

log = logging.getLogger(__name__)
TASKS = ("depth", "detector", "joint")


@dataclass
class TrainConfig:
    """One training run. Defaults are the paper's recipe for the task (filled in by :func:`recipe`)."""

    task: str
    data: Path
    preset: str
    out: Path
    val_data: Path | None = None  # default: --data with --val-split, else the training folder
    train_split: Path | None = None
    val_split: Path | None = None
    input_mode: str = "lidar16"  # detector: lidar64 | lidar16 | pseudo
    # The lines the stored scans are thinned to (pipeline.beams.BEAM_COUNTS) wherever the run reads a "16-line"
    # scan; 0: as stored, a 16-line sensor's own (emulate_beams refuses to thin those again).
    emulate_beams: int = 16
    pseudo_dir: Path | None = None  # detector --input pseudo: cached dense depth PNGs of the training frames
    val_pseudo_dir: Path | None = None  # … of the validation frames (default: pseudo_dir, one folder for both)
    depth_checkpoint: Path | None = None  # joint: trained depth.pt; depth: weights to start from
    pixor_checkpoint: Path | None = None  # joint: trained pixor.pt; detector: weights to start from
    train_only: tuple[str, ...] = ()  # submodules to train (say "refine"); the rest frozen, batch norms included
    freeze_bn: bool = False  # batch-norm statistics stay as loaded (their scale and shift still train)
    epochs: int | None = None
    batch_size: int | None = None
    lr: float | None = None
    lr_step: int = 5  # depth and joint: multiply the rate by lr_gamma every lr_step epochs
    depth_loss: str = "mse"  # depth and joint: mse (the paper) | l1 (why: losses.masked_l1, docs/models.md "Losses")
    car_weight: float = 1.0  # depth: the loss weight of the labelled cars' own pixels (models.data.car_pixels)
    lr_gamma: float = 0.5
    resnet18: Path | None = None  # depth: ImageNet ResNet-18 weights (torchvision's format) for the encoder
    max_train_frames: int | None = None
    max_val_frames: int | None = None
    workers: int = 0
    seed: int = 0
    resume: bool = False  # continue the run in ``out`` if it has one (a library caller's rerun: else start it)
    strict_resume: bool = False  # with resume: no run to continue in ``out`` is an error (the command's --resume)
    quick: bool = False
    progress: bool = True
    threads: int | None = None
    precision: str = "auto"  # auto | bf16 | fp32 (bf16 = autocast; weights and optimizer stay fp32)
    device: str = "auto"  # auto (cuda when torch sees a GPU, else cpu) | cpu | cuda | cuda:N
    compile: str = "auto"  # auto | on | off: torch.compile the training forward pass (module docstring)


@dataclass
class TrainResult:
    """What a run made."""

    run_dir: Path
    checkpoints: dict[str, Path]
    history: list[dict] = field(default_factory=list)
    first_loss: float = float("nan")  # mean training loss of the first epoch of this invocation
    last_loss: float = float("nan")  # … and of the last
    epochs_before: int = 0  # epochs the run had trained when this invocation started (resumed)
    epochs: int = 0  # epochs the run is to have in all (the recipe's or --epochs)

    @property
    def nothing_to_do(self) -> bool:
        """A resumed run that had already trained its epochs: this invocation trained none."""
        return self.epochs_before >= self.epochs > 0


# Defaults per task: (epochs, batch size, learning rate). Depth is the paper's recipe; for the detector the paper
# gives the batch and rate but no epoch count (30 is ours); joint fine-tuning's numbers are ours throughout.
RECIPES = {
    "depth": (10, 4, 1e-4),
    "detector": (30, 8, 1e-3),
    "joint": (3, 2, 1e-5),
}


def recipe(config: TrainConfig) -> TrainConfig:
    """Fill unset epochs / batch size / lr from the task's recipe; ``quick`` shrinks everything."""
    epochs, batch, lr = RECIPES[config.task]
    config.epochs = config.epochs or epochs
    config.batch_size = config.batch_size or batch
    config.lr = config.lr or lr
    if config.quick:
        config.epochs = min(config.epochs, 3)
        config.batch_size = min(config.batch_size, 2)
        config.max_train_frames = config.max_train_frames or 4
        config.max_val_frames = config.max_val_frames or 2
    return config


# ----------------------------------------------------------------------------- checks before a run
# (this one reads TrainConfig's defaults; the others, and the run's saved state: models/run_checks.py)
def check_flags_apply(config: TrainConfig) -> None:
    """Refuse a setting the task does not use: silently ignored, it would leave a user believing the run
    used it (a depth run given --pixor-checkpoint, a detector given --depth-loss)."""
    pseudo = config.task == "detector" and config.input_mode == "pseudo"
    unused = [
        ("--input", config.input_mode != TrainConfig.input_mode and config.task != "detector",
         "only a detector run reads another input (lidar64, pseudo)"),
        ("--pseudo-dir", config.pseudo_dir is not None and not pseudo, "read by detector runs with --input pseudo only"),
        ("--val-pseudo-dir", config.val_pseudo_dir is not None and not pseudo,
         "read by detector runs with --input pseudo only"),
        ("--depth-checkpoint", config.depth_checkpoint is not None and config.task == "detector",
         "a detector run trains PIXOR alone"),
        ("--pixor-checkpoint", config.pixor_checkpoint is not None and config.task == "depth",
         "a depth run trains the depth net alone"),
        ("--emulate-beams", config.emulate_beams != TrainConfig.emulate_beams and not thins_scans(config),
         "--input lidar64 reads the scans as stored"),
        ("--depth-loss", config.depth_loss != TrainConfig.depth_loss and config.task == "detector",
         "a detector run has no depth loss"),
        ("--car-weight", config.car_weight != TrainConfig.car_weight and config.task != "depth",
         "it weights the depth loss of a depth run"),
        ("--freeze-bn", config.freeze_bn and config.depth_checkpoint is None and config.pixor_checkpoint is None,
         "it keeps the batch norms of the weights a run starts from: give --depth-checkpoint or --pixor-checkpoint"),
        ("--lr-step", config.lr_step != TrainConfig.lr_step and config.task == "detector",
         "a detector run halves its rate when the validation loss stops falling"),
        ("--lr-gamma", config.lr_gamma != TrainConfig.lr_gamma and config.task == "detector",
         "a detector run halves its rate when the validation loss stops falling"),
        ("--resnet18", config.resnet18 is not None and config.task != "depth",
         "it starts a depth run's encoder; a joint run starts from the trained --depth-checkpoint"),
        ("--resnet18", config.resnet18 is not None and config.depth_checkpoint is not None,
         "--depth-checkpoint gives every weight of the depth net already"),
        ("--compile", config.compile == "on" and config.task not in COMPILED_TASKS,
         "its per-frame soft BEV has no fixed shapes to compile for; it runs eager"),
        ("--workers", config.workers != TrainConfig.workers and config.task == "joint",
         "it loads its frames one by one in the training loop"),
    ]
    for flag, given, why in unused:
        if given:
            raise InputError(f"{flag}: not used by a {config.task} run ({why})")


def start_networks(config: TrainConfig, preset: Preset, resumed: bool = False) -> dict[str, torch.nn.Module]:
    """The task's networks with the weights the run starts from: ``--depth-checkpoint`` / ``--pixor-checkpoint``,
    or for a depth run ``--resnet18``'s ImageNet encoder (as Ma et al. start theirs; not when resumed: the run's
    state holds every weight)."""
    networks: dict[str, torch.nn.Module] = {}
    if config.task in ("depth", "joint"):
        networks["depth"] = build_depth_net(preset)
    if config.task in ("detector", "joint"):
        networks["pixor"] = build_pixor(preset)
    for name, path in (("depth", config.depth_checkpoint), ("pixor", config.pixor_checkpoint)):
        if name in networks and path is not None:
            load_start_weights(networks[name], name, Path(path), preset, config.train_only)
            if Path(path).suffix == ".onnx" and not config.freeze_bn and not config.train_only and not resumed:
                # Its batch norms are identities (folded into the convolutions): in training mode they would
                # normalise each batch afresh, and the network starts as another function than the one loaded.
                log.warning("--%s-checkpoint %s: an exported network's batch norms are folded into its "
                            "convolutions; without --freeze-bn (or --train-only) they re-learn their statistics "
                            "from the first batches and the run starts from other weights than these", name, path)
    if config.resnet18 is not None and not resumed:
        try:
            load_resnet18_encoder(networks["depth"], config.resnet18)
        except FileNotFoundError:
            raise InputError(f"--resnet18: {config.resnet18} does not exist") from None
        except (TypeError, ValueError) as exc:  # not a state dict, or widths that do not fit: it names the file
            raise InputError(f"--resnet18: {exc}") from None
    return networks


# ----------------------------------------------------------------------------- data
def check_layout(task: str, folder: Path, flag: str, split: Path | None) -> None:
    """``folder`` is a KITTI object folder, or (depth runs only) a depth-completion drive in the flat layout
    (:func:`pipeline.depth_completion.is_drive_folder`); KITTI's own ``proj_depth`` layout gets the way to link a
    drive into the flat one. With a split file a folder lacking its frames' files is named by :func:`check_frames`."""
    if is_drive_folder(folder):
        if task != "depth":
            raise InputError(f"{flag} {folder}: a depth-completion drive (velodyne_raw/, groundtruth/), which only a "
                             f"depth run trains on; a {task} run needs a KITTI object folder (velodyne/, label_2/)")
        return
    if (folder / "velodyne").is_dir():
        return
    if task == "depth":  # KITTI's layout: how to link one drive, whether or not a split is given
        refuse_kitti_layout(folder, flag)
    if split is None:
        also = " nor a depth-completion drive (no velodyne_raw/ and groundtruth/ inside)" if task == "depth" else ""
        raise InputError(f"{flag} {folder}: not a KITTI object folder (no velodyne/ inside){also}")


def folder_frame_ids(folder: Path, split: Path | None) -> list[str]:
    """The split file's ids, else every frame of the folder: an object folder's scans, a drive's ground truths."""
    if split is None and is_drive_folder(folder):
        return drive_frame_ids(folder)
    return frame_ids(folder, split)


def warn_overlap(config: TrainConfig, train_dir: Path, train_ids: list[str], val_dir: Path,
                 val_ids: list[str]) -> None:
    """One warning when frames of one folder are both trained and validated on (of those the run uses, after
    --max-*-frames): their validation figures, which pick the run's best epoch, then flatter the net. Refused it
    is not (a smoke test may mean it); validating on the very training frames, for want of --val-data or
    --val-split, has its own warning, as before."""
    if config.val_data is None and config.val_split is None:
        log.warning("no --val-data or --val-split: validating on the training frames")
        return
    if train_dir.resolve() != val_dir.resolve():
        return
    trained = set(train_ids)
    shared = [fid for fid in val_ids if fid in trained]
    if not shared:
        return
    validated = (f"--val-split {config.val_split}" if config.val_split is not None
                 else f"--val-data {val_dir} (every frame)")
    training = (f"--train-split {config.train_split}" if config.train_split is not None
                else f"every frame of --data {train_dir}, for want of --train-split")
    log.warning("%s: %d of its %d validation frames (%s among them) are training frames too (%s): their "
                "validation figures flatter the net; give a --train-split without them", validated, len(shared),
                len(val_ids), shared[0], training)


def split_ids(config: TrainConfig) -> tuple[Path, list[str], Path, list[str]]:
    """(train dir, train ids, val dir, val ids) from folders and optional split files.

    Every frame listed (before ``--max-train-frames`` / ``--max-val-frames`` take the first N) is checked
    to be there (:func:`check_frames`), so a bad split fails now, not an epoch in. A folder is a KITTI
    object folder or, for depth runs, a depth-completion drive (:func:`check_layout`).
    """
    for flag, folder, split in (("--data", config.data, config.train_split),
                                ("--val-data", config.val_data, config.val_split)):
        if folder is None:
            continue
        if not Path(folder).is_dir():
            raise InputError(f"{flag} {folder}: no such folder")
        check_layout(config.task, Path(folder), flag, split)
    train_dir, val_dir = Path(config.data), Path(config.val_data or config.data)
    train_ids = folder_frame_ids(train_dir, config.train_split)
    val_ids = folder_frame_ids(val_dir, config.val_split)
    check_frames(config, train_dir, train_ids, val_dir, val_ids, emulated_lines(config))
    if config.max_train_frames:
        train_ids = train_ids[: config.max_train_frames]
    if config.max_val_frames:
        val_ids = val_ids[: config.max_val_frames]
    if not train_ids or not val_ids:
        raise InputError(f"--data: no frames to train on in {config.data} or to validate on in {val_dir}")
    warn_overlap(config, train_dir, train_ids, val_dir, val_ids)
    return train_dir, train_ids, val_dir, val_ids


def depth_dataset(folder: Path, ids: list[str], preset: Preset, augment: bool = False, seed: int = 0,
                  car_weight: float = 1.0, beams: int | None = 16) -> DepthDataset | DepthCompletionDataset:
    """A depth run's frames of ``folder``, their scans thinned to ``beams`` lines (None or 0: as stored): an object
    folder's, or a depth-completion drive's (thinned through the drive's calibration, which :func:`check_frames`
    found; --car-weight is refused on a drive)."""
    if is_drive_folder(folder):
        return DepthCompletionDataset(folder, ids, preset, drive_calibration(folder) if beams else None, beams=beams,
                                      augment=augment, seed=seed)
    return DepthDataset(folder, ids, preset, beams=beams, augment=augment, seed=seed, car_weight=car_weight)


def stack_in_layout(samples: list[tuple[torch.Tensor, ...]], inputs: int = 0,
                    layout: torch.memory_format = torch.contiguous_format) -> tuple[torch.Tensor, ...]:
    """The batch of ``samples`` (tuples of (C, H, W) tensors); the first ``inputs`` fields (the network
    inputs) are allocated in ``layout`` and filled sample by sample, the targets are stacked as usual.

    The same values as ``torch.stack`` followed by ``.contiguous(memory_format=layout)``, without the
    second full copy: measured here (1 thread, a batch of 8 edge BEVs, 86 MB), 77 ms for stack +
    channels-last, 19 ms this way. Targets keep the default layout, so the losses sum in the same order.
    """
    batch = []
    for index, tensors in enumerate(zip(*samples)):
        if index >= inputs or layout == torch.contiguous_format:
            batch.append(torch.stack(tensors))
            continue
        out = torch.empty((len(tensors), *tensors[0].shape), dtype=tensors[0].dtype, memory_format=layout)
        for i, tensor in enumerate(tensors):
            out[i].copy_(tensor)
        batch.append(out)
    return tuple(batch)


def loader(dataset, batch_size: int, shuffle: bool, seed: int, workers: int, inputs: int = 0,
           layout: torch.memory_format = torch.contiguous_format) -> DataLoader:
    """Deterministic order: the shuffling generator is seeded per epoch by the caller. The first ``inputs``
    fields of each batch come in ``layout`` (:func:`stack_in_layout`)."""
    generator = torch.Generator().manual_seed(seed)
    return DataLoader(dataset, batch_size=batch_size, shuffle=shuffle, generator=generator, num_workers=workers,
                      drop_last=shuffle and len(dataset) > batch_size, persistent_workers=False,
                      collate_fn=functools.partial(stack_in_layout, inputs=inputs, layout=layout))


# ----------------------------------------------------------------------------- run
def run(config: TrainConfig) -> TrainResult:
    """Train one task; see the module docstring. The run folder is held (run_lock) while it trains."""
    with contextlib.ExitStack() as guard:
        return _run(config, guard)


def _write_log(log_path: Path, history: list[dict]) -> None:
    """The run's log from its state's records: one line per finished epoch, replaced whole."""
    text = "".join(json.dumps(record) + "\n" for record in history)
    if not log_path.is_file() or log_path.read_text(encoding="utf-8") != text:
        write_text_atomic(log_path, text)


def _append_log(log_path: Path, record: dict) -> None:
    """One epoch's line; a write that fails (a full disk) is undone, so no line is left cut short."""
    with open(log_path, "a", encoding="utf-8") as handle:
        size = handle.tell()
        try:
            handle.write(json.dumps(record) + "\n")
            handle.flush()
        except OSError:
            with contextlib.suppress(OSError):
                handle.truncate(size)
            raise


@dataclass
class _RunFolder:
    """The run folder (``--out``) as the checks found it: the state it holds when the run resumes, and whether
    this process holds its lock yet (a folder that did not exist is locked once made: :func:`_make_run_folder`)."""

    out: Path
    state: dict | None
    locked: bool

    @property
    def state_path(self) -> Path:
        """The run's training state: written before the first epoch and after each."""
        return self.out / STATE_FILE

    @property
    def log_path(self) -> Path:
        """The run's log: one JSON line per finished epoch."""
        return self.out / "log.jsonl"


@dataclass
class _Frames:
    """The frames the run trains and validates on (:func:`split_ids`, after ``--max-*-frames``)."""

    train_dir: Path
    train_ids: list[str]
    val_dir: Path
    val_ids: list[str]


@dataclass
class _Model:
    """The task's networks on the run's device, and what trains them."""

    networks: dict[str, torch.nn.Module]
    trained: list[torch.nn.Module]  # with --train-only, the submodules that train; else empty (whole networks)
    layout: torch.memory_format
    optimizer: torch.optim.Optimizer
    scheduler: torch.optim.lr_scheduler.ReduceLROnPlateau | torch.optim.lr_scheduler.StepLR
    # The training forward passes, compiled or not (:func:`_training_forward`); validation calls the networks.
    forward: dict[str, Callable[..., Any]] = field(default_factory=dict)


@dataclass
class _Data:
    """What the epochs read: the frames, the lines their scans are thinned to (None: as stored) and the datasets
    (a depth or detector run trains on one; a joint run loads its frames one by one; only a depth run validates
    on one)."""

    frames: _Frames
    beams: int | None
    train_set: DepthDataset | DepthCompletionDataset | DetectorDataset | None = None
    val_set: DepthDataset | DepthCompletionDataset | None = None


@dataclass
class _Progress:
    """Where the run stands: the epoch this invocation starts at, the best selection criterion so far, the
    finished epochs' log records, and this invocation's first and last mean training loss."""

    start_epoch: int = 0
    best: float = float("inf")
    history: list[dict] = field(default_factory=list)
    first_loss: float = float("nan")
    last_loss: float = float("nan")

    def add_train_loss(self, loss: float) -> None:
        """Note an epoch's mean training loss: the first of this invocation and the last so far."""
        if np.isnan(self.first_loss):
            self.first_loss = loss
        self.last_loss = loss


def _run(config: TrainConfig, guard: contextlib.ExitStack) -> TrainResult:
    """:func:`run` with ``guard`` holding the run folder's lock once it is taken: the checks, the networks, the
    run folder and its first state, the data, then each epoch (train, validate, log, keep the best weights, save
    the state). The steps keep this order: the random generators draw in it, so a fixed seed repeats the run."""
    config, device, preset = _settings(config)
    # Every input is checked before anything is trained or written: --out is made only after the checks.
    folder = _open_run_folder(config, preset, guard)
    _check_joint_start(config)
    frames = _checked_frames(config, folder, preset)
    # The first line of a run that will train (a refused one stays one error line; the checks' own warnings,
    # such as no validation split, come before it): a wrong preset or input is seen now, not at export.
    info = RunInfo(config.task, preset.name, config.input_mode, config.emulate_beams)
    log.info("%s", run_description(info, preset))
    if folder.state is not None and folder.state["epoch"] >= config.epochs:  # nothing to train: the run stays as it is
        return _nothing_left_to_train(config, folder.out, folder.state)
    seed_everything(config.seed)

    model = _build_model(config, preset, device, resumed=folder.state is not None)
    progress = _restore_progress(folder, model, config.preset)
    _make_run_folder(folder, guard)
    recorded_config = _recorded_config(config, preset, frames, folder.state)
    if folder.state is None:
        # The state before the first epoch, right after the folder is made: a run stopped in its first epoch
        # resumes (--resume) like any other, and the flags it was started with are there to compare.
        _save_state(folder, model, 0, progress, recorded_config)
    data = _build_data(config, preset, frames)
    model.forward, compiled = _training_forward(config, model, data, device)
    metadata_base = _checkpoint_metadata(config, preset, model.networks, frames.train_dir, frames.train_ids,
                                         frames.val_dir, frames.val_ids, compiled)
    # One line per epoch the state holds (a stale log in a folder without one would otherwise keep its lines).
    _write_log(folder.log_path, progress.history)

    for epoch in range(progress.start_epoch, config.epochs):
        tic = time.perf_counter()
        losses = _train_epoch(config, preset, device, model, data, epoch)
        progress.add_train_loss(float(np.mean(losses)))
        metrics = _validate(config, preset, device, model, data)
        trained_at = _step_schedule(config.task, model, metrics)
        record = _epoch_record(epoch, losses, trained_at, metrics, tic)
        progress.history.append(record)
        log.info("epoch %d: %s", epoch + 1,  # 4 significant digits: a learning rate of 5e-5 stays 5e-05
                 {k: float(f"{v:.4g}") if isinstance(v, float) else v for k, v in record.items()})
        criterion = selection_criterion(config.task, metrics)
        if criterion < progress.best:
            progress.best = criterion
            _save_checkpoints(folder.out, preset, model.networks,
                              {**metadata_base, "epoch": epoch + 1, "metrics": metrics})
        # Best checkpoints, then the state, then the log line: stopped between two of them, the run resumes at
        # this epoch and writes them again, and the log never shows an epoch the state does not hold.
        _save_state(folder, model, epoch + 1, progress, recorded_config)
        _append_log(folder.log_path, record)
        after_epoch(folder.out, info)  # curves.png from the whole log (a resumed run's earlier epochs too)
    return TrainResult(folder.out, _checkpoints(folder.out, model.networks), progress.history, progress.first_loss,
                       progress.last_loss, epochs_before=progress.start_epoch, epochs=config.epochs)


# ----------------------------------------------------------------------------- run: before the first epoch
def _check_choices(config: TrainConfig) -> None:
    """The task, the detector's input and the line count among the command's choices (argparse checks them on
    the command line; a library caller's config is checked here), and every flag given one the task uses."""
    if config.task not in TASKS:
        raise InputError(f"task: {config.task!r} is not one of {', '.join(TASKS)}")
    if config.task == "detector" and config.input_mode not in DETECTOR_INPUTS:
        raise InputError(f"--input: {config.input_mode!r} is not one of {', '.join(DETECTOR_INPUTS)}")
    if config.emulate_beams not in (0, *BEAM_COUNTS):  # argparse's choices, for library callers
        raise InputError(f"--emulate-beams: {config.emulate_beams} is not one of 0, "
                         f"{', '.join(map(str, BEAM_COUNTS))}")
    check_flags_apply(config)


def _settings(config: TrainConfig) -> tuple[TrainConfig, torch.device, Preset]:
    """The config checked and completed from the task's recipe, the process set up to train (allocator,
    threads), and the device, arithmetic and preset the run uses."""
    _check_choices(config)
    config = recipe(config)
    keep_freed_memory()  # a PIXOR epoch 16 % shorter: no mmap/munmap of the step's buffers (models/allocator.py)
    if config.threads:
        torch.set_num_threads(config.threads)
    device = resolve_device(config.device)
    config.precision = resolve_precision(config.precision, device)
    try:
        preset = get_preset(config.preset)
    except ValueError as exc:
        raise InputError(f"--preset: {exc}") from None
    return config, device, preset


def _open_run_folder(config: TrainConfig, preset: Preset, guard: contextlib.ExitStack) -> _RunFolder:
    """``--out`` checked, locked if it exists already, and the state of the run it holds read when resumed."""
    out = Path(config.out)
    check_out(out)
    locked = out.is_dir()
    if locked:  # before its state is read: another process may be writing it
        guard.enter_context(run_lock(out))
    return _RunFolder(out, _saved_state(config, out, preset), locked)


def _saved_state(config: TrainConfig, out: Path, preset: Preset) -> dict | None:
    """The state of the run in ``out`` that ``--resume`` continues, checked against this run's flags; None for
    a new run. Refused: a run's folder without --resume, the command's --resume without one, and checkpoints
    without a run's state."""
    state_path = out / STATE_FILE
    if config.resume and (state_path.exists() or config.strict_resume):
        if not state_path.is_file():
            raise InputError(f"{out}: nothing to resume (no {STATE_FILE}); leave out --resume to start a new run")
        state = load_state(state_path)
        check_resumable(config, state, out, preset)
        return state
    if state_path.exists():
        raise InputError(f"--out: {out} already holds a run ({STATE_FILE}); pass --resume to continue it")
    if not config.resume and (held := [f for f in CHECKPOINT_FILES.values() if (out / f).exists()]):
        # Checkpoints without a run's state (models.onnx_weights writes such folders): a new run would replace
        # one and leave the other beside it, for export --checkpoints to pair.
        first_epoch = " (a run stopped in its first epoch, by a version that kept no state before it: remove the " \
            "folder to start it again)" if (out / "log.jsonl").is_file() else ""
        raise InputError(f"--out: {out} already holds {' and '.join(held)} but no {STATE_FILE} (not a run to "
                         f"resume){first_epoch}; give a new folder")
    return None


def _check_joint_start(config: TrainConfig) -> None:
    """A joint run fine-tunes two trained networks: it needs both checkpoints."""
    if config.task == "joint" and (config.depth_checkpoint is None or config.pixor_checkpoint is None):
        raise InputError("joint: pass the trained --depth-checkpoint and --pixor-checkpoint to fine-tune")


def _checked_frames(config: TrainConfig, folder: _RunFolder, preset: Preset) -> _Frames:
    """The run's frames (:func:`split_ids`), checked to be those a resumed run started on, and to hold what the
    task reads: scans that can be thinned, cars, cached pseudo depth maps."""
    train_dir, train_ids, val_dir, val_ids = split_ids(config)
    if folder.state is not None:  # the same flags may name other frames now (a split file edited, frames added)
        check_same_frames(folder.state, folder.out, train_ids, val_ids)
    check_thinnable_scans(config, train_dir, train_ids, val_dir, val_ids)
    check_cars(config, train_dir, train_ids, val_dir, val_ids)
    check_pseudo_maps(config, train_ids, val_ids, preset)
    return _Frames(train_dir, train_ids, val_dir, val_ids)


def _checkpoints(out: Path, names: Iterable[str]) -> dict[str, Path]:
    """The best-weights checkpoints the run folder holds, by network name."""
    return {name: out / f"{name}.pt" for name in names if (out / f"{name}.pt").exists()}


def _nothing_left_to_train(config: TrainConfig, out: Path, state: dict) -> TrainResult:
    """A resumed run that has trained all its epochs: nothing trains, its log is rewritten from its state."""
    _write_log(out / "log.jsonl", list(state["history"]))  # its last line, if a kill came before it
    return TrainResult(out, _checkpoints(out, state["networks"]), list(state["history"]), epochs_before=state["epoch"],
                       epochs=config.epochs)


def _build_model(config: TrainConfig, preset: Preset, device: torch.device, resumed: bool) -> _Model:
    """The task's networks from the weights they start from (drawn from the seed when none are given), moved to
    ``device`` in the run's memory layout; Adam over the weights that train, and the task's rate schedule."""
    networks = start_networks(config, preset, resumed=resumed)
    trained = freeze_except(networks, config.train_only)
    layout = run_layout(networks)
    for net in networks.values():
        net.to(device=device, memory_format=layout)
    parameters = [p for net in networks.values() for p in net.parameters() if p.requires_grad]
    optimizer = torch.optim.Adam(parameters, lr=config.lr)
    scheduler: torch.optim.lr_scheduler.ReduceLROnPlateau | torch.optim.lr_scheduler.StepLR
    if config.task == "detector":
        scheduler = torch.optim.lr_scheduler.ReduceLROnPlateau(optimizer, factor=0.5, patience=1)
    else:
        scheduler = torch.optim.lr_scheduler.StepLR(optimizer, step_size=config.lr_step, gamma=config.lr_gamma)
    return _Model(networks, trained, layout, optimizer, scheduler)


def _restore_progress(folder: _RunFolder, model: _Model, preset_name: str) -> _Progress:
    """A new run's start, or a resumed run's: weights, optimizer, schedule and random generators restored from
    its state, with its epoch, best criterion and log records."""
    if folder.state is None:
        return _Progress()
    state = folder.state
    restore_state(state, folder.state_path, model.networks, model.optimizer, model.scheduler, preset_name)
    progress = _Progress(state["epoch"], state["best"], list(state["history"]))
    log.info("resuming %s at epoch %d", folder.out, progress.start_epoch + 1)
    return progress


def _make_run_folder(folder: _RunFolder, guard: contextlib.ExitStack) -> None:
    """``--out`` made if it is new, and then locked; refused if another process started a run in it meanwhile."""
    try:
        folder.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"--out: cannot create {folder.out} ({exc.strerror or exc})") from None
    if not folder.locked:  # a folder this run has just made
        guard.enter_context(run_lock(folder.out))
        if folder.state is None and folder.state_path.exists():  # another process made it too, and held it first
            raise InputError(f"--out: {folder.out} was started by another training process meanwhile "
                             f"({STATE_FILE}); give a new folder, or --resume it once that process has ended")


def _recorded_config(config: TrainConfig, preset: Preset, frames: _Frames, state: dict | None) -> dict:
    """The run's settings as its state records them, for ``--resume`` to compare: the flags, the frames'
    fingerprints and the preset's own settings."""
    recorded = {**_jsonable(asdict(config)), **frame_fingerprints(frames.train_ids, frames.val_ids),
                "preset_config": preset.to_dict()}  # what --preset gave, compared on --resume
    started = state.get("config") if state is not None and isinstance(state.get("config"), dict) else {}
    if "preset" in started:  # a resume's --preset may spell the same preset otherwise (a copy of the file):
        recorded["preset"] = started["preset"]  # the run's messages name the one it was started with
    return recorded


def _save_state(folder: _RunFolder, model: _Model, epoch: int, progress: _Progress, recorded_config: dict) -> None:
    """The run's state after ``epoch`` epochs (0: before the first), whole or not at all (:func:`save_state`)."""
    save_state(folder.state_path, model.networks, model.optimizer, model.scheduler, epoch, progress.best,
               progress.history, recorded_config)


def _build_data(config: TrainConfig, preset: Preset, frames: _Frames) -> _Data:
    """The lines the run's scans are thinned to (said once) and the depth or detector task's datasets."""
    beams = emulated_lines(config)
    if thins_scans(config):  # which scans the run learns from, said once at its start
        log.info("scans: %s (--emulate-beams %d)", f"thinned to {beams} lines" if beams else "as stored",
                 config.emulate_beams)
    data = _Data(frames, beams)
    if config.task == "depth":
        data.train_set = depth_dataset(frames.train_dir, frames.train_ids, preset, augment=not config.quick,
                                       seed=config.seed, car_weight=config.car_weight, beams=beams)
        data.val_set = depth_dataset(frames.val_dir, frames.val_ids, preset, beams=beams)
    elif config.task == "detector":
        data.train_set = DetectorDataset(frames.train_dir, frames.train_ids, preset, config.input_mode,
                                         config.pseudo_dir, beams, augment=not config.quick, seed=config.seed)
    return data


def _training_forward(config: TrainConfig, model: _Model, data: _Data,
                      device: torch.device) -> tuple[dict[str, Callable[..., Any]], bool]:
    """The training forward passes by network name (the depth net's, PIXOR's logits), and whether --compile
    compiles them (:func:`resolve_compile`)."""
    # The training forward passes, compiled or not; validation calls the networks themselves (eager).
    networks = model.networks
    forward = {"depth": networks["depth"].forward} if "depth" in networks else {}
    if "pixor" in networks:
        forward["pixor"] = networks["pixor"].forward_logits
    # The whole run's steps, not the ones left: a resumed run must compile (or not) as it started.
    steps = config.epochs * (len(data.train_set) // config.batch_size) if config.task != "joint" else 0
    compiled = resolve_compile(config.compile, config.task, steps, device)
    if compiled:
        if model.layout != torch.channels_last:
            # Inductor would move convolutions to channels-last on its own, into the oneDNN defect that
            # run_layout avoids (the tiny preset's compiled backward aborted here): keep the layout chosen.
            from torch._inductor import config as inductor_config

            inductor_config.layout_optimization = False
        forward = {name: torch.compile(fn) for name, fn in forward.items()}
        log.info("torch.compile: %s (the first step compiles, about a minute)", ", ".join(forward))
    return forward, compiled


# ----------------------------------------------------------------------------- run: one epoch
def _train_epoch(config: TrainConfig, preset: Preset, device: torch.device, model: _Model, data: _Data,
                 epoch: int) -> list[float]:
    """One epoch's training steps behind its progress bar: the loss of each batch. An epoch without a batch
    is refused."""
    _set_train_modes(config, model)
    if config.task == "joint":
        losses = _train_joint_epoch(config, preset, device, model, data, epoch)
    else:
        losses = _train_dataset_epoch(config, device, model, data.train_set, epoch)
    if not losses:
        raise InputError(f"--data: no training batch (frames {len(data.frames.train_ids)}, batch size "
                         f"{config.batch_size})")
    return losses


def _set_train_modes(config: TrainConfig, model: _Model) -> None:
    """Training mode for what trains (the whole networks, or --train-only's submodules), batch norms frozen
    with --freeze-bn."""
    for net in model.networks.values():
        net.train(not model.trained)
    for module in model.trained:  # with --train-only, only these leave eval mode (frozen batch norms stay put)
        module.train()
    if config.freeze_bn:
        freeze_batch_norms(model.networks)


def _train_joint_epoch(config: TrainConfig, preset: Preset, device: torch.device, model: _Model, data: _Data,
                       epoch: int) -> list[float]:
    """A joint epoch: the frames in an order drawn from (seed, epoch), a :func:`joint_step` each, one optimizer
    step per batch of them; each batch's mean frame loss."""
    frames = data.frames
    order = np.random.default_rng((config.seed, epoch)).permutation(len(frames.train_ids))
    batches = [order[i : i + config.batch_size] for i in range(0, len(order), config.batch_size)]
    bar = tqdm(batches, desc=f"joint epoch {epoch + 1}/{config.epochs}", disable=not config.progress)
    losses = []
    for batch in bar:
        model.optimizer.zero_grad()
        total = 0.0
        for index in batch:
            loss = joint_step(model.networks, preset, frames.train_dir, frames.train_ids[index], config.precision,
                              device, model.layout, config.depth_loss, data.beams)
            (loss / len(batch)).backward()
            total += loss.item() / len(batch)
        model.optimizer.step()
        losses.append(total)
        bar.set_postfix(loss=f"{total:.4f}")
    return losses


def _train_dataset_epoch(config: TrainConfig, device: torch.device, model: _Model,
                         train_set: DepthDataset | DepthCompletionDataset | DetectorDataset,
                         epoch: int) -> list[float]:
    """A depth or detector epoch: the dataset's batches (order and augmentation from the seed and the epoch),
    one optimizer step each; each batch's loss."""
    train_set.epoch = epoch
    batches = loader(train_set, config.batch_size, True, config.seed * 1000 + epoch, config.workers,
                     train_set.inputs, model.layout)
    bar = tqdm(batches, desc=f"{config.task} epoch {epoch + 1}/{config.epochs}", disable=not config.progress)
    losses = []
    for batch in bar:
        model.optimizer.zero_grad()
        loss = _batch_loss(config, device, model, [t.to(device, non_blocking=True) for t in batch])
        loss.backward()
        model.optimizer.step()
        losses.append(loss.item())
        bar.set_postfix(loss=f"{loss.item():.4f}")
    return losses


def _batch_loss(config: TrainConfig, device: torch.device, model: _Model, batch: list[torch.Tensor]) -> torch.Tensor:
    """A depth or detector batch's training loss: the forward pass in the run's arithmetic, the loss in fp32."""
    layout = model.layout
    if config.task == "depth":
        rgb, sparse, target, *weight = batch  # weight: with --car-weight
        with autocast(config.precision, device):
            prediction = model.forward["depth"](rgb.contiguous(memory_format=layout),
                                                sparse.contiguous(memory_format=layout))
        return DEPTH_LOSSES[config.depth_loss](prediction.float(), target, *weight)
    bev, score_t, reg_t = batch
    with autocast(config.precision, device):
        logits, regression = model.forward["pixor"](bev.contiguous(memory_format=layout))
    return pixor_loss(logits.float(), regression.float(), score_t, reg_t).total


def _validate(config: TrainConfig, preset: Preset, device: torch.device, model: _Model, data: _Data) -> dict:
    """The epoch's validation metrics: depth RMSE/MAE and loss; detector and joint: loss and KITTI BEV AP."""
    if config.task == "depth":
        return validate_depth(model.networks["depth"], data.val_set, device, config.depth_loss)
    return validate_detector(model.networks["pixor"], preset, data.frames.val_dir, data.frames.val_ids,
                             config.input_mode, config.val_pseudo_dir or config.pseudo_dir,
                             model.networks.get("depth") if config.task == "joint" else None, device, data.beams)


def _step_schedule(task: str, model: _Model, metrics: dict) -> float:
    """The rate's schedule advanced after an epoch (the detector's on its validation loss); the rate the epoch
    trained at."""
    trained_at = model.optimizer.param_groups[0]["lr"]  # the log's rate: the one this epoch ran, not the next one's
    if task == "detector":
        model.scheduler.step(metrics["val_loss"])
    else:
        model.scheduler.step()
    return trained_at


def _epoch_record(epoch: int, losses: list[float], trained_at: float, metrics: dict, tic: float) -> dict:
    """The epoch's log line: its number, mean training loss, rate, seconds since ``tic`` and validation metrics
    (without the whole ``bev_ap`` table)."""
    return {"epoch": epoch + 1, "train_loss": float(np.mean(losses)), "lr": trained_at,
            "seconds": round(time.perf_counter() - tic, 1),
            **{k: v for k, v in metrics.items() if k != "bev_ap"}}


def _save_checkpoints(out: Path, preset: Preset, networks: dict[str, torch.nn.Module], metadata: dict) -> None:
    """Each network's weights as ``out/NAME.pt`` with ``metadata``, the format export --checkpoints reads."""
    for name, net in networks.items():
        save_checkpoint(out / f"{name}.pt", preset, {name: net}, metadata)  # save_checkpoint stores CPU tensors


def _checkpoint_metadata(config: TrainConfig, preset: Preset, networks: dict[str, torch.nn.Module],
                         train_dir: Path, train_ids: list[str], val_dir: Path, val_ids: list[str],
                         compiled: bool) -> dict:
    """What every checkpoint of the run records besides its epoch and metrics: the task, the data and the
    recipe, with the flags that changed it and the weights the run started from (and how those were trained)."""
    metadata = {"task": config.task, "preset": preset.name, "code": code_version(), "data": str(train_dir),
                "train_frames": len(train_ids),
                "val_data": str(val_dir), "val_frames": len(val_ids),
                # A joint run's PIXOR reads the depth net's pseudo points with the scan, whatever --input says.
                "input": "pseudo" if config.task == "joint" else config.input_mode,
                "recipe": {"epochs": config.epochs, "batch_size": config.batch_size, "lr": config.lr,
                           "optimizer": "Adam", "seed": config.seed, "precision": config.precision,
                           "compiled": compiled}}
    if thins_scans(config):  # the lines its scans were thinned to (0: as stored); a lidar64 run reads them as stored
        metadata["emulate_beams"] = config.emulate_beams
    if config.task in ("depth", "joint"):
        metadata["recipe"]["depth_loss"] = config.depth_loss
        metadata["recipe"]["lr_decay"] = {"every_epochs": config.lr_step, "factor": config.lr_gamma}
    if config.resnet18 is not None:
        metadata["recipe"]["encoder_start"] = str(config.resnet18)
    if config.train_only:
        metadata["recipe"]["train_only"] = list(config.train_only)
    if config.car_weight != 1.0:
        metadata["recipe"]["car_weight"] = config.car_weight
    if config.freeze_bn:
        metadata["recipe"]["freeze_bn"] = True
    for name, path in (("depth", config.depth_checkpoint), ("pixor", config.pixor_checkpoint)):
        if name in networks and path is not None:
            metadata["recipe"][f"{name}_start"] = str(path)
            earlier = start_training_metadata(Path(path), name)
            if earlier:
                metadata["recipe"][f"{name}_start_training"] = earlier
    return metadata


def selection_criterion(task: str, metrics: dict) -> float:
    """Lower is better. Depth: the validation loss (MSE or L1, as trained). Detector and joint: minus the mean of BEV AP at IoU 0.7 and
    0.5 (moderate) — the validation loss can fall while AP does not (seen here: PIXOR on 16-line input had
    a lower loss after its first epoch but 24 points less AP at IoU 0.7), and AP is what the table reports."""
    if task == "depth":
        return float(metrics["val_loss"])
    return -0.5 * (metrics["bev_ap_0.7_moderate"] + metrics["bev_ap_0.5_moderate"])


def joint_step(networks: dict, preset: Preset, data_dir: Path, frame_id: str, precision: str = "fp32",
               device: torch.device = CPU, layout: torch.memory_format = torch.contiguous_format,
               depth_loss: str = "mse", beams: int | None = 16) -> torch.Tensor:
    """Loss of one frame through depth net → soft BEV → PIXOR (+ the depth loss); its scan thinned to ``beams``
    lines (None or 0: as stored)."""
    frame = load_frame(data_dir, frame_id)
    lidar16 = frame_points(frame, beams)
    inputs = depth_inputs(frame.image, lidar16, frame.calib, preset)
    with autocast(precision, device):
        depth = networks["depth"](torch.from_numpy(inputs.rgb).to(device).contiguous(memory_format=layout),
                                  torch.from_numpy(inputs.sparse_depth).to(device).contiguous(memory_format=layout))
    depth = depth[0].float()
    h, w = preset.depth.input_hw
    rays, origin = pixel_rays(inputs.calib, h, w, preset.decode.pseudo_stride)
    bev = joint_bev(depth, torch.from_numpy(rays).to(device), torch.from_numpy(origin.astype(np.float32)).to(device),
                    lidar16, preset)
    targets = encode_targets(car_boxes(frame), preset.bev, preset.pixor.output_stride, preset.decode)
    with autocast(precision, device):
        logits, regression = networks["pixor"].forward_logits(bev[None].contiguous(memory_format=layout))
    detection = pixor_loss(logits.float(), regression.float(), torch.from_numpy(targets.score)[None, None].to(device),
                           torch.from_numpy(targets.regression)[None].to(device)).total
    target = torch.from_numpy(depth_target(data_dir, frame, preset))[None, None].to(device)
    return detection + 0.1 * DEPTH_LOSSES[depth_loss](depth[None], target)


def _jsonable(value):
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, Path):
        return str(value)
    return value


def _parser() -> argparse.ArgumentParser:
    """The command line; ``--help`` ends with the module docstring's details and an example."""
    epilog = __doc__.split("\n\n", 1)[1] + "\n" + examples(
        "python -m models.train depth --data data/sim/train --val-data data/sim/val --preset edge --out runs/depth")
    parser = argparse.ArgumentParser(allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
                                     prog="python -m models.train", description=__doc__.split("\n\n")[0],
                                     epilog=epilog, formatter_class=HelpFormatter)
    parser.add_argument("task", choices=TASKS, help="what to train: depth, detector or joint (below)")
    parser.add_argument("--data", type=Path, required=True, metavar="DIR",
                        help="KITTI object training folder; depth: or a depth-completion drive (flat layout)")
    parser.add_argument("--val-data", type=Path, metavar="DIR",
                        help="validation folder of either kind (default: --data + --val-split)")
    parser.add_argument("--train-split", type=Path, metavar="F",
                        help="training frame ids, one per line (default: all of --data)")
    parser.add_argument("--val-split", type=Path, metavar="F", help="validation frame ids, one per line")
    parser.add_argument("--preset", default="edge", metavar="P",
                        help="model preset (default edge): a registered name, with suffixes such as -split-near35 (the "
                        "shipped camera model), or a preset file FILE.json (docs/models.md, \"Adding a preset\")")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR",
                        help="run directory (log.jsonl, state.pt, depth.pt/pixor.pt)")
    parser.add_argument("--input", dest="input_mode", default="lidar16", choices=DETECTOR_INPUTS,
                        help="detector input (default lidar16)")
    parser.add_argument("--emulate-beams", type=int, default=16, choices=(0, *BEAM_COUNTS), metavar="N",
                        help=f"thin the stored scans to N lines ({', '.join(map(str, BEAM_COUNTS))}; default 16) for "
                        "the depth net and PIXOR's lidar16 and pseudo inputs; 0: train on them as stored (a 16-line "
                        "sensor's own scans need it)")
    parser.add_argument("--pseudo-dir", type=Path, metavar="DIR", help="cached dense depth PNGs for --input pseudo (training frames)")
    parser.add_argument("--val-pseudo-dir", type=Path, metavar="DIR", help="… of the validation frames (default: --pseudo-dir)")
    parser.add_argument("--depth-checkpoint", type=Path, metavar="FILE",
                        help="trained depth.pt (joint); depth: weights to start from (depth.pt or depth.onnx)")
    parser.add_argument("--pixor-checkpoint", type=Path, metavar="FILE",
                        help="trained pixor.pt (joint); detector: weights to start from (pixor.pt or pixor.onnx)")
    parser.add_argument("--train-only", type=lambda text: tuple(n for n in text.split(",") if n), default=(),
                        metavar="MODULES", help="train only these submodules (comma-separated, say refine); "
                                                "the rest stays frozen as loaded")
    parser.add_argument("--freeze-bn", action="store_true",
                        help="batch-norm statistics stay as loaded (use with weights from an exported .onnx)")
    parser.add_argument("--epochs", type=positive_int, metavar="N", help="default: the task's recipe")
    parser.add_argument("--batch-size", type=positive_int, metavar="N", help="default: the task's recipe")
    parser.add_argument("--lr", type=positive_float, help="default: the task's recipe")
    parser.add_argument("--lr-step", type=positive_int, default=TrainConfig.lr_step, metavar="N",
                        help=f"depth and joint: decay the rate every N epochs (default {TrainConfig.lr_step}, the paper's)")
    parser.add_argument("--lr-gamma", type=positive_float, default=TrainConfig.lr_gamma, metavar="F",
                        help=f"depth and joint: the rate's factor at each decay (default {TrainConfig.lr_gamma}; the "
                             "paper gives none, Ma et al.'s code uses 0.1)")
    parser.add_argument("--resnet18", type=Path, metavar="FILE",
                        help="depth: start the encoder from ImageNet ResNet-18 weights in torchvision's format "
                             "(resnet18-f37072fd.pth; the paper preset's widths only), as Ma et al. do")
    parser.add_argument("--depth-loss", default="mse", choices=tuple(DEPTH_LOSSES),
                        help="depth and joint: per-pixel loss on the depth map (default mse, the paper's)")
    parser.add_argument("--car-weight", type=positive_float, default=1.0,
                        help="depth: loss weight of the labelled cars' own pixels (default 1: every pixel alike)")
    parser.add_argument("--max-train-frames", type=positive_int, metavar="N", help="use only the first N training frames")
    parser.add_argument("--max-val-frames", type=positive_int, metavar="N", help="use only the first N validation frames")
    parser.add_argument("--workers", type=non_negative_int, default=0, metavar="N", help="depth and detector: data-loading processes (default 0)")
    parser.add_argument("--threads", type=positive_int, metavar="N", help="torch intra-op threads")
    parser.add_argument("--seed", type=non_negative_int, default=0,
                        help="seed of the initial weights, the augmentation and the data order (default 0)")
    parser.add_argument("--device", default="auto",
                        help="auto (default: the first CUDA GPU torch sees, else the CPU), cpu, cuda or cuda:N")
    parser.add_argument("--precision", default="auto", choices=("auto", "bf16", "fp32"),
                        help="training arithmetic: bf16 autocast where the CPU has AVX-512 BF16 (auto, default)")
    parser.add_argument("--compile", default="auto", choices=("auto", "on", "off"),
                        help=f"torch.compile the training forward pass (auto, default: depth and detector runs of "
                             f"at least {COMPILE_MIN_STEPS} steps, where a C++ compiler is found)")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in --out from its last epoch (its state.pt; the same flags, only "
                             "--epochs may change; another --precision, --device, --threads or --compile is "
                             "allowed with a warning)")
    parser.add_argument("--quick", action="store_true", help="a few frames and epochs: a smoke test")
    add_no_progress(parser, "no progress bars (drawn into a log too: a run of hours in the background, "
                    "nohup … > log, shows its epoch's progress there)")
    return parser


def main(argv: list[str] | None = None) -> int:
    """``python -m models.train``: 0 when the run has trained (or had nothing left to train), 2 on a refused
    input or a failed write; stopped (Ctrl-C, SIGTERM), it says which epoch the run keeps."""
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    options = vars(args)
    # Unlike the frame-by-frame commands (show_progress: on a terminal only), a training run draws its bars into
    # a log too: it runs for hours in the background, with one line an epoch, and writes nothing between bars.
    progress = not options.pop("no_progress")
    config = TrainConfig(**options, progress=progress, strict_resume=args.resume)
    try:
        with sigterm_as_interrupt():  # a cluster's pre-emption (SIGTERM) stops the run as Ctrl-C does
            result = run(config)
    except (InputError, FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a full disk, a folder made read-only or removed while the run writes
        print(f"error: {exc.filename or args.out}: cannot write it ({exc.strerror or exc}); "
              f"{stopped_at(args.out)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        return stopped(exc, stopped_at(args.out))
    if result.nothing_to_do:
        print(already_trained(result))
        return 0
    print(f"run {result.run_dir}: loss {result.first_loss:.4f} → {result.last_loss:.4f}; "
          f"checkpoints {', '.join(str(p) for p in result.checkpoints.values())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
