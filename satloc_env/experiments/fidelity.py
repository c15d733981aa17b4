"""``satloc experiment fidelity``: does the simulator predict a real road? Its default world held against the
paper's real KITTI figures and against real street imagery.

Two parts, each at ``aliasing`` 0 (the default world) and 1 (the knob at its worst, to show that it still
controls aliasing):

* **Localization.** Table I's ``kitti-city`` protocol (the paper's KITTI-City as it ran it: one pass, a frame
  every 0.77 m, a seeded random 40 % the database; :func:`satloc_env.experiments.tables.table1`) on ``city``
  and its ``residential`` protocol (a second pass, one frame a second) on ``residential``, every method, beside
  the paper's real figure (:data:`PAPER`): the ratio of the simulated mean to the real one with the ratio of the
  simulated interval's ends, and the fraction of queries beyond 10 m. A simulator that predicts the real road
  gives ratios near 1 and almost no query beyond 10 m, as KITTI did.
* **What the camera sees** (:func:`image_stats`): ORB keypoints per 620x188 grey frame (OpenCV's ORB,
  ``nfeatures`` 5000, ``fastThreshold`` 20) and the slope of the radially averaged power spectrum (log-log over
  4 to 92 cycles per frame, Hann window), medians over frames rendered every 20 steps of the autopilot's drive
  (seed 0), beside the same statistics of real street frames where they are at hand (KITTI raw frames resized
  to 620x188, e.g. ``../shared/realdata``).

With ``variety`` (a list of values of the grid generator's ``variety``,
:mod:`satloc_env.world.variety`), the image statistics are measured on each scene at each, from a copy of its
scene file with that value (``out/scenes/<scene>_variety<v>.yaml``), and ``pictures_<scene>.jpg`` shows the same
places (the 1st, middle and last rendered frame) at each, a row per value (``<scene>``: the file's stem for a
path).

Writes ``fidelity.md``, ``fidelity.csv`` and ``fidelity.json`` into ``out``; the Table I runs live in
``out/a<aliasing>/`` and are reused when run again.
"""
from __future__ import annotations

import csv
import glob
import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from satloc.config import from_dict, to_dict
from satloc.errors import ConfigError
from satloc.persist import atomic_path, header, write_json

__all__ = ["FidelityConfig", "PAPER", "image_stats", "fidelity", "orb_keypoints", "spectral_slope"]

#: the paper's real KITTI figures (Chu et al., Table I: mean error in metres), by protocol and method; the rows
#: the paper reports that this project's tables name the same way
PAPER = {
    "kitti-city": {"FAB-MAP": 1.24, "EFM": 0.87, "Ours-GO": 0.81, "Ours-full": 0.39},
    "residential": {"FAB-MAP": 2.29, "EFM": 1.18, "Ours-full": 0.42},
}
#: the scene each protocol runs on
PROTOCOL_SCENES = {"kitti-city": "city", "residential": "residential"}


@dataclass
class FidelityConfig:
    aliasing: tuple[float, ...] = (0.0, 1.0)
    protocols: tuple[str, ...] = ("kitti-city", "residential")
    # Table I's settings for the runs (ExperimentConfig fields; protocols and aliasing are set per run)
    experiment: dict = field(default_factory=lambda: {"database_frames": 600, "modes": ["go", "np", "full",
                                                                                       "full+track"]})
    images: bool = True                   # the image statistics of renders (and of real frames)
    image_scenes: tuple[str, ...] = ("city", "residential")
    reference_images: str | None = None   # a folder of real street frames (PNG/JPEG, searched recursively);
                                          # None: ../shared/realdata beside the checkout, where it is
    frames: int = 15                      # rendered frames per scene: one every 20 steps of the autopilot
    variety: tuple[float, ...] = ()       # the image statistics at each of these generator variety values
                                          # (grid scenes; empty: the scenes as they are)

    def __post_init__(self):
        bad = [p for p in self.protocols if p not in PAPER]
        if bad:
            raise ConfigError(f"fidelity protocols: unknown {bad}; expected some of {list(PAPER)}")
        if not self.aliasing or any(not 0 <= a <= 1 for a in self.aliasing):
            raise ConfigError(f"fidelity aliasing: expected values in [0, 1], got {list(self.aliasing)}")
        if any(not 0 <= v <= 1 for v in self.variety):
            raise ConfigError(f"fidelity variety: expected values in [0, 1], got {list(self.variety)}")


def orb_keypoints(gray: np.ndarray) -> int:
    """ORB keypoints (OpenCV, ``nfeatures`` 5000, ``fastThreshold`` 20) of a grey 620x188 frame."""
    return len(cv2.ORB_create(5000, fastThreshold=20).detect(gray, None))


