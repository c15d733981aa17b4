"""A scene's 3-D objects from map vectors: building footprints extruded, trees from points or canopy areas.

The glue between an image scene (:mod:`satloc_env.world.scene`) and :mod:`satloc.geodata.vectors`: footprints and trees
are read in the CRS their file declares, taken to the scene's frame through pyproj and clipped to the tile.

* **Buildings** (``generator.buildings``): each footprint (its exterior ring; courtyards are filled) is
  clipped to the tile and simplified to 5 cm, and extruded to its height: ``height`` / ``building:height``,
  else ``building:levels`` x 3 m, else drawn from ``generator.building_height_m`` (seeded by the scene's
  seed and the footprint's index, so a scene is the same on every load). The roof shows the imagery under
  the footprint (:attr:`satloc_env.world.layout.Building.roof_from_ground`); the walls come from the facade
  painters (a style drawn per building). A footprint that overlaps the road (the drivable ground, vectorised
  and widened by :data:`ROAD_CLEARANCE_M`) would stand in the car's way: it is **trimmed** by the road
  (shapely), and left out only when less than :data:`MIN_KEPT_FRACTION` of it (or under 2 m\\ :sup:`2`)
  remains. An invalid footprint (a self-intersecting ring) is repaired (``shapely.make_valid``). The scene
  reports how many footprints it kept, trimmed, repaired and dropped (:meth:`Scene.summary`
  ``footprints``), with a :class:`satloc.SatlocWarning` naming the file and the features it trimmed or
  dropped. With ``generator.heights`` (a DSM or nDSM, :mod:`satloc.geodata.heights`) the surface model's
  height comes first where it covers a footprint, and over each tree's crown.
* **Trees** (``generator.trees``): a Point is one tree, its crown radius and height from the attributes
  (``diameter_crown`` / ``radius``, ``height``) or drawn (2-3.5 m, 6-11 m). A Polygon is a canopy area,
  filled with trees about :data:`CANOPY_SPACING_M` apart (jittered, seeded). A tree whose trunk stands on
  the road is left out (with a warning); a canopy may overhang the road.

The ground labels under a footprint become ``building`` and under a crown ``tree``, except on drivable
ground (roads stay roads): the tile's label image carries both classes, while the tile itself stays the
imagery.
"""
from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np

from satloc.errors import ConfigError, SatlocWarning

from .layout import Building, Tree
from .scene_roads import read_vectors

__all__ = ["CANOPY_SPACING_M", "MAX_TREES", "MIN_KEPT_FRACTION", "ROAD_CLEARANCE_M", "height_raster",
           "road_polygons", "vector_buildings", "vector_trees"]

#: spacing of the trees that fill a canopy area, metres
CANOPY_SPACING_M = 6.0
#: the most trees a scene's tree file may make (each is a mesh of a few hundred triangles)
MAX_TREES = 20000
#: number of facade styles drawn from (satloc_env.world.meshes's painters)
_FACADES = 8
#: a footprint trimmed by the road is left out when less than this fraction of its area remains
MIN_KEPT_FRACTION = 0.25
#: a trimmed footprint keeps this far from the road's edge (metres): its walls stand off the drivable pixels
ROAD_CLEARANCE_M = 0.5
#: a footprint overlapping the road by less than this (m^2) counts as untouched (edge pixels, rounding)
_TRIM_M2 = 0.5
#: clipped footprint parts smaller than this (m^2) are dropped
_MIN_PART_M2 = 2.0


def _ids_raster(polys: list, shape: tuple[int, int], mpp: float) -> np.ndarray:
    """(H, W) int32 raster of polygon ids (1-based; 0 none) on the scene's raster (north up, origin at the
    south-west corner); a pixel belongs to a polygon when its centre does (later polygons win)."""
    from affine import Affine
    from rasterio.features import rasterize

    h, w = shape
    if not polys:
        return np.zeros((h, w), np.int32)
    return rasterize([(p, i + 1) for i, p in enumerate(polys)], out_shape=(h, w),
                     transform=Affine(mpp, 0.0, 0.0, 0.0, -mpp, h * mpp), fill=0, dtype="int32")


def _listing(idx: list[int], n: int = 8) -> str:
    return ", ".join(map(str, idx[:n])) + (f" and {len(idx) - n} more" if len(idx) > n else "")


def height_raster(path: Path, frame, where: str):
    """The :class:`satloc.geodata.heights.HeightRaster` of ``generator.heights`` reached from the scene's metres
    (``frame``, its GeoFrame); ConfigError naming the field and the file."""
    from satloc.errors import FormatError
    from satloc.geodata.heights import HeightRaster

    if frame is None:
        raise ConfigError(f"{where}: generator.heights: {path}: the image is not georeferenced, so a height raster "
                          f"has no place on it")
    try:
        return HeightRaster(path, frame.crs)
    except FormatError as e:
        raise ConfigError(f"{where}: generator.heights: {e}") from e


