"""Map vectors as users export them: road centre lines, building footprints and trees from any vector file
GDAL reads: GeoJSON, GeoPackage, Shapefile, FlatGeobuf, KML, GML and OpenStreetMap ``.osm`` / ``.osm.pbf``.

A file is a vector file when GDAL (through ``pyogrio``) opens it as one (:func:`is_vector_file`), whatever its
name. Features are read into ``shapely`` geometries in the coordinate reference system the file declares (a
GeoJSON file without one is CRS84: longitude, latitude in degrees). **OpenStreetMap** files are read by GDAL's
OSM driver: its ``points``, ``lines`` and ``multipolygons`` layers (not the route relations of
``multilinestrings``, which repeat the ways they group), each feature's tags that the driver keeps apart in
``other_tags`` unpacked into attributes. One OSM file may serve as roads, buildings and trees at once.

:func:`read_road_lines` reads the LineStrings (and the parts of MultiLineStrings); other geometry types are
skipped. Where a file's features carry a ``highway`` attribute (an OSM export: its railways, waterways,
fences and power lines carry it empty), only the road classes of ``classes`` are roads, by default those
for cars (:data:`OSM_CAR_ROADS`: motorway ... residential, service, living_street, the ``*_link`` ramps,
``road``; not footway, cycleway, path, steps, pedestrian or track). A file without such an attribute (any
other source) is all roads, as it always was. OSM's ``oneway`` (``yes`` / ``1`` / ``true``, ``-1`` /
``reverse``; implied by ``highway=motorway`` and ``junction=roundabout``) and ``layer`` (else 1 on a
``bridge``, -1 in a ``tunnel``, else 0) are kept per line: ``RoadLines.oneway`` (+1: drawn direction only,
-1: against it, 0: both) and ``RoadLines.layers`` (lines on different layers do not meet where they cross).

Each line's road **width** (metres, the whole carriageway) comes from its attributes, the first usable of:

* ``width`` (or ``est_width``): a length (:func:`parse_length`: ``"7"``, ``"7.5 m"``, ``"7,5"``, ``"24 ft"``,
  ``"23'6\""``);
* ``lanes`` (OpenStreetMap) or ``lane_number`` (SpaceNet road labels): the number of lanes x
  :data:`LANE_WIDTH_M` (``"2;3"`` reads as 2);

else ``default_width_m``. :meth:`RoadLines.to_frame` takes the lines to a :class:`~satloc.geoframe.GeoFrame`
(metres east / north of its origin) through pyproj.

**Buildings** (:func:`read_footprints`): the exterior rings of Polygons and MultiPolygons (courtyards are
filled), each with its **height** from its attributes, the first usable of ``height`` / ``building:height``
(a length, as widths) and ``building:levels`` x :data:`LEVEL_HEIGHT_M`, else None (the caller picks one);
its **base** (``min_height``, else ``building:min_level`` x :data:`LEVEL_HEIGHT_M`, else 0) and its
``roof:shape`` (``flat`` when none is given). Where the features have an OpenStreetMap ``building``
attribute, those without one (or with ``building=no``) are skipped, so a whole OSM export can be given as it
is.

**Trees** (:func:`read_trees`): Points are single trees; Polygons and MultiPolygons are canopy areas. Each
keeps its ``height`` and its crown radius (``diameter_crown`` / ``crown_diameter`` / 2, or ``radius``,
metres) where the attributes give them, else None. Where the features have ``natural`` or ``landuse``
attributes, or are OpenStreetMap features (every node, way and area of an ``.osm`` file), only
``natural=tree`` / ``wood`` / ``tree_row`` and ``landuse=forest`` are trees.

This module is pure data: it knows nothing of the simulator.
"""
from __future__ import annotations

import math
import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError, FormatError, SatlocWarning

__all__ = ["LANE_WIDTH_M", "LEVEL_HEIGHT_M", "OSM_CAR_ROADS", "VECTOR_SUFFIXES", "Footprints", "RoadLines", "declared_bounds",
           "Trees", "building_base", "building_height", "is_vector_file", "parse_length", "read_footprints",
           "read_road_lines", "read_trees", "road_layer", "road_oneway", "road_width", "roof_shape", "vector_files"]

