"""Tracking (satloc.tracking.track): the odometry-driven belief over candidate poses, and its use by the localizer."""
import math

import numpy as np
import pytest
from test_method import GridConfig, build_dictionary, tiny_setup

from satloc import ConfigError, Pose2
from satloc.localizers.database import Localizer, LocalizerConfig
from satloc.tracking.track import TrackConfig, Tracker, compose_motion, noisy_odometry, relative_motion

STEP = 5.0


def line_candidates(length=200.0, spacing=0.5):
    """Candidates along the x axis (heading east), plus the same positions heading west."""
    x = np.arange(0.0, length + 1e-9, spacing)
    east = np.stack([x, np.zeros_like(x), np.zeros_like(x)], 1)
    west = np.stack([x, np.zeros_like(x), np.full_like(x, math.pi)], 1)
    return np.concatenate([east, west])


def peaks(cands, centres, sigma=0.7):
    """A posterior with equal Gaussian peaks at the x positions ``centres`` (eastward candidates only)."""
    p = np.zeros(len(cands))
    for c in centres:
        p += np.exp(-0.5 * ((cands[:, 0] - c) / sigma) ** 2) * (cands[:, 2] == 0)
    return p / p.sum()


def argmax_x(belief, cands):
    return float(cands[int(np.argmax(belief)), 0])


def test_motion_helpers_round_trip():
    a, b, c = Pose2(3.0, -2.0, 0.4), Pose2(7.0, 1.0, 1.3), Pose2(4.0, 6.0, -2.9)
    ab, bc = relative_motion(a, b), relative_motion(b, c)
    assert (a @ Pose2(*ab)).as_array() == pytest.approx(b.as_array())
    assert (a @ Pose2(*compose_motion(ab, bc))).as_array() == pytest.approx(c.as_array())
    poses = np.array([[0, 0, 0], [5, 0, 0.1], [9, 1, 0.5], [np.nan, np.nan, np.nan], [12, 3, 0.6]], float)
    odo = noisy_odometry(poses, (0.0, 0.0))
    assert np.all(np.isnan(odo[[0, 3, 4]]))          # no previous pose, or a pose missing on either side
    assert (Pose2(*poses[1]) @ Pose2(*odo[2])).as_array() == pytest.approx(poses[2])
    noisy = noisy_odometry(poses, (0.05, 0.02), seed=3)
    assert np.array_equal(noisy[1:3], noisy_odometry(poses, (0.05, 0.02), seed=3)[1:3])  # seeded
    assert not np.allclose(noisy[1:3], odo[1:3])


def test_predict_moves_the_belief_by_the_odometry_and_keeps_headings_apart():
    cands = line_candidates()
    t = Tracker(cands, TrackConfig(revive=0.0))
    t.predict(np.array([STEP, 0.0, 0.0]))          # before the first frame: nothing to move
    assert t.belief is None
    start = np.zeros(len(cands))
    start[40] = 1.0                                  # x = 20 m, heading east
    t.fuse(start)
    t.predict(np.array([STEP, 0.0, 0.0]))
    b = t.belief
    assert b.sum() == pytest.approx(1.0)
    assert float(b @ cands[:, 0]) == pytest.approx(20.0 + STEP, abs=0.05)
    assert b[cands[:, 2] != 0].sum() == 0            # no probability crosses to the opposite heading
    # the spread grows with the distance travelled (odometry error)
    spread = lambda b: math.sqrt(float(b @ (cands[:, 0] - b @ cands[:, 0]) ** 2))
    t2 = Tracker(cands, TrackConfig(revive=0.0))
    t2.fuse(start)
    t2.predict(np.array([40.0, 0.0, 0.0]))
    assert spread(t2.belief) > 1.5 * spread(b)


def test_predict_follows_turns_and_sideways_motion():
    # candidates on a counter-clockwise circle of radius 20 m, heading along it, on 3 lanes 1 m apart
    th = np.arange(0.0, 2 * math.pi, 0.5 / 20.0)
    cands = np.concatenate([np.stack([(20 + o) * np.cos(th), (20 + o) * np.sin(th), th + math.pi / 2], 1)
                            for o in (-1.0, 0.0, 1.0)])
    cands[:, 2] = np.vectorize(lambda a: math.atan2(math.sin(a), math.cos(a)))(cands[:, 2])
    t = Tracker(cands, TrackConfig(sigma_m=0.3, sigma_frac=0.0, revive=0.0))
    i, j = 10, len(th) + 70       # from the inner lane to the middle lane, 60 candidates (30 m) on
    start = np.zeros(len(cands))
    start[i] = 1.0
    t.fuse(start)
    t.predict(relative_motion(Pose2(*cands[i]), Pose2(*cands[j])))   # a turn with a sideways component
    assert int(np.argmax(t.belief)) == j
    assert abs(float(t.belief @ cands[:, 0]) - cands[j, 0]) < 0.15
    assert abs(float(t.belief @ cands[:, 1]) - cands[j, 1]) < 0.15


