"""Camera–LiDAR geometry: KITTI calibration, projections and the depth-net crop.

Frames: velodyne (x forward, y left, z up) → rectified camera (x right, y down,
z forward) → image pixels. ``P2 · R0_rect · Tr_velo_to_cam · [x y z 1]ᵀ``.

Depth here is always the projective depth of camera 2, the third row of
``P2 · [X_rect, 1]ᵀ`` (the rectified z plus P2's small z offset); it is what
KITTI depth PNGs store and what back-projection expects.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from pipeline.errors import InputError


def affine_rows(matrix: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``matrix[:, :3] @ rows + matrix[:, 3:]`` for (3, N) coordinate rows: an (M, N) array.

    Written out as element-wise arithmetic on purpose. NumPy hands a matrix product of these shapes to
    OpenBLAS, which for more than about 30,000 points splits it over its worker thread; that thread then
    spins for about 0.1 s waiting for more work, on the cores ONNX Runtime needs for the network that
    runs next (a 64-line scan given to the camera pipeline: its depth net took 85 ms instead of 45;
    docs/measurements.md, session 35). Element-wise NumPy stays on the calling thread. The rows are
    made contiguous and summed in place: as fast as the single-threaded product (0.073 against 0.066 ms
    for 27,600 points), where strided rows took 0.121 ms.
    """
    rows = np.ascontiguousarray(rows)  # in its own dtype: the products take the wider of the two
    out = np.multiply(matrix[:, 0:1], rows[0])
    term = np.empty_like(out)
    for axis in (1, 2):
        out += np.multiply(matrix[:, axis : axis + 1], rows[axis], out=term)
    out += matrix[:, 3:4]
    return out


