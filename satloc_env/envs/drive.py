"""The Gymnasium environment ``satloc/SatLoc-v0``: a car driving over a scene, seeing it in stereo.

Configuration is :class:`EnvConfig` (``SatLocEnv.default_config()`` as a dict); any field can be given as a
keyword to ``gymnasium.make`` and the per-episode ones (see :data:`EPISODE_KEYS`) again in
``reset(options={...})``. Unknown keys, wrong types and out-of-range values raise :class:`satloc.ConfigError`;
actions that are not 2 finite numbers raise :class:`ActionError` (a ValueError), finite ones are clipped to
the action space (see :class:`SatLocEnv`).

With a localizer (``localizer=``: ``"cross"``, the default, no database; ``"auto"``, the paper's method built
from the scene's database pass; a build directory or a :class:`satloc.localizers.database.Localizer`), every ``localize_every`` steps the stereo pair the agent sees is
localized against the satellite map and the result goes into ``info`` (see :class:`SatLocEnv`).
"""
from __future__ import annotations

import dataclasses
import math
import os
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Mapping

import cv2
import gymnasium as gym
import numpy as np
from gymnasium import spaces

from satloc.config import from_dict, override, to_dict
from satloc.errors import ConfigError, FormatError
from satloc.geometry import Pose2, StereoCamera
from satloc.labels import NUM_CLASSES
from satloc.localizers.gnss import GnssConfig, GnssReceiver
from satloc.persist import read_json
from satloc.satmap import SatelliteMap
from satloc.sequence import Frame
from satloc.tracking.track import compose_motion
from satloc_env.render.sensor import Sensor
from satloc_env.world.meshes import LOD_M
from satloc_env.world.revisit import PARTS as REVISIT_PARTS
from satloc_env.world.revisit import check_parts
from satloc_env.world.scene import Scene, load_scene

from .occluders import Appearance, sample_occluders
from .vehicle import (
    DEFAULT_DT,
    DEFAULT_SPEED_WANDER,
    DEFAULT_WANDER_M,
    Attitude,
    Autopilot,
    VehicleParams,
    Wander,
    action_bounds,
    default_wander_seed,
    drift_at,
    step_bicycle,
    wander_profile,
)


@dataclass
class EnvConfig:
    scene: str = "city"                     # shipped scene name, YAML path or saved scene directory
    resolution: Literal["half", "full"] = "half"   # 620x188 or 1242x375 (KITTI rig)
    route: str | None = None                # route name; default: the scene's database route
    lane_offset_m: float = -1.75            # lateral offset from the route centre line (left positive)
    wander_m: float = DEFAULT_WANDER_M      # the autopilot's lateral drift around the lane offset: std, metres
                                            # (a smooth random process along the route; satloc_env.envs.vehicle;
                                            # 0: exactly on the lane offset)
    speed_wander: float = DEFAULT_SPEED_WANDER   # the autopilot's speed drift: relative std
    wander_seed: int | None = None          # the drift's seed (None: drawn from the episode's seed)
    start_s_m: float = 0.0                  # start position along the route
    random_start: bool = False              # start at a random place on the route (from the episode seed)
    speed_mps: float = 8.0                  # autopilot cruising speed
    dt: float = DEFAULT_DT                  # seconds per step
    max_steps: int = 1000                   # episode time limit (truncation)
    depth: bool = False                     # add true left-camera depth (metres) to observations
    labels: bool = False                    # add left-camera semantic labels to observations
    odometry: Literal["noisy_truth", "visual"] = "noisy_truth"   # what the odometry observation is: the true
                                            # motion plus noise, or stereo visual odometry of the rendered pair
                                            # (satloc.tracking.vo; NaN where it fails)
    odometry_noise: tuple[float, float] = (0.02, 0.003)  # std: fraction of distance, radians per step
    aliasing: float | None = None           # scene knobs (None: the scene file's value)
    occlusion: float | None = None
    appearance: float | None = None
    change: float | None = None             # revisit change of the world (satloc_env.world.revisit): shadows of another
                                            # sun, road wear, parked cars moved, season; 0 none
    change_parts: tuple[str, ...] = REVISIT_PARTS   # which of those (satloc_env.world.revisit.PARTS: "vegetation",
                                            # "road", "cars", "shadows"): a revisit a few days later has no season
    satellite_gap: float | None = None      # how far the satellite map is a capture of the world, not the rendered
                                            # ground (satloc_env.world.capture); None: the scene's; fixed when made
    sensor: float = 0.0                     # the camera's vignetting, motion blur and noise (satloc_env.render.sensor):
                                            # 1 an automotive camera in daylight, 0 the renderer's exact pixels
    attitude: float = 1.0                   # the body's pitch and roll as the car brakes, accelerates, turns and rides
                                            # the road (satloc_env.envs.vehicle.Attitude): 1 a passenger car's, 0 a
                                            # level, fixed mount (the bird's-eye homography exact)
    anisotropy: int = 1                     # >1: anisotropic texture filtering (sharper far ground, ~4x slower on llvmpipe)
    zfar_m: float = 150.0
    detail_m: float | None = LOD_M          # street furniture and trees of their own species keep their full detail
                                            # within this many metres of the car; beyond, furniture is left out and
                                            # trees are drawn coarse (faster); None: full detail at any distance
    localizer: str | None = "cross"         # None/"none": off; "cross": no database, the satellite map alone
                                            # from a GPS-like prior (satloc_env.envs.cross_localizer); "auto": the
                                            # paper's method, a cached build of the scene's database pass
                                            # (satloc_env.envs.auto_localizer); else a build directory; a Localizer
                                            # instance given as the keyword is stored here as "<instance>"
    localizer_mode: Literal["full", "np", "go"] = "full"   # for "auto" / a build directory
    localizer_refine: bool = False          # for "auto" / a build directory: bird's-eye alignment (satloc.tracking.align)
    localizer_track: bool = False           # fuse each localization into a belief moved by the odometry
                                            # observations (satloc.tracking.track); a new episode starts a new belief
    localize_every: int = 1                 # localize at the steps that are multiples of this (reset: step 0)
    prior_radius_m: float = 20.0            # "cross": each localization's prior, drawn around the true pose as a
    prior_yaw_deg: float = 10.0             # GPS fix gives it: within this radius and heading range
    gnss: GnssConfig = field(default_factory=GnssConfig)   # how the prior's centre strays from the true pose
                                            # (satloc.localizers.gnss): "uniform" within the radius, step by step;
                                            # "receiver", a receiver's correlated error, multipath and outages
    reward: Literal["none", "neg_error"] = "none"  # neg_error: minus the localization error (metres)

    def __post_init__(self):
        # types are checked by satloc.config.from_dict; here the values (NaN and inf included), so that a bad
        # value fails when the env is made or reset, naming the field, instead of giving NaN poses later
        limits = VehicleParams()
        _check_finite(self, "lane_offset_m")
        _check_finite(self, "wander_m", lo=0.0, hi=0.5)
        _check_finite(self, "speed_wander", lo=0.0, hi=0.5)
        if self.wander_seed is not None and self.wander_seed < 0:
            raise ConfigError(f"wander_seed: expected an integer >= 0 or None, got {self.wander_seed}")
        _check_finite(self, "start_s_m", lo=0.0)   # its upper bound (the route's length) is checked at reset
        _check_finite(self, "speed_mps", lo=0.0, hi=limits.max_speed_mps)
        _check_finite(self, "dt", lo=0.0, lo_open=True)
        _check_finite(self, "zfar_m", lo=1.0)
        if self.detail_m is not None:
            _check_finite(self, "detail_m", lo=0.0)
        _check_noise(self.odometry_noise)
        for k in ("sensor", "attitude"):
            _check_finite(self, k, lo=0.0, hi=1.0)
        for k in ("aliasing", "occlusion", "appearance", "change", "satellite_gap"):
            v = getattr(self, k)
            if v is not None and not 0.0 <= v <= 1.0:   # False for NaN
                raise ConfigError(f"{k}: expected a value in [0, 1] (or None: the scene's), got {v}")
        check_parts(self.change_parts, "change_parts")
        from satloc.localizers.crossview import Prior

        Prior(0.0, 0.0, 0.0, self.prior_radius_m, self.prior_yaw_deg)   # a prior's checks, naming the field
        for k in ("max_steps", "anisotropy", "localize_every"):
            if getattr(self, k) < 1:
                raise ConfigError(f"{k}: expected an integer >= 1, got {getattr(self, k)}")
        if not self.scene:
            raise ConfigError("scene: expected a shipped scene name, a scene YAML or a saved scene directory, got ''")


def _check_finite(cfg, name: str, lo: float | None = None, hi: float | None = None, lo_open: bool = False) -> None:
    """``cfg.name`` must be finite and within [lo, hi] (``lo_open``: above ``lo``); else :class:`ConfigError`."""
    v = getattr(cfg, name)
    below = lo is not None and (v <= lo if lo_open else v < lo)
    if not math.isfinite(v) or below or (hi is not None and v > hi):
        if lo is None and hi is None:
            rng = "a finite number"
        elif hi is None:
            rng = f"a finite number {'>' if lo_open else '>='} {lo:g}"
        else:
            rng = f"a finite number in [{lo:g}, {hi:g}]"
        raise ConfigError(f"{name}: expected {rng}, got {v}")


