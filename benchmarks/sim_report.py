"""Compare simulated frames with real KITTI frames: points per frame, points on cars vs distance
(64 and 16 lines), car sizes, and a side-by-side picture (image | LiDAR projection | BEV).

    python benchmarks/sim_report.py --sim-data DIR --frames 100 --plot docs/img/sim_vs_kitti.jpg

Prints markdown tables (paste into docs/simulation.md). Without --sim-data it first generates --frames
frames (seed --seed) into a temporary folder, about 1 s a frame, and deletes them afterwards.
The picture needs matplotlib (the dev extras: make setup-dev).
"""

from __future__ import annotations

import argparse
import importlib.util
import itertools
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.beams import emulate_beams
from pipeline.boxes import box_corners_3d, labels_to_boxes, points_in_boxes
from pipeline.calib import Calibration
from pipeline.cli import (
    HelpFormatter,
    as_given,
    check_figure,
    examples,
    non_negative_int,
    positive_int,
    quiet_interrupt,
)
from pipeline.errors import InputError
from pipeline.kitti import Object3D, read_calib, read_image, read_labels, read_velodyne

KITTI_SUBDIRS = ("velodyne", "image_2", "calib", "label_2")
DISTANCE_BINS = (0, 10, 20, 30, 40, 50, 60, 70)
KITTI_CAR_SIZE = {"h": (1.53, 0.14), "w": (1.63, 0.10), "l": (3.88, 0.43)}


@dataclass
class FrameFiles:
    """One frame read from a KITTI-layout folder."""

    name: str
    image: np.ndarray
    points: np.ndarray
    calib: Calibration
    objects: list[Object3D]


@dataclass
class ReportConfig:
    """Inputs: a simulated folder (generated with ``frames``/``seed`` if absent) and the real KITTI folder."""

    kitti: Path
    sim: Path | None = None
    frames: int = 20
    seed: int = 1
    figure: Path | None = None
    progress: bool = True  # the generation's progress bar


def load(folder: Path, limit: int | None = None) -> list[FrameFiles]:
    """Frames of a KITTI-layout folder (sorted by name)."""
    names = sorted(p.stem for p in (folder / "velodyne").glob("*.bin"))[:limit]
    return [FrameFiles(n, read_image(folder / "image_2" / f"{n}.png"),
                       read_velodyne(folder / "velodyne" / f"{n}.bin").points,
                       read_calib(folder / "calib" / f"{n}.txt"),
                       read_labels(folder / "label_2" / f"{n}.txt")) for n in names]


def car_points_by_distance(frames: list[FrameFiles]) -> dict[int, tuple[list[int], list[int]]]:
    """Per distance bin: points inside each labelled car's box with 64 lines and with 16 lines."""
    bins: dict[int, tuple[list[int], list[int]]] = {b: ([], []) for b in DISTANCE_BINS[:-1]}
    for f in frames:
        cars = [o for o in f.objects if o.type == "Car"]
        if not cars:
            continue
        boxes = labels_to_boxes(cars, f.calib)
        sparse = emulate_beams(f.points, beams=16)
        n64 = points_in_boxes(f.points, boxes).sum(axis=0)
        n16 = points_in_boxes(sparse, boxes).sum(axis=0)
        for box, a, b in zip(boxes, n64, n16):
            k = int(np.searchsorted(DISTANCE_BINS, np.hypot(box[0], box[1]), side="right")) - 1
            if 0 <= k < len(DISTANCE_BINS) - 1:
                bins[DISTANCE_BINS[k]][0].append(int(a))
                bins[DISTANCE_BINS[k]][1].append(int(b))
    return bins


def _fmt(values: list[int]) -> str:
    return f"{np.median(values):.0f} ({len(values)})" if values else "–"


def tables(sim: list[FrameFiles], real: list[FrameFiles]) -> str:
    """The report's markdown tables."""
    lines = ["### Points per frame (64-line)", "", "| | frames | median | min | max |", "|---|---|---|---|---|"]
    for label, frames in (("simulated", sim), ("KITTI", real)):
        n = [f.points.shape[0] for f in frames]
        lines.append(f"| {label} | {len(n)} | {np.median(n):,.0f} | {min(n):,} | {max(n):,} |")
    lines += ["", "### Points inside a labelled car's box vs distance: median (cars)", "",
              "| distance (m) | sim 64 | sim 16 | KITTI 64 | KITTI 16 |", "|---|---|---|---|---|"]
    s_bins, r_bins = car_points_by_distance(sim), car_points_by_distance(real)
    for lo, hi in itertools.pairwise(DISTANCE_BINS):
        lines.append(f"| {lo}–{hi} | {_fmt(s_bins[lo][0])} | {_fmt(s_bins[lo][1])} | "
                     f"{_fmt(r_bins[lo][0])} | {_fmt(r_bins[lo][1])} |")
    lines += ["", "### Car sizes (labelled cars), mean ± std in metres", "",
              "| | cars | h | w | l |", "|---|---|---|---|---|"]
    lines.append("| KITTI training set (reference from the issue) | – | " + " | ".join(
        f"{m:.2f} ± {s:.2f}" for m, s in KITTI_CAR_SIZE.values()) + " |")
    for label, frames in (("simulated", sim), ("KITTI samples", real)):
        dims = np.array([o.dimensions for f in frames for o in f.objects if o.type == "Car"]).reshape(-1, 3)
        # No labelled car (a folder of pedestrians only): dashes, as the distance table's empty bins, rather
        # than "nan ± nan" after NumPy's warnings of an empty mean.
        lines.append(f"| {label} | {len(dims)} | " + " | ".join(
            f"{dims[:, k].mean():.2f} ± {dims[:, k].std():.2f}" if len(dims) else "–" for k in range(3)) + " |")
    return "\n".join(lines)


