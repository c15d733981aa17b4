"""The satellite map as a capture of the world: taken at another time, by another sensor, registered with an
error; never the ground texture the camera renders.

A generated scene's tile used to be its ground texture downsampled, with roofs, canopies, shadows and cars
drawn on top: the asphalt, grass and pavement texture below a metre was the same pattern in both views, a
fingerprint no real satellite image offers. :func:`capture_tile` paints the tile of a
:class:`~satloc_env.world.layout.Layout` as a sensor would capture it. One knob, ``gap`` in [0, 1], sets every
part (:func:`capture_params`); 0 gives :func:`satloc_env.world.tile.paint_tile`'s tile byte for byte. The
parts (:data:`PARTS`), in the order they are applied, each drawn from its own generator seeded by (seed,
part), so leaving one out changes none of the others:

``time``
    Another capture time: the layout changed by :func:`satloc_env.world.revisit.changed_layout` at strength
    ``gap`` (another season's grass, road wear and patches, parked cars moved, removed and added) and another
    sun (azimuth moved by ``gap`` x 60-100 degrees either way, elevation by ``gap`` x -0.3 to +0.2 rad, kept
    in [0.35, 1.3]): the tile's shadows fall where that sun casts them.
``lean``
    The sensor off nadir by ``gap`` x :data:`MAX_OFF_NADIR_DEG` towards a random azimuth: roofs and
    canopies displaced from their footprints by height x tan(off-nadir), facades in between.
``texture``
    Texture below the sensor's resolution of the capture's own. In the ground texture the tile is painted
    from, each class's fine residual (the texture minus its Gaussian blur of ``2 gsd_m`` taken within the class,
    so that the edges between classes, lane markings included, stay where they are) becomes
    ``cos(a) residual + sin(a) noise``, ``a = min(1, 2 gap) pi / 2``, where the noise has the residual's grain
    (white noise blurred until neighbouring texels correlate as the residual's do, then high-passed alike) and
    the residual's standard deviation per class and channel (one noise field for the three channels: the
    texture's grain is in its brightness). From ``gap`` 0.5 on, no sub-resolution texture of the ground
    survives.
``blur``
    The sensor's point spread: a Gaussian of ``gsd_m / 2`` (``gsd_m = mpp (1 + gap)``, 0.3 m on a 0.2 m tile
    at 0.5).
``registration``
    A georegistration error: a smooth random warp (displacements drawn every :data:`WARP_SPACING_M` and
    interpolated) of RMS ``gap`` x :data:`MAX_REGISTRATION_RMS_M`; the labels move with the image. Truth stays
    in the world frame: the warp is part of what a localizer must live with.
``jpeg``
    Compression: JPEG at quality ``100 - 40 gap`` (80 at 0.5).

A scene over an image (:func:`capture_image`) has no layout to paint from: its ground is the image itself.
Its map is the image captured the same way without ``lean`` (the image already is a view from above) and
without ``texture`` or ``coarse_texture`` (:data:`IMAGE_SKIPS`): the world changed at the capture's time where
its labels say what lies there (season, road wear), blurred, warped and compressed. An image has no texture
below its own resolution, which is all ``texture`` replaces in a painted world; applied to an image it
replaced the image's own detail below 2 GSDs within each label class, the markings, cars and kerbs of labels
that hold only the roads included (Vienna at 0.3 m: single-frame median 1.71 m with it, 0.35 m without;
docs/results.md). The camera keeps seeing the image as it is, so the figures of a scene over an image are
an upper bound ("same image, an upper bound").

:data:`DEFAULT_GAP` (0.5) is a tile captured by a 0.3 m sensor 15 degrees off nadir, registered to 0.3 m
RMS, at JPEG quality 80, in another season with another sun and other parked cars. What that rests on
(orders of magnitude, not a survey): the sharpest commercial satellite imagery is delivered at 0.3-0.5 m,
collected up to a few tens of degrees off nadir; orthoimagery registered with ground control is good to a
few decimetres, while a satellite's own geolocation without control is metres (WorldView-3's specification:
under 3.5 m CE90), which ``gap`` towards 1 only begins to cover; imagery is usually distributed compressed.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from satloc.errors import ConfigError
from satloc.labels import CLASS_ID

from .layout import Layout
from .revisit import changed_layout
from .tile import SHADOW_GAIN, paint_tile, shadow_mask
from .traffic import TRAFFIC_PER_KM, traffic_cars

__all__ = ["PARTS", "DEFAULT_GAP", "Capture", "capture_params", "capture_tile", "capture_image", "class_lowpass",
           "fine_residual", "road_cover", "texture_correlation", "OPTIONAL_PARTS", "IMAGE_SKIPS"]

#: the parts of a capture, in the order they are applied
PARTS = ("time", "lean", "texture", "blur", "registration", "jpeg")
#: parts a capture may be asked for that the default leaves out (issue 46, being measured): ``coarse_texture``
#: makes each class's texture below :data:`COARSE_TEXTURE_M` the capture's own as well, with the ground's
#: spectrum (random phases), after ``texture``; ``traffic`` puts cars driving in the lanes at the capture's
#: instant (:func:`satloc_env.world.traffic.traffic_cars`, ``min(1, 2 gap)`` x
#: :data:`~satloc_env.world.traffic.TRAFFIC_PER_KM` per km of lane), after ``time``; ``deep_shadows`` paints the
#: cast shadows at :data:`REAL_SHADOW_GAIN` of the lit ground's brightness instead of the tiles' 0.55
OPTIONAL_PARTS = ("coarse_texture", "traffic", "deep_shadows")
#: the parts a scene over an image leaves out of its capture (:func:`capture_image`): an image has no texture
#: below its own resolution to replace
IMAGE_SKIPS = ("lean", "texture", "coarse_texture")
#: the scale (metres) below which ``coarse_texture`` replaces the ground's texture: twice the generator's
#: coarsest texture layer (12 m)
COARSE_TEXTURE_M = 24.0
#: the brightness of asphalt in a cast shadow over sunlit asphalt in a real orthophoto: the canton of Zurich's
#: 2014 summer orthophoto at 0.5 m (docs/tools/tile_realism.py), modes of the grey level on carriageways 56
#: and 174
REAL_SHADOW_GAIN = 0.32
#: a realistic gap (see the module docstring)
DEFAULT_GAP = 0.5
#: off-nadir angle (degrees) at gap 1
MAX_OFF_NADIR_DEG = 30.0
#: RMS of the registration error (metres) at gap 1
MAX_REGISTRATION_RMS_M = 0.6
#: spacing (metres) of the registration warp's random displacements
WARP_SPACING_M = 40.0
#: the capture's own texture replaces what lies below this many GSDs (a Gaussian of that sigma): sub-metre
#: texture entirely, and most of it up to a couple of metres
TEXTURE_SCALE = 2.0
_PART_SEED = {"time": 21, "lean": 22, "texture": 23, "blur": 24, "registration": 25, "jpeg": 26,
              "coarse_texture": 27, "traffic": 28, "deep_shadows": 29}


@dataclass(frozen=True)
class Capture:
    """The settings of one capture (:func:`capture_params`)."""

    gap: float
    gsd_m: float                 # the sensor's ground sample distance
    time: float                  # strength of the capture time's change of the world
    off_nadir_deg: float
    texture: float               # fraction of a right angle: 0 the ground's texture, 1 the capture's own
    registration_rms_m: float
    jpeg_quality: int | None     # None: no compression


def capture_params(gap: float, mpp: float) -> Capture:
    """The capture of knob value ``gap`` for a tile of ``mpp`` metres per pixel."""
    gap = float(gap)
    if not 0.0 <= gap <= 1.0:   # False for NaN
        raise ConfigError(f"satellite_gap: expected a value in [0, 1], got {gap}")
    return Capture(gap=gap, gsd_m=mpp * (1.0 + gap), time=gap, off_nadir_deg=MAX_OFF_NADIR_DEG * gap,
                   texture=min(1.0, 2.0 * gap), registration_rms_m=MAX_REGISTRATION_RMS_M * gap,
                   jpeg_quality=None if gap == 0.0 else int(round(100 - 40 * gap)))


def _rng(seed: int, part: str) -> np.random.Generator:
    return np.random.default_rng([int(seed), _PART_SEED[part]])


def capture_tile(lay: Layout, mpp: float, seed: int, gap: float, parts: Iterable[str] = PARTS
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(image (h, w, 3) uint8, labels (h, w) uint8) of the tile of ``lay`` at ``mpp`` captured with knob
    ``gap`` (see the module docstring); ``gap`` 0, or no ``parts``, is :func:`paint_tile`'s tile. Deterministic
    for (``lay``, ``mpp``, ``seed``, ``gap``, ``parts``)."""
    cap, parts = _checked(gap, mpp, parts)
    if cap.gap == 0.0 or not parts:
        return paint_tile(lay, mpp, seed)
    lay, lean = _captured_layout(lay, cap, seed, parts)
    img, labels = paint_tile(lay, mpp, seed, lean=lean, shadow_gain=_shadow_gain(parts))
    return _sensor(img, labels, cap, mpp, seed, parts)


