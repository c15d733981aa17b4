"""Georeferenced satellite input (satloc.geodata.georef) and the satellite map's geo frame (satloc.satmap)."""
import json
import shutil

import numpy as np
import pytest
from affine import Affine
from geofixtures import REF, UTM, make_geotiff, make_tiles, make_world_image, mark_errors, texture, write_image
from PIL import Image

from satloc import ConfigError, FormatError, SatelliteMap
from satloc.geodata.georef import load_map, read_world_file, save_geotiff, write_geotiff, write_world_file
from satloc.geoframe import GeoFrame


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """One file (or folder) per input kind, all painting the same ground."""
    d = tmp_path_factory.mktemp("geo")
    kinds = {
        "geotiff_4326": make_geotiff(d / "g4326.tif", "EPSG:4326")[0],
        "geotiff_3857": make_geotiff(d / "g3857.tiff", "EPSG:3857")[0],
        "geotiff_utm": make_geotiff(d / "gutm.tif", UTM)[0],
        "png_world_utm": make_world_image(d / "wutm.png", UTM)[0],
        "png_world_4326": make_world_image(d / "w4326.png", "EPSG:4326")[0],
        "jpg_world_rotated": make_world_image(d / "wrot.jpg", UTM, rotation_deg=12.0)[0],
        "xyz_tiles": make_tiles(d / "tiles", zoom=18)[0],
    }
    return kinds


def _fraction_matching_texture(sm: SatelliteMap, tol: int) -> float:
    """Share of pixels whose colour is the pattern's colour at the pixel's lon/lat (within ``tol``)."""
    v, u = np.mgrid[0:sm.shape[0]:3, 0:sm.shape[1]:3]
    ll = sm.pixel_to_lonlat(np.stack([u, v], axis=-1).astype(np.float64))
    want = texture(ll[..., 0], ll[..., 1]).astype(int)
    got = sm.image[v, u].astype(int)
    return float((np.abs(got - want).max(axis=-1) <= tol).mean())


@pytest.mark.parametrize("kind", ["geotiff_4326", "geotiff_3857", "geotiff_utm", "png_world_utm", "png_world_4326",
                                  "jpg_world_rotated", "xyz_tiles"])
def test_every_kind_lands_on_its_lon_lat(inputs, kind):
    sm = load_map(inputs[kind])
    assert sm.frame is not None and sm.image.dtype == np.uint8 and sm.image.shape[2] == 3
    # default resolution: the source's own (0.5 m; z18 tiles at 49 deg: 0.597 * cos(49.01) = 0.39 m)
    assert sm.meters_per_pixel == (0.39 if kind == "xyz_tiles" else 0.5)
    # the default frame is at the image centre (the box centre, or the tile mosaic's)
    centre = REF.to_map(np.array([sm.frame.lon0, sm.frame.lat0]))
    assert np.allclose(centre, 0.0, atol=60.0 if kind == "xyz_tiles" else 1.0)
    # pixel -> lon/lat -> metres -> pixel
    rng = np.random.default_rng(0)
    uv = rng.uniform([0, 0], [sm.shape[1] - 1, sm.shape[0] - 1], (200, 2))
    back = sm.world_to_pixel(sm.frame.to_map(sm.pixel_to_lonlat(uv)))
    assert np.abs(back - uv).max() < 0.5
    # each painted lon/lat mark is found at lonlat_to_pixel of its lon/lat
    errors = mark_errors(sm)
    assert max(errors.values()) < 1.0, errors
    # and the whole picture agrees with the pattern at each pixel's lon/lat (cell borders blend)
    assert _fraction_matching_texture(sm, tol=25 if kind.startswith("jpg") else 6) > 0.8


def test_default_extent_has_no_black_wedges(inputs):
    # UTM is rotated by the grid convergence in the frame; a 12 degree rotated world file even more
    for kind in ("geotiff_utm", "jpg_world_rotated"):
        sm = load_map(inputs[kind])
        border = np.concatenate([sm.image[0], sm.image[-1], sm.image[:, 0], sm.image[:, -1]])
        assert (border.max(axis=-1) > 30).all(), kind


