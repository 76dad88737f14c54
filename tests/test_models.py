"""The PyTorch networks: paper layer shapes and parameter counts, tiny forward passes, losses, checkpoints."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from torch import nn

from models import build_depth_net, build_network, build_pixor
from models.checkpoint import find_checkpoints, load_checkpoint, load_network_weights, save_checkpoint
from models.depth_net import SparsePrefill, load_resnet18_encoder
from models.losses import focal_loss, masked_l1, masked_mse, pixor_loss
from pipeline.presets import get_preset

PAPER = get_preset("paper")
TINY = get_preset("tiny")


# --------------------------------------------------------------------------- expected counts, from the layer list
def conv(cin: int, cout: int, k: int, bias: bool = False) -> int:
    return cin * cout * k * k + (cout if bias else 0)


def bn(channels: int) -> int:
    return 2 * channels  # weight and bias (running stats are buffers)


def basic_block(cin: int, cout: int, stride: int) -> int:
    total = conv(cin, cout, 3) + bn(cout) + conv(cout, cout, 3) + bn(cout)
    if stride != 1 or cin != cout:
        total += conv(cin, cout, 1) + bn(cout)
    return total


def bottleneck(cin: int, width: int, stride: int, expansion: int = 4) -> int:
    out = width * expansion
    total = conv(cin, width, 1) + bn(width) + conv(width, width, 3) + bn(width) + conv(width, out, 1) + bn(out)
    if stride != 1 or cin != out:
        total += conv(cin, out, 1) + bn(out)
    return total


def paper_depth_parameters(use_gam: bool = True, use_aspp: bool = True) -> int:
    """Ma et al. + ResNet-18 as issue 3 lists it, plus our GAM/ASPP design."""
    stem = conv(1, 16, 3) + bn(16) + conv(3, 48, 3) + bn(48)
    encoder = sum(
        basic_block(cin, cout, stride) + basic_block(cout, cout, 1)
        for cin, cout, stride in [(64, 64, 1), (64, 128, 2), (128, 256, 2), (256, 512, 2)]
    )
    conv6 = conv(512, 512, 3) + bn(512)
    decoder = sum(conv(cin, cout, 3) + bn(cout) for cin, cout in [(512, 256), (768, 128), (384, 64), (192, 64), (128, 64)])
    convtf = conv(128, 1, 1, bias=True)
    gam = sum(conv(high, skip, 1, bias=True) for high, skip in [(256, 512), (128, 256), (64, 128), (64, 64), (64, 64)])
    aspp = 4 * (conv(512, 128, 3) + bn(128)) + conv(512, 512, 1) + bn(512)
    return stem + encoder + conv6 + decoder + convtf + (gam if use_gam else 0) + (aspp if use_aspp else 0)


def paper_pixor_parameters() -> int:
    total = conv(36, 32, 3) + bn(32) + conv(32, 32, 3) + bn(32)
    cin = 32
    for width, blocks in zip((24, 48, 64, 96), (3, 6, 6, 3)):
        total += bottleneck(cin, width, 2) + (blocks - 1) * bottleneck(width * 4, width, 1)
        cin = width * 4
    # PIXOR's own top-down path: laterals to 96 (/4), 128 (/8) and 196 (/16) channels, transposed convs
    # 196 → 128 (/16 → /8) and 128 → 96 (/8 → /4).
    total += conv(192, 96, 1, bias=True) + conv(256, 128, 1, bias=True) + conv(384, 196, 1, bias=True)
    total += conv(196, 128, 3, bias=True) + conv(128, 96, 3, bias=True)
    total += 4 * (conv(96, 96, 3) + bn(96))  # header
    total += conv(96, 1, 3, bias=True) + conv(96, 6, 3, bias=True)
    return total


def n_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def output_shapes(model: nn.Module, names: list[str], *inputs: torch.Tensor) -> dict[str, tuple[int, ...]]:
    """Run on the meta device (shapes only, no arithmetic) and record the named modules' output shapes."""
    shapes: dict[str, tuple[int, ...]] = {}
    modules = dict(model.named_modules())
    hooks = [
        modules[name].register_forward_hook(lambda _m, _i, out, name=name: shapes.__setitem__(name, tuple(out.shape)))
        for name in names
    ]
    with torch.no_grad():
        model(*inputs)
    for hook in hooks:
        hook.remove()
    return shapes


