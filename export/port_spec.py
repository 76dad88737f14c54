"""What a re-implementation of the NumPy stages needs, machine-readable: the ``port`` section and ``port.json``.

The networks are ONNX files; everything around them (the depth net's inputs, the pseudo point cloud, the BEV
voxelization, decoding, rotated NMS and box heights) is NumPy in pipeline/. A port to another runtime (C++ over
ONNX Runtime's C API or TensorRT) rebuilds those stages from this spec: each constant with its value and each
rule in the units and conventions the code uses. Exports write it into the manifest (``port``); for a manifest
from before that, :func:`port_spec_of` computes it from the manifest's ``preset_config``.
:func:`graph_report` describes an ONNX file as a port meets it (inputs, outputs, opset, operators and what
TensorRT's ONNX parser refuses). tests/test_porting.py checks every value against what the pipeline does, so
the spec cannot drift from the code. No torch here: the golden command (export/golden.py) runs on the runtime.
"""

from __future__ import annotations

import inspect
import math
from collections import Counter
from pathlib import Path

import numpy as np

from pipeline.boxes import NEAR_PLANE_M
from pipeline.calib import sparse_depth_map
from pipeline.kitti import RESULT_DECIMALS
from pipeline.postprocess import _HEIGHT_RANGE, _HIGH_Q, _LOW_Q  # private, but the values the heights use
from pipeline.presets import Preset, preset_from_dict
from pipeline.targets import LOG_SIZE_CLIP  # decode_maps clips the log sizes so: boxes 0.05–20 m at most

PORT_FORMAT = "lowres3d-port/1"
REGRESSION_CHANNELS = ("cos_yaw", "sin_yaw", "dx", "dy", "log_w", "log_l")  # pipeline/targets.py
# Mirror TTA (pipeline/detector.py, MIRRORED_TARGETS): the targets whose sign a left-right mirror flips.
MIRROR_NEGATED = ("sin_yaw", "dy")
# Each box size's direction as an angle from the box's yaw: l along the heading, w across it (pipeline/iou.py
# rect_corners); tests/test_porting.py builds corners from these and checks them against the pipeline's.
SIZE_DIRECTIONS = {"l": 0.0, "w": math.pi / 2}
# TensorRT's ONNX parser: opsets up to 17 before TensorRT 10 (8.5 and 8.6: JetPack 5 and JetPack 6.0), 9–20 from 10.0.
TENSORRT_8_MAX_OPSET = 17
TENSORRT_10_MAX_OPSET = 20
# Operators TensorRT's ONNX parser does not import (its operator matrix, 8.x–10.x) that a converted CNN may hold.
TENSORRT_UNSUPPORTED_OPS = frozenset({
    "ConvInteger", "MatMulInteger", "QLinearConv", "QLinearMatMul", "DynamicQuantizeLinear", "MaxUnpool",
    "MaxRoiPool", "Compress", "Unique", "Det", "BitShift", "StringNormalizer", "TfIdfVectorizer", "Multinomial",
    "SequenceAt", "SequenceConstruct", "SequenceEmpty", "SequenceErase", "SequenceInsert", "SequenceLength",
    "SplitToSequence", "ConcatFromSequence", "Optional", "OptionalGetElement", "OptionalHasElement", "Col2Im",
})


def port_spec(preset: Preset) -> dict:
    """Every constant and rule of the NumPy stages of ``preset``'s pipeline, as plain JSON."""
    return {
        "format": PORT_FORMAT,
        "scan": scan_section(),
        "image": image_section(preset),
        "view_calibration": view_calibration_section(preset),
        "sparse_depth": sparse_depth_section(preset),
        "pseudo_points": pseudo_points_section(preset),
        "bev": bev_section(preset),
        "pixor": pixor_section(preset),
        "decode": decode_section(preset),
        "heights": heights_section(preset),
        "mirror_tta": mirror_section(),
        "kitti_results": kitti_results_section(),
    }


