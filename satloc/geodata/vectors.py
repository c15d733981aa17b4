"""Map vectors as users export them: road centre lines, building footprints and trees from GeoJSON,
GeoPackage or Shapefile files.

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

**Buildings** (:func:`read_footprints`): the exterior rings of Polygons and MultiPolygons (courtyards are
filled), each with its **height** from its attributes, the first usable of ``height`` / ``building:height``
(metres, ``"12 m"`` reads as 12) and ``building:levels`` x :data:`LEVEL_HEIGHT_M`, else None (the caller
picks one). Where the features have an OpenStreetMap ``building`` attribute, those without one (or with
``building=no``) are skipped, so a whole OSM export can be given as it is.

**Trees** (:func:`read_trees`): Points are single trees; Polygons and MultiPolygons are canopy areas. Each
keeps its ``height`` and its crown radius (``diameter_crown`` / ``crown_diameter`` / 2, or ``radius``,
metres) where the attributes give them, else None. Where the features have ``natural`` or ``landuse``
attributes, only ``natural=tree`` / ``wood`` / ``tree_row`` and ``landuse=forest`` are trees.

This module is pure data: it knows nothing of the simulator.
"""
from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError, FormatError

__all__ = ["LANE_WIDTH_M", "LEVEL_HEIGHT_M", "VECTOR_SUFFIXES", "Footprints", "RoadLines", "Trees",
           "building_height", "is_vector_file", "read_footprints", "read_road_lines", "read_trees", "road_width",
           "vector_files"]

#: width of one driving lane, metres (as the simulator's generator paints them)
LANE_WIDTH_M = 3.5
#: height of one storey, metres (``building:levels``)
LEVEL_HEIGHT_M = 3.0
#: file name endings read as vector files
VECTOR_SUFFIXES = (".geojson", ".json", ".gpkg", ".shp")
#: OpenStreetMap ``highway`` values kept as roads for cars
OSM_CAR_ROADS = frozenset({
    "motorway", "trunk", "primary", "secondary", "tertiary", "unclassified", "residential", "service",
    "living_street", "road", "motorway_link", "trunk_link", "primary_link", "secondary_link", "tertiary_link"})
_WIDTH_KEYS = ("width", "est_width")
_HEIGHT_KEYS = ("height", "building:height", "building_h")
_LEVEL_KEYS = ("building:levels", "levels", "building_l")      # Shapefile names stop at 10 characters
_CROWN_KEYS = ("diameter_crown", "crown_diameter", "diameter_c")
_TREE_NATURAL = frozenset({"tree", "wood", "tree_row"})
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

        return RoadLines(_to_crs(self.lines, self.crs, crs, self.source), self.widths.copy(),
                         pyproj.CRS.from_user_input(crs), self.source)

    def to_frame(self, frame) -> "RoadLines":
        """The lines in metres of a :class:`~satloc.geoframe.GeoFrame`."""
        return self.to_crs(frame.crs)


def _measure(attrs: dict, value_keys, value_range, count_keys, count_range, unit: float) -> float | None:
    """The first usable of a measured value (``value_keys``, metres within ``value_range``) and a count
    (``count_keys``, within ``count_range``, ``"2;3"`` reads as 2) times ``unit``; else None."""
    low = {str(k).lower(): v for k, v in attrs.items()}
    for k in value_keys:
        v = _number(low.get(k))
        if v is not None and value_range[0] <= v <= value_range[1]:
            return v
    for k in count_keys:
        n = _number(low.get(k), first_of_list=True)
        if n is not None and count_range[0] <= n <= count_range[1]:
            return round(n) * unit
    return None


def road_width(attrs: dict, default_width_m: float) -> float:
    """The road width (metres) from a feature's attributes (see the module docstring)."""
    w = _measure(attrs, _WIDTH_KEYS, (0.5, 100), _LANE_KEYS, (1, 20), LANE_WIDTH_M)
    return float(default_width_m) if w is None else w


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
    import shapely

    if not default_width_m > 0:
        raise ConfigError(f"default road width: expected metres > 0, got {default_width_m}")
    lines: list[np.ndarray] = []
    widths: list[float] = []
    crs = None
    for g, attrs, layer_crs in _read_layers(path, ("LINE",), "road centre lines"):
        hw = attrs.get("highway")
        if hw is not None and str(hw) not in OSM_CAR_ROADS:
            continue
        parts = list(g.geoms) if g.geom_type == "MultiLineString" else [g] if g.geom_type == "LineString" else []
        for part in parts:
            xy = np.asarray(shapely.get_coordinates(part), np.float64)
            if len(xy) >= 2 and np.all(np.isfinite(xy)):
                crs = _one_crs(crs, layer_crs, path)
                lines.append(xy)
                widths.append(road_width(attrs, default_width_m))
    if not lines:
        raise FormatError(f"{path}: holds no LineString (road centre lines are read from LineString and "
                          f"MultiLineString features)")
    return RoadLines(lines, np.asarray(widths, np.float64), crs, str(path))


