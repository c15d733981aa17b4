"""Agents for ``satloc/ActiveLoc-v0`` (:mod:`satloc_env.envs.active`): the policies that pick a branch.

* :class:`RandomAgent`: uniform over the branches the junction offers.
* :class:`RouteAgent`: the autopilot's fixed route: the scene's tour from wherever the car is.
* :class:`EntropyAgent`: greedy expected entropy, active Markov localization's rule (Burgard, Fox and Thrun):
  for each branch, predict the belief after driving it to the next junction under each of the most probable
  places (the tracker moved by that place's odometry and fused with the localizer's posteriors of the frames
  on that place's path, from the active map) and take the branch with the lowest expected entropy.
* :class:`LearnedAgent`: a small MLP over the observation (64-64, tanh), trained with sb3-contrib's
  ``MaskablePPO`` (:func:`satloc_env.agents.train.train_agent`, ``examples/train_agent.py``); the shipped weights are
  ``satloc_env/weights/active_policy.pt`` (torch, ``weights_only``); inference needs only torch.

:func:`satloc_env.agents.evaluate.evaluate_agents` runs them on the same seeded starts (``satloc agent
evaluate``); :func:`satloc_env.agents.train.train_agent` trains the learned one.
"""
from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import numpy as np

from satloc.errors import ConfigError, FormatError
from satloc.geometry import Pose2
from satloc.tracking.track import relative_motion
from satloc_env.envs.active import ActiveLocEnv, K, belief_entropy

__all__ = ["RandomAgent", "RouteAgent", "EntropyAgent", "LearnedAgent", "make_agent", "AGENTS", "POLICY_PATH"]

POLICY_PATH = Path(__file__).resolve().parents[1] / "weights" / "active_policy.pt"
AGENTS = ("random", "route", "entropy", "learned")


