"""Georeferenced satellite map: an image of the map plane with its pixel <-> metre transform.

Georeference: ``origin`` is the map-frame position (metres) of the *top-left corner* of pixel (0, 0);
``meters_per_pixel`` is the ground sampling distance. Image columns grow east (+x), rows grow south (-y).
Pixel (u, v) has its centre at map point ``(origin_x + (u + 0.5) * mpp, origin_y - (v + 0.5) * mpp)``.

``frame`` places the map plane on Earth: a :class:`~satloc.geoframe.GeoFrame` for maps of real places (loaded
by :func:`satloc.geodata.georef.load_map`), ``None`` for the local frame of a synthetic scene, which has no place on
Earth. ``map.json`` records it as ``"geo_frame"`` (the frame's ``to_dict()``, or null); a ``map.json`` written
before the key existed loads with no frame.

``radiometry`` records how a map read from imagery got its 8-bit colours (the source's sample type, the bands,
the stretch and its per-band levels: :func:`satloc.geodata.radiometry.to_rgb8`), None for other maps; ``map.json``
keeps it as ``"radiometry"``.
"""
from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .errors import ConfigError, FormatError
from .geoframe import GeoFrame
from .persist import atomic_path, header, header_number, header_point, read_json, write_json


@dataclass
class SatelliteMap:
    image: np.ndarray  # (H, W, 3) uint8 RGB
    meters_per_pixel: float
    origin: tuple[float, float] = (0.0, 0.0)
    labels: np.ndarray | None = field(default=None, repr=False)  # optional (H, W) uint8 semantic classes
    frame: GeoFrame | None = None  # where the map plane lies on Earth; None: a synthetic local frame
    radiometry: dict | None = field(default=None, repr=False, compare=False)  # how imagery became 8-bit RGB
    # (H, W) bool: the pixels that hold imagery (False: nodata, masked, transparent or beyond the image's
    # footprint, black in ``image``); None: every pixel. Set by satloc.geodata.georef.load_map; not saved.
    valid: np.ndarray | None = field(default=None, repr=False, compare=False)

    def __post_init__(self):
        img = np.asarray(self.image)
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise ConfigError(f"SatelliteMap.image: expected an (H, W, 3) uint8 RGB image, got {img.dtype} {img.shape}")
        if not self.meters_per_pixel > 0:
            raise ConfigError(f"SatelliteMap.meters_per_pixel: expected > 0, got {self.meters_per_pixel}")
        if self.labels is not None and self.labels.shape != img.shape[:2]:
            raise ConfigError(f"SatelliteMap.labels: expected shape {img.shape[:2]}, got {self.labels.shape}")
        if self.frame is not None and not isinstance(self.frame, GeoFrame):
            raise ConfigError(f"SatelliteMap.frame: expected a GeoFrame or None, got {type(self.frame).__name__}")
        if self.valid is not None and (np.shape(self.valid) != img.shape[:2] or np.asarray(self.valid).dtype != bool):
            raise ConfigError(f"SatelliteMap.valid: expected an {img.shape[:2]} bool mask, got "
                              f"{np.asarray(self.valid).dtype} {np.shape(self.valid)}")
        if self.radiometry is not None and not isinstance(self.radiometry, dict):
            raise ConfigError(f"SatelliteMap.radiometry: expected a dict or None, got {type(self.radiometry).__name__}")
        self.origin = (float(self.origin[0]), float(self.origin[1]))

    @property
    def shape(self) -> tuple[int, int]:
        return self.image.shape[:2]

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) in metres."""
        h, w = self.shape
        x0, y1 = self.origin
        return (x0, x0 + w * self.meters_per_pixel, y1 - h * self.meters_per_pixel, y1)

    def world_to_pixel(self, xy: np.ndarray) -> np.ndarray:
        """Continuous pixel coordinates (u, v) of map points (..., 2); centres at integers."""
        xy = np.asarray(xy, dtype=np.float64)
        u = (xy[..., 0] - self.origin[0]) / self.meters_per_pixel - 0.5
        v = (self.origin[1] - xy[..., 1]) / self.meters_per_pixel - 0.5
        return np.stack([u, v], axis=-1)

    def pixel_to_world(self, uv: np.ndarray) -> np.ndarray:
        uv = np.asarray(uv, dtype=np.float64)
        x = self.origin[0] + (uv[..., 0] + 0.5) * self.meters_per_pixel
        y = self.origin[1] - (uv[..., 1] + 0.5) * self.meters_per_pixel
        return np.stack([x, y], axis=-1)

    def _geo(self, what: str) -> GeoFrame:
        if self.frame is None:
            raise ConfigError(f"SatelliteMap.{what}: this map has no geo frame (a synthetic local frame); "
                              f"load a georeferenced image with satloc.geodata.georef.load_map")
        return self.frame

    def lonlat_to_pixel(self, lonlat) -> np.ndarray:
        """Continuous pixel coordinates (u, v) (..., 2) of WGS84 (lon, lat) degrees (..., 2)."""
        return self.world_to_pixel(self._geo("lonlat_to_pixel").to_map(lonlat))

    def pixel_to_lonlat(self, uv) -> np.ndarray:
        """WGS84 (lon, lat) degrees (..., 2) of pixel coordinates (u, v) (..., 2)."""
        return self._geo("pixel_to_lonlat").to_lonlat(self.pixel_to_world(uv))

    def check_covers(self, xy, where: str, margin_m: float = 0.0) -> None:
        """Raise :class:`ConfigError` unless every map point of ``xy`` (..., 2) lies ``margin_m`` inside the map.

        ``where`` names the points in the message (e.g. ``"sequence 'kitti_0023' poses"``); the message gives
        the first index outside, how many are, the points' extent and the map's.
        """
        pts = np.asarray(xy, dtype=np.float64)
        if pts.ndim == 0 or pts.shape[-1] != 2:
            raise ConfigError(f"{where}: expected (..., 2) map points, got shape {pts.shape}")
        pts = pts.reshape(-1, 2)
        if len(pts) == 0:
            return
        inside = self.contains(pts, margin_m)
        if inside.all():
            return
        bad = np.flatnonzero(~inside)
        i = int(bad[0])
        finite = np.isfinite(pts).all(axis=1)
        x0, x1, y0, y1 = self.extent
        span = (f"x [{pts[finite, 0].min():.1f}, {pts[finite, 0].max():.1f}] y [{pts[finite, 1].min():.1f}, "
                f"{pts[finite, 1].max():.1f}] m" if finite.any() else "no finite points")
        raise ConfigError(
            f"{where}: {len(bad)} of {len(pts)} points lie outside the satellite map"
            f"{f' (with a {margin_m:g} m margin)' if margin_m else ''}, the first is #{i} at "
            f"({pts[i, 0]:.1f}, {pts[i, 1]:.1f}); the points span {span}, the map covers "
            f"x [{x0:.1f}, {x1:.1f}] y [{y0:.1f}, {y1:.1f}] m")

    def contains(self, xy: np.ndarray, margin_m: float = 0.0) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64)
        x0, x1, y0, y1 = self.extent
        return (
            (xy[..., 0] >= x0 + margin_m) & (xy[..., 0] <= x1 - margin_m)
            & (xy[..., 1] >= y0 + margin_m) & (xy[..., 1] <= y1 - margin_m)
        )

    def crop(self, center_xy, size_m: float, yaw: float | None = None, out_px: int | None = None) -> np.ndarray:
        """Square patch of ``size_m`` metres around ``center_xy`` (north up, or heading up if ``yaw``)."""
        out_px = out_px or max(1, int(round(size_m / self.meters_per_pixel)))
        s = out_px / size_m * self.meters_per_pixel  # output px per map px
        cu, cv_ = self.world_to_pixel(np.asarray(center_xy))
        rot = 0.0 if yaw is None else math.degrees(yaw) - 90.0
        m = cv2.getRotationMatrix2D((float(cu), float(cv_)), -rot, s)
        m[0, 2] += out_px / 2 - 0.5 - cu
        m[1, 2] += out_px / 2 - 0.5 - cv_
        return cv2.warpAffine(self.image, m, (out_px, out_px), flags=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))

    # --- persistence ------------------------------------------------------------------------------
    def save(self, directory: str | Path) -> None:
        """Write ``map.png`` (+ ``labels.png``) and ``map.json`` into ``directory``."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        with atomic_path(d / "map.png", suffix=".png") as tmp:
            if not cv2.imwrite(str(tmp), cv2.cvtColor(self.image, cv2.COLOR_RGB2BGR)):
                raise OSError(f"{d / 'map.png'}: could not write image")
        if self.labels is not None:
            with atomic_path(d / "labels.png", suffix=".png") as tmp:
                cv2.imwrite(str(tmp), self.labels)
        meta = header("satellite_map")
        meta.update(meters_per_pixel=self.meters_per_pixel, origin=list(self.origin),
                    image="map.png", labels="labels.png" if self.labels is not None else None,
                    width=int(self.shape[1]), height=int(self.shape[0]),
                    geo_frame=self.frame.to_dict() if self.frame is not None else None)
        if self.radiometry is not None:
            meta["radiometry"] = self.radiometry
        write_json(d / "map.json", meta)

    @staticmethod
    def load(directory: str | Path) -> "SatelliteMap":
        d = Path(directory)
        mj = d / "map.json"
        meta = read_json(mj, "satellite_map")
        mpp = header_number(meta, "meters_per_pixel", mj, positive=True)
        origin = header_point(meta, "origin", mj)
        names = {}
        for k, required in (("image", True), ("labels", False)):
            v = meta.get(k)
            if v is None and not required:
                continue
            if not isinstance(v, str) or not v or Path(v).name != v:
                raise FormatError(f"{mj}: field '{k}': expected the name of an image file in {d}, got {str(v)[:60]!r}")
            names[k] = v
        size = [header_number(meta, k, mj, positive=True, integer=True, default=None) for k in ("width", "height")]
        try:
            img = read_image(d / names["image"])
        except FormatError as e:
            raise FormatError(f"{mj}: image {names['image']!r}: {e}") from e
        if any(s is not None and s != n for s, n in zip(size, (img.shape[1], img.shape[0]))):
            raise FormatError(f"{d / names['image']}: size {img.shape[1]}x{img.shape[0]} differs from {mj} "
                              f"({size[0]}x{size[1]})")
        if not all(math.isfinite(v) for v in (origin[0] + img.shape[1] * mpp, origin[1] - img.shape[0] * mpp)):
            raise FormatError(f"{mj}: origin {list(origin)} and meters_per_pixel {mpp} put the map beyond finite "
                              f"coordinates")
        labels = None
        if "labels" in names:
            lp = d / names["labels"]
            try:
                labels = read_image(lp, grayscale=True)
            except FormatError as e:
                raise FormatError(f"{mj}: labels {names['labels']!r}: {e}") from e
            if labels.dtype != np.uint8 or labels.shape != img.shape[:2]:
                raise FormatError(f"{lp}: expected 8-bit class ids of the map's size {img.shape[1]}x{img.shape[0]}, "
                                  f"got {labels.dtype} {labels.shape[1::-1]}")
            from .labels import NUM_CLASSES

            if labels.max() >= NUM_CLASSES:
                raise FormatError(f"{lp}: class id {labels.max()} >= {NUM_CLASSES} (satloc.labels.CLASSES)")
        frame = None
        if meta.get("geo_frame") is not None:  # absent in map.json written before maps had a geo frame
            try:
                frame = GeoFrame.from_dict(meta["geo_frame"], where="geo_frame")
            except ConfigError as e:
                raise FormatError(f"{mj}: {e}") from e
        radiometry = meta.get("radiometry")
        if radiometry is not None and not isinstance(radiometry, dict):
            raise FormatError(f"{mj}: field 'radiometry': expected a mapping or null, got {type(radiometry).__name__}")
        return SatelliteMap(img, float(mpp), origin, labels, frame, radiometry)


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def check_image_bytes(data: bytes, path: str | Path, what: str = "image") -> None:
    """Integrity of an image file's bytes where the decoders are lenient: content of the kind its suffix
    names (``.png``, ``.jpg``/``.jpeg``, ``.tif``/``.tiff``: decoders go by content, so a foreign image under
    the right name would load), a PNG's chunks (lengths and CRC-32s, up to IEND) and a JPEG's end-of-image
    marker (a truncated JPEG otherwise decodes with a grey bottom, and GDAL ignores PNG CRCs). The decoder
    judges the rest. FormatError ``<path>: not a readable <what>: <why>``."""
    def bad(why: str):
        raise FormatError(f"{path}: not a readable {what}: {why}")

    suffix = Path(path).suffix.lower()
    tiff = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
    magic = {".png": (_PNG_SIGNATURE,), ".jpg": (b"\xff\xd8",), ".jpeg": (b"\xff\xd8",), ".tif": tiff, ".tiff": tiff}
    if suffix in magic and not data.startswith(magic[suffix]):
        bad(f"no {suffix[1:].upper()} content (a file of another kind, or damaged)")
    if data[:8] == _PNG_SIGNATURE:
        pos = 8
        while True:
            if pos + 12 > len(data):
                bad(f"damaged PNG (truncated at byte {len(data)}, no IEND chunk)")
            n = int.from_bytes(data[pos:pos + 4], "big")
            kind = data[pos + 4:pos + 8]
            end = pos + 12 + n
            if n > 2**31 - 1 or end > len(data):
                bad(f"damaged PNG (chunk {kind!r} at byte {pos} runs past the end of the file)")
            if zlib.crc32(data[pos + 4:pos + 8 + n]) != int.from_bytes(data[end - 4:end], "big"):
                bad(f"damaged PNG (CRC mismatch in chunk {kind!r} at byte {pos})")
            if kind == b"IEND":
                return
            pos = end
    if data[:2] == b"\xff\xd8" and not data.rstrip(b"\x00").endswith(b"\xff\xd9"):
        bad("damaged JPEG (truncated: no end-of-image marker)")


