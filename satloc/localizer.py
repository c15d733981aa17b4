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

Satellite neighbour sets depend only on the satellite pixel, so they are computed once for every map pixel in
a corridor around the candidate path (the "satellite table"); a query then costs one ground NN search plus
table look-ups.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from scipy.spatial import cKDTree

from .dictionary import Dictionary, FrameDepth, SatelliteFeatures, ground_samples
from .errors import ConfigError
from .features import FeatureExtractor
from .geometry import Pose2, StereoCamera
from .nn import NNIndex
from .projection import Projections
from .sequence import Frame


@dataclass(frozen=True)
class LocalizerConfig:
    mode: Literal["full", "np", "go"] = "full"
    neighbors: int = 20                   # M
    candidate_spacing_m: float = 0.5      # along the database path
    lateral_offsets_m: tuple[float, ...] = (-1.5, -1.0, -0.5, 0.0, 0.5, 1.0, 1.5)
    top_k: int = 3                        # the estimate averages the top-k candidates
    posterior_k: int = 32                 # candidates reported in the fixed-shape posterior
    go_radius_m: float = 1.0
    corridor_m: float = 35.0              # satellite table: pixels within this of a candidate
    inlier_threshold: float = 3.0         # peak score / mean score; below: outside the mapped area
    min_distance_frac: float = 0.05       # feature distances are floored at this fraction of the median distance
                                          # between random entries, so duplicates do not get infinite weight
    depth_source: Literal["stereo", "frame"] = "stereo"
    prune_regions: int = 0                # >0: score only candidates near the best-voted database frames
    prune_window_m: float = 12.0          # half-length of the path window kept around each voted frame

    def __post_init__(self):
        if self.candidate_spacing_m <= 0:
            raise ConfigError(f"candidate_spacing_m: expected > 0, got {self.candidate_spacing_m}")
        if self.neighbors < 1 or self.top_k < 1 or self.posterior_k < self.top_k:
            raise ConfigError("neighbors, top_k >= 1 and posterior_k >= top_k are required")


def _spread(x: np.ndarray, n: int = 4000) -> float:
    """Median distance between random pairs of rows of ``x`` (a scale for feature distances)."""
    rng = np.random.default_rng(0)
    a, b = rng.integers(0, len(x), n), rng.integers(0, len(x), n)
    return float(np.median(np.linalg.norm(x[a] - x[b], axis=1)))


