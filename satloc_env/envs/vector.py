"""``satloc/SatLoc-v0`` as a batched vector environment: N cars, one GL context, one read-back per step.

``gym.make_vec("satloc/SatLoc-v0", num_envs=N)`` (the registered ``vector_entry_point``, the default
vectorization mode of this id) returns a :class:`SatLocVectorEnv`. It holds N :class:`~satloc_env.envs.drive.SatLocEnv`
sub-environments, each with its own random generator, car, occluders, appearance and localizer state, and one
:class:`~satloc_env.render.stereo.BatchStereoRenderer` that renders the N stereo pairs of a step in one framebuffer:
every world is uploaded once (all N cars share the scene's), every car's pair is drawn into a layer of its own
of one layered framebuffer, exactly as the single environment draws it (same draw order, same window
positions), and the layers are read back with one call for the colour and one for the depth.

It returns what N single environments return, bit for bit (with a localizer see ``batch_network`` below):
``gym.make_vec(..., vectorization_mode="sync")``
with the same seeds gives the same observations, rewards, flags and infos (tested). Autoreset follows
Gymnasium 1.x's default, ``AutoresetMode.NEXT_STEP``: the step after a sub-environment ended resets it (its
action is ignored) and returns the first observation of the new episode, with reward 0 and both flags False.
Infos are batched as Gymnasium's vector environments batch them (an array per key, and ``_key``, the mask of
sub-environments that gave it). ``reset(seed=s)`` seeds sub-environment i with ``s + i``; ``options`` apply to
every sub-environment (``options["reset_mask"]``: reset only those).

Configuration: the keywords of ``SatLoc-v0`` (:class:`~satloc_env.envs.drive.EnvConfig`), the same for all
sub-environments, ``batch_network``, and ``max_episode_steps`` (``gym.make_vec(..., max_episode_steps=n)``:
each car's episodes are truncated after n steps, as ``gym.make``'s TimeLimit truncates a single environment's).
Every action is checked before any car moves: a bad one raises :class:`~satloc_env.envs.drive.ActionError` naming its
sub-environment and changes nothing. With a localizer, each sub-environment localizes its own frames;
with ``batch_network`` (the default) the network part of the features of all the frames localized in a step
runs first as one batch (:meth:`satloc.localizers.database.Localizer.prefetch`; 1.5 times the throughput of 8 single
calls on the 2-core CPU machine). Batched convolutions round differently: the network's outputs differ from
the single environment's by about 1e-6, so results with a localizer match N single environments to that
rounding (tested: the same estimates to 1e-6 m); ``batch_network=False`` keeps them bit for bit.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space, concatenate, create_empty_array

from satloc.errors import ConfigError

from .drive import ActionError, SatLocEnv, unshare

__all__ = ["SatLocVectorEnv"]


class SatLocVectorEnv(VectorEnv):
    """N :class:`SatLocEnv` cars stepped together, their views rendered in one batch (see the module notes)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 1, render_mode: str | None = None, batch_network: bool = True,
                 **config: Any):
        from satloc_env.render.stereo import BatchStereoRenderer

        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ConfigError(f"num_envs: expected an integer >= 1, got {num_envs!r}")
        # What gym.make_vec passes on: max_episode_steps truncates each car's episodes as gym.make's TimeLimit
        # does (on top of SatLoc-v0's own max_steps); the env checker is for single environments.
        limit = config.pop("max_episode_steps", None)
        config.pop("disable_env_checker", None)
        if limit is not None and (isinstance(limit, bool) or not isinstance(limit, (int, np.integer)) or limit < 1):
            raise ConfigError(f"max_episode_steps: expected an integer >= 1 or None, got {limit!r}")
        self.max_episode_steps = None if limit is None else int(limit)
        self.num_envs = int(num_envs)
        loc = config.get("localizer")
        loc = unshare(loc)   # as gym.make's spec holds it
        if isinstance(loc, str) and self.num_envs > 1:
            from .drive import is_localizer_spec

            if is_localizer_spec(loc):   # 'module:Name' naming an object: each car gets it, so it must be a maker
                from satloc.localizers.interface import import_object

                loc = import_object(loc, "localizer")
        if (self.num_envs > 1 and callable(getattr(loc, "localize", None)) and callable(getattr(loc, "reset", None))
                and not isinstance(loc, type)):
            raise ConfigError(f"localizer: one {type(loc).__name__} object cannot serve {self.num_envs} cars (each "
                              "keeps its own state); give its class, a function that makes one, or 'module:Name', "
                              "and each car gets its own")
        self.envs = [SatLocEnv(render_mode=render_mode, **config) for _ in range(self.num_envs)]
        first = self.envs[0]
        self._batch = BatchStereoRenderer(first.camera, anisotropy=first.config.anisotropy, zfar=first.config.zfar_m,
                                          detail_m=first.config.detail_m)
        for env in self.envs:
            env._batch = self._batch
        self.render_mode = render_mode
        self.metadata = dict(self.metadata)
        self.single_observation_space = first.observation_space
        self.single_action_space = first.action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.batch_network = bool(batch_network)
        self._autoreset = np.zeros(self.num_envs, dtype=np.bool_)
        self._obs_list: list = [None] * self.num_envs   # each car's latest observation
        self._ready = False

    # --- gym API ------------------------------------------------------------------------------------------
    def reset(self, *, seed: int | list[int | None] | None = None, options: dict | None = None):
        if seed is None:
            seeds: list = [None] * self.num_envs
        elif isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
            seeds = [int(seed) + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ConfigError(f"reset: expected {self.num_envs} seeds (one per sub-environment), got {len(seeds)}")
        options = dict(options or {})
        mask = options.pop("reset_mask", None)
        if mask is None:
            mask = np.ones(self.num_envs, dtype=np.bool_)
        else:
            mask = np.asarray(mask)
            if mask.shape != (self.num_envs,) or mask.dtype != np.bool_ or not mask.any():
                raise ConfigError(f"reset options: reset_mask must be a bool array of shape ({self.num_envs},) with "
                                  f"at least one True, got {mask!r}")
            if not self._ready and not mask.all():
                raise RuntimeError("reset: the first reset must reset every sub-environment (no reset_mask)")
        infos: dict = {}
        for i in np.flatnonzero(mask):
            obs, info = self.envs[i].reset(seed=seeds[i], options=options or None)
            self._obs_list[i] = obs
            infos = self._add_info(infos, info, i)
            self._autoreset[i] = False
        self._ready = True
        return self._batched_obs(), infos

    def step(self, actions):
        if not self._ready:
            raise RuntimeError("call reset() first")
        actions = np.asarray(actions)
        if actions.shape[:1] != (self.num_envs,):
            raise ConfigError(f"step: expected actions of shape ({self.num_envs}, 2), one per sub-environment, got "
                              f"shape {actions.shape}")
        n = self.num_envs
        rewards = np.zeros(n, np.float64)
        terminations = np.zeros(n, np.bool_)
        truncations = np.zeros(n, np.bool_)
        infos: dict = {}
        stepping, moved = [], {}
        for i, env in enumerate(self.envs):   # every action checked before any car moves: a bad one changes nothing
            if not self._autoreset[i]:
                try:
                    env._check_action(actions[i])
                except ActionError as e:
                    raise ActionError(f"sub-environment {i}: {e}") from None
        for i, env in enumerate(self.envs):
            if self._autoreset[i]:
                continue
            moved[i] = env._advance(actions[i])
            stepping.append(i)
        if stepping:
            groups: dict[tuple, list[int]] = {}   # the render arguments (depth, labels) are the same for all
            for i in stepping:
                groups.setdefault(self.envs[i]._render_args(), []).append(i)
            rendered: dict[int, dict] = {}
            for (depth, labels), idx in groups.items():
                outs = self._batch.render_many([(self.envs[i]._renderer, self.envs[i].pose, self.envs[i].attitude.tilt)
                                                for i in idx],
                                               depth=depth, labels=labels)
                rendered.update(zip(idx, outs))
        observed = {i: self.envs[i]._observe_step(rendered[i], moved[i][0]) for i in stepping}
        if self.batch_network:
            self._prefetch([i for i in stepping if self.envs[i]._localizes_now()])
        for i, env in enumerate(self.envs):
            if self._autoreset[i]:
                self._obs_list[i], info = env.reset()
            else:
                (self._obs_list[i], rewards[i], terminations[i], truncations[i],
                 info) = env._finish_step(observed[i], moved[i][1])
                if self.max_episode_steps is not None and env.steps >= self.max_episode_steps:
                    truncations[i] = True   # env.steps: the steps since its reset, as TimeLimit counts them
            infos = self._add_info(infos, info, i)
        self._autoreset = terminations | truncations
        return self._batched_obs(), rewards, terminations, truncations, infos

    def render(self):
        return tuple(env.render() for env in self.envs)

    def close_extras(self, **kwargs: Any) -> None:
        for env in self.envs:
            env.close()
        self._batch.close()

    # --- helpers ------------------------------------------------------------------------------------------
    def _prefetch(self, idx: list[int]) -> None:
        """One network call for the frames the cars ``idx`` localize this step, per built-in localizer they share
        (each car's localizer wraps the shared ``engine``; a localizer without ``prefetch`` batches nothing)."""
        by_loc: dict[int, tuple] = {}
        for i in idx:
            loc = self.envs[i].localizer
            target = getattr(loc, "engine", loc)
            if callable(getattr(target, "prefetch", None)):
                by_loc.setdefault(id(target), (target, []))[1].append(self.envs[i]._frame())
        for target, frames in by_loc.values():
            target.prefetch(frames)

    def _batched_obs(self) -> dict:
        out = create_empty_array(self.single_observation_space, n=self.num_envs, fn=np.empty)
        return concatenate(self.single_observation_space, self._obs_list, out)

    @property
    def np_random_seed(self) -> tuple:
        return tuple(env.np_random_seed for env in self.envs)

    def get_attr(self, name: str) -> tuple:
        """The attribute ``name`` of each sub-environment."""
        return tuple(getattr(env, name) for env in self.envs)

    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple:
        """Call the method ``name`` of each sub-environment (or read the attribute)."""
        out = []
        for env in self.envs:
            f = getattr(env, name)
            out.append(f(*args, **kwargs) if callable(f) else f)
        return tuple(out)

    def autopilot_actions(self) -> np.ndarray:
        """(N, 2) the route followers' actions of the sub-environments (a scripted driver for each car)."""
        return np.stack([env.autopilot_action() for env in self.envs]).astype(self.single_action_space.dtype)
