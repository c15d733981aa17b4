"""Street furniture: lamp posts, traffic signs and lights, bins, benches, bollards, hydrants and bus shelters, and
the small greenery of streets and yards: hedges, shrubs and planters.

A generated grid with ``variety`` > 0 (:mod:`satloc_env.world.generator`) lines its sidewalks with them, each a
:class:`~satloc_env.world.layout.Furniture` (a kind, a position, the direction it faces and a seed of its own).
:func:`furniture_parts` turns one into simple solids (:class:`Part`: a vertical prism over a footprint, with a
picture on some of its faces, such as a sign's face or a poster), which :mod:`satloc_env.world.meshes` builds
like every other object and :mod:`satloc_env.world.tile` paints from above (tops and shadows). Everything comes
from the object's seed, so an aliased cell copies its furniture too.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from .layout import Building, Furniture
from .paint import fbm, rect_poly, right_angled
from .variety import leaf_texture

__all__ = ["KINDS", "ROWS", "HEDGE_SEGMENT_M", "ROOF_MIN_HEIGHT_M", "Part", "furniture_parts", "footprint_radius",
           "roof_parts"]

#: furniture kinds by their code in :attr:`Furniture.kind`
KINDS = {1: "lamp post", 2: "traffic sign", 3: "litter bin", 4: "bench", 5: "bollards", 6: "hydrant",
         7: "traffic light", 8: "bus shelter", 9: "hedge", 10: "shrub", 11: "planter", 12: "fence", 13: "garden wall"}

#: a hedge (a fence, a garden wall) is a row of these, each a piece of furniture (metres, along its ``yaw``)
HEDGE_SEGMENT_M = 2.0

#: how far (metres) the kind reaches from its centre on the ground: what placement keeps clear
_REACH = {1: 0.3, 2: 0.3, 3: 0.4, 4: 1.1, 5: 2.6, 6: 0.3, 7: 0.3, 8: 1.9, 9: 1.1, 10: 0.8, 11: 0.7, 12: 1.1,
          13: 1.1}
#: kinds whose pieces make rows metres long (a hedge, a fence, a wall): seen from afar, so drawn at any distance
ROWS = (9, 12, 13)


def footprint_radius(kind: int) -> float:
    """Metres around a piece of furniture's centre that nothing else may stand on."""
    return _REACH[int(kind)]


@dataclass
class Part:
    """A vertical prism: ``footprint`` (N, 2, metres, map frame) from ``z0`` to ``z1``, painted ``rgb``
    (mottled), with ``faces`` mapping an edge index of the footprint (edge k runs from point k to k+1) to a
    picture (H, W, 3 uint8) shown on it; ``texel`` metres per texel. ``leaves``: foliage (a hedge, a shrub),
    painted as leaves around ``rgb`` and labelled ``tree``; else ``obstacle``."""

    footprint: np.ndarray
    z0: float
    z1: float
    rgb: tuple[int, int, int]
    texel: float = 0.04
    faces: dict[int, np.ndarray] = field(default_factory=dict)
    leaves: bool = False


#: the greens of hedges and shrubs (RGB)
_GREENS = ((58, 92, 40), (46, 80, 36), (72, 104, 46), (64, 86, 52), (84, 110, 56), (50, 72, 44))


#: edges of a :func:`_box` (of :func:`satloc_env.world.paint.rect_poly`'s corners): its front (facing ``yaw``)
#: and its back, and its two sides along ``yaw`` (a row's long faces)
_FRONT, _BACK, _SIDE, _OTHER_SIDE = 3, 1, 0, 2


