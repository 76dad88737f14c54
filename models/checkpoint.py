"""Checkpoint files shared by training and export.

A checkpoint is a ``torch.save`` of a plain dict::

    {"format": "lowres3d-checkpoint/1", "preset": name, "preset_config": preset.to_dict(),
     "state_dicts": {"depth": {...}, "pixor": {...}},  # one or both networks
     "metadata": {...}}                                # JSON-able: epochs, losses, data, git commit …

Plain tensors and builtins only, so it loads with ``torch.load(weights_only=True)``.
By convention a checkpoint directory holds ``depth.pt`` and/or ``pixor.pt``.
"""

from __future__ import annotations

import contextlib
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import nn

from pipeline.presets import Preset, preset_from_dict, registered_preset

log = logging.getLogger(__name__)

FORMAT = "lowres3d-checkpoint/1"
CHECKPOINT_FILES: dict[str, str] = {"depth": "depth.pt", "pixor": "pixor.pt"}


@dataclass
class Checkpoint:
    """A loaded checkpoint: which preset, the networks' state dicts, free-form JSON-able metadata."""

    preset: str
    preset_config: dict
    state_dicts: dict[str, dict[str, torch.Tensor]]
    metadata: dict = field(default_factory=dict)
    path: Path | None = None


def save_checkpoint(path: str | Path, preset: Preset, networks: dict[str, nn.Module], metadata: dict) -> Path:
    """Write the state dicts of ``networks`` (name → module) with the preset and metadata."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": FORMAT,
        "preset": preset.name,
        "preset_config": preset.to_dict(),
        "state_dicts": {name: {k: v.detach().cpu() for k, v in module.state_dict().items()}  # GPU runs too
                        for name, module in networks.items()},
        "metadata": dict(metadata),
    }
    return save_atomic(payload, path)


def save_atomic(payload: object, path: Path) -> Path:
    """``torch.save`` into ``path`` whole or not at all: written beside it as ``NAME.tmp``, flushed to the disk,
    then renamed over it. A process killed meanwhile, or a full disk, leaves the earlier file as it was (and
    no ``.tmp`` when the error can be caught). Raises OSError naming ``path`` when it cannot be written."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        # Through a file of our own: torch.save given a path reports a full disk as a RuntimeError without errno.
        with open(tmp, "wb") as handle:
            torch.save(payload, handle)
            handle.flush()
            os.fsync(handle.fileno())  # renamed only once the bytes are on the disk: a node failure keeps one whole
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        # The error that stopped the save is the one to report: torch's zip writer, closed on the way out,
        # raises a RuntimeError of its own over a write error or a Ctrl-C / SIGTERM that came mid-write.
        cause = _wrapped(exc) if isinstance(exc, RuntimeError) else exc
        if isinstance(cause, OSError):
            raise OSError(cause.errno, cause.strerror or str(cause), str(path)) from exc
        if isinstance(cause, KeyboardInterrupt):
            raise cause.with_traceback(None) from None
        raise
    return path


def _wrapped(exc: BaseException) -> BaseException:
    """The write error or interruption a RuntimeError of torch's was raised while handling (its chain of
    "during handling of …" contexts), else ``exc`` itself."""
    context = exc.__context__
    while context is not None and context is not exc:
        if isinstance(context, (OSError, KeyboardInterrupt)):
            return context
        context = context.__context__
    return exc


def write_text_atomic(path: Path, text: str) -> None:
    """Replace a small text file whole (beside it as ``NAME.tmp``, then renamed): a reader, or a run killed
    meanwhile, never sees it cut short."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise


def load_checkpoint(path: str | Path) -> Checkpoint:
    """Read a checkpoint written by :func:`save_checkpoint`; ValueError if it is not one."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: checkpoint not found")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises pickle, zip and runtime errors for files that are not its own
        raise ValueError(f"{path}: not a lowres3d checkpoint (torch.load cannot read it: {type(exc).__name__})") from exc
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise ValueError(f"{path}: not a lowres3d checkpoint (expected format {FORMAT!r})")
    return Checkpoint(
        preset=payload["preset"],
        preset_config=payload["preset_config"],
        state_dicts=payload["state_dicts"],
        metadata=payload.get("metadata", {}),
        path=path,
    )


# The preset sections each network's weights depend on: its layers, and what its input and output mean.
NETWORK_SECTIONS: dict[str, tuple[str, ...]] = {
    "depth": ("depth", "crop_hw"),
    "pixor": ("pixor", "bev", "decode"),
}
# Fields of those sections that only say which pseudo points the pipeline builds from the depth map (the
# range kept), not what the depth net computes: a depth net may be exported with another range (``-near35``).
PSEUDO_RANGE_FIELDS: dict[str, tuple[str, ...]] = {"depth": ("max_depth",)}


