"""Experiments on simulated scenes: the whole pipeline from recording to errors and pictures.

:func:`run_scene` records a scene's database and query passes (revisit mode: the query pass drives another
lane, with other appearance and occluders), builds the dictionary, learns the projections, localizes the
queries with the ablations GO, NP and full (single images, refined by bird's-eye alignment, and tracked
over the query sequence with simulated odometry), and writes per-mode results and pictures. :func:`table1` runs
every method (the modes and the baselines FAB-MAP and EFM, :mod:`satloc_env.experiments.tables`) on several scenes under
the protocols ``revisit`` (the above), ``city`` (a seeded random 40 % of the database pass is the database, the
rest the queries) and ``residential`` (the database pass and a second pass, both at one frame per second), each
protocol's dictionary and projections learned on its own database frames only, and writes ``table1.csv``
(:data:`satloc_env.experiments.tables.TABLE1_COLUMNS`). Every table row follows one rule (:func:`table_stats`): a query
a method does not answer is a gross failure, counted with the worst answer on the map.
``satloc demo`` and ``satloc experiment table1`` call these. :func:`aliasing` (``satloc experiment aliasing``) measures, on the same
folders, how often each single-image cue scores a place more than 10 m away above the truth.

Every stage's output is kept in the experiment folder and reused when the folder is run again with the same
configuration (delete the folder to start over).

The two halves are shared with ``satloc evaluate`` (:mod:`satloc_env.experiments.evaluate`, real data): :func:`build_and_learn`
(build + projections, with stage stamps) and :func:`localize_and_report` (every mode on any database/query pair
and satellite map: ``localization_<mode>.*``, ``summary.json`` and the pictures).
"""
from __future__ import annotations

import csv
import dataclasses
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from satloc.baselines import EfmConfig, FabMapConfig
from satloc.config import added_field, from_dict, to_dict
from satloc.errors import ConfigError, FormatError
from satloc.features.context import ContextConfig
from satloc.features.pixelwise import features_identity
from satloc.features.projection import ProjectionConfig
from satloc.geometry import Pose2, wrap_angle
from satloc.localizers.crossview import CrossViewConfig, Prior
from satloc.localizers.database import Localization, LocalizerConfig
from satloc.localizers.gnss import GnssConfig
from satloc.persist import atomic_path, header, read_json, write_json
from satloc.pipeline import BuildConfig, build, load_localizer, train_projection
from satloc.satmap import SatelliteMap
from satloc.sequence import Sequence
from satloc.tracking.track import compose_between, noisy_odometry
from satloc_env.envs.record import (
    QUERY_CHANGE,
    PassConfig,
    RecordConfig,
    check_passes,
    pass_routes,
    record_passes,
    record_stamp,
)
from satloc_env.envs.vehicle import DEFAULT_SPEED_WANDER, DEFAULT_WANDER_M
from satloc_env.world.revisit import PARTS as REVISIT_PARTS
from satloc_env.world.revisit import check_parts
from satloc_env.world.scene import load_scene

from .grading import table_stats  # noqa: F401  (the tables import it from here)

# "<mode>[+track][+align]": tracked over the query sequence with odometry (satloc.tracking.track), refined by bird's-eye
# alignment (satloc.tracking.align)
MODES = ("go", "np", "full", "full+align", "go+track", "np+track", "full+track", "full+track+align")
_BASE_NAMES = {"go": "Ours-GO", "np": "Ours-NP", "full": "Ours-full"}
_SUFFIX_NAMES = {"track": "track", "align": "BEV align"}
METHOD_NAMES = {b + "".join("+" + s for s in suf): " + ".join([name] + [_SUFFIX_NAMES[s] for s in suf])
                for b, name in _BASE_NAMES.items() for suf in ((), ("align",), ("track",), ("track", "align"))}


BASELINES = ("fabmap", "fabmap+seq", "efm")
BASELINE_NAMES = {"fabmap": "FAB-MAP", "fabmap+seq": "FAB-MAP + seq", "efm": "EFM"}


@dataclass
class CompareConfig:
    """The baselines' part of a comparison (:mod:`satloc_env.experiments.tables`; the method's part is an
    :class:`ExperimentConfig`)."""

    baselines: tuple[str, ...] = BASELINES
    fabmap: FabMapConfig = field(default_factory=FabMapConfig)
    efm: EfmConfig = field(default_factory=EfmConfig)
    fabmap_train_scene: str | None = None   # None: residential for city, city for any other scene
    fabmap_train_frames: int = 300
    fabmap_train_spacing_m: float = 2.0
    database_step: int = 1                  # the baselines' database: every this many database frames (EFM's
                                            # time per query grows with the database's image count)
    fabmap_motion_window: int | None = None  # fabmap+seq: places within this many database places are adjacent
                                            # (None: the median query step over the median place spacing, + 1)

    def __post_init__(self):
        if self.database_step < 1:
            raise ConfigError(f"database_step: expected an integer >= 1, got {self.database_step}")
        bad = [b for b in self.baselines if b not in BASELINES]
        if bad:
            raise ConfigError(f"baselines: unknown {bad}; expected a subset of {list(BASELINES)}")
        if self.fabmap_train_frames < 2:
            raise ConfigError(f"fabmap_train_frames: expected an integer >= 2, got {self.fabmap_train_frames}")
        if self.fabmap_train_spacing_m <= 0:
            raise ConfigError(f"fabmap_train_spacing_m: expected > 0, got {self.fabmap_train_spacing_m}")
        if self.fabmap_motion_window is not None and self.fabmap_motion_window < 0:
            raise ConfigError(f"fabmap_motion_window: expected an integer >= 0 or null, got {self.fabmap_motion_window}")

    def train_scene(self, test_scene: str) -> str:
        if self.fabmap_train_scene is not None:
            return self.fabmap_train_scene
        return "residential" if scene_label(test_scene) == "city" else "city"


