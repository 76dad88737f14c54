"""The ``paper`` preset is the paper's architecture and recipe: each number pinned to where DESIGN.md states it.

DESIGN.md's sections are quoted in each test's docstring. Where DESIGN.md names an upstream network
(Ma et al.'s sparse-to-dense net, PIXOR), the number comes from that network's public code, cited too.
Networks are built on the meta device (shapes, no arithmetic), so nothing here computes a convolution.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from models import build_depth_net, build_pixor
from models.depth_net import LEAKY_SLOPE, OUTPUT_SCALE, BasicBlock, GlobalAttention
from models.losses import masked_mse
from models.pixor import Bottleneck
from models.train import RECIPES, TrainConfig
from pipeline.bev import voxelize_bev
from pipeline.presets import get_preset

PAPER = get_preset("paper")
SKIPS = {  # gamN weights the skip that convtN's output is concatenated with (models/depth_net.py layout)
    "gam5": ("convt5", "layer4"),
    "gam4": ("convt4", "layer3"),
    "gam3": ("convt3", "layer2"),
    "gam2": ("convt2", "layer1"),
    "gam1": ("convt1", "conv1"),
}


def n_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def paper_depth_net() -> nn.Module:
    with torch.device("meta"):
        return build_depth_net(PAPER).eval()


def paper_pixor() -> nn.Module:
    with torch.device("meta"):
        return build_pixor(PAPER).eval()


def record_calls(model: nn.Module, names: list[str], *inputs: torch.Tensor) -> dict[str, tuple]:
    """Run ``model`` once and return, per named module, (its input tensors, its output)."""
    calls: dict[str, tuple] = {}
    modules = dict(model.named_modules())
    hooks = [modules[name].register_forward_hook(lambda _m, args, out, name=name: calls.__setitem__(name, (args, out)))
             for name in names]
    with torch.no_grad():
        model(*inputs)
    for hook in hooks:
        hook.remove()
    return calls


def conv_flops(model: nn.Module, *inputs: torch.Tensor) -> int:
    """2 · multiply–accumulates of every Conv2d and ConvTranspose2d in one forward pass (as export/flops.py counts)."""
    macs = []

    def count(module: nn.Module, args: tuple, out: torch.Tensor) -> None:
        kernel = module.weight.shape[2] * module.weight.shape[3]
        if isinstance(module, nn.ConvTranspose2d):  # every input element scatters into C_out · k² outputs
            macs.append(args[0].numel() * module.out_channels // module.groups * kernel)
        else:  # every output element sums C_in · k² products
            macs.append(out.numel() * module.in_channels // module.groups * kernel)

    hooks = [m.register_forward_hook(count) for m in model.modules() if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d))]
    with torch.no_grad():
        model(*inputs)
    for hook in hooks:
        hook.remove()
    return 2 * sum(macs)


# --------------------------------------------------------------------------- BEV grid
def test_bev_grid_is_the_papers() -> None:
    """DESIGN.md, Conventions: "x ∈ [0, 70) m, y ∈ [-40, 40) m, z ∈ [-2.5, 1.0) m, 0.1 m cells → 800 × 700
    cells; 35 height-occupancy channels + 1 reflectance channel = 36"; pseudo and real points share them."""
    grid = PAPER.bev
    assert (grid.x_min, grid.x_max, grid.y_min, grid.y_max, grid.z_min, grid.z_max) == (0.0, 70.0, -40.0, 40.0, -2.5, 1.0)
    assert (grid.cell, grid.z_cell) == (0.1, 0.1)
    assert (grid.nz, grid.shape) == (35, (36, 800, 700))
    assert not grid.split_pseudo


def test_bev_grid_edges_on_the_paper_grid() -> None:
    """DESIGN.md, Conventions: "points outside the grid are dropped; a point on a bin edge belongs to the bin
    above it"; channel 35 = mean reflectance. The last cell of each axis is in, the far edges are out."""
    points = np.array([
        [69.95, 39.95, 0.95, 0.5],   # the last cell on every axis: column 699, row 799, slice 34
        [0.0, -40.0, -2.5, 0.25],    # the first cell, on its lower edges
        [70.0, 0.0, 0.0, 1.0],       # x = 70 m: out
        [10.0, 40.0, 0.0, 1.0],      # y = 40 m: out
        [10.0, 0.0, 1.0, 1.0],       # z = 1.0 m: out
    ], np.float32)
    bev = voxelize_bev(points, PAPER.bev)
    assert bev.shape == (36, 800, 700)
    assert bev[34, 799, 699] == 1.0 and bev[35, 799, 699] == pytest.approx(0.5)
    assert bev[0, 0, 0] == 1.0 and bev[35, 0, 0] == pytest.approx(0.25)
    assert np.count_nonzero(bev) == 4


