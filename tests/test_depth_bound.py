"""benchmarks/depth_bound.py: the filled scan plus the exact correction, at a chosen resolution."""

import numpy as np

from benchmarks.depth_bound import bounded_depth, main, to_full_image
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


def test_maps_go_to_the_full_image_so_that_the_runtime_reads_them_back_exactly():
    preset = get_preset("edge")
    view = np.random.default_rng(0).uniform(1, 80, preset.depth.input_hw).astype(np.float32)
    full = to_full_image(view, (375, 1242), preset)
    assert np.array_equal(depth_view(full, preset), view)


def test_command_refuses_what_it_cannot_use(tmp_path, capsys):
    assert main(["--data", str(tmp_path), "--models", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "manifest" in capsys.readouterr().err
