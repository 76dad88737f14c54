"""simulation/ pinned by geometry and KITTI's conventions, from a mutation audit of the simulator.

The shipped models were trained and validated on these frames, so a label or a piece of geometry that
silently goes wrong here corrupts training and every AP in the README while the frames still read back as
valid KITTI. The other simulation tests check that frames are self-consistent (labels agree with the render
they came from, files read back); these pin what the frames must be: a car placed at a known spot gets the
label KITTI's conventions give it (bottom-centre location in the rectified camera frame, ``rotation_y =
−yaw − π/2``, ``alpha = rotation_y − atan2(x, z)``, pixel-edge 2D boxes around its silhouette), its solids stay
inside that box, the scan has the HDL-64E's geometry and the documented range rules, the calibration keeps
camera 2's physics, and frames, seeds and the command line map to the files they should.

Expectations come from the scene placed by the test and from documented rules (docs/simulation.md), not from
values read off the simulator's output. Each test failed on a mutant of simulation/ (see the audit's report).
Scenes are built by hand (a flat road, a few solids) and rendered in memory; the few generated frames go to
tmp_path.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.beams import recover_rings
from pipeline.calib import KITTI_CALIBRATION
from simulation import shapes
from simulation.camera import render, sample_calibration
from simulation.geometry import Material, Primitive, Shape
from simulation.labels import label_objects, occlusion_level
from simulation.lidar import scan
from simulation.road import Road
from simulation.scene import Actor, Lighting, Scene

CALIB = KITTI_CALIBRATION
HEIGHT = 1.73  # KITTI's velodyne above the road
W, H = 1242, 375
GREY = np.array([0.5, 0.5, 0.5])


def flat_road(**changes: float) -> Road:
    """A straight road along x, two lanes each way (|y| < 7 m), no parking lanes, the ground 1.73 m under the
    sensor."""
    values = {"z0": -HEIGHT, "slope": 0.0, "bend_v": 0.0, "cross_slope": 0.0, "y0": 0.0, "heading": 0.0,
              "bend_h": 0.0, "lanes_left": 2, "lanes_right": 2, "parking_left": False, "parking_right": False,
              "sidewalk_width": 2.0, "verge_grass": False}
    return Road(**{**values, **changes})


def make_scene(actors: list[tuple[str, tuple[float, float], float, tuple[float, float, float]]],
               scenery: list[Primitive] = (), road: Road | None = None) -> Scene:
    """A scene of labelled actors (kind, (x, y) of the bottom centre on the road, yaw, (l, w, h)) and scenery."""
    road = road or flat_road()
    builders = {"Car": shapes.car, "Van": shapes.van, "Pedestrian": shapes.pedestrian, "Cyclist": shapes.cyclist}
    placed, prims = [], list(scenery)
    for index, (kind, (x, y), yaw, size) in enumerate(actors):
        bottom = np.array([x, y, float(road.base_height(x, y))])
        solids = builders[kind](bottom, yaw, *size, GREY, index)
        placed.append(Actor(kind, bottom, size, yaw, solids))
        prims.extend(solids)
    light = Lighting(sun=np.array([0.3, 0.2, 0.93]) / np.linalg.norm([0.3, 0.2, 0.93]), ambient=0.4,
                     sky_horizon=np.array([0.8, 0.84, 0.9]), sky_zenith=np.array([0.3, 0.5, 0.85]), exposure=1.0)
    return Scene(road, placed, prims, light, np.zeros((0, 8, 3)))


def box_corners_rect(bottom: np.ndarray, yaw: float, size: tuple[float, float, float]) -> np.ndarray:
    """(8, 3) corners of a LiDAR-frame box (bottom centre, yaw about z, l w h) in the rectified camera frame."""
    l, w, h = size
    c, s = np.cos(yaw), np.sin(yaw)
    local = np.array([[dx * l / 2, dy * w / 2, dz * h] for dx in (-1, 1) for dy in (-1, 1) for dz in (0, 1)])
    velo = local @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + bottom
    return velo_to_rect(velo)


def velo_to_rect(points: np.ndarray) -> np.ndarray:
    """KITTI's devkit chain, written out: x_rect = R0_rect · Tr_velo_to_cam · [x 1]."""
    homog = np.column_stack([points, np.ones(len(points))])
    return (CALIB.R0_rect @ (CALIB.Tr_velo_to_cam @ homog.T)).T