def road_polygons(drivable: np.ndarray, mpp: float):
    """The drivable pixels of the scene's raster (north up, origin at the south-west corner) as one shapely
    geometry in map metres (``rasterio.features.shapes``)."""
    import shapely
    from affine import Affine
    from rasterio.features import shapes

    h = drivable.shape[0]
    m = np.ascontiguousarray(drivable, np.uint8)
    if not m.any():
        return shapely.Polygon()
    polys = [shapely.geometry.shape(g) for g, v in shapes(m, mask=m.astype(bool), connectivity=4,
                                                          transform=Affine(mpp, 0.0, 0.0, 0.0, -mpp, h * mpp)) if v]
    return shapely.union_all(polys)


def vector_buildings(path: Path, frame, shape: tuple[int, int], mpp: float, drivable: np.ndarray,
                     height_range: tuple[float, float], seed: int, where: str, surface=None
                     ) -> tuple[list[Building], np.ndarray, dict]:
    """The buildings of the footprint file ``path`` on the scene's tile (``shape`` pixels of ``mpp`` metres,
    ``frame`` its GeoFrame), the (H, W) bool mask of their footprints off the drivable ground and the report
    ``{"read", "kept", "trimmed", "repaired", "dropped"}`` (footprints read from the file, inside the tile
    untouched, trimmed by the road, repaired, left out; see the module docstring). ``surface``: a
    :class:`satloc.geodata.heights.HeightRaster` whose heights come first where it covers a footprint (the
    report's ``heights_from_raster``)."""
    import shapely
    from shapely.geometry import Polygon, box

    from satloc.geodata.vectors import read_footprints

    fps = read_vectors("buildings", read_footprints, path, frame, where)
    h, w = shape
    tile = box(0.0, 0.0, w * mpp, h * mpp)
    road = road_polygons(drivable, mpp)
    road = road.buffer(ROAD_CLEARANCE_M) if not road.is_empty else road
    road_tree = shapely.STRtree(list(getattr(road, "geoms", [road]))) if not road.is_empty else None
    polys, heights, feature = [], [], []
    trimmed, dropped, inside = set(), set(), set()
    whole: dict[int, object] = {}   # each footprint as read (made valid), for the surface model

    def simple(q):   # a part's exterior, simplified to 5 cm; None when too small
        q = Polygon(q.exterior).simplify(0.05, preserve_topology=True)
        return q if q.geom_type == "Polygon" and q.area >= _MIN_PART_M2 else None

    for i, (ring, height) in enumerate(zip(fps.rings, fps.heights)):
        whole[i] = shapely.make_valid(Polygon(ring))
        g = whole[i].intersection(tile)
        parts = [q for q in getattr(g, "geoms", [g]) if q.geom_type == "Polygon" and q.area >= _MIN_PART_M2]
        if parts:
            inside.add(i)
        for q in filter(None, map(simple, parts)):
            near = road_tree.query(q, predicate="intersects") if road_tree is not None else []
            kept = [q]
            if len(near):
                cut = q.difference(shapely.union_all(road_tree.geometries.take(near)))
                if q.area - cut.area >= _TRIM_M2:
                    trimmed.add(i)
                    pieces = [c for c in getattr(cut, "geoms", [cut]) if c.geom_type == "Polygon"
                              and c.area >= _MIN_PART_M2]
                    if sum(c.area for c in pieces) < MIN_KEPT_FRACTION * q.area:
                        dropped.add(i)
                        continue
                    kept = list(filter(None, map(simple, pieces)))
            polys += kept
            heights += [height] * len(kept)
            feature += [i] * len(kept)
    standing = set(feature)
    dropped = sorted(dropped - standing)     # every part of it was left out
    trimmed = sorted(trimmed & standing)
    report = {"read": len(fps.rings), "kept": len(standing - set(trimmed)), "trimmed": len(trimmed),
              "repaired": int(fps.repaired), "dropped": len(dropped), "outside_tile": len(fps.rings) - len(inside)}
    if trimmed or dropped:
        msg = [f"{len(trimmed)} trimmed to the road's edge (features {_listing(trimmed)})"] if trimmed else []
        if dropped:
            msg.append(f"{len(dropped)} left out, less than {MIN_KEPT_FRACTION:.0%} of them off the road "
                       f"(features {_listing(dropped)})")
        warnings.warn(f"{where}: generator.buildings: {path}: of {len(fps.rings)} footprints, {len(trimmed) + len(dropped)} "
                      f"overlap the road: {'; '.join(msg)}", SatlocWarning, stacklevel=2)
    if surface is not None:   # the surface model's heights first, where it has them
        standing_whole = {i: whole[i] for i in sorted(standing)}
        everything = shapely.union_all(list(standing_whole.values()))
        measured = {i: surface.height(g, everything.difference(g.buffer(0.01))) for i, g in standing_whole.items()}
        heights = [measured[f] if measured[f] is not None else h for f, h in zip(feature, heights)]
        report["heights_from_raster"] = sum(v is not None for v in measured.values())
    ids = _ids_raster(polys, shape, mpp)
    lo, hi = (float(v) for v in height_range)
    out: list[Building] = []
    keep = np.zeros(len(polys) + 1, bool)
    for k, (q, height) in enumerate(zip(polys, heights)):
        rng = np.random.default_rng([int(seed), 21, feature[k]])
        drawn_h, facade = float(rng.uniform(lo, hi)), int(rng.integers(0, _FACADES))
        ring = np.asarray(q.exterior.coords, np.float64)[:-1]
        if not shapely.LinearRing(ring).is_ccw:
            ring = ring[::-1]
        top = float(height) if height is not None else drawn_h
        base = min(float(fps.bases[feature[k]]), max(top - 1.0, 0.0))   # a part starts below its top
        out.append(Building(ring, top, facade, roof_from_ground=True, base=base,
                            roof=fps.roofs[feature[k]] if fps.roofs[feature[k]] == "gabled" else "flat"))
        keep[k + 1] = True
    mask = keep[ids] & ~drivable
    return out, mask, report


