"""Request and response bodies of the HTTP API (pydantic models with examples for the OpenAPI schema)."""

from __future__ import annotations

from enum import Enum, IntEnum
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field

from pipeline.checks import (
    FRAME_WARNING_CODES,
    LOAD_WARNING_CODES,
    STAMP_NS_MAX,
    WARNING_MEANINGS,
    WarningCode,
)


def _code_list(codes: tuple[WarningCode, ...]) -> str:
    """``code`` — what it means; … for a field's description."""
    return "; ".join(f"`{code}` — {WARNING_MEANINGS[code]}" for code in codes)


class OutputFormat(str, Enum):
    """How ``POST /v1/detect`` answers."""

    json = "json"
    kitti = "kitti"


class BeamCount(IntEnum):
    """Lines a 64-line scan can be thinned to on the server; 0 takes the scan as sent, as leaving it out does and
    as ``--emulate-beams 0`` does in the commands."""

    as_sent = 0
    four = 4
    eight = 8
    sixteen = 16
    thirty_two = 32


class NonFinitePolicy(str, Enum):
    """What to do with scan rows holding NaN or infinite values."""

    drop = "drop"
    reject = "reject"


class Box(BaseModel):
    """A 3D box in the LiDAR frame: KITTI's velodyne frame (x forward, y left, z up, origin at the sensor;
    metres, radians), not KITTI's camera frame, whose labels give the bottom centre and ``rotation_y``."""

    x: float = Field(description="centre, forward of the LiDAR (metres)")
    y: float = Field(description="centre, left of the LiDAR (metres)")
    z: float = Field(description="centre (not the bottom), above the LiDAR (metres; the road is near -1.73)")
    l: float = Field(description="length along the heading (metres)")
    w: float = Field(description="width (metres)")
    h: float = Field(description="height (metres)")
    yaw: float = Field(description="heading about z from the x axis towards y (radians); KITTI rotation_y = -yaw - π/2, wrapped to [-π, π)")


class Detection(BaseModel):
    """One detected object."""

    label: str = Field(description="object class; the models detect cars only", examples=["Car"])
    score: float = Field(ge=0.0, le=1.0, description="confidence in [0, 1]; the answer holds those at or above "
                         "`score_threshold`, best first")
    box: Box
    bev_corners: list[Annotated[list[float], Field(min_length=2, max_length=2)]] = Field(
        min_length=4, max_length=4,
        description="the box seen from above: [x, y] of its four corners in the LiDAR frame (metres; not pixels "
        "of the BEV picture), counter-clockwise from front-left: front-left, rear-left, rear-right, front-right",
    )


class ModelRef(BaseModel):
    """Which models answered (the same as the X-Model-* headers of every detection answer)."""

    id: str = Field(description="sha256 (hex) of the model directory's manifest.json, which lists every file's "
                    "sha256: equal ids, equal models (header X-Model-ID)",
                    examples=["9c1f3e0a5b7d2c4e6f8a0b1c3d5e7f9a1b3c5d7e9f0a2b4c6d8e0f1a3b5c7d9e"])
    directory: str = Field(description="the model directory's own name, after symbolic links (header "
                           "X-Model-Directory, percent-encoded)", examples=["edge"])
    preset: str = Field(description="the model preset (manifest.json; header X-Model-Preset)", examples=["edge"])
    precision: str = Field(description="`fp32`, `fp16` or `int8` (header X-Model-Precision)", examples=["fp32"])
    sha256: dict[str, str] = Field(description="sha256 (hex) of each model file, by file name")


class ModelIdentityInfo(ModelRef):
    """Which model the service runs: what each detection answer's `model` says, and the rest of its identity."""

    path: str = Field(description="the model directory's absolute path, after symbolic links")
    format: int = Field(description="the manifest's format version (`lowres3d-models/N`)", examples=[1])
    weights: str = Field(description="the manifest's `weights`: `trained`, `initialised (untrained)`, or each "
                         "network's state when they differ (`partially trained: depth trained, pixor initialised "
                         "(untrained)`)", examples=["trained"])
    training_data: dict[str, str | None] = Field(
        description="each network's training data as its training record names it (null: not recorded)")


