"""The training losses' defaults and normalisation, against values worked out by hand (mutation audit)."""

import math

import pytest
import torch

from models.losses import DEPTH_LOSSES, pixor_loss


def _focal(p: float, positive: bool, alpha: float = 0.25, gamma: float = 2.0) -> float:
    """Lin et al.'s focal term of one cell with sigmoid probability p, from its definition."""
    if positive:
        return -alpha * (1.0 - p) ** gamma * math.log(p)
    return -(1.0 - alpha) * p**gamma * math.log(1.0 - p)


def _cells() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """A 1×2×2 map: two positive cells (logits 1 and -0.5), two negatives (logits 0 and 2); regression
    errors 0.5 on the positives' six channels (smooth L1: 0.125 each) and 3 on the negatives'."""
    logits = torch.tensor([1.0, -0.5, 0.0, 2.0]).view(1, 1, 2, 2)
    score = torch.tensor([1.0, 1.0, 0.0, 0.0]).view(1, 1, 2, 2)
    regression = torch.zeros(1, 6, 2, 2)
    target = torch.full((1, 6, 2, 2), 3.0)
    target[0, :, 0, :] = 0.5
    return logits, regression, score, target


def test_pixor_loss_defaults_are_retinanets_focal_terms_normalised_by_the_positives():
    """alpha 0.25, gamma 2 by default; both terms are divided by the number of positive cells (2 here)."""
    logits, regression, score, target = _cells()
    loss = pixor_loss(logits, regression, score, target)
    sig = [1 / (1 + math.exp(-v)) for v in (1.0, -0.5, 0.0, 2.0)]
    focal = _focal(sig[0], True) + _focal(sig[1], True) + _focal(sig[2], False) + _focal(sig[3], False)
    assert loss.classification.item() == pytest.approx(focal / 2, rel=1e-5)
    assert loss.regression.item() == pytest.approx(2 * 6 * 0.125 / 2, rel=1e-6)  # the negatives' errors stay out
    assert loss.total.item() == pytest.approx(focal / 2 + 0.75, rel=1e-5)


def test_regression_weight_scales_the_regression_term_only():
    logits, regression, score, target = _cells()
    plain = pixor_loss(logits, regression, score, target)
    weighted = pixor_loss(logits, regression, score, target, regression_weight=3.0)
    assert weighted.total.item() == pytest.approx(plain.classification.item() + 3.0 * plain.regression.item(), rel=1e-6)


def test_depth_loss_names_pick_their_losses():
    """--depth-loss mse is the squared error (the paper's), l1 the absolute one."""
    target = torch.tensor([[[[10.0, 20.0, 0.0]]]])
    prediction = torch.tensor([[[[13.0, 19.0, 50.0]]]])
    assert DEPTH_LOSSES["mse"](prediction, target).item() == pytest.approx((9.0 + 1.0) / 2)
    assert DEPTH_LOSSES["l1"](prediction, target).item() == pytest.approx((3.0 + 1.0) / 2)
