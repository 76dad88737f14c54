"""How good the camera pipeline could be at a given resolution of the depth net's correction.

    python benchmarks/depth_bound.py --data data/sim/val --models weights/edge --factor 2 --out DIR
    python benchmarks/accuracy.py --data data/sim/val --models weights/edge --input lidar16+camera \\
        --depth-dir DIR/depth_2 --out RESULTS

With PIXOR adapted to the bound (session 21): ``--cache`` writes the maps in the
network's view, the layout ``python -m models.cache_pseudo`` writes, for the
training and the validation frames (TRAIN_CACHE and VAL_CACHE below), and this
fine-tunes the camera PIXOR on them (docs/measurements.md, session 21; the
shipped model's preset is edge-split-near35):

    python -m models.train detector --input pseudo --preset edge-split-near35 \\
        --data data/sim/train --val-data data/sim/val --pseudo-dir TRAIN_CACHE --val-pseudo-dir VAL_CACHE \\
        --pixor-checkpoint weights/edge/pixor.onnx --freeze-bn --epochs 1 --lr 2e-5 --out RUN

The edge depth net fills the 16-line scan inside its graph and predicts a
correction to that filled map (docs/models.md). For each frame this writes the
filled map plus the exact correction to the simulator's true depth, averaged
over blocks of ``factor`` × ``factor`` pixels of the network's view and
upsampled back bilinearly, as the network upsamples its own output: factor 1
is the best a correction at the network's input resolution can give, factor 2
the best one at half of it. ``--upsample closest`` replaces the bilinear
upsampling by an oracle of an edge-aware one: each pixel takes whichever of the
3×3 block corrections around it lands closest to the true depth (block means
over the pixels that have a correction). The maps are full-image KITTI depth
PNGs (metres × 256, 0 = none) for ``benchmarks/accuracy.py --depth-dir``;
pixels the fill does not reach stay empty, as they do with the network.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.errors import TORCH_MISSING, InputError

try:  # the filled scan comes from the depth net's own prefill module, in PyTorch
    import torch

    from models.depth_net import SparsePrefill
except ModuleNotFoundError as exc:
    if exc.name != "torch":
        raise
    from pipeline.cli import missing_extra

    raise missing_extra(TORCH_MISSING) from exc
from pipeline.beams import emulate_beams
from pipeline.calib import depth_crop
from pipeline.cli import (
    HelpFormatter,
    add_no_progress,
    check_not_input,
    check_output,
    examples,
    positive_int,
    quiet_interrupt,
    show_progress,
    unwritable,
)
from pipeline.frame import frame_ids, load_frame
from pipeline.kitti import read_depth_png, write_depth_png
from pipeline.model_files import ModelFileError, load_manifest
from pipeline.preprocess import depth_inputs, depth_view
from pipeline.presets import Preset, preset_from_dict


def _blocks(values: np.ndarray, factor: int) -> np.ndarray:
    """(h, w) → (h/factor, factor, w/factor, factor): the blocks of the view; ValueError if factor does not divide it."""
    h, w = values.shape
    if h % factor or w % factor:
        raise ValueError(f"--factor {factor} does not divide the network's view {w}×{h}")
    return values.reshape(h // factor, factor, w // factor, factor)


def _exact_correction(filled: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where both the fill and the truth have depth, and the correction truth − filled there (0 elsewhere)."""
    has = (filled > 0) & (truth > 0)
    return has, np.where(has, truth - filled, 0.0).astype(np.float32)


def _corrected(filled: np.ndarray, correction: np.ndarray, min_depth: float) -> np.ndarray:
    """filled + correction, floored at min_depth, on the pixels the fill reaches (0 elsewhere, as the net)."""
    return np.where(filled > 0, np.maximum(filled + correction, min_depth), 0.0).astype(np.float32)


def bounded_depth(filled: np.ndarray, truth: np.ndarray, factor: int, min_depth: float) -> np.ndarray:
    """filled + the true correction at 1/factor resolution (view pixels; 0 where the fill or the truth has none)."""
    _, correction = _exact_correction(filled, truth)
    if factor > 1:
        h, w = correction.shape
        coarse = _blocks(correction, factor).mean(axis=(1, 3))
        correction = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_LINEAR)  # half-pixel centres, like the net
    return _corrected(filled, correction, min_depth)


