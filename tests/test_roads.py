"""Map vectors (satloc.geodata.vectors), the road graph and its derived routes (satloc_env.world.roadgraph), snapped routes,
lane offsets that follow the road's width, the ground beyond the tile's edge, and the drivability check
that ``satloc scene``, the recorder and the experiments run before any work (satloc_env.envs.drivecheck).

The imagery and the vectors are made here, in tmp_path: a GeoTIFF in UTM zone 32N near lon 8.43, lat 49.01
(160 m x 120 m at 0.5 m per pixel) and road centre lines written with pyogrio as GeoJSON (CRS84),
GeoPackage (the image's UTM) and Shapefile (Web Mercator).
"""
from __future__ import annotations

import math
import re
import warnings

import numpy as np
import pyproj
import pytest
import shapely
import yaml
from affine import Affine

from satloc import ConfigError, FormatError
from satloc.geodata.georef import write_geotiff
from satloc.geodata.vectors import LANE_WIDTH_M, read_road_lines, road_width
from satloc_env.world.roadgraph import GraphParams, covering_tour, graph_from_lines, graph_from_mask
from satloc_env.world.route import Route
from satloc_env.world.scene import load_scene

UTM = "EPSG:32632"
TO_UTM = pyproj.Transformer.from_crs("EPSG:4326", UTM, always_xy=True)
E0, N0 = (round(v) for v in TO_UTM.transform(8.43, 49.01))
RES, W_PX, H_PX = 0.5, 320, 240

# the network, in metres east / north of (E0, N0): a main road across the image (and 20 m beyond it), a
# side street to the north ending in a turning ring, and a block loop to the south
MAIN = [(-20.0, 60.0), (60.0, 62.0), (100.0, 58.0), (180.0, 60.0)]
NORTH = [(100.0, 58.0), (102.0, 92.0)]
RING_C, RING_R = (102.0, 99.0), 7.0
SOUTH = [(60.0, 62.0), (60.0, 25.0), (100.0, 25.0), (100.0, 58.0)]


def ring() -> list[tuple[float, float]]:
    a = np.linspace(-math.pi / 2, 1.5 * math.pi, 41)
    pts = [(RING_C[0] + RING_R * math.cos(t), RING_C[1] + RING_R * math.sin(t)) for t in a]
    pts[-1] = pts[0]
    return pts


FEATURES = [  # (local metres, attributes)
    (MAIN, {"highway": "residential", "width": "8 m", "lanes": None, "lane_number": None}),
    (NORTH, {"highway": "residential", "width": None, "lanes": "1", "lane_number": None}),
    (ring(), {"highway": "residential", "width": 5.0, "lanes": None, "lane_number": None}),
    (SOUTH, {"highway": "service", "width": None, "lanes": None, "lane_number": 2}),
    ([(10.0, 10.0), (10.0, 100.0)], {"highway": "footway", "width": 3.0, "lanes": None, "lane_number": None}),
]
WIDTHS = [8.0, LANE_WIDTH_M, 5.0, 2 * LANE_WIDTH_M]   # the car roads' widths from their attributes