def spectral_slope(gray: np.ndarray) -> float:
    """Slope of the radially averaged power spectrum of a grey frame (log-log, radii 4 to min(H, W) / 2 - 2
    cycles, normalised frame times a Hann window): about -2 for natural images, steeper for smoother ones."""
    g = gray.astype(np.float32)
    g = (g - g.mean()) / (g.std() + 1e-6)
    h, w = g.shape
    p = np.abs(np.fft.fftshift(np.fft.fft2(g * np.outer(np.hanning(h), np.hanning(w))))) ** 2
    yy, xx = np.indices(p.shape)
    r = np.hypot(yy - h / 2, xx - w / 2).astype(int)
    prof = np.bincount(r.ravel(), p.ravel()) / np.maximum(np.bincount(r.ravel()), 1)
    k = np.arange(len(prof))
    sel = (k >= 4) & (k <= min(h, w) // 2 - 2)
    return float(np.polyfit(np.log(k[sel]), np.log(prof[sel]), 1)[0])


def _gray(img: np.ndarray) -> np.ndarray:
    g = img if img.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(img[..., :3]), cv2.COLOR_RGB2GRAY)
    return g if g.shape == (188, 620) else cv2.resize(g, (620, 188), interpolation=cv2.INTER_AREA)


def image_stats(frames) -> dict:
    """Medians over ``frames`` (RGB or grey images, resized to 620x188) of :func:`orb_keypoints` and
    :func:`spectral_slope`."""
    grays = [_gray(f) for f in frames]
    if not grays:
        raise ConfigError("image statistics: no frames")
    return {"orb_keypoints": int(np.median([orb_keypoints(g) for g in grays])),
            "spectral_slope": round(float(np.median([spectral_slope(g) for g in grays])), 3), "frames": len(grays)}


def rendered_frames(scene: str, aliasing: float | None = None, frames: int = 15, every: int = 20) -> list:
    """Left frames of SatLoc-v0 on ``scene`` driven by its autopilot (seed 0), one every ``every`` steps."""
    import gymnasium as gym

    import satloc_env  # noqa: F401  (registers the ids)

    env = gym.make("satloc/SatLoc-v0", scene=scene, aliasing=aliasing, localizer=None)
    out = []
    try:
        env.reset(seed=0)
        for i in range(frames * every):
            obs, _, term, trunc, _ = env.step(env.unwrapped.autopilot_action())
            if i % every == every - 1:
                out.append(obs["left"])
            if term or trunc:
                break
    finally:
        env.close()
    return out


