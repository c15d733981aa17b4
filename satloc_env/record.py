"""Database and query passes: drive a route with the autopilot and record stereo frames to disk.

``record_passes(scene, out_dir)`` writes::

    out_dir/map/          the scene's satellite map (SatelliteMap layout)
    out_dir/database/     Sequence: the database pass (lane offset, no occluders, reference appearance)
    out_dir/query/        Sequence: the query pass (another lane offset, appearance and occluders)

Both sequences use the on-disk layout of :mod:`satloc.sequence`, which the dataset readers also produce.

This module does not import :mod:`satloc_env.env`: the environment uses :mod:`satloc_env.autoloc` for
``localizer="auto"``, which records the scene's database pass with this module, so the recorders make their
environments through gymnasium's registry entry of ``satloc/SatLoc-v0`` (:func:`make_env`) and the imports
go one way (env -> autoloc -> record).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.envs.registration import load_env_creator
from tqdm import tqdm

from satloc.config import from_dict, to_dict
from satloc.geometry import Pose2
from satloc.sequence import Frame, Sequence, SequenceWriter

#: the id ``satloc_env`` registers the simulator under (``satloc_env.ENV_ID``; importing the package, which
#: every import of this module does first, registers it)
ENV_ID = "satloc/SatLoc-v0"


def make_env(**config: Any) -> gym.Env:
    """A new, unwrapped ``satloc/SatLoc-v0`` environment (:class:`satloc_env.env.SatLocEnv`) with ``config``:
    the class of the registry's entry point, called without gymnasium's wrappers."""
    return load_env_creator(gym.spec(ENV_ID).entry_point)(**config)


@dataclass
class PassConfig:
    route: str | None = None        # default: the scene's database_route / query_route
    lane_offset_m: float = -1.75
    spacing_m: float = 1.0          # record a frame every this many metres driven
    max_frames: int | None = None   # stop early after this many frames
    occlusion: float = 0.0
    appearance: float = 0.0
    seed: int = 0
    depth: bool = True              # store true depth (simulator ground truth) with each frame
    labels: bool = False


@dataclass
class RecordConfig:
    scene: str = "city"
    resolution: str = "half"
    aliasing: float | None = None
    speed_mps: float = 8.0
    database: PassConfig = field(default_factory=PassConfig)
    query: PassConfig = field(default_factory=lambda: PassConfig(lane_offset_m=-0.75, spacing_m=10.0,
                                                                   occlusion=0.3, appearance=0.5, seed=1))


def record_pass(env: gym.Env, p: PassConfig, route: str, out: Path, name: str, progress: bool = True,
                meta: dict | None = None) -> Sequence:
    """Drive ``route`` once with the autopilot of ``env`` (a ``satloc/SatLoc-v0`` environment, wrapped or
    not), writing a frame every ``p.spacing_m`` metres to ``out``."""
    obs, info = env.reset(seed=p.seed, options={
        "route": route, "lane_offset_m": p.lane_offset_m, "occlusion": p.occlusion, "appearance": p.appearance,
        "max_steps": 10**9})
    length = env.unwrapped.route.length
    total = p.max_frames or int(length // p.spacing_m) + 1
    m = dict(meta or {})
    m.update(pass_config=to_dict(p), route=route, route_length_m=length)
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
                    raise RuntimeError(f"the autopilot left the road on route {route!r} at {info['pose']}")
                break
        seq = w.close()
    bar.close()
    return seq


def record_passes(config: RecordConfig | dict[str, Any], out_dir: str | Path, progress: bool = True
                  ) -> tuple[Sequence, Sequence]:
    """Record the database and query passes of a scene into ``out_dir`` (see the module docstring)."""
    cfg = config if isinstance(config, RecordConfig) else from_dict(RecordConfig, config, "record config")
    out = Path(out_dir)
    sequences = []
    for name, p in (("database", cfg.database), ("query", cfg.query)):
        # localizer=None: recording needs no localization (and "auto" would itself record the database pass)
        env = make_env(scene=cfg.scene, resolution=cfg.resolution, aliasing=cfg.aliasing, speed_mps=cfg.speed_mps,
                       depth=p.depth, labels=p.labels, localizer=None)
        try:
            env.reset(seed=p.seed)
            scene = env.scene
            route = p.route or (scene.spec.database_route if name == "database" else scene.spec.query_route)
            if name == "database":
                scene.satmap.save(out / "map")
            meta = {"source": "satloc_env", "scene": scene.name, "aliasing": scene.spec.knobs.aliasing}
            if scene.satmap.frame is not None:  # a scene over georeferenced imagery: poses are in its GeoFrame
                meta["geo_frame"] = scene.satmap.frame.to_dict()
            sequences.append(record_pass(env, p, route, out / name, name, progress, meta))
        finally:
            env.close()
    return sequences[0], sequences[1]
