"""The depth validation figures that pick a run's best epoch, against sums worked out here (mutation audit)."""

import math
import shutil

import numpy as np
import pytest
import torch

from models.data import DepthDataset, car_boxes
from models.validation import validate_depth, validate_detector
from pipeline.frame import load_frame
from pipeline.presets import PRESETS
from pipeline.targets import encode_targets
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


# --------------------------------------------------------------------------- the detector's figures
class _Oracle(torch.nn.Module):
    """A 'PIXOR' that, frame after frame, gives the maps PIXOR's targets would have for chosen boxes, each with a
    score of its own: the detections are known, so every AP the validation reports follows from the labels."""

    def __init__(self, maps: list[tuple[np.ndarray, np.ndarray]]) -> None:
        super().__init__()
        self.maps = list(maps)

    def forward_logits(self, bev: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        logits, regression = self.maps.pop(0)
        return torch.from_numpy(logits)[None, None], torch.from_numpy(regression)[None]


def _oracle_maps(boxes: np.ndarray, scores: list[float], preset) -> tuple[np.ndarray, np.ndarray]:
    """PIXOR's logits and regression for ``boxes`` (N, 7), box i's cells at ``scores[i]``, the rest at ~0."""
    stride = preset.pixor.output_stride
    logits, regression = None, None
    for box, score in zip(boxes, scores):
        one = encode_targets(box[None], preset.bev, stride, preset.decode)
        if logits is None:
            logits, regression = np.full(one.score.shape, -30.0, np.float32), np.zeros_like(one.regression)
        cells = one.score > 0
        logits[cells] = math.log(score / (1 - score))
        regression[:, cells] = one.regression[:, cells]
    return logits, regression


def test_detector_figures_are_moderate_r40_at_each_iou(tmp_path):
    """The AP that picks a detector's best epoch is KITTI's BEV AP, moderate, R40, at IoU 0.7 (and 0.5).

    The five KITTI frames' eight cars, by the devkit's rules: easy A (000003), B and C (000006, 41 and 61 px high),
    moderate D (000004, 30 px), and F (000006, 34 px, occlusion 1, made 2 here so that it is hard only); the other
    three are under 25 px and count nowhere. The oracle finds A, B, C and F exactly (scores 0.9, 0.8, 0.7, 0.6)
    and D shifted by a quarter of its length (IoU 0.6; score 0.85). Its best-scored box (0.95) lies 72° to the
    left, outside the camera's view, where the Detector drops it (kept, it was a false positive above all).
    The devkit samples precision only at the scores of true positives, one recall point per detection:
    R40 AP = Σ over the 2nd to last of the interpolated precisions / 40. IoU 0.7: easy 1 + 1 (D and F are under easy's 40 px: ignored) → 5.0;
    moderate with D a false positive, 2/3, 3/4 → 0.75 + 0.75 → 3.75; hard 2/3, 3/4, 4/5 → 3 × 0.8 → 6.0.
    IoU 0.5: easy 5.0, moderate 3 × 1 → 7.5, hard 4 × 1 → 10.0."""
    data = tmp_path / "training"
    shutil.copytree(KITTI, data)
    labels = data / "label_2" / "000006.txt"
    lines = labels.read_text().splitlines()
    f_line = [i for i, line in enumerate(lines) if line.startswith("Car")][3]
    fields = lines[f_line].split(" ")
    assert fields[11:14] == ["-12.66", "1.13", "38.44"] and fields[2] == "1"  # F, occlusion 1
    fields[2] = "2"
    lines[f_line] = " ".join(fields)
    labels.write_text("\n".join(lines) + "\n")

    preset = PRESETS["tiny"]
    ids = ["000003", "000004", "000006"]
    maps = []
    for fid in ids:
        cars = car_boxes(load_frame(data, fid, with_image=False))
        if fid == "000003":  # A, and the box outside the camera's view
            outside = np.array([[8.0, 24.0, cars[0, 2], *cars[0, 3:6], 0.0]])
            maps.append(_oracle_maps(np.vstack([cars, outside]), [0.9, 0.95], preset))
        elif fid == "000004":
            near = cars[np.argmin(cars[:, 0])]  # D, the nearer of the two (38 m; the other is 20 px high)
            shifted = near.copy()
            shifted[:2] += 0.25 * near[3] * np.array([math.cos(near[6]), math.sin(near[6])])
            maps.append(_oracle_maps(shifted[None], [0.85], preset))
        else:
            by_range = cars[np.argsort(cars[:, 0])]  # C 19.7 m, B 31.7, F 38.4, the 23-px one 48.2
            maps.append(_oracle_maps(by_range[[1, 0, 2]], [0.8, 0.7, 0.6], preset))  # B, C, F
    figures = validate_detector(_Oracle(maps), preset, data, ids, "lidar64", None, beams=None)
    table = figures["bev_ap"]
    assert [table["0.7"]["R40"][i] for i in range(3)] == pytest.approx([5.0, 3.75, 6.0], abs=1e-6)
    assert [table["0.5"]["R40"][i] for i in range(3)] == pytest.approx([5.0, 7.5, 10.0], abs=1e-6)
    assert figures["bev_ap_0.7_moderate"] == pytest.approx(3.75, abs=1e-6)
    assert figures["bev_ap_0.5_moderate"] == pytest.approx(7.5, abs=1e-6)
    # R11 reads every fourth of the same 41 points: of the three, only the first (interpolated precision 1).
    assert table["0.7"]["R11"][1] == pytest.approx(100 / 11, abs=1e-6)
