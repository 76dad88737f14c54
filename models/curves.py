"""A training run's curves as one picture: ``python -m models.curves RUN_DIR [--out FILE]``.

``models.train`` writes ``RUN_DIR/curves.png`` after every epoch, drawn from the run's own ``log.jsonl`` (so a
resumed run's picture holds all its epochs): the training and validation loss per epoch with the learning rate
on a second axis, the validation metrics on their own axes (depth: RMSE and MAE; detector and joint: BEV AP at
IoU 0.7 and 0.5, moderate), and the epoch the run keeps as best (its ``depth.pt`` / ``pixor.pt``) marked on both.
This command draws it again, say for a run stopped between its log line and its picture, or into another file.

matplotlib comes with the ``train`` extra; without it a run trains on and says once that it draws no picture.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from pipeline.errors import InputError
from pipeline.presets import Preset

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

log = logging.getLogger(__name__)
CURVES_FILE = "curves.png"
LOG_FILE = "log.jsonl"
BEST_COLOUR = "#d62728"  # the best epoch's mark: no curve is drawn in it
# The validation metrics each task logs, with their labels and colours.
METRICS = {
    "depth": (("rmse_mm", "RMSE (mm)", "#2ca02c"), ("mae_mm", "MAE (mm)", "#9467bd")),
    "detector": (("bev_ap_0.7_moderate", "BEV AP IoU 0.7 moderate", "#2ca02c"),
                 ("bev_ap_0.5_moderate", "BEV AP IoU 0.5 moderate", "#9467bd")),
}
MARKERS = ("o-", "^-")  # two metrics that coincide (AP 0 at both IoUs early on) still show as two
NETWORKS = {"depth": "depth net", "detector": "PIXOR", "joint": "depth net + PIXOR (joint)"}
_missing_warned = False  # the missing-matplotlib line is said once per process, not once per epoch


@dataclass(frozen=True)
class RunInfo:
    """What the picture's title says of the run: its task, preset and input."""

    task: str  # depth | detector | joint
    preset: str
    input_mode: str | None = "lidar16"  # the detector's --input; None: not known (a folder without state.pt)
    emulate_beams: int = 16  # the lines its scans are thinned to; 0: as stored


def input_label(task: str, input_mode: str | None, emulate_beams: int) -> str:
    """The run's input in words: the scans it reads (thinned to N lines or as stored) and the camera's part."""
    if input_mode is None:
        return "unknown"
    lines = f"{emulate_beams}-line scans" if emulate_beams else "scans as stored"
    if task == "depth":
        return f"image + {lines}"
    if task == "joint":
        return f"pseudo points from image + {lines}, with the scans"
    if input_mode == "lidar64":
        return "lidar64 (scans as stored)"
    if input_mode == "pseudo":
        return f"pseudo (cached depth maps' points + {lines})"
    return f"{input_mode} ({lines})"


def run_description(info: RunInfo, preset: Preset) -> str:
    """One line naming the preset, its BEV grid (nz × ny × nx, ranges, cells) and the input: ``models.train``'s
    first log line, so a run with the wrong preset is seen before hours are spent on it. ``preset``: the one the
    run trains (a registered one or a preset file's, which no name alone would find again)."""
    g = preset.bev
    h, w = preset.depth.input_hw
    depth = f", depth net input {h} × {w}" if info.task in ("depth", "joint") else ""
    return (f"{info.task}: preset {preset.name}, BEV grid {g.nz} × {g.ny} × {g.nx} (nz × ny × nx), "
            f"x {g.x_min:g}…{g.x_max:g} m, y {g.y_min:g}…{g.y_max:g} m, z {g.z_min:g}…{g.z_max:g} m, "
            f"cell {g.cell:g} m (z {g.z_cell:g} m), {g.channels} channels{depth}; "
            f"input {input_label(info.task, info.input_mode, info.emulate_beams)}")


def read_log(path: Path) -> list[dict]:
    """The epochs of a run's ``log.jsonl``, in order; InputError naming the file and line of a bad one."""
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise InputError(f"{path}: cannot read it ({exc.strerror or exc})") from None
    history = []
    for number, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except json.JSONDecodeError as exc:
            raise InputError(f"{path}, line {number}: not JSON (column {exc.colno}: {exc.msg})") from None
        if not isinstance(record, dict) or not isinstance(record.get("epoch"), int):
            raise InputError(f"{path}, line {number}: not an epoch's record (no integer 'epoch')")
        history.append(record)
    return history


def best_epoch(task: str, history: list[dict]) -> int | None:
    """The epoch whose weights the run keeps, as models.train chooses it: by its selection_criterion (depth: the
    validation loss; detector and joint: minus the mean BEV AP at IoU 0.7 and 0.5, moderate), a new best only
    when strictly lower, so of tied epochs the first is kept (and a NaN never is); None if no epoch was."""
    # The run's own rule, not a copy (imported here: models.train imports this module).
    from models.train import selection_criterion

    best, chosen = math.inf, None
    for record in history:
        try:
            value = selection_criterion(task, record)
        except (KeyError, TypeError):  # a line without the metric (another version's log): it cannot be the kept one
            continue
        if value < best:
            best, chosen = value, record["epoch"]
    return chosen


