"""KITTI accuracy: evaluate KITTI result files against KITTI labels with the official protocol.

    python benchmarks/accuracy.py --gt-labels DIR --pred-labels DIR [--split-file F]
                                  [--by-distance EDGES] [--json OUT] [--plots DIR]
    python benchmarks/accuracy.py --data DIR --models DIR --input lidar64|lidar16|lidar16+camera
                                  [--frames LIST|N] [--out DIR] [--depth-dir DIR] [--json OUT] [--plots DIR]
    python benchmarks/accuracy.py --depth --data DIR --models DIR [--depth-dir DIR] [--frames LIST|N] [--json OUT]

prints the paper's table (Car BEV AP at IoU 0.7 and 0.5, easy / moderate / hard,
40- and 11-point; 3D and 2D-box AP when the results carry them), writes every
figure as JSON and one precision-recall PNG per difficulty.

The mode is chosen by flags (no subcommands): ``--gt-labels`` / ``--pred-labels``
evaluate existing result files; ``--data`` / ``--models`` / ``--input`` run the
detector over a KITTI-layout dataset first (results in ``--out``, default
``outputs/accuracy/MODELS/INPUT``: a folder per model and input) and evaluate them against its
``label_2``; ``--depth`` measures depth completion (RMSE, MAE, iRMSE, iMAE).
``--by-distance`` adds AP per distance band, and ``--depth-dir`` feeds the
camera pipeline depth maps from files instead of its depth network (with the
synthetic scenes' ``depth_2``: the upper bound of perfect depth); with
``--depth`` it evaluates those maps instead of the network's.

``--split-file`` and ``--frames`` are one flag under two names: the frames to
run and evaluate, in every mode; ``--frames N`` (a number) takes the first N
frames in id order, as the other commands' ``--frames N`` counts frames. A flag of another mode is refused, not ignored
(``--gt-labels`` with ``--data``: the ground truth is ``DATA/label_2``). Inputs
and output paths are checked before any model runs.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from itertools import pairwise
from pathlib import Path
from typing import TYPE_CHECKING, Any

from evaluation import DEFAULT_SCORE_THRESHOLD
from evaluation.frames import (
    LabelSet,
    check_ground_truth,
    first_frames,
    ground_truth_frames,
    load_label_dirs,
    read_split_file,
)
from evaluation.kitti_eval import (
    DEFAULT_IOU_THRESHOLDS,
    DIFFICULTIES,
    INTERVAL_METHODS,
    BootstrapResult,
    KittiEvalResult,
    bootstrap,
    evaluate,
    evaluate_by_distance,
)
from evaluation.report import (
    METRIC_TITLES,
    distance_json,
    format_difference,
    format_distance_table,
    format_gap,
    format_spread,
    format_table,
    gap_json,
    plot_by_distance,
    plot_car_depth,
    plot_pr_curves,
    spread_json,
    to_json,
)
from pipeline.beams import BEAM_COUNTS
from pipeline.cli import (
    HelpFormatter,
    add_no_progress,
    check_not_input,
    check_output,
    examples,
    list_or_count,
    non_negative_int,
    positive_int,
    probability,
    quiet_interrupt,
    show_progress,
    skipped_summary,
)
from pipeline.errors import InputError
from pipeline.frame import frame_ids
from pipeline.model_files import load_manifest_with_digest
from pipeline.provenance import code_version

if TYPE_CHECKING:  # imported when a dataset mode runs: the harness loads OpenCV and ONNX Runtime
    from evaluation.harness import DepthRun, DetectionRun

log = logging.getLogger("accuracy")


@dataclass(frozen=True)
class LabelEvalConfig:
    """Evaluate result files in ``pred_labels`` against ground truth in ``gt_labels``.

    split_file: frame ids to evaluate (default: every ground-truth file). first_frames: only the first
    N of those (of the ground-truth files in id order without a split file).
    json_path / plots_dir: where to write the JSON document and the PR plots (optional).
    """

    gt_labels: Path
    pred_labels: Path
    split_file: Path | None = None
    first_frames: int | None = None
    json_path: Path | None = None
    plots_dir: Path | None = None
    class_name: str = "Car"
    iou_thresholds: tuple[float, ...] = DEFAULT_IOU_THRESHOLDS
    progress: bool = True
    ignore_small_detections: bool = True  # the devkit's rule (evaluation.kitti_eval.evaluate)
    missing_as_empty: bool = False  # a frame without a result file has no detections (the devkit: an error)
    distance_edges: tuple[float, ...] = ()  # also AP per band [edge_i, edge_i+1) of camera depth z
    depth_dir: Path | None = None  # the camera row's depth came from these PNGs, not the network (JSON note)
    bootstrap: int = 0  # draws of the frame bootstrap (0: none): the AP's spread over frame samples
    seed: int = 0  # of the bootstrap draws
    interval: str = "bca"  # bootstrap interval: bca (default), bc (no jackknife) or percentile (INTERVAL_METHODS)
    compare_pred_labels: Path | None = None  # another model's results on the same frames: AP differences
    gap_to_pred_labels: Path | None = None  # a stronger model's: the share of the gap up to it that pred_labels closes
    detector: dict[str, Any] | None = None  # what made pred_labels, when this run detected (JSON "run")
    source: str | None = None  # what the plots are of, in their titles (default: the two label directories)


@dataclass(frozen=True)
class LabelEvalRun:
    """What a run made: the evaluation, its table, and the files written."""

    result: KittiEvalResult
    table: str
    by_distance: dict[tuple[float, float], KittiEvalResult]
    spread: BootstrapResult | None
    missing_predictions: tuple[str, ...]
    json_path: Path | None
    plot_paths: tuple[Path, ...]


def run(config: LabelEvalConfig) -> LabelEvalRun:
    """Load both label directories, evaluate, write the JSON and plots if asked."""
    frame_ids = _selected_frames(config)
    _check_compared(config.compare_pred_labels, config.gap_to_pred_labels)
    labels = load_label_dirs(config.gt_labels, config.pred_labels, frame_ids, progress=config.progress,
                             missing_as_empty=config.missing_as_empty)
    if not any((d.types == config.class_name.lower()).any() for d in labels.detections):
        log.warning("no %s detection in %s: every AP is 0", config.class_name, config.pred_labels)
    _warn_if_cut_at_a_score(labels, config)
    evaluation = _evaluate_all(config, frame_ids, labels)
    if config.json_path:
        _write_json(config.json_path, _json_document(config, evaluation))
    plot_paths = _plot(config, config.plots_dir, evaluation) if config.plots_dir else ()
    return LabelEvalRun(
        result=evaluation.result, table=_table(config, evaluation), by_distance=evaluation.by_distance,
        spread=evaluation.spread, missing_predictions=labels.missing_predictions, json_path=config.json_path,
        plot_paths=plot_paths,
    )


@dataclass(frozen=True)
class _Evaluation:
    """Every figure of a run: this model's evaluation (overall and per distance band), the compared models', the
    bootstrap's spread, and the frames without a result file."""

    result: KittiEvalResult
    by_distance: dict[tuple[float, float], KittiEvalResult]
    other: KittiEvalResult | None  # --compare-pred-labels'
    other_by_distance: dict[tuple[float, float], KittiEvalResult]
    upper: KittiEvalResult | None  # --gap-to-pred-labels'
    spread: BootstrapResult | None
    missing_predictions: tuple[str, ...]


