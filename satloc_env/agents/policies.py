"""Agents for ``satloc/ActiveLoc-v0`` (:mod:`satloc_env.active`), their training and their evaluation.

* :class:`RandomAgent`: uniform over the branches the junction offers.
* :class:`RouteAgent`: the autopilot's fixed route: the scene's tour from wherever the car is.
* :class:`EntropyAgent`: greedy expected entropy, active Markov localization's rule (Burgard, Fox and Thrun):
  for each branch, predict the belief after driving it to the next junction under each of the most probable
  places (the tracker moved by that place's odometry and fused with the localizer's posteriors of the frames
  on that place's path, from the active map) and take the branch with the lowest expected entropy.
* :class:`LearnedAgent`: a small MLP over the observation (64-64, tanh), trained with sb3-contrib's
  ``MaskablePPO`` (:func:`train_agent`, ``examples/train_agent.py``); the shipped weights are
  ``satloc_env/weights/active_policy.pt`` (torch, ``weights_only``); inference needs only torch.

:func:`evaluate_agents` runs them on the same seeded starts (``satloc agent evaluate``).
"""
from __future__ import annotations

import copy
import csv
import json
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from satloc.config import from_dict, to_dict
from satloc.errors import ConfigError, FormatError
from satloc.geometry import Pose2
from satloc.metrics import bootstrap_ci
from satloc.persist import atomic_path, write_json
from satloc.track import relative_motion

from .active import ActiveLocEnv, K, belief_entropy, obs_fields

__all__ = ["RandomAgent", "RouteAgent", "EntropyAgent", "LearnedAgent", "make_agent", "AGENTS", "POLICY_PATH",
           "run_episode", "evaluate_agents", "train_agent", "plot_episode", "CSV_COLUMNS"]

POLICY_PATH = Path(__file__).resolve().parent / "weights" / "active_policy.pt"
AGENTS = ("random", "route", "entropy", "learned")
CSV_COLUMNS = ["agent", "success_rate", "wrong_lock_rate", "median_distance_m", "mean_distance_m", "final_error_m",
               "ci95_low", "ci95_high"]


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


# --- running and evaluating -------------------------------------------------------------------------------
def run_episode(env: ActiveLocEnv, agent, seed: int, record: bool = False) -> dict[str, Any]:
    """One episode from ``reset(seed=seed)``; returns its outcome (and, with ``record``, the belief's top
    candidates and the car's path at each decision, for :func:`plot_episode`)."""
    obs, info = env.reset(seed=seed)
    agent.reset(seed)
    frames = []
    t_act = 0.0
    decisions = 0
    term = trunc = False
    while True:
        if record:
            frames.append(_snapshot(env, info))
        if term or trunc:
            break
        t = time.perf_counter()
        a = agent.act(env, obs, info)
        t_act += time.perf_counter() - t
        obs, _, term, trunc, info = env.step(a)
        decisions += 1
    out = {"seed": seed, "outcome": env.outcome, "success": bool(info["success"]),
           "wrong_lock": bool(info["wrong_lock"]), "truncated": bool(trunc), "distance_m": info["distance_m"],
           "final_error_m": info["error_m"], "decisions": decisions, "act_s": t_act, "redraws": info["redraws"]}
    if record:
        out["frames"] = frames
    return out


def _snapshot(env: ActiveLocEnv, info: dict) -> dict:
    b = env.tracker.belief
    top = np.argsort(-b)[:400]
    return {"cands": env.map.candidates[top].copy(), "p": b[top].copy(), "pose": env.pose.copy(),
            "estimate": env.estimate().copy(), "path": np.array(env.trajectory), "entropy": belief_entropy(b),
            "leg": env.leg}


def summarize(agent: str, eps: list[dict]) -> dict[str, Any]:
    """The table row of one agent's episodes (rates in percent; distances over the successful episodes; the
    95 % interval is a bootstrap of the success rate)."""
    succ = np.array([e["success"] for e in eps], float)
    dist = np.array([e["distance_m"] for e in eps if e["success"]])
    lo, hi = bootstrap_ci(100.0 * succ)
    return {"agent": agent, "success_rate": round(100.0 * succ.mean(), 1),
            "wrong_lock_rate": round(100.0 * np.mean([e["wrong_lock"] for e in eps]), 1),
            "median_distance_m": round(float(np.median(dist)), 1) if len(dist) else float("nan"),
            "mean_distance_m": round(float(dist.mean()), 1) if len(dist) else float("nan"),
            "final_error_m": round(float(np.mean([e["final_error_m"] for e in eps])), 1),
            "ci95_low": round(lo, 1), "ci95_high": round(hi, 1)}


