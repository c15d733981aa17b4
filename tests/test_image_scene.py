"""Scenes over georeferenced imagery (``generator: {type: image}`` with a GeoTIFF or a world file), lon/lat
routes, routes traced from a road mask (satloc_env.world.roadtrace), their errors, and the shipped `suburb_utm`
(its GeoJSON roads and derived routes, and the same image with its raster road mask and a traced route).

The imagery is made here, in tmp_path: small GeoTIFFs in UTM zone 32N (EPSG:32632) near lon 8.43, lat
49.01, whose colours encode the UTM position, and road masks drawn from known centre lines.
"""
from __future__ import annotations

import copy

import cv2
import numpy as np
import pyproj
import pytest
import yaml
from affine import Affine

from satloc import ConfigError
from satloc.geodata.georef import write_geotiff, write_world_file
from satloc.geometry import Pose2, StereoCamera
from satloc.labels import CLASS_ID
from satloc_env.world.roadtrace import RoadTraceError, TraceParams, trace_route
from satloc_env.world.scene import Scene, load_scene, load_spec

UTM = "EPSG:32632"
TO_UTM = pyproj.Transformer.from_crs("EPSG:4326", UTM, always_xy=True)
TO_LL = pyproj.Transformer.from_crs(UTM, "EPSG:4326", always_xy=True)
E0, N0 = (round(v) for v in TO_UTM.transform(8.43, 49.01))   # the south-west corner of the test images
RES = 0.5                                                       # metres per source pixel
W_PX, H_PX = 320, 240                                           # 160 m x 120 m