def image(tmp_path):
    rr, cc = np.mgrid[0:H_PX, 0:W_PX]
    img = np.stack([cc // 2 % 256, rr // 2 % 256, ((rr // 8 + cc // 8) % 2) * 120 + 60], -1).astype(np.uint8)
    write_geotiff(tmp_path / "tile.tif", img, Affine(RES, 0.0, E0, 0.0, -RES, N0 + H_PX * RES), UTM)
    return "tile.tif"


def write_vectors(path, crs: str | None, features=FEATURES, driver: str | None = None):
    """The features' lines (local metres -> UTM -> ``crs``) written with pyogrio; ``crs`` None: a GeoJSON
    without a CRS (CRS84)."""
    from pyogrio.raw import write

    to = pyproj.Transformer.from_crs(UTM, crs or "OGC:CRS84", always_xy=True)
    geoms = []
    for pts, _ in features:
        xy = np.asarray(pts) + [E0, N0]
        x, y = to.transform(xy[:, 0], xy[:, 1])
        geoms.append(shapely.to_wkb(shapely.LineString(np.stack([x, y], 1))))
    names = ["highway", "width", "lanes", "lane_number"]
    cols = [np.array([str(a[n]) if a[n] is not None else None for _, a in features], dtype=object) for n in names]
    with warnings.catch_warnings():   # no crs (a GeoJSON file in CRS84); a Shapefile's 10-character names
        warnings.simplefilter("ignore")
        write(str(path), np.array(geoms, dtype=object), cols, names, driver=driver, crs=crs,
              geometry_type="LineString")
    return path


def write_scene(tmp_path, routes=None, name="s.yaml", roads="roads.geojson", **extra):
    d = {"name": "roads", "generator": {"type": "image", "image": image(tmp_path), "roads": roads},
         "meters_per_pixel": RES, "ground_mpp": RES, **extra}
    if routes is not None:
        d["routes"] = routes
    p = tmp_path / name
    p.write_text(yaml.safe_dump(d))
    return p


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("roads")
    write_vectors(d / "roads.geojson", None)
    return d


@pytest.fixture(scope="module")
def derived(scene_dir):
    return load_scene(write_scene(scene_dir))


def local(scene, xy_local) -> np.ndarray:
    """Scene metres of points given in metres east / north of (E0, N0)."""
    xy = np.asarray(xy_local, np.float64) + [E0, N0]
    lon, lat = pyproj.Transformer.from_crs(UTM, "EPSG:4326", always_xy=True).transform(xy[..., 0], xy[..., 1])
    return scene.satmap.frame.to_map(np.stack([lon, lat], -1))


def dist_to(p: np.ndarray, line: np.ndarray) -> np.ndarray:
    g = shapely.LineString(line)
    return np.array([g.distance(shapely.Point(q)) for q in p])


# --- vectors ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("fmt, crs, driver", [("geojson", None, None), ("gpkg", UTM, "GPKG"),
                                              ("shp", "EPSG:3857", "ESRI Shapefile")])
def test_vector_readers_in_three_crss(tmp_path, fmt, crs, driver):
    p = write_vectors(tmp_path / f"roads.{fmt}", crs, driver=driver)
    lines = read_road_lines(p, default_width_m=6.0)
    assert lines.crs.equals(pyproj.CRS.from_user_input(crs or "OGC:CRS84"), ignore_axis_order=True)
    assert len(lines.lines) == 4                                   # the footway is not a road for cars
    assert lines.widths.tolist() == WIDTHS
    utm = lines.to_crs(UTM)
    for got, (want, _) in zip(utm.lines, FEATURES):
        assert np.abs(got - (np.asarray(want) + [E0, N0])).max() < 0.01   # a centimetre
    # a scene reads each format onto the same roads
    s = load_scene(write_scene(tmp_path, roads=f"roads.{fmt}", routes={"main": {"waypoints": [[30, 60], [90, 60]],
                                                                                "snap": True}}))
    main = local(s, np.asarray(MAIN))
    assert dist_to(s.routes["main"].points, main).max() < 0.5


def test_road_width_attributes():
    assert road_width({"width": "7.5 m"}, 6) == 7.5
    assert road_width({"WIDTH": 9}, 6) == 9
    assert road_width({"width": "wide", "lanes": "2;3"}, 6) == 2 * LANE_WIDTH_M
    assert road_width({"lane_number": 3}, 6) == 3 * LANE_WIDTH_M
    assert road_width({"width": None, "lanes": None}, 6) == 6