def _selected_frames(config: LabelEvalConfig) -> list[str] | None:
    """The frame ids to evaluate: the split file's, cut to the first N; None for every ground-truth file."""
    frame_ids = read_split_file(config.split_file) if config.split_file else None
    if config.first_frames is not None:
        frame_ids = first_frames(frame_ids or ground_truth_frames(config.gt_labels), config.first_frames)
    return frame_ids


def _evaluate_all(config: LabelEvalConfig, frame_ids: list[str] | None, labels: LabelSet) -> _Evaluation:
    """This model's results evaluated, then the compared models' and the bootstrap, then the distance bands."""
    result = evaluate(
        labels.ground_truth, labels.detections, class_name=config.class_name,
        iou_thresholds=config.iou_thresholds, progress=config.progress,
        ignore_small_detections=config.ignore_small_detections,
    )
    if not result.metrics:  # detections of the class, but none a metric can use: an empty table otherwise
        raise InputError(f"{config.pred_labels}: no {config.class_name} detection carries a 2D box (left >= 0) or "
                         "a ground-plane box (x, z != -1000, w, l > 0): nothing to evaluate")
    other, other_labels, upper, spread = _compare_and_bootstrap(config, frame_ids, labels, result)
    by_distance = _by_distance(config, labels)
    other_by_distance = _by_distance(config, other_labels) if other_labels is not None else {}
    return _Evaluation(result=result, by_distance=by_distance, other=other, other_by_distance=other_by_distance,
                       upper=upper, spread=spread, missing_predictions=labels.missing_predictions)


def _json_document(config: LabelEvalConfig, evaluation: _Evaluation) -> dict[str, Any]:
    """The JSON document: the AP tables, what was compared, and what the figures are of."""
    result, other, upper, spread = evaluation.result, evaluation.other, evaluation.upper, evaluation.spread
    document = to_json(result)
    if evaluation.by_distance:
        document["by_distance"] = distance_json(evaluation.by_distance)
    if evaluation.other_by_distance:
        document["compared_by_distance"] = distance_json(evaluation.other_by_distance)
    if spread is not None:
        document["bootstrap"] = _spread_document(result, spread, other, upper is not None)
    if other is not None:
        document["compared_with"] = {"pred_labels": str(config.compare_pred_labels), **other.ap_table()}
    if upper is not None:
        document["gap_to"] = {"pred_labels": str(config.gap_to_pred_labels), **upper.ap_table()}
        document["gap_share"] = gap_json(result, other, upper, spread)
        if spread is not None:
            document["gap_share"]["method"] = spread.method
            document["gap_share"]["percentile_interval"] = gap_json(
                result, other, upper, replace(spread, method="percentile"))["interval"]
    if config.depth_dir is not None:
        document["depth_source"] = f"{config.depth_dir} (not the depth network)"
    document["missing_predictions"] = list(evaluation.missing_predictions)
    # What the figures are of, so a JSON file read later needs no command line beside it.
    document["run"] = {"gt_labels": str(config.gt_labels), "pred_labels": str(config.pred_labels),
                       "split_file": None if config.split_file is None else str(config.split_file),
                       "first_frames": config.first_frames, **(config.detector or {}), "code": code_version()}
    document["small_detections"] = "ignored (devkit)" if config.ignore_small_detections else "counted (diagnostic)"
    return document


def _write_json(path: Path, document: dict[str, Any]) -> None:
    """``document`` written to ``path`` (--json) as strict JSON, NaN as null."""
    with _writing(path, "--json"):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(_without_nan(document), indent=1, allow_nan=False) + "\n", encoding="utf-8")


def _plot(config: LabelEvalConfig, plots_dir: Path, evaluation: _Evaluation) -> tuple[Path, ...]:
    """The precision-recall curves (and AP by distance, with bands) as PNGs in ``plots_dir``; their paths."""
    with _writing(plots_dir, "--plots"):
        source = config.source or f"{config.pred_labels} against {config.gt_labels}"
        names = (_short_name(config.pred_labels), _short_name(config.compare_pred_labels))
        plot_paths = tuple(plot_pr_curves(evaluation.result, plots_dir, source, evaluation.other, names))
        if evaluation.by_distance:
            plot_paths += (plot_by_distance(evaluation.by_distance, plots_dir / "ap_by_distance.png",
                                            evaluation.other_by_distance, names, source),)
    return plot_paths


