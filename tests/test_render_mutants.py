"""What the pictures and ``make demo`` show, pinned where a mutation audit of pipeline/render.py and
pipeline/demo.py found nothing that would notice a change (session 45): where a point or a box lands in the BEV
picture and which way it faces, how bright the points are, the range rings and their labels, scores, colours the
right way round, the keys' boxes, the depth panel's colours, the video's frames, and the demo's pictures, summary,
defaults and errors. Each test reads real pixels of pictures drawn from the bundled KITTI frames or from small
hand-built inputs."""

from __future__ import annotations

import json
import re
import time
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline import demo
from pipeline.boxes import box_corners_3d, labels_to_boxes
from pipeline.frame import load_frame
from pipeline.presets import PRESETS, get_preset
from pipeline.render import (
    GROUND_TRUTH_BGR,
    NO_TRUTH_BGR,
    PREDICTION_BGR,
    FrameVideo,
    bev_key_rows,
    depth_colours,
    draw_colour_scale,
    draw_key,
    draw_label,
    error_colours,
    render_bev,
    render_camera,
    render_depth,
    render_depth_panel,
    stack_views,
    write_png,
)
from tests.conftest import KITTI

REPO = Path(__file__).resolve().parents[1]
GRID = PRESETS["tiny"].bev  # x 0–70.4 m, y −40–40 m: 704 × 800 pixels at the pictures' 0.1 m
M = 0.1  # render_bev's metres a pixel
NO_POINTS = np.zeros((0, 4), np.float32)
CAR = np.array([[30.0, 0.0, -0.9, 4.0, 1.7, 1.5, 0.0]])  # 30 m straight ahead, heading forward


@pytest.fixture(scope="module")
def frame():
    return load_frame(KITTI, "000006")


def _points_at(pixels: list[tuple[int, int]], per_pixel: int = 50) -> np.ndarray:
    """Points in the LiDAR frame that the BEV picture's layout (forward up, left left, 0.1 m a pixel, the grid's
    far-left corner at the top left) puts in each (row, column), 0.7 of a pixel in from its top-left corner."""
    rows, cols = np.array(pixels, float).T
    x, y = GRID.x_max - (rows + 0.7) * M, GRID.y_max - (cols + 0.7) * M
    xyz = np.stack([x, y, np.full_like(x, -1.0), np.zeros_like(x)], axis=1)
    return np.repeat(xyz, per_pixel, axis=0).astype(np.float32)


def _white(picture: np.ndarray) -> set[tuple[int, int]]:
    """The pure white pixels but the sensor's triangle (the rings are grey, their labels light grey)."""
    white = (picture == 255).all(axis=2)
    white[-20:, 390:411] = False  # the sensor at the bottom centre
    rows, cols = np.nonzero(white)
    return set(zip(rows.tolist(), cols.tolist(), strict=True))


