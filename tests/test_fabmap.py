"""FAB-MAP baseline: the Chow-Liu tree on a hand-checked tiny vocabulary, the observation likelihood against
a brute-force evaluation of the paper's equations, new-place detection and place recognition on rendered
frames, persistence and errors."""
import itertools
import math

import numpy as np
import pytest
import scipy.sparse as sp

from satloc import ConfigError, FormatError
from satloc.baselines import FabMap, FabMapConfig, chow_liu_tree
from satloc.baselines.fabmap import motion_prior
from satloc.persist import load_npz, save_npz

# 9 images x 5 words, hand-written: 0 and 1 mostly co-occur, 2 excludes 0, 3 and 4 weakly dependent; chosen
# so that the maximum-MI spanning tree is unique
OCC = np.array([
    [1, 1, 0, 0, 1],
    [1, 1, 0, 1, 0],
    [0, 0, 1, 1, 0],
    [0, 0, 1, 0, 1],
    [1, 1, 0, 0, 0],
    [0, 1, 1, 1, 0],
    [1, 0, 0, 1, 1],
    [0, 0, 1, 0, 0],
    [0, 0, 0, 1, 0],
], dtype=bool)


def hand_mi(a: np.ndarray, b: np.ndarray) -> float:
    """Mutual information (nats) of two binary columns from their empirical 2x2 table, written out."""
    n = len(a)
    mi = 0.0
    for x in (0, 1):
        for y in (0, 1):
            pxy = np.sum((a == x) & (b == y)) / n
            px, py = np.sum(a == x) / n, np.sum(b == y) / n
            if pxy > 0:
                mi += pxy * math.log(pxy / (px * py))
    return mi


def prufer_trees(v: int):
    """Every labelled spanning tree of v nodes (Prüfer decoding), as sets of (min, max) edges."""
    for seq in itertools.product(range(v), repeat=v - 2):
        degree = [1] * v
        for s in seq:
            degree[s] += 1
        edges = set()
        for s in seq:
            leaf = min(i for i in range(v) if degree[i] == 1)
            edges.add((min(leaf, s), max(leaf, s)))
            degree[leaf] -= 1
            degree[s] -= 1
        u, w = [i for i in range(v) if degree[i] == 1]
        edges.add((u, w))
        yield edges


def test_chow_liu_tree_is_the_maximum_mutual_information_tree():
    v = OCC.shape[1]
    mi = {(i, j): hand_mi(OCC[:, i], OCC[:, j]) for i in range(v) for j in range(i + 1, v)}
    ranked = sorted(((sum(mi[e] for e in t), sorted(t)) for t in prufer_trees(v)), reverse=True)
    assert len(ranked) == v ** (v - 2)
    best_weight, best_edges = ranked[0]
    assert best_weight > ranked[1][0] + 1e-6            # the maximum is unique: the test can tell trees apart

    for root in (None, 3):
        tree = chow_liu_tree(OCC, pseudo_count=0.0, root=root)
        assert tree.edges() == set(best_edges)
        assert tree.root == (int(np.argmax(OCC.sum(0))) if root is None else root)
        assert (tree.parent < 0).sum() == 1
        for q in range(v):                              # every word reaches the root through its parents
            seen, p = 0, q
            while tree.parent[p] >= 0 and seen <= v:
                p, seen = tree.parent[p], seen + 1
            assert p == tree.root
        for q in range(v):
            p = tree.parent[q]
            if p < 0:
                assert tree.mutual_information[q] == 0
                continue
            assert tree.mutual_information[q] == pytest.approx(mi[min(q, p), max(q, p)], abs=1e-12)
            for s in (0, 1):                            # p(z_q = 1 | z_p = s), maximum likelihood
                rows = OCC[:, p] == s
                assert tree.cond[q, s] == pytest.approx(OCC[rows, q].mean(), abs=1e-8)
        assert tree.marginal == pytest.approx(OCC.mean(0), abs=1e-8)


def test_chow_liu_conditionals_with_pseudo_counts():
    a = 1.0
    tree = chow_liu_tree(sp.csr_matrix(OCC), pseudo_count=a)
    n = len(OCC)
    assert tree.marginal == pytest.approx((OCC.sum(0) + a) / (n + 2 * a))
    for q, p in enumerate(tree.parent):
        if p < 0:
            continue
        for s in (0, 1):
            rows = OCC[:, p] == s
            assert tree.cond[q, s] == pytest.approx((OCC[rows, q].sum() + a) / (rows.sum() + 2 * a))