def _table(config: LabelEvalConfig, evaluation: _Evaluation) -> str:
    """The printed tables: AP, per distance band, the comparison or spread, the gap, and the notes above them."""
    result, other, upper, spread = evaluation.result, evaluation.other, evaluation.upper, evaluation.spread
    table = format_table(result)
    if evaluation.by_distance:
        table += "\n" + format_distance_table(evaluation.by_distance)
    if evaluation.other_by_distance:
        table += "\n" + format_distance_table(evaluation.other_by_distance, str(config.compare_pred_labels))
    if spread is not None:
        table += "\n" + format_spread(result, spread, other, str(config.compare_pred_labels))
    elif other is not None:
        table += "\n" + format_difference(result, other, str(config.compare_pred_labels))
    if upper is not None:
        table += "\n" + format_gap(result, other, upper, str(config.compare_pred_labels), str(config.gap_to_pred_labels),
                                   spread)
    if spread is not None:
        table += "\n" + "\n".join([f"intervals: {INTERVAL_NAMES[spread.method]}",
                                   *_interval_notes(spread, upper is not None)])
    if not config.ignore_small_detections:
        table = "not the devkit protocol: detections with 2D boxes under the minimum height are counted\n" + table
    if evaluation.missing_predictions:
        # With --data the detector's skipped frames (named above the table) are counted so, without the flag.
        why = "frames the detector skipped" if config.detector else "--missing-as-empty"
        table = (f"{len(evaluation.missing_predictions)} of {result.n_frames} frames have no result file, counted as "
                 f"frames without detections ({why})\n" + table)
    return table


# Lowest score below which a result folder looks complete. The precision-recall curve's tail needs the
# low-score detections: accuracy.py's own runs keep scores above DEFAULT_SCORE_THRESHOLD, pipeline.detect above 0.5.
CUT_SCORE = 0.1


def _check_compared(compare: Path | None, gap_to: Path | None) -> None:
    """The other models' result folders (--compare-pred-labels, --gap-to-pred-labels) exist, and a gap has its
    lower end: checked once, before the evaluation (and, with --data, before the detector runs)."""
    if compare is not None and not Path(compare).is_dir():
        raise InputError(f"--compare-pred-labels: {compare}: prediction label directory not found")
    if gap_to is not None:
        if compare is None:
            raise InputError("--gap-to-pred-labels: give --compare-pred-labels too (the gap runs from that model "
                             "up to this one)")
        if not Path(gap_to).is_dir():
            raise InputError(f"--gap-to-pred-labels: {gap_to}: prediction label directory not found")


def _warn_if_cut_at_a_score(labels: LabelSet, config: LabelEvalConfig) -> None:
    """A warning when the results were (or look) cut at a score threshold: it lowers AP (5 points at IoU 0.7
    moderate on 30 of the synthetic validation frames with pipeline.detect's 0.5, docs/evaluation.md). When
    this run made them, its own --score-threshold says; result files are judged by their lowest car score."""
    if config.detector is not None:
        threshold = config.detector["score_threshold"]
        if threshold >= CUT_SCORE:
            log.warning("--score-threshold %.2f leaves out the low-score detections that AP's recall needs, and AP "
                        "comes out lower; the default %g keeps them", threshold, DEFAULT_SCORE_THRESHOLD)
        return
    scores = [d.score[d.types == config.class_name.lower()] for d in labels.detections]
    lowest = min((float(s.min()) for s in scores if s.size), default=None)
    if lowest is not None and lowest >= CUT_SCORE:
        log.warning("the lowest %s score in %s is %.2f: if these results were written with a score threshold, "
                    "they miss the low-score detections that AP's recall needs, and AP comes out lower; write them "
                    "with --score-threshold %g (python -m pipeline.detect keeps 0.5 and up by default)",
                    config.class_name, config.pred_labels, lowest, DEFAULT_SCORE_THRESHOLD)


@contextmanager
def _writing(path: Path, flag: str) -> Iterator[None]:
    """An OSError while writing ``path`` as an InputError naming the flag (paths are checked up front;
    this is for what changes in between, such as a full disk)."""
    try:
        yield
    except OSError as exc:
        raise InputError(f"{flag} {path}: cannot write ({exc.strerror or exc})") from exc


def _short_name(folder: Path | None) -> str:
    """A result folder's name for a legend: ``runs/x/acc_edge/data`` → ``acc_edge``."""
    folder = Path(folder or "")
    return folder.parent.name if folder.name == "data" else folder.name


def _by_distance(config: LabelEvalConfig, labels: LabelSet) -> dict[tuple[float, float], KittiEvalResult]:
    """One evaluation per distance band of ``config.distance_edges`` (empty without bands)."""
    return evaluate_by_distance(labels.ground_truth, labels.detections, config.distance_edges,
                                class_name=config.class_name, iou_thresholds=config.iou_thresholds,
                                ignore_small_detections=config.ignore_small_detections)


def _other_results(config: LabelEvalConfig, frame_ids: list[str] | None, folder: Path | None,
                   flag: str) -> tuple[KittiEvalResult | None, LabelSet | None]:
    """Another model's result files on the same frames (``flag``'s ``folder``), evaluated; (None, None) without."""
    if folder is None:
        return None, None
    try:
        labels = load_label_dirs(config.gt_labels, folder, frame_ids, progress=False,
                                 missing_as_empty=config.missing_as_empty)
    except InputError as exc:
        raise InputError(f"{flag}: {exc}") from exc
    return evaluate(labels.ground_truth, labels.detections, class_name=config.class_name,
                    iou_thresholds=config.iou_thresholds,
                    ignore_small_detections=config.ignore_small_detections), labels