def port_spec_of(manifest: dict) -> tuple[dict, str]:
    """The port spec of a model directory's manifest, and where it came from: its own ``port`` section, or
    (a manifest written before exports had one) computed from its ``preset_config``."""
    if isinstance(manifest.get("port"), dict):
        return manifest["port"], "manifest"
    return port_spec(preset_from_dict(manifest["preset_config"])), "computed from preset_config (no 'port' section)"


def scan_section() -> dict:
    """The LiDAR scan as every stage reads it."""
    return {
        "columns": ["x", "y", "z", "reflectance"],
        "dtype": "float32",
        "frame": "LiDAR (velodyne): x forward, y left, z up, metres",
        "reflectance_range": [0.0, 1.0],
        "reflectance_note": "KITTI's scale: divide 0-255 intensities by 255",
        "lines": "the line count the model learned from: port.json models.scan_lines (16 for the shipped models but "
                 "edge-lidar64); a golden set's scan is the bundled 64-line one thinned to golden.json "
                 "frame.emulate_beams lines (0: as stored)",
        "thinning": {
            "function": "pipeline.beams.emulate_beams",
            "mode": "stride",
            "rings": "a new ring wherever |atan2(y, x) - atan2(y, x) of the point before| > pi (the azimuth wraps; "
                     "float32, scan order), when that gives 16 to 200 rings of 200 points or more on average; "
                     "else 64 clusters of the elevations (1-D k-means); a 64-line KITTI scan gives 64-65 rings",
            "rank": "rings by their median elevation atan2(z, hypot(x, y)) (of an even count the lower middle one), "
                    "lowest 0",
            "keep": "n rings: those ranked n-1, n-1-k, n-1-2k … (k = 64 / lines), the first `lines` of them; the kept "
                    "points in their order in the scan",
            "refused": "a scan thinned already: azimuth wraps giving fewer than 56 rings, or (clustered) far returns "
                       "whose elevations leave the gaps of beams far apart",
            "docs": "README.md, 'Conventions and design decisions' (16-line emulation) and 'Your own vehicle' (beams); "
                    "pipeline/beams.py (recover_rings, select_rings)",
            "own_sensor": "a real 16-line sensor's scan goes in as stored: no thinning (golden --emulate-beams 0)",
        },
    }


def image_section(preset: Preset) -> dict:
    """The camera image → the depth net's ``rgb`` input."""
    crop_h, crop_w = preset.crop_hw
    height, width = preset.depth.input_hw
    scale = preset.depth.input_scale
    resize = {"scale": scale, "output_hw": [height, width],
              "interpolation": "area: OpenCV cv::resize INTER_AREA, on the uint8 crop (before the float conversion)"}
    if scale == 0.5:  # OpenCV's exact fast path for ×½; other factors round otherwise (use cv::resize itself)
        resize["uint8_equivalent"] = "(sum of each 2x2 block + 2) // 4"
    return {
        "channels": "RGB (an image decoded by OpenCV is BGR: swap it)",
        "dtype": "uint8",
        "crop": {"height": crop_h, "width": crop_w, "top": "rows - height", "left": "(columns - width) // 2",
                 "smaller_image": "refused: scale it up first (README, 'Your own vehicle')"},
        "resize": resize,
        "network_input": {"name": "rgb", "shape": [1, 3, height, width], "dtype": "float32",
                          "layout": "NCHW, planes R, G, B",
                          "values": "0-255 as they are: the mean/std normalisation is inside depth.onnx "
                                    "(manifest normalisation.rgb_mean, rgb_std)"},
    }


def view_calibration_section(preset: Preset) -> dict:
    """How P2 follows the crop and the resize (pipeline/preprocess.py); R0_rect and Tr_velo_to_cam do not change."""
    scale = preset.depth.input_scale
    return {
        "crop": "P2 <- [[1, 0, -left], [0, 1, -top], [0, 0, 1]] @ P2",
        "resize": "P2 <- [[s, 0, o], [0, s, o], [0, 0, 1]] @ P2, o = (s - 1) / 2 (pixel centres at integers)",
        "scale": scale,
        "offset": (scale - 1.0) / 2.0,
    }


