"""Procedural scene layout: a street with buildings, furniture, parked rows, traffic and people.

All randomness comes from the generator passed in, so a frame's scene is a pure
function of its seed.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from simulation import shapes
from simulation.constants import (
    CAR_COLOURS,
    CAR_MAX_DISTANCE,
    CAR_SIZE,
    CYCLIST_SIZE,
    LANE_WIDTH,
    LIDAR_HEIGHT,
    MAX_CROSS_SLOPE,
    MAX_HORIZONTAL_CURVATURE,
    MAX_SLOPE,
    MAX_VERTICAL_CURVATURE,
    PARKING_WIDTH,
    PEDESTRIAN_SIZE,
    ROAD_AHEAD,
    ROAD_BEHIND,
    VAN_SIZE,
)
from simulation.geometry import UNIT_CORNERS, Material, Primitive, Texture, rotation_z
from simulation.road import Road
from simulation.scene import Actor, Lighting, Scene

FACADE_COLOURS = np.array([
    [0.75, 0.70, 0.60], [0.85, 0.83, 0.78], [0.55, 0.30, 0.22], [0.60, 0.60, 0.62], [0.80, 0.65, 0.45],
    [0.45, 0.42, 0.40],
])
CLOTHES_COLOURS = np.array([
    [0.1, 0.1, 0.12], [0.6, 0.1, 0.1], [0.15, 0.25, 0.55], [0.8, 0.8, 0.8], [0.3, 0.45, 0.25], [0.7, 0.55, 0.2],
])
Builder = Callable[..., list[Primitive]]


def _size(rng: np.random.Generator, spec: tuple[tuple[float, float], ...]) -> tuple[float, float, float]:
    """(l, w, h) from KITTI (mean, sigma) for h, w, l, clipped at two sigma."""
    h, w, l = (float(np.clip(rng.normal(m, s), m - 2 * s, m + 2 * s)) for m, s in spec)
    return l, w, h


def sample_road(rng: np.random.Generator) -> Road:
    """A road with the ego car in one of the right-hand lanes at x = 0."""
    lanes_right = int(rng.choice([1, 2], p=[0.6, 0.4]))
    ego_lane = int(rng.integers(lanes_right))
    return Road(
        z0=-LIDAR_HEIGHT + rng.normal(0, 0.02),
        slope=rng.uniform(-MAX_SLOPE, MAX_SLOPE),
        bend_v=rng.uniform(-MAX_VERTICAL_CURVATURE, MAX_VERTICAL_CURVATURE),
        cross_slope=rng.uniform(-MAX_CROSS_SLOPE, MAX_CROSS_SLOPE),
        y0=(ego_lane + 0.5) * LANE_WIDTH + rng.normal(0, 0.3),
        heading=rng.normal(0, 0.02),
        bend_h=rng.uniform(-MAX_HORIZONTAL_CURVATURE, MAX_HORIZONTAL_CURVATURE),
        lanes_left=int(rng.choice([1, 2], p=[0.6, 0.4])),
        lanes_right=lanes_right,
        parking_left=bool(rng.random() < 0.7),
        parking_right=bool(rng.random() < 0.7),
        sidewalk_width=rng.uniform(1.5, 4.0),
        verge_grass=bool(rng.random() < 0.5),
    )


def sample_lighting(rng: np.random.Generator) -> Lighting:
    """Daylight: sun 15–65° high from any direction, overcast to clear."""
    elevation = np.radians(rng.uniform(15, 65))
    azimuth = rng.uniform(-np.pi, np.pi)
    sun = np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
    return Lighting(
        sun=sun, ambient=rng.uniform(0.3, 0.5),
        sky_horizon=np.clip(np.array([0.78, 0.84, 0.9]) + rng.normal(0, 0.04, 3), 0, 1),
        sky_zenith=np.clip(np.array([0.3, 0.5, 0.85]) + rng.normal(0, 0.06, 3), 0, 1),
        exposure=rng.uniform(0.85, 1.15),
    )


def _side_offset(road: Road, side: int) -> float:
    """Lateral offset of the outer sidewalk edge on a side (+1 left, -1 right)."""
    edge = road.left_edge if side > 0 else road.right_edge
    return edge + side * road.sidewalk_width


class _Placer:
    """Collects primitives, actors and shadow casters; rejects overlapping footprints."""

    def __init__(self, road: Road) -> None:
        self.road = road
        self.primitives: list[Primitive] = []
        self.actors: list[Actor] = []
        self.casters: list[np.ndarray] = []
        # Footprints are circles (x, y, radius); the ego car plus a safety gap is five along its length.
        self.footprints: list[tuple[float, float, float]] = [(3.0, 0.0, 1.0), (1.2, 0.0, 1.0), (-0.3, 0.0, 1.0), (-1.8, 0.0, 1.0), (-3.6, 0.0, 1.0)]

    def free(self, x: float, y: float, radius: float) -> bool:
        """True when a circle at (x, y) overlaps nothing placed so far."""
        return all(np.hypot(x - fx, y - fy) > radius + fr for fx, fy, fr in self.footprints)

    @staticmethod
    def _circles(x: float, y: float, yaw: float, l: float, w: float) -> list[tuple[float, float, float]]:
        """Circles of radius ≈ w/2 covering an l × w footprint (tighter than one circle for long objects)."""
        radius = 0.5 * w + 0.1
        n = max(1, int(np.ceil(l / w)))
        offsets = np.linspace(-(l / 2 - w / 2), l / 2 - w / 2, n) if n > 1 else np.zeros(1)
        return [(x + o * np.cos(yaw), y + o * np.sin(yaw), radius) for o in offsets]

    def scenery(self, prims: list[Primitive], footprint: tuple[float, float, float] | None = None,
                caster: np.ndarray | None = None) -> None:
        """Add unlabelled solids."""
        self.primitives.extend(prims)
        if footprint is not None:
            self.footprints.append(footprint)
        if caster is not None:
            self.casters.append(caster)

    def actor(self, kind: str, builder: Builder, along: float, lateral: float, yaw_offset: float,
              size: tuple[float, float, float], colour: np.ndarray, check: bool = False) -> bool:
        """Place a labelled object on the road surface; returns False if it would overlap something."""
        x, y, z, heading = self.road.place(along, lateral)
        l, w, h = size
        yaw = float((heading + yaw_offset + np.pi) % (2 * np.pi) - np.pi)
        circles = self._circles(x, y, yaw, l, w)
        if check and not all(self.free(*c) for c in circles):
            return False
        bottom = np.array([x, y, z])
        index = len(self.actors)
        prims = builder(bottom, yaw, l, w, h, colour, index)
        self.actors.append(Actor(kind, bottom, size, yaw, prims))
        self.primitives.extend(prims)
        self.footprints.extend(circles)
        corners = UNIT_CORNERS * np.array([l / 2, w / 2, h / 2])
        self.casters.append(corners @ rotation_z(yaw).T + bottom + [0, 0, h / 2])
        return True


def _buildings(rng: np.random.Generator, p: _Placer, style: str) -> None:
    """Rows of buildings (urban), houses with hedges (residential) or tree lines (open road), both sides."""
    road = p.road
    for side in (1, -1):
        base = _side_offset(road, side)
        along = ROAD_BEHIND + rng.uniform(0, 10)
        while along < ROAD_AHEAD:
            if style == "open" or rng.random() < 0.15:
                gap = rng.uniform(5, 20)
                if rng.random() < 0.6:  # a hedge or wall fills the gap
                    hedge = rng.random() < 0.5
                    mat = Material((0.12, 0.3, 0.1), Texture.FOLIAGE, 0.45, 0.08) if hedge else Material(
                        tuple(FACADE_COLOURS[rng.integers(len(FACADE_COLOURS))] * 0.9), Texture.PLAIN, 0.35)
                    height = rng.uniform(0.8, 2.0)
                    lat = base + side * rng.uniform(0.3, 1.5)
                    x, y, z, heading = road.place(along + gap / 2, lat)
                    p.scenery([shapes.block(np.array([x, y, z]), heading, gap, 0.5 if not hedge else 1.0,
                                            height, mat, sink=1.0 + abs(road.slope) * gap)])
                along += gap
                continue
            width = rng.uniform(8, 25) if style == "urban" else rng.uniform(8, 14)
            depth = rng.uniform(8, 15)
            height = rng.uniform(6, 20) if style == "urban" else rng.uniform(4, 8)
            setback = rng.uniform(0, 1.5) if style == "urban" else rng.uniform(3, 8)
            lat = base + side * (setback + depth / 2)
            x, y, z, heading = road.place(along + width / 2, lat)
            colour = np.clip(FACADE_COLOURS[rng.integers(len(FACADE_COLOURS))] + rng.normal(0, 0.04, 3), 0, 1)
            mat = Material(tuple(float(v) for v in colour), Texture.FACADE, albedo=rng.uniform(0.3, 0.5))
            prim = shapes.block(np.array([x, y, z]), heading, width, depth, height, mat,
                                sink=1.0 + abs(road.slope) * width)
            p.scenery([prim], caster=prim.corners())
            along += width + (rng.uniform(0, 2) if style == "urban" else rng.uniform(2, 8))


def _furniture(rng: np.random.Generator, p: _Placer, style: str) -> None:
    """Lamp poles and sign posts at the curb, trees along the sidewalk."""
    road = p.road
    for side in (1, -1):
        edge = road.left_edge if side > 0 else road.right_edge
        along = ROAD_BEHIND + rng.uniform(0, 20)
        while along < ROAD_AHEAD:
            x, y, z, heading = road.place(along, edge + side * 0.5)
            if p.free(x, y, 0.3):
                sign = rng.random() < 0.3
                p.scenery(shapes.pole(np.array([x, y, z]), heading + (np.pi if side > 0 else 0),
                                      rng.uniform(2.5, 3.0) if sign else rng.uniform(6, 8), sign), (x, y, 0.3))
            along += rng.uniform(20, 40)
        along = ROAD_BEHIND + rng.uniform(0, 10)
        spacing = (8, 15) if style != "urban" else (15, 40)
        while along < ROAD_AHEAD:
            x, y, z, _ = road.place(along, edge + side * (road.sidewalk_width - 0.8 + rng.uniform(0, 2)))
            height, crown = rng.uniform(5, 11), rng.uniform(1.5, 3.0)
            if p.free(x, y, 0.5):
                green = np.clip(np.array([0.12, 0.32, 0.1]) * rng.uniform(0.7, 1.3) + rng.normal(0, 0.02, 3), 0, 1)
                foliage = Material(tuple(float(v) for v in green), Texture.FOLIAGE, 0.45, range_noise=0.08)
                prims = shapes.tree(np.array([x, y, z]), height, crown, foliage)
                p.scenery(prims, (x, y, 0.5), prims[1].corners())
            along += rng.uniform(*spacing)


def _car_colour(rng: np.random.Generator) -> np.ndarray:
    return np.clip(CAR_COLOURS[rng.integers(len(CAR_COLOURS))] * rng.uniform(0.85, 1.1), 0, 1)


def _vehicle(rng: np.random.Generator, p: _Placer, along: float, lateral: float, yaw: float,
             van_fraction: float = 0.1) -> float:
    """Place a car or a van; returns its length (placed or not)."""
    is_van = rng.random() < van_fraction
    size = _size(rng, VAN_SIZE if is_van else CAR_SIZE)
    colour = _car_colour(rng)
    builder = shapes.van if is_van else shapes.car
    p.actor("Van" if is_van else "Car", builder, along + size[0] / 2, lateral, yaw, size, colour, check=True)
    return size[0]


def _vehicles(rng: np.random.Generator, p: _Placer) -> None:
    """Parked rows in the parking lanes and traffic in every lane, out to CAR_MAX_DISTANCE."""
    road = p.road
    for side, parking, lanes in ((1, road.parking_left, road.lanes_left), (-1, road.parking_right, road.lanes_right)):
        if parking:
            lat = side * (lanes * LANE_WIDTH + PARKING_WIDTH / 2)
            along = ROAD_BEHIND + rng.uniform(0, 8)
            occupancy = rng.uniform(0.4, 1.0)
            while along < CAR_MAX_DISTANCE:
                if rng.random() > occupancy:
                    along += rng.uniform(4, 15)
                    continue
                flip = np.pi if rng.random() < 0.25 else 0.0
                length = _vehicle(rng, p, along, lat + rng.normal(0, 0.12), flip + rng.normal(0, 0.04))
                along += length + rng.uniform(0.6, 3.0)
        for lane in range(lanes):
            lat = side * (lane + 0.5) * LANE_WIDTH
            along = ROAD_BEHIND + rng.uniform(0, 20)
            spacing = rng.uniform(8, 45)
            while along < CAR_MAX_DISTANCE:
                direction = 0.0 if side < 0 else np.pi
                length = _vehicle(rng, p, along, lat + rng.normal(0, 0.25), direction + rng.normal(0, 0.03))
                along += length + rng.exponential(spacing) + 3.0


def _people(rng: np.random.Generator, p: _Placer) -> None:
    """Pedestrians on the sidewalks; cyclists at the road edge."""
    road = p.road
    for _ in range(rng.poisson(3)):
        side = 1 if rng.random() < 0.5 else -1
        edge = road.left_edge if side > 0 else road.right_edge
        lat = edge + side * rng.uniform(0.4, max(road.sidewalk_width - 0.4, 0.5))
        colour = CLOTHES_COLOURS[rng.integers(len(CLOTHES_COLOURS))]
        p.actor("Pedestrian", shapes.pedestrian, rng.uniform(-20, 50), lat, rng.uniform(-np.pi, np.pi),
                _size(rng, PEDESTRIAN_SIZE), colour, check=True)
    for _ in range(rng.choice([0, 1, 2], p=[0.5, 0.35, 0.15])):
        side = 1 if rng.random() < 0.4 else -1
        edge = road.left_edge if side > 0 else road.right_edge
        lat = edge - side * (0.6 + PARKING_WIDTH * (road.parking_left if side > 0 else road.parking_right))
        colour = CLOTHES_COLOURS[rng.integers(len(CLOTHES_COLOURS))]
        p.actor("Cyclist", shapes.cyclist, rng.uniform(5, 50), lat, (0.0 if side < 0 else np.pi) + rng.normal(0, 0.05),
                _size(rng, CYCLIST_SIZE), colour, check=True)


def generate_scene(rng: np.random.Generator) -> Scene:
    """A random street scene around the ego car (see module doc)."""
    style = str(rng.choice(["urban", "residential", "open"], p=[0.5, 0.35, 0.15]))
    road = sample_road(rng)
    placer = _Placer(road)
    _furniture(rng, placer, style)
    _people(rng, placer)
    _vehicles(rng, placer)
    _buildings(rng, placer, style)
    casters = np.array(placer.casters).reshape(-1, 8, 3)
    return Scene(road=road, actors=placer.actors, primitives=placer.primitives,
                 lighting=sample_lighting(rng), shadow_casters=casters)
