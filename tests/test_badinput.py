"""Bad actions, bad reset options and a localizer of other data, on every environment id (issue 15, item 5), and
the soak benchmark in miniature (item 6).

- Actions: NaN, +-inf, another shape, another dtype raise ``ActionError`` (a ValueError) whose message says
  what was expected, and leave the episode as it was. SatLoc-v0 clips finite out-of-range actions to its Box
  (checked against the clipped action and the bicycle model's steering limit); SatLocReplay-v0's Discrete
  skip count is never clipped.
- ``reset(options=...)`` and ``gym.make``: unknown or fixed keys (named), wrong types, NaN/inf, values out of
  range raise ``satloc.ConfigError`` naming the field.
- A localizer (instance or build directory) of another scene, of the same scene at another aliasing, or of
  another camera raises ``ConfigError`` naming both sides, when the env is made and when a reset changes the
  scene; the right one is accepted and localizes.

The data are tiny: one-block scenes of 84 m (as in tests/test_process.py), a localizer built from 20 frames
with RGB features and one projection epoch, recorded passes of 8 frames.
"""
from __future__ import annotations

import copy
import dataclasses
import json
import math

import gymnasium as gym
import numpy as np
import pytest

import satloc_env
from satloc import ConfigError
from satloc.features.projection import ProjectionConfig
from satloc.geoframe import GeoFrame
from satloc.geometry import Pose2
from satloc.localizers.database import LocalizerConfig
from satloc.pipeline import BuildConfig, build, load_localizer
from satloc.sequence import Sequence
from satloc_env.envs import auto_localizer as autoloc
from satloc_env.envs.drive import (
    MAP_MAX_DIFFERING,
    ActionError,
    SatLocEnv,
    build_identity,
    check_localizer_map,
    map_difference,
)
from satloc_env.envs.record import PassConfig, record_pass
from satloc_env.envs.vehicle import VehicleParams, step_bicycle

ENV_ID, REPLAY_ID = satloc_env.ENV_ID, satloc_env.REPLAY_ID

# A one-block scene (84 m x 84 m, as TINY_SCENE in tests/test_process.py); TINY2 has the same size and another
# seed (other content), WIDE another size.
TINY = """\
name: {name}
seed: {seed}
generator: {{type: grid, style: city, blocks: [1, 1], pitch_m: {pitch}, road_width_m: 12, sidewalk_m: 3, margin_m: 12}}
meters_per_pixel: 0.4
ground_mpp: 0.2
routes:
  main:
    waypoints: [[12, 12], [72, 12], [72, 72], [12, 72]]
    closed: true
database_route: main
query_route: main
knobs: {{aliasing: 0.0, occlusion: 0.0, appearance: 0.0}}
"""
SMALL = dict(max_frames=20, build_config=BuildConfig(features="rgb"),
             projection_config=ProjectionConfig(max_anchors=1000, max_epochs=1))
K = 8


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    d = tmp_path_factory.mktemp("scenes")
    out = {}
    for name, seed, pitch in (("tiny", 3, 60), ("tiny2", 4, 60), ("wide", 3, 64)):
        (d / f"{name}.yaml").write_text(TINY.format(name=name, seed=seed, pitch=pitch))
        out[name] = str(d / f"{name}.yaml")
    return out


@pytest.fixture(scope="module")
def build_dir(scenes, tmp_path_factory):
    return autoloc.auto_build_dir(scenes["tiny"], None, "half", progress=False,
                                  cache_dir=tmp_path_factory.mktemp("cache"), **SMALL)


@pytest.fixture(scope="module")
def loc(build_dir):
    return load_localizer(build_dir, LocalizerConfig(mode="full", corridor_m=8.0, posterior_k=K))


def record(scene: str, out, name="query", frames=8, meta=None):
    env = SatLocEnv(scene=scene, localizer=None)
    try:
        env.reset(seed=0)
        env.scene.satmap.save(out / "map")
        record_pass(env, PassConfig(lane_offset_m=-1.25, spacing_m=3.0, max_frames=frames, seed=1), "main",
                    out / name, name, progress=False, meta=meta)
    finally:
        env.close()
    return Sequence.load(out / name)


