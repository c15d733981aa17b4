"""Revisits that change: a per-pass change of what lies in a scene, for query passes.

A revisit of a place on another day differs from the database pass by more than its colours
(:class:`satloc_env.envs.occluders.Appearance`, a global lookup table, to which SIFT is nearly invariant): the sun
stands elsewhere, so shadows fall elsewhere; the road has been worn and patched; parked cars have come and
gone; grass and trees are in another season. :func:`changed_layout` makes such a revisit of a scene
:class:`~satloc_env.world.layout.Layout`: a new layout (the original is not touched) from which
:func:`satloc_env.world.meshes.build_world` builds the world the ground camera sees. :func:`changed_world` builds that
world, changes its tree foliage (:func:`change_foliage`: foliage lives in the world's object textures, not in
the layout) and keeps the last two worlds it built. The satellite tile is never changed: it is the map, the
scene's ``satmap``, painted once from the original layout.

``strength`` in [0, 1] scales every part (0: the layout itself, unchanged; 1: a strong change) and ``seed``
(an integer >= 0) draws them: the same (strength, seed) gives the same layout, byte for byte. Each part draws
from its own generator, seeded by (seed, part), so leaving a part out (``parts``) does not change the others.
The parts (:data:`PARTS`), in the order they are applied:

``vegetation``
    A season, one of :data:`SEASONS`: the ``grass`` texels are blended a fraction ``strength`` x 0.4-0.8
    (varying by +-60 % over 12 m patches) of the way to its grass colour, by a per-channel gain (the
    texture's contrast stays). In :func:`changed_world` (:func:`change_foliage`) the foliage texels of the
    trees (``tree`` texels whose green is at least their red: not bark) are blended ``strength`` x 0.35-0.7
    of the way to its foliage colour, and their leaf-scale pattern partly moves (leaves in another wind,
    grown or fallen): ``0.6 strength`` of each texel taken from the foliage 3-5 texels away, plus new
    2-texel grain of ``0.18 strength``.
``road``
    Road wear on the ``road`` and ``parking`` classes (:mod:`satloc.labels`): patches (repairs in fresh,
    darker asphalt, x 0.6-0.8, 60 %; worn, lighter ones, x 1.12-1.3), rectangles of 1.5-7 m x 0.8-3.5 m
    along or across the texture's axes with a dark sealed outline, one per :data:`PATCH_M2` m^2 of road at
    strength 1 (Poisson); cracks, random walks of 3-10 steps of 0.3-1.2 m, one per :data:`CRACK_M2` m^2,
    darkened x 0.6 (30 % of them sealed: thicker, x 0.42); lane markings (``lane_marking``) faded towards
    the asphalt's median colour by ``strength`` x 0.25-0.6 (8 m patches) x 1-1.7 (per revisit), at most
    85 %. The labels stay as they are.
``cars``
    Parked cars (``layout.cars``) come and go: each is removed with probability 0.45 ``strength`` or moved
    with 0.35 ``strength`` along its own axis (in a parking stall, on ``parking`` ground, by up to 0.5 m; at
    a curb by up to 2.5 m; elsewhere, e.g. a driveway, 0.8 m), within 0.15 m sideways and about 0.03 rad of
    yaw, unless that brings it too close to another car or onto other ground. Then about 0.35 ``strength``
    x (number of cars) are added (binomial), as far as there are free parking places: a stall beside a
    parked car's (2.6 m and 5.2 m sideways) or a curb place before or after one (6.5 m and 13 m along it),
    where the ground (at the place, 3 m before and behind it, and 2 m to either side of those) is of the
    same kind (drivable or not) as around the car it comes from (so never in an intersection or beyond the
    end of a lot) and no car stands within 0.9 place spacings. New cars get a random colour and size; kept
    cars keep their order.
``shadows``
    The sun moves: its azimuth by ``strength`` x 60-100 degrees either way (:data:`SUN_AZIMUTH_MAX_DEG`), its
    elevation by ``strength`` x -0.45 to +0.2 rad, kept in [0.3, 1.3] rad (lower sun, longer shadows). The
    new sun is the layout's ``sun_azimuth`` / ``sun_elevation``, so the world's baked facade and object
    shading follow it (:func:`satloc_env.world.meshes.build_world`). Buildings, tree canopies and trunks and the
    revisit's parked cars cast shadows away from that sun onto the ground texture ``ground_rgb``: each
    object's outline swept along the shadow direction over its height (buildings: footprint and each wall;
    trees: the canopy disc from its bottom to its top height, 85 % as dark; cars: their box), edges blurred
    by 0.1 m, not inside building footprints (an image scene's roofs are its ground image). A shadowed texel
    is multiplied per channel by ``1 - depth (1 - SHADOW_RGB)`` (:data:`SHADOW_RGB`, bluish: lit by the sky
    only), ``depth = min(1, 2 strength) x U(0.75, 1)``. The database pass's ground has no cast shadows (the
    tile has them, at the scene's sun), so the revisit shows shadows where its database did not.

Cost on ``residential`` (352 m x 352 m, ground 3520 x 3520 texels, 79 cars, 223 trees, 96 buildings), on
the shared 2-core machine: the layout about 2 s, the world (:func:`changed_world`) about 4.5 s in all.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Iterable

import cv2
import numpy as np

from satloc.errors import ConfigError
from satloc.labels import CLASS_ID as C
from satloc.labels import DRIVABLE

from .furniture import furniture_parts
from .layout import Car, Layout
from .paint import fill_poly, noise, rect_poly

__all__ = ["PARTS", "SEASONS", "change_foliage", "changed_layout", "changed_world", "check_parts"]

#: the parts of a change, in the order they are applied
PARTS = ("vegetation", "road", "cars", "shadows")
#: largest change of the sun's azimuth (degrees) at strength 1; the change is 60-100 % of strength x this
SUN_AZIMUTH_MAX_DEG = 100.0
#: colour of full shadow as a fraction of the lit colour, per channel (RGB): lit by the bluish sky only
SHADOW_RGB = (0.5, 0.54, 0.64)
#: square metres of road per repair patch, and per crack, at strength 1
PATCH_M2 = 120.0
CRACK_M2 = 60.0
#: (name, grass colour, foliage colour) the vegetation is blended towards
SEASONS = (
    ("dry summer", (160, 146, 88), (108, 114, 52)),
    ("autumn", (132, 116, 66), (166, 106, 46)),
    ("spring", (66, 128, 44), (60, 126, 42)),
    ("winter", (112, 112, 88), (92, 94, 66)),
)
#: mean foliage colour of the world's tree textures (satloc_env.world.meshes), the reference of the foliage gain
_FOLIAGE_REF = np.array([62.0, 102.0, 53.0])
_PART_SEED = {"vegetation": 4, "road": 2, "cars": 3, "shadows": 1}


def _rng(seed: int, part: str, k: int = 0) -> np.random.Generator:
    return np.random.default_rng([seed, _PART_SEED[part], k])


def _check(strength: float, seed: int, parts: Iterable[str]) -> tuple[float, int, tuple[str, ...]]:
    strength = float(strength)
    if not 0.0 <= strength <= 1.0:   # False for NaN
        raise ConfigError(f"change: expected a strength in [0, 1], got {strength}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"change seed: expected an integer >= 0, got {seed!r}")
    return strength, int(seed), check_parts(parts, "change parts")


def check_parts(parts: Iterable[str], where: str) -> tuple[str, ...]:
    """``parts`` as a tuple; :class:`satloc.ConfigError` naming ``where`` for a part not in :data:`PARTS`."""
    parts = tuple(parts)
    unknown = sorted(set(parts) - set(PARTS))
    if unknown:
        raise ConfigError(f"{where}: unknown {unknown}; the parts are {list(PARTS)}")
    return parts


def changed_layout(layout: Layout, strength: float, seed: int, parts: Iterable[str] = PARTS,
                   cast: bool = True) -> Layout:
    """A revisit of ``layout`` (see the module docstring): a new :class:`Layout` with another sun, cast
    shadows, road wear, moved parked cars and another season's grass, deterministic for (``strength``,
    ``seed``). ``parts``: which of :data:`PARTS` to apply; ``cast`` False moves the sun without painting its
    shadows (for a scene whose world casts them itself, :attr:`satloc_env.world.scene.SceneSpec.casts_shadows`).
    ``strength`` 0 (or no parts) returns ``layout`` itself. :class:`satloc.ConfigError` for a strength outside
    [0, 1], a negative seed or an unknown part."""
    strength, seed, parts = _check(strength, seed, parts)
    if strength == 0.0 or not parts:
        return layout
    lay = dataclasses.replace(
        layout, ground_rgb=layout.ground_rgb.copy(), ground_labels=layout.ground_labels.copy(),
        buildings=[dataclasses.replace(b, footprint=np.array(b.footprint, np.float64)) for b in layout.buildings],
        trees=[dataclasses.replace(t) for t in layout.trees], cars=[dataclasses.replace(c) for c in layout.cars])
    if "vegetation" in parts:
        _vegetation(lay, strength, seed)
    if "road" in parts:
        _road_wear(lay, strength, _rng(seed, "road"))
    if "cars" in parts:
        lay.cars = _move_cars(lay, strength, _rng(seed, "cars"))
    if "shadows" in parts:
        r = _rng(seed, "shadows")
        d_az = math.radians(SUN_AZIMUTH_MAX_DEG) * strength * r.uniform(0.6, 1.0) * r.choice([-1.0, 1.0])
        lay.sun_azimuth = float((layout.sun_azimuth + d_az) % (2 * math.pi))
        lay.sun_elevation = float(np.clip(layout.sun_elevation + strength * r.uniform(-0.45, 0.2), 0.3, 1.3))
        depth = min(1.0, 2.0 * strength) * r.uniform(0.75, 1.0)
        if cast:
            cast_shadows(lay, depth)
    return lay


# --- vegetation --------------------------------------------------------------------------------------------
def _season(strength: float, seed: int) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(grass colour, foliage colour, grass blend, foliage blend) of the revisit's season."""
    r = _rng(seed, "vegetation")
    _, grass, foliage = SEASONS[int(r.integers(len(SEASONS)))]
    return (np.asarray(grass, np.float64), np.asarray(foliage, np.float64), strength * r.uniform(0.4, 0.8),
            strength * r.uniform(0.35, 0.7))


