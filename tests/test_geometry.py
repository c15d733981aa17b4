import math

import numpy as np
import pytest

from satloc import ConfigError, Pose2, SatelliteMap, StereoCamera, wrap_angle


def random_poses(rng, n=20):
    return [Pose2(*rng.uniform(-100, 100, 2), rng.uniform(-4, 4)) for _ in range(n)]


def test_wrap_angle_range():
    a = np.linspace(-20, 20, 1001)
    w = wrap_angle(a)
    assert np.all(w > -math.pi) and np.all(w <= math.pi)
    assert np.allclose(np.sin(w), np.sin(a)) and np.allclose(np.cos(w), np.cos(a))
    assert wrap_angle(-math.pi) == pytest.approx(math.pi)


def test_pose_inverse_and_composition_round_trip():
    rng = np.random.default_rng(0)
    for a, b in zip(random_poses(rng), random_poses(rng)):
        ident = a @ a.inverse()
        assert abs(ident.x) < 1e-9 and abs(ident.y) < 1e-9 and abs(ident.yaw) < 1e-9
        rel = a.between(b)
        back = a @ rel
        assert back.distance(b) < 1e-9 and abs(wrap_angle(back.yaw - b.yaw)) < 1e-9
        assert np.allclose(Pose2.from_matrix(a.matrix() @ b.matrix()).as_array(), (a @ b).as_array())


def test_pose_point_transforms_round_trip():
    rng = np.random.default_rng(1)
    pts = rng.uniform(-50, 50, (100, 2))
    for p in random_poses(rng, 5):
        assert np.allclose(p.transform_inv(p.transform(pts)), pts)
        h = np.c_[pts, np.ones(len(pts))] @ p.matrix().T
        assert np.allclose(h[:, :2], p.transform(pts))


def test_pose_known_values():
    p = Pose2(10, 5, math.pi / 2)
    assert np.allclose(p.transform(np.array([1.0, 0.0])), [10, 6])  # forward is north
    assert np.allclose(p.transform(np.array([0.0, 1.0])), [9, 5])   # left is west
    with pytest.raises(ValueError):
        Pose2.from_array([1, 2])


def test_camera_projection_round_trip_and_known_point():
    cam = StereoCamera.kitti()
    pose = Pose2(3.0, -2.0, 0.4)
    rng = np.random.default_rng(2)
    uv = np.c_[rng.uniform(0, cam.width, 50), rng.uniform(0, cam.height, 50)]
    depth = rng.uniform(2, 80, 50)
    for side in ("left", "right"):
        pts = cam.pixels_to_map(pose, uv, depth, side)
        uv2, d2 = cam.map_to_pixels(pose, pts, side)
        assert np.allclose(uv2, uv) and np.allclose(d2, depth)
    # a ground point 10 m straight ahead of the left camera (pitch 0): below the principal point by fy*h/10
    uv, z = cam.map_to_pixels(Pose2(0, 0, 0), np.array([[10.0, 0.0, 0.0]]))
    assert np.allclose(uv[0], [cam.cx, cam.cy + cam.fy * 1.65 / 10]) and z[0] == pytest.approx(10.0)
    # the right camera sees it shifted left by the disparity fx * b / z
    uvr, _ = cam.map_to_pixels(Pose2(0, 0, 0), np.array([[10.0, 0.0, 0.0]]), "right")
    assert uv[0, 0] - uvr[0, 0] == pytest.approx(cam.fx * cam.baseline / 10)


def test_camera_pitch_looks_down():
    cam = StereoCamera(640, 480, 500, 500, 319.5, 239.5, 0.5, 1.5, pitch=math.radians(10))
    # the optical axis hits the ground at h / tan(pitch) ahead
    ahead = 1.5 / math.tan(math.radians(10))
    uv, _ = cam.map_to_pixels(Pose2(), np.array([[ahead, 0.0, 0.0]]))
    assert np.allclose(uv[0], [319.5, 239.5])
    vfc = cam.vehicle_from_camera()
    assert np.allclose(vfc[:3, :3] @ vfc[:3, :3].T, np.eye(3)) and np.linalg.det(vfc[:3, :3]) == pytest.approx(1)


def test_camera_presets_and_errors():
    half = StereoCamera.kitti_half()
    assert (half.width, half.height) == (620, 188)
    assert half.fx == pytest.approx(StereoCamera.kitti().fx / 2)
    assert half.disparity_to_depth(np.array([half.fx * half.baseline / 5.0, 0.0]))[0] == pytest.approx(5.0)
    with pytest.raises(ConfigError, match="preset"):
        StereoCamera.preset("quarter")
    with pytest.raises(ConfigError, match="baseline"):
        StereoCamera(10, 10, 1, 1, 5, 5, 0.0)


def test_satellite_map_pixel_round_trip_and_convention():
    img = np.zeros((100, 200, 3), np.uint8)
    sm = SatelliteMap(img, 0.2, (50.0, 30.0))
    assert sm.extent == pytest.approx((50.0, 90.0, 10.0, 30.0))
    assert np.allclose(sm.pixel_to_world(np.array([0.0, 0.0])), [50.1, 29.9])  # centre of the top-left pixel
    rng = np.random.default_rng(3)
    xy = np.c_[rng.uniform(50, 90, 30), rng.uniform(10, 30, 30)]
    assert np.allclose(sm.pixel_to_world(sm.world_to_pixel(xy)), xy)
    assert sm.contains(np.array([60.0, 20.0])) and not sm.contains(np.array([49.0, 20.0]))


def test_satellite_map_save_load(tmp_path):
    rng = np.random.default_rng(4)
    img = rng.integers(0, 255, (40, 60, 3), dtype=np.uint8)
    lab = rng.integers(0, 5, (40, 60), dtype=np.uint8)
    SatelliteMap(img, 0.25, (1.0, 2.0), lab).save(tmp_path / "m")
    sm = SatelliteMap.load(tmp_path / "m")
    assert np.array_equal(sm.image, img) and np.array_equal(sm.labels, lab)
    assert sm.meters_per_pixel == 0.25 and sm.origin == (1.0, 2.0)


def test_satellite_map_crop_centre():
    img = np.zeros((101, 101, 3), np.uint8)
    img[50, 50] = 255
    sm = SatelliteMap(img, 1.0, (0.0, 101.0))
    c = sm.crop(sm.pixel_to_world(np.array([50.0, 50.0])), 21.0, out_px=21)
    assert c[10, 10, 0] == 255 and c.sum() == 3 * 255
