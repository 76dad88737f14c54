"""Calibration, projection, the depth-net crop, sparse depth and pseudo points on real frames."""

import numpy as np
import pytest

from pipeline.calib import crop_calibration, depth_crop, sparse_depth_map
from pipeline.errors import InputError
from pipeline.frame import load_frame
from pipeline.pseudo import depth_to_points, merge_points
from tests.conftest import FRAMES, KITTI


@pytest.mark.parametrize("frame_id", FRAMES)
def test_project_and_backproject_within_1mm(frame_id):
    frame = load_frame(KITTI, frame_id)
    xyz = frame.points[:, :3].astype(np.float64)
    uv, depth = frame.calib.velo_to_image(xyz)
    front = depth > 1.0
    back = frame.calib.image_to_velo(uv[front, 0], uv[front, 1], depth[front])
    assert np.abs(back - xyz[front]).max() < 1e-3


def test_velo_rect_roundtrip_is_exact():
    frame = load_frame(KITTI, "000006")
    xyz = frame.points[:1000, :3].astype(np.float64)
    np.testing.assert_allclose(frame.calib.rect_to_velo(frame.calib.velo_to_rect(xyz)), xyz, atol=1e-9)


@pytest.mark.parametrize("frame_id", FRAMES)
def test_crop_shifts_intrinsics_exactly(frame_id):
    frame = load_frame(KITTI, frame_id)
    crop = depth_crop(frame.image_hw)
    assert crop.top == frame.image_hw[0] - 352 and crop.height == 352 and crop.width == 1216
    assert crop.left == (frame.image_hw[1] - 1216) // 2
    cropped = crop_calibration(frame.calib, crop)
    uv, depth = frame.calib.velo_to_image(frame.points[:, :3])
    uv_c, depth_c = cropped.velo_to_image(frame.points[:, :3])
    np.testing.assert_allclose(uv_c, uv - [crop.left, crop.top], atol=1e-9)
    np.testing.assert_allclose(depth_c, depth, atol=1e-12)
    assert crop.apply(frame.image).shape == (352, 1216, 3)


def test_crop_refuses_small_image():
    with pytest.raises(InputError, match="smaller than the model's 1216×352 crop"):
        depth_crop((300, 1242))


def test_sparse_depth_nearest_return_wins():
    frame = load_frame(KITTI, "000006")
    calib = frame.calib
    # Three points on one camera ray: the nearest must win, wherever it is in the array.
    xyz = calib.image_to_velo(np.full(3, 600.0), np.full(3, 200.0), np.array([20.0, 10.0, 30.0]))
    points = np.column_stack([xyz, np.zeros(3)]).astype(np.float32)
    depth_map = sparse_depth_map(points, calib, frame.image_hw)
    assert np.count_nonzero(depth_map) == 1
    assert depth_map[200, 600] == pytest.approx(10.0, rel=1e-6)


