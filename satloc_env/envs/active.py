"""``satloc/ActiveLoc-v0``: active localization. Where should a car that does not know where it is drive so
that the localizer finds out soonest?

The car starts at a seeded random place on a scene's streets with a fresh tracked belief (no prior). At each
junction the agent picks a branch: the action is ``Discrete(3)``, the slots of :data:`satloc_env.envs.active_map.SLOTS`
(left, straight, right), with ``info["action_mask"]`` (and :meth:`ActiveLocEnv.action_masks`, which
sb3-contrib's ``MaskablePPO`` reads) saying which exist here; the way back is never offered. Between
junctions the autopilot drives the chosen street and the tracked localizer (:class:`satloc.tracking.track.Tracker`)
fuses a frame every ``fuse_every`` steps; a step is one recorded frame of the map, 5 m of driving on the
shipped maps, so a decision costs about a dozen steps (a 60-70 m block). A junction with one branch is
driven through without a decision.

The frames' posteriors are the method's own, computed once per scene (:mod:`satloc_env.envs.active_map`): the full
method (W_g, W_s, co-occurrence scores) on frames the simulator rendered at those places under another day's
conditions. The odometry between fused frames is the true relative motion plus noise (``odometry_noise``, as
``SatLoc-v0``'s ``noisy_truth``).

**Episode end.** After each fused frame: *success* (terminated) when the belief locks
(:meth:`satloc.tracking.track.Tracker.locked`: at least ``lock_mass`` of it within ``lock_m`` of its mode) with the
mode within ``success_m`` (10 m) of the truth; *wrong lock* (terminated) when it locks elsewhere; truncated
once ``budget_m`` metres are driven. A start whose belief locks (or that spends the budget) before the first
junction is drawn again (``info["redraws"]``): there the choice cannot matter.

**Reward** (see :class:`ActiveConfig`): ``-distance / 100 m`` per decision (the cost of driving),
``+success_reward`` for a correct lock, ``-wrong_lock_penalty`` for a wrong one. The penalty equals the bonus so
that a guess is worth nothing on average at 50 % and an agent cannot profit from locking early on purpose: its
alternative is to drive on and pay only distance. Truncation adds nothing.

**A localizer of one's own** (``gym.make("satloc/ActiveLoc-v0", localizer=obj | Class | "module:Name")``, any
localizer of :mod:`satloc.localizers.interface`): each frame to fuse is rendered at its recorded pose (the scene's
world, the map's camera), localized with the odometry since the last fused frame and no prior, and its answer
(its pose, or each entry of its posterior) spread over the map's candidate poses as a Gaussian of
``evidence_sigma_m`` within ``evidence_yaw_deg`` of heading; that is the frame's posterior the tracker fuses. A
frame with no answer adds no evidence. ``reset(context)`` is called at every start drawn.

**Observation** (``Box``, float32, :data:`OBS_FIELDS`): the belief's normalised entropy, the locked mass,
P(on the map), the budget used; the ``top_k`` most probable places (modes of the belief at least ``lock_m``
apart) relative to the most probable one (dx, dy in 100 m, cos and sin of the heading difference) and their
probability; per slot whether it exists, the branch's length (100 m), its turn (pi) and how well it would
separate the top places: the entropy (normalised) of their probability split by what driving that branch
would show under each (whether the branch exists there, its length, which branches its end offers).
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from scipy.spatial import cKDTree

from satloc.config import from_dict, to_dict
from satloc.errors import ConfigError
from satloc.geometry import Pose2, wrap_angle
from satloc.tracking.track import TrackConfig, Tracker, compose_motion, relative_motion

from .active_map import SLOTS, ActiveMap
from .drive import ActionError, SharedSpecMixin
from .ids import ACTIVE_ID

__all__ = ["ActiveConfig", "ActiveLocEnv", "OBS_FIELDS", "ACTIVE_ID", "belief_entropy"]

K = len(SLOTS)


@dataclass(frozen=True)
class ActiveConfig:
    """Settings of ``satloc/ActiveLoc-v0``; every field may also be given to ``reset(options=...)``."""

    map: str = "active_grid"            # a scene with a shipped active map, or the path of an active map npz
    fuse_every: int = 1                 # fuse a frame every this many steps (frames of the map)
    budget_m: float = 800.0             # truncate once this many metres are driven
    success_m: float = 10.0             # a lock within this of the truth is a success, else a wrong lock
    top_k: int = 4                      # places described in the observation
    success_reward: float = 5.0
    wrong_lock_penalty: float = 5.0
    distance_cost_per_100m: float = 1.0
    evidence: float = 1.0               # each fused posterior is raised to this power (< 1: frames count less)
    odometry_noise: tuple[float, float] = (0.02, 0.003)   # std: fraction of the distance, radians per step
    tracking: TrackConfig = field(default_factory=lambda: TrackConfig(sigma_m=1.0))   # >= candidate spacing
    max_redraws: int = 100
    # with a localizer of one's own (ActiveLocEnv(localizer=...)): its answer's pose (or each entry of its
    # posterior) is spread over the map's candidate poses within 3 such standard deviations (metres), the
    # candidates' headings within evidence_yaw_deg of it
    evidence_sigma_m: float = 3.0
    evidence_yaw_deg: float = 45.0

    def __post_init__(self):
        if self.fuse_every < 1 or self.top_k < 1 or self.max_redraws < 1:
            raise ConfigError("ActiveLoc: fuse_every, top_k and max_redraws must be >= 1")
        if not (self.budget_m > 0 and self.success_m > 0):
            raise ConfigError("ActiveLoc: budget_m and success_m must be > 0")
        if not (math.isfinite(self.evidence) and self.evidence >= 0):
            raise ConfigError(f"ActiveLoc: evidence must be a finite number >= 0, got {self.evidence}")
        if len(self.odometry_noise) != 2 or min(self.odometry_noise) < 0:
            raise ConfigError(f"ActiveLoc: odometry_noise: expected 2 non-negative numbers, got {self.odometry_noise}")
        if not (math.isfinite(self.evidence_sigma_m) and self.evidence_sigma_m > 0
                and 0 < self.evidence_yaw_deg <= 180):
            raise ConfigError("ActiveLoc: evidence_sigma_m must be > 0 and evidence_yaw_deg in (0, 180]")


def _slot(action) -> int:
    """The action as a slot in [0, 3) (a Python or numpy integer, or an integer array of one element); anything
    else raises :class:`satloc_env.envs.drive.ActionError` (a ValueError) and changes nothing."""
    try:
        a = np.asarray(action)
    except (ValueError, TypeError):
        a = np.asarray(None)
    if a.size != 1 or not np.issubdtype(a.dtype, np.integer) or not 0 <= int(a.reshape(())) < K:
        raise ActionError(f"action: expected a branch slot, an integer in [0, {K}) ({', '.join(SLOTS)}), got "
                          f"{action!r} (a Python or numpy integer or an integer array of one element, not a float, "
                          "bool or string; a slot the junction lacks takes its first allowed branch)")
    return int(a.reshape(()))


def obs_fields(top_k: int) -> list[str]:
    """Names of the observation's entries."""
    f = ["entropy", "locked_mass", "p_on", "budget_used"]
    for i in range(top_k):
        f += [f"place{i}_dx", f"place{i}_dy", f"place{i}_cos", f"place{i}_sin", f"place{i}_p"]
    for s in SLOTS:
        f += [f"{s}_exists", f"{s}_length", f"{s}_turn", f"{s}_separation"]
    return f


