"""Training: ``python -m models.train depth|detector|joint --data DIR --preset P --out RUN_DIR [--resume] …``

* depth — the paper's recipe by default: batch 4, Adam lr 1e-4 halved every 5
  epochs, 10 epochs, MSE on pixels with ground truth; input = 16-line sparse
  depth + image.
* detector — PIXOR from scratch: Adam, batch 8, lr 1e-3 halved when the
  validation loss stops falling; ``--input lidar64|lidar16|pseudo``.
* joint — both networks fine-tuned together through a differentiable BEV
  occupancy (models/soft_bev.py); starts from the two trained checkpoints.

``--depth-checkpoint`` / ``--pixor-checkpoint`` also start a depth or detector
run from trained weights: a checkpoint, or the ``depth.onnx`` / ``pixor.onnx``
of an exported model directory (its batch norms come folded into the
convolutions, so train such weights with ``--train-only`` or ``--freeze-bn``). ``--train-only
refine`` trains only that submodule (here the depth net's full-resolution head,
which an older export lacks and which then starts from its initialisation);
every other weight and batch-norm statistic stays as loaded.

Each epoch: a progress bar, validation metrics (depth RMSE/MAE; detector loss
and KITTI BEV AP), one JSON line in ``RUN_DIR/log.jsonl``, the full training
state in ``RUN_DIR/state.pt`` (exact resume with ``--resume``: weights,
optimizer, schedule, RNG, the epoch's data order comes from the seed and the
epoch number) and the best weights as ``RUN_DIR/depth.pt`` / ``pixor.pt`` in
the checkpoint format ``python -m export --checkpoints RUN_DIR`` reads.

Arithmetic: bf16 autocast with channels-last tensors where the CPU supports it
(``--precision auto``, the default; ``fp32`` to turn it off). Weights, optimizer
state and losses stay fp32, so checkpoints and exported models are the same
either way.

Compilation: the training forward pass of the depth and detector tasks runs
through ``torch.compile`` (``--compile auto``, the default, when the run has
at least :data:`COMPILE_MIN_STEPS` steps and, on the CPU, a C++ compiler is on
the PATH; ``on``, ``off``). Compiling takes about a minute per network and
process; Inductor fuses batch norm's backward pass with its neighbours, which
eager PyTorch runs as separate memory-bound passes (44 % of an eager edge PIXOR
step here). Validation and the joint task stay eager. Compiled and eager steps
compute the same function; their floating-point results differ in the last
bits (fused reductions), so losses agree to a few decimals, not to the digit.
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import random
import shutil
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader
from tqdm import tqdm

from evaluation.depth_metrics import car_box_shares, car_shares_by_band, moderate_cars_in_view
from evaluation.kitti_eval import evaluate
from evaluation.labels import LabelArrays
from models import build_depth_net, build_pixor
from models.allocator import keep_freed_memory
from models.checkpoint import CHECKPOINT_FILES, load_checkpoint, load_network_weights, save_checkpoint
from models.data import (
    DETECTOR_INPUTS,
    DepthDataset,
    DetectorDataset,
    cached_pseudo_depth,
    car_boxes,
    detector_points,
    frame_points,
)
from models.losses import DEPTH_LOSSES, pixor_loss
from models.soft_bev import soft_occupancy
from pipeline.bev import BevVoxelizer, pseudo_bins, voxelize_bev
from pipeline.boxes import boxes_to_objects, in_camera_view
from pipeline.calib import Calibration
from pipeline.cli import non_negative_int, positive_float, positive_int
from pipeline.errors import InputError
from pipeline.frame import frame_ids, load_frame
from pipeline.kitti import read_calib, read_image_size, read_labels
from pipeline.model_files import ModelFileError, load_manifest
from pipeline.postprocess import boxes_from_maps
from pipeline.preprocess import depth_inputs, view_calibration
from pipeline.presets import Preset, get_preset, lidar_only, preset_from_dict
from pipeline.pseudo import pixel_rays
from pipeline.targets import encode_targets

log = logging.getLogger(__name__)
TASKS = ("depth", "detector", "joint")
CPU = torch.device("cpu")
COMPILE_MIN_STEPS = 200  # below this, compiling (about a minute per network) costs more than it saves
COMPILED_TASKS = ("depth", "detector")  # joint's per-frame soft BEV has no fixed shapes to compile for


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
    pseudo_dir: Path | None = None  # detector --input pseudo: cached dense depth PNGs of the training frames
    val_pseudo_dir: Path | None = None  # … of the validation frames (default: pseudo_dir, one folder for both)
    depth_checkpoint: Path | None = None  # joint (and pseudo caching): trained depth.pt; depth: weights to start from
    pixor_checkpoint: Path | None = None  # joint: trained pixor.pt; detector: weights to start from
    train_only: tuple[str, ...] = ()  # submodules to train (say "refine"); the rest frozen, batch norms included
    freeze_bn: bool = False  # batch-norm statistics stay as loaded (their scale and shift still train)
    epochs: int | None = None
    batch_size: int | None = None
    lr: float | None = None
    lr_step: int = 5  # depth: halve every lr_step epochs
    depth_loss: str = "mse"  # depth and joint: mse (the paper) | l1 (models/reproduce.py says why)
    car_weight: float = 1.0  # depth: the loss weight of the labelled cars' own pixels (models.data.car_pixels)
    lr_gamma: float = 0.5
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


RECIPES = {  # the paper's settings per task: (epochs, batch size, learning rate)
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


def resolve_device(device: str) -> torch.device:
    """``auto`` → the first CUDA GPU when this torch build sees one, else the CPU."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        resolved = torch.device(device)
    except RuntimeError:
        raise InputError(f"--device: {device!r} is not a torch device (auto, cpu, cuda, cuda:N)") from None
    if resolved.type == "cuda" and not torch.cuda.is_available():
        raise InputError(f"--device: {device} asked for, but this torch build sees no CUDA GPU "
                         f"(torch {torch.__version__}; install a CUDA build of torch)")
    if resolved.type not in ("cpu", "cuda"):
        raise InputError(f"--device: {device!r}: only cpu and cuda are supported")
    return resolved


