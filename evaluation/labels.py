"""KITTI label lines of one frame as arrays, the form the evaluation works on."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pipeline.kitti import Object3D


@dataclass(frozen=True)
class LabelArrays:
    """The label lines of one frame, one row per object, in file order.

    types: (N,) str, lower-cased (the devkit compares class names case-insensitively).
    truncated: (N,) float64. occluded: (N,) int64.
    bbox: (N, 4) float64 ``left, top, right, bottom`` in pixels.
    dimensions: (N, 3) float64 ``h, w, l`` in metres.
    location: (N, 3) float64 ``x, y, z`` of the bottom centre, rectified camera frame.
    rotation_y: (N,) float64.
    score: (N,) float64; NaN where the line has no score (ground truth).
    """

    types: np.ndarray
    truncated: np.ndarray
    occluded: np.ndarray
    bbox: np.ndarray
    dimensions: np.ndarray
    location: np.ndarray
    rotation_y: np.ndarray
    score: np.ndarray

    def __len__(self) -> int:
        return int(self.types.shape[0])

    @classmethod
    def from_objects(cls, objects: Sequence[Object3D]) -> LabelArrays:
        """Collect parsed label lines (``pipeline.kitti.read_labels``) into arrays."""
        n = len(objects)
        return cls(
            types=np.array([o.type.lower() for o in objects], dtype=object).reshape(n),
            truncated=np.array([o.truncated for o in objects], dtype=np.float64).reshape(n),
            occluded=np.array([o.occluded for o in objects], dtype=np.int64).reshape(n),
            bbox=np.array([o.bbox for o in objects], dtype=np.float64).reshape(n, 4),
            dimensions=np.array([o.dimensions for o in objects], dtype=np.float64).reshape(n, 3),
            location=np.array([o.location for o in objects], dtype=np.float64).reshape(n, 3),
            rotation_y=np.array([o.rotation_y for o in objects], dtype=np.float64).reshape(n),
            score=np.array(
                [np.nan if o.score is None else o.score for o in objects], dtype=np.float64
            ).reshape(n),
        )

    @classmethod
    def empty(cls) -> LabelArrays:
        """A frame without objects."""
        return cls.from_objects([])

    def select(self, mask: np.ndarray) -> LabelArrays:
        """The rows where the boolean ``mask`` (N,) is true, order kept."""
        return LabelArrays(
            types=self.types[mask], truncated=self.truncated[mask], occluded=self.occluded[mask],
            bbox=self.bbox[mask], dimensions=self.dimensions[mask], location=self.location[mask],
            rotation_y=self.rotation_y[mask], score=self.score[mask],
        )

    @property
    def box_height(self) -> np.ndarray:
        """(N,) 2D box height ``bottom - top`` in pixels (signed, as the devkit uses for ground truth)."""
        return self.bbox[:, 3] - self.bbox[:, 1]