def _compare_and_bootstrap(config: LabelEvalConfig, frame_ids: list[str] | None, labels: LabelSet, result: KittiEvalResult
                           ) -> tuple[KittiEvalResult | None, LabelSet | None, KittiEvalResult | None,
                                      BootstrapResult | None]:
    """The other model's evaluation and labels (``compare_pred_labels``), the stronger one's evaluation
    (``gap_to_pred_labels``), and the bootstrap of all on the same draws, when asked."""
    other, other_labels = _other_results(config, frame_ids, config.compare_pred_labels, "--compare-pred-labels")
    upper, upper_labels = _other_results(config, frame_ids, config.gap_to_pred_labels, "--gap-to-pred-labels")
    if not config.bootstrap:
        return other, other_labels, upper, None
    compared = [(o, lab) for o, lab in ((other, other_labels), (upper, upper_labels)) if o is not None]
    sets = [labels.detections] + [lab.detections for _, lab in compared]  # this, other, upper: index 0, 1, 2
    # BEV and 3D only: the paper's table and its 3D counterpart; each metric costs a matching pass per draw.
    metrics = tuple(m for m in ("bev", "3d") if m in result.metrics and all(m in o.metrics for o, _ in compared))
    spread = bootstrap(labels.ground_truth, sets, config.bootstrap, config.seed, class_name=config.class_name,
                       iou_thresholds=config.iou_thresholds, metrics=metrics,
                       ignore_small_detections=config.ignore_small_detections, progress=config.progress,
                       jackknife=config.interval == "bca", method=config.interval,
                       frame_ids=labels.frame_ids)  # draws by id: the split file's order changes nothing
    return other, other_labels, upper, spread


# What each --interval gives, for the line under the bootstrap tables.
INTERVAL_NAMES = {
    "bca": "BCa, bias-corrected and accelerated (Efron 1987): AP on frames drawn with replacement leans above "
           "the whole set's, and the bounds are the draws' percentiles moved against that lean (z0) and for the "
           "skew (acceleration, from leaving each frame out in turn); --interval percentile gives the central "
           "share of the draws",
    "bc": "BC, bias-corrected (BCa without the jackknife: acceleration 0); --interval bca adds it",
    "percentile": "percentile, the central share of the draws, not corrected for their lean above the whole "
                  "set's AP (--interval bca corrects it)",
}


def _interval_notes(spread: BootstrapResult, with_gap: bool) -> list[str]:
    """A line per interval the table gives otherwise than asked (every draw on one side of the value on all frames:
    the percentile one) or not at all (a share without a gap), naming the column and why."""
    notes = []
    for metric in spread.metrics:
        for iou in sorted(spread.iou_thresholds):
            for d in DIFFICULTIES:
                cells = [("AP", spread.ap_bounds(metric, iou, d))]
                if spread.ap.shape[0] > 1:
                    cells.append(("this − other", spread.difference_bounds(metric, iou, d)))
                if with_gap and spread.ap.shape[0] > 2:
                    cells.append(("share of the gap", spread.gap_share_bounds(metric, iou, d)))
                notes += [f"  {METRIC_TITLES[metric]} @{iou} {d}, {what}: {bounds.note}"
                          for what, bounds in cells if bounds.note]
    return notes


def _spread_document(result: KittiEvalResult, spread: BootstrapResult, other: KittiEvalResult | None,
                     with_gap: bool) -> dict[str, Any]:
    """The JSON's ``bootstrap``: report.spread_json with the method's intervals, the method's name, the percentile
    intervals beside them (``percentile``), and the notes of intervals not given."""
    document = spread_json(result, spread, other)
    document["method"] = spread.method
    plain = spread_json(result, replace(spread, method="percentile"), other)
    document["percentile"] = {key: plain[key] for key in ("interval", "difference_interval") if key in plain}
    document["notes"] = [line.strip() for line in _interval_notes(spread, with_gap)]
    return document


def _without_nan(value: Any) -> Any:
    """``value`` with every NaN float replaced by None (JSON null; an interval that could not be made)."""
    if isinstance(value, float) and math.isnan(value):
        return None
    if isinstance(value, dict):
        return {key: _without_nan(v) for key, v in value.items()}
    if isinstance(value, list | tuple):
        return [_without_nan(v) for v in value]
    return value


def distance_edges(text: str) -> tuple[float, ...]:
    """Band edges in metres, comma-separated and increasing, such as ``0,20,35,50,80`` (argparse type)."""
    try:
        edges = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated metres such as 0,20,35,50,80; got {text!r}") from None
    if len(edges) < 2 or any(b <= a for a, b in pairwise(edges)) or edges[0] < 0:
        raise argparse.ArgumentTypeError(f"expected at least two increasing distances from 0 up; got {text!r}")
    return edges