def test_vector_errors(tmp_path):
    write_vectors(tmp_path / "roads.shp", "EPSG:3857", driver="ESRI Shapefile")
    (tmp_path / "roads.prj").unlink()
    with pytest.raises(FormatError, match=r"roads\.shp: layer .* declares no coordinate reference system \(no "
                                          r"roads\.prj beside it\)"):
        read_road_lines(tmp_path / "roads.shp")
    write_vectors(tmp_path / "foot.geojson", None, FEATURES[-1:])
    with pytest.raises(FormatError, match="holds no LineString"):
        read_road_lines(tmp_path / "foot.geojson")
    (tmp_path / "bad.geojson").write_text("{not json")
    with pytest.raises(FormatError, match="bad.geojson: not a readable vector file"):
        read_road_lines(tmp_path / "bad.geojson")
    far = [([(900.0, 900.0), (1000.0, 900.0)], FEATURES[0][1])]
    write_vectors(tmp_path / "far.geojson", None, far)
    with pytest.raises(ConfigError, match=r"generator\.roads: .*far\.geojson: no road lies inside the tile"):
        load_scene(write_scene(tmp_path, roads="far.geojson"))


# --- the graph and the tour -----------------------------------------------------------------------------------
def test_graph_from_lines_nodes_crossings_and_snaps_near_misses():
    lines = [np.array([[0.0, 50.0], [100.0, 50.0]]), np.array([[50.0, 0.0], [50.0, 100.0]]),   # a crossing
             np.array([[20.0, 51.2], [20.0, 90.0]])]                                           # ends 1.2 m short
    g = graph_from_lines(lines, [7.0, 7.0, 4.0], 100.0, 100.0, GraphParams(edge_margin_m=0.0)).graph
    deg = sorted(d for _, d in g.degree())
    assert deg == [1, 1, 1, 1, 1, 3, 4]          # 5 ends, the crossing and the snapped T
    assert g.number_of_edges() == 6
    w = sorted(round(float(np.median(d["w"])), 1) for *_, d in g.edges(data=True))
    assert w == [4.0, 7.0, 7.0, 7.0, 7.0, 7.0]


def test_tour_covers_the_network_and_its_revisit_drives_it_back(derived):
    from satloc_env.envs.drivecheck import first_off_road

    rg_main = local(derived, np.asarray(MAIN))
    assert sorted(derived.routes) == ["main", "revisit"] and derived.spec.query_route == "main"
    tour, back = derived.routes["main"], derived.routes["revisit"]
    assert not tour.closed                       # it starts and ends where the main road leaves the tile
    # every road is driven: the route passes within a metre of points all along every road
    for pts, _ in FEATURES[:4]:
        line = shapely.LineString(local(derived, np.asarray(pts)))
        samples = [line.interpolate(t, normalized=True) for t in np.linspace(0.05, 0.95, 12)]
        xy = np.array([[q.x, q.y] for q in samples])
        inside = (xy[:, 0] > 3) & (xy[:, 0] < derived.layout.width_m - 3)
        assert dist_to(xy[inside], tour.points).max() < 1.5
    # the revisit is the same roads the other way round
    assert back.length == pytest.approx(tour.length, rel=0.01)
    assert dist_to(back.points, tour.points).max() < 1.0
    assert np.linalg.norm(tour.points[0] - back.points[-1]) < 1.0
    # both drivable by the autopilot at the database and the query lanes
    for r in ("main", "revisit"):
        for off in (-1.75, -0.75):
            assert first_off_road(derived, r, off) is None, (r, off)
    assert dist_to(tour.points[:3], rg_main).max() < 0.5


