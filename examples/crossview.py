"""Localize the frames of a recorded pass with no database: each frame against the satellite map alone, from a
prior drawn around its true pose as a GPS fix would give (satloc.localizers.crossview).

    satloc demo --out satloc_demo                      # or: satloc record --scene city --out satloc_demo/rec
    python examples/crossview.py --recording satloc_demo/rec --frames 40

Takes ``--frames`` frames evenly spaced along the recording's query pass; for each, a prior centred uniformly
within ``--radius`` metres of the truth with a heading within ``--yaw`` degrees (seeded), localizes and prints
one line per frame and the summary: mean and median error, the fractions within 1 m, within 1 m laterally and
longitudinally, the median heading error and the time per frame.

``--track``: the frames are localized in order by a :class:`satloc.localizers.crossview.CrossViewTracker`, the previous
answer moved by the visual odometry between them (``odometry_visual.npz`` beside the recording's passes, which
`satloc demo` and the experiments write): ``--track-mode gate`` searches ``--track-radius`` metres and
``--track-yaw`` degrees around it, ``fuse`` the whole GPS-like prior with it as a Gaussian belief of
``--sigma`` metres / ``--sigma-yaw`` degrees; the GPS-like prior alone where the moved answer lies outside it
(the fix says the track is lost) or after a frame with no answer.

``--gnss receiver``: the priors as a receiver gives them over the pass's time (satloc.localizers.gnss: a drifting
bias, multipath jumps that may put the truth outside the prior, outages with no fix, seeded by ``--seed``);
``--no-accuracy``: its fixes report no accuracy; ``--lost-after S`` and ``--fix-nu NU``: the tracker's and the
localizer's settings for such priors (``CrossViewConfig.lost_after_s``, ``fix_nu``). A frame in an outage has no
answer single, and follows the track tracked.

``--temperatures T1 T2 ...`` also scores the posterior at each temperature: the mean log of the posterior
mass within 1 m and 2 degrees of the truth (higher is better calibrated), to choose ``CrossViewConfig.
temperature`` on a calibration recording (``satloc experiment tune`` records one on ``calib/town_a``).
"""
import argparse
import math
import sys
from pathlib import Path

import numpy as np

