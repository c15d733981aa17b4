"""The Gymnasium environment ``satloc/SatLocReplay-v0``: replay a recorded stereo sequence over its satellite map.

Where ``satloc/SatLoc-v0`` (:mod:`satloc_env.envs.drive`) renders what a car sees as it drives, this environment steps
through a recorded :class:`satloc.sequence.Sequence`: a directory written by ``satloc record`` or
``Sequence.save``, or a ``Sequence`` object (e.g. a dataset reader's lazy sequence, :meth:`Sequence.lazy`). The
observation and ``info`` follow SatLoc-v0's contract, so an agent or a script written for one runs on the
other, and with a localizer each step reports the same localization keys::

    import gymnasium as gym, satloc_env
    env = gym.make("satloc/SatLocReplay-v0", sequence="rec/query", map="rec/map", localizer="rec/build")
    obs, info = env.reset(seed=0)
    while True:
        obs, reward, terminated, truncated, info = env.step(1)   # advance one stride
        print(info["frame_index"], info["error_m"])
        if truncated:
            break

Configuration is :class:`ReplayConfig`; any field can be given to ``gymnasium.make``, and the per-episode ones
(:data:`EPISODE_KEYS`) again in ``reset(options=...)``. Unknown keys raise :class:`satloc.ConfigError`.
"""
from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from satloc.config import from_dict, override, to_dict
from satloc.errors import ConfigError
from satloc.geometry import Pose2
from satloc.localizers.gnss import GnssConfig, GnssReceiver
from satloc.persist import read_json
from satloc.satmap import SatelliteMap
from satloc.sequence import Sequence
from satloc.tracking.track import compose_motion

from .drive import (
    LOCALIZER_INSTANCE,
    LOCALIZER_SPAWN_KEY,
    PANEL_M,
    PRIOR_SPAWN_KEY,
    ActionError,
    LocalizationState,
    SharedSpecMixin,
    _check_noise,
    _split_localizer,
    build_identity,
    check_localizer_camera,
    check_localizer_config,
    check_reset_options,
    close_localizer,
    compose_view,
    is_localizer_spec,
    make_localizer,
    unshare,
)

#: the value of ``ReplayConfig.sequence`` / ``.map`` when an object (a Sequence, a SatelliteMap) was passed.
INSTANCE = "<instance>"
#: georeferenced imagery given as ``map`` is read at its own resolution, or coarser to stay within this many
#: pixels a side (it is only drawn)
MAX_MAP_PX = 8192


@dataclass
class ReplayConfig:
    sequence: str | None = None             # sequence directory; a Sequence object given as the keyword is
                                            # stored here as "<instance>" (required: one or the other)
    map: str | None = None                  # satellite map directory (SatelliteMap.load), a GeoTIFF, an image with
                                            # a world file or an XYZ tile folder (satloc.geodata.georef), or "<instance>" for a
                                            # SatelliteMap object; None: see SatLocReplayEnv (render only)
    start_frame: int = 0                    # first frame of an episode
    end_frame: int | None = None            # frames from this index on are not replayed (None: to the end)
    random_start: bool = False              # start at a random frame in [start_frame, last - stride] (episode seed)
    stride: int = 1                         # frames advanced by an action of 1
    max_skip: int = 1                       # actions are 1..max_skip: advance action * stride frames
    depth: bool = False                     # add a left-camera depth observation (the frame's own, else stereo)
    odometry: Literal["noisy_truth", "visual", "oxts"] = "noisy_truth"   # the odometry observation: the poses'
                                            # motion plus noise, the stereo visual odometry of the frames
                                            # (satloc.tracking.vo), or a KITTI drive's OXTS speed and yaw rate, integrated
    odometry_noise: tuple[float, float] = (0.02, 0.003)  # std: fraction of the distance, radians per step
    localizer: str | None = None            # None/"none": off; "cross": no database, the map alone; a build
                                            # directory; "module:Name" (a localizer of one's own); a localizer
                                            # object (or a class that makes one) given as the keyword is stored
                                            # here as "<instance>"
    localizer_mode: Literal["full", "np", "go"] = "full"   # for a build directory
    localizer_refine: bool = False          # for a build directory: bird's-eye alignment (satloc.tracking.align)
    localizer_track: bool = False           # fuse each localization into a belief moved by the odometry
                                            # observations (satloc.tracking.track); a new episode starts a new belief
    localize_every: int = 1                 # localize at reset and at the steps that are multiples of this
    prior_radius_m: float = 20.0            # each localization's prior, drawn around the frame's GPS / OXTS pose
    prior_yaw_deg: float = 10.0             # as a fix gives it: within this radius and heading range
    gnss: GnssConfig = field(default_factory=GnssConfig)   # how the prior's centre strays from that pose
                                            # (satloc.localizers.gnss): "uniform" within the radius, frame by frame;
                                            # "receiver", a receiver's correlated error, multipath and outages over
                                            # the sequence's timestamps
    reward: Literal["none", "neg_error"] = "none"  # neg_error: minus the localization error (metres)

    def __post_init__(self):
        # types are checked by satloc.config.from_dict; here the values that do not depend on the data (the
        # frame indices are checked against the sequence by SatLocReplayEnv)
        from satloc.localizers.interface import Prior

        Prior(0.0, 0.0, 0.0, self.prior_radius_m, self.prior_yaw_deg)   # a prior's checks, naming the field
        for k in ("stride", "max_skip", "localize_every"):
            if getattr(self, k) < 1:
                raise ConfigError(f"{k}: expected an integer >= 1, got {getattr(self, k)}")
        if self.start_frame < 0:
            raise ConfigError(f"start_frame: expected an index >= 0, got {self.start_frame}")
        if self.end_frame is not None and self.end_frame < 1:
            raise ConfigError(f"end_frame: expected an index >= 1 or None, got {self.end_frame}")
        _check_noise(self.odometry_noise)


