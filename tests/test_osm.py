"""OpenStreetMap extracts as users bring them (issue 35): any vector file GDAL reads, found by opening it;
OSM's tags (drivable classes only, oneway, bridge / tunnel / layer, lengths with units, building bases and
roofs); footprints repaired, not dropped; road layers that do not meet where they cross; ends snapped
through a spatial index.

The OSM file is written here: an XML export over the GeoTIFF of ``test_roads`` (UTM 32N, 160 m x 120 m).
"""
from __future__ import annotations

import numpy as np
import pyproj
import pytest
import shapely
import yaml
from test_roads import E0, N0, RES, UTM, image

from satloc import FormatError, SatlocWarning
from satloc.geodata.vectors import (
    is_vector_file,
    parse_length,
    read_footprints,
    read_road_lines,
    read_trees,
    road_layer,
    road_oneway,
)
from satloc_env.world.roadgraph import GraphParams, _snap_ends, graph_from_lines
from satloc_env.world.scene import load_scene

TO_LONLAT = pyproj.Transformer.from_crs(UTM, "EPSG:4326", always_xy=True)

# ways in metres east / north of (E0, N0): (node list, tags)
NODES = {
    1: (5.0, 60.0), 2: (155.0, 60.0),                                       # main street, west to east
    3: (80.0, 5.0), 4: (80.0, 45.0), 5: (80.0, 75.0), 6: (80.0, 115.0),     # a road south to north ...
    7: (20.0, 95.0), 8: (140.0, 95.0), 9: (140.0, 103.0), 10: (20.0, 103.0),   # a one-way pair
    11: (10.0, 10.0), 12: (10.0, 110.0),                                    # a footway
    13: (20.0, 20.0), 14: (150.0, 22.0),                                    # a railway
    20: (30.0, 30.0), 21: (50.0, 30.0), 22: (50.0, 45.0), 23: (30.0, 45.0),  # a house
    24: (100.0, 30.0), 25: (120.0, 45.0), 26: (120.0, 30.0), 27: (100.0, 45.0),  # a bow tie
}
WAYS = [
    ([1, 2], {"highway": "residential", "width": "7,5"}),
    ([3, 4], {"highway": "primary", "lanes": "2"}),
    ([4, 5], {"highway": "primary", "lanes": "2", "bridge": "yes", "layer": "1"}),   # ... over the main street
    ([5, 6], {"highway": "primary", "lanes": "2"}),
    ([7, 8], {"highway": "residential", "oneway": "yes"}),
    ([9, 10], {"highway": "residential", "oneway": "-1"}),
    ([11, 12], {"highway": "footway"}),
    ([13, 14], {"railway": "rail"}),
    ([20, 21, 22, 23, 20], {"building": "house", "height": "24 ft", "roof:shape": "gabled", "min_height": "3"}),
    ([24, 25, 26, 27, 24], {"building": "yes", "building:levels": "2"}),
]
TREE = ((65.0, 85.0), {"natural": "tree", "height": "9,5"})


def osm_xml(nodes=NODES, ways=WAYS) -> str:
    def node(i, xy, tags=None):
        lon, lat = TO_LONLAT.transform(E0 + xy[0], N0 + xy[1])
        inner = "".join(f'<tag k="{k}" v="{v}"/>' for k, v in (tags or {}).items())
        return f'  <node id="{i}" lat="{lat:.8f}" lon="{lon:.8f}">{inner}</node>\n'

    out = ['<?xml version="1.0" encoding="UTF-8"?>\n<osm version="0.6" generator="satloc tests">\n']
    out += [node(i, xy) for i, xy in nodes.items()]
    out.append(node(99, *TREE))
    for w, (refs, tags) in enumerate(ways):
        nds = "".join(f'<nd ref="{r}"/>' for r in refs)
        tg = "".join(f'<tag k="{k}" v="{v}"/>' for k, v in tags.items())
        out.append(f'  <way id="{100 + w}">{nds}{tg}</way>\n')
    out.append("</osm>\n")
    return "".join(out)


@pytest.fixture(scope="module")
def osm(tmp_path_factory):
    d = tmp_path_factory.mktemp("osm")
    (d / "export.osm").write_text(osm_xml())
    return d / "export.osm"


def test_lengths_with_units():
    assert parse_length("7,5") == 7.5 and parse_length("7.5 m") == 7.5 and parse_length(6) == 6.0
    assert parse_length("24 ft") == pytest.approx(7.3152) and parse_length("24'") == pytest.approx(7.3152)
    assert parse_length("23'6\"") == pytest.approx(23 * 0.3048 + 6 * 0.0254)
    assert parse_length("350 cm") == pytest.approx(3.5)
    for bad in ("wide", "2;3", "", None, "7 furlongs", float("nan")):
        assert parse_length(bad) is None


def test_oneway_and_layer_tags():
    assert road_oneway({"oneway": "yes"}) == 1 and road_oneway({"oneway": "-1"}) == -1
    assert road_oneway({"highway": "motorway"}) == 1 and road_oneway({"junction": "roundabout"}) == 1
    assert road_oneway({"highway": "motorway", "oneway": "no"}) == 0 and road_oneway({}) == 0
    assert road_layer({"layer": "2"}) == 2 and road_layer({"bridge": "viaduct"}) == 1
    assert road_layer({"tunnel": "yes"}) == -1 and road_layer({"layer": "-1", "bridge": "yes"}) == -1
    assert road_layer({"bridge": "no"}) == 0