def sparse_depth_section(preset: Preset) -> dict:
    """The scan projected into the depth net's view (pipeline/calib.py, sparse_depth_map)."""
    height, width = preset.depth.input_hw
    # depth_inputs calls sparse_depth_map without a min_depth: its default is the value in use.
    min_depth = inspect.signature(sparse_depth_map).parameters["min_depth"].default
    return {
        "network_input": {"name": "sparse_depth", "shape": [1, 1, height, width], "dtype": "float32",
                          "units": "metres", "empty": 0.0},
        "points": "every point of the scan (x, y, z; the reflectance is not used)",
        "projection": "[u*d, v*d, d] = P2_view @ [R0_rect @ Tr_velo_to_cam @ [x, y, z, 1], 1]",
        "depth": "d: projective depth of camera 2 (rectified z plus P2[2][3])",
        "pixel": "column round(u), row round(v), rounding half to even (numpy.rint)",
        "min_depth": min_depth,
        "keep": "d > min_depth and 0 <= column < width and 0 <= row < height",
        "several_in_a_pixel": "the smallest d",
        "arithmetic": "float64, d stored as float32",
    }


def pseudo_points_section(preset: Preset) -> dict:
    """The dense depth map back-projected (pipeline/pseudo.py, pipeline/bev.py pseudo_bins)."""
    min_depth, max_depth, stride, max_height = preset.pseudo_limits
    return {
        "from": "depth.onnx's output (1, 1, H, W), metres, in the view of sparse_depth (P2_view)",
        "min_depth": min_depth,
        "max_depth": max_depth,
        "stride": stride,
        "max_height": max_height,
        # float32: a depth of exactly float32(0.9), 0.89999998, is kept (a float64 comparison would drop it).
        "keep": "min_depth <= d <= max_depth and z <= max_height (z of `point`, LiDAR frame), compared in float32; "
                "rows and columns 0, stride, 2*stride …",
        "back_projection": "X_rect = d * inv(K) @ [u, v, 1] - inv(K) @ P2_view[:, 3], K = P2_view[:, :3], u the column, "
                           "v the row; [x, y, z, 1] = inv(4x4 [R0_rect @ Tr_velo_to_cam; 0 0 0 1]) @ [X_rect, 1]",
        # pipeline/pseudo.py pixel_rays and pseudo_xyz: both transforms folded into one ray per pixel.
        "rays": "the back_projection folded, in float64: A, b the 3x3 and translation of inv(4x4 [R0_rect @ "
                "Tr_velo_to_cam; 0 0 0 1]), [Du, Dv, D0] = the columns of A @ inv(K); per pixel, per axis "
                "ray = Dv * v + (Du * u + D0), rounded once to ray_dtype; origin = b - A @ inv(K) @ P2_view[:, 3], "
                "rounded once to ray_dtype",
        "ray_dtype": "float32",
        "point": "per axis d * ray + origin in point_dtype: the product rounded, then the sum (two roundings, "
                 "not a fused multiply-add)",
        "point_dtype": "float32",
        "float64_rule": "back_projection evaluated in float64 lands within 6e-6 m of these points on the five bundled "
                        "KITTI frames (inside golden.json's 1e-4 m); rays and point above give them bit for bit",
        "reflectance": 0.0,
        "depth_jumps": {
            "max_jump": preset.decode.height_max_jump,
            "jump": "max over the 4 neighbours inside the map of |d_n - d| > max_jump * d (float32), on the full map",
            "used_for": "box heights only: a point on a jump is left out of the height occupancy; the BEV keeps it",
        },
    }