def _changed(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return (a != b).any(axis=2)


def _dominant(picture: np.ndarray, mask: np.ndarray) -> int:
    """The BGR channel (0 blue, 1 green, 2 red) brightest on average over ``mask``."""
    return int(np.argmax(picture[mask].astype(float).mean(axis=0)))


# ----------------------------------------------------------------------------- the BEV picture


def test_bev_points_land_forward_up_left_left_and_nowhere_off_the_grid():
    """A point lights the pixel of its 0.1 m cell, the picture's top row the grid's far end, its left column the
    grid's left edge (y = +40 m), even in the cells along the picture's edges; a point just off the grid on any side
    lights nothing (not a pixel of the next row, nor a crash)."""
    inside = [(0, 0), (0, 799), (353, 0), (353, 799), (703, 249), (100, 400), (600, 150)]
    off = np.array([[35.0, GRID.y_min - 0.05, -1, 0], [35.0, GRID.y_max + 0.05, -1, 0],
                    [GRID.x_max + 0.05, 0.0, -1, 0], [-0.05, 15.0, -1, 0]], np.float32)
    picture = render_bev(np.vstack([_points_at(inside), np.repeat(off, 50, axis=0)]), GRID)
    assert picture.shape == (704, 800, 3)
    assert _white(picture) == set(inside)


def test_bev_points_are_brighter_where_denser_and_never_wrap():
    """One point is dim, five brighter, a hundred white: not all alike, and not wrapped round past 255."""
    cells = [(200, 200), (200, 600), (500, 200)]
    points = np.vstack([_points_at([cell], n) for cell, n in zip(cells, (1, 5, 100), strict=True)])
    picture = render_bev(points, GRID)
    one, five, hundred = (int(picture[r, c, 0]) for r, c in cells)
    assert 0 < one < five < hundred == 255


def test_bev_range_rings_every_10_m_to_the_farthest_corner():
    """Rings every 10 m round the sensor, out to the grid's farthest corner (80.97 m: the 80 m ring crosses only
    the top corners), nothing between them straight ahead."""
    picture = render_bev(NO_POINTS, GRID)
    grey = picture[..., 0].astype(int)
    origin_row, origin_col = 704, 400  # the sensor: x = 0 at the bottom edge, y = 0 in the middle
    for metres in range(10, 80, 10):
        ring = origin_row - round(metres / M)
        assert grey[ring - 1:ring + 2, origin_col].max() >= 50, metres
        assert grey[ring + 40:ring + 60, origin_col].max() == 0, metres  # 4–6 m inside it: black
    across = int(np.sqrt((80 / M) ** 2 - origin_row**2))  # where the 80 m ring crosses the top row
    for col in (origin_col - across, origin_col + across):
        assert grey[0:3, col - 2:col + 3].max() >= 50
    assert grey[0:3, 300:500].max() == 0  # the top edge is 70.4 m ahead: no ring between the corners


def test_bev_ring_labels_sit_whole_beside_the_axis_clear_of_their_ring():
    """Each ring's label lies just right of the forward axis, its text clear of its own ring's line (not struck
    through) and whole inside the picture: the 70 m ring, 4 pixels from the far edge, has its label under it."""
    picture = render_bev(NO_POINTS, GRID)
    light = (picture > 120).all(axis=2) & (picture < 200).all(axis=2)  # the labels' light grey
    for metres in range(10, 80, 10):
        crossing = 704 - round(metres / M)
        text = np.flatnonzero(light[:, 403:440].any(axis=1))
        near = text[np.abs(text - crossing) < 20]
        assert len(near) >= 6, metres
        assert not ((near >= crossing - 1) & (near <= crossing + 1)).any(), metres  # clear of the ring's line
        assert (near > crossing).all() if metres == 70 else (near < crossing).all(), metres


def test_bev_sensor_is_a_triangle_pointing_ahead():
    """The sensor's white triangle is narrow at its top (the tip, ahead) and wide at its base."""
    picture = render_bev(NO_POINTS, GRID)
    white = (picture[-20:, 390:411] == 255).all(axis=2).sum(axis=1)
    rows = np.flatnonzero(white)
    assert len(rows) >= 8 and white[rows[0]] < white[rows[-1]]


def test_bev_box_is_closed_and_its_heading_line_runs_from_its_centre_to_its_front():
    """A car heading forward: its outline includes the front edge, and the line inside it runs from its centre
    up to the middle of its front edge, nothing in its rear half."""
    picture = render_bev(NO_POINTS, GRID, CAR)
    green = (picture == PREDICTION_BGR).all(axis=2)
    centre_row, col = round((GRID.x_max - 30) / M), round(GRID.y_max / M)  # 404, 400
    front_row, rear_row = centre_row - 20, centre_row + 20
    assert green[front_row - 1:front_row + 2, col - 7:col + 8].all(axis=0).sum() >= 10  # the front edge
    inside = green[front_row + 3:rear_row - 2, col - 6:col + 7]  # within the outline
    rows, cols = np.nonzero(inside)
    rows, cols = rows + front_row + 3, cols + col - 6
    assert len(rows) > 20 and set(cols.tolist()) <= {col - 1, col, col + 1}
    assert rows.max() <= centre_row + 1 and rows.min() <= front_row + 4


def test_bev_boxes_no_pixel_can_hold_are_left_out_without_a_warning():
    """A box a broken scan puts 1e9 m away (its corners past what an int32 pixel holds) or at NaN is left out
    quietly: no RuntimeWarning from a cast that overflows (printed once by the commands, logged by the service)."""
    boxes = np.array([[1e9, 0.0, -0.9, 4.0, 1.7, 1.5, 0.0], [np.nan, 0.0, -0.9, 4.0, 1.7, 1.5, 0.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        picture = render_bev(NO_POINTS, GRID, boxes, np.array([0.9, 0.8]), boxes)
    np.testing.assert_array_equal(picture, render_bev(NO_POINTS, GRID))


def test_bev_ground_truth_is_blue_and_detections_orange_on_a_real_frame(frame):
    """Colours a colour-blind reader tells apart: the labelled cars sky blue, detections orange (blue, green, red
    channel order in OpenCV; red and green, as until session 48, look alike to a deuteranope)."""
    cars = labels_to_boxes([o for o in frame.labels if o.type == "Car"], frame.calib)
    grid = get_preset("edge").bev
    plain = render_bev(frame.points, grid)
    truth = render_bev(frame.points, grid, gt_boxes=cars)
    found = render_bev(frame.points, grid, cars, np.full(len(cars), 0.9))
    assert _dominant(truth, _changed(truth, plain)) == 0
    assert _dominant(found, _changed(found, plain)) == 2


def test_bev_detection_over_its_ground_truth_shows_orange():
    """A detection drawn over its own ground truth is seen: detections are drawn last."""
    both = render_bev(NO_POINTS, GRID, CAR, None, CAR)
    changed = _changed(both, render_bev(NO_POINTS, GRID))
    assert _dominant(both, changed) == 2


def test_bev_scores_are_each_boxs_own_two_decimals_above_its_front_left_corner():
    """Each detection carries its score, to two decimals, just above its front-left corner; with a box too far
    off to draw before it, the score drawn is still the drawn box's own."""
    with_score = render_bev(NO_POINTS, GRID, CAR, np.array([0.91]))
    without = render_bev(NO_POINTS, GRID, CAR)
    text = _changed(with_score, without)
    rows, cols = np.nonzero(text)
    front_row, left_col = 384, 391  # the front-left corner: x = 32 m, y = 0.85 m
    assert len(rows) > 20 and rows.max() < front_row and cols.min() >= left_col
    assert _changed(render_bev(NO_POINTS, GRID, CAR, np.array([0.94])), with_score).any()  # 0.91 ≠ 0.94
    far_off = np.array([[1e25, 0.0, -0.9, 4.0, 1.7, 1.5, 0.0]])
    np.testing.assert_array_equal(render_bev(NO_POINTS, GRID, np.vstack([far_off, CAR]), np.array([0.3, 0.91])),
                                  with_score)


def _bev_score_text(box: list[float]) -> tuple[int, int, int]:
    """The pixels a score of 0.91 adds to the BEV picture of ``box``: how many, how tall, how wide."""
    boxes = np.array([box])
    text = _changed(render_bev(NO_POINTS, GRID, boxes, np.array([0.91])), render_bev(NO_POINTS, GRID, boxes))
    rows, cols = np.nonzero(text)
    return (int(text.sum()), int(rows.max() - rows.min()), int(cols.max() - cols.min())) if len(rows) else (0, 0, 0)


def test_bev_scores_stay_whole_inside_the_picture():
    """A detection whose front reaches past the far edge (a car 69.5 m ahead), whose side is at the right edge, or
    an oncoming one whose front-left corner is behind the sensor keeps its whole score in the picture, as the
    camera picture does (it was drawn off the picture, or cut)."""
    count, height, width = _bev_score_text(CAR[0].tolist())
    assert count > 50
    for box in ([69.5, 0.0, -0.9, 4.0, 1.7, 1.5, 0.0], [40.0, -39.3, -0.9, 4.0, 1.7, 1.5, 0.0],
                [1.5, 10.0, -0.9, 4.0, 1.7, 1.5, np.pi]):
        other = _bev_score_text(box)
        assert other[1:] == (height, width) and abs(other[0] - count) <= 10, (box, other)


def test_bev_key_shows_its_title_and_stays_in_its_black_box():
    """The title is the key's first row; every pixel the key draws lies in the box draw_key returns, and a title
    longer than the picture is cut to it."""
    keyed = render_bev(NO_POINTS, GRID, CAR, None, CAR, title="frame 000006", legend=True)
    untitled = render_bev(NO_POINTS, GRID, CAR, None, CAR, legend=True)
    assert _changed(keyed[:18], untitled[:18]).sum() > 50
    grey = np.full((120, 300, 3), 128, np.uint8)
    long = "frame 000006, model " + "x" * 200
    left, top, right, bottom = draw_key(grey, [(long, None), ("detection (score)", (60, 220, 60))])
    assert right <= grey.shape[1]
    outside = np.ones(grey.shape[:2], bool)
    outside[top:bottom + 1, left:right + 1] = False
    assert (grey[outside] == 128).all()
    grey = np.full((60, 400, 3), 128, np.uint8)  # a row with a swatch as the widest: the box holds both
    left, top, right, bottom = draw_key(grey, [("detection (score)", (60, 220, 60))])
    outside = np.ones(grey.shape[:2], bool)
    outside[top:bottom + 1, left:right + 1] = False
    assert (grey[outside] == 128).all() and (grey[top:bottom, left:right] > 200).all(axis=2).any()  # white text


# ----------------------------------------------------------------------------- the camera picture


def test_camera_picture_of_an_rgb_image_has_the_files_colours(frame):
    """RGB in, BGR out: without boxes the camera picture is the image file's pixels as OpenCV writes them."""
    np.testing.assert_array_equal(render_camera(frame.image, frame.calib), cv2.imread(str(KITTI / "image_2" / "000006.png")))


def test_camera_wireframe_crosses_the_front_face(frame):
    """The crossed face shows the heading: the centre of the front face (where its diagonals cross) is drawn on,
    the centre of the rear face is not, for a car heading away and one turned across the road."""
    black = np.zeros_like(frame.image)
    for box in (np.array([[15.0, 2.0, -0.9, 4.0, 1.7, 1.5, 0.0]]), np.array([[12.0, -3.0, -0.9, 4.0, 1.7, 1.5, 0.6]])):
        corners = box_corners_3d(box)[0]
        green = (render_camera(black, frame.calib, box) == PREDICTION_BGR).all(axis=2)
        drawn = []
        for face in ([0, 3, 4, 7], [1, 2, 5, 6]):  # front (corners 0 and 3 the front edge), rear
            uv, _ = frame.calib.velo_to_image(corners[face].mean(axis=0)[None])
            u, v = np.rint(uv[0]).astype(int)
            drawn.append(bool(green[v - 1:v + 2, u - 1:u + 2].any()))
        assert drawn == [True, False], box


def test_camera_picture_leaves_out_a_box_more_than_a_km_away(frame):
    """A box 5 km ahead would be a dot on the horizon: left out."""
    far = np.array([[5000.0, 0.0, -0.9, 4.0, 1.7, 1.5, 0.0]])
    black = np.zeros_like(frame.image)
    assert (render_camera(black, frame.calib, far, np.array([0.9]), far) == 0).all()


def _score_text(frame, box: np.ndarray, score: float = 0.91) -> tuple[int, int, int]:
    """The score's text on a white image (the bright green pixels it adds): how many, how tall, how wide."""
    white = np.full_like(frame.image, 255)
    scored = render_camera(white, frame.calib, box, np.array([score]))
    text = _changed(scored, render_camera(white, frame.calib, box)) & (scored[..., 1] > 100)
    rows, cols = np.nonzero(text)
    return int(text.sum()), int(rows.max() - rows.min()), int(cols.max() - cols.min())


def test_camera_scores_are_two_decimals_on_a_dark_box_kept_inside_the_picture(frame):
    """A score's text is drawn whole wherever its box is: in view, cut by the image's left edge, or reaching above
    its top edge; on a dark box (on a white image, a black patch about it); 0.91 and 0.94 read apart."""
    ahead = np.array([[15.0, 2.0, -0.9, 4.0, 1.7, 1.5, 0.3]])
    left_edge = np.array([[7.0, 6.0, -0.9, 4.0, 1.7, 1.5, 0.0]])
    tall = np.array([[6.0, 0.0, 1.5, 4.0, 1.7, 4.0, 0.0]])  # reaching above the top of the image
    count, height, width = _score_text(frame, ahead)
    assert count > 50 and height >= 8 and width >= 20
    for box in (left_edge, tall):
        uv, _ = frame.calib.velo_to_image(box_corners_3d(box).reshape(-1, 3))
        assert uv[:, 0].min() < 0 or uv[:, 1].min() < 0  # the box does leave the picture
        other = _score_text(frame, box)
        assert other[1:] == (height, width) and abs(other[0] - count) <= 5
    white = np.full_like(frame.image, 255)
    scored = render_camera(white, frame.calib, ahead, np.array([0.91]))
    dark = _changed(scored, render_camera(white, frame.calib, ahead)) & (scored.max(axis=2) < 30)
    assert dark.sum() > 300  # the dark box behind the text
    assert _changed(render_camera(white, frame.calib, ahead, np.array([0.94])), scored).any()


# ----------------------------------------------------------------------------- depth panel, bars, labels, video


def test_depth_colours_run_warm_near_to_blue_far_and_stay_blue_beyond_the_range():
    """Near is warm (red above blue), far blue; everything at or past ``max_depth`` is its colour; the colour is
    the fraction of the range (20 m of 40 colours as 40 m of 80)."""
    near, middle, far, at_end, beyond, very_far = render_depth(np.array([[3.0, 40.0, 75.0, 80.0, 500.0, 1e6]]))[0]
    assert int(near[2]) > int(near[0]) + 100 and int(far[0]) > int(far[2]) + 100
    np.testing.assert_array_equal(np.stack([beyond, very_far]), np.stack([at_end, at_end]))
    assert (middle != near).any() and (middle != far).any()
    np.testing.assert_array_equal(render_depth(np.array([[20.0, 30.0]]), max_depth=40.0),
                                  render_depth(np.array([[40.0, 60.0]]), max_depth=80.0))


def test_depth_panel_error_row_uses_its_bars_colours_for_over_and_under_estimates():
    """The error row: zero error in the bar's first colour, 10 m too far or too near both in its last (over the
    5 m it shows), grey where there is no ground truth (black was zero error's colour too); the maps' rows show
    the prediction, then the truth."""
    height, width = 120, 600
    truth = np.full((height, width), 30.0, np.float32)
    truth[:, 500:] = 0.0  # no ground truth
    prediction = truth.copy()
    prediction[:, 200:300] = 40.0
    prediction[:, 300:400] = 20.0
    prediction[:, 500:] = 60.0
    panel = render_depth_panel(np.zeros((height, width, 3), np.uint8), prediction, truth)
    error = panel[3 * height + 40:]
    np.testing.assert_array_equal(error[:, 50], np.broadcast_to(error_colours()[0], error[:, 50].shape))
    for col in (250, 350):
        np.testing.assert_array_equal(error[:, col], np.broadcast_to(error_colours()[-1], error[:, col].shape))
    assert (error[:, 510:] == NO_TRUTH_BGR).all()
    predicted, truth_row = panel[height + 40:2 * height], panel[2 * height + 40:3 * height]
    np.testing.assert_array_equal(predicted[:, 250], np.broadcast_to(render_depth(np.array([[40.0]]))[0, 0], (80, 3)))
    np.testing.assert_array_equal(truth_row[:, 250], np.broadcast_to(render_depth(np.array([[30.0]]))[0, 0], (80, 3)))


def test_depth_panel_camera_row_has_the_files_colours(frame):
    """The camera row: the RGB image back in the file's BGR, below its label."""
    truth = np.zeros(frame.image.shape[:2], np.float32)
    panel = render_depth_panel(frame.image, truth, truth)
    file = cv2.imread(str(KITTI / "image_2" / "000006.png"))
    np.testing.assert_array_equal(panel[40:file.shape[0]], file[40:])


def test_colour_bar_fits_a_narrow_picture():
    """On a picture narrower than the bar asked for, the bar and its labels are shortened to fit it."""
    picture = np.zeros((40, 200, 3), np.uint8)
    left, top, right, _ = draw_colour_scale(picture, depth_colours(), 0.0, 80.0, "m", length=200)
    assert 0 <= left < right <= picture.shape[1]
    np.testing.assert_array_equal(picture[top, right - 1], depth_colours()[-1])


def test_label_is_white_on_a_black_box():
    """A picture's label reads on a white sky: white text on black."""
    picture = draw_label(np.full((60, 300, 3), 255, np.uint8), "camera")
    assert (picture[:20, :60] == 0).all(axis=2).sum() > 300


def test_video_frame_is_the_camera_above_the_bev_at_most_as_tall():
    """stack_views puts the camera picture above the BEV picture, scaled to its width but never taller than it."""
    bev = np.full((704, 800, 3), 50, np.uint8)
    wide = np.full((375, 1242, 3), 200, np.uint8)
    stacked = stack_views(wide, bev)
    np.testing.assert_array_equal(stacked[-704:], bev)
    assert stacked.shape[0] == 704 + round(375 * 800 / 1242) and (stacked[:100] == 200).all()
    tall = np.full((1000, 100, 3), 200, np.uint8)  # taller than wide: capped at the BEV's height
    assert stack_views(tall, bev).shape == (2 * 704, 800, 3)


def test_video_discarded_before_its_first_frame_leaves_nothing(tmp_path):
    """Probing the folder leaves nothing; a run that fails before its first frame discards a video that never
    started: no error, no file."""
    video = FrameVideo(tmp_path / "run.mp4")
    video.probe()  # the folder is checked by making and removing the hidden file
    assert list(tmp_path.iterdir()) == []
    video.discard()
    assert list(tmp_path.iterdir()) == []


def test_video_plays_at_kittis_10_hz_by_default(tmp_path):
    """The default frame rate is the LiDAR's (10 a second), what pipeline.detect --help says."""
    video = FrameVideo(tmp_path / "run.mp4")
    for _ in range(2):
        video.add(np.zeros((64, 64, 3), np.uint8))
    assert video.close()
    capture = cv2.VideoCapture(str(tmp_path / "run.mp4"))
    try:
        assert capture.get(cv2.CAP_PROP_FPS) == 10 and capture.get(cv2.CAP_PROP_FRAME_COUNT) == 2
    finally:
        capture.release()


def test_a_picture_opencv_refuses_is_an_oserror_naming_the_file(tmp_path):
    for path, picture in ((tmp_path / "empty.png", np.zeros((0, 0, 3), np.uint8)),
                          (tmp_path / "picture.xyz", np.zeros((4, 4, 3), np.uint8))):
        with pytest.raises(OSError, match="could not write the PNG") as caught:
            write_png(path, picture)
        assert caught.value.filename == str(path)


# ----------------------------------------------------------------------------- the demo


def test_demo_sparse_depth_picture_keeps_colours_grows_returns_and_uses_the_depth_scale():
    """The camera view keeps its colours (RGB in), each return is a 3 × 3 patch, coloured as every depth picture
    colours that depth (0–80 m)."""
    rgb = np.zeros((1, 3, 100, 500), np.float32)
    rgb[0, 0] = 255.0  # pure red
    sparse = np.zeros((1, 1, 100, 500), np.float32)
    sparse[0, 0, 60, 100] = 40.0
    picture = demo.sparse_depth_picture(rgb, sparse)
    np.testing.assert_array_equal(picture[50, 250], [0, 0, 255])
    patch = picture[100 + 59:100 + 62, 99:102]
    np.testing.assert_array_equal(patch, np.broadcast_to(render_depth(np.array([[40.0]]))[0, 0], (3, 3, 3)))
    assert (picture[100 + 58, 100] == 0).all() and (picture[100 + 62, 100] == 0).all()


def test_demo_core_pictures_summary_and_key(tmp_path):
    """The core's two BEV pictures: the 64-line scan lights more cells than its thinning to 16 lines (which keeps
    about a quarter of the points), each with every labelled car in dashed blue and its own title in the key; the summary
    counts what it says it counts."""
    tic = time.perf_counter()
    summary = demo.run_core("000006", tmp_path)
    wall_ms = (time.perf_counter() - tic) * 1e3
    labels = (KITTI / "label_2" / "000006.txt").read_text().splitlines()
    cars = sum(line.split()[0] == "Car" for line in labels)
    assert summary["labelled_cars"] == cars == 4
    assert 0.2 < summary["points_16"] / summary["points_64"] < 0.3
    assert 0 < summary["sparse_depth_pixels"] <= summary["points_16"]
    assert 0 < summary["core_ms"] <= wall_ms
    empty = render_bev(NO_POINTS, get_preset("edge").bev)
    lit = {}
    for lines in (64, 16):
        picture = cv2.imread(str(tmp_path / f"000006_bev_{lines}.png"))
        scene = picture[-empty.shape[0]:]  # below the key's strip
        lit[lines] = int(((scene != empty).any(axis=2) & (scene == scene[..., :1]).all(axis=2)).sum())
        blue = (picture == GROUND_TRUTH_BGR).all(axis=2)
        blue[:80, :300] = False  # the key's swatch
        # A box's dashes (5-pixel gaps) joined into one outline: one outline per labelled car.
        joined = cv2.dilate(blue.astype(np.uint8), np.ones((7, 7), np.uint8))
        assert cv2.connectedComponents(joined)[0] - 1 == cars
        title = f"KITTI 000006: {'the 64-line scan' if lines == 64 else 'the scan thinned to 16 lines'}"
        expected = np.zeros_like(picture)
        left, top, right, bottom = draw_key(expected, bev_key_rows(title, False, True))
        np.testing.assert_array_equal(picture[top:bottom + 1, left:right + 1], expected[top:bottom + 1, left:right + 1])
    assert lit[16] < 0.5 * lit[64]


def test_demo_defaults_to_the_shipped_model_on_000006_into_outputs_demo(tmp_path, monkeypatch, capsys):
    """``make demo`` (no arguments): the shipped weights/edge on frame 000006, written under outputs/demo."""
    monkeypatch.chdir(tmp_path)
    assert demo.main([]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["mode"].startswith(f"detector ({REPO / 'weights' / 'edge'})") and summary["frame"] == "000006"
    assert sorted(p.relative_to(tmp_path).as_posix() for p in (tmp_path / "outputs").rglob("*.*")) == [
        "outputs/demo/bev/000006.png", "outputs/demo/camera/000006.png", "outputs/demo/data/000006.txt"]


def test_demo_without_the_shipped_weights_says_so_and_runs_the_core(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(demo, "DEFAULT_MODELS", tmp_path / "weights" / "edge")
    assert demo.main(["--out", str(tmp_path / "o")]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["mode"] == "core (no model directory)"
    assert captured.err == (f"no model directory at {tmp_path / 'weights' / 'edge'}: running the frame-processing "
                            "core alone\n")


def test_demo_bad_input_is_one_line_and_status_2(tmp_path, capsys):
    """--models with --core is a usage error; a broken manifest, a frame that is not bundled and an --out that is a
    file are one line each, and leave no --out behind."""
    with pytest.raises(SystemExit) as usage:
        demo.main(["--core", "--models", str(REPO / "weights" / "edge"), "--out", str(tmp_path / "o")])
    assert usage.value.code == 2 and "not allowed with argument" in capsys.readouterr().err
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "manifest.json").write_text("{")
    assert demo.main(["--models", str(broken), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {broken / 'manifest.json'}: unreadable manifest") and err.count("\n") == 1
    for flags in (["--core"], []):  # a frame that is not bundled, with the core alone and with the detector
        assert demo.main([*flags, "--frame", "999999", "--out", str(tmp_path / "o")]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and "999999" in err and err.count("\n") == 1
    (tmp_path / "a-file").write_text("")
    assert demo.main(["--core", "--out", str(tmp_path / "a-file")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: --out {tmp_path / 'a-file'}: ") and err.count("\n") == 1
    assert err.count(str(tmp_path / "a-file")) == 1  # the path once, not again as the error's own file name
    assert not (tmp_path / "o").exists()


def test_demo_help_says_what_it_does_and_lists_exactly_the_bundled_frames(capsys):
    with pytest.raises(SystemExit) as done:
        demo.main(["--help"])
    text = capsys.readouterr().out
    assert done.value.code == 0
    description = " ".join(text.split("\n\n")[1].split())
    assert "KITTI frame" in description and not description.lstrip().startswith("python -m")
    listed = re.search(r"bundled KITTI frame:(.*?)\(default (\d+)\)", text, re.DOTALL)
    assert listed is not None
    bundled = sorted(p.stem for p in (KITTI / "velodyne").glob("*.bin"))
    assert re.findall(r"\d{6}", listed.group(1)) == bundled and listed.group(2) in bundled
