"""Boxes: label ↔ LiDAR conversion on real labels, rotated IoU against shapely, targets, NMS."""

import numpy as np
import pytest
from shapely.geometry import Polygon

from pipeline.boxes import bev_corners, box_corners_3d, boxes_to_objects, labels_to_boxes, points_in_boxes
from pipeline.frame import load_frame
from pipeline.iou import rect_corners, rotated_iou_matrix, rotated_iou_pairs, rotated_nms
from pipeline.presets import PRESETS
from pipeline.targets import decode_maps, encode_targets
from tests.conftest import FRAMES, KITTI


def test_every_car_of_000006_contains_lidar_points():
    frame = load_frame(KITTI, "000006")
    cars = [o for o in frame.labels if o.type == "Car"]
    boxes = labels_to_boxes(cars, frame.calib)
    inside = points_in_boxes(frame.points, boxes).sum(axis=0)
    assert len(cars) == 4 and (inside >= 5).all()
    # The nearest car (19.7 m) holds by far the most points.
    assert inside.argmax() == int(np.argmin(boxes[:, 0]))


@pytest.mark.parametrize("frame_id", FRAMES)
def test_label_box_label_roundtrip(frame_id):
    frame = load_frame(KITTI, frame_id)
    objects = [o for o in frame.labels if o.type != "DontCare"]
    boxes = labels_to_boxes(objects, frame.calib)
    back = boxes_to_objects(boxes, frame.calib, frame.image_hw, scores=np.ones(len(boxes)))
    assert len(objects) > 0 and len(back) == len(objects)
    for original, again in zip(objects, back, strict=True):
        np.testing.assert_allclose(again.location, original.location, atol=1e-9)
        np.testing.assert_allclose(again.dimensions, original.dimensions, atol=1e-12)
        assert np.cos(again.rotation_y - original.rotation_y) == pytest.approx(1.0, abs=1e-12)
        assert np.cos(again.alpha - original.alpha) == pytest.approx(1.0, abs=2e-4)  # labels give alpha to 0.01
        if original.type == "Car" and original.truncated == 0:  # a car fills its projected 3D box
            np.testing.assert_allclose(again.bbox, original.bbox, atol=3.0)


def test_corners_layout():
    box = np.array([[10.0, 2.0, -1.0, 4.0, 2.0, 1.5, np.pi / 2]])
    corners = bev_corners(box)[0]
    np.testing.assert_allclose(corners, [[9, 4], [9, 0], [11, 0], [11, 4]], atol=1e-12)
    c3 = box_corners_3d(box)[0]
    # Bottom ring at z − h/2 = −1.75, top ring at z + h/2 = −0.25, both over the same BEV corners.
    np.testing.assert_allclose(c3[:4, 2], -1.75)
    np.testing.assert_allclose(c3[4:, 2], -0.25)
    np.testing.assert_allclose(c3[:4, :2], corners, atol=1e-12)
    np.testing.assert_allclose(c3[4:, :2], corners, atol=1e-12)


def random_boxes(rng, n):
    return np.column_stack([
        rng.uniform(-3, 3, (n, 2)), rng.uniform(0.3, 6, n), rng.uniform(0.3, 3, n), rng.uniform(-np.pi, np.pi, n)
    ])


def shapely_iou(a, b):
    pa, pb = Polygon(rect_corners(a)[0]), Polygon(rect_corners(b)[0])
    return pa.intersection(pb).area / pa.union(pb).area


def test_rotated_iou_matches_shapely_on_10000_pairs():
    rng = np.random.default_rng(7)
    a, b = random_boxes(rng, 10000), random_boxes(rng, 10000)
    # Include pairs sharing a centre or an angle, the degenerate cases for clipping.
    b[:1000, :2] = a[:1000, :2]
    b[1000:2000, 4] = a[1000:2000, 4]
    ours = rotated_iou_pairs(a, b)
    reference = np.array([shapely_iou(a[i : i + 1], b[i : i + 1]) for i in range(len(a))])
    assert np.abs(ours - reference).max() < 1e-6
    assert 0.2 < (reference > 0).mean() < 0.9


