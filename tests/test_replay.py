"""The replay environment ``satloc/SatLocReplay-v0`` (satloc_env/envs/replay.py): stepping through a recorded sequence,
its observation and info contract (the same as SatLoc-v0's), the skip action, truncation, frames without a pose,
the localizer in the loop, rendering and configuration errors.

The data: a short pass recorded by the simulator in the module's tmp directory (8 frames, 3 m apart, 0.5 m
beside the database lane, a mild appearance change) and the small localizer of tests/test_env_localizer.py
(the first 25 m of the city database pass, RGB features).
"""
import dataclasses
import itertools
import math

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import satloc_env  # noqa: F401  (registers the ids)
from satloc import ConfigError, SatelliteMap
from satloc.features.projection import ProjectionConfig
from satloc.geometry import Pose2
from satloc.localizers.database import LocalizerConfig
from satloc.pipeline import BuildConfig, load_localizer
from satloc.sequence import Frame, Sequence
from satloc.tracking.track import Tracker, compose_motion, relative_motion
from satloc_env.envs import auto_localizer as autoloc
from satloc_env.envs.drive import PANEL_PX, SatLocEnv, compose_view
from satloc_env.envs.record import PassConfig, record_pass
from satloc_env.envs.replay import EPISODE_KEYS, SatLocReplayEnv

ID = "satloc/SatLocReplay-v0"
K = 16
SMALL = dict(max_frames=25, build_config=BuildConfig(features="rgb"),
             projection_config=ProjectionConfig(max_anchors=2000, max_epochs=2))
LOC_KEYS = {"posterior_poses", "posterior_probs", "estimate", "error_m", "inlier", "inlier_score", "localized_step"}
BASE_KEYS = {"pose", "odometry_true", "odometry_valid", "step", "frame_index", "timestamp"}
N = 8


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    """rec/query: 8 frames every 3 m (true depth stored), 0.5 m left of the database lane; rec/map: the tile."""
    out = tmp_path_factory.mktemp("replay_rec")
    env = SatLocEnv(scene="city", localizer=None, depth=True)
    try:
        env.reset(seed=0)
        env.scene.satmap.save(out / "map")
        record_pass(env, PassConfig(lane_offset_m=-1.25, spacing_m=3.0, max_frames=N, appearance=0.2, seed=1,
                                    wander_m=0.0, speed_wander=0.0),
                    "main", out / "query", "query", progress=False)
    finally:
        env.close()
    return out


@pytest.fixture(scope="module")
def seq(rec):
    return Sequence.load(rec / "query")


@pytest.fixture(scope="module")
def build_dir(tmp_path_factory):
    return autoloc.auto_build_dir("city", None, "half", progress=False,
                                  cache_dir=tmp_path_factory.mktemp("satloc_cache"), **SMALL)


@pytest.fixture(scope="module")
def loc(build_dir):
    return load_localizer(build_dir, LocalizerConfig(mode="full", corridor_m=8.0, posterior_k=K))


def check_loc_info(info, k=K):
    assert LOC_KEYS <= set(info)
    assert info["posterior_poses"].shape == (k, 3) and info["posterior_poses"].dtype == np.float64
    assert info["posterior_probs"].shape == (k,) and info["posterior_probs"].dtype == np.float64
    assert info["estimate"].shape == (3,) and info["estimate"].dtype == np.float64
    for key, t in (("error_m", np.float64), ("inlier", np.bool_), ("inlier_score", np.float64),
                   ("localized_step", np.int64)):
        assert type(info[key]) is t, key
    est, pose = info["estimate"], info["pose"]
    if np.isfinite(pose).all():
        assert info["error_m"] == pytest.approx(math.hypot(est[0] - pose[0], est[1] - pose[1]), abs=1e-12)


def replay(env, seed=0, actions=None, options=None):
    obs, info = env.reset(seed=seed, options=options)
    out = [(obs, info, 0.0, False)]
    for a in actions or itertools.repeat(1):   # default: action 1 until truncated
        obs, r, term, trunc, info = env.step(a)
        assert term is False
        out.append((obs, info, r, trunc))
        if trunc:
            break
    return out


