"""Georeferenced satellite input: GeoTIFFs, images with world files and XYZ tile folders as a :class:`SatelliteMap`.

:func:`load_map` reads any of

* a **GeoTIFF** (``.tif``/``.tiff``) in any CRS that rasterio reads (EPSG:4326, EPSG:3857, UTM, ...);
* a **plain image** (``.png``, ``.jpg``/``.jpeg``, or a ``.tif`` without an internal georeference) with a
  **world file** beside it: ``<stem>.pgw``/``.jgw``/``.tfw`` (first and last letter of the extension plus
  ``w``), ``<name>.<ext>w`` (``a.pngw``) or ``<stem>.wld``. The world file holds six numbers, one a line:
  A (x size of a pixel), D and B (rotation terms), E (y size, negative for north up), C and F (the
  coordinates of the *centre* of the top-left pixel). Its CRS comes from a ``<stem>.prj`` sidecar (WKT,
  ESRI WKT included) or the ``crs=`` argument (which wins over the sidecar);
* a **folder of Web-Mercator XYZ tiles** ``<folder>/<z>/<x>/<y>.png`` (or ``.jpg``/``.jpeg``; y counted
  from the north, as OpenStreetMap and most tile servers do, not TMS), mosaicked at one zoom: the highest
  present or ``zoom=``. The tiles are georeferenced in EPSG:3857 from their indices. A tile missing inside
  the area to load is an error naming it (never silently black): pass a ``region`` to load a part of an
  incompletely downloaded folder.

and reprojects the image with ``rasterio.warp.reproject`` (bilinear, or area averaging when the output is
coarser than the source) into a :class:`~satloc.geoframe.GeoFrame` at ``mpp`` metres per pixel, north up,
as an RGB uint8 map whose ``frame`` is set. rasterio and pyproj do every CRS conversion.

Output grid: pixel edges lie on multiples of ``mpp`` from the frame's origin, so maps loaded in one frame
at one resolution share their pixel lattice (a region's map is a crop of the whole map). Without a
``region`` the map is a north-up rectangle inside the image's footprint, bounded by the innermost reach of
each image edge (no black wedges where a UTM or rotated image does not reach): the whole image when it is
north up in the frame, nearly all of it when it is turned by a few degrees (UTM's grid convergence), but
much less than the largest inscribed rectangle when it is turned by tens of degrees (pass a ``region``
then). A ``region`` is widened outwards to the lattice and must lie in the image (within half an output
pixel). :func:`map_bounds` gives a load's frame, resolution and extent without reading pixels.

Radiometry (:mod:`satloc.geodata.radiometry`, chosen by ``radiometry=``): any integer or float sample type and any
band count. Grey (1 band) becomes three equal channels; grey + alpha and RGBA are composited over black (a
transparent pixel is black); a palette image is expanded through its colour table; more than four bands
take the bands GDAL interprets as red, green and blue, or those of ``Radiometry(bands=...)``. Nodata,
GDAL masks and NaN are invalid and come out black. The default stretch takes 8-bit samples as they are and
maps every other type per band from its 0.5-99.5 % percentiles of the area read to 0..255. The returned
map's ``radiometry`` records what was applied; a picture that comes out nearly constant or mostly dark is
warned about (:class:`~satloc.errors.SatlocWarning`, naming the file).

:func:`input_files` lists the files a load reads (for caches of loaded maps), :func:`is_georeferenced` tells a
georeferenced image from a plain one, and :func:`reproject_band` takes a raster aligned with an image (a label
image, a road mask) onto a loaded map's grid.
:func:`write_geotiff`, :func:`save_geotiff` and :func:`write_world_file` write these formats (atomically)
for tests and scenes.
"""
from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import ConfigError, FormatError
from ..geoframe import GeoFrame
from ..persist import atomic_path
from ..satmap import SatelliteMap
from .radiometry import Radiometry, Samples, plan_bands, read_samples, to_rgb8

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff")
TILE_SUFFIXES = (".png", ".jpg", ".jpeg")
_AVERAGE_ABOVE = 1.25  # output pixels this much coarser than the source's: area averaging instead of bilinear


