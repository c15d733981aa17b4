"""Cars in traffic at the capture's instant (satloc_env.world.traffic) and what hides the road in a tile
(capture.road_cover)."""
import math

import cv2
import numpy as np
import pytest

from satloc.labels import CLASS_ID as C
from satloc_env.world.capture import DEFAULT_GAP, PARTS, capture_tile, road_cover
from satloc_env.world.layout import Car, Layout
from satloc_env.world.traffic import (
    GAP_KERB_M,
    LANE_FROM_CENTRE_M,
    PARKED_FROM_KERB_M,
    kerb_texels,
    lane_texels,
    parked_cars,
    traffic_cars,
)


def street(length_m=400.0, width_m=12.0, mpp=0.1):
    """A straight east-west street of ``width_m`` across the middle of a field of grass, a centre line marked."""
    h_m = 60.0
    H, W = int(h_m / mpp), int(length_m / mpp)
    lab = np.full((H, W), C["grass"], np.uint8)
    y0, y1 = int((h_m - width_m) / 2 / mpp), int((h_m + width_m) / 2 / mpp)
    lab[y0:y1] = C["road"]
    mid = (y0 + y1) // 2
    dash = (np.arange(W) * mpp // 3) % 2 == 0          # 3 m dashes, 3 m gaps, 0.4 m wide
    lab[mid - 2:mid + 2, dash] = C["lane_marking"]
    rgb = np.full((H, W, 3), 90, np.uint8)
    rgb[lab == C["grass"]] = (70, 110, 50)
    rgb[lab == C["lane_marking"]] = 230
    return Layout(width_m=length_m, height_m=h_m, ground_mpp=mpp, ground_rgb=rgb, ground_labels=lab)


def test_lanes_of_a_straight_street_and_right_hand_traffic():
    lay = street()
    xy, heading, length = lane_texels(lay)
    # two lanes, each 1.9 m from the centre line (y = 30), along the street, less its ends
    assert 2 * (400 - 2 * 10) < length <= 2 * 400, length
    assert np.allclose(np.abs(xy[:, 1] - 30.0), LANE_FROM_CENTRE_M, atol=0.35), np.unique(np.round(xy[:, 1], 1))
    assert np.allclose(np.abs(heading[:, 0]), 1.0, atol=1e-3)
    south = xy[:, 1] < 30.0
    assert south.any() and (~south).any()
    assert (heading[south, 0] > 0).all() and (heading[~south, 0] < 0).all()   # east on the south lane: keep right

    cars = traffic_cars(lay, 20.0, np.random.default_rng(4))
    # a Poisson count of mean 20 per km of lane (about 15 cars), each clear of the others and on the road
    assert 5 <= len(cars) <= 30, len(cars)
    for c in cars:
        assert abs(abs(c.center[1] - 30.0) - LANE_FROM_CENTRE_M) < 0.35
        assert min(abs(c.yaw), abs(abs(c.yaw) - math.pi)) < 1e-3
    d = [math.dist(a.center, b.center) for i, a in enumerate(cars) for b in cars[i + 1:]]
    assert min(d) >= 8.0
    again = traffic_cars(lay, 20.0, np.random.default_rng(4))
    assert [(c.center, c.yaw, c.rgb) for c in again] == [(c.center, c.yaw, c.rgb) for c in cars]
    assert traffic_cars(lay, 0.0, np.random.default_rng(4)) == []


def test_cars_parked_along_the_kerbs_of_wide_streets_only():
    lay = street()                         # 12 m wide: kerbs at y = 24 and 36
    xy, _, length = kerb_texels(lay)
    assert 2 * (400 - 2 * 10) < length <= 2 * 400, length
    assert np.allclose(np.abs(xy[:, 1] - 30.0), 6.0 - PARKED_FROM_KERB_M, atol=0.35)
    cars = parked_cars(lay, 54.0, np.random.default_rng(2))
    # a Poisson count of mean 54 per km of kerb (about 40 cars), each on the road at its kerb, with its side's traffic
    assert 25 <= len(cars) <= 55, len(cars)
    for c in cars:
        assert abs(abs(c.center[1] - 30.0) - (6.0 - PARKED_FROM_KERB_M)) < 0.35
        assert (c.center[1] < 30.0) == (abs(c.yaw) < 1e-3)          # east on the south side: keep right
    d = [math.dist(a.center, b.center) for i, a in enumerate(cars) for b in cars[i + 1:]]
    assert min(d) >= GAP_KERB_M
    assert [(c.center, c.rgb) for c in parked_cars(lay, 54.0, np.random.default_rng(2))] == \
        [(c.center, c.rgb) for c in cars]
    # clear of the cars already there, and none on a street too narrow to park beside a lane (8 m: half-width 4 m)
    lay.cars = list(cars)
    assert all(min(math.dist(n.center, c.center) for c in cars) >= GAP_KERB_M
               for n in parked_cars(lay, 200.0, np.random.default_rng(3)))
    assert parked_cars(street(width_m=8.0), 200.0, np.random.default_rng(2)) == []
    assert parked_cars(lay, 0.0, np.random.default_rng(2)) == []


def test_traffic_keeps_clear_of_parked_cars():
    lay = street(length_m=120.0)
    lay.cars = [Car((x, 30.0 - LANE_FROM_CENTRE_M), 0.0) for x in np.arange(5.0, 120.0, 5.0)]
    assert traffic_cars(lay, 200.0, np.random.default_rng(0)) and all(
        c.center[1] > 30.0 for c in traffic_cars(lay, 200.0, np.random.default_rng(0)))


def test_no_lanes_on_a_junction_or_off_the_road():
    lay = street()
    lab = lay.ground_labels
    lab[:, 1900:2100] = C["road"]      # a north-south road crossing it: 20 m wide, no lane texel in the crossing
    xy, _, _ = lane_texels(lay)
    assert not ((np.abs(xy[:, 0] - 200.0) < 12.0) & (np.abs(xy[:, 1] - 30.0) < 8.0)).any()
    empty = street()
    empty.ground_labels[:] = C["grass"]
    assert lane_texels(empty)[2] == 0.0 and traffic_cars(empty, 50.0, np.random.default_rng(0)) == []


def test_traffic_in_the_capture_and_the_road_s_cover():
    lay = street(length_m=200.0)
    lay.trees = []
    mpp, seed = 0.2, 5
    _, base_lab = capture_tile(lay, mpp, seed, DEFAULT_GAP)
    with_cars, lab = capture_tile(lay, mpp, seed, DEFAULT_GAP, PARTS + ("traffic",))
    assert (lab == C["car"]).sum() > (base_lab == C["car"]).sum() == 0
    assert np.array_equal(capture_tile(lay, mpp, seed, DEFAULT_GAP, PARTS + ("traffic",))[0], with_cars)
    cover = road_cover(lay, mpp, seed, DEFAULT_GAP, PARTS + ("traffic",))
    plain = road_cover(lay, mpp, seed, DEFAULT_GAP)
    assert plain["car"] == 0.0 and plain["canopy"] == 0.0 and plain["open"] > 0.95
    assert 0.005 < cover["car"] < 0.1 and cover["shadow"] > 0.0     # the cars cast shadows too
    total = sum(cover[k] for k in ("car", "canopy", "building", "shadow", "open"))
    assert total == pytest.approx(1.0, abs=1e-9)
    assert cover["marking_contrast"] > 0.5      # white paint on grey asphalt
    # a tree over the road hides it; the copy (gap 0) measures the painted tile itself
    from satloc_env.world.layout import Tree
    lay.trees = [Tree((100.0, 30.0), canopy_radius=4.0, canopy_bottom=3.0, canopy_top=8.0)]
    shaded = road_cover(lay, mpp, seed, 0.0)
    assert shaded["canopy"] == pytest.approx(math.pi * 16 / (200 * 12), rel=0.15)


def test_deep_shadows_darken_the_shadows_only():
    from satloc_env.world.capture import REAL_SHADOW_GAIN, _captured_layout, capture_params
    from satloc_env.world.layout import Building
    from satloc_env.world.tile import shadow_mask

    lay = street(length_m=120.0)
    lay.buildings = [Building(np.array([[50.0, 40.0], [70.0, 40.0], [70.0, 55.0], [50.0, 55.0]]), 12.0)]
    parts = ("time", "blur")       # no texture of its own, warp or compression: the shadows alone differ
    plain, lab = capture_tile(lay, 0.2, 1, DEFAULT_GAP, parts)
    deep, lab2 = capture_tile(lay, 0.2, 1, DEFAULT_GAP, parts + ("deep_shadows",))
    assert np.array_equal(lab, lab2)
    seen, _ = _captured_layout(lay, capture_params(DEFAULT_GAP, 0.2), 1, parts)
    m = shadow_mask(seen, 0.2, lab.shape) > 0
    inner = m & (lab == C["grass"])
    inner[:, :5] = inner[:, -5:] = False
    lit = ~m & (lab == C["grass"])
    assert inner.sum() > 100
    ratio = deep[inner].astype(float).mean() / plain[inner].astype(float).mean()
    assert ratio == pytest.approx(REAL_SHADOW_GAIN / 0.55, rel=0.1)
    far = lit & (cv2.dilate(m.astype(np.uint8), np.ones((9, 9), np.uint8)) == 0)
    assert np.array_equal(deep[far], plain[far])