def test_steps_through_the_data_with_its_poses_odometry_and_truncation(seq):
    env = gym.make(ID, sequence=seq, odometry_noise=(0.0, 0.0), depth=True)
    steps = replay(env)
    assert len(steps) == N and [s[3] for s in steps] == [False] * (N - 1) + [True]  # truncated at the last frame
    poses, stamps = seq.poses, seq.timestamps
    for i, (obs, info, r, _) in enumerate(steps):
        assert set(info) == BASE_KEYS | {"depth_from_stereo"} and r == 0.0
        assert env.observation_space.contains(obs)
        assert info["frame_index"] == i and info["step"] == i and type(info["frame_index"]) is np.int64
        assert np.array_equal(info["pose"], poses[i]) and info["timestamp"] == stamps[i]
        frame = seq[i]
        assert np.array_equal(obs["left"], frame.left) and np.array_equal(obs["right"], frame.right)
        # the sequence stores true depth: the observation is that, not stereo
        assert not info["depth_from_stereo"] and np.array_equal(obs["depth"], frame.depth)
        assert info["odometry_valid"]
        if i == 0:
            assert not obs["odometry"].any() and not info["odometry_true"].any()
        else:  # noise 0: the data's relative motion, in the previous frame's vehicle frame
            want = relative_motion(Pose2(*poses[i - 1]), Pose2(*poses[i]))
            assert info["odometry_true"] == pytest.approx(want, abs=1e-12)
            assert obs["odometry"].dtype == np.float32 and obs["odometry"] == pytest.approx(want, abs=1e-5)
            assert 2.9 < want[0] < 3.3  # a frame every 3 m, straight ahead
    # integrating the observed odometry reproduces the last pose
    p = Pose2(*poses[0])
    for obs, *_ in steps[1:]:
        p = p @ Pose2(*obs["odometry"].astype(np.float64))
    assert p.distance(Pose2(*poses[-1])) < 1e-3
    with pytest.raises(RuntimeError, match="end of the data"):
        env.step(1)
    env.close()


def test_skip_action_stride_start_and_end(seq):
    env = gym.make(ID, sequence=seq, odometry_noise=(0.0, 0.0), max_skip=3, stride=2)
    assert env.action_space == gym.spaces.Discrete(3, start=1)
    steps = replay(env, actions=[1, 3, 3])
    # 0 -> 2 -> 6 (a skip of 3 strides would pass the last frame, 7: stopped at the last whole stride)
    assert [int(s[1]["frame_index"]) for s in steps] == [0, 2, 6] and steps[-1][3]
    poses = seq.poses
    assert steps[2][1]["odometry_true"] == pytest.approx(relative_motion(Pose2(*poses[2]), Pose2(*poses[6])))
    for bad in (0, 4, 1.0, "1", [1, 2]):
        env.reset(seed=0)
        with pytest.raises(ValueError, match=r"action: expected an integer skip count in \[1, 3\]"):
            env.unwrapped.step(bad)
    # per-episode start and end; the default action space is the single action 1 (advance one stride)
    plain = gym.make(ID, sequence=seq, odometry_noise=(0.0, 0.0))
    assert plain.action_space == gym.spaces.Discrete(1, start=1)
    steps = replay(plain, options={"start_frame": 2, "end_frame": 5})
    assert [int(s[1]["frame_index"]) for s in steps] == [2, 3, 4] and steps[-1][3]
    steps = replay(plain)   # options hold for that episode only
    assert int(steps[-1][1]["frame_index"]) == N - 1
    plain.reset(seed=0)
    with pytest.raises(ValueError, match=r"\[1, 1\], got 2"):
        plain.unwrapped.step(2)
    env.close(), plain.close()