def _path_positions(db_poses: np.ndarray, cands: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Arc length along the database path of every database frame and of every candidate (nearest frame)."""
    p = np.nan_to_num(db_poses[:, :2])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    _, nearest = cKDTree(p).query(cands[:, :2])
    return s, s[nearest]


def candidate_poses(db_poses: np.ndarray, spacing: float, lateral: tuple[float, ...]) -> np.ndarray:
    """(C, 3) poses interpolated along the database path every ``spacing`` metres (yaw from the path),
    each repeated at the lateral offsets (left positive)."""
    p = db_poses[np.all(np.isfinite(db_poses), axis=1)]
    if len(p) < 2:
        raise ConfigError("the database path needs at least 2 posed frames to interpolate candidates")
    seg = np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-6])
    p = p[keep]
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1))])
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

    def top(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` most probable candidates (k, 3) and their probabilities (k,), padded with zeros."""
        order = np.argsort(-self.posterior)[:k]
        poses = np.zeros((k, 3))
        probs = np.zeros(k)
        poses[: len(order)] = self.candidates[order]
        probs[: len(order)] = self.posterior[order]
        return poses, probs


class Localizer:
    """Localizes stereo frames against a dictionary and the dense satellite features of its map."""

    def __init__(self, dictionary: Dictionary, satfeat: SatelliteFeatures, extractor: FeatureExtractor,
                 camera: StereoCamera, projections: Projections | None = None,
                 config: LocalizerConfig = LocalizerConfig()):
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
        self.candidates = candidate_poses(dictionary.poses, config.candidate_spacing_m, config.lateral_offsets_m)
        self._frame_s, self._cand_s = _path_positions(dictionary.poses, self.candidates)
        pg = self.proj.project_g(dictionary.g)
        self.ground_index = NNIndex(pg)
        self.eps_g = config.min_distance_frac * _spread(pg) + 1e-9
        if config.mode != "go":
            self._build_satellite_table()

    # --- satellite table ---------------------------------------------------------------------------
    def _build_satellite_table(self) -> None:
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
        index = NNIndex(self.proj.project_s(self.dictionary.s))
        feats = sf.features.reshape(-1, sf.dim)
        ids = np.empty((len(flat), self.config.neighbors), np.int32)
        dist = np.empty((len(flat), self.config.neighbors), np.float32)
        for b in range(0, len(flat), 65536):
            sel = flat[b:b + 65536]
            d, i = index.search(self.proj.project_s(feats[sel].astype(np.float32)), self.config.neighbors)
            ids[b:b + len(sel)], dist[b:b + len(sel)] = i, d
        self.pixel_row = np.full(h * w, -1, np.int64)
        self.pixel_row[flat] = np.arange(len(flat))
        self.eps_s = self.config.min_distance_frac * _spread(self.proj.project_s(self.dictionary.s)) + 1e-9
        self.sat_ids, self.sat_w = ids, (1.0 / np.maximum(dist, self.eps_s)).astype(np.float32)

    # --- localization ------------------------------------------------------------------------------
    def localize(self, frame: Frame, candidates: np.ndarray | None = None) -> Localization:
        """Posterior over candidate poses and the estimate for one stereo frame."""
        cfg = self.config
        frame.check(self.camera, where="query frame")
        uv, pv = ground_samples(self.camera, self.depth(frame, "query frame"), self.dictionary.grid)
        if len(uv) == 0:
            raise ConfigError("query frame: no grid sample has valid depth (textureless, dark or mismatched pair?)")
        g = self.extractor(frame.left, "ground")[uv[:, 1], uv[:, 0]]
        dg, gid = self.ground_index.search(self.proj.project_g(g), cfg.neighbors)
        wg = np.where(gid >= 0, 1.0 / np.maximum(dg, self.eps_g), 0.0).astype(np.float32)
        cands = self.candidates if candidates is None else candidates
        scores = np.zeros(len(cands))
        sel = self._pruned(gid, wg) if candidates is None and cfg.prune_regions > 0 else slice(None)
        scores[sel] = self._scores(cands[sel], pv[:, :2], gid, wg)
        return self._answer(cands, scores, len(uv))

    def _pruned(self, gid: np.ndarray, wg: np.ndarray) -> np.ndarray:
        """Indices of the candidates within ``prune_window_m`` (along the path) of the database frames that
        the query's ground neighbours vote for most: cost independent of the number of candidates."""
        cfg = self.config
        nf = len(self.dictionary.poses)
        votes = np.bincount(self.dictionary.frame[np.maximum(gid, 0)].ravel(), weights=wg.ravel(), minlength=nf)
        s = self._frame_s
        # smooth the votes along the path, then take peaks at least a window apart
        order = np.argsort(s)
        smooth = np.zeros(nf)
        cs = np.concatenate([[0.0], np.cumsum(votes[order])])
        lo = np.searchsorted(s[order], s[order] - cfg.prune_window_m / 2)
        hi = np.searchsorted(s[order], s[order] + cfg.prune_window_m / 2, side="right")
        smooth[order] = cs[hi] - cs[lo]
        keep = np.zeros(len(self.candidates), bool)
        taken: list[float] = []
        for f in np.argsort(-smooth):
            if len(taken) >= cfg.prune_regions or smooth[f] <= 0:
                break
            if all(abs(s[f] - t) > cfg.prune_window_m for t in taken):
                taken.append(s[f])
                keep |= np.abs(self._cand_s - s[f]) <= cfg.prune_window_m
        return np.flatnonzero(keep) if keep.any() else np.arange(len(self.candidates))

    def _scores(self, cands: np.ndarray, pv: np.ndarray, gid: np.ndarray, wg: np.ndarray) -> np.ndarray:
        n, m = gid.shape
        scores = np.zeros(len(cands))
        if self.config.mode == "go":
            loc = self.dictionary.loc[np.maximum(gid, 0)]                       # (n, M, 2)
        else:
            # compact weight table: ground-neighbour entry id -> (sample j, weight)
            uniq, inv = np.unique(gid, return_inverse=True)
            table = np.zeros((n, len(uniq)), np.float32)
            np.add.at(table, (np.repeat(np.arange(n), m), inv.ravel()), wg.ravel())
            remap = np.full(len(self.dictionary) + 1, -1, np.int64)
            remap[uniq] = np.arange(len(uniq))
        batch = max(1, 4_000_000 // max(1, n * m))
        for b in range(0, len(cands), batch):
            c = cands[b:b + batch]
            cos, sin = np.cos(c[:, 2])[:, None], np.sin(c[:, 2])[:, None]
            x = c[:, 0:1] + cos * pv[None, :, 0] - sin * pv[None, :, 1]          # (B, n)
            y = c[:, 1:2] + sin * pv[None, :, 0] + cos * pv[None, :, 1]
            if self.config.mode == "go":
                d = np.hypot(loc[None, :, :, 0] - x[..., None], loc[None, :, :, 1] - y[..., None])  # (B, n, M)
                w = np.where(d <= self.config.go_radius_m, wg[None] / np.maximum(d, 0.25), 0.0)
                scores[b:b + len(c)] = w.sum(axis=(1, 2))
                continue
            flat, inside = self.satfeat.pixel_index(np.stack([x, y], -1))
            row = np.where(inside, self.pixel_row[np.maximum(flat, 0)], -1)     # (B, n)
            ok = row >= 0
            sid = self.sat_ids[np.maximum(row, 0)]                               # (B, n, M)
            sw = self.sat_w[np.maximum(row, 0)] * ok[..., None]
            col = remap[np.maximum(sid, 0)]                                      # (B, n, M)
            j = np.broadcast_to(np.arange(n)[None, :, None], col.shape)
            hit = np.where(col >= 0, table[j, np.maximum(col, 0)], 0.0)
            scores[b:b + len(c)] = (hit * sw).sum(axis=(1, 2))
        return scores

    def _answer(self, cands: np.ndarray, scores: np.ndarray, n: int) -> Localization:
        total = scores.sum()
        if total <= 0 or not np.isfinite(total):
            post = np.full(len(cands), 1.0 / len(cands))
            inlier_score = 0.0
        else:
            post = scores / total
            inlier_score = float(scores.max() / scores.mean())
        k = min(self.config.top_k, len(cands))
        top = np.argsort(-post)[:k]
        w = post[top] / max(post[top].sum(), 1e-300)
        x, y = float(w @ cands[top, 0]), float(w @ cands[top, 1])
        yaw = math.atan2(float(w @ np.sin(cands[top, 2])), float(w @ np.cos(cands[top, 2])))
        return Localization(Pose2(x, y, yaw), cands, post, inlier_score,
                            inlier_score >= self.config.inlier_threshold, n)
