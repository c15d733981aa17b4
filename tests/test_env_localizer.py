"""The localizer in the environment loop (``localizer=``, ``localize_every``, ``reward``, the render panels)
and the on-disk cache of ``localizer="auto"``.

The real "auto" build of a shipped scene takes minutes, so the module builds one small entry (the first
frames of the city database pass, RGB features, a short projection training) through the same cache code,
and points the other cases at it.
"""
import math
import os

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import satloc_env  # noqa: F401  (registers the ids)
from satloc import ConfigError
from satloc.features.projection import ProjectionConfig
from satloc.localizers.database import LocalizerConfig
from satloc.persist import read_json
from satloc.pipeline import BuildConfig, load_localizer
from satloc.tracking.track import Tracker, compose_motion
from satloc_env.envs import auto_localizer as autoloc
from satloc_env.envs.drive import ESTIMATE_RGB, PANEL_PX, PosteriorView, compose_view

ID = "satloc/SatLoc-v0"
K = 16  # posterior_k of the small localizer (the default is 32)
SMALL = dict(max_frames=25, build_config=BuildConfig(features="rgb"),
             projection_config=ProjectionConfig(max_anchors=2000, max_epochs=2))
LOC_KEYS = {"posterior_poses", "posterior_probs", "estimate", "error_m", "inlier", "inlier_score", "localized_step"}


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("satloc_cache")


@pytest.fixture(scope="module")
def build_dir(cache):
    return autoloc.auto_build_dir("city", None, "half", progress=False, cache_dir=cache, **SMALL)


@pytest.fixture(scope="module")
def loc(build_dir):
    # a narrow satellite-table corridor keeps loading fast; the first ~40 m of the route are mapped
    return load_localizer(build_dir, LocalizerConfig(mode="full", corridor_m=8.0, posterior_k=K))


def autopilot(env):
    return env.unwrapped.autopilot_action()


def check_info(info, k=K):
    assert LOC_KEYS <= set(info)
    assert info["posterior_poses"].shape == (k, 3) and info["posterior_poses"].dtype == np.float64
    assert info["posterior_probs"].shape == (k,) and info["posterior_probs"].dtype == np.float64
    assert info["estimate"].shape == (3,) and info["estimate"].dtype == np.float64
    for key, t in (("error_m", np.float64), ("inlier", np.bool_), ("inlier_score", np.float64),
                   ("localized_step", np.int64)):
        assert type(info[key]) is t, key
    p = info["posterior_probs"]
    assert np.all(np.diff(p) <= 0) and 0 < p.sum() <= 1 + 1e-9
    est, pose = info["estimate"], info["pose"]
    assert info["error_m"] == pytest.approx(math.hypot(est[0] - pose[0], est[1] - pose[1]), abs=1e-12)


def test_info_reward_and_render_with_a_localizer_instance(loc):
    env = gym.make(ID, scene="city", localizer=loc, reward="neg_error", render_mode="rgb_array")
    plain = gym.make(ID, scene="city", localizer=None, render_mode="rgb_array")
    obs, info = env.reset(seed=0)
    obs0, _ = plain.reset(seed=0)
    assert env.unwrapped.config.localizer == "<instance>" and env.unwrapped.config.localizer_mode == "full"
    check_info(info)
    assert info["localized_step"] == 0
    frame, frame0 = env.render(), plain.render()
    assert frame.shape == frame0.shape and frame.shape[0] == PANEL_PX
    cam_w = frame.shape[1] - 2 * PANEL_PX
    # localization leaves the camera alone and draws the posterior, estimate and error on the map panels
    assert np.array_equal(frame[:, :cam_w], frame0[:, :cam_w])
    changed = np.any(frame[:, cam_w:cam_w + PANEL_PX] != frame0[:, cam_w:cam_w + PANEL_PX], axis=2)
    assert changed.sum() > 2000
    for _ in range(3):
        a = autopilot(env)
        obs, r, term, trunc, info = env.step(a)
        obs0, *_ = plain.step(a)
        check_info(info)
        assert info["localized_step"] == info["step"]
        assert r == -float(info["error_m"])
        assert env.render().shape == frame.shape
        for key in obs:  # the localizer draws nothing from the episode's RNG: same observations
            assert np.array_equal(obs[key], obs0[key]), key
    # on its own database pass the estimate is within a couple of metres
    assert info["error_m"] < 2.0 and bool(info["inlier"])
    env.close(), plain.close()


