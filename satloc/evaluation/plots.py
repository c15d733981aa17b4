"""Pictures of localization results: posterior heatmaps over the satellite image, errors along the route."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..geometry import Pose2, arc_length
from ..localizers.database import Localization
from ..persist import atomic_path, load_npz
from ..satmap import SatelliteMap
from ..sequence import Sequence


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> None:
    with atomic_path(path, suffix=Path(path).suffix) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")


def plot_posterior(satmap: SatelliteMap, result: Localization, truth: Pose2 | None, path: str | Path,
                   window_m: float = 120.0, title: str = "") -> int:
    """The whole map and a ``window_m`` crop around the truth (or the estimate), each with the posterior over
    candidate poses as a heatmap, the estimate (cross) and the truth (circle); for a refined result also the
    co-occurrence estimate before alignment (plus). When the estimate lies outside the truth's crop, a third
    panel crops around the estimate, so both are seen up close. Returns the number of panels drawn."""
    plt = _pyplot()
    post, c = result.posterior, result.candidates
    rel = post / max(post.max(), 1e-300)
    order = np.argsort(post)                         # most probable drawn last, on top
    order = order[rel[order] >= 1e-4]                # below the colour scale: not drawn, the map shows through
    e = result.estimate
    crops = [("around the truth", truth)] if truth is not None else [("around the estimate", e)]
    if truth is not None and max(abs(e.x - truth.x), abs(e.y - truth.y)) > 0.45 * window_m:
        crops.append((f"around the estimate, {e.distance(truth):.0f} m away", e))
    panels = [("whole map", None)] + crops
    fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 5.6))
    h, w = satmap.image.shape[:2]
    mpp = satmap.meters_per_pixel
    x0, y0 = satmap.origin
    full = (x0, x0 + w * mpp, y0 - h * mpp, y0)
    for ax, (name, centre) in zip(axes, panels):
        ax.imshow(satmap.image, extent=full, interpolation="bilinear")
        sc = ax.scatter(c[order, 0], c[order, 1], c=np.log10(np.maximum(rel[order], 1e-4)), cmap="inferno",
                        vmin=-4, vmax=0, s=2 if centre is None else 6, alpha=0.85, linewidths=0)
        ax.plot([e.x], [e.y], "x", color="cyan", ms=12, mew=2.5, label="estimate")
        if result.coarse_estimate is not None:   # refined: also the co-occurrence estimate it started from
            ce = result.coarse_estimate
            ax.plot([ce.x], [ce.y], "+", color="white", ms=10, mew=2, label="before alignment")
        if truth is not None:
            ax.plot([truth.x], [truth.y], "o", mfc="none", mec="lime", ms=12, mew=2.5, label="truth")
        if centre is not None:
            ax.set_xlim(centre.x - window_m / 2, centre.x + window_m / 2)
            ax.set_ylim(centre.y - window_m / 2, centre.y + window_m / 2)
        ax.set_title(name, fontsize=10)
        ax.set_xlabel("x east (m)")
        ax.set_ylabel("y north (m)")
    axes[-1].legend(loc="lower right", fontsize=8)
    cb = fig.colorbar(sc, ax=axes, shrink=0.8)
    cb.set_label("log10 P(L|I) / max")
    parts = [title] if title else []
    if truth is not None:
        parts.append(f"error {result.estimate.distance(truth):.2f} m")
    fig.suptitle(", ".join(parts + [f"inlier score {result.inlier_score:.1f}"]))
    _save(fig, Path(path))
    plt.close(fig)
    return len(panels)


def _along(poses: np.ndarray) -> np.ndarray:
    """Distance along a pass to each frame over its posed frames (NaN for a frame without a pose: a real
    sequence's frames outside its GPS track), so a frame without a pose adds no jump to the origin."""
    ok = np.all(np.isfinite(poses[:, :2]), axis=1)
    s = np.full(len(poses), np.nan)
    s[ok] = arc_length(poses[ok])
    return s


def plot_errors_along_route(results_dir: str | Path, queries: Sequence, frames: np.ndarray, modes,
                            path: str | Path) -> None:
    """Localization error of each mode (``localization_<mode>.npz`` in ``results_dir``) against the query's
    distance along its pass."""
    plt = _pyplot()
    s = _along(queries.poses)
    fig, ax = plt.subplots(figsize=(10, 4))
    for mode in modes:
        a, _ = load_npz(Path(results_dir) / f"localization_{mode}.npz", "localization")
        e = np.maximum(a["errors"], 1e-2)
        ax.semilogy(s[a["frames"]], e, ".-", lw=0.8, ms=4, label=f"{mode}: mean {np.nanmean(a['errors']):.2f} m")
    ax.axhline(1.0, color="grey", lw=0.6, ls="--")
    ax.set_xlabel("query position along the pass (m)")
    ax.set_ylabel("error (m)")
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    _save(fig, Path(path))
    plt.close(fig)


def plot_margins_along_route(queries: Sequence, frames: np.ndarray, margins: dict[str, np.ndarray],
                             far_m: float, path: str | Path, title: str = "") -> None:
    """Single-image margins of the truth over the best place more than ``far_m`` away, per cue, against the
    query's distance along its pass: co-occurrence cues (log-probability ratios) above, ``bev`` (a
    correlation difference) below; under the red line a look-alike wins."""
    plt = _pyplot()
    s = _along(queries.poses)[frames]
    fig, axes = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    for cue, m in margins.items():
        ax = axes[1] if cue == "bev" else axes[0]
        ax.plot(s, m, ".-", lw=0.8, ms=4, color="tab:purple" if cue == "bev" else None,
                label=f"{cue}: far place wins {int((m <= 0).sum())}x")
    axes[0].set_ylabel(f"log P(near truth) - log P(> {far_m:g} m)")
    axes[1].set_ylabel(f"NCC(near truth) - NCC(> {far_m:g} m)")
    axes[1].set_xlabel("query position along the pass (m)")
    for ax in axes:
        ax.axhline(0.0, color="red", lw=0.8)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="upper right")
    fig.suptitle(f"{title}single-image margin of the truth over the best place more than {far_m:g} m away "
                 "(below the red line: a look-alike wins)")
    _save(fig, Path(path))
    plt.close(fig)


