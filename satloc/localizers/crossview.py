"""Localization with no database: a stereo frame against the satellite map of a place no car has mapped.

The method of the paper needs a database drive through every place before it can localize there. This
module localizes from the satellite map alone, inside a prior such as a GPS fix gives (a position within
``radius_m``, a heading within ``yaw_deg``), with the bird's-eye comparison of :mod:`satloc.tracking.align`:

1. the query's ground pixels are warped to a bird's-eye view (BEV) of the ground ahead of the vehicle at the
   map's resolution, keeping only cells whose stereo depth agrees with the ground plane;
2. for each heading in the prior's range (every ``yaw_step_deg``), the satellite features are resampled in
   the vehicle frame of that heading around the prior's position, grown by the prior's radius, and the BEV
   is slid over them by masked normalised cross-correlation: the score of every position of the map's
   pixel grid inside the prior disc at once;
3. positions off the drivable area are left out (``drivable="semantic"``: where the satellite features' own
   semantic segmentation gives road, lane marking or parking at least ``drivable_min``, grown by
   ``drivable_margin_m``; ``"labels"``: where the map's label raster or road vectors say so (a mask given to
   the localizer: :func:`drivable_from_labels`, :func:`drivable_from_roads`); ``"none"``: every position); the posterior over the rest is
   ``softmax(correlation / temperature)``, its ``top_k`` strongest kept; the answer is the best position,
   refined to sub-pixel by a parabola through its neighbours, at its heading.

Nothing here is learned from the place: the features are the shipped ones (RGB, edge potentials, FCN
semantics), computed on the ground image and on the satellite map alike. ``temperature`` shapes the
posterior, not the answer; it was chosen on calibration data (``fcn_train/town_a``).

Over a sequence, :class:`CrossViewTracker` carries the previous answer, moved by the odometry since its frame,
to the next: with ``track="fuse"`` (the default) the frame's whole prior is searched and the moved answer
multiplies the posterior as a Gaussian belief (``track_sigma_m``, widened by ``track_sigma_per_m`` times the
distance travelled since the track's last answer, and ``track_sigma_deg``), so a strong match elsewhere can
still win; with ``"gate"`` only ``track_radius_m`` / ``track_yaw_deg`` around it are searched. Where the moved
answer lies outside the frame's own prior by more than the belief reaches (3 sigma; ``gate``:
``track_radius_m``: the GPS fix says the track is lost), after a frame with no
answer or after an unknown motion, the prior alone is searched (with ``hold_motion``, the last motion measured
moves the track meanwhile, a fallback for the frames that have no answer of their own). A frame it cannot
localize (too little ground in view, no drivable position within its prior) coasts on the odometry (``coast``):
its answer is the moved track, with no correlation (NaN). :func:`localize_frames` runs either over the frames of a
sequence.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..config import added_field
from ..errors import ConfigError
from ..features.dictionary import FrameDepth, SatelliteFeatures
from ..geometry import Pose2, StereoCamera, wrap_angle
from ..labels import CLASS_ID, DRIVABLE, NUM_CLASSES
from ..tracking.align import AlignConfig, BevAligner, _parabola_peak
from .gnss import draw_prior
from .interface import MAX_RADIUS_M, Prior

__all__ = ["Prior", "CrossViewConfig", "CrossViewResult", "CrossViewLocalizer", "CrossViewTracker", "prior_on_map",
           "draw_prior", "drivable_from_features", "drivable_from_labels", "drivable_from_roads", "localize_frames", "parse_prior",
           "NoDatabaseLocalizer"]

#: the shipped learned channels (``CrossViewConfig(projections="shipped")``; ``crossview_report.json`` beside it
#: says what they were trained on and how)
SHIPPED_PROJECTIONS = str(Path(__file__).resolve().parent.parent / "weights" / "crossview.pt")


@dataclass(frozen=True)
class CrossViewConfig:
    yaw_step_deg: float = 2.0             # headings searched: the prior's heading +- yaw_deg in these steps
    # auto | semantic | labels | none (see the module docstring); auto: labels where the localizer is given the
    # map's label raster (road vectors), else none. Labels and semantic gave the same answers on the generated
    # calibration place (fcn_train/town_a, 60 frames); on the real calibration place (scenes/real/vienna_schoenbrunn,
    # 351 localizations) the FCN's semantic mask, trained on the generator's tiles, left 0.9 % of them with a
    # drivable position, no mask answered all (median 2.18 m single, 2.65 m tracked mean; the roads' labels 1.47 m
    # and 1.90 m): on a bare map, the semantics are not used unless asked for (docs/results.md)
    drivable: str = "auto"
    drivable_min: float = 0.5             # drivable classes' probability at least this
    drivable_margin_m: float = 1.0        # the drivable area grown by this (the semantics' edges are soft)
    # posterior = softmax(correlation / temperature); 0.02 scored best on calibration data (fcn_train/town_a, 40
    # frames: mean log posterior mass within 1 m and 2 degrees of the truth -0.54, against -0.63 at 0.01 and -1.50
    # at 0.05; examples/crossview.py --temperatures)
    temperature: float = 0.02
    top_k: int = 256                      # posterior entries kept
    # learned channels (satloc.features.crossview_learn, `satloc train-crossview`): a crossview.pt file, or "shipped" (the
    # package's, trained on calib/town_b, suburb_a, suburb_b at the default world: the default); None: the grey
    # level. On calibration data (fcn_train/town_a, 60 frames) the first learned ones (trained on the plain world)
    # gave single frames 1.46 m mean, 92 % within 1 m against the grey level's 1.82 m, 88 %, tracked 0.43 against
    # 0.51 m, at 0.16 against 0.08 s per frame; those retrained at the default world beat them on calib/town_a
    # (tracked 0.91 -> 0.60 m) and tie on Vienna (docs/method.md, docs/results.md)
    projections: str | None = "shipped"
    # CrossViewTracker: "fuse" searches the whole prior with the previous answer moved by the odometry as a
    # Gaussian belief of track_sigma_m / track_sigma_deg; "gate" searches track_radius_m / track_yaw_deg around it.
    # Chosen on calibration data (fcn_train/town_a, 60 frames ~12 m apart, visual odometry, examples/crossview.py
    # --track): mean error gate 0.67 m; fuse sigma 2 m 0.51, 3 m 0.52, 5 m 0.75, 8 m 1.32. The belief widens with
    # the distance d travelled since the track's last answer: sigma = hypot(track_sigma_m, track_sigma_per_m * d)
    # (track_sigma_per_m 0: a fixed sigma, the behaviour before, with track_sigma_m 2). At the default world
    # (calib/town_a, docs/tools/capture_calibration.py --tracked; docs/results.md) a fixed sigma of 0.5 / 1 / 2 m
    # gave 0.52 / 0.51 / 1.05 m tracked on every frame (1.5 m apart, as an environment localizing each step) and
    # 1.07 / 0.57 / 0.60 m on frames 12.4 m apart (3 m: 1.10): 1 m where the frames are near, and 0.14 per metre
    # keeps 2 m at 12.4 m, the spacing sigma 2 was first chosen at
    track: str = "fuse"
    track_radius_m: float = 5.0
    track_yaw_deg: float = 4.0
    track_sigma_m: float = 1.0
    track_sigma_per_m: float = added_field(0.14, before=0.0)
    track_sigma_deg: float = 3.0
    # a fix whose disc the moved answer lies beyond (by more than the belief reaches) says the track is lost; with a
    # receiver whose error persists and now and then outgrows the disc (satloc.localizers.gnss, model "receiver"),
    # the track counts as lost only once the fixes have disagreed with it for longer than this many seconds (the
    # frames' timestamps); meanwhile it goes on around the moved answer. 0: at the first such fix (the default before).
    # Chosen on calibration data (fcn_train/town_a, docs/tools/gnss_calibration.py): on the 8 receiver passes of
    # 23 that put the truth outside the prior, tracked mean 5.04 m at 0 s, 3.21 at 10, 1.04 at 30, 60 and 120 s;
    # under the uniform prior 0.51 m at 0 and at 30 s
    lost_after_s: float = added_field(30.0, before=0.0)
    # a prior that reports its accuracy (Prior.sigma_m: a receiver's fix) weighs each position by a Student t density
    # of that scale around its centre, with fix_nu degrees of freedom (heavy tails: the fix may be misled by
    # multipath); a prior without one is flat within its radius
    fix_nu: float = added_field(3.0)
    # a tracked frame that cannot be localized (too little ground in view: a bus in front; or no drivable position
    # within its prior) coasts: its answer is the track moved by the odometry, and the track goes on. False: the
    # frame has no answer and the track is lost (the behaviour before; an occluded frame then counted as a gross
    # failure, and the next frame searched its prior alone)
    coast: bool = added_field(True, before=False)
    # an unknown motion (the odometry failed: visual odometry with too few features, as with a bus filling the view)
    # moves a tracked belief by the last motion measured, for at most this many steps in a row (a constant-velocity
    # model), as a fallback only: the next frames search their prior alone and take the moved track only where they
    # have no answer of their own (then they coast on it); after that the track is lost. 0: lost at the first
    # unknown motion (the behaviour before). On the real calibration place (scenes/real/vienna_schoenbrunn,
    # docs/tools/capture_calibration.py, 351 tracked localizations) 0, 1, 2 and 4 give the same answers (every frame
    # there has one of its own); used as the track's belief instead, a held motion had cost 0.38 -> 0.41 m (1 step)
    # and 0.50 m (2 steps), hence a fallback only. 2: a bus in view for two query steps (docs/results.md)
    hold_motion: int = added_field(2, before=0)
    # map pixels whose label (the map's label raster, where the localizer is given one) is one of these classes are
    # set to the normalised channels' local mean (0) before the correlation. The bird's-eye view holds the ground
    # alone, and what stands above the ground hides the road beneath it in a view from above, the more so off nadir
    # (a capture's lean moves a 29 m roof 7.7 m over the street on city). Not neutral: matchTemplate still counts
    # the zeros in the crop's mean and energy, so a position whose ground falls on hidden pixels scores lower.
    # Off by default: it needs a segmentation of the map image itself (roofs where the image shows them, not
    # building footprints), which a simulated capture's labels give exactly and a real map does not come with.
    # With those exact labels, on calib/town_a (261 localizations, docs/tools/capture_calibration.py) single /
    # tracked mean 3.19 / 0.59 m with none, 3.07 / 0.55 m with [building], 2.97 / 0.51 m with [building, tree]
    # (docs/results.md)
    hidden_classes: tuple[str, ...] = added_field(())
    # where hidden_classes are read: "labels", the map's label raster (nothing hidden without one); "semantic", the
    # satellite features' own class probabilities (the FCN's, the default extractor's), a pixel hidden where those
    # classes together reach drivable_min: what a bare GeoTIFF allows. On calib/town_a the semantics gained nothing
    # (single / tracked 3.15 / 0.64 m with [building, tree], against 3.19 / 0.59 m with none; docs/results.md)
    hidden_from: str = added_field("labels")
    align: AlignConfig = field(default_factory=AlignConfig)   # the BEV: extent, channels, normalisation

    def __post_init__(self):
        if not 0 < self.yaw_step_deg <= 10:
            raise ConfigError(f"crossview.yaw_step_deg: expected degrees in (0, 10], got {self.yaw_step_deg!r}")
        if self.drivable not in ("auto", "semantic", "labels", "none"):
            raise ConfigError(f"crossview.drivable: expected 'auto', 'semantic', 'labels' or 'none', got "
                              f"{self.drivable!r}")
        if not 0 <= self.drivable_min <= 1 or self.drivable_margin_m < 0:
            raise ConfigError("crossview: drivable_min must lie in [0, 1] and drivable_margin_m be >= 0")
        if not self.temperature > 0 or self.top_k < 1:
            raise ConfigError("crossview: temperature must be > 0 and top_k >= 1")
        if self.track not in ("gate", "fuse"):
            raise ConfigError(f"crossview.track: expected 'gate' or 'fuse', got {self.track!r}")
        if not self.track_sigma_m > 0 or not self.track_sigma_deg > 0:
            raise ConfigError("crossview: track_sigma_m and track_sigma_deg must be > 0")
        if not (self.track_sigma_per_m >= 0 and math.isfinite(self.track_sigma_per_m)):
            raise ConfigError(f"crossview.track_sigma_per_m: expected metres per metre travelled >= 0, got "
                              f"{self.track_sigma_per_m!r}")
        if not (self.fix_nu > 0 and math.isfinite(self.fix_nu)):
            raise ConfigError(f"crossview.fix_nu: expected degrees of freedom > 0, got {self.fix_nu!r}")
        if isinstance(self.hold_motion, bool) or not isinstance(self.hold_motion, int) or self.hold_motion < 0:
            raise ConfigError(f"crossview.hold_motion: expected a whole number of steps >= 0, got {self.hold_motion!r}")
        if not (self.lost_after_s >= 0 and math.isfinite(self.lost_after_s)):
            raise ConfigError(f"crossview.lost_after_s: expected seconds >= 0, got {self.lost_after_s!r}")
        hidden = self.hidden_classes
        if not isinstance(hidden, (list, tuple)) or not all(isinstance(c, str) and c in CLASS_ID for c in hidden):
            raise ConfigError(f"crossview.hidden_classes: expected a list of classes among {list(CLASS_ID)}, got "
                              f"{hidden!r}")
        object.__setattr__(self, "hidden_classes", tuple(sorted(set(hidden))))
        if self.hidden_from not in ("labels", "semantic"):
            raise ConfigError(f"crossview.hidden_from: expected 'labels' or 'semantic', got {self.hidden_from!r}")
        if not 0 < self.track_radius_m <= MAX_RADIUS_M or not 0 <= self.track_yaw_deg <= 180:
            raise ConfigError(f"crossview: track_radius_m must lie in (0, {MAX_RADIUS_M:g}] m and track_yaw_deg in "
                              f"[0, 180] degrees")


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
    p = _class_probability(satfeat, DRIVABLE, "drivable", "; use drivable: none")
    return _grown(p >= min_prob, margin_m, satfeat.meters_per_pixel)


def _class_probability(satfeat: SatelliteFeatures, classes, field: str, hint: str = "") -> np.ndarray:
    """(H, W) float32: the satellite features' semantic probabilities of ``classes`` (class ids) summed. ConfigError
    naming ``crossview.<field>`` for features without the default extractor's semantic channels."""
    f = satfeat.features
    if f.shape[2] != 4 + NUM_CLASSES:
        raise ConfigError(f"crossview.{field} 'semantic' needs the default features (RGB, edge and {NUM_CLASSES} "
                          f"class probabilities), got {f.shape[2]} channels{hint}")
    return sum(f[..., 4 + c].astype(np.float32) for c in classes)


