"""Writing a model directory safely: never over something that is not one, never left half-written.

The commands that write a model directory from another (``python -m export.lower``,
``python -m export.precision``) replace their ``--out`` as a whole. So they refuse an
``--out`` that holds anything but a model directory (an empty folder is fine), and they
write into a staging copy beside it that is swapped in only when everything is written:
a failure on the way (a calibration error, a full disk) leaves the source and any earlier
``--out`` as they were.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from pipeline.model_files import MANIFEST_NAME, ModelFileError


def check_destination(out: Path) -> None:
    """Refuse an ``--out`` that exists and is neither a model directory nor an empty folder."""
    out = Path(out)
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / MANIFEST_NAME).exists())):
        raise ModelFileError(f"--out {out}: exists and is not a model directory; give a new or empty folder")


@contextmanager
def staged_copy(source: Path, out: Path) -> Iterator[Path]:
    """A copy of the model directory ``source`` to write into; it becomes ``out`` when the block ends
    without an error, and is removed when it raises (``out`` may be ``source`` itself)."""
    source, out = Path(source), Path(out)
    staging = out.parent / f".{out.name}.staging"
    if staging.exists():  # left by a run that was killed
        shutil.rmtree(staging)
    out.parent.mkdir(parents=True, exist_ok=True)
    shutil.copytree(source, staging)
    try:
        yield staging
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    if out.exists():
        previous = out.parent / f".{out.name}.previous"
        if previous.exists():
            shutil.rmtree(previous)
        out.rename(previous)
        staging.rename(out)
        shutil.rmtree(previous)
    else:
        staging.rename(out)
