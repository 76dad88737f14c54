"""Feeding a network whose graph input is split into channel ranges.

A lowered PIXOR graph (export/rewrite.py, 8) reads its BEV tensor as two graph
inputs named ``bev[0:32]`` and ``bev[32:37]`` instead of one ``bev`` that the graph
slices: channels lo…hi of a C-contiguous (1, C, H, W) array are themselves a
C-contiguous block, so the pieces are views of the voxelizer's one buffer and
ONNX Runtime reads them without the copy its Split made (1.4 ms of an edge frame).

Callers keep working with whole tensors by name: :func:`session_feeds` maps them
onto whatever inputs a session has.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from itertools import pairwise
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # the annotation only: this module works on names and arrays, and need not load ONNX Runtime
    import onnxruntime as ort

_PIECE = re.compile(r"^(?P<base>.+)\[(?P<lo>\d+):(?P<hi>\d+)\]$")


def channel_piece(name: str) -> tuple[str, int, int] | None:
    """``(base, lo, hi)`` of an input named ``base[lo:hi]`` (channels lo…hi−1 of ``base``), else None."""
    match = _PIECE.match(name)
    if match is None:
        return None
    return match["base"], int(match["lo"]), int(match["hi"])


def piece_name(base: str, lo: int, hi: int) -> str:
    """The graph input name of channels lo…hi−1 of ``base``."""
    return f"{base}[{lo}:{hi}]"


def session_feeds(input_names: Iterable[str], arrays: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The feeds of a session with these inputs from whole (1, C, …) tensors named by their base names.

    An input named like a whole tensor gets it; one named ``base[lo:hi]`` gets ``arrays[base][:, lo:hi]``,
    a view (contiguous when the whole tensor is). KeyError names an input no array provides.
    """
    feeds = {}
    for name in input_names:
        if name in arrays:
            feeds[name] = arrays[name]
            continue
        piece = channel_piece(name)
        if piece is None or piece[0] not in arrays:
            raise KeyError(f"no array for the network input '{name}' (given: {', '.join(arrays)})")
        base, lo, hi = piece
        feeds[name] = arrays[base][:, lo:hi]
    return feeds


def tiles(ranges: list[tuple[int, int]]) -> bool:
    """Channel ranges (lo, hi), sorted, that cover 0…hi of the last once each, none empty."""
    return (bool(ranges) and ranges[0][0] == 0 and all(lo < hi for lo, hi in ranges)
            and all(a[1] == b[0] for a, b in pairwise(ranges)))


def whole_inputs(input_names: Iterable[str]) -> dict[str, list[tuple[int, int]]]:
    """Each whole tensor a session reads in pieces, with its pieces' channel ranges in order."""
    pieces: dict[str, list[tuple[int, int]]] = {}
    for name in input_names:
        piece = channel_piece(name)
        if piece is not None:
            pieces.setdefault(piece[0], []).append(piece[1:])
    return {base: sorted(ranges) for base, ranges in pieces.items()}


def feeds_for(session: ort.InferenceSession, arrays: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """:func:`session_feeds` for an ONNX Runtime session (its inputs as the graph names them)."""
    return session_feeds([graph_input.name for graph_input in session.get_inputs()], arrays)


def whole_shapes(shapes: Mapping[str, tuple[int, ...]]) -> dict[str, tuple[int, ...]]:
    """Input shapes with the pieces of each whole tensor joined back into its (N, C, …) shape.

    ValueError when a tensor's pieces do not cover channels 0…C−1 once each, in order, or disagree on
    the other dimensions.
    """
    joined = {name: tuple(shape) for name, shape in shapes.items() if channel_piece(name) is None}
    for base, ranges in whole_inputs(shapes).items():
        if not tiles(ranges):
            raise ValueError(f"the inputs {', '.join(piece_name(base, lo, hi) for lo, hi in ranges)} do not cover "
                             f"the channels of '{base}' once each")
        pieces = [tuple(shapes[piece_name(base, lo, hi)]) for lo, hi in ranges]
        if any(len(p) < 2 or p[1] != hi - lo or p[:1] + p[2:] != pieces[0][:1] + pieces[0][2:]
               for p, (lo, hi) in zip(pieces, ranges)):
            raise ValueError(f"the inputs of '{base}' in channel pieces have shapes {pieces} that do not match their channel ranges or each other")
        joined[base] = (pieces[0][0], ranges[-1][1], *pieces[0][2:])
    return joined