def resolve_precision(precision: str, device: torch.device | None = None) -> str:
    """``auto`` → bf16 where the hardware has native bf16 arithmetic (a CPU with AVX-512 BF16 or AMX, a GPU
    that supports it), else fp32.

    Measured here (2-core AMD EPYC with AVX-512 BF16), one training step: bf16 autocast with channels-last
    tensors took PIXOR (edge, batch 8) from 1.42 s to 0.41 s and the depth net (edge, batch 4) from 0.33 s
    to 0.17 s; weights, optimizer state and losses stay fp32.
    """
    if precision not in ("auto", "bf16", "fp32"):
        raise InputError(f"--precision: {precision!r} is not one of auto, bf16, fp32")
    if precision == "auto":
        if device is not None and device.type == "cuda":
            supported = torch.cuda.is_bf16_supported()
        else:
            supported = torch.backends.mkldnn.is_available() and torch.cpu._is_avx512_bf16_supported()
        return "bf16" if supported else "fp32"
    return precision


def resolve_compile(mode: str, task: str, steps: int, device: torch.device = CPU) -> bool:
    """Whether to ``torch.compile`` the training forward pass (module docstring).

    ``auto`` → yes for the depth and detector tasks when the run has at least :data:`COMPILE_MIN_STEPS`
    steps and the device can compile: a CUDA GPU, or a CPU with a C++ compiler on the PATH (Inductor
    builds its CPU kernels with it). ``on`` insists (an InputError where it cannot), ``off`` never.
    """
    if mode not in ("auto", "on", "off"):
        raise InputError(f"--compile: {mode!r} is not one of auto, on, off")
    if mode == "off" or task not in COMPILED_TASKS:
        return False
    can = device.type == "cuda" or any(shutil.which(c) for c in ("c++", "g++", "clang++"))
    if mode == "on" and not can:
        raise InputError("--compile on: torch.compile on the CPU needs a C++ compiler (c++, g++ or clang++) on "
                         "the PATH; install one or pass --compile off")
    return can and (mode == "on" or steps >= COMPILE_MIN_STEPS)


def channels_last_safe(networks: dict[str, torch.nn.Module]) -> bool:
    """False when a network has a convolution oneDNN's channels-last path mishandles.

    Found here (torch 2.13.0, oneDNN 3.12): the backward pass of a 1×1 stride-2 convolution with 8 input
    channels in channels-last layout corrupts the heap ("double free or corruption"), in fp32 and bf16.
    Such thin strided shortcuts exist only in the ``tiny`` test preset (the 3×3 strided stems of ``edge``
    with 1 and 3 input channels were checked and are fine).
    """
    return not any(m.kernel_size == (1, 1) and m.stride != (1, 1) and m.in_channels < 16
                   for net in networks.values() for m in net.modules() if isinstance(m, torch.nn.Conv2d))


def autocast(precision: str, device: torch.device | None = None):
    """Mixed-precision context for the forward pass (a no-op in fp32)."""
    device_type = "cpu" if device is None else device.type
    return torch.autocast(device_type, dtype=torch.bfloat16, enabled=precision == "bf16")


def run_layout(networks: dict[str, torch.nn.Module]) -> torch.memory_format:
    """NHWC (oneDNN's fast path for convolutions on the CPU) unless a network trips the defect above."""
    return torch.channels_last if channels_last_safe(networks) else torch.contiguous_format


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % (2**32))
    torch.manual_seed(seed)


# ----------------------------------------------------------------------------- data
def split_ids(config: TrainConfig) -> tuple[Path, list[str], Path, list[str]]:
    """(train dir, train ids, val dir, val ids) from folders and optional split files.

    Every frame listed (before ``--max-train-frames`` / ``--max-val-frames`` take the first N) is checked
    to be there (:func:`check_frames`), so a bad split fails now, not an epoch in.
    """
    for flag, folder, split in (("--data", config.data, config.train_split),
                                ("--val-data", config.val_data, config.val_split)):
        if folder is None:
            continue
        if not Path(folder).is_dir():
            raise InputError(f"{flag} {folder}: no such folder")
        if split is None and not (Path(folder) / "velodyne").is_dir():
            raise InputError(f"{flag} {folder}: not a KITTI object folder (no velodyne/ inside)")
    train_ids = frame_ids(config.data, config.train_split)
    val_dir = config.val_data or config.data
    if config.val_data is None and config.val_split is None:
        log.warning("no --val-data or --val-split: validating on the training frames")
    val_ids = frame_ids(val_dir, config.val_split)
    check_frames(config, Path(config.data), train_ids, Path(val_dir), val_ids)
    if config.max_train_frames:
        train_ids = train_ids[: config.max_train_frames]
    if config.max_val_frames:
        val_ids = val_ids[: config.max_val_frames]
    if not train_ids or not val_ids:
        raise InputError(f"--data: no frames to train on in {config.data} or to validate on in {val_dir}")
    return Path(config.data), train_ids, Path(val_dir), val_ids


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


