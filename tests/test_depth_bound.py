"""benchmarks/depth_bound.py: the filled scan plus the exact correction, at a chosen resolution."""

import shutil
from pathlib import Path

import numpy as np

from benchmarks.depth_bound import bounded_depth, closest_neighbour_depth, main, to_full_image
from pipeline.kitti import read_depth_png, read_image, write_depth_png
from pipeline.preprocess import depth_view
from pipeline.presets import get_preset


def test_full_resolution_gives_the_truth_and_half_resolution_blurs_an_edge():
    truth = np.full((4, 8), 40.0, np.float32)
    truth[:, 3:] = 10.0  # a car's edge between columns 2 and 3: inside a 2 × 2 block of columns 2–3
    filled = np.full_like(truth, 20.0)
    filled[0, 0] = 0.0  # a pixel the fill does not reach stays empty
    exact = bounded_depth(filled, truth, 1, 0.9)
    assert exact[0, 0] == 0.0 and np.array_equal(exact[filled > 0], truth[filled > 0])
    blurred = bounded_depth(filled, truth, 2, 0.9)
    # Columns 2 and 3 share a block whose mean correction is halfway: the edge smears into both.
    assert 10.0 < blurred[1, 2] < 40.0 and 10.0 < blurred[1, 3] < 40.0
    assert blurred[1, 6] == 10.0  # far from the edge the block mean is exact


def test_the_closest_neighbour_keeps_an_edge_inside_a_block_that_bilinear_blurs():
    """Columns 2 and 3 share a block across the edge; each takes the block beside it whole instead."""
    truth = np.full((4, 8), 40.0, np.float32)
    truth[:, 3:] = 10.0
    filled = np.full_like(truth, 20.0)
    filled[0, 0] = 0.0
    sharp = closest_neighbour_depth(filled, truth, 2, 0.9)
    assert sharp[0, 0] == 0.0 and np.array_equal(sharp[filled > 0], truth[filled > 0])
    assert np.array_equal(closest_neighbour_depth(filled, truth, 1, 0.9), bounded_depth(filled, truth, 1, 0.9))
    # Where the truth has no depth the pixel keeps the fill (no correction to choose).
    truth[2, 5] = 0.0
    assert closest_neighbour_depth(filled, truth, 2, 0.9)[2, 5] == 20.0


def test_maps_go_to_the_full_image_so_that_the_runtime_reads_them_back_exactly():
    preset = get_preset("edge")
    view = np.random.default_rng(0).uniform(1, 80, preset.depth.input_hw).astype(np.float32)
    full = to_full_image(view, (375, 1242), preset)
    assert np.array_equal(depth_view(full, preset), view)


def test_command_refuses_what_it_cannot_use(tmp_path, capsys):
    (tmp_path / "models").mkdir()  # no manifest in it (an --out inside it would be refused for that first)
    assert main(["--data", str(tmp_path), "--models", str(tmp_path / "models"), "--out", str(tmp_path / "o")]) == 2
    assert "manifest" in capsys.readouterr().err


# ------------------------------------------------------------------ the command: one-line errors before any work
REPO = Path(__file__).resolve().parents[1]
KITTI = REPO / "tests" / "data" / "kitti" / "training"


def _dataset(root: Path, with_depth: bool = True) -> Path:
    """One real KITTI frame in the layout the command reads, with an (empty) true-depth map when asked."""
    fid = "000006"
    for sub, ext in (("image_2", ".png"), ("velodyne", ".bin"), ("calib", ".txt")):
        (root / sub).mkdir(parents=True)
        shutil.copy(KITTI / sub / f"{fid}{ext}", root / sub / f"{fid}{ext}")
    if with_depth:
        (root / "depth_2").mkdir()
        truth = np.zeros(read_image(root / "image_2" / f"{fid}.png").shape[:2], np.float32)
        truth[200:, :] = 12.0
        write_depth_png(root / "depth_2" / f"{fid}.png", truth)
    return root


def _run(capsys, *args: str) -> tuple[int, str]:
    code = main(list(args))
    return code, capsys.readouterr().err


