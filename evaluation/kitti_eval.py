"""The official KITTI object evaluation (devkit ``evaluate_object.cpp``), re-implemented with arrays.

Protocol, per metric (2D box, BEV, 3D), overlap threshold and difficulty:

1. Clean each frame. Ground truth of the class counts (``ignored_gt = 0``) unless it
   is too occluded, too truncated or too small for the difficulty (box height
   ``<=`` the minimum); then, like the neighbouring class (Van for Car), it is
   ignored (``1``): it may absorb a detection but is neither found nor missed.
   Other classes play no part (``-1``). A detection whose 2D box height is ``<``
   the minimum is ignored (``1``) whatever its class; otherwise it counts (``0``)
   if it is of the class and plays no part (``-1``) if not.
2. First pass, no score threshold: walking the ground truth in file order, each
   takes the highest-scoring unassigned detection that overlaps it by more than
   the threshold; the scores of the true positives (counted ground truth ×
   counted detection) over all frames give, with the number of counted ground
   truth, the 41 recall-sampling score thresholds (``getThresholds``).
3. Second pass, at each score threshold: detections scoring below it are dropped;
   each ground truth takes the unassigned counted detection with the largest
   overlap (ties: the first), else the first ignored detection above the
   threshold. Counted ground truth left alone is a false negative; a counted
   pair is a true positive; pairs involving an ignored side are discarded.
   Unassigned counted detections are false positives, except, in the 2D-box
   metric only, those covered by more than the threshold (intersection over
   the detection's own area) by a DontCare region (BEV and 3D do not use the
   DontCare regions: they are 2D image areas without a 3D extent).
4. Precision at each threshold, made monotone by the maximum over the later
   points; 11-point AP = mean of points 0, 4, ..., 40, 40-point AP = mean of
   points 1 ... 40.

Every frame is matched once per pass for all (metric, threshold, difficulty,
score threshold) rows at the same time: the per-ground-truth loop of the
devkit runs over (rows × detections) arrays.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from itertools import pairwise
from statistics import NormalDist
from typing import Literal

import numpy as np
from tqdm import tqdm

from evaluation.labels import LabelArrays
from evaluation.overlaps import bev_overlap, box3d_overlap, image_overlap

log = logging.getLogger(__name__)

DIFFICULTIES = ("easy", "moderate", "hard")
MIN_HEIGHT = np.array([40.0, 25.0, 25.0])  # minimum 2D box height in pixels
MAX_OCCLUSION = np.array([0, 1, 2])
MAX_TRUNCATION = np.array([0.15, 0.30, 0.50])
N_SAMPLE_PTS = 41
METRICS = ("bbox", "bev", "3d")
DEFAULT_IOU_THRESHOLDS = (0.7, 0.5)
# A neighbouring class is ignored rather than counted as a false positive when detected.
NEIGHBOUR_CLASSES = {"car": "van", "pedestrian": "person_sitting"}
# The devkit's "no detection yet" score: a detection scoring at or below it can never match.
NO_DETECTION = -10000000.0

Points = Literal["R40", "R11"]


@dataclass(frozen=True)
class PrCurve:
    """Precision-recall statistics of one (metric, overlap threshold, difficulty).

    thresholds: (K,) score thresholds, K ≤ 41, from the first pass.
    tp, fp, fn: (K,) int64 totals over all frames at each threshold.
    precision: (41,) float64, precision at the K thresholds made monotone by the
    maximum over later points, 0 beyond K (the devkit's stats-file row).
    """

    metric: str
    iou_threshold: float
    difficulty: str
    n_ground_truth: int
    thresholds: np.ndarray
    tp: np.ndarray
    fp: np.ndarray
    fn: np.ndarray
    precision: np.ndarray

    @property
    def recall(self) -> np.ndarray:
        """(K,) recall ``tp / (tp + fn)`` at each score threshold."""
        total = self.tp + self.fn
        out = np.zeros(total.shape)
        np.divide(self.tp, total, out=out, where=total > 0)
        return out

    @property
    def ap_r40(self) -> float:
        """40-point interpolated AP in percent (recall points 1/40 ... 1)."""
        return float(self.precision[1:].sum() / 40.0 * 100.0)

    @property
    def ap_r11(self) -> float:
        """11-point interpolated AP in percent (recall points 0, 0.1, ..., 1 = every 4th of 41)."""
        return float(self.precision[0::4].sum() / 11.0 * 100.0)

    def ap(self, points: Points) -> float:
        """AP in percent with ``R40`` or ``R11`` interpolation."""
        if points == "R40":
            return self.ap_r40
        if points == "R11":
            return self.ap_r11
        raise ValueError(f"points must be 'R40' or 'R11', got {points!r}")


@dataclass(frozen=True)
class KittiEvalResult:
    """All curves of one evaluation run."""

    class_name: str
    n_frames: int
    metrics: tuple[str, ...]
    iou_thresholds: tuple[float, ...]
    curves: tuple[PrCurve, ...]

    def curve(self, metric: str, iou_threshold: float, difficulty: str) -> PrCurve:
        """The curve for one metric, overlap threshold and difficulty name."""
        for c in self.curves:
            if c.metric == metric and c.iou_threshold == iou_threshold and c.difficulty == difficulty:
                return c
        raise KeyError(f"no curve for {metric} @ {iou_threshold} {difficulty}; metrics: {self.metrics}")

    def ap(self, metric: str, iou_threshold: float, difficulty: str, points: Points = "R40") -> float:
        """AP in percent."""
        return self.curve(metric, iou_threshold, difficulty).ap(points)

    def ap_table(self) -> dict[str, dict[str, dict[str, list[float]]]]:
        """``{metric: {"0.7": {"R40": [easy, moderate, hard], "R11": [...]}}}`` in percent."""
        return {
            metric: {
                f"{iou}": {
                    points: [self.ap(metric, iou, d, points) for d in DIFFICULTIES] for points in ("R40", "R11")
                }
                for iou in self.iou_thresholds
            }
            for metric in self.metrics
        }


def recall_thresholds(tp_scores: np.ndarray, n_ground_truth: int) -> np.ndarray:
    """Score thresholds that sample recall at ``N_SAMPLE_PTS`` evenly spaced points (``getThresholds``).

    Scores are walked from best to worst; a score is kept when its recall is at
    least as close to the next sampling point as the following score's recall,
    and the last score is always kept. The sampling point advances by 1/40 in
    floating point, as the devkit does, so ties at the boundaries break the same way.
    """
    scores = np.sort(np.asarray(tp_scores, np.float64))[::-1]
    kept: list[float] = []
    current_recall = 0.0
    last = scores.size - 1
    for i, score in enumerate(scores.tolist()):
        left_recall = (i + 1) / n_ground_truth
        right_recall = (i + 2) / n_ground_truth if i < last else left_recall
        if i < last and (right_recall - current_recall) < (current_recall - left_recall):
            continue
        kept.append(score)
        current_recall += 1.0 / (N_SAMPLE_PTS - 1.0)
    if len(kept) > N_SAMPLE_PTS:
        # Recall never exceeds 1, so at most 41 points are reachable; more would mean corrupt counts.
        raise RuntimeError(f"{len(kept)} recall thresholds for {n_ground_truth} ground truth boxes")
    return np.asarray(kept, dtype=np.float64)


def available_metrics(detections: Sequence[LabelArrays], class_name: str = "Car") -> tuple[str, ...]:
    """Metrics the detections support, by the devkit's rule.

    A metric is evaluated when at least one detection of the class carries its
    fields: 2D box with ``left >= 0``; BEV with ``x, z != -1000`` and ``w, l > 0``;
    3D additionally ``y != -1000`` and ``h > 0``.
    """
    name = class_name.lower()
    found = {"bbox": False, "bev": False, "3d": False}
    for det in detections:
        mine = det.types == name
        if not mine.any():
            continue
        bbox, (h, w, l), loc = det.bbox[mine], det.dimensions[mine].T, det.location[mine]
        found["bbox"] |= bool((bbox[:, 0] >= 0).any())
        ground = (loc[:, 0] != -1000) & (loc[:, 2] != -1000) & (w > 0) & (l > 0)
        found["bev"] |= bool(ground.any())
        found["3d"] |= bool((ground & (loc[:, 1] != -1000) & (h > 0)).any())
        if all(found.values()):
            break
    return tuple(m for m in METRICS if found[m])


def _default_metrics(detections: Sequence[LabelArrays], class_name: str) -> tuple[str, ...]:
    """:func:`available_metrics`, or every metric when no detection is of the class at all.

    The devkit reads which metrics to evaluate off the detections; a detector that found
    nothing leaves it nothing to read, yet it scores 0 in each (every counted box is missed).
    """
    found = available_metrics(detections, class_name)
    if not found and not any((det.types == class_name.lower()).any() for det in detections):
        return METRICS
    return found


@dataclass(frozen=True)
class _Frame:
    """One frame reduced to what matching needs.

    scores: (D,) detection scores. ignored_det: (3, D) int8 per difficulty (-1, 0, 1).
    ignored_gt: (3, G) int8 per difficulty (0 counted, 1 ignored). n_counted_gt: (3,).
    overlaps: (M, D, G) per evaluated metric. dontcare: (D,) the largest
    intersection-over-detection-area with a DontCare region (0 without one).
    Only detections and ground truth that can take part are kept, order preserved.
    """

    scores: np.ndarray
    ignored_det: np.ndarray
    ignored_gt: np.ndarray
    n_counted_gt: np.ndarray
    overlaps: np.ndarray
    dontcare: np.ndarray


def too_hard_for(occluded: np.ndarray, truncated: np.ndarray, box_height: np.ndarray) -> np.ndarray:
    """(3, N) bool: a ground-truth box is ignored at each difficulty (easy, moderate, hard), as ``cleanData``
    decides it; a box exactly at a minimum height is too small (``height <= MIN_HEIGHT``)."""
    occluded, truncated, box_height = (np.asarray(a, np.float64).reshape(-1) for a in (occluded, truncated, box_height))
    return ((occluded[None, :] > MAX_OCCLUSION[:, None])
            | (truncated[None, :] > MAX_TRUNCATION[:, None])
            | (box_height[None, :] <= MIN_HEIGHT[:, None]))


def _prepare_frame(gt: LabelArrays, det: LabelArrays, class_name: str, metrics: Sequence[str],
                   ignore_small_detections: bool = True,
                   distance_range: tuple[float, float] | None = None) -> _Frame:
    """Clean one frame (``cleanData``) and compute its overlap matrices once."""
    name = class_name.lower()
    neighbour = NEIGHBOUR_CLASSES.get(name)
    gt_mine = gt.types == name
    keep_gt = gt_mine | (gt.types == neighbour) if neighbour else gt_mine
    gt_kept = gt.select(keep_gt)
    mine = gt_mine[keep_gt]
    too_hard = too_hard_for(gt_kept.occluded, gt_kept.truncated, gt_kept.box_height)
    if distance_range is not None:  # outside the band: ignored, like a too-hard box
        too_hard |= ~_within(gt_kept.location[:, 2], distance_range)[None, :]
    ignored_gt = np.where(mine[None, :] & ~too_hard, 0, 1).astype(np.int8)

    # The devkit truncates the detection height to an integer before comparing with an
    # integer minimum; for integer minima that is the same as comparing the real height.
    det_height = np.abs(det.bbox[:, 3] - det.bbox[:, 1])
    too_small = (det_height[None, :] < MIN_HEIGHT[:, None]) & ignore_small_detections
    if distance_range is not None:
        too_small |= ~_within(det.location[:, 2], distance_range)[None, :]
    ignored_det = np.where(too_small, 1, np.where(det.types == name, 0, -1)[None, :]).astype(np.int8)
    takes_part = (ignored_det != -1).any(axis=0)
    det_kept = det.select(takes_part)
    ignored_det = ignored_det[:, takes_part]

    overlaps = np.zeros((len(metrics), len(det_kept), len(gt_kept)))
    if len(det_kept) and len(gt_kept):
        for m, metric in enumerate(metrics):
            if metric == "bbox":
                overlaps[m] = image_overlap(det_kept.bbox, gt_kept.bbox)
            elif metric == "bev":
                overlaps[m] = bev_overlap(det_kept, gt_kept)
            else:
                overlaps[m] = box3d_overlap(det_kept, gt_kept)
    dontcare = np.zeros(len(det_kept))
    dontcare_boxes = gt.bbox[gt.types == "dontcare"]
    if "bbox" in metrics and len(det_kept) and len(dontcare_boxes):
        dontcare = image_overlap(det_kept.bbox, dontcare_boxes, criterion="detection").max(axis=1)
    return _Frame(
        scores=det_kept.score, ignored_det=ignored_det, ignored_gt=ignored_gt,
        n_counted_gt=(ignored_gt == 0).sum(axis=1), overlaps=overlaps, dontcare=dontcare,
    )


def _within(depth: np.ndarray, distance_range: tuple[float, float]) -> np.ndarray:
    """(N,) whether each box centre's camera depth z lies in [low, high)."""
    low, high = distance_range
    return (depth >= low) & (depth < high)


@dataclass(frozen=True)
class _Rows:
    """A batch of evaluation rows matched together: one (metric, overlap, difficulty[, score threshold]) each.

    metric: (B,) index into the frame's overlap stack. difficulty: (B,) 0..2.
    min_overlap: (B,) overlap that must be exceeded. score_threshold: (B,) minimum
    score (``-inf`` in the first pass). is_bbox: (B,) whether DontCare regions apply.
    """

    metric: np.ndarray
    difficulty: np.ndarray
    min_overlap: np.ndarray
    score_threshold: np.ndarray
    is_bbox: np.ndarray


@dataclass
class _Assignment:
    """Matching outcome of one frame for a batch of rows: (B,) counts and (B, D) masks."""

    tp: np.ndarray
    fn: np.ndarray
    assigned: np.ndarray
    tp_detections: np.ndarray


def _assign(frame: _Frame, rows: _Rows, by_score: bool) -> _Assignment:
    """Greedy ground-truth-order matching of one frame for all rows (``computeStatistics``).

    by_score: first pass (each ground truth takes the best-scoring candidate);
    otherwise the second pass (the largest-overlap counted candidate, else the
    first ignored candidate).
    """
    n_rows, n_det = rows.metric.size, frame.scores.size
    ignored_det = frame.ignored_det[rows.difficulty]  # (B, D)
    ignored_gt = frame.ignored_gt[rows.difficulty]  # (B, G)
    eligible = (ignored_det != -1) & (frame.scores[None, :] >= rows.score_threshold[:, None])
    if by_score:
        eligible &= frame.scores[None, :] > NO_DETECTION
    counted_det = ignored_det == 0
    assigned = np.zeros((n_rows, n_det), dtype=bool)
    tp_detections = np.zeros((n_rows, n_det), dtype=bool)
    tp = np.zeros(n_rows, dtype=np.int64)
    fn = np.zeros(n_rows, dtype=np.int64)
    row_index = np.arange(n_rows)
    for g in range(ignored_gt.shape[1]):
        overlap = frame.overlaps[:, :, g][rows.metric]  # (B, D)
        candidate = eligible & ~assigned & (overlap > rows.min_overlap[:, None])
        has = candidate.any(axis=1)
        if by_score:
            pick = np.where(candidate, frame.scores[None, :], -np.inf).argmax(axis=1)
            pair_counts = counted_det[row_index, pick]
        else:
            counted_candidate = candidate & counted_det
            pair_counts = counted_candidate.any(axis=1)
            best_overlap = np.where(counted_candidate, overlap, -np.inf).argmax(axis=1)
            pick = np.where(pair_counts, best_overlap, candidate.argmax(axis=1))
        gt_counts = ignored_gt[:, g] == 0
        fn += ~has & gt_counts
        is_tp = has & gt_counts & pair_counts
        tp += is_tp
        assigned[row_index[has], pick[has]] = True
        tp_detections[row_index[is_tp], pick[is_tp]] = True
    return _Assignment(tp=tp, fn=fn, assigned=assigned, tp_detections=tp_detections)


def _false_positives(frame: _Frame, rows: _Rows, assigned: np.ndarray) -> np.ndarray:
    """(B,) counted, above-threshold, unassigned detections not covered by a DontCare region."""
    counted = (frame.ignored_det[rows.difficulty] == 0) & (
        frame.scores[None, :] >= rows.score_threshold[:, None]
    )
    under_dontcare = rows.is_bbox[:, None] & (frame.dontcare[None, :] > rows.min_overlap[:, None])
    return (counted & ~assigned & ~under_dontcare).sum(axis=1)


def evaluate(
    ground_truth: Sequence[LabelArrays],
    detections: Sequence[LabelArrays],
    class_name: str = "Car",
    iou_thresholds: Sequence[float] = DEFAULT_IOU_THRESHOLDS,
    metrics: Sequence[str] | None = None,
    progress: bool = False,
    ignore_small_detections: bool = True,
    distance_range: tuple[float, float] | None = None,
) -> KittiEvalResult:
    """Evaluate per-frame detections against per-frame ground truth, KITTI style.

    ground_truth, detections: one entry per frame, same order (an empty
    ``LabelArrays`` for a frame without detections). Detection scores must be set.
    metrics: subset of ``METRICS``; default: those the detections support
    (``available_metrics``), or all of them when no detection is of the class (each
    AP is then 0). Returns every (metric, overlap threshold, difficulty) curve.
    ignore_small_detections: the devkit's rule that a detection whose 2D box is
    lower than a difficulty's minimum height takes no part in it. False counts
    every detection (not the devkit): for a BEV detector whose 2D boxes come from
    estimated heights, its BEV AP then depends on the BEV boxes alone.
    distance_range: (low, high) metres, AP of one distance band (not the devkit,
    which has none): ground truth and detections whose box centre's depth z in
    the camera frame is outside [low, high) are ignored the way the devkit
    ignores a too-hard box and a too-small detection: a car and its detection
    on either side of the band's edge count as neither a hit, a miss nor a
    false positive.
    """
    if len(ground_truth) != len(detections):
        raise ValueError(f"{len(ground_truth)} ground-truth frames but {len(detections)} detection frames")
    _require_scores(detections)
    metrics = tuple(_default_metrics(detections, class_name) if metrics is None else metrics)
    unknown = set(metrics) - set(METRICS)
    if unknown:
        raise ValueError(f"unknown metric(s) {sorted(unknown)}; choose from {METRICS}")
    iou_thresholds = tuple(float(t) for t in iou_thresholds)
    if not metrics:
        log.warning("no %s detection carries a 2D box or a ground-plane box: nothing to evaluate", class_name)

    frames = [
        _prepare_frame(gt, det, class_name, metrics, ignore_small_detections, distance_range)
        for gt, det in tqdm(
            zip(ground_truth, detections), total=len(ground_truth), desc="overlaps", disable=not progress
        )
    ]
    curves = _curves(frames, metrics, iou_thresholds, progress)
    return KittiEvalResult(
        class_name=class_name, n_frames=len(ground_truth), metrics=metrics,
        iou_thresholds=iou_thresholds, curves=tuple(curves),
    )


def _require_scores(detections: Sequence[LabelArrays], where: str = "") -> None:
    """ValueError naming the first frame with a detection without a score (NaN): the protocol ranks by score, and
    unscored ones gave every AP 0 without a word (bootstrap, until session 50)."""
    for i, det in enumerate(detections):
        if np.isnan(det.score).any():
            raise ValueError(f"{where}frame {i}: detections need a score (16th label field)")


def evaluate_by_distance(ground_truth: Sequence[LabelArrays], detections: Sequence[LabelArrays],
                         edges: Sequence[float], **options) -> dict[tuple[float, float], KittiEvalResult]:
    """:func:`evaluate` once per distance band [edges[i], edges[i + 1]); ``options`` go to each call."""
    return {(low, high): evaluate(ground_truth, detections, distance_range=(low, high), **options)
            for low, high in pairwise(edges)}


def _first_pass_rows(metrics: tuple[str, ...], iou_thresholds: tuple[float, ...]) -> _Rows:
    """One row per (metric, overlap threshold, difficulty), in that order, with no score threshold: the
    protocol's first matching pass."""
    configs = [(m, iou, d) for m in range(len(metrics)) for iou in iou_thresholds for d in range(3)]
    return _Rows(np.array([c[0] for c in configs], dtype=np.int64), np.array([c[2] for c in configs], dtype=np.int64),
                 np.array([c[1] for c in configs], dtype=np.float64), np.full(len(configs), -np.inf),
                 np.array([metrics[c[0]] == "bbox" for c in configs], dtype=bool))


def _curves(frames: Sequence[_Frame], metrics: tuple[str, ...], iou_thresholds: tuple[float, ...],
            progress: bool = False) -> list[PrCurve]:
    """Steps 2–4 of the protocol over prepared frames: one curve per (metric, threshold, difficulty)."""
    first = _first_pass_rows(metrics, iou_thresholds)
    n_cfg, cfg_metric, cfg_iou, cfg_diff, cfg_bbox = (first.metric.size, first.metric, first.min_overlap,
                                                      first.difficulty, first.is_bbox)

    # First pass: true-positive scores and counted ground truth per configuration.
    tp_scores: list[list[np.ndarray]] = [[] for _ in range(n_cfg)]
    n_gt = np.zeros(n_cfg, dtype=np.int64)
    for frame in tqdm(frames, desc="thresholds", disable=not progress):
        n_gt += frame.n_counted_gt[cfg_diff]
        if frame.scores.size == 0 or frame.ignored_gt.shape[1] == 0:
            continue
        outcome = _assign(frame, first, by_score=True)
        for c in np.flatnonzero(outcome.tp):
            tp_scores[c].append(frame.scores[outcome.tp_detections[c]])
    thresholds = [
        recall_thresholds(np.concatenate(s) if s else np.zeros(0), int(n)) for s, n in zip(tp_scores, n_gt)
    ]
    padded = np.full((n_cfg, N_SAMPLE_PTS), np.inf)  # +inf: no detection passes, the row is unused
    for c, t in enumerate(thresholds):
        padded[c, : t.size] = t

    # Second pass: every configuration at each of its score thresholds, all rows at once.
    second = _Rows(
        np.repeat(cfg_metric, N_SAMPLE_PTS), np.repeat(cfg_diff, N_SAMPLE_PTS),
        np.repeat(cfg_iou, N_SAMPLE_PTS), padded.ravel(), np.repeat(cfg_bbox, N_SAMPLE_PTS),
    )
    n_rows = n_cfg * N_SAMPLE_PTS
    tp = np.zeros(n_rows, dtype=np.int64)
    fp = np.zeros(n_rows, dtype=np.int64)
    fn = np.zeros(n_rows, dtype=np.int64)
    for frame in tqdm(frames, desc="precision", disable=not progress):
        if frame.scores.size == 0:
            fn += frame.n_counted_gt[second.difficulty]
            continue
        outcome = _assign(frame, second, by_score=False)
        tp += outcome.tp
        fn += outcome.fn
        fp += _false_positives(frame, second, outcome.assigned)

    curves = []
    for c, (m, iou, d) in enumerate(zip(cfg_metric.tolist(), cfg_iou.tolist(), cfg_diff.tolist(), strict=True)):
        k = thresholds[c].size
        sl = slice(c * N_SAMPLE_PTS, c * N_SAMPLE_PTS + k)
        precision = np.zeros(N_SAMPLE_PTS)
        # tp + fp can only be 0 in contrived cases; the devkit would produce NaN there.
        np.divide(tp[sl], tp[sl] + fp[sl], out=precision[:k], where=(tp[sl] + fp[sl]) > 0)
        precision = np.maximum.accumulate(precision[::-1])[::-1]  # max over this and later points
        curves.append(
            PrCurve(
                metric=metrics[m], iou_threshold=iou, difficulty=DIFFICULTIES[d], n_ground_truth=int(n_gt[c]),
                thresholds=thresholds[c], tp=tp[sl].copy(), fp=fp[sl].copy(), fn=fn[sl].copy(),
                precision=precision,
            )
        )
    return curves


# ----------------------------------------------------------------------------- frame bootstrap
IntervalMethod = Literal["bca", "bc", "percentile"]
INTERVAL_METHODS: tuple[str, ...] = ("bca", "bc", "percentile")
METHOD_NAMES = {"bca": "BCa", "bc": "BC", "percentile": "percentile"}  # as tables and titles name them
_NORMAL = NormalDist()


@dataclass(frozen=True)
class _StepTables:
    """One detection set's prepared frames reduced to what R40 AP needs on any weighting of the frames.

    A frame's second-pass counts are step functions of the score threshold t: detections scoring ``>= t``
    take part, so the counts change only at the frame's own scores. Matching each frame once at each of its
    scores (and the first pass once, which has no threshold) gives AP of any multiset of the frames (a
    bootstrap draw: weight = times drawn; a jackknife sample: weight 0 for the frame left out) with no
    matching at all, and exactly the AP that :func:`evaluate` gives on the frames listed that many times.

    cfg_difficulty: (C,) difficulty of each (metric, overlap threshold, difficulty), in ``_curves``' order.
    n_counted_gt: (F, 3) int64 counted ground truth per frame and difficulty.
    tp_scores, tp_frames: per configuration, (P_c,) first-pass true-positive scores and the frame of each.
    step_scores: (E,) ascending, the scores at which a frame's counts change; step_frames: (E,) that frame.
    step_tp, step_fp: (C, E) int64, how much the frame's true / false positives grow when t falls from
    above the score to the score.
    """

    cfg_difficulty: np.ndarray
    n_counted_gt: np.ndarray
    tp_scores: tuple[np.ndarray, ...]
    tp_frames: tuple[np.ndarray, ...]
    step_scores: np.ndarray
    step_frames: np.ndarray
    step_tp: np.ndarray
    step_fp: np.ndarray


def _step_tables(frames: Sequence[_Frame], metrics: tuple[str, ...],
                 iou_thresholds: tuple[float, ...]) -> _StepTables:
    """Both matching passes of every frame, once: the first as in ``_curves``, the second at the frame's scores."""
    first = _first_pass_rows(metrics, iou_thresholds)
    n_cfg, cfg_metric, cfg_iou, cfg_diff, cfg_bbox = (first.metric.size, first.metric, first.min_overlap,
                                                      first.difficulty, first.is_bbox)
    tp_scores: list[list[np.ndarray]] = [[] for _ in range(n_cfg)]
    tp_frames: list[list[np.ndarray]] = [[] for _ in range(n_cfg)]
    scores, owners, grow_tp, grow_fp = [], [], [], []
    for f, frame in enumerate(frames):
        if frame.scores.size == 0:
            continue  # counts nothing but its missed cars, which the weights' total of counted ground truth holds
        if frame.ignored_gt.shape[1]:
            outcome = _assign(frame, first, by_score=True)
            for c in np.flatnonzero(outcome.tp):
                found = frame.scores[outcome.tp_detections[c]]
                tp_scores[c].append(found)
                tp_frames[c].append(np.full(found.size, f, dtype=np.int64))
        levels = np.unique(frame.scores)  # ascending
        k = levels.size
        rows = _Rows(np.repeat(cfg_metric, k), np.repeat(cfg_diff, k), np.repeat(cfg_iou, k),
                     np.tile(levels, n_cfg), np.repeat(cfg_bbox, k))
        outcome = _assign(frame, rows, by_score=False)
        counts = np.stack([outcome.tp, _false_positives(frame, rows, outcome.assigned)]).reshape(2, n_cfg, k)
        # Above the frame's top score no detection takes part: no true or false positive.
        grown = counts - np.concatenate([counts[:, :, 1:], np.zeros((2, n_cfg, 1), np.int64)], axis=2)
        scores.append(levels)
        owners.append(np.full(k, f, dtype=np.int64))
        grow_tp.append(grown[0])
        grow_fp.append(grown[1])
    if scores:
        all_scores = np.concatenate(scores)
        order = np.argsort(all_scores, kind="stable")
        step_scores, step_frames = all_scores[order], np.concatenate(owners)[order]
        step_tp, step_fp = np.concatenate(grow_tp, axis=1)[:, order], np.concatenate(grow_fp, axis=1)[:, order]
    else:
        step_scores, step_frames = np.zeros(0), np.zeros(0, dtype=np.int64)
        step_tp = step_fp = np.zeros((n_cfg, 0), dtype=np.int64)
    empty_scores, empty_frames = np.zeros(0), np.zeros(0, dtype=np.int64)
    return _StepTables(
        cfg_difficulty=cfg_diff,
        n_counted_gt=np.array([frame.n_counted_gt for frame in frames], dtype=np.int64).reshape(len(frames), 3),
        tp_scores=tuple(np.concatenate(s) if s else empty_scores for s in tp_scores),
        tp_frames=tuple(np.concatenate(s) if s else empty_frames for s in tp_frames),
        step_scores=step_scores, step_frames=step_frames, step_tp=step_tp, step_fp=step_fp,
    )


def _weighted_ap(tables: _StepTables, weights: np.ndarray) -> np.ndarray:
    """(C,) R40 AP in percent of the frames taken ``weights`` (F,) times each, per configuration of ``tables``."""
    n_gt = weights @ tables.n_counted_gt  # (3,)
    step_weights = weights[tables.step_frames]
    # Totals at a threshold t: the growth of every step at or above t (steps ascending: a suffix sum).
    suffix = np.zeros((2, tables.step_tp.shape[0], step_weights.size + 1), dtype=np.int64)
    grown = np.stack([tables.step_tp, tables.step_fp]) * step_weights
    suffix[:, :, :-1] = np.cumsum(grown[:, :, ::-1], axis=2)[:, :, ::-1]
    ap = np.zeros(tables.cfg_difficulty.size)
    for c, difficulty in enumerate(tables.cfg_difficulty):
        found = np.repeat(tables.tp_scores[c], weights[tables.tp_frames[c]])
        thresholds = recall_thresholds(found, int(n_gt[difficulty]))
        start = np.searchsorted(tables.step_scores, thresholds, side="left")
        tp, fp = suffix[0, c, start], suffix[1, c, start]
        precision = np.zeros(N_SAMPLE_PTS)
        np.divide(tp, tp + fp, out=precision[: thresholds.size], where=(tp + fp) > 0)  # as in _curves
        precision = np.maximum.accumulate(precision[::-1])[::-1]
        ap[c] = precision[1:].sum() / 40.0 * 100.0
    return ap


@dataclass(frozen=True)
class BootstrapInterval:
    """An interval of one statistic (an AP, a difference of two, a share of a gap) over the bootstrap draws.

    low, high: the bounds; NaN when there are none, and ``note`` says why. method: ``bca`` (bias-corrected
    and accelerated, Efron 1987), ``bc`` (bias-corrected, acceleration 0: no jackknife was run) or
    ``percentile`` (the central ``level`` of the draws; also where BCa was asked for and z0 is infinite,
    with a note). estimate: the statistic on all frames. z0: the bias
    correction, Φ⁻¹ of the share of draws below the estimate (ties count half); ±inf when every draw lies on
    one side; NaN for ``percentile``. acceleration: from the leave-one-frame-out jackknife (0 for ``bc``,
    NaN for ``percentile``). draws: the draws the statistic exists on (a share needs a gap in the draw).
    """

    low: float
    high: float
    method: str
    estimate: float
    z0: float
    acceleration: float
    draws: int
    note: str = ""


def _acceleration(jackknife: np.ndarray) -> float:
    """Efron's acceleration from leave-one-out values θ_i: Σ(θ̄ − θ_i)³ / (6 (Σ(θ̄ − θ_i)²)^1.5); 0 if they are equal."""
    values = jackknife[np.isfinite(jackknife)]
    if values.size < 2:
        return 0.0
    spread = values.mean() - values
    squares = float((spread**2).sum())
    if squares <= 0.0:
        return 0.0
    return float((spread**3).sum() / (6.0 * squares**1.5))


def _bca_point(z0: float, z: float, acceleration: float) -> float:
    """Φ(z0 + (z0 + z) / (1 − a (z0 + z))), the share of the draws below a BCa bound."""
    shifted = z0 + z
    denominator = 1.0 - acceleration * shifted
    if denominator <= 0.0:  # past the pole of the adjustment: the draws' edge on the bound's side
        return 1.0 if shifted > 0 else 0.0
    return _NORMAL.cdf(z0 + shifted / denominator)


def bootstrap_interval(draws: np.ndarray, estimate: float, jackknife: np.ndarray | None = None,
                       level: float = 0.95, method: str = "bca") -> BootstrapInterval:
    """The ``level`` interval of a statistic from its values on the draws (B,), on all frames, and on the
    leave-one-out jackknife samples (n,) (needed for ``bca`` only; without them ``bca`` falls back to ``bc``).

    Draws where the statistic does not exist (NaN: a share without a gap) are left out. BCa takes the draws'
    percentiles Φ(z0 + (z0 + z_q) / (1 − a (z0 + z_q))) for q = (1 ∓ level) / 2 instead of q itself: z0
    moves the interval against the draws' lean (AP on a drawn frame set leans above the whole set's), a
    widens it on the side where the statistic's spread grows. When every draw lies above (or below) the
    estimate, z0 is infinite and there is no BCa interval: the percentile one, ``method`` saying so, with a note.
    """
    if method not in INTERVAL_METHODS:
        raise ValueError(f"method must be one of {INTERVAL_METHODS}, got {method!r}")
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be between 0 and 1, got {level}")
    values = np.asarray(draws, dtype=np.float64)
    values = values[np.isfinite(values)]
    nan = float("nan")
    tails = (50.0 * (1.0 - level), 50.0 * (1.0 + level))
    if values.size == 0:
        return BootstrapInterval(nan, nan, method, estimate, nan, nan, 0, "no draw has a value")
    if method == "percentile":
        low, high = np.percentile(values, tails)
        return BootstrapInterval(float(low), float(high), method, estimate, nan, nan, int(values.size))
    if not np.isfinite(estimate):
        return BootstrapInterval(nan, nan, method, estimate, nan, nan, int(values.size), "no value on all frames")
    below = (float((values < estimate).sum()) + 0.5 * float((values == estimate).sum())) / values.size
    if below in (0.0, 1.0):
        side = "above" if below == 0.0 else "below"
        low, high = np.percentile(values, tails)
        return BootstrapInterval(
            float(low), float(high), "percentile", estimate, -np.inf if below == 0.0 else np.inf, nan,
            int(values.size), f"every draw lies {side} the value on all frames ({estimate:.4g}): z0 is infinite "
            "and no BCa interval can be read off the draws; this is the percentile one")
    z0 = _NORMAL.inv_cdf(below)
    note = ""
    acceleration = 0.0
    if method == "bca" and jackknife is None:
        method, note = "bc", "no jackknife: acceleration 0 (BC)"
    elif method == "bca":
        acceleration = _acceleration(np.asarray(jackknife, dtype=np.float64))
    shares = [_bca_point(z0, _NORMAL.inv_cdf(tail / 100.0), acceleration) for tail in tails]
    low, high = np.percentile(values, [100.0 * s for s in shares])
    return BootstrapInterval(float(low), float(high), method, estimate, z0, acceleration, int(values.size), note)


@dataclass(frozen=True)
class BootstrapResult:
    """R40 AP (percent) of one or more detection sets on frame sets drawn with replacement.

    ap: (sets, resamples, metrics, overlap thresholds, 3 difficulties); every set was scored on
    the same draws, so differences between sets are paired. full: (sets, metrics, overlap thresholds, 3)
    on all frames. jackknife: (sets, frames, metrics, overlap thresholds, 3) with each frame left out in
    turn (in the order of their ids when :func:`bootstrap` had them), or None when it was not run.
    method: the interval the methods give unless told (``bca``; ``bc`` without a jackknife; ``percentile``).
    Every statistic (one set's AP, a paired difference, the share of a gap) is computed alike on the draws,
    on all frames and on the jackknife samples, set by set within each, so the BCa interval of a difference
    or share stays paired.
    """

    metrics: tuple[str, ...]
    iou_thresholds: tuple[float, ...]
    ap: np.ndarray
    seed: int
    full: np.ndarray
    jackknife: np.ndarray | None = None
    method: str = "bca"

    def _bounds(self, statistic: Callable[[np.ndarray], np.ndarray], metric: str, iou_threshold: float,
                difficulty: str, level: float, method: str | None) -> BootstrapInterval:
        """``statistic`` maps an array whose first axis is the sets to its value, on draws, all frames and
        jackknife samples alike."""
        m, t, d = (self.metrics.index(metric), self.iou_thresholds.index(float(iou_threshold)),
                   DIFFICULTIES.index(difficulty))
        jackknife = None if self.jackknife is None else statistic(self.jackknife[:, :, m, t, d])
        return bootstrap_interval(statistic(self.ap[:, :, m, t, d]), float(statistic(self.full[:, m, t, d])),
                                  jackknife, level, method or self.method)

    def ap_bounds(self, metric: str, iou_threshold: float, difficulty: str, index: int = 0, level: float = 0.95,
                  method: str | None = None) -> BootstrapInterval:
        """Interval of set ``index``'s AP, with how it was made."""
        return self._bounds(lambda ap: ap[index], metric, iou_threshold, difficulty, level, method)

    def difference_bounds(self, metric: str, iou_threshold: float, difficulty: str, first: int = 0,
                          second: int = 1, level: float = 0.95, method: str | None = None) -> BootstrapInterval:
        """Interval of AP(first) − AP(second) over the same draws (a paired bootstrap), with how it was made."""
        return self._bounds(lambda ap: ap[first] - ap[second], metric, iou_threshold, difficulty, level, method)

    def gap_share_bounds(self, metric: str, iou_threshold: float, difficulty: str, middle: int = 0, low: int = 1,
                         high: int = 2, level: float = 0.95, method: str | None = None) -> BootstrapInterval:
        """Interval of the share of the gap from set ``low`` up to set ``high`` that set ``middle`` closes,
        (AP(middle) − AP(low)) / (AP(high) − AP(low)), over the draws (and jackknife samples) where high is
        above low; none (NaN, with a note) when it is not on all frames."""
        def share(ap: np.ndarray) -> np.ndarray:
            gap = ap[high] - ap[low]
            return np.where(gap > 0, (ap[middle] - ap[low]) / np.where(gap > 0, gap, 1.0), np.nan)

        bounds = self._bounds(share, metric, iou_threshold, difficulty, level, method)
        if not np.isfinite(bounds.estimate):
            nan = float("nan")
            return BootstrapInterval(nan, nan, bounds.method, nan, nan, nan, bounds.draws,
                                     "no gap on all frames (the upper set is not above the lower one): no share")
        return bounds

    def interval(self, metric: str, iou_threshold: float, difficulty: str, index: int = 0,
                 level: float = 0.95, method: str | None = None) -> tuple[float, float]:
        """Interval of set ``index``'s AP (``method``, default the result's: BCa)."""
        bounds = self.ap_bounds(metric, iou_threshold, difficulty, index, level, method)
        return bounds.low, bounds.high

    def gap_share_interval(self, metric: str, iou_threshold: float, difficulty: str, middle: int = 0, low: int = 1,
                           high: int = 2, level: float = 0.95, method: str | None = None
                           ) -> tuple[float, float, int]:
        """Interval of the share of the gap (:meth:`gap_share_bounds`) and how many draws had a gap (a draw
        without one has no share)."""
        bounds = self.gap_share_bounds(metric, iou_threshold, difficulty, middle, low, high, level, method)
        return bounds.low, bounds.high, bounds.draws

    def difference_interval(self, metric: str, iou_threshold: float, difficulty: str, first: int = 0,
                            second: int = 1, level: float = 0.95, method: str | None = None) -> tuple[float, float]:
        """Interval of AP(first) − AP(second) over the same draws (a paired bootstrap)."""
        bounds = self.difference_bounds(metric, iou_threshold, difficulty, first, second, level, method)
        return bounds.low, bounds.high


def _by_id(frame_ids: Sequence[str] | None, n: int) -> np.ndarray:
    """The positions of ``n`` frames in the order of their ids (as given when there are none): a bootstrap's
    draws go to the frames in this order, so they do not hang on the order the frames were listed in."""
    if frame_ids is None:
        return np.arange(n)
    if len(frame_ids) != n:
        raise ValueError(f"frame_ids: {len(frame_ids)} ids for {n} frames of ground truth")
    return np.argsort(np.asarray(frame_ids, dtype=str), kind="stable")


def _check_bootstrap_inputs(ground_truth: Sequence[LabelArrays], detection_sets: Sequence[Sequence[LabelArrays]],
                            resamples: int, method: str, frame_ids: Sequence[str] | None = None) -> None:
    """Refuse what :func:`bootstrap` cannot draw from (ValueError naming the argument or detection set)."""
    if not detection_sets:  # NumPy's "need at least one array to stack" named nothing
        raise ValueError("detection_sets: none given; give at least one list of a frame's detections per frame")
    if isinstance(frame_ids, str):  # a str is a Sequence[str] of its characters: a broadcasting error followed
        raise TypeError(f"frame_ids: one id per frame, not the string {frame_ids[:20]!r}")
    if resamples < 1:
        raise ValueError(f"resamples must be at least 1, got {resamples}")
    if method not in INTERVAL_METHODS:
        raise ValueError(f"method must be one of {INTERVAL_METHODS}, got {method!r}")
    for i, detections in enumerate(detection_sets):
        if len(detections) != len(ground_truth):
            raise ValueError(f"detection set {i}: {len(detections)} frames, ground truth {len(ground_truth)}")
        _require_scores(detections, f"detection set {i}, ")


def _common_metrics(detection_sets: Sequence[Sequence[LabelArrays]], class_name: str) -> tuple[str, ...]:
    """The metrics every detection set can be scored on, in the order of ``METRICS``."""
    found = [set(_default_metrics(d, class_name)) for d in detection_sets]
    return tuple(m for m in METRICS if all(m in f for f in found))


def _scored(tables: Sequence[_StepTables], weights: np.ndarray, cell: tuple[int, int, int]) -> np.ndarray:
    """(sets, *cell) R40 AP of every detection set on the frames taken ``weights`` (F,) times each."""
    return np.stack([_weighted_ap(t, weights).reshape(cell) for t in tables])


def _drawn_ap(tables: Sequence[_StepTables], n: int, order: np.ndarray, cell: tuple[int, int, int],
              resamples: int, rng: np.random.Generator, progress: bool) -> np.ndarray:
    """(sets, resamples, *cell) AP on ``resamples`` draws of the ``n`` frames, ``n`` times with replacement;
    a draw's k-th count goes to frame ``order[k]``."""
    ap = np.zeros((len(tables), resamples, *cell))
    for r in tqdm(range(resamples), desc="bootstrap", disable=not progress):
        weights = np.zeros(n, dtype=np.int64)
        weights[order] = np.bincount(rng.integers(0, n, n), minlength=n)
        ap[:, r] = _scored(tables, weights, cell)
    return ap


def _jackknife_ap(tables: Sequence[_StepTables], n: int, order: np.ndarray, cell: tuple[int, int, int],
                  progress: bool) -> np.ndarray:
    """(sets, frames, *cell) AP on the ``n`` frames with each left out in turn, frame ``order[k]`` in sample k."""
    left_out = np.zeros((len(tables), n, *cell))
    for k, i in enumerate(tqdm(order, desc="jackknife", disable=not progress)):
        weights = np.ones(n, dtype=np.int64)
        weights[i] = 0
        left_out[:, k] = _scored(tables, weights, cell)
    return left_out


def bootstrap(
    ground_truth: Sequence[LabelArrays],
    detection_sets: Sequence[Sequence[LabelArrays]],
    resamples: int = 200,
    seed: int = 0,
    class_name: str = "Car",
    iou_thresholds: Sequence[float] = DEFAULT_IOU_THRESHOLDS,
    metrics: Sequence[str] | None = None,
    ignore_small_detections: bool = True,
    distance_range: tuple[float, float] | None = None,
    progress: bool = False,
    jackknife: bool = True,
    method: str = "bca",
    frame_ids: Sequence[str] | None = None,
) -> BootstrapResult:
    """How much AP moves with the choice of frames: the frame-level bootstrap.

    Each draw takes as many frames as there are, with replacement (a frame drawn twice counts
    twice), and scores every detection set with the official protocol (:func:`evaluate`) on
    those frames. Frames, not boxes, are drawn because boxes of one frame are matched together.
    The same frames also give each set's AP on all frames and, with ``jackknife``, on every
    leave-one-frame-out sample: the three ingredients of the BCa interval (``method``, the
    default of the result's interval methods). Each frame is matched once, at every one of its
    detection scores; an AP of any draw or sample then needs no matching (:class:`_StepTables`),
    and the jackknife of 300 frames costs about as much as 300 draws (~20 ms each per set here).

    frame_ids: the frames' ids, in the order of ``ground_truth``. The draws are made over the frames sorted by
    id (and the jackknife leaves them out in that order), so a seed gives the same draws of the same frames
    however they are listed (a split file's lines reversed gave other intervals); without ids, the frames are
    taken in the order given.
    """
    _check_bootstrap_inputs(ground_truth, detection_sets, resamples, method, frame_ids)
    metrics = _common_metrics(detection_sets, class_name) if metrics is None else tuple(metrics)
    iou_thresholds = tuple(float(t) for t in iou_thresholds)
    tables = [
        _step_tables([_prepare_frame(gt, det, class_name, metrics, ignore_small_detections, distance_range)
                      for gt, det in zip(ground_truth, detections)], metrics, iou_thresholds)
        for detections in tqdm(detection_sets, desc="matching", disable=not progress)
    ]
    n = len(ground_truth)
    order = _by_id(frame_ids, n)  # the k-th frame by id: the one each draw's k-th count goes to
    cell = (len(metrics), len(iou_thresholds), len(DIFFICULTIES))
    full = _scored(tables, np.ones(n, dtype=np.int64), cell)
    ap = _drawn_ap(tables, n, order, cell, resamples, np.random.default_rng(seed), progress)
    left_out = _jackknife_ap(tables, n, order, cell, progress) if jackknife else None
    return BootstrapResult(metrics=metrics, iou_thresholds=iou_thresholds, ap=ap, seed=seed, full=full,
                           jackknife=left_out, method=method)