def tiny_fabmap(**kw) -> FabMap:
    """A FabMap on the tiny vocabulary, its places the training images themselves."""
    cfg = FabMapConfig(vocabulary_size=5, max_train_descriptors=5, **kw)
    tree = chow_liu_tree(OCC, pseudo_count=1.0)
    centres = np.random.default_rng(0).normal(size=(5, 128)).astype(np.float32)
    fm = FabMap(cfg, centres, tree, sp.csr_matrix(OCC))
    fm.places = sp.csr_matrix(OCC.astype(np.float32))
    fm.place_poses = np.stack([np.arange(len(OCC)) * 10.0, np.zeros(len(OCC)), np.zeros(len(OCC))], axis=1)
    return fm


def brute_likelihood(tree, z, e_prob, r=0.39, f=0.005) -> float:
    """p(Z | L) = prod_q sum_e p(z_q | e, z_pq) p(e | L), the paper's factors written out word by word.
    ``e_prob[q]`` = p(e_q = 1 | L)."""
    def det(zv, e):                                     # p(z | e)
        p1 = r if e else f
        return p1 if zv else 1 - p1

    total = 1.0
    for q in range(len(z)):
        m = tree.marginal[q]
        pz = lambda zv: m if zv else 1 - m             # noqa: E731
        p = tree.parent[q]
        factor = 0.0
        for e in (0, 1):
            pe = e_prob[q] if e else 1 - e_prob[q]
            if p < 0:
                factor += det(z[q], e) * pe
                continue
            c1 = tree.cond[q, int(z[p])]
            pzp = lambda zv: c1 if zv else 1 - c1      # noqa: E731   p(z_q = zv | z_p)
            alpha = pz(z[q]) * det(not z[q], e) * pzp(not z[q])
            beta = pz(not z[q]) * det(z[q], e) * pzp(z[q])
            factor += beta / (alpha + beta) * pe
        total *= factor
    return total


def place_existence(tree, lz, r=0.39, f=0.005):
    """p(e_q = 1 | L) from the place's single observation lz, prior p(e_q = 1) = marginal p(z_q = 1)."""
    m = tree.marginal
    d1 = np.where(lz, r, 1 - r)
    d0 = np.where(lz, f, 1 - f)
    return d1 * m / (d1 * m + d0 * (1 - m))


def test_observation_likelihood_matches_brute_force_and_is_normalised():
    fm = tiny_fabmap()
    tree = fm.tree
    all_z = [np.array(b, bool) for b in itertools.product((0, 1), repeat=5)]
    for j, lz in enumerate(OCC):
        pe = place_existence(tree, lz)
        total = 0.0
        for z in all_z:
            ll = fm.log_likelihoods(z)
            assert ll[j] == pytest.approx(math.log(brute_likelihood(tree, z, pe)), abs=1e-9)
            total += math.exp(ll[j])
        assert total == pytest.approx(1.0, abs=1e-9)    # the tree factors form a distribution over Z
    # the mean-field new place is the "average place" (p(e) = marginal); the sampled one a mixture of places
    for kind in ("mean_field", "sampled"):
        fm2 = fm.with_config(new_place=kind)
        probs = [math.exp(fm2.new_place_log_likelihood(z)) for z in all_z]
        assert sum(probs) == pytest.approx(1.0, abs=1e-9)
    mf = fm.with_config(new_place="mean_field")
    z = OCC[2]
    assert math.exp(mf.new_place_log_likelihood(z)) == pytest.approx(brute_likelihood(tree, z, tree.marginal))
    sm = fm.with_config(new_place="sampled", new_place_samples=1000)
    want = np.mean([brute_likelihood(tree, z, place_existence(tree, lz)) for lz in OCC])
    assert math.exp(sm.new_place_log_likelihood(z)) == pytest.approx(want)


