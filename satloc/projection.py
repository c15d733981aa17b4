"""Location-discriminative projections W_g, W_s (Chu et al., section on learning).

Both start at the identity. For each dictionary entry i, N(i) are its ``neighbors`` nearest entries in feature
space (ground and satellite features side by side) and k* the one nearest to i in location. For every view
v in {g, s} the hinge ranking loss

    sum_i sum_{k in N(i), k != k*} max(0, alpha * m(i, k) + D_v(i, k*) - D_v(i, k)),
    m(i, k) = dL(i, k) - dL(i, k*),   D_v(i, k) = || W_v (x_i - x_k) ||^2

asks that, after projection, entries nearer in location are nearer in feature space, by a margin that grows
with the location difference. Unless set, alpha is chosen per view so that margins and squared feature
distances have the same median at W = I (features of different kinds have very different scales). W_v is renormalised to its initial Frobenius norm after each Adam step, so the
loss cannot be lowered by merely scaling features up. Training stops when the epoch loss improves by less
than ``tol`` (relative) for ``patience`` epochs, or after ``max_epochs``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from .dictionary import Dictionary
from .errors import ConfigError, FormatError
from .nn import NNIndex
from .persist import FORMAT_VERSION, atomic_path

FORMAT = "projections"


@dataclass(frozen=True)
class ProjectionConfig:
    neighbors: int = 20             # |N(i)|
    alpha: float | None = None      # margin per metre of location difference (feature units^2 / m); None:
                                    # per view, median neighbour distance^2 at W = I over median margin
    max_margin_m: float = 20.0      # location differences are clipped here
    lr: float = 5e-3
    batch_size: int = 2048
    max_epochs: int = 40
    tol: float = 2e-3
    patience: int = 3
    max_anchors: int = 100_000      # anchors subsampled from the dictionary
    seed: int = 0


@dataclass
class Projections:
    W_g: np.ndarray
    W_s: np.ndarray
    loss_curve: list[float] = field(default_factory=list)
    converged: bool = False

    @staticmethod
    def identity(dg: int, ds: int) -> "Projections":
        return Projections(np.eye(dg, dtype=np.float32), np.eye(ds, dtype=np.float32))

    def project_g(self, g: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(g @ self.W_g.T, dtype=np.float32)

    def project_s(self, s: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(s @ self.W_s.T, dtype=np.float32)

    def save(self, path: str | Path) -> None:
        obj = {"format": FORMAT, "version": FORMAT_VERSION, "W_g": torch.from_numpy(self.W_g),
               "W_s": torch.from_numpy(self.W_s), "loss_curve": [float(v) for v in self.loss_curve],
               "converged": bool(self.converged)}
        with atomic_path(path, suffix=".pt") as tmp:
            torch.save(obj, tmp)

    @staticmethod
    def load(path: str | Path) -> "Projections":
        path = Path(path)
        if not path.is_file():
            raise FormatError(f"{path}: file not found")
        try:
            obj = torch.load(path, weights_only=True, map_location="cpu")
        except Exception as e:  # torch raises several types for damaged or non-torch files
            raise FormatError(f"{path}: damaged or not a torch file ({type(e).__name__}: {e})") from e
        if not isinstance(obj, dict) or obj.get("format") != FORMAT:
            raise FormatError(f"{path}: not a satloc '{FORMAT}' file")
        if obj.get("version") != FORMAT_VERSION:
            raise FormatError(f"{path}: '{FORMAT}' file of version {obj.get('version')!r}; this satloc reads "
                              f"version {FORMAT_VERSION}")
        return Projections(obj["W_g"].numpy(), obj["W_s"].numpy(), list(obj.get("loss_curve", [])),
                           bool(obj.get("converged", False)))


def ranking_triplets(d: Dictionary, cfg: ProjectionConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Anchors i, their location-nearest neighbour k*, the other neighbours k (A, K-1) and margins (A, K-1)."""
    rng = np.random.default_rng(cfg.seed)
    n = len(d)
    if n < cfg.neighbors + 1:
        raise ConfigError(f"dictionary has {n} entries; projection learning needs more than {cfg.neighbors}")
    joint = np.concatenate([d.g, d.s], axis=1)
    anchors = rng.choice(n, size=min(cfg.max_anchors, n), replace=False)
    _, ids = NNIndex(joint).search(joint[anchors], cfg.neighbors + 1)
    ids = ids[:, 1:]                                                   # drop the anchor itself
    dl = np.linalg.norm(d.loc[ids] - d.loc[anchors][:, None], axis=2)
    dl = np.minimum(dl, cfg.max_margin_m)
    best = np.argmin(dl, axis=1)
    rows = np.arange(len(anchors))
    kstar = ids[rows, best]
    mask = np.ones_like(ids, dtype=bool)
    mask[rows, best] = False
    others = ids[mask].reshape(len(anchors), -1)
    margins = (dl[mask].reshape(len(anchors), -1) - dl[rows, best][:, None]).astype(np.float32)
    return anchors, kstar, others, margins