def gradient_image(w: int = W_PX, h: int = H_PX) -> np.ndarray:
    """Colours that encode the pixel: red grows east (1 per 2 px), green grows south, blue a fine checker."""
    rr, cc = np.mgrid[0:h, 0:w]
    return np.stack([cc // 2 % 256, rr // 2 % 256, ((rr // 8 + cc // 8) % 2) * 120 + 60], -1).astype(np.uint8)


def utm_transform(res: float = RES, h: int = H_PX) -> Affine:
    return Affine(res, 0.0, E0, 0.0, -res, N0 + h * res)


def utm_to_px(e, n, res: float = RES, h: int = H_PX) -> np.ndarray:
    """Continuous source pixel (column, row), centres at integers, of UTM points."""
    return np.stack([(np.asarray(e) - E0) / res - 0.5, (N0 + h * res - np.asarray(n)) / res - 0.5], -1)


def draw_road(shape, centre_utm: np.ndarray, width_m: float, res: float = RES) -> np.ndarray:
    m = np.zeros(shape, np.uint8)
    uv = utm_to_px(centre_utm[:, 0], centre_utm[:, 1], res, shape[0])
    cv2.polylines(m, [np.round(uv * 16).astype(np.int32).reshape(-1, 1, 2)], False, 255,
                  thickness=int(round(width_m / res)), lineType=cv2.LINE_8, shift=4)
    return m


def write_scene(tmp_path, generator: dict, routes: dict, name: str = "s.yaml", mpp: float = 0.5, **extra):
    """A scene over an image; its map the image itself (``satellite_gap`` 0: these tests check where its
    pixels lie, which the capture's registration error would move) unless ``knobs`` says otherwise."""
    d = {"name": "geo", "generator": generator, "meters_per_pixel": mpp, "ground_mpp": mpp, "routes": routes,
         "knobs": {"satellite_gap": 0.0}, **extra}
    p = tmp_path / name
    p.write_text(yaml.safe_dump(d))
    return p


def dist_to_polyline(p: np.ndarray, line: np.ndarray) -> np.ndarray:
    a, b = line[:-1], line[1:]
    ab = b - a
    t = np.clip(np.einsum("pkd,kd->pk", p[:, None] - a[None], ab) / np.maximum((ab ** 2).sum(1), 1e-12), 0, 1)
    q = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(q - p[:, None], axis=2).min(axis=1)


def rounded_l(e0: float, n0: float) -> np.ndarray:
    """An L-shaped road centre line (UTM, metres): 100 m east, a 20 m radius bend, 70 m south."""
    arc = np.linspace(np.pi / 2, 0, 24)
    pts = [(e0 + 10, n0 + 100)] + [(e0 + 110 + 20 * np.cos(a), n0 + 80 + 20 * np.sin(a)) for a in arc] + \
          [(e0 + 130, n0 + 10)]
    return np.array(pts, np.float64)


@pytest.fixture()
def geotiff(tmp_path):
    write_geotiff(tmp_path / "tile.tif", gradient_image(), utm_transform(), UTM)
    return tmp_path / "tile.tif"


# --- georeference ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("source", ["geotiff", "png+pgw+prj", "png+pgw, crs field"])
def test_tile_pixel_at_a_known_lonlat(tmp_path, source):
    img = gradient_image()
    gen = {"type": "image"}
    if source == "geotiff":
        write_geotiff(tmp_path / "tile.tif", img, utm_transform(), UTM)
        gen["image"] = "tile.tif"
    else:
        cv2.imwrite(str(tmp_path / "tile.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        write_world_file(tmp_path / "tile.pgw", utm_transform())
        gen["image"] = "tile.png"
        if source == "png+pgw+prj":
            (tmp_path / "tile.prj").write_text(pyproj.CRS(UTM).to_wkt("WKT1_ESRI"))
        else:
            gen["crs"] = UTM
    s = load_scene(write_scene(tmp_path, gen, {"main": {"waypoints": [[20, 60], [140, 60]]}}))
    sm, frame = s.satmap, s.satmap.frame
    assert frame is not None
    # the local frame: the south-west corner of the loaded area is the origin of the scene and of its frame
    assert sm.origin == (0.0, pytest.approx(s.layout.height_m))
    assert sm.extent[2] == 0.0 and sm.extent[0] == 0.0
    assert np.allclose(frame.to_map(sm.pixel_to_lonlat(np.array([-0.5, sm.shape[0] - 0.5]))), 0.0, atol=1e-6)
    # the UTM grid is turned by about 0.4 degrees in the frame: the largest north-up box inside it
    assert 155 < s.layout.width_m <= 160 and 115 < s.layout.height_m <= 120
    # known places: the tile's colour at a lon/lat is the source image's colour at that UTM point
    rng = np.random.default_rng(1)
    e = E0 + rng.uniform(15, 145, 25)
    n = N0 + rng.uniform(15, 105, 25)
    lonlat = np.stack(TO_LL.transform(e, n), -1)
    uv = sm.lonlat_to_pixel(lonlat)
    got = sm.image[np.round(uv[:, 1]).astype(int), np.round(uv[:, 0]).astype(int)].astype(float)
    src = utm_to_px(e, n)
    want_r, want_g = src[:, 0] / 2, src[:, 1] / 2
    # within about a source pixel (bilinear resampling, nearest output pixel at 0.5 m)
    assert np.abs(got[:, 0] - want_r).max() < 1.0 and np.abs(got[:, 1] - want_g).max() < 1.0
    # the ground the camera sees is the same image, in the scene's metres
    xy = frame.to_map(lonlat)
    assert np.array_equal(s.layout.ground_rgb, sm.image)
    assert np.allclose(sm.world_to_pixel(xy), uv)


def test_plain_image_keeps_working_and_has_no_frame(tmp_path):
    cv2.imwrite(str(tmp_path / "tile.png"), np.full((200, 300, 3), 90, np.uint8))
    s = load_scene(write_scene(tmp_path, {"type": "image", "image": "tile.png"},
                               {"main": {"waypoints": [[5, 20], [55, 20]]}}, mpp=0.2))
    assert s.satmap.frame is None and s.satmap.image.shape == (200, 300, 3)
    assert s.layout.width_m == pytest.approx(60) and s.is_drivable(30, 20)


def test_region_crops_to_a_lonlat_box(tmp_path, geotiff):
    lo = TO_LL.transform(E0 + 30, N0 + 20)
    hi = TO_LL.transform(E0 + 90, N0 + 70)
    s = load_scene(write_scene(tmp_path, {"type": "image", "image": "tile.tif", "region": [*lo, *hi]},
                               {"main": {"waypoints": [[5, 20], [55, 20]]}}))
    assert (s.satmap.frame.lon0, s.satmap.frame.lat0) == pytest.approx(lo)
    assert s.layout.width_m == pytest.approx(60, abs=0.6) and s.layout.height_m == pytest.approx(50, abs=0.6)
    # its south-west pixel shows the source at UTM (E0 + 30, N0 + 20)
    want = utm_to_px(E0 + 30.25, N0 + 20.25) / 2
    assert s.satmap.image[-1, 0, :2] == pytest.approx(want, abs=1.0)


def test_lonlat_routes_equal_metre_routes(tmp_path, geotiff):
    wp = [[12.0, 15.0], [80.0, 22.5], [140.0, 100.0], [30.0, 90.0]]
    a = load_scene(write_scene(tmp_path, {"type": "image", "image": "tile.tif"},
                               {"main": {"waypoints": wp, "closed": True}}, "a.yaml"))
    lonlat = a.satmap.frame.to_lonlat(np.array(wp)).tolist()
    b = load_scene(write_scene(tmp_path, {"type": "image", "image": "tile.tif"},
                               {"main": {"lonlat": lonlat, "closed": True}}, "b.yaml"))
    assert np.allclose(b.routes["main"].points, a.routes["main"].points, atol=1e-6)
    assert b.routes["main"].length == pytest.approx(a.routes["main"].length)
    # the resolved spec holds metres (what a saved scene keeps)
    assert b.spec.routes["main"].lonlat is None and b.spec.routes["main"].waypoints is not None


# --- tracing ----------------------------------------------------------------------------------------------
def test_traced_l_road_follows_its_centre_line():
    mpp = 0.25
    centre = rounded_l(0.0, 0.0) + np.array([10.0, 10.0])             # metres in a 160 m x 130 m raster
    h, w = int(130 / mpp), int(160 / mpp)
    m = np.zeros((h, w), np.uint8)
    uv = np.stack([centre[:, 0] / mpp - 0.5, (h * mpp - centre[:, 1]) / mpp - 0.5], -1)
    cv2.polylines(m, [np.round(uv * 16).astype(np.int32).reshape(-1, 1, 2)], False, 1, int(10 / mpp), cv2.LINE_8, 4)
    r = trace_route(m > 0, mpp)
    assert not r.closed
    d = dist_to_polyline(r.waypoints, centre)
    assert d.max() < 1.0, d.max()
    true_len = float(np.sum(np.linalg.norm(np.diff(centre, axis=0), axis=1)))
    assert r.length_m > 0.9 * true_len
    steps = np.linalg.norm(np.diff(r.waypoints, axis=0), axis=1)
    assert steps[:-1] == pytest.approx(2.0, abs=0.01) and steps[-1] <= 2.0 + 1e-6


def test_traced_ring_road_with_ragged_edges_is_a_closed_loop():
    mpp = 0.25
    h, w = 560, 640                                                 # 140 m x 160 m
    ring = np.zeros((h, w), np.uint8)
    c = (80.0, 70.0)
    cv2.ellipse(ring, (int(c[0] / mpp), int(h - c[1] / mpp)), (int(55 / mpp), int(45 / mpp)), 15, 0, 360, 1,
                int(9 / mpp))
    # a ragged outline: blobs of road up to 1 m beyond the edges, and holes (cars, markings) inside it
    rng = np.random.default_rng(3)
    rough = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), 4)
    near = cv2.distanceTransform((ring == 0).astype(np.uint8), cv2.DIST_L2, 5) * mpp < 1.0
    mask = (ring > 0) | (near & (rough > 0.05))
    for _ in range(30):
        u, v = np.argwhere(ring > 0)[rng.integers(int((ring > 0).sum()))]
        mask[u:u + 6, v:v + 10] = False
    r = trace_route(mask, mpp)
    assert r.closed
    ang = np.linspace(0, 2 * np.pi, 720)
    t = np.radians(15)
    ex, ey = 55 * np.cos(ang), 45 * np.sin(ang)
    cx, cy = c[0] + mpp / 2, c[1] - mpp / 2                         # cv2 draws around the pixel centre
    centre = np.stack([cx + ex * np.cos(t) - ey * np.sin(t), cy - (ex * np.sin(t) + ey * np.cos(t))], 1)
    d = dist_to_polyline(r.waypoints, np.vstack([centre, centre[:1]]))
    assert d.max() < 1.0, d.max()
    perimeter = float(np.sum(np.linalg.norm(np.diff(np.vstack([centre, centre[:1]]), axis=0), axis=1)))
    assert r.length_m == pytest.approx(perimeter, rel=0.03)


def test_trace_errors():
    with pytest.raises(RoadTraceError, match="empty"):
        trace_route(np.zeros((50, 50), bool), 0.5)
    m = np.zeros((200, 200), bool)
    m[90:110, 20:60] = True                                        # 20 m of road at 0.5 m/px
    with pytest.raises(RoadTraceError, match=r"shorter than min_length_m = 50 m"):
        trace_route(m, 0.5)
    assert trace_route(m, 0.5, TraceParams(min_length_m=10)).length_m > 10


def test_scene_route_traced_from_a_utm_road_mask(tmp_path, geotiff):
    centre = rounded_l(E0, N0)
    cv2.imwrite(str(tmp_path / "roads.png"), draw_road((H_PX, W_PX), centre, 10.0))
    p = write_scene(tmp_path, {"type": "image", "image": "tile.tif", "roads": "roads.png"},
                    {"main": {"trace": True}, "back": {"trace": {"reverse": True, "spacing_m": 2.0}}},
                    query_route="back")
    s = load_scene(p)
    frame = s.satmap.frame
    centre_xy = frame.to_map(np.stack(TO_LL.transform(centre[:, 0], centre[:, 1]), -1))
    pts = s.routes["main"].points
    assert dist_to_polyline(pts, centre_xy).max() < 1.0
    assert s.routes["main"].length > 150
    assert np.allclose(s.routes["back"].points, pts[::-1])
    # drivable: road inside the mask, void outside
    mid = pts[len(pts) // 2]
    assert s.is_drivable(*mid) and s.ground_label(mid) == CLASS_ID["road"]
    assert not s.is_drivable(*(mid + [0.0, 9.0])) or not s.is_drivable(*(mid - [0.0, 9.0]))
    assert s.ground_label(np.array([150.0, 110.0])) == CLASS_ID["void"]
    # a saved scene keeps the traced waypoints and the geo frame
    s.save(tmp_path / "saved")
    r = Scene.load(tmp_path / "saved")
    assert np.allclose(r.routes["main"].points, pts) and r.satmap.frame == frame


# --- errors -----------------------------------------------------------------------------------------------
def _base(tmp_path):
    write_geotiff(tmp_path / "tile.tif", gradient_image(), utm_transform(), UTM)
    cv2.imwrite(str(tmp_path / "roads.png"), draw_road((H_PX, W_PX), rounded_l(E0, N0), 10.0))
    return {"type": "image", "image": "tile.tif", "roads": "roads.png"}


def _small_mask(tmp_path):
    m = np.zeros((H_PX, W_PX), np.uint8)
    m[100:120, 100:140] = 255
    cv2.imwrite(str(tmp_path / "roads.png"), m)


def _far_lonlat(tmp_path):
    return [list(TO_LL.transform(E0 + 20, N0 + 20)), list(TO_LL.transform(E0 + 400, N0 + 20))]


@pytest.mark.parametrize("change, routes, message", [
    (lambda t, g: g.update(image="missing.tif"), None, r"generator\.image: image file .*missing\.tif not found"),
    (lambda t, g: g.update(roads="nope.png"), None, r"generator\.roads: road mask .*nope\.png not found"),
    (lambda t, g: cv2.imwrite(str(t / "roads.png"), np.zeros((10, 10), np.uint8)), None,
     r"generator\.roads: .*roads\.png is 10x10 px, but the image tile\.tif is 320x240 px"),
    (lambda t, g: cv2.imwrite(str(t / "roads.png"), np.zeros((H_PX, W_PX), np.uint8)), None,
     r"generator\.roads: the road mask .*roads\.png is empty"),
    (lambda t, g: _small_mask(t), None,
     r"routes\.main\.trace: generator\.roads \(.*roads\.png\): the longest road .* shorter than min_length_m"),
    (lambda t, g: None, {"main": {"trace": True, "closed": True}}, r"routes\.main\.closed: .* is not a loop"),
    (lambda t, g: None, {"main": {"waypoints": [[10, 10], [500, 10]]}},
     r"routes\.main\.waypoints\[1\] = \[500(\.0)?, 10(\.0)?\] lies outside the tile"),
    (lambda t, g: None, "far", r"routes\.main\.lonlat\[1\] = \[.*\] lies outside the image"),
    (lambda t, g: None, {"main": {"trace": True, "waypoints": [[1, 1], [2, 2]]}},
     r"routes\.main\.waypoints/lonlat/trace: expected exactly one of them, got waypoints and trace"),
    (lambda t, g: None, {"main": {"closed": True}}, r"routes\.main\.waypoints/lonlat/trace: .* got none"),
    (lambda t, g: g.pop("roads"), {"main": {"trace": True}}, r"routes\.main\.trace: tracing needs a road mask"),
    (lambda t, g: g.update(region=[8.0, 49.0, 8.01, 49.01]), None, r"generator\.region: region: .* not covered"),
    (lambda t, g: g.update(region=[8.44, 49.0, 8.43, 49.01]), None,
     r"generator\.region: expected \[lon_min, lat_min, lon_max, lat_max\]"),
    (lambda t, g: g.update(crs="EPSG:4326"), None, r"generator\.crs: .* differs from crs="),
    (lambda t, g: g.update(roads=None, labels="labels.png") or cv2.imwrite(
        str(t / "labels.png"), np.full((H_PX, W_PX), 40, np.uint8)), None, r"generator\.labels: class id 40 >= 12"),
])
def test_bad_image_scenes_name_the_file_and_field(tmp_path, change, routes, message):
    g = _base(tmp_path)
    change(tmp_path, g)
    if routes == "far":
        routes = {"main": {"lonlat": _far_lonlat(tmp_path)}}
    p = write_scene(tmp_path, g, routes or {"main": {"trace": True}})
    with pytest.raises(ConfigError, match=message) as e:
        load_scene(p)
    assert str(p) in str(e.value)


def test_plain_image_refuses_geo_fields(tmp_path):
    cv2.imwrite(str(tmp_path / "tile.png"), np.full((100, 100, 3), 90, np.uint8))
    for gen, routes, message in (
            ({"region": [8.0, 49.0, 8.1, 49.1]}, {"main": {"waypoints": [[1, 1], [9, 9]]}},
             r"generator\.region: .*tile\.png is not georeferenced"),
            ({}, {"main": {"lonlat": [[8.43, 49.01], [8.431, 49.01]]}},
             r"routes\.main\.lonlat: the scene has no geo frame"),
    ):
        p = write_scene(tmp_path, {"type": "image", "image": "tile.png", **gen}, routes, mpp=0.2)
        with pytest.raises(ConfigError, match=message):
            load_scene(p)


def test_a_plain_image_with_a_road_mask_is_traced(tmp_path):
    cv2.imwrite(str(tmp_path / "tile.png"), np.full((240, 320, 3), 90, np.uint8))
    m = np.zeros((240, 320), np.uint8)
    m[110:130, 10:310] = 255                                       # 150 m east-west road at 0.5 m/px
    cv2.imwrite(str(tmp_path / "roads.png"), m)
    s = load_scene(write_scene(tmp_path, {"type": "image", "image": "tile.png", "roads": "roads.png"},
                               {"main": {"trace": {"min_length_m": 100}}}))
    pts = s.routes["main"].points
    assert s.satmap.frame is None and s.routes["main"].length > 130
    assert np.abs(pts[:, 1] - (120 - 120 * 0.5)).max() < 0.3      # the road's centre: y = 60 m


# --- the shipped scene --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def suburb():
    return load_scene("suburb_utm")


@pytest.fixture(scope="module")
def suburb_raster(tmp_path_factory):
    """The shipped suburb's image with its raster road mask (beside the GeoJSON) and a route traced from it."""
    base = load_spec("suburb_utm")[1]
    d = yaml.safe_load(open(base / "suburb_utm.yaml"))
    d["generator"]["image"] = str(base / "suburb_utm.tif")
    d["generator"]["roads"] = str(base / "suburb_utm_roads.png")
    d["generator"].pop("buildings", None)          # flat: the raster mask alone
    d["routes"] = {"main": {"trace": {"smooth_m": 2.0, "spacing_m": 2.0, "min_length_m": 300}}}
    p = tmp_path_factory.mktemp("suburb_raster") / "suburb_raster.yaml"
    p.write_text(yaml.safe_dump(d))
    return load_scene(p)


def test_shipped_suburb_loads_with_its_frame_and_derived_routes(suburb):
    spec, _ = load_spec("suburb_utm")
    assert spec.generator["type"] == "image" and spec.generator["roads"].endswith(".geojson") and not spec.routes
    f = suburb.satmap.frame
    assert f is not None and abs(f.lon0 - 8.43) < 0.01 and abs(f.lat0 - 49.01) < 0.01
    assert sorted(suburb.routes) == ["main", "revisit"] and suburb.spec.query_route == "main"
    route = suburb.routes["main"]
    assert route.length > 650 and not route.closed          # the main road and both cul-de-sacs, in and out
    # the route runs on the roads, with room for the right lane
    on = [suburb.is_drivable(x, y) for x, y, _ in route.sample(np.arange(0, route.length, 2.0), -1.75)]
    assert all(on)
    back = suburb.routes["revisit"]
    assert back.length == pytest.approx(route.length, rel=0.01)
    assert np.linalg.norm(back.points[0] - route.points[-1]) < 3 and np.linalg.norm(back.points[-1] - route.points[0]) < 3


def test_suburb_raster_mask_still_traces_its_main_road(suburb_raster, suburb):
    route = suburb_raster.routes["main"]
    assert 350 < route.length < 420 and not route.closed
    on = [suburb_raster.is_drivable(x, y) for x, y, _ in route.sample(np.arange(0, route.length, 2.0), -1.75)]
    assert all(on)
    # the raster mask and the GeoJSON roads make nearly the same drivable area
    a, b = suburb_raster.drivable, suburb.drivable
    assert a.shape == b.shape and (a ^ b).sum() < 0.08 * a.sum()


def test_shipped_suburb_renders_the_image_on_the_ground(suburb):
    from satloc_env.render.stereo import StereoRenderer

    cam = StereoCamera.kitti_half()
    route = suburb.routes["main"]
    x, y, yaw = route.sample(np.array([150.0]), -1.75)[0]
    pose = Pose2(x, y, yaw)
    with StereoRenderer(suburb.world, cam) as r:
        out = r.render(pose, depth="left", labels=True)
    img, depth = out["left"], out["depth_left"]
    vv, uu = np.mgrid[cam.height // 2 + 20:cam.height:4, 0:cam.width:8]
    uv = np.stack([uu.ravel(), vv.ravel()], 1).astype(np.float64)
    z = depth[uv[:, 1].astype(int), uv[:, 0].astype(int)]
    standing = out["labels_left"][uv[:, 1].astype(int), uv[:, 0].astype(int)] == CLASS_ID["building"]
    ok = (z > 0) & (z < 20) & ~standing                 # the ground, not the houses' walls
    assert ok.sum() > 200

    def diff(p: Pose2) -> float:
        xyz = cam.pixels_to_map(p, uv[ok], z[ok])
        assert np.abs(xyz[:, 2]).max() < 0.05                       # the ground plane
        tp = np.round(suburb.satmap.world_to_pixel(xyz[:, :2])).astype(int)
        tile = suburb.satmap.image[tp[:, 1], tp[:, 0]].astype(float)
        seen = img[uv[ok][:, 1].astype(int), uv[ok][:, 0].astype(int)].astype(float)
        return float(np.median(np.abs(tile - seen)))

    right = diff(pose)
    assert right < 12, right
    assert diff(Pose2(x + 6 * np.cos(yaw + np.pi / 2), y + 6 * np.sin(yaw + np.pi / 2), yaw)) > right + 8


def test_autopilot_drives_the_traced_route_on_road(suburb):
    import gymnasium as gym

    import satloc_env  # noqa: F401  (registers the environment)

    env = gym.make("satloc/SatLoc-v0", scene="suburb_utm", localizer=None, max_steps=200)
    try:
        env.reset(seed=0, options={"occlusion": 0.5, "appearance": 0.3, "start_s_m": 80.0})
        s0 = None
        for k in range(60):
            obs, _, term, trunc, info = env.step(env.unwrapped.autopilot_action())
            s0 = float(info["route_s"]) if s0 is None else s0
            assert not info["off_road"], (k, info["pose"])
            assert not term and not trunc
        assert float(info["route_s"]) - s0 > 40                   # about 8 m/s for 5.9 s
        assert obs["left"].shape == (188, 620, 3) and obs["left"].std() > 5
    finally:
        env.close()


def test_changing_the_mask_changes_the_auto_localizer_key(tmp_path):
    from satloc_env.envs.auto_localizer import cache_key

    g = _base(tmp_path)
    p = write_scene(tmp_path, g, {"main": {"trace": True}})
    a = cache_key(p)
    cv2.imwrite(str(tmp_path / "roads.png"), draw_road((H_PX, W_PX), rounded_l(E0, N0), 12.0))
    assert cache_key(p)["scene_sha256"] != a["scene_sha256"]


def test_shipped_suburb_spec_round_trips(tmp_path, suburb):
    d = copy.deepcopy(yaml.safe_load(open(load_spec("suburb_utm")[1] / "suburb_utm.yaml")))
    assert d["generator"]["image"].endswith(".tif") and d["generator"]["roads"].endswith(".geojson")
    suburb.save(tmp_path / "saved")
    r = Scene.load(tmp_path / "saved")
    assert r.satmap.frame == suburb.satmap.frame
    for k in ("main", "revisit"):
        assert np.allclose(r.routes[k].points, suburb.routes[k].points)
        assert np.allclose(r.routes[k].offset_scale, suburb.routes[k].offset_scale)


def test_experiment_records_again_when_a_scene_file_changes(tmp_path, monkeypatch):
    """``satloc experiment`` reuses a scene's recorded passes only while the scene's files are unchanged (the
    YAML, the image and the road mask: what the auto-localizer's key hashes), not just its name or path."""
    import satloc_env.experiments.scene_run as experiment
    import satloc_env.experiments.tables as compare

    recorded = []
    monkeypatch.setattr(experiment, "record_passes", lambda rec, out, progress: recorded.append(rec.scene))
    monkeypatch.setattr(experiment.Sequence, "load", staticmethod(lambda path: None))
    monkeypatch.setattr(experiment, "build_and_learn", lambda *a, **k: (tmp_path / "build", {}))
    p = write_scene(tmp_path, _base(tmp_path), {"main": {"trace": True}})
    cfg = experiment.ExperimentConfig(scene=str(p))
    for _ in range(2):
        experiment._stages(cfg, tmp_path / "out", False, lambda m: None)
    assert recorded == [str(p)]                                    # the second run reused the recording
    cv2.imwrite(str(tmp_path / "roads.png"), draw_road((H_PX, W_PX), rounded_l(E0, N0), 12.0))
    experiment._stages(cfg, tmp_path / "out", False, lambda m: None)
    assert recorded == [str(p), str(p)]                            # a wider road: recorded again
    with pytest.raises(ConfigError, match="both named 'geo'"):
        compare.table1(tmp_path / "t", (str(p), str(write_scene(tmp_path, _base(tmp_path), {"main": {
            "trace": True}}, "other.yaml"))), progress=False)


def test_an_image_scene_parks_cars_of_its_own_that_the_map_does_not_show(tmp_path):
    """``parked_per_km``: 3-D cars along the kerbs in the camera's world; the map, the image captured, is the same."""
    write_geotiff(tmp_path / "tile.tif", gradient_image(), utm_transform(), UTM)
    cv2.imwrite(str(tmp_path / "roads.png"), draw_road((H_PX, W_PX), rounded_l(E0, N0), 14.0))
    g = {"type": "image", "image": "tile.tif", "roads": "roads.png"}
    routes = {"main": {"trace": True}}
    knobs = {"satellite_gap": 0.5}
    plain = load_scene(write_scene(tmp_path, g, routes, "plain.yaml", knobs=knobs))
    parked = load_scene(write_scene(tmp_path, {**g, "parked_per_km": 100.0}, routes, "parked.yaml", knobs=knobs))
    assert plain.layout.cars == [] and 5 <= len(parked.layout.cars) <= 60, len(parked.layout.cars)
    assert all(parked.is_drivable(*c.center) for c in parked.layout.cars)
    assert np.array_equal(parked.satmap.image, plain.satmap.image)        # not in the map
    assert np.array_equal(parked.layout.ground_rgb, plain.layout.ground_rgb)
    # the route's right lane stays clear of them (1.75 m right of the centre line; a car's half-width 0.9 m)
    route = parked.routes["main"]
    lane = route.sample(np.arange(0.0, route.length, 1.0), -1.75)[:, :2]
    gap = min(float(np.min(np.hypot(*(lane - c.center).T))) for c in parked.layout.cars)
    assert gap > 2.0, gap
    bad = write_scene(tmp_path, {**g, "parked_per_km": -1.0}, routes, "bad.yaml", knobs=knobs)
    with pytest.raises(ConfigError, match=r"generator\.parked_per_km"):
        load_scene(bad)
