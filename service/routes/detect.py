"""``POST /v1/detect`` (JSON or KITTI lines), ``POST /v1/detect/bev.png`` (the BEV picture) and
``POST /v1/detect/camera.png`` (the camera image with the boxes as wireframes).

All three take multipart/form-data parts ``image``, ``points`` and optionally
``calib`` (and ``image`` too for a LiDAR-only model, unless the answer is about
the camera: ``format=kitti``, ``camera.png``). The frame's place in the inference
pool was taken before its upload was read (service.middleware.AdmissionMiddleware);
the checks that need no decoding run on the event loop before the frame is queued;
decoding, detection and rendering run on the inference pool. A client that closes
the connection while its frame waits or runs stops the frame (counted 499).

A client pairing an unsynchronised camera and LiDAR sends each one's capture time (query ``image_stamp_ns``,
``points_stamp_ns``): the answer echoes them (``stamps``; X-Image-Stamp-Ns, X-Points-Stamp-Ns) and warns
``sensor_skew`` when they lie further apart than ``--max-sensor-skew-ms``.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from enum import Enum
from typing import Annotated, Any, TypeVar
from urllib.parse import quote

import cv2
from fastapi import APIRouter, Depends, File, Query, Request, UploadFile
from fastapi.responses import PlainTextResponse, Response
from pydantic import BeforeValidator

from pipeline.boxes import BOX_FIELDS, bev_corners, in_camera_view
from pipeline.calib import Calibration
from pipeline.checks import MAX_SENSOR_SKEW_MS, CodedWarning, WarningCode
from pipeline.detector import Cancellation, Detections, Detector, RunCancelled
from pipeline.kitti import format_label
from pipeline.model_files import ModelIdentity
from pipeline.render import render_bev, render_camera, split_scan_and_pseudo
from service.deps import (
    MetricsDep,
    ReadyRuntimeDep,
    RequestIdDep,
    SettingsDep,
    check_parts,
    reject_unknown_query,
    require_multipart,
)
from service.errors import ServiceError
from service.inputs import (
    DecodedFrame,
    FrameStamps,
    FrameUpload,
    check_stamps,
    check_upload,
    decode_frame,
    stamp_query,
    stamp_warnings,
)
from service.metrics import Metrics
from service.pool import JobResult, PoolClosed, PoolFull, PoolTimeout, Reservation
from service.routes.responses import error_responses
from service.runtime import Runtime
from service.schemas import (
    STAMP_TIME_BASE,
    BeamCount,
    Box,
    Detection,
    DetectResponse,
    ModelRef,
    NonFinitePolicy,
    OutputFormat,
    SensorStamps,
    StampNs,
)
from service.settings import Settings

T = TypeVar("T")

# Every route here takes query options: a misspelt one is a 422, not a silently ignored default.
router = APIRouter(prefix="/v1", tags=["detect"], dependencies=[Depends(reject_unknown_query)])

_KITTI_EXAMPLE = "Car 0.00 0 -1.59 582.33 178.06 629.75 207.93 1.52 1.63 3.88 -0.95 1.68 25.30 -1.61 0.9137\n"


class Picture(Enum):
    """The picture a detection route answers (its value names it in messages)."""

    bev = "BEV"
    camera = "camera view"


@dataclass(frozen=True)
class FrameOptions:
    """Query options shared by the three detection routes."""

    score_threshold: float | None
    emulate_beams: int | None
    nonfinite: NonFinitePolicy
    stamps: FrameStamps


# Query text → int64 nanoseconds, digits only (service.inputs.stamp_query says what else is wrong); the schema says
# integer, int64.
StampQuery = Annotated[StampNs | None, BeforeValidator(stamp_query)]


def frame_options(
    score_threshold: Annotated[
        float | None,
        # allow_inf_nan=False: NaN would otherwise fail the range check with a misleading "≤ 1".
        Query(
            ge=0.0, le=1.0, allow_inf_nan=False, description="minimum score (default: the model's)", examples=[0.5]
        ),
    ] = None,
    emulate_beams: Annotated[
        BeamCount | None,
        Query(description="thin a 64-line scan to this many lines on the server first (0, or left out: the scan "
              "as sent)", examples=[16]),
    ] = None,
    nonfinite: Annotated[
        NonFinitePolicy,
        Query(description="scan rows with NaN/Inf: `drop` them (with a warning) or `reject` the request (422)"),
    ] = NonFinitePolicy.drop,
    image_stamp_ns: Annotated[StampQuery, Query(
        description=f"the image's capture time, {STAMP_TIME_BASE} (a float of seconds is refused); echoed in "
        "`stamps` and X-Image-Stamp-Ns. With `points_stamp_ns`, the warning `sensor_skew` when they lie further "
        f"apart than the server's --max-sensor-skew-ms (default {MAX_SENSOR_SKEW_MS:g}) and the image is used",
        examples=[1718000000012000000],
    )] = None,
    points_stamp_ns: Annotated[StampQuery, Query(
        description="the scan's capture time, on the image's clock and in its unit (nanoseconds), best the moment "
        "the LiDAR swept the camera's view: the time of the boxes; echoed in `stamps` and X-Points-Stamp-Ns",
        examples=[1718000000000000000],
    )] = None,
) -> FrameOptions:
    """Collect the query options."""
    beams = int(emulate_beams) if emulate_beams else None  # 0 (BeamCount.as_sent) as left out: the scan as sent
    return FrameOptions(score_threshold, beams, nonfinite, FrameStamps(image_stamp_ns, points_stamp_ns))


FrameOptionsDep = Annotated[FrameOptions, Depends(frame_options)]
# Optional in the signature: a LiDAR-only model answers from the scan alone. The schema marks it required
# for a camera model (service.app), and service.inputs.check_upload answers 422 when it is missing.
ImagePart = Annotated[UploadFile | None, File(
    description="camera image, PNG or JPEG (at least the model's crop); a LiDAR-only model needs it only for "
    "`format=kitti` and the camera picture"
)]
PointsPart = Annotated[UploadFile, File(description="KITTI velodyne .bin: little-endian float32 rows x, y, z, reflectance")]
CalibPart = Annotated[
    UploadFile | None, File(description="KITTI object calib.txt (P2, R0_rect, Tr_velo_to_cam); optional with a server default")
]


@dataclass
class FrameResult:
    """What a worker made of one frame."""

    frame: DecodedFrame
    detections: Detections
    timings_ms: dict[str, float]
    png: bytes | None = None
    stamp_warnings: list[CodedWarning] = field(default_factory=list)  # the capture times' (sensor_skew)

    @property
    def warnings(self) -> list[str]:
        """The frame's warnings: its capture times', its decoding's, then the Detector's."""
        return [w.message for w in self.stamp_warnings] + self.frame.warnings + self.detections.warnings

    @property
    def warning_codes(self) -> list[str]:
        """Each warning's code, parallel to :attr:`warnings`."""
        return [w.code for w in self.stamp_warnings] + self.frame.warning_codes + self.detections.warning_codes