def test_geotiff_and_world_file_give_the_same_map(tmp_path):
    _, img, tr = make_geotiff(tmp_path / "a.tif", UTM)
    write_image(tmp_path / "b.png", img)
    write_world_file(tmp_path / "b.pgw", tr)
    (tmp_path / "b.prj").write_text(_utm_wkt())  # ESRI WKT, as GIS software writes it
    write_image(tmp_path / "c.png", img)  # <name>.<ext>w form, CRS from the argument
    write_world_file(tmp_path / "c.pngw", tr)
    write_image(tmp_path / "d.png", img)  # .wld form
    write_world_file(tmp_path / "d.wld", tr)
    write_geotiff(tmp_path / "e.tif", img, Affine.identity())  # a TIFF without georeference + .tfw
    write_world_file(tmp_path / "e.tfw", tr)
    a = load_map(tmp_path / "a.tif")
    others = (load_map(tmp_path / "b.png"), load_map(tmp_path / "c.png", crs=UTM),
              load_map(tmp_path / "d.png", crs="EPSG:32632"), load_map(tmp_path / "e.tif", crs=UTM))
    for other in others:
        assert other.frame == a.frame and other.meters_per_pixel == a.meters_per_pixel
        assert np.allclose(other.extent, a.extent, atol=a.meters_per_pixel)
        assert other.shape == a.shape
        assert np.abs(other.image.astype(int) - a.image.astype(int)).max() <= 1


def _utm_wkt():
    import pyproj

    return pyproj.CRS.from_user_input(UTM).to_wkt(pyproj.enums.WktVersion.WKT1_ESRI)


def test_world_file_round_trip(tmp_path):
    tr = Affine(0.25, 0.01, 455000.0, -0.02, -0.25, 5430000.0)
    write_world_file(tmp_path / "x.wld", tr)
    lines = (tmp_path / "x.wld").read_text().split()
    assert float(lines[4]) == pytest.approx(455000.0 + 0.5 * 0.25 + 0.5 * 0.01)  # C: centre of the top-left pixel
    assert read_world_file(tmp_path / "x.wld").almost_equals(tr, precision=1e-9)


def test_region_is_a_crop_of_the_whole_map(inputs):
    for kind in ("geotiff_utm", "xyz_tiles"):
        whole = load_map(inputs[kind], mpp=0.5, frame=REF)
        region = (-50.2, -30.1, 60.3, 40.7)
        part = load_map(inputs[kind], mpp=0.5, frame=REF, region=region)
        x0, x1, y0, y1 = part.extent
        assert (x0, y0, x1, y1) == pytest.approx((-50.5, -30.5, 60.5, 41.0))  # widened to the 0.5 m lattice
        u0, v0 = np.round(whole.world_to_pixel(np.array([x0, y1])) + 0.5).astype(int)
        block = whole.image[v0:v0 + part.shape[0], u0:u0 + part.shape[1]]
        assert block.shape == part.image.shape
        assert np.abs(block.astype(int) - part.image.astype(int)).max() <= 1, kind


def test_explicit_frame_and_coarser_resolution(inputs):
    elsewhere = GeoFrame(8.425, 49.013)  # about 370 m west and 330 m north of the box centre
    for kind in ("geotiff_4326", "geotiff_utm", "xyz_tiles"):
        sm = load_map(inputs[kind], mpp=1.0, frame=elsewhere)  # area averaging
        assert sm.frame == elsewhere and sm.meters_per_pixel == 1.0
        assert max(mark_errors(sm).values()) < 1.0, kind
        centre = elsewhere.to_map(np.array([REF.lon0, REF.lat0]))
        assert sm.contains(centre)