# --- public API ------------------------------------------------------------------------------------------
def load_map(path: str | os.PathLike, mpp: float | None = None, frame: GeoFrame | None = None,
             region: tuple[float, float, float, float] | None = None, crs=None,
             zoom: int | None = None, radiometry: Radiometry | None = None) -> SatelliteMap:
    """Load a georeferenced image (GeoTIFF, image + world file, XYZ tile folder) as a :class:`SatelliteMap`.

    ``mpp``: output metres per pixel (default: the image's ground resolution at its centre, rounded to two
    significant digits). ``frame``: the map frame (default: a :class:`GeoFrame` at the image's centre).
    ``region``: ``(x_min, y_min, x_max, y_max)`` in the frame's metres to load (default: the whole image).
    ``crs``: the CRS of a file that carries none (anything pyproj reads: ``"EPSG:32632"``, WKT, PROJ).
    ``zoom``: the zoom level of a tile folder (default: the highest present).
    ``radiometry``: the bands to read and how to stretch them to 8 bits (:class:`satloc.geodata.radiometry.Radiometry`;
    default ``Radiometry()``: the image's colour bands, 8-bit samples as stored, other types stretched per
    band over their 0.5-99.5 % percentiles). The map's ``radiometry`` records what was applied.

    Raises :class:`FormatError` for missing, unreadable or ungeoreferenced input (naming the file and, for a
    world file, the line) and :class:`ConfigError` for bad arguments, a region the image does not cover, or
    bands the image does not have. Warns (:class:`~satloc.errors.SatlocWarning`, naming the file) when the
    8-bit picture comes out nearly constant or mostly dark.
    """
    from affine import Affine
    from rasterio.enums import Resampling
    from rasterio.warp import reproject

    mpp = _check_args(mpp, frame, region, zoom)
    if radiometry is None:
        radiometry = Radiometry()
    elif not isinstance(radiometry, Radiometry):
        raise ConfigError(f"radiometry: expected a satloc.geodata.radiometry.Radiometry, got {type(radiometry).__name__}")
    src = _open_source(Path(path), crs, zoom, radiometry)
    frame, frame_crs, mpp, src_gsd, (x0, y0, x1, y1) = _plan(src, mpp, frame, region)
    width, height = int(round((x1 - x0) / mpp)), int(round((y1 - y0) / mpp))
    if width < 1 or height < 1:
        raise ConfigError(f"{src.where}: the image covers less than one {mpp:g} m pixel of the frame")
    if width * height > 20000 * 20000:
        raise ConfigError(f"{src.where}: a {width}x{height} px map at {mpp:g} m/px is too large; "
                          f"pass a larger mpp or a region")
    dst_transform = Affine(mpp, 0.0, x0, 0.0, -mpp, y1)
    samples, src_transform = src.read_for(_src_window(src, frame_crs, (x0, y0, x1, y1), mpp / src_gsd))
    src_rgb, record = to_rgb8(samples, radiometry, src.where)
    src_valid = np.full(src_rgb.shape[1:], 255, np.uint8)       # where the source holds imagery
    if samples.valid is not None:
        src_valid[~samples.valid] = 0
    if samples.alpha is not None:
        src_valid[samples.alpha == 0] = 0
    del samples
    out = np.zeros((3, height, width), np.uint8)
    valid = np.zeros((height, width), np.uint8)                 # beyond the source's footprint: no imagery
    resampling = Resampling.average if mpp > _AVERAGE_ABOVE * src_gsd else Resampling.bilinear
    try:
        reproject(src_rgb, out, src_transform=src_transform, src_crs=src.crs, src_nodata=None,
                  dst_transform=dst_transform, dst_crs=frame_crs, dst_nodata=None, resampling=resampling,
                  num_threads=1)
        reproject(src_valid, valid, src_transform=src_transform, src_crs=src.crs, src_nodata=None,
                  dst_transform=dst_transform, dst_crs=frame_crs, dst_nodata=None, resampling=Resampling.nearest,
                  num_threads=1)
    except _gdal_error() as e:
        raise FormatError(f"{src.where}: could not be reprojected ({str(e)[:200]})") from e
    ok = valid > 0
    return SatelliteMap(np.ascontiguousarray(out.transpose(1, 2, 0)), float(mpp), (x0, y1), None, frame,
                        radiometry=record, valid=None if ok.all() else ok)


def map_bounds(path: str | os.PathLike, mpp: float | None = None, frame: GeoFrame | None = None, crs=None,
               zoom: int | None = None) -> tuple[GeoFrame, float, tuple[float, float, float, float]]:
    """(frame, mpp, (x_min, y_min, x_max, y_max)) of the map :func:`load_map` returns for these arguments
    without a ``region``, from the georeference alone (no pixel is read). Same arguments and errors."""
    mpp = _check_args(mpp, frame, None, zoom)
    src = _open_source(Path(path), crs, zoom)
    frame, _, mpp, _, bounds = _plan(src, mpp, frame, None)
    return frame, mpp, bounds


def input_files(path: str | os.PathLike, zoom: int | None = None) -> list[Path]:
    """Every existing file that :func:`load_map` may read for ``path``: the image, then its world file,
    ``.prj``, GDAL ``.aux.xml`` and ``.msk`` (valid pixels) sidecars; for a tile folder, every tile of the zoom
    level it loads (``zoom``, default the highest), sorted. What a cache of a loaded map must depend on."""
    path = Path(path)
    if path.is_dir():
        tiles = _scan_tiles(path)
        if not tiles:
            return []
        level = tiles.get(max(tiles) if zoom is None else zoom, {})
        return sorted(level.values())
    if not path.is_file():
        return []
    sidecars = [*world_file_candidates(path), path.with_suffix(".prj"), path.with_name(path.name + ".aux.xml"),
                path.with_name(path.name + ".msk")]
    return [path] + [p for p in sidecars if p.is_file()]


def is_georeferenced(path: str | os.PathLike, crs=None) -> bool:
    """Whether the image file ``path`` claims a place on Earth, so that it is for :func:`load_map` and not a
    plain picture: a world file beside it, a geotransform of its own (a GeoTIFF's, or GDAL's ``.aux.xml``),
    ground control points (which :func:`load_map` then refuses by name: it reads geotransforms only), or a
    ``crs`` given for it. False for a plain image and for a file rasterio cannot open (the caller's own reader
    reports that)."""
    import rasterio
    from rasterio.errors import RasterioIOError

    path = Path(path)
    if crs is not None or any(p.is_file() for p in world_file_candidates(path)):
        return True
    if path.suffix.lower() not in IMAGE_SUFFIXES:
        return False
    try:
        with _quiet(), rasterio.Env(GDAL_GEOREF_SOURCES="PAM,INTERNAL"), rasterio.open(path) as ds:
            return not ds.transform.is_identity or bool(ds.gcps[0])
    except RasterioIOError:
        return False