def test_tour_coverage_and_dead_ends():
    """A T of roads whose three ends cannot be turned in: the tour starts and ends at two of them and
    leaves the third out; a mask with a turning circle at the end of a road turns there in a loop."""
    lines = [np.array([[0.0, 50.0], [100.0, 50.0]]), np.array([[50.0, 50.0], [50.0, 90.0]])]
    rg = graph_from_lines(lines, [7.0, 7.0], 100.0, 100.0)
    mpp = 0.25
    yy, xx = np.mgrid[0:400, 0:400]
    x, y = (xx + 0.5) * mpp, 100 - (yy + 0.5) * mpp
    drivable = (np.abs(y - 50) <= 3.5) | ((np.abs(x - 50) <= 3.5) & (y >= 50) & (y <= 90))
    tour, back = covering_tour(rg, drivable, mpp)
    assert tour.loops == 0 and not tour.closed
    assert tour.component_m == pytest.approx(96 + 40, abs=0.5)     # 2 m kept from each tile edge
    assert tour.covered_m == pytest.approx(96, abs=0.5)            # the 40 m stub to the north is left out
    assert tour.coverage == pytest.approx(96 / 136, abs=0.01)
    # the same with a turning circle (radius 9 m) at the stub's end: driven in and out, turning in a loop
    bulb = drivable | (np.hypot(x - 50, y - 82) <= 9.0)
    mask_graph = graph_from_mask(bulb, mpp)
    tour, back = covering_tour(mask_graph, bulb, mpp)
    assert tour.loops == 1 and back.loops == 1 and tour.coverage == 1.0
    assert np.hypot(tour.waypoints[:, 0] - 50, tour.waypoints[:, 1] - 82).min() > 2   # round the circle


def test_derived_routes_keep_the_margin_and_no_view_shows_the_tile_edge(derived, scene_dir):
    from satloc.geometry import StereoCamera
    from satloc_env.render.stereo import StereoRenderer
    from satloc_env.world.meshes import build_world

    m = derived.spec.road_graph.edge_margin_m
    w, h = derived.layout.width_m, derived.layout.height_m
    for r in derived.routes.values():
        p = r.points
        assert p[:, 0].min() >= m - 0.5 and p[:, 1].min() >= m - 0.5
        assert p[:, 0].max() <= w - m + 0.5 and p[:, 1].max() <= h - m + 0.5
    # at the route's end the car looks out past the tile's edge, 2 m ahead: the ground goes on
    cam = StereoCamera.kitti_half()
    pose = derived.routes["main"].pose_at(derived.routes["main"].length - 1.0, -1.75)
    K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
    vv, uu = np.mgrid[0:cam.height, 0:cam.width]
    rays = np.linalg.inv(K) @ np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)])
    dz = (cam.map_from_camera(pose)[:3, :3] @ rays)[2].reshape(cam.height, cam.width)
    ground = (dz < 0) & (cam.mount_height / np.maximum(-dz, 1e-9) < 140)   # ground within the view distance
    empty = {}
    for pad in (0.0, None):
        world = derived.world if pad is None else build_world(derived.layout, pad_m=pad)
        with StereoRenderer(world, cam) as r:
            depth = r.render(pose, depth="left")["depth_left"]
        empty[pad] = float((ground & (depth <= 0)).sum() / ground.sum())
    assert empty[0.0] > 0.05 and empty[None] == 0.0, empty


# --- lane offsets that follow the road -----------------------------------------------------------------------
def test_lane_offset_follows_the_road_width():
    r = Route([[0, 0], [100, 0]], widths=[4.0, 4.0])
    assert r.pose_at(50, -1.75).y == pytest.approx(-1.0)           # the centre of a 4 m road's right lane
    assert Route([[0, 0], [100, 0]], widths=[12.0, 12.0]).pose_at(50, -1.75).y == pytest.approx(-1.75)
    assert Route([[0, 0], [100, 0]]).pose_at(50, -1.75).y == pytest.approx(-1.75)
    closed = Route([[0, 0], [100, 0], [100, 100]], closed=True, laps=2, widths=[7.0, 3.5, 7.0])
    assert len(closed.offset_scale) == len(closed.points)
    with pytest.raises(ValueError, match="one road width > 0"):
        Route([[0, 0], [100, 0]], widths=[4.0])


