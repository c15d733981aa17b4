"""Database and query passes: drive a route with the autopilot and record stereo frames to disk.

``record_passes(scene, out_dir)`` writes::

    out_dir/map/          the scene's satellite map (SatelliteMap layout)
    out_dir/database/     Sequence: the database pass (lane offset, no occluders, reference appearance)
    out_dir/query/        Sequence: the query pass (another lane offset, appearance, occluders and, by default,
                          a revisit change of the world: :data:`QUERY_CHANGE`)
    out_dir/recording.json  the configuration and which passes are done; ``complete`` once both are

Both sequences use the on-disk layout of :mod:`satloc.sequence`, which the dataset readers also produce.

Before any work, :func:`record_passes` checks that the autopilot can drive both passes (route and lane
offset) on the road (:func:`check_passes`, the same off-road check as the recorder's, run without
rendering: :mod:`satloc_env.envs.drivecheck`); a pass that would leave the road is a :class:`satloc.ConfigError`
naming the route and the first point off the road, as it is when a pass leaves the road while recording.

Interrupted runs: each pass is written whole (a temporary directory renamed into place) and marked done in
``recording.json`` after it. A rerun with the same configuration and satloc version after an interruption
keeps the passes marked done and records the rest (it resumes); otherwise it starts over, first marking
the recording incomplete and removing the earlier map and passes, so a recording is never a mix of two
configurations. :func:`load_recording` loads a recording only when it is complete.

This module does not import :mod:`satloc_env.envs.drive`: the environment uses :mod:`satloc_env.envs.auto_localizer` for
``localizer="auto"``, which records the scene's database pass with this module, so the recorders make their
environments through gymnasium's registry entry of ``satloc/SatLoc-v0`` (:func:`make_env`) and the imports
go one way (envs.drive -> envs.auto_localizer -> envs.record).
"""
from __future__ import annotations

import hashlib
import os
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.envs.registration import load_env_creator
from tqdm import tqdm

from satloc import __version__ as SATLOC_VERSION
from satloc.config import added_field, from_dict, to_dict
from satloc.errors import ConfigError, FormatError
from satloc.geometry import Pose2
from satloc.persist import header, read_json, write_json
from satloc.satmap import SatelliteMap
from satloc.sequence import Frame, Sequence, SequenceWriter
from satloc_env.world.revisit import PARTS as REVISIT_PARTS
from satloc_env.world.revisit import check_parts
from satloc_env.world.scene import SCENES_DIR, load_scene, load_spec, scene_path

from .drivecheck import check_route, off_road_message
from .ids import ENV_ID
from .vehicle import DEFAULT_SPEED_WANDER, DEFAULT_WANDER_M, Wander, default_wander_seed, wander_profile


def make_env(**config: Any) -> gym.Env:
    """A new, unwrapped ``satloc/SatLoc-v0`` environment (:class:`satloc_env.envs.drive.SatLocEnv`) with ``config``:
    the class of the registry's entry point, called without gymnasium's wrappers."""
    return load_env_creator(gym.spec(ENV_ID).entry_point)(**config)


#: the revisit change (:mod:`satloc_env.world.revisit`) of the default query pass; 0.5, like its appearance: the sun
#: 30-50 degrees round and 0.22 rad lower to 0.1 higher, cast shadows at 75-100 % depth, a repair patch per
#: 240 m^2 and a crack per 120 m^2 of road, markings 12-51 % faded, 22 % of the parked cars gone, up to 18 %
#: moved and about 18 % added, grass and foliage a fifth to two fifths of the way to another season's colour:
#: another day, not another world. Measured by examples/revisit_change.py (40 places of ``residential``): the
#: median SIFT RANSAC inliers between the database and the query pass fall from 146 (change 0) to 101 (0.25),
#: 95 (0.5) and 85 (1): most of the effect is there by 0.5, while 1 turns the sun 60-100 degrees and removes
#: 45 % of the parked cars.
QUERY_CHANGE = 0.5


