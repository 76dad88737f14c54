"""Training data from KITTI-layout folders (real KITTI or the synthetic scenes), as torch Datasets.

Every sample is built with the runtime's own NumPy code (pipeline/), so the
networks train on exactly what the Detector feeds them at inference.

Depth samples: the 16-line scan projected into the depth net's view, the
image, and the target — ``depth_2/ID.png`` (dense ground truth of the
synthetic scenes, of the image's own size) when the folder has ``depth_2/``, else
the stored scan projected into the view, not thinned (a 64-line scan on real KITTI,
a 16-line sensor's own under ``--emulate-beams 0``; real KITTI object frames have no
dense ground truth). On a KITTI depth-completion drive
(:class:`DepthCompletionDataset`) the 16 lines are thinned on its projected scan
and the target is its semi-dense ``groundtruth``.

Detector samples: the BEV tensor of the chosen input — ``lidar64`` (scan as
stored), ``lidar16`` (thinned), ``pseudo`` (pseudo points from a cached dense
depth map in ``PSEUDO_DIR/ID.png`` plus the 16 real lines) — and PIXOR targets
of the Car labels (the class read case-insensitively, as the evaluator reads it: :func:`is_car`).

Every "16-line" scan here is the stored scan thinned to ``beams`` lines (16 by
default, ``models.train --emulate-beams``); ``beams`` 0 or None takes the scans
as stored: a 16-line sensor's own, which cannot be thinned again.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch
from torch.utils.data import Dataset

from evaluation.depth_metrics import box_in_view, car_surface
from pipeline.beams import emulate_beams
from pipeline.bev import voxelize_bev
from pipeline.boxes import labels_to_boxes
from pipeline.calib import Calibration, depth_crop, sparse_depth_map
from pipeline.depth_completion import read_frame
from pipeline.errors import InputError
from pipeline.frame import Frame, load_frame
from pipeline.kitti import Object3D, read_depth_png, read_image_depth_png
from pipeline.preprocess import depth_inputs, depth_view, view_calibration, view_from_depth_png
from pipeline.presets import Preset
from pipeline.pseudo import depth_to_points, merge_points
from pipeline.targets import encode_targets

DETECTOR_INPUTS = ("lidar64", "lidar16", "pseudo")
CAR_CLASS = "Car"  # KITTI's class the detector learns and the evaluation scores
SAMPLE_CACHE_BYTES = 6 * 1024**3  # per dataset: the edge depth set of 2,000 frames takes 2.4 GB


@dataclass
class SampleCache:
    """A dataset's samples before augmentation, kept in memory from their first load, up to a byte budget.

    Loading a depth sample (PNG decodes, 16-line emulation, projection) took 20 ms here, a quarter of
    a training step's time per frame, and gives the same arrays every epoch: augmentation comes after
    it. Samples past the budget are loaded each time, as without the cache. Callers must not modify
    the arrays they get. With data-loading worker processes (``--workers``, off by default) each
    worker fills its own copy, which ends with the epoch's workers: the cache then saves nothing.
    """

    max_bytes: int = SAMPLE_CACHE_BYTES
    items: dict[int, tuple[np.ndarray, ...]] = field(default_factory=dict)
    nbytes: int = 0

    def get(self, index: int, load: Callable[[int], tuple[np.ndarray, ...]]) -> tuple[np.ndarray, ...]:
        item = self.items.get(index)
        if item is None:
            item = load(index)
            size = sum(array.nbytes for array in item)
            if self.nbytes + size <= self.max_bytes:
                self.items[index] = item
                self.nbytes += size
        return item


def frame_points(frame: Frame, beams: int | None) -> np.ndarray:
    """The scan as the sensor under test would give it: thinned to ``beams`` lines (None or 0: as stored)."""
    return emulate_beams(frame.points, beams) if beams else frame.points


def depth_target(data_dir: Path, frame: Frame, preset: Preset) -> np.ndarray:
    """(H, W) target depth in the network's view (metres, 0 = none): the frame's ``depth_2/`` map when the folder
    has ``depth_2/`` (an InputError naming the map when it is missing or not of the image's size: the crop is
    taken from the map's own shape, so another size would train on another part of the scene), else its scan."""
    dense_dir = Path(data_dir) / "depth_2"
    if dense_dir.is_dir():
        return depth_view(read_image_depth_png(dense_dir / f"{frame.frame_id}.png", frame.image_hw), preset)
    view_calib = view_calibration(frame.image_hw, frame.calib, preset)
    return sparse_depth_map(frame.points, view_calib, preset.depth.input_hw)


@dataclass
class DepthDataset(Dataset):
    """(rgb (3,H,W), sparse (1,H,W), target (1,H,W)) float32 tensors per frame, and with ``car_weight`` != 1 a
    fourth, the per-pixel loss weight (1,H,W) (:func:`depth_sample`)."""

    inputs: ClassVar[int] = 2  # leading fields that are network inputs (rgb, sparse); the rest are targets
    data_dir: Path
    frame_ids: list[str]
    preset: Preset
    beams: int | None = 16  # the lines the scan is thinned to (None or 0: as stored, a 16-line sensor's own)
    augment: bool = False
    seed: int = 0
    epoch: int = 0  # set by the training loop: augmentation differs per epoch, reproducibly
    # != 1: a 4th field, the per-pixel loss weight: this on the labelled cars' own pixels, 1 elsewhere.
    car_weight: float = 1.0
    cache: SampleCache = field(default_factory=SampleCache, repr=False)

    def __len__(self) -> int:
        return len(self.frame_ids)

    def _load(self, index: int) -> tuple[np.ndarray, ...]:
        """uint8 rgb (3, H, W) (the view's pixels, exact), float32 sparse and target (1, H, W)
        [, uint8 car mask (1, H, W) with car_weight]."""
        frame = load_frame(self.data_dir, self.frame_ids[index], with_labels=self.car_weight != 1.0)
        inputs = depth_inputs(frame.image, frame_points(frame, self.beams), frame.calib, self.preset)
        target = depth_target(self.data_dir, frame, self.preset)[None]
        sample = (inputs.rgb[0].astype(np.uint8), inputs.sparse_depth[0], target)
        if self.car_weight != 1.0:
            sample += (car_pixels(frame, target[0], self.preset)[None].astype(np.uint8),)
        return sample

    def __getitem__(self, index: int) -> tuple[torch.Tensor, ...]:
        return depth_sample(self.cache.get(index, self._load), self.augment, (self.seed, self.epoch, index),
                            self.car_weight)


def depth_sample(item: tuple[np.ndarray, ...], augment: bool, key: tuple[int, int, int],
                 car_weight: float = 1.0) -> tuple[torch.Tensor, ...]:
    """A depth sample's tensors from its cached arrays (uint8 rgb, sparse, target[, car mask]): mirrored and
    brightened when ``augment``, reproducibly per ``key`` (seed, epoch, index); the mask as loss weights."""
    rgb, sparse, target, *mask = item
    rgb = rgb.astype(np.float32)
    if augment:
        rng = np.random.default_rng(key)
        if rng.random() < 0.5:  # mirror image, input and target together
            rgb, sparse, target = rgb[..., ::-1], sparse[..., ::-1], target[..., ::-1]
            mask = [m[..., ::-1] for m in mask]
        rgb = np.clip(rgb * rng.uniform(0.8, 1.2) + rng.uniform(-10, 10), 0, 255)
    sample = (torch.from_numpy(np.ascontiguousarray(rgb, np.float32)),
              torch.from_numpy(np.array(sparse, np.float32)),  # copies: the cache keeps its arrays
              torch.from_numpy(np.array(target, np.float32)))
    if mask:
        sample += (torch.from_numpy(np.where(mask[0] > 0, car_weight, 1.0).astype(np.float32)),)
    return sample


def car_pixels(frame: Frame, target: np.ndarray, preset: Preset) -> np.ndarray:
    """(H, W) bool in the network's view: the own pixels of every labelled car (of any difficulty), each found
    as the depth evaluation finds a moderate car's (the 2D box moved into the view by
    :func:`evaluation.depth_metrics.box_in_view`, and in it the pixels on the car's surface:
    :func:`evaluation.depth_metrics.car_surface`)."""
    crop = depth_crop(frame.image_hw, *preset.crop_hw)
    mask = np.zeros(target.shape, bool)
    for label in frame.labels or []:  # a handful of cars per frame; the pixels are array slices
        if not is_car(label):
            continue
        box = box_in_view(label.bbox, crop, preset.depth.input_scale)
        window, on_car = car_surface(target, box, label.location[2])
        mask[window] |= on_car
    return mask


def is_car(label: Object3D) -> bool:
    """A label of KITTI's Car class, its name compared case-insensitively as the evaluation compares it
    (evaluation.labels.LabelArrays): a ``car`` the trainer skipped would be a car it never learnt but is scored on."""
    return label.type.lower() == CAR_CLASS.lower()


def car_boxes(frame: Frame) -> np.ndarray:
    """(N, 7) LiDAR-frame boxes of the labelled cars."""
    return labels_to_boxes([o for o in (frame.labels or []) if is_car(o)], frame.calib)


def detector_points(frame: Frame, preset: Preset, input_mode: str,
                    pseudo_dir: Path | None, beams: int | None = 16) -> np.ndarray:
    """The point cloud PIXOR sees for ``input_mode``: pseudo points first (``pseudo``), then the scan."""
    pseudo, real = detector_clouds(frame, preset, input_mode, pseudo_dir, beams)
    return real if pseudo is None else merge_points(pseudo, real)


def detector_clouds(frame: Frame, preset: Preset, input_mode: str, pseudo_dir: Path | None,
                    beams: int | None = 16) -> tuple[np.ndarray | None, np.ndarray]:
    """The (M, 4) pseudo points (``pseudo`` only, else None) and the (N, 4) scan PIXOR sees for ``input_mode``;
    ``lidar16`` and ``pseudo`` thin it to ``beams`` lines (None or 0: as stored)."""
    if input_mode == "lidar64":
        return None, frame.points
    lidar16 = frame_points(frame, beams)
    if input_mode == "lidar16":
        return None, lidar16
    if input_mode != "pseudo":
        raise InputError(f"--input: {input_mode!r} is not one of {', '.join(DETECTOR_INPUTS)}")
    depth, view_calib = cached_pseudo_depth(pseudo_dir, frame, preset)
    return depth_to_points(depth, view_calib, *preset.pseudo_limits), lidar16


def cached_pseudo_depth(pseudo_dir: Path | None, frame: Frame, preset: Preset) -> tuple[np.ndarray, Calibration]:
    """A frame's cached dense depth (``models.cache_pseudo``) and the calibration of the view it is in."""
    if pseudo_dir is None:
        raise InputError("--input pseudo needs the cached dense depth maps (--pseudo-dir)")
    path = Path(pseudo_dir) / f"{frame.frame_id}.png"
    depth = read_depth_png(path)
    if depth.shape != tuple(preset.depth.input_hw):  # another view: this view's calibration would misplace its pixels
        h, w = preset.depth.input_hw
        raise InputError(f"{path}: a cached {depth.shape[0]}×{depth.shape[1]} map, not the {h}×{w} view of "
                         f"preset {preset.name!r}'s depth net; cache the maps again with a model of this preset")
    return depth, view_calibration(frame.image_hw, frame.calib, preset)


@dataclass
class DetectorDataset(Dataset):
    """(bev (C,ny,nx), score target (1,h,w), regression target (6,h,w)) per frame."""

    inputs: ClassVar[int] = 1  # leading fields that are network inputs (bev); the rest are targets
    data_dir: Path
    frame_ids: list[str]
    preset: Preset
    input_mode: str = "lidar16"
    pseudo_dir: Path | None = None
    beams: int | None = 16  # lidar16 and pseudo: the lines the scan is thinned to (None or 0: as stored)
    augment: bool = False
    seed: int = 0
    epoch: int = 0  # set by the training loop: augmentation differs per epoch, reproducibly
    cache: SampleCache = field(default_factory=SampleCache, repr=False)

    def __len__(self) -> int:
        return len(self.frame_ids)

    def _load(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The (M, 4) pseudo points (M = 0 without), the (N, 4) scan PIXOR sees, and the (K, 7) car boxes."""
        frame = load_frame(self.data_dir, self.frame_ids[index], with_image=False)  # PIXOR sees no pixels
        pseudo, real = detector_clouds(frame, self.preset, self.input_mode, self.pseudo_dir, self.beams)
        return (np.zeros((0, 4), np.float32) if pseudo is None else pseudo), real, car_boxes(frame)

    def __getitem__(self, index: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        pseudo, points, boxes = self.cache.get(index, self._load)  # mirrored below as copies, never in place
        if self.augment:
            rng = np.random.default_rng((self.seed, self.epoch, index))
            if rng.random() < 0.5:  # mirror left ↔ right: y → −y, yaw → −yaw
                points, pseudo = points.copy(), pseudo.copy()
                points[:, 1] *= -1
                pseudo[:, 1] *= -1
                boxes = boxes.copy()
                boxes[:, 1] *= -1
                boxes[:, 6] *= -1
        # Pseudo points apart from the scan: the same BEV as their merged cloud, or their own channels
        # on a split grid (BevGrid.split_pseudo).
        bev = voxelize_bev(points, self.preset.bev, pseudo=tuple(pseudo[:, :3].T) if len(pseudo) else None)
        targets = encode_targets(boxes, self.preset.bev, self.preset.pixor.output_stride, self.preset.decode)
        return (torch.from_numpy(bev), torch.from_numpy(targets.score[None]),
                torch.from_numpy(targets.regression))


@dataclass
class DepthCompletionDataset(Dataset):
    """(rgb (3,H,W), sparse (1,H,W), target (1,H,W)) float32 tensors per frame of a KITTI depth-completion drive
    in the flat layout (:mod:`pipeline.depth_completion`: ``image_02/``, ``velodyne_raw/``, ``groundtruth/``).

    The projected 64-line ``velodyne_raw`` map is thinned to ``beams`` lines through ``calib``, the drive's
    calibration (:func:`pipeline.depth_completion.drive_calibration`; exact with the drive's raw scans in
    ``velodyne_points/``, else by each pixel's elevation), then cropped and shrunk into the network's view as
    the runtime does for such frames (:func:`pipeline.preprocess.view_from_depth_png`); the target is KITTI's
    semi-dense ``groundtruth`` in that view. Samples are cached and augmented as :class:`DepthDataset`'s.
    """

    inputs: ClassVar[int] = 2  # leading fields that are network inputs (rgb, sparse); the rest are targets
    data_dir: Path
    frame_ids: list[str]
    preset: Preset
    calib: Calibration | None  # None: only with beams None or 0 (the scan as given)
    beams: int | None = 16
    augment: bool = False
    seed: int = 0
    epoch: int = 0  # set by the training loop: augmentation differs per epoch, reproducibly
    cache: SampleCache = field(default_factory=SampleCache, repr=False)

    def __len__(self) -> int:
        return len(self.frame_ids)

    def _load(self, index: int) -> tuple[np.ndarray, ...]:
        """uint8 rgb (3, H, W) (the view's pixels, exact), float32 sparse and target (1, H, W)."""
        frame = read_frame(Path(self.data_dir), self.frame_ids[index], self.calib, self.beams)
        rgb, sparse = view_from_depth_png(frame.image, frame.sparse, self.preset)
        target = depth_view(frame.ground_truth, self.preset)[None]
        return rgb[0].astype(np.uint8), sparse[0], target  # the view's pixels are whole numbers: uint8 is exact

    def __getitem__(self, index: int) -> tuple[torch.Tensor, ...]:
        return depth_sample(self.cache.get(index, self._load), self.augment, (self.seed, self.epoch, index))
