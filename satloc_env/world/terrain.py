"""Ground that is not a plane: gentle hills under a world, and the tilt of a car standing on them.

A :class:`Terrain` is a smooth height field ``h(x, y)`` (metres, map frame) drawn from a seed: a sum of a few
long plane waves in random directions, of wavelengths around ``wavelength_m`` and with heights whose standard
deviation over the map is ``relief_m``. Its slopes are those of real streets on rolling ground: at 1.5 m over
250 m (seed 7, a 360 m square) the grade has a standard deviation of 1.6 %, 6.7 % at the 95th percentile.

What stands on it (:func:`satloc_env.world.meshes.build_world`): the ground is a grid of :data:`GROUND_STEP_M`
squares whose corners lie on ``h``; trees, parked cars, street furniture and an episode's moving objects follow
the ground under each of their vertices (the slopes are a few percent, so they lean imperceptibly); a building
stands level on the lowest point of its footprint, its walls running into the ground uphill. The car that
carries the cameras stands on ``h`` too: its body is lifted to the ground under it and pitched and rolled to
the plane through the ground under its four wheels (:meth:`Terrain.tilt`), on top of the body's own motion
(:class:`satloc_env.envs.vehicle.Attitude`). So a camera looks at ground that is neither level nor in the
plane of its car's wheels ahead, and the bird's-eye homography every method uses is no longer exact.

The satellite tile is a true orthophoto of the same ground (the capture paints the layout seen straight from
above, which is what orthorectification over a height field gives): its pixels stay where they are.

``relief_m`` 0 (the default of every scene) is a plane: the world, its renders and every figure are those of
a flat world, bit for bit.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from satloc.errors import ConfigError

__all__ = ["Terrain", "GROUND_STEP_M", "WHEELBASE_M", "TRACK_M"]

#: side (metres) of the squares of the ground grid over a terrain: a wave of the shortest wavelength drawn
#: (0.6 x ``wavelength_m``) departs from its chords by at most (pi x step / wavelength)^2 / 2 of its height
#: (0.5 % of the relief at 250 m)
GROUND_STEP_M = 12.8
#: the car under the cameras: front to rear axle, and left to right wheel (KITTI's VW Passat estate)
WHEELBASE_M, TRACK_M = 2.71, 1.55
_WAVES = 8


@dataclass(frozen=True)
class Terrain:
    """Gentle hills: heights with standard deviation ``relief_m`` (0: a plane), hills about ``wavelength_m``
    apart, drawn from ``seed``."""

    relief_m: float = 0.0
    wavelength_m: float = 250.0
    seed: int = 0
    _w: tuple = field(default=(), init=False, repr=False, compare=False)

    def __post_init__(self):
        for name, v, lo, hi in (("relief_m", self.relief_m, 0.0, 50.0), ("wavelength_m", self.wavelength_m, 20.0, 1e5)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not lo <= float(v) <= hi:
                raise ConfigError(f"terrain.{name}: expected a number from {lo:g} to {hi:g}, got {v!r}")
        rng = np.random.default_rng([int(self.seed), 7331])
        angle = rng.uniform(0, 2 * math.pi, _WAVES)
        k = 2 * math.pi / (float(self.wavelength_m) * rng.uniform(0.6, 1.6, _WAVES))
        # each wave's variance is a^2 / 2, so K waves of amplitude relief * sqrt(2 / K) have the relief's
        amp = float(self.relief_m) * math.sqrt(2.0 / _WAVES) * np.ones(_WAVES)
        object.__setattr__(self, "_w", (k * np.cos(angle), k * np.sin(angle), rng.uniform(0, 2 * math.pi, _WAVES),
                                        amp))

    @property
    def flat(self) -> bool:
        return float(self.relief_m) == 0.0

    def height(self, x, y) -> np.ndarray:
        """The ground's height (metres) at map points ``x``, ``y`` (arrays of one shape)."""
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        if self.flat:
            return np.zeros(np.broadcast(x, y).shape)
        kx, ky, ph, amp = self._w
        return np.tensordot(np.cos(x[..., None] * kx + y[..., None] * ky + ph), amp, axes=([-1], [0]))

    def tilt(self, x: float, y: float, yaw: float) -> tuple[float, float, float]:
        """Where a car standing at ``(x, y)`` heading ``yaw`` has its body: (height of its origin, pitch, roll)
        in the conventions of :func:`satloc_env.render.stereo.body_tilt` (pitch positive nose down, roll
        positive left side up), from the plane through the ground under its four wheels."""
        if self.flat:
            return 0.0, 0.0, 0.0
        c, s = math.cos(yaw), math.sin(yaw)
        fx, fy, lx, ly = c * WHEELBASE_M / 2, s * WHEELBASE_M / 2, -s * TRACK_M / 2, c * TRACK_M / 2
        px = np.array([x + fx + lx, x + fx - lx, x - fx + lx, x - fx - lx])
        py = np.array([y + fy + ly, y + fy - ly, y - fy + ly, y - fy - ly])
        h = self.height(px, py)                        # front left, front right, rear left, rear right
        grade = ((h[0] + h[1]) - (h[2] + h[3])) / 2 / WHEELBASE_M
        cross = ((h[0] + h[2]) - (h[1] + h[3])) / 2 / TRACK_M
        return float(h.mean()), -math.atan(grade), math.atan(cross)

    def to_dict(self) -> dict:
        return {"relief_m": float(self.relief_m), "wavelength_m": float(self.wavelength_m), "seed": int(self.seed)}
