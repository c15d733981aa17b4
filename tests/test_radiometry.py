"""Radiometry of georeferenced imagery (satloc.geodata.radiometry through satloc.geodata.georef.load_map): any bit depth and
band count, band selection, nodata / alpha / NaN masks, the per-band stretch (recorded, overridable), the
warnings for pictures that come out dark or constant, scenes' ``bands:``/``stretch:``, and GeoTIFFs read
without OpenCV's TIFF tag warnings.

The imagery is the ground pattern of :mod:`geofixtures` (colours in 60..190) written in other sample types
and band layouts, so each load can be compared with the 8-bit load of the same ground.
"""
from __future__ import annotations

import json
import re
import warnings

import cv2
import numpy as np
import pytest
import yaml
from geofixtures import REF, UTM, grid, make_geotiff, paint, write_image, write_raster
from rasterio.enums import ColorInterp

from satloc import ConfigError, FormatError, SatelliteMap, SatlocWarning
from satloc.geodata.georef import load_map, save_geotiff, write_geotiff
from satloc.geodata.radiometry import Radiometry
from satloc.satmap import read_image

GSD = 2.0   # metres per source pixel: small rasters, quick loads


@pytest.fixture(scope="module")
def ground():
    """(transform, rgb (H, W, 3) uint8) of the pattern in UTM at GSD."""
    tr, w, h = grid(UTM, GSD)
    return tr, paint(tr, w, h, UTM)