@pytest.fixture(scope="module")
def rec(scenes, tmp_path_factory):
    """Passes of 8 frames recorded on tiny and on tiny2 (meta: scene, aliasing, as ``satloc record`` writes)."""
    out = {}
    for name in ("tiny", "tiny2"):
        d = tmp_path_factory.mktemp(f"rec_{name}")
        out[name] = record(scenes[name], d, meta={"source": "test", "scene": name, "aliasing": 0.0})
    return out


def make(env_id, scenes, rec, **kw):
    if env_id == ENV_ID:
        return gym.make(ENV_ID, scene=scenes["tiny"], **{"localizer": None, **kw})
    return gym.make(REPLAY_ID, sequence=rec["tiny"], **kw)


def test_every_registered_id_is_covered():
    ids = {k for k in gym.registry if k.startswith("satloc/")}
    assert ids == {ENV_ID, REPLAY_ID, satloc_env.ACTIVE_ID}   # add the new id's bad-input cases here


def test_activeloc_refuses_non_integer_and_out_of_range_actions():
    from satloc_env.envs.active import ActiveLocEnv

    env = ActiveLocEnv(map="active_town")
    _, info = env.reset(seed=0)
    before = (env.distance, env.decisions, env.leg)
    for bad in (np.nan, 1.0, 2.5, "1", True, None, [1, 2], np.array([0, 1]), -1, 3, 10**9, np.array([1.0])):
        with pytest.raises(ActionError, match=r"expected a branch slot, an integer in \[0, 3\)") as e:
            env.step(bad)
        assert isinstance(e.value, ValueError)
        assert (env.distance, env.decisions, env.leg) == before          # nothing applied
    ok = int(np.flatnonzero(info["action_mask"])[0])
    _, _, _, _, info = env.step(np.array([ok]))
    assert info["decisions"] == 1 and not info["invalid_action"]


# --- actions --------------------------------------------------------------------------------------------------
NON_FINITE = [[np.nan, 0.0], [0.0, np.nan], [np.inf, 0.0], [-np.inf, 0.0], [5.0, np.inf], [5.0, -np.inf],
              np.array([np.nan, np.nan], np.float32)]
WRONG_SHAPE = [[1.0, 2.0, 3.0], [[1.0, 2.0]], np.zeros((2, 1)), 5.0, [], np.zeros(0)]
WRONG_TYPE = ["ab", ["8", "0"], [True, False], None, [1.0, [2.0, 3.0]], {"speed": 1.0}, np.array([1 + 2j, 0])]


def test_satloc_v0_refuses_non_finite_misshapen_and_non_numeric_actions(scenes, rec):
    env = make(ENV_ID, scenes, rec)
    env.reset(seed=0)
    u = env.unwrapped
    for bad, expect in ([(a, "got non-finite values") for a in NON_FINITE] + [(a, r"got shape \(") for a in WRONG_SHAPE]
                        + [(a, "of dtype|inhomogeneous") for a in WRONG_TYPE]):
        pose, steps = u.pose, u.steps
        with pytest.raises(ActionError, match=expect) as e:
            env.step(bad)
        assert isinstance(e.value, ValueError)
        msg = str(e.value)
        assert "shape (2,)" in msg and "[0, 20]" in msg and "[-1, 1]" in msg, msg  # says what is expected
        assert u.pose == pose and u.steps == steps   # nothing applied
    # numbers of any numeric dtype are fine: ints, float16/32/64, a list or a tuple
    for good in ([8, 0], (8.0, 0.0), np.array([8, 0], np.int64), np.array([8, 0], np.float16)):
        _, _, _, _, info = env.step(good)
        assert info["odometry_true"][0] == pytest.approx(0.8, abs=1e-3)
    env.close()


