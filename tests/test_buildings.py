"""3-D objects from map vectors: building footprints and trees (satloc.geodata.vectors, satloc_env.world.scene_buildings).

The imagery and the vectors are made here, in tmp_path, as in test_roads.py: a GeoTIFF in UTM zone 32N near
lon 8.43, lat 49.01 (160 m x 120 m at 0.5 m per pixel), road centre lines in CRS84 GeoJSON, and footprints
and trees written with pyogrio in three CRSs.
"""
from __future__ import annotations

import warnings

import numpy as np
import pyproj
import pytest
import shapely
import yaml
from test_roads import E0, N0, RES, UTM, image, local, plain_image_scene, write_vectors

from satloc import ConfigError, SatlocWarning
from satloc.geodata.vectors import LEVEL_HEIGHT_M, building_height, read_footprints, read_trees
from satloc.labels import CLASS_ID
from satloc_env.world.scene import Scene, load_scene

# footprints in metres east / north of (E0, N0): beside the main road (y about 60, 8 m wide), a courtyard
# block, one straddling the tile's east edge (x = 160), one on the road, and one tagged building=no
HOUSE_A = [(70.0, 68.0), (82.0, 68.0), (82.0, 78.0), (70.0, 78.0)]
HOUSE_B = [(110.0, 66.0), (122.0, 66.0), (122.0, 76.0), (110.0, 76.0)]
BLOCK = [(20.0, 75.0), (45.0, 75.0), (45.0, 100.0), (20.0, 100.0)]
BLOCK_HOLE = [(28.0, 83.0), (37.0, 83.0), (37.0, 92.0), (28.0, 92.0)]
EDGE = [(150.0, 70.0), (170.0, 70.0), (170.0, 80.0), (150.0, 80.0)]
ON_ROAD = [(130.0, 55.0), (138.0, 55.0), (138.0, 65.0), (130.0, 65.0)]
NOT_A_BUILDING = [(120.0, 90.0), (130.0, 90.0), (130.0, 100.0), (120.0, 100.0)]
FOOTPRINTS = [
    ([HOUSE_A], {"building": "house", "height": "12 m", "building:levels": None}),
    ([HOUSE_B], {"building": "yes", "height": None, "building:levels": "4"}),
    ([BLOCK, BLOCK_HOLE], {"building": "apartments", "height": None, "building:levels": None}),
    ([EDGE], {"building": "yes", "height": "9", "building:levels": None}),
    ([ON_ROAD], {"building": "yes", "height": "6", "building:levels": None}),
    ([NOT_A_BUILDING], {"building": "no", "height": "6", "building:levels": None}),
]
# trees: two single ones (one with its height and crown, one on the road) and a canopy area
TREE_POINTS = [((90.0, 75.0), {"height": "10", "diameter_crown": "6"}), ((40.0, 61.0), {"height": None,
                                                                                       "diameter_crown": None})]
WOOD = [(120.0, 5.0), (150.0, 5.0), (150.0, 20.0), (120.0, 20.0)]


def _to(crs):
    return pyproj.Transformer.from_crs(UTM, crs or "OGC:CRS84", always_xy=True)


def _geom(rings, crs):
    to = _to(crs)
    out = []
    for r in rings:
        xy = np.asarray(r) + [E0, N0]
        x, y = to.transform(xy[:, 0], xy[:, 1])
        out.append(np.stack([x, y], 1))
    return shapely.Polygon(out[0], out[1:])


def write_footprints(path, crs, driver=None, features=FOOTPRINTS):
    from pyogrio.raw import write

    names = ["building", "height", "building:levels"] if driver != "ESRI Shapefile" else \
        ["building", "height", "building_l"]
    geoms = np.array([shapely.to_wkb(_geom(rings, crs)) for rings, _ in features], dtype=object)
    cols = [np.array([a[k] for _, a in features], dtype=object) for k in ("building", "height", "building:levels")]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        write(str(path), geoms, cols, names, driver=driver, crs=crs, geometry_type="Polygon")
    return path


