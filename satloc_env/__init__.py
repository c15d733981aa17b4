"""satloc_env: a Gymnasium simulator for satellite-image localization, built on :mod:`satloc`.

Importing it registers ``satloc/SatLoc-v0`` (drive a simulated scene), ``satloc/SatLocReplay-v0`` (replay a
recorded sequence, :mod:`satloc_env.replay`) and ``satloc/ActiveLoc-v0`` (choose the streets that localize the
car soonest, :mod:`satloc_env.active`)::

    import gymnasium as gym, satloc_env
    env = gym.make("satloc/SatLoc-v0", scene="city", render_mode="rgb_array")
    replay = gym.make("satloc/SatLocReplay-v0", sequence="rec/query", map="rec/map", localizer="rec/build")
    cars = gym.make_vec("satloc/SatLoc-v0", num_envs=8)   # batched: one GL context (satloc_env.vector)
    active = gym.make("satloc/ActiveLoc-v0", map="active_grid")
"""
from gymnasium.envs.registration import register, registry

ENV_ID = "satloc/SatLoc-v0"
REPLAY_ID = "satloc/SatLocReplay-v0"
ACTIVE_ID = "satloc/ActiveLoc-v0"

if ENV_ID not in registry:
    register(id=ENV_ID, entry_point="satloc_env.env:SatLocEnv", max_episode_steps=None,
             vector_entry_point="satloc_env.vector:SatLocVectorEnv")
if REPLAY_ID not in registry:
    register(id=REPLAY_ID, entry_point="satloc_env.replay:SatLocReplayEnv", max_episode_steps=None)
if ACTIVE_ID not in registry:
    register(id=ACTIVE_ID, entry_point="satloc_env.active:ActiveLocEnv", max_episode_steps=None)

from .env import EnvConfig, SatLocEnv  # noqa: E402
from .replay import ReplayConfig, SatLocReplayEnv  # noqa: E402
from .scene import Scene, available_scenes, load_scene  # noqa: E402

__all__ = ["ENV_ID", "REPLAY_ID", "ACTIVE_ID", "EnvConfig", "ReplayConfig", "SatLocEnv", "SatLocReplayEnv", "Scene",
           "available_scenes", "load_scene"]
