"""Procedural scene generators: a grid of city or residential blocks, painted as a satellite tile and
built as a 3-D world from one layout.

A grid scene has ``nx x ny`` cells of ``pitch`` metres, road centre lines on the cell borders, and a
``margin`` of open land (with the roads continuing to the edge) around them. Each cell is painted in its own
coordinates from a cell seed, so an *aliased* cell (one that reuses another cell's seed) is an exact copy of
it: the same layout, objects and texture.

``variety`` (0 to 1, :mod:`satloc_env.world.variety`) gives that share of the objects looks of their own (a facade
grammar, a tree species, a car body and colour), parks more cars at the kerbs and plants more street trees, and
wears the road surface. Its draws come from a generator of their own, so at ``variety`` 0 a scene is exactly what
it was before the knob, and at any ``variety`` every object stands where it stood.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from satloc.labels import CLASS_ID as C

from .furniture import HEDGE_SEGMENT_M, footprint_radius
from .layout import Building, Car, Furniture, Layout, Tree
from .paint import fill_poly, noise, tint, to_px
from .variety import BODIES, SPECIES, car_body, car_colour, ground_detail, marking_wear, road_wear

LANE_W = 3.5            # metres, one driving lane
MARK_W = 0.15           # lane marking width


@dataclass(frozen=True)
class GridParams:
    style: Literal["city", "residential"] = "city"
    blocks: tuple[int, int] = (4, 4)
    pitch_m: float = 80.0
    road_width_m: float = 12.0
    sidewalk_m: float = 3.0
    margin_m: float = 20.0
    variety: float = 0.0    # satloc_env.world.variety: objects of their own, denser kerbs, a worn road (0: none)

    def size_m(self) -> tuple[float, float]:
        return (self.blocks[0] * self.pitch_m + 2 * self.margin_m, self.blocks[1] * self.pitch_m + 2 * self.margin_m)

    def road_lines(self) -> tuple[np.ndarray, np.ndarray]:
        """x of the north-south roads and y of the east-west roads (centre lines, metres)."""
        xs = self.margin_m + self.pitch_m * np.arange(self.blocks[0] + 1)
        ys = self.margin_m + self.pitch_m * np.arange(self.blocks[1] + 1)
        return xs, ys


def alias_sources(n_cells: int, aliasing: float, rng: np.random.Generator) -> np.ndarray:
    """For each cell the index of the cell whose seed it uses; ``round(aliasing * n)`` cells are copies."""
    src = np.arange(n_cells)
    n_copy = min(int(round(aliasing * n_cells)), n_cells - 1)
    if n_copy <= 0:
        return src
    order = rng.permutation(n_cells)
    copies, originals = order[:n_copy], order[n_copy:]
    src[copies] = rng.choice(originals, size=n_copy)
    return src


def _paint_base(labels: np.ndarray, rgb: np.ndarray, rng: np.random.Generator, mpp: float) -> None:
    """Colour every pixel from its class with natural, class-specific texture."""
    h, w = labels.shape
    px = lambda m: max(1.0, m / mpp)  # metres to pixels
    fine = noise((h, w), rng, (px(0.4), 1), [1.0, 0.6])
    coarse = noise((h, w), rng, (px(12.0), px(3.0)), [1.0, 0.5])
    for cls, col, amp_f, amp_c in (
        ("road", (88, 88, 92), 10, 10), ("parking", (100, 100, 102), 10, 8), ("sidewalk", (168, 163, 155), 8, 10),
        ("grass", (78, 118, 48), 16, 22), ("soil", (132, 108, 78), 14, 16), ("building", (120, 118, 112), 6, 6),
        ("lane_marking", (232, 232, 226), 6, 4), ("void", (60, 60, 60), 6, 6),
    ):
        m = labels == C[cls]
        if m.any():
            tint(m, rgb, col, amp_f * fine + amp_c * coarse, 1.0)
    g = labels == C["grass"]
    if g.any():  # dry patches: shift some grass towards yellow-brown
        dry = np.clip(coarse[g] * 1.5, 0, 1)[:, None]
        rgb[g] = np.clip(rgb[g] * (1 - 0.35 * dry) + np.array([150, 135, 80]) * 0.35 * dry, 0, 255).astype(np.uint8)
    sw = labels == C["sidewalk"]
    if sw.any():  # paving slab joints every 1.5 m
        step = max(2, int(round(1.5 / mpp)))
        joints = np.zeros((h, w), bool)
        joints[::step, :] = True
        joints[:, ::step] = True
        j = sw & joints
        rgb[j] = (rgb[j] * 0.82).astype(np.uint8)


class CellPainter:
    """Paints one cell (road centre to road centre) and lists its objects, in cell coordinates:
    metres with the origin at the cell's south-west corner, x east, y north."""

    def __init__(self, p: GridParams, mpp: float, seed: int):
        self.p, self.mpp = p, mpp
        self.rng = np.random.default_rng(seed)
        self.vrng = np.random.default_rng([seed, 4242])   # variety's own draws: the layout's stay as they were
        self.roof_rng = np.random.default_rng([seed, 4245])   # houses' roof forms (variety), a generator of their own
        self.seed = seed
        self.n = int(round(p.pitch_m / mpp))
        self.labels = np.full((self.n, self.n), C["sidewalk"], np.uint8)
        self.buildings: list[Building] = []
        self.trees: list[Tree] = []
        self.cars: list[Car] = []
        self.furniture: list[Furniture] = []

    # geometry helpers -----------------------------------------------------------------------------
    def poly(self, pts_m, cls: int) -> None:
        fill_poly(self.labels, to_px(np.asarray(pts_m), self.p.pitch_m, self.mpp), int(cls))

    def rect(self, x0, y0, x1, y1, cls: int) -> None:
        self.poly([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], cls)

    def paint(self) -> np.ndarray:
        p, P = self.p, self.p.pitch_m
        hr = p.road_width_m / 2
        inner0, inner1 = hr + p.sidewalk_m, P - hr - p.sidewalk_m
        # half roads on the four sides (the cell border is a road centre line)
        for x0, y0, x1, y1 in ((0, 0, P, hr), (0, P - hr, P, P), (0, 0, hr, P), (P - hr, 0, P, P)):
            self.rect(x0, y0, x1, y1, C["road"])
        if p.style == "city":
            self._city_block(inner0, inner1)
        else:
            self._residential_block(inner0, inner1)
        self._street_trees(hr, inner0, inner1)
        self._curb_cars(hr)
        if p.variety > 0:
            self._more_street_objects(hr, inner0, inner1)
        self._markings(hr)
        rgb = np.zeros((self.n, self.n, 3), np.uint8)
        _paint_base(self.labels, rgb, self.rng, self.mpp)
        road_wear(self.labels, rgb, self.vrng, self.mpp, p.variety, C["road"], C["sidewalk"])
        marking_wear(self.labels, rgb, np.random.default_rng([self.seed, 4244]), self.mpp, p.variety,
                     C["lane_marking"], C["road"])
        ground_detail(self.labels, rgb, np.random.default_rng([self.seed, 4243]), self.mpp, p.variety, C)
        self._parking_stripes(rgb)
        return rgb

    # block contents -------------------------------------------------------------------------------
    def _lots(self, a: float, b: float, lo: float, hi: float) -> list[float]:
        cuts, x = [a], a
        while b - x > hi:
            x += self.rng.uniform(lo, hi)
            cuts.append(x)
        cuts[-1] = b
        return cuts

    def _city_block(self, i0: float, i1: float) -> None:
        r = self.rng
        xs, ys = self._lots(i0, i1, 18, 32), self._lots(i0, i1, 18, 32)
        self._parking_lots: list[tuple[float, float, float, float]] = []
        self._parks: list[tuple[float, float, float, float]] = []
        for xa, xb in zip(xs[:-1], xs[1:]):
            for ya, yb in zip(ys[:-1], ys[1:]):
                kind = r.choice(["building", "parking", "park"], p=[0.72, 0.16, 0.12])
                if kind == "building":
                    inset = r.uniform(0.0, 1.5)
                    fp = np.array([[xa + inset, ya + inset], [xb - inset, ya + inset], [xb - inset, yb - inset],
                                   [xa + inset, yb - inset]])
                    self.buildings.append(self._styled(Building(fp, float(r.uniform(8, 30)), int(r.integers(0, 8)),
                                                                _roof_rgb(r, 95, 175))))
                    self.rect(xa + inset, ya + inset, xb - inset, yb - inset, C["building"])
                elif kind == "parking":
                    self.rect(xa + 1, ya + 1, xb - 1, yb - 1, C["parking"])
                    self._parking_lots.append((xa + 1, ya + 1, xb - 1, yb - 1))
                    self._fill_parking(xa + 1, ya + 1, xb - 1, yb - 1)
                else:
                    self.rect(xa + 0.5, ya + 0.5, xb - 0.5, yb - 0.5, C["grass"])
                    self._parks.append((xa + 0.5, ya + 0.5, xb - 0.5, yb - 0.5))
                    for _ in range(int(r.integers(2, 6))):
                        self._tree(r.uniform(xa + 3, xb - 3), r.uniform(ya + 3, yb - 3))

    def _residential_block(self, i0: float, i1: float) -> None:
        r = self.rng
        self._parking_lots = []
        self._fronts: list[tuple[float, float, int, float, float]] = []   # each lot: xa, xb, side, driveway, front
        self.rect(i0, i0, i1, i1, C["grass"])
        depth = min(24.0, (i1 - i0) / 2)
        # lots along the south and north edges, facing the street
        for side in (0, 1):
            xs = self._lots(i0, i1, 14, 20)
            for xa, xb in zip(xs[:-1], xs[1:]):
                w = xb - xa
                hw, hd = min(w - 4, r.uniform(8, 12)), r.uniform(8, 11)
                cx = r.uniform(xa + 2 + hw / 2, xb - 2 - hw / 2) if w - 4 > hw else (xa + xb) / 2
                setback = r.uniform(5, 8)
                y_front = i0 + setback if side == 0 else i1 - setback
                y0, y1 = (y_front, y_front + hd) if side == 0 else (y_front - hd, y_front)
                fp = np.array([[cx - hw / 2, y0], [cx + hw / 2, y0], [cx + hw / 2, y1], [cx - hw / 2, y1]])
                self.buildings.append(self._roofed(self._styled(Building(fp, float(r.uniform(5.5, 9)),
                                                                         int(r.integers(0, 8)),
                                                                         _roof_rgb(r, 70, 150)))))
                self.rect(fp[0, 0], y0, fp[1, 0], y1, C["building"])
                # driveway from the sidewalk to the house, beside it
                dx = cx + hw / 2 + 0.5 if cx + hw / 2 + 3.5 < xb else cx - hw / 2 - 3.5
                ys = (i0, y0 + 2) if side == 0 else (y1 - 2, i1)
                self.rect(dx, ys[0], dx + 3.0, ys[1], C["soil"] if r.random() < 0.4 else C["sidewalk"])
                self._fronts.append((xa, xb, side, dx, y_front))
                if r.random() < 0.5:
                    self.cars.append(self._car(dx + 1.5, ys[0] + 3.5 if side == 0 else ys[1] - 3.5, math.pi / 2))
                for _ in range(int(r.integers(0, 3))):  # yard trees behind the houses
                    ty = r.uniform(y1 + 2, i0 + depth - 1) if side == 0 else r.uniform(i1 - depth + 1, y0 - 2)
                    self._tree(r.uniform(xa + 2, xb - 2), ty)
        # garden soil patches in the block centre
        if i1 - i0 > 2 * depth + 2:
            self.rect(i0 + 3, i0 + depth + 1, i1 - 3, i1 - depth - 1, C["soil"] if r.random() < 0.5 else C["grass"])

    def _fill_parking(self, x0, y0, x1, y1) -> None:
        r = self.rng
        stall = 2.6
        rows = [y0 + 2.8, y1 - 2.8]
        for ry in rows:
            x = x0 + stall / 2
            while x < x1 - stall / 2:
                if r.random() < 0.6:
                    self.cars.append(self._car(x, ry, math.pi / 2 + (math.pi if ry > (y0 + y1) / 2 else 0)))
                x += stall

    def _parking_stripes(self, rgb: np.ndarray) -> None:
        for x0, y0, x1, y1 in getattr(self, "_parking_lots", []):
            x = x0
            while x <= x1 + 1e-6:
                for ya, yb in ((y0, y0 + 5.2), (y1 - 5.2, y1)):
                    q = to_px(np.array([[x - MARK_W / 2, ya], [x + MARK_W / 2, ya], [x + MARK_W / 2, yb],
                                        [x - MARK_W / 2, yb]]), self.p.pitch_m, self.mpp)
                    fill_poly(rgb, q, (225, 225, 220))
                    fill_poly(self.labels, q, C["lane_marking"])
                x += 2.6

    def _styled(self, b: Building) -> Building:
        """``b`` with a facade of its own (a style seed) for a share ``variety`` of the buildings."""
        v = self.vrng
        if self.p.variety > 0 and v.random() < self.p.variety:
            b.style_seed = int(v.integers(0, 2**31 - 1))
        return b

    def _roofed(self, b: Building) -> Building:
        """``variety``: a house with a roof of its own form: gabled (a ridge along its long side) for 80 % of a
        share ``variety`` of them (a generator of its own: every other draw stays as it was)."""
        if self.p.variety > 0 and self.roof_rng.random() < 0.8 * self.p.variety:
            b.roof = "gabled"
        return b

    def _car(self, x, y, yaw, own: bool = False) -> Car:
        """A parked car: one of ``variety`` 0's (the layout's draws, always made), or for a share ``variety`` of
        them (``own``: always) a body type and colour of its own (variety's draws)."""
        r = self.rng
        palette = [(200, 200, 205), (30, 30, 35), (150, 25, 30), (40, 60, 120), (120, 120, 125), (230, 230, 230),
                   (60, 90, 60), (170, 140, 90)]
        car = Car((float(x), float(y)), float(yaw), float(r.uniform(3.9, 4.8)), float(r.uniform(1.7, 1.9)),
                  float(r.uniform(1.4, 1.6)), palette[int(r.integers(len(palette)))])
        v = self.vrng
        if own or (self.p.variety > 0 and v.random() < self.p.variety):
            body = car_body(v)
            spec = BODIES[body]
            car = Car(car.center, car.yaw, float(v.uniform(*spec["length"])), float(v.uniform(*spec["width"])),
                      float(v.uniform(*spec["height"])), car_colour(v), body)
        return car

    def _tree(self, x, y, own: bool = False) -> None:
        """A tree: one of ``variety`` 0's (the layout's draws, always made), or for a share ``variety`` of them
        (``own``: always) a species of its own with its size (variety's draws)."""
        r = self.rng
        rad = float(r.uniform(1.8, 3.8))
        bottom = float(r.uniform(2.0, 3.5))
        tree = Tree((float(x), float(y)), rad, bottom, bottom + float(r.uniform(2.5, 6.0)), int(r.integers(0, 4)))
        v = self.vrng
        if own or (self.p.variety > 0 and v.random() < self.p.variety):
            tree = _own_tree(v, *tree.center)
        self.trees.append(tree)

    def _more_street_objects(self, hr, i0, i1) -> None:
        """``variety``: kerbs lined with more parked cars and sidewalks with more trees, as streets have them
        (variety's draws; none within a car's length of a parked car or a tree's crown of a tree)."""
        v, P = self.vrng, self.p.pitch_m
        city = self.p.style == "city"
        off_car = hr - 1.2
        taken = np.array([c.center for c in self.cars] or np.zeros((0, 2)), np.float64).reshape(-1, 2)
        p_car = self.p.variety * (0.55 if city else 0.4)
        for side in range(4):
            t = hr + 6 + v.uniform(0, 3)
            while t < P - hr - 6:
                x, y, yaw = ((t, off_car, 0.0), (t, P - off_car, math.pi), (off_car, t, -math.pi / 2),
                             (P - off_car, t, math.pi / 2))[side]
                if v.random() < p_car and (len(taken) == 0 or np.hypot(*(taken - (x, y)).T).min() > 5.2):
                    c = self._car(x, y, yaw + (math.pi if v.random() < 0.15 else 0.0), own=True)
                    self.cars.append(c)
                    taken = np.vstack([taken, c.center])
                t += v.uniform(5.3, 6.2)
        off_tree = hr + self.p.sidewalk_m * 0.55
        trees = np.array([tr.center for tr in self.trees] or np.zeros((0, 2)), np.float64).reshape(-1, 2)
        p_tree = self.p.variety * (0.3 if city else 0.45)
        t = i0 + 3
        while t < i1 - 3:
            for x, y in ((t, off_tree), (t, P - off_tree), (off_tree, t), (P - off_tree, t)):
                if v.random() < p_tree and (len(trees) == 0 or np.hypot(*(trees - (x, y)).T).min() > 5.0):
                    self._tree(x, y, own=True)
                    trees = np.vstack([trees, (x, y)])
            t += v.uniform(6, 9)
        self._street_furniture(hr)
        self._yards(i0, i1)
        self._furnish_parks()

    def _furnish_parks(self) -> None:
        """``variety``: a city block's pocket parks as parks are: a paved path across, benches beside it, more
        trees of their own species, shrubs, and a hedge along some edges (a gap for the path) (variety's draws)."""
        v, amount = self.vrng, self.p.variety
        for x0, y0, x1, y1 in getattr(self, "_parks", []):
            along_x = v.random() < 0.5                       # the path: 2 m wide, across the long way or not
            c = float(v.uniform(y0 + 4, y1 - 4) if along_x else v.uniform(x0 + 4, x1 - 4))
            if along_x:
                self.rect(x0, c - 1.0, x1, c + 1.0, C["sidewalk"])
            else:
                self.rect(c - 1.0, y0, c + 1.0, y1, C["sidewalk"])
            taken = [t.center for t in self.trees]

            def free(x: float, y: float, gap: float) -> bool:
                return abs((y if along_x else x) - c) > 1.6 and all(math.dist((x, y), q) > gap for q in taken)

            for _ in range(int(v.poisson(amount * 3))):
                x, y = float(v.uniform(x0 + 2.5, x1 - 2.5)), float(v.uniform(y0 + 2.5, y1 - 2.5))
                if free(x, y, 4.0):
                    self._tree(x, y, own=True)
                    taken.append((x, y))
            for _ in range(int(v.poisson(amount * 2))):      # benches facing the path
                t = float(v.uniform(x0 + 2, x1 - 2) if along_x else v.uniform(y0 + 2, y1 - 2))
                side = 1.0 if v.random() < 0.5 else -1.0
                x, y = (t, c + side * 1.6) if along_x else (c + side * 1.6, t)
                yaw = (-math.pi / 2 if side > 0 else math.pi / 2) if along_x else (math.pi if side > 0 else 0.0)
                if all(math.dist((x, y), q) > 1.5 for q in taken):
                    self.furniture.append(Furniture((x, y), yaw, 4, int(v.integers(0, 2**31 - 1))))
                    taken.append((x, y))
            for _ in range(int(v.poisson(amount * 4))):
                x, y = float(v.uniform(x0 + 1, x1 - 1)), float(v.uniform(y0 + 1, y1 - 1))
                if free(x, y, 1.5):
                    self.furniture.append(Furniture((x, y), 0.0, 10, int(v.integers(0, 2**31 - 1))))
                    taken.append((x, y))
            seed = int(v.integers(0, 2**31 - 1))
            for edge in range(4):                            # hedges along some edges, inside the park
                if v.random() >= amount * 0.4:
                    continue
                horizontal = edge < 2
                lo, hi = (x0, x1) if horizontal else (y0, y1)
                fixed = (y0 + 0.6, y1 - 0.6, x0 + 0.6, x1 - 0.6)[edge]
                crosses = horizontal != along_x              # the path crosses this edge at t = c
                self._hedge(lo, hi, fixed, horizontal, seed, lambda t, x, y: not (
                    crosses and abs(t - c) < 1.0 + HEDGE_SEGMENT_M / 2 + 0.5)
                    and all(math.dist((x, y), q) > 1.2 for q in taken))

    def _hedge(self, lo: float, hi: float, at: float, horizontal: bool, seed: int, keep, kind: int = 9) -> None:
        """A hedge (or a fence, ``kind`` 12, or a garden wall, 13) of :data:`HEDGE_SEGMENT_M` segments (one
        ``seed``: one look) from ``lo`` to ``hi`` (0.5 m in from each end) along x at y = ``at`` (``horizontal``)
        or along y at x = ``at``, each segment where ``keep(t, x, y)`` (its centre's coordinate along the hedge,
        and its centre) allows."""
        half = HEDGE_SEGMENT_M / 2
        t = lo + 0.5 + half
        while t + half <= hi - 0.5:
            x, y = (t, at) if horizontal else (at, t)
            if keep(t, x, y):
                self.furniture.append(Furniture((float(x), float(y)), 0.0 if horizontal else math.pi / 2, kind, seed))
            t += HEDGE_SEGMENT_M

    def _yards(self, i0: float, i1: float) -> None:
        """``variety``: a residential block's front yards: a hedge along the sidewalk (its segments of one seed,
        a gap at the driveway) for some, a fence or a low garden wall for some of the others, shrubs between it
        and the house for most (variety's draws; the fences' from the yard's own seed)."""
        v, amount = self.vrng, self.p.variety
        half = HEDGE_SEGMENT_M / 2
        for xa, xb, side, dx, y_front in getattr(self, "_fronts", []):
            seed = int(v.integers(0, 2**31 - 1))
            gap = lambda t, x, y, dx=dx: t + half < dx - 0.5 or t - half > dx + 3.5  # noqa: E731  (the driveway)
            at = i0 + 0.6 if side == 0 else i1 - 0.6
            if v.random() < amount * 0.55:
                self._hedge(xa, xb, at, True, seed, gap)
            else:
                f = np.random.default_rng([seed, 12])
                if f.random() < amount * 0.6:
                    self._hedge(xa, xb, at, True, seed, gap, kind=12 if f.random() < 0.6 else 13)
            lo, hi = (i0 + 2.0, y_front - 1.2) if side == 0 else (y_front + 1.2, i1 - 2.0)
            for _ in range(int(v.poisson(amount * 1.6))):
                x = float(v.uniform(xa + 1.0, xb - 1.0))
                if hi > lo and not dx - 1.0 < x < dx + 4.0:
                    self.furniture.append(Furniture((x, float(v.uniform(lo, hi))), 0.0, 10,
                                                    int(v.integers(0, 2**31 - 1))))

    def _street_furniture(self, hr: float) -> None:
        """``variety``: the sidewalks' furniture (:mod:`satloc_env.world.furniture`): lamp posts of one style per
        side at the kerb, traffic lights at corners, signs, bins, hydrants, benches and bollards, a bus shelter;
        none on a tree's trunk or another piece (variety's draws)."""
        v, P, sw, amount = self.vrng, self.p.pitch_m, self.p.sidewalk_m, self.p.variety
        city = self.p.style == "city"
        taken = [(t.center[0], t.center[1], 0.5) for t in self.trees]

        def place(side: int, t: float, d: float, kind: int, seed: int, facing: str = "road") -> None:
            x, y = ((t, hr + d), (t, P - hr - d), (hr + d, t), (P - hr - d, t))[side]
            r = footprint_radius(kind)
            if any(math.hypot(x - a, y - b) < r + q for a, b, q in taken):
                return
            road = (-math.pi / 2, math.pi / 2, math.pi, 0.0)[side]
            yaw = road if facing == "road" else road + (math.pi / 2 if v.random() < 0.5 else -math.pi / 2)
            self.furniture.append(Furniture((float(x), float(y)), float(yaw), kind, seed))
            taken.append((x, y, r))

        seed = lambda: int(v.integers(0, 2**31 - 1))   # noqa: E731
        lo, hi = hr + 3.0, P - hr - 3.0
        for corner in range(4):                       # traffic lights at the corners
            if v.random() < amount * (0.5 if city else 0.15):
                side = (0, 0, 1, 1)[corner] if v.random() < 0.5 else (2, 3, 2, 3)[corner]
                t = hr + 0.6 if corner in (0, 2) and side < 2 or corner in (0, 1) and side >= 2 else P - hr - 0.6
                place(side, t, 0.6, 7, seed(), "along")
        for side in range(4):
            if v.random() < amount * (0.3 if city else 0.15):     # a bus shelter
                place(side, v.uniform(lo + 4, hi - 4), sw / 2 + 0.15, 8, seed())
            style = seed()                            # the side's lamp posts are all alike
            t = lo + v.uniform(2, 8)
            while t < hi:
                if v.random() < amount * 0.9:
                    place(side, t, 0.45, 1, style)
                t += v.uniform(22, 30)
            for kind, n, d, facing in ((2, 2.5, 0.35, "along"), (3, 1.5, 0.5, "road"), (6, 0.6, 0.4, "road"),
                                       (4, 0.7 if city else 0.3, sw - 0.5, "road"), (5, 0.4 if city else 0.1, 0.35,
                                                                                      "road"),
                                       (11, 1.2 if city else 0.2, sw - 0.6, "road")):
                for _ in range(int(v.poisson(amount * n))):
                    place(side, v.uniform(lo, hi), d, kind, seed(), facing)

    def _street_trees(self, hr, i0, i1) -> None:
        r = self.rng
        p_tree = 0.35 if self.p.style == "city" else 0.6
        off = hr + self.p.sidewalk_m * 0.55
        P = self.p.pitch_m
        t = i0 + 4
        while t < i1 - 4:
            for x, y in ((t, off), (t, P - off), (off, t), (P - off, t)):
                if r.random() < p_tree / 2:
                    self._tree(x, y)
            t += r.uniform(7, 12)

    def _curb_cars(self, hr) -> None:
        r = self.rng
        P = self.p.pitch_m
        off = hr - 1.2  # parking strip beside the curb
        p_car = 0.35 if self.p.style == "city" else 0.25
        t = hr + 6
        while t < P - hr - 6:
            if r.random() < p_car:
                side = int(r.integers(4))
                x, y, yaw = ((t, off, 0.0), (t, P - off, math.pi), (off, t, -math.pi / 2), (P - off, t, math.pi / 2))[side]
                self.cars.append(self._car(x, y, yaw))
            t += r.uniform(5.5, 7.5)

    def _markings(self, hr) -> None:
        """Dashed centre lines on the cell border, solid lane edges, zebra crossings at the corners."""
        P, w = self.p.pitch_m, MARK_W
        m = C["lane_marking"]
        a, b = hr + 4.5, P - hr - 4.5
        dash, period = 3.0, 6.0
        edge = LANE_W
        s = math.ceil(a / period) * period
        while s + dash <= b:  # cells sharing a border share its axis origin, so dashes line up
            for x0, y0, x1, y1 in ((s, 0, s + dash, w / 2), (s, P - w / 2, s + dash, P), (0, s, w / 2, s + dash),
                                   (P - w / 2, s, P, s + dash)):
                self.rect(x0, y0, x1, y1, m)
            s += period
        for x0, y0, x1, y1 in ((a, edge - w / 2, b, edge + w / 2), (a, P - edge - w / 2, b, P - edge + w / 2),
                               (edge - w / 2, a, edge + w / 2, b), (P - edge - w / 2, a, P - edge + w / 2, b)):
            self.rect(x0, y0, x1, y1, m)
        # zebra crossings just outside each intersection, stripes across the half road
        for cx, cy in ((0, 0), (P, 0), (0, P), (P, P)):
            sx = 1 if cx == 0 else -1
            sy = 1 if cy == 0 else -1
            for k in range(int(hr / 1.0)):
                u = k * 1.0 + 0.25
                # crossing the east-west road (stripes along x) and the north-south road
                self.rect(*_ordered(cx + sx * (hr + 0.8), cy + sy * u, cx + sx * (hr + 3.8), cy + sy * (u + 0.5)), m)
                self.rect(*_ordered(cx + sx * u, cy + sy * (hr + 0.8), cx + sx * (u + 0.5), cy + sy * (hr + 3.8)), m)