def test_localizer_info_has_satloc_v0_contract(seq, loc):
    env = gym.make(ID, sequence=seq, localizer=loc, reward="neg_error", render_mode="rgb_array")
    assert env.unwrapped.config.localizer == "<instance>" and env.unwrapped.config.localizer_mode == "full"
    steps = replay(env)
    errors = []
    for obs, info, r, _ in steps:
        check_loc_info(info)
        assert info["localized_step"] == info["step"]
        assert set(info) == BASE_KEYS | LOC_KEYS
        if info["step"] > 0:
            assert r == -float(info["error_m"])
        errors.append(float(info["error_m"]))
    # 0.5 m beside the database lane with a mild appearance change, on the default captured map (measured:
    # 0.18-1.60 m; 0.01-0.42 m on the ground's copy)
    assert np.all(np.isfinite(errors)) and max(errors) < 2.5 and np.median(errors) < 0.8
    # the same keys, dtypes and shapes as SatLoc-v0 with the same localizer
    drive = gym.make("satloc/SatLoc-v0", scene="city", localizer=loc)
    _, dinfo = drive.reset(seed=0)
    info = steps[-1][1]
    for key in LOC_KEYS | {"pose", "odometry_true", "step"}:
        a, b = np.asarray(info[key]), np.asarray(dinfo[key])
        assert (type(info[key]), a.shape, a.dtype) == (type(dinfo[key]), b.shape, b.dtype), key
    drive.close(), env.close()


def test_localize_every_and_tracking_use_the_observed_odometry(seq, loc, monkeypatch):
    seen = []
    real_predict = Tracker.predict
    monkeypatch.setattr(Tracker, "predict", lambda self, o: seen.append(np.array(o)) or real_predict(self, o))
    env = gym.make(ID, sequence=seq, localizer=loc, localizer_track=True, localize_every=2)
    steps = replay(env)
    assert [int(s[1]["localized_step"]) for s in steps] == [0, 0, 2, 2, 4, 4, 6, 6]
    odo = [s[0]["odometry"].astype(np.float64) for s in steps]
    # localized at steps 0, 2, 4, 6: the first with no odometry (a new belief), the others moved by the two noisy
    # odometry observations since, composed
    assert len(seen) == 3
    for j, s in enumerate((1, 3, 5)):
        assert seen[j] == pytest.approx(compose_motion(odo[s], odo[s + 1]), abs=1e-9)
        assert not np.allclose(odo[s], steps[s][1]["odometry_true"])   # noisy, not the true motion
    tracker = env.unwrapped.localizer.tracker
    assert np.allclose(steps[-1][1]["posterior_probs"], np.sort(tracker.belief)[::-1][:K])
    for _, info, *_ in steps:
        check_loc_info(info)
    # at the steps localized (in between, the error grows by the 3.2 m driven since: no propagation)
    errors = [float(i["error_m"]) for _, i, *_ in steps if i["localized_step"] == i["step"]]
    assert len(errors) == 4 and max(errors) < 1.5
    env.reset(seed=1)  # a new episode: a new belief
    assert env.unwrapped.localizer.tracker is not tracker
    env.close()


def test_frames_without_a_pose(seq, loc, monkeypatch):
    frames = [seq[i] for i in range(N)]
    frames[3] = dataclasses.replace(frames[3], pose=None)
    holey = Sequence(seq.camera, frames, "holey")
    assert np.isnan(holey.poses[3]).all()
    resets = []
    real_reset = Tracker.reset
    monkeypatch.setattr(Tracker, "reset", lambda self: resets.append(1) or real_reset(self))
    env = gym.make(ID, sequence=holey, localizer=loc, localizer_track=True, odometry_noise=(0.0, 0.0),
                   render_mode="rgb_array")
    steps = replay(env)
    shape = None
    for i, (obs, info, _, _) in enumerate(steps):
        check_loc_info(info)
        assert env.observation_space.contains(obs)
        unknown = i in (3, 4)   # the motion into and out of the frame without a pose
        assert bool(info["odometry_valid"]) == (not unknown)
        if unknown:
            assert not obs["odometry"].any() and np.isnan(info["odometry_true"]).all()
        if i == 3:
            assert np.isnan(info["pose"]).all() and np.isnan(info["error_m"])
            assert np.isfinite(info["estimate"]).all()   # localized all the same
        else:
            assert np.isfinite(info["error_m"]) and info["error_m"] < 3.0
        img = env.render()   # no truth to draw at frame 3: centred on the estimate
        assert shape is None or img.shape == shape
        shape = img.shape
    # the belief starts again at each localization after an unknown motion: at frames 3 and 4
    assert len(resets) == 2
    env.close()


