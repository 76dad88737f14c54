"""Export one or both of a preset's networks (``--networks``) into a model directory: ONNX files, parity check,
manifest."""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import torch
from tqdm import tqdm

from export.directory import check_destination, staged
from export.inputs import (
    DEFAULT_FRAME,
    DEFAULT_KITTI_DIR,
    NetworkInputs,
    check_frame,
    kitti_inputs,
    random_inputs,
)
from export.manifest import UNTRAINED, NetworkEntry, build_manifest, verify_model_dir, write_manifest
from export.onnx_export import EXPORTER, OPSET, NetworkIO, depth_io, export_onnx, pixor_io
from export.parity import ParityResult, cpu_session, depth_parity, pixor_parity, require_parity
from models import build_network
from models.checkpoint import Checkpoint, find_checkpoints, load_checkpoint, load_network_weights
from models.depth_net import IMAGENET_MEAN, IMAGENET_STD
from pipeline.errors import InputError
from pipeline.model_files import MANIFEST_NAME, ModelFileError
from pipeline.presets import Preset, check_preset, get_preset, preset_from_dict, registered_preset

log = logging.getLogger(__name__)

FILES = {"depth": "depth.onnx", "pixor": "pixor.onnx"}


@dataclass
class ExportConfig:
    """What to export and how to check it."""

    preset: str | None  # a registered name or a .json preset file; None: the checkpoints' own (checkpoint_preset)
    out: Path
    checkpoints: Path | None = None  # directory with depth.pt and/or pixor.pt (models/checkpoint.py)
    kitti_dir: Path = DEFAULT_KITTI_DIR  # real frame for the parity check
    frame: str = DEFAULT_FRAME
    seed: int = 0  # initialisation of untrained weights and the random parity inputs
    parity: bool = True  # compare ONNX Runtime with PyTorch (a real frame + random inputs)
    networks: tuple[str, ...] = ("depth", "pixor")  # ("pixor",) for a LiDAR-only model directory
    progress: bool = False


@dataclass
class ExportResult:
    """What :func:`run` made."""

    directory: Path
    files: dict[str, Path]
    manifest_path: Path
    manifest: dict
    parity: list[ParityResult] = field(default_factory=list)
    networks: dict[str, torch.nn.Module] = field(default_factory=dict)  # the exported modules, eval mode


def normalisation(preset: Preset) -> dict:
    """Constants the runtime must agree with (the image normalisation itself is inside depth.onnx)."""
    return {
        "rgb_input": "raw RGB 0-255, float32, channels first; normalised inside depth.onnx",
        "rgb_mean": [round(m * 255.0, 6) for m in IMAGENET_MEAN],
        "rgb_std": [round(s * 255.0, 6) for s in IMAGENET_STD],
        "depth_units": "metres",
        **preset.described()["normalisation"],
    }


def _checkpoint_files(config: ExportConfig) -> dict[str, Path]:
    """The checkpoints to load (network → path) among ``config.networks``; {} for initialised weights.

    Checked before any work: a --checkpoints folder holding none of the networks asked for would
    otherwise export initialised weights where the user meant trained ones.
    """
    if config.checkpoints is None:
        return {}
    folder = Path(config.checkpoints)
    if folder.is_file():
        raise InputError(f"--checkpoints {folder}: is a file; give the folder that holds depth.pt and/or pixor.pt")
    try:
        found = find_checkpoints(folder)
    except FileNotFoundError as exc:
        raise FileNotFoundError(f"--checkpoints {exc}") from None
    wanted = {name: path for name, path in found.items() if name in config.networks}
    if not wanted:
        raise FileNotFoundError(f"--checkpoints {folder}: holds {', '.join(p.name for p in found.values())} but no "
                                f"checkpoint of --networks {' '.join(config.networks)}")
    return wanted


def export_preset(config: ExportConfig) -> Preset:
    """The preset ``config`` exports with: ``--preset`` (a name or a file), else the checkpoints' own."""
    if config.preset is not None:
        return get_preset(config.preset)
    if config.checkpoints is None:
        raise InputError("--preset: needed without --checkpoints (with them, export takes the preset they were "
                         "trained with)")
    preset, path = checkpoint_preset(config)
    log.info("preset %s: the one %s was trained with (no --preset given)", preset.name, path)
    return preset


