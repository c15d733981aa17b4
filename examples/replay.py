"""Evaluate a localizer on a recorded sequence by replaying it in ``satloc/SatLocReplay-v0``.

    satloc record --scene city --out rec
    satloc build --database rec/database --map rec/map --out rec/build && satloc train-projection rec/build
    python examples/replay.py --sequence rec/query --localizer rec/build --track --out replay_out

Steps the replay environment over the sequence, localizing every ``--localize-every`` steps, and prints the mean,
median and largest error of the localizations. Writes into ``--out``: ``errors.csv`` (one row per step
localized), ``errors.png`` (the error along the sequence) and ``view_<frame>.png``, the environment's render of a
few frames (camera, bird's-eye crop and map overview with the posterior, the estimate and the truth).
"""
import argparse
import csv
import math
import sys
from pathlib import Path

import cv2
import gymnasium as gym
import numpy as np

import satloc_env  # noqa: F401  (registers satloc/SatLocReplay-v0)
from satloc.errors import run_script


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequence", required=True,
                    help="a sequence directory (satloc record, Sequence.save), a KITTI raw drive or a Malaga extract")
    ap.add_argument("--map", default=None, help="a satellite map directory or georeferenced imagery (GeoTIFF, image + "
                    "world file, XYZ tiles; default: the build's map, or ../map)")
    ap.add_argument("--localizer", default="none", help="a build directory of `satloc build`, or none")
    ap.add_argument("--mode", default="full", choices=["full", "np", "go"])
    ap.add_argument("--track", action="store_true", help="fuse localizations over time with the odometry")
    ap.add_argument("--refine", action="store_true", help="refine each estimate by bird's-eye alignment")
    ap.add_argument("--localize-every", type=int, default=1)
    ap.add_argument("--stride", type=int, default=1, help="frames advanced per step")
    ap.add_argument("--start", type=int, default=0, help="first frame")
    ap.add_argument("--end", type=int, default=None, help="replay the frames before this index")
    ap.add_argument("--noise", type=float, nargs=2, default=(0.02, 0.003), metavar=("FRAC", "RAD"),
                    help="odometry noise std: fraction of the distance, radians per step")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--views", type=int, default=3, help="how many rendered frames to save")
    ap.add_argument("--out", default="replay_out")
    args = ap.parse_args(argv)

    localizer = None if args.localizer == "none" else args.localizer
    env = gym.make("satloc/SatLocReplay-v0", sequence=args.sequence, map=args.map, localizer=localizer,
                   localizer_mode=args.mode, localizer_track=args.track, localizer_refine=args.refine,
                   localize_every=args.localize_every, stride=args.stride, start_frame=args.start,
                   end_frame=args.end, odometry_noise=tuple(args.noise), render_mode="rgb_array")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    seq = env.unwrapped.sequence
    end = len(seq) if args.end is None else args.end
    n_steps = (end - 1 - args.start) // args.stride + 1
    shots = set(np.linspace(0, n_steps - 1, max(0, min(args.views, n_steps))).round().astype(int).tolist())
    rows = []

    def record(info):
        if "error_m" in info and info["localized_step"] == info["step"]:
            rows.append({"frame": int(info["frame_index"]), "timestamp": float(info["timestamp"]),
                         "error_m": float(info["error_m"]), "inlier": bool(info["inlier"]),
                         "x": float(info["estimate"][0]), "y": float(info["estimate"][1])})
        if int(info["step"]) in shots:
            view = env.render()
            cv2.imwrite(str(out / f"view_{int(info['frame_index']):06d}.png"), cv2.cvtColor(view, cv2.COLOR_RGB2BGR))

    obs, info = env.reset(seed=args.seed)
    record(info)
    truncated = False
    while not truncated:                    # the replay ends (truncated) at the last frame
        obs, reward, terminated, truncated, info = env.step(1)   # the action: advance 1 stride
        record(info)
    env.close()
    print(f"replayed {int(info['step']) + 1} frames of {seq.name!r} (frames {args.start}..{int(info['frame_index'])}, "
          f"stride {args.stride})")
    if not rows:
        print("no localizer: nothing to evaluate")
        return {}
    with open(out / "errors.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    e = np.array([r["error_m"] for r in rows])
    ok = e[np.isfinite(e)]   # NaN: a frame without a result (no valid stereo depth) or without a true pose
    summary = {"localized": len(e), "evaluated": len(ok), "mean_m": float(ok.mean()) if len(ok) else math.nan,
               "median_m": float(np.median(ok)) if len(ok) else math.nan,
               "max_m": float(ok.max()) if len(ok) else math.nan, "over_10m": int(np.sum(ok > 10))}
    name = env.unwrapped.config.localizer_mode + ("+track" if args.track else "") + ("+align" if args.refine else "")
    print(f"{name}: localized {summary['localized']} times, {summary['evaluated']} with an error; mean "
          f"{summary['mean_m']:.2f} m, median {summary['median_m']:.2f} m, max {summary['max_m']:.2f} m, "
          f"{summary['over_10m']} off by more than 10 m")
    plot(rows, name, out / "errors.png")
    return summary


def plot(rows, name: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frames = np.array([r["frame"] for r in rows])
    e = np.array([r["error_m"] for r in rows])
    fig, ax = plt.subplots(figsize=(9, 3.5))
    ax.semilogy(frames, np.maximum(e, 1e-2), ".-", lw=0.8, ms=4, label=name)
    ax.axhline(1.0, color="grey", lw=0.6, ls="--")
    ax.set_xlabel("frame")
    ax.set_ylabel("error (m)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(run_script(main))