def test_a_lazy_sequence_replays_like_its_directory(rec, seq):
    lazy = Sequence.lazy(seq.camera, seq.poses, seq.timestamps, lambda i: seq[i], "lazy", seq.meta)
    kw = dict(odometry_noise=(0.05, 0.01), random_start=True, depth=True)
    a = gym.make(ID, sequence=str(rec / "query"), **kw)
    b = gym.make(ID, sequence=lazy, **kw)
    ra, rb = replay(a, seed=3), replay(b, seed=3)
    assert len(ra) == len(rb)
    for (oa, ia, *_), (ob, ib, *_) in zip(ra, rb):
        for k in oa:
            assert np.array_equal(oa[k], ob[k]), k
        for k in ia:
            assert np.array_equal(ia[k], ib[k]), k
    a.close(), b.close()


def test_determinism_same_seed_same_info(seq, loc):
    kw = dict(sequence=seq, localizer=loc, localizer_track=True, odometry_noise=(0.05, 0.01), random_start=True)
    a, b = gym.make(ID, **kw), gym.make(ID, **kw)
    ra, rb = replay(a, seed=5), replay(b, seed=5)
    for (oa, ia, *_), (ob, ib, *_) in zip(ra, rb):
        for k in oa:
            assert np.array_equal(oa[k], ob[k]), k
        for k in ia:
            assert np.array_equal(ia[k], ib[k]), k
    rc = replay(a, seed=6)
    odo = lambda r: np.array([s[0]["odometry"] for s in r[1:3]])  # noqa: E731
    assert not np.array_equal(odo(ra), odo(rc))   # another seed, other noise (or another start)
    a.close(), b.close()


def test_check_env_and_spec_shares_the_objects(seq, loc):
    env = gym.make(ID, sequence=seq, localizer=loc, depth=True, max_skip=2)
    check_env(env.unwrapped, skip_render_check=True)   # also re-creates the env from env.spec
    again = env.spec.make()
    assert again.unwrapped.localizer.engine is loc and again.unwrapped.sequence is seq   # shared, never copied
    again.close(), env.close()
    plain = gym.make(ID, sequence=seq)
    check_env(plain.unwrapped, skip_render_check=True)
    plain.close()


def test_stereo_depth_when_the_sequence_has_none(seq):
    frames = [dataclasses.replace(seq[i], depth=None) for i in range(3)]
    env = gym.make(ID, sequence=Sequence(seq.camera, frames, "nodepth"), depth=True)
    obs, info = env.reset(seed=0)
    assert info["depth_from_stereo"] and env.observation_space.contains(obs)
    d, true = obs["depth"], seq[0].depth
    ok = (d > 0) & (true > 0) & (true < 30)
    assert ok.mean() > 0.2
    assert np.median(np.abs(d[ok] - true[ok]) / true[ok]) < 0.05   # stereo, close to the true depth
    env.close()


