"""The generated world of a scene, as vector objects plus rasters; both the satellite tile and the 3-D
world the ground camera sees are made from this one description.

Map frame: x east, y north, metres; the scene covers ``[0, width_m] x [0, height_m]``. Rasters are stored
north-up: row 0 is the northern edge (y = height_m), column 0 the western edge (x = 0). A raster of
resolution ``mpp`` metres per pixel has pixel (u, v) centred at ``((u + 0.5) * mpp, height_m - (v + 0.5) * mpp)``.

An object's ``look``: the 3-D world (:mod:`satloc_env.world.meshes`) draws an object's textures and small shape
jitter from its index in the layout's list, so two objects with equal parameters still differ in their details;
``look`` names the index to draw them from instead (None: its own). A generated grid's aliased cells
(:func:`satloc_env.world.generator.alias_sources`) set it on every object they copy, so that a copied block is
a copy down to its window panes and leaves.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Building:
    footprint: np.ndarray      # (N, 2) polygon, metres, counter-clockwise
    height: float              # metres
    facade: int = 0            # facade style index (texture variant)
    roof_rgb: tuple[int, int, int] = (120, 110, 100)
    roof_from_ground: bool = False   # the roof shows the layout's ground image under it (real imagery)
    base: float = 0.0          # metres above the ground the walls start at (OSM min_height)
    roof: str = "flat"         # "flat", or "gabled" (a ridge along a rectangular footprint's long axis)
    style_seed: int | None = None   # a facade of its own drawn from this seed (satloc_env.world.variety); None: the
                                    # ``facade`` style
    look: int | None = None    # the index whose textures it copies (see above)


@dataclass
class Tree:
    center: tuple[float, float]
    canopy_radius: float       # metres
    canopy_bottom: float       # trunk height, metres
    canopy_top: float          # metres
    shade: int = 0             # foliage colour variant
    species: int = 0           # satloc_env.world.variety.SPECIES (0: the one tree of variety 0)
    look: int | None = None    # the index whose textures it copies (see above)


@dataclass
class Car:
    center: tuple[float, float]
    yaw: float                 # radians, counter-clockwise from east
    length: float = 4.3
    width: float = 1.8
    height: float = 1.5
    rgb: tuple[int, int, int] = (150, 30, 30)
    body: int = 0              # satloc_env.world.variety.BODIES (0: the one car of variety 0)
    look: int | None = None    # the index whose textures it copies (see above)


@dataclass
class Furniture:
    """A piece of street furniture (satloc_env.world.furniture.KINDS: lamp post, sign, bin, ...), its look
    drawn from ``seed``, facing ``yaw`` (radians, counter-clockwise from east)."""
    center: tuple[float, float]
    yaw: float
    kind: int
    seed: int = 0
    look: int | None = None    # the index whose textures it copies (see above)


@dataclass
class Person:
    center: tuple[float, float]
    radius: float = 0.3
    height: float = 1.75
    rgb: tuple[int, int, int] = (60, 60, 120)


@dataclass
class Obstacle:
    """A box obstacle (construction barrier, container, kiosk)."""
    center: tuple[float, float]
    yaw: float
    length: float
    width: float
    height: float
    rgb: tuple[int, int, int] = (230, 120, 20)


@dataclass
class Layout:
    width_m: float
    height_m: float
    ground_mpp: float                          # resolution of ``ground_rgb`` / ``ground_labels``
    ground_rgb: np.ndarray                     # (H, W, 3) uint8: what lies on the ground plane (no roofs/canopies)
    ground_labels: np.ndarray                  # (H, W) uint8 class ids (satloc.labels) of the ground plane
    buildings: list[Building] = field(default_factory=list)
    trees: list[Tree] = field(default_factory=list)
    cars: list[Car] = field(default_factory=list)   # parked cars: in the world and on the tile
    sun_azimuth: float = 2.4                   # radians, direction the light comes from (ccw from east)
    sun_elevation: float = 0.9                 # radians
    furniture: list[Furniture] = field(default_factory=list)   # street furniture: in the world and on the tile

    def world_to_raster(self, xy: np.ndarray, mpp: float | None = None) -> np.ndarray:
        mpp = mpp or self.ground_mpp
        xy = np.asarray(xy, dtype=np.float64)
        return np.stack([xy[..., 0] / mpp - 0.5, (self.height_m - xy[..., 1]) / mpp - 0.5], axis=-1)
