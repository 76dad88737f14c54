"""Presenting a KITTI evaluation: the paper's AP table, a JSON document and precision-recall plots."""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import Any

import numpy as np

from evaluation.depth_metrics import CAR_BOX_MARGIN_M
from evaluation.kitti_eval import DIFFICULTIES, METHOD_NAMES, BootstrapResult, KittiEvalResult

METRIC_TITLES = {"bev": "BEV", "3d": "3D", "bbox": "2D bbox"}


def format_table(result: KittiEvalResult) -> str:
    """The paper's table, one block per metric (BEV first): AP in percent per overlap threshold."""
    ious = sorted(result.iou_thresholds)  # the paper lists IoU 0.5 before 0.7
    header = "".join(f" | IoU {iou:<4} easy  mod.  hard" for iou in ious)
    lines = [f"{result.class_name} AP (%), {result.n_frames} frames"]
    for metric in sorted(result.metrics, key=("bev", "3d", "bbox").index):
        lines.append(f"{METRIC_TITLES[metric]:<8}{header}")
        for points in ("R40", "R11"):
            cells = "".join(
                " | " + " " * 8 + " ".join(f"{result.ap(metric, iou, d, points):5.2f}" for d in DIFFICULTIES)
                for iou in ious
            )
            lines.append(f"  {points:<6}{cells}")
    return "\n".join(lines)


def to_json(result: KittiEvalResult) -> dict[str, Any]:
    """``{class: {metric: {"0.7": {"R40": [e, m, h], "R11": [...]}}}, "details": ...}``, AP in percent.

    ``details`` holds, per class, metric, threshold and difficulty, the number of
    counted ground-truth boxes, the score thresholds, tp / fp / fn at each, and
    the 41-point interpolated precision (the devkit's stats-file row).
    """
    details: dict[str, Any] = {}
    for c in result.curves:
        details.setdefault(c.metric, {}).setdefault(f"{c.iou_threshold}", {})[c.difficulty] = {
            "num_ground_truth": c.n_ground_truth,
            "score_thresholds": c.thresholds.tolist(),
            "tp": c.tp.tolist(),
            "fp": c.fp.tolist(),
            "fn": c.fn.tolist(),
            "recall": c.recall.tolist(),
            "precision_41": c.precision.tolist(),
        }
    return {
        result.class_name: result.ap_table(),
        "frames": result.n_frames,
        "metrics": list(result.metrics),
        "details": {result.class_name: details},
    }


def _pyplot():
    """matplotlib's pyplot, drawing to files only; a clear error in the runtime install, which has no plotting."""
    try:
        import matplotlib
    except ImportError as exc:  # a dev-only dependency
        raise RuntimeError("plots need matplotlib: pip install -e '.[dev]'") from exc
    matplotlib.use("Agg")  # files only; never needs a display
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: str | Path) -> Path:
    """Lay out, write at the reports' 120 dpi (creating the folder), and close a figure."""
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")  # a long source line in the title is kept whole
    _pyplot().close(fig)
    return path


# One colour per (metric, overlap threshold) in every plot, so BEV @0.7 is the same line in the PR curves and
# in AP by distance. Okabe and Ito's palette: no two of the six within 17 CIELAB units of each other for normal
# vision or simulated deuteranopia, protanopia or tritanopia (matplotlib's tab: colours put 3D and 2D at 7 under
# deuteranopia). BEV in blues, 3D in orange-reds, 2D black and purple; the strict threshold the darker.
SERIES_COLOURS = {("bev", 0.7): "#0072B2", ("bev", 0.5): "#56B4E9", ("3d", 0.7): "#D55E00",
                  ("3d", 0.5): "#E69F00", ("bbox", 0.7): "#000000", ("bbox", 0.5): "#CC79A7"}
