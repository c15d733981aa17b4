"""Localize the frames of a recorded pass with no database: each frame against the satellite map alone, from a
prior drawn around its true pose as a GPS fix would give (satloc.crossview).

    satloc demo --out satloc_demo                      # or: satloc record --scene city --out satloc_demo/rec
    python examples/crossview.py --recording satloc_demo/rec --frames 40

Takes ``--frames`` frames evenly spaced along the recording's query pass; for each, a prior centred uniformly
within ``--radius`` metres of the truth with a heading within ``--yaw`` degrees (seeded), localizes and prints
one line per frame and the summary: mean and median error, the fractions within 1 m, within 1 m laterally and
longitudinally, the median heading error and the time per frame.

``--track``: the frames are localized in order, each prior but the first centred on the previous answer moved by
the visual odometry between them (``odometry_visual.npz`` beside the recording's passes, which `satloc demo`
and the experiments write), ``--track-radius`` metres and ``--track-yaw`` degrees wide; the first frame's is
the GPS-like prior, and so is any frame's whose moved answer lies outside that frame's GPS-like prior (the
fix says the track is lost) or follows a frame with no answer.

``--temperatures T1 T2 ...`` also scores the posterior at each temperature: the mean log of the posterior
mass within 1 m and 2 degrees of the truth (higher is better calibrated), to choose ``CrossViewConfig.
temperature`` on a calibration recording (``satloc experiment tune`` records one on ``fcn_train/town_a``).
"""
import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

from satloc import Sequence
from satloc.crossview import CrossViewConfig, CrossViewLocalizer, Prior
from satloc.dictionary import SatelliteFeatures
from satloc.errors import ConfigError, run_script
from satloc.features import make_extractor
from satloc.satmap import SatelliteMap


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
    ap.add_argument("--track-radius", type=float, default=5.0)
    ap.add_argument("--track-yaw", type=float, default=4.0)
    a = ap.parse_args(argv)
    rec = Path(a.recording)
    seq, sm = Sequence.load(rec / "query"), SatelliteMap.load(rec / "map")
    ext = make_extractor("default")
    from satloc.align import AlignConfig

    cfg = CrossViewConfig(top_k=10**9 if a.temperatures else 256, align=AlignConfig(channels=a.channels))
    cv = CrossViewLocalizer(seq.camera, SatelliteFeatures.compute(sm, ext), ext, cfg)
    logscore = {t: [] for t in a.temperatures}
    rng = np.random.default_rng(a.seed)
    err, lat, lon, yaw, secs = [], [], [], [], []
    steps = None
    if a.track:
        odo = rec.parent / "odometry_visual.npz"
        if not odo.is_file():
            raise ConfigError(f"--track: {odo} not found (satloc demo and the experiments write it)")
        steps = np.load(odo, allow_pickle=False)["steps"]
    last, last_i = None, None
    for i in np.linspace(0, len(seq) - 1, min(a.frames, len(seq))).astype(int):
        f = seq[int(i)]
        t = f.pose
        r, ang = a.radius * math.sqrt(rng.uniform()), rng.uniform(0, 2 * math.pi)
        prior = Prior(t.x + r * math.cos(ang), t.y + r * math.sin(ang), t.yaw + math.radians(rng.uniform(-a.yaw, a.yaw)),
                      a.radius, a.yaw)
        if steps is not None and last is not None:   # the previous answer moved by the odometry since its frame
            x, y, th = last.x, last.y, last.yaw
            for dx, dy, dth in steps[last_i + 1:i + 1]:
                if np.all(np.isfinite([dx, dy, dth])):
                    x, y, th = x + math.cos(th) * dx - math.sin(th) * dy, y + math.sin(th) * dx + math.cos(th) * dy, th + dth
            if math.hypot(x - prior.x, y - prior.y) <= a.radius:   # else the GPS-like fix says the track is lost
                prior = Prior(x, y, th, a.track_radius, a.track_yaw)
        t0 = time.perf_counter()
        res = cv.localize(f, prior)
        secs.append(time.perf_counter() - t0)
        last, last_i = res.pose, int(i)
        if res.pose is None:
            print(f"frame {i}: too little ground seen")
            err.append(math.inf), lat.append(math.inf), lon.append(math.inf), yaw.append(math.inf)
            continue
        if a.temperatures:   # softmax(score / T) is the posterior at cfg.temperature raised to cfg.temperature / T
            near = ((np.hypot(res.candidates[:, 0] - t.x, res.candidates[:, 1] - t.y) <= 1.0)
                    & (np.abs(np.remainder(res.candidates[:, 2] - t.yaw + np.pi, 2 * np.pi) - np.pi)
                       <= math.radians(2.0)))
            lp = np.log(np.maximum(res.posterior, 1e-300))
            for temp in a.temperatures:
                q = lp * (cfg.temperature / temp)
                q = np.exp(q - q.max())
                logscore[temp].append(math.log(max(float(q[near].sum() / q.sum()), 1e-12)))
        dx, dy = res.pose.x - t.x, res.pose.y - t.y
        c, s = math.cos(t.yaw), math.sin(t.yaw)
        err.append(math.hypot(dx, dy))
        lon.append(abs(c * dx + s * dy))
        lat.append(abs(-s * dx + c * dy))
        yaw.append(abs(math.degrees(math.remainder(res.pose.yaw - t.yaw, 2 * math.pi))))
        print(f"frame {i}: error {err[-1]:.2f} m (lateral {lat[-1]:.2f}, longitudinal {lon[-1]:.2f}), "
              f"heading {yaw[-1]:.1f} deg, correlation {res.correlation:.3f}")
    e = np.array(err)
    print(f"{len(e)} frames{', tracked' if a.track else ''}, prior +-{a.radius:g} m / +-{a.yaw:g} deg: mean {e[np.isfinite(e)].mean():.2f} m, "
          f"median {np.median(e):.2f} m, within 1 m {np.mean(e < 1):.0%}, lateral within 1 m "
          f"{np.mean(np.array(lat) < 1):.0%}, longitudinal within 1 m {np.mean(np.array(lon) < 1):.0%}, "
          f"heading median {np.median(yaw):.1f} deg, {np.mean(secs):.2f} s per frame")
    for temp, v in logscore.items():
        print(f"temperature {temp:g}: mean log posterior mass within 1 m and 2 deg of the truth {np.mean(v):.3f}")


if __name__ == "__main__":
    sys.exit(run_script(main))