@dataclass(frozen=True)
class EvalConfig:
    agents: tuple[str, ...] = AGENTS
    maps: tuple[str, ...] = ("active_suburb", "active_grid")   # the held-out scene; the training scene's held-out seeds
    episodes: int = 100
    seed: int = 10_000          # episode i starts from reset(seed=seed + i): seeds no training run uses
    policy: str | None = None   # the learned agent's weights (default: the shipped ones)
    env: dict = field(default_factory=dict)   # ActiveConfig overrides


def _write_csv(path: Path, rows: list[dict], columns: list[str]) -> None:
    with atomic_path(path, suffix=".csv") as tmp:
        with open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=columns)
            w.writeheader()
            for r in rows:
                w.writerow({c: r.get(c) for c in columns})


def markdown_rows(rows: list[dict], columns: list[str]) -> str:
    head = "| " + " | ".join(columns) + " |\n|" + "---|" * len(columns) + "\n"
    return head + "".join("| " + " | ".join(str(r[c]) for c in columns) + " |\n" for r in rows)


def evaluate_agents(config: EvalConfig | dict | None = None, out: str | Path = "agents_eval", progress: bool = True,
                    log=print) -> list[dict]:
    """Every agent on the same starts of every map; writes ``out/agents.csv`` (one row per agent, all maps
    pooled), ``out/agents_by_map.csv``, ``out/episodes.csv``, ``out/summary.json`` and a picture of one episode
    of the first agent that is not random (``out/episode.png``); with the learned agent, its training curve
    (``out/learning_curve.png``, from the ``learning_curve.csv`` or ``<policy>_curve.csv`` beside its weights).
    Returns the pooled rows."""
    from tqdm import tqdm

    cfg = config if isinstance(config, EvalConfig) else from_dict(EvalConfig, dict(config or {}), "agent evaluate")
    if cfg.episodes < 1:
        raise ConfigError(f"agent evaluate: episodes must be >= 1, got {cfg.episodes}")
    if not cfg.agents or not cfg.maps:
        raise ConfigError(f"agent evaluate: need at least one agent and one map, got agents={list(cfg.agents)}, "
                          f"maps={list(cfg.maps)}")
    for a in cfg.agents:
        if a not in AGENTS:
            raise ConfigError(f"agent evaluate: unknown agent {a!r}; expected some of {', '.join(AGENTS)}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    per_agent: dict[str, list[dict]] = {a: [] for a in cfg.agents}
    by_map, episodes, timing = [], [], {}
    for mp in cfg.maps:
        env = ActiveLocEnv(dict(cfg.env, map=mp))
        for name in cfg.agents:
            agent = make_agent(name, policy=cfg.policy)
            eps = []
            t0 = time.perf_counter()
            for i in tqdm(range(cfg.episodes), desc=f"{mp} {name}", unit="episode", disable=not progress, leave=False):
                e = run_episode(env, agent, cfg.seed + i)
                e.update(agent=name, map=env.map.scene)
                eps.append(e)
            wall = time.perf_counter() - t0
            dec = sum(e["decisions"] for e in eps)
            timing[f"{env.map.scene}/{name}"] = {"wall_s": round(wall, 1), "decisions": dec,
                                                 "decisions_per_s": round(dec / wall, 1) if wall > 0 else None}
            per_agent[name] += eps
            episodes += eps
            row = dict(summarize(name, eps), map=env.map.scene)
            by_map.append(row)
            log(f"[{env.map.scene}] {name:8s} success {row['success_rate']:5.1f} % "
                f"[{row['ci95_low']:.1f}, {row['ci95_high']:.1f}], wrong lock {row['wrong_lock_rate']:4.1f} %, "
                f"median distance {row['median_distance_m']} m ({wall:.0f} s, {dec / max(wall, 1e-9):.1f} decisions/s)")
    rows = [summarize(a, per_agent[a]) for a in cfg.agents]
    _write_csv(out / "agents.csv", rows, CSV_COLUMNS)
    _write_csv(out / "agents_by_map.csv", by_map, ["map"] + CSV_COLUMNS)
    _write_csv(out / "episodes.csv", episodes, ["map", "agent", "seed", "outcome", "success", "wrong_lock",
                                                "truncated", "distance_m", "final_error_m", "decisions", "redraws",
                                                "act_s"])
    write_json(out / "summary.json", {"config": to_dict(cfg), "agents": rows, "by_map": by_map, "timing": timing})
    log("\n" + markdown_rows(rows, CSV_COLUMNS))
    if "learned" in cfg.agents:   # the learned agent's training curve, from beside its weights
        pol = Path(cfg.policy) if cfg.policy else POLICY_PATH
        for c in (pol.parent / "learning_curve.csv", pol.with_name(pol.stem + "_curve.csv")):
            if c.is_file():
                with open(c, newline="") as f:
                    curve = [{k: float(v) for k, v in r.items()} for r in csv.DictReader(f)]
                _plot_curve(curve, out / "learning_curve.png", window=100)
                break
        else:
            log(f"no learning curve beside {pol} (learning_curve.csv or {pol.stem}_curve.csv)")
    pick = next((a for a in cfg.agents if a != "random"), cfg.agents[0])
    env = ActiveLocEnv(dict(cfg.env, map=cfg.maps[0]))
    ep = run_episode(env, make_agent(pick, policy=cfg.policy), cfg.seed, record=True)
    plot_episode(env, ep, out / "episode.png", title=f"{env.map.scene}, {pick} agent, seed {cfg.seed}")
    return rows


# --- pictures -------------------------------------------------------------------------------------------
def plot_episode(env: ActiveLocEnv, episode: dict, path: str | Path, title: str = "") -> None:
    """One panel per decision (and the end): the belief over the scene's satellite image (its 400 most
    probable candidates), the car (circle), the belief's mode (cross) and the path driven so far."""
    from satloc.plots import _pyplot

    from .scene import load_scene

    plt = _pyplot()
    sat = load_scene(env.map.scene).satmap
    frames = episode["frames"]
    n = len(frames)
    cols = min(n, 4)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.6 * rows), squeeze=False)
    h, w = sat.image.shape[:2]
    x0, y0 = sat.origin
    ext = (x0, x0 + w * sat.meters_per_pixel, y0 - h * sat.meters_per_pixel, y0)
    for k, ax in enumerate(axes.ravel()):
        ax.axis("off")
        if k >= n:
            continue
        f = frames[k]
        ax.imshow(sat.image, extent=ext, interpolation="bilinear")
        rel = f["p"] / max(f["p"].max(), 1e-300)
        o = np.argsort(rel)
        ax.scatter(f["cands"][o, 0], f["cands"][o, 1], c=np.log10(np.maximum(rel[o], 1e-3)), cmap="inferno",
                   vmin=-3, vmax=0, s=5, linewidths=0)
        ax.plot(f["path"][:, 0], f["path"][:, 1], "-", color="deepskyblue", lw=1.5)
        ax.plot([f["pose"][0]], [f["pose"][1]], "o", mfc="none", mec="lime", ms=9, mew=2)
        ax.plot([f["estimate"][0]], [f["estimate"][1]], "x", color="cyan", ms=9, mew=2)
        label = "start" if k == 0 else (f"decision {k}" if k < n - 1 or not episode.get("outcome") else
                                         f"end: {episode['outcome']}")
        ax.set_title(f"{label}, H = {f['entropy']:.1f} nats", fontsize=9)
    fig.suptitle((title + "\n" if title else "") + f"{episode['outcome']} after {episode['distance_m']:.0f} m; "
                 "belief (log, 3 decades), car (circle), mode (cross), path (blue)", fontsize=10)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)


