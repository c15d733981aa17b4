"""Procedural texture painting helpers (numpy + OpenCV), deterministic from a ``numpy.random.Generator``."""
from __future__ import annotations

import math

import cv2
import numpy as np


def noise(shape: tuple[int, int], rng: np.random.Generator, scales_px=(64, 16, 4, 1), weights=None) -> np.ndarray:
    """Multi-octave value noise in roughly [-1, 1], float32, of size ``shape`` (rows, cols)."""
    h, w = shape
    weights = weights or [1.0 / (i + 1) for i in range(len(scales_px))]
    out = np.zeros((h, w), np.float32)
    for s, wt in zip(scales_px, weights):
        gh, gw = max(2, int(np.ceil(h / s)) + 1), max(2, int(np.ceil(w / s)) + 1)
        g = rng.standard_normal((gh, gw)).astype(np.float32)
        if s <= 1:
            layer = rng.standard_normal((h, w)).astype(np.float32)
        else:
            layer = cv2.resize(g, (int(gw * s), int(gh * s)), interpolation=cv2.INTER_CUBIC)[:h, :w]
        out += wt * layer
    return out / (sum(weights) or 1.0)


def tint(mask: np.ndarray, img: np.ndarray, rgb, n: np.ndarray, amp: float, chroma=(1.0, 1.0, 1.0)) -> None:
    """Fill ``img`` where ``mask`` with colour ``rgb`` modulated by noise ``n`` (amplitude ``amp``)."""
    base = np.asarray(rgb, np.float32)[None, :] * np.asarray(chroma, np.float32)[None, :]
    vals = base + (amp * n[mask])[:, None]
    img[mask] = np.clip(vals, 0, 255).astype(np.uint8)


def to_px(xy_local_m: np.ndarray, size_m: float, mpp: float) -> np.ndarray:
    """Patch-local metres (x east, y north, origin SW corner) to pixel coordinates (u right, v down)."""
    xy = np.asarray(xy_local_m, dtype=np.float64)
    return np.stack([xy[..., 0] / mpp - 0.5, (size_m - xy[..., 1]) / mpp - 0.5], axis=-1)


def fill_poly(img: np.ndarray, poly_px: np.ndarray, value) -> None:
    """Anti-alias-free polygon fill with sub-pixel vertex precision (pixel centres at integers)."""
    shift = 4
    pts = np.round((np.asarray(poly_px) ) * (1 << shift)).astype(np.int32).reshape(-1, 1, 2)
    cv2.fillPoly(img, [pts], value, lineType=cv2.LINE_8, shift=shift)


def rect_poly(cx: float, cy: float, length: float, width: float, yaw: float) -> np.ndarray:
    """Corners (4, 2) of an oriented rectangle, counter-clockwise."""
    c, s = np.cos(yaw), np.sin(yaw)
    hl, hw = length / 2, width / 2
    local = np.array([[hl, hw], [-hl, hw], [-hl, -hw], [hl, -hw]])
    return np.stack([cx + c * local[:, 0] - s * local[:, 1], cy + s * local[:, 0] + c * local[:, 1]], axis=1)


def right_angled(quad: np.ndarray, tol_deg: float = 5.0) -> bool:
    """Whether the four corners ``quad`` ((4, 2), in order round the polygon, sides longer than zero) meet at
    right angles within ``tol_deg`` degrees at every corner: a rectangle."""
    e = np.roll(quad, -1, axis=0) - quad
    lengths = np.linalg.norm(e, axis=1)
    cos = np.abs(np.sum(e * np.roll(e, -1, axis=0), axis=1)) / (lengths * np.roll(lengths, -1))
    return bool(cos.max() <= math.sin(math.radians(tol_deg)))


def value_noise(rng: np.random.Generator, h: int, w: int, cell: int) -> np.ndarray:
    """Smooth value noise in [-1, 1], (h, w) float32, with features about ``cell`` texels wide."""
    gh, gw = h // cell + 2, w // cell + 2
    grid = rng.uniform(-1.0, 1.0, (gh, gw)).astype(np.float32)
    if cell == 1:
        return grid[:h, :w]
    return cv2.resize(grid, (gw * cell, gh * cell), interpolation=cv2.INTER_LINEAR)[:h, :w]


def fbm(rng: np.random.Generator, h: int, w: int, cells, amps) -> np.ndarray:
    """Sum of value noises (:func:`value_noise`) of several feature sizes (``cells``) and amplitudes."""
    return sum(a * value_noise(rng, h, w, c) for c, a in zip(cells, amps))
