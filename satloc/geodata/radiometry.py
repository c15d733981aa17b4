"""Radiometry of georeferenced imagery: which bands make the picture, which pixels are valid, and how the
samples become the 8-bit RGB of a :class:`~satloc.satmap.SatelliteMap` (the reader behind
:func:`satloc.geodata.georef.load_map`, and so behind image scenes, ``satloc evaluate`` and the replay environment).

**Sample types**: every integer type GDAL reads (8 bit; 11-, 12- or 16-bit data stored in 16 bits; int16;
32 bit) and floats (NaN and infinities are invalid pixels). Complex samples are refused.

**Bands** (:attr:`Radiometry.bands`: band numbers counted from 1, as GDAL counts; one band is grey, three
are red, green and blue). Without it:

* 1 band: grey (a palette band is expanded through its colour table, whose alpha is the pixel's alpha);
* 2 bands: grey, and the 2nd band is alpha where the file says so;
* 3 bands: red, green, blue;
* 4 bands: red, green, blue, and the 4th band is alpha where the file says so;
* more: the bands GDAL interprets as red, green and blue; without that interpretation the load stops with
  a :class:`~satloc.errors.ConfigError` asking for ``bands``.

**Alpha** (:attr:`Radiometry.alpha`): ``"auto"`` (the default) is the band the file marks as alpha (GDAL's
colour interpretation ``alpha``: a TIFF's ExtraSamples, a PNG's alpha channel), in every case (with
``bands`` too). A 2nd or 4th band the file leaves undefined (a TIFF with ExtraSamples "unspecified", as
RGB + near-infrared orthophotos are written) is *not* alpha: it is read as an extra band and left aside,
with a one-line :class:`~satloc.errors.SatlocWarning` naming the choice and how to change it (``alpha: 4``).
``alpha`` may name the band (an int) or be ``None`` (no alpha, even where the file marks one).

**Invalid pixels**: GDAL's nodata (a pixel whose selected bands all hold their band's nodata value), its
per-dataset mask (a TIFF's internal mask, a ``.msk`` sidecar), NaN or infinite samples, and alpha 0. They
come out black, as a fully transparent pixel always has (colour is composited over black by alpha), and
take no part in the stretch statistics or the warnings.

**Stretch** (:attr:`Radiometry.stretch`; per band, a sample ``x`` becomes
``(x - low) / (high - low) * 255``, rounded and clipped to 0..255):

* ``"auto"`` (the default): **8-bit samples are taken as stored** (low 0, high 255: 8-bit imagery loads
  byte for byte as it always has; ask for a stretch explicitly to change it). Every other type: per band,
  low and high are the :data:`PERCENTILES` (0.5 % and 99.5 %) of the valid samples of the area read (a
  regular subsample of at most :data:`MAX_STAT_PIXELS` pixels; for a tile folder, of all the tiles read). A
  constant band comes out mid-grey.
* ``"none"``: the type's full range: 0..255 for 8 bit, 0..65535 for 16 bit (the 1/257 scaling of earlier
  versions, under which 11-bit data comes out nearly black), the type's limits for other integers, 0..1
  for floats.
* ``[low, high]``: the same range for every band; ``[[low, high], ...]``: one range per band read (1 for
  grey, 3 for RGB).

:func:`to_rgb8` returns what it applied as a JSON-able dict (source type, bands, alpha band, stretch,
per-band levels, the valid fraction), which :func:`~satloc.geodata.georef.load_map` puts on the map as
``SatelliteMap.radiometry``. It warns (:class:`~satloc.errors.SatlocWarning`, naming the file) when the
8-bit picture is nearly constant (:data:`CONSTANT_STD`) or mostly dark (:data:`DARK_MEDIAN`) over its valid
pixels, or has none.
"""
from __future__ import annotations

import math
import numbers
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import ConfigError, FormatError, SatlocWarning

STRETCHES = ("auto", "none")
PERCENTILES = (0.5, 99.5)     #: the ``auto`` stretch's low and high, percent of the valid samples
MAX_STAT_PIXELS = 1_000_000   #: the ``auto`` statistics and the warnings look at a subsample of this many pixels
CONSTANT_STD = 2.0            #: warn when the 8-bit grey level's std over the valid pixels is below this ...
DARK_MEDIAN = 20.0            #: ... or its median is below this
_CHUNK = 1 << 20              # samples converted at a time (bounds the float64 temporaries)