# --------------------------------------------------------------------------- paper depth net
def test_paper_depth_parameter_count_matches_layer_list() -> None:
    with torch.device("meta"):
        assert n_parameters(build_depth_net(PAPER)) == paper_depth_parameters()


def test_paper_depth_encoder_is_resnet18_layers() -> None:
    # torchvision ResNet-18: 11,689,512 parameters, of which conv1 7×7 (9,408), bn1 (128) and fc (513,000)
    # are not part of layer1–layer4.
    with torch.device("meta"):
        model = build_depth_net(PAPER)
    encoder = sum(n_parameters(getattr(model, f"layer{i}")) for i in range(1, 5))
    assert encoder == 11_689_512 - 9_408 - 128 - 513_000


def test_paper_depth_ablations_remove_exactly_gam_and_aspp() -> None:
    import dataclasses

    from models.depth_net import DepthCompletionNet

    with torch.device("meta"):
        plain = DepthCompletionNet(dataclasses.replace(PAPER.depth, use_gam=False, use_aspp=False))
    assert n_parameters(plain) == paper_depth_parameters(use_gam=False, use_aspp=False)
    assert not any(name.startswith(("gam", "aspp")) for name, _ in plain.named_parameters())


def test_paper_depth_layer_shapes() -> None:
    with torch.device("meta"):
        model = build_depth_net(PAPER).eval()
        rgb, sparse = torch.empty(1, 3, 352, 1216), torch.empty(1, 1, 352, 1216)
    expected = {
        "conv1_d": (1, 16, 352, 1216),
        "conv1_img": (1, 48, 352, 1216),
        "layer1": (1, 64, 352, 1216),
        "layer2": (1, 128, 176, 608),
        "layer3": (1, 256, 88, 304),
        "layer4": (1, 512, 44, 152),
        "conv6": (1, 512, 22, 76),
        "aspp": (1, 512, 22, 76),
        "convt5": (1, 256, 44, 152),
        "convt4": (1, 128, 88, 304),
        "convt3": (1, 64, 176, 608),
        "convt2": (1, 64, 352, 1216),
        "convt1": (1, 64, 352, 1216),
        "convtf": (1, 1, 352, 1216),
    }
    assert output_shapes(model, list(expected), rgb, sparse) == expected
    # Decoder inputs are the concatenations the issue lists: 768, 384, 192, 128, 128 channels.
    assert [getattr(model, f"convt{i}")[0].in_channels for i in (4, 3, 2, 1)] == [768, 384, 192, 128]
    assert model.convtf.in_channels == 128 and model.convtf.kernel_size == (1, 1)
    assert [model.aspp.branches[i][0].dilation for i in range(4)] == [(2, 2), (4, 4), (8, 8), (16, 16)]


# --------------------------------------------------------------------------- paper PIXOR
def test_paper_pixor_parameter_count_matches_layer_list() -> None:
    with torch.device("meta"):
        assert n_parameters(build_pixor(PAPER)) == paper_pixor_parameters()


def test_paper_pixor_layer_shapes_pad_and_crop() -> None:
    with torch.device("meta"):
        model = build_pixor(PAPER).eval()
        bev = torch.empty(1, 36, 800, 700)
    # 700 is padded to 704 (multiple of 16) inside the network, outputs cropped to 200 × 175.
    expected = {
        "stem": (1, 32, 800, 704),
        "block2": (1, 96, 400, 352),
        "block3": (1, 192, 200, 176),
        "block4": (1, 256, 100, 88),
        "block5": (1, 384, 50, 44),
        "header": (1, 96, 200, 175),
        "score": (1, 1, 200, 175),
        "regression": (1, 6, 200, 175),
    }
    assert output_shapes(model, list(expected), bev) == expected
    assert [len(getattr(model, f"block{i}")) for i in (2, 3, 4, 5)] == [3, 6, 6, 3]