def checkpoint_preset(config: ExportConfig) -> tuple[Preset, Path]:
    """The preset ``config.checkpoints`` were trained with, and the checkpoint it was read from, for an export without
    --preset: PIXOR's (its grid and decoding are the model directory's; the depth net is checked against it on
    loading, as under any --preset), else the depth net's. A registered name is taken by name, so a preset whose
    definition changed since training is refused on loading as under --preset; any other is the checkpoint's own
    ``preset_config``, checked (:func:`check_preset`) as a --preset file would be."""
    checkpoints = _checkpoint_files(config)
    path = checkpoints.get("pixor") or checkpoints["depth"]
    checkpoint = load_checkpoint(path)
    try:
        preset = registered_preset(checkpoint.preset)
    except ValueError:
        preset = preset_from_dict(checkpoint.preset_config)
    try:
        check_preset(preset)
    except ValueError as exc:
        raise InputError(f"{path}: its preset_config: {exc}") from None
    return preset, path


def _unregistered_preset(checkpoint: Checkpoint, preset: Preset) -> str | None:
    """Why ``checkpoint`` does not load under ``preset`` and how to export it anyway, when it was trained with a
    preset not registered here (a preset file's, or one added to another copy of pipeline/presets.py): its
    message would send the user to a --preset of that name, which is unknown here. None for a registered one."""
    try:
        registered_preset(checkpoint.preset)
    except ValueError:
        pass
    else:
        return None
    try:
        trained = preset_from_dict(checkpoint.preset_config).to_dict()
    except ValueError:
        return None
    wanted = preset.to_dict()
    differing = [f"{section}.{key} {value!r} in the checkpoint, {wanted[section].get(key)!r} in {preset.name!r}"
                 for section in ("depth", "pixor", "bev", "decode") for key, value in trained[section].items()
                 if value != wanted[section].get(key)] + (
                     [f"crop_hw {trained['crop_hw']!r} in the checkpoint"] if trained["crop_hw"] != wanted["crop_hw"] else [])
    return (f"{checkpoint.path}: trained with preset {checkpoint.preset!r}, which is not registered here (it is the "
            f"checkpoint's own preset_config), and its weights do not fit preset {preset.name!r} "
            f"({'; '.join(differing[:3]) or 'another configuration'}): leave --preset out, and export takes the "
            "checkpoints' own preset")


def _check_keeps_trained(out: Path, checkpoints: dict[str, Path], networks: tuple[str, ...]) -> None:
    """Refuse to replace a trained network at ``out`` by initialised weights (a forgotten --checkpoints)."""
    try:
        held = json.loads((out / MANIFEST_NAME).read_text(encoding="utf-8"))["networks"]
        # A network the directory does not hold (the depth net over a LiDAR-only one) has nothing to lose; the
        # ones it does hold must still be checked.
        trained = [name for name in networks
                   if name not in checkpoints and held.get(name, {}).get("weights") == "trained"]
        dropped = [name for name in held if name not in networks and held[name].get("weights") == "trained"]
    except (OSError, ValueError, KeyError, TypeError, AttributeError):  # no or broken model directory there
        return
    if trained:
        raise ModelFileError(f"--out {out}: holds trained {' and '.join(trained)} weights, which this export would "
                             "replace by initialised ones; give --checkpoints with them, or another --out")
    if dropped:
        raise ModelFileError(f"--out {out}: holds a trained {' and '.join(dropped)} network, which this export "
                             f"(--networks {' '.join(networks)}) would delete; give another --out")


def _load_weights(checkpoints: dict[str, Path], preset: Preset, models: dict[str, torch.nn.Module]) -> dict[str, dict | None]:
    """Load trained weights where checkpoints exist; returns network → training metadata (None = untrained)."""
    training: dict[str, dict | None] = {name: None for name in models}
    for name, path in checkpoints.items():
        checkpoint = load_checkpoint(path)
        try:
            load_network_weights(models[name], checkpoint, name, preset)
        except ValueError as exc:
            hint = _unregistered_preset(checkpoint, preset) if name in checkpoint.state_dicts else None
            if hint is None:
                raise
            raise InputError(hint) from exc
        training[name] = {"checkpoint": path.name, **checkpoint.metadata}
    untrained = [name for name, meta in training.items() if meta is None]
    if checkpoints and untrained:
        folder = next(iter(checkpoints.values())).parent
        log.warning("no checkpoint for %s in %s: exporting initialised weights", ", ".join(untrained), folder)
    return training


@contextmanager
def _step(bar: tqdm, label: str) -> Iterator[None]:
    bar.set_description(label)
    if bar.disable:  # no bar in a pipe or a log (pipeline.cli.show_progress): a line per step there instead
        log.info("%s …", label)
    yield
    bar.update(1)