def _grown(mask: np.ndarray, margin_m: float, meters_per_pixel: float) -> np.ndarray:
    """(H, W) bool ``mask`` grown by ``margin_m`` (a disc)."""
    m = mask.astype(np.uint8)
    r = int(round(margin_m / meters_per_pixel))
    if r > 0:
        m = cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    return m.astype(bool)


def drivable_from_labels(labels: np.ndarray, satfeat: SatelliteFeatures, margin_m: float = 1.0) -> np.ndarray:
    """(H, W) bool: where a label raster of the map (``SatelliteMap.labels``: one class of :mod:`satloc.labels`
    per pixel, as road vectors give it, e.g. rasterized from OpenStreetMap) holds a drivable class (road, lane
    marking, parking), grown by ``margin_m``. ConfigError when it does not match the map or holds no road."""
    lab = np.asarray(labels)
    if lab.shape != satfeat.features.shape[:2]:
        raise ConfigError(f"crossview.drivable 'labels': the label raster is {lab.shape}, the map "
                          f"{satfeat.features.shape[:2]}")
    mask = np.isin(lab, DRIVABLE)
    if not mask.any():
        raise ConfigError("crossview.drivable 'labels': the map's labels hold no road, lane marking or parking")
    return _grown(mask, margin_m, satfeat.meters_per_pixel)