def vector_trees(path: Path, frame, shape: tuple[int, int], mpp: float, drivable: np.ndarray, seed: int,
                 where: str, surface=None) -> tuple[list[Tree], np.ndarray]:
    """The trees of the file ``path`` on the scene's tile and the (H, W) bool mask of their crowns off the
    drivable ground (see the module docstring); ``surface``: a height raster whose heights (over each crown)
    come first where it has them."""
    from shapely import contains_xy
    from shapely.geometry import Point, Polygon, box

    from satloc.geodata.vectors import read_trees

    tr = read_vectors("trees", read_trees, path, frame, where)
    h, w = shape
    W, H = w * mpp, h * mpp
    rng = np.random.default_rng([int(seed), 22])
    xy, radius, height = [], [], []
    for p, r, ht in zip(tr.points, tr.point_radii, tr.point_heights):
        xy.append(p)
        radius.append(r if r is not None else float(rng.uniform(2.0, 3.5)))
        height.append(ht if ht is not None else float(rng.uniform(6.0, 11.0)))
    tile = box(0.0, 0.0, W, H)
    for ring, ht in zip(tr.canopies, tr.canopy_heights):
        area = Polygon(ring).buffer(0).intersection(tile)
        if area.is_empty:
            continue
        x0, y0, x1, y1 = area.bounds
        n_est = area.area / (CANOPY_SPACING_M ** 2 * math.sqrt(3) / 2)
        if len(xy) + n_est > MAX_TREES:
            raise ConfigError(f"{where}: generator.trees: {path}: its canopy areas would make about "
                              f"{len(xy) + n_est:.0f} trees, more than {MAX_TREES}")
        dy = CANOPY_SPACING_M * math.sqrt(3) / 2
        for j, yy in enumerate(np.arange(y0 + dy / 2, y1, dy)):
            xs = np.arange(x0 + (CANOPY_SPACING_M / 2 if j % 2 else 0.0), x1, CANOPY_SPACING_M)
            pts = np.stack([xs, np.full(len(xs), yy)], 1) + rng.uniform(-1.2, 1.2, (len(xs), 2))
            for q in pts[contains_xy(area, pts[:, 0], pts[:, 1])]:
                xy.append(q)
                radius.append(float(rng.uniform(2.5, 3.5)))
                height.append(ht if ht is not None else float(rng.uniform(7.0, 12.0)))
    if len(xy) > MAX_TREES:
        raise ConfigError(f"{where}: generator.trees: {path} makes {len(xy)} trees, more than {MAX_TREES}")
    xy_arr = np.asarray(xy, np.float64).reshape(-1, 2)
    inside = (xy_arr[:, 0] >= 0) & (xy_arr[:, 0] <= W) & (xy_arr[:, 1] >= 0) & (xy_arr[:, 1] <= H)
    u = np.clip((xy_arr[:, 0] / mpp).astype(int), 0, w - 1)
    v = np.clip(((H - xy_arr[:, 1]) / mpp).astype(int), 0, h - 1)
    on_road = inside & drivable[v, u]
    if on_road.any():
        idx = list(np.flatnonzero(on_road))
        warnings.warn(f"{where}: generator.trees: {path}: {len(idx)} trees stand on the road and were left out "
                      f"(trees {_listing(idx)})", SatlocWarning, stacklevel=2)
    trees: list[Tree] = []
    crowns = np.zeros(shape, bool)
    for k in np.flatnonzero(inside & ~on_road):
        (x, y), r, ht = xy_arr[k], float(radius[k]), float(height[k])
        if surface is not None:
            measured = surface.height(Point(x, y).buffer(max(r, 1.0)))
            ht = measured if measured is not None else ht
        r = min(r, 0.45 * ht)
        bottom = ht * float(rng.uniform(0.3, 0.45))
        trees.append(Tree((float(x), float(y)), r, bottom, ht, int(rng.integers(0, 4))))
        cu, cv = x / mpp - 0.5, (H - y) / mpp - 0.5
        rp = r / mpp
        r0, r1 = max(0, int(cv - rp - 1)), min(h, int(cv + rp + 2))
        c0, c1 = max(0, int(cu - rp - 1)), min(w, int(cu + rp + 2))
        yy, xx = np.ogrid[r0:r1, c0:c1]
        crowns[r0:r1, c0:c1] |= (xx - cu) ** 2 + (yy - cv) ** 2 <= rp * rp
    return trees, crowns & ~drivable
