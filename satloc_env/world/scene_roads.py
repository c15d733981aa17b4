"""A scene's roads: vector roads on an image scene's tile, its road graph, derived and snapped routes.

The glue between a scene (:mod:`satloc_env.world.scene`) and :mod:`satloc.geodata.vectors` / :mod:`satloc_env.world.roadgraph`:
every failure is a :class:`satloc.ConfigError` naming the scene and the field. The functions return plain
arrays; the scene makes its specs from them.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from satloc.errors import ConfigError, FormatError
from satloc.labels import CLASS_ID

from .roadgraph import (
    GraphParams,
    RoadGraph,
    RoadGraphError,
    Tour,
    covering_tour,
    graph_from_lines,
    graph_from_mask,
    lane_widths,
    rasterize_area,
    road_area,
    snapped_route,
)

__all__ = ["DERIVED_ROUTES", "MIN_COVERAGE", "line_network", "read_vectors", "vector_roads", "road_graph", "derived_routes",
           "snap_waypoints", "mask_widths", "tour_report"]

#: names of the routes a scene without ``routes:`` gets: the tour and its revisit
DERIVED_ROUTES = ("main", "revisit")


def read_vectors(field: str, reader, path: Path, frame, where: str):
    """``reader(path)`` (a reader of :mod:`satloc.geodata.vectors`) taken to the metres of ``frame``, the scene's
    GeoFrame; ConfigError naming ``generator.<field>`` and the file."""
    from satloc.geodata.vectors import VECTOR_SUFFIXES, is_vector_file

    if not is_vector_file(path):
        raise ConfigError(f"{where}: generator.{field}: {path} is not a vector file GDAL opens (such as "
                          f"{', '.join(VECTOR_SUFFIXES)})")
    if frame is None:
        raise ConfigError(f"{where}: generator.{field}: {path} is a vector file, in map coordinates; the image is "
                          f"not georeferenced, so its features have no place on it"
                          + (" (give a raster road mask)" if field == "roads" else ""))
    if not path.is_file():
        raise ConfigError(f"{where}: generator.{field}: vector file {path} not found")
    try:
        return reader(path).to_frame(frame)
    except (FormatError, ConfigError) as e:
        raise ConfigError(f"{where}: generator.{field}: {e}") from e


def vector_roads(path: Path, frame, shape: tuple[int, int], mpp: float, default_width_m: float,
                 params: GraphParams, where: str) -> tuple[RoadGraph, np.ndarray]:
    """The road graph of the vector file ``path``'s centre lines (in the metres of ``frame``, the scene's
    GeoFrame) and the road mask they make on the scene's raster (``shape``, ``mpp``): the lines buffered by
    their widths, the corners at junctions rounded (``params.curb_radius_m``)."""
    from satloc.geodata.vectors import read_road_lines

    lines = read_vectors("roads", lambda p: read_road_lines(p, default_width_m), path, frame, where)
    h, w = shape
    graph, area = line_network(lines, w * mpp, h * mpp, params, path, where)
    mask = rasterize_area(area, shape, mpp)
    if not mask.any():
        raise ConfigError(f"{where}: generator.roads: no road of {path} lies in the loaded area of the image")
    return graph, mask


def line_network(lines, width_m: float, height_m: float, params: GraphParams, path: Path, where: str):
    """(road graph, road surface) of ``lines`` (:class:`satloc.geodata.vectors.RoadLines` in the scene's metres,
    read from ``path``) on a tile of ``width_m`` x ``height_m``: their graph (layers and one-way streets kept)
    and the surface of the lines buffered by their widths, the junctions' corners rounded."""
    try:
        graph = graph_from_lines(lines.lines, lines.widths, width_m, height_m, params, lines.layers, lines.oneway)
    except RoadGraphError as e:
        raise ConfigError(f"{where}: generator.roads: {path}: {e}") from e
    return graph, road_area(lines.lines, lines.widths, graph, params.curb_radius_m)


def road_graph(params: GraphParams, roads: np.ndarray | None, labels: np.ndarray, mpp: float, where: str
               ) -> RoadGraph:
    """The road graph of a road mask (else of the road classes of the ground labels): its skeleton's."""
    if roads is None:
        roads = np.isin(labels, (CLASS_ID["road"], CLASS_ID["lane_marking"]))
    try:
        return graph_from_mask(roads, mpp, params)
    except RoadGraphError as e:
        raise ConfigError(f"{where}: road_graph: {e}") from e


#: a derived tour that drives less of the road network than this warns
MIN_COVERAGE = 0.8


def derived_routes(graph: RoadGraph, drivable: np.ndarray, mpp: float, params: GraphParams, where: str
                   ) -> tuple[Tour, Tour]:
    """The tour covering the graph's largest connected part and its revisit (:func:`covering_tour`); a
    :class:`satloc.SatlocWarning` when the tour drives less than :data:`MIN_COVERAGE` of the whole network."""
    import warnings

    from satloc.errors import SatlocWarning

    try:
        tours = covering_tour(graph, drivable, mpp, params)
    except RoadGraphError as e:
        raise ConfigError(f"{where}: routes: none given, and none could be derived from the road graph: {e}") from e
    t = tours[0]
    share = t.covered_m / t.graph_m if t.graph_m > 0 else 1.0
    if share < MIN_COVERAGE:
        warnings.warn(f"{where}: routes: the derived tour drives {100 * share:.0f} % of the road network "
                      f"({t.covered_m / 1000:.2f} of {t.graph_m / 1000:.2f} km): roads cut off from its largest "
                      f"part, one-way streets that lead nowhere and dead ends too narrow to turn in are left out",
                      SatlocWarning, stacklevel=2)
    return tours


def tour_report(t: Tour) -> dict:
    """What a scene reports of its derived tour: lengths (km) and its share of the network and of the part
    it drives."""
    return {"network_km": round(t.graph_m / 1000, 3), "covered_km": round(t.covered_m / 1000, 3),
            "coverage": round(t.covered_m / t.graph_m, 3) if t.graph_m > 0 else 1.0,
            "component_coverage": round(t.coverage, 3), "loops": int(t.loops)}


def snap_waypoints(graph: RoadGraph, xy: np.ndarray, closed: bool, params: GraphParams, field: str, where: str
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Waypoints (map metres) moved onto the roads and joined along them (:func:`snapped_route`)."""
    try:
        return snapped_route(graph, xy, closed, params)
    except RoadGraphError as e:
        raise ConfigError(f"{where}: {field}{e}") from e


def mask_widths(mask: np.ndarray, mpp: float, xy: np.ndarray, spacing_m: float, closed: bool) -> np.ndarray:
    """The road's width at waypoints ``xy`` (map metres, ``spacing_m`` apart) of a route traced through
    ``mask``: twice the distance to the mask's edge (the tile's border is none: the road goes on beyond it),
    as lane offsets should follow it (:func:`satloc_env.world.roadgraph.lane_widths`)."""
    from scipy import ndimage

    m = np.asarray(mask, bool)
    h, w = m.shape
    edt = ndimage.distance_transform_edt(np.pad(m, 1, mode="edge"))[1:-1, 1:-1] * mpp
    u = np.clip(np.floor(xy[:, 0] / mpp).astype(int), 0, w - 1)
    v = np.clip(np.floor(h - xy[:, 1] / mpp).astype(int), 0, h - 1)
    return lane_widths(np.maximum(2.0 * edt[v, u], mpp), spacing_m, closed)
