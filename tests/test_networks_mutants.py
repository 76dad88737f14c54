"""The PyTorch networks' behaviour that the layer-shape and shipped-weight tests leave open (mutation audit of
models/depth_net.py, models/pixor.py): where each starts before training, which input sizes and configurations
they refuse, how PIXOR pads and crops a grid, and what the full-resolution head reads."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from models import build_depth_net, build_pixor
from models.depth_net import ASPP, ConvexUpsample, DepthCompletionNet, FullResolutionRefine, SparsePrefill
from models.pixor import Pixor
from pipeline.presets import get_preset

TINY = get_preset("tiny")
HEIGHT, WIDTH = TINY.depth.input_hw


def _beams() -> torch.Tensor:
    """A sparse map with a beam every 6 rows, 5 m at the left to 60 m at the right."""
    sparse = torch.zeros(1, 1, HEIGHT, WIDTH)
    sparse[..., ::6, :] = torch.linspace(5.0, 60.0, WIDTH)
    return sparse


def _rgb() -> torch.Tensor:
    return torch.rand(1, 3, HEIGHT, WIDTH, generator=torch.Generator().manual_seed(7)) * 255


# --------------------------------------------------------------------------- where training starts
def test_a_depth_net_without_the_prefill_starts_near_20_m_everywhere() -> None:
    """Ma et al.'s ×100 output starts at a typical KITTI depth, 20 m, with a spread of centimetres, not at 0 m
    (the clamp) or hundreds of metres (mutants: convtf's bias 0, its weights left at He scale)."""
    torch.manual_seed(0)
    model = DepthCompletionNet(replace(TINY.depth, prefill_passes=0)).eval()
    with torch.no_grad():
        depth = model(_rgb(), _beams())
    assert depth.median().item() == pytest.approx(20.0, abs=1.0)
    assert 15.0 < depth.min().item() and depth.max().item() < 25.0


def test_a_prefill_net_starts_as_its_filled_map() -> None:
    """With the prefill the output is a correction to the filled map and starts near zero (mutant: the no-prefill
    net's 0.2 bias, which would add 2 m everywhere)."""
    torch.manual_seed(0)
    model = build_depth_net(TINY).eval()
    sparse = _beams()
    with torch.no_grad():
        depth, filled = model(_rgb(), sparse), model.prefill(sparse)
    covered = filled > 0
    assert abs((depth - filled)[covered].median().item()) < 0.5


def test_pixor_starts_at_the_prior_in_every_cell() -> None:
    """RetinaNet's start: small score and regression weights, so every cell's score is the prior π = 0.01 (not
    only the bias) and the regression starts near 0 (mutants: either left at He scale)."""
    torch.manual_seed(0)
    model = build_pixor(TINY).eval()
    bev = (torch.rand(1, *TINY.bev.shape, generator=torch.Generator().manual_seed(1)) < 0.02).float()
    with torch.no_grad():
        score, regression = model(bev)
    assert 0.005 < score.min().item() and score.max().item() < 0.02
    assert regression.abs().max().item() < 1.0


@pytest.mark.parametrize("network", ["depth", "pixor"])
def test_convolutions_start_he_normal_with_zero_biases(network: str) -> None:
    """Both networks train from scratch with He (fan-out) weights and zero biases (the depth net's docstring: 'weights
    start He-normal'); the mutant left torch's default init (a third of the scale, random biases)."""
    torch.manual_seed(0)
    model = build_depth_net(TINY) if network == "depth" else build_pixor(TINY)
    own_init = {"convtf", "score", "regression"}  # set on purpose after the He init
    checked = 0
    for name, module in model.named_modules():
        if not isinstance(module, nn.Conv2d | nn.ConvTranspose2d) or name in own_init:
            continue
        if module.bias is not None:
            assert not module.bias.any(), name
        if module.weight.numel() >= 500:  # enough weights for the standard deviation to be within 20 %
            fan_out = module.weight.shape[0] * module.weight.shape[2] * module.weight.shape[3]
            assert module.weight.std().item() == pytest.approx(math.sqrt(2.0 / fan_out), rel=0.2), name
            checked += 1
    assert checked >= 5


# --------------------------------------------------------------------------- what is refused
@pytest.mark.parametrize(("rgb_hw", "sparse_hw"), [((HEIGHT, WIDTH), (HEIGHT - 8, WIDTH)),
                                                   ((HEIGHT, WIDTH - 16), (HEIGHT, WIDTH))])
def test_the_depth_net_names_a_wrong_size_of_either_input(rgb_hw: tuple[int, int], sparse_hw: tuple[int, int]) -> None:
    """One input of the built size does not let the other through (mutants: the check needing both wrong, or
    looking at the image alone): a one-line ValueError, not torch's error from deep inside the network."""
    model = build_depth_net(TINY).eval()
    with pytest.raises(ValueError, match=rf"built for {HEIGHT}×{WIDTH} inputs, got rgb"):
        model(torch.zeros(1, 3, *rgb_hw), torch.zeros(1, 1, *sparse_hw))


def test_pixor_refuses_a_grid_it_would_otherwise_run_on_silently() -> None:
    """A grid 16 rows taller than the built one pads to a multiple of 16 all the same, and would give a score map
    cropped to the built size without complaint (mutant: the check removed)."""
    model = build_pixor(TINY).eval()
    with pytest.raises(ValueError, match=r"PIXOR built for a \(200, 176\) grid, got bev \(1, 8, 216, 176\)"):
        model(torch.zeros(1, TINY.bev.channels, TINY.bev.ny + 16, TINY.bev.nx))


@pytest.mark.parametrize("stride", [16, 1, 3])
def test_pixor_output_strides_other_than_2_4_8_are_refused(stride: int) -> None:
    """1 and 3 are no stage's stride, and /16 would leave the FPN one level with no top-down path (mutant: 16
    accepted)."""
    with pytest.raises(ValueError, match=r"output_stride must be one of \(2, 4, 8\), got"):
        Pixor(replace(TINY.pixor, output_stride=stride), in_channels=8, input_hw=(208, 176))


@pytest.mark.parametrize("stride", [0, 3, 4])
def test_depth_stem_strides_other_than_1_and_2_are_refused(stride: int) -> None:
    """The output is upsampled back by the stem stride alone: only ×1 and ×2 are designed (mutant: 4 accepted)."""
    with pytest.raises(ValueError, match=rf"stem_stride must be 1 or 2, got {stride}"):
        DepthCompletionNet(replace(TINY.depth, stem_stride=stride))


@pytest.mark.parametrize(("passes", "kernel"), [(0, (5, 3)), (2, (4, 3)), (2, (5, 2))])
def test_prefill_refuses_no_pass_and_even_kernels(passes: int, kernel: tuple[int, int]) -> None:
    """An even kernel has no centre pixel and shifts the map by half a pixel (mutants: passes 0 allowed, the
    odd-kernel check dropped)."""
    with pytest.raises(ValueError, match="prefill needs ≥ 1 pass and an odd kernel"):
        SparsePrefill(passes, kernel)


def test_prefill_keeps_a_return_nearer_than_a_metre() -> None:
    """Measured pixels never change, however near (the reciprocal's guard is at 1 mm; mutant: at 1 m, so a 0.3 m
    return, and the gap it fills, became 1 m)."""
    sparse = torch.zeros(1, 1, 5, 5)
    sparse[0, 0, 2, 2] = 0.3
    filled = SparsePrefill(1, (3, 3))(sparse)[0, 0]
    assert torch.allclose(filled[1:4, 1:4], torch.full((3, 3), 0.3))


def test_aspp_without_rates_is_named() -> None:
    """Mutant: the check removed, leaving Python's ZeroDivisionError from the branch width."""
    with pytest.raises(ValueError, match="ASPP needs at least one dilation rate"):
        ASPP(16, ())


# --------------------------------------------------------------------------- padding and cropping
def test_pixor_pads_a_grid_bottom_and_right_and_keeps_the_top_left_outputs() -> None:
    """tiny's 200 rows are padded to 208 inside the network and the FPN's output is cropped back to 50 rows: the
    top 50 rows of the same weights run on the grid zero-padded below, so output cell (i, j) stays over grid cells
    (4i, 4j) (mutants: pad above, or keep the bottom rows: every detection 2 cells off)."""
    torch.manual_seed(0)
    model = build_pixor(TINY).eval()
    assert model.pad_hw == (8, 0)
    twin = Pixor(TINY.pixor, in_channels=TINY.bev.channels, input_hw=(TINY.bev.ny + 8, TINY.bev.nx)).eval()
    twin.load_state_dict(model.state_dict())
    bev = (torch.rand(1, *TINY.bev.shape, generator=torch.Generator().manual_seed(2)) < 0.05).float()
    seen: list[torch.Tensor] = []
    for net in (model, twin):
        net.header.register_forward_hook(lambda _m, args, _out: seen.append(args[0]))
    with torch.no_grad():
        model(bev)
        twin(F.pad(bev, (0, 0, 0, 8)))
    cropped, padded = seen
    assert cropped.shape[-2:] == (50, 44) and padded.shape[-2:] == (52, 44)
    # The header's own 3×3 convs then see the cropped grid's edge as zero, as at its other edges.
    torch.testing.assert_close(cropped, padded[..., :50, :])


# --------------------------------------------------------------------------- the full-resolution head
@pytest.mark.parametrize("preset_name", ["tiny-refine", "tiny-convex"])
def test_the_refine_head_reads_the_current_estimate_and_a_bilinear_context(preset_name: str) -> None:
    """The head's guide sees image, sparse and filled depth and the current estimate in metres (filled map plus
    the coarse correction, upsampled): what the output is before the head's own correction (mutants: the estimate
    without the filled map). The decoder's context reaches it upsampled bilinearly (mutant: nearest)."""
    torch.manual_seed(0)
    model = build_depth_net(get_preset(preset_name)).eval()
    head = model.refine.head if isinstance(model.refine, ConvexUpsample) else model.refine
    assert isinstance(head, FullResolutionRefine)
    seen: dict[str, tuple] = {}
    hooks = [head.guide.register_forward_hook(lambda _m, args, _out: seen.__setitem__("guide", args)),
             head.fuse.register_forward_hook(lambda _m, args, _out: seen.__setitem__("fuse", args)),
             head.register_forward_hook(lambda _m, args, _out: seen.__setitem__("head", args))]
    with torch.no_grad():
        depth = model(_rgb(), _beams())  # the head's output starts at zero: the estimate is the output
        features = seen["head"][3]
        context = F.interpolate(head.context(features), scale_factor=2.0, mode="bilinear", align_corners=False)
    for hook in hooks:
        hook.remove()
    estimate = seen["guide"][0][:, 5:6, :HEIGHT, :WIDTH]
    torch.testing.assert_close(estimate.clamp(min=TINY.depth.min_depth), depth, atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(seen["fuse"][0][:, head.fuse[0].in_channels // 2 :], context)


def test_the_add_heads_correction_is_in_the_coarse_corrections_units() -> None:
    """One unit of the head's output moves the depth by CORRECTION_SCALE (10) metres, as one of convtf's does
    with the prefill (mutant: the head's output added unscaled, a tenth of the step the head was trained with)."""
    torch.manual_seed(0)
    model = build_depth_net(get_preset("tiny-refine")).eval()
    rgb, sparse = _rgb(), _beams()
    with torch.no_grad():
        before = model(rgb, sparse)
        model.refine.out.bias.fill_(0.1)
        after = model(rgb, sparse)
    assert torch.allclose(after - before, torch.ones_like(before), atol=1e-4)


# --------------------------------------------------------------------------- ResNet-18 encoder files
def test_a_resnet18_file_saved_from_data_parallel_loads_and_one_lacking_a_tensor_is_named(tmp_path) -> None:
    """torch.nn.DataParallel saves every name under ``module.``: the prefix is dropped (mutant: kept, 'no layer1–layer4
    tensors'). A file lacking one encoder tensor is refused by name, not loaded half (mutant: the check removed)."""
    from models.depth_net import load_resnet18_encoder
    from tests.test_models import torchvision_resnet18_state

    state = torchvision_resnet18_state()
    path = tmp_path / "parallel.pth"
    torch.save({f"module.{name}": tensor for name, tensor in state.items()}, path)
    model = build_depth_net(get_preset("paper"))
    loaded = load_resnet18_encoder(model, path)
    assert torch.equal(model.state_dict()["layer4.1.conv2.weight"], state["layer4.1.conv2.weight"])
    assert len(loaded) == sum(name.startswith("layer") for name in state)
    del state["layer3.0.downsample.0.weight"]
    torch.save(state, path)
    with pytest.raises(ValueError, match=r"parallel\.pth: checkpoint lacks 1 encoder tensors, e\.g\. layer3\.0\.downsample"):
        load_resnet18_encoder(build_depth_net(get_preset("paper")), path)