def test_localize_every_recomputes_every_n_steps(loc, monkeypatch):
    calls = []
    real = loc.localize
    monkeypatch.setattr(loc, "localize", lambda frame, *a, **k: calls.append(1) or real(frame, *a, **k))
    env = gym.make(ID, scene="city", localizer=loc, localize_every=3)
    _, info = env.reset(seed=0)
    infos = [info]
    for _ in range(7):
        infos.append(env.step(autopilot(env))[4])
    assert len(calls) == 3  # steps 0, 3, 6
    assert [int(i["localized_step"]) for i in infos] == [0, 0, 0, 3, 3, 3, 6, 6]
    for i in infos:
        check_info(i)  # error_m follows the current pose
    assert np.array_equal(infos[1]["estimate"], infos[2]["estimate"])
    assert infos[1]["error_m"] != infos[2]["error_m"]
    assert not np.array_equal(infos[2]["estimate"], infos[3]["estimate"])
    env.close()


def test_tracking_moves_the_belief_with_the_observed_odometry(loc, monkeypatch):
    env = gym.make(ID, scene="city", localizer=loc, localizer_track=True, localize_every=2)
    seen = []
    real_predict = Tracker.predict
    monkeypatch.setattr(Tracker, "predict", lambda self, o: seen.append(np.array(o)) or real_predict(self, o))
    _, info = env.reset(seed=0)
    check_info(info)
    tracker = env.unwrapped._tracker
    assert tracker is not None and tracker.belief is not None
    odo = []
    for _ in range(4):
        obs, _, _, _, info = env.step(autopilot(env))
        odo.append(obs["odometry"].astype(np.float64))
        check_info(info)
    # localized at steps 0 (no odometry: a new belief), 2 and 4: moved by the two noisy odometry observations
    # composed, each time
    assert len(seen) == 2
    assert seen[0] == pytest.approx(compose_motion(odo[0], odo[1]), abs=1e-9)
    assert seen[1] == pytest.approx(compose_motion(odo[2], odo[3]), abs=1e-9)
    assert np.allclose(info["posterior_probs"], np.sort(tracker.belief)[::-1][:K])
    assert info["error_m"] < 2.0
    env.reset(seed=1)   # a new episode: a new belief
    assert env.unwrapped._tracker is not tracker
    env.close()


def test_frame_without_valid_depth_reports_nan(loc):
    env = gym.make(ID, scene="city", localizer=loc, reward="neg_error", render_mode="rgb_array")
    env.reset(seed=0)
    shape = env.render().shape
    env.unwrapped.appearance = np.zeros_like  # black images: no stereo depth anywhere
    _, r, _, _, info = env.step(autopilot(env))
    assert set(info) >= LOC_KEYS and info["localized_step"] == 1
    assert np.isnan(info["estimate"]).all() and np.isnan(info["error_m"]) and not info["inlier"]
    assert info["posterior_probs"].shape == (K,) and not info["posterior_probs"].any()
    assert r == 0.0 and "no grid sample has valid depth" in env.unwrapped.localization_error
    assert env.render().shape == shape
    env.close()


def test_no_localizer_no_keys():
    for off in (None, "none"):
        env = gym.make(ID, scene="city", localizer=off)
        _, info = env.reset(seed=0)
        _, r, *_, info2 = env.step(autopilot(env))
        assert not (LOC_KEYS & set(info)) and not (LOC_KEYS & set(info2)) and r == 0.0
        assert env.unwrapped.localizer is None and env.unwrapped.config.localizer is None
        env.close()


