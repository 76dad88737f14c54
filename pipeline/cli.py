"""Argument types and output checks shared by the commands: numbers that must be positive are refused by
argparse itself, output files that cannot be written before any work.

A count of 0 is not "the default": ``--epochs 0`` used to fall through to the recipe's 30 epochs.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from pipeline.errors import InputError


def positive_int(text: str) -> int:
    """An integer ≥ 1 (argparse type)."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def non_negative_int(text: str) -> int:
    """An integer ≥ 0 (argparse type)."""
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {value}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0 (argparse type)."""
    value = float(text)
    if not (0 < value < float("inf")):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def probability(text: str) -> float:
    """A number in [0, 1] (argparse type), such as a score threshold."""
    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be between 0 and 1, got {text}")
    return value


def unwritable(out: object, exc: OSError) -> str:
    """The one-line error for an output folder the system refused (a file in the way, no permission, full)."""
    where = f"{exc.filename}: " if exc.filename else ""
    return f"error: --out {out}: {where}{exc.strerror or exc}"


def writable_file_flag(flag: str, path: Path | None) -> None:
    """Refuse an output file (``--json``, ``--plot``) that could not be written, before any work is done.

    The file's folder may not exist yet (it is made when the file is written): then its nearest
    existing ancestor must be a writable directory.
    """
    if path is None:
        return
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{flag} {path}: is a directory; give a file name")
    ancestor = path.parent
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise InputError(f"{flag} {path}: {ancestor} is a file, not a directory")
    if not os.access(ancestor, os.W_OK):
        raise InputError(f"{flag} {path}: {ancestor} is not writable")


def write_text_file(path: Path, text: str) -> None:
    """Write an output file checked by :func:`writable_file_flag`, making its folder first."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
