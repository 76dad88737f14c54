"""Model directories: where the shipped one is (``DEFAULT_MODELS``), reading ``manifest.json`` and checking
each file's sha256, and what identifies a loaded model (:class:`ModelIdentity`).

Imports only the standard library so the runtime (and the service container,
which has no torch) can refuse a corrupted or swapped model file before ONNX
Runtime ever parses it.

The manifest's ``format`` is ``lowres3d-models/N``. A runtime reads every version
from :data:`OLDEST_FORMAT_VERSION` to :data:`FORMAT_VERSION` and refuses a newer one
with one line naming both. Fields a runtime does not know are ignored: an exporter
adds fields without a new version, and raises the version only when a runtime that
ignored what it adds would run the model differently (a new preset field, a new
input, a new meaning of an old field).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import stat
from dataclasses import dataclass
from pathlib import Path

MANIFEST_NAME = "manifest.json"
FORMAT_NAME = "lowres3d-models"
FORMAT_VERSION = 1  # what python -m export writes and the newest this runtime reads
OLDEST_FORMAT_VERSION = 1  # every manifest ever exported says lowres3d-models/1
FORMAT = f"{FORMAT_NAME}/{FORMAT_VERSION}"
PRECISIONS = ("fp32", "fp16", "int8")
# The shipped detector, in the source tree: `pip install .` (not -e) leaves weights/ behind.
DEFAULT_MODELS = Path(__file__).resolve().parents[1] / "weights" / "edge"


def default_models_hint(models: Path) -> str | None:
    """What to do when the default model directory is missing (an install outside the source tree)."""
    if Path(models) != DEFAULT_MODELS or DEFAULT_MODELS.is_dir():
        return None
    return (f"the default --models {DEFAULT_MODELS} exists only in a source checkout (make setup, or pip install "
            "-e .); give the model directory with --models")


_CHUNK = 1 << 20
# What a model directory's files may weigh. The shipped manifests are 8–25 KB and 9–13 levels deep: the bounds are
# hundreds of times that, and keep a manifest.json that is /dev/zero, a gigabyte of JSON or 100,000 nested brackets
# (Python's parser: RecursionError) to one line instead of all the memory or a traceback.
MAX_MANIFEST_BYTES = 8 << 20
MAX_MANIFEST_DEPTH = 64
# An ONNX file holds its weights inside it (the exporter writes no external data), and protobuf caps a message at
# 2 GiB: a bigger file is no model this runtime loads.
MAX_MODEL_FILE_BYTES = 2 << 30


class ModelFileError(RuntimeError):
    """A model directory is missing a file, has a malformed manifest, or a file's checksum differs."""


def _reason(exc: OSError) -> str:
    """The operating system's words for an OSError ("Permission denied"), without its errno and path."""
    return exc.strerror or str(exc)