def build_parser() -> argparse.ArgumentParser:
    """Command-line flags; each mode is a flag group."""
    parser = argparse.ArgumentParser(
        allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
        prog="python benchmarks/accuracy.py",
        description="KITTI object evaluation (official devkit protocol): Car BEV / 3D / 2D-box AP, "
        "R40 and R11, easy / moderate / hard.",
        epilog="Modes: --gt-labels/--pred-labels (result files), --data/--models/--input (run the detector, "
        "then evaluate against DATA/label_2), --depth --data/--models (depth completion). --split-file and "
        "--frames are the same flag and choose the frames in every mode. A flag of another mode is refused, "
        "not ignored (e.g. --gt-labels with --data). Inputs and output paths are checked before any work.\n\n"
        + examples("python benchmarks/accuracy.py --gt-labels data/kitti/training/label_2 --pred-labels "
                   "outputs/val/data --split-file data/kitti/ImageSets/val.txt",
                   "python benchmarks/accuracy.py --data data/sim/val --models weights/edge --input "
                   "lidar16+camera --out outputs/accuracy/edge"),
        formatter_class=HelpFormatter,
    )
    labels = parser.add_argument_group("evaluate result files")
    labels.add_argument("--gt-labels", type=Path, metavar="DIR", help="KITTI label_2 directory (ground truth)")
    labels.add_argument(
        "--pred-labels", type=Path, metavar="DIR",
        help="KITTI result files <id>.txt (label lines + score), one per frame (an empty file: no detections)",
    )
    labels.add_argument("--missing-as-empty", action="store_true",
                        help="count a frame without a result file as a frame without detections (default: refuse, "
                        "as the KITTI devkit does; a detector that finds nothing writes an empty file)")
    labels.add_argument("--split-file", type=Path, metavar="F",
                        help="frame ids to evaluate, one per line (default: every ground-truth file); in every "
                        "mode, and the same as --frames (with --data: the frames the detector runs on)")
    labels.add_argument(
        "--count-small-detections", action="store_true",
        help="diagnostic, not the devkit: count detections whose 2D box is under a difficulty's minimum "
        "height (25 or 40 px), which the devkit ignores; for a BEV detector whose 2D boxes come from "
        "estimated heights, BEV AP then measures the BEV boxes alone",
    )
    labels.add_argument(
        "--by-distance", type=distance_edges, default=(), metavar="EDGES",
        help="also AP per distance band, e.g. 0,20,35,80 (metres of camera depth z of the box centre; cars "
        "and detections outside a band are ignored in it, not missed or false); a table, the JSON's "
        "by_distance, and ap_by_distance.png with --plots",
    )
    spread = parser.add_argument_group("how sure: spread over frames and comparison with another model")
    spread.add_argument(
        "--bootstrap", type=positive_int, default=0, metavar="N",
        help="N frame-bootstrap draws (e.g. 200; with the jackknife about 8 s per model on 300 frames): each BEV "
        "and 3D AP with its 95%% interval, and with --compare-pred-labels the paired interval of the difference",
    )
    spread.add_argument("--seed", type=non_negative_int, default=0, help="seed of the bootstrap draws (default 0)")
    spread.add_argument(
        "--interval", choices=INTERVAL_METHODS, default="bca",
        help="which bootstrap interval (default bca): bca, bias-corrected and accelerated (Efron 1987), because AP "
        "on frames drawn with replacement leans above the whole set's AP and the plain percentile interval "
        "inherits that lean (on the 300 validation frames 71%% of the draws lie above the camera model's BEV AP "
        "at IoU 0.7 moderate); the bias correction comes from the share of draws below the value on all frames, "
        "the acceleration from leaving each frame out in turn (the jackknife); bc: without the jackknife "
        "(acceleration 0); percentile: the central 95%% of the draws, as until session 40. The JSON carries the "
        "percentile intervals beside the chosen ones",
    )
    spread.add_argument(
        "--compare-pred-labels", type=Path, metavar="DIR",
        help="another model's KITTI result files on the same frames: prints this − other for every AP",
    )
    spread.add_argument(
        "--gap-to-pred-labels", type=Path, metavar="DIR",
        help="with --compare-pred-labels LOW: a stronger model's result files on the same frames; prints the share "
        "of the gap from LOW up to DIR that this closes, per BEV and 3D column (the paper's camera row between its "
        "16- and 64-line rows), and with --bootstrap its 95%% interval over the same draws",
    )
    detect = parser.add_argument_group("run the detector over a dataset, then evaluate")
    detect.add_argument("--data", type=Path, metavar="DIR", help="KITTI object folder (image_2, velodyne, calib, label_2)")
    detect.add_argument("--models", type=Path, metavar="DIR", help="model directory trained for --input")
    detect.add_argument("--input", choices=["lidar64", "lidar16", "lidar16+camera"], help="the paper's table row")
    detect.add_argument("--frames", type=list_or_count, metavar="LIST|N",
                        help="frame ids to run and evaluate, one per line, as --split-file (default all); or N: "
                        "the first N frames in id order, as --frames N of the other commands")
    detect.add_argument("--out", type=Path, metavar="DIR", help="run folder: result files go to DIR/data (default outputs/accuracy/MODELS/INPUT, MODELS the model "
                        "directory's name, + written _: outputs/accuracy/edge/lidar16_camera)")
    detect.add_argument("--score-threshold", type=probability, default=DEFAULT_SCORE_THRESHOLD, metavar="SCORE",
                        help=f"keep detections above this score (default {DEFAULT_SCORE_THRESHOLD}: AP needs the "
                        "whole curve)")
    detect.add_argument("--provider", choices=["cpu", "cuda", "tensorrt"], help="execution provider")
    detect.add_argument("--mirror-tta", action="store_true",
                        help="PIXOR also on the BEV mirrored left to right, maps averaged (pipeline.detect --mirror-tta)")
    detect.add_argument("--emulate-beams", type=int, choices=(0, *BEAM_COUNTS), metavar="N",
                        help="thin the scans to N lines first (16, 32, 8, 4; 0: keep them as stored, as a 16-line "
                        "sensor's own scans need); default: the --input row's, 16 for lidar16 and lidar16+camera "
                        "(thinning KITTI's 64-line scans), none for lidar64; with --depth, 16; as in pipeline.detect "
                        "and latency.py")
    detect.add_argument(
        "--depth-dir", type=Path, metavar="DIR",
        help="with --input lidar16+camera or --depth: dense depth PNGs of the full camera image (KITTI depth "
        "format, <id>.png) used instead of the depth network, e.g. DATA/depth_2 of the synthetic scenes for the "
        "upper bound that perfect depth gives, or benchmarks/depth_bound.py's maps (with --depth: the maps "
        "evaluated; --models gives the crop and the view)",
    )
    depth = parser.add_argument_group("depth completion")
    depth.add_argument("--depth", action="store_true",
                       help="depth metrics with --data (KITTI depth-completion layout, or an object folder with depth_2/)")
    output = parser.add_argument_group("output")
    output.add_argument("--json", type=Path, metavar="FILE", help="write every figure as JSON (AP in percent)")
    output.add_argument("--plots", type=Path, metavar="DIR",
                        help="write PNGs: precision-recall curves per difficulty (pr_*.png) and, with --by-distance, "
                        "ap_by_distance.png; with --depth a picture per frame (depth_<id>.png: camera, prediction, "
                        "ground truth, error) and car_depth.png")
    add_no_progress(output)
    return parser