Levels = tuple[tuple[float, float], ...]


@dataclass(frozen=True)
class Radiometry:
    """How :func:`satloc.geodata.georef.load_map` turns an image's samples into 8-bit RGB (see the module docstring).

    ``bands``: ``None`` (the image's own colour bands), or 1 (grey) or 3 (red, green, blue) band numbers
    counted from 1, as GDAL counts (a single int is one band). ``stretch``: ``"auto"``, ``"none"``,
    ``[low, high]`` or ``[[low, high], ...]`` (one per band read). Lists are normalised to tuples; bad values
    raise :class:`ConfigError` naming the field (``bands: ...``, ``stretch: ...``).
    """

    bands: tuple[int, ...] | None = None
    stretch: str | tuple = "auto"
    alpha: str | int | None = "auto"

    def __post_init__(self):
        object.__setattr__(self, "bands", _check_bands(self.bands))
        object.__setattr__(self, "stretch", _check_stretch(self.stretch))
        a = self.alpha
        if isinstance(a, str) and a.lower() == "none":
            object.__setattr__(self, "alpha", None)
        elif not (a is None or a == "auto" or (_is_int(a) and a >= 1)):
            raise ConfigError(f"alpha: expected 'auto' (the band the file marks as alpha), a band number counted "
                              f"from 1, or none; got {a!r}")

    def to_dict(self) -> dict:
        """``{"bands": [...] | None, "stretch": "auto" | "none" | [low, high] | [[low, high], ...]}``, and
        ``"alpha"`` where it is not ``"auto"``."""
        s = self.stretch
        if not isinstance(s, str):
            s = [list(p) for p in s] if isinstance(s[0], tuple) else list(s)
        out = {"bands": list(self.bands) if self.bands is not None else None, "stretch": s}
        if self.alpha != "auto":
            out["alpha"] = self.alpha
        return out


def _is_int(v: Any) -> bool:
    return isinstance(v, numbers.Integral) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


def _check_bands(value: Any) -> tuple[int, ...] | None:
    if value is None:
        return None
    vals = [value] if _is_int(value) else value
    if (isinstance(vals, (list, tuple)) and len(vals) in (1, 3) and all(_is_int(b) and b >= 1 for b in vals)):
        return tuple(int(b) for b in vals)
    raise ConfigError(f"bands: expected 1 band (grey) or 3 bands (red, green, blue), numbered from 1 as GDAL "
                      f"counts, e.g. [3, 2, 1] or [1]; got {value!r}")


def _check_stretch(value: Any) -> str | tuple:
    def pair(p) -> tuple[float, float] | None:
        if isinstance(p, (list, tuple)) and len(p) == 2 and all(_is_number(v) for v in p):
            lo, hi = float(p[0]), float(p[1])
            if math.isfinite(lo) and math.isfinite(hi) and lo < hi:
                return lo, hi
        return None

    if isinstance(value, str) and value in STRETCHES:
        return value
    if isinstance(value, (list, tuple)) and value:
        if pair(value) is not None:
            return pair(value)
        pairs = [pair(p) for p in value]
        if len(pairs) in (1, 3) and all(p is not None for p in pairs):
            return tuple(pairs)
    raise ConfigError(f"stretch: expected 'auto', 'none', [low, high] (every band) or [[low, high], ...] (one "
                      f"per band: 1 for grey, 3 for RGB), with finite low < high; got {value!r}")


# --- which bands, which pixels ---------------------------------------------------------------------------
@dataclass(frozen=True)
class BandPlan:
    """What to read from a raster: the colour bands, the alpha band, a palette and the validity masks."""

    colour: tuple[int, ...]          # 1-based bands giving grey (1) or red, green, blue (3)
    alpha: int | None                # 1-based alpha band
    palette: np.ndarray | None       # (n, 4) uint8 RGBA table of a palette band
    nodata: tuple[float | None, ...]  # per colour band
    mask: bool                       # GDAL's per-dataset mask (internal, .msk) marks invalid pixels
    dtype: str                       # the colour bands' sample type

    def describe(self) -> dict:
        return {"dtype": self.dtype, "bands": list(self.colour), "alpha_band": self.alpha,
                "palette": self.palette is not None}