#: the GeoTIFF tags (ModelPixelScale, ModelTiepoint, ModelTransformation, GeoKeyDirectory, GeoDoubleParams,
#: GeoAsciiParams): OpenCV's libtiff does not know them and prints a TIFF_Warning line for each
GEOTIFF_TAGS = frozenset({33550, 33922, 34264, 34735, 34736, 34737})


def has_geotiff_tags(data: bytes) -> bool:
    """Whether the first image directory of TIFF (or BigTIFF) bytes holds a GeoTIFF tag (False for anything
    else, damaged bytes included: the decoder judges those)."""
    try:
        order = {b"II": "<", b"MM": ">"}[data[:2]]
        (magic,) = struct.unpack(order + "H", data[2:4])
        if magic == 42:
            (ifd,) = struct.unpack(order + "I", data[4:8])
            (n,) = struct.unpack(order + "H", data[ifd:ifd + 2])
            first, size = ifd + 2, 12
        elif magic == 43:
            (ifd,) = struct.unpack(order + "Q", data[8:16])
            (n,) = struct.unpack(order + "Q", data[ifd:ifd + 8])
            first, size = ifd + 8, 20
        else:
            return False
        tags = {struct.unpack(order + "H", data[first + i * size:first + i * size + 2])[0] for i in range(min(n, 4096))}
    except (KeyError, struct.error):
        return False
    return bool(tags & GEOTIFF_TAGS)