def drivable_from_roads(lines, widths, satfeat: SatelliteFeatures, margin_m: float = 1.0) -> np.ndarray:
    """(H, W) bool: the map's pixels within half a road's width plus ``margin_m`` of its centre line; ``lines``:
    (N_i, 2) arrays of points in the map's metres (e.g. :meth:`satloc.geodata.vectors.RoadLines.to_frame`),
    ``widths``: each road's width (metres). ConfigError when no line crosses the map."""
    h, w = satfeat.features.shape[:2]
    mask = np.zeros((h, w), np.uint8)
    x0, y1 = satfeat.origin
    mpp = satfeat.meters_per_pixel
    for xy, width in zip(lines, widths):
        xy = np.asarray(xy, np.float64)
        px = np.stack([(xy[:, 0] - x0) / mpp - 0.5, (y1 - xy[:, 1]) / mpp - 0.5], 1)   # pixel centres
        if not np.all(np.isfinite(px)):
            continue
        px = np.clip(px, -1e5, 1e5)
        thick = max(1, int(round((float(width) + 2 * margin_m) / mpp)))
        cv2.polylines(mask, [np.round(px * 16).astype(np.int32).reshape(-1, 1, 2)], False, 1, thick, cv2.LINE_8, 4)
    if not mask.any():
        raise ConfigError("crossview: no road line crosses the satellite map (are the roads in the map's frame?)")
    return mask.astype(bool)