def write_trees(path, crs=None):
    from pyogrio.raw import write

    to = _to(crs)
    geoms = []
    for (x, y), _ in TREE_POINTS:
        geoms.append(shapely.to_wkb(shapely.Point(*to.transform(E0 + x, N0 + y))))
    geoms.append(shapely.to_wkb(_geom([WOOD], crs)))
    attrs = [a for _, a in TREE_POINTS] + [{"height": "15", "diameter_crown": None}]
    cols = [np.array([a[k] for a in attrs], dtype=object) for k in ("height", "diameter_crown")]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        write(str(path), np.array(geoms, dtype=object), cols, ["height", "diameter_crown"], crs=crs,
              driver="GeoJSON", geometry_type="Unknown")
    return path


def write_scene(d, name="b.yaml", **gen):
    g = {"type": "image", "image": image(d), "roads": "roads.geojson", **gen}
    p = d / name
    p.write_text(yaml.safe_dump({"name": "buildings", "seed": 5, "generator": g, "meters_per_pixel": RES,
                                 "ground_mpp": RES}))
    return p


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("buildings")
    write_vectors(d / "roads.geojson", None)
    write_footprints(d / "buildings.geojson", None)
    write_trees(d / "trees.geojson")
    return d


@pytest.fixture(scope="module")
def scene(scene_dir):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sc = load_scene(write_scene(scene_dir, buildings="buildings.geojson", trees="trees.geojson"))
    sc.caught = [str(w.message) for w in caught if issubclass(w.category, SatlocWarning)]
    return sc


def _centroid(scene, ring) -> np.ndarray:
    return local(scene, np.asarray(ring).mean(0))


def _building_at(scene, ring):
    c = _centroid(scene, ring)
    for b in scene.layout.buildings:
        if shapely.Polygon(b.footprint).contains(shapely.Point(*c)):
            return b
    return None


# --- reading ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("fmt, crs, driver", [("geojson", None, None), ("gpkg", UTM, "GPKG"),
                                              ("shp", "EPSG:3857", "ESRI Shapefile")])
def test_footprints_in_three_crss(tmp_path, fmt, crs, driver):
    fp = read_footprints(write_footprints(tmp_path / f"b.{fmt}", crs, driver))
    assert len(fp.rings) == 5                              # building=no left out
    assert fp.heights == [12.0, 4 * LEVEL_HEIGHT_M, None, 9.0, 6.0]
    to_utm = pyproj.Transformer.from_crs(fp.crs, UTM, always_xy=True)
    x, y = to_utm.transform(fp.rings[0][:, 0], fp.rings[0][:, 1])
    got = np.stack([x, y], 1) - [E0, N0]
    # the same corners back in metres (a ring may start elsewhere or run the other way)
    assert shapely.Polygon(got).symmetric_difference(shapely.Polygon(HOUSE_A)).area < 1e-3
    # the courtyard is filled: the exterior ring only
    x, y = to_utm.transform(fp.rings[2][:, 0], fp.rings[2][:, 1])
    assert abs(shapely.Polygon(np.stack([x, y], 1)).area - 25 * 25) < 0.1


def test_building_height_attributes():
    assert building_height({"height": "7.5 m"}) == 7.5
    assert building_height({"building:height": 20}) == 20.0
    assert building_height({"building:levels": "3;4"}) == 3 * LEVEL_HEIGHT_M
    assert building_height({"height": "tall", "building:levels": "2"}) == 2 * LEVEL_HEIGHT_M
    assert building_height({"height": -4}) is None and building_height({}) is None


def test_trees_read_points_and_canopies(scene_dir):
    t = read_trees(scene_dir / "trees.geojson")
    assert len(t.points) == 2 and len(t.canopies) == 1
    assert t.point_heights == [10.0, None] and t.point_radii == [3.0, None] and t.canopy_heights == [15.0]