def test_command_refuses_bad_inputs_naming_the_flag_before_writing(tmp_path, capsys):
    data = _dataset(tmp_path / "data")
    out = tmp_path / "out"
    edge = str(REPO / "weights" / "edge")
    code, err = _run(capsys, "--data", str(data), "--models", str(REPO / "weights" / "edge-lidar16"), "--out", str(out))
    assert code == 2 and "--models" in err and "LiDAR-only" in err  # used to write maps for a model with no depth net
    code, err = _run(capsys, "--data", str(data), "--models", edge, "--factor", "7", "--out", str(out))
    assert code == 2 and "--factor 7: does not divide" in err and "2, 4, 8, 16" in err
    no_truth = _dataset(tmp_path / "kitti", with_depth=False)
    code, err = _run(capsys, "--data", str(no_truth), "--models", edge, "--out", str(out))
    assert code == 2 and "--data" in err and "depth_2/" in err
    (tmp_path / "empty" / "velodyne").mkdir(parents=True)
    (tmp_path / "empty" / "depth_2").mkdir()
    code, err = _run(capsys, "--data", str(tmp_path / "empty"), "--models", edge, "--out", str(out))
    assert code == 2 and "no frames" in err
    assert not out.exists()  # every refusal came before the output folder was made
    blocker = tmp_path / "file"
    blocker.write_text("x")
    code, err = _run(capsys, "--data", str(data), "--models", edge, "--out", str(blocker / "out"))
    assert code == 2 and err.startswith("error: --out") and "Traceback" not in err  # was a FileExistsError trace


def test_command_never_overwrites_depth_maps(tmp_path, capsys):
    """Not the data's true depth (--out the data folder), not an earlier run's maps, not a training cache."""
    data = _dataset(tmp_path / "data")
    truth = (data / "depth_2" / "000006.png").read_bytes()
    edge = str(REPO / "weights" / "edge")
    code, err = _run(capsys, "--data", str(data), "--models", edge, "--out", str(data))
    assert code == 2 and f"--out {data}: would be written over what --data {data.resolve()} holds" in err
    assert (data / "depth_2" / "000006.png").read_bytes() == truth
    # --cache writes OUT/<id>.png: into image_2/ it replaced the frame's camera image; into the model directory.
    image = (data / "image_2" / "000006.png").read_bytes()
    for out, flag in ((data / "image_2", "--data"), (REPO / "weights" / "edge" / "maps", "--models")):
        code, err = _run(capsys, "--data", str(data), "--models", edge, "--cache", "--out", str(out))
        assert code == 2 and f"--out {out}: would be written over what {flag} " in err, err
    assert (data / "image_2" / "000006.png").read_bytes() == image and not (REPO / "weights" / "edge" / "maps").exists()
    assert _run(capsys, "--data", str(data), "--models", edge, "--factor", "2", "--out", str(tmp_path / "out"))[0] == 0
    code, err = _run(capsys, "--data", str(data), "--models", edge, "--out", str(tmp_path / "out"))
    assert code == 2 and "already holds depth maps" in err
    cache = tmp_path / "cache"
    cache.mkdir()
    (cache / "cache.json").write_text("{}")
    code, err = _run(capsys, "--data", str(data), "--models", edge, "--cache", "--out", str(cache))
    assert code == 2 and "models.cache_pseudo cache" in err and list(cache.iterdir()) == [cache / "cache.json"]


def test_command_writes_a_map_per_frame(tmp_path, capsys):
    data = _dataset(tmp_path / "data")
    code = main(["--data", str(data), "--models", str(REPO / "weights" / "edge"), "--factor", "2",
                 "--out", str(tmp_path / "out")])
    assert code == 0, capsys.readouterr().err
    written = read_depth_png(tmp_path / "out" / "depth_2" / "000006.png")
    assert written.shape == read_image(data / "image_2" / "000006.png").shape[:2] and (written > 0).any()


def test_command_writes_training_caches_in_the_network_view(tmp_path, capsys):
    """--cache writes what models.cache_pseudo writes (the network's view, named by frame id), so the
    camera PIXOR can be fine-tuned on a bound; the full-image map of the same bound reads back to it."""
    data = _dataset(tmp_path / "data")
    edge = str(REPO / "weights" / "edge")
    for extra in ([], ["--cache"]):
        code = main(["--data", str(data), "--models", edge, "--factor", "2", "--upsample", "closest", *extra,
                     "--out", str(tmp_path / ("cache" if extra else "full"))])
        assert code == 0, capsys.readouterr().err
    view = read_depth_png(tmp_path / "cache" / "000006.png")
    assert view.shape == get_preset("edge").depth.input_hw and (view > 0).any()
    full = read_depth_png(tmp_path / "full" / "depth_2" / "000006.png")
    assert np.array_equal(depth_view(full, get_preset("edge")), view)
