"""Scenes as data: YAML files naming a generator (or a georeferenced image), routes, objects and lighting.

A scene file (see ``scenes/*.yaml``)::

    name: city
    seed: 7
    generator: {type: grid, style: city, blocks: [4, 4], pitch_m: 80, road_width_m: 12, sidewalk_m: 3,
                margin_m: 20}
      # or {type: image, image: tile.png, labels: labels.png}  (paths relative to the YAML file)
    meters_per_pixel: 0.2          # satellite tile resolution
    ground_mpp: 0.1                # resolution of the ground texture the camera sees
    routes:
      main: {waypoints: [[x, y], ...], closed: true, laps: 1}
    database_route: main
    query_route: main
    objects: {buildings: [...], trees: [...], cars: [...]}   # extra hand-placed objects
    lighting: {sun_azimuth_deg: 135, sun_elevation_deg: 50}
    knobs: {aliasing: 0.0, occlusion: 0.0, appearance: 0.0}

Every field is checked; unknown keys, wrong types, missing images and routes leaving the tile raise
:class:`satloc.ConfigError` naming the file and the field.
"""
from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml

from satloc.config import from_dict, to_dict
from satloc.errors import ConfigError, FormatError
from satloc.labels import CLASS_ID, DRIVABLE, NUM_CLASSES
from satloc.persist import atomic_dir, load_npz, save_npz, write_json, read_json, header
from satloc.satmap import SatelliteMap, read_image

from .generator import GridParams, generate_grid
from .layout import Building, Car, Layout, Tree
from .route import Route
from .tile import paint_tile

# the repository's scenes/ (source checkout, editable install) or its installed copy (satloc_env/scenes)
SCENES_DIR = next((d for d in (Path(__file__).resolve().parent.parent / "scenes",
                               Path(__file__).resolve().parent / "scenes") if d.is_dir()),
                  Path(__file__).resolve().parent.parent / "scenes")


@dataclass
class GridGeneratorSpec:
    type: Literal["grid"] = "grid"
    style: Literal["city", "residential"] = "city"
    blocks: tuple[int, int] = (4, 4)
    pitch_m: float = 80.0
    road_width_m: float = 12.0
    sidewalk_m: float = 3.0
    margin_m: float = 20.0


@dataclass
class ImageGeneratorSpec:
    type: Literal["image"]
    image: str
    labels: str | None = None


@dataclass
class RouteSpec:
    waypoints: list[tuple[float, float]]
    closed: bool = False
    laps: int = 1


@dataclass
class BuildingSpec:
    footprint: list[tuple[float, float]]
    height: float
    facade: int = 0
    roof_rgb: tuple[int, int, int] = (120, 110, 100)


@dataclass
class TreeSpec:
    center: tuple[float, float]
    canopy_radius: float = 3.0
    canopy_bottom: float = 2.5
    canopy_top: float = 7.0


@dataclass
class CarSpec:
    center: tuple[float, float]
    yaw_deg: float = 0.0
    rgb: tuple[int, int, int] = (150, 30, 30)


@dataclass
class ObjectsSpec:
    buildings: list[BuildingSpec] = field(default_factory=list)
    trees: list[TreeSpec] = field(default_factory=list)
    cars: list[CarSpec] = field(default_factory=list)


@dataclass
class LightingSpec:
    sun_azimuth_deg: float = 135.0
    sun_elevation_deg: float = 50.0


@dataclass
class Knobs:
    """Scene difficulty knobs, each in [0, 1].

    aliasing: fraction of blocks that are exact copies of other blocks (layout and texture).
    occlusion: density of objects the ground camera sees but the tile does not (cars, people, obstacles).
    appearance: strength of the lighting / colour / exposure change of an episode (another time of day).
    """

    aliasing: float = 0.0
    occlusion: float = 0.0
    appearance: float = 0.0

    def __post_init__(self):
        for k in ("aliasing", "occlusion", "appearance"):
            v = getattr(self, k)
            if not 0.0 <= v <= 1.0:
                raise ConfigError(f"{k}: expected a value in [0, 1], got {v}")


