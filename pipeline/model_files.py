"""Model directories: where the shipped one is (``DEFAULT_MODELS``), reading ``manifest.json`` and checking
each file's sha256.

Imports only json, hashlib and pathlib so the runtime (and the service
container, which has no torch) can refuse a corrupted or swapped model file
before ONNX Runtime ever parses it.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

MANIFEST_NAME = "manifest.json"
# The shipped detector, in the source tree: `pip install .` (not -e) leaves weights/ behind.
DEFAULT_MODELS = Path(__file__).resolve().parents[1] / "weights" / "edge"


def default_models_hint(models: Path) -> str | None:
    """What to do when the default model directory is missing (an install outside the source tree)."""
    if Path(models) != DEFAULT_MODELS or DEFAULT_MODELS.is_dir():
        return None
    return (f"the default --models {DEFAULT_MODELS} exists only in a source checkout (make setup, or pip install "
            "-e .); give the model directory with --models")


_CHUNK = 1 << 20


class ModelFileError(RuntimeError):
    """A model directory is missing a file, has a malformed manifest, or a file's checksum differs."""


def _reason(exc: OSError) -> str:
    """The operating system's words for an OSError ("Permission denied"), without its errno and path."""
    return exc.strerror or str(exc)


def sha256_file(path: str | Path) -> str:
    """Hex sha256 of a file, read in 1 MiB chunks; ModelFileError naming the file when it cannot be read."""
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as handle:
            for chunk in iter(lambda: handle.read(_CHUNK), b""):
                digest.update(chunk)
    except OSError as exc:  # no permission, a directory in its place, a failing disk
        raise ModelFileError(f"{path}: cannot read the model file ({_reason(exc)})") from exc
    return digest.hexdigest()


def load_manifest(directory: str | Path) -> dict:
    """Parse ``directory/manifest.json``; ModelFileError if it is missing or not a manifest."""
    path = Path(directory) / MANIFEST_NAME
    try:
        # is_dir() and exists() raise for some errors too: no permission on a parent folder, a name too long.
        if not Path(directory).is_dir():  # a mistyped path, rather than a model directory that lost its manifest
            what = "a file, not a model directory" if Path(directory).exists() else "no such model directory"
            raise ModelFileError(f"{directory}: {what} (one holds manifest.json and its ONNX files)")
    except OSError as exc:
        raise ModelFileError(f"{directory}: cannot open the model directory ({_reason(exc)})") from exc
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ModelFileError(f"{path}: no manifest; export the models with `python -m export`") from None
    except OSError as exc:
        raise ModelFileError(f"{path}: unreadable manifest ({_reason(exc)})") from exc
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ModelFileError(f"{path}: unreadable manifest ({exc})") from exc
    if not isinstance(manifest, dict) or not isinstance(manifest.get("files"), dict) or not manifest["files"]:
        raise ModelFileError(f"{path}: manifest has no 'files' table with sha256 checksums")
    _check_tables(manifest, path)
    return manifest


def _check_tables(manifest: dict, path: Path) -> None:
    """The manifest's tables that the runtime reads have the types it reads them as (a hand-edited or
    truncated manifest gets one line naming the field, not a traceback later)."""
    for name, entry in manifest["files"].items():
        if not isinstance(entry, dict) or not isinstance(entry.get("sha256"), str):
            raise ModelFileError(f"{path}: files.{name}: expected {{\"sha256\": \"<hex>\"}}, got {entry!r:.60}")
    networks = manifest.get("networks", {})
    if not isinstance(networks, dict):
        raise ModelFileError(f"{path}: networks: expected a table of networks, got {networks!r:.60}")
    for name, entry in networks.items():
        if not isinstance(entry, dict) or not isinstance(entry.get("file"), str):
            raise ModelFileError(f"{path}: networks.{name}: expected a table with its \"file\", got {entry!r:.60}")
        if not isinstance(entry.get("training") or {}, dict):
            raise ModelFileError(f"{path}: networks.{name}.training: expected a table, got {entry['training']!r:.60}")
    if not isinstance(manifest.get("preset_config"), dict):
        raise ModelFileError(f"{path}: preset_config: missing or not a table")


def verify_sha256(directory: str | Path, manifest: dict) -> None:
    """Check every file listed in ``manifest["files"]`` against its sha256.

    Raises ModelFileError naming the first missing, unreadable or mismatching file.
    """
    directory = Path(directory)
    for name, entry in manifest["files"].items():
        path = directory / name
        expected = entry.get("sha256") if isinstance(entry, dict) else None
        if not expected:
            raise ModelFileError(f"{directory / MANIFEST_NAME}: no sha256 for {name}")
        try:
            is_dir, is_file = path.is_dir(), path.is_file()
        except OSError as exc:  # no permission on the directory, a name too long
            raise ModelFileError(f"{path}: cannot open the model file ({_reason(exc)})") from exc
        if is_dir:
            raise ModelFileError(f"{path}: a directory, where the manifest lists a model file")
        if not is_file:
            raise ModelFileError(f"{path}: model file listed in the manifest is missing")
        actual = sha256_file(path)
        if actual != expected:
            raise ModelFileError(
                f"{path}: sha256 mismatch (manifest {expected[:12]}…, file {actual[:12]}…): "
                "the file is corrupted or was replaced; re-export the model directory"
            )