def test_pixor_score_bias_is_the_prior() -> None:
    model = build_pixor(TINY)
    assert torch.sigmoid(model.score.bias).item() == pytest.approx(0.01, rel=1e-6)


def test_pixor_rejects_grid_not_divisible_by_output_stride() -> None:
    from models.pixor import Pixor

    with pytest.raises(ValueError, match="not divisible by the output stride 4"):
        Pixor(PAPER.pixor, in_channels=36, input_hw=(800, 350))


def test_pixor_fpn_takes_one_width_per_level_or_one_for_all() -> None:
    """PIXOR's own top-down path narrows 196 → 128 → 96 towards the output; the edge and tiny presets give
    one width for every level. A tuple of the wrong length names the levels it needed."""
    from models.pixor import Pixor

    with torch.device("meta"):
        narrowing = Pixor(replace(TINY.pixor, fpn_channels=(16, 24, 40)), in_channels=8, input_hw=(200, 176))
        uniform = Pixor(replace(TINY.pixor, fpn_channels=16), in_channels=8, input_hw=(200, 176))
    assert [lateral.out_channels for lateral in narrowing.laterals] == [16, 24, 40]
    assert [(up.in_channels, up.out_channels) for up in narrowing.upsamples] == [(24, 16), (40, 24)]
    assert narrowing.header[0][0].in_channels == 16
    assert [lateral.out_channels for lateral in uniform.laterals] == [16, 16, 16]
    with pytest.raises(ValueError, match="gives 2 widths, but the FPN has 3 levels"):
        Pixor(replace(TINY.pixor, fpn_channels=(16, 24)), in_channels=8, input_hw=(200, 176))


# --------------------------------------------------------------------------- tiny forward passes
def test_tiny_depth_forward_shapes_and_min_depth_clamp() -> None:
    torch.manual_seed(0)
    model = build_depth_net(TINY)
    height, width = TINY.depth.input_hw
    rgb = torch.rand(2, 3, height, width) * 255
    sparse = (torch.rand(2, 1, height, width) < 0.05) * 30.0
    with torch.no_grad():
        model.convtf.bias.fill_(-0.5)  # push raw outputs to −50 m: training mode keeps them, eval clamps
        model.train()
        raw = model(rgb, sparse)
        model.eval()
        depth = model(rgb, sparse)
    assert raw.shape == depth.shape == (2, 1, height, width)
    assert raw.min().item() < 0.0
    assert depth.min().item() == pytest.approx(TINY.depth.min_depth)


def test_prefill_keeps_returns_fills_gaps_with_the_nearest_and_leaves_far_pixels_empty() -> None:
    sparse = torch.zeros(1, 1, 12, 9)
    sparse[0, 0, 2, :] = 20.0  # an upper beam
    sparse[0, 0, 6, :] = 10.0  # a lower beam, nearer
    sparse[0, 0, 6, 4] = 0.0  # a missing return inside the lower beam
    filled = SparsePrefill(passes=2, kernel=(3, 3))(sparse)[0, 0]
    measured = sparse[0, 0] > 0
    assert torch.equal(filled[measured], sparse[0, 0][measured])
    assert filled[6, 4] == 10.0  # the gap in a beam takes its neighbours
    assert filled[4, 2] == 10.0  # between the beams, two rows from each: the nearer return wins
    assert filled[3, 2] == 20.0 and filled[5, 2] == 10.0  # one row away from only one beam
    assert filled[0, 2] == 20.0  # two passes of ±1 row reach two rows above the top beam …
    assert torch.all(filled[9:] == 0.0)  # … and no further below the bottom one