@dataclass
class CrossAreaConfig:
    """Table I's ``cross-area`` protocol (:mod:`satloc_env.experiments.cross_area`): the revisit queries localized
    with no database (:mod:`satloc.localizers.crossview`), each from a prior drawn around its true pose (seeded per query)."""

    prior_radius_m: float = 20.0
    prior_yaw_deg: float = 10.0
    seed: int = 0
    crossview: CrossViewConfig = field(default_factory=CrossViewConfig)
    # how each prior's centre strays from the truth (satloc.localizers.gnss): "uniform" (the default) within the
    # radius and heading range, query by query; "receiver", a receiver's time-correlated error with multipath
    # jumps and outages over the query pass's timeline (a query in an outage has no prior: the tracked rows follow
    # their track, the single-frame rows give no answer)
    gnss: GnssConfig = added_field(GnssConfig())

    def __post_init__(self):
        Prior(0.0, 0.0, 0.0, self.prior_radius_m, self.prior_yaw_deg)   # the same checks as a prior's


PROTOCOLS = ("revisit", "city", "residential", "cross-area", "kitti-city")
#: the paper's KITTI-City protocol as it ran it: one drive of 1,067 frames over 822.9 m (KITTI raw's frames at
#: 10 Hz, one every 0.77 m), a seeded random 40 % of them the database and the rest the queries. Here: a pass of
#: the scene's database route (its lane and conditions) at KITTI_CITY_SPEED_MPS, a frame at every 0.1 s step
KITTI_CITY_LENGTH_M = 822.9
KITTI_CITY_SPEED_MPS = 7.7
#: the seed of the kitti-city protocol's pass (its drift, its speed's)
KITTI_CITY_SEED = 3
#: the protocols a Table I configuration runs by default (cross-area: satloc_env.experiments.cross_area)
DEFAULT_PROTOCOLS = ("revisit", "city", "residential")
#: odometry sources of the tracked modes: ``visual``, stereo visual odometry of the recorded frames
#: (satloc.tracking.vo: the passes are recorded a frame every DENSE_SPACING_M metres and the queries taken from them as
#: far apart as the pass asks, spaced_frames; the odometry between two queries composed over the frames between
#: them); ``noisy_truth``, the true
#: motion between queries plus noise and drift (satloc.tracking.track.noisy_odometry)
ODOMETRY = ("visual", "noisy_truth")
#: frame spacing (metres) of passes whose queries are tracked by visual odometry
DENSE_SPACING_M = 1.0
#: the seed of Table I's residential protocol's second pass (satloc_env.experiments.tables._protocol)
SECOND_PASS_SEED = 2


@dataclass
class ExperimentConfig:
    scene: str = "city"
    aliasing: float | None = None           # the scene's aliasing knob (None: the scene file's value)
    database_frames: int | None = None      # stop the database pass early (None: the whole route)
    query_frames: int | None = None
    query_spacing_m: float = 10.0
    query_lane_m: float = -0.75             # revisit mode: another lane than the database's -1.75 m ...
    occlusion: float = 0.3                  # ... with occluders and another appearance ...
    appearance: float = 0.5
    change: float = QUERY_CHANGE            # ... and the world changed as on another day (satloc_env.world.revisit)
    change_parts: tuple[str, ...] = added_field(REVISIT_PARTS)   # which parts of that change (the revisit pass's and
                                            # the residential protocol's second pass's; satloc_env.world.revisit.PARTS)
    satellite_gap: float | None = added_field(None)   # the map as a capture (satloc_env.world.capture); None: scene's
    wander_m: float = added_field(DEFAULT_WANDER_M, before=0.0)          # both passes' lateral drift (std, m)
    speed_wander: float = added_field(DEFAULT_SPEED_WANDER, before=0.0)  # and speed drift (relative std), each
                                            # pass seeded by its own seed (satloc_env.envs.vehicle.Wander)
    coverage_m: float = 5.0                 # evaluate queries whose true pose is this close to the database path
    coverage_yaw_deg: float = added_field(45.0, before=180.0)   # ... and heading within this of a database frame's
                                            # there (180: any; a query crossing the path at an intersection is out)
    features: str = "default"
    context: ContextConfig = field(default_factory=ContextConfig)
    projection: ProjectionConfig = field(default_factory=ProjectionConfig)
    localizer: dict = field(default_factory=dict)   # LocalizerConfig fields other than mode
    modes: tuple[str, ...] = MODES
    odometry: str = "visual"                # tracked modes: what moves the belief between queries (ODOMETRY)
    odometry_noise: tuple[float, float] = (0.02, 0.01)  # noisy_truth: simulated odometry between queries, std
                                                        # (fraction of the distance, radians)
    odometry_scale_error: float = 0.0       # noisy_truth: drift, fraction of the distance (wheel odometry's scale)
    odometry_yaw_bias: float = 0.0          # noisy_truth: drift, radians per metre
    odometry_seed: int = 0
    # table1: the protocols (revisit: the query pass above; city: a seeded random ``city_database_fraction`` of
    # the database pass is the database, the rest the queries; residential: the database pass and a second
    # pass, both one frame every speed x 1 s), and the baselines run beside the modes
    protocols: tuple[str, ...] = DEFAULT_PROTOCOLS
    city_database_fraction: float = 0.4     # also kitti-city's
    kitti_city_length_m: float = added_field(KITTI_CITY_LENGTH_M)   # kitti-city: the pass's length (the route's
                                            # if shorter)
    split_seed: int = 0
    compare: CompareConfig = field(default_factory=CompareConfig)
    cross_area: CrossAreaConfig = field(default_factory=CrossAreaConfig)   # also every query's GPS-like prior
    # beside the methods (satloc_env.experiments.grading): the reference floors (satloc.localizers.reference:
    # prior, dead-reckoning) and a user's localizers ("module:Name" or "path/to/file.py:Name")
    references: tuple[str, ...] = added_field(("prior", "dead-reckoning"), before=())
    localizers: tuple[str, ...] = added_field(())
    pictures: bool = True                   # draw errors_along_route.png and a few posteriors per mode

    def __post_init__(self):
        bad = [p for p in self.protocols if p not in PROTOCOLS]
        if bad:
            raise ConfigError(f"protocols: unknown {bad}; expected a subset of {list(PROTOCOLS)}")
        check_parts(self.change_parts, "change_parts")
        if not 0 < self.city_database_fraction < 1:
            raise ConfigError(f"city_database_fraction: expected a fraction in (0, 1), got "
                              f"{self.city_database_fraction}")
        if len(self.odometry_noise) != 2 or min(self.odometry_noise) < 0:
            raise ConfigError(f"odometry_noise: expected 2 non-negative numbers, got {list(self.odometry_noise)}")
        bad = [m for m in self.modes if m not in METHOD_NAMES]
        if bad:
            raise ConfigError(f"modes: unknown {bad}; expected a subset of {list(METHOD_NAMES)}")
        if not 0.0 <= self.change <= 1.0:
            raise ConfigError(f"change: expected a value in [0, 1], got {self.change}")
        if self.odometry not in ODOMETRY:
            raise ConfigError(f"odometry: expected one of {list(ODOMETRY)}, got {self.odometry!r}")
        from .grading import check_extra

        check_extra(self)