class CrossViewLocalizer:
    """Localize stereo frames against ``satfeat`` within a :class:`Prior`, with no database (see the module
    docstring). ``extractor`` computes the ground image's features (the one that made ``satfeat``);
    ``drivable``: a (H, W) bool mask of the map's pixels where the vehicle may be; ``labels``: the map's label
    raster (``SatelliteMap.labels``), for ``config.drivable`` ``"labels"`` or ``"auto"``; ``projections``: the
    learned channels ``config.projections`` names, when the caller has read them already."""

    def __init__(self, camera: StereoCamera, satfeat: SatelliteFeatures, extractor, config: CrossViewConfig = CrossViewConfig(),
                 drivable: np.ndarray | None = None, labels: np.ndarray | None = None, projections=None):
        self.camera, self.satfeat, self.extractor, self.config = camera, satfeat, extractor, config
        h, w = satfeat.features.shape[:2]
        mode = config.drivable
        if mode == "auto":
            mode = "labels" if (drivable is not None or labels is not None) else "none"
        if drivable is not None and mode != "none":
            drivable = np.asarray(drivable, bool)
            if drivable.shape != (h, w):
                raise ConfigError(f"crossview: the drivable mask is {drivable.shape}, the map {(h, w)}")
        elif mode == "semantic":
            drivable = drivable_from_features(satfeat, config.drivable_min, config.drivable_margin_m)
        elif mode == "labels":
            if labels is None:
                raise ConfigError("crossview.drivable 'labels': give the map's label raster (labels=) or a mask "
                                  "(drivable=, e.g. drivable_from_roads of its road vectors)")
            drivable = drivable_from_labels(labels, satfeat, config.drivable_margin_m)
        else:
            drivable = None
        self.drivable_source = mode
        self.drivable = drivable
        self.depth = FrameDepth(camera)
        self.projections = None
        sat, align = satfeat.features, config.align
        if config.projections is not None:
            from dataclasses import replace

            from ..features.crossview_channels import CrossViewProjections

            # ``projections``: the ones config.projections names, read already (e.g. from a plain copy)
            self.projections = projections if projections is not None else CrossViewProjections.load(
                SHIPPED_PROJECTIONS if config.projections == "shipped" else config.projections)
            sat, align = self.projections.satellite(satfeat.features), replace(config.align, channels="learned")
        self._aligner = BevAligner(camera, sat, satfeat.meters_per_pixel, satfeat.origin, align)
        # the map's pixels of hidden_classes: the normalised channels set to their local mean, 0 (a penalty where a
        # position's ground falls on them, not an exclusion: see CrossViewConfig.hidden_classes)
        self.hidden: np.ndarray | None = None
        hidden, ids = None, [CLASS_ID[c] for c in config.hidden_classes]
        if ids and config.hidden_from == "semantic":
            hidden = _class_probability(satfeat, ids, "hidden_from") >= config.drivable_min
        elif ids and labels is not None:
            lab = np.asarray(labels)
            if lab.shape != (h, w):
                raise ConfigError(f"crossview: the label raster is {lab.shape}, the map {(h, w)}")
            hidden = np.isin(lab, ids)
        if hidden is not None and hidden.any():
            self.hidden = hidden
            for c in self._aligner.sat:
                c[hidden] = 0.0
        self._searchers: dict[float, BevAligner] = {}
        from ..features.pixelwise import BilateralRGB

        if (config.align.channels == "gray" or config.projections is not None) and \
                getattr(extractor, "name", "") not in ("default", "rgb"):
            raise ConfigError(f"crossview: channels 'gray' compare the bilateral RGB that the 'default' and 'rgb' "
                              f"features start with; the extractor is {getattr(extractor, 'name', '?')!r}")
        self._rgb = BilateralRGB()

    def as_localizer(self, track: bool = False) -> "NoDatabaseLocalizer":
        """This localizer as one of the common interface (:class:`NoDatabaseLocalizer`); tracked, a query without a
        prior (a receiver's outage, a frame with no fix) searches ``track_radius_m`` / ``track_yaw_deg`` around the
        tracked answer."""
        follow = (self.config.track_radius_m, self.config.track_yaw_deg) if track else None
        return NoDatabaseLocalizer(self, bool(track), follow=follow)

    def _searcher(self, radius_m: float) -> BevAligner:
        """The aligner whose satellite crop is grown by ``radius_m`` (the normalised map shared)."""
        key = round(float(radius_m), 3)
        s = self._searchers.get(key)
        if s is None:
            s = self._searchers[key] = self._aligner.with_search(key)
        return s

    def localize(self, frame, prior: Prior, predicted: tuple[Pose2, float, float] | None = None) -> CrossViewResult:
        """The pose of ``frame`` (a :class:`satloc.sequence.Frame` with left image and stereo or depth) within
        ``prior``. ``predicted`` (pose, sigma metres, sigma degrees): a Gaussian belief, e.g. the previous answer
        moved by the odometry, multiplied into the posterior (its log added to correlation / temperature)."""
        if not isinstance(prior, Prior):
            raise ConfigError(f"crossview: prior must be a satloc.localizers.crossview.Prior, got {type(prior).__name__}")
        sf = self.satfeat
        h, w = sf.features.shape[:2]
        x0, y1 = sf.origin
        if not prior_on_map(prior, sf):
            raise ConfigError(f"crossview: the prior ({prior.x:.1f}, {prior.y:.1f}) m +- {prior.radius_m:g} m lies "
                              f"outside the satellite map (x {x0:g} to {x0 + w * sf.meters_per_pixel:g}, y "
                              f"{y1 - h * sf.meters_per_pixel:g} to {y1:g} m)")
        depth = self.depth(frame, "query frame")
        # the gray channel alone needs no network: the bilateral RGB the default features start with
        if self.projections is not None:   # the learned channels of the bilateral RGB
            feats = self.projections.ground(self._rgb(frame.left, "ground"))
        elif self.config.align.channels == "gray":
            feats = self._rgb(frame.left, "ground")
        else:
            feats = self.extractor(frame.left, "ground")
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
        fix_nll = None
        if prior.sigma_m is not None:   # the fix's reported accuracy: a Student t's negative log density, in
            nu = self.config.fix_nu     # units of the temperature (the same for every heading)
            fix_nll = self.config.temperature * (nu + 2) / 2 * np.log1p((dx * dx + dy * dy) / (nu * prior.sigma_m ** 2))
        xs, ys, yaws, scores, surfaces = [], [], [], [], []
        for dyaw in offsets:
            yaw = wrap_angle(prior.yaw + math.radians(float(dyaw)))
            crop = al._crop(Pose2(prior.x, prior.y, yaw))
            with np.errstate(invalid="ignore"):   # a flat window (beyond the map) is +-inf in some channels
                r = sum(cv2.matchTemplate(c, t, cv2.TM_CCOEFF_NORMED, mask=mask) for c, t in zip(crop, chans)) / len(chans)
            r = raw = np.nan_to_num(r, nan=-1.0, posinf=-1.0, neginf=-1.0)
            c, s = math.cos(yaw), math.sin(yaw)
            wx, wy = prior.x + c * dx - s * dy, prior.y + s * dx + c * dy
            ok = in_disc.copy()
            if fix_nll is not None:
                r = r - fix_nll
            if predicted is not None:   # log of the predicted belief, in units of the temperature
                pp, sm, sd = predicted
                dyaw_p = float(wrap_angle(yaw - pp.yaw))
                r = r - self.config.temperature * (((wx - pp.x) ** 2 + (wy - pp.y) ** 2) / (2 * sm * sm)
                                                    + dyaw_p * dyaw_p / (2 * math.radians(sd) ** 2))
            if self.drivable is not None:
                flat, inside = sf.pixel_index(np.stack([wx, wy], -1))
                ok &= inside & self.drivable.reshape(-1)[np.maximum(flat, 0)]
            xs.append(wx[ok])
            ys.append(wy[ok])
            yaws.append(np.full(int(ok.sum()), yaw))
            scores.append(r[ok])
            surfaces.append((r, ok, yaw, raw))
        score = np.concatenate(scores)
        if score.size == 0:
            return empty
        # the answer: the best position, sub-pixel on its heading's surface
        best = int(np.argmax([sc.max() if sc.size else -np.inf for sc in scores]))
        r, ok, yaw, raw = surfaces[best]
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
        return CrossViewResult(pose, float(raw[i, j]), cand, p[keep], cells)