def test_config_errors(loc, build_dir, tmp_path):
    bad = [
        (dict(reward="distance"), r"reward: expected one of \['none', 'neg_error'\]"),
        (dict(localizer=None, reward="neg_error"), "needs a localizer"),
        (dict(localizer="none", localizer_track=True), "localizer_track: tracking needs a localizer"),
        (dict(localizer=None, localize_every=0), "localize_every: expected an integer >= 1"),
        (dict(localizer=str(build_dir), localizer_mode="fast"), "localizer_mode: expected one of"),
        (dict(localizer=str(tmp_path / "nope")), "is not a build directory"),
        (dict(localizer=42), "expected None, 'none', 'cross', 'auto', a build directory, 'module:Name', or a "
                             "localizer object"),
        (dict(localizer="<instance>"), "pass the object itself"),
        (dict(localizer=loc, resolution="full"), "built for 620x188 images"),
    ]
    for kw, msg in bad:
        with pytest.raises(ConfigError, match=msg):
            gym.make(ID, scene="city", **kw)
    with pytest.raises(ConfigError, match="needs learned projections|no projections.pt"):
        # a build without projections cannot be loaded in mode full
        b = tmp_path / "b"
        b.mkdir()
        for f in ("build.json", "dictionary.npz", "satellite_features.npz"):
            os.symlink(build_dir / f, b / f)
        gym.make(ID, scene="city", localizer=str(b))


def test_localizer_of_another_map_is_refused(loc):
    from types import SimpleNamespace

    from satloc import SatelliteMap

    env = gym.make(ID, scene="city", localizer=loc)
    other = SimpleNamespace(name="other", satmap=SatelliteMap(np.zeros((50, 60, 3), np.uint8), 0.2, (0.0, 10.0)))
    with pytest.raises(ConfigError, match="is not the map of scene 'other'"):
        env.unwrapped._check_localizer_map(other)  # what reset does when the scene changes
    env.unwrapped._check_localizer_map(satloc_env.load_scene("city"))
    env.close()


def test_localizer_of_a_captured_map_is_refused_on_the_copy(build_dir, cache):
    """A build made on the default capture (satellite_gap 0.5) does not localize on the same scene's ground
    copy (gap 0): the map check compares content, and the auto localizer's cache keeps the two apart (entries
    at gap 0 keep the names of before)."""
    with pytest.raises(ConfigError, match="captured at satellite_gap 0.5, not on the map at 0"):
        gym.make(ID, scene="city", localizer=str(build_dir), satellite_gap=0.0)
    # a Localizer instance (no record of its data): its map's content is compared
    with pytest.raises(ConfigError, match="is not the map of scene 'city'"):
        gym.make(ID, scene="city", localizer=load_localizer(build_dir, LocalizerConfig(mode="go")), satellite_gap=0.0)
    a = autoloc.build_path("city", None, "half", cache_dir=cache, **SMALL)
    b = autoloc.build_path("city", None, "half", satellite_gap=0.0, cache_dir=cache, **SMALL)
    assert a == build_dir and b != a and "gap0.5" in a.name and "gap" not in b.name
    assert autoloc.build_path("city", None, "half", satellite_gap=0.5, cache_dir=cache, **SMALL) == a


def test_build_dir_path_and_auto(build_dir, tmp_path, monkeypatch):
    env = gym.make(ID, scene="city", localizer=str(build_dir), localizer_mode="go")
    _, info = env.reset(seed=0)
    assert env.unwrapped.localizer.engine.config.mode == "go"
    check_info(info, k=LocalizerConfig().posterior_k)
    # "auto" with the default settings: serve the small build from the cache location of the default key
    monkeypatch.setenv("SATLOC_CACHE", str(tmp_path / "cache"))
    entry = autoloc.build_path("city", None, "half")
    assert entry.parent == tmp_path / "cache"
    entry.parent.mkdir()
    entry.symlink_to(build_dir, target_is_directory=True)
    monkeypatch.setattr(autoloc, "_build_entry", lambda *a, **k: pytest.fail("cache hit expected"))
    auto = gym.make(ID, scene="city", localizer="auto", localizer_mode="go")
    assert auto.unwrapped.config.localizer == "auto" and auto.unwrapped.localizer is None  # resolved at reset
    _, info = auto.reset(seed=0)
    check_info(info, k=LocalizerConfig().posterior_k)
    assert auto.unwrapped.localizer.engine is env.unwrapped.localizer.engine  # loaded once per process
    # the refined localizer is another one (its own cache slot), and reports an aligned estimate
    ref = gym.make(ID, scene="city", localizer=str(build_dir), localizer_mode="go", localizer_refine=True)
    _, info_r = ref.reset(seed=0)
    assert ref.unwrapped.localizer.engine is not env.unwrapped.localizer.engine
    assert ref.unwrapped.localizer.engine.config.refine
    check_info(info_r, k=LocalizerConfig().posterior_k)
    assert info_r["error_m"] <= info["error_m"] + 0.5
    env.close(), auto.close(), ref.close()


