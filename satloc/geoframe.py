"""The metric map frame of real data: where a longitude/latitude lies on the map plane, and back.

Synthetic scenes use a local frame with no place on Earth. Real data (KITTI, Malaga, georeferenced
satellite images) shares one :class:`GeoFrame`: the Mercator projection scaled at a reference latitude
``lat0``, with its origin at (``lon0``, ``lat0``), x east and y north in metres. This is the projection
KITTI's development kit uses for OXTS positions (``scale = cos(lat0)``; Mercator on a sphere of radius
6378137 m), so KITTI poses read through it match the devkit's. It is conformal (headings are true, no grid
convergence) and its scale error grows by about 1.6e-4 per km north or south of ``lat0`` at 49 degrees.

The frame is a PROJ Mercator (variant B, ``lat_ts = lat0``) on the WGS84 sphere, the way EPSG:3857 treats
WGS84 coordinates, with a false northing that puts ``lat0`` at y = 0: pyproj does every conversion, and
rasterio can reproject an image straight into it (:mod:`satloc.geodata.georef`).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from .errors import ConfigError

EARTH_RADIUS_M = 6378137.0  # the sphere of Web Mercator and of KITTI's devkit


@dataclass(frozen=True)
class GeoFrame:
    """Local metric frame: Mercator scaled at ``lat0``, origin at (``lon0``, ``lat0``), x east, y north."""

    lon0: float
    lat0: float

    def __post_init__(self):
        lon0, lat0 = float(self.lon0), float(self.lat0)
        if not (math.isfinite(lon0) and -180.0 <= lon0 <= 180.0):
            raise ConfigError(f"GeoFrame.lon0: expected a longitude in [-180, 180] degrees, got {self.lon0!r}")
        if not (math.isfinite(lat0) and -85.0 <= lat0 <= 85.0):
            raise ConfigError(f"GeoFrame.lat0: expected a latitude in [-85, 85] degrees (Mercator), got {self.lat0!r}")
        object.__setattr__(self, "lon0", lon0)
        object.__setattr__(self, "lat0", lat0)

    @property
    def scale(self) -> float:
        """Metres on the ground per Web-Mercator metre at ``lat0`` (KITTI's ``scale``)."""
        return math.cos(math.radians(self.lat0))

    @property
    def proj4(self) -> str:
        """The frame as a PROJ string (usable as a pyproj / rasterio CRS)."""
        return _proj4(self.lon0, self.lat0)

    @property
    def crs(self):
        """The frame as a :class:`pyproj.CRS`."""
        return _crs(self.lon0, self.lat0)

    def to_map(self, lonlat) -> np.ndarray:
        """Map-frame metres (..., 2) of WGS84 (lon, lat) degrees (..., 2)."""
        ll = np.asarray(lonlat, dtype=np.float64)
        if ll.shape[-1:] != (2,):
            raise ConfigError(f"GeoFrame.to_map: expected (..., 2) lon/lat values, got shape {ll.shape}")
        x, y = _to_frame(self.lon0, self.lat0).transform(ll[..., 0], ll[..., 1])
        return np.stack([np.asarray(x, np.float64), np.asarray(y, np.float64)], axis=-1)

    def to_lonlat(self, xy) -> np.ndarray:
        """WGS84 (lon, lat) degrees (..., 2) of map-frame metres (..., 2)."""
        p = np.asarray(xy, dtype=np.float64)
        if p.shape[-1:] != (2,):
            raise ConfigError(f"GeoFrame.to_lonlat: expected (..., 2) x/y values, got shape {p.shape}")
        lon, lat = _to_frame(self.lon0, self.lat0).transform(p[..., 0], p[..., 1], direction="INVERSE")
        return np.stack([np.asarray(lon, np.float64), np.asarray(lat, np.float64)], axis=-1)

    def to_dict(self) -> dict:
        return {"type": "mercator_scaled", "lon0": self.lon0, "lat0": self.lat0}

    @staticmethod
    def from_dict(d, where: str = "geo frame") -> "GeoFrame":
        if not isinstance(d, dict) or d.get("type") != "mercator_scaled" or set(d) != {"type", "lon0", "lat0"}:
            raise ConfigError(f"{where}: expected {{type: mercator_scaled, lon0: <deg>, lat0: <deg>}}, got {d!r}")
        for k in ("lon0", "lat0"):
            if isinstance(d[k], bool) or not isinstance(d[k], (int, float)):
                raise ConfigError(f"{where}.{k}: expected a number, got {d[k]!r}")
        try:
            return GeoFrame(d["lon0"], d["lat0"])
        except ConfigError as e:
            raise ConfigError(f"{where}: {e}") from e


def _proj4(lon0: float, lat0: float) -> str:
    import pyproj

    merc = pyproj.Transformer.from_crs("EPSG:4326", _merc_crs(lon0, lat0, 0.0), always_xy=True)
    _, north = merc.transform(lon0, lat0)
    return _merc_string(lon0, lat0, -north)


def _merc_string(lon0: float, lat0: float, y0: float) -> str:
    return (f"+proj=merc +a={EARTH_RADIUS_M:.1f} +b={EARTH_RADIUS_M:.1f} +lat_ts={lat0!r} +lon_0={lon0!r} "
            f"+x_0=0 +y_0={y0!r} +k=1 +units=m +nadgrids=@null +wktext +no_defs")


def _merc_crs(lon0: float, lat0: float, y0: float):
    import pyproj

    return pyproj.CRS.from_proj4(_merc_string(lon0, lat0, y0))


@functools.lru_cache(maxsize=64)
def _crs(lon0: float, lat0: float):
    import pyproj

    return pyproj.CRS.from_proj4(_proj4(lon0, lat0))


@functools.lru_cache(maxsize=64)
def _to_frame(lon0: float, lat0: float):
    import pyproj

    return pyproj.Transformer.from_crs("EPSG:4326", _crs(lon0, lat0), always_xy=True)