from satloc import Sequence
from satloc.errors import ConfigError, run_script
from satloc.evaluation.metrics import pose_errors
from satloc.features import make_extractor
from satloc.features.dictionary import SatelliteFeatures
from satloc.localizers.crossview import CrossViewConfig, CrossViewLocalizer, draw_prior, localize_frames
from satloc.localizers.gnss import GnssConfig, gnss_priors
from satloc.satmap import SatelliteMap
from satloc.tracking.align import AlignConfig
from satloc.tracking.track import compose_between


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recording", required=True, help="a recording directory (query/ and map/ inside)")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--radius", type=float, default=20.0, help="the prior's radius, metres")
    ap.add_argument("--yaw", type=float, default=10.0, help="the prior's heading range, +- degrees")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--temperatures", type=float, nargs="*", default=[])
    ap.add_argument("--track", action="store_true")
    ap.add_argument("--channels", default="gray", choices=["gray", "edge", "gray+edge"],
                    help="what the bird's-eye views compare (gray needs no network on the ground image)")
    d = CrossViewConfig()
    ap.add_argument("--drivable", default=d.drivable, choices=["auto", "semantic", "labels", "none"],
                    help="where the vehicle may be: the map's own road semantics, its label raster (the road "
                         "vectors; auto: these where the map has them), or anywhere in the prior")
    ap.add_argument("--projections", default="shipped",
                    help="learned channels: 'shipped' (the default), a crossview.pt of satloc train-crossview, or "
                         "'none' (the grey level alone)")
    ap.add_argument("--track-mode", default=d.track, choices=["gate", "fuse"])
    ap.add_argument("--track-radius", type=float, default=d.track_radius_m)
    ap.add_argument("--track-yaw", type=float, default=d.track_yaw_deg)
    ap.add_argument("--sigma", type=float, default=d.track_sigma_m, help="metres (CrossViewConfig.track_sigma_m)")
    ap.add_argument("--sigma-per-m", type=float, default=d.track_sigma_per_m,
                    help="the belief's widening per metre travelled since the track's last answer "
                         "(CrossViewConfig.track_sigma_per_m; 0: a fixed --sigma)")
    ap.add_argument("--sigma-yaw", type=float, default=d.track_sigma_deg)
    ap.add_argument("--gnss", default="uniform", choices=["uniform", "receiver"], help="how the priors stray")
    ap.add_argument("--no-accuracy", action="store_true", help="--gnss receiver: fixes without their accuracy")
    ap.add_argument("--lost-after", type=float, default=d.lost_after_s, help="seconds (CrossViewConfig.lost_after_s)")
    ap.add_argument("--fix-nu", type=float, default=d.fix_nu, help="CrossViewConfig.fix_nu")
    a = ap.parse_args(argv)
    rec = Path(a.recording)
    seq, sm = Sequence.load(rec / "query"), SatelliteMap.load(rec / "map")
    ext = make_extractor("default")
    cfg = CrossViewConfig(top_k=10**9 if a.temperatures else 256, align=AlignConfig(channels=a.channels),
                          track=a.track_mode, track_radius_m=a.track_radius, track_yaw_deg=a.track_yaw,
                          track_sigma_m=a.sigma, track_sigma_per_m=a.sigma_per_m, track_sigma_deg=a.sigma_yaw,
                          drivable=a.drivable,
                          lost_after_s=a.lost_after, fix_nu=a.fix_nu,
                          projections=None if a.projections == "none" else a.projections)
    sf = SatelliteFeatures.compute(sm, ext)
    cv = CrossViewLocalizer(seq.camera, sf, ext, cfg, labels=sm.labels)
    rng = np.random.default_rng(a.seed)
    idx = np.linspace(0, len(seq) - 1, min(a.frames, len(seq))).astype(int)
    truth = np.asarray(seq.poses, np.float64)[idx]
    if a.gnss == "uniform":
        priors = [draw_prior(t, a.radius, a.yaw, rng) for t in truth]
    else:   # the receiver's track over the whole pass: a frame's fix does not depend on which frames are taken
        stamps = np.asarray(seq.timestamps, np.float64)
        priors = gnss_priors(truth, stamps[idx], GnssConfig(model="receiver", reports_accuracy=not a.no_accuracy),
                             a.radius, a.yaw, a.seed, keys=idx, start=float(stamps.min()))
    odo = None
    if a.track:
        path = rec.parent / "odometry_visual.npz"
        if not path.is_file():
            raise ConfigError(f"--track: {path} not found (satloc demo and the experiments write it)")
        steps = np.load(path, allow_pickle=False)["steps"]
        odo = compose_between(steps, idx)   # the odometry between consecutive evaluated frames
    has = np.array([p is not None for p in priors])
    follow = (cfg.track_radius_m, cfg.track_yaw_deg) if a.track else None
    if a.track or has.all():
        r = localize_frames(cv, (seq[int(i)] for i in idx), priors, odo, top=cfg.top_k if a.temperatures else 32,
                            follow=follow)
    else:   # single frames: those in an outage have no answer
        got = localize_frames(cv, (seq[int(i)] for i in idx[has]), [p for p in priors if p is not None], None,
                              top=cfg.top_k if a.temperatures else 32)
        r = {k: np.full((len(idx),) + v.shape[1:], np.nan if v.dtype.kind == "f" else 0, v.dtype)
             for k, v in got.items()}
        for k, v in got.items():
            r[k][has] = v
    outside = np.mean([p is not None and math.hypot(p.x - t[0], p.y - t[1]) > p.radius_m
                       for p, t in zip(priors, truth)])
    pe = pose_errors(r["estimates"], truth)
    for k, i in enumerate(idx):
        if not np.isfinite(pe["error"][k]):
            print(f"frame {i}: too little ground seen")
            continue
        print(f"frame {i}: error {pe['error'][k]:.2f} m (lateral {pe['lateral'][k]:.2f}, longitudinal "
              f"{pe['longitudinal'][k]:.2f}), heading {pe['heading_deg'][k]:.1f} deg, correlation {r['correlation'][k]:.3f}")
    e = np.where(np.isfinite(pe["error"]), pe["error"], np.inf)
    print(f"{len(e)} frames{', tracked (' + a.track_mode + ')' if a.track else ''}, prior +-{a.radius:g} m / "
          f"+-{a.yaw:g} deg: mean {e[np.isfinite(e)].mean():.2f} m, median {np.median(e):.2f} m, within 1 m "
          f"{np.mean(e < 1):.0%}, lateral within 1 m {np.mean(pe['lateral'] < 1):.0%}, longitudinal within 1 m "
          f"{np.mean(pe['longitudinal'] < 1):.0%}, heading median {np.nanmedian(pe['heading_deg']):.1f} deg, "
          f"{np.nanmean(r['seconds']):.2f} s per frame")
    if a.gnss != "uniform":
        print(f"priors ({a.gnss}): {np.mean(~has):.0%} of frames with no fix, the truth outside the prior in "
              f"{outside:.0%}")
    for temp in a.temperatures:   # softmax(score / T) is the posterior at cfg.temperature raised to cfg.temperature / T
        scores = []
        for k in range(len(idx)):
            q, c = r["top_probs"][k], r["top_poses"][k]
            if not q.sum():
                continue
            near = ((np.hypot(c[:, 0] - truth[k, 0], c[:, 1] - truth[k, 1]) <= 1.0)
                    & (np.abs(np.remainder(c[:, 2] - truth[k, 2] + np.pi, 2 * np.pi) - np.pi) <= math.radians(2.0)))
            lp = np.log(np.maximum(q, 1e-300)) * (cfg.temperature / temp)
            w = np.exp(lp - lp.max()) * (q > 0)
            scores.append(math.log(max(float(w[near].sum() / w.sum()), 1e-12)))
        print(f"temperature {temp:g}: mean log posterior mass within 1 m and 2 deg of the truth {np.mean(scores):.3f}")


if __name__ == "__main__":
    sys.exit(run_script(main))
