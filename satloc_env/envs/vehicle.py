"""Vehicle motion (kinematic bicycle model) and a route-following autopilot, which may wander.

A driver does not hold the lane's centre line to the centimetre, nor one speed. :class:`Wander` describes
how far they drift: the lateral position follows a smooth random process around the lane offset (standard
deviation ``lateral_m``, correlated over ``scale_m`` of route) and the cruising speed likewise (relative
standard deviation ``speed``). :func:`wander_profile` draws one such drive, seeded; the autopilot steers
towards the wandering offset at its look-ahead point. With no wander it drives exactly as before.

The environment and the recorder drive with :data:`DEFAULT_WANDER_M` and :data:`DEFAULT_SPEED_WANDER` unless
told otherwise (0 and 0 give the lane-exact drives of the versions before the drift). What the lateral figure
rests on: the standard deviation of lateral position (SDLP) that driving studies measure is of the order of
0.2 m on a highway for a driver told to hold the lane (the standardised on-the-road test: Verster & Roth 2011,
Int J Gen Med 4:359-371); 0.3 m allows for city streets, where lanes are wide for the speed and parked cars
and turns move the line. Speed: a tenth of the cruising speed, a driver in city traffic.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from satloc.geometry import Pose2
from satloc_env.world.route import REFERENCE_ROAD_M, Route

#: the autopilot's lateral drift (std, metres) and speed drift (relative std) by default (see the module docstring)
DEFAULT_WANDER_M = 0.3
DEFAULT_SPEED_WANDER = 0.1

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


@dataclass(frozen=True)
class Wander:
    """How far a driver drifts (see the module docstring); all zero: not at all."""

    lateral_m: float = 0.0      # standard deviation of the lateral position around the lane offset (metres)
    speed: float = 0.0          # relative standard deviation of the cruising speed
    scale_m: float = 30.0       # correlation length of both along the route (metres)
    max_lateral_m: float = 0.8  # the drift never exceeds this (a car in a 3.5 m lane)

    @property
    def active(self) -> bool:
        return self.lateral_m > 0 or self.speed > 0


def _smooth_process(length_m: float, scale_m: float, rng: np.random.Generator):
    """A smooth zero-mean process of unit standard deviation over [-scale_m, length_m + scale_m]: Gaussian
    values every scale_m / 3 metres, smoothed over neighbouring knots, through a cubic spline."""
    from scipy.interpolate import CubicSpline

    step = scale_m / 3.0
    s = np.arange(-scale_m, length_m + 2 * scale_m, step)
    v = rng.standard_normal(s.size + 4)
    v = np.convolve(v, np.array([1.0, 2.0, 3.0, 2.0, 1.0]) / 9.0, mode="valid")
    v = (v - v.mean()) / (v.std() or 1.0)
    return CubicSpline(s, v)


#: the spawn key of the episode seed sequence's child that seeds the drift when no seed is given (the revisit
#: change takes the first spawned child, key 0)
WANDER_SPAWN_KEY = 7919


def default_wander_seed(seed_seq) -> int:
    """The drift's seed of an episode whose seed sequence is ``seed_seq`` (a ``numpy.random.SeedSequence``, or
    the integer given to ``reset(seed=...)``): drawn from its child with the spawn key of its own
    :data:`WANDER_SPAWN_KEY`, so it depends neither on the change nor on the episode's other draws."""
    ss = seed_seq if isinstance(seed_seq, np.random.SeedSequence) else np.random.SeedSequence(int(seed_seq))
    child = np.random.SeedSequence(ss.entropy, spawn_key=tuple(ss.spawn_key) + (WANDER_SPAWN_KEY,))
    return int(np.random.default_rng(child).integers(2**31 - 1))


def wander_profile(length_m: float, wander: Wander, seed: int):
    """(lateral(s), speed_factor(s)): one seeded drive's drift in metres and its speed factor, as functions of
    the arc length ``s`` along a route of ``length_m`` (beyond its ends they hold their end values)."""
    rng = np.random.default_rng([int(seed), 7])
    lat, spd = _smooth_process(length_m, wander.scale_m, rng), _smooth_process(length_m, wander.scale_m, rng)

    def lateral(s: float) -> float:
        s = min(max(s, -wander.scale_m), length_m + wander.scale_m)
        return float(np.clip(wander.lateral_m * lat(s), -wander.max_lateral_m, wander.max_lateral_m))

    def speed_factor(s: float) -> float:
        s = min(max(s, -wander.scale_m), length_m + wander.scale_m)
        return float(np.clip(1.0 + wander.speed * spd(s), 0.5, 1.5))
    return lateral, speed_factor


#: half a car's width plus a margin (metres): on a road whose width the route knows, the drift never takes the
#: car's side beyond its edge
CAR_HALF_WIDTH_M = 1.0