@dataclass
class SceneSpec:
    name: str
    routes: dict[str, RouteSpec]
    generator: dict[str, Any] = field(default_factory=lambda: {"type": "grid"})
    seed: int = 0
    description: str = ""
    meters_per_pixel: float = 0.2
    ground_mpp: float = 0.1
    database_route: str = "main"
    query_route: str = "main"
    objects: ObjectsSpec = field(default_factory=ObjectsSpec)
    lighting: LightingSpec = field(default_factory=LightingSpec)
    knobs: Knobs = field(default_factory=Knobs)

    def generator_spec(self, where: str = "scene") -> GridGeneratorSpec | ImageGeneratorSpec:
        kind = self.generator.get("type")
        if kind == "grid":
            return from_dict(GridGeneratorSpec, self.generator, f"{where}: generator")
        if kind == "image":
            return from_dict(ImageGeneratorSpec, self.generator, f"{where}: generator")
        raise ConfigError(f"{where}: generator.type: expected 'grid' or 'image', got {kind!r}")


def scene_path(name_or_path: str | os.PathLike) -> Path:
    """Resolve a shipped scene name (``city``) or a path to a YAML file."""
    p = Path(name_or_path)
    cand = SCENES_DIR / f"{name_or_path}.yaml"
    # a bare shipped name wins over a same-named file or folder in the working directory (e.g. an output dir)
    if p.suffix in (".yaml", ".yml") or (p.exists() and not (len(p.parts) == 1 and cand.is_file())):
        return p
    if not cand.is_file():
        shipped = sorted(q.stem for q in SCENES_DIR.glob("*.yaml"))
        raise ConfigError(f"scene {str(name_or_path)!r}: no such file and not a shipped scene (shipped: {shipped})")
    return cand


def available_scenes() -> list[str]:
    return sorted(q.stem for q in SCENES_DIR.glob("*.yaml"))


def load_spec(name_or_path: str | os.PathLike) -> tuple[SceneSpec, Path]:
    path = scene_path(name_or_path)
    if not path.is_file():
        raise ConfigError(f"{path}: scene file not found")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: not valid YAML ({e})") from e
    spec = from_dict(SceneSpec, data, f"{path}:")
    spec.generator_spec(str(path))
    for k in ("database_route", "query_route"):
        if getattr(spec, k) not in spec.routes:
            raise ConfigError(f"{path}: {k}: route {getattr(spec, k)!r} is not in routes {sorted(spec.routes)}")
    return spec, path.resolve().parent