def _stage_done(path: Path, config: dict) -> bool:
    """Whether ``path`` (a stage's JSON stamp) exists and was written for this configuration."""
    if not path.is_file():
        return False
    try:
        return read_json(path).get("config") == config
    except Exception:  # damaged stamp: redo the stage
        return False


def _stamp(path: Path, config: dict, **extra) -> None:
    write_json(path, {"format": "experiment_stage", "config": config, **extra})


def covered_queries(db: Sequence, q: Sequence, radius_m: float, max_yaw_deg: float = 180.0) -> np.ndarray:
    """Indices of the query frames whose true position lies within ``radius_m`` of a database frame whose
    heading is within ``max_yaw_deg`` degrees of the query's (180: any heading; a query crossing the database
    path at an intersection lies within a few metres of it, looking across its views)."""
    from scipy.spatial import cKDTree

    ok = np.all(np.isfinite(db.poses), axis=1)
    P = db.poses[ok]
    Q = np.nan_to_num(q.poses, nan=1e12)
    if max_yaw_deg >= 180.0:
        d, _ = cKDTree(P[:, :2]).query(Q[:, :2])
        return np.flatnonzero(d <= radius_m)
    near = cKDTree(P[:, :2]).query_ball_point(Q[:, :2], radius_m)
    cos_max = math.cos(math.radians(max_yaw_deg))
    return np.array([i for i, js in enumerate(near) if js and np.any(np.cos(P[js, 2] - Q[i, 2]) >= cos_max)], int)


def record_config(cfg: ExperimentConfig) -> RecordConfig:
    """The recording of an experiment's scene: the database pass and the revisit (query) pass (recorded
    densely for visual odometry, :func:`dense_pass`, where a tracked mode or the ``cross-area`` protocol's
    tracked row needs it)."""
    wander = {"wander_m": cfg.wander_m, "speed_wander": cfg.speed_wander}
    return RecordConfig(scene=cfg.scene, aliasing=cfg.aliasing, satellite_gap=cfg.satellite_gap,
                        database=PassConfig(max_frames=cfg.database_frames, **wander),
                        query=dense_pass(cfg, PassConfig(lane_offset_m=cfg.query_lane_m, spacing_m=cfg.query_spacing_m,
                                                         occlusion=cfg.occlusion, appearance=cfg.appearance,
                                                         change=cfg.change, change_parts=cfg.change_parts, seed=1,
                                                         max_frames=cfg.query_frames, **wander),
                                         tracked=is_tracked(cfg) or "cross-area" in cfg.protocols))


def is_tracked(cfg) -> bool:
    """Whether a mode of ``cfg.modes`` is tracked, so needs the odometry between the queries."""
    return any("track" in m.split("+") for m in getattr(cfg, "modes", ()))


def dense_pass(cfg, p: PassConfig, tracked: bool | None = None) -> PassConfig:
    """A query pass as recorded: where tracked modes (``tracked``, default :func:`is_tracked`) use
    ``cfg.odometry == "visual"``, a frame every :data:`DENSE_SPACING_M` metres (the queries are then the frames
    ``p.spacing_m`` apart, :func:`spaced_frames`; ``max_frames`` scaled to cover as much), else ``p`` itself."""
    tracked = is_tracked(cfg) if tracked is None else tracked
    if (not tracked or getattr(cfg, "odometry", "noisy_truth") != "visual"
            or p.spacing_m <= DENSE_SPACING_M):
        return p
    k = max(1, int(round(p.spacing_m / DENSE_SPACING_M)))
    return dataclasses.replace(p, spacing_m=DENSE_SPACING_M,
                               max_frames=None if p.max_frames is None else (p.max_frames - 1) * k + 1)


def spaced_frames(q: Sequence, spacing_m: float, limit: int | None = None) -> np.ndarray:
    """The frames of the recorded pass ``q`` that a pass recorded a frame every ``spacing_m`` metres would have
    kept: all of them when ``q`` was recorded at that spacing or coarser; of a dense pass (:func:`dense_pass`),
    the first frame and then each frame at least ``spacing_m`` metres further along the path than the last one
    kept, as the recorder keeps frames; the first ``limit`` of them (the pass's ``max_frames``)."""
    rec = float((q.meta.get("pass_config") or {}).get("spacing_m", spacing_m))
    if rec >= spacing_m - 1e-9 or len(q) == 0:
        return np.arange(len(q))[:limit]
    xy = np.asarray(q.poses, np.float64)[:, :2]
    steps = np.hypot(*np.diff(xy, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(np.nan_to_num(steps))])
    keep, last = [0], 0.0
    for i in range(1, len(q)):
        if s[i] - last >= spacing_m - 1e-9:
            keep.append(i)
            last = s[i]
    return np.asarray(keep, np.int64)[:limit]


