"""Depth completion: Ma et al.'s sparse-to-dense network with a ResNet-18 encoder, GAMs and ASPP.

Layout (paper preset, 352 × 1216 input, stem stride 1)::

    conv1_d   1 → 16  ┐ 3×3, BN, ReLU          352 × 1216
    conv1_img 3 → 48  ┘ concatenated → conv1 (64)
    layer1 64, layer2 128 /2, layer3 256 /4, layer4 512 /8   (ResNet-18 BasicBlocks, no stem, no max-pool)
    conv6 512 → 512, stride 2                                 /16
    aspp (rates 2, 4, 8, 16)                                  /16
    convt5 512 → 256 ⊕ gam(layer4)  → 768                     /8
    convt4 768 → 128 ⊕ gam(layer3)  → 384                     /4
    convt3 384 → 64  ⊕ gam(layer2)  → 192                     /2
    convt2 192 → 64  ⊕ gam(layer1)  → 128                     /1
    convt1 128 → 64 (stride 1) ⊕ gam(conv1) → 128             /1
    convtf 128 → 1 (1×1)  → depth in metres

Departures from Ma et al.'s code in the ``paper`` preset, each kept on purpose: conv1_d, conv1_img and
conv6 end with ReLU where theirs end with LeakyReLU(0.2) (the decoder's convt5 … convt1 do use it, as
theirs); the image is normalised with ImageNet's statistics inside the network, where theirs reads raw
0–255 RGB; weights start He-normal (theirs: normal, σ 0.02). Why the activations stay: the layers are
shared by every preset, the shipped edge weights were trained (and are fine-tuned from ONNX) with ReLU,
and a paper-only switch would be a preset field every shipped manifest must state
(tests/test_shipped_weights.py). After a BN the two differ only on negative pre-activations.

``stem_stride`` 2 gives conv1_d and conv1_img stride 2, so every feature map is
halved (a quarter of the FLOPs of everything after the stem); the 1-channel
output is then upsampled ×2 bilinearly back to the input resolution. Inputs
whose size is not a multiple of the total stride (16 × stem_stride) are padded
bottom/right inside the network (sparse depth with 0 = "no measurement", the
normalised image with 0 = the ImageNet mean colour) and the output is cropped
back, so ONNX shapes stay static and exact.

With ``prefill_passes`` > 0 (the edge preset) the network first fills the sparse
map's gaps itself (:class:`SparsePrefill`), conv1_d reads the sparse map and
the filled one (2 → depth_stem), and convtf's output is a correction added to
the filled map. Why: trained from scratch on a few thousand frames, the plain
network reproduced even the measured depths poorly (median error 0.44 m at
0–10 m and 2.23 m at 30–40 m on the synthetic validation set, where the filled
map alone is off by 0.13 and 0.36 m on the pixels it covers); starting from the filled
map, it only has to learn where the image says the fill is wrong. The fill is
part of the graph, so the runtime and ONNX inputs are unchanged.

With ``refine_channels`` > 0 (the ``-refine`` variants of the edge and tiny
presets; stem stride 2 and the prefill) a small head
(:class:`FullResolutionRefine`) adds a second correction at the input
resolution, where every other feature map is at half of it: the coarse
correction, upsampled, smears a distant car into what is behind it. With
``refine_mode`` "convex" (the ``-convex`` variants) the same head instead
upsamples the half-resolution correction, each input pixel taking a learned
convex combination of its 3×3 neighbours (:class:`ConvexUpsample`). No shipped
model has either: trained on the frozen shipped net, neither lifted the camera
pipeline's BEV AP, nor did the ``-refine`` head trained with the net from
scratch (docs/models.md).

Module names follow Ma et al. and torchvision (``layer1.0.conv1.weight`` …), so a
torchvision-format ResNet-18 checkpoint loads into ``layer1``–``layer4``.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from models.init import init_conv_and_bn, projection_shortcut
from pipeline.presets import DepthNetConfig

log = logging.getLogger(__name__)

# ImageNet statistics on 0–1 RGB; the network scales them to 0–255 so its input is raw RGB.
IMAGENET_MEAN: tuple[float, float, float] = (0.485, 0.456, 0.406)
IMAGENET_STD: tuple[float, float, float] = (0.229, 0.224, 0.225)
# Ma et al. multiply the last 1×1 conv by 100: a unit-scale activation maps to tens of metres.
OUTPUT_SCALE = 100.0
# With the prefill the same output is a correction to the filled map, mostly small: ×100 made every
# optimizer step move all depths by metres (median error at 0–10 m grew from 0.13 m, the filled
# map's, to 0.73 m after one epoch), so the correction is scaled by 10 instead.
CORRECTION_SCALE = 10.0
LEAKY_SLOPE = 0.2


def conv_bn_relu(in_channels: int, out_channels: int, kernel_size: int = 3, stride: int = 1) -> nn.Sequential:
    """Conv (no bias, BN follows) + BN + ReLU: Ma et al.'s encoder stems and conv6 (theirs end with
    LeakyReLU(0.2); the module docstring says why ours do not)."""
    return nn.Sequential(
        nn.Conv2d(in_channels, out_channels, kernel_size, stride, kernel_size // 2, bias=False),
        nn.BatchNorm2d(out_channels),
        nn.ReLU(inplace=True),
    )


def convt_bn_relu(in_channels: int, out_channels: int, stride: int) -> nn.Sequential:
    """3×3 transposed conv + BN + LeakyReLU(0.2); stride 2 doubles height and width exactly."""
    return nn.Sequential(
        nn.ConvTranspose2d(in_channels, out_channels, 3, stride, padding=1, output_padding=stride - 1, bias=False),
        nn.BatchNorm2d(out_channels),
        nn.LeakyReLU(LEAKY_SLOPE, inplace=True),
    )


class BasicBlock(nn.Module):
    """torchvision's ResNet BasicBlock (same attribute names, so its checkpoints load)."""

    def __init__(self, in_channels: int, out_channels: int, stride: int = 1) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, out_channels, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(out_channels)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(out_channels, out_channels, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(out_channels)
        self.downsample = projection_shortcut(in_channels, out_channels, stride)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


def make_layer(in_channels: int, out_channels: int, blocks: int, stride: int) -> nn.Sequential:
    """A ResNet stage: the first block changes stride/width, the rest keep it."""
    layers = [BasicBlock(in_channels, out_channels, stride)]
    layers += [BasicBlock(out_channels, out_channels) for _ in range(blocks - 1)]
    return nn.Sequential(*layers)


class GlobalAttention(nn.Module):
    """Global attention module on a skip: the decoder's higher-level feature, globally pooled,
    goes through a 1×1 conv and a sigmoid to give one weight per skip channel.

    Why this form: it is the paper's description (pool the higher-level feature,
    1×1 conv, re-weight the skip), costs one (C_high × C_skip) matrix per skip, and
    lets the decoder's semantic context suppress skip channels that carry texture
    instead of depth edges.
    """

    def __init__(self, high_channels: int, skip_channels: int) -> None:
        super().__init__()
        self.pool = nn.AdaptiveAvgPool2d(1)
        self.conv = nn.Conv2d(high_channels, skip_channels, 1, bias=True)

    def forward(self, high: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        weights = torch.sigmoid(self.conv(self.pool(high)))
        return skip * weights


class ASPP(nn.Module):
    """Atrous spatial pyramid pooling at the bottleneck: parallel 3×3 convs with the given
    dilation rates, concatenated and fused by a 1×1 conv, added back to the input.

    Each branch has ``channels // len(rates)`` outputs, so the concatenation has the
    bottleneck's width and the fuse is a square 1×1 conv. The residual sum keeps Ma
    et al.'s direct path from conv6 to the decoder: switching ASPP off is the exact
    ablation, and switching it on starts near the same function.
    """

    def __init__(self, channels: int, rates: tuple[int, ...]) -> None:
        super().__init__()
        if not rates:
            raise ValueError("ASPP needs at least one dilation rate")
        branch = max(1, channels // len(rates))
        self.branches = nn.ModuleList(
            nn.Sequential(
                nn.Conv2d(channels, branch, 3, padding=rate, dilation=rate, bias=False),
                nn.BatchNorm2d(branch),
                nn.ReLU(inplace=True),
            )
            for rate in rates
        )
        self.fuse = nn.Sequential(
            nn.Conv2d(branch * len(rates), channels, 1, bias=False),
            nn.BatchNorm2d(channels),
            nn.ReLU(inplace=True),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.fuse(torch.cat([b(x) for b in self.branches], dim=1))


class SparsePrefill(nn.Module):
    """Fill a sparse depth map's gaps by repeated max-pooling of inverse depth; 0 stays "none".

    Each pass gives every empty pixel the largest inverse depth (the nearest return) within the
    kernel, so measured pixels never change and, at an occlusion edge, the foreground grows over
    the background, as a depth sensor's dilation does. Pixels still empty after all passes
    (above the top beam) stay 0. No parameters: the same in training, PyTorch and ONNX.
    """

    def __init__(self, passes: int, kernel: tuple[int, int]) -> None:
        super().__init__()
        self.passes = int(passes)
        self.kernel = (int(kernel[0]), int(kernel[1]))
        if self.passes < 1 or min(self.kernel) < 1 or not all(k % 2 for k in self.kernel):
            raise ValueError(f"prefill needs ≥ 1 pass and an odd kernel, got {passes} × {kernel}")

    def forward(self, sparse_depth: torch.Tensor) -> torch.Tensor:
        measured = sparse_depth > 0
        inverse = torch.where(measured, 1.0 / sparse_depth.clamp(min=1e-3), torch.zeros_like(sparse_depth))
        padding = (self.kernel[0] // 2, self.kernel[1] // 2)
        for _ in range(self.passes):
            pooled = F.max_pool2d(inverse, self.kernel, stride=1, padding=padding)
            inverse = torch.where(inverse > 0, inverse, pooled)
        return torch.where(inverse > 0, 1.0 / inverse.clamp(min=1e-6), torch.zeros_like(inverse))


class FullResolutionRefine(nn.Module):
    """A correction at the input resolution for a stem-stride-2 network (whose features are all at half of it).

    Why: upsampled ×2, the half-resolution correction blurs depth edges over two input pixels, and a car
    40 m away is 15 pixels wide in the edge view. With the exact correction to the true depth averaged to
    half resolution and upsampled like that (benchmarks/depth_bound.py), the camera pipeline's BEV AP at
    IoU 0.7 moderate on the 300 synthetic validation frames was 80.9 (34.3 beyond 35 m); at the input
    resolution, 85.4 (54.0) (docs/models.md).

    The head sees the input at full resolution (normalised image, sparse and filled depth, the current
    estimate) through one 3×3 conv, and the decoder's last features reduced by a 1×1 conv and upsampled;
    a 3×3 conv fuses both, and a 1×1 conv, initialised to zero, gives the correction: a network with the
    head starts as the same function as without it.
    """

    def __init__(self, context_channels: int, channels: int, outputs: int = 1) -> None:
        super().__init__()
        self.guide = conv_bn_relu(3 + 3, channels, 3, 1)  # image, sparse, filled, estimate
        self.context = nn.Conv2d(context_channels, channels, 1, bias=True)
        self.fuse = conv_bn_relu(2 * channels, channels, 3, 1)
        self.out = nn.Conv2d(channels, outputs, 1, bias=True)

    def zero_output(self) -> None:
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, image: torch.Tensor, depth: torch.Tensor, estimate: torch.Tensor,
                features: torch.Tensor) -> torch.Tensor:
        """image (N, 3, H, W) normalised, depth (N, 2, H, W) sparse + filled, estimate (N, 1, H, W) metres,
        features (N, C, H/2, W/2) → (N, outputs, H, W): the correction (before the correction scale), or
        the logits of :class:`ConvexUpsample`."""
        context = F.interpolate(self.context(features), scale_factor=2.0, mode="bilinear", align_corners=False)
        guide = self.guide(torch.cat((image, depth, estimate), dim=1))
        return self.out(self.fuse(torch.cat((guide, context), dim=1)))


class ConvexUpsample(nn.Module):
    """×2 upsampling of the half-resolution correction as a learned convex combination of its 3×3 neighbours.

    Why: each correction of a stem-stride-2 network covers 2×2 input pixels, and bilinear upsampling
    mixes the corrections of a car and of what is behind it across its outline. With the exact
    correction to the true depth at half resolution, upsampled bilinearly, the camera pipeline's BEV AP
    at IoU 0.7 moderate stays at 83.0 even with PIXOR fine-tuned on those maps; at the input
    resolution it reaches 91.2, as with the true depth itself (docs/measurements.md, session 21). Here
    every input pixel takes a weighted mean of the 3×3 half-resolution corrections around it, with
    weights from a softmax over logits that :class:`FullResolutionRefine`'s head predicts at the input
    resolution: a pixel on a car's outline can take the car's correction alone. The logits start as
    the log of the bilinear weights (the head's last conv at zero), so a network with this head
    starts as the same function as without it. The five neighbours outside bilinear's 2×2 start at
    e^-30, where an L1 loss gives them no gradient: trained so, the head chooses within the 2×2.
    Measured: it did not lift the camera row (docs/models.md).
    """

    # Bilinear ×2 (half-pixel centres): input pixel 2i + a samples the half-resolution grid at
    # i + (a − ½)/2, so its weights over the neighbours i − 1, i, i + 1 are these, per a.
    BILINEAR = ((0.25, 0.75, 0.0), (0.0, 0.75, 0.25))
    NEVER = -30.0  # the log of a zero bilinear weight: e^-30 ≈ 1e-13 of the mass

    def __init__(self, context_channels: int, channels: int) -> None:
        super().__init__()
        self.head = FullResolutionRefine(context_channels, channels, outputs=9)
        prior = torch.full((9, 2, 2), self.NEVER)
        for a in range(2):
            for b in range(2):
                for k, (dy, dx) in enumerate((dy, dx) for dy in range(3) for dx in range(3)):
                    weight = self.BILINEAR[a][dy] * self.BILINEAR[b][dx]
                    if weight > 0:
                        prior[k, a, b] = math.log(weight)
        self.register_buffer("prior", prior, persistent=False)

    def zero_output(self) -> None:
        self.head.zero_output()

    def forward(self, coarse: torch.Tensor, image: torch.Tensor, depth: torch.Tensor, estimate: torch.Tensor,
                features: torch.Tensor) -> torch.Tensor:
        """coarse (N, 1, h, w) correction → (N, 1, 2h, 2w); image, depth, estimate at (2h, 2w), features at (h, w)."""
        h, w = coarse.shape[-2:]
        logits = self.head(image, depth, estimate, features) + self.prior.repeat(1, h, w)[None]
        weights = torch.softmax(logits, dim=1)
        padded = F.pad(coarse, (1, 1, 1, 1), mode="replicate")  # at the border, as bilinear clamps
        neighbours = torch.cat([padded[:, :, dy : dy + h, dx : dx + w] for dy in range(3) for dx in range(3)], dim=1)
        neighbours = F.interpolate(neighbours, scale_factor=2.0, mode="nearest")
        return (weights * neighbours).sum(dim=1, keepdim=True)


class DepthCompletionNet(nn.Module):
    """Image-guided depth completion.

    forward(rgb, sparse_depth): rgb float32 (N, 3, H, W) raw 0–255 RGB; sparse_depth
    float32 (N, 1, H, W) metres, 0 = no return. Returns float32 (N, 1, H, W) depth in
    metres; in eval mode clamped to ≥ ``config.min_depth``.
    """

    def __init__(self, config: DepthNetConfig) -> None:
        super().__init__()
        self.config = config
        if config.stem_stride not in (1, 2):
            raise ValueError(f"stem_stride must be 1 or 2, got {config.stem_stride}")
        self.input_hw = (int(config.input_hw[0]), int(config.input_hw[1]))
        self.total_stride = 16 * config.stem_stride  # layer2, layer3, layer4, conv6 halve; stem maybe
        self.pad_hw = tuple(-size % self.total_stride for size in self.input_hw)
        self.register_buffer("rgb_mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1) * 255.0, persistent=False)
        self.register_buffer("rgb_std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1) * 255.0, persistent=False)

        w1, w2, w3, w4 = config.encoder_widths
        b1, b2, b3, b4 = config.encoder_blocks
        d5, d4, d3, d2, d1 = config.decoder_widths
        stem = config.depth_stem + config.image_stem
        s = config.stem_stride
        self.prefill = SparsePrefill(config.prefill_passes, config.prefill_kernel) if config.prefill_passes else None
        self.conv1_d = conv_bn_relu(1 if self.prefill is None else 2, config.depth_stem, 3, s)
        self.conv1_img = conv_bn_relu(3, config.image_stem, 3, s)
        self.layer1 = make_layer(stem, w1, b1, 1)
        self.layer2 = make_layer(w1, w2, b2, 2)
        self.layer3 = make_layer(w2, w3, b3, 2)
        self.layer4 = make_layer(w3, w4, b4, 2)
        self.conv6 = conv_bn_relu(w4, config.bottleneck_width, 3, 2)
        self.aspp = ASPP(config.bottleneck_width, tuple(config.aspp_rates)) if config.use_aspp else None

        self.convt5 = convt_bn_relu(config.bottleneck_width, d5, 2)
        self.convt4 = convt_bn_relu(d5 + w4, d4, 2)
        self.convt3 = convt_bn_relu(d4 + w3, d3, 2)
        self.convt2 = convt_bn_relu(d3 + w2, d2, 2)
        self.convt1 = convt_bn_relu(d2 + w1, d1, 1)
        self.convtf = nn.Conv2d(d1 + stem, 1, 1, bias=True)
        self.refine = None
        if config.refine_channels:
            if s != 2 or self.prefill is None:
                raise ValueError("refine_channels needs stem_stride 2 and the prefill (it refines a correction)")
            if config.refine_mode == "convex":
                self.refine = ConvexUpsample(d1 + stem, config.refine_channels)
            elif config.refine_mode == "add":
                self.refine = FullResolutionRefine(d1 + stem, config.refine_channels)
            else:
                raise ValueError(f"refine_mode {config.refine_mode!r}: use 'add' or 'convex'")
        if config.use_gam:
            self.gam5 = GlobalAttention(d5, w4)
            self.gam4 = GlobalAttention(d4, w3)
            self.gam3 = GlobalAttention(d3, w2)
            self.gam2 = GlobalAttention(d2, w1)
            self.gam1 = GlobalAttention(d1, stem)
        self._init_weights()

    def _init_weights(self) -> None:
        """He init for convs, BN at identity: training starts from scratch here (no downloads)."""
        init_conv_and_bn(self)
        # Ma et al.'s ×100 output: a small last layer keeps the initial depths in metres, not km.
        nn.init.normal_(self.convtf.weight, std=1e-3)
        # ≈ 20 m, a typical KITTI depth; with the prefill the output starts as the filled map.
        nn.init.constant_(self.convtf.bias, 0.2 if self.prefill is None else 0.0)
        if self.refine is not None:
            self.refine.zero_output()

    def _skip(self, name: str, high: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        """Concatenate a decoder feature with its (attention-weighted) encoder skip."""
        if self.config.use_gam:
            skip = getattr(self, name)(high, skip)
        return torch.cat((high, skip), dim=1)

    def forward(self, rgb: torch.Tensor, sparse_depth: torch.Tensor) -> torch.Tensor:
        height, width = self.input_hw
        exporting = torch.jit.is_tracing() or torch.onnx.is_in_onnx_export()
        wrong_size = tuple(rgb.shape[-2:]) != self.input_hw or tuple(sparse_depth.shape[-2:]) != self.input_hw
        if not exporting and wrong_size:
            raise ValueError(
                f"depth net built for {height}×{width} inputs, got rgb {tuple(rgb.shape)} "
                f"and sparse_depth {tuple(sparse_depth.shape)}"
            )
        image = (rgb - self.rgb_mean) / self.rgb_std
        prior = None if self.prefill is None else self.prefill(sparse_depth)
        depth = sparse_depth if prior is None else torch.cat((sparse_depth, prior), dim=1)
        pad_h, pad_w = self.pad_hw
        if pad_h or pad_w:
            image = F.pad(image, (0, pad_w, 0, pad_h))
            depth = F.pad(depth, (0, pad_w, 0, pad_h))

        conv1 = torch.cat((self.conv1_d(depth), self.conv1_img(image)), dim=1)
        conv2 = self.layer1(conv1)
        conv3 = self.layer2(conv2)
        conv4 = self.layer3(conv3)
        conv5 = self.layer4(conv4)
        conv6 = self.conv6(conv5)
        if self.aspp is not None:
            conv6 = self.aspp(conv6)

        convt5 = self.convt5(conv6)
        y = self._skip("gam5", convt5, conv5)
        convt4 = self.convt4(y)
        y = self._skip("gam4", convt4, conv4)
        convt3 = self.convt3(y)
        y = self._skip("gam3", convt3, conv3)
        convt2 = self.convt2(y)
        y = self._skip("gam2", convt2, conv2)
        convt1 = self.convt1(y)
        y = self._skip("gam1", convt1, conv1)
        out = (OUTPUT_SCALE if prior is None else CORRECTION_SCALE) * self.convtf(y)

        if isinstance(self.refine, ConvexUpsample):
            padded_prior = depth[:, 1:2]
            bilinear = F.interpolate(out, scale_factor=2.0, mode="bilinear", align_corners=False)
            out = self.refine(out, image, depth, padded_prior + bilinear, y)
        elif self.config.stem_stride != 1:
            # Padded size is a multiple of the stem stride: an exact ×2, pixel centres aligned.
            out = F.interpolate(out, scale_factor=float(self.config.stem_stride), mode="bilinear", align_corners=False)
        if isinstance(self.refine, FullResolutionRefine):
            padded_prior = depth[:, 1:2]
            out = out + CORRECTION_SCALE * self.refine(image, depth, padded_prior + out, y)
        if pad_h or pad_w:
            out = out[:, :, :height, :width]
        if prior is not None:
            out = out + prior
        if not self.training:
            out = torch.clamp(out, min=self.config.min_depth)
        return out


def load_resnet18_encoder(model: DepthCompletionNet, path: str | Path) -> list[str]:
    """Load ``layer1``–``layer4`` from a torchvision-format ResNet-18 checkpoint file.

    Accepts a plain state dict or one nested under ``state_dict``/``model``, with or
    without a ``module.`` prefix, with or without the batch norms' ``num_batches_tracked``
    counters (not weights). Returns the loaded parameter names. Raises
    ValueError naming the first mismatched tensor when widths differ (for example a
    narrow preset), and when the file has no layer1–layer4 weights at all.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: ResNet-18 checkpoint not found")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch raises pickle, zip and runtime errors for files not its own
        raise ValueError(f"{path}: not a PyTorch state dict, such as torchvision's resnet18-f37072fd.pth "
                         f"({type(exc).__name__})") from None
    for key in ("state_dict", "model"):
        if isinstance(state, dict) and isinstance(state.get(key), dict):
            state = state[key]
    if not isinstance(state, dict):
        raise TypeError(f"{path}: expected a state dict, got {type(state).__name__}")
    state = {k.removeprefix("module."): v for k, v in state.items()}
    ours = model.state_dict()
    wanted = {k: v for k, v in state.items() if k.split(".", 1)[0] in {"layer1", "layer2", "layer3", "layer4"}}
    if not wanted:
        raise ValueError(f"{path}: no layer1–layer4 tensors; is this a torchvision ResNet-18 checkpoint?")
    for name, tensor in wanted.items():
        if name not in ours:
            raise ValueError(
                f"{path}: {name} has no counterpart in the depth net "
                f"(encoder_blocks={model.config.encoder_blocks}; ResNet-18 is (2, 2, 2, 2))"
            )
        if tuple(ours[name].shape) != tuple(tensor.shape):
            raise ValueError(
                f"{path}: {name} has shape {tuple(tensor.shape)} but the depth net expects "
                f"{tuple(ours[name].shape)} (encoder_widths={model.config.encoder_widths}; "
                "ResNet-18 needs (64, 128, 256, 512) and a 64-channel stem)"
            )
    # Batch-norm counters (num_batches_tracked) are not weights and torchvision's published files may lack them:
    # not required; those missing keep the depth net's own values (load_state_dict(strict=False) leaves them).
    missing = [k for k in ours if k.split(".", 1)[0] in {"layer1", "layer2", "layer3", "layer4"} and k not in wanted
               and not k.endswith(".num_batches_tracked")]
    if missing:
        raise ValueError(f"{path}: checkpoint lacks {len(missing)} encoder tensors, e.g. {missing[0]}")
    model.load_state_dict(wanted, strict=False)
    log.info("loaded %d ResNet-18 encoder tensors from %s", len(wanted), path)
    return sorted(wanted)