METRIC_ORDER = ("bev", "3d", "bbox")  # as the table: BEV first
# Beside the colour, a marker per metric, and a width narrowing in drawing order (BEV, 3D, 2D; the loose
# threshold first): curves lying on each other (BEV and 3D at 0.5 under 2D, or 2D at 0.5 under 2D at 0.7, often)
# show as nested stripes and markers, not as the last one drawn. The line style is the model's: solid this one,
# dashed the one it is compared with.
METRIC_MARKERS = {"bev": "o", "3d": "^", "bbox": "s"}
LINE_WIDTHS = (4.6, 3.8, 3.0, 2.3, 1.6, 0.9)  # by (metric, threshold) in drawing order
MARKER_SIZES = (9.5, 8.0, 6.5, 5.2, 4.0, 2.8)
# Below this many counted cars (40 or fewer) the devkit cannot give AP 100: it credits the k-th found car to its
# k-th sampling point, the first of which (recall 0) is not averaged, so AP_40 is at most 100 (n - 1) / 40 (a lone
# car found exactly scores 0).
FEW_CARS = 41


def series_colour(metric: str, iou: float) -> str:
    """The line colour of (metric, overlap threshold) in every plot; grey for a threshold outside the
    protocol's two."""
    return SERIES_COLOURS.get((metric, round(float(iou), 2)), "tab:gray")


def series_style(metric: str, iou: float, compared: bool = False) -> dict[str, Any]:
    """Matplotlib line properties of (metric, threshold): its colour, its metric's marker, its width and marker
    size by drawing order; the compared model's line dashed with hollow markers."""
    rank = len(LINE_WIDTHS) - 1  # an unknown metric: the thinnest
    if metric in METRIC_ORDER:
        rank = 2 * METRIC_ORDER.index(metric) + (0 if round(float(iou), 2) < 0.7 else 1)
    return {"color": series_colour(metric, iou), "marker": METRIC_MARKERS.get(metric, "o"),
            "linewidth": LINE_WIDTHS[rank], "markersize": MARKER_SIZES[rank],
            "linestyle": "--" if compared else "-", "markerfacecolor": "white" if compared else None}


def cars(n: int) -> str:
    """``1 car``, ``22 cars``."""
    return f"{n} car" if n == 1 else f"{n} cars"


def frames(n: int) -> str:
    """``1 frame``, ``5 frames``."""
    return f"{n} frame" if n == 1 else f"{n} frames"


def ap_ceiling(n_ground_truth: int) -> float:
    """The highest AP_40 (%) the devkit can give with ``n_ground_truth`` counted cars: with fewer than 41 it
    samples recall at most at ``n`` of its 40 points, and the first of them (recall 0) is not averaged."""
    return min(100.0, 100.0 * max(n_ground_truth - 1, 0) / 40.0)


def few_cars_note(n_ground_truth: int) -> str:
    """The warning a curve or band with fewer than :data:`FEW_CARS` counted cars carries ("" otherwise)."""
    if n_ground_truth >= FEW_CARS or n_ground_truth == 0:
        return ""
    return (f"n={cars(n_ground_truth)} < {FEW_CARS}: the devkit's 40-point AP is coarse "
            f"(at most {ap_ceiling(n_ground_truth):.1f})")


def _series(result: KittiEvalResult) -> list[tuple[str, float]]:
    """(metric, threshold) in the table's order: BEV, 3D, 2D; the looser threshold first."""
    return [(m, iou) for m in sorted(result.metrics, key=METRIC_ORDER.index) for iou in sorted(result.iou_thresholds)]


def pr_points(result: KittiEvalResult, metric: str, iou: float, difficulty: str) -> tuple[np.ndarray, np.ndarray]:
    """A curve's real points: the recall ``tp / (tp + fn)`` at each of the devkit's K score thresholds and the
    devkit's interpolated precision there (the best at that recall or above), K ≤ 41 pairs. The 41-point
    precision row is indexed by sampling point, not recall: k / 40 is its recall only with 40 or more cars."""
    curve = result.curve(metric, iou, difficulty)
    return curve.recall, curve.precision[: curve.thresholds.size]


