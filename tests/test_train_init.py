"""Weight initialisation of a from-scratch run and the residual shortcut (mutation audit)."""

import math

import pytest
import torch
from torch import nn

from models.init import init_conv_and_bn, projection_shortcut


def test_convs_start_he_fan_out_with_zero_bias_and_batch_norm_at_identity():
    """He init for ReLU: std sqrt(2 / fan_out), fan_out = the weight's dim 0 × kernel area (output channels of a
    conv, input channels of a transposed conv in torch's layout), for both kinds of convolution."""
    torch.manual_seed(0)
    conv, deconv, norm = nn.Conv2d(16, 96, 3), nn.ConvTranspose2d(96, 16, 3), nn.BatchNorm2d(96)
    for module in (conv, deconv):
        nn.init.constant_(module.weight, 5.0)
        nn.init.constant_(module.bias, 5.0)
    nn.init.constant_(norm.weight, 5.0)
    nn.init.constant_(norm.bias, 5.0)
    init_conv_and_bn(nn.Sequential(conv, deconv, norm))
    for module in (conv, deconv):
        fan_out = module.weight.shape[0] * 9
        assert module.weight.std().item() == pytest.approx(math.sqrt(2.0 / fan_out), rel=0.05)
        assert abs(module.weight.mean().item()) < 0.01
        assert not module.bias.any()
    assert torch.equal(norm.weight, torch.ones(96)) and not norm.bias.any()


def test_a_shortcut_projects_only_when_the_block_changes_shape():
    assert projection_shortcut(64, 64, 1) is None
    for in_channels, out_channels, stride in ((64, 128, 1), (64, 64, 2), (64, 128, 2)):
        shortcut = projection_shortcut(in_channels, out_channels, stride)
        assert shortcut(torch.zeros(1, in_channels, 8, 8)).shape == (1, out_channels, 8 // stride, 8 // stride)
