"""Training losses: PIXOR's focal + smooth-L1, and the depth net's masked MSE (the paper's) and masked L1
(the edge recipe's, ``--depth-loss l1``)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F


@dataclass
class PixorLoss:
    """The two terms of the PIXOR loss and their sum (scalars, differentiable)."""

    total: torch.Tensor
    classification: torch.Tensor
    regression: torch.Tensor


def focal_loss(logits: torch.Tensor, targets: torch.Tensor, alpha: float = 0.25, gamma: float = 2.0) -> torch.Tensor:
    """Sigmoid focal loss (Lin et al.), summed over cells.

    logits, targets: same shape; targets in {0, 1}. Computed from logits with
    BCE-with-logits so very confident cells neither overflow nor give log(0).
    """
    targets = targets.to(logits.dtype)
    probability = torch.sigmoid(logits)
    bce = F.binary_cross_entropy_with_logits(logits, targets, reduction="none")
    p_t = probability * targets + (1.0 - probability) * (1.0 - targets)
    alpha_t = alpha * targets + (1.0 - alpha) * (1.0 - targets)
    return (alpha_t * (1.0 - p_t) ** gamma * bce).sum()


def pixor_loss(
    score_logits: torch.Tensor,
    regression: torch.Tensor,
    score_target: torch.Tensor,
    regression_target: torch.Tensor,
    alpha: float = 0.25,
    gamma: float = 2.0,
    regression_weight: float = 1.0,
) -> PixorLoss:
    """Focal loss on every cell + smooth L1 on positive cells, both normalised by the positives.

    score_logits, score_target: (N, 1, h, w); regression, regression_target: (N, 6, h, w),
    targets already normalised as the preset's DecodeConfig says. The normaliser is
    max(1, #positives), as in RetinaNet, so frames without cars still train the
    classifier.
    """
    positives = score_target > 0.5
    normaliser = positives.sum().clamp(min=1).to(score_logits.dtype)
    classification = focal_loss(score_logits, score_target, alpha, gamma) / normaliser
    mask = positives.expand_as(regression)
    if mask.any():
        regression_loss = F.smooth_l1_loss(regression[mask], regression_target[mask], reduction="sum") / normaliser
    else:
        regression_loss = regression.sum() * 0.0  # keeps the graph connected on empty frames
    return PixorLoss(
        total=classification + regression_weight * regression_loss,
        classification=classification,
        regression=regression_loss,
    )


def _masked_mean(errors: torch.Tensor, valid: torch.Tensor, weight: torch.Tensor | None) -> torch.Tensor:
    """Mean of ``errors`` over the valid pixels, each weighted by ``weight`` (a weighted mean) when given."""
    if weight is None:
        return errors[valid].mean()
    w = weight[valid]
    return (errors[valid] * w).sum() / w.sum()


def masked_mse(prediction: torch.Tensor, target: torch.Tensor, weight: torch.Tensor | None = None) -> torch.Tensor:
    """Mean squared error over the pixels with ground truth (target > 0), as in Ma et al.

    prediction, target: (N, 1, H, W) metres; weight: optional (N, 1, H, W) per-pixel weights (a weighted
    mean). Returns 0 (differentiable) when no pixel has ground truth.
    """
    valid = target > 0
    if not valid.any():
        return prediction.sum() * 0.0
    return _masked_mean((prediction - target) ** 2, valid, weight)


def masked_l1(prediction: torch.Tensor, target: torch.Tensor, weight: torch.Tensor | None = None) -> torch.Tensor:
    """Mean absolute error over the pixels with ground truth (target > 0); weight as in :func:`masked_mse`.

    Where foreground and background are both plausible (an object's outline) the L1 optimum
    is one of the two depths, the L2 optimum their mean: a point floating between them.
    """
    valid = target > 0
    if not valid.any():
        return prediction.sum() * 0.0
    return _masked_mean((prediction - target).abs(), valid, weight)


DEPTH_LOSSES = {"mse": masked_mse, "l1": masked_l1}  # --depth-loss; mse is the paper's
