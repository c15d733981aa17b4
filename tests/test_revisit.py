"""Revisits that change (satloc_env.world.revisit): the layout function, the env's ``change`` knob, the recorded
query pass and the example script, on one-block scenes (they load in under a second)."""
import hashlib
import importlib.util
import json
import math
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from test_env import run

import satloc_env  # noqa: F401  (registers the ids)
from satloc import ConfigError
from satloc.config import to_dict
from satloc.labels import CLASS_ID as C
from satloc.labels import DRIVABLE
from satloc_env.envs.record import QUERY_CHANGE, PassConfig, RecordConfig, record_passes
from satloc_env.world.generator import GridParams, generate_grid
from satloc_env.world.revisit import changed_layout, changed_world
from satloc_env.world.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent

SCENE = """\
name: tinyres
seed: 2
generator: {type: grid, style: residential, blocks: [1, 1], pitch_m: 78, road_width_m: 12, sidewalk_m: 2.5,
            margin_m: 12}
meters_per_pixel: 0.2
ground_mpp: 0.1
routes:
  main:
    waypoints: [[12, 12], [90, 12], [90, 90], [12, 90]]
    closed: true
lighting: {sun_azimuth_deg: 210, sun_elevation_deg: 40}
knobs: {aliasing: 0.0, occlusion: 0.0, appearance: 0.0}
"""


@pytest.fixture(scope="module")
def scene_path(tmp_path_factory) -> str:
    p = tmp_path_factory.mktemp("scene") / "tinyres.yaml"
    p.write_text(SCENE)
    return str(p)


@pytest.fixture(scope="module")
def lots():
    """A one-block city layout with a parking lot (15 cars in stalls, 4 at the curb)."""
    return generate_grid(GridParams("city", (1, 1), 78.0, 12.0, 2.5, 12.0), 5, 0.0, 0.1)[0]


def digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def cars_of(lay):
    return [(c.center, c.yaw, c.length, c.rgb) for c in lay.cars]


def test_deterministic_per_seed_and_the_original_untouched(lots):
    before = (digest(lots.ground_rgb, lots.ground_labels), cars_of(lots), lots.sun_azimuth, len(lots.trees))
    a, b, c = changed_layout(lots, 0.6, 5), changed_layout(lots, 0.6, 5), changed_layout(lots, 0.6, 6)
    assert a is not lots and np.array_equal(a.ground_rgb, b.ground_rgb) and cars_of(a) == cars_of(b)
    assert (a.sun_azimuth, a.sun_elevation) == (b.sun_azimuth, b.sun_elevation)
    assert not np.array_equal(a.ground_rgb, c.ground_rgb) and cars_of(a) != cars_of(c)
    assert np.array_equal(a.ground_labels, lots.ground_labels)      # the classes stay
    assert (digest(lots.ground_rgb, lots.ground_labels), cars_of(lots), lots.sun_azimuth, len(lots.trees)) == before


def test_strength_zero_is_the_identity(lots):
    assert changed_layout(lots, 0.0, 5) is lots and changed_layout(lots, 0.7, 5, parts=()) is lots
    for bad in (-0.1, 1.5, math.nan):
        with pytest.raises(ConfigError, match="change"):
            changed_layout(lots, bad, 5)
    with pytest.raises(ConfigError, match="unknown"):
        changed_layout(lots, 0.5, 5, parts=("snow",))


def changed_pixels(lay, part, strength=0.8, seed=3):
    out = changed_layout(lay, strength, seed, parts=(part,))
    diff = np.any(out.ground_rgb != lay.ground_rgb, axis=2)
    return out, diff


