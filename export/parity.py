"""ONNX Runtime vs PyTorch on the same inputs, with the issue's tolerances.

Depth: max relative error ≤ 1e-3 (outputs are ≥ min_depth > 0, so relative is
well defined). Scores: max absolute error ≤ 1e-4 (they are probabilities).
Regression: max absolute error ≤ 1e-3 · max(1, max |reference|), so the check
scales with the map instead of failing on a trained net's larger values.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from export.inputs import NetworkInputs
from models.depth_net import DepthCompletionNet
from models.pixor import Pixor
from pipeline.graph_inputs import feeds_for

DEPTH_MAX_RELATIVE = 1e-3
SCORE_MAX_ABSOLUTE = 1e-4
REGRESSION_RELATIVE_TO_SCALE = 1e-3


class ParityError(RuntimeError):
    """ONNX Runtime disagrees with PyTorch beyond tolerance."""


@dataclass
class ParityResult:
    """Errors of one comparison (ONNX Runtime against PyTorch eager, same weights and inputs)."""

    network: str
    source: str
    metric: str
    error: float
    tolerance: float
    extra: dict[str, float]

    @property
    def passed(self) -> bool:
        return bool(self.error <= self.tolerance)

    def to_dict(self) -> dict:
        return {**asdict(self), "passed": self.passed}


def cpu_session(path: str | Path) -> ort.InferenceSession:
    """An ONNX Runtime CPU session with full graph optimisation."""
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def depth_parity(model: DepthCompletionNet, session: ort.InferenceSession, inputs: NetworkInputs) -> ParityResult:
    """Compare depth.onnx with the PyTorch depth net (eval mode) on ``inputs``."""
    model.eval()
    with torch.no_grad():
        reference = model(torch.from_numpy(inputs.rgb), torch.from_numpy(inputs.sparse_depth)).numpy()
    (onnx_out,) = session.run(["depth"], {"rgb": inputs.rgb, "sparse_depth": inputs.sparse_depth})
    relative = np.abs(onnx_out - reference) / np.maximum(np.abs(reference), 1e-6)
    return ParityResult(
        network="depth",
        source=inputs.source,
        metric="max relative error",
        error=float(relative.max()),
        tolerance=DEPTH_MAX_RELATIVE,
        extra={"max_abs_error_m": float(np.abs(onnx_out - reference).max()), "min_depth_m": float(onnx_out.min())},
    )


def pixor_parity(model: Pixor, session: ort.InferenceSession, inputs: NetworkInputs) -> list[ParityResult]:
    """Compare pixor.onnx with PyTorch PIXOR on ``inputs``: scores and regression."""
    model.eval()
    with torch.no_grad():
        score_ref, reg_ref = (t.numpy() for t in model(torch.from_numpy(inputs.bev)))
    score, reg = session.run(["score", "regression"], feeds_for(session, {"bev": inputs.bev}))
    reg_scale = max(1.0, float(np.abs(reg_ref).max()))
    return [
        ParityResult(
            network="pixor",
            source=inputs.source,
            metric="score max absolute error",
            error=float(np.abs(score - score_ref).max()),
            tolerance=SCORE_MAX_ABSOLUTE,
            extra={"max_score": float(score_ref.max())},
        ),
        ParityResult(
            network="pixor",
            source=inputs.source,
            metric="regression max absolute error",
            error=float(np.abs(reg - reg_ref).max()),
            tolerance=REGRESSION_RELATIVE_TO_SCALE * reg_scale,
            extra={"max_abs_regression": float(np.abs(reg_ref).max())},
        ),
    ]


def require_parity(results: list[ParityResult]) -> None:
    """Raise ParityError listing every comparison past tolerance."""
    failures = [r for r in results if not r.passed]
    if failures:
        lines = [f"{r.network} on {r.source}: {r.metric} {r.error:.3g} > {r.tolerance:.3g}" for r in failures]
        raise ParityError("ONNX Runtime disagrees with PyTorch:\n  " + "\n  ".join(lines))
