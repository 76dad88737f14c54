"""PIXOR: single-stage car detector on the bird's-eye-view occupancy tensor.

Layout (paper preset, input 36 × 800 × 700)::

    stem      two 3×3 conv, 32 channels, BN, ReLU          /1
    block2    3 bottlenecks, width 24 → 96,  first stride 2  /2
    block3    6 bottlenecks, width 48 → 192, first stride 2  /4
    block4    6 bottlenecks, width 64 → 256, first stride 2  /8
    block5    3 bottlenecks, width 96 → 384, first stride 2  /16
    FPN       1×1 laterals to the level's width (fpn_channels: one for all levels, or one per level);
              top-down 3×3 stride-2 transposed convs, summed, from /16 down to /4 (output_stride)
    header    4 × (3×3 conv 96, BN, ReLU)
    score     3×3 conv → 1, sigmoid (bias = −log((1 − π)/π), π = 0.01)
    regression 3×3 conv → 6 (cos θ, sin θ, dx, dy, log w, log l, normalised)

The grid's 700 columns are not a multiple of the total stride 16 (its 800 rows
are), so the input is zero-padded bottom/right inside the network (zero = empty cell) and the outputs
are cropped to exactly (ny / output_stride, nx / output_stride): static, exact
ONNX shapes.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from models.init import init_conv_and_bn, projection_shortcut
from pipeline.presets import PIXOR_STAGE_STRIDES as STAGE_STRIDES  # cumulative stride of block2 … block5
from pipeline.presets import PixorConfig


def conv3x3_bn_relu(in_channels: int, out_channels: int) -> nn.Sequential:
    """3×3 conv (no bias: BN follows) + BN + ReLU."""
    return nn.Sequential(
        nn.Conv2d(in_channels, out_channels, 3, 1, 1, bias=False), nn.BatchNorm2d(out_channels), nn.ReLU(inplace=True)
    )


class Bottleneck(nn.Module):
    """ResNet bottleneck: 1×1 reduce, 3×3 (carries the stride), 1×1 expand, residual."""

    def __init__(self, in_channels: int, width: int, expansion: int, stride: int) -> None:
        super().__init__()
        out_channels = width * expansion
        self.conv1 = nn.Conv2d(in_channels, width, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = nn.Conv2d(width, width, 3, stride, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(width)
        self.conv3 = nn.Conv2d(width, out_channels, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(out_channels)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = projection_shortcut(in_channels, out_channels, stride)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        return self.relu(out + identity)


def fpn_widths(fpn_channels: int | tuple[int, ...], levels: int) -> tuple[int, ...]:
    """Output channels of each FPN level, from the output level up to /16.

    ``fpn_channels`` is one width for every level, or one per level in that order: PIXOR's own
    top-down path narrows towards the output, 196 → 128 → 96 (``(96, 128, 196)`` here).
    """
    if isinstance(fpn_channels, int):
        return (fpn_channels,) * levels
    widths = tuple(int(width) for width in fpn_channels)
    if len(widths) != levels:
        raise ValueError(
            f"fpn_channels {widths} gives {len(widths)} widths, but the FPN has {levels} levels "
            f"(output stride to /{STAGE_STRIDES[-1]}): give one width per level or a single int"
        )
    return widths


class Pixor(nn.Module):
    """PIXOR backbone + FPN + header.

    forward(bev): bev float32 (N, C, ny, nx) → (score, regression), score float32
    (N, 1, ny/s, nx/s) after sigmoid, regression float32 (N, 6, ny/s, nx/s), s =
    ``config.output_stride``. ``forward_logits`` returns the score before the sigmoid
    (what the focal loss takes, for numerical stability).
    """

    def __init__(self, config: PixorConfig, in_channels: int, input_hw: tuple[int, int]) -> None:
        super().__init__()
        self.config = config
        self.input_hw = (int(input_hw[0]), int(input_hw[1]))
        stride = config.output_stride
        if stride not in STAGE_STRIDES[:-1]:
            raise ValueError(f"output_stride must be one of {STAGE_STRIDES[:-1]}, got {stride}")
        if any(size % stride for size in self.input_hw):
            raise ValueError(
                f"BEV grid {self.input_hw[0]}×{self.input_hw[1]} is not divisible by the output stride {stride}: "
                "choose the grid extent so that ny and nx are multiples of it"
            )
        self.output_hw = (self.input_hw[0] // stride, self.input_hw[1] // stride)
        total = STAGE_STRIDES[-1]
        self.pad_hw = tuple(-size % total for size in self.input_hw)

        self.stem = nn.Sequential(
            conv3x3_bn_relu(in_channels, config.stem_channels), conv3x3_bn_relu(config.stem_channels, config.stem_channels)
        )
        channels = config.stem_channels
        stages = []
        stage_out: list[int] = []
        for width, blocks in zip(config.stage_widths, config.stage_blocks, strict=True):
            layers = [Bottleneck(channels, width, config.expansion, 2)]
            channels = width * config.expansion
            layers += [Bottleneck(channels, width, config.expansion, 1) for _ in range(blocks - 1)]
            stages.append(nn.Sequential(*layers))
            stage_out.append(channels)
        self.block2, self.block3, self.block4, self.block5 = stages

        # FPN: laterals on every stage from the output level up to /16, top-down transposed convs, each
        # from a level's width to the next finer level's.
        self.first_level = STAGE_STRIDES.index(stride)
        widths = fpn_widths(config.fpn_channels, len(stage_out) - self.first_level)
        self.laterals = nn.ModuleList(
            nn.Conv2d(c, width, 1) for c, width in zip(stage_out[self.first_level :], widths, strict=True)
        )
        self.upsamples = nn.ModuleList(
            nn.ConvTranspose2d(widths[level + 1], widths[level], 3, 2, padding=1, output_padding=1)
            for level in range(len(widths) - 1)
        )

        header = []
        previous = widths[0]
        for _ in range(config.header_convs):
            header.append(conv3x3_bn_relu(previous, config.header_channels))
            previous = config.header_channels
        self.header = nn.Sequential(*header)
        self.score = nn.Conv2d(previous, 1, 3, 1, 1)
        self.regression = nn.Conv2d(previous, 6, 3, 1, 1)
        self._init_weights()

    def _init_weights(self) -> None:
        """He init; score bias for the prior π so the focal loss starts balanced (RetinaNet)."""
        init_conv_and_bn(self)
        nn.init.normal_(self.score.weight, std=0.01)
        nn.init.constant_(self.score.bias, -math.log((1.0 - self.config.prior) / self.config.prior))
        nn.init.normal_(self.regression.weight, std=0.01)

    def forward_logits(self, bev: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(score logits (N, 1, h, w), regression (N, 6, h, w)), h, w = grid / output_stride."""
        exporting = torch.jit.is_tracing() or torch.onnx.is_in_onnx_export()
        if not exporting and tuple(bev.shape[-2:]) != self.input_hw:
            raise ValueError(f"PIXOR built for a {self.input_hw} grid, got bev {tuple(bev.shape)}")
        pad_h, pad_w = self.pad_hw
        if pad_h or pad_w:
            bev = F.pad(bev, (0, pad_w, 0, pad_h))
        x = self.stem(bev)
        features = []
        for stage in (self.block2, self.block3, self.block4, self.block5):
            x = stage(x)
            features.append(x)
        features = features[self.first_level :]
        top = self.laterals[-1](features[-1])
        for level in range(len(features) - 2, -1, -1):
            top = self.laterals[level](features[level]) + self.upsamples[level](top)
        out_h, out_w = self.output_hw
        top = top[:, :, :out_h, :out_w]
        x = self.header(top)
        return self.score(x), self.regression(x)

    def forward(self, bev: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        logits, regression = self.forward_logits(bev)
        return torch.sigmoid(logits), regression