def test_tracking_resolves_aliasing_that_single_frames_cannot():
    cands = line_candidates()
    rng = np.random.default_rng(0)
    t = Tracker(cands)
    wrong_single = 0
    for k in range(12):
        truth = 10.0 + STEP * k
        alias = 100.0 + 90.0 * rng.random()      # a look-alike place, not where the odometry leads
        p = peaks(cands, [alias]) if k % 3 == 2 else peaks(cands, [truth, alias])
        if k:
            t.predict(np.array([STEP, 0.0, 0.0]))
        b = t.fuse(p)
        wrong_single += abs(argmax_x(p, cands) - truth) > 0.5
        if k >= 1:
            assert abs(argmax_x(b, cands) - truth) <= 0.5, k
    assert wrong_single == 4                     # the frames that show only the alias


def test_a_belief_locked_on_the_wrong_place_recovers():
    cands = line_candidates()
    t = Tracker(cands)
    x = 20.0
    for _ in range(5):
        t.fuse(peaks(cands, [x]))
        t.predict(np.array([STEP, 0.0, 0.0]))
        x += STEP
    x += 70.0                                        # moved without odometry (kidnapped)
    recovered = None
    for k in range(6):
        b = t.fuse(peaks(cands, [x]))
        if abs(argmax_x(b, cands) - x) <= 0.5:
            recovered = k
            break
        t.predict(np.array([STEP, 0.0, 0.0]))
        x += STEP
    assert recovered is not None and recovered <= 3


def detour():
    """Poses along the candidate line, a detour off it (north, east, south) and back onto it further on."""
    h = math.pi / 2
    return np.array([(20, 0, 0), (30, 0, 0), (40, 0, 0), (50, 0, 0), (55, 10, h), (55, 20, h), (55, 30, h),
                     (65, 35, 0), (75, 35, 0), (85, 30, -h), (85, 20, -h), (85, 10, -h), (95, 0, 0), (105, 0, 0),
                     (115, 0, 0)], float)


def run_detour(config):
    """Track the detour with noise-free odometry: on the line each frame shows the truth and a look-alike,
    off it only a look-alike (a street like the mapped one). Returns (p_on, argmax x, on the line) per frame."""
    cands, poses = line_candidates(), detour()
    rng = np.random.default_rng(1)
    t = Tracker(cands, config)
    out = []
    for k, pose in enumerate(poses):
        on_line = abs(pose[1]) < 1e-9
        alias = 130.0 + 60.0 * rng.random()
        if k:
            t.predict(relative_motion(Pose2(*poses[k - 1]), Pose2(*pose)))
        b = t.fuse(peaks(cands, [pose[0], alias] if on_line else [alias]))
        out.append((t.p_on, argmax_x(b, cands), on_line))
    return out


def test_leaving_the_map_is_recognised_by_the_odometry_and_the_return_is_found():
    out = run_detour(TrackConfig())
    poses = detour()
    for (p_on, x, on_line), pose in zip(out, poses):
        if on_line:
            assert p_on > 0.99, pose                      # on the mapped line: inside ...
            assert abs(x - pose[0]) <= 0.5, pose          # ... and at the truth, the look-alike rejected
        else:
            assert p_on < 0.01, pose                      # off it, although every image shows a look-alike
    # without off-map hypotheses the lost probability is dropped: P(on the map) stays 1, and after the
    # detour the belief starts again from the images alone
    plain = run_detour(TrackConfig(off_map=False))
    assert all(p == 1.0 for p, _, _ in plain)


def test_off_map_hypotheses_are_grouped_and_bounded():
    cands = line_candidates()
    t = Tracker(cands, TrackConfig(off_map_hypotheses=2, revive=0.0))
    t.fuse(peaks(cands, [20.0, 60.0, 100.0, 140.0]))        # four separate peaks ...
    t.predict(np.array([0.0, 10.0, 0.0]))                    # ... all moved 10 m sideways, off the line
    assert len(t.off) == 2 and t.p_on == pytest.approx(0.0, abs=1e-9)
    assert t.off[:, 3].sum() == pytest.approx(1.0)
    assert t.belief.sum() == pytest.approx(1.0) and np.all(np.isfinite(t.belief))
    t.predict(np.array([0.0, -10.0, 0.0]))                   # straight back: both groups land again
    assert len(t.off) == 0 and t.p_on == pytest.approx(1.0)
    with pytest.raises(ConfigError, match="off_map_hypotheses"):
        TrackConfig(off_map_hypotheses=0)
    with pytest.raises(ConfigError, match="inlier_threshold"):
        TrackConfig(inlier_threshold=0.0)


