"""satloc.evaluation.metrics on hand-made cases whose answers are worked out by hand below."""
import math

import numpy as np
import pytest

from satloc import ConfigError
from satloc.evaluation.metrics import (
    PRCurve,
    bootstrap_ci,
    error_stats,
    pr_curve,
    precision_recall,
    precision_recall_ci,
    select_threshold,
    worst_case_errors,
)


def test_error_stats_by_hand():
    # errors 0.5, 1.0, 3.0, 20.0 and one failed query (NaN)
    s = error_stats([0.5, 1.0, 3.0, 20.0, float("nan")])
    assert s["count"] == 5 and s["failed"] == 1
    assert s["mean"] == pytest.approx((0.5 + 1.0 + 3.0 + 20.0) / 4)          # 6.125
    # population std: deviations -5.625, -5.125, -3.125, 13.875
    var = (5.625 ** 2 + 5.125 ** 2 + 3.125 ** 2 + 13.875 ** 2) / 4
    assert s["std"] == pytest.approx(math.sqrt(var))
    assert s["median"] == pytest.approx((1.0 + 3.0) / 2)
    assert s["max"] == 20.0
    # within 1 m: 0.5 and 1.0 (<= counts) of all 5 queries, the failed one a miss; within 10 m: three of five
    assert s["within_1m"] == pytest.approx(2 / 5)
    assert s["within_10m"] == pytest.approx(3 / 5)


def test_error_stats_edge_cases():
    s = error_stats([])
    assert s["count"] == 0 and s["failed"] == 0 and math.isnan(s["mean"]) and math.isnan(s["within_1m"])
    s = error_stats([float("nan"), float("inf")])
    assert s["failed"] == 2 and math.isnan(s["median"]) and s["within_10m"] == 0.0
    with pytest.raises(ConfigError, match="errors"):
        error_stats([[1.0, 2.0], [3.0, 4.0]])
    with pytest.raises(ConfigError, match=">= 0"):
        error_stats([1.0, -0.5])
    with pytest.raises(ConfigError, match="errors"):
        error_stats(["a", "b"])


def test_a_failed_query_counts_as_a_gross_failure():
    # the same five queries; the failed one counts with its worst-case error, 100 m
    s = error_stats([0.5, 1.0, 3.0, 20.0, float("nan")], gross_m=[7.0, 7.0, 7.0, 7.0, 100.0])
    assert s["failed"] == 1 and s["failure_rate"] == pytest.approx(0.2)
    assert s["mean"] == pytest.approx((0.5 + 1.0 + 3.0 + 20.0 + 100.0) / 5)
    assert s["median"] == 3.0 and s["max"] == 100.0
    assert s["within_1m"] == pytest.approx(2 / 5) and s["within_10m"] == pytest.approx(3 / 5)   # a miss still
    assert error_stats([2.0, float("nan")], gross_m=50.0)["mean"] == pytest.approx(26.0)       # a scalar
    with pytest.raises(ConfigError, match="gross_m"):
        error_stats([2.0, float("nan")], gross_m=[1.0, float("nan")])


def test_worst_case_errors_are_the_farthest_place():
    places = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0], [5.0, 5.0], [2.0, 3.0]])
    truth = np.array([[0.0, 0.0], [5.0, 5.0], [20.0, 0.0]])
    brute = np.sqrt(((truth[:, None] - places[None]) ** 2).sum(-1)).max(1)
    np.testing.assert_allclose(worst_case_errors(truth, places), brute)
    line = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.0], [4.0, 0.0]])   # collinear: no hull
    np.testing.assert_allclose(worst_case_errors([[0.0, 1.0]], line), [math.hypot(4, 1)])


def test_bootstrap_intervals():
    rng = np.random.default_rng(3)
    x = rng.normal(10.0, 2.0, 400)
    lo, hi = bootstrap_ci(x, seed=1)
    # the normal-theory interval of the mean: mean +- 1.96 s / sqrt(n)
    half = 1.96 * x.std() / math.sqrt(len(x))
    assert lo == pytest.approx(x.mean() - half, abs=0.05) and hi == pytest.approx(x.mean() + half, abs=0.05)
    assert bootstrap_ci(x, seed=1) == (lo, hi)                                  # seeded
    assert bootstrap_ci([5.0, 5.0, 5.0]) == (5.0, 5.0)
    assert all(math.isnan(v) for v in bootstrap_ci([]))
    lo_m, hi_m = bootstrap_ci(x, np.median)
    assert lo_m < np.median(x) < hi_m
    with pytest.raises(ConfigError, match="level"):
        bootstrap_ci(x, level=1.5)