def _kind(mode: int) -> str:
    """What a file that is not a regular one is, in words."""
    for test, kind in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a named pipe"), (stat.S_ISCHR, "a device"),
                       (stat.S_ISBLK, "a device"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return kind
    return "not a regular file"


def _open_regular(path: str | Path, what: str) -> int:
    """A read-only descriptor of the regular file at ``path`` (symbolic links followed). Opened without blocking,
    then checked on the descriptor itself: a named pipe in a file's place would otherwise hang the open, and a link
    to /dev/zero the read, for ever; checking the name first would leave a moment to swap the file."""
    try:
        descriptor = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:  # no permission, a name too long; a missing file is the caller's to say first
        raise ModelFileError(f"{path}: cannot read the {what} ({_reason(exc)})") from exc
    mode = os.fstat(descriptor).st_mode
    if not stat.S_ISREG(mode):
        os.close(descriptor)
        raise ModelFileError(f"{path}: {_kind(mode)}, where the model directory needs the {what} as a regular file")
    return descriptor


def _read_bounded(path: str | Path, what: str, limit: int) -> bytes:
    """The whole regular file at ``path``; ModelFileError when it is not one, cannot be read, or holds more than
    ``limit`` bytes (counted as read: /proc files report a size of 0)."""
    descriptor = _open_regular(path, what)
    try:
        with os.fdopen(descriptor, "rb") as handle:
            size = os.fstat(handle.fileno()).st_size
            # The size it states and one byte more (to see it grew), then on in chunks: read(limit + 1) asks for
            # a buffer of the whole limit up front (2 GiB for a model file), a MemoryError under a memory limit.
            data = handle.read(size + 1) if size <= limit else b""
            if len(data) > size:  # grown since, or a /proc file stating 0: on in chunks, to a byte past the limit
                grown = bytearray(data)
                while len(grown) <= limit and (chunk := handle.read(min(_CHUNK, limit + 1 - len(grown)))):
                    grown += chunk
                data = bytes(grown)
    except OSError as exc:  # a failing disk, /proc/self/mem
        raise ModelFileError(f"{path}: cannot read the {what} ({_reason(exc)})") from exc
    if size > limit or len(data) > limit:
        raise ModelFileError(f"{path}: more than {limit >> 20} MiB, far more than any {what} this lowres3d reads")
    return data


def sha256_file(path: str | Path) -> str:
    """Hex sha256 of a regular file, read in 1 MiB chunks; ModelFileError naming the file when it cannot be read
    or is no regular file (a named pipe, /dev/zero)."""
    digest = hashlib.sha256()
    descriptor = _open_regular(path, "model file")
    try:
        with os.fdopen(descriptor, "rb") as handle:
            for chunk in iter(lambda: handle.read(_CHUNK), b""):
                digest.update(chunk)
    except OSError as exc:  # no permission, a failing disk
        raise ModelFileError(f"{path}: cannot read the model file ({_reason(exc)})") from exc
    return digest.hexdigest()


def _nesting(value: object) -> int:
    """How deeply lists and tables nest in a parsed JSON value (1: a scalar), counted without recursion."""
    deepest, stack = 0, [(value, 1)]
    while stack:
        item, depth = stack.pop()
        deepest = max(deepest, depth)
        if isinstance(item, dict):
            stack.extend((child, depth + 1) for child in item.values())
        elif isinstance(item, list):
            stack.extend((child, depth + 1) for child in item)
    return deepest


def load_manifest(directory: str | Path) -> dict:
    """Parse ``directory/manifest.json``; ModelFileError if it is missing or not a manifest."""
    return load_manifest_with_digest(directory)[0]


def load_manifest_with_digest(directory: str | Path) -> tuple[dict, str]:
    """:func:`load_manifest` and the hex sha256 of the very bytes it parsed (the model's id: no second read
    that a copy in progress could change between)."""
    path = Path(directory) / MANIFEST_NAME
    try:
        # is_dir() and exists() raise for some errors too: no permission on a parent folder, a name too long.
        if not Path(directory).is_dir():  # a mistyped path, rather than a model directory that lost its manifest
            what = "a file, not a model directory" if Path(directory).exists() else "no such model directory"
            raise ModelFileError(f"{directory}: {what} (one holds manifest.json and its ONNX files)")
    except OSError as exc:
        raise ModelFileError(f"{directory}: cannot open the model directory ({_reason(exc)})") from exc
    try:
        exists = path.exists() or path.is_symlink()
    except OSError as exc:
        raise ModelFileError(f"{path}: unreadable manifest ({_reason(exc)})") from exc
    if not exists:
        inside = sorted(p.parent.name for p in Path(directory).glob(f"*/{MANIFEST_NAME}"))
        if inside:  # the folder above the model directories (weights/ for weights/edge)
            raise ModelFileError(f"{path}: no manifest; the model directories in {directory}: {', '.join(inside)}: "
                                 "give one of them")
        raise ModelFileError(f"{path}: no manifest; export the models with `python -m export`")
    data = _read_bounded(path, "manifest", MAX_MANIFEST_BYTES)  # a regular file of a manifest's size, or one line
    try:
        manifest = json.loads(data.decode("utf-8"))
    except RecursionError:  # Python's parser recurses once per bracket
        raise ModelFileError(f"{path}: unreadable manifest (lists and tables nested too deep to parse)") from None
    except ValueError as exc:  # bad JSON or UTF-8, and an integer of more than 4,300 digits
        raise ModelFileError(f"{path}: unreadable manifest ({exc})") from exc
    if _nesting(manifest) > MAX_MANIFEST_DEPTH:  # a later comparison or copy of it would recurse as deep
        raise ModelFileError(f"{path}: unreadable manifest (lists and tables nested more than {MAX_MANIFEST_DEPTH} "
                             "deep)")
    if not isinstance(manifest, dict):
        raise ModelFileError(f"{path}: manifest has no 'files' table with sha256 checksums")
    manifest_format(manifest, path)  # first: a newer format's tables may differ from those checked below
    if not isinstance(manifest.get("files"), dict) or not manifest["files"]:
        raise ModelFileError(f"{path}: manifest has no 'files' table with sha256 checksums")
    _check_tables(manifest, path)
    return manifest, hashlib.sha256(data).hexdigest()


def manifest_format(manifest: dict, path: Path | str = MANIFEST_NAME) -> int:
    """The manifest's format version; ModelFileError for a format this runtime cannot read.

    A manifest without ``format`` (none was ever exported so: a hand-made one) is read as version 1."""
    given = manifest.get("format", f"{FORMAT_NAME}/1")
    match = re.fullmatch(rf"{re.escape(FORMAT_NAME)}/([0-9]+)", given) if isinstance(given, str) else None
    if match is None:
        raise ModelFileError(f"{path}: format {given!r:.60} is not a lowres3d model manifest (expected {FORMAT})")
    version = int(match.group(1))
    if version > FORMAT_VERSION:
        raise ModelFileError(
            f"{path}: format {FORMAT_NAME}/{version} is newer than this lowres3d reads ({FORMAT}); update lowres3d "
            "on this machine, or export the models with the version it runs")
    if version < OLDEST_FORMAT_VERSION:
        raise ModelFileError(f"{path}: format {FORMAT_NAME}/{version} is older than this lowres3d reads "
                             f"({FORMAT_NAME}/{OLDEST_FORMAT_VERSION} to {FORMAT}); export the models again")
    return version


def _check_tables(manifest: dict, path: Path) -> None:
    """The manifest's tables that the runtime reads have the types it reads them as (a hand-edited or
    truncated manifest gets one line naming the field, not a traceback later)."""
    for name, entry in manifest["files"].items():
        if not isinstance(entry, dict) or not isinstance(entry.get("sha256"), str):
            raise ModelFileError(f"{path}: files.{name}: expected {{\"sha256\": \"<hex>\"}}, got {entry!r:.60}")
        if Path(name).name != name or name in ("", ".", ".."):  # a path would check a file outside the directory
            raise ModelFileError(f"{path}: files.{name}: a file name in the model directory, not a path")
    networks = manifest.get("networks")
    if networks is None:  # every reader walks this table: a missing one is named here, not as a KeyError
        raise ModelFileError(f"{path}: manifest has no 'networks' table")
    if not isinstance(networks, dict):
        raise ModelFileError(f"{path}: networks: expected a table of networks, got {networks!r:.60}")
    for name, entry in networks.items():
        if not isinstance(entry, dict) or not isinstance(entry.get("file"), str):
            raise ModelFileError(f"{path}: networks.{name}: expected a table with its \"file\", got {entry!r:.60}")
        training = entry.get("training") or {}
        if not isinstance(training, dict):
            raise ModelFileError(f"{path}: networks.{name}.training: expected a table, got {entry['training']!r:.60}")
        _check_training_record(training, f"{path}: networks.{name}.training")
        if entry["file"] not in manifest["files"]:  # it would be loaded without its sha256 checked
            raise ModelFileError(f"{path}: networks.{name}.file: {entry['file']!r:.60} has no sha256 in 'files'")
    if not isinstance(manifest.get("preset_config"), dict):
        raise ModelFileError(f"{path}: preset_config: missing or not a table")
    precision = manifest.get("precision", "fp32")
    if precision not in PRECISIONS:
        raise ModelFileError(f"{path}: precision: {precision!r:.60} is none of {', '.join(PRECISIONS)}")


def check_descriptions(manifest: dict, described: dict[str, dict], path: Path) -> None:
    """The manifest's descriptive tables (``bev_grid``, and ``normalisation``'s constants of the stages around the
    networks) say what its ``preset_config`` gives (``described``: :meth:`pipeline.presets.Preset.described`).

    This runtime runs ``preset_config``; another runtime may read the descriptions. A hand edit of one of them
    changed nothing here while a port would run the edited value, so the two are refused when they differ.
    A field the manifest leaves out is not compared (a hand-made manifest may describe less)."""
    for table, record in described.items():
        given = manifest.get(table)
        if given is None:
            continue
        if not isinstance(given, dict):
            raise ModelFileError(f"{path}: {table}: expected a table, got {given!r:.60}")
        for key, value in record.items():
            if key in given and given[key] != value:
                raise ModelFileError(
                    f"{path}: {table}.{key} is {given[key]!r:.60} where preset_config gives {value!r}: this runtime "
                    f"runs preset_config, which {table} only describes (for other runtimes), and the graphs were "
                    "exported for it: export the models again with the preset wanted (python -m export) rather "
                    "than edit the manifest")


def _check_training_record(training: dict, where: str) -> None:
    """The training record's fields the runtime reads (the scan lines a PIXOR learned from): ``input`` a name and
    ``emulate_beams`` a whole line count, each when recorded. A list there made the Detector fail with a
    TypeError traceback."""
    given = training.get("input")
    if given is not None and not isinstance(given, str):
        raise ModelFileError(f"{where}.input: expected the name of the input (such as \"pseudo\"), got {given!r:.60}")
    emulated = training.get("emulate_beams")
    if emulated is not None and (isinstance(emulated, bool) or not isinstance(emulated, int)):
        raise ModelFileError(f"{where}.emulate_beams: expected a whole number of lines (0: as stored), got "
                             f"{emulated!r:.60}")


def verify_sha256(directory: str | Path, manifest: dict) -> None:
    """Check every file listed in ``manifest["files"]`` against its sha256.

    Raises ModelFileError naming the first missing, unreadable or mismatching file.
    """
    directory = Path(directory)
    for name, entry in manifest["files"].items():
        path = _listed_file(directory, name, entry)
        _check_digest(path, entry, sha256_file(path))


def read_verified(directory: str | Path, manifest: dict, name: str, check: bool = True) -> bytes:
    """The bytes of the listed file ``name``, read once and (``check``) checked against its sha256: what ONNX
    Runtime is then given, so that no file replaced between the check and the load (nor a path read twice) is run.

    Raises ModelFileError as :func:`verify_sha256` does, and for a file over :data:`MAX_MODEL_FILE_BYTES`."""
    entry = manifest["files"][name]
    path = _listed_file(Path(directory), name, entry)
    data = _read_bounded(path, "model file", MAX_MODEL_FILE_BYTES)
    if check:
        _check_digest(path, entry, hashlib.sha256(data).hexdigest(), len(data))
    return data


def _listed_file(directory: Path, name: str, entry: object) -> Path:
    """The path of the manifest's file ``name``; ModelFileError when it has no sha256 or is not a file."""
    path = directory / name
    if not isinstance(entry, dict) or not entry.get("sha256"):
        raise ModelFileError(f"{directory / MANIFEST_NAME}: no sha256 for {name}")
    try:
        is_dir, exists = path.is_dir(), path.exists()
    except OSError as exc:  # no permission on the directory, a name too long
        raise ModelFileError(f"{path}: cannot open the model file ({_reason(exc)})") from exc
    if is_dir:
        raise ModelFileError(f"{path}: a directory, where the manifest lists a model file")
    if not exists:
        raise ModelFileError(f"{path}: model file listed in the manifest is missing")
    return path  # a named pipe or a device in its place: the read says so (_open_regular)


def _check_digest(path: Path, entry: dict, actual: str, size: int | None = None) -> None:
    """ModelFileError when ``actual`` is not the sha256 ``entry`` lists, saying a cut-off copy as such."""
    expected = entry["sha256"]
    if actual == expected:
        return
    listed = entry.get("bytes")
    if size is None:
        try:
            size = path.stat().st_size
        except OSError:  # removed since it was read: the mismatch is what there is to say
            size, listed = None, None
    if isinstance(listed, int) and size != listed:  # a cut-off copy: the likeliest cause, said as such
        raise ModelFileError(f"{path}: sha256 mismatch: {size} bytes, where the manifest lists {listed} (a copy cut "
                             "off or still in progress, or another model's file); copy the whole model directory "
                             "again")
    raise ModelFileError(
        f"{path}: sha256 mismatch (manifest {expected[:12]}…, file {actual[:12]}…): "
        "the file is corrupted or was replaced; re-export the model directory"
    )


@dataclass(frozen=True)
class ModelIdentity:
    """Which model a process runs, as a fleet tells its vehicles apart: the manifest's sha256 (``id``: it lists
    every file's sha256 and the preset, so equal ids are equal models), the directory it was loaded from, and the
    manifest's fields an operator reads at a glance."""

    id: str  # hex sha256 of manifest.json's bytes
    directory: str  # the model directory's own name, after symbolic links (a "current" link names its target)
    path: str  # its absolute path, after symbolic links
    format: int
    preset: str
    precision: str  # fp32, fp16 or int8
    weights: str  # "trained", "initialised (untrained)" or which network is trained
    sha256: dict[str, str]  # each file's, by name
    training_data: dict[str, str | None]  # each network's training data as its training record names it (None: unrecorded)

    @property
    def short_id(self) -> str:
        """The id's first 12 hex digits, for log lines."""
        return self.id[:12]

    def summary(self) -> str:
        """One line for a log: directory, id, preset, precision, files."""
        files = ", ".join(f"{name} {digest[:12]}" for name, digest in self.sha256.items())
        return (f"model {self.directory} (id {self.short_id}, manifest {FORMAT_NAME}/{self.format}, preset "
                f"{self.preset}, {self.precision}, {self.weights}; {files})")


def model_identity(directory: str | Path, manifest: dict, manifest_sha256: str) -> ModelIdentity:
    """The identity of the model ``manifest`` (checked by :func:`load_manifest`) describes in ``directory``."""
    resolved = Path(directory).resolve()
    training = {name: (entry.get("training") or {}).get("data") for name, entry in manifest["networks"].items()}
    return ModelIdentity(
        id=manifest_sha256, directory=resolved.name, path=str(resolved), format=manifest_format(manifest),
        preset=str(manifest["preset_config"].get("name", manifest.get("preset"))),  # the preset that runs
        precision=manifest.get("precision", "fp32"), weights=str(manifest.get("weights", "unrecorded")),
        sha256={name: entry["sha256"] for name, entry in manifest["files"].items()},
        training_data={name: str(data) if data is not None else None for name, data in training.items()},
    )