# --------------------------------------------------------------------------- depth net: input and early fusion
def test_depth_input_is_the_kitti_depth_completion_crop_at_full_resolution() -> None:
    """DESIGN.md, Conventions: "Depth-net input: bottom 352 rows, centre 1216 columns of the image"; the paper
    runs Ma et al.'s network on it unresized (layer1 at 1216 × 352, DESIGN.md's measurements)."""
    depth = PAPER.depth
    assert PAPER.crop_hw == depth.input_hw == (352, 1216)
    assert (depth.input_scale, depth.stem_stride) == (1.0, 1)
    assert depth.prefill_passes == 0 and depth.refine_channels == 0  # Ma et al. read the sparse map as is


def test_depth_net_fuses_early_with_ma_et_al_stems() -> None:
    """DESIGN.md, Depth net: "separate first convolutions for sparse depth and RGB, concatenated: early
    fusion". Ma et al.'s code (rgbd input) splits the 64 channels of ResNet's stem 16 for depth, 48 for RGB."""
    model = paper_depth_net()
    assert (model.conv1_d[0].in_channels, model.conv1_d[0].out_channels) == (1, 16)
    assert (model.conv1_img[0].in_channels, model.conv1_img[0].out_channels) == (3, 48)
    assert model.layer1[0].conv1.in_channels == 16 + 48
    rgb, sparse = torch.empty(1, 3, 352, 1216, device="meta"), torch.empty(1, 1, 352, 1216, device="meta")
    calls = record_calls(model, ["conv1_d", "conv1_img", "layer1"], rgb, sparse)
    assert calls["conv1_d"][0][0].shape[1] == 1 and calls["conv1_img"][0][0].shape[1] == 3
    assert tuple(calls["layer1"][0][0].shape) == (1, 64, 352, 1216)  # the concatenation, at full resolution


def test_depth_decoder_activations_are_ma_et_als() -> None:
    """DESIGN.md, Depth net: "Ma et al.'s sparse-to-dense network". Their code ends every convt_bn_relu
    (convt5 … convt1) with LeakyReLU(0.2) and convtf with none. (Their conv1_d, conv1_img and conv6 end with
    LeakyReLU(0.2) too; ours with ReLU: a documented departure, models/depth_net.py says why.)"""
    model = paper_depth_net()
    for name in ("convt5", "convt4", "convt3", "convt2", "convt1"):
        activation = getattr(model, name)[-1]
        assert isinstance(activation, nn.LeakyReLU) and activation.negative_slope == LEAKY_SLOPE == 0.2, name
    assert isinstance(model.convtf, nn.Conv2d) and model.convtf.kernel_size == (1, 1)


# --------------------------------------------------------------------------- depth net: ResNet-18 encoder, decoder
def test_depth_encoder_is_resnet18_without_its_stem() -> None:
    """DESIGN.md, Depth net: "ResNet-34 replaced by ResNet-18": BasicBlocks, 2 per stage, 64/128/256/512
    channels, strides 1/2/2/2 (Ma et al. drop ResNet's 7×7 conv and max-pool: layer1 at full resolution)."""
    model = paper_depth_net()
    for index, (width, stride) in enumerate(zip((64, 128, 256, 512), (1, 2, 2, 2), strict=True), start=1):
        layer = getattr(model, f"layer{index}")
        assert len(layer) == 2 and all(isinstance(block, BasicBlock) for block in layer)
        assert layer[0].conv1.stride == (stride, stride) and layer[1].conv1.stride == (1, 1)
        assert layer[0].conv2.out_channels == layer[1].conv2.out_channels == width
    assert not any(isinstance(m, nn.MaxPool2d) for m in model.modules())
    assert (model.conv6[0].out_channels, model.conv6[0].stride) == (512, (2, 2))