OBS_FIELDS = obs_fields(ActiveConfig().top_k)


def belief_entropy(b: np.ndarray) -> float:
    """Shannon entropy (nats) of a probability vector."""
    p = b[b > 0]
    return float(-(p * np.log(p)).sum())


class ActiveLocEnv(SharedSpecMixin, gym.Env):
    """See the module docstring. ``ActiveLocEnv(map="active_grid", budget_m=800, ...)``: the fields of
    :class:`ActiveConfig` (unknown keys are an error), or ``config=ActiveConfig(...)``."""

    metadata = {"render_modes": []}

    def __init__(self, config: ActiveConfig | dict | None = None, localizer: Any = None, **kw: Any):
        if config is not None and kw:
            raise ConfigError("ActiveLoc: give either config or keyword settings, not both")
        self.config = self._make_config(config if config is not None else kw, ActiveConfig())
        self._load_map()
        self._user = None          # a localizer of one's own: each fused frame rendered and localized by it
        self._renderer = None
        if localizer is not None and not (isinstance(localizer, str) and localizer.strip().lower() == "none"):
            from satloc.localizers.interface import resolve_localizer

            from .drive import unshare

            self._user = resolve_localizer(unshare(localizer), "ActiveLoc localizer")
        n = len(obs_fields(self.config.top_k))
        self.observation_space = spaces.Box(-5.0, 5.0, (n,), np.float32)
        self.action_space = spaces.Discrete(K)
        self.tracker: Tracker | None = None

    @staticmethod
    def _make_config(c, base: ActiveConfig) -> ActiveConfig:
        """``base`` overridden by the settings ``c`` (a dict; ``tracking`` may be a dict of some of its fields)."""
        if isinstance(c, ActiveConfig):
            return c
        d = dict(c or {})
        if isinstance(d.get("tracking"), TrackConfig):
            d["tracking"] = to_dict(d["tracking"])
        if isinstance(d.get("tracking"), dict):
            d["tracking"] = dict(to_dict(base.tracking), **d["tracking"])
        return from_dict(ActiveConfig, dict(to_dict(base), **d), "ActiveLoc config")

    def _load_map(self, config: ActiveConfig | None = None) -> None:
        """Load ``config``'s map (default: the current config's) and make ``config`` the current one; nothing
        changes if the map cannot be loaded."""
        config = self.config if config is None else config
        m = ActiveMap.load(config.map)
        tree = cKDTree(m.candidates[:, :2])
        template = Tracker(m.candidates, config.tracking)   # copied per episode: its k-d tree is shared
        self.config, self.map, self._tree, self._template = config, m, tree, template

    # --- gymnasium API --------------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if options:
            config = self._make_config(options, self.config)
            if config.map != self.config.map:
                self._load_map(config)      # a map that fails to load leaves the config and the map as they were
            self.config = config
        cfg, m = self.config, self.map
        self.redraws = 0
        while True:
            leg = int(self.np_random.integers(len(m.legs)))
            frames = m.leg_frames[leg]
            start = int(self.np_random.integers(len(frames)))
            self._begin(leg, start)
            outcome = self._drive()
            if outcome is None:
                break
            self.redraws += 1
            if self.redraws >= cfg.max_redraws:
                raise ConfigError(f"ActiveLoc: {cfg.max_redraws} starts in a row locked (or spent budget_m) before "
                                  f"their first junction on map {m.scene!r}; raise budget_m or tracking.lock_mass, or "
                                  "use a more aliased map")
        return self._obs(), self._info()

    def step(self, action):
        if self.tracker is None:
            raise RuntimeError("call reset() first")
        if self._done:
            raise RuntimeError("the episode has ended; call reset()")
        a = _slot(action)
        mask = self.action_masks()
        self.invalid_action = not mask[a]
        if self.invalid_action:   # gymnasium's checkers sample the whole space: take the first allowed branch
            a = int(np.flatnonzero(mask)[0])
        self.decisions += 1
        before = self.distance
        self._enter(int(self.map.branches[self.leg, a]))
        outcome = self._drive()
        cfg = self.config
        reward = -cfg.distance_cost_per_100m * (self.distance - before) / 100.0
        terminated = truncated = False
        if outcome == "success":
            reward += cfg.success_reward
            terminated = True
        elif outcome == "wrong_lock":
            reward -= cfg.wrong_lock_penalty
            terminated = True
        elif outcome == "budget":
            truncated = True
        self.outcome = outcome
        self._done = terminated or truncated
        return self._obs(), float(reward), terminated, truncated, self._info()

    def action_masks(self) -> np.ndarray:
        """(3,) bool: the slots that exist at the junction the car is at (sb3-contrib's MaskablePPO reads it)."""
        return self.map.branches[self.leg] >= 0

    # --- driving --------------------------------------------------------------------------------------------
    def _begin(self, leg: int, start: int) -> None:
        if self._template.config != self.config.tracking:
            self._template = Tracker(self.map.candidates, self.config.tracking)
        self.tracker = copy.copy(self._template)
        self.tracker.reset()
        if self._user is not None:   # a new start: the localizer's reset(context), its queries numbered from 0
            self._user.reset(self._user_context())
            self._queries = 0
        self.leg, self.pos = leg, start
        q = int(self.map.leg_frames[leg][start])
        self.pose = self.map.frame_pose[q].copy()
        self.trajectory = [self.pose.copy()]
        self.distance = 0.0
        self.steps = 0
        self.decisions = 0
        self.outcome: str | None = None
        self.invalid_action = False
        self._done = False
        self._odo = np.zeros(3)        # odometry since the last fused frame
        self._since = 0
        self._fuse(q)

    def _enter(self, leg: int) -> None:
        self.leg, self.pos = leg, -1

    def _fuse(self, q: int) -> None:
        post = self.map.posterior(q) if self._user is None else self._user_posterior(q)
        if self.config.evidence != 1.0:
            post = post ** self.config.evidence
        if self.tracker.belief is not None:
            self.tracker.predict(self._odo)
        if post.sum() > 0:
            self.tracker.fuse(post)
        elif self.tracker.belief is None:   # the start frame has no posterior: a uniform belief
            self.tracker.fuse(np.full(len(post), 1.0 / len(post)))
        self._odo = np.zeros(3)
        self._since = 0

    # --- a localizer of one's own ------------------------------------------------------------------------------
    def _scene(self):
        from satloc_env.world.scene import load_scene

        key = (self.map.scene, self.map.satellite_gap)
        if getattr(self, "_scene_obj", None) is None or self._scene_obj[0] != key:
            self._scene_obj = (key, load_scene(self.map.scene, None, self.map.satellite_gap))
        return self._scene_obj[1]

    def _user_context(self):
        """The localizer's context: the map's scene's camera and satellite map, the episode's seed, no database and
        no prior (ActiveLoc's car does not know where it is)."""
        from satloc.geometry import StereoCamera
        from satloc.localizers.interface import Context

        scene = self._scene()
        camera = StereoCamera.preset(str((self.map.meta.get("config") or {}).get("resolution", "half")))
        if self._renderer is None or self._renderer.camera != camera or self._renderer.world is not scene.world:
            from satloc_env.render.stereo import StereoRenderer

            if self._renderer is not None:
                self._renderer.close()
            self._renderer = StereoRenderer(scene.world, camera)
        seed = int(self.np_random.bit_generator.seed_seq.spawn(1)[0].generate_state(1)[0]) \
            if hasattr(self.np_random.bit_generator, "seed_seq") else 0
        return Context(camera, scene.satmap, seed=seed, database=None, place=scene.name)

    def _user_posterior(self, q: int) -> np.ndarray:
        """Frame ``q`` rendered at its recorded pose, localized by the localizer with the odometry since the last
        fused frame and no prior, its answer spread over the map's candidates (see :class:`ActiveConfig`);
        zeros where it gives none."""
        from satloc.errors import ConfigError as _CE
        from satloc.localizers.interface import Query, as_estimate, localizer_name
        from satloc.sequence import Frame

        out = self._renderer.render(Pose2(*self.map.frame_pose[q]), False, False)
        frame = Frame(out["left"], out["right"], None, float(self._queries))
        odometry = Pose2(*self._odo) if self._queries > 0 else None
        query = Query(frame, odometry, None, self._queries, float(self._queries))
        self._queries += 1
        try:
            ans = as_estimate(self._user.localize(query), f"ActiveLoc localizer {localizer_name(self._user)!r}")
        except _CE:
            ans = None
        post = np.zeros(len(self.map.candidates))
        if ans is None:
            return post
        if ans.candidates is not None and len(ans.candidates):
            cand, prob = ans.candidates, ans.posterior
        else:
            cand, prob = ans.pose.as_array()[None], np.ones(1)
        keep = prob > 1e-6 * max(float(prob.max()), 1e-300)
        cfg, c = self.config, self.map.candidates
        sig = cfg.evidence_sigma_m
        for (x, y, yaw), w in zip(cand[keep], prob[keep]):
            near = np.asarray(self._tree.query_ball_point((x, y), 3.0 * sig), np.int64)
            if len(near) == 0:
                continue
            ok = np.abs(wrap_angle(c[near, 2] - yaw)) <= math.radians(cfg.evidence_yaw_deg)
            near = near[ok]
            d2 = (c[near, 0] - x) ** 2 + (c[near, 1] - y) ** 2
            post[near] += w * np.exp(-d2 / (2 * sig * sig))
        return post

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        from .drive import close_localizer

        close_localizer(self._user)

    def _drive(self) -> str | None:
        """Drive on along the current leg (and through junctions with one branch), fusing frames, until a
        decision is due (None) or the episode ends ("success", "wrong_lock", "budget")."""
        m, cfg = self.map, self.config
        end = self._check_lock()
        if end:
            return end
        while True:
            frames = m.leg_frames[self.leg]
            while self.pos + 1 < len(frames):
                self.pos += 1
                q = int(frames[self.pos])
                new = m.frame_pose[q]
                true = relative_motion(Pose2(*self.pose), Pose2(*new))
                d = math.hypot(true[0], true[1])
                z = self.np_random.normal(0.0, 1.0, 3)
                noisy = true + z * np.array([cfg.odometry_noise[0] * d, cfg.odometry_noise[0] * d, cfg.odometry_noise[1]])
                self._odo = compose_motion(self._odo, noisy)
                self.pose = new.copy()
                self.distance += d
                self.steps += 1
                self._since += 1
                self.trajectory.append(self.pose.copy())
                if self._since >= cfg.fuse_every:
                    self._fuse(q)
                    end = self._check_lock()
                    if end:
                        return end
                if self.distance >= cfg.budget_m:
                    return "budget"
            options = np.flatnonzero(m.branches[self.leg] >= 0)
            if len(options) == 1:
                self._enter(int(m.branches[self.leg, options[0]]))
                continue
            if len(options) == 0:
                raise ConfigError(f"{m.where}: leg {self.leg} ends at a dead end (ActiveLoc maps have none)")
            return None

    def _check_lock(self) -> str | None:
        t = self.tracker
        if t.belief is None or not t.locked():
            return None
        return "success" if self.error_m() <= self.config.success_m else "wrong_lock"

    # --- what the agent sees --------------------------------------------------------------------------------
    def estimate(self) -> np.ndarray:
        """The belief's most probable candidate pose (x, y, yaw)."""
        return self.map.candidates[int(np.argmax(self.tracker.belief))]

    def error_m(self) -> float:
        """Distance from the belief's most probable place to the car."""
        e = self.estimate()
        return float(math.hypot(e[0] - self.pose[0], e[1] - self.pose[1]))

    def places(self, k: int | None = None) -> list[tuple[int, float]]:
        """The ``k`` most probable places: (candidate index of a mode, probability within ``lock_m`` of it),
        modes taken greedily, each at least ``lock_m`` from the ones before."""
        k = self.config.top_k if k is None else k
        b = self.tracker.belief
        r = self.config.tracking.lock_m
        order = np.argsort(-b, kind="stable")
        order = order[b[order] >= 1e-4 * b[order[0]]]
        taken = np.zeros(len(b), bool)
        out = []
        c = self.map.candidates
        for i in order:
            if taken[i]:
                continue
            near = self._tree.query_ball_point(c[i, :2], r, return_sorted=False)
            near = np.asarray(near, np.int64)
            mass = float(b[near[~taken[near]]].sum())
            taken[near] = True
            out.append((int(i), mass * self.tracker.p_on))
            if len(out) >= k:
                break
        return out

    def outcome_signature(self, cand: int, slot: int) -> tuple:
        """What driving branch ``slot`` would show if the car were at candidate ``cand``: (), if that place's
        junction has no such branch, else the branch's length (10 m bins) and the branches its end offers."""
        m = self.map
        leg = int(m.cand_leg[cand])
        nxt = int(m.branches[leg, slot])
        if nxt < 0:
            return ()
        return (int(round(m.leg_length[nxt] / 10.0)), tuple(bool(x) for x in m.branches[nxt] >= 0))

    def _obs(self) -> np.ndarray:
        cfg, m, t = self.config, self.map, self.tracker
        b = t.belief
        est = self.estimate()
        v = [belief_entropy(b) / math.log(len(b)), t.locked_mass(), t.p_on, self.distance / cfg.budget_m]
        places = self.places()
        c, s = math.cos(est[2]), math.sin(est[2])
        for i in range(cfg.top_k):
            if i < len(places):
                p = m.candidates[places[i][0]]
                dx, dy = p[0] - est[0], p[1] - est[1]
                dyaw = wrap_angle(p[2] - est[2])
                v += [(c * dx + s * dy) / 100.0, (-s * dx + c * dy) / 100.0, math.cos(dyaw), math.sin(dyaw),
                      places[i][1]]
            else:
                v += [0.0, 0.0, 0.0, 0.0, 0.0]
        mass = np.array([p for _, p in places])
        mass = mass / mass.sum() if mass.sum() > 0 else mass
        for slot in range(K):
            nxt = int(m.branches[self.leg, slot])
            if nxt < 0:
                v += [0.0, 0.0, 0.0, 0.0]
                continue
            groups: dict[tuple, float] = {}
            for (ci, _), w in zip(places, mass):
                sig = self.outcome_signature(ci, slot)
                groups[sig] = groups.get(sig, 0.0) + float(w)
            g = np.array(list(groups.values()))
            sep = belief_entropy(g / g.sum()) / math.log(cfg.top_k) if cfg.top_k > 1 and g.sum() > 0 else 0.0
            v += [1.0, m.leg_length[nxt] / 100.0, m.turns[self.leg, slot] / math.pi, sep]
        return np.clip(np.asarray(v, np.float32), -5.0, 5.0)

    def _info(self) -> dict[str, Any]:
        t = self.tracker
        return {
            "action_mask": self.action_masks().astype(np.int8),
            "pose": self.pose.astype(np.float64).copy(),
            "estimate": self.estimate().astype(np.float64).copy(),
            "error_m": self.error_m(),
            "locked": bool(t.locked()),
            "success": self.outcome == "success",
            "wrong_lock": self.outcome == "wrong_lock",
            "distance_m": float(self.distance),
            "steps": int(self.steps),
            "decisions": int(self.decisions),
            "entropy": belief_entropy(t.belief),
            "p_on": float(t.p_on),
            "redraws": int(self.redraws),
            "invalid_action": bool(self.invalid_action),
            "route_action": self.route_action(),
        }

    def route_action(self) -> int:
        """The slot the scene's tour takes at this junction (-1 if the tour's next leg is the way back)."""
        nxt = int(self.map.next_in_tour[self.leg])
        hit = np.flatnonzero(self.map.branches[self.leg] == nxt)
        return int(hit[0]) if len(hit) else -1
