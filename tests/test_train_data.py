"""What each training sample holds: which scan, which target, which car pixels, pixel ranges (mutation audit)."""

import numpy as np
import pytest

from models.data import (
    DepthDataset,
    SampleCache,
    car_boxes,
    car_pixels,
    depth_target,
    detector_clouds,
    frame_points,
)
from pipeline.beams import emulate_beams
from pipeline.frame import Frame, load_frame
from pipeline.kitti import Object3D, read_depth_png
from pipeline.preprocess import depth_view
from pipeline.presets import PRESETS
from tests.conftest import KITTI


@pytest.fixture(scope="module")
def sim_frame(tmp_path_factory):
    from simulation.run import RunConfig, run

    out = tmp_path_factory.mktemp("sim")
    run(RunConfig(out, frames=1, seed=2, start=0, split="val", progress=False))
    return out


def test_the_depth_target_is_the_dense_ground_truth_when_the_folder_has_it(sim_frame):
    preset = PRESETS["tiny"]
    frame_id = min(p.stem for p in (sim_frame / "depth_2").glob("*.png"))
    expected = depth_view(read_depth_png(sim_frame / "depth_2" / f"{frame_id}.png"), preset)
    target = DepthDataset(sim_frame, [frame_id], preset)[0][2][0].numpy()
    np.testing.assert_array_equal(target, expected)
    assert (target > 0).mean() > 0.5  # dense, not the scan's projection
    assert (depth_target(sim_frame, load_frame(sim_frame, frame_id), preset) > 0).mean() > 0.5


def test_scans_are_thinned_to_the_asked_lines_and_lidar64_is_never_thinned():
    frame = load_frame(KITTI, "000006", with_image=False)
    np.testing.assert_array_equal(frame_points(frame, 32), emulate_beams(frame.points, 32))
    assert len(emulate_beams(frame.points, 16)) < len(frame_points(frame, 32)) < len(frame.points)
    np.testing.assert_array_equal(frame_points(frame, 0), frame.points)
    _, scan = detector_clouds(frame, PRESETS["edge"], "lidar64", None, beams=16)
    np.testing.assert_array_equal(scan, frame.points)


def test_augmented_pixels_stay_in_the_cameras_range():
    """Brightness augmentation clips to [0, 255], the range every pixel the runtime sees is in."""
    dataset = DepthDataset(KITTI, ["000006"], PRESETS["tiny"], augment=True)
    brightest = []
    for epoch in range(8):
        dataset.epoch = epoch
        rgb = dataset[0][0]
        assert float(rgb.min()) >= 0.0 and float(rgb.max()) <= 255.0
        brightest.append(float(rgb.max()))
    assert max(brightest) == 255.0  # some epoch brightens the sky into the clip


def test_car_pixels_are_the_cars_boxes_in_the_view_on_the_cars_depths():
    """Two overlapping Car boxes at 10 m and 20 m, a Pedestrian's box at 10 m: the car pixels are the union of
    each car's box moved into the network's view (the bottom 352 rows, the centre 1216 columns, scaled) where
    the target is at that car's depth."""
    preset = PRESETS["tiny"]  # input_scale 0.25
    scale = preset.depth.input_scale
    top, left = 375 - 352, (1242 - 1216) // 2  # 23, 13
    h, w = preset.depth.input_hw
    target = np.full((h, w), 10.0, np.float32)
    target[:, 40:] = 20.0

    def label(kind: str, view_box: tuple[int, int, int, int], z: float) -> Object3D:
        """A label whose image box is the view's pixel box (left, top, right, bottom) before the crop and scale."""
        c0, r0, c1, r1 = view_box
        bbox = (c0 / scale + left, r0 / scale + top, c1 / scale + left, r1 / scale + top)
        return Object3D(kind, 0.0, 0, 0.0, bbox, (1.5, 1.6, 3.9), (0.0, 1.6, z), 0.0)

    labels = [label("Car", (20, 30, 50, 40), 10.0), label("Car", (30, 35, 60, 45), 20.0),
              label("Pedestrian", (0, 0, 10, 10), 10.0)]
    frame = Frame("000000", None, np.zeros((0, 4), np.float32), None, labels, size_hw=(375, 1242))
    expected = np.zeros((h, w), bool)
    # The pixels whose centres lie in each box, the box being the view box shifted by the offset (s − 1)/2 = −0.375
    # (until session 50 also a ring of one pixel around it: [29:41, 19:40] and [34:46, 40:61]).
    expected[30:40, 20:40] = True  # first car's box, 19.625 … 49.625 × 29.625 … 39.625, where the target is 10 m
    expected[35:45, 40:60] = True  # second car's box, 29.625 … 59.625 × 34.625 … 44.625, where it is 20 m
    np.testing.assert_array_equal(car_pixels(frame, target, preset), expected)


def test_detector_targets_are_of_the_cars_alone():
    frame = load_frame(KITTI, "000001", with_image=False)  # a Car, a Cyclist, a Truck
    boxes = car_boxes(frame)
    assert boxes.shape == (1, 7)
    car = next(o for o in frame.labels if o.type == "Car")
    assert boxes[0, 3:6] == pytest.approx([car.dimensions[2], car.dimensions[1], car.dimensions[0]], abs=1e-5)


def test_sample_cache_keeps_a_sample_that_fills_its_budget_exactly():
    item = (np.zeros(10, np.float32), np.zeros(6, np.uint8))  # 46 bytes
    cache = SampleCache(max_bytes=46)
    cache.get(0, lambda index: item)
    assert list(cache.items) == [0] and cache.nbytes == 46
    cache.get(1, lambda index: item)
    assert list(cache.items) == [0] and cache.nbytes == 46  # the next one is loaded, not kept
