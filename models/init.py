"""Weight initialisation shared by the networks (training starts from scratch: no downloads here)."""

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