# ----------------------------------------------------------------------------- validation
@torch.no_grad()
def validate_depth(net, dataset: DepthDataset, device: torch.device = CPU, loss: str = "mse") -> dict:
    """RMSE and MAE (mm) of the validation frames; val_loss is the training loss (MSE in m², or L1 in m).

    On labelled object frames also ``car_in_box_<band>``: per distance band, the mean over the moderate
    cars of the share of their pixels whose point lands in their BEV box, and ``car_stray_<band>``: the
    share of the other pixels of their 2D boxes that land there too (benchmarks/accuracy.py --depth's two
    figures: the depth sources that lift the camera row put 0.87–0.96 of the far cars' pixels on them and
    at most 0.02 of the rest; docs/measurements.md, sessions 23 and 24).
    """
    net.eval()
    sq, ab, n = 0.0, 0.0, 0
    per_frame_rmse = []
    shares: list[tuple[float, float]] = []
    strays: list[tuple[float, float]] = []
    labelled = isinstance(dataset, DepthDataset) and (Path(dataset.data_dir) / "label_2").is_dir()
    index = 0
    for rgb, sparse, target, *_ in DataLoader(dataset, batch_size=2):
        prediction = net(rgb.to(device), sparse.to(device)).cpu()
        valid = target > 0
        err = (prediction - target)[valid] * 1000.0
        sq += float((err**2).sum())
        ab += float(err.abs().sum())
        n += int(valid.sum())
        for i in range(rgb.shape[0]):
            v = valid[i]
            if v.any():
                per_frame_rmse.append(float(torch.sqrt((((prediction[i] - target[i])[v] * 1000) ** 2).mean())))
            if labelled:
                on_car, stray = _car_shares(dataset, index, prediction[i, 0].numpy(), target[i, 0].numpy())
                shares += on_car
                strays += stray
            index += 1
    val_loss = sq / max(n, 1) / 1e6 if loss == "mse" else ab / max(n, 1) / 1e3
    metrics = {"val_loss": val_loss, "rmse_mm": float(np.mean(per_frame_rmse)) if per_frame_rmse else float("nan"),
               "mae_mm": ab / max(n, 1), "pixels": n}
    for name, per_car in (("car_in_box", shares), ("car_stray", strays)):
        metrics.update({f"{name}_{band}": c["mean_share"] for band, c in car_shares_by_band(per_car).items()
                        if c["cars"]})  # no NaN in log.jsonl
    return metrics


def _car_shares(dataset: DepthDataset, index: int, prediction: np.ndarray, target: np.ndarray
                ) -> tuple[list[tuple[float, float]], list[tuple[float, float]]]:
    """(car depth, share of its pixels landing in its BEV box) and (car depth, share of the other pixels of
    its 2D box landing there) of one validation frame's moderate cars.

    Reads only the frame's labels, calibration and image size, not its scan: this runs every epoch."""
    data, frame_id, preset = Path(dataset.data_dir), dataset.frame_ids[index], dataset.preset
    label_path = data / "label_2" / f"{frame_id}.txt"
    if not label_path.exists():
        return [], []
    image_hw = read_image_size(data / "image_2" / f"{frame_id}.png")
    cars = moderate_cars_in_view(read_labels(label_path), image_hw, preset.crop_hw, preset.depth.input_scale)
    calib = view_calibration(image_hw, read_calib(data / "calib" / f"{frame_id}.txt"), preset)
    return car_box_shares(prediction, target, cars, calib)


@torch.no_grad()
def validate_detector(pixor, preset: Preset, data_dir: Path, ids: list[str], input_mode: str,
                      pseudo_dir: Path | None, depth_net=None, device: torch.device = CPU) -> dict:
    """Validation loss and KITTI BEV AP (moderate, R40) of PIXOR on the validation frames.

    The camera rows go through the Detector's own path (pseudo bins, then the voxelizer, whose height
    occupancy leaves out the pseudo points on depth edges), so the AP that picks a run's best epoch is
    the one ``benchmarks/accuracy.py`` measures, up to where the dense depth comes from (the PyTorch
    net in joint runs, the cached ONNX Runtime maps otherwise).
    """
    pixor.eval()
    if depth_net is not None:
        depth_net.eval()
    voxelizer = BevVoxelizer(preset.bev)
    gts, dets, losses = [], [], []
    for fid in ids:
        frame = load_frame(data_dir, fid, with_image=depth_net is not None)  # only joint runs the camera net
        if depth_net is not None or input_mode == "pseudo":
            depth, view_calib = (joint_depth(depth_net, frame, preset, device) if depth_net is not None
                                 else cached_pseudo_depth(pseudo_dir, frame, preset))
            pseudo = pseudo_bins(depth, view_calib, preset.bev, *preset.pseudo_limits,
                                 max_jump=preset.decode.height_max_jump)
            bev = voxelizer(frame_points(frame, 16), pseudo)
        else:
            pseudo = None
            bev = voxelizer(detector_points(data_dir, frame, preset, input_mode, pseudo_dir))
        targets = encode_targets(car_boxes(frame), preset.bev, preset.pixor.output_stride, preset.decode)
        logits, regression = (t.cpu() for t in pixor.forward_logits(torch.from_numpy(bev)[None].to(device)))
        losses.append(float(pixor_loss(logits, regression, torch.from_numpy(targets.score)[None, None],
                                       torch.from_numpy(targets.regression)[None]).total))
        score = torch.sigmoid(logits)[0, 0].numpy()
        boxes, scores = boxes_from_maps(score, regression[0].numpy(), voxelizer.height_occupancy, preset,
                                        score_threshold=0.05, with_pseudo=pseudo is not None,
                                        mark=voxelizer.height_mark)
        seen = in_camera_view(boxes, frame.calib, frame.image_hw)
        objects = boxes_to_objects(boxes[seen], frame.calib, frame.image_hw, scores[seen])
        gts.append(LabelArrays.from_objects(frame.labels or []))
        dets.append(LabelArrays.from_objects(objects))
    result = evaluate(gts, dets, metrics=("bev",))
    table = result.ap_table()
    return {"val_loss": float(np.mean(losses)),
            "bev_ap_0.7_moderate": table["bev"]["0.7"]["R40"][1], "bev_ap_0.5_moderate": table["bev"]["0.5"]["R40"][1],
            "bev_ap": table["bev"]}


# ----------------------------------------------------------------------------- joint
def joint_depth(depth_net, frame, preset: Preset, device: torch.device = CPU) -> tuple[np.ndarray, Calibration]:
    """The (torch) depth net's dense depth of a frame's 16-line scan, and its view's calibration (validation)."""
    inputs = depth_inputs(frame.image, frame_points(frame, 16), frame.calib, preset)
    depth = depth_net(torch.from_numpy(inputs.rgb).to(device), torch.from_numpy(inputs.sparse_depth).to(device))
    return depth[0, 0].cpu().numpy(), inputs.calib