def test_prefill_net_starts_from_the_filled_map() -> None:
    torch.manual_seed(0)
    model = build_depth_net(TINY).eval()
    assert model.prefill is not None and model.conv1_d[0].in_channels == 2
    height, width = TINY.depth.input_hw
    sparse = torch.zeros(1, 1, height, width)
    sparse[..., ::6, :] = torch.linspace(5.0, 60.0, width)  # beams every 6 rows
    with torch.no_grad():
        model.convtf.weight.zero_()
        model.convtf.bias.zero_()
        depth = model(torch.rand(1, 3, height, width) * 255, sparse)
        prior = model.prefill(sparse)
    assert (prior > 0).float().mean() > 0.9
    covered = prior > 0
    assert torch.allclose(depth[covered], prior[covered].clamp(min=TINY.depth.min_depth))


def _with_head_and_without(preset_name: str) -> tuple[nn.Module, nn.Module, torch.Tensor, torch.Tensor]:
    """The tiny depth net, the same net with a full-resolution head (its other weights copied), and an input."""
    torch.manual_seed(0)
    plain = build_depth_net(TINY).eval()
    torch.manual_seed(1)
    model = build_depth_net(get_preset(preset_name)).eval()
    result = model.load_state_dict(plain.state_dict(), strict=False)
    assert result.unexpected_keys == [] and all(k.startswith("refine.") for k in result.missing_keys)
    height, width = TINY.depth.input_hw
    rgb = torch.rand(1, 3, height, width) * 255
    sparse = torch.zeros(1, 1, height, width)
    sparse[..., ::6, :] = torch.linspace(5.0, 60.0, width)
    return plain, model, rgb, sparse


def test_refine_head_starts_as_the_network_without_it_and_corrects_at_full_resolution() -> None:
    """The full-resolution head's zero-initialised output leaves the network's function as it was; with
    weights, it changes single pixels, which the half-resolution correction (upsampled ×2) cannot."""
    assert TINY.depth.refine_channels == 0 and get_preset("tiny-refine").depth.refine_channels > 0
    plain, model, rgb, sparse = _with_head_and_without("tiny-refine")
    with torch.no_grad():
        assert torch.equal(model(rgb, sparse), plain(rgb, sparse))
        model.refine.out.weight.normal_(std=0.05)
        refined = model(rgb, sparse)
    change = (refined - plain(rgb, sparse))[0, 0]
    assert change.abs().max() > 0.1
    # Neighbouring pixels of one half-resolution cell get different corrections from the head.
    assert (change[:, 0::2] - change[:, 1::2]).abs().max() > 0.01


def test_convex_upsampling_starts_bilinear_and_can_give_a_pixel_one_neighbours_correction() -> None:
    """-convex starts as the network without it (bilinear ×2, borders included); its weights are a
    convex combination, so a pixel whose logits pick one neighbour takes exactly that correction."""
    assert get_preset("tiny-convex").depth.refine_mode == "convex"
    plain, model, rgb, sparse = _with_head_and_without("tiny-convex")
    with torch.no_grad():
        assert torch.allclose(model(rgb, sparse), plain(rgb, sparse), atol=1e-5)
        coarse = torch.randn(1, 1, 5, 7)
        image, depth = torch.zeros(1, 3, 10, 14), torch.zeros(1, 2, 10, 14)
        estimate, features = torch.zeros(1, 1, 10, 14), torch.zeros(1, model.refine.head.context.in_channels, 5, 7)
        bilinear = torch.nn.functional.interpolate(coarse, scale_factor=2.0, mode="bilinear", align_corners=False)
        assert torch.allclose(model.refine(coarse, image, depth, estimate, features), bilinear, atol=1e-6)
        # Logits that favour the neighbour above-left by far: every pixel takes that cell's correction.
        model.refine.head.out.bias.copy_(torch.tensor([100.0] + [0.0] * 8))
        upper_left = torch.nn.functional.pad(coarse, (1, 0, 1, 0), mode="replicate")[..., :5, :7]
        expected = torch.nn.functional.interpolate(upper_left, scale_factor=2.0, mode="nearest")
        assert torch.allclose(model.refine(coarse, image, depth, estimate, features), expected, atol=1e-6)


