"""Ground that is not a plane (satloc_env.world.terrain): heights, the world standing on them, the car's tilt."""
import copy

import numpy as np
import pytest
import yaml

from satloc import ConfigError
from satloc.geometry import StereoCamera
from satloc.labels import CLASS_ID
from satloc_env.world.meshes import GROUND, load_world, save_world
from satloc_env.world.scene import load_scene
from satloc_env.world.terrain import TRACK_M, WHEELBASE_M, Terrain

SMALL = {
    "name": "hills", "seed": 3,
    "generator": {"type": "grid", "style": "city", "blocks": [2, 2], "pitch_m": 60, "margin_m": 10, "variety": 1.0},
    "meters_per_pixel": 0.2, "ground_mpp": 0.2,
    "routes": {"main": {"waypoints": [[10, 10], [130, 10], [130, 130], [10, 130]], "closed": True}},
    "terrain": {"relief_m": 1.5, "wavelength_m": 150},
}


def write(tmp_path, data, name="s.yaml"):
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data))
    return p


def test_heights_are_gentle_hills_drawn_from_the_seed():
    t = Terrain(1.5, 250.0, seed=4)
    x, y = np.meshgrid(np.linspace(0, 2000, 300), np.linspace(0, 2000, 300))
    h = t.height(x, y)
    assert 1.0 < h.std() < 2.2                                     # the relief asked for
    gy, gx = np.gradient(h, 2000 / 299)
    grade = np.hypot(gx, gy)
    assert 0.01 < np.percentile(grade, 95) < 0.09 and grade.max() < 0.15   # a street's grades, not a mountain's
    assert np.array_equal(h, Terrain(1.5, 250.0, seed=4).height(x, y))
    assert not np.allclose(h, Terrain(1.5, 250.0, seed=5).height(x, y))
    assert not Terrain().height(x, y).any() and Terrain().flat
    assert Terrain().tilt(3.0, 4.0, 1.0) == (0.0, 0.0, 0.0)
    for bad in ({"relief_m": -1.0}, {"wavelength_m": 5.0}, {"relief_m": "high"}):
        with pytest.raises(ConfigError, match=r"terrain\.(relief_m|wavelength_m)"):
            Terrain(**bad)


def test_a_car_on_a_slope_pitches_and_rolls_with_it():
    t = Terrain(2.0, 200.0, seed=1)
    rng = np.random.default_rng(0)
    for x, y, yaw in rng.uniform([0, 0, -np.pi], [400, 400, np.pi], (20, 3)):
        z, pitch, roll = t.tilt(x, y, yaw)
        c, s = np.cos(yaw), np.sin(yaw)
        ahead = (t.height(x + c, y + s) - t.height(x - c, y - s)) / 2       # the grade, per metre ahead
        left = (t.height(x - s, y + c) - t.height(x + s, y - c)) / 2
        assert pitch == pytest.approx(-np.arctan(ahead), abs=2e-3)        # uphill: nose up (pitch < 0)
        assert roll == pytest.approx(np.arctan(left), abs=2e-3)            # ground rising to the left: left up
        assert z == pytest.approx(float(t.height(x, y)), abs=0.02)
    assert WHEELBASE_M > TRACK_M > 1.0


def _ground_start(chunk) -> int:
    """The first face of a chunk's ground: its cells of band GROUND, after the objects'."""
    return int(chunk.cell_faces[np.flatnonzero(chunk.cell_bands == GROUND)[0]])