def test_an_osm_export_is_roads_buildings_and_trees(osm):
    roads = read_road_lines(osm)
    # the footway and the railway are not roads for cars; the six car ways are
    assert len(roads.lines) == 6
    assert roads.widths.tolist() == [7.5, 7.0, 7.0, 7.0, 7.0, 7.0]
    assert roads.oneway.tolist() == [0, 0, 0, 0, 1, -1]
    assert roads.layers.tolist() == [0, 0, 1, 0, 0, 0]
    # asked for, the footway is a road too
    assert len(read_road_lines(osm, classes={"residential", "primary", "footway"}).lines) == 7
    with pytest.raises(FormatError, match=r"highway classes \(.*footway: 1.*\) are none of the road classes"):
        read_road_lines(osm, classes={"motorway"})
    fp = read_footprints(osm)
    assert len(fp.rings) == 3   # the house, and the bow tie repaired into its two triangles
    assert fp.repaired == 1
    house = int(np.argmax([len(r) == 4 for r in fp.rings]))
    assert fp.heights[house] == pytest.approx(24 * 0.3048) and fp.bases[house] == 3.0
    assert fp.roofs[house] == "gabled" and sorted(fp.roofs) == ["flat", "flat", "gabled"]
    assert sorted(h for h in fp.heights if h != fp.heights[house]) == [6.0, 6.0]
    t = read_trees(osm)   # the OSM nodes of the ways are not trees; the natural=tree node is
    assert len(t.points) == 1 and t.point_heights == [9.5] and not t.canopies


def test_a_vector_file_is_found_by_opening_it(osm, tmp_path):
    xml = tmp_path / "export.xml"              # an OSM export without the .osm ending
    xml.write_bytes(osm.read_bytes())
    noext = tmp_path / "roads"
    noext.write_bytes(osm.read_bytes())
    assert is_vector_file(xml) and is_vector_file(noext) and is_vector_file(tmp_path / "missing.fgb")
    image(tmp_path)
    assert not is_vector_file(tmp_path / "tile.tif") and not is_vector_file(tmp_path / "missing.xml")
    (tmp_path / "notes.txt").write_text("not vectors")
    assert not is_vector_file(tmp_path / "notes.txt")
    assert len(read_road_lines(xml).lines) == 6


@pytest.mark.parametrize("driver, name", [("FlatGeobuf", "roads.fgb"), ("KML", "roads.kml")])
def test_other_gdal_formats(osm, tmp_path, driver, name):
    from pyogrio.raw import write

    roads = read_road_lines(osm)
    geoms = np.array([shapely.to_wkb(shapely.LineString(xy)) for xy in roads.lines], dtype=object)
    hw = np.array(["residential"] * len(geoms), dtype=object)
    write(str(tmp_path / name), geoms, [hw], ["highway"], driver=driver, crs="EPSG:4326",
          geometry_type="LineString")
    got = read_road_lines(tmp_path / name)
    assert len(got.lines) == 6
    for a in got.lines:   # FlatGeobuf orders the features by its spatial index
        assert min(np.abs(a[:, :2] - b).max() if a.shape == b.shape else 1.0 for b in roads.lines) < 1e-6


def test_a_bridge_is_no_junction(osm):
    roads = read_road_lines(osm).to_crs(UTM)
    lines = [xy - [E0, N0] for xy in roads.lines[:4]]      # the main street and the road over it
    crossing = np.array([80.0, 60.0])
    flat = graph_from_lines(lines, roads.widths[:4], 160, 120, GraphParams())
    layered = graph_from_lines(lines, roads.widths[:4], 160, 120, GraphParams(), roads.layers[:4])

    def junctions(rg):
        return [n for n in rg.graph.nodes if rg.graph.degree(n) >= 3
                and np.linalg.norm(rg.graph.nodes[n]["xy"] - crossing) < 1.0]

    assert len(junctions(flat)) == 1        # without layers the crossing is a four-way junction
    assert junctions(layered) == []         # with them the bridge passes over: two roads, no junction
    import networkx as nx

    assert nx.number_connected_components(layered.graph) == 2
    assert layered.length_m == pytest.approx(flat.length_m, rel=1e-6)


def test_snapping_uses_only_nearby_lines_of_the_same_layer():
    a = np.array([[0.0, 0.0], [100.0, 0.0]])
    b = np.array([[50.0, 1.5], [50.0, 50.0]])          # ends 1.5 m from a: snapped onto it
    out, _ = _snap_ends([a, b], [np.full(2, 7.0), np.full(2, 7.0)], 2.0)
    assert np.allclose(out[1][0], [50.0, -0.01], atol=1e-6) and np.array_equal(out[0], a)
    out, _ = _snap_ends([a, b], [np.full(2, 7.0), np.full(2, 7.0)], 2.0, np.array([0, 1]))
    assert np.array_equal(out[1], b)                    # on another layer: left as it is


def test_a_scene_from_one_osm_export(osm, tmp_path):
    """One OSM file named without its ending serves as the roads, the buildings and the trees of a scene."""
    (tmp_path / "map").write_bytes(osm.read_bytes())
    p = tmp_path / "osm.yaml"
    p.write_text(yaml.safe_dump({"name": "osm", "generator": {
        "type": "image", "image": image(tmp_path), "roads": "map", "buildings": "map", "trees": "map"},
        "meters_per_pixel": RES, "ground_mpp": RES}))
    with pytest.warns(SatlocWarning, match=r"routes: the derived tour drives \d+ % of the road network"):
        sc = load_scene(p)
    assert len(sc.layout.trees) >= 1 and sc.routes["main"].length > 100
    assert len(sc.layout.buildings) >= 1
    # the tour drives the main street; the road over its bridge and the one-way pair are parts of their own
    tour = sc.summary()["tour"]
    assert 0.2 < tour["coverage"] < 0.5 and tour["network_km"] > 0.4