def test_tracker_errors():
    cands = line_candidates()
    with pytest.raises(ConfigError, match="sigma_m"):
        TrackConfig(sigma_m=0.0)
    with pytest.raises(ConfigError, match="heading_gate_deg"):
        TrackConfig(heading_gate_deg=0.0)
    with pytest.raises(ConfigError, match="revive"):
        TrackConfig(revive=1.0)
    with pytest.raises(ConfigError, match="odometry noise: expected 2 non-negative"):
        noisy_odometry(np.zeros((3, 3)), (-0.1, 0.0))
    with pytest.raises(ConfigError, match=r"non-empty \(C, 3\)"):
        Tracker(np.zeros((0, 3)))
    t = Tracker(cands)
    with pytest.raises(ConfigError, match="does not match the 802 candidates"):
        t.fuse(np.ones(10))
    t.fuse(peaks(cands, [20.0]))
    for bad in (None, [1.0, 2.0], [np.nan, 0.0, 0.0]):
        with pytest.raises(ConfigError, match="odometry must be 3 finite numbers"):
            t.predict(bad)
    with pytest.raises(ConfigError, match="finite and non-negative"):
        t.fuse(np.full(len(cands), np.nan))
    t.reset()
    assert t.belief is None


def test_localizer_tracks_a_stream_like_single_calls():
    cam, seq, sf, ext = tiny_setup()
    d = build_dictionary(seq, sf, ext, GridConfig(step_px=4, min_depth_m=1.0), depth_source="frame", progress=False)
    loc = Localizer(d, sf, ext, cam, None, LocalizerConfig(mode="np", depth_source="frame", track=True))
    assert loc.config.name == "np+track"
    frames = [seq[i] for i in range(len(seq))]
    odo = noisy_odometry(seq.poses, (0.02, 0.01))
    manual, t = [], loc.tracker()
    for f, o in zip(frames, odo):
        t.predict(o)
        manual.append(loc.localize(f, tracker=t))
    assert np.allclose(t.belief, manual[-1].posterior)
    streamed = list(loc.localize_stream(frames, tracker=loc.tracker(), odometry=odo))
    for a, b in zip(manual, streamed):
        assert a.estimate == b.estimate and np.array_equal(a.posterior, b.posterior)
    single = loc.localize(frames[-1])
    # tracked, the inlier test is the tracker's P(on the map): the frames follow the database path
    assert manual[-1].inlier_score == t.p_on and t.p_on > 0.99 and manual[-1].inlier
    assert single.inlier_score != manual[-1].inlier_score             # single-image: peak / mean score
    # the answer is the belief times the frame's posterior (plus the floor), renormalised
    t_before = loc.tracker()
    for f, o in zip(frames[:-1], odo[:-1]):
        t_before.predict(o)
        loc.localize(f, tracker=t_before)
    t_before.predict(odo[-1])
    prior = t_before.belief.copy()
    fused = prior * (single.posterior + loc.config.tracking.floor / len(prior))
    assert np.allclose(manual[-1].posterior, fused / fused.sum(), rtol=1e-9, atol=1e-15)
    # a None first odometry row is a value (unused: no belief yet), not the end of the odometry
    first = list(loc.localize_stream(frames, tracker=loc.tracker(), odometry=[None] + list(odo[1:])))
    assert np.array_equal(first[-1].posterior, manual[-1].posterior)
    # an unknown motion (NaN, e.g. visual odometry lost) starts a new belief there: the next frame's answer is
    # its own posterior, as a first frame's
    lost = np.array(odo, np.float64)
    lost[-1] = np.nan
    t_lost = loc.tracker()
    gone = list(loc.localize_stream(frames, tracker=t_lost, odometry=lost))
    fresh = loc.tracker()
    alone = loc.localize(frames[-1], tracker=fresh)
    assert np.array_equal(gone[-1].posterior, alone.posterior) and np.array_equal(t_lost.belief, fresh.belief)
    with pytest.raises(ConfigError, match="needs both a tracker and the odometry"):
        list(loc.localize_stream(frames, tracker=loc.tracker()))
    with pytest.raises(ConfigError, match="odometry ran out"):
        list(loc.localize_stream(frames, tracker=loc.tracker(), odometry=odo[:2]))
    with pytest.raises(ConfigError, match="the localizer's own candidates"):
        loc.localize(frames[0], candidates=loc.candidates[:10], tracker=loc.tracker())