def _as_lists(value: object) -> object:
    """Tuples → lists recursively, so a preset dict compares equal to its JSON/pickled form."""
    if isinstance(value, dict):
        return {k: _as_lists(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_as_lists(v) for v in value]
    return value


def _check_pseudo_range(checkpoint: Checkpoint, network: str, saved_config: dict, preset: Preset) -> None:
    """ValueError for a PIXOR that learned on pseudo points (a ``pseudo`` or joint run) loaded under a preset that
    keeps them up to another depth: the range is no part of its layers, but it is of what its BEV holds
    (``-near35``'s camera PIXOR, exported as ``edge-split``, lost 4 BEV AP on points beyond 35 m it never saw)."""
    metadata = checkpoint.metadata or {}
    if network != "pixor" or not (metadata.get("task") == "joint" or metadata.get("input") == "pseudo"):
        return
    depth = saved_config.get("depth") if isinstance(saved_config, dict) else None
    trained = depth.get("max_depth") if isinstance(depth, dict) else None
    if trained is not None and trained != preset.depth.max_depth:
        way_out = (f"give --preset {checkpoint.preset}" if _is_registered(checkpoint.preset)
                   else f"give the preset file it was trained with ({PRESET_FILE_HINT})")
        raise ValueError(f"{checkpoint.path}: its PIXOR learned on pseudo points up to {trained:g} m (preset "
                         f"{checkpoint.preset!r}); preset {preset.name!r} keeps them up to {preset.depth.max_depth:g} "
                         f"m, so its BEV would hold points it never saw: {way_out}")


# How a user gets back the preset file a checkpoint (or an exported model) was trained with: the preset_config it
# records is a whole preset as a preset file holds it (docs/models.md, "Adding a preset").
PRESET_FILE_HINT = ("its preset_config, written to a .json file as it stands, is one: docs/models.md, "
                    "\"Adding a preset\"")


def _is_registered(name: str) -> bool:
    """Whether a --preset of this name means a preset here (else it was a preset file's, or another copy's)."""
    try:
        registered_preset(name)
    except ValueError:
        return False
    return True


def check_preset_fits(checkpoint: Checkpoint, network: str, preset: Preset,
                      ignored: dict[str, tuple[str, ...]] | None = None) -> None:
    """ValueError unless ``checkpoint``'s ``network`` was trained with ``preset`` as far as its weights mean:
    the preset sections ``NETWORK_SECTIONS[network]`` are compared, but for the pseudo range's fields and the
    ``ignored`` ones (section → fields), and a PIXOR's pseudo range.

    Also for an exported ``.onnx`` (its manifest's preset and preset_config, a checkpoint of no state dicts).
    """
    saved_config = checkpoint.preset_config
    try:  # a checkpoint from before a preset field existed holds that field's default
        saved_config = preset_from_dict(saved_config).to_dict()
    except ValueError:  # not a whole preset: compare what there is
        pass
    saved, wanted = _as_lists(saved_config), _as_lists(preset.to_dict())
    for config in (saved, wanted):
        for section in config:
            left_out = PSEUDO_RANGE_FIELDS.get(section, ()) + (ignored or {}).get(section, ())
            if left_out and isinstance(config.get(section), dict):
                config[section] = {k: v for k, v in config[section].items() if k not in left_out}
    compared = NETWORK_SECTIONS.get(network, tuple(wanted))
    differing = [key for key in compared if saved.get(key) != wanted.get(key)]
    changed = [(f"{key}.{field}", saved[key].get(field), value) for key in differing
               if isinstance(saved.get(key), dict) and isinstance(wanted.get(key), dict)
               for field, value in wanted[key].items() if saved[key].get(field) != value]
    fields = [f"{name}: {then!r} then, {now!r} now" for name, then, now in changed]
    if differing and not _is_registered(checkpoint.preset):
        # A preset file's: --preset cannot name it, and under the same name it is the file that was edited since
        # (the earlier-lowres3d story below would send the user after a code change that never was).
        first = (f"{changed[0][0]} {changed[0][1]!r} in the checkpoint, {changed[0][2]!r} in {preset.name!r}"
                 if changed else ", ".join(differing))
        raise ValueError(
            f"{checkpoint.path}: trained with preset {checkpoint.preset!r}, not a registered one (a preset file's), "
            f"whose preset_config differs from preset {preset.name!r} given ({first}): give the preset file it was "
            f"trained with ({PRESET_FILE_HINT})"
        )
    if differing and checkpoint.preset == preset.name:  # the preset itself changed since the checkpoint was made
        raise ValueError(
            f"{checkpoint.path}: trained with preset {preset.name!r} as an earlier lowres3d defined it "
            f"({'; '.join(fields) or ', '.join(differing)}); this version builds another network under that name, "
            "so the weights do not fit it: train again, or export it with the lowres3d it was trained with"
        )
    if differing:
        raise ValueError(
            f"{checkpoint.path}: trained with preset {checkpoint.preset!r} whose {', '.join(differing)} "
            f"configuration differs from the requested preset {preset.name!r}; give --preset {checkpoint.preset} "
            f"with it, or a checkpoint trained with {preset.name}"
        )
    _check_pseudo_range(checkpoint, network, saved_config, preset)


def load_network_weights(model: nn.Module, checkpoint: Checkpoint, network: str, preset: Preset) -> None:
    """Load ``checkpoint.state_dicts[network]`` into ``model`` after checking the preset matches.

    Only the sections that give this network's weights their meaning are compared (see
    ``NETWORK_SECTIONS``): a PIXOR stays valid when the preset's depth net changes.
    """
    check_preset_fits(checkpoint, network, preset)
    if network not in checkpoint.state_dicts:
        raise ValueError(
            f"{checkpoint.path}: no {network!r} weights (it holds {', '.join(checkpoint.state_dicts) or 'none'})"
        )
    model.load_state_dict(checkpoint.state_dicts[network], strict=True)
    log.info("loaded %s weights from %s", network, checkpoint.path)


def find_checkpoints(directory: str | Path) -> dict[str, Path]:
    """The checkpoint files present in ``directory`` (network → path); error if there are none."""
    directory = Path(directory)
    if not directory.is_dir():
        raise FileNotFoundError(f"{directory}: checkpoint directory not found")
    found = {name: directory / file for name, file in CHECKPOINT_FILES.items() if (directory / file).is_file()}
    if not found:
        raise FileNotFoundError(
            f"{directory}: no checkpoints; expected {' and/or '.join(CHECKPOINT_FILES.values())}"
        )
    return found
