"""The validation at the end of every training epoch: the depth net's RMSE and MAE on the validation frames
(and where the labelled cars' pixels land), PIXOR's loss and KITTI BEV AP. Their figures go into the run's
log, and one of them picks the run's best epoch (models.train.selection_criterion).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from evaluation import DEFAULT_SCORE_THRESHOLD
from evaluation.depth_metrics import car_box_shares, car_shares_by_band, moderate_cars_in_view
from evaluation.kitti_eval import evaluate
from evaluation.labels import LabelArrays
from models.data import (
    DepthCompletionDataset,
    DepthDataset,
    cached_pseudo_depth,
    car_boxes,
    detector_points,
    frame_points,
)
from models.devices import CPU
from models.joint import joint_depth
from models.losses import pixor_loss
from pipeline.bev import BevVoxelizer, pseudo_bins
from pipeline.boxes import boxes_to_objects, in_camera_view
from pipeline.frame import load_frame
from pipeline.kitti import read_calib, read_image_size, read_labels
from pipeline.postprocess import boxes_from_maps
from pipeline.preprocess import view_calibration
from pipeline.presets import Preset
from pipeline.targets import encode_targets


@torch.no_grad()
def validate_depth(net, dataset: DepthDataset | DepthCompletionDataset, device: torch.device = CPU,
                   loss: str = "mse") -> dict:
    """Depth errors on the validation pixels with ground truth: ``rmse_mm`` is the mean of the frames' RMSEs
    (KITTI's depth benchmark averages per frame), ``mae_mm`` and ``val_loss`` (the training loss: MSE in m², or
    L1 in m) are over all those pixels at once, ``pixels`` is how many there were.

    On labelled object frames also ``car_in_box_<band>``: per distance band, the mean over the moderate
    cars of the share of their pixels whose point lands in their BEV box, and ``car_stray_<band>``: the
    share of the other pixels of their 2D boxes that land there too (benchmarks/accuracy.py --depth's two
    figures: the depth sources that lift the camera row put 0.87–0.96 of the far cars' pixels on them and
    at most 0.02 of the rest; docs/measurements.md, sessions 23 and 24).
    """
    net.eval()
    sq, ab, n = 0.0, 0.0, 0
    per_frame_rmse = []
    shares: list[tuple[float, float]] = []
    strays: list[tuple[float, float]] = []
    # Object folders may have labels; a depth-completion drive has none (its figures are RMSE and MAE alone).
    labelled = isinstance(dataset, DepthDataset) and (Path(dataset.data_dir) / "label_2").is_dir()
    index = 0
    for rgb, sparse, target, *_ in DataLoader(dataset, batch_size=2):
        prediction = net(rgb.to(device), sparse.to(device)).cpu()
        valid = target > 0
        err = (prediction - target)[valid] * 1000.0
        sq += float((err**2).sum())
        ab += float(err.abs().sum())
        n += int(valid.sum())
        for i in range(rgb.shape[0]):
            v = valid[i]
            if v.any():
                per_frame_rmse.append(float(torch.sqrt((((prediction[i] - target[i])[v] * 1000) ** 2).mean())))
            if labelled:
                on_car, stray = _car_shares(dataset, index, prediction[i, 0].numpy(), target[i, 0].numpy())
                shares += on_car
                strays += stray
            index += 1
    val_loss = sq / max(n, 1) / 1e6 if loss == "mse" else ab / max(n, 1) / 1e3
    metrics = {"val_loss": val_loss, "rmse_mm": float(np.mean(per_frame_rmse)) if per_frame_rmse else float("nan"),
               "mae_mm": ab / max(n, 1), "pixels": n}
    for name, per_car in (("car_in_box", shares), ("car_stray", strays)):
        metrics.update({f"{name}_{band}": c["mean_share"] for band, c in car_shares_by_band(per_car).items()
                        if c["cars"]})  # no NaN in log.jsonl
    return metrics


def _car_shares(dataset: DepthDataset, index: int, prediction: np.ndarray, target: np.ndarray
                ) -> tuple[list[tuple[float, float]], list[tuple[float, float]]]:
    """(car depth, share of its pixels landing in its BEV box) and (car depth, share of the other pixels of
    its 2D box landing there) of one validation frame's moderate cars.

    Reads only the frame's labels, calibration and image size, not its scan: this runs every epoch."""
    data, frame_id, preset = Path(dataset.data_dir), dataset.frame_ids[index], dataset.preset
    label_path = data / "label_2" / f"{frame_id}.txt"
    if not label_path.exists():
        return [], []
    image_hw = read_image_size(data / "image_2" / f"{frame_id}.png")
    cars = moderate_cars_in_view(read_labels(label_path), image_hw, preset.crop_hw, preset.depth.input_scale)
    calib = view_calibration(image_hw, read_calib(data / "calib" / f"{frame_id}.txt"), preset)
    return car_box_shares(prediction, target, cars, calib)


