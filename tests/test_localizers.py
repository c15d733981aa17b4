"""The one localizer interface (satloc.localizers.interface): answers, naming a localizer, the grading path, the
reference floors, and a user's localizer in every environment. The tables, the sweep and ``satloc evaluate``
with a user's localizer are in test_compare.py and test_evaluate.py."""
import math
import textwrap
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import satloc_env  # noqa: F401
from satloc import Frame, Pose2, SatelliteMap, Sequence, StereoCamera
from satloc.errors import ConfigError
from satloc.evaluation.run import run_localizer
from satloc.localizers.crossview import draw_prior
from satloc.localizers.interface import (
    Context,
    Estimate,
    LocalizerProtocol,
    Prior,
    as_estimate,
    check_localizer,
    import_object,
    localizer_name,
    resolve_localizer,
)
from satloc.localizers.reference import DeadReckoning, PriorAlone

ROOT = Path(__file__).resolve().parent.parent


class Recorder:
    """A localizer of one's own (subclasses nothing): answers the prior's centre, keeps every query and context."""

    name = "recorder"

    def __init__(self):
        self.contexts, self.queries = [], []

    def reset(self, context):
        self.contexts.append(context)

    def localize(self, query):
        self.queries.append(query)
        return None if query.prior is None else Pose2(query.prior.x + 1.0, query.prior.y, query.prior.yaw)


def tiny_sequence(n=6, spacing=2.0):
    cam = StereoCamera.kitti().resized(64, 20)
    img = np.zeros((20, 64, 3), np.uint8)
    frames = [Frame(img, img, Pose2(spacing * i, 0.0, 0.0), 0.1 * i) for i in range(n)]
    return Sequence(cam, frames, "tiny")


def blank_map():
    return SatelliteMap(np.zeros((40, 40, 3), np.uint8), 1.0, (-10.0, 20.0))


# --- answers ------------------------------------------------------------------------------------------------------

def test_answers_become_estimates_or_name_what_is_wrong():
    assert as_estimate(None) is None
    e = as_estimate(Pose2(1, 2, 0.5))
    assert e.pose == Pose2(1, 2, 0.5) and e.candidates is None and math.isnan(e.inlier_score) and e.inlier
    assert as_estimate([1, 2, 0.5]).pose == Pose2(1, 2, 0.5)   # three numbers do as well

    class WithPose:                                            # any object with pose (and optional extras)
        pose = Pose2(3, 4, 0)
        candidates = np.array([[3, 4, 0], [5, 4, 0]])
        posterior = np.array([0.25, 0.75])
        inlier_score = 2.5

    e = as_estimate(WithPose())
    assert e.inlier_score == 2.5 and e.inlier
    poses, probs = e.top(3)                                    # most probable first, zero-padded
    assert np.allclose(poses[:2], [[5, 4, 0], [3, 4, 0]]) and np.allclose(probs, [0.75, 0.25, 0.0])
    poses, probs = as_estimate(Pose2(7, 8, 0)).top(2)         # no posterior: the pose with probability 1
    assert np.allclose(poses, [[7, 8, 0], [0, 0, 0]]) and np.allclose(probs, [1, 0])
    bad = [("text", "expected a satloc.Pose2"), ([1, 2], "expected a satloc.Pose2"),
           ([float("nan"), 0, 0], "not finite"),
           (Estimate(Pose2(), np.zeros((2, 3)), np.zeros(3)), "expected \\(K, 3\\) and \\(K,\\)"),
           (Estimate(Pose2(), np.zeros((1, 3)), np.array([-1.0])), "negative or non-finite"),
           (Estimate(Pose2(), np.zeros((1, 3)), None), "candidates without a posterior")]
    for answer, msg in bad:
        with pytest.raises(ConfigError, match=msg):
            as_estimate(answer, "localizer 'x'")


