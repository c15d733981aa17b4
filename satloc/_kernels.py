"""Compiled inner loops of the localizer (numba). Each is the plain-loop form of a formula in
:mod:`satloc.localizers.database`; the numpy reference of the co-occurrence score is kept in the tests."""
from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True, inline="always")
def _place(cx, cy, co, si, px, py):
    """Map point of the vehicle-frame point (px, py) seen from pose (cx, cy, yaw) with cos/sin (co, si)."""
    return cx + co * px - si * py, cy + si * px + co * py


@numba.njit(cache=True, nogil=True)
def cooccurrence_scores(cands, pv, gid, wg, origin_x, origin_y, mpp, h, w, pixel_row, sat_ids, sat_w,
                        n_entries):
    """score[c] = sum_j sum over entries i in NN(g_j) ∩ NN(s at c ⊕ pv_j) of wg[j, i] * ws[pixel, i]."""
    n, m = gid.shape
    # per query: entry id -> its weight for each sample (dense over the samples' neighbour ids)
    remap = np.full(n_entries, -1, np.int64)
    uniq = 0
    for j in range(n):
        for k in range(m):
            i = gid[j, k]
            if i >= 0 and remap[i] < 0:
                remap[i] = uniq
                uniq += 1
    table = np.zeros((n, max(uniq, 1)), np.float32)
    for j in range(n):
        for k in range(m):
            i = gid[j, k]
            if i >= 0:
                table[j, remap[i]] += wg[j, k]
    out = np.zeros(len(cands))
    for c in range(len(cands)):
        co, si = math.cos(cands[c, 2]), math.sin(cands[c, 2])
        acc = 0.0
        for j in range(n):
            x, y = _place(cands[c, 0], cands[c, 1], co, si, pv[j, 0], pv[j, 1])
            col = math.floor((x - origin_x) / mpp)
            row = math.floor((origin_y - y) / mpp)
            if row < 0 or row >= h or col < 0 or col >= w:
                continue
            r = pixel_row[row * w + col]
            if r < 0:
                continue
            for k in range(sat_ids.shape[1]):
                i = sat_ids[r, k]
                if i >= 0:
                    t = remap[i]
                    if t >= 0:
                        acc += table[j, t] * sat_w[r, k]
        out[c] = acc
    return out


@numba.njit(cache=True, nogil=True)
def location_scores(cands, pv, loc, wg, radius, raster, origin_x, origin_y, cell):
    """Ground-only: entry i (of NN(g_j)) counts when its location lies within ``radius`` of c ⊕ pv_j,
    weighted wg / max(distance, 0.25). Also, per candidate, the sum over its samples of the ``raster`` cell under
    c ⊕ pv_j (row 0 from ``origin_y`` up, column 0 from ``origin_x``, cells of side ``cell``; 0 off the raster;
    an empty raster gives 0). Returns (scores, raster sums)."""
    n, m = wg.shape
    h, w = raster.shape
    out = np.zeros(len(cands))
    chance = np.zeros(len(cands))
    r2 = radius * radius
    for c in range(len(cands)):
        co, si = math.cos(cands[c, 2]), math.sin(cands[c, 2])
        acc = 0.0
        bg = 0.0
        for j in range(n):
            x, y = _place(cands[c, 0], cands[c, 1], co, si, pv[j, 0], pv[j, 1])
            if h > 0:
                col = int(math.floor((x - origin_x) / cell))
                row = int(math.floor((y - origin_y) / cell))
                if 0 <= row < h and 0 <= col < w:
                    bg += raster[row, col]
            for k in range(m):
                if wg[j, k] <= 0:
                    continue
                dx, dy = loc[j, k, 0] - x, loc[j, k, 1] - y
                d2 = dx * dx + dy * dy
                if d2 <= r2:
                    acc += wg[j, k] / max(math.sqrt(d2), 0.25)
        out[c] = acc
        chance[c] = bg
    return out, chance
