"""The ids the package registers its environments under (``import satloc_env`` registers them)."""

ENV_ID = "satloc/SatLoc-v0"             # satloc_env.envs.drive.SatLocEnv (and the batched vector env)
REPLAY_ID = "satloc/SatLocReplay-v0"    # satloc_env.envs.replay.SatLocReplayEnv
ACTIVE_ID = "satloc/ActiveLoc-v0"       # satloc_env.envs.active.ActiveLocEnv

__all__ = ["ENV_ID", "REPLAY_ID", "ACTIVE_ID"]