# A capture time as the query parameters take it and the answer echoes it: int64 nanoseconds (pipeline.checks).
StampNs = Annotated[int, Field(ge=0, le=STAMP_NS_MAX, json_schema_extra={"format": "int64"})]
STAMP_TIME_BASE = ("integer nanoseconds on a clock both sensors share, since the Unix epoch for ROS (sec * "
                   "1000000000 + nanosec) and Python's time.time_ns()")


class SensorStamps(BaseModel):
    """The capture times the request sent, echoed so that an answer arriving out of order can be placed in time."""

    image_ns: StampNs | None = Field(description=f"the image's capture time as sent (`image_stamp_ns`): {STAMP_TIME_BASE}; "
                                     "null when not sent. Over 2^53: read it as a 64-bit integer, not a double",
                                     examples=[1718000000050000000])
    points_ns: StampNs | None = Field(description="the scan's capture time as sent (`points_stamp_ns`), the time of the "
                                      "boxes (they are in the scan's frame); null when not sent",
                                      examples=[1718000000000000000])
    skew_ms: float | None = Field(description="image_ns - points_ns in milliseconds (positive: the image after the "
                                  "scan); null unless both were sent. Beyond --max-sensor-skew-ms, with a camera "
                                  "the warning `sensor_skew`", examples=[50.0])


_DETECT_EXAMPLE: dict[str, Any] = {
    "detections": [
        {
            "label": "Car",
            "score": 0.91,
            "box": {"x": 12.4, "y": -3.1, "z": -0.9, "l": 3.9, "w": 1.6, "h": 1.5, "yaw": 0.02},
            "bev_corners": [[14.35, -2.26], [10.45, -2.34], [10.45, -3.94], [14.35, -3.86]],
        }
    ],
    "timings_ms": {
        "queue_wait": 0.1, "parse_inputs": 9.8, "prepare": 4.1, "depth_net": 180.2, "ray_table": 0.01, "pseudo_points": 2.0,
        "voxelize": 3.1, "pixor": 95.4, "decode": 0.9, "total": 296.0,
    },
    "model": {"id": "9c1f…", "directory": "edge", "preset": "edge-split-near35", "precision": "fp32",
              "sha256": {"depth.onnx": "3f1c…", "pixor.onnx": "9a0b…"}},
    "warnings": ["points: dropped 3 rows with NaN or infinite values"],
    "warning_codes": ["nonfinite_dropped"],
    "request_id": "5f0c8e7a9b2d4c1e8f3a6b7c9d0e1f2a",
    "stamps": {"image_ns": 1718000000012000000, "points_ns": 1718000000000000000, "skew_ms": 12.0},
}


class DetectResponse(BaseModel):
    """The answer of ``POST /v1/detect`` (``format=json``)."""

    model_config = ConfigDict(json_schema_extra={"examples": [_DETECT_EXAMPLE]})

    detections: list[Detection] = Field(description="best score first; empty when no car is found")
    timings_ms: dict[str, float] = Field(
        description="milliseconds per stage (`queue_wait`, `parse_inputs`, `emulate_beams`, `prepare`, `depth_net`, "
        "`ray_table`, `pseudo_points`, `voxelize`, `pixor`, `decode`, ...: the stages present vary with the model "
        "and options); `total` is the server time from entering the queue to the result"
    )
    model: ModelRef
    warnings: list[str] = Field(description="what was dropped or adjusted on the way, and inputs unlike the "
                                "training data (the boxes are then fewer or worse, not wrong)")
    warning_codes: list[str] = Field(
        description="each warning's stable, machine-readable code, in the same order as `warnings` (whose text "
        "carries the frame's figures): alert on these. " + _code_list(FRAME_WARNING_CODES) + ". A code added later "
        "is a new warning: treat an unknown one as a warning"
    )
    request_id: str = Field(description="this request's id, as in the X-Request-ID header")
    # Left out of the answer unless a stamp was sent (the route answers without unset fields): a client that sends
    # none, as KITTI's, gets the answer it always had.
    stamps: SensorStamps | None = Field(None, description="the capture times the request sent "
                                        "(`image_stamp_ns`, `points_stamp_ns`), echoed; absent when it sent none")


