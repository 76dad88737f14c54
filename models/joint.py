"""The joint task's torch path from the depth net to PIXOR's input: the net's dense depth of a frame, and a
bird's-eye view of it whose occupancy is differentiable (models/soft_bev.py), so that PIXOR's loss reaches
the depth net. The training step that joins them is models.train.joint_step.
"""

from __future__ import annotations

import numpy as np
import torch

from models.data import frame_points
from models.devices import CPU
from models.soft_bev import soft_occupancy
from pipeline.bev import voxelize_bev
from pipeline.calib import Calibration
from pipeline.preprocess import depth_inputs
from pipeline.presets import Preset, lidar_only


def joint_depth(depth_net, frame, preset: Preset, device: torch.device = CPU,
                beams: int | None = 16) -> tuple[np.ndarray, Calibration]:
    """The (torch) depth net's dense depth of a frame's scan thinned to ``beams`` lines (None or 0: as stored),
    and its view's calibration (validation)."""
    inputs = depth_inputs(frame.image, frame_points(frame, beams), frame.calib, preset)
    depth = depth_net(torch.from_numpy(inputs.rgb).to(device), torch.from_numpy(inputs.sparse_depth).to(device))
    return depth[0, 0].cpu().numpy(), inputs.calib


def joint_bev(depth: torch.Tensor, rays: torch.Tensor, origin: torch.Tensor, lidar16: np.ndarray,
              preset: Preset) -> torch.Tensor:
    """Differentiable BEV of one frame: soft occupancy of pseudo + real points, hard reflectance channel."""
    d = preset.decode
    stride = d.pseudo_stride
    sub = depth[0, ::stride, ::stride]
    points = sub[None] * rays + origin[:, None, None]  # (3, h, w)
    valid = (sub >= preset.depth.min_depth) & (sub <= preset.depth.max_depth) & (points[2] <= d.pseudo_max_height)
    pseudo = points.permute(1, 2, 0)[valid]
    if preset.bev.split_pseudo:  # the scan's own channels are hard; only the pseudo channels have a gradient
        lidar = voxelize_bev(lidar16.astype(np.float32, copy=False), lidar_only(preset).bev)
        return torch.cat([torch.from_numpy(lidar).to(depth.device), soft_occupancy(pseudo, preset.bev)])
    real = torch.from_numpy(lidar16[:, :3]).to(depth.device)
    occupancy = soft_occupancy(torch.cat([pseudo, real]), preset.bev)
    merged = np.concatenate([np.column_stack([pseudo.detach().cpu().numpy(), np.zeros(len(pseudo), np.float32)]),
                             lidar16])
    reflectance = torch.from_numpy(voxelize_bev(merged.astype(np.float32), preset.bev)[-1:]).to(depth.device)
    return torch.cat([occupancy, reflectance])
