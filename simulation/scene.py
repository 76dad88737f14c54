"""What a frame contains: the road, labelled actors, scenery primitives, and the lighting."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from simulation.geometry import Primitive
from simulation.road import Road


@dataclass
class Actor:
    """A labelled object: KITTI type, its 3D box in the LiDAR frame, and the solids that draw it.

    bottom: (3,) centre of the box's bottom face. size: (l, w, h). yaw: heading about z.
    The box is the tight extent of the primitives (KITTI boxes exclude mirrors; so do ours).
    """

    kind: str
    bottom: np.ndarray
    size: tuple[float, float, float]
    yaw: float
    primitives: list[Primitive] = field(default_factory=list)

    @property
    def box(self) -> np.ndarray:
        """(7,) ``x, y, z, l, w, h, yaw`` with z the box centre, as pipeline.boxes uses."""
        l, w, h = self.size
        return np.array([self.bottom[0], self.bottom[1], self.bottom[2] + h / 2, l, w, h, self.yaw])

    @property
    def distance(self) -> float:
        """Horizontal distance of the box centre from the LiDAR."""
        return float(np.hypot(self.bottom[0], self.bottom[1]))


@dataclass
class Lighting:
    """Sun direction (unit, pointing to the sun), ambient level, sky colours, exposure."""

    sun: np.ndarray
    ambient: float
    sky_horizon: np.ndarray
    sky_zenith: np.ndarray
    exposure: float


@dataclass
class Scene:
    """Everything the sensors see. ``primitives`` holds scenery and actors' solids alike.

    shadow_casters: (K, 8, 3) boxes whose shadows fall on the ground in the image.
    """

    road: Road
    actors: list[Actor]
    primitives: list[Primitive]
    lighting: Lighting
    shadow_casters: np.ndarray