def test_each_part_changes_what_it_should_and_only_that(lots):
    labels = lots.ground_labels
    # road wear: patches and cracks on road / parking, faded markings; nothing else
    out, diff = changed_pixels(lots, "road")
    road = np.isin(labels, (C["road"], C["parking"], C["lane_marking"]))
    assert diff[road].mean() > 0.01 and not diff[~road].any()
    marks = labels == C["lane_marking"]
    assert out.ground_rgb[marks].mean() < lots.ground_rgb[marks].mean() - 3   # faded towards the asphalt
    assert cars_of(out) == cars_of(lots) and out.sun_azimuth == lots.sun_azimuth
    # the season: grass only, its mean colour moves
    out, diff = changed_pixels(lots, "vegetation")
    grass = labels == C["grass"]
    assert diff[grass].mean() > 0.5 and not diff[~grass].any()
    shift = np.abs(out.ground_rgb[grass].mean(0) - lots.ground_rgb[grass].mean(0))
    assert shift.max() > 5
    # shadows: another sun, ground only darker, on road and grass alike, never inside a footprint
    out, diff = changed_pixels(lots, "shadows")
    assert abs(out.sun_azimuth - lots.sun_azimuth) > 0.3 and cars_of(out) == cars_of(lots)
    assert np.all(out.ground_rgb <= lots.ground_rgb)
    dark = np.all(out.ground_rgb.astype(int) < lots.ground_rgb.astype(int) - 10, axis=2)
    for cls in ("road", "sidewalk", "grass"):
        assert dark[labels == C[cls]].mean() > 0.005, cls
    assert not dark[labels == C["building"]].any()
    # cars: some gone, some moved, some new, none on top of another, none on other ground than their kind
    out, diff = changed_pixels(lots, "cars", strength=1.0)
    assert not diff.any()
    old = {c.center for c in lots.cars}
    kept = [c for c in out.cars if c.center in old]
    assert len(kept) < len(lots.cars) and len(out.cars) > len(kept)
    xy = np.array([c.center for c in out.cars])
    d = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1)) + np.eye(len(xy)) * 1e9
    assert d.min() > 2.3
    uv = np.round(lots.world_to_raster(xy)).astype(int)
    new = np.array([c.center not in old for c in out.cars])
    assert np.isin(labels[uv[new, 1], uv[new, 0]], DRIVABLE).all()             # added in parking places


def test_changed_world_changes_foliage_and_never_the_tile(scene_path):
    from satloc_env.world.meshes import build_world
    from satloc_env.world.revisit import change_foliage

    scene = load_scene(scene_path)
    tile = digest(scene.satmap.image, scene.satmap.labels)
    base = scene.world
    w = changed_world(scene, 0.8, 4)
    assert w is changed_world(scene, 0.8, 4) and changed_world(scene, 0.0, 4) is base
    assert not np.allclose(w.sun_direction, base.sun_direction)      # the facades' shading follows the sun
    # the foliage: only tree texels that are green, not bark, not the ground, not other objects
    fresh = build_world(scene.layout, pad_m=250.0, beyond=scene.spec.beyond_edge)
    change_foliage(fresh, 0.8, 4)
    changed = 0
    for a, b in zip(base.chunks, fresh.chunks):
        d = np.any(a.texture != b.texture, axis=2)
        tree = a.labels == C["tree"]
        assert not d[~tree].any() and not d[tree & (a.texture[..., 1] < a.texture[..., 0])].any()
        changed += int(d.sum())
    assert changed > 1000
    assert digest(scene.satmap.image, scene.satmap.labels) == tile


def test_env_change_option(scene_path):
    tile = digest(load_scene(scene_path).satmap.image)
    env = gym.make("satloc/SatLoc-v0", scene=scene_path, localizer=None, occlusion=0.5, appearance=0.3)
    try:
        plain = run(env, 3, 3)
        zero = run(env, 3, 3, {"change": 0.0})
        assert env.unwrapped.change_seed is None
        changed = run(env, 3, 3, {"change": 0.6})
        seed = env.unwrapped.change_seed
        again = run(env, 3, 3, {"change": 0.6})
        assert env.unwrapped.change_seed == seed
        for (o0, i0), (o1, i1), (o2, i2), (o3, i3) in zip(plain, zero, changed, again):
            assert all(np.array_equal(o0[k], o1[k]) for k in o0)                  # 0: as without the knob
            assert all(np.array_equal(o2[k], o3[k]) for k in o2)                  # deterministic per seed
            assert not np.array_equal(o0["left"], o2["left"])                     # the revisit differs
            assert np.array_equal(o0["odometry"], o2["odometry"])                 # the episode's draws stay
            assert all(np.array_equal(i0[k], i2[k]) for k in i0)
        run(env, 4, 0, {"change": 0.6})
        assert env.unwrapped.change_seed != seed
        assert digest(env.unwrapped.scene.satmap.image) == tile
        with pytest.raises(ConfigError, match="change"):
            env.reset(seed=0, options={"change": 1.5})
    finally:
        env.close()


def test_check_env_with_change(scene_path):
    env = gym.make("satloc/SatLoc-v0", scene=scene_path, localizer=None, change=0.5, depth=True)
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