def test_grey_rgba_and_palette_images(tmp_path):
    _, grey, _ = make_geotiff(tmp_path / "grey.tif", UTM, bands="grey")
    sm = load_map(tmp_path / "grey.tif")
    assert (sm.image[..., 0] == sm.image[..., 1]).all() and (sm.image[..., 1] == sm.image[..., 2]).all()
    rgb = load_map(make_geotiff(tmp_path / "rgb.tif", UTM)[0])
    assert np.corrcoef(sm.image[..., 0].ravel(), rgb.image.mean(axis=2).ravel())[0, 1] > 0.99

    # north up in EPSG:3857 as in the frame, so the transparent western half ends at a column of the map
    make_world_image(tmp_path / "rgba.png", "EPSG:3857", bands="rgba")
    sm = load_map(tmp_path / "rgba.png")
    rgb3857 = load_map(make_geotiff(tmp_path / "rgb3857.tif", "EPSG:3857")[0])
    w = sm.shape[1]
    assert sm.image[:, : w // 2 - 1].max() == 0  # transparent: black
    assert np.abs(sm.image[:, w // 2 + 1:].astype(int) - rgb3857.image[:, w // 2 + 1:].astype(int)).max() <= 1

    _, img, tr = make_world_image(tmp_path / "p.png", UTM)
    pal = Image.fromarray(img).quantize(colors=64, method=Image.Quantize.MEDIANCUT)
    pal.save(tmp_path / "p.png")
    sm = load_map(tmp_path / "p.png")
    expanded = np.asarray(pal.convert("RGB"))
    assert sm.shape == rgb.shape
    assert np.median(np.abs(sm.image.astype(int) - rgb.image.astype(int))) <= np.median(
        np.abs(expanded.astype(int) - img.astype(int))) + 2


def test_zoom_levels(tmp_path):
    make_tiles(tmp_path / "t", zoom=17)
    make_tiles(tmp_path / "t", zoom=18)
    assert load_map(tmp_path / "t").meters_per_pixel == 0.39  # the highest zoom by default
    sm = load_map(tmp_path / "t", zoom=17)
    assert sm.meters_per_pixel == 0.78 and max(mark_errors(sm).values()) < 1.0
    with pytest.raises(ConfigError, match=r"zoom 16; it has zoom \[17, 18\]"):
        load_map(tmp_path / "t", zoom=16)


def test_missing_tile(tmp_path):
    root, written = make_tiles(tmp_path / "t", zoom=18)
    corner = min(written)  # the north-western tile
    (root / "18" / str(corner[0]) / f"{corner[1]}.png").unlink()
    with pytest.raises(FormatError, match=rf"tile 18/{corner[0]}/{corner[1]} is missing"):
        load_map(root)
    sm = load_map(root, frame=REF, region=(-50, -50, 50, 50))  # the missing tile is not needed here
    x0, x1, y0, y1 = sm.extent
    assert x0 <= -50 and y0 <= -50 and x1 >= 50 and y1 >= 50 and _fraction_matching_texture(sm, tol=6) > 0.8


def test_save_geotiff_round_trip(tmp_path, inputs):
    sm = load_map(inputs["geotiff_utm"], mpp=0.5, frame=REF, region=(-100, -80, 100, 80))
    save_geotiff(sm, tmp_path / "out" / "map.tif")
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["map.tif"]
    back = load_map(tmp_path / "out" / "map.tif", mpp=0.5, frame=REF)
    assert back.extent == pytest.approx(sm.extent)
    assert np.abs(back.image.astype(int) - sm.image.astype(int)).max() <= 1
    with pytest.raises(ConfigError, match="no geo frame"):
        save_geotiff(SatelliteMap(np.zeros((4, 4, 3), np.uint8), 1.0), tmp_path / "x.tif")
    with pytest.raises(ConfigError, match="uint8"):
        write_geotiff(tmp_path / "y.tif", np.zeros((4, 4, 2), np.uint8), Affine.identity())
    assert not (tmp_path / "x.tif").exists() and not (tmp_path / "y.tif").exists()


# --- bad input -------------------------------------------------------------------------------------------
def test_bad_files(tmp_path, inputs):
    with pytest.raises(FormatError, match="nowhere.tif: file or tile folder not found"):
        load_map(tmp_path / "nowhere.tif")
    (tmp_path / "junk.png").write_bytes(b"not a png at all")
    with pytest.raises(FormatError, match="junk.png: not a readable image"):
        load_map(tmp_path / "junk.png")
    (tmp_path / "junk.tif").write_bytes(b"II*\x00garbage")
    with pytest.raises(FormatError, match="junk.tif: not a readable image"):
        load_map(tmp_path / "junk.tif")
    (tmp_path / "map.bmp").write_bytes(b"BM")
    with pytest.raises(FormatError, match="map.bmp: expected a GeoTIFF"):
        load_map(tmp_path / "map.bmp")
    # a GeoTIFF with a transform but no CRS
    make_geotiff(tmp_path / "nocrs.tif", None)
    with pytest.raises(FormatError, match=r"nocrs.tif: has no CRS .*crs="):
        load_map(tmp_path / "nocrs.tif")
    assert max(mark_errors(load_map(tmp_path / "nocrs.tif", crs=UTM)).values()) < 1.0
    # a GeoTIFF whose own CRS differs from crs=
    with pytest.raises(ConfigError, match="carries its own CRS"):
        load_map(inputs["geotiff_utm"], crs="EPSG:3857")
    # an image with neither geotransform nor world file
    write_image(tmp_path / "plain.png", np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(FormatError, match=r"plain.png: not georeferenced.*plain.pgw"):
        load_map(tmp_path / "plain.png")


def test_bad_world_files_and_crs(tmp_path):
    path, _, _ = make_world_image(tmp_path / "w.png", UTM, prj=False)
    with pytest.raises(FormatError, match=r"w.png: has no CRS .*w.prj"):
        load_map(path)
    with pytest.raises(ConfigError, match="crs: expected a coordinate reference system"):
        load_map(path, crs="EPSG:99999999")
    (tmp_path / "w.prj").write_text("GEOGCS[broken")
    with pytest.raises(FormatError, match="w.prj: not a readable CRS"):
        load_map(path)
    (tmp_path / "w.prj").unlink()
    good = (tmp_path / "w.pgw").read_text().splitlines()
    (tmp_path / "w.pgw").write_text("\n".join(good[:5]) + "\n")
    with pytest.raises(FormatError, match=r"w.pgw: a world file has 6 lines .*found 5"):
        load_map(path, crs=UTM)
    (tmp_path / "w.pgw").write_text("\n".join(good[:2] + ["0,0"] + good[3:]) + "\n")
    with pytest.raises(FormatError, match=r"w.pgw: line 3: expected a number for B"):
        load_map(path, crs=UTM)
    (tmp_path / "w.pgw").write_text("0\n0\n0\n0\n1\n2\n")
    with pytest.raises(FormatError, match="degenerate"):
        load_map(path, crs=UTM)


def test_bad_tile_folders(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(FormatError, match="empty: no XYZ tiles"):
        load_map(tmp_path / "empty")
    (tmp_path / "other" / "a" / "b").mkdir(parents=True)
    (tmp_path / "other" / "readme.txt").write_text("x")
    with pytest.raises(FormatError, match="no XYZ tiles"):
        load_map(tmp_path / "other")
    root, _ = make_tiles(tmp_path / "t", zoom=18)
    with pytest.raises(ConfigError, match="crs: a tile folder"):
        load_map(root, crs=UTM)
    bad = next((root / "18").iterdir())
    next(bad.iterdir()).write_bytes(b"junk")
    with pytest.raises(FormatError, match="not a readable tile image"):
        load_map(root)


def test_bad_arguments(inputs):
    path = inputs["geotiff_utm"]
    for kw, match in [(dict(mpp=0), "mpp"), (dict(mpp=-1.0), "mpp"), (dict(mpp="0.2"), "mpp"),
                      (dict(frame=(8.4, 49.0)), "frame"), (dict(region=(0, 0, -1, 1)), "region"),
                      (dict(region=(0, 0, 1)), "region"), (dict(zoom=18), "zoom")]:
        with pytest.raises(ConfigError, match=match):
            load_map(path, **kw)
    with pytest.raises(ConfigError, match=r"region: .* is not covered by .*gutm.tif, which covers x \["):
        load_map(path, frame=REF, region=(150.0, 0.0, 260.0, 50.0))


# --- the map's geo frame ---------------------------------------------------------------------------------
def test_map_json_with_and_without_frame(tmp_path):
    rng = np.random.default_rng(1)
    img = rng.integers(0, 255, (30, 40, 3), dtype=np.uint8)
    SatelliteMap(img, 0.2, (1.0, 2.0), frame=REF).save(tmp_path / "geo")
    back = SatelliteMap.load(tmp_path / "geo")
    assert back.frame == REF and np.array_equal(back.image, img) and back.origin == (1.0, 2.0)
    assert json.loads((tmp_path / "geo" / "map.json").read_text())["geo_frame"] == REF.to_dict()

    SatelliteMap(img, 0.2, (1.0, 2.0)).save(tmp_path / "local")
    assert json.loads((tmp_path / "local" / "map.json").read_text())["geo_frame"] is None
    assert SatelliteMap.load(tmp_path / "local").frame is None

    shutil.copytree(tmp_path / "local", tmp_path / "old")  # a map.json written before the key existed
    meta = json.loads((tmp_path / "old" / "map.json").read_text())
    del meta["geo_frame"]
    (tmp_path / "old" / "map.json").write_text(json.dumps(meta))
    old = SatelliteMap.load(tmp_path / "old")
    assert old.frame is None and np.array_equal(old.image, img)

    meta["geo_frame"] = {"type": "utm", "zone": 32}
    (tmp_path / "old" / "map.json").write_text(json.dumps(meta))
    with pytest.raises(FormatError, match=r"old/map.json: geo_frame: expected \{type: mercator_scaled"):
        SatelliteMap.load(tmp_path / "old")


def test_lonlat_pixel_methods():
    sm = SatelliteMap(np.zeros((100, 200, 3), np.uint8), 0.5, (-50.0, 25.0), frame=REF)
    ll = np.array([[REF.lon0, REF.lat0], [8.4305, 49.0101]])
    uv = sm.lonlat_to_pixel(ll)
    assert np.allclose(uv[0], [99.5, 49.5])  # the frame origin: 50 m east, 25 m south of the corner
    assert np.allclose(sm.pixel_to_lonlat(uv), ll, atol=1e-10, rtol=0)
    local = SatelliteMap(np.zeros((10, 10, 3), np.uint8), 0.5)
    with pytest.raises(ConfigError, match="lonlat_to_pixel: this map has no geo frame"):
        local.lonlat_to_pixel(ll)
    with pytest.raises(ConfigError, match="pixel_to_lonlat: this map has no geo frame"):
        local.pixel_to_lonlat(uv)
    with pytest.raises(ConfigError, match="SatelliteMap.frame"):
        SatelliteMap(np.zeros((10, 10, 3), np.uint8), 0.5, frame={"lon0": 8.4})


def test_check_covers():
    sm = SatelliteMap(np.zeros((100, 200, 3), np.uint8), 0.5, (0.0, 50.0))  # x [0, 100], y [0, 50]
    inside = np.array([[20.0, 20.0], [90.0, 40.0]])
    sm.check_covers(inside, "sequence 'kitti_0023' poses")
    sm.check_covers(inside, "poses", margin_m=5.0)
    with pytest.raises(ConfigError, match=r"poses: 1 of 2 points lie outside .*5 m margin.*#1 at \(90.0, 40.0\)"):
        sm.check_covers(inside, "poses", margin_m=10.0 + 0.5)
    pts = np.array([[10.0, 10.0], [120.0, 10.0], [130.0, 60.0], [50.0, 20.0]])
    with pytest.raises(ConfigError) as e:
        sm.check_covers(pts, "sequence 'kitti_0023' poses")
    msg = str(e.value)
    assert msg.startswith("sequence 'kitti_0023' poses: 2 of 4 points lie outside the satellite map")
    assert "#1 at (120.0, 10.0)" in msg
    assert "x [10.0, 130.0] y [10.0, 60.0]" in msg and "x [0.0, 100.0] y [0.0, 50.0]" in msg
    with pytest.raises(ConfigError, match="expected"):
        sm.check_covers(np.zeros(3), "poses")
    sm.check_covers(np.zeros((0, 2)), "poses")  # nothing to check


def test_map_bounds_input_files_and_aligned_bands(tmp_path, inputs):
    from satloc.geodata.georef import input_files, is_georeferenced, map_bounds, reproject_band

    for kind in ("geotiff_utm", "jpg_world_rotated", "xyz_tiles"):
        sm = load_map(inputs[kind], mpp=1.0)               # map_bounds: the same frame and extent, no pixels
        frame, mpp, (x0, y0, x1, y1) = map_bounds(inputs[kind], 1.0)
        assert frame == sm.frame and mpp == 1.0
        assert (x0, x1, y0, y1) == pytest.approx(sm.extent, abs=1e-6), kind
    assert map_bounds(inputs["geotiff_utm"])[1] == 0.5
    # the files a load reads: the image and its sidecars; every tile of the level
    path, img, tr = make_world_image(tmp_path / "w.png", UTM)
    assert input_files(path) == [path, tmp_path / "w.pgw", tmp_path / "w.prj"]
    assert input_files(inputs["geotiff_utm"]) == [inputs["geotiff_utm"]]
    root, written = make_tiles(tmp_path / "t", zoom=16)
    coarse = make_tiles(tmp_path / "t", zoom=15)[1]
    assert input_files(root) == sorted(root / "16" / str(x) / f"{y}.png" for x, y in written)
    assert len(input_files(root, zoom=15)) == len(coarse)
    assert input_files(tmp_path / "nothing.tif") == []
    # a band aligned with the image (its red channel) lands where the image's own pixels land
    sm = load_map(path, 1.0, frame=REF)
    red = reproject_band(img[..., 0], path, sm, resampling="average")   # as load_map at 2x its source pixel
    assert red.shape == sm.shape[:2] and np.abs(red.astype(int) - sm.image[..., 0].astype(int)).max() <= 2
    with pytest.raises(ConfigError, match=r"mask.png is 10x8 px, but the image w.png is 800x600 px"):
        reproject_band(np.zeros((8, 10), np.uint8), path, sm, what="mask.png")
    # georeferenced or plain
    write_image(tmp_path / "plain.png", np.zeros((8, 8, 3), np.uint8))
    write_geotiff(tmp_path / "plain.tif", np.zeros((8, 8, 3), np.uint8), Affine.identity())
    (tmp_path / "junk.tif").write_bytes(b"junk")
    assert is_georeferenced(path) and is_georeferenced(inputs["geotiff_4326"])
    assert is_georeferenced(tmp_path / "plain.png", crs=UTM)
    assert not any(is_georeferenced(tmp_path / n) for n in ("plain.png", "plain.tif", "junk.tif"))