def test_satloc_v0_clips_out_of_range_actions_to_the_box(scenes, rec):
    env, ref = make(ENV_ID, scenes, rec, odometry_noise=(0.0, 0.0)), make(ENV_ID, scenes, rec,
                                                                         odometry_noise=(0.0, 0.0))
    assert env.action_space.low.tolist() == [0.0, -1.0] and env.action_space.high.tolist() == [20.0, 1.0]
    env.reset(seed=0), ref.reset(seed=0)
    dt = env.unwrapped.config.dt
    # each component clipped on its own: the same motion and observation as the clipped action
    for wild, clipped in (([100.0, 5.0], [20.0, 1.0]), ([1e300, -1e300], [20.0, -1.0]), ([-3.0, 0.2], [0.0, 0.2]),
                          ([10.0, -7.0], [10.0, -1.0])):
        obs, _, _, _, info = env.step(wild)
        obs_r, _, _, _, info_r = ref.step(clipped)
        assert np.array_equal(info["pose"], info_r["pose"]) and np.array_equal(obs["left"], obs_r["left"])
        dx, dy, dyaw = info["odometry_true"]
        assert math.hypot(dx, dy) <= clipped[0] * dt + 1e-9          # speed within [0, 20] m/s
        assert abs(dyaw) <= 1.0 * dt + 1e-9                            # yaw rate within [-1, 1] rad/s
    # reversing is not possible: a negative speed is 0, and the car stands still
    _, _, _, _, info = env.step([-20.0, 1.0])
    assert np.allclose(info["odometry_true"], 0.0)
    # the bicycle model then limits steering to 0.6 rad: at 1 m/s the yaw rate is at most tan(0.6) / 2.7
    _, _, _, _, info = env.step([1.0, 1.0])
    v = VehicleParams()
    assert info["odometry_true"][2] == pytest.approx(math.tan(v.max_steer_rad) / v.wheelbase_m * dt, rel=1e-9)
    assert step_bicycle(env.unwrapped.pose, 1.0, 1.0, dt, v)[2] < 1.0
    env.close(), ref.close()


def test_replay_refuses_bad_skip_counts_and_never_clips(scenes, rec):
    env = make(REPLAY_ID, scenes, rec, max_skip=3)
    env.reset(seed=0)
    u = env.unwrapped
    for bad in (np.nan, np.inf, -np.inf, 1.0, 2.5, "1", True, None, [1, 2], np.array([1, 2]), 0, 4, -1, 10**9,
                np.array([1.0])):
        before = u.frame_index
        with pytest.raises(ActionError, match=r"expected an integer skip count in \[1, 3\]") as e:
            env.step(bad)
        assert isinstance(e.value, ValueError) and "not clipped" in str(e.value)
        assert u.frame_index == before and u.steps == 0
    for good, frame in ((np.int64(1), 1), (np.array([2]), 3), (1, 4)):
        _, _, _, _, info = env.step(good)
        assert info["frame_index"] == frame
    env.close()


# --- reset options and configuration --------------------------------------------------------------------------
def test_satloc_v0_reset_options(scenes, rec):
    env = make(ENV_ID, scenes, rec)
    env.reset(seed=0)
    bad = [
        ({"fov": 90}, r"\['fov'\] cannot change per episode: unknown key"),
        ({"resolution": "full"}, r"\['resolution'\] cannot change per episode: fixed when the env is made"),
        ({"localizer": "auto"}, r"\['localizer'\] cannot change per episode"),
        ("speed_mps=3", "reset options: expected a dict of per-episode keys"),
        ([("speed_mps", 3.0)], "reset options: expected a dict"),
        ({"speed_mps": "fast"}, "reset options.speed_mps: expected a number, got str 'fast'"),
        ({"speed_mps": True}, "reset options.speed_mps: expected a number, got bool"),
        ({"speed_mps": float("nan")}, r"speed_mps: expected a finite number in \[0, 20\], got nan"),
        ({"speed_mps": 25.0}, r"speed_mps: expected a finite number in \[0, 20\], got 25"),
        ({"lane_offset_m": float("inf")}, "lane_offset_m: expected a finite number, got inf"),
        ({"lane_offset_m": "left"}, "lane_offset_m: expected a number"),
        ({"start_s_m": -1.0}, "start_s_m: expected a finite number >= 0"),
        ({"start_s_m": 1e4}, r"start_s_m: expected a position along route 'main' of scene 'tiny', in \[0, 240.0\]"),
        ({"max_steps": 0}, "max_steps: expected an integer >= 1, got 0"),
        ({"max_steps": 2.5}, "max_steps: expected an integer, got float 2.5"),
        ({"occlusion": 1.5}, r"occlusion: expected a value in \[0, 1\]"),
        ({"appearance": float("nan")}, r"appearance: expected a value in \[0, 1\]"),
        ({"aliasing": -0.1}, r"aliasing: expected a value in \[0, 1\]"),
        ({"odometry_noise": [0.1, float("nan")]}, "odometry_noise: expected 2 non-negative numbers"),
        ({"odometry_noise": [0.1, -1.0]}, "odometry_noise: expected 2 non-negative numbers"),
        ({"odometry_noise": [0.1]}, "odometry_noise: expected 2 values, got 1"),
        ({"odometry_noise": "x"}, "odometry_noise: expected a list"),
        ({"random_start": "yes"}, "random_start: expected true or false"),
        ({"route": "nope"}, r"route: 'nope' is not a route of scene 'tiny' \(\['main'\]\)"),
        ({"scene": 42}, "scene: expected a string, got int 42"),
        ({"scene": ""}, "scene: expected a shipped scene name"),
    ]
    for opts, msg in bad:
        with pytest.raises(ConfigError, match=msg):
            env.reset(seed=0, options=opts)
        with pytest.raises(RuntimeError, match="call reset"):   # a failed reset leaves no half-made episode
            env.unwrapped.step([1.0, 0.0])
    # a good reset works again, and options hold for that episode only
    _, info = env.reset(seed=0, options={"start_s_m": 20.0, "speed_mps": 5.0})
    assert float(info["route_s"]) == pytest.approx(20.0, abs=0.5)
    _, info = env.reset(seed=0)
    assert float(info["route_s"]) == pytest.approx(0.0, abs=0.5) and env.unwrapped.config.speed_mps == 8.0
    env.close()


