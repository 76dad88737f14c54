"""BEV voxelization against a plain per-point reference loop."""

import math
import warnings

import numpy as np
import pytest

from pipeline.bev import BevVoxelizer, voxelize_bev
from pipeline.kitti import read_velodyne
from pipeline.presets import PRESETS, BevGrid
from tests.conftest import KITTI


def reference_voxelize(points: np.ndarray, grid: BevGrid) -> np.ndarray:
    """The definition, one point at a time: floor bins, occupancy, mean reflectance."""
    out = np.zeros(grid.shape, np.float32)
    sums = np.zeros((grid.ny, grid.nx))
    counts = np.zeros((grid.ny, grid.nx))
    for x, y, z, r in points.tolist():
        ix = math.floor((x - grid.x_min) / grid.cell)
        iy = math.floor((y - grid.y_min) / grid.cell)
        iz = math.floor((z - grid.z_min) / grid.z_cell)
        if 0 <= ix < grid.nx and 0 <= iy < grid.ny and 0 <= iz < grid.nz:
            out[iz, iy, ix] = 1.0
            sums[iy, ix] += r
            counts[iy, ix] += 1
    np.divide(sums, counts, out=sums, where=counts > 0)
    out[grid.nz] = sums
    return out


def random_cloud(grid: BevGrid, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    margin = 2.0
    points = np.column_stack([
        rng.uniform(grid.x_min - margin, grid.x_max + margin, n),
        rng.uniform(grid.y_min - margin, grid.y_max + margin, n),
        rng.uniform(grid.z_min - margin, grid.z_max + margin, n),
        rng.uniform(0, 1, n),
    ])
    # A third of the points exactly on bin edges (and the grid's own borders).
    edges = rng.random((n, 3)) < 0.33
    points[:, 0] = np.where(edges[:, 0], grid.x_min + rng.integers(-2, grid.nx + 2, n) * grid.cell, points[:, 0])
    points[:, 1] = np.where(edges[:, 1], grid.y_min + rng.integers(-2, grid.ny + 2, n) * grid.cell, points[:, 1])
    points[:, 2] = np.where(edges[:, 2], grid.z_min + rng.integers(-2, grid.nz + 2, n) * grid.z_cell, points[:, 2])
    return points.astype(np.float32)


@pytest.mark.parametrize("preset", ["paper", "edge", "tiny"])
def test_equals_reference_loop_on_random_clouds(preset):
    grid = PRESETS[preset].bev
    points = random_cloud(grid, 20000, seed=1)
    np.testing.assert_array_equal(voxelize_bev(points, grid), reference_voxelize(points, grid))


def test_layout_of_a_single_point():
    grid = BevGrid()
    bev = voxelize_bev(np.array([[12.34, -5.0, 0.05, 0.7]], np.float32), grid)
    assert bev.shape == (36, 800, 700) and bev.dtype == np.float32
    # x 12.34 → column 123; y -5.0 (an edge) → row 350; z 0.05 → slice 25.
    assert bev[25, 350, 123] == 1.0
    assert bev[35, 350, 123] == pytest.approx(0.7)
    assert np.count_nonzero(bev) == 2


def test_reused_buffer_clears_previous_frame():
    grid = PRESETS["edge"].bev
    voxelizer = BevVoxelizer(grid)
    first = random_cloud(grid, 5000, seed=2)
    second = random_cloud(grid, 3000, seed=3)
    voxelizer(first)
    np.testing.assert_array_equal(voxelizer(second), reference_voxelize(second, grid))
    np.testing.assert_array_equal(voxelizer(np.zeros((0, 4), np.float32)), np.zeros(grid.shape, np.float32))


def test_reused_buffers_clear_the_pseudo_points_of_the_previous_frame():
    """Frames with pseudo points, on the shared and the split grid, then frames with fewer or none: each
    result equals a fresh voxelizer's, in the BEV and in the occupancy box heights read."""
    from pipeline.bev import pseudo_bins
    from pipeline.presets import get_preset

    frame, preset, view_calib = _kitti_view()
    depth, limits = _road_with_a_near_object(preset)
    for grid in (preset.bev, get_preset("edge-split-near35").bev):
        many = pseudo_bins(depth, view_calib, grid, *limits, max_jump=0.1)
        few = pseudo_bins(depth[::-1].copy(), view_calib, grid, *limits, max_jump=0.1)
        voxelizer = BevVoxelizer(grid)
        for points, pseudo in ((frame.points, many), (frame.points[:500], few), (frame.points[:100], None)):
            fresh = BevVoxelizer(grid)
            np.testing.assert_array_equal(voxelizer(points, pseudo), fresh(points, pseudo))
            np.testing.assert_array_equal(voxelizer.height_voxels(), fresh.height_voxels())


# Run in a fresh interpreter: in a process whose allocator already holds freed memory (as the test
# workers do, and training's allocator settings), np.zeros may reuse it, zeroed and so already written.
_PAGE_FAULTS = """
import resource, sys
from pipeline.bev import BevVoxelizer
from pipeline.kitti import read_velodyne
from pipeline.presets import PRESETS

points = read_velodyne(sys.argv[1]).points
kept = []
for prefault in (False, True):
    voxelizer = BevVoxelizer(PRESETS["edge"].bev, prefault=prefault)
    kept += [voxelizer(points), voxelizer.mirrored()]
    before = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
    for buffer in kept[-2:]:
        buffer.fill(0.5)  # every page of the BEV and of its mirror
    print(resource.getrusage(resource.RUSAGE_THREAD).ru_minflt - before)
"""


def test_a_prefaulted_voxelizer_writes_every_page_when_made():
    """A Detector's kept voxelizer pays its page faults at start-up, not over its first frames; its BEV
    and mirror are the plain voxelizer's."""
    import subprocess
    import sys

    scan = KITTI / "velodyne" / "000006.bin"
    result = subprocess.run([sys.executable, "-c", _PAGE_FAULTS, str(scan)], capture_output=True, text=True,
                            check=True, timeout=120)
    plain, prefaulted = map(int, result.stdout.split())
    assert prefaulted <= 2 < plain
    points = read_velodyne(scan).points
    grid = PRESETS["edge"].bev
    voxelizer = BevVoxelizer(grid, prefault=True)
    np.testing.assert_array_equal(voxelizer(points), voxelize_bev(points, grid))
    np.testing.assert_array_equal(voxelizer.mirrored(), voxelize_bev(points, grid)[:, ::-1])


def test_real_scan_equals_reference():
    points = read_velodyne(KITTI / "velodyne" / "000006.bin").points
    grid = BevGrid()
    bev = voxelize_bev(points, grid)
    np.testing.assert_array_equal(bev, reference_voxelize(points, grid))
    assert 10000 < np.count_nonzero(bev[:35]) < 60000


def test_pseudo_arrays_voxelize_like_the_merged_cloud():
    """The Detector's fused path (pseudo x, y, z arrays + real points) equals voxelizing the merged cloud."""
    from pipeline.frame import load_frame
    from pipeline.preprocess import network_view
    from pipeline.pseudo import depth_to_points, merge_points, pseudo_xyz

    frame = load_frame(KITTI, "000006")
    preset = PRESETS["edge"]
    _, view_calib = network_view(frame.image, frame.calib, preset)
    depth = np.random.default_rng(4).uniform(0.5, 90, preset.depth.input_hw).astype(np.float32)
    limits = (preset.depth.min_depth, preset.depth.max_depth, 1, preset.decode.pseudo_max_height)
    voxelizer = BevVoxelizer(preset.bev)
    voxelizer(frame.points)  # a previous frame in the reused buffer
    fused = voxelizer(frame.points, pseudo_xyz(depth, view_calib, *limits)).copy()
    merged = merge_points(depth_to_points(depth, view_calib, *limits), frame.points)
    np.testing.assert_array_equal(fused, reference_voxelize(merged, preset.bev))
    # Pseudo points dilute the reflectance of the cells they share with real returns.
    assert 0 < np.count_nonzero(fused[-1]) < np.count_nonzero(fused[:-1].any(axis=0))


def _kitti_view(preset_name: str = "edge"):
    from pipeline.frame import load_frame
    from pipeline.preprocess import network_view

    frame = load_frame(KITTI, "000006")
    preset = PRESETS[preset_name]
    _, view_calib = network_view(frame.image, frame.calib, preset)
    return frame, preset, view_calib


def _road_with_a_near_object(preset):
    """A depth map of the preset's view: a road whose depth falls from 60 to 3 m down the rows, and a near
    object (8 m) whose outline jumps against it; and the Detector's pseudo-point limits at stride 1."""
    h, w = preset.depth.input_hw
    depth = np.repeat(np.linspace(60, 3, h, dtype=np.float32)[:, None], w, axis=1)
    depth[h // 2:, w // 3:w // 2] = 8.0
    limits = (preset.depth.min_depth, preset.depth.max_depth, 1, preset.decode.pseudo_max_height)
    return depth, limits


def test_pseudo_bins_straight_from_depth_match_binning_the_points():
    """The Detector bins pseudo points from the depth map without building them; it matches binning the
    points themselves but for float32 rounding at bin edges (pipeline.bev.pseudo_bins says why)."""
    from pipeline.bev import bins_of_xyz, pseudo_bins
    from pipeline.pseudo import pseudo_xyz

    frame, preset, view_calib = _kitti_view()
    h, w = preset.depth.input_hw
    # A road-like map: depth grows towards the horizon, plus noise (every value a fresh float).
    rows = np.linspace(80, 2, h, dtype=np.float32)[:, None]
    depth = (rows + np.random.default_rng(5).uniform(-1, 1, (h, w))).astype(np.float32)
    limits = (preset.depth.min_depth, preset.depth.max_depth, 1, preset.decode.pseudo_max_height)
    fused = pseudo_bins(depth, view_calib, preset.bev, *limits)
    reference = bins_of_xyz(*pseudo_xyz(depth, view_calib, *limits), preset.bev)
    assert reference.cell.size > 30000
    assert abs(fused.cell.size - reference.cell.size) <= 1e-3 * reference.cell.size
    ours, theirs = np.unique(fused.occupancy), np.unique(reference.occupancy)
    assert np.setxor1d(ours, theirs).size <= 1e-3 * theirs.size
    np.testing.assert_array_equal(fused.occupancy % (preset.bev.ny * preset.bev.nx), fused.cell)
    # The same voxelizer output but for those few voxels.
    voxelizer = BevVoxelizer(preset.bev)
    with_bins = voxelizer(frame.points, fused).copy()
    with_xyz = voxelizer(frame.points, reference).copy()
    assert np.count_nonzero(with_bins != with_xyz) <= 1e-3 * np.count_nonzero(with_xyz)


def test_pseudo_bins_drop_what_is_outside_without_warnings():
    from pipeline.bev import pseudo_bins

    _, preset, view_calib = _kitti_view()
    depth = np.full(preset.depth.input_hw, 20.0, np.float32)
    depth[0, :4] = [np.nan, np.inf, 1e30, -5.0]  # not depths, or far beyond int32 bins
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        bins = pseudo_bins(depth, view_calib, preset.bev, 0.9, 80.0, 1, None)
        marked = pseudo_bins(depth, view_calib, preset.bev, 0.9, 80.0, 1, None, max_jump=0.1)
    np.testing.assert_array_equal(marked.occupancy, bins.occupancy)
    assert marked.sharp.dtype == bool and marked.sharp.size == bins.cell.size
    grid = preset.bev
    assert bins.cell.size > 0 and bins.cell.min() >= 0 and bins.occupancy.max() < grid.nz * grid.ny * grid.nx
    # Every kept point sits 20 m ahead (the 20 m depth plane), whatever row its bin came from.
    ix = bins.cell % grid.nx
    assert np.all(np.abs(grid.x_min + (ix + 0.5) * grid.cell - 20.0) < 1.5)
    # Another grid on the same calibration gets its own bin rays.
    other = pseudo_bins(depth, view_calib, PRESETS["paper"].bev, 0.9, 80.0, 1, None)
    assert other.occupancy.max() >= grid.nz * grid.ny * grid.nx  # the paper grid is larger


def test_depth_jumps_mark_both_sides_of_an_edge_and_the_smear_between():
    """A car at 10 m in front of a wall at 30 m, with two smeared pixels between them: the edge pixels and
    the smear are marked; the flat car, the flat wall and a road whose depth grows smoothly are not."""
    from pipeline.pseudo import depth_jumps

    depth = np.full((6, 12), 30.0, np.float32)
    depth[:, :5] = 10.0
    depth[:, 5:7] = [15.0, 25.0]  # the completion network's blur across the edge
    marked = depth_jumps(depth, 0.1)
    np.testing.assert_array_equal(marked.any(axis=0), [0, 0, 0, 0, 1, 1, 1, 1, 0, 0, 0, 0])
    assert marked[:, 4:8].all()
    road = np.repeat(np.geomspace(80, 5, 40, dtype=np.float32)[:, None], 30, axis=1)  # 7 % per row
    assert not depth_jumps(road, 0.1).any()
    assert depth_jumps(road, 0.05)[1:-1].all()
    # The same as comparing each pixel with its four neighbours one by one.
    rng = np.random.default_rng(3)
    noisy = rng.uniform(5, 50, (20, 30)).astype(np.float32)
    expected = np.zeros(noisy.shape, bool)
    for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        shifted = np.full((22, 32), np.nan, np.float32)
        shifted[1 + dy:21 + dy, 1 + dx:31 + dx] = noisy
        with np.errstate(invalid="ignore"):
            expected |= np.abs(shifted[1:21, 1:31] - noisy) > np.float32(0.2) * noisy
    np.testing.assert_array_equal(depth_jumps(noisy, 0.2), expected)


def test_heights_read_the_real_and_sharp_pseudo_points_only():
    """PIXOR's BEV keeps every pseudo point; the occupancy for box heights leaves out those on depth jumps,
    and is exactly the voxelization of the real points plus the pseudo points off the jumps."""
    from pipeline.bev import pseudo_bins
    from pipeline.pseudo import depth_jumps

    frame, preset, view_calib = _kitti_view()
    grid = preset.bev
    depth, limits = _road_with_a_near_object(preset)
    plain = pseudo_bins(depth, view_calib, grid, *limits)
    marked = pseudo_bins(depth, view_calib, grid, *limits, max_jump=0.1)
    np.testing.assert_array_equal(marked.occupancy, plain.occupancy)
    assert plain.sharp is None and 0 < np.count_nonzero(~marked.sharp) < marked.sharp.size

    voxelizer = BevVoxelizer(grid)
    bev = voxelizer(frame.points, marked).copy()
    np.testing.assert_array_equal(bev, BevVoxelizer(grid)(frame.points, plain))
    cleaned = depth.copy()
    cleaned[depth_jumps(depth, 0.1)] = 0.0  # below min_depth: dropped
    expected = BevVoxelizer(grid)(frame.points, pseudo_bins(cleaned, view_calib, grid, *limits))[:grid.nz]
    np.testing.assert_array_equal(voxelizer.height_voxels(), expected.astype(bool))
    assert voxelizer.height_voxels().sum() < bev[:grid.nz].sum()

    # The next frame clears what this one set; without marked points the heights read the BEV itself.
    voxelizer(frame.points[:1000], pseudo_bins(depth[::-1].copy(), view_calib, grid, *limits, max_jump=0.1))
    again = voxelizer(frame.points, marked)
    np.testing.assert_array_equal(voxelizer.height_voxels(), expected.astype(bool))
    voxelizer(frame.points)
    assert voxelizer.height_occupancy is again


def test_height_grid_stamps_come_round_without_stale_voxels():
    """The height grid is never cleared cell by cell: each frame writes its own stamp, and after 255 frames
    the stamps start again on a zeroed grid. Around that turn, and with frames that read the BEV itself in
    between, every frame's heights equal a fresh voxelizer's."""
    from pipeline.bev import pseudo_bins

    frame, preset, view_calib = _kitti_view()
    grid = preset.bev
    depth, limits = _road_with_a_near_object(preset)
    near = pseudo_bins(depth, view_calib, grid, *limits, max_jump=0.1)
    far = pseudo_bins(depth[::-1].copy(), view_calib, grid, *limits, max_jump=0.1)
    voxelizer = BevVoxelizer(grid)
    stamps = []
    # The first frame's voxels are never written again: a stale stamp 1 would show at the turn.
    frames = [(frame.points[:300], near)] + [(frame.points[300:600], far), (frame.points[600:650], None)] * 300
    for index, (points, pseudo) in enumerate(frames):
        bev = voxelizer(points, pseudo)
        if pseudo is None:
            assert voxelizer.height_occupancy is bev and voxelizer.height_mark == 1
        else:
            stamps.append(voxelizer.height_mark)
        if voxelizer.height_mark in (1, 2, 254, 255) or index >= len(frames) - 4:
            fresh = BevVoxelizer(grid)
            fresh(points, pseudo)
            np.testing.assert_array_equal(voxelizer.height_voxels(), fresh.height_voxels())
    assert stamps[:255] == list(range(1, 256)) and stamps[255:258] == [1, 2, 3]


def test_split_grid_keeps_the_pseudo_points_in_channels_of_their_own():
    """On a ``split_pseudo`` grid the first nz + 1 channels are the scan's own BEV (the reflectance of its
    returns alone) and the last nz the pseudo points' occupancy: together what the shared grid holds, and
    box heights read the same occupancy as there."""
    from dataclasses import replace

    from pipeline.bev import pseudo_bins

    frame, preset, view_calib = _kitti_view()
    shared = preset.bev
    split = replace(shared, split_pseudo=True)
    nz = shared.nz
    depth, limits = _road_with_a_near_object(preset)
    bins = pseudo_bins(depth, view_calib, split, *limits, max_jump=0.1)

    voxelizer = BevVoxelizer(split)
    voxelizer(frame.points[::7], pseudo_bins(depth[::-1].copy(), view_calib, split, *limits))  # a previous frame
    out = voxelizer(frame.points, bins).copy()
    assert out.shape == (2 * nz + 1, shared.ny, shared.nx) == split.shape
    np.testing.assert_array_equal(out[:nz + 1], reference_voxelize(frame.points, shared))
    merged = BevVoxelizer(shared)
    together = merged(frame.points, bins)
    np.testing.assert_array_equal(np.maximum(out[:nz], out[nz + 1:]), together[:nz])
    assert np.count_nonzero(out[nz + 1:]) > np.count_nonzero(out[:nz]) > 0
    np.testing.assert_array_equal(voxelizer.height_voxels(), merged.height_voxels())
    # Without pseudo points the pseudo channels are empty and the rest is the scan's BEV.
    alone = voxelizer(frame.points)
    assert not alone[nz + 1:].any()
    np.testing.assert_array_equal(alone[:nz + 1], reference_voxelize(frame.points, shared))


@pytest.mark.parametrize("split_pseudo", [False, True])
def test_points_then_pseudo_points_equal_one_call(split_pseudo):
    """The Detector writes a frame in two halves (the real points while the depth net runs, then the pseudo
    points): the tensor and the heights' occupancy equal one call's, frame after frame of the reused buffer."""
    from dataclasses import replace

    from pipeline.bev import pseudo_bins

    frame, preset, view_calib = _kitti_view()
    grid = replace(preset.bev, split_pseudo=split_pseudo)
    depth, limits = _road_with_a_near_object(preset)
    whole, halves = BevVoxelizer(grid), BevVoxelizer(grid)
    for points, d in ((frame.points, depth), (frame.points[::5], depth[::-1].copy()), (frame.points[1::3], None)):
        bins = None if d is None else pseudo_bins(d, view_calib, grid, *limits, max_jump=0.1)
        expected = whole(points, bins).copy()
        halves.add_points(points)
        np.testing.assert_array_equal(halves.add_pseudo(bins), expected)
        np.testing.assert_array_equal(halves.height_voxels(), whole.height_voxels())


@pytest.mark.parametrize("split_pseudo", [False, True])
def test_mirrored_bev_equals_the_reversed_rows_frame_after_frame(split_pseudo):
    """``mirrored()`` writes only the cells a frame set into its own reused buffer: it must equal the BEV with
    its rows reversed, with nothing left over from a fuller frame before (pseudo points, then none)."""
    from dataclasses import replace

    from pipeline.bev import pseudo_bins

    frame, preset, view_calib = _kitti_view()
    grid = replace(preset.bev, split_pseudo=split_pseudo)
    depth, limits = _road_with_a_near_object(preset)
    voxelizer = BevVoxelizer(grid)
    for points, d in ((frame.points, depth), (frame.points[::5], depth[::-1].copy()), (frame.points[1::3], None),
                      (frame.points[:200], depth)):
        bins = None if d is None else pseudo_bins(d, view_calib, grid, *limits, max_jump=0.1)
        bev = voxelizer(points, bins)
        mirrored = voxelizer.mirrored()
        assert mirrored is not bev and mirrored.flags.c_contiguous
        np.testing.assert_array_equal(mirrored, bev[:, ::-1])
        assert np.count_nonzero(mirrored[grid.nz]) > 0  # the reflectance plane came along


def test_near35_keeps_the_pseudo_points_up_to_35_m_only():
    """``-near35``: on the real frame's view, a road-like depth map keeps its pixels up to 35 m, whose bins
    all lie within 35 m ahead of the camera, and drops the farther ones that ``edge`` keeps."""
    from pipeline.bev import pseudo_bins
    from pipeline.presets import get_preset

    _, preset, view_calib = _kitti_view()
    h, w = preset.depth.input_hw
    depth = np.repeat(np.linspace(80, 2, h, dtype=np.float32)[:, None], w, axis=1)
    near = get_preset(f"{preset.name}-near35")
    kept = pseudo_bins(depth, view_calib, near.bev, *near.pseudo_limits)
    everything = pseudo_bins(depth, view_calib, preset.bev, *preset.pseudo_limits)
    assert 0 < kept.cell.size < everything.cell.size
    x_metres = near.bev.x_min + (kept.cell % near.bev.nx + 1) * near.bev.cell  # the far edge of each bin
    assert x_metres.max() <= 35.0 + 0.3 + near.bev.cell  # the camera sits 0.27 m ahead of the LiDAR
    far = near.bev.x_min + (everything.cell % near.bev.nx) * near.bev.cell
    assert far.max() > 45.0


def test_pseudo_bins_keep_depths_on_the_limits_as_the_points_do():
    """Pixels at exactly min_depth or max_depth are kept (compared in float32, as pseudo_xyz and the port spec
    keep them); one float32 step outside either limit is dropped."""
    from pipeline.bev import bins_of_xyz, pseudo_bins
    from pipeline.pseudo import pseudo_xyz

    _, preset, view_calib = _kitti_view()
    h, w = preset.depth.input_hw
    for limit, outside in ((2.0, 1.0), (30.0, 80.0)):  # exactly on min_depth, then on max_depth
        on = np.full((h, w), np.float32(limit))
        bins = pseudo_bins(on, view_calib, preset.bev, 2.0, 30.0)
        reference = bins_of_xyz(*pseudo_xyz(on, view_calib, 2.0, 30.0), preset.bev)
        assert bins.cell.size == reference.cell.size > 1000
        beyond = np.full((h, w), np.nextafter(np.float32(limit), np.float32(outside)))
        assert pseudo_bins(beyond, view_calib, preset.bev, 2.0, 30.0).cell.size == 0


def test_pseudo_bins_on_a_grid_whose_slices_are_not_its_cells():
    """A grid whose height slices differ from its cells (tiny: 0.4 m cells, 0.5 m slices): z bins and the
    max_height limit are in slices, not cells, so the bins equal binning the points themselves."""
    from pipeline.bev import bins_of_xyz, pseudo_bins
    from pipeline.pseudo import pseudo_xyz

    _, preset, view_calib = _kitti_view()
    grid = PRESETS["tiny"].bev
    assert grid.cell != grid.z_cell
    h, w = preset.depth.input_hw
    rows = np.linspace(60, 2, h, dtype=np.float32)[:, None]
    depth = (rows + np.random.default_rng(6).uniform(-1, 1, (h, w))).astype(np.float32)
    for max_height in (None, -1.0):
        bins = pseudo_bins(depth, view_calib, grid, 0.9, 80.0, 1, max_height)
        reference = bins_of_xyz(*pseudo_xyz(depth, view_calib, 0.9, 80.0, 1, max_height), grid)
        assert reference.cell.size > 10000
        assert abs(bins.cell.size - reference.cell.size) <= 1e-3 * reference.cell.size
        ours, theirs = np.unique(bins.occupancy), np.unique(reference.occupancy)
        assert np.setxor1d(ours, theirs).size <= 1e-3 * theirs.size
    top = grid.z_min + (bins.occupancy // (grid.ny * grid.nx)) * grid.z_cell  # the lower edge of each slice
    assert top.max() <= -1.0


def test_pseudo_bins_of_two_grids_on_one_calibration_are_each_grids_own():
    """The bin rays are cached per calibration and grid: a second grid on the same view gets its own bins."""
    from pipeline.bev import bins_of_xyz, pseudo_bins
    from pipeline.pseudo import pseudo_xyz

    _, preset, view_calib = _kitti_view()
    depth = np.full(preset.depth.input_hw, 20.0, np.float32)
    for grid in (preset.bev, PRESETS["paper"].bev, preset.bev):
        bins = pseudo_bins(depth, view_calib, grid, 0.9, 80.0)
        reference = bins_of_xyz(*pseudo_xyz(depth, view_calib, 0.9, 80.0), grid)
        assert np.setxor1d(np.unique(bins.occupancy), np.unique(reference.occupancy)).size <= 2


def test_a_depth_jump_of_exactly_max_jump_is_not_one():
    """"More than max_jump × its own depth": 10 m beside 15 m is a jump of exactly 0.5 × 10 m, not more, so at
    max_jump 0.5 neither side is marked; at 0.49 the 10 m side is (5 > 4.9) and the 15 m side is not (5 < 7.35)."""
    from pipeline.pseudo import depth_jumps

    depth = np.array([[10.0, 15.0]], np.float32)
    np.testing.assert_array_equal(depth_jumps(depth, 0.5), [[False, False]])
    np.testing.assert_array_equal(depth_jumps(depth, 0.49), [[True, False]])