def empty_chart_note(result: KittiEvalResult, difficulty: str, models: list[KittiEvalResult]) -> str | None:
    """What a precision-recall chart with no point on any curve says instead (None when a curve has points): no
    car of the class counted at this difficulty, or no detection matched one (no detections, or none on a car).
    The devkit keeps a score threshold only where a detection matches a car, so an empty curve is one of the two."""
    series = [(model, metric, iou) for model in models for metric, iou in _series(model)]
    if any(model.curve(metric, iou, difficulty).thresholds.size for model, metric, iou in series):
        return None
    name = f"{result.class_name.lower()}s"
    if all(model.curve(metric, iou, difficulty).n_ground_truth == 0 for model, metric, iou in series):
        return f"no {name} labelled ({difficulty})"
    return f"no detections on the labelled {name}: every AP is 0"


def pr_figure(result: KittiEvalResult, difficulty: str, source: str | None = None,
              other: KittiEvalResult | None = None, names: tuple[str, str] = ("this", "other")):
    """The figure of one difficulty's precision-recall curves (not saved): a line per (metric, threshold) in
    its style of :func:`series_style` through the curve's real (recall, precision) points, its legend entry
    giving the devkit's AP_40; ``other`` (another model on the same frames) dashed beside it. The title names
    the class, difficulty, frames, counted cars and ``source`` (the model or result files, when the caller
    knows it); with fewer than :data:`FEW_CARS` cars the legend says the AP is coarse."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.4 if other is not None else 6.6, 3.8))
    models = [(result, False)] + ([(other, True)] if other is not None else [])
    counts = {r.curve(m, t, difficulty).n_ground_truth for r, _ in models for m, t in _series(r)}
    shared = counts.pop() if len(counts) == 1 else None  # one count for every curve: said once, in the title
    for model, compared in models:
        for metric, iou in _series(model):
            if compared and metric not in result.metrics:
                continue
            curve = model.curve(metric, iou, difficulty)
            recall, precision = pr_points(model, metric, iou, difficulty)
            who = f"{names[int(compared)]}, " if other is not None else ""
            note = few_cars_note(curve.n_ground_truth) if shared is None else ""
            label = f"{METRIC_TITLES[metric]} @{iou} ({who}AP$_{{40}}$ {curve.ap_r40:.1f}{'; ' + note if note else ''})"
            # steps-pre: the interpolated precision holds from the previous point's recall up to this one's.
            ax.plot(recall, precision, drawstyle="steps-pre", label=label, **series_style(metric, iou, compared))
    cars_text = f", {cars(shared)}" if shared is not None else ""
    title = f"{result.class_name} precision-recall, {difficulty}, {frames(result.n_frames)}{cars_text}"
    ax.set(xlim=(0, 1.03), ylim=(0, 1.05), xlabel="recall tp / (tp + fn) at each of the devkit's score thresholds",
           ylabel="precision (interpolated:\nbest at this recall or above)", title=title + (f"\n{source}" if source else ""))
    ax.grid(alpha=0.3)
    empty = empty_chart_note(result, difficulty, [model for model, _ in models])
    if empty:  # said in the chart, not by an empty axis beside a legend of "AP 0.0"
        ax.text(0.5, 0.5, empty, transform=ax.transAxes, ha="center", va="center", fontsize=10, color="0.3",
                gid="empty_note")
    elif result.metrics:  # beside the axes: inside, it covers the curves of a run with low recall
        legend_title = "metric @IoU (the devkit's AP$_{40}$)"
        if shared is not None and few_cars_note(shared):
            legend_title += "\n" + textwrap.fill(few_cars_note(shared), 36)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), title=legend_title, title_fontsize=7)
    return fig


def plot_pr_curves(result: KittiEvalResult, out_dir: str | Path, source: str | None = None,
                   other: KittiEvalResult | None = None, names: tuple[str, str] = ("this", "other")) -> list[Path]:
    """One PNG per difficulty: the devkit's interpolated precision against recall at its score thresholds.

    Every (metric, overlap threshold) is a line, like the devkit's plots and the
    paper's PR figure; ``other``'s dashed beside it. Returns the written paths.
    """
    plt = _pyplot()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for difficulty in DIFFICULTIES:
        fig = pr_figure(result, difficulty, source, other, names)
        fig.tight_layout()
        path = out_dir / f"pr_{result.class_name.lower()}_{difficulty}.png"
        fig.savefig(path, dpi=120, bbox_inches="tight")
        plt.close(fig)
        paths.append(path)
    return paths


def band_ap(result: KittiEvalResult, metric: str, iou: float, difficulty: str = "moderate",
            points: str = "R40") -> float:
    """A distance band's AP, NaN when the band holds no car of that difficulty: the protocol's 0 there would
    read as "misses every car near", where there is nothing to miss."""
    if result.curve(metric, iou, difficulty).n_ground_truth == 0:
        return float("nan")
    return result.ap(metric, iou, difficulty, points)


def format_distance_table(bands: dict[tuple[float, float], KittiEvalResult], name: str | None = None) -> str:
    """AP per distance band at moderate difficulty (R40): one row per band, counted cars beside it ("n/a" in a
    band without cars)."""
    first = next(iter(bands.values()))
    columns = [(m, iou) for m in ("bev", "3d") if m in first.metrics for iou in sorted(first.iou_thresholds)]
    header = "".join(f" | {METRIC_TITLES[m]} {iou}" for m, iou in columns)
    whose = f" of {name}" if name else ""
    lines = [f"{first.class_name} AP (%){whose} by distance (box centre's camera depth z), moderate, R40",
             f"  band (m)    cars{header}"]
    for (low, high), result in bands.items():
        cars = result.curve(columns[0][0], columns[0][1], "moderate").n_ground_truth if columns else 0
        cells = "".join(f" | {_ap_cell(band_ap(result, m, iou), len(METRIC_TITLES[m]) + 4)}" for m, iou in columns)
        lines.append(f"  {low:>4g}–{high:<4g}  {cars:>6}{cells}")
    return "\n".join(lines)


def _ap_cell(ap: float, width: int) -> str:
    return f"{'n/a':>{width}}" if np.isnan(ap) else f"{ap:{width}.1f}"


def distance_json(bands: dict[tuple[float, float], KittiEvalResult]) -> list[dict[str, Any]]:
    """``[{"range_m": [low, high], "num_ground_truth": {difficulty: n}, class: AP table}, …]``; an AP is null
    where the band holds no car of its difficulty."""
    out = []
    for (low, high), result in bands.items():
        metric, iou = result.metrics[0], result.iou_thresholds[0]
        counts = {d: result.curve(metric, iou, d).n_ground_truth for d in DIFFICULTIES}
        table = {m: {f"{t}": {points: [None if np.isnan(ap := band_ap(result, m, t, d, points)) else ap
                                       for d in DIFFICULTIES] for points in ("R40", "R11")}
                     for t in result.iou_thresholds} for m in result.metrics}
        out.append({"range_m": [low, high], "num_ground_truth": counts, result.class_name: table})
    return out


def by_distance_figure(bands: dict[tuple[float, float], KittiEvalResult],
                       other: dict[tuple[float, float], KittiEvalResult] | None = None,
                       names: tuple[str, str] = ("this", "other"), source: str | None = None):
    """The figure of :func:`plot_by_distance` (not saved). A band with cars but fewer than :data:`FEW_CARS` is
    hatched and carries its AP_40 ceiling: there the devkit's 40-point AP reads low (a lone car found exactly
    scores 0)."""
    from matplotlib.patches import Patch

    plt = _pyplot()
    first = next(iter(bands.values()))
    counts = [r.curve(first.metrics[0], first.iou_thresholds[0], "moderate").n_ground_truth for r in bands.values()]
    labels = [f"{low:g}–{high:g}\n{cars(n)}" for (low, high), n in zip(bands, counts)]
    fig, ax = plt.subplots(figsize=(7.8 if other else 6.8, 3.8))
    for metric, iou in [(m, t) for m, t in _series(first) if m in ("bev", "3d")]:
        suffix = f" ({names[0]})" if other else ""
        # A band without cars has no AP: NaN leaves a gap in the line, not a point at 0.
        ax.plot(labels, [band_ap(r, metric, iou) for r in bands.values()], label=f"{METRIC_TITLES[metric]} @{iou}{suffix}",
                **series_style(metric, iou))
        if other and metric in next(iter(other.values())).metrics:
            ax.plot(labels, [band_ap(r, metric, iou) for r in other.values()],
                    label=f"{METRIC_TITLES[metric]} @{iou} ({names[1]})", **series_style(metric, iou, compared=True))
    handles, _ = ax.get_legend_handles_labels()
    few = [(i, n) for i, n in enumerate(counts) if few_cars_note(n)]
    for i, n in few:
        ax.axvspan(i - 0.45, i + 0.45, facecolor="none", edgecolor="0.75", hatch="//", linewidth=0, zorder=0)
        ax.hlines(ap_ceiling(n), i - 0.45, i + 0.45, colors="0.4", linestyles=":", linewidth=1.2, zorder=1)
        ax.text(i, 103, f"n={n} < {FEW_CARS}:\nAP$_{{40}}$ ≤ {ap_ceiling(n):.1f}", ha="center", va="top", fontsize=7,
                bbox={"facecolor": "white", "edgecolor": "0.6", "boxstyle": "round,pad=0.2"})
    if few:
        handles.append(Patch(facecolor="none", edgecolor="0.75", hatch="//",
                             label=f"< {FEW_CARS} cars: the devkit's\n40-point AP is coarse;\ndotted: its ceiling"))
    title = f"{first.class_name} AP by distance, {frames(first.n_frames)}"
    ax.set(ylim=(-2, 104), xlim=(-0.5, len(labels) - 0.5), xlabel="distance band (m, camera depth of the box centre)",
           ylabel="AP$_{40}$ (%), moderate", title=title + (f"\n{source}" if source else ""))
    ax.grid(alpha=0.3)
    # Beside the axes, not over the lines.
    ax.legend(handles=handles, fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), title="metric @IoU",
              title_fontsize=7)
    return fig


def plot_by_distance(bands: dict[tuple[float, float], KittiEvalResult], path: str | Path,
                     other: dict[tuple[float, float], KittiEvalResult] | None = None,
                     names: tuple[str, str] = ("this", "other"), source: str | None = None) -> Path:
    """One PNG: moderate AP (R40) against distance band, a line per (metric, overlap threshold) in the PR
    curves' colours; ``other`` (another model on the same bands) in dashed lines of the same colours."""
    return _save(by_distance_figure(bands, other, names, source), path)