def real_frames(folder: str | os.PathLike) -> list:
    """The PNG/JPEG frames under ``folder`` (recursively) whose name lies in an ``image_02`` or ``image_03``
    folder where there are such (KITTI's colour cameras), else every image."""
    files = sorted(f for e in ("png", "jpg", "jpeg") for f in glob.glob(os.path.join(str(folder), "**", f"*.{e}"),
                                                                          recursive=True))
    cams = [f for f in files if os.sep + "image_02" + os.sep in f or os.sep + "image_03" + os.sep in f]
    out = []
    for f in cams or files:
        img = cv2.imread(f, cv2.IMREAD_COLOR)
        if img is not None:
            out.append(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
    return out


def variety_scene(scene: str, variety: float, folder: Path) -> Path:
    """A copy of the grid scene file ``scene`` (a shipped name or a path to a YAML file) with
    ``generator.variety`` set, written into ``folder`` as ``<name>_variety<v>.yaml``."""
    import yaml

    from satloc_env.world.scene import SCENES_DIR

    src = Path(scene) if str(scene).endswith((".yaml", ".yml")) else SCENES_DIR / f"{scene}.yaml"
    if not src.is_file():
        raise ConfigError(f"fidelity variety: no scene file {src}")
    data = yaml.safe_load(src.read_text())
    gen = data.get("generator") if isinstance(data, dict) else None
    if not isinstance(gen, dict) or gen.get("type", "grid") != "grid":
        raise ConfigError(f"fidelity variety: {src}: variety is a grid generator's field; this scene has none")
    name = f"{data.get('name', src.stem)}_variety{variety:g}"
    data = dict(data, name=name, generator=dict(gen, variety=float(variety)))
    folder.mkdir(parents=True, exist_ok=True)
    dst = folder / f"{name}.yaml"
    with atomic_path(dst, suffix=".yaml") as tmp:
        tmp.write_text(yaml.safe_dump(data, sort_keys=False))
    return dst


def _write_pictures(path: Path, rows: list[list]) -> None:
    """A row per list of frames: its first, middle and last frame side by side."""
    strips = []
    for frames in rows:
        pick = [frames[0], frames[len(frames) // 2], frames[-1]] if len(frames) >= 3 else list(frames)
        strips.append(np.hstack([cv2.resize(f, (620, 188)) for f in pick]))
    width = max(s.shape[1] for s in strips)
    img = np.vstack([np.pad(s, ((0, 4), (0, width - s.shape[1]), (0, 0)), constant_values=255) for s in strips])
    with atomic_path(path, suffix=".jpg") as tmp:
        cv2.imwrite(str(tmp), cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 88])


def _default_reference() -> Path | None:
    p = Path(__file__).resolve().parents[2].parent / "shared" / "realdata"
    return p if p.is_dir() else None


def protocol_rows(cfg: FidelityConfig, out: Path, progress: bool = True, log=print, runner=None) -> list[dict]:
    """Every method under each protocol of ``cfg`` at each aliasing, beside the paper's figure (see the module
    docstring)."""
    from .tables import table1

    rows = []
    for a in cfg.aliasing:
        for protocol in cfg.protocols:
            scene = PROTOCOL_SCENES[protocol]
            conf = dict(cfg.experiment, aliasing=a, protocols=[protocol])
            log(f"[fidelity] {protocol} on {scene} at aliasing {a:g}")
            got = table1(out / f"a{a:g}", (scene,), conf, progress, log, runner)
            paper = PAPER[protocol]
            for r in got:
                real = paper.get(r["method"])
                beyond = 1.0 - r["within_10m"]
                rows.append({"protocol": protocol, "scene": scene, "aliasing": a, "method": r["method"],
                             "mean_m": r["mean_m"], "ci95_low": r["ci95_low"], "ci95_high": r["ci95_high"],
                             "median_m": r["median_m"], "beyond_10m": round(beyond, 4), "queries": r["queries"],
                             "paper_m": real,
                             "ratio": None if real is None else round(r["mean_m"] / real, 3),
                             "ratio_low": None if real is None else round(r["ci95_low"] / real, 3),
                             "ratio_high": None if real is None else round(r["ci95_high"] / real, 3)})
    return rows


def fidelity(out: str | Path, config: dict | None = None, progress: bool = True, log=print, runner=None) -> dict:
    """The fidelity report (see the module docstring); returns what ``fidelity.json`` holds."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = from_dict(FidelityConfig, dict(config or {}), "fidelity config")
    images = []
    if cfg.images:
        shown: dict[str, list] = {}
        for a in cfg.aliasing:
            for scene in cfg.image_scenes:
                for v in cfg.variety or (None,):
                    path = scene if v is None else variety_scene(scene, v, out / "scenes")
                    frames = rendered_frames(str(path), a, cfg.frames)
                    s = image_stats(frames)
                    label = f"{scene} (aliasing {a:g}" + ("" if v is None else f", variety {v:g}") + ")"
                    images.append({"source": label, **s})
                    log(f"[fidelity] {label}: {s['orb_keypoints']} ORB keypoints, spectral slope "
                        f"{s['spectral_slope']:.2f} ({s['frames']} frames)")
                    if v is not None and a == cfg.aliasing[0]:
                        shown.setdefault(scene, []).append(frames)
        for scene, rows in shown.items():
            if len(rows) > 1:
                _write_pictures(out / f"pictures_{Path(scene).stem}.jpg", rows)
        ref = Path(cfg.reference_images) if cfg.reference_images else _default_reference()
        if ref is not None:
            frames = real_frames(ref)
            if frames:
                images.append({"source": f"real frames: {ref}", **image_stats(frames)})
    rows = protocol_rows(cfg, out, progress, log, runner) if cfg.protocols else []
    cols = ("protocol", "scene", "aliasing", "method", "mean_m", "ci95_low", "ci95_high", "median_m", "beyond_10m",
            "queries", "paper_m", "ratio", "ratio_low", "ratio_high")
    with atomic_path(out / "fidelity.csv", suffix=".csv") as tmp:
        with open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(cols)
            for r in rows:
                w.writerow(["" if r[c] is None else r[c] for c in cols])
    report = dict(header("fidelity"), config=to_dict(cfg), images=images, rows=rows)
    write_json(out / "fidelity.json", report)
    with atomic_path(out / "fidelity.md", suffix=".md") as tmp:
        tmp.write_text(_markdown(images, rows))
    return report


def _markdown(images: list[dict], rows: list[dict]) -> str:
    lines = []
    if images:
        lines += ["| source | ORB keypoints per 620x188 frame (median) | spectral slope (median) | frames |",
                  "|---|---|---|---|"]
        lines += [f"| {i['source']} | {i['orb_keypoints']} | {i['spectral_slope']:.2f} | {i['frames']} |" for i in images]
        lines.append("")
    for (protocol, a), part in _groups(rows):
        lines += [f"**{protocol}** on `{part[0]['scene']}`, aliasing {a:g} ({part[0]['queries']} queries):", "",
                  "| method | mean m [95 % CI] | median m | beyond 10 m | paper (real KITTI) | simulated / real [CI] |",
                  "|---|---|---|---|---|---|"]
        for r in part:
            paper = "" if r["paper_m"] is None else f"{r['paper_m']:.2f}"
            ratio = "" if r["ratio"] is None else f"{r['ratio']:.2f} [{r['ratio_low']:.2f}-{r['ratio_high']:.2f}]"
            lines.append(f"| {r['method']} | {r['mean_m']:.2f} [{r['ci95_low']:.2f}-{r['ci95_high']:.2f}] | "
                         f"{r['median_m']:.2f} | {100 * r['beyond_10m']:.0f} % | {paper} | {ratio} |")
        lines.append("")
    return "\n".join(lines)


def _groups(rows: list[dict]):
    keys = list(dict.fromkeys((r["protocol"], r["aliasing"]) for r in rows))
    return [(k, [r for r in rows if (r["protocol"], r["aliasing"]) == k]) for k in keys]