def test_a_localizer_is_named_and_checked_by_what_it_has():
    assert isinstance(Recorder(), LocalizerProtocol) and isinstance(PriorAlone(), LocalizerProtocol)
    assert localizer_name(Recorder()) == "recorder"

    class Unnamed:
        def reset(self, context):
            pass

        def localize(self, query):
            return None

    assert localizer_name(Unnamed()) == "Unnamed"
    with pytest.raises(ConfigError, match="has no reset method"):
        check_localizer(type("OnlyLocalize", (), {"localize": lambda self, q: None})())
    with pytest.raises(ConfigError, match="no reset and no localize"):
        check_localizer(object())


def test_module_name_and_file_specs(tmp_path):
    f = tmp_path / "mine.py"
    f.write_text(textwrap.dedent("""
        class Mine:
            name = "mine"
            def __init__(self):
                self.made = True
            def reset(self, context):
                pass
            def localize(self, query):
                return None

        def factory():
            return Mine()

        instance = Mine()
        needs_args = lambda a: Mine()
    """))
    made = resolve_localizer(f"{f}:Mine")                     # a class: made with no arguments
    assert type(made).__name__ == "Mine" and made.made
    assert type(resolve_localizer(f"{f}:factory")).__name__ == "Mine"   # a function that makes one
    assert resolve_localizer(f"{f}:instance") is import_object(f"{f}:instance")   # an instance as it is
    assert isinstance(resolve_localizer("satloc.localizers.reference:PriorAlone"), PriorAlone)
    for spec, msg in [("nocolon", "expected 'module:Name'"), (f"{f}:Nope", "has no attribute 'Nope'"),
                      (f"{tmp_path / 'gone.py'}:Mine", "no file"), ("no_such_module_x:Mine", "no module named"),
                      (f"{f}:needs_args", "cannot be made with no arguments"),
                      ("satloc.geometry:Pose2", "is not a localizer")]:
        with pytest.raises(ConfigError, match=msg):
            resolve_localizer(spec, "localizers")


# --- the grading path and the reference floors ----------------------------------------------------------------

def test_run_localizer_gives_queries_as_the_interface_says_and_grades_the_answers():
    seq = tiny_sequence()
    rng = np.random.default_rng(0)
    priors = [draw_prior(p, 5.0, 10.0, rng) for p in seq.poses]
    odo = np.full((len(seq), 3), np.nan)
    odo[2:] = [[2.0, 0.0, 0.0]] * (len(seq) - 2)              # row 1 unknown (NaN), row 0 never used
    rec = Recorder()
    ctx = Context(seq.camera, blank_map(), seed=3, place="tiny")
    run = run_localizer(rec, ctx, seq, None, odo, priors, top=4)
    assert rec.contexts == [ctx]
    q = rec.queries
    assert [x.index for x in q] == list(range(6)) and [x.prior for x in q] == priors
    assert q[0].odometry is None and q[1].odometry is None and q[2].odometry == Pose2(2.0, 0.0, 0.0)
    assert all(x.frame.pose is None and x.frame.labels is None for x in q)   # the question, not the answer
    assert np.isclose(q[3].timestamp, 0.3)
    expect = np.array([[p.x + 1.0, p.y, p.yaw] for p in priors])
    assert np.allclose(run.estimates, expect) and run.name == "recorder" and not run.failures
    assert np.allclose(run.errors, np.hypot(expect[:, 0] - seq.poses[:, 0], expect[:, 1] - seq.poses[:, 1]))
    assert np.allclose(run.priors[:, :2], [[p.x, p.y] for p in priors])
    assert np.allclose(run.top_probs[:, 0], 1.0) and np.allclose(run.top_poses[:, 0], expect)

    class Failing(Recorder):
        def localize(self, query):
            if query.index == 1:
                raise ConfigError("too dark")
            return None if query.index == 2 else super().localize(query)

    run = run_localizer(Failing(), ctx, seq, [0, 1, 2, 3], None, priors[:4])
    assert run.failures == [(1, "too dark"), (2, "no answer")]
    assert np.isnan(run.errors[1:3]).all() and np.isfinite(run.errors[[0, 3]]).all()
    assert not run.inlier[1:3].any()
    with pytest.raises(ConfigError, match="priors: expected 4"):
        run_localizer(Recorder(), ctx, seq, [0, 1, 2, 3], None, priors)
    with pytest.raises(ConfigError, match="odometry: expected an \\(2, 3\\) array"):
        run_localizer(Recorder(), ctx, seq, [0, 1], np.zeros((3, 3)))


