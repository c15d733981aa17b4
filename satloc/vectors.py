"""Map vectors as users export them: road centre lines from GeoJSON, GeoPackage or Shapefile files.

:func:`read_road_lines` reads the LineStrings (and the parts of MultiLineStrings) of a vector file with
``pyogrio`` into ``shapely`` geometries, in the coordinate reference system the file declares (a GeoJSON
file without one is CRS84: longitude, latitude in degrees). Other geometry types (points, polygons) are
skipped. Where a feature has an OpenStreetMap ``highway`` attribute, only the roads for cars are kept
(motorway ... residential, service, living_street, the ``*_link`` ramps, ``road``), so a whole OSM extract
can be given as it is.

Each line's road **width** (metres, the whole carriageway) comes from its attributes, the first usable of:

* ``width`` (or ``est_width``): a number of metres, or a text such as ``"7"``, ``"7.5 m"``;
* ``lanes`` (OpenStreetMap) or ``lane_number`` (SpaceNet road labels): the number of lanes x
  :data:`LANE_WIDTH_M` (``"2;3"`` reads as 2);

else ``default_width_m``. :meth:`RoadLines.to_frame` takes the lines to a :class:`~satloc.geoframe.GeoFrame`
(metres east / north of its origin) through pyproj.

This module is pure data: it knows nothing of the simulator.
"""
from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import ConfigError, FormatError

__all__ = ["LANE_WIDTH_M", "VECTOR_SUFFIXES", "RoadLines", "is_vector_file", "read_road_lines", "road_width",
           "vector_files"]

#: width of one driving lane, metres (as the simulator's generator paints them)
LANE_WIDTH_M = 3.5
#: file name endings read as vector files
VECTOR_SUFFIXES = (".geojson", ".json", ".gpkg", ".shp")
#: OpenStreetMap ``highway`` values kept as roads for cars
OSM_CAR_ROADS = frozenset({
    "motorway", "trunk", "primary", "secondary", "tertiary", "unclassified", "residential", "service",
    "living_street", "road", "motorway_link", "trunk_link", "primary_link", "secondary_link", "tertiary_link"})
_WIDTH_KEYS = ("width", "est_width")
_LANE_KEYS = ("lanes", "lane_number", "lane_numbe")   # a Shapefile's field names stop at 10 characters
_SHAPEFILE_SIDECARS = (".shx", ".dbf", ".prj", ".cpg")
_NUMBER = re.compile(r"^\s*([0-9]+(?:\.[0-9]*)?|\.[0-9]+)\s*(m|metres|meters)?\s*$", re.IGNORECASE)


def is_vector_file(path: str | os.PathLike) -> bool:
    """Whether ``path`` names a vector file by its ending (see :data:`VECTOR_SUFFIXES`)."""
    return Path(path).suffix.lower() in VECTOR_SUFFIXES


def vector_files(path: str | os.PathLike) -> list[Path]:
    """The file and its existing sidecars (a Shapefile's ``.shx``, ``.dbf``, ``.prj``, ``.cpg``)."""
    p = Path(path)
    out = [p]
    if p.suffix.lower() == ".shp":
        out += [q for q in (p.with_suffix(s) for s in _SHAPEFILE_SIDECARS) if q.is_file()]
    return out


@dataclass
class RoadLines:
    """Road centre lines and their widths, in one CRS."""

    lines: list[np.ndarray]   #: (N_i, 2) float64 coordinates of each line, N_i >= 2
    widths: np.ndarray        #: (L,) road width of each line, metres
    crs: object               #: pyproj.CRS of the coordinates
    source: str = ""          #: where they were read from (for messages)

    def to_crs(self, crs) -> "RoadLines":
        """The lines in another CRS (anything pyproj accepts); FormatError for points it cannot transform."""
        import pyproj

        dst = pyproj.CRS.from_user_input(crs)
        tr = pyproj.Transformer.from_crs(self.crs, dst, always_xy=True)
        out = []
        for i, xy in enumerate(self.lines):
            x, y = tr.transform(xy[:, 0], xy[:, 1], errcheck=False)
            q = np.stack([np.asarray(x, np.float64), np.asarray(y, np.float64)], axis=1)
            if not np.all(np.isfinite(q)):
                raise FormatError(f"{self.source}: line {i} has points outside the coordinate system's domain "
                                  f"({self.crs.name} to {dst.name})")
            out.append(q)
        return RoadLines(out, self.widths.copy(), dst, self.source)

    def to_frame(self, frame) -> "RoadLines":
        """The lines in metres of a :class:`~satloc.geoframe.GeoFrame`."""
        return self.to_crs(frame.crs)