def test_auto_cache_hits_the_second_time(build_dir, cache, monkeypatch):
    assert autoloc.is_complete(build_dir) and build_dir.parent == cache
    assert not (build_dir / "recording").exists()
    assert not [p for p in cache.iterdir() if p.name.endswith(".tmp")]
    key = autoloc.describe_entry(build_dir)
    assert key["scene"] == "city" and key["aliasing"] == 0.0 and key["resolution"] == "half"
    db = key["database_pass"]
    assert (db["max_frames"], db["lane_offset_m"], db["occlusion"], db["appearance"]) == (25, -1.75, 0.0, 0.0)
    assert read_json(build_dir / "build.json")["database_frames"] == 25
    monkeypatch.setattr(autoloc, "_build_entry", lambda *a, **k: pytest.fail("cache hit expected"))
    assert autoloc.auto_build_dir("city", 0.0, "half", progress=False, cache_dir=cache, **SMALL) == build_dir
    # the key separates what changes the build, and only that
    path = lambda *a, **k: autoloc.build_path(*a, **{**SMALL, "cache_dir": cache, **k})  # noqa: E731
    assert path("city", None, "half") == path(os.path.join(autoloc.SCENES_DIR, "city.yaml"), 0.0, "half") == build_dir
    others = {path("city", 0.5, "half"), path("city", None, "full"), path("city", None, "half", max_frames=26),
              path("residential", None, "half"), path("city", None, "half", build_config=BuildConfig())}
    assert build_dir not in others and len(others) == 5
    monkeypatch.setenv("SATLOC_CACHE", "/x/y")
    assert str(autoloc.cache_root()) == "/x/y"
    monkeypatch.delenv("SATLOC_CACHE")
    monkeypatch.setenv("HOME", "/home/u")
    assert str(autoloc.cache_root()) == "/home/u/.cache/satloc"


def test_auto_cache_builds_atomically_and_repairs(tmp_path, monkeypatch):
    calls = []

    def fake_build(out, *a, **k):
        calls.append(out)
        assert out.parent == tmp_path and out.name.endswith(".tmp")  # built beside the entry, then renamed
        if len(calls) == 2:
            raise RuntimeError("interrupted")
        for f in autoloc.ENTRY_FILES[:-1]:
            (out / f).write_text("x")

    monkeypatch.setattr(autoloc, "_build_entry", fake_build)
    entry = autoloc.auto_build_dir("city", progress=False, cache_dir=tmp_path)
    assert autoloc.is_complete(entry) and len(calls) == 1
    assert autoloc.auto_build_dir("city", progress=False, cache_dir=tmp_path) == entry and len(calls) == 1
    (entry / "projections.pt").unlink()  # damaged entry: rebuilt; an interrupted build leaves nothing behind
    with pytest.raises(RuntimeError, match="interrupted"):
        autoloc.auto_build_dir("city", progress=False, cache_dir=tmp_path)
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
    assert autoloc.auto_build_dir("city", progress=False, cache_dir=tmp_path) == entry and len(calls) == 3
    assert autoloc.is_complete(entry)


def test_check_env_with_a_localizer_instance(loc):
    env = gym.make(ID, scene="city", localizer=loc)
    check_env(env.unwrapped, skip_render_check=True)  # also re-creates the env from env.spec
    again = env.spec.make()
    assert again.unwrapped.localizer.engine is loc  # the spec shares the instance, never copies it
    again.close(), env.close()