def project(rect: np.ndarray) -> np.ndarray:
    """(N, 2) pixels of rectified-camera points through P2."""
    uvw = np.column_stack([rect, np.ones(len(rect))]) @ CALIB.P2.T
    return uvw[:, :2] / uvw[:, 2:]


# Two cars: listed farther first, so the label order has to come from their distances.
FAR = ("Car", (25.0, 2.0), 0.3, (4.2, 1.7, 1.45))  # left of the lane, turned 0.3 rad to the left
NEAR = ("Car", (15.0, -2.0), 0.0, (4.0, 1.6, 1.5))  # ahead on the right, heading along the road


@pytest.fixture(scope="module")
def two_cars():
    scene = make_scene([FAR, NEAR])
    shot = render(scene, CALIB, np.random.default_rng(0))
    return scene, shot, label_objects(scene, shot, CALIB)


def test_a_car_at_a_known_place_gets_kitti_s_label(two_cars) -> None:
    """Location = the box's bottom centre in the rectified camera frame, (h, w, l), rotation_y = −yaw − π/2,
    alpha = rotation_y − atan2(x, z), nothing truncated or occluded, labels nearest first."""
    _, _, objects = two_cars
    assert [o.type for o in objects] == ["Car", "Car"]
    for obj, (_, (x, y), yaw, (l, w, h)) in zip(objects, (NEAR, FAR)):
        bottom = np.array([x, y, -HEIGHT])
        np.testing.assert_allclose(obj.location, velo_to_rect(bottom[None])[0], atol=1e-6)
        assert obj.dimensions == pytest.approx((h, w, l))
        assert obj.rotation_y == pytest.approx(-yaw - np.pi / 2)
        assert obj.alpha == pytest.approx(obj.rotation_y - np.arctan2(obj.location[0], obj.location[2]))
        assert obj.truncated == 0.0 and obj.occluded == 0


def test_a_car_s_2d_box_is_its_silhouette_in_pixel_edges(two_cars) -> None:
    """The 2D box hugs the projection of the 3D box (the body fills its box's sides and top: within 1.5 px;
    the bottom sits higher, as only the tyres reach the ground: docs/simulation.md) and its edges are pixel
    edges (centre ± 0.5), so width and height are whole pixels."""
    _, _, objects = two_cars
    for obj, (_, (x, y), yaw, size) in zip(objects, (NEAR, FAR)):
        uv = project(box_corners_rect(np.array([x, y, -HEIGHT]), yaw, size))
        left, top, right, bottom = obj.bbox
        np.testing.assert_allclose((left, top, right), (uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max()), atol=1.5)
        assert uv[:, 1].max() - 8 <= bottom <= uv[:, 1].max() + 1.5, (bottom, uv[:, 1].max())
        assert all(float(v) % 1.0 == 0.5 for v in obj.bbox), obj.bbox


def test_occlusion_levels_at_their_edges() -> None:
    """Occluded < 20 % → 0, < 50 % → 1, < 90 % → 2, else 3 (docs/simulation.md): the thresholds themselves
    belong to the next level."""
    assert [occlusion_level(f) for f in (0.0, 0.19, 0.2, 0.49, 0.5, 0.89, 0.9, 1.0)] == [0, 0, 1, 1, 2, 2, 3, 3]


@pytest.mark.parametrize("kind,size", [("Car", (4.6, 1.8, 1.6)), ("Van", (5.2, 1.95, 2.3)),
                                       ("Pedestrian", (0.9, 0.7, 1.8)), ("Cyclist", (1.8, 0.6, 1.75))])
def test_every_solid_of_an_actor_stays_inside_its_label_box(kind: str, size: tuple[float, float, float]) -> None:
    """A label is the tight box of what draws the object: every solid's surface, sampled, lies in the box
    (bottom centre, l × w × h, yaw), up to 1 cm."""
    yaw, bottom = 0.7, np.array([12.0, -3.0, -HEIGHT])
    actor = make_scene([(kind, (12.0, -3.0), yaw, size)]).actors[0]
    l, w, h = size
    np.testing.assert_allclose(actor.box, [12.0, -3.0, -HEIGHT + h / 2, l, w, h, yaw])  # z: the box centre
    unit = np.random.default_rng(1).normal(size=(400, 3))
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    for prim in actor.primitives:
        if prim.shape == Shape.BOX:
            local = np.array([[(i >> k & 1) * 2.0 - 1.0 for k in range(3)] for i in range(8)]) * prim.half
        elif prim.shape == Shape.ELLIPSOID:
            local = unit * prim.half
        else:  # cylinder: its two rims
            ring = unit[:, :2] / np.linalg.norm(unit[:, :2], axis=1, keepdims=True) * prim.half[0]
            local = np.concatenate([np.column_stack([ring, np.full(len(ring), z * prim.half[2])]) for z in (-1, 1)])
        world = local @ prim.rotation.T + prim.centre
        rel = world - bottom
        c, s = np.cos(yaw), np.sin(yaw)
        along, across = rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c
        tol = 0.01
        assert np.abs(along).max() <= l / 2 + tol and np.abs(across).max() <= w / 2 + tol, (kind, prim)
        assert rel[:, 2].min() >= -tol and rel[:, 2].max() <= h + tol, (kind, prim)


