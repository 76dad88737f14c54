"""Writing a model directory safely: never over something that is not one, never left half-written.

The commands that write a model directory (``python -m export``, ``export.lower``,
``export.precision``) replace their ``--out`` as a whole. So they refuse an ``--out`` that
holds anything but a model directory (an empty folder is fine) or a model directory of
another preset or precision (a typo in ``--out``, not a wish to lose that model), and they write into a
staging folder beside it that is swapped in only when everything is written and checked:
a failure on the way (a parity check, a calibration error, a full disk) leaves the source
and any earlier ``--out`` as they were.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from pipeline.cli import check_output
from pipeline.model_files import MANIFEST_NAME, ModelFileError, load_manifest


def check_destination(out: Path, preset: str | None = None, precision: str | None = None) -> None:
    """Refuse an ``--out`` that exists and is neither a model directory nor an empty folder, or that cannot
    be made (a file above it, no permission): before any work, not when the staging folder is made.

    preset, precision: what will be written; a model directory of another preset or precision is refused
    too (replacing one with a new export of the same model is what ``--out`` over a model directory is for).
    """
    out = Path(out)
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / MANIFEST_NAME).exists())):
        raise ModelFileError(f"--out {out}: exists and is not a model directory; give a new or empty folder")
    if (out / MANIFEST_NAME).exists():
        held = load_manifest(out)
        held_preset, held_precision = held.get("preset"), held.get("precision", "fp32")
        if (preset is not None and held_preset != preset) or (precision is not None and held_precision != precision):
            raise ModelFileError(
                f"--out {out}: holds a model of preset {held_preset} ({held_precision}); this writes preset "
                f"{preset or held_preset} ({precision or held_precision}): give a new folder, or remove {out} "
                "first to replace that model")
    check_output(out, "--out", directory=True)


@contextmanager
def staged(out: Path, source: Path | None = None) -> Iterator[Path]:
    """A folder to write the model directory ``out`` in: a copy of the model directory ``source``, or empty.

    It becomes ``out`` when the block ends without an error (``out`` may be ``source`` itself) and is
    removed when the block raises. Into another folder only the model's own files are copied (its manifest
    and the files it lists), not what else lies in ``source``, such as a TensorRT engine cache built for the
    source's graphs; rewriting ``source`` in place keeps everything. An ``out`` inside ``source`` is refused.
    """
    target = Path(out).resolve()
    in_place = source is not None and target == Path(source).resolve()
    if source is not None and not in_place and target.is_relative_to(Path(source).resolve()):
        raise ModelFileError(f"--out {out}: lies inside the model directory {source}, whose copies would then "
                             "carry it along; give a folder outside it")
    staging = target.parent / f".{target.name}.staging"
    if staging.exists():  # left by a run that was killed
        shutil.rmtree(staging)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        staging.mkdir()
    except OSError as exc:  # what check_destination cannot foresee (a read-only mount): one line, no traceback
        raise ModelFileError(f"--out {out}: cannot write there ({exc.strerror or exc})") from exc
    try:
        if in_place:
            staging.rmdir()
            shutil.copytree(source, staging)
        elif source is not None:
            for name in (MANIFEST_NAME, *load_manifest(source)["files"]):
                shutil.copy2(Path(source) / name, staging / name)
        yield staging
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    if target.exists():
        previous = target.parent / f".{target.name}.previous"
        if previous.exists():
            shutil.rmtree(previous)
        target.rename(previous)
        staging.rename(target)
        shutil.rmtree(previous)
    else:
        staging.rename(target)