def test_precision_recall_intervals_contain_the_estimate():
    rng = np.random.default_rng(0)
    n = 300
    inside = rng.random(n) < 0.7
    err = np.where(rng.random(n) < 0.8, 1.0, 50.0)
    score = np.where(inside, rng.normal(1.0, 0.5, n), rng.normal(0.0, 0.5, n))
    pr = precision_recall(err, score, 0.5, inside)
    ci = precision_recall_ci(err, score, 0.5, inside, seed=2)
    assert ci["precision_ci"][0] < pr["precision"] < ci["precision_ci"][1]
    assert ci["recall_ci"][0] < pr["recall"] < ci["recall_ci"][1]
    assert 0.02 < ci["recall_ci"][1] - ci["recall_ci"][0] < 0.2     # about 2 x 1.96 x sqrt(r(1-r)/n)


# six queries: four taken inside the map, two outside
ERR = np.array([0.4, 2.0, 30.0, 5.0, 50.0, 80.0])
SCORE = np.array([9.0, 7.0, 6.0, 2.0, 8.0, 1.0])
INSIDE = np.array([True, True, True, True, False, False])


def test_precision_recall_by_hand():
    # threshold 5: declared inside q0 (9), q1 (7), q2 (6), q4 (8) -> 4 declared.
    # true positives: declared, inside, within 10 m -> q0 and q1 (q2 is 30 m off, q4 is outside): TP = 2.
    # precision 2 / 4; recall = TP / truly inside (4 queries) = 2 / 4
    r = precision_recall(ERR, SCORE, 5.0, INSIDE)
    assert (r["tp"], r["declared"], r["positives"]) == (2, 4, 4)
    assert r["precision"] == pytest.approx(0.5) and r["recall"] == pytest.approx(0.5)
    assert r["f1"] == pytest.approx(0.5)
    # threshold 1.5: also q3 (2.0, inside, 5 m) -> TP 3 of 5 declared; recall 3 / 4
    r = precision_recall(ERR, SCORE, 1.5, INSIDE)
    assert (r["tp"], r["declared"]) == (3, 5)
    assert r["precision"] == pytest.approx(3 / 5) and r["recall"] == pytest.approx(3 / 4)
    # radius 1 m: only q0 counts
    r = precision_recall(ERR, SCORE, 1.5, INSIDE, radius_m=1.0)
    assert r["tp"] == 1
    # a threshold above every score declares nothing: precision undefined, recall 0
    r = precision_recall(ERR, SCORE, 100.0, INSIDE)
    assert r["declared"] == 0 and math.isnan(r["precision"]) and r["recall"] == 0.0
    # inside omitted: every query counts as inside -> 6 positives
    assert precision_recall(ERR, SCORE, 5.0)["positives"] == 6


def test_outside_queries_are_never_positives():
    # q4 (outside) localized "within 10 m" of its true pose still is no true positive
    err = ERR.copy()
    err[4] = 1.0
    r = precision_recall(err, SCORE, 7.5, INSIDE)   # declared: q0 (9), q4 (8)
    assert (r["tp"], r["declared"]) == (1, 2)
    assert r["precision"] == pytest.approx(0.5) and r["recall"] == pytest.approx(1 / 4)


def test_nan_scores_and_errors():
    # a NaN score is never declared inside; a NaN error is never within the radius
    r = precision_recall([1.0, float("nan"), 1.0], [float("nan"), 5.0, 5.0], 0.0, [True, True, True])
    assert (r["tp"], r["declared"], r["positives"]) == (1, 2, 3)


def test_pr_curve_by_hand():
    c = pr_curve(ERR, SCORE, INSIDE)
    # distinct thresholds, highest first: 9 8 7 6 2 1
    np.testing.assert_array_equal(c.thresholds, [9, 8, 7, 6, 2, 1])
    # declared:          1  2  3  4  5  6
    # TP (q0 q1 q3 good): 1  1  2  2  3  3
    np.testing.assert_array_equal(c.declared, [1, 2, 3, 4, 5, 6])
    np.testing.assert_array_equal(c.tp, [1, 1, 2, 2, 3, 3])
    np.testing.assert_allclose(c.precision, [1, 1 / 2, 2 / 3, 2 / 4, 3 / 5, 3 / 6])
    np.testing.assert_allclose(c.recall, [1 / 4, 1 / 4, 2 / 4, 2 / 4, 3 / 4, 3 / 4])
    # F1 = 2PR / (P + R)
    f1 = [2 * p * r / (p + r) for p, r in zip(c.precision, c.recall)]
    np.testing.assert_allclose(c.f1, f1)
    assert c.positives == 4 and len(c) == 6
    # the curve agrees with precision_recall at every threshold
    for t, p, r in zip(c.thresholds, c.precision, c.recall):
        one = precision_recall(ERR, SCORE, t, INSIDE)
        assert one["precision"] == pytest.approx(p) and one["recall"] == pytest.approx(r)


