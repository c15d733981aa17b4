"""The batched vector environment (``gym.make_vec("satloc/SatLoc-v0", n)``, :mod:`satloc_env.envs.vector`): the same
results as n single environments, bit for bit, Gymnasium 1.x's autoreset, seeding and errors."""
import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import satloc_env  # noqa: F401  (registers the ids)
from satloc import ConfigError
from satloc_env.envs.drive import ActionError
from satloc_env.envs.vector import SatLocVectorEnv

ID = "satloc/SatLoc-v0"
KW = dict(scene="city", localizer=None)


def assert_same(x, y, what="") -> None:
    """``x`` and ``y`` (nested dicts of arrays / numbers) are equal: same keys, shapes, dtypes and values."""
    if isinstance(x, dict):
        assert isinstance(y, dict) and set(x) == set(y), (what, set(x) ^ set(y))
        for k in x:
            assert_same(x[k], y[k], f"{what}.{k}")
        return
    if isinstance(x, (tuple, list)):
        assert isinstance(y, (tuple, list)) and len(x) == len(y), what
        for i, (a, b) in enumerate(zip(x, y)):
            assert_same(a, b, f"{what}[{i}]")
        return
    x, y = np.asarray(x), np.asarray(y)
    assert x.shape == y.shape and x.dtype == y.dtype, (what, x.shape, y.shape, x.dtype, y.dtype)
    assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), what


def noisy_autopilot(env, rng) -> np.ndarray:
    act = np.stack([e.autopilot_action() for e in env.unwrapped.envs]).astype(np.float32)
    return act + rng.normal(0, 0.2, act.shape).astype(np.float32)


def test_make_vec_uses_the_batched_env_and_its_spaces():
    env = gym.make_vec(ID, 3, **KW)
    try:
        assert isinstance(env.unwrapped, SatLocVectorEnv)
        assert env.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
        assert env.action_space.shape == (3, 2)
        obs, info = env.reset(seed=0)
        assert obs in env.observation_space
        assert obs["left"].shape == (3, 188, 620, 3) and obs["left"].dtype == np.uint8
        assert info["pose"].shape == (3, 3) and info["_pose"].all()
        obs, rew, term, trunc, info = env.step(env.unwrapped.autopilot_actions())
        assert obs in env.observation_space
        assert rew.shape == term.shape == trunc.shape == (3,) and rew.dtype == np.float64
        assert term.dtype == trunc.dtype == np.bool_
        # three cars at three places (seeds 0, 1, 2 with random starts differ; here all start at s = 0 but
        # their images still agree: same route, same world, same occluders only if the seeds agree)
        assert (info["step"] == 1).all()
    finally:
        env.close()


@pytest.mark.parametrize("extra", [dict(depth=True, labels=True, occlusion=0.6, appearance=0.5, random_start=True),
                                   dict(odometry="visual", random_start=True, max_steps=6),
                                   dict(change=0.5, n=2, steps=3),
                                   dict(max_episode_steps=3, n=2, steps=7)])
def test_same_as_single_environments_bit_for_bit(extra):
    """Observations, rewards, flags and infos equal those of the same number of single environments
    (Gymnasium's SyncVectorEnv over gym.make), through an autoreset (max_steps 6), with occluders, appearance
    changes, depth, labels, visual odometry, and revisit-changed worlds (each car its own, in one scene); with
    make_vec's max_episode_steps (gym.make's TimeLimit for the single environments)."""
    extra = dict(extra)
    n, steps = extra.pop("n", 3), extra.pop("steps", 14)
    kw = dict(KW, **{"max_steps": 6, **extra})
    ref = gym.make_vec(ID, n, vectorization_mode="sync", **kw)
    vec = gym.make_vec(ID, n, vectorization_mode="vector_entry_point", **kw)
    try:
        assert_same(ref.reset(seed=11), vec.reset(seed=11), "reset")
        rng = np.random.default_rng(0)
        ends = 0
        for t in range(steps):
            act = noisy_autopilot(vec, rng)
            a, b = ref.step(act), vec.step(act)
            for x, y, name in zip(a, b, ("obs", "reward", "terminated", "truncated", "info")):
                assert_same(x, y, f"{name} at step {t}")
            ends += int(np.sum(b[2] | b[3]))
        if steps > 6:
            assert ends >= n        # every car went through at least one autoreset
        else:
            worlds = {id(e._renderer.world) for e in vec.unwrapped.envs}
            assert len(worlds) == n   # each car drives in a world of its own (its own change seed)
    finally:
        ref.close()
        vec.close()


def test_next_step_autoreset_and_reset_mask():
    env = SatLocVectorEnv(2, max_steps=2, **KW)
    try:
        first, _ = env.reset(seed=3)
        for _ in range(2):
            _, _, term, trunc, info = env.step(env.autopilot_actions())
        assert trunc.all() and not term.any() and (info["step"] == 2).all()
        obs, rew, term, trunc, info = env.step(np.full((2, 2), 5.0, np.float32))  # ignored: the cars are reset
        assert (info["step"] == 0).all() and not (term | trunc).any() and (rew == 0).all()
        assert np.array_equal(obs["left"][0], first["left"][0])   # the same start, s = 0, no random start
        # reset only car 1
        env.step(env.autopilot_actions())
        _, info = env.reset(options={"reset_mask": np.array([False, True])})
        assert not info["_step"][0] and info["_step"][1] and info["step"][1] == 0
        _, _, _, _, info = env.step(env.autopilot_actions())
        assert info["step"].tolist() == [2, 1]
    finally:
        env.close()