@dataclass
class Samples:
    """Pixels as read: colour ``values`` (k, h, w) with k = 1 (grey) or 3 in the source's type (a palette
    band expanded to uint8 RGB), ``alpha`` (h, w) uint8 opacity or None, ``valid`` (h, w) bool or None
    (all valid), and the :class:`BandPlan` they were read by."""

    values: np.ndarray
    alpha: np.ndarray | None
    valid: np.ndarray | None
    plan: BandPlan


def plan_bands(ds, path, rad: Radiometry) -> BandPlan:
    """The :class:`BandPlan` of an open rasterio dataset ``ds`` (the file ``path``) under ``rad``."""
    from rasterio.enums import ColorInterp, MaskFlags

    count = ds.count
    ci = list(ds.colorinterp)
    alpha = next((i + 1 for i, c in enumerate(ci) if c == ColorInterp.alpha), None)
    if rad.bands is not None:
        missing = [b for b in rad.bands if b > count]
        if missing:
            raise ConfigError(f"bands: {path} has {count} band{'s' * (count != 1)}, so band {missing[0]} does not "
                              f"exist (bands are numbered from 1, as GDAL counts)")
        colour = rad.bands
    else:
        colour = _default_bands(ci, count, path)
    if rad.alpha == "auto":
        extra = {2: 2, 4: 4}.get(count) if len(colour) == count - 1 else None
        if alpha is None and extra is not None and extra not in colour and ci[extra - 1] == ColorInterp.undefined:
            warnings.warn(f"{path}: band {extra} of {count} is read as an extra band (such as near infrared), not "
                          f"as alpha: the file does not mark it as alpha (GDAL colour interpretation undefined); "
                          f"if it is alpha, set alpha: {extra} (generator.alpha in a scene file)", SatlocWarning,
                          stacklevel=3)
    elif rad.alpha is None:
        alpha = None
    else:
        if rad.alpha > count:
            raise ConfigError(f"alpha: {path} has {count} band{'s' * (count != 1)}, so band {rad.alpha} does not "
                              f"exist (bands are numbered from 1, as GDAL counts)")
        alpha = int(rad.alpha)
    if alpha in colour:
        alpha = None
    kinds = {np.dtype(ds.dtypes[b - 1]).kind for b in colour + ((alpha,) if alpha else ())}
    if not kinds <= {"u", "i", "f"}:
        raise FormatError(f"{path}: {sorted({ds.dtypes[b - 1] for b in colour})} samples; expected integer or "
                          f"floating-point bands")
    dtype = np.result_type(*[ds.dtypes[b - 1] for b in colour]).name
    palette = None
    if len(colour) == 1 and ci[colour[0] - 1] == ColorInterp.palette:
        try:
            cmap = ds.colormap(colour[0])
        except ValueError:
            cmap = None
        if cmap:
            palette = palette_table(cmap)
    flags = ds.mask_flag_enums[colour[0] - 1]
    mask = (MaskFlags.per_dataset in flags and MaskFlags.alpha not in flags and MaskFlags.nodata not in flags)
    nodata = tuple(ds.nodatavals[b - 1] for b in colour)
    return BandPlan(tuple(colour), alpha, palette, nodata, mask, dtype)


def palette_table(cmap: dict) -> np.ndarray:
    """(n, 4) uint8 RGBA lookup table of a GDAL colour map ``{index: (r, g, b, a)}`` (missing entries: 0)."""
    table = np.zeros((max(256, max(cmap) + 1), 4), np.uint8)
    for k, v in cmap.items():
        if k >= 0:
            table[k] = v
    return table


def expand_palette(table: np.ndarray, band: np.ndarray) -> np.ndarray:
    """(h, w, 4) RGBA of a band of palette indices (indices outside the table: its last entry or its first)."""
    return table[np.clip(band, 0, len(table) - 1).astype(np.intp)]


