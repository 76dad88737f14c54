"""Builders that turn an object's pose and size into primitives: cars, vans, people, cyclists, scenery.

Every builder takes the bottom centre (3,) in the LiDAR frame and a yaw, works in
the object's frame (x forward, y left, z up from the ground) and keeps every
solid inside the object's nominal box, so that box is a tight KITTI label.
"""

from __future__ import annotations

import numpy as np

from simulation.geometry import Material, Primitive, Shape, Texture, rotation_x, rotation_y, rotation_z

RUBBER = Material((0.03, 0.03, 0.03), Texture.PLAIN, albedo=0.06)
GLASS = Material((0.05, 0.06, 0.08), Texture.GLASS, albedo=0.05, range_noise=0.05)
TAIL_LIGHT = Material((0.7, 0.02, 0.02), Texture.LIGHT, albedo=0.9)
HEAD_LIGHT = Material((0.9, 0.9, 0.8), Texture.LIGHT, albedo=0.9)
SKIN = Material((0.65, 0.45, 0.35), Texture.PLAIN, albedo=0.35)
METAL = Material((0.45, 0.45, 0.47), Texture.PAINT, albedo=0.5)
BARK = Material((0.25, 0.17, 0.10), Texture.PLAIN, albedo=0.35)
SIGN = Material((0.85, 0.85, 0.9), Texture.LIGHT, albedo=0.95)  # retro-reflective sheeting

_WHEEL_AXIS = rotation_x(np.pi / 2)  # cylinder axis (local z) → the object's y axis


class _Frame:
    """An object's frame: bottom centre and yaw; converts local solids to world primitives."""

    def __init__(self, bottom: np.ndarray, yaw: float, actor: int) -> None:
        self.bottom = np.asarray(bottom, np.float64)
        self.rot = rotation_z(yaw)
        self.actor = actor

    def add(self, shape: Shape, centre: tuple[float, float, float], half: tuple[float, float, float],
            material: Material, local_rot: np.ndarray | None = None) -> Primitive:
        """A primitive centred at ``centre`` in the object frame."""
        rot = self.rot if local_rot is None else self.rot @ local_rot
        return Primitive(shape, self.bottom + self.rot @ np.asarray(centre, np.float64), rot,
                         np.asarray(half, np.float64), material, self.actor)


def paint(colour: np.ndarray) -> Material:
    """Car paint of a colour; bright paints reflect the laser better."""
    c = tuple(float(v) for v in np.clip(colour, 0, 1))
    return Material(c, Texture.PAINT, albedo=0.12 + 0.35 * float(np.mean(c)))


def car(bottom: np.ndarray, yaw: float, l: float, w: float, h: float, colour: np.ndarray,
        actor: int) -> list[Primitive]:
    """A saloon: body, glass cabin with roof, sloped windscreen and rear window, four wheels, lights."""
    f = _Frame(bottom, yaw, actor)
    body = paint(colour)
    r = float(np.clip(0.21 * h, 0.28, 0.36))  # wheel radius
    clearance = 0.55 * r
    belt = 0.56 * h  # top of the body, bottom of the windows
    roof = 0.06
    cab_l, cab_w, cab_x = 0.46 * l, 0.84 * w, -0.06 * l
    wheel_x = 0.5 * l - 1.15 * r - 0.12 * l
    prims = [
        f.add(Shape.BOX, (0.005, 0, (clearance + belt) / 2), (l / 2 - 0.01, w / 2, (belt - clearance) / 2), body),
        f.add(Shape.BOX, (cab_x, 0, (belt + h - roof) / 2), (cab_l / 2, cab_w / 2, (h - roof - belt) / 2), GLASS),
        f.add(Shape.BOX, (cab_x, 0, h - roof / 2), (cab_l / 2, cab_w / 2, roof / 2), body),
    ]
    # Windscreen and rear window: glass slabs leaning onto the cabin, kept below the roof line.
    glass_h = h - roof - belt
    for sign, lean in ((1.0, 0.95), (-1.0, 0.75)):
        run = lean * glass_h
        x_mid = cab_x + sign * (cab_l / 2 + run / 2) - sign * 0.05
        tilt = rotation_y(-sign * np.arctan2(run, glass_h))  # top leans towards the cabin
        slab = np.hypot(run, glass_h) / 2
        prims.append(f.add(Shape.BOX, (x_mid, 0, belt + glass_h / 2 - 0.02), (0.05, cab_w / 2, slab * 0.92),
                           GLASS, tilt))
    for x in (wheel_x, -wheel_x):
        for y in (w / 2 - 0.13, -(w / 2 - 0.13)):
            prims.append(f.add(Shape.CYLINDER, (x, y, r), (r, r, 0.12), RUBBER, _WHEEL_AXIS))
    for y in (w / 2 - 0.2, -(w / 2 - 0.2)):
        prims.append(f.add(Shape.BOX, (-l / 2 + 0.02, y, belt - 0.12), (0.02, 0.14, 0.06), TAIL_LIGHT))
        prims.append(f.add(Shape.BOX, (l / 2 - 0.02, y, belt - 0.15), (0.02, 0.15, 0.05), HEAD_LIGHT))
    return prims


