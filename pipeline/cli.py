"""Argument types shared by the commands: numbers that must be positive are refused by argparse itself.

A count of 0 is not "the default": ``--epochs 0`` used to fall through to the recipe's 30 epochs.
"""

from __future__ import annotations

import argparse


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