# Flags (by dest) that only some modes read; main refuses them in the others.
_RESULT_FILES = ("gt_labels", "pred_labels", "missing_as_empty")
_RUN = ("data", "models", "provider")
_DETECTION = ("input", "out", "score_threshold", "mirror_tta")
_SCANS = ("emulate_beams",)  # how the scans are thinned: for the detector and for --depth
_DEPTH_SOURCE = ("depth_dir",)  # the camera row's depth, or the maps --depth evaluates
_AP = ("count_small_detections", "by_distance", "bootstrap", "seed", "interval", "compare_pred_labels",
       "gap_to_pred_labels")


def default_out(models: Path, input_mode: str) -> Path:
    """``outputs/accuracy/<the model directory's name>/<input>`` (``+`` written ``_``): a run folder of its own for
    each model and input, so that evaluating another model does not replace one's result files."""
    return Path("outputs") / "accuracy" / Path(models).resolve().name / input_mode.replace("+", "_")


def _flag(dest: str) -> str:
    return "--" + dest.replace("_", "-")


def _refuse_flags_of_other_modes(parser: argparse.ArgumentParser, args: argparse.Namespace,
                                 argv: list[str] | None) -> None:
    """parser.error (exit 2) for a flag the chosen mode would ignore, naming it and the mode's flag."""
    unset = object()  # parsed again into a namespace that already holds every flag: defaults are not filled in
    again = vars(parser.parse_args(argv, argparse.Namespace(**dict.fromkeys(vars(args), unset))))
    given = {dest for dest, value in again.items() if value is not unset}

    def refuse(dests: tuple[str, ...], mode_flag: str, why: str) -> None:
        for dest in dests:
            if dest in given:
                parser.error(f"argument {_flag(dest)}: not allowed with argument {mode_flag} ({why})")

    if "split_file" in given and "frames" in given:
        parser.error("argument --frames: not allowed with argument --split-file (the same flag: give one)")
    if "seed" in given and not args.bootstrap:
        parser.error("argument --seed: only with --bootstrap N (it seeds the bootstrap's frame draws)")
    if "interval" in given and not args.bootstrap:
        parser.error("argument --interval: only with --bootstrap N (it chooses the bootstrap's interval)")
    if args.depth:
        refuse(_RESULT_FILES + _DETECTION + _AP, "--depth", "depth completion evaluates depth maps, not boxes")
    elif args.data is not None:
        refuse(_RESULT_FILES, "--data", "the detector writes the results and DATA/label_2 is the ground truth")
    else:
        mode = next((dest for dest in _RESULT_FILES if dest in given), None)
        for dest in _RUN + _DETECTION + _SCANS + _DEPTH_SOURCE:
            if dest in given and mode is not None:
                parser.error(f"argument {_flag(dest)}: not allowed with argument {_flag(mode)} "
                             "(result files are evaluated as they are; no model runs)")
            if dest in given:
                parser.error(f"argument {_flag(dest)}: only with --data DIR (the detector runs over a dataset)")