def _bands(rgb: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(rgb.transpose(2, 0, 1))


def _grey(rgb: np.ndarray) -> np.ndarray:
    return np.round(rgb.mean(axis=2)).astype(np.uint8)


def _load(path, **kw):
    """load_map at the source resolution in the pattern's frame, warnings recorded."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sm = load_map(path, GSD, frame=REF, **kw)
    return sm, [w for w in caught if issubclass(w.category, SatlocWarning)]


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.corrcoef(a.astype(np.float64).ravel(), b.astype(np.float64).ravel())[0, 1])


def _at_source_px(sm: SatelliteMap, tr, cols, rows) -> np.ndarray:
    """The map's colours (n, 3) at the centres of source pixels (cols, rows) of a UTM raster with transform tr."""
    import pyproj

    x, y = tr.a * (np.asarray(cols) + 0.5) + tr.c, tr.e * (np.asarray(rows) + 0.5) + tr.f
    lon, lat = pyproj.Transformer.from_crs(UTM, "EPSG:4326", always_xy=True).transform(x, y)
    uv = np.round(sm.lonlat_to_pixel(np.stack([lon, lat], -1))).astype(int)
    return sm.image[uv[:, 1], uv[:, 0]]


def _spans_most(img: np.ndarray) -> bool:
    lo, hi = np.percentile(img, [1, 99])
    return lo < 25 and hi > 230


# --- sample types and band layouts -----------------------------------------------------------------------
def test_eleven_bit_single_band_comes_out_as_sane_grey(tmp_path, ground):
    tr, rgb = ground
    eleven = (_grey(rgb).astype(np.uint16) - 60) * 15       # 0..1950: 11-bit data in 16-bit samples
    path = write_raster(tmp_path / "pan11.tif", eleven[None], tr)
    sm, caught = _load(path)
    img = sm.image
    assert (img[..., 0] == img[..., 1]).all() and (img[..., 1] == img[..., 2]).all()
    assert _spans_most(img) and not caught
    ref = load_map(write_raster(tmp_path / "pan8.tif", _grey(rgb)[None], tr), GSD, frame=REF)
    assert _corr(img[..., 0], ref.image[..., 0]) > 0.99
    r = sm.radiometry
    assert r["dtype"] == "uint16" and r["bands"] == [1] and r["stretch"] == "auto"
    assert r["percentiles"] == [0.5, 99.5] and len(r["levels"]) == 1
    lo, hi = r["levels"][0]
    assert 0 <= lo < 400 and 1500 < hi <= 1950

    # stretch: none is the old scaling by 1/257 (rounded): 11-bit data lands at 0..8, and says so
    old, caught = _load(path, radiometry=Radiometry(stretch="none"))
    assert old.image.max() <= 8 and old.radiometry["levels"] == [[0.0, 65535.0]]
    assert len(caught) == 1 and "pan11.tif" in str(caught[0].message) and "mostly dark" in str(caught[0].message)
    scaled = ((eleven.astype(np.uint32) * 255 + 32767) // 65535).astype(np.uint8)
    same, _ = _load(write_raster(tmp_path / "scaled.tif", scaled[None], tr))
    assert np.array_equal(old.image, same.image)


def test_sixteen_bit_rgba(tmp_path, ground):
    tr, rgb = ground
    w = rgb.shape[1]
    a16 = _bands(rgb).astype(np.uint16) * 30                 # 1800..5700: 13-bit data
    a16[:, :, : w // 2] = 65535                               # under alpha 0: must not count in the stretch
    alpha = np.full(rgb.shape[:2], 65535, np.uint16)
    alpha[:, : w // 2] = 0
    path = write_raster(tmp_path / "rgba16.tif", np.concatenate([a16, alpha[None]]), tr, photometric="RGB",
                        alpha="YES")   # unassociated alpha: ExtraSamples says so
    sm, caught = _load(path)
    assert not caught and sm.radiometry["alpha_band"] == 4 and sm.radiometry["bands"] == [1, 2, 3]
    assert all(hi <= 5700 for _, hi in sm.radiometry["levels"])
    assert sm.radiometry["valid_fraction"] == pytest.approx(0.5, abs=0.01)
    write_geotiff(tmp_path / "rgb8.tif", rgb, tr, UTM)
    ref = load_map(tmp_path / "rgb8.tif", GSD, frame=REF)
    # the transparent western half is black, the eastern half is the 8-bit picture, stretched
    rows = np.arange(5, rgb.shape[0] - 5, 7)
    assert _at_source_px(sm, tr, np.full(rows.shape, w // 2 - 3), rows).max() == 0
    assert _at_source_px(sm, tr, np.full(rows.shape, 5), rows).max() == 0
    east = sm.image[:, -sm.shape[1] // 3:]
    for c in range(3):
        assert _corr(east[..., c], ref.image[:, -sm.shape[1] // 3:, c]) > 0.99
    assert _spans_most(east)


def test_nodata_is_masked_and_left_out_of_the_stretch(tmp_path, ground):
    tr, rgb = ground
    eleven = (_grey(rgb).astype(np.uint16) - 60) * 15 + 10
    eleven[:20, :] = 65535                                    # a nodata band along the north edge
    eleven[-20:, :] = 0                                       # valid zeros: counted
    path = write_raster(tmp_path / "nd.tif", eleven[None], tr, nodata=65535)
    sm, caught = _load(path)
    assert not caught
    lo, hi = sm.radiometry["levels"][0]
    assert hi <= 1960 and lo == 0.0 and sm.radiometry["valid_fraction"] < 0.95
    # the nodata rows are black; the others are not (grey 60..190 stretches to well above 0)
    cols = np.arange(5, rgb.shape[1] - 5, 7)
    assert _at_source_px(sm, tr, cols, np.full(cols.shape, 17)).max() == 0
    assert _at_source_px(sm, tr, cols, np.full(cols.shape, 24)).min() > 0
    # the map says which pixels hold imagery: not the nodata rows; the valid zeros do
    import pyproj

    def valid_at(rows):
        x, y = tr.a * (cols + 0.5) + tr.c, tr.e * (np.full(cols.shape, rows) + 0.5) + tr.f
        lon, lat = pyproj.Transformer.from_crs(UTM, "EPSG:4326", always_xy=True).transform(x, y)
        uv = np.round(sm.lonlat_to_pixel(np.stack([lon, lat], -1))).astype(int)
        return sm.valid[uv[:, 1], uv[:, 0]]

    assert sm.valid is not None and not valid_at(17).any() and valid_at(24).all() and valid_at(rgb.shape[0] - 5).all()
    assert 0.8 < sm.valid.mean() < 0.95


def test_internal_mask(tmp_path, ground):
    import rasterio

    tr, rgb = ground
    b = _bands(rgb).astype(np.uint16) * 16
    b[:, :, :30] = 65535                                      # masked off: must not count in the stretch
    path = write_raster(tmp_path / "masked.tif", b, tr, photometric="RGB")
    with rasterio.open(path, "r+") as ds:
        valid = np.full(rgb.shape[:2], 255, np.uint8)
        valid[:, :30] = 0
        ds.write_mask(valid)
    assert not (tmp_path / "masked.tif.msk").exists()        # an internal mask
    sm, caught = _load(path)
    assert not caught and all(hi <= 190 * 16 for _, hi in sm.radiometry["levels"]) and _spans_most(sm.image)
    rows = np.arange(5, rgb.shape[0] - 5, 7)
    assert _at_source_px(sm, tr, np.full(rows.shape, 25), rows).max() == 0


def test_float_with_nan(tmp_path, ground):
    tr, rgb = ground
    refl = _bands(rgb).astype(np.float32) / 255 * 0.4         # reflectance 0.09..0.3
    refl[:, 30:50, 40:80] = np.nan
    path = write_raster(tmp_path / "refl.tif", refl, tr, photometric="RGB")
    sm, caught = _load(path)
    assert not caught and sm.radiometry["dtype"] == "float32" and _spans_most(sm.image)
    assert all(0.09 <= lo < hi <= 0.3 for lo, hi in sm.radiometry["levels"])
    cols, rows = np.meshgrid(np.arange(42, 78, 5), np.arange(32, 48, 5))
    assert _at_source_px(sm, tr, cols.ravel(), rows.ravel()).max() == 0     # NaN: invalid, black
    # float none: 0..1 -> 0..255, so reflectance stays dark (and says so)
    none, caught = _load(path, radiometry=Radiometry(stretch="none"))
    assert none.image.max() <= 0.4 * 255 + 1


def test_five_bands_need_bands(tmp_path, ground):
    tr, rgb = ground
    b = _bands(rgb).astype(np.uint16) * 16
    nir = (b.mean(axis=0) * 0.5).astype(np.uint16)
    five = np.stack([b[2], b[1], b[0], nir, np.full_like(nir, 7)])   # blue, green, red, NIR, a constant
    path = write_raster(tmp_path / "five.tif", five, tr)
    with pytest.raises(ConfigError, match=r"bands: .*five\.tif has 5 bands .*bands: \[r, g, b\]"):
        load_map(path, GSD, frame=REF)
    sm, caught = _load(path, radiometry=Radiometry(bands=[3, 2, 1]))
    assert not caught and sm.radiometry["bands"] == [3, 2, 1]
    ref = load_map(make_geotiff(tmp_path / "rgb.tif", UTM, gsd_m=GSD)[0], GSD, frame=REF)
    for c in range(3):
        assert _corr(sm.image[..., c], ref.image[..., c]) > 0.99
    grey, _ = _load(path, radiometry=Radiometry(bands=4))
    assert (grey.image[..., 0] == grey.image[..., 2]).all() and grey.radiometry["bands"] == [4]
    # GDAL's colour interpretation names the bands: then no bands: is needed
    named = write_raster(tmp_path / "named.tif", five, tr, colorinterp=[
        ColorInterp.blue, ColorInterp.green, ColorInterp.red, ColorInterp.nir, ColorInterp.undefined])
    sm2, _ = _load(named)
    assert sm2.radiometry["bands"] == [3, 2, 1] and np.array_equal(sm2.image, sm.image)


def test_four_bands_whose_fourth_is_not_alpha(tmp_path, ground):
    tr, rgb = ground
    b = _bands(rgb).astype(np.uint16) * 16
    nir = np.zeros_like(b[0])                                 # as alpha, it would make everything transparent
    path = write_raster(tmp_path / "rgbn.tif", np.concatenate([b, nir[None]]), tr, photometric="RGB",
                        colorinterp=[ColorInterp.red, ColorInterp.green, ColorInterp.blue, ColorInterp.nir])
    sm, caught = _load(path)
    assert not caught and sm.radiometry["alpha_band"] is None and _spans_most(sm.image)


def test_a_fourth_band_the_file_leaves_undefined_is_not_alpha(tmp_path, ground):
    """RGB + NIR as orthophotos come (uint16, ExtraSamples unspecified: GDAL calls band 4 undefined): read as
    RGB with a one-line warning naming the choice and how to change it; alpha: 4 makes it alpha."""
    import rasterio

    tr, rgb = ground
    b = _bands(rgb).astype(np.uint16) * 16
    nir = np.zeros_like(b[0])                                 # as alpha, it would make everything black
    nir[:, : nir.shape[1] // 2] = 65535
    path = write_raster(tmp_path / "rgbn16.tif", np.concatenate([b, nir[None]]), tr, photometric="RGB")
    with rasterio.open(path) as ds:
        assert ds.colorinterp[3] == ColorInterp.undefined
    sm, caught = _load(path)
    assert sm.radiometry["alpha_band"] is None and _spans_most(sm.image)
    assert len(caught) == 1 and "band 4 of 4 is read as an extra band" in str(caught[0].message)
    assert "set alpha: 4" in str(caught[0].message)
    as_alpha, _ = _load(path, radiometry=Radiometry(alpha=4))
    assert as_alpha.radiometry["alpha_band"] == 4
    west = as_alpha.image[:, : as_alpha.image.shape[1] // 3]
    east = as_alpha.image[:, -as_alpha.image.shape[1] // 3:]
    assert east.max() == 0 and west.mean() > 20          # composited over black where "alpha" is 0
    none, caught = _load(path, radiometry=Radiometry(alpha="none"))
    assert none.radiometry["alpha_band"] is None and not caught
    with pytest.raises(ConfigError, match="alpha: .* has 4 bands, so band 5 does not exist"):
        _load(path, radiometry=Radiometry(alpha=5))
    with pytest.raises(ConfigError, match="alpha: expected 'auto'"):
        Radiometry(alpha="yes")


def test_explicit_stretch(tmp_path, ground):
    tr, rgb = ground
    eleven = _bands(rgb).astype(np.uint16) * 8
    path = write_raster(tmp_path / "e.tif", eleven, tr, photometric="RGB")
    sm, _ = _load(path, radiometry=Radiometry(stretch=[0, 2047]))
    ref = load_map(make_geotiff(tmp_path / "rgb.tif", UTM, gsd_m=GSD)[0], GSD, frame=REF)
    assert sm.radiometry["stretch"] == "explicit" and sm.radiometry["levels"] == [[0.0, 2047.0]] * 3
    # x * 8 / 2047 * 255 is within one level of x
    assert np.abs(sm.image.astype(int) - ref.image.astype(int)).max() <= 2
    per_band = Radiometry(stretch=[[480, 1520], [0, 2047], [0, 4095]])
    sm2, _ = _load(path, radiometry=per_band)
    assert sm2.image[..., 0].mean() > sm.image[..., 0].mean() > sm2.image[..., 2].mean()
    assert sm2.image[..., 1].tolist() == sm.image[..., 1].tolist()
    with pytest.raises(ConfigError, match=r"stretch: 3 ranges for the 1 band read from .*grey\.tif"):
        load_map(write_raster(tmp_path / "grey.tif", eleven[:1], tr), GSD, frame=REF, radiometry=per_band)
    # an explicit stretch applies to 8-bit imagery too
    sm8, _ = _load(tmp_path / "rgb.tif", radiometry=Radiometry(stretch=[60, 190]))
    assert _spans_most(sm8.image)


def test_eight_bit_default_is_unchanged_byte_for_byte(tmp_path):
    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)
    sm = SatelliteMap(img, 0.5, (-20.0, 15.0), frame=REF)     # on the frame's 0.5 m lattice: no resampling
    save_geotiff(sm, tmp_path / "rgb.tif")
    back, caught = _load_native(tmp_path / "rgb.tif")
    assert np.array_equal(back.image, img) and not caught
    assert back.radiometry["levels"] == [[0.0, 255.0]] * 3 and back.radiometry["dtype"] == "uint8"
    # RGBA: composited over black by alpha exactly as before: (v * a + 127) // 255
    alpha = rng.integers(0, 256, img.shape[:2], dtype=np.uint8)
    from affine import Affine

    tr = Affine(0.5, 0.0, -20.0, 0.0, -0.5, 15.0)
    write_geotiff(tmp_path / "rgba.tif", np.dstack([img, alpha]), tr, REF.crs)
    rgba, _ = _load_native(tmp_path / "rgba.tif")
    want = ((img.astype(np.uint16) * alpha[..., None] + 127) // 255).astype(np.uint8)
    assert np.array_equal(rgba.image, want)
    grey = img[..., 0]
    write_geotiff(tmp_path / "grey.tif", grey, tr, REF.crs)
    assert np.array_equal(_load_native(tmp_path / "grey.tif")[0].image, np.dstack([grey] * 3))


def _load_native(path):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sm = load_map(path, 0.5, frame=REF)
    return sm, [w for w in caught if issubclass(w.category, SatlocWarning)]


def test_sixteen_bit_tiles_are_stretched_once(tmp_path):
    from geofixtures import make_tiles

    root, written = make_tiles(tmp_path / "t", zoom=16)
    for f in (root / "16").rglob("*.png"):                   # the same tiles as 11-bit PNGs
        bgr = cv2.imread(str(f), cv2.IMREAD_COLOR)
        cv2.imwrite(str(f), bgr.astype(np.uint16) * 8)
    sm, caught = _load(root)
    assert not caught and sm.radiometry["dtype"] == "uint16" and _spans_most(sm.image)
    f = next((root / "16").rglob("*.png"))
    cv2.imwrite(str(f), (cv2.imread(str(f), cv2.IMREAD_UNCHANGED) // 8).astype(np.uint8))
    with pytest.raises(FormatError, match=rf"{re.escape(f.name)}: tile of uint8 samples; .* uint16"):
        load_map(root, GSD, frame=REF)


# --- warnings --------------------------------------------------------------------------------------------
def test_constant_and_dark_pictures_are_warned_about_by_name(tmp_path, ground):
    tr, rgb = ground
    const = np.full((1, *rgb.shape[:2]), 1234, np.uint16)
    _, caught = _load(write_raster(tmp_path / "flat.tif", const, tr))
    assert len(caught) == 1 and re.search(r"flat\.tif: is nearly constant", str(caught[0].message))
    dark = (_bands(rgb) // 8).astype(np.uint8)               # 8-bit, 7..23: shown as stored, so dark
    _, caught = _load(write_raster(tmp_path / "dark.tif", dark, tr, photometric="RGB"))
    assert len(caught) == 1 and re.search(r"dark\.tif: is mostly dark after conversion to 8 bits .*set stretch",
                                          str(caught[0].message))
    _, caught = _load(write_raster(tmp_path / "darker.tif", dark // 4, tr, photometric="RGB"))
    assert len(caught) == 1 and "darker.tif: is mostly dark and nearly constant" in str(caught[0].message)
    empty = np.zeros((1, *rgb.shape[:2]), np.uint16)
    _, caught = _load(write_raster(tmp_path / "empty.tif", empty, tr, nodata=0))
    assert len(caught) == 1 and "empty.tif: has no valid pixel" in str(caught[0].message)


# --- bad values ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("bands", [0, [0], [1, 2], [1, 2, 3, 4], ["r", "g", "b"], [True], [1.5]])
def test_bad_bands(bands):
    with pytest.raises(ConfigError, match=r"^bands: expected 1 band \(grey\) or 3 bands"):
        Radiometry(bands=bands)


@pytest.mark.parametrize("stretch", ["linear", "", [], [1], [5, 1], [0, float("nan")], [[0, 1], [0, 1]],
                                     [[0, 1], 3, [0, 1]], None])
def test_bad_stretch(stretch):
    with pytest.raises(ConfigError, match=r"^stretch: expected 'auto', 'none'"):
        Radiometry(stretch=stretch)


def test_band_out_of_range_names_the_file(tmp_path, ground):
    tr, rgb = ground
    path = write_raster(tmp_path / "pan.tif", _grey(rgb)[None], tr)
    with pytest.raises(ConfigError, match=r"bands: .*pan\.tif has 1 band, so band 2 does not exist"):
        load_map(path, GSD, frame=REF, radiometry=Radiometry(bands=[2]))
    with pytest.raises(ConfigError, match="radiometry: expected a satloc.geodata.radiometry.Radiometry"):
        load_map(path, GSD, frame=REF, radiometry={"bands": [1]})


# --- scenes ----------------------------------------------------------------------------------------------
def _scene_yaml(tmp_path, image: str, name: str = "s.yaml", **generator) -> str:
    p = tmp_path / name      # load_scene caches by path: one name per scene
    p.write_text(yaml.safe_dump({
        "name": "eleven", "meters_per_pixel": GSD, "ground_mpp": GSD,
        "knobs": {"satellite_gap": 0.0},   # the map is the image itself: its radiometry is what is checked
        "generator": {"type": "image", "image": image, **generator},
        "routes": {"main": {"lonlat": [REF.to_lonlat(np.array([-80.0, -40.0])).tolist(),
                                       REF.to_lonlat(np.array([80.0, 40.0])).tolist()]}}}))
    return str(p)


def test_scene_with_bands_and_stretch(tmp_path, ground, capsys):
    from satloc_env.cli import main
    from satloc_env.world.scene import load_scene

    tr, rgb = ground
    b = _bands(rgb).astype(np.uint16) * 8
    write_raster(tmp_path / "five.tif", np.stack([b[2], b[1], b[0], b[0] // 2, b[1] // 2]), tr)
    path = _scene_yaml(tmp_path, "five.tif", bands=[3, 2, 1], stretch=[480, 1520])
    scene = load_scene(path)
    r = scene.summary()["radiometry"]
    assert r["bands"] == [3, 2, 1] and r["levels"] == [[480.0, 1520.0]] * 3 and r["stretch"] == "explicit"
    assert _spans_most(scene.satmap.image)
    assert main(["scene", path, "--save", str(tmp_path / "saved")]) == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed["radiometry"] == r and printed["scene"] == "eleven"
    saved = json.loads((tmp_path / "saved" / "tile" / "map.json").read_text())
    assert saved["radiometry"] == r
    assert SatelliteMap.load(tmp_path / "saved" / "tile").radiometry == r
    # the default: the auto stretch, recorded
    auto = load_scene(_scene_yaml(tmp_path, "five.tif", "auto.yaml", bands=[3, 2, 1]))
    assert auto.summary()["radiometry"]["stretch"] == "auto" and _spans_most(auto.satmap.image)


@pytest.mark.parametrize("generator, match", [
    ({"bands": [0]}, r"s\.yaml: generator\.bands: expected 1 band"),
    ({"bands": [1, 2]}, r"s\.yaml: generator\.bands: expected 1 band"),
    ({"bands": [9]}, r"s\.yaml: generator\.bands: bands: .*five\.tif has 5 bands, so band 9 does not exist"),
    ({}, r"s\.yaml: generator\.bands: bands: .*five\.tif has 5 bands .*bands: \[r, g, b\]"),
    ({"bands": [1], "stretch": "max"}, r"s\.yaml: generator\.stretch: expected 'auto', 'none'"),
    ({"bands": [1], "stretch": [[0, 1], [0, 1], [0, 1]]}, r"generator\.stretch: stretch: 3 ranges for the 1 band"),
    ({"bands": [1], "gamma": 2}, r"unknown key\(s\) \['gamma'\]"),
])
def test_scene_bad_bands_and_stretch(tmp_path, ground, generator, match):
    from satloc_env.world.scene import load_scene

    tr, rgb = ground
    write_raster(tmp_path / "five.tif", np.repeat(_bands(rgb)[:1].astype(np.uint16), 5, axis=0), tr)
    with pytest.raises(ConfigError, match=match):
        load_scene(_scene_yaml(tmp_path, "five.tif", **generator))


def test_plain_image_scene_refuses_bands(tmp_path):
    from satloc_env.world.scene import load_scene

    write_image(tmp_path / "plain.png", np.full((100, 120, 3), 128, np.uint8))
    p = tmp_path / "p.yaml"
    p.write_text(yaml.safe_dump({"name": "p", "meters_per_pixel": 1.0, "ground_mpp": 1.0,
                                 "generator": {"type": "image", "image": "plain.png", "stretch": "none"},
                                 "routes": {"main": {"waypoints": [[10, 10], [90, 50]]}}}))
    with pytest.raises(ConfigError, match=r"generator\.stretch: .*plain\.png is not georeferenced"):
        load_scene(p)


def test_evaluate_config_fields():
    from satloc.config import from_dict
    from satloc_env.experiments.evaluate import EvaluateConfig

    cfg = from_dict(EvaluateConfig, {"satellite_bands": [3, 2, 1], "satellite_stretch": "none"})
    assert cfg.satellite_radiometry == Radiometry((3, 2, 1), "none")
    with pytest.raises(ConfigError, match=r"satellite_bands: expected 1 band"):
        from_dict(EvaluateConfig, {"satellite_bands": [0, 1, 2]})
    with pytest.raises(ConfigError, match=r"satellite_stretch: expected 'auto'"):
        from_dict(EvaluateConfig, {"satellite_stretch": "max"})


# --- OpenCV's TIFF tag warnings --------------------------------------------------------------------------
def test_geotiff_masks_are_read_without_tiff_tag_warnings(tmp_path, ground, capfd):
    """A road mask written as a GeoTIFF: OpenCV's libtiff prints a ``TIFF_Warning ... Unknown field with tag``
    line for each GeoTIFF tag; read_image hands GeoTIFFs to GDAL, with OpenCV's conventions."""
    tr, rgb = ground
    mask = np.zeros(rgb.shape[:2], np.uint8)
    mask[40:60, :] = 255
    write_geotiff(tmp_path / "roads.tif", mask, tr, UTM)
    write_geotiff(tmp_path / "rgb.tif", rgb, tr, UTM)
    data = (tmp_path / "roads.tif").read_bytes()
    capfd.readouterr()
    via_cv2 = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    opencv_warns = "Unknown field with tag" in capfd.readouterr().err   # as OpenCV is configured here
    grey = read_image(tmp_path / "roads.tif", grayscale=True)
    colour = read_image(tmp_path / "rgb.tif")
    err = capfd.readouterr().err
    assert "TIFF_Warning" not in err and "Unknown field with tag" not in err, err
    assert np.array_equal(grey, via_cv2) and np.array_equal(colour, rgb)
    (tmp_path / "cut.tif").write_bytes(data[: len(data) // 2])   # damaged: an error naming the file
    with pytest.raises(FormatError, match=r"cut\.tif: not a readable image"):
        read_image(tmp_path / "cut.tif", grayscale=True)
    if not opencv_warns:
        pytest.skip("this OpenCV does not print TIFF tag warnings: the silence above proves nothing")


def test_scene_with_a_geotiff_road_mask_prints_no_tiff_warnings(tmp_path, ground, capfd):
    from satloc_env.world.scene import load_scene

    tr, rgb = ground
    write_geotiff(tmp_path / "img.tif", rgb, tr, UTM)
    mask = np.zeros(rgb.shape[:2], np.uint8)
    mask[70:80, 20:-20] = 255
    write_geotiff(tmp_path / "roads.tif", mask, tr, UTM)
    capfd.readouterr()
    scene = load_scene(_scene_yaml(tmp_path, "img.tif", roads="roads.tif"))
    err = capfd.readouterr().err
    assert "TIFF_Warning" not in err and "Unknown field with tag" not in err, err
    assert scene.drivable.any() and scene.summary()["radiometry"]["dtype"] == "uint8"


def test_the_command_prints_a_warning_as_one_line(tmp_path, ground):
    """``satloc scene`` over a dark image: the warning is one ``satloc: warning:`` line naming the file, not
    Python's form (the internal file and line, then the source line); said again when the scene is read back
    from the disk cache (the second run), not only when it is built."""
    import os
    import subprocess
    import sys

    tr, rgb = ground
    write_raster(tmp_path / "dark.tif", (_bands(rgb) // 8).astype(np.uint8), tr, photometric="RGB")
    path = _scene_yaml(tmp_path, "dark.tif")
    env = {**os.environ, "SATLOC_CACHE": str(tmp_path / "cache"), "SATLOC_SCENE_CACHE": "1"}
    for run in ("built", "from the cache"):
        r = subprocess.run([sys.executable, "-m", "satloc_env.cli", "scene", path], capture_output=True, text=True,
                           timeout=300, env=env)
        assert r.returncode == 0, r.stderr
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1, (run, r.stderr)
        assert re.fullmatch(r"satloc: warning: .*dark\.tif: is mostly dark after conversion to 8 bits .*", lines[0])
        assert "SatlocWarning" not in r.stderr and ".py:" not in r.stderr
    assert len(list((tmp_path / "cache" / "scenes").glob("eleven-*/scene.json"))) == 1