def _check_noise(noise) -> None:
    if len(noise) != 2 or not all(math.isfinite(v) and v >= 0 for v in noise):
        raise ConfigError(f"odometry_noise: expected 2 non-negative numbers (finite): the std as a fraction of the "
                          f"distance and in radians per step, got {tuple(noise)}")


class ActionError(ValueError):
    """An action the environment cannot apply (wrong shape or type, NaN or inf); the message says what was
    expected. A ValueError, as gymnasium's own checks raise for bad actions."""


#: the spawn key of the seed sequence the GPS-like priors of ``localizer="cross"`` are drawn from
PRIOR_SPAWN_KEY = 104729

#: the spawn key of the seed sequence the localizer's ``context.seed`` is drawn from
LOCALIZER_SPAWN_KEY = 130363
#: spawn keys of the camera's noise and the body's ride: none of the episode's other draws change with them
SENSOR_SPAWN_KEY, ATTITUDE_SPAWN_KEY = 154303, 179426

#: the value of ``EnvConfig.localizer`` when a localizer object (or a class that makes one) was passed.
LOCALIZER_INSTANCE = "<instance>"


#: keys that ``reset(options=...)`` may change; the others fix the spaces or the renderer.
EPISODE_KEYS = frozenset({
    "scene", "route", "lane_offset_m", "start_s_m", "random_start", "speed_mps", "max_steps",
    "odometry", "odometry_noise", "aliasing", "occlusion", "appearance", "change", "change_parts",
    "wander_m", "speed_wander", "wander_seed", "sensor", "attitude",
})


# --- shared by SatLoc-v0 and SatLocReplay-v0 (satloc_env.envs.replay) ----------------------------------------------
class _Shared:
    """Holds an object given to ``gym.make`` (a Localizer, a Sequence, a SatelliteMap) in ``env.spec.kwargs``;
    copies share it (see :class:`SharedSpecMixin`)."""

    __slots__ = ("obj",)

    def __init__(self, obj):
        self.obj = obj

    def __copy__(self):
        return self

    def __deepcopy__(self, memo):
        return self

    def __repr__(self) -> str:
        return f"<shared {type(self.obj).__name__}>"


def unshare(value: Any) -> Any:
    """The object a :class:`_Shared` holder holds (anything else unchanged)."""
    return value.obj if isinstance(value, _Shared) else value


class SharedSpecMixin:
    """An object given to ``gym.make`` as one of the keywords in ``_SHARED_KWARGS`` ends up in
    ``env.spec.kwargs``, which gymnasium deep-copies (wrappers' spec, ``spec.make()``); it is wrapped in a
    holder that those copies share (a Localizer holds OpenCV/faiss objects; a lazy Sequence a reader)."""

    _SHARED_KWARGS: tuple[str, ...] = ("localizer",)
    _spec = None

    @property
    def spec(self):
        return self._spec

    @spec.setter
    def spec(self, value):
        if value is not None:
            wrap = {k: _Shared(v) for k, v in value.kwargs.items() if k in self._SHARED_KWARGS
                    and v is not None and not isinstance(v, (str, os.PathLike, _Shared))}
            if wrap:
                value = dataclasses.replace(value, kwargs={**value.kwargs, **wrap})
        self._spec = value


def _split_localizer(config: dict, owner: str = "SatLocEnv", allow_auto: bool = True) -> tuple[dict, Any]:
    """Config with an object given as the ``localizer`` keyword (a localizer of the common interface, a class or
    function that makes one, or the paper's method's :class:`satloc.localizers.database.Localizer`) replaced by its
    marker, and the object."""
    config = dict(config)
    if "localizer" not in config:
        return config, None
    value = config["localizer"] = unshare(config["localizer"])
    if value is None or isinstance(value, str):
        return config, None
    if isinstance(value, os.PathLike):
        config["localizer"] = os.fspath(value)
        return config, None
    if not (callable(getattr(value, "localize", None)) or callable(value)):
        auto = " 'auto'," if allow_auto else ""
        raise ConfigError(f"{owner} config.localizer: expected None, 'none', 'cross',{auto} a build directory, "
                          "'module:Name', or a localizer object (one with reset(context) and localize(query), see "
                          f"satloc.localizers.interface) or a class that makes one, got {type(value).__name__} "
                          f"{value!r}")
    config["localizer"] = LOCALIZER_INSTANCE
    return config, value


def make_localizer(value: Any, track: bool, owner: str = "SatLocEnv") -> tuple[Any, dict]:
    """The localizer of the common interface an environment uses for ``value`` (an object given as the
    ``localizer`` keyword, or a ``module:Name`` string), and what is known of it (``source`` for messages): a
    localizer object as it is; a class or function called to make one; the paper's method's engine wrapped
    (:meth:`satloc.localizers.database.Localizer.as_localizer`, tracked with ``track`` or its own
    ``config.track``). ``localizer_track`` (``track``) is an option of the built-in localizers only."""
    from satloc.localizers.interface import localizer_name, resolve_localizer

    if isinstance(value, str):
        loc = resolve_localizer(value, f"{owner} config.localizer {value!r}")
        ident = {"source": f"the localizer {value!r}"}
    elif (not isinstance(value, type) and not callable(getattr(value, "reset", None))
          and callable(getattr(value, "as_localizer", None))):
        loc = value.as_localizer(track=track or None)
        return loc, {"source": "the Localizer instance"}
    else:   # an instance as it is; a class or a function made into one
        loc = resolve_localizer(value, f"{owner} config.localizer")
        ident = {"source": f"the localizer {localizer_name(loc)!r}"}
    if track:
        named = "'cross', 'auto' or a build directory" if owner == "SatLocEnv" else "'cross' or a build directory"
        raise ConfigError(f"localizer_track: tracks the localizers the environment makes ({named}); "
                          f"{ident['source']} is an object given to it, which tracks as it was made (a localizer "
                          "of your own gets every query's odometry; a built-in one takes track=True where made)")
    return loc, ident


def check_reset_options(options: Any, episode_keys: frozenset, cls: type) -> dict:
    """``reset(options=...)`` as a dict of per-episode keys; :class:`ConfigError` naming the keys that are unknown
    (not a field of ``cls``) or fixed when the env is made. Values are checked by the caller (``override``)."""
    if options is None:
        return {}
    if not isinstance(options, Mapping):
        raise ConfigError(f"reset options: expected a dict of per-episode keys {sorted(episode_keys)}, got "
                          f"{type(options).__name__} {options!r}")
    options = dict(options)
    bad_type = [k for k in options if not isinstance(k, str)]
    if bad_type:
        raise ConfigError(f"reset options: keys must be strings, got {bad_type}")
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(k for k in options if k not in fields)
    fixed = sorted(k for k in options if k in fields and k not in episode_keys)
    if unknown:
        raise ConfigError(f"reset options: {unknown} cannot change per episode: unknown key(s) (not a field of "
                          f"{cls.__name__}); the per-episode keys are {sorted(episode_keys)}")
    if fixed:
        raise ConfigError(f"reset options: {fixed} cannot change per episode: fixed when the env is made "
                          f"(give them to gymnasium.make); the per-episode keys are {sorted(episode_keys)}")
    return options


def check_localizer_config(cfg, have_instance: bool, allow_auto: bool = True, allow_cross: bool | None = None):
    """``cfg`` (an env config dataclass with the fields ``localizer``, ``localizer_track``, ``localize_every`` and
    ``reward``) with ``localizer`` normalised ("none" -> None, a build directory -> its path); raises
    :class:`ConfigError` for a bad combination. ``allow_cross`` (default: ``allow_auto``): whether ``"cross"``
    (:mod:`satloc_env.envs.cross_localizer`) is allowed."""
    allow_cross = allow_auto if allow_cross is None else allow_cross
    loc = cfg.localizer
    if loc is not None and loc.strip().lower() == "none":
        cfg = dataclasses.replace(cfg, localizer=None)
        loc = None
    if loc == LOCALIZER_INSTANCE and not have_instance:
        raise ConfigError(f"localizer: {LOCALIZER_INSTANCE!r} stands for a localizer object passed as the "
                          "localizer keyword; pass the object itself")
    if loc == "auto" and not allow_auto:
        raise ConfigError("localizer: 'auto' builds a localizer from a simulated scene's database pass, which a "
                          "replay has not; expected None, 'none', 'cross', a build directory, 'module:Name' or a "
                          "localizer object")
    if loc == "cross" and not allow_cross:
        raise ConfigError("localizer: 'cross' localizes from a prior drawn around the true pose, which this "
                          "environment has not; expected None, 'none', a build directory, 'module:Name' or a "
                          "localizer object")
    if loc == "cross" and getattr(cfg, "localizer_refine", False):
        raise ConfigError("localizer_refine: the 'cross' localizer aligns the bird's-eye view already; refinement "
                          "is an option of 'auto' and build directories")
    if loc not in (None, "auto", "cross", LOCALIZER_INSTANCE) and not is_localizer_spec(loc):
        p = Path(loc).expanduser()
        if not (p / "build.json").is_file():
            auto = " 'auto'," if allow_auto else ""
            raise ConfigError(f"localizer: {loc!r} is not a build directory (no build.json); expected None, "
                              f"'none',{auto}{' cross,' if allow_cross else ''} a directory written by `satloc build`, "
                              "'module:Name' (a localizer of your own) or a localizer object")
        cfg = dataclasses.replace(cfg, localizer=str(p))
    if cfg.localizer_track and loc is None:
        raise ConfigError("localizer_track: tracking needs a localizer (localizer is None)")
    if cfg.localize_every < 1:
        raise ConfigError(f"localize_every: expected an integer >= 1, got {cfg.localize_every}")
    if cfg.reward == "neg_error" and loc is None:
        raise ConfigError("reward: 'neg_error' needs a localizer (localizer is None)")
    return cfg


