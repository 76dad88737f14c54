"""Porting to another runtime (docs/models.md, "Porting to another runtime"): the spec a port reads is complete
and true, and the golden frame lets a port check itself stage by stage.

The spec of every shipped model directory is held against what the pipeline does, through probes of its own
functions, so that no constant can drift from the code. Then a NumPy port written from port.json alone (the
``port_*`` functions below use no pipeline code) reproduces each stage of the golden frame within the
tolerances golden.json states, and end to end gives the golden boxes.
"""

from __future__ import annotations

import importlib
import itertools
import json
import math
import re
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import onnx
import onnxruntime as ort
import pytest
from shapely.geometry import Polygon

from export.port_spec import graph_report, port_spec, port_spec_of
from pipeline.beams import emulate_beams
from pipeline.bev import pseudo_bins, voxelize_bev
from pipeline.boxes import bev_corners, boxes_to_objects, in_camera_view, labels_to_boxes
from pipeline.calib import KITTI_CALIBRATION, KITTI_IMAGE_HW, depth_crop, sparse_depth_map
from pipeline.detector import MIRRORED_TARGETS
from pipeline.errors import InputError
from pipeline.frame import load_frame
from pipeline.iou import rotated_nms
from pipeline.kitti import format_label
from pipeline.postprocess import estimate_heights
from pipeline.preprocess import depth_inputs, network_view, view_calibration
from pipeline.presets import get_preset, preset_from_dict
from pipeline.pseudo import depth_jumps, depth_to_points
from pipeline.targets import decode_maps
from tests.conftest import KITTI

ROOT = Path(__file__).resolve().parents[1]
WEIGHTS = ROOT / "weights"
SHIPPED = ["edge", "edge-int8", "edge-lidar16", "edge-lidar64"]
HIDE_TORCH = "import runpy, sys; sys.modules['torch'] = None; "  # the runtime install has no torch


def _manifest(name: str) -> dict:
    return json.loads((WEIGHTS / name / "manifest.json").read_text())


def _spec_and_preset(name: str):
    manifest = _manifest(name)
    spec, _ = port_spec_of(manifest)
    return json.loads(json.dumps(spec)), preset_from_dict(manifest["preset_config"]), manifest


# --------------------------------------------------------------------------- a port written from port.json alone
def port_crop(spec: dict, rows: int, columns: int) -> tuple[int, int]:
    """(top, left) of the depth net's crop."""
    crop = spec["image"]["crop"]
    return rows - crop["height"], (columns - crop["width"]) // 2


def port_view_p2(spec: dict, p2: np.ndarray, rows: int, columns: int) -> np.ndarray:
    top, left = port_crop(spec, rows, columns)
    s, o = spec["view_calibration"]["scale"], spec["view_calibration"]["offset"]
    shift = np.array([[1.0, 0, -left], [0, 1.0, -top], [0, 0, 1.0]])
    return np.array([[s, 0, o], [0, s, o], [0, 0, 1.0]]) @ shift @ p2


def port_view_image(spec: dict, image: np.ndarray) -> np.ndarray:
    """The crop resized; ×½ by the spec's integer rule (what a port without OpenCV does)."""
    top, left = port_crop(spec, *image.shape[:2])
    crop = image[top:top + spec["image"]["crop"]["height"], left:left + spec["image"]["crop"]["width"]]
    height, width = spec["image"]["resize"]["output_hw"]
    if spec["image"]["resize"]["scale"] != 0.5:
        return cv2.resize(crop, (width, height), interpolation=cv2.INTER_AREA)
    blocks = crop.reshape(height, 2, width, 2, 3).astype(np.int32).sum(axis=(1, 3))
    return ((blocks + 2) // 4).astype(np.uint8)


def _velo_to_rect(r0: np.ndarray, tr: np.ndarray) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, :4] = r0 @ tr
    return matrix


def port_sparse_depth(spec: dict, points: np.ndarray, view_p2: np.ndarray, r0: np.ndarray, tr: np.ndarray) -> np.ndarray:
    rule = spec["sparse_depth"]
    _, _, height, width = rule["network_input"]["shape"]
    xyz1 = np.column_stack([points[:, :3].astype(np.float64), np.ones(len(points))])
    projected = xyz1 @ (view_p2 @ _velo_to_rect(r0, tr)).T
    d = projected[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        column, row = np.rint(projected[:, 0] / d), np.rint(projected[:, 1] / d)
    keep = (d > rule["min_depth"]) & (column >= 0) & (column < width) & (row >= 0) & (row < height)
    out = np.full(height * width, np.inf)
    np.minimum.at(out, (row[keep] * width + column[keep]).astype(np.int64), d[keep])
    return np.where(np.isfinite(out), out, 0).astype(np.float32).reshape(height, width)


def port_pseudo_points(spec: dict, depth: np.ndarray, view_p2: np.ndarray, r0: np.ndarray, tr: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """(M, 3) float64 points and the flat pixel index of each."""
    rule = spec["pseudo_points"]
    stride = rule["stride"]
    rows, columns = np.mgrid[0:depth.shape[0]:stride, 0:depth.shape[1]:stride]
    d32 = depth[::stride, ::stride]
    keep = (d32 >= np.float32(rule["min_depth"])) & (d32 <= np.float32(rule["max_depth"]))
    pixel = (rows * depth.shape[1] + columns)[keep]
    d = d32[keep].astype(np.float64)
    k_inv = np.linalg.inv(view_p2[:, :3])
    rays = k_inv @ np.stack([columns[keep], rows[keep], np.ones(d.size)])
    rect = d * rays - (k_inv @ view_p2[:, 3])[:, None]
    velo = np.linalg.inv(_velo_to_rect(r0, tr)) @ np.vstack([rect, np.ones(d.size)])
    low = velo[2] <= np.float32(rule["max_height"])
    return velo[:3, low].T, pixel[low]


def port_rays(spec: dict, view_p2: np.ndarray, r0: np.ndarray, tr: np.ndarray, shape: tuple[int, int],
              scale: tuple[float, ...] = (1.0, 1.0, 1.0), low: tuple[float, ...] = (0.0, 0.0, 0.0)
              ) -> tuple[np.ndarray, np.ndarray]:
    """pseudo_points.rays: (3, H·W) rays and (3,) origin in ray_dtype, every axis scaled before the one rounding."""
    dtype = np.dtype(spec["pseudo_points"]["ray_dtype"])
    k_inv = np.linalg.inv(view_p2[:, :3])
    to_velo = np.linalg.inv(_velo_to_rect(r0, tr))
    a, b, factor = to_velo[:3, :3], to_velo[:3, 3], np.asarray(scale, np.float64)
    columns = factor[:, None] * (a @ k_inv)  # Du, Dv, D0
    u, v = np.arange(shape[1], dtype=np.float64), np.arange(shape[0], dtype=np.float64)
    rays = np.stack([((columns[axis, 1] * v)[:, None] + (columns[axis, 0] * u + columns[axis, 2])).astype(dtype)
                     for axis in range(3)]).reshape(3, -1)
    origin = factor * (b - a @ (k_inv @ view_p2[:, 3])) - factor * np.asarray(low, np.float64)
    return rays, origin.astype(dtype)


def port_pseudo_points_exact(spec: dict, depth: np.ndarray, view_p2: np.ndarray, r0: np.ndarray, tr: np.ndarray
                             ) -> np.ndarray:
    """(M, 3) points by pseudo_points.rays and .point (stride 1, as every shipped preset)."""
    rule = spec["pseudo_points"]
    assert rule["stride"] == 1  # every shipped preset's; the port handles no other
    rays, origin = port_rays(spec, view_p2, r0, tr, depth.shape)
    d = depth.reshape(-1).astype(rule["point_dtype"])
    keep = (d >= np.float32(rule["min_depth"])) & (d <= np.float32(rule["max_depth"]))
    keep &= d * rays[2] + origin[2] <= np.float32(rule["max_height"])
    return np.column_stack([d[keep] * rays[axis, keep] + origin[axis] for axis in range(3)])


def port_pseudo_bins(spec: dict, depth: np.ndarray, view_p2: np.ndarray, r0: np.ndarray, tr: np.ndarray
                     ) -> tuple[np.ndarray, ...]:
    """bev.pseudo_bin: (iz, iy, ix) of the pseudo points straight from the depth map, and each one's pixel."""
    bev, limits, rule = spec["bev"], spec["pseudo_points"], spec["bev"]["pseudo_bin"]
    rays, origin = port_rays(spec, view_p2, r0, tr, depth.shape, rule["scale"], (bev["x_min"], bev["y_min"], bev["z_min"]))
    d = depth.reshape(-1).astype(np.float32)
    keep = (d >= np.float32(limits["min_depth"])) & (d <= np.float32(limits["max_depth"]))
    bins = []
    for axis, n in ((0, bev["nx"]), (1, bev["ny"]), (2, bev["nz"])):
        c = d * rays[axis] + origin[axis]
        if axis == 2:
            keep &= c <= np.float32(rule["max_height_bin"])
        b = np.floor(c)
        keep &= (b >= 0) & (b < n)
        bins.append(b)
    ix, iy, iz = (b[keep].astype(np.int64) for b in bins)
    return iz, iy, ix, np.flatnonzero(keep)


def port_depth_jumps(spec: dict, depth: np.ndarray) -> np.ndarray:
    d = depth.astype(np.float32)
    padded = np.pad(d, 1, constant_values=np.nan)
    h, w = d.shape
    differences = [np.abs(padded[1 + dy:1 + dy + h, 1 + dx:1 + dx + w] - d) for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1))]
    largest = np.nanmax(np.stack(differences), axis=0)
    return largest > np.float32(spec["pseudo_points"]["depth_jumps"]["max_jump"]) * d


