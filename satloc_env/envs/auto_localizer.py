"""The environment's ``localizer="auto"``: a localizer built from the scene's database pass, cached on disk.

On first use for a (scene, aliasing, resolution, satellite gap) the database pass is recorded (the scene's
``database_route``, lane offset -1.75 m, drifting as the recorder's default pass does, no occluders, reference
appearance: ``RecordConfig().database``) on the scene's map at that gap,
then :func:`satloc.pipeline.build` and :func:`satloc.pipeline.train_projection` run on it; this takes minutes
for a shipped scene. The result is a build directory under the cache root::

    $SATLOC_CACHE (default ~/.cache/satloc)/
        city-alias0-half-<hash>/       build.json, dictionary.npz, satellite_features.npz, projections.pt,
                                       projection.json, projection_loss.png, autoloc.json (the cache key)
        .city-alias0-half-<hash>.lock  serialises concurrent builds of that entry

``<hash>`` covers the scene file's content (YAML, plus the image of an image scene or all files of a saved
scene), the effective aliasing, the resolution, satloc's format and package versions, and the recording,
build and projection configurations. Anything else (the recording itself) is not kept. An entry is built in
a temporary directory beside it and renamed into place when complete, under an exclusive lock, so concurrent
processes (e.g. async vector env workers) build it once and never see a partial entry. A build interrupted
by Ctrl-C removes its temporary directory; one killed outright (SIGKILL) leaves it, and the next build of
that entry removes it (under the lock) and starts over.

:func:`auto_build_dir` returns the directory (building it on a miss); the CLI and scripts can use it like a
build directory of ``satloc build``. :func:`load_cached_localizer` loads a build directory once per process.

The environment (:mod:`satloc_env.envs.drive`) imports this module; this module records the database pass with
:mod:`satloc_env.envs.record` in an environment made through gymnasium's registry (:func:`satloc_env.envs.record.make_env`)
and imports neither of them back.
"""
from __future__ import annotations

import contextlib
import functools
import glob
import hashlib
import json
import logging
import os
import re
import shutil
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Iterator

from satloc import __version__ as SATLOC_VERSION
from satloc.config import to_dict
from satloc.errors import ConfigError
from satloc.features.pixelwise import features_identity
from satloc.persist import FORMAT_VERSION, atomic_dir, header, read_json, write_json
from satloc_env.world.cache import CACHE_ENV, cache_root  # noqa: F401  (their home before)
from satloc_env.world.scene import (
    SCENES_DIR,  # noqa: F401  (auto_localizer.SCENES_DIR: where the shipped scenes are)
    own_satellite_gap,
)

from .record import RecordConfig, make_env, record_pass
from .record import scene_identity as _scene_identity

log = logging.getLogger(__name__)

#: files a complete cache entry has
ENTRY_FILES = ("build.json", "dictionary.npz", "satellite_features.npz", "projections.pt", "autoloc.json")
_KEY_VERSION = 4  # bump when the way an entry is made changes in a way the key does not show (2: ground beyond the tile;
#                    3: real places mirrored beyond it, an OSM extract's declared bounds; 4: textures sampled
#                    from the nearest mipmap level)



def _configs(max_frames, build_config, projection_config):
    from satloc.features.projection import ProjectionConfig
    from satloc.pipeline import BuildConfig

    rc = RecordConfig()
    db = replace(rc.database, max_frames=max_frames, depth=False)  # stereo depth unless the build wants true depth
    bc = build_config if build_config is not None else BuildConfig()
    if bc.depth_source == "frame":
        db = replace(db, depth=True)
    pc = projection_config if projection_config is not None else ProjectionConfig()
    return rc.speed_mps, db, bc, pc


