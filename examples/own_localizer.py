"""Bring your own localizer: a class of your own, graded as the built-in ones are.

A localizer is any object with ``reset(context)`` and ``localize(query)`` (satloc.localizers.interface); it
subclasses nothing of satloc's. This one fuses what every query carries besides the images: it moves its last
answer by the odometry and pulls it towards the query's GPS-like prior (a complementary filter). It is a
floor a vision method should beat, and a template to start from.

Run it in the environment (prints its error along a drive beside the prior's)::

    python examples/own_localizer.py --steps 60

and in the tables, beside the built-in methods, by naming it ``path/to/file.py:Name``::

    satloc experiment table1 --out t1 --scenes city --localizer examples/own_localizer.py:GpsOdometryFilter
    satloc evaluate --database DRIVE --satellite MAP --out ev --localizer examples/own_localizer.py:GpsOdometryFilter
"""
import argparse
import sys

import numpy as np

from satloc import Pose2
from satloc.errors import run_script


# --8<-- [start:localizer]
class GpsOdometryFilter:
    """Dead reckoning pulled towards each prior by ``gain`` (0: dead reckoning alone, 1: the prior alone)."""

    name = "GPS + odometry filter"

    def __init__(self, gain: float = 0.15):
        self.gain = gain
        self.pose = None

    def reset(self, context):
        """A new drive: ``context.camera``, ``context.satmap`` (a SatelliteMap), ``context.seed``, and
        ``context.database`` where the protocol has a database drive (None otherwise)."""
        self.pose = None

    def localize(self, query):
        """``query.frame`` (the stereo pair), ``query.odometry`` (a Pose2 since the previous query, or None) and
        ``query.prior`` (x, y, yaw within radius_m / yaw_deg, or None); return a Pose2 (or None: no answer)."""
        if self.pose is not None and query.odometry is not None:
            self.pose = self.pose @ query.odometry           # dead reckoning
        elif query.odometry is None and query.index > 0:
            self.pose = None                                 # the motion is unknown: start again
        p = query.prior
        if p is None:
            return self.pose
        if self.pose is None:
            self.pose = p.pose
        else:                                                # pulled towards the fix (heading from the odometry)
            g = self.gain
            self.pose = Pose2(self.pose.x + g * (p.x - self.pose.x), self.pose.y + g * (p.y - self.pose.y),
                              self.pose.yaw)
        return self.pose
# --8<-- [end:localizer]


def main(argv=None):
    import gymnasium as gym

    import satloc_env  # noqa: F401  (registers the environments)

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="city")
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    env = gym.make("satloc/SatLoc-v0", scene=args.scene, localizer=GpsOdometryFilter())
    loc = env.unwrapped.localizer
    _, info = env.reset(seed=args.seed)
    errors, prior_errors = [], []
    for _ in range(args.steps):
        _, _, terminated, truncated, info = env.step(env.unwrapped.autopilot_action())
        errors.append(float(info["error_m"]))
        if terminated or truncated:
            break
    env.close()
    print(f"{loc.name} on {args.scene}, {len(errors)} steps: mean error {np.mean(errors):.2f} m, last "
          f"{errors[-1]:.2f} m (the prior alone: about 13.3 m, 2/3 of its 20 m radius)")
    return errors


if __name__ == "__main__":
    sys.exit(run_script(main))
