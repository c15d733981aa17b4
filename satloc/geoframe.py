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
import warnings
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


# --- datums ----------------------------------------------------------------------------------------------------

#: Helmert methods of the EPSG registry whose parameters PROJ's ``+towgs84`` takes (rotations' sign: the
#: position-vector convention, which ``+towgs84`` uses; coordinate-frame rotations have the opposite sign)
_HELMERT = {"Geocentric translations": 0, "Position Vector transformation": 1, "Coordinate Frame rotation": -1}
_ROTATION_ARCSEC = {"arc-second": 1.0, "microradian": 0.206264806247, "radian": 206264.806247,
                    "milliarc-second": 1e-3}
_SCALE_PPM = {"parts per million": 1.0, "unity": 1e6, "parts per billion": 1e-3}


def wgs84_bound(crs):
    """``crs`` (anything pyproj reads) as a :class:`pyproj.CRS` that carries its datum's shift to WGS84 (PROJ's
    ``+towgs84``, from the best transformation of the EPSG registry), where that shift is a Helmert
    transformation and not zero; else ``crs`` as it is.

    Why: the map frame (:class:`GeoFrame`) is a Mercator on the WGS84 sphere that PROJ ties to WGS84 by a null
    grid, as EPSG:3857 is. From a CRS on another datum (the Swiss CH1903+ of LV95, Austria's MGI, the Dutch
    Amersfoort of RD New, OSGB36 of the British National Grid, DHDN of Gauss-Krueger) PROJ finds no path to
    such a frame and takes a ballpark one that ignores the datum shift: on LV95 near Zurich, 57 m east and 103 m
    north off. Tied to WGS84, the source goes through WGS84 to the frame, as vectors in WGS84 lon/lat do.
    Datums within a metre of WGS84 (ETRS89, NAD83, RGF93, GDA) have a zero shift and stay as they are."""
    import pyproj
    from pyproj.transformer import TransformerGroup

    src = pyproj.CRS.from_user_input(crs)
    geod = src.geodetic_crs
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        p4 = src.to_proj4() or ""
    if src.is_bound or geod is None or "+towgs84" in p4 or "+nadgrids" in p4:
        return src
    wgs84 = pyproj.CRS.from_epsg(4326)
    if geod.datum is not None and geod.datum.name in (wgs84.datum.name, "World Geodetic System 1984"):
        return src
    try:
        group = TransformerGroup(geod, wgs84, always_xy=True)
    except pyproj.exceptions.ProjError:
        return src
    for t in group.transformers:
        params = _towgs84(t.to_json_dict())
        if params is not None:
            if not any(params):
                return src
            with warnings.catch_warnings():   # the PROJ string keeps what +towgs84 needs: projection and ellipsoid
                warnings.simplefilter("ignore", UserWarning)
                p4 = src.to_proj4().replace("+type=crs", "").strip()
            return pyproj.CRS.from_proj4(f"{p4} +towgs84={','.join(f'{v:.10g}' for v in params)}")
    return src


def _towgs84(op: dict) -> list[float] | None:
    """The seven ``+towgs84`` parameters of a Helmert step of a PROJ JSON coordinate operation, else None."""
    steps = op.get("steps") or [op]
    core = [s for s in steps if s.get("type") != "Conversion" and "axis order" not in str(s.get("name", ""))]
    if len(core) != 1:
        return None
    method = str((core[0].get("method") or {}).get("name", ""))
    sign = next((v for k, v in _HELMERT.items() if method.startswith(k)), None)
    if sign is None:
        return None
    vals = {}
    for p in core[0].get("parameters", []):
        unit = p.get("unit")
        unit = unit.get("name") if isinstance(unit, dict) else unit
        vals[p.get("name")] = (float(p.get("value", 0.0)), unit)
    out = []
    for axis in ("X", "Y", "Z"):
        v, unit = vals.get(f"{axis}-axis translation", (0.0, "metre"))
        if unit not in ("metre", None):
            return None
        out.append(v)
    for axis in ("X", "Y", "Z"):
        v, unit = vals.get(f"{axis}-axis rotation", (0.0, "arc-second"))
        if unit not in _ROTATION_ARCSEC:
            return None
        out.append(sign * v * _ROTATION_ARCSEC[unit] if sign else 0.0)
    v, unit = vals.get("Scale difference", (0.0, "parts per million"))
    if unit not in _SCALE_PPM:
        return None
    out.append(v * _SCALE_PPM[unit])
    return out
