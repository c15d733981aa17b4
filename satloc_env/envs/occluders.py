"""Episode occluders and appearance changes: what the ground camera sees that the tile does not show."""
from __future__ import annotations

import math

import cv2
import numpy as np

from satloc.labels import CLASS_ID as C
from satloc_env.world.layout import Car, Obstacle, Person
from satloc_env.world.route import Route

#: occluders per 100 m of route at occlusion = 1
DENSITY_PER_100M = 12.0
LANES = (-1.75, 1.75)


def sample_occluders(route: Route, ground_label, occlusion: float, ego_offset: float,
                     rng: np.random.Generator) -> tuple[list[Car], list[Person], list[Obstacle]]:
    """Draw cars (other lane or parking strip), people (sidewalks, verges) and box obstacles along ``route``.

    ``ground_label(xy)`` returns the class of the ground at map points. The ego vehicle's own lane
    (``ego_offset``) is kept clear so the car never drives through an occluder.
    """
    cars: list[Car] = []
    persons: list[Person] = []
    obstacles: list[Obstacle] = []
    n = rng.poisson(occlusion * DENSITY_PER_100M * route.length / 100.0) if occlusion > 0 else 0
    if n == 0:
        return cars, persons, obstacles
    s = rng.uniform(0, route.length, n)
    kind = rng.choice(3, n, p=[0.45, 0.4, 0.15])
    other_lanes = [o for o in LANES if abs(o - ego_offset) > 1.5] or [LANES[1]]
    palette = rng.integers(20, 235, (n, 3))
    for i in range(n):
        if kind[i] == 0:
            off = float(rng.choice(other_lanes + [-4.75, 4.75]))
        elif kind[i] == 1:
            off = float(rng.choice([-1, 1]) * rng.uniform(6.3, 8.5))
        else:
            off = float(rng.choice([-1, 1]) * rng.uniform(5.0, 7.5))
        x, y, yaw = route.sample(np.array([s[i]]), off)[0]
        lab = int(ground_label(np.array([x, y])))
        rgb = tuple(int(v) for v in palette[i])
        if kind[i] == 0 and lab in (C["road"], C["lane_marking"], C["parking"]):
            cars.append(Car((x, y), yaw + (math.pi if off > 0 and abs(off) < 3 else 0.0),
                            float(rng.uniform(3.9, 4.9)), float(rng.uniform(1.7, 1.95)), float(rng.uniform(1.4, 1.9)), rgb))
        elif kind[i] == 1 and lab not in (C["building"],):
            persons.append(Person((x, y), 0.28, float(rng.uniform(1.55, 1.9)), rgb))
        elif kind[i] == 2 and lab not in (C["building"],):
            obstacles.append(Obstacle((x, y), yaw + float(rng.uniform(-0.3, 0.3)), float(rng.uniform(1.0, 3.0)),
                                      float(rng.uniform(0.4, 1.2)), float(rng.uniform(0.8, 2.2)), rgb))
    return cars, persons, obstacles


class Appearance:
    """A per-episode photometric change (exposure, white balance, gamma, contrast) as a colour lookup table.

    ``strength`` 0 is the identity; 1 is a strong change such as dusk or a hazy noon.
    """

    def __init__(self, strength: float, rng: np.random.Generator):
        self.strength = strength
        if strength <= 0:
            self.lut = None
            return
        a = strength
        gain = math.exp(rng.normal(0, 0.35) * a)
        wb = 1.0 + rng.normal(0, 0.08, 3) * a
        gamma = math.exp(rng.normal(0, 0.25) * a)
        contrast = 1.0 + rng.normal(0, 0.15) * a
        x = np.arange(256, dtype=np.float64) / 255.0
        lut = np.empty((256, 3))
        for c in range(3):
            y = np.clip(x * gain * wb[c], 0, 1) ** gamma
            y = (y - 0.5) * contrast + 0.5
            lut[:, c] = y
        self.lut = np.clip(lut * 255 + 0.5, 0, 255).astype(np.uint8).reshape(256, 1, 3)

    def __call__(self, img: np.ndarray) -> np.ndarray:
        if self.lut is None:
            return img
        return cv2.LUT(img, self.lut)
