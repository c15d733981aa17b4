"""The receiver models of the priors (satloc.localizers.gnss) and the tracker's rule for fixes that disagree."""
import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest

from satloc.config import from_dict
from satloc.errors import ConfigError
from satloc.geometry import Pose2
from satloc.localizers.crossview import CrossViewConfig, CrossViewResult, CrossViewTracker, draw_prior
from satloc.localizers.gnss import GnssConfig, GnssReceiver, gnss_priors

QUIET = dict(model="receiver", multipath_per_min=0.0, outage_per_min=0.0)


def test_uniform_priors_are_the_draws_of_each_frames_own_generator():
    truth = np.array([[0.0, 0.0, 0.1], [10.0, 5.0, -1.0], [np.nan, 0.0, 0.0], [3.0, 4.0, 2.0]])
    keys = np.array([7, 3, 9, 12])
    got = gnss_priors(truth, None, GnssConfig(), 20.0, 10.0, seed=4, keys=keys)
    assert got[2] is None
    for g, t, k in zip(got, truth, keys):
        if g is not None:
            assert g == draw_prior(t, 20.0, 10.0, np.random.default_rng([4, int(k)]))
            assert math.hypot(g.x - t[0], g.y - t[1]) <= 20.0


def test_receiver_fixes_depend_on_the_seed_and_time_only():
    truth = np.column_stack([np.linspace(0, 300, 400), np.zeros(400), np.zeros(400)])
    times = np.arange(400) * 0.1 + 5.0
    cfg = GnssConfig(model="receiver")
    a = gnss_priors(truth, times, cfg, seed=1, start=5.0)
    assert a == gnss_priors(truth, times, cfg, seed=1, start=5.0)
    assert a != gnss_priors(truth, times, cfg, seed=2, start=5.0)
    # each fix reports the receiver's accuracy (bias and noise together); uniform priors report none
    assert all(p.sigma_m == pytest.approx(math.hypot(4.0, 1.0)) for p in a if p is not None)
    assert gnss_priors(truth[:3], times[:3], GnssConfig())[0].sigma_m is None
    bare = gnss_priors(truth, times, dataclasses.replace(cfg, reports_accuracy=False), seed=1, start=5.0)
    assert all(p.sigma_m is None for p in bare if p is not None)
    assert [(p.x, p.y) for p in bare if p is not None] == [(p.x, p.y) for p in a if p is not None]
    sub = np.arange(0, 400, 37)   # asking for fewer frames of the same pass gives them the same fixes
    assert gnss_priors(truth[sub], times[sub], cfg, seed=1, start=5.0) == [a[i] for i in sub]


def test_receiver_bias_has_its_standard_deviation_and_correlation_time():
    cfg = GnssConfig(noise_sigma_m=0.0, heading_sigma_deg=0.0, bias_sigma_m=4.0, bias_tau_s=30.0, rate_hz=1.0, **QUIET)
    rx = GnssReceiver(cfg, rng=np.random.default_rng(0))
    e = np.array([rx.error(float(t))[0] for t in range(60000)])
    assert np.std(e, axis=0) == pytest.approx([4.0, 4.0], rel=0.1)
    x = e[:, 0] - e[:, 0].mean()
    rho = np.corrcoef(x[:-30], x[30:])[0, 1]   # one correlation time apart: exp(-1)
    assert rho == pytest.approx(math.exp(-1.0), abs=0.05)
    assert np.corrcoef(x[:-300], x[300:])[0, 1] < 0.1