def road_width(attrs: dict, default_width_m: float) -> float:
    """The road width (metres) from a feature's attributes (see the module docstring)."""
    low = {str(k).lower(): v for k, v in attrs.items()}
    for k in _WIDTH_KEYS:
        w = _number(low.get(k))
        if w is not None and 0.5 <= w <= 100:
            return w
    for k in _LANE_KEYS:
        n = _number(low.get(k), first_of_list=True)
        if n is not None and 1 <= n <= 20:
            return round(n) * LANE_WIDTH_M
    return float(default_width_m)


def _number(v, first_of_list: bool = False) -> float | None:
    if v is None or isinstance(v, bool):
        return None
    if isinstance(v, (int, float, np.integer, np.floating)):
        f = float(v)
        return f if math.isfinite(f) else None
    s = str(v)
    if first_of_list:
        s = s.split(";")[0]
    m = _NUMBER.match(s)
    return float(m.group(1)) if m else None


def read_road_lines(path: str | os.PathLike, default_width_m: float = 2 * LANE_WIDTH_M) -> RoadLines:
    """The road centre lines of a vector file (every layer with line geometries), in its own CRS (see the
    module docstring). FormatError naming the file when it cannot be read, declares no CRS (a Shapefile
    without ``.prj``) or holds no line."""
    import pyogrio
    import pyproj
    import shapely

    p = Path(path)
    if not p.is_file():
        raise FormatError(f"{p}: vector file not found")
    if not default_width_m > 0:
        raise ConfigError(f"default road width: expected metres > 0, got {default_width_m}")
    try:
        layers = [str(name) for name, gtype in pyogrio.list_layers(p)     # all but point and polygon layers
                  if not any(k in str(gtype).upper() for k in ("POINT", "POLYGON"))]
    except Exception as e:  # pyogrio raises DataSourceError / DataLayerError and GDAL's own errors
        raise FormatError(f"{p}: not a readable vector file ({type(e).__name__}: {str(e)[:200]})") from e
    lines: list[np.ndarray] = []
    widths: list[float] = []
    crs = None
    for layer in layers:
        try:
            meta, _, geoms, fields = pyogrio.raw.read(p, layer=layer)
        except Exception as e:
            raise FormatError(f"{p}: layer {layer!r} is not readable ({type(e).__name__}: {str(e)[:200]})") from e
        names = [str(n) for n in meta["fields"]]
        if meta.get("crs") is None:
            if p.suffix.lower() in (".geojson", ".json"):
                layer_crs = pyproj.CRS.from_user_input("OGC:CRS84")
            else:
                raise FormatError(f"{p}: layer {layer!r} declares no coordinate reference system"
                                  + (f" (no {p.with_suffix('.prj').name} beside it)" if p.suffix.lower() == ".shp"
                                     else ""))
        else:
            layer_crs = pyproj.CRS.from_user_input(meta["crs"])
        shapes = shapely.from_wkb(geoms)
        got = 0
        for i, g in enumerate(shapes):
            if g is None or g.is_empty:
                continue
            attrs = {n: f[i] for n, f in zip(names, fields)}
            hw = attrs.get("highway")
            if hw is not None and str(hw) not in OSM_CAR_ROADS:
                continue
            parts = list(g.geoms) if g.geom_type == "MultiLineString" else [g] if g.geom_type == "LineString" else []
            for part in parts:
                xy = np.asarray(shapely.get_coordinates(part), np.float64)
                if len(xy) >= 2 and np.all(np.isfinite(xy)):
                    lines.append(xy)
                    widths.append(road_width(attrs, default_width_m))
                    got += 1
        if got:
            if crs is not None and not crs.equals(layer_crs, ignore_axis_order=True):
                raise FormatError(f"{p}: its line layers are in different coordinate systems ({crs.name}, "
                                  f"{layer_crs.name})")
            crs = layer_crs
    if not lines:
        raise FormatError(f"{p}: holds no LineString (road centre lines are read from LineString and "
                          f"MultiLineString features)")
    return RoadLines(lines, np.asarray(widths, np.float64), crs, str(p))