def test_the_world_stands_on_the_terrain_and_the_camera_sees_it(tmp_path):
    s = load_scene(write(tmp_path, SMALL))
    terrain = s.world.terrain
    assert terrain == Terrain(1.5, 150.0, 3)
    assert s.summary()["terrain"] == {"relief_m": 1.5, "wavelength_m": 150}
    ground = s.world.chunks[0]
    gpos = ground.positions[ground.faces[_ground_start(ground):].ravel()]       # the ground's cells, the last
    assert len(np.unique(gpos[:, :2], axis=0)) > 4                              # a grid, not one quad
    assert np.allclose(gpos[:, 2], terrain.height(gpos[:, 0], gpos[:, 1]), atol=1e-4)
    assert np.ptp(gpos[:, 2]) > 1.0
    # a building stands level on the lowest ground under its footprint, a tree on the ground under it
    import dataclasses

    from satloc_env.world.meshes import build_world

    b = s.layout.buildings[0]
    t = s.layout.trees[0]
    one = build_world(dataclasses.replace(s.layout, buildings=[b], trees=[], cars=[], furniture=[]), terrain=terrain)
    objects = lambda c: c.positions[c.faces[:_ground_start(c)].ravel()]  # noqa: E731
    p = objects(one.chunks[0])
    under = terrain.height(p[:, 0], p[:, 1])
    base = p[:, 2] <= p[:, 2].min() + 1e-4
    assert base.sum() >= 3 and (p[base, 2] <= under[base] + 1e-4).all()
    assert p[base, 2].min() == pytest.approx(under[base].min(), abs=1e-3)
    tree = build_world(dataclasses.replace(s.layout, buildings=[], trees=[t], cars=[], furniture=[]), terrain=terrain)
    p = objects(tree.chunks[0])
    low = p[:, 2] - terrain.height(p[:, 0], p[:, 1])
    assert np.abs(low.min()) < 1e-3 and (low > -1e-3).all()       # the trunk's foot on the ground, none below
    # the camera's depth: the ground it sees lies on the terrain, seen from a car standing on it
    from satloc_env.render.stereo import StereoRenderer

    cam = StereoCamera.kitti_half()
    route = s.routes["main"]
    with StereoRenderer(s.world, cam) as r:
        heights = []
        for d in np.linspace(5, route.length - 5, 6):
            pose = route.pose_at(float(d), -1.75)
            out = r.render(pose, depth=True, labels=True)
            road = np.isin(out["labels_left"], [CLASS_ID[k] for k in ("road", "lane_marking", "sidewalk")])
            v, u = np.nonzero(road & (out["depth_left"] > 0) & (out["depth_left"] < 25))
            pts = cam.backproject(np.stack([u, v], 1).astype(np.float64), out["depth_left"][v, u].astype(np.float64))
            m = r._slot._map_from_camera(pose, "left", None)
            world = pts @ m[:3, :3].T + m[:3, 3]
            inside = (world[:, :2] > 0).all(1) & (world[:, :2] < [s.world.width_m, s.world.height_m]).all(1)
            assert inside.sum() > 1000      # (beyond the layout's edge the world is its mirror image)
            gap = world[inside, 2] - terrain.height(world[inside, 0], world[inside, 1])
            assert np.abs(gap).max() < 0.1  # the ground's grid departs from the hills by centimetres
            vehicle = pts @ cam.vehicle_from_camera("left")[:3, :3].T + cam.vehicle_from_camera("left")[:3, 3]
            heights.append(np.abs(vehicle[:, 2]).max())
    assert max(heights) > 0.1      # in the car's frame the ground ahead is not its wheels' plane
    # saved and loaded with the world
    save_world(s.world, tmp_path / "w.npz")
    assert load_world(tmp_path / "w.npz").terrain == terrain


def test_a_flat_terrain_builds_the_flat_world_and_bad_values_are_named(tmp_path):
    d = copy.deepcopy(SMALL)
    d["terrain"] = {"relief_m": 0.0}
    flat = load_scene(write(tmp_path, d, "flat.yaml"))
    del d["terrain"]
    plain = load_scene(write(tmp_path, d, "plain.yaml"))
    for a, b in zip(flat.world.chunks, plain.world.chunks):
        assert np.array_equal(a.positions, b.positions) and np.array_equal(a.faces, b.faces)
    d["terrain"] = {"relief_m": 100.0}
    with pytest.raises(ConfigError, match=r"bad\.yaml.*terrain\.relief_m"):
        load_scene(write(tmp_path, d, "bad.yaml"))
    d["terrain"] = {"relief": 1.0}
    with pytest.raises(ConfigError, match=r"relief"):
        load_scene(write(tmp_path, d, "bad2.yaml"))


def test_the_environment_drives_over_hills(tmp_path):
    """SatLoc-v0 on a scene with a terrain, the body's own attitude on top: steps render, the same seed gives
    the same frames, and they differ from the same scene's on a plane."""
    import gymnasium as gym

    import satloc_env  # noqa: F401

    flat = copy.deepcopy(SMALL)
    del flat["terrain"]
    frames = {}
    for name, d in (("hills", SMALL), ("flat", flat)):
        path = write(tmp_path, d, f"{name}.yaml")
        env = gym.make("satloc/SatLoc-v0", scene=str(path), localizer=None, attitude=1.0, max_steps=10)
        runs = []
        for _ in range(2):
            obs, info = env.reset(seed=3)
            for _ in range(3):
                obs, _, _, _, info = env.step(env.unwrapped.autopilot_action())
            runs.append(obs["left"].copy())
        env.close()
        assert np.array_equal(runs[0], runs[1])
        frames[name] = runs[0]
    assert np.abs(frames["hills"].astype(int) - frames["flat"].astype(int)).mean() > 2.0


