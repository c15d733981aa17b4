"""The database pass and a revisit of the same places, side by side, and what the revisit change does to SIFT.

At each of N places evenly spread along the scene's database route, the database pass's view (right lane, no
occluders, reference appearance) and the query pass's (1 m further left, occlusion 0.3, appearance 0.5: the
defaults of ``satloc_env.envs.record.RecordConfig().query``) at each ``--change`` strength (``satloc_env.world.revisit``)
are rendered, and the RANSAC inliers between the two left images are counted by EFM's own pipeline (SIFT,
1,000 features, ratio test, USAC homography: ``satloc.baselines.efm.estimate_homography``). Prints, per
strength, the median, the 10th and 90th percentiles and the share of places under EFM's 12-inlier minimum.

    python examples/revisit_change.py --scene residential --places 40 --change 0 0.5 1
    python examples/revisit_change.py --scene residential --picture docs/images/revisit_change.jpg
"""
import argparse
import sys
import time

import cv2
import numpy as np

from satloc.baselines.efm import estimate_homography
from satloc.errors import run_script
from satloc_env.envs.drive import SatLocEnv
from satloc_env.envs.record import QUERY_CHANGE, RecordConfig


def view(env: SatLocEnv, s: float, change: float | None = None, database: bool = False,
         plain: bool = False) -> np.ndarray:
    """The left image at ``s`` metres along the database route: the database pass's (``database``), else the
    query pass's with revisit ``change`` (None: the query pass's default), with ``plain`` without its occluders
    and appearance change."""
    p = RecordConfig().database if database else RecordConfig().query
    opts = {"start_s_m": s, "lane_offset_m": p.lane_offset_m, "occlusion": 0.0 if plain else p.occlusion,
            "appearance": 0.0 if plain else p.appearance, "change": p.change if change is None else change}
    obs, _ = env.reset(seed=p.seed, options=opts)
    return obs["left"]


def _label(img: np.ndarray, text: str) -> np.ndarray:
    img = img.copy()
    (w, h), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
    img[:h + 12, :w + 12] //= 3
    cv2.putText(img, text, (6, h + 5), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def picture(env: SatLocEnv, places: list[float], path: str) -> None:
    """Rows of (database pass, the revisit change alone, the default query pass) at ``places``; a JPEG."""
    rows = [np.hstack([_label(view(env, s, database=True), f"database pass, {s:g} m"),
                       _label(view(env, s, plain=True), f"revisit change {QUERY_CHANGE:g} alone"),
                       _label(view(env, s), f"query pass: change {QUERY_CHANGE:g} + appearance + occluders")])
            for s in places]
    cv2.imwrite(path, cv2.cvtColor(np.vstack(rows), cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 70])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="residential")
    ap.add_argument("--places", type=int, default=40, help="places along the database route")
    ap.add_argument("--change", type=float, nargs="+", default=[0.0, QUERY_CHANGE, 1.0])
    ap.add_argument("--picture", default=None, help="write the side-by-side picture here (JPEG) instead")
    ap.add_argument("--at", type=float, nargs="+", default=[100.0, 556.0, 900.0], help="places of the picture, metres")
    args = ap.parse_args(argv)

    env = SatLocEnv(scene=args.scene, localizer=None)
    try:
        if args.picture:
            picture(env, args.at, args.picture)
            print(f"wrote {args.picture}")
            return None
        env.reset(seed=0)
        length = env.route.length
        places = np.linspace(5.0, length - 5.0, args.places)
        t = time.time()
        db = [view(env, s, database=True) for s in places]
        result = {}
        for change in args.change:
            n = np.array([estimate_homography(view(env, s, change), d)[1] for s, d in zip(places, db)])
            result[change] = n
            print(f"{args.scene}: change {change:4.2f}: SIFT RANSAC inliers, database vs query pass at {len(n)} "
                  f"places: median {np.median(n):.0f}, p10 {np.percentile(n, 10):.0f}, "
                  f"p90 {np.percentile(n, 90):.0f}, under 12: {np.mean(n < 12):.0%}", flush=True)
        print(f"({time.time() - t:.0f} s)")
        return result
    finally:
        env.close()


if __name__ == "__main__":
    sys.exit(run_script(main))
