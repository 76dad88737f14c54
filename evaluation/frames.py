"""Reading a KITTI ground-truth label directory and a result directory into evaluation frames."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from evaluation.labels import LabelArrays
from pipeline.errors import InputError
from pipeline.frame import read_split_file  # noqa: F401  (re-exported: evaluation's callers use it)
from pipeline.kitti import read_labels

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LabelSet:
    """Ground truth and detections of the evaluated frames, in the same order.

    missing_predictions: frame ids without a result file, counted as frames without detections; empty
    unless ``load_label_dirs`` was given ``missing_as_empty``, without which such a frame is refused.
    """

    frame_ids: tuple[str, ...]
    ground_truth: tuple[LabelArrays, ...]
    detections: tuple[LabelArrays, ...]
    missing_predictions: tuple[str, ...]


def _require_dir(path: Path, what: str) -> None:
    if path.exists() and not path.is_dir():
        raise InputError(f"{path}: not a directory (the {what} folder is meant)")
    if not path.is_dir():
        raise InputError(f"{path}: {what} directory not found")


def _some(ids: Sequence[str], shown: int = 5) -> str:
    """``a, b, c`` or, for a long list, ``a, b, c, … 7481 frames``."""
    if len(ids) <= shown:
        return ", ".join(ids)
    return ", ".join(ids[: shown - 2]) + f", … {len(ids)} frames"


def first_frames(ids: list[str], count: int | None) -> list[str]:
    """The first ``count`` of ``ids`` (--frames N; all with None), with a warning when there are fewer: the
    table's "(N frames)" would be the only sign."""
    if count is not None and len(ids) < count:
        log.warning("--frames %d: only %d frame(s) to evaluate; using them all", count, len(ids))
    return ids[:count]


def ground_truth_frames(gt_dir: str | Path, frame_ids: Sequence[str] | None = None) -> list[str]:
    """The frames to evaluate, checked before any work: ``frame_ids`` or every ``*.txt`` in ``gt_dir``.

    A missing directory, an empty one and a listed frame without a ground-truth file are errors.
    """
    gt_dir = Path(gt_dir)
    _require_dir(gt_dir, "ground-truth label")
    if frame_ids is None:
        frame_ids = sorted(p.stem for p in gt_dir.glob("*.txt"))
        if not frame_ids:
            raise InputError(f"{gt_dir}: no ground-truth label files (*.txt)")
    for frame_id in frame_ids:
        gt_path = gt_dir / f"{frame_id}.txt"
        if not gt_path.is_file():
            raise InputError(f"{gt_path}: ground-truth label file not found for frame {frame_id}")
    return list(frame_ids)


def check_ground_truth(gt_dir: str | Path, frame_ids: Sequence[str], progress: bool = False) -> None:
    """Parse the ground-truth label file of every frame in ``frame_ids``; the first unusable one is an InputError
    naming its line and field. For a run that detects before it evaluates: a broken label file is otherwise
    found only after the detector has been over every frame (tens of minutes on KITTI's val split), and the
    run ends without its table. About 0.1 ms a file."""
    gt_dir = Path(gt_dir)
    for frame_id in tqdm(frame_ids, desc="check labels", disable=not progress):
        try:
            read_labels(gt_dir / f"{frame_id}.txt")
        except InputError as exc:
            raise InputError(f"{exc}; mend the ground truth, or give --split-file or --frames to leave frame "
                             f"{frame_id} out") from exc


def load_label_dirs(
    gt_dir: str | Path,
    pred_dir: str | Path,
    frame_ids: Sequence[str] | None = None,
    progress: bool = False,
    missing_as_empty: bool = False,
) -> LabelSet:
    """Read ``<gt_dir>/<id>.txt`` and ``<pred_dir>/<id>.txt`` for every frame.

    frame_ids: frames to evaluate; default every ``*.txt`` in ``gt_dir`` (then a result file of
    another frame is named in a warning). A listed frame without a ground-truth file is an error, and so is a
    frame without a result file, as in the official devkit: a detector that found nothing writes an empty
    file, so a missing one is a lost or unfinished result. ``missing_as_empty`` counts those frames as
    having no detections instead (with a warning); no result file for any frame is an error either way (the
    wrong folder or file names). Every result line needs a score (16 fields).
    """
    gt_dir, pred_dir = Path(gt_dir), Path(pred_dir)
    every_gt_file = frame_ids is None
    frame_ids = ground_truth_frames(gt_dir, frame_ids)
    _require_dir(pred_dir, "prediction label")
    missing = [frame_id for frame_id in frame_ids if not (pred_dir / f"{frame_id}.txt").is_file()]
    if len(missing) == len(frame_ids):
        results = sorted(p.name for p in pred_dir.glob("*.txt"))
        held = f"it holds {len(results)} *.txt file(s), e.g. {results[0]}" if results else "it holds no *.txt file"
        raise InputError(f"{pred_dir}: no result file matches a frame of {gt_dir} ({_some(frame_ids)}); {held}")
    if every_gt_file:  # a split leaves results out on purpose; every label file should cover every result
        unscored = sorted({p.stem for p in pred_dir.glob("*.txt")} - set(frame_ids))
        if unscored:
            log.warning("%d result file(s) in %s have no ground truth in %s and are not scored, e.g. %s.txt",
                        len(unscored), pred_dir, gt_dir, unscored[0])
    if missing and not missing_as_empty:
        raise InputError(
            f"{pred_dir}: {len(missing)} of {len(frame_ids)} frames have no result file, e.g. {missing[0]}.txt; the "
            "KITTI devkit refuses such a submission (a detector that finds nothing in a frame writes an empty file); "
            "--missing-as-empty counts them as frames without detections")
    if missing:
        log.warning("%d of %d frames have no result file in %s (counted as no detections), e.g. %s",
                    len(missing), len(frame_ids), pred_dir, missing[0])
    ground_truth: list[LabelArrays] = []
    detections: list[LabelArrays] = []
    absent = set(missing)
    for frame_id in tqdm(frame_ids, desc="labels", disable=not progress):
        ground_truth.append(LabelArrays.from_objects(read_labels(gt_dir / f"{frame_id}.txt")))
        detections.append(LabelArrays.empty() if frame_id in absent
                          else LabelArrays.from_objects(read_labels(pred_dir / f"{frame_id}.txt", needs_score=True)))
    return LabelSet(
        frame_ids=tuple(frame_ids), ground_truth=tuple(ground_truth), detections=tuple(detections),
        missing_predictions=tuple(missing),
    )