def _own_tree(v: np.random.Generator, x: float, y: float) -> Tree:
    """A tree of a species of its own (:data:`SPECIES`, as often as streets have them) and its size."""
    sp = int(v.choice(list(SPECIES), p=[0.45, 0.15, 0.15, 0.25]))
    s = SPECIES[sp]
    bottom = float(v.uniform(*s["bottom"]))
    return Tree((float(x), float(y)), float(v.uniform(*s["radius"])), bottom, bottom + float(v.uniform(*s["crown"])),
                int(v.integers(0, len(s["leaf"]))), sp)


def _roof_rgb(r: np.random.Generator, lo: int, hi: int) -> tuple[int, int, int]:
    """A greyish roof colour with a slight warm or cool tint."""
    g = r.uniform(lo, hi)
    tint_ = r.normal(0, 10, 3) + (np.array([14, 4, -10]) if r.random() < 0.5 else np.array([-6, 0, 8]))
    return tuple(int(v) for v in np.clip(g + tint_, 0, 255))


def _ordered(x0, y0, x1, y1):
    return min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1)


def _shift(obj, dx: float, dy: float):
    if isinstance(obj, Building):
        return dataclasses.replace(obj, footprint=obj.footprint + np.array([dx, dy]))
    return dataclasses.replace(obj, center=(obj.center[0] + dx, obj.center[1] + dy))


