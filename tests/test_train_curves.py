"""models/curves.py: the run folder's curves.png, drawn after every epoch from the run's own log (needs torch:
real tiny training runs), and models.train's first log line naming the preset, its grid and the input."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from models.checkpoint import load_checkpoint
from models.curves import BEST_COLOUR, RunInfo, best_epoch, draw, main, read_log, write_curves
from models.train import TrainConfig, run
from pipeline.presets import get_preset
from tests import test_training

REPO = Path(__file__).resolve().parents[1]
small_sim = test_training.small_sim  # the tiny synthetic frames test_training trains on (module-scoped fixture)
TINY_DEPTH = {"task": "depth", "preset": "tiny", "quick": True, "lr": 1e-3, "progress": False, "max_train_frames": 2,
              "max_val_frames": 1}


def _lines(figure) -> dict[str, list]:
    """The figure's drawn lines by gid (each curve's series), over every panel."""
    found: dict[str, list] = {}
    for ax in figure.axes:
        for line in ax.get_lines():
            if line.get_gid():
                found.setdefault(line.get_gid(), []).append(line)
    return found


def _red_share(image: np.ndarray, column: int, rows: tuple[int, int]) -> float:
    """Share of the rows (top, bottom) in which a pixel within ±1 of ``column`` is the best-epoch red."""
    red = np.array([int(BEST_COLOUR[i:i + 2], 16) for i in (5, 3, 1)])  # BGR, as OpenCV reads it
    band = image[rows[0]:rows[1], column - 1:column + 2].astype(int)
    return float(np.mean((np.abs(band - red).max(axis=2) < 40).any(axis=1)))


def test_a_resumed_runs_picture_holds_all_its_epochs_and_marks_the_kept_one(small_sim, tmp_path, caplog):
    """One epoch whose picture cannot be written (a folder in its place: a warning, the run goes on), then
    --resume to two: the picture the resumed run drew has both logged epochs in every curve, and its red line
    stands at the epoch whose weights depth.pt holds (at that x in the PNG itself)."""
    out = tmp_path / "run"
    (out / "curves.png").mkdir(parents=True)
    first = run(TrainConfig(data=small_sim, out=out, epochs=1, **TINY_DEPTH))
    assert len(first.history) == 1 and "curves.png: not drawn (IsADirectoryError" in caplog.text
    (out / "curves.png").rmdir()
    resumed = run(TrainConfig(data=small_sim, out=out, epochs=2, resume=True, **TINY_DEPTH))
    assert resumed.epochs_before == 1
    history = read_log(out / "log.jsonl")
    assert [r["epoch"] for r in history] == [1, 2]
    assert not list(out.glob("*.tmp*"))  # written under a temporary name, then renamed

    kept = load_checkpoint(out / "depth.pt").metadata["epoch"]
    figure = draw(history, RunInfo("depth", "tiny"), out)
    lines = _lines(figure)
    for gid in ("train_loss", "val_loss", "lr", "rmse_mm", "mae_mm"):
        (line,) = lines[gid]
        assert list(line.get_xdata()) == [1, 2], gid
    np.testing.assert_allclose(lines["val_loss"][0].get_ydata(), [r["val_loss"] for r in history])
    assert {float(x) for line in lines["best"] for x in line.get_xdata()} == {kept}

    # The saved file: the same layout (same size and dpi), so the data's x lands on the same pixel column.
    image = cv2.imread(str(out / "curves.png"))
    assert image.shape[:2] == (750, 1000)
    # … and it is the drawing of the whole log (both epochs), not of the resumed invocation's alone.
    redrawn = write_curves(out, RunInfo("depth", "tiny", "lidar16", 16), tmp_path / "redrawn.png")
    assert np.array_equal(cv2.imread(str(redrawn)), image)
    figure.draw_without_rendering()  # the layout savefig applies (constrained)
    bottom = figure.axes[1]
    top_row, bottom_row = (image.shape[0] - int(v) for v in bottom.bbox.extents[[3, 1]])
    for epoch in (1, 2):
        column = round(float(bottom.transData.transform((epoch, 0))[0]))
        share = _red_share(image, column, (top_row + 3, bottom_row - 3))
        assert share > 0.3 if epoch == kept else share < 0.05, (epoch, kept, share)


def test_of_tied_epochs_the_first_is_marked_as_the_run_keeps_it(tmp_path):
    """A detector log in models.train's format: epochs 2 and 3 tie on the mean BEV AP (the run keeps 2: a new
    best must be strictly better), epoch 4 has a higher AP at 0.7 but a lower mean, a NaN epoch never wins."""
    aps = [(10.0, 20.0), (30.0, 40.0), (40.0, 30.0), (36.0, 32.0), (float("nan"), 90.0)]
    history = [{"epoch": i + 1, "train_loss": 2.0 - 0.1 * i, "lr": 1e-3 if i < 3 else 5e-4, "seconds": 1.0,
                "val_loss": 2.5 - 0.1 * i, "bev_ap_0.7_moderate": a7, "bev_ap_0.5_moderate": a5}
               for i, (a7, a5) in enumerate(aps)]
    (tmp_path / "log.jsonl").write_text("".join(json.dumps(r) + "\n" for r in history))
    assert best_epoch("detector", history) == best_epoch("joint", history) == 2
    written = write_curves(tmp_path, RunInfo("joint", "tiny"))
    figure = draw(read_log(written.parent / "log.jsonl"), RunInfo("joint", "tiny"), tmp_path)
    lines = _lines(figure)
    assert {float(x) for line in lines["best"] for x in line.get_xdata()} == {2.0}
    assert len(lines["best"]) == 2  # on both panels
    assert list(lines["lr"][0].get_ydata()) == [1e-3, 1e-3, 1e-3, 5e-4, 5e-4]  # the halving, as logged
    assert len(lines["bev_ap_0.7_moderate"][0].get_xdata()) == len(history)


def test_without_matplotlib_a_run_trains_on_with_one_warning_after_a_first_line_naming_the_grid(small_sim,
                                                                                              tmp_path):
    """matplotlib made unimportable in a real `python -m models.train` process: two epochs train, one warning
    line says so, no picture; the first line names the preset, its grid and the input."""
    out = tmp_path / "run"
    ids = (small_sim / "ImageSets" / "train.txt").read_text().split()
    (tmp_path / "train.txt").write_text("\n".join(ids[:2]) + "\n")
    (tmp_path / "val.txt").write_text(ids[2] + "\n")  # frames of their own: no warning comes before the first line
    prelude = "import runpy, sys; sys.modules['matplotlib'] = None; "
    argv = ["models.train", "depth", "--data", str(small_sim), "--train-split", str(tmp_path / "train.txt"),
            "--val-split", str(tmp_path / "val.txt"), "--preset", "tiny", "--out", str(out), "--quick",
            "--epochs", "2", "--no-progress"]
    done = subprocess.run([sys.executable, "-c", prelude + f"sys.argv = {argv!r}; "
                           "runpy.run_module('models.train', run_name='__main__')"],
                          cwd=REPO, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert len(read_log(out / "log.jsonl")) == 2
    assert not (out / "curves.png").exists()
    warned = [line for line in done.stderr.splitlines() if "matplotlib" in line]
    assert len(warned) == 1 and "curves.png: not drawn" in warned[0], done.stderr
    grid = get_preset("tiny").bev
    first = done.stderr.splitlines()[0]
    assert first.startswith(f"depth: preset tiny, BEV grid {grid.nz} × {grid.ny} × {grid.nx} (nz × ny × nx), "
                            f"x {grid.x_min:g}…{grid.x_max:g} m"), first
    assert first.endswith("input image + 16-line scans"), first


def test_the_command_redraws_a_run_and_names_a_bad_log_line(tmp_path, capsys):
    history = [{"epoch": 1, "train_loss": 3.0, "lr": 1e-4, "val_loss": 2.0, "rmse_mm": 900.0, "mae_mm": 400.0}]
    (tmp_path / "log.jsonl").write_text(json.dumps(history[0]) + "\n")
    assert main([str(tmp_path), "--out", str(tmp_path / "pictures" / "c.png")]) == 0
    assert cv2.imread(str(tmp_path / "pictures" / "c.png")).shape[:2] == (750, 1000)
    assert "1 epoch(s)" in capsys.readouterr().out
    (tmp_path / "log.jsonl").write_text(json.dumps(history[0]) + "\n{cut short\n")
    assert main([str(tmp_path)]) == 2
    assert capsys.readouterr().err.strip().endswith("log.jsonl, line 2: not JSON (column 2: Expecting property name "
                                                    "enclosed in double quotes)")
    assert main([str(tmp_path / "nothing")]) == 2
    assert "no log.jsonl" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exited:
        main(["--help"])
    assert exited.value.code == 0 and "python -m models.curves runs/depth" in capsys.readouterr().out