def close_localizer(loc) -> None:
    """A localizer's optional ``close()`` (what it holds: a model, files, processes), once."""
    closer = getattr(loc, "close", None)
    if callable(closer) and not getattr(loc, "_satloc_closed", False):
        closer()
        try:
            loc._satloc_closed = True
        except AttributeError:   # slots or a frozen object: it may be closed again
            pass


def is_localizer_spec(value: str) -> bool:
    """Whether ``value`` names a localizer of one's own (``module:Name`` or ``path/to/file.py:Name``) rather
    than a build directory."""
    head, sep, tail = value.rpartition(":")
    return bool(sep and head and tail) and not Path(value).expanduser().is_dir()


def build_identity(build_dir: str | os.PathLike) -> dict:
    """What a build directory tells of the data it was built from, as far as it is known: ``scene`` and
    ``aliasing`` (a simulated database pass's ``meta``, or an auto cache entry's key), ``geo_frame`` (a real-data
    database's frame, as a dict) and always ``source``, the build described in words for messages."""
    b = Path(build_dir)
    out: dict = {"source": f"the build {str(b)!r}"}
    meta: dict = {}
    try:
        db = read_json(b / "build.json", "build").get("database")
        if db and (Path(db) / "sequence.json").is_file():
            meta = read_json(Path(db) / "sequence.json", "sequence").get("meta") or {}
        if "scene" not in meta and (b / "autoloc.json").is_file():
            key = read_json(b / "autoloc.json", "autoloc_cache").get("key") or {}
            meta = {**meta, **{k: key[k] for k in ("scene", "aliasing", "satellite_gap") if k in key}}
    except (FormatError, OSError, AttributeError):  # an unreadable record only loses the description
        pass
    if isinstance(meta, dict) and isinstance(meta.get("scene"), str) and "geo_frame" not in meta:
        meta.setdefault("satellite_gap", 0.0)   # a simulated pass recorded before the knob: the ground's copy
    for k in ("scene", "aliasing", "satellite_gap", "geo_frame"):
        if meta.get(k) is not None:
            out[k] = meta[k]
    if isinstance(out.get("scene"), str):
        out["source"] += f" of scene {out['scene']!r}" + (f" (aliasing {out['aliasing']:g})"
                                                           if isinstance(out.get("aliasing"), (int, float)) else "")
        gap = out.get("satellite_gap")
        if isinstance(gap, (int, float)) and gap:
            out["source"] += f" (satellite gap {gap:g})"
    return out


def _describe_map(shape, mpp: float, origin) -> str:
    return f"{shape[1]}x{shape[0]} px at {mpp:g} m/px, top-left corner ({origin[0]:g}, {origin[1]:g}) m"


#: the content check of :func:`check_localizer_map`: the two maps are compared in cells of this many pixels a
#: side; a cell differs when its mean colour differs by more than MAP_CELL_LEVELS grey levels, and the maps
#: differ when more than MAP_MAX_DIFFERING of the cells do. Measured: the same map 0 % (bilateral filtering and
#: float16 storage move a cell's mean by under 1 level); city against city with aliasing 0.5, 22 %; two
#: one-block scenes of different seeds, 43 %.
MAP_CELL_PX = 8
MAP_CELL_LEVELS = 20.0
MAP_MAX_DIFFERING = 0.02


def _rgb_channels(extractor) -> slice | None:
    """The channels of the localizer's satellite features that are the map's (bilateral-filtered) colours in
    [0, 1], or None when it has none (the ``semantic`` feature set)."""
    from satloc.features import BilateralRGB, FeatureStack

    if isinstance(extractor, BilateralRGB):
        return slice(0, 3)
    if (isinstance(extractor, FeatureStack) and extractor.extractors
            and isinstance(extractor.extractors[0], BilateralRGB) and extractor.weights[0] == 1.0):
        return slice(0, 3)
    return None