def tracked_odometry(cfg, seq: Sequence, idx: np.ndarray, cache: Path | None = None) -> np.ndarray:
    """(len(idx), 3) the odometry the tracked modes move their belief by, from query ``idx[i - 1]`` to
    ``idx[i]`` of ``seq`` (row 0 NaN), by ``cfg.odometry``:

    * ``visual``: every step of :func:`satloc.tracking.vo.visual_odometry` over ``seq`` (cached in ``cache``, an npz
      reused for the same frames and VO configuration), composed between the queries;
    * ``oxts`` (a KITTI drive): :func:`satloc.datasets.kitti.oxts_odometry` of ``seq``, composed likewise;
    * ``noisy_truth``: :func:`satloc.tracking.track.noisy_odometry` of the queries' true poses.

    Composed odometry is NaN where a step between two queries failed (the belief starts anew there)."""
    idx = np.asarray(idx, np.int64)
    kind = getattr(cfg, "odometry", "noisy_truth")
    if kind == "noisy_truth":
        return noisy_odometry(seq.poses[idx], cfg.odometry_noise, cfg.odometry_seed,
                              scale_error=getattr(cfg, "odometry_scale_error", 0.0),
                              yaw_bias=getattr(cfg, "odometry_yaw_bias", 0.0))
    if kind == "oxts":
        from satloc.datasets.kitti import oxts_odometry

        steps = oxts_odometry(seq)
    else:
        steps = vo_steps(seq, cache)
    return compose_between(steps, idx)


def sequence_identity(seq: Sequence) -> str:
    """A recorded pass's identity, not only its count and name: its poses, timestamps and the recording's
    settings (scene, pass, revisit change, satellite gap), so that a pass recorded again (other drift, another
    scene with the same routes, other knobs) never reuses another's cached results."""
    import hashlib

    meta = {k: seq.meta.get(k) for k in ("scene", "pass_config", "change_seed", "satellite_gap")}
    h = hashlib.sha256(np.ascontiguousarray(np.asarray(seq.poses, np.float64)).tobytes())
    h.update(np.ascontiguousarray(np.asarray(seq.timestamps, np.float64)).tobytes())
    h.update(json.dumps(meta, sort_keys=True, default=str).encode())
    return h.hexdigest()[:32]


def vo_steps(seq: Sequence, cache: Path | None = None, config=None, progress: bool = False) -> np.ndarray:
    """(N, 3) :func:`satloc.tracking.vo.visual_odometry` of every frame of ``seq`` with ``config`` (default
    ``VOConfig()``), cached in ``cache`` (kept apart by the pass's identity and the configuration)."""
    from satloc.persist import load_npz, save_npz
    from satloc.tracking.vo import VOConfig, visual_odometry

    config = config or VOConfig()
    key = {"frames": len(seq), "vo": to_dict(config), "name": seq.name, "identity": sequence_identity(seq)}
    if cache is not None and Path(cache).is_file():
        try:
            a, meta = load_npz(cache, "visual_odometry")
            if meta.get("key") == key and a["steps"].shape == (len(seq), 3):
                return a["steps"]
        except Exception:  # damaged or foreign: compute again
            pass
    steps = visual_odometry(seq, config, progress)
    if cache is not None:
        save_npz(cache, "visual_odometry", {"steps": steps}, {"key": key})
    return steps


def check_recordings(recs, second_pass: bool = False) -> None:
    """Before any work: every pass of every recording (:class:`RecordConfig`) drivable by the autopilot
    (:func:`satloc_env.envs.record.check_passes`), and with ``second_pass`` the database route at the query
    pass's lane too (Table I's residential protocol); ConfigError naming the scene, the route and the first
    point where it leaves the road."""
    for rec in recs:
        scene = load_scene(rec.scene, rec.aliasing, rec.satellite_gap)
        passes = pass_routes(scene, rec)
        if second_pass:   # the residential protocol's second pass: the query's lane and drift, seed 2
            passes.append((passes[0][0], dataclasses.replace(rec.query, seed=SECOND_PASS_SEED)))
        check_passes(scene, passes, rec.speed_mps, f"scene {rec.scene!r}")


def _stages(cfg: ExperimentConfig, out: Path, progress: bool, log) -> tuple[Sequence, Sequence, Path, dict]:
    """Record, build and learn (each stage skipped where its output is already there with the same
    configuration); the database and query passes, the build folder and the stage times."""
    out.mkdir(parents=True, exist_ok=True)
    rec = record_config(cfg)
    times: dict[str, float] = {}
    t = time.perf_counter()
    from satloc_env.envs.auto_localizer import cache_key

    # the scene files' content too (YAML, image, road mask): an edited scene is recorded again
    rc = dict(record_stamp(rec), scene_sha256=cache_key(cfg.scene, cfg.aliasing)["scene_sha256"])
    if not _stage_done(out / "record.json", rc):
        log(f"[{cfg.scene}] recording the database and query passes into {out / 'rec'}")
        record_passes(rec, out / "rec", progress)
        _stamp(out / "record.json", rc)
    times["record_s"] = time.perf_counter() - t
    db, q = Sequence.load(out / "rec" / "database"), Sequence.load(out / "rec" / "query")
    bdir, more = build_and_learn(cfg, cfg.scene, db, out / "rec" / "map", out, {"record": rc}, progress, log)
    times.update(more)
    return db, q, bdir, times


