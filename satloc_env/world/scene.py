"""Scenes as data: YAML files naming a generator (or a georeferenced image), routes, objects and lighting.

A scene file (see ``scenes/*.yaml``)::

    name: city
    seed: 7
    generator: {type: grid, style: city, blocks: [4, 4], pitch_m: 80, road_width_m: 12, sidewalk_m: 3,
                margin_m: 20, variety: 0}   # variety 0..1: objects with looks of their own (world.variety)
      # or {type: image, image: tile.tif, roads: roads.png}  (paths relative to the YAML file; see below)
    meters_per_pixel: 0.2          # satellite tile resolution
    ground_mpp: 0.1                # resolution of the ground texture the camera sees
    routes:                        # optional: without it, derived from the road graph (see below)
      main: {waypoints: [[x, y], ...], closed: true, laps: 1}
      # or {lonlat: [[lon, lat], ...]} (an image scene with a georeference)
      # or {trace: true} / {trace: {smooth_m: 2, spacing_m: 2, min_length_m: 50, prune_m: 8, reverse: false}}
      #    (traced from the image scene's road mask or label image: satloc_env.world.roadtrace)
      # waypoints / lonlat with snap: true: moved onto the roads and joined along them
    database_route: main
    query_route: main              # derived routes: main (the other lane) or revisit (the other direction)
    road_graph: {snap_m: 2, edge_margin_m: 2, smooth_m: 3, spacing_m: 2, turn_radius_m: 4.5, snap_route_m: 20}
    ground_pad_m: 250              # world around the tile, so no view shows its edge
    ground_beyond: mirror          # what it is: the tile mirrored, or neutral ground (default: see below)
    ground_shadows: true           # the camera's ground shows the world's cast shadows (default: grids with variety)
    capture_parts: [time, lean, texture, blur, registration, jpeg, deep_shadows]   # the map's capture (default:
                                   # world.capture.PARTS; optional parts: world.capture.OPTIONAL_PARTS)
    objects: {buildings: [...], trees: [...], cars: [...]}   # extra hand-placed objects
    lighting: {sun_azimuth_deg: 135, sun_elevation_deg: 50}   # where the light comes from: degrees counter-clockwise
                                   # from east (90: from the north, 225: from the south-west), above the horizon
    terrain: {relief_m: 1.5, wavelength_m: 250, camber: 0.01}   # gentle hills, cambered roads (default: a plane)
    knobs: {aliasing: 0.0, occlusion: 0.0, appearance: 0.0, satellite_gap: 0.5}

**Image scenes** (``generator: {type: image, ...}``) drape an image over the ground plane: the camera sees
the image as the textured ground (``ground_mpp`` must equal ``meters_per_pixel``) and the satellite tile
is the same image. ``image`` is

* a georeferenced image: a GeoTIFF in any CRS, or an image with a world file (``.pgw/.jgw/.tfw/.wld``)
  whose CRS comes from a ``.prj`` beside it or the ``crs`` field. It is loaded through
  :func:`satloc.geodata.georef.load_map` at ``meters_per_pixel``, north up, into a
  :class:`~satloc.geoframe.GeoFrame` whose origin (lon0, lat0) is the loaded area's south-west corner, so
  the scene keeps the simulator's local frame (x in [0, width_m], y in [0, height_m]) and the scene's
  ``satmap.frame`` still converts to and from lon/lat. Without ``region`` the area is the largest north-up
  rectangle inside the image's footprint; ``region: [lon_min, lat_min, lon_max, lat_max]`` (WGS84
  degrees) crops it;
* or a plain image (no georeference), taken as it is: north up, ``meters_per_pixel`` per pixel, its
  south-west corner at the origin.

A georeferenced image may be of any bit depth and band count (:mod:`satloc.geodata.radiometry`): ``bands: [r, g, b]``
(or ``[grey]``; numbered from 1, as GDAL counts) picks the bands, and ``stretch`` says how samples become 8
bits: ``auto`` (the default: 8-bit images as stored, any other type stretched per band from its 0.5-99.5 %
percentiles to 0..255), ``none`` (the type's full range), ``[low, high]`` or ``[[low, high], ...]`` (one per
band). What was applied is the scene's ``satmap.radiometry``, in its :meth:`Scene.summary` (``satloc scene``).

``labels`` (class ids of :mod:`satloc.labels`) and ``roads`` (a road mask: non-zero is road) are images of
the same size as ``image``, pixel for pixel, and follow it through the reprojection (nearest class; the
mask bilinear, then halved). The drivable area and the ground classes come from them: with ``roads``,
road inside the mask and, outside it, the label image's class or else ``void`` (not drivable); with only
``labels``, the label image; with neither, road everywhere. A ``trace`` route follows the mask (or the
label image's road and lane-marking classes): see :func:`satloc_env.world.roadtrace.trace_route`. Occluders and
appearance changes work on image scenes as on generated ones. ``parked_per_km`` parks the camera's world's own 3-D
cars along the kerbs of streets wide enough (:func:`satloc_env.world.traffic.parked_cars`), which the map does not
show (with ``ground_shadows: true`` they shade the ground at the scene's sun): the camera's view is then no longer
the map's pixels alone, though its ground is still the image the map is captured from.

**Roads as vectors.** ``roads`` may instead be a vector file of road centre lines (GeoJSON, GeoPackage or
Shapefile, as OpenStreetMap extracts and public benchmark labels come; read by :mod:`satloc.geodata.vectors` in the
CRS the file declares, CRS84 for a GeoJSON file without one). The lines are taken to the scene's frame
through pyproj and buffered by their width (``width`` / ``lanes`` / ``lane_number`` attributes, else
``generator.road_width_m``, 7 m) into the road mask, which then serves as a raster mask does.

**The road graph and derived routes** (:mod:`satloc_env.world.roadgraph`, parameters ``road_graph:``). The road
graph is built from the vector centre lines, else from the skeleton of the road mask (or of the road classes
of the label image, or of a generated scene's ground). Without ``routes:``, two routes are derived from it:
``main`` (the ``database_route``), a tour that drives every road of the graph's largest connected part,
turning at its intersections and turning round in a loop at dead ends where the road is wide enough (a
turning circle), and ``revisit``, the same tour the other way round, every road in the other direction. The
query pass drives ``query_route``, by default ``main`` in the other lane (1 m to the left, as on every
scene); ``query_route: revisit`` drives it the other way, which the method cannot localize (it has seen
each place from one direction only: on ``suburb_utm``, full + track + BEV align has a median error of 0.09 m
on the other lane and 43 m the other way). ``waypoints`` or ``lonlat`` with ``snap: true`` are moved onto the roads (from
up to ``road_graph.snap_route_m`` away, even from beyond the loaded area's edge) and joined by the shortest
way along them. Routes over the graph carry the road's width at each waypoint (``widths``): lane offsets
follow it (:class:`satloc_env.world.route.Route`: -1.75 m is the centre of the right lane on roads up to 7 m
wide, -width / 4 on narrower ones).

**The tile's edge.** The world goes on ``ground_pad_m`` metres (default 250, more than the renderer's view
distance, 150 m) beyond the tile on every side, so no view shows the tile's edge and sky below the horizon:
with ``ground_beyond: mirror`` the tile's ground and objects reflected across its edges, so a road that
meets the edge goes on and houses stand beyond it; with ``ground_beyond: neutral``, flat ground in a neutral
texture (:func:`satloc_env.world.meshes.pad_texture`), where roads end at the edge. The default is
``mirror`` for real places (image and vector generators) and ``neutral`` for the generated grids, whose
measured figures rest on it (:attr:`SceneSpec.beyond_edge`). The reflections are scenery: routes stay on the
tile, and the satellite map covers the tile alone. The alternative, keeping routes the view distance
inside the tile, would leave nothing of a 377 m x 277 m image such as ``suburb_utm``. Derived routes keep
``road_graph.edge_margin_m`` (2 m) inside the tile. Pixels of a georeferenced image that hold no imagery
(nodata, masked, transparent, or beyond a reprojected image's footprint: :attr:`SatelliteMap.valid`) are
filled with the imagery's median colour, on the ground and on the tile alike, rather than left black.

Every field is checked; unknown keys, wrong types, missing images, images or masks of another size, empty
masks, masks without a long enough road and routes leaving the tile raise :class:`satloc.ConfigError`
naming the file and the field.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import os
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml

from satloc.config import from_dict, to_dict
from satloc.errors import ConfigError, FormatError, SatlocWarning
from satloc.labels import CLASS_ID, DRIVABLE, NUM_CLASSES
from satloc.persist import (
    ArraySpec,
    atomic_dir,
    header,
    header_number,
    load_npz,
    nonfinite_path,
    read_json,
    save_npz,
    write_json,
)
from satloc.satmap import SatelliteMap, read_image

from .capture import DEFAULT_GAP, OPTIONAL_PARTS, PARTS, capture_image, capture_tile
from .furniture import KINDS as FURNITURE_KINDS
from .generator import GridParams, generate_grid
from .layout import Building, Car, Furniture, Layout, Tree
from .meshes import BEYOND, DEFAULT_GROUND_PAD_M
from .roadgraph import GraphParams
from .route import Route
from .vector_world import VectorGeneratorSpec

# the repository's scenes/ (source checkout, editable install) or its installed copy (satloc_env/scenes)
_PACKAGE = Path(__file__).resolve().parents[1]          # satloc_env/
SCENES_DIR = next((d for d in (_PACKAGE.parent / "scenes", _PACKAGE / "scenes") if d.is_dir()),
                  _PACKAGE.parent / "scenes")


@dataclass
class GridGeneratorSpec:
    type: Literal["grid"] = "grid"
    style: Literal["city", "residential"] = "city"
    blocks: tuple[int, int] = (4, 4)
    pitch_m: float = 80.0
    road_width_m: float = 12.0
    sidewalk_m: float = 3.0
    margin_m: float = 20.0
    variety: float = 0.0   #: 0..1: that share of the objects with looks of their own (satloc_env.world.variety)


@dataclass
class ImageGeneratorSpec:
    type: Literal["image"]
    image: str
    labels: str | None = None    #: class ids, same size as ``image``
    roads: str | None = None     #: road mask (non-zero: road), same size as ``image``
    crs: str | None = None       #: CRS of an image with a world file and no ``.prj`` (e.g. "EPSG:32632")
    region: tuple[float, float, float, float] | None = None   #: lon_min, lat_min, lon_max, lat_max (degrees)
    bands: Any = None            #: [r, g, b] or [grey], numbered from 1 (satloc.geodata.radiometry.Radiometry.bands)
    stretch: Any = "auto"        #: auto, none, [low, high] or [[low, high], ...] (Radiometry.stretch)
    alpha: Any = "auto"          #: auto (the band the file marks as alpha), a band number, or none (Radiometry.alpha)
    road_width_m: float = 7.0    #: width of vector roads whose attributes give none (width, lanes, lane_number)
    buildings: str | None = None  #: building footprints (vector file), extruded (satloc_env.world.scene_buildings)
    trees: str | None = None      #: trees: points or canopy polygons (vector file)
    building_height_m: tuple[float, float] = (5.0, 9.0)   #: height range of footprints whose attributes give none
    heights: str | None = None    #: a DSM / nDSM GeoTIFF (any CRS): building and tree heights where it covers them
    #: the camera's world's own cars parked along the kerbs of streets wide enough to park beside a lane, per km of
    #: kerb (satloc_env.world.traffic.parked_cars; the generated grids' city streets have 54): 3-D cars that the map,
    #: the image captured, does not show. 0: none (the image's own cars, flat on its ground, are in both views)
    parked_per_km: float = 0.0

    def __post_init__(self):
        self.radiometry   # bad bands or stretch: ConfigError naming the field
        if not (isinstance(self.parked_per_km, (int, float)) and 0 <= self.parked_per_km <= 1000):
            raise ConfigError(f"generator.parked_per_km: expected cars per km of kerb from 0 to 1000, got "
                              f"{self.parked_per_km!r}")
        lo, hi = (float(v) for v in self.building_height_m)
        if not 1.0 <= lo <= hi <= 500.0:
            raise ConfigError(f"building_height_m: expected [low, high] metres with 1 <= low <= high <= 500, got "
                              f"{list(self.building_height_m)}")

    @property
    def radiometry(self):
        """The :class:`satloc.geodata.radiometry.Radiometry` of ``bands`` and ``stretch``."""
        from satloc.geodata.radiometry import Radiometry

        return Radiometry(self.bands, self.stretch, self.alpha)

    def files(self, base: Path) -> list[tuple[str, Path]]:
        """(field, path) of every existing file the generator reads: the image, its world file and ``.prj``
        sidecars, the label image and the road mask (what a cache of the scene must depend on)."""
        from satloc.geodata.georef import input_files

        img = base / self.image
        out = [("image", img)]
        out += [("image_sidecar", p) for p in input_files(img)[1:]]
        out += [(k, base / getattr(self, k)) for k in ("labels", "roads", "buildings", "trees", "heights")
                if getattr(self, k)]
        from satloc.geodata.vectors import vector_files

        for k in ("roads", "buildings", "trees"):
            if getattr(self, k):
                out += [(f"{k}_sidecar", p) for p in vector_files(base / getattr(self, k))[1:]]
        return out


@dataclass(frozen=True)
class TraceSpec:
    """How a route is traced from an image scene's road mask (see :mod:`satloc_env.world.roadtrace`)."""

    smooth_m: float = 2.0       #: Gaussian smoothing along the traced centre line, metres
    spacing_m: float = 2.0      #: waypoint spacing, metres
    min_length_m: float = 50.0  #: a shorter road is an error
    prune_m: float = 8.0        #: skeleton twigs shorter than this are ignored, metres
    reverse: bool = False       #: drive it the other way


