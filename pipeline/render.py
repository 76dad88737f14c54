"""Pictures people look at (OpenCV only): the BEV view of points and boxes, the camera image with the boxes
as 3D wireframes, depth maps, and a frame's views stacked into the frames of an MP4 video (FrameVideo)."""

from __future__ import annotations

import errno
import os
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from pipeline.boxes import BOX_EDGES, bev_corners, box_corners_3d, in_camera_view, segments_in_front
from pipeline.calib import Calibration
from pipeline.preprocess import scale_calibration
from pipeline.presets import BevGrid

# Okabe–Ito colours (BGR), apart under every common colour-vision deficiency: detections orange on solid lines,
# the labelled cars sky blue on dashed lines, so that neither the hue nor the line alone carries the difference.
PREDICTION_BGR = (0, 159, 230)
GROUND_TRUTH_BGR = (233, 180, 86)
# A detection outside the camera's view (not in the result file): the orange at half brightness, on thin lines.
OUTSIDE_VIEW_BGR = (0, 110, 160)
# The camera's pseudo points (magenta) under the scan's own returns (grey to white, drawn on top): a sector the
# LiDAR lost shows as magenta alone. Magenta stays a colour (blue) for a red-green colour-blind reader, where the
# Okabe–Ito bluish green turns grey, as the scan is.
PSEUDO_BGR = (200, 70, 200)
SCAN_KEY_BGR = (255, 255, 255)
VIEW_BGR = (150, 150, 150)  # the camera's field of view: lighter than the rings
DASH_PX, GAP_PX = 8, 5
# The two diagonals of a box's front face (corners 0 and 3 are the front edge), drawn to show its heading.
FRONT_DIAGONALS = ((0, 7), (3, 4))

# A key's row: (text, colour) or (text, colour, swatch style: "line", "dashed", "thin" or "points"); no colour:
# a title row.
KeyRow = tuple[str, tuple[int, int, int] | None] | tuple[str, tuple[int, int, int] | None, str]


def _to_pixels(xy: np.ndarray, grid: BevGrid, scale: float) -> np.ndarray:
    """LiDAR (x, y) → picture (column, row): x forward points up, y left points left."""
    col = (grid.y_max - xy[..., 1]) / scale
    row = (grid.x_max - xy[..., 0]) / scale
    return np.stack([col, row], axis=-1)


# Text of the keys and labels drawn on the pictures: OpenCV's plain font at a size that stays readable.
FONT = cv2.FONT_HERSHEY_SIMPLEX
KEY_SCALE = 0.45
RING_LABEL_BGR = (170, 170, 170)  # bright enough on black to read, dimmer than the points and boxes
RING_BGR = (70, 70, 70)
RING_STEP_M = 10


def fit_text(text: str, width: int, scale: float = KEY_SCALE) -> str:
    """``text`` cut (with "...") to fit ``width`` pixels at ``scale``: a long model path must not run off the
    picture."""
    if cv2.getTextSize(text, FONT, scale, 1)[0][0] <= width:
        return text
    while len(text) > 1 and cv2.getTextSize(text + "...", FONT, scale, 1)[0][0] > width:
        text = text[:-1]
    return text + "..."


_KEY_LINE_H, _KEY_SWATCH, _KEY_PAD = 18, 22, 6
_KEY_STRIP_GAP = 3  # black rows between a BEV key's box and the line above the scene


def key_box(picture_width: int, rows: list[KeyRow], corner: str = "top-left") -> tuple[int, int, int, int]:
    """Where :func:`draw_key` puts a key of ``rows`` on a picture ``picture_width`` wide, as (left, top, right,
    bottom): labels drawn before the key keep out of it."""
    room = picture_width - 2 * _KEY_PAD - _KEY_SWATCH - 6
    width = max(cv2.getTextSize(fit_text(row[0], room), FONT, KEY_SCALE, 1)[0][0]
                + (_KEY_SWATCH + 6 if row[1] else 0) for row in rows) + 2 * _KEY_PAD
    height = _KEY_LINE_H * len(rows) + _KEY_PAD
    left = 0 if corner == "top-left" else max(picture_width - width, 0)
    return left, 0, left + width, height


def _swatch(picture: np.ndarray, x: int, y: int, colour: tuple[int, int, int], style: str) -> None:
    """A key row's sample of what it names, ``_KEY_SWATCH`` pixels wide from (x, y): a line as the boxes draw
    it, or dots for points."""
    if style == "points":
        for dx in range(1, _KEY_SWATCH, 5):
            cv2.rectangle(picture, (x + dx, y - 1), (x + dx + 1, y + 1), colour, -1)
        return
    segment = np.array([[[x, y], [x + _KEY_SWATCH, y]]], np.int32)
    _draw_segments(picture, segment, colour, style)


