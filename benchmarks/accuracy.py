"""KITTI accuracy: evaluate KITTI result files against KITTI labels with the official protocol.

    python benchmarks/accuracy.py --gt-labels DIR --pred-labels DIR [--split-file F]
                                  [--json OUT] [--plots DIR]

prints the paper's table (Car BEV AP at IoU 0.7 and 0.5, easy / moderate / hard,
40- and 11-point; 3D and 2D-box AP when the results carry them), writes every
figure as JSON and one precision-recall PNG per difficulty.

The mode is chosen by flags (no subcommands): ``--gt-labels`` / ``--pred-labels``
evaluate existing result files; running the detector over a dataset first is a
separate mode with its own flags.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import dataclass
from pathlib import Path

from evaluation.frames import load_label_dirs, read_split_file
from evaluation.kitti_eval import DEFAULT_IOU_THRESHOLDS, KittiEvalResult, evaluate
from evaluation.report import format_table, plot_pr_curves, to_json
from pipeline.errors import InputError

log = logging.getLogger("accuracy")


@dataclass(frozen=True)
class LabelEvalConfig:
    """Evaluate result files in ``pred_labels`` against ground truth in ``gt_labels``.

    split_file: frame ids to evaluate (default: every ground-truth file).
    json_path / plots_dir: where to write the JSON document and the PR plots (optional).
    """

    gt_labels: Path
    pred_labels: Path
    split_file: Path | None = None
    json_path: Path | None = None
    plots_dir: Path | None = None
    class_name: str = "Car"
    iou_thresholds: tuple[float, ...] = DEFAULT_IOU_THRESHOLDS
    progress: bool = True


@dataclass(frozen=True)
class LabelEvalRun:
    """What a run made: the evaluation, its table, and the files written."""

    result: KittiEvalResult
    table: str
    missing_predictions: tuple[str, ...]
    json_path: Path | None
    plot_paths: tuple[Path, ...]


def run(config: LabelEvalConfig) -> LabelEvalRun:
    """Load both label directories, evaluate, write the JSON and plots if asked."""
    frame_ids = read_split_file(config.split_file) if config.split_file else None
    labels = load_label_dirs(config.gt_labels, config.pred_labels, frame_ids, progress=config.progress)
    result = evaluate(
        labels.ground_truth, labels.detections, class_name=config.class_name,
        iou_thresholds=config.iou_thresholds, progress=config.progress,
    )
    if config.json_path:
        document = to_json(result)
        document["missing_predictions"] = list(labels.missing_predictions)
        config.json_path.parent.mkdir(parents=True, exist_ok=True)
        config.json_path.write_text(json.dumps(document, indent=1) + "\n", encoding="utf-8")
    plot_paths = tuple(plot_pr_curves(result, config.plots_dir)) if config.plots_dir else ()
    return LabelEvalRun(
        result=result, table=format_table(result), missing_predictions=labels.missing_predictions,
        json_path=config.json_path, plot_paths=plot_paths,
    )


def build_parser() -> argparse.ArgumentParser:
    """Command-line flags; each mode is a flag group."""
    parser = argparse.ArgumentParser(
        description="KITTI object evaluation (official devkit protocol): Car BEV / 3D / 2D-box AP, "
        "R40 and R11, easy / moderate / hard.",
    )
    labels = parser.add_argument_group("evaluate result files")
    labels.add_argument("--gt-labels", type=Path, metavar="DIR", help="KITTI label_2 directory (ground truth)")
    labels.add_argument(
        "--pred-labels", type=Path, metavar="DIR",
        help="KITTI result files <id>.txt (label lines + score); a missing file means no detections",
    )
    labels.add_argument("--split-file", type=Path, metavar="F", help="frame ids to evaluate, one per line")
    output = parser.add_argument_group("output")
    output.add_argument("--json", type=Path, metavar="OUT", help="write every figure as JSON (AP in percent)")
    output.add_argument("--plots", type=Path, metavar="DIR", help="write precision-recall PNGs per difficulty")
    output.add_argument("--no-progress", action="store_true", help="no progress bars")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Parse flags, run, print the table; input errors are printed without a traceback (exit code 2)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.gt_labels is None or args.pred_labels is None:
        parser.error("give --gt-labels DIR and --pred-labels DIR")
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    config = LabelEvalConfig(
        gt_labels=args.gt_labels, pred_labels=args.pred_labels, split_file=args.split_file,
        json_path=args.json, plots_dir=args.plots, progress=not args.no_progress,
    )
    try:
        outcome = run(config)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(outcome.table)
    if outcome.json_path:
        print(f"JSON: {outcome.json_path}")
    for path in outcome.plot_paths:
        print(f"plot: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
