"""Heights of buildings and trees from a surface model: a DSM (elevations of the surface) or an nDSM (heights
above the ground) as a GeoTIFF in any CRS.

:class:`HeightRaster` reads the raster's first band (its nodata, mask and NaN samples are no data) and
answers, for a footprint given in another CRS (a scene's metres), how high the object on it stands:

* **top**: the 90th percentile of the samples whose centres lie inside the footprint (the roof's ridge and
  chimneys above it do not count, nor do a few samples of the street the footprint's edge takes in);
* **ground**: the median of the samples in a ring 2-8 m around the footprint, less every other footprint
  (the ``exclude`` geometry): on an nDSM about 0, on a DSM the terrain's elevation there;
* the height is top minus ground, or None where fewer than :data:`MIN_SAMPLES` valid samples lie inside or
  in the ring, or where the difference is below 1 m (the model has no object there).

So one rule serves both kinds of model, and no flag says which one a file is. This module is pure data: it
knows nothing of the simulator.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import FormatError

__all__ = ["MIN_SAMPLES", "HeightRaster"]

#: samples needed inside a footprint and in its ground ring
MIN_SAMPLES = 3
_RING_M = (2.0, 8.0)
_TOP_PERCENTILE = 90.0


class HeightRaster:
    """A surface model's first band in memory, and how to reach it from ``crs`` (see the module docstring)."""

    def __init__(self, path: str | os.PathLike, crs):
        import pyproj
        import rasterio

        self.path = Path(path)
        if not self.path.is_file():
            raise FormatError(f"{self.path}: height raster not found")
        try:
            with rasterio.open(self.path) as ds:
                if ds.crs is None:
                    raise FormatError(f"{self.path}: declares no coordinate reference system; a height raster "
                                      f"needs one to be placed under the footprints")
                band = ds.read(1, masked=True)
                self.transform = ds.transform
                raster_crs = pyproj.CRS.from_user_input(ds.crs.to_wkt())
        except rasterio.errors.RasterioIOError as e:
            raise FormatError(f"{self.path}: not a readable raster ({str(e)[:200]})") from e
        values = np.ma.asarray(band).astype(np.float64).filled(np.nan)   # integer models with nodata too
        values[~np.isfinite(values)] = np.nan
        if not np.isfinite(values).any():
            raise FormatError(f"{self.path}: holds no valid sample (every pixel nodata, masked or NaN)")
        self.values = values
        self._to = pyproj.Transformer.from_crs(pyproj.CRS.from_user_input(crs), raster_crs, always_xy=True)

    def _samples(self, geom) -> np.ndarray:
        """Valid samples whose pixel centres lie inside ``geom`` (a shapely geometry in the raster's CRS)."""
        from affine import Affine
        from rasterio.features import geometry_mask
        from rasterio.windows import from_bounds

        h, w = self.values.shape
        win = from_bounds(*geom.bounds, transform=self.transform).round_offsets().round_lengths()
        r0, c0 = max(0, int(win.row_off) - 1), max(0, int(win.col_off) - 1)
        r1, c1 = min(h, int(win.row_off + win.height) + 2), min(w, int(win.col_off + win.width) + 2)
        if r1 <= r0 or c1 <= c0:
            return np.zeros(0)
        t = self.transform   # the window's transform: its origin moved to pixel (c0, r0)
        sub = Affine(t.a, t.b, t.c + c0 * t.a + r0 * t.b, t.d, t.e, t.f + c0 * t.d + r0 * t.e)
        inside = ~geometry_mask([geom], out_shape=(r1 - r0, c1 - c0), transform=sub, all_touched=False)
        v = self.values[r0:r1, c0:c1][inside]
        return v[np.isfinite(v)]

    def _in_raster_crs(self, geom):
        import shapely

        return shapely.transform(geom, lambda xy: np.stack(self._to.transform(xy[:, 0], xy[:, 1]), axis=1))

    def height(self, footprint, exclude=None) -> float | None:
        """The height (metres) of the object on ``footprint`` (a shapely Polygon in the CRS given to the
        constructor), the ground measured around it less ``exclude`` (other footprints), or None."""
        ring = footprint.buffer(_RING_M[1]).difference(footprint.buffer(_RING_M[0]))
        if exclude is not None and not exclude.is_empty:
            ring = ring.difference(exclude)
        top = self._samples(self._in_raster_crs(footprint))
        ground = self._samples(self._in_raster_crs(ring)) if not ring.is_empty else np.zeros(0)
        if len(top) < MIN_SAMPLES or len(ground) < MIN_SAMPLES:
            return None
        h = float(np.percentile(top, _TOP_PERCENTILE) - np.median(ground))
        return h if h >= 1.0 else None

