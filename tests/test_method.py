import math

import numpy as np
import pytest

from satloc import ConfigError, FormatError, Frame, Pose2, SatelliteMap, Sequence, StereoCamera
from satloc.features import BilateralRGB
from satloc.features.dictionary import Dictionary, GridConfig, SatelliteFeatures, build_dictionary, ground_samples
from satloc.features.projection import ProjectionConfig, Projections, evaluate_loss, train_projections
from satloc.localizers.database import Localizer, LocalizerConfig, candidate_poses


def flat_ground_depth(cam: StereoCamera) -> np.ndarray:
    """Exact z-depth of a flat ground plane for a level camera (0 above the horizon)."""
    v = np.arange(cam.height, dtype=np.float64)[:, None] - cam.cy
    d = np.where(v > 0.5, cam.fy * cam.mount_height / np.maximum(v, 1e-9), 0.0)
    return np.broadcast_to(d, (cam.height, cam.width)).astype(np.float32).copy()


def test_known_ground_point_projects_onto_the_satellite_map():
    cam = StereoCamera(100, 60, 50.0, 50.0, 49.5, 29.5, 0.5, mount_height=1.5)
    depth = flat_ground_depth(cam)
    uv, pv = ground_samples(cam, depth, GridConfig(step_px=1, row_start_frac=0.0, min_depth_m=1.0, max_depth_m=100))
    # pixel (u=79, v=44): z = fy * h / (v - cy) = 50 * 1.5 / 14.5, lateral x_cam = (u - cx) / fx * z
    k = np.flatnonzero((uv[:, 0] == 79) & (uv[:, 1] == 44))[0]
    z = 50 * 1.5 / 14.5
    lateral = (79 - 49.5) / 50 * z
    assert pv[k] == pytest.approx([z, -lateral, 0.0], abs=1e-5)  # float32 depth map  # ahead, to the right (negative y), on the ground
    # vehicle at (10, 20) heading north: ahead is +y, right is +x; map 0.5 m/px with origin (0, 40)
    pose = Pose2(10.0, 20.0, math.pi / 2)
    xy = pose.transform(pv[k:k + 1, :2])[0]
    assert xy == pytest.approx([10 + lateral, 20 + z], abs=1e-5)
    sm = SatelliteMap(np.zeros((80, 80, 3), np.uint8), 0.5, (0.0, 40.0))
    col, row = sm.world_to_pixel(xy)
    assert (col, row) == pytest.approx(((10 + lateral) / 0.5 - 0.5, (40 - 20 - z) / 0.5 - 0.5), abs=1e-4)


def synthetic_dictionary(n=3000, seed=0):
    rng = np.random.default_rng(seed)
    loc = rng.uniform(0, 100, (n, 2))
    # features: a location-informative part plus a nuisance dimension with large variance
    g = np.c_[loc / 50 + 0.05 * rng.standard_normal((n, 2)), 3 * rng.standard_normal((n, 1))].astype(np.float32)
    s = np.c_[loc / 50 + 0.05 * rng.standard_normal((n, 2)), 3 * rng.standard_normal((n, 1))].astype(np.float32)
    poses = np.c_[np.linspace(0, 100, 50), np.full(50, 50.0), np.zeros(50)]
    return Dictionary(g, s, loc, np.zeros(n, np.int32), poses, GridConfig(), "synthetic")


def test_ranking_loss_decreases_on_a_fixed_seed_problem():
    d = synthetic_dictionary()
    cfg = ProjectionConfig(max_anchors=2000, max_epochs=15, alpha=0.01, lr=0.02)
    p = train_projections(d, cfg, progress=False)
    assert p.loss_curve[-1] < 0.8 * p.loss_curve[0]
    assert evaluate_loss(d, p, cfg) < evaluate_loss(d, Projections.identity(3, 3), cfg)
    # the nuisance dimension is suppressed
    assert abs(p.W_g[2, 2]) < abs(p.W_g[0, 0])
    # the held-out co-occurrence margin was measured from the identity on, and the kept epoch is its best
    assert len(p.val_curve) == len(p.loss_curve) + 1 and p.best_epoch >= 1
    assert p.val_curve[p.best_epoch] > p.val_curve[0]