def _to_crs(parts: list[np.ndarray], src, crs, source: str) -> list[np.ndarray]:
    """Coordinate arrays (N, 2) taken from CRS ``src`` to ``crs`` through pyproj; FormatError naming
    ``source`` for points outside the coordinate system's domain."""
    import pyproj

    dst = pyproj.CRS.from_user_input(crs)
    tr = pyproj.Transformer.from_crs(src, dst, always_xy=True)
    out = []
    for i, xy in enumerate(parts):
        x, y = tr.transform(xy[:, 0], xy[:, 1], errcheck=False)
        q = np.stack([np.asarray(x, np.float64), np.asarray(y, np.float64)], axis=1)
        if not np.all(np.isfinite(q)):
            raise FormatError(f"{source}: feature {i} has points outside the coordinate system's domain "
                              f"({src.name} to {dst.name})")
        out.append(q)
    return out


def building_height(attrs: dict) -> float | None:
    """A building's height (metres) from its attributes (see the module docstring), else None."""
    return _measure(attrs, _HEIGHT_KEYS, (1.0, 1000.0), _LEVEL_KEYS, (1, 300), LEVEL_HEIGHT_M)


@dataclass
class Footprints:
    """Building footprints (exterior rings) and their heights where the attributes give them."""

    rings: list[np.ndarray]            #: (N_i, 2) float64 ring of each footprint, not closed, N_i >= 3
    heights: list[float | None]        #: metres, or None where the attributes give none
    crs: object                        #: pyproj.CRS of the coordinates
    source: str = ""

    def to_frame(self, frame) -> "Footprints":
        """The footprints in metres of a :class:`~satloc.geoframe.GeoFrame`."""
        return Footprints(_to_crs(self.rings, self.crs, frame.crs, self.source), list(self.heights), frame.crs,
                          self.source)


@dataclass
class Trees:
    """Trees: single ones (points) and canopy areas (rings), with heights and crown radii where given."""

    points: np.ndarray                 #: (P, 2) float64 positions of single trees
    point_heights: list[float | None]
    point_radii: list[float | None]
    canopies: list[np.ndarray]         #: (N_i, 2) rings of canopy areas, not closed
    canopy_heights: list[float | None]
    crs: object
    source: str = ""

    def to_frame(self, frame) -> "Trees":
        """The trees in metres of a :class:`~satloc.geoframe.GeoFrame`."""
        pts = _to_crs([self.points], self.crs, frame.crs, self.source)[0] if len(self.points) else self.points
        return Trees(pts, list(self.point_heights), list(self.point_radii),
                     _to_crs(self.canopies, self.crs, frame.crs, self.source), list(self.canopy_heights),
                     frame.crs, self.source)


def _read_layers(path: str | os.PathLike, wanted: tuple[str, ...], what: str):
    """Yield (shapely geometry, attributes, pyproj CRS) of every feature of the file's layers whose geometry
    type contains one of ``wanted`` (``"POINT"``, ``"POLYGON"``, ``"LINE"``); FormatError naming the file."""
    import pyogrio
    import pyproj
    import shapely

    p = Path(path)
    if not p.is_file():
        raise FormatError(f"{p}: vector file not found")
    try:
        layers = [str(name) for name, gtype in pyogrio.list_layers(p)
                  if gtype is None or any(k in str(gtype).upper() for k in wanted)
                  or str(gtype).upper() in ("UNKNOWN", "GEOMETRY", "GEOMETRYCOLLECTION")]
    except Exception as e:  # pyogrio raises DataSourceError / DataLayerError and GDAL's own errors
        raise FormatError(f"{p}: not a readable vector file ({type(e).__name__}: {str(e)[:200]})") from e
    for layer in layers:
        try:
            meta, _, geoms, fields = pyogrio.raw.read(p, layer=layer)
        except Exception as e:
            raise FormatError(f"{p}: layer {layer!r} is not readable ({type(e).__name__}: {str(e)[:200]})") from e
        names = [str(n) for n in meta["fields"]]
        if meta.get("crs") is None:
            if p.suffix.lower() not in (".geojson", ".json"):
                raise FormatError(f"{p}: layer {layer!r} declares no coordinate reference system"
                                  + (f" (no {p.with_suffix('.prj').name} beside it)" if p.suffix.lower() == ".shp"
                                     else "") + f"; {what} need one")
            crs = pyproj.CRS.from_user_input("OGC:CRS84")
        else:
            crs = pyproj.CRS.from_user_input(meta["crs"])
        for i, g in enumerate(shapely.from_wkb(geoms)):
            if g is not None and not g.is_empty:
                yield g, {n: f[i] for n, f in zip(names, fields)}, crs


