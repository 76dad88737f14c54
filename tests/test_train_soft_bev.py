"""The joint fine-tuning's differentiable BEV: the soft occupancy's gradient against a float64 reference of its
definition, and joint_bev's forward value against the runtime's own pseudo points (mutation audit)."""

import numpy as np
import pytest
import torch

from models.joint import joint_bev, joint_depth
from models.soft_bev import soft_occupancy
from pipeline.beams import emulate_beams
from pipeline.bev import voxelize_bev
from pipeline.frame import load_frame
from pipeline.preprocess import depth_inputs, network_view
from pipeline.presets import BevGrid, get_preset
from pipeline.pseudo import pixel_rays, pseudo_xyz
from tests.conftest import KITTI

# A small grid with cells of other sizes in x, y (0.5 m) and z (0.25 m), and nx != ny != nz.
GRID = BevGrid(x_min=0.0, x_max=2.0, y_min=-1.0, y_max=0.5, z_min=-1.0, z_max=0.0, cell=0.5, z_cell=0.25)


def _reference_soft(points: torch.Tensor, sigma: float = 0.5) -> torch.Tensor:
    """(nz, ny, nx) soft occupancy 1 − exp(−Σ w) from its definition: each point gives each of the (up to 8)
    voxels whose centre is less than one cell away on every axis the weight exp(−d²/σ²), d in cell units."""
    origin = torch.tensor([GRID.x_min, GRID.y_min, GRID.z_min], dtype=torch.float64)
    size = torch.tensor([GRID.cell, GRID.cell, GRID.z_cell], dtype=torch.float64)
    q = (points - origin) / size  # cell units; voxel k's centre at k + 0.5
    iz, iy, ix = torch.meshgrid(torch.arange(GRID.nz), torch.arange(GRID.ny), torch.arange(GRID.nx), indexing="ij")
    centres = torch.stack([ix, iy, iz], dim=-1).to(torch.float64) + 0.5  # (nz, ny, nx, 3)
    offsets = q[:, None, None, None, :] - centres[None]  # (N, nz, ny, nx, 3)
    near = (offsets.abs() < 1.0).all(dim=-1)
    weights = torch.exp(-(offsets**2).sum(dim=-1) / sigma**2) * near
    return 1.0 - torch.exp(-weights.sum(dim=0))


def test_soft_occupancy_gradient_is_its_definitions_and_its_value_the_hard_grid():
    points = torch.tensor([[0.83, -0.31, -0.47],   # inside, away from every edge
                           [0.10, -0.90, -0.95],   # in the first cell of every axis: its lower neighbours are off-grid
                           [1.61, 0.22, -0.13]], dtype=torch.float64)
    jacobian = torch.autograd.functional.jacobian(lambda p: soft_occupancy(p, GRID), points)
    expected = torch.autograd.functional.jacobian(_reference_soft, points)
    assert jacobian.shape == (GRID.nz, GRID.ny, GRID.nx, 3, 3)
    assert expected.abs().sum() > 0
    torch.testing.assert_close(jacobian, expected, rtol=1e-9, atol=1e-12)
    hard = np.zeros((GRID.nz, GRID.ny, GRID.nx))
    for x, y, z in points.numpy():  # voxel k spans [k, k + 1) cells from the grid's minimum
        hard[int((z - GRID.z_min) // GRID.z_cell), int((y - GRID.y_min) // GRID.cell), int(x // GRID.cell)] = 1.0
    np.testing.assert_array_equal(soft_occupancy(points, GRID).detach().numpy(), hard)


def _joint_inputs(preset, depth_map: np.ndarray):
    frame = load_frame(KITTI, "000006")
    lidar16 = emulate_beams(frame.points, 16)
    _, view_calib = network_view(frame.image, frame.calib, preset)
    h, w = preset.depth.input_hw
    rays, origin = pixel_rays(view_calib, h, w, preset.decode.pseudo_stride)
    depth = torch.from_numpy(depth_map)[None].requires_grad_(True)
    bev = joint_bev(depth, torch.from_numpy(rays), torch.from_numpy(origin.astype(np.float32)), lidar16, preset)
    limits = (preset.depth.min_depth, preset.depth.max_depth, preset.decode.pseudo_stride,
              preset.decode.pseudo_max_height)
    return bev, depth, voxelize_bev(lidar16, preset.bev, pseudo=pseudo_xyz(depth_map, view_calib, *limits))


@pytest.mark.parametrize("name", ["tiny-near35", "edge-near35"])  # edge's grid reaches 10 cm above the height limit
def test_joint_bev_on_a_shared_grid_is_the_runtimes_bev_of_the_pseudo_points_and_the_scan(name):
    """The paper's shared grid: occupancy of pseudo + scan points and the reflectance channel as the runtime
    builds them, with the runtime's limits: depths from the net's floor (min_depth, kept) to max_depth (kept),
    nothing nearer or farther, nothing above pseudo_max_height."""
    preset = get_preset(name)  # max_depth 35 m: inside the 70 m grid, so the far limit shows
    h, w = preset.depth.input_hw
    depth_map = np.zeros((h, w), np.float32)
    band = h // 6
    depth_map[:2 * band] = 20.0  # the top rows at 20 m: up to metres above the sensor, dropped above the limit
    depth_map[h - 4 * band:h - 3 * band] = 35.0  # exactly max_depth: kept
    depth_map[h - 3 * band:h - 2 * band] = 50.0  # beyond max_depth: dropped
    depth_map[h - 2 * band:h - band] = preset.depth.min_depth  # the net's floor: kept
    depth_map[h - band:] = 0.5  # nearer than the floor: dropped
    bev, depth, expected = _joint_inputs(preset, depth_map)
    nz = preset.bev.nz
    assert bev.shape == expected.shape == preset.bev.shape
    scan_only = voxelize_bev(emulate_beams(load_frame(KITTI, "000006").points, 16), preset.bev)
    added = int((expected[:nz] > scan_only[:nz]).sum())  # voxels only the pseudo points fill
    assert added > 50
    # float32 back-projection here, float64 in pseudo_xyz: a point on a bin edge may land in the next voxel.
    assert int((bev[:nz].detach().numpy() != expected[:nz]).sum()) <= 0.02 * added
    np.testing.assert_allclose(bev[nz].detach().numpy(), expected[nz], atol=1e-6)  # reflectance: pseudo points as 0
    near = slice(0, round(2.0 / preset.bev.cell))  # x < 2 m: the floor band's points alone, the scan has none
    assert expected[:nz, :, near].sum() > 0
    np.testing.assert_array_equal(bev[:nz, :, near].detach().numpy(), expected[:nz, :, near])
    bev[:nz].sum().backward()
    assert depth.grad is not None and depth.grad.abs().sum() > 0


class _SparseInput(torch.nn.Module):
    """A 'depth net' that returns its sparse input, so joint_depth's output is the scan it was given."""

    def forward(self, rgb: torch.Tensor, sparse: torch.Tensor) -> torch.Tensor:
        return sparse


def test_joint_depth_feeds_the_net_the_scan_thinned_to_the_runs_lines():
    preset = get_preset("tiny")
    frame = load_frame(KITTI, "000006")
    thinned, _ = joint_depth(_SparseInput(), frame, preset, beams=16)
    stored, _ = joint_depth(_SparseInput(), frame, preset, beams=None)
    expected = depth_inputs(frame.image, emulate_beams(frame.points, 16), frame.calib, preset).sparse_depth[0, 0]
    np.testing.assert_array_equal(thinned, expected)
    assert 0 < int((thinned > 0).sum()) < 0.5 * int((stored > 0).sum())  # 16 of the stored 64 lines