@dataclass
class RouteSpec:
    """A route: ``waypoints`` in map metres, or ``lonlat`` (WGS84 degrees, an image scene with a
    georeference), or ``trace`` (traced from the image scene's road mask); exactly one of them. ``snap``:
    move the waypoints onto the scene's roads and join them along the roads. ``widths``: the road's width
    at each waypoint (set on routes over the road graph; lane offsets follow it)."""

    waypoints: list[tuple[float, float]] | None = None
    closed: bool = False
    laps: int = 1
    lonlat: list[tuple[float, float]] | None = None
    trace: bool | TraceSpec | None = None
    snap: bool = False
    widths: list[float] | None = None

    def __post_init__(self):
        given = [k for k in ("waypoints", "lonlat", "trace") if getattr(self, k) not in (None, False)]
        if len(given) != 1:
            raise ConfigError(f"waypoints/lonlat/trace: expected exactly one of them, got "
                              f"{' and '.join(given) if given else 'none'}")
        if self.laps < 1:
            raise ConfigError(f"laps: expected an integer >= 1, got {self.laps}")
        if self.snap and self.trace not in (None, False):
            raise ConfigError("snap: a traced route follows the road already; snap applies to waypoints and lonlat")
        if self.widths is not None and (self.waypoints is None or self.snap):
            raise ConfigError("widths: the road width at each waypoint goes with waypoints (not lonlat, trace or "
                              "snap, whose widths come from the road graph)")


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
class TerrainSpec:
    """The ground's heights (:class:`satloc_env.world.terrain.Terrain`, drawn from the scene's seed):
    ``relief_m`` their standard deviation (0: a plane), ``wavelength_m`` about how far apart the hills are,
    ``camber`` the roads' cross-fall from their crown to their kerbs (a fraction; 0: flat across)."""

    relief_m: float = 0.0
    wavelength_m: float = 250.0
    camber: float = 0.0


@dataclass
class Knobs:
    """Scene difficulty knobs, each in [0, 1].

    aliasing: fraction of blocks that are exact copies of other blocks (layout and texture).
    occlusion: density of objects the ground camera sees but the tile does not (cars, people, obstacles).
    appearance: strength of the lighting / colour / exposure change of an episode (another time of day).
    change: strength of an episode's revisit change of the world (:mod:`satloc_env.world.revisit`: shadows of another
        sun, road wear and patches, parked cars moved, another season); the satellite tile never changes.
    satellite_gap: how far the satellite map is a capture of the world rather than a copy of the rendered
        ground (:mod:`satloc_env.world.capture`: its own sub-resolution texture, capture time, off-nadir view,
        sensor blur, registration error, compression); 0 is the ground texture itself. Default
        :data:`~satloc_env.world.capture.DEFAULT_GAP` (0.5), a realistic capture; a scene saved before the knob
        (its ``scene.json`` without it) was a copy, and loads as 0.
    """

    aliasing: float = 0.0
    occlusion: float = 0.0
    appearance: float = 0.0
    change: float = 0.0
    satellite_gap: float = DEFAULT_GAP

    def __post_init__(self):
        for k in ("aliasing", "occlusion", "appearance", "change", "satellite_gap"):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ConfigError(f"{k}: expected a number in [0, 1], got {v!r}")
            if not 0.0 <= v <= 1.0:
                raise ConfigError(f"{k}: expected a value in [0, 1], got {v}")


#: how dark (0 to 1 of :data:`satloc_env.world.revisit.SHADOW_RGB`'s darkening) the shadows of a world that
#: casts them are (:attr:`SceneSpec.casts_shadows`): a clear day
SHADOW_DEPTH = 0.85


