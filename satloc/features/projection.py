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

Model selection. The loss only ranks the 20 neighbours each anchor had at W = I; pushed far, W reorders the
whole space and the neighbour sets the localizer intersects stop agreeing between the two views (measured on
the city route: ground and satellite neighbour precision both rise, yet the co-occurrence count at the true
pose falls from 0.98 to 0.87 per sample). So a share ``val_frac`` of the database, in blocks of ``val_block``
frames spread along the route, is held out, and after every epoch the *co-occurrence margin* is measured on
it: for held-out samples, the mean size of NN_M(W_g g) ∩ NN_M(W_s s) among the training entries at the
sample's own satellite feature, minus the same at the satellite feature of a held-out sample more than
``val_far_m`` away. The W of the best epoch is kept, the identity (epoch 0) included (an epoch counts as
better only if its per-sample gain over the best so far is ``val_z`` standard errors above zero), and training stops after ``patience`` epochs without improvement.

Device. The optimisation runs on ``device`` (:mod:`satloc.device`: ``"auto"`` is CUDA when it is available,
else the CPU); the anchors and the order of the batches are drawn on the CPU wherever it runs, the held-out
neighbour search runs on the CPU, and the learned W come back as CPU arrays (saved as CPU tensors).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from ..device import check_device, device_field, resolve_device
from ..errors import ConfigError, FormatError
from ..persist import FORMAT_VERSION, atomic_path, check_header, check_zip
from .dictionary import Dictionary
from .nn import NNIndex

FORMAT = "projections"
MAX_NORM = 1e12  # of a loaded W (trained ones have sqrt(D)): projected float32 distances stay finite


def load_torch_dict(path: Path, fmt: str) -> dict:
    """The dict a satloc torch file of format ``fmt`` holds (loaded with ``weights_only=True`` on the CPU);
    FormatError naming the file when it is missing, damaged, not a torch file or of another format or version."""
    if not path.is_file():
        raise FormatError(f"{path}: file not found")
    check_zip(path)  # torch.load does not check the CRCs: a flipped bit would load as another weight
    try:
        obj = torch.load(path, weights_only=True, map_location="cpu")
    except Exception as e:  # torch raises several types for damaged or non-torch files
        raise FormatError(f"{path}: damaged or not a torch file ({type(e).__name__}: {str(e)[:200]})") from e
    if not isinstance(obj, dict) or obj.get("format") != fmt:
        raise FormatError(f"{path}: not a satloc '{fmt}' file")
    check_header(obj, fmt, path)
    return obj


@dataclass(frozen=True)
class ProjectionConfig:
    neighbors: int = 20             # |N(i)|
    alpha: float | None = None      # margin per metre of location difference (feature units^2 / m); None:
                                    # per view, median neighbour distance^2 at W = I over median margin
    max_margin_m: float = 20.0      # location differences are clipped here
    lr: float = 1e-3
    batch_size: int = 2048
    max_epochs: int = 20
    tol: float = 2e-3
    patience: int = 3
    max_anchors: int = 100_000      # anchors subsampled from the dictionary
    seed: int = 0
    val_frac: float = 0.1           # share of the database held out to select the epoch (0: keep the last epoch)
    val_block: int = 5              # held out in blocks of this many consecutive frames
    val_samples: int = 3000         # held-out samples measured per epoch
    val_neighbors: int = 20         # M of the co-occurrence margin
    val_far_m: float = 20.0         # the "wrong place" sample lies at least this far away
    val_z: float = 2.0              # an epoch is better only if it raises the margin by this many standard errors
    device: str = device_field()    # where the optimisation runs (satloc.device): auto, cpu, cuda, cuda:N

    def __post_init__(self):
        check_device(self.device)
        if not 0.0 <= self.val_frac < 1.0:
            raise ConfigError(f"val_frac: expected in [0, 1), got {self.val_frac}")
        if self.neighbors < 2 or self.lr <= 0 or self.max_epochs < 1 or self.batch_size < 1:
            raise ConfigError("neighbors >= 2, lr > 0, max_epochs >= 1 and batch_size >= 1 are required")