def closest_neighbour_depth(filled: np.ndarray, truth: np.ndarray, factor: int, min_depth: float) -> np.ndarray:
    """filled + per pixel the one of the 3×3 block-mean exact corrections around its block closest to its own.

    An oracle (it reads the truth to choose): the best an upsampling that gives each pixel one neighbouring
    coarse correction whole, rather than a bilinear mix of them, could do at 1/factor resolution.
    """
    has, correction = _exact_correction(filled, truth)
    sums = _blocks(correction, factor).sum(axis=(1, 3))
    counts = _blocks(has, factor).sum(axis=(1, 3))
    coarse = np.where(counts > 0, sums / np.maximum(counts, 1), 0.0).astype(np.float32)
    padded = np.pad(coarse, 1, mode="edge")
    hc, wc = coarse.shape
    neighbours = np.stack([padded[dy : dy + hc, dx : dx + wc] for dy in range(3) for dx in range(3)])
    neighbours = neighbours.repeat(factor, axis=1).repeat(factor, axis=2)  # (9, h, w): each pixel's 3×3
    chosen = np.take_along_axis(neighbours, np.abs(neighbours - correction).argmin(axis=0)[None], axis=0)[0]
    return _corrected(filled, np.where(has, chosen, 0.0), min_depth)


def to_full_image(view: np.ndarray, image_hw: tuple[int, int], preset: Preset) -> np.ndarray:
    """A map of the network's view as a full-image map that :func:`pipeline.preprocess.depth_view` reads back exactly."""
    crop = depth_crop(image_hw, *preset.crop_hw)
    scale = round(1 / preset.depth.input_scale)
    full = np.zeros(image_hw, np.float32)
    full[crop.top : crop.top + crop.height, crop.left : crop.left + crop.width] = np.repeat(
        np.repeat(view, scale, axis=0), scale, axis=1)
    return full