def test_overview_shows_a_far_off_estimate():
    scene = satloc_env.load_scene("city")
    route = scene.routes[scene.spec.database_route]
    pose = route.pose_at(0.0, -1.75)
    far = np.array([300.0, 40.0, 0.0])  # on the map, far outside the 80 m bird's-eye window
    assert scene.satmap.contains(far[:2]) and math.hypot(far[0] - pose.x, far[1] - pose.y) > 100
    cands = far + np.array([[dx, 0.0, 0.0] for dx in np.arange(-3, 3.5, 0.5)])
    view = PosteriorView(cands, np.full(len(cands), 1 / len(cands)), far)
    cam = np.zeros((188, 620, 3), np.uint8)
    with_est, without = compose_view(cam, scene, pose, route, view), compose_view(cam, scene, pose, route)
    assert with_est.shape == without.shape
    cam_w = with_est.shape[1] - 2 * PANEL_PX
    green = lambda img: np.all(np.abs(img.astype(int) - ESTIMATE_RGB) < 40, axis=2)  # noqa: E731
    bird = slice(cam_w, cam_w + PANEL_PX)
    ov = slice(cam_w + PANEL_PX, None)
    # the border arrow: green the view without an estimate does not have (the map has a few green-ish
    # texels of its own: awnings, cars)
    assert (green(with_est[:, bird]) & ~green(without[:, bird])).sum() > 20
    # in the overview, the estimate ring sits where the map puts it
    sm = scene.satmap
    s = PANEL_PX / max(sm.image.shape[:2])
    u, v = (sm.world_to_pixel(far[:2]) + 0.5) * s - 0.5
    g = green(with_est[:, ov]) & ~green(without[:, ov])
    ys, xs = np.nonzero(g)
    assert len(xs) > 10 and abs(xs.mean() - u) < 4 and abs(ys.mean() - v) < 4


def test_vector_env_with_a_localizer_equals_single_envs(loc):
    """The batched vector environment (satloc_env.envs.vector) localizes each car as a single environment does:
    tracked posteriors, estimates and rewards equal those of SyncVectorEnv over the same seeds (this small
    localizer has RGB features: no network, so the batched network call changes nothing)."""
    from test_vector import assert_same

    kw = dict(scene="city", localizer=loc, localizer_track=True, reward="neg_error")
    ref = gym.make_vec(ID, 2, vectorization_mode="sync", **kw)
    vec = gym.make_vec(ID, 2, vectorization_mode="vector_entry_point", **kw)
    try:
        assert_same(ref.reset(seed=4), vec.reset(seed=4), "reset")
        for t in range(3):
            act = vec.unwrapped.autopilot_actions()
            a, b = ref.step(act), vec.step(act)
            for x, y, name in zip(a, b, ("obs", "reward", "terminated", "truncated", "info")):
                assert_same(x, y, f"{name} at step {t}")
        assert b[4]["_error_m"].all() and (b[4]["localized_step"] == 3).all()
        assert (b[1] < 0).all()
    finally:
        ref.close()
        vec.close()


def test_auto_cache_key_holds_the_fcn_weights(monkeypatch, tmp_path):
    """Retrained FCN weights make another entry: its features would not match an entry made with others."""
    from satloc.features import pixelwise

    w = tmp_path / "fcn.pt"
    w.write_bytes(b"weights one")
    monkeypatch.setattr(pixelwise, "DEFAULT_WEIGHTS", w)
    fcn = dict(SMALL, build_config=BuildConfig())   # the default features: the FCN's
    one = autoloc.build_path("city", None, "half", cache_dir=tmp_path, **fcn)
    assert autoloc.cache_key("city", None, "half", **fcn)["features_id"].startswith("default:fcn-")
    assert autoloc.cache_key("city", None, "half", **SMALL)["features_id"] == "rgb"
    w.write_bytes(b"weights two")
    assert autoloc.build_path("city", None, "half", cache_dir=tmp_path, **fcn) != one