def test_locked_needs_the_belief_concentrated_near_its_mode():
    cands = line_candidates()
    t = Tracker(cands, TrackConfig(lock_m=10.0, lock_mass=0.9))
    assert not t.locked()                                   # no belief yet: a uniform prior
    t.fuse(peaks(cands, [50.0]))
    assert t.locked()
    t.fuse(peaks(cands, [50.0, 120.0]))                     # the belief keeps its peak at 50 m
    assert t.locked()
    t.reset()
    t.fuse(peaks(cands, [50.0, 120.0]))                     # two equal places 70 m apart: half the mass each
    assert not t.locked()
    t.fuse(peaks(cands, [50.0]))
    assert t.belief[np.abs(cands[:, 0] - 50) <= 10].sum() > 0.99 and t.locked()
    t.p_on = 0.5                                            # probably off the map: not locked
    assert not t.locked()
    lazy = Tracker(cands, TrackConfig(lock_mass=0.0))       # 0: only a new belief searches everything
    assert not lazy.locked()
    lazy.fuse(peaks(cands, [50.0, 120.0]))
    assert lazy.locked()
    with pytest.raises(ConfigError, match="lock_mass"):
        TrackConfig(lock_mass=1.5)


def test_a_tracker_that_has_not_locked_scores_every_candidate():
    cam, seq, sf, ext = tiny_setup()
    d = build_dictionary(seq, sf, ext, GridConfig(step_px=4, min_depth_m=1.0), depth_source="frame", progress=False)
    common = dict(mode="np", depth_source="frame", candidate_spacing_m=0.5)
    pruned = Localizer(d, sf, ext, cam, None, LocalizerConfig(prune_regions=1, prune_window_m=2.0, **common))
    every = Localizer(d, sf, ext, cam, None, LocalizerConfig(prune_regions=0, **common))
    f = seq[2]
    single, full = pruned.localize(f), every.localize(f)
    assert np.count_nonzero(single.posterior) < np.count_nonzero(full.posterior)    # pruning drops candidates
    tracked = pruned.localize(f, tracker=pruned.tracker())                            # a new belief: all scored
    assert np.allclose(tracked.posterior, full.posterior, rtol=1e-9, atol=1e-15)
    lazy = pruned.tracker(TrackConfig(lock_mass=0.0))
    lazy.fuse(single.posterior)                               # a belief that counts as locked: pruned again
    again = pruned.localize(f, tracker=lazy)
    b = single.posterior * (single.posterior + lazy.config.floor / len(single.posterior))
    assert np.allclose(again.posterior, b / b.sum(), rtol=1e-9, atol=1e-15)


def test_pipeline_localize_needs_matching_odometry_to_track(tmp_path):
    from satloc.pipeline import localize

    cam, seq, sf, ext = tiny_setup()
    d = build_dictionary(seq, sf, ext, GridConfig(step_px=4, min_depth_m=1.0), depth_source="frame", progress=False)
    cfg = LocalizerConfig(mode="np", depth_source="frame", track=True)
    loc = Localizer(d, sf, ext, cam, None, cfg)
    with pytest.raises(ConfigError, match="needs odometry"):
        localize(None, seq, cfg, progress=False, localizer=loc)
    with pytest.raises(ConfigError, match=r"expected a \(5, 3\) array"):
        localize(None, seq, cfg, progress=False, localizer=loc, odometry=np.zeros((4, 3)))
    s = localize(None, seq, cfg, tmp_path, progress=False, localizer=loc, odometry=noisy_odometry(seq.poses, (0.02, 0.01)))
    assert s["mode"] == "np+track" and (tmp_path / "localization_np+track.npz").is_file()
    assert s["queries"] == 5 and s["failed"] == 0 and np.isfinite(s["mean_m"])


def test_experiment_modes_name_tracking_and_alignment():
    from satloc_env.experiments.scene_run import METHOD_NAMES, MODES, ExperimentConfig

    assert set(MODES) <= set(METHOD_NAMES)
    assert METHOD_NAMES["full+track+align"] == "Ours-full + track + BEV align"
    assert METHOD_NAMES["go+track"] == "Ours-GO + track"
    with pytest.raises(ConfigError, match="unknown"):
        ExperimentConfig(modes=("full+align+track",))


def test_compose_between_composes_the_steps_between_the_frames_taken():
    from satloc.tracking.track import compose_between, compose_motion

    steps = np.array([[np.nan] * 3, [1.0, 0.0, 0.1], [1.0, 0.2, -0.05], [0.5, 0.0, 0.0], [np.nan, 0.0, 0.0]])
    out = compose_between(steps, [0, 2, 3, 3, 4])
    assert np.isnan(out[0]).all() and np.isnan(out[3]).all() and np.isnan(out[4]).any()   # none / repeated / unknown
    assert np.allclose(out[1], compose_motion(steps[1], steps[2])) and np.allclose(out[2], steps[3])