class Scene:
    """A generated (or image-based) scene: layout, satellite map, routes, drivable area."""

    def __init__(self, spec: SceneSpec, layout: Layout, satmap: SatelliteMap, alias_source: np.ndarray | None = None):
        self.spec = spec
        self.layout = layout
        self.satmap = satmap
        self.alias_source = alias_source if alias_source is not None else np.zeros(0, int)
        self.routes = {k: Route(r.waypoints, r.closed, r.laps, name=f"routes.{k}") for k, r in spec.routes.items()}
        self.drivable = np.isin(layout.ground_labels, DRIVABLE)
        self._check_routes()

    @property
    def name(self) -> str:
        return self.spec.name

    @functools.cached_property
    def world(self):
        """Renderable geometry of the scene (:class:`satloc_env.world.World`), built once per scene."""
        from .world import build_world

        return build_world(self.layout)

    def _check_routes(self) -> None:
        W, H = self.layout.width_m, self.layout.height_m
        for k, r in self.spec.routes.items():
            for i, (x, y) in enumerate(r.waypoints):
                if not (0 <= x <= W and 0 <= y <= H):
                    raise ConfigError(f"scene {self.name!r}: routes.{k}.waypoints[{i}] = [{x}, {y}] lies outside "
                                      f"the tile, which covers x in [0, {W}] and y in [0, {H}] metres")

    def is_drivable(self, x: float, y: float) -> bool:
        u, v = self.layout.world_to_raster(np.array([x, y]))
        iu, iv = int(round(u)), int(round(v))
        h, w = self.drivable.shape
        return 0 <= iu < w and 0 <= iv < h and bool(self.drivable[iv, iu])

    def ground_label(self, xy: np.ndarray) -> np.ndarray:
        uv = np.round(self.layout.world_to_raster(np.asarray(xy))).astype(int)
        h, w = self.layout.ground_labels.shape
        ok = (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h)
        out = np.zeros(uv.shape[:-1], np.uint8)
        out[ok] = self.layout.ground_labels[uv[..., 1][ok], uv[..., 0][ok]]
        return out

    # --- persistence ------------------------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> None:
        """Write the generated scene to a directory (spec, layout arrays, objects, tile); atomic."""
        lay = self.layout
        with atomic_dir(path) as d:
            b = lay.buildings
            arrays = {
                "ground_rgb": lay.ground_rgb, "ground_labels": lay.ground_labels,
                "alias_source": self.alias_source,
                "bld_nverts": np.array([len(x.footprint) for x in b], np.int64),
                "bld_verts": np.concatenate([x.footprint for x in b]) if b else np.zeros((0, 2)),
                "bld_params": np.array([[x.height, x.facade, *x.roof_rgb] for x in b], np.float64).reshape(-1, 5),
                "trees": np.array([[*t.center, t.canopy_radius, t.canopy_bottom, t.canopy_top, t.shade]
                                   for t in lay.trees], np.float64).reshape(-1, 6),
                "cars": np.array([[*c.center, c.yaw, c.length, c.width, c.height, *c.rgb] for c in lay.cars],
                                 np.float64).reshape(-1, 9),
            }
            save_npz(d / "layout.npz", "scene_layout", arrays, {
                "width_m": lay.width_m, "height_m": lay.height_m, "ground_mpp": lay.ground_mpp,
                "sun_azimuth": lay.sun_azimuth, "sun_elevation": lay.sun_elevation})
            meta = header("scene")
            meta["spec"] = to_dict(self.spec)
            write_json(d / "scene.json", meta)
            self.satmap.save(d / "tile")

    @staticmethod
    def load(path: str | os.PathLike) -> "Scene":
        d = Path(path)
        meta = read_json(d / "scene.json", "scene")
        spec = from_dict(SceneSpec, meta.get("spec"), f"{d / 'scene.json'}: spec")
        a, m = load_npz(d / "layout.npz", "scene_layout")
        try:
            verts = np.split(a["bld_verts"], np.cumsum(a["bld_nverts"])[:-1]) if len(a["bld_nverts"]) else []
            buildings = [Building(v, float(p[0]), int(p[1]), tuple(int(c) for c in p[2:5]))
                         for v, p in zip(verts, a["bld_params"])]
            trees = [Tree((t[0], t[1]), t[2], t[3], t[4], int(t[5])) for t in a["trees"]]
            cars = [Car((c[0], c[1]), c[2], c[3], c[4], c[5], tuple(int(v) for v in c[6:9])) for c in a["cars"]]
            lay = Layout(m["width_m"], m["height_m"], m["ground_mpp"], a["ground_rgb"], a["ground_labels"],
                         buildings, trees, cars, m["sun_azimuth"], m["sun_elevation"])
        except KeyError as e:
            raise FormatError(f"{d / 'layout.npz'}: missing entry {e}") from e
        return Scene(spec, lay, SatelliteMap.load(d / "tile"), a["alias_source"])


def _objects_from_spec(spec: ObjectsSpec) -> tuple[list[Building], list[Tree], list[Car]]:
    b = [Building(np.asarray(o.footprint, np.float64), o.height, o.facade, tuple(o.roof_rgb)) for o in spec.buildings]
    t = [Tree(tuple(o.center), o.canopy_radius, o.canopy_bottom, o.canopy_top) for o in spec.trees]
    c = [Car(tuple(o.center), math.radians(o.yaw_deg), rgb=tuple(o.rgb)) for o in spec.cars]
    return b, t, c