def _detect_job(
    upload: FrameUpload, options: FrameOptions, calib: Calibration | None, picture: Picture | None,
    early_warnings: list[CodedWarning], title: str | None = None,
) -> Callable[[Detector, Cancellation], FrameResult]:
    """The work of one frame on a worker: decode the parts, detect, optionally render a picture as PNG (``title``
    in its key, with the frame's warning codes)."""

    def job(detector: Detector, cancel: Cancellation) -> FrameResult:
        tic = time.perf_counter()
        frame = decode_frame(upload, calib, options.nonfinite)
        parse_ms = (time.perf_counter() - tic) * 1e3
        if cancel.cancelled:  # decoding a large upload takes a while: nobody may wait for the frame any more
            raise RunCancelled("the frame was cancelled while its parts were decoded")
        detections = detector.detect(
            frame.image, frame.points, frame.calib, options.score_threshold, options.emulate_beams,
            keep_points=picture is Picture.bev, cancel=cancel,
        )
        timings = {"parse_inputs": parse_ms, **{k: v for k, v in detections.timings_ms.items() if k != "total"}}
        png = None
        if picture is not None:
            tic = time.perf_counter()
            if picture is Picture.bev:
                assert detections.points is not None  # keep_points=True: the points PIXOR saw
                # As pipeline.detect draws it: the scan over the camera's pseudo points, the camera's view.
                scan, pseudo = split_scan_and_pseudo(detections.points, detections.pseudo_count)
                view = (frame.calib, frame.image_hw) if frame.calib is not None and frame.image_hw else None
                bgr = render_bev(scan, detector.preset.bev, detections.boxes, detections.scores,
                                 title=title, legend=True,  # what the colours are and which way is ahead
                                 warnings=_picture_warnings(early_warnings, frame.warning_codes, detections),
                                 pseudo=pseudo, view=view)
            else:  # the boxes of format=kitti: those whose centre the camera sees
                assert frame.image is not None and frame.calib is not None and frame.image_hw is not None  # checked
                seen = in_camera_view(detections.boxes, frame.calib, frame.image_hw)
                bgr = render_camera(frame.image, frame.calib, detections.boxes[seen], detections.scores[seen],
                                    title=title, legend=True,  # what the wireframes and numbers are, as on the BEV
                                    warnings=_picture_warnings(early_warnings, frame.warning_codes, detections))
            ok, encoded = cv2.imencode(".png", bgr)
            if not ok:
                raise RuntimeError(f"PNG encoding of the {picture.value} picture failed")
            png = encoded.tobytes()
            timings["render"] = (time.perf_counter() - tic) * 1e3
        return FrameResult(frame, detections, timings, png, early_warnings)

    return job