def test_a_road_falls_from_its_crown_to_its_kerbs():
    from satloc_env.world.terrain import Crown

    mpp, camber = 0.1, 0.02
    labels = np.full((600, 800), CLASS_ID["sidewalk"], np.uint8)      # 60 m x 80 m
    labels[:, 200:320] = CLASS_ID["road"]                              # a street 12 m wide from x = 20 m to 32 m
    labels[:, 259:261] = CLASS_ID["lane_marking"]                      # its centre line: still the road
    labels[400:520, :] = CLASS_ID["road"]                              # a cross street, y = 8 to 20 m
    crown = Crown.of(labels, mpp, camber)
    assert np.allclose(crown.xlines, [20.0, 26.0, 32.0])                # edges and the centre line
    assert np.allclose(crown.ylines, [8.0, 14.0, 20.0])
    y = np.full(5, 45.0)
    h = crown.height(np.array([10.0, 20.0, 23.0, 26.0, 29.0]), y)
    assert h[0] == 0.0 and h[1] == pytest.approx(0.0, abs=4e-3)         # off the road, at its kerb
    assert h[3] == pytest.approx(camber * 6.0, abs=5e-3)                # the crown: 12 cm at 2 %
    assert h[2] == pytest.approx(camber * 3.0, abs=3e-3) and h[4] == pytest.approx(h[2], abs=2e-3)
    assert crown.height(np.array([26.0]), np.array([14.0]))[0] <= camber * 10.0 + 1e-6   # the crossing: capped
    with pytest.raises(ConfigError, match=r"terrain\.camber"):
        Terrain(camber=0.5)


def test_a_cambered_street_rolls_the_car_and_is_saved_with_the_world(tmp_path):
    data = copy.deepcopy(SMALL)
    data["terrain"] = {"relief_m": 0.0, "wavelength_m": 150, "camber": 0.02}
    s = load_scene(write(tmp_path, data))
    terrain = s.world.terrain
    assert not terrain.flat and terrain.crown is not None and len(terrain.crown.xlines) >= 3
    assert s.summary()["terrain"]["camber"] == 0.02
    # the ground's grid has vertices on the crown's lines, so its surface is the crown's heights
    ground = s.world.chunks[0]
    gpos = ground.positions[ground.faces[_ground_start(ground):].ravel()]
    assert np.allclose(gpos[:, 2], terrain.height(gpos[:, 0], gpos[:, 1]), atol=1e-4)
    centre = (np.abs(gpos[:, 1] - 10.0) < 1e-3) & (gpos[:, 0] > 20.0) & (gpos[:, 0] < 60.0)   # a street's centre
    assert centre.any() and np.allclose(gpos[centre, 2], 0.02 * 6.0, atol=6e-3)                # line: its crown
    tri = ground.positions[ground.faces[_ground_start(ground):]].astype(np.float64)
    inner = tri.mean(axis=1)                                             # each triangle's centroid, and its surface
    gap = np.abs(inner[:, 2] - terrain.height(inner[:, 0], inner[:, 1]))
    assert np.percentile(gap, 90) < 0.05 * 0.12 and gap.max() < 0.05    # within 5 % of the crown (crossings: more)
    # a car in the right lane of a straight street stands on the lane's fall: its left side up by atan(camber)
    route = s.routes["main"]
    pose = route.pose_at(40.0, -1.75)
    assert terrain.tilt(pose.x, pose.y, pose.yaw)[2] == pytest.approx(np.arctan(0.02), abs=1e-3)
    left = route.pose_at(40.0, 1.75)
    assert terrain.tilt(left.x, left.y, left.yaw)[2] == pytest.approx(-np.arctan(0.02), abs=1e-3)
    save_world(s.world, tmp_path / "w.npz")
    back = load_world(tmp_path / "w.npz").terrain
    x, y = np.meshgrid(np.linspace(0, 140, 50), np.linspace(0, 140, 50))
    assert back == terrain and np.array_equal(back.height(x, y), terrain.height(x, y))