def bev_section(preset: Preset) -> dict:
    """The voxelized BEV tensor (pipeline/presets.py BevGrid, pipeline/bev.py)."""
    grid = preset.bev
    nz = grid.nz
    pseudo_channels = [nz + 1, 2 * nz + 1] if grid.split_pseudo else None
    if grid.split_pseudo:
        pseudo = "occupancy[nz + 1 + iz, iy, ix] = 1 (channels of their own)"
        reflectance = "mean reflectance of the real points in the cell; 0 where the cell has none"
    else:
        pseudo = "occupancy[iz, iy, ix] = 1, as a real point"
        reflectance = ("sum of the real points' reflectance / number of real and pseudo points in the cell, "
                       "written where the cell has a real point; 0 elsewhere")
    return {
        "x_min": grid.x_min, "x_max": grid.x_max, "y_min": grid.y_min, "y_max": grid.y_max,
        "z_min": grid.z_min, "z_max": grid.z_max, "cell": grid.cell, "z_cell": grid.z_cell,
        "nx": grid.nx, "ny": grid.ny, "nz": nz, "channels": grid.channels, "shape": list(grid.shape),
        "split_pseudo": grid.split_pseudo,
        "layout": "float32 (1, channels, ny, nx), C order; row iy: y bin from y_min; column ix: x bin from x_min",
        "bin": "real points (and points given as coordinates): i = floor((v - v_min) / cell) per axis, v converted "
               "to float64 first (z: z_cell); a point is kept when 0 <= i < n on all three axes (a point on an "
               "upper edge lies outside)",
        "pseudo_bin": pseudo_bin_rule(preset),
        "channel_ranges": {"occupancy": [0, nz], "reflectance": [nz, nz + 1], "pseudo_occupancy": pseudo_channels},
        "occupied": 1.0,
        "empty": 0.0,
        "real_points": "occupancy[iz, iy, ix] = 1",
        "pseudo_points": pseudo,
        "reflectance": reflectance,
        "reflectance_points": "only points kept in the grid (on all three axes) count",
    }


def pseudo_bin_rule(preset: Preset) -> dict:
    """How the BEV bins the pseudo points: straight from the depth map, never through their coordinates
    (pipeline/bev.py pseudo_bins, pipeline/pseudo.py bin_rays)."""
    grid, (_, _, _, max_height) = preset.bev, preset.pseudo_limits
    scale = [1 / grid.cell, 1 / grid.cell, 1 / grid.z_cell]
    return {
        "scale": scale,
        "rays": "pseudo_points.rays with every axis of A @ inv(K) and of origin multiplied by scale (x, y, z) before "
                "the one rounding to float32; origin = float32(scale * (b - A @ inv(K) @ P2_view[:, 3]) - "
                "scale * (x_min, y_min, z_min)), all in float64 before the rounding",
        "bin": "per axis i = floor(c), c = d * ray + origin in float32 (the product rounded, then the sum: two "
               "roundings, not a fused multiply-add)",
        "keep": "pseudo_points' depth limits (float32), c_z <= max_height_bin before the floor (float32), and "
                "0 <= i < n on all three axes",
        "max_height_bin": float(np.float32((max_height - grid.z_min) / grid.z_cell)),
        "max_height_bin_rule": "float32((max_height - z_min) / z_cell), computed in float64",
        "why": "the real points' rule on the float32 pseudo points (or on float64 ones) rounds differently: on KITTI "
               "000004 it put 1 of 14,428 pseudo voxels in another cell, which moved a result line's 4th decimal "
               "at score threshold 0.05",
    }