def test_vector_object_errors(tmp_path, scene_dir):
    roads = write_vectors(tmp_path / "lines.geojson", None)
    with pytest.raises(Exception, match="lines.geojson: holds no Polygon"):
        read_footprints(roads)
    with pytest.raises(Exception, match="lines.geojson: holds no Point or Polygon"):
        read_trees(roads)
    write_vectors(tmp_path / "roads.geojson", None)
    (tmp_path / "b.txt").write_text("x")
    for gen, msg in [({"buildings": "missing.geojson"}, r"generator.buildings: vector file .*missing.geojson not found"),
                     ({"buildings": "b.txt"}, r"generator.buildings: .*b.txt is not a vector file"),
                     ({"buildings": "lines.geojson"}, r"generator.buildings: .*lines.geojson: holds no Polygon"),
                     ({"trees": "lines.geojson"}, r"generator.trees: .*lines.geojson: holds no Point or Polygon"),
                     ({"building_height_m": [9, 3]}, r"building_height_m: expected \[low, high\]")]:
        with pytest.raises(ConfigError, match=msg):
            load_scene(write_scene(tmp_path, name=f"e{len(msg)}.yaml", **gen))


def test_vector_objects_need_a_georeferenced_image(tmp_path):
    write_footprints(tmp_path / "b.geojson", None)
    p = plain_image_scene(tmp_path, {"buildings": "b.geojson"}, routes={"main": {"waypoints": [[5, 20], [45, 20]]}})
    with pytest.raises(ConfigError, match="generator.buildings: .*not georeferenced"):
        load_scene(p)


# --- the scene -------------------------------------------------------------------------------------------------
def test_footprints_become_buildings_on_the_tile(scene):
    b = scene.layout.buildings
    assert len(b) == 4                                     # the one on the road is left out, with a warning
    assert any("of 5 footprints, 1 overlap the road: 1 left out, less than 25% of them off the road (features 4)"
               in m for m in scene.caught)
    assert scene.summary()["footprints"] == {"read": 5, "kept": 4, "trimmed": 0, "repaired": 0, "dropped": 1,
                                             "outside_tile": 0}
    assert all(x.roof_from_ground for x in b)
    assert _building_at(scene, HOUSE_A).height == 12.0
    assert _building_at(scene, HOUSE_B).height == 4 * LEVEL_HEIGHT_M
    lo, hi = 5.0, 9.0                                      # generator.building_height_m's default
    assert lo <= _building_at(scene, BLOCK).height <= hi
    assert _building_at(scene, ON_ROAD) is None
    # clipped at the tile's east edge
    edge = _building_at(scene, [(152.0, 75.0)])
    assert edge is not None and edge.footprint[:, 0].max() <= scene.layout.width_m + 1e-6
    assert abs(shapely.Polygon(edge.footprint).area - 10 * (scene.layout.width_m - local(scene, [150.0, 75.0])[0])) < 2
    # labels: building under the footprints (off the road), on the ground and on the tile's label image
    lab = scene.satmap.labels
    assert lab is not None and (lab == CLASS_ID["building"]).sum() * RES ** 2 > 0.9 * (144 + 120 + 625)
    for ring in (HOUSE_A, HOUSE_B, BLOCK):
        assert scene.ground_label(_centroid(scene, ring)) == CLASS_ID["building"]
    assert scene.ground_label(_centroid(scene, ON_ROAD)) in (CLASS_ID["road"], CLASS_ID["lane_marking"])