@quiet_interrupt("the maps written so far stay in --out")
def main(argv: list[str] | None = None) -> int:
    epilog = __doc__.split("\n\n", 1)[1] + "\n" + examples(
        "python benchmarks/depth_bound.py --data data/sim/val --models weights/edge --factor 2 --out outputs/bound2")
    parser = argparse.ArgumentParser(allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
                                     prog="python benchmarks/depth_bound.py", description=__doc__.split("\n\n")[0],
                                     epilog=epilog, formatter_class=HelpFormatter)
    parser.add_argument("--data", type=Path, required=True, metavar="DIR",
                        help="KITTI-layout folder with the true depth in depth_2/ (the synthetic scenes)")
    parser.add_argument("--models", type=Path, required=True, metavar="DIR",
                        help="two-stage model directory (its preset gives the view and the fill)")
    parser.add_argument("--factor", type=positive_int, default=1,
                        help="correction at 1/factor of the view; must divide its height and width (default 1)")
    parser.add_argument("--upsample", choices=("bilinear", "closest"), default="bilinear",
                        help="bilinear (default, as the network), or closest: each pixel takes the one of the 3×3 "
                             "block corrections around it closest to the truth (an oracle)")
    parser.add_argument("--frames", type=positive_int, metavar="N", help="only the first N frames (default: all)")
    parser.add_argument("--cache", action="store_true",
                        help="write OUT/<id>.png in the network's view (models.train --pseudo-dir) instead of "
                             "full-image maps")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR",
                        help="writes DIR/depth_2/<id>.png (DIR/<id>.png with --cache)")
    add_no_progress(parser)
    args = parser.parse_args(argv)
    try:
        check_output(args.out, "--out", directory=True)
        check_not_input(args.out, "--out", {"--data": args.data, "--models": args.models})
        count = write_bounds(args.data, args.models, args.factor, args.out, args.frames, args.upsample, args.cache,
                             progress=show_progress(args.no_progress))
    except (InputError, ModelFileError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # the output folder refused a write after the check (full disk, permissions)
        print(unwritable(args.out, exc), file=sys.stderr)
        return 2
    print(f"wrote {count} maps to {args.out if args.cache else args.out / 'depth_2'}")
    return 0


def check_inputs(data: Path, models: Path, factor: int) -> Preset:
    """Everything a run needs, checked before any work; the model directory's preset."""
    manifest = load_manifest(models)
    if "depth" not in manifest.get("networks", {}):
        raise InputError(f"--models {models}: a LiDAR-only model directory (no depth network); give a two-stage "
                         "one such as weights/edge")
    try:
        preset = preset_from_dict(manifest["preset_config"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ModelFileError(f"{models / 'manifest.json'}: preset_config: {exc}") from exc
    if not preset.depth.prefill_passes:
        raise InputError(f"{models}: the depth net has no fill to correct (prefill_passes 0)")
    height, width = preset.depth.input_hw
    if height % factor or width % factor:
        fits = [f for f in range(2, min(height, width) + 1) if height % f == 0 and width % f == 0][:6]
        raise InputError(f"--factor {factor}: does not divide the network's view {width}×{height}; "
                         f"use 1 or one of {', '.join(map(str, fits))}")
    if not (data / "velodyne").is_dir():
        raise InputError(f"--data {data}: not a KITTI object folder (no velodyne/ inside)")
    if not (data / "depth_2").is_dir():
        raise InputError(f"--data {data}: no depth_2/ folder with the true depth (only the synthetic scenes "
                         "have it: python -m simulation)")
    return preset


def check_destination(data: Path, out: Path, cache: bool) -> Path:
    """The folder the maps go to, refused when it would overwrite depth maps: the true depth of ``data``
    (``--out`` the data folder itself), an earlier run's bounds, or a ``models.cache_pseudo`` cache."""
    target = out if cache else out / "depth_2"
    if target.resolve() == (data / "depth_2").resolve():
        raise InputError(f"--out {out}: would overwrite the true depth in {data / 'depth_2'}; give another folder")
    if (out / "cache.json").exists():
        raise InputError(f"--out {out}: holds a models.cache_pseudo cache (cache.json); give a new or empty folder")
    if target.is_dir() and next(target.glob("*.png"), None) is not None:
        raise InputError(f"--out {out}: {target} already holds depth maps; give a new or empty folder")
    return target


def write_bounds(data: Path, models: Path, factor: int, out: Path, frames: int | None = None,
                 upsample: str = "bilinear", cache: bool = False, progress: bool = True) -> int:
    """Write OUT/depth_2/<id>.png (OUT/<id>.png in the network's view with ``cache``) for the first
    ``frames`` frames of ``data`` (all by default); returns how many."""
    preset = check_inputs(data, models, factor)
    fill = SparsePrefill(preset.depth.prefill_passes, preset.depth.prefill_kernel)
    bound = closest_neighbour_depth if upsample == "closest" else bounded_depth
    ids = frame_ids(data)[:frames]
    if not ids:
        raise InputError(f"--data {data}: no frames (velodyne/ has no .bin file)")
    target = check_destination(data, out, cache)
    target.mkdir(parents=True, exist_ok=True)
    for fid in tqdm(ids, desc="bounded depth", unit="frame", disable=not progress):
        frame = load_frame(data, fid)
        truth_path = data / "depth_2" / f"{fid}.png"
        if not truth_path.exists():
            raise InputError(f"{truth_path}: no true depth (only the synthetic scenes have it)")
        inputs = depth_inputs(frame.image, emulate_beams(frame.points, 16), frame.calib, preset)
        with torch.no_grad():
            filled = fill(torch.from_numpy(inputs.sparse_depth))[0, 0].numpy()
        truth = depth_view(read_depth_png(truth_path), preset)
        view = bound(filled, truth, factor, preset.depth.min_depth)
        write_depth_png(target / f"{fid}.png", view if cache else to_full_image(view, frame.image_hw, preset))
    return len(ids)


if __name__ == "__main__":
    sys.exit(main())
