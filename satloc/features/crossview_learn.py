"""Cross-view projections learned across places: the paper's W_g, W_s for localization with no database.

:mod:`satloc.localizers.crossview` compares the query's bird's-eye view (BEV) with the satellite map by masked normalised
cross-correlation of one channel each, by default the grey level of the bilateral-filtered colours. Here the
channels are learned: ``k`` channels of the ground BEV are ``W_g`` (k x 3) times its bilateral RGB (no network
runs on the ground image, so a frame costs what the grey level costs), and ``k`` channels of the map are ``W_s``
(k x D) times its features (RGB, edge potential and the FCN's class probabilities, computed once per map).
Channel 0 of both starts at the grey level, the others at the grey level plus small random weights, so the
untrained projections make (about) the grey-level comparison.

Training data (:func:`samples_from_sequence`): for each frame of a recorded pass on a training place, its BEV
and the satellite features resampled on the BEV grid at the true pose grown by ``search_m`` on every side.
Far negatives: the map at ``far`` poses moved along the true heading by 4-25 m either way (where look-alike
frontage repeats, the misses of the untrained comparison), a little sideways and turned. Loss, the paper's hinge
ranking with a margin that grows with the location difference: for every offset k of the near surface at
distance d(k) from the truth, ``max(0, margin * min(d(k) / margin_far_m, 1) - (r(truth) - r(k)))``, averaged,
plus ``max(0, margin - (r(truth) - r(far)))`` averaged over the far negatives; minimised with Adam. Model
selection: a share ``val_frac`` of the frames (in blocks along each pass) is held out; after every epoch the
share of held-out frames scored right (the near surface's peak within 1 m of the truth and above every far
negative) is measured, and the projections of the best epoch are kept, the untrained ones (epoch 0) included.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from ..device import device_field, resolve_device
from ..errors import ConfigError
from ..geometry import Pose2
from ..persist import atomic_path
from ..tracking.align import AlignConfig
from .crossview_channels import CrossViewProjections

__all__ = ["CrossTrainConfig", "CrossViewProjections", "samples_from_sequence", "train_crossview"]


@dataclass(frozen=True)
class CrossTrainConfig:
    channels: int = 3                 # k: learned channels of each view
    search_m: float = 2.0             # near surface: offsets within +- this of the truth (each axis)
    far: int = 8                      # far negatives per frame: the map at the true pose moved along the
    far_m: tuple[float, float] = (4.0, 25.0)   # heading by this many metres (either way; where look-alike
    far_lateral_m: float = 1.0        # frontage repeats), up to this laterally and far_yaw_deg in heading
    far_yaw_deg: float = 3.0
    margin: float = 0.2               # hinge margin (correlation units) at margin_far_m and beyond
    margin_far_m: float = 2.0
    lr: float = 0.01
    epochs: int = 30
    batch_size: int = 8
    val_frac: float = 0.2
    val_block: int = 5                # held-out frames come in blocks of this many along each pass
    patience: int = 6                 # epochs without a better held-out score before stopping
    seed: int = 0
    device: str = device_field()

    def __post_init__(self):
        if self.channels < 1 or self.search_m <= 0 or self.margin <= 0 or self.margin_far_m <= 0:
            raise ConfigError("train-crossview: channels >= 1, search_m > 0, margin > 0, margin_far_m > 0")
        if not 0 < self.val_frac < 1 or self.epochs < 1 or self.batch_size < 1 or self.val_block < 1:
            raise ConfigError("train-crossview: val_frac in (0, 1), epochs, batch_size and val_block >= 1")


def samples_from_sequence(seq, satfeat, frames=None, search_m: float = 2.0, align: AlignConfig = AlignConfig(),
                          progress: bool = False, config: CrossTrainConfig | None = None) -> dict:
    """Training samples of the frames ``frames`` (default all) of ``seq`` (a pass with true poses) on the map
    whose features are ``satfeat`` (:class:`satloc.features.dictionary.SatelliteFeatures`, the default extractor's):
    ``ground`` (N, 3, nx, ny) float16 BEV of the bilateral RGB, ``mask`` (N, nx, ny) uint8 (ground seen),
    ``sat`` (N, D, nx + 2(m + p), ny + 2(m + p)) float16 map features on the BEV grid of the true pose grown by
    m = search_m / resolution cells and p = :func:`pad_cells` more (normalised, then trimmed, in training), and
    ``far`` (N, F, D, nx + 2p, ny + 2p) float16 the map at ``config.far`` poses away from the truth
    (:class:`CrossTrainConfig`, seeded by ``config.seed`` and the frame). Frames with fewer than
    ``align.min_cells`` ground cells are left out (``index``: the frames kept)."""
    from tqdm.auto import tqdm

    from ..tracking.align import BevAligner
    from .dictionary import FrameDepth
    from .pixelwise import BilateralRGB

    al = BevAligner(seq.camera, satfeat.features[..., :3], satfeat.meters_per_pixel, satfeat.origin, align)
    al = al.with_search(search_m)
    depth, rgb = FrameDepth(seq.camera), BilateralRGB()
    f = satfeat.features
    frames = range(len(seq)) if frames is None else frames
    cfg = config or CrossTrainConfig(search_m=search_m)
    nx, ny = al.shape
    pad = pad_cells(align.normalize_m / al.res)   # crops grown so that normalising them matches the whole map's
    m = al.margin + pad
    cx, cy = np.meshgrid(al.x0 + al.res * np.arange(-m, nx + m), al.y0 + al.res * np.arange(-m, ny + m),
                         indexing="ij")
    bx, by = np.meshgrid(al.x0 + al.res * np.arange(-pad, nx + pad), al.y0 + al.res * np.arange(-pad, ny + pad),
                         indexing="ij")

    planes = [np.ascontiguousarray(f[..., k], np.float32) for k in range(f.shape[2])]

    def crop_at(p: Pose2, X, Y) -> np.ndarray:
        c, s = math.cos(p.yaw), math.sin(p.yaw)
        mu = ((p.x + c * X - s * Y - al.origin[0]) / al.res - 0.5).astype(np.float32)
        mv = ((al.origin[1] - (p.y + s * X + c * Y)) / al.res - 0.5).astype(np.float32)
        return np.stack([cv2.remap(pl, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
                         for pl in planes])

    out = {"ground": [], "mask": [], "sat": [], "far": [], "index": []}
    for i in tqdm(list(frames), desc="cross-view samples", unit="frame", disable=not progress, leave=False):
        fr = seq[int(i)]
        if fr.pose is None or not np.all(np.isfinite(fr.pose.as_array())):
            continue
        d = depth(fr, "training frame")
        g = rgb(fr.left, "ground")
        map_u, map_v, mask = al.grid(d)   # the localizer's BEV grid: on the fitted plane with fit_ground
        if mask.sum() < align.min_cells:
            continue
        bev = np.stack([cv2.remap(np.ascontiguousarray(g[..., c], np.float32), map_u, map_v, cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_REPLICATE) for c in range(3)])
        p = fr.pose
        crop = crop_at(p, cx, cy)
        rng = np.random.default_rng([cfg.seed, int(i)])
        far = []
        for _ in range(cfg.far):
            along = rng.uniform(*cfg.far_m) * rng.choice([-1.0, 1.0])
            side = rng.uniform(-cfg.far_lateral_m, cfg.far_lateral_m)
            q = p @ Pose2(along, side, math.radians(rng.uniform(-cfg.far_yaw_deg, cfg.far_yaw_deg)))
            far.append(crop_at(q, bx, by))
        out["far"].append(np.stack(far).astype(np.float16) if far else np.zeros((0, f.shape[2], nx, ny), np.float16))
        out["ground"].append(bev.astype(np.float16))
        out["mask"].append(mask.astype(np.uint8))
        out["sat"].append(crop.astype(np.float16))
        out["index"].append(int(i))
    if not out["index"]:
        raise ConfigError(f"cross-view samples: no frame of {seq.name!r} sees enough ground")
    return {k: np.stack(v) if k != "index" else np.asarray(v, np.int64) for k, v in out.items()}


def pad_cells(sigma_px: float) -> int:
    """The cells a satellite crop is grown by on every side so that normalising it gives, inside, what
    normalising the whole map gives (the Gaussian window's radius, as OpenCV truncates it: 4 sigma)."""
    if not sigma_px > 0:
        raise ConfigError("learned cross-view channels need local contrast normalisation (align.normalize_m > 0)")
    return int(round(4 * sigma_px))


def _gauss(sigma: float, device) -> torch.Tensor:
    r = pad_cells(sigma)   # cv2.GaussianBlur's kernel for float images: 2 * round(4 sigma) + 1 taps
    x = torch.arange(-r, r + 1, dtype=torch.float32, device=device)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def _blur(x: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian blur of (B, C, H, W), borders reflected."""
    b, c, h, w = x.shape
    r = (len(k) - 1) // 2
    y = x.reshape(b * c, 1, h, w)
    y = F.conv2d(F.pad(y, (r, r, 0, 0), mode="reflect"), k.view(1, 1, 1, -1))
    y = F.conv2d(F.pad(y, (0, 0, r, r), mode="reflect"), k.view(1, 1, -1, 1))
    return y.reshape(b, c, h, w)


def _normalize(x: torch.Tensor, mask: torch.Tensor | None, k: torch.Tensor) -> torch.Tensor:
    """satloc.tracking.align's local contrast normalisation (masked cells excluded and zeroed)."""
    m = torch.ones_like(x[:, :1]) if mask is None else mask
    wsum = _blur(m, k).clamp_min(1e-3)
    mu = _blur(x * m, k) / wsum
    var = (_blur(x * x * m, k) / wsum - mu * mu).clamp_min(0.0)
    return (x - mu) / torch.sqrt(var + 1e-4) * m


def surfaces(pg: CrossViewProjections | tuple, ground, mask, sat, sigma_px: float) -> torch.Tensor:
    """(B, 2m+1, 2m+1) masked NCC surfaces (OpenCV's TM_CCOEFF_NORMED with a mask), the mean over the learned
    channels; ``pg``: (W_g, W_s) tensors; ``ground`` (B, 3, nx, ny), ``mask`` (B, nx, ny), ``sat`` (B, D, H, W),
    the satellite crops grown by :func:`pad_cells` on every side (trimmed after normalising)."""
    wg, ws = pg
    kern = _gauss(sigma_px, ground.device)
    m = mask[:, None].float()
    g = _normalize(torch.einsum("kc,bchw->bkhw", wg, ground.float()), m, kern)
    p = pad_cells(sigma_px)
    s = _normalize(torch.einsum("kc,bchw->bkhw", ws, sat.float()), None, kern)[..., p:-p, p:-p]
    b, k, nx, ny = g.shape
    t = m * (g - (g * m).sum((2, 3), keepdim=True) / m.sum((2, 3), keepdim=True).clamp_min(1.0))
    si = s.reshape(1, b * k, *s.shape[2:])
    num = F.conv2d(si, t.reshape(b * k, 1, nx, ny), groups=b * k)
    mk = m.expand(b, k, nx, ny).reshape(b * k, 1, nx, ny)
    s1 = F.conv2d(si, mk, groups=b * k)
    s2 = F.conv2d(si * si, mk, groups=b * k)
    n = m.sum((2, 3)).reshape(1, b, 1, 1, 1).expand(1, b, k, 1, 1).reshape(1, b * k, 1, 1)
    var_i = (s2 - s1 * s1 / n).clamp_min(1e-6)
    tt = (t * t).sum((2, 3)).reshape(1, b * k, 1, 1)
    r = num / torch.sqrt(var_i * tt + 1e-12)
    return r.reshape(b, k, *r.shape[2:]).mean(1)


def far_scores(pg, ground, mask, far, sigma_px: float) -> torch.Tensor:
    """(B, F) masked NCC of each BEV against each of its far negatives (B, F, D, nx + 2p, ny + 2p; p:
    :func:`pad_cells`), mean over channels."""
    wg, ws = pg
    kern = _gauss(sigma_px, ground.device)
    m = mask[:, None].float()
    g = _normalize(torch.einsum("kc,bchw->bkhw", wg, ground.float()), m, kern)
    t = m * (g - (g * m).sum((2, 3), keepdim=True) / m.sum((2, 3), keepdim=True).clamp_min(1.0))   # (B, k, nx, ny)
    b, nf = far.shape[:2]
    p = pad_cells(sigma_px)
    s = _normalize(torch.einsum("kc,bfchw->bfkhw", ws, far.float()).flatten(0, 1), None, kern)[..., p:-p, p:-p]
    s = s.reshape(b, nf, *s.shape[1:])
    mm = m[:, None]
    n = mm.sum((3, 4)).clamp_min(1.0)
    s1, s2 = (s * mm).sum((3, 4)), (s * s * mm).sum((3, 4))
    num = (s * t[:, None]).sum((3, 4))
    tt = (t * t).sum((2, 3))[:, None]
    return (num / torch.sqrt((s2 - s1 * s1 / n).clamp_min(1e-6) * tt + 1e-12)).mean(2)


def _loss(r: torch.Tensor, rf: torch.Tensor, dist: torch.Tensor, cfg: CrossTrainConfig) -> torch.Tensor:
    """The hinge ranking loss: the truth against every offset of the near surface ``r`` (margin growing with
    the distance) and against the far negatives' scores ``rf`` (the full margin), averaged per frame."""
    c = r.shape[1] // 2
    rt = r[:, c, c]
    margin = cfg.margin * torch.clamp(dist / cfg.margin_far_m, max=1.0)
    w = (dist > 0).float()
    near = (F.relu(margin - (rt[:, None, None] - r)) * w).sum((1, 2)) / w.sum()
    if rf.shape[1] == 0:
        return near.mean()
    return (near + F.relu(cfg.margin - (rt[:, None] - rf)).mean(1)).mean()


def _correct(r: torch.Tensor, rf: torch.Tensor, dist: torch.Tensor) -> torch.Tensor:
    """Per frame: the near surface's peak within 1 m of the truth and above every far negative."""
    flat = r.reshape(r.shape[0], -1)
    best = flat.argmax(1)
    ok = dist.reshape(-1)[best] <= 1.0
    if rf.shape[1]:
        ok &= flat.max(1).values > rf.max(1).values
    return ok


def train_crossview(samples: list[dict], config: CrossTrainConfig = CrossTrainConfig(), trained_on=(),
                    meters_per_pixel: float = 0.2, align: AlignConfig = AlignConfig(), progress: bool = True,
                    log=print) -> CrossViewProjections:
    """Learn the projections on ``samples`` (a list of :func:`samples_from_sequence` outputs, one per pass),
    held-out blocks chosen per pass (see the module docstring). ``trained_on`` names the places."""
    from tqdm.auto import tqdm

    torch.manual_seed(config.seed)
    dev = resolve_device(config.device)
    rng = np.random.default_rng(config.seed)
    tr, va = [], []
    for si, s in enumerate(samples):
        n = len(s["index"])
        blocks = np.arange(n) // config.val_block
        nb = int(blocks.max()) + 1
        held = set(rng.choice(nb, max(1, int(round(nb * config.val_frac))), replace=False).tolist())
        for j in range(n):
            (va if blocks[j] in held else tr).append((si, j))
    if not tr or not va:
        raise ConfigError("train-crossview: too few frames for a training and a held-out part")
    d = samples[0]["sat"].shape[1]
    for s in samples:
        if s["sat"].shape[1] != d:
            raise ConfigError("train-crossview: the passes' maps have different feature channels")
    init = CrossViewProjections.initial(config.channels, d, config.seed)
    wg = torch.tensor(init.W_g, device=dev, requires_grad=True)
    ws = torch.tensor(init.W_s, device=dev, requires_grad=True)
    opt = torch.optim.Adam([wg, ws], lr=config.lr)
    sigma = align.normalize_m / meters_per_pixel
    m = (samples[0]["sat"].shape[2] - samples[0]["ground"].shape[2]) // 2 - pad_cells(sigma)
    ii, jj = np.mgrid[-m:m + 1, -m:m + 1]
    dist = torch.tensor(np.hypot(ii, jj) * meters_per_pixel, dtype=torch.float32, device=dev)

    def batch(idx):
        return [torch.tensor(np.stack([samples[a][key][b] for a, b in idx]), device=dev)
                for key in ("ground", "mask", "sat", "far")]

    def scores(idx):
        g, mk, st, fa = batch(idx)
        return surfaces((wg, ws), g, mk, st, sigma), far_scores((wg, ws), g, mk, fa, sigma)

    def evaluate() -> tuple[float, float]:
        with torch.no_grad():
            acc, loss, n = 0.0, 0.0, 0
            for k0 in range(0, len(va), config.batch_size):
                idx = va[k0:k0 + config.batch_size]
                r, rf = scores(idx)
                acc += float(_correct(r, rf, dist).float().sum())
                loss += float(_loss(r, rf, dist, config)) * len(idx)
                n += len(idx)
        return acc / n, loss / n

    acc0, vl0 = evaluate()
    curves = {"loss": [float("nan")], "val_loss": [vl0], "val_within_1m": [acc0]}
    best = (acc0, -vl0, 0, init.W_g.copy(), init.W_s.copy())
    log(f"train-crossview: {len(tr)} training and {len(va)} held-out frames; epoch 0 (untrained, the grey level "
        f"on every channel): held-out frames right {acc0:.1%} (peak within 1 m, above every far negative)")
    stale = 0
    for ep in tqdm(range(1, config.epochs + 1), desc="train-crossview", unit="epoch", disable=not progress):
        order = rng.permutation(len(tr))
        tot = 0.0
        for k0 in range(0, len(order), config.batch_size):
            idx = [tr[i] for i in order[k0:k0 + config.batch_size]]
            r, rf = scores(idx)
            loss = _loss(r, rf, dist, config)
            opt.zero_grad()
            loss.backward()
            opt.step()
            tot += loss.item() * len(idx)
        acc, vl = evaluate()
        curves["loss"].append(tot / len(tr))
        curves["val_loss"].append(vl)
        curves["val_within_1m"].append(acc)
        log(f"train-crossview: epoch {ep}: loss {tot / len(tr):.4f}, held-out loss {vl:.4f}, right {acc:.1%}")
        if (acc, -vl) > best[:2]:
            best = (acc, -vl, ep, wg.detach().cpu().numpy().copy(), ws.detach().cpu().numpy().copy())
            stale = 0
        else:
            stale += 1
            if stale >= config.patience:
                break
    return CrossViewProjections(best[3], best[4], list(trained_on), curves, best[2])


def plot_learning_curve(proj: CrossViewProjections, path: str | Path) -> None:
    """The loss and the held-out share of frames scored right per epoch, the kept epoch marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = proj.curves
    ep = np.arange(len(c.get("val_within_1m", [])))
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
    ax[0].plot(ep[1:], c["loss"][1:], label="training")
    ax[0].plot(ep, c["val_loss"], label="held out")
    ax[0].set_xlabel("epoch")
    ax[0].set_ylabel("hinge ranking loss")
    ax[0].legend()
    ax[1].plot(ep, 100 * np.asarray(c["val_within_1m"]), marker="o")
    ax[1].axvline(proj.best_epoch, color="k", ls=":", label=f"kept: epoch {proj.best_epoch}")
    ax[1].set_xlabel("epoch")
    ax[1].set_ylabel("held-out frames right (%)")
    ax[1].legend()
    fig.suptitle("cross-view projections, trained on " + ", ".join(proj.trained_on), fontsize=9)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