def test_heights_are_seeded_and_the_same_on_every_load(scene_dir, scene):
    from satloc_env.world.scene import build_scene, load_spec

    spec, base = load_spec(write_scene(scene_dir, buildings="buildings.geojson", trees="trees.geojson"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SatlocWarning)
        again = build_scene(spec, base)
        other = build_scene(type(spec)(**{**spec.__dict__, "seed": 6}), base)
    h = [x.height for x in scene.layout.buildings]
    assert [x.height for x in again.layout.buildings] == h
    assert [x.height for x in other.layout.buildings] != h          # the drawn one changes with the seed
    assert [x.facade for x in again.layout.buildings] == [x.facade for x in scene.layout.buildings]


def test_trees_from_points_and_canopy_areas(scene):
    t = scene.layout.trees
    single = [x for x in t if np.hypot(*(np.array(x.center) - _centroid(scene, [(90.0, 75.0)]))) < 0.1]
    assert len(single) == 1 and single[0].canopy_top == 10.0 and single[0].canopy_radius == 3.0
    wood = shapely.Polygon([local(scene, p) for p in WOOD])
    in_wood = [x for x in t if wood.buffer(1.3).contains(shapely.Point(x.center))]
    assert 8 <= len(in_wood) <= 16 and all(x.canopy_top == 15.0 for x in in_wood)   # 450 m^2 at 6 m spacing
    assert len(t) == 1 + len(in_wood)                      # the tree on the road is left out, with a warning
    assert any("1 trees stand on the road and were left out" in m for m in scene.caught)
    assert scene.ground_label(_centroid(scene, [(90.0, 75.0)])) == CLASS_ID["tree"]


def test_saved_scene_keeps_roofs_from_the_imagery(scene, tmp_path):
    scene.save(tmp_path / "saved")
    back = Scene.load(tmp_path / "saved")
    assert [b.roof_from_ground for b in back.layout.buildings] == [True] * 4
    assert [b.height for b in back.layout.buildings] == [b.height for b in scene.layout.buildings]


def test_extruded_buildings_and_trees_appear_in_the_label_and_depth_images(scene):
    """The camera on the main road looks north at HOUSE_A's south wall, 7 m off the road's centre line, then
    at the tree; labels and depth show them standing, where the flat world has ground."""
    from satloc.geometry import Pose2, StereoCamera
    from satloc_env.render.stereo import StereoRenderer
    from satloc_env.world.layout import Layout
    from satloc_env.world.meshes import build_world

    cam = StereoCamera.kitti_half()
    lay = scene.layout
    flat = Layout(lay.width_m, lay.height_m, lay.ground_mpp, lay.ground_rgb, lay.ground_labels)
    out = {}
    for name, world in (("3d", scene.world), ("flat", build_world(flat, pad_m=250.0, beyond="neutral"))):
        with StereoRenderer(world, cam) as r:
            for what, target in (("house", (76.0, 60.0)), ("tree", (90.0, 61.0))):
                x, y = local(scene, target)
                view = r.render(Pose2(x, y, np.pi / 2), depth="left", labels=True)
                out[name, what] = (view["labels_left"], view["depth_left"])
    h, w = cam.height, cam.width
    centre = (slice(h // 2 - h // 8, h // 2), slice(w // 2 - w // 16, w // 2 + w // 16))   # just above the horizon
    lab, depth = out["3d", "house"]
    assert (lab[centre] == CLASS_ID["building"]).mean() > 0.9
    # the wall stands 8 m ahead (y 68 against the camera's 60), less the camera's few centimetres forward
    d = depth[centre][lab[centre] == CLASS_ID["building"]]
    assert np.all(np.abs(d - 8.0) < 0.6), (d.min(), d.max())
    lab, depth = out["3d", "tree"]
    # above the horizon: its trunk and crown, 14 m ahead, radius 3 m (the trees mirrored beyond the tile's edge
    # stand 60 m off or more)
    tree = (lab[: h // 2] == CLASS_ID["tree"]) & (depth[: h // 2] < 50.0)
    assert tree.sum() > 0.02 * h * w / 2
    d = depth[: h // 2][tree]
    assert np.all(np.abs(d - 14.0) < 3.4), (d.min(), d.max())   # the crown seen from below: its far side too
    for what in ("house", "tree"):   # (neutral ground beyond the edge: its painted roofs lie near the horizon)
        lab, depth = out["flat", what]
        assert not np.isin(lab[: h // 2], (CLASS_ID["building"], CLASS_ID["tree"])).any()   # nothing stands


def test_shipped_suburb_utm_stands_its_houses():
    sc = load_scene("suburb_utm")
    assert len(sc.layout.buildings) == 49 and all(b.roof_from_ground for b in sc.layout.buildings)
    assert all(5.0 <= b.height <= 9.0 for b in sc.layout.buildings)
    frac = (sc.satmap.labels == CLASS_ID["building"]).mean()
    assert 0.02 < frac < 0.06


def test_one_osm_export_gives_roads_buildings_and_trees(tmp_path):
    """A whole OpenStreetMap export (one GeoJSON of mixed geometries and tags, as overpass or osmium give it)
    named as roads, buildings and trees: each takes its own features."""
    import json

    to = _to(None)

    def lonlat(pts):
        xy = np.asarray(pts, np.float64) + [E0, N0]
        x, y = to.transform(xy[:, 0], xy[:, 1])
        return [[float(a), float(b)] for a, b in zip(x, y)]

    from test_roads import MAIN

    def feat(kind, coords, **tags):
        geom = lonlat([coords])[0] if kind == "Point" else lonlat(coords) if kind == "LineString" else \
            [lonlat(list(coords) + [coords[0]])]
        return {"type": "Feature", "properties": tags, "geometry": {"type": kind, "coordinates": geom}}

    park = [(60.0, 5.0), (100.0, 5.0), (100.0, 40.0), (60.0, 40.0)]
    fc = {"type": "FeatureCollection", "features": [
        feat("LineString", MAIN, highway="residential", lanes="2"),
        feat("LineString", [(10.0, 10.0), (10.0, 100.0)], highway="footway"),
        feat("Polygon", HOUSE_A, building="house", **{"building:levels": "2"}),
        feat("Polygon", park, landuse="grass"),
        feat("Polygon", WOOD, natural="wood"),
        feat("Point", (90.0, 75.0), natural="tree", height="9"),
        feat("Point", (30.0, 70.0), amenity="bench"),
    ]}
    (tmp_path / "osm.geojson").write_text(json.dumps(fc))
    fp = read_footprints(tmp_path / "osm.geojson")
    assert len(fp.rings) == 1 and fp.heights == [2 * LEVEL_HEIGHT_M]          # not the park
    t = read_trees(tmp_path / "osm.geojson")
    assert len(t.points) == 1 and len(t.canopies) == 1 and t.point_heights == [9.0]   # not the bench or park
    p = tmp_path / "osm.yaml"
    p.write_text(yaml.safe_dump({"name": "osm", "generator": {
        "type": "image", "image": image(tmp_path), "roads": "osm.geojson", "buildings": "osm.geojson",
        "trees": "osm.geojson"}, "meters_per_pixel": RES, "ground_mpp": RES}))
    sc = load_scene(p)
    assert len(sc.layout.buildings) == 1 and sc.layout.buildings[0].height == 6.0
    assert len(sc.layout.trees) > 5 and sc.routes["main"].length > 150


def test_pixels_without_imagery_are_neutral_ground_not_black(tmp_path):
    """A tile whose west strip is nodata: the scene's ground (and tile) there is the imagery's median colour."""
    from affine import Affine
    from test_roads import H_PX, W_PX

    rr, cc = np.mgrid[0:H_PX, 0:W_PX]
    img = np.stack([cc // 2 % 200 + 30, rr // 2 % 200 + 30, np.full_like(cc, 90)], 0).astype(np.uint16) * 8
    img[:, :, :40] = 0                                                   # nodata: the west 20 m
    import rasterio

    with rasterio.open(tmp_path / "nd.tif", "w", driver="GTiff", width=W_PX, height=H_PX, count=3, dtype="uint16",
                       crs=UTM, transform=Affine(RES, 0.0, E0, 0.0, -RES, N0 + H_PX * RES), nodata=0) as ds:
        ds.write(img)
    write_vectors(tmp_path / "roads.geojson", None)
    p = tmp_path / "nd.yaml"
    p.write_text(yaml.safe_dump({"name": "nd", "generator": {"type": "image", "image": "nd.tif",
                                                             "roads": "roads.geojson"},
                                 "meters_per_pixel": RES, "ground_mpp": RES}))
    sc = load_scene(p)
    g = sc.layout.ground_rgb
    west, east = g[:, :30].reshape(-1, 3), g[:, 60:].reshape(-1, 3)
    assert np.ptp(west, axis=0).max() == 0 and west.min() > 20          # one neutral colour, not black
    assert np.abs(west[0].astype(int) - np.median(east, axis=0)).max() <= 12      # about the imagery's median