def van(bottom: np.ndarray, yaw: float, l: float, w: float, h: float, colour: np.ndarray,
        actor: int) -> list[Primitive]:
    """A box van: tall body, short bonnet, windscreen and side-window band, four wheels."""
    f = _Frame(bottom, yaw, actor)
    body = paint(colour)
    r = 0.36
    clearance = 0.5 * r
    bonnet = 0.16 * l
    prims = [
        f.add(Shape.BOX, (-bonnet / 2, 0, (clearance + h) / 2), ((l - bonnet) / 2, w / 2 - 0.02, (h - clearance) / 2), body),
        f.add(Shape.BOX, (l / 2 - bonnet / 2, 0, (clearance + 0.5 * h) / 2), (bonnet / 2, w / 2 - 0.02,
                                                                                (0.5 * h - clearance) / 2), body),
        f.add(Shape.BOX, (l / 2 - bonnet - 0.6, 0, 0.73 * h), (0.62, w / 2, 0.14 * h), GLASS),
    ]
    for x in (l / 2 - bonnet - 0.2, -l / 2 + 0.9):
        for y in (w / 2 - 0.15, -(w / 2 - 0.15)):
            prims.append(f.add(Shape.CYLINDER, (x, y, r), (r, r, 0.13), RUBBER, _WHEEL_AXIS))
    return prims


def pedestrian(bottom: np.ndarray, yaw: float, l: float, w: float, h: float, colour: np.ndarray,
               actor: int) -> list[Primitive]:
    """A walking person: two legs mid-stride, torso, arms, head."""
    f = _Frame(bottom, yaw, actor)
    clothes = Material(tuple(float(v) for v in colour), Texture.PLAIN, albedo=0.25 + 0.3 * float(np.mean(colour)))
    trousers = Material((0.12, 0.13, 0.2), Texture.PLAIN, albedo=0.2)
    leg_h = 0.47 * h
    stride = min(0.25 * l, 0.18)
    prims = [f.add(Shape.CYLINDER, (sign * stride, side * 0.09, leg_h / 2), (0.075, 0.075, leg_h / 2), trousers)
             for sign, side in ((1, 1), (-1, -1))]
    torso_w = min(0.22, w / 2 - 0.08)
    prims.append(f.add(Shape.ELLIPSOID, (0, 0, 0.65 * h), (0.15, torso_w, 0.19 * h), clothes))
    for side in (1, -1):
        prims.append(f.add(Shape.CYLINDER, (0, side * (torso_w + 0.03), 0.63 * h), (0.045, 0.045, 0.15 * h), clothes))
    prims.append(f.add(Shape.ELLIPSOID, (0, 0, h - 0.12), (0.1, 0.09, 0.12), SKIN))
    return prims


def cyclist(bottom: np.ndarray, yaw: float, l: float, w: float, h: float, colour: np.ndarray,
            actor: int) -> list[Primitive]:
    """A bicycle (two wheels, frame) with a rider leaning forward."""
    f = _Frame(bottom, yaw, actor)
    clothes = Material(tuple(float(v) for v in colour), Texture.PLAIN, albedo=0.3)
    r = 0.34
    axle = l / 2 - r
    prims = [f.add(Shape.CYLINDER, (x, 0, r), (r, r, 0.025), RUBBER, _WHEEL_AXIS) for x in (axle, -axle)]
    prims.append(f.add(Shape.BOX, (0, 0, r + 0.15), (axle * 0.8, 0.03, 0.12), METAL))
    prims.append(f.add(Shape.BOX, (-0.1, 0, 0.55 * h), (0.2, min(0.15, w / 2 - 0.02), 0.08),
                       Material((0.12, 0.13, 0.2), Texture.PLAIN, albedo=0.2)))  # thighs
    prims.append(f.add(Shape.ELLIPSOID, (0.05, 0, 0.78 * h), (0.22, min(0.2, w / 2 - 0.02), 0.17 * h), clothes,
                       rotation_y(0.6)))
    prims.append(f.add(Shape.ELLIPSOID, (0.22, 0, h - 0.12), (0.11, 0.1, 0.12), SKIN))
    return prims


def tree(bottom: np.ndarray, height: float, crown: float, foliage: Material) -> list[Primitive]:
    """A trunk and an ellipsoid crown."""
    f = _Frame(bottom, 0.0, -1)
    trunk_h = height - crown * 1.2
    return [
        f.add(Shape.CYLINDER, (0, 0, trunk_h / 2 + 0.3), (0.15, 0.15, trunk_h / 2 + 0.3), BARK),
        f.add(Shape.ELLIPSOID, (0, 0, height - crown * 0.9), (crown, crown, crown * 0.9), foliage),
    ]


def pole(bottom: np.ndarray, yaw: float, height: float, with_sign: bool) -> list[Primitive]:
    """A street-lamp pole with its lamp arm, or a traffic-sign post with a plate."""
    f = _Frame(bottom, yaw, -1)
    prims = [f.add(Shape.CYLINDER, (0, 0, height / 2 - 0.3), (0.08, 0.08, height / 2 + 0.3), METAL)]
    if with_sign:
        prims.append(f.add(Shape.BOX, (0, 0, height - 0.35), (0.02, 0.35, 0.35), SIGN))
    else:
        prims.append(f.add(Shape.BOX, (0, 0.6, height), (0.08, 0.7, 0.06), METAL))
        prims.append(f.add(Shape.BOX, (0, 1.2, height - 0.08), (0.15, 0.25, 0.04), HEAD_LIGHT))
    return prims


def block(centre_bottom: np.ndarray, yaw: float, length: float, depth: float, height: float,
          material: Material, sink: float = 1.0) -> Primitive:
    """A building, wall or hedge: a box standing on the ground, sunk ``sink`` metres to meet sloping ground."""
    f = _Frame(centre_bottom, yaw, -1)
    return f.add(Shape.BOX, (0, 0, (height - sink) / 2), (length / 2, depth / 2, (height + sink) / 2), material)