def _box(center, yaw: float, length: float, width: float, dx: float = 0.0, dy: float = 0.0) -> np.ndarray:
    """Corners (4, 2) of a ``length`` (along ``yaw``) x ``width`` rectangle whose centre is ``dx`` ahead and
    ``dy`` to the left of ``center`` (:func:`rect_poly`; edge :data:`_FRONT` faces ``yaw``)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return rect_poly(center[0] + c * dx - s * dy, center[1] + s * dx + c * dy, length, width, yaw)


def _disc(center, r: float, n: int = 8) -> np.ndarray:
    """``n`` corners of a circle of radius ``r``; posts thinner than 12 cm get 4 (a square post: the camera
    cannot tell, and it costs half the triangles)."""
    n = 4 if r < 0.12 else n
    a = 2 * math.pi * (np.arange(n) + 0.5) / n
    return np.stack([center[0] + r * np.cos(a), center[1] + r * np.sin(a)], axis=1)


def _pick(rng: np.random.Generator, options):
    return options[int(rng.integers(len(options)))]


def _jitter(rng: np.random.Generator, rgb, spread: float = 10.0) -> tuple[int, int, int]:
    return tuple(int(v) for v in np.clip(np.asarray(rgb, np.float64) + rng.normal(0, spread), 0, 255))


# --- pictures ---------------------------------------------------------------------------------------------------
def _sign_face(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A traffic sign's face: a prohibition (red ring), a mandatory (blue disc with an arrow), a warning (red
    triangle), an information (blue square) or a street-name plate with text."""
    img = np.full((h, w, 3), 235, np.uint8)
    kind = int(rng.integers(5))
    c, r = (w // 2, h // 2), max(2, min(h, w) // 2 - 1)
    if kind == 0:
        cv2.circle(img, c, r, (200, 30, 30), -1, cv2.LINE_AA)
        cv2.circle(img, c, int(r * 0.72), (240, 240, 240), -1, cv2.LINE_AA)
        cv2.putText(img, str(int(_pick(rng, (20, 30, 40, 50)))), (int(w * 0.2), int(h * 0.64)),
                    cv2.FONT_HERSHEY_SIMPLEX, w / 64, (20, 20, 20), max(1, w // 24), cv2.LINE_AA)
    elif kind == 1:
        img[:] = 140
        cv2.circle(img, c, r, (30, 70, 170), -1, cv2.LINE_AA)
        cv2.arrowedLine(img, (w // 2, int(h * 0.8)), (w // 2, int(h * 0.2)), (245, 245, 245), max(1, w // 10),
                        cv2.LINE_AA, tipLength=0.4)
    elif kind == 2:
        img[:] = 140
        tri = np.array([[w // 2, 2], [w - 2, h - 3], [2, h - 3]], np.int32)
        cv2.fillPoly(img, [tri], (200, 30, 30), cv2.LINE_AA)
        inner = ((tri - tri.mean(0)) * 0.62 + tri.mean(0) + [0, h * 0.05]).astype(np.int32)
        cv2.fillPoly(img, [inner], (240, 240, 235), cv2.LINE_AA)
        cv2.putText(img, "!", (int(w * 0.44), int(h * 0.8)), cv2.FONT_HERSHEY_SIMPLEX, w / 70, (20, 20, 20),
                    max(1, w // 20), cv2.LINE_AA)
    elif kind == 3:
        img[:] = (30, 80, 160)
        cv2.rectangle(img, (2, 2), (w - 3, h - 3), (240, 240, 240), max(1, w // 30))
        cv2.putText(img, _pick(rng, ("P", "i", "H", "+")), (int(w * 0.3), int(h * 0.75)),
                    cv2.FONT_HERSHEY_SIMPLEX, w / 40, (245, 245, 245), max(1, w // 12), cv2.LINE_AA)
    else:
        img[:] = _pick(rng, ((30, 90, 50), (30, 60, 140), (240, 240, 235)))
        fg = (20, 20, 20) if img[0, 0, 0] > 200 else (240, 240, 240)
        word = "".join(chr(int(v)) for v in rng.integers(65, 91, int(rng.integers(4, 8))))
        cv2.putText(img, word + " ST", (3, int(h * 0.7)), cv2.FONT_HERSHEY_SIMPLEX, w / 190, fg,
                    max(1, w // 80), cv2.LINE_AA)
    return img


def _signal_face(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A traffic light's front: a dark housing with three lamps, one of them lit."""
    img = np.full((h, w, 3), _pick(rng, ((30, 30, 30), (40, 44, 40), (190, 160, 40))), np.uint8)
    lit = int(rng.integers(3))
    for k, col in enumerate(((220, 40, 30), (230, 160, 30), (40, 200, 90))):
        c = (w // 2, int(h * (k + 0.5) / 3))
        cv2.circle(img, c, max(1, int(min(w, h / 3) * 0.36)), col if k == lit else tuple(v // 4 for v in col), -1,
                   cv2.LINE_AA)
    return img


def _poster(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """An advertising poster: colour fields, a shape and a word."""
    base = rng.integers(30, 230, 3)
    img = np.empty((h, w, 3), np.float32)
    img[:] = base
    img += 40 * fbm(rng, h, w, (max(2, w // 3), max(2, w // 10)), (0.7, 0.3))[..., None]
    band = int(rng.integers(h // 4, h // 2))
    img[band:band + h // 5] = rng.integers(0, 255, 3)
    img = np.clip(img, 0, 255).astype(np.uint8)
    cv2.circle(img, (int(rng.integers(w)), int(rng.integers(h // 2))), int(w * rng.uniform(0.15, 0.35)),
               tuple(int(v) for v in rng.integers(0, 255, 3)), -1, cv2.LINE_AA)
    word = "".join(chr(int(v)) for v in rng.integers(65, 91, int(rng.integers(3, 6))))
    cv2.putText(img, word, (2, int(h * 0.9)), cv2.FONT_HERSHEY_SIMPLEX, w / 110, (245, 245, 240), max(1, w // 40),
                cv2.LINE_AA)
    return img


# --- the kinds --------------------------------------------------------------------------------------------------
_METAL = ((48, 52, 50), (32, 34, 36), (110, 114, 116), (40, 70, 55), (150, 150, 146))


def furniture_parts(f: Furniture) -> list[Part]:
    """The solids of one piece of furniture (see :data:`KINDS`), facing ``f.yaw`` (towards the road)."""
    rng = np.random.default_rng([int(f.seed), 90210, int(f.kind)])
    c, yaw, kind = np.asarray(f.center, np.float64), float(f.yaw), int(f.kind)
    fwd = np.array([math.cos(yaw), math.sin(yaw)])
    left = np.array([-fwd[1], fwd[0]])
    parts: list[Part] = []
    if kind == 1:                                       # lamp post: a pole, an arm over the road and a head
        metal = _jitter(rng, _pick(rng, _METAL), 6)
        h = float(rng.uniform(5.5, 9.0))
        r = float(rng.uniform(0.06, 0.11))
        parts.append(Part(_disc(c, r * 1.6, 8), 0.0, 0.5, metal))
        parts.append(Part(_disc(c, r, 6), 0.5, h, metal))
        if rng.random() < 0.3:                          # a lantern on top
            parts.append(Part(_box(c, yaw, 0.45, 0.45), h, h + 0.6, (230, 226, 200), 0.03))
            parts.append(Part(_box(c, yaw, 0.55, 0.55), h + 0.6, h + 0.7, metal))
        else:
            arm = float(rng.uniform(0.8, 2.2))
            parts.append(Part(_box(c, yaw, arm, 0.08, dx=arm / 2), h - 0.12, h, metal))
            parts.append(Part(_box(c, yaw, 0.7, 0.28, dx=arm), h - 0.22, h + 0.02, metal))
    elif kind == 2:                                     # traffic sign: a post and one or two plates
        parts.append(Part(_disc(c, 0.035, 6), 0.0, float(rng.uniform(2.6, 3.2)), (150, 152, 150)))
        z = float(rng.uniform(2.0, 2.4))
        for k in range(1 + int(rng.random() < 0.35)):
            wd = float(rng.uniform(0.5, 0.75))
            hd = wd if rng.random() < 0.7 else wd * 0.45
            plate = _box(c, yaw, 0.04, wd, dx=0.05)
            side = int(rng.integers(64, 96))
            parts.append(Part(plate, z - hd, z, (150, 152, 150), 0.01,
                              {_FRONT: _sign_face(rng, max(8, int(side * hd / wd)), side)}))
            z -= hd + 0.08
    elif kind == 3:                                     # litter bin
        col = _jitter(rng, _pick(rng, ((40, 90, 50), (60, 62, 66), (30, 30, 32), (30, 70, 140), (210, 120, 30))))
        r, h = float(rng.uniform(0.22, 0.34)), float(rng.uniform(0.85, 1.1))
        parts.append(Part(_disc(c, r, 8), 0.0, h, col))
        parts.append(Part(_disc(c, r * 1.08, 8), h, h + 0.06, tuple(int(v * 0.6) for v in col)))
    elif kind == 4:                                     # bench: legs, a seat and a back, facing the road
        wood = _jitter(rng, _pick(rng, ((120, 80, 50), (150, 110, 70), (70, 70, 72), (40, 80, 60))), 12)
        ln = float(rng.uniform(1.5, 2.1))
        for s in (-0.4, 0.4):
            parts.append(Part(_box(c, yaw, 0.4, 0.06, dy=s * ln), 0.0, 0.4, (40, 40, 42)))
        parts.append(Part(_box(c, yaw, 0.45, ln), 0.4, 0.46, wood))
        parts.append(Part(_box(c, yaw, 0.06, ln, dx=-0.22), 0.5, 0.9, wood))
    elif kind == 5:                                     # bollards: a row along the kerb
        col = _jitter(rng, _pick(rng, ((40, 40, 42), (150, 152, 150), (200, 170, 40), (110, 40, 30))), 8)
        n, step = int(rng.integers(3, 6)), float(rng.uniform(1.0, 1.5))
        r, h = float(rng.uniform(0.06, 0.11)), float(rng.uniform(0.7, 1.05))
        for k in range(n):
            p = c + left * (k - (n - 1) / 2) * step
            parts.append(Part(_disc(p, r, 6), 0.0, h, col))
            if rng.random() < 0.5:
                parts.append(Part(_disc(p, r * 1.02, 6), h - 0.18, h - 0.1, (235, 235, 230)))
    elif kind == 6:                                     # hydrant
        col = _pick(rng, ((190, 30, 30), (220, 180, 30), (200, 200, 200)))
        parts.append(Part(_disc(c, 0.12, 8), 0.0, 0.55, col))
        parts.append(Part(_box(c, yaw, 0.34, 0.1), 0.3, 0.4, col))
        parts.append(Part(_disc(c, 0.08, 8), 0.55, 0.68, tuple(int(v * 0.7) for v in col)))
    elif kind == 7:                                     # traffic light: a pole and a signal facing the road
        metal = _jitter(rng, _pick(rng, _METAL[:3]), 6)
        h = float(rng.uniform(3.0, 3.8))
        parts.append(Part(_disc(c, 0.08, 6), 0.0, h, metal))
        head = c + fwd * 0.2
        parts.append(Part(_box(head, yaw, 0.25, 0.32), h - 1.0, h, (30, 30, 30), 0.01,
                          {_FRONT: _signal_face(rng, 96, 32)}))
    elif kind == 8:                                     # bus shelter: back glass, a poster panel, a roof, a bench
        ln, dp, h = float(rng.uniform(2.8, 3.6)), float(rng.uniform(1.3, 1.6)), float(rng.uniform(2.3, 2.6))
        frame = _jitter(rng, _pick(rng, _METAL), 6)
        back = c - fwd * dp / 2
        parts.append(Part(_box(back, yaw, 0.06, ln), 0.1, h, (120, 140, 150), 0.05))
        end = back + left * (ln / 2) + fwd * dp / 2
        parts.append(Part(_box(end, yaw + math.pi / 2, 0.08, dp), 0.1, h, frame, 0.01,
                          {_FRONT: _poster(rng, 220, 128), _BACK: _poster(rng, 220, 128)}))
        for s in (-1, 1):
            parts.append(Part(_disc(back + left * s * ln / 2, 0.05, 4), 0.0, h, frame))
        parts.append(Part(_box(c, yaw, dp + 0.2, ln + 0.2), h, h + 0.12, frame))
        parts.append(Part(_box(back + fwd * 0.3, yaw, 0.4, ln * 0.7), 0.42, 0.48, (150, 152, 154)))
    elif kind == 9:                                     # a hedge's segment (a hedge's segments share a seed)
        h, d = float(rng.uniform(0.9, 1.8)), float(rng.uniform(0.6, 1.0))
        parts.append(Part(_box(c, yaw, HEDGE_SEGMENT_M, d), 0.0, h, _jitter(rng, _pick(rng, _GREENS), 6), 0.04,
                          leaves=True))
    elif kind == 10:                                    # shrub: a bush on the ground
        r, h = float(rng.uniform(0.4, 0.8)), float(rng.uniform(0.6, 1.5))
        parts.append(Part(_disc(c, r, 7), 0.0, h, _jitter(rng, _pick(rng, _GREENS), 8), 0.04, leaves=True))
    elif kind == 11:                                    # planter: a box of concrete or wood with a bush in it
        ln, wd, h = float(rng.uniform(0.8, 1.3)), float(rng.uniform(0.5, 0.8)), float(rng.uniform(0.45, 0.7))
        box = _jitter(rng, _pick(rng, ((150, 148, 142), (120, 118, 114), (110, 80, 54), (60, 62, 64))), 8)
        parts.append(Part(_box(c, yaw + math.pi / 2, ln, wd), 0.0, h, box))
        parts.append(Part(_disc(c, min(ln, wd) * 0.45, 6), h, h + float(rng.uniform(0.4, 0.9)),
                          _jitter(rng, _pick(rng, _GREENS), 8), 0.04, leaves=True))
    elif kind == 12:                                    # a fence's segment: pickets or railings between posts
        paint = _pick(rng, ((235, 232, 222), (120, 84, 52), (150, 120, 86), (40, 44, 42), (70, 90, 70)))
        h = float(rng.uniform(0.8, 1.3))
        face = _fence_face(rng, _jitter(rng, paint, 6), max(8, int(h / 0.02)), int(HEDGE_SEGMENT_M / 0.02))
        parts.append(Part(_box(c, yaw, HEDGE_SEGMENT_M, 0.05), 0.0, h, _jitter(rng, paint, 6), 0.02,
                          {_SIDE: face, _OTHER_SIDE: face}))
    elif kind == 13:                                    # a garden wall's segment: brick, stone or rendered, a coping
        body = _jitter(rng, _pick(rng, ((150, 80, 60), (130, 120, 105), (190, 184, 170), (110, 100, 90))), 10)
        h, d = float(rng.uniform(0.5, 1.1)), float(rng.uniform(0.22, 0.35))
        face = _wall_face(rng, body, max(8, int(h / 0.02)), int(HEDGE_SEGMENT_M / 0.02))
        parts.append(Part(_box(c, yaw, HEDGE_SEGMENT_M, d), 0.0, h, body, 0.02, {_SIDE: face, _OTHER_SIDE: face}))
        parts.append(Part(_box(c, yaw, HEDGE_SEGMENT_M, d + 0.06), h, h + 0.06, _jitter(rng, (150, 148, 142), 8)))
    else:
        raise ValueError(f"furniture kind {kind}: expected one of {sorted(KINDS)}")
    return parts


def _fence_face(rng: np.random.Generator, paint, h: int, w: int) -> np.ndarray:
    """A fence seen from the side: pickets (or railings) of ``paint`` with the dark garden between them, a
    rail near the top and the bottom, weathering."""
    img = np.empty((h, w, 3), np.float32)
    img[:] = (46, 58, 40)                                           # what shows between the pickets
    pitch = int(rng.integers(6, 12))                                # 12-24 cm
    width = max(2, int(pitch * rng.uniform(0.4, 0.7)))
    for x in range(int(rng.integers(pitch)), w, pitch):
        img[int(rng.integers(0, 3)):, x:x + width] = paint
    for r in (0.2, 0.8):
        img[int(r * h):int(r * h) + 3] = paint
    img *= (1 + 0.12 * fbm(rng, h, w, (max(2, h // 3), 2), (0.6, 0.4)))[..., None]
    return np.clip(img, 0, 255).astype(np.uint8)


def _wall_face(rng: np.random.Generator, body, h: int, w: int) -> np.ndarray:
    """A garden wall's face: courses of bricks or stones (joints darker, each unit its own tone), or render
    with stains."""
    base = np.asarray(body, np.float32)
    img = base * (1 + 0.1 * fbm(rng, h, w, (12, 3), (0.6, 0.4)))[..., None]
    if rng.random() < 0.7:
        ch, cw = (int(rng.integers(3, 5)), int(rng.integers(10, 13))) if rng.random() < 0.6 else \
            (int(rng.integers(8, 14)), int(rng.integers(12, 22)))
        for k, r0 in enumerate(range(0, h, ch)):
            off = (cw // 2) * (k % 2)
            for c0 in range(-off, w, cw):
                img[r0:r0 + ch, max(0, c0):c0 + cw] *= float(rng.uniform(0.86, 1.12))
            img[r0:r0 + 1] *= 0.7
            for c0 in range(-off, w, cw):
                img[r0:r0 + ch, max(0, c0):max(0, c0) + 1] *= 0.7
    return np.clip(img, 0, 255).astype(np.uint8)


#: metres: buildings with a look of their own (``style_seed``) and a flat roof at least this high carry roof
#: furniture (:func:`roof_parts`); lower ones (houses, shops) do not
ROOF_MIN_HEIGHT_M = 8.0


def roof_parts(b: Building) -> list[Part]:
    """The furniture on ``b``'s flat roof, drawn from ``b.style_seed``: on most roofs of 10 m x 10 m or more a
    housing for the stairs or the lift, and one to four air-conditioning units with louvres on their long
    sides, each at least 1.5 m in from the roof's edge and 0.8 m from the others (metres, map frame; heights
    above the building's ground, from its roof up). None for a building without a look of its own (variety
    0), a gabled roof or one from the imagery, a roof below :data:`ROOF_MIN_HEIGHT_M`, or a footprint that is
    not a rectangle (4 corners, right angles within 5 degrees, sides of 6 m or more). The world's mesh and the
    tile's painter both call it, so the two show the same units."""
    if b.style_seed is None or b.roof != "flat" or b.roof_from_ground or b.height < ROOF_MIN_HEIGHT_M:
        return []
    p = np.asarray(b.footprint, np.float64)
    if len(p) != 4:
        return []
    if np.linalg.norm(np.roll(p, -1, axis=0) - p, axis=1).min() < 6.0 or not right_angled(p):
        return []
    e, f = p[1] - p[0], p[3] - p[0]
    length, width = float(np.linalg.norm(e)), float(np.linalg.norm(f))
    u, v = e / length, f / width
    yaw = math.atan2(u[1], u[0])
    rng = np.random.default_rng([int(b.style_seed), 7001])
    placed: list[tuple[float, float, float, float]] = []
    parts: list[Part] = []

    def put(lu: float, lv: float, z1: float, rgb: tuple[int, int, int], margin: float, faces: dict) -> None:
        if lu + 2 * margin > length or lv + 2 * margin > width:
            return
        for _ in range(12):
            cu = rng.uniform(margin + lu / 2, length - margin - lu / 2)
            cv_ = rng.uniform(margin + lv / 2, width - margin - lv / 2)
            box = (cu - lu / 2, cu + lu / 2, cv_ - lv / 2, cv_ + lv / 2)
            if all(box[1] + 0.8 <= q[0] or q[1] + 0.8 <= box[0] or box[3] + 0.8 <= q[2] or q[3] + 0.8 <= box[2]
                   for q in placed):
                placed.append(box)
                c = p[0] + cu * u + cv_ * v
                parts.append(Part(rect_poly(c[0], c[1], lu, lv, yaw), b.height, b.height + z1, rgb, 0.04, faces))
                return

    if min(length, width) >= 10.0 and rng.random() < 0.7:      # stairs or lift
        g = rng.uniform(140, 200)
        tint = rng.uniform(-8, 8, 3)
        put(rng.uniform(3.0, 4.5), rng.uniform(2.5, 3.5), rng.uniform(2.4, 3.1),
            tuple(int(np.clip(g + t, 0, 255)) for t in tint), 2.0, {})
    for _ in range(int(rng.integers(1, 5))):                   # air-conditioning units
        g = rng.uniform(165, 215)
        rgb = (int(g), int(g), int(min(255, g + rng.uniform(0, 10))))
        lu, lv, hu = rng.uniform(1.2, 3.0), rng.uniform(0.9, 2.0), rng.uniform(0.9, 1.7)
        louvre = _louvres(rgb, hu, lu)
        put(lu, lv, hu, rgb, 1.5, {_SIDE: louvre, _OTHER_SIDE: louvre})
    return parts


def _louvres(rgb: tuple[int, int, int], height_m: float, length_m: float, texel: float = 0.04) -> np.ndarray:
    """The picture (H, W, 3 uint8) of an air-conditioning unit's side: a frame in ``rgb`` around a panel of
    dark horizontal slats every 8 cm."""
    h, w = max(4, int(round(height_m / texel))), max(4, int(round(length_m / texel)))
    img = np.empty((h, w, 3), np.float32)
    img[:] = rgb
    y, x = np.mgrid[0:h, 0:w]
    panel = (y >= 2) & (y < h - 2) & (x >= 2) & (x < w - 2)
    img[panel] *= 0.82
    img[panel & (y % 2 == 0)] *= 0.55
    return np.clip(img, 0, 255).astype(np.uint8)


def part_paint(rng: np.random.Generator, part: Part, walls: list[tuple[int, float]], h: int) -> np.ndarray:
    """The texture strip of ``part``'s walls (``walls``: (edge, length m) left to right, ``h`` texels high):
    its paint, mottled, with each edge in ``part.faces`` showing its picture."""
    cols = [max(1, int(round(ln / part.texel))) for _, ln in walls]
    w = sum(cols)
    if part.leaves:
        return leaf_texture(rng, h, w, part.rgb)
    base = np.asarray(part.rgb, np.float32)
    img = base * (1 + 0.07 * fbm(rng, h, w, (8, 1), (0.6, 0.4)))[..., None]
    x = 0
    for (edge, _), n in zip(walls, cols):
        pic = part.faces.get(edge)
        if pic is not None:
            img[:, x:x + n] = cv2.resize(pic, (n, h), interpolation=cv2.INTER_AREA)
        x += n
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)
