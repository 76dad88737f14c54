"""PyTorch networks of lowres3d, built from a preset through a small name → builder registry."""

from __future__ import annotations

import sys
from collections.abc import Callable

from pipeline.cli import ctrl_c_held_while_loading, missing_extra
from pipeline.errors import TORCH_MISSING

# Python imports this package on its way to run `python -m models.…`, with sys.argv[0] "-m" until it has found the
# module (documented): only then is Ctrl-C here a command's.
with ctrl_c_held_while_loading(sys.argv[:1] == ["-m"]):
    try:
        from torch import nn
    except ModuleNotFoundError as exc:  # every `python -m models.…` command passes through here first
        raise missing_extra(TORCH_MISSING) from exc  # one error line, exit status 2
    from models.depth_net import DepthCompletionNet
    from models.pixor import Pixor
    from pipeline.presets import Preset


def build_depth_net(preset: Preset) -> DepthCompletionNet:
    """The depth-completion network of ``preset`` (input ``preset.depth.input_hw``)."""
    return DepthCompletionNet(preset.depth)


def build_pixor(preset: Preset) -> Pixor:
    """PIXOR for ``preset``'s BEV grid."""
    return Pixor(preset.pixor, in_channels=preset.bev.channels, input_hw=(preset.bev.ny, preset.bev.nx))


NETWORKS: dict[str, Callable[[Preset], nn.Module]] = {
    "depth": build_depth_net,
    "pixor": build_pixor,
}


def build_network(name: str, preset: Preset) -> nn.Module:
    """Build a network by registry name ("depth" or "pixor")."""
    try:
        builder = NETWORKS[name]
    except KeyError:
        raise ValueError(f"unknown network {name!r}; choose one of {', '.join(NETWORKS)}") from None
    return builder(preset)


__all__ = ["NETWORKS", "DepthCompletionNet", "Pixor", "build_depth_net", "build_network", "build_pixor"]
