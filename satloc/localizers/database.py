"""Co-occurrence localization (Chu et al.): score candidate poses along the database path.

For a query, ground features g_j are taken at the grid samples with valid stereo depth; their 3-D points are
placed on the map by each candidate pose, where the dense satellite features s_j(c) are read. A pair scores

    sum over dictionary entries i in NN_M(W_g g_j) ∩ NN_M(W_s s_j(c)) of 1 / (d_g(j, i) * d_s(j, c, i))

(NN_M: the M nearest dictionary entries in the projected ground / satellite feature space; d: their
distances). A candidate's score sums its pairs; scores normalised over the candidates give P(L | I), and the
estimate is the probability-weighted mean of the top 3 candidates.

Configurations of the same code (``mode``):

* ``full``: learned projections W_g, W_s;
* ``np`` (no projection): W_g = W_s = I;
* ``go`` (ground only): the satellite neighbour set is replaced by location: entry i co-occurs with sample j
  at candidate c when L(i) lies within ``go_radius_m`` of where c places j, weighted 1 / (d_g * max(dist, 0.25)).
  With ``go_density_m`` > 0 (the default) a candidate's sum is divided by the sum neighbours drawn at random
  from the dictionary would give it: the dictionary's entries under its samples, weighted by the same kernel
  and smoothed over ``go_density_m`` (:func:`entry_density`). A place the database saw from few frames (a gap in
  a random split) holds few entries, so its plain sum is small even where its few entries match best; divided
  by what chance gives there, it competes with places seen from many frames on what matches, not on how often
  the database looked.

With ``refine`` (any mode), the estimate is then refined by bird's-eye alignment around the posterior's
strongest peaks (:mod:`satloc.tracking.align`); the posterior itself is the co-occurrence one.

Satellite neighbour sets depend only on the satellite pixel, so they are computed once for every map pixel in
a corridor around the candidate path (the "satellite table"); a query then costs one ground NN search plus
table look-ups.
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator, Literal, NamedTuple, Sequence

import cv2
import numpy as np
from scipy.spatial import cKDTree
from tqdm import tqdm

from .._threads import _END, overlapped, single_threaded_blas
from ..config import added_field
from ..device import check_device, device_field
from ..errors import ConfigError, FormatError
from ..features.dictionary import Dictionary, FrameDepth, SatelliteFeatures, ground_features, ground_samples
from ..features.nn import NNIndex
from ..features.pixelwise import FeatureExtractor
from ..features.projection import Projections
from ..geometry import Pose2, StereoCamera, arc_length
from ..persist import ArraySpec, check_arrays, header_number, load_npz, save_npz
from ..sequence import Frame
from ..tracking.align import AlignConfig, BevAligner, posterior_peaks
from ..tracking.track import TrackConfig, Tracker


@dataclass(frozen=True)
class LocalizerConfig:
    mode: Literal["full", "np", "go"] = "full"
    neighbors: int = 20                   # M
    candidate_spacing_m: float = 0.5      # along the database path
    lateral_offsets_m: tuple[float, ...] = (-1.5, -1.0, -0.5, 0.0, 0.5, 1.0, 1.5)
    top_k: int = 3                        # the estimate averages the top-k candidates
    posterior_k: int = 32                 # candidates reported in the fixed-shape posterior
    go_radius_m: float = 1.0
    go_density_m: float = added_field(2.0, before=0.0)   # go: divide by the entries' density smoothed over this
                                          # (0: the plain sum). Chosen on fcn_train/town_a and town_b at the default
                                          # world (kitti-city protocol, Ours-GO): beyond 10 m 3.1 -> 1.1 % and
                                          # 1.1 -> 0.5 %, medians unchanged (0.72 / 0.65 m); 0 m (the density
                                          # unsmoothed) raised town_b's median to 0.78 m, 4 m was no better than 2 m
    corridor_m: float = 35.0              # satellite table: pixels within this of a candidate
    inlier_threshold: float = 3.0         # peak score / mean score; below: outside the mapped area
    min_distance_frac: float = 0.05       # feature distances are floored at this fraction of the median distance
                                          # between random entries, so duplicates do not get infinite weight
    depth_source: Literal["stereo", "frame"] = "stereo"
    ef_search: int = 24                   # HNSW search breadth of the ground index (large databases): chosen by
                                          # `satloc experiment tune` on calib/town_a (no table tests there)
                                          # at the default world (varied streets over hills, captured map,
                                          # drifting passes): the smallest value within 0.05 m of 96's mean
                                          # error (24 / 32 / 48 / 96: 33.42 / 33.43 / 33.44 / 33.52 m;
                                          # full+align, 57 queries; on the plain world 96 had won by 1.2 m)
    prune_regions: int = 3                # >0: score only candidates near the best-voted path positions
    prune_window_m: float = 12.0          # path length kept around each voted position (and peak separation)
    refine: bool = False                  # refine the estimate by bird's-eye alignment (satloc.tracking.align)
    align: AlignConfig = field(default_factory=AlignConfig)
    track: bool = False                   # sequences: fuse each frame into a belief moved by odometry (satloc.tracking.track);
                                          # acted on by satloc.pipeline.localize and the environment; a direct
                                          # localize()/localize_stream() call tracks when given a tracker
    tracking: TrackConfig = field(default_factory=TrackConfig)
    device: str = device_field()          # where the query features' FCN runs (satloc.device), when
                                          # satloc.pipeline.load_localizer makes the extractor

    def __post_init__(self):
        check_device(self.device)
        if self.candidate_spacing_m <= 0:
            raise ConfigError(f"candidate_spacing_m: expected > 0, got {self.candidate_spacing_m}")
        if self.neighbors < 1 or self.top_k < 1 or self.posterior_k < self.top_k:
            raise ConfigError("neighbors, top_k >= 1 and posterior_k >= top_k are required")
        if not (math.isfinite(self.go_density_m) and self.go_density_m >= 0):
            raise ConfigError(f"go_density_m: expected a number >= 0, got {self.go_density_m}")
        if self.ef_search < self.neighbors:
            raise ConfigError(f"ef_search: expected >= neighbors ({self.neighbors}), got {self.ef_search}")

    @property
    def name(self) -> str:
        """The mode, with ``+track`` when sequences are tracked and ``+align`` when the estimate is refined
        (names result files and table rows)."""
        return self.mode + ("+track" if self.track else "") + ("+align" if self.refine else "")


def _spread(x: np.ndarray, n: int = 4000) -> float:
    """Median distance between random pairs of rows of ``x`` (a scale for feature distances)."""
    rng = np.random.default_rng(0)
    a, b = rng.integers(0, len(x), n), rng.integers(0, len(x), n)
    return float(np.median(np.linalg.norm(x[a] - x[b], axis=1)))


def _path_positions(db_poses: np.ndarray, cands: np.ndarray) -> np.ndarray:
    """Arc length along the database path of every candidate (that of its nearest database frame)."""
    p = np.nan_to_num(db_poses[:, :2])
    _, nearest = cKDTree(p).query(cands[:, :2])
    return arc_length(p)[nearest]


#: side (metres) of the cells of the entry-density raster (:func:`entry_density`), and the most cells it may
#: have (a larger area gets coarser cells)
DENSITY_CELL_M, DENSITY_MAX_CELLS = 0.25, 16_000_000


def entry_density(loc: np.ndarray, radius_m: float, sigma_m: float) -> tuple[np.ndarray, float, float, float]:
    """What ground-only voting gives a map point by chance: sum over the dictionary's entry locations ``loc``
    (N, 2) of the voting kernel 1 / max(dist, 0.25) within ``radius_m``, smoothed by a Gaussian of ``sigma_m``.
    Returns (raster, x0, y0, cell): raster[row, col] is the value at (x0 + (col + 0.5) cell, y0 + (row + 0.5) cell)."""
    pad = radius_m + 3.0 * sigma_m + 1.0
    x0, y0 = float(loc[:, 0].min()) - pad, float(loc[:, 1].min()) - pad
    wm, hm = float(loc[:, 0].max()) + pad - x0, float(loc[:, 1].max()) + pad - y0
    cell = max(DENSITY_CELL_M, math.sqrt(wm * hm / DENSITY_MAX_CELLS))
    w, h = int(math.ceil(wm / cell)) + 1, int(math.ceil(hm / cell)) + 1
    hist = np.zeros((h, w), np.float32)
    np.add.at(hist, (((loc[:, 1] - y0) / cell).astype(np.int64), ((loc[:, 0] - x0) / cell).astype(np.int64)), 1.0)
    k = int(math.ceil(radius_m / cell))
    d = np.hypot(*np.mgrid[-k:k + 1, -k:k + 1]) * cell
    kernel = np.where(d <= radius_m, 1.0 / np.maximum(d, 0.25), 0.0).astype(np.float32)
    dens = cv2.filter2D(hist, -1, kernel, borderType=cv2.BORDER_CONSTANT)
    if sigma_m > 0:
        dens = cv2.GaussianBlur(dens, (0, 0), sigma_m / cell, borderType=cv2.BORDER_CONSTANT)
    return dens, x0, y0, cell


def candidate_poses(db_poses: np.ndarray, spacing: float, lateral: tuple[float, ...]) -> np.ndarray:
    """(C, 3) poses interpolated along the database path every ``spacing`` metres (yaw from the path),
    each repeated at the lateral offsets (left positive)."""
    p = db_poses[np.all(np.isfinite(db_poses), axis=1)]
    if len(p) < 2:
        raise ConfigError("the database path needs at least 2 posed frames to interpolate candidates")
    seg = np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-6])
    p = p[keep]
    cum = arc_length(p)
    s = np.arange(0.0, cum[-1] + 1e-9, spacing)
    x, y = np.interp(s, cum, p[:, 0]), np.interp(s, cum, p[:, 1])
    # yaw from the path: direction of the local tangent (central differences over about 1 m)
    h = max(spacing, 1.0)
    xa, ya = np.interp(s + h, cum, p[:, 0]), np.interp(s + h, cum, p[:, 1])
    xb, yb = np.interp(s - h, cum, p[:, 0]), np.interp(s - h, cum, p[:, 1])
    yaw = np.arctan2(ya - yb, xa - xb)
    out = [np.stack([x - o * np.sin(yaw), y + o * np.cos(yaw), yaw], axis=1) for o in lateral]
    return np.concatenate(out, axis=0)


@dataclass
class Localization:
    """A localizer's answer for one query."""

    estimate: Pose2
    candidates: np.ndarray          # (C, 3) all candidate poses
    posterior: np.ndarray           # (C,) P(L | I) over the candidates
    inlier_score: float
    inlier: bool
    num_samples: int
    coarse_estimate: Pose2 | None = None    # with ``refine``: the co-occurrence estimate before alignment
    alignment: float = float("nan")         # with ``refine``: correlation of the aligned pose (nan: not aligned)

    @property
    def pose(self) -> Pose2:
        """The estimate (the name of the common interface's answers, :mod:`satloc.localizers.interface`)."""
        return self.estimate

    def top(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` most probable candidates (k, 3) and their probabilities (k,), padded with zeros."""
        order = np.argsort(-self.posterior)[:k]
        poses = np.zeros((k, 3))
        probs = np.zeros(k)
        poses[: len(order)] = self.candidates[order]
        probs[: len(order)] = self.posterior[order]
        return poses, probs


def top_k_estimate(candidates: np.ndarray, posterior: np.ndarray, k: int = 3) -> Pose2:
    """The posterior-weighted mean pose of the ``k`` most probable candidates (the paper reports k = 3);
    headings are averaged on the circle."""
    k = min(int(k), len(candidates))
    top = np.argsort(-posterior)[:k]
    w = posterior[top] / max(float(posterior[top].sum()), 1e-300)
    x, y = float(w @ candidates[top, 0]), float(w @ candidates[top, 1])
    yaw = math.atan2(float(w @ np.sin(candidates[top, 2])), float(w @ np.cos(candidates[top, 2])))
    return Pose2(x, y, yaw)


class _Observation(NamedTuple):
    depth: np.ndarray     # (H, W) metres
    uv: np.ndarray        # (n, 2) grid samples with valid depth
    pv: np.ndarray        # (n, 3) their points in the vehicle frame
    fmap: np.ndarray      # (H, W, D) pixel-wise features of the left image
    g: np.ndarray         # (n, Dg) ground features of the samples


class Localizer:
    """Localizes stereo frames against a dictionary and the dense satellite features of its map."""

    def __init__(self, dictionary: Dictionary, satfeat: SatelliteFeatures, extractor: FeatureExtractor,
                 camera: StereoCamera, projections: Projections | None = None,
                 config: LocalizerConfig = LocalizerConfig(), table_cache: str | Path | None = None,
                 progress: bool = False):
        if len(dictionary) == 0:
            raise ConfigError("the dictionary is empty: nothing to localize against")
        if config.mode == "full" and projections is None:
            raise ConfigError("mode 'full' needs learned projections (or use mode 'np')")
        self.dictionary, self.satfeat, self.extractor, self.camera = dictionary, satfeat, extractor, camera
        self.config = config
        dg, ds = dictionary.g.shape[1], dictionary.s.shape[1]
        self.proj = projections if config.mode == "full" else Projections.identity(dg, ds)
        if self.proj.W_g.shape != (dg, dg) or self.proj.W_s.shape != (ds, ds):
            raise ConfigError(f"projections of shape {self.proj.W_g.shape}/{self.proj.W_s.shape} do not match the "
                              f"dictionary's feature dimensions {dg}/{ds}")
        self.depth = FrameDepth(camera, config.depth_source)
        self.span = dictionary.context.span(extractor.dim, extractor.name)
        if dictionary.context.dim(extractor.dim, extractor.name) != dg:
            raise ConfigError(f"the extractor {extractor.name!r} ({extractor.dim} channels) with the dictionary's "
                              f"context does not give its {dg}-dimensional ground features")
        self.candidates = candidate_poses(dictionary.poses, config.candidate_spacing_m, config.lateral_offsets_m)
        self._cand_s = _path_positions(dictionary.poses, self.candidates)
        # for vote pruning: candidates binned by path position, the heading each entry was seen with
        self._bin_m = config.candidate_spacing_m
        self._cand_bin = np.round(self._cand_s / self._bin_m).astype(np.int64)
        self._cand_tree = cKDTree(self.candidates[:, :2])
        self._entry_yaw = np.nan_to_num(dictionary.poses[dictionary.frame, 2])
        pg = self.proj.project_g(dictionary.g)
        self.ground_index = NNIndex(pg, ef_search=config.ef_search)
        self.eps_g = config.min_distance_frac * _spread(pg) + 1e-9
        if config.mode != "go":
            self._satellite_table(table_cache, progress)
        # (raster, x0, y0, cell, floor per sample); an empty raster and no floor: the plain sum
        self._density = (np.zeros((0, 0), np.float32), 0.0, 0.0, 1.0, 0.0)
        if config.mode == "go" and config.go_density_m > 0:
            dens, x0, y0, cell = entry_density(dictionary.loc, config.go_radius_m, config.go_density_m)
            # a floor for the density under a candidate's samples: 5 % of a typical cell's, per sample
            typical = float(np.median(dens[dens > 1e-3 * dens.max()]))
            self._density = (dens, x0, y0, cell, 0.05 * typical)
        self._aligner: BevAligner | None = None

    @property
    def aligner(self) -> BevAligner:
        """The bird's-eye aligner of the refinement stage (built on first use)."""
        if self._aligner is None:
            sf = self.satfeat
            self._aligner = BevAligner(self.camera, sf.features, sf.meters_per_pixel, sf.origin, self.config.align)
        return self._aligner

    # --- satellite table ---------------------------------------------------------------------------
    def _table_key(self) -> str:
        """What the satellite table depends on (a cached table with another key is recomputed)."""
        h = hashlib.sha256()
        for a in (self.proj.W_s, self.dictionary.s[:: max(1, len(self.dictionary) // 997)], self.candidates):
            h.update(np.ascontiguousarray(a).tobytes())
        h.update(repr((len(self.dictionary), self.config.neighbors, self.config.corridor_m,
                       self.satfeat.features.shape, self.config.min_distance_frac)).encode())
        return h.hexdigest()[:20]

    def _satellite_table(self, cache: str | Path | None, progress: bool) -> None:
        key = self._table_key()
        if cache is not None and Path(cache).is_file():
            try:
                a, m = load_npz(cache, "satellite_table")
                if m.get("key") == key:
                    self.pixel_row, self.sat_ids, self.sat_w, self.eps_s = self._checked_table(a, m, cache)
                    return
            except FormatError:
                pass  # damaged, foreign or inconsistent: recompute and overwrite
        self._build_satellite_table(progress)
        if cache is not None:
            save_npz(cache, "satellite_table", {"pixel_row": self.pixel_row, "ids": self.sat_ids,
                                                "weights": self.sat_w}, {"key": key, "eps_s": self.eps_s})

    def _checked_table(self, a: dict, m: dict, path) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """A cached table's arrays and eps_s, after checking that they are one as the builder writes it
        (dtypes, shapes, a row index, ids of dictionary entries, weights 1 / max(distance, eps_s));
        FormatError otherwise."""
        h, w = self.satfeat.features.shape[:2]
        m_nn = self.config.neighbors
        sizes = check_arrays(a, {"pixel_row": ArraySpec("iu", (h * w,), min=-1),
                                 "ids": ArraySpec("iu", ("R", m_nn), min=0, max=len(self.dictionary) - 1),
                                 "weights": ArraySpec("f", ("R", m_nn))}, path)
        eps_s = header_number(m, "eps_s", path, positive=True)
        rows, row = sizes["R"], a["pixel_row"]
        if not np.array_equal(row[row >= 0], np.arange(rows)):
            raise FormatError(f"{path}: array 'pixel_row' is not an index of the table's {rows} rows")
        wts = a["weights"]
        if wts.size and not (wts.min() > 0 and wts.max() <= np.float32(1.0 / eps_s) * (1 + 1e-6)):
            raise FormatError(f"{path}: array 'weights' outside (0, 1 / eps_s]")
        dtypes = (np.int32 if rows < 2**31 else np.int64, np.int32, np.float32)  # as the builder writes them
        if any(a[k].dtype != t for k, t in zip(("pixel_row", "ids", "weights"), dtypes)):
            raise FormatError(f"{path}: arrays of dtypes {[str(a[k].dtype) for k in ('pixel_row', 'ids', 'weights')]}, "
                              f"expected {[np.dtype(t).name for t in dtypes]}")
        return row, a["ids"], wts, float(eps_s)

    def _build_satellite_table(self, progress: bool = False) -> None:
        """M nearest dictionary entries (projected satellite features) of every map pixel near a candidate."""
        sf = self.satfeat
        h, w = sf.features.shape[:2]
        mpp = sf.meters_per_pixel
        mask = np.zeros((h, w), np.uint8)
        pts = np.stack([(self.candidates[:, 0] - sf.origin[0]) / mpp, (sf.origin[1] - self.candidates[:, 1]) / mpp], 1)
        r = int(math.ceil(self.config.corridor_m / mpp))
        for u, v in np.round(pts).astype(int):
            cv2.circle(mask, (int(u), int(v)), r, 1, -1)
        flat = np.flatnonzero(mask.ravel())
        # millions of pixel queries: an HNSW graph pays off from a few thousand entries on
        index = NNIndex(self.proj.project_s(self.dictionary.s), exact_max=5000)
        ids = np.empty((len(flat), self.config.neighbors), np.int32)
        dist = np.empty((len(flat), self.config.neighbors), np.float32)
        for b in tqdm(range(0, len(flat), 65536), desc="satellite table", unit="block", disable=not progress,
                      leave=False):
            sel = flat[b:b + 65536]
            f = sf.features_at(sel, self.dictionary.context, self.span)
            d, i = index.search(self.proj.project_s(f), self.config.neighbors)
            ids[b:b + len(sel)], dist[b:b + len(sel)] = i, d
        self.pixel_row = np.full(h * w, -1, np.int32 if len(flat) < 2**31 else np.int64)
        self.pixel_row[flat] = np.arange(len(flat))
        self.eps_s = self.config.min_distance_frac * _spread(self.proj.project_s(self.dictionary.s)) + 1e-9
        self.sat_ids, self.sat_w = ids, (1.0 / np.maximum(dist, self.eps_s)).astype(np.float32)

    # --- localization ------------------------------------------------------------------------------
    def localize(self, frame: Frame, candidates: np.ndarray | None = None, refine: bool | None = None,
                 tracker: Tracker | None = None) -> Localization:
        """Posterior over candidate poses and the estimate for one stereo frame (``refine``: whether to refine
        the estimate by bird's-eye alignment; None: as configured). With a ``tracker`` (:mod:`satloc.tracking.track`,
        already moved by the odometry since its last frame) the frame's posterior is fused into its belief and
        the answer (posterior, estimate, refinement peaks) is the fused one, and the inlier score is the tracker's
        probability of being on the mapped path (:attr:`satloc.tracking.track.Tracker.p_on`)."""
        with single_threaded_blas():  # see satloc._threads: spinning BLAS workers slow the network and stereo
            return self._score(self._observe(frame), candidates, refine, tracker)

    def prefetch(self, frames: Sequence[Frame]) -> None:
        """Compute the network part of the features of several query frames' left images in one batch (one
        network call, see :meth:`satloc.features.fcn.FCNPredictor.prefetch`), so that the :meth:`localize` calls that
        follow for these frames reuse it. Extractors without a network (``rgb``) ignore it. The features equal
        those of :meth:`localize` alone up to float rounding of the batched convolutions (about 1e-6)."""
        pre = getattr(self.extractor, "prefetch", None)
        lefts = [f.left for f in frames if f.left is not None]
        if pre is not None and len(lefts) > 1:
            pre(lefts, "ground")

    def as_localizer(self, track: bool | None = None) -> "DatabaseLocalizer":
        """This localizer as one of the common interface (:class:`DatabaseLocalizer`; ``track``: default
        ``config.track``)."""
        return DatabaseLocalizer(self, track)

    def tracker(self, config: TrackConfig | None = None) -> Tracker:
        """A :class:`satloc.tracking.track.Tracker` over this localizer's candidate poses (``config``: default
        ``self.config.tracking``)."""
        return Tracker(self.candidates, self.config.tracking if config is None else config)

    def localize_stream(self, frames: Iterable[Frame], refine: bool | None = None, overlap: bool = True,
                        errors: Literal["raise", "yield"] = "raise", tracker: Tracker | None = None,
                        odometry: Iterable[np.ndarray] | None = None) -> Iterator[Localization | ConfigError]:
        """Localizations of a stream of frames, in order, the same as :meth:`localize` gives for each.

        With ``overlap`` the next frame is fetched and its stereo depth and features computed on a worker
        thread while the current one is scored (:func:`satloc._threads.overlapped`): on 2 cores, 12-30 % more
        queries per second (measured on the loop and city scenes). ``errors="yield"``: a frame that cannot be
        localized (e.g. no grid sample with valid depth) yields its :class:`ConfigError` instead of ending the
        stream.

        With a ``tracker``, ``odometry`` gives for each frame the motion (dx, dy, dyaw) since the previous frame
        (the first one's is used only if the tracker already holds a belief); the tracker is moved by it before
        the frame is fused, also for a frame that cannot be localized."""
        if errors not in ("raise", "yield"):
            raise ConfigError(f"localize_stream: errors must be 'raise' or 'yield', got {errors!r}")
        if (tracker is None) != (odometry is None):
            raise ConfigError("localize_stream: tracking needs both a tracker and the odometry of every frame")
        odo = iter(odometry) if odometry is not None else None

        def observe(frame: Frame) -> _Observation | ConfigError:
            try:
                return self._observe(frame)
            except ConfigError as e:
                return e

        for obs in overlapped(observe, frames, enabled=overlap):
            if tracker is not None:
                motion = next(odo, _END)
                if motion is _END:
                    raise ConfigError("localize_stream: the odometry ran out before the frames")
                m = np.asarray(motion, np.float64).ravel()
                if m.shape == (3,) and np.all(np.isfinite(m)):
                    tracker.predict(m)
                else:
                    tracker.reset()   # moved by an unknown amount (e.g. visual odometry lost): a new belief
            if not isinstance(obs, ConfigError):
                try:
                    with single_threaded_blas():  # only this thread sets the (process-wide) limit
                        obs = self._score(obs, None, refine, tracker)
                except ConfigError as e:
                    obs = e
            if isinstance(obs, ConfigError) and errors == "raise":
                raise obs
            yield obs

    def _observe(self, frame: Frame) -> _Observation:
        """What a query frame gives before any look-up: depth, grid samples, the feature map and its features
        (the per-image work: stereo matching and the network)."""
        frame.check(self.camera, where="query frame")
        depth = self.depth(frame, "query frame")
        uv, pv = ground_samples(self.camera, depth, self.dictionary.grid)
        if len(uv) == 0:
            raise ConfigError("query frame: no grid sample has valid depth (textureless, dark or mismatched pair?)")
        fmap = self.extractor(frame.left, "ground")
        g = ground_features(fmap, uv, depth, self.camera, self.dictionary.context, self.span)
        return _Observation(depth, uv, pv, fmap, g)

    def _score(self, obs: _Observation, candidates: np.ndarray | None, refine: bool | None,
               tracker: Tracker | None = None) -> Localization:
        """The posterior over the candidates (and the refined estimate) from an observation."""
        cfg = self.config
        if tracker is not None and (candidates is not None or not (
                tracker.candidates is self.candidates or np.array_equal(tracker.candidates, self.candidates))):
            raise ConfigError("tracking needs the localizer's own candidates (make the tracker with "
                              "Localizer.tracker() and pass no candidates)")
        pv = obs.pv
        dg, gid = self.ground_index.search(self.proj.project_g(obs.g), cfg.neighbors)
        wg = np.where(gid >= 0, 1.0 / np.maximum(dg, self.eps_g), 0.0).astype(np.float32)
        cands = self.candidates if candidates is None else candidates
        scores = np.zeros(len(cands))
        # a tracker that has not locked (a new belief: a uniform prior) needs every candidate's score: vote
        # pruning drops the truth of most aliased single images, and a dropped candidate is all but ruled out
        # by the fusion (satloc.tracking.track, "global search")
        prune = candidates is None and cfg.prune_regions > 0 and (tracker is None or tracker.locked())
        sel = self._pruned(gid, wg, pv) if prune else slice(None)
        if tracker is not None and tracker.belief is not None and not isinstance(sel, slice):
            # also score where the tracked belief is, wherever this frame's votes point
            b = tracker.belief
            sel = np.union1d(sel, np.flatnonzero(b >= 1e-3 * b.max()))
        scores[sel] = self._scores(cands[sel], pv[:, :2], gid, wg)
        out = self._answer(cands, scores, len(obs.uv), tracker)
        if (cfg.refine if refine is None else refine) and out.inlier_score > 0:
            self._refine(out, obs.fmap, obs.depth)
        return out

    def _refine(self, out: Localization, fmap: np.ndarray, depth: np.ndarray) -> None:
        """Replace the estimate by the bird's-eye alignment around the posterior's peaks (where it is found)."""
        a = self.config.align
        peaks = posterior_peaks(out.candidates, out.posterior, a.peaks, a.peak_separation_m)
        if not peaks:
            return
        if a.prior_weight > 0:  # a peak this much less probable cannot win (correlations lie in [-1, 1])
            peaks = [i for i in peaks if out.posterior[i] >= out.posterior[peaks[0]] * math.exp(-2.0 / a.prior_weight)]
        prior = np.log(out.posterior[peaks] / out.posterior[peaks[0]])
        r = self.aligner.align(fmap, depth, [Pose2(*out.candidates[i]) for i in peaks], prior)
        if r is not None and r.correlation >= a.min_correlation:
            out.coarse_estimate, out.estimate, out.alignment = out.estimate, r.pose, r.correlation

    def _pruned(self, gid: np.ndarray, wg: np.ndarray, pv: np.ndarray) -> np.ndarray:
        """Indices of the candidates near the path positions the query's ground neighbours vote for most.

        Ground neighbour i of sample j (at ``pv[j]`` in the vehicle frame) implies the vehicle stood at
        L(i) - R(yaw_i) pv[j], yaw_i being the heading of the database frame that saw i. Votes (weighted like the
        pairs, 1 / d_g) are binned by path position, smoothed over ``prune_window_m`` and the ``prune_regions``
        best peaks, at least a window apart, keep the candidates within half a window of them. The cost depends
        on the query's samples, not on the length of the database."""
        cfg = self.config
        ok = gid >= 0
        ids = np.where(ok, gid, 0)
        yaw = self._entry_yaw[ids]                                              # (n, M)
        c, s = np.cos(yaw), np.sin(yaw)
        loc = self.dictionary.loc[ids]
        px = loc[..., 0] - (c * pv[:, None, 0] - s * pv[:, None, 1])
        py = loc[..., 1] - (s * pv[:, None, 0] + c * pv[:, None, 1])
        reach = 2.0 * max(abs(o) for o in cfg.lateral_offsets_m) + 2.0   # farther implied positions do not vote
        dist, near = self._cand_tree.query(np.stack([px[ok], py[ok]], 1), distance_upper_bound=reach * (1 + 1e-9))
        w = wg[ok] * (dist <= reach)
        near = np.where(np.isfinite(dist), near, 0)  # beyond reach: no neighbour (index n)
        votes = np.bincount(self._cand_bin[near], weights=w, minlength=int(self._cand_bin.max()) + 1)
        half = max(1, int(round(cfg.prune_window_m / 2 / self._bin_m)))
        smooth = np.convolve(votes, np.ones(2 * half + 1), mode="same")
        keep = np.zeros(len(self.candidates), bool)
        taken: list[int] = []
        for b in np.argsort(-smooth):
            if len(taken) >= cfg.prune_regions or smooth[b] <= 0:
                break
            if all(abs(b - t) > 2 * half for t in taken):
                taken.append(int(b))
                keep |= np.abs(self._cand_bin - b) <= half
        return np.flatnonzero(keep) if keep.any() else np.arange(len(self.candidates))

    def _scores(self, cands: np.ndarray, pv: np.ndarray, gid: np.ndarray, wg: np.ndarray) -> np.ndarray:
        """Scores of the candidate poses ``cands`` (C, 3) for samples at ``pv`` (n, 2) with ground neighbours
        ``gid`` and weights ``wg`` (n, M); the loops are compiled (:mod:`satloc._kernels`)."""
        from .. import _kernels

        cands = np.ascontiguousarray(cands, dtype=np.float64)
        pv = np.ascontiguousarray(pv, dtype=np.float64)
        wg = np.ascontiguousarray(wg, dtype=np.float32)
        if self.config.mode == "go":
            loc = np.ascontiguousarray(self.dictionary.loc[np.maximum(gid, 0)], dtype=np.float64)
            dens, x0, y0, cell, floor = self._density
            scores, chance = _kernels.location_scores(cands, pv, loc, np.where(gid >= 0, wg, 0).astype(np.float32),
                                                      float(self.config.go_radius_m), dens, x0, y0, cell)
            if floor > 0:   # divided by what chance gives each candidate (see the module docstring)
                scores = scores / np.maximum(chance, floor * len(pv))
            return scores
        sf = self.satfeat
        h, w = sf.features.shape[:2]
        return _kernels.cooccurrence_scores(cands, pv, np.ascontiguousarray(gid, dtype=np.int64), wg,
                                            float(sf.origin[0]), float(sf.origin[1]), float(sf.meters_per_pixel),
                                            h, w, self.pixel_row, self.sat_ids, self.sat_w, len(self.dictionary))

    def _answer(self, cands: np.ndarray, scores: np.ndarray, n: int, tracker: Tracker | None = None) -> Localization:
        total = scores.sum()
        if total <= 0 or not np.isfinite(total):
            post = np.full(len(cands), 1.0 / len(cands))
            inlier_score = 0.0
        else:
            post = scores / total
            inlier_score = float(scores.max() / scores.mean())
        inlier = inlier_score >= self.config.inlier_threshold
        if tracker is not None:   # tracked: the inlier test is the tracker's P(on the mapped path)
            post = tracker.fuse(post)
            inlier_score = tracker.p_on
            inlier = inlier_score >= tracker.config.inlier_threshold
        return Localization(top_k_estimate(cands, post, self.config.top_k), cands, post, inlier_score, inlier, n)


class DatabaseLocalizer:
    """The paper's method (a :class:`Localizer` built from a database drive) as a localizer of the common
    interface (:mod:`satloc.localizers.interface`). With ``track`` (default: the engine's ``config.track``) the
    queries of a run are fused into a belief over the candidate poses (:class:`satloc.tracking.track.Tracker`)
    that each query's odometry moves first; an unknown motion starts a new belief. ``reset`` starts a new belief.

    The engine is shared: several of these (the cars of a vector environment, say) may wrap one
    :class:`Localizer`, each with its own belief. A frame with no grid sample of valid stereo depth has no
    answer (:class:`ConfigError`). ``name`` defaults to the engine's configuration name (``full+track+align``)."""

    def __init__(self, engine: Localizer, track: bool | None = None, name: str | None = None):
        self.engine = engine
        self.track = bool(engine.config.track if track is None else track)
        cfg = engine.config
        self.name = name or (cfg.mode + ("+track" if self.track else "") + ("+align" if cfg.refine else ""))
        self.posterior_k = cfg.posterior_k
        self.wants_depth = cfg.depth_source == "frame"
        self.camera = engine.camera
        self.tracker: Tracker | None = None

    def reset(self, context=None) -> None:
        self.tracker = self.engine.tracker() if self.track else None

    def localize(self, query) -> Localization:
        t = self.tracker
        if t is not None:
            if query.odometry is not None:
                t.predict(query.odometry.as_array())
            elif query.index > 0:
                t.reset()   # moved by an unknown amount: a new belief (the first query's is new already)
        return self.engine.localize(query.frame, tracker=t)

    def localize_many(self, queries):
        """The answers to ``queries`` (an iterable), in order, as :meth:`localize` gives them one by one (a
        :class:`ConfigError` instance where a frame has no answer), with the next query's stereo depth and
        features computed on a worker thread while the current one is scored (:meth:`Localizer.localize_stream`:
        12-30 % more queries per second on 2 cores). The optional fast path of the interface: the graders use it
        where a localizer has it."""
        import collections

        pending: collections.deque = collections.deque()   # queries whose odometry the tracker has not read
        t = self.tracker

        def frames():
            for q in queries:
                if t is not None:
                    pending.append(q)
                yield q.frame

        def odometry():
            while pending:
                o = pending.popleft().odometry
                yield o.as_array() if o is not None else np.full(3, np.nan)

        yield from self.engine.localize_stream(frames(), errors="yield", tracker=t,
                                               odometry=odometry() if t is not None else None)

    def prefetch(self, frames) -> None:
        """Run the network part of several frames' features in one batch (:meth:`Localizer.prefetch`)."""
        self.engine.prefetch(frames)