def port_thin(spec: dict, points: np.ndarray, lines: int) -> np.ndarray:
    """scan.thinning of a 64-line scan in scan order (its rings from the azimuth wraps; mode stride)."""
    assert spec["scan"]["thinning"]["mode"] == "stride"
    azimuth = np.arctan2(points[:, 1], points[:, 0])
    ring = np.concatenate([[0], np.cumsum(np.abs(np.diff(azimuth)) > np.pi)])
    elevation = np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1]))
    medians = [np.sort(elevation[ring == r])[(np.count_nonzero(ring == r) - 1) // 2] for r in range(ring[-1] + 1)]
    rank = np.empty(len(medians), np.int64)
    rank[np.argsort(medians, kind="stable")] = np.arange(len(medians))
    kept = np.arange(len(medians) - 1, -1, -(64 // lines))[:lines]
    return points[np.isin(rank[ring], kept)]


def _bins(bev: dict, xyz: np.ndarray) -> tuple[np.ndarray, ...]:
    """(iz, iy, ix) and the inside mask, by the spec's bin rule."""
    bins = []
    for axis, (low, cell, n) in enumerate(((bev["x_min"], bev["cell"], bev["nx"]), (bev["y_min"], bev["cell"], bev["ny"]),
                                           (bev["z_min"], bev["z_cell"], bev["nz"]))):
        b = np.floor((xyz[:, axis].astype(np.float64) - low) / cell)
        bins.append((b, (b >= 0) & (b < n)))
    inside = bins[0][1] & bins[1][1] & bins[2][1]
    return bins[2][0][inside].astype(np.int64), bins[1][0][inside].astype(np.int64), bins[0][0][inside].astype(np.int64), inside


def port_voxelize(spec: dict, points: np.ndarray, pseudo: np.ndarray | tuple | None = None,
                  sharp: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The BEV (C, ny, nx) and the height occupancy (nz, ny, nx) of real points and pseudo points (with the flags
    of those off depth jumps): pseudo as (M, 3) coordinates (binned as real points) or as the (iz, iy, ix) of
    :func:`port_pseudo_bins`."""
    bev = spec["bev"]
    ranges = bev["channel_ranges"]
    out = np.zeros(bev["shape"], np.float32)
    height = np.zeros((bev["nz"], bev["ny"], bev["nx"]), bool)
    iz, iy, ix, inside = _bins(bev, points)
    out[iz, iy, ix] = bev["occupied"]
    height[iz, iy, ix] = True
    plane = bev["ny"] * bev["nx"]
    counts = np.bincount(iy * bev["nx"] + ix, minlength=plane).astype(np.float64)
    sums = np.bincount(iy * bev["nx"] + ix, weights=points[inside, 3].astype(np.float64), minlength=plane)
    real = counts > 0
    if pseudo is not None:
        if isinstance(pseudo, tuple):
            (pz, py, px), pin = pseudo, np.arange(len(pseudo[0]))
        else:
            pz, py, px, pin = _bins(bev, pseudo)
        first = ranges["pseudo_occupancy"][0] if ranges["pseudo_occupancy"] else ranges["occupancy"][0]
        out[first + pz, py, px] = bev["occupied"]
        keep = sharp[pin]
        height[pz[keep], py[keep], px[keep]] = True
        if not ranges["pseudo_occupancy"]:  # shared channels: the pseudo points dilute the reflectance
            counts += np.bincount(py * bev["nx"] + px, minlength=plane)
    reflectance = np.zeros(plane, np.float64)
    reflectance[real] = sums[real] / counts[real]
    out[ranges["reflectance"][0]] = reflectance.reshape(bev["ny"], bev["nx"])
    return out, height


def port_decode(spec: dict, score: np.ndarray, regression: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    rule, grid = spec["decode"], spec["decode"]["output_grid"]
    flat = score.reshape(-1)
    index = np.flatnonzero(flat >= np.float32(threshold))
    if index.size > rule["max_candidates"]:
        index = index[np.argsort(-flat[index], kind="stable")[: rule["max_candidates"]]]
    index = index[np.lexsort((index, -flat[index]))]
    rows, columns = np.divmod(index, grid["nx"])
    t = {name: regression[c].reshape(-1)[index].astype(np.float64) * rule["reg_std"][c] + rule["reg_mean"][c]
         for c, name in enumerate(rule["regression_channels"])}
    low, high = rule["log_size_clip"]
    boxes = np.column_stack([
        spec["bev"]["x_min"] + (columns + 0.5) * grid["step"] + t["dx"],
        spec["bev"]["y_min"] + (rows + 0.5) * grid["step"] + t["dy"],
        np.exp(np.clip(t["log_l"], low, high)), np.exp(np.clip(t["log_w"], low, high)),
        np.arctan2(t["sin_yaw"], t["cos_yaw"]),
    ])
    return boxes, flat[index].astype(np.float64)


def _size_axes(spec: dict, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors along which l and w run (decode.box.size_directions)."""
    directions = spec["decode"]["box"]["size_directions"]
    return tuple(np.array([np.cos(yaw + directions[k]), np.sin(yaw + directions[k])]) for k in ("l", "w"))


def port_corners(spec: dict, box: np.ndarray) -> np.ndarray:
    """(4, 2) BEV corners of an (x, y, l, w, yaw) box, in order around it."""
    x, y, length, width, yaw = box
    along, across = _size_axes(spec, yaw)
    return np.array([(x, y) + a * length / 2 * along + b * width / 2 * across
                     for a, b in ((1, 1), (-1, 1), (-1, -1), (1, -1))])


def _polygon(spec: dict, box: np.ndarray) -> Polygon:
    return Polygon(port_corners(spec, box))


def port_nms(spec: dict, boxes: np.ndarray) -> np.ndarray:
    """Greedy NMS in the candidate order with exact rotated IoU (shapely)."""
    rule = spec["decode"]["nms"]
    polygons = [_polygon(spec, b) for b in boxes]
    kept: list[int] = []
    for i, polygon in enumerate(polygons):
        if len(kept) == rule["max_detections"]:
            break
        if all(polygon.intersection(polygons[k]).area / polygon.union(polygons[k]).area <= rule["iou_threshold"]
               for k in kept):
            kept.append(i)
    return np.asarray(kept, np.int64)


def port_heights(spec: dict, boxes: np.ndarray, height: np.ndarray, with_pseudo: bool) -> tuple[np.ndarray, np.ndarray]:
    rule, bev, grid = spec["heights"], spec["bev"], spec["decode"]["output_grid"]
    stride = spec["pixor"]["output_stride"]
    centre_y, centre_x = np.meshgrid(bev["y_min"] + (np.arange(grid["ny"]) + 0.5) * grid["step"],
                                     bev["x_min"] + (np.arange(grid["nx"]) + 0.5) * grid["step"], indexing="ij")
    z, h = np.full(len(boxes), rule["ground_z"] + rule["car_height"] / 2), np.full(len(boxes), rule["car_height"])
    for n, (x, y, length, width, yaw) in enumerate(boxes):
        (lx, ly), (wx, wy) = _size_axes(spec, yaw)
        along = (centre_x - x) * lx + (centre_y - y) * ly
        across = (centre_x - x) * wx + (centre_y - y) * wy
        histogram = np.zeros(bev["nz"], np.int64)
        for i, j in zip(*np.nonzero((np.abs(along) <= length / 2) & (np.abs(across) <= width / 2)), strict=True):
            histogram += height[:, stride * i:stride * (i + 1), stride * j:stride * (j + 1)].sum(axis=(1, 2))
        total, cumulative = histogram.sum(), np.cumsum(histogram)
        if total < rule["min_occupied"]:
            continue
        low = int(np.argmax(cumulative >= rule["quantiles"][0] * total))
        high = int(np.argmax(cumulative >= rule["quantiles"][1] * total))
        bottom = bev["z_min"] + (low + rule["bottom_in_slice_with_pseudo" if with_pseudo else "bottom_in_slice"]) * bev["z_cell"]
        measured = np.clip(bev["z_min"] + (high + 1) * bev["z_cell"] - bottom, *rule["height_range"])
        seen = total * rule["voxel_volume"]
        h[n] = (seen * measured + rule["prior_volume"] * rule["car_height"]) / (seen + rule["prior_volume"])
        z[n] = bottom + h[n] / 2
    return z, h


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def port_kitti_lines(spec: dict, boxes: np.ndarray, scores: np.ndarray, p2: np.ndarray, r0: np.ndarray, tr: np.ndarray,
                     image_hw: tuple[int, int]) -> list[str]:
    """kitti_results: the result lines of (x, y, z, l, w, h, yaw) boxes."""
    rule = spec["kitti_results"]
    places, near, (rows, columns) = rule["decimals"], rule["near_plane_m"], image_hw
    to_rect = _velo_to_rect(r0, tr)

    def project(rect: np.ndarray) -> np.ndarray:  # [u * depth, v * depth, depth]
        return p2 @ np.append(rect, 1.0)

    lines = []
    for (x, y, z, length, width, height, yaw), score in zip(boxes, scores, strict=True):
        seen_z = {"centre": z, "bottom_centre": z - height / 2}[rule["visibility_point"]]
        u, v, depth = project((to_rect @ [x, y, seen_z, 1.0])[:3])
        if not (depth > 0 and 0 <= u / depth < columns and 0 <= v / depth < rows):
            continue
        corners = port_corners(spec, np.array([x, y, length, width, yaw]))
        rect = np.array([(to_rect @ [cx, cy, cz, 1.0])[:3] for cz in (z - height / 2, z + height / 2) for cx, cy in corners])
        edges = [(k, (k + 1) % 4) for k in range(4)] + [(4 + k, 4 + (k + 1) % 4) for k in range(4)] + [(k, k + 4) for k in range(4)]
        ends = []
        for a, b in ((rect[i], rect[j]) for i, j in edges):
            if max(a[2], b[2]) <= near:
                continue  # wholly behind the near plane
            for end, other in ((a, b), (b, a)):
                ends.append(end if end[2] > near else end + (near - end[2]) / (other[2] - end[2]) * (other - end))
        if ends:
            uv = np.array([project(e)[:2] / project(e)[2] for e in ends])
            left, top = uv.min(axis=0)
            right, bottom = uv.max(axis=0)
            bbox = (min(max(left, 0), columns - 1), min(max(top, 0), rows - 1),
                    min(max(right, 0), columns - 1), min(max(bottom, 0), rows - 1))
        else:
            bbox = (0.0, 0.0, columns - 1.0, rows - 1.0)
        location = (to_rect @ [x, y, z - height / 2, 1.0])[:3]
        rotation_y = _wrap(-yaw - math.pi / 2)
        alpha = _wrap(rotation_y - math.atan2(location[0], location[2]))
        values = rule["values"]
        fields = [values["type"], f"{values['truncated']:.{places['truncated']}f}", f"{values['occluded']:.{places['occluded']}f}",
                  f"{alpha:.{places['alpha']}f}", *(f"{b:.{places['bbox']}f}" for b in bbox),
                  *(f"{d:.{places['dimensions']}f}" for d in (height, width, length)),
                  *(f"{c:.{places['location']}f}" for c in location), f"{rotation_y:.{places['rotation_y']}f}",
                  f"{score:.{places['score']}f}"]
        assert len(fields) == len(rule["fields"])
        lines.append(" ".join(fields))
    return lines


# --------------------------------------------------------------------------- the spec of each shipped model
@pytest.mark.parametrize("name", SHIPPED)
def test_spec_image_crop_and_view_calibration_are_the_pipelines(name: str) -> None:
    spec, preset, manifest = _spec_and_preset(name)
    for rows, columns in ((375, 1242), (376, 1241), (400, 1300), (352, 1216)):
        window = depth_crop((rows, columns), *preset.crop_hw)
        assert port_crop(spec, rows, columns) == (window.top, window.left)
        view = view_calibration((rows, columns), KITTI_CALIBRATION, preset)
        np.testing.assert_allclose(port_view_p2(spec, KITTI_CALIBRATION.P2, rows, columns), view.P2, rtol=0, atol=1e-9)
    image = np.random.default_rng(1).integers(0, 256, (*KITTI_IMAGE_HW, 3), dtype=np.uint8)
    assert np.array_equal(port_view_image(spec, image), network_view(image, KITTI_CALIBRATION, preset)[0])
    if "depth" in manifest["networks"]:
        inputs = {i["name"]: i["shape"] for i in manifest["networks"]["depth"]["inputs"]}
        assert inputs == {"rgb": spec["image"]["network_input"]["shape"],
                          "sparse_depth": spec["sparse_depth"]["network_input"]["shape"]}


@pytest.mark.parametrize("name", SHIPPED)
def test_spec_sparse_depth_is_the_pipelines(name: str) -> None:
    spec, preset, _ = _spec_and_preset(name)
    view = view_calibration(KITTI_IMAGE_HW, KITTI_CALIBRATION, preset)
    rng = np.random.default_rng(2)
    points = np.column_stack([rng.uniform(-5, 80, 20000), rng.uniform(-25, 25, 20000), rng.uniform(-3, 2, 20000),
                              rng.uniform(0, 1, 20000)])
    # Two returns just either side of min_depth on one pixel: the nearer one, if kept, would win it.
    min_depth = spec["sparse_depth"]["min_depth"]
    edge = view.image_to_velo(np.array([300.0, 300.0]), np.array([100.0, 100.0]), np.array([min_depth + 1e-4, min_depth - 1e-4]))
    points = np.vstack([points, np.column_stack([edge, np.zeros(2)])]).astype(np.float32)
    height, width = preset.depth.input_hw
    reference = sparse_depth_map(points, view, (height, width))
    port = port_sparse_depth(spec, points, port_view_p2(spec, KITTI_CALIBRATION.P2, *KITTI_IMAGE_HW),
                             KITTI_CALIBRATION.R0_rect, KITTI_CALIBRATION.Tr_velo_to_cam)
    assert reference[100, 300] == pytest.approx(min_depth + 1e-4, abs=1e-6)
    assert np.array_equal(port > 0, reference > 0)
    np.testing.assert_allclose(port, reference, rtol=1e-6)


@pytest.mark.parametrize("name", SHIPPED)
def test_spec_pseudo_points_and_depth_jumps_are_the_pipelines(name: str) -> None:
    spec, preset, _ = _spec_and_preset(name)
    view = view_calibration(KITTI_IMAGE_HW, KITTI_CALIBRATION, preset)
    rng = np.random.default_rng(3)
    depth = rng.uniform(0.5, 90.0, preset.depth.input_hw).astype(np.float32)
    depth[::7, ::5] = np.float32(preset.depth.min_depth)  # on the limits: kept (compared in float32)
    depth[3::11, ::3] = np.float32(preset.depth.max_depth)
    reference = depth_to_points(depth, view, *preset.pseudo_limits)
    port, _ = port_pseudo_points(spec, depth, port_view_p2(spec, KITTI_CALIBRATION.P2, *KITTI_IMAGE_HW),
                                 KITTI_CALIBRATION.R0_rect, KITTI_CALIBRATION.Tr_velo_to_cam)
    assert port.shape == (len(reference), 3)
    np.testing.assert_allclose(port, reference[:, :3], rtol=0, atol=1e-4)
    assert not reference[:, 3].any() and spec["pseudo_points"]["reflectance"] == 0.0
    # The exact rules: the points bit for bit, the BEV's pseudo bins voxel for voxel.
    view_p2, r0, tr = view.P2, view.R0_rect, view.Tr_velo_to_cam
    assert np.array_equal(port_pseudo_points_exact(spec, depth, view_p2, r0, tr), reference[:, :3])
    iz, iy, ix, _ = port_pseudo_bins(spec, depth, view_p2, r0, tr)
    bev = spec["bev"]
    assert np.array_equal((iz * bev["ny"] + iy) * bev["nx"] + ix, pseudo_bins(depth, view, preset.bev, *preset.pseudo_limits).occupancy)
    smooth = np.cumsum(rng.uniform(0.0, 0.3, preset.depth.input_hw), axis=0).astype(np.float32) + 5
    for map_ in (depth, smooth):
        assert np.array_equal(port_depth_jumps(spec, map_), depth_jumps(map_, preset.decode.height_max_jump))


@pytest.mark.parametrize("name", SHIPPED)
def test_spec_bev_is_the_pipelines(name: str) -> None:
    spec, preset, manifest = _spec_and_preset(name)
    bev = spec["bev"]
    assert manifest["bev_grid"] == {k: bev[k] for k in manifest["bev_grid"]}  # the manifest's own copy agrees
    axes = [(bev["x_min"], bev["x_max"], bev["cell"]), (bev["y_min"], bev["y_max"], bev["cell"]),
            (bev["z_min"], bev["z_max"], bev["z_cell"])]
    edges = [[low - 1e-3, low, low + cell, (low + high) / 2, high - 1e-3, high] for low, high, cell in axes]
    rng = np.random.default_rng(4)
    probes = np.array(list(itertools.product(*edges)))
    scattered = np.column_stack([rng.uniform(low - 2, high + 2, 6000) for low, high, _ in axes])
    xyz = np.vstack([probes, scattered, scattered[:500] + 0.01])  # some cells with several points
    points = np.column_stack([xyz, rng.uniform(0, 1, len(xyz))]).astype(np.float32)
    pseudo = np.column_stack([rng.uniform(low - 1, high + 1, 6000) for low, high, _ in axes]).astype(np.float32)
    reference = voxelize_bev(points, preset.bev, pseudo=tuple(pseudo.T))
    port, _ = port_voxelize(spec, points, pseudo, np.ones(len(pseudo), bool))
    assert list(reference.shape) == bev["shape"] == manifest["networks"]["pixor"]["inputs"][0]["shape"][1:]
    np.testing.assert_allclose(port, reference, rtol=0, atol=1e-6)
    assert np.array_equal(port != 0, reference != 0)


@pytest.fixture(scope="module")
def real_depth_maps() -> dict[str, tuple]:
    """The shipped camera model's depth maps of KITTI 000004 and 000006 (their scans thinned to 16 lines) and the
    view calibration of each."""
    preset = preset_from_dict(_manifest("edge")["preset_config"])
    session = ort.InferenceSession(str(WEIGHTS / "edge" / "depth.onnx"), providers=["CPUExecutionProvider"])
    maps = {}
    for frame_id in ("000004", "000006"):
        frame = load_frame(KITTI, frame_id, with_labels=False)
        inputs = depth_inputs(frame.image, emulate_beams(frame.points, 16), frame.calib, preset)
        (depth,) = session.run(["depth"], {"rgb": inputs.rgb, "sparse_depth": inputs.sparse_depth})
        maps[frame_id] = depth[0, 0], inputs.calib
    return maps


@pytest.mark.parametrize("frame_id", ["000004", "000006"])
def test_spec_pseudo_points_and_bins_are_the_pipelines_on_real_depth_maps(frame_id: str, real_depth_maps: dict) -> None:
    """pseudo_points.rays/.point give the points bit for bit and bev.pseudo_bin the BEV's pseudo voxels one for one;
    the float64 back-projection stays within its stated bound, and on 000004 the real points' bin rule on it
    puts a voxel elsewhere (what bev.pseudo_bin is for)."""
    spec, preset, _ = _spec_and_preset("edge")
    depth, view = real_depth_maps[frame_id]
    view_p2, r0, tr = view.P2, view.R0_rect, view.Tr_velo_to_cam
    reference = depth_to_points(depth, view, *preset.pseudo_limits)[:, :3]
    assert np.array_equal(port_pseudo_points_exact(spec, depth, view_p2, r0, tr), reference)
    float64_points, _ = port_pseudo_points(spec, depth, view_p2, r0, tr)
    assert np.abs(float64_points - reference).max() < 6e-6  # pseudo_points.float64_rule
    bev = spec["bev"]
    iz, iy, ix, _ = port_pseudo_bins(spec, depth, view_p2, r0, tr)
    runtime = pseudo_bins(depth, view, preset.bev, *preset.pseudo_limits)
    assert np.array_equal((iz * bev["ny"] + iy) * bev["nx"] + ix, runtime.occupancy)
    fz, fy, fx, _ = _bins(bev, float64_points)
    moved = set(((fz * bev["ny"] + fy) * bev["nx"] + fx).tolist()) ^ set(runtime.occupancy.tolist())
    assert len(moved) == (1 if frame_id == "000004" else 0)  # bev.pseudo_bin.why: one voxel set by one rule only


def test_spec_pseudo_bins_on_a_grid_whose_z_cell_is_not_its_cell() -> None:
    """bev.pseudo_bin.scale per axis: the tiny grid's voxels are 0.4 m wide and 0.5 m high (the shipped ones cubes)."""
    preset = get_preset("tiny")
    spec = json.loads(json.dumps(port_spec(preset)))
    assert preset.bev.cell != preset.bev.z_cell
    view = view_calibration(KITTI_IMAGE_HW, KITTI_CALIBRATION, preset)
    depth = np.random.default_rng(10).uniform(0.5, 90.0, preset.depth.input_hw).astype(np.float32)
    iz, iy, ix, _ = port_pseudo_bins(spec, depth, view.P2, view.R0_rect, view.Tr_velo_to_cam)
    bev = spec["bev"]
    assert np.array_equal((iz * bev["ny"] + iy) * bev["nx"] + ix, pseudo_bins(depth, view, preset.bev, *preset.pseudo_limits).occupancy)


@pytest.mark.parametrize("name", SHIPPED)
def test_spec_box_sizes_run_along_and_across_the_yaw(name: str) -> None:
    spec, _, _ = _spec_and_preset(name)
    rng = np.random.default_rng(8)
    boxes = np.column_stack([rng.uniform(0, 60, 50), rng.uniform(-30, 30, 50), rng.uniform(0, 2, 50) - 1,
                             rng.uniform(3, 5, 50), rng.uniform(1.4, 2, 50), rng.uniform(1.4, 1.8, 50), rng.uniform(-4, 4, 50)])
    for box, corners in zip(boxes, bev_corners(boxes), strict=True):
        np.testing.assert_allclose(port_corners(spec, box[[0, 1, 3, 4, 6]]), corners, rtol=0, atol=1e-12)


def test_spec_kitti_result_lines_are_the_pipelines() -> None:
    """The result lines a port writes from kitti_results equal the pipeline's, character for character: the
    bundled frames' labelled cars and boxes around the camera (some reaching behind the near plane, some whose
    centre the camera sees and bottom centre not, or the other way round)."""
    spec, _, _ = _spec_and_preset("edge")
    rng = np.random.default_rng(9)
    checked = near_plane_decides = centre_decides = 0
    for frame_id in ("000000", "000001", "000003", "000004", "000006"):
        frame = load_frame(KITTI, frame_id)
        calib, image_hw = frame.calib, frame.image.shape[:2]
        labelled = labels_to_boxes([o for o in frame.labels if o.type != "DontCare"], calib)
        n = 400  # around the camera, and 50 of them again 8 m ahead on the road
        near = np.column_stack([rng.uniform(-1.5, 4, n), rng.uniform(-3, 3, n), rng.uniform(-1.5, 1, n),
                                rng.uniform(0.5, 6, n), rng.uniform(0.3, 3, n), rng.uniform(0.2, 3, n), rng.uniform(-4, 4, n)])
        boxes = np.vstack([labelled, near, near[:50] * [1, 1, 0, 1, 1, 1, 1] + [8, 0, -1, 0, 0, 0, 0]])
        scores = rng.uniform(0, 1, len(boxes))
        seen = in_camera_view(boxes, calib, image_hw)
        expected = [format_label(o) for o in boxes_to_objects(boxes[seen], calib, image_hw, scores[seen])]
        matrices = (calib.P2, calib.R0_rect, calib.Tr_velo_to_cam)
        assert port_kitti_lines(spec, boxes, scores, *matrices, image_hw) == expected
        checked += len(expected)
        # The set is one where the stated near plane and visibility point matter.
        moved = json.loads(json.dumps(spec))
        moved["kitti_results"]["near_plane_m"] *= 2
        near_plane_decides += sum(a != b for a, b in zip(port_kitti_lines(moved, boxes, scores, *matrices, image_hw),
                                                         expected, strict=True))
        moved = json.loads(json.dumps(spec))
        moved["kitti_results"]["visibility_point"] = "bottom_centre"
        centre_decides += port_kitti_lines(moved, boxes, scores, *matrices, image_hw) != expected
    assert checked > 100 and near_plane_decides > 0 and centre_decides > 0
    document, heading = spec["kitti_results"]["docs"].split(", ")
    assert f"**{heading.strip(chr(39))}**" in (ROOT / document).read_text()  # the pointer names a real paragraph


def test_spec_beam_thinning_is_the_pipelines() -> None:
    """scan.thinning names the function the golden scans go through, and its rule, ported, keeps the same points
    of the bundled 64-line scans; a scan with 16 lines already is refused, so a 16-line sensor's goes in as stored."""
    spec, _, _ = _spec_and_preset("edge")
    thinning = spec["scan"]["thinning"]
    module, function = thinning["function"].rsplit(".", 1)
    thin = getattr(importlib.import_module(module), function)
    assert thin is emulate_beams
    for frame_id in ("000004", "000006"):
        points = load_frame(KITTI, frame_id, with_labels=False, with_image=False).points
        for lines in (16, 32, 8):
            thinned = thin(points, lines, thinning["mode"])
            assert np.array_equal(port_thin(spec, points, lines), thinned)
        with pytest.raises(InputError, match="thinned already"):
            thin(thin(points, 16, thinning["mode"]), 16, thinning["mode"])


@pytest.mark.parametrize("name", SHIPPED)
def test_spec_decode_and_nms_are_the_pipelines(name: str) -> None:
    spec, preset, manifest = _spec_and_preset(name)
    grid, stride, decode = preset.bev, preset.pixor.output_stride, preset.decode
    outputs = {o["name"]: o["shape"] for o in manifest["networks"]["pixor"]["outputs"]}
    assert outputs == {"score": spec["pixor"]["score"]["shape"], "regression": spec["pixor"]["regression"]["shape"]}
    shape = (grid.ny // stride, grid.nx // stride)
    rng = np.random.default_rng(5)
    regression = rng.normal(0, 0.5, (6, *shape)).astype(np.float32)
    score = np.zeros(shape, np.float32)
    threshold = np.float32(decode.score_threshold)
    cells = {(10, 10): 0.95, (10, 11): 0.95, (50, 40): threshold, (60, 40): np.nextafter(threshold, np.float32(0)),
             (70, 20): 0.7}
    for (i, j), value in cells.items():
        score[i, j] = value
    regression[5, 10, 10], regression[4, 10, 11] = 100.0, -100.0  # log sizes far past the clip
    for maps in ((score, regression), (rng.uniform(0, 1, shape).astype(np.float32), regression)):
        boxes, scores = decode_maps(*maps, grid, stride, decode)
        port_boxes, port_scores = port_decode(spec, *maps, decode.score_threshold)
        np.testing.assert_allclose(port_boxes, boxes, rtol=0, atol=1e-9)
        assert np.array_equal(port_scores, scores)
    # A cluster per car, some neighbours apart: greedy NMS with shapely's IoU keeps what rotated_nms keeps.
    centres = rng.uniform([5, -20], [60, 20], (6, 2)).repeat(15, axis=0) + rng.normal(0, 0.6, (90, 2))
    candidates = np.column_stack([centres, rng.uniform(3.5, 4.5, 90), rng.uniform(1.5, 1.9, 90), rng.uniform(-3, 3, 90)])
    ranked = np.argsort(-rng.uniform(0, 1, 90), kind="stable")
    candidates = candidates[ranked]
    assert np.array_equal(port_nms(spec, candidates),
                          rotated_nms(candidates, np.linspace(1, 0, 90), decode.nms_iou, decode.max_detections))
    # Mirror TTA negates the targets the spec names.
    assert [spec["decode"]["regression_channels"].index(t) for t in spec["mirror_tta"]["negated"]] == MIRRORED_TARGETS


@pytest.mark.parametrize("name", SHIPPED)
def test_spec_box_heights_are_the_pipelines(name: str) -> None:
    spec, preset, _ = _spec_and_preset(name)
    grid = preset.bev
    rng = np.random.default_rng(6)
    occupancy = np.zeros((grid.nz, grid.ny, grid.nx), np.uint8)
    for _ in range(40):  # columns of returns, as cars give
        row, column = rng.integers(0, grid.ny - 12), rng.integers(0, grid.nx - 20)
        low, high = sorted(rng.integers(0, grid.nz, 2))
        occupancy[low:high + 1, row:row + 10, column:column + 18] = rng.uniform(0, 1, (high + 1 - low, 10, 18)) < 0.3
    boxes = np.column_stack([rng.uniform(2, 68, 30), rng.uniform(-38, 38, 30), rng.uniform(3, 5, 30),
                             rng.uniform(1.4, 2.0, 30), rng.uniform(-3, 3, 30)])
    for with_pseudo in (False, True):
        z, h = estimate_heights(boxes, occupancy, preset, with_pseudo)
        port_z, port_h = port_heights(spec, boxes, occupancy.astype(bool), with_pseudo)
        np.testing.assert_allclose(np.column_stack([port_z, port_h]), np.column_stack([z, h]), rtol=0, atol=1e-9)
    assert (h != spec["heights"]["car_height"]).any() and (h == spec["heights"]["car_height"]).any()


def test_new_exports_write_the_spec_into_the_manifest(tiny_models: Path) -> None:
    """The shipped manifests predate the ``port`` section; a new export writes it, the preset's own."""
    manifest = json.loads((tiny_models / "manifest.json").read_text())
    spec, source = port_spec_of(manifest)
    assert source == "manifest"
    assert spec == json.loads(json.dumps(port_spec(get_preset("tiny"))))
    assert "uint8_equivalent" not in spec["image"]["resize"]  # ×¼: OpenCV's own rounding, no integer rule given


# --------------------------------------------------------------------------- the graphs
@pytest.mark.parametrize("name", SHIPPED)
def test_graph_report_gives_each_graphs_interface_and_what_tensorrt_refuses(name: str) -> None:
    manifest = _manifest(name)
    for network, entry in manifest["networks"].items():
        path = WEIGHTS / name / entry["file"]
        onnx.checker.check_model(onnx.load(str(path)), full_check=True)
        report = graph_report(path)
        assert report["static_shapes"] and not report["external_data"] and report["opset"] == 18
        assert [{"name": i["name"], "shape": i["shape"]} for i in report["inputs"]] == entry["graph_inputs"]
        assert [(o["name"], o["shape"], o["dtype"]) for o in report["outputs"]] == \
            [(o["name"], o["shape"], o["dtype"]) for o in entry["outputs"]]
        assert all(i["dtype"] == "float32" for i in report["inputs"])
        quantized = "QuantizeLinear" in report["ops"]
        assert quantized == (manifest.get("precision") == "int8")
        notes = report["tensorrt"]
        assert notes[0].startswith("opset 18: TensorRT 10 parses it")
        assert len(notes) == (2 if quantized else 1) and (not quantized or "zero point 0" in notes[1])
        if network == "depth":  # the normalisation the spec leaves to the graph is the manifest's
            graph = onnx.load(str(path)).graph
            stored = {i.name: onnx.numpy_helper.to_array(i) for i in graph.initializer}
            for op, key in (("Sub", "rgb_mean"), ("Div", "rgb_std")):
                node = next(n for n in graph.node if n.op_type == op and n.input[0] in ("rgb", "sub"))
                np.testing.assert_allclose(stored[node.input[1]].ravel(), manifest["normalisation"][key], rtol=1e-6)


# --------------------------------------------------------------------------- the golden frame
@pytest.fixture(scope="module")
def golden(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The golden set of the shipped camera model on KITTI 000006, written on a runtime without torch."""
    out = tmp_path_factory.mktemp("golden")
    subprocess.run([sys.executable, "-c", HIDE_TORCH + "runpy.run_module('export.golden', run_name='__main__')",
                    "--models", str(WEIGHTS / "edge"), "--data", str(KITTI), "--frame", "000006", "--out", str(out)],
                   check=True, cwd=ROOT, timeout=300)
    return out


def _load(folder: Path) -> tuple[dict, dict, dict[str, np.ndarray]]:
    """golden.json, port.json and the arrays, read as a port without NumPy's .npy reader would: raw bytes at the
    recorded offset."""
    index = json.loads((folder / "golden.json").read_text())
    spec = json.loads((folder / "port.json").read_text())
    arrays = {}
    for name, entry in index["arrays"].items():
        raw = np.fromfile(folder / entry["file"], dtype=np.dtype(entry["dtype"]), offset=entry["data_offset"])
        arrays[name] = raw.reshape(entry["shape"])
        assert np.array_equal(arrays[name], np.load(folder / entry["file"])), name
    return index, spec, arrays


def _pixor_feeds(spec: dict, session: ort.InferenceSession, bev: np.ndarray) -> dict[str, np.ndarray]:
    """bev[lo:hi] inputs from the names the graphs section gives."""
    feeds = {}
    for graph_input in spec["graphs"]["pixor"]["inputs"]:
        piece = re.fullmatch(r"bev\[(\d+):(\d+)\]", graph_input["name"])
        feeds[graph_input["name"]] = bev if piece is None else bev[:, int(piece[1]):int(piece[2])]
    assert set(feeds) == {i.name for i in session.get_inputs()}
    return feeds


def test_a_port_from_the_spec_reproduces_every_golden_stage(golden: Path) -> None:
    index, spec, a = _load(golden)
    stages = {stage["stage"]: stage for stage in index["stages"]}
    assert list(stages) == ["prepare", "depth_net", "pseudo_points", "voxelize", "pixor", "decode"]
    assert spec["spec_source"].startswith("computed") and spec["models"]["scan_lines"] == 16
    calib = index["calibration"]
    r0, tr = np.array(calib["R0_rect"]), np.array(calib["Tr_velo_to_cam"])
    view_p2 = port_view_p2(spec, np.array(calib["P2"]), *a["image"].shape[:2])
    np.testing.assert_allclose(view_p2, calib["view_P2"], rtol=0, atol=1e-9)

    # prepare: exact, with the integer rule for the ×½ resize
    assert np.array_equal(port_view_image(spec, a["image"]), a["view_image"])
    assert np.array_equal(a["view_image"].transpose(2, 0, 1)[None].astype(np.float32), a["rgb"])
    sparse = port_sparse_depth(spec, a["points"], view_p2, r0, tr)
    assert np.array_equal(sparse > 0, a["sparse_depth"][0, 0] > 0)
    np.testing.assert_allclose(sparse, a["sparse_depth"][0, 0], rtol=stages["prepare"]["tolerance"]["sparse_depth"]["rtol"])

    # depth_net, fed by name
    session = ort.InferenceSession(str(WEIGHTS / "edge" / "depth.onnx"), providers=["CPUExecutionProvider"])
    (depth,) = session.run(["depth"], {"rgb": a["rgb"], "sparse_depth": a["sparse_depth"]})
    np.testing.assert_allclose(depth, a["depth"], rtol=stages["depth_net"]["tolerance"]["depth"]["rtol"])

    # pseudo points from the golden depth
    pseudo, pixel = port_pseudo_points(spec, a["depth"][0, 0], view_p2, r0, tr)
    assert pseudo.shape[0] == a["pseudo_points"].shape[0]
    np.testing.assert_allclose(pseudo, a["pseudo_points"][:, :3], rtol=0,
                               atol=stages["pseudo_points"]["tolerance"]["pseudo_points"]["atol_m"])
    jumps = port_depth_jumps(spec, a["depth"][0, 0])
    assert np.array_equal(jumps, a["depth_jumps"].astype(bool))
    # by the exact rule (pseudo_points.rays, .point): bit for bit
    assert np.array_equal(port_pseudo_points_exact(spec, a["depth"][0, 0], view_p2, r0, tr), a["pseudo_points"][:, :3])

    # voxelize the golden scan and the port's pseudo points: within the tolerance from the float64 points …
    bev, height = port_voxelize(spec, a["points"], pseudo, ~jumps.reshape(-1)[pixel])
    real = spec["bev"]["channel_ranges"]["reflectance"][1]
    np.testing.assert_allclose(bev[:real], a["bev"][0, :real], rtol=0, atol=1e-6)
    tolerance = stages["voxelize"]["tolerance"]
    pseudo_golden = a["bev"][0, real:]
    assert (bev[real:] != pseudo_golden).sum() <= tolerance["bev"]["pseudo_voxels_differing_max_share"] * pseudo_golden.sum()
    assert (height != a["height_occupancy"].astype(bool)).sum() <= \
        tolerance["height_occupancy"]["voxels_differing_max_share"] * a["height_occupancy"].sum()
    # … and exactly by bev.pseudo_bin, straight from the depth map
    *bins, pixel = port_pseudo_bins(spec, a["depth"][0, 0], view_p2, r0, tr)
    bev, height = port_voxelize(spec, a["points"], tuple(bins), ~jumps.reshape(-1)[pixel])
    assert np.array_equal(bev, a["bev"][0]) and np.array_equal(height, a["height_occupancy"].astype(bool))

    # pixor on the golden BEV, its graph inputs as channel ranges of it
    session = ort.InferenceSession(str(WEIGHTS / "edge" / "pixor.onnx"), providers=["CPUExecutionProvider"])
    score, regression = session.run(["score", "regression"], _pixor_feeds(spec, session, a["bev"]))
    np.testing.assert_allclose(score, a["score"], rtol=0, atol=stages["pixor"]["tolerance"]["score"]["atol"])
    np.testing.assert_allclose(regression, a["regression"], rtol=0, atol=stages["pixor"]["tolerance"]["regression"]["atol"])

    # decode, NMS and heights on the golden maps and height occupancy
    threshold = index["frame"]["score_threshold"]
    candidates, scores = port_decode(spec, a["score"][0, 0], a["regression"][0], threshold)
    np.testing.assert_allclose(candidates, a["candidates"], rtol=0, atol=stages["decode"]["tolerance"]["candidates"]["atol"])
    assert np.array_equal(scores, a["candidate_scores"])
    kept = port_nms(spec, candidates)
    assert np.array_equal(kept, a["kept"]) and len(kept) > 0
    z, h = port_heights(spec, candidates[kept], a["height_occupancy"].astype(bool), spec["models"]["two_stage"])
    boxes = np.column_stack([candidates[kept, :2], z, candidates[kept, 2:4], h, candidates[kept, 4]])
    np.testing.assert_allclose(boxes, a["boxes"], rtol=0, atol=stages["decode"]["tolerance"]["boxes"]["atol"])


def test_the_whole_port_chained_gives_the_golden_boxes(golden: Path) -> None:
    """Chained, each stage on the port's own output of the one before: the boxes agree within end_to_end."""
    index, spec, a = _load(golden)
    calib = index["calibration"]
    r0, tr = np.array(calib["R0_rect"]), np.array(calib["Tr_velo_to_cam"])
    view_p2 = port_view_p2(spec, np.array(calib["P2"]), *a["image"].shape[:2])
    rgb = port_view_image(spec, a["image"]).transpose(2, 0, 1)[None].astype(np.float32)
    sparse = port_sparse_depth(spec, a["points"], view_p2, r0, tr)[None, None]
    depth_net = ort.InferenceSession(str(WEIGHTS / "edge" / "depth.onnx"), providers=["CPUExecutionProvider"])
    (depth,) = depth_net.run(["depth"], {"rgb": rgb, "sparse_depth": sparse})
    pseudo, pixel = port_pseudo_points(spec, depth[0, 0], view_p2, r0, tr)
    bev, height = port_voxelize(spec, a["points"], pseudo, ~port_depth_jumps(spec, depth[0, 0]).reshape(-1)[pixel])
    pixor = ort.InferenceSession(str(WEIGHTS / "edge" / "pixor.onnx"), providers=["CPUExecutionProvider"])
    score, regression = pixor.run(["score", "regression"], _pixor_feeds(spec, pixor, bev[None]))
    candidates, scores = port_decode(spec, score[0, 0], regression[0], index["frame"]["score_threshold"])
    kept = port_nms(spec, candidates)
    z, h = port_heights(spec, candidates[kept], height, with_pseudo=True)
    tolerance = index["end_to_end"]["tolerance"]
    sure = a["scores"] >= index["frame"]["score_threshold"] + tolerance["score_atol"]
    assert sure.any()
    for box, golden_score in zip(a["boxes"][sure], a["scores"][sure], strict=True):
        polygon = _polygon(spec, box[[0, 1, 3, 4, 6]])
        ious = [polygon.intersection(p).area / polygon.union(p).area for p in (_polygon(spec, c) for c in candidates[kept])]
        best = int(np.argmax(ious))
        assert ious[best] >= tolerance["bev_iou_min"] and abs(scores[kept][best] - golden_score) <= tolerance["score_atol"]
        assert abs(z[best] - box[2]) < 0.2 and abs(h[best] - box[5]) < 0.2


def test_the_golden_result_lines_are_the_specs_on_the_golden_boxes(golden: Path, tmp_path: Path) -> None:
    """result_lines.txt (a port had only pipeline.detect's output to check its last stage against): the spec's
    kitti_results on the golden boxes and scores gives it character for character, and it is detect's file."""
    from pipeline.detect import main as detect_main

    index, spec, a = _load(golden)
    calib, lines = index["calibration"], index["result_lines"]
    ported = port_kitti_lines(spec, a["boxes"], a["scores"], np.array(calib["P2"]), np.array(calib["R0_rect"]),
                              np.array(calib["Tr_velo_to_cam"]), tuple(lines["image_hw"]))
    written = (golden / lines["file"]).read_text(encoding="utf-8")
    assert lines["lines"] == len(ported) > 0 and written == "".join(f"{line}\n" for line in ported)
    out = tmp_path / "detect"
    assert detect_main(["--models", str(WEIGHTS / "edge"), "--data", str(KITTI), "--frame", index["frame"]["frame"],
                        "--emulate-beams", str(index["frame"]["emulate_beams"]), "--no-pictures", "--no-progress",
                        "--out", str(out)]) == 0
    assert (out / "data" / f"{index['frame']['frame']}.txt").read_text(encoding="utf-8") == written


def test_a_lidar_only_golden_set_has_no_camera_stages_and_the_port_reproduces_it(tmp_path: Path) -> None:
    """The 16-line PIXOR's golden set: the scan, the shared-channel BEV and the decode, which the port matches."""
    from export.golden import write_golden

    write_golden(WEIGHTS / "edge-lidar16", tmp_path, KITTI, "000006")
    index, spec, a = _load(tmp_path)
    assert [s["stage"] for s in index["stages"]] == ["voxelize", "pixor", "decode"] and "image" not in a
    assert index["frame"]["emulate_beams"] == 16 and len(a["points"]) == index["frame"]["points"]
    scan = load_frame(KITTI, "000006", with_labels=False, with_image=False).points  # scan.thinning, ported
    assert np.array_equal(a["points"], port_thin(spec, scan, index["frame"]["emulate_beams"]))
    bev, height = port_voxelize(spec, a["points"])
    assert np.array_equal(bev, a["bev"][0]) and np.array_equal(height, a["height_occupancy"].astype(bool))
    candidates, _ = port_decode(spec, a["score"][0, 0], a["regression"][0], index["frame"]["score_threshold"])
    kept = port_nms(spec, candidates)
    z, h = port_heights(spec, candidates[kept], height, with_pseudo=False)
    np.testing.assert_allclose(np.column_stack([z, h]), a["boxes"][:, [2, 5]], rtol=0, atol=1e-6)


# --------------------------------------------------------------------------- the command
def test_golden_command_answers_help_and_refuses_what_it_would_not_use(tmp_path: Path) -> None:
    def run(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-c", HIDE_TORCH + "runpy.run_module('export.golden', run_name='__main__')",
                               *args], capture_output=True, text=True, cwd=ROOT, timeout=120, check=False)

    helped = run("--help")
    assert helped.returncode == 0 and all(flag in helped.stdout for flag in ("--models", "--data", "--frame", "--out"))
    refused = run("--spec-only", "--frame", "000001", "--out", str(tmp_path / "spec"))
    assert refused.returncode == 2 and "--spec-only" in refused.stderr and not (tmp_path / "spec").exists()
    models = shutil.copytree(WEIGHTS / "edge-lidar16", tmp_path / "edge-lidar16")  # a regression writes there
    inside = run("--models", str(models), "--out", str(models / "golden"))
    assert inside.returncode == 2 and "Traceback" not in inside.stderr and not (models / "golden").exists()
    spec_only = run("--models", str(WEIGHTS / "edge-lidar16"), "--spec-only", "--out", str(tmp_path / "spec"))
    assert spec_only.returncode == 0, spec_only.stderr
    written = json.loads((tmp_path / "spec" / "port.json").read_text())
    assert written["models"]["two_stage"] is False and list(written["graphs"]) == ["pixor"]
    assert sorted(p.name for p in (tmp_path / "spec").iterdir()) == ["port.json"]