# Every code an error answer can carry, by status (docs/service.md has when each is answered).
ERROR_CODES: dict[int, tuple[str, ...]] = {
    400: ("bad_request",),
    401: ("unauthorized",),
    404: ("not_found",),
    405: ("method_not_allowed",),
    408: ("request_timeout",),
    413: ("body_too_large",),
    415: ("unsupported_media_type",),
    422: ("invalid_input",),
    500: ("internal_error",),
    503: ("overloaded", "not_ready", "shutting_down"),
    504: ("timeout",),
}


class ErrorDetail(BaseModel):
    """What went wrong; ``message`` names the field or part at fault."""

    code: str = Field(
        description="stable and machine-readable, for a client's logic: "
        + "; ".join(f"{status}: {', '.join(codes)}" for status, codes in ERROR_CODES.items())
        + ". A code added later keeps its status's meaning: handle an unknown one by the HTTP status",
        examples=["invalid_input"],
    )
    message: str = Field(description="for people: starts with the field, part, header or option at fault",
                         examples=["points: size 100 bytes is not a multiple of 16"])
    request_id: str = Field(description="this request's id, as in the X-Request-ID header; quote it when reporting "
                            "a problem (the server log names it)")


class ErrorResponse(BaseModel):
    """Every error answer has this shape."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {"error": {"code": "invalid_input", "message": "calib: missing calibration key(s) P2",
                           "request_id": "5f0c8e7a9b2d4c1e8f3a6b7c9d0e1f2a"}}
            ]
        }
    )

    error: ErrorDetail


class Health(BaseModel):
    """Liveness or readiness."""

    status: str = Field(examples=["ok"])
    ready: bool | None = Field(default=None, description="models loaded and warmed up")


class SessionPair(BaseModel):
    """One Detector's sessions: where they run, and what loading them warned of."""

    device_id: int | None = Field(description="its GPU (--device-ids); null: the provider's default, GPU 0 on a GPU")
    providers_in_use: dict[str, list[str]] = Field(description="per network, after ONNX Runtime's own fallback")
    warnings: list[str] = Field(default_factory=list, description="what loading this pair warned of")


class ModelInfo(BaseModel):
    """The loaded model directory: its identity, its manifest and the execution providers actually in use."""

    identity: ModelIdentityInfo = Field(description="which model runs: the same id, directory, preset and "
                                        "precision as each detection answer's `model` and X-Model-* headers and "
                                        "`lowres3d_model_info` in /metrics")
    preset: str
    sha256: dict[str, str]
    providers_in_use: dict[str, list[str]] = Field(description="per network, after ONNX Runtime's own fallback")
    two_stage: bool = Field(description="depth completion + PIXOR (true) or LiDAR-only PIXOR (false)")
    workers: int
    sessions: str = Field(description="'shared' or 'per-worker'")
    intra_op_threads: int = Field(description="ONNX Runtime intra-op threads per session")
    queue_size: int
    crop_hw: Annotated[list[int], Field(min_length=2, max_length=2)] | None = Field(
        description="smallest image [height, width] the model accepts; null for a LiDAR-only model, which "
        "needs no image"
    )
    default_calib: bool = Field(description="a default calibration is configured (calib is optional)")
    mirror_tta: bool = Field(description="PIXOR also runs on the mirrored BEV, maps averaged (--mirror-tta)")
    session_pairs: list[SessionPair] = Field(
        description="each session pair (one per worker with --sessions per-worker, else one): its GPU and the "
        "providers it runs on; providers_in_use above is the first pair's"
    )
    warnings: list[str] = Field(
        default_factory=list, description="from loading any session pair: untrained weights, a provider that did "
        "not load, the model's precision on this machine (INT8 this CPU may run inexactly, FP16 on the CPU)"
    )
    warning_codes: list[str] = Field(
        default_factory=list, description="each of `warnings`' stable code, in the same order: "
        + _code_list(LOAD_WARNING_CODES)
    )
    manifest: dict = Field(description="manifest.json of the model directory")
