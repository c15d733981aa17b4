import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import satloc_env  # noqa: F401  (registers the ids)
from satloc import ConfigError

# the driving envs (the replay env needs a recorded sequence: tests/test_replay.py runs check_env on it; the
# ActiveLoc env takes other settings: tests/test_active.py runs check_env on it)
IDS = [k for k in gym.registry if k.startswith("satloc/") and "Replay" not in k and "Active" not in k]


def test_ids_registered():
    assert "satloc/SatLoc-v0" in IDS


@pytest.mark.parametrize("env_id", IDS)
def test_check_env(env_id):
    # localizer=None: this checks the driving env's API; the default localizer="cross" would localize every
    # step, "auto" build the scene's localizer cache (minutes). tests/test_env_localizer.py runs check_env with
    # a small localizer.
    env = gym.make(env_id, scene="city", depth=True, labels=True, localizer=None)
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


def test_depth_is_bounded_by_the_far_plane_and_only_odometry_is_unbounded():
    """The depth Box is [0, zfar_m] and the rendered depth stays in it; check_env warns only about the
    odometry Box, the one observation with no finite bound (Gaussian noise; NaN from visual odometry)."""
    import warnings

    env = gym.make("satloc/SatLoc-v0", scene="city", depth=True, localizer=None, zfar_m=40.0)
    box = env.observation_space["depth"]
    assert float(box.low.min()) == 0.0 and float(box.high.max()) == 40.0
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        check_env(env.unwrapped, skip_render_check=True)
    infinite = [str(x.message) for x in w if "infinity" in str(x.message)]
    assert len(infinite) == 2   # the odometry's -inf and +inf
    assert np.all(np.isinf(env.observation_space["odometry"].high))
    obs, _ = env.reset(seed=0)
    for _ in range(20):
        obs, *_ = env.step(env.unwrapped.autopilot_action())
        assert box.contains(obs["depth"]) and obs["depth"].max() > 30.0   # the far road, near the far plane
    env.close()


def test_normalised_actions_for_rl_libraries():
    """RL libraries expect a symmetric, normalised action Box; gymnasium's RescaleAction maps [-1, 1]^2 onto
    SatLoc-v0's [0, 20] m/s x [-1, 1] rad/s (docs/environment.md's recipe). check_env's warning about the action space
    is gone on the wrapped env, and -1 is standstill, 0 half speed."""
    import warnings

    from gymnasium.wrappers import RescaleAction

    env = RescaleAction(gym.make("satloc/SatLoc-v0", scene="city", localizer=None), -1.0, 1.0)
    try:
        assert env.action_space.low.tolist() == [-1, -1] and env.action_space.high.tolist() == [1, 1]
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            check_env(env, skip_render_check=True)
        assert not [x for x in w if "action space" in str(x.message).lower() and "normal" in str(x.message).lower()]
        env.reset(seed=0)
        _, _, _, _, info = env.step(np.array([-1.0, 0.0], np.float32))
        assert np.hypot(*info["odometry_true"][:2]) < 1e-9
        _, _, _, _, info = env.step(np.array([0.0, 0.0], np.float32))
        assert np.hypot(*info["odometry_true"][:2]) == pytest.approx(10.0 * env.unwrapped.config.dt, rel=1e-6)
    finally:
        env.close()


def run(env, seed, n, options=None):
    obs, info = env.reset(seed=seed, options=options)
    out = [(obs, info)]
    for _ in range(n):
        obs, r, term, trunc, info = env.step(env.unwrapped.autopilot_action())
        out.append((obs, info))
    return out


def test_determinism_same_seed_same_actions():
    kw = dict(scene="city", depth=True, occlusion=0.8, appearance=0.7, random_start=True, localizer=None)
    a, b = gym.make("satloc/SatLoc-v0", **kw), gym.make("satloc/SatLoc-v0", **kw)
    ra, rb = run(a, 5, 6), run(b, 5, 6)
    for (oa, ia), (ob, ib) in zip(ra, rb):
        for k in oa:
            assert np.array_equal(oa[k], ob[k]), k
        for k in ia:
            assert np.array_equal(ia[k], ib[k]), k
    rc = run(a, 6, 0)
    assert not np.array_equal(rc[0][1]["pose"], ra[0][1]["pose"])
    a.close(), b.close()


def test_autopilot_drives_along_route_and_odometry_is_consistent():
    env = gym.make("satloc/SatLoc-v0", scene="city", localizer=None, odometry_noise=(0.0, 0.0))
    steps = run(env, 0, 60)
    info = steps[-1][1]
    assert 40 < float(info["route_s"]) < 60  # ~8 m/s for 6 s, slower at the corner
    assert not bool(info["off_road"])
    # integrating the (noise-free) odometry reproduces the true pose
    from satloc import Pose2
    p = Pose2.from_array(steps[0][1]["pose"])
    for obs, _ in steps[1:]:
        p = p @ Pose2.from_array(obs["odometry"].astype(np.float64))
    assert p.distance(Pose2.from_array(info["pose"])) < 1e-3
    env.close()


