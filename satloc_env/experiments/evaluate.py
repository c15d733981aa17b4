"""``satloc evaluate``: the method on replayed real sequences (KITTI raw drives, Malaga Urban extracts).

:func:`evaluate` reads a database drive (and optionally a query drive) with the dataset readers of
:mod:`satloc.datasets`, all in ONE :class:`~satloc.geoframe.GeoFrame` (the database's: the query reader gets
``frame=`` it), loads the georeferenced satellite image with :func:`satloc.geodata.georef.load_map` into that frame
over the bounding box of the drive's poses (with ``queries=``: of the database's and of the query drive's
frames within ``coverage_m`` of it, so a query drive may run on beyond the area the image covers) plus
``margin_m``, and then runs the same stages as the synthetic experiments (:mod:`satloc_env.experiments.scene_run`):
build (dictionary + dense satellite features), learn the projections, localize the covered queries in each
mode (GO, NP, full, +align, +track) and draw.

Where the queries come from (exactly one):

* ``queries=``: another drive / extract (read in the database's frame). Its frames are resampled into the
  database camera's intrinsics when its calibration differs (a rectified pinhole pair: an affine warp); its
  baseline, mounting height and pitch must agree with the database's (within 3 %, 0.1 m, 0.02 rad);
* ``split="random:F"``: a seeded random fraction **F of the posed frames is the database** and the other
  1 - F are the queries, e.g. ``random:0.4`` = 40 % database, 60 % queries (the paper's city protocol keeps
  40 % of the frames as the database); ``split_seed`` picks the draw;
* ``split="passes"``: the drive's first pass is the database and the rest are queries. The split is at the
  first frame that comes back within ``passes_near_m`` of an earlier frame driven at least
  ``passes_gap_m`` before it (so standing still or a slow turn is not a return) and heading the same way
  (within ``passes_heading_deg``: candidate poses carry the database path's heading, a pass driven the
  other way cannot be localized against it). A drive that never comes back is an error.

Only queries within ``coverage_m`` of the database path are evaluated (as in the synthetic experiments);
every ``query_stride``-th of them. The tracked modes get the odometry between consecutive evaluated queries
from ``odometry``: ``visual`` (the default: stereo visual odometry over every frame of the drive between them,
:mod:`satloc.tracking.vo`), ``oxts`` (KITTI's forward speed and yaw rate, integrated) or ``noisy_truth`` (their true
poses plus noise).

``resolution``: ``"half"`` resizes images and camera by 1/2 (KITTI 1242x375 -> 621x188, the scale the
method and its shipped FCN are tuned for: the simulator's 620x188 at fx 361; Malaga 1024x768 -> 512x384,
800x600 -> 400x300); ``"full"`` keeps the data's size.

``satellite="lidar-mosaic"`` (the literal value; KITTI drives only): no satellite image, but a stand-in made
from the database drive's own images placed with its LiDAR (:mod:`satloc.datasets.lidar_mosaic`), written to
``out/lidar_mosaic.tif`` (with its record ``lidar_mosaic.tif.json``; reused while made from the same drive files
and settings) and then used as the satellite image. The map is made from the same images that are localized, so
this is a **self-consistency check** of the data, calibration and pipeline, not an evaluation against satellite
imagery: ``summary.json``'s ``map_kind`` says so, and the sequence in ``results.csv`` / ``results.md`` carries
``[lidar-mosaic self-check]``.

``satellite_bands`` and ``satellite_stretch`` choose the satellite image's bands and its conversion to 8 bits
(:class:`satloc.geodata.radiometry.Radiometry`: by default the image's colour bands, 8-bit samples as stored and any
other type stretched per band from its 0.5-99.5 % percentiles); ``summary.json`` records what was applied
(``map.radiometry``).

The output folder ``out`` holds::

    map/                       the satellite map in the frame (SatelliteMap layout), reused by later runs
                               while the files it was read from (image, world file, .prj, tiles) are unchanged
    build/                     dictionary, satellite features, projections (satloc build / train-projection)
    map_stage.json, build_stage.json, projection_stage.json     stage stamps: a stage is redone only when
                               its inputs or configuration change
    localization_<mode>.npz/.json, summary.json, errors_along_route.png, posterior_<mode>_q<i>.png
    results.csv                method,sequence,mean_m,std_m,median_m,within_1m,queries
    results.md                 the same as a markdown table
"""
from __future__ import annotations