#: width of one driving lane, metres (as the simulator's generator paints them)
LANE_WIDTH_M = 3.5
#: height of one storey, metres (``building:levels``)
LEVEL_HEIGHT_M = 3.0
#: file name endings known as vector files without opening them (any other file GDAL opens as vectors is one too)
VECTOR_SUFFIXES = (".geojson", ".json", ".gpkg", ".shp", ".fgb", ".kml", ".kmz", ".gml", ".osm", ".pbf")
#: file name endings never read as vectors (images: GDAL's vector drivers would only fail on them)
_RASTER_SUFFIXES = (".tif", ".tiff", ".png", ".jpg", ".jpeg", ".jp2", ".bmp", ".img", ".vrt")
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
#: a length: a number (decimal point or comma) and an optional unit
_LENGTH = re.compile(r"^\s*([0-9]+(?:[.,][0-9]*)?|[.,][0-9]+)\s*(m|metres?|meters?|cm|km|mi|ft|feet|foot|'|in|inch|"
                     r"inches|\")?\s*$", re.IGNORECASE)
#: feet and inches, as OpenStreetMap writes them: 23'6"
_FEET_INCHES = re.compile(r"^\s*([0-9]+(?:\.[0-9]*)?)\s*'\s*([0-9]+(?:\.[0-9]*)?)\s*\"\s*$")
_UNIT_M = {"m": 1.0, "metre": 1.0, "metres": 1.0, "meter": 1.0, "meters": 1.0, "cm": 0.01, "km": 1000.0,
           "mi": 1609.344, "ft": 0.3048, "feet": 0.3048, "foot": 0.3048, "'": 0.3048, "in": 0.0254,
           "inch": 0.0254, "inches": 0.0254, '"': 0.0254}
#: OpenStreetMap's hstore of the tags GDAL's OSM driver keeps in ``other_tags``: "key"=>"value",...
_HSTORE = re.compile(r'"((?:[^"\\]|\\.)*)"=>"((?:[^"\\]|\\.)*)"')
#: the OSM driver's layers that repeat other layers' features (route relations) or hold none of ours
_OSM_SKIP_LAYERS = ("multilinestrings", "other_relations")
_YES = ("yes", "true", "1")


