"""Pictures people look at (OpenCV only): the BEV view of points and boxes, the camera image with the boxes
as 3D wireframes, depth maps, and a frame's views stacked into the frames of an MP4 video (FrameVideo)."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import cv2
import numpy as np

from pipeline.boxes import BOX_EDGES, bev_corners, box_corners_3d, segments_in_front
from pipeline.calib import Calibration
from pipeline.preprocess import scale_calibration
from pipeline.presets import BevGrid

PREDICTION_BGR = (60, 220, 60)
GROUND_TRUTH_BGR = (60, 60, 230)
# The two diagonals of a box's front face (corners 0 and 3 are the front edge), drawn to show its heading.
FRONT_DIAGONALS = ((0, 7), (3, 4))


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


def draw_key(picture: np.ndarray, rows: list[tuple[str, tuple[int, int, int] | None]],
             corner: str = "top-left") -> tuple[int, int, int, int]:
    """A key in a corner of the picture (in place): one row per (text, colour), a short line of the colour
    before the text (no line: a title row), white text on a black box so it reads on any background.
    Returns the box as (left, top, right, bottom)."""
    line_h, swatch, pad = 18, 22, 6
    room = picture.shape[1] - 2 * pad - swatch - 6
    rows = [(fit_text(text, room), colour) for text, colour in rows]
    width = max(cv2.getTextSize(text, FONT, KEY_SCALE, 1)[0][0] + (swatch + 6 if colour else 0)
                for text, colour in rows) + 2 * pad
    height = line_h * len(rows) + pad
    left = 0 if corner == "top-left" else max(picture.shape[1] - width, 0)
    cv2.rectangle(picture, (left, 0), (left + width, height), (0, 0, 0), thickness=-1)
    for i, (text, colour) in enumerate(rows):
        baseline = pad + line_h * i + 11
        x = left + pad
        if colour is not None:
            cv2.line(picture, (x, baseline - 4), (x + swatch, baseline - 4), colour, 2, cv2.LINE_AA)
            x += swatch + 6
        cv2.putText(picture, text, (x, baseline), FONT, KEY_SCALE, (255, 255, 255), 1, cv2.LINE_AA)
    return left, 0, left + width, height


def _ring_label_at(radius_px: int, origin: tuple[int, int], size: tuple[int, int], text: str) -> tuple[int, int]:
    """Where a range ring's label goes: just right of where the ring leaves the picture (its bottom edge, or
    its right edge for a ring wider than the picture), away from the lane ahead where the cars are."""
    width, height = size
    (text_w, text_h), _ = cv2.getTextSize(text, FONT, 0.4, 1)
    if origin[0] + radius_px + text_w + 4 < width:
        return origin[0] + radius_px + 3, min(origin[1], height) - 4
    across = width - 1 - origin[0]
    row = origin[1] - int(np.sqrt(max(radius_px**2 - across**2, 0)))
    return width - text_w - 3, row + text_h + 5


def _put_score(canvas: np.ndarray, text: str, corners: np.ndarray, colour: tuple[int, int, int]) -> None:
    """A BEV box's score just above and right of its front-left corner (``corners``: its four (column, row)),
    kept whole in the picture: under the box when the front reaches past the far edge, moved in from a side."""
    (text_w, text_h), _ = cv2.getTextSize(text, FONT, 0.45, 1)
    height, width = canvas.shape[:2]
    column, row = corners[0, 0] + 4, corners[0, 1] - 4
    if row - text_h < 0:  # above the top edge: under the box's lowest point, clear of its lines
        row = corners[:, 1].max() + text_h + 6
    at = (int(np.clip(column, 0, max(width - text_w - 1, 0))),
          int(np.clip(row, text_h + 1, max(height - 3, text_h + 1))))
    cv2.putText(canvas, text, at, FONT, 0.45, colour, 1, cv2.LINE_AA)


def render_bev(
    points: np.ndarray,
    grid: BevGrid,
    boxes: np.ndarray | None = None,
    scores: np.ndarray | None = None,
    gt_boxes: np.ndarray | None = None,
    metres_per_pixel: float = 0.1,
    title: str | None = None,
    legend: bool = False,
) -> np.ndarray:
    """BGR uint8 picture of the BEV grid, forward (x) up, left (y) left, the sensor a white triangle at the
    bottom centre: points (brighter where denser), range rings every 10 m labelled where they leave the
    picture, ground truth in red, predictions in green with their scores.

    legend: a key in the top-left corner (``title`` first, then what each colour is and which way is ahead)
    for pictures people look at; off for a picture compared pixel by pixel."""
    width = round((grid.y_max - grid.y_min) / metres_per_pixel)
    height = round((grid.x_max - grid.x_min) / metres_per_pixel)
    density = np.zeros(height * width, np.float32)
    pix = np.floor(_to_pixels(points[:, :2], grid, metres_per_pixel)).astype(np.int64)
    ok = (pix[:, 0] >= 0) & (pix[:, 0] < width) & (pix[:, 1] >= 0) & (pix[:, 1] < height)
    density += np.bincount(pix[ok, 1] * width + pix[ok, 0], minlength=height * width)
    grey = (np.clip(np.log1p(density) / np.log(20.0), 0, 1) * 255).astype(np.uint8).reshape(height, width)
    canvas = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    # Range rings every 10 m help reading distances; their labels sit off the lane ahead, where boxes are.
    column, row = _to_pixels(np.array([0.0, 0.0]), grid, metres_per_pixel)
    origin = (int(column), int(row))
    farthest = float(np.hypot(max(grid.x_max, -grid.x_min), max(grid.y_max, -grid.y_min)))
    for r in range(RING_STEP_M, int(farthest) + 1, RING_STEP_M):
        radius = int(r / metres_per_pixel)
        cv2.circle(canvas, origin, radius, RING_BGR, 1, cv2.LINE_AA)
        at = _ring_label_at(radius, origin, (width, height), f"{r} m")
        if 0 <= at[1] - 10 and at[1] < height:
            cv2.putText(canvas, f"{r} m", at, FONT, 0.4, RING_LABEL_BGR, 1, cv2.LINE_AA)
    # The sensor: a triangle pointing ahead, so the picture says which way is forward without the key.
    tip = (origin[0], min(origin[1], height) - 14)
    cv2.fillPoly(canvas, [np.array([tip, (tip[0] - 6, tip[1] + 12), (tip[0] + 6, tip[1] + 12)], np.int32)],
                 (255, 255, 255), cv2.LINE_AA)
    for drawn, colour, with_score in ((gt_boxes, GROUND_TRUTH_BGR, False), (boxes, PREDICTION_BGR, True)):
        if drawn is None or len(drawn) == 0:
            continue
        corners = _to_pixels(bev_corners(drawn), grid, metres_per_pixel)
        # A box far off the picture (a broken scan can give one) has no pixel position OpenCV accepts.
        drawable = np.isfinite(corners).all(axis=(1, 2)) & (np.abs(corners) < 1e5).all(axis=(1, 2))
        corners = np.rint(corners[drawable]).astype(np.int32)
        if with_score and scores is not None:
            scores = scores[drawable]
        cv2.polylines(canvas, list(corners), True, colour, 2, cv2.LINE_AA)
        front = np.rint(corners[:, [0, 3]].mean(axis=1)).astype(np.int32)  # mid front edge: heading
        centre = np.rint(corners.mean(axis=1)).astype(np.int32)
        for i in range(len(corners)):  # one line and label per box: tens of boxes at most
            cv2.line(canvas, tuple(centre[i]), tuple(front[i]), colour, 2, cv2.LINE_AA)
            if with_score and scores is not None:
                _put_score(canvas, f"{scores[i]:.2f}", corners[i], colour)
    if legend:
        draw_key(canvas, bev_key_rows(title, boxes is not None, gt_boxes is not None))
    return canvas


def key_rows(title: str | None, predictions: bool, ground_truth: bool) -> list[tuple[str, tuple[int, int, int] | None]]:
    """The rows of a picture's key: its title, then what the colours drawn are."""
    rows: list[tuple[str, tuple[int, int, int] | None]] = [(title, None)] if title else []
    if predictions:
        rows.append(("detection (score)", PREDICTION_BGR))
    if ground_truth:
        rows.append(("ground truth", GROUND_TRUTH_BGR))
    return rows