#: keys that ``reset(options=...)`` may change; the others fix the spaces, the data or the localizer.
EPISODE_KEYS = frozenset({"start_frame", "end_frame", "random_start", "stride", "odometry", "odometry_noise"})


class SatLocReplayEnv(SharedSpecMixin, gym.Env):
    """Step through a recorded stereo sequence; localize its frames against a satellite map.

    **Data.** ``sequence``: a sequence directory (``satloc record``, ``Sequence.save``) or a
    :class:`satloc.sequence.Sequence` object given as the keyword (shared, not copied, by ``env.spec``; a
    lazy dataset sequence reads its frames as they are replayed). ``map``: a map directory
    (:meth:`SatelliteMap.load`), georeferenced imagery that :func:`satloc.geodata.georef.load_map` reads (a GeoTIFF,
    an image with a world file, an XYZ tile folder: read into the sequence's ``meta["geo_frame"]`` around its
    path, at the image's resolution or coarser within :data:`MAX_MAP_PX` pixels a side) or a
    :class:`SatelliteMap` object. It is used for rendering only (the
    localizer carries its own satellite features); without one, the map is the one the localizer's build
    directory was built from (``build.json``), else ``<sequence dir>/../map`` (the layout of
    ``satloc record``), else a plain grey canvas around the sequence's path. A map and a sequence that both
    name their geographic frame (``SatelliteMap.frame``, ``meta["geo_frame"]``) must name the same one.

    **Episode.** It starts at ``start_frame`` (or a random frame with ``random_start``) and each step advances
    ``action * stride`` frames. ``truncated`` is True at the step after which one more stride would run past
    the last frame (``end_frame - 1`` or the end of the data); stepping again raises ``RuntimeError``
    (call ``reset``). ``terminated`` is always False: a replay cannot leave the road.

    **Action.** ``Discrete(max_skip, start=1)``: a skip count, the number of strides to advance. With the
    default ``max_skip=1`` the only action is 1 (one stride per step). A skip that would run past the last frame
    stops at the last frame reachable in whole strides. An action must be an integer (a Python or numpy integer,
    or an integer array of one element) in [1, ``max_skip``]: anything else (0 or above ``max_skip``, a float
    such as 1.0 or NaN, inf, a bool, a string, an array of another size) raises
    :class:`satloc_env.envs.drive.ActionError` (a ValueError) naming the range, and the step is not taken. Unlike
    SatLoc-v0's Box, a Discrete action out of range is not clipped.

    **Configuration errors** (:class:`satloc.ConfigError`, naming the field): unknown keys, wrong types,
    ``stride``, ``max_skip`` and ``localize_every`` below 1, frame indices outside the sequence,
    ``odometry_noise`` not two finite non-negative numbers. ``reset(options=...)`` must be a dict of keys in
    :data:`EPISODE_KEYS`; an unknown key, or one fixed when the env is made, is named in the error.

    **Observation** (Dict), as SatLoc-v0's: ``left``, ``right`` uint8 RGB images of the frame; ``odometry``
    float32 (dx, dy, dyaw), the motion from the previous step's frame to this one in the previous frame's
    vehicle frame (from the two frames' poses in the data), plus Gaussian noise of std ``odometry_noise[0]``
    times the distance (x and y) and ``odometry_noise[1]`` radians (heading) per step, drawn from the
    episode's RNG: SatLoc-v0's model. Zero at reset. Where either frame has no pose the motion is unknown:
    the observation is zero, ``info["odometry_valid"]`` False and ``odometry_true`` NaN (with tracking, the
    next localization starts a new belief). ``odometry="visual"`` observes the stereo visual odometry of the
    frames instead (:class:`satloc.tracking.vo.StereoVO`, from the previous step's pair to this one), ``odometry="oxts"``
    a KITTI drive's forward speed and yaw rate integrated over the frames stepped
    (:func:`satloc.datasets.kitti.oxts_odometry`); where they fail the observation is zero and
    ``odometry_valid`` False. With ``depth=True``: ``depth`` float32 metres, 0 = invalid: the
    frame's stored depth channel when it has one (the simulator's true depth in a recorded pass), otherwise
    stereo depth from the pair (:class:`satloc.stereo.StereoDepth`); ``info["depth_from_stereo"]`` says which.

    **info** (fixed-shape numpy values): ``pose`` (x, y, yaw) of the frame in the data (NaN for a frame without
    a pose), ``odometry_true`` (the noise-free motion of the step), ``odometry_valid``, ``step``,
    ``frame_index`` (into the sequence), ``timestamp`` (the frame's, seconds). With a localizer, as SatLoc-v0
    (see :class:`satloc_env.envs.drive.SatLocEnv`): ``estimate``, ``error_m`` (to the current frame's pose: NaN for a
    frame without a pose), ``posterior_poses`` (K, 3), ``posterior_probs`` (K,), ``inlier``, ``inlier_score``
    and ``localized_step``, computed at reset and at every ``localize_every``-th step (step count, not frame
    index); ``localizer_track`` fuses them over the episode with the noisy odometry observations. A frame that
    cannot be localized has NaN ``estimate`` and ``error_m``, and its message in ``env.unwrapped
    .localization_error``.

    **Localizer**: None (default); ``"cross"`` (no database: the replay's map alone, which must then be given
    as ``map``); a build directory (``satloc build`` + ``satloc train-projection``, loaded in ``localizer_mode``,
    once per process) or a :class:`satloc.localizers.database.Localizer` (its own mode holds); or a localizer of
    one's own (:mod:`satloc.localizers.interface`: an object, its class or ``"module:Name"``). Every localization
    is given a prior drawn around the frame's pose in the data (the GPS / OXTS fix): its centre uniformly within
    ``prior_radius_m`` of it, its heading within ``prior_yaw_deg``, from a generator seeded by the episode's seed
    (``env.unwrapped.last_prior``; none for a frame without a pose). A built-in localizer
    must have been built for the sequence's camera (every :class:`StereoCamera` field; the message gives both
    cameras' differing values) and for the sequence's data: :class:`satloc.ConfigError`, naming the localizer
    (its build directory and recorded scene where known) and the sequence, when the two record different
    geographic frames (``meta["geo_frame"]`` of the sequence and of the build's database) or different
    simulated scenes or aliasing (``meta["scene"]``, ``meta["aliasing"]`` of a recording; an auto cache
    entry's key), or when none of the sequence's poses lies on the localizer's satellite map. ``"auto"`` is
    refused (it builds from a simulated scene).

    **Reward**: 0, or with ``reward="neg_error"`` minus ``error_m`` (0 while there is no finite error).

    **Rendering** (``render_mode="rgb_array"``): SatLoc-v0's panels (:func:`satloc_env.envs.drive.compose_view`): the
    left image, a bird's-eye crop of the map around the frame's pose and the whole map with the sequence's
    path, the posterior heatmap, the estimate (green) and the truth (red).

    **Determinism**: the same data, seed and actions give identical observations and info.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}
    _SHARED_KWARGS = ("localizer", "sequence", "map")

    def __init__(self, render_mode: str | None = None, **config: Any):
        if render_mode not in (None, "rgb_array"):
            raise ConfigError(f"render_mode: expected None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        config, loc_instance = _split_localizer(config, "SatLocReplayEnv", allow_auto=False)
        config, seq_instance = _split_instance(config, "sequence", Sequence, "a sequence directory or a "
                                               "satloc.sequence.Sequence")
        config, map_instance = _split_instance(config, "map", SatelliteMap, "None, a map directory or a "
                                               "satloc.satmap.SatelliteMap")
        self._loc = LocalizationState()
        self._vo = None                       # satloc.tracking.vo.StereoVO of the episode (odometry="visual")
        self._oxts = None                     # odometry="oxts": the drive's per-frame OXTS odometry
        cfg = from_dict(ReplayConfig, config, "SatLocReplayEnv config")
        cfg = check_localizer_config(cfg, loc_instance is not None, allow_auto=False, allow_cross=True)
        for key, inst in (("sequence", seq_instance), ("map", map_instance)):
            if getattr(cfg, key) == INSTANCE and inst is None:
                raise ConfigError(f"{key}: {INSTANCE!r} stands for an object passed as the {key} keyword; pass the "
                                  "object itself")
        if cfg.max_skip < 1:
            raise ConfigError(f"max_skip: expected an integer >= 1, got {cfg.max_skip}")
        self.sequence = seq_instance if seq_instance is not None else _load_sequence(cfg.sequence)
        if len(self.sequence) < 2:
            raise ConfigError(f"sequence {self.sequence.name!r}: has {len(self.sequence)} frame(s); a replay needs "
                              "at least 2")
        # the localizer
        self._loc_identity: dict = {"source": "the localizer"}   # what is known of the localizer's data
        if loc_instance is not None or (cfg.localizer is not None and is_localizer_spec(cfg.localizer)):
            self._loc.localizer, self._loc_identity = make_localizer(
                loc_instance if loc_instance is not None else cfg.localizer, cfg.localizer_track, "SatLocReplayEnv")
            engine = getattr(self.localizer, "engine", None)   # the paper's method given as its engine
            if (engine is not None and loc_instance is not None and not callable(getattr(loc_instance, "reset", None))
                    and hasattr(engine.config, "mode")):
                cfg = dataclasses.replace(cfg, localizer_mode=engine.config.mode, localizer_refine=engine.config.refine,
                                          localizer_track=bool(self.localizer.track))
        elif cfg.localizer not in (None, "cross"):
            from .auto_localizer import load_cached_localizer

            self._loc.localizer = load_cached_localizer(cfg.localizer, cfg.localizer_mode,
                                                        cfg.localizer_refine).as_localizer(cfg.localizer_track)
            self._loc_identity = build_identity(cfg.localizer)
        self._seq_dir = getattr(self.sequence, "_dir", None)   # a recording's folder (its map/ is beside it)
        engine = getattr(self.localizer, "engine", None)        # a built-in localizer's (its camera, its map)
        if engine is not None:
            self.sequence = _in_camera(self.sequence, engine.camera)
        self.camera = self.sequence.camera
        self._poses = self.sequence.poses
        self._stamps = self.sequence.timestamps
        self.config = cfg
        self._episode = self._check_episode(cfg, "SatLocReplayEnv config")
        if engine is not None:
            check_localizer_camera(engine, self.camera, f"sequence {self.sequence.name!r}",
                                   self._loc_identity["source"])
            self._check_localizer_data()
        if self._loc.needs_frame_depth and self.sequence[self._episode.start_frame].depth is None:
            raise ConfigError(f"localizer: it reads the frames' depth (depth_source 'frame'), but sequence "
                              f"{self.sequence.name!r} has no depth channel")
        self._map_instance = map_instance
        self._blank_map_used = False                # no map of the place: a grey canvas
        self.last_prior = None                      # the prior of the last localization
        self.satmap: SatelliteMap | None = None     # resolved on first use (render) by the ``map`` property
        if map_instance is not None or cfg.map is not None:
            self.satmap = self._resolve_map()
        if cfg.localizer == "cross":   # no database: the satellite map alone, which the replay must have
            from .cross_localizer import cross_localizer

            sm = self.map
            if self._blank_map_used:
                raise ConfigError("localizer: 'cross' localizes against the satellite map; give map= (a map "
                                  "directory or georeferenced imagery of the drive)")
            import hashlib

            # the map's own pixels and georeference, not where it came from (an object's id may be reused)
            h = hashlib.sha256(np.ascontiguousarray(sm.image).tobytes())
            h.update(repr((float(sm.meters_per_pixel), tuple(sm.origin))).encode())
            key = ("replay", h.hexdigest())
            self._loc.localizer = cross_localizer(sm, self.camera, key).as_localizer(cfg.localizer_track)
            self._loc_identity = {"source": "the cross-view localizer of the replay's map"}
        # spaces
        h, w = self.camera.height, self.camera.width
        obs = {
            "left": spaces.Box(0, 255, (h, w, 3), np.uint8),
            "right": spaces.Box(0, 255, (h, w, 3), np.uint8),
            "odometry": spaces.Box(-np.inf, np.inf, (3,), np.float32),
        }
        if cfg.depth:
            obs["depth"] = spaces.Box(0.0, np.inf, (h, w), np.float32)
        self.observation_space = spaces.Dict(obs)
        self.action_space = spaces.Discrete(cfg.max_skip, start=1)
        self._stereo = None
        self.frame_index: int | None = None
        self.steps = 0
        self._last_left: np.ndarray | None = None
        self._done = False

    # --- configuration ----------------------------------------------------------------------------
    @staticmethod
    def default_config() -> dict:
        return to_dict(ReplayConfig())

    @property
    def localizer(self):
        """The :class:`satloc.localizers.database.Localizer` in use (None: off)."""
        return self._loc.localizer

    @property
    def localization_error(self) -> str | None:
        """The message of the last frame that could not be localized (None after a result)."""
        return self._loc.error

    @property
    def map(self) -> SatelliteMap:
        """The satellite map the render panels draw on (see the class docstring for the default)."""
        if self.satmap is None:
            self.satmap = self._resolve_map()
        return self.satmap

    def _check_episode(self, cfg: ReplayConfig, where: str) -> ReplayConfig:
        n = len(self.sequence)
        if cfg.stride < 1:
            raise ConfigError(f"{where}: stride: expected an integer >= 1, got {cfg.stride}")
        end = n if cfg.end_frame is None else cfg.end_frame
        if not 0 < end <= n:
            raise ConfigError(f"{where}: end_frame: expected an index in [1, {n}] (the sequence has {n} frames) or "
                              f"None, got {cfg.end_frame}")
        if not 0 <= cfg.start_frame < end - cfg.stride:
            raise ConfigError(f"{where}: start_frame: expected an index in [0, {end - cfg.stride - 1}], leaving at "
                              f"least one stride ({cfg.stride}) before the end (frame {end - 1}), got "
                              f"{cfg.start_frame}")
        return cfg

    def _check_localizer_data(self) -> None:
        """Refuse a localizer built for other data than the sequence: another geographic frame or simulated scene
        (where both record theirs), or a satellite map that none of the sequence's poses lies on."""
        seq, ident, loc = self.sequence, self._loc_identity, getattr(self.localizer, "engine", None)
        src = ident["source"]
        frame, theirs = seq.geo_frame, ident.get("geo_frame")
        if frame is not None and isinstance(theirs, dict):
            from satloc.geoframe import GeoFrame

            other = GeoFrame.from_dict(theirs, f"{src}: database meta.geo_frame")
            if not (math.isclose(frame.lon0, other.lon0, abs_tol=1e-9)
                    and math.isclose(frame.lat0, other.lat0, abs_tol=1e-9)):
                raise ConfigError(f"localizer: {src} was built in the geographic frame (lon0 {other.lon0}, lat0 "
                                  f"{other.lat0}), not in that of sequence {seq.name!r} (lon0 {frame.lon0}, lat0 "
                                  f"{frame.lat0}); read the sequence in the build's frame")
        scene, alias = seq.meta.get("scene"), seq.meta.get("aliasing")
        if isinstance(scene, str) and isinstance(ident.get("scene"), str):
            a, b = ident.get("aliasing"), alias
            if scene != ident["scene"] or (isinstance(a, (int, float)) and isinstance(b, (int, float))
                                           and not math.isclose(a, b, abs_tol=1e-9)):
                what = f"scene {scene!r}" + (f" (aliasing {b:g})" if isinstance(b, (int, float)) else "")
                raise ConfigError(f"localizer: {src} is not a build of {what}, where sequence {seq.name!r} was "
                                  "recorded; a localizer localizes only on the map it was built on")
        xy = self._poses[np.all(np.isfinite(self._poses[:, :2]), axis=1), :2]
        sf = getattr(loc, "satfeat", None)
        if len(xy) and sf is not None and not sf.pixel_index(xy)[1].any():
            h, w = sf.features.shape[:2]
            x0, y1 = sf.origin
            x1, y0 = x0 + w * sf.meters_per_pixel, y1 - h * sf.meters_per_pixel
            lo, hi = xy.min(0), xy.max(0)
            raise ConfigError(f"localizer: none of the {len(xy)} poses of sequence {seq.name!r} (x {lo[0]:.1f} to "
                              f"{hi[0]:.1f} m, y {lo[1]:.1f} to {hi[1]:.1f} m) lies on the satellite map {src} was "
                              f"built on (x {x0:.1f} to {x1:.1f} m, y {y0:.1f} to {y1:.1f} m): a build of other data")

    def _resolve_map(self) -> SatelliteMap:
        cfg, seq = self.config, self.sequence
        if self._map_instance is not None:
            sm = self._map_instance
        elif cfg.map is not None:
            d = Path(cfg.map).expanduser()
            sm = SatelliteMap.load(d) if (d / "map.json").is_file() else self._load_geo_map(d)
        else:
            sm = self._default_map()
        _check_same_geo_frame(sm, seq)
        return sm

    def _load_geo_map(self, path: Path) -> SatelliteMap:
        """A GeoTIFF, image + world file or XYZ tile folder, read into the sequence's GeoFrame around its path."""
        seq = self.sequence
        if not path.exists():
            raise ConfigError(f"map: {str(path)!r} not found; expected None, a map directory (map.json), a GeoTIFF, "
                              "an image with a world file, an XYZ tile folder or a SatelliteMap")
        frame = seq.geo_frame
        if frame is None:
            raise ConfigError(f"map: {str(path)!r} is georeferenced imagery, but sequence {seq.name!r} has no "
                              "meta['geo_frame'] to place it in (only real-data readers and georeferenced scenes set it)")
        from satloc.geodata.georef import load_map, map_bounds

        xy = self._poses[np.all(np.isfinite(self._poses[:, :2]), axis=1), :2]
        m = PANEL_M / 2
        region = (*(xy.min(0) - m), *(xy.max(0) + m)) if len(xy) else None
        # the image's own resolution, coarsened for a long path so that the map stays within MAX_MAP_PX a side
        # (it is drawn in panels of PANEL_M / PANEL_PX m per pixel; a 0.1 m orthophoto of a 5 km drive would
        # take gigabytes)
        _, mpp, bounds = map_bounds(path, frame=frame)
        x0, y0, x1, y1 = region if region is not None else bounds
        mpp = max(mpp, max(x1 - x0, y1 - y0) / MAX_MAP_PX)
        return load_map(path, mpp, frame=frame, region=region)

    def _default_map(self) -> SatelliteMap:
        """The build's map, else the recording's ``map/`` beside the sequence, else a grey canvas."""
        candidates = []
        if self.config.localizer not in (None, LOCALIZER_INSTANCE, "cross") and not is_localizer_spec(
                self.config.localizer):
            try:
                m = read_json(Path(self.config.localizer) / "build.json").get("map")
            except Exception:  # noqa: BLE001 - an unreadable build.json only loses this default
                m = None
            if m:
                candidates.append(Path(m))
        if self._seq_dir is not None:
            candidates.append(Path(self._seq_dir).parent / "map")
        for d in candidates:
            if (d / "map.json").is_file():
                return SatelliteMap.load(d)
        self._blank_map_used = True
        return _blank_map(self._poses)

    # --- gym API ----------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = check_reset_options(options, EPISODE_KEYS, ReplayConfig)
        cfg = self._check_episode(override(self.config, options, "reset options"), "reset options")
        self._episode = cfg
        start = cfg.start_frame
        if cfg.random_start:
            start = int(self.np_random.integers(cfg.start_frame, self._end(cfg) - cfg.stride))
        self.frame_index, self.steps, self._done = start, 0, False
        # the priors and the localizer's seed: children of the episode's seed sequence with spawn keys of their
        # own (none of the episode's other draws change), numbered by the episodes since the last seeded reset
        self._episodes_since_seed = 0 if seed is not None else getattr(self, "_episodes_since_seed", -1) + 1
        if self.localizer is not None:
            ss = self.np_random.bit_generator.seed_seq

            def child(key):
                return np.random.SeedSequence(ss.entropy, spawn_key=tuple(ss.spawn_key) + (key, self._episodes_since_seed))

            from satloc.localizers.interface import Context

            self._prior_rng = np.random.default_rng(child(PRIOR_SPAWN_KEY))
            stamps = np.asarray(self.sequence.timestamps, np.float64)
            self._gnss = GnssReceiver(self.config.gnss, self.config.prior_radius_m, self.config.prior_yaw_deg,
                                      self._prior_rng, float(stamps.min()) if len(stamps) else 0.0)
            self._loc.begin(Context(self.camera, self.map, seed=int(child(LOCALIZER_SPAWN_KEY).generate_state(1)[0]),
                                    database=None, place=self.sequence.name))
        else:
            self._loc.reset()
        obs, from_stereo = self._observe(np.zeros(3, np.float32))
        self._vo = None
        if cfg.odometry == "visual":          # its first pair: the reference of the first step's motion
            from satloc.tracking.vo import StereoVO

            self._vo = StereoVO(self.sequence.camera)
            self._vo.step(obs["left"], obs["right"])
        elif cfg.odometry == "oxts" and self._oxts is None:
            from satloc.datasets.kitti import oxts_odometry

            if (self.sequence.meta or {}).get("source") != "kitti_raw":
                raise ConfigError("odometry: 'oxts' reads a KITTI drive's motion sensors; this sequence is not one "
                                  "(give noisy_truth or visual)")
            self._oxts = oxts_odometry(self.sequence)
        self._localize()
        return obs, self._info(np.zeros(3), True, from_stereo)

    def step(self, action):
        if self.frame_index is None:
            raise RuntimeError("call reset() first")
        if self._done:
            raise RuntimeError("the replay reached the end of the data (truncated); call reset()")
        skip = _skip_count(action, self.config.max_skip)
        cfg = self._episode
        last = self._end(cfg) - 1
        prev = self.frame_index
        target = prev + min(skip, (last - prev) // cfg.stride) * cfg.stride
        self.frame_index = target
        self.steps += 1
        a, b = self._poses[prev], self._poses[target]
        noise = self.np_random.normal(0.0, 1.0, 3)   # drawn on every step: the stream does not depend on the data
        if np.all(np.isfinite(a)) and np.all(np.isfinite(b)):
            true_odo = Pose2(*a).between(Pose2(*b)).as_array()
            dist = math.hypot(true_odo[0], true_odo[1])
            odo = true_odo + noise * np.array([cfg.odometry_noise[0] * dist, cfg.odometry_noise[0] * dist,
                                               cfg.odometry_noise[1]])
            valid = True
        else:
            true_odo, odo, valid = np.full(3, np.nan), np.zeros(3), False
        obs, from_stereo = self._observe(odo.astype(np.float32))
        sensed = None
        if self._vo is not None:              # the motion as the stereo pairs show it
            sensed = self._vo.step(obs["left"], obs["right"])
        elif cfg.odometry == "oxts":          # the drive's speed and yaw rate, over the frames stepped
            sensed = np.zeros(3)
            for j in range(prev + 1, target + 1):
                sensed = compose_motion(sensed, self._oxts[j])
        if sensed is not None:
            valid = bool(np.all(np.isfinite(sensed)))
            obs["odometry"] = np.asarray(sensed if valid else np.zeros(3), np.float32)
        self._loc.add_odometry(obs["odometry"] if valid else np.full(3, np.nan))
        if self.steps % self.config.localize_every == 0:
            self._localize()
        info = self._info(true_odo, valid, from_stereo)
        self._done = target + cfg.stride > last
        reward = 0.0
        if self.config.reward == "neg_error" and np.isfinite(info["error_m"]):
            reward = -float(info["error_m"])
        return obs, reward, False, self._done, info

    def _end(self, cfg: ReplayConfig) -> int:
        return len(self.sequence) if cfg.end_frame is None else cfg.end_frame

    def _observe(self, odometry: np.ndarray) -> tuple[dict, bool]:
        frame = self.sequence[self.frame_index]
        self._frame = frame
        obs = {"left": np.ascontiguousarray(frame.left, np.uint8), "right": np.ascontiguousarray(frame.right, np.uint8),
               "odometry": odometry}
        from_stereo = False
        if self.config.depth:
            if frame.depth is not None:
                d = frame.depth
            else:
                if self._stereo is None:
                    from satloc.stereo import StereoDepth

                    self._stereo = StereoDepth(self.camera)
                d, from_stereo = self._stereo(frame.left, frame.right), True
            obs["depth"] = np.maximum(np.nan_to_num(np.asarray(d, np.float32), nan=0.0, posinf=0.0), 0.0)
        self._last_left = obs["left"]
        return obs, from_stereo

    def _localize(self) -> None:
        """Localize the current frame from a prior drawn around its pose in the data (the GPS / OXTS fix; none for
        a frame without a pose) as ``gnss`` gives it (by default uniform within ``prior_radius_m``, heading within
        ``prior_yaw_deg``)."""
        if self.localizer is None:
            return
        f = self._frame
        frame = dataclasses.replace(f, pose=None, labels=None,
                                    depth=f.depth if self._loc.needs_frame_depth else None)
        p = self._poses[self.frame_index]
        prior = self._gnss.fix(p, float(f.timestamp)) if np.all(np.isfinite(p)) else None
        self.last_prior = prior
        self._loc.localize(frame, self.steps, prior)

    def _info(self, true_odo: np.ndarray, valid: bool, from_stereo: bool) -> dict:
        i = self.frame_index
        pose = np.array(self._poses[i], np.float64)
        info = {
            "pose": pose,
            "odometry_true": np.asarray(true_odo, np.float64),
            "odometry_valid": np.bool_(valid),
            "step": np.int64(self.steps),
            "frame_index": np.int64(i),
            "timestamp": np.float64(self._stamps[i]),
        }
        if self.config.depth:
            info["depth_from_stereo"] = np.bool_(from_stereo)
        info.update(self._loc.info(pose))
        return info

    # --- rendering --------------------------------------------------------------------------------
    def render(self):
        if self.render_mode != "rgb_array" or self._last_left is None:
            return None
        p = self._poses[self.frame_index]
        pose = Pose2(*p) if np.all(np.isfinite(p)) else None
        return compose_view(self._last_left, self.map, pose, self._poses, self._loc.view,
                            localized=self._loc.localized)

    def close(self):
        self._stereo = None
        close_localizer(self._loc.localizer)


# --- helpers ----------------------------------------------------------------------------------------------
def _split_instance(config: dict, key: str, cls: type, expected: str) -> tuple[dict, Any]:
    """Config with an object of ``cls`` given as ``key`` replaced by :data:`INSTANCE`, and the object."""
    config = dict(config)
    if key not in config:
        return config, None
    value = config[key] = unshare(config[key])
    if value is None or isinstance(value, str):
        return config, None
    if isinstance(value, os.PathLike):
        config[key] = os.fspath(value)
        return config, None
    if not isinstance(value, cls):
        raise ConfigError(f"SatLocReplayEnv config.{key}: expected {expected}, got {type(value).__name__}")
    config[key] = INSTANCE
    return config, value


def _load_sequence(path: str | None) -> Sequence:
    if path is None:
        raise ConfigError("SatLocReplayEnv config.sequence: a sequence is required (a sequence directory, a KITTI "
                          "raw drive, a Malaga Urban extract or a satloc.sequence.Sequence)")
    from satloc.datasets import open_sequence

    return open_sequence(Path(path).expanduser())


def _in_camera(seq: Sequence, camera) -> Sequence:
    """``seq`` resampled into the localizer's ``camera`` when the two differ only in image size and intrinsics
    (e.g. a KITTI drive at 1242x375 and a localizer built at half resolution); otherwise ``seq`` unchanged, and
    the camera check that follows says what differs."""
    c = seq.camera
    if c == camera or c.rig_differences(camera, 1e-6, 1e-6, 1e-6):
        return seq
    return seq.view(None, camera)


def _skip_count(action, max_skip: int) -> int:
    """The action as a skip count in [1, ``max_skip``] (an integer, a numpy integer or a 1-element integer
    array); anything else raises :class:`satloc_env.envs.drive.ActionError` (a ValueError): a Discrete action out of
    range is not clipped."""
    try:
        a = np.asarray(action)
    except (ValueError, TypeError):
        a = np.asarray(None)
    if a.size != 1 or not np.issubdtype(a.dtype, np.integer) or not 1 <= int(a.reshape(())) <= max_skip:
        raise ActionError(f"action: expected an integer skip count in [1, {max_skip}], got {action!r} (a skip count "
                          "is a Python or numpy integer, or an integer array of one element, not a float, bool or "
                          "string; out-of-range counts are not clipped)")
    return int(a.reshape(()))


def _check_same_geo_frame(sm: SatelliteMap, seq: Sequence) -> None:
    """A map and a sequence that both name their geographic frame must name the same one."""
    mine, theirs = sm.frame, seq.geo_frame
    if mine is None or theirs is None:
        return
    if not (math.isclose(mine.lon0, theirs.lon0, abs_tol=1e-9) and math.isclose(mine.lat0, theirs.lat0, abs_tol=1e-9)):
        raise ConfigError(f"map: its geographic frame (lon0 {mine.lon0}, lat0 {mine.lat0}) is not the frame of "
                          f"sequence {seq.name!r} (lon0 {theirs.lon0}, lat0 {theirs.lat0}); load the map into the "
                          "sequence's frame")


def _blank_map(poses: np.ndarray, margin_m: float = PANEL_M / 2, max_px: int = 2048) -> SatelliteMap:
    """A grey canvas around the path of ``poses`` (the render's map when there is none)."""
    xy = poses[np.all(np.isfinite(poses[:, :2]), axis=1), :2]
    lo, hi = (xy.min(0), xy.max(0)) if len(xy) else (np.zeros(2), np.zeros(2))
    lo, hi = lo - margin_m, hi + margin_m
    mpp = max(0.5, float((hi - lo).max()) / max_px)
    w, h = (int(math.ceil(v / mpp)) for v in hi - lo)
    return SatelliteMap(np.full((h, w, 3), 90, np.uint8), mpp, (float(lo[0]), float(hi[1])))