def car_depth_figure(car_errors: list[tuple[float, float]], car_in_box: list[tuple[float, float]],
                     title: str = "depth on the moderate cars", box_margin_m: float = CAR_BOX_MARGIN_M):
    """The figure of :func:`plot_car_depth` (not saved): its title is ``title``'s first line (the caller names
    the frames), the count of cars drawn, then ``title``'s other lines (the model and data)."""
    plt = _pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(9.0, 3.8))
    if car_errors:
        z, mm = np.array(car_errors).T
        left.scatter(z, np.maximum(mm, 1.0), s=8, alpha=0.6)  # 0 mm (exact depth) drawn at 1 mm on the log axis
    left.set(yscale="log", xlabel="car depth z (m)", ylabel="median |error| on its pixels (mm)")
    if car_in_box:
        z, share = np.array(car_in_box).T
        right.scatter(z, share, s=8, alpha=0.6)
    right.set(ylim=(-0.02, 1.02), xlabel="car depth z (m)",
              ylabel=f"share of its pixels whose point lands\nin its BEV box grown by {box_margin_m:g} m")
    for ax in (left, right):
        ax.grid(alpha=0.3)
    head, _, rest = title.partition("\n")
    fig.suptitle(f"{head}, {cars(len(car_errors))}" + (f"\n{rest}" if rest else ""))
    return fig