def joint_bev(depth: torch.Tensor, rays: torch.Tensor, origin: torch.Tensor, lidar16: np.ndarray,
              preset: Preset) -> torch.Tensor:
    """Differentiable BEV of one frame: soft occupancy of pseudo + real points, hard reflectance channel."""
    d = preset.decode
    stride = d.pseudo_stride
    sub = depth[0, ::stride, ::stride]
    points = sub[None] * rays + origin[:, None, None]  # (3, h, w)
    valid = (sub >= preset.depth.min_depth) & (sub <= preset.depth.max_depth) & (points[2] <= d.pseudo_max_height)
    pseudo = points.permute(1, 2, 0)[valid]
    if preset.bev.split_pseudo:  # the scan's own channels are hard; only the pseudo channels have a gradient
        lidar = voxelize_bev(lidar16.astype(np.float32, copy=False), lidar_only(preset).bev)
        return torch.cat([torch.from_numpy(lidar).to(depth.device), soft_occupancy(pseudo, preset.bev)])
    real = torch.from_numpy(lidar16[:, :3]).to(depth.device)
    occupancy = soft_occupancy(torch.cat([pseudo, real]), preset.bev)
    merged = np.concatenate([np.column_stack([pseudo.detach().cpu().numpy(), np.zeros(len(pseudo), np.float32)]),
                             lidar16])
    reflectance = torch.from_numpy(voxelize_bev(merged.astype(np.float32), preset.bev)[-1:]).to(depth.device)
    return torch.cat([occupancy, reflectance])