def _gain(pixels: np.ndarray, target: np.ndarray, reference: np.ndarray, blend) -> np.ndarray:
    """``pixels`` (N, 3) uint8 recoloured by the per-channel gain that takes ``reference`` a fraction ``blend``
    (scalar or (N,)) of the way to ``target``."""
    b = np.asarray(blend, np.float32).reshape(-1, 1)
    gain = 1.0 + b * (target / np.maximum(reference, 1.0) - 1.0).astype(np.float32)
    return np.clip(pixels * gain + 0.5, 0, 255).astype(np.uint8)


def _vegetation(lay: Layout, strength: float, seed: int) -> None:
    grass = lay.ground_labels == C["grass"]
    if not grass.any():
        return
    target, _, blend, _ = _season(strength, seed)
    rgb = lay.ground_rgb
    patchy = noise(grass.shape, _rng(seed, "vegetation", 1), (max(2.0, 12.0 / lay.ground_mpp),), [1.0])
    px = rgb[grass]
    reference = px[:: max(1, len(px) // 50000)].mean(axis=0)
    rgb[grass] = _gain(px, target, reference, np.clip(blend * (1.0 + 0.6 * patchy[grass]), 0.0, 0.95))


def change_foliage(world, strength: float, seed: int) -> None:
    """Give the foliage of ``world``'s trees (texels labelled ``tree`` whose green is at least their red, so
    not bark) the season of (``strength``, ``seed``), in place: blended towards its foliage colour, and the
    leaf-scale pattern partly moved (leaves in another wind, grown or fallen): a texel becomes
    ``((1 - k) t + k t') (1 + 0.3 k n)`` with ``t'`` the foliage 3-5 texels away, ``n`` new 2-texel noise in
    [-1, 1] and ``k = 0.6 strength``."""
    strength, seed, _ = _check(strength, seed, ())
    _, target, _, blend = _season(strength, seed)
    if blend <= 0:
        return
    r = _rng(seed, "vegetation", 2)
    k = 0.6 * strength
    for mesh in world.chunks:
        if mesh.mirror:   # shares its chunk's texture, changed there
            continue
        tree = mesh.labels == C["tree"]
        rows, cols = np.flatnonzero(tree.any(axis=1)), np.flatnonzero(tree.any(axis=0))
        if rows.size == 0:
            continue
        box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
        tex = mesh.texture[box]              # a view: the texture changes in place
        sel = tree[box] & (tex[..., 1] >= tex[..., 0])
        shift = tuple(int(v) for v in r.integers(3, 6, 2) * r.choice([-1, 1], 2))
        moved = np.roll(tex, shift, axis=(0, 1))
        both = sel & np.roll(sel, shift, axis=(0, 1))
        f = tex[sel].astype(np.float32)
        f[both[sel]] = (1 - k) * f[both[sel]] + k * moved[both].astype(np.float32)
        grain = noise(tex.shape[:2], r, (2,), [1.0])[sel]
        f *= (1 + 0.3 * k * np.clip(grain, -1.0, 1.0))[:, None]
        tex[sel] = _gain(f, target, _FOLIAGE_REF, blend)


# --- road wear ---------------------------------------------------------------------------------------------
def _road_wear(lay: Layout, strength: float, r: np.random.Generator) -> None:
    rgb, labels, mpp = lay.ground_rgb, lay.ground_labels, float(lay.ground_mpp)
    road = np.isin(labels, (C["road"], C["parking"]))
    idx = np.flatnonzero(road)
    if idx.size == 0:
        return
    h, w = road.shape
    area = idx.size * mpp * mpp
    for _ in range(int(r.poisson(strength * area / PATCH_M2))):      # repairs and worn patches
        v, u = divmod(int(idx[r.integers(idx.size)]), w)
        corners = rect_poly(u, v, r.uniform(1.5, 7.0) / mpp, r.uniform(0.8, 3.5) / mpp,
                            r.choice([0.0, math.pi / 2]) + r.normal(0.0, 0.08))
        factor = r.uniform(0.6, 0.8) if r.random() < 0.6 else r.uniform(1.12, 1.3)
        x0, y0 = np.maximum(np.floor(corners.min(0)).astype(int) - 1, 0)
        x1, y1 = np.minimum(np.ceil(corners.max(0)).astype(int) + 2, (w, h))
        if x0 >= x1 or y0 >= y1:
            continue
        m = np.zeros((y1 - y0, x1 - x0), np.uint8)
        fill_poly(m, corners - (x0, y0), 1)
        cv2.polylines(m, [np.round(corners - (x0, y0)).astype(np.int32).reshape(-1, 1, 2)], True, 2, 1)
        box = rgb[y0:y1, x0:x1]
        on = road[y0:y1, x0:x1]
        for value, f in ((1, factor), (2, 0.55)):
            sel = (m == value) & on
            box[sel] = np.clip(box[sel] * f, 0, 255).astype(np.uint8)
    cracks = np.zeros((h, w), np.uint8)
    for _ in range(int(r.poisson(strength * area / CRACK_M2))):
        v, u = divmod(int(idx[r.integers(idx.size)]), w)
        n = int(r.integers(3, 11))
        heading = r.uniform(0, 2 * math.pi) + np.cumsum(r.normal(0.0, 0.5, n))
        step = r.uniform(0.3, 1.2, n) / mpp
        pts = np.array([u, v]) + np.vstack([[0.0, 0.0], np.cumsum(np.c_[np.cos(heading), np.sin(heading)]
                                                                  * step[:, None], axis=0)])
        sealed = r.random() < 0.3
        cv2.polylines(cracks, [np.round(pts).astype(np.int32).reshape(-1, 1, 2)], False, 2 if sealed else 1,
                      max(1, round((0.2 if sealed else 0.08) / mpp)))
    for value, f in ((1, 0.6), (2, 0.42)):
        sel = (cracks == value) & road
        rgb[sel] = (rgb[sel] * f).astype(np.uint8)
    marks = labels == C["lane_marking"]
    if marks.any():                     # faded markings: towards the asphalt's colour, in patches
        asphalt = np.median(rgb.reshape(-1, 3)[idx[:: max(1, idx.size // 50000)]], axis=0)
        patchy = noise((h, w), r, (max(2.0, 8.0 / mpp),), [1.0])[marks]
        f = np.clip(strength * (0.25 + 0.35 * (patchy + 1.0) / 2.0) * r.uniform(1.0, 1.7), 0.0, 0.85)[:, None]
        rgb[marks] = np.clip(rgb[marks] * (1 - f) + asphalt * f + 0.5, 0, 255).astype(np.uint8)


# --- parked cars -------------------------------------------------------------------------------------------
#: per kind of parking place (by the ground under the car): (spacing of places, direction of the neighbouring
#: places: 0 along the car's axis, 1 across it, largest shift along the axis when moved), metres
_PLACES = {"stall": (2.6, 1, 0.5), "curb": (6.5, 0, 2.5), "other": (None, 0, 0.8)}


def _labels_at(lay: Layout, xy: np.ndarray) -> np.ndarray:
    """Ground class at map points ``xy`` (..., 2); ``void`` outside the layout."""
    uv = np.round(lay.world_to_raster(xy)).astype(np.int64)
    h, w = lay.ground_labels.shape
    inside = (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h)
    return np.where(inside, lay.ground_labels[np.clip(uv[..., 1], 0, h - 1), np.clip(uv[..., 0], 0, w - 1)],
                    C["void"])


def _context(lay: Layout, xy, yaw: float) -> tuple[bool, ...]:
    """Whether the ground is drivable at a car of heading ``yaw`` at ``xy``, 3 m before and behind it, and 2 m
    to either side of those three points."""
    c, s = math.cos(yaw), math.sin(yaw)
    along, side = np.array([c, s]) * 3.0, np.array([-s, c]) * 2.0
    pts = np.asarray(xy, np.float64) + np.array([a * along + b * side for a in (0, 1, -1) for b in (0, 1, -1)])
    return tuple(bool(v) for v in np.isin(_labels_at(lay, pts), DRIVABLE))


def _place_kind(lay: Layout, car: Car) -> str:
    lab = int(_labels_at(lay, np.asarray(car.center)))
    return "stall" if lab == C["parking"] else "curb" if lab in DRIVABLE else "other"


def _free(xy, cars: list[Car], gap: float, skip: Car | None = None) -> bool:
    return all(c is skip or math.dist(xy, c.center) >= gap for c in cars)


def _move_cars(lay: Layout, strength: float, r: np.random.Generator) -> list[Car]:
    originals = lay.cars
    kinds = [_place_kind(lay, c) for c in originals]
    cars: list[Car] = []
    for car, kind in zip(originals, kinds):
        u = r.random()
        along, across, dyaw = r.uniform(-1, 1), r.uniform(-0.15, 0.15), r.normal(0.0, 0.03)
        if u < 0.45 * strength:
            continue
        if u < 0.8 * strength:
            c, s = math.cos(car.yaw), math.sin(car.yaw)
            d = along * _PLACES[kind][2]
            xy = (car.center[0] + c * d - s * across, car.center[1] + s * d + c * across)
            gap = min(_PLACES[kind][0] or 3.0, 5.0) * 0.9
            if (_context(lay, xy, car.yaw) == _context(lay, car.center, car.yaw)
                    and _free(xy, originals + cars, gap, skip=car)):
                car = dataclasses.replace(car, center=(float(xy[0]), float(xy[1])), yaw=float(car.yaw + dyaw))
        cars.append(car)
    # free places beside / before and after the original cars, in a random order
    places = []
    for car, kind in zip(originals, kinds):
        spacing, axis, _ = _PLACES[kind]
        if spacing is None:
            continue
        c, s = math.cos(car.yaw), math.sin(car.yaw)
        unit = np.array([c, s]) if axis == 0 else np.array([-s, c])
        for k in (-2, -1, 1, 2):
            places.append((np.asarray(car.center) + k * spacing * unit, car, spacing))
    n_add = int(r.binomial(len(originals), 0.35 * strength)) if originals else 0
    palette = r.integers(20, 235, (len(places), 3))
    for i in r.permutation(len(places)):
        if n_add == 0:
            break
        xy, src, spacing = places[i]
        if _context(lay, xy, src.yaw) != _context(lay, src.center, src.yaw) or not _free(xy, cars, 0.9 * spacing):
            continue
        yaw = src.yaw + (math.pi if r.random() < 0.2 and spacing < 5 else 0.0) + r.normal(0.0, 0.03)
        cars.append(Car((float(xy[0]), float(xy[1])), float(yaw), float(r.uniform(3.9, 4.8)),
                        float(r.uniform(1.7, 1.9)), float(r.uniform(1.4, 1.65)), tuple(int(v) for v in palette[i])))
        n_add -= 1
    return cars


# --- cast shadows ------------------------------------------------------------------------------------------
def _hull(*rings: np.ndarray) -> np.ndarray:
    return cv2.convexHull(np.vstack(rings).astype(np.float32)).reshape(-1, 2).astype(np.float64)


def _circle(center, radius: float, n: int = 16) -> np.ndarray:
    a = np.linspace(0, 2 * math.pi, n, endpoint=False)
    return np.asarray(center, np.float64) + radius * np.c_[np.cos(a), np.sin(a)]


def cast_shadows(lay: Layout, depth: float) -> None:
    """Darken ``lay.ground_rgb`` (in place) where its buildings, trees, cars and street furniture shade the
    ground from ``lay``'s sun, by ``depth`` (0 to 1) of a shadow's darkening (bluish: lit by the sky alone)."""
    mpp = float(lay.ground_mpp)
    h, w = lay.ground_labels.shape
    away = -np.array([math.cos(lay.sun_azimuth), math.sin(lay.sun_azimuth)]) / math.tan(max(lay.sun_elevation, 0.15))
    solid = np.zeros((h, w), np.uint8)       # buildings, cars, trunks
    leafy = np.zeros((h, w), np.uint8)       # canopies: 85 % as dark
    px = lay.world_to_raster
    for b in lay.buildings:
        fp = np.asarray(b.footprint, np.float64)
        off = away * float(b.height)
        fill_poly(solid, px(fp + off), 1)
        for a, c in zip(fp, np.roll(fp, -1, axis=0)):   # each wall swept along the shadow
            fill_poly(solid, px(np.array([a, c, c + off, a + off])), 1)
    for t in lay.trees:
        lo, hi = away * float(t.canopy_bottom), away * float(t.canopy_top)
        fill_poly(leafy, px(_hull(_circle(t.center, t.canopy_radius) + lo, _circle(t.center, t.canopy_radius) + hi)),
                  1)
        trunk = np.asarray(t.center, np.float64)
        fill_poly(solid, px(_hull(_circle(trunk, 0.15, 6), _circle(trunk + lo, 0.15, 6))), 1)
    for car in lay.cars:
        box = rect_poly(car.center[0], car.center[1], car.length, car.width, car.yaw)
        fill_poly(solid, px(_hull(box, box + away * float(car.height))), 1)
    for part in (q for f in lay.furniture for q in furniture_parts(f)):
        fill_poly(solid, px(_hull(part.footprint + away * part.z0, part.footprint + away * part.z1)), 1)
    shade = np.maximum(solid.astype(np.float32), 0.85 * leafy.astype(np.float32))
    shade = cv2.GaussianBlur(shade, (0, 0), max(0.5, 0.1 / mpp))
    shade[lay.ground_labels == C["building"]] = 0.0   # not on roofs (an image scene's roofs are its ground image)
    for b in lay.buildings:
        fill_poly(shade, px(np.asarray(b.footprint, np.float64)), 0.0)
    rgb = lay.ground_rgb
    for ch in range(3):
        k = np.float32(depth * (1.0 - SHADOW_RGB[ch]))
        rgb[..., ch] = np.clip(rgb[..., ch] * (1.0 - k * shade) + 0.5, 0, 255).astype(np.uint8)


# --- the world ---------------------------------------------------------------------------------------------
def changed_world(scene, strength: float, seed: int, parts: Iterable[str] = PARTS):
    """The :class:`satloc_env.world.meshes.World` a revisit of ``scene`` (a :class:`satloc_env.world.scene.Scene`) at
    (``strength``, ``seed``) shows the ground camera: built from :func:`changed_layout` of the scene's layout
    (its ``parts`` of the change) with the scene's ground padding, its foliage changed (:func:`change_foliage`,
    with the part ``vegetation``). ``scene.world`` for strength 0 or no parts. The last two are kept (per
    process), so episodes of one revisit build it once."""
    strength, seed, parts = _check(strength, seed, parts)
    return _changed_world(scene, strength, seed, tuple(p for p in PARTS if p in parts))


@functools.lru_cache(maxsize=2)
def _changed_world(scene, strength: float, seed: int, parts: tuple[str, ...]):
    if strength == 0.0 or not parts:
        return scene.world
    world = scene.spec.build_world(changed_layout(scene.layout, strength, seed, parts=parts,
                                                  cast=not scene.spec.casts_shadows))
    if "vegetation" in parts:
        change_foliage(world, strength, seed)
    return world