PROJECTION_MAX_DEPTH_M = 80.0  # the depth pictures' range (pipeline.render.render_depth)


def depth_colour_map():
    """pipeline.render's depth colours (near warm, far blue, 0–80 m) as a matplotlib colour map, so the
    projected LiDAR reads as the depth maps of the other tools."""
    from matplotlib.colors import ListedColormap

    from pipeline.render import depth_colours

    return ListedColormap(depth_colours(PROJECTION_MAX_DEPTH_M)[:, ::-1] / 255.0, name="lowres3d_depth")


def figure(rows: list[tuple[str, FrameFiles]], path: Path) -> None:
    """Image, LiDAR projection on the image (colour = depth), and BEV with car boxes, one row per frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = figure_of(rows)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)


# Text at the figure's 80 dpi: matplotlib's default 10 pt came out about 9 pixels high.
FONT_PT = 13


def figure_of(rows: list[tuple[str, FrameFiles]]):
    """The figure of :func:`figure` (not saved): the projection coloured by depth and the BEV by height, each
    with its colour bar; the BEV's axes in metres, forward up, as tall as a row allows (its column was 260 of
    1920 pixels, the cars' outlines lines of a pixel)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with matplotlib.rc_context({"font.size": FONT_PT}):
        fig, axes = plt.subplots(len(rows), 3, figsize=(24, 6.5 * len(rows)), dpi=80, layout="constrained",
                                 gridspec_kw={"width_ratios": [1242 / 375, 1242 / 375, 2.2]})
        _draw_rows(fig, axes, rows)
    # Room between and around the rows: without it the last depth bar's label ran past the figure's foot.
    fig.get_layout_engine().set(h_pad=0.2)
    return fig


def _draw_rows(fig, axes, rows: list[tuple[str, FrameFiles]]) -> None:
    """Each row of :func:`figure_of`: the image, the projected scan, the BEV."""
    for (title, f), ax in zip(rows, np.atleast_2d(axes)):
        h, w = f.image.shape[:2]
        ax[0].imshow(f.image)
        ax[0].set_title(f"{title}: image")
        uv, depth = f.calib.velo_to_image(f.points[:, :3])
        ok = (depth > 1) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        ax[1].imshow((f.image * 0.35).astype(np.uint8))
        projected = ax[1].scatter(uv[ok, 0], uv[ok, 1], c=depth[ok], s=0.3, cmap=depth_colour_map(), vmin=0,
                                  vmax=PROJECTION_MAX_DEPTH_M)
        fig.colorbar(projected, ax=ax[1], orientation="horizontal", shrink=0.5, aspect=40, pad=0.02,
                     label="depth (m), as the depth maps of the other tools")
        ax[1].set_title(f"{title}: 64-line LiDAR projected")
        keep = (f.points[:, 0] > -5) & (f.points[:, 0] < 70) & (np.abs(f.points[:, 1]) < 40)
        heights = ax[2].scatter(-f.points[keep, 1], f.points[keep, 0], s=0.1, c=f.points[keep, 2], cmap="viridis",
                                vmin=-2, vmax=1)
        fig.colorbar(heights, ax=ax[2], shrink=0.8, pad=0.02, label="height z (m)")
        cars = [o for o in f.objects if o.type in ("Car", "Van")]
        for corners in box_corners_3d(labels_to_boxes(cars, f.calib))[:, :4, :2] if cars else []:
            loop = np.vstack([corners, corners[:1]])
            ax[2].plot(-loop[:, 1], loop[:, 0], "-", color="tab:red", lw=2.0)
        ax[2].set_xlim(-40, 40)
        ax[2].set_ylim(-5, 70)
        ax[2].set_aspect("equal")
        ax[2].set(xlabel="right of the sensor (m)", ylabel="ahead of the sensor (m)")
        # Two lines: on one, wider than the panel, it ran into the colour bar's top tick label.
        ax[2].set_title(f"{title}: BEV\nlabelled cars and vans red")
        for a in ax[:2]:
            a.axis("off")


