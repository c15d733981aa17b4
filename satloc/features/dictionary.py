"""The ground-satellite feature dictionary.

For each database frame, ground features are sampled on a fixed 2-D pixel grid, lifted to 3-D with stereo
depth and projected onto the satellite map at the frame's pose; samples with no valid depth, out of the depth
range or falling outside the map are rejected. Each kept sample i gives a pair (g_i, s_i): the ground
feature at its pixel and the dense satellite feature at its map point L(i).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .._threads import single_threaded_blas
from ..config import from_dict, to_dict
from ..errors import ConfigError, FormatError
from ..geometry import StereoCamera
from ..persist import ArraySpec, header_number, header_point, load_npz, nonfinite_path, save_npz
from ..satmap import SatelliteMap
from ..sequence import Frame, Sequence
from ..stereo import StereoConfig, StereoDepth
from .context import ContextConfig, ground_context, satellite_context
from .pixelwise import FeatureExtractor


@dataclass(frozen=True)
class GridConfig:
    """The fixed grid of ground-image samples (pixel coordinates at the image's own resolution)."""

    step_px: int = 12               # grid spacing
    row_start_frac: float = 0.3     # first grid row, as a fraction of the image height (skips most sky)
    min_depth_m: float = 3.0        # samples nearer or farther than this are rejected
    max_depth_m: float = 30.0

    def __post_init__(self):
        if self.step_px < 1:
            raise ConfigError(f"step_px: expected >= 1, got {self.step_px}")
        if not 0 < self.min_depth_m < self.max_depth_m:
            raise ConfigError(f"min_depth_m/max_depth_m: need 0 < min < max, got {self.min_depth_m}, {self.max_depth_m}")


def grid_pixels(camera: StereoCamera, grid: GridConfig) -> np.ndarray:
    """(n, 2) integer pixel coordinates (u, v) of the fixed sampling grid."""
    s = grid.step_px
    v0 = int(round(grid.row_start_frac * camera.height))
    vs = np.arange(v0 + s // 2, camera.height, s)
    us = np.arange(s // 2, camera.width, s)
    uu, vv = np.meshgrid(us, vs)
    return np.stack([uu.ravel(), vv.ravel()], axis=1)


def ground_samples(camera: StereoCamera, depth: np.ndarray, grid: GridConfig) -> tuple[np.ndarray, np.ndarray]:
    """Grid pixels with valid depth and their 3-D points in the vehicle frame: (m, 2) int, (m, 3) float."""
    if depth.shape != (camera.height, camera.width):
        raise ConfigError(f"depth map is {depth.shape[1]}x{depth.shape[0]}, the camera is {camera.width}x{camera.height}")
    uv = grid_pixels(camera, grid)
    d = depth[uv[:, 1], uv[:, 0]].astype(np.float64)
    ok = np.isfinite(d) & (d >= grid.min_depth_m) & (d <= grid.max_depth_m)
    uv, d = uv[ok], d[ok]
    pc = camera.backproject(uv.astype(np.float64), d)
    t = camera.vehicle_from_camera("left")
    return uv, pc @ t[:3, :3].T + t[:3, 3]


@dataclass
class SatelliteFeatures:
    """Dense features of a whole satellite map, computed once (stored as float16)."""

    features: np.ndarray            # (H, W, D) float16
    meters_per_pixel: float
    origin: tuple[float, float]
    name: str = ""

    @staticmethod
    def compute(satmap: SatelliteMap, extractor: FeatureExtractor) -> "SatelliteFeatures":
        f = extractor(satmap.image, "satellite")
        return SatelliteFeatures(f.astype(np.float16), satmap.meters_per_pixel, satmap.origin, extractor.name)

    @property
    def dim(self) -> int:
        return self.features.shape[2]

    def pixel_index(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest pixel (row, col) of map points (..., 2) and whether it lies inside the map."""
        xy = np.asarray(xy, dtype=np.float64)
        col = np.floor((xy[..., 0] - self.origin[0]) / self.meters_per_pixel).astype(np.int64)
        row = np.floor((self.origin[1] - xy[..., 1]) / self.meters_per_pixel).astype(np.int64)
        h, w = self.features.shape[:2]
        inside = (row >= 0) & (row < h) & (col >= 0) & (col < w)
        return np.where(inside, row * w + col, -1), inside

    def sample(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Features (n, D) float32 at map points (n, 2) (nearest pixel) and the inside-the-map mask."""
        flat, inside = self.pixel_index(xy)
        out = np.zeros((len(flat), self.dim), np.float32)
        out[inside] = self.features.reshape(-1, self.dim)[flat[inside]]
        return out, inside

    def features_at(self, flat: np.ndarray, context: ContextConfig, span: tuple[int, int]) -> np.ndarray:
        """(n, D) base features with their metric context (see :mod:`satloc.features.context`) at flat pixel indices."""
        w = self.features.shape[1]
        base = self.features.reshape(-1, self.dim)[flat].astype(np.float32)
        ctx = satellite_context(self.features, flat // w, flat % w, self.meters_per_pixel, context, span)
        return np.concatenate([base, ctx], axis=1)

    def save(self, path: str | Path, compress: bool = True) -> None:
        """In an npz (:func:`satloc.persist.save_npz`; ``compress`` False: stored as they are)."""
        save_npz(path, "satellite_features", {"features": self.features},
                 {"meters_per_pixel": self.meters_per_pixel, "origin": list(self.origin), "name": self.name},
                 compress=compress)

    @staticmethod
    def load(path: str | Path) -> "SatelliteFeatures":
        a, m = load_npz(path, "satellite_features", {"features": ArraySpec("f", (None, None, None))})
        f = a["features"]
        if min(f.shape) < 1:
            raise FormatError(f"{path}: array 'features': expected (H, W, D) with H, W, D >= 1, got {f.shape}")
        mpp = header_number(m, "meters_per_pixel", path, positive=True)
        origin = header_point(m, "origin", path)
        name = m.get("name", "")
        if not isinstance(name, str):
            raise FormatError(f"{path}: field 'name': expected a string, got {str(name)[:60]!r}")
        return SatelliteFeatures(f, float(mpp), origin, name)


@dataclass
class Dictionary:
    """Ground-satellite feature pairs with their map locations."""

    g: np.ndarray                   # (N, Dg) float32 ground features
    s: np.ndarray                   # (N, Ds) float32 satellite features at L(i)
    loc: np.ndarray                 # (N, 2) float64 map location L(i) (metres)
    frame: np.ndarray               # (N,) int32 database frame index
    poses: np.ndarray               # (F, 3) database frame poses (x, y, yaw)
    grid: GridConfig
    feature_name: str = ""
    context: ContextConfig = ContextConfig(scales_m=())

    def __post_init__(self):
        n = len(self.g)
        if not (len(self.s) == len(self.loc) == len(self.frame) == n):
            raise FormatError("dictionary arrays g, s, loc, frame must have the same length")

    def __len__(self) -> int:
        return len(self.g)

    def save(self, path: str | Path) -> None:
        save_npz(path, "dictionary", {"g": self.g, "s": self.s, "loc": self.loc, "frame": self.frame,
                                      "poses": self.poses},
                 {"grid": to_dict(self.grid), "feature_name": self.feature_name, "context": to_dict(self.context)})

    @staticmethod
    def load(path: str | Path) -> "Dictionary":
        a, m = load_npz(path, "dictionary", {
            "g": ArraySpec("f", ("N", "Dg")), "s": ArraySpec("f", ("N", "Ds")), "loc": ArraySpec("f", ("N", 2)),
            "frame": ArraySpec("iu", ("N",), min=0), "poses": ArraySpec("f", ("F", 3))})
        if min(a["g"].shape[1], a["s"].shape[1]) < 1:
            raise FormatError(f"{path}: arrays 'g' and 's' need at least one feature channel, got "
                              f"{a['g'].shape} and {a['s'].shape}")
        if len(a["frame"]) and a["frame"].max() >= len(a["poses"]):
            raise FormatError(f"{path}: array 'frame': index {a['frame'].max()} out of range for the "
                              f"{len(a['poses'])} database poses")
        bad = nonfinite_path({k: m.get(k) for k in ("grid", "context")})
        if bad is not None:
            raise FormatError(f"{path}: header field {bad}: expected a finite number")
        name = m.get("feature_name", "")
        if not isinstance(name, str):
            raise FormatError(f"{path}: field 'feature_name': expected a string, got {str(name)[:60]!r}")
        try:
            grid = from_dict(GridConfig, m.get("grid", {}), f"{path}: grid")
            context = from_dict(ContextConfig, m.get("context", {"scales_m": []}), f"{path}: context")
        except ConfigError as e:
            raise FormatError(str(e)) from e
        if not 0 <= grid.row_start_frac < 1:
            raise FormatError(f"{path}: grid.row_start_frac: expected a fraction in [0, 1), got {grid.row_start_frac}")
        return Dictionary(a["g"], a["s"], a["loc"], a["frame"], a["poses"], grid, name, context)


class FrameDepth:
    """Depth for a frame: stereo (the method) or the frame's stored depth (``source='frame'``, for ablations)."""

    def __init__(self, camera: StereoCamera, source: str = "stereo", stereo: StereoConfig = StereoConfig()):
        if source not in ("stereo", "frame"):
            raise ConfigError(f"depth source: expected 'stereo' or 'frame', got {source!r}")
        self.source = source
        self.stereo = StereoDepth(camera, stereo) if source == "stereo" else None

    def __call__(self, frame: Frame, where: str = "frame") -> np.ndarray:
        if self.source == "frame":
            if frame.depth is None:
                raise ConfigError(f"{where}: depth source 'frame' but the frame has no stored depth")
            return frame.depth
        return self.stereo(frame.left, frame.right)


def ground_features(fmap: np.ndarray, uv: np.ndarray, depth: np.ndarray, camera: StereoCamera,
                    context: ContextConfig, span: tuple[int, int]) -> np.ndarray:
    """(n, D) ground features at grid samples ``uv``: the pixel's own features and their metric context
    (``depth``: the samples' depths in metres)."""
    d = depth[uv[:, 1], uv[:, 0]].astype(np.float64)
    base = fmap[uv[:, 1], uv[:, 0]].astype(np.float32)
    if not context.scales_m:
        return base
    return np.concatenate([base, ground_context(fmap, uv, d, camera.fx, context, span)], axis=1)


def build_dictionary(database: Sequence, satfeat: SatelliteFeatures, extractor: FeatureExtractor,
                     grid: GridConfig = GridConfig(), depth_source: str = "stereo", progress: bool = True,
                     context: ContextConfig = ContextConfig()) -> Dictionary:
    """Pair ground features of every database frame with the satellite features where they project."""
    if len(database) == 0:
        raise ConfigError(f"database sequence {database.name!r} is empty")
    cam = database.camera
    depth_of = FrameDepth(cam, depth_source)
    span = context.span(extractor.dim, extractor.name)
    gs, ss, locs, frames = [], [], [], []
    with single_threaded_blas():  # per-frame work: see satloc._threads
        for k in tqdm(range(len(database)), desc="dictionary", unit="frame", disable=not progress, leave=False):
            f = database[k]
            if f.pose is None:
                raise ConfigError(f"database frame {k}: has no pose; a database needs poses")
            depth = depth_of(f, f"database frame {k}")
            uv, pv = ground_samples(cam, depth, grid)
            xy = f.pose.transform(pv[:, :2])
            flat, inside = satfeat.pixel_index(xy)
            if not inside.any():
                continue
            gs.append(ground_features(extractor(f.left, "ground"), uv[inside], depth, cam, context, span))
            ss.append(flat[inside])
            locs.append(xy[inside])
            frames.append(np.full(int(inside.sum()), k, np.int32))
    if not gs:
        raise ConfigError(f"database {database.name!r}: no ground sample projects inside the satellite map "
                          f"(check the poses and the map's georeference)")
    # satellite features of all samples at once (one pass over the map for the context windows)
    s = satfeat.features_at(np.concatenate(ss), context, span)
    return Dictionary(np.concatenate(gs).astype(np.float32), s,
                      np.concatenate(locs), np.concatenate(frames), database.poses, grid, extractor.name,
                      context)