def test_recorded_query_pass_changes_by_default(scene_path, tmp_path):
    assert RecordConfig().query.change == QUERY_CHANGE > 0 and RecordConfig().database.change == 0
    q = {"lane_offset_m": -0.75, "spacing_m": 6.0, "max_frames": 2, "seed": 1}
    cfg = RecordConfig(scene=scene_path, database=PassConfig(spacing_m=6.0, max_frames=2, depth=False),
                       query=PassConfig(**q, change=QUERY_CHANGE, depth=False))
    db, changed = record_passes(cfg, tmp_path / "rec", progress=False)
    st = json.loads((tmp_path / "rec" / "recording.json").read_text())
    assert st["config"]["query"]["change"] == QUERY_CHANGE and st["config"]["database"]["change"] == 0
    assert "change_seed" in changed.meta and "change_seed" not in db.meta
    db, changed = [f.left for f in db], [(f.left, f.pose) for f in changed]   # read before the rerun rewrites them
    # the same recording without the change: the configuration differs, so it is recorded again, not resumed
    db2, plain = record_passes(RecordConfig(scene=scene_path, database=cfg.database,
                                            query=PassConfig(**q, change=0.0, depth=False)),
                               tmp_path / "rec", progress=False)
    assert len(plain) == len(changed) == 2 and all(np.array_equal(a, b.left) for a, b in zip(db, db2))
    for (left, pose), f in zip(changed, plain):
        assert np.allclose(pose.as_array(), f.pose.as_array()) and not np.array_equal(left, f.left)


def test_example_script_measures_and_draws(scene_path, tmp_path, capsys):
    spec = importlib.util.spec_from_file_location("revisit_change", ROOT / "examples" / "revisit_change.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    res = mod.main(["--scene", scene_path, "--places", "3", "--change", "0", "0.5"])
    out = capsys.readouterr().out
    assert "change 0.00: SIFT RANSAC inliers" in out and "change 0.50" in out
    assert len(res[0.0]) == 3 and np.all(res[0.0] >= 0)
    assert mod.main(["--scene", scene_path, "--picture", str(tmp_path / "p.jpg"), "--at", "20"]) is None
    assert (tmp_path / "p.jpg").stat().st_size > 5000


def test_a_revisit_with_some_parts_of_the_change(scene_path):
    from satloc_env.experiments.scene_run import ExperimentConfig
    from satloc_env.world.revisit import PARTS

    scene = load_scene(scene_path)
    full = changed_world(scene, 0.8, 4)
    assert changed_world(scene, 0.8, 4, PARTS) is full                     # every part: the default
    assert changed_world(scene, 0.8, 4, ()) is scene.world                 # none: the scene's own world
    cars = changed_world(scene, 0.8, 4, ["cars", "shadows"])
    assert cars is not full and np.allclose(cars.sun_direction, full.sun_direction)   # another day's sun, but ...
    plain = scene.spec.build_world(changed_layout(scene.layout, 0.8, 4, parts=("cars", "shadows"),
                                                  cast=not scene.spec.casts_shadows))
    assert all(np.array_equal(a.texture, b.texture) for a, b in zip(cars.chunks, plain.chunks))   # no season's foliage
    with pytest.raises(ConfigError, match="change parts: unknown"):
        changed_world(scene, 0.8, 4, ["snow"])
    env = gym.make("satloc/SatLoc-v0", scene=scene_path, localizer=None)
    try:
        every = run(env, 3, 2, {"change": 0.6})
        some = run(env, 3, 2, {"change": 0.6, "change_parts": ["shadows"]})
        none = run(env, 3, 2, {"change": 0.6, "change_parts": []})
        plain = run(env, 3, 2)
        assert not np.array_equal(every[-1][0]["left"], some[-1][0]["left"])
        assert all(np.array_equal(a[0]["left"], b[0]["left"]) for a, b in zip(none, plain))
        with pytest.raises(ConfigError, match="change_parts: unknown"):
            env.reset(seed=0, options={"change_parts": ["snow"]})
    finally:
        env.close()
    # a pass and an experiment take the parts; the default (every part) stamps as before the field
    assert "change_parts" not in to_dict(PassConfig(), stamp=True)
    assert to_dict(PassConfig(change_parts=("cars",)), stamp=True)["change_parts"] == ["cars"]
    with pytest.raises(ConfigError, match="change_parts"):
        PassConfig(change_parts=("snow",))
    with pytest.raises(ConfigError, match="change_parts"):
        ExperimentConfig(change_parts=("snow",))
