"""A road graph of a scene, and the routes derived from it: a tour that covers the roads, its revisit, and
given waypoints snapped to the roads.

**The graph** (:class:`RoadGraph`, a :class:`networkx.MultiGraph`) is built once per scene, from road centre
lines in map metres (:func:`graph_from_lines`: a vector file read by :mod:`satloc.geodata.vectors`) or from the
skeleton of a road mask (:func:`graph_from_mask`: cleaned, thinned and pruned as :mod:`satloc_env.world.roadtrace`
does, then cut into chains between junctions and dead ends). The lines are clipped to the tile, kept
``edge_margin_m`` inside it; a line end within ``snap_m`` of another line is joined to it; crossing lines
are cut at their crossing (shapely's noding: one node per intersection); dead-end stubs and edges shorter
than ``snap_m`` are dropped; nodes where just two edges meet are merged away. Every edge keeps its geometry
``xy`` (from its ``start`` node), the road width ``w`` at each of its vertices, and its ``length``. The
surface of vector roads (:func:`road_area`) is each line buffered by half its width, with the corners where
roads meet rounded by a curb radius (``curb_radius_m``), as kerbs are, so a car can turn into a narrow street.

**The tour** (:func:`covering_tour`) drives every road of the graph's largest connected part, turning at its
intersections: a Chinese-postman walk. Odd-degree nodes are paired at the least total distance (a minimum
weight matching of their shortest-path distances) and the shortest paths between the pairs are driven twice;
an Euler walk of the result (Fleury's algorithm, preferring at each intersection the straightest way on, and
right over left, and never turning back where another way is left) covers every edge. A dead end is turned
in a loop (a "keyhole": round a circle centred where the road is widest near its end, counter-clockwise, so
the car keeps to the outside; a ring road at the end, mapped as a loop, is driven counter-clockwise too)
when the drivable area holds one of ``turn_radius_m`` at the lane offset;
else it cannot be turned in: up to two such ends are where the tour starts and ends (an open route), the
roads leading to any others are left out (the coverage says how much). The walk's polyline is smoothed
(Gaussian, ``smooth_m``) and resampled every ``spacing_m``. Its ``widths`` (the road width at each waypoint,
smoothed and taken as the narrowest within 20 m, so the car moves over before a narrower street) let the
lane offset follow the road (:class:`satloc_env.world.route.Route`).

**The revisit** is the same walk driven the other way round (its loops again counter-clockwise): the other
direction, so the other lane, of every road.

**Snapped routes** (:func:`snapped_route`): given waypoints are moved to the nearest road (within
``snap_route_m``) and joined by the shortest way along the roads.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from satloc.geometry import arc_length

from .roadtrace import _clean, _neighbour_count, _prune, _resample, _skeleton, _smooth
from .route import REFERENCE_ROAD_M

if TYPE_CHECKING:
    import networkx as nx

__all__ = ["GraphParams", "RoadGraph", "RoadGraphError", "Tour", "allowed", "arc_graph", "covering_tour",
           "graph_from_lines", "graph_from_mask", "has_oneway", "lane_widths", "rasterize_area", "road_area",
           "snapped_route"]

#: the coarsest resolution a road mask is thinned at (metres per pixel)
GRAPH_MPP = 0.2
#: the heading change (radians) above which a step is a U-turn
_UTURN = math.radians(150)


class RoadGraphError(ValueError):
    """No road graph or no route could be made (empty graph, a waypoint far from every road, ...)."""


@dataclass(frozen=True)
class GraphParams:
    """How the road graph is built and routes are derived from it (the scene's ``road_graph:``)."""

    snap_m: float = 2.0           #: line ends this close to another line join it; shorter edges are dropped
    edge_margin_m: float = 2.0    #: the graph (and every derived route) keeps this far inside the tile
    smooth_m: float = 3.0         #: Gaussian smoothing of a derived route's turns, metres
    spacing_m: float = 2.0        #: waypoint spacing of derived routes, metres
    turn_radius_m: float = 4.5    #: the smallest loop the car turns around in at a dead end, metres
    snap_route_m: float = 20.0    #: a snapped route's waypoints may lie this far from the nearest road
    prune_m: float = 8.0          #: skeleton twigs shorter than this are cut (road masks), metres
    lane_offset_m: float = -1.75  #: the lane the loops at dead ends must hold (for a 7 m road; scaled)
    curb_radius_m: float = 5.0    #: vector roads: the corners where roads meet are rounded with this radius

    def __post_init__(self):
        self.check()

    def check(self) -> None:
        for k in ("snap_m", "smooth_m", "edge_margin_m", "prune_m", "curb_radius_m"):
            if not getattr(self, k) >= 0:
                raise ValueError(f"{k}: expected metres >= 0, got {getattr(self, k)}")
        for k in ("spacing_m", "turn_radius_m", "snap_route_m"):
            if not getattr(self, k) > 0:
                raise ValueError(f"{k}: expected metres > 0, got {getattr(self, k)}")
        if not math.isfinite(self.lane_offset_m):
            raise ValueError(f"lane_offset_m: expected a finite number, got {self.lane_offset_m}")


@dataclass
class RoadGraph:
    """Roads as a multigraph: node attribute ``xy``; edge attributes ``xy`` ((N, 2) metres from the node
    ``start``), ``w`` ((N,) road width, metres), ``length``."""

    graph: "nx.MultiGraph"
    width_m: float                  #: the tile the graph lies on
    height_m: float

    def edge_xy(self, u, v, k) -> tuple[np.ndarray, np.ndarray]:
        """Geometry and widths of edge (u, v, k) oriented from ``u`` to ``v``."""
        d = self.graph.edges[u, v, k]
        if d["start"] == u:
            return d["xy"], d["w"]
        return d["xy"][::-1], d["w"][::-1]

    @property
    def length_m(self) -> float:
        return float(sum(d["length"] for *_, d in self.graph.edges(data=True)))

    def largest_component(self) -> set:
        import networkx as nx

        comps = list(nx.connected_components(self.graph))
        if not comps:
            raise RoadGraphError("the road graph is empty (no road inside the tile)")
        return max(comps, key=lambda c: sum(d["length"] for *_, d in self.graph.subgraph(c).edges(data=True)))


@dataclass
class Tour:
    """A derived route: waypoints (map metres), the road width at each, and what it covers."""

    waypoints: np.ndarray    #: (N, 2)
    widths: np.ndarray       #: (N,) road width at each waypoint, metres
    closed: bool
    covered_m: float         #: length of the graph's roads the tour drives (each counted once)
    component_m: float       #: length of the roads of the graph's largest connected part
    graph_m: float           #: length of all roads of the graph
    steps: list = field(default_factory=list)   #: the walk: (u, v, key) per edge driven
    loops: int = 0           #: dead ends turned in a loop

    @property
    def coverage(self) -> float:
        """Fraction of the largest connected part's road length the tour drives."""
        return self.covered_m / self.component_m if self.component_m > 0 else 0.0


# --- building the graph -----------------------------------------------------------------------------------
def graph_from_lines(lines, widths, width_m: float, height_m: float, params: GraphParams = GraphParams(),
                     layers=None, oneway=None) -> RoadGraph:
    """The road graph of centre lines in map metres (see the module docstring). ``widths``: per line, a road
    width (metres) or an array of one per vertex. ``layers``: per line, its vertical layer (OpenStreetMap's
    ``layer``, bridges above, tunnels below; None: all on one): lines on different layers meet only where
    one ends on the other's vertex, never where they cross, and a line end is snapped only to lines of its
    own layer. ``oneway``: per line, +1 (drivable in its drawn direction only), -1 (against it) or 0 (both;
    None: all 0): each edge's ``oneway`` is then 1 where it may be driven only from its ``start`` node."""
    import networkx as nx
    import shapely
    from shapely.strtree import STRtree

    params.check()
    m = params.edge_margin_m
    box = shapely.box(m, m, width_m - m, height_m - m)
    lines = list(lines)
    layers = np.zeros(len(lines), np.int64) if layers is None else np.asarray(layers, np.int64)
    if layers.shape != (len(lines),):
        raise RoadGraphError(f"layers: expected one per line ({len(lines)}), got {layers.shape}")
    oneway = np.zeros(len(lines), np.int64) if oneway is None else np.sign(np.asarray(oneway, np.int64))
    if oneway.shape != (len(lines),):
        raise RoadGraphError(f"oneway: expected one per line ({len(lines)}), got {oneway.shape}")
    src, src_w, src_layer, src_oneway = [], [], [], []
    for xy, w, layer, one in zip(lines, widths, layers, oneway):
        xy = np.asarray(xy, np.float64)
        wv = np.broadcast_to(np.asarray(w, np.float64), (len(xy),)).copy()
        keep = np.concatenate([[True], np.linalg.norm(np.diff(xy, axis=0), axis=1) > 1e-9])
        xy, wv = xy[keep], wv[keep]
        if len(xy) < 2:
            continue
        clipped = shapely.intersection(shapely.LineString(xy), box)
        for part in _line_parts(clipped):
            pxy = np.asarray(shapely.get_coordinates(part), np.float64)
            src.append(pxy)
            src_w.append(np.interp(_project(xy, pxy), arc_length(xy), wv))
            src_layer.append(int(layer))
            src_oneway.append(int(one))
    if not src:
        raise RoadGraphError(f"no road lies inside the tile (x in [{m:g}, {width_m - m:g}], y in [{m:g}, "
                             f"{height_m - m:g}] metres: the tile less edge_margin_m)")
    src_layer = np.asarray(src_layer, np.int64)
    src, src_w = _snap_ends(src, src_w, params.snap_m, src_layer)
    g = nx.MultiGraph()
    node_at: dict[tuple[int, int], int] = {}

    def node(p: np.ndarray) -> int:
        key = (int(round(p[0] * 100)), int(round(p[1] * 100)))     # 1 cm: the noding's own precision
        if key not in node_at:
            node_at[key] = len(node_at)
            g.add_node(node_at[key], xy=np.asarray(p, np.float64))
        return node_at[key]

    multi_layer = len(np.unique(src_layer)) > 1
    foreign_ends = np.array([xy[e] for xy in src for e in (0, -1)], np.float64).reshape(-1, 2)
    foreign_layer = np.repeat(src_layer, 2)
    for layer in np.unique(src_layer):   # each layer noded on its own: no junction where layers cross
        idx = np.flatnonzero(src_layer == layer)
        geoms = [shapely.LineString(src[i]) for i in idx]
        noded = _line_parts(shapely.unary_union(shapely.MultiLineString(geoms)))
        if multi_layer:   # a line of another layer ending on this one's vertex (a ramp onto it) joins it there
            noded = _split_at_points(noded, foreign_ends[foreign_layer != layer])
        tree = STRtree(geoms)
        for piece in noded:
            xy = np.asarray(shapely.get_coordinates(piece), np.float64)
            if len(xy) < 2 or shapely.length(piece) < 1e-6:
                continue
            j = int(idx[int(tree.nearest(shapely.line_interpolate_point(piece, 0.5, normalized=True)))])
            along = _project(src[j], xy)
            w = np.interp(along, arc_length(src[j]), src_w[j])
            # the piece's own direction, judged inside it: an end may be a ring's closing point (projecting to 0)
            inner = np.asarray(shapely.get_coordinates(shapely.line_interpolate_point(
                piece, [0.25, 0.75], normalized=True)), np.float64)
            s_in = _project(src[j], inner)
            one = src_oneway[j] * (1 if s_in[1] >= s_in[0] else -1)
            if one < 0:                       # stored from the node it may be driven from
                xy, w = xy[::-1].copy(), w[::-1].copy()
            u, v = node(xy[0]), node(xy[-1])   # layers meet where their lines share an end (1 cm)
            g.add_edge(u, v, xy=xy, w=w, length=float(arc_length(xy)[-1]), start=u, layer=int(layer),
                       oneway=int(one != 0))
    rg = RoadGraph(g, float(width_m), float(height_m))
    _drop_stubs(rg, params.snap_m)
    _merge_degree_two(rg)
    if g.number_of_edges() == 0:
        raise RoadGraphError("the road graph is empty: every road inside the tile is shorter than snap_m")
    return rg


def _split_at_points(pieces: list, points: np.ndarray, tol: float = 0.01) -> list:
    """``pieces`` (LineStrings) cut where one of ``points`` lies on a piece within ``tol`` metres, away from
    its ends (shapely's substrings)."""
    import shapely
    from shapely.ops import substring

    if not len(points):
        return pieces
    pts = shapely.points(points)
    tree = shapely.STRtree(pts)
    out = []
    for piece in pieces:
        near = tree.query(piece, predicate="dwithin", distance=tol)
        cuts = sorted({float(piece.project(pts[i])) for i in near})
        cuts = [c for c in cuts if tol < c < piece.length - tol]
        if not cuts:
            out.append(piece)
            continue
        bounds = [0.0, *cuts, piece.length]
        out += [substring(piece, a, b) for a, b in zip(bounds[:-1], bounds[1:])]
    return out


def road_area(lines, widths, graph: RoadGraph | None = None, curb_radius_m: float = 0.0):
    """The roads' surface (a shapely geometry, map metres): each centre line buffered by half its width
    (round ends and joins), and, at each junction of ``graph`` (a node where three or more roads meet), the
    corners between the roads rounded with ``curb_radius_m`` (a morphological closing of the surface,
    kept within the junction's reach: its widest road's half width plus twice the radius)."""
    import shapely

    polys = [shapely.buffer(shapely.LineString(np.asarray(xy, np.float64)), float(np.median(wd)) / 2.0)
             for xy, wd in zip(lines, widths) if len(xy) >= 2]
    area = shapely.union_all(polys)
    if graph is None or curb_radius_m <= 0 or area.is_empty:
        return area
    g = graph.graph
    discs = []
    for n in g.nodes:
        if g.degree(n) >= 3:
            half = max(float(np.max(d["w"])) for *_, d in g.edges(n, data=True)) / 2.0
            discs.append(shapely.Point(g.nodes[n]["xy"]).buffer(half + 2 * curb_radius_m))
    if not discs:
        return area
    closed = area.buffer(curb_radius_m).buffer(-curb_radius_m)
    return shapely.union(area, shapely.intersection(closed, shapely.union_all(discs)))


def rasterize_area(area, shape: tuple[int, int], mpp: float) -> np.ndarray:
    """(H, W) bool raster (north up, ``mpp`` metres per pixel, the map frame's origin at its south-west
    corner) of a shapely geometry in map metres: a pixel is in when its centre is."""
    from affine import Affine
    from rasterio.features import rasterize

    h, w = shape
    if area is None or area.is_empty:
        return np.zeros((h, w), bool)
    out = rasterize([(area, 1)], out_shape=(h, w), transform=Affine(mpp, 0.0, 0.0, 0.0, -mpp, h * mpp), fill=0,
                    dtype="uint8")
    return out.astype(bool)


def graph_from_mask(mask: np.ndarray, mpp: float, params: GraphParams = GraphParams()) -> RoadGraph:
    """The road graph of a road mask (north-up raster, ``mpp`` metres per pixel, as
    :func:`satloc_env.world.roadtrace.trace_route` reads it): the pruned skeleton cut into chains between
    junctions and dead ends, the road width from the distance to the mask's edge. A mask finer than
    :data:`GRAPH_MPP` is thinned at that resolution (the graph needs no finer detail)."""
    import cv2
    from scipy import ndimage

    params.check()
    m = np.asarray(mask).astype(bool)
    if not m.any():
        raise RoadGraphError("the road mask is empty (no road pixel)")
    f = int(GRAPH_MPP // mpp) if mpp < GRAPH_MPP else 1
    if f > 1:
        h0, w0 = m.shape
        # whole f x f blocks from the south-west corner (the map frame's origin)
        m = cv2.resize(m[h0 % f:, :w0 - w0 % f].astype(np.float32), ((w0 - w0 % f) // f, (h0 - h0 % f) // f),
                       interpolation=cv2.INTER_AREA) >= 0.5
        mpp *= f
    m = _clean(m, mpp, 20.0)
    # the distance to the road's edge; the tile's border is none (the road goes on beyond it)
    # (so the mask is thinned as if it went on: no fork towards the corners where a road meets the border)
    pad = max(1, int(round(20.0 / mpp)))
    big = np.pad(m, pad, mode="edge")
    edt = ndimage.distance_transform_edt(big)[pad:-pad, pad:-pad] * mpp
    skel = _skeleton(big)
    if skel.sum() >= 2:
        pruned = _prune(skel, max(1, int(round(params.prune_m / mpp))))
        if pruned.sum() >= 2:
            skel = pruned
    skel = skel[pad:-pad, pad:-pad]
    h = m.shape[0]
    chains = _skeleton_chains(skel)
    lines, widths = [], []
    for rc in chains:
        xy = np.stack([(rc[:, 1] + 0.5) * mpp, (h - rc[:, 0] - 0.5) * mpp], axis=1)
        lines.append(xy)
        widths.append(2.0 * edt[rc[:, 0], rc[:, 1]])
    if not lines:
        raise RoadGraphError("the road mask thins to points: no road to follow")
    return graph_from_lines(lines, widths, m.shape[1] * mpp, h * mpp, params)


def _line_parts(geom) -> list:
    if geom is None or geom.is_empty:
        return []
    if geom.geom_type == "LineString":
        return [geom]
    if hasattr(geom, "geoms"):
        return [p for g in geom.geoms for p in _line_parts(g)]
    return []


def _project(line: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Arc length along the polyline ``line`` of the closest point to each of ``pts``."""
    a, b = line[:-1], line[1:]
    ab = b - a
    l2 = np.maximum((ab ** 2).sum(1), 1e-18)
    t = np.clip(np.einsum("pkd,kd->pk", pts[:, None] - a[None], ab) / l2, 0, 1)
    q = a[None] + t[..., None] * ab[None]
    d = np.linalg.norm(q - pts[:, None], axis=2)
    k = np.argmin(d, axis=1)
    cum = arc_length(line)
    return cum[k] + t[np.arange(len(pts)), k] * np.sqrt(l2[k])


def _snap_ends(lines: list[np.ndarray], widths: list[np.ndarray], tol: float, layers: np.ndarray | None = None
               ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Join each line end that lies within ``tol`` of another line of its layer (but does not touch it) to
    that line: extend it to the closest point, a centimetre beyond, so that noding cuts the other line there.
    Returns the lines and their per-vertex widths. The candidates of each end come from a spatial index (a
    shapely STRtree queried within ``tol``), so the work grows with the lines near each end, not with all
    lines."""
    import shapely
    from shapely.strtree import STRtree

    if tol <= 0 or len(lines) < 1:
        return lines, widths
    layers = np.zeros(len(lines), np.int64) if layers is None else np.asarray(layers)
    geoms = [shapely.LineString(xy) for xy in lines]
    tree = STRtree(geoms)
    out = [xy.copy() for xy in lines]
    wout = [w.copy() for w in widths]
    ends = shapely.points(np.array([xy[e] for xy in lines for e in (0, -1)]))
    near: dict[int, list[int]] = {}
    for q, j in zip(*tree.query(ends, predicate="dwithin", distance=tol)):
        near.setdefault(int(q), []).append(int(j))
    for i, xy in enumerate(lines):
        for n_end, end in enumerate((0, -1)):
            p = ends[2 * i + n_end]
            best, best_d = None, tol
            for j in sorted(near.get(2 * i + n_end, ())):
                if layers[j] != layers[i]:
                    continue
                g = geoms[j]
                d = g.distance(p)
                if j == i:   # the line's own far part may pass near its end (a loop)
                    far = shapely.LineString(xy[1:] if end == 0 else xy[:-1]) if len(xy) > 2 else None
                    if far is None or abs(g.project(p) - (0 if end == 0 else g.length)) < 2 * tol:
                        continue
                    d = far.distance(p)
                if 1e-6 < d < best_d:
                    best, best_d = g, d
            if best is None:
                continue
            q = np.asarray(shapely.get_coordinates(best.interpolate(best.project(p))))[0]
            direction = (q - xy[end]) / max(np.linalg.norm(q - xy[end]), 1e-12)
            tip = q + 0.01 * direction
            out[i] = np.vstack([tip[None], out[i]]) if end == 0 else np.vstack([out[i], tip[None]])
            wout[i] = np.concatenate([wout[i][:1], wout[i]]) if end == 0 else np.append(wout[i], wout[i][-1])
    return out, wout


def _drop_stubs(rg: RoadGraph, min_len: float) -> None:
    """Drop dead-end edges and loops shorter than ``min_len`` (noding debris, snapped ends' overshoot) and
    isolated nodes; merge the ends of other edges shorter than it."""
    g = rg.graph
    changed = True
    while changed:
        changed = False
        for u, v, k, d in list(g.edges(keys=True, data=True)):
            if not g.has_edge(u, v, k) or d["length"] >= max(min_len, 1e-3):
                continue
            if u == v or g.degree(u) == 1 or g.degree(v) == 1:
                g.remove_edge(u, v, k)
                changed = True
        g.remove_nodes_from([n for n in list(g.nodes) if g.degree(n) == 0])
        if changed:
            continue
        short = [(u, v, k) for u, v, k, d in g.edges(keys=True, data=True) if u != v and d["length"] < min_len]
        if short:                                   # one at a time: a contraction may leave a short loop
            _contract(rg, *short[0])
            changed = True


def _contract(rg: RoadGraph, u, v, k) -> None:
    """Remove the short edge (u, v, k) and merge ``v`` into ``u`` (the edges at ``v`` end at ``u``)."""
    g = rg.graph
    g.remove_edge(u, v, k)
    pu = g.nodes[u]["xy"]
    for a, b, kk, d in list(g.edges(v, keys=True, data=True)):
        other = b if a == v else a
        xy, w = rg.edge_xy(v, other, kk)
        xy = np.vstack([pu[None], xy[1:]]) if len(xy) > 2 else np.vstack([pu[None], xy[-1:]])
        w = np.concatenate([w[:1], w[1:]]) if len(w) > 2 else w[[0, -1]]
        g.remove_edge(a, b, kk)
        if other == v:
            other = u
            xy[-1] = pu
        one = int(d.get("oneway", 0))
        if one and d["start"] != v:           # a one-way road towards v: it now ends at u, driven from other
            g.add_edge(other, u, xy=xy[::-1].copy(), w=w[::-1].copy(), length=float(arc_length(xy)[-1]),
                       start=other, oneway=1)
            continue
        g.add_edge(u, other, xy=xy, w=w, length=float(arc_length(xy)[-1]), start=u, oneway=one)
    g.remove_node(v)


def _merge_degree_two(rg: RoadGraph) -> None:
    """Remove the nodes where just two edges meet (not a loop's own node): one edge through them."""
    g = rg.graph
    for n in list(g.nodes):
        if not g.has_node(n) or g.degree(n) != 2:
            continue
        es = list(g.edges(n, keys=True))
        if len(es) != 2 or any(a == b for a, b, _ in es):
            continue
        (a1, b1, k1), (a2, b2, k2) = es
        p = b1 if a1 == n else a1
        q = b2 if a2 == n else a2
        d1, d2 = g.edges[a1, b1, k1], g.edges[a2, b2, k2]
        o1, o2 = int(d1.get("oneway", 0)), int(d2.get("oneway", 0))
        if o1 != o2:
            continue          # a one-way road goes on as a two-way one: the node stays
        if o1:
            if d1["start"] == n and d2["start"] == q:     # driven q -> n -> p: merge it from q
                p, q, k1, k2 = q, p, k2, k1
            elif not (d1["start"] == p and d2["start"] == n):
                continue      # both one-way towards n, or both away from it: no way through
        x1, w1 = rg.edge_xy(p, n, k1)
        x2, w2 = rg.edge_xy(n, q, k2)
        xy, w = np.vstack([x1, x2[1:]]), np.concatenate([w1, w2[1:]])
        g.remove_node(n)
        g.add_edge(p, q, xy=xy, w=w, length=float(arc_length(xy)[-1]), start=p, oneway=o1)


def _skeleton_chains(skel: np.ndarray) -> list[np.ndarray]:
    """The skeleton as chains of pixels (row, col) between nodes (dead ends and junctions; a junction's
    touching pixels are one node, its chains start at the node's centre pixel), plus cycles without nodes."""
    from scipy import ndimage

    nb = _neighbour_count(skel)
    is_node = skel & (nb != 2)
    lab, n_nodes = ndimage.label(is_node, structure=np.ones((3, 3), bool))
    centre = {}
    for i, sl in enumerate(ndimage.find_objects(lab), start=1):
        rc = np.argwhere(lab[sl] == i) + [sl[0].start, sl[1].start]
        c = rc.mean(axis=0)
        centre[i] = rc[np.argmin(((rc - c) ** 2).sum(1))]
    h, w = skel.shape
    offs = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]

    def neighbours(r, c):
        for dr, dc in offs:
            rr, cc = r + dr, c + dc
            if 0 <= rr < h and 0 <= cc < w and skel[rr, cc]:
                yield rr, cc

    seen = np.zeros_like(skel, bool)       # chain pixels (not node pixels) already walked
    chains = []
    for i in range(1, n_nodes + 1):
        node_px = np.argwhere(lab == i)
        for r, c in node_px:
            for rr, cc in neighbours(r, c):
                if lab[rr, cc] == i or seen[rr, cc]:
                    continue
                path = [tuple(centre[i]), (r, c)] if (r, c) != tuple(centre[i]) else [(r, c)]
                cur, prev = (rr, cc), (r, c)
                end = None
                while True:
                    if lab[cur]:
                        end = lab[cur]
                        path.append(cur)
                        break
                    seen[cur] = True
                    path.append(cur)
                    nxt = [p for p in neighbours(*cur) if p != prev and not seen[p] and p not in path[-3:]]
                    if not nxt:
                        break
                    # prefer a 4-neighbour step (skeleton corners have both)
                    nxt.sort(key=lambda p: abs(p[0] - cur[0]) + abs(p[1] - cur[1]))
                    prev, cur = cur, nxt[0]
                if end is not None:
                    path.append(tuple(centre[end]))
                chains.append(_dedupe(np.array(path)))
    # cycles without any node (a ring road)
    rest = skel & ~seen & (lab == 0)
    while rest.any():
        r, c = np.argwhere(rest)[0]
        path, cur, prev = [(r, c)], (r, c), None
        rest[r, c] = False
        while True:
            nxt = [p for p in neighbours(*cur) if rest[p]]
            if not nxt:
                break
            prev, cur = cur, nxt[0]
            rest[cur] = False
            path.append(cur)
        path.append((r, c))
        if len(path) > 3:
            chains.append(_dedupe(np.array(path)))
    return [ch for ch in chains if len(ch) >= 2]


def _dedupe(rc: np.ndarray) -> np.ndarray:
    keep = np.concatenate([[True], np.any(np.diff(rc, axis=0) != 0, axis=1)])
    return rc[keep]


# --- the tour ---------------------------------------------------------------------------------------------
def _heading(xy: np.ndarray, from_start: bool, reach: float = 5.0) -> float:
    """Heading (radians) of a polyline leaving its first point (``from_start``) or arriving at its last,
    over its first / last ``reach`` metres."""
    p = xy if from_start else xy[::-1]
    s = arc_length(p)
    j = int(np.searchsorted(s, min(reach, s[-1])))
    j = min(max(j, 1), len(p) - 1)
    d = p[j] - p[0]
    a = math.atan2(d[1], d[0])
    return a if from_start else math.atan2(-d[1], -d[0])


def _turn(a: float, b: float) -> float:
    """Signed heading change from ``a`` to ``b`` in (-pi, pi] (left positive)."""
    return (b - a + math.pi) % (2 * math.pi) - math.pi


@dataclass
class _DeadEnd:
    centre: np.ndarray   # where the loop is centred
    radius: float        # the loop's radius (the route's centre line)
    turnable: bool


def _turn_loop(arriving: np.ndarray, width: float, edt_m, mpp: float, height_m: float, params: GraphParams
               ) -> _DeadEnd:
    """Where and whether the car can turn round at the end of the polyline ``arriving`` (a road of
    ``width``): the loop centred on one of its points within its last 20 m, of the largest radius that
    leaves room for the lane offset and 0.75 m inside the drivable area, and that the polyline enters from
    outside (the point at least a radius along it)."""
    s = arc_length(arriving)
    # candidate centres every 0.5 m of the last 20 m (a straight road's polyline has no vertex there)
    along = np.union1d(s[s >= s[-1] - 20.0], np.arange(max(s[-1] - 20.0, 0.0), s[-1], 0.5))
    pts = np.stack([np.interp(along, s, arriving[:, 0]), np.interp(along, s, arriving[:, 1])], axis=1)
    off = abs(params.lane_offset_m) * min(1.0, width / REFERENCE_ROAD_M)
    radius = np.minimum(_edt_at(edt_m, pts, mpp, height_m) - off - 0.75, 10.0)
    ok = (radius >= params.turn_radius_m) & (along >= radius)
    if not ok.any():
        return _DeadEnd(arriving[-1], params.turn_radius_m, False)
    i = int(np.argmax(np.where(ok, radius, -np.inf)))
    return _DeadEnd(pts[i], float(radius[i]), True)


def _dead_end(rg: RoadGraph, n, edt_m, mpp: float, params: GraphParams) -> _DeadEnd:
    """:func:`_turn_loop` at the dead end ``n``, arriving along its one edge."""
    (a, b, k), = list(rg.graph.edges(n, keys=True))
    xy, w = rg.edge_xy(b if a == n else a, n, k)
    return _turn_loop(xy, float(w[-1]), edt_m, mpp, rg.height_m, params)


def _edt_at(edt_m, pts: np.ndarray, mpp: float, height_m: float) -> np.ndarray:
    if edt_m is None:
        return np.zeros(len(pts))
    h, w = edt_m.shape
    u = np.clip(np.floor(pts[:, 0] / mpp).astype(int), 0, w - 1)
    v = np.clip(np.floor((height_m - pts[:, 1]) / mpp).astype(int), 0, h - 1)
    return edt_m[v, u]


def covering_tour(rg: RoadGraph, drivable: np.ndarray | None, mpp: float, params: GraphParams = GraphParams()
                  ) -> tuple[Tour, Tour]:
    """The tour that covers the largest connected part of ``rg`` and its revisit (see the module
    docstring). ``drivable``: the scene's drivable raster (``mpp`` metres per pixel, north up, covering the
    tile), where the loops at dead ends must fit; None: no loop fits anywhere."""
    import networkx as nx
    from scipy import ndimage

    params.check()
    edt_m = None if drivable is None else ndimage.distance_transform_edt(
        np.pad(np.asarray(drivable, bool), 1))[1:-1, 1:-1] * mpp
    if has_oneway(rg.graph):   # one-way streets: the largest part in which every road can be driven and left
        comp = _largest_strong_component(rg.graph)
    else:
        comp = rg.largest_component()
    g = nx.MultiGraph(rg.graph.subgraph(comp))
    sub = RoadGraph(g, rg.width_m, rg.height_m)
    component_m = sub.length_m
    stuck = [n for n in g.nodes if g.degree(n) == 1 and not _dead_end(sub, n, edt_m, mpp, params).turnable]
    # the roads to dead ends beyond the first two that cannot be turned in are left out: keep the two
    # whose roads are longest (the length of road up to the first junction)
    if len(stuck) > 2:
        stuck.sort(key=lambda n: -_pendant_length(g, n))
        for n in stuck[2:]:
            _cut_pendant(g, n)
        stuck = stuck[:2]
    if g.number_of_edges() == 0:
        raise RoadGraphError("no road of the graph can be driven: every dead end is too narrow to turn in")
    covered_m = sub.length_m
    if has_oneway(g):
        return _directed_tours(sub, edt_m, mpp, params, covered_m, component_m, rg.length_m, stuck)
    start = stuck[0] if stuck else min(g.nodes, key=lambda n: (-g.degree(n), n))
    stop = stuck[1] if len(stuck) == 2 else start
    doubled = RoadGraph(_eulerize(sub, start, stop), rg.width_m, rg.height_m)
    walk = _euler_walk(doubled, start)
    closed = not stuck
    tours = []
    for steps in (walk, [(v, u, k) for u, v, k in reversed(walk)]):
        xy, w, loops = _walk_polyline(doubled, steps, edt_m, mpp, params, closed)
        tours.append(Tour(xy, w, closed, covered_m, component_m, rg.length_m, steps, loops))
    return tours[0], tours[1]


def has_oneway(g) -> bool:
    """Whether any edge of the (multi)graph ``g`` is one-way."""
    return any(d.get("oneway", 0) for *_, d in g.edges(data=True))


def allowed(g, u, v, k) -> bool:
    """Whether edge (u, v, k) of ``g`` may be driven from ``u`` to ``v``."""
    d = g.edges[u, v, k]
    return not d.get("oneway", 0) or d["start"] == u


def arc_graph(g) -> nx.MultiDiGraph:
    """The roads of ``g`` as the arcs a car may drive: a one-way edge one arc (from its ``start``), another two
    (one each way); each arc keyed ``(u, v, k, i)`` with the undirected edge ``(u, v, k)`` in ``edge``."""
    import networkx as nx

    d_g = nx.MultiDiGraph()
    d_g.add_nodes_from(g.nodes)
    for u, v, k, d in g.edges(keys=True, data=True):
        a = d["start"]
        b = v if a == u else u
        d_g.add_edge(a, b, key=(u, v, k, 0), length=d["length"], edge=(u, v, k))
        if not d.get("oneway", 0):
            d_g.add_edge(b, a, key=(u, v, k, 1), length=d["length"], edge=(u, v, k))
    return d_g


def _largest_strong_component(g) -> set:
    """The nodes of the strongly connected part of ``g``'s arcs (:func:`arc_graph`) with the most road."""
    import networkx as nx

    comps = [c for c in nx.strongly_connected_components(arc_graph(g)) if len(c) > 1 or any(
        u == v for u, v in g.subgraph(c).edges())]
    if not comps:
        raise RoadGraphError("no road can be driven round: the one-way streets lead nowhere they can be left")
    return max(comps, key=lambda c: sum(d["length"] for *_, d in g.subgraph(c).edges(data=True)))


def _directed_tours(sub: RoadGraph, edt_m, mpp: float, params: GraphParams, covered_m: float,
                    component_m: float, graph_m: float, stuck: list) -> tuple[Tour, Tour]:
    """The tour and its revisit on a graph with one-way streets. Each road is driven at least once, a one-way
    street only its way: the two-way roads are oriented as the undirected tour would drive them (the
    revisit: the other way), the nodes balanced by the shortest drivable detours (a minimum-cost flow over
    the arcs, :func:`arc_graph`), and the result walked as an Euler circuit preferring the straightest way on
    (:func:`_directed_walk`); of the two orientations the shorter walk is the tour, the other its revisit.
    ``stuck``: up to two dead ends the car cannot turn in, where the tour (an open route) starts and ends
    (left only, or only arrived at, once; the revisit the other way round)."""
    g = sub.graph
    start = stuck[0] if stuck else min(g.nodes, key=lambda n: (-g.degree(n), n))
    stop = stuck[1] if len(stuck) == 2 else start
    if stuck:   # the start's road must lead out of it, the stop's into it: swap them if one-way says so
        (a, b, k), = list(g.edges(start, keys=True))
        if not allowed(g, start, b if a == start else a, k):
            start, stop = stop, start
    und = RoadGraph(_eulerize(sub, start, stop), sub.width_m, sub.height_m)
    orient: dict[int, object] = {}
    for a, b, k in _euler_walk(und, start):
        if g.has_edge(a, b, k):
            orient.setdefault(id(g.edges[a, b, k]), a)
    walks = []
    for flip in (False, True):
        first, last = (stop, start) if flip else (start, stop)
        need = []
        for u, v, k, d in g.edges(keys=True, data=True):
            a = d["start"] if d.get("oneway", 0) else orient.get(id(d), d["start"])
            if flip and not d.get("oneway", 0):
                a = v if a == u else u
            if stuck and not d.get("oneway", 0) and u != v:   # out of the first stuck end, into the last
                if first in (u, v) and g.degree(first) == 1:
                    a = first
                elif last in (u, v) and g.degree(last) == 1:
                    a = v if last == u else u
            need.append((a, v if a == u else u, (u, v, k)))
        try:
            walks.append(_directed_walk(sub, need, first, last if len(stuck) == 2 else None,
                                        no_turn=set(stuck)))
        except RoadGraphError:
            if not flip:
                raise
            walks.append(None)   # the revisit's way round is impossible (a one-way street out of a dead end)
    if walks[1] is None:
        raise RoadGraphError("the roads cannot be driven the other way round (the revisit): a one-way street "
                             "leads into or out of a dead end the car cannot turn in")
    # the tour is the shorter of the two orientations (the one that goes with the one-way streets' flow)
    lengths = [sum(g.edges[u, v, k]["length"] for u, v, k in w) for w in walks]
    if lengths[1] < lengths[0] - 1e-6:
        walks.reverse()
    tours = []
    closed = not stuck
    for steps in walks:
        xy, w, loops = _walk_polyline(sub, steps, edt_m, mpp, params, closed)
        tours.append(Tour(xy, w, closed, covered_m, component_m, graph_m, steps, loops))
    return tours[0], tours[1]


def _directed_walk(rg: RoadGraph, need: list[tuple], start, stop=None, no_turn=frozenset()) -> list[tuple]:
    """A walk from ``start`` over every required arc ``need`` ((from, to, (u, v, k)) of ``rg``'s edges) and the
    fewest metres of detours that make it one: each node's surplus of arriving over leaving arcs sent along
    the shortest drivable ways (networkx's minimum-cost flow), then an Euler circuit that at each node takes
    the arc turning least, keeping each node's last exit (a tree of arcs towards the circuit's first node)
    for when no other is left. ``stop``: the walk is open and ends there; neither it nor ``start`` is passed
    through (dead ends the car cannot turn in: no detour enters ``start`` or leaves ``stop``), else it is
    closed. ``no_turn``: dead ends the car cannot turn in (no detour round a block turns back there).
    Returns (u, v, key) steps, ``u`` to ``v`` along edge key ``key``."""
    import networkx as nx

    g = rg.graph
    h = nx.MultiDiGraph()
    h.add_nodes_from(g.nodes)
    for a, b, e in need:
        h.add_edge(a, b, edge=e)
    if stop is not None:
        h.add_edge(stop, start, edge=None)    # a virtual arc closes the walk; the circuit starts with it
    surplus = {n: h.in_degree(n) - h.out_degree(n) for n in h.nodes}
    if any(surplus.values()):
        f = nx.DiGraph()
        f.add_nodes_from(g.nodes)
        for a, b, d in arc_graph(g).edges(data=True):
            if stop is not None and (b == start or a == stop):
                continue
            cost = int(round(100 * d["length"])) + 1
            if a != b and (not f.has_edge(a, b) or f[a][b]["weight"] > cost):
                f.add_edge(a, b, weight=cost, edge=d["edge"])
        for n in f.nodes:
            f.nodes[n]["demand"] = -surplus.get(n, 0)
        try:
            flow = nx.min_cost_flow(f)
        except nx.NetworkXUnfeasible as e:
            raise RoadGraphError(f"the one-way streets cannot all be driven in one tour ({e})") from e
        for a, out in flow.items():
            for b, n in out.items():
                for _ in range(int(n)):
                    h.add_edge(a, b, edge=f[a][b]["edge"])
    origin = stop if stop is not None else start
    last: dict = {}                   # each node's last exit: a tree of arcs towards the circuit's origin
    seen, queue = {origin}, [origin]
    while queue:
        x = queue.pop(0)
        for a, _, key in h.in_edges(x, keys=True):
            if a not in seen:
                seen.add(a)
                last[a] = (x, key)          # keys count per pair of nodes: the arc is (a, x, key)
                queue.append(a)
    steps, cur, heading = [], origin, None
    while h.out_degree(cur) > 0:
        options = list(h.out_edges(cur, keys=True, data=True))
        best, best_cost = None, math.inf
        for _, b, key, d in options:
            xy = None
            if d["edge"] is None:             # the virtual arc: first, and only then
                cost = -math.inf if not steps else math.inf
            else:
                xy, _ = rg.edge_xy(cur, b, d["edge"][2])
                cost = _turn_cost(heading, xy) + (1000.0 if len(options) > 1 and last.get(cur) == (b, key) else 0.0)
            if best is None or cost < best_cost:
                best, best_cost = (b, key, d["edge"], xy), cost
        b, key, e, xy = best
        h.remove_edge(cur, b, key)
        if e is not None:
            heading = _heading(xy, False)
            steps.append((cur, b, e[2]))
        cur = b
    if h.number_of_edges():
        raise RoadGraphError("internal: the directed walk left arcs undriven")
    return _around_the_block(g, steps, closed=stop is None, no_turn=no_turn)


def _around_the_block(g, steps: list[tuple], closed: bool, no_turn=frozenset()) -> list[tuple]:
    """``steps`` with each U-turn at a node where other roads meet (driven back along the road it came by)
    replaced by a drive round the block: the shortest legal loop from that node back to it that leaves by
    another road, arrives by another road and makes no U-turn on the way but at dead ends (where the tour
    turns in a loop, where one fits). A U-turn with no such loop stays."""
    arcs = None
    out: list[tuple] = []
    n_steps = len(steps)
    for i, (a, b, k) in enumerate(steps):
        out.append((a, b, k))
        if i + 1 >= n_steps and not closed:
            continue
        _, nb, nk = steps[(i + 1) % n_steps]
        if nb == a and nk == k and a != b and g.degree(b) >= 3:
            arcs = arc_graph(g) if arcs is None else arcs
            out += _block_loop(g, arcs, b, (a, b, k), no_turn)
    return out


def _block_loop(g, arcs, b, banned: tuple, no_turn=frozenset()) -> list[tuple]:
    """The shortest walk from ``b`` back to ``b`` over ``arcs`` that neither leaves nor arrives along the edge
    ``banned`` and never turns back along the edge it came by but at a dead end: (u, v, key) steps, or []
    (a Dijkstra over (node, edge arrived by) states)."""
    import heapq

    def same(e) -> bool:   # the same road as ``banned``, whichever end it is named from
        return frozenset(e[:2]) == frozenset(banned[:2]) and e[2] == banned[2]

    heap, seen, tick = [], set(), 0
    for _, q, d in arcs.out_edges(b, data=True):
        if not same(d["edge"]):
            heapq.heappush(heap, (d["length"], tick, q, d["edge"], [(b, q, d["edge"][2])]))
            tick += 1
    while heap:
        dist, _, x, e, path = heapq.heappop(heap)
        if x == b:
            if not same(e):
                return path
            continue
        if (x, e) in seen:
            continue
        seen.add((x, e))
        for _, y, d in arcs.out_edges(x, data=True):
            e2 = d["edge"]
            back = e2 == e and e2[0] != e2[1]     # arcs name their edge alike from either end
            if back and (g.degree(x) > 1 or x in no_turn):
                continue                      # no U-turn but at a dead end the car can turn in
            heapq.heappush(heap, (dist + d["length"], tick, y, e2, path + [(x, y, e2[2])]))
            tick += 1
    return []


def _pendant_length(g: nx.MultiGraph, n) -> float:
    total, prev, cur = 0.0, None, n
    while g.degree(cur) <= 2:
        nxt = [(b if a == cur else a, d) for a, b, d in g.edges(cur, data=True) if (b if a == cur else a) != prev]
        if not nxt:
            break
        prev, (cur, d) = cur, nxt[0]
        total += d["length"]
        if cur == n:
            break
    return total


def _cut_pendant(g: nx.MultiGraph, n) -> None:
    """Remove dead end ``n`` and the road up to the first junction."""
    while g.has_node(n) and g.degree(n) == 1:
        (a, b), = [(a, b) for a, b in g.edges(n)]
        nxt = b if a == n else a
        g.remove_node(n)
        n = nxt


def _eulerize(rg: RoadGraph, start, stop) -> nx.MultiGraph:
    """A copy of the graph with the shortest paths between its odd nodes (all but ``start`` and ``stop``
    when they differ) doubled, paired at the least total length: every node even but those two."""
    import networkx as nx

    g = rg.graph
    h = nx.MultiGraph(g)
    odd = [n for n in g.nodes if g.degree(n) % 2 == 1 and (start == stop or n not in (start, stop))]
    if start != stop:   # an open walk: start and stop must be odd, the others even
        odd += [n for n in (start, stop) if g.degree(n) % 2 == 0]
    if not odd:
        return h
    dist = {n: nx.single_source_dijkstra(g, n, weight="length") for n in odd}
    k = nx.Graph()
    for i, a in enumerate(odd):
        for b in odd[i + 1:]:
            k.add_edge(a, b, weight=dist[a][0][b])
    for a, b in nx.min_weight_matching(k, weight="weight"):
        path = dist[a][1][b]
        for p, q in zip(path[:-1], path[1:]):
            kk = min(g[p][q], key=lambda key: g[p][q][key]["length"])
            h.add_edge(p, q, **g.edges[p, q, kk])
    return h


def _euler_walk(rg: RoadGraph, start) -> list[tuple]:
    """Fleury's walk over every edge of ``rg`` (every node even, or all but ``start`` and one other) from
    ``start``, at each node taking the edge that turns least (right before left), never a bridge while
    another edge is left and never back the way it came while another way is left. Returns (u, v, key)
    steps."""
    import networkx as nx

    h = nx.MultiGraph(rg.graph)
    steps = []
    cur, heading = start, None
    while h.degree(cur) > 0:
        best, best_cost = None, math.inf
        options = list(h.edges(cur, keys=True))
        for a, b, k in options:
            nxt = b if a == cur else a
            xy, _ = rg.edge_xy(cur, nxt, k)
            cost = _turn_cost(heading, xy)
            if len(options) > 1 and _is_bridge(h, cur, nxt, k):
                cost += 100.0
            if cost < best_cost:
                best, best_cost = (cur, nxt, k), cost
        u, v, k = best
        xy, _ = rg.edge_xy(u, v, k)
        heading = _heading(xy, False)
        steps.append((u, v, k))
        h.remove_edge(u, v, k)
        cur = v
    if h.number_of_edges():
        raise RoadGraphError("internal: the Euler walk left edges undriven")
    return steps


def _turn_cost(heading: float | None, xy: np.ndarray) -> float:
    """What taking the road ``xy`` on from ``heading`` costs a walk: the turn (radians), left a little dearer
    than right, a U-turn much dearer; nothing for the first step."""
    if heading is None:
        return 0.0
    t = _turn(heading, _heading(xy, True))
    return abs(t) + (0.05 if t > 0 else 0.0) + (10.0 if abs(t) > _UTURN else 0.0)


def _is_bridge(h: nx.MultiGraph, u, v, k) -> bool:
    """Whether removing edge (u, v, k) leaves ``v`` unreachable from ``u`` (a self-loop never is)."""
    import networkx as nx

    if u == v or h.number_of_edges(u, v) > 1:
        return False
    d = h.edges[u, v, k]
    h.remove_edge(u, v, k)
    try:
        return not nx.has_path(h, u, v)
    finally:
        h.add_edge(u, v, key=k, **d)


def _walk_polyline(rg: RoadGraph, steps, edt_m, mpp: float, params: GraphParams, closed: bool):
    """The walk as a smoothed, resampled polyline with the road width at each point; a keyhole loop where
    it turns back at a node. Returns (xy, widths, number of loops)."""
    xs, ws = [], []
    loops = 0
    pending = None          # a loop's entry point: where the next edge is driven from
    for i, (u, v, k) in enumerate(steps):
        xy, w = rg.edge_xy(u, v, k)
        if u == v and _signed_area(xy) < 0:    # a ring (a turning circle): counter-clockwise, car outside
            xy, w = xy[::-1], w[::-1]
        if pending is not None:
            xy, w = _from_point(xy, w, pending)
            pending = None
        nxt = steps[i + 1] if i + 1 < len(steps) else (steps[0] if closed else None)
        if nxt is not None:
            nxy, _ = rg.edge_xy(*nxt)
            if abs(_turn(_heading(xy, False), _heading(nxy, True))) > _UTURN:
                end = _turn_loop(xy, float(w[-1]), edt_m, mpp, rg.height_m, params)
                xy, w, loop = _keyhole(xy, w, end.centre, end.radius)
                xs += [xy, loop]
                ws += [w, np.full(len(loop), w[-1])]
                pending = xy[-1]
                loops += 1
                continue
        xs.append(xy)
        ws.append(w)
    if pending is not None:   # a closed walk that turns back where it started
        xs[0], ws[0] = _from_point(xs[0], ws[0], pending)
    xy, w = np.vstack(xs), np.concatenate(ws)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(xy, axis=0), axis=1) > 1e-6])
    xy, w = xy[keep], w[keep]
    if closed and len(xy) > 2 and np.linalg.norm(xy[-1] - xy[0]) < 1e-6:
        xy, w = xy[:-1], w[:-1]
    return _finish(xy, w, params, closed) + (loops,)