def test_seeded_resets_repeat():
    kw = dict(KW, random_start=True, occlusion=0.5)
    with_seed = []
    for _ in range(2):
        env = SatLocVectorEnv(2, **kw)
        try:
            obs, info = env.reset(seed=[7, 8])
            obs2, *_ = env.step(env.autopilot_actions())
            with_seed.append((obs, info, obs2))
        finally:
            env.close()
    assert_same(with_seed[0], with_seed[1])
    assert not np.array_equal(with_seed[0][1]["pose"][0], with_seed[0][1]["pose"][1])   # two seeds, two starts


def test_errors():
    with pytest.raises(ConfigError, match="num_envs"):
        SatLocVectorEnv(0, **KW)
    with pytest.raises(ConfigError, match="scene"):
        SatLocVectorEnv(2, scene="", localizer=None)
    env = SatLocVectorEnv(2, **KW)
    try:
        with pytest.raises(RuntimeError, match="reset"):
            env.step(np.zeros((2, 2)))
        env.reset(seed=0)
        with pytest.raises(ConfigError, match=r"shape \(2, 2\)"):
            env.step(np.zeros((3, 2)))
        with pytest.raises(ConfigError, match="2 seeds"):
            env.reset(seed=[1, 2, 3])
        with pytest.raises(ConfigError, match="reset_mask"):
            env.reset(options={"reset_mask": np.array([False, False])})
        with pytest.raises(ConfigError, match="resolution"):
            env.reset(options={"resolution": "full"})   # fixed when made, as for the single env
        poses = [e.pose for e in env.envs]
        with pytest.raises(ActionError, match="sub-environment 1"):
            env.step(np.array([[5.0, 0.0], [np.nan, 0.0]]))
        assert [e.pose for e in env.envs] == poses and [e.steps for e in env.envs] == [0, 0]   # no car moved
        with pytest.raises(ConfigError, match="max_episode_steps"):
            SatLocVectorEnv(2, max_episode_steps=0, **KW)
    finally:
        env.close()


def test_view_volume_culling_changes_no_pixel(monkeypatch):
    """Chunks and cells wholly outside a camera's view volume (beside, behind, or beyond the far plane) are skipped
    (satloc_env.render.stereo._box_in_view); the images are the same as when every chunk and cell within reach is drawn."""
    import satloc_env.render.stereo as render

    def box(xs, ys, zs):   # min and max rows in the camera frame (the camera at the origin: map_from_cam = identity)
        return np.array([[[xs[0], ys[0], zs[0]], [xs[1], ys[1], zs[1]]]], np.float64)

    cam = _camera()
    for xs, ys, zs, seen in (((-1, 1), (-1, 1), (10, 12), True),      # ahead
                             ((-1, 1), (-1, 1), (-9, -2), False),     # behind
                             ((50, 60), (-1, 1), (5, 6), False),      # far to the right of the image
                             ((-60, 50), (-1, 1), (5, 6), True),      # wider than the view: spans it
                             ((-1, 1), (20, 30), (5, 6), False),      # below the image (y down)
                             ((-1, 1), (-1, 1), (-5, 0.05), False),   # behind the near plane
                             ((-1, 1), (-1, 1), (-5, 0.2), True)):    # reaching past it
        assert render._box_in_view(box(xs, ys, zs), np.eye(4), cam, 0.1).tolist() == [seen], (xs, ys, zs)
    for zs, seen in (((151, 160), False), ((149, 160), True)):     # beyond the far plane at 150 m, or reaching it
        assert render._box_in_view(box((-1, 1), (-1, 1), zs), np.eye(4), cam, 0.1, zfar=150.0).tolist() == [seen]
        assert render._box_in_view(box((-1, 1), (-1, 1), zs), np.eye(4), cam, 0.1).tolist() == [True]   # no far plane
    runs = []
    for cull in (True, False):
        if not cull:
            monkeypatch.setattr(render, "_box_in_view", lambda boxes, *a, **k: np.ones(len(boxes), bool))
        env = SatLocVectorEnv(2, scene="residential", localizer=None, depth=True, labels=True, occlusion=0.5,
                              random_start=True)
        try:
            out = [env.reset(seed=2)[0]]
            out += [env.step(env.autopilot_actions())[0] for _ in range(12)]
            drawn = [e._renderer._in_view[0].sum() for e in env.envs]
            reach = [e._renderer._visible.sum() for e in env.envs]
        finally:
            env.close()
        runs.append(out)
        if cull:
            assert sum(drawn) < sum(reach)       # something was culled
    assert_same(runs[0], runs[1])


def _camera():
    from satloc.geometry import StereoCamera

    return StereoCamera.preset("half")
