"""Ring recovery and beam emulation on the real 64-line scans, and the folder command."""

import subprocess
import sys

import numpy as np
import pytest

from pipeline.beams import convert_folder, elevation_deg, emulate_beams, recover_rings, select_rings
from pipeline.errors import InputError
from pipeline.kitti import read_velodyne
from tests.conftest import FRAMES, KITTI


def scan(frame_id: str) -> np.ndarray:
    return read_velodyne(KITTI / "velodyne" / f"{frame_id}.bin").points


@pytest.mark.parametrize("frame_id", FRAMES)
def test_ring_recovery_finds_64_rings(frame_id):
    rings = recover_rings(scan(frame_id))
    assert rings.method == "azimuth-wrap"
    assert abs(rings.n_rings - 64) <= 1
    # Rings are numbered by elevation: medians increase, spanning the HDL-64E field of view.
    assert np.all(np.diff(rings.elevation_deg) >= 0)
    assert -26 < rings.elevation_deg[0] < -22 and 1 < rings.elevation_deg[-1] < 3.5


@pytest.mark.parametrize("frame_id", FRAMES)
def test_float32_medians_by_one_key_sort_equal_the_lexsort(frame_id):
    """A float32 scan's per-ring medians come from one sort of (segment, elevation-bits) keys; they equal the
    lexsort path's on the same values widened to float64, for the real rings, for shuffled points (the
    elevation clusters), and for ties, zeros and negative elevations with an empty segment between."""
    from pipeline.beams import _segment_medians

    points = scan(frame_id)
    rings = recover_rings(points)
    elevation = elevation_deg(points)
    assert elevation.dtype == np.float32
    shuffled = np.random.default_rng(0).permutation(points.shape[0])
    crafted = np.array([-3.5, 0.0, -0.0, 2.25, -3.5, 7.0, -1e-30, 2.25], np.float32)
    cases = [(rings.ring.astype(np.int64), elevation, rings.n_rings),
             (recover_rings(points[shuffled], method="elevation").ring.astype(np.int64), elevation[shuffled], 64),
             (np.array([0, 0, 0, 0, 2, 2, 2, 3]), crafted, 5)]
    for segment, values, count in cases:
        by_key = _segment_medians(segment, values, count)
        by_lexsort = _segment_medians(segment, values.astype(np.float64), count)
        assert by_key.dtype == np.float32
        np.testing.assert_array_equal(by_key, by_lexsort.astype(np.float32))
    # Sorted, segment 0 is -3.5, ±0, ±0, 2.25 (the lower middle: zero) and segment 2 is -3.5, -1e-30, 7.
    np.testing.assert_array_equal(_segment_medians(*cases[2]), np.array([0.0, -np.inf, -1e-30, 2.25, -np.inf],
                                                                         np.float32))
    # The whole recovery: the same rings from the float32 scan as from its float64 copy.
    np.testing.assert_array_equal(recover_rings(points.astype(np.float64)).ring, rings.ring)


@pytest.mark.parametrize("frame_id", FRAMES)
def test_16_line_emulation_keeps_16_rings_and_a_quarter(frame_id):
    points = scan(frame_id)
    kept = emulate_beams(points, 16)
    assert 0.24 <= kept.shape[0] / points.shape[0] <= 0.26
    again = recover_rings(kept, expected_rings=16)
    assert again.n_rings == 16
    # Kept points are a subset, in their original order.
    source_index = {row.tobytes(): i for i, row in enumerate(points)}
    positions = np.array([source_index[row.tobytes()] for row in kept[::97]])
    assert np.all(np.diff(positions) > 0)
    # Thinning the thinned scan again would keep 4 of its 16 rings: refused, naming the ring count.
    with pytest.raises(InputError, match="the scan has 16 rings, not 64"):
        emulate_beams(kept, 16)


