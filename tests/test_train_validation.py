"""The depth validation figures that pick a run's best epoch, against sums worked out here (mutation audit)."""

import math

import numpy as np
import pytest
import torch

from models.data import DepthDataset
from models.validation import validate_depth
from pipeline.presets import PRESETS
from tests.conftest import KITTI

IDS = ["000006", "000003", "000004"]  # three frames: a batch of two, then one


class _Constant(torch.nn.Module):
    """A 'depth net' that says every pixel is 12 m, so each figure follows from the targets alone."""

    def forward(self, rgb: torch.Tensor, sparse: torch.Tensor) -> torch.Tensor:
        return torch.full_like(sparse, 12.0)


@pytest.fixture(scope="module")
def targets():
    dataset = DepthDataset(KITTI, IDS, PRESETS["tiny"])
    return dataset, [dataset[i][2].numpy().astype(np.float64) for i in range(len(IDS))]


def test_depth_figures_are_over_the_pixels_with_ground_truth(targets):
    """rmse_mm: the mean of the frames' RMSEs (KITTI's per-frame average); mae_mm and val_loss over all the
    pixels with ground truth at once; val_loss is the training loss: MSE in m² (mse) or MAE in m (l1)."""
    dataset, maps = targets
    errors = [12.0 - t[t > 0] for t in maps]
    pooled = np.concatenate(errors)
    mse = validate_depth(_Constant(), dataset, loss="mse")
    l1 = validate_depth(_Constant(), dataset, loss="l1")
    assert mse["pixels"] == l1["pixels"] == pooled.size
    assert mse["rmse_mm"] == pytest.approx(1000 * np.mean([math.sqrt(np.mean(e**2)) for e in errors]), rel=1e-5)
    assert mse["rmse_mm"] != pytest.approx(1000 * math.sqrt(np.mean(pooled**2)), rel=1e-4)  # not the pooled RMSE
    assert mse["mae_mm"] == pytest.approx(1000 * np.mean(np.abs(pooled)), rel=1e-5)
    assert mse["val_loss"] == pytest.approx(np.mean(pooled**2), rel=1e-5)
    assert l1["val_loss"] == pytest.approx(np.mean(np.abs(pooled)), rel=1e-5)


def test_car_figures_do_not_depend_on_the_frames_order(targets):
    """Each frame's cars are scored on that frame's prediction, whatever its place in the batches."""
    dataset, _ = targets
    forward = validate_depth(_Constant(), dataset)
    backward = validate_depth(_Constant(), DepthDataset(KITTI, IDS[::-1], PRESETS["tiny"]))
    cars = {k: v for k, v in forward.items() if k.startswith("car_")}
    assert cars and all(math.isfinite(v) for v in forward.values())
    assert cars == pytest.approx({k: v for k, v in backward.items() if k.startswith("car_")})