def test_pr_curve_ties_and_nan():
    # two queries share score 5: both declared at threshold 5 (one step on the curve)
    c = pr_curve([1.0, 20.0, 1.0, 1.0], [5.0, 5.0, 3.0, float("nan")], [True] * 4)
    np.testing.assert_array_equal(c.thresholds, [5.0, 3.0])
    np.testing.assert_array_equal(c.declared, [2, 3])
    np.testing.assert_array_equal(c.tp, [1, 2])
    np.testing.assert_allclose(c.recall, [1 / 4, 2 / 4])   # the NaN-score query still counts as a positive
    with pytest.raises(ConfigError, match="one value per query"):
        pr_curve([1.0, 2.0], [1.0], [True, True])
    with pytest.raises(ConfigError, match="boolean"):
        pr_curve([1.0], [1.0], [1])
    with pytest.raises(ConfigError, match="radius_m"):
        pr_curve([1.0], [1.0], [True], radius_m=0)


def test_select_threshold_max_f1_by_hand():
    c = pr_curve(ERR, SCORE, INSIDE)
    # F1 along the curve: t=9: P 1, R .25 -> .4; t=8: .5,.25 -> 1/3; t=7: 2/3,1/2 -> 4/7 (.571);
    # t=6: .5,.5 -> .5; t=2: .6,.75 -> 2/3 (.667); t=1: .5,.75 -> .6.  Best: threshold 2.
    s = select_threshold(c, "max_f1")
    assert s["threshold"] == 2.0 and s["rule"] == "max_f1"
    assert s["precision"] == pytest.approx(0.6) and s["recall"] == pytest.approx(0.75)
    assert s["f1"] == pytest.approx(2 / 3)


def test_select_threshold_recall_at_precision_by_hand():
    c = pr_curve(ERR, SCORE, INSIDE)
    # precision >= 0.6 at t = 9 (1.0), 7 (2/3), 2 (0.6); highest recall among them: t=2 (0.75)
    s = select_threshold(c, "recall_at_precision", min_precision=0.6)
    assert s["threshold"] == 2.0 and s["recall"] == pytest.approx(0.75)
    # precision >= 0.65: t = 9 (R .25) and 7 (R .5) -> 7
    s = select_threshold(c, "recall_at_precision", min_precision=0.65)
    assert s["threshold"] == 7.0 and s["precision"] == pytest.approx(2 / 3) and s["recall"] == pytest.approx(0.5)
    # precision 1.0: only t = 9
    assert select_threshold(c, "recall_at_precision", min_precision=1.0)["threshold"] == 9.0


def test_select_threshold_ties_and_unreachable():
    # recall ties: t=8 and t=9 both have recall 1/4 at precision >= 0.5 -> the higher precision (t=9, P 1.0)
    c = pr_curve(ERR, SCORE, INSIDE)
    c2 = PRCurve(c.thresholds[:2], c.precision[:2], c.recall[:2], c.f1[:2], c.tp[:2], c.declared[:2],
                 c.positives, c.radius_m)
    assert select_threshold(c2, "recall_at_precision", min_precision=0.5)["threshold"] == 9.0
    # equal F1 and precision: the higher threshold wins
    c3 = PRCurve(np.array([3.0, 2.0]), np.array([0.5, 0.5]), np.array([0.5, 0.5]), np.array([0.5, 0.5]),
                 np.array([1, 1]), np.array([2, 2]), 2, 10.0)
    assert select_threshold(c3)["threshold"] == 3.0
    # no threshold reaches the precision: declare nothing
    bad = pr_curve([50.0, 50.0], [2.0, 1.0], [True, True])
    s = select_threshold(bad, "recall_at_precision", min_precision=0.5)
    assert s["threshold"] == math.inf and s["recall"] == 0.0 and math.isnan(s["precision"])
    empty = pr_curve([1.0], [float("nan")], [True])
    assert len(empty) == 0 and select_threshold(empty)["threshold"] == math.inf
    with pytest.raises(ConfigError, match="rule"):
        select_threshold(c, "best")
    with pytest.raises(ConfigError, match="min_precision"):
        select_threshold(c, "recall_at_precision", min_precision=90)


def _ar1(n, rho, rng):
    x = np.zeros(n)
    e = rng.standard_normal(n)
    for i in range(1, n):
        x[i] = rho * x[i - 1] + e[i]
    return x


