"""The ground: a road with slope, vertical and horizontal curvature, curbs, sidewalks and verges.

Ground height (LiDAR frame) ``z = z0 + slope·x + bend_v·x² + cross_slope·y``, raised by
the curb height off the carriageway. The road centre line runs along
``y = y0 + heading·x + bend_h·x²``; ``lateral`` is the signed distance from it
(positive to the left). Both surfaces are quadrics in the ray parameter, so a ray
meets them in closed form.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from simulation.constants import CURB_HEIGHT, LANE_WIDTH, PARKING_WIDTH


class Zone(IntEnum):
    """What the ground is at a point."""

    ROAD = 0
    SIDEWALK = 1
    VERGE = 2


@dataclass(frozen=True)
class Road:
    """Ground surface and road cross-section. Lane counts per side; parking lanes at the road edges."""

    z0: float
    slope: float
    bend_v: float
    cross_slope: float
    y0: float
    heading: float
    bend_h: float
    lanes_left: int
    lanes_right: int
    parking_left: bool
    parking_right: bool
    sidewalk_width: float
    verge_grass: bool  # grass beyond the sidewalk, else paving

    # ---- cross-section (lateral offsets, left positive)
    @property
    def left_edge(self) -> float:
        """Lateral offset of the left curb."""
        return self.lanes_left * LANE_WIDTH + self.parking_left * PARKING_WIDTH

    @property
    def right_edge(self) -> float:
        """Lateral offset of the right curb (negative)."""
        return -(self.lanes_right * LANE_WIDTH + self.parking_right * PARKING_WIDTH)

    # ---- shape
    def centre_y(self, x: np.ndarray | float) -> np.ndarray:
        """y of the centre line at x."""
        return self.y0 + self.heading * x + self.bend_h * np.square(x)

    def direction(self, x: np.ndarray | float) -> np.ndarray:
        """Heading angle of the road at x (radians, about z)."""
        return np.arctan(self.heading + 2.0 * self.bend_h * np.asarray(x))

    def lateral(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Signed distance of (x, y) from the centre line, left positive (first order in the bend)."""
        return (y - self.centre_y(x)) * np.cos(self.direction(x))

    def base_height(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        """Carriageway surface height at (x, y)."""
        return self.z0 + self.slope * np.asarray(x) + self.bend_v * np.square(x) + self.cross_slope * np.asarray(y)

    def zone(self, lateral: np.ndarray) -> np.ndarray:
        """Zone per lateral offset (int8 values of :class:`Zone`)."""
        out = np.full(np.shape(lateral), Zone.VERGE, np.int8)
        beyond = np.maximum(lateral - self.left_edge, self.right_edge - lateral)
        out[beyond <= self.sidewalk_width] = Zone.SIDEWALK
        out[beyond <= 0] = Zone.ROAD
        return out

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Ground height including the curb rise off the carriageway."""
        raised = self.zone(self.lateral(x, y)) != Zone.ROAD
        return self.base_height(x, y) + CURB_HEIGHT * raised

    def place(self, along: float, lateral: float) -> tuple[float, float, float, float]:
        """World (x, y, ground z, road heading) of the point ``lateral`` metres off the centre line at x=along."""
        theta = float(self.direction(along))
        x = along - lateral * np.sin(theta)
        y = float(self.centre_y(along)) + lateral * np.cos(theta)
        return x, y, float(self.height(np.array([x]), np.array([y]))[0]), theta

    # ---- rays
    def _surface_hit(self, origin: np.ndarray, dirs: np.ndarray, rise: float) -> np.ndarray:
        """First positive t where the ray meets the base surface raised by ``rise``; inf if none."""
        ox, oy, oz = origin
        dx, dy, dz = dirs[:, 0], dirs[:, 1], dirs[:, 2]
        a = -self.bend_v * dx * dx
        b = dz - self.slope * dx - 2.0 * self.bend_v * ox * dx - self.cross_slope * dy
        c = oz - (self.z0 + rise + self.slope * ox + self.bend_v * ox * ox + self.cross_slope * oy)
        disc = b * b - 4.0 * a * c
        with np.errstate(invalid="ignore", divide="ignore"):
            # Stable roots: q = -(b + sign(b)·√disc)/2, roots q/a and c/q.
            q = -0.5 * (b + np.copysign(np.sqrt(np.maximum(disc, 0.0)), b))
            r1 = np.where(np.abs(a) > 1e-12, q / a, np.inf)
            r2 = c / q
        r1 = np.where((disc >= 0) & (r1 > 1e-6), r1, np.inf)
        r2 = np.where((disc >= 0) & (r2 > 1e-6), r2, np.inf)
        return np.minimum(r1, r2)

    def intersect(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Ray parameter of the ground hit, (M,) with inf for rays that never reach the ground."""
        t_high = self._surface_hit(origin, dirs, CURB_HEIGHT)
        t_low = self._surface_hit(origin, dirs, 0.0)
        with np.errstate(invalid="ignore"):
            p_high = origin + np.where(np.isfinite(t_high), t_high, 0.0)[:, None] * dirs
        raised = self.zone(self.lateral(p_high[:, 0], p_high[:, 1])) != Zone.ROAD
        # A ray that misses the raised surface over the sidewalk but meets the carriageway level
        # there has entered through the curb face; t_low is within a curb height of that face.
        return np.where(np.isfinite(t_high) & raised, t_high, t_low)