# ----------------------------------------------------------------------------- run
def run(config: TrainConfig) -> TrainResult:
    """Train one task; see the module docstring."""
    if config.task not in TASKS:
        raise InputError(f"task: {config.task!r} is not one of {', '.join(TASKS)}")
    if config.task == "detector" and config.input_mode not in DETECTOR_INPUTS:
        raise InputError(f"--input: {config.input_mode!r} is not one of {', '.join(DETECTOR_INPUTS)}")
    check_flags_apply(config)
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
    # Every input is checked before anything is trained or written: --out is made only after the checks.
    out = Path(config.out)
    check_out(out)
    state_path = out / STATE_FILE
    state = None
    if config.resume and (state_path.exists() or config.strict_resume):
        if not state_path.is_file():
            raise InputError(f"{out}: nothing to resume (no {STATE_FILE}); leave out --resume to start a new run")
        state = load_state(state_path)
        check_resumable(config, state, out)
    elif state_path.exists():
        raise InputError(f"--out: {out} already holds a run ({STATE_FILE}); pass --resume to continue it")
    elif not config.resume and (held := [f for f in CHECKPOINT_FILES.values() if (out / f).exists()]):
        # Checkpoints without a run's state (models.onnx_weights writes such folders): a new run would replace
        # one and leave the other beside it, for export --checkpoints to pair.
        raise InputError(f"--out: {out} already holds {' and '.join(held)} but no {STATE_FILE} (not a run to "
                         "resume); give a new folder")
    if config.task == "joint" and (config.depth_checkpoint is None or config.pixor_checkpoint is None):
        raise InputError("joint: pass the trained --depth-checkpoint and --pixor-checkpoint to fine-tune")
    train_dir, train_ids, val_dir, val_ids = split_ids(config)
    check_pseudo_maps(config, train_ids, val_ids)
    if state is not None and state["epoch"] >= config.epochs:  # nothing to train: the run stays as it is
        checkpoints = {name: out / f"{name}.pt" for name in state["networks"] if (out / f"{name}.pt").exists()}
        return TrainResult(out, checkpoints, list(state["history"]), epochs_before=state["epoch"],
                           epochs=config.epochs)
    seed_everything(config.seed)

    networks: dict[str, torch.nn.Module] = {}
    if config.task in ("depth", "joint"):
        networks["depth"] = build_depth_net(preset)
    if config.task in ("detector", "joint"):
        networks["pixor"] = build_pixor(preset)
    for name, path in (("depth", config.depth_checkpoint), ("pixor", config.pixor_checkpoint)):
        if name in networks and path is not None:
            load_start_weights(networks[name], name, Path(path), preset, config.train_only)
    trained = freeze_except(networks, config.train_only)
    layout = run_layout(networks)
    for net in networks.values():
        net.to(device=device, memory_format=layout)
    parameters = [p for net in networks.values() for p in net.parameters() if p.requires_grad]
    optimizer = torch.optim.Adam(parameters, lr=config.lr)
    if config.task == "detector":
        scheduler = torch.optim.lr_scheduler.ReduceLROnPlateau(optimizer, factor=0.5, patience=1)
    else:
        scheduler = torch.optim.lr_scheduler.StepLR(optimizer, step_size=config.lr_step, gamma=config.lr_gamma)

    start_epoch, best, history = 0, float("inf"), []
    if state is not None:
        restore_state(state, state_path, networks, optimizer, scheduler, config.preset)
        start_epoch, best, history = state["epoch"], state["best"], list(state["history"])
        log.info("resuming %s at epoch %d", out, start_epoch + 1)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"--out: cannot create {out} ({exc.strerror or exc})") from None

    if config.task == "depth":
        train_set = DepthDataset(train_dir, train_ids, preset, augment=not config.quick, seed=config.seed,
                                 car_weight=config.car_weight)
        val_set = DepthDataset(val_dir, val_ids, preset)
    elif config.task == "detector":
        train_set = DetectorDataset(train_dir, train_ids, preset, config.input_mode, config.pseudo_dir,
                                    augment=not config.quick, seed=config.seed)
    # The training forward passes, compiled or not; validation calls the networks themselves (eager).
    forward = {"depth": networks["depth"].forward} if "depth" in networks else {}
    if "pixor" in networks:
        forward["pixor"] = networks["pixor"].forward_logits
    # The whole run's steps, not the ones left: a resumed run must compile (or not) as it started.
    steps = config.epochs * (len(train_set) // config.batch_size) if config.task != "joint" else 0
    compiled = resolve_compile(config.compile, config.task, steps, device)
    if compiled:
        if layout != torch.channels_last:
            # Inductor would move convolutions to channels-last on its own, into the oneDNN defect that
            # run_layout avoids (the tiny preset's compiled backward aborted here): keep the layout chosen.
            from torch._inductor import config as inductor_config

            inductor_config.layout_optimization = False
        forward = {name: torch.compile(fn) for name, fn in forward.items()}
        log.info("torch.compile: %s (the first step compiles, about a minute)", ", ".join(forward))
    first_loss = last_loss = float("nan")
    metadata_base = {"task": config.task, "preset": preset.name, "data": str(train_dir), "train_frames": len(train_ids),
                     "val_data": str(val_dir), "val_frames": len(val_ids), "input": config.input_mode,
                     "recipe": {"epochs": config.epochs, "batch_size": config.batch_size, "lr": config.lr,
                                "optimizer": "Adam", "seed": config.seed, "precision": config.precision,
                                "compiled": compiled}}
    if config.task in ("depth", "joint"):
        metadata_base["recipe"]["depth_loss"] = config.depth_loss
    if config.train_only:
        metadata_base["recipe"]["train_only"] = list(config.train_only)
    if config.car_weight != 1.0:
        metadata_base["recipe"]["car_weight"] = config.car_weight
    if config.freeze_bn:
        metadata_base["recipe"]["freeze_bn"] = True
    for name, path in (("depth", config.depth_checkpoint), ("pixor", config.pixor_checkpoint)):
        if name in networks and path is not None:
            metadata_base["recipe"][f"{name}_start"] = str(path)
            earlier = start_training_metadata(Path(path), name)
            if earlier:
                metadata_base["recipe"][f"{name}_start_training"] = earlier
    log_path = out / "log.jsonl"
    # One line per epoch the state holds: an interruption after an epoch's log line but before its state.pt
    # (or a stale log in a folder without one) would otherwise leave that epoch twice once it is trained again.
    log_path.write_text("".join(json.dumps(record) + "\n" for record in history), encoding="utf-8")
    for epoch in range(start_epoch, config.epochs):
        tic = time.perf_counter()
        for net in networks.values():
            net.train(not trained)
        for module in trained:  # with --train-only, only these leave eval mode (frozen batch norms stay put)
            module.train()
        if config.freeze_bn:
            freeze_batch_norms(networks)
        epoch_losses = []
        if config.task == "joint":
            order = np.random.default_rng((config.seed, epoch)).permutation(len(train_ids))
            batches = [order[i : i + config.batch_size] for i in range(0, len(order), config.batch_size)]
            bar = tqdm(batches, desc=f"joint epoch {epoch + 1}/{config.epochs}", disable=not config.progress)
            for batch in bar:
                optimizer.zero_grad()
                total = 0.0
                for index in batch:
                    loss = joint_step(networks, preset, train_dir, train_ids[index], config.precision, device, layout,
                                      config.depth_loss)
                    (loss / len(batch)).backward()
                    total += loss.item() / len(batch)
                optimizer.step()
                epoch_losses.append(total)
                bar.set_postfix(loss=f"{total:.4f}")
        else:
            train_set.epoch = epoch
            batches = loader(train_set, config.batch_size, True, config.seed * 1000 + epoch, config.workers,
                             train_set.inputs, layout)
            bar = tqdm(batches, desc=f"{config.task} epoch {epoch + 1}/{config.epochs}", disable=not config.progress)
            for batch in bar:
                optimizer.zero_grad()
                batch = [t.to(device, non_blocking=True) for t in batch]
                if config.task == "depth":
                    rgb, sparse, target, *weight = batch  # weight: with --car-weight
                    with autocast(config.precision, device):
                        prediction = forward["depth"](rgb.contiguous(memory_format=layout),
                                                      sparse.contiguous(memory_format=layout))
                    loss = DEPTH_LOSSES[config.depth_loss](prediction.float(), target, *weight)
                else:
                    bev, score_t, reg_t = batch
                    with autocast(config.precision, device):
                        logits, regression = forward["pixor"](bev.contiguous(memory_format=layout))
                    loss = pixor_loss(logits.float(), regression.float(), score_t, reg_t).total
                loss.backward()
                optimizer.step()
                epoch_losses.append(loss.item())
                bar.set_postfix(loss=f"{loss.item():.4f}")
        if not epoch_losses:
            raise InputError(f"--data: no training batch (frames {len(train_ids)}, batch size {config.batch_size})")
        if np.isnan(first_loss):
            first_loss = float(np.mean(epoch_losses))
        last_loss = float(np.mean(epoch_losses))

        if config.task == "depth":
            metrics = validate_depth(networks["depth"], val_set, device, config.depth_loss)
        else:
            metrics = validate_detector(networks["pixor"], preset, val_dir, val_ids, config.input_mode,
                                        config.val_pseudo_dir or config.pseudo_dir,
                                        networks.get("depth") if config.task == "joint" else None, device)
        if config.task == "detector":
            scheduler.step(metrics["val_loss"])
        else:
            scheduler.step()
        record = {"epoch": epoch + 1, "train_loss": float(np.mean(epoch_losses)), "lr": optimizer.param_groups[0]["lr"],
                  "seconds": round(time.perf_counter() - tic, 1),
                  **{k: v for k, v in metrics.items() if k != "bev_ap"}}
        history.append(record)
        with open(log_path, "a", encoding="utf-8") as handle:
            handle.write(json.dumps(record) + "\n")
        log.info("epoch %d: %s", epoch + 1,  # 4 significant digits: a learning rate of 5e-5 stays 5e-05
                 {k: float(f"{v:.4g}") if isinstance(v, float) else v for k, v in record.items()})
        criterion = selection_criterion(config.task, metrics)
        improved = criterion < best
        if improved:
            best = criterion
            for name, net in networks.items():
                save_checkpoint(out / f"{name}.pt", preset, {name: net},  # save_checkpoint stores CPU tensors
                                {**metadata_base, "epoch": epoch + 1, "metrics": metrics})
        torch.save({"networks": {n: net.state_dict() for n, net in networks.items()},
                    "optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(),
                    "epoch": epoch + 1, "best": best, "history": history, "config": _jsonable(asdict(config)),
                    "torch_rng": torch.get_rng_state(), "numpy_rng": np.random.get_state(),
                    "python_rng": random.getstate()}, state_path.with_suffix(".tmp"))
        state_path.with_suffix(".tmp").replace(state_path)
    checkpoints = {name: out / f"{name}.pt" for name in networks if (out / f"{name}.pt").exists()}
    return TrainResult(out, checkpoints, history, first_loss, last_loss, epochs_before=start_epoch,
                       epochs=config.epochs)


# ----------------------------------------------------------------------------- checks before a run
STATE_FILE = "state.pt"
STATE_KEYS = ("networks", "optimizer", "scheduler", "epoch", "best", "history", "torch_rng", "numpy_rng",
              "python_rng")
FRAME_FILES = ("velodyne/{}.bin", "image_2/{}.png", "calib/{}.txt")  # what load_frame reads of every frame


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
        ("--depth-loss", config.depth_loss != TrainConfig.depth_loss and config.task == "detector",
         "a detector run has no depth loss"),
        ("--car-weight", config.car_weight != TrainConfig.car_weight and config.task != "depth",
         "it weights the depth loss of a depth run"),
        ("--freeze-bn", config.freeze_bn and config.depth_checkpoint is None and config.pixor_checkpoint is None,
         "it keeps the batch norms of the weights a run starts from: give --depth-checkpoint or --pixor-checkpoint"),
    ]
    for flag, given, why in unused:
        if given:
            raise InputError(f"{flag}: not used by a {config.task} run ({why})")