def run(config: ExportConfig, preset: Preset | None = None) -> ExportResult:
    """Build (and load) the networks of ``config.networks``, export each to ONNX, check them, write the manifest.

    Raises ParityError when ONNX Runtime disagrees with PyTorch past tolerance, ValueError/FileNotFoundError for
    bad presets or checkpoints, and ModelFileError for an ``--out`` that holds something other than an FP32 model
    directory of this preset, or trained networks this export would replace by initialised ones or delete;
    ``--out`` is then left as it was.
    """
    preset = preset or export_preset(config)  # resolved already by a caller that checked its destination
    out = Path(config.out)
    unknown = set(config.networks) - set(FILES)
    if unknown or "pixor" not in config.networks:
        raise ValueError(f"--networks: {', '.join(config.networks)}; choose 'depth pixor' or 'pixor'")
    # Every input is checked before the minutes of export: a misspelt flag fails at once.
    check_destination(out, preset.name, "fp32")
    checkpoints = _checkpoint_files(config)
    _check_keeps_trained(out, checkpoints, config.networks)
    sources: list[NetworkInputs] = []
    if config.parity:
        check_frame(config.kitti_dir, config.frame)
        sources = [kitti_inputs(preset, config.kitti_dir, config.frame), random_inputs(preset, config.seed)]
    torch.manual_seed(config.seed)
    # Written in a staging folder and swapped in when complete and checked (export.directory): a parity
    # failure must not leave an earlier model directory at --out with new ONNX files and its old manifest.
    with staged(out) as staging:
        manifest, models, results = _export(config, preset, staging, checkpoints, sources)
    files = {name: out / FILES[name] for name in models}
    return ExportResult(
        directory=out, files=files, manifest_path=out / MANIFEST_NAME, manifest=manifest, parity=results,
        networks=models,
    )


def _export(config: ExportConfig, preset: Preset, staging: Path, checkpoints: dict[str, Path],
            sources: list[NetworkInputs]) -> tuple[dict, dict, list[ParityResult]]:
    """Export, check (on ``sources``) and describe the networks in ``staging``; returns (manifest, modules,
    parity results)."""
    models = {name: build_network(name, preset).eval() for name in FILES if name in config.networks}
    interfaces: dict[str, NetworkIO] = {
        "depth": depth_io(preset.depth.input_hw),
        "pixor": pixor_io(preset.bev.shape, preset.pixor.output_stride),
    }
    steps = 1 + len(models) + (2 * len(models) if config.parity else 0) + 1  # weights, exports, parity, manifest
    with tqdm(total=steps, disable=not config.progress, unit="step") as bar:
        with _step(bar, "loading weights"):
            training = _load_weights(checkpoints, preset, models)
        graphs = {}
        for name, module in models.items():
            with _step(bar, f"exporting {FILES[name]}"):
                graphs[name] = export_onnx(module, interfaces[name], staging / FILES[name])
        files = {name: graph.path for name, graph in graphs.items()}
        results: list[ParityResult] = []
        if config.parity:
            sessions = {name: cpu_session(path) for name, path in files.items()}
            for inputs in sources:
                if "depth" in models:
                    with _step(bar, f"depth parity ({inputs.source.split()[0]})"):
                        results.append(depth_parity(models["depth"], sessions["depth"], inputs))
                with _step(bar, f"pixor parity ({inputs.source.split()[0]})"):
                    results.extend(pixor_parity(models["pixor"], sessions["pixor"], inputs))
            for result in results:
                log.info("%s on %s: %s %.3g (tolerance %.3g)", result.network, result.source, result.metric,
                         result.error, result.tolerance)
            require_parity(results)
        with _step(bar, "writing manifest"):
            entries = {
                name: NetworkEntry(
                    file=FILES[name],
                    inputs=interfaces[name].inputs,
                    outputs=interfaces[name].outputs,
                    parameters=sum(p.numel() for p in models[name].parameters()),
                    flops=graphs[name].flops.total,
                    flops_by_op=graphs[name].flops.by_op,
                    weights=UNTRAINED if training[name] is None else "trained",
                    training=training[name],
                )
                for name in models
            }
            manifest = build_manifest(
                preset,
                entries,
                staging,
                normalisation(preset),
                export_info={"exporter": EXPORTER, "opset": OPSET, "torch_seed": config.seed,
                             "cpu_rewrites": {name: graph.rewrites for name, graph in graphs.items()}},
                parity=(
                    {"checked": True, "results": [r.to_dict() for r in results]}
                    if config.parity
                    else {"checked": False, "results": []}
                ),
            )
            write_manifest(staging, manifest)
    verify_model_dir(staging)  # the directory as written must pass the runtime's own check
    return manifest, models, results