def prior_on_map(prior: Prior, satfeat: SatelliteFeatures) -> bool:
    """Whether ``prior``'s centre lies within its radius of the satellite features' map (what
    :meth:`CrossViewLocalizer.localize` can search; it refuses any other prior)."""
    h, w = satfeat.features.shape[:2]
    x0, y1 = satfeat.origin
    m = satfeat.meters_per_pixel
    return (x0 - prior.radius_m <= prior.x <= x0 + w * m + prior.radius_m
            and y1 - h * m - prior.radius_m <= prior.y <= y1 + prior.radius_m)


class CrossViewTracker:
    """Cross-view localization over a sequence (see the module docstring): :meth:`predict` with the odometry
    since the previous frame (dx, dy, dyaw in the previous vehicle frame; non-finite: unknown, the next frame
    searches its wide prior), then :meth:`localize` with the frame's wide prior."""

    def __init__(self, localizer: CrossViewLocalizer):
        self.localizer = localizer
        self.reset()

    def reset(self) -> None:
        self.pose: Pose2 | None = None   # the last answer moved by the odometry since (None: lost)
        self.travelled = 0.0             # metres the track moved since its last answer (widens the belief)
        self.disagree_since: float | None = None   # the time of the first fix of a run that disagrees with the track
        self.last_motion: np.ndarray | None = None  # the last motion measured (held through unknown ones)
        self.held = 0                               # unknown motions in a row replaced by it
        self.stale = False   # the track moved by a held motion since its last answer of its own: a fallback only

    def predict(self, motion) -> None:
        """Move the track by ``motion`` (dx, dy, dyaw in the previous frame). An unknown one (NaN) loses the track,
        or with ``hold_motion`` moves it by the last motion measured (that many times in a row at most) and makes
        it stale: the next frames search their prior alone and fall back on it only where they have no answer."""
        m = np.asarray(motion, np.float64).reshape(-1)
        if m.shape == (3,) and np.all(np.isfinite(m)):
            self.last_motion, self.held = m, 0
        elif self.pose is not None and self.last_motion is not None \
                and self.held < self.localizer.config.hold_motion:
            m, self.held, self.stale = self.last_motion, self.held + 1, True
        else:
            self.pose, self.stale, self.travelled = None, False, 0.0
            return
        if self.pose is not None:
            self.pose = self.pose @ Pose2(*m)
            self.travelled += math.hypot(float(m[0]), float(m[1]))

    def sigma_m(self) -> float:
        """The belief's spread in metres now: ``track_sigma_m`` widened by ``track_sigma_per_m`` times the distance
        travelled since the track's last answer."""
        cfg = self.localizer.config
        return math.hypot(cfg.track_sigma_m, cfg.track_sigma_per_m * self.travelled)

    def localize(self, frame, prior: Prior) -> CrossViewResult:
        """The frame's pose: ``fuse``, across ``prior`` with the moved answer as a Gaussian belief; ``gate``,
        within ``track_radius_m`` of the moved answer; across ``prior`` alone where the moved answer lies
        farther outside ``prior`` than 3 ``track_sigma_m`` (``gate``: ``track_radius_m``), and has for longer than
        ``lost_after_s`` (by the frames' timestamps; meanwhile the fix's disc is searched around the moved answer),
        or where the track is stale (moved by a held motion, :meth:`predict`). A frame with no answer of its
        own, the track not lost, coasts (``coast``): the moved answer, correlation NaN, the track kept."""
        cfg = self.localizer.config
        use, predicted = prior, None
        lost = self.pose is None
        # lost: the moved answer lies farther outside the fix's disc than the belief reaches (3 sigma; gate: its
        # search radius). Slightly outside is not lost: a fix drawn near its disc's edge puts a right answer there
        sigma = self.sigma_m()
        reach = 3.0 * sigma if cfg.track == "fuse" else cfg.track_radius_m
        if self.pose is not None:
            far = math.hypot(self.pose.x - prior.x, self.pose.y - prior.y) > prior.radius_m + reach
            if self.stale:   # a fallback only: the prior alone is searched; beyond the fix's reach, not even that
                lost = far
            else:
                t = float(getattr(frame, "timestamp", 0.0) or 0.0)
                if not far:
                    self.disagree_since = None
                elif self.disagree_since is None:
                    self.disagree_since = t
                if far and t - self.disagree_since >= cfg.lost_after_s:
                    self.disagree_since = None   # lost: the fix's disc alone
                    lost = True
                elif cfg.track == "gate":
                    use = Prior(self.pose.x, self.pose.y, self.pose.yaw, min(cfg.track_radius_m, prior.radius_m),
                                min(cfg.track_yaw_deg, prior.yaw_deg))
                else:   # fuse: the fix's disc, or (a fix that disagrees, not yet for long) its extent around the track
                    if far:
                        use = Prior(self.pose.x, self.pose.y, self.pose.yaw, prior.radius_m, prior.yaw_deg)
                    predicted = (self.pose, sigma, cfg.track_sigma_deg)
        else:
            self.disagree_since = None
        res = self.localizer.localize(frame, use, predicted)
        if res.pose is None and not lost and cfg.coast:   # nothing to see: the track moved by the odometry
            return CrossViewResult(self.pose, float("nan"), self.pose.as_array()[None], np.ones(1), res.cells)
        self.pose, self.stale, self.travelled = res.pose, False, 0.0
        return res