def _default_bands(ci: list, count: int, path) -> tuple[int, ...]:
    """The colour bands of an image read without ``bands`` (see the module docstring)."""
    from rasterio.enums import ColorInterp

    if count in (1, 2):
        return (1,)
    rgb = [ci.index(c) + 1 for c in (ColorInterp.red, ColorInterp.green, ColorInterp.blue) if c in ci]
    if len(rgb) == 3:
        return tuple(rgb)
    if count in (3, 4):
        return (1, 2, 3)
    names = ", ".join(c.name for c in ci)
    raise ConfigError(f"bands: {path} has {count} bands ({names}) and GDAL names none of them red, green and "
                      f"blue; choose them with bands: [r, g, b] (e.g. [3, 2, 1]), or one band for grey, "
                      f"numbered from 1 as GDAL counts")


def read_samples(ds, plan: BandPlan, window=None) -> Samples:
    """The :class:`Samples` of ``window`` (a rasterio Window; None: the whole raster) of open dataset ``ds``."""
    idx = list(plan.colour) + ([plan.alpha] if plan.alpha else [])
    arr = ds.read(indexes=idx, window=window)
    values = arr[:len(plan.colour)]
    invalid = None
    if values.dtype.kind == "f":
        invalid = ~np.isfinite(values).all(axis=0)
    nd = [(v, d) for v, d in zip(values, plan.nodata) if d is not None]
    if nd:
        at_nodata = np.logical_and.reduce([(v == d) | (np.isnan(v) if math.isnan(d) else False) for v, d in nd])
        invalid = at_nodata if invalid is None else invalid | at_nodata
    if plan.mask:
        masked = ds.read_masks(plan.colour[0], window=window) == 0
        invalid = masked if invalid is None else invalid | masked
    alpha = _alpha8(arr[-1]) if plan.alpha else None
    if plan.palette is not None:
        rgba = expand_palette(plan.palette, values[0])
        values = np.ascontiguousarray(rgba[..., :3].transpose(2, 0, 1))
        if (rgba[..., 3] < 255).any():
            alpha = rgba[..., 3] if alpha is None else ((alpha.astype(np.uint16) * rgba[..., 3] + 127) // 255
                                                        ).astype(np.uint8)
    return Samples(values, alpha, None if invalid is None else ~invalid, plan)