def box_actor(kind: str, x: float, y: float, size: tuple[float, float, float], index: int) -> Actor:
    """A labelled object drawn as one box (l × w × h on the flat road): its silhouette is its 3D box."""
    l, w, h = size
    bottom = np.array([x, y, -HEIGHT])
    solid = Primitive(Shape.BOX, bottom + [0, 0, h / 2], np.eye(3), np.array([l / 2, w / 2, h / 2]),
                      Material((0.5, 0.5, 0.5)), index)
    return Actor(kind, bottom, size, 0.0, [solid])


def labels_of(actors: list[Actor]) -> list:
    """label_2 objects of a flat-road scene holding these actors, in the base KITTI calibration."""
    scene = make_scene([])
    scene.actors.extend(actors)
    scene.primitives.extend(p for a in actors for p in a.primitives)
    return label_objects(scene, render(scene, CALIB, np.random.default_rng(0)), CALIB)


def test_cars_beyond_75_m_become_dont_care_and_nearer_ones_are_labelled() -> None:
    """KITTI's annotators stopped at about 75 m: a car at 72 m is a Car, one at 78 m a DontCare region, and so is
    one 73.8 m ahead and 14 m to the side (75.1 m away: the distance is horizontal, not along x alone)."""
    objects = labels_of([box_actor("Car", 72.0, -2.5, (4.0, 1.6, 1.5), 0), box_actor("Car", 78.0, 2.5, (4.0, 1.6, 1.5), 1),
                         box_actor("Car", 73.8, 14.0, (4.0, 1.6, 1.5), 2)])
    assert [o.type for o in objects] == ["Car", "DontCare", "DontCare"]
    assert objects[0].location[2] == pytest.approx(72.0 - 0.27, abs=0.1)


def test_objects_under_8_px_are_dont_care_and_under_20_pixels_unlabelled() -> None:
    """A 0.4 m tall object at 45 m is 0.4 · 721 / 45 ≈ 6.4 px tall: DontCare (with ~200 visible pixels); at
    28 m (≈ 10 px) it is labelled. A 0.2 m cube at 40 m covers ~16 pixels: no label of any kind."""
    flat = (0.3, 2.0, 0.4)
    assert [o.type for o in labels_of([box_actor("Car", 45.0, -2.0, flat, 0)])] == ["DontCare"]
    assert [o.type for o in labels_of([box_actor("Car", 28.0, -2.0, flat, 0)])] == ["Car"]
    assert labels_of([box_actor("Car", 40.0, -2.0, (0.2, 0.2, 0.2), 0)]) == []


def truncated_by_definition(actor: Actor) -> float:
    """Fraction of the actor's box volume (dense random samples) projecting outside the image or behind the camera."""
    l, w, h = actor.size
    local = np.random.default_rng(2).uniform(-0.5, 0.5, (40_000, 3)) * [l, w, h] + [0, 0, h / 2]
    c, s = np.cos(actor.yaw), np.sin(actor.yaw)
    velo = local @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + actor.bottom
    rect = velo_to_rect(velo)
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = project(rect)
    depth = rect[:, 2]
    inside = (depth > 0.1) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= W - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= H - 0.5)
    return float(1 - inside.mean())


