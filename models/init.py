"""Pieces shared by both networks: weight initialisation (training starts from scratch here) and the
residual projection shortcut."""

from __future__ import annotations

from torch import nn


def init_conv_and_bn(root: nn.Module) -> None:
    """He (fan-out) init for every conv and transposed conv, zero biases; BatchNorm at identity."""
    for module in root.modules():
        if isinstance(module, (nn.Conv2d, nn.ConvTranspose2d)):
            nn.init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")
            if module.bias is not None:
                nn.init.zeros_(module.bias)
        elif isinstance(module, nn.BatchNorm2d):
            nn.init.ones_(module.weight)
            nn.init.zeros_(module.bias)


def projection_shortcut(in_channels: int, out_channels: int, stride: int) -> nn.Module | None:
    """ResNet's 1×1 conv + BN shortcut when a residual block changes shape, else None (identity).

    Named ``downsample`` by its callers with children 0 and 1, as in torchvision, so ResNet-18
    checkpoints load into the depth net's encoder.
    """
    if stride == 1 and in_channels == out_channels:
        return None
    return nn.Sequential(nn.Conv2d(in_channels, out_channels, 1, stride, bias=False), nn.BatchNorm2d(out_channels))