@quiet_interrupt("no table was made; what was written before (--out's result files, --plots' pictures) stays")
def main(argv: list[str] | None = None) -> int:
    """Parse flags, run, print the table; input errors are printed without a traceback (exit code 2)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    _refuse_flags_of_other_modes(parser, args, argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    selection = args.split_file or args.frames
    split_file = selection if isinstance(selection, Path) else None
    first = selection if isinstance(selection, int) else None
    if args.depth or args.data is not None:
        return _main_run(parser, args, split_file, first)
    if args.gt_labels is None or args.pred_labels is None:
        parser.error("give --gt-labels DIR and --pred-labels DIR, or --data DIR --models DIR --input …, or --depth")
    config = LabelEvalConfig(
        gt_labels=args.gt_labels, pred_labels=args.pred_labels, split_file=split_file, first_frames=first,
        json_path=args.json, plots_dir=args.plots, progress=show_progress(args.no_progress),
        ignore_small_detections=not args.count_small_detections, distance_edges=args.by_distance,
        bootstrap=args.bootstrap, seed=args.seed, interval=args.interval, compare_pred_labels=args.compare_pred_labels,
        gap_to_pred_labels=args.gap_to_pred_labels, missing_as_empty=args.missing_as_empty,
    )
    try:
        _check_outputs(args)
        outcome = run(config)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(outcome.table)
    _print_written(outcome)
    return 0


def _print_written(outcome: LabelEvalRun) -> None:
    """Where the JSON and the plots went, a line each."""
    if outcome.json_path:
        print(f"JSON: {outcome.json_path}")
    for path in outcome.plot_paths:
        print(f"plot: {path}")


def _check_outputs(args: argparse.Namespace, out: Path | None = None) -> None:
    """--json, --plots and (detect mode) --out, before any work: writable, and not over an input (a --json
    named as a label file used to replace it)."""
    inputs = {"--gt-labels": args.gt_labels, "--pred-labels": args.pred_labels,
              "--compare-pred-labels": args.compare_pred_labels, "--gap-to-pred-labels": args.gap_to_pred_labels,
              "--split-file": args.split_file,
              "--depth-dir": args.depth_dir, "--data": args.data, "--models": args.models}
    for path, flag, directory in ((args.json, "--json", False), (args.plots, "--plots", True),
                                  (out, "--out", True)):
        if path is not None:
            check_output(path, flag, directory=directory)
            check_not_input(path, flag, inputs)
    if out is not None:
        check_output(out / "data", "--out", directory=True)  # where the result files go


def _check_detection_inputs(args: argparse.Namespace, frames: list[str] | None, first: int | None, out: Path) -> None:
    """What the evaluation after the detector reads, before the detector runs."""
    if not args.data.is_dir():
        raise InputError(f"--data {args.data}: directory not found")
    if not (args.data / "label_2").is_dir():
        raise InputError(f"--data {args.data}: no label_2/ (the ground truth to evaluate the detections against)")
    scored = ground_truth_frames(args.data / "label_2", frames)
    if frames is None and first is None:  # every scan is run and every label scored: each needs the other
        scans = frame_ids(args.data)
        unlabelled = [fid for fid in scans if not (args.data / "label_2" / f"{fid}.txt").is_file()]
        if unlabelled:
            more = f" (and {len(unlabelled) - 1} more)" if len(unlabelled) > 1 else ""
            raise InputError(f"--data {args.data}: frame {unlabelled[0]}{more} has no ground truth "
                             f"(label_2/{unlabelled[0]}.txt), so its cars could not be scored; give --split-file or "
                             "--frames to leave it out")
        unscanned = sorted({p.stem for p in (args.data / "label_2").glob("*.txt")} - set(scans))
        if unscanned:
            more = f" (and {len(unscanned) - 1} more)" if len(unscanned) > 1 else ""
            raise InputError(f"--data {args.data}: label_2/{unscanned[0]}.txt{more} has no scan "
                             f"(velodyne/{unscanned[0]}.bin), so its cars would count as missed; give --split-file or "
                             "--frames to leave it out")
    # Parsed now, not after the detector's run: one broken label file would otherwise cost the whole table.
    check_ground_truth(args.data / "label_2", scored[:first], progress=show_progress(args.no_progress))
    _check_compared(args.compare_pred_labels, args.gap_to_pred_labels)
    for flag, folder in (("--compare-pred-labels", args.compare_pred_labels),
                         ("--gap-to-pred-labels", args.gap_to_pred_labels)):
        if folder is not None and (out / "data").resolve() == folder.resolve():
            raise InputError(f"--out {out}: the detector would overwrite the results of {flag} {folder}, which it is "
                             "compared with")


def _main_run(parser: argparse.ArgumentParser, args: argparse.Namespace, split_file: Path | None,
              first: int | None) -> int:
    """The dataset modes: run the networks, then evaluate."""
    from pipeline.model_files import ModelFileError

    _require_run_flags(parser, args)
    # By default a folder per model and input: one shared by every model let a second model's run replace the
    # first's result files without a word.
    out = None if args.depth else args.out or default_out(args.models, args.input)
    try:
        _check_outputs(args, out)
        frames = read_split_file(split_file) if split_file else None
        if args.depth_dir is not None and not args.depth_dir.is_dir():  # both modes read it
            raise InputError(f"--depth-dir {args.depth_dir}: directory not found")
        if args.depth:
            _main_depth(args, frames, first)
            return 0
        detection, outcome = _detect_and_evaluate(args, out, frames, split_file, first)
    except (InputError, ModelFileError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return _print_detection(args, detection, outcome)


def _require_run_flags(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """parser.error (exit 2) without --data and --models, or without --input outside --depth."""
    if args.data is None or args.models is None:
        parser.error("--data DIR and --models DIR are both required to run the models")
    if not args.depth and args.input is None:
        parser.error("--input lidar64|lidar16|lidar16+camera is required with --data and --models")


# A figure per band of the cars' depth (evaluation.depth_metrics.CAR_BANDS_M): {band: {figure: value, "cars": n}}.
_CarBands = dict[str, dict[str, float]]


def _main_depth(args: argparse.Namespace, frames: list[str] | None, first: int | None) -> None:
    """--depth: depth completion measured and printed, its pictures drawn (--plots) and its JSON written (--json)."""
    from evaluation.harness import run_depth

    beams = 16 if args.emulate_beams is None else args.emulate_beams  # 0: a 16-line sensor's own, as stored
    outcome = run_depth(args.data, args.models, frames, beams=beams, provider=args.provider,
                        progress=show_progress(args.no_progress), pictures=args.plots, depth_dir=args.depth_dir,
                        first=first)
    cars, in_box, stray = _car_bands(outcome)
    _print_depth(outcome, cars, in_box, stray)
    if args.plots:
        _depth_pictures(args, outcome)
    if args.json:
        _write_json(args.json, _depth_document(args, outcome, cars, in_box, stray))


def _car_bands(outcome: DepthRun) -> tuple[_CarBands, _CarBands, _CarBands]:
    """The moderate cars' figures by their depth: median |error| on their pixels, the share of those landing in
    their BEV box, and the share of the other pixels of their 2D box landing there too (empty without cars)."""
    from evaluation.depth_metrics import car_errors_by_band, car_shares_by_band

    cars = car_errors_by_band(outcome.car_errors) if outcome.car_errors else {}
    in_box = car_shares_by_band(outcome.car_in_box) if outcome.car_in_box else {}
    stray = car_shares_by_band(outcome.car_stray) if outcome.car_stray else {}
    return cars, in_box, stray


def _print_depth(outcome: DepthRun, cars: _CarBands, in_box: _CarBands, stray: _CarBands) -> None:
    """The depth metrics, a line each: what was run, the means, by ground-truth depth, and the cars' bands."""
    from evaluation.depth_metrics import CAR_BOX_MARGIN_M

    m = outcome.mean
    print(f"depth completion on {len(outcome.per_frame)} frame(s) ({outcome.layout}; input: {outcome.input})")
    print(f"RMSE {m.rmse_mm:.1f} mm   MAE {m.mae_mm:.1f} mm   iRMSE {m.irmse_per_km:.2f} 1/km   "
          f"iMAE {m.imae_per_km:.2f} 1/km   ({m.n_pixels} pixels)")
    print("median |error| by ground-truth depth: "
          + ", ".join(f"{band} m {mm:.0f} mm" for band, mm in m.median_abs_mm_by_band.items()))
    if cars:
        print("median |error| on the pixels of moderate cars, by the car's depth: "
              + ", ".join(f"{band} m {c['median_mm']:.0f} mm ({c['cars']} cars)" if c["cars"] else
                          f"{band} m no cars" for band, c in cars.items()))
    if in_box:
        print(f"share of those pixels whose point lands in the car's BEV box (grown by {CAR_BOX_MARGIN_M} m), "
              "mean over cars: "
              + ", ".join(f"{band} m {c['mean_share']:.2f}" if c["cars"] else f"{band} m no cars"
                          for band, c in in_box.items()))
    if stray:
        print("share of the other pixels of each car's 2D box (road, background) whose point lands in that "
              "box too, mean over cars: "
              + ", ".join(f"{band} m {c['mean_share']:.3f}" if c["cars"] else f"{band} m no cars"
                          for band, c in stray.items()))


