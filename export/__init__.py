"""torch → ONNX export of the networks (the depth net, PIXOR or both), the parity check and the model-directory manifest.

``from export import run`` gives the command's entry point; it imports torch
lazily so that torch-free modules of this package (``export.flops``,
``export.manifest``, ``export.inputs``) stay usable from the runtime.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from export.exporter import ExportConfig, ExportResult


def run(config: ExportConfig) -> ExportResult:
    """Export a preset into a model directory (see :func:`export.exporter.run`)."""
    from export.exporter import run as _run

    return _run(config)
