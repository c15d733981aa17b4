"""Imagery and vectors on a national grid whose datum is not WGS84 land where WGS84 puts them (the datum's shift
applied: satloc.geoframe.wgs84_bound), not tens of metres off."""
import numpy as np
import pyproj
import pytest

from satloc.geodata.georef import load_map, write_geotiff
from satloc.geodata.vectors import RoadLines
from satloc.geoframe import GeoFrame, wgs84_bound

# a point of each grid near a city: Zurich (LV95), London (British National Grid), Amsterdam (RD New), Vienna
# (MGI Austria GK East), Munich (DHDN Gauss-Krueger 4), and two on WGS84-like datums that need no shift
POINTS = {"EPSG:2056": (2679062.5, 1247700.0), "EPSG:27700": (530000.0, 180000.0),
          "EPSG:28992": (121000.0, 487000.0), "EPSG:31256": (-1750.0, 338300.0),
          "EPSG:31468": (4468000.0, 5333000.0), "EPSG:25832": (456000.0, 5428000.0),
          "EPSG:32632": (456000.0, 5428000.0)}


def truth_lonlat(code, xy):
    return pyproj.Transformer.from_crs(code, "EPSG:4326", always_xy=True).transform(*xy)


@pytest.mark.parametrize("code", sorted(POINTS))
def test_a_grid_point_lands_at_its_wgs84_place_in_the_map_frame(code):
    xy = POINTS[code]
    frame = GeoFrame(*truth_lonlat(code, xy))     # the frame's origin is the point's true place
    tr = pyproj.Transformer.from_crs(wgs84_bound(code), frame.crs, always_xy=True)
    assert np.hypot(*tr.transform(*xy)) * frame.scale < 0.01
    if code in ("EPSG:25832", "EPSG:32632"):     # ETRS89 and WGS84 themselves: left as they are
        assert not wgs84_bound(code).is_bound
    else:                                         # without the shift PROJ is tens of metres off here
        raw = pyproj.Transformer.from_crs(code, frame.crs, always_xy=True)
        assert np.hypot(*raw.transform(*xy)) * frame.scale > 10.0


def test_an_lv95_geotiff_and_lv95_vectors_land_where_wgs84_puts_them(tmp_path):
    e0, n1, mpp = 2679062.5, 1248000.0, 0.5
    img = np.zeros((200, 240, 3), np.uint8)
    img[:, :, 0] = np.arange(240, dtype=np.uint8)[None, :]
    img[:, :, 1] = np.arange(200, dtype=np.uint8)[:, None]
    path = tmp_path / "lv95.tif"
    write_geotiff(path, img, (mpp, 0.0, e0, 0.0, -mpp, n1), "EPSG:2056")
    sm = load_map(path, mpp)
    # the image's centre pixel, where the map frame says it is, against where WGS84 says it is
    lon, lat = truth_lonlat("EPSG:2056", (e0 + 120.25 * mpp, n1 - 100.25 * mpp))
    px = sm.world_to_pixel(sm.frame.to_map([lon, lat]))
    assert np.allclose(img[100, 120, :2], sm.image[int(round(px[1])), int(round(px[0])), :2], atol=2), px
    # a road line given in LV95 and the same line given in lon/lat come out at the same place
    pts = np.array([[e0 + 10, n1 - 50], [e0 + 100, n1 - 60]])
    ll = np.array([truth_lonlat("EPSG:2056", p) for p in pts])
    a = RoadLines([pts], np.array([7.0]), pyproj.CRS("EPSG:2056")).to_frame(sm.frame).lines[0]
    b = RoadLines([ll], np.array([7.0]), pyproj.CRS("OGC:CRS84")).to_frame(sm.frame).lines[0]
    assert np.abs(a - b).max() * sm.frame.scale < 0.01