def test_rotated_iou_known_cases():
    box = np.array([[0, 0, 4, 2, 0.3]])
    assert rotated_iou_pairs(box, box)[0] == pytest.approx(1.0, abs=1e-12)
    shifted = np.array([[2, 0, 4, 2, 0.0]])
    assert rotated_iou_pairs(np.array([[0, 0, 4, 2, 0.0]]), shifted)[0] == pytest.approx(1 / 3)
    turned = np.array([[0, 0, 2, 2, np.pi / 4]])  # a square against itself turned 45°
    assert rotated_iou_pairs(np.array([[0, 0, 2, 2, 0.0]]), turned)[0] == pytest.approx((8 * (np.sqrt(2) - 1)) / (8 - 8 * (np.sqrt(2) - 1)))
    far = np.array([[50, 50, 4, 2, 0.0]])
    assert rotated_iou_pairs(box, far)[0] == 0.0
    # Same box with heading flipped by π is the same rectangle.
    assert rotated_iou_pairs(box, box + [0, 0, 0, 0, np.pi])[0] == pytest.approx(1.0, abs=1e-12)


def test_rotated_iou_of_boxes_sharing_or_touching_sides():
    """Collinear edges are where clipping double-counts or drops area; shapely itself is unreliable there."""
    box = np.array([[0.0, 0.0, 4.0, 2.0, 0.0]])
    cases = [
        ([1.0, 0.0, 2.0, 2.0, 0.0], 0.5),  # inside, sharing parts of both long sides
        ([1.0, 0.0, 2.0, 2.0, np.pi], 0.5),  # the same, its edges running the other way
        ([0.0, 2.0, 4.0, 2.0, 0.0], 0.0),  # touching along a long side
        ([4.0, 0.0, 4.0, 2.0, np.pi], 0.0),  # touching end to end
        ([0.0, 0.0, 2.0, 1.0, 0.0], 0.25),  # concentric, half the size
        ([0.0, 0.0, 4.0, 0.0, 0.0], 0.0),  # a degenerate (zero-width) box
    ]
    for other, expected in cases:
        for yaw in (0.0, 0.7):  # the same layout turned as a whole
            turn = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
            a = np.concatenate([box[0, :4], [box[0, 4] + yaw]])
            b = np.concatenate([turn @ other[:2], other[2:4], [other[4] + yaw]])
            got = rotated_iou_pairs(a[None], b[None])[0]
            assert got == pytest.approx(expected, abs=1e-9), (other, yaw)
            assert rotated_iou_pairs(b[None], a[None])[0] == pytest.approx(expected, abs=1e-9), (other, yaw)


def test_iou_matrix_equals_pairs():
    rng = np.random.default_rng(3)
    a, b = random_boxes(rng, 30), random_boxes(rng, 20)
    matrix = rotated_iou_matrix(a, b)
    ia, ib = np.meshgrid(np.arange(30), np.arange(20), indexing="ij")
    np.testing.assert_allclose(matrix.reshape(-1), rotated_iou_pairs(a[ia.ravel()], b[ib.ravel()]), atol=1e-12)
    assert rotated_iou_matrix(a[:0], b).shape == (0, 20)


def test_nms_keeps_what_it_should():
    boxes = np.array([
        [10, 0, 4, 2, 0.0],
        [10.2, 0, 4, 2, 0.05],  # duplicate of 0, lower score → suppressed
        [20, 5, 4, 2, 1.0],  # far away → kept
        [10, 2.1, 4, 2, 0.0],  # touching but not overlapping box 0 → kept
    ])
    scores = np.array([0.9, 0.8, 0.7, 0.95])
    keep = rotated_nms(boxes, scores, iou_threshold=0.1)
    assert keep.tolist() == [3, 0, 2]
    assert rotated_nms(boxes, scores, iou_threshold=0.1, max_keep=2).tolist() == [3, 0]
    assert rotated_nms(boxes[:0], scores[:0], 0.1).size == 0


