"""Georeferenced test images of our own making, in the formats :mod:`satloc.geodata.georef` reads.

Every fixture paints one ground pattern, defined on lon/lat, over the same box near Karlsruhe (the KITTI
area): each pixel's centre is taken to lon/lat through pyproj and coloured by :func:`texture`, so the
GeoTIFFs in EPSG:4326, EPSG:3857 and UTM 32N, the PNG + world file and the XYZ tiles are independent
renderings of the same ground, not reprojections of one another. The pattern is a checker of 8 m cells with
a colour per cell (every channel in [60, 190]) and discs of 4 m radius in pure red, green and blue at the
lon/lat of :data:`MARKS`, which :func:`find_mark` locates in a loaded map.

Import from a test module as ``from geofixtures import ...`` (pytest puts ``tests/`` on ``sys.path``).
"""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pyproj
from affine import Affine

from satloc.geodata.georef import write_geotiff, write_world_file
from satloc.geoframe import GeoFrame

LON0, LAT0 = 8.43, 49.01
REF = GeoFrame(LON0, LAT0)  # the frame the pattern is defined in (metres east/north of LON0, LAT0)
HALF_W, HALF_H = 200.0, 150.0  # the box: 400 m x 300 m around (LON0, LAT0)
BOX_LONLAT = tuple(REF.to_lonlat(np.array([-HALF_W, -HALF_H]))) + tuple(REF.to_lonlat(np.array([HALF_W, HALF_H])))
CELL_M = 8.0
MARK_RADIUS_M = 4.0
# (name, lon/lat, colour): inside the box, away from its edges
MARKS = [
    ("red", tuple(REF.to_lonlat(np.array([-123.0, 61.0]))), (255, 0, 0)),
    ("green", tuple(REF.to_lonlat(np.array([37.5, -88.25]))), (0, 255, 0)),
    ("blue", tuple(REF.to_lonlat(np.array([141.3, 97.7]))), (0, 0, 255)),
]
UTM = "EPSG:32632"  # UTM zone 32N: Karlsruhe


def texture(lon, lat) -> np.ndarray:
    """(..., 3) uint8 colour of the ground at WGS84 lon/lat (degrees)."""
    xy = REF.to_map(np.stack([np.asarray(lon, np.float64), np.asarray(lat, np.float64)], axis=-1))
    i = np.floor(xy[..., 0] / CELL_M).astype(np.int64)
    j = np.floor(xy[..., 1] / CELL_M).astype(np.int64)
    h = (i * 73856093) ^ (j * 19349663)
    rgb = np.stack([60 + (h >> s) % 131 for s in (3, 11, 19)], axis=-1).astype(np.uint8)
    for _, ll, colour in MARKS:
        c = REF.to_map(np.array(ll))
        inside = np.hypot(xy[..., 0] - c[0], xy[..., 1] - c[1]) <= MARK_RADIUS_M
        rgb[inside] = colour
    return rgb


def paint(transform: Affine, width: int, height: int, crs) -> np.ndarray:
    """(height, width, 3) image of the pattern; pixel (col, row) has its centre at (col + .5, row + .5)."""
    cols, rows = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    x, y = _apply(transform, cols, rows)
    lon, lat = pyproj.Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(x, y)
    return texture(lon, lat)


def grid(crs, gsd_m: float = 0.5, rotation_deg: float = 0.0, margin_m: float = 0.0):
    """A (transform, width, height) over the box in ``crs`` at about ``gsd_m`` ground metres per pixel.

    The grid is north up in ``crs`` (rotated by ``rotation_deg`` counter-clockwise about the box centre if
    given); ``margin_m`` widens the box.
    """
    to = pyproj.Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    corners = REF.to_lonlat(np.array([[-HALF_W - margin_m, -HALF_H - margin_m],
                                      [HALF_W + margin_m, HALF_H + margin_m]]))
    xs, ys = to.transform(corners[:, 0], corners[:, 1])
    width = int(round((2 * HALF_W + 2 * margin_m) / gsd_m))
    height = int(round((2 * HALF_H + 2 * margin_m) / gsd_m))
    sx, sy = (xs[1] - xs[0]) / width, (ys[1] - ys[0]) / height
    tr = Affine(sx, 0.0, xs[0], 0.0, -sy, ys[1])
    if rotation_deg:
        cx, cy = _apply(tr, width / 2, height / 2)
        tr = _compose(Affine.translation(cx, cy), Affine.rotation(rotation_deg), Affine.translation(-cx, -cy), tr)
    return tr, width, height


def make_geotiff(path, crs, gsd_m: float = 0.5, bands: str = "rgb",
                 **grid_kw) -> tuple[Path, np.ndarray, Affine]:
    """Write the pattern as a GeoTIFF in ``crs`` (``bands``: rgb, grey or rgba; ``crs=None``: no CRS)."""
    tr, w, h = grid(crs or UTM, gsd_m, **grid_kw)
    img = _bands(paint(tr, w, h, crs or UTM), bands)
    write_geotiff(path, img, tr, crs)
    return Path(path), img, tr