def plot_car_depth(car_errors: list[tuple[float, float]], car_in_box: list[tuple[float, float]],
                   path: str | Path, title: str = "depth on the moderate cars",
                   box_margin_m: float = CAR_BOX_MARGIN_M) -> Path:
    """One PNG, a dot per car against its distance: the median |error| over its pixels (left, log scale)
    and the share of them whose point lands in its BEV box grown by ``box_margin_m`` (right)."""
    return _save(car_depth_figure(car_errors, car_in_box, title, box_margin_m), path)


def format_spread(result: KittiEvalResult, spread: BootstrapResult, other: KittiEvalResult | None = None,
                  other_name: str = "other", level: float = 0.95) -> str:
    """R40 AP with its bootstrap interval, and with ``other``: the paired difference this − other."""
    n = spread.ap.shape[1]
    title = (f"{result.class_name} AP (%, R40) with its {level:.0%} {METHOD_NAMES[spread.method]} interval over {n} "
             "bootstrap draws of the "
             f"{result.n_frames} frames (seed {spread.seed})")
    lines = [title]

    def row(value, interval, sign: str = "") -> str:
        return "  ".join(f"{d} {value(d):{sign}6.1f} [{interval(d)[0]:5.1f}, {interval(d)[1]:5.1f}]"
                         for d in DIFFICULTIES)

    for metric in spread.metrics:
        for iou in sorted(spread.iou_thresholds):
            lines.append(f"  {METRIC_TITLES[metric]:<7} @{iou:<4} " + row(
                lambda d, m=metric, t=iou: result.ap(m, t, d),
                lambda d, m=metric, t=iou: spread.interval(m, t, d, 0, level)))
    if other is not None and spread.ap.shape[0] > 1:
        lines.append(f"this − {other_name} (paired: the same draws for both)")
        for metric in spread.metrics:
            for iou in sorted(spread.iou_thresholds):
                lines.append(f"  {METRIC_TITLES[metric]:<7} @{iou:<4} " + row(
                    lambda d, m=metric, t=iou: result.ap(m, t, d) - other.ap(m, t, d),
                    lambda d, m=metric, t=iou: spread.difference_interval(m, t, d, 0, 1, level), sign="+"))
    return "\n".join(lines)