def build_and_learn(cfg, label: str, database: Sequence, satmap: str | Path, out: Path, source: dict,
                    progress: bool = True, log=print) -> tuple[Path, dict]:
    """The method's offline stages on any database: build the dictionary of ``database`` against the map
    directory ``satmap`` into ``out/build``, then learn the projections if a mode of ``cfg.modes`` needs them.

    ``cfg`` gives ``features``, ``context``, ``projection`` and ``modes`` (an :class:`ExperimentConfig` or a
    :class:`satloc_env.experiments.evaluate.EvaluateConfig`). Each stage is skipped when ``out`` holds its stamp
    (``build_stage.json``, ``projection_stage.json``) for the same configuration and ``source`` (a dict that
    identifies the data, e.g. ``{"record": <record config>}``). Returns the build folder and the stage times."""
    bc = BuildConfig(features=cfg.features, context=cfg.context)
    bdir = out / "build"
    times: dict[str, float] = {}
    t = time.perf_counter()
    bstamp = dict(to_dict(bc, runtime=False), **source)   # runtime settings (the device) do not redo a stage
    bstamp["features_id"] = features_identity(bc.features)   # retrained FCN weights redo the build
    if not _stage_done(out / "build_stage.json", bstamp):
        log(f"[{label}] building the dictionary ({len(database)} database frames)")
        (out / "projection_stage.json").unlink(missing_ok=True)   # projections of an earlier build are stale
        build(database, satmap, bdir, bc, progress)
        _stamp(out / "build_stage.json", bstamp)
    times["build_s"] = time.perf_counter() - t
    t = time.perf_counter()
    if any(m.startswith("full") for m in cfg.modes):
        pc = dict(to_dict(cfg.projection, runtime=False), build=read_json(bdir / "build.json").get("entries"))
        if not _stage_done(out / "projection_stage.json", pc) or not (bdir / "projections.pt").is_file():
            log(f"[{label}] learning the projections W_g, W_s")
            train_projection(bdir, cfg.projection, progress)
            _stamp(out / "projection_stage.json", pc)
    times["projection_s"] = time.perf_counter() - t
    return bdir, times


def _covered(cfg: ExperimentConfig, db: Sequence, q: Sequence) -> np.ndarray:
    """The evaluated queries: the frames of the query pass ``query_spacing_m`` apart (:func:`spaced_frames`)
    whose true position lies within ``coverage_m`` of the database path, heading within ``coverage_yaw_deg`` of
    the database's there."""
    sel = np.intersect1d(covered_queries(db, q, cfg.coverage_m, cfg.coverage_yaw_deg),
                         spaced_frames(q, cfg.query_spacing_m, cfg.query_frames))
    if len(sel) == 0:
        raise ConfigError(f"[{cfg.scene}] no query frame lies within {cfg.coverage_m} m of the database path, heading "
                          f"within {cfg.coverage_yaw_deg} degrees of it")
    return sel


def mode_config(cfg, mode: str) -> LocalizerConfig:
    """The localizer configuration of a mode of ``cfg.modes`` (``go``, ``full+align+track``, ...): its base
    mode, bird's-eye alignment and tracking flags over ``cfg.localizer``."""
    base, *flags = mode.split("+")
    return from_dict(LocalizerConfig, dict(cfg.localizer, mode=base, refine="align" in flags, track="track" in flags),
                     "experiment localizer")