def picture_title(identity: ModelIdentity, emulate_beams: int | None) -> str:
    """What a bev.png or camera.png shows, for its key: the model (its id's first 12 hex digits, as X-Model-ID
    begins, and its directory), its preset and whether the scan was thinned."""
    thinned = f", scan thinned to {emulate_beams} lines" if emulate_beams else ""
    return f"model {identity.id[:12]} ({identity.directory}), preset {identity.preset}{thinned}"


def _picture_warnings(early: list[CodedWarning], decoding: list[str], detections: Detections) -> list[str]:
    """The frame's warning codes (as X-Warning-Codes carries them; X-Warnings the messages) for a picture's key,
    but the thinning asked for, which its title says."""
    codes = [w.code for w in early] + list(decoding) + list(detections.warning_codes)
    return [c for c in codes if c != WarningCode.BEAMS_EMULATED]


def _camera_use(runtime: Runtime, answer: str | None) -> str | None:
    """Why a request needs the camera image and a calibration, for the 422 when one is missing; None when the
    scan alone answers it. ``answer``: what of the answer needs them (None: nothing, boxes in the LiDAR frame)."""
    if runtime.detector.two_stage:
        return "a camera model: depth completion projects the scan into the image"
    return answer


async def _until_disconnected(receive: Callable[[], Awaitable[Any]]) -> None:
    """Return once the client has closed the connection. Only once the body has been read: what the server
    has to say then is that the connection ended (or, from a test client, that the answer is complete)."""
    while (await receive())["type"] != "http.disconnect":
        pass


async def _unless_the_client_leaves(work: Awaitable[T], request: Request) -> T:
    """``work``'s result, or ServiceError 499 when the client closes the connection first: ``work`` is then
    cancelled, which stops the frame (never started if queued, stopped at its next stage if on a worker)."""
    task = asyncio.ensure_future(work)
    watcher = asyncio.ensure_future(_until_disconnected(request.receive))
    try:
        await asyncio.wait({task, watcher}, return_when=asyncio.FIRST_COMPLETED)
    except asyncio.CancelledError:  # the request itself is cancelled (the shutdown's grace ran out): its frame too
        task.cancel()
        watcher.cancel()
        raise
    if task.done() or watcher.exception() is not None:  # done, or no word on the connection: the frame decides
        watcher.cancel()
        return await task
    task.cancel()
    await asyncio.wait({task})  # the frame's place given back; our own cancellation still propagates
    raise ServiceError(499, "client_disconnected", "the client closed the connection before its answer")