def ranking_loss(W: torch.Tensor, x: torch.Tensor, i: torch.Tensor, kstar: torch.Tensor, others: torch.Tensor,
                 margins: torch.Tensor, alpha: float) -> torch.Tensor:
    xi = x[i]
    d_star = ((xi - x[kstar]) @ W.T).pow(2).sum(-1)                     # (B,)
    d_other = ((xi[:, None] - x[others]) @ W.T).pow(2).sum(-1)          # (B, K-1)
    return torch.relu(alpha * margins + d_star[:, None] - d_other).mean()


def auto_alpha(x: torch.Tensor, anchors: torch.Tensor, others: torch.Tensor, margins: torch.Tensor) -> float:
    """alpha making the median margin equal the median squared neighbour distance at W = I."""
    d = (x[anchors][:, None] - x[others]).pow(2).sum(-1)
    m = float(margins[margins > 0].median()) if bool((margins > 0).any()) else 1.0
    return max(float(d.median()), 1e-12) / max(m, 1e-12)


def train_projections(d: Dictionary, cfg: ProjectionConfig = ProjectionConfig(), progress: bool = True) -> Projections:
    """Learn W_g and W_s on dictionary ``d`` (see the module docstring)."""
    torch.manual_seed(cfg.seed)
    anchors, kstar, others, margins = ranking_triplets(d, cfg)
    views = {"g": torch.from_numpy(np.ascontiguousarray(d.g)), "s": torch.from_numpy(np.ascontiguousarray(d.s))}
    W = {v: torch.eye(x.shape[1], requires_grad=True) for v, x in views.items()}
    norms = {v: float(torch.linalg.norm(w.detach())) for v, w in W.items()}
    opt = torch.optim.Adam(list(W.values()), lr=cfg.lr)
    t_anchor, t_star = torch.from_numpy(anchors), torch.from_numpy(kstar)
    t_others, t_marg = torch.from_numpy(others), torch.from_numpy(margins)
    gen = torch.Generator().manual_seed(cfg.seed)
    alpha = {v: cfg.alpha if cfg.alpha is not None else auto_alpha(x, t_anchor, t_others, t_marg) for v, x in views.items()}
    curve: list[float] = []
    stale, converged = 0, False
    bar = tqdm(range(cfg.max_epochs), desc="projections", unit="epoch", disable=not progress, leave=False)
    for _ in bar:
        perm = torch.randperm(len(anchors), generator=gen)
        total, count = 0.0, 0
        for b in range(0, len(perm), cfg.batch_size):
            sel = perm[b:b + cfg.batch_size]
            loss = sum(ranking_loss(W[v], views[v], t_anchor[sel], t_star[sel], t_others[sel], t_marg[sel], alpha[v])
                       for v in views)
            opt.zero_grad()
            loss.backward()
            opt.step()
            with torch.no_grad():
                for v, w in W.items():
                    w.mul_(norms[v] / torch.linalg.norm(w))
            total += float(loss.detach()) * len(sel)
            count += len(sel)
        curve.append(total / count)
        bar.set_postfix(loss=f"{curve[-1]:.4f}")
        if len(curve) > 1 and (curve[-2] - curve[-1]) < cfg.tol * max(abs(curve[-2]), 1e-12):
            stale += 1
            if stale >= cfg.patience:
                converged = True
                break
        else:
            stale = 0
    return Projections(W["g"].detach().numpy().copy(), W["s"].detach().numpy().copy(), curve, converged)


def evaluate_loss(d: Dictionary, p: Projections, cfg: ProjectionConfig = ProjectionConfig()) -> float:
    """The ranking loss of projections ``p`` on dictionary ``d`` (both views, all sampled anchors)."""
    anchors, kstar, others, margins = (torch.from_numpy(a) for a in ranking_triplets(d, cfg))
    total = 0.0
    with torch.no_grad():
        for W, x in ((p.W_g, d.g), (p.W_s, d.s)):
            xt = torch.from_numpy(np.ascontiguousarray(x))
            alpha = cfg.alpha if cfg.alpha is not None else auto_alpha(xt, anchors, others, margins)
            total += float(ranking_loss(torch.from_numpy(W), xt, anchors, kstar, others, margins, alpha))
    return total


def plot_loss(curve: list[float], path: str | Path) -> None:
    """PNG of the loss curve."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.2), dpi=110)
    ax.plot(np.arange(1, len(curve) + 1), curve, marker="o", ms=3)
    ax.set_xlabel("epoch")
    ax.set_ylabel("ranking loss")
    ax.set_title("projection learning")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
