"""The Gymnasium environments and what only they use.

* :mod:`~satloc_env.envs.drive`: ``satloc/SatLoc-v0``, a car driving a simulated scene
  (:class:`~satloc_env.envs.drive.SatLocEnv`), its panels and the localizer it reports;
* :mod:`~satloc_env.envs.vector`: the batched ``gym.make_vec`` form (one GL context for N cars);
* :mod:`~satloc_env.envs.replay`: ``satloc/SatLocReplay-v0``, a recorded or real sequence played back;
* :mod:`~satloc_env.envs.active` and :mod:`~satloc_env.envs.active_map`: ``satloc/ActiveLoc-v0``, choosing
  streets that localize the car soonest, and the recorded posterior maps it runs on;
* :mod:`~satloc_env.envs.auto_localizer`: ``localizer="auto"``, a localizer built from the scene's database
  pass and cached;
* :mod:`~satloc_env.envs.vehicle`, :mod:`~satloc_env.envs.occluders`,
  :mod:`~satloc_env.envs.drivecheck`, :mod:`~satloc_env.envs.record`: the car, what blocks its view, whether
  the autopilot can drive a route, and database/query passes recorded to disk.

Importing this package registers the three ids. It may import :mod:`satloc`, :mod:`satloc_env.world` and
:mod:`satloc_env.render`; never the agents, the experiments or the command line (an import-linter contract
in ``pyproject.toml`` checks it).
"""
from gymnasium.envs.registration import register, registry

from .ids import ACTIVE_ID, ENV_ID, REPLAY_ID

if ENV_ID not in registry:
    register(id=ENV_ID, entry_point="satloc_env.envs.drive:SatLocEnv", max_episode_steps=None,
             vector_entry_point="satloc_env.envs.vector:SatLocVectorEnv")
if REPLAY_ID not in registry:
    register(id=REPLAY_ID, entry_point="satloc_env.envs.replay:SatLocReplayEnv", max_episode_steps=None)
if ACTIVE_ID not in registry:
    register(id=ACTIVE_ID, entry_point="satloc_env.envs.active:ActiveLocEnv", max_episode_steps=None)

from .drive import ActionError, EnvConfig, SatLocEnv  # noqa: E402
from .replay import ReplayConfig, SatLocReplayEnv  # noqa: E402

__all__ = ["ENV_ID", "REPLAY_ID", "ACTIVE_ID", "ActionError", "EnvConfig", "ReplayConfig", "SatLocEnv",
           "SatLocReplayEnv"]
