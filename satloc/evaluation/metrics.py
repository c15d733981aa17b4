"""Evaluation metrics shared by every method and baseline: error statistics and inside/outside-the-map
precision and recall. Pure numpy, no satloc state.

Errors are planar distances in metres from a method's estimate to the query's true position, one per query.
A query a method could not answer (no result at all) has error NaN. **One rule for every method:** such a
query is a gross failure. It counts in ``count``, ``failed`` and ``failure_rate``, is never "within" any
radius (within X m means error <= X, everywhere), and, when the caller gives ``gross_m`` (the tables do:
:func:`worst_case_errors`, the distance from the query's true position to the farthest place of the map, the
worst answer a method could have given), takes that error in the mean, std, median and max. Without
``gross_m`` the failures are left out of those four (what a single localization stage reports about its own
answers).

**Confidence intervals.** :func:`bootstrap_ci` gives a percentile bootstrap interval of any statistic over
the queries (seeded); :func:`precision_recall_ci` of precision and recall at a fixed threshold;
:func:`paired_bootstrap_ci` of the difference of a statistic between two methods on the same queries. With
``method="iid"`` the queries are resampled one by one, which assumes they are independent. Queries along a
sequence are not: a tracked error persists for tens of frames and single-image failures cluster on
look-alike blocks. ``method="stationary"`` resamples blocks (Politis and Romano's stationary bootstrap,
from ``arch``) of random length with mean ``block_length``, by default chosen from the data
(:func:`stationary_block_length`: Politis and White 2004, with Patton, Politis and White's 2009 correction);
:func:`ci_method` names what an interval is, for the tables' ``ci_method`` column.

Outside-the-map detection (the paper's Table II). Every method gives each query an inlier score (higher: more
sure the query lies inside the mapped area). With a threshold ``t``:

* a query is **declared inside** when its score >= t (a NaN score is never declared inside);
* a **true positive** is a query that is declared inside, truly inside the map (``inside``) *and* localized
  within ``radius_m`` (10 m in the paper) of its true position;
* **precision** = TP / (queries declared inside);
* **recall** = TP / (queries truly inside the map). Queries taken outside the mapped area are never positives:
  declaring one inside only costs precision.

Precision is undefined (NaN) when nothing is declared inside, recall when no query is inside.

Choosing the threshold. The paper reports one precision/recall pair per method, each at a threshold picked
from that method's precision-recall curve. :func:`select_threshold` implements two stated rules:

* ``"max_f1"`` (default): the threshold maximising F1 = 2PR / (P + R), parameter-free;
* ``"recall_at_precision"``: the highest recall among thresholds with precision >= ``min_precision``.

Which rule the paper used could not be read from its text here (only its abstract was reachable); its
Table II figures (precision/recall 90.2/86.6 % for the method, 89.4/43.6 % for EFM, 49.3/61.6 % for FAB-MAP)
put two of three methods at about 90 % precision, which fits an operating point near 90 % precision better
than maximal F1, but FAB-MAP's 49 % shows it was not a hard precision floor for every method. Treat the rule
as this project's choice, stated with every table.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ..errors import ConfigError


def _vector(x, name: str, dtype=np.float64) -> np.ndarray:
    try:
        a = np.asarray(x, dtype=dtype)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{name}: expected a 1-D array of numbers ({e})") from e
    if a.ndim != 1:
        raise ConfigError(f"{name}: expected a 1-D array, got shape {np.shape(x)}")
    return a


def worst_case_errors(truth_xy, map_xy) -> np.ndarray:
    """(Q,) for each query, the distance (metres) from its true position ``truth_xy`` (Q, 2) to the farthest of
    the map's places ``map_xy`` (P, 2) (e.g. the database poses): the error of the worst answer on the map, the
    error a failed query counts with (:func:`error_stats`' ``gross_m``). NaN where the truth is unknown."""
    t = np.asarray(truth_xy, np.float64).reshape(-1, 2)
    m = np.asarray(map_xy, np.float64).reshape(-1, 2)
    m = m[np.all(np.isfinite(m), axis=1)]
    if not len(m):
        raise ConfigError("map_xy: no finite place")
    from scipy.spatial import ConvexHull, QhullError

    try:   # the farthest point of a set is one of its convex hull's vertices
        m = m[ConvexHull(m).vertices] if len(m) > 3 else m
    except QhullError:   # collinear or repeated places: all of them
        pass
    return np.sqrt(((t[:, None, :] - m[None, :, :]) ** 2).sum(-1)).max(axis=1)


def error_stats(errors, gross_m=None) -> dict:
    """Statistics of per-query errors (metres):

    ``count`` (all queries), ``failed`` (NaN or infinite errors: queries not answered) and ``failure_rate``;
    ``mean``, ``std`` (population, ddof 0), ``median``, ``max``: over every query, a failed one counting with
    its ``gross_m`` (a scalar or one value per query, see the module docstring), else over the answered ones
    (NaN when there is none); ``within_1m`` and ``within_10m``: the fraction of *all* queries (failed ones
    included, as misses) with error <= 1 m / 10 m (NaN with no query).
    """
    e = _vector(errors, "errors")
    finite = np.isfinite(e)
    n = int(e.size)
    nan = float("nan")
    if np.any(e[finite] < 0):
        raise ConfigError(f"errors: distances must be >= 0, got {float(e[finite].min())}")
    if gross_m is not None:
        g = np.broadcast_to(np.asarray(gross_m, np.float64), e.shape)
        if not np.all(np.isfinite(g[~finite])):
            raise ConfigError("gross_m: expected a finite error for every failed query")
        ok = np.where(finite, e, g)
    else:
        ok = e[finite]
    return {
        "count": n,
        "failed": int(n - finite.sum()),
        "failure_rate": float((n - finite.sum()) / n) if n else nan,
        "mean": float(ok.mean()) if ok.size else nan,
        "std": float(ok.std()) if ok.size else nan,
        "median": float(np.median(ok)) if ok.size else nan,
        "max": float(ok.max()) if ok.size else nan,
        "within_1m": float(np.sum(e[finite] <= 1.0) / n) if n else nan,
        "within_10m": float(np.sum(e[finite] <= 10.0) / n) if n else nan,
    }


def pose_errors(estimates, truth) -> dict:
    """Per-query error components of (N, 3) ``estimates`` (x, y, yaw; NaN rows: not answered) against (N, 3)
    ``truth``: ``error`` (planar distance, m), ``lateral`` and ``longitudinal`` (its absolute components across
    and along the true heading, m) and ``heading_deg`` (absolute heading error); NaN where not answered."""
    e = np.asarray(estimates, np.float64).reshape(-1, 3)
    t = np.asarray(truth, np.float64).reshape(-1, 3)
    if e.shape != t.shape:
        raise ConfigError(f"pose_errors: {len(e)} estimates against {len(t)} true poses")
    dx, dy = e[:, 0] - t[:, 0], e[:, 1] - t[:, 1]
    c, s = np.cos(t[:, 2]), np.sin(t[:, 2])
    dyaw = np.remainder(e[:, 2] - t[:, 2] + np.pi, 2 * np.pi) - np.pi
    return {"error": np.hypot(dx, dy), "lateral": np.abs(-s * dx + c * dy), "longitudinal": np.abs(c * dx + s * dy),
            "heading_deg": np.degrees(np.abs(dyaw))}


def recall_within(values, radius: float) -> float:
    """The fraction of all queries with ``values`` <= ``radius`` (NaN, a query not answered, is a miss)."""
    v = _vector(values, "values")
    return float(np.sum(np.isfinite(v) & (v <= radius)) / v.size) if v.size else float("nan")


CIMethod = Literal["iid", "stationary"]


def stationary_block_length(values) -> float:
    """The stationary bootstrap's mean block length for ``values`` (a sequence in its order), chosen from its
    autocorrelation by Politis and White's rule (``arch.bootstrap.optimal_block_length``); at least 1 and at
    most the series' length; 1 for a series too short or too constant to estimate it."""
    from arch.bootstrap import optimal_block_length

    v = _vector(values, "values")
    v = v[np.isfinite(v)]
    if v.size < 8 or float(np.std(v)) == 0.0:
        return 1.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        b = float(optimal_block_length(v)["stationary"].iloc[0])
    return float(min(max(b, 1.0), v.size)) if np.isfinite(b) else 1.0


def ci_method(method: CIMethod, block_length=None, level: float = 0.95) -> str:
    """How an interval was made, as the tables' ``ci_method`` column says it (no comma: a plain CSV cell)."""
    if method == "iid":
        return f"percentile bootstrap {level:.0%}; queries resampled one by one"
    if block_length is None:
        return f"stationary block bootstrap {level:.0%}; no query"
    if isinstance(block_length, (list, tuple)):
        each = " / ".join(f"{b:.1f}" for b in block_length)
        return f"stationary block bootstrap {level:.0%} within each pass; mean blocks {each} queries (Politis-White)"
    return f"stationary block bootstrap {level:.0%}; mean block {block_length:.1f} queries (Politis-White)"


def bootstrap_indices(n: int, n_boot: int, seed: int, method: CIMethod = "iid",
                      block_length: float | None = None) -> np.ndarray:
    """(n_boot, n) resampled indices of ``n`` queries: one by one (``"iid"``) or in stationary-bootstrap
    blocks of mean length ``block_length`` (``"stationary"``; wrapping around the end)."""
    return grouped_bootstrap_indices([n], n_boot, seed, method, [block_length])


def grouped_bootstrap_indices(sizes, n_boot: int, seed: int, method: CIMethod, block_lengths) -> np.ndarray:
    """(n_boot, sum(sizes)) resampled indices of sequences laid end to end (e.g. several passes joined):
    each sequence resampled within itself, with its own block length, so that no block runs from one
    sequence into the next and each keeps its size."""
    if method not in ("iid", "stationary"):
        raise ConfigError(f"bootstrap: method: expected 'iid' or 'stationary', got {method!r}")
    rng = np.random.default_rng(seed)
    out, start = [], 0
    for n, b in zip(sizes, block_lengths):
        out.append(start + _indices(int(n), n_boot, rng, method, b))
        start += int(n)
    return np.concatenate(out, axis=1) if out else np.zeros((n_boot, 0), np.int64)


def _indices(n: int, n_boot: int, rng: np.random.Generator, method: CIMethod, block_length) -> np.ndarray:
    if method == "iid" or n < 2:
        return rng.integers(0, n, (n_boot, n))
    from arch.bootstrap import StationaryBootstrap

    if block_length is None or not (np.isfinite(block_length) and block_length >= 1):
        raise ConfigError(f"bootstrap: block_length: expected a number >= 1, got {block_length!r}")
    bs = StationaryBootstrap(float(block_length), np.arange(n), seed=rng)
    return np.stack([pos[0] for pos, _ in bs.bootstrap(n_boot)])


def bootstrap_ci(values, statistic=np.mean, n_boot: int = 2000, level: float = 0.95, seed: int = 0,
                 method: CIMethod = "iid", block_length: float | None = None) -> tuple[float, float]:
    """Percentile bootstrap interval (low, high) at ``level`` of ``statistic`` over ``values`` (one per query,
    in sequence order; resampled ``n_boot`` times, seeded); (NaN, NaN) for no value. ``statistic`` takes a
    (n_boot, n) array and an ``axis=1`` keyword (numpy's mean, median, ...). ``method``: ``"iid"`` resamples
    queries one by one, ``"stationary"`` in blocks of mean ``block_length`` (None: from the data,
    :func:`stationary_block_length`)."""
    v = _vector(values, "values")
    _check_level(level, n_boot)
    if v.size == 0:
        return float("nan"), float("nan")
    if method == "stationary" and block_length is None:
        block_length = stationary_block_length(v)
    idx = bootstrap_indices(v.size, n_boot, seed, method, block_length)
    return _percentiles(statistic(v[idx], axis=1), level)


def paired_bootstrap_ci(a, b, statistic=np.mean, n_boot: int = 2000, level: float = 0.95, seed: int = 0,
                        method: CIMethod = "stationary", block_length: float | None = None
                        ) -> tuple[float, float]:
    """Interval of ``statistic(a) - statistic(b)`` for two methods on the same queries (``a[i]`` and ``b[i]``
    of query i, in sequence order): both resampled with the same indices, so what the queries share cancels.
    ``block_length`` None: from the per-query differences."""
    x, y = _vector(a, "a"), _vector(b, "b")
    if x.shape != y.shape:
        raise ConfigError(f"paired bootstrap: a and b must have one value per query each, got {x.size} and {y.size}")
    _check_level(level, n_boot)
    if x.size == 0:
        return float("nan"), float("nan")
    if method == "stationary" and block_length is None:
        block_length = stationary_block_length(x - y)
    idx = bootstrap_indices(x.size, n_boot, seed, method, block_length)
    return _percentiles(statistic(x[idx], axis=1) - statistic(y[idx], axis=1), level)


def _check_level(level: float, n_boot: int) -> None:
    if not 0 < level < 1 or n_boot < 1:
        raise ConfigError(f"bootstrap: expected 0 < level < 1 and n_boot >= 1, got {level}, {n_boot}")


def _percentiles(stats: np.ndarray, level: float) -> tuple[float, float]:
    """The central ``level`` interval of bootstrap statistics."""
    a = (1 - level) / 2
    return float(np.quantile(stats, a)), float(np.quantile(stats, 1 - a))


def _inputs(errors, scores, inside) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    e = _vector(errors, "errors")
    s = _vector(scores, "scores")
    ins = np.ones(e.shape, bool) if inside is None else np.asarray(inside)
    if ins.dtype != bool:
        raise ConfigError(f"inside: expected a boolean array, got dtype {ins.dtype}")
    ins = ins.reshape(-1)
    if not (e.shape == s.shape == ins.shape):
        raise ConfigError(f"errors, scores and inside must have one value per query; got lengths {e.size}, "
                          f"{s.size} and {ins.size}")
    return e, s, ins


def _f1(p: np.ndarray, r: np.ndarray) -> np.ndarray:
    p, r = np.nan_to_num(p), np.nan_to_num(r)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(p + r > 0, 2 * p * r / np.where(p + r > 0, p + r, 1.0), 0.0)


def precision_recall(errors, scores, threshold: float, inside=None, radius_m: float = 10.0) -> dict:
    """Precision and recall at one threshold (see the module docstring for the definitions).

    ``inside``: boolean per query, True when the query was taken inside the mapped area (None: all inside).
    Returns ``precision``, ``recall``, ``f1``, ``tp``, ``declared`` (queries declared inside), ``positives``
    (queries truly inside), ``threshold`` and ``radius_m``."""
    if radius_m <= 0:
        raise ConfigError(f"radius_m: expected > 0, got {radius_m}")
    e, s, ins = _inputs(errors, scores, inside)
    with np.errstate(invalid="ignore"):
        declared = s >= threshold          # NaN scores compare False
        close = e <= radius_m              # NaN errors compare False
    tp = int(np.sum(declared & ins & close))
    nd, npos = int(declared.sum()), int(ins.sum())
    p = tp / nd if nd else float("nan")
    r = tp / npos if npos else float("nan")
    return {"precision": p, "recall": r, "f1": float(_f1(np.array(p), np.array(r))), "tp": tp,
            "declared": nd, "positives": npos, "threshold": float(threshold), "radius_m": float(radius_m)}


def precision_recall_ci(errors, scores, threshold: float, inside=None, radius_m: float = 10.0,
                        n_boot: int = 2000, level: float = 0.95, seed: int = 0, method: CIMethod = "iid",
                        block_length: float | None = None, groups=None) -> dict:
    """Percentile bootstrap intervals of precision and recall at a fixed ``threshold`` (queries resampled,
    seeded; a resample where one is undefined is left out of its interval): ``precision_ci`` and
    ``recall_ci``, each (low, high), and ``block_length`` (None for ``"iid"``). ``method="stationary"``
    resamples blocks of queries; ``block_length`` None: the longer of what :func:`stationary_block_length`
    gives for the declared and the true-positive indicators (not for "truly inside", which steps once between
    passes). ``groups``: the sizes of sequences laid end to end (passes joined), each resampled within
    itself with its own block length (``block_length`` is then their list)."""
    e, s, ins = _inputs(errors, scores, inside)
    with np.errstate(invalid="ignore"):
        declared = s >= threshold
        good = declared & ins & (e <= radius_m)
    if e.size == 0:
        return {"precision_ci": (float("nan"),) * 2, "recall_ci": (float("nan"),) * 2, "block_length": None}

    def blocks(sl):
        return max(stationary_block_length(x[sl].astype(np.float64)) for x in (declared, good))

    sizes = [e.size] if groups is None else [int(g) for g in groups]
    if sum(sizes) != e.size or min(sizes, default=1) < 1:
        raise ConfigError(f"precision_recall_ci: groups: expected sizes >= 1 adding up to {e.size}, got {sizes}")
    bounds = np.cumsum([0] + sizes)
    if method == "stationary" and block_length is None:
        lengths = [blocks(slice(a, b)) for a, b in zip(bounds[:-1], bounds[1:])]
        block_length = lengths if groups is not None else lengths[0]
    else:
        lengths = block_length if isinstance(block_length, (list, tuple)) else [block_length] * len(sizes)
    idx = grouped_bootstrap_indices(sizes, n_boot, seed, method, lengths)
    tp, nd, npos = good[idx].sum(1), declared[idx].sum(1), ins[idx].sum(1)

    def ci(num, den):
        ok = den > 0
        return _percentiles(num[ok] / den[ok], level) if ok.any() else (float("nan"), float("nan"))

    return {"precision_ci": ci(tp, nd), "recall_ci": ci(tp, npos),
            "block_length": block_length if method == "stationary" else None}


@dataclass
class PRCurve:
    """Precision and recall at every distinct threshold, highest threshold first.

    ``thresholds[i]`` is a score some query has; at it, the queries with score >= thresholds[i] are declared
    inside. ``declared`` and ``tp`` therefore never decrease along the curve, nor does ``recall``."""

    thresholds: np.ndarray    # (T,) descending
    precision: np.ndarray     # (T,)
    recall: np.ndarray        # (T,) NaN everywhere when no query is inside
    f1: np.ndarray            # (T,)
    tp: np.ndarray            # (T,) int
    declared: np.ndarray      # (T,) int
    positives: int            # queries truly inside the map
    radius_m: float

    def __len__(self) -> int:
        return len(self.thresholds)

    def to_dict(self) -> dict:
        return {"thresholds": self.thresholds.tolist(), "precision": self.precision.tolist(),
                "recall": self.recall.tolist(), "f1": self.f1.tolist(), "tp": self.tp.tolist(),
                "declared": self.declared.tolist(), "positives": self.positives, "radius_m": self.radius_m}


def pr_curve(errors, scores, inside=None, radius_m: float = 10.0) -> PRCurve:
    """Precision and recall for every threshold that changes the answer (each distinct finite score), as
    :func:`precision_recall` would give them one by one. Queries with a NaN score are never declared inside;
    a score of +inf is (at every threshold)."""
    if radius_m <= 0:
        raise ConfigError(f"radius_m: expected > 0, got {radius_m}")
    e, s, ins = _inputs(errors, scores, inside)
    with np.errstate(invalid="ignore"):
        good = (ins & (e <= radius_m)).astype(np.int64)
    valid = ~np.isnan(s)
    sv, gv = s[valid], good[valid]
    order = np.argsort(-sv, kind="stable")
    sv, gv = sv[order], gv[order]
    thresholds = np.unique(sv[np.isfinite(sv)])[::-1]
    # queries declared at threshold t: those with score >= t, i.e. the first `count` of the descending order
    count = np.searchsorted(-sv, -thresholds, side="right")
    ctp = np.concatenate([[0], np.cumsum(gv)])
    tp = ctp[count]
    declared = count.astype(np.int64)
    npos = int(ins.sum())
    with np.errstate(invalid="ignore", divide="ignore"):
        precision = np.where(declared > 0, tp / np.maximum(declared, 1), np.nan)
        recall = tp / npos if npos else np.full(len(tp), np.nan)
    return PRCurve(thresholds.astype(np.float64), precision.astype(np.float64), np.asarray(recall, np.float64),
                   _f1(precision, np.asarray(recall)), tp.astype(np.int64), declared, npos, float(radius_m))


def select_threshold(curve: PRCurve, rule: Literal["max_f1", "recall_at_precision"] = "max_f1",
                     min_precision: float = 0.9) -> dict:
    """The operating point picked from a PR curve by a stated ``rule`` (see the module docstring):

    * ``"max_f1"``: the largest F1; ties go to the higher precision, then the higher threshold;
    * ``"recall_at_precision"``: among thresholds with precision >= ``min_precision``, the highest recall;
      ties go to the higher precision, then the higher threshold. When no threshold reaches ``min_precision``
      the answer is to declare nothing inside: threshold +inf, precision NaN, recall 0.

    Returns ``threshold``, ``precision``, ``recall``, ``f1`` and ``rule``. An empty curve (no finite score)
    gives threshold +inf, recall 0."""
    if rule not in ("max_f1", "recall_at_precision"):
        raise ConfigError(f"rule: expected 'max_f1' or 'recall_at_precision', got {rule!r}")
    if not 0.0 <= min_precision <= 1.0:
        raise ConfigError(f"min_precision: expected a fraction in [0, 1], got {min_precision}")
    none = {"threshold": float("inf"), "precision": float("nan"),
            "recall": 0.0 if curve.positives else float("nan"), "f1": 0.0, "rule": rule}
    if len(curve) == 0:
        return none
    p = np.nan_to_num(curve.precision, nan=-1.0)
    r = np.nan_to_num(curve.recall, nan=-1.0)
    idx = np.arange(len(curve))
    if rule == "max_f1":
        primary = curve.f1
        mask = np.ones(len(curve), bool)
    else:
        primary = r
        mask = p >= min_precision - 1e-12
        if not mask.any():
            return none
    # lexicographic: primary, then precision, then threshold (curve is sorted by descending threshold: -idx)
    keys = np.lexsort((-idx[mask], p[mask], primary[mask]))
    best = idx[mask][keys[-1]]
    return {"threshold": float(curve.thresholds[best]), "precision": float(curve.precision[best]),
            "recall": float(curve.recall[best]), "f1": float(curve.f1[best]), "rule": rule}
