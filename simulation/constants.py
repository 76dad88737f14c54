"""The simulator's shared numbers: sensor, calibration, scene layout, labelling rules. How things look and
scatter (materials, colours, shading, the return model's noise) stays beside the code that uses it
(docs/simulation.md).

Units are metres, degrees where the name says so, radians otherwise. The LiDAR
frame is KITTI's velodyne frame (x forward, y left, z up) with the sensor at
the origin, so the ground under the car is at about ``-LIDAR_HEIGHT``.
"""

from __future__ import annotations

import numpy as np

from pipeline.calib import KITTI_CALIBRATION, KITTI_IMAGE_HW

# --------------------------------------------------------------------------- camera
IMAGE_HW = KITTI_IMAGE_HW

# Base calibration: KITTI drive 2011_09_26 (pipeline.calib.KITTI_CALIBRATION). Frames perturb it slightly.
BASE_P2 = KITTI_CALIBRATION.P2
BASE_R0_RECT = KITTI_CALIBRATION.R0_rect
BASE_TR_VELO_TO_CAM = KITTI_CALIBRATION.Tr_velo_to_cam
# Per-frame calibration jitter (1 sigma): KITTI's drives differ by about this much.
CALIB_FOCAL_SIGMA = 3.0  # pixels
CALIB_PRINCIPAL_SIGMA = 4.0  # pixels
CALIB_ROTATION_SIGMA_DEG = 0.15
CALIB_TRANSLATION_SIGMA = 0.01

# --------------------------------------------------------------------------- LiDAR (HDL-64E)
LIDAR_HEIGHT = 1.73  # KITTI: velodyne above the ground
# HDL-64E: upper block of 32 lasers +2° … -8.33° (≈1/3° apart), lower block -8.83° … -24.9° (≈1/2°).
HDL64_ELEVATIONS_DEG = np.concatenate([np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.9, 32)])
LIDAR_COLUMNS = 2000  # firings per revolution: 0.18° steps, as measured on KITTI scans
LIDAR_MAX_RANGE = 120.0
LIDAR_MIN_RANGE = 1.5  # KITTI scans hold nothing nearer
LIDAR_REFERENCE_ALBEDO = 0.4  # a target this bright (at normal incidence) returns out to LIDAR_MAX_RANGE
LIDAR_RANGE_NOISE = 0.02  # 1 sigma, metres
LIDAR_ELEVATION_JITTER_DEG = 0.03  # per-laser calibration residual, 1 sigma
LIDAR_AZIMUTH_JITTER_DEG = 0.02  # per-firing timing jitter, 1 sigma
LIDAR_DROPOUT = 0.015  # random missing returns
LIDAR_GRAZING_COS = 0.08  # below this incidence cosine most returns are lost

# --------------------------------------------------------------------------- rendering
MAX_RENDER_DISTANCE = 400.0  # beyond this a ray sees the sky (the horizon)
MAX_DEPTH_GT = 250.0  # depth ground truth stops here (uint16 PNG holds < 256 m)
NEAR_PLANE = 0.1
IMAGE_NOISE_SIGMA = 2.5  # grey levels
IMAGE_BLUR_SIGMA = 0.6  # pixels; stands in for the lens and anti-aliasing

# --------------------------------------------------------------------------- scene layout
LANE_WIDTH = 3.5
PARKING_WIDTH = 2.3
CURB_HEIGHT = 0.15
ROAD_BEHIND = -60.0  # the road and its furniture span this range of x
ROAD_AHEAD = 150.0
MAX_SLOPE = 0.04  # longitudinal grade
MAX_CROSS_SLOPE = 0.015
MAX_VERTICAL_CURVATURE = 2.5e-4  # z = … + c·x², crests and sags
MAX_HORIZONTAL_CURVATURE = 1.5e-3  # lateral offset = … + k·x²

# KITTI object sizes (mean, sigma) for h, w, l
CAR_SIZE = ((1.53, 0.14), (1.63, 0.10), (3.88, 0.43))
VAN_SIZE = ((2.21, 0.12), (1.90, 0.09), (5.08, 0.44))
PEDESTRIAN_SIZE = ((1.76, 0.11), (0.66, 0.14), (0.84, 0.23))
CYCLIST_SIZE = ((1.74, 0.09), (0.60, 0.12), (1.76, 0.18))
CAR_COLOURS = np.array([  # common car paints, linear RGB 0..1
    [0.85, 0.85, 0.86], [0.62, 0.63, 0.66], [0.35, 0.36, 0.38], [0.05, 0.05, 0.06],
    [0.55, 0.05, 0.05], [0.08, 0.15, 0.45], [0.10, 0.25, 0.15], [0.65, 0.58, 0.45],
    [0.80, 0.75, 0.20], [0.25, 0.30, 0.55],
])

CAR_MAX_DISTANCE = 85.0  # cars are placed out to here (beyond LABEL_MAX_DISTANCE → DontCare)

# --------------------------------------------------------------------------- labels (KITTI semantics)
LABEL_MAX_DISTANCE = 75.0  # KITTI annotators stopped at about this range: farther → DontCare
OCCLUSION_LEVELS = (0.2, 0.5, 0.9)  # occluded fraction below these → level 0, 1, 2; above the last → DontCare
MIN_VISIBLE_PIXELS = 20  # fewer visible pixels → not labelled at all
MIN_BOX_HEIGHT = 8.0  # pixels; smaller boxes are DontCare
TRUNCATION_SAMPLES = 6  # per box axis, for the fraction of the object outside the image
