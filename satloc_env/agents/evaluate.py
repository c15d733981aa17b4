"""Evaluating ActiveLoc agents: episodes from the same seeded starts, the table, and pictures of an episode
and of a training curve (``satloc agent evaluate``)."""
from __future__ import annotations

import csv
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from satloc.config import from_dict, to_dict
from satloc.errors import ConfigError
from satloc.evaluation.metrics import bootstrap_ci
from satloc.persist import atomic_path, write_json
from satloc_env.envs.active import ActiveLocEnv, belief_entropy

from .policies import AGENTS, POLICY_PATH, make_agent

__all__ = ["run_episode", "summarize", "EvalConfig", "evaluate_agents", "plot_episode", "plot_learning_curve",
           "markdown_rows", "CSV_COLUMNS"]

CSV_COLUMNS = ["agent", "success_rate", "wrong_lock_rate", "median_distance_m", "mean_distance_m", "final_error_m",
               "ci95_low", "ci95_high"]


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
                plot_learning_curve(curve, out / "learning_curve.png", window=100)
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
    from satloc.evaluation.plots import _pyplot
    from satloc_env.world.scene import load_scene

    plt = _pyplot()
    sat = load_scene(env.map.scene, satellite_gap=env.map.satellite_gap).satmap   # the map it was made on
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




def plot_learning_curve(curve: list[dict], path: Path, window: int = 100) -> None:
    from satloc.evaluation.plots import _pyplot

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
