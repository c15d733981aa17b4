"""Variety in what the camera sees: every building, tree and parked car its own, drawn from the scene's seed.

A generated grid (:mod:`satloc_env.world.generator`) with ``variety`` > 0 gives its objects parameters of their
own instead of the few shared looks of ``variety`` 0 (six facade styles with one window grammar, four foliage
tints on one tree shape, one car shape in eight colours):

* **buildings** (:func:`facade_params`, :func:`facade_texture`): a wall material (plaster, brick, stone,
  siding, concrete, glass) and colour from a wide palette, floor height, window size, spacing and grammar
  (frames, mullions, sills, lintels, shutters, curtains and blinds, lit or dark panes), a ground floor with
  shop windows, awnings and signs carrying text and a logo, doors, drainpipes and string courses;
* **trees** (:data:`SPECIES`): broadleaf, conifer, columnar and spreading species with their own canopy
  profile, size, colour and leaf texture (:func:`leaf_texture`: leaves, gaps and sunlit clumps at the scale of
  leaves and twigs);
* **parked cars** (:data:`BODIES`, :func:`car_colour`): saloons, hatchbacks, estates, SUVs and vans in the
  colours real car parks have (mostly white, grey, black and silver);
* **the road surface** (:func:`road_wear`): patches, cracks, manhole covers, drain grates and oil stains;
* **the markings' wear** (:func:`marking_wear`): each stripe and dash faded by its own amount, its paint worn
  through in blotches and along the tyres' paths, and dirt;
* **the ground's finest detail** (:func:`ground_detail`): the grain of grass, soil and asphalt, paving slabs and
  kerb stones.

Each object's look comes from its own seed (``Building.style_seed``, ``Tree.species`` and its index, ``Car.body``),
so an aliased cell (a copy of another, :func:`satloc_env.world.generator.alias_sources`) copies its objects'
looks too: ``aliasing`` still makes look-alike blocks. Everything is deterministic per seed.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .paint import fbm as _fbm

__all__ = ["FacadeParams", "facade_params", "facade_texture", "SPECIES", "leaf_texture", "BODIES", "car_colour",
           "road_wear", "marking_wear", "ground_detail", "SHOP_WORDS"]


# --- buildings -------------------------------------------------------------------------------------------------

#: wall materials and their colour families (RGB centre, spread)
_MATERIALS = {
    "plaster": [((222, 214, 196), 18), ((236, 226, 190), 14), ((214, 190, 160), 16), ((200, 206, 204), 14),
                ((232, 200, 170), 16), ((190, 200, 176), 12), ((240, 236, 228), 8), ((205, 170, 140), 16)],
    "brick": [((150, 78, 58), 16), ((172, 98, 70), 16), ((120, 62, 50), 12), ((186, 130, 96), 14),
              ((110, 92, 84), 10)],
    "stone": [((196, 188, 170), 12), ((170, 164, 150), 12), ((214, 204, 178), 10)],
    "siding": [((214, 218, 214), 14), ((160, 184, 196), 16), ((200, 180, 140), 16), ((150, 168, 140), 14)],
    "concrete": [((160, 160, 156), 14), ((128, 130, 132), 12), ((184, 180, 172), 10)],
    "glass": [((70, 96, 118), 16), ((84, 110, 104), 14), ((60, 70, 86), 10)],
}
_MATERIAL_P = {"plaster": 0.34, "brick": 0.26, "stone": 0.1, "siding": 0.1, "concrete": 0.12, "glass": 0.08}

#: words of shop signs
SHOP_WORDS = ("CAFE", "BAKERY", "PHARMACY", "BOOKS", "MARKET", "HAIR", "BANK", "PIZZA", "OPTIK", "SHOES",
              "DELI", "BAR", "HOTEL", "FLOWERS", "KIOSK", "LAUNDRY", "TAILOR", "GROCERY", "TOYS", "WINE",
              "SUSHI", "TAXI", "BIKES", "DENTIST", "BEAUTY", "SPORT", "POST", "NAILS", "ART", "MUSIC")


@dataclass(frozen=True)
class FacadeParams:
    """One building's facade grammar (see :func:`facade_params`)."""

    material: str
    wall: tuple[int, int, int]
    trim: tuple[int, int, int]           # string courses, sills, lintels, the parapet
    floor_h: float
    win_w: float
    win_h: float
    spacing: float
    glass: tuple[int, int, int]
    frame: tuple[int, int, int]
    door: tuple[int, int, int]
    mullions: int                        # vertical bars per window (0-2)
    transom: bool                        # a horizontal bar
    sills: bool
    shutters: tuple[int, int, int] | None
    curtain_p: float                     # share of windows with curtains or blinds
    lit_p: float                         # share of panes lit from inside
    shopfront: bool
    awning: tuple[int, int, int] | None
    sign: tuple[int, int, int] | None    # the sign board's colour (its text from the seed)
    drainpipes: bool
    string_course: bool
    seed: int
    balcony_p: float = 0.0               # share of the upper floors' window columns with a balcony at each floor
    railing: int = 0                     # the balconies' railing: 0 bars, 1 a solid panel, 2 glass
    fire_escape: bool = False            # an iron fire escape down one end of long walls


