"""Training the learned ActiveLoc agent with sb3-contrib's MaskablePPO (``satloc agent train``; needs the
``rl`` extra)."""
from __future__ import annotations

import json
import time
from collections.abc import Sequence
from pathlib import Path

from satloc.errors import ConfigError
from satloc.persist import atomic_path, write_json
from satloc_env.envs.active import ActiveLocEnv, K, obs_fields

from .evaluate import _write_csv, plot_learning_curve
from .policies import _mlp

__all__ = ["train_agent"]


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
    plot_learning_curve(curve, out / "learning_curve.png", window=100)
    write_json(out / "train.json", dict(meta, episodes=len(curve), decisions_per_s=round(timesteps / wall, 1)))
    log(f"trained {timesteps} decisions in {wall:.0f} s ({timesteps / wall:.1f} decisions/s), {len(curve)} episodes; "
        f"policy {path}")
    venv.close()
    return path