def test_receiver_outages_and_multipath_put_the_truth_outside_the_prior_now_and_then():
    cfg = GnssConfig(model="receiver", outage_per_min=1.0, outage_mean_s=6.0)
    rx = GnssReceiver(cfg, 20.0, 10.0, np.random.default_rng(3))
    fixes = [rx.fix((0.0, 0.0, 0.0), 0.1 * k) for k in range(36000)]   # an hour at 10 Hz
    up = np.array([f is not None for f in fixes])
    # outages begin once a minute and last 6 s on average: about a tenth of the time without a fix, in runs
    assert 0.05 < 1 - up.mean() < 0.15
    assert np.count_nonzero(np.diff(up.astype(int)) == -1) > 20
    r = np.array([math.hypot(f.x, f.y) for f in fixes if f is not None])
    assert 3.0 < np.median(r) < 8.0
    assert 0.005 < np.mean(r > 20.0) < 0.1       # beyond the prior's radius
    quiet = GnssReceiver(dataclasses.replace(cfg, **QUIET), 20.0, 10.0, np.random.default_rng(3))
    rq = np.array([math.hypot(f.x, f.y) for f in (quiet.fix((0, 0, 0), 0.1 * k) for k in range(36000))])
    assert rq.max() < r.max() and np.mean(rq > 20.0) < np.mean(r > 20.0)


def test_gnss_configuration_errors_name_the_field():
    with pytest.raises(ConfigError, match="gnss.model"):
        GnssConfig(model="gps")
    with pytest.raises(ConfigError, match="gnss.bias_tau_s"):
        GnssConfig(bias_tau_s=0.0)
    with pytest.raises(ConfigError, match="gnss.noise_sigma_m"):
        GnssConfig(noise_sigma_m=-1.0)
    with pytest.raises(ConfigError, match="unknown key"):
        from_dict(GnssConfig, {"modle": "receiver"}, "gnss")
    rx = GnssReceiver(GnssConfig(model="receiver"), start=10.0)
    with pytest.raises(ConfigError, match="before the receiver's first output"):
        rx.fix((0.0, 0.0, 0.0), 9.0)
    with pytest.raises(ConfigError, match="needs the frames' times"):
        gnss_priors(np.zeros((2, 3)), None, GnssConfig(model="receiver"))
    with pytest.raises(ConfigError, match="lost_after_s"):
        CrossViewConfig(lost_after_s=-1.0)


class _Recorder:
    """A stand-in for the cross-view localizer: answers at the centre of what it is asked to search."""

    def __init__(self, **kw):
        self.config = CrossViewConfig(**kw)
        self.calls = []

    def localize(self, frame, prior, predicted=None):
        self.calls.append((prior, predicted))
        return CrossViewResult(Pose2(prior.x, prior.y, prior.yaw), 1.0, np.zeros((1, 3)), np.ones(1), 100)


def _far_fixes(tracker, times):
    """The track at the origin; fixes 40 m away (beyond the disc and the belief's reach) at ``times``."""
    searched = []
    for t in times:
        tracker.pose = Pose2(0.0, 0.0, 0.0)
        fix = draw_prior((40.0, 0.0, 0.0), 1e-3, 0.0, np.random.default_rng(0))
        tracker.localize(SimpleNamespace(timestamp=t), fix)
        searched.append(tracker.localizer.calls[-1][0])
    return searched


def test_tracker_yields_to_disagreeing_fixes_after_lost_after_s():
    assert CrossViewConfig().lost_after_s == 30.0                     # the default: after 30 s of disagreement
    dflt = CrossViewTracker(_Recorder())
    assert [p.x < 1 for p in _far_fixes(dflt, [0.0, 29.0, 30.0])] == [True, True, False]
    now = CrossViewTracker(_Recorder(lost_after_s=0.0))
    assert all(p.x > 39 for p in _far_fixes(now, [0.0, 1.0]))          # lost at the first such fix
    patient = CrossViewTracker(_Recorder(lost_after_s=5.0))
    s = _far_fixes(patient, [0.0, 2.0, 4.0, 5.0, 6.0])
    assert [p.x < 1 for p in s] == [True, True, True, False, True]    # around the track, until 5 s of disagreement
    # a fix that agrees again starts the count afresh
    patient.pose = Pose2(0.0, 0.0, 0.0)
    patient.localize(SimpleNamespace(timestamp=7.0), draw_prior((1.0, 0.0, 0.0), 1e-3, 0.0, np.random.default_rng(0)))
    assert patient.disagree_since is None
    assert _far_fixes(patient, [8.0])[0].x < 1