def test_derived_routes_narrow_the_lane_on_the_narrow_street(derived):
    """The north street is one lane (3.5 m): the right-lane offset shrinks to a quarter of its width."""
    tour = derived.routes["main"]
    street = shapely.LineString(local(derived, np.asarray(NORTH)))
    s = np.arange(0, tour.length, 1.0)
    c = tour.sample(s, 0.0)
    on = np.array([street.distance(shapely.Point(p)) < 0.3 for p in c[:, :2]])
    mid = on & (np.array([street.project(shapely.Point(p)) for p in c[:, :2]]) > 12)
    lane = tour.sample(s[mid], -1.75)
    d = np.linalg.norm(lane[:, :2] - c[mid, :2], axis=1)
    assert np.median(d) == pytest.approx(LANE_WIDTH_M / 4, abs=0.1)


# --- snapped routes -------------------------------------------------------------------------------------------
def test_snapped_lonlat_waypoints_follow_the_roads(derived, scene_dir):
    to_ll = pyproj.Transformer.from_crs(UTM, "EPSG:4326", always_xy=True)
    # 3 m off the main road; on the south loop's far corner; 0.4 m beyond the image's east edge
    pts = [(20.0, 63.0), (98.0, 26.0), (160.4, 60.0)]
    lonlat = [list(to_ll.transform(E0 + x, N0 + y)) for x, y in pts]
    p = write_scene(scene_dir, {"main": {"lonlat": lonlat, "snap": True}}, "snap.yaml")
    s = load_scene(p)
    r = s.routes["main"]
    roads = shapely.MultiLineString([local(s, np.asarray(f)) for f, _ in FEATURES[:4]])
    # on the roads (the turns, smoothed over 3 m, cut the square corners by about a metre)
    assert max(roads.distance(shapely.Point(q)) for q in r.points) < 1.5
    assert r.points[:, 0].max() <= s.layout.width_m
    assert np.linalg.norm(r.points[-1] - local(s, [[158.0, 60.0]])[0]) < 3.0
    # without snap the point beyond the edge is refused, and the message says why and what helps
    p = write_scene(scene_dir, {"main": {"lonlat": lonlat}}, "nosnap.yaml")
    with pytest.raises(ConfigError, match=r"routes\.main\.lonlat\[2\] = .* lies outside the image.*north-up "
                                          r"rectangle.*snap: true"):
        load_scene(p)


@pytest.mark.parametrize("routes, message", [
    ({"main": {"waypoints": [[30, 60], [80, 20], [20, 110]], "snap": True}},
     r"routes\.main\.waypoints\[2\]: the point \(20\.0, 110\.0\) m lies .* m from the nearest road; "
     r"snap_route_m is 20 m"),
    ({"main": {"trace": True, "snap": True}}, r"routes\.main\.snap: a traced route follows the road already"),
    ({"main": {"lonlat": [[8.43, 49.01], [8.431, 49.01]], "widths": [7, 7]}},
     r"routes\.main\.widths: the road width at each waypoint goes with waypoints"),
    ({"main": {"waypoints": [[30, 60], [90, 60]], "widths": [7]}}, r"routes\.main: widths: expected one road width"),
])
def test_route_spec_errors(scene_dir, routes, message):
    p = write_scene(scene_dir, routes, "bad.yaml")
    with pytest.raises(ConfigError, match=message) as e:
        load_scene(p)
    assert str(p) in str(e.value)


def plain_image_scene(tmp_path, generator: dict, **extra):
    """A scene file over a plain (not georeferenced) grey image, its generator given ``generator`` too."""
    import cv2

    cv2.imwrite(str(tmp_path / "plain.png"), np.full((100, 100, 3), 90, np.uint8))
    p = tmp_path / "plain.yaml"
    p.write_text(yaml.safe_dump({"name": "plain", "generator": {"type": "image", "image": "plain.png", **generator},
                                 "meters_per_pixel": 0.5, "ground_mpp": 0.5, **extra}))
    return p


