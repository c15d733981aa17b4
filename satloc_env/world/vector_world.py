"""Worlds from map vectors alone (``generator: {type: vectors, ...}``): any OpenStreetMap extract becomes a
scene, with no imagery.

The scene's ground is painted from the vectors, as the grid generator paints its blocks (the same painters,
:func:`satloc_env.world.generator._paint_base`): open land (grass with patches of bare soil) everywhere; the
roads (:mod:`satloc_env.world.scene_roads`: the centre lines buffered by their widths, the junction corners
rounded) in asphalt, each road the area's edge cuts ending in a turning bulb (``turn_bulb_m``: the roads go
on past the map, so a car may turn there); a sidewalk ``sidewalk_m`` wide along every road edge; a dashed centre line on every road
of two lanes or more (3 m dashes, 6 m gaps, kept out of the junctions); building footprints
(:mod:`satloc_env.world.scene_buildings`: trimmed by the road, extruded to their heights) with a roof colour
each; trees from points and wooded areas. The satellite map is a capture of this world, as for the grid scenes
(:func:`satloc_env.world.capture.capture_tile`: shadows, roofs leaning off nadir, canopies, the capture's
own time and texture).

The scene's frame is a :class:`satloc.geoframe.GeoFrame` with its origin at the area's south-west corner:
``region`` (lon/lat degrees) if given, else the bounds an OpenStreetMap XML road file declares (its
``<bounds>``: an extract's ways run on to their last node, often far beyond the area asked for), else the
roads' bounds widened by ``margin_m``. Routes are derived from the road graph (one-way streets honoured)
unless the scene file gives them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from satloc.errors import ConfigError
from satloc.labels import CLASS_ID

__all__ = ["VectorGeneratorSpec", "vector_layout"]

#: dashes of the centre line: on, off (metres)
DASH_M = (3.0, 6.0)
#: a road this wide or wider (two lanes) gets a centre line
CENTRE_LINE_MIN_M = 5.5
#: width of a painted line (metres)
LINE_M = 0.15


@dataclass
class VectorGeneratorSpec:
    """A world painted from map vectors (see the module docstring)."""

    type: Literal["vectors"]
    roads: str                     #: road centre lines: any vector file GDAL reads (an OSM extract as it comes)
    buildings: str | None = None   #: building footprints (vector file; may be the same file as roads)
    trees: str | None = None       #: tree points and wooded areas (vector file)
    heights: str | None = None     #: a DSM / nDSM GeoTIFF (any CRS): building and tree heights
    region: tuple[float, float, float, float] | None = None   #: lon_min, lat_min, lon_max, lat_max (degrees); None: see above
    margin_m: float = 20.0         #: without region or declared bounds: the roads' bounds widened by this much
    road_width_m: float = 7.0      #: roads whose attributes give no width
    sidewalk_m: float = 2.0        #: sidewalk along every road edge (0: none)
    turn_bulb_m: float = 12.0      #: a road the area's edge cuts ends in a turning bulb of this radius (0: none)
    building_height_m: tuple[float, float] = (5.0, 9.0)   #: footprints whose attributes give no height

    def __post_init__(self):
        for name, v, ok in (("margin_m", self.margin_m, self.margin_m >= 0),
                            ("road_width_m", self.road_width_m, self.road_width_m > 0),
                            ("sidewalk_m", self.sidewalk_m, 0 <= self.sidewalk_m <= 20),
                            ("turn_bulb_m", self.turn_bulb_m, 0 <= self.turn_bulb_m <= 30)):
            if not (math.isfinite(float(v)) and ok):
                raise ConfigError(f"{name}: expected a finite number of metres in range, got {v!r}")
        lo, hi = (float(v) for v in self.building_height_m)
        if not 1.0 <= lo <= hi <= 500.0:
            raise ConfigError(f"building_height_m: expected [low, high] metres with 1 <= low <= high <= 500, got "
                              f"{list(self.building_height_m)}")

    def files(self, base: Path) -> list[tuple[str, Path]]:
        """(field, path) of every file the generator reads (what a cache of the scene must depend on)."""
        from satloc.geodata.vectors import vector_files

        out = []
        for k in ("roads", "buildings", "trees", "heights"):
            if getattr(self, k):
                out.append((k, base / getattr(self, k)))
                if k != "heights":
                    out += [(f"{k}_sidecar", p) for p in vector_files(base / getattr(self, k))[1:]]
        return out


def _frame_and_lines(g: VectorGeneratorSpec, base: Path, mpp: float, where: str):
    """The GeoFrame (origin at the area's south-west corner), the area's size in metres (whole pixels), the
    road lines in the frame's metres (the road file read once) and the margin the area keeps around the roads
    (``margin_m`` when the area is the roads' extent, else 0)."""
    from satloc.geodata.vectors import RoadLines, declared_bounds, read_road_lines
    from satloc.geoframe import GeoFrame

    from .scene_roads import read_vectors

    probe = GeoFrame(0.0, 0.0)   # any frame: the lines' lon/lat, then the area's own frame
    read = read_vectors("roads", lambda p: read_road_lines(p, g.road_width_m), base / g.roads, probe, where)
    lonlat = [probe.to_lonlat(xy) for xy in read.lines]
    region = g.region if g.region is not None else declared_bounds(base / g.roads)
    if region is not None:
        lon0, lat0, lon1, lat1 = (float(v) for v in region)
        if not (-180 <= lon0 < lon1 <= 180 and -85 <= lat0 < lat1 <= 85):
            raise ConfigError(f"{where}: generator.region: expected [lon_min, lat_min, lon_max, lat_max] in "
                              f"degrees with lon_min < lon_max and lat_min < lat_max, got {list(region)}")
    else:
        every = np.vstack(lonlat)
        (lon0, lat0), (lon1, lat1) = every.min(axis=0), every.max(axis=0)
        corner = GeoFrame(float(lon0), float(lat0))
        sw, ne = corner.to_map(np.array([[lon0, lat0], [lon1, lat1]]))
        (lon0, lat0), (lon1, lat1) = corner.to_lonlat(np.array([sw - g.margin_m, ne + g.margin_m]))
    frame = GeoFrame(float(lon0), float(lat0))
    ex, ny = frame.to_map(np.array([lon1, lat1]))
    w_m, h_m = math.floor(ex / mpp + 1e-6) * mpp, math.floor(ny / mpp + 1e-6) * mpp
    if w_m < 10 * mpp or h_m < 10 * mpp:
        raise ConfigError(f"{where}: generator: the area ({w_m:g} m x {h_m:g} m) is smaller than 10 pixels a side")
    lines = RoadLines([frame.to_map(ll) for ll in lonlat], read.widths, frame.crs, read.source, read.oneway,
                      read.layers)
    return frame, w_m, h_m, lines, (g.margin_m if region is None else 0.0)


def _centre_lines(graph, shape: tuple[int, int], mpp: float) -> np.ndarray:
    """(H, W) bool: the dashed centre lines of the graph's roads of two lanes or more, out of the junctions."""
    import cv2

    from satloc.geometry import arc_length

    h = shape[0]
    out = np.zeros(shape, np.uint8)
    g = graph.graph
    junction = {n for n in g.nodes if g.degree(n) >= 3}
    thick = max(1, int(round(LINE_M / mpp)))
    for u, v, _, d in g.edges(keys=True, data=True):
        xy, wv = d["xy"], d["w"]
        s = arc_length(xy)
        if len(xy) < 2 or s[-1] < 1.0:
            continue
        keep = (wv >= CENTRE_LINE_MIN_M).astype(float)
        clear = float(np.max(wv)) / 2 + 2.0        # out of the junction's area
        fine = np.arange(0.0, s[-1], mpp / 2)
        paint = (np.interp(fine, s, keep) > 0.5) & ((fine % sum(DASH_M)) < DASH_M[0])
        if d["start"] in junction:
            paint &= fine >= clear
        if (v if d["start"] == u else u) in junction:
            paint &= fine <= s[-1] - clear
        pts = np.stack([np.interp(fine, s, xy[:, 0]) / mpp - 0.5, h - np.interp(fine, s, xy[:, 1]) / mpp - 0.5], 1)
        pts = np.round(pts * 16).astype(np.int32)
        edges = np.flatnonzero(np.diff(np.concatenate([[0], paint.astype(np.int8), [0]])))
        for a, b in zip(edges[::2], edges[1::2]):   # each dash: a run of painted samples
            if b - a >= 2:
                cv2.polylines(out, [pts[a:b].reshape(-1, 1, 2)], False, 1, thick, cv2.LINE_8, shift=4)
    return out.astype(bool)


def _turn_bulbs(graph, w_m: float, h_m: float, reach: float, radius: float):
    """Discs of ``radius`` where the extract's edge cuts a road (a dead end of the graph within ``reach`` of
    the area's edge: the graph's margin, and the area's margin around the roads' bounds), centred ``radius``
    back along the road, or farther back where a road running along the edge would put the disc partly off
    the area (the first centre whose disc lies 1 m inside; else the one farthest inside): the roads went on
    past the extract, so a car may turn there (a tour turns round only where a turn fits). None when there
    are none."""
    import shapely

    from satloc.geometry import arc_length

    if radius <= 0:
        return None
    g = graph.graph
    discs = []
    for n in g.nodes:
        if g.degree(n) != 1:
            continue
        x, y = g.nodes[n]["xy"]
        if min(x, y, w_m - x, h_m - y) > reach:
            continue                                     # a dead end of the map itself: left as it is
        (a, b, k), = list(g.edges(n, keys=True))
        xy, _ = graph.edge_xy(b if a == n else a, n, k)  # arriving at the dead end
        s = arc_length(xy)
        back = np.arange(max(s[-1] - radius, 0.0), -1e-9, -0.5)      # from the end backwards
        c = np.stack([np.interp(back, s, xy[:, 0]), np.interp(back, s, xy[:, 1])], axis=1)
        inside = np.min(np.stack([c[:, 0], c[:, 1], w_m - c[:, 0], h_m - c[:, 1]]), axis=0)
        fits = np.flatnonzero(inside >= radius + 1.0)
        i = int(fits[0]) if len(fits) else int(np.argmax(inside))
        discs.append(shapely.Point(c[i]).buffer(radius))
    return shapely.union_all(discs) if discs else None


def vector_layout(g: VectorGeneratorSpec, spec, base: Path, where: str, check_size) -> tuple:
    """The scene's ground from the vectors (see the module docstring): (layout, frame, road mask, road graph,
    footprint report). ``check_size(w_m, h_m, mpp, where, field)`` refuses an area too large (the scene's
    check)."""
    from .generator import _paint_base, _roof_rgb
    from .layout import Layout
    from .paint import noise
    from .roadgraph import rasterize_area
    from .scene_buildings import height_raster, vector_buildings, vector_trees
    from .scene_roads import line_network

    mpp = spec.ground_mpp
    frame, w_m, h_m, lines, margin = _frame_and_lines(g, base, mpp, where)
    check_size(w_m, h_m, mpp, where, "generator")
    h, w = int(round(h_m / mpp)), int(round(w_m / mpp))
    graph, area = line_network(lines, w_m, h_m, spec.road_graph, base / g.roads, where)
    reach = spec.road_graph.edge_margin_m + margin + 1.0
    bulbs = _turn_bulbs(graph, w_m, h_m, reach, g.turn_bulb_m)
    if bulbs is not None:   # the bulbs' necks rounded (a closing of the road near them), as kerbs are
        near = area.intersection(bulbs.buffer(10.0)).union(bulbs)
        area = area.union(near.buffer(3.0).buffer(-3.0))
    roads = rasterize_area(area, (h, w), mpp)
    if not roads.any():
        raise ConfigError(f"{where}: generator.roads: no road of {base / g.roads} lies in the area")
    # open land, sidewalks, roads, centre lines
    labels = np.full((h, w), CLASS_ID["grass"], np.uint8)
    land = noise((h, w), np.random.default_rng([spec.seed, 2]), (max(2, 25 / mpp),))
    labels[land > 0.35] = CLASS_ID["soil"]
    if g.sidewalk_m > 0:
        labels[rasterize_area(area.buffer(g.sidewalk_m), (h, w), mpp)] = CLASS_ID["sidewalk"]
    labels[roads] = CLASS_ID["road"]
    labels[_centre_lines(graph, (h, w), mpp) & roads] = CLASS_ID["lane_marking"]
    surface = height_raster(base / g.heights, frame, where) if g.heights else None
    buildings, trees, report, crowns = [], [], None, None
    if g.trees:
        trees, crowns = vector_trees(base / g.trees, frame, (h, w), mpp, roads, spec.seed, where, surface)
    if g.buildings:
        buildings, fp_mask, report = vector_buildings(base / g.buildings, frame, (h, w), mpp, roads,
                                                      g.building_height_m, spec.seed, where, surface)
        labels[fp_mask] = CLASS_ID["building"]
        rng = np.random.default_rng([spec.seed, 23])
        for b in buildings:   # a roof colour each: the tile paints the roofs, the camera sees the meshes
            b.roof_from_ground = False
            b.roof_rgb = _roof_rgb(rng, 70, 170)
    rgb = np.zeros((h, w, 3), np.uint8)
    _paint_base(labels, rgb, np.random.default_rng([spec.seed, 3]), mpp)
    if crowns is not None:   # the ground under a crown stays painted as what it is; its label is the tree's
        labels[crowns & ~roads] = CLASS_ID["tree"]
    return Layout(w_m, h_m, mpp, rgb, labels, buildings, trees), frame, roads, graph, report