def test_render_over_the_sequences_map(rec, seq, loc, build_dir):
    with_loc = gym.make(ID, sequence=str(rec / "query"), map=str(rec / "map"), localizer=loc,
                        render_mode="rgb_array")
    plain = gym.make(ID, sequence=str(rec / "query"), render_mode="rgb_array")   # map: rec/map, beside it
    with_loc.reset(seed=0), plain.reset(seed=0)
    a, b = with_loc.render(), plain.render()
    sm = SatelliteMap.load(rec / "map")
    assert np.array_equal(plain.unwrapped.map.image, sm.image)
    # the same panels as SatLoc-v0's compose_view over that map and the sequence's path
    frame0 = seq[0]
    want = compose_view(frame0.left, sm, Pose2(*seq.poses[0]), seq.poses)
    assert b.shape == a.shape == want.shape and a.shape[0] == PANEL_PX and np.array_equal(b, want)
    cam_w = a.shape[1] - 2 * PANEL_PX
    assert np.array_equal(a[:, :cam_w], b[:, :cam_w])
    changed = np.any(a[:, cam_w:cam_w + PANEL_PX] != b[:, cam_w:cam_w + PANEL_PX], axis=2)
    assert changed.sum() > 2000   # the posterior heatmap and the estimate
    # a sequence with no map anywhere: a grey canvas around its path
    mem = Sequence(seq.camera, [seq[i] for i in range(3)], "mem")
    blank = gym.make(ID, sequence=mem, render_mode="rgb_array", localizer=str(build_dir), localizer_mode="go")
    blank.reset(seed=0)
    m = blank.unwrapped.map
    assert m.contains(seq.poses[:3, :2], margin_m=30).all() and len(np.unique(m.image)) == 1
    assert blank.render().shape == a.shape
    # a map object is used as it is
    obj = gym.make(ID, sequence=mem, map=sm, render_mode="rgb_array")
    assert obj.unwrapped.map is sm and obj.unwrapped.config.map == "<instance>"
    with_loc.close(), plain.close(), blank.close(), obj.close()


def test_map_in_another_geo_frame_is_refused(seq):
    from satloc.geoframe import GeoFrame

    mem = Sequence(seq.camera, [seq[i] for i in range(2)], "geo",
                   {"geo_frame": GeoFrame(8.43, 49.01).to_dict()})
    sm = SatelliteMap(np.zeros((100, 100, 3), np.uint8), 0.5, (0.0, 50.0))
    sm.frame = GeoFrame(8.44, 49.01)
    with pytest.raises(ConfigError, match="map: its geographic frame .* is not the frame of sequence 'geo'"):
        gym.make(ID, sequence=mem, map=sm)
    sm.frame = GeoFrame(8.43, 49.01)
    gym.make(ID, sequence=mem, map=sm).close()


def test_oxts_odometry_needs_a_kitti_drive(seq):
    env = gym.make(ID, sequence=seq)
    with pytest.raises(ConfigError, match="odometry: 'oxts' reads a KITTI drive's motion sensors"):
        env.reset(seed=0, options={"odometry": "oxts"})
    env.close()