def reproject_band(band: np.ndarray, path: str | os.PathLike, satmap: SatelliteMap, crs=None,
                   resampling: str = "nearest", what: str = "the band") -> np.ndarray:
    """A single-band uint8 raster aligned pixel for pixel with the image at ``path`` (e.g. its label image or
    road mask), reprojected onto the grid of ``satmap`` (a map :func:`load_map` read from ``path``, or any map
    with a geo frame). ``crs`` as for :func:`load_map`; ``resampling``: a ``rasterio.enums.Resampling`` name;
    ``what`` names the band in the :class:`ConfigError` raised when its size is not the image's."""
    from affine import Affine
    from rasterio.crs import CRS
    from rasterio.enums import Resampling
    from rasterio.warp import reproject

    if satmap.frame is None:
        raise ConfigError("reproject_band: the map has no geo frame (a synthetic local frame)")
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"reproject_band: {path} is a tile folder; expected an image file")
    src = _open_source(path, crs, None)
    a = np.asarray(band)
    if a.shape != (src.height, src.width):
        size = f"{a.shape[1]}x{a.shape[0]}" if a.ndim == 2 else f"of shape {a.shape}"
        raise ConfigError(f"{what} is {size} px, but the image {path.name} is {src.width}x{src.height} px; it "
                          f"must be aligned with the image pixel for pixel")
    if not hasattr(Resampling, resampling):
        raise ConfigError(f"reproject_band: resampling {resampling!r} is not a rasterio Resampling name")
    mpp = satmap.meters_per_pixel
    out = np.zeros(satmap.shape[:2], np.uint8)
    reproject(np.ascontiguousarray(a, np.uint8), out, src_transform=src.transform, src_crs=src.crs,
              src_nodata=None, dst_transform=Affine(mpp, 0.0, satmap.origin[0], 0.0, -mpp, satmap.origin[1]),
              dst_crs=CRS.from_proj4(satmap.frame.proj4), dst_nodata=None,
              resampling=getattr(Resampling, resampling), num_threads=1)
    return out


def write_geotiff(path: str | os.PathLike, image: np.ndarray, transform, crs=None) -> None:
    """Write a uint8 image (H, W), (H, W, 3) or (H, W, 4 = RGBA) as a tiled, deflated GeoTIFF, atomically.

    ``transform``: the pixel-corner -> CRS affine transform (an ``affine.Affine`` or its six coefficients
    a, b, c, d, e, f). ``crs``: anything pyproj reads, or None for a GeoTIFF without a CRS.
    """
    import rasterio
    from affine import Affine
    from rasterio.enums import ColorInterp

    img = np.asarray(image)
    if img.dtype != np.uint8 or not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] in (3, 4))):
        raise ConfigError(f"write_geotiff: expected an (H, W), (H, W, 3) or (H, W, 4) uint8 image, got "
                          f"{img.dtype} {img.shape}")
    bands = img[None] if img.ndim == 2 else img.transpose(2, 0, 1)
    tr = transform if isinstance(transform, Affine) else Affine(*transform)
    rcrs = _parse_crs(crs) if crs is not None else None
    path = Path(path)
    profile = dict(driver="GTiff", width=img.shape[1], height=img.shape[0], count=bands.shape[0],
                   dtype="uint8", transform=tr, compress="deflate")
    if img.shape[0] >= 256 and img.shape[1] >= 256:
        profile.update(tiled=True, blockxsize=256, blockysize=256)
    if rcrs is not None:
        profile["crs"] = rcrs
    if bands.shape[0] >= 3:
        profile["photometric"] = "RGB"
    if bands.shape[0] == 4:
        profile["alpha"] = "YES"   # GDAL: unassociated alpha (ExtraSamples)
    with atomic_path(path, suffix=path.suffix or ".tif") as tmp, _quiet(), rasterio.Env(GDAL_PAM_ENABLED="NO"):
        with rasterio.open(tmp, "w", **profile) as dst:
            dst.write(bands)
            if bands.shape[0] == 4:
                dst.colorinterp = [ColorInterp.red, ColorInterp.green, ColorInterp.blue, ColorInterp.alpha]


def save_geotiff(satmap: SatelliteMap, path: str | os.PathLike) -> None:
    """Write a map with a geo frame as an RGB GeoTIFF in its frame's CRS (``load_map`` reads it back)."""
    if satmap.frame is None:
        raise ConfigError("save_geotiff: the map has no geo frame (a synthetic local frame); it has no place "
                          "on Earth to write")
    from affine import Affine

    mpp = satmap.meters_per_pixel
    write_geotiff(path, satmap.image, Affine(mpp, 0.0, satmap.origin[0], 0.0, -mpp, satmap.origin[1]),
                  satmap.frame.crs)


def write_world_file(path: str | os.PathLike, transform) -> None:
    """Write the six lines of a world file (A, D, B, E, C, F; C, F at the top-left pixel's centre), atomically."""
    from affine import Affine

    tr = transform if isinstance(transform, Affine) else Affine(*transform)
    cx, cy = _apply(tr, 0.5, 0.5)
    with atomic_path(path) as tmp:
        tmp.write_text("".join(f"{v!r}\n" for v in (tr.a, tr.d, tr.b, tr.e, float(cx), float(cy))))


