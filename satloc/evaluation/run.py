"""Run any localizer over the frames of a sequence and keep what it answered: the one grading path.

:func:`run_localizer` drives a localizer of the common interface (:mod:`satloc.localizers.interface`) through a
run: :meth:`reset` with the run's :class:`~satloc.localizers.interface.Context`, then one
:class:`~satloc.localizers.interface.Query` per selected frame, in order, with the odometry since the previous
selected frame and the frame's prior. Its :class:`Run` holds the same arrays for every localizer, built-in or
a user's (estimates, errors against the sequence's poses, inlier scores, the posterior's strongest entries,
the priors, the time per query); the tables compute their columns from them with one rule
(:func:`satloc.evaluation.metrics.error_stats`).

The frames a localizer sees carry no pose and no semantic labels (depth where the sequence has it). A query
answered with ``None``, by raising :class:`~satloc.errors.ConfigError` or with something that is not an answer (a
non-finite pose, a posterior whose shape does not match its candidates) has no answer: NaN estimate and error,
``inlier`` False, the message kept in :attr:`Run.failures`. A localizer with the optional
``localize_many(queries)`` (answers in order, a ConfigError instance for no answer) is run through it: the
paper's method overlaps the next frame's stereo and features with the current frame's scoring there.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable
from typing import Sequence as Seq

import numpy as np

from ..errors import ConfigError
from ..geometry import Pose2
from ..localizers.interface import (
    DEFAULT_POSTERIOR_K,
    Context,
    Estimate,
    Prior,
    Query,
    as_estimate,
    check_localizer,
    localizer_name,
)
from ..persist import save_npz
from ..sequence import Sequence

__all__ = ["Run", "run_localizer", "odometry_queries"]


@dataclass
class Run:
    """What one localizer answered over a run; arrays over the queries in order (see the module docstring)."""

    name: str
    frames: np.ndarray            # (n,) int64: the frames of the sequence localized
    estimates: np.ndarray         # (n, 3) x, y, yaw; NaN: no answer
    truth: np.ndarray             # (n, 3) the sequence's poses; NaN where unknown
    errors: np.ndarray            # (n,) planar distance from the truth; NaN: no answer or no truth
    inlier_score: np.ndarray      # (n,) the answer's inlier score (NaN: none given, or no answer)
    inlier: np.ndarray            # (n,) bool: answered and not declared off the map
    top_poses: np.ndarray         # (n, k, 3) the posterior's k strongest candidates (the answer alone without one)
    top_probs: np.ndarray         # (n, k)
    priors: np.ndarray            # (n, 5) x, y, yaw, radius_m, yaw_deg of each query's prior; zeros: none
    seconds: np.ndarray           # (n,) time of each query's localization
    reset_s: float = 0.0          # time of reset(context)
    failures: list = field(default_factory=list)   # (frame, message) of the queries with no answer

    @property
    def queries(self) -> int:
        return len(self.frames)

    @property
    def queries_per_s(self) -> float | None:
        s = float(self.seconds.sum())
        return round(len(self.frames) / s, 2) if s > 0 else None

    def arrays(self) -> dict:
        """The arrays the results files hold (``localization_<name>.npz``): what was answered, not how long it
        took (the times go into the summaries, so that the same run on another machine or on Ray writes the same
        bytes)."""
        return {"frames": self.frames, "estimates": self.estimates, "truth": self.truth, "errors": self.errors,
                "inlier_score": self.inlier_score, "inlier": self.inlier, "top_poses": self.top_poses,
                "top_probs": self.top_probs, "prior": self.priors}

    def save(self, path: str | Path, meta: dict | None = None) -> None:
        """The arrays into ``path`` (a ``localization`` npz), with ``meta`` (the localizer's name and the queries
        without an answer added)."""
        save_npz(path, "localization", self.arrays(), dict(meta or {}, name=self.name, failed=len(self.failures)))


def odometry_queries(odometry: np.ndarray | None, n: int) -> list[Pose2 | None]:
    """Each query's odometry as the interface gives it: row i of ``odometry`` ((n, 3), the motion from query i - 1
    to i) as a :class:`Pose2`; None for row 0 (no query before it), for a non-finite row (motion unknown) and
    for every query without ``odometry``."""
    if odometry is None:
        return [None] * n
    o = np.asarray(odometry, np.float64)
    if o.shape != (n, 3):
        raise ConfigError(f"odometry: expected an ({n}, 3) array, one motion per query, got shape {o.shape}")
    return [None] + [Pose2(*r) if np.all(np.isfinite(r)) else None for r in o[1:]]


def run_localizer(localizer: Any, context: Context, sequence: Sequence, frames: Seq[int] | np.ndarray | None = None,
                  odometry: np.ndarray | None = None, priors: Iterable[Prior | None] | None = None,
                  top: int = DEFAULT_POSTERIOR_K, progress: bool = False,
                  on_result: Callable[[int, Estimate, Any], None] | None = None) -> Run:
    """Run ``localizer`` over the ``frames`` of ``sequence`` (default: every frame) in ``context`` (see the module
    docstring). ``odometry`` ((len(frames), 3), row i the motion from frame ``frames[i - 1]`` to ``frames[i]``;
    non-finite: unknown) and ``priors`` (one :class:`Prior` or None per frame) go into the queries; ``top``: the
    posterior entries kept per query; ``on_result(i, estimate, answer)`` is called for each answered query
    (``answer``: what the localizer returned, e.g. the paper's method's full :class:`Localization`)."""
    check_localizer(localizer)
    name = localizer_name(localizer)
    idx = np.arange(len(sequence), dtype=np.int64) if frames is None else np.asarray(frames, np.int64).reshape(-1)
    n = len(idx)
    if n and (idx.min() < 0 or idx.max() >= len(sequence)):
        raise ConfigError(f"frames: indices must lie in [0, {len(sequence)}), got {idx.min()}..{idx.max()}")
    pri = [None] * n if priors is None else list(priors)
    if len(pri) != n:
        raise ConfigError(f"priors: expected {n}, one per query (None where none), got {len(pri)}")
    odo = odometry_queries(odometry, n)
    truth = np.asarray(sequence.poses, np.float64).reshape(len(sequence), 3)[idx] if n else np.zeros((0, 3))
    est = np.full((n, 3), np.nan)
    score, inl = np.full(n, np.nan), np.zeros(n, bool)
    top_poses, top_probs = np.zeros((n, top, 3)), np.zeros((n, top))
    prior_arr, secs = np.zeros((n, 5)), np.zeros(n)
    failures: list[tuple[int, str]] = []
    for i, p in enumerate(pri):
        if p is not None:
            if not isinstance(p, Prior):
                raise ConfigError(f"priors: entry {i} is {type(p).__name__}, expected a satloc Prior or None")
            prior_arr[i] = p.as_array()

    t = time.perf_counter()
    localizer.reset(context)
    reset_s = time.perf_counter() - t

    def query(i: int) -> Query:
        f = sequence[int(idx[i])]
        f = dataclasses.replace(f, pose=None, labels=None)   # the question, not the answer
        return Query(f, odo[i], pri[i], i, float(f.timestamp))

    from tqdm.auto import tqdm

    bar = tqdm(total=n, desc=f"localize ({name})", unit="query", disable=not progress, leave=False)
    many = getattr(localizer, "localize_many", None)
    last = time.perf_counter()
    if callable(many):
        answers = many(query(i) for i in range(n))
    else:
        from .._threads import overlapped

        def answer(q: Query):
            try:
                return localizer.localize(q)
            except ConfigError as e:
                return e

        # the next frame is read from disk on a worker thread while this one is localized
        answers = (answer(q) for q in overlapped(query, range(n)))
    i = -1
    for i, a in enumerate(answers):
        if i >= n:
            raise ConfigError(f"localizer {name!r}: localize_many gave more answers than the {n} queries")
        now = time.perf_counter()
        secs[i], last = now - last, now
        bar.update(1)
        if isinstance(a, ConfigError):
            failures.append((int(idx[i]), str(a)))
            continue
        try:   # an answer that is not one (a non-finite pose, a posterior of the wrong shape): no answer, said why
            e = as_estimate(a, f"localizer {name!r}")
        except ConfigError as err:
            failures.append((int(idx[i]), str(err)))
            continue
        if e is None:
            failures.append((int(idx[i]), "no answer"))
            continue
        est[i] = e.pose.as_array()
        score[i], inl[i] = e.inlier_score, bool(e.inlier)
        top_poses[i], top_probs[i] = e.top(top)
        if on_result is not None:
            on_result(i, e, a)
    bar.close()
    if i + 1 != n:
        raise ConfigError(f"localizer {name!r}: localize_many gave {i + 1} answers for {n} queries")
    err = np.hypot(est[:, 0] - truth[:, 0], est[:, 1] - truth[:, 1])
    return Run(name, idx, est, truth, err, score, inl, top_poses, top_probs, prior_arr, secs, reset_s, failures)