def test_satloc_v0_config_values_checked_at_make(scenes):
    bad = [
        (dict(dt=0.0), "dt: expected a finite number > 0"),
        (dict(dt=float("nan")), "dt: expected a finite number > 0"),
        (dict(zfar_m=float("inf")), "zfar_m: expected a finite number >= 1"),
        (dict(detail_m=-1.0), "detail_m: expected a finite number >= 0"),
        (dict(detail_m=float("nan")), "detail_m: expected a finite number >= 0"),
        (dict(anisotropy=0), "anisotropy: expected an integer >= 1"),
        (dict(max_steps=-5), "max_steps: expected an integer >= 1"),
        (dict(speed_mps=-1.0), r"speed_mps: expected a finite number in \[0, 20\]"),
        (dict(resolution="quarter"), r"resolution: expected one of \['half', 'full'\]"),
        (dict(depth="yes"), "depth: expected true or false"),
        (dict(localize_every=0), "localize_every: expected an integer >= 1"),
    ]
    for kw, msg in bad:
        with pytest.raises(ConfigError, match="SatLocEnv config.*" + msg):
            gym.make(ENV_ID, scene=scenes["tiny"], localizer=None, **kw)


def test_replay_reset_options_and_config(scenes, rec):
    env = make(REPLAY_ID, scenes, rec)
    env.reset(seed=0)
    bad = [
        ({"frame": 1}, r"\['frame'\] cannot change per episode: unknown key"),
        ({"localizer": None}, r"\['localizer'\] cannot change per episode: fixed when the env is made"),
        (("start_frame", 1), "reset options: expected a dict"),
        ({"stride": "2"}, "stride: expected an integer, got str"),
        ({"stride": 1.5}, "stride: expected an integer, got float 1.5"),
        ({"stride": 0}, "stride: expected an integer >= 1"),
        ({"start_frame": float("nan")}, "start_frame: expected an integer, got float nan"),
        ({"start_frame": -1}, "start_frame: expected an index >= 0"),
        ({"start_frame": 7}, r"start_frame: expected an index in \[0, 6\]"),
        ({"end_frame": 0}, "end_frame: expected an index >= 1 or None"),
        ({"end_frame": 99}, r"end_frame: expected an index in \[1, 8\]"),
        ({"random_start": 1}, "random_start: expected true or false"),
        ({"odometry_noise": [float("inf"), 0.0]}, "odometry_noise: expected 2 non-negative numbers"),
    ]
    for opts, msg in bad:
        with pytest.raises(ConfigError, match=msg):
            env.reset(seed=0, options=opts)
    _, info = env.reset(seed=0, options={"start_frame": 2})
    assert info["frame_index"] == 2
    assert env.reset(seed=0)[1]["frame_index"] == 0
    for kw, msg in ((dict(max_skip=0), "max_skip: expected an integer >= 1"),
                    (dict(odometry_noise=(float("nan"), 0.0)), "odometry_noise: expected 2 non-negative numbers"),
                    (dict(stride=-2), "stride: expected an integer >= 1")):
        with pytest.raises(ConfigError, match="SatLocReplayEnv config.*" + msg):
            gym.make(REPLAY_ID, sequence=rec["tiny"], **kw)
    env.close()