@dataclass
class PassConfig:
    route: str | None = None        # default: the scene's database_route / query_route
    lane_offset_m: float = -1.75
    spacing_m: float = 1.0          # record a frame every this many metres driven
    max_frames: int | None = None   # stop early after this many frames
    occlusion: float = 0.0
    appearance: float = 0.0
    change: float = 0.0             # revisit change of the world (satloc_env.world.revisit), seeded by ``seed``
    seed: int = 0
    depth: bool = True              # store true depth (simulator ground truth) with each frame
    labels: bool = False
    wander_m: float = added_field(DEFAULT_WANDER_M, before=0.0)        # the autopilot's lateral drift (std, m;
    speed_wander: float = added_field(DEFAULT_SPEED_WANDER, before=0.0)  # satloc_env.envs.vehicle) and its speed's
                                                                         # (relative std), seeded by ``seed``
    attitude: float = added_field(1.0, before=0.0)   # the body's pitch and roll (the environment's ``attitude``:
                                                     # 1 a passenger car's, 0 a level mount, as before the field)
    change_parts: tuple[str, ...] = added_field(REVISIT_PARTS)   # which parts of the revisit change
                                                     # (satloc_env.world.revisit.PARTS; the environment's ``change_parts``)

    def __post_init__(self):
        for k, hi in (("wander_m", 0.5), ("speed_wander", 0.5), ("attitude", 1.0)):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= v <= hi:
                raise ConfigError(f"pass {k}: expected a number in [0, {hi}], got {v!r}")
        check_parts(self.change_parts, "pass change_parts")


@dataclass
class RecordConfig:
    scene: str = "city"
    resolution: str = "half"
    aliasing: float | None = None
    satellite_gap: float | None = added_field(None)   # the map as a capture (satloc_env.world.capture); None: the scene's
    speed_mps: float = 8.0
    database: PassConfig = field(default_factory=PassConfig)
    query: PassConfig = field(default_factory=lambda: PassConfig(lane_offset_m=-0.75, spacing_m=10.0,
                                                                   occlusion=0.3, appearance=0.5,
                                                                   change=QUERY_CHANGE, seed=1))


def record_stamp(cfg: RecordConfig) -> dict:
    """What a recording of ``cfg`` is stamped with and compared by (its ``recording.json``, the experiments'
    stage stamps): :func:`satloc.config.to_dict` of ``cfg`` with ``satellite_gap`` the gap its map is captured
    at (None resolved to the scene's own), written only when not 0, as recordings made before the knob (their
    maps the ground's copy) were stamped."""
    from satloc_env.world.scene import own_satellite_gap

    d = to_dict(cfg, stamp=True)
    d.pop("satellite_gap", None)
    gap = own_satellite_gap(cfg.scene) if cfg.satellite_gap is None else float(cfg.satellite_gap)
    if gap != 0.0:
        d["satellite_gap"] = gap
    return d