import csv
import hashlib
import math
import re
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from satloc.config import added_field, from_dict, to_dict
from satloc.datasets import load_kitti, load_malaga
from satloc.datasets.kitti import CAMERAS, IMU_HEIGHT_M, MISSING
from satloc.datasets.malaga import MalagaConfig
from satloc.errors import ConfigError, SatlocWarning
from satloc.features.context import ContextConfig
from satloc.features.projection import ProjectionConfig
from satloc.geodata.radiometry import Radiometry
from satloc.geoframe import GeoFrame
from satloc.geometry import StereoCamera, arc_length, wrap_angle
from satloc.persist import atomic_dir, atomic_path, write_json
from satloc.satmap import SatelliteMap
from satloc.sequence import Sequence

from .scene_run import (
    METHOD_NAMES,
    MODES,
    CrossAreaConfig,
    _stage_done,
    _stamp,
    build_and_learn,
    covered_queries,
    is_tracked,
    localize_and_report,
    tracked_odometry,
)

RESOLUTIONS = ("half", "full")
LIDAR_MOSAIC = "lidar-mosaic"   # the satellite= value that makes the map from the database drive itself
MAP_KINDS = {"image": "satellite imagery",
             LIDAR_MOSAIC: "lidar-mosaic (self-consistency check, not satellite imagery)"}


@dataclass
class KittiOptions:
    """Keyword arguments of :func:`satloc.datasets.load_kitti`."""

    camera: str = "color"            # "color" (image_02/03) or "gray" (image_00/01)
    missing: str = "skip"            # frames without a left/right image or OXTS file: "skip" or "error"
    imu_height: float = IMU_HEIGHT_M  # the IMU's height above the road (KITTI's sensor setup)