def draw_key(picture: np.ndarray, rows: list[KeyRow], corner: str = "top-left") -> tuple[int, int, int, int]:
    """A key in a corner of the picture (in place): one row per (text, colour[, style]), a short sample of the
    colour before the text drawn as the picture draws it (no colour: a title row), white text on a black box so it
    reads on any background. Returns the box as (left, top, right, bottom), as :func:`key_box`."""
    room = picture.shape[1] - 2 * _KEY_PAD - _KEY_SWATCH - 6
    left, top, right, bottom = key_box(picture.shape[1], rows, corner)
    cv2.rectangle(picture, (left, top), (right, bottom), (0, 0, 0), thickness=-1)
    for i, row in enumerate(rows):
        text, colour = fit_text(row[0], room), row[1]
        baseline = _KEY_PAD + _KEY_LINE_H * i + 11
        x = left + _KEY_PAD
        if colour is not None:
            _swatch(picture, x, baseline - 4, colour, row[2] if len(row) > 2 else "line")
            x += _KEY_SWATCH + 6
        cv2.putText(picture, text, (x, baseline), FONT, KEY_SCALE, (255, 255, 255), 1, cv2.LINE_AA)
    return left, top, right, bottom


def _dashes(segments: np.ndarray) -> np.ndarray:
    """(M, 2, 2) segments (two (column, row) ends each) → (D, 2, 2) int32 dashes along them, ``DASH_PX`` drawn
    then ``GAP_PX`` left, each segment starting with a dash."""
    ends = segments.astype(np.float64)
    delta = ends[:, 1] - ends[:, 0]
    length = np.hypot(delta[:, 0], delta[:, 1])
    count = np.maximum(np.ceil(length / (DASH_PX + GAP_PX)), 1).astype(np.int64)
    which = np.repeat(np.arange(len(ends)), count)
    nth = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    start = nth * float(DASH_PX + GAP_PX)
    stop = np.minimum(start + DASH_PX, length[which])
    unit = delta[which] / np.maximum(length[which], 1e-9)[:, None]
    dashes = ends[which, 0][:, None] + unit[:, None] * np.stack([start, stop], axis=1)[..., None]
    return np.rint(dashes).astype(np.int32)


def _draw_segments(canvas: np.ndarray, segments: np.ndarray, colour: tuple[int, int, int], style: str) -> None:
    """(M, 2, 2) int32 segments drawn in place: ``line`` solid 2 px (detections), ``dashed`` 2 px dashes (the
    labelled cars), ``thin`` solid 1 px (detections outside the camera's view, the camera's field of view)."""
    if len(segments) == 0:
        return
    if style == "dashed":
        segments = _dashes(segments)
    cv2.polylines(canvas, list(segments), False, colour, 1 if style == "thin" else 2, cv2.LINE_AA)