def bev_key_rows(title: str | None, predictions: bool, ground_truth: bool) -> list[tuple[str, tuple[int, int, int] | None]]:
    """The rows of a BEV picture's key: :func:`key_rows` and how to read the view."""
    return [*key_rows(title, predictions, ground_truth),
            (f"bird's-eye view: forward up, rings every {RING_STEP_M} m", None)]


def render_camera(
    image: np.ndarray,
    calib: Calibration,
    boxes: np.ndarray | None = None,
    scores: np.ndarray | None = None,
    gt_boxes: np.ndarray | None = None,
    scale: float = 1.0,
    title: str | None = None,
    legend: bool = False,
) -> np.ndarray:
    """BGR uint8 picture of the camera image (RGB in) with the 3D boxes drawn as wireframes, the front face
    crossed: ground truth in red, predictions in green with their scores (kept inside the picture). An edge
    reaching behind the camera (a car beside it) is cut at :data:`pipeline.boxes.NEAR_PLANE_M` in front of it; a box wholly
    behind the camera, with a corner more than 1 km in front of or behind it, not finite or projecting more than 1e5 pixels away is left
    out (the BEV picture shows every box).

    scale: the image is resized by it first and the boxes drawn on the result, so lines and scores keep
    their size in pixels (a video's frame: :func:`camera_scale_in_stack`). legend: a key in the top-right
    corner (``title`` first, then what each colour is), clear of a video's caption at the top left."""
    if scale != 1.0:
        size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        calib = scale_calibration(calib, scale)
    canvas = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2BGR)
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
        cv2.polylines(canvas, list(pixels[shown[drawable]]), False, colour, 2, cv2.LINE_AA)
        if with_score and scores is not None:
            # Each score above the top-left end of its box's drawn segments, moved into the picture when that
            # end is off it (a box cut by the image's edge or by the near plane).
            top_left = np.where(shown[drawable][..., None, None], pixels, np.iinfo(np.int32).max).min(axis=(1, 2))
            height, width = canvas.shape[:2]
            for (left, top), score in zip(top_left, np.asarray(scores)[drawable], strict=True):
                at = (int(np.clip(left, 0, max(width - 40, 0))), int(np.clip(top - 4, 14, max(height - 2, 14))))
                text = f"{score:.2f}"
                (text_w, text_h), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
                # On a dark box: thin green text alone is lost on foliage and on a green car.
                cv2.rectangle(canvas, (at[0] - 2, at[1] - text_h - 3), (at[0] + text_w + 2, at[1] + 3), (0, 0, 0), -1)
                cv2.putText(canvas, text, at, cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1, cv2.LINE_AA)
    if legend:
        draw_key(canvas, key_rows(title, boxes is not None, gt_boxes is not None), corner="top-right")
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