def task_of(history: list[dict]) -> str:
    """depth or detector, from what the log's validation recorded (a joint run logs the detector's metrics)."""
    return "depth" if history and "rmse_mm" in history[0] else "detector"


def _series(history: list[dict], key: str) -> tuple[list[int], list[float]]:
    """Epochs and values of ``key`` (NaN where an epoch lacks it: the line breaks there, the count stays)."""
    return ([r["epoch"] for r in history],
            [float(r[key]) if isinstance(r.get(key), (int, float)) else math.nan for r in history])


def _positive_span(values: list[float]) -> bool:
    """Whether values are all positive and span more than 10×: then a log axis shows them better."""
    finite = [v for v in values if math.isfinite(v)]
    return bool(finite) and min(finite) > 0 and max(finite) > 10 * min(finite)


def _draw_losses(ax: Axes, history: list[dict]) -> None:
    """Training and validation loss per epoch, the learning rate on a second axis."""
    epochs, train = _series(history, "train_loss")
    _, val = _series(history, "val_loss")
    # Above the best epoch's line (zorder 2), which hid a one-epoch run's validation loss.
    ax.plot(epochs, train, "o-", color="#1f77b4", label="training loss (epoch mean)", gid="train_loss", zorder=3)
    ax.plot(epochs, val, "s-", color="#ff7f0e", label="validation loss", gid="val_loss", zorder=3)
    if _positive_span(train + val):
        ax.set_yscale("log")
    ax.set_ylabel("loss")
    ax.set_title("loss per epoch, learning rate (right)", fontsize=9, loc="left")
    rate = ax.twinx()
    _, lr = _series(history, "lr")
    # The rate an epoch ran at, held across it: the schedule's halvings show as steps; a marker at each epoch, or
    # a one-epoch run's rate (no step to draw) would not show at all.
    rate.plot(epochs, lr, "d--", drawstyle="steps-mid", color="0.45", alpha=0.8, markersize=5,
              label="learning rate", gid="lr")
    if all(v > 0 for v in lr if math.isfinite(v)) and any(math.isfinite(v) for v in lr):
        rate.set_yscale("log")
    rate.set_ylabel("learning rate", color="0.35")
    handles = ax.get_legend_handles_labels()
    more = rate.get_legend_handles_labels()
    ax.legend(handles[0] + more[0], handles[1] + more[1], loc="best", fontsize=8)


def _draw_metrics(ax: Axes, task: str, history: list[dict]) -> None:
    """The validation metrics the task logs, on their own axes."""
    for (key, label, colour), style in zip(METRICS["depth" if task == "depth" else "detector"], MARKERS):
        epochs, values = _series(history, key)
        ax.plot(epochs, values, style, color=colour, label=label, gid=key, zorder=3)  # over the best line
    if task == "depth":
        ax.set_ylabel("validation error (mm)")
    else:
        ax.set_ylabel("BEV AP (%, R40)")
        # AP's zero is meaningful: the axis starts there, a little below so an AP of 0 shows above the frame.
        values = [v for key, _, _ in METRICS["detector"] for v in _series(history, key)[1] if math.isfinite(v)]
        top = max([1.0, *values]) * 1.08
        ax.set_ylim(-0.03 * top, top)
    ax.set_xlabel("epoch")
    ax.set_title("validation", fontsize=9, loc="left")


def _mark_best(axes: list[Axes], task: str, best: int | None) -> None:
    """A vertical line at the kept epoch on every panel, saying how it was chosen."""
    if best is None:
        return
    rule = "lowest validation loss" if task == "depth" else "highest mean BEV AP 0.7/0.5 moderate"
    for ax in axes:
        ax.axvline(best, color=BEST_COLOUR, linestyle="--", linewidth=1.5, gid="best",
                   label=f"best: epoch {best} ({rule}; of ties the first)" if ax is axes[-1] else None)