def _colour(rng: np.random.Generator, centre, spread) -> tuple[int, int, int]:
    """``centre`` varied: mostly in brightness (``spread``), a little in hue (a third of it per channel)."""
    c = np.asarray(centre, np.float64) + rng.normal(0, spread / 3, 3) + rng.normal(0, spread)
    return tuple(int(v) for v in np.clip(c, 0, 255))


def facade_params(seed: int, city: bool = True) -> FacadeParams:
    """A facade grammar drawn from ``seed`` (``city``: offices and shops, else houses)."""
    rng = np.random.default_rng([int(seed), 1729])
    names = list(_MATERIAL_P)
    p = np.array([_MATERIAL_P[n] for n in names])
    if not city:   # houses: no glass curtain walls, more siding and plaster
        p = p * np.array([1.3, 1.2, 0.6, 2.2, 0.4, 0.0])
    material = str(names[int(rng.choice(len(names), p=p / p.sum()))])
    fam = _MATERIALS[material]
    centre, spread = fam[int(rng.integers(len(fam)))]
    wall = _colour(rng, centre, spread)
    dark = rng.random() < 0.5
    trim = _colour(rng, (70, 66, 62) if dark else (236, 232, 222), 12)
    glass = _colour(rng, (62, 80, 100), 14)
    frame = _colour(rng, (36, 36, 40) if rng.random() < 0.35 else (232, 230, 224) if rng.random() < 0.7
                    else (120, 90, 60), 10)
    doors = [(80, 50, 30), (40, 60, 90), (120, 30, 30), (40, 40, 44), (30, 80, 60)]
    door = _colour(rng, doors[int(rng.integers(5))], 12)
    glassy = material == "glass"
    floor_h = float(rng.uniform(3.4, 4.2) if city else rng.uniform(2.7, 3.2))
    win_w = float(rng.uniform(1.6, 3.0) if glassy else rng.uniform(0.8, 1.8))
    win_h = float(min(floor_h - 0.6, rng.uniform(2.2, 3.0) if glassy else rng.uniform(1.2, 2.0)))
    spacing = float(win_w + (rng.uniform(0.2, 0.6) if glassy else rng.uniform(0.8, 2.2)))
    shop = city and rng.random() < 0.7
    return FacadeParams(
        material=material, wall=wall, trim=trim, floor_h=floor_h, win_w=win_w, win_h=win_h, spacing=spacing,
        glass=glass, frame=frame, door=door, mullions=int(rng.integers(0, 3)), transom=bool(rng.random() < 0.4),
        sills=bool(rng.random() < 0.7), shutters=(_colour(rng, [(40, 80, 60), (90, 60, 40), (60, 70, 100),
                                                                (200, 200, 190)][int(rng.integers(4))], 10)
                                                  if not city and rng.random() < 0.4 else None),
        curtain_p=float(rng.uniform(0.1, 0.7)), lit_p=float(rng.uniform(0.0, 0.25)), shopfront=bool(shop),
        awning=(_colour(rng, [(160, 40, 40), (40, 90, 60), (50, 60, 120), (200, 160, 40), (90, 90, 90)]
                        [int(rng.integers(5))], 16) if shop and rng.random() < 0.5 else None),
        sign=(_colour(rng, [(30, 30, 30), (200, 40, 40), (30, 70, 140), (240, 240, 230), (40, 110, 60)]
                      [int(rng.integers(5))], 10) if shop and rng.random() < 0.85 else None),
        drainpipes=bool(rng.random() < 0.6), string_course=bool(rng.random() < 0.5), seed=int(seed),
        **_extras(seed, material, city))


def _extras(seed: int, material: str, city: bool) -> dict:
    """Balconies and fire escapes, from a generator of their own (every other part of a facade stays as it
    was drawn without them): balconies on half the houses and a third of the plaster, brick and concrete
    blocks downtown; a fire escape on a quarter of the brick ones downtown."""
    rng = np.random.default_rng([int(seed), 1730])
    has = rng.random() < (0.5 if not city else 0.33 if material in ("plaster", "brick", "concrete") else 0.0)
    return {"balcony_p": float(rng.uniform(0.2, 0.8)) if has else 0.0, "railing": int(rng.integers(3)),
            "fire_escape": bool(city and material == "brick" and rng.random() < 0.25)}


