"""Any localizer in the experiments: the reference floors and a user's localizers beside the built-in methods.

Every experiment that grades localizers (Table I's protocols, the sweep and the gap curve, ``satloc evaluate``,
``satloc demo`` and the stress example) runs, beside the paper's modes and the baselines:

* the reference localizers of ``references`` (:mod:`satloc.localizers.reference`: ``prior``, the prior's centre;
  ``dead-reckoning``, the first prior moved by the odometry), floors that look at no image;
* the localizers of ``localizers`` (``module:Name`` or ``path/to/file.py:Name``, :func:`satloc.localizers.interface.resolve_localizer`),
  a user's own, made anew for every run.

Each goes through :func:`satloc.evaluation.run.run_localizer` exactly as the built-in ones do, with the same
queries, the same odometry as the tracked modes and one prior per query drawn around its true pose as a GPS fix
gives it (:func:`query_priors`: by default uniform within ``cross_area.prior_radius_m`` and
``cross_area.prior_yaw_deg``, seeded by ``cross_area.seed`` and the query's frame index; ``cross_area.gnss``: a
receiver's correlated error instead), so every protocol and every method sees the same prior for the same frame.
Its rows carry the same columns (:func:`table_stats`),
named by the object's ``name`` attribute or its class name; its answers go into ``localization_<key>.npz``.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from satloc.errors import ConfigError
from satloc.evaluation.metrics import bootstrap_ci, ci_method, error_stats, stationary_block_length, worst_case_errors
from satloc.evaluation.run import Run, run_localizer
from satloc.localizers.gnss import gnss_priors
from satloc.localizers.interface import Context, localizer_name, resolve_localizer
from satloc.localizers.reference import REFERENCES, reference_localizer
from satloc.persist import header, write_json

__all__ = ["REFERENCE_NAMES", "USER_PREFIX", "table_stats", "query_priors", "extra_localizers", "check_extra", "run_graded",
           "user_key", "prune_extra"]

#: the reference localizers' rows
REFERENCE_NAMES = {k: v.name for k, v in REFERENCES.items()}
#: the key (and file name) of a user's localizer's rows: this prefix and its name made safe for a file name
USER_PREFIX = "user-"


def table_stats(errors, truth, db_poses, seed: int = 0) -> dict:
    """The error columns of every table row, one rule for every method (:mod:`satloc.evaluation.metrics`): a query not
    answered is a gross failure, counted with the worst answer on the map (the farthest database pose from its
    truth); ``mean_m, std_m, median_m, within_1m, within_10m`` (error <= 1 m, 10 m), ``failure_rate`` and the
    95 % bootstrap interval of the mean (``ci95_low, ci95_high``, seeded) over the queries in their order along
    the pass: a stationary block bootstrap (errors persist from query to query), named by ``ci_method``."""
    e = np.asarray(errors, np.float64)
    gross = worst_case_errors(np.asarray(truth, np.float64)[:, :2], np.asarray(db_poses, np.float64)[:, :2])
    st = error_stats(e, gross)
    counted = np.where(np.isfinite(e), e, gross)
    block = stationary_block_length(counted)
    lo, hi = bootstrap_ci(counted, seed=seed, method="stationary", block_length=block)
    return {"mean_m": st["mean"], "std_m": st["std"], "median_m": st["median"], "within_1m": st["within_1m"],
            "within_10m": st["within_10m"], "failure_rate": st["failure_rate"], "ci95_low": lo, "ci95_high": hi,
            "ci_method": ci_method("stationary", block)}


def query_priors(ca, truth: np.ndarray, frames: np.ndarray, timestamps: np.ndarray | None = None) -> list:
    """Each query's prior around its true pose (``truth`` (N, 3)), of ``ca.prior_radius_m`` and ``ca.prior_yaw_deg``
    (a :class:`satloc_env.experiments.scene_run.CrossAreaConfig`) as its receiver model ``ca.gnss`` gives it
    (:func:`satloc.localizers.gnss.gnss_priors`): ``uniform``, from a generator seeded with ``ca.seed`` and the
    query's frame index (``frames``); ``receiver``, the fix at the frame's time on the receiver's track over the
    whole pass (``timestamps``: the pass's, indexed by ``frames``; seeded by ``ca.seed``). Either way a query's
    prior does not depend on which other queries are evaluated. A query without a true pose, or in an outage,
    gets none."""
    frames = np.asarray(frames, np.int64)
    times = start = None
    if timestamps is not None:
        stamps = np.asarray(timestamps, np.float64)
        times, start = stamps[frames], float(stamps.min()) if len(stamps) else 0.0
    return gnss_priors(truth, times, ca.gnss, ca.prior_radius_m, ca.prior_yaw_deg, ca.seed, keys=frames, start=start)


def user_key(name: str) -> str:
    """The key of a user's localizer named ``name``: :data:`USER_PREFIX` and the name in lower case, runs of other
    characters than letters, digits, ``.`` and ``_`` made ``-``."""
    return USER_PREFIX + (re.sub(r"[^a-z0-9._]+", "-", name.lower()).strip("-") or "localizer")


def check_extra(cfg) -> None:
    """:class:`ConfigError` for an unknown reference or a ``localizers`` entry that does not name an object
    (``module:Name``, imported now: before any work; the localizers themselves are made when they run)."""
    from satloc.localizers.interface import import_object

    bad = [r for r in getattr(cfg, "references", ()) if r not in REFERENCES]
    if bad:
        raise ConfigError(f"references: unknown {bad}; expected some of {list(REFERENCES)}")
    for spec in getattr(cfg, "localizers", ()):
        if not isinstance(spec, str) or ":" not in spec or spec.startswith(":") or spec.endswith(":"):
            raise ConfigError(f"localizers: expected 'module:Name' or 'path/to/file.py:Name', got {spec!r}")
        import_object(spec, f"localizers: {spec}")


def prune_extra(out: Path, keep: set[str]) -> None:
    """Remove the results of reference floors and user's localizers in ``out`` that this run did not produce
    (``localization_<key>.npz/.json`` for a key of :data:`REFERENCES` or with :data:`USER_PREFIX` not in ``keep``),
    so that a localizer dropped from the configuration leaves no stale row behind."""
    for p in Path(out).glob("localization_*"):
        key = p.name[len("localization_"):].split(".")[0]
        if (key in REFERENCES or key.startswith(USER_PREFIX)) and key not in keep:
            p.unlink(missing_ok=True)


def extra_localizers(cfg, taken: set[str] = frozenset()) -> list[tuple[str, str, Any]]:
    """(key, display name, a new instance) of the references and the user's localizers of ``cfg``; a user's
    localizer whose name is another row's (one of ``taken``, or another of its own) is a :class:`ConfigError`."""
    out = [(r, REFERENCE_NAMES[r], reference_localizer(r)) for r in getattr(cfg, "references", ())]
    names = set(taken) | {n for _, n, _ in out}
    keys = {k for k, _, _ in out}
    for spec in getattr(cfg, "localizers", ()):
        obj = resolve_localizer(spec, f"localizers: {spec}")
        name = localizer_name(obj)
        key = user_key(name)
        if name in names or key in keys:
            raise ConfigError(f"localizers: {spec} is named {name!r}, as another row of the table is; give it "
                              "another name (its `name` attribute)")
        names.add(name)
        keys.add(key)
        out.append((key, name, obj))
    return out


def run_graded(loc: Any, key: str, name: str, context: Context, q, sel: np.ndarray, odometry: np.ndarray | None,
               priors: list, out: Path, db_poses: np.ndarray, label: str, progress: bool = True, log=print,
               meta: dict | None = None, on_result=None, stem: str = "localization") -> tuple[dict, Run]:
    """Run ``loc`` over the frames ``sel`` of ``q`` (:func:`satloc.evaluation.run.run_localizer`) and grade it as
    every table row is graded (:func:`table_stats`; ``db_poses``: where the worst
    answer of a query with no answer is measured). Writes ``out/<stem>_<key>.npz`` (the run's arrays) and
    ``.json`` (the summary); returns the summary (with the arrays ``errors`` and ``inlier_score``) and the run."""
    from satloc.localizers.interface import DEFAULT_POSTERIOR_K

    k = getattr(loc, "posterior_k", DEFAULT_POSTERIOR_K)
    k = int(k) if isinstance(k, (int, np.integer)) and not isinstance(k, bool) and k > 0 else DEFAULT_POSTERIOR_K
    run = run_localizer(loc, context, q, sel, odometry, priors, top=k, progress=progress, on_result=on_result)
    run.name = name   # the row's name (the paper's modes: their table names)
    truth = np.asarray(q.poses, np.float64)[np.asarray(sel, np.int64)]
    s = {"mode": key, "name": name, "queries": run.queries, **table_stats(run.errors, truth, db_poses),
         "s_per_query": float(run.seconds.mean()) if run.queries else float("nan"),
         "queries_per_s": run.queries_per_s, "failed": len(run.failures), "reset_s": round(run.reset_s, 3)}
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    run.save(out / f"{stem}_{key}.npz", dict(meta or {}, method=key, sequence=q.name))
    write_json(out / f"{stem}_{key}.json", dict(header("localization_summary"),
                                                      **{k: v for k, v in s.items() if not isinstance(v, np.ndarray)}))
    log(f"[{label}] {name}: mean {s['mean_m']:.2f} m (std {s['std_m']:.2f}), median {s['median_m']:.2f} m, "
        f"{100 * s['within_1m']:.0f} % within 1 m over {run.queries} queries"
        + (f", {len(run.failures)} without an answer" if run.failures else ""))
    return dict(s, errors=run.errors, inlier_score=np.where(np.isfinite(run.errors), run.inlier_score, np.nan)), run
