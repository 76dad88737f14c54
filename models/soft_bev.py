"""Differentiable BEV occupancy for end-to-end fine-tuning (as in End-to-end Pseudo-LiDAR).

Hard voxelization has no gradient with respect to point positions. Here each
point spreads a Gaussian weight ``exp(-d²/σ²)`` (d in cell units) over the 2×2×2
voxels around it, soft occupancy is ``1 − exp(−Σ weights)``, and the forward
value is the hard occupancy exactly: ``hard + (soft − soft.detach())``. The
network sees the same grid as at inference; the gradient is the soft one.
"""

from __future__ import annotations

import torch

from pipeline.presets import BevGrid


def soft_occupancy(points: torch.Tensor, grid: BevGrid, sigma: float = 0.5) -> torch.Tensor:
    """(N, 3) points (differentiable) → (nz, ny, nx) occupancy, hard forward, soft gradient."""
    origin = points.new_tensor([grid.x_min, grid.y_min, grid.z_min])
    size = points.new_tensor([grid.cell, grid.cell, grid.z_cell])
    dims = torch.tensor([grid.nx, grid.ny, grid.nz], device=points.device)
    continuous = (points - origin) / size  # voxel k spans [k, k+1)
    # Hard bins in float64, exactly as pipeline.bev computes them.
    origin64 = torch.tensor([grid.x_min, grid.y_min, grid.z_min], dtype=torch.float64, device=points.device)
    size64 = torch.tensor([grid.cell, grid.cell, grid.z_cell], dtype=torch.float64, device=points.device)
    hard_index = torch.floor((points.detach().double() - origin64) / size64).long()
    inside = ((hard_index >= 0) & (hard_index < dims)).all(dim=1)
    flat_size = grid.nz * grid.ny * grid.nx

    def flat(ix: torch.Tensor) -> torch.Tensor:
        return (ix[:, 2] * grid.ny + ix[:, 1]) * grid.nx + ix[:, 0]

    hard = points.new_zeros(flat_size)
    hard[flat(hard_index[inside])] = 1.0

    # Soft part: the 8 voxel centres around each point.
    centred = continuous - 0.5
    base = torch.floor(centred.detach()).long()
    accumulated = points.new_zeros(flat_size)
    for corner in range(8):  # 8 neighbours, each a vectorized scatter over all points
        offset = torch.tensor([(corner >> 0) & 1, (corner >> 1) & 1, (corner >> 2) & 1], device=points.device)
        index = base + offset
        valid = ((index >= 0) & (index < dims)).all(dim=1)
        distance2 = ((centred - index.to(points.dtype)) ** 2).sum(dim=1)
        weight = torch.exp(-distance2 / sigma**2)
        accumulated = accumulated.index_add(0, flat(index[valid]), weight[valid])
    soft = 1.0 - torch.exp(-accumulated)
    occupancy = hard + (soft - soft.detach())
    return occupancy.view(grid.nz, grid.ny, grid.nx)