def test_sparse_depth_of_real_scan_matches_projection():
    frame = load_frame(KITTI, "000006")
    depth_map = sparse_depth_map(frame.points, frame.calib, frame.image_hw)
    filled = np.count_nonzero(depth_map) / depth_map.size
    assert 0.03 < filled < 0.08  # a 64-line scan fills about 4–5 % of a KITTI image
    # Every filled pixel is the minimum depth of the points landing on it.
    uv, depth = frame.calib.velo_to_image(frame.points[:, :3])
    cols, rows = np.rint(uv[:, 0]), np.rint(uv[:, 1])
    h, w = frame.image_hw
    ok = (depth > 0.1) & (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
    reference = np.full(h * w, np.inf)
    np.minimum.at(reference, (rows[ok] * w + cols[ok]).astype(int), depth[ok])
    reference[np.isinf(reference)] = 0
    np.testing.assert_array_equal(depth_map.reshape(-1), reference.astype(np.float32))


def test_pseudo_points_reproduce_the_scan_they_came_from():
    frame = load_frame(KITTI, "000006")
    depth_map = sparse_depth_map(frame.points, frame.calib, frame.image_hw)
    pseudo = depth_to_points(depth_map, frame.calib, min_depth=0.9, max_depth=80.0)
    assert pseudo.shape == (np.count_nonzero((depth_map >= 0.9) & (depth_map <= 80)), 4)
    assert (pseudo[:, 3] == 0).all()
    # Pixel rounding moves a point by at most half a pixel: under 3 cm at 80 m.
    uv, _ = frame.calib.velo_to_image(pseudo[:, :3])
    assert np.abs(uv - np.rint(uv)).max() < 1e-3
    ranges = np.hypot(pseudo[:, 0], pseudo[:, 1])
    assert ranges.max() < 81 and pseudo[:, 0].min() > 0
    # Subsampling and height limit.
    assert depth_to_points(depth_map, frame.calib, 0.9, 80.0, stride=2).shape[0] < pseudo.shape[0] / 3
    assert (depth_to_points(depth_map, frame.calib, 0.9, 80.0, max_height=0.5)[:, 2] <= 0.5).all()
    merged = merge_points(pseudo, frame.points)
    assert merged.shape[0] == pseudo.shape[0] + frame.points.shape[0]


def test_pixel_rays_equal_exact_backprojection():
    from pipeline.preprocess import network_view
    from pipeline.presets import PRESETS

    frame = load_frame(KITTI, "000006")
    _, view_calib = network_view(frame.image, frame.calib, PRESETS["edge"])
    rng = np.random.default_rng(0)
    depth = rng.uniform(1, 80, (176, 608)).astype(np.float32)
    points = depth_to_points(depth, view_calib, 0.0, 1e9)
    rows, cols = np.divmod(np.arange(depth.size), depth.shape[1])
    exact = view_calib.image_to_velo(cols, rows, depth.reshape(-1))
    assert np.abs(points[:, :3] - exact).max() < 2e-4  # float32 rays, metres


def test_pixel_rays_are_the_float64_rays_rounded_once():
    """Each float32 ray is its float64 value d/du·u + d/dv·v + c rounded once, at any stride: the
    pseudo points of training and of the runtime agree bit for bit however the table is built."""
    from pipeline.pseudo import pixel_rays

    calib = load_frame(KITTI, "000001").calib
    direction = calib.rect_to_velo_matrix[:3, :3] @ np.linalg.inv(calib.P2[:, :3])
    for stride in (1, 3):
        rays, _ = pixel_rays(calib, 37, 53, stride)
        v, u = np.mgrid[0:37:stride, 0:53:stride].astype(np.float64)
        for axis in range(3):
            expected = (direction[axis, 0] * u + direction[axis, 1] * v) + direction[axis, 2]
            np.testing.assert_array_equal(rays[axis], expected.astype(np.float32))


def test_resized_view_calibration_matches_area_resampling():
    from pipeline.preprocess import depth_inputs, network_view
    from pipeline.presets import PRESETS

    frame = load_frame(KITTI, "000006")
    preset = PRESETS["edge"]
    view, view_calib = network_view(frame.image, frame.calib, preset)
    assert view.shape == (*preset.depth.input_hw, 3)
    crop = depth_crop(frame.image_hw)
    full_calib = crop_calibration(frame.calib, crop)
    # A full-resolution pixel centre (u, v) lands at s·u + (s − 1)/2 in the half-resolution view.
    xyz = frame.points[frame.points[:, 0] > 5, :3]
    uv_full, _ = full_calib.velo_to_image(xyz)
    uv_half, _ = view_calib.velo_to_image(xyz)
    np.testing.assert_allclose(uv_half, 0.5 * uv_full - 0.25, atol=1e-9)
    inputs = depth_inputs(frame.image, frame.points, frame.calib, preset)
    assert inputs.rgb.shape == (1, 3, 176, 608) and inputs.sparse_depth.shape == (1, 1, 176, 608)
    assert inputs.rgb.dtype == np.float32 and 0 < np.count_nonzero(inputs.sparse_depth)


def test_downscale_sparse_depth_keeps_nearest_return_per_block():
    from pipeline.preprocess import downscale_sparse_depth

    sparse = np.zeros((4, 6), np.float32)
    sparse[0, 0], sparse[1, 1] = 10.0, 7.0  # same 2×2 block: 7 wins
    sparse[3, 5] = 3.0
    small = downscale_sparse_depth(sparse, 2)
    np.testing.assert_array_equal(small, [[7.0, 0.0, 0.0], [0.0, 0.0, 3.0]])
    with pytest.raises(ValueError, match="not divisible"):
        downscale_sparse_depth(np.zeros((5, 6), np.float32), 2)


def _axis_aligned_calibration(p2_offset: float = 0.0):
    """A calibration with no rotation but the axes' swap (camera z = LiDAR x) and no translation: a point's depth
    is its x, exactly, so a test can put one on a limit."""
    from pipeline.calib import Calibration

    return Calibration(P2=np.array([[700.0, 0.0, 600.0, p2_offset], [0.0, 700.0, 180.0, 0.0], [0.0, 0.0, 1.0, 0.0]]),
                       R0_rect=np.eye(3),
                       Tr_velo_to_cam=np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0]]))