async def _run_frame(
    request: Request, runtime: Runtime, settings: Settings, metrics: Metrics, upload: FrameUpload,
    options: FrameOptions, picture: Picture | None, needs_camera: str | None = None,
) -> FrameResult:
    """Check, queue and run one frame; pool conditions become 503/504 answers, a client gone a 499.

    needs_camera: what of the answer needs the image and a calibration even from a LiDAR-only model."""
    # Before the queue: a request that can never succeed gets its 4xx without waiting for a worker.
    camera_use = _camera_use(runtime, needs_camera)
    calib = check_upload(upload, settings.max_points, settings.max_image_pixels, runtime.crop_hw,
                         runtime.default_calib, camera_use)
    check_stamps(options.stamps, upload)
    # Only where the image is used: a LiDAR-only model's boxes do not depend on when the image was taken.
    job = _detect_job(upload, options, calib, picture,
                      stamp_warnings(options.stamps, settings.max_sensor_skew_ms, camera_use),
                      picture_title(runtime.identity, options.emulate_beams) if picture is not None else None)
    state = request.scope.get("state") or {}
    # The place AdmissionMiddleware took before the upload was read (None: an app served without it).
    reservation: Reservation | None = state.get("reservation")
    started = time.perf_counter()
    try:
        outcome: JobResult[FrameResult] = await _unless_the_client_leaves(
            runtime.pool.run(job, settings.request_timeout_s, reservation, state.get("request_id")), request)
    except PoolFull as exc:
        raise ServiceError(
            503, "overloaded", f"inference queue: full ({runtime.pool.capacity} frames admitted); retry later",
            {"Retry-After": str(exc.retry_after_s)},
        ) from None
    except PoolTimeout as exc:
        raise ServiceError(504, "timeout", f"request: {exc}") from None
    except PoolClosed:
        raise ServiceError(503, "shutting_down", "the service is shutting down", {"Retry-After": "1"}) from None
    result = outcome.value
    result.timings_ms = {
        "queue_wait": outcome.queue_wait_ms, **result.timings_ms, "total": (time.perf_counter() - started) * 1e3
    }
    metrics.observe_stages(result.timings_ms)
    metrics.count_warnings(result.warning_codes)
    state["warning_codes"] = result.warning_codes  # the request's access line (service/middleware.py)
    return result


async def _read_upload(image: UploadFile | None, points: UploadFile, calib: UploadFile | None) -> FrameUpload:
    return FrameUpload(
        image=await image.read() if image is not None else None, points=await points.read(),
        calib=await calib.read() if calib is not None else None,
    )


def _to_response(result: FrameResult, runtime: Runtime, request_id: str, stamps: FrameStamps) -> DetectResponse:
    detections = result.detections
    corners = bev_corners(detections.boxes)
    # Set only when a stamp was sent: the route leaves unset fields out, so answers without stamps stay as they were.
    echoed = {"stamps": SensorStamps(image_ns=stamps.image_ns, points_ns=stamps.points_ns,
                                     skew_ms=stamps.skew_ms)} if stamps.sent else {}
    return DetectResponse(
        detections=[
            Detection(
                label=detections.label,
                score=float(score),
                box=Box(**dict(zip(BOX_FIELDS, map(float, box), strict=True))),
                bev_corners=[[float(x), float(y)] for x, y in corners[i]],
            )
            for i, (box, score) in enumerate(zip(detections.boxes, detections.scores, strict=True))
        ],
        timings_ms={k: round(v, 3) for k, v in result.timings_ms.items()},
        model=ModelRef(id=runtime.identity.id, directory=runtime.identity.directory, preset=runtime.identity.preset,
                       precision=runtime.identity.precision, sha256=runtime.identity.sha256),
        warnings=result.warnings,
        warning_codes=result.warning_codes,
        request_id=request_id,
        **echoed,
    )


def _warning_headers(result: FrameResult) -> dict[str, str]:
    """The warnings of a frame and their codes as headers, for the answers whose body has no room for them
    (KITTI lines, the PNG): JSON-encoded ASCII, absent when there are none."""
    warnings = result.warnings
    if not warnings:
        return {}
    return {"X-Warnings": json.dumps(warnings), "X-Warning-Codes": json.dumps(result.warning_codes)}


def stamp_headers(stamps: FrameStamps) -> dict[str, str]:
    """The capture times the request sent, echoed on every detection answer (a KITTI-lines or PNG answer has no
    room for them in its body): decimal nanoseconds, each header absent when its stamp was not sent."""
    headers = {}
    if stamps.image_ns is not None:
        headers["X-Image-Stamp-Ns"] = str(stamps.image_ns)
    if stamps.points_ns is not None:
        headers["X-Points-Stamp-Ns"] = str(stamps.points_ns)
    return headers