def is_vector_file(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a vector file: its ending is one of :data:`VECTOR_SUFFIXES`, or GDAL opens the file
    as a vector data source with at least one layer (so an ``.xml`` OSM export or a file without an ending
    counts; an image never does). A file that does not exist counts by its ending only."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix in VECTOR_SUFFIXES:
        return True
    if suffix in _RASTER_SUFFIXES or not p.is_file():
        return False
    import pyogrio

    try:
        return len(pyogrio.list_layers(p)) > 0
    except Exception:  # noqa: BLE001 - pyogrio raises DataSourceError and GDAL's own errors: not vectors
        return False


def declared_bounds(path: str | os.PathLike) -> tuple[float, float, float, float] | None:
    """(lon_min, lat_min, lon_max, lat_max) the file says it covers: in an OpenStreetMap XML file, the
    ``<bounds minlat= minlon= maxlat= maxlon=>`` elements (osmconvert, the OSM API, Overpass; JOSM writes one
    per downloaded area: their union) or Osmosis's ``<bound box="s,w,n,e">``, all before the first node; None
    for other files, for an OSM file without them and for bounds beyond +-85 degrees of latitude. An
    extract's ways run on past these bounds to their last node ("complete ways"), often far: the declared
    area, not the features' extent, is what was asked for."""
    head = b""
    try:
        with open(path, "rb") as f:
            while len(head) < (16 << 20):          # the header ends at the first node; 16 MB at most
                chunk = f.read(1 << 16)
                if not chunk:
                    break
                head += chunk
                if b"<node" in head[-len(chunk) - 5:]:   # the new chunk and the seam before it
                    break
    except OSError:
        return None
    if b"<osm" not in head[: 1 << 16]:
        return None
    head = head.split(b"<node", 1)[0]
    num = rb"([-+0-9.eE]+)"
    boxes = []
    for attrs in re.findall(rb"<bounds\b([^>]*)>", head):
        got = {a + b: c for a, b, c in re.findall(rb"(min|max)(lat|lon)\s*=\s*[\"']" + num + rb"[\"']", attrs)}
        try:
            boxes.append(tuple(float(got[k]) for k in (b"minlon", b"minlat", b"maxlon", b"maxlat")))
        except (KeyError, ValueError):
            continue
    for box in re.findall(rb"<bound\b[^>]*\bbox\s*=\s*[\"']([^\"']*)[\"']", head):
        try:
            s_, w_, n_, e_ = (float(v) for v in box.split(b","))
        except ValueError:
            continue
        boxes.append((w_, s_, e_, n_))
    boxes = [b for b in boxes if -180 <= b[0] < b[2] <= 180 and -85 <= b[1] < b[3] <= 85]
    if not boxes:
        return None
    a = np.asarray(boxes, np.float64)
    return float(a[:, 0].min()), float(a[:, 1].min()), float(a[:, 2].max()), float(a[:, 3].max())


def parse_length(v) -> float | None:
    """A length in metres from an attribute: a number (metres), or a text with a decimal point or comma and an
    optional unit (m, cm, km, mi, ft / feet / ', in / inch / ", or 23'6" in feet and inches); None when it is
    none of these (``"wide"``, ``"2;3"``, an empty value)."""
    s = _text_or_number(v)
    if not isinstance(s, str):
        return s
    m = _FEET_INCHES.match(s)
    if m:
        return float(m.group(1)) * 0.3048 + float(m.group(2)) * 0.0254
    m = _LENGTH.match(s)
    if not m or re.fullmatch(r"[0-9]{1,3},[0-9]{3}", m.group(1)):
        return None                      # "1,000": a thousands separator or a decimal comma; neither is safe
    return float(m.group(1).replace(",", ".")) * _UNIT_M[(m.group(2) or "m").lower()]


def _osm_tags(text) -> dict:
    """The tags of GDAL's OSM ``other_tags`` hstore text."""
    if not text:
        return {}
    unescape = lambda t: t.replace('\\"', '"').replace("\\\\", "\\")
    return {unescape(k): unescape(v) for k, v in _HSTORE.findall(str(text))}


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
    oneway: np.ndarray | None = None   #: (L,) int8: +1 drawn direction only, -1 against it, 0 both (None: all 0)
    layers: np.ndarray | None = None   #: (L,) int: lines on different layers do not meet (None: all 0)

    def __post_init__(self):
        n = len(self.lines)
        self.oneway = np.zeros(n, np.int8) if self.oneway is None else np.asarray(self.oneway, np.int8)
        self.layers = np.zeros(n, np.int64) if self.layers is None else np.asarray(self.layers, np.int64)
        if len(self.widths) != n or self.oneway.shape != (n,) or self.layers.shape != (n,):
            raise ValueError(f"RoadLines: {n} lines but {len(self.widths)} widths, {self.oneway.shape} oneway, "
                             f"{self.layers.shape} layers")

    def to_crs(self, crs) -> RoadLines:
        """The lines in another CRS (anything pyproj accepts); FormatError for points it cannot transform."""
        import pyproj

        return RoadLines(_to_crs(self.lines, self.crs, crs, self.source), self.widths.copy(),
                         pyproj.CRS.from_user_input(crs), self.source, self.oneway.copy(), self.layers.copy())

    def to_frame(self, frame) -> RoadLines:
        """The lines in metres of a :class:`~satloc.geoframe.GeoFrame`."""
        return self.to_crs(frame.crs)


def _measure(attrs: dict, value_keys, value_range, count_keys, count_range, unit: float) -> float | None:
    """The first usable of a measured value (``value_keys``, metres within ``value_range``) and a count
    (``count_keys``, within ``count_range``, ``"2;3"`` reads as 2) times ``unit``; else None."""
    low = {str(k).lower(): v for k, v in attrs.items()}
    for k in value_keys:
        v = parse_length(low.get(k))
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


def _text_or_number(v) -> str | float | None:
    """An attribute as a finite number (None for NaN, infinities, booleans and None), or else as text."""
    if v is None or isinstance(v, bool):
        return None
    if isinstance(v, (int, float, np.integer, np.floating)):
        f = float(v)
        return f if math.isfinite(f) else None
    return str(v)


def _number(v, first_of_list: bool = False) -> float | None:
    s = _text_or_number(v)
    if not isinstance(s, str):
        return s
    if first_of_list:
        s = s.split(";")[0]
    m = _NUMBER.match(s)
    return float(m.group(1)) if m else None


def road_oneway(attrs: dict) -> int:
    """+1 (the drawn direction only), -1 (against it) or 0 (both ways) from a feature's OpenStreetMap tags."""
    raw = attrs.get("oneway")
    if isinstance(raw, (int, float, np.integer, np.floating)) and not isinstance(raw, bool) and math.isfinite(raw):
        raw = str(int(raw))                # a numeric field (Shapefile, GeoPackage): 1, -1, 0
    v = str(raw or "").strip().lower()
    if v in _YES:
        return 1
    if v in ("-1", "reverse"):
        return -1
    if v in ("no", "false", "0", "reversible", "alternating"):
        return 0
    implied = str(attrs.get("highway") or "") in ("motorway", "motorway_link") or \
        str(attrs.get("junction") or "").lower() in ("roundabout", "circular")
    return 1 if implied else 0


def road_layer(attrs: dict) -> int:
    """A line's vertical layer from its tags: ``layer`` where it is an integer, else 1 on a bridge, -1 in a
    tunnel, else 0."""
    raw = attrs.get("layer")
    try:
        if isinstance(raw, (int, float, np.integer, np.floating)) and not isinstance(raw, bool):
            return int(raw)                # a numeric field; NaN raises ValueError below
        return int(str(raw).strip().split(";")[0])
    except (ValueError, OverflowError):
        pass
    if str(attrs.get("bridge") or "no").strip().lower() not in ("no", "false", "0", ""):
        return 1
    if str(attrs.get("tunnel") or "no").strip().lower() not in ("no", "false", "0", ""):
        return -1
    return 0


def read_road_lines(path: str | os.PathLike, default_width_m: float = 2 * LANE_WIDTH_M,
                    classes=OSM_CAR_ROADS) -> RoadLines:
    """The road centre lines of a vector file (every layer with line geometries), in its own CRS (see the
    module docstring); ``classes``: the ``highway`` values that are roads where the file has that attribute.
    FormatError naming the file when it cannot be read, declares no CRS (a Shapefile without ``.prj``) or
    holds no line."""
    import shapely

    if not default_width_m > 0:
        raise ConfigError(f"default road width: expected metres > 0, got {default_width_m}")
    classes = frozenset(str(c) for c in classes)
    lines: list[np.ndarray] = []
    widths: list[float] = []
    oneway: list[int] = []
    layers: list[int] = []
    crs = None
    skipped: dict[str, int] = {}
    for g, attrs, layer_crs in _read_layers(path, ("LINE",), "road centre lines"):
        if "highway" in attrs:   # an OSM-style file: its railways, fences, paths ... are not roads
            hw = str(attrs["highway"] or "")
            if hw not in classes:
                skipped[hw or "(none)"] = skipped.get(hw or "(none)", 0) + 1
                continue
        parts = list(g.geoms) if g.geom_type == "MultiLineString" else [g] if g.geom_type == "LineString" else []
        for part in parts:
            xy = np.asarray(shapely.get_coordinates(part), np.float64)
            if len(xy) >= 2 and np.all(np.isfinite(xy)):
                crs = _one_crs(crs, layer_crs, path)
                lines.append(xy)
                widths.append(road_width(attrs, default_width_m))
                oneway.append(road_oneway(attrs))
                layers.append(road_layer(attrs))
    if not lines:
        extra = (f"; its lines' highway classes ({', '.join(f'{k}: {v}' for k, v in sorted(skipped.items()))}) "
                 f"are none of the road classes asked for ({', '.join(sorted(classes))})") if skipped else ""
        raise FormatError(f"{path}: holds no LineString (road centre lines are read from LineString and "
                          f"MultiLineString features){extra}")
    return RoadLines(lines, np.asarray(widths, np.float64), crs, str(path), np.asarray(oneway, np.int8),
                     np.asarray(layers, np.int64))


def _to_crs(parts: list[np.ndarray], src, crs, source: str) -> list[np.ndarray]:
    """Coordinate arrays (N, 2) taken from CRS ``src`` to ``crs`` through pyproj; FormatError naming
    ``source`` for points outside the coordinate system's domain."""
    import pyproj

    from ..geoframe import wgs84_bound

    dst = pyproj.CRS.from_user_input(crs)
    tr = pyproj.Transformer.from_crs(wgs84_bound(src), dst, always_xy=True)   # another datum: through WGS84
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


def building_base(attrs: dict) -> float:
    """The height (metres) a building part starts at: ``min_height``, else ``building:min_level`` x
    :data:`LEVEL_HEIGHT_M`, else 0."""
    v = _measure(attrs, ("min_height", "building:min_height"), (0.0, 1000.0), ("building:min_level", "min_level"),
                 (0, 300), LEVEL_HEIGHT_M)
    return 0.0 if v is None else float(v)


def roof_shape(attrs: dict) -> str:
    """The ``roof:shape`` tag in lower case, ``flat`` where none is given."""
    v = str(attrs.get("roof:shape") or attrs.get("roof_shape") or "").strip().lower()
    return v or "flat"


@dataclass
class Footprints:
    """Building footprints (exterior rings) and their heights where the attributes give them."""

    rings: list[np.ndarray]            #: (N_i, 2) float64 ring of each footprint, not closed, N_i >= 3
    heights: list[float | None]        #: metres, or None where the attributes give none
    crs: object                        #: pyproj.CRS of the coordinates
    source: str = ""
    bases: list[float] | None = None   #: metres above the ground the part starts at (None: all 0)
    roofs: list[str] | None = None     #: ``roof:shape`` of each (None: all flat)
    repaired: int = 0                  #: footprints that were invalid (a self-intersecting ring) and were repaired

    def __post_init__(self):
        n = len(self.rings)
        self.bases = [0.0] * n if self.bases is None else list(self.bases)
        self.roofs = ["flat"] * n if self.roofs is None else list(self.roofs)
        if len(self.heights) != n or len(self.bases) != n or len(self.roofs) != n:
            raise ValueError(f"Footprints: {n} rings but {len(self.heights)} heights, {len(self.bases)} bases, "
                             f"{len(self.roofs)} roofs")

    def to_frame(self, frame) -> Footprints:
        """The footprints in metres of a :class:`~satloc.geoframe.GeoFrame`."""
        return Footprints(_to_crs(self.rings, self.crs, frame.crs, self.source), list(self.heights), frame.crs,
                          self.source, list(self.bases), list(self.roofs), self.repaired)


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

    def to_frame(self, frame) -> Trees:
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
        listed = [(str(name), gtype) for name, gtype in pyogrio.list_layers(p)]
        osm = bool(listed) and pyogrio.read_info(p, layer=listed[0][0]).get("driver") == "OSM"
        layers = [name for name, gtype in listed
                  if (gtype is None or any(k in str(gtype).upper() for k in wanted)
                      or str(gtype).upper() in ("UNKNOWN", "GEOMETRY", "GEOMETRYCOLLECTION"))
                  and not (osm and name in _OSM_SKIP_LAYERS)]
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
                attrs = {n: f[i] for n, f in zip(names, fields)}
                if "other_tags" in attrs:   # GDAL's OSM driver: the tags without a column of their own
                    for k, v in _osm_tags(attrs.pop("other_tags")).items():
                        attrs.setdefault(k, v)
                if osm:
                    attrs["_osm"] = True
                yield g, attrs, crs


def _one_crs(crs, new, p) -> object:
    if crs is not None and not crs.equals(new, ignore_axis_order=True):
        raise FormatError(f"{p}: its layers are in different coordinate systems ({crs.name}, {new.name})")
    return new


def _valid(g):
    """(the polygonal part of ``g`` made valid, whether it was invalid): a self-intersecting ring (a bow tie, as
    real exports have) becomes the polygons it encloses (``shapely.make_valid``), not nothing."""
    import shapely

    if g.geom_type not in ("Polygon", "MultiPolygon") or g.is_valid:
        return g, False
    fixed = shapely.make_valid(g)
    polys = [q for q in getattr(fixed, "geoms", [fixed]) if q.geom_type in ("Polygon", "MultiPolygon")]
    parts = [q for poly in polys for q in getattr(poly, "geoms", [poly])]
    return shapely.MultiPolygon(parts) if parts else shapely.Polygon(), True


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


def _is_tagged(attrs: dict, key: str) -> bool:
    return str(attrs.get(key) or "no").strip().lower() not in ("no", "none", "")


def read_footprints(path: str | os.PathLike) -> Footprints:
    """The building footprints of a vector file (every polygon layer), in its own CRS (see the module
    docstring). OpenStreetMap ``building:part`` ways (which GDAL's OSM driver files as closed lines) are
    footprints too, and a ``building`` outline that its parts cover (90 % of its area) gives way to them, as
    OSM's renderers draw it. FormatError naming the file when it cannot be read, declares no CRS or holds no
    polygon."""
    import shapely

    found: list[tuple] = []     # (polygon, attrs, is_part)
    crs = None
    repaired = 0
    for g, attrs, layer_crs in _read_layers(path, ("POLYGON", "LINE"), "building footprints"):
        if g.geom_type in ("LineString", "MultiLineString"):
            if not (attrs.get("_osm") and _is_tagged(attrs, "building:part") and g.geom_type == "LineString"
                    and g.is_closed and len(g.coords) >= 4):
                continue   # lines are footprints only as OSM's closed building:part ways
            g = shapely.Polygon(g.coords)
        if ("building" in attrs or "building:part" in attrs) and not (
                _is_tagged(attrs, "building") or _is_tagged(attrs, "building:part")):
            continue   # an export with other polygons too (landuse, areas): its buildings are tagged
        g, fixed = _valid(g)
        if g.is_empty:
            continue
        repaired += bool(fixed)
        crs = _one_crs(crs, layer_crs, path)
        found.append((g, attrs, _is_tagged(attrs, "building:part") and not _is_tagged(attrs, "building")))
    parts = shapely.union_all([g for g, _, is_part in found if is_part]) if any(p for *_, p in found) else None
    rings: list[np.ndarray] = []
    heights: list[float | None] = []
    bases: list[float] = []
    roofs: list[str] = []
    for g, attrs, is_part in found:
        if parts is not None and not is_part and g.area > 0 and g.intersection(parts).area >= 0.9 * g.area:
            continue   # an outline drawn as its parts
        got = _rings(g)
        rings += got
        heights += [building_height(attrs)] * len(got)
        bases += [building_base(attrs)] * len(got)
        roofs += [roof_shape(attrs)] * len(got)
    if not rings:
        raise FormatError(f"{path}: holds no Polygon (building footprints are read from Polygon and MultiPolygon "
                          f"features)")
    return Footprints(rings, heights, crs, str(path), bases, roofs, repaired)


def read_trees(path: str | os.PathLike) -> Trees:
    """The trees of a vector file: Points (single trees) and Polygons (canopy areas), in its own CRS (see the
    module docstring). FormatError naming the file when it cannot be read, declares no CRS or holds neither. A
    map with other features but no trees (an OpenStreetMap extract of a place whose trees nobody mapped, given
    as ``trees:`` as well as ``roads:``) gives no trees and a warning."""
    import shapely

    pts, ph, pr, canopies, ch = [], [], [], [], []
    crs = None
    others = None   # the CRS of the features that are not trees (OSM exports)
    for g, attrs, layer_crs in _read_layers(path, ("POINT", "POLYGON"), "trees"):
        low = {str(k).lower(): v for k, v in attrs.items()}
        if ("natural" in low or "landuse" in low or "_osm" in low) and not (
                str(low.get("natural")).lower() in _TREE_NATURAL or str(low.get("landuse")).lower() == "forest"):
            others = layer_crs if others is None else others
            continue   # an OSM export with other features too: trees are natural=tree / wood, landuse=forest
        h = parse_length(low.get("height"))
        h = h if h is not None and 1.0 <= h <= 150.0 else None
        if g.geom_type in ("Point", "MultiPoint"):
            xy = np.asarray(shapely.get_coordinates(g), np.float64)
            xy = xy[np.all(np.isfinite(xy), axis=1)]
            if not len(xy):
                continue
            crs = _one_crs(crs, layer_crs, path)
            d = next((v for v in (parse_length(low.get(k)) for k in _CROWN_KEYS) if v is not None), None)
            r = d / 2 if d is not None else parse_length(low.get("radius"))
            r = r if r is not None and 0.3 <= r <= 30.0 else None
            pts += list(xy)
            ph += [h] * len(xy)
            pr += [r] * len(xy)
        else:
            got = _rings(_valid(g)[0])
            if got:
                crs = _one_crs(crs, layer_crs, path)
            canopies += got
            ch += [h] * len(got)
    if not pts and not canopies and others is not None:
        warnings.warn(SatlocWarning(f"{path}: holds no trees (natural=tree points, natural=wood or landuse=forest "
                                    f"areas): none stand"), stacklevel=2)
        return Trees(np.zeros((0, 2)), [], [], [], [], others, str(path))
    if not pts and not canopies:
        raise FormatError(f"{path}: holds no Point or Polygon (trees are read from Points, single trees, and "
                          f"Polygons, canopy areas)")
    return Trees(np.asarray(pts, np.float64).reshape(-1, 2), ph, pr, canopies, ch, crs, str(path))