def _depth_pictures(args: argparse.Namespace, outcome: DepthRun) -> None:
    """Where run_depth put the per-frame pictures, and car_depth.png (each car's error and share against its
    distance) drawn when there are cars."""
    from evaluation.depth_metrics import CAR_BOX_MARGIN_M

    print(f"pictures (camera, prediction, ground truth, error): {args.plots}/depth_<id>.png")
    if outcome.car_errors:
        n = len(outcome.per_frame)
        depth_from = f"depth from {args.depth_dir} (not the depth network)" if args.depth_dir else args.models
        title = (f"depth on the moderate cars, {n} frame{'' if n == 1 else 's'}\n"
                 f"{depth_from} ({outcome.input}) on {args.data}")
        picture = plot_car_depth(outcome.car_errors, outcome.car_in_box, args.plots / "car_depth.png",
                                 title, CAR_BOX_MARGIN_M)
        print(f"plot (each car's error and share on the car against its distance): {picture}")


def _depth_document(args: argparse.Namespace, outcome: DepthRun, cars: _CarBands, in_box: _CarBands,
                    stray: _CarBands) -> dict[str, Any]:
    """--depth's JSON document: what was run, on what input, and every figure printed."""
    m = outcome.mean
    # A band without cars has no figure: null, not NaN (which strict JSON parsers refuse; _write_json's job).
    return {
        "run": {"data": str(args.data), "models": str(args.models),
                "depth_dir": None if args.depth_dir is None else str(args.depth_dir)},
        "layout": outcome.layout, "input": outcome.input, "frames": len(outcome.per_frame),
        "depth": {"rmse_mm": m.rmse_mm, "mae_mm": m.mae_mm, "irmse_per_km": m.irmse_per_km,
                  "imae_per_km": m.imae_per_km, "pixels": m.n_pixels,
                  "median_abs_mm_by_band": m.median_abs_mm_by_band,
                  "car_median_abs_mm_by_band": cars,
                  "car_points_in_box_by_band": in_box,
                  "car_stray_points_in_box_by_band": stray},
    }


def _detect_and_evaluate(args: argparse.Namespace, out: Path, frames: list[str] | None, split_file: Path | None,
                         first: int | None) -> tuple[DetectionRun, LabelEvalRun]:
    """--data --input: what the evaluation reads checked, the detector run into ``out``, its results evaluated."""
    from evaluation.harness import run_detection

    _check_detection_inputs(args, frames, first, out)
    if first is not None:  # the first N ground-truth frames: the ones the evaluation below takes
        frames = first_frames(ground_truth_frames(args.data / "label_2", frames), first)
    detection = run_detection(args.data, args.models, args.input, out, frames, args.provider,
                              progress=show_progress(args.no_progress), score_threshold=args.score_threshold,
                              depth_dir=args.depth_dir, mirror_tta=args.mirror_tta, beams=args.emulate_beams)
    outcome = run(LabelEvalConfig(
        gt_labels=args.data / "label_2", pred_labels=detection.results, split_file=split_file, first_frames=first,
        json_path=args.json, plots_dir=args.plots, progress=show_progress(args.no_progress),
        ignore_small_detections=not args.count_small_detections, distance_edges=args.by_distance,
        depth_dir=args.depth_dir, bootstrap=args.bootstrap, seed=args.seed, interval=args.interval,
        compare_pred_labels=args.compare_pred_labels, gap_to_pred_labels=args.gap_to_pred_labels,
        missing_as_empty=bool(detection.skipped), detector=_detector_run(args),
        source=f"{args.models} ({args.input}) on {args.data}",
    ))
    return detection, outcome


def _detector_run(args: argparse.Namespace) -> dict[str, Any]:
    """What made the result files, for the JSON's ``run``: the data, the models (and their digest) and the flags."""
    return {"data": str(args.data), "models": str(args.models),
            "model_id": load_manifest_with_digest(args.models)[1], "input": args.input,
            "score_threshold": args.score_threshold, "mirror_tta": args.mirror_tta,
            **({} if args.emulate_beams is None else {"emulate_beams": args.emulate_beams}),
            "provider": args.provider or "best available"}


def _print_detection(args: argparse.Namespace, detection: DetectionRun, outcome: LabelEvalRun) -> int:
    """What ran on what, the table and the files written; exit code 1 when frames were skipped, else 0."""
    source = f", depth from {args.depth_dir} instead of the depth network" if args.depth_dir else ""
    source += ", PIXOR with mirror test-time augmentation" if args.mirror_tta else ""
    print(f"{args.input} on {args.data} ({outcome.result.n_frames} frames{source}), results in {detection.results}")
    print(outcome.table)
    _print_written(outcome)
    if detection.skipped:  # the table is then not the model's score on this data: say so, and fail
        print(f"error: {skipped_summary(list(detection.skipped), 'frame')}; the table counts their cars as missed",
              file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
