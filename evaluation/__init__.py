"""Accuracy evaluation: the official KITTI object protocol (2D box, BEV and 3D AP) and
KITTI depth-completion error metrics.

Modules:
    labels        KITTI label lines of one frame as typed arrays.
    overlaps      2D box, BEV and 3D overlap matrices in the devkit's conventions.
    kitti_eval    the official KITTI object evaluation (41 recall points, R11 / R40 AP).
    frames        reading a ground-truth and a result directory into frames.
    report        the paper's table, the JSON document and precision-recall plots.
    depth_metrics RMSE, MAE, iRMSE, iMAE of a dense depth map against sparse ground truth.
    harness       accuracy runs: the detector over a KITTI-layout dataset, and depth completion.
"""

# The score above which accuracy runs keep detections: low, as AP integrates over the whole precision–recall
# curve (pipeline.detect keeps 0.5 and up, for use). Here, not in harness, so --help need not import the runtime.
DEFAULT_SCORE_THRESHOLD = 0.05