def generate_grid(p: GridParams, seed: int, aliasing: float, mpp: float) -> tuple[Layout, np.ndarray]:
    """Paint and populate a grid scene. Returns the layout and the per-cell alias source indices."""
    for name, v in (("pitch_m", p.pitch_m), ("margin_m", p.margin_m)):
        if abs(v / mpp - round(v / mpp)) > 1e-6:
            raise ValueError(f"generator.{name}={v} must be a multiple of ground_mpp={mpp}")
    W, H = p.size_m()
    nx, ny = p.blocks
    rng = np.random.default_rng(seed)
    cell_seeds = rng.integers(0, 2**31 - 1, size=nx * ny)
    src = alias_sources(nx * ny, aliasing, np.random.default_rng([seed, 1]))
    Wp, Hp, n, mp = int(round(W / mpp)), int(round(H / mpp)), int(round(p.pitch_m / mpp)), int(round(p.margin_m / mpp))
    labels = np.full((Hp, Wp), C["grass"], np.uint8)
    # margins: open land, with the roads running on to the edge of the map
    land = noise((Hp, Wp), np.random.default_rng([seed, 2]), (max(2, 25 / mpp),))
    labels[land > 0.35] = C["soil"]
    hr = p.road_width_m / 2
    xs, ys = p.road_lines()
    for x in xs:
        labels[:, int(round((x - hr) / mpp)):int(round((x + hr) / mpp))] = C["road"]
    for y in ys:
        labels[int(round((H - y - hr) / mpp)):int(round((H - y + hr) / mpp)), :] = C["road"]
    rgb = np.zeros((Hp, Wp, 3), np.uint8)
    _paint_base(labels, rgb, np.random.default_rng([seed, 3]), mpp)
    ground_detail(labels, rgb, np.random.default_rng([seed, 6]), mpp, p.variety, C)   # the margins' (the cells
    cache: dict[int, CellPainter] = {}                                                 # paint their own)
    first: dict[int, tuple[int, ...]] = {}     # where a source cell's objects first went in the four lists
    objects: tuple[list, ...] = ([], [], [], [])    # buildings, trees, cars, furniture
    for j in range(ny):
        for i in range(nx):
            k = src[j * nx + i]
            if k not in cache:
                cp = CellPainter(p, mpp, int(cell_seeds[k]))
                cp.rgb = cp.paint()
                cache[k] = cp
            cp = cache[k]
            r0 = Hp - mp - (j + 1) * n
            c0 = mp + i * n
            labels[r0:r0 + n, c0:c0 + n] = cp.labels
            rgb[r0:r0 + n, c0:c0 + n] = cp.rgb
            dx, dy = p.margin_m + i * p.pitch_m, p.margin_m + j * p.pitch_m
            starts = first.setdefault(k, tuple(len(o) for o in objects))
            for out, own, s0 in zip(objects, (cp.buildings, cp.trees, cp.cars, cp.furniture), starts):
                copy = s0 != len(out)      # a copy of a cell placed before: its objects take those looks
                out += [dataclasses.replace(_shift(o, dx, dy), look=s0 + m if copy else None)
                        for m, o in enumerate(own)]
    _alias_margins(labels, rgb, p, seed, aliasing, mp, n, mpp, objects)
    buildings, trees, cars, furniture = objects
    return Layout(W, H, mpp, rgb, labels, buildings, trees, cars, furniture=furniture), src