def localize_frames(localizer: CrossViewLocalizer, frames, priors, odometry=None, progress: bool = False,
                    top: int = 32, follow: tuple[float, float] | None = None) -> dict:
    """Localize ``frames`` (an iterable of frames) each within its prior of ``priors``; with ``odometry``
    ((N, 3), row i the motion from frame i - 1 to i, row 0 unused) tracked by a :class:`CrossViewTracker`.
    A prior may be None where ``follow`` (radius metres, heading degrees) is given: that frame's prior is the
    tracker's moved answer that wide (no fix of its own; skipped while the track is lost). Returns arrays over
    the frames: ``estimates`` (N, 3; NaN where no answer), ``correlation``, ``cells``, ``seconds``, ``priors``
    (N, 5: x, y, yaw, radius, heading range of the prior searched; zeros where none) and the posterior's
    ``top`` strongest entries ``top_poses`` (N, top, 3), ``top_probs``."""
    from tqdm.auto import tqdm

    priors = list(priors)
    tracker = CrossViewTracker(localizer) if odometry is not None else None
    n = len(priors)
    est = np.full((n, 3), np.nan)
    corr, cells, secs, used = np.full(n, np.nan), np.zeros(n, np.int64), np.zeros(n), np.zeros((n, 5))
    tp, tq = np.zeros((n, top, 3)), np.zeros((n, top))
    for i, f in enumerate(tqdm(frames, total=n, desc="cross-view", unit="frame", disable=not progress, leave=False)):
        if i >= n:
            raise ConfigError(f"localize_frames: more frames than the {n} priors")
        if tracker is not None and i > 0:
            tracker.predict(odometry[i])
        p = priors[i]
        if p is None:
            if follow is None or tracker is None:
                raise ConfigError(f"localize_frames: frame {i} has no prior, and none follows the track")
            if tracker.pose is None:   # lost with no fix to fall back on: nothing to search
                continue
            p = Prior(tracker.pose.x, tracker.pose.y, tracker.pose.yaw, *follow)
        used[i] = (p.x, p.y, p.yaw, p.radius_m, p.yaw_deg)
        t = time.perf_counter()
        r = tracker.localize(f, p) if tracker is not None else localizer.localize(f, p)
        secs[i] = time.perf_counter() - t
        cells[i] = r.cells
        if r.pose is not None:
            est[i] = r.pose.as_array()
            corr[i] = r.correlation
            k = min(top, len(r.posterior))
            tp[i, :k], tq[i, :k] = r.candidates[:k], r.posterior[:k]
    return {"estimates": est, "correlation": corr, "cells": cells, "seconds": secs, "priors": used,
            "top_poses": tp, "top_probs": tq}