def test_vector_roads_need_a_georeferenced_image(tmp_path):
    write_vectors(tmp_path / "roads.geojson", None)
    p = plain_image_scene(tmp_path, {"roads": "roads.geojson"})
    with pytest.raises(ConfigError, match=r"generator\.roads: .*roads\.geojson is a vector file, in map "
                                          r"coordinates; the image is not georeferenced"):
        load_scene(p)


# --- drivability, checked before any work ----------------------------------------------------------------------
OFF_ROAD = {"main": {"waypoints": [[10, 60], [60, 61], [62, 110]]}}   # turns north where there is no street
OFF_MSG = r"routes\.main: the autopilot leaves the road at \(\d+\.\d, \d+\.\d\) m \(lon 8\.\d+, lat 49\.\d+\), \d+ m of"


def test_the_check_drives_as_the_environment_does(derived, scene_dir):
    from satloc_env.envs.drivecheck import autopilot_drive
    from satloc_env.envs.record import make_env

    env = make_env(scene=str(scene_dir / "s.yaml"), localizer=None)
    try:
        env.reset(seed=0, options={"route": "main", "lane_offset_m": -1.75, "wander_m": 0.0, "speed_wander": 0.0})
        poses = []
        for _ in range(40):
            _, _, term, trunc, info = env.step(env.unwrapped.autopilot_action())
            poses.append(info["pose"])
    finally:
        env.close()
    dry = [p.as_array() for p, _, _ in autopilot_drive(derived, "main", -1.75)][:40]
    assert np.allclose(np.array(poses), np.array(dry), atol=1e-9)