def _shadow_gain(parts: tuple[str, ...]) -> float:
    return REAL_SHADOW_GAIN if "deep_shadows" in parts else SHADOW_GAIN


def _captured_layout(lay: Layout, cap: Capture, seed: int, parts: tuple[str, ...]
                     ) -> tuple[Layout, tuple[float, float]]:
    """The layout as the capture sees it and the sensor's lean (east, north per metre of height)."""
    lay = _captured_ground(lay, cap, seed, parts)
    lean = (0.0, 0.0)
    if "lean" in parts:
        r = _rng(seed, "lean")
        az = r.uniform(0.0, 2 * math.pi)
        t = math.tan(math.radians(cap.off_nadir_deg))
        lean = (t * math.cos(az), t * math.sin(az))
    return lay, lean


def road_cover(lay: Layout, mpp: float, seed: int, gap: float, parts: Iterable[str] = PARTS) -> dict:
    """What hides the road in the tile :func:`capture_tile` makes, as fractions of the road's pixels (``road`` and
    ``lane_marking`` of the ground's labels at ``mpp``), before the sensor's blur and warp: ``car`` (parked and,
    with the ``traffic`` part, driving), ``canopy`` (tree crowns over it), ``building`` (roofs and facades
    leaning over it off nadir), ``shadow`` (road still seen but in a shadow at the capture's sun), ``open`` (the
    rest); and ``marking_contrast``: the lane markings' mean grey level over the road's, minus 1, in the
    captured tile (NaN without markings). Measures to hold against real orthophotos (issue 46)."""
    cap, parts = _checked(gap, mpp, parts)
    copy = cap.gap == 0.0 or not parts
    seen, lean = (lay, (0.0, 0.0)) if copy else _captured_layout(lay, cap, seed, parts)
    painted, labels = paint_tile(seen, mpp, seed, lean=lean, shadow_gain=_shadow_gain(parts))
    h, w = labels.shape
    k = int(round(mpp / lay.ground_mpp))
    ground = lay.ground_labels[k // 2: h * k: k, k // 2: w * k: k]
    road = np.isin(ground, (CLASS_ID["road"], CLASS_ID["lane_marking"]))
    n = max(int(road.sum()), 1)
    out = {name: float((road & (labels == CLASS_ID[cls])).sum()) / n
           for name, cls in (("car", "car"), ("canopy", "tree"), ("building", "building"))}
    visible = road & np.isin(labels, (CLASS_ID["road"], CLASS_ID["lane_marking"]))
    out["shadow"] = float((visible & (shadow_mask(seen, mpp, (h, w)) > 0)).sum()) / n
    out["open"] = float(visible.sum()) / n - out["shadow"]
    # the captured tile (capture_tile's, from the same painting): the sensor's blur, warp and compression
    img, lab = (painted, labels) if copy else _sensor(painted, labels.copy(), cap, mpp, seed, parts)
    grey = cv2.cvtColor(np.ascontiguousarray(img, np.uint8), cv2.COLOR_RGB2GRAY).astype(np.float64)
    mark, asphalt = lab == CLASS_ID["lane_marking"], lab == CLASS_ID["road"]
    out["marking_contrast"] = (float(grey[mark].mean() / max(grey[asphalt].mean(), 1e-6) - 1.0)
                               if mark.any() and asphalt.any() else float("nan"))
    return out


def capture_image(lay: Layout, mpp: float, seed: int, gap: float, parts: Iterable[str] = PARTS
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The map of a scene over an image (``lay.ground_rgb`` is the image, at ``mpp``) captured with knob
    ``gap``: the parts of :func:`capture_tile` but those of :data:`IMAGE_SKIPS`; ``gap`` 0, or no other
    ``parts``, is the image itself."""
    cap, parts = _checked(gap, mpp, parts)
    parts = tuple(p for p in parts if p not in IMAGE_SKIPS)
    if cap.gap == 0.0 or not parts:
        return lay.ground_rgb, lay.ground_labels
    lay = _captured_ground(lay, cap, seed, parts)   # (the capture's sun has nothing to shade in an image)
    return _sensor(lay.ground_rgb, lay.ground_labels.copy(), cap, mpp, seed, parts)


def _captured_ground(lay: Layout, cap: Capture, seed: int, parts: tuple[str, ...]) -> Layout:
    """``lay`` at the capture's time, its ground texture below the sensor's resolution the capture's own, as
    ``parts`` ask (a new layout; ``lay`` is not touched)."""
    if "time" in parts:
        lay = _capture_time(lay, cap.time, seed)
    if "traffic" in parts:
        lay = dataclasses.replace(lay, cars=list(lay.cars) + traffic_cars(
            lay, TRAFFIC_PER_KM * min(1.0, 2.0 * cap.gap), _rng(seed, "traffic")))
    if "texture" in parts:
        lay = dataclasses.replace(lay, ground_rgb=_own_texture(
            lay.ground_rgb, lay.ground_labels, TEXTURE_SCALE * cap.gsd_m / lay.ground_mpp, cap.texture,
            _rng(seed, "texture")))
    if "coarse_texture" in parts:
        lay = dataclasses.replace(lay, ground_rgb=_spectral_texture(
            lay.ground_rgb, lay.ground_labels, COARSE_TEXTURE_M / 2 / lay.ground_mpp, cap.texture,
            _rng(seed, "coarse_texture")))
    return lay


def _checked(gap: float, mpp: float, parts: Iterable[str]) -> tuple[Capture, tuple[str, ...]]:
    cap = capture_params(gap, mpp)
    parts = tuple(parts)
    unknown = sorted(set(parts) - set(PARTS) - set(OPTIONAL_PARTS))
    if unknown:
        raise ConfigError(f"satellite capture parts: unknown {unknown}; the parts are {list(PARTS + OPTIONAL_PARTS)}")
    return cap, parts


def _sensor(img: np.ndarray, labels: np.ndarray, cap: Capture, mpp: float, seed: int, parts: tuple[str, ...]
            ) -> tuple[np.ndarray, np.ndarray]:
    """The sensor's blur, the registration warp and the compression, as ``parts`` ask."""
    img = img.astype(np.float32)
    if "blur" in parts:
        img = cv2.GaussianBlur(img, (0, 0), 0.5 * cap.gsd_m / mpp, borderType=cv2.BORDER_REFLECT)
    out = np.clip(np.round(img), 0, 255).astype(np.uint8)
    if "registration" in parts and cap.registration_rms_m > 0:
        out, labels = _warp(out, labels, cap.registration_rms_m / mpp, WARP_SPACING_M / mpp,
                            _rng(seed, "registration"))
    if "jpeg" in parts and cap.jpeg_quality is not None:
        ok, buf = cv2.imencode(".jpg", out[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, cap.jpeg_quality])
        out = np.ascontiguousarray(cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1])
    return out, labels


def _capture_time(lay: Layout, strength: float, seed: int) -> Layout:
    """The world at the capture's time: another season, road wear, parked cars, and another sun (the tile's
    shadows are drawn at it; none are cast onto the ground texture)."""
    r = _rng(seed, "time")
    out = changed_layout(lay, strength, int(r.integers(0, 2**31)), parts=("vegetation", "road", "cars"))
    if out is lay:
        out = dataclasses.replace(lay)
    d_az = math.radians(100.0) * strength * r.uniform(0.6, 1.0) * r.choice([-1.0, 1.0])
    out.sun_azimuth = float((lay.sun_azimuth + d_az) % (2 * math.pi))
    out.sun_elevation = float(np.clip(lay.sun_elevation + strength * r.uniform(-0.3, 0.2), 0.35, 1.3))
    return out


def fine_residual(img: np.ndarray, sigma_px: float) -> np.ndarray:
    """The texture below a scale: ``img`` (float) minus its Gaussian blur of ``sigma_px`` pixels, per channel."""
    img = np.asarray(img, np.float32)
    return img - cv2.GaussianBlur(img, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)


def class_lowpass(img: np.ndarray, labels: np.ndarray, sigma_px: float) -> np.ndarray:
    """``img`` (float) blurred by a Gaussian of ``sigma_px`` within each class of ``labels`` (normalised
    convolution: no class's colour leaks across an edge). Computed at 1/f of the resolution (f = sigma_px / 2,
    at least 1) and interpolated back: it is a low-pass."""
    img = np.asarray(img, np.float32)
    h, w = labels.shape
    f = max(1, int(sigma_px // 2))
    small = (max(1, w // f), max(1, h // f))
    low = np.zeros_like(img)
    for c in np.unique(labels):
        m = (labels == c).astype(np.float32)
        num = img * m[..., None]
        if f > 1:
            num = cv2.resize(num, small, interpolation=cv2.INTER_AREA)
            m_s = cv2.resize(m, small, interpolation=cv2.INTER_AREA)
        else:
            m_s = m
        num = cv2.GaussianBlur(num, (0, 0), sigma_px / f, borderType=cv2.BORDER_REFLECT)
        den = cv2.GaussianBlur(m_s, (0, 0), sigma_px / f, borderType=cv2.BORDER_REFLECT)
        mean = num / np.maximum(den, 1e-6)[..., None]
        if f > 1:
            mean = cv2.resize(mean, (w, h), interpolation=cv2.INTER_LINEAR)
        low += mean * m[..., None]
    return low


def _own_texture(img: np.ndarray, labels: np.ndarray, sigma_px: float, amount: float,
                 r: np.random.Generator) -> np.ndarray:
    """(uint8) ``img`` with the fraction ``amount`` (as an angle) of each class's texture below ``sigma_px``
    replaced by noise of the same band and of the same standard deviation per class and channel."""
    img = np.asarray(img, np.float32)
    low = class_lowpass(img, labels, sigma_px)
    res = img - low
    # noise with the residual's grain: white noise blurred so that neighbouring texels correlate as the
    # residual's do (a Gaussian of s correlates neighbours by exp(-1 / (4 s^2))), then the same high-pass
    rho = _neighbour_correlation(res.mean(axis=2))
    n = r.standard_normal(labels.shape).astype(np.float32)
    if rho > 0.05:
        n = cv2.GaussianBlur(n, (0, 0), math.sqrt(-1.0 / (4.0 * math.log(min(rho, 0.95)))),
                             borderType=cv2.BORDER_REFLECT)
    n = fine_residual(n, sigma_px)
    new = (n / _class_std(n, labels)[labels])[..., None] * _class_std(res, labels)[labels]
    a = amount * math.pi / 2
    return np.clip(np.round(low + math.cos(a) * res + math.sin(a) * new), 0, 255).astype(np.uint8)


def _spectral_texture(img: np.ndarray, labels: np.ndarray, sigma_px: float, amount: float,
                      r: np.random.Generator) -> np.ndarray:
    """(uint8) ``img`` with the fraction ``amount`` (as an angle) of each class's texture below ``sigma_px`` (all
    of it up to about twice that scale) replaced by a field of the same power spectrum and random phases (a
    phase-randomised surrogate of the class's residual: its own pattern, the ground's grain at every scale),
    scaled to the residual's standard deviation per class and channel; one field for the three channels."""
    img = np.asarray(img, np.float32)
    low = class_lowpass(img, labels, sigma_px)
    res = img - low
    grey = res.mean(axis=2)
    phase = np.exp(1j * np.angle(np.fft.rfft2(r.standard_normal(grey.shape))))
    new = np.zeros_like(grey)
    for c in np.unique(labels):
        m = labels == c
        if m.sum() < 64:
            continue
        amp = np.abs(np.fft.rfft2(np.where(m, grey, 0.0)))
        new[m] = np.fft.irfft2(amp * phase, s=grey.shape)[m]
    new = (new / _class_std(new, labels)[labels])[..., None] * _class_std(res, labels)[labels]
    a = amount * math.pi / 2
    return np.clip(np.round(low + math.cos(a) * res + math.sin(a) * new), 0, 255).astype(np.uint8)


def _neighbour_correlation(x: np.ndarray) -> float:
    """Correlation of horizontally and vertically neighbouring values of ``x`` (h, w)."""
    a = np.concatenate([x[:, :-1].ravel(), x[:-1, :].ravel()])
    b = np.concatenate([x[:, 1:].ravel(), x[1:, :].ravel()])
    c = np.corrcoef(a, b)[0, 1]
    return float(c) if np.isfinite(c) else 0.0


def _class_std(x: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Standard deviation of ``x`` (h, w) or (h, w, k) within each class id of ``labels``: (256,) or (256, k),
    1 where a class is absent or constant."""
    lab = labels.ravel().astype(np.intp)
    flat = x.reshape(lab.size, -1).astype(np.float64)
    n = np.bincount(lab, minlength=256).astype(np.float64)[:, None]
    s1 = np.stack([np.bincount(lab, flat[:, k], minlength=256) for k in range(flat.shape[1])], 1)
    s2 = np.stack([np.bincount(lab, flat[:, k] ** 2, minlength=256) for k in range(flat.shape[1])], 1)
    var = s2 / np.maximum(n, 1) - (s1 / np.maximum(n, 1)) ** 2
    sd = np.sqrt(np.maximum(var, 0.0))
    sd[sd == 0] = 1.0
    sd = sd.astype(np.float32)
    return sd[:, 0] if x.ndim == 2 else sd


def _warp(img: np.ndarray, labels: np.ndarray, rms_px: float, spacing_px: float,
          r: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A smooth random displacement field of RMS ``rms_px`` (both axes together), correlated over about
    ``spacing_px``; the image resampled bilinearly, the labels by nearest neighbour."""
    h, w = labels.shape
    gh, gw = int(math.ceil(h / spacing_px)) + 3, int(math.ceil(w / spacing_px)) + 3
    d = r.standard_normal((2, gh, gw)).astype(np.float32)
    field = np.stack([cv2.resize(d[k], (int(gw * spacing_px), int(gh * spacing_px)),
                                 interpolation=cv2.INTER_CUBIC)[:h, :w] for k in range(2)])
    rms = float(np.sqrt((field ** 2).sum(axis=0).mean())) or 1.0
    field *= rms_px / rms
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    mx, my = xx + field[0], yy + field[1]
    out = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    lab = cv2.remap(labels, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REFLECT)
    return out, lab


#: the scales (metres) at which :func:`texture_correlation` compares the ground and the map
CORRELATION_SCALES_M = (0.6, 1.2, 2.4, 4.8, 9.6)


def texture_correlation(ground_rgb: np.ndarray, ground_labels: np.ndarray, map_rgb: np.ndarray,
                        map_labels: np.ndarray, classes: Iterable[str] = ("road", "grass"),
                        scales_m: Iterable[float] = CORRELATION_SCALES_M, mpp: float = 0.2) -> dict:
    """How much of the ground's texture the map shows: per class and scale, the correlation between the grey level
    of the ground texture the camera renders (``ground_rgb``, ``ground_labels``: any resolution, the same
    extent) and of the map (``map_rgb``, ``map_labels`` at ``mpp`` metres a pixel) over the pixels that both label
    as the class, each band-passed around the scale within the class alone (a difference of Gaussians of sigma
    s/4 and s/2, each a normalised convolution over the class's pixels, so that class edges and markings, which a
    capture keeps, do not enter), where the class fills at least half of the wider Gaussian's window. A capture
    that shares no texture with the ground gives about 0 at every scale; the ground against itself gives 1.
    Returns ``{class: {scale: correlation}}`` (NaN where too few pixels qualify)."""

    h, w = map_labels.shape
    def gray(img):
        return cv2.cvtColor(np.ascontiguousarray(img, np.uint8), cv2.COLOR_RGB2GRAY).astype(np.float32)

    g = cv2.resize(gray(ground_rgb), (w, h), interpolation=cv2.INTER_AREA)
    g_lab = cv2.resize(np.ascontiguousarray(ground_labels), (w, h), interpolation=cv2.INTER_NEAREST)
    m = gray(map_rgb)
    out: dict = {}
    for name in classes:
        c = CLASS_ID[name]
        mask = ((g_lab == c) & (map_labels == c)).astype(np.float32)
        out[name] = {}
        for s in scales_m:
            lo, hi = s / 4 / mpp, s / 2 / mpp
            support = {sig: cv2.GaussianBlur(mask, (0, 0), sig) for sig in (lo, hi)}
            use = (mask > 0) & (support[hi] >= 0.5)
            if use.sum() < 100:
                out[name][float(s)] = float("nan")
                continue

            def band(x):
                return (cv2.GaussianBlur(x * mask, (0, 0), lo) / np.maximum(support[lo], 1e-6)
                        - cv2.GaussianBlur(x * mask, (0, 0), hi) / np.maximum(support[hi], 1e-6))

            a, b = band(g)[use], band(m)[use]
            a, b = a - a.mean(), b - b.mean()
            den = math.sqrt(float((a * a).sum()) * float((b * b).sum()))
            out[name][float(s)] = float((a * b).sum() / den) if den > 0 else float("nan")
    return out