def check_out(out: Path) -> None:
    """``--out`` is a folder, or a path where one can be made (no file in its place or above it)."""
    if out.exists() and not out.is_dir():
        raise InputError(f"--out: {out} is a file, not a run folder")
    existing = next((parent for parent in out.parents if parent.exists()), None)
    if existing is not None and not existing.is_dir():
        raise InputError(f"--out: cannot create {out}: {existing} is a file")


def load_state(state_path: Path) -> dict:
    """The training state a run folder holds (written at the end of each epoch); InputError if it is not one."""
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


def check_resumable(config: TrainConfig, state: dict, out: Path) -> None:
    """The resumed run is the one started in ``out``: the same task and flags; only --epochs may change.

    The state records the configuration it was started with; a state without one (an older run) is
    compared by the networks it holds.
    """
    recorded = state.get("config") if isinstance(state.get("config"), dict) else {}
    held = {("depth",): "depth", ("pixor",): "detector", ("depth", "pixor"): "joint"}
    task = recorded.get("task") or held.get(tuple(sorted(state["networks"])), config.task)
    if task != config.task:
        raise InputError(f"task {config.task}: {out} was started as a {task} run "
                         f"(resume it with python -m models.train {task} … --resume)")
    compared = [("--preset", "preset"), ("--train-only", "train_only")]
    if config.task == "detector":
        compared.insert(1, ("--input", "input_mode"))
    # Everything else that decides what the remaining epochs train on and how (--epochs may grow):
    # resumed with other values, the run would silently stop being the one its log and checkpoints describe
    # (the optimizer's saved learning rate would even override --lr, while the metadata recorded --lr).
    compared += [("--data", "data"), ("--val-data", "val_data"), ("--train-split", "train_split"),
                 ("--val-split", "val_split"), ("--max-train-frames", "max_train_frames"),
                 ("--max-val-frames", "max_val_frames"), ("--batch-size", "batch_size"), ("--lr", "lr"),
                 ("--seed", "seed"), ("--depth-loss", "depth_loss"), ("--car-weight", "car_weight"),
                 ("--freeze-bn", "freeze_bn"), ("--quick", "quick"), ("--pseudo-dir", "pseudo_dir"),
                 ("--val-pseudo-dir", "val_pseudo_dir"), ("--depth-checkpoint", "depth_checkpoint"),
                 ("--pixor-checkpoint", "pixor_checkpoint")]
    for flag, key in compared:
        if key not in recorded:
            continue
        wanted, started = getattr(config, key), recorded[key]
        if isinstance(wanted, (list, tuple)) or isinstance(started, (list, tuple)):
            wanted, started = tuple(wanted or ()), tuple(started or ())
        elif key.endswith(("data", "split", "dir", "checkpoint")):  # the same file, however it is spelt
            wanted, started = (None if v is None else str(Path(v).resolve()) for v in (wanted, started))
        if wanted != started:
            raise InputError(f"{_flag_text(flag, wanted)}, but {out} was started with {_flag_text(flag, started)}"
                             f" (resume with the same flags; only --epochs may change)")
    for flag, key in (("--precision", "precision"), ("--device", "device")):
        if key in recorded and recorded[key] != getattr(config, key):
            log.warning("%s: resumed with %s %s, started with %s: the remaining epochs compute differently",
                        out, flag, getattr(config, key), recorded[key])


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


def check_frames(config: TrainConfig, train_dir: Path, train_ids: list[str], val_dir: Path,
                 val_ids: list[str]) -> None:
    """Every frame file the run reads is there, before it trains: each frame's scan, image and calibration;
    its labels (``label_2/``) for the detector and joint tasks, whose targets and AP come from them. Depth
    runs need no labels (the target is ``depth_2/ID.png`` when present, else the frame's own 64-line scan)
    unless ``--car-weight`` weighs the labelled cars' pixels."""
    labels = config.task in ("detector", "joint") or config.car_weight != 1.0
    needs = f"a {config.task} run" + (" with --car-weight" if config.task == "depth" else "")
    val_flag = "--val-data" if config.val_data is not None else "--data"
    for folder, ids, flag, split in ((train_dir, train_ids, "--data", ("--train-split", config.train_split)),
                                     (val_dir, val_ids, val_flag, ("--val-split", config.val_split))):
        for pattern in FRAME_FILES:
            missing = _missing(folder, pattern, ids)
            if missing is None:
                continue
            frame, path, more = missing
            if split[1] is not None:  # the ids come from a split file: name it
                raise InputError(f"{split[0]} {split[1]}: frame {frame}{more} is not in {folder} (no {path})")
            raise InputError(f"{flag} {folder}: frame {frame}{more} has no {path}")
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


