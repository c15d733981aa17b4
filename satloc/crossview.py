"""Localization with no database: a stereo frame against the satellite map of a place no car has mapped.

The method of the paper needs a database drive through every place before it can localize there. This
module localizes from the satellite map alone, inside a prior such as a GPS fix gives (a position within
``radius_m``, a heading within ``yaw_deg``), with the bird's-eye comparison of :mod:`satloc.align`:

1. the query's ground pixels are warped to a bird's-eye view (BEV) of the ground ahead of the vehicle at the
   map's resolution, keeping only cells whose stereo depth agrees with the ground plane;
2. for each heading in the prior's range (every ``yaw_step_deg``), the satellite features are resampled in
   the vehicle frame of that heading around the prior's position, grown by the prior's radius, and the BEV
   is slid over them by masked normalised cross-correlation: the score of every position of the map's
   pixel grid inside the prior disc at once;
3. positions off the drivable area are left out (``drivable="semantic"``: where the satellite features' own
   semantic segmentation gives road, lane marking or parking at least ``drivable_min``, grown by
   ``drivable_margin_m``; ``"none"``: every position); the posterior over the rest is
   ``softmax(correlation / temperature)``, its ``top_k`` strongest kept; the answer is the best position,
   refined to sub-pixel by a parabola through its neighbours, at its heading.

Nothing here is learned from the place: the features are the shipped ones (RGB, edge potentials, FCN
semantics), computed on the ground image and on the satellite map alike. ``temperature`` shapes the
posterior, not the answer; it was chosen on calibration data (``fcn_train/town_a``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from .align import AlignConfig, BevAligner, _parabola_peak
from .dictionary import FrameDepth, SatelliteFeatures
from .errors import ConfigError
from .geometry import Pose2, StereoCamera, wrap_angle
from .labels import DRIVABLE, NUM_CLASSES

__all__ = ["Prior", "CrossViewConfig", "CrossViewResult", "CrossViewLocalizer", "drivable_from_features"]

#: the widest prior searched (metres): the correlation's cost grows with the square of the radius
MAX_RADIUS_M = 100.0


@dataclass(frozen=True)
class Prior:
    """Where the vehicle is believed to be: within ``radius_m`` of (``x``, ``y``) (map metres), heading within
    ``yaw_deg`` degrees of ``yaw`` (radians, counter-clockwise from east)."""

    x: float
    y: float
    yaw: float
    radius_m: float = 20.0
    yaw_deg: float = 10.0

    def __post_init__(self):
        for k in ("x", "y", "yaw", "radius_m", "yaw_deg"):
            v = getattr(self, k)
            if not isinstance(v, (int, float, np.floating, np.integer)) or not math.isfinite(float(v)):
                raise ConfigError(f"prior.{k}: expected a finite number, got {v!r}")
        if not 0 < self.radius_m <= MAX_RADIUS_M:
            raise ConfigError(f"prior.radius_m: expected metres in (0, {MAX_RADIUS_M:g}], got {self.radius_m!r}")
        if not 0 <= self.yaw_deg <= 180:
            raise ConfigError(f"prior.yaw_deg: expected degrees in [0, 180], got {self.yaw_deg!r}")


@dataclass(frozen=True)
class CrossViewConfig:
    yaw_step_deg: float = 2.0             # headings searched: the prior's heading +- yaw_deg in these steps
    drivable: str = "semantic"            # semantic | none (see the module docstring)
    drivable_min: float = 0.5             # drivable classes' probability at least this
    drivable_margin_m: float = 1.0        # the drivable area grown by this (the semantics' edges are soft)
    # posterior = softmax(correlation / temperature); 0.02 scored best on calibration data (fcn_train/town_a, 40
    # frames: mean log posterior mass within 1 m and 2 degrees of the truth -0.54, against -0.63 at 0.01 and -1.50
    # at 0.05; examples/crossview.py --temperatures)
    temperature: float = 0.02
    top_k: int = 256                      # posterior entries kept
    align: AlignConfig = field(default_factory=AlignConfig)   # the BEV: extent, channels, normalisation

    def __post_init__(self):
        if not 0 < self.yaw_step_deg <= 10:
            raise ConfigError(f"crossview.yaw_step_deg: expected degrees in (0, 10], got {self.yaw_step_deg!r}")
        if self.drivable not in ("semantic", "none"):
            raise ConfigError(f"crossview.drivable: expected 'semantic' or 'none', got {self.drivable!r}")
        if not 0 <= self.drivable_min <= 1 or self.drivable_margin_m < 0:
            raise ConfigError("crossview: drivable_min must lie in [0, 1] and drivable_margin_m be >= 0")
        if not self.temperature > 0 or self.top_k < 1:
            raise ConfigError("crossview: temperature must be > 0 and top_k >= 1")


@dataclass
class CrossViewResult:
    """One frame's answer: the estimate (None where too little ground is seen or no position of the prior is
    drivable), its correlation, the posterior (``candidates`` (K, 3) x, y, yaw with ``posterior`` (K,),
    summing to 1 over the positions searched, the ``top_k`` strongest kept) and the BEV cells seen."""

    pose: Pose2 | None
    correlation: float
    candidates: np.ndarray
    posterior: np.ndarray
    cells: int


def drivable_from_features(satfeat: SatelliteFeatures, min_prob: float = 0.5, margin_m: float = 1.0) -> np.ndarray:
    """(H, W) bool: where the satellite features' semantic channels (the default extractor's: RGB, edge, then
    one probability per class of :mod:`satloc.labels`) give the drivable classes at least ``min_prob``, grown
    by ``margin_m``. ConfigError for features without semantic channels."""
    f = satfeat.features
    if f.shape[2] != 4 + NUM_CLASSES:
        raise ConfigError(f"crossview.drivable 'semantic' needs the default features (RGB, edge and {NUM_CLASSES} "
                          f"class probabilities), got {f.shape[2]} channels; use drivable: none")
    p = sum(f[..., 4 + c].astype(np.float32) for c in DRIVABLE)
    mask = (p >= min_prob).astype(np.uint8)
    r = int(round(margin_m / satfeat.meters_per_pixel))
    if r > 0:
        mask = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    return mask.astype(bool)


class CrossViewLocalizer:
    """Localize stereo frames against ``satfeat`` within a :class:`Prior`, with no database (see the module
    docstring). ``extractor`` computes the ground image's features (the one that made ``satfeat``);
    ``drivable``: a (H, W) bool mask of the map's pixels where the vehicle may be (None: as
    ``config.drivable`` says)."""

    def __init__(self, camera: StereoCamera, satfeat: SatelliteFeatures, extractor, config: CrossViewConfig = CrossViewConfig(),
                 drivable: np.ndarray | None = None):
        self.camera, self.satfeat, self.extractor, self.config = camera, satfeat, extractor, config
        h, w = satfeat.features.shape[:2]
        if drivable is not None:
            drivable = np.asarray(drivable, bool)
            if drivable.shape != (h, w):
                raise ConfigError(f"crossview: the drivable mask is {drivable.shape}, the map {(h, w)}")
        elif config.drivable == "semantic":
            drivable = drivable_from_features(satfeat, config.drivable_min, config.drivable_margin_m)
        self.drivable = drivable
        self.depth = FrameDepth(camera)
        self._aligner = BevAligner(camera, satfeat.features, satfeat.meters_per_pixel, satfeat.origin, config.align)
        self._searchers: dict[float, BevAligner] = {}
        from .features import BilateralRGB

        if config.align.channels == "gray" and getattr(extractor, "name", "") not in ("default", "rgb"):
            raise ConfigError(f"crossview: channels 'gray' compare the bilateral RGB that the 'default' and 'rgb' "
                              f"features start with; the extractor is {getattr(extractor, 'name', '?')!r}")
        self._rgb = BilateralRGB()

    def _searcher(self, radius_m: float) -> BevAligner:
        """The aligner whose satellite crop is grown by ``radius_m`` (the normalised map shared)."""
        key = round(float(radius_m), 3)
        s = self._searchers.get(key)
        if s is None:
            s = self._searchers[key] = self._aligner.with_search(key)
        return s

    def localize(self, frame, prior: Prior) -> CrossViewResult:
        """The pose of ``frame`` (a :class:`satloc.sequence.Frame` with left image and stereo or depth) within
        ``prior``."""
        if not isinstance(prior, Prior):
            raise ConfigError(f"crossview: prior must be a satloc.crossview.Prior, got {type(prior).__name__}")
        sf = self.satfeat
        h, w = sf.features.shape[:2]
        x0, y1 = sf.origin
        if not (x0 - prior.radius_m <= prior.x <= x0 + w * sf.meters_per_pixel + prior.radius_m
                and y1 - h * sf.meters_per_pixel - prior.radius_m <= prior.y <= y1 + prior.radius_m):
            raise ConfigError(f"crossview: the prior ({prior.x:.1f}, {prior.y:.1f}) m +- {prior.radius_m:g} m lies "
                              f"outside the satellite map (x {x0:g} to {x0 + w * sf.meters_per_pixel:g}, y "
                              f"{y1 - h * sf.meters_per_pixel:g} to {y1:g} m)")
        depth = self.depth(frame, "query frame")
        # the gray channel alone needs no network: the bilateral RGB the default features start with
        feats = self._rgb(frame.left, "ground") if self.config.align.channels == "gray" else \
            self.extractor(frame.left, "ground")
        al = self._searcher(prior.radius_m)
        chans, mask = al.bev(feats, depth)
        cells = int(mask.sum())
        empty = CrossViewResult(None, float("nan"), np.zeros((0, 3)), np.zeros(0), cells)
        if cells < self.config.align.min_cells:
            return empty
        n = int(math.floor(prior.yaw_deg / self.config.yaw_step_deg + 1e-9))
        offsets = self.config.yaw_step_deg * np.arange(-n, n + 1)
        res, m = al.res, al.margin
        # the surface's cells as offsets in the vehicle frame of each heading (every heading's surface has the
        # same shape), and which lie in the prior's disc
        ii, jj = np.mgrid[0:2 * m + 1, 0:2 * m + 1]
        dx, dy = (ii - m) * res, (jj - m) * res
        in_disc = (dx * dx + dy * dy) <= prior.radius_m ** 2
        xs, ys, yaws, scores, surfaces = [], [], [], [], []
        for dyaw in offsets:
            yaw = wrap_angle(prior.yaw + math.radians(float(dyaw)))
            crop = al._crop(Pose2(prior.x, prior.y, yaw))
            r = sum(cv2.matchTemplate(c, t, cv2.TM_CCOEFF_NORMED, mask=mask) for c, t in zip(crop, chans)) / len(chans)
            r = np.nan_to_num(r, nan=-1.0, posinf=-1.0, neginf=-1.0)
            c, s = math.cos(yaw), math.sin(yaw)
            wx, wy = prior.x + c * dx - s * dy, prior.y + s * dx + c * dy
            ok = in_disc.copy()
            if self.drivable is not None:
                flat, inside = sf.pixel_index(np.stack([wx, wy], -1))
                ok &= inside & self.drivable.reshape(-1)[np.maximum(flat, 0)]
            xs.append(wx[ok])
            ys.append(wy[ok])
            yaws.append(np.full(int(ok.sum()), yaw))
            scores.append(r[ok])
            surfaces.append((r, ok, yaw))
        score = np.concatenate(scores)
        if score.size == 0:
            return empty
        # the answer: the best position, sub-pixel on its heading's surface
        best = int(np.argmax([sc.max() if sc.size else -np.inf for sc in scores]))
        r, ok, yaw = surfaces[best]
        i, j = np.unravel_index(int(np.argmax(np.where(ok, r, -np.inf))), r.shape)
        di = _parabola_peak(r[i - 1, j], r[i, j], r[i + 1, j]) if 0 < i < r.shape[0] - 1 else 0.0
        dj = _parabola_peak(r[i, j - 1], r[i, j], r[i, j + 1]) if 0 < j < r.shape[1] - 1 else 0.0
        dx, dy = (i + di - m) * res, (j + dj - m) * res
        c, s = math.cos(yaw), math.sin(yaw)
        pose = Pose2(prior.x + c * dx - s * dy, prior.y + s * dx + c * dy, yaw)
        # the posterior over every position searched, its strongest entries kept
        z = (score - score.max()) / self.config.temperature
        p = np.exp(z)
        p /= p.sum()
        keep = np.argsort(-p, kind="stable")[: self.config.top_k]
        cand = np.stack([np.concatenate(xs)[keep], np.concatenate(ys)[keep], np.concatenate(yaws)[keep]], 1)
        return CrossViewResult(pose, float(r[i, j]), cand, p[keep], cells)