class _Blind(_Recorder):
    """A stand-in that sees nothing on the frames whose ``blind`` attribute is set (a bus in front)."""

    def localize(self, frame, prior, predicted=None):
        if getattr(frame, "blind", False):
            self.calls.append((prior, predicted))
            return CrossViewResult(None, float("nan"), np.zeros((0, 3)), np.zeros(0), 9)
        return super().localize(frame, prior, predicted)


def test_tracker_coasts_through_a_frame_it_cannot_localize_and_loses_it_without_coast():
    fix = draw_prior((0.0, 0.0, 0.0), 1e-3, 0.0, np.random.default_rng(0))
    t = CrossViewTracker(_Blind())
    assert t.localize(SimpleNamespace(timestamp=0.0, blind=False), fix).pose is not None
    t.predict([2.0, 0.0, 0.0])
    r = t.localize(SimpleNamespace(timestamp=0.1, blind=True), fix)
    # the answer is the track moved by the odometry, with no correlation; the track goes on from it
    assert r.pose is not None and math.isclose(r.pose.x, fix.x + 2.0, abs_tol=1e-9) and math.isnan(r.correlation)
    assert r.cells == 9 and t.pose is r.pose
    t.predict([1.0, 0.0, 0.0])
    r = t.localize(SimpleNamespace(timestamp=0.2, blind=True), fix)
    assert math.isclose(r.pose.x, fix.x + 3.0, abs_tol=1e-9)
    # a lost track has nothing to coast on: no answer (unknown motions beyond hold_motion lose it)
    for _ in range(t.localizer.config.hold_motion + 1):
        t.predict([float("nan")] * 3)
    assert t.localize(SimpleNamespace(timestamp=0.3, blind=True), fix).pose is None and t.pose is None
    # coast: false, the behaviour before: the frame has no answer and the track is lost
    old = CrossViewTracker(_Blind(coast=False))
    old.localize(SimpleNamespace(timestamp=0.0, blind=False), fix)
    old.predict([2.0, 0.0, 0.0])
    assert old.localize(SimpleNamespace(timestamp=0.1, blind=True), fix).pose is None and old.pose is None
    # a track the fixes say is lost does not coast either
    far = CrossViewTracker(_Blind(lost_after_s=0.0))
    far.pose = Pose2(0.0, 0.0, 0.0)
    assert far.localize(SimpleNamespace(timestamp=0.0, blind=True),
                        draw_prior((40.0, 0.0, 0.0), 1e-3, 0.0, np.random.default_rng(0))).pose is None