def check_pseudo_maps(config: TrainConfig, train_ids: list[str], val_ids: list[str]) -> None:
    """``--input pseudo``: the cached dense depth map of every frame the run trains and validates on."""
    if config.task == "detector" and config.input_mode == "pseudo":
        if config.pseudo_dir is None:
            raise InputError("--input pseudo needs the cached dense depth maps (--pseudo-dir; "
                             "python -m models.cache_pseudo makes them)")
        val_pseudo = ("--val-pseudo-dir", config.val_pseudo_dir) if config.val_pseudo_dir else ("--pseudo-dir",
                                                                                                config.pseudo_dir)
        for (flag, folder), ids in ((("--pseudo-dir", config.pseudo_dir), train_ids), (val_pseudo, val_ids)):
            missing = _missing(Path(folder), "{}.png", ids)
            if missing is not None:
                frame, path, more = missing
                raise InputError(f"{flag} {folder}: no cached depth map of frame {frame}{more} ({path})")


def load_start_weights(net: torch.nn.Module, name: str, path: Path, preset: Preset,
                       train_only: tuple[str, ...] = ()) -> None:
    """Weights to start from: a checkpoint, or an exported ``.onnx`` of the same network.

    From ONNX, the ``train_only`` submodules the graph lacks (a head added since the export) keep their
    initialisation; a checkpoint must match the preset exactly (models/checkpoint.py).
    """
    if not path.exists():
        raise InputError(f"--{name}-checkpoint: {path} does not exist")
    if path.is_dir():  # a run folder: the checkpoint is a file in it
        inside = path / f"{name}.pt"
        hint = f": give the checkpoint in it, {inside}" if inside.is_file() else f" (no {name}.pt in it)"
        raise InputError(f"--{name}-checkpoint: {path} is a folder{hint}")
    if name == "pixor" and preset.bev.split_pseudo and _bev_channels(path) == preset.bev.lidar_channels:
        # A LiDAR-only PIXOR of the same grid: the split net starts as exactly it, its pseudo channels'
        # weights at zero, so the camera pipeline starts from the scan's detector and learns what the
        # pseudo points add.
        lidar_net = build_pixor(lidar_only(preset))
        load_start_weights(lidar_net, name, path, lidar_only(preset), train_only)
        widen_input_channels(lidar_net, net)
        log.info("pixor: %s is LiDAR-only; its pseudo channels start at zero", path)
        return
    if path.suffix == ".onnx":
        from models.onnx_weights import load_onnx_weights

        network, exported = _exported_as(path)
        if network not in (None, name):
            raise InputError(f"--{name}-checkpoint: {path} is the {network} network of {path.parent}, not the {name} one")
        try:
            left = load_onnx_weights(net, path, optional=train_only)
        except ValueError as exc:  # a weight that does not fit; the manifest can say why
            if exported and exported != preset.name:
                raise ValueError(f"{exc}; its manifest says it was exported with --preset {exported}, and this run's "
                                 f"--preset is {preset.name}") from None
            raise
        if left:
            log.info("%s: %s not in %s, starting from initialisation", name, ", ".join(left), path)
    else:
        load_network_weights(net, load_checkpoint(path), name, preset)


def _exported_as(path: Path) -> tuple[str | None, str | None]:
    """(network, preset) the manifest beside an exported ``.onnx`` records for it; None where it says nothing."""
    try:
        manifest = load_manifest(path.parent)
    except ModelFileError:  # a lone .onnx, or a broken manifest: the weights themselves are checked
        return None, None
    network = next((n for n, entry in manifest.get("networks", {}).items() if entry.get("file") == path.name), None)
    return network, manifest.get("preset")


def _bev_channels(path: Path) -> int | None:
    """The BEV channels a PIXOR checkpoint or ``pixor.onnx`` reads (None if it says not)."""
    try:
        if path.suffix == ".onnx":
            from models.onnx_weights import read_onnx

            graph = read_onnx(path, load_external_data=False).graph
            return graph.input[0].type.tensor_type.shape.dim[1].dim_value
        return preset_from_dict(load_checkpoint(path).preset_config).bev.channels
    except (OSError, ValueError, KeyError, IndexError, AttributeError):
        return None


def widen_input_channels(source: torch.nn.Module, target: torch.nn.Module) -> None:
    """Copy ``source``'s weights into ``target``, whose first conv reads more input channels: those start at zero."""
    state = source.state_dict()
    for key, value in target.state_dict().items():
        if state[key].shape != value.shape:  # the first conv: (out, in, k, k) → (out, in + extra, k, k)
            widened = torch.zeros_like(value)
            widened[:, : state[key].shape[1]] = state[key]
            state[key] = widened
    target.load_state_dict(state, strict=True)


def start_training_metadata(path: Path, name: str) -> dict | None:
    """How the starting weights were trained: a checkpoint's metadata, or the manifest beside an ONNX file."""
    try:
        if path.suffix == ".onnx":
            manifest = json.loads((path.parent / "manifest.json").read_text(encoding="utf-8"))
            return manifest["networks"][name].get("training")
        return load_checkpoint(path).metadata
    except (OSError, KeyError, ValueError):
        return None


def freeze_except(networks: dict[str, torch.nn.Module], train_only: tuple[str, ...]) -> list[torch.nn.Module]:
    """With ``train_only`` submodule names: freeze every other parameter; the submodules to put in train mode.

    Without: every network trains (an empty list; the caller puts whole networks in train mode).
    """
    if not train_only:
        return []
    trained = []
    for prefix in train_only:
        found = [net.get_submodule(prefix) for net in networks.values() if _has_submodule(net, prefix)]
        if not found:
            raise InputError(f"--train-only: no submodule {prefix!r} in the {', '.join(networks)} network(s)")
        trained.extend(found)
    keep = {id(p) for module in trained for p in module.parameters()}
    for net in networks.values():
        for parameter in net.parameters():
            parameter.requires_grad_(id(parameter) in keep)
    return trained