def test_truncation_is_the_box_volume_outside_the_image_or_behind_the_camera() -> None:
    """Turned cars cut by the image's left and right borders, one beside the ego car (mostly below and right of
    the image), and a 20 m long box reaching 10 m behind the camera (whose rear, mirrored through the camera
    centre, would project into the image): `truncated` is the fraction of the box outside the view, to the
    label's two decimals (sampled: ±0.015, ±0.04 for the long box, sampled on a 6-point grid per axis)."""
    scene = make_scene([("Car", (6.0, 5.0), 0.5, (4.4, 1.7, 1.5)), ("Car", (7.0, -5.5), -0.5, (4.4, 1.7, 1.5)),
                        ("Car", (2.0, -3.5), 0.0, (4.5, 1.7, 1.5))])
    objects = label_objects(scene, render(scene, CALIB, np.random.default_rng(0)), CALIB)
    by_x = {round(float(o.location[2])): o for o in objects if o.type == "Car"}
    assert sorted(by_x) == [2, 6, 7]
    for actor in scene.actors:
        obj = by_x[round(float(velo_to_rect(actor.bottom[None])[0, 2]))]
        expected = truncated_by_definition(actor)
        assert expected > 0.3  # the scene does cut every car
        assert obj.truncated == pytest.approx(expected, abs=0.015), actor.bottom
    # Boxes of cut objects are clipped to the image, [0, 1241] × [0, 374], as KITTI's are.
    assert by_x[6].bbox[0] == 0.0 and by_x[7].bbox[2:] == (W - 1.0, H - 1.0)
    long = box_actor("Car", 0.0, -3.0, (20.0, 2.0, 1.5), 0)
    (obj,) = labels_of([long])
    assert obj.truncated == pytest.approx(truncated_by_definition(long), abs=0.04)


def wall(x: float, y: float, half: tuple[float, float, float], albedo: float = 0.4, range_noise: float = 0.0,
         yaw: float = 0.0) -> Primitive:
    """A scenery box standing on the flat road, turned ``yaw`` about z."""
    c, s = np.cos(yaw), np.sin(yaw)
    rotation = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    return Primitive(Shape.BOX, np.array([x, y, -HEIGHT + half[2]]), rotation, np.array(half),
                     Material((0.5, 0.5, 0.5), albedo=albedo, range_noise=range_noise))


def returns_on(points: np.ndarray, x_lo: float, x_hi: float) -> np.ndarray:
    """Scan points above the road (z > -1.5) whose x lies in [x_lo, x_hi]."""
    return points[(points[:, 0] >= x_lo) & (points[:, 0] <= x_hi) & (points[:, 2] > -1.5)]


def test_lidar_reach_grows_with_the_square_root_of_reflected_power() -> None:
    """Reach = 120 m · √(albedo · (0.3 + 0.7 cos) / 0.4): a dark wall (albedo 0.1) facing the sensor is seen
    at 45 m (reach 60 m), not at 75 m; a bright one (0.4) 108 m away, 22° to the side, only while it faces the
    sensor (cos 0.93: reach 117 m), not turned to cos 0.23 (power 0.46: reach 81 m). Its points lie on it,
    within the 2 cm range noise."""
    dark = [wall(45.0, -10.0, (0.2, 4.0, 1.5), albedo=0.1), wall(75.0, 10.0, (0.2, 6.0, 2.5), albedo=0.1)]
    bright = [wall(100.0, -40.0, (0.2, 6.0, 3.0)), wall(100.0, 40.0, (0.2, 6.0, 3.0), yaw=np.radians(-55))]
    points = scan(make_scene([], scenery=dark + bright), np.random.default_rng(0))
    seen_45 = returns_on(points, 44.0, 46.0)
    assert len(seen_45) > 100 and np.abs(seen_45[:, 0] - 44.8).max() < 0.1
    assert len(returns_on(points, 70.0, 80.0)) == 0
    far = returns_on(points, 94.0, 106.0)
    # The turned wall's broad face (y 36.6 … 43.4) stays dark; its 0.4 m end, facing the sensor, may return.
    assert (far[:, 1] < 0).sum() > 50 and (far[:, 1] > 37.5).sum() == 0


def test_no_return_nearer_than_1_5_m_and_ground_at_the_road() -> None:
    """KITTI scans hold nothing nearer than 1.5 m, even off a wall 1 m to the side; ground returns lie on the
    road surface z = z0 + slope·x + cross_slope·y (road.py), here a 4 % grade and 1.5 % cross slope."""
    road = flat_road(slope=0.04, cross_slope=0.015)
    points = scan(make_scene([], scenery=[wall(0.0, -1.2, (6.0, 0.2, 2.0))], road=road), np.random.default_rng(0))
    assert np.linalg.norm(points[:, :3], axis=1).min() >= 1.5 - 0.1  # the cut is on the true range: 2 cm noise
    assert len(points[np.abs(points[:, 1] + 1.0) < 0.05]) > 100  # the wall is there beyond 1.5 m
    ground = points[(points[:, 1] > 0.5) & (np.abs(points[:, 1]) < 6.5) & (np.hypot(points[:, 0], points[:, 1]) < 40)]
    surface = -HEIGHT + 0.04 * ground[:, 0] + 0.015 * ground[:, 1]
    assert len(ground) > 5000 and np.abs(ground[:, 2] - surface).max() < 0.1