def test_bayes_update_over_places_and_new_place():
    fm = tiny_fabmap(smoothing=1.0, new_place_prior=0.5)
    z = OCC[5]
    ll = fm.log_likelihoods(z)
    lnew = fm.new_place_log_likelihood(z)
    w = np.concatenate([0.5 / len(OCC) * np.exp(ll), [0.5 * math.exp(lnew)]])
    post = w / w.sum()
    out = fm._answer(z, 7, sequential=False)
    assert out.posterior == pytest.approx(post[:-1] / post[:-1].sum())
    assert out.inlier_score == pytest.approx(1 - post[-1])
    assert out.num_samples == 7 and out.candidates.shape == (len(OCC), 3)
    assert int(np.argmax(out.posterior)) == 5
    # smoothing mixes in the uniform distribution over the n + 1 hypotheses
    sm = fm.with_config(smoothing=0.9)._answer(z, 7, sequential=False)
    assert sm.inlier_score == pytest.approx(1 - (0.9 * post[-1] + 0.1 / (len(OCC) + 1)))
    # the place posterior is p(L | Z, in the map), smoothed over the places: the new-place model leaves it alone
    assert sm.posterior == pytest.approx(0.9 * post[:-1] / post[:-1].sum() + 0.1 / len(OCC))
    assert sm.posterior.sum() == pytest.approx(1.0)
    for kind in ("mean_field", "sampled"):
        assert fm.with_config(smoothing=0.9, new_place=kind)._answer(z, 7, False).posterior == \
            pytest.approx(sm.posterior)


def test_motion_prior_moves_mass_to_adjacent_places():
    belief = np.zeros(7)                                 # 6 places + new place
    belief[2] = 0.8
    belief[6] = 0.2
    prior = motion_prior(belief, window=1)
    assert prior.sum() == pytest.approx(1.0)
    want = np.full(6, 0.2 / 6)
    want[1:4] += 0.8 / 3
    assert prior == pytest.approx(want)
    edge = np.zeros(4)
    edge[0] = 1.0                                        # at the first place: mass stays on the places that exist
    assert motion_prior(edge, window=1) == pytest.approx([0.5, 0.5, 0.0])
    assert motion_prior(belief, window=0) == pytest.approx(belief[:6] + 0.2 / 6)


def test_config_errors():
    with pytest.raises(ConfigError, match="p_false"):
        FabMapConfig(p_false=0.5)
    with pytest.raises(ConfigError, match="vocabulary_size"):
        FabMapConfig(vocabulary_size=1)
    with pytest.raises(ConfigError, match="new_place_prior"):
        FabMapConfig(new_place_prior=1.0)
    with pytest.raises(ConfigError, match="new_place"):
        FabMapConfig(new_place="guess")
    with pytest.raises(ConfigError, match="at least 2 images"):
        chow_liu_tree(OCC[:1])
    fm = tiny_fabmap()
    with pytest.raises(ConfigError, match="build settings"):
        fm.with_config(vocabulary_size=10)
    with pytest.raises(ConfigError, match="expected an occurrence vector of 5 words"):
        fm.log_likelihoods(np.zeros(4, bool))
    with pytest.raises(ConfigError, match="uint8"):
        fm.localize(np.zeros((50, 50, 3), np.float32))
    blank = [np.full((60, 80, 3), 90, np.uint8)] * 3      # no local features at all
    with pytest.raises(ConfigError, match="fewer than vocabulary_size"):
        FabMap.train(blank, FabMapConfig(vocabulary_size=10), progress=False)
    with pytest.raises(ConfigError, match="training image 0"):
        FabMap.train([np.zeros((60, 80), np.int32)] * 3, FabMapConfig(vocabulary_size=10), progress=False)
    empty = tiny_fabmap()
    empty.places = sp.csr_matrix((0, 5), dtype=np.float32)
    empty.place_poses = np.zeros((0, 3))
    with pytest.raises(ConfigError, match="add_places"):
        empty._answer(OCC[0], 1, sequential=False)