def test_projection_learning_keeps_the_identity_when_the_held_out_margin_does_not_improve():
    """Features carry no location information: whatever the ranking loss does, the held-out co-occurrence
    margin does not rise significantly (val_z standard errors), so W stays the identity."""
    rng = np.random.default_rng(1)
    n = 3000
    loc = rng.uniform(0, 100, (n, 2))
    g, s = (rng.standard_normal((n, 3)).astype(np.float32) for _ in range(2))
    poses = np.c_[np.linspace(0, 100, 50), np.full(50, 50.0), np.zeros(50)]
    d = Dictionary(g, s, loc, np.repeat(np.arange(50, dtype=np.int32), n // 50), poses, GridConfig(), "noise")
    p = train_projections(d, ProjectionConfig(max_anchors=2000, max_epochs=6, lr=0.02), progress=False)
    assert p.best_epoch == 0 and len(p.val_curve) >= 2
    assert np.array_equal(p.W_g, np.eye(3, dtype=np.float32)) and np.array_equal(p.W_s, np.eye(3, dtype=np.float32))


def test_dictionary_and_projection_round_trips(tmp_path):
    d = synthetic_dictionary(200)
    d.save(tmp_path / "d.npz")
    e = Dictionary.load(tmp_path / "d.npz")
    for k in ("g", "s", "loc", "frame", "poses"):
        assert np.array_equal(getattr(d, k), getattr(e, k))
    assert e.grid == d.grid and e.feature_name == "synthetic"
    p = Projections(np.arange(9, dtype=np.float32).reshape(3, 3), np.eye(3, dtype=np.float32), [3.0, 2.0], True,
                    [0.5, 0.75, 0.7], 1)
    p.save(tmp_path / "p.pt")
    q = Projections.load(tmp_path / "p.pt")
    assert np.array_equal(p.W_g, q.W_g) and q.loss_curve == [3.0, 2.0] and q.converged
    assert q.val_curve == [0.5, 0.75, 0.7] and q.best_epoch == 1
    sf = SatelliteFeatures(np.ones((4, 5, 2), np.float16), 0.2, (1.0, 2.0), "x")
    sf.save(tmp_path / "sf.npz")
    assert np.array_equal(SatelliteFeatures.load(tmp_path / "sf.npz").features, sf.features)


def test_damaged_and_foreign_saved_files(tmp_path):
    (tmp_path / "p.pt").write_bytes(b"not a torch file")
    with pytest.raises(FormatError, match="p.pt: damaged"):
        Projections.load(tmp_path / "p.pt")
    synthetic_dictionary(50).save(tmp_path / "d.npz")
    with pytest.raises(FormatError, match="expected a satloc 'satellite_features' file, found format 'dictionary'"):
        SatelliteFeatures.load(tmp_path / "d.npz")
    import torch
    torch.save({"format": "something_else"}, tmp_path / "o.pt")
    with pytest.raises(FormatError, match="not a satloc 'projections' file"):
        Projections.load(tmp_path / "o.pt")


def test_candidates_follow_the_path():
    poses = np.array([[0, 0, 0], [10, 0, 0], [10, 10, math.pi / 2]], float)
    c = candidate_poses(poses, 0.5, (0.0, 1.0))
    assert len(c) == 2 * 41
    assert np.all(np.linalg.norm(np.diff(c[:41, :2], axis=0), axis=1) <= 0.5 + 1e-9)
    assert c[5] == pytest.approx([2.5, 0.0, 0.0])
    assert c[41 + 5] == pytest.approx([2.5, 1.0, 0.0])  # one metre to the left


def tiny_setup():
    cam = StereoCamera(64, 40, 32.0, 32.0, 31.5, 19.5, 0.5, 1.5)
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (40, 64, 3), np.uint8)
    frames = [Frame(img, img, Pose2(20 + i, 20, 0.0), i, flat_ground_depth(cam)) for i in range(5)]
    seq = Sequence(cam, frames)
    sm = SatelliteMap(rng.integers(0, 255, (200, 200, 3), np.uint8), 0.2, (0.0, 40.0))
    ext = BilateralRGB()
    sf = SatelliteFeatures.compute(sm, ext)
    return cam, seq, sf, ext


def test_clear_errors():
    cam, seq, sf, ext = tiny_setup()
    grid = GridConfig(step_px=4, min_depth_m=1.0)
    with pytest.raises(ConfigError, match="database sequence .* is empty"):
        build_dictionary(Sequence(cam, []), sf, ext, grid, depth_source="frame", progress=False)
    d = build_dictionary(seq, sf, ext, grid, depth_source="frame", progress=False)
    assert len(d) > 0
    empty = Dictionary(d.g[:0], d.s[:0], d.loc[:0], d.frame[:0], d.poses, d.grid)
    with pytest.raises(ConfigError, match="dictionary is empty"):
        Localizer(empty, sf, ext, cam, None, LocalizerConfig(mode="np", depth_source="frame"))
    loc = Localizer(d, sf, ext, cam, None, LocalizerConfig(mode="np", depth_source="frame"))
    f = seq[0]
    with pytest.raises(FormatError, match="query frame.left: expected a 64x40"):
        loc.localize(Frame(f.left[:20], f.right, None, 0.0, f.depth))
    with pytest.raises(ConfigError, match="no grid sample has valid depth"):
        loc.localize(Frame(f.left, f.right, None, 0.0, np.zeros_like(f.depth)))
    with pytest.raises(ConfigError, match="mode 'full' needs learned projections"):
        Localizer(d, sf, ext, cam, None, LocalizerConfig(mode="full", depth_source="frame"))
    with pytest.raises(ConfigError, match="ef_search: expected >= neighbors"):
        LocalizerConfig(ef_search=8)
    r = loc.localize(f)
    assert r.posterior.shape == (len(loc.candidates),) and r.posterior.sum() == pytest.approx(1.0)


def test_metric_context_windows_are_box_means():
    from satloc.features.context import ContextConfig, ground_context, satellite_context

    rng = np.random.default_rng(3)
    fmap = rng.random((60, 80, 5)).astype(np.float32)
    cfg = ContextConfig(scales_m=(1.0, 2.2))
    # satellite: 0.2 m/px -> windows of 5 and 11 px (half 2 and 6 rounded: 1.0/0.2/2=2.5->2, 2.2/0.2/2=5.5->6)
    rows, cols = np.array([10, 30, 59, 0]), np.array([10, 40, 79, 0])
    out = satellite_context(fmap, rows, cols, 0.2, cfg, (1, 4), strip=7)
    for n, (r, c) in enumerate(zip(rows, cols)):
        for k, hr in enumerate((2, 6)):
            win = fmap[max(0, r - hr):r + hr + 1, max(0, c - hr):c + hr + 1, 1:4]
            np.testing.assert_allclose(out[n, 3 * k:3 * k + 3], win.mean(axis=(0, 1)), rtol=1e-5)
    # strips are an implementation detail: the same answer with one strip
    np.testing.assert_allclose(out, satellite_context(fmap, rows, cols, 0.2, cfg, (1, 4), strip=1000), rtol=1e-6)
    # ground: a window of s metres at depth d is fx * s / d pixels wide
    uv = np.array([[40, 30], [5, 5]])
    g = ground_context(fmap, uv, np.array([10.0, 20.0]), 50.0, cfg, (0, 5))
    r = int(round(50.0 * 1.0 / 10.0 / 2))       # 2.5 -> 2 (round half to even)
    np.testing.assert_allclose(g[0, :5], fmap[30 - r:30 + r + 1, 40 - r:40 + r + 1].mean(axis=(0, 1)), rtol=1e-5)
    assert g.shape == (2, 10)


def test_compiled_scores_match_the_numpy_formula():
    """The numba kernel against the co-occurrence score written out directly."""
    from satloc._kernels import cooccurrence_scores

    rng = np.random.default_rng(5)
    n, m, n_entries, h, w = 30, 4, 50, 20, 25
    gid = rng.integers(-1, n_entries, (n, m))
    wg = rng.random((n, m)).astype(np.float32)
    pixel_row = np.where(rng.random(h * w) < 0.8, np.arange(h * w), -1).astype(np.int32)
    sat_ids = rng.integers(0, n_entries, (h * w, m)).astype(np.int64)
    sat_w = rng.random((h * w, m)).astype(np.float32)
    pv = rng.uniform(0, 2, (n, 2))
    cands = np.column_stack([rng.uniform(0, 2, 6), rng.uniform(-2, 0, 6), rng.uniform(-3, 3, 6)])
    got = cooccurrence_scores(cands, pv, gid, wg, 0.0, 0.0, 0.2, h, w, pixel_row, sat_ids, sat_w, n_entries)
    for c, (x, y, yaw) in enumerate(cands):
        want = 0.0
        for j in range(n):
            px = x + np.cos(yaw) * pv[j, 0] - np.sin(yaw) * pv[j, 1]
            py = y + np.sin(yaw) * pv[j, 0] + np.cos(yaw) * pv[j, 1]
            col, row = int(np.floor(px / 0.2)), int(np.floor(-py / 0.2))
            if not (0 <= row < h and 0 <= col < w) or pixel_row[row * w + col] < 0:
                continue
            r = pixel_row[row * w + col]
            for k in range(m):
                for k2 in range(m):
                    if gid[j, k2] >= 0 and gid[j, k2] == sat_ids[r, k]:
                        want += wg[j, k2] * sat_w[r, k]
        assert got[c] == pytest.approx(want, rel=1e-5, abs=1e-9)
    assert got.max() > 0


def test_entry_density_is_the_voting_kernel_summed_over_the_entries():
    """Unsmoothed, the raster at a cell is the ground-only voting kernel summed over the dictionary's entries
    (entries on cell centres: exact); smoothing keeps its sum; the compiled look-up reads the cell under each
    sample of each candidate."""
    from satloc._kernels import location_scores
    from satloc.localizers.database import entry_density

    rng = np.random.default_rng(3)
    loc = rng.integers(0, 40, (60, 2)) * 0.25 + 0.125 + 10.0          # on the centres of 0.25 m cells
    dens, x0, y0, cell = entry_density(loc, 1.0, 0.0)
    assert cell == 0.25 and (x0 - 0.125) / cell == pytest.approx(round((x0 - 0.125) / cell))
    for _ in range(20):
        p = loc[rng.integers(len(loc))] + rng.integers(-6, 7, 2) * 0.25
        d = np.hypot(*(loc - p).T)
        want = np.sum(np.where(d <= 1.0 + 1e-9, 1.0 / np.maximum(d, 0.25), 0.0))
        got = dens[int((p[1] - y0) // cell), int((p[0] - x0) // cell)]
        assert got == pytest.approx(want, rel=1e-5)
    smooth = entry_density(loc, 1.0, 2.0)
    assert smooth[0].sum() == pytest.approx(dens.sum(), rel=1e-3) and smooth[0].max() < dens.max()
    pv = rng.uniform(0, 5, (7, 2))
    cands = np.column_stack([rng.uniform(8, 20, 5), rng.uniform(8, 20, 5), rng.uniform(-3, 3, 5)])
    none = np.zeros((len(pv), 1, 2))
    got = location_scores(cands, pv, none, np.zeros((len(pv), 1), np.float32), 1.0, dens, x0, y0, cell)[1]
    assert not location_scores(cands, pv, none, np.zeros((len(pv), 1), np.float32), 1.0,
                               np.zeros((0, 0), np.float32), 0.0, 0.0, 1.0)[1].any()
    for c, (x, y, yaw) in enumerate(cands):
        px = x + np.cos(yaw) * pv[:, 0] - np.sin(yaw) * pv[:, 1]
        py = y + np.sin(yaw) * pv[:, 0] + np.cos(yaw) * pv[:, 1]
        col, row = np.floor((px - x0) / cell).astype(int), np.floor((py - y0) / cell).astype(int)
        on = (row >= 0) & (row < dens.shape[0]) & (col >= 0) & (col < dens.shape[1])
        assert got[c] == pytest.approx(dens[row[on], col[on]].sum(), rel=1e-6)


def test_ground_only_weighs_a_place_by_what_chance_gives_it():
    """A place the database saw from few frames (2 entries, both among a sample's neighbours) against one it saw
    from many (20 entries, 4 among the neighbours): the plain ground-only sum prefers the second, the sum divided
    by the entries' density (``go_density_m``) the first."""
    cam, seq, sf, ext = tiny_setup()
    d = build_dictionary(seq, sf, ext, GridConfig(step_px=4, min_depth_m=1.0), depth_source="frame", progress=False)
    assert len(d) >= 22
    poses = np.column_stack([np.arange(0.0, 41.0), np.zeros(41), np.zeros(41)])
    loc = np.vstack([np.full((2, 2), [10.0, 0.0]),
                     np.array([30.0, 0.0]) + np.random.default_rng(0).normal(0, 0.3, (20, 2))])
    toy = Dictionary(d.g[:22], d.s[:22], loc, np.r_[np.full(2, 10), np.full(20, 30)].astype(np.int32), poses,
                     d.grid, d.feature_name, d.context)
    gid = np.array([[0, 1, 2, 3, 4, 5]])                      # one sample: both of the first place, 4 of the second
    wg = np.ones((1, 6), np.float32)
    pv = np.array([[5.0, 0.0]])
    cands = np.array([[5.0, 0.0, 0.0], [25.0, 0.0, 0.0]])     # placing the sample at the first / second place
    common = dict(mode="go", depth_source="frame", go_radius_m=1.0)
    plain = Localizer(toy, sf, ext, cam, None, LocalizerConfig(go_density_m=0.0, **common))._scores(cands, pv, gid, wg)
    dens = Localizer(toy, sf, ext, cam, None, LocalizerConfig(**common))._scores(cands, pv, gid, wg)
    assert plain[1] > plain[0] > 0
    assert dens[0] > dens[1] > 0
    with pytest.raises(ConfigError, match="go_density_m"):
        LocalizerConfig(go_density_m=-1.0)


def test_stream_gives_what_single_calls_give_and_reports_bad_frames():
    cam, seq, sf, ext = tiny_setup()
    d = build_dictionary(seq, sf, ext, GridConfig(step_px=4, min_depth_m=1.0), depth_source="frame", progress=False)
    loc = Localizer(d, sf, ext, cam, None, LocalizerConfig(mode="np", depth_source="frame"))
    frames = [seq[i] for i in range(len(seq))]
    single = [loc.localize(f) for f in frames]
    for overlap in (True, False):
        streamed = list(loc.localize_stream(iter(frames), overlap=overlap))
        assert len(streamed) == len(frames)
        for a, b in zip(single, streamed):
            assert a.estimate == b.estimate and np.array_equal(a.posterior, b.posterior)
    # a frame without valid depth: its error in place (errors="yield"), or raised, ending the stream
    bad = Frame(frames[0].left, frames[0].right, None, 0.0, np.zeros_like(frames[0].depth))
    out = list(loc.localize_stream([frames[1], bad, frames[2]], errors="yield"))
    assert isinstance(out[1], ConfigError) and "no grid sample has valid depth" in str(out[1])
    assert out[0].estimate == single[1].estimate and out[2].estimate == single[2].estimate
    got = []
    with pytest.raises(ConfigError, match="no grid sample has valid depth"):
        for r in loc.localize_stream([frames[1], bad, frames[2]]):
            got.append(r)
    assert len(got) == 1
    with pytest.raises(ConfigError, match="errors must be 'raise' or 'yield'"):
        list(loc.localize_stream(frames, errors="ignore"))


def test_overlapped_keeps_order_propagates_errors_and_stops_early():
    import threading

    from satloc._threads import overlapped

    workers = set()

    def square(x):
        workers.add(threading.current_thread().name)
        if x == 7:
            raise ValueError("seven")
        return x * x

    assert list(overlapped(square, range(6))) == [0, 1, 4, 9, 16, 25]
    assert workers and all(w.startswith("satloc-overlap") for w in workers)
    assert list(overlapped(square, [])) == []
    with pytest.raises(ValueError, match="seven"):
        list(overlapped(square, range(10)))
    pulled = []
    gen = overlapped(square, (pulled.append(i) or i for i in range(100)))
    assert [next(gen), next(gen)] == [0, 1]
    gen.close()                               # the worker stops: at most one item beyond those taken
    assert len(pulled) <= 3
    workers.clear()
    assert list(overlapped(square, range(3), enabled=False)) == [0, 1, 4] and workers == {threading.current_thread().name}


def test_single_threaded_blas_limits_and_restores():
    from threadpoolctl import threadpool_info

    from satloc._threads import single_threaded_blas

    before = [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]
    assert before  # numpy's BLAS at least
    with single_threaded_blas():
        assert all(i["num_threads"] == 1 for i in threadpool_info() if i["user_api"] == "blas")
        with single_threaded_blas():  # nested (localize inside a stream's consumer): the outer limit stays
            pass
        assert all(i["num_threads"] == 1 for i in threadpool_info() if i["user_api"] == "blas")
    assert [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"] == before