def test_range_noise_is_2_cm_and_more_on_foliage() -> None:
    """Ranges carry 2 cm of Gaussian noise, plus a material's own (leaves: 8 cm more, σ = 10 cm in all)."""
    plain, leafy = wall(20.0, -4.0, (0.2, 3.0, 1.5)), wall(20.0, 4.0, (0.2, 3.0, 1.5), range_noise=0.08)
    points = scan(make_scene([], scenery=[plain, leafy]), np.random.default_rng(0))
    for y_sign, sigma in ((-1, 0.02), (1, 0.10)):
        on = returns_on(points, 19.0, 20.5)
        on = on[np.sign(on[:, 1]) == y_sign]
        # The wall's face is x = 19.8: along a ray, range error = x error / (x / range).
        error = (on[:, 0] - 19.8) * np.linalg.norm(on[:, :3], axis=1) / on[:, 0]
        assert len(on) > 200 and np.std(error) == pytest.approx(sigma, rel=0.2), y_sign
        # Every firing across the wall returns (1.5 % dropouts): its points reach both of its ends (y ± 3 m).
        assert on[:, 1].min() < 4 * y_sign - 2.95 and on[:, 1].max() > 4 * y_sign + 2.95


def test_reflectance_has_kitti_s_two_decimals() -> None:
    """KITTI stores reflectance in steps of 0.01, in [0, 1)."""
    points = scan(make_scene([NEAR], scenery=[wall(20.0, 4.0, (0.2, 3.0, 1.5))]), np.random.default_rng(0))
    hundredths = points[:, 3].astype(np.float64) * 100
    assert np.abs(hundredths - np.rint(hundredths)).max() < 1e-3
    assert points[:, 3].min() >= 0 and points[:, 3].max() < 1


@pytest.fixture(scope="module")
def frame():
    """One generated frame (a street with buildings, so every laser has returns)."""
    from simulation import generate_frame

    return generate_frame(31, 0)


def test_the_scan_has_the_hdl64e_s_lasers_and_firing_step(frame) -> None:
    """HDL-64E: an upper block of 32 lasers from +2° to −8.33° (≈ 1/3° apart) and a lower block of 32 from
    −8.83° to −24.9° (≈ 1/2°); 2000 firings per revolution (0.18°), one revolution per ring."""
    rings = recover_rings(frame.points)
    assert rings.n_rings == 64
    elevation = np.sort(rings.elevation_deg)[::-1]  # top laser first
    assert elevation[0] == pytest.approx(2.0, abs=0.15) and elevation[31] == pytest.approx(-8.33, abs=0.15)
    assert elevation[32] == pytest.approx(-8.83, abs=0.15) and elevation[63] == pytest.approx(-24.9, abs=0.15)
    np.testing.assert_allclose(np.diff(elevation[:32]), -10.33 / 31, atol=0.1)
    np.testing.assert_allclose(np.diff(elevation[32:]), -16.07 / 31, atol=0.1)
    azimuth = np.degrees(np.arctan2(frame.points[:, 1], frame.points[:, 0]))
    steps = np.diff(azimuth)[(rings.ring[1:] == rings.ring[:-1])]
    assert np.median(steps) == pytest.approx(0.18, abs=0.005)  # neighbouring returns: one firing apart
    assert np.median(steps[steps < 0.3]) == pytest.approx(0.18, abs=0.005)
    # Ring after ring, azimuth rising from −180° to +180° through each: exactly one wrap between rings, none inside.
    assert (np.abs(np.diff(azimuth)) > 180).sum() == 63 and (steps > -1e-3).all()
    # …so each ring found holds one laser's returns alone (none of the next laser's first firing, say).
    points = frame.points.astype(np.float64)
    own = np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))
    assert np.abs(own - rings.elevation_deg[rings.ring]).max() < 0.1


def test_the_road_is_1_73_m_under_the_sensor() -> None:
    """KITTI's velodyne is mounted 1.73 m above the road: every sampled road passes within a few cm of that
    height under the sensor (z0 has σ 2 cm)."""
    from simulation.layout import sample_road

    z0 = np.array([sample_road(np.random.default_rng(seed)).z0 for seed in range(40)])
    assert np.abs(z0 + HEIGHT).max() < 0.1 and z0.std() > 0.005


