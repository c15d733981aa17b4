"""Train the project's FCN (:mod:`satloc.features.fcn`) on images rendered by the simulator, whose labels are exact.

``train_features(out_dir)`` (or ``python -m satloc_env.experiments.train_features --out DIR``) writes ``DIR/fcn.pt``
(the weights, both views) and ``DIR/fcn_report.json`` (configuration, timings, losses, held-out metrics).

Data:

- ground: left frames and label images of ``satloc/SatLoc-v0`` (``labels=True, random_start=True``), driven
  by the autopilot, one frame every ``frame_every`` steps. Every episode draws its occlusion and appearance
  knobs in [0, 1] and a lane offset in [-3.5, 3.5] m from its seed; the training scenes are rendered at each
  of the ``aliasing`` levels (other block arrangements). The network sees the frame at ``ground_scale``.
- satellite: crops of each training scene's tile and label map, rotated by any angle, rescaled by up to
  +-25 % and mirrored; also of ``sat_seed_variants`` tiles per training scene generated from the same scene
  file with other seeds (other layouts and textures; never a held-out scene's seed), their ground textures
  painted at the resolutions of ``sat_variant_ground_mpp`` in turn (the shipped scenes use 0.1 and 0.2 m;
  the coarser one gives the tile rougher grass that an untrained network mistakes for tree canopies).
  Aliased tiles are not used: their blocks are copies of the unaliased tile's blocks, which would leak into
  the held-out strip.

Both views get a random photometric change (gain, white balance, gamma, contrast) per image, and the loss is
cross-entropy over classes plus a class-balanced binary cross-entropy on the boundary target (pixels whose
4-neighbourhood holds another class), at the network's input resolution (labels resized by nearest
neighbour). AdamW with a one-cycle (warm-up, then cosine decay) learning rate.

Held out, never trained on, and reported:

- the ``heldout`` scenes (default ``city``, ``residential`` and ``loop``, every scene the method is evaluated
  on; the default training scenes are ``scenes/fcn_train/*.yaml``, generated scenes disjoint from them): ground
  frames of its episodes, and its whole satellite tile;
- ground: episodes of the training scenes with seeds disjoint from the training seeds (same streets, other
  starts, lanes, occluders and appearance);
- satellite: the bottom ``sat_holdout`` fraction of rows of every training tile (training crops come from
  the rows above it only).

Metrics: pixel accuracy, per-class IoU, mean IoU over the classes present in the ground truth, and boundary
precision / recall / F1 (edge probability > 0.5 against the boundary target, with a 2-pixel tolerance).
Runs are deterministic for a given seed and thread count (on the CPU).

Device: training and the held-out evaluation run on ``device`` (:mod:`satloc.device`: ``"auto"``, the
default, is CUDA when it is available, else the CPU). The batches, their photometric changes and the initial
weights are drawn on the CPU wherever training runs; the weights are saved as CPU tensors, and the report
records the device used.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Iterator, Mapping, Sequence

import cv2
import gymnasium as gym
import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from satloc.config import added_field, from_dict, to_dict
from satloc.device import HELP as DEVICE_HELP
from satloc.device import device_field, resolve_device
from satloc.errors import ConfigError, SatlocError
from satloc.features.fcn import FCNPredictor, SegEdgeNet, ViewNet, save_fcn, torch_threads
from satloc.labels import CLASSES, NUM_CLASSES
from satloc.persist import header, write_json
from satloc.satmap import SatelliteMap
from satloc_env.envs import ENV_ID
from satloc_env.world.capture import DEFAULT_GAP
from satloc_env.world.scene import SceneSpec, build_scene, load_scene

IGNORE = 255
WEIGHTS_NAME = "fcn.pt"
REPORT_NAME = "fcn_report.json"
BOUNDARY_TOLERANCE_PX = 2


@dataclass
class TrainConfig:
    """Everything a training run depends on besides the scenes; recorded in the report and the weights."""

    seed: int = 0
    widths: tuple[int, ...] = (16, 32, 48, 64, 96)
    ground_scale: float = 0.5           # the ground network sees frames at this scale
    aliasing: tuple[float, ...] = (0.0, 0.5)   # ground: each training scene at each of these levels
    ground_episodes: int = 24           # per training scene and aliasing level
    frames_per_episode: int = 12
    dt: float = 0.25                    # simulator step (s): the autopilot's 8 m/s make 2 m per rendered step
    frame_every: int = 2                # steps between kept frames (about 4 m)
    eval_episodes: int = 8              # held-out ground episodes per scene (and per training scene)
    ground_iters: int = 800
    ground_batch: int = 12
    sat_iters: int = 800
    sat_batch: int = 12
    sat_crop: int = 192
    sat_holdout: float = 0.2            # bottom fraction of each training tile kept for evaluation
    sat_seed_variants: int = 2          # extra satellite tiles per training scene, from other seeds
    sat_variant_ground_mpp: tuple[float, ...] = (0.1, 0.2)   # their ground-texture resolutions, in turn
    satellite_gap: float = added_field(DEFAULT_GAP, before=0.0)   # the satellite tiles (training and held out)
                                        # as captures of the world at this gap (satloc_env.world.capture)
    lr: float = 3e-3
    weight_decay: float = 1e-4
    boundary_weight: float = 1.0
    threads: int | None = None          # torch threads (None: torch's default)
    device: str = device_field()        # where the networks train and are evaluated (satloc.device)
    # occlusion cap of held-out scene episodes: on the 6 km loop route, occlusion above ~0.45 makes the
    # simulator's occluder texture exceed OpenGL's size limit (GLError at reset)
    heldout_max_occlusion: float = 0.4
    # ground episodes' lane offsets are drawn in [-lane_offset_m, lane_offset_m] (m); the varied grids' kerbs leave
    # less room at corners than the plain ones (fcn_train's town_b keeps the road to +-2.5 m at variety 1)
    lane_offset_m: float = added_field(3.5)


# --- data -----------------------------------------------------------------------------------------------
@dataclass
class GroundData:
    """Frames and labels at the network's input scale."""

    images: np.ndarray   # (N, h, w, 3) uint8
    labels: np.ndarray   # (N, h, w) uint8


