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

**Camber.** A real carriageway is not flat across either: it falls from its crown to its kerbs so that rain
runs off (a cross-fall of 1-2.5 %), and a car in its lane stands rolled by that fall. ``camber`` is that
cross-fall (a fraction; 0: none): over the layout's road (its ``road`` and ``lane_marking`` ground) the ground
is raised by ``camber`` x the distance to the road's nearest edge (at most :data:`CROWN_CAP_M`), so each
half of a street falls from its centre line to its kerb and a crossing is a low dome; off the road the ground is
the hills alone. :class:`Crown` holds those heights as a raster and the lines along which the ground's grid
must have vertices to draw them exactly (the edges and centre lines of axis-aligned streets, as the grid
generator lays them: a street at another angle is drawn through the grid's vertices only).

``relief_m`` and ``camber`` 0 (the default of every scene) is a plane: the world, its renders and every figure
are those of a flat world, bit for bit.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from satloc.errors import ConfigError

__all__ = ["Terrain", "Crown", "GROUND_STEP_M", "WHEELBASE_M", "TRACK_M", "CROWN_CAP_M"]

#: side (metres) of the squares of the ground grid over a terrain: a wave of the shortest wavelength drawn
#: (0.6 x ``wavelength_m``) departs from its chords by at most (pi x step / wavelength)^2 / 2 of its height
#: (0.5 % of the relief at 250 m)
GROUND_STEP_M = 12.8
#: the car under the cameras: front to rear axle, and left to right wheel (KITTI's VW Passat estate)
WHEELBASE_M, TRACK_M = 2.71, 1.55
_WAVES = 8
#: the crown rises with the distance from the road's edge up to this far in (metres): the centre of a street up
#: to 20 m wide, a flat top on a wider square
CROWN_CAP_M = 10.0
#: resolution (metres) of the crown's raster (bilinear between its samples: a ridge is blunted by about
#: camber x this / 2, 2 mm at 1 %)
_CROWN_MPP = 0.4
#: a column (row) boundary of the road mask is an edge line of the crown when the road starts or ends across
#: it along at least this fraction of the map's height (width): a street running the length of the map
_LINE_FRACTION = 0.25


@dataclass(frozen=True, eq=False)
class Crown:
    """The heights a road's camber adds (see the module docstring): ``offset`` (H, W) metres on a north-up
    raster of ``mpp`` metres over a map ``height_m`` tall, and ``xlines``, ``ylines`` (metres): the lines along
    which the heights' slope breaks (street edges and centre lines)."""

    offset: np.ndarray
    mpp: float
    height_m: float
    xlines: np.ndarray
    ylines: np.ndarray

    @classmethod
    def of(cls, labels: np.ndarray, mpp: float, camber: float, height_m: float | None = None) -> "Crown":
        """The crown of the road in ``labels`` (a north-up label raster of ``mpp`` metres) at cross-fall
        ``camber``."""
        from scipy import ndimage

        from satloc.labels import CLASS_ID

        road = np.isin(labels, (CLASS_ID["road"], CLASS_ID["lane_marking"]))
        rows, cols = road.shape
        height_m = rows * mpp if height_m is None else float(height_m)
        # distance from each road texel's centre to the nearest texel off the road, less the half texel to the
        # edge between them (scipy's exact transform: OpenCV's rounds differently with its thread count, so a
        # Ray worker's world differed from the same world built alone)
        dist = ndimage.distance_transform_edt(road) * mpp
        rise = float(camber) * np.clip(dist - mpp / 2, 0.0, CROWN_CAP_M)
        f = max(1, min(int(round(_CROWN_MPP / mpp)), rows // 2, cols // 2))   # (at least 2 x 2 samples)
        h, w = rows // f, cols // f
        offset = rise[:h * f, :w * f].reshape(h, f, w, f).mean(axis=(1, 3)).astype(np.float32)

        def lines(mask: np.ndarray, along: int) -> list[float]:
            """Texel boundaries (in texels from the raster's first column) where the road starts or ends
            along much of the other axis, and the centre lines (or the cap's lines) of the streets between."""
            change = (mask[:, 1:] != mask[:, :-1]).sum(axis=0)
            edges = np.flatnonzero(change >= _LINE_FRACTION * along) + 1.0
            out = list(edges)
            cap = CROWN_CAP_M / mpp
            for a, b in zip(edges[:-1], edges[1:]):
                mid = int((a + b) / 2)
                if mask[:, min(mid, mask.shape[1] - 1)].mean() >= _LINE_FRACTION:   # a street between the edges
                    half = min(cap, (b - a) / 2)
                    out += [a + half, b - half]
            return sorted(set(out))

        xlines = np.array(lines(road, rows)) * mpp
        ylines = height_m - np.array(lines(road.T, cols)) * mpp
        return cls(offset, f * mpp, height_m, np.unique(xlines), np.unique(ylines))

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The crown's heights (metres) at map points ``x``, ``y`` (bilinear; beyond the raster its edge)."""
        h, w = self.offset.shape
        u = np.clip(x / self.mpp - 0.5, 0.0, w - 1.0)
        v = np.clip((self.height_m - y) / self.mpp - 0.5, 0.0, h - 1.0)
        u0, v0 = np.minimum(np.floor(u).astype(np.int64), w - 2), np.minimum(np.floor(v).astype(np.int64), h - 2)
        fu, fv = u - u0, v - v0
        o = self.offset
        return ((o[v0, u0] * (1 - fu) + o[v0, u0 + 1] * fu) * (1 - fv)
                + (o[v0 + 1, u0] * (1 - fu) + o[v0 + 1, u0 + 1] * fu) * fv)


@dataclass(frozen=True)
class Terrain:
    """Gentle hills: heights with standard deviation ``relief_m`` (0: a plane), hills about ``wavelength_m``
    apart, drawn from ``seed``."""

    relief_m: float = 0.0
    wavelength_m: float = 250.0
    seed: int = 0
    camber: float = 0.0
    _w: tuple = field(default=(), init=False, repr=False, compare=False)
    #: the road's heights (:class:`Crown`), once a world laid the terrain under its layout (:meth:`with_crown`)
    crown: Crown | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self):
        for name, v, lo, hi in (("relief_m", self.relief_m, 0.0, 50.0), ("wavelength_m", self.wavelength_m, 20.0, 1e5),
                                ("camber", self.camber, 0.0, 0.05)):
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
        return float(self.relief_m) == 0.0 and self.crown is None

    def with_crown(self, crown: Crown | None) -> "Terrain":
        """This terrain with the road heights ``crown`` on top of its hills."""
        out = dataclasses.replace(self)   # (the crown is not an init field: not copied)
        object.__setattr__(out, "crown", crown)
        return out

    def height(self, x, y) -> np.ndarray:
        """The ground's height (metres) at map points ``x``, ``y`` (arrays of one shape)."""
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        if self.flat:
            return np.zeros(np.broadcast(x, y).shape)
        h = np.zeros(np.broadcast(x, y).shape)
        if float(self.relief_m) > 0.0:
            kx, ky, ph, amp = self._w
            h = np.tensordot(np.cos(x[..., None] * kx + y[..., None] * ky + ph), amp, axes=([-1], [0]))
        if self.crown is not None:
            h = h + self.crown.height(x, y)
        return h

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
        out = {"relief_m": float(self.relief_m), "wavelength_m": float(self.wavelength_m), "seed": int(self.seed)}
        if float(self.camber) > 0.0:
            out["camber"] = float(self.camber)
        return out