def test_sparse_depth_drops_a_return_exactly_at_min_depth():
    """The spec a port reads says ``d > min_depth``: a return exactly at min_depth is dropped, one just beyond kept."""
    calib = _axis_aligned_calibration()
    limit = float(np.float32(0.1))
    points = np.array([[limit, 0.0, 0.0, 0.5], [20.0, 0.0, 1.0, 0.5]], np.float32)  # on the axis; 1 m up
    depth_map = sparse_depth_map(points, calib, (375, 1242), min_depth=limit)
    assert np.count_nonzero(depth_map) == 1 and depth_map[145, 600] == 20.0
    beyond = points.copy()
    beyond[0, 0] = np.nextafter(np.float32(limit), np.float32(1))
    assert sparse_depth_map(beyond, calib, (375, 1242), min_depth=limit)[180, 600] == beyond[0, 0]


def test_ray_tables_are_cached_per_calibration_shape_and_stride():
    """The ray cache tells apart calibrations that differ in any one matrix, and strides: each table is its own
    calibration's rays."""
    from dataclasses import replace

    from pipeline.pseudo import pixel_rays, ray_table

    base = _axis_aligned_calibration()
    turned = replace(base, Tr_velo_to_cam=base.Tr_velo_to_cam + [[0, 0, 0, 0.5], [0, 0, 0, 0], [0, 0, 0, 0]])
    rotated = replace(base, R0_rect=np.array([[1.0, 0.0, 0.0], [0.0, 0.8, -0.6], [0.0, 0.6, 0.8]]))
    shifted = _axis_aligned_calibration(p2_offset=40.0)
    for calib, stride in ((base, 1), (turned, 1), (rotated, 1), (shifted, 1), (base, 2), (base, 1)):
        table = ray_table(calib, 30, 40, stride)
        rays, origin = pixel_rays(calib, 30, 40, stride)
        np.testing.assert_array_equal(table.rays, rays.reshape(3, -1))
        np.testing.assert_array_equal(table.origin, origin.astype(np.float32))


def test_the_depth_nets_view_is_area_resampled_and_in_rgb_order():
    """The network's image input: the crop averaged over each scale × scale block (area resampling, which
    scale_calibration's geometry assumes) in R, G, B planes; at the tiny preset's quarter scale, bilinear
    sampling would read 2 of each block's 4 rows and columns instead."""
    from pipeline.preprocess import depth_inputs
    from pipeline.presets import PRESETS

    frame = load_frame(KITTI, "000006")
    preset = PRESETS["tiny"]
    factor = round(1 / preset.depth.input_scale)
    rng = np.random.default_rng(8)
    image = np.zeros((*frame.image_hw, 3), np.uint8)
    image[..., 0] = rng.integers(0, 256, frame.image_hw)  # red: noise, which only an area average keeps
    image[..., 1] = 100  # green and blue flat, told apart by their level
    image[..., 2] = 200
    rgb = depth_inputs(image, frame.points, frame.calib, preset).rgb
    crop = depth_crop(frame.image_hw).apply(image).astype(np.float64)
    h, w = preset.depth.input_hw
    blocks = crop.reshape(h, factor, w, factor, 3).mean(axis=(1, 3))
    assert rgb.shape == (1, 3, h, w)
    np.testing.assert_allclose(rgb[0, 0], blocks[..., 0], atol=0.51)  # rounded to uint8
    assert (rgb[0, 1] == 100).all() and (rgb[0, 2] == 200).all()


def test_a_dense_depth_map_in_the_nets_view_keeps_real_depths_only():
    """depth_view resizes by nearest neighbour: a car at 8 m before a wall at 40 m gives no depth between them
    (an interpolating resize would put points in the empty space along every outline)."""
    from pipeline.preprocess import depth_view
    from pipeline.presets import PRESETS

    depth = np.full((375, 1242), 40.0, np.float32)
    depth[:, 301::2] = 8.0  # every other column from an odd one: each 2 × 2 block of the view straddles an edge
    view = depth_view(depth, PRESETS["edge"])
    assert view.shape == PRESETS["edge"].depth.input_hw and view.dtype == np.float32
    assert set(np.unique(view)) == {8.0, 40.0}


