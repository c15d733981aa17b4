"""Cars driving on the roads at the instant a satellite captures the world (issue 46).

A real tile shows the traffic of its moment: cars in the lanes, between and beside the parked ones, other
cars than any the ground pass meets. :func:`traffic_cars` draws them for a layout from its ground labels
alone (a generated grid, a world from map vectors or one over an image all have those): the lanes are found
from the road's distance to its kerb, and cars stand in them, heading along the road, right-hand traffic.

How the lanes are found: the road (``road`` and ``lane_marking`` texels) is resampled to :data:`RES_M`; ``d`` is
each texel's distance to the nearest texel off the road, and its gradient points from the kerb to the
street's middle. From every texel the distance is followed uphill to the ridge (the street's centre line):
``R``, the half-width there. A lane's centre lies ``max(R / 2, R - LANE_FROM_CENTRE_M)`` from the kerb: half
the half-width on a narrow street, :data:`LANE_FROM_CENTRE_M` from the centre line on a wide one, beside
the kerb's parking. Texels within one texel of that distance (a band two texels wide), where the gradient is clean (not at a
junction or a corner), where the half-width is a street's and where the distance to the kerb holds
:data:`STEADY_M` ahead and behind (not in a junction), are the lanes; their area over the band's width is the
lanes' length. A car is drawn at a random lane texel, its heading the direction along the road with the
centre line on its left; one is kept only where its footprint is on the road and it stands clear of the
parked cars and of the other cars in traffic.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from satloc.labels import CLASS_ID as C

from .layout import Car, Layout
from .revisit import _labels_at
from .variety import BODIES, car_body, car_colour

__all__ = ["TRAFFIC_PER_KM", "kerb_texels", "lane_texels", "parked_cars", "traffic_cars"]

#: cars in traffic per kilometre of lane at the capture's instant (the default of the capture's ``traffic``
#: part at full strength)
TRAFFIC_PER_KM = 15.0
#: resolution (metres) at which the lanes are found
RES_M = 0.25
#: a lane's centre lies this far from the street's centre line on a wide street
LANE_FROM_CENTRE_M = 1.9
#: half-widths (metres) taken as a street's: narrower is a path, wider a square or a junction
HALF_WIDTH_M = (1.5, 8.0)
#: a lane texel keeps its distance to the kerb within STEADY_TOL_M this far (metres) ahead and behind
STEADY_M, STEADY_TOL_M = 4.0, 0.35
#: clearance (metres, centre to centre) from a car in traffic to another one, and to a parked car
GAP_TRAFFIC_M, GAP_PARKED_M = 8.0, 3.0
#: a parked car's centre lies this far from the kerb (its half-width and a hand's breadth)
PARKED_FROM_KERB_M = 1.1
#: streets narrower than this half-width (metres) have no parking: a car in the lane beside a parked one
#: (its centre 1.75 m from the centre line) needs the street's half-width to hold both
PARKING_HALF_WIDTH_M = 5.0
#: clearance (metres, centre to centre) between parked cars: a car's length and a gap
GAP_KERB_M = 6.0


def _road(lay: Layout) -> tuple[np.ndarray, float]:
    """The road mask (uint8) at about :data:`RES_M` and its exact resolution."""
    lab = lay.ground_labels
    k = max(1, int(round(RES_M / lay.ground_mpp)))
    road = np.isin(lab[k // 2::k, k // 2::k], (C["road"], C["lane_marking"])).astype(np.uint8)
    return road, lay.ground_mpp * k


def lane_texels(lay: Layout) -> tuple[np.ndarray, np.ndarray, float]:
    """The lanes of ``lay``'s roads: (world points (n, 2), unit headings (n, 2) of right-hand traffic, the lanes'
    length in metres). See the module docstring."""
    return _band_texels(lay, None, HALF_WIDTH_M)


def kerb_texels(lay: Layout, from_kerb_m: float = PARKED_FROM_KERB_M,
                min_half_width_m: float = PARKING_HALF_WIDTH_M) -> tuple[np.ndarray, np.ndarray, float]:
    """The parking strips of ``lay``'s roads: texels ``from_kerb_m`` from the kerb on streets whose half-width is at
    least ``min_half_width_m`` (and at most a street's, :data:`HALF_WIDTH_M`), away from junctions, as
    :func:`lane_texels` finds lanes: (world points, unit headings of right-hand traffic, the strips' length)."""
    return _band_texels(lay, float(from_kerb_m), (float(min_half_width_m), HALF_WIDTH_M[1]))


def _band_texels(lay: Layout, from_kerb_m: float | None, half_width_m: tuple[float, float]
                 ) -> tuple[np.ndarray, np.ndarray, float]:
    """Texels of a band along the kerbs: ``from_kerb_m`` from it, or (None) the lane's distance of the module
    docstring; on streets of half-width within ``half_width_m``."""
    road, res = _road(lay)
    if not road.any():
        return np.zeros((0, 2)), np.zeros((0, 2)), 0.0
    d = cv2.distanceTransform(road, cv2.DIST_L2, 5).astype(np.float32) * res
    gr, gc = np.gradient(d)                      # per texel, along rows and columns
    gr, gc = gr / res, gc / res
    rows, cols = np.nonzero(road)
    g = np.hypot(gr[rows, cols], gc[rows, cols])
    keep = g > 0.9                               # a clean slope: off the ridge, not in a corner
    rows, cols = rows[keep], cols[keep]
    ur, uc = gr[rows, cols] / g[keep], gc[rows, cols] / g[keep]
    h, w = d.shape
    # follow the slope uphill to the ridge: R, the street's half-width there
    r_f, c_f = rows.astype(np.float32), cols.astype(np.float32)
    half = d[rows, cols].copy()
    alive = np.ones(rows.size, bool)
    for _ in range(int(HALF_WIDTH_M[1] / res) + 2):
        r_f += ur
        c_f += uc
        ri = np.clip(np.round(r_f).astype(np.int64), 0, h - 1)
        ci = np.clip(np.round(c_f).astype(np.int64), 0, w - 1)
        nxt = d[ri, ci]
        up = alive & (nxt > half)
        half = np.where(up, nxt, half)
        alive = up
        if not alive.any():
            break
    target = np.maximum(half / 2, half - LANE_FROM_CENTRE_M) if from_kerb_m is None else from_kerb_m
    off = d[rows, cols] - target        # a band of two texels' width: exactly two rows of texels across a lane
    sel = ((off >= -res) & (off < res) & (half >= half_width_m[0]) & (half <= half_width_m[1])
           & ~alive)
    rows, cols, ur, uc = rows[sel], cols[sel], ur[sel], uc[sel]
    # a lane keeps its distance to the kerb along the road: not so in a junction or round a corner
    d0 = d[rows, cols]
    steady = np.ones(rows.size, bool)
    for sign in (-1.0, 1.0):
        ri = np.clip(np.round(rows + sign * STEADY_M / res * uc).astype(np.int64), 0, h - 1)
        ci = np.clip(np.round(cols - sign * STEADY_M / res * ur).astype(np.int64), 0, w - 1)
        steady &= np.abs(d[ri, ci] - d0) <= STEADY_TOL_M
    rows, cols, ur, uc = rows[steady], cols[steady], ur[steady], uc[steady]
    xy = np.stack([(cols + 0.5) * res, lay.height_m - (rows + 0.5) * res], 1)
    g_world = np.stack([uc, -ur], 1)             # towards the centre line, x east and y north
    heading = np.stack([g_world[:, 1], -g_world[:, 0]], 1)    # the centre line on the left
    return xy, heading, float(steady.sum() * res / 2.0)


def _on_road(lay: Layout, car: Car) -> bool:
    """Whether the car's corners, edge midpoints and centre all lie on the road (void beyond the layout)."""
    c, s = math.cos(car.yaw), math.sin(car.yaw)
    pts = [(car.center[0] + a * c * car.length / 2 - b * s * car.width / 2,
            car.center[1] + a * s * car.length / 2 + b * c * car.width / 2)
           for a in (-1, 0, 1) for b in (-1, 0, 1)]
    return bool(np.isin(_labels_at(lay, np.asarray(pts)), (C["road"], C["lane_marking"])).all())


def traffic_cars(lay: Layout, per_km: float, rng: np.random.Generator) -> list[Car]:
    """Cars in traffic on ``lay``'s roads, ``per_km`` per kilometre of lane on average (a Poisson count; fewer where
    the lanes are full), placed as the module docstring says; their bodies and colours as streets have them."""
    if per_km <= 0:
        return []
    xy, heading, length_m = lane_texels(lay)
    return _draw_cars(lay, xy, heading, per_km * length_m / 1000.0, rng, GAP_PARKED_M, GAP_TRAFFIC_M)


def parked_cars(lay: Layout, per_km: float, rng: np.random.Generator) -> list[Car]:
    """Cars parked along the kerbs of ``lay``'s streets that are wide enough (:func:`kerb_texels`), ``per_km`` per
    kilometre of kerb on average (a Poisson count; fewer where the kerbs are full), heading with the traffic of
    their side, :data:`GAP_KERB_M` apart and clear of ``lay``'s cars; each kept only where its footprint is on the
    road. Bodies and colours as streets have them."""
    if per_km <= 0:
        return []
    xy, heading, length_m = kerb_texels(lay)
    return _draw_cars(lay, xy, heading, per_km * length_m / 1000.0, rng, GAP_KERB_M, GAP_KERB_M)


def _draw_cars(lay: Layout, xy: np.ndarray, heading: np.ndarray, mean: float, rng: np.random.Generator,
               gap_others: float, gap_own: float) -> list[Car]:
    """A Poisson count of mean ``mean`` cars at random texels of ``xy`` heading along ``heading``, each at least
    ``gap_others`` (centre to centre) from ``lay``'s cars and ``gap_own`` from the others drawn, with its footprint
    on the road."""
    if xy.shape[0] == 0:
        return []
    n = int(rng.poisson(mean))
    cars: list[Car] = []
    others = np.asarray([c.center for c in lay.cars], np.float64).reshape(-1, 2)
    for i in rng.permutation(xy.shape[0]):
        if len(cars) >= n:
            break
        p = xy[i]
        if others.size and np.min(np.hypot(*(others - p).T)) < gap_others:
            continue
        if cars and min(math.dist(p, c.center) for c in cars) < gap_own:
            continue
        body = car_body(rng)
        spec = BODIES[body]
        car = Car((float(p[0]), float(p[1])), float(math.atan2(heading[i, 1], heading[i, 0])),
                  float(rng.uniform(*spec["length"])), float(rng.uniform(*spec["width"])),
                  float(rng.uniform(*spec["height"])), car_colour(rng), body=body)
        if _on_road(lay, car):
            cars.append(car)
    return cars