def _signed_area(xy: np.ndarray) -> float:
    """Signed area of the closed polygon ``xy`` (positive: counter-clockwise)."""
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _keyhole(xy: np.ndarray, w: np.ndarray, centre: np.ndarray, radius: float):
    """Cut the arriving polyline ``xy`` (widths ``w``) where it enters the circle (``centre``, ``radius``;
    where it comes closest, if it never does) and return it with the loop: once round a circle about
    ``centre`` counter-clockwise from that point, back to it. Returns (xy, w, loop)."""
    s = arc_length(xy)
    dense = np.linspace(0.0, s[-1], max(2, int(s[-1] / 0.05) + 1))
    px, py = np.interp(dense, s, xy[:, 0]), np.interp(dense, s, xy[:, 1])
    d = np.hypot(px - centre[0], py - centre[1])
    inside = np.flatnonzero(d <= radius)
    j = int(inside[0]) if len(inside) else int(np.argmin(d))
    se = dense[j]
    entry = np.array([px[j], py[j]])
    cut = s < se - 1e-9
    arriving = np.vstack([xy[cut], entry[None]])
    warr = np.append(w[cut], np.interp(se, s, w))
    if len(arriving) < 2:
        arriving, warr = np.vstack([xy[:1], entry[None]]), np.append(w[:1], warr[-1])
    r = max(float(np.linalg.norm(entry - centre)), 1e-3)
    a0 = math.atan2(entry[1] - centre[1], entry[0] - centre[0])
    n = max(16, int(2 * math.pi * r / 0.5))
    ang = a0 + np.linspace(0, 2 * math.pi, n + 1)
    loop = centre[None] + r * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    return arriving, warr, loop[1:]