@dataclass
class Projections:
    W_g: np.ndarray
    W_s: np.ndarray
    loss_curve: list[float] = field(default_factory=list)
    converged: bool = False
    val_curve: list[float] = field(default_factory=list)   # co-occurrence margin, epoch 0 (identity) first
    best_epoch: int = -1                                    # the epoch kept (0: identity); -1: last, no validation

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
               "converged": bool(self.converged), "val_curve": [float(v) for v in self.val_curve],
               "best_epoch": int(self.best_epoch)}
        with atomic_path(path, suffix=".pt") as tmp:
            torch.save(obj, tmp)

    @staticmethod
    def load(path: str | Path) -> "Projections":
        path = Path(path)
        obj = load_torch_dict(path, FORMAT)
        w = {}
        for k in ("W_g", "W_s"):
            t = obj.get(k)
            if not isinstance(t, torch.Tensor) or t.dtype not in (torch.float32, torch.float64) or t.dim() != 2 \
                    or t.shape[0] != t.shape[1] or t.shape[0] < 1:
                got = f"{t.dtype} {tuple(t.shape)}" if isinstance(t, torch.Tensor) else type(t).__name__
                raise FormatError(f"{path}: '{k}': expected a square float32 (or float64) matrix, got {got}")
            if not bool(torch.isfinite(t).all()):
                raise FormatError(f"{path}: '{k}': non-finite values")
            # training keeps ||W||_F at its initial sqrt(D); far beyond, float32 feature distances overflow
            if float(torch.linalg.norm(t.double())) > MAX_NORM:
                raise FormatError(f"{path}: '{k}': Frobenius norm {float(torch.linalg.norm(t.double())):.3g} above "
                                  f"{MAX_NORM:g} (feature distances would overflow)")
            w[k] = t.numpy().astype(np.float32)
        curves = {}
        for k in ("loss_curve", "val_curve"):
            v = obj.get(k, [])
            if not isinstance(v, list) or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                  and math.isfinite(x) for x in v):
                raise FormatError(f"{path}: '{k}': expected a list of finite numbers, got {str(v)[:60]}")
            curves[k] = [float(x) for x in v]
        converged, best = obj.get("converged", False), obj.get("best_epoch", -1)
        if not isinstance(converged, bool) or isinstance(best, bool) or not isinstance(best, int) or best < -1:
            raise FormatError(f"{path}: 'converged' must be true/false and 'best_epoch' an integer >= -1, got "
                              f"{converged!r}, {best!r}")
        return Projections(w["W_g"], w["W_s"], curves["loss_curve"], converged, curves["val_curve"], best)


