"""Metric context: pixel features pooled over windows of fixed size in metres, on both views.

A pixel's own semantic attributes (road, sidewalk, ...) say little about *where* it is: every road pixel looks
alike. What surrounds it does: how far the curb is, whether a crosswalk, a park or a parking lot is near. So
each sample's feature is its own pixel-wise feature followed by the mean of chosen channels (by default the
semantic class probabilities) over square windows of ``scales_m`` metres centred on it:

* satellite view: the window is ``scale / metres_per_pixel`` pixels wide;
* ground view: a window of ``scale`` metres at the sample's stereo depth ``d`` is ``fx * scale / d`` pixels
  wide in the image (clipped to the image), so the same world extent is pooled whatever the viewpoint.

Box means come from integral images (float64), so their cost does not depend on the window size. The views
pool different things (a ground window is a frontal slice of the world, a satellite window a horizontal one);
the method never compares g with s directly, only through the dictionary, so each needs only to be consistent
with itself across viewpoints and discriminative of place.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import ConfigError


@dataclass(frozen=True)
class ContextConfig:
    scales_m: tuple[float, ...] = (1.0, 3.0, 9.0, 27.0)   # window sizes; () turns context off
    channels: tuple[int, int] | None = None              # [start, stop) of the pooled base channels; None: the
                                                         # feature set's semantic channels (all for plain RGB)
    weight: float = 1.0                                   # scale of the pooled channels relative to the base

    def __post_init__(self):
        if any(s <= 0 for s in self.scales_m):
            raise ConfigError(f"context.scales_m: expected positive sizes in metres, got {self.scales_m}")
        if self.channels is not None and not (0 <= self.channels[0] < self.channels[1]):
            raise ConfigError(f"context.channels: expected [start, stop) with 0 <= start < stop, got {self.channels}")

    def span(self, base_dim: int, feature_name: str = "") -> tuple[int, int]:
        """The pooled channel range for a base feature of ``base_dim`` channels."""
        if self.channels is not None:
            if self.channels[1] > base_dim:
                raise ConfigError(f"context.channels {self.channels}: the features have only {base_dim} channels")
            return self.channels
        from ..labels import NUM_CLASSES

        if feature_name in ("default", "semantic") and base_dim >= NUM_CLASSES:
            return base_dim - NUM_CLASSES, base_dim
        return 0, base_dim

    def dim(self, base_dim: int, feature_name: str = "") -> int:
        a, b = self.span(base_dim, feature_name)
        return base_dim + len(self.scales_m) * (b - a)


def _box_means(ii: np.ndarray, r0, r1, c0, c1) -> np.ndarray:
    """Means over [r0, r1) x [c0, c1) from an integral image (h+1, w+1, C)."""
    s = ii[r1, c1] - ii[r0, c1] - ii[r1, c0] + ii[r0, c0]
    area = np.maximum((r1 - r0) * (c1 - c0), 1).astype(np.float64)
    return (s / area[:, None]).astype(np.float32)


def ground_context(fmap: np.ndarray, uv: np.ndarray, depth: np.ndarray, fx: float, cfg: ContextConfig,
                   span: tuple[int, int]) -> np.ndarray:
    """(n, len(scales) * C) window means around ground samples ``uv`` (n, 2) at depths ``depth`` (n,)."""
    n = len(uv)
    if not cfg.scales_m or n == 0:
        return np.zeros((n, len(cfg.scales_m) * (span[1] - span[0])), np.float32)
    h, w = fmap.shape[:2]
    # float64 sums of the channels as they are (converting the input first would cost a copy and be no more exact)
    src = fmap[..., span[0]:span[1]]
    src = np.ascontiguousarray(src, dtype=src.dtype if src.dtype in (np.float32, np.float64) else np.float32)
    ii = cv2.integral(src, sdepth=cv2.CV_64F)
    ii = ii.reshape(h + 1, w + 1, -1)
    u, v = uv[:, 0].astype(np.int64), uv[:, 1].astype(np.int64)
    out = []
    for s in cfg.scales_m:
        r = np.maximum(np.round(fx * s / np.maximum(depth, 1e-3) / 2.0), 0).astype(np.int64)
        out.append(_box_means(ii, np.clip(v - r, 0, h), np.clip(v + r + 1, 0, h),
                              np.clip(u - r, 0, w), np.clip(u + r + 1, 0, w)))
    return np.concatenate(out, axis=1) * np.float32(cfg.weight)


def satellite_context(fmap: np.ndarray, rows: np.ndarray, cols: np.ndarray, meters_per_pixel: float,
                      cfg: ContextConfig, span: tuple[int, int], strip: int = 256) -> np.ndarray:
    """(n, len(scales) * C) window means around map pixels (rows, cols); computed strip by strip so memory
    stays bounded on large maps."""
    n = len(rows)
    c = span[1] - span[0]
    out = np.zeros((n, len(cfg.scales_m) * c), np.float32)
    if not cfg.scales_m or n == 0:
        return out
    h, w = fmap.shape[:2]
    half = [int(round(s / meters_per_pixel / 2.0)) for s in cfg.scales_m]
    margin = max(half)
    order = np.argsort(rows, kind="stable")
    rs = rows[order]
    for top in range(0, h, strip):
        lo, hi = np.searchsorted(rs, top), np.searchsorted(rs, top + strip)
        if lo == hi:
            continue
        a, b = max(0, top - margin), min(h, top + strip + margin + 1)
        ii = cv2.integral(np.ascontiguousarray(fmap[a:b, :, span[0]:span[1]], dtype=np.float64))
        ii = ii.reshape(b - a + 1, w + 1, -1)
        idx = order[lo:hi]
        r, cc = rows[idx] - a, cols[idx]
        for k, hr in enumerate(half):
            out[idx, k * c:(k + 1) * c] = _box_means(
                ii, np.clip(r - hr, 0, b - a), np.clip(r + hr + 1, 0, b - a), np.clip(cc - hr, 0, w),
                np.clip(cc + hr + 1, 0, w))
    # windows clipped by the strip's margin only at the map border, where the map itself ends
    return out * np.float32(cfg.weight)
