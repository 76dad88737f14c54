"""``GET /v1/model``: the loaded model directory, its manifest and the execution providers in use."""

from __future__ import annotations

from dataclasses import asdict

from fastapi import APIRouter

from service.deps import RuntimeDep, SettingsDep
from service.routes.responses import error_responses
from service.schemas import ModelIdentityInfo, ModelInfo, SessionPair

router = APIRouter(tags=["model"])


@router.get(
    "/v1/model",
    summary="The loaded model directory",
    responses=error_responses(401, 408, 500, 503),
)
async def model_info(runtime: RuntimeDep, settings: SettingsDep) -> ModelInfo:
    """Identity (manifest sha256, directory, preset, precision), manifest, sha256 of each file and the execution
    providers each network actually runs on."""
    detector = runtime.detector
    # Every pair's, once each: a second worker's GPU that fell back must not hide behind the first's.
    loaded = list(dict.fromkeys((code, warning) for d in runtime.detectors
                                for code, warning in zip(d.load_warning_codes, d.load_warnings, strict=True)))
    return ModelInfo(
        identity=ModelIdentityInfo(**asdict(runtime.identity)),
        preset=detector.preset.name,
        sha256=detector.sha256,
        providers_in_use=detector.providers_in_use,
        two_stage=detector.two_stage,
        workers=settings.workers,
        sessions=settings.sessions,
        intra_op_threads=settings.resolved_intra_op_threads(),
        queue_size=settings.queue_size,
        crop_hw=list(runtime.crop_hw) if runtime.crop_hw is not None else None,
        default_calib=runtime.default_calib is not None,
        mirror_tta=detector.mirror_tta,
        session_pairs=[SessionPair(device_id=d.device_id, providers_in_use=d.providers_in_use, warnings=d.load_warnings)
                       for d in runtime.detectors],
        warnings=[warning for _, warning in loaded],
        warning_codes=[code for code, _ in loaded],
        manifest=detector.manifest,
    )