def test_a_held_motion_is_a_fallback_for_frames_without_an_answer_then_the_track_is_lost():
    nan = [float("nan")] * 3
    fix = draw_prior((0.0, 0.0, 0.0), 1e-3, 0.0, np.random.default_rng(0))
    t = CrossViewTracker(_Blind())
    t.localize(SimpleNamespace(timestamp=0.0, blind=False), fix)
    t.predict([1.0, 0.0, 0.1])                       # (2 m in all: within the fix's reach, 3 track_sigma_m)
    t.predict(nan)                                   # the odometry failed: moved by the last motion again
    assert t.stale
    r = t.localize(SimpleNamespace(timestamp=0.2, blind=True), fix)    # nothing to see: the held track answers
    want = Pose2(fix.x, fix.y, fix.yaw) @ Pose2(1.0, 0.0, 0.1) @ Pose2(1.0, 0.0, 0.1)
    assert np.allclose(r.pose.as_array(), want.as_array()) and math.isnan(r.correlation)
    assert t.localizer.calls[-1] == (fix, None)      # it searched its prior alone, with no belief from the track
    t.predict(nan)                                   # the second in a row: still held
    assert t.pose is not None
    t.predict(nan)                                   # the third: the track is lost
    assert t.pose is None and t.localize(SimpleNamespace(timestamp=0.4, blind=True), fix).pose is None
    # a frame with an answer of its own takes it, not the held track's; the track is fresh again
    t.localize(SimpleNamespace(timestamp=0.5, blind=False), fix)
    t.predict([1.0, 0.0, 0.0])
    t.predict(nan)
    other = draw_prior((5.0, 0.0, 0.0), 1e-3, 0.0, np.random.default_rng(0))
    r = t.localize(SimpleNamespace(timestamp=0.6, blind=False), other)
    assert t.localizer.calls[-1] == (other, None) and math.isclose(r.pose.x, other.x) and not t.stale
    # a held track beyond the fix's reach answers nothing
    t.predict([1.0, 0.0, 0.0])
    t.predict(nan)
    far = draw_prior((60.0, 0.0, 0.0), 1e-3, 0.0, np.random.default_rng(0))
    assert t.localize(SimpleNamespace(timestamp=0.7, blind=True), far).pose is None and t.pose is None
    # hold_motion 0, the behaviour before: lost at the first unknown motion (the default holds two)
    assert CrossViewConfig().hold_motion == 2
    old = CrossViewTracker(_Blind(hold_motion=0))
    old.localize(SimpleNamespace(timestamp=0.0, blind=False), fix)
    old.predict([2.0, 0.0, 0.0])
    old.predict(nan)
    assert old.pose is None
    with pytest.raises(ConfigError, match="hold_motion"):
        CrossViewConfig(hold_motion=-1)
    with pytest.raises(ConfigError, match="hold_motion"):
        CrossViewConfig(hold_motion=1.5)


def test_the_tracks_belief_widens_with_the_distance_travelled_since_its_last_answer():
    fix = draw_prior((0.0, 0.0, 0.0), 20.0, 0.0, np.random.default_rng(0))
    t = CrossViewTracker(_Blind())
    cfg = t.localizer.config
    assert (cfg.track_sigma_m, cfg.track_sigma_per_m) == (1.0, 0.14)
    t.localize(SimpleNamespace(timestamp=0.0, blind=False), fix)
    assert t.travelled == 0.0 and t.sigma_m() == cfg.track_sigma_m
    t.predict([3.0, 4.0, 0.0])
    t.localize(SimpleNamespace(timestamp=0.1, blind=False), fix)
    assert math.isclose(t.localizer.calls[-1][1][1], math.hypot(1.0, 0.14 * 5.0))   # the belief it searched with
    assert t.travelled == 0.0                         # an answer of its own: narrow again
    # a frame with no answer coasts and keeps widening: 5 m, then 5 m more
    t.predict([5.0, 0.0, 0.0])
    t.localize(SimpleNamespace(timestamp=0.2, blind=True), fix)
    t.predict([5.0, 0.0, 0.0])
    t.localize(SimpleNamespace(timestamp=0.3, blind=True), fix)
    assert math.isclose(t.localizer.calls[-1][1][1], math.hypot(1.0, 0.14 * 10.0)) and t.travelled == 10.0
    # track_sigma_per_m 0: a fixed belief (with track_sigma_m 2, the behaviour before)
    fixed = CrossViewTracker(_Blind(track_sigma_m=2.0, track_sigma_per_m=0.0))
    fixed.localize(SimpleNamespace(timestamp=0.0, blind=False), fix)
    fixed.predict([30.0, 0.0, 0.0])
    fixed.localize(SimpleNamespace(timestamp=0.1, blind=False), fix)
    assert fixed.localizer.calls[-1][1][1] == 2.0
    with pytest.raises(ConfigError, match="track_sigma_per_m"):
        CrossViewConfig(track_sigma_per_m=-0.1)