def plot_cross_posterior(satmap: SatelliteMap, candidates: np.ndarray, posterior: np.ndarray, prior, truth,
                         estimate, path: str | Path, title: str = "") -> None:
    """A no-database posterior (:mod:`satloc.localizers.crossview`) over its prior disc: the satellite map around the
    prior (``prior``: a :class:`satloc.localizers.crossview.Prior`), the disc, the posterior's strongest positions
    (``candidates`` (K, 3), ``posterior`` (K,); every position and heading drawn as a dot, the more probable on
    top, so a position shows its strongest heading), the estimate and the truth (Pose2 or None)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.2, 5.6))
    h, w = satmap.image.shape[:2]
    mpp = satmap.meters_per_pixel
    x0, y0 = satmap.origin
    ax.imshow(satmap.image, extent=(x0, x0 + w * mpp, y0 - h * mpp, y0), interpolation="bilinear")
    p = np.asarray(posterior, np.float64)
    c = np.asarray(candidates, np.float64)
    if len(p):
        rel = p / max(p.max(), 1e-300)
        order = np.argsort(p)
        order = order[rel[order] >= 1e-4]
        sc = ax.scatter(c[order, 0], c[order, 1], c=np.log10(np.maximum(rel[order], 1e-4)), cmap="inferno",
                        vmin=-4, vmax=0, s=10, alpha=0.9, linewidths=0)
        cb = fig.colorbar(sc, ax=ax, shrink=0.8)
        cb.set_label("log10 posterior / max")
    t = np.linspace(0, 2 * np.pi, 181)
    ax.plot(prior.x + prior.radius_m * np.cos(t), prior.y + prior.radius_m * np.sin(t), "--", color="white", lw=1.2,
            label=f"prior (+-{prior.radius_m:g} m)")
    ax.plot([prior.x], [prior.y], "s", mfc="none", mec="white", ms=8, mew=1.5)
    if estimate is not None:
        ax.plot([estimate.x], [estimate.y], "x", color="cyan", ms=12, mew=2.5, label="estimate")
    if truth is not None:
        ax.plot([truth.x], [truth.y], "o", mfc="none", mec="lime", ms=12, mew=2.5, label="truth")
    r = prior.radius_m * 1.35
    ax.set_xlim(prior.x - r, prior.x + r)
    ax.set_ylim(prior.y - r, prior.y + r)
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    ax.legend(loc="lower right", fontsize=8)
    parts = [title] if title else []
    if truth is not None and estimate is not None:
        parts.append(f"error {estimate.distance(truth):.2f} m")
    ax.set_title(", ".join(parts), fontsize=10)
    _save(fig, Path(path))
    plt.close(fig)
