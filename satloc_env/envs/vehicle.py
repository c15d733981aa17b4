"""Vehicle motion (kinematic bicycle model) and a route-following autopilot."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from satloc.geometry import Pose2
from satloc_env.world.route import Route

#: seconds per simulator step (the environment's default ``dt``, which the recorder drives at)
DEFAULT_DT = 0.1


@dataclass(frozen=True)
class VehicleParams:
    wheelbase_m: float = 2.7
    max_steer_rad: float = 0.6
    max_speed_mps: float = 20.0
    max_yaw_rate: float = 1.0


def action_bounds(p: VehicleParams) -> tuple[np.ndarray, np.ndarray]:
    """The action space's bounds (float32): [speed m/s, yaw rate rad/s] from [0, -max yaw rate] to
    [max speed, max yaw rate]."""
    return (np.array([0.0, -p.max_yaw_rate], np.float32), np.array([p.max_speed_mps, p.max_yaw_rate], np.float32))


def step_bicycle(pose: Pose2, speed: float, yaw_rate: float, dt: float, p: VehicleParams) -> tuple[Pose2, float, float]:
    """Advance ``pose`` by ``dt`` seconds. The commanded yaw rate is turned into a steering angle
    (``atan(L * yaw_rate / v)``), limited to the steering range, and integrated exactly along the arc.

    Returns the new pose and the speed and yaw rate actually applied.
    """
    v = float(np.clip(speed, 0.0, p.max_speed_mps))
    w = float(np.clip(yaw_rate, -p.max_yaw_rate, p.max_yaw_rate))
    if v > 1e-6:
        steer = float(np.clip(math.atan(p.wheelbase_m * w / v), -p.max_steer_rad, p.max_steer_rad))
        w = v * math.tan(steer) / p.wheelbase_m
    else:
        w = 0.0
    dth = w * dt
    if abs(dth) < 1e-9:
        dx, dy = v * dt, 0.0
    else:
        r = v / w
        dx, dy = r * math.sin(dth), r * (1.0 - math.cos(dth))
    return pose @ Pose2(dx, dy, dth), v, w


class Autopilot:
    """Pure-pursuit route follower at a lateral lane offset: ``action = pilot.act(pose)``.

    Slows down before sharp turns. Keeps track of its progress ``s`` along the route so laps that overlap
    are not confused.
    """

    def __init__(self, route: Route, lane_offset: float, speed: float = 8.0, lookahead: float = 6.0,
                 s0: float = 0.0):
        self.route, self.offset, self.speed, self.lookahead = route, lane_offset, speed, lookahead
        self.s = s0

    def follow(self, pose: Pose2) -> None:
        """Update the progress ``s`` along the route after the vehicle moved to ``pose``."""
        self.s, _ = self.route.project((pose.x, pose.y), s_hint=self.s, window=15.0)

    def act(self, pose: Pose2) -> np.ndarray:
        self.s, _ = self.route.project((pose.x, pose.y), s_hint=self.s, window=15.0)
        target = self.route.pose_at(self.s + self.lookahead, self.offset)
        local = pose.transform_inv(np.array([target.x, target.y]))
        ld2 = max(float(local @ local), 1e-6)
        curvature = 2.0 * local[1] / ld2
        turn = abs(self.route.curvature_ahead(self.s, 12.0))
        v = self.speed * (1.0 - 0.6 * min(1.0, turn / (math.pi / 2)))
        return np.array([v, v * curvature], dtype=np.float32)

    @property
    def done(self) -> bool:
        return self.s >= self.route.length - 1.0