def check_folder(folder: Path, flag: str) -> None:
    """A KITTI-layout folder with at least one frame, or an InputError naming the flag and what is missing."""
    if not folder.is_dir():
        raise InputError(f"{flag} {folder}: not a folder")
    missing = [sub for sub in KITTI_SUBDIRS if not (folder / sub).is_dir()]
    if missing:
        raise InputError(f"{flag} {folder}: not a KITTI-layout folder (no {', '.join(s + '/' for s in missing)} inside)")
    if not any((folder / "velodyne").glob("*.bin")):
        raise InputError(f"{flag} {folder}: no frames (velodyne/ has no .bin file)")


def check_config(config: ReportConfig) -> None:
    """Everything the report needs, checked before any frame is generated or read."""
    check_folder(config.kitti, "--kitti")
    if config.sim is not None:
        check_folder(config.sim, "--sim")
    if config.figure is not None:
        check_figure(config.figure, "--figure")
        try:
            config.figure.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError(f"--figure {config.figure}: cannot create its folder ({exc.strerror})") from exc
        if importlib.util.find_spec("matplotlib") is None:
            raise InputError("--figure: drawing needs matplotlib, which the runtime install leaves out; install "
                             "the dev extras (make setup-dev)")


def run(config: ReportConfig) -> str:
    """Build the tables (and the figure when asked); returns the markdown."""
    check_config(config)
    real = load(config.kitti)
    if config.sim is None:
        from simulation import RunConfig
        from simulation import run as simulate

        with tempfile.TemporaryDirectory(prefix="sim_report_") as tmp:
            simulate(RunConfig(out=Path(tmp), frames=config.frames, seed=config.seed, progress=config.progress))
            sim = load(Path(tmp), config.frames)
    else:
        sim = load(config.sim, config.frames)
    if config.figure is not None:
        real_frame = max(real, key=lambda f: sum(o.type == "Car" for o in f.objects))
        try:
            figure([("simulated " + sim[0].name, sim[0]), ("KITTI " + real_frame.name, real_frame)], config.figure)
        except OSError as exc:
            raise InputError(f"--figure {config.figure}: cannot write it ({exc.strerror or exc})") from exc
    return tables(sim, real)


# Each flag's family name (--data and --plot as in the other commands; --sim-data as models.train's --val-data),
# then this command's old spelling of it, still accepted (a hidden alias).
DATA, SIM_DATA, PLOT = ("--data", "--kitti"), ("--sim-data", "--sim"), ("--plot", "--figure")


@quiet_interrupt("no report was written (--plot is drawn at the end)")
def main(argv: list[str] | None = None) -> int:
    epilog = __doc__.split("\n\n", 1)[1] + "\n" + examples(
        "python benchmarks/sim_report.py --sim-data data/sim/val --frames 100 --plot outputs/sim_vs_kitti.png")
    parser = argparse.ArgumentParser(allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
                                     prog="python benchmarks/sim_report.py", description=__doc__.split("\n\n")[0],
                                     epilog=epilog, formatter_class=HelpFormatter)
    parser.add_argument(*DATA, dest="kitti", type=Path, default=ROOT / "tests" / "data" / "kitti" / "training",
                        metavar="DIR",
                        help="real KITTI folder (image_2, velodyne, calib, label_2; default: the bundled samples)")
    parser.add_argument(*SIM_DATA, dest="sim", type=Path, metavar="DIR",
                        help="simulated folder; generated into a temp dir when omitted")
    parser.add_argument("--frames", type=positive_int, default=20, metavar="N",
                        help="simulated frames to use, or to generate without --sim-data (default 20)")
    parser.add_argument("--seed", type=non_negative_int, default=1, help="seed when generating (default 1)")
    parser.add_argument(*PLOT, dest="figure", type=Path, metavar="FILE",
                        help="write the side-by-side picture here (.png, .jpg, .pdf or .svg; needs matplotlib)")
    parser.add_argument("--no-progress", action="store_true",
                        help="no progress bar while the simulated frames are generated")
    args = parser.parse_args(argv)
    try:
        # Checked here first, so that an error names each flag as the command line spells it (check_config's
        # messages use the old names).
        check_folder(args.kitti, as_given(argv, *DATA))
        if args.sim is not None:
            check_folder(args.sim, as_given(argv, *SIM_DATA))
        if args.figure is not None:
            check_figure(args.figure, as_given(argv, *PLOT))
        print(run(ReportConfig(kitti=args.kitti, sim=args.sim, frames=args.frames, seed=args.seed,
                               # Drawn in a pipe too, as python -m simulation draws it (its own rule).
                               figure=args.figure, progress=not args.no_progress)))
        if args.figure is not None:  # as benchmarks/accuracy.py and latency.py name theirs
            print(f"\nplot: {args.figure}")
    except (ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