def read_world_file(path: str | os.PathLike):
    """The pixel-corner affine transform of a world file; :class:`FormatError` naming the line at fault."""
    from affine import Affine

    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise FormatError(f"{path}: unreadable world file ({e})") from e
    lines = text.splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    if len(lines) != 6:
        raise FormatError(f"{path}: a world file has 6 lines (A, D, B, E, C, F), found {len(lines)}")
    names = ("A (pixel x size)", "D (rotation)", "B (rotation)", "E (pixel y size)", "C (x of the top-left "
             "pixel centre)", "F (y of the top-left pixel centre)")
    vals = []
    for i, (line, name) in enumerate(zip(lines, names)):
        try:
            v = float(line.strip())
        except ValueError:
            v = math.nan
        if not math.isfinite(v):
            raise FormatError(f"{path}: line {i + 1}: expected a number for {name}, got {line.strip()!r}")
        vals.append(v)
    a, d, b, e, c, f = vals
    if abs(a * e - b * d) == 0.0:
        raise FormatError(f"{path}: degenerate world file (A*E - B*D = 0: pixels have no area)")
    return _compose(Affine(a, b, c, d, e, f), Affine.translation(-0.5, -0.5))


def world_file_candidates(image: str | os.PathLike) -> list[Path]:
    """Where a world file of ``image`` may lie: ``a.pgw``, ``a.pngw``, ``a.wld`` (and upper-case forms)."""
    p = Path(image)
    ext = p.suffix[1:]
    names = []
    if len(ext) >= 2:
        names.append(p.stem + "." + ext[0] + ext[-1] + "w")
    names += [p.name + "w", p.stem + ".wld"]
    out = []
    for n in names:
        for cand in (p.with_name(n), p.with_name(Path(n).stem + Path(n).suffix.upper())):
            if cand not in out:
                out.append(cand)
    return out


# --- sources ---------------------------------------------------------------------------------------------
@dataclass
class _Source:
    """A raster to reproject: its CRS, pixel-corner transform and size, and a reader of pixel windows."""

    path: Path
    crs: object  # rasterio CRS
    transform: object  # affine.Affine
    width: int
    height: int
    read: Callable[[int, int, int, int], Samples]  # (col0, row0, cols, rows) -> the window's samples
    where: str = ""  # how messages name the source: the path, and the world file that georeferences it

    def __post_init__(self):
        self.where = self.where or str(self.path)

    def read_for(self, window: tuple[int, int, int, int]):
        from affine import Affine

        c0, r0, w, h = window
        return self.read(c0, r0, w, h), _compose(self.transform, Affine.translation(c0, r0))


def _open_source(path: Path, crs, zoom: int | None, radiometry: Radiometry | None = None) -> _Source:
    """The raster at ``path``: a tile folder or an image file (``crs``: the user's CRS argument; ``radiometry``:
    the bands its reader reads, default ``Radiometry()``)."""
    user_crs = _parse_crs(crs) if crs is not None else None
    radiometry = radiometry or Radiometry()
    if path.is_dir():
        if user_crs is not None:
            raise ConfigError(f"crs: a tile folder ({path}) is always in EPSG:3857; do not pass crs=")
        return _tile_source(path, zoom, radiometry)
    if path.is_file():
        if zoom is not None:
            raise ConfigError(f"zoom: only a tile folder has zoom levels; {path} is a file")
        return _file_source(path, user_crs, radiometry)
    raise FormatError(f"{path}: file or tile folder not found")


def _plan(src: _Source, mpp: float | None, frame: GeoFrame | None, region):
    """(frame, its rasterio CRS, mpp, the source's ground resolution, output bounds) of a load."""
    from rasterio.crs import CRS

    if frame is None:
        centre = _apply(src.transform, src.width / 2, src.height / 2)
        lon, lat = _transform_points(src.crs, CRS.from_epsg(4326), *centre, where=src.where)
        try:
            frame = GeoFrame(float(lon[0]), float(lat[0]))
        except ConfigError as e:
            raise FormatError(f"{src.where}: the image centre is not a valid map origin ({e})") from e
    frame_crs = CRS.from_proj4(frame.proj4)
    src_gsd = _ground_resolution(src, frame_crs)
    if mpp is None:
        mpp = _round_mpp(src_gsd)
    return frame, frame_crs, mpp, src_gsd, _output_bounds(src, frame_crs, mpp, region, src_gsd)


