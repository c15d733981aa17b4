"""satloc_env: a Gymnasium simulator for satellite-image localization, built on :mod:`satloc`.

Importing it registers ``satloc/SatLoc-v0``::

    import gymnasium as gym, satloc_env
    env = gym.make("satloc/SatLoc-v0", scene="city", render_mode="rgb_array")
"""
from gymnasium.envs.registration import register, registry

ENV_ID = "satloc/SatLoc-v0"

if ENV_ID not in registry:
    register(id=ENV_ID, entry_point="satloc_env.env:SatLocEnv", max_episode_steps=None)

from .env import EnvConfig, SatLocEnv  # noqa: E402
from .scene import Scene, available_scenes, load_scene  # noqa: E402

__all__ = ["ENV_ID", "EnvConfig", "SatLocEnv", "Scene", "available_scenes", "load_scene"]