def _alpha8(a: np.ndarray) -> np.ndarray:
    """An alpha band as 0..255 opacity: 8 bit as stored, 16 bit scaled by 1/257, other integers over
    0..their maximum, floats over 0..1."""
    if a.dtype == np.uint8:
        return a
    if a.dtype == np.uint16:
        return ((a.astype(np.uint32) * 255 + 32767) // 65535).astype(np.uint8)
    top = float(np.iinfo(a.dtype).max) if a.dtype.kind in "ui" else 1.0
    x = np.nan_to_num(a.astype(np.float64), nan=0.0) * (255.0 / top) + 0.5
    return np.clip(x, 0, 255).astype(np.uint8)


# --- the stretch ----------------------------------------------------------------------------------------
def dtype_range(dtype) -> tuple[float, float]:
    """The ``none`` stretch's range of a sample type: its limits for integers, 0..1 for floats."""
    dt = np.dtype(dtype)
    if dt.kind in "ui":
        info = np.iinfo(dt)
        return float(info.min), float(info.max)
    return 0.0, 1.0


def _subsample(shape: tuple[int, int]) -> int:
    """The stride of a regular subsample of at most MAX_STAT_PIXELS pixels."""
    return max(1, math.ceil(math.sqrt(shape[0] * shape[1] / MAX_STAT_PIXELS)))


def _usable(s: Samples) -> np.ndarray | None:
    """Pixels that count: valid and not fully transparent (None: all)."""
    use = s.valid
    if s.alpha is not None:
        use = s.alpha > 0 if use is None else use & (s.alpha > 0)
    return use


def levels(s: Samples, rad: Radiometry, where) -> Levels:
    """(low, high) per colour channel of ``s`` under ``rad.stretch`` (see the module docstring)."""
    k = s.values.shape[0]
    st = rad.stretch
    if not isinstance(st, str):
        if not isinstance(st[0], tuple):
            return (st,) * k
        if len(st) != k:
            raise ConfigError(f"stretch: {len(st)} ranges for the {k} band{'s' * (k != 1)} read from {where} "
                              f"({'grey' if k == 1 else 'red, green, blue'}); give {k} or one [low, high]")
        return st
    dtype = s.values.dtype
    if st == "none" or dtype == np.uint8:
        return (dtype_range(dtype),) * k
    step = _subsample(s.values.shape[1:])
    sub = s.values[:, ::step, ::step]
    use = _usable(s)
    out = []
    for c in range(k):
        v = sub[c] if use is None else sub[c][use[::step, ::step]]
        v = v.ravel()
        if v.size == 0:
            out.append(dtype_range(dtype))
            continue
        lo, hi = (float(x) for x in np.percentile(v, PERCENTILES))
        out.append((lo, hi) if hi > lo else (lo - 0.5, lo + 0.5))   # a constant band: mid-grey
    return tuple(out)


def _stretch(band: np.ndarray, low: float, high: float) -> np.ndarray:
    """One band to uint8: ``(x - low) / (high - low) * 255``, rounded half up, clipped; NaN -> 0."""
    if band.dtype == np.uint8 and (low, high) == (0.0, 255.0):
        return band
    flat = band.reshape(-1)
    out = np.empty(flat.shape, np.uint8)
    scale = 255.0 / (high - low)
    for i in range(0, flat.size, _CHUNK):
        x = flat[i:i + _CHUNK].astype(np.float64)
        x -= low
        x *= scale
        x += 0.5
        np.clip(x, 0.0, 255.0, out=x)
        x[np.isnan(x)] = 0.0
        out[i:i + _CHUNK] = x.astype(np.uint8)
    return out.reshape(band.shape)


def to_rgb8(s: Samples, rad: Radiometry, where) -> tuple[np.ndarray, dict]:
    """``(3, h, w)`` uint8 RGB of ``s`` and the record of what was applied; warns (naming ``where``, the
    file) when the result is nearly constant, mostly dark or has no valid pixel."""
    lv = levels(s, rad, where)
    chans = np.stack([_stretch(s.values[c], lo, hi) for c, (lo, hi) in enumerate(lv)])
    rgb = np.repeat(chans, 3, axis=0) if chans.shape[0] == 1 else chans
    if s.alpha is not None:
        rgb = ((rgb.astype(np.uint16) * s.alpha[None] + 127) // 255).astype(np.uint8)
    if s.valid is not None:
        rgb[:, ~s.valid] = 0
    use = _usable(s)
    record = dict(s.plan.describe(), stretch=rad.stretch if isinstance(rad.stretch, str) else "explicit",
                  levels=[[lo, hi] for lo, hi in lv],
                  valid_fraction=1.0 if use is None else round(float(use.mean()), 4) if use.size else 0.0)
    if rad.stretch == "auto" and s.values.dtype != np.uint8:
        record["percentiles"] = list(PERCENTILES)
    _check_visible(rgb, use, record, where)
    return np.ascontiguousarray(rgb), record


def _check_visible(rgb: np.ndarray, use: np.ndarray | None, record: dict, where) -> None:
    """Warn when the 8-bit picture cannot show much: no valid pixel, nearly constant, or mostly dark."""
    step = _subsample(rgb.shape[1:])
    grey = rgb[:, ::step, ::step].mean(axis=0, dtype=np.float32)
    if use is not None:
        grey = grey[use[::step, ::step]]
    how = (f"{record['dtype']} samples, bands {record['bands']}, stretch {record['stretch']!r}, levels "
           f"{[[round(v, 4) for v in p] for p in record['levels']]}")
    if grey.size == 0:
        problem = "has no valid pixel in the area read (all nodata, masked or transparent)"
    else:
        median, std = float(np.median(grey)), float(grey.std())
        found = [w for w, bad in (("mostly dark", median < DARK_MEDIAN), ("nearly constant", std < CONSTANT_STD))
                 if bad]
        if not found:
            return
        problem = (f"is {' and '.join(found)} after conversion to 8 bits (grey median {median:.1f}, std "
                   f"{std:.2f} of 255 over its valid pixels; {how}); set stretch: or bands: (see satloc.geodata.radiometry)")
    warnings.warn(f"{where}: {problem}", SatlocWarning, stacklevel=4)