def test_refine_mode_must_be_known() -> None:
    refined = get_preset("tiny-refine")
    with pytest.raises(ValueError, match="refine_mode 'sharp'"):
        build_depth_net(replace(refined, depth=replace(refined.depth, refine_mode="sharp")))


def test_a_checkpoint_from_before_a_preset_field_existed_still_loads(tmp_path: Path) -> None:
    """Fields added to a preset later (refine_mode, say) take their defaults in an older checkpoint."""
    torch.manual_seed(0)
    model = build_depth_net(TINY)
    path = save_checkpoint(tmp_path / "depth.pt", TINY, {"depth": model}, {})
    payload = torch.load(path, weights_only=True)
    del payload["preset_config"]["depth"]["refine_mode"]
    torch.save(payload, path)
    fresh = build_depth_net(TINY)
    load_network_weights(fresh, load_checkpoint(path), "depth", TINY)
    assert all(torch.equal(a, b) for a, b in zip(fresh.state_dict().values(), model.state_dict().values()))


def test_refine_head_needs_a_strided_stem_and_the_prefill() -> None:
    refined = get_preset("tiny-refine")
    with pytest.raises(ValueError, match="refine_channels needs stem_stride 2"):
        build_depth_net(replace(refined, depth=replace(refined.depth, prefill_passes=0)))
    with pytest.raises(ValueError, match="refine_channels needs stem_stride 2"):
        build_depth_net(get_preset("paper-refine"))


def test_depth_net_rejects_wrong_input_size() -> None:
    model = build_depth_net(TINY).eval()
    with pytest.raises(ValueError, match="built for 88×304"):
        model(torch.zeros(1, 3, 80, 304), torch.zeros(1, 1, 80, 304))


def test_tiny_pixor_forward_shapes_and_logits() -> None:
    torch.manual_seed(0)
    model = build_network("pixor", TINY).eval()
    bev = (torch.rand(1, *TINY.bev.shape) < 0.02).float()
    with torch.no_grad():
        score, regression = model(bev)
        logits, regression_again = model.forward_logits(bev)
    ny, nx = TINY.bev.ny // 4, TINY.bev.nx // 4
    assert score.shape == (1, 1, ny, nx) and regression.shape == (1, 6, ny, nx)
    assert torch.allclose(score, torch.sigmoid(logits)) and torch.equal(regression, regression_again)
    assert 0.0 < score.min().item() and score.max().item() < 1.0


def test_registry_rejects_unknown_network() -> None:
    with pytest.raises(ValueError, match="choose one of depth, pixor"):
        build_network("resnet", TINY)


# --------------------------------------------------------------------------- ResNet-18 encoder loading
def torchvision_resnet18_state(seed: int = 0) -> dict[str, torch.Tensor]:
    """A state dict with torchvision's ResNet-18 names and shapes (random values)."""
    gen = torch.Generator().manual_seed(seed)
    state: dict[str, torch.Tensor] = {"conv1.weight": torch.randn(64, 3, 7, 7, generator=gen)}

    def add_bn(prefix: str, c: int) -> None:
        state.update({f"{prefix}.weight": torch.rand(c, generator=gen), f"{prefix}.bias": torch.randn(c, generator=gen),
                      f"{prefix}.running_mean": torch.randn(c, generator=gen),
                      f"{prefix}.running_var": torch.rand(c, generator=gen) + 0.5,
                      f"{prefix}.num_batches_tracked": torch.tensor(7)})

    add_bn("bn1", 64)
    cin = 64
    for layer, cout in enumerate((64, 128, 256, 512), start=1):
        for block in range(2):
            prefix = f"layer{layer}.{block}"
            first_in = cin if block == 0 else cout
            state[f"{prefix}.conv1.weight"] = torch.randn(cout, first_in, 3, 3, generator=gen)
            add_bn(f"{prefix}.bn1", cout)
            state[f"{prefix}.conv2.weight"] = torch.randn(cout, cout, 3, 3, generator=gen)
            add_bn(f"{prefix}.bn2", cout)
            if block == 0 and layer > 1:
                state[f"{prefix}.downsample.0.weight"] = torch.randn(cout, cin, 1, 1, generator=gen)
                add_bn(f"{prefix}.downsample.1", cout)
        cin = cout
    state["fc.weight"] = torch.randn(1000, 512, generator=gen)
    state["fc.bias"] = torch.randn(1000, generator=gen)
    return state