@dataclass
class EvaluateConfig:
    resolution: str = "half"                 # "half": images and camera / 2; "full": the data's size
    mpp: float = 0.2                         # satellite map metres per pixel
    margin_m: float = 60.0                   # the map covers every pose's bounding box plus this
    satellite_crs: str | None = None         # CRS of a satellite image that carries none (load_map's crs=)
    satellite_zoom: int | None = None        # zoom level of an XYZ tile folder (default: the highest)
    satellite_bands: Any = None              # bands of the satellite image: [r, g, b] or [grey], from 1 (GDAL's)
    satellite_stretch: Any = "auto"          # to 8 bits: auto, none, [low, high], [[low, high], ...]
                                             # (satloc.geodata.radiometry; auto: 8 bit as stored, else 0.5-99.5 %)
    split: str = "random:0.4"                # without queries=: "random:F" (F = database fraction) or "passes"
    split_seed: int = 0
    passes_near_m: float = 5.0               # passes: a frame this close to an earlier one has come back ...
    passes_gap_m: float = 50.0               # ... if that one was driven at least this much earlier ...
    passes_heading_deg: float = 60.0         # ... heading the same way within this
    coverage_m: float = 5.0                  # evaluate queries whose true pose is this close to the database path
    query_stride: int = 1                    # evaluate every n-th covered query
    features: str = "default"
    context: ContextConfig = field(default_factory=ContextConfig)
    projection: ProjectionConfig = field(default_factory=ProjectionConfig)
    localizer: dict = field(default_factory=dict)   # LocalizerConfig fields other than mode
    modes: tuple[str, ...] = MODES
    odometry: str = "visual"                 # tracked modes: visual (stereo VO of the drive's frames), oxts
                                             # (KITTI's speed and yaw rate) or noisy_truth (poses plus noise)
    odometry_noise: tuple[float, float] = (0.02, 0.01)  # noisy_truth: std (fraction of the distance, radians)
    odometry_scale_error: float = 0.0        # noisy_truth: drift, fraction of the distance
    odometry_yaw_bias: float = 0.0           # noisy_truth: drift, radians per metre
    odometry_seed: int = 0
    kitti: KittiOptions = field(default_factory=KittiOptions)
    malaga: MalagaConfig = field(default_factory=MalagaConfig)
    # also localize the same queries with no database (satloc.localizers.crossview), each from a prior drawn around its
    # pose (the OXTS / GPS fix) within cross_area.prior_radius_m, single and tracked by the same odometry
    no_database: bool = False
    cross_area: CrossAreaConfig = field(default_factory=CrossAreaConfig)   # also every query's GPS-like prior
    # beside the modes (satloc_env.experiments.grading): the reference floors and a user's localizers
    # ("module:Name" or "path/to/file.py:Name"), each with the database drive, the queries' priors (drawn around
    # their OXTS / GPS poses as cross_area says) and the tracked modes' odometry
    references: tuple[str, ...] = added_field(("prior", "dead-reckoning"), before=())
    localizers: tuple[str, ...] = added_field(())

    def __post_init__(self):
        if self.resolution not in RESOLUTIONS:
            raise ConfigError(f"resolution: expected one of {list(RESOLUTIONS)}, got {self.resolution!r}")
        for name in ("mpp", "passes_near_m", "coverage_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"{name}: expected a positive number of metres, got {v!r}")
        for name in ("margin_m", "passes_gap_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"{name}: expected a non-negative number of metres, got {v!r}")
        if not 0 < self.passes_heading_deg <= 180:
            raise ConfigError(f"passes_heading_deg: expected degrees in (0, 180], got {self.passes_heading_deg!r}")
        if self.query_stride < 1:
            raise ConfigError(f"query_stride: expected an integer >= 1, got {self.query_stride!r}")
        parse_split(self.split)
        self.satellite_radiometry  # bad satellite_bands or satellite_stretch: ConfigError naming the field
        if len(self.odometry_noise) != 2 or min(self.odometry_noise) < 0:
            raise ConfigError(f"odometry_noise: expected 2 non-negative numbers, got {list(self.odometry_noise)}")
        if self.odometry not in ("visual", "oxts", "noisy_truth"):
            raise ConfigError(f"odometry: expected 'visual', 'oxts' or 'noisy_truth', got {self.odometry!r}")
        bad = [m for m in self.modes if m not in METHOD_NAMES]
        if bad or not self.modes:
            raise ConfigError(f"modes: unknown {bad}; expected a non-empty subset of {list(METHOD_NAMES)}")
        from .grading import check_extra

        check_extra(self)
        if self.kitti.camera not in CAMERAS or self.kitti.missing not in MISSING:
            raise ConfigError(f"kitti: expected camera in {sorted(CAMERAS)} and missing in {list(MISSING)}, got "
                              f"camera {self.kitti.camera!r}, missing {self.kitti.missing!r}")

    @property
    def satellite_radiometry(self) -> Radiometry:
        """The :class:`satloc.geodata.radiometry.Radiometry` of ``satellite_bands`` and ``satellite_stretch``."""
        try:
            return Radiometry(self.satellite_bands, self.satellite_stretch)
        except ConfigError as e:
            raise ConfigError(f"satellite_{e}") from e


# --- splits ----------------------------------------------------------------------------------------------

def parse_split(text: str) -> tuple[str, float | None]:
    """``"random:F"`` -> ("random", F) with 0 < F < 1 (F: the database's fraction); ``"passes"`` -> ("passes",
    None); anything else raises :class:`ConfigError`."""
    if text == "passes":
        return "passes", None
    m = re.fullmatch(r"random:([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)", text.strip()) if isinstance(text, str) else None
    f = float(m.group(1)) if m else math.nan
    if not (0.0 < f < 1.0):
        raise ConfigError(f"split: expected 'random:F' with 0 < F < 1 (F: the fraction of frames that form the "
                          f"database, e.g. random:0.4 = 40 % database, 60 % queries) or 'passes', got {text!r}")
    return "random", f


def random_split(poses: np.ndarray, fraction: float, seed: int = 0,
                 where: str = "split") -> tuple[np.ndarray, np.ndarray]:
    """(database, query) frame indices: a seeded random ``fraction`` of the posed frames is the database, the
    rest the queries (both sorted). Raises :class:`ConfigError` when one side would be empty."""
    posed = np.flatnonzero(np.all(np.isfinite(poses), axis=1))
    n_db = int(math.floor(fraction * len(posed) + 0.5))
    if n_db == 0:
        raise ConfigError(f"{where}: random:{fraction:g} of {len(posed)} posed frames leaves no database frame; "
                          f"use a larger fraction")
    if n_db >= len(posed):
        raise ConfigError(f"{where}: random:{fraction:g} of {len(posed)} posed frames leaves no query frame; "
                          f"use a smaller fraction")
    perm = np.random.default_rng(seed).permutation(len(posed))
    return np.sort(posed[perm[:n_db]]), np.sort(posed[perm[n_db:]])


def passes_split(poses: np.ndarray, near_m: float = 5.0, gap_m: float = 50.0, heading_deg: float = 60.0,
                 where: str = "split passes") -> tuple[np.ndarray, np.ndarray, int]:
    """(database, query, return frame): the posed frames before the first frame that comes back within
    ``near_m`` of an earlier frame driven more than ``gap_m`` before it, heading the same way within
    ``heading_deg``, are the database; that frame and the posed frames after it are the queries."""
    from scipy.spatial import cKDTree

    posed = np.flatnonzero(np.all(np.isfinite(poses), axis=1))
    if len(posed) < 2:
        raise ConfigError(f"{where}: the drive has {len(posed)} posed frame(s); a split needs more")
    p = np.asarray(poses, np.float64)[posed]
    s = arc_length(p[:, :2])
    tree = cKDTree(p[:, :2])
    max_turn = math.radians(heading_deg)
    for k in range(1, len(p)):
        near = [j for j in tree.query_ball_point(p[k, :2], near_m)
                if j < k and s[k] - s[j] > gap_m and abs(wrap_angle(p[k, 2] - p[j, 2])) <= max_turn]
        if near:
            return posed[:k], posed[k:], int(posed[k])
    raise ConfigError(f"{where}: the drive ({s[-1]:.0f} m, {len(posed)} posed frames) never comes back within "
                      f"{near_m:g} m of a part of itself driven more than {gap_m:g} m earlier in the same "
                      f"direction, so it has no second pass to use as queries; use --split random:F or --queries")


# --- frames at the evaluation's camera ---------------------------------------------------------------------

def output_camera(camera: StereoCamera, resolution: str) -> StereoCamera:
    """The camera of the frames evaluated: ``half`` halves the image size (rounded) and scales the
    intrinsics to match; ``full`` is the data's camera."""
    if resolution == "full":
        return camera
    if resolution != "half":
        raise ConfigError(f"resolution: expected one of {list(RESOLUTIONS)}, got {resolution!r}")
    return camera.resized(int(math.floor(camera.width / 2 + 0.5)), int(math.floor(camera.height / 2 + 0.5)))


def check_query_camera(q: StereoCamera, db: StereoCamera, where: str) -> None:
    """Queries are resampled into the database camera's intrinsics, but the rig must be the same: baseline
    within 3 %, mounting height within 0.1 m, pitch within 0.02 rad."""
    bad = db.rig_differences(q)
    if bad:
        raise ConfigError(f"{where}: the query rig differs from the database's ({'; '.join(bad)}); the localizer "
                          "uses the database camera for both")


# --- the whole evaluation ----------------------------------------------------------------------------------

def _read(path, reader: str, cfg: EvaluateConfig, frame: GeoFrame | None) -> Sequence:
    if reader == "kitti":
        return load_kitti(path, frame, camera=cfg.kitti.camera, missing=cfg.kitti.missing,
                          imu_height=cfg.kitti.imu_height)
    return load_malaga(path, frame, cfg.malaga)


def _files_stamp(path: Path, zoom: int | None) -> dict:
    """Size and modification time of every file a load of ``path`` reads (the image and its world file,
    ``.prj`` and ``.aux.xml`` sidecars; every tile of a tile folder's zoom level), as a count and a digest."""
    from satloc.geodata.georef import input_files

    base = path if path.is_dir() else path.parent
    h = hashlib.sha1()
    files = input_files(path, zoom)
    for f in files:
        st = f.stat()
        h.update(f"{f.relative_to(base)}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return {"count": len(files), "sha1": h.hexdigest()}


def _sequence_stamp(seq: Sequence) -> dict:
    poses = np.ascontiguousarray(seq.poses, np.float64)
    return {"frames": len(seq), "camera": seq.camera.to_dict(),
            "poses_sha1": hashlib.sha1(np.nan_to_num(poses, nan=1e300).tobytes()).hexdigest()}


def load_satellite(path: str | Path, cfg: EvaluateConfig, frame: GeoFrame, poses: np.ndarray, out: Path,
                   log=print) -> tuple[SatelliteMap, dict, float]:
    """The satellite map over the bounding box of ``poses`` plus ``cfg.margin_m`` in ``frame`` at ``cfg.mpp``,
    from ``out/map`` when an earlier run saved it for the same inputs, else loaded with
    :func:`satloc.geodata.georef.load_map` and saved there. Returns the map, its stage stamp and the seconds taken."""
    from satloc.geodata.georef import load_map

    t = time.perf_counter()
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"satellite map {path}: file or tile folder not found")
    xy = poses[np.all(np.isfinite(poses), axis=1), :2]
    m = cfg.margin_m
    region = (float(xy[:, 0].min() - m), float(xy[:, 1].min() - m), float(xy[:, 0].max() + m),
              float(xy[:, 1].max() + m))
    stamp = {"satellite": str(path.resolve()), "satellite_files": _files_stamp(path, cfg.satellite_zoom),
             "mpp": cfg.mpp, "region": [round(v, 3) for v in region], "geo_frame": frame.to_dict(),
             "crs": cfg.satellite_crs, "zoom": cfg.satellite_zoom,
             "radiometry": cfg.satellite_radiometry.to_dict()}
    mdir = out / "map"
    if _stage_done(out / "map_stage.json", stamp) and (mdir / "map.json").is_file():
        return SatelliteMap.load(mdir), stamp, time.perf_counter() - t
    log(f"loading the satellite map {path} at {cfg.mpp:g} m/px over x [{region[0]:.0f}, {region[2]:.0f}] "
        f"y [{region[1]:.0f}, {region[3]:.0f}] m (every pose plus {m:g} m)")
    try:
        sm = load_map(path, cfg.mpp, frame=frame, region=region, crs=cfg.satellite_crs, zoom=cfg.satellite_zoom,
                      radiometry=cfg.satellite_radiometry)
    except ConfigError as e:
        if str(e).startswith("region:"):
            raise ConfigError(f"satellite map {path} does not cover the route and its {m:g} m margin: use a larger "
                              f"image or lower margin_m (an EvaluateConfig field; with satloc evaluate: a YAML file "
                              f"holding e.g. 'margin_m: 20' passed as --config cfg.yaml): {e}") from e
        if str(e).startswith(("bands:", "stretch:")):
            raise ConfigError(f"satellite_{e}") from e
        raise
    log(f"satellite map radiometry: {sm.radiometry}")
    with atomic_dir(mdir) as tmp:
        sm.save(tmp)
    _stamp(out / "map_stage.json", stamp)
    return sm, stamp, time.perf_counter() - t


def evaluate(database: str | Path, satellite: str | Path, out: str | Path, config: EvaluateConfig | dict | None = None,
             queries: str | Path | None = None, reader: str = "kitti", progress: bool = True, log=print) -> dict:
    """Evaluate the method on real data (see the module docstring); returns the summary written to
    ``out/summary.json``. ``reader``: ``"kitti"`` (``database``/``queries`` are KITTI raw drive folders) or
    ``"malaga"`` (Malaga Urban extract folders). ``satellite``: the image, or ``"lidar-mosaic"`` (a map made from
    the database drive itself: a self-consistency check, see the module docstring)."""
    cfg = config if isinstance(config, EvaluateConfig) else from_dict(EvaluateConfig, config or {}, "evaluate config")
    if reader not in ("kitti", "malaga"):
        raise ConfigError(f"reader: expected 'kitti' or 'malaga', got {reader!r}")
    mosaic = isinstance(satellite, str) and satellite == LIDAR_MOSAIC
    if mosaic and reader != "kitti":
        raise ConfigError(f"satellite {LIDAR_MOSAIC}: made from a KITTI raw drive's LiDAR (--database), not from a "
                          f"{reader} extract ({database}); give a georeferenced satellite image with --satellite")
    out = Path(out)
    times: dict[str, float] = {}
    t = time.perf_counter()
    full = _read(database, reader, cfg, None)
    frame = full.geo_frame
    camera = output_camera(full.camera, cfg.resolution)
    name = full.name
    if queries is not None:
        qfull = _read(queries, reader, cfg, frame)
        check_query_camera(output_camera(qfull.camera, cfg.resolution), camera, f"queries {queries}")
        posed = np.flatnonzero(np.all(np.isfinite(full.poses), axis=1))
        db = full.view(posed, camera)
        q = qfull.view(None, camera)
        parent, in_parent = q, np.arange(len(q))   # the drive the queries are frames of, and where
        split = f"queries from {Path(queries).resolve()}"
        name = f"{full.name} / {qfull.name}"
    else:
        kind, fraction = parse_split(cfg.split)
        if kind == "random":
            di, qi = random_split(full.poses, fraction, cfg.split_seed, where=f"split of {database}")
            split = f"random:{fraction:g} (seed {cfg.split_seed}): {len(di)} database frames, {len(qi)} queries"
        else:
            di, qi, back = passes_split(full.poses, cfg.passes_near_m, cfg.passes_gap_m, cfg.passes_heading_deg,
                                        where=f"split passes of {database}")
            split = f"passes: frames before {back} (first pass) database, from {back} on queries"
        db, q = full.view(di, camera), full.view(qi, camera, name=f"{full.name} queries")
        parent, in_parent = full.view(None, camera), np.asarray(qi)
    if len(db) < 2:
        raise ConfigError(f"{database}: the database has {len(db)} posed frame(s); the method needs at least 2")
    covered = covered_queries(db, q, cfg.coverage_m)
    sel = covered[::cfg.query_stride]
    if len(sel) == 0:
        raise ConfigError(f"{queries or database}: no query frame lies within {cfg.coverage_m:g} m of the database "
                          f"path (split: {split})")
    times["read_s"] = time.perf_counter() - t
    log(f"[{name}] {split}; {len(sel)} queries within {cfg.coverage_m:g} m of the database path")

    out.mkdir(parents=True, exist_ok=True)
    # the map covers the drive (whatever the split), or the database and the query drive's frames near it
    poses = full.poses if queries is None else np.concatenate([db.poses, q.poses[covered]])
    made = None
    if mosaic:
        from satloc.datasets.lidar_mosaic import ensure_lidar_mosaic

        log(f"[{name}] --satellite {LIDAR_MOSAIC}: the map is made from this drive's own images and LiDAR, so "
            f"the results are a self-consistency check, not an evaluation against satellite imagery")
        t = time.perf_counter()
        satellite = out / "lidar_mosaic.tif"   # over the drive's poses, and the queries within coverage_m of them
        made = ensure_lidar_mosaic(database, satellite, cfg.mpp, cfg.margin_m + cfg.coverage_m + 1.0 + 2 * cfg.mpp,
                                   log=log)
        times["lidar_mosaic_s"] = time.perf_counter() - t
    with warnings.catch_warnings():
        if mosaic:   # black beyond the road by construction (its covered fraction is logged above)
            warnings.filterwarnings("ignore", message=".*is mostly dark after conversion", category=SatlocWarning)
        sm, map_stamp, times["map_s"] = load_satellite(satellite, cfg, frame, poses, out, log)
    source = {"data": {"reader": reader, "database": str(Path(database).resolve()),
                       "options": to_dict(cfg.kitti if reader == "kitti" else cfg.malaga),
                       "resolution": cfg.resolution, "sequence": _sequence_stamp(db)},
              "map": map_stamp}
    bdir, more = build_and_learn(cfg, name, db, out / "map", out, source, progress, log)
    times.update(more)
    head = {"sequence": name, "reader": reader, "database": str(Path(database).resolve()),
            "queries_from": str(Path(queries).resolve()) if queries is not None else None, "split": split,
            "satellite": str(Path(satellite).resolve()), "map_kind": MAP_KINDS[LIDAR_MOSAIC if mosaic else "image"],
            "geo_frame": frame.to_dict(),
            "map": {"meters_per_pixel": sm.meters_per_pixel, "size_px": [int(sm.shape[1]), int(sm.shape[0])],
                    "extent_m": [round(v, 2) for v in sm.extent], "radiometry": sm.radiometry},
            "camera": camera.to_dict(), "config": to_dict(cfg)}
    odo = None
    if is_tracked(cfg):   # between the queries, over every frame of their drive
        if cfg.odometry == "oxts" and reader != "kitti":
            raise ConfigError("odometry: 'oxts' is KITTI's; give visual or noisy_truth for this reader")
        t = time.perf_counter()
        odo = tracked_odometry(cfg, parent, in_parent[sel], out / "odometry_visual.npz")
        times["odometry_s"] = time.perf_counter() - t
    if made is not None:
        head["lidar_mosaic"] = {k: made[k] for k in ("covered_fraction", "size_px", "frames_used",
                                                     "frames_without_lidar", "frames_without_ground", "lidar",
                                                     "reused")}
    summary = localize_and_report(cfg, name, db, q, sel, bdir, sm, out, head, times, progress, log, odo)
    if cfg.no_database:   # the same queries against the satellite map alone, from priors around their poses
        from .cross_area import CROSS_NAMES, run_cross

        t = time.perf_counter()
        codo = odo if odo is not None else tracked_odometry(cfg, parent, in_parent[sel], out / "odometry_visual.npz")
        res = run_cross(q, sel, cfg.cross_area, codo, cfg.odometry, out / "cross_area", db.poses, name, sm, None,
                        progress, log)
        summary["no_database"] = {row: {k: v for k, v in m.items() if not isinstance(v, np.ndarray)}
                                  for row, m in res.items()}
        summary["no_database_names"] = dict(CROSS_NAMES)
        times["no_database_s"] = time.perf_counter() - t
        write_json(out / "summary.json", summary)
    write_results(out, summary, f"{name} [{LIDAR_MOSAIC} self-check]" if mosaic else name)
    return summary


def result_rows(summary: dict, sequence: str) -> list[dict]:
    rows = []
    for mode, m in summary["modes"].items():
        rows.append({"method": METHOD_NAMES[mode], "sequence": sequence, "mean_m": m["mean_m"], "std_m": m["std_m"],
                     "median_m": m["median_m"], "within_1m": m["within_1m"], "queries": m["queries"]})
    names = summary.get("no_database_names", {})
    for row, m in summary.get("no_database", {}).items():
        rows.append({"method": names.get(row, row), "sequence": sequence, "mean_m": m["mean_m"], "std_m": m["std_m"],
                     "median_m": m["median_m"], "within_1m": m["within_1m"], "queries": m["queries"]})
    for key, m in summary.get("localizers", {}).items():   # the reference floors and a user's localizers
        rows.append({"method": m.get("name", key), "sequence": sequence, "mean_m": m["mean_m"], "std_m": m["std_m"],
                     "median_m": m["median_m"], "within_1m": m["within_1m"], "queries": m["queries"]})
    return rows


def _num(v, digits: int = 3) -> str:
    return "" if v is None or not math.isfinite(v) else f"{v:.{digits}f}"


def write_results(out: Path, summary: dict, sequence: str) -> list[dict]:
    """``results.csv`` (method,sequence,mean_m,std_m,median_m,within_1m,queries) and ``results.md``."""
    rows = result_rows(summary, sequence)
    cols = ["method", "sequence", "mean_m", "std_m", "median_m", "within_1m", "queries"]
    with atomic_path(out / "results.csv", suffix=".csv") as tmp:
        with open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(cols)
            for r in rows:
                w.writerow([r["method"], r["sequence"], _num(r["mean_m"]), _num(r["std_m"]), _num(r["median_m"]),
                            _num(r["within_1m"]), r["queries"]])
    lines = [f"| method | {sequence}: mean (std) m | median m | within 1 m | queries |", "|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['method']} | {_num(r['mean_m'], 2)} ({_num(r['std_m'], 2)}) | {_num(r['median_m'], 2)} | "
                     f"{100 * r['within_1m']:.0f} % | {r['queries']} |")
    with atomic_path(out / "results.md", suffix=".md") as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return rows