def test_dead_reckoning_starts_at_the_first_prior_and_restarts_after_an_unknown_motion():
    seq = tiny_sequence()
    exact = [Prior(*p, radius_m=5.0) for p in seq.poses]
    odo = np.array([[np.nan] * 3] + [[2.0, 0.0, 0.0]] * (len(seq) - 1))
    run = run_localizer(DeadReckoning(), Context(seq.camera, blank_map()), seq, None, odo, exact)
    assert np.allclose(run.errors, 0.0, atol=1e-9)
    shifted = [Prior(p.x + 3.0, p.y, p.yaw, 5.0) for p in exact]
    odo[3] = np.nan                                            # lost: starts again at query 3's prior
    dr = DeadReckoning()
    run = run_localizer(dr, Context(seq.camera, blank_map()), seq, None, odo, shifted)
    assert np.allclose(run.errors, 3.0)
    run = run_localizer(dr, Context(seq.camera, blank_map()), seq, None, odo, [shifted[0]] + [None] * 5)
    assert np.allclose(run.errors[:3], 3.0) and np.isnan(run.errors[3:]).all()   # no prior to restart from
    assert np.isnan(run_localizer(PriorAlone(), Context(seq.camera, blank_map()), seq, None, None,
                                  [None] * 6).errors).all()


def test_the_prior_alone_has_the_mean_error_of_a_uniform_disc():
    """Drawn as the tables and the environments draw it, a prior of radius r lies 2r/3 from the truth on average."""
    n, r = 3000, 20.0
    truth = np.zeros((n, 3))
    seq = Sequence.lazy(StereoCamera.kitti().resized(64, 20), truth, np.arange(n, dtype=float),
                        lambda i: Frame(np.zeros((20, 64, 3), np.uint8), np.zeros((20, 64, 3), np.uint8)), "disc")
    rng = np.random.default_rng(5)
    run = run_localizer(PriorAlone(), Context(seq.camera, blank_map()), seq, None, None,
                        [draw_prior(t, r, 10.0, rng) for t in truth])
    assert run.errors.max() <= r and abs(run.errors.mean() - 2 * r / 3) < 0.3   # std of the mean: 0.09 m


# --- a user's localizer in the environments ------------------------------------------------------------------------

def test_a_users_localizer_in_satloc_v0():
    rec = Recorder()
    env = gym.make("satloc/SatLoc-v0", scene="city", localizer=rec, localize_every=2)
    assert env.unwrapped.localizer is rec and env.unwrapped.config.localizer == "<instance>"
    _, info = env.reset(seed=4)
    steps = [info] + [env.step(env.unwrapped.autopilot_action())[4] for _ in range(4)]
    ctx = rec.contexts[0]
    assert isinstance(ctx.satmap, SatelliteMap) and ctx.satmap is env.unwrapped.scene.satmap
    assert ctx.satmap.labels is not None and ctx.camera == env.unwrapped.camera and ctx.database is None
    assert len(rec.queries) == 3                                # steps 0, 2, 4
    q0, q1 = rec.queries[:2]
    assert q0.odometry is None and isinstance(q1.odometry, Pose2) and q1.index == 1
    for q, info in zip(rec.queries, (steps[0], steps[2], steps[4])):
        assert q.frame.pose is None and q.frame.left.shape == (188, 620, 3)
        p = info["pose"]
        assert math.hypot(q.prior.x - p[0], q.prior.y - p[1]) <= 20.0     # a GPS-like prior around the truth
        # the answer is the estimate, its distance from the truth the error
        assert np.allclose(info["estimate"], [q.prior.x + 1.0, q.prior.y, q.prior.yaw])
        assert np.isclose(info["error_m"], math.hypot(q.prior.x + 1.0 - p[0], q.prior.y - p[1]))
        assert info["posterior_probs"][0] == 1.0 and info["posterior_poses"].shape == (32, 3)
    # the odometry since the previous query: the two observations composed
    _, info2 = env.reset(seed=4)
    assert len(rec.contexts) == 2 and rec.contexts[1].seed == ctx.seed   # seeded: the same context seed
    assert np.allclose(info2["estimate"], steps[0]["estimate"])             # and the same prior
    env.close()
    with pytest.raises(ConfigError, match="localizer_track: tracks the localizers the environment makes"):
        gym.make("satloc/SatLoc-v0", scene="city", localizer=Recorder(), localizer_track=True)
    with pytest.raises(ConfigError, match="is not a localizer"):
        gym.make("satloc/SatLoc-v0", scene="city", localizer=lambda: object())