def validation_split(d: Dictionary, cfg: ProjectionConfig) -> tuple[np.ndarray, np.ndarray]:
    """Training and held-out entry ids: held-out entries come from every ``1/val_frac``-th block of
    ``val_block`` database frames (spread along the route); a dictionary from one frame block is split by
    entry instead. ``val_frac = 0`` holds nothing out."""
    n = len(d)
    if cfg.val_frac <= 0:
        return np.arange(n), np.zeros(0, np.int64)
    block = d.frame.astype(np.int64) // max(1, cfg.val_block)
    blocks = np.unique(block)
    step = max(2, int(round(1.0 / cfg.val_frac)))
    if len(blocks) >= 2 * step:
        held = np.isin(block, blocks[step // 2::step])
    else:
        held = np.random.default_rng(cfg.seed).random(n) < cfg.val_frac
    return np.flatnonzero(~held), np.flatnonzero(held)


def ranking_triplets(d: Dictionary, cfg: ProjectionConfig, pool: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Anchors i, their location-nearest neighbour k*, the other neighbours k (A, K-1) and margins (A, K-1);
    anchors and neighbours are drawn from the entry ids ``pool`` (default: all)."""
    rng = np.random.default_rng(cfg.seed)
    pool = np.arange(len(d)) if pool is None else pool
    n = len(pool)
    if n < cfg.neighbors + 1:
        raise ConfigError(f"dictionary has {n} usable entries; projection learning needs more than {cfg.neighbors}")
    joint = np.concatenate([d.g[pool], d.s[pool]], axis=1)
    local = rng.choice(n, size=min(cfg.max_anchors, n), replace=False)
    _, ids = NNIndex(joint).search(joint[local], cfg.neighbors + 1)
    ids = pool[ids[:, 1:]]                                             # drop the anchor itself
    anchors = pool[local]
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


class CooccurrenceMargin:
    """The validation measure of the module docstring, for held-out entries ``held`` against ``train``."""

    def __init__(self, d: Dictionary, train: np.ndarray, held: np.ndarray, cfg: ProjectionConfig):
        rng = np.random.default_rng(cfg.seed + 1)
        v = np.sort(rng.choice(held, size=min(cfg.val_samples, len(held)), replace=False))
        # a "wrong place" partner for each sample: another held-out sample at least val_far_m away
        far = np.zeros(len(v), np.int64)
        for t in range(len(v)):
            cand = np.flatnonzero(np.linalg.norm(d.loc[v] - d.loc[v[t]], axis=1) >= cfg.val_far_m)
            far[t] = v[rng.choice(cand)] if len(cand) else -1
        keep = far >= 0
        self.g, self.s, self.s_far = d.g[v[keep]], d.s[v[keep]], d.s[far[keep]]
        self.base_g, self.base_s = d.g[train], d.s[train]
        self.m = cfg.val_neighbors
        self.usable = bool(keep.any()) and len(train) > self.m

    @staticmethod
    def _overlap(a: np.ndarray, b: np.ndarray) -> torch.Tensor:
        return torch.from_numpy((a[:, :, None] == b[:, None, :]).any(-1).sum(1).astype(np.float32))

    @staticmethod
    def better(new: torch.Tensor, best: torch.Tensor, z: float) -> bool:
        """Whether per-sample margins ``new`` beat ``best`` by ``z`` standard errors of the paired gain."""
        gain = new - best
        return bool(gain.mean() > z * gain.std() / math.sqrt(len(gain)) and gain.mean() > 0)

    def __call__(self, W_g: torch.Tensor, W_s: torch.Tensor) -> torch.Tensor:
        """Per-sample co-occurrence margins (exact neighbour search)."""
        p = Projections(W_g.detach().cpu().numpy(), W_s.detach().cpu().numpy())
        _, gid = NNIndex(p.project_g(self.base_g), exact_max=len(self.base_g)).search(p.project_g(self.g), self.m)
        # both satellite query sets in one batch
        _, sid = NNIndex(p.project_s(self.base_s), exact_max=len(self.base_s)).search(
            p.project_s(np.concatenate([self.s, self.s_far])), self.m)
        n = len(self.g)
        return self._overlap(gid, sid[:n]) - self._overlap(gid, sid[n:])


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
    """Learn W_g and W_s on dictionary ``d`` (see the module docstring), on ``cfg.device``."""
    device = resolve_device(cfg.device)
    torch.manual_seed(cfg.seed)
    train, held = validation_split(d, cfg)
    anchors, kstar, others, margins = ranking_triplets(d, cfg, train)
    views = {v: torch.from_numpy(np.ascontiguousarray(x)).to(device) for v, x in (("g", d.g), ("s", d.s))}
    W = {v: torch.eye(x.shape[1], device=device, requires_grad=True) for v, x in views.items()}
    norms = {v: float(torch.linalg.norm(w.detach())) for v, w in W.items()}
    opt = torch.optim.Adam(list(W.values()), lr=cfg.lr)
    t_anchor, t_star, t_others, t_marg = (torch.from_numpy(a).to(device) for a in (anchors, kstar, others, margins))
    gen = torch.Generator().manual_seed(cfg.seed)
    alpha = {v: cfg.alpha if cfg.alpha is not None else auto_alpha(x, t_anchor, t_others, t_marg) for v, x in views.items()}
    validate = CooccurrenceMargin(d, train, held, cfg) if len(held) else None
    validate = validate if validate is not None and validate.usable else None
    margins0 = validate(W["g"], W["s"]) if validate else None
    val: list[float] = [float(margins0.mean())] if validate else []
    best = (0, W["g"].detach().clone(), W["s"].detach().clone(), margins0)
    curve: list[float] = []
    stale, converged = 0, False
    bar = tqdm(range(cfg.max_epochs), desc="projections", unit="epoch", disable=not progress, leave=False)
    for epoch in bar:
        perm = torch.randperm(len(anchors), generator=gen).to(device)   # drawn on the CPU: the same batches anywhere
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
        if validate:
            m = validate(W["g"], W["s"])
            val.append(float(m.mean()))
            if CooccurrenceMargin.better(m, best[3], cfg.val_z):
                best = (epoch + 1, W["g"].detach().clone(), W["s"].detach().clone(), m)
            bar.set_postfix(loss=f"{curve[-1]:.4f}", margin=f"{val[-1]:.3f}")
            if epoch + 1 - best[0] >= cfg.patience:      # no better held-out margin for `patience` epochs
                converged = True
                break
        else:
            bar.set_postfix(loss=f"{curve[-1]:.4f}")
        if len(curve) > 1 and (curve[-2] - curve[-1]) < cfg.tol * max(abs(curve[-2]), 1e-12):
            stale += 1
            if stale >= cfg.patience:
                converged = True
                break
        else:
            stale = 0
    if validate:
        W_g, W_s, kept = best[1], best[2], best[0]
    else:
        W_g, W_s, kept = W["g"].detach(), W["s"].detach(), -1
    return Projections(W_g.cpu().numpy().copy(), W_s.cpu().numpy().copy(), curve, converged, val, kept)


def evaluate_loss(d: Dictionary, p: Projections, cfg: ProjectionConfig = ProjectionConfig()) -> float:
    """The ranking loss of projections ``p`` on dictionary ``d`` (both views, all sampled anchors), on
    ``cfg.device``."""
    device = resolve_device(cfg.device)
    anchors, kstar, others, margins = (torch.from_numpy(a).to(device) for a in ranking_triplets(d, cfg))
    total = 0.0
    with torch.no_grad():
        for W, x in ((p.W_g, d.g), (p.W_s, d.s)):
            xt = torch.from_numpy(np.ascontiguousarray(x)).to(device)
            alpha = cfg.alpha if cfg.alpha is not None else auto_alpha(xt, anchors, others, margins)
            total += float(ranking_loss(torch.from_numpy(W).to(device), xt, anchors, kstar, others, margins, alpha))
    return total


def plot_loss(curve: list[float], path: str | Path, val_curve: list[float] | None = None, best_epoch: int = -1) -> None:
    """PNG of the loss curve (and of the held-out co-occurrence margin, epoch 0 = identity, if given)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.2), dpi=110)
    ax.plot(np.arange(1, len(curve) + 1), curve, marker="o", ms=3, label="ranking loss")
    ax.set_xlabel("epoch")
    ax.set_ylabel("ranking loss")
    ax.set_title("projection learning")
    ax.grid(alpha=0.3)
    if val_curve:
        ax2 = ax.twinx()
        ax2.plot(np.arange(len(val_curve)), val_curve, color="tab:orange", marker="s", ms=3,
                 label="held-out co-occurrence margin")
        if best_epoch >= 0:
            ax2.axvline(best_epoch, color="tab:orange", ls=":", lw=1)
        ax2.set_ylabel("co-occurrence margin", color="tab:orange")
        lines = ax.get_lines() + ax2.get_lines()[:1]
        ax.legend(lines, [ln.get_label() for ln in lines], loc="center right", fontsize=7)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