def test_calibration_jitter_keeps_camera_2_s_physics() -> None:
    """Per-frame calibrations differ as KITTI's drives do, but stay a camera: square pixels (fx = fy), camera 2
    still 6 cm left of the reference camera (K⁻¹ · P2[:, 3] unchanged whatever the focal length), rotations
    within 1° of the base (σ 0.15°), translations within centimetres (σ 1 cm)."""
    calibs = [sample_calibration(np.random.default_rng(seed)) for seed in range(40)]
    base_offset = np.linalg.solve(CALIB.P2[:, :3], CALIB.P2[:, 3])
    for c in calibs:
        assert c.P2[0, 0] == c.P2[1, 1] and c.P2[0, 1] == 0
        np.testing.assert_allclose(np.linalg.solve(c.P2[:, :3], c.P2[:, 3]), base_offset, atol=1e-9)
        for mine, base in ((c.R0_rect, CALIB.R0_rect), (c.Tr_velo_to_cam[:, :3], CALIB.Tr_velo_to_cam[:, :3])):
            cos = (np.trace(mine @ base.T) - 1) / 2
            assert np.degrees(np.arccos(min(cos, 1.0))) < 1.0
    shifts = np.array([c.Tr_velo_to_cam[:, 3] - CALIB.Tr_velo_to_cam[:, 3] for c in calibs])
    assert 0.005 < shifts.std() < 0.015
    assert len({c.P2[0, 0] for c in calibs}) == len(calibs)


def test_dense_depth_stops_at_250_m(two_cars) -> None:
    """The depth PNG holds metres × 256 in uint16 (< 256 m): ground truth stops at 250 m, while the flat road
    is seen out to the 400 m horizon."""
    depth = two_cars[1].depth
    assert 240 < depth.max() <= 250
    assert (depth == 0).any() and (depth[depth > 0] > 1).all()


def test_frames_of_neighbouring_seeds_are_not_shifted_copies() -> None:
    """Frame i of seed S comes from (S, i), not S + i: otherwise seed 2's frame 0 (val) would be seed 1's frame 1
    (train). The same (S, i) gives the same streams."""
    from simulation.frame import frame_rngs

    def draws(seed: int, index: int) -> np.ndarray:
        return np.concatenate([g.random(3) for g in frame_rngs(seed, index).values()])

    np.testing.assert_array_equal(draws(1, 1), draws(1, 1))
    assert not np.isin(draws(2, 0), draws(1, 1)).any() and not np.isin(draws(1, 0), draws(0, 1)).any()


def test_a_frame_with_a_file_missing_is_made_again_and_stale_scratch_of_its_run_removed(
        tmp_path, caplog: pytest.LogCaptureFixture) -> None:
    """A frame counts as written only with all five files (depth_2 alone is not enough); the scratch folders a
    killed run left are removed for the frames this run makes, not for others (another run may be making
    those). Into a KITTI ``training`` folder, the log says where OpenPCDet reads split lists."""
    import logging

    from simulation import RunConfig, run

    out = tmp_path / "root" / "training"
    run(RunConfig(out=out, frames=1, seed=5, progress=False))
    (out / "label_2" / "000000.txt").unlink()
    mine, other = out / ".partial-000000-abc", out / ".partial-000007-def"
    mine.mkdir()
    other.mkdir()
    with caplog.at_level(logging.INFO, logger="simulation.run"):
        result = run(RunConfig(out=out, frames=1, seed=5, progress=False))
    assert len(result.seconds_per_frame) == 1 and (out / "label_2" / "000000.txt").is_file()
    assert not mine.exists() and other.exists()
    assert f"OpenPCDet and mmdetection3d read {tmp_path / 'root' / 'ImageSets' / 'train.txt'}" in caplog.text


def test_run_options_that_would_write_nothing_are_refused(tmp_path) -> None:
    """No frames, no workers or a negative first frame: one line naming the flag, before any folder is made (a
    negative --start from Python used to reach NumPy's "expected non-negative integer" after making the
    folders and an empty split list)."""
    from simulation import RunConfig, run

    with pytest.raises(ValueError, match="--start: must be 0 or more, got -1"):
        run(RunConfig(out=tmp_path / "c", frames=1, seed=1, start=-1, progress=False))

    with pytest.raises(ValueError, match="--frames: need at least 1 frame, got 0"):
        run(RunConfig(out=tmp_path / "a", frames=0, seed=1, progress=False))
    with pytest.raises(ValueError, match="--workers: need at least 1 worker, got 0"):
        run(RunConfig(out=tmp_path / "b", frames=1, seed=1, workers=0, progress=False))
    assert list(tmp_path.iterdir()) == []