def _overlaps(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    """Whether two (left, top, right, bottom) boxes share a pixel."""
    return a[0] <= b[2] and b[0] <= a[2] and a[1] <= b[3] and b[1] <= a[3]


def _free_spot(candidates: list[tuple[float, float]], text_wh: tuple[int, int], picture_wh: tuple[int, int],
               taken: list[tuple[int, int, int, int]]) -> tuple[int, int]:
    """Where a label goes: the first of ``candidates`` (its text's left end and baseline), moved whole into the
    picture, whose box (the text and 2–3 pixels about it) meets none of ``taken`` (earlier labels, the sensor, the
    camera picture's key, the BEV's labelled cars); the first one when every one does. Its box is added to
    ``taken``. A loop over a few candidates of a few boxes: labels are one a box, tens at most."""
    (text_w, text_h), (width, height) = text_wh, picture_wh
    spots = []
    for column, row in candidates:
        at = (int(np.clip(column, 0, max(width - text_w - 1, 0))),
              int(np.clip(row, text_h + 1, max(height - 3, text_h + 1))))
        box = (at[0] - 2, at[1] - text_h - 3, at[0] + text_w + 2, at[1] + 3)
        if not any(_overlaps(box, other) for other in taken):
            taken.append(box)
            return at
        spots.append((at, box))
    taken.append(spots[0][1])
    return spots[0][0]


def _ring_label_at(radius_px: int, origin: tuple[int, int], text_h: int) -> tuple[int, int] | None:
    """Where a range ring's label goes: on the forward axis, just right of it and above the ring (just below it
    for a ring at the picture's far edge), so a box ahead reads against the rings' distances; None for a ring
    that crosses the axis off the picture."""
    row = origin[1] - radius_px
    if row < 0:
        return None
    return origin[0] + 4, row - 3 if row - 3 - text_h >= 0 else row + text_h + 4


def _score_candidates(corners: np.ndarray, text_w: int, text_h: int) -> list[tuple[float, float]]:
    """Where a BEV box's score may go (``corners``: its four (column, row), the front-left first), first choice
    first: above and right of its front-left corner (under the box when that is past the far edge), then right of
    it, left of it, under it and above it."""
    left, top = corners.min(axis=0)
    right, bottom = corners.max(axis=0)
    first = (corners[0, 0] + 4, corners[0, 1] - 4)
    if first[1] - text_h < 0:  # above the top edge: under the box's lowest point, clear of its lines
        first = (corners[0, 0] + 4, bottom + text_h + 6)
    return [first, (right + 5, top + text_h), (left - text_w - 5, top + text_h), (left, bottom + text_h + 6),
            (left, top - 5)]


def render_bev(
    points: np.ndarray,
    grid: BevGrid,
    boxes: np.ndarray | None = None,
    scores: np.ndarray | None = None,
    gt_boxes: np.ndarray | None = None,
    metres_per_pixel: float = 0.1,
    title: str | None = None,
    legend: bool = False,
    pseudo: np.ndarray | None = None,
    view: tuple[Calibration, tuple[int, int]] | None = None,
    warnings: Sequence[str] = (),
) -> np.ndarray:
    """BGR uint8 picture of the BEV grid, forward (x) up, left (y) left, the sensor a white triangle at the
    bottom centre: points (grey to white, brighter where denser), range rings every 10 m labelled along the
    forward axis, the labelled cars in dashed sky blue, detections in orange with their scores.

    pseudo: the camera's pseudo points, drawn in magenta under ``points`` (then the scan's own returns), so
    a sector the LiDAR lost shows. view: the camera's (calibration, image (rows, columns)): its field of view is
    drawn, and the detections whose centre it does not see (those a result file leaves out) dimmed on thin lines.
    warnings: the frame's warning codes, for the key. legend: a key (``title`` first, the warnings, then what
    each colour is and which way is ahead) for pictures people look at, in its own strip above the scene
    (:func:`key_strip_height` rows, room for a warnings row kept), so it covers nothing: the scene is the
    picture's last rows, as without the key, at ``metres_per_pixel``; off for a picture compared pixel by
    pixel."""
    size = _scene_size(grid, metres_per_pixel)
    canvas = _draw_points(points, pseudo, grid, metres_per_pixel, size)
    origin, tip = _sensor_at(grid, metres_per_pixel, size[1])
    # The boxes the camera sees, as a result file keeps them (pipeline.boxes.in_camera_view).
    seen = in_camera_view(boxes, *view) if view is not None and boxes is not None else None
    taken = [_sensor_box(tip)]  # what labels keep clear of; each label drawn joins it
    _draw_range_rings(canvas, grid, metres_per_pixel, origin, taken)
    if view is not None:
        _draw_camera_view(canvas, view, grid, metres_per_pixel)
    # Under the boxes, as the points and rings are: a box at the sensor stays whole.
    _draw_sensor(canvas, tip)
    # The labelled cars first: their extents join ``taken``, so the detections' scores keep off them.
    _draw_bev_boxes(canvas, gt_boxes, None, None, grid, metres_per_pixel, taken)
    _draw_bev_boxes(canvas, boxes, scores, seen, grid, metres_per_pixel, taken, prediction=True)
    if not legend:
        return canvas
    split = None if seen is None else (int(seen.sum()), int((~seen).sum()))
    rows = bev_key_rows(title, boxes is not None, gt_boxes is not None, pseudo is not None, view is not None,
                        warnings, split)
    return _under_key_strip(canvas, rows, bool(warnings))


def _scene_size(grid: BevGrid, metres_per_pixel: float) -> tuple[int, int]:
    """The BEV scene's (width, height) in pixels: the grid's y extent across, its x extent up."""
    width = round((grid.y_max - grid.y_min) / metres_per_pixel)
    height = round((grid.x_max - grid.x_min) / metres_per_pixel)
    return width, height


def _point_shade(cloud: np.ndarray, grid: BevGrid, metres_per_pixel: float, size: tuple[int, int]) -> np.ndarray:
    """(height, width) 0–1: log of the points a pixel holds, 1 from 19 on."""
    width, height = size
    pix = np.floor(_to_pixels(cloud[:, :2], grid, metres_per_pixel)).astype(np.int64)
    ok = (pix[:, 0] >= 0) & (pix[:, 0] < width) & (pix[:, 1] >= 0) & (pix[:, 1] < height)
    density = np.bincount(pix[ok, 1] * width + pix[ok, 0], minlength=height * width).astype(np.float32)
    return np.clip(np.log1p(density) / np.log(20.0), 0, 1).reshape(height, width)


def _draw_points(points: np.ndarray, pseudo: np.ndarray | None, grid: BevGrid, metres_per_pixel: float,
                 size: tuple[int, int]) -> np.ndarray:
    """The scene's first layer, a new BGR picture of ``size``: the scan's points grey to white, and the camera's
    ``pseudo`` points in magenta where the scan has none."""
    scan = (_point_shade(points, grid, metres_per_pixel, size) * 255).astype(np.uint8)
    canvas = cv2.cvtColor(scan, cv2.COLOR_GRAY2BGR)
    if pseudo is not None and len(pseudo):
        camera = (_point_shade(pseudo, grid, metres_per_pixel, size)[..., None]
                  * np.array(PSEUDO_BGR, np.float32)).astype(np.uint8)
        canvas = np.where((scan > 0)[..., None], canvas, camera)  # the scan on top
    return canvas


def _sensor_at(grid: BevGrid, metres_per_pixel: float, height: int) -> tuple[tuple[int, int], tuple[int, int]]:
    """The sensor's pixel (the range rings' centre) and the tip of its triangle: 14 rows above the sensor, or above
    the picture's bottom edge for a sensor on or below it (a grid from x = 0 forward, as the presets')."""
    column, row = _to_pixels(np.array([0.0, 0.0]), grid, metres_per_pixel)
    origin = (int(column), int(row))
    return origin, (origin[0], min(origin[1], height) - 14)


def _sensor_box(tip: tuple[int, int]) -> tuple[int, int, int, int]:
    """The sensor's triangle (:func:`_draw_sensor`) with a margin, as (left, top, right, bottom)."""
    return tip[0] - 8, tip[1] - 2, tip[0] + 8, tip[1] + 14


def _draw_sensor(canvas: np.ndarray, tip: tuple[int, int]) -> None:
    """The sensor, in place: a white triangle pointing ahead, so the picture says which way is forward without
    the key."""
    cv2.fillPoly(canvas, [np.array([tip, (tip[0] - 6, tip[1] + 12), (tip[0] + 6, tip[1] + 12)], np.int32)],
                 (255, 255, 255), cv2.LINE_AA)


def _draw_range_rings(canvas: np.ndarray, grid: BevGrid, metres_per_pixel: float, origin: tuple[int, int],
                      taken: list[tuple[int, int, int, int]]) -> None:
    """Range rings every ``RING_STEP_M`` about the sensor at ``origin``, in place, out to the grid's farthest
    corner; each ring's label goes on the forward axis (:func:`_ring_label_at`) and its box joins ``taken``."""
    # Range rings every 10 m help reading distances; labelled on the forward axis, where a box ahead is read.
    farthest = float(np.hypot(max(grid.x_max, -grid.x_min), max(grid.y_max, -grid.y_min)))
    for r in range(RING_STEP_M, int(farthest) + 1, RING_STEP_M):
        radius = int(r / metres_per_pixel)
        cv2.circle(canvas, origin, radius, RING_BGR, 1, cv2.LINE_AA)
        (text_w, text_h), _ = cv2.getTextSize(f"{r} m", FONT, 0.4, 1)
        at = _ring_label_at(radius, origin, text_h)
        if at is not None:
            cv2.putText(canvas, f"{r} m", at, FONT, 0.4, RING_LABEL_BGR, 1, cv2.LINE_AA)
            taken.append((at[0], at[1] - text_h, at[0] + text_w, at[1] + 2))


def _draw_camera_view(canvas: np.ndarray, view: tuple[Calibration, tuple[int, int]], grid: BevGrid,
                      metres_per_pixel: float) -> None:
    """The camera's field of view (``view``: its calibration and image (rows, columns)), in place: the left and
    right edges of :func:`camera_view_edges` on thin grey lines."""
    edges = _to_pixels(camera_view_edges(*view), grid, metres_per_pixel)
    _draw_segments(canvas, np.rint(edges).astype(np.int32), VIEW_BGR, "thin")


def _under_key_strip(scene: np.ndarray, rows: list[KeyRow], has_warnings: bool) -> np.ndarray:
    """The scene under a strip of its own holding the key of ``rows``, with a grey line along the scene's far
    edge."""
    # The key in a strip of its own above the scene: drawn on the scene, its black box (about 500 × 130 pixels
    # with the service's title) hid all beyond 57 m on the left, the 60 and 70 m ring labels and a detection at
    # 61 m with them. The strip keeps room for a warnings row the frame may lack, so a video's frames keep one size.
    width = scene.shape[1]
    strip = np.zeros((key_strip_height(width, rows if has_warnings else [*rows, ("", None)]), width, 3), np.uint8)
    draw_key(strip, rows)
    strip[-1] = RING_BGR  # where the scene begins: its far edge
    return np.vstack([strip, scene])


def key_strip_height(picture_width: int, rows: list[KeyRow]) -> int:
    """Rows of the strip above a BEV scene that holds a key of ``rows`` (:func:`render_bev` with ``legend``):
    the key's box, a gap, and a one-pixel line along the scene's far edge."""
    return key_box(picture_width, rows)[3] + 1 + _KEY_STRIP_GAP + 1


def _draw_bev_boxes(canvas: np.ndarray, drawn: np.ndarray | None, scores: np.ndarray | None,
                    seen: np.ndarray | None, grid: BevGrid, metres_per_pixel: float,
                    taken: list[tuple[int, int, int, int]], prediction: bool = False) -> None:
    """Boxes as outlines with a line from the centre to the front (the heading), in place: detections (with
    their scores, dimmed where ``seen`` is False, placed clear of ``taken``) or the labelled cars (dashed; their
    extents join ``taken``)."""
    if drawn is None or len(drawn) == 0:
        return
    corners = _to_pixels(bev_corners(drawn), grid, metres_per_pixel)
    # A box far off the picture (a broken scan can give one) has no pixel position OpenCV accepts.
    drawable = np.isfinite(corners).all(axis=(1, 2)) & (np.abs(corners) < 1e5).all(axis=(1, 2))
    corners = np.rint(corners[drawable]).astype(np.int32)
    inside = np.ones(len(corners), bool) if seen is None else np.asarray(seen)[drawable]
    front = np.rint(corners[:, [0, 3]].mean(axis=1)).astype(np.int32)  # mid front edge: heading
    centre = np.rint(corners.mean(axis=1)).astype(np.int32)
    # (K, 5, 2, 2): the four edges and the heading line, each as its two ends.
    segments = np.concatenate([np.stack([corners, np.roll(corners, -1, axis=1)], axis=2),
                               np.stack([centre, front], axis=1)[:, None]], axis=1)
    if not prediction:
        _draw_segments(canvas, segments.reshape(-1, 2, 2), GROUND_TRUTH_BGR, "dashed")
        # The detections' scores keep off the labelled cars (KITTI 000006's 0.53 sat on one).
        taken += [(int(left), int(top), int(right), int(bottom))
                  for (left, top), (right, bottom) in zip(corners.min(axis=1), corners.max(axis=1), strict=True)]
        return
    _draw_segments(canvas, segments[~inside].reshape(-1, 2, 2), OUTSIDE_VIEW_BGR, "thin")
    _draw_segments(canvas, segments[inside].reshape(-1, 2, 2), PREDICTION_BGR, "line")
    if scores is None:
        return
    height, width = canvas.shape[:2]
    for i, score in enumerate(np.asarray(scores)[drawable]):  # one label a box: tens of boxes at most
        text = f"{score:.2f}"
        (text_w, text_h), _ = cv2.getTextSize(text, FONT, 0.45, 1)
        at = _free_spot(_score_candidates(corners[i], text_w, text_h), (text_w, text_h), (width, height), taken)
        colour = PREDICTION_BGR if inside[i] else OUTSIDE_VIEW_BGR
        cv2.putText(canvas, text, at, FONT, 0.45, colour, 1, cv2.LINE_AA)


def split_scan_and_pseudo(seen: np.ndarray, pseudo_count: int) -> tuple[np.ndarray, np.ndarray | None]:
    """The points PIXOR saw (``seen``: the camera's ``pseudo_count`` pseudo points first, then the scan's, as
    :attr:`pipeline.detector.Detections.points` keeps them) as the scan's own returns and the pseudo points (None:
    none, a LiDAR-only model's), for :func:`render_bev`'s ``points`` and ``pseudo``."""
    if pseudo_count <= 0:
        return seen, None
    return seen[pseudo_count:], seen[:pseudo_count]


def camera_view_edges(calib: Calibration, image_hw: tuple[int, int], far_m: float = 200.0) -> np.ndarray:
    """(2, 2, 2): the left and right edges of the camera's view on the BEV, each as two (x, y) in the LiDAR frame
    (0.5 m and ``far_m`` in front of the camera, through the middle row of the image's first and last column)."""
    height, width = image_hw
    u = np.array([0.0, 0.0, width, width])
    depth = np.array([0.5, far_m, 0.5, far_m])
    xyz = calib.image_to_velo(u, np.full(4, height / 2), depth)
    return xyz[:, :2].reshape(2, 2, 2)


def key_rows(title: str | None, predictions: bool, ground_truth: bool,
             warnings: Sequence[str] = ()) -> list[KeyRow]:
    """The rows of a picture's key: its title, the frame's warning codes, then what the colours drawn are."""
    rows: list[KeyRow] = [(title, None)] if title else []
    if warnings:
        rows.append((f"frame warnings: {', '.join(dict.fromkeys(map(str, warnings)))}", None))
    if predictions:
        rows.append(("detection (score)", PREDICTION_BGR, "line"))
    if ground_truth:
        rows.append(("labelled cars", GROUND_TRUTH_BGR, "dashed"))
    return rows


def bev_key_rows(title: str | None, predictions: bool, ground_truth: bool, pseudo: bool = False,
                 view: bool = False, warnings: Sequence[str] = (),
                 split: tuple[int, int] | None = None) -> list[KeyRow]:
    """The rows of a BEV picture's key: :func:`key_rows`, how many detections the camera sees (``split``: in
    view, outside), the points (the scan's and the camera's, when ``pseudo``), the camera's view and how to read
    the view."""
    rows = key_rows(title, predictions, ground_truth, warnings)
    if split is not None and predictions:
        shown = rows.index(("detection (score)", PREDICTION_BGR, "line"))
        rows[shown] = (f"detection (score): {split[0]} in view (written), {split[1]} outside", PREDICTION_BGR, "line")
        rows.insert(shown + 1, ("detection outside the camera's view", OUTSIDE_VIEW_BGR, "thin"))
    if pseudo:
        rows += [("LiDAR returns (on top)", SCAN_KEY_BGR, "points"), ("camera's pseudo points", PSEUDO_BGR, "points")]
    if view:
        rows.append(("camera's field of view", VIEW_BGR, "thin"))
    return [*rows, (f"bird's-eye view: forward up, rings every {RING_STEP_M} m", None)]


def render_camera(
    image: np.ndarray,
    calib: Calibration,
    boxes: np.ndarray | None = None,
    scores: np.ndarray | None = None,
    gt_boxes: np.ndarray | None = None,
    scale: float = 1.0,
    title: str | None = None,
    legend: bool = False,
    warnings: Sequence[str] = (),
) -> np.ndarray:
    """BGR uint8 picture of the camera image (RGB in) with the 3D boxes drawn as wireframes, the front face
    crossed: the labelled cars in dashed sky blue, detections in orange with their scores (kept inside the
    picture, each moved clear of the labels before it). An edge reaching behind the camera (a car beside it) is
    cut at :data:`pipeline.boxes.NEAR_PLANE_M` in front of it; a box wholly behind the camera, with a corner more
    than 1 km in front of or behind it, not finite or projecting more than 1e5 pixels away is left out (the BEV
    picture shows every box).

    scale: the image is resized by it first and the boxes drawn on the result, so lines and scores keep
    their size in pixels (a video's frame: :func:`camera_scale_in_stack`). legend: a key in the top-right
    corner (``title`` first, the frame's ``warnings`` codes, then what each colour is), clear of a video's caption
    at the top left."""
    if scale != 1.0:
        size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        calib = scale_calibration(calib, scale)
    canvas = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2BGR)
    rows = key_rows(title, boxes is not None, gt_boxes is not None, warnings)
    taken = [key_box(canvas.shape[1], rows, "top-right")] if legend else []
    for drawn, colour, with_score in ((gt_boxes, GROUND_TRUTH_BGR, False), (boxes, PREDICTION_BGR, True)):
        if drawn is None or len(drawn) == 0:
            continue
        rect = calib.velo_to_rect(box_corners_3d(drawn).reshape(-1, 3)).reshape(-1, 8, 3)
        # (K, 14, 2, 3): each segment's two ends, cut at the near plane; one wholly behind it is not drawn.
        ends, shown = segments_in_front(rect, BOX_EDGES + FRONT_DIAGONALS)
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = calib.rect_to_image(ends.reshape(-1, 3))[0].reshape(*ends.shape[:-1], 2)
            # Not finite, or a box at 1e25 m (a broken scan can make one) that would project to a dot at the horizon.
            sane = (np.isfinite(rect).all(axis=(1, 2)) & (np.abs(rect[..., 2]) < 1e3).all(axis=1)
                    & (np.abs(np.where(shown[..., None, None], uv, 0.0)) < 1e5).all(axis=(1, 2, 3)))
        drawable = sane & shown.any(axis=1)
        pixels = np.rint(np.where(shown[..., None, None], uv, 0.0)[drawable]).astype(np.int32)  # (K, 14, 2, 2)
        _draw_segments(canvas, pixels[shown[drawable]], colour, "line" if with_score else "dashed")
        if with_score and scores is not None:
            # Each score above the top-left end of its box's drawn segments (else higher up, or under the box,
            # clear of the scores before it and the key), moved into the picture when that end is off it (a box
            # cut by the image's edge or by the near plane).
            mask = shown[drawable][..., None, None]
            top_left = np.where(mask, pixels, np.iinfo(np.int32).max).min(axis=(1, 2))
            bottom = np.where(mask, pixels, np.iinfo(np.int32).min).max(axis=(1, 2))[:, 1]
            height, width = canvas.shape[:2]
            for (left, top), low, score in zip(top_left, bottom, np.asarray(scores)[drawable], strict=True):
                text = f"{score:.2f}"
                (text_w, text_h), _ = cv2.getTextSize(text, FONT, 0.5, 1)
                step = text_h + 8
                candidates = [(left, top - 4), (left, top - 4 - step), (left, top - 4 - 2 * step),
                              (left, low + text_h + 6), (left + text_w + 8, top - 4)]
                at = _free_spot(candidates, (text_w, text_h), (width, height), taken)
                # On a dark box: thin orange text alone is lost on a bright or orange car.
                cv2.rectangle(canvas, (at[0] - 2, at[1] - text_h - 3), (at[0] + text_w + 2, at[1] + 3), (0, 0, 0), -1)
                cv2.putText(canvas, text, at, FONT, 0.5, colour, 1, cv2.LINE_AA)
    if legend:
        draw_key(canvas, rows, corner="top-right")
    return canvas


