"""Drives that wander (satloc_env.envs.vehicle.Wander): the autopilot's lateral position and speed drift
smoothly inside the lane, seeded per drive; without wander it holds the lane offset."""
import gymnasium as gym
import numpy as np
import pytest

import satloc_env  # noqa: F401
from satloc import ConfigError
from satloc_env.envs.vehicle import Wander, wander_profile

STEPS = 320


def _drive(**kw):
    env = gym.make("satloc/SatLoc-v0", scene="city", localizer=None, **kw)
    try:
        _, info = env.reset(seed=3)
        u = env.unwrapped
        route = u.route
        s, lat, speed = [], [], []
        for _ in range(STEPS):
            _, _, term, trunc, info = env.step(u.autopilot_action())
            si, li = route.project(info["pose"][:2], s_hint=float(info["route_s"]))
            s.append(si)
            lat.append(li)
            speed.append(float(np.hypot(*info["odometry_true"][:2])) / u.config.dt)
            assert not info["off_road"] and not term
        straight = np.array([abs(route.curvature_ahead(x - 15, 30)) < 0.05 for x in s])
        return np.array(s), np.array(lat), np.array(speed), straight
    finally:
        env.close()


def test_the_lateral_position_and_speed_wander_inside_the_lane_and_differ_between_drives():
    s0, lat0, v0, st0 = _drive(wander_m=0.0, speed_wander=0.0)
    s1, lat1, v1, st1 = _drive(wander_seed=1)     # the default drift
    s2, lat2, v2, st2 = _drive(wander_seed=2)
    assert st0.sum() > 100 and st1.sum() > 100
    assert lat0[st0].std() < 0.05                                   # the lane offset held
    for lat, st in ((lat1, st1), (lat2, st2)):
        assert lat[st].std() > 0.2                                  # a spread on straight stretches
        assert np.all(np.abs(lat[st] + 1.75) <= 0.8 + 0.1)          # inside the lane
    # no two drives share it: the drift of one seed does not predict the other's at the same place
    common = st1 & (s1 < min(s1.max(), s2.max()))
    other = np.interp(s1[common], s2, lat2)
    assert np.mean(np.abs(lat1[common] - other)) > 0.1
    assert v1[st1][20:].std() > v0[st0][20:].std() + 0.3            # the speed varies too


#: poses and noisy odometry at steps 100, 130 and 160 of city, reset(seed=3), change 0.5, occlusion 0.3, as the
#: code before the wander knob drove them (computed with that code, commit ed6bb44)
BEFORE = [[26.719999933, 181.75, 3.141592654, 0.321889549, -0.000204964, -0.0036492],
          [17.693766794, 174.033410601, -1.65671994, 0.761721909, 0.035477504, 0.056524295],
          [18.266228796, 150.052538365, -1.573902069, 0.799659193, -0.027608618, 0.005317484]]


def _steps(n, **kw):
    env = gym.make("satloc/SatLoc-v0", scene="city", localizer=None, change=0.5, occlusion=0.3, **kw)
    try:
        env.reset(seed=3)
        out = []
        for i in range(n):
            obs, _, _, _, info = env.step(env.unwrapped.autopilot_action())
            if i in (99, 129, 159):
                out.append(list(info["pose"]) + list(obs["odometry"]))
        return out, env.unwrapped.wander_seed
    finally:
        env.close()


def test_no_wander_drives_as_before_and_the_default_seed_does_not_depend_on_the_change():
    from satloc_env.envs.vehicle import DEFAULT_SPEED_WANDER, DEFAULT_WANDER_M

    assert (DEFAULT_WANDER_M, DEFAULT_SPEED_WANDER) == (0.3, 0.1)   # the environment's default drive wanders
    out, seed = _steps(160, wander_m=0.0, speed_wander=0.0)
    assert seed is None and np.allclose(np.array(out), np.array(BEFORE), atol=1e-6)
    _, with_change = _steps(1)
    assert with_change is not None
    env = gym.make("satloc/SatLoc-v0", scene="city", localizer=None, change=0.0)
    try:
        env.reset(seed=3)
        assert env.unwrapped.wander_seed == with_change
    finally:
        env.close()


def test_wander_profile_is_seeded_smooth_and_bounded():
    w = Wander(lateral_m=0.5, speed=0.2, scale_m=30.0)
    a, b = wander_profile(500.0, w, 4), wander_profile(500.0, w, 4)
    c = wander_profile(500.0, w, 5)
    s = np.linspace(0, 500, 2001)
    la, lb, lc = (np.array([p[0](x) for x in s]) for p in (a, b, c))
    assert np.array_equal(la, lb) and not np.allclose(la, lc)
    assert np.abs(la).max() <= w.max_lateral_m and 0.25 < la.std() < 0.6
    assert np.abs(np.diff(la)).max() < 0.05                         # smooth: < 5 cm per 25 cm of route
    sp = np.array([a[1](x) for x in s])
    assert 0.5 <= sp.min() and sp.max() <= 1.5 and sp.std() > 0.1


def test_bad_wander_settings_are_refused():
    for kw, field in (({"wander_m": -0.1}, "wander_m"), ({"wander_m": 0.6}, "wander_m"),
                      ({"speed_wander": 0.9}, "speed_wander"), ({"wander_seed": -1}, "wander_seed")):
        with pytest.raises(ConfigError, match=field):
            gym.make("satloc/SatLoc-v0", scene="city", localizer=None, **kw)


def test_the_off_road_check_drives_the_same_wandering_path():
    """drivecheck.autopilot_drive with a drift profile moves the car exactly as the environment does with
    that wander seed (what a recorder's check before recording needs)."""
    from satloc_env import load_scene
    from satloc_env.envs.drivecheck import autopilot_drive

    env = gym.make("satloc/SatLoc-v0", scene="city", localizer=None, wander_m=0.3, speed_wander=0.1, wander_seed=9)
    try:
        env.reset(seed=0)
        u = env.unwrapped
        poses = []
        for _ in range(60):
            _, _, _, _, info = env.step(u.autopilot_action())
            poses.append(info["pose"].copy())
        route = u.route
    finally:
        env.close()
    profile = wander_profile(route.length, Wander(0.3, 0.1), 9)
    checked = [p.as_array() for p, _, _ in autopilot_drive(load_scene("city"), "main", -1.75, wander=profile)][:60]
    assert np.allclose(np.array(checked), np.array(poses), atol=1e-6)