def test_leaving_the_road_terminates():
    env = gym.make("satloc/SatLoc-v0", scene="city", localizer=None)
    env.reset(seed=0)
    term = False
    for _ in range(40):
        _, _, term, _, info = env.step(np.array([10.0, 1.0], np.float32))  # circle off the road
        if term:
            break
    assert term and bool(info["off_road"])
    env.close()


def test_time_limit_truncates():
    env = gym.make("satloc/SatLoc-v0", scene="city", localizer=None, max_steps=3)
    env.reset(seed=0)
    truncs = [env.step(env.unwrapped.autopilot_action())[3] for _ in range(3)]
    assert truncs == [False, False, True]
    env.close()


def test_config_errors_and_reset_options():
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['fov'\]"):
        gym.make("satloc/SatLoc-v0", fov=90)
    env = gym.make("satloc/SatLoc-v0", scene="city", localizer=None)
    with pytest.raises(ConfigError, match="cannot change per episode"):
        env.reset(options={"resolution": "full"})
    with pytest.raises(ConfigError, match=r"occlusion: expected a value in \[0, 1\]"):
        env.reset(options={"occlusion": 3.0})
    obs, info = env.reset(seed=1, options={"lane_offset_m": 1.75, "occlusion": 1.0})
    assert env.unwrapped.pilot.offset == 1.75
    assert env.unwrapped.config.lane_offset_m == -1.75  # the options last one episode
    assert default_keys() == set(env.unwrapped.default_config())
    env.close()


def test_make_refuses_a_route_the_autopilot_cannot_drive():
    """gym.make checks the route at its lane offset as `satloc scene` does (the same message), before any
    episode; a reset option that moves the car off the road is refused the same way, nothing changed."""
    msg = r"SatLocEnv scene 'city': routes\.main: the autopilot leaves the road at .* lane offset -9 m"
    with pytest.raises(ConfigError, match=msg):
        gym.make("satloc/SatLoc-v0", scene="city", localizer=None, lane_offset_m=-9.0)
    env = gym.make("satloc/SatLoc-v0", scene="city", localizer=None)
    with pytest.raises(ConfigError, match=r"the autopilot leaves the road .* lane offset 9 m"):
        env.reset(seed=0, options={"lane_offset_m": 9.0})
    env.reset(seed=0)
    assert env.unwrapped.pilot.offset == -1.75
    env.close()


def default_keys():
    return set(satloc_env.SatLocEnv.default_config())


def test_occluders_appear_in_labels():
    """The episode's occluders (people, obstacles, cars the map does not show) appear in the labels: no person
    without them, and more person and obstacle pixels with them than the world's own street furniture (class
    obstacle, in worlds with variety) gives over the same drive."""
    from satloc.labels import CLASS_ID

    env = gym.make("satloc/SatLoc-v0", scene="city", localizer=None, labels=True)
    seen = {}
    for occlusion in (0.0, 1.0):
        obs, _ = env.reset(seed=2, options={"occlusion": occlusion})
        n = np.zeros(2, np.int64)
        for _ in range(30):
            obs, *_ = env.step(env.unwrapped.autopilot_action())
            n += [(obs["labels"] == CLASS_ID["person"]).sum(), (obs["labels"] == CLASS_ID["obstacle"]).sum()]
        seen[occlusion] = n
    assert seen[0.0][0] == 0 and seen[1.0][0] > 0, seen
    assert seen[1.0].sum() > seen[0.0].sum(), seen
    env.close()


def test_appearance_changes_colours_not_geometry():
    env = gym.make("satloc/SatLoc-v0", scene="city", localizer=None, depth=True)
    a, _ = env.reset(seed=3, options={"appearance": 0.0})
    b, _ = env.reset(seed=3, options={"appearance": 1.0})
    assert np.array_equal(a["depth"], b["depth"])
    assert np.abs(a["left"].astype(int) - b["left"].astype(int)).mean() > 3
    env.close()


def test_render_rgb_array_and_record_video(tmp_path):
    from gymnasium.wrappers import RecordVideo
    pytest.importorskip("moviepy")
    env = RecordVideo(gym.make("satloc/SatLoc-v0", scene="city", localizer=None, render_mode="rgb_array"),
                      str(tmp_path))
    env.reset(seed=0)
    for _ in range(5):
        env.step(env.unwrapped.autopilot_action())
    env.close()
    assert list(tmp_path.glob("*.mp4"))


def test_render_frame_shape():
    env = gym.make("satloc/SatLoc-v0", scene="city", localizer=None, render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.shape[0] == 360 and frame.shape[2] == 3
    env.step(env.unwrapped.autopilot_action())
    assert env.render().shape == frame.shape
    env.close()


def test_async_vector_env_steps():
    envs = gym.make_vec("satloc/SatLoc-v0", 2, vectorization_mode="async", scene="city", localizer=None,
                        vector_kwargs={"context": "spawn"})
    obs, info = envs.reset(seed=[0, 1])
    assert obs["left"].shape == (2, 188, 620, 3)
    for _ in range(3):
        obs, r, term, trunc, info = envs.step(np.array([[8.0, 0.0], [8.0, 0.0]], np.float32))
    assert info["pose"].shape == (2, 3)
    envs.close()