def drift_at(route: Route, lane_offset: float, wander, s: float) -> float:
    """The lateral drift (metres, before the route's narrowing of offsets) of the profile ``wander`` at arc
    length ``s``, 0 without one. On a route that knows its road's width (``route.offset_scale``: routes over
    a road graph), clipped to the room between the lane and the road's edge for a car
    (:data:`CAR_HALF_WIDTH_M`): none where the car barely fits, as on a one-lane street; on routes without
    widths (generated scenes) the profile's own bound only."""
    if wander is None:
        return 0.0
    d = float(wander[0](s))
    if route.offset_scale is None:
        return d
    scale = float(np.interp(s, route.cum, route.offset_scale))
    room = max(0.0, (scale * (REFERENCE_ROAD_M / 2 - abs(lane_offset)) - CAR_HALF_WIDTH_M) / scale)
    return float(np.clip(d, -room, room))


class Autopilot:
    """Pure-pursuit route follower at a lateral lane offset: ``action = pilot.act(pose)``.

    Slows down before sharp turns. Keeps track of its progress ``s`` along the route so laps that overlap
    are not confused. With a ``wander`` profile (:func:`wander_profile`) it steers towards the lane offset
    plus the drift at its look-ahead point and cruises at the speed times the profile's factor.
    """

    def __init__(self, route: Route, lane_offset: float, speed: float = 8.0, lookahead: float = 6.0,
                 s0: float = 0.0, wander=None):
        self.route, self.offset, self.speed, self.lookahead = route, lane_offset, speed, lookahead
        self.s = s0
        self.wander = wander

    def follow(self, pose: Pose2) -> None:
        """Update the progress ``s`` along the route after the vehicle moved to ``pose``."""
        self.s, _ = self.route.project((pose.x, pose.y), s_hint=self.s, window=15.0)

    def act(self, pose: Pose2) -> np.ndarray:
        self.s, _ = self.route.project((pose.x, pose.y), s_hint=self.s, window=15.0)
        ahead = self.s + self.lookahead
        offset = self.offset + drift_at(self.route, self.offset, self.wander, ahead)
        target = self.route.pose_at(ahead, offset)
        local = pose.transform_inv(np.array([target.x, target.y]))
        ld2 = max(float(local @ local), 1e-6)
        curvature = 2.0 * local[1] / ld2
        turn = abs(self.route.curvature_ahead(self.s, 12.0))
        v = self.speed * (1.0 - 0.6 * min(1.0, turn / (math.pi / 2)))
        if self.wander is not None:
            v *= self.wander[1](self.s)
        return np.array([v, v * curvature], dtype=np.float32)

    @property
    def done(self) -> bool:
        return self.s >= self.route.length - 1.0


@dataclass(frozen=True)
class AttitudeParams:
    """A passenger car's body motion (``strength`` 1 of :class:`Attitude`): pitch and roll gradients (radians per
    m/s^2 of longitudinal and lateral acceleration), the suspension's time constant (s), and the ride's pitch
    and roll over the road surface (standard deviations, radians; correlation time, s)."""

    pitch_per_mps2: float = math.radians(0.35)
    roll_per_mps2: float = math.radians(0.5)
    tau_s: float = 0.25
    ride_pitch: float = math.radians(0.25)
    ride_roll: float = math.radians(0.15)
    ride_tau_s: float = 0.4
    max_accel_mps2: float = 8.0      # the accelerations the body feels are clipped to what tyres can give: the
                                     # bicycle model changes speed in one step

class Attitude:
    """The body's pitch and roll (radians; :func:`satloc_env.render.stereo.body_tilt`) as the car brakes,
    accelerates and turns (the accelerations through a first-order suspension) and rides the road (a smooth
    random process drawn from ``rng``), all scaled by ``strength``; 0: level, :attr:`tilt` None (the fixed
    mount)."""

    def __init__(self, strength: float, dt: float, rng: np.random.Generator, params: AttitudeParams = AttitudeParams()):
        self.strength, self.dt, self.rng, self.p = float(strength), float(dt), rng, params
        self._dyn = np.zeros(2)          # pitch, roll from the accelerations
        self._ride = np.zeros(2)         # unit-variance ride process
        self._speed: float | None = None

    @property
    def tilt(self) -> tuple[float, float] | None:
        """(pitch, roll) radians now, or None at strength 0."""
        if self.strength == 0.0:
            return None
        ride = self.strength * np.array([self.p.ride_pitch, self.p.ride_roll]) * self._ride
        return float(self._dyn[0] + ride[0]), float(self._dyn[1] + ride[1])

    def step(self, speed: float, yaw_rate: float) -> None:
        """Advance by one step at ``speed`` (m/s) and ``yaw_rate`` (rad/s)."""
        if self.strength == 0.0:
            return
        p = self.p
        accel = 0.0 if self._speed is None else (speed - self._speed) / self.dt
        self._speed = speed
        lim = p.max_accel_mps2
        accel, lateral = (float(np.clip(x, -lim, lim)) for x in (accel, speed * yaw_rate))
        target = self.strength * np.array([-p.pitch_per_mps2 * accel, p.roll_per_mps2 * lateral])
        self._dyn += (1.0 - math.exp(-self.dt / p.tau_s)) * (target - self._dyn)
        a = math.exp(-self.dt / p.ride_tau_s)
        self._ride = a * self._ride + math.sqrt(1 - a * a) * self.rng.standard_normal(2)