def freeze_batch_norms(networks: dict[str, torch.nn.Module]) -> None:
    """Batch norms normalise with their running statistics and stop updating them (scale and shift still
    train). For weights read back from ONNX, whose batch norms come folded into the convolutions (identity
    statistics), and for batches too small to estimate statistics from."""
    for net in networks.values():
        for module in net.modules():
            if isinstance(module, torch.nn.modules.batchnorm._BatchNorm):
                module.eval()


def _has_submodule(net: torch.nn.Module, name: str) -> bool:
    try:
        net.get_submodule(name)
    except AttributeError:
        return False
    return True


def selection_criterion(task: str, metrics: dict) -> float:
    """Lower is better. Depth: the validation loss (MSE or L1, as trained). Detector and joint: minus the mean of BEV AP at IoU 0.7 and
    0.5 (moderate) — the validation loss can fall while AP does not (seen here: PIXOR on 16-line input had
    a lower loss after its first epoch but 24 points less AP at IoU 0.7), and AP is what the table reports."""
    if task == "depth":
        return float(metrics["val_loss"])
    return -0.5 * (metrics["bev_ap_0.7_moderate"] + metrics["bev_ap_0.5_moderate"])


def joint_step(networks: dict, preset: Preset, data_dir: Path, frame_id: str, precision: str = "fp32",
               device: torch.device = CPU, layout: torch.memory_format = torch.contiguous_format,
               depth_loss: str = "mse") -> torch.Tensor:
    """Loss of one frame through depth net → soft BEV → PIXOR (+ the depth loss)."""
    from models.data import depth_target

    frame = load_frame(data_dir, frame_id)
    lidar16 = frame_points(frame, 16)
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m models.train", description=__doc__.split("\n\n")[0],
                                     epilog=__doc__.split("\n\n", 1)[1], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("task", choices=TASKS)
    parser.add_argument("--data", type=Path, required=True, help="KITTI-layout training folder")
    parser.add_argument("--val-data", type=Path, help="KITTI-layout validation folder (default: --data + --val-split)")
    parser.add_argument("--train-split", type=Path, help="training frame ids, one per line (default: all of --data)")
    parser.add_argument("--val-split", type=Path, help="validation frame ids, one per line")
    parser.add_argument("--preset", default="edge", help="model preset (default edge)")
    parser.add_argument("--out", type=Path, required=True, help="run directory (log.jsonl, state.pt, depth.pt/pixor.pt)")
    parser.add_argument("--input", dest="input_mode", default="lidar16", choices=DETECTOR_INPUTS,
                        help="detector input (default lidar16)")
    parser.add_argument("--pseudo-dir", type=Path, help="cached dense depth PNGs for --input pseudo (training frames)")
    parser.add_argument("--val-pseudo-dir", type=Path, help="… of the validation frames (default: --pseudo-dir)")
    parser.add_argument("--depth-checkpoint", type=Path,
                        help="trained depth.pt (joint); depth: weights to start from (depth.pt or depth.onnx)")
    parser.add_argument("--pixor-checkpoint", type=Path,
                        help="trained pixor.pt (joint); detector: weights to start from (pixor.pt or pixor.onnx)")
    parser.add_argument("--train-only", type=lambda text: tuple(n for n in text.split(",") if n), default=(),
                        metavar="MODULES", help="train only these submodules (comma-separated, say refine); "
                                                "the rest stays frozen as loaded")
    parser.add_argument("--freeze-bn", action="store_true",
                        help="batch-norm statistics stay as loaded (use with weights from an exported .onnx)")
    parser.add_argument("--epochs", type=positive_int, help="default: the task's recipe")
    parser.add_argument("--batch-size", type=positive_int, help="default: the task's recipe")
    parser.add_argument("--lr", type=positive_float, help="default: the task's recipe")
    parser.add_argument("--depth-loss", default="mse", choices=tuple(DEPTH_LOSSES),
                        help="depth and joint: per-pixel loss on the depth map (default mse, the paper's)")
    parser.add_argument("--car-weight", type=positive_float, default=1.0,
                        help="depth: loss weight of the labelled cars' own pixels (default 1: every pixel alike)")
    parser.add_argument("--max-train-frames", type=positive_int, help="use only the first N training frames")
    parser.add_argument("--max-val-frames", type=positive_int, help="use only the first N validation frames")
    parser.add_argument("--workers", type=non_negative_int, default=0, help="data-loading processes (default 0)")
    parser.add_argument("--threads", type=positive_int, help="torch intra-op threads")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="auto",
                        help="auto (default: the first CUDA GPU torch sees, else the CPU), cpu, cuda or cuda:N")
    parser.add_argument("--precision", default="auto", choices=("auto", "bf16", "fp32"),
                        help="training arithmetic: bf16 autocast where the CPU has AVX-512 BF16 (auto, default)")
    parser.add_argument("--compile", default="auto", choices=("auto", "on", "off"),
                        help=f"torch.compile the training forward pass (auto, default: depth and detector runs of "
                             f"at least {COMPILE_MIN_STEPS} steps, where a C++ compiler is found)")
    parser.add_argument("--resume", action="store_true", help="continue the run in --out from its last epoch (its state.pt; the same flags, only --epochs may change)")
    parser.add_argument("--quick", action="store_true", help="a few frames and epochs: a smoke test")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    config = TrainConfig(**{k: v for k, v in vars(args).items()}, strict_resume=args.resume)
    try:
        result = run(config)
    except (InputError, FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        kept = ("keeps the last finished epoch (state.pt); rerun with --resume to continue"
                if (args.out / STATE_FILE).is_file() else "has no finished epoch yet; nothing to resume")
        print(f"interrupted: {args.out} {kept}", file=sys.stderr)
        return 130
    if result.nothing_to_do:
        print(already_trained(result))
        return 0
    print(f"run {result.run_dir}: loss {result.first_loss:.4f} → {result.last_loss:.4f}; "
          f"checkpoints {', '.join(str(p) for p in result.checkpoints.values())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
