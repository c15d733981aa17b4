"""Routes: polylines in map metres, driven at a lateral lane offset, possibly several laps."""
from __future__ import annotations

import math

import numpy as np

from satloc.geometry import Pose2, wrap_angle

#: the road width lateral offsets are given for: two lanes of 3.5 m (-1.75 m is the right lane's centre)
REFERENCE_ROAD_M = 7.0


class Route:
    """A polyline route. ``closed`` routes return to the first waypoint; ``laps`` repeats it.

    Arc length ``s`` runs over the whole drive (all laps). ``pose_at(s, offset)`` gives the pose at ``s``
    displaced ``offset`` metres to the left of the centre line (negative: to the right).

    A route that knows the road's width at its waypoints (``widths``, metres: routes over a road graph,
    :mod:`satloc_env.world.roadgraph`) narrows every lateral offset with the road: an offset is meant for a
    :data:`REFERENCE_ROAD_M` road and is scaled by ``min(1, width / 7 m)`` where the road is narrower, so
    the lane offset -1.75 m is the centre of the right lane (-width / 4) on any road up to 7 m wide.
    """

    def __init__(self, waypoints, closed: bool = False, laps: int = 1, name: str = "route", widths=None):
        pts = np.asarray(waypoints, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 2:
            raise ValueError(f"{name}: needs at least 2 waypoints [x, y], got shape {pts.shape}")
        scale = None
        if widths is not None:
            w = np.asarray(widths, dtype=np.float64)
            if w.shape != (len(pts),) or not np.all(np.isfinite(w) & (w > 0)):
                raise ValueError(f"{name}: widths: expected one road width > 0 (metres) per waypoint, got "
                                 f"{w.shape[0] if w.ndim == 1 else w.shape} for {len(pts)} waypoints")
            scale = np.minimum(1.0, w / REFERENCE_ROAD_M)
        if closed:
            pts = np.vstack([pts, pts[:1]])
            scale = None if scale is None else np.append(scale, scale[:1])
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        keep = np.concatenate([[True], seg > 1e-9])
        pts = pts[keep]
        scale = None if scale is None else scale[keep]
        if len(pts) < 2:
            raise ValueError(f"{name}: waypoints are all the same point")
        if laps > 1:
            if not closed:
                raise ValueError(f"{name}: laps > 1 needs a closed route")
            pts = np.vstack([pts] + [pts[1:]] * (laps - 1))
            scale = None if scale is None else np.concatenate([scale] + [scale[1:]] * (laps - 1))
        self.name = name
        self.closed = closed
        self.laps = laps
        self.points = pts
        self.offset_scale = scale   #: (N,) factor of lateral offsets at each point, None: 1 everywhere
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        self.cum = np.concatenate([[0.0], np.cumsum(seg)])
        self.headings = np.arctan2(np.diff(pts[:, 1]), np.diff(pts[:, 0]))

    @property
    def length(self) -> float:
        return float(self.cum[-1])

    def _seg(self, s: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(self.cum, s, side="right") - 1, 0, len(self.headings) - 1)

    def pose_at(self, s: float, offset: float = 0.0) -> Pose2:
        x, y, yaw = self.sample(np.array([s]), offset)[0]
        return Pose2(x, y, yaw)

    def sample(self, s: np.ndarray, offset: float = 0.0) -> np.ndarray:
        """(N, 3) [x, y, yaw] at arc lengths ``s``; the heading is that of the segment."""
        s = np.clip(np.asarray(s, dtype=np.float64), 0.0, self.length)
        i = self._seg(s)
        t = s - self.cum[i]
        h = self.headings[i]
        if self.offset_scale is not None:
            offset = offset * np.interp(s, self.cum, self.offset_scale)
        x = self.points[i, 0] + t * np.cos(h) - offset * np.sin(h)
        y = self.points[i, 1] + t * np.sin(h) + offset * np.cos(h)
        return np.stack([x, y, h], axis=1)

    def project(self, xy, s_hint: float | None = None, window: float = 30.0) -> tuple[float, float]:
        """Arc length and signed lateral offset (left positive) of the closest route point to ``xy``.

        With ``s_hint`` only segments within ``window`` metres of it are searched, so a lap is not confused
        with the next one.
        """
        p = np.asarray(xy, dtype=np.float64)
        a, b = self.points[:-1], self.points[1:]
        if s_hint is not None:
            sel = (self.cum[1:] >= s_hint - window) & (self.cum[:-1] <= s_hint + window)
            idx = np.flatnonzero(sel)
        else:
            idx = np.arange(len(a))
        ab = b[idx] - a[idx]
        l2 = np.maximum((ab ** 2).sum(1), 1e-12)
        t = np.clip(((p - a[idx]) * ab).sum(1) / l2, 0, 1)
        q = a[idx] + t[:, None] * ab
        d = np.linalg.norm(q - p, axis=1)
        k = int(np.argmin(d))
        j = idx[k]
        s = float(self.cum[j] + t[k] * math.sqrt(l2[k]))
        cross = ab[k, 0] * (p[1] - a[j, 1]) - ab[k, 1] * (p[0] - a[j, 0])
        return s, float(math.copysign(d[k], cross))

    def heading_at(self, s: float) -> float:
        return float(self.headings[self._seg(np.array([s]))[0]])

    def curvature_ahead(self, s: float, lookahead: float) -> float:
        """Heading change (radians, wrapped) between ``s`` and ``s + lookahead``."""
        return wrap_angle(self.heading_at(min(s + lookahead, self.length)) - self.heading_at(s))