def localize_and_report(cfg, label: str, db: Sequence, q: Sequence, sel: np.ndarray, bdir: Path,
                        satmap: SatelliteMap, out: Path, head: dict, times: dict, progress: bool = True,
                        log=print, odometry: np.ndarray | None = None) -> dict:
    """Localize the query frames ``sel`` of ``q`` against the build ``bdir`` in every mode of ``cfg.modes``, then
    with the reference localizers and the user's localizers of ``cfg`` (:mod:`satloc_env.experiments.grading`),
    every one through the common interface and graded alike (:func:`satloc_env.experiments.grading.run_graded`),
    and report: per method ``localization_<key>.npz/.json``, ``summary.json`` (``head``, then the database size,
    the query count, the stage ``times``, each mode's summary under ``modes`` and the others' under
    ``localizers``), ``errors_along_route.png`` and the posteriors of the best, a median and the worst query of
    each mode drawn on ``satmap`` (``posterior_<mode>_q<i>.png``). Returns the summary.

    ``cfg`` gives ``modes``, ``localizer`` (LocalizerConfig fields other than the mode), ``odometry`` (with its
    noise settings), ``references``, ``localizers`` and ``cross_area`` (the queries' priors): the tracked modes
    move their belief by ``odometry`` (N, 3) when given, else by :func:`tracked_odometry` of the query pass
    between the evaluated queries; the other localizers get the same odometry (where no mode is tracked, the
    true motion plus noise). Works on any database/query pair: a simulated recording (:func:`run_scene`) or
    replayed real data (:mod:`satloc_env.experiments.evaluate`)."""
    from satloc.localizers.database import DatabaseLocalizer
    from satloc.localizers.interface import Context

    from .grading import extra_localizers, prune_extra, query_priors, run_graded

    # tracked modes: the odometry between consecutive evaluated queries (given, or of the query pass itself)
    odo = odometry
    if odo is None and is_tracked(cfg):
        odo = tracked_odometry(cfg, q, sel, Path(out) / "odometry_visual.npz")
    truth = np.asarray(q.poses, np.float64)[np.asarray(sel, np.int64)]
    priors = query_priors(cfg.cross_area, truth, sel, q.timestamps)
    context = Context(q.camera, satmap, seed=0, database=db, place=label)
    results: dict[str, dict] = {}
    examples: dict[str, list[tuple[int, Localization]]] = {}
    for mode in cfg.modes:
        lc = mode_config(cfg, mode)
        stamp = _localization_stamp(lc, bdir, q, sel, odo if lc.track else None)
        done = _localization_done(out, lc.name, stamp)
        if done is not None:   # this mode ran before on the same build, queries, settings and odometry
            s, err = done
            s.update(**table_stats(err, q.poses[sel], db.poses))
            results[mode] = s
            log(f"[{label}] {METHOD_NAMES[mode]:9s} mean {s['mean_m']:.2f} m (reused: {out}/localization_{lc.name}.*)")
            continue
        t = time.perf_counter()
        loc = load_localizer(bdir, lc, progress=progress)
        t_init = time.perf_counter() - t
        kept: dict[int, Localization] = {}   # every result, to draw a few posteriors without localizing again
        s, run = run_graded(DatabaseLocalizer(loc), lc.name, METHOD_NAMES[mode], context, q, sel,
                            odo if lc.track else None, priors, out, db.poses, label, progress, log=lambda m: None,
                            meta={"config": to_dict(lc)}, on_result=lambda i, e, raw, keep=kept: keep.__setitem__(i, raw))
        err = s.pop("errors")
        s.pop("inlier_score")
        s.update(mode=lc.name, localizer_init_s=round(t_init, 2))
        results[mode] = s
        write_json(out / f"localization_{lc.name}.stamp.json", dict(header("localization_stamp"), stamp=stamp,
                                                                     summary=_plain_summary(s)))
        log(f"[{label}] {METHOD_NAMES[mode]:9s} mean {s['mean_m']:.2f} m (std {s['std_m']:.2f}), median "
            f"{s['median_m']:.2f} m, {100 * s['within_1m']:.0f} % within 1 m, {s['queries_per_s']:.1f} queries/s "
            f"over {s['queries']} queries")
        # a few posteriors to draw: the best, a median and the worst query of this mode
        order = np.argsort(np.nan_to_num(err, nan=1e9))
        picks = sorted({int(order[0]), int(order[len(order) // 2]), int(order[-1])})
        examples[mode] = [(int(sel[i]), kept[i]) for i in picks if i in kept]
        del loc, run
    # the reference floors and the user's localizers, with the same queries, priors and odometry
    others: dict[str, dict] = {}
    extra = extra_localizers(cfg, {METHOD_NAMES[m] for m in cfg.modes})
    prune_extra(out, {k for k, _, _ in extra})
    if extra:
        eodo = odo if odo is not None else noisy_odometry(
            truth, cfg.odometry_noise, cfg.odometry_seed, scale_error=getattr(cfg, "odometry_scale_error", 0.0),
            yaw_bias=getattr(cfg, "odometry_yaw_bias", 0.0))
        for key, name, obj in extra:
            s, _ = run_graded(obj, key, name, context, q, sel, eodo, priors, out, db.poses, label, progress, log,
                              meta={"odometry": cfg.odometry if odo is not None else "noisy_truth"})
            s.pop("errors")
            s.pop("inlier_score")
            s["odometry"] = "" if key == "prior" else cfg.odometry if odo is not None else "noisy_truth"
            others[key] = s
    summary = dict(head, database_frames=len(db), database_m=round(db.path_length(), 1), queries=int(len(sel)),
                   times_s={k: round(v, 1) for k, v in times.items()}, modes=results, localizers=others)
    write_json(out / "summary.json", summary)
    if not getattr(cfg, "pictures", True):
        return summary
    from satloc.evaluation.plots import plot_errors_along_route, plot_posterior

    plot_errors_along_route(out, q, sel, cfg.modes, out / "errors_along_route.png")
    poses = q.poses
    for mode, ex in examples.items():
        for old in out.glob(f"posterior_{mode}_q*.png"):   # an earlier run's: queries this one may not show
            old.unlink()
        for qi, r in ex:
            truth = Pose2.from_array(poses[qi]) if np.all(np.isfinite(poses[qi])) else None
            plot_posterior(satmap, r, truth, out / f"posterior_{mode}_q{qi:03d}.png",
                           title=f"{label} query {qi}, {METHOD_NAMES[mode]}")
    return summary


#: the files of a build directory that make the build (satloc.pipeline.build, train_projection)
_BUILD_FILES = ("build.json", "dictionary.npz", "satellite_features.npz", "projection.json", "projections.pt")


def _localization_stamp(lc, bdir: Path, q: Sequence, sel: np.ndarray, odometry) -> dict:
    """What a mode's localization depends on: its settings, the build (each file's name, size and time), the
    query frames (their sequence's identity and the selection) and, tracked, the odometry."""
    import hashlib

    def digest(*arrays) -> str:
        h = hashlib.sha256()
        for a in arrays:
            h.update(np.ascontiguousarray(np.asarray(a, np.float64)).tobytes())
        return h.hexdigest()[:32]

    build = sorted((p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in Path(bdir).iterdir()
                   if p.name in _BUILD_FILES and p.is_file())   # not the caches a localizer adds on load
    return {"config": to_dict(lc), "build": [list(b) for b in build], "queries": [q.name, len(q)],
            "frames": digest(np.asarray(sel), np.asarray(q.poses)[np.asarray(sel, int)]),
            "odometry": digest(odometry) if odometry is not None else None}


def _plain_summary(s: dict) -> dict:
    return {k: v for k, v in s.items() if isinstance(v, (int, float, str, bool, type(None)))}


def _localization_done(out: Path, name: str, stamp: dict) -> tuple[dict, np.ndarray] | None:
    """(summary, errors) of a mode localized before under the same ``stamp`` (its ``localization_<name>``
    files, stamped when it finished), else None."""
    from satloc.persist import load_npz

    path = Path(out) / f"localization_{name}.stamp.json"
    try:
        saved = read_json(path, "localization_stamp")
        if saved.get("stamp") != json.loads(json.dumps(stamp)):
            return None
        a, _ = load_npz(Path(out) / f"localization_{name}.npz", "localization")
        return dict(saved["summary"]), np.asarray(a["errors"], np.float64)
    except (FormatError, KeyError, OSError, ValueError):   # none, damaged or foreign: localize again
        return None


def run_scene(cfg: ExperimentConfig, out: str | Path, progress: bool = True, log=print) -> dict:
    """Record, build, learn, localize (each mode) and draw; returns the per-mode summaries."""
    out = Path(out)
    db, q, bdir, times = _stages(cfg, out, progress, log)
    sel = _covered(cfg, db, q)
    # the scene's satellite map, as record_passes saved it (the same pixels as the scene's tile)
    return localize_and_report(cfg, cfg.scene, db, q, sel, bdir, SatelliteMap.load(out / "rec" / "map"), out,
                               {"scene": cfg.scene, "config": to_dict(cfg)}, times, progress, log)


def scene_label(scene: str) -> str:
    """The name a scene's results are filed under: its ``name`` (a shipped name, or the name inside a scene
    file given by path, so ``scenes/suburb_utm.yaml`` is filed as ``suburb_utm``)."""
    from satloc_env.world.scene import load_spec, scene_path

    p = scene_path(scene)
    return load_spec(p)[0].name if p.suffix in (".yaml", ".yml") else Path(scene).name


def scene_labels(scenes) -> list[str]:
    """:func:`scene_label` of each scene; :class:`ConfigError` when two would be filed under one name."""
    labels = [scene_label(s) for s in scenes]
    for i, label in enumerate(labels):
        if label in labels[:i]:
            j = labels.index(label)
            raise ConfigError(f"scenes: {scenes[j]!r} and {scenes[i]!r} are both named {label!r}; their results "
                              "would be filed in one folder (give the scene files different names)")
    return labels


# single-image separability (``satloc experiment aliasing``): where does a cue put the truth against look-alikes?
NEAR_M, NEAR_YAW_DEG, FAR_M = 2.0, 20.0, 10.0


def aliasing_scene(cfg: ExperimentConfig, out: str | Path, progress: bool = True, log=print) -> dict:
    """Single-image perceptual aliasing on one scene, cue by cue.

    For every evaluated query and each cue, the *margin* compares the best candidate pose near the truth
    (within ``NEAR_M`` m and ``NEAR_YAW_DEG`` degrees) with the best candidate more than ``FAR_M`` m away:

    * co-occurrence cues (the modes GO, NP, full of ``cfg.modes``): log P(near) - log P(far), the posterior
      computed over *all* candidates (no vote pruning, no refinement, no tracking);
    * ``bev``: bird's-eye correlation of the query's ground view with the satellite image at every candidate
      (:meth:`satloc.tracking.align.BevAligner.scan`), NCC(near) - NCC(far).

    A margin <= 0 means that cue, alone, prefers a place more than ``FAR_M`` m away: a gross failure of that
    cue (the bird's-eye refinement can still rescue it where the truth is among the posterior's few strongest
    peaks). Writes ``aliasing.json`` (per-query margins) and ``aliasing.png`` into
    ``out``; returns the summary."""
    out = Path(out)
    db, q, bdir, _ = _stages(cfg, out, progress, log)
    sel = _covered(cfg, db, q)
    bases = list(dict.fromkeys(m.split("+")[0] for m in cfg.modes))
    locs = {b: load_localizer(bdir, from_dict(LocalizerConfig, dict(cfg.localizer, mode=b, prune_regions=0,
                                                                    refine=False, track=False),
                                              "experiment localizer"), progress=progress) for b in bases}
    any_loc = next(iter(locs.values()))
    cands = any_loc.candidates
    cues = bases + ["bev"]
    margins = {c: np.full(len(sel), np.nan) for c in cues}
    from tqdm import tqdm

    t = time.perf_counter()
    for n, qi in enumerate(tqdm(sel, desc=f"{cfg.scene} aliasing", unit="query", disable=not progress, leave=False)):
        f = q[int(qi)]
        d = np.hypot(cands[:, 0] - f.pose.x, cands[:, 1] - f.pose.y)
        dyaw = np.abs(wrap_angle(cands[:, 2] - f.pose.yaw))
        near, far = (d <= NEAR_M) & (dyaw <= np.radians(NEAR_YAW_DEG)), d > FAR_M
        if not near.any() or not far.any():
            continue
        for b, loc in locs.items():
            try:
                p = loc.localize(f).posterior
            except ConfigError:
                continue
            margins[b][n] = float(np.log(max(p[near].max(), 1e-300)) - np.log(max(p[far].max(), 1e-300)))
        corr = any_loc.aligner.scan(any_loc.extractor(f.left, "ground"), any_loc.depth(f), cands)
        if corr is not None:
            margins["bev"][n] = float(corr[near].max() - corr[far].max())
    elapsed = time.perf_counter() - t
    valid = np.all([np.isfinite(margins[c]) for c in cues], axis=0)
    lost = {c: margins[c] <= 0 for c in cues}
    lost_cooc = np.all([lost[b] for b in bases], axis=0) & valid
    lost_all = lost_cooc & lost["bev"]
    summary = {"scene": cfg.scene, "queries": int(len(sel)), "measured": int(valid.sum()),
               "near_m": NEAR_M, "near_yaw_deg": NEAR_YAW_DEG, "far_m": FAR_M, "seconds": round(elapsed, 1),
               "cues": {c: {"far_wins": int((lost[c] & valid).sum()),
                            "median_margin": float(np.median(margins[c][valid])) if valid.any() else None}
                        for c in cues},
               "lost_by_every_cooccurrence_mode": [int(sel[i]) for i in np.flatnonzero(lost_cooc)],
               "lost_by_every_cue": [int(sel[i]) for i in np.flatnonzero(lost_all)],
               "frames": [int(i) for i in sel],
               "measured_mask": [bool(v) for v in valid],    # every cue measured (the counts are over these)
               "margins": {c: [None if not np.isfinite(v) else round(float(v), 4) for v in margins[c]] for c in cues}}
    write_json(out / "aliasing.json", summary)
    from satloc.evaluation.plots import plot_margins_along_route

    plot_margins_along_route(q, sel[valid], {c: m[valid] for c, m in margins.items()}, FAR_M, out / "aliasing.png",
                             f"{cfg.scene}: ")
    return summary


def aliasing(out: str | Path, scenes: tuple[str, ...] = ("city", "residential"), config: dict | None = None,
             progress: bool = True, log=print) -> list[dict]:
    """Run :func:`aliasing_scene` on each scene (in ``out/<scene>``, the same stages as :func:`table1`, reused
    when already there); write ``aliasing.csv`` (scene,cue,measured,far_wins,median_margin) and ``aliasing.md``
    into ``out``; return the rows."""
    out = Path(out)
    rows = []
    cfgs = [from_dict(ExperimentConfig, dict(config or {}, scene=scene), "experiment config") for scene in scenes]
    check_recordings(record_config(c) for c in cfgs)
    for cfg, label in zip(cfgs, scene_labels(scenes)):
        s = aliasing_scene(cfg, out / label, progress, log)
        for cue, c in s["cues"].items():
            rows.append({"scene": label, "cue": cue, "measured": s["measured"], "far_wins": c["far_wins"],
                         "median_margin": round(c["median_margin"], 3) if c["median_margin"] is not None else None})
        rows.append({"scene": label, "cue": "every co-occurrence mode", "measured": s["measured"],
                     "far_wins": len(s["lost_by_every_cooccurrence_mode"]), "median_margin": None})
        rows.append({"scene": label, "cue": "every cue", "measured": s["measured"],
                     "far_wins": len(s["lost_by_every_cue"]), "median_margin": None})
        log(f"[{cfg.scene}] queries where every cue prefers a place > {FAR_M:.0f} m away: {s['lost_by_every_cue']}")
    with atomic_path(out / "aliasing.csv", suffix=".csv") as tmp:
        with open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["scene", "cue", "measured", "far_wins", "median_margin"])
            for r in rows:
                w.writerow([r["scene"], r["cue"], r["measured"], r["far_wins"],
                            "" if r["median_margin"] is None else f"{r['median_margin']:.3f}"])
    lines = ["| scene | cue | queries measured | a place > 10 m away wins | median margin |", "|---|---|---|---|---|"]
    lines += [f"| {r['scene']} | {r['cue']} | {r['measured']} | {r['far_wins']} | "
              f"{'' if r['median_margin'] is None else r['median_margin']} |" for r in rows]
    with atomic_path(out / "aliasing.md", suffix=".md") as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return rows


def earlier_rows(path: Path, fmt: str, columns, redone) -> tuple[list[dict], dict]:
    """The rows of an earlier table file ``path`` (JSON of format ``fmt`` with ``rows``) that this run does not
    redo (``redone(row)`` false) and that have every one of ``columns``, and the file itself; none from a
    missing, damaged or foreign file. A run of part of a table adds its rows instead of dropping the others."""
    try:
        old = read_json(path)
        if not isinstance(old, dict) or old.get("format") != fmt or not isinstance(old.get("rows"), list):
            return [], {}
    except (OSError, FormatError):
        return [], {}
    return [r for r in old["rows"] if isinstance(r, dict) and all(c in r for c in columns) and not redone(r)], old


def write_rows_csv(path: Path, columns, rows: list[dict]) -> None:
    """``rows`` as CSV (``columns`` in order; floats to 3 decimals), written atomically."""
    with atomic_path(path, suffix=".csv") as tmp:
        with open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(columns)
            for r in rows:
                w.writerow([f"{r[c]:.3f}" if isinstance(r[c], float) else r[c] for c in columns])


def markdown_table(rows: list[dict]) -> str:
    """Table I as Markdown: one table per protocol (rows without ``protocol``: one table), a column group per
    scene: mean (std), the 95 % bootstrap interval of the mean, median, within 1 m, the failure rate and
    seconds per query; then the odometry of the tracked rows."""
    out = []
    for protocol in dict.fromkeys(r.get("protocol") for r in rows):
        part = [r for r in rows if r.get("protocol") == protocol]
        scenes = list(dict.fromkeys(r["scene"] for r in part))
        methods = list(dict.fromkeys(r["method"] for r in part))
        cell = {(r["method"], r["scene"]): r for r in part}
        if protocol is not None:
            out.append(f"Protocol **{protocol}**:\n")
        lines = ["| method | " + " | ".join(f"{s}: mean (std) m | {s}: 95 % CI of the mean | {s}: median m | "
                                           f"{s}: within 1 m | {s}: failed | {s}: s per query" for s in scenes)
                 + " | odometry |", "|---|" + "---|---|---|---|---|---|" * len(scenes) + "---|"]
        for m in methods:
            parts = []
            odo = ""
            for s in scenes:
                r = cell.get((m, s))
                if not r:
                    parts += [""] * 6
                    continue
                spq, lo, fr = r.get("s_per_query"), r.get("ci95_low"), r.get("failure_rate")
                parts += [f"{r['mean_m']:.2f} ({r['std_m']:.2f})",
                          "" if lo is None else f"{lo:.2f}-{r['ci95_high']:.2f}", f"{r['median_m']:.2f}",
                          f"{100 * r['within_1m']:.0f} %", "" if fr is None else f"{100 * fr:.0f} %",
                          "" if spq is None else f"{spq:.3f}"]
                odo = odo or r.get("odometry", "")
            lines.append(f"| {m} | " + " | ".join(parts) + f" | {odo} |")
        out.append("\n".join(lines) + "\n")
    return "\n".join(out)
