"""satloc_env: a Gymnasium simulator for satellite-image localization, built on :mod:`satloc`.

Importing it registers ``satloc/SatLoc-v0`` (drive a simulated scene), ``satloc/SatLocReplay-v0`` (replay a
recorded sequence, :mod:`satloc_env.envs.replay`) and ``satloc/ActiveLoc-v0`` (choose the streets that
localize the car soonest, :mod:`satloc_env.envs.active`)::

    import gymnasium as gym, satloc_env
    env = gym.make("satloc/SatLoc-v0", scene="city", render_mode="rgb_array")
    replay = gym.make("satloc/SatLocReplay-v0", sequence="rec/query", map="rec/map", localizer="rec/build")
    cars = gym.make_vec("satloc/SatLoc-v0", num_envs=8)   # batched: one GL context (satloc_env.envs.vector)
    active = gym.make("satloc/ActiveLoc-v0", map="active_grid")

The package is layered by trade; each layer imports only those below it (checked by import-linter, see
``pyproject.toml``):

* :mod:`satloc_env.world`: scene files into geometry and pixels (no GL);
* :mod:`satloc_env.render`: the GL entry point and the stereo renderers;
* :mod:`satloc_env.envs`: the Gymnasium environments and what only they use;
* :mod:`satloc_env.agents`: the ActiveLoc agents and their training;
* :mod:`satloc_env.experiments`: tables, sweeps, tuning, evaluation on real data, benchmarks, scale-out;
* :mod:`satloc_env.cli`: the ``satloc`` command, on top.
"""
from satloc import __version__  # noqa: F401  (one version for both packages: the distribution's)
from satloc._moved import alias_modules as _alias_modules

from .envs import ACTIVE_ID, ENV_ID, REPLAY_ID, ActionError, EnvConfig, ReplayConfig, SatLocEnv, SatLocReplayEnv
from .world.scene import Scene, available_scenes, load_scene

# modules that moved after 0.1.0 (CHANGELOG.md): the old names still import, with a FutureWarning naming the
# new one. satloc_env.world and satloc_env.render are packages now; they re-export the old modules' names.
MOVED = {f"satloc_env.{old}": f"satloc_env.{new}" for old, new in {
    "_gl": "render.gl",
    "layout": "world.layout", "paint": "world.paint", "generator": "world.generator", "tile": "world.tile",
    "route": "world.route", "roadtrace": "world.roadtrace", "roadgraph": "world.roadgraph",
    "sceneroads": "world.scene_roads", "scenebuildings": "world.scene_buildings", "scene": "world.scene",
    "revisit": "world.revisit",
    "env": "envs.drive", "vector": "envs.vector", "replay": "envs.replay", "active": "envs.active",
    "activemap": "envs.active_map", "autoloc": "envs.auto_localizer", "vehicle": "envs.vehicle",
    "occluders": "envs.occluders", "record": "envs.record", "drivecheck": "envs.drivecheck",
    "experiment": "experiments.scene_run", "compare": "experiments.tables", "tune": "experiments.tune",
    "evaluate": "experiments.evaluate", "bench": "experiments.bench", "soak": "experiments.soak",
    "determinism": "experiments.determinism", "train_features": "experiments.train_features",
    "scale": "experiments.scale",
}.items()}
__getattr__ = _alias_modules(__name__, MOVED)

__all__ = ["ENV_ID", "REPLAY_ID", "ACTIVE_ID", "ActionError", "EnvConfig", "ReplayConfig", "SatLocEnv",
           "SatLocReplayEnv", "Scene", "available_scenes", "load_scene"]
