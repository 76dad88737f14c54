"""Ring recovery and 64 → N beam emulation for KITTI HDL-64E scans.

KITTI stores a scan ring after ring: within a ring the azimuth sweeps once
around and wraps. Cutting the point sequence at every wrap recovers the rings
(64–65 segments on real scans: the first and last rings are partial). When the
order is lost (a shuffled or merged cloud) rings fall back to clustering the
elevation angles. Rings are then ranked by elevation and thinned.

CLI: ``python -m pipeline.beams --beams 16 SRC_DIR DST_DIR`` converts a whole
velodyne folder, never writing into the source.
"""

from __future__ import annotations

import argparse
import logging
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.cli import HelpFormatter, add_no_progress, examples, interrupted, show_progress, skipped_summary
from pipeline.errors import InputError

if TYPE_CHECKING:  # the annotation only: emulate_beams_on_depth_map imports pipeline.calib when it runs
    from pipeline.calib import Calibration

# HDL-64E: about +2° … −24.9°; VLP-16: −15° … +15° in 2° steps.
HDL64_ELEVATION_RANGE_DEG = (-24.9, 2.0)
# The HDL-64E's nominal beam elevations, top first: the upper block's 32 lasers a third of a degree apart from
# +2°, the lower block's 32 half a degree apart from −8.83° (Velodyne's data sheet).
HDL64_NOMINAL_ELEVATIONS_DEG = np.concatenate([2.0 - np.arange(32) / 3.0, -8.83 - 0.5 * np.arange(32)])
# Seen from the velodyne frame's origin a KITTI beam's elevation is not one angle: its laser sits above the origin,
# which adds atan(offset / range) (1.7° at 5 m for 0.15 m), and the spin axis leans, which adds about −0.4° ×
# sin(azimuth). Fitted per ring on the five shared KITTI scans, whose rings the scan order gives: offsets
# 0.06–0.18 m (median per scan), lean −0.37° … −0.46°. Pixel beams are read against the nominal table with both
# taken out (:func:`beams_from_elevation`).
KITTI_BEAM_OFFSET_M = 0.15
KITTI_SPIN_LEAN_DEG = -0.4
# The whole table may sit a little off for one sensor: the shift that puts most pixels near a beam, in this range.
_TABLE_SHIFTS_DEG = np.arange(-1.0, 1.0 + 1e-9, 0.02)
_NEAR_BEAM_DEG = 0.2
VLP16_ELEVATIONS_DEG = np.arange(-15.0, 15.1, 2.0)
BEAM_COUNTS = (32, 16, 8, 4)  # what a 64-line scan thins to by keeping every k-th ring
MIN_RINGS_OF_64_LINES = 56  # a KITTI HDL-64E scan splits into 64–65 azimuth-wrap segments, a thinned one into 32 or 16
# A ring-ordered scan has one wrap per ring; far more segments means the order is lost.
_MAX_PLAUSIBLE_SEGMENTS = 200
_MIN_POINTS_PER_SEGMENT = 200
# A scan out of ring order (a VLP-16 driver's firing order, an FOV-cut scan) has no wraps to count its rings by.
# Its far returns (beyond 20 m, where a beam's offset from the origin blurs its elevation by under 0.5°) leave
# gaps of over 0.5° between beams 1.3–2° apart: 2–7 gaps between their 5th and 95th percentiles on the five KITTI
# scans and 40 synthetic ones thinned to 16 lines (either mode), none on the 64-line originals, cut or not.
_GAP_RANGE_M = 20.0
_GAP_DEG = 0.5
_MOST_GAPS_OF_64_LINES = 1
# Fewer far returns than this tell nothing: sampled that thinly a 64-line scan's elevations leave gaps too. Of
# 200 random draws of 100 far returns from each of the five KITTI scans, 28 of 1,000 showed more than one gap
# (684 of 1,000 at 50; none at 150), and no draw of 50 to 200 from their 16-line thinnings fewer than two.
_FEWEST_FAR_RETURNS = 100