def cache_key(scene: str | os.PathLike, aliasing: float | None = None, resolution: str = "half", *,
              max_frames: int | None = None, build_config=None, projection_config=None,
              satellite_gap: float | None = None) -> dict:
    """Everything a cache entry depends on, as a plain dict (written to its ``autoloc.json``). A satellite map
    captured with a gap (``satellite_gap``, None: the scene's) adds the key ``satellite_gap``; gap 0 keeps the
    keys (and so the entries) of the versions before it."""
    if resolution not in ("half", "full"):
        raise ConfigError(f"resolution: expected 'half' or 'full', got {resolution!r}")
    if max_frames is not None and max_frames < 2:
        raise ConfigError(f"max_frames: expected None or >= 2, got {max_frames}")
    name, source, sha, own_aliasing = _scene_identity(scene)
    speed, db, bc, pc = _configs(max_frames, build_config, projection_config)
    key = {"scene": name, "source": source, "scene_sha256": sha,
            "aliasing": float(own_aliasing if aliasing is None else aliasing), "resolution": resolution,
            "format_version": FORMAT_VERSION, "satloc_version": SATLOC_VERSION, "key_version": _KEY_VERSION,
            "speed_mps": speed, "database_pass": to_dict(db, stamp=True), "build": to_dict(bc, runtime=False),
            "projection": to_dict(pc, runtime=False),   # not the device: how an entry is made, not what it holds
            "features_id": features_identity(bc.features)}   # the FCN weights' content: retrained ones rebuild
    if satellite_gap is not None and (isinstance(satellite_gap, bool) or not isinstance(satellite_gap, (int, float))
                                      or not 0.0 <= satellite_gap <= 1.0):
        raise ConfigError(f"satellite_gap: expected a number in [0, 1] or None (the scene's), got {satellite_gap!r}")
    gap = own_satellite_gap(scene) if satellite_gap is None else float(satellite_gap)
    if gap != 0.0:
        key["satellite_gap"] = gap
    return key


def _entry_name(key: dict) -> str:
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]
    slug = re.sub(r"[^A-Za-z0-9_.-]+", "_", key["scene"]).strip("._") or "scene"
    gap = f"-gap{key['satellite_gap']:g}" if "satellite_gap" in key else ""
    return f"{slug}-alias{key['aliasing']:g}{gap}-{key['resolution']}-{digest}"


def build_path(scene: str | os.PathLike, aliasing: float | None = None, resolution: str = "half", *,
               max_frames: int | None = None, build_config=None, projection_config=None,
               cache_dir: str | os.PathLike | None = None, satellite_gap: float | None = None) -> Path:
    """Where :func:`auto_build_dir` keeps the entry for these arguments (whether or not it exists yet)."""
    key = cache_key(scene, aliasing, resolution, max_frames=max_frames, build_config=build_config,
                    projection_config=projection_config, satellite_gap=satellite_gap)
    return cache_root(cache_dir) / _entry_name(key)


def is_complete(entry: Path) -> bool:
    return all((entry / f).is_file() for f in ENTRY_FILES)