@pytest.mark.parametrize("beams", [32, 16, 8, 4])
def test_every_kth_ring(beams):
    points = scan("000006")
    rings = recover_rings(points)
    kept = select_rings(rings, beams)
    assert kept.size == beams
    assert np.all(np.diff(kept) == 64 // beams)
    assert kept[-1] == rings.n_rings - 1  # the top ring is always kept
    fraction = emulate_beams(points, beams).shape[0] / points.shape[0]
    assert fraction == pytest.approx(beams / 64, abs=0.02)


def test_lost_order_falls_back_to_elevation_clusters():
    points = scan("000006")
    shuffled = points[np.random.default_rng(0).permutation(points.shape[0])]
    rings = recover_rings(shuffled)
    assert rings.method == "elevation-clusters"
    assert rings.n_rings == 64
    fraction = emulate_beams(shuffled, 16).shape[0] / points.shape[0]
    assert 0.2 < fraction < 0.3


def test_vlp16_mode_keeps_rings_near_vlp16_angles():
    points = scan("000006")
    rings = recover_rings(points)
    kept = select_rings(rings, 16, "vlp16")
    # −15° … +1° in 2° steps lie inside the HDL-64E field: 9 lines.
    assert kept.size == 9
    targets = np.arange(-15.0, 2.0, 2.0)
    assert np.abs(rings.elevation_deg[kept] - targets).max() < 0.5
    thinned = emulate_beams(points, 16, "vlp16")
    assert np.abs(elevation_deg(thinned)).max() < 16


def test_bad_beam_count():
    with pytest.raises(InputError, match="must divide 64"):
        emulate_beams(scan("000006"), 12)


def test_folder_command_never_touches_source(tmp_path):
    src = tmp_path / "velodyne"
    src.mkdir()
    for frame_id in ("000003", "000006"):
        (src / f"{frame_id}.bin").write_bytes((KITTI / "velodyne" / f"{frame_id}.bin").read_bytes())
    before = {p.name: p.read_bytes() for p in src.iterdir()}
    dst = tmp_path / "velodyne16"
    result = subprocess.run(
        [sys.executable, "-m", "pipeline.beams", "--beams", "16", str(src), str(dst)],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert result.returncode == 0, result.stderr
    assert {p.name: p.read_bytes() for p in src.iterdir()} == before
    for name in before:
        out = read_velodyne(dst / name).points
        np.testing.assert_array_equal(out, emulate_beams(read_velodyne(src / name).points, 16))
    refused = subprocess.run(
        [sys.executable, "-m", "pipeline.beams", str(src), str(src / "inside")], capture_output=True, text=True, check=False,
    )
    assert refused.returncode == 2 and "must not be the source" in refused.stderr
    assert "Traceback" not in refused.stderr



def test_the_folder_command_takes_the_familys_emulate_beams_too(tmp_path):
    """Every other command calls the lines a scan is thinned to --emulate-beams; here it is --beams, and
    --emulate-beams 8 was 'unrecognized arguments: --emulate-beams DST_DIR'. It is a hidden alias now."""
    from pipeline.beams import main

    src = tmp_path / "velodyne"
    src.mkdir()
    (src / "000006.bin").write_bytes((KITTI / "velodyne" / "000006.bin").read_bytes())
    assert main(["--emulate-beams", "8", str(src), str(tmp_path / "v8"), "--no-progress"]) == 0
    np.testing.assert_array_equal(read_velodyne(tmp_path / "v8" / "000006.bin").points,
                                  emulate_beams(read_velodyne(src / "000006.bin").points, 8))

def test_elevation_method_clusters_even_an_ordered_scan():
    points = scan("000006")
    assert recover_rings(points).method == "azimuth-wrap"
    asked = recover_rings(points, method="elevation")
    assert asked.method == "elevation-clusters" and asked.n_rings == 64
    with pytest.raises(ValueError, match="method"):
        recover_rings(points, method="elevations")


def test_folder_command_names_the_problem_file(tmp_path):
    """A destination that is a file, and a scan already thinned, each get one line naming the path."""
    src = tmp_path / "velodyne"
    src.mkdir()
    (src / "000006.bin").write_bytes((KITTI / "velodyne" / "000006.bin").read_bytes())
    (tmp_path / "a-file").write_text("")
    blocked = subprocess.run([sys.executable, "-m", "pipeline.beams", str(src), str(tmp_path / "a-file")],
                             capture_output=True, text=True, timeout=120, check=False)
    assert blocked.returncode == 2 and "a-file: exists and is not a directory" in blocked.stderr
    assert "Traceback" not in blocked.stderr
    thin = tmp_path / "thin"
    assert convert_folder(src, thin, 16, progress=False).written == 1
    again = subprocess.run([sys.executable, "-m", "pipeline.beams", str(thin), str(tmp_path / "thinner")],
                           capture_output=True, text=True, timeout=120, check=False)
    assert again.returncode == 1 and f"{thin / '000006.bin'}: points: the scan has " in again.stderr
    assert "it is thinned already" in again.stderr and "Traceback" not in again.stderr


def test_folder_command_goes_on_past_a_bad_scan(tmp_path):
    """Each unusable scan is named with its reason and skipped, the others are written, the command exits 1;
    an old copy of a skipped scan in DST_DIR is removed, and rows that are not finite are dropped with a warning."""
    src, dst = tmp_path / "velodyne", tmp_path / "thin"
    src.mkdir()
    scan = (KITTI / "velodyne" / "000006.bin").read_bytes()
    (src / "000001.bin").write_bytes(scan[:1000])  # truncated: not a multiple of 16 bytes
    (src / "000002.bin").write_bytes(b"")
    with_nan = np.frombuffer(scan, np.float32).reshape(-1, 4).copy()
    with_nan[:11, 2] = np.nan
    with_nan.tofile(src / "000003.bin")
    (src / "000004.bin").write_bytes(scan)
    dst.mkdir()
    thin_copy = emulate_beams(np.frombuffer(scan, np.float32).reshape(-1, 4), 16)
    thin_copy.tofile(dst / "000001.bin")  # an earlier run's copy
    done = subprocess.run([sys.executable, "-m", "pipeline.beams", str(src), str(dst)],
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 1 and "Traceback" not in done.stderr
    assert f"error: {src / '000001.bin'}: size 1000 bytes" in done.stderr and f"removed the old {dst / '000001.bin'}" in done.stderr
    assert f"error: {src / '000002.bin'}: " in done.stderr and "rings" not in done.stderr.split("000002.bin")[1].split("\n")[0]
    assert f"warning: {src / '000003.bin'}: dropped 11 rows with NaN or infinite values" in done.stderr
    assert "2 of 4 scan(s) skipped (each named above with its reason): 000001.bin, 000002.bin" in done.stderr
    assert "wrote 2 scans" in done.stdout
    assert sorted(p.name for p in dst.iterdir()) == ["000003.bin", "000004.bin"]
    thinned = np.fromfile(dst / "000004.bin", np.float32).reshape(-1, 4)
    np.testing.assert_array_equal(thinned, emulate_beams(np.frombuffer(scan, np.float32).reshape(-1, 4), 16))


def test_source_and_destination_swapped_is_refused_and_loses_nothing(tmp_path):
    """A DST_DIR of full 64-line scans (the folders given the wrong way round) is refused before any scan is
    written or removed: a thinned scan given as a source used to be skipped and its full-scan namesake in
    DST_DIR removed, emptying the original folder."""
    velodyne, thin = tmp_path / "velodyne", tmp_path / "velodyne16"
    velodyne.mkdir()
    for frame_id in ("000003", "000006"):
        (velodyne / f"{frame_id}.bin").write_bytes((KITTI / "velodyne" / f"{frame_id}.bin").read_bytes())
    before = {p.name: p.read_bytes() for p in velodyne.iterdir()}
    assert convert_folder(velodyne, thin, 16, progress=False).written == 2
    done = subprocess.run([sys.executable, "-m", "pipeline.beams", str(thin), str(velodyne)],
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert f"DST_DIR {velodyne}: holds full 64-line scans" in done.stderr and "wrong way round" in done.stderr
    assert {p.name: p.read_bytes() for p in velodyne.iterdir()} == before


def test_vlp16_mode_takes_16_lines_only():
    """--mode vlp16 used to keep the same 9 rings for --beams 4 or 32 as for 16."""
    for beams in (4, 8, 32):
        with pytest.raises(InputError, match=f"--beams: {beams} with --mode vlp16"):
            emulate_beams(scan("000006"), beams, "vlp16")


def test_convert_folder_rejects_missing_source(tmp_path):
    with pytest.raises(InputError, match="not a directory"):
        convert_folder(tmp_path / "missing", tmp_path / "out", 16, progress=False)


def _ring_per_pixel(points: np.ndarray, calib, image_hw: tuple[int, int]) -> np.ndarray:
    """Each pixel's ring by the scan order (-1: no return), the nearest return winning as in a projected map."""
    rings = recover_rings(points).ring
    uv, depth = calib.velo_to_image(points[:, :3])
    rows, cols = np.rint(uv[:, 1]), np.rint(uv[:, 0])
    inside = (depth > 0.1) & (cols >= 0) & (cols < image_hw[1]) & (rows >= 0) & (rows < image_hw[0])
    far_first = np.argsort(-depth[inside])  # the nearest return is written last
    ring_map = np.full(image_hw, -1)
    ring_map[rows[inside][far_first].astype(int), cols[inside][far_first].astype(int)] = rings[inside][far_first]
    return ring_map


def _projected(frame_id: str):
    from pipeline.calib import sparse_depth_map
    from pipeline.kitti import read_calib, read_image_size

    points, calib = scan(frame_id), read_calib(KITTI / "calib" / f"{frame_id}.txt")
    image_hw = read_image_size(KITTI / "image_2" / f"{frame_id}.png")
    return points, calib, image_hw, sparse_depth_map(points, calib, image_hw)


@pytest.mark.parametrize("frame_id", FRAMES)
def test_a_depth_map_thinned_with_its_raw_scan_is_the_scans_16_lines(frame_id):
    """With the frame's raw scan, thinning a projected map (KITTI depth completion's velodyne_raw) keeps exactly
    the pixels of the 16 rings a scan-order thinning keeps, at the map's own depths; also when the map was
    projected with pixel coordinates rounded half a pixel otherwise (KITTI's rounding is not documented)."""
    from pipeline.beams import emulate_beams_on_depth_map
    from pipeline.calib import Calibration, sparse_depth_map

    points, calib, image_hw, whole = _projected(frame_id)
    true16 = sparse_depth_map(emulate_beams(points, 16), calib, image_hw) > 0
    thinned = emulate_beams_on_depth_map(whole, calib, 16, scan=points)
    kept = thinned > 0
    assert np.array_equal(thinned[kept], whole[kept])
    # At most a pixel or so another ring's, where a kept ring's return in the next pixel has the same depth.
    assert np.count_nonzero(kept & ~true16) <= 2 and np.count_nonzero(kept) >= 0.99 * np.count_nonzero(true16)
    shift = np.array([[1.0, 0.0, -0.5], [0.0, 1.0, -0.5], [0.0, 0.0, 1.0]])  # rint(u − ½): floor, near enough
    floored = sparse_depth_map(points, Calibration(shift @ calib.P2, calib.R0_rect, calib.Tr_velo_to_cam), image_hw)
    kept_floored = emulate_beams_on_depth_map(floored, calib, 16, scan=points) > 0
    assert 0.97 * np.count_nonzero(true16) <= np.count_nonzero(kept_floored) <= 1.03 * np.count_nonzero(true16)


def test_a_raw_scan_of_another_frame_is_refused_naming_the_files():
    from pipeline.beams import emulate_beams_on_depth_map

    _, calib, _, whole = _projected("000003")
    with pytest.raises(InputError, match=r"velodyne_raw/3.png and 1.bin: holds \d+ of the raw scan's \d+ returns"):
        emulate_beams_on_depth_map(whole, calib, 16, scan=scan("000001"), source="velodyne_raw/3.png and 1.bin")
    with pytest.raises(InputError, match="x.png: points: the scan has 16 rings, not 64"):
        emulate_beams_on_depth_map(whole, calib, 16, scan=emulate_beams(scan("000003"), 16), source="x.png")


def test_without_the_raw_scan_each_pixels_beam_comes_from_its_elevation():
    """Without the scan, pixels get beams from their elevation (the HDL-64E's nominal table, less each beam's
    offset and the spin axis's lean). On the five shared scans: 77 % of the pixels on their true ring (52 % for
    clusters of the raw elevations), and of the pixels a 16-line thinning keeps, 53–78 % on the 16 rings a
    scan-order thinning keeps (30 % for the clusters), with a quarter of the returns."""
    from pipeline.beams import beams_from_elevation, emulate_beams_on_depth_map

    right_ring, on_kept_rings = [], []
    for frame_id in FRAMES:
        points, calib, image_hw, whole = _projected(frame_id)
        truth = _ring_per_pixel(points, calib, image_hw)
        rows, cols = np.nonzero(whole > 0)
        ring = truth[rows, cols]
        guessed = beams_from_elevation(calib.image_to_velo(cols, rows, whole[rows, cols])).ring
        # Each guessed beam stands for the true ring most of its pixels are on.
        pairs = np.bincount(guessed * 128 + ring + 1, minlength=64 * 128).reshape(64, 128)
        right_ring.append(pairs.max(axis=1).sum() / ring.size)
        kept = emulate_beams_on_depth_map(whole, calib, 16)[rows, cols] > 0
        assert 0.2 < kept.mean() < 0.3
        on_kept_rings.append(max(np.count_nonzero(kept & (ring % 4 == k)) / np.count_nonzero(kept) for k in range(4)))
    assert np.mean(right_ring) > 0.75 and min(right_ring) > 0.65
    assert np.mean(on_kept_rings) > 0.6 and min(on_kept_rings) > 0.5


def test_a_64_line_scan_is_thinned_to_the_models_own_lines():
    """The rule the demo, check_models, latency.py and INT8 calibration share: as stored for a 64-line model, the
    recorded lines otherwise, the recipe's 16 when the manifest does not say."""
    from pipeline.beams import lines_to_thin_to

    assert [lines_to_thin_to(lines) for lines in (64, 32, 16, 8, None)] == [0, 32, 16, 8, 16]


def test_the_golden_frame_thins_its_scan_as_the_other_tools_do():
    """export.golden's bundled 64-line scan follows the same rule, a manifest without a recorded line count
    included (it used to be kept as stored there, where the other tools thin to 16)."""
    from export.golden import default_beams

    records = [{"input": "lidar64"}, {"input": "lidar16", "emulate_beams": 32}, {"input": "pseudo"},
               {"input": "lidar16", "emulate_beams": 8}, {}]
    assert [default_beams({"networks": {"pixor": {"training": record}}}) for record in records] == [0, 32, 16, 8, 16]


def test_a_scan_with_a_sector_missing_keeps_its_64_rings():
    """A scan with a 120° sector of no returns (masked by a mount, or cut to a field of view): within a ring the
    azimuth jumps across the gap by less than half a turn, which is no wrap, so each ring stays one segment."""
    points = scan("000006")
    azimuth = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
    for low, high in ((30, 150), (100, 170)):
        rings = recover_rings(points[(azimuth <= low) | (azimuth >= high)])
        assert rings.method == "azimuth-wrap" and abs(rings.n_rings - 64) <= 1



def test_beam_gaps_are_counted_only_with_enough_far_returns():
    """Beam gaps are told from the returns beyond 20 m. A scan without them (taken in a garage, say) has no gaps
    to count and is thinned, not failed; with fewer than 100 of them even a 16-line scan's far returns are too
    few to tell, and with more they show its gaps."""
    from pipeline.beams import beam_gaps

    points = scan("000006")
    shuffled = points[np.random.default_rng(0).permutation(points.shape[0])]
    near = shuffled[np.hypot(shuffled[:, 0], shuffled[:, 1]) < 20.0]
    assert beam_gaps(near) == 0
    assert 0.2 < emulate_beams(near, 16).shape[0] / near.shape[0] < 0.3
    lines16 = emulate_beams(points, 16)
    far16 = lines16[np.hypot(lines16[:, 0], lines16[:, 1]) > 20.0]
    far16 = far16[np.random.default_rng(1).permutation(far16.shape[0])]
    assert beam_gaps(far16[:99]) == 0
    assert beam_gaps(far16[:400]) > 0