@torch.no_grad()
def validate_detector(pixor, preset: Preset, data_dir: Path, ids: list[str], input_mode: str,
                      pseudo_dir: Path | None, depth_net=None, device: torch.device = CPU,
                      beams: int | None = 16) -> dict:
    """Validation loss and KITTI BEV AP (moderate, R40) of PIXOR on the validation frames, their scans thinned to
    ``beams`` lines as the run's training frames are (None or 0: as stored; ``lidar64`` reads them as stored).

    The camera rows go through the Detector's own path (pseudo bins, then the voxelizer, whose height
    occupancy leaves out the pseudo points on depth edges), so the AP that picks a run's best epoch is
    the one ``benchmarks/accuracy.py`` measures, up to where the dense depth comes from (the PyTorch
    net in joint runs, the cached ONNX Runtime maps otherwise).
    """
    pixor.eval()
    if depth_net is not None:
        depth_net.eval()
    voxelizer = BevVoxelizer(preset.bev)
    gts, dets, losses = [], [], []
    for fid in ids:
        frame = load_frame(data_dir, fid, with_image=depth_net is not None)  # only joint runs the camera net
        if depth_net is not None or input_mode == "pseudo":
            depth, view_calib = (joint_depth(depth_net, frame, preset, device, beams) if depth_net is not None
                                 else cached_pseudo_depth(pseudo_dir, frame, preset))
            pseudo = pseudo_bins(depth, view_calib, preset.bev, *preset.pseudo_limits,
                                 max_jump=preset.decode.height_max_jump)
            bev = voxelizer(frame_points(frame, beams), pseudo)
        else:
            pseudo = None
            bev = voxelizer(detector_points(frame, preset, input_mode, pseudo_dir, beams))
        targets = encode_targets(car_boxes(frame), preset.bev, preset.pixor.output_stride, preset.decode)
        logits, regression = (t.cpu() for t in pixor.forward_logits(torch.from_numpy(bev)[None].to(device)))
        losses.append(float(pixor_loss(logits, regression, torch.from_numpy(targets.score)[None, None],
                                       torch.from_numpy(targets.regression)[None]).total))
        score = torch.sigmoid(logits)[0, 0].numpy()
        boxes, scores = boxes_from_maps(score, regression[0].numpy(), voxelizer.height_occupancy, preset,
                                        score_threshold=DEFAULT_SCORE_THRESHOLD, with_pseudo=pseudo is not None,
                                        mark=voxelizer.height_mark)
        seen = in_camera_view(boxes, frame.calib, frame.image_hw)
        objects = boxes_to_objects(boxes[seen], frame.calib, frame.image_hw, scores[seen])
        gts.append(LabelArrays.from_objects(frame.labels or []))
        dets.append(LabelArrays.from_objects(objects))
    result = evaluate(gts, dets, metrics=("bev",))
    table = result.ap_table()
    return {"val_loss": float(np.mean(losses)),
            "bev_ap_0.7_moderate": table["bev"]["0.7"]["R40"][1], "bev_ap_0.5_moderate": table["bev"]["0.5"]["R40"][1],
            "bev_ap": table["bev"]}