def test_load_resnet18_encoder_into_paper(tmp_path: Path) -> None:
    state = torchvision_resnet18_state()
    path = tmp_path / "resnet18.pth"
    torch.save(state, path)
    model = build_depth_net(PAPER)
    loaded = load_resnet18_encoder(model, path)
    ours = model.state_dict()
    assert len(loaded) == sum(k.startswith("layer") for k in state)
    assert all(torch.equal(ours[name], state[name]) for name in loaded)


def test_load_resnet18_encoder_refuses_narrow_preset(tmp_path: Path) -> None:
    path = tmp_path / "resnet18.pth"
    torch.save({"state_dict": torchvision_resnet18_state()}, path)
    with pytest.raises(ValueError, match=r"layer1\.0\.conv1\.weight has no counterpart|shape \(64, 64, 3, 3\)"):
        load_resnet18_encoder(build_depth_net(get_preset("edge")), path)


# --------------------------------------------------------------------------- losses
def test_focal_loss_matches_formula() -> None:
    logits = torch.tensor([2.0, -1.0, 0.5])
    targets = torch.tensor([1.0, 0.0, 0.0])
    p = torch.sigmoid(logits)
    expected = (
        -0.25 * (1 - p[0]) ** 2 * torch.log(p[0])
        - 0.75 * p[1] ** 2 * torch.log(1 - p[1])
        - 0.75 * p[2] ** 2 * torch.log(1 - p[2])
    )
    assert focal_loss(logits, targets).item() == pytest.approx(expected.item(), rel=1e-5)


def test_masked_l1_ignores_pixels_without_ground_truth_and_prefers_a_surface() -> None:
    target = torch.tensor([[[[10.0, 30.0, 0.0]]]])
    assert masked_l1(torch.tensor([[[[12.0, 27.0, 99.0]]]]), target).item() == pytest.approx(2.5)
    # One pixel, seen as foreground (10 m) in one frame and background (30 m) in another: the
    # mean depth (20 m) is the MSE optimum, while L1 is no worse on a surface than between them.
    both = torch.tensor([10.0, 30.0]).view(2, 1, 1, 1)
    at = lambda d: torch.full((2, 1, 1, 1), d)
    assert masked_mse(at(20.0), both) < masked_mse(at(10.0), both)
    assert masked_l1(at(10.0), both) == masked_l1(at(20.0), both)
    assert masked_l1(torch.zeros(1, 1, 2, 2), torch.zeros(1, 1, 2, 2)).item() == 0.0


def test_focal_loss_is_finite_for_confident_cells() -> None:
    loss = focal_loss(torch.tensor([100.0, -100.0]), torch.tensor([0.0, 1.0]))
    assert math.isfinite(loss.item()) and loss.item() > 10.0


def test_pixor_loss_regresses_positive_cells_only() -> None:
    logits = torch.zeros(1, 1, 2, 2)
    target = torch.zeros(1, 1, 2, 2)
    target[0, 0, 1, 1] = 1.0
    regression = torch.zeros(1, 6, 2, 2, requires_grad=True)
    reg_target = torch.full((1, 6, 2, 2), 5.0)
    reg_target[0, :, 1, 1] = 0.5  # smooth L1 of 0.5 is 0.5²/2 = 0.125 per channel
    loss = pixor_loss(logits, regression, target, reg_target)
    assert loss.regression.item() == pytest.approx(6 * 0.125)
    loss.total.backward()
    grad = regression.grad[0].abs().sum(dim=0)
    assert grad[1, 1] > 0 and grad[0, 0] == grad[0, 1] == grad[1, 0] == 0


