"""``satloc experiment tune``: choose the settings that were once tuned on test runs again, on a calibration scene
that no table tests on, and report the choice with the figures behind it.

The settings (each of them was once tuned on the scenes its tables report):

* the method's ``ef_search`` (HNSW search breadth of the ground index): the smallest value of ``ef_search``
  whose mean error in ``ef_mode`` stays within ``ef_tolerance_m`` of the largest value's, with no more failures
  (a smaller breadth is faster; :func:`pick_smallest_within`);
* the tracker's global-search rule (``tracking.lock_mass``: the belief mass that locks it, below which every
  candidate is scored): the value with the lowest mean error in ``lock_mode`` (:func:`pick_lowest`);
* FAB-MAP's vocabulary size, then its SIFT contrast threshold at that size: the lowest mean error of
  ``fabmap`` (single images). FAB-MAP is trained on ``experiment.compare.fabmap_train_scene``, another
  calibration scene;
* EFM's SIFT contrast threshold (``efm.contrast_threshold``): the lowest mean error of ``efm``;
* the visual odometry's detector, then (for ``gftt``) its Lucas-Kanade window: the lowest mean translation
  error over 50 m segments (KITTI's odometry metric, :func:`satloc.tracking.vo.odometry_drift`) of the calibration
  query pass, every frame of it, against its true poses (:func:`pick_lowest_vo`).

The default calibration scene is ``calib/town_a`` (``scenes/calib/town_a.yaml``) (FAB-MAP trained on ``calib/town_b``):
scenes that Table I, Table II and the sweep never test on (they test on ``city``, ``residential`` and ``loop``), at
the default world as those are (varied streets over gentle hills, cambered roads). They are two of the scenes the
shipped FCN was trained on (``scenes/fcn_train``, the same seeds and streets on the plain world), so its features
are at their best there; the choices are
relative (one setting against another on the same features), which that does not favour.

Every figure counts a query the method does not answer as a gross failure (:func:`satloc_env.experiments.scene_run.
table_stats`). Writes ``tune.json`` (every grid point and the choices), ``tune.md`` and, per grid point, the
localization outputs under ``out/<setting>_<value>``; the recording, build and FAB-MAP trainings are stages
reused by a rerun.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from satloc.baselines.efm import EfmConfig
from satloc.baselines.fabmap import FabMapConfig
from satloc.config import from_dict, to_dict
from satloc.errors import ConfigError
from satloc.localizers.database import LocalizerConfig
from satloc.persist import write_json
from satloc.satmap import SatelliteMap
from satloc.tracking.track import TrackConfig
from satloc.tracking.vo import VOConfig

from .scene_run import (
    MODES,
    CompareConfig,
    ExperimentConfig,
    _covered,
    _stages,
    is_tracked,
    localize_and_report,
    scene_label,
    tracked_odometry,
    vo_steps,
)

#: the scenes Table I, Table II and the sweep test on: never calibration data
TEST_SCENES = ("city", "residential", "loop")
#: scenes/calib: fcn_train/town_a and town_b at the default world (varied streets over hills, cambered roads), as
#: the scenes the tables test on are; until commit 4eeedd7 the tune ran on the plain, flat fcn_train scenes
CALIBRATION_SCENE = "calib/town_a"
FABMAP_CALIBRATION_TRAIN = "calib/town_b"


def _experiment() -> ExperimentConfig:
    return ExperimentConfig(scene=CALIBRATION_SCENE, database_frames=400, modes=("full+align", "full+track+align"),
                            pictures=False, compare=CompareConfig(fabmap_train_scene=FABMAP_CALIBRATION_TRAIN))


@dataclass
class TuneConfig:
    """``satloc experiment tune``: the calibration run (``experiment``: its scene, passes and modes) and the
    grid of each setting."""

    experiment: ExperimentConfig = field(default_factory=_experiment)
    ef_search: tuple[int, ...] = (24, 32, 48, 96)
    ef_mode: str = "full+align"
    ef_tolerance_m: float = 0.05
    lock_mass: tuple[float, ...] = (0.0, 0.5, 0.9, 0.99)
    lock_mode: str = "full+track+align"
    vocabulary_size: tuple[int, ...] = (500, 1000, 2000, 5000)
    contrast_threshold: tuple[float, ...] = (0.005, 0.01, 0.04)
    efm_contrast_threshold: tuple[float, ...] = (0.0025, 0.005, 0.01, 0.04)
    vo_detector: tuple[str, ...] = ("gftt", "orb")
    vo_lk_window_px: tuple[int, ...] = (9, 15, 21)
    vo_segment_m: float = 50.0

    def __post_init__(self):
        for name in ("ef_mode", "lock_mode"):
            if getattr(self, name) not in MODES:
                raise ConfigError(f"{name}: expected one of {list(MODES)}, got {getattr(self, name)!r}")
        if "track" not in self.lock_mode.split("+"):
            raise ConfigError(f"lock_mode: expected a tracked mode (lock_mass acts on the tracker), got "
                              f"{self.lock_mode!r}")
        for name in ("ef_search", "lock_mass", "vocabulary_size", "contrast_threshold", "efm_contrast_threshold",
                     "vo_detector", "vo_lk_window_px"):
            if not getattr(self, name):
                raise ConfigError(f"{name}: expected a non-empty list of values, got []")
        if self.ef_tolerance_m < 0:
            raise ConfigError(f"ef_tolerance_m: expected >= 0, got {self.ef_tolerance_m}")
        if not self.vo_segment_m > 0:
            raise ConfigError(f"vo_segment_m: expected > 0, got {self.vo_segment_m}")
        for d in self.vo_detector:   # every VO grid point a valid VOConfig (names the field at fault)
            for w in self.vo_lk_window_px:
                VOConfig(detector=d, lk_window_px=int(w))
        for t in self.efm_contrast_threshold:
            EfmConfig(contrast_threshold=float(t))


def _merged(base: dict, over: dict) -> dict:
    """``base`` with ``over``'s keys set, nested dicts merged key by key."""
    out = dict(base)
    for k, v in over.items():
        out[k] = _merged(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


#: means closer than this (metres) are equal: the same answers can differ in the last bits of a float (lock_mass
#: at the default world gave 21.431019949 and 21.431019951 m for the same answers to a micrometre)
TIE_M = 1e-6


def pick_lowest(rows: list[dict], prefer=None) -> dict:
    """The row with the lowest ``mean_m``; among means equal to within :data:`TIE_M` the one whose ``value`` is
    ``prefer`` (the current default: a tie does not change it), else the first listed."""
    if not rows:
        raise ValueError("pick_lowest: no rows")
    best = min(r["mean_m"] for r in rows)
    tied = [r for r in rows if r["mean_m"] <= best + TIE_M]
    return next((r for r in tied if r["value"] == prefer), tied[0])


def pick_smallest_within(rows: list[dict], tolerance_m: float) -> dict:
    """The row of the smallest ``value`` whose ``mean_m`` is within ``tolerance_m`` of the largest value's and
    whose ``failure_rate`` is no higher than it (the largest value is the reference a cheaper one must match)."""
    if not rows:
        raise ValueError("pick_smallest_within: no rows")
    ref = max(rows, key=lambda r: r["value"])
    ok = [r for r in rows if r["mean_m"] <= ref["mean_m"] + tolerance_m and r["failure_rate"] <= ref["failure_rate"]]
    return min(ok, key=lambda r: r["value"])


def pick_lowest_vo(rows: list[dict], prefer=None) -> dict:
    """The VO row with the lowest ``trans_pct`` (mean translation error over the segments); fewer failed steps
    break a tie, then ``prefer`` (the current default), then the first listed."""
    if not rows:
        raise ValueError("pick_lowest_vo: no rows")
    best = min((r["trans_pct"], r["failed_steps"]) for r in rows)
    tied = [r for r in rows if (r["trans_pct"], r["failed_steps"]) <= best]
    return next((r for r in tied if r["value"] == prefer), tied[0])


def _vo_row(setting: str, value, drift: dict, segment_m: float) -> dict:
    seg = drift["segments"].get(f"{segment_m:g}")
    if seg is None:
        raise ConfigError(f"tune config: vo_segment_m: the calibration query pass ({drift['distance_m']} m) is "
                          f"shorter than one {segment_m:g} m segment")
    return {"setting": setting, "value": value, "trans_pct": float(seg["trans_pct"]),
            "rot_deg_per_100m": float(seg["rot_deg_per_100m"]), "segments": int(seg["n"]),
            "failed_steps": int(drift["failed_steps"]), "frames": int(drift["frames"]),
            "distance_m": float(drift["distance_m"])}


def _row(setting: str, value, s: dict) -> dict:
    keep = ("mean_m", "median_m", "within_1m", "failure_rate", "ci95_low", "ci95_high")
    spq = s.get("s_per_query")
    if spq is None:
        spq = 1.0 / s["queries_per_s"] if s.get("queries_per_s") else float("nan")
    return {"setting": setting, "value": value, **{k: float(s[k]) for k in keep}, "s_per_query": float(spq),
            "queries": int(s["queries"])}


def tune(out: str | Path, config: dict | None = None, progress: bool = True, log=print) -> dict:
    """Run the grids of :class:`TuneConfig` (from ``config``) on its calibration run into ``out``; returns
    ``{"rows": [...], "chosen": {setting: value}, "calibrated_on": ...}`` (also ``tune.json``, ``tune.md``)."""
    from .tables import run_baseline

    out = Path(out)
    config = dict(config or {})
    if isinstance(config.get("experiment"), dict):   # over the calibration defaults, not ExperimentConfig's
        config["experiment"] = _merged(to_dict(_experiment()), config["experiment"])
    tc = from_dict(TuneConfig, config, "tune config")
    cfg = tc.experiment
    for name, scene in (("experiment.scene", cfg.scene),
                        ("experiment.compare.fabmap_train_scene", cfg.compare.train_scene(cfg.scene))):
        if scene_label(scene) in TEST_SCENES:
            raise ConfigError(f"tune config: {name}: {scene!r} is a scene the tables test on ({', '.join(TEST_SCENES)}); "
                              "calibrate on another (default: calib/town_a, FAB-MAP trained on calib/town_b)")
    cfg = dataclasses.replace(cfg, modes=tuple(dict.fromkeys((tc.ef_mode, tc.lock_mode))))
    track = dict(cfg.localizer.get("tracking", {}))
    for v in tc.ef_search:   # before any work: every grid point a valid localizer
        for m in tc.lock_mass:
            from_dict(LocalizerConfig, dict(cfg.localizer, ef_search=int(v), tracking=dict(track, lock_mass=float(m))),
                      "tune config: experiment localizer")
    for v in tc.vocabulary_size:
        for t in tc.contrast_threshold:
            dataclasses.replace(cfg.compare.fabmap, vocabulary_size=int(v), contrast_threshold=float(t))
    db, q, bdir, _ = _stages(cfg, out, progress, log)
    sel = _covered(cfg, db, q)
    satmap = SatelliteMap.load(out / "rec" / "map")
    odo = tracked_odometry(cfg, q, sel, out / "odometry_visual.npz") if is_tracked(cfg) else None
    rows, chosen = [], {}

    def ours(setting: str, value, mode: str, localizer: dict) -> dict:
        c = dataclasses.replace(cfg, modes=(mode,), localizer=localizer)
        d = out / f"{setting}_{value}"
        d.mkdir(parents=True, exist_ok=True)
        s = localize_and_report(c, f"{cfg.scene} {setting}={value}", db, q, sel, bdir, satmap, d,
                                {"scene": cfg.scene, "config": to_dict(c)}, {}, progress, log, odo)
        return _row(setting, value, s["modes"][mode])

    grid = [ours("ef_search", int(v), tc.ef_mode, dict(cfg.localizer, ef_search=int(v))) for v in tc.ef_search]
    chosen["ef_search"] = pick_smallest_within(grid, tc.ef_tolerance_m)["value"]
    rows += grid
    grid = [ours("lock_mass", float(v), tc.lock_mode,
                 dict(cfg.localizer, ef_search=chosen["ef_search"], tracking=dict(track, lock_mass=float(v))))
            for v in tc.lock_mass]
    chosen["lock_mass"] = pick_lowest(grid, TrackConfig().lock_mass)["value"]
    rows += grid

    def fabmap(setting: str, value, **change) -> dict:
        cc = dataclasses.replace(cfg.compare, fabmap=dataclasses.replace(cfg.compare.fabmap, **change))
        d = out / f"fabmap_{setting}_{value}"
        d.mkdir(parents=True, exist_ok=True)
        return _row(f"fabmap.{setting}", value, run_baseline("fabmap", cc, cfg.scene, db, q, sel, d, progress, log))

    grid = [fabmap("vocabulary_size", int(v), vocabulary_size=int(v)) for v in tc.vocabulary_size]
    chosen["fabmap.vocabulary_size"] = pick_lowest(grid, FabMapConfig().vocabulary_size)["value"]
    rows += grid
    grid = [fabmap("contrast_threshold", float(v), vocabulary_size=chosen["fabmap.vocabulary_size"],
                   contrast_threshold=float(v)) for v in tc.contrast_threshold]
    chosen["fabmap.contrast_threshold"] = pick_lowest(grid, FabMapConfig().contrast_threshold)["value"]
    rows += grid

    def efm(value: float) -> dict:
        cc = dataclasses.replace(cfg.compare, efm=dataclasses.replace(cfg.compare.efm, contrast_threshold=value))
        d = out / f"efm_contrast_threshold_{value}"
        d.mkdir(parents=True, exist_ok=True)
        return _row("efm.contrast_threshold", value, run_baseline("efm", cc, cfg.scene, db, q, sel, d, progress, log))

    grid = [efm(float(v)) for v in tc.efm_contrast_threshold]
    chosen["efm.contrast_threshold"] = pick_lowest(grid, EfmConfig().contrast_threshold)["value"]
    rows += grid
    chosen.update(_tune_vo(tc, q, out, vo_rows := [], progress))
    calibrated_on = (f"{cfg.scene} (revisit, {len(sel)} queries, {len(db)} database frames); FAB-MAP trained on "
                     f"{cfg.compare.train_scene(cfg.scene)}")
    res = {"format": "tune", "calibrated_on": calibrated_on, "chosen": chosen, "rows": rows, "vo_rows": vo_rows,
           "config": to_dict(tc)}
    write_json(out / "tune.json", res)
    (out / "tune.md").write_text(tune_markdown(res))
    return res


def _tune_vo(tc: TuneConfig, q, out: Path, rows: list, progress: bool) -> dict:
    """The odometry's grid on every frame of the calibration query pass ``q`` (appended to ``rows``): the
    detector at the default window, then the window at the chosen detector (``gftt`` only: ORB has no
    window); each run cached in ``out/vo_<setting>_<value>.npz`` (:func:`vo_steps`), a configuration met twice
    (the default window in both grids) measured once."""
    import json

    from satloc.tracking.vo import odometry_drift

    measured: dict = {}   # configuration -> its odometry

    def run(setting: str, value, config: VOConfig) -> dict:
        key = json.dumps(to_dict(config), sort_keys=True)
        if key not in measured:
            measured[key] = vo_steps(q, out / f"vo_{setting}_{value}.npz", config, progress)
        drift = odometry_drift(measured[key], q.poses, (tc.vo_segment_m,))
        return _vo_row(f"vo.{setting}", value, drift, tc.vo_segment_m)

    base = VOConfig()
    grid = [run("detector", d, VOConfig(detector=d)) for d in tc.vo_detector]
    chosen = {"vo.detector": pick_lowest_vo(grid, base.detector)["value"]}
    rows += grid
    if chosen["vo.detector"] == "gftt":
        grid = [run("lk_window_px", int(w), VOConfig(lk_window_px=int(w))) for w in tc.vo_lk_window_px]
        chosen["vo.lk_window_px"] = pick_lowest_vo(grid, base.lk_window_px)["value"]
        rows += grid
    return chosen


def tune_markdown(res: dict) -> str:
    """``tune.md``: one table of every grid point, the chosen ones in bold, and the calibration data."""
    lines = [f"Calibrated on {res['calibrated_on']}.", "",
             "| setting | value | mean m [95 % CI] | median m | within 1 m | failed | s per query |",
             "|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        v = f"**{r['value']}**" if res["chosen"].get(r["setting"]) == r["value"] else f"{r['value']}"
        lines.append(f"| {r['setting']} | {v} | {r['mean_m']:.2f} [{r['ci95_low']:.2f}-{r['ci95_high']:.2f}] | "
                     f"{r['median_m']:.2f} | {100 * r['within_1m']:.0f} % | {100 * r['failure_rate']:.0f} % | "
                     f"{r['s_per_query']:.3f} |")
    if res.get("vo_rows"):
        r0 = res["vo_rows"][0]
        lines += ["", (f"Visual odometry on every frame of the calibration query pass ({r0['frames']} frames, "
                       f"{r0['distance_m']:.0f} m), against its true poses:"), "",
                  "| setting | value | translation error % | heading deg / 100 m | segments | failed steps |",
                  "|---|---|---|---|---|---|"]
        for r in res["vo_rows"]:
            v = f"**{r['value']}**" if res["chosen"].get(r["setting"]) == r["value"] else f"{r['value']}"
            lines.append(f"| {r['setting']} | {v} | {r['trans_pct']:.3f} | {r['rot_deg_per_100m']:.3f} | "
                         f"{r['segments']} | {r['failed_steps']} |")
    return "\n".join(lines) + "\n"


__all__ = [
    "CALIBRATION_SCENE",
    "FABMAP_CALIBRATION_TRAIN",
    "TEST_SCENES",
    "TuneConfig",
    "pick_lowest",
    "pick_lowest_vo",
    "pick_smallest_within",
    "tune",
    "tune_markdown",
]