def read_image(path: str | Path, grayscale: bool = False) -> np.ndarray:
    """Read an image file as RGB uint8 (or single-channel); clear error if missing, damaged or unreadable.

    OpenCV decodes it, except a GeoTIFF (a TIFF with GeoTIFF tags, e.g. a road mask aligned with an
    orthophoto): GDAL decodes that (with OpenCV's conventions), because OpenCV's libtiff prints a warning
    line for every GeoTIFF tag it does not know."""
    path = Path(path)
    try:
        if not path.is_file():
            raise FormatError(f"{path}: image file not found")
        data = path.read_bytes()
    except OSError as e:  # a name too long, a permission, ...
        raise FormatError(f"{path}: not readable ({e})") from e
    check_image_bytes(data, path)
    if data[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+") and has_geotiff_tags(data):
        return _read_tiff_gdal(data, path, grayscale)
    flag = cv2.IMREAD_UNCHANGED if grayscale else cv2.IMREAD_COLOR
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), flag) if data else None
    except cv2.error as e:
        raise FormatError(f"{path}: not a readable image ({str(e).strip()[:200]})") from e
    if img is None:
        raise FormatError(f"{path}: not a readable image")
    if grayscale:
        return img if img.ndim == 2 else img[..., 0]
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _read_tiff_gdal(data: bytes, path: str | Path, grayscale: bool) -> np.ndarray:
    """The pixels of TIFF bytes decoded by GDAL (rasterio), as :func:`read_image` gives them (OpenCV's
    conventions): ``grayscale``: one channel in the stored sample type (band 1, or band 3 of three or more
    bands: the first channel of OpenCV's BGR order); else (H, W, 3) uint8 RGB of an 8- or 16-bit image
    (grey repeated, alpha dropped, 16 bit as OpenCV scales it: grey by 1/256, colour by 1/257). A palette
    image is expanded. :class:`FormatError` naming ``path`` for what it cannot decode."""
    import warnings

    import rasterio
    from rasterio._err import CPLE_BaseError
    from rasterio.enums import ColorInterp
    from rasterio.errors import NotGeoreferencedWarning, RasterioIOError

    from .geodata.radiometry import expand_palette, palette_table

    try:
        with warnings.catch_warnings(), rasterio.MemoryFile(data) as mem:
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with mem.open() as ds:
                arr = ds.read()
                ci = list(ds.colorinterp)
                cmap = ds.colormap(1) if ds.count == 1 and ci[0] == ColorInterp.palette else None
    except (RasterioIOError, CPLE_BaseError, ValueError) as e:
        raise FormatError(f"{path}: not a readable image ({type(e).__name__}: {str(e)[:200]})") from e
    if cmap:
        arr = expand_palette(palette_table(cmap), arr[0])[..., :3].transpose(2, 0, 1)
    count = arr.shape[0]
    if grayscale:
        return np.ascontiguousarray(arr[2 if count >= 3 else 0])
    if arr.dtype not in (np.uint8, np.uint16) or count > 4:
        raise FormatError(f"{path}: not a readable image ({count} bands of {arr.dtype}; expected 1 to 4 bands of "
                          f"8- or 16-bit samples)")
    rgb = arr[:3] if count >= 3 else np.repeat(arr[:1], 3, axis=0)
    if rgb.dtype == np.uint16:
        rgb = (rgb >> 8 if count < 3 else (rgb.astype(np.uint32) * 255 + 32767) // 65535).astype(np.uint8)
    return np.ascontiguousarray(rgb.transpose(1, 2, 0))