def test_a_users_localizer_by_name_and_by_class_in_vector_envs(tmp_path):
    f = tmp_path / "userloc.py"
    f.write_text(textwrap.dedent("""
        from satloc import Pose2
        made = []
        class Rec:
            def __init__(self):
                made.append(self)
            def reset(self, context):
                pass
            def localize(self, query):
                return query.prior.pose
    """))
    env = gym.make("satloc/SatLoc-v0", scene="city", localizer=f"{f}:Rec")
    _, info = env.reset(seed=0)
    assert type(env.unwrapped.localizer).__name__ == "Rec" and np.isfinite(info["error_m"])
    env.close()
    vec = gym.make_vec("satloc/SatLoc-v0", num_envs=2, scene="city", localizer=Recorder)   # a class: one each
    _, infos = vec.reset(seed=0)
    locs = vec.unwrapped.get_attr("localizer")
    assert locs[0] is not locs[1] and all(len(loc.queries) == 1 for loc in locs)
    assert np.isfinite(infos["error_m"]).all()
    vec.close()
    with pytest.raises(ConfigError, match="cannot serve 2 cars"):
        gym.make_vec("satloc/SatLoc-v0", num_envs=2, scene="city", localizer=Recorder())


def test_a_users_localizer_in_the_replay_gets_priors_around_the_drives_poses(tmp_path):
    from satloc_env.envs.record import PassConfig, make_env, record_pass

    env = make_env(scene="city", depth=False, labels=False, localizer=None)
    env.reset(seed=0)
    seq = record_pass(env, PassConfig(spacing_m=4.0, max_frames=5), env.scene.spec.database_route,
                      tmp_path / "seq", "seq", False, {"source": "satloc_env", "scene": "city"})
    env.close()
    rec = Recorder()
    replay = gym.make("satloc/SatLocReplay-v0", sequence=seq, localizer=rec, prior_radius_m=8.0)
    _, info = replay.reset(seed=1)
    for _ in range(3):
        _, _, _, trunc, info = replay.step(1)
    assert len(rec.queries) == 4 and rec.contexts[0].camera == seq.camera
    for q, p in zip(rec.queries, seq.poses[:4]):
        assert q.prior is not None and q.prior.radius_m == 8.0 and math.hypot(q.prior.x - p[0], q.prior.y - p[1]) <= 8
    assert rec.queries[0].odometry is None and isinstance(rec.queries[1].odometry, Pose2)
    assert np.isclose(info["error_m"], math.hypot(rec.queries[-1].prior.x + 1 - seq.poses[3][0],
                                                  rec.queries[-1].prior.y - seq.poses[3][1]))
    replay.close()
    # the replay's priors also let the no-database localizer run on a replayed drive, against its map
    from satloc_env.world.scene import load_scene

    load_scene("city").satmap.save(tmp_path / "map")
    cross = gym.make("satloc/SatLocReplay-v0", sequence=seq, map=str(tmp_path / "map"), localizer="cross",
                     localizer_track=True)
    _, info = cross.reset(seed=1)
    errors = [info["error_m"]] + [cross.step(1)[4]["error_m"] for _ in range(2)]
    # measured at the default world: 0.3, 4.6 and 4.5 m (on the plain, flat world of earlier releases: under 1 m)
    assert np.all(np.isfinite(errors)) and min(errors) < 1.0 and max(errors) < 7.0, errors
    cross.close()
    with pytest.raises(ConfigError, match="'cross' localizes against the satellite map; give map="):
        gym.make("satloc/SatLocReplay-v0", sequence=Sequence(seq.camera, [seq[i] for i in range(3)], "mapless"),
                 localizer="cross")