def write_raster(path, bands: np.ndarray, transform: Affine, crs=UTM, **profile) -> Path:
    """Write (count, H, W) samples of any type as a GeoTIFF with rasterio (``profile``: creation options such
    as ``nodata``, ``photometric``, ``alpha``; ``colorinterp``: a list of ``rasterio.enums.ColorInterp``)."""
    import rasterio

    colorinterp = profile.pop("colorinterp", None)
    prof = dict(driver="GTiff", width=bands.shape[2], height=bands.shape[1], count=bands.shape[0],
                dtype=bands.dtype.name, transform=transform, crs=crs, compress="deflate", **profile)
    with rasterio.Env(GDAL_PAM_ENABLED="NO"), rasterio.open(path, "w", **prof) as dst:
        dst.write(bands)
        if colorinterp is not None:
            dst.colorinterp = colorinterp
    return Path(path)


def make_world_image(path, crs, gsd_m: float = 0.5, prj: bool = True, bands: str = "rgb",
                     world_name: str | None = None, **grid_kw) -> tuple[Path, np.ndarray, Affine]:
    """Write the pattern as a plain image (PNG/JPEG by suffix) + world file (+ ``.prj`` in WKT)."""
    path = Path(path)
    tr, w, h = grid(crs, gsd_m, **grid_kw)
    img = _bands(paint(tr, w, h, crs), bands)
    write_image(path, img)
    ext = path.suffix[1:]
    write_world_file(path.with_name(world_name or f"{path.stem}.{ext[0]}{ext[-1]}w"), tr)
    if prj:
        path.with_suffix(".prj").write_text(pyproj.CRS.from_user_input(crs).to_wkt(pyproj.enums.WktVersion.WKT1_ESRI))
    return path, img, tr


def make_tiles(root, zoom: int = 18, ext: str = "png", skip: tuple[int, int] | None = None) -> tuple[Path, list]:
    """Write the XYZ tiles (256 px, EPSG:3857) at ``zoom`` that cover the box; ``skip`` leaves one out."""
    root = Path(root)
    half = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:3857", always_xy=True).transform(180.0, 0.0)[0]
    tile_m = 2 * half / 2 ** zoom
    to = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:3857", always_xy=True)
    (x0, x1), (y0, y1) = to.transform([BOX_LONLAT[0], BOX_LONLAT[2]], [BOX_LONLAT[1], BOX_LONLAT[3]])
    tx = range(int((x0 + half) // tile_m), int((x1 + half) // tile_m) + 1)
    ty = range(int((half - y1) // tile_m), int((half - y0) // tile_m) + 1)
    written = []
    for x in tx:
        for y in ty:
            if (x, y) == skip:
                continue
            tr = Affine(tile_m / 256, 0.0, -half + x * tile_m, 0.0, -tile_m / 256, half - y * tile_m)
            f = root / str(zoom) / str(x) / f"{y}.{ext}"
            f.parent.mkdir(parents=True, exist_ok=True)
            write_image(f, paint(tr, 256, 256, "EPSG:3857"))
            written.append((x, y))
    return root, written


def write_image(path, img: np.ndarray) -> None:
    """Write an RGB, RGBA or grey uint8 array with OpenCV (PNG/JPEG by suffix)."""
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR if img.shape[2] == 3 else cv2.COLOR_RGBA2BGRA)
    params = [cv2.IMWRITE_JPEG_QUALITY, 98] if Path(path).suffix.lower() in (".jpg", ".jpeg") else []
    if not cv2.imwrite(str(path), img, params):
        raise OSError(f"{path}: could not write image")


def _apply(tr: Affine, x, y):
    return tr.a * x + tr.b * y + tr.c, tr.d * x + tr.e * y + tr.f


def _compose(*transforms: Affine) -> Affine:
    m = np.eye(3)
    for t in transforms:
        m = m @ np.asarray(tuple(t), np.float64).reshape(3, 3)
    return Affine(*m.ravel()[:6])


def _bands(rgb: np.ndarray, bands: str) -> np.ndarray:
    if bands == "rgb":
        return rgb
    if bands == "grey":
        return np.round(rgb.mean(axis=2)).astype(np.uint8)
    if bands == "rgba":  # the western half transparent
        a = np.full(rgb.shape[:2], 255, np.uint8)
        a[:, : rgb.shape[1] // 2] = 0
        return np.dstack([rgb, a])
    raise ValueError(bands)


def find_mark(image: np.ndarray, colour) -> tuple[float, float] | None:
    """Centroid (u, v) of the pixels of a pure-colour mark, or None when fewer than 5 are found."""
    img = image.astype(np.int16)
    on = np.asarray(colour) > 0
    sel = (img[..., on] > 220).all(axis=-1) & (img[..., ~on] < 40).all(axis=-1)
    v, u = np.nonzero(sel)
    if len(u) < 5:
        return None
    return float(u.mean()), float(v.mean())


def mark_errors(satmap) -> dict[str, float]:
    """Pixel distance between each mark found in the map and ``lonlat_to_pixel`` of its lon/lat."""
    out = {}
    for name, ll, colour in MARKS:
        found = find_mark(satmap.image, colour)
        want = satmap.lonlat_to_pixel(np.array(ll))
        out[name] = math.inf if found is None else float(np.hypot(found[0] - want[0], found[1] - want[1]))
    return out