def _image_layout(g: ImageGeneratorSpec, spec: SceneSpec, base: Path, where: str) -> Layout:
    img_path = base / g.image
    if not img_path.is_file():
        raise ConfigError(f"{where}: generator.image: image file {img_path} not found")
    try:
        rgb = read_image(img_path)
    except FormatError as e:
        raise ConfigError(f"{where}: generator.image: {e}") from e
    if g.labels:
        lab_path = base / g.labels
        if not lab_path.is_file():
            raise ConfigError(f"{where}: generator.labels: label image {lab_path} not found")
        labels = read_image(lab_path, grayscale=True)
        if labels.shape != rgb.shape[:2]:
            raise ConfigError(f"{where}: generator.labels: size {labels.shape[::-1]} differs from the image "
                              f"{rgb.shape[1::-1]}")
        if labels.max() >= NUM_CLASSES:
            raise ConfigError(f"{where}: generator.labels: class id {labels.max()} >= {NUM_CLASSES}")
    else:
        labels = np.full(rgb.shape[:2], CLASS_ID["road"], np.uint8)
    if abs(spec.ground_mpp - spec.meters_per_pixel) > 1e-9:
        raise ConfigError(f"{where}: an image scene uses the image as the ground texture: ground_mpp must equal "
                          f"meters_per_pixel ({spec.meters_per_pixel})")
    h, w = labels.shape
    return Layout(w * spec.meters_per_pixel, h * spec.meters_per_pixel, spec.ground_mpp, rgb, labels)


def build_scene(spec: SceneSpec, base_dir: Path | None = None, aliasing: float | None = None,
                where: str | None = None) -> Scene:
    """Generate the scene described by ``spec`` (deterministic from ``spec.seed``)."""
    where = where or f"scene {spec.name!r}"
    base_dir = base_dir or SCENES_DIR
    aliasing = spec.knobs.aliasing if aliasing is None else aliasing
    Knobs(aliasing=aliasing)
    g = spec.generator_spec(where)
    src = None
    if g.type == "grid":
        params = GridParams(g.style, tuple(g.blocks), g.pitch_m, g.road_width_m, g.sidewalk_m, g.margin_m)
        try:
            lay, src = generate_grid(params, spec.seed, aliasing, spec.ground_mpp)
        except ValueError as e:
            raise ConfigError(f"{where}: {e}") from e
    else:
        lay = _image_layout(g, spec, base_dir, where)
    b, t, c = _objects_from_spec(spec.objects)
    lay.buildings += b
    lay.trees += t
    lay.cars += c
    lay.sun_azimuth = math.radians(spec.lighting.sun_azimuth_deg)
    lay.sun_elevation = math.radians(spec.lighting.sun_elevation_deg)
    if g.type == "grid":
        try:
            tile, tile_labels = paint_tile(lay, spec.meters_per_pixel, spec.seed)
        except ValueError as e:
            raise ConfigError(f"{where}: {e}") from e
    else:
        tile, tile_labels = lay.ground_rgb, lay.ground_labels
    satmap = SatelliteMap(tile, spec.meters_per_pixel, (0.0, lay.height_m), tile_labels)
    return Scene(replace(spec, knobs=replace(spec.knobs, aliasing=aliasing)), lay, satmap, src)


@functools.lru_cache(maxsize=4)
def _cached_scene(path: str, aliasing: float | None) -> Scene:
    spec, base = load_spec(path)
    return build_scene(spec, base, aliasing, where=path)


def load_scene(name_or_path: str | os.PathLike, aliasing: float | None = None) -> Scene:
    """Load a scene by shipped name, YAML path, or saved-scene directory (cached per process)."""
    p = Path(name_or_path)
    if p.is_dir() and (p / "scene.json").is_file():
        return Scene.load(p)
    return _cached_scene(str(scene_path(name_or_path).resolve()), aliasing)