# a shop whose footprint reaches 4 m into the main street (y 56.25-63.75 m): trimmed, not dropped
SHOP_NODES = {30: (40.0, 58.0), 31: (60.0, 58.0), 32: (60.0, 75.0), 33: (40.0, 75.0)}
SHOP = ([30, 31, 32, 33, 30], {"building": "retail", "height": "8"})


def _scene(tmp_path, gen: dict, routes=None, nodes=NODES, ways=WAYS):
    (tmp_path / "map.osm").write_text(osm_xml(nodes, ways))
    d = {"name": "osm", "generator": {"type": "image", "image": image(tmp_path), **gen},
         "meters_per_pixel": RES, "ground_mpp": RES}
    if routes:
        d["routes"] = routes
    p = tmp_path / "s.yaml"
    p.write_text(yaml.safe_dump(d))
    return load_scene(p)


def test_a_footprint_over_the_road_is_trimmed_by_it(tmp_path):
    with pytest.warns(SatlocWarning, match=r"of 4 footprints, 1 overlap the road: 1 trimmed to the road's edge"):
        sc = _scene(tmp_path, {"roads": "map.osm", "buildings": "map.osm"}, nodes={**NODES, **SHOP_NODES},
                    ways=[*WAYS, SHOP])
    rep = sc.summary()["footprints"]
    assert rep == {"read": 4, "kept": 3, "trimmed": 1, "repaired": 1, "dropped": 0, "outside_tile": 0}
    main_y = sc.satmap.frame.to_map(np.array(TO_LONLAT.transform(E0 + 50.0, N0 + 60.0))[None])[0, 1]
    shop = [b for b in sc.layout.buildings if shapely.Polygon(b.footprint).contains(
        shapely.Point(sc.satmap.frame.to_map(np.array(TO_LONLAT.transform(E0 + 50.0, N0 + 70.0))[None])[0]))]
    assert len(shop) == 1
    ys = shop[0].footprint[:, 1]
    assert ys.min() > main_y + 7.5 / 2          # off the road's surface
    area = shapely.Polygon(shop[0].footprint).area
    assert 0.4 * 340 < area < 0.75 * 340        # most of the north part stands: 20 m x ~11 m of 20 x 17
    assert sc.layout.buildings and all(b.height > 0 for b in sc.layout.buildings)


def test_without_road_data_the_routes_corridor_is_the_road(tmp_path):
    """No roads: and no labels: a footprint is trimmed by the given route's corridor only, not dropped because
    the whole tile counted as road (every one of them was, before)."""
    route = {"main": {"waypoints": [[5.0, 60.0], [155.0, 60.0]]}}
    with pytest.warns(SatlocWarning, match="1 trimmed to the road's edge"):
        sc = _scene(tmp_path, {"buildings": "map.osm"}, routes=route, nodes={**NODES, **SHOP_NODES},
                    ways=[*WAYS, SHOP])
    assert sc.summary()["footprints"]["dropped"] == 0
    assert len(sc.layout.buildings) == 4        # the house, the bow tie's two halves and the trimmed shop


def test_bench_osm_loads_a_synthetic_extract_into_one_graph(tmp_path):
    """`satloc bench osm`'s extract (a street grid, one way per block side) becomes a graph with one edge per
    way, but for the grid's corners, whose two sides merge (the figures it prints are timings: not tested)."""
    from satloc_env.experiments.bench import bench_osm

    (row,) = bench_osm((200,), tmp_path)
    assert row["ways"] == 180 and row["side_m"] == 540.0         # k = 9 blocks a side: 2 k (k + 1) ways
    assert row["graph_edges"] == 180 - 4
    assert row["graph_km"] == pytest.approx(180 * 60 / 1000, rel=0.05)
    assert all(row[k] >= 0 for k in ("read_s", "to_crs_s", "graph_s", "total_s"))


def _write_dsm(path, crs: str, ground: float, objects: list[tuple[list, float]], res: float = 0.5):
    """A surface model over the test tile in ``crs``: ``ground`` everywhere (a gentle slope of 1 m per 100 m to
    the east, which the ring around each footprint absorbs), each (local-metres polygon, height) above it."""
    import rasterio
    from affine import Affine
    from rasterio.features import rasterize

    to = pyproj.Transformer.from_crs(UTM, crs, always_xy=True)
    x0, y0 = to.transform(E0 - 20, N0 - 20)
    x1, y1 = to.transform(E0 + 180, N0 + 140)
    w, h = int((x1 - x0) / res), int((y1 - y0) / res)
    tr = Affine(res, 0, x0, 0, -res, y1)
    cols = np.arange(w) * res + x0
    z = np.tile(ground + (cols - x0) / 100.0, (h, 1)).astype(np.float32)
    for ring, height in objects:
        xy = np.asarray(ring) + [E0, N0]
        poly = shapely.Polygon(np.stack(to.transform(xy[:, 0], xy[:, 1]), 1))
        inside = rasterize([(poly, 1)], out_shape=(h, w), transform=tr, fill=0, dtype="uint8").astype(bool)
        z[inside] += height
    z[:5, :5] = -9999.0   # nodata in a corner
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=1, dtype="float32", crs=crs,
                       transform=tr, nodata=-9999.0) as ds:
        ds.write(z, 1)
    return path


