"""The no-database localizer under the receiver model of the priors (satloc.localizers.gnss), on a calibration
recording: uniform priors against a receiver's, single frames and tracked, with and without the fixes' accuracy,
and the tracker's ``lost_after_s``.

    satloc experiment tune --out tune             # records the calibration pass on calib/town_a (before 2026-12-07: fcn_train/town_a, the plain world)
    python docs/tools/gnss_calibration.py tune/rec 8 6 gnss_cal.json

Takes every STEP-th frame of the recording's query pass (``odometry_visual.npz`` beside the recording: the
visual odometry between them), draws each frame's prior with each of SEEDS seeds (uniform: seeded by the seed
and the frame's index; receiver: one receiver per seed over the pass's time), localizes with the shipped
features, and prints and writes per configuration: the share of frames answered (a frame in an outage, or
whose fix lies off the map, has no answer single; tracked, it follows its track), the mean error over the answered, the median (an unanswered
frame counted infinite), the shares within 1 m and beyond 10 m, the share of frames without a fix and with the
truth outside the 20 m prior, and each seed's mean.

SEEDS ``outside:N:K`` instead screens the receiver seeds 0 to N-1 (drawing their fixes only, no localizing) and
keeps the first K whose pass puts the truth outside the 20 m prior at some frame: a pass of 2.5 minutes rarely
does (the model's long-run rate is 4 % of fixes, in episodes), and the tracker's rule for disagreeing fixes
only acts there. Only the receiver's runs are made on them; the screen's tally (passes kept of those drawn)
is printed.

    python docs/tools/gnss_calibration.py tune/rec 8 outside:400:8 gnss_outside.json
"""
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from satloc import Sequence
from satloc.features import make_extractor
from satloc.features.dictionary import SatelliteFeatures
from satloc.localizers.crossview import (CrossViewConfig, CrossViewLocalizer, draw_prior, localize_frames,
                                         prior_on_map)
from satloc.localizers.gnss import GnssConfig, gnss_priors
from satloc.satmap import SatelliteMap
from satloc.tracking.track import compose_between

#: (prior model, tracked, fixes report their accuracy, CrossViewConfig fields)
RUNS = [("uniform", False, True, {}), ("uniform", True, True, {}),
        ("receiver", False, True, {}), ("receiver", False, False, {}),
        ("receiver", True, True, {"lost_after_s": 0.0}), ("receiver", True, True, {"lost_after_s": 10.0}),
        ("receiver", True, True, {"lost_after_s": 30.0}),
        ("receiver", True, False, {"lost_after_s": 0.0}), ("receiver", True, False, {"lost_after_s": 10.0})]


def screen(truth: np.ndarray, times: np.ndarray, idx: np.ndarray, start: float, n: int, k: int) -> list[int]:
    """The first ``k`` receiver seeds of ``range(n)`` whose fixes put the truth outside the 20 m prior somewhere."""
    kept = []
    for seed in range(n):
        pri = gnss_priors(truth, times, GnssConfig(model="receiver"), 20.0, 10.0, seed, keys=idx, start=start)
        if any(p is not None and math.hypot(p.x - t[0], p.y - t[1]) > 20 for p, t in zip(pri, truth)):
            kept.append(seed)
            if len(kept) == k:
                break
    print(f"screen: {len(kept)} of {seed + 1} receiver passes put the truth outside the prior: {kept}", flush=True)
    return kept


def main(rec: Path, step: int, seeds_spec: str, dest: Path) -> None:
    seq, sm = Sequence.load(rec / "query"), SatelliteMap.load(rec / "map")
    ext = make_extractor("default")
    t0 = time.time()
    sf = SatelliteFeatures.compute(sm, ext)
    print("features", time.time() - t0, flush=True)
    idx = np.arange(0, len(seq), step)
    truth = np.asarray(seq.poses, np.float64)[idx]
    stamps = np.asarray(seq.timestamps, np.float64)
    steps = np.load(rec.parent / "odometry_visual.npz", allow_pickle=False)["steps"]
    odo = compose_between(steps, idx)   # the odometry between consecutive frames taken
    print(len(idx), "frames over", stamps[idx[-1]] - stamps[idx[0]], "s", flush=True)
    runs, seeds = RUNS, None
    if seeds_spec.startswith("outside:"):
        _, n, k = seeds_spec.split(":")
        seeds = screen(truth, stamps[idx], idx, float(stamps.min()), int(n), int(k))
        runs = [r for r in RUNS if r[0] == "receiver"]
    else:
        seeds = list(range(int(seeds_spec)))
    cvs, out = {}, []
    for model, track, acc, kw in runs:
        key = tuple(sorted(kw.items()))
        if key not in cvs:
            cvs[key] = CrossViewLocalizer(seq.camera, sf, ext, CrossViewConfig(**kw), labels=sm.labels)
        cv = cvs[key]
        errs, nofix, outside = [], [], []
        for seed in seeds:
            if model == "uniform":
                priors = [draw_prior(t, 20.0, 10.0, np.random.default_rng([seed, int(i)])) for t, i in zip(truth, idx)]
            else:
                priors = gnss_priors(truth, stamps[idx], GnssConfig(model="receiver", reports_accuracy=acc), 20.0,
                                     10.0, seed, keys=idx, start=float(stamps.min()))
            # a fix whose disc lies off the map (multipath of tens of metres near its edge) is one the localizer
            # cannot search: counted as no fix, as the harness counts the error it raises as a failed query
            priors = [p if p is not None and prior_on_map(p, sf) else None for p in priors]
            has = np.array([p is not None for p in priors])
            nofix.append(1 - has.mean())
            outside.append(np.mean([p is not None and math.hypot(p.x - t[0], p.y - t[1]) > 20
                                    for p, t in zip(priors, truth)]))
            if track:
                r = localize_frames(cv, (seq[int(i)] for i in idx), priors, odo, follow=(5.0, 4.0))
                est = r["estimates"]
            else:   # single frames: those without a fix have no answer
                est = np.full((len(idx), 3), np.nan)
                sel = np.flatnonzero(has)
                r = localize_frames(cv, (seq[int(idx[k])] for k in sel), [priors[k] for k in sel], None)
                est[sel] = r["estimates"]
            errs.append(np.hypot(est[:, 0] - truth[:, 0], est[:, 1] - truth[:, 1]))
        e = np.concatenate(errs)
        ans = np.isfinite(e)
        row = dict(model=model, track=track, accuracy=acc, **kw, answered=float(ans.mean()),
                   mean=float(e[ans].mean()), median=float(np.median(np.where(ans, e, np.inf))),
                   within1=float(np.mean(e[ans] < 1)), beyond10=float(np.mean(np.where(ans, e, np.inf) > 10)),
                   nofix=float(np.mean(nofix)), outside=float(np.mean(outside)),
                   per_seed_mean=[float(np.nanmean(x)) for x in errs])
        out.append(row)
        print(json.dumps(row), flush=True)
    dest.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main(Path(sys.argv[1]), int(sys.argv[2]), sys.argv[3], Path(sys.argv[4]))