def format_difference(result: KittiEvalResult, other: KittiEvalResult, other_name: str = "other") -> str:
    """AP (R40) of this evaluation minus ``other``'s, per metric both have, overlap threshold and difficulty."""
    lines = [f"{result.class_name} AP (%, R40): this − {other_name}"]
    for metric in [m for m in result.metrics if m in other.metrics]:
        for iou in sorted(result.iou_thresholds):
            cells = "  ".join(f"{d} {result.ap(metric, iou, d) - other.ap(metric, iou, d):+6.1f}" for d in DIFFICULTIES)
            lines.append(f"  {METRIC_TITLES[metric]:<7} @{iou:<4} {cells}")
    return "\n".join(lines)


def spread_json(result: KittiEvalResult, spread: BootstrapResult, other: KittiEvalResult | None = None,
                level: float = 0.95) -> dict[str, Any]:
    """``{"draws", "seed", "level", "interval": {metric: {iou: [[low, high] × 3]}}, "difference": …}``."""
    def table(interval) -> dict[str, dict[str, list[list[float]]]]:
        return {m: {f"{t}": [list(interval(m, t, d)) for d in DIFFICULTIES] for t in spread.iou_thresholds}
                for m in spread.metrics}

    out: dict[str, Any] = {"draws": int(spread.ap.shape[1]), "seed": spread.seed, "level": level,
                           "interval": table(lambda m, t, d: spread.interval(m, t, d, 0, level))}
    if other is not None and spread.ap.shape[0] > 1:
        out["difference"] = {m: {f"{t}": [result.ap(m, t, d) - other.ap(m, t, d) for d in DIFFICULTIES]
                                 for t in spread.iou_thresholds} for m in spread.metrics}
        out["difference_interval"] = table(lambda m, t, d: spread.difference_interval(m, t, d, 0, 1, level))
    return out