def _alias_margins(labels: np.ndarray, rgb: np.ndarray, p: GridParams, seed: int, aliasing: float, mp: int,
                   n: int, mpp: float, objects: tuple[list, ...]) -> None:
    """Alias the open land around the grid as the cells are: each side's margin is cut into one stretch per
    cell along it, and ``round(aliasing * n)`` stretches of a side are copies of others (labels and texture),
    so that at ``aliasing`` 1 an edge road runs past the same land at every block, as it runs past the same
    block (the corners stay their own). With ``variety``, each stretch's land gets trees and shrubs of its
    own (a copy: its source's, with their looks), appended to ``objects`` (buildings, trees, cars, furniture)."""
    nx, ny = p.blocks
    H, W = labels.shape
    P, M, hr = p.pitch_m, p.margin_m, p.road_width_m / 2
    Hm, Wm = H * mpp, W * mpp
    rng = np.random.default_rng([seed, 5])
    sides = (  # (stretches, the rows and columns of stretch i, its land's x0, y0, x1, y1 in metres, roads out)
        (nx, lambda i: (slice(H - mp, H), slice(mp + i * n, mp + (i + 1) * n)),
         lambda i: (M + i * P + hr, 0.0, M + (i + 1) * P - hr, M - hr)),                           # south
        (nx, lambda i: (slice(0, mp), slice(mp + i * n, mp + (i + 1) * n)),
         lambda i: (M + i * P + hr, Hm - M + hr, M + (i + 1) * P - hr, Hm)),                        # north
        (ny, lambda j: (slice(H - mp - (j + 1) * n, H - mp - j * n), slice(0, mp)),
         lambda j: (0.0, M + j * P + hr, M - hr, M + (j + 1) * P - hr)),                           # west
        (ny, lambda j: (slice(H - mp - (j + 1) * n, H - mp - j * n), slice(W - mp, W)),
         lambda j: (Wm - M + hr, M + j * P + hr, Wm, M + (j + 1) * P - hr)),                        # east
    )
    trees, furniture = objects[1], objects[3]
    for k, (count, where, land) in enumerate(sides):
        src = alias_sources(count, aliasing, rng)
        for i in np.flatnonzero(src != np.arange(count)):
            labels[where(i)] = labels[where(src[i])]
            rgb[where(i)] = rgb[where(src[i])]
        if p.variety <= 0:
            continue
        first: dict[int, tuple[int, int]] = {}
        for i in range(count):
            s = int(src[i])
            t0, f0 = first.setdefault(s, (len(trees), len(furniture)))
            copy = t0 != len(trees) or f0 != len(furniture)
            v = np.random.default_rng([seed, 7, k, s])      # the stretch's own draws: a copy makes the same
            x0, y0, x1, y1 = land(i)     # the same draws in stretch i's frame: a copy's objects, shifted
            placed: list[tuple[float, float]] = []
            if min(x1 - x0, y1 - y0) >= 6.0:                      # a tree every 16 m of margin or so
                for _ in range(int(v.poisson(p.variety * P / 16))):
                    tr = _own_tree(v, float(v.uniform(x0 + 3, x1 - 3)), float(v.uniform(y0 + 3, y1 - 3)))
                    trees.append(dataclasses.replace(tr, look=t0 + len(placed) if copy else None))
                    placed.append(tr.center)
            if min(x1 - x0, y1 - y0) >= 2.0:
                m = 0
                for _ in range(int(v.poisson(p.variety * P / 10))):
                    xy = (float(v.uniform(x0 + 1, x1 - 1)), float(v.uniform(y0 + 1, y1 - 1)))
                    seed_f = int(v.integers(0, 2**31 - 1))
                    if all(math.dist(xy, q) > 1.2 for q in placed):
                        furniture.append(Furniture(xy, 0.0, 10, seed_f, f0 + m if copy else None))
                        m += 1