def _from_point(xy: np.ndarray, w: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The polyline ``xy`` (widths ``w``) from its point closest to ``p`` on, starting at ``p``."""
    s = _project(xy, p[None])[0]
    cum = arc_length(xy)
    j = int(np.searchsorted(cum, s, side="right"))
    ws = float(np.interp(s, cum, w))
    if j >= len(xy):
        return np.vstack([p[None], xy[-1:]]), np.array([ws, w[-1]])
    return np.vstack([p[None], xy[j:]]), np.concatenate([[ws], w[j:]])


def lane_widths(w: np.ndarray, spacing_m: float, closed: bool) -> np.ndarray:
    """Road widths at a route's waypoints (``spacing_m`` apart) as its lane offsets should follow them: the
    narrowest within 20 m, smoothed, so the car moves over to a narrower street's lane before it gets there
    (the autopilot looks 6 m ahead and takes about three times that to settle on a new lateral offset)."""
    from scipy import ndimage

    k = max(1, int(round(20.0 / spacing_m)))
    mode = "wrap" if closed else "nearest"
    w = ndimage.minimum_filter1d(np.asarray(w, np.float64), 2 * k + 1, mode=mode)
    return ndimage.gaussian_filter1d(w, max(1.0, 3.0 / spacing_m), mode=mode)


def _finish(xy: np.ndarray, w: np.ndarray, params: GraphParams, closed: bool) -> tuple[np.ndarray, np.ndarray]:
    """Smooth and resample a walk's polyline; its widths follow (:func:`lane_widths`)."""
    s_raw = arc_length(np.vstack([xy, xy[:1]]) if closed else xy)
    out = _smooth(xy, params.smooth_m, closed)
    out = _resample(out, params.spacing_m, closed)
    # widths: at each output point, the raw width at the same fraction of the arc length
    s_out = arc_length(np.vstack([out, out[:1]]) if closed else out)
    frac = s_out[:len(out)] / max(s_out[-1], 1e-9)
    wr = np.append(w, w[:1]) if closed else w
    return out, lane_widths(np.interp(frac * s_raw[-1], s_raw, wr), params.spacing_m, closed)


# --- snapped routes ---------------------------------------------------------------------------------------
def snapped_route(rg: RoadGraph, points: np.ndarray, closed: bool, params: GraphParams = GraphParams()
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Waypoints along the roads through ``points`` (map metres), each moved to the nearest road: the
    shortest way along the roads from one to the next (and back to the first when ``closed``), smoothed and
    resampled as a tour. Returns (waypoints, widths); RoadGraphError naming the first point farther than
    ``snap_route_m`` from every road."""
    import networkx as nx

    params.check()
    g = nx.MultiGraph(rg.graph)
    work = RoadGraph(g, rg.width_m, rg.height_m)
    anchors = []
    for i, p in enumerate(np.asarray(points, np.float64).reshape(-1, 2)):
        best = None
        for u, v, k, d in g.edges(keys=True, data=True):
            s = _project(d["xy"], p[None])[0]
            q = np.array([np.interp(s, arc_length(d["xy"]), d["xy"][:, 0]),
                          np.interp(s, arc_length(d["xy"]), d["xy"][:, 1])])
            dist = float(np.linalg.norm(q - p))
            if best is None or dist < best[0]:
                best = (dist, u, v, k, s)
        if best is None or best[0] > params.snap_route_m:
            raise RoadGraphError(f"[{i}]: the point ({p[0]:.1f}, {p[1]:.1f}) m lies "
                                 f"{'nowhere near a road' if best is None else f'{best[0]:.1f} m from the nearest road'}"
                                 f"; snap_route_m is {params.snap_route_m:g} m")
        anchors.append(_split_at(work, *best[1:]))
    seq = anchors + ([anchors[0]] if closed else [])
    ways = arc_graph(g) if has_oneway(g) else g     # one-way streets: only the ways a car may drive
    pieces, wpieces = [], []
    for i, (a, b) in enumerate(zip(seq[:-1], seq[1:])):
        if a == b:
            continue
        try:
            path = nx.shortest_path(ways, a, b, weight="length")
        except nx.NetworkXNoPath as e:
            raise RoadGraphError(f"[{(i + 1) % len(anchors)}]: no way leads there from the waypoint before it "
                                 f"along the roads' one-way streets") from e
        for p, q in zip(path[:-1], path[1:]):
            kk = min(ways[p][q], key=lambda key: ways[p][q][key]["length"])
            if ways is not g:
                kk = ways[p][q][kk]["edge"][2]
            xy, w = work.edge_xy(p, q, kk)
            pieces.append(xy)
            wpieces.append(w)
    if not pieces:
        raise RoadGraphError("the snapped waypoints all lie at one point of the roads")
    xy = np.vstack(pieces)
    w = np.concatenate(wpieces)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(xy, axis=0), axis=1) > 1e-6])
    xy, w = xy[keep], w[keep]
    if closed and np.linalg.norm(xy[-1] - xy[0]) < 1e-6:
        xy, w = xy[:-1], w[:-1]
    return _finish(xy, w, params, closed)


def _split_at(rg: RoadGraph, u, v, k, s: float):
    """A node at arc length ``s`` (from the edge's ``start``) of edge (u, v, k): an end node when ``s`` is
    within 1 cm of an end, else a new node splitting the edge."""
    g = rg.graph
    d = g.edges[u, v, k]
    xy, w, start = d["xy"], d["w"], d["start"]
    end = v if start == u else u
    cum = arc_length(xy)
    if s <= 0.01:
        return start
    if s >= cum[-1] - 0.01:
        return end
    p = np.array([np.interp(s, cum, xy[:, 0]), np.interp(s, cum, xy[:, 1])])
    pw = float(np.interp(s, cum, w))
    j = int(np.searchsorted(cum, s, side="right"))
    a_xy, a_w = np.vstack([xy[:j], p[None]]), np.append(w[:j], pw)
    b_xy, b_w = np.vstack([p[None], xy[j:]]), np.concatenate([[pw], w[j:]])
    n = max((x for x in g.nodes if isinstance(x, int)), default=-1) + 1
    one = int(d.get("oneway", 0))
    g.add_node(n, xy=p)
    g.remove_edge(u, v, k)
    g.add_edge(start, n, xy=a_xy, w=a_w, length=float(arc_length(a_xy)[-1]), start=start, oneway=one)
    g.add_edge(n, end, xy=b_xy, w=b_w, length=float(arc_length(b_xy)[-1]), start=n, oneway=one)
    return n
