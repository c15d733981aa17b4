"""Bird's-eye alignment: a refinement stage after the co-occurrence localizer.

The co-occurrence posterior (:mod:`satloc.localizers.database`) lands most queries within a metre or two, on a grid of
candidates 0.5 m apart with the heading of the path. This stage re-checks its few strongest peaks densely:

1. the query's ground pixels are warped to a bird's-eye view (BEV) of the ground plane in front of the
   vehicle, at the satellite map's resolution, through the camera's known mounting (height, pitch), or with
   ``fit_ground`` (the default) the plane the stereo depth shows: a least-squares plane through the points
   near the mounting's plane, outliers dropped, kept where it is plausible for a road (a road ahead climbing or
   banking otherwise than the ground under the wheels puts the mounting's plane metres off at 20 m). Only
   cells whose stereo depth agrees with the plane are kept, so cars, people, walls and anything else standing
   on the ground are masked out;
2. around each peak, for a few heading offsets, the satellite features are resampled in the peak's vehicle
   frame, and the BEV is slid over them by masked normalised cross-correlation (``cv2.matchTemplate``),
   which gives every translation on the map's pixel grid at once; the best is refined to sub-pixel by a
   parabola through its neighbours;
3. peaks compete by correlation plus ``prior_weight`` times the log of their posterior ratio; the winner is
   searched over the heading offsets too. The answer is its aligned pose, or the co-occurrence estimate
   where it correlates less than ``min_correlation``.

:meth:`BevAligner.scan` computes the same correlation at every candidate pose of the map at once, a
likelihood from the ground view alone (used to measure perceptual aliasing).

The channels compared are features both views already have: the bilateral RGB as grey level (the default;
normalised cross-correlation is blind to the gain and offset of another exposure) and, optionally, the edge
potentials.
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import ConfigError
from ..geometry import Pose2, StereoCamera


@dataclass(frozen=True)
class AlignConfig:
    peaks: int = 3                        # posterior peaks re-checked
    peak_separation_m: float = 6.0        # peaks closer than this are one
    search_m: float = 4.0                 # translations searched around a peak (each axis, +-)
    yaw_offsets_deg: tuple[float, ...] = (-2.0, -1.0, 0.0, 1.0, 2.0)
    forward_m: tuple[float, float] = (3.0, 20.0)    # BEV extent ahead of the vehicle
    half_width_m: float = 10.0                      # and to each side
    ground_tolerance: float = 0.08        # |stereo depth - ground-plane depth| / ground-plane depth
    channels: str = "gray"                # gray | edge | gray+edge | learned (every channel of features already
                                          # projected: satloc.features.crossview_learn)
    normalize_m: float = 1.0              # local contrast normalisation window (Gaussian sigma); 0: off
    min_correlation: float = 0.2          # below: keep the co-occurrence estimate
    min_cells: int = 400                  # fewer visible ground cells: keep the co-occurrence estimate
    prior_weight: float = 0.1             # peak score: correlation + prior_weight * log(P(peak) / P(best peak))
    shift_penalty: float = 0.01           # per m^2: subtracted from a translation's correlation for its squared
                                          # distance from the seed (a lane over must correlate that much better);
                                          # chosen on the calibration scenes (docs/method.md); 0: off
    fit_ground: bool = True               # the ground plane fitted to the stereo depth (a road's grade and camber
                                          # ahead differ from those under the wheels); False: the mounting's
                                          # plane, exact only on flat ground under a level car

    def __post_init__(self):
        if self.peaks < 1 or self.search_m <= 0 or not self.yaw_offsets_deg:
            raise ConfigError("align: peaks >= 1, search_m > 0 and at least one yaw offset are required")
        if not 0 < self.forward_m[0] < self.forward_m[1] or self.half_width_m <= 0:
            raise ConfigError(f"align: forward_m must be 0 < near < far, got {self.forward_m}")
        if not self.shift_penalty >= 0:
            raise ConfigError(f"align.shift_penalty: expected a number >= 0, got {self.shift_penalty!r}")
        if self.channels not in ("gray", "edge", "gray+edge", "learned"):
            raise ConfigError(f"align.channels: expected gray, edge, gray+edge or learned, got {self.channels!r}")


@dataclass
class Alignment:
    pose: Pose2            # best aligned pose
    correlation: float     # its normalised cross-correlation
    peak: int              # which seed it came from
    cells: int             # visible ground cells in the BEV


def _channel_maps(features: np.ndarray, channels: str) -> list[np.ndarray]:
    f = features
    if channels == "learned":   # already the learned channels (satloc.features.crossview_learn.CrossViewProjections)
        return [np.ascontiguousarray(f[..., c], np.float32) for c in range(f.shape[2])]
    out = []
    if "gray" in channels:
        out.append(np.ascontiguousarray(f[..., :3].astype(np.float32).mean(axis=2)))
    if "edge" in channels:
        if f.shape[2] < 4:
            raise ConfigError("align: channels 'edge' need the default feature set (RGB + edge + semantic)")
        out.append(np.ascontiguousarray(f[..., 3].astype(np.float32)))
    return out


class BevAligner:
    """Dense alignment of a query's bird's-eye view against satellite features (see the module docstring)."""

    def __init__(self, camera: StereoCamera, sat_features: np.ndarray, meters_per_pixel: float,
                 origin: tuple[float, float], config: AlignConfig = AlignConfig()):
        if sat_features.ndim != 3 or (sat_features.shape[2] < 3 and config.channels != "learned"):
            raise ConfigError(f"align: satellite features must be (H, W, D>=3) with RGB first, got {sat_features.shape}")
        self.camera, self.config = camera, config
        self.res, self.origin = float(meters_per_pixel), (float(origin[0]), float(origin[1]))
        self.sat = [self._normalize(c, None) for c in _channel_maps(sat_features, config.channels)]
        # BEV grid: row r <-> x = x0 + r * res (ahead), column c <-> y = y0 + c * res (left)
        self.x0, self.y0 = config.forward_m[0], -config.half_width_m
        nx = int(round((config.forward_m[1] - config.forward_m[0]) / self.res)) + 1
        ny = int(round(2 * config.half_width_m / self.res)) + 1
        xs, ys = self.x0 + self.res * np.arange(nx), self.y0 + self.res * np.arange(ny)
        self._X, self._Y = np.meshgrid(xs, ys, indexing="ij")
        self._vehicle_from_cam = camera.vehicle_from_camera("left")
        self._cam_from_vehicle = np.linalg.inv(self._vehicle_from_cam)
        self.map_u, self.map_v, self.plane_z, self.in_image = self._grid_on((0.0, 0.0, 0.0))
        self.shape = (nx, ny)
        # the satellite crop around a pose: the BEV grid grown by the search margin, in the vehicle frame
        self.margin = int(math.ceil(config.search_m / self.res))
        self._crop_x, self._crop_y = np.meshgrid(self.x0 + self.res * np.arange(-self.margin, nx + self.margin),
                                                 self.y0 + self.res * np.arange(-self.margin, ny + self.margin),
                                                 indexing="ij")
        self._scan_key: tuple | None = None     # the candidate set whose scan plan is cached
        self._scan_groups: list = []

    def with_search(self, search_m: float) -> BevAligner:
        """A copy that searches translations of +- ``search_m`` around a pose (the normalised satellite channels
        and the BEV grid shared, not recomputed)."""
        import copy

        if not search_m > 0:
            raise ConfigError(f"align: search_m must be > 0, got {search_m!r}")
        out = copy.copy(self)
        nx, ny = self.shape
        out.margin = int(math.ceil(search_m / self.res))
        out._crop_x, out._crop_y = np.meshgrid(self.x0 + self.res * np.arange(-out.margin, nx + out.margin),
                                               self.y0 + self.res * np.arange(-out.margin, ny + out.margin),
                                               indexing="ij")
        out._scan_key, out._scan_groups = None, []
        return out

    def _grid_on(self, plane: tuple[float, float, float]) -> tuple[np.ndarray, ...]:
        """The BEV grid's cells on the ground plane z = a x + b y + c (vehicle frame): their pixels (u, v), their
        depth and whether the left image sees them."""
        a, b, c = plane
        X, Y, t, cam = self._X, self._Y, self._cam_from_vehicle, self.camera
        pc = np.stack([X, Y, a * X + b * Y + c], -1) @ t[:3, :3].T + t[:3, 3]
        uv, z = cam.project(pc)
        seen = ((z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] <= cam.width - 1)
                & (uv[..., 1] >= 0) & (uv[..., 1] <= cam.height - 1))
        return uv[..., 0].astype(np.float32), uv[..., 1].astype(np.float32), z.astype(np.float32), seen

    def ground_plane(self, depth: np.ndarray) -> tuple[float, float, float] | None:
        """The plane z = a x + b y + c (vehicle frame) through the ground the stereo depth shows in the BEV's
        extent: least squares over the cells whose depth lies within 25 % of the mounting's plane, refitted
        twice without those more than 0.15 m off it. None where fewer than ``min_cells`` cells support it or
        it is implausible for a road (a grade or a bank above 15 %, or 0.5 m above or below the wheels)."""
        d = cv2.remap(depth.astype(np.float32), self.map_u, self.map_v, cv2.INTER_NEAREST,
                      borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        near = self.in_image & (d > 0) & (np.abs(d - self.plane_z) <= 0.25 * self.plane_z)
        if int(near.sum()) < self.config.min_cells:
            return None
        uv = np.stack([self.map_u[near], self.map_v[near]], -1)
        v = self._vehicle_from_cam
        p = self.camera.backproject(uv, d[near]) @ v[:3, :3].T + v[:3, 3]
        keep = np.ones(len(p), bool)
        for _ in range(3):
            if int(keep.sum()) < self.config.min_cells:
                return None
            A = np.c_[p[keep, 0], p[keep, 1], np.ones(int(keep.sum()))]
            coef = np.linalg.lstsq(A, p[keep, 2], rcond=None)[0]
            keep = np.abs(np.c_[p[:, 0], p[:, 1], np.ones(len(p))] @ coef - p[:, 2]) <= 0.15
        a, b, c = (float(x) for x in coef)
        if not (abs(a) <= 0.15 and abs(b) <= 0.15 and abs(c) <= 0.5) or int(keep.sum()) < self.config.min_cells:
            return None
        return a, b, c

    def grid(self, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where each BEV cell lies in the left image for this query, on the ground plane ``fit_ground`` fits
        to ``depth`` (else, or where no plausible plane is found, the mounting's): ``map_u``, ``map_v`` (pixel
        coordinates, float32) and the ground mask (bool: in the image, and the stereo depth within
        ``ground_tolerance`` of the plane's)."""
        grid = (self.map_u, self.map_v, self.plane_z, self.in_image)
        if self.config.fit_ground:
            plane = self.ground_plane(depth)
            if plane is not None:
                grid = self._grid_on(plane)
        map_u, map_v, plane_z, in_image = grid
        d = cv2.remap(depth.astype(np.float32), map_u, map_v, cv2.INTER_NEAREST,
                      borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return map_u, map_v, in_image & (np.abs(d - plane_z) <= self.config.ground_tolerance * plane_z)

    def bev(self, features: np.ndarray, depth: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
        """The query's BEV channels and the mask (float32, 1 where the ground is seen, else 0)."""
        map_u, map_v, ground = self.grid(depth)
        mask = ground.astype(np.float32)
        chans = [self._normalize(cv2.remap(c, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE), mask)
                 for c in _channel_maps(features, self.config.channels)]
        return chans, mask

    def _normalize(self, img: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
        """Local contrast normalisation: (x - local mean) / local std over a Gaussian window (masked cells
        excluded), so that faint ground texture weighs as much as bright markings."""
        sigma = self.config.normalize_m / self.res
        if sigma <= 0:
            return img
        m = np.ones_like(img) if mask is None else mask
        blur = lambda a: cv2.GaussianBlur(a, (0, 0), sigma)
        wsum = np.maximum(blur(m), 1e-3)
        mu = blur(img * m) / wsum
        var = np.maximum(blur(img * img * m) / wsum - mu * mu, 0.0)
        return ((img - mu) / np.sqrt(var + 1e-4)).astype(np.float32) * m

    def _crop(self, pose: Pose2) -> list[np.ndarray]:
        """Satellite channels resampled on the BEV grid of ``pose``, grown by the search margin on every side."""
        X, Y = self._crop_x, self._crop_y
        c, s = math.cos(pose.yaw), math.sin(pose.yaw)
        wx, wy = pose.x + c * X - s * Y, pose.y + s * X + c * Y
        mu = ((wx - self.origin[0]) / self.res - 0.5).astype(np.float32)
        mv = ((self.origin[1] - wy) / self.res - 0.5).astype(np.float32)
        return [cv2.remap(ch, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0) for ch in self.sat]

    def correlate(self, chans: list[np.ndarray], mask: np.ndarray, pose: Pose2,
                  yaw_offsets_deg: tuple[float, ...] | None = None) -> tuple[float, Pose2]:
        """Best masked NCC around ``pose`` over the translations and heading offsets searched, and its pose."""
        best, best_pose = -np.inf, pose
        for dyaw in self.config.yaw_offsets_deg if yaw_offsets_deg is None else yaw_offsets_deg:
            p = Pose2(pose.x, pose.y, pose.yaw + math.radians(dyaw))
            crop = self._crop(p)
            r = sum(cv2.matchTemplate(cr, t, cv2.TM_CCOEFF_NORMED, mask=mask) for cr, t in zip(crop, chans)) / len(chans)
            r = np.nan_to_num(r, nan=-1.0, posinf=-1.0, neginf=-1.0)
            if self.config.shift_penalty > 0:
                k = (np.arange(r.shape[0]) - self.margin) * self.res, (np.arange(r.shape[1]) - self.margin) * self.res
                r = r - self.config.shift_penalty * (k[0][:, None] ** 2 + k[1][None, :] ** 2)
            i, j = np.unravel_index(int(np.argmax(r)), r.shape)
            if r[i, j] > best:
                di = _parabola_peak(r[i - 1, j], r[i, j], r[i + 1, j]) if 0 < i < r.shape[0] - 1 else 0.0
                dj = _parabola_peak(r[i, j - 1], r[i, j], r[i, j + 1]) if 0 < j < r.shape[1] - 1 else 0.0
                dx, dy = (i + di - self.margin) * self.res, (j + dj - self.margin) * self.res
                c, s = math.cos(p.yaw), math.sin(p.yaw)
                best, best_pose = float(r[i, j]), Pose2(p.x + c * dx - s * dy, p.y + s * dx + c * dy, p.yaw)
        return best, best_pose

    def align(self, features: np.ndarray, depth: np.ndarray, seeds: list[Pose2],
              log_prior: np.ndarray | None = None) -> Alignment | None:
        """The best pose around the ``seeds`` (by correlation plus ``prior_weight`` times the seeds'
        ``log_prior``); None where too little ground is seen."""
        chans, mask = self.bev(features, depth)
        n = int(mask.sum())
        if n < self.config.min_cells:
            return None
        # the seeds at their own heading first; then the other headings around the best of them only
        results = [self.correlate(chans, mask, s, (0.0,)) for s in seeds]
        prior = np.zeros(len(seeds)) if log_prior is None else np.asarray(log_prior, np.float64)
        k = int(np.argmax([r[0] + self.config.prior_weight * p for r, p in zip(results, prior)]))
        others = tuple(d for d in self.config.yaw_offsets_deg if d != 0.0)
        if others:
            c, p = self.correlate(chans, mask, seeds[k], others)
            if c > results[k][0]:
                results[k] = (c, p)
        return Alignment(results[k][1], results[k][0], k, n)

    def scan(self, features: np.ndarray, depth: np.ndarray, candidates: np.ndarray, search_m: float = 1.0,
             yaw_bin_deg: float = 2.0) -> np.ndarray | None:
        """Bird's-eye correlation of one query at every candidate pose: (C,) best masked NCC within
        ``search_m`` (each axis) of each candidate's position, at its heading rounded to a bin of
        360 / round(360 / ``yaw_bin_deg``) degrees, the position snapped to the map's pixel lattice of its
        group; None where too little ground is seen.

        A likelihood over the whole map from the ground view alone, independent of the dictionary (used to
        measure perceptual aliasing, :func:`satloc_env.experiments.scene_run.aliasing`). Candidates are grouped by heading
        bin and by connected stretches of path; each group's satellite crop is resampled once per candidate
        set (cached) and slid under the BEV by one ``cv2.matchTemplate``, so the cost grows with the length of
        path, not with the number of candidates."""
        if search_m < 0 or not 0 < yaw_bin_deg <= 10:
            raise ConfigError(f"scan: expected search_m >= 0 and 0 < yaw_bin_deg <= 10 (wider bins turn the view "
                              f"too far from a candidate's heading), got {search_m}, {yaw_bin_deg}")
        chans, mask = self.bev(features, depth)
        if int(mask.sum()) < self.config.min_cells:
            return None
        cand = np.asarray(candidates, np.float64)
        key = (cand.shape, hashlib.blake2b(np.ascontiguousarray(cand).tobytes(), digest_size=16).digest(),
               float(search_m), float(yaw_bin_deg))
        if self._scan_key != key:
            self._scan_groups, self._scan_key = self._scan_plan(cand, search_m, yaw_bin_deg), key
        m = int(math.ceil(search_m / self.res))
        kernel = np.ones((2 * m + 1, 2 * m + 1), np.uint8)
        out = np.full(len(cand), -1.0)
        for idx, crops, ri, rj in self._scan_groups:
            r = sum(cv2.matchTemplate(cr, t, cv2.TM_CCOEFF_NORMED, mask=mask) for cr, t in zip(crops, chans)) / len(chans)
            r = cv2.dilate(np.nan_to_num(r, nan=-1.0, posinf=-1.0, neginf=-1.0).astype(np.float32), kernel)
            out[idx] = r[ri, rj]
        return out

    def _scan_plan(self, cand: np.ndarray, search_m: float, yaw_bin_deg: float) -> list:
        """Groups of candidates (same heading bin, connected within 2 m) with their rotated satellite crops
        and each candidate's cell in the correlation map."""
        from scipy.sparse.csgraph import connected_components
        from scipy.spatial import cKDTree

        m = int(math.ceil(search_m / self.res))
        nx, ny = self.shape
        nbins = max(1, int(round(360.0 / yaw_bin_deg)))
        ybin = np.round(np.degrees(cand[:, 2]) / (360.0 / nbins)).astype(np.int64) % nbins
        groups = []
        for b in np.unique(ybin):
            sel = np.flatnonzero(ybin == b)
            tree = cKDTree(cand[sel, :2])
            _, comp = connected_components(tree.sparse_distance_matrix(tree, 2.0, output_type="coo_matrix"),
                                           directed=False)
            th = math.radians(b * 360.0 / nbins)
            c, s = math.cos(th), math.sin(th)
            for k in np.unique(comp):
                idx = sel[comp == k]
                a = cand[idx, 0] * c + cand[idx, 1] * s          # along the heading
                l = -cand[idx, 0] * s + cand[idx, 1] * c         # to its left
                a0, l0 = a.min() + self.x0 - m * self.res, l.min() + self.y0 - m * self.res
                na = int(math.ceil((a.max() - a.min()) / self.res)) + nx + 2 * m + 1
                nl = int(math.ceil((l.max() - l.min()) / self.res)) + ny + 2 * m + 1
                A, L = np.meshgrid(a0 + self.res * np.arange(na), l0 + self.res * np.arange(nl), indexing="ij")
                mu = ((A * c - L * s - self.origin[0]) / self.res - 0.5).astype(np.float32)
                mv = ((self.origin[1] - (A * s + L * c)) / self.res - 0.5).astype(np.float32)
                crops = [cv2.remap(ch, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
                         for ch in self.sat]
                # the template's first cell (x0, y0 in the vehicle frame) sits at crop cell (i, j) for a vehicle
                # at a = a0 + i * res - x0, l = l0 + j * res - y0
                ri = np.clip(np.round((a + self.x0 - a0) / self.res).astype(np.int64), 0, na - nx)
                rj = np.clip(np.round((l + self.y0 - l0) / self.res).astype(np.int64), 0, nl - ny)
                groups.append((idx, crops, ri, rj))
        return groups


def _parabola_peak(a: float, b: float, c: float) -> float:
    """Offset (in [-0.5, 0.5] samples) of the vertex of the parabola through (-1, a), (0, b), (1, c)."""
    a, b, c = float(a), float(b), float(c)
    den = a - 2 * b + c
    return float(np.clip(0.5 * (a - c) / den, -0.5, 0.5)) if den < 0 else 0.0


def posterior_peaks(candidates: np.ndarray, posterior: np.ndarray, k: int, separation_m: float) -> list[int]:
    """Indices of up to ``k`` most probable candidates at least ``separation_m`` apart."""
    order = np.argsort(-posterior)
    taken: list[int] = []
    for i in order:
        if posterior[i] <= 0 or len(taken) >= k:
            break
        if all(np.hypot(*(candidates[i, :2] - candidates[t, :2])) >= separation_m for t in taken):
            taken.append(int(i))
    return taken