def test_config_errors(rec, seq, loc, build_dir, tmp_path):
    other_cam = Sequence(dataclasses.replace(seq.camera, pitch=0.05), [seq[i] for i in range(2)], "pitched")
    one = Sequence(seq.camera, [seq[0]], "one")
    bad = [
        (dict(), "a sequence is required"),
        (dict(sequence=seq, scene="city"), r"unknown key\(s\) \['scene'\]"),
        (dict(sequence="<instance>"), "pass the object itself"),
        (dict(sequence=42), "config.sequence: expected a sequence directory or a satloc.sequence.Sequence"),
        (dict(sequence=seq, map=np.zeros((4, 4, 3), np.uint8)), "config.map: expected None, a map directory"),
        (dict(sequence=seq, localizer="auto"), "'auto' builds a localizer from a simulated scene"),
        (dict(sequence=seq, localizer=str(tmp_path)), "is not a build directory"),
        (dict(sequence=seq, localizer=3.5), "SatLocReplayEnv config.localizer: expected None, 'none', 'cross', a build"),
        (dict(sequence=other_cam, localizer=loc), r"built for another camera than that of sequence 'pitched'.*pitch 0 vs 0.05"),
        (dict(sequence=seq, reward="neg_error"), "needs a localizer"),
        (dict(sequence=seq, localizer_track=True), "tracking needs a localizer"),
        (dict(sequence=seq, localizer=loc, localize_every=0), "localize_every: expected an integer >= 1"),
        (dict(sequence=seq, start_frame=7), r"start_frame: expected an index in \[0, 6\]"),
        (dict(sequence=seq, end_frame=9), r"end_frame: expected an index in \[1, 8\]"),
        (dict(sequence=seq, stride=0), "stride: expected an integer >= 1"),
        (dict(sequence=seq, max_skip=0), "max_skip: expected an integer >= 1"),
        (dict(sequence=seq, odometry_noise=(0.1, -1.0)), "odometry_noise: expected 2 non-negative numbers"),
        (dict(sequence=one), "has 1 frame"),
        (dict(sequence=seq, map=str(tmp_path / "nomap")), "nomap' not found; expected None, a map directory"),
        (dict(sequence=str(tmp_path / "none")), "none: not a sequence: expected a satloc sequence folder"),
    ]
    for kw, msg in bad:
        with pytest.raises(ConfigError, match=msg):
            gym.make(ID, **kw)
    env = gym.make(ID, sequence=seq)
    for opts, msg in (({"localizer": None}, r"\['localizer'\] cannot change per episode"),
                      ({"frame": 1}, "cannot change per episode"),
                      ({"start_frame": 99}, "reset options: start_frame"),
                      ({"stride": 4, "start_frame": 4}, r"start_frame: expected an index in \[0, 3\]")):
        with pytest.raises(ConfigError, match=msg):
            env.reset(seed=0, options=opts)
    assert EPISODE_KEYS == {"start_frame", "end_frame", "random_start", "stride", "odometry", "odometry_noise"}
    assert SatLocReplayEnv.default_config()["localizer"] is None
    env.close()


def test_map_from_georeferenced_imagery(tmp_path, monkeypatch):
    """``map=`` a GeoTIFF: read into the sequence's GeoFrame around its path; lon/lat marks land where they lie."""
    from geofixtures import REF, UTM, make_geotiff, mark_errors

    tif, _, _ = make_geotiff(tmp_path / "area.tif", UTM)
    cam = SatLocEnv(localizer=None).camera
    img = np.zeros((cam.height, cam.width, 3), np.uint8)
    # two frames near the red mark (-123, 61 m from the fixture's reference), in a frame 30 m east of it
    frame = type(REF)(*REF.to_lonlat(np.array([30.0, 0.0])))
    frames = [Frame(img, img, Pose2(x, 55.0, 0.0), 0.1 * i) for i, x in enumerate((-160.0, -145.0))]
    seq = Sequence(cam, frames, "geo", {"geo_frame": frame.to_dict()})
    env = gym.make(ID, sequence=seq, map=str(tif), render_mode="rgb_array")
    env.reset(seed=0)
    sm = env.unwrapped.map
    assert sm.frame == frame
    sm.check_covers(seq.poses[:, :2], "the path", margin_m=30.0)
    errs = mark_errors(sm)     # the mark inside the loaded window lies where its lon/lat says
    assert errs["red"] < 1.0 and math.isinf(errs["blue"]), errs
    assert env.render().shape[0] == PANEL_PX
    # a path longer than MAX_MAP_PX pixels of the image's own resolution: read coarser, never larger
    import satloc_env.envs.replay as replay_module

    monkeypatch.setattr(replay_module, "MAX_MAP_PX", 64)
    coarse = gym.make(ID, sequence=seq, map=str(tif)).unwrapped.map
    assert max(coarse.shape[:2]) <= 65 and coarse.meters_per_pixel > 1.4 and coarse.frame == frame
    coarse.check_covers(seq.poses[:, :2], "the path", margin_m=30.0)
    with pytest.raises(ConfigError, match="no meta\\['geo_frame'\\]"):
        gym.make(ID, sequence=Sequence(cam, frames, "plain"), map=str(tif)).reset(seed=0)
    with pytest.raises(ConfigError, match="not found"):
        gym.make(ID, sequence=seq, map=str(tmp_path / "nothing.tif")).reset(seed=0)