def render_depth_panel(image: np.ndarray, prediction: np.ndarray, ground_truth: np.ndarray,
                       max_depth: float = 80.0, max_error: float = 5.0, title: str | None = None) -> np.ndarray:
    """BGR uint8 picture of one depth-completion frame, stacked top to bottom: the camera crop (RGB),
    the predicted depth, the ground truth (black: none) and the absolute error where there is ground
    truth (0 m dark to ``max_error`` bright), all at the ground truth's resolution, each labelled, each map
    with its colour bar in the top-right corner. title: what the frame is (its id, the model), before the
    camera row's label."""
    height, width = ground_truth.shape
    camera = cv2.cvtColor(cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA), cv2.COLOR_RGB2BGR)
    known = ground_truth > 0
    error = np.where(known, np.abs(prediction - ground_truth), 0.0)
    error_map = cv2.applyColorMap((255 * np.clip(error / max_error, 0, 1)).astype(np.uint8), cv2.COLORMAP_INFERNO)
    error_map[~known] = 0
    depth_scale = (depth_colours(max_depth), 0.0, max_depth, "m")
    rows = [(camera, f"{title}: camera" if title else "camera", None),
            (render_depth(prediction, max_depth), f"predicted depth (0-{max_depth:.0f} m)", depth_scale),
            (render_depth(ground_truth, max_depth), f"ground truth (0-{max_depth:.0f} m, black: none)", depth_scale),
            (error_map, f"absolute error where ground truth exists (0-{max_error:.0f} m)",
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
            self._size = (picture.shape[1], picture.shape[0])
            self._writer = cv2.VideoWriter(str(self._partial), cv2.VideoWriter.fourcc(*"mp4v"), self.fps, self._size)
            if not self._writer.isOpened():
                raise VideoError(errno.EIO, f"OpenCV could not open an MP4 writer for {self._size[0]}×{self._size[1]} "
                                 "frames", str(self.path))
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