@pytest.mark.parametrize("kind, ground", [("dsm", 312.0), ("ndsm", 0.0)])
def test_heights_from_a_surface_model_in_another_crs(tmp_path, kind, ground):
    """generator.heights: a DSM (terrain at 312 m) or an nDSM in Web Mercator sets the house's height (its
    attribute says 24 ft) and the tree's; footprints outside the model keep their attributes."""
    house = [NODES[i] for i in (20, 21, 22, 23)]
    tree = shapely.Point(TREE[0]).buffer(2.5)
    _write_dsm(tmp_path / "dsm.tif", "EPSG:3857", ground, [(house, 12.5), (list(tree.exterior.coords), 14.0)])
    sc = _scene(tmp_path, {"roads": "map.osm", "buildings": "map.osm", "trees": "map.osm", "heights": "dsm.tif"})
    centre = sc.satmap.frame.to_map(np.array(TO_LONLAT.transform(E0 + 40.0, N0 + 37.5))[None])[0]
    (b,) = [b for b in sc.layout.buildings if shapely.Polygon(b.footprint).contains(shapely.Point(centre))]
    # Web Mercator's scale at 49 degrees: the model's 0.5 m pixels are 0.33 m on the ground
    assert b.height == pytest.approx(12.5, abs=0.5)
    assert sc.summary()["footprints"]["heights_from_raster"] == 1   # the bow tie stands on bare ground there:
    assert sorted(x.height for x in sc.layout.buildings if x is not b) == [6.0, 6.0]   # its 2 levels
    (t,) = sc.layout.trees
    assert t.canopy_top == pytest.approx(14.0, abs=0.5)


def test_a_height_raster_needs_objects_and_a_crs(tmp_path):
    from satloc import ConfigError

    _write_dsm(tmp_path / "dsm.tif", "EPSG:3857", 0.0, [])
    with pytest.raises(ConfigError, match="generator.heights: a height raster sets the heights of buildings"):
        _scene(tmp_path, {"roads": "map.osm", "heights": "dsm.tif"})
    (tmp_path / "bad.tif").write_text("not a raster")
    with pytest.raises(ConfigError, match=r"generator\.heights: .*bad\.tif: not a readable raster"):
        _scene(tmp_path, {"roads": "map.osm", "buildings": "map.osm", "heights": "bad.tif"})


# one-way streets: a block (two-way bottom, right and left sides), its top one-way westwards as drawn, and a
# middle street drawn southwards but one-way northwards (oneway=-1)
BLOCK_LINES = [np.array(p, np.float64) + 10 for p in (
    [(0, 0), (100, 0)], [(100, 0), (100, 60)], [(100, 60), (0, 60)], [(0, 60), (0, 0)], [(50, 60), (50, 0)])]
BLOCK_ONEWAY = [0, 0, 1, 0, -1]


def _block_graph():
    return graph_from_lines(BLOCK_LINES, [7.0] * 5, 120, 80, GraphParams(), oneway=BLOCK_ONEWAY)


def test_one_way_streets_keep_their_direction_in_the_graph():
    from satloc_env.world.roadgraph import allowed

    rg = _block_graph()
    g = rg.graph
    ones = [(u, v, k) for u, v, k, d in g.edges(keys=True, data=True) if d["oneway"]]
    assert len(ones) == 3      # the top street, cut by the middle one, and the middle street
    for u, v, k in ones:
        d = g.edges[u, v, k]
        xy = d["xy"]           # stored from the node it may be driven from
        if abs(xy[0, 0] - xy[-1, 0]) < 1:           # the middle street: northwards only
            assert xy[-1, 1] > xy[0, 1]
        else:                                        # the top: westwards only
            assert xy[-1, 0] < xy[0, 0]
        assert allowed(g, d["start"], v if d["start"] == u else u, k)
        assert not allowed(g, v if d["start"] == u else u, d["start"], k)


def test_tours_drive_one_way_streets_their_way_and_cover_every_road():
    from satloc_env.world.roadgraph import allowed, covering_tour

    rg = _block_graph()
    g = rg.graph
    main, revisit = covering_tour(rg, None, 0.5, GraphParams())
    assert main.closed and revisit.closed and main.coverage == pytest.approx(1.0)
    directions = []
    for tour in (main, revisit):
        assert all(allowed(g, u, v, k) for u, v, k in tour.steps)          # never against a one-way street
        assert {frozenset((u, v, k)) for u, v, k in tour.steps} >= {frozenset(e) for e in g.edges(keys=True)}
        directions.append({(u, v, k) for u, v, k in tour.steps})
        # consecutive steps join up
        assert all(a[1] == b[0] for a, b in zip(tour.steps, tour.steps[1:] + tour.steps[:1]))
    two_way = [(u, v, k) for u, v, k, d in g.edges(keys=True, data=True) if not d["oneway"]]
    for u, v, k in two_way:   # the revisit drives every two-way road the other way from a drive of the tour
        assert any((b, a, k) in directions[0] for a, b, kk in directions[1] if kk == k and {a, b} == {u, v})
    # the tour goes with the one-way streets' flow: no longer than its revisit
    length = lambda t: sum(g.edges[u, v, k]["length"] for u, v, k in t.steps)   # noqa: E731
    assert length(main) <= length(revisit)


def test_snapped_routes_go_round_one_way_streets():
    from satloc_env.world.roadgraph import snapped_route

    rg = _block_graph()
    # from the top's east end to its west end: westwards along it, 100 m
    xy, _ = snapped_route(rg, np.array([[105.0, 70.0], [15.0, 70.0]]), False, GraphParams())
    assert np.max(xy[:, 1]) < 72 and np.min(xy[:, 1]) > 68
    # the other way round it may not: it goes round the block (down, along the bottom, up the right side)
    xy, _ = snapped_route(rg, np.array([[15.0, 70.0], [105.0, 70.0]]), False, GraphParams())
    assert np.min(xy[:, 1]) < 15
    from satloc_env.world.roadgraph import RoadGraphError
    from satloc_env.world.roadgraph import graph_from_lines as gfl

    trap = gfl([BLOCK_LINES[0]], [7.0], 120, 80, GraphParams(), oneway=[1])
    with pytest.raises(RoadGraphError, match=r"\[1\]: no way leads there .* one-way"):
        snapped_route(trap, np.array([[100.0, 10.0], [20.0, 10.0]]), False, GraphParams())