def record_pass(env: gym.Env, p: PassConfig, route: str, out: Path, name: str, progress: bool = True,
                meta: dict | None = None) -> Sequence:
    """Drive ``route`` once with the autopilot of ``env`` (a ``satloc/SatLoc-v0`` environment, wrapped or
    not), writing a frame every ``p.spacing_m`` metres to ``out``."""
    options = {"route": route, "lane_offset_m": p.lane_offset_m, "occlusion": p.occlusion,
               "appearance": p.appearance, "change": p.change, "max_steps": 10**9,
               "wander_m": p.wander_m, "speed_wander": p.speed_wander, "attitude": p.attitude,
               "change_parts": list(p.change_parts)}
    obs, info = env.reset(seed=p.seed, options=options)
    length = env.unwrapped.route.length
    total = p.max_frames or int(length // p.spacing_m) + 1
    m = dict(meta or {})
    m.update(pass_config=to_dict(p), route=route, route_length_m=length)
    if env.unwrapped.change_seed is not None:
        m["change_seed"] = env.unwrapped.change_seed
    bar = tqdm(total=total, desc=f"recording {name}", unit="frame", disable=not progress, leave=False)
    n = 0
    last_s = -np.inf
    t = 0.0
    with SequenceWriter(out, env.unwrapped.camera, name, m) as w:
        while True:
            s = float(info["route_s"])
            if s - last_s >= p.spacing_m - 1e-9:
                w.add(Frame(obs["left"], obs["right"], Pose2.from_array(info["pose"]), t,
                            obs.get("depth"), obs.get("labels")))
                last_s = s
                n += 1
                bar.update(1)
                if p.max_frames and n >= p.max_frames:
                    break
            obs, _, term, trunc, info = env.step(env.unwrapped.autopilot_action())
            t += env.unwrapped.config.dt
            if term or trunc:
                if bool(info["off_road"]):
                    raise ConfigError(f"scene {env.unwrapped.scene.name!r}: " + off_road_message(
                        env.unwrapped.scene, route, p.lane_offset_m, info["pose"], float(info["route_s"])))
                break
        seq = w.close()
    bar.close()
    return seq


def pass_routes(scene, cfg: RecordConfig) -> list[tuple[str, PassConfig]]:
    """(route, pass) of the database and query passes of ``cfg`` on ``scene`` (a pass's own route, else the
    scene's ``database_route`` / ``query_route``)."""
    return [(cfg.database.route or scene.spec.database_route, cfg.database),
            (cfg.query.route or scene.spec.query_route, cfg.query)]


def check_passes(scene, passes, speed_mps: float, where: str | None = None) -> None:
    """ConfigError naming the route and the first point where the autopilot would leave the road, for the
    first of ``passes`` ((route, PassConfig) pairs) it cannot drive (:func:`satloc_env.envs.drivecheck.check_route`:
    the recorder's own off-road check, without rendering)."""
    for route, p in passes:
        check_route(scene, route, p.lane_offset_m, speed_mps, where=where, wander=pass_wander(scene, route, p))


def pass_wander(scene, route: str, p: PassConfig):
    """The drift profile a pass drives (:func:`satloc_env.envs.vehicle.wander_profile`, seeded as the environment
    seeds it from ``reset(seed=p.seed)``), None without wander."""
    w = Wander(p.wander_m, p.speed_wander)
    if not w.active or route not in scene.routes:
        return None
    return wander_profile(scene.routes[route].length, w, default_wander_seed(p.seed))


def check_scene_routes(scene, cfg: RecordConfig | None = None, where: str | None = None) -> None:
    """Every route of ``scene`` drivable at the database pass's lane offset of ``cfg`` (default: the
    defaults of :class:`RecordConfig`), and the query route at the query pass's too (what ``satloc scene``
    checks)."""
    cfg = cfg or RecordConfig()
    passes = [(k, cfg.database) for k in scene.routes]
    if cfg.query.lane_offset_m != cfg.database.lane_offset_m:
        passes.append((cfg.query.route or scene.spec.query_route, cfg.query))
    check_passes(scene, passes, cfg.speed_mps, where)


def _hash_files(h: "hashlib._Hash", files: list[tuple[str, Path]]) -> None:
    for name, path in files:
        h.update(name.encode() + b"\0")
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
        h.update(b"\0")


def scene_identity(scene: str | os.PathLike) -> tuple[str, str, str, float]:
    """(name, source, sha256 of the scene's files, the scene's own aliasing) of a scene argument as
    :func:`satloc_env.world.scene.load_scene` reads it. ``source`` is the shipped name or the resolved path."""
    p = Path(scene).expanduser()
    h = hashlib.sha256()
    if p.is_dir() and (p / "scene.json").is_file():  # a saved scene: all its files
        spec = read_json(p / "scene.json", "scene").get("spec") or {}
        files = sorted((str(f.relative_to(p)), f) for f in p.rglob("*") if f.is_file())
        _hash_files(h, files)
        name = str(spec.get("name", p.name))
        return name, str(p.resolve()), h.hexdigest(), float((spec.get("knobs") or {}).get("aliasing", 0.0))
    spec, base = load_spec(scene)
    path = scene_path(scene).resolve()
    files = [("scene.yaml", path)]
    g = spec.generator_spec(str(path))
    if g.type in ("image", "vectors"):
        files += g.files(base)
    _hash_files(h, files)
    source = path.stem if path.parent == SCENES_DIR.resolve() else str(path)
    return spec.name, source, h.hexdigest(), float(spec.knobs.aliasing)


#: the status file of a recording directory (format ``recording``)
STATUS = "recording.json"
PASSES = ("database", "query")


def _status(cfg: dict, scene_sha: str, done: list[str], complete: bool = False) -> dict:
    return dict(header("recording"), config=cfg, scene_sha256=scene_sha, satloc_version=SATLOC_VERSION,
                done=list(done), complete=complete)


def _resumable(out: Path, cfg: dict, scene_sha: str) -> list[str]:
    """The passes an interrupted earlier run with configuration ``cfg`` (and the same scene files and satloc
    version) finished, if they load; else []."""
    try:
        st = read_json(out / STATUS, "recording")
    except FormatError:
        return []
    if st.get("complete") or st.get("config") != cfg or st.get("scene_sha256") != scene_sha \
            or st.get("satloc_version") != SATLOC_VERSION:
        return []
    done = []
    for name in PASSES:  # in order: the query pass counts only after the database pass (and the map)
        if name not in (st.get("done") or []):
            break
        try:
            Sequence.load(out / name)
            if name == "database":
                SatelliteMap.load(out / "map")
        except FormatError:
            break
        done.append(name)
    return done


def _start_over(out: Path, cfg: dict, scene_sha: str) -> None:
    """Mark the recording incomplete (for ``cfg``), then remove the map and passes of an earlier run."""
    write_json(out / STATUS, _status(cfg, scene_sha, []))
    for name in PASSES:
        if (out / name).is_symlink():
            (out / name).unlink()
        elif (out / name).is_dir():
            shutil.rmtree(out / name)
    for f in ("map.json", "map.png", "labels.png"):  # only the map's own files: never a folder we did not write
        (out / "map" / f).unlink(missing_ok=True)


def record_passes(config: RecordConfig | dict[str, Any], out_dir: str | Path, progress: bool = True
                  ) -> tuple[Sequence, Sequence]:
    """Record the database and query passes of a scene into ``out_dir`` (see the module docstring); after an
    interrupted run with the same configuration, only the passes it did not finish."""
    cfg = config if isinstance(config, RecordConfig) else from_dict(RecordConfig, config, "record config")
    scene = load_scene(cfg.scene, cfg.aliasing, cfg.satellite_gap)   # before any work: both passes drivable
    check_passes(scene, pass_routes(scene, cfg), cfg.speed_mps)
    out = Path(out_dir)
    conf = record_stamp(cfg)
    sha = scene_identity(cfg.scene)[2]
    done = _resumable(out, conf, sha)
    if not done:
        _start_over(out, conf, sha)
    sequences = []
    for name, p in (("database", cfg.database), ("query", cfg.query)):
        if name in done:
            if progress:
                print(f"satloc: resuming: the {name} pass in {out / name} was recorded by an interrupted run",
                      file=sys.stderr, flush=True)
            sequences.append(Sequence.load(out / name))
            continue
        # localizer=None: recording needs no localization (and "auto" would itself record the database pass)
        env = make_env(scene=cfg.scene, resolution=cfg.resolution, aliasing=cfg.aliasing, speed_mps=cfg.speed_mps,
                       satellite_gap=cfg.satellite_gap, depth=p.depth, labels=p.labels, localizer=None)
        try:
            env.reset(seed=p.seed)
            scene = env.scene
            route = p.route or (scene.spec.database_route if name == "database" else scene.spec.query_route)
            if name == "database":
                scene.satmap.save(out / "map")
            meta = {"source": "satloc_env", "scene": scene.name, "aliasing": scene.spec.knobs.aliasing,
                    "satellite_gap": scene.spec.knobs.satellite_gap}
            if scene.satmap.frame is not None:  # a scene over georeferenced imagery: poses are in its GeoFrame
                meta["geo_frame"] = scene.satmap.frame.to_dict()
            sequences.append(record_pass(env, p, route, out / name, name, progress, meta))
        finally:
            env.close()
        done.append(name)
        write_json(out / STATUS, _status(conf, sha, done))
    write_json(out / STATUS, _status(conf, sha, done, complete=True))
    return sequences[0], sequences[1]


def load_recording(out_dir: str | Path) -> tuple[SatelliteMap, Sequence, Sequence]:
    """The map, database and query pass of a complete recording (:func:`record_passes`); FormatError naming
    ``recording.json`` for an incomplete one (an interrupted run: rerun it to finish) or a directory that is
    not a recording."""
    out = Path(out_dir)
    st = read_json(out / STATUS, "recording")
    if st.get("complete") is not True:
        done = ", ".join(st.get("done") or []) or "no pass"
        raise FormatError(f"{out / STATUS}: the recording is incomplete ({done} done; interrupted?); run "
                          "record_passes / satloc record again with the same options to finish it")
    return SatelliteMap.load(out / "map"), Sequence.load(out / "database"), Sequence.load(out / "query")
