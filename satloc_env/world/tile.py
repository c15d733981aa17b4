"""Paint the satellite tile (overhead view) from a layout: ground downsampled to the tile resolution, then
shadows, roofs, tree canopies and cars drawn from above. Also returns the tile's semantic labels.

``lean`` (metres east and north per metre of height, default none) draws the view of a sensor off nadir:
roofs and canopies displaced from their footprints by their height times ``lean``, with the facades in
between (see :mod:`satloc_env.world.capture`)."""
from __future__ import annotations

import math

import cv2
import numpy as np

from satloc.labels import CLASS_ID as C

from .furniture import furniture_parts, roof_parts
from .layout import Layout
from .paint import fill_poly, noise, rect_poly

NOISE_PERIOD_M = 64.0  # texture noise repeats every 64 m, so aliased copies of cells stay copies


def _poly_px(lay: Layout, pts: np.ndarray, mpp: float) -> np.ndarray:
    return lay.world_to_raster(pts, mpp)


def _local_mask(px: np.ndarray, h: int, w: int):
    """Bounding-box slice of polygon ``px`` (pixels) clipped to the image, and its fill mask there."""
    x0, y0 = np.maximum(np.floor(px.min(0)).astype(int) - 1, 0)
    x1, y1 = np.minimum(np.ceil(px.max(0)).astype(int) + 2, (w, h))
    if x0 >= x1 or y0 >= y1:
        return None, None
    m = np.zeros((y1 - y0, x1 - x0), np.uint8)
    fill_poly(m, px - (x0, y0), 1)
    return (slice(y0, y1), slice(x0, x1)), m > 0


def shadow_mask(lay: Layout, mpp: float, shape: tuple[int, int]) -> np.ndarray:
    """(h, w) uint8, 1 where the tile of ``lay`` at ``mpp`` is in the shadow of a building, tree, car or piece of
    street furniture at the layout's sun (the tile's roofs, canopies and cars are drawn over it)."""
    h, w = shape
    sun = np.array([math.cos(lay.sun_azimuth), math.sin(lay.sun_azimuth)])
    cot = 1.0 / math.tan(max(lay.sun_elevation, 0.15))
    shadow = np.zeros((h, w), np.uint8)
    for b in lay.buildings:
        off = -sun * b.height * cot
        pts = np.vstack([b.footprint, b.footprint + off])
        hull = cv2.convexHull(pts.astype(np.float32)).reshape(-1, 2)
        fill_poly(shadow, _poly_px(lay, hull, mpp), 1)
    for t in lay.trees:
        c = np.array(t.center) - sun * (t.canopy_bottom + t.canopy_top) / 2 * cot
        ang = np.linspace(0, 2 * np.pi, 16, endpoint=False)
        circ = c + t.canopy_radius * np.stack([np.cos(ang), np.sin(ang)], 1)
        fill_poly(shadow, _poly_px(lay, circ, mpp), 1)
    for car in lay.cars:
        c = np.array(car.center) - sun * car.height * cot * 0.5
        fill_poly(shadow, _poly_px(lay, rect_poly(c[0], c[1], car.length, car.width, car.yaw), mpp), 1)
    parts = [p for f in lay.furniture for p in furniture_parts(f)]     # street furniture: thin shadows, small tops
    for p in parts:
        hull = cv2.convexHull(np.vstack([p.footprint - sun * p.z0 * cot, p.footprint - sun * p.z1 * cot])
                              .astype(np.float32)).reshape(-1, 2)
        fill_poly(shadow, _poly_px(lay, hull, mpp), 1)
    return shadow


#: the brightness of ground in a cast shadow, as a fraction of the lit ground's (the tiles' default)
SHADOW_GAIN = 0.55


