"""Step the environment in a script: drive a route with the autopilot and save a few views.

    python examples/drive.py --scene residential --steps 200 --out drive_out
"""
import argparse
import sys
from pathlib import Path

import cv2
import gymnasium as gym
import numpy as np

import satloc_env  # noqa: F401  (registers satloc/SatLoc-v0)
from satloc.errors import run_script


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="city")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--occlusion", type=float, default=0.3)
    ap.add_argument("--appearance", type=float, default=None, help="appearance change (default: the scene's)")
    ap.add_argument("--lane", type=float, default=-1.75, help="lateral offset from the route centre, metres")
    ap.add_argument("--out", default="drive_out")
    ap.add_argument("--localizer", default="none",
                    help="none, cross (no database), auto or a build directory (see docs/environment.md)")
    ap.add_argument("--localize-every", type=int, default=10)
    ap.add_argument("--track", action="store_true", help="fuse localizations over time with the odometry")
    ap.add_argument("--refine", action="store_true", help="refine each estimate by bird's-eye alignment")
    args = ap.parse_args(argv)

    # localizer: "none" drives only; "cross" localizes against the satellite map alone from a GPS-like prior
    # (seconds the first time); "auto" against a localizer built once from the scene's database pass and cached
    # (minutes the first time); or a build directory of `satloc build`
    localizer = None if args.localizer == "none" else args.localizer
    env = gym.make("satloc/SatLoc-v0", scene=args.scene, render_mode="rgb_array", depth=True, localizer=localizer,
                   localize_every=args.localize_every, localizer_track=args.track, localizer_refine=args.refine,
                   lane_offset_m=args.lane)
    obs, info = env.reset(seed=0, options={"occlusion": args.occlusion, "appearance": args.appearance})
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    odo_pose = info["pose"].copy()
    errors = []                                          # localization errors at the steps localized
    for t in range(args.steps):
        action = env.unwrapped.autopilot_action()       # or any policy: [speed m/s, yaw rate rad/s]
        obs, reward, terminated, truncated, info = env.step(action)
        dx, dy, dyaw = obs["odometry"]                  # noisy motion since the last step
        c, s = np.cos(odo_pose[2]), np.sin(odo_pose[2])
        odo_pose += [c * dx - s * dy, s * dx + c * dy, dyaw]
        if "error_m" in info and info["localized_step"] == info["step"]:
            errors.append(float(info["error_m"]))       # NaN: a frame without valid stereo depth
        if t % 50 == 0:
            cv2.imwrite(str(out / f"view_{t:04d}.png"), cv2.cvtColor(env.render(), cv2.COLOR_RGB2BGR))
        if terminated or truncated:
            break
    drift = float(np.hypot(*(odo_pose[:2] - info["pose"][:2])))
    print(f"drove {float(info['route_s']):.0f} m in {t + 1} steps; dead-reckoning drift {drift:.2f} m")
    if errors:
        e = np.array(errors)
        print(f"localized {len(e)} times; error mean {np.nanmean(e):.2f} m, median {np.nanmedian(e):.2f} m, "
              f"max {np.nanmax(e):.2f} m, {int(np.sum(e > 10))} off by more than 10 m")
    env.close()
    return drift


if __name__ == "__main__":
    sys.exit(run_script(main))