def label_boundaries(labels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Boundary target and validity of (N, H, W) labels: pixels with another class among their 4-neighbours
    (lines two pixels wide); pixels that are, or touch, ``IGNORE`` are invalid."""
    edge = torch.zeros_like(labels, dtype=torch.bool)
    bad = labels == IGNORE
    invalid = bad.clone()
    for dim in (1, 2):
        a, b = labels.narrow(dim, 0, labels.shape[dim] - 1), labels.narrow(dim, 1, labels.shape[dim] - 1)
        diff = a != b
        edge.narrow(dim, 0, labels.shape[dim] - 1).logical_or_(diff)
        edge.narrow(dim, 1, labels.shape[dim] - 1).logical_or_(diff)
        invalid.narrow(dim, 0, labels.shape[dim] - 1).logical_or_(bad.narrow(dim, 1, labels.shape[dim] - 1))
        invalid.narrow(dim, 1, labels.shape[dim] - 1).logical_or_(bad.narrow(dim, 0, labels.shape[dim] - 1))
    return edge, ~invalid


def _episode_options(seed: int, max_occlusion: float, lane_offset_m: float = 3.5) -> dict:
    r = np.random.default_rng(seed)
    # no drift: the lane offset is drawn over the whole road already (and drift on top would leave it)
    return {"occlusion": float(r.uniform(0, max_occlusion)), "appearance": float(r.uniform(0, 1)),
            "lane_offset_m": float(r.uniform(-lane_offset_m, lane_offset_m)), "wander_m": 0.0, "speed_wander": 0.0}


def render_ground(scene: str, aliasing: float | None, seeds: Sequence[int], frames_per_episode: int,
                  frame_every: int, dt: float = 0.1, max_occlusion: float = 1.0, progress: tqdm | None = None,
                  lane_offset_m: float = 3.5) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Left frames and their labels from one episode per seed, driven by the autopilot; each episode draws
    its occlusion in [0, max_occlusion], appearance in [0, 1] and lane offset in [-lane_offset_m, lane_offset_m]."""
    env = gym.make(ENV_ID, scene=scene, labels=True, random_start=True, aliasing=aliasing, dt=dt, localizer=None)
    images, labels = [], []
    try:
        for s in seeds:
            obs, _ = env.reset(seed=int(s), options=_episode_options(int(s), max_occlusion, lane_offset_m))
            for i in range(frames_per_episode * frame_every):
                if i % frame_every == 0:
                    images.append(obs["left"])
                    labels.append(obs["labels"])
                obs, _, term, trunc, _ = env.step(env.unwrapped.autopilot_action())
                if term or trunc:
                    break
            if progress is not None:
                progress.update(1)
    finally:
        env.close()
    return images, labels


def _scaled(images: Sequence[np.ndarray], scale: float, labels: bool = False) -> np.ndarray:
    """Images (area-averaged) or label images (nearest) resized by ``scale``, stacked."""
    if scale == 1.0:
        return np.stack(images)
    h, w = images[0].shape[:2]
    size = (max(1, int(round(w * scale))), max(1, int(round(h * scale))))
    interp = cv2.INTER_NEAREST if labels else cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    return np.stack([cv2.resize(im, size, interpolation=interp) for im in images])


class SatelliteCrops:
    """Random rotated, rescaled, mirrored square crops of (image, labels) tiles; outside pixels are IGNORE."""

    def __init__(self, tiles: Sequence[tuple[np.ndarray, np.ndarray]], crop: int):
        self.tiles, self.crop = list(tiles), crop
        self.weights = np.array([t[1].size for t in self.tiles], np.float64)
        self.weights /= self.weights.sum()

    def sample(self, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
        c = self.crop
        images, labels = np.empty((n, c, c, 3), np.uint8), np.empty((n, c, c), np.uint8)
        for k in range(n):
            img, lab = self.tiles[rng.choice(len(self.tiles), p=self.weights)]
            h, w = lab.shape
            cx, cy = rng.uniform(0, w), rng.uniform(0, h)
            m = cv2.getRotationMatrix2D((cx, cy), float(rng.uniform(0, 360)), float(rng.uniform(0.8, 1.25)))
            m[:, 2] += (c / 2 - cx, c / 2 - cy)
            images[k] = cv2.warpAffine(img, m, (c, c), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            labels[k] = cv2.warpAffine(lab, m, (c, c), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                                       borderValue=IGNORE)
            if rng.random() < 0.5:
                images[k], labels[k] = images[k][:, ::-1], labels[k][:, ::-1]
        return images, labels


def seed_variant_tiles(spec: SceneSpec, n: int, ground_mpp: Sequence[float], rng: np.random.Generator,
                       exclude: set[int]) -> list[tuple[np.ndarray, np.ndarray]]:
    """(image, labels) satellite tiles of ``n`` scenes generated from a procedural scene's ``spec`` with random
    seeds not in ``exclude`` (nor the spec's own seed), variant ``k`` with its ground texture painted at
    ``ground_mpp[k % len(ground_mpp)]`` metres per texel; none for an image scene, which seeds do not change."""
    if spec.generator_spec().type != "grid":
        return []
    tiles = []
    while len(tiles) < n:
        s = int(rng.integers(2**31 - 1))
        if s in exclude or s == spec.seed:
            continue
        mpp = float(ground_mpp[len(tiles) % len(ground_mpp)])
        sm = build_scene(replace(spec, seed=s, ground_mpp=mpp)).satmap   # the spec's knobs: its satellite gap
        tiles.append((sm.image, sm.labels))
    return tiles


def _photometric(x: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    """Per-image random gain, white balance, gamma and contrast of (N, 3, H, W) RGB in [0, 1] (drawn from the
    CPU generator ``g``, applied on ``x``'s device)."""
    n = x.shape[0]
    gain = torch.exp(0.3 * torch.randn(n, 1, 1, 1, generator=g)).to(x.device)
    wb = (1.0 + 0.06 * torch.randn(n, 3, 1, 1, generator=g)).to(x.device)
    gamma = torch.exp(0.2 * torch.randn(n, 1, 1, 1, generator=g)).to(x.device)
    contrast = (1.0 + 0.12 * torch.randn(n, 1, 1, 1, generator=g)).to(x.device)
    y = (x * gain * wb).clamp(1e-4, 1.0) ** gamma
    return ((y - 0.5) * contrast + 0.5).clamp(0.0, 1.0)


# --- training -------------------------------------------------------------------------------------------
Batches = Callable[[np.random.Generator], tuple[np.ndarray, np.ndarray]]


def class_weights(labels: np.ndarray) -> torch.Tensor:
    """Cross-entropy weights from class frequencies: inverse square root, normalised to mean 1 over present
    classes, clipped to [0.25, 4]; absent classes get 0."""
    counts = np.bincount(labels[labels != IGNORE].ravel(), minlength=NUM_CLASSES)[:NUM_CLASSES].astype(np.float64)
    present = counts > 0
    w = np.zeros(NUM_CLASSES)
    w[present] = 1.0 / np.sqrt(counts[present] / counts.sum())
    w[present] = np.clip(w[present] / w[present].mean(), 0.25, 4.0)
    return torch.tensor(w, dtype=torch.float32)


def segmentation_loss(net: SegEdgeNet, images: np.ndarray, labels: np.ndarray, weights: torch.Tensor,
                      boundary_weight: float, g: torch.Generator | None = None) -> torch.Tensor:
    """Cross-entropy + boundary BCE of ``net`` on a batch of (N, h, w, 3) images and (N, h, w) labels, on the
    device of ``net``'s parameters. With a (CPU) generator ``g``, images get a random photometric change."""
    device = next(net.parameters()).device
    x = torch.from_numpy(images).to(device).permute(0, 3, 1, 2).float().div_(255.0)
    if g is not None:
        x = _photometric(x, g)
    y = torch.from_numpy(labels).to(device).long()
    scores, edge = net.forward_with_edges(x)
    ce = F.cross_entropy(scores, y, weight=weights.to(device), ignore_index=IGNORE)
    target, valid = label_boundaries(y)
    pos = (target & valid).sum().clamp(min=1)
    pos_weight = ((valid.sum() - pos) / pos).clamp(min=1.0).sqrt().float()
    bce = F.binary_cross_entropy_with_logits(edge[:, 0], target.float(), weight=valid.float(),
                                             pos_weight=pos_weight, reduction="sum") / valid.sum().clamp(min=1)
    return ce + boundary_weight * bce


def train_view(net: SegEdgeNet, batches: Batches, weights: torch.Tensor, iters: int, cfg: TrainConfig,
               rng: np.random.Generator, desc: str, progress: bool = True) -> list[float]:
    """Adam with cosine decay over ``iters`` batches; returns the loss of every iteration."""
    g = torch.Generator().manual_seed(int(rng.integers(2**62)))
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=cfg.lr, total_steps=max(iters, 1), pct_start=0.05)
    net.train()
    losses = []
    bar = tqdm(range(iters), desc=desc, disable=not progress, dynamic_ncols=True)
    for _ in bar:
        images, labels = batches(rng)
        loss = segmentation_loss(net, images, labels, weights, cfg.boundary_weight, g)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        losses.append(loss.item())
        bar.set_postfix(loss=f"{np.mean(losses[-20:]):.3f}", refresh=False)
    net.eval()
    return losses


# --- evaluation -----------------------------------------------------------------------------------------
class Metrics:
    """Accumulates a confusion matrix and boundary matches over images."""

    def __init__(self) -> None:
        self.confusion = np.zeros((NUM_CLASSES, NUM_CLASSES), np.int64)
        self.edge_counts = np.zeros(4, np.int64)  # predicted, predicted near truth, true, true near predicted
        self.images = 0

    def add(self, pred: np.ndarray, edge: np.ndarray, labels: np.ndarray) -> None:
        """One image: predicted classes (H, W), predicted boundary mask (H, W) bool, true labels (H, W)."""
        ok = labels != IGNORE
        self.confusion += np.bincount(labels[ok].astype(np.int64) * NUM_CLASSES + pred[ok],
                                      minlength=NUM_CLASSES**2).reshape(NUM_CLASSES, NUM_CLASSES)
        target, valid = label_boundaries(torch.from_numpy(labels)[None])
        target, valid = target[0].numpy(), valid[0].numpy()
        p = edge & valid
        t = target & valid
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * BOUNDARY_TOLERANCE_PX + 1,) * 2)
        near_t = cv2.dilate(t.astype(np.uint8), k).astype(bool)
        near_p = cv2.dilate(p.astype(np.uint8), k).astype(bool)
        self.edge_counts += (p.sum(), (p & near_t).sum(), t.sum(), (t & near_p).sum())
        self.images += 1

    def summary(self) -> dict:
        c = self.confusion
        tp = np.diag(c).astype(np.float64)
        gt, pr = c.sum(1), c.sum(0)
        union = gt + pr - tp
        iou = {name: (round(float(tp[i] / union[i]), 4) if gt[i] > 0 else None) for i, name in enumerate(CLASSES)}
        present = [v for v in iou.values() if v is not None]
        npred, pnear, ntrue, tnear = (float(v) for v in self.edge_counts)
        prec = pnear / npred if npred else 0.0
        rec = tnear / ntrue if ntrue else 0.0
        f1 = 2 * prec * rec / (prec + rec) if prec + rec else 0.0
        return {"images": self.images, "pixels": int(c.sum()),
                "pixel_accuracy": round(float(tp.sum() / max(c.sum(), 1)), 4),
                "mean_iou": round(float(np.mean(present)), 4) if present else None,
                "iou": iou, "boundary_precision": round(prec, 4), "boundary_recall": round(rec, 4),
                "boundary_f1": round(f1, 4)}


def evaluate(predictor: FCNPredictor, view: str, pairs: Iterator[tuple[np.ndarray, np.ndarray]]) -> dict:
    """Metrics of the predictor on (image, labels) pairs of one view."""
    m = Metrics()
    for image, labels in pairs:
        out = predictor(image, view)
        m.add(out.scores.argmax(axis=0), out.edge > 0.0, labels)  # logit > 0: probability > 0.5
    return m.summary()


# --- driver ---------------------------------------------------------------------------------------------
def _split_tile(labels: np.ndarray, holdout: float) -> int:
    """Row where the held-out bottom strip of a tile starts."""
    return int(round(labels.shape[0] * (1.0 - holdout)))


def _training_frames(scenes: Sequence[str], seeds: Mapping[str, np.ndarray], cfg: TrainConfig,
                     progress: bool) -> GroundData:
    """Frames of the training episodes: ``seeds[scene]`` holds ``ground_episodes`` seeds per aliasing level."""
    images, labels = [], []
    n = cfg.ground_episodes
    with tqdm(total=sum(len(v) for v in seeds.values()), desc="render ground", disable=not progress,
              dynamic_ncols=True) as bar:
        for s in scenes:
            for j, a in enumerate(cfg.aliasing):
                im, lab = render_ground(s, a, seeds[s][j * n:(j + 1) * n], cfg.frames_per_episode, cfg.frame_every,
                                        cfg.dt, progress=bar, lane_offset_m=cfg.lane_offset_m)
                images += im
                labels += lab
    return GroundData(_scaled(images, cfg.ground_scale), _scaled(labels, cfg.ground_scale, labels=True))


def _heldout_metrics(predictor: FCNPredictor, scenes: Sequence[str], heldout: Sequence[str],
                     eval_seeds: Mapping[str, np.ndarray], satmaps: Mapping[str, SatelliteMap],
                     cfg: TrainConfig) -> dict[str, dict]:
    """Metrics on everything training did not see (see the module docstring); the held-out scenes' tiles
    captured at ``cfg.satellite_gap``."""
    metrics: dict[str, dict] = {"ground": {}, "satellite": {}}
    for s in [*heldout, *scenes]:
        kind = "scene" if s in heldout else "episodes"
        im, lab = render_ground(s, None if s in heldout else 0.0, eval_seeds[s], max(1, cfg.frames_per_episode // 2),
                                cfg.frame_every * 2, cfg.dt, cfg.heldout_max_occlusion if s in heldout else 1.0,
                                lane_offset_m=cfg.lane_offset_m)
        metrics["ground"][f"{kind}:{s}"] = evaluate(predictor, "ground", zip(im, lab))
    for s in heldout:
        sm = load_scene(s, satellite_gap=cfg.satellite_gap).satmap
        metrics["satellite"][f"scene:{s}"] = evaluate(predictor, "satellite", iter([(sm.image, sm.labels)]))
    for s, sm in satmaps.items():
        r = _split_tile(sm.labels, cfg.sat_holdout)
        metrics["satellite"][f"strip:{s}"] = evaluate(predictor, "satellite", iter([(sm.image[r:], sm.labels[r:])]))
    return metrics


def _loss_summary(losses: list[float]) -> dict:
    k = max(1, min(20, len(losses)))
    return {"iterations": len(losses), "first": round(float(np.mean(losses[:k])), 4),
            "last": round(float(np.mean(losses[-k:])), 4)}


#: the shipped weights' training scenes, in scenes/fcn_train/ (the order matters: it assigns the seeds)
TRAINING_SCENES = ("town_a", "town_b", "suburb_a", "suburb_b")


def training_scenes() -> list[str]:
    """The shipped weights' training scenes: :data:`TRAINING_SCENES` of ``scenes/fcn_train/``, generated scenes
    disjoint from every scene the method is evaluated on (other seeds, block sizes, pitches, road widths,
    light)."""
    from satloc_env.world.scene import SCENES_DIR

    return [str(SCENES_DIR / "fcn_train" / f"{name}.yaml") for name in TRAINING_SCENES]


#: the shipped weights' held-out scenes: every evaluation scene (none of them is trained on)
HELDOUT = ("city", "residential", "loop")


def train_features(out_dir: str | Path, scenes: Sequence[str] | None = None,
                   heldout: Sequence[str] = HELDOUT, config: TrainConfig | dict | None = None,
                   progress: bool = True) -> dict:
    """Render training data, train the ground and satellite networks, evaluate on held-out data.
    ``scenes``: the training scenes (default: :func:`training_scenes`).

    Writes ``out_dir/fcn.pt`` and ``out_dir/fcn_report.json`` atomically and returns the report.
    ``config``: a :class:`TrainConfig` or a dict of its fields.
    """
    cfg = config if isinstance(config, TrainConfig) else from_dict(TrainConfig, dict(config or {}), "train config")
    scenes = training_scenes() if scenes is None else scenes
    if not scenes:
        raise ConfigError("train_features: need at least one training scene")
    if set(scenes) & set(heldout):
        raise ConfigError(f"train_features: scenes {sorted(set(scenes) & set(heldout))} are both trained on and "
                          f"held out")
    if not 0.0 < cfg.sat_holdout < 0.5:
        raise ConfigError(f"sat_holdout: expected a value in (0, 0.5), got {cfg.sat_holdout}")
    if not 0.0 <= cfg.lane_offset_m <= 10.0:
        raise ConfigError(f"lane_offset_m: expected metres in [0, 10], got {cfg.lane_offset_m}")
    if not 0.0 < cfg.ground_scale <= 1.0:
        raise ConfigError(f"ground_scale: expected a value in (0, 1], got {cfg.ground_scale}")
    device = resolve_device(cfg.device)
    with torch_threads(cfg.threads):
        return _train(Path(out_dir), list(scenes), list(heldout), cfg, device, progress)


def episode_seeds(rng: np.random.Generator, scenes: Sequence[str], heldout: Sequence[str], cfg: TrainConfig
                  ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Disjoint episode seeds, as a training run draws them first from its generator: ``ground_episodes`` per
    aliasing level for each training scene, then ``eval_episodes`` held-out ones for every training and held-out
    scene. Returns (training seeds, held-out seeds) by scene."""
    n_train, n_eval = cfg.ground_episodes * len(cfg.aliasing), cfg.eval_episodes
    seeds = rng.choice(2**31, size=len(scenes) * n_train + (len(scenes) + len(heldout)) * n_eval, replace=False)
    train_seeds = {s: seeds[i * n_train:(i + 1) * n_train] for i, s in enumerate(scenes)}
    rest = seeds[len(scenes) * n_train:]
    return train_seeds, {s: rest[i * n_eval:(i + 1) * n_eval] for i, s in enumerate([*scenes, *heldout])}


def _train(out_dir: Path, scenes: list[str], heldout: list[str], cfg: TrainConfig, device: torch.device,
           progress: bool) -> dict:
    t_start = time.perf_counter()
    rng = np.random.default_rng(cfg.seed)
    torch.manual_seed(cfg.seed)
    times: dict[str, float] = {}

    train_seeds, eval_seeds = episode_seeds(rng, scenes, heldout, cfg)
    # the unaliased tiles (also the scenes of the held-out ground episodes), kept for evaluation
    satmaps = {s: load_scene(s, 0.0, cfg.satellite_gap).satmap for s in scenes}

    t0 = time.perf_counter()
    ground = _training_frames(scenes, train_seeds, cfg, progress)
    times["render_ground_s"] = time.perf_counter() - t0

    # satellite data: the unaliased tiles above their held-out strips, and seed variants
    t0 = time.perf_counter()
    sat_tiles = []
    for sm in satmaps.values():
        r = _split_tile(sm.labels, cfg.sat_holdout)
        sat_tiles.append((sm.image[:r], sm.labels[:r]))
    heldout_seeds = {load_scene(h).spec.seed for h in heldout}
    for s in scenes:
        sat_tiles += seed_variant_tiles(load_scene(s, 0.0, cfg.satellite_gap).spec, cfg.sat_seed_variants,
                                        cfg.sat_variant_ground_mpp, rng, heldout_seeds)
    times["generate_tiles_s"] = time.perf_counter() - t0
    crops = SatelliteCrops(sat_tiles, cfg.sat_crop)

    def ground_batch(r: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        idx = r.choice(len(ground.labels), size=cfg.ground_batch, replace=False)
        im, lab = ground.images[idx], ground.labels[idx]
        flip = r.random(len(idx)) < 0.5
        im[flip], lab[flip] = im[flip][:, :, ::-1], lab[flip][:, :, ::-1]
        return np.ascontiguousarray(im), np.ascontiguousarray(lab)

    # made on the CPU (the same initial weights anywhere), then moved
    nets = {v: SegEdgeNet(NUM_CLASSES, cfg.widths).to(device) for v in ("ground", "satellite")}
    losses = {}
    t0 = time.perf_counter()
    losses["ground"] = train_view(nets["ground"], ground_batch, class_weights(ground.labels), cfg.ground_iters, cfg,
                                  rng, "train ground", progress)
    times["train_ground_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    sat_w = class_weights(np.concatenate([lab.ravel() for _, lab in sat_tiles]))
    losses["satellite"] = train_view(nets["satellite"], lambda r: crops.sample(r, cfg.sat_batch), sat_w,
                                     cfg.sat_iters, cfg, rng, "train satellite", progress)
    times["train_satellite_s"] = time.perf_counter() - t0

    weights_path = out_dir / WEIGHTS_NAME
    summary = {"config": to_dict(cfg), "scenes": scenes, "heldout": heldout}
    save_fcn(weights_path, {"ground": ViewNet(nets["ground"], cfg.ground_scale),
                            "satellite": ViewNet(nets["satellite"], 1.0)}, summary)

    t0 = time.perf_counter()
    metrics = _heldout_metrics(FCNPredictor(weights_path, device=device), scenes, heldout, eval_seeds, satmaps, cfg)
    times["evaluate_s"] = time.perf_counter() - t0
    times["total_s"] = time.perf_counter() - t_start

    report = dict(header("satloc_fcn_report"))
    report.update(summary)
    report.update(weights=WEIGHTS_NAME, weights_bytes=weights_path.stat().st_size,
                  parameters={v: sum(p.numel() for p in n.parameters()) for v, n in nets.items()},
                  threads=torch.get_num_threads(), device=str(device), ground_frames_trained=len(ground.labels),
                  times={k: round(v, 1) for k, v in times.items()},
                  loss={v: _loss_summary(x) for v, x in losses.items()}, heldout_metrics=metrics)
    write_json(out_dir / REPORT_NAME, report)
    return report


DESCRIPTION = ("Train the semantic and edge network (satloc.features.fcn) on images rendered by the simulator; write the "
               "weights (fcn.pt) and a report of held-out metrics (fcn_report.json).")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The command-line options (for ``satloc train-features``: add them to a subparser, call :func:`run`)."""
    p.add_argument("--out", required=True, help="directory for fcn.pt and fcn_report.json (the shipped "
                   "weights live in satloc/weights)")
    p.add_argument("--scenes", nargs="+", default=None,
                   help="training scenes (default: scenes/fcn_train/*.yaml, disjoint from every evaluation scene)")
    p.add_argument("--heldout", nargs="*", default=list(HELDOUT), help="held-out scenes (evaluation only)")
    p.add_argument("--seed", type=int, default=TrainConfig.seed)
    p.add_argument("--ground-iters", type=int, default=TrainConfig.ground_iters)
    p.add_argument("--sat-iters", type=int, default=TrainConfig.sat_iters)
    p.add_argument("--ground-episodes", type=int, default=TrainConfig.ground_episodes,
                   help="training episodes per scene and aliasing level")
    p.add_argument("--lane-offset-m", type=float, default=TrainConfig.lane_offset_m,
                   help="ground episodes' lane offsets drawn in [-this, this] m (default %(default)s)")
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads (default: torch's; 1 is faster when other processes load the cores)")
    p.add_argument("--device", default=TrainConfig.device, help=DEVICE_HELP)
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    """Train with parsed options; print a one-line JSON summary (held-out metrics, times)."""
    cfg = TrainConfig(seed=args.seed, ground_iters=args.ground_iters, sat_iters=args.sat_iters,
                      ground_episodes=args.ground_episodes, threads=args.threads, device=args.device,
                      lane_offset_m=args.lane_offset_m)
    report = train_features(args.out, args.scenes, args.heldout, cfg, progress=not args.quiet)
    brief = {k: {s: {"pixel_accuracy": m["pixel_accuracy"], "mean_iou": m["mean_iou"], "boundary_f1": m["boundary_f1"]}
                 for s, m in v.items()} for k, v in report["heldout_metrics"].items()}
    print(json.dumps({"out": str(args.out), "times": report["times"], "heldout": brief}))
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="satloc train-features", description=DESCRIPTION)
    add_arguments(p)
    args = p.parse_args(argv)
    try:
        return run(args)
    except SatlocError as e:
        print(f"satloc train-features: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