def test_block_bootstrap_widens_intervals_of_a_persistent_sequence_and_covers():
    from satloc.evaluation.metrics import bootstrap_ci, stationary_block_length

    rng = np.random.default_rng(5)
    x = _ar1(300, 0.9, rng)
    white = rng.standard_normal(300)
    assert stationary_block_length(x) > 5 and stationary_block_length(white) < 4
    w = lambda ci: ci[1] - ci[0]  # noqa: E731
    assert w(bootstrap_ci(x, method="stationary")) > 1.8 * w(bootstrap_ci(x))
    assert 0.7 < w(bootstrap_ci(white, method="stationary")) / w(bootstrap_ci(white)) < 1.4
    # coverage of the true mean (0) over 100 persistent sequences (rho 0.8, 200 queries): resampling single
    # queries covers it 41 times of 100, blocks 80 (still below the nominal 95 at this length and persistence)
    cover = {"iid": 0, "stationary": 0}
    for k in range(100):
        s = _ar1(200, 0.8, np.random.default_rng(100 + k))
        for m in cover:
            lo, hi = bootstrap_ci(s, n_boot=400, seed=k, method=m)
            cover[m] += lo <= 0.0 <= hi
    assert cover["iid"] < 60 and cover["stationary"] >= 75, cover


def test_block_bootstrap_is_seeded_and_checks_its_arguments():
    from satloc.evaluation.metrics import bootstrap_ci, bootstrap_indices, ci_method

    x = _ar1(120, 0.7, np.random.default_rng(1))
    assert bootstrap_ci(x, method="stationary", seed=3) == bootstrap_ci(x, method="stationary", seed=3)
    assert bootstrap_ci(x, method="stationary", seed=3) != bootstrap_ci(x, method="stationary", seed=4)
    idx = bootstrap_indices(50, 10, 0, "stationary", 5.0)
    assert idx.shape == (10, 50) and idx.min() >= 0 and idx.max() < 50
    runs = np.mean(np.diff(idx, axis=1) % 50 == 1)   # consecutive indices: blocks of mean length 5
    assert 0.7 < runs < 0.9
    with pytest.raises(ConfigError, match="method"):
        bootstrap_ci(x, method="blocks")
    with pytest.raises(ConfigError, match="block_length"):
        bootstrap_ci(x, method="stationary", block_length=0.5)
    assert "stationary block bootstrap" in ci_method("stationary", 6.25) and "6.2" in ci_method("stationary", 6.25)
    assert "one by one" in ci_method("iid")
    assert bootstrap_ci(np.ones(30), method="stationary") == (1.0, 1.0)   # constant: block length 1


def test_paired_bootstrap_cancels_what_the_queries_share():
    from satloc.evaluation.metrics import bootstrap_ci, paired_bootstrap_ci

    rng = np.random.default_rng(2)
    hard = np.abs(_ar1(300, 0.9, rng)) * 5          # how hard each query is: shared by both methods
    a = hard + 0.3 + 0.2 * rng.standard_normal(300)
    b = hard + 0.2 * rng.standard_normal(300)
    lo, hi = paired_bootstrap_ci(a, b)
    assert lo < 0.3 < hi and lo > 0                 # the paired difference is resolved
    la, ha = bootstrap_ci(a, method="stationary")
    lb, hb = bootstrap_ci(b, method="stationary")
    assert la < hb                                  # the two separate intervals overlap
    with pytest.raises(ConfigError, match="one value per query"):
        paired_bootstrap_ci(a, b[:-1])


def test_joined_passes_are_resampled_each_within_itself():
    """Two passes laid end to end (inside, then outside the map): the step of "truly inside" between them
    does not set the block length, no block runs across, and each pass keeps its size in every resample."""
    from satloc.evaluation.metrics import ci_method, grouped_bootstrap_indices, precision_recall_ci

    rng = np.random.default_rng(4)
    n_in, n_out = 150, 100
    errors = np.where(rng.random(n_in + n_out) < 0.8, 2.0, 50.0)     # independent queries
    scores = rng.random(n_in + n_out)
    inside = np.r_[np.ones(n_in, bool), np.zeros(n_out, bool)]
    ci = precision_recall_ci(errors, scores, 0.3, inside, method="stationary", groups=[n_in, n_out])
    assert len(ci["block_length"]) == 2 and max(ci["block_length"]) < 5
    assert "within each pass" in ci_method("stationary", ci["block_length"])
    iid = precision_recall_ci(errors, scores, 0.3, inside)
    width = lambda c: c[1] - c[0]  # noqa: E731
    assert width(ci["precision_ci"]) < 1.5 * width(iid["precision_ci"])
    idx = grouped_bootstrap_indices([n_in, n_out], 50, 0, "stationary", [4.0, 4.0])
    assert np.all(idx[:, :n_in] < n_in) and np.all(idx[:, n_in:] >= n_in)
    with pytest.raises(ConfigError, match="groups"):
        precision_recall_ci(errors, scores, 0.3, inside, method="stationary", groups=[n_in, n_out + 1])