@dataclass
class SceneSpec:
    name: str
    routes: dict[str, RouteSpec] = field(default_factory=dict)   # none: derived from the road graph
    generator: dict[str, Any] = field(default_factory=lambda: {"type": "grid"})
    seed: int = 0
    description: str = ""
    meters_per_pixel: float = 0.2
    ground_mpp: float = 0.1
    database_route: str = "main"
    query_route: str = "main"
    objects: ObjectsSpec = field(default_factory=ObjectsSpec)
    lighting: LightingSpec = field(default_factory=LightingSpec)
    terrain: TerrainSpec = field(default_factory=TerrainSpec)
    knobs: Knobs = field(default_factory=Knobs)
    road_graph: GraphParams = field(default_factory=GraphParams)
    ground_pad_m: float | None = None    # None: DEFAULT_GROUND_PAD_M
    ground_beyond: str | None = None     # satloc_env.world.meshes.BEYOND; None: see beyond_edge
    ground_shadows: bool | None = None   # the camera's world casts its shadows on the ground; None: see casts_shadows
    capture_parts: list[str] | None = None   # the satellite capture's parts (world.capture); None: its PARTS

    @property
    def beyond_edge(self) -> str:
        """What the world is beyond the tile: ``ground_beyond`` if given, else ``mirror`` for scenes of real
        places (image and vector generators) and for grids with ``variety`` (a street goes on past the map's
        edge), and ``neutral`` for generated grids without it, whose measured figures (the tables, the tuned
        settings, the active-localization maps) rest on it."""
        if self.ground_beyond is not None:
            return self.ground_beyond
        if self.generator.get("type") == "grid":
            return "mirror" if self._grid_variety > 0 else "neutral"
        return "mirror"

    @property
    def _grid_variety(self) -> float:
        """A grid generator's ``variety`` (0 for other generators, or where it is not a number yet: checked
        later, naming the field)."""
        variety = self.generator.get("variety") or 0.0
        ok = self.generator.get("type") == "grid" and isinstance(variety, (int, float))
        return float(variety) if ok else 0.0

    @property
    def parts(self) -> tuple[str, ...]:
        """The satellite capture's parts (:mod:`satloc_env.world.capture`): ``capture_parts`` if given, else the
        default :data:`~satloc_env.world.capture.PARTS`, in the order given (each is applied in its own place)."""
        return PARTS if self.capture_parts is None else tuple(self.capture_parts)

    @property
    def casts_shadows(self) -> bool:
        """Whether the camera's world has the shadows of its buildings, trees, cars and furniture on its ground
        (at the layout's sun, :data:`SHADOW_DEPTH`): ``ground_shadows`` if given, else for grids with
        ``variety`` only (the tables' worlds rest on none; an image scene's ground is imagery with its own)."""
        if self.ground_shadows is not None:
            return bool(self.ground_shadows)
        return self._grid_variety > 0

    def build_world(self, layout):
        """The renderable world of ``layout`` (this scene's or a changed copy) with this spec's ground beyond
        the tile (``ground_pad_m``, ``beyond_edge``) and, where it :attr:`casts_shadows`, the layout's shadows
        painted on its ground (the satellite tile paints its own, at its capture's sun)."""
        from .meshes import build_world

        pad = DEFAULT_GROUND_PAD_M if self.ground_pad_m is None else self.ground_pad_m
        if self.casts_shadows:
            from .revisit import cast_shadows

            layout = dataclasses.replace(layout, ground_rgb=layout.ground_rgb.copy())
            cast_shadows(layout, SHADOW_DEPTH)
        return build_world(layout, pad_m=pad, beyond=self.beyond_edge, terrain=self.ground_terrain)

    @property
    def ground_terrain(self):
        """The :class:`~satloc_env.world.terrain.Terrain` of ``terrain`` and the scene's seed."""
        from .terrain import Terrain

        return Terrain(self.terrain.relief_m, self.terrain.wavelength_m, int(self.seed), self.terrain.camber)

    @property
    def route_names(self) -> list[str]:
        """The routes the scene has: those given, else the derived ones."""
        from .scene_roads import DERIVED_ROUTES

        return sorted(self.routes) if self.routes else list(DERIVED_ROUTES)

    def generator_spec(self, where: str = "scene") -> GridGeneratorSpec | ImageGeneratorSpec | VectorGeneratorSpec:
        kind = self.generator.get("type")
        if kind == "grid":
            return from_dict(GridGeneratorSpec, self.generator, f"{where}: generator")
        if kind == "image":
            return from_dict(ImageGeneratorSpec, self.generator, f"{where}: generator")
        if kind == "vectors":
            return from_dict(VectorGeneratorSpec, self.generator, f"{where}: generator")
        raise ConfigError(f"{where}: generator.type: expected 'grid', 'image' or 'vectors', got {kind!r}")


MAX_GROUND_PX = 20000 * 20000  # the largest ground raster a scene may ask for (as satloc.geodata.georef's maps)
MAX_LAPS = 1000
MAX_GROUND_PAD_M = 5000.0


def check_spec(spec: SceneSpec, where: str) -> None:
    """The spec's numbers within their ranges (a scene file may be damaged or hand-edited): resolutions,
    seed, laps, lighting, and hand-placed objects of positive size and valid colours; ConfigError naming
    ``where`` and the field."""
    def need(ok: bool, field_: str, what: str, value) -> None:
        if not ok:
            raise ConfigError(f"{where}: {field_}: expected {what}, got {value!r}")

    need(spec.meters_per_pixel > 0, "meters_per_pixel", "> 0", spec.meters_per_pixel)
    need(spec.ground_mpp > 0, "ground_mpp", "> 0", spec.ground_mpp)
    need(spec.seed >= 0, "seed", "an integer >= 0", spec.seed)
    for k, r in spec.routes.items():
        need(r.laps <= MAX_LAPS, f"routes.{k}.laps", f"at most {MAX_LAPS}", r.laps)
    if spec.ground_pad_m is not None:
        need(0 <= spec.ground_pad_m <= MAX_GROUND_PAD_M, "ground_pad_m", f"metres in [0, {MAX_GROUND_PAD_M:g}]",
             spec.ground_pad_m)
    need(spec.ground_beyond is None or spec.ground_beyond in BEYOND, "ground_beyond", f"one of {BEYOND}",
         spec.ground_beyond)
    if spec.capture_parts is not None:
        known = PARTS + OPTIONAL_PARTS
        need(isinstance(spec.capture_parts, list) and all(p in known for p in spec.capture_parts)
             and len(set(spec.capture_parts)) == len(spec.capture_parts), "capture_parts",
             f"a list of distinct parts of {list(known)}", spec.capture_parts)
    need(0 < spec.lighting.sun_elevation_deg <= 90, "lighting.sun_elevation_deg", "degrees in (0, 90]",
         spec.lighting.sun_elevation_deg)
    try:
        spec.ground_terrain
    except ConfigError as e:
        raise ConfigError(f"{where}: {e}") from None
    rgb_ok = lambda c: all(0 <= v <= 255 for v in c)  # noqa: E731
    for i, b in enumerate(spec.objects.buildings):
        f = f"objects.buildings[{i}]"
        need(len(b.footprint) >= 3, f"{f}.footprint", "a polygon of >= 3 points", b.footprint)
        need(b.height > 0, f"{f}.height", "metres > 0", b.height)
        need(b.facade >= 0, f"{f}.facade", "a style index >= 0", b.facade)
        need(rgb_ok(b.roof_rgb), f"{f}.roof_rgb", "[r, g, b] in 0..255", b.roof_rgb)
    for i, t in enumerate(spec.objects.trees):
        f = f"objects.trees[{i}]"
        need(t.canopy_radius > 0, f"{f}.canopy_radius", "metres > 0", t.canopy_radius)
        need(0 <= t.canopy_bottom < t.canopy_top, f"{f}.canopy_bottom/canopy_top", "0 <= bottom < top",
             [t.canopy_bottom, t.canopy_top])
    for i, c in enumerate(spec.objects.cars):
        need(rgb_ok(c.rgb), f"objects.cars[{i}].rgb", "[r, g, b] in 0..255", c.rgb)


#: bytes of memory a generated world takes per ground pixel at its peak (its rasters, the satellite capture and
#: the renderable world): osm_town, 10.1 Mpx, peaked at 1.6 GB resident with the interpreter and libraries
BYTES_PER_GROUND_PX = 150


def _available_memory() -> int | None:
    """Bytes of memory this process may still take: Linux's MemAvailable, or less where a cgroup (v2) limits
    the process (a container); None where unknown."""
    out = None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    out = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        pass
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            room = int(limit) - int(Path("/sys/fs/cgroup/memory.current").read_text().strip())
            out = room if out is None else min(out, room)
    except (OSError, ValueError):
        pass
    return out