def map_difference(localizer, satmap: SatelliteMap) -> float | None:
    """The fraction of cells in which the colours of the map the localizer was built on (its satellite features'
    RGB channels) differ from ``satmap``'s image (see :data:`MAP_CELL_PX`); None when they cannot be compared (no
    RGB channels, or maps of different sizes)."""
    sf = localizer.satfeat
    rgb = _rgb_channels(localizer.extractor)
    img = satmap.image
    if rgb is None or sf.features.shape[:2] != img.shape[:2] or sf.features.shape[2] < 3 or img.ndim != 3:
        return None
    c = MAP_CELL_PX
    h, w = (img.shape[0] // c) * c, (img.shape[1] // c) * c
    if h == 0 or w == 0:
        return None
    diff = np.zeros((h // c, w // c), np.float64)
    for ch in range(3):  # one channel at a time: a float32 copy of one channel of the map, not of all features
        a = sf.features[:h, :w, rgb.start + ch].astype(np.float32).reshape(h // c, c, w // c, c).mean((1, 3)) * 255
        b = img[:h, :w, ch].astype(np.float32).reshape(h // c, c, w // c, c).mean((1, 3))
        diff += np.abs(a - b) / 3
    return float(np.mean(diff > MAP_CELL_LEVELS))


def check_localizer_map(localizer, satmap, what: str, source: str = "the localizer") -> float | None:
    """Refuse a localizer whose satellite map is not ``satmap`` (the map of ``what``): another size, resolution or
    origin, or (where the localizer's features hold the map's colours) other content. ``source`` names the
    localizer in the message (e.g. its build directory and scene). Returns :func:`map_difference` (None: the
    content could not be compared)."""
    sf = getattr(localizer, "satfeat", None)
    if sf is None:
        return None
    sm = satmap
    same = (sf.features.shape[:2] == sm.image.shape[:2]
            and abs(sf.meters_per_pixel - sm.meters_per_pixel) < 1e-9
            and np.allclose(sf.origin, sm.origin, atol=1e-6))
    if not same:
        raise ConfigError(f"localizer: {source} was built on a satellite map "
                          f"({_describe_map(sf.features.shape, sf.meters_per_pixel, sf.origin)}) that is not the map "
                          f"of {what} ({_describe_map(sm.image.shape, sm.meters_per_pixel, sm.origin)}); a localizer "
                          "localizes only on the map it was built on")
    frac = map_difference(localizer, sm)
    if frac is not None and frac > MAP_MAX_DIFFERING:
        raise ConfigError(f"localizer: {source} was built on a satellite map of the same size as the map of {what} "
                          f"({_describe_map(sm.image.shape, sm.meters_per_pixel, sm.origin)}) but with other content "
                          f"({frac:.0%} of its {MAP_CELL_PX}x{MAP_CELL_PX}-pixel cells differ by more than "
                          f"{MAP_CELL_LEVELS:g} grey levels): it is not the map of {what}; a localizer localizes only "
                          "on the map it was built on")
    return frac


class LocalizationState:
    """The localizer in an environment loop (shared by SatLoc-v0 and SatLocReplay-v0), through the common
    interface (:mod:`satloc.localizers.interface`).

    :meth:`begin` starts an episode (the localizer's ``reset(context)``); :meth:`localize` asks it for a frame,
    with the odometry given to :meth:`add_odometry` since the previous localization (None at the first one and
    where some of that motion is unknown) and the prior, and keeps the answer as the fixed-shape ``info`` arrays
    that :meth:`info` returns with ``error_m`` against the current true pose, and as the :class:`PosteriorView`
    the render panels draw. A frame with no answer (the localizer returns None or raises :class:`ConfigError`,
    e.g. no grid sample with valid stereo depth) gives NaN ``estimate``, zero posterior, ``inlier`` False, and
    its message in :attr:`error`."""

    def __init__(self, localizer=None):
        self.localizer = localizer
        self.reset()

    def reset(self) -> None:
        """No result, no odometry (the localizer keeps its state until :meth:`begin`)."""
        self.arrays: dict | None = None     # latest result as info arrays (error_m is added by info())
        self.view: PosteriorView | None = None
        self.error: str | None = None       # message of the last frame that could not be localized
        self.odo_since = np.zeros(3)        # odometry since the last localization
        self.motion_known = True            # False: some motion since the last localization is unknown
        self.count = 0                      # localizations this episode

    def begin(self, context) -> None:
        """A new episode: :meth:`reset`, then the localizer's ``reset(context)``."""
        self.reset()
        if self.localizer is not None:
            self.localizer.reset(context)

    @property
    def localized(self) -> bool:
        """Whether a localization was attempted this episode."""
        return self.arrays is not None

    @property
    def posterior_k(self) -> int:
        """The posterior entries ``info`` reports: the localizer's ``posterior_k``, else 32."""
        from satloc.localizers.interface import DEFAULT_POSTERIOR_K

        k = getattr(self.localizer, "posterior_k", DEFAULT_POSTERIOR_K)
        return int(k) if isinstance(k, (int, np.integer)) and not isinstance(k, bool) and k > 0 else DEFAULT_POSTERIOR_K

    @property
    def needs_frame_depth(self) -> bool:
        """A localizer with ``wants_depth`` (the paper's method with ``depth_source="frame"``) reads the
        simulator's true depth in the frame."""
        return self.localizer is not None and bool(getattr(self.localizer, "wants_depth", False))

    def add_odometry(self, odometry) -> None:
        """The odometry (dx, dy, dyaw) of one step; a non-finite one marks the motion unknown."""
        o = np.asarray(odometry, np.float64).reshape(-1)
        if o.shape != (3,) or not np.all(np.isfinite(o)):
            self.motion_known = False
        elif self.motion_known:
            self.odo_since = compose_motion(self.odo_since, o)

    def localize(self, frame: Frame, step: int, prior=None) -> None:
        """Localize ``frame`` (no pose) at ``step`` with ``prior`` (a :class:`satloc.localizers.interface.Prior`
        or None)."""
        from satloc.localizers.interface import Query, as_estimate, localizer_name

        loc = self.localizer
        if loc is None:
            return
        k = self.posterior_k
        odometry = Pose2(*self.odo_since) if self.count > 0 and self.motion_known else None
        query = Query(frame, odometry, prior, self.count, float(frame.timestamp))
        self.count += 1
        self.odo_since, self.motion_known = np.zeros(3), True
        try:
            r = as_estimate(loc.localize(query), f"localizer {localizer_name(loc)!r}")
        except ConfigError as e:  # no grid sample with valid depth (e.g. a wall fills the view): no result
            r, message = None, str(e)
        else:
            message = "no answer (the localizer returned None)"
        if r is None:
            self.error = message
            self.arrays = {"estimate": np.full(3, np.nan), "posterior_poses": np.zeros((k, 3)),
                           "posterior_probs": np.zeros(k), "inlier": np.bool_(False),
                           "inlier_score": np.float64(0.0), "localized_step": np.int64(step)}
            self.view = None
            return
        self.error = None
        poses, probs = r.top(k)
        self.arrays = {"estimate": np.asarray(r.pose.as_array(), np.float64),
                       "posterior_poses": np.asarray(poses, np.float64),
                       "posterior_probs": np.asarray(probs, np.float64),
                       "inlier": np.bool_(r.inlier), "inlier_score": np.float64(r.inlier_score),
                       "localized_step": np.int64(step)}
        cand = r.candidates if r.candidates is not None else r.pose.as_array()[None]
        post = r.posterior if r.posterior is not None else np.ones(1)
        self.view = PosteriorView(np.asarray(cand, np.float64), np.asarray(post, np.float64),
                                  self.arrays["estimate"].copy(), bool(r.inlier))

    def info(self, pose: np.ndarray) -> dict:
        """The localization keys of ``info`` (none before the first localization); ``error_m`` is the planar
        distance from the estimate to ``pose`` (x, y, yaw), NaN when either is unknown."""
        if self.arrays is None:
            return {}
        out = {k: v.copy() for k, v in self.arrays.items()}
        est = out["estimate"]
        out["error_m"] = np.float64(math.hypot(est[0] - pose[0], est[1] - pose[1]))
        return out


#: (scene, route, lane offset, speed, dt) drives already checked in this process (weakly keyed by the scene)
_DRIVABLE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def check_drivable(scene: Scene, route: str, lane_offset_m: float, speed_mps: float, dt: float, where: str) -> None:
    """:func:`satloc_env.envs.drivecheck.check_route` once per scene, route, lane offset, speed and step in
    this process (a vector env's sub-environments share it): the autopilot can drive the route at that lane
    offset without leaving the road, else the ConfigError ``satloc scene`` gives."""
    from .drivecheck import check_route

    done = _DRIVABLE.setdefault(scene, set())
    key = (route, float(lane_offset_m), float(speed_mps), float(dt))
    if key in done:
        return
    check_route(scene, route, lane_offset_m, max(float(speed_mps), 1.0), dt, where=where)
    done.add(key)


def check_localizer_camera(localizer, camera: StereoCamera, what: str, source: str = "the localizer") -> None:
    """Refuse a localizer built for another camera than ``camera`` (``what`` names where it comes from, ``source``
    the localizer); the message gives both cameras' differing fields."""
    c = localizer.camera
    if (c.width, c.height) != (camera.width, camera.height):
        rig = c.rig_differences(camera, 1e-6, 1e-6, 1e-6)   # the sequence's values against the localizer's
        why = ("" if not rig else
               f"; images are resampled into a localizer's camera only when the two rigs are the same, and these "
               f"differ ({what} against the localizer: {', '.join(rig)}): use a localizer built from a database "
               f"taken with this rig (satloc build --database <a recording or drive of it>)")
        raise ConfigError(f"localizer: {source} was built for {c.width}x{c.height} images, but {what} has "
                          f"{camera.width}x{camera.height} images{why}")
    diff = [f"{f.name} {getattr(c, f.name):g} vs {getattr(camera, f.name):g}"
            for f in dataclasses.fields(StereoCamera)
            if not math.isclose(getattr(c, f.name), getattr(camera, f.name), rel_tol=1e-6, abs_tol=1e-6)]
    if diff:
        raise ConfigError(f"localizer: {source} was built for another camera than that of {what} (localizer vs "
                          f"{what}: " + ", ".join(diff) + ")")


class SatLocEnv(SharedSpecMixin, gym.Env):
    """Drive a stereo-camera car over a textured scene rendered from its satellite tile.

    Observation (Dict): ``left``, ``right`` uint8 RGB images; ``odometry`` float32 (dx, dy, dyaw) of the
    motion since the previous step in the previous vehicle frame: with ``odometry="noisy_truth"`` (the default)
    the true motion plus noise, with ``odometry="visual"`` the stereo visual odometry of the rendered pairs
    (:class:`satloc.tracking.vo.StereoVO`; NaN on a step where it fails: the tracked localizer then starts a new belief);
    ``depth`` (float32 metres in [0, ``zfar_m``], 0 = nothing) and ``labels`` (uint8 class ids) when enabled.
    The ``odometry`` Box is unbounded, so ``check_env`` warns about it: the noise of ``noisy_truth`` is
    Gaussian, and ``visual`` reports NaN on a step it cannot measure.

    Action: Box [speed m/s, yaw rate rad/s] = ``[0, -1]`` to ``[20, 1]``, applied through a kinematic bicycle
    model. ``autopilot_action()`` returns the route follower's action for scripts.

    * An action must be 2 finite numbers of shape (2,) (a list, a tuple or an integer or float array). Another
      shape, a non-numeric dtype (strings, booleans, objects), NaN or inf raise :class:`ActionError` (a
      ``ValueError``) naming what was expected; the episode is left as it was.
    * Finite values outside the Box are **clipped** to it, each component on its own: a speed below 0 is 0 (the
      car does not reverse), above 20 is 20 m/s; a yaw rate beyond +-1 rad/s is +-1. The bicycle model then
      limits the steering angle to +-0.6 rad (wheelbase 2.7 m), so the yaw rate actually applied is at most
      ``speed * tan(0.6) / 2.7`` (and 0 at standstill). ``info["odometry_true"]`` shows the motion that resulted.

    Configuration errors (:class:`satloc.ConfigError`, naming the field): unknown keys, wrong types (a string
    where a number is expected, a bool for a number), NaN or inf in any number, and values out of range:
    ``speed_mps`` in [0, 20], ``dt`` > 0, ``start_s_m`` in [0, route length] (checked at reset),
    ``max_steps``, ``localize_every`` and ``anisotropy`` >= 1, the knobs in [0, 1], ``odometry_noise`` two
    non-negative numbers. ``reset(options=...)`` must be a dict of keys in :data:`EPISODE_KEYS`; a key that is
    unknown, or fixed when the env is made (``resolution``, ``localizer``, ...), is named in the error. Options
    hold for one episode only. After a reset that raised, ``step`` raises ``RuntimeError`` until a reset
    succeeds.

    ``info``: ``pose`` (x, y, yaw), ``odometry_true``, ``route_s``, ``off_road``, ``route_complete``,
    ``step`` - all fixed-shape numpy values.

    Localization (``localizer`` not None / ``"none"``). ``localizer`` is ``"cross"`` (the default: no database,
    the scene's satellite map alone, each localization from a prior drawn around the true pose within
    ``prior_radius_m`` / ``prior_yaw_deg`` as a GPS fix gives it, :mod:`satloc_env.envs.cross_localizer`; the
    first use of a scene costs seconds; the posterior's candidates are positions and headings within the prior,
    ``inlier_score`` its best correlation), ``"auto"`` (the paper's method: a localizer
    built from the scene's database pass, cached on disk by :mod:`satloc_env.envs.auto_localizer`; the first use of a
    scene costs minutes), a build directory of ``satloc build`` + ``satloc train-projection`` (loaded in mode
    ``localizer_mode``), or a :class:`satloc.localizers.database.Localizer` given as the ``localizer`` keyword (its own
    mode holds; ``config.localizer`` then reads ``"<instance>"``). At reset and at every step that is a
    multiple of ``localize_every``, the observed (appearance-changed) stereo pair is localized; ``info`` then
    always carries the latest result, with K = the localizer's ``posterior_k``:

    * ``estimate`` (3,) float64: x, y, yaw;
    * ``error_m`` float64: planar distance from ``estimate`` to the *current* true ``pose`` (between
      localizations it grows with the motion since ``localized_step``; the estimate is not propagated);
    * ``posterior_poses`` (K, 3) and ``posterior_probs`` (K,) float64: the K most probable candidate poses
      and their probabilities (zero-padded);
    * ``inlier`` np.bool_ and ``inlier_score`` float64 (single images: the peak / mean score; tracked: the
      probability of being on the mapped path, :attr:`satloc.tracking.track.Tracker.p_on`; False means "probably
      outside the mapped area");
    * ``localized_step`` int64: the step the result was computed at.

    With ``localizer_track`` each localization is fused into a belief over the candidate poses that the
    odometry observations move between localizations (:mod:`satloc.tracking.track`; ``"cross"``: the previous answer
    moved by them, :class:`satloc.localizers.crossview.CrossViewTracker`): the posterior, estimate and
    error are then the tracked ones. The belief starts again at every reset. A Localizer instance whose
    ``config.track`` is set is tracked too.

    A localizer given as a build directory or an instance is checked when the env is made, and again whenever
    ``reset(options={"scene": ...})`` changes the scene: :class:`satloc.ConfigError` if it was built for
    another camera (image size, intrinsics, baseline, mounting height or pitch: both cameras' values are given)
    or on another satellite map than the scene's: another size, resolution or origin, or the same size but
    other content (the localizer's features hold the map's colours for the ``rgb`` and ``default`` feature
    sets; more than :data:`MAP_MAX_DIFFERING` of 8x8-pixel cells differing by 20 grey levels, e.g. the same
    scene at another ``aliasing``). For the ``semantic`` feature set, whose features hold no colours, a build
    directory's recorded scene and aliasing are compared instead. The message names the localizer (its build
    directory and the scene it records, where known) and the scene. ``"auto"`` always builds for the scene.

    A frame in which no grid sample has valid stereo depth (e.g. a wall fills the view) has no result: the
    localizer raises :class:`satloc.ConfigError`, which is caught; ``estimate`` and ``error_m`` are NaN,
    ``posterior_*`` zeros, ``inlier`` False, ``inlier_score`` 0 and the error message is kept in
    ``env.unwrapped.localization_error``. Without a localizer these keys are absent.

    Revisit change (``change`` > 0, :mod:`satloc_env.world.revisit`): the episode sees a world built from a changed
    layout (shadows of another sun, road wear, parked cars moved, another season), seeded from the episode's
    seed (``change_seed``); the satellite map stays the scene's. The last two such worlds are kept per process.

    Reward: 0 (``reward="none"``), or with ``reward="neg_error"`` minus ``error_m`` (0 while there is no
    result, i.e. after a frame without valid depth). ``neg_error`` needs a localizer.

    A Localizer instance is shared, not copied, by ``env.spec.make()``; it cannot be pickled, so for
    ``gym.make_vec(..., vectorization_mode="async")`` pass a build directory (or ``"auto"``) instead.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, render_mode: str | None = None, **config: Any):
        if render_mode not in (None, "rgb_array"):
            raise ConfigError(f"render_mode: expected None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        config, instance = _split_localizer(config)
        self._loc = LocalizationState()        # the localizer in use and its latest result (see LocalizationState)
        self._vo = None                        # satloc.tracking.vo.StereoVO of the episode (odometry="visual")
        self.config = from_dict(EnvConfig, config, "SatLocEnv config")
        self._check_localizer_config(instance is not None)
        self.camera = StereoCamera.preset(self.config.resolution)
        self.vehicle = VehicleParams()
        h, w = self.camera.height, self.camera.width
        obs = {
            "left": spaces.Box(0, 255, (h, w, 3), np.uint8),
            "right": spaces.Box(0, 255, (h, w, 3), np.uint8),
            "odometry": spaces.Box(-np.inf, np.inf, (3,), np.float32),
        }
        if self.config.depth:
            obs["depth"] = spaces.Box(0.0, self.config.zfar_m, (h, w), np.float32)   # 0: nothing; nothing beyond zfar
        if self.config.labels:
            obs["labels"] = spaces.Box(0, NUM_CLASSES - 1, (h, w), np.uint8)
        self.observation_space = spaces.Dict(obs)
        v = self.vehicle
        self.action_space = spaces.Box(*action_bounds(v))
        self._episode = self.config
        self._scene: Scene | None = None
        self._scene_key: tuple | None = None
        self._renderer = None
        self._batch = None                     # a BatchStereoRenderer shared with other environments (vector env)
        self.pose = Pose2()
        self._last_obs: dict | None = None
        self._last_depth: np.ndarray | None = None
        self._ready = False                    # True after a successful reset
        self.change_seed: int | None = None   # the episode's revisit change seed (with change > 0)
        self._preloaded: tuple | None = None   # (scene key, Scene) loaded by __init__ for the localizer check
        self.last_prior = None                 # the prior of the last localization (satloc.localizers.interface.Prior)
        self._loc_identity: dict = {"source": "the localizer"}   # what is known of the localizer's data
        cfg = self.config
        if instance is not None or (cfg.localizer is not None and is_localizer_spec(cfg.localizer)):
            self.localizer, self._loc_identity = make_localizer(instance if instance is not None else cfg.localizer,
                                                                cfg.localizer_track)
            engine = getattr(self.localizer, "engine", None)   # the paper's method given as its engine
            if (engine is not None and instance is not None and not callable(getattr(instance, "reset", None))
                    and hasattr(engine.config, "mode")):
                self.config = dataclasses.replace(cfg, localizer_mode=engine.config.mode,
                                                  localizer_refine=engine.config.refine,
                                                  localizer_track=bool(self.localizer.track))
        elif cfg.localizer not in (None, "auto", "cross"):
            from .auto_localizer import load_cached_localizer

            self.localizer = load_cached_localizer(cfg.localizer, cfg.localizer_mode,
                                                   cfg.localizer_refine).as_localizer(cfg.localizer_track)
            self._loc_identity = build_identity(cfg.localizer)
        key = (self.config.scene, self.config.aliasing, self.config.satellite_gap)
        scene = load_scene(*key)
        if self.localizer is not None:
            self._check_localizer_camera()
            # a localizer of another scene fails here, when the env is made, not at the first reset
            self._check_localizer_map(scene)
        # a route the autopilot cannot drive fails here too, as `satloc scene` says it
        self._check_route(scene, self.config)
        self._preloaded = (key, scene)

    def _check_route(self, scene: Scene, cfg: EnvConfig) -> None:
        route = cfg.route or scene.spec.database_route
        if route not in scene.routes:
            raise ConfigError(f"route: {route!r} is not a route of scene {scene.name!r} ({sorted(scene.routes)})")
        check_drivable(scene, route, cfg.lane_offset_m, cfg.speed_mps, cfg.dt, f"SatLocEnv scene {scene.name!r}")

    # --- localization state (kept in self._loc, shared code with the replay environment) ----------------
    @property
    def localizer(self):
        """The :class:`satloc.localizers.database.Localizer` in use (None: off)."""
        return self._loc.localizer

    @localizer.setter
    def localizer(self, value) -> None:
        self._loc.localizer = value

    @property
    def localization_error(self) -> str | None:
        """The message of the last frame that could not be localized (None after a result)."""
        return self._loc.error

    @property
    def _tracker(self):
        """The built-in localizer's tracker of this episode (None: not tracked, or a localizer of one's own)."""
        return getattr(self._loc.localizer, "tracker", None)

    # --- configuration ----------------------------------------------------------------------------
    @staticmethod
    def default_config() -> dict:
        return to_dict(EnvConfig())

    def _check_localizer_config(self, have_instance: bool) -> None:
        self.config = check_localizer_config(self.config, have_instance, allow_auto=True)

    def _check_localizer_camera(self) -> None:
        """Refuse a built-in localizer built for another camera: other image size, intrinsics, baseline, mounting
        (a localizer of one's own checks what it needs in reset(context))."""
        engine = getattr(self.localizer, "engine", None)
        if engine is not None:
            check_localizer_camera(engine, self.camera, f"the environment (resolution {self.config.resolution!r})",
                                   self._loc_identity["source"])

    def _check_localizer_map(self, scene: Scene) -> None:
        """A build directory or instance is tied to one satellite map: refuse a scene with another one (size,
        resolution, origin; content where the localizer's features hold the map's colours, else the scene and
        aliasing its build directory records)."""
        spec = getattr(scene, "spec", None)
        aliasing = getattr(getattr(spec, "knobs", None), "aliasing", None)
        what = f"scene {scene.name!r}" + (f" (aliasing {aliasing:g})" if aliasing is not None else "")
        ident = self._loc_identity
        gap = getattr(getattr(spec, "knobs", None), "satellite_gap", None)
        built = ident.get("satellite_gap")
        if (isinstance(gap, (int, float)) and isinstance(built, (int, float)) and ident.get("scene") == scene.name
                and not math.isclose(gap, built, abs_tol=1e-9)):
            raise ConfigError(f"localizer: {ident['source']} was built on scene {scene.name!r}'s satellite map "
                              f"captured at satellite_gap {built:g}, not on the map at {gap:g}; a localizer localizes "
                              "only on the map it was built on")
        engine = getattr(self.localizer, "engine", None)
        if engine is None:   # a localizer of one's own: it is given the scene's map in reset(context)
            return
        compared = check_localizer_map(engine, scene.satmap, what, ident["source"]) is not None
        if not compared and isinstance(ident.get("scene"), str):
            other = (ident["scene"] != scene.name
                     or (aliasing is not None and isinstance(ident.get("aliasing"), (int, float))
                         and not math.isclose(ident["aliasing"], aliasing, abs_tol=1e-9)))
            if other:
                raise ConfigError(f"localizer: {ident['source']} is not a build of {what}; a localizer localizes only "
                                  "on the map it was built on")

    @property
    def scene(self) -> Scene:
        if self._scene is None:
            raise RuntimeError("call reset() first")
        return self._scene

    def _ensure_scene(self, cfg: EnvConfig) -> None:
        key = (cfg.scene, cfg.aliasing, cfg.satellite_gap)
        if key == self._scene_key:
            return
        if self._preloaded is not None and self._preloaded[0] == key:
            scene = self._preloaded[1]       # loaded and checked by __init__
        else:
            scene = load_scene(*key)
        self._preloaded = None
        if self.config.localizer == "auto":
            from .auto_localizer import auto_localizer

            self.localizer = auto_localizer(cfg.scene, cfg.aliasing, cfg.resolution, cfg.localizer_mode,
                                            refine=cfg.localizer_refine, satellite_gap=cfg.satellite_gap
                                            ).as_localizer(self.config.localizer_track)
            self._loc_identity = {"source": f"the auto localizer of scene {scene.name!r}"}
            self._check_localizer_camera()
        elif self.config.localizer == "cross":
            from .cross_localizer import cross_localizer

            self.localizer = cross_localizer(scene.satmap, self.camera, key).as_localizer(self.config.localizer_track)
            self._loc_identity = {"source": f"the cross-view localizer of scene {scene.name!r}"}
        elif self.localizer is not None:
            self._check_localizer_map(scene)
        self._scene, self._scene_key = scene, key
        self._use_world(scene.world)

    def _use_world(self, world) -> None:
        """Render ``world`` (the scene's, or a revisit's :func:`satloc_env.world.revisit.changed_world`) from now on."""
        from satloc_env.render.stereo import StereoRenderer

        if self._renderer is not None and self._renderer.world is world:
            return
        if self._renderer is not None:
            self._renderer.close()
        if self._batch is not None:          # a sub-environment of satloc_env.envs.vector.SatLocVectorEnv
            self._renderer = self._batch.slot(world)
        else:
            self._renderer = StereoRenderer(world, self.camera, anisotropy=self.config.anisotropy,
                                            zfar=self.config.zfar_m, detail_m=self.config.detail_m)

    # --- gym API ----------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._ready = False                    # until this reset succeeds, step() refuses
        options = check_reset_options(options, EPISODE_KEYS, EnvConfig)
        cfg = override(self.config, options, "reset options")
        self._ensure_scene(cfg)
        scene = self.scene
        route_name = cfg.route or scene.spec.database_route
        self._check_route(scene, cfg)   # reset options may change the route, its lane or the speed
        route = scene.routes[route_name]
        if not cfg.random_start and cfg.start_s_m > route.length:
            raise ConfigError(f"start_s_m: expected a position along route {route_name!r} of scene {scene.name!r}, in "
                              f"[0, {route.length:.1f}] m, got {cfg.start_s_m:g}")
        knobs = scene.spec.knobs
        occ = knobs.occlusion if cfg.occlusion is None else cfg.occlusion
        app = knobs.appearance if cfg.appearance is None else cfg.appearance
        change = knobs.change if cfg.change is None else cfg.change
        for k, val in (("occlusion", occ), ("appearance", app), ("change", change)):
            if not 0.0 <= val <= 1.0:
                raise ConfigError(f"{k}: expected a value in [0, 1], got {val}")
        self.change_seed, world = None, scene.world
        if change > 0:   # seeded by a child of the episode's seed sequence: the episode's own draws stay as they are
            from satloc_env.world.revisit import changed_world

            self.change_seed = int(self.np_random.spawn(1)[0].integers(2**31 - 1))
            world = changed_world(scene, change, self.change_seed, cfg.change_parts)
        self._use_world(world)
        self._episode, self.route = cfg, route
        rng = self.np_random
        s0 = float(rng.uniform(0, self.route.length * 0.9)) if cfg.random_start else cfg.start_s_m
        wander, self.wander_seed = Wander(cfg.wander_m, cfg.speed_wander), None
        profile = None
        if wander.active:
            self.wander_seed = (cfg.wander_seed if cfg.wander_seed is not None   # none of the episode's draws
                                else default_wander_seed(self.np_random.bit_generator.seed_seq))
            profile = wander_profile(self.route.length, wander, self.wander_seed)
        self.pose = self.route.pose_at(s0, cfg.lane_offset_m + drift_at(self.route, cfg.lane_offset_m, profile, s0))
        self.pilot = Autopilot(self.route, cfg.lane_offset_m, cfg.speed_mps, s0=s0, wander=profile)
        self._renderer.set_occluders(*sample_occluders(self.route, scene.ground_label, occ, cfg.lane_offset_m, rng))
        self.appearance = Appearance(app, rng)
        self.steps = 0
        # the GPS-like priors and the localizer's seed, from children of the episode's seed sequence with spawn
        # keys of their own and the episode's number since the last seeded reset (spawning would move the other
        # children's counter): none of the episode's other draws change
        self._episodes_since_seed = 0 if seed is not None else getattr(self, "_episodes_since_seed", -1) + 1
        cam = self.camera
        self.sensor = Sensor(cfg.sensor, cam.width, cam.height, cam.fx, cam.cx, cam.cy,
                             np.random.default_rng(self._child_seed(SENSOR_SPAWN_KEY)))
        self.attitude = Attitude(cfg.attitude, cfg.dt, np.random.default_rng(self._child_seed(ATTITUDE_SPAWN_KEY)))
        self._motion = (0.0, 0.0)
        self._prior_rng = None
        if self.localizer is not None:
            self._prior_rng = np.random.default_rng(self._child_seed(PRIOR_SPAWN_KEY))
            self._gnss = GnssReceiver(cfg.gnss, cfg.prior_radius_m, cfg.prior_yaw_deg, self._prior_rng)
            # a new episode: the localizer's reset(context) (tracking: a new belief)
            self._loc.begin(self._context(scene, int(self._child_seed(LOCALIZER_SPAWN_KEY).generate_state(1)[0])))
        obs = self._observe(np.zeros(3, np.float32))
        self._vo = None
        if cfg.odometry == "visual":           # its first pair: the reference of the first step's motion
            from satloc.tracking.vo import StereoVO

            self._vo = StereoVO(self.camera)
            self._vo.step(obs["left"], obs["right"])
        self._localize()
        self._ready = True
        return obs, self._info(np.zeros(3), off_road=False)

    def step(self, action):
        odometry, true_odo = self._advance(action)
        return self._complete_step(self._renderer.render(self.pose, *self._render_args(), tilt=self.attitude.tilt),
                                   odometry, true_odo)

    def _advance(self, action) -> tuple[np.ndarray, np.ndarray]:
        """The first part of :meth:`step`, up to the rendering: move the car by ``action``; returns the odometry
        observation (noisy) and the true motion. (:class:`satloc_env.envs.vector.SatLocVectorEnv` renders all its
        environments' cars between the two parts.)"""
        if not self._ready:
            raise RuntimeError("call reset() first" + (" (the last reset raised an error)" if self._scene else ""))
        a = self._check_action(action)
        cfg = self._episode
        prev = self.pose
        self.pose, v, w = step_bicycle(prev, a[0], a[1], cfg.dt, self.vehicle)
        self.attitude.step(v, w)
        self._motion = (v, w)
        self.steps += 1
        self.pilot.follow(self.pose)
        true_odo = prev.between(self.pose).as_array()
        dist = math.hypot(true_odo[0], true_odo[1])
        noise = self.np_random.normal(0.0, 1.0, 3) * np.array(
            [cfg.odometry_noise[0] * dist, cfg.odometry_noise[0] * dist, cfg.odometry_noise[1]])
        return (true_odo + noise).astype(np.float32), true_odo

    def _complete_step(self, rendered: dict, odometry: np.ndarray, true_odo: np.ndarray):
        """The rest of :meth:`step` once the car's views are ``rendered`` (:meth:`_render_args`)."""
        return self._finish_step(self._observe_step(rendered, odometry), true_odo)

    def _observe_step(self, rendered: dict, odometry: np.ndarray) -> dict:
        """The step's observation from the rendered views (appearance, visual odometry)."""
        obs = self._observe_rendered(rendered, odometry)
        if self._vo is not None:               # the motion as the stereo pair shows it (noise drawn all the same)
            obs["odometry"] = np.asarray(self._vo.step(obs["left"], obs["right"]), np.float32)
        self._loc.add_odometry(obs["odometry"])
        return obs

    def _localizes_now(self) -> bool:
        """Whether this step localizes the observed pair (a localizer is on and the step is due)."""
        return self.localizer is not None and self.steps % self.config.localize_every == 0

    def _finish_step(self, obs: dict, true_odo: np.ndarray):
        """Localize (when due), then the step's reward, flags and info."""
        cfg = self._episode
        if self.steps % self.config.localize_every == 0:
            self._localize()
        off_road = not self.scene.is_drivable(self.pose.x, self.pose.y)
        info = self._info(true_odo, off_road)
        terminated = bool(off_road or info["route_complete"])
        truncated = self.steps >= cfg.max_steps
        reward = 0.0
        if self.config.reward == "neg_error" and np.isfinite(info["error_m"]):
            reward = -float(info["error_m"])
        return obs, reward, terminated, truncated, info

    def _check_action(self, action) -> np.ndarray:
        """The action as 2 float64 values clipped to the action space; :class:`ActionError` for an action of
        another shape or type or with NaN/inf."""
        box = self.action_space
        what = (f"an action of shape (2,): [speed m/s in [{box.low[0]:g}, {box.high[0]:g}], yaw rate rad/s in "
                f"[{box.low[1]:g}, {box.high[1]:g}]], finite numbers (out-of-range values are clipped to that range)")
        try:
            a = np.asarray(action)
        except (ValueError, TypeError) as e:   # ragged nested lists
            raise ActionError(f"action: expected {what}; got {action!r} ({e})") from None
        if a.dtype.kind not in "iuf":
            raise ActionError(f"action: expected {what}; got {action!r} of dtype {a.dtype}")
        if a.shape != (2,):
            raise ActionError(f"action: expected {what}; got shape {a.shape}: {action!r}")
        a = a.astype(np.float64)
        if not np.all(np.isfinite(a)):
            raise ActionError(f"action: expected {what}; got non-finite values {a.tolist()}")
        return np.clip(a, box.low.astype(np.float64), box.high.astype(np.float64))

    def autopilot_action(self) -> np.ndarray:
        """The route follower's action for the current pose (a scripted driver)."""
        return self.pilot.act(self.pose)

    def _frame_depth_needed(self) -> bool:
        """A localizer configured with ``depth_source="frame"`` reads the (true) depth from the frame."""
        return self._loc.needs_frame_depth

    def _render_args(self) -> tuple:
        """``depth`` and ``labels`` of the renderer's ``render`` for this environment's observations."""
        want_depth = self.config.depth or self._frame_depth_needed()
        return ("left" if want_depth else False), self.config.labels

    def _observe(self, odometry: np.ndarray) -> dict:
        return self._observe_rendered(self._renderer.render(self.pose, *self._render_args(), tilt=self.attitude.tilt),
                                      odometry)

    def _observe_rendered(self, out: dict, odometry: np.ndarray) -> dict:
        cfg = self.config
        want_depth = cfg.depth or self._frame_depth_needed()
        v, w = self._motion
        obs = {"left": self.sensor(self.appearance(out["left"]), v, w),
               "right": self.sensor(self.appearance(out["right"]), v, w), "odometry": odometry}
        if cfg.depth:
            obs["depth"] = out["depth_left"]
        if cfg.labels:
            obs["labels"] = out["labels_left"]
        self._last_obs = obs
        self._last_depth = out.get("depth_left") if want_depth else None
        return obs

    def _child_seed(self, key: int) -> np.random.SeedSequence:
        """A child of the episode's seed sequence with its own spawn ``key`` (see :meth:`reset`)."""
        ss = self.np_random.bit_generator.seed_seq
        return np.random.SeedSequence(ss.entropy, spawn_key=tuple(ss.spawn_key) + (key, self._episodes_since_seed))

    def _context(self, scene: Scene, seed: int):
        """What the localizer is told at the start of an episode (:class:`satloc.localizers.interface.Context`):
        the camera, the scene's satellite map (the capture, with its road labels) and the episode's seed."""
        from satloc.localizers.interface import Context

        return Context(self.camera, scene.satmap, seed=seed, database=None, place=scene.name)

    def _localize(self) -> None:
        """Localize the last observed stereo pair from a GPS-like prior drawn around the true pose (uniform within
        ``prior_radius_m``, heading within ``prior_yaw_deg``); keeps the result for ``info`` and ``render``."""
        if self.localizer is None:
            return
        cfg = self._episode
        prior = self.last_prior = self._gnss.fix(self.pose, self.steps * cfg.dt)
        self._loc.localize(self._frame(), self.steps, prior)

    def _frame(self) -> Frame:
        """The last observed stereo pair as the localizer's query frame."""
        return Frame(self._last_obs["left"], self._last_obs["right"], None, self.steps * self._episode.dt,
                     self._last_depth if self._frame_depth_needed() else None)

    def _info(self, true_odo: np.ndarray, off_road: bool) -> dict:
        info = {
            "pose": self.pose.as_array(),
            "odometry_true": np.asarray(true_odo, np.float64),
            "route_s": np.float64(self.pilot.s),
            "off_road": np.bool_(off_road),
            "route_complete": np.bool_(self.pilot.done),
            "step": np.int64(self.steps),
        }
        info.update(self._loc.info(self.pose.as_array()))
        return info

    # --- rendering --------------------------------------------------------------------------------
    def render(self):
        if self.render_mode != "rgb_array" or self._last_obs is None:
            return None
        return compose_view(self._last_obs["left"], self.scene.satmap, self.pose, self.route.points,
                            self._loc.view, localized=self._loc.localized)

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        self._scene = self._scene_key = None
        close_localizer(self._loc.localizer)


PANEL_PX = 360
PANEL_M = 80.0
HEAT_SIGMA_M = 1.5          # the posterior is drawn as a sum of Gaussians of this std over the candidates
TRUTH_RGB = (255, 40, 40)
ESTIMATE_RGB = (60, 255, 60)


@dataclass
class PosteriorView:
    """What the bird's-eye panels draw of a localization: the posterior over all candidates and the estimate."""

    candidates: np.ndarray          # (C, 3)
    posterior: np.ndarray           # (C,)
    estimate: np.ndarray            # (3,)
    inlier: bool = True
    _peaks: dict = field(default_factory=dict, repr=False)

    def peak_density(self, sigma_m: float) -> float:
        """Largest value (per m^2) of the Gaussian-smoothed posterior, at the most probable candidates."""
        if sigma_m not in self._peaks:
            xy, p = self.candidates[:, :2], self.posterior
            q = xy[np.argsort(-p)[:64]]
            acc = np.zeros(len(q))
            for b in range(0, len(xy), 8192):
                d2 = ((xy[b:b + 8192, None, :] - q[None]) ** 2).sum(-1)
                acc += p[b:b + 8192] @ np.exp(-d2 / (2 * sigma_m ** 2))
            self._peaks[sigma_m] = float(acc.max()) / (2 * math.pi * sigma_m ** 2) if len(q) else 0.0
        return self._peaks[sigma_m]


def _draw_heat(img: np.ndarray, view: PosteriorView, to_px, px_per_m: float) -> None:
    """Alpha-blend the posterior heatmap onto ``img`` (in place). Normalised by the posterior's global peak,
    so a crop away from the peak shows how little mass lies there."""
    h, w = img.shape[:2]
    sigma_m = max(HEAT_SIGMA_M, 1.0 / px_per_m)  # at least a pixel wide on coarse panels
    peak = view.peak_density(sigma_m)
    if peak <= 0:
        return
    sig_px = sigma_m * px_per_m
    pad = int(math.ceil(3 * sig_px)) + 1
    uv = np.round(to_px(view.candidates[:, :2])).astype(np.int64) + pad
    ok = ((uv[:, 0] >= 0) & (uv[:, 0] < w + 2 * pad) & (uv[:, 1] >= 0) & (uv[:, 1] < h + 2 * pad)
          & (view.posterior > 0))
    if not ok.any():
        return
    canvas = np.zeros((h + 2 * pad, w + 2 * pad), np.float32)
    np.add.at(canvas, (uv[ok, 1], uv[ok, 0]), view.posterior[ok].astype(np.float32))
    dens = cv2.GaussianBlur(canvas, (0, 0), sig_px)[pad:pad + h, pad:pad + w] * px_per_m ** 2
    heat = np.sqrt(np.clip(dens / peak, 0.0, 1.0))
    alpha = np.where(heat > 0.05, 0.75 * heat, 0.0)[..., None]
    colour = cv2.applyColorMap(np.round(heat * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)[..., ::-1]
    img[:] = np.round(img * (1 - alpha) + colour * alpha).astype(np.uint8)


def _draw_estimate(img: np.ndarray, est: np.ndarray, to_px, radius: int = 6) -> None:
    """A green ring with a heading tick; if outside the panel, an arrow at the border pointing to it."""
    h, w = img.shape[:2]
    c = to_px(est[:2])
    if 0 <= c[0] < w and 0 <= c[1] < h:
        tip = to_px(est[:2] + (2.0 * radius / max(1e-9, np.linalg.norm(to_px(est[:2] + (1.0, 0.0)) - c)))
                    * np.array([math.cos(est[2]), math.sin(est[2])]))
        p, t = tuple(int(v) for v in np.round(c)), tuple(int(v) for v in np.round(tip))
        cv2.line(img, p, t, (0, 0, 0), 4, cv2.LINE_AA)
        cv2.line(img, p, t, ESTIMATE_RGB, 2, cv2.LINE_AA)
        cv2.circle(img, p, radius, (0, 0, 0), 4, cv2.LINE_AA)
        cv2.circle(img, p, radius, ESTIMATE_RGB, 2, cv2.LINE_AA)
        return
    centre = np.array([w / 2, h / 2])
    d = c - centre
    f = min((w / 2 - 10) / max(abs(d[0]), 1e-9), (h / 2 - 10) / max(abs(d[1]), 1e-9))
    tip = centre + d * f
    tail = tip - d / np.linalg.norm(d) * 24
    a, b = tuple(int(v) for v in np.round(tail)), tuple(int(v) for v in np.round(tip))
    cv2.arrowedLine(img, a, b, (0, 0, 0), 5, cv2.LINE_AA, tipLength=0.45)
    cv2.arrowedLine(img, a, b, ESTIMATE_RGB, 2, cv2.LINE_AA, tipLength=0.45)


def _text(img: np.ndarray, text: str, org: tuple[int, int]) -> None:
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)


def _route_lines(route) -> list[np.ndarray]:
    """The polylines (each (n, 2) map metres) of ``route``: a :class:`satloc_env.world.route.Route`, an (N, 2+) array of
    path points (rows with NaN split it: frames without a pose), or None."""
    if route is None:
        return []
    pts = np.asarray(getattr(route, "points", route), np.float64)
    if pts.ndim != 2 or pts.shape[1] < 2:
        raise ValueError(f"route: expected a Route or an (N, 2) array of points, got shape {pts.shape}")
    pts = pts[:, :2]
    ok = np.all(np.isfinite(pts), axis=1)
    if ok.all():
        return [pts] if len(pts) > 1 else []
    breaks = np.flatnonzero(np.diff(ok.astype(np.int8)) != 0) + 1
    return [seg for seg, good in zip(np.split(pts, breaks), np.split(ok, breaks)) if good[0] and len(seg) > 1]


def _draw_heat_and_route(img, posterior, route, to_px, px_per_m: float) -> None:
    """The posterior heatmap (if any), then the route on top, in a panel mapped by ``to_px``."""
    if posterior is not None:
        _draw_heat(img, posterior, to_px, px_per_m)
    lines = [np.round(to_px(pts) * 16).astype(np.int32).reshape(-1, 1, 2) for pts in _route_lines(route)]
    if lines:
        cv2.polylines(img, lines, False, (80, 200, 255), 1, cv2.LINE_AA, shift=4)


def _satmap(where) -> SatelliteMap:
    """The satellite map of a panel: a :class:`SatelliteMap`, or a scene's (anything with ``.satmap``)."""
    sm = getattr(where, "satmap", where)
    if not isinstance(sm, SatelliteMap):
        raise TypeError(f"expected a SatelliteMap or a Scene, got {type(where).__name__}")
    return sm


def _known(pose: Pose2 | None) -> bool:
    return pose is not None and math.isfinite(pose.x) and math.isfinite(pose.y)


def _panel_centre(sm: SatelliteMap, pose: Pose2 | None, posterior: PosteriorView | None) -> np.ndarray:
    """Where the bird's-eye panel looks: the true pose, else the estimate, else the map's centre."""
    if _known(pose):
        return np.array([pose.x, pose.y])
    if posterior is not None and np.all(np.isfinite(posterior.estimate[:2])):
        return np.asarray(posterior.estimate[:2], np.float64)
    x0, x1, y0, y1 = sm.extent
    return np.array([(x0 + x1) / 2, (y0 + y1) / 2])


def birdseye(satmap: SatelliteMap | Scene, pose: Pose2 | None, route=None, size_px: int = PANEL_PX,
             size_m: float = PANEL_M, posterior: PosteriorView | None = None, localized: bool = False) -> np.ndarray:
    """North-up crop of the satellite map (a :class:`SatelliteMap` or a scene's) around ``pose`` with the route
    (a Route or an (N, 2) polyline) and the vehicle (red) drawn on it; with ``posterior``, also the posterior
    heatmap and the estimate (green). ``localized`` without a ``posterior`` marks a frame that could not be
    localized. ``pose`` None (or NaN: a frame without a pose) draws no vehicle and centres the crop on the
    estimate (else the map's centre)."""
    sm = _satmap(satmap)
    centre = _panel_centre(sm, pose, posterior)
    img = sm.crop(centre, size_m, out_px=size_px).copy()
    scale = size_px / size_m

    def to_px(xy):
        d = np.asarray(xy, np.float64) - centre
        return np.stack([size_px / 2 + d[..., 0] * scale, size_px / 2 - d[..., 1] * scale], -1)

    _draw_heat_and_route(img, posterior, route, to_px, scale)
    if posterior is not None and np.all(np.isfinite(posterior.estimate[:2])):
        _draw_estimate(img, posterior.estimate, to_px)
    if _known(pose):
        tri = pose.transform(np.array([[2.6, 0.0], [-1.6, 1.3], [-1.6, -1.3]]))
        cv2.fillPoly(img, [np.round(to_px(tri) * 16).astype(np.int32).reshape(-1, 1, 2)], TRUTH_RGB, cv2.LINE_AA,
                     shift=4)
    if posterior is not None:
        tag = "" if posterior.inlier else "  (outlier)"
        if _known(pose):
            err = math.hypot(posterior.estimate[0] - pose.x, posterior.estimate[1] - pose.y)
            _text(img, f"error {err:.1f} m" + tag, (6, 18))
        else:
            _text(img, "no true pose" + tag, (6, 18))
    elif localized:
        _text(img, "no estimate (no valid depth)", (6, 18))
    return img


_OVERVIEW_BASE: dict[int, tuple] = {}   # id(map) -> (weakref to the map, size_px, panel, scales, offset)


def _overview_base(sm: SatelliteMap, size_px: int) -> tuple:
    """The whole map scaled into a ``size_px`` square (letterboxed), cached per map object."""
    cached = _OVERVIEW_BASE.get(id(sm))
    if cached is not None and cached[0]() is sm and cached[1] == size_px:
        return cached[2:]
    H, W = sm.image.shape[:2]
    s = size_px / max(H, W)
    bw, bh = max(1, int(round(W * s))), max(1, int(round(H * s)))
    panel = np.full((size_px, size_px, 3), 24, np.uint8)
    ox, oy = (size_px - bw) // 2, (size_px - bh) // 2
    panel[oy:oy + bh, ox:ox + bw] = cv2.resize(sm.image, (bw, bh), interpolation=cv2.INTER_AREA)
    for key in [k for k, v in _OVERVIEW_BASE.items() if v[0]() is None]:  # maps gone
        del _OVERVIEW_BASE[key]
    _OVERVIEW_BASE[id(sm)] = (weakref.ref(sm), size_px, panel, (bw / W, bh / H), (ox, oy))
    return _OVERVIEW_BASE[id(sm)][2:]


def overview(satmap: SatelliteMap | Scene, pose: Pose2 | None, route=None, size_px: int = PANEL_PX,
             window_m: float = PANEL_M, posterior: PosteriorView | None = None) -> np.ndarray:
    """The whole satellite map (a :class:`SatelliteMap` or a scene's) scaled into a ``size_px`` square
    (letterboxed), with the route, the bird's-eye window (white), the posterior heatmap, the truth (red) and
    the estimate (green). ``pose`` None or NaN: no truth (the window is where :func:`birdseye` looks)."""
    sm = _satmap(satmap)
    base, (sx, sy), (ox, oy) = _overview_base(sm, size_px)
    img = base.copy()

    def to_px(xy):
        uv = sm.world_to_pixel(np.asarray(xy, np.float64))
        return np.stack([(uv[..., 0] + 0.5) * sx - 0.5 + ox, (uv[..., 1] + 0.5) * sy - 0.5 + oy], -1)

    px_per_m = sx / sm.meters_per_pixel
    _draw_heat_and_route(img, posterior, route, to_px, px_per_m)
    c = to_px(_panel_centre(sm, pose, posterior))
    half = window_m / 2 * px_per_m
    cv2.rectangle(img, tuple(int(v) for v in np.round(c - half)), tuple(int(v) for v in np.round(c + half)),
                  (255, 255, 255), 1, cv2.LINE_AA)
    has_est = posterior is not None and np.all(np.isfinite(posterior.estimate[:2]))
    if has_est:
        e = to_px(posterior.estimate[:2])
        if _known(pose):
            cv2.line(img, tuple(int(v) for v in np.round(c)), tuple(int(v) for v in np.round(e)), (255, 255, 255),
                     1, cv2.LINE_AA)
        _draw_estimate(img, posterior.estimate, to_px, radius=4)
    if _known(pose):
        cv2.circle(img, tuple(int(v) for v in np.round(c)), 4, (0, 0, 0), -1, cv2.LINE_AA)
        cv2.circle(img, tuple(int(v) for v in np.round(c)), 3, TRUTH_RGB, -1, cv2.LINE_AA)
    return img


def compose_view(camera_img: np.ndarray, satmap: SatelliteMap | Scene, pose: Pose2 | None, route=None,
                 posterior: PosteriorView | None = None, localized: bool = False) -> np.ndarray:
    """Camera view (scaled to the panel height), the bird's-eye panel and the whole-map overview, over
    ``satmap`` (a :class:`SatelliteMap` or a scene's) with ``route`` (a Route or an (N, 2) polyline of the
    path; NaN rows split it). The shape depends only on the camera's image size."""
    h, w = camera_img.shape[:2]
    cam = cv2.resize(camera_img, (int(round(w * PANEL_PX / h)), PANEL_PX), interpolation=cv2.INTER_LINEAR)
    return np.ascontiguousarray(np.hstack([
        cam, birdseye(satmap, pose, route, posterior=posterior, localized=localized),
        overview(satmap, pose, route, posterior=posterior)]))