def test_depth_png_inputs_follow_the_presets_own_crop():
    """A preset with a crop other than KITTI's (a manifest may carry one): the sparse map of a depth-completion
    frame is cropped as the image is, so both inputs have the network's shape."""
    from dataclasses import replace

    from pipeline.preprocess import view_from_depth_png
    from pipeline.presets import PRESETS

    edge = PRESETS["edge"]
    preset = replace(edge, crop_hw=(344, 1200), depth=replace(edge.depth, input_hw=(172, 600)))
    image = np.zeros((375, 1242, 3), np.uint8)
    sparse = np.zeros((375, 1242), np.float32)
    sparse[-1, -22], sparse[30, 20] = 5.0, 7.0  # the crop's last row and column; a pixel just outside it
    rgb, sparse_view = view_from_depth_png(image, sparse, preset)
    assert rgb.shape == (1, 3, 172, 600) and sparse_view.shape == (1, 1, 172, 600)
    assert sparse_view[0, 0, -1, -1] == 5.0 and np.count_nonzero(sparse_view) == 1


def _fresh_calibration(seed: int):
    """KITTI's calibration with P2's principal point moved by a random fraction of a pixel: values no other
    test has checked, so the cache of passed calibrations starts without them."""
    from pipeline.calib import KITTI_CALIBRATION, Calibration

    p2 = KITTI_CALIBRATION.P2.copy()
    p2[0, 2] += np.random.default_rng(seed).uniform(0.01, 0.99)
    return Calibration(P2=p2, R0_rect=KITTI_CALIBRATION.R0_rect.copy(),
                       Tr_velo_to_cam=KITTI_CALIBRATION.Tr_velo_to_cam.copy())


@pytest.fixture
def full_checks(monkeypatch):
    """How many times check_calibration ran its full checks (the real ones, counted)."""
    import pipeline.calib as calib_module

    calls = []
    real = calib_module._check_calibration_values

    def counted(calib, source):
        calls.append(calib)
        return real(calib, source)

    monkeypatch.setattr(calib_module, "_check_calibration_values", counted)
    return calls


def test_a_calibration_that_passed_is_not_checked_again(full_checks):
    """The detector checks every frame's calibration, which its reader checked already: equal values that
    passed pass at once, as the object given (0.2 ms of an edge frame, session 42)."""
    from dataclasses import replace

    from pipeline.calib import check_calibration

    first = _fresh_calibration(1)
    assert check_calibration(first) is first
    again = replace(first, P2=first.P2.copy())  # another object, the same values: as each frame's file reads
    assert check_calibration(again, "frame 2's calib") is again
    assert full_checks == [first]


def test_a_calibration_is_checked_by_its_values_not_its_object(full_checks):
    """A matrix changed in place after it passed is checked anew, and refused; a refused one is never let
    through later; a calibration of another dtype is checked (and copied to float64) every time."""
    from pipeline.calib import Calibration, check_calibration

    calib = _fresh_calibration(2)
    check_calibration(calib)
    calib.P2[1, 1] = np.nan
    for _ in range(2):
        with pytest.raises(InputError, match="^calib: P2 has a non-finite value"):
            check_calibration(calib)
    assert len(full_checks) == 3
    single = _fresh_calibration(3)
    single = Calibration(**{key: value.astype(np.float32) for key, value in vars(single).items()})
    for _ in range(2):
        assert check_calibration(single).P2.dtype == np.float64
    assert len(full_checks) == 5


def test_the_passed_calibrations_kept_are_bounded(full_checks, monkeypatch):
    """A service sent a new calibration with every frame keeps the last _PASSED_MAX, oldest out first."""
    from collections import OrderedDict

    import pipeline.calib as calib_module
    from pipeline.calib import check_calibration

    monkeypatch.setattr(calib_module, "_PASSED", OrderedDict())
    monkeypatch.setattr(calib_module, "_PASSED_MAX", 3)
    calibrations = [_fresh_calibration(seed) for seed in range(10, 15)]
    for calib in calibrations:
        check_calibration(calib)
    assert len(calib_module._PASSED) == 3
    check_calibration(calibrations[-1])  # among the last three: no checks
    assert len(full_checks) == 5
    check_calibration(calibrations[0])  # dropped: checked again
    assert len(full_checks) == 6