def test_satloc_scene_refuses_a_route_leaving_the_road(scene_dir, capsys):
    from satloc_env.cli import main

    p = write_scene(scene_dir, OFF_ROAD, "off.yaml")
    assert main(["scene", str(p)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("satloc: error: ")
    assert re.search(OFF_MSG, err[0]), err[0]
    assert main(["scene", str(scene_dir / "s.yaml")]) == 0


def test_recording_and_experiments_check_before_any_work(scene_dir, tmp_path, monkeypatch):
    import satloc_env.experiments.tables as compare
    from satloc_env.envs.record import PassConfig, RecordConfig, record_passes

    bad = write_scene(scene_dir, OFF_ROAD, "off.yaml")
    good = scene_dir / "s.yaml"
    with pytest.raises(ConfigError, match=OFF_MSG):
        record_passes(RecordConfig(scene=str(bad)), tmp_path / "rec", progress=False)
    assert not (tmp_path / "rec").exists()                       # nothing written
    # the query pass's own route and lane are checked too: -4 m is off a 3.5 m street
    with pytest.raises(ConfigError, match=r"routes\.revisit: the autopilot leaves the road .* lane offset -4 m"):
        record_passes(RecordConfig(scene=str(good), query=PassConfig(route="revisit", lane_offset_m=-4.0)),
                      tmp_path / "rec2", progress=False)
    stages = []
    monkeypatch.setattr(compare, "_stages", lambda *a, **k: stages.append(a) or (_ for _ in ()).throw(
        AssertionError("recorded before checking")))
    with pytest.raises(ConfigError, match=OFF_MSG):
        compare.table1(tmp_path / "t1", (str(good), str(bad)), progress=False)
    assert stages == []


def test_recorder_reports_leaving_the_road_as_a_config_error(scene_dir, tmp_path):
    """Where a pass is recorded without the check (record_pass alone), leaving the road is still a
    ConfigError naming the route and the point, not a RuntimeError (the env, made on a drivable route,
    refuses the other one when the pass's reset asks for it)."""
    from satloc_env.envs.record import PassConfig, make_env, record_pass

    routes = {**OFF_ROAD, "ok": {"waypoints": [[10, 60], [150, 60]]}}
    bad = write_scene(scene_dir, routes, "off_ok.yaml", database_route="ok", query_route="ok")
    env = make_env(scene=str(bad), localizer=None, depth=False)
    try:
        with pytest.raises(ConfigError, match=OFF_MSG):
            record_pass(env, PassConfig(spacing_m=20.0, depth=False), "main", tmp_path / "p", "p", progress=False)
    finally:
        env.close()


def test_traced_routes_narrow_the_lane_on_a_narrow_road(tmp_path):
    """``trace`` routes carry the road's width too: on a 4 m road the right lane is 1 m right of the centre,
    where a 1.75 m offset would leave 0.25 m to the edge."""
    import cv2

    cv2.imwrite(str(tmp_path / "tile.png"), np.full((240, 320, 3), 90, np.uint8))
    m = np.zeros((240, 320), np.uint8)
    m[116:124, 10:310] = 255                                       # a 4 m road, 150 m long, at 0.5 m/px
    cv2.imwrite(str(tmp_path / "roads.png"), m)
    p = tmp_path / "narrow.yaml"
    p.write_text(yaml.safe_dump({"name": "narrow", "generator": {"type": "image", "image": "tile.png",
                                                                 "roads": "roads.png"},
                                 "meters_per_pixel": 0.5, "ground_mpp": 0.5,
                                 "routes": {"main": {"trace": {"min_length_m": 100}}}}))
    s = load_scene(p)
    r = s.routes["main"]
    assert np.median(s.spec.routes["main"].widths) == pytest.approx(4.0, abs=0.3)
    mid = r.length / 2
    c, lane = r.pose_at(mid, 0.0), r.pose_at(mid, -1.75)
    assert math.hypot(lane.x - c.x, lane.y - c.y) == pytest.approx(1.0, abs=0.1)


def test_a_street_ending_centimetres_off_a_ring_joins_it_once():
    """A street ending 5 cm short of a turning ring, 7.5 cm along the ring from its first vertex (as in
    suburb_utm): one junction, one loop, no debris."""
    a = np.linspace(0, 2 * math.pi, 41)
    ring_xy = np.stack([50 + 6 * np.cos(a), 50 + 6 * np.sin(a)], 1)
    ring_xy[-1] = ring_xy[0]
    on_ring = ring_xy[0] + 0.075 * (ring_xy[1] - ring_xy[0]) / np.linalg.norm(ring_xy[1] - ring_xy[0])
    street = np.array([[on_ring[0] + 0.05, 10.0], on_ring + [0.05, 0.0]])   # 5 cm short of the ring, 7.5 cm
    #                                                                        along it from its first vertex
    g = graph_from_lines([street, ring_xy], [6.0, 5.0], 100.0, 100.0).graph
    lengths = sorted(round(d["length"], 1) for *_, d in g.edges(data=True))
    assert g.number_of_edges() == 2 and lengths[0] > 30, lengths
    assert sorted(d for _, d in g.degree()) == [1, 3]


def test_a_generated_scene_without_routes_gets_them_from_its_ground(tmp_path):
    """A grid scene with no routes: the road graph of its painted roads, a tour over them and its revisit;
    the streets' stubs that end at the tile's edge are left out but two (where the tour starts and ends)."""
    from satloc_env.envs.drivecheck import first_off_road

    p = tmp_path / "grid.yaml"
    p.write_text(yaml.safe_dump({"name": "grid", "seed": 3, "meters_per_pixel": 0.2, "ground_mpp": 0.2,
                                 "generator": {"type": "grid", "style": "city", "blocks": [2, 2], "pitch_m": 60,
                                               "margin_m": 10}}))
    s = load_scene(p)
    assert sorted(s.routes) == ["main", "revisit"] and s.routes["main"].length > 700
    for r in ("main", "revisit"):
        assert first_off_road(s, r, -1.75) is None