@dataclass(frozen=True)
class RingAssignment:
    """Ring id per point, rings numbered 0 … n_rings-1 from the lowest elevation up.

    ring: int32 (N,). elevation_deg: median elevation of each ring (n_rings,); for "elevation-model" the
    nominal beam table, shifted.
    method: "azimuth-wrap" (file order) or "elevation-clusters" (fallback), from :func:`recover_rings`;
    "elevation-model" from :func:`beams_from_elevation`.
    """

    ring: np.ndarray
    n_rings: int
    elevation_deg: np.ndarray
    method: str


def elevation_deg(points: np.ndarray) -> np.ndarray:
    """Elevation angle of each point seen from the sensor origin, in degrees."""
    return np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))


def _rank_by_elevation(segment: np.ndarray, elevation: np.ndarray, n_segments: int) -> tuple[np.ndarray, np.ndarray]:
    """Renumber segments by median elevation (lowest = 0); return per-point ring and per-ring elevation."""
    medians = _segment_medians(segment, elevation, n_segments)
    rank_of_segment = np.empty(n_segments, dtype=np.int32)
    rank_of_segment[np.argsort(medians, kind="stable")] = np.arange(n_segments, dtype=np.int32)
    return rank_of_segment[segment], np.sort(medians)


def _segment_medians(segment: np.ndarray, elevation: np.ndarray, n_segments: int) -> np.ndarray:
    """Each segment's median elevation (the lower middle one of an even count), -inf for an empty segment."""
    if elevation.dtype == np.float32:
        # A float32 scan's elevations sort within their segments as one uint64 key each: the segment, then the
        # elevation's bits made to order like its value (sign bit set on positives, all bits flipped on
        # negatives). One sort of the keys alone replaces a lexsort of the two: 7.0 → 1.7 ms for a 64-line
        # scan, 14.0 → 6.9 ms for the whole 16-line emulation. The median is read back from its key.
        bits = elevation.view(np.uint32)
        ordered = np.where(bits >> np.uint32(31), ~bits, bits | np.uint32(1 << 31))
        key = (segment.astype(np.uint64) << np.uint64(32)) | ordered
        key.sort()
        edges = np.searchsorted(key, np.arange(n_segments + 1, dtype=np.uint64) << np.uint64(32))
        starts, ends = edges[:-1], edges[1:]
        low = key[np.clip((starts + ends - 1) // 2, 0, max(key.size - 1, 0))].astype(np.uint32)
        sorted_middle = np.where(low >> np.uint32(31), low & np.uint32(0x7FFFFFFF), ~low).view(np.float32)
    else:
        order = np.lexsort((elevation, segment))  # by segment, then elevation within it
        sorted_segment = segment[order]
        starts = np.searchsorted(sorted_segment, np.arange(n_segments))
        ends = np.searchsorted(sorted_segment, np.arange(n_segments), side="right")
        sorted_middle = elevation[order][np.clip((starts + ends - 1) // 2, 0, max(elevation.size - 1, 0))]
    return np.where(ends > starts, sorted_middle, -np.inf)


def _cluster_elevations(elevation: np.ndarray, n_clusters: int = 64, iterations: int = 25) -> np.ndarray:
    """1-D k-means on elevation angles (centres start at quantiles); returns a cluster id per point."""
    centres = np.quantile(elevation, (np.arange(n_clusters) + 0.5) / n_clusters)
    labels = np.zeros(elevation.size, dtype=np.int64)
    for _ in range(iterations):  # iterations over cluster updates, not points
        centres = np.unique(centres)
        bounds = (centres[1:] + centres[:-1]) / 2
        labels = np.searchsorted(bounds, elevation)
        sums = np.bincount(labels, weights=elevation, minlength=centres.size)
        counts = np.bincount(labels, minlength=centres.size)
        new = np.where(counts > 0, sums / np.maximum(counts, 1), centres)
        if np.allclose(new, centres):
            break
        centres = new
    return labels


def recover_rings(points: np.ndarray, expected_rings: int = 64, method: str = "auto") -> RingAssignment:
    """Assign every point to a laser ring (see module doc).

    method: "auto" (azimuth wraps when the order looks like a scan, else elevation
    clusters) or "elevation" (always cluster, for points whose order means nothing).
    """
    if method not in ("auto", "elevation"):
        raise ValueError(f"method: {method!r} is not 'auto' or 'elevation'")
    points = np.asarray(points)
    if points.shape[0] == 0:
        return RingAssignment(np.zeros(0, np.int32), 0, np.zeros(0), "azimuth-wrap")
    elevation = elevation_deg(points)
    azimuth = np.arctan2(points[:, 1], points[:, 0])
    wraps = np.abs(np.diff(azimuth)) > np.pi
    segment = np.concatenate([[0], np.cumsum(wraps)]).astype(np.int64)
    n_segments = int(segment[-1]) + 1
    ordered = (
        method != "elevation"
        and n_segments <= _MAX_PLAUSIBLE_SEGMENTS
        and points.shape[0] / n_segments >= _MIN_POINTS_PER_SEGMENT
        and n_segments >= expected_rings // 4
    )
    used = "azimuth-wrap"
    if not ordered:
        segment = _cluster_elevations(elevation, expected_rings)
        n_segments = int(segment.max()) + 1
        used = "elevation-clusters"
    ring, medians = _rank_by_elevation(segment, elevation, n_segments)
    return RingAssignment(ring=ring, n_rings=n_segments, elevation_deg=medians, method=used)


def lines_to_thin_to(trained: int | None) -> int:
    """The lines a 64-line scan is thinned to for a model whose PIXOR was trained on ``trained`` lines (its
    manifest's record): 0, the scan as stored, for a 64-line model; 16, the recipe's, when the record does not
    say. What the tools that feed a model 64-line frames of their own choose (the demo, check_models, latency.py,
    export.precision's calibration)."""
    return 0 if trained == 64 else (trained or 16)


def check_beam_mode(beams: int, mode: str) -> None:
    """Refuse a line count its mode cannot give (a folder run checks it before its first scan)."""
    if mode == "stride":
        if beams <= 0 or 64 % beams != 0:
            raise InputError(f"--beams: {beams} must divide 64 ({', '.join(map(str, BEAM_COUNTS))})")
    elif mode == "vlp16":
        if beams != 16:  # it used to keep the same 9 rings for --beams 4 as for 16, under the 4-line label
            raise InputError(f"--beams: {beams} with --mode vlp16, which emulates a VLP-16's 16 lines: give --beams 16, "
                             "or --mode stride for other line counts")
    else:
        raise InputError(f"--mode: unknown beam emulation mode {mode!r} (stride or vlp16)")


def select_rings(rings: RingAssignment, beams: int, mode: str = "stride") -> np.ndarray:
    """Ring ids to keep.

    mode "stride": every k-th ring in elevation order from the top, k = 64 / beams
    (beams ∈ 32, 16, 8, 4), exactly ``beams`` rings even when a partial 65th segment exists.
    mode "vlp16" (beams 16): for each VLP-16 elevation inside the HDL-64E field of view, the nearest ring:
    9 of its 16 (−15° … +1°; the others look above the HDL-64E's +2°).
    """
    check_beam_mode(beams, mode)
    if mode == "stride":
        step = 64 // beams
        top = rings.n_rings - 1
        kept = np.arange(top, -1, -step)[:beams]
        return np.sort(kept).astype(np.int32)
    lo, hi = HDL64_ELEVATION_RANGE_DEG
    targets = VLP16_ELEVATIONS_DEG[(VLP16_ELEVATIONS_DEG >= lo) & (VLP16_ELEVATIONS_DEG <= hi)]
    nearest = np.argmin(np.abs(rings.elevation_deg[None, :] - targets[:, None]), axis=1)
    return np.unique(nearest).astype(np.int32)


def emulate_beams(points: np.ndarray, beams: int = 16, mode: str = "stride") -> np.ndarray:
    """Thin a 64-line scan to ``beams`` lines; returns the kept points in their original order."""
    if len(points) == 0:
        raise InputError("points: the scan has no points")
    rings = recover_rings(points)
    if rings.method == "azimuth-wrap" and rings.n_rings < MIN_RINGS_OF_64_LINES:
        # Thinning a 16-line scan "to 16 lines" would keep 4 of its rings, silently.
        raise InputError(f"points: the scan has {rings.n_rings} rings, not 64: it is thinned already "
                         "(emulate beams on 64-line scans only)")
    if rings.method == "elevation-clusters":
        gaps = beam_gaps(points)
        if gaps > _MOST_GAPS_OF_64_LINES:  # 64 clusters of a 16-line scan's elevations would keep about 4 lines
            raise InputError(f"points: the scan's returns lie on beams far apart ({gaps} gaps of over {_GAP_DEG:g}° "
                             "between the elevations of its far returns, none in a 64-line scan's): it has 16 lines "
                             "or so already, such as a VLP-16's (emulate beams on 64-line scans only)")
    keep_rings = select_rings(rings, beams, mode)
    return points[np.isin(rings.ring, keep_rings)]


def check_thinnable(data: Path, frames: list[str] | None, beams: int, purpose: str = "evaluate") -> None:
    """InputError, before any model runs or trains, when the first frame's scan in ``data`` (of ``frames``, else
    of the folder) cannot be thinned to ``beams`` lines: a 16-line sensor's scans would otherwise fail or be
    skipped one by one. It names the file and says to give ``--emulate-beams 0``, to ``purpose`` them as stored
    (benchmarks/accuracy.py evaluates, models.train trains on, models.cache_pseudo caches).

    ``beams`` 0 (scans taken as stored, a 16-line sensor's own): InputError when the first scan has 64 lines,
    which a run would learn from as if a 16-line sensor's, and its manifest record so."""
    from pipeline.frame import frame_ids
    from pipeline.kitti import read_velodyne

    ids = frames or frame_ids(data)
    if not ids:
        return  # no frame: the command says so
    path = Path(data) / "velodyne" / f"{ids[0]}.bin"
    if not path.is_file():
        return  # the command names the missing scan
    points = read_velodyne(path).points  # an unusable file is refused as such, its reader naming it once
    if beams:
        check_scan_thinnable(path, points, beams, purpose)
        return
    try:
        emulate_beams(points, 16)
    except InputError:
        return  # not a 64-line scan: a sensor's own, as --emulate-beams 0 says
    raise InputError(f"{path}: the scan has 64 lines, and --emulate-beams 0 would {purpose} it as stored, as a "
                     "16-line sensor's; give --emulate-beams 16 to thin such scans")


def check_scan_thinnable(path: Path, points: np.ndarray, beams: int, purpose: str = "evaluate") -> None:
    """InputError naming the scan file ``path`` when its ``points`` cannot be thinned to ``beams`` lines (a
    16-line sensor's own), saying to give ``--emulate-beams 0`` to ``purpose`` such scans as they are."""
    try:
        emulate_beams(points, beams)
    except InputError as exc:
        raise InputError(f"{path}: {exc}; to {purpose} scans of a {beams}-line sensor as they are, give "
                         "--emulate-beams 0") from None


def beam_gaps(points: np.ndarray) -> int:
    """How many gaps of over _GAP_DEG lie between the sorted elevations of a scan's returns beyond _GAP_RANGE_M,
    within their 5th to 95th percentile: none for a 64-line scan's beams a third to half a degree apart, several
    for 16 lines (0 when too few returns are that far to tell)."""
    far = points[np.hypot(points[:, 0], points[:, 1]) > _GAP_RANGE_M]
    if far.shape[0] < _FEWEST_FAR_RETURNS:
        return 0
    elevation = np.sort(elevation_deg(far))
    low, high = elevation[int(0.05 * elevation.size)], elevation[int(0.95 * elevation.size)]
    middle = elevation[(elevation >= low) & (elevation <= high)]
    return int(np.count_nonzero(np.diff(middle) > _GAP_DEG))


def beams_from_elevation(xyz: np.ndarray) -> RingAssignment:
    """The HDL-64E beam of points whose scan order is lost (a projected depth map's pixels), from their elevation.

    Each point's elevation, less its beam's offset and the spin axis's lean (:data:`KITTI_BEAM_OFFSET_M`,
    :data:`KITTI_SPIN_LEAN_DEG`), is matched to the nearest beam of the nominal table
    (:data:`HDL64_NOMINAL_ELEVATIONS_DEG`), shifted as a whole by the amount that puts most points within 0.2°
    of a beam. Rings are numbered 0–63 from the lowest beam, as :func:`recover_rings` numbers them. Approximate:
    the projected pixels of the five shared KITTI scans, so assigned, lie on their true ring 77 % of the time
    (the beams are 0.33° apart and a pixel's elevation scatters by about 0.1° around its beam's), against 52 %
    for clusters of the raw elevations; a raw scan's order gives them exactly (:func:`emulate_beams_on_depth_map`).
    """
    horizontal = np.hypot(xyz[:, 0], xyz[:, 1])
    azimuth = np.arctan2(xyz[:, 1], xyz[:, 0])
    corrected = (np.degrees(np.arctan2(xyz[:, 2] - KITTI_BEAM_OFFSET_M, horizontal))
                 - KITTI_SPIN_LEAN_DEG * np.sin(azimuth))
    table = np.sort(HDL64_NOMINAL_ELEVATIONS_DEG)  # ascending: ring 0 is the lowest beam

    def nearest(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each value's nearest beam of the (ascending) table and its distance in degrees."""
        upper = np.clip(np.searchsorted(table, values), 1, table.size - 1)
        below = values - table[upper - 1] < table[upper] - values
        ring = np.where(below, upper - 1, upper)
        return ring, np.abs(values - table[ring])

    # One pass over the points per shift of the table (101 shifts), none per point.
    near = [np.count_nonzero(nearest(corrected - shift)[1] < _NEAR_BEAM_DEG) for shift in _TABLE_SHIFTS_DEG]
    shift = float(_TABLE_SHIFTS_DEG[int(np.argmax(near))])
    ring, _ = nearest(corrected - shift)
    return RingAssignment(ring=ring.astype(np.int32), n_rings=table.size, elevation_deg=table + shift,
                          method="elevation-model")


def _returns_nearby(depth: np.ndarray, returns: np.ndarray) -> np.ndarray:
    """Pixels of ``depth`` (> 0) with a return of ``returns`` at the same depth (5 cm, or 0.5 % beyond 10 m) on
    the pixel or one of its eight neighbours.

    The neighbours absorb a projection that rounds pixel coordinates otherwise than this one (KITTI's maps
    are not documented to the pixel); a beam's next return above or below is 4 pixels or more away (its
    beams are 0.33° apart, 4.2 pixels at KITTI's focal length), so no other beam's return is taken for it.
    """
    height, width = depth.shape
    padded = np.zeros((height + 2, width + 2), returns.dtype)
    padded[1:-1, 1:-1] = returns
    tolerance = np.maximum(0.05, 0.005 * depth)
    found = np.zeros(depth.shape, bool)
    for dy in range(3):  # nine shifted views of the map, not a loop over pixels
        for dx in range(3):
            near = padded[dy:dy + height, dx:dx + width]
            found |= (near > 0) & (np.abs(near - depth) <= tolerance)
    return found & (depth > 0)


def emulate_beams_on_depth_map(depth: np.ndarray, calib: Calibration, beams: int = 16, mode: str = "stride",
                               scan: np.ndarray | None = None, source: str = "depth map") -> np.ndarray:
    """Thin a projected 64-line depth map (KITTI depth completion's velodyne_raw) to ``beams`` lines.

    scan: the frame's own raw 64-line scan (KITTI raw's ``velodyne_points``), when at hand: its rings are
    thinned in scan order, as :func:`emulate_beams` thins a scan (exact), projected through ``calib``, and the
    map keeps the pixels that hold one of those returns (:func:`_returns_nearby`). An InputError naming
    ``source`` when the map holds under 90 % of the whole scan's projected returns: another frame's scan, or
    another drive's calibration. Without it each pixel is back-projected through ``calib`` and its beam read
    from its elevation angle (:func:`beams_from_elevation`): on the five shared KITTI scans 66 % of the pixels a
    16-line emulation keeps lie on the 16 rings a scan-order thinning keeps (53–78 % per scan; 30 % with the
    clusters of raw elevations used until session 36), so the map has 16 lines' density but not their whole
    lines. Pixels of dropped beams become 0.
    """
    from pipeline.calib import sparse_depth_map

    check_beam_mode(beams, mode)
    out = np.zeros_like(depth)
    if scan is not None:
        try:
            thinned = emulate_beams(scan, beams, mode)
        except InputError as exc:  # a thinned scan given as the raw one
            raise InputError(f"{source}: {exc}") from exc
        whole = sparse_depth_map(scan, calib, depth.shape)
        matched = np.count_nonzero(_returns_nearby(whole, depth))
        if matched < 0.9 * max(int(np.count_nonzero(whole)), 1):
            raise InputError(f"{source}: holds {matched} of the raw scan's {np.count_nonzero(whole)} returns projected "
                             "into the image: another frame's scan, or another drive's calibration?")
        keep = _returns_nearby(depth, sparse_depth_map(thinned, calib, depth.shape))
        out[keep] = depth[keep]
        return out
    rows, cols = np.nonzero(depth > 0)
    if rows.size == 0:
        return out
    rings = beams_from_elevation(calib.image_to_velo(cols, rows, depth[rows, cols]))
    keep = np.isin(rings.ring, select_rings(rings, beams, mode))
    out[rows[keep], cols[keep]] = depth[rows[keep], cols[keep]]
    return out


# --------------------------------------------------------------------------- CLI
@dataclass(frozen=True)
class FolderRun:
    """What :func:`convert_folder` did: scans written, and the scans it skipped (path → why)."""

    written: int
    skipped: dict[Path, str]


def _refuse_full_scans_in(dst: Path, targets: list[Path]) -> None:
    """Refuse a ``dst`` whose scans of the names to be written are full 64-line scans: SRC and DST given the
    wrong way round. The run would overwrite them, and remove those of the scans it cannot thin."""
    from pipeline.kitti import read_velodyne

    existing = next((path for path in targets if path.is_file()), None)
    if existing is None:
        return
    try:
        rings = recover_rings(read_velodyne(existing).points)
    except InputError:  # an unreadable old copy is not a scan to keep
        return
    if rings.method == "azimuth-wrap" and rings.n_rings >= MIN_RINGS_OF_64_LINES:
        raise InputError(f"DST_DIR {dst}: holds full 64-line scans ({existing.name} among them), which "
                         "this run would overwrite: are SRC_DIR and DST_DIR the wrong way round? Give a folder for "
                         "the thinned copies")


def convert_folder(src: Path, dst: Path, beams: int, mode: str = "stride", progress: bool = True) -> FolderRun:
    """Write the beam-emulated copy of every ``*.bin`` in ``src`` into ``dst``.

    A scan that cannot be thinned (truncated, empty, thinned already) is named on stderr and skipped, and
    the rest are still written, as ``pipeline.detect`` goes on past a bad frame; an old copy of it in
    ``dst`` is removed, so ``dst`` holds only this run's scans. Rows with NaN or infinite values are dropped
    from the copy, with a warning.
    """
    from tqdm import tqdm

    from pipeline.kitti import read_velodyne, write_velodyne

    src, dst = Path(src), Path(dst)
    if not src.is_dir():
        raise InputError(f"{src}: not a directory")
    if dst.resolve() == src.resolve() or src.resolve() in dst.resolve().parents:
        raise InputError(f"{dst}: the destination must not be the source folder or inside it")
    files = sorted(src.glob("*.bin"))
    if not files:
        raise InputError(f"{src}: no velodyne .bin files")
    if dst.exists() and not dst.is_dir():
        raise InputError(f"{dst}: exists and is not a directory")
    check_beam_mode(beams, mode)
    _refuse_full_scans_in(dst, [dst / path.name for path in files])
    dst.mkdir(parents=True, exist_ok=True)
    skipped: dict[Path, str] = {}
    for path in tqdm(files, desc=f"{beams}-line", unit="scan", disable=not progress):
        try:
            scan = read_velodyne(path)  # names the file
            try:
                thinned = emulate_beams(scan.points, beams, mode)
            except InputError as exc:  # name the scan: a folder may hold one that is already thin
                raise InputError(f"{path}: {exc}") from exc
        except InputError as exc:
            skipped[path] = str(exc)
            old = dst / path.name
            removed = f"; removed the old {old}" if old.is_file() else ""
            old.unlink(missing_ok=True)
            tqdm.write(f"error: {exc} (skipped{removed})", file=sys.stderr)
            continue
        if scan.dropped_nonfinite:
            tqdm.write(f"warning: {path}: dropped {scan.dropped_nonfinite} rows with NaN or infinite values",
                       file=sys.stderr)
        write_velodyne(dst / path.name, thinned)
    return FolderRun(len(files) - len(skipped), skipped)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
        prog="python -m pipeline.beams",
        description="Emulate a low-resolution LiDAR: thin every KITTI velodyne scan in SRC_DIR to N lines "
        "and write it, with the same file name, into DST_DIR (the source is never modified).",
        epilog=examples("python -m pipeline.beams --beams 16 data/kitti/training/velodyne "
                        "data/kitti/training/velodyne16"),
        formatter_class=HelpFormatter,
    )
    parser.add_argument("src_dir", type=Path, metavar="SRC_DIR", help="folder of KITTI velodyne .bin scans")
    parser.add_argument("dst_dir", type=Path, metavar="DST_DIR", help="output folder (created if needed)")
    # --emulate-beams, the other commands' name for the lines a scan is thinned to, is accepted as a hidden alias.
    parser.add_argument("--beams", "--emulate-beams", type=int, default=16, choices=BEAM_COUNTS, metavar="N",
                        help="lines to keep: 32, 16, 8 or 4 (default 16)")
    parser.add_argument("--mode", choices=["stride", "vlp16"], default="stride",
                        help="stride: every k-th ring by elevation; vlp16 (with --beams 16): the rings nearest the "
                        "VLP-16's angles inside the HDL-64E's field, 9 of its 16 (-15° … +1°)")
    add_no_progress(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        run = convert_folder(args.src_dir, args.dst_dir, args.beams, args.mode, show_progress(args.no_progress))
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # DST_DIR cannot be written (no permission, a full disk)
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"error: DST_DIR {args.dst_dir}: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return interrupted(f"the scans written so far stay in {args.dst_dir}")
    print(f"wrote {run.written} scans to {args.dst_dir}")
    if run.skipped:
        print(f"error: {skipped_summary([path.name for path in run.skipped], 'scan', run.written + len(run.skipped))}",
              file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