class RandomAgent:
    """Uniform over the allowed branches (its own generator, seeded per episode)."""

    name = "random"

    def __init__(self, seed: int = 0):
        self.rng = np.random.default_rng(seed)

    def reset(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def act(self, env: ActiveLocEnv, obs: np.ndarray, info: dict) -> int:
        return int(self.rng.choice(np.flatnonzero(info["action_mask"])))


class RouteAgent:
    """The autopilot's fixed route: the branch the scene's tour takes at this junction."""

    name = "route"

    def reset(self, seed: int) -> None:
        pass

    def act(self, env: ActiveLocEnv, obs: np.ndarray, info: dict) -> int:
        a = int(info["route_action"])
        return a if a >= 0 and info["action_mask"][a] else int(np.flatnonzero(info["action_mask"])[0])


class EntropyAgent:
    """Greedy expected entropy over the next street (see the module docstring). ``places``: how many of the
    belief's most probable places the expectation runs over; ``stride``: fuse every this many frames of a
    predicted path (1: every frame, as the environment does with ``fuse_every`` 1)."""

    name = "entropy"

    def __init__(self, places: int = 4, stride: int = 2):
        if places < 1 or stride < 1:
            raise ConfigError("EntropyAgent: places and stride must be >= 1")
        self.places, self.stride = places, stride

    def reset(self, seed: int) -> None:
        pass

    def act(self, env: ActiveLocEnv, obs: np.ndarray, info: dict) -> int:
        allowed = np.flatnonzero(info["action_mask"])
        if len(allowed) == 1:
            return int(allowed[0])
        hyps = env.places(self.places)
        best, best_h = int(allowed[0]), math.inf
        for a in allowed:
            total, weight = 0.0, 0.0
            for cand, p in hyps:
                path = self._path(env, cand, int(a))
                if path is None or p <= 0:   # that place has no such branch: the mask rules it out
                    continue
                total += p * self._entropy_after(env, cand, path)
                weight += p
            h = total / weight if weight > 0 else math.inf
            if h < best_h - 1e-12:
                best, best_h = int(a), h
        return best

    def _path(self, env: ActiveLocEnv, cand: int, slot: int) -> list[int] | None:
        """The recorded frames the car would pass if it stood at candidate ``cand`` and took ``slot`` at the end
        of that candidate's leg (the frames ahead on the leg, then the branch's)."""
        m = env.map
        leg = int(m.cand_leg[cand])
        nxt = int(m.branches[leg, slot])
        if nxt < 0:
            return None
        ahead = [int(q) for q in m.leg_frames[leg] if m.frame_rest[q] < m.cand_rest[cand]]
        return ahead + [int(q) for q in m.leg_frames[nxt]]

    def _entropy_after(self, env: ActiveLocEnv, cand: int, path: list[int]) -> float:
        return belief_entropy(self._belief_after(env, cand, path))

    def _belief_after(self, env: ActiveLocEnv, cand: int, path: list[int]) -> np.ndarray:
        """The belief after driving ``path`` from candidate ``cand``: before each fused frame it moves by the
        motion from the previous one (from ``cand`` before the first), as the environment moves it by the
        odometry since its last fused frame."""
        m = env.map
        t = copy.copy(env.tracker)
        t.belief, t.off = env.tracker.belief.copy(), env.tracker.off.copy()
        prev = m.candidates[cand]
        fused = path[self.stride - 1::self.stride] or path[-1:]
        for q in fused:
            pose = m.frame_pose[q]
            t.predict(relative_motion(Pose2(*prev), Pose2(*pose)))
            prev = pose
            post = m.posterior(q)
            if env.config.evidence != 1.0:   # tempered as the environment tempers what it fuses
                post = post ** env.config.evidence
            if post.sum() > 0:
                t.fuse(post)
        return t.belief


class LearnedAgent:
    """A policy MLP (observation -> 3 logits) from :data:`POLICY_PATH` or ``path``; acts greedily over the
    allowed branches."""

    name = "learned"

    def __init__(self, path: str | Path | None = None):
        import torch

        self.path = Path(path) if path is not None else POLICY_PATH
        if not self.path.is_file():
            raise ConfigError(f"learned agent: no policy at {self.path}; train one with "
                              "`python examples/train_agent.py --out DIR` (needs the `rl` extra)")
        try:
            blob = torch.load(self.path, map_location="cpu", weights_only=True)
            meta = json.loads(blob["meta"])
            state = blob["state"]
        except Exception as e:   # damaged file, not ours, pickled objects
            raise FormatError(f"{self.path}: not a satloc active policy ({type(e).__name__}: {str(e)[:200]})") from e
        if meta.get("format") != "satloc-active-policy":
            raise FormatError(f"{self.path}: not a satloc active policy (format {meta.get('format')!r})")
        self.meta = meta
        self.net = _mlp(int(meta["obs_dim"]), list(meta["hidden"]), K)
        try:
            self.net.load_state_dict(state)
        except (RuntimeError, KeyError) as e:
            raise FormatError(f"{self.path}: policy weights do not match its header ({str(e)[:200]})") from e
        self.net.eval()

    def reset(self, seed: int) -> None:
        pass

    def act(self, env: ActiveLocEnv, obs: np.ndarray, info: dict) -> int:
        import torch

        if obs.shape != (int(self.meta["obs_dim"]),):
            raise ConfigError(f"learned agent: the policy takes {self.meta['obs_dim']} observation entries, the "
                              f"environment gives {obs.shape[0]} (top_k must be {self.meta.get('top_k')})")
        with torch.no_grad():
            logits = self.net(torch.as_tensor(obs, dtype=torch.float32)[None])[0].numpy()
        logits = np.where(np.asarray(info["action_mask"], bool), logits, -np.inf)
        return int(np.argmax(logits))


def _mlp(n_in: int, hidden: list[int], n_out: int):
    import torch.nn as nn

    layers: list = []
    for h in hidden:
        layers += [nn.Linear(n_in, h), nn.Tanh()]
        n_in = h
    layers.append(nn.Linear(n_in, n_out))
    return nn.Sequential(*layers)


def make_agent(name: str, seed: int = 0, policy: str | Path | None = None):
    if name == "random":
        return RandomAgent(seed)
    if name == "route":
        return RouteAgent()
    if name == "entropy":
        return EntropyAgent()
    if name == "learned":
        return LearnedAgent(policy)
    raise ConfigError(f"unknown agent {name!r}; expected one of {', '.join(AGENTS)}")
