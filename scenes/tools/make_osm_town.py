"""Write ``scenes/osm_town.osm``: a small fictional town as an OpenStreetMap XML extract, made by the project
(MIT, like the rest of it) so that a vector world ships without third-party map data.

    python scenes/tools/make_osm_town.py scenes/osm_town.osm

Deterministic (seeded): ``tests/test_osm.py`` checks that it writes the shipped file byte for byte. The town
lies near lon 0.5, lat 0.5 (open sea: it is nowhere) and covers about 330 m x 270 m: a main street with two
lanes, side streets, a curved lane, a diagonal avenue, a one-way pair, a cul-de-sac ending in a one-way
turning circle, a footway and a railway (neither a road for cars), buildings along the streets (levels or
heights, some with gabled roofs), street trees and a small wood.
"""
from __future__ import annotations

import math
import sys

import numpy as np

LON0, LAT0 = 0.5, 0.5
M_LAT = 111_320.0
M_LON = M_LAT * math.cos(math.radians(LAT0))


def _mx(y: float) -> float:
    """x of the curved lane (Muehlweg) at y: bowing west south of the main street, east north of it."""
    if y <= 120.0:
        return round(230.0 - 8.0 * math.sin(math.pi * y / 120.0), 2)
    return round(230.0 + 10.0 * math.sin(math.pi * (y - 120.0) / 150.0), 2)


def town() -> tuple[list, list, list]:
    """(ways: [(points (N, 2) metres, tags)], areas: [(ring (N, 2), tags)], trees: [((x, y), tags)])."""
    import shapely

    rng = np.random.default_rng(7)
    south = [0.0, 15.0, 30.0, 50.0, 65.0, 80.0, 95.0, 108.0, 120.0]
    north = [120.0, 133.0, 146.0, 160.0, 180.0, 200.0, 220.0, 245.0, 270.0]
    ways = [
        (np.array([(0, 120), (100, 120), (230, 120), (330, 120)], float),
         {"highway": "secondary", "name": "Hauptstrasse", "lanes": "2", "width": "9"}),
        (np.array([(100, 0), (100, 50), (100, 120)], float), {"highway": "residential", "name": "Bahnhofstrasse"}),
        (np.array([(100, 120), (100, 160), (100, 200), (100, 270)], float),
         {"highway": "residential", "name": "Bahnhofstrasse"}),
        (np.array([(_mx(y), y) for y in south]), {"highway": "residential", "name": "Muehlweg"}),
        (np.array([(_mx(y), y) for y in north]), {"highway": "residential", "name": "Muehlweg"}),
        (np.array([(0, 50), (100, 50), (_mx(50.0), 50)], float), {"highway": "residential", "name": "Gartenweg"}),
        (np.array([(55, 120), (25, 165), (0, 205)], float),
         {"highway": "tertiary", "name": "Allee", "width": "8"}),
        (np.array([(100, 200), (160, 200), (_mx(200.0), 200)], float),
         {"highway": "residential", "name": "Kirchgasse", "oneway": "yes", "width": "6"}),
        (np.array([(_mx(160.0), 160), (160, 160), (100, 160)], float),
         {"highway": "residential", "name": "Schulgasse", "oneway": "yes", "width": "6"}),
        (np.array([(_mx(80.0), 80), (290, 80)], float), {"highway": "residential", "name": "Sackgasse", "width": "8"}),
        (np.array([(130, 20), (200, 20)], float), {"highway": "footway"}),
        (np.array([(320, 0), (320, 270)], float), {"railway": "rail"}),
    ]
    # the cul-de-sac's turning circle: a one-way ring, as OSM maps them
    ang = np.linspace(math.pi, -math.pi, 25)
    ring = np.stack([299.0 + 9.0 * np.cos(ang), 80.0 + 9.0 * np.sin(ang)], 1)
    ring[-1] = ring[0]
    ways.append((ring, {"highway": "residential", "junction": "circular", "oneway": "yes", "width": "6"}))
    roads = shapely.union_all([shapely.LineString(p).buffer(6.0) for p, t in ways if "highway" in t
                               and t["highway"] != "footway"] + [shapely.LineString(ring).buffer(7.5)])
    wood = np.array([(130, 60), (200, 62), (205, 108), (135, 106), (130, 60)], float)
    # buildings: along each street's sides, set back from the road, where they fit (not in the wood)
    areas, placed = [], [shapely.Polygon(wood)]
    for p, t in ways:
        if t.get("highway") not in ("secondary", "residential", "tertiary") or t.get("junction"):
            continue
        line = shapely.LineString(p)
        s = 6.0
        while s < line.length - 10:
            front = float(rng.uniform(10, 16))
            depth = float(rng.uniform(9, 14))
            a, b = line.interpolate(s), line.interpolate(min(s + front, line.length))
            d = np.array([b.x - a.x, b.y - a.y])
            if np.linalg.norm(d) < 5:
                break
            d /= np.linalg.norm(d)
            nrm = np.array([-d[1], d[0]])
            for side in (1, -1):
                back = float(t.get("width", 7)) / 2 + 2.0 + 4.0 + float(rng.uniform(0, 2))
                o = np.array([a.x, a.y]) + side * nrm * back
                poly = shapely.Polygon([o, o + d * front, o + d * front + side * nrm * depth,
                                        o + side * nrm * depth])
                if poly.intersects(roads) or any(poly.buffer(1.5).intersects(q) for q in placed):
                    continue
                if not shapely.box(2, 2, 328, 268).contains(poly):
                    continue
                placed.append(poly)
                tags = {"building": str(rng.choice(["house", "apartments", "yes", "retail"]))}
                if rng.random() < 0.6:
                    tags["building:levels"] = str(int(rng.integers(2, 6)))
                else:
                    tags["height"] = f"{rng.uniform(6, 16):.1f}"
                if rng.random() < 0.4:
                    tags["roof:shape"] = "gabled"
                ring_xy = np.asarray(poly.exterior.coords)
                if not shapely.LinearRing(ring_xy).is_ccw:
                    ring_xy = ring_xy[::-1]
                areas.append((ring_xy, tags))
            s += front + float(rng.uniform(3, 7))
    areas.append((wood, {"natural": "wood"}))
    trees = [((float(x), 112.0), {"natural": "tree", "height": f"{rng.uniform(7, 12):.1f}"})
             for x in range(10, 95, 15)]
    trees += [((float(x), 128.0), {"natural": "tree"}) for x in range(112, 225, 18)]
    return ways, areas, trees