def model_headers(identity: ModelIdentity) -> dict[str, str]:
    """Which model answered, on every detection answer (a fleet's proxy or dashboard reads headers, whatever
    the body's format): ASCII, the directory's name percent-encoded."""
    return {"X-Model-ID": identity.id, "X-Model-Directory": quote(identity.directory, safe=""),
            "X-Model-Preset": quote(identity.preset, safe=""), "X-Model-Precision": identity.precision}


_MODEL_HEADERS = {
    "X-Model-ID": {"description": "sha256 (hex) of the model directory's manifest.json: equal ids, equal models "
                   "(`model.id`; `id` in `lowres3d_model_info`)", "required": True, "schema": {"type": "string"}},
    "X-Model-Directory": {"description": "the model directory's own name after symbolic links, percent-encoded",
                          "required": True, "schema": {"type": "string"}},
    "X-Model-Preset": {"description": "the model's preset, percent-encoded", "required": True, "schema": {"type": "string"}},
    "X-Model-Precision": {"description": "`fp32`, `fp16` or `int8`", "required": True, "schema": {"type": "string"}},
}


_WARNINGS_HEADER = {
    "X-Warnings": {
        "description": "with `format=kitti` and on the pictures: the frame's warnings as a JSON list (absent when "
        "none)",
        "schema": {"type": "string"},
    },
    "X-Warning-Codes": {
        "description": "with X-Warnings: each warning's stable code (`warning_codes` of the JSON answer), a JSON list "
        "in the same order",
        "schema": {"type": "string"},
    },
}

_STAMP_HEADERS = {
    "X-Image-Stamp-Ns": {"description": "`image_stamp_ns` as sent (decimal nanoseconds; absent when not sent)",
                         "schema": {"type": "string"}},
    "X-Points-Stamp-Ns": {"description": "`points_stamp_ns` as sent (decimal nanoseconds; absent when not sent)",
                          "schema": {"type": "string"}},
}

# The detection routes answer the same errors (documented for clients and the OpenAPI fuzz test).
DETECT_ERRORS = error_responses(400, 401, 408, 413, 415, 422, 500, 503, 504)


# The PNG as a binary string: a bare `image/png: {}` made code generators' methods return nothing at all.
_PNG_SCHEMA = {"type": "string", "format": "binary", "contentMediaType": "image/png"}

# What each multipart part is (FastAPI's schema calls every file application/octet-stream): the Content-Type a
# generated client sends with it. The service reads the bytes whatever the part's Content-Type says.
_FRAME_PARTS = {"requestBody": {"content": {"multipart/form-data": {"encoding": {
    "image": {"contentType": "image/png, image/jpeg"},
    "points": {"contentType": "application/octet-stream"},
    "calib": {"contentType": "text/plain"},
}}}}}


def _picture_responses(description: str) -> dict:
    """The OpenAPI answers of a route answering a PNG picture."""
    return {200: {"description": description, "content": {"image/png": {"schema": _PNG_SCHEMA}},
                  "headers": {**_WARNINGS_HEADER, **_MODEL_HEADERS, **_STAMP_HEADERS}},
            **DETECT_ERRORS}


async def _picture_answer(request: Request, runtime: Runtime, settings: Settings, metrics: Metrics,
                          options: FrameOptions, upload: FrameUpload, picture: Picture) -> Response:
    """Detect on an uploaded frame and answer ``picture`` as PNG, the frame's warnings in X-Warnings."""
    needs = "the camera picture draws the boxes on the image" if picture is Picture.camera else None
    result = await _run_frame(request, runtime, settings, metrics, upload, options, picture=picture,
                              needs_camera=needs)
    assert result.png is not None
    return Response(result.png, media_type="image/png",
                    headers={**model_headers(runtime.identity), **_warning_headers(result), **stamp_headers(options.stamps)})