def test_pixor_loss_without_positives_is_finite_and_differentiable() -> None:
    regression = torch.zeros(1, 6, 3, 3, requires_grad=True)
    loss = pixor_loss(torch.zeros(1, 1, 3, 3), regression, torch.zeros(1, 1, 3, 3), torch.ones(1, 6, 3, 3))
    loss.total.backward()
    assert loss.regression.item() == 0.0 and math.isfinite(loss.total.item())


def test_depth_losses_take_a_weighted_mean_over_pixels_with_ground_truth() -> None:
    target = torch.tensor([[[[10.0, 20.0, 0.0, 30.0]]]])
    prediction = torch.tensor([[[[11.0, 20.0, 5.0, 33.0]]]])
    weight = torch.tensor([[[[1.0, 1.0, 100.0, 10.0]]]])  # the pixel without ground truth stays out
    assert masked_l1(prediction, target, weight).item() == pytest.approx((1.0 + 0.0 + 30.0) / 12.0)
    assert masked_mse(prediction, target, weight).item() == pytest.approx((1.0 + 0.0 + 90.0) / 12.0)
    assert masked_l1(prediction, target, torch.ones_like(target)).item() == pytest.approx(masked_l1(prediction, target).item())


def test_masked_mse_ignores_pixels_without_ground_truth() -> None:
    prediction = torch.tensor([[[[10.0, 3.0], [100.0, 4.0]]]])
    target = torch.tensor([[[[12.0, 0.0], [0.0, 5.0]]]])
    assert masked_mse(prediction, target).item() == pytest.approx((4.0 + 1.0) / 2)
    assert masked_mse(prediction, torch.zeros_like(target)).item() == 0.0


# --------------------------------------------------------------------------- checkpoints
def test_checkpoint_round_trip(tmp_path: Path) -> None:
    torch.manual_seed(1)
    trained = build_depth_net(TINY).eval()
    save_checkpoint(tmp_path / "depth.pt", TINY, {"depth": trained}, {"epochs": 3, "val_rmse_m": 2.5})
    assert find_checkpoints(tmp_path) == {"depth": tmp_path / "depth.pt"}
    checkpoint = load_checkpoint(tmp_path / "depth.pt")
    assert checkpoint.preset == "tiny" and checkpoint.metadata == {"epochs": 3, "val_rmse_m": 2.5}
    torch.manual_seed(2)
    fresh = build_depth_net(TINY).eval()
    load_network_weights(fresh, checkpoint, "depth", TINY)
    height, width = TINY.depth.input_hw
    rgb, sparse = torch.rand(1, 3, height, width) * 255, torch.rand(1, 1, height, width) * 20
    with torch.no_grad():
        assert torch.equal(fresh(rgb, sparse), trained(rgb, sparse))


def test_checkpoint_refuses_other_preset(tmp_path: Path) -> None:
    save_checkpoint(tmp_path / "pixor.pt", TINY, {"pixor": build_pixor(TINY)}, {})
    checkpoint = load_checkpoint(tmp_path / "pixor.pt")
    edge = get_preset("edge")
    with pytest.raises(ValueError, match="--preset tiny"):
        load_network_weights(build_pixor(edge), checkpoint, "pixor", edge)
    with pytest.raises(ValueError, match="no 'depth' weights"):
        load_network_weights(build_depth_net(TINY), checkpoint, "depth", TINY)