def draw(history: list[dict], info: RunInfo, run_dir: Path) -> Figure:
    """The run's picture as a matplotlib Figure (no pyplot: nothing global, safe in any thread)."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    figure = Figure(figsize=(10, 7.5), dpi=100, layout="constrained")
    top, bottom = figure.subplots(2, 1, sharex=True)
    task = info.task
    best = best_epoch(task, history)
    _draw_losses(top, history)
    _draw_metrics(bottom, task, history)
    _mark_best([top, bottom], task, best)
    bottom.legend(loc="best", fontsize=8)  # after the best line, which it lists
    # Whole epochs only, a single one too (without min_n_ticks=1 a one-epoch run's axis read 0.5, 0.6, … 1.5).
    bottom.xaxis.set_major_locator(MaxNLocator(integer=True, min_n_ticks=1))
    if history:
        first, last = history[0]["epoch"], history[-1]["epoch"]
        bottom.set_xlim(first - 0.5, last + 0.5)
    for ax in (top, bottom):
        ax.grid(alpha=0.3)
    kept = f"best epoch {best}" if best is not None else "no best epoch yet"
    figure.suptitle(f"{NETWORKS.get(info.task, info.task)} · preset {info.preset} · input "
                    f"{input_label(info.task, info.input_mode, info.emulate_beams)}\n"
                    f"{run_dir} · {len(history)} epoch(s), {kept}", fontsize=10)
    return figure


def save_atomic_png(figure: Figure, path: Path) -> None:
    """Write the picture whole or not at all: into ``NAME.tmp.png`` beside it, then renamed over it, so a viewer
    that reloads the file never reads half of one."""
    tmp = path.with_name(f"{path.stem}.tmp{path.suffix}")
    try:
        figure.savefig(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_curves(run_dir: Path, info: RunInfo, out: Path | None = None, history: list[dict] | None = None) -> Path:
    """Draw ``run_dir``'s log (``history`` when already read) into ``out`` (default ``RUN_DIR/curves.png``);
    returns the file written."""
    history = read_log(run_dir / LOG_FILE) if history is None else history
    out = out or run_dir / CURVES_FILE
    out.parent.mkdir(parents=True, exist_ok=True)
    save_atomic_png(draw(history, info, run_dir), out)
    return out


def after_epoch(run_dir: Path, info: RunInfo) -> None:
    """models.train's call at each epoch's end: the picture redrawn, and nothing a picture could do stops the
    run (no matplotlib, or one that cannot load: one warning line, once; a picture that cannot be written: a
    warning line)."""
    global _missing_warned
    try:
        write_curves(run_dir, info)
    except ImportError as exc:
        if not _missing_warned:
            _missing_warned = True
            log.warning("%s: not drawn, matplotlib cannot be imported (%s; it comes with the train extra: "
                        "pip install -e '.[train]'); the run trains on", run_dir / CURVES_FILE, exc)
    except Exception as exc:  # noqa: BLE001 - a side product: no fault of the picture's may end hours of training
        log.warning("%s: not drawn (%s: %s); the run trains on", run_dir / CURVES_FILE, type(exc).__name__, exc)


def recorded_info(run_dir: Path, history: list[dict]) -> RunInfo:
    """The run's task, preset and input from its ``state.pt`` (the flags it was started with); without one,
    the task the log's metrics show and an unknown preset."""
    state_path = run_dir / "state.pt"
    if state_path.is_file():
        from models.run_checks import load_state

        config = load_state(state_path).get("config")
        if not isinstance(config, dict) or not all(isinstance(config.get(key), str) for key in ("task", "preset")):
            raise InputError(f"{state_path}: no run configuration with its task and preset (not a state models.train "
                             "wrote?)")
        beams = config.get("emulate_beams", 16)
        # The preset's name, as models.train titles the picture: --preset may have been a file's path. A run
        # started before preset_config was recorded names it as --preset did.
        started = config.get("preset_config")
        name = started.get("name") if isinstance(started, dict) else None
        return RunInfo(config["task"], name if isinstance(name, str) and name else config["preset"],
                       config.get("input_mode", "lidar16"), beams if isinstance(beams, int) else 16)
    return RunInfo(task_of(history), "unknown (no state.pt)", input_mode=None)


def main(argv: list[str] | None = None) -> int:
    from pipeline.cli import HelpFormatter, check_figure, examples, quiet_interrupt

    parser = argparse.ArgumentParser(
        allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
        prog="python -m models.curves", description=__doc__.split("\n\n")[0].split(": ", 1)[0] + ": draw it again.",
        epilog=__doc__.split("\n\n", 1)[1] + "\n" + examples("python -m models.curves runs/depth",
                                                             "python -m models.curves runs/depth --out depth.png"),
        formatter_class=HelpFormatter)
    parser.add_argument("run_dir", type=Path, metavar="RUN_DIR", help="a models.train run folder (its log.jsonl)")
    parser.add_argument("--out", type=Path, metavar="FILE", help="the picture (default RUN_DIR/curves.png)")
    args = parser.parse_args(argv)

    @quiet_interrupt("the picture is written whole or not at all")
    def run() -> int:
        try:
            if not (args.run_dir / LOG_FILE).is_file():
                raise InputError(f"{args.run_dir}: no {LOG_FILE} (not a models.train run folder)")
            check_figure(args.out or args.run_dir / CURVES_FILE, "--out")
            history = read_log(args.run_dir / LOG_FILE)
            written = write_curves(args.run_dir, recorded_info(args.run_dir, history), args.out, history)
        except (InputError, OSError, ValueError, KeyError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        print(f"wrote {written} ({len(history)} epoch(s))")
        return 0

    return run()


if __name__ == "__main__":
    sys.exit(main())
