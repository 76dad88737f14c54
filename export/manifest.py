"""The model directory's ``manifest.json``: what the runtime needs to run the ONNX files the same way.

No torch here: versions come from package metadata, and verification is
delegated to :mod:`pipeline.model_files` (the runtime's own verifier).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from importlib import metadata
from pathlib import Path

import onnx

from export.port_spec import port_spec
from export.rewrite import value_shape

# FORMAT ("lowres3d-models/N") is the runtime's (pipeline/model_files.py): the version written is the newest the
# runtime of the same release reads. Raise it there when a field added here changes how the models must run.
from pipeline.model_files import FORMAT, MANIFEST_NAME, load_manifest, sha256_file, verify_sha256
from pipeline.presets import Preset
from pipeline.provenance import code_version

UNTRAINED = "initialised (untrained)"


@dataclass(frozen=True)
class TensorSpec:
    """A named ONNX input or output with its static shape."""

    name: str
    shape: tuple[int, ...]
    dtype: str = "float32"
    description: str = ""


@dataclass
class NetworkEntry:
    """One ONNX network of the directory."""

    file: str
    inputs: list[TensorSpec]
    outputs: list[TensorSpec]
    parameters: int
    flops: int  # 2 · MACs of Conv/ConvTranspose/MatMul/Gemm, counted from the ONNX graph
    flops_by_op: dict[str, int]
    weights: str  # "trained" or UNTRAINED
    training: dict | None  # checkpoint metadata when trained


def package_versions(names: tuple[str, ...] = ("torch", "onnx", "onnxruntime", "numpy")) -> dict[str, str]:
    """Installed versions of the packages that produced (and will run) the files."""
    versions = {}
    for name in names:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions


def graph_inputs(model: onnx.ModelProto | str | Path) -> list[dict]:
    """An ONNX model's (or file's) own inputs, name and shape, as a runtime other than the Detector must feed them.

    They differ from the network's ``inputs`` where the lowering reads a tensor in channel pieces
    (export/rewrite.py, 8: ``bev[0:32]`` and ``bev[32:37]`` are channels 0–31 and 32–36 of ``bev``).
    """
    if not isinstance(model, onnx.ModelProto):
        model = onnx.load(str(model), load_external_data=False)
    stored = {init.name for init in model.graph.initializer}
    return [{"name": value.name, "shape": value_shape(value)} for value in model.graph.input if value.name not in stored]


def weights_summary(networks: dict[str, NetworkEntry]) -> str:
    """One string for the whole directory: trained, untrained, or which part is trained."""
    states = {name: entry.weights for name, entry in networks.items()}
    if all(s == UNTRAINED for s in states.values()):
        return UNTRAINED
    if all(s == "trained" for s in states.values()):
        return "trained"
    return "partially trained: " + ", ".join(f"{name} {state}" for name, state in states.items())


def build_manifest(
    preset: Preset,
    networks: dict[str, NetworkEntry],
    directory: Path,
    normalisation: dict,
    export_info: dict,
    parity: dict,
) -> dict:
    """The manifest dict; file checksums are computed from the files now in ``directory``."""
    return {
        "format": FORMAT,
        "preset": preset.name,
        "preset_config": preset.to_dict(),
        "weights": weights_summary(networks),
        "networks": {name: {**asdict(entry), "graph_inputs": graph_inputs(directory / entry.file)}
                     for name, entry in networks.items()},
        "bev_grid": preset.described()["bev_grid"],
        "normalisation": normalisation,
        # Every constant and rule of the NumPy stages, for a port to another runtime (docs/models.md, "Porting").
        "port": port_spec(preset),
        "files": {
            entry.file: {"sha256": sha256_file(directory / entry.file), "bytes": (directory / entry.file).stat().st_size}
            for entry in networks.values()
        },
        "versions": package_versions(),
        "code": code_version(),  # the lowres3d code that exported it (git commit in a checkout)
        "export": export_info,
        "parity": parity,
    }


def write_manifest(directory: str | Path, manifest: dict) -> Path:
    """Write ``manifest.json`` (indented, stable key order) into ``directory``."""
    path = Path(directory) / MANIFEST_NAME
    path.write_text(json.dumps(manifest, indent=2) + "\n", encoding="utf-8")
    return path


def verify_model_dir(directory: str | Path) -> dict:
    """Load the manifest and check every file's sha256; returns the manifest.

    Raises :class:`pipeline.model_files.ModelFileError` naming the bad file.
    """
    manifest = load_manifest(directory)
    verify_sha256(directory, manifest)
    return manifest
