"""The camera's vignetting, motion blur and noise (satloc_env.render.sensor) and the body's pitch and roll
(satloc_env.envs.vehicle.Attitude), alone and in the environment."""
from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import satloc_env  # noqa: F401
from satloc.errors import ConfigError
from satloc_env.envs.vehicle import Attitude
from satloc_env.render.sensor import Sensor, SensorParams

W, H = 320, 120


def _sensor(strength=1.0, seed=0):
    return Sensor(strength, W, H, 200.0, W / 2, H / 2, np.random.default_rng(seed))


def test_strength_zero_is_the_identity_and_bad_strength_is_refused():
    img = np.random.default_rng(0).integers(0, 256, (H, W, 3), dtype=np.uint8)
    assert _sensor(0.0)(img, 10.0, 0.5) is img
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="sensor strength"):
            _sensor(bad)


def test_noise_vignetting_and_determinism():
    grey = np.full((H, W, 3), 128, np.uint8)
    a, b = _sensor(seed=3)(grey), _sensor(seed=3)(grey)
    assert np.array_equal(a, b)                                   # the same seed, the same noise
    assert not np.array_equal(a, _sensor(seed=4)(grey))
    p = SensorParams()
    centre = a[H // 2 - 10:H // 2 + 10, W // 2 - 20:W // 2 + 20].astype(np.float64)
    expected = math.sqrt(p.shot * 128 + p.read ** 2)
    assert 0.8 * expected < centre.std() < 1.2 * expected         # Poisson-Gaussian at grey 128
    assert abs(centre.mean() - 128) < 1.0
    corner = a[:8, :8].astype(np.float64).mean()
    assert corner < 128 * (1 - 0.8 * p.vignetting)                # the corners darkened by about vignetting
    s = _sensor(seed=3)
    assert not np.array_equal(s(grey), s(grey))                   # each frame draws its own noise


def test_motion_blur_smears_along_the_motion():
    stripes = np.zeros((H, W, 3), np.uint8)
    stripes[:, ::8] = 255
    s = Sensor(1.0, W, H, 200.0, W / 2, H / 2, np.random.default_rng(0), SensorParams(read=0.0, shot=0.0,
                                                                                       vignetting=0.0))
    still, turning = s(stripes, 0.0, 0.0), s(stripes, 0.0, 20.0)   # 20 rad/s x 2 ms x 200 px: an 8 px smear
    grad = lambda img: float(np.abs(np.diff(img.astype(np.float64), axis=1)).mean())  # noqa: E731
    assert np.array_equal(still, stripes)
    assert grad(turning) < 0.2 * grad(still)
    fast = s(stripes, 60.0, 0.0)                                   # forward motion: a zoom blur off the centre
    assert grad(fast[:, :40]) < 0.8 * grad(still[:, :40])


def test_attitude_pitches_when_braking_and_rolls_out_of_a_turn():
    assert Attitude(0.0, 0.1, np.random.default_rng(0)).tilt is None
    a = Attitude(1.0, 0.1, np.random.default_rng(0))
    a.p = type(a.p)(ride_pitch=0.0, ride_roll=0.0)                # the accelerations alone
    a.step(10.0, 0.0)
    for _ in range(5):
        a.step(a._speed - 0.5, 0.0)                               # braking at 5 m/s^2: nose down
    assert a.tilt[0] > math.radians(1.0) and abs(a.tilt[1]) < 1e-9
    b = Attitude(1.0, 0.1, np.random.default_rng(0))
    b.p = a.p
    for _ in range(20):
        b.step(8.0, 0.5)                                          # a steady left turn: 4 m/s^2, the left side up
    assert abs(b.tilt[1] - math.radians(0.5) * 4.0) < 1e-3 and abs(b.tilt[0]) < 1e-9
    ride = [Attitude(1.0, 0.1, np.random.default_rng(7)) for _ in range(2)]
    for r in ride:
        for _ in range(50):
            r.step(8.0, 0.0)
    assert ride[0].tilt == ride[1].tilt and ride[0].tilt != (0.0, 0.0)


def test_the_environment_applies_both_deterministically():
    def run(**kw):
        env = gym.make("satloc/SatLoc-v0", scene="city", localizer=None, **kw).unwrapped
        obs, _ = env.reset(seed=5)
        frames = [obs["left"]]
        for _ in range(4):
            obs, *_ = env.step(env.autopilot_action())
            frames.append(obs["left"])
        tilt = env.attitude.tilt
        env.close()
        return frames, tilt

    plain, t0 = run(sensor=0.0, attitude=0.0)
    real, t1 = run(sensor=1.0, attitude=1.0)
    again, t2 = run(sensor=1.0, attitude=1.0)
    assert t0 is None and t1 == t2 and t1 is not None
    default, td = run()                  # the defaults: the body's attitude on, the sensor off
    assert td == t1                                   # the same seed: the same pitch and roll
    assert not any(np.array_equal(x, y) for x, y in zip(default, real))   # no sensor noise
    assert all(np.array_equal(x, y) for x, y in zip(real, again))
    assert not any(np.array_equal(x, y) for x, y in zip(real, plain))
    diff = np.abs(real[-1].astype(np.int16) - plain[-1]).mean()
    assert 1.0 < diff < 40.0
    with pytest.raises(ConfigError, match="sensor"):
        gym.make("satloc/SatLoc-v0", scene="city", localizer=None, sensor=2.0)