# --- a localizer of other data --------------------------------------------------------------------------------
def test_the_right_localizer_is_accepted_and_localizes(scenes, rec, loc, build_dir):
    for arg in (loc, str(build_dir)):
        env = gym.make(ENV_ID, scene=scenes["tiny"], localizer=arg)
        _, info = env.reset(seed=0)
        assert info["error_m"] < 2.0
        env.close()
    assert map_difference(loc, satloc_env.load_scene(scenes["tiny"]).satmap) == 0.0
    replay = gym.make(REPLAY_ID, sequence=rec["tiny"], localizer=str(build_dir))
    _, info = replay.reset(seed=0)
    assert info["error_m"] < 2.0
    replay.close()
    ident = build_identity(build_dir)
    assert ident["scene"] == "tiny" and ident["aliasing"] == 0.0 and "of scene 'tiny'" in ident["source"]


def test_localizer_of_another_scene_is_refused_by_satloc_v0(scenes, loc, build_dir):
    # another size: refused whatever the features, naming both maps
    with pytest.raises(ConfigError, match=r"the Localizer instance was built on a satellite map \(210x210 px at "
                                          r"0.4 m/px.*not the map of scene 'wide' \(aliasing 0\) \(220x220 px"):
        gym.make(ENV_ID, scene=scenes["wide"], localizer=loc)
    # the same size and resolution, other content: the build's colours against the scene's map
    other = satloc_env.load_scene(scenes["tiny2"]).satmap
    assert map_difference(loc, other) > 10 * MAP_MAX_DIFFERING
    with pytest.raises(ConfigError, match=r"the Localizer instance was built on a satellite map of the same size as "
                                          r"the map of scene 'tiny2' .* other content \(\d+% of its 8x8-pixel cells"):
        gym.make(ENV_ID, scene=scenes["tiny2"], localizer=loc)
    with pytest.raises(ConfigError, match=r"the build '.*tiny-alias0-gap0\.5-half-\w+' of scene 'tiny' \(aliasing 0\) "
                                          r"\(satellite gap 0\.5\) was built on .* not the map of scene 'tiny2'"):
        gym.make(ENV_ID, scene=scenes["tiny2"], localizer=str(build_dir))
    # and when a reset changes the scene; the env stays usable on its own scene
    env = gym.make(ENV_ID, scene=scenes["tiny"], localizer=loc)
    env.reset(seed=0)
    with pytest.raises(ConfigError, match="not the map of scene 'tiny2'"):
        env.reset(seed=0, options={"scene": scenes["tiny2"]})
    with pytest.raises(RuntimeError, match="call reset"):
        env.unwrapped.step([1.0, 0.0])
    _, info = env.reset(seed=0)
    assert env.unwrapped.scene.name == "tiny" and info["error_m"] < 2.0
    env.close()


def test_without_colour_features_the_build_record_decides(scenes, loc, build_dir, monkeypatch):
    """A localizer whose features hold no colours (the semantic set) cannot be compared with the map; a build
    directory's recorded scene then decides."""
    monkeypatch.setattr("satloc_env.envs.drive._rgb_channels", lambda extractor: None)
    assert map_difference(loc, satloc_env.load_scene(scenes["tiny2"]).satmap) is None
    with pytest.raises(ConfigError, match=r"the build '.*' of scene 'tiny' \(aliasing 0\) \(satellite gap 0\.5\) is "
                                          r"not a build of scene 'tiny2' \(aliasing 0\)"):
        gym.make(ENV_ID, scene=scenes["tiny2"], localizer=str(build_dir))
    gym.make(ENV_ID, scene=scenes["tiny"], localizer=str(build_dir)).close()