def test_shipped_suburb_tour_honours_its_one_way_turning_circles():
    """suburb_utm's turning circles are mapped oneway=yes (junction=circular): its open tour (both ends of the
    main road stop at the tile's edge) drives each circle its way and covers the whole network."""
    from satloc_env.world.roadgraph import allowed, covering_tour, has_oneway
    from satloc_env.world.scene import DRIVABLE

    sc = load_scene("suburb_utm")
    g = sc.road_graph.graph
    assert has_oneway(g)
    main, revisit = covering_tour(sc.road_graph, np.isin(sc.layout.ground_labels, DRIVABLE), sc.layout.ground_mpp,
                                  sc.spec.road_graph)
    assert not main.closed and main.coverage == pytest.approx(1.0) and sc.summary()["tour"]["coverage"] == 1.0
    for t in (main, revisit):
        assert all(allowed(g, u, v, k) for u, v, k in t.steps)
    assert main.steps[0][0] == revisit.steps[-1][1] and main.steps[-1][1] == revisit.steps[0][0]


def _vector_scene(tmp_path, **gen):
    (tmp_path / "map.osm").write_text(osm_xml())
    p = tmp_path / "v.yaml"
    p.write_text(yaml.safe_dump({"name": "vworld", "seed": 3, "generator": {
        "type": "vectors", "roads": "map.osm", "buildings": "map.osm", "trees": "map.osm", **gen},
        "meters_per_pixel": 0.5, "ground_mpp": 0.25}))
    return p