@dataclass(frozen=True)
class Calibration:
    """KITTI object calibration: P2 (3×4), R0_rect (3×3), Tr_velo_to_cam (3×4), float64."""

    P2: np.ndarray
    R0_rect: np.ndarray
    Tr_velo_to_cam: np.ndarray

    # ---- derived matrices (cheap; computed on use so the dataclass stays plain)
    @property
    def velo_to_rect_matrix(self) -> np.ndarray:
        """4×4 transform velodyne → rectified camera."""
        m = np.eye(4)
        m[:3, :4] = self.R0_rect @ self.Tr_velo_to_cam
        return m

    @property
    def velo_to_pixels_f32(self) -> np.ndarray:
        """3×4 float32 projection velodyne → homogeneous pixels (u·d, v·d, d): for screening many points at
        once, where float32's error at LiDAR ranges is far below a pixel."""
        return (self.P2 @ self.velo_to_rect_matrix).astype(np.float32)

    @property
    def rect_to_velo_matrix(self) -> np.ndarray:
        """4×4 transform rectified camera → velodyne (exact inverse)."""
        return np.linalg.inv(self.velo_to_rect_matrix)

    # ---- velodyne ↔ rectified camera
    # The forward projections work on (3, N) coordinate rows and return their transposes: an (N, 3) block
    # whose columns are contiguous. Broadcasting a translation over rows of length 3 runs NumPy's inner
    # loop three elements at a time: projecting 4,200 points took 141 µs that way, 59 µs this way.
    def velo_to_rect(self, xyz: np.ndarray) -> np.ndarray:
        """(N, 3) velodyne points → (N, 3) rectified camera coordinates (float64)."""
        return affine_rows(self.velo_to_rect_matrix[:3], np.asarray(xyz)[:, :3].T).T

    def rect_to_velo(self, xyz: np.ndarray) -> np.ndarray:
        """(N, 3) rectified camera coordinates → (N, 3) velodyne points (float64)."""
        return affine_rows(self.rect_to_velo_matrix[:3], np.asarray(xyz)[:, :3].T).T

    # ---- rectified camera ↔ image
    def rect_to_image(self, xyz_rect: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project rectified points: returns pixel coordinates (N, 2) and depth (N,).

        Points with depth ≤ 0 get non-finite pixel coordinates; filter on depth.
        """
        homog = affine_rows(self.P2, np.asarray(xyz_rect).T)
        depth = homog[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = homog[:2] / depth
        return uv.T, depth

    def image_to_rect(self, u: np.ndarray, v: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Back-project pixels (u, v) with depth into (N, 3) rectified coordinates (exact inverse)."""
        depth = np.asarray(depth, np.float64)
        k_inv = np.linalg.inv(self.P2[:, :3])
        homog = np.stack([np.asarray(u, np.float64) * depth, np.asarray(v, np.float64) * depth, depth])
        return affine_rows(np.column_stack([k_inv, -k_inv @ self.P2[:, 3]]), homog).T

    def velo_to_image(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project velodyne points to pixels: (N, 2) pixel coordinates, (N,) depth."""
        return self.rect_to_image(self.velo_to_rect(xyz))

    def image_to_velo(self, u: np.ndarray, v: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Back-project pixels with depth into (N, 3) velodyne points."""
        return self.rect_to_velo(self.image_to_rect(u, v, depth))

    @classmethod
    def from_matrices(cls, P2: object, R0_rect: object, Tr_velo_to_cam: object,
                      source: str = "calib") -> Calibration:
        """A checked calibration from matrices in code, e.g. a ROS node's: ``P2`` the rectified camera's
        projection (``CameraInfo.p``), ``R0_rect`` its rectifying rotation (``CameraInfo.r``; the identity for
        an unrectified camera) and ``Tr_velo_to_cam`` the LiDAR → camera transform, into the camera's optical
        frame (x right, y down, z forward: TF's ``*_optical_frame``, not the camera body's x-forward frame).

        Each may be a nested or flat sequence in row order (``CameraInfo``'s 12 and 9 numbers); ``R0_rect`` and
        ``Tr_velo_to_cam`` also as 4×4 homogeneous matrices. Copied to float64; else an InputError naming
        ``source`` and the matrix, with :func:`check_calibration`'s checks (finite, invertible)."""
        given = {"P2": P2, "R0_rect": R0_rect, "Tr_velo_to_cam": Tr_velo_to_cam}
        matrices = {key: _matrix_of(value, CALIBRATION_SHAPES[key], f"{source}: {key}", homogeneous=key != "P2")
                    for key, value in given.items()}
        return check_calibration(cls(**matrices), source)

    def shifted(self, left: float, top: float) -> Calibration:
        """Calibration of an image cropped at (left, top): P2 ← T·P2 with T a pixel translation.

        Exact for any P2: both the principal point and P2's last column move,
        so projective depth is unchanged and pixels shift by exactly (left, top).
        """
        shift = np.array([[1.0, 0.0, -left], [0.0, 1.0, -top], [0.0, 0.0, 1.0]])
        return Calibration(P2=shift @ self.P2, R0_rect=self.R0_rect, Tr_velo_to_cam=self.Tr_velo_to_cam)


# --------------------------------------------------------------------------- checks
CALIBRATION_SHAPES = {"P2": (3, 4), "R0_rect": (3, 3), "Tr_velo_to_cam": (3, 4)}
# Bounds far outside any real rig's calibration, within which the projections cannot overflow (with points
# bounded as the Detector bounds them): a value's magnitude (P2's focal lengths and offsets are 1e2–1e6 even in
# millimetres, the rotations' at most 1), and each 3×3 block's smallest singular value (KITTI's P2 0.76, a
# rotation's 1). A P2 scaled by 1e300, or a rotation by 1e-300, passed the rank test and overflowed later.
MAX_CALIBRATION_VALUE = 1e9
MIN_SINGULAR_VALUE = 1e-6


def _describe(value: object) -> str:
    """What a value is, for an error message: an array's dtype and shape, else its type."""
    if isinstance(value, np.ndarray):
        return f"a {value.dtype} array of shape {value.shape}"
    return f"a {type(value).__name__}"


def _matrix_of(value: object, shape: tuple[int, int], where: str, homogeneous: bool) -> np.ndarray:
    """``value`` as a float64 ``shape`` matrix: given so, flat in row order, or (``homogeneous``: a rigid
    transform's block) as a 4×4 homogeneous matrix; else an InputError naming ``where``."""
    try:
        given = np.asarray(value)
    except (TypeError, ValueError):  # ragged nested sequences
        given = None
    # Real numbers only: a cast to float64 would take strings of digits and dates, drop a complex part (with a
    # warning) and raise OverflowError on a Python int beyond float64 (which NumPy holds as an object).
    if given is None or given.dtype.kind not in "fiu":
        raise InputError(f"{where}: expected a {shape[0]}×{shape[1]} matrix of numbers, got {_describe(value)}")
    with np.errstate(over="ignore"):  # a long double beyond float64's range: infinite, refused by check_calibration
        matrix = np.array(given, dtype=np.float64)  # a copy: a caller's (or a message's) buffer may change later
    rows, cols = shape
    if matrix.shape in ((rows * cols,), shape):
        return matrix.reshape(shape)
    if homogeneous and matrix.shape in ((16,), (4, 4)):
        return homogeneous_block(matrix.reshape(4, 4), shape, where)
    also = " or a 4×4 homogeneous one" if homogeneous else ""
    raise InputError(f"{where}: expected a {rows}×{cols} matrix (or {rows * cols} numbers in row order){also}, got "
                     f"{_describe(matrix)}")


def homogeneous_block(matrix: np.ndarray, shape: tuple[int, int], where: str) -> np.ndarray:
    """The ``shape`` block (3×4 or 3×3) of a 4×4 homogeneous matrix, whose last row must be 0 0 0 1 (and, for a
    3×3 rotation, its last column 0 0 0): anything else is a projective matrix the block cannot hold, refused
    with an InputError naming ``where``, not cut."""
    rows, cols = shape
    padding_ok = np.allclose(matrix[3], (0.0, 0.0, 0.0, 1.0), rtol=0.0, atol=1e-9)
    if cols == 3:
        padding_ok = padding_ok and np.allclose(matrix[:3, 3], 0.0, rtol=0.0, atol=1e-9)
    if not padding_ok:
        corner = "last row 0 0 0 1" + ("" if cols == 4 else " and last column 0 0 0")
        raise InputError(f"{where}: a 4×4 matrix, but not a homogeneous one ({corner}); give the {rows}×{cols} "
                         f"block, {rows * cols} numbers")
    return matrix[:rows, :cols].copy()


# The values of the float64 calibrations that passed check_calibration, in the order they first passed (a hit
# does not move one: the oldest is dropped first, however often it is used since). The detector checks
# every frame's calibration, which its reader (pipeline.kitti, the service's parser) has checked already, and a
# vehicle's every frame has the same one: the full checks took 0.20 ms of an edge frame (p50, AMD Zen 3,
# session 42; 0.06 ms alone in a loop, the rest the caches the networks left cold), a lookup by value a few µs.
# Keyed by the bytes themselves, so a matrix changed in place is checked anew. Bounded for a service that is
# sent a new calibration with every frame; 1,024 keys of 264 bytes hold any data set's drives (KITTI: one
# calibration per day of driving) and the frames a benchmark reads before it times them (a synthetic
# scene has a calibration of its own).
_PASSED: OrderedDict[bytes, None] = OrderedDict()
_PASSED_MAX = 1024
_PASSED_LOCK = threading.Lock()


def _passed_key(calib: object) -> bytes | None:
    """The key of ``calib`` in _PASSED: its three matrices' bytes when each is a float64 array of its shape (the
    only calibrations check_calibration returns as they are), else None."""
    if not isinstance(calib, Calibration):
        return None
    matrices = (calib.P2, calib.R0_rect, calib.Tr_velo_to_cam)
    for shape, matrix in zip(CALIBRATION_SHAPES.values(), matrices, strict=True):
        if not isinstance(matrix, np.ndarray) or matrix.dtype != np.float64 or matrix.shape != shape:
            return None
    return b"".join(matrix.tobytes() for matrix in matrices)


def check_calibration(calib: object, source: str = "calib") -> Calibration:
    """``calib`` if it is a :class:`Calibration` of real, finite matrices of its shapes whose 3×3 blocks can be
    inverted, as back-projection needs, and whose values lie within a real rig's bounds; else an InputError
    naming ``source`` and the matrix (a singular, NaN or absurdly scaled matrix would otherwise fail deep
    inside the pipeline, overflow, or give boxes that vanish later). A copy in float64 when a matrix is of
    another real dtype. The detector checks every frame's: float64 values that passed before (the last
    :data:`_PASSED_MAX` distinct ones to pass, counted from their first pass) pass at once."""
    key = _passed_key(calib)
    if key is not None and key in _PASSED:
        return calib  # type: ignore[return-value]  # _passed_key returns a key for Calibrations only
    checked = _check_calibration_values(calib, source)
    if key is not None:
        with _PASSED_LOCK:  # two threads trimming at once could pop one entry too many, or from an empty dict
            _PASSED[key] = None
            while len(_PASSED) > _PASSED_MAX:
                _PASSED.popitem(last=False)
    return checked


def _check_calibration_values(calib: object, source: str) -> Calibration:
    """:func:`check_calibration`'s checks, every one."""
    if not isinstance(calib, Calibration):
        raise InputError(f"{source}: expected a pipeline.calib.Calibration (pipeline.kitti.read_calib or parse_calib "
                         f"makes one), got {_describe(calib)}")
    matrices = (calib.P2, calib.R0_rect, calib.Tr_velo_to_cam)
    for (key, shape), matrix in zip(CALIBRATION_SHAPES.items(), matrices, strict=True):
        if not isinstance(matrix, np.ndarray) or matrix.shape != shape or matrix.dtype.kind not in "fiu":
            raise InputError(f"{source}: {key} must be a {shape[0]}×{shape[1]} array of real numbers, "
                             f"got {_describe(matrix)}")
    if any(matrix.dtype != np.float64 for matrix in matrices):  # float32, ints, long double: as parse_calib's
        with np.errstate(over="ignore"):  # a long double beyond float64's range: infinite, refused below
            calib = Calibration(*(matrix.astype(np.float64) for matrix in matrices))
        matrices = (calib.P2, calib.R0_rect, calib.Tr_velo_to_cam)
    p2, r0, tr = matrices
    for key, matrix in zip(CALIBRATION_SHAPES, matrices, strict=True):
        if not np.isfinite(matrix).all():
            raise InputError(f"{source}: {key} has a non-finite value (NaN or infinity)")
        largest = float(np.abs(matrix).max())
        if largest > MAX_CALIBRATION_VALUE:
            raise InputError(f"{source}: {key} has a value of magnitude {largest:.3g}, beyond any camera's or rig's "
                             f"calibration (at most {MAX_CALIBRATION_VALUE:g}): a damaged file?")
    # One stacked call (matrix_rank's own tolerance, and the absolute floor), in about a third of the time of three.
    singular = np.linalg.svd(np.stack([p2[:, :3], r0, tr[:, :3]]), compute_uv=False)
    tolerance = singular[:, 0] * 3 * np.finfo(np.float64).eps
    for key, values, tol in zip(CALIBRATION_SHAPES, singular, tolerance, strict=True):
        if values[-1] <= max(tol, MIN_SINGULAR_VALUE):
            raise InputError(f"{source}: {key} is singular (its 3×3 block cannot be inverted): not a camera calibration")
    # A rectified camera's P2 is K [I | t] with positive focal lengths. A negative one (a mirrored camera, or P2
    # negated: the same projective map) passed every check above, and back-projection put the pseudo points
    # behind the camera: no real rig's calibration, so refused rather than answered with boxes.
    for axis, (row, col) in (("fx", (0, 0)), ("fy", (1, 1))):
        if p2[row, col] <= 0:
            raise InputError(f"{source}: P2's focal length {axis} = P2[{row},{col}] = {p2[row, col]:g} is not positive "
                             "(a mirrored or negated projection matrix?): not a KITTI camera calibration")
    return calib


# --------------------------------------------------------------------------- a typical KITTI camera
# KITTI drive 2011_09_26 (training frames 000001/000003/000004 in tests/data/kitti; a test checks these
# against the file): the simulator's base calibration, and the frame the service warms its workers up on.
KITTI_IMAGE_HW = (375, 1242)  # image_2 size (rows, columns)
KITTI_CALIBRATION = Calibration(
    P2=np.array([
        [7.215377e02, 0.0, 6.095593e02, 4.485728e01],
        [0.0, 7.215377e02, 1.728540e02, 2.163791e-01],
        [0.0, 0.0, 1.0, 2.745884e-03],
    ]),
    R0_rect=np.array([
        [9.999239e-01, 9.837760e-03, -7.445048e-03],
        [-9.869795e-03, 9.999421e-01, -4.278459e-03],
        [7.402527e-03, 4.351614e-03, 9.999631e-01],
    ]),
    Tr_velo_to_cam=np.array([
        [7.533745e-03, -9.999714e-01, -6.166020e-04, -4.069766e-03],
        [1.480249e-02, 7.280733e-04, -9.998902e-01, -7.631618e-02],
        [9.998621e-01, 7.523790e-03, 1.480755e-02, -2.717806e-01],
    ]),
)
for _matrix in (KITTI_CALIBRATION.P2, KITTI_CALIBRATION.R0_rect, KITTI_CALIBRATION.Tr_velo_to_cam):
    _matrix.setflags(write=False)  # shared by every user of the constant


# --------------------------------------------------------------------------- depth-net crop
@dataclass(frozen=True)
class CropWindow:
    """A crop of the camera image: rows [top, top+height), columns [left, left+width)."""

    top: int
    left: int
    height: int
    width: int

    def apply(self, image: np.ndarray) -> np.ndarray:
        """Crop an (H, W, ...) array."""
        return image[self.top : self.top + self.height, self.left : self.left + self.width]


# What a camera with smaller images must do: the networks read the KITTI crop's pixels at KITTI's scale.
SMALL_IMAGE_HINT = ("; upscale the image until it covers the crop and P2 with it "
                    "(pipeline.preprocess.scale_calibration; README, 'Your own vehicle')")


def depth_crop(image_hw: tuple[int, int], height: int = 352, width: int = 1216) -> CropWindow:
    """The KITTI depth-completion crop: the bottom ``height`` rows, the centre ``width`` columns."""
    img_h, img_w = int(image_hw[0]), int(image_hw[1])
    if img_h < height or img_w < width:
        raise InputError(
            f"image: {img_w}×{img_h} pixels is smaller than the model's {width}×{height} crop{SMALL_IMAGE_HINT}"
        )
    return CropWindow(top=img_h - height, left=(img_w - width) // 2, height=height, width=width)


def crop_calibration(calib: Calibration, crop: CropWindow) -> Calibration:
    """The calibration of the cropped image (principal point and P2 offsets shifted exactly)."""
    return calib.shifted(crop.left, crop.top)


# --------------------------------------------------------------------------- sparse depth
def sparse_depth_map(
    points: np.ndarray, calib: Calibration, image_hw: tuple[int, int], min_depth: float = 0.1
) -> np.ndarray:
    """Project LiDAR points into a float32 (H, W) depth map in metres, 0 = no return.

    Each point lands on the pixel nearest its projection (pixel centres at
    integer coordinates, as P2 defines them); where several land on one pixel
    the nearest return wins, as a camera would see it.
    """
    h, w = int(image_hw[0]), int(image_hw[1])
    # A float32 pass finds the points that can land in the image (most of a 360° scan cannot);
    # the exact float64 projection then runs on those alone. The 2-pixel and 1 cm margins are far
    # wider than float32's error at LiDAR ranges, so the result equals projecting every point.
    # (3, N): each coordinate a contiguous row, so the range tests below stream through memory.
    su, sv, near = affine_rows(calib.velo_to_pixels_f32, points[:, :3].astype(np.float32, copy=False).T)
    candidates = np.flatnonzero(
        (near > min_depth - 0.01)
        & (su > -2.0 * near) & (su < (w + 2.0) * near)
        & (sv > -2.0 * near) & (sv < (h + 2.0) * near)
    )
    uv, depth = calib.velo_to_image(points[candidates, :3])
    cols = np.rint(uv[:, 0])
    rows = np.rint(uv[:, 1])
    keep = (depth > min_depth) & (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
    flat = rows[keep].astype(np.int64) * w + cols[keep].astype(np.int64)
    depth = depth[keep].astype(np.float32)
    # Sort by pixel, then by depth: the first entry of each pixel run is the nearest return. Positive
    # float32 values order like their bit patterns, so one uint64 key (pixel, depth bits) sorts both
    # at once, exactly, 7× faster than np.lexsort of the two keys; the key alone is sorted and both
    # are read back from it (against an argsort and two gathers, 0.50 → 0.44 ms for a 16-line scan).
    key = (flat.astype(np.uint64) << np.uint64(32)) | depth.view(np.uint32).astype(np.uint64)
    key.sort()
    flat = (key >> np.uint64(32)).astype(np.intp)
    first = np.ones(flat.size, dtype=bool)
    first[1:] = flat[1:] != flat[:-1]
    out = np.zeros(h * w, dtype=np.float32)
    out[flat[first]] = key[first].astype(np.uint32).view(np.float32)
    return out.reshape(h, w)