def test_content_check_on_a_shifted_map(scenes, loc):
    """The content check compares colours cell by cell: the same map shifted by 8 m is refused."""
    sm = satloc_env.load_scene(scenes["tiny"]).satmap
    shifted = dataclasses.replace(sm, image=np.roll(sm.image, 20, axis=1))
    with pytest.raises(ConfigError, match="other content"):
        check_localizer_map(loc, shifted, "the shifted map")
    check_localizer_map(loc, sm, "the map")   # the right one passes


def test_localizer_of_another_camera_is_refused(scenes, rec, loc):
    with pytest.raises(ConfigError, match=r"the Localizer instance was built for 620x188 images, but the environment "
                                          r"\(resolution 'full'\) has 1242x375 images"):
        gym.make(ENV_ID, scene=scenes["tiny"], localizer=loc, resolution="full")
    pitched = copy.copy(loc)
    pitched.camera = dataclasses.replace(loc.camera, pitch=0.05, baseline=0.6)
    with pytest.raises(ConfigError, match=r"built for another camera than that of the environment \(resolution "
                                          r"'half'\) \(localizer vs the environment.*baseline 0.6 vs 0.54.*pitch 0.05 "
                                          r"vs 0\)"):
        gym.make(ENV_ID, scene=scenes["tiny"], localizer=pitched)
    with pytest.raises(ConfigError, match=r"built for another camera than that of sequence 'query' .*baseline 0.6 vs "
                                          r"0.54"):
        gym.make(REPLAY_ID, sequence=rec["tiny"], localizer=pitched)
    # another size and another rig (the city demo's build on a KITTI drive): the message says why the replay does
    # not resample the images, and what to use instead
    kitti_like = copy.copy(loc)
    kitti_like.camera = dataclasses.replace(loc.camera.resized(1242, 375), baseline=0.532, mount_height=1.72)
    with pytest.raises(ConfigError, match=r"built for 1242x375 images, but sequence 'query' has 620x188 images; "
                                          r"images are resampled into a localizer's camera only when the two rigs "
                                          r"are the same, and these differ \(sequence 'query' against the localizer: "
                                          r"baseline 0.5400 m against 0.5320 m, mount_height .*\): use a localizer "
                                          r"built from a database taken with this rig"):
        gym.make(REPLAY_ID, sequence=rec["tiny"], localizer=kitti_like)
    same_rig = copy.copy(loc)
    same_rig.camera = loc.camera.resized(1242, 375)   # same rig, other size: resampled, so no size error
    try:
        gym.make(REPLAY_ID, sequence=rec["tiny"], localizer=same_rig).close()
    except ConfigError as e:
        assert "images, but" not in str(e)


def test_replay_refuses_a_localizer_of_other_data(scenes, rec, loc, build_dir, tmp_path):
    # a recording of another scene: the build records 'tiny', the sequence 'tiny2'
    with pytest.raises(ConfigError, match=r"the build '.*' of scene 'tiny' \(aliasing 0\) \(satellite gap 0\.5\) is "
                                          r"not a build of scene 'tiny2' \(aliasing 0\), where sequence 'query' was "
                                          r"recorded"):
        gym.make(REPLAY_ID, sequence=rec["tiny2"], localizer=str(build_dir))
    # a sequence whose path lies off the localizer's map
    moved = [rec["tiny"][i] for i in range(3)]
    far = Sequence(rec["tiny"].camera, [dataclasses.replace(f, pose=Pose2(f.pose.x + 500, f.pose.y, f.pose.yaw))
                                        for f in moved], "far")
    with pytest.raises(ConfigError, match=r"none of the 3 poses of sequence 'far' .* lies on the satellite map the "
                                          r"Localizer instance was built on \(x 0.0 to 84.0 m, y 0.0 to 84.0 m\)"):
        gym.make(REPLAY_ID, sequence=far, localizer=loc)
    # geographic frames: a build of a database read in one frame, a sequence in another
    a, b = GeoFrame(8.40, 49.0), GeoFrame(8.41, 49.0)
    seq = rec["tiny"]
    frames = [seq[i] for i in range(len(seq))]
    Sequence(seq.camera, frames, "db", {"geo_frame": a.to_dict()}).save(tmp_path / "db")
    build(tmp_path / "db", seq._dir.parent / "map", tmp_path / "build", BuildConfig(features="rgb"), progress=False)
    assert build_identity(tmp_path / "build")["geo_frame"] == a.to_dict()
    kw = dict(localizer=str(tmp_path / "build"), localizer_mode="np")
    with pytest.raises(ConfigError, match=r"was built in the geographic frame \(lon0 8.4, lat0 49.0\), not in that of "
                                          r"sequence 'q' \(lon0 8.41, lat0 49.0\)"):
        gym.make(REPLAY_ID, sequence=Sequence(seq.camera, frames, "q", {"geo_frame": b.to_dict()}), **kw)
    gym.make(REPLAY_ID, sequence=Sequence(seq.camera, frames, "q", {"geo_frame": a.to_dict()}), **kw).close()