def _wall(rng: np.random.Generator, f: FacadeParams, h: int, w: int, texel: float) -> np.ndarray:
    """The wall's material: plaster mottle, brick courses and joints, stone blocks, siding boards, concrete
    panels, or glass with spandrels."""
    wall = np.asarray(f.wall, np.float32)
    shade = 0.10 * _fbm(rng, h, w, (24, 6, 1), (0.45, 0.3, 0.25))
    rr, cc = np.mgrid[0:h, 0:w]
    img = wall * (1 + shade)[..., None]
    if f.material == "brick":
        course = max(2, int(round(0.075 / texel)))        # 7.5 cm courses, bricks 25 cm with a half offset
        brick = max(3, int(round(0.25 / texel)))
        row = rr // course
        col = (cc + (row % 2) * brick // 2) // brick
        tone = np.random.default_rng([f.seed, 7]).uniform(-0.14, 0.14, (int(row.max()) + 2, int(col.max()) + 2))
        img *= (1 + tone[row, col].astype(np.float32))[..., None]
        joint = (rr % course == 0) | ((cc + (row % 2) * brick // 2) % brick == 0)
        img[joint] = img[joint] * 0.72 + 40
    elif f.material == "stone":
        bh, bw = max(3, int(round(0.45 / texel))), max(4, int(round(0.9 / texel)))
        row = rr // bh
        col = (cc + (row % 2) * bw // 3) // bw
        tone = np.random.default_rng([f.seed, 8]).uniform(-0.08, 0.08, (int(row.max()) + 2, int(col.max()) + 2))
        img *= (1 + tone[row, col].astype(np.float32))[..., None]
        joint = (rr % bh == 0) | ((cc + (row % 2) * bw // 3) % bw == 0)
        img[joint] *= 0.8
    elif f.material == "siding":
        board = max(2, int(round(0.18 / texel)))
        img[rr % board == 0] *= 0.7
    elif f.material == "concrete":
        ph, pw = max(4, int(round(f.floor_h / texel))), max(4, int(round(2.4 / texel)))
        img[(rr % ph == 0) | (cc % pw == 0)] *= 0.75
        img *= (1 + 0.05 * _fbm(rng, h, w, (3, 1), (0.5, 0.5)))[..., None]
    elif f.material == "glass":
        img = img * (1 + 0.25 * _fbm(rng, h, w, (40, 12), (0.6, 0.4)))[..., None]   # reflections
    return img


def _text_patch(word: str, fg, bg, h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    """A sign board ``h`` x ``w`` with ``word`` in its middle and a small round logo."""
    img = np.empty((h, w, 3), np.uint8)
    img[:] = bg
    scale = max(0.2, min(h / 28.0, w / (20.0 * max(len(word), 1))))
    th = max(1, int(round(scale * 2)))
    (tw, tht), _ = cv2.getTextSize(word, cv2.FONT_HERSHEY_SIMPLEX, scale, th)
    logo = min(h - 2, int(0.7 * h))
    x0 = max(1, (w - tw - logo - 4) // 2 + logo + 4)
    cv2.putText(img, word, (x0, (h + tht) // 2), cv2.FONT_HERSHEY_SIMPLEX, scale, tuple(int(v) for v in fg), th,
                cv2.LINE_AA)
    if logo >= 4 and x0 - logo - 2 > 0:
        c = (x0 - logo // 2 - 3, h // 2)
        cv2.circle(img, c, logo // 2, tuple(int(v) for v in rng.integers(0, 255, 3)), -1, cv2.LINE_AA)
        cv2.circle(img, c, max(1, logo // 5), tuple(int(v) for v in fg), -1, cv2.LINE_AA)
    return img


def facade_texture(rng: np.random.Generator, f: FacadeParams, segs: list[float], h: int, texel: float
                   ) -> np.ndarray:
    """A facade strip for wall segments of lengths ``segs`` (metres), ``h`` texels high at ``texel`` metres per
    texel: the material, per floor a row of windows of the grammar ``f`` (frames, mullions, transoms, sills,
    lintels, shutters, curtains or blinds, some panes lit), a ground floor of shop windows with a sign and an
    awning (or a door) on long walls, drainpipes at the wall's ends, string courses and a parapet."""
    cuts = np.round(np.concatenate([[0.0], np.cumsum(segs)]) / texel).astype(int)
    w = max(2, int(cuts[-1]))
    img = _wall(rng, f, h, w, texel)
    wall_h = h * texel
    trim = np.asarray(f.trim, np.float32)

    def rows(z_lo: float, z_hi: float) -> tuple[int, int]:
        return max(0, int(round((wall_h - z_hi) / texel))), min(h, int(round((wall_h - z_lo) / texel)))

    def pane(r0, r1, c0, c1, lit: bool, curtain: int) -> None:
        if r1 - r0 < 2 or c1 - c0 < 2:
            return
        glass = np.asarray((235, 210, 140) if lit else f.glass, np.float32)
        g = np.linspace(1.2, 0.75, r1 - r0, dtype=np.float32)[:, None, None]
        img[r0:r1, c0:c1] = glass * g * (1 + 0.12 * rng.uniform(-1, 1, (r1 - r0, c1 - c0, 1)).astype(np.float32))
        if curtain == 1:         # curtains at the sides
            cw = max(1, (c1 - c0) // 4)
            col = np.asarray(rng.integers(120, 245, 3), np.float32)
            img[r0:r1, c0:c0 + cw] = col * 0.85
            img[r0:r1, c1 - cw:c1] = col * 0.85
        elif curtain == 2:       # a blind half down, with slats
            b = r0 + int((r1 - r0) * rng.uniform(0.2, 0.7))
            img[r0:b, c0:c1] = np.asarray((210, 206, 196), np.float32)
            img[r0:b:2, c0:c1] *= 0.86

    def window(r0, r1, c0, c1) -> None:
        if r1 - r0 < 3 or c1 - c0 < 3:
            return
        lit = bool(rng.random() < f.lit_p)
        curtain = int(rng.choice(3, p=[1 - f.curtain_p, f.curtain_p * 0.6, f.curtain_p * 0.4]))
        pane(r0, r1, c0, c1, lit, curtain)
        fr = np.asarray(f.frame, np.float32)
        img[r0, c0:c1] = img[r1 - 1, c0:c1] = fr
        img[r0:r1, c0] = img[r0:r1, c1 - 1] = fr
        for k in range(1, f.mullions + 1):
            img[r0:r1, c0 + k * (c1 - c0) // (f.mullions + 1)] = fr
        if f.transom:
            img[r0 + (r1 - r0) // 3, c0:c1] = fr
        if f.sills:
            s0 = max(0, c0 - 1)
            img[min(h - 1, r1):min(h, r1 + 2), s0:c1 + 1] = trim
            img[max(0, r0 - 2):r0, s0:c1 + 1] = trim * 0.95       # lintel
        if f.shutters is not None:
            sw = max(1, (c1 - c0) // 2)
            sh = np.asarray(f.shutters, np.float32)
            for a, b in ((max(0, c0 - sw), c0), (c1, min(w, c1 + sw))):
                img[r0:r1, a:b] = sh
                img[r0:r1:3, a:b] *= 0.8

    n_floors = max(1, int((wall_h - 0.5) // f.floor_h))
    shop_h = min(3.4, f.floor_h - 0.3)
    words = np.random.default_rng([f.seed, 11])
    for k, seg in enumerate(segs):
        a, b = cuts[k], cuts[k + 1]
        n_win = int(seg // f.spacing)
        centres = a + (np.arange(n_win) + 0.5) * (b - a) / max(n_win, 1)
        half = f.win_w / texel / 2
        for fl in range(n_floors):
            z = fl * f.floor_h + (0.9 if fl else 0.8)
            if z + f.win_h > wall_h - 0.4:
                break
            if fl == 0 and f.shopfront and seg > 5.0:
                r0, r1 = rows(0.2, shop_h - 0.5)
                c0, c1 = a + int(0.6 / texel), b - int(0.6 / texel)
                if c1 - c0 > 8:
                    for s0 in range(c0, c1, max(8, int(2.4 / texel))):         # shop windows and a door
                        e = min(c1, s0 + max(8, int(2.4 / texel)) - 2)
                        window(r0, r1, s0, e)
                    if f.sign is not None:
                        sr = rows(shop_h - 0.45, shop_h)
                        word = SHOP_WORDS[int(words.integers(len(SHOP_WORDS)))]
                        fg = (250, 250, 245) if sum(f.sign) < 360 else (30, 30, 30)
                        sign_w = min(c1 - c0, max(12, int(len(word) * 0.45 / texel) + int(0.8 / texel)))
                        s0 = c0 + (c1 - c0 - sign_w) // 2
                        if sr[1] - sr[0] >= 3:
                            img[sr[0]:sr[1], s0:s0 + sign_w] = _text_patch(word, fg, f.sign, sr[1] - sr[0], sign_w,
                                                                          words)
                    if f.awning is not None:
                        ar = rows(shop_h - 0.95, shop_h - 0.5)
                        aw = np.asarray(f.awning, np.float32)
                        stripe = max(1, int(0.25 / texel))
                        cols = np.arange(c0, c1)
                        band = np.where(((cols - c0) // stripe) % 2 == 0, 1.0, 0.72).astype(np.float32)
                        img[ar[0]:ar[1], c0:c1] = aw * band[None, :, None]
                        img[ar[1] - 1:ar[1], c0:c1] *= 0.6
                continue
            for cx in centres:
                r0, r1 = rows(z, z + f.win_h)
                window(r0, r1, int(cx - half), int(cx + half))
        if not (f.shopfront and seg > 5.0) and seg > 5.0:                 # a door
            cx = (a + b) // 2 + int(rng.integers(-2, 3)) * max(1, int(f.spacing / texel / 2))
            dw = int(0.55 / texel)
            if cx - dw < 0 or cx + dw > img.shape[1]:                    # shifted past the texture's end
                cx = min(max(cx, dw + 2), img.shape[1] - dw - 2)
            r0, r1 = rows(0.0, 2.2)
            img[r0:r1, cx - dw:cx + dw] = np.asarray(f.door, np.float32)
            img[r0:r1, cx - dw] = img[r0:r1, cx + dw - 1] = np.asarray(f.frame, np.float32)
            img[r0:r0 + 2, cx - dw - 2:cx + dw + 2] = trim
        if f.drainpipes and b - a > 6:
            pw = max(1, int(0.1 / texel))
            img[:, a + 2:a + 2 + pw] = np.asarray((70, 70, 72), np.float32)
    if f.balcony_p > 0 or f.fire_escape:
        _balconies(img, f, segs, cuts, rows, n_floors, texel)
    if f.string_course:
        for fl in range(1, n_floors):
            r0, _ = rows(fl * f.floor_h, fl * f.floor_h)
            img[max(0, r0 - 1):r0 + 1] = trim
    p0, p1 = rows(wall_h - 0.4, wall_h)
    img[p0:p1] = trim * (1 + 0.05 * rng.uniform(-1, 1, (p1 - p0, w, 1)).astype(np.float32))
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def _balconies(img: np.ndarray, f: FacadeParams, segs, cuts, rows, n_floors: int, texel: float) -> None:
    """Paint balconies (a slab and its shadow, a railing of bars, a panel or glass in front of the window's
    lower part; whole columns of them, floor above floor) and fire escapes (landings at every floor joined by
    ladders, at one end of a long wall) onto ``img`` (float, the facade strip of :func:`facade_texture`)."""
    rng = np.random.default_rng([int(f.seed), 1731])
    h, w = img.shape[:2]
    trim = np.asarray(f.trim, np.float32)
    metal = np.asarray((38, 38, 40), np.float32)
    for k, seg in enumerate(segs):
        a, b = int(cuts[k]), int(cuts[k + 1])
        n_win = int(seg // f.spacing)
        if n_win == 0:
            continue
        centres = a + (np.arange(n_win) + 0.5) * (b - a) / n_win
        half = f.win_w / texel / 2 + 0.4 / texel
        columns = [cx for cx in centres if rng.random() < f.balcony_p]
        for fl in range(1, n_floors):
            z = fl * f.floor_h + 0.85
            if z + f.win_h > h * texel - 0.4:
                break
            s0, s1 = rows(z - 0.15, z)
            d0, d1 = rows(z - 0.6, z - 0.15)
            g0, g1 = rows(z, z + 1.0)
            for cx in columns:
                c0, c1 = max(0, int(cx - half)), min(w, int(cx + half))
                if d1 > d0:
                    img[d0:d1, c0:c1] *= np.linspace(1.0, 0.55, d1 - d0, dtype=np.float32)[:, None, None]
                img[s0:s1, c0:c1] = trim * 0.9
                if g1 - g0 < 3:
                    continue
                if f.railing == 0:
                    img[g0:g0 + 1, c0:c1] = metal
                    img[g0:g1, c0:c1:max(2, int(0.12 / texel))] = metal
                elif f.railing == 1:
                    img[g0:g1, c0:c1] = trim * 0.8
                    img[g0:g0 + 1, c0:c1] = trim * 0.6
                else:
                    img[g0:g1, c0:c1] = img[g0:g1, c0:c1] * 0.6 + np.asarray((120, 150, 160), np.float32) * 0.4
                    img[g0:g0 + 1, c0:c1] = metal
        if f.fire_escape and seg > 12 and n_win >= 3:
            c0, c1 = a + int(0.3 / texel), min(b, a + int(2 * f.spacing / texel))
            floors = [fl * f.floor_h + 0.8 for fl in range(1, n_floors) if fl * f.floor_h + 2.0 < h * texel]
            for i, z in enumerate(floors):
                p0, p1 = rows(z - 0.1, z)
                img[p0:p1 + 1, c0:c1] = metal                                   # the landing
                r0, _ = rows(z + 1.0, z + 1.0)
                img[r0:r0 + 1, c0:c1] = metal                                   # its railing
                img[r0:p0, c0:c1:max(2, int(0.3 / texel))] = metal
                if i > 0:                                                       # a ladder down to the one below
                    q0, _ = rows(floors[i - 1], floors[i - 1])
                    x0, x1 = (c0 + 2, c1 - 3) if i % 2 else (c1 - 3, c0 + 2)
                    for dx in (0, max(1, int(0.35 / texel))):
                        cv2.line(img, (x0, p1), (x1 + dx * (1 if i % 2 else -1), q0), metal.tolist(), 1)


# --- trees -------------------------------------------------------------------------------------------------------

#: tree species (index 1..; 0 is ``variety`` 0's one tree): canopy profile (relative height, relative radius)
#: pairs, the radius and canopy height ranges (metres), the trunk's share of the height and the leaf colours
SPECIES = {
    1: {"name": "broadleaf", "profile": [(0.0, 0.0), (0.1, 0.7), (0.35, 1.0), (0.7, 0.9), (0.9, 0.55), (1.0, 0.0)],
        "radius": (2.2, 4.2), "crown": (3.5, 7.0), "bottom": (2.0, 3.2),
        "leaf": [(62, 102, 42), (74, 112, 40), (52, 90, 40)]},
    2: {"name": "conifer", "profile": [(0.0, 0.0), (0.05, 1.0), (0.35, 0.78), (0.65, 0.5), (0.88, 0.22), (1.0, 0.0)],
        "radius": (1.4, 2.6), "crown": (5.0, 10.0), "bottom": (0.6, 1.5),
        "leaf": [(38, 70, 46), (44, 80, 52), (32, 62, 44)]},
    3: {"name": "columnar", "profile": [(0.0, 0.0), (0.08, 0.8), (0.3, 1.0), (0.7, 0.95), (0.92, 0.6), (1.0, 0.0)],
        "radius": (0.9, 1.6), "crown": (6.0, 11.0), "bottom": (1.2, 2.2),
        "leaf": [(70, 110, 46), (84, 120, 52), (60, 98, 40)]},
    4: {"name": "spreading", "profile": [(0.0, 0.0), (0.15, 0.9), (0.45, 1.0), (0.75, 0.8), (0.95, 0.35), (1.0, 0.0)],
        "radius": (3.5, 5.5), "crown": (3.0, 5.0), "bottom": (2.8, 4.0),
        "leaf": [(78, 110, 50), (66, 104, 46), (90, 118, 54)]},
}


def leaf_texture(rng: np.random.Generator, h: int, w: int, base) -> np.ndarray:
    """A canopy at the scale of leaves and twigs: clumps and gaps of several sizes, each leaf a small blob brighter
    or darker than its clump, a few dark twig gaps and sunlit tips."""
    base = np.asarray(base, np.float32)
    v = _fbm(rng, h, w, (16, 5), (0.6, 0.4))
    img = base * (1 + 0.35 * v)[..., None]
    n = max(1, h * w // 5)
    ys, xs = rng.integers(0, h, n), rng.integers(0, w, n)
    lum = rng.uniform(0.5, 1.55, n)
    tone = rng.normal(0, 0.06, (n, 3))
    rad = rng.integers(1, 3, n)
    for y, x, gain, t, r in zip(ys, xs, lum, tone, rad):
        cv2.circle(img, (int(x), int(y)), int(r), (base * (gain + t)).tolist(), -1)
    gaps = rng.random((h, w)) < 0.02
    img[gaps] *= 0.35
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


# --- cars ----------------------------------------------------------------------------------------------------------

#: car body types (index 1..; 0 is ``variety`` 0's car): length, width and height ranges (metres) and the cabin's
#: length share, its offset towards the rear (share of the length), the roof's share of the cabin and the body's
#: share of the height
BODIES = {
    1: {"name": "saloon", "length": (4.4, 4.9), "width": (1.75, 1.85), "height": (1.4, 1.5), "cab": 0.5,
        "dx": 0.05, "roof": 0.7, "body": 0.55},
    2: {"name": "hatchback", "length": (3.8, 4.2), "width": (1.68, 1.78), "height": (1.45, 1.55), "cab": 0.58,
        "dx": 0.1, "roof": 0.78, "body": 0.55},
    3: {"name": "estate", "length": (4.5, 4.9), "width": (1.78, 1.86), "height": (1.45, 1.55), "cab": 0.66,
        "dx": 0.1, "roof": 0.9, "body": 0.55},
    4: {"name": "suv", "length": (4.3, 4.8), "width": (1.82, 1.95), "height": (1.65, 1.8), "cab": 0.6,
        "dx": 0.08, "roof": 0.86, "body": 0.58},
    5: {"name": "van", "length": (4.8, 5.4), "width": (1.9, 2.05), "height": (1.95, 2.3), "cab": 0.82,
        "dx": 0.06, "roof": 0.96, "body": 0.5},
}
_BODY_P = np.array([0.28, 0.26, 0.14, 0.22, 0.10])

#: car colours as car parks have them: white, grey, black and silver most, then blue, red and others
_CAR_COLOURS = [((236, 236, 234), 0.22), ((128, 130, 134), 0.18), ((28, 28, 32), 0.2), ((178, 180, 184), 0.12),
                ((40, 62, 120), 0.09), ((150, 28, 32), 0.08), ((70, 96, 70), 0.03), ((190, 160, 110), 0.03),
                ((210, 120, 40), 0.02), ((90, 40, 70), 0.03)]


def car_body(rng: np.random.Generator) -> int:
    """A body type of :data:`BODIES`, as often as streets have them."""
    return int(rng.choice(list(BODIES), p=_BODY_P / _BODY_P.sum()))


def car_colour(rng: np.random.Generator) -> tuple[int, int, int]:
    """A car colour, as often as car parks have it, with a little variation."""
    p = np.array([q for _, q in _CAR_COLOURS])
    c = _CAR_COLOURS[int(rng.choice(len(_CAR_COLOURS), p=p / p.sum()))][0]
    return _colour(rng, c, 6)


# --- the road surface ------------------------------------------------------------------------------------------

def road_wear(labels: np.ndarray, rgb: np.ndarray, rng: np.random.Generator, mpp: float, amount: float,
              road: int, sidewalk: int) -> None:
    """Paint what a used road surface shows onto ``rgb`` (in place), where ``labels`` is ``road``: patches of newer
    and older asphalt, crack lines, manhole covers, drain grates at the kerb and oil stains; on the sidewalk a few
    darker slabs and stains. ``amount`` in [0, 1] scales how many."""
    if amount <= 0:
        return
    h, w = labels.shape
    px = lambda m: max(1, int(round(m / mpp)))  # noqa: E731
    on_road = labels == road
    area_m2 = on_road.sum() * mpp * mpp
    if area_m2 <= 0:
        return
    layer = np.zeros((h, w), np.float32)           # brightness change, applied on the road only
    for _ in range(int(amount * area_m2 / 60)):    # patches: rectangles of other asphalt
        cy, cx = rng.integers(0, h), rng.integers(0, w)
        a, b = px(rng.uniform(0.8, 4.0)), px(rng.uniform(0.8, 3.0))
        ang = float(rng.uniform(0, 180))
        box = cv2.boxPoints(((float(cx), float(cy)), (float(a), float(b)), ang)).astype(np.int32)
        cv2.fillPoly(layer, [box], float(rng.choice([-0.18, -0.1, 0.12])))
    for _ in range(int(amount * area_m2 / 25)):    # cracks: thin dark polylines
        y, x = int(rng.integers(0, h)), int(rng.integers(0, w))
        pts = [(x, y)]
        for _ in range(int(rng.integers(3, 9))):
            x += int(rng.normal(0, px(0.5)))
            y += int(rng.normal(0, px(0.5)))
            pts.append((x, y))
        cv2.polylines(layer, [np.array(pts, np.int32)], False, -0.45, 1)
    for _ in range(int(amount * area_m2 / 300)):   # manhole covers and stains
        cy, cx = int(rng.integers(0, h)), int(rng.integers(0, w))
        if rng.random() < 0.5:
            r = px(0.32)
            cv2.circle(layer, (cx, cy), r, -0.35, -1)
            cv2.circle(layer, (cx, cy), r, 0.15, 1)
        else:
            cv2.ellipse(layer, (cx, cy), (px(rng.uniform(0.3, 1.0)), px(rng.uniform(0.2, 0.6))),
                        float(rng.uniform(0, 180)), 0, 360, -0.22, -1)
    layer = cv2.GaussianBlur(layer, (0, 0), 0.6) + layer * 0.5
    m = on_road
    rgb[m] = np.clip(rgb[m].astype(np.float32) * (1 + layer[m])[:, None], 0, 255).astype(np.uint8)
    sw = labels == sidewalk
    if sw.any():
        stains = np.zeros((h, w), np.float32)
        for _ in range(int(amount * sw.sum() * mpp * mpp / 40)):
            cy, cx = int(rng.integers(0, h)), int(rng.integers(0, w))
            cv2.circle(stains, (cx, cy), px(rng.uniform(0.1, 0.4)), float(rng.uniform(-0.2, -0.08)), -1)
        rgb[sw] = np.clip(rgb[sw].astype(np.float32) * (1 + stains[sw])[:, None], 0, 255).astype(np.uint8)


def marking_wear(labels: np.ndarray, rgb: np.ndarray, rng: np.random.Generator, mpp: float, amount: float,
                 marking: int, road: int) -> None:
    """Wear the painted markings of ``rgb`` (in place), where ``labels`` is ``marking``, towards the asphalt
    under them: every stripe and dash (a connected piece of paint) fades by its own amount (up to 60 % at
    ``amount`` 1), the paint is worn through in blotches of 0.2-1 m and, more, in bands where tyres run
    (along the road, about 1.8 m apart), and dirt greys what is left. Real crossings and lane lines are never
    as new as each other, so two crossings of the same design look different up close; the class (the labels)
    stays a marking. ``amount`` in [0, 1] scales it all."""
    if amount <= 0:
        return
    m = labels == marking
    if not m.any():
        return
    h, w = labels.shape
    on_road = labels == road
    asphalt = (np.median(rgb[on_road], axis=0) if on_road.any() else np.array([88.0, 88.0, 92.0])).astype(np.float32)
    n, comp = cv2.connectedComponents(m.astype(np.uint8), connectivity=4)
    fade = rng.uniform(0.0, 0.6, n).astype(np.float32)          # each piece of paint its own age
    px = lambda metres: max(1, int(round(metres / mpp)))  # noqa: E731
    blotch = _fbm(rng, h, w, (px(1.0), px(0.45), px(0.2)), (0.5, 0.3, 0.2))
    # tyre tracks: bands along each road direction (the noise's phase drawn, so every cell has its own)
    period = 1.8 / mpp
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    tracks = np.maximum(np.cos(2 * np.pi * (xs / period + rng.random())),
                        np.cos(2 * np.pi * (ys / period + rng.random())))
    worn = fade[comp] + 1.2 * np.clip(blotch - 0.1, 0, None) + 0.3 * np.clip(tracks - 0.6, 0, None) / 0.4
    worn = np.clip(amount * worn, 0, 0.9)[m][:, None]
    dirt = 1 - 0.1 * amount * np.abs(_fbm(rng, h, w, (px(0.3),), (1.0,)))[m][:, None]
    paint = rgb[m].astype(np.float32)
    rgb[m] = np.clip((paint * (1 - worn) + asphalt * worn) * dirt, 0, 255).astype(np.uint8)


#: ground_detail's texel grain per class name: the brightness spread of single texels (a relative change)
_GRAIN = {"road": 0.07, "lane_marking": 0.05, "parking": 0.07, "sidewalk": 0.06, "grass": 0.24, "soil": 0.16}


def ground_detail(labels: np.ndarray, rgb: np.ndarray, rng: np.random.Generator, mpp: float, amount: float,
                  classes: dict[str, int]) -> None:
    """Paint the ground's finest detail onto ``rgb`` (in place), at the scale of single texels, as the ground
    camera sees it within a few metres: grain (blades and tufts of grass, clods, the asphalt's aggregate), the
    sidewalk's paving slabs (0.6 m, axis-aligned, each its own tone, with dark joints) and a kerb of lighter
    stones (1 m, with joints) along its edge with the road. ``classes``: the class ids by name (``road``,
    ``parking``, ``sidewalk``, ``grass``, ``soil``). ``amount`` in [0, 1] scales it all.

    This detail lies below the 0.6 m a satellite capture keeps (:mod:`satloc_env.world.capture`), so it is the
    ground camera's alone."""
    if amount <= 0:
        return
    h, w = labels.shape
    gain = np.zeros((h, w), np.float32)
    grain = rng.standard_normal((h, w)).astype(np.float32)
    for name, spread in _GRAIN.items():
        m = labels == classes[name]
        gain[m] = spread * grain[m]
    sw = labels == classes["sidewalk"]
    if sw.any():
        slab = max(2, int(round(0.6 / mpp)))
        ys, xs = np.arange(h)[:, None], np.arange(w)[None, :]
        tone = rng.normal(0, 0.05, ((h + slab - 1) // slab, (w + slab - 1) // slab)).astype(np.float32)
        paving = np.repeat(np.repeat(tone, slab, 0), slab, 1)[:h, :w]
        paving -= 0.16 * (((ys % slab) == 0) | ((xs % slab) == 0))
        road = (labels == classes["road"]).astype(np.uint8)
        kerb = sw & (cv2.dilate(road, np.ones((3, 3), np.uint8), iterations=2) > 0)
        stone = max(2, int(round(1.0 / mpp)))     # the kerb's stones; a joint crosses a kerb of either direction
        paving[kerb] = np.where(((ys + xs) % stone == 0), -0.12, 0.14)[kerb]
        gain[sw] += paving[sw]
    out = rgb.astype(np.float32) * (1 + amount * gain)[..., None]
    np.clip(out, 0, 255, out=out)
    rgb[...] = out.astype(np.uint8)