@router.post(
    "/detect",
    summary="Detect cars in one frame",
    response_model=DetectResponse,
    response_model_exclude_unset=True,  # `stamps` only when sent (_to_response); every other field is always set
    dependencies=[Depends(require_multipart), Depends(check_parts)],
    openapi_extra=_FRAME_PARTS,
    responses={
        200: {
            "description": "detections (JSON), or KITTI result lines with `format=kitti` (`text/plain`: the query "
                           "parameter chooses, the `Accept` header does not)",
            "content": {"text/plain": {"schema": {"type": "string", "description": "one KITTI label_2 line per "
                                                  "box the camera sees, with the score as a 16th value"},
                                       "example": _KITTI_EXAMPLE}},
            "headers": {**_WARNINGS_HEADER, **_MODEL_HEADERS, **_STAMP_HEADERS},
        },
        **DETECT_ERRORS,
    },
)
async def detect(
    request: Request,
    response: Response,
    runtime: ReadyRuntimeDep,
    settings: SettingsDep,
    metrics: MetricsDep,
    options: FrameOptionsDep,
    *,
    image: ImagePart = None,
    points: PointsPart,
    calib: CalibPart = None,
    output_format: Annotated[
        OutputFormat, Query(
            alias="format",
            description="`json`, or `kitti` for KITTI label_2 result lines (the boxes the camera sees)",
        )
    ] = OutputFormat.json,
    request_id: RequestIdDep,
) -> DetectResponse | Response:
    """Boxes in the LiDAR frame with scores, per-stage timings, the model's identity and warnings.

    A camera model needs `image`, `points` and a calibration (`calib`, or the server's default); a LiDAR-only
    model (`two_stage` false in `/v1/model`) needs `points` alone, and the image and a calibration only for
    `format=kitti`.

    Example: `curl -F image=@000006.png -F points=@000006.bin -F calib=@000006.txt
    'http://127.0.0.1:8000/v1/detect?emulate_beams=16'`
    """
    upload = await _read_upload(image, points, calib)
    kitti = output_format is OutputFormat.kitti
    needs = "format=kitti gives the boxes the camera sees, in its image" if kitti else None
    result = await _run_frame(request, runtime, settings, metrics, upload, options, picture=None, needs_camera=needs)
    if kitti:
        frame = result.frame
        assert frame.calib is not None and frame.image_hw is not None  # check_upload refused a frame without
        objects = result.detections.to_objects(frame.calib, frame.image_hw)
        return PlainTextResponse("".join(format_label(o) + "\n" for o in objects),
                                 headers={**model_headers(runtime.identity), **_warning_headers(result),
                                          **stamp_headers(options.stamps)})
    # FastAPI copies them onto the JSON answer
    response.headers.update({**model_headers(runtime.identity), **stamp_headers(options.stamps)})
    return _to_response(result, runtime, request_id, options.stamps)


@router.post(
    "/detect/bev.png",
    summary="Detect cars and answer the bird's-eye-view picture",
    dependencies=[Depends(require_multipart), Depends(check_parts)],
    openapi_extra=_FRAME_PARTS,
    response_class=Response,
    responses=_picture_responses("BEV picture: points, detected boxes and scores, a key in the top-left corner"),
)
async def detect_bev_png(
    request: Request,
    runtime: ReadyRuntimeDep,
    settings: SettingsDep,
    metrics: MetricsDep,
    options: FrameOptionsDep,
    *,
    image: ImagePart = None,
    points: PointsPart,
    calib: CalibPart = None,
) -> Response:
    """The same inputs as `/v1/detect`; the answer is a PNG (x forward points up)."""
    return await _picture_answer(request, runtime, settings, metrics, options,
                                 await _read_upload(image, points, calib), Picture.bev)


@router.post(
    "/detect/camera.png",
    summary="Detect cars and answer the camera image with the boxes drawn",
    dependencies=[Depends(require_multipart), Depends(check_parts)],
    openapi_extra=_FRAME_PARTS,
    response_class=Response,
    responses=_picture_responses("the uploaded image with each box the camera sees as a wireframe and its score, "
                                  "a key in the top-right corner"),
)
async def detect_camera_png(
    request: Request,
    runtime: ReadyRuntimeDep,
    settings: SettingsDep,
    metrics: MetricsDep,
    options: FrameOptionsDep,
    *,
    image: ImagePart = None,
    points: PointsPart,
    calib: CalibPart = None,
) -> Response:
    """The same inputs as `/v1/detect`; the answer is the image as PNG with the boxes of `format=kitti` drawn."""
    return await _picture_answer(request, runtime, settings, metrics, options,
                                 await _read_upload(image, points, calib), Picture.camera)