def test_checkpoint_compares_only_the_sections_its_network_depends_on(tmp_path: Path) -> None:
    from dataclasses import replace

    save_checkpoint(tmp_path / "both.pt", TINY, {"pixor": build_pixor(TINY), "depth": build_depth_net(TINY)}, {})
    checkpoint = load_checkpoint(tmp_path / "both.pt")
    other_depth = replace(TINY, depth=replace(TINY.depth, prefill_passes=3))
    load_network_weights(build_pixor(other_depth), checkpoint, "pixor", other_depth)  # PIXOR unaffected
    # Under the same name the preset can only differ by a change of the code since: each field is named.
    with pytest.raises(ValueError, match=r"depth\.prefill_passes: \d+ then, 3 now"):
        load_network_weights(build_depth_net(other_depth), checkpoint, "depth", other_depth)
    other_grid = replace(TINY, bev=replace(TINY.bev, x_max=80.0))
    with pytest.raises(ValueError, match=r"bev\.x_max: [\d.]+ then, 80\.0 now"):
        load_network_weights(build_pixor(other_grid), checkpoint, "pixor", other_grid)


def test_a_paper_pixor_trained_before_the_fpn_widths_changed_is_named_as_such(tmp_path: Path) -> None:
    """A paper PIXOR saved with 96 channels at every FPN level (before session 40) does not fit today's paper
    preset: the error says the preset changed, and how, rather than suggesting the same --preset paper."""
    before = replace(PAPER, pixor=replace(PAPER.pixor, fpn_channels=96))
    save_checkpoint(tmp_path / "pixor.pt", before, {"pixor": build_pixor(before)}, {})
    with pytest.raises(ValueError) as refused:
        load_network_weights(build_pixor(PAPER), load_checkpoint(tmp_path / "pixor.pt"), "pixor", PAPER)
    message = str(refused.value)
    assert "as an earlier lowres3d defined it (pixor.fpn_channels: 96 then, [96, 128, 196] now)" in message
    assert "give --preset paper" not in message


def test_a_depth_net_exports_with_another_pseudo_range_but_not_another_layer(tmp_path: Path) -> None:
    """``-near35`` only changes which pseudo points are kept: the depth net trained under ``tiny`` loads
    into ``tiny-near35``; a change to what the net computes is still refused."""
    save_checkpoint(tmp_path / "depth.pt", TINY, {"depth": build_depth_net(TINY)}, {})
    checkpoint = load_checkpoint(tmp_path / "depth.pt")
    near = get_preset("tiny-near35")
    assert near.depth.max_depth == 35.0 and near.pseudo_limits[1] == 35.0
    load_network_weights(build_depth_net(near), checkpoint, "depth", near)
    other = get_preset("tiny-no-aspp-near35")
    with pytest.raises(ValueError, match="whose depth configuration differs"):
        load_network_weights(build_depth_net(other), checkpoint, "depth", other)


def test_a_pixor_trained_on_pseudo_points_keeps_its_range(tmp_path: Path) -> None:
    """The pseudo points' range (depth.max_depth) is no part of PIXOR's layers, so a camera PIXOR trained under
    tiny-near35 loaded under tiny (85 m) without a word, and its BEV then held points it never saw (the shipped
    camera model exported as edge-split lost 4 BEV AP on a user's frames). Refused for a PIXOR that learned on
    pseudo points (a pseudo or joint run); a LiDAR-only PIXOR and a depth net may still change the range."""
    near = get_preset("tiny-near35")
    pixor, depth = build_pixor(near), build_depth_net(near)
    for metadata, refused in (({"task": "detector", "input": "pseudo"}, True), ({"task": "joint"}, True),
                              ({"task": "detector", "input": "lidar16"}, False)):
        path = save_checkpoint(tmp_path / "pixor.pt", near, {"pixor": pixor, "depth": depth}, metadata)
        if refused:
            with pytest.raises(ValueError, match=r"its PIXOR learned on pseudo points up to 35 m \(preset "
                                                 r"'tiny-near35'\); preset 'tiny' keeps them up to 85 m.*--preset "
                                                 r"tiny-near35$"):
                load_network_weights(build_pixor(TINY), load_checkpoint(path), "pixor", TINY)
        else:
            load_network_weights(build_pixor(TINY), load_checkpoint(path), "pixor", TINY)
        load_network_weights(build_pixor(near), load_checkpoint(path), "pixor", near)  # its own range: loads
        load_network_weights(build_depth_net(TINY), load_checkpoint(path), "depth", TINY)  # the depth net: any