def test_the_command_line_passes_start_split_and_imagesets_on(tmp_path, capsys: pytest.CaptureFixture) -> None:
    """`--start 999999 --frames 1` is the last six-digit id (allowed); `--split` and `--imagesets` name the list;
    `--no-progress` draws no bar; an --out that is a file is one `error:` line and status 2."""
    from simulation.__main__ import main

    out, lists = tmp_path / "sim", tmp_path / "sets"
    assert main(["--out", str(out), "--frames", "1", "--seed", "3", "--start", "999999", "--split", "val",
                 "--imagesets", str(lists), "--no-progress"]) == 0
    assert (lists / "val.txt").read_text() == "999999\n" and not (out / "ImageSets").exists()
    assert sorted(p.name for p in (out / "velodyne").iterdir()) == ["999999.bin"]
    assert "simulating" not in capsys.readouterr().err
    (tmp_path / "file").write_text("")
    assert main(["--out", str(tmp_path / "file"), "--frames", "1", "--seed", "3", "--no-progress"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        f"error: --out {tmp_path / 'file'}: exists and is not a directory"]


def pixel(point: tuple[float, float, float]) -> np.ndarray:
    """(u, v) of one LiDAR-frame point."""
    return project(velo_to_rect(np.array([point], float)))[0]


def test_occlusion_level_and_dont_care_from_what_a_wall_hides() -> None:
    """Thin boxes 30 m ahead, their right parts behind walls 15 m ahead, and one 70 m ahead behind a low wall:
    the hidden share of each silhouette (from the projected edges) gives the level; more than 90 % hidden → a
    DontCare box around the visible sliver; the 8 px rule applies to the whole silhouette, not to the part left
    visible."""
    targets = [box_actor("Car", 30.0, y, (0.3, 2.0, 1.5), i) for i, y in enumerate((8.0, 0.0, -8.0))]
    low = box_actor("Car", 70.0, -12.0, (0.3, 2.0, 1.5), 3)
    # Each wall's left edge (its +y side) at 15 m hides about 35 %, 70 % and 97 % of a target's width.
    edges = [(y - 1 + 2 * share) / 2 for y, share in ((8.0, 0.35), (0.0, 0.7), (-8.0, 0.97))]
    walls = [wall(15.0, edge - 1.0, (0.05, 1.0, 3.0)) for edge in edges]
    walls.append(wall(35.0, -6.0, (0.05, 2.0, (HEIGHT - 0.455) / 2)))  # top at z = -0.455: hides z < -0.83 at 70 m
    scene = make_scene([], scenery=walls, road=flat_road(lanes_left=4, lanes_right=4))  # all on the carriageway
    scene.actors.extend([*targets, low])
    scene.primitives.extend(p for a in (*targets, low) for p in a.primitives)
    objects = label_objects(scene, render(scene, CALIB, np.random.default_rng(0)), CALIB)
    cars = {round(float(o.location[0])): o for o in objects if o.type == "Car"}

    hidden = []
    for target, edge in zip(targets, edges):
        y = target.bottom[1]
        left, right = pixel((29.85, y + 1.0, -1.0))[0], pixel((29.85, y - 1.0, -1.0))[0]
        hidden.append(float(np.clip((right - pixel((14.95, edge, -1.0))[0]) / (right - left), 0, 1)))
    assert cars[-8].occluded == occlusion_level(hidden[0]) == 1, (hidden, cars)
    assert cars[0].occluded == occlusion_level(hidden[1]) == 2, (hidden, cars)
    assert hidden[2] > 0.9 and 8 not in cars
    dont_care = [o for o in objects if o.type == "DontCare"]
    assert len(dont_care) == 1
    left, _, right, _ = dont_care[0].bbox
    assert right - left < 0.2 * (pixel((29.85, -9.0, -1.0))[0] - pixel((29.85, -7.0, -1.0))[0])  # the sliver
    top, bottom = pixel((69.85, -12.0, -0.23))[1], pixel((69.85, -12.0, -HEIGHT))[1]
    assert bottom - top > 8 and cars[12].occluded == 2, cars  # 15 px tall, its lower ~60 % hidden


def test_ray_entry_distances_normals_and_near_plane_clipping() -> None:
    """A ray along x meets a unit box, cylinder or ball centred 10 m ahead at 9 m (its entry, not its exit); one
    passing 1.5 m above a cylinder's 1 m half-length misses it; a box's normal on its long side is that side's;
    the part of a cube in front of a plane keeps its 4 corners there and the 4 edge crossings on the plane."""
    from simulation.geometry import UNIT_CORNERS, clip_box_to_near, intersect, surface_normals

    origin = np.zeros(3)
    ahead, above = np.array([[1.0, 0.0, 0.0]]), np.array([[10.0, 0.0, 1.5]])
    for shape in Shape:
        solid = Primitive(shape, np.array([10.0, 0, 0]), np.eye(3), np.ones(3), Material((0.5, 0.5, 0.5)))
        assert intersect(solid, origin, ahead)[0] == pytest.approx(9.0), shape
        # Aimed 1.5 m above the centre: over every solid of half-size 1 (the ball and the cylinder too).
        assert intersect(solid, origin, above / np.linalg.norm(above))[0] == np.inf, shape
    cap = Primitive(Shape.CYLINDER, np.array([10.0, 0, -3.0]), np.eye(3), np.array([1.0, 1.0, 1.0]),
                    Material((0.5, 0.5, 0.5)))
    down = np.array([[0.0, 0.0, -1.0]])
    assert intersect(cap, np.array([10.5, 0.0, 0.0]), down)[0] == pytest.approx(2.0)  # enters through its top
    assert intersect(cap, np.array([11.6, 0.0, 0.0]), down)[0] == np.inf  # beside it
    long = Primitive(Shape.BOX, np.zeros(3), np.eye(3), np.array([2.0, 0.5, 0.5]), Material((0.5, 0.5, 0.5)))
    normal, _ = surface_normals(long, np.array([[1.5, 0.5, 0.0], [2.0, 0.3, 0.1]]))
    np.testing.assert_allclose(normal, [[0, 1, 0], [1, 0, 0]])
    clipped = clip_box_to_near(UNIT_CORNERS, UNIT_CORNERS[:, 0], 0.0)
    assert len(clipped) == 8 and (clipped[:, 0] >= 0).all()
    np.testing.assert_allclose(np.sort(np.abs(clipped[clipped[:, 0] == 0][:, 1:]).ravel()), np.ones(8))
    shifted = clip_box_to_near(UNIT_CORNERS, UNIT_CORNERS[:, 0], 0.5)
    np.testing.assert_allclose(np.sort(shifted[:, 0]), [0.5] * 4 + [1.0] * 4)


def test_placed_objects_stand_on_the_surface_the_rays_hit() -> None:
    """road.place puts a point ``lateral`` metres off the centre line (on its perpendicular) at the ground height
    that rays meet there: the carriageway, or 15 cm higher on the sidewalk beyond the curb."""
    road = flat_road(slope=0.03, cross_slope=-0.012, heading=0.3, bend_v=1e-4, y0=1.0)
    for along, lateral in ((20.0, 3.0), (35.0, -5.0), (15.0, 8.0)):
        x, y, z, heading = road.place(along, lateral)
        assert heading == pytest.approx(np.arctan(0.3))
        # On a straight road the perpendicular foot is (along, centre_y(along)).
        assert np.hypot(x - along, y - road.centre_y(along)) == pytest.approx(abs(lateral))
        assert road.lateral(np.array([x]), np.array([y]))[0] == pytest.approx(lateral)
        surface = -HEIGHT + 0.03 * x + 1e-4 * x * x - 0.012 * y + (0.15 if abs(lateral) > 7.0 else 0.0)
        assert z == pytest.approx(surface)
        t = road.intersect(np.array([x, y, 10.0]), np.array([[0.0, 0.0, -1.0]]))[0]
        assert 10.0 - t == pytest.approx(z, abs=1e-6)


def test_a_car_s_windscreen_and_rear_window_lean_onto_its_cabin() -> None:
    """The sloped glass slabs lean in: the top of each is nearer the cabin than its bottom (a saloon's profile)."""
    car = make_scene([("Car", (10.0, 0.0), 0.0, (4.4, 1.7, 1.5))]).actors[0]
    glass = [p for p in car.primitives if p.material == shapes.GLASS]
    cabin = next(p for p in glass if np.allclose(p.rotation, np.eye(3)))
    slabs = [p for p in glass if p is not cabin]
    assert len(slabs) == 2
    for slab in slabs:
        top = slab.centre + slab.rotation @ [0, 0, slab.half[2]]
        bottom = slab.centre - slab.rotation @ [0, 0, slab.half[2]]
        assert abs(top[0] - cabin.centre[0]) < abs(bottom[0] - cabin.centre[0]) - 0.3