def camera_scale_in_stack(image_hw: tuple[int, int], bev: np.ndarray) -> float:
    """How much :func:`stack_views` scales a camera picture of ``image_hw`` to sit above ``bev``: to the BEV's
    width, at most to its height (an image taller than wide)."""
    return min(bev.shape[1] / image_hw[1], bev.shape[0] / image_hw[0])


def stack_views(camera: np.ndarray, bev: np.ndarray) -> np.ndarray:
    """One frame of a video: the camera picture above the BEV picture, scaled by
    :func:`camera_scale_in_stack` (not at all when drawn at that scale already), centred on black."""
    height = max(1, round(camera.shape[0] * camera_scale_in_stack(camera.shape[:2], bev)))
    return np.vstack([fit_into(camera, (bev.shape[1], height)), bev])


def draw_label(picture: np.ndarray, text: str) -> np.ndarray:
    """``text`` in white on a black box in the picture's top-left corner (in place; readable on any colour,
    a bright sky included); returns the picture."""
    (text_w, text_h), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.6, 1)
    cv2.rectangle(picture, (0, 0), (text_w + 16, text_h + 14), (0, 0, 0), thickness=-1)
    cv2.putText(picture, text, (8, text_h + 6), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
    return picture


# The colour map's darkest blues are left out, so that the farthest depth stays apart from black (no depth).
FARTHEST_COLOUR_INDEX = 30


def render_depth(depth: np.ndarray, max_depth: float = 80.0) -> np.ndarray:
    """BGR uint8 colour map of a depth map (near = warm, far = blue at ``max_depth`` and beyond, black = no
    depth)."""
    scaled = np.clip(depth / max_depth, 0, 1)
    index = FARTHEST_COLOUR_INDEX + (255 - FARTHEST_COLOUR_INDEX) * (1 - scaled)
    colour = cv2.applyColorMap(index.astype(np.uint8), cv2.COLORMAP_TURBO)
    colour[depth <= 0] = 0
    return colour


def draw_colour_scale(picture: np.ndarray, colours: np.ndarray, low: float, high: float, unit: str,
                      length: int = 200) -> tuple[int, int, int, int]:
    """A colour bar in the picture's top-right corner (in place): ``colours`` (N × 3 BGR, ``low`` to ``high``
    from left to right) with its two ends labelled, on a black box. Returns the bar's own pixels as (left,
    top, right, bottom), so a test can read its colours back."""
    pad, bar_h = 6, 10
    low_text, high_text = f"{low:g}", f"{high:g} {unit}"
    (low_w, text_h), _ = cv2.getTextSize(low_text, FONT, KEY_SCALE, 1)
    high_w = cv2.getTextSize(high_text, FONT, KEY_SCALE, 1)[0][0]
    length = max(min(length, picture.shape[1] - low_w - high_w - 6 * pad), 8)
    box_w = low_w + length + high_w + 4 * pad
    left = max(picture.shape[1] - box_w, 0)
    cv2.rectangle(picture, (left, 0), (left + box_w, bar_h + 2 * pad), (0, 0, 0), thickness=-1)
    bar_left, bar_top = left + low_w + 2 * pad, pad
    index = np.linspace(0, len(colours) - 1, length).round().astype(int)
    picture[bar_top:bar_top + bar_h, bar_left:bar_left + length] = colours[index][None]
    baseline = bar_top + (bar_h + text_h) // 2
    cv2.putText(picture, low_text, (left + pad, baseline), FONT, KEY_SCALE, (255, 255, 255), 1, cv2.LINE_AA)
    cv2.putText(picture, high_text, (bar_left + length + pad, baseline), FONT, KEY_SCALE, (255, 255, 255), 1,
                cv2.LINE_AA)
    return bar_left, bar_top, bar_left + length, bar_top + bar_h


def depth_colours(max_depth: float = 80.0, n: int = 256) -> np.ndarray:
    """(n, 3) BGR: :func:`render_depth`'s colours from 0 m to ``max_depth``, for its colour bar."""
    return render_depth(np.linspace(1e-3, max_depth, n)[None], max_depth)[0]


def error_colours(n: int = 256) -> np.ndarray:
    """(n, 3) BGR: the error map's colours from no error to the most it shows."""
    return cv2.applyColorMap(np.linspace(0, 255, n).astype(np.uint8)[None], cv2.COLORMAP_INFERNO)[0]


# The error map's pixels without ground truth: a mid grey, which the inferno colours (black, purple, orange,
# yellow) never give, where black is no error.
NO_TRUTH_BGR = (128, 128, 128)


def render_depth_panel(image: np.ndarray, prediction: np.ndarray, ground_truth: np.ndarray,
                       max_depth: float = 80.0, max_error: float = 5.0, title: str | None = None) -> np.ndarray:
    """BGR uint8 picture of one depth-completion frame, stacked top to bottom: the camera crop (RGB),
    the predicted depth, the ground truth (black: none) and the absolute error where there is ground
    truth (0 m dark to ``max_error`` bright; :data:`NO_TRUTH_BGR` grey where there is none), all at the ground
    truth's resolution, each labelled, each map with its colour bar in the top-right corner. title: what the
    frame is (its id, the model), before the camera row's label."""
    height, width = ground_truth.shape
    camera = cv2.cvtColor(cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA), cv2.COLOR_RGB2BGR)
    known = ground_truth > 0
    error = np.where(known, np.abs(prediction - ground_truth), 0.0)
    error_map = cv2.applyColorMap((255 * np.clip(error / max_error, 0, 1)).astype(np.uint8), cv2.COLORMAP_INFERNO)
    error_map[~known] = NO_TRUTH_BGR  # apart from the black of no error
    depth_scale = (depth_colours(max_depth), 0.0, max_depth, "m")
    rows = [(camera, f"{title}: camera" if title else "camera", None),
            (render_depth(prediction, max_depth), f"predicted depth (0-{max_depth:.0f} m)", depth_scale),
            (render_depth(ground_truth, max_depth), f"ground truth (0-{max_depth:.0f} m, black: none)", depth_scale),
            (error_map, f"absolute error where ground truth exists (0-{max_error:.0f} m, grey: none)",
             (error_colours(), 0.0, max_error, "m")),]
    for row, _, scale in rows:
        if scale is not None:
            draw_colour_scale(row, *scale)
    return np.vstack([draw_label(row, label) for row, label, _ in rows])


