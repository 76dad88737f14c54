"""The weights a training run starts from (``--depth-checkpoint`` / ``--pixor-checkpoint``): a checkpoint or
an exported ``.onnx``, widened when a LiDAR-only PIXOR starts a split-input one; how they were trained (for
the new run's metadata); and which parameters and batch norms stay frozen (``--train-only``, ``--freeze-bn``).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import torch

from models import build_pixor
from models.checkpoint import (
    Checkpoint,
    check_preset_fits,
    load_checkpoint,
    load_network_weights,
)
from pipeline.errors import InputError
from pipeline.model_files import ModelFileError, load_manifest
from pipeline.presets import Preset, lidar_only, preset_from_dict

log = logging.getLogger(__name__)


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
        _check_exported_preset(path, name, preset, train_only)
        try:
            left = load_onnx_weights(net, path, optional=train_only)
        except ValueError as exc:  # a weight that does not fit; the manifest can say why
            if exported and exported != preset.name:
                raise ValueError(f"{exc}; its manifest says it was exported with --preset {exported}, and this run's "
                                 f"--preset is {preset.name}") from None
            raise
        log.info("loaded %s weights from %s", name, path)  # as a checkpoint's load says
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


# The preset fields of the heads a --train-only run adds to an exported network (the depth net's full-resolution
# refine head): the export has none, so they may differ; every other field of the network's section must not.
TRAIN_ONLY_HEAD_FIELDS: dict[str, tuple[str, ...]] = {"depth": ("refine_channels", "refine_mode")}


def _check_exported_preset(path: Path, name: str, preset: Preset, train_only: tuple[str, ...]) -> None:
    """The preset sections a checkpoint's load compares (models/checkpoint.py), from the manifest beside an
    exported ``.onnx``: a grid or crop changed keeps every weight's shape, so the graph alone cannot tell.

    With ``train_only`` the fields of the head added since the export (TRAIN_ONLY_HEAD_FIELDS) may differ: it
    starts from initialisation; the rest of the network's section must be the export's.
    """
    try:
        manifest = load_manifest(path.parent)
    except ModelFileError:  # a lone .onnx: only its weights' shapes can be checked
        return
    if not isinstance(manifest.get("preset_config"), dict) or not isinstance(manifest.get("preset"), str):
        return
    training = manifest.get("networks", {}).get(name, {}).get("training")
    exported = Checkpoint(preset=manifest["preset"], preset_config=manifest["preset_config"], state_dicts={},
                          metadata=training if isinstance(training, dict) else {}, path=path)
    check_preset_fits(exported, name, preset, ignored=TRAIN_ONLY_HEAD_FIELDS if train_only else None)


def _bev_channels(path: Path) -> int | None:
    """The BEV channels a PIXOR checkpoint or ``pixor.onnx`` reads (None if it says not)."""
    try:
        if path.suffix == ".onnx":
            from models.onnx_weights import read_onnx

            graph = read_onnx(path, load_external_data=False).graph
            # The lowered graphs take the BEV in channel pieces (bev[0:16], bev[16:19]): their sum is the grid's.
            pieces = [i for i in graph.input if i.name.startswith("bev")] or list(graph.input[:1])
            return sum(i.type.tensor_type.shape.dim[1].dim_value for i in pieces)
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