def _file_source(path: Path, user_crs, radiometry: Radiometry) -> _Source:
    import rasterio
    from rasterio.errors import RasterioIOError

    suffix = path.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise FormatError(f"{path}: expected a GeoTIFF (.tif, .tiff), an image with a world file "
                          f"({', '.join(IMAGE_SUFFIXES)}) or a folder of XYZ tiles")
    world = next((c for c in world_file_candidates(path) if c.is_file()), None)
    world_transform = None
    if world is not None and suffix not in (".tif", ".tiff"):  # a plain image: its world file is its georeference
        world_transform = read_world_file(world)
    _check_integrity(path)
    try:
        with _quiet(), rasterio.Env(GDAL_GEOREF_SOURCES="PAM,INTERNAL"):  # world files: read here, with line errors
            with rasterio.open(path) as ds:
                width, height, driver = ds.width, ds.height, ds.driver
                own_transform = None if ds.transform.is_identity else ds.transform
                own_crs = ds.crs
    except (RasterioIOError, _gdal_error()) as e:
        sidecars = ", ".join(p.name for p in input_files(path)[1:])
        raise FormatError(f"{path}: not a readable image{f' (or sidecar {sidecars})' if sidecars else ''} "
                          f"({type(e).__name__}: {str(e)[:200]})") from e
    from_world = False
    if own_transform is None or driver != "GTiff":  # PNG/JPEG: GDAL would apply a world file; we read it
        from_world = world is not None
        if world is None:
            if own_transform is None:
                raise FormatError(
                    f"{path}: not georeferenced: no geotransform in the file and no world file beside it "
                    f"(looked for {', '.join(c.name for c in world_file_candidates(path)[::2])})")
        else:
            own_transform = world_transform if world_transform is not None else read_world_file(world)
    _check_transform(own_transform, width, height, world if from_world else path)
    src_crs = _datum_tied(_resolve_crs(path, own_crs, user_crs))
    prj = path.with_suffix(".prj")
    sidecars = ([world] if from_world else []) + ([prj] if own_crs is None and user_crs is None else [])

    def read(c0, r0, w, h):
        from rasterio.windows import Window

        try:
            with _quiet(), rasterio.Env(GDAL_GEOREF_SOURCES="NONE"), rasterio.open(path) as ds:
                return read_samples(ds, plan_bands(ds, path, radiometry), Window(c0, r0, w, h))
        except (RasterioIOError, _gdal_error()) as e:
            raise FormatError(f"{path}: not a readable image ({type(e).__name__}: {str(e)[:200]})") from e

    where = f"{path} (georeferenced by {' and '.join(map(str, sidecars))})" if sidecars else ""
    return _Source(path, src_crs, own_transform, width, height, read, where)


def _scan_tiles(root: Path) -> dict[int, dict[tuple[int, int], Path]]:
    """{zoom: {(x, y): tile file}} of a ``<z>/<x>/<y>.<png|jpg|jpeg>`` folder."""
    tiles: dict[int, dict[tuple[int, int], Path]] = {}
    for zdir in root.iterdir():
        if not (zdir.is_dir() and zdir.name.isdigit()):
            continue
        z = int(zdir.name)
        for xdir in zdir.iterdir():
            if not (xdir.is_dir() and xdir.name.isdigit()):
                continue
            for f in xdir.iterdir():
                if f.is_file() and f.suffix.lower() in TILE_SUFFIXES and f.stem.isdigit():
                    tiles.setdefault(z, {})[(int(xdir.name), int(f.stem))] = f
    return tiles