# --- soak (issue 15 item 6), in miniature ---------------------------------------------------------------------
def test_soak_report(scenes, build_dir, tmp_path, capsys):
    from satloc_env.experiments.soak import SoakConfig, main, soak

    lines = []
    # the default "small" localizer, with the module's small build configuration: served from its cache entry
    res = soak(SoakConfig(steps=50, queries=20, scene=scenes["tiny"], episode_steps=20, localize_every=5,
                          sample_every=10, query_sample_every=5, small_frames=20, query_frames=8, cache_dir=str(build_dir.parent)),
               emit=lines.append, build_config=SMALL["build_config"], projection_config=SMALL["projection_config"])
    assert set(res) == {"config", "localizer", "process_start", "env", "stream", "samples"}
    assert res["localizer"].startswith("small: the first 20 database frames") and str(build_dir) in res["localizer"]
    json.dumps(res, allow_nan=False)   # plain JSON: no NaN
    env, stream = res["env"], res["stream"]
    assert env["steps"] == 50 and env["episodes"] >= 3 and env["localizations"] == 10   # every 5th step
    assert stream["queries"] == 20 and stream["frames_without_result"] == 0
    for s, unit in ((env, "steps"), (stream, "queries")):
        for k in ("rss_start_mb", "rss_end_mb", "rss_peak_mb", "rss_max_sampled_mb", f"{unit}_per_s"):
            assert math.isfinite(s[k]) and s[k] > 0, k
        assert math.isfinite(s["rss_slope_mb_per_1000"])
        assert 0 < s["rss_start_mb"] <= s["rss_peak_mb"] and s["rss_end_mb"] <= s["rss_peak_mb"]
        assert s["fds_start"] > 0 and s["fds_end"] - s["fds_start"] <= 3 and s["fds_max"] - s["fds_start"] <= 3
        assert math.isfinite(s["fds_slope_per_1000"])
    assert env["mean_error_m"] < 2.0 and stream["mean_error_m"] < 2.0   # the localizer localized meanwhile
    samples = res["samples"]
    assert [s["steps"] for s in samples if s["soak"] == "env"] == [0, 10, 20, 30, 40, 50]
    assert [s["queries"] for s in samples if s["soak"] == "stream"] == [0, 5, 10, 15, 20]
    assert all(math.isfinite(s["rss_mb"]) and s["fds"] > 0 for s in samples)
    assert lines[-1] == stream and sum(1 for x in lines if x.get("summary")) == 2
    # the command line: JSON lines on stdout and the --out file (the small build is cached by now)
    with pytest.raises(SystemExit):
        main(["--help"])
    capsys.readouterr()
    assert main(["--steps", "0"]) == 2 and "steps: expected an integer >= 1" in capsys.readouterr().err
    assert main(["--steps", "5", "--queries", "3", "--scene", scenes["tiny"], "--sample-every", "5",
                 "--query-sample-every", "3", "--localize-every", "5", "--localizer", str(build_dir),
                 "--out", str(tmp_path / "soak.json")]) == 0
    out = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert [x["soak"] for x in out if x.get("summary")] == ["env", "stream"]
    assert json.loads((tmp_path / "soak.json").read_text())["env"]["steps"] == 5