def test_a_users_localizer_in_activeloc_drives_the_belief():
    """ActiveLoc-v0 renders each fused frame at its recorded pose and spreads the localizer's answer over the
    map's candidates: an oracle locks onto the truth at once, a localizer that never answers never locks."""
    holder = {}

    class Oracle:
        def reset(self, context):
            holder.setdefault("contexts", []).append(context)

        def localize(self, query):
            assert query.prior is None and query.frame.left.shape == (188, 620, 3)
            return Pose2(*holder["env"].pose)

    env = gym.make("satloc/ActiveLoc-v0", localizer=Oracle(), max_redraws=3)
    holder["env"] = env.unwrapped
    with pytest.raises(ConfigError, match="locked .* before their first junction"):
        env.reset(seed=0)   # the oracle locks at the start: every start is drawn again
    assert holder["contexts"][0].database is None and holder["contexts"][0].satmap is not None
    env.close()

    class Silent:
        def reset(self, context):
            pass

        def localize(self, query):
            return None

    env = gym.make("satloc/ActiveLoc-v0", localizer=Silent())
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs) and not info["locked"]
    env.close()


def test_close_once_and_malformed_answers_are_no_answers():
    class Closing(Recorder):
        closed = 0

        def close(self):
            Closing.closed += 1

        def localize(self, query):
            return [float("nan"), 0.0, 0.0] if query.index == 1 else super().localize(query)

    loc = Closing()
    env = gym.make("satloc/SatLoc-v0", scene="city", localizer=loc)
    _, info = env.reset(seed=0)
    assert np.isfinite(info["error_m"])
    _, _, _, _, info = env.step(env.unwrapped.autopilot_action())
    assert np.isnan(info["error_m"]) and "not finite" in env.unwrapped.localization_error
    env.close()
    env.close()
    assert Closing.closed == 1
    seq = tiny_sequence()
    run = run_localizer(Closing(), Context(seq.camera, blank_map()), seq, [0, 1, 2], None,
                        [Prior(*p, radius_m=5.0) for p in seq.poses[:3]])
    assert [f for f, _ in run.failures] == [1] and "not finite" in run.failures[0][1]


def test_a_name_for_an_instance_cannot_serve_several_cars(tmp_path):
    f = tmp_path / "inst.py"
    f.write_text("class L:\n    def reset(self, c): pass\n    def localize(self, q): return None\none = L()\n")
    with pytest.raises(ConfigError, match="cannot serve 2 cars"):
        gym.make_vec("satloc/SatLoc-v0", num_envs=2, scene="city", localizer=f"{f}:one")


def test_stale_rows_of_dropped_localizers_are_removed(tmp_path):
    from satloc_env.experiments.grading import prune_extra

    for key in ("prior", "dead-reckoning", "user-old", "go", "full+track"):
        (tmp_path / f"localization_{key}.npz").write_bytes(b"x")
        (tmp_path / f"localization_{key}.json").write_text("{}")
    prune_extra(tmp_path, {"prior"})
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        f"localization_{k}.{e}" for k in ("prior", "go", "full+track") for e in ("npz", "json"))