def test_depth_decoder_is_ma_et_als() -> None:
    """Ma et al.'s decoder (DESIGN.md: their network): convt5 512→256, convt4 768→128, convt3 384→64,
    convt2 192→64 (3×3, stride 2), convt1 128→64 (stride 1), convtf 1×1 128→1, output ×100, clamped at
    0.9 m in evaluation."""
    model = paper_depth_net()
    shapes = [(getattr(model, f"convt{i}")[0].in_channels, getattr(model, f"convt{i}")[0].out_channels,
               getattr(model, f"convt{i}")[0].stride) for i in (5, 4, 3, 2, 1)]
    assert shapes == [(512, 256, (2, 2)), (768, 128, (2, 2)), (384, 64, (2, 2)), (192, 64, (2, 2)), (128, 64, (1, 1))]
    assert (model.convtf.in_channels, model.convtf.out_channels) == (128, 1)
    assert OUTPUT_SCALE == 100.0 and PAPER.depth.min_depth == 0.9


# --------------------------------------------------------------------------- depth net: GAMs and ASPP
def test_a_gam_sits_on_every_encoder_decoder_skip() -> None:
    """DESIGN.md, Depth net: "global attention modules ... on the encoder-decoder skips": one per skip, five,
    each reading the decoder feature (convtN's output) and weighting the encoder feature it is joined with."""
    model = paper_depth_net()
    assert PAPER.depth.use_gam
    assert sorted(name for name, m in model.named_modules() if isinstance(m, GlobalAttention)) == sorted(SKIPS)
    rgb, sparse = torch.empty(1, 3, 352, 1216, device="meta"), torch.empty(1, 1, 352, 1216, device="meta")
    calls = record_calls(model, [*SKIPS, *(d for d, _ in SKIPS.values()), "layer1", "layer2", "layer3", "layer4"],
                         rgb, sparse)
    encoder = {name: calls[name][1] for name in ("layer1", "layer2", "layer3", "layer4")}
    encoder["conv1"] = calls["layer1"][0][0]  # the stems' concatenation: layer1's input
    for gam, (decoder, skip) in SKIPS.items():
        high, low = calls[gam][0]
        assert high is calls[decoder][1], f"{gam} reads {decoder}'s output"
        assert low is encoder[skip], f"{gam} weights {skip}"


def test_a_gam_weights_each_skip_channel_by_the_globally_pooled_decoder_feature() -> None:
    """DESIGN.md, Depth net: "global pooling of a feature map, fused back to weight the features": the weights
    come from the decoder feature's global average (its layout does not matter), one per skip channel, in (0, 1)."""
    torch.manual_seed(0)
    gam = GlobalAttention(high_channels=4, skip_channels=3)
    high, skip = torch.randn(2, 4, 5, 6), torch.rand(2, 3, 5, 6) + 0.5
    out = gam(high, skip)
    weights = out / skip
    assert torch.allclose(weights, weights[:, :, :1, :1].expand_as(weights), atol=1e-6)  # one per channel
    assert ((weights > 0) & (weights < 1)).all()
    expected = torch.sigmoid(gam.conv(high.mean(dim=(2, 3), keepdim=True)))
    assert torch.allclose(weights[:, :, :1, :1], expected, atol=1e-6)
    shuffled = high.flatten(2)[:, :, torch.randperm(30)].view_as(high)  # global: where a value sits is irrelevant
    assert torch.allclose(gam(shuffled, skip), out, atol=1e-6)


def test_aspp_with_the_papers_rates_sits_between_encoder_and_decoder() -> None:
    """DESIGN.md, Depth net: "an ASPP with dilation rates 2, 4, 8, 16 between encoder and decoder": it takes
    conv6's output (the encoder's last, 1/16) and feeds convt5 (the decoder's first)."""
    model = paper_depth_net()
    assert PAPER.depth.use_aspp and tuple(PAPER.depth.aspp_rates) == (2, 4, 8, 16)
    assert [branch[0].dilation for branch in model.aspp.branches] == [(2, 2), (4, 4), (8, 8), (16, 16)]
    rgb, sparse = torch.empty(1, 3, 352, 1216, device="meta"), torch.empty(1, 1, 352, 1216, device="meta")
    calls = record_calls(model, ["conv6", "aspp", "convt5"], rgb, sparse)
    assert calls["aspp"][0][0] is calls["conv6"][1] and calls["convt5"][0][0] is calls["aspp"][1]
    assert tuple(calls["aspp"][1].shape) == (1, 512, 22, 76)


# --------------------------------------------------------------------------- depth net: loss and recipe
def test_depth_recipe_is_the_papers() -> None:
    """DESIGN.md, Training in the paper: "depth net ... batch 4, lr 1e-4 decayed every 5 epochs, 10 epochs,
    MSE loss on pixels with ground truth" (the decay factor is not stated there)."""
    epochs, batch, lr = RECIPES["depth"]
    assert (epochs, batch, lr) == (10, 4, 1e-4)
    defaults = TrainConfig.__dataclass_fields__
    assert defaults["lr_step"].default == 5 and defaults["depth_loss"].default == "mse"