def pixor_section(preset: Preset) -> dict:
    """PIXOR's interface as the decode reads it."""
    grid, stride = preset.bev, preset.pixor.output_stride
    out = [grid.ny // stride, grid.nx // stride]
    return {
        "input": "the BEV (1, channels, ny, nx); an input named bev[lo:hi] takes channels lo … hi-1 "
                 "(manifest networks.pixor.graph_inputs): a pointer into the one buffer, no copy",
        "output_stride": stride,
        "score": {"name": "score", "shape": [1, 1, *out], "values": "probability, after the sigmoid"},
        "regression": {"name": "regression", "shape": [1, 6, *out], "channels": list(REGRESSION_CHANNELS),
                       "values": "normalised: (t - reg_mean) / reg_std"},
    }


def decode_section(preset: Preset) -> dict:
    """Maps → BEV boxes (pipeline/targets.py decode_maps, pipeline/iou.py rotated_nms)."""
    grid, stride, decode = preset.bev, preset.pixor.output_stride, preset.decode
    return {
        "output_grid": {"ny": grid.ny // stride, "nx": grid.nx // stride, "step": grid.cell * stride,
                        "centre_x": "x_min + (j + 0.5) * step (column j)",
                        "centre_y": "y_min + (i + 0.5) * step (row i)"},
        "score_threshold": decode.score_threshold,
        "candidate": "score >= score_threshold, compared in float32",
        "max_candidates": decode.max_candidates,
        "over_max_candidates": "keep the max_candidates highest scores",
        # Sigmoid scores saturate at 1.0f on confident cars, so equal scores happen and the order decides NMS.
        "order": "score descending; equal scores by cell index (row-major) ascending (past max_candidates, "
                 "of the equal scores at the cut those of the lowest cell indices are kept)",
        "regression_channels": list(REGRESSION_CHANNELS),
        "reg_mean": list(decode.reg_mean),
        "reg_std": list(decode.reg_std),
        "denormalise": "t = r * reg_std + reg_mean, float64",
        "log_size_clip": list(LOG_SIZE_CLIP),
        "box": {"x": "centre_x + dx", "y": "centre_y + dy", "l": "exp(clip(log_l))", "w": "exp(clip(log_w))",
                "yaw": "atan2(sin_yaw, cos_yaw)", "fields": ["x", "y", "l", "w", "yaw"],
                "size_directions": dict(SIZE_DIRECTIONS),
                "sizes": "each size runs along the direction at yaw + size_directions[size] (radians, from +x "
                         "towards +y): l along the heading (cos yaw, sin yaw), w across it (-sin yaw, cos yaw); "
                         "corners (x, y) + a * l/2 * (cos yaw, sin yaw) + b * w/2 * (-sin yaw, cos yaw), a, b = +-1"},
        "nms": {"iou_threshold": decode.nms_iou,
                "rule": "greedy in the candidate order: drop a box whose IoU with a kept box is > iou_threshold",
                "iou": "exact: area of the intersection of the two rotated rectangles / area of their union",
                "max_detections": decode.max_detections},
    }


def heights_section(preset: Preset) -> dict:
    """z and h of each kept box from the height occupancy (pipeline/postprocess.py estimate_heights)."""
    grid, decode, stride = preset.bev, preset.decode, preset.pixor.output_stride
    return {
        "car_height": decode.car_height,
        "ground_z": decode.ground_z,
        "min_occupied": decode.min_occupied_for_height,
        "prior_volume": decode.height_prior_volume,
        "voxel_volume": grid.cell * grid.cell * grid.z_cell,
        "quantiles": [_LOW_Q, _HIGH_Q],
        "height_range": list(_HEIGHT_RANGE),
        "bottom_in_slice": decode.bottom_in_slice,
        "bottom_in_slice_with_pseudo": decode.bottom_in_slice_with_pseudo,
        "occupancy": "the nz height slices of the real points and of the pseudo points off depth jumps; "
                     "a LiDAR-only model: its BEV occupancy channels",
        "cells": f"each output cell (i, j) whose centre lies inside the box (|along| <= l/2 and |across| <= w/2), "
                 f"in the output grid; under it the BEV rows {stride}i … {stride}i+{stride - 1}, columns "
                 f"{stride}j … {stride}j+{stride - 1}",
        "histogram": "per box: occupied voxels per height slice k over those cells; T their total, C the cumulative sum",
        "low": "first k with C[k] >= quantiles[0] * T",
        "high": "first k with C[k] >= quantiles[1] * T",
        "bottom": "z_min + (low + b) * z_cell; b = bottom_in_slice_with_pseudo for a model with a depth net, "
                  "else bottom_in_slice",
        "top": "z_min + (high + 1) * z_cell",
        "measured": "T >= min_occupied: m = clip(top - bottom, height_range); V = T * voxel_volume; "
                    "h = (V * m + prior_volume * car_height) / (V + prior_volume); z = bottom + h / 2",
        "otherwise": "h = car_height; z = ground_z + car_height / 2",
        "box": "(x, y, z, l, w, h, yaw), z the box centre, LiDAR frame, float64; l along yaw, w across it "
               "(decode.box.sizes), h along z",
    }


def mirror_section() -> dict:
    """Mirror test-time augmentation, off by default (docs/models.md)."""
    return {
        "default": False,
        "mirrored_bev": "rows reversed (y -> -y)",
        "negated": list(MIRROR_NEGATED),
        "merge": "the mirrored run's maps rows reversed back, its de-normalised negated targets negated, "
                 "re-normalised; score and regression: the mean of the two runs",
    }


def kitti_results_section() -> dict:
    """The KITTI result lines of the boxes (pipeline/boxes.py in_camera_view, boxes_to_objects, image_boxes;
    pipeline/kitti.py format_label; docs/evaluation.md, 'What each line holds')."""
    return {
        "calibration": "the frame's own P2 (the whole image's, not P2_view), R0_rect, Tr_velo_to_cam; rows and "
                       "columns of the image as read",
        "written": "the boxes whose visibility_point projects to depth > 0 and 0 <= u < columns, 0 <= v < rows: "
                   "[u * depth, v * depth, depth] = P2 @ [R0_rect @ Tr_velo_to_cam @ [x, y, z, 1], 1], float64; in "
                   "the boxes' order (the others are in JSON answers only)",
        "visibility_point": "centre",
        "visibility_point_note": "centre: the box's 3D centre (x, y, z) as decoded, not its bottom centre",
        "fields": ["type", "truncated", "occluded", "alpha", "left", "top", "right", "bottom", "h", "w", "l",
                   "x", "y", "z", "rotation_y", "score"],
        "values": {"type": "Car", "truncated": 0.0, "occluded": 0},
        "decimals": {"truncated": 2, "occluded": 0, "alpha": RESULT_DECIMALS, "bbox": 2, "dimensions": RESULT_DECIMALS,
                     "location": RESULT_DECIMALS, "rotation_y": RESULT_DECIMALS, "score": 4},
        "number_format": "fixed point with that many decimals, rounded to nearest as C's printf(\"%.4f\") and "
                         "Python's format(v, '.4f') round; one space between fields, each line ending in \\n; a "
                         "frame without a written box: an empty file",
        "location": "the bottom centre (x, y, z - h/2) through R0_rect @ Tr_velo_to_cam: rectified camera frame",
        "dimensions": "h, w, l (l along yaw, w across: decode.box.sizes)",
        "rotation_y": "wrap(-yaw - pi/2), wrap(a) = ((a + pi) mod 2 pi) - pi in [-pi, pi), mod taking the sign of "
                      "2 pi (Python's %, not C's fmod)",
        "alpha": "wrap(rotation_y - atan2(location x, location z))",
        "bbox": "the 12 edges of the 3D box (its 4 BEV corners at z - h/2 and at z + h/2) in the rectified frame; "
                "an edge with no end in front of the near plane (rectified z > near_plane_m) is dropped, an end at "
                "or behind it moved along its edge onto it; the ends left projected with P2 (u, v: the first two "
                "components over the third); left, top = min u, min v and right, bottom = max u, max v, clipped "
                "to 0 … columns - 1 (u) and 0 … rows - 1 (v); no edge left: 0, 0, columns - 1, rows - 1",
        "near_plane_m": NEAR_PLANE_M,
        "docs": "docs/evaluation.md, 'What each line holds'",
    }


# --------------------------------------------------------------------------- the ONNX graphs
def graph_report(path: str | Path) -> dict:
    """An ONNX file as a port meets it: opset, inputs and outputs (name, dtype, shape), operator counts, and what
    TensorRT's ONNX parser would refuse (:func:`tensorrt_notes`)."""
    import onnx  # the runtime's pyproject has it; imported here so the spec above needs only the pipeline

    model = onnx.load(str(path))
    stored = {init.name for init in model.graph.initializer}

    def describe(value: onnx.ValueInfoProto) -> dict:
        tensor = value.type.tensor_type
        shape = [d.dim_value if d.HasField("dim_value") else (d.dim_param or None) for d in tensor.shape.dim]
        return {"name": value.name, "dtype": onnx.helper.tensor_dtype_to_np_dtype(tensor.elem_type).name,
                "shape": shape}

    ops = Counter(n.op_type if n.domain in ("", "ai.onnx") else f"{n.domain}.{n.op_type}" for n in model.graph.node)
    return {
        "file": Path(path).name,
        "ir_version": model.ir_version,
        "opset": _default_opset(model),
        "inputs": [describe(v) for v in model.graph.input if v.name not in stored],
        "outputs": [describe(v) for v in model.graph.output],
        "static_shapes": all(isinstance(d, int) and d > 0 for v in [*model.graph.input, *model.graph.output]
                             if v.name not in stored for d in describe(v)["shape"]),
        "external_data": any(i.data_location == onnx.TensorProto.EXTERNAL for i in model.graph.initializer),
        "ops": dict(sorted(ops.items())),
        "tensorrt": tensorrt_notes(model),
    }


def _default_opset(model) -> int:
    return next((o.version for o in model.opset_import if o.domain in ("", "ai.onnx")), 0)


def tensorrt_notes(model) -> list[str]:
    """What TensorRT's ONNX parser would refuse or needs a version for, reasoned from the graph (no TensorRT
    here): the opset, operators it does not import, custom domains, and quantization it does not take (its
    explicit quantization is int8 with zero points 0)."""
    from onnx import TensorProto, numpy_helper

    notes = []
    opset = _default_opset(model)
    if opset > TENSORRT_10_MAX_OPSET:
        notes.append(f"opset {opset}: above {TENSORRT_10_MAX_OPSET}, what TensorRT 10.0 parses")
    elif opset > TENSORRT_8_MAX_OPSET:
        notes.append(f"opset {opset}: TensorRT 10 parses it (opsets 9-{TENSORRT_10_MAX_OPSET}); TensorRT 8.5/8.6 "
                     f"(JetPack 5, JetPack 6.0) document opsets up to {TENSORRT_8_MAX_OPSET}")
    nodes = model.graph.node
    unsupported = sorted({n.op_type for n in nodes if n.op_type in TENSORRT_UNSUPPORTED_OPS})
    if unsupported:
        notes.append(f"operators TensorRT's ONNX parser does not import: {', '.join(unsupported)}")
    custom = sorted({n.domain for n in nodes if n.domain not in ("", "ai.onnx")})
    if custom:
        notes.append(f"operators of custom domains ({', '.join(custom)}): not parsed by TensorRT")
    initializers = {i.name: i for i in model.graph.initializer}
    zero_points = [initializers[n.input[2]] for n in nodes
                   if n.op_type in ("QuantizeLinear", "DequantizeLinear") and len(n.input) > 2 and n.input[2] in initializers]
    not_int8 = sum(z.data_type != TensorProto.INT8 for z in zero_points)
    nonzero = sum(bool(numpy_helper.to_array(z).any()) for z in zero_points)
    if not_int8 or nonzero:
        notes.append(f"quantization: {not_int8} of {len(zero_points)} Quantize/DequantizeLinear nodes are not int8 "
                     f"(uint8 activations, int32 biases) and {nonzero} have non-zero zero points; TensorRT takes int8 "
                     "with zero point 0 only: build its INT8 engine from the FP32 graph with TensorRT's calibration")
    return notes