def test_a_world_from_vectors_alone(tmp_path):
    """generator type vectors: the OSM extract alone makes a world: its frame from the roads' bounds, the
    ground painted by class (roads, sidewalks, centre lines, grass), the buildings standing, a captured map,
    derived routes an env drives."""
    import gymnasium as gym

    from satloc.labels import CLASS_ID
    from satloc_env.world.scene import DRIVABLE

    with pytest.warns(SatlocWarning, match="derived tour drives"):
        sc = load_scene(_vector_scene(tmp_path))
    lab = sc.layout.ground_labels
    frac = {c: float((lab == CLASS_ID[c]).mean()) for c in ("road", "sidewalk", "lane_marking", "grass", "building")}
    assert all(v > 0 for v in frac.values()), frac
    assert 0.05 < frac["road"] < 0.4 and frac["lane_marking"] < 0.02
    # the frame: the roads' bounds and 20 m around them (main street 150 m, the road over it 110 m long)
    assert 185 <= sc.layout.width_m <= 195 and 145 <= sc.layout.height_m <= 155
    ll = sc.satmap.frame.to_lonlat(np.array([sc.layout.width_m / 2, sc.layout.height_m / 2]))
    x, y = pyproj.Transformer.from_crs("EPSG:4326", UTM, always_xy=True).transform(*ll)
    assert abs(x - (E0 + 80)) < 3 and abs(y - (N0 + 60)) < 3
    assert len(sc.layout.buildings) == 3 and all(not b.roof_from_ground for b in sc.layout.buildings)
    assert len(sc.layout.trees) == 1
    # the map is a capture of the painted world, not its copy; at gap 0 it is the painted tile
    assert sc.satmap.image.shape[:2] == (lab.shape[0] // 2, lab.shape[1] // 2)
    (tmp_path / "b").mkdir()
    copy = load_scene(_vector_scene(tmp_path / "b"), satellite_gap=0.0)
    assert np.abs(copy.satmap.image.astype(int) - sc.satmap.image.astype(int)).mean() > 3
    route = sc.routes["main"]
    assert route.length > 140 and np.isin(lab, DRIVABLE).any()     # the main street, end to end
    env = gym.make("satloc/SatLoc-v0", scene=str(tmp_path / "v.yaml"), localizer=None)
    obs, _ = env.reset(seed=0)
    for _ in range(5):
        obs, _, terminated, _, _ = env.step(env.unwrapped.autopilot_action())
    assert obs["left"].std() > 5 and not terminated
    env.close()


def test_a_vector_world_refuses_bad_fields(tmp_path):
    from satloc import ConfigError

    with pytest.raises(ConfigError, match=r"generator\.type: expected 'grid', 'image' or 'vectors'"):
        p = tmp_path / "x.yaml"
        p.write_text(yaml.safe_dump({"name": "x", "generator": {"type": "osm", "roads": "map.osm"}}))
        load_scene(p)
    with pytest.raises(ConfigError, match="sidewalk_m"):
        load_scene(_vector_scene(tmp_path, sidewalk_m=-1))
    (tmp_path / "r").mkdir()
    with pytest.raises(ConfigError, match=r"generator\.region"):
        load_scene(_vector_scene(tmp_path / "r", region=[11.0, 48.0, 10.0, 49.0]))


def test_shipped_osm_town_is_made_by_its_tool_and_drives(tmp_path):
    """scenes/osm_town.osm is what scenes/tools/make_osm_town.py writes (byte for byte: its provenance), and
    the vector world made of it alone is driven end to end: every road covered (the roads the extract cuts
    end in turning bulbs), one-way streets their way, both routes drivable (gym.make checks them)."""
    import subprocess
    import sys

    import gymnasium as gym

    from satloc_env.world.roadgraph import allowed, covering_tour
    from satloc_env.world.scene import DRIVABLE, SCENES_DIR

    subprocess.run([sys.executable, str(SCENES_DIR / "tools" / "make_osm_town.py"), str(tmp_path / "t.osm")],
                   check=True)
    assert (tmp_path / "t.osm").read_bytes() == (SCENES_DIR / "osm_town.osm").read_bytes()
    sc = load_scene("osm_town")
    summary = sc.summary()
    assert summary["tour"]["coverage"] == 1.0 and summary["footprints"]["dropped"] == 0
    assert summary["buildings"] > 60 and summary["trees"] > 100
    g = sc.road_graph.graph
    main, _ = covering_tour(sc.road_graph, np.isin(sc.layout.ground_labels, DRIVABLE), sc.layout.ground_mpp,
                            sc.spec.road_graph)
    assert all(allowed(g, u, v, k) for u, v, k in main.steps)
    env = gym.make("satloc/SatLoc-v0", scene="osm_town", localizer=None)
    env.reset(seed=0, options={"route": "revisit"})
    env.close()


@pytest.mark.parametrize("roof", ["flat", "gabled"])
def test_building_bases_and_gabled_roofs_in_3d(roof):
    """A building part from min_height up, under a flat roof or a gabled one whose ridge runs along the long
    axis at its height; its walls up to the eaves."""
    from satloc_env.world.layout import Building, Layout
    from satloc_env.world.meshes import build_world

    fp = np.array([[10.0, 10.0], [22.0, 10.0], [22.0, 18.0], [10.0, 18.0]])
    lay = Layout(40.0, 30.0, 0.5, np.full((60, 80, 3), 90, np.uint8), np.zeros((60, 80), np.uint8),
                 [Building(fp, 9.0, 1, base=2.0, roof=roof)], [], [])
    w = build_world(lay)
    pos = np.vstack([c.positions for c in w.chunks]).astype(np.float64)
    above = pos[pos[:, 2] > 1e-3]
    assert above[:, 2].min() == pytest.approx(2.0) and above[:, 2].max() == pytest.approx(9.0)
    top = above[np.isclose(above[:, 2], 9.0)][:, :2]
    if roof == "flat":   # the roof's corners (and the walls' splits along its edges)
        ring = shapely.LinearRing(fp)
        assert {tuple(p) for p in fp} <= {tuple(p) for p in np.round(top, 3)}
        assert all(ring.distance(shapely.Point(p)) < 1e-6 for p in top)
    else:   # the ridge: the short sides' midpoints; the eaves at 9 - 0.4 x 8 m
        assert {tuple(p) for p in np.round(top, 3)} == {(10.0, 14.0), (22.0, 14.0)}
        assert np.isclose(above[:, 2], 9.0 - 3.2).any()


def test_a_scene_keeps_bases_and_roofs_through_save_and_load(tmp_path):
    from satloc_env.world.scene import Scene

    sc = _scene(tmp_path, {"roads": "map.osm", "buildings": "map.osm"})
    house = [b for b in sc.layout.buildings if b.roof == "gabled"]
    assert len(house) == 1 and house[0].base == 3.0
    sc.save(tmp_path / "saved")
    back = Scene.load(tmp_path / "saved")
    assert [(b.base, b.roof) for b in back.layout.buildings] == [(b.base, b.roof) for b in sc.layout.buildings]


def test_a_one_way_roundabout_with_spokes_is_driven_round():
    """A closed one-way ring (a roundabout, drawn counter-clockwise from its east point) with four two-way
    spokes: every ring piece keeps the drawn direction, even the one ending at the ring's closing point, so
    the whole network is one strongly connected part and the tour covers it."""
    import networkx as nx

    from satloc_env.world.roadgraph import allowed, arc_graph, covering_tour

    ang = np.linspace(0.0, 2 * np.pi, 33)
    ring = np.stack([100 + 15 * np.cos(ang), 100 + 15 * np.sin(ang)], 1)
    ring[-1] = ring[0]
    spokes = [np.array([(115.0, 100.0), (190.0, 100.0)]), np.array([(100.0, 115.0), (100.0, 190.0)]),
              np.array([(85.0, 100.0), (10.0, 100.0)]), np.array([(100.0, 85.0), (100.0, 10.0)])]
    rg = graph_from_lines([ring, *spokes], [7.0] * 5, 200, 200, GraphParams(), oneway=[1, 0, 0, 0, 0])
    g = rg.graph
    for u, v, k, d in g.edges(keys=True, data=True):
        if d["oneway"]:   # counter-clockwise: the cross product of (start - centre) and (end - centre) > 0
            a, b = d["xy"][0] - 100, d["xy"][-1] - 100
            assert a[0] * b[1] - a[1] * b[0] > 0
    assert nx.is_strongly_connected(arc_graph(g))
    main, _ = covering_tour(rg, None, 0.5, GraphParams())
    # no dead end can be turned in (no drivable raster): the tour runs from one spoke's end round the ring to
    # another's, and the other two spokes are left out
    assert main.covered_m == pytest.approx(rg.length_m - 2 * 75.0, abs=1.0)
    ring_edges = {(u, v, k) for u, v, k, d in g.edges(keys=True, data=True) if d["oneway"]}
    assert ring_edges <= {(u, v, k) for u, v, k in main.steps} | {(v, u, k) for u, v, k in main.steps}
    assert all(allowed(g, u, v, k) for u, v, k in main.steps)


def test_one_dead_end_it_cannot_turn_in_beside_one_way_streets():
    """A one-way block with one two-way spur ending where the car cannot turn: the tour starts there, drives
    everything and ends there (it failed with no feasible flow)."""
    from satloc_env.world.roadgraph import covering_tour

    block = np.array([(50.0, 50.0), (150.0, 50.0), (150.0, 150.0), (50.0, 150.0), (50.0, 50.0)])
    spur = np.array([(150.0, 100.0), (190.0, 100.0)])
    rg = graph_from_lines([block, spur], [7.0, 7.0], 200, 200, GraphParams(), oneway=[1, 0])
    main, revisit = covering_tour(rg, None, 0.5, GraphParams())
    assert not main.closed and main.coverage == pytest.approx(1.0)
    end = [n for n in rg.graph.nodes if rg.graph.degree(n) == 1][0]
    assert main.steps[0][0] == end and main.steps[-1][1] == end
    assert sum(1 for u, v, k in main.steps if end in (u, v)) == 2      # out once, back once


def test_a_ramp_ending_on_another_layer_joins_it_at_its_vertex():
    import networkx as nx

    street = np.array([(10.0, 100.0), (100.0, 100.0), (190.0, 100.0)])
    ramp = np.array([(100.0, 20.0), (100.0, 100.0)])
    rg = graph_from_lines([street, ramp], [7.0, 7.0], 200, 200, GraphParams(), layers=[0, 1])
    assert nx.is_connected(rg.graph) and sorted(dict(rg.graph.degree()).values()) == [1, 1, 1, 3]


def test_numeric_oneway_and_layer_fields_and_ambiguous_lengths():
    assert road_oneway({"oneway": -1.0}) == -1 and road_oneway({"oneway": 1}) == 1
    assert road_layer({"layer": 1.0}) == 1 and road_layer({"layer": float("nan"), "bridge": "yes"}) == 1
    assert parse_length("1,000") is None and parse_length("12,5 m") == 12.5


def test_an_integer_surface_model_with_nodata(tmp_path):
    import rasterio
    from affine import Affine

    from satloc.geodata.heights import HeightRaster

    z = np.full((100, 100), 300, np.int16)
    z[40:60, 40:60] = 312
    z[:5, :5] = -32768
    with rasterio.open(tmp_path / "dsm.tif", "w", driver="GTiff", width=100, height=100, count=1, dtype="int16",
                       crs=UTM, transform=Affine(1, 0, E0, 0, -1, N0 + 100), nodata=-32768) as ds:
        ds.write(z, 1)
    hr = HeightRaster(tmp_path / "dsm.tif", UTM)
    house = shapely.box(E0 + 42, N0 + 42, E0 + 58, N0 + 58)
    assert hr.height(house) == pytest.approx(12.0)


def test_building_parts_replace_their_outline(tmp_path):
    """An OSM building drawn as an outline and two building:part ways (GDAL's OSM driver files those as closed
    lines): the parts are the footprints, with their own heights, bases and roofs; the outline gives way."""
    parts = {1: (0.0, 0.0), 2: (30.0, 0.0), 3: (30.0, 20.0), 4: (0.0, 20.0), 5: (15.0, 0.0), 6: (15.0, 20.0)}
    ways = [([1, 2, 3, 4, 1], {"building": "yes", "height": "20"}),
            ([1, 5, 6, 4, 1], {"building:part": "yes", "height": "20"}),
            ([5, 2, 3, 6, 5], {"building:part": "yes", "height": "12", "min_height": "3", "roof:shape": "gabled"}),
            ([1, 2], {"highway": "residential"})]
    (tmp_path / "parts.osm").write_text(osm_xml(parts, ways))
    fp = read_footprints(tmp_path / "parts.osm")
    assert sorted(zip(fp.heights, fp.bases, fp.roofs)) == [(12.0, 3.0, "gabled"), (20.0, 0.0, "flat")]
    # without parts the outline stands
    (tmp_path / "one.osm").write_text(osm_xml(parts, [ways[0], ways[3]]))
    assert read_footprints(tmp_path / "one.osm").heights == [20.0]


def _with_bounds(xml: str, sw, ne) -> str:
    """The export with a ``<bounds>`` element (as osmconvert, Osmosis and the OSM API write) for the UTM box
    from ``sw`` to ``ne`` (metres east / north of (E0, N0))."""
    lon0, lat0 = TO_LONLAT.transform(E0 + sw[0], N0 + sw[1])
    lon1, lat1 = TO_LONLAT.transform(E0 + ne[0], N0 + ne[1])
    b = f'  <bounds minlat="{lat0:.7f}" minlon="{lon0:.7f}" maxlat="{lat1:.7f}" maxlon="{lon1:.7f}"/>\n'
    head, rest = xml.split("\n", 2)[:2], xml.split("\n", 2)[2]
    return "\n".join(head) + "\n" + b + rest


def test_an_extract_is_the_area_it_declares(tmp_path):
    """A vectors world over an OSM XML extract covers the extract's declared <bounds>, not the extent of its
    ways, which run on past them to their last node (here 25 to 30 m past every side): the roads are cut at
    the edge and end in turning bulbs inside the area."""
    from satloc.geodata.vectors import declared_bounds

    (tmp_path / "map.osm").write_text(_with_bounds(osm_xml(), (30.0, 30.0), (130.0, 90.0)))
    b = declared_bounds(tmp_path / "map.osm")
    assert b is not None and b[0] < b[2] and b[1] < b[3]
    assert declared_bounds(tmp_path / "v.yaml") is None
    (tmp_path / "plain").mkdir()
    (tmp_path / "plain" / "map.osm").write_text(osm_xml())
    assert declared_bounds(tmp_path / "plain" / "map.osm") is None
    p = tmp_path / "v.yaml"
    p.write_text(yaml.safe_dump({"name": "bounded", "seed": 3, "generator": {
        "type": "vectors", "roads": "map.osm", "buildings": "map.osm", "trees": "map.osm"},
        "meters_per_pixel": 0.5, "ground_mpp": 0.25}))
    with pytest.warns(SatlocWarning):
        sc = load_scene(p)
    # 100 m x 60 m of UTM, give or take the grid convergence between UTM north and true north
    assert 97 <= sc.layout.width_m <= 103 and 57 <= sc.layout.height_m <= 63
    from satloc_env.envs.drivecheck import first_off_road
    assert first_off_road(sc, "main", -1.75) is None


def test_an_extract_without_trees_has_none_and_says_so(tmp_path):
    xml = osm_xml().replace('<tag k="natural" v="tree"/>', "")
    (tmp_path / "map.osm").write_text(xml)
    with pytest.warns(SatlocWarning, match="holds no trees"):
        t = read_trees(tmp_path / "map.osm")
    assert len(t.points) == 0 and not t.canopies


def test_a_world_too_large_for_the_memory_is_refused_before_it_is_built(tmp_path, monkeypatch):
    from satloc import ConfigError
    from satloc_env.world import scene as scene_mod

    monkeypatch.setattr(scene_mod, "_available_memory", lambda: 20_000_000)   # 0.02 GB: the scene needs about 0.07
    with pytest.raises(ConfigError, match=r"needs about .* GB to build, more than the 0\.0 GB available.*"
                                          r"generator\.region"):
        load_scene(_vector_scene(tmp_path))


def test_a_road_cut_along_the_edge_gets_its_bulb_inside_the_area():
    """A road that meets the area's edge at a glancing angle: the turning bulb moves back along it until the
    whole disc lies inside (it would stick out centred one radius back from the cut)."""
    from satloc_env.world.vector_world import _turn_bulbs

    w, h = 200.0, 100.0
    # along the south edge, 3 m inside it, to its cut end at the east edge (2 m in, the graph's margin)
    g = graph_from_lines([np.array([[20.0, 50.0], [60.0, 3.0], [198.0, 3.0]])], [7.0], w, h)
    disc = _turn_bulbs(g, w, h, 3.0, 12.0)
    assert disc is not None
    x0, y0, x1, y1 = disc.bounds
    assert x0 >= 0.5 and y0 >= 0.5 and x1 <= w - 0.5 and y1 <= h - 0.5, disc.bounds


def test_an_undrivable_derived_route_says_what_to_change(tmp_path):
    """A route the user drew is to be moved; a derived one has a turn the car cannot follow, and the user can
    change the area or give routes: the message says which."""
    from satloc_env.envs.drivecheck import off_road_message

    (tmp_path / "a").mkdir()
    with pytest.warns(SatlocWarning):
        sc = load_scene(_vector_scene(tmp_path / "a"))
    msg = off_road_message(sc, "main", -1.75, np.array([10.0, 10.0]), 5.0)
    assert "derived from the road graph" in msg and "generator.region" in msg
    drawn = load_scene("city")
    assert "move the route onto the road there" in off_road_message(drawn, "main", -1.75, np.array([1.0, 1.0]), 1.0)


@pytest.mark.parametrize("header, box", [
    ('<bound box="48.1,10.0,48.2,10.1" origin="osmosis"/>', (10.0, 48.1, 10.1, 48.2)),          # Osmosis
    ('<bounds minlat="0.49" minlon="0.49" maxlat="0.5" maxlon="0.5"/>\n'                          # JOSM: one per
     '<bounds minlon=\'0.49\' maxlat=\'0.5012\' minlat=\'0.5\' maxlon=\'0.5\'/>', (0.49, 0.49, 0.5, 0.5012)),  # area
    ("<!-- " + "x" * 100_000 + ' -->\n<bounds minlat="1" minlon="2" maxlat="1.1" maxlon="2.1"/>', (2.0, 1.0, 2.1, 1.1)),
    ('<bounds minlat="-90" minlon="-180" maxlat="90" maxlon="180"/>', None),   # beyond the map projection's reach
    ("", None),
])
def test_declared_bounds_as_the_tools_write_them(tmp_path, header, box):
    from satloc.geodata.vectors import declared_bounds

    p = tmp_path / "x.osm"
    p.write_text(f'<?xml version="1.0"?>\n<osm version="0.6">\n{header}\n<node id="1" lat="1" lon="2"/>\n</osm>\n')
    got = declared_bounds(p)
    assert got == (None if box is None else pytest.approx(box))


def test_a_saved_scene_keeps_its_tour_and_its_world_beyond_the_edge(tmp_path):
    import json

    from satloc_env.world.scene import Scene

    (tmp_path / "a").mkdir()
    with pytest.warns(SatlocWarning):
        sc = load_scene(_vector_scene(tmp_path / "a"))
    sc.save(tmp_path / "saved")
    back = Scene.load(tmp_path / "saved")
    assert back.tour == sc.tour and back.tour is not None and back.spec.beyond_edge == "mirror"
    # a scene saved before ground_beyond existed was rendered with neutral ground: it stays so
    sj = tmp_path / "saved" / "scene.json"
    meta = json.loads(sj.read_text())
    del meta["spec"]["ground_beyond"]
    sj.write_text(json.dumps(meta))
    assert Scene.load(tmp_path / "saved").spec.beyond_edge == "neutral"