def paint_tile(lay: Layout, mpp: float, seed: int, lean: tuple[float, float] = (0.0, 0.0),
               shadow_gain: float = SHADOW_GAIN) -> tuple[np.ndarray, np.ndarray]:
    k = mpp / lay.ground_mpp
    if abs(k - round(k)) > 1e-6 or round(k) < 1:
        raise ValueError(f"tile meters_per_pixel={mpp} must be an integer multiple of ground_mpp={lay.ground_mpp}")
    k = int(round(k))
    H, W = lay.ground_labels.shape
    h, w = H // k, W // k
    img = cv2.resize(lay.ground_rgb[: h * k, : w * k], (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)
    labels = lay.ground_labels[k // 2: h * k: k, k // 2: w * k: k].copy()
    rng = np.random.default_rng([seed, 11])
    period = max(8, int(round(NOISE_PERIOD_M / mpp)))
    tex = noise((period, period), rng, (max(1, 1.0 / mpp), 1), [1.0, 0.7])
    yy, xx = np.mgrid[0:h, 0:w]
    tex = tex[yy % period, xx % period]

    # shadows, cast away from the sun
    sun = np.array([math.cos(lay.sun_azimuth), math.sin(lay.sun_azimuth)])
    cot = 1.0 / math.tan(max(lay.sun_elevation, 0.15))
    shadow = shadow_mask(lay, mpp, (h, w))
    img[shadow > 0] *= shadow_gain
    parts = [p for f in lay.furniture for p in furniture_parts(f)]

    # roofs: base colour, texture, a darker outline and a ridge; off nadir, the roof moves by its height x lean
    # and the facades facing the sensor fill the gap between footprint and roof
    lean_v = np.asarray(lean, np.float64)
    leaning = bool(np.any(lean_v != 0.0))
    for b in lay.buildings:
        fp = b.footprint + lean_v * b.height if leaning else b.footprint
        if leaning:
            hull = cv2.convexHull(np.vstack([b.footprint, fp]).astype(np.float32)).reshape(-1, 2)
            fill_poly(img, _poly_px(lay, hull, mpp), tuple(float(v) * 0.55 + 30.0 for v in b.roof_rgb))
            fill_poly(labels, _poly_px(lay, hull, mpp), C["building"])
        px = _poly_px(lay, fp, mpp)
        box, sel = _local_mask(px, h, w)
        if box is None:
            continue
        region = img[box]
        region[sel] = np.clip(np.asarray(b.roof_rgb, np.float32) + 14 * tex[box][sel, None], 0, 255)
        labels[box][sel] = C["building"]
        cv2.polylines(img, [np.round(px).astype(np.int32).reshape(-1, 1, 2)], True,
                      tuple(float(v) * 0.6 for v in b.roof_rgb), 1)
        units = roof_parts(b)
        for part in units:   # roof furniture: the shadows on the roof, then the tops (lit), off nadir with height
            base = part.footprint + lean_v * part.z0 if leaning else part.footprint
            hull = cv2.convexHull(np.vstack([base, base - sun * (part.z1 - part.z0) * cot]).astype(np.float32))
            fill_poly(img, _poly_px(lay, hull.reshape(-1, 2), mpp), tuple(float(v) * 0.55 for v in b.roof_rgb))
        for part in units:
            top = _poly_px(lay, part.footprint + lean_v * part.z1 if leaning else part.footprint, mpp)
            fill_poly(img, top, tuple(min(255.0, float(v) * 1.08) for v in part.rgb))
            cv2.polylines(img, [np.round(top).astype(np.int32).reshape(-1, 1, 2)], True,
                          tuple(float(v) * 0.7 for v in part.rgb), 1)
        if len(fp) == 4 and not units:  # ridge along the long side (houses) or a rooftop unit (tall blocks)
            e = fp[1] - fp[0]
            f = fp[3] - fp[0]
            if np.linalg.norm(e) < np.linalg.norm(f):
                e, f = f, e
            c0 = fp[0] + f / 2
            ridge = _poly_px(lay, np.array([c0 + 0.1 * e, c0 + 0.9 * e]), mpp)
            cv2.line(img, tuple(np.round(ridge[0]).astype(int)), tuple(np.round(ridge[1]).astype(int)),
                     tuple(float(v) * 0.75 for v in b.roof_rgb), max(1, int(round(0.4 / mpp))))
    # tree canopies: leafy noise, darker towards the shadow side
    leaf = [(52, 92, 40), (44, 80, 34), (70, 104, 46), (60, 84, 38)]
    for t in lay.trees:
        centre = np.array(t.center) + lean_v * (t.canopy_bottom + t.canopy_top) / 2
        cu, cv_ = _poly_px(lay, centre, mpp)
        r = t.canopy_radius / mpp
        y0, y1 = max(0, int(cv_ - r - 1)), min(h, int(cv_ + r + 2))
        x0, x1 = max(0, int(cu - r - 1)), min(w, int(cu + r + 2))
        if y0 >= y1 or x0 >= x1:
            continue
        gy, gx = np.mgrid[y0:y1, x0:x1]
        dx, dy = gx - cu, gy - cv_
        d = np.hypot(dx, dy) / max(r, 1e-6)
        sel = d <= 1.0
        shade = 1.0 + 0.25 * (dx * sun[0] - dy * sun[1]) / max(r, 1e-6) - 0.2 * d
        col = np.asarray(leaf[t.shade % len(leaf)], np.float32)
        patch = col[None, None] * shade[..., None] + 22 * tex[y0:y1, x0:x1, None]
        img[y0:y1, x0:x1][sel] = np.clip(patch[sel], 0, 255)
        labels[y0:y1, x0:x1][sel] = C["tree"]
    for p in sorted(parts, key=lambda q: q.z1):
        fill_poly(img, _poly_px(lay, p.footprint + lean_v * p.z1, mpp), tuple(float(v) for v in p.rgb))
        if p.leaves:    # hedges and shrubs: vegetation from above
            fill_poly(labels, _poly_px(lay, p.footprint + lean_v * p.z1, mpp), C["tree"])
    # cars: body, darker windscreen and rear window
    for car in lay.cars:
        body = rect_poly(car.center[0], car.center[1], car.length, car.width, car.yaw)
        fill_poly(img, _poly_px(lay, body, mpp), tuple(float(v) for v in car.rgb))
        fill_poly(labels, _poly_px(lay, body, mpp), C["car"])
        c, s = math.cos(car.yaw), math.sin(car.yaw)
        for off, ln in ((0.45, 0.5), (-0.75, 0.35)):
            cx, cy = car.center[0] + c * off, car.center[1] + s * off
            fill_poly(img, _poly_px(lay, rect_poly(cx, cy, ln, car.width * 0.8, car.yaw), mpp), (35, 40, 50))
    return np.clip(img, 0, 255).astype(np.uint8), labels