# --- training ---------------------------------------------------------------------------------------------
def train_agent(out: str | Path, timesteps: int = 20_000, seed: int = 0, map: str = "active_grid", n_envs: int = 4,
                hidden: Sequence[int] = (64, 64), env: dict | None = None, n_steps: int = 256,
                progress: bool = True, log=print) -> Path:
    """Train the learned agent with sb3-contrib's MaskablePPO on ``map`` (training starts: the environments'
    own seeded streams ``seed`` .. ``seed + n_envs - 1``, never the evaluation's ``reset(seed=10000 + i)``);
    writes ``out/active_policy.pt`` (the policy MLP, loadable by :class:`LearnedAgent`), ``out/learning_curve.csv``
    and ``.png`` (per finished training episode: timesteps, success, wrong_lock, distance_m) and ``out/train.json``.
    Needs the ``rl`` extra (``pip install -e '.[rl]'``)."""
    try:
        from sb3_contrib import MaskablePPO
        from stable_baselines3.common.callbacks import BaseCallback
        from stable_baselines3.common.vec_env import DummyVecEnv
    except ImportError as e:
        raise ConfigError("training the learned agent needs stable-baselines3 and sb3-contrib: "
                          "pip install -e '.[rl]'") from e
    import torch

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    kw = dict(env or {}, map=map)
    venv = DummyVecEnv([lambda: ActiveLocEnv(dict(kw)) for _ in range(n_envs)])
    venv.seed(seed)
    curve: list[dict] = []

    class Curve(BaseCallback):
        def _on_step(self) -> bool:
            for info, done in zip(self.locals["infos"], self.locals["dones"]):
                if done:
                    curve.append({"timesteps": self.num_timesteps, "success": int(info["success"]),
                                  "wrong_lock": int(info["wrong_lock"]), "distance_m": round(info["distance_m"], 1)})
            return True

    model = MaskablePPO("MlpPolicy", venv, n_steps=n_steps, batch_size=min(64, n_steps * n_envs), n_epochs=10, gamma=0.99, learning_rate=3e-4,
                        ent_coef=0.01, seed=seed, policy_kwargs=dict(net_arch=list(hidden)), verbose=0, device="cpu")
    t0 = time.perf_counter()
    model.learn(total_timesteps=timesteps, callback=Curve(), progress_bar=False)
    wall = time.perf_counter() - t0
    # the deterministic policy: the actor MLP and its action head
    pol = model.policy
    net = _mlp(venv.observation_space.shape[0], list(hidden), K)
    linears = [m for m in pol.mlp_extractor.policy_net if isinstance(m, torch.nn.Linear)] + [pol.action_net]
    mine = [m for m in net if isinstance(m, torch.nn.Linear)]
    for a, b in zip(mine, linears):
        a.weight.data.copy_(b.weight.data)
        a.bias.data.copy_(b.bias.data)
    top_k = venv.envs[0].config.top_k
    meta = {"format": "satloc-active-policy", "obs_dim": int(venv.observation_space.shape[0]), "hidden": list(hidden),
            "top_k": top_k, "obs_fields": obs_fields(top_k), "map": map, "timesteps": timesteps, "seed": seed,
            "n_envs": n_envs, "n_steps": n_steps, "env": kw, "algorithm": "sb3-contrib MaskablePPO",
            "train_wall_s": round(wall, 1)}
    path = out / "active_policy.pt"
    with atomic_path(path, suffix=".pt") as tmp:
        torch.save({"meta": json.dumps(meta), "state": net.state_dict()}, tmp)
    _write_csv(out / "learning_curve.csv", curve, ["timesteps", "success", "wrong_lock", "distance_m"])
    _plot_curve(curve, out / "learning_curve.png", window=100)
    write_json(out / "train.json", dict(meta, episodes=len(curve), decisions_per_s=round(timesteps / wall, 1)))
    log(f"trained {timesteps} decisions in {wall:.0f} s ({timesteps / wall:.1f} decisions/s), {len(curve)} episodes; "
        f"policy {path}")
    venv.close()
    return path


def _plot_curve(curve: list[dict], path: Path, window: int = 100) -> None:
    from satloc.plots import _pyplot

    plt = _pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    if curve:
        t = np.array([c["timesteps"] for c in curve])
        for i, (key, lab) in enumerate((("success", "success rate (%)"), ("distance_m", "distance driven (m)"))):
            v = np.array([c[key] for c in curve], float) * (100.0 if key == "success" else 1.0)
            k = min(window, len(v))
            smooth = np.convolve(v, np.ones(k) / k, mode="valid")
            ax[i].plot(t[k - 1:], smooth)
            ax[i].set_xlabel("decisions (timesteps)")
            ax[i].set_ylabel(f"{lab}, mean of {k} episodes")
    fig.suptitle("MaskablePPO on ActiveLoc-v0: training episodes")
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