@pytest.mark.parametrize("preset", ["paper", "edge"])
def test_encode_decode_recovers_boxes(preset):
    p = PRESETS[preset]
    frame = load_frame(KITTI, "000006")
    boxes = labels_to_boxes([o for o in frame.labels if o.type == "Car"], frame.calib)
    targets = encode_targets(boxes, p.bev, p.pixor.output_stride, p.decode)
    assert targets.score.shape == (p.bev.ny // 4, p.bev.nx // 4)
    assert targets.regression.shape == (6, *targets.score.shape)
    candidates, scores = decode_maps(targets.score, targets.regression, p.bev, p.pixor.output_stride, p.decode)
    keep = rotated_nms(candidates, scores, 0.1)
    decoded = candidates[keep]
    assert len(decoded) == len(boxes)
    iou = rotated_iou_matrix(decoded, boxes[:, [0, 1, 3, 4, 6]])
    assert (iou.max(axis=0) > 0.999).all()


def test_past_max_candidates_equal_scores_keep_the_cell_order():
    """Past max_candidates the highest scores are kept; of equal scores (sigmoids saturate at 1.0f), the
    first cells, in cell order. np.argpartition left both to the CPU's sort kernels: the same maps gave
    other boxes on an AVX2 machine than on an AVX-512 one (session 42)."""
    p = PRESETS["edge"]
    shape = (p.bev.ny // 4, p.bev.nx // 4)
    rng = np.random.default_rng(7)
    # 2,000 cells over the threshold with four distinct scores, so that ties fill both sides of the cut.
    score = np.zeros(shape, np.float32)
    cells = rng.choice(score.size, 2000, replace=False)
    score.reshape(-1)[cells] = rng.choice(np.float32([0.6, 0.8, 0.9, 1.0]), 2000, p=[0.5, 0.3, 0.1, 0.1])
    regression = rng.normal(0, 0.5, (6, *shape)).astype(np.float32)
    limit = p.decode.max_candidates
    candidates, scores = decode_maps(score, regression, p.bev, p.pixor.output_stride, p.decode)
    flat = score.reshape(-1)
    above = np.flatnonzero(flat >= p.decode.score_threshold)
    expected = above[np.lexsort((above, -flat[above]))][:limit]  # score descending, then cell index
    at_cut = flat[expected[-1]]
    assert len(scores) == limit and 0 < (flat[expected] == at_cut).sum() < (flat == at_cut).sum()  # the cut splits a tie
    _, cols = np.divmod(expected, shape[1])
    step = p.bev.cell * p.pixor.output_stride
    cx = p.bev.x_min + (cols + 0.5) * step + regression[2].reshape(-1)[expected] * p.decode.reg_std[2] + p.decode.reg_mean[2]
    np.testing.assert_allclose(candidates[:, 0], cx, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(scores, flat[expected])


def test_max_candidates_of_zero_keeps_no_candidate():
    """A manifest may say 0 (preset_from_dict takes it): no boxes, not a ValueError from np.partition."""
    from dataclasses import replace

    p = PRESETS["edge"]
    shape = (p.bev.ny // 4, p.bev.nx // 4)
    candidates, scores = decode_maps(np.full(shape, 0.9, np.float32), np.zeros((6, *shape), np.float32), p.bev,
                                     p.pixor.output_stride, replace(p.decode, max_candidates=0))
    assert candidates.shape == (0, 5) and scores.shape == (0,)


def test_encoding_owner_is_nearest_box():
    p = PRESETS["paper"]
    # Two boxes overlapping in BEV: each cell goes to the closer centre.
    boxes = np.array([[20.0, 0.0, -1, 4.0, 2.0, 1.5, 0.0], [22.0, 0.0, -1, 4.0, 2.0, 1.5, 0.0]])
    targets = encode_targets(boxes, p.bev, 4, p.decode)
    rows, cols = np.nonzero(targets.score)
    std, mean = np.array(p.decode.reg_std), np.array(p.decode.reg_mean)
    dx = targets.regression[2, rows, cols] * std[2] + mean[2]
    cell_x = p.bev.x_min + (cols + 0.5) * p.bev.cell * 4
    overlap = (cell_x > 20.0) & (cell_x < 22.0)
    assert overlap.sum() > 0
    assert np.abs(dx[overlap]).max() <= 1.0 + 1e-6  # never the farther of the two centres
    assert np.abs(dx).max() > 1.5  # outside the overlap the only box owns the cell


def test_cell_assignment_equals_brute_force():
    from pipeline.targets import OutputGrid, assign_cells

    p = PRESETS["paper"]
    out = OutputGrid.from_bev(p.bev, 4)
    rng = np.random.default_rng(5)
    n = 40
    boxes = np.column_stack([
        rng.uniform(-2, 72, n), rng.uniform(-42, 42, n), np.zeros(n),
        rng.uniform(2, 6, n), rng.uniform(1.4, 2.2, n), np.ones(n), rng.uniform(-np.pi, np.pi, n),
    ])
    boxes[1, :2] = boxes[0, :2] + 1.0  # an overlapping pair
    cx, cy = out.centres()
    rel_x, rel_y = cx[..., None] - boxes[:, 0], cy[..., None] - boxes[:, 1]
    along = rel_x * np.cos(boxes[:, 6]) + rel_y * np.sin(boxes[:, 6])
    across = -rel_x * np.sin(boxes[:, 6]) + rel_y * np.cos(boxes[:, 6])
    inside = (np.abs(along) <= boxes[:, 3] / 2) & (np.abs(across) <= boxes[:, 4] / 2)
    nearest = np.argmin(np.where(inside, rel_x**2 + rel_y**2, np.inf), axis=-1)
    expected = np.where(inside.any(axis=-1), nearest, -1)
    np.testing.assert_array_equal(assign_cells(boxes, out), expected)


def test_heights_from_bev_occupancy():
    from pipeline.bev import voxelize_bev
    from pipeline.postprocess import estimate_heights

    p = PRESETS["paper"]
    frame = load_frame(KITTI, "000006")
    cars = labels_to_boxes([o for o in frame.labels if o.type == "Car"], frame.calib)
    bev = voxelize_bev(frame.points, p.bev)
    z, h = estimate_heights(cars[:, [0, 1, 3, 4, 6]], bev, p)
    near = cars[:, 0] < 35  # enough returns to measure
    assert np.abs(z[near] - cars[near, 2]).max() < 0.3
    assert np.abs(h[near] - cars[near, 5]).max() < 0.45
    # An empty box sits on the road with the mean car height.
    z0, h0 = estimate_heights(np.array([[60.0, -30.0, 4.0, 1.7, 0.0]]), np.zeros(p.bev.shape, np.float32), p)
    assert h0[0] == p.decode.car_height and z0[0] == pytest.approx(p.decode.ground_z + p.decode.car_height / 2)
    # A stamped height grid (pipeline.bev.BevVoxelizer): only the voxels holding this frame's mark count,
    # whatever older stamps lie around them.
    stamped = np.where(bev[: p.bev.nz] > 0, 7, 0).astype(np.uint8)
    stamped[(stamped == 0) & (np.arange(p.bev.nz)[:, None, None] % 2 == 0)] = 6
    z_stamped, h_stamped = estimate_heights(cars[:, [0, 1, 3, 4, 6]], stamped, p, mark=7)
    np.testing.assert_array_equal(z_stamped, z)
    np.testing.assert_array_equal(h_stamped, h)


def test_heights_weigh_what_was_seen_against_the_mean_car_height():
    """A 2.0 m van: its measured height is averaged with the mean car height, weighted by the occupied volume
    seen under the box against height_prior_volume, so seen whole it keeps nearly 2.0 m and seen by four
    voxels nearly the mean. The bottom is the lowest slice's lower edge, or its centre with pseudo points."""
    from pipeline.postprocess import estimate_heights
    from pipeline.targets import OutputGrid, box_cells

    p = PRESETS["edge"]
    grid, decode, stride = p.bev, p.decode, p.pixor.output_stride
    box = np.array([[30.0, 0.0, 4.0, 2.0, 0.0]])  # x, y, l, w, yaw
    ground_slice = 4  # z from -1.7 m
    bottom = grid.z_min + ground_slice * grid.z_cell
    voxel = grid.cell * grid.cell * grid.z_cell

    def expected_height(seen_m3: float) -> float:  # the measured extent is exactly 2.0 m in both cases
        return (seen_m3 * 2.0 + decode.height_prior_volume * decode.car_height) / (seen_m3 + decode.height_prior_volume)

    # Seen whole: ten 0.2 m slices occupied over an area larger than the box, so every BEV cell under
    # the box's output cells counts.
    whole = np.zeros(grid.shape, np.float32)
    rows = slice(int((-3.0 - grid.y_min) / grid.cell), int((3.0 - grid.y_min) / grid.cell))
    cols = slice(int((26.0 - grid.x_min) / grid.cell), int((34.0 - grid.x_min) / grid.cell))
    whole[ground_slice:ground_slice + 10, rows, cols] = 1.0
    boxes7 = np.array([[30.0, 0.0, 0.0, 4.0, 2.0, 1.0, 0.0]])
    cells = box_cells(boxes7, OutputGrid.from_bev(grid, stride))[0].size
    z, h = estimate_heights(box, whole, p)
    assert h[0] == pytest.approx(expected_height(cells * stride * stride * 10 * voxel))
    assert h[0] > 1.95 and z[0] == pytest.approx(bottom + h[0] / 2)
    z_pseudo, h_pseudo = estimate_heights(box, whole, p, with_pseudo=True)
    assert z_pseudo[0] - h_pseudo[0] / 2 == pytest.approx(bottom + grid.z_cell / 2)

    # Seen by four voxels of one cell under the box, spanning the same 2.0 m.
    glimpse = np.zeros(grid.shape, np.float32)
    row, col = int((0.1 - grid.y_min) / grid.cell), int((30.1 - grid.x_min) / grid.cell)
    glimpse[[ground_slice, ground_slice + 3, ground_slice + 6, ground_slice + 9], row, col] = 1.0
    _, h_glimpse = estimate_heights(box, glimpse, p)
    assert h_glimpse[0] == pytest.approx(expected_height(4 * voxel))
    assert abs(h_glimpse[0] - decode.car_height) < 0.05


def test_camera_view_filter():
    from pipeline.boxes import in_camera_view

    frame = load_frame(KITTI, "000006")
    cars = labels_to_boxes([o for o in frame.labels if o.type == "Car"], frame.calib)
    assert in_camera_view(cars, frame.calib, frame.image_hw).all()
    outside = np.array([[5.0, 30.0, -1, 4, 1.7, 1.5, 0.0], [-10.0, 0.0, -1, 4, 1.7, 1.5, 0.0]])
    assert not in_camera_view(outside, frame.calib, frame.image_hw).any()


def test_nms_quick_accept_is_a_true_lower_bound():
    """The inscribed-circle test NMS uses to skip clipping never calls a pair over the threshold that
    is not (checked against shapely), and does call most pairs of a car's candidate cluster."""
    from shapely.geometry import Point

    from pipeline.iou import _certainly_over

    rng = np.random.default_rng(11)
    a = random_boxes(rng, 3000)
    b = a + np.column_stack([rng.normal(0, 0.6, (3000, 2)), rng.normal(0, 0.3, (3000, 2)), rng.normal(0, 0.5, 3000)])
    b[:, 2:4] = np.abs(b[:, 2:4]) + 0.5
    exact = rotated_iou_pairs(a, b)
    for threshold in (0.05, 0.1, 0.3):
        sure = _certainly_over(a, b, threshold)
        assert not np.any(sure & (exact <= threshold))
    assert _certainly_over(a, b, 0.1).mean() > 0.3
    # The lens itself, against shapely's (polygonal) circles, through the bound at threshold ε.
    for i in range(20):
        r1, r2 = min(a[i, 2:4]) / 2, min(b[i, 2:4]) / 2
        lens = Point(a[i, :2]).buffer(r1, 256).intersection(Point(b[i, :2]).buffer(r2, 256)).area
        areas = a[i, 2] * a[i, 3] + b[i, 2] * b[i, 3]
        assert bool(_certainly_over(a[i : i + 1], b[i : i + 1], 0.98 * lens / areas)[0]) == (lens > 0)
        assert not _certainly_over(a[i : i + 1], b[i : i + 1], 1.02 * lens / areas + 1e-12)[0]


def test_nms_quick_reject_finds_exactly_the_disjoint_pairs():
    """The separating-axis test NMS uses to skip clipping never calls overlapping boxes apart, and calls
    every pair apart that lies apart by more than rounding (checked against shapely's areas)."""
    from shapely.geometry import Polygon

    from pipeline.iou import _certainly_apart

    rng = np.random.default_rng(12)
    a = random_boxes(rng, 2000)
    b = a + np.column_stack([rng.normal(0, 3.0, (2000, 2)), rng.normal(0, 0.5, (2000, 2)), rng.uniform(-3, 3, 2000)])
    b[:, 2:4] = np.abs(b[:, 2:4]) + 0.3
    apart = _certainly_apart(a, b)
    corners_a, corners_b = rect_corners(a), rect_corners(b)
    gaps = np.array([Polygon(ca).distance(Polygon(cb)) for ca, cb in zip(corners_a, corners_b)])
    overlap = np.array([Polygon(ca).intersection(Polygon(cb)).area for ca, cb in zip(corners_a, corners_b)])
    assert not np.any(apart & (overlap > 0))
    np.testing.assert_array_equal(apart[gaps > 1e-6], True)
    assert 0.2 < apart.mean() < 0.8  # both kinds of pair are there
    # Boxes sharing a side or a corner are not apart: their gap is 0.
    touching = np.array([[0, 0, 4, 2, 0.0], [0, 0, 4, 2, 0.0], [0, 0, 4, 2, 0.3]])
    others = np.array([[4, 0, 4, 2, 0.0], [0, 2, 4, 2, 0.0], [0, 0, 1, 1, 0.0]])
    assert not _certainly_apart(touching, others).any()


def test_nms_equals_plain_greedy_on_clustered_candidates():
    """The circle prefilter changes no decision: compare with greedy NMS over the full IoU matrix."""

    def greedy(boxes, scores, threshold, max_keep=None):
        order = np.argsort(-scores, kind="stable")
        iou = rotated_iou_matrix(boxes[order], boxes[order])
        alive, keep = np.ones(len(order), bool), []
        for i in range(len(order)):
            if alive[i] and (max_keep is None or len(keep) < max_keep):
                keep.append(i)
                alive[iou[i] > threshold] = False
        return order[keep]

    rng = np.random.default_rng(5)
    for _ in range(20):
        centres = rng.uniform([0, -30], [60, 30], (6, 2))  # a few cars, each with jittered candidates
        n = rng.integers(1, 120)
        pick = rng.integers(0, 6, n)
        boxes = np.column_stack([centres[pick] + rng.normal(0, 0.8, (n, 2)), rng.uniform(3.2, 4.8, n),
                                 rng.uniform(1.4, 2.0, n), rng.uniform(-np.pi, np.pi, n)])
        scores = rng.uniform(0, 1, n)
        for threshold, max_keep in ((0.1, None), (0.5, None), (0.0, 3)):
            np.testing.assert_array_equal(rotated_nms(boxes, scores, threshold, max_keep),
                                          greedy(boxes, scores, threshold, max_keep))


def test_the_2d_box_of_a_car_reaching_behind_the_camera_runs_to_the_image_border():
    """A 2D box (the result file's bbox, which the devkit's minimum height reads) is that of the box's part in
    front of the camera: a car beside the vehicle runs to the image's border on its side, as KITTI labels such
    a car. Dropping its corners behind the camera made the box only as large as its far end."""
    from pipeline.boxes import image_boxes

    frame = load_frame(KITTI, "000006")
    h, w = frame.image_hw
    ahead = np.array([[15, 2, -0.9, 4, 1.7, 1.5, 0.3]])
    beside = np.array([[2.5, -2.0, -0.9, 4.5, 1.8, 1.5, 0.0]])  # from 0.25 m behind the LiDAR to 4.75 m ahead
    uv, depth = frame.calib.velo_to_image(box_corners_3d(ahead).reshape(-1, 3))
    assert (depth > 0).all()
    np.testing.assert_allclose(image_boxes(ahead, frame.calib, frame.image_hw)[0],
                               [uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), uv[:, 1].max()])
    left, _, right, bottom = image_boxes(beside, frame.calib, frame.image_hw)[0]
    _, corner_depth = frame.calib.velo_to_image(box_corners_3d(beside).reshape(-1, 3))
    assert (corner_depth < 0).any() and (corner_depth > 0).any()
    # On the right (y < 0), to the border; its corners in front alone end 150 px short of it.
    assert right == w - 1 and bottom == h - 1 and w / 2 < left < w - 300


def test_a_cell_centre_on_a_box_edge_is_inside_it():
    """Targets count a cell whose centre lies on the box's edge as inside (boundary included, as
    points_in_boxes): a 1 m square centred on a 0.5 m cell covers that cell and its eight neighbours."""
    from pipeline.targets import OutputGrid, assign_cells

    out = OutputGrid(x_min=0.0, y_min=-4.0, step=0.5, ny=16, nx=16)  # every centre exact in binary
    box = np.array([[2.25, 0.25, 0.0, 1.0, 1.0, 1.5, 0.0]])  # centred on row 8, column 4
    owner = assign_cells(box, out)
    expected = np.full((16, 16), -1)
    expected[7:10, 3:6] = 0
    np.testing.assert_array_equal(owner, expected)


def test_cell_assignment_reaches_the_far_corner_of_a_box_lying_along_its_diagonal():
    """A box turned so that its diagonal lies along x reaches its full circumscribed radius: the cells at that
    corner are found (the search window is wide enough), as the brute force finds them."""
    from pipeline.targets import OutputGrid, assign_cells

    out = OutputGrid(x_min=0.0, y_min=-20.0, step=0.5, ny=80, nx=120)
    rng = np.random.default_rng(9)
    n = 400
    length, width = rng.uniform(2.0, 6.0, n), rng.uniform(1.0, 3.0, n)
    yaw = np.arctan2(width, length) * rng.choice([-1, 1], n) + rng.choice([0, np.pi / 2], n)
    boxes = np.column_stack([rng.uniform(5, 55, n), rng.uniform(-15, 15, n), np.zeros(n), length, width,
                             np.ones(n), yaw])
    cx, cy = out.centres()
    for box in boxes:  # one at a time: no neighbour takes a corner cell
        rel_x, rel_y = cx - box[0], cy - box[1]
        along = rel_x * np.cos(box[6]) + rel_y * np.sin(box[6])
        across = -rel_x * np.sin(box[6]) + rel_y * np.cos(box[6])
        inside = (np.abs(along) <= box[3] / 2) & (np.abs(across) <= box[4] / 2)
        np.testing.assert_array_equal(assign_cells(box[None], out) == 0, inside)


def test_nms_suppresses_an_overlapping_box_more_than_a_radius_ahead():
    """Two cars' candidates 3 m apart along x (4.5 m long, so more than one circumscribed radius apart, less
    than two) overlap with IoU 0.2: the lower one is suppressed at 0.1, kept at 0.3."""
    boxes = np.array([[10.0, 0.0, 4.5, 1.8, 0.0], [13.0, 0.0, 4.5, 1.8, 0.0]])
    assert rotated_iou_pairs(boxes[:1], boxes[1:])[0] == pytest.approx(0.2)
    assert rotated_nms(boxes, np.array([0.9, 0.8]), 0.1).tolist() == [0]
    assert rotated_nms(boxes, np.array([0.8, 0.9]), 0.1).tolist() == [1]
    assert rotated_nms(boxes, np.array([0.9, 0.8]), 0.3).tolist() == [0, 1]


def test_box_bottom_is_the_first_slice_reaching_the_low_quantile():
    """The bottom is the first height slice whose cumulative count reaches (>=) 5 % of the box's voxels, as the
    port spec states: of 20 voxels, one low return (a kerb, the road) is exactly 5 % and sets the bottom."""
    from pipeline.postprocess import estimate_heights

    p = PRESETS["edge"]
    grid, decode = p.bev, p.decode
    occupancy = np.zeros(grid.shape, np.float32)
    row, col = int((0.1 - grid.y_min) / grid.cell), int((30.1 - grid.x_min) / grid.cell)
    occupancy[2, row, col] = 1.0  # one voxel low down
    occupancy[8, row - 1, col - 9:col + 10] = 1.0  # 19 at a car's roof
    z, h = estimate_heights(np.array([[30.0, 0.0, 4.0, 2.0, 0.0]]), occupancy, p)
    bottom, top = grid.z_min + 2 * grid.z_cell, grid.z_min + 9 * grid.z_cell
    seen = 20 * grid.cell * grid.cell * grid.z_cell
    measured = np.clip(top - bottom, 1.2, 2.4)
    expected = (seen * measured + decode.height_prior_volume * decode.car_height) / (seen + decode.height_prior_volume)
    assert h[0] == pytest.approx(expected) and z[0] == pytest.approx(bottom + expected / 2)


def test_nms_with_a_negative_threshold_keeps_only_the_best_box():
    """Every IoU, 0 included, exceeds a negative threshold: the best box suppresses all others, even far ones."""
    boxes = np.array([[10.0, 0.0, 4.0, 2.0, 0.0], [40.0, 20.0, 4.0, 2.0, 0.0], [60.0, -30.0, 4.0, 2.0, 1.0]])
    assert rotated_nms(boxes, np.array([0.2, 0.9, 0.5]), -0.5).tolist() == [1]


def test_the_2d_box_of_a_box_wholly_behind_the_camera_covers_the_image():
    """image_boxes' docstring: a box wholly behind the camera covers the image, quietly (no RuntimeWarning in
    library code; nanmin's 'All-NaN slice' used to be raised four times per such box)."""
    import warnings

    from pipeline.boxes import image_boxes

    frame = load_frame(KITTI, "000006")
    h, w = frame.image_hw
    behind = np.array([[-10.0, 0.0, -0.9, 4.0, 1.7, 1.5, 0.0], [15.0, 2.0, -0.9, 4.0, 1.7, 1.5, 0.3]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        bbox = image_boxes(behind, frame.calib, frame.image_hw)
    np.testing.assert_array_equal(bbox[0], [0, 0, w - 1, h - 1])
    uv, _ = frame.calib.velo_to_image(box_corners_3d(behind[1:]).reshape(-1, 3))  # the one ahead: its corners'
    np.testing.assert_allclose(bbox[1], [uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), uv[:, 1].max()])


def test_boxes_from_maps_keep_at_most_max_detections_best_first():
    from dataclasses import replace

    from pipeline.postprocess import boxes_from_maps

    p = PRESETS["edge"]
    preset = replace(p, decode=replace(p.decode, max_detections=2))
    shape = (p.bev.ny // 4, p.bev.nx // 4)
    score = np.zeros(shape, np.float32)
    regression = np.zeros((6, *shape), np.float32)  # the mean box at each cell
    peaks = {(10, 10): 0.6, (30, 40): 0.9, (50, 20): 0.7, (70, 60): 0.8}  # cells 8 m and more apart
    for cell, value in peaks.items():
        score[cell] = value
    boxes, scores = boxes_from_maps(score, regression, np.zeros(p.bev.shape, np.float32), preset)
    assert scores.tolist() == pytest.approx([0.9, 0.8]) and boxes.shape == (2, 7)
    _, every = boxes_from_maps(score, regression, np.zeros(p.bev.shape, np.float32), p)
    assert every.size == 4