def write_png(path: str | Path, picture: np.ndarray) -> None:
    """Write a picture as PNG; an OSError naming the file when it cannot be written.

    cv2.imwrite answers False (or raises cv2.error) where open() would raise: a directory in the way,
    no permission, a full disk. Raising OSError lets the commands report it as any other unwritable output.
    """
    try:
        written = cv2.imwrite(str(path), picture)
    except cv2.error as exc:
        raise OSError(errno.EIO, f"could not write the PNG ({exc.err})", str(path)) from exc
    if not written:
        raise OSError(errno.EIO, "could not write the PNG (a directory in the way, no permission or a full disk?)",
                      str(path))


VIDEO_FPS = 10.0  # a video's default frame rate: KITTI's LiDAR turns at 10 Hz, one frame a turn


class VideoError(OSError):
    """A video that cannot be written (reported as ``--video``, not as the output folder)."""


def fit_into(picture: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``picture`` scaled to fit a (width, height) frame, centred on black: the frames of a run whose images
    differ in size (KITTI's do) keep the first frame's size, as a video must."""
    width, height = size
    if (picture.shape[1], picture.shape[0]) == (width, height):
        return picture
    scale = min(width / picture.shape[1], height / picture.shape[0])
    new_w, new_h = max(1, round(picture.shape[1] * scale)), max(1, round(picture.shape[0] * scale))
    frame = np.zeros((height, width, 3), np.uint8)
    top, left = (height - new_h) // 2, (width - new_w) // 2
    frame[top:top + new_h, left:left + new_w] = cv2.resize(picture, (new_w, new_h), interpolation=cv2.INTER_AREA)
    return frame


class FrameVideo:
    """Pictures of consecutive frames as one MP4 (MPEG-4 Part 2, ``mp4v``: VLC, ffmpeg and most players, not web
    browsers), written to a hidden file beside ``path`` and renamed into place by :meth:`close`, so a run that
    stops half-way leaves no cut-off video under the name asked for.

    The first picture sets the video's size; a later one of another size (an image of another size above the
    BEV) is fitted into it. ``written`` says whether :meth:`close` put the video in place.
    """

    def __init__(self, path: str | Path, fps: float = VIDEO_FPS) -> None:
        self.path, self.fps = Path(path), fps
        # The process id keeps two runs writing the same name from sharing one partial file.
        self._partial = self.path.with_name(f".{self.path.stem}.{os.getpid()}.partial.mp4")
        self._writer: cv2.VideoWriter | None = None
        self._size = (0, 0)
        self.frames = 0
        self.written = False

    def probe(self) -> None:
        """Create and remove the hidden file beside the name, before any work: a folder the video cannot be
        written into (not writable, immutable, a file in the way) is a :class:`VideoError` at once."""
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._partial.open("xb").close()
            self._partial.unlink()
        except OSError as exc:
            raise VideoError(exc.errno, f"cannot create files in {self.path.parent} ({exc.strerror or exc})",
                             str(self.path)) from exc

    def add(self, picture: np.ndarray) -> None:
        """Append one BGR picture; a :class:`VideoError` naming the file when the video cannot be written."""
        if self._writer is None:
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise VideoError(exc.errno, exc.strerror, str(self.path)) from exc
            self._size = (picture.shape[1] + picture.shape[1] % 2, picture.shape[0] + picture.shape[0] % 2)
            self._writer = cv2.VideoWriter(str(self._partial), cv2.VideoWriter.fourcc(*"mp4v"), self.fps, self._size)
            if not self._writer.isOpened():
                raise VideoError(errno.EIO, f"OpenCV could not open an MP4 writer for {self._size[0]}×{self._size[1]} "
                                 "frames", str(self.path))
        # Even sides: MPEG-4's 4:2:0 colour has one sample per 2×2 pixels, and OpenCV's writer drops an odd last
        # row or column (the BEV picture with its key is 877 rows); one black row or column is added instead.
        picture = np.pad(picture, ((0, picture.shape[0] % 2), (0, picture.shape[1] % 2), (0, 0)))
        self._writer.write(fit_into(picture, self._size))
        self.frames += 1

    def close(self) -> bool:
        """Finish the video and move it into place; False when no picture was added (nothing written)."""
        if self._writer is None:
            return False
        self._writer.release()
        self._writer = None
        try:
            self._partial.replace(self.path)
        except OSError as exc:
            raise VideoError(exc.errno, exc.strerror, str(self.path)) from exc
        self.written = True
        return True

    def discard(self) -> None:
        """Drop a video whose run failed: the partial file goes, the name asked for is left as it was."""
        if self._writer is not None:
            self._writer.release()
            self._writer = None
        self._partial.unlink(missing_ok=True)