def test_save_load_round_trip_and_damage(tmp_path):
    fm = tiny_fabmap(new_place="mean_field")
    p = tmp_path / "fabmap.npz"
    fm.save(p)
    back = FabMap.load(p)
    assert back.config == fm.config
    assert np.array_equal(back.tree.parent, fm.tree.parent) and np.allclose(back.tree.cond, fm.tree.cond)
    assert (back.places != fm.places).nnz == 0 and np.array_equal(back.place_poses, fm.place_poses)
    for z in OCC:
        assert back.log_likelihoods(z) == pytest.approx(fm.log_likelihoods(z))
        assert back.new_place_log_likelihood(z) == pytest.approx(fm.new_place_log_likelihood(z))
    assert not list(tmp_path.glob(".*.tmp*"))           # written atomically, nothing left over

    broken = tmp_path / "broken.npz"
    broken.write_bytes(p.read_bytes()[:200])
    with pytest.raises(FormatError, match="broken.npz"):
        FabMap.load(broken)
    foreign = tmp_path / "foreign.npz"
    save_npz(foreign, "something_else", {"x": np.zeros(3)})
    with pytest.raises(FormatError, match="expected a satloc 'fabmap' file"):
        FabMap.load(foreign)
    arrays, meta = load_npz(p, "fabmap")
    arrays["cond"] = arrays["cond"][:3]
    bad = tmp_path / "bad_shape.npz"
    save_npz(bad, "fabmap", arrays, {k: v for k, v in meta.items() if k not in ("format", "version")})
    with pytest.raises(FormatError, match="'cond' has shape"):
        FabMap.load(bad)
    arrays, _ = load_npz(p, "fabmap")
    arrays["parent"] = np.full(5, -1)
    save_npz(bad, "fabmap", arrays, {k: v for k, v in meta.items() if k not in ("format", "version")})
    with pytest.raises(FormatError, match="not a rooted tree"):
        FabMap.load(bad)


# --- rendered frames -------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """Places: 40 city frames. Training (vocabulary, tree, new-place samples): the first 30 frames of a
    residential drive, disjoint from the places as the paper requires; its last 4 frames are unseen images."""
    from satloc_env.envs.record import PassConfig, RecordConfig, record_passes

    out = tmp_path_factory.mktemp("fabmap")
    city = RecordConfig(scene="city", database=PassConfig(spacing_m=6.0, max_frames=40, depth=False),
                        query=PassConfig(spacing_m=50.0, max_frames=1, depth=False))
    db, _ = record_passes(city, out / "city", progress=False)
    other = RecordConfig(scene="residential", database=PassConfig(spacing_m=6.0, max_frames=34, depth=False),
                         query=PassConfig(spacing_m=50.0, max_frames=1, depth=False))
    res, _ = record_passes(other, out / "residential", progress=False)
    cfg = FabMapConfig(vocabulary_size=300, max_features=600, seed=0)
    fm = FabMap.train([res[i] for i in range(30)], cfg, progress=False)
    assert fm.add_places(db, progress=False) == len(db)
    return fm, db, [res[i] for i in range(30, 34)]


def test_a_database_frame_is_recognised_as_its_place(rendered):
    fm, db, _ = rendered
    for i in (3, 17, 31):
        out = fm.localize(db[i])
        assert int(np.argmax(out.posterior)) == i
        assert out.posterior[i] > 0.9 and out.inlier and out.inlier_score > 0.9
        assert np.hypot(out.estimate.x - db.poses[i, 0], out.estimate.y - db.poses[i, 1]) < 1.0
        assert out.num_samples > 50


def test_new_place_probability_rises_on_unseen_images(rendered):
    """Images of another scene (not among the training images) and noise: the best place's likelihood no longer
    dominates the new place's, and p(new place) rises from the smoothing floor it has on the places' frames."""
    fm, db, unseen_frames = rendered
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 256, size=db[0].left.shape, dtype=np.uint8)

    def margin_and_p_new(img):
        z, _ = fm.observe(img)
        margin = fm.log_likelihoods(z).max() - fm.new_place_log_likelihood(z)
        return margin, 1.0 - fm.localize(img).inlier_score

    seen = [margin_and_p_new(db[i]) for i in range(0, 40, 5)]
    unseen = [margin_and_p_new(f) for f in unseen_frames] + [margin_and_p_new(noise)]
    assert min(m for m, _ in seen) > 2 * max(m for m, _ in unseen)
    p_seen = max(p for _, p in seen)
    p_unseen = float(np.mean([p for _, p in unseen]))
    assert p_seen < 1e-3 and p_unseen > 0.1 and p_unseen > 100 * p_seen


def test_sequential_stream_follows_the_database(rendered):
    fm, db, _ = rendered
    seq = fm.with_config(sequential=True, motion_window=2)
    outs = list(seq.localize_stream(db[i] for i in range(10, 16)))
    assert [int(np.argmax(o.posterior)) for o in outs] == list(range(10, 16))
    assert seq._belief is not None and seq._belief.shape == (fm.num_places + 1,)