@contextlib.contextmanager
def _locked(path: Path, on_wait=None) -> Iterator[bool]:
    """An exclusive advisory lock on ``path``; yields True, or False where ``fcntl`` is missing (no lock: the
    final rename stays safe). ``on_wait()`` is called if another process holds it. The kernel releases the
    lock when its holder dies, however it dies (SIGKILL included)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield False
        return
    with open(path, "a") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            if on_wait is not None:
                on_wait()
            fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield True
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _leftovers(entry: Path) -> list[Path]:
    """Temporary and set-aside directories of ``entry`` (``.<entry>.*.tmp``, ``.<entry>.*.old*``): an
    interrupted build's. Only the holder of the entry's lock builds it, so under the lock they are all stale."""
    pre = f".{entry.name}."
    return [p for p in entry.parent.glob(f"{glob.escape(pre)}*")
            if p.name.endswith(".tmp") or ".old" in p.name[len(pre):]]


def _announce(msg: str, progress: bool) -> None:
    log.info(msg)
    if progress:
        print(f"satloc: {msg}", file=sys.stderr, flush=True)


def auto_build_dir(scene: str | os.PathLike, aliasing: float | None = None, resolution: str = "half",
                   progress: bool = True, *, max_frames: int | None = None, build_config=None,
                   projection_config=None, cache_dir: str | os.PathLike | None = None,
                   satellite_gap: float | None = None) -> Path:
    """The cached build directory of ``scene``'s database pass; records and builds it on a miss.

    ``max_frames`` (stop the database pass early), ``build_config`` (:class:`satloc.pipeline.BuildConfig`) and
    ``projection_config`` (:class:`satloc.features.projection.ProjectionConfig`) are for small builds (tests); they are
    part of the cache key. ``cache_dir`` overrides the cache root (see :func:`cache_root`).
    """
    key = cache_key(scene, aliasing, resolution, max_frames=max_frames, build_config=build_config,
                    projection_config=projection_config, satellite_gap=satellite_gap)
    root = cache_root(cache_dir)
    entry = root / _entry_name(key)
    if is_complete(entry):
        log.debug("auto localizer cache hit: %s", entry)
        return entry
    root.mkdir(parents=True, exist_ok=True)
    wait = lambda: _announce(f"waiting for another process building {entry}", progress)  # noqa: E731
    with _locked(root / f".{entry.name}.lock", wait) as exclusive:
        if is_complete(entry):  # built by another process while we waited
            return entry
        if exclusive:  # an earlier build killed mid-way (SIGKILL) left its temporary directory
            for p in _leftovers(entry):
                log.info("removing the leftover of an interrupted build: %s", p)
                if p.is_dir() and not p.is_symlink():
                    shutil.rmtree(p, ignore_errors=True)
                else:
                    p.unlink(missing_ok=True)
        _announce(f"building the localizer for scene {key['scene']!r} (aliasing {key['aliasing']:g}, "
                  f"{resolution}) once, into the cache {entry}", progress)
        # built in a temporary directory beside the entry, renamed into place whole (an incomplete leftover
        # entry, e.g. with files deleted by hand, is replaced); on any exception, Ctrl-C included, removed
        with atomic_dir(entry) as tmp:
            t0 = time.perf_counter()
            _build_entry(tmp, key, scene, aliasing, resolution, max_frames, build_config, projection_config,
                         progress)
            write_json(tmp / "autoloc.json", dict(header("autoloc_cache"), key=key,
                                                  seconds=round(time.perf_counter() - t0, 1)))
        _announce(f"localizer cache ready: {entry}", progress)
    return entry


def _build_entry(out: Path, key: dict, scene, aliasing, resolution, max_frames, build_config, projection_config,
                 progress: bool) -> None:
    from tqdm import tqdm

    from satloc.pipeline import build, train_projection

    speed, db, bc, pc = _configs(max_frames, build_config, projection_config)
    rec = out / "recording"
    stages = tqdm(total=3, desc="auto localizer", unit="stage", disable=not progress, leave=False)
    # localizer=None: the recorder's env must not itself ask for an auto localizer (infinite recursion)
    env = make_env(scene=os.fspath(scene), resolution=resolution, aliasing=aliasing, speed_mps=speed,
                   satellite_gap=key.get("satellite_gap", 0.0),   # load_scene: the same cache entry as None
                   depth=db.depth, labels=db.labels, localizer=None)
    try:
        env.reset(seed=db.seed)
        sc = env.scene
        sc.satmap.save(rec / "map")
        record_pass(env, db, db.route or sc.spec.database_route, rec / "database", "database", progress,
                    {"source": "satloc_env.envs.auto_localizer", "scene": sc.name, "aliasing": sc.spec.knobs.aliasing,
                     "satellite_gap": sc.spec.knobs.satellite_gap})
    finally:
        env.close()
    stages.update(1)
    build(rec / "database", rec / "map", out, bc, progress)
    stages.update(1)
    train_projection(out, pc, progress)
    stages.update(1)
    stages.close()
    shutil.rmtree(rec, ignore_errors=True)  # only the build is kept


def _stamp(build_dir: Path) -> tuple:
    return tuple((f, (build_dir / f).stat().st_mtime_ns if (build_dir / f).exists() else None)
                 for f in ("build.json", "dictionary.npz", "satellite_features.npz", "projections.pt"))


@functools.lru_cache(maxsize=2)
def _load(build_dir: str, mode: str, refine: bool, stamp: tuple):
    from satloc.localizers.database import LocalizerConfig
    from satloc.pipeline import load_localizer

    return load_localizer(build_dir, LocalizerConfig(mode=mode, refine=refine))


def load_cached_localizer(build_dir: str | os.PathLike, mode: str = "full", refine: bool = False):
    """:func:`satloc.pipeline.load_localizer` in ``mode`` (``refine``: with bird's-eye alignment), loaded once
    per process per (directory, mode, refine) while the directory's files are unchanged (loading builds the
    satellite table: seconds to minutes)."""
    b = Path(build_dir).expanduser().resolve()
    return _load(str(b), mode, bool(refine), _stamp(b))


def auto_localizer(scene: str | os.PathLike, aliasing: float | None = None, resolution: str = "half",
                   mode: str = "full", progress: bool = True, refine: bool = False,
                   satellite_gap: float | None = None):
    """The localizer of ``localizer="auto"``: :func:`auto_build_dir` loaded in ``mode``."""
    return load_cached_localizer(auto_build_dir(scene, aliasing, resolution, progress, satellite_gap=satellite_gap),
                                 mode, refine)


#: the fields of a cache key (:func:`cache_key`) and their types
_KEY_FIELDS = {"scene": str, "source": str, "scene_sha256": str, "aliasing": float, "resolution": str,
               "format_version": int, "satloc_version": str, "key_version": int, "speed_mps": float,
               "database_pass": dict, "build": dict, "projection": dict}


def describe_entry(entry: str | os.PathLike) -> dict[str, Any]:
    """The cache key an entry was built for (its ``autoloc.json``), checked field by field (a damaged or
    foreign file raises :class:`satloc.FormatError` naming it and the field)."""
    from satloc.errors import FormatError
    from satloc.persist import nonfinite_path

    path = Path(entry) / "autoloc.json"
    key = read_json(path, "autoloc_cache").get("key")
    # optional: satellite_gap (maps captured with a gap), features_id (entries made since the key held the FCN's)
    if not isinstance(key, dict) or set(key) - {"satellite_gap", "features_id"} != set(_KEY_FIELDS):
        got = sorted(key) if isinstance(key, dict) else type(key).__name__
        raise FormatError(f"{path}: field 'key': expected a mapping of {sorted(_KEY_FIELDS)}, got {got}")
    if not isinstance(key.get("features_id", ""), str):
        raise FormatError(f"{path}: key.features_id: expected str, got {str(key['features_id'])[:60]!r}")
    for k, tp in _KEY_FIELDS.items():
        v = key[k]
        ok = isinstance(v, (int, float) if tp is float else tp) and not isinstance(v, bool)
        if not ok:
            raise FormatError(f"{path}: key.{k}: expected {tp.__name__}, got {str(v)[:60]!r}")
    bad = nonfinite_path(key)
    if bad is not None:
        raise FormatError(f"{path}: key.{bad}: expected a finite number")
    gap = key.get("satellite_gap")
    if gap is not None and (isinstance(gap, bool) or not isinstance(gap, (int, float)) or not 0 < gap <= 1):
        raise FormatError(f"{path}: key.satellite_gap: expected a number in (0, 1], got {str(gap)[:60]!r}")
    if not (0 <= key["aliasing"] <= 1 and key["speed_mps"] > 0 and key["resolution"] in ("half", "full")):
        raise FormatError(f"{path}: key: expected aliasing in [0, 1], speed_mps > 0 and resolution half or full, got "
                          f"{key['aliasing']!r}, {key['speed_mps']!r}, {key['resolution'][:20]!r}")
    from satloc.config import from_dict
    from satloc.features.projection import ProjectionConfig
    from satloc.pipeline import BuildConfig

    from .record import PassConfig

    try:
        for k, cls in (("database_pass", PassConfig), ("build", BuildConfig), ("projection", ProjectionConfig)):
            from_dict(cls, key[k], f"{path}: key.{k}")
    except ConfigError as e:
        raise FormatError(str(e)) from e
    return key