def _check_size(width_m: float, height_m: float, mpp: float, where: str, what: str,
                advice: str = "generator.region, lon/lat, for the part you need") -> None:
    px = (width_m / mpp) * (height_m / mpp)
    if not (math.isfinite(px) and 1 <= px <= MAX_GROUND_PX and width_m > 0 and height_m > 0):
        raise ConfigError(f"{where}: {what}: a {width_m:g} m x {height_m:g} m ground at {mpp:g} m per pixel is "
                          f"{px:.3g} pixels; expected 1 to {MAX_GROUND_PX:.3g}")
    need, have = px * BYTES_PER_GROUND_PX, _available_memory()
    if have is not None and need > have:
        raise ConfigError(f"{where}: {what}: a {width_m:.0f} m x {height_m:.0f} m ground at {mpp:g} m per pixel "
                          f"({px / 1e6:.0f} Mpx) needs about {need / 1e9:.1f} GB to build, more than the "
                          f"{have / 1e9:.1f} GB available here: make the area smaller ({advice}) or ground_mpp "
                          f"coarser")


def _check_objects_inside(spec: SceneSpec, width_m: float, height_m: float, where: str) -> None:
    """Hand-placed objects lie on the tile (as routes must)."""
    for kind, objs in (("buildings", spec.objects.buildings), ("trees", spec.objects.trees),
                       ("cars", spec.objects.cars)):
        for i, o in enumerate(objs):
            pts = o.footprint if kind == "buildings" else [o.center]
            for x, y in pts:
                if not (0 <= x <= width_m and 0 <= y <= height_m):
                    raise ConfigError(f"{where}: objects.{kind}[{i}]: point [{x}, {y}] lies outside the tile, which "
                                      f"covers x in [0, {width_m}] and y in [0, {height_m}] metres")


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
        data = yaml.safe_load(path.read_bytes().decode("utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError, RecursionError) as e:
        raise ConfigError(f"{path}: not valid YAML text ({type(e).__name__}: {str(e)[:300]})") from e
    except OSError as e:
        raise ConfigError(f"{path}: not readable ({e})") from e
    bad = nonfinite_path(data)
    if bad is not None:
        raise ConfigError(f"{path}: {bad}: expected a finite number")
    spec = from_dict(SceneSpec, data, f"{path}:")
    check_spec(spec, str(path))
    spec.generator_spec(str(path))
    for k in ("database_route", "query_route"):
        if getattr(spec, k) not in spec.route_names:
            raise ConfigError(f"{path}: {k}: route {getattr(spec, k)!r} is not in routes {spec.route_names}"
                              + ("" if spec.routes else " (the routes derived where none are given)"))
    return spec, path.resolve().parent


class Scene:
    """A generated (or image-based) scene: layout, satellite map, routes, drivable area."""

    def __init__(self, spec: SceneSpec, layout: Layout, satmap: SatelliteMap, alias_source: np.ndarray | None = None,
                 where: str | None = None):
        unresolved = sorted(k for k, r in spec.routes.items() if r.waypoints is None)
        if unresolved:
            raise ConfigError(f"{where or f'scene {spec.name!r}'}: routes {unresolved}: a Scene needs waypoints; "
                              f"build it with build_scene (which converts lonlat and traces trace routes)")
        self.spec = spec
        self.layout = layout
        self.satmap = satmap
        #: vector buildings' report (kept, trimmed, repaired, dropped footprints), for a scene built from them
        self.footprints: dict | None = None
        #: the derived tour's lengths and coverage of the road network, for a scene whose routes were derived
        self.tour: dict | None = None
        self.alias_source = alias_source if alias_source is not None else np.zeros(0, int)
        try:
            self.routes = {k: Route(r.waypoints, r.closed, r.laps, name=f"routes.{k}", widths=r.widths)
                           for k, r in spec.routes.items()}
        except ValueError as e:
            raise ConfigError(f"{where or f'scene {spec.name!r}'}: {e}") from e
        self.drivable = np.isin(layout.ground_labels, DRIVABLE)
        self._check_routes(where or f"scene {self.name!r}")

    @property
    def name(self) -> str:
        return self.spec.name

    def summary(self) -> dict:
        """What ``satloc scene`` prints: name, size, tile pixels, route lengths, object counts and, for a scene
        over imagery, how the image got its 8-bit colours (``radiometry``: :func:`satloc.geodata.radiometry.to_rgb8`)."""
        out = {"scene": self.name, "size_m": [self.layout.width_m, self.layout.height_m],
               "tile_px": list(self.satmap.image.shape[1::-1]),
               "routes_m": {k: round(r.length, 1) for k, r in self.routes.items()},
               "buildings": len(self.layout.buildings), "trees": len(self.layout.trees),
               "cars": len(self.layout.cars)}
        if self.layout.furniture:
            out["furniture"] = len(self.layout.furniture)
        if self.spec.terrain.relief_m > 0 or self.spec.terrain.camber > 0:
            out["terrain"] = {"relief_m": self.spec.terrain.relief_m, "wavelength_m": self.spec.terrain.wavelength_m}
            if self.spec.terrain.camber > 0:
                out["terrain"]["camber"] = self.spec.terrain.camber
        if self.satmap.radiometry is not None:
            out["radiometry"] = self.satmap.radiometry
        if self.footprints is not None:
            out["footprints"] = dict(self.footprints)
        if self.tour is not None:
            out["tour"] = dict(self.tour)
        return out

    @functools.cached_property
    def road_graph(self):
        """The scene's road graph (:class:`satloc_env.world.roadgraph.RoadGraph`): the one its routes were made
        from, else the skeleton's of the road classes of its ground labels."""
        from .scene_roads import road_graph

        return road_graph(self.spec.road_graph, None, self.layout.ground_labels, self.layout.ground_mpp,
                          f"scene {self.name!r}")

    #: the disk cache folder this scene was read from or saved to (:func:`scene_cache_path`), where its world is
    #: kept too; None: not cached
    cache_dir = None
    #: the :class:`~satloc.errors.SatlocWarning` messages building it gave (about its files: a dark image, roads
    #: left out, ...); kept in ``scene.json`` so that a scene read back from the disk cache says them again
    build_warnings: tuple[str, ...] = ()

    @functools.cached_property
    def world(self):
        """Renderable geometry of the scene (:class:`satloc_env.world.meshes.World`), built once per scene (and
        once per machine for a scene of the disk cache: read from its ``world.npz`` there)."""
        from .meshes import load_world, save_world

        path = None if self.cache_dir is None else Path(self.cache_dir) / "world.npz"
        if path is not None and path.is_file():
            try:
                return load_world(path)
            except FormatError:
                pass   # damaged: built again
        world = self.spec.build_world(self.layout)
        if path is not None:
            try:
                save_world(world, path)
            except OSError:
                pass
        return world

    def _check_routes(self, where: str) -> None:
        W, H = self.layout.width_m, self.layout.height_m
        for k, r in self.spec.routes.items():
            for i, (x, y) in enumerate(r.waypoints):
                if not (0 <= x <= W and 0 <= y <= H):
                    raise ConfigError(f"{where}: routes.{k}.waypoints[{i}] = [{x}, {y}] lies outside "
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
                "bld_roof_ground": np.array([x.roof_from_ground for x in b], np.uint8),
                "bld_base": np.array([x.base for x in b], np.float64),
                "bld_gabled": np.array([x.roof == "gabled" for x in b], np.uint8),
                "trees": np.array([[*t.center, t.canopy_radius, t.canopy_bottom, t.canopy_top, t.shade]
                                   for t in lay.trees], np.float64).reshape(-1, 6),
                "cars": np.array([[*c.center, c.yaw, c.length, c.width, c.height, *c.rgb] for c in lay.cars],
                                 np.float64).reshape(-1, 9),
                # variety (satloc_env.world.variety): a facade's own seed (-1: its style), species, car bodies
                "bld_style": np.array([-1 if x.style_seed is None else x.style_seed for x in b], np.int64),
                "tree_species": np.array([t.species for t in lay.trees], np.int64),
                "car_body": np.array([c.body for c in lay.cars], np.int64),
                # street furniture (satloc_env.world.furniture): x, y, yaw, kind, seed
                "furniture": np.array([[*f.center, f.yaw, f.kind, f.seed] for f in lay.furniture],
                                      np.float64).reshape(-1, 5),
            }
            # the index each object copies its look from (-1: its own; satloc_env.world.layout)
            for key, objs in (("bld_look", b), ("tree_look", lay.trees), ("car_look", lay.cars),
                              ("furn_look", lay.furniture)):
                arrays[key] = np.array([-1 if o.look is None else o.look for o in objs], np.int64)
            save_npz(d / "layout.npz", "scene_layout", arrays, {
                "width_m": lay.width_m, "height_m": lay.height_m, "ground_mpp": lay.ground_mpp,
                "sun_azimuth": lay.sun_azimuth, "sun_elevation": lay.sun_elevation})
            meta = header("scene")
            meta["spec"] = to_dict(self.spec)
            if self.tour is not None:
                meta["tour"] = dict(self.tour)
            if self.build_warnings:
                meta["build_warnings"] = list(self.build_warnings)
            write_json(d / "scene.json", meta)
            self.satmap.save(d / "tile")

    @staticmethod
    def load(path: str | os.PathLike) -> "Scene":
        d = Path(path)
        sj, lz = d / "scene.json", d / "layout.npz"
        meta = read_json(sj, "scene")
        _saved_gap(meta)
        bad = nonfinite_path(meta.get("spec"))
        if bad is not None:
            raise FormatError(f"{sj}: spec.{bad}: expected a finite number")
        try:
            spec = from_dict(SceneSpec, meta.get("spec"), f"{sj}: spec")
            if isinstance(meta.get("spec"), dict) and "ground_beyond" not in meta["spec"]:
                spec = dataclasses.replace(spec, ground_beyond="neutral")   # saved before the mirror: as it was
            spec.generator_spec(f"{sj}: spec")
            check_spec(spec, f"{sj}: spec")
        except ConfigError as e:
            raise FormatError(str(e)) from e
        a, m = load_npz(lz, "scene_layout", {
            "ground_rgb": ArraySpec("u", ("H", "W", 3)), "ground_labels": ArraySpec("u", ("H", "W")),
            "alias_source": ArraySpec("iu", (None,), min=0), "bld_nverts": ArraySpec("iu", ("B",), min=3),
            "bld_verts": ArraySpec("f", (None, 2)), "bld_params": ArraySpec("f", ("B", 5)),
            "bld_roof_ground": ArraySpec("iub", ("B",), min=0, max=1, required=False),
            "bld_base": ArraySpec("f", ("B",), min=0, required=False),
            "bld_gabled": ArraySpec("iub", ("B",), min=0, max=1, required=False),
            "trees": ArraySpec("f", (None, 6)), "cars": ArraySpec("f", (None, 9)),
            "furniture": ArraySpec("f", (None, 5), required=False)})
        if a["ground_rgb"].dtype != np.uint8 or a["ground_labels"].dtype != np.uint8 or min(a["ground_rgb"].shape) < 1:
            raise FormatError(f"{lz}: ground_rgb and ground_labels must be non-empty uint8 rasters, got "
                              f"{a['ground_rgb'].dtype} {a['ground_rgb'].shape}, {a['ground_labels'].dtype}")
        if a["ground_labels"].max() >= NUM_CLASSES:
            raise FormatError(f"{lz}: array 'ground_labels': class id {a['ground_labels'].max()} >= {NUM_CLASSES}")
        w_m, h_m, mpp = (header_number(m, k, lz, positive=True) for k in ("width_m", "height_m", "ground_mpp"))
        az, el = header_number(m, "sun_azimuth", lz), header_number(m, "sun_elevation", lz)
        hp, wp = a["ground_rgb"].shape[:2]
        if abs(wp * mpp - w_m) > mpp or abs(hp * mpp - h_m) > mpp or not 0 < el <= math.pi / 2:
            raise FormatError(f"{lz}: a {wp}x{hp} px ground at {mpp} m per pixel does not cover width_m {w_m}, "
                              f"height_m {h_m}, or sun_elevation {el} is outside (0, pi/2]")
        nv, verts, bp, tr, ca = (a[k] for k in ("bld_nverts", "bld_verts", "bld_params", "trees", "cars"))
        if int(nv.sum()) != len(verts):
            raise FormatError(f"{lz}: array 'bld_verts' has {len(verts)} vertices, 'bld_nverts' sums to "
                              f"{int(nv.sum())}")
        for key, arr, cols, what in (("bld_params", bp, [0], "height"), ("trees", tr, [2], "canopy radius"),
                                     ("cars", ca, [3, 4, 5], "size")):
            if len(arr) and not (arr[:, cols] > 0).all():
                raise FormatError(f"{lz}: array '{key}': every {what} must be > 0")
        colours = [bp[:, 2:5], ca[:, 6:9], bp[:, 1:2], tr[:, 5:6]]
        if any(len(c) and not ((c >= 0).all() and (c == np.round(c)).all()) for c in colours) or \
                (len(bp) and bp[:, 2:5].max() > 255) or (len(ca) and ca[:, 6:9].max() > 255) or \
                (len(tr) and not (tr[:, 3] < tr[:, 4]).all()):
            raise FormatError(f"{lz}: facade, shade and colour values must be integers (colours 0..255) and every "
                              f"tree's canopy bottom below its top")
        verts_split = np.split(verts, np.cumsum(nv)[:-1]) if len(nv) else []
        roof_ground = a.get("bld_roof_ground")
        roof_ground = np.zeros(len(bp), bool) if roof_ground is None else roof_ground.astype(bool)
        base = a.get("bld_base")
        base = np.zeros(len(bp)) if base is None else base
        gabled = a.get("bld_gabled")
        gabled = np.zeros(len(bp), bool) if gabled is None else gabled.astype(bool)
        def extra(key: str, n: int, fill: int) -> np.ndarray:   # scenes saved before the field: its default
            v = a.get(key)
            if v is None:
                return np.full(n, fill, np.int64)
            if v.shape != (n,):
                raise FormatError(f"{lz}: array {key!r} of shape {v.shape}, expected ({n},)")
            return v.astype(np.int64)

        styles, species, bodies = extra("bld_style", len(bp), -1), extra("tree_species", len(tr), 0), \
            extra("car_body", len(ca), 0)
        looks = {}
        for key, n in (("bld_look", len(bp)), ("tree_look", len(tr)), ("car_look", len(ca)),
                       ("furn_look", 0 if a.get("furniture") is None else len(a["furniture"]))):
            v = extra(key, n, -1)
            if len(v) and not ((v >= -1) & (v < n)).all():
                raise FormatError(f"{lz}: array {key!r}: every look must be -1 (its own) or an index below {n}")
            looks[key] = [None if x < 0 else int(x) for x in v]
        buildings = [Building(v, float(q[0]), int(q[1]), tuple(int(c) for c in q[2:5]), bool(rg), float(z),
                              "gabled" if gb else "flat", None if s < 0 else int(s), lk)
                     for v, q, rg, z, gb, s, lk in zip(verts_split, bp, roof_ground, base, gabled, styles,
                                                       looks["bld_look"])]
        trees = [Tree((t[0], t[1]), t[2], t[3], t[4], int(t[5]), int(sp), lk)
                 for t, sp, lk in zip(tr, species, looks["tree_look"])]
        cars = [Car((c[0], c[1]), c[2], c[3], c[4], c[5], tuple(int(v) for v in c[6:9]), int(bd), lk)
                for c, bd, lk in zip(ca, bodies, looks["car_look"])]
        fu = a.get("furniture")
        fu = np.zeros((0, 5)) if fu is None else fu
        if len(fu) and not (np.isin(fu[:, 3], list(FURNITURE_KINDS)).all() and (fu[:, 4] >= 0).all()
                            and (fu[:, 4] == np.round(fu[:, 4])).all()):
            raise FormatError(f"{lz}: array 'furniture': every kind must be one of {sorted(FURNITURE_KINDS)} and "
                              f"every seed a non-negative integer")
        furniture = [Furniture((f[0], f[1]), f[2], int(f[3]), int(f[4]), lk) for f, lk in zip(fu, looks["furn_look"])]
        lay = Layout(w_m, h_m, mpp, a["ground_rgb"], a["ground_labels"], buildings, trees, cars, az, el, furniture)
        tile = d / "tile"
        sm = SatelliteMap.load(tile)
        x0, x1, y0, y1 = sm.extent
        smpp = sm.meters_per_pixel
        if (abs(smpp - spec.meters_per_pixel) > 1e-9 or abs(x0) > 1e-6 or abs(y1 - h_m) > 1e-6
                or not (-smpp < x1 - w_m <= 1e-6) or not (-1e-6 <= y0 < smpp)):
            raise FormatError(f"{tile / 'map.json'}: the tile (x [{x0:g}, {x1:g}] y [{y0:g}, {y1:g}] m at {smpp:g} m "
                              f"per pixel) does not cover the layout in {lz} ({w_m:g} m x {h_m:g} m) at the "
                              f"spec's {spec.meters_per_pixel:g} m per pixel ({sj})")
        try:
            scene = Scene(spec, lay, sm, a["alias_source"], where=f"{sj}: spec")
        except ConfigError as e:
            raise FormatError(str(e)) from e
        tour = meta.get("tour")
        scene.tour = dict(tour) if isinstance(tour, dict) else None
        said = meta.get("build_warnings", [])
        if not (isinstance(said, list) and all(isinstance(w, str) for w in said)):
            raise FormatError(f"{sj}: build_warnings: expected a list of strings")
        scene.build_warnings = tuple(said)
        return scene


def _objects_from_spec(spec: ObjectsSpec) -> tuple[list[Building], list[Tree], list[Car]]:
    b = [Building(np.asarray(o.footprint, np.float64), o.height, o.facade, tuple(o.roof_rgb)) for o in spec.buildings]
    t = [Tree(tuple(o.center), o.canopy_radius, o.canopy_bottom, o.canopy_top) for o in spec.trees]
    c = [Car(tuple(o.center), math.radians(o.yaw_deg), rgb=tuple(o.rgb)) for o in spec.cars]
    return b, t, c


@dataclass
class _ImageGround:
    """An image scene's ground: the layout, the geo frame (None for a plain image) and the road mask."""

    layout: Layout
    frame: Any                      # satloc.geoframe.GeoFrame | None
    roads: np.ndarray | None        # (H, W) bool road mask on the layout's raster, if any
    radiometry: dict | None = None  # how a georeferenced image became 8-bit RGB (SatelliteMap.radiometry)
    road_graph: Any = None          # the road graph of vector roads (satloc_env.world.roadgraph.RoadGraph), if any
    footprints: dict | None = None  # vector buildings: how many footprints were kept, trimmed, repaired, dropped


def _route_corridor(spec: SceneSpec, frame, shape: tuple[int, int], mpp: float, width_m: float) -> np.ndarray | None:
    """(H, W) bool: the given routes (``waypoints`` in metres, ``lonlat`` through ``frame``) buffered by half
    ``width_m``: the road of a scene that has no road data, where its buildings and trees must not stand;
    None when no route gives its points."""
    import shapely

    from .roadgraph import rasterize_area

    lines = []
    for r in (spec.routes or {}).values():
        if r.waypoints is not None:
            xy = np.asarray(r.waypoints, np.float64).reshape(-1, 2)
        elif r.lonlat is not None and frame is not None:
            xy = frame.to_map(np.asarray(r.lonlat, np.float64).reshape(-1, 2))
        else:
            continue
        if r.closed and len(xy) > 2:
            xy = np.vstack([xy, xy[:1]])
        if len(xy) >= 2:
            lines.append(shapely.LineString(xy).buffer(width_m / 2))
    return rasterize_area(shapely.union_all(lines), shape, mpp) if lines else None


def _image_layout(g: ImageGeneratorSpec, spec: SceneSpec, base: Path, where: str) -> _ImageGround:
    img_path = base / g.image
    if not img_path.is_file():
        raise ConfigError(f"{where}: generator.image: image file {img_path} not found")
    if abs(spec.ground_mpp - spec.meters_per_pixel) > 1e-9:
        raise ConfigError(f"{where}: an image scene uses the image as the ground texture: ground_mpp must equal "
                          f"meters_per_pixel ({spec.meters_per_pixel})")
    mpp = spec.meters_per_pixel
    geo = None   # the map read from a georeferenced image
    from satloc.geodata.georef import is_georeferenced

    if is_georeferenced(img_path, g.crs):
        geo = _load_georeferenced(img_path, g, mpp, where)
        rgb, frame = geo.image, geo.frame
        if geo.valid is not None and geo.valid.any():
            # pixels without imagery (nodata, masked, beyond a reprojected image's footprint) are neutral ground,
            # the median colour of the imagery, as the padding beyond the tile is: not a black hole in the view
            rgb = rgb.copy()
            rgb[~geo.valid] = np.median(rgb[geo.valid], axis=0).astype(np.uint8)
    else:
        for k in ("crs", "region"):
            if getattr(g, k) is not None:
                raise ConfigError(f"{where}: generator.{k}: {img_path} is not georeferenced (no geotransform "
                                  f"and no world file beside it), so it has no place on Earth to apply {k} to")
        for k, default in (("bands", None), ("stretch", "auto"), ("alpha", "auto")):
            if getattr(g, k) != default:
                raise ConfigError(f"{where}: generator.{k}: {img_path} is not georeferenced, so it is read as an "
                                  f"8-bit picture as it is; {k} applies to georeferenced imagery only")
        try:
            rgb = read_image(img_path)
        except FormatError as e:
            raise ConfigError(f"{where}: generator.image: {e}") from e
        frame = None

    def aligned(field_name: str, kind: str, resampling: str, value=None) -> tuple[np.ndarray, np.ndarray]:
        """The raster of ``field_name`` as read (uint8, or ``value`` where non-zero) and on the scene's tile."""
        path = base / getattr(g, field_name)
        if not path.is_file():
            raise ConfigError(f"{where}: generator.{field_name}: {kind} {path} not found")
        try:
            a = read_image(path, grayscale=True)
        except FormatError as e:
            raise ConfigError(f"{where}: generator.{field_name}: {e}") from e
        if value is not None:
            a = np.where(a > 0, value, 0).astype(np.uint8)
        if geo is None:
            if a.shape != rgb.shape[:2]:
                raise ConfigError(f"{where}: generator.{field_name}: {path} is {a.shape[1]}x{a.shape[0]} px, but "
                                  f"the image {img_path.name} is {rgb.shape[1]}x{rgb.shape[0]} px; it must be "
                                  f"aligned with the image pixel for pixel")
            return a, a
        from satloc.geodata.georef import reproject_band

        try:
            return a, reproject_band(a, img_path, geo, g.crs, resampling, what=str(path))
        except (ConfigError, FormatError) as e:
            raise ConfigError(f"{where}: generator.{field_name}: {e}") from e

    labels = roads = road_graph = None
    if g.labels:
        raw, labels = aligned("labels", "label image", "nearest")
        if raw.max() >= NUM_CLASSES:
            raise ConfigError(f"{where}: generator.labels: class id {raw.max()} >= {NUM_CLASSES}")
    from satloc.geodata.vectors import is_vector_file

    if g.roads and is_vector_file(base / g.roads):
        from .scene_roads import vector_roads

        road_graph, roads = vector_roads(base / g.roads, frame, rgb.shape[:2], mpp, g.road_width_m, spec.road_graph,
                                         where)
    elif g.roads:
        raw, tiled = aligned("roads", "road mask", "bilinear", value=255)   # bilinear, then halved
        if not raw.any():
            raise ConfigError(f"{where}: generator.roads: the road mask {base / g.roads} is empty (no non-zero "
                              f"pixel)")
        roads = tiled >= 128
        if not roads.any():
            raise ConfigError(f"{where}: generator.roads: no road of the mask {base / g.roads} lies in the "
                              f"loaded area of the image")
    if roads is not None:
        base_labels = labels if labels is not None else np.full(rgb.shape[:2], CLASS_ID["void"], np.uint8)
        labels = np.where(roads, np.where(np.isin(base_labels, DRIVABLE), base_labels, CLASS_ID["road"]),
                          np.where(np.isin(base_labels, DRIVABLE), CLASS_ID["void"], base_labels)).astype(np.uint8)
    elif labels is None:
        labels = np.full(rgb.shape[:2], CLASS_ID["road"], np.uint8)
    h, w = labels.shape
    buildings, trees, report = [], [], None
    if g.heights and not (g.buildings or g.trees):
        raise ConfigError(f"{where}: generator.heights: a height raster sets the heights of buildings and trees; "
                          f"give generator.buildings or generator.trees too")
    if g.buildings or g.trees:
        from .scene_buildings import height_raster, vector_buildings, vector_trees

        surface = height_raster(base / g.heights, frame, where) if g.heights else None

        drivable = np.isin(labels, DRIVABLE)
        if roads is None and not g.labels:   # no road data: the routes' own corridor is the road
            corridor = _route_corridor(spec, frame, labels.shape, mpp, g.road_width_m)
            if corridor is not None:
                drivable = corridor
        if g.trees:
            trees, crowns = vector_trees(base / g.trees, frame, labels.shape, mpp, drivable, spec.seed, where,
                                         surface)
            labels = np.where(crowns, CLASS_ID["tree"], labels).astype(np.uint8)
        if g.buildings:
            buildings, fp_mask, report = vector_buildings(base / g.buildings, frame, labels.shape, mpp, drivable,
                                                          g.building_height_m, spec.seed, where, surface)
            labels = np.where(fp_mask, CLASS_ID["building"], labels).astype(np.uint8)
    return _ImageGround(Layout(w * mpp, h * mpp, spec.ground_mpp, rgb, labels, buildings, trees), frame, roads,
                        geo.radiometry if geo is not None else None, road_graph=road_graph, footprints=report)


def _load_georeferenced(path: Path, g: ImageGeneratorSpec, mpp: float, where: str):
    """The image as a :class:`SatelliteMap` in a GeoFrame whose origin is the loaded area's south-west corner."""
    from satloc.geodata.georef import load_map, map_bounds
    from satloc.geoframe import GeoFrame

    def call(fn, *args, **kw):
        try:
            return fn(*args, crs=g.crs, **kw)
        except FormatError as e:
            raise ConfigError(f"{where}: generator.image: {e}") from e
        except ConfigError as e:
            msg = str(e)
            field = "region" if msg.startswith("region") and g.region is not None else next(
                (k for k in ("crs", "bands", "stretch", "alpha") if msg.startswith(k + ":")), "image")
            raise ConfigError(f"{where}: generator.{field}: {msg}") from e

    if g.region is None:                                  # the largest north-up rectangle in the footprint
        probe_frame, _, (x0, y0, x1, y1) = call(map_bounds, path, mpp)
        (lon0, lat0), (lon1, lat1) = probe_frame.to_lonlat(np.array([[x0, y0], [x1, y1]]))
    else:
        lon0, lat0, lon1, lat1 = (float(v) for v in g.region)
        if not (-180 <= lon0 < lon1 <= 180 and -85 <= lat0 < lat1 <= 85):
            raise ConfigError(f"{where}: generator.region: expected [lon_min, lat_min, lon_max, lat_max] in "
                              f"degrees with lon_min < lon_max and lat_min < lat_max, got {list(g.region)}")
    frame = GeoFrame(lon0, lat0)
    ex, ny = frame.to_map(np.array([lon1, lat1]))
    # whole pixels only; a corner from another frame lands within a micrometre of this frame's lattice
    w_m = math.floor(ex / mpp + 1e-6) * mpp
    h_m = math.floor(ny / mpp + 1e-6) * mpp
    if w_m < mpp or h_m < mpp:
        raise ConfigError(f"{where}: generator.region: {list(g.region or ())} is smaller than one "
                          f"{mpp:g} m pixel")
    sm = call(load_map, path, mpp, frame=frame, region=(0.0, 0.0, w_m, h_m), radiometry=g.radiometry)
    ox = sm.origin[0]
    if abs(ox) > 1e-6 or abs(sm.extent[2]) > 1e-6:
        raise ConfigError(f"{where}: generator.image: the loaded map's south-west corner lies at ({ox:.3f}, "
                          f"{sm.extent[2]:.3f}) m of its frame, expected the origin")
    return sm


def _resolve_routes(spec: SceneSpec, ground: _ImageGround | None, lay: Layout, g, base: Path,
                    where: str, graph_out: list | None = None, info: dict | None = None) -> dict[str, RouteSpec]:
    """Every route as waypoints in map metres: ``lonlat`` converted through the geo frame, ``trace`` traced
    from the road mask (or the label image's roads), ``snap`` routes snapped to the road graph; without
    routes, the derived ones (:mod:`satloc_env.world.scene_roads`)."""
    from .roadtrace import RoadTraceError, TraceParams, trace_route
    from .scene_roads import DERIVED_ROUTES, derived_routes, mask_widths, road_graph, snap_waypoints, tour_report

    out: dict[str, RouteSpec] = {}
    traced: dict[TraceSpec, Any] = {}

    @functools.lru_cache(maxsize=1)
    def graph():
        if ground is not None and ground.road_graph is not None:
            rg = ground.road_graph
        else:
            rg = road_graph(spec.road_graph, ground.roads if ground is not None else None, lay.ground_labels,
                            lay.ground_mpp, where)
        if graph_out is not None:
            graph_out.append(rg)
        return rg

    def as_route(xy, widths, closed: bool, laps: int) -> RouteSpec:
        return RouteSpec(waypoints=[(float(x), float(y)) for x, y in xy], closed=closed, laps=laps,
                         widths=[round(float(v), 3) for v in widths])

    if not spec.routes:
        tours = derived_routes(graph(), np.isin(lay.ground_labels, DRIVABLE), lay.ground_mpp, spec.road_graph, where)
        if info is not None:
            info["tour"] = tour_report(tours[0])
        return {k: as_route(t.waypoints, t.widths, t.closed, 1) for k, t in zip(DERIVED_ROUTES, tours)}
    for k, r in spec.routes.items():
        field_ = f"routes.{k}"
        if r.waypoints is not None and r.snap:
            xy, w = snap_waypoints(graph(), np.asarray(r.waypoints, np.float64).reshape(-1, 2), r.closed,
                                   spec.road_graph, f"{field_}.waypoints", where)
            out[k] = as_route(xy, w, r.closed, r.laps)
            continue
        if r.waypoints is not None:
            out[k] = r
            continue
        if r.lonlat is not None:
            frame = ground.frame if ground is not None else None
            if frame is None:
                raise ConfigError(f"{where}: {field_}.lonlat: the scene has no geo frame (lon/lat routes need "
                                  f"an image scene with a georeferenced image); give waypoints in metres")
            xy = frame.to_map(np.asarray(r.lonlat, np.float64).reshape(-1, 2))
            if r.snap:
                xy, w = snap_waypoints(graph(), xy, r.closed, spec.road_graph, f"{field_}.lonlat", where)
                out[k] = as_route(xy, w, r.closed, r.laps)
                continue
            for i, (x, y) in enumerate(xy):
                if not (0 <= x <= lay.width_m and 0 <= y <= lay.height_m):
                    raise ConfigError(f"{where}: {field_}.lonlat[{i}] = {list(r.lonlat[i])} lies outside the "
                                      f"image, at ({x:.1f}, {y:.1f}) m; the image covers lon/lat "
                                      f"{_lonlat_box(frame, lay)} (the largest north-up rectangle inside the "
                                      f"image's footprint: a rotated or reprojected image loses its edges); "
                                      f"with snap: true the point moves onto the nearest road")
            out[k] = RouteSpec(waypoints=[(float(x), float(y)) for x, y in xy], closed=r.closed, laps=r.laps)
            continue
        t = r.trace if isinstance(r.trace, TraceSpec) else TraceSpec()
        if ground is None or (ground.roads is None and not (isinstance(g, ImageGeneratorSpec) and g.labels)):
            raise ConfigError(f"{where}: {field_}.trace: tracing needs a road mask: an image scene with "
                              f"generator.roads (or generator.labels)")
        mask = ground.roads if ground.roads is not None else np.isin(
            lay.ground_labels, (CLASS_ID["road"], CLASS_ID["lane_marking"]))
        src = f"generator.roads ({base / g.roads})" if ground.roads is not None else \
            f"generator.labels ({base / g.labels})"
        key = dataclasses.replace(t, reverse=False)
        if key not in traced:
            try:
                traced[key] = trace_route(mask, lay.ground_mpp, TraceParams(t.smooth_m, t.spacing_m, t.min_length_m,
                                                                             t.prune_m))
            except RoadTraceError as e:
                raise ConfigError(f"{where}: {field_}.trace: {src}: {e}") from e
            except ValueError as e:
                raise ConfigError(f"{where}: {field_}.trace.{e}") from e
        tr = traced[key]
        if r.closed and not tr.closed:
            raise ConfigError(f"{where}: {field_}.closed: the road traced from {src} is not a loop (it has dead "
                              f"ends); drop closed: true")
        pts = tr.waypoints[::-1] if t.reverse else tr.waypoints
        out[k] = as_route(pts, mask_widths(mask, lay.ground_mpp, pts, t.spacing_m, tr.closed), tr.closed, r.laps)
    return out


def _lonlat_box(frame, lay: Layout) -> str:
    (a, b), (c, d) = frame.to_lonlat(np.array([[0.0, 0.0], [lay.width_m, lay.height_m]]))
    return f"[{a:.6f}, {b:.6f}] to [{c:.6f}, {d:.6f}]"


def build_scene(spec: SceneSpec, base_dir: Path | None = None, aliasing: float | None = None,
                where: str | None = None, satellite_gap: float | None = None) -> Scene:
    """Generate the scene described by ``spec`` (deterministic from ``spec.seed``). The returned scene's spec
    has every route as waypoints in metres (lon/lat converted, traced routes traced). ``aliasing`` and
    ``satellite_gap`` (None: the spec's knobs) override the spec's knobs, and the returned spec records them."""
    where = where or f"scene {spec.name!r}"
    base_dir = base_dir or SCENES_DIR
    aliasing = spec.knobs.aliasing if aliasing is None else aliasing
    satellite_gap = spec.knobs.satellite_gap if satellite_gap is None else satellite_gap
    Knobs(aliasing=aliasing, satellite_gap=satellite_gap)
    g = spec.generator_spec(where)
    src = None
    ground = None
    check_spec(spec, where)
    if g.type == "grid":
        params = GridParams(g.style, tuple(g.blocks), g.pitch_m, g.road_width_m, g.sidewalk_m, g.margin_m,
                            float(g.variety))
        if min(g.blocks) < 1 or not (g.pitch_m > 0 and g.road_width_m > 0 and g.sidewalk_m >= 0 and g.margin_m >= 0):
            raise ConfigError(f"{where}: generator: expected blocks >= 1, pitch_m and road_width_m > 0, sidewalk_m "
                              f"and margin_m >= 0, got {to_dict(g)}")
        if not 0.0 <= float(g.variety) <= 1.0:
            raise ConfigError(f"{where}: generator.variety: expected a number from 0 to 1, got {g.variety!r}")
        _check_size(*params.size_m(), spec.ground_mpp, where, "generator", "fewer blocks, a smaller pitch_m or margin_m")
        try:
            lay, src = generate_grid(params, spec.seed, aliasing, spec.ground_mpp)
        except ValueError as e:
            raise ConfigError(f"{where}: {e}") from e
    elif g.type == "vectors":
        from .vector_world import vector_layout

        lay, frame, roads, graph, report = vector_layout(g, spec, base_dir, where, _check_size)
        ground = _ImageGround(lay, frame, roads, None, road_graph=graph, footprints=report)
    else:
        ground = _image_layout(g, spec, base_dir, where)
        lay = ground.layout
    _check_objects_inside(spec, lay.width_m, lay.height_m, where)
    graphs: list = []
    info: dict = {}
    routes = _resolve_routes(spec, ground, lay, g, base_dir, where, graphs, info)
    if not graphs and ground is not None and ground.road_graph is not None:
        graphs.append(ground.road_graph)
    b, t, c = _objects_from_spec(spec.objects)
    lay.buildings += b
    lay.trees += t
    lay.cars += c
    lay.sun_azimuth = math.radians(spec.lighting.sun_azimuth_deg)
    lay.sun_elevation = math.radians(spec.lighting.sun_elevation_deg)
    if g.type in ("grid", "vectors"):   # painted worlds: the tile is a capture of the painted layout
        try:
            tile, tile_labels = capture_tile(lay, spec.meters_per_pixel, spec.seed, satellite_gap, spec.parts)
        except ValueError as e:
            raise ConfigError(f"{where}: {e}") from e
    else:
        tile, tile_labels = capture_image(lay, spec.meters_per_pixel, spec.seed, satellite_gap, spec.parts)
        if g.parked_per_km > 0:   # the camera's own parked cars: not in the map (the image's capture has none)
            from .traffic import parked_cars

            lay.cars += parked_cars(lay, float(g.parked_per_km), np.random.default_rng([spec.seed, 4246]))
    frame = ground.frame if ground is not None else None
    satmap = SatelliteMap(tile, spec.meters_per_pixel, (0.0, lay.height_m), tile_labels, frame,
                          radiometry=ground.radiometry if ground is not None else None)
    spec = replace(spec, routes=routes, knobs=replace(spec.knobs, aliasing=aliasing, satellite_gap=satellite_gap))
    scene = Scene(spec, lay, satmap, src, where=where)
    if graphs:
        scene.__dict__["road_graph"] = graphs[0]
    scene.footprints = ground.footprints if ground is not None else None
    scene.tour = info.get("tour")
    return scene


#: set to 0 to build every scene anew instead of reading it from the disk cache
SCENE_CACHE_ENV = "SATLOC_SCENE_CACHE"


def scene_cache_path(path: str, spec: SceneSpec, base: Path, aliasing: float | None,
                     satellite_gap: float | None) -> Path | None:
    """Where the disk cache keeps the scene ``path`` built with ``aliasing`` and ``satellite_gap``: under
    ``$SATLOC_CACHE/scenes``, named by a digest of the scene's files (its YAML and, for scenes over imagery or map
    vectors, those files), the knobs, the satloc version, the code that builds it (:mod:`satloc_env.world`,
    the data model's modules, :mod:`satloc.geodata`) and the versions of the libraries that paint and read it,
    so that an edit or an upgrade of any of them misses. None where a file cannot be read."""
    import hashlib
    import json

    from satloc import __version__

    from .cache import cache_root, code_digest, library_versions

    h = hashlib.sha256()
    try:
        files = [("scene.yaml", Path(path))]
        g = spec.generator_spec(path)
        if g.type in ("image", "vectors"):
            files += g.files(base)
        for name, f in files:
            h.update(name.encode() + b"\0" + Path(f).read_bytes() + b"\0")
    except (OSError, ConfigError):   # a file missing or unreadable: not cached (building it says what is wrong)
        return None
    import satloc

    sat = Path(satloc.__file__).parent
    code = [code_digest(str(Path(__file__).parent)),            # the world's code
            code_digest(str(sat), recursive=False),             # the data model it builds on (labels, maps, ...)
            code_digest(str(sat / "geodata"))]                  # imagery and map vectors
    libs = library_versions("numpy", "opencv-python-headless", "opencv-python", "trimesh", "shapely", "pyproj",
                            "rasterio", "scikit-image", "scipy", "networkx", "pyogrio")
    h.update(json.dumps([aliasing, satellite_gap, __version__, code, libs]).encode())
    return cache_root() / "scenes" / f"{spec.name}-{h.hexdigest()[:20]}"


@functools.lru_cache(maxsize=4)
def _cached_scene(path: str, aliasing: float | None, satellite_gap: float | None = None) -> Scene:
    """The scene built once per process, and once per machine: a scene built before with the same files, knobs
    and code is read from the disk cache (:func:`scene_cache_path`; 0.3 s for ``city`` against 8-13 s to build it
    on 2 cores). Scenes whose road graph or building footprints come from their data (what :meth:`Scene.save`
    does not keep) are built every time."""
    spec, base = load_spec(path)
    use = os.environ.get(SCENE_CACHE_ENV, "1").strip() not in ("0", "false", "no")
    cached = scene_cache_path(path, spec, base, aliasing, satellite_gap) if use else None
    damaged = False
    if cached is not None and (cached / "scene.json").is_file():
        try:
            scene = Scene.load(cached)
            scene.cache_dir = cached
        except (FormatError, ConfigError, OSError):
            damaged = True   # built again below, and saved over it
        else:
            for message in scene.build_warnings:   # what building it said, said again
                warnings.warn(message, SatlocWarning, stacklevel=3)
            return scene
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", SatlocWarning)
        scene = build_scene(spec, base, aliasing, where=path, satellite_gap=satellite_gap)
    scene.build_warnings = tuple(dict.fromkeys(str(w.message) for w in caught if issubclass(w.category, SatlocWarning)))
    if cached is not None and "road_graph" not in scene.__dict__ and scene.footprints is None:
        try:
            if damaged or not (cached / "scene.json").is_file():   # another process may have saved it meanwhile
                scene.save(cached)
            scene.cache_dir = cached
        except OSError:   # a read-only cache, or another process saved it first: the scene is used all the same
            pass
    for w in caught:   # through the caller's filters now (an error filter raises here, after the build)
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno, source=w.source)
    return scene


def _saved_gap(meta: dict) -> None:
    """A saved scene's ``scene.json`` from before the satellite_gap knob: its tile was the ground's copy, gap 0
    (not today's default)."""
    spec = meta.get("spec")
    if isinstance(spec, dict):
        if spec.get("knobs") is None:
            spec["knobs"] = {}
        if isinstance(spec["knobs"], dict):
            spec["knobs"].setdefault("satellite_gap", 0.0)


def own_satellite_gap(scene: str | os.PathLike) -> float:
    """The satellite gap a scene argument gives by itself: its YAML's ``knobs.satellite_gap`` (default
    :data:`~satloc_env.world.capture.DEFAULT_GAP`), or a saved scene's (0 when saved before the knob)."""
    p = Path(scene).expanduser()
    if p.is_dir() and (p / "scene.json").is_file():
        meta = read_json(p / "scene.json", "scene")
        _saved_gap(meta)
        knobs = (meta.get("spec") or {}).get("knobs") if isinstance(meta.get("spec"), dict) else None
        return float(knobs["satellite_gap"]) if isinstance(knobs, dict) else 0.0   # damaged: Scene.load says so
    return float(load_spec(scene)[0].knobs.satellite_gap)


def load_scene(name_or_path: str | os.PathLike, aliasing: float | None = None,
               satellite_gap: float | None = None) -> Scene:
    """Load a scene by shipped name, YAML path, or saved-scene directory (cached per process). ``aliasing``
    and ``satellite_gap`` (None: the scene file's knobs) override its knobs; a saved scene keeps its own (a
    value other than the saved one is a :class:`satloc.ConfigError`)."""
    p = Path(name_or_path)
    if p.is_dir() and (p / "scene.json").is_file():
        scene = Scene.load(p)
        if satellite_gap is not None and not math.isclose(satellite_gap, scene.spec.knobs.satellite_gap):
            raise ConfigError(f"{p}: a saved scene's satellite map is fixed (satellite_gap "
                              f"{scene.spec.knobs.satellite_gap:g}); got satellite_gap {satellite_gap:g}")
        return scene
    path = str(scene_path(name_or_path).resolve())
    if satellite_gap is None:   # one cache entry for "the file's gap" and that gap given explicitly
        satellite_gap = load_spec(path)[0].knobs.satellite_gap
    return _cached_scene(path, aliasing, float(satellite_gap))