def parse_prior(text: str, radius_m: float = 20.0, yaw_deg: float = 10.0) -> Prior:
    """``"X,Y,YAW"`` (map metres, heading in degrees counter-clockwise from east) as a :class:`Prior` of
    ``radius_m`` / ``yaw_deg``; ConfigError naming the text otherwise."""
    parts = [p.strip() for p in str(text).split(",")]
    try:
        x, y, yaw = (float(p) for p in parts)
    except ValueError:
        raise ConfigError(f"prior: expected 'X,Y,YAW_DEG' (metres, metres, degrees) or 'truth', got {text!r}") from None
    return Prior(x, y, math.radians(yaw), radius_m, yaw_deg)



class NoDatabaseLocalizer:
    """A :class:`CrossViewLocalizer` as a localizer of the common interface (:mod:`satloc.localizers.interface`):
    each query within its prior, with ``track`` carried over the run by a :class:`CrossViewTracker` moved by the
    queries' odometry (an unknown motion loses the track: the next query searches its prior alone).

    A query needs a prior; with ``follow`` (radius metres, heading degrees) a query without one searches around
    the tracked answer that wide instead (:func:`localize_frames`' ``follow``). A frame with too little ground in
    view or no drivable position within its prior has no answer (:class:`ConfigError`). Answers carry the
    posterior's strongest entries and the best correlation as ``inlier_score``."""

    posterior_k = 32

    def __init__(self, engine: CrossViewLocalizer, track: bool = False, name: str | None = None,
                 follow: tuple[float, float] | None = None):
        self.engine, self.track, self.follow = engine, bool(track), follow
        self.name = name or ("cross+track" if self.track else "cross")
        self.camera = engine.camera
        self.tracker: CrossViewTracker | None = None

    def reset(self, context=None) -> None:
        self.tracker = CrossViewTracker(self.engine) if self.track else None

    def localize(self, query):
        t = self.tracker
        if t is not None and query.index > 0:   # the first query of a run has no motion before it
            t.predict(query.odometry.as_array() if query.odometry is not None else np.full(3, np.nan))
        prior = query.prior
        if prior is None:
            if self.follow is None or t is None:
                raise ConfigError(f"localizer {self.name!r}: a localization needs a prior (a position and heading "
                                  "within a radius)")
            if t.pose is None:
                raise ConfigError(f"localizer {self.name!r}: the track is lost and the query has no prior")
            prior = Prior(t.pose.x, t.pose.y, t.pose.yaw, *self.follow)
        r = t.localize(query.frame, prior) if t is not None else self.engine.localize(query.frame, prior)
        if r.pose is None:
            raise ConfigError(f"localizer {self.name!r}: too little ground seen ({r.cells} bird's-eye cells) or no "
                              "drivable position within the prior")
        from .interface import Estimate

        return Estimate(r.pose, np.asarray(r.candidates, np.float64), np.asarray(r.posterior, np.float64),
                        float(r.correlation), True)

    def prefetch(self, frames) -> None:
        """Nothing to batch: no network runs on the ground image."""


# localize_sequence (the ``satloc localize --no-database`` stage) moved to satloc.pipeline.localize_no_database
def __getattr__(name: str):
    if name == "localize_sequence":
        import warnings
        from importlib import import_module

        warnings.warn("satloc.localizers.crossview.localize_sequence moved to satloc.pipeline.localize_no_database; "
                      "import it from there (the old name goes in a later version)", FutureWarning, stacklevel=2)
        return import_module("satloc.pipeline").localize_no_database
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