def _tile_source(root: Path, zoom: int | None, radiometry: Radiometry) -> _Source:
    import rasterio
    from affine import Affine
    from rasterio.crs import CRS
    from rasterio.errors import RasterioIOError

    tiles = _scan_tiles(root)
    if not tiles:
        raise FormatError(f"{root}: no XYZ tiles (expected <zoom>/<x>/<y>.png or .jpg under the folder)")
    if zoom is None:
        zoom = max(tiles)
    elif zoom not in tiles:
        raise ConfigError(f"zoom: {root} has no tiles at zoom {zoom}; it has zoom {sorted(tiles)}")
    level = tiles[zoom]
    n = 2 ** zoom
    for (x, y), f in level.items():
        if x >= n or y >= n:
            raise FormatError(f"{f}: tile index out of range for zoom {zoom} (x and y below {n})")
    xs = [x for x, _ in level]
    ys = [y for _, y in level]
    tx0, ty0 = min(xs), min(ys)
    nx, ny = max(xs) - tx0 + 1, max(ys) - ty0 + 1
    first = level[(xs[0], ys[0])]
    _check_integrity(first, "tile image")
    try:
        with _quiet(), rasterio.open(first) as ds:
            size = ds.width
            square = ds.width == ds.height
    except (RasterioIOError, _gdal_error()) as e:
        raise FormatError(f"{first}: not a readable tile image ({type(e).__name__}: {str(e)[:200]})") from e
    if not square:
        raise FormatError(f"{first}: expected a square tile, got a non-square image")
    half = _web_mercator_half_extent()
    tile_m = 2.0 * half / n
    res = tile_m / size
    transform = Affine(res, 0.0, -half + tx0 * tile_m, 0.0, -res, half - ty0 * tile_m)

    def read(c0, r0, w, h):
        mosaic = _Mosaic(h, w)
        for ty in range(r0 // size, (r0 + h - 1) // size + 1):
            for tx in range(c0 // size, (c0 + w - 1) // size + 1):
                key = (tx0 + tx, ty0 + ty)
                f = level.get(key)
                if f is None:
                    raise FormatError(
                        f"{root}: tile {zoom}/{key[0]}/{key[1]} is missing inside the area to load "
                        f"({zoom}/{key[0]}/{key[1]}.png or .jpg; tiles x "
                        f"{tx0 + c0 // size}..{tx0 + (c0 + w - 1) // size}, y {ty0 + r0 // size}.."
                        f"{ty0 + (r0 + h - 1) // size} at zoom {zoom}); download it or pass a smaller region")
                _check_integrity(f, "tile image")
                try:
                    with _quiet(), rasterio.Env(GDAL_GEOREF_SOURCES="NONE"), rasterio.open(f) as ds:
                        if (ds.width, ds.height) != (size, size):
                            raise FormatError(f"{f}: tile of {ds.width}x{ds.height} px; the folder's tiles "
                                              f"are {size}x{size} (as {first})")
                        tile = read_samples(ds, plan_bands(ds, f, radiometry))
                except (RasterioIOError, _gdal_error()) as e:
                    raise FormatError(f"{f}: not a readable tile image ({type(e).__name__}: {str(e)[:200]})") from e
                # the part of this tile inside the window
                a0, b0 = max(c0, tx * size), max(r0, ty * size)
                a1, b1 = min(c0 + w, (tx + 1) * size), min(r0 + h, (ty + 1) * size)
                mosaic.put(tile, (slice(b0 - r0, b1 - r0), slice(a0 - c0, a1 - c0)),
                           (slice(b0 - ty * size, b1 - ty * size), slice(a0 - tx * size, a1 - tx * size)), f, first)
        return mosaic.samples()

    return _Source(root, CRS.from_epsg(3857), transform, nx * size, ny * size, read)


class _Mosaic:
    """The samples of a tile folder's window, tile by tile: one sample type (the stretch is decided once over
    all the tiles read), grey tiles beside colour ones widened to three channels, alpha and validity kept
    where any tile has them."""

    def __init__(self, h: int, w: int):
        self.shape = (h, w)
        self.values = self.alpha = self.valid = self.plan = None

    def put(self, tile: Samples, dst, src, path: Path, first: Path) -> None:
        if self.values is None:
            self.plan = tile.plan
            self.values = np.zeros((tile.values.shape[0], *self.shape), tile.values.dtype)
        elif tile.values.dtype != self.values.dtype:
            raise FormatError(f"{path}: tile of {tile.values.dtype} samples; the folder's tiles hold "
                              f"{self.values.dtype} (as {first}), and one stretch must serve them all")
        k = max(tile.values.shape[0], self.values.shape[0])
        if self.values.shape[0] < k:
            self.values = np.repeat(self.values, k, axis=0)
        self.values[(slice(None), *dst)] = tile.values[(slice(None), *src)]
        for name, value, fill in (("alpha", tile.alpha, 255), ("valid", tile.valid, True)):
            if value is not None or getattr(self, name) is not None:
                if getattr(self, name) is None:
                    setattr(self, name, np.full(self.shape, fill, np.uint8 if name == "alpha" else bool))
                getattr(self, name)[dst] = fill if value is None else value[src]

    def samples(self) -> Samples:
        return Samples(self.values, self.alpha, self.valid, self.plan)


# --- helpers ---------------------------------------------------------------------------------------------
def _check_args(mpp, frame, region, zoom):
    if mpp is not None:
        if isinstance(mpp, bool) or not isinstance(mpp, (int, float)) or not (math.isfinite(mpp) and mpp > 0):
            raise ConfigError(f"mpp: expected metres per pixel > 0, got {mpp!r}")
        mpp = float(mpp)
    if frame is not None and not isinstance(frame, GeoFrame):
        raise ConfigError(f"frame: expected a satloc.geoframe.GeoFrame, got {type(frame).__name__}")
    if region is not None:
        try:
            r = [float(v) for v in region]
        except (TypeError, ValueError):
            r = []
        if len(r) != 4 or not all(abs(v) <= MAX_COORD for v in r) or not (r[0] < r[2] and r[1] < r[3]):
            raise ConfigError(f"region: expected (x_min, y_min, x_max, y_max) in metres with x_min < x_max "
                              f"and y_min < y_max, each within +-{MAX_COORD:g}, got {region!r}")
    if zoom is not None and (isinstance(zoom, bool) or not isinstance(zoom, int) or not 0 <= zoom <= 30):
        raise ConfigError(f"zoom: expected an integer zoom level in [0, 30], got {zoom!r}")
    return mpp


def _parse_crs(crs):
    import pyproj
    from rasterio.crs import CRS

    try:
        c = pyproj.CRS.from_user_input(crs)
    except (pyproj.exceptions.CRSError, TypeError, ValueError) as e:
        raise ConfigError(f"crs: expected a coordinate reference system (e.g. 'EPSG:32632'), got {crs!r} ({e})") from e
    if c.is_geographic or c.is_projected or c.is_bound:
        return CRS.from_wkt(c.to_wkt())
    raise ConfigError(f"crs: expected a geographic or projected CRS, got {c.name!r}")


def _datum_tied(crs):
    """The rasterio CRS ``crs`` tied to WGS84 by its datum's shift where it is on another datum
    (:func:`satloc.geoframe.wgs84_bound`: without it PROJ places such an image tens of metres off), else
    ``crs`` itself."""
    from rasterio.crs import CRS

    from ..geoframe import wgs84_bound

    bound = wgs84_bound(crs.to_wkt())
    if not bound.is_bound and "+towgs84" not in bound.srs:
        return crs
    return CRS.from_proj4(bound.srs)


def _resolve_crs(path: Path, own, user):
    """The file's own CRS, else ``crs=``, else a ``.prj`` sidecar; error when none or when they conflict."""
    import pyproj
    from rasterio.crs import CRS

    if own is not None:
        if user is not None and not pyproj.CRS.from_wkt(own.to_wkt()).equals(
                pyproj.CRS.from_wkt(user.to_wkt()), ignore_axis_order=True):
            raise ConfigError(f"crs: {path} carries its own CRS ({own.to_string()}), which differs from "
                              f"crs={user.to_string()!r}")
        return own
    if user is not None:
        return user
    prj = path.with_suffix(".prj")
    if prj.is_file():
        try:
            text = prj.read_text().strip()
            return CRS.from_wkt(pyproj.CRS.from_user_input(text).to_wkt())
        except (OSError, UnicodeDecodeError, pyproj.exceptions.CRSError) as e:
            raise FormatError(f"{prj}: not a readable CRS (expected WKT) ({e})") from e
    raise FormatError(f"{path}: has no CRS (no coordinate reference system in the file and no {prj.name} "
                      f"beside it); pass crs=, e.g. 'EPSG:32632'")


MAX_COORD = 1e10  # |coordinate| of a georeference: GDAL's transformer loops for ages on values near 1e20


def _gdal_error():
    """GDAL's own error type as rasterio raises it for some damaged inputs (besides RasterioIOError)."""
    from rasterio._err import CPLE_BaseError

    return CPLE_BaseError


def _check_integrity(path: Path, what: str = "image") -> None:
    """Damage that GDAL's PNG and JPEG drivers let through (chunk CRCs, a truncated JPEG, content of another
    kind than the suffix says)."""
    from ..satmap import check_image_bytes

    suffix = path.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        return
    try:
        if suffix == ".png":  # every chunk's CRC: the whole file
            data = path.read_bytes()
        else:  # the magic number, and a JPEG's end-of-image marker: the head and the tail suffice
            with open(path, "rb") as f:
                data = f.read(4)
                if suffix != ".tif" and suffix != ".tiff":
                    f.seek(max(4, f.seek(0, os.SEEK_END) - 1024))
                    data += f.read()
    except OSError as e:
        raise FormatError(f"{path}: not a readable {what} ({e})") from e
    check_image_bytes(data, path, what)


def _check_transform(tr, width: int, height: int, path: Path) -> None:
    """A georeference whose pixels have an area and whose corners lie at finite, sane coordinates (GDAL's
    coordinate transformer can loop for ages on huge ones)."""
    if tr is None:
        return
    x, y = _apply(tr, np.array([0.0, width, 0.0, width]), np.array([0.0, 0.0, height, height]))
    vals = np.concatenate([[tr.a, tr.b, tr.d, tr.e], x, y])
    if not (np.isfinite(vals).all() and np.abs(vals).max() <= MAX_COORD):
        raise FormatError(f"{path}: georeference out of range (pixel size {tr.a:g}, {tr.e:g}, corners x "
                          f"{x.min():g}..{x.max():g}, y {y.min():g}..{y.max():g}; expected within +-{MAX_COORD:g})")
    if tr.a * tr.e - tr.b * tr.d == 0.0:
        raise FormatError(f"{path}: degenerate georeference (pixels have no area)")


def _transform_points(src_crs, dst_crs, xs, ys, where: str = "coordinates"):
    """Points from one CRS to another; FormatError naming ``where`` when GDAL refuses them (outside the
    projection's domain)."""
    from rasterio.warp import transform

    xs, ys = np.atleast_1d(np.asarray(xs, np.float64)), np.atleast_1d(np.asarray(ys, np.float64))
    try:
        ox, oy = transform(src_crs, dst_crs, xs.ravel(), ys.ravel())
    except _gdal_error() as e:
        raise FormatError(f"{where}: points outside the coordinate system's domain ({str(e)[:200]})") from e
    return np.asarray(ox, np.float64).reshape(xs.shape), np.asarray(oy, np.float64).reshape(ys.shape)


def _ground_resolution(src: _Source, frame_crs) -> float:
    """Frame metres per source pixel at the image centre: sqrt of the area of one pixel."""
    cu, cv = src.width / 2, src.height / 2
    corners = _apply(src.transform, np.array([cu, cu + 1, cu]), np.array([cv, cv, cv + 1]))
    x, y = _transform_points(src.crs, frame_crs, *corners, where=src.where)
    if not np.isfinite(x).all() or not np.isfinite(y).all():
        raise FormatError(f"{src.where}: the image centre does not project into the map frame")
    area = abs((x[1] - x[0]) * (y[2] - y[0]) - (x[2] - x[0]) * (y[1] - y[0]))
    if not area > 0:
        raise FormatError(f"{src.where}: degenerate georeference (pixels have no area on the ground)")
    return math.sqrt(area)


def _round_mpp(gsd: float) -> float:
    """Two significant digits: 0.1963 -> 0.2, 0.2986 -> 0.3, 0.149 -> 0.15."""
    e = math.floor(math.log10(gsd)) - 1
    return round(round(gsd / 10.0 ** e) * 10.0 ** e, 12)


def _edge_samples(width: float, height: float, n: int = 33) -> np.ndarray:
    """Points along the border of a (width x height) pixel rectangle, clockwise from the top-left corner."""
    t = np.linspace(0.0, 1.0, n)
    return {
        "top": np.c_[t * width, np.zeros(n)], "right": np.c_[np.full(n, width), t * height],
        "bottom": np.c_[t * width, np.full(n, height)], "left": np.c_[np.zeros(n), t * height],
    }


def _output_bounds(src: _Source, frame_crs, mpp: float, region, src_gsd: float):
    """(x0, y0, x1, y1) of the output grid on the mpp lattice of the frame."""
    if region is None:
        # the largest north-up box inside the footprint: innermost of each edge's extreme
        edges = {}
        for name, uv in _edge_samples(src.width, src.height).items():
            edges[name] = _transform_points(src.crs, frame_crs, *_apply(src.transform, uv[:, 0], uv[:, 1]),
                                             where=src.where)
        if not all(np.isfinite(np.concatenate(v)).all() for v in edges.values()):
            raise FormatError(f"{src.where}: the image does not project into the map frame")
        # which image edge faces which way in the frame (the transform may flip or rotate the image)
        by_x = sorted(edges, key=lambda k: np.mean(edges[k][0]))
        by_y = sorted(edges, key=lambda k: np.mean(edges[k][1]))
        west, east, south, north = by_x[0], by_x[-1], by_y[0], by_y[-1]
        bx0, bx1 = np.max(edges[west][0]), np.min(edges[east][0])
        by0, by1 = np.max(edges[south][1]), np.min(edges[north][1])
        x0, x1 = math.ceil(bx0 / mpp - 1e-6) * mpp, math.floor(bx1 / mpp + 1e-6) * mpp
        y0, y1 = math.ceil(by0 / mpp - 1e-6) * mpp, math.floor(by1 / mpp + 1e-6) * mpp
        if not (x0 < x1 and y0 < y1):
            raise ConfigError(f"{src.where}: the image covers less than one {mpp:g} m pixel of the frame")
        return x0, y0, x1, y1
    r = [float(v) for v in region]
    x0, x1 = math.floor(r[0] / mpp + 1e-6) * mpp, math.ceil(r[2] / mpp - 1e-6) * mpp
    y0, y1 = math.floor(r[1] / mpp + 1e-6) * mpp, math.ceil(r[3] / mpp - 1e-6) * mpp
    # every output pixel centre must fall in the image (within half an output pixel of the region)
    h = 0.5 * mpp
    box = np.concatenate([v for v in _edge_samples(x1 - x0 - 2 * h, y1 - y0 - 2 * h).values()])
    fx, fy = x0 + h + box[:, 0], y0 + h + box[:, 1]
    sx, sy = _transform_points(frame_crs, src.crs, fx, fy, where=src.where)
    cu, cv = _apply(~src.transform, sx, sy)
    tol = h / src_gsd + 1e-6  # source pixels
    ok = (np.isfinite(cu) & np.isfinite(cv) & (cu >= -tol) & (cu <= src.width + tol)
          & (cv >= -tol) & (cv <= src.height + tol))
    if not ok.all():
        cover = _output_bounds(src, frame_crs, mpp, None, src_gsd)
        raise ConfigError(
            f"region: ({r[0]:.1f}, {r[1]:.1f}, {r[2]:.1f}, {r[3]:.1f}) m is not covered by {src.where}, which "
            f"covers x [{cover[0]:.1f}, {cover[2]:.1f}] y [{cover[1]:.1f}, {cover[3]:.1f}] m of the frame")
    return x0, y0, x1, y1


def _src_window(src: _Source, frame_crs, bounds, ratio: float) -> tuple[int, int, int, int]:
    """(col0, row0, cols, rows) of the source pixels that the output grid ``bounds`` needs, with a margin."""
    x0, y0, x1, y1 = bounds
    pts = np.concatenate(list(_edge_samples(x1 - x0, y1 - y0).values()))
    sx, sy = _transform_points(frame_crs, src.crs, x0 + pts[:, 0], y0 + pts[:, 1], where=src.where)
    cu, cv = _apply(~src.transform, sx, sy)
    pad = 2 + int(math.ceil(max(ratio, 1.0)))
    c0 = max(0, int(math.floor(np.nanmin(cu))) - pad)
    r0 = max(0, int(math.floor(np.nanmin(cv))) - pad)
    c1 = min(src.width, int(math.ceil(np.nanmax(cu))) + pad)
    r1 = min(src.height, int(math.ceil(np.nanmax(cv))) + pad)
    if c1 <= c0 or r1 <= r0:
        raise ConfigError(f"{src.where}: the area to load lies outside the image")
    return c0, r0, c1 - c0, r1 - r0


def _apply(tr, x, y):
    """An affine transform applied to coordinates (scalars or arrays), whatever the ``affine`` version."""
    return tr.a * x + tr.b * y + tr.c, tr.d * x + tr.e * y + tr.f


def _compose(first, second):
    """``first`` after ``second`` (the matrix product first @ second)."""
    from affine import Affine

    m = np.asarray(tuple(first), np.float64).reshape(3, 3) @ np.asarray(tuple(second), np.float64).reshape(3, 3)
    return Affine(*m.ravel()[:6])


def _web_mercator_half_extent() -> float:
    """Half the width of the EPSG:3857 world (x of longitude 180), from pyproj."""
    import pyproj

    x, _ = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:3857", always_xy=True).transform(180.0, 0.0)
    return float(x)


class _quiet(warnings.catch_warnings):
    """Silence rasterio's NotGeoreferencedWarning (a plain image is read for its pixels only)."""

    def __enter__(self):
        super().__enter__()
        from rasterio.errors import NotGeoreferencedWarning

        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        return self