@pytest.mark.skipif(not __import__("realfixtures").REAL.is_dir(), reason="shared KITTI fixture absent")
def test_real_kitti_drive_replayed_with_a_localizer_built_from_it(tmp_path):
    """The real 7-frame KITTI excerpt given as its drive folder: the env reads it with the KITTI reader,
    resamples it into the half-resolution camera of a localizer built from it (against a LiDAR ground mosaic of
    its own frames: no real satellite imagery is available here), and reports a finite error at every frame."""
    from realfixtures import REAL, lidar_mosaic

    from satloc.datasets import load_kitti
    from satloc.geodata.georef import load_map
    from satloc.geoframe import GeoFrame
    from satloc.pipeline import build, train_projection

    lidar_mosaic(REAL, tmp_path / "mosaic.tif")
    seq = load_kitti(REAL)
    half = seq.camera.resized(621, 188)
    sm = load_map(tmp_path / "mosaic.tif", 0.2, GeoFrame.from_dict(seq.meta["geo_frame"]))
    build(seq.view(None, half), sm, tmp_path / "build", BuildConfig(features="rgb"), progress=False)
    train_projection(tmp_path / "build", ProjectionConfig(max_anchors=2000, max_epochs=2), progress=False)
    env = gym.make(ID, sequence=str(REAL), map=str(tmp_path / "mosaic.tif"), localizer=str(tmp_path / "build"),
                   localizer_refine=True, render_mode="rgb_array")
    check_env(env.unwrapped, skip_render_check=True)
    obs, info = env.reset(seed=0)
    assert obs["left"].shape == (188, 621, 3) and env.unwrapped.sequence.meta["source"] == "kitti_raw"
    errors = [info["error_m"]]
    truncated = False
    while not truncated:
        obs, _, _, truncated, info = env.step(1)
        errors.append(info["error_m"])
    assert len(errors) == 7 and np.all(np.isfinite(errors))
    # the map is made from these very frames, so this bounds the chain (calibration, resampling, georeference),
    # not the method's accuracy against satellite imagery
    assert np.median(errors) < 1.0, errors
    assert env.render().shape[0] == PANEL_PX
    # the drive's own sensors as the odometry observation: OXTS speed and yaw rate, and stereo visual odometry
    for kind, tol in (("oxts", 0.1), ("visual", 0.1)):   # steps of 0.89-0.98 m, the poses' timing jitters
        obs, info = env.reset(seed=0, options={"odometry": kind})
        truncated = False
        while not truncated:
            obs, _, _, truncated, info = env.step(1)
            assert info["odometry_valid"], kind
            err = np.abs(obs["odometry"].astype(np.float64) - info["odometry_true"])
            assert err[0] < tol and err[1] < tol and err[2] < 0.01, (kind, err)


def test_a_recording_in_another_resolution_is_resampled_and_keeps_its_map(rec, seq, loc, tmp_path):
    """A recording at twice the localizer's resolution: replayed in the localizer's camera, and its ``map/``
    beside it is still the default map (the resampled view has no folder of its own)."""
    import shutil

    big = seq.camera.resized(2 * seq.camera.width, 2 * seq.camera.height)
    seq.view(range(3), big).save(tmp_path / "rec" / "query")
    shutil.copytree(rec / "map", tmp_path / "rec" / "map")
    env = gym.make(ID, sequence=str(tmp_path / "rec" / "query"), localizer=loc, render_mode="rgb_array")
    obs, info = env.reset(seed=0)
    assert env.unwrapped.camera == loc.camera and obs["left"].shape == seq[0].left.shape
    # up and down again: the original frame, but for the resampling's blur
    assert np.mean(np.abs(obs["left"].astype(int) - seq[0].left.astype(int))) < 6
    assert np.isfinite(info["error_m"]) and info["error_m"] < 1.5
    assert np.array_equal(env.unwrapped.map.image, SatelliteMap.load(rec / "map").image)
    env.close()