def gap_share(middle: KittiEvalResult, low: KittiEvalResult, high: KittiEvalResult, metric: str, iou: float,
              difficulty: str) -> float | None:
    """The share of the gap from ``low`` up to ``high`` that ``middle`` closes (R40 AP; the paper's camera row
    between its 16- and 64-line rows); None where ``high`` is not above ``low``."""
    gap = high.ap(metric, iou, difficulty) - low.ap(metric, iou, difficulty)
    return (middle.ap(metric, iou, difficulty) - low.ap(metric, iou, difficulty)) / gap if gap > 0 else None


def _gap_metrics(middle: KittiEvalResult, low: KittiEvalResult, high: KittiEvalResult) -> list[str]:
    return [m for m in ("bev", "3d") if m in middle.metrics and m in low.metrics and m in high.metrics]


def format_gap(middle: KittiEvalResult, low: KittiEvalResult, high: KittiEvalResult, low_name: str, high_name: str,
               spread: BootstrapResult | None = None, level: float = 0.95) -> str:
    """Per column, the share of the gap from ``low`` up to ``high`` that this evaluation closes; with ``spread``
    (sets: this, low, high) its interval over the bootstrap draws."""
    lines = [f"share of the gap from {low_name} up to {high_name} that this closes (R40; (this − low) / (high − low))"]
    if spread is not None:
        lines[0] += (f", with its {level:.0%} {METHOD_NAMES[spread.method]} interval over the {spread.ap.shape[1]} "
                     "bootstrap draws")
    for metric in _gap_metrics(middle, low, high):
        for iou in sorted(middle.iou_thresholds):
            cells = []
            for d in DIFFICULTIES:
                share = gap_share(middle, low, high, metric, iou, d)
                cell = f"{d} {'n/a':>5}" if share is None else f"{d} {100 * share:4.0f} %"
                if spread is not None and metric in spread.metrics:
                    lo, hi, _ = spread.gap_share_interval(metric, iou, d, 0, 1, 2, level)
                    cell += f" [{100 * lo:4.0f}, {100 * hi:4.0f}]" if not np.isnan(lo) else " [ n/a ]"
                cells.append(cell)
            lines.append(f"  {METRIC_TITLES[metric]:<7} @{iou:<4} " + "  ".join(cells))
    return "\n".join(lines)


def gap_json(middle: KittiEvalResult, low: KittiEvalResult, high: KittiEvalResult,
             spread: BootstrapResult | None = None, level: float = 0.95) -> dict[str, Any]:
    """``{"share": {metric: {iou: [easy, moderate, hard]}}, "interval": …, "draws_used": …}`` (shares as
    fractions, None where there is no gap; the interval only with ``spread``)."""
    metrics = _gap_metrics(middle, low, high)
    out: dict[str, Any] = {"share": {m: {f"{t}": [gap_share(middle, low, high, m, t, d) for d in DIFFICULTIES]
                                         for t in middle.iou_thresholds} for m in metrics}}
    if spread is not None:
        intervals = {m: {f"{t}": [spread.gap_share_interval(m, t, d, 0, 1, 2, level) for d in DIFFICULTIES]
                         for t in spread.iou_thresholds} for m in metrics if m in spread.metrics}
        out["interval"] = {m: {t: [None if np.isnan(lo) else [lo, hi] for lo, hi, _ in cells]
                               for t, cells in by_iou.items()} for m, by_iou in intervals.items()}
        out["draws_used"] = {m: {t: [used for _, _, used in cells] for t, cells in by_iou.items()}
                             for m, by_iou in intervals.items()}
        out["level"] = level
    return out