def _one_crs(crs, new, p) -> object:
    if crs is not None and not crs.equals(new, ignore_axis_order=True):
        raise FormatError(f"{p}: its layers are in different coordinate systems ({crs.name}, {new.name})")
    return new


def _rings(g) -> list[np.ndarray]:
    """The exterior rings (not closed, finite, >= 3 distinct points) of a Polygon or MultiPolygon."""
    import shapely

    parts = list(g.geoms) if g.geom_type == "MultiPolygon" else [g] if g.geom_type == "Polygon" else []
    out = []
    for part in parts:
        xy = np.asarray(shapely.get_coordinates(part.exterior), np.float64)[:-1]
        if len(xy) >= 3 and np.all(np.isfinite(xy)) and len(np.unique(xy, axis=0)) >= 3:
            out.append(xy)
    return out


def read_footprints(path: str | os.PathLike) -> Footprints:
    """The building footprints of a vector file (every polygon layer), in its own CRS (see the module
    docstring). FormatError naming the file when it cannot be read, declares no CRS or holds no polygon."""
    rings: list[np.ndarray] = []
    heights: list[float | None] = []
    crs = None
    for g, attrs, layer_crs in _read_layers(path, ("POLYGON",), "building footprints"):
        if "building" in attrs and str(attrs["building"] or "no").strip().lower() in ("no", "none", ""):
            continue   # an export with other polygons too (landuse, areas): its buildings are tagged
        got = _rings(g)
        if got:
            crs = _one_crs(crs, layer_crs, path)
        rings += got
        heights += [building_height(attrs)] * len(got)
    if not rings:
        raise FormatError(f"{path}: holds no Polygon (building footprints are read from Polygon and MultiPolygon "
                          f"features)")
    return Footprints(rings, heights, crs, str(path))


def read_trees(path: str | os.PathLike) -> Trees:
    """The trees of a vector file: Points (single trees) and Polygons (canopy areas), in its own CRS (see the
    module docstring). FormatError naming the file when it cannot be read, declares no CRS or holds neither."""
    import shapely

    pts, ph, pr, canopies, ch = [], [], [], [], []
    crs = None
    for g, attrs, layer_crs in _read_layers(path, ("POINT", "POLYGON"), "trees"):
        low = {str(k).lower(): v for k, v in attrs.items()}
        if ("natural" in low or "landuse" in low) and not (
                str(low.get("natural")).lower() in _TREE_NATURAL or str(low.get("landuse")).lower() == "forest"):
            continue   # an OSM export with other features too: trees are natural=tree / wood, landuse=forest
        h = _number(low.get("height"))
        h = h if h is not None and 1.0 <= h <= 150.0 else None
        if g.geom_type in ("Point", "MultiPoint"):
            xy = np.asarray(shapely.get_coordinates(g), np.float64)
            xy = xy[np.all(np.isfinite(xy), axis=1)]
            if not len(xy):
                continue
            crs = _one_crs(crs, layer_crs, path)
            d = next((v for v in (_number(low.get(k)) for k in _CROWN_KEYS) if v is not None), None)
            r = d / 2 if d is not None else _number(low.get("radius"))
            r = r if r is not None and 0.3 <= r <= 30.0 else None
            pts += list(xy)
            ph += [h] * len(xy)
            pr += [r] * len(xy)
        else:
            got = _rings(g)
            if got:
                crs = _one_crs(crs, layer_crs, path)
            canopies += got
            ch += [h] * len(got)
    if not pts and not canopies:
        raise FormatError(f"{path}: holds no Point or Polygon (trees are read from Points, single trees, and "
                          f"Polygons, canopy areas)")
    return Trees(np.asarray(pts, np.float64).reshape(-1, 2), ph, pr, canopies, ch, crs, str(path))