def write(path: str) -> None:
    ways, areas, trees = town()
    nodes: dict[tuple[float, float], int] = {}
    out_ways = []

    def node(x: float, y: float) -> int:
        key = (round(x, 2), round(y, 2))
        if key not in nodes:
            nodes[key] = len(nodes) + 1
        return nodes[key]

    for p, t in [*ways, *areas]:
        refs = [node(x, y) for x, y in p]
        out_ways.append((refs, t))
    tree_nodes = [(node(*xy), t) for xy, t in trees]
    tagged = dict(tree_nodes)
    with open(path, "w", newline="\n") as f:
        f.write('<?xml version="1.0" encoding="UTF-8"?>\n')
        f.write('<osm version="0.6" generator="satloc scenes/tools/make_osm_town.py">\n')
        for (x, y), i in nodes.items():
            lat, lon = LAT0 + y / M_LAT, LON0 + x / M_LON
            tags = "".join(f'<tag k="{k}" v="{v}"/>' for k, v in tagged.get(i, {}).items())
            f.write(f'  <node id="{i}" lat="{lat:.8f}" lon="{lon:.8f}">{tags}</node>\n')
        for w, (refs, t) in enumerate(out_ways):
            nds = "".join(f'<nd ref="{r}"/>' for r in refs)
            tags = "".join(f'<tag k="{k}" v="{v}"/>' for k, v in t.items())
            f.write(f'  <way id="{w + 1}">{nds}{tags}</way>\n')
        f.write("</osm>\n")


if __name__ == "__main__":
    write(sys.argv[1] if len(sys.argv) > 1 else "osm_town.osm")