def test_depth_loss_is_mse_over_pixels_with_ground_truth_only() -> None:
    """DESIGN.md, Training in the paper: "MSE loss on pixels with ground truth" (0 = none, the PNG convention)."""
    prediction = torch.tensor([[[[1.0, 2.0], [3.0, 50.0]]]])
    target = torch.tensor([[[[2.0, 0.0], [5.0, 0.0]]]])
    assert masked_mse(prediction, target).item() == pytest.approx((1.0 + 4.0) / 2)


def test_detector_recipe_is_the_papers() -> None:
    """DESIGN.md, Training in the paper: "PIXOR from scratch, Adam, batch 8, lr 1e-3 halved when validation
    loss stops falling" (the epochs are not stated there)."""
    _, batch, lr = RECIPES["detector"]
    assert (batch, lr) == (8, 1e-3)


# --------------------------------------------------------------------------- PIXOR
def test_pixor_backbone_is_pixors() -> None:
    """DESIGN.md: "PIXOR detects cars in bird's-eye view"; PIXOR's network (its public code, whose size DESIGN.md
    quotes): two 3×3 convs of 32, then [3, 6, 6, 3] bottlenecks of widths 24/48/64/96 (×4 out), each stage
    starting with stride 2 (/2, /4, /8, /16)."""
    model = paper_pixor()
    assert [conv[0].out_channels for conv in model.stem] == [32, 32]
    assert [conv[0].kernel_size for conv in model.stem] == [(3, 3), (3, 3)]
    for index, (blocks, width) in enumerate(zip((3, 6, 6, 3), (24, 48, 64, 96), strict=True), start=2):
        stage = getattr(model, f"block{index}")
        assert len(stage) == blocks and all(isinstance(block, Bottleneck) for block in stage)
        assert stage[0].conv2.stride == (2, 2) and all(block.conv2.stride == (1, 1) for block in stage[1:])
        assert stage[0].conv1.out_channels == width and stage[-1].conv3.out_channels == 4 * width


def test_pixor_top_down_path_and_header_are_pixors() -> None:
    """PIXOR's public code (the network of DESIGN.md's "2.1 M parameters"): 1×1 laterals to 196 (/16), 128 (/8)
    and 96 (/4) channels, 3×3 stride-2 transposed convs 196 → 128 → 96; a header of four 3×3 convs of 96; a
    1-channel score and a 6-channel regression (cos θ, sin θ, dx, dy, log w, log l: DESIGN.md, Conventions)."""
    model = paper_pixor()
    assert [(lat.in_channels, lat.out_channels) for lat in model.laterals] == [(192, 96), (256, 128), (384, 196)]
    assert [(up.in_channels, up.out_channels, up.stride) for up in model.upsamples] == [
        (128, 96, (2, 2)), (196, 128, (2, 2))]
    assert [(conv[0].in_channels, conv[0].out_channels, conv[0].kernel_size) for conv in model.header] == [
        (96, 96, (3, 3))] * 4
    assert (model.score.out_channels, model.regression.out_channels) == (1, 6)
    assert len(PAPER.decode.reg_mean) == len(PAPER.decode.reg_std) == 6


def test_pixor_outputs_are_a_quarter_of_the_grid() -> None:
    """DESIGN.md, Conventions: "Output maps at 1/4 resolution (200 × 175)"."""
    model = paper_pixor()
    score, regression = model(torch.empty(1, 36, 800, 700, device="meta"))
    assert tuple(score.shape) == (1, 1, 200, 175) and tuple(regression.shape) == (1, 6, 200, 175)


def test_pixor_size_and_cost_are_design_mds() -> None:
    """DESIGN.md, Measured on this kind of machine: "PIXOR at the paper grid (36×800×700): about 90 GFLOP,
    2.1 M parameters"."""
    model = paper_pixor()
    assert round(n_parameters(model) / 1e6, 1) == 2.1
    flops = conv_flops(model, torch.empty(1, 36, 800, 700, device="meta"))
    # 90.26 GFLOP, as export/flops.py counts the exported graph (the grid padded to 704 columns inside it);
    # with 96 channels on every FPN level, 88.83 GFLOP and 1.92 M parameters.
    assert round(flops / 1e9) == 90
