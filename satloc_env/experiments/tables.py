"""The comparison harness: the method's modes and the published baselines on the same split, in one run.

Every method reads the same database and query :class:`satloc.sequence.Sequence` objects and localizes the
same query frames in the same process, one method after the other:

* the method's modes (Ours-GO, Ours-NP, Ours-full, + BEV align, + track, ...) through
  :func:`satloc_env.experiments.scene_run.localize_and_report` (``localization_<mode>.npz``);
* FAB-MAP (:class:`satloc.baselines.FabMap`) and EFM (:class:`satloc.baselines.Efm`), single image, each
  query's left image: ``baseline_<name>.npz`` with the same arrays (frames, estimates, truth, errors,
  inlier_score, inlier);
* ``fabmap+seq`` ("FAB-MAP + seq"): the same FAB-MAP over the query stream with the paper's sequential
  prior (the last posterior moved to the places within ``fabmap_motion_window`` database places; by default
  the median query step over the median place spacing, rounded up, + 1: :func:`fabmap_motion_window`), the
  baseline's counterpart of the method's tracked rows.

FAB-MAP's vocabulary and Chow-Liu tree are trained on frames disjoint from the test scene: the database pass
(route, lane -1.75 m, no occluders, reference appearance) of *another scene* (``fabmap_train_scene``; default
``residential`` when testing on ``city`` and ``city`` otherwise), ``fabmap_train_frames`` frames every
``fabmap_train_spacing_m`` metres. The training recording and the trained model are a stage of the
experiment folder (``fabmap/``, stamped by ``fabmap_stage.json``, reused on rerun).

Time per query is wall time of the query loop divided by the number of queries (frame reading included, for
every method; the method's one-off localizer set-up and the baselines' database indexing are not included and
are reported separately).

:func:`table2` (``satloc experiment table2``) measures outside-the-map detection on ``loop``;
:func:`sweep` (``satloc experiment sweep``) runs every method over aliasing x occlusion x appearance x satellite
gap; :func:`gap_curve` (``satloc experiment gap``) over the satellite gap alone.
Table I's protocols are in :func:`table1`.
"""
from __future__ import annotations

import csv
import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from satloc.baselines import FabMap
from satloc.config import from_dict, to_dict
from satloc.errors import ConfigError
from satloc.evaluation.metrics import ci_method, pr_curve, precision_recall, precision_recall_ci, select_threshold
from satloc.persist import atomic_path, header, load_npz, read_json, write_json
from satloc.satmap import SatelliteMap
from satloc.sequence import Sequence
from satloc_env.envs.record import (
    PassConfig,
    RecordConfig,
    check_passes,
    make_env,
    pass_routes,
    record_pass,
    record_stamp,
)
from satloc_env.world.capture import DEFAULT_GAP
from satloc_env.world.scene import load_scene

from .cross_area import CROSS_NAMES, cross_area, cross_area_rows, write_cross_area
from .grading import REFERENCE_NAMES
from .scale import Runner, Unit
from .scene_run import (  # noqa: F401
    BASELINE_NAMES,
    METHOD_NAMES,
    MODES,
    SECOND_PASS_SEED,
    CompareConfig,
    ExperimentConfig,
    _covered,
    _stage_done,
    _stages,
    _stamp,
    build_and_learn,
    check_recordings,
    covered_queries,
    dense_pass,
    earlier_rows,
    is_tracked,
    localize_and_report,
    markdown_table,
    mode_config,
    record_config,
    scene_label,
    scene_labels,
    spaced_frames,
    table_stats,
    tracked_odometry,
    write_rows_csv,
)


def method_name(method: str, result: dict | None = None) -> str:
    """Display name of a row: a mode of :data:`satloc_env.experiments.scene_run.METHOD_NAMES`, a baseline, a row
    of the cross-area protocol, a reference localizer, or (from its ``result``'s ``name``) a user's localizer."""
    if result is not None and result.get("name"):
        return result["name"]
    return (BASELINE_NAMES.get(method) or CROSS_NAMES.get(method) or REFERENCE_NAMES.get(method)
            or METHOD_NAMES[method])


def trained_fabmap(cc: CompareConfig, test_scene: str, out: Path, progress: bool = True, log=print) -> Path:
    """Train FAB-MAP (vocabulary, Chow-Liu tree) on another scene's database pass into ``out/fabmap`` unless
    the stage is there for the same configuration; returns the path of the trained model (``fabmap.npz``)."""
    train_scene = cc.train_scene(test_scene)
    if scene_label(train_scene) == scene_label(test_scene):
        raise ConfigError(f"fabmap_train_scene: {train_scene!r} is the test scene; FAB-MAP's training images "
                          "must be disjoint from the test images (give another scene)")
    d = Path(out) / "fabmap"
    from satloc_env.envs.auto_localizer import cache_key

    p = PassConfig(spacing_m=cc.fabmap_train_spacing_m, max_frames=cc.fabmap_train_frames, depth=False)
    stamp = {"train_scene": train_scene, "frames": cc.fabmap_train_frames, "spacing_m": cc.fabmap_train_spacing_m,
             "fabmap": to_dict(cc.fabmap), "scene_sha256": cache_key(train_scene, None)["scene_sha256"],
             **{k: v for k, v in to_dict(p, stamp=True).items()   # drift and attitude: since they existed
                if k in ("wander_m", "speed_wander", "attitude")}}
    model = d / "fabmap.npz"
    if _stage_done(Path(out) / "fabmap_stage.json", stamp) and model.is_file():
        return model
    log(f"[{test_scene}] training FAB-MAP on {cc.fabmap_train_frames} frames of {train_scene!r}")
    env = make_env(scene=train_scene, resolution="half", depth=False, labels=False, localizer=None)
    try:
        env.reset(seed=0)
        train = record_pass(env, p, env.scene.spec.database_route, d / "train", "fabmap_train", progress,
                            {"source": "satloc_env", "scene": env.scene.name})
    finally:
        env.close()
    fm = FabMap.train(train, cc.fabmap, progress)
    fm.save(model)
    _stamp(Path(out) / "fabmap_stage.json", stamp, training_images=len(train))
    return model


def uses_fabmap(cc: CompareConfig) -> bool:
    """Whether a baseline of ``cc`` is FAB-MAP (so needs its trained model)."""
    return any(b.startswith("fabmap") for b in cc.baselines)


def _fabmap_unit(cc: CompareConfig, test_scene: str, out: Path, progress: bool = True, log=print) -> None:
    """FAB-MAP's training stage of ``out`` (:func:`trained_fabmap`) as a unit of its own, for configurations
    that use it: the units after it that share it only read it (the model stays on disk)."""
    trained_fabmap(cc, test_scene, out, progress, log)


def _stages_unit(cfg: ExperimentConfig, out: Path, progress: bool = True, log=print) -> dict:
    """An experiment folder's recording, build and projections (:func:`satloc_env.experiments.scene_run._stages`, each
    skipped when done) as a unit; returns the stage times."""
    return _stages(cfg, out, progress, log)[3]


def fabmap_motion_window(db_poses: np.ndarray, query_poses: np.ndarray) -> int:
    """FAB-MAP's motion window in database places for a query stream: the median step between consecutive
    queries over the median spacing of consecutive database places, rounded up, plus one (so that the place
    reached after a typical step, and its neighbour, are adjacent to the previous one)."""
    def steps(p):
        p = np.asarray(p, np.float64)[:, :2]
        d = np.hypot(*np.diff(p, axis=0).T)
        d = d[np.isfinite(d) & (d > 0)]
        return float(np.median(d)) if len(d) else float("nan")

    place, step = steps(db_poses), steps(query_poses)
    if not (np.isfinite(place) and np.isfinite(step)):
        return 1
    return int(math.ceil(step / place)) + 1


def run_baseline(name: str, cc: CompareConfig, test_scene: str, db: Sequence, q: Sequence, sel: np.ndarray,
                 out: Path, progress: bool = True, log=print, fabmap_dir: Path | None = None,
                 satmap: SatelliteMap | None = None) -> dict:
    """Build baseline ``name`` on ``db`` (every ``cc.database_step``-th frame of it), localize the frames ``sel``
    of ``q``; writes ``baseline_<name>.npz``
    and returns its summary (with ``errors``, ``inlier_score``). FAB-MAP's training stage lives in
    ``fabmap_dir`` (default ``out``)."""
    from satloc.baselines import EfmLocalizer, FabMapLocalizer
    from satloc.localizers.interface import Context

    from .grading import run_graded

    if cc.database_step > 1:
        db = db.view(np.arange(0, len(db), cc.database_step))
    meta: dict = {"baseline": name}
    if name.startswith("fabmap"):
        window = None
        if name == "fabmap+seq":   # the paper's motion model: each frame's prior is the last posterior, moved
            window = cc.fabmap_motion_window
            if window is None:
                window = fabmap_motion_window(db.poses, q.poses[sel])
            meta["motion_window"] = int(window)
        loc = FabMapLocalizer(trained_fabmap(cc, test_scene, Path(fabmap_dir or out), progress, log),
                              sequential=name == "fabmap+seq", motion_window=window, progress=progress,
                              name=BASELINE_NAMES[name])
    else:
        loc = EfmLocalizer(cc.efm, progress)
    # through the common interface, graded as every method is; the database indexing is reset(context)'s time
    s, run = run_graded(loc, name, BASELINE_NAMES[name], Context(q.camera, satmap, seed=0, database=db,
                                                                 place=test_scene),
                        q, sel, None, [None] * len(sel), Path(out), db.poses, test_scene, progress,
                        log=lambda m: None, meta=meta, stem="baseline")
    s.update(index_s=round(run.reset_s, 2))
    log(f"[{test_scene}] {BASELINE_NAMES[name]:9s} mean {s['mean_m']:.2f} m (std {s['std_m']:.2f}), median "
        f"{s['median_m']:.2f} m, {100 * s['within_1m']:.0f} % within 1 m, {s['s_per_query']:.3f} s per query")
    return s


def compare(cfg: ExperimentConfig, cc: CompareConfig, label: str, db: Sequence, q: Sequence, sel: np.ndarray,
            bdir: Path, satmap: SatelliteMap, out: Path, head: dict, times: dict, progress: bool = True,
            log=print, fabmap_dir: Path | None = None, odometry: np.ndarray | None = None) -> dict:
    """Every method on one split: the modes of ``cfg`` (:func:`localize_and_report`, which writes
    ``summary.json``) then the baselines of ``cc``. Returns ``{method: summary}`` in that order; each summary
    has ``mean_m, std_m, median_m, within_1m, within_10m, s_per_query``, and ``errors`` and ``inlier_score``
    (arrays over ``sel``). FAB-MAP's trained model is a stage of ``fabmap_dir`` (default ``out``). Also
    writes ``compare.json`` (the summaries without the arrays). ``odometry``: the tracked modes' (default: of
    ``q`` itself, :func:`satloc_env.experiments.scene_run.tracked_odometry`)."""
    out = Path(out)
    s = localize_and_report(cfg, label, db, q, sel, bdir, satmap, out, head, times, progress, log, odometry)
    res: dict[str, dict] = {}
    for mode in cfg.modes:
        a, _ = load_npz(out / f"localization_{mode}.npz", "localization")
        m = dict(s["modes"][mode])
        m["s_per_query"] = 1.0 / m["queries_per_s"] if m.get("queries_per_s") else float("nan")
        m.update(errors=a["errors"], inlier_score=np.where(np.isfinite(a["errors"]), a["inlier_score"], np.nan))
        res[mode] = m
    for b in cc.baselines:
        res[b] = run_baseline(b, cc, cfg.scene, db, q, sel, out, progress, log, fabmap_dir, satmap)
    for key, m in s.get("localizers", {}).items():   # the reference floors and the user's localizers
        a, _ = load_npz(out / f"localization_{key}.npz", "localization")
        res[key] = dict(m, errors=a["errors"], inlier_score=np.where(np.isfinite(a["errors"]), a["inlier_score"],
                                                                     np.nan))
    write_json(out / "compare.json", {"format": "compare", "head": head, "frames": [int(i) for i in sel],
                                      "methods": {k: _plain(v) for k, v in res.items()}})
    return res


def _plain(s: dict) -> dict:
    return {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in s.items()
            if not isinstance(v, np.ndarray)}


# --- Table II: queries outside the map ---------------------------------------------------------------------------

@dataclass
class Table2Config:
    """``satloc experiment table2``: on ``scene`` (a ring ``inside_route`` driven by the database, a
    ``outside_route`` that leaves it) the database pass, a revisit of the ring and a pass on the branch."""

    scene: str = "loop"
    inside_route: str = "main"
    outside_route: str = "branch"
    experiment: ExperimentConfig = field(default_factory=lambda: ExperimentConfig(scene="loop"))  # its
    # ``compare`` configures the baselines; its ``protocols`` are not used here
    outside_frames: int | None = None     # branch queries (None: the whole branch)
    radius_m: float = 10.0                # a true positive is declared inside, inside and within this
    rule: str = "max_f1"                  # satloc.evaluation.metrics.select_threshold's rule
    min_precision: float = 0.9            # rule "recall_at_precision"
    # calibration: a revisit of a ring and a branch pass (other seeds for occluders, appearance and drift,
    # queries every calibration_spacing_m) at another place: ``calibration_scene``'s own ring and branch (routes
    # of the same names) against its own map; None: the test scene's (nearer than ``radius_m`` to the test
    # queries: the same places). Each method's threshold is picked there and frozen for the test
    calibration_scene: str | None = "loop_calib"
    calibration_seeds: tuple[int, int] = (3, 4)
    calibration_spacing_m: float = 7.0

    def __post_init__(self):
        if self.rule not in ("max_f1", "recall_at_precision"):
            raise ConfigError(f"rule: expected 'max_f1' or 'recall_at_precision', got {self.rule!r}")
        if self.radius_m <= 0:
            raise ConfigError(f"radius_m: expected > 0, got {self.radius_m}")
        if len(self.calibration_seeds) != 2 or set(self.calibration_seeds) & {0, 1, 2}:
            raise ConfigError(f"calibration_seeds: expected two seeds other than the database (0) and test "
                              f"passes' (1, 2), got {list(self.calibration_seeds)}")
        if self.calibration_spacing_m <= 0:
            raise ConfigError(f"calibration_spacing_m: expected > 0, got {self.calibration_spacing_m}")
        if self.calibration_scene is not None and scene_label(self.calibration_scene) == scene_label(self.scene):
            raise ConfigError(f"calibration_scene: {self.calibration_scene!r} is the test scene; give another "
                              "place, or null for calibration passes on the test scene")

    @property
    def separate_calibration(self) -> bool:
        """Whether the calibration passes drive another scene (``calibration_scene``) than the test."""
        return self.calibration_scene is not None


def operating_point(errors, scores, inside, rule: str = "max_f1", min_precision: float = 0.9,
                    radius_m: float = 10.0) -> dict:
    """One method's Table II row: its PR curve over the queries (a true positive is declared inside, truly
    ``inside`` and within ``radius_m``), the threshold picked by :func:`satloc.evaluation.metrics.select_threshold`'s
    ``rule`` and the counts at it (:func:`satloc.evaluation.metrics.precision_recall`): ``precision, recall, threshold,
    tp, declared, positives, curve``."""
    curve = pr_curve(errors, scores, inside, radius_m)
    pick = select_threshold(curve, rule, min_precision)
    pr = precision_recall(errors, scores, pick["threshold"], inside, radius_m)
    return {"precision": pr["precision"], "recall": pr["recall"], "threshold": pick["threshold"], "tp": pr["tp"],
            "declared": pr["declared"], "positives": pr["positives"], "rule": rule, "curve": curve}


def _table2_recording(t2: Table2Config, calibration: bool = False
                      ) -> tuple[RecordConfig, dict[str, PassConfig], dict]:
    """Table II's recordings of one scene: the database pass of the ring and the query passes. The test
    scene's (``calibration`` False): ``inside`` (a revisit of the ring, the recording's query pass) and
    ``outside`` (the branch), with ``calib_inside`` and ``calib_outside`` (other seeds and spacing) when the
    calibration drives the test scene too; ``calibration_scene``'s (``calibration`` True): ``calib_inside``
    (the recording's query pass) and ``calib_outside`` against its own database pass. Checks that every pass
    is drivable; returns the recording of the database and its query pass, the other passes by name and the
    stage's stamp."""
    e = t2.experiment
    wander = {"wander_m": e.wander_m, "speed_wander": e.speed_wander}
    scene_name = t2.calibration_scene if calibration else t2.scene

    def extra(route, seed, spacing, frames):
        return dense_pass(e, PassConfig(route=route, lane_offset_m=e.query_lane_m, spacing_m=spacing,
                                        occlusion=e.occlusion, appearance=e.appearance, change=e.change,
                                        seed=seed, max_frames=frames, **wander))

    cs, cb = t2.calibration_seeds
    calib = {"calib_inside": extra(t2.inside_route, cs, t2.calibration_spacing_m, e.query_frames),
             "calib_outside": extra(t2.outside_route, cb, t2.calibration_spacing_m, t2.outside_frames)}
    if calibration:
        query, more = calib.pop("calib_inside"), calib
    else:
        query = extra(t2.inside_route, 1, e.query_spacing_m, e.query_frames)
        more = {"outside": extra(t2.outside_route, 2, e.query_spacing_m, t2.outside_frames)}
        if not t2.separate_calibration:
            more.update(calib)
    rec = RecordConfig(scene=scene_name, aliasing=e.aliasing, satellite_gap=e.satellite_gap,
                       database=PassConfig(route=t2.inside_route, max_frames=e.database_frames, **wander),
                       query=query)
    scene = load_scene(scene_name, e.aliasing, e.satellite_gap)   # before any work: every pass drivable
    check_passes(scene, pass_routes(scene, rec) + [(p.route, p) for p in more.values()], rec.speed_mps,
                 f"scene {scene_name!r}")
    from satloc_env.envs.auto_localizer import cache_key

    rc = dict(record_stamp(rec), scene_sha256=cache_key(scene_name, e.aliasing)["scene_sha256"],
              **{name: to_dict(p, stamp=True) for name, p in more.items()})
    return rec, more, rc


def _record_table2_pass(rec: RecordConfig, name: str, p: PassConfig | None, out: Path, rc: dict,
                        progress: bool = True, log=print) -> None:
    """One recording of Table II into ``out/rec``: with ``p`` None the database and query passes of ``rec``
    (:func:`satloc_env.envs.record.record_passes`), else the pass ``p`` into ``out/rec/<name>`` with an environment
    of its own (the same frames as one environment reset with each pass's seed). Each finished recording is
    stamped (``out/record_<name>.json``, for Table II's recording configuration ``rc``), so that a rerun after
    a failure elsewhere in its batch (another recording, FAB-MAP's training) skips it."""
    stamp = out / f"record_{name}.json"
    if _stage_done(stamp, rc) and (out / "rec" / name / "sequence.json").is_file():
        log(f"[table2] the {name} recording of an earlier run is reused")
        return
    if p is None:
        from satloc_env.envs.record import record_passes

        record_passes(rec, out / "rec", progress)
    else:
        env = make_env(scene=rec.scene, resolution=rec.resolution, aliasing=rec.aliasing, speed_mps=rec.speed_mps,
                       satellite_gap=rec.satellite_gap, depth=True, labels=False, localizer=None)
        try:
            env.reset(seed=p.seed)
            record_pass(env, p, p.route, out / "rec" / name, name, progress,
                        {"source": "satloc_env", "scene": env.scene.name})
        finally:
            env.close()
    _stamp(stamp, rc)


#: Table II's query passes: the test revisit of the ring and the branch pass, their calibration counterparts
TABLE2_PARTS = ("inside", "outside", "calib_inside", "calib_outside")


def _table2_build(t2: Table2Config, e: ExperimentConfig, out: Path, rc: dict, warm: bool, progress: bool = True,
                  log=print) -> dict:
    """Table II's build on the database pass recorded in ``out`` (``rc``: the recording's stamp; ``e.scene``
    its scene) and (``warm``: for parts running at the same time) the localizers' satellite tables cached in
    it, so that the parts only read them. Returns the stage times."""
    db = Sequence.load(out / "rec" / "database")
    bdir, times = build_and_learn(e, e.scene, db, out / "rec" / "map", out, {"record": rc}, progress, log)
    if warm:
        from satloc.pipeline import load_localizer

        first = {}
        for m in e.modes:
            first.setdefault(m.split("+")[0], m)
        for base, m in first.items():
            if base != "go":   # go needs no satellite table
                load_localizer(bdir, mode_config(e, m), progress=progress)
    return times


def _part_source(t2: Table2Config, out: Path, part: str) -> tuple[Path, str]:
    """Where a part of Table II (:data:`TABLE2_PARTS`) was recorded: the folder of its scene's recording and
    build (``out``, or ``out/calibration`` for the calibration parts on ``calibration_scene``), and its pass."""
    if part.startswith("calib") and t2.separate_calibration:
        return out / "calibration", "query" if part == "calib_inside" else part
    return out, "query" if part == "inside" else part


def _calibration_experiment(t2: Table2Config, e: ExperimentConfig) -> ExperimentConfig:
    """The experiment on ``calibration_scene``: the test's settings, and the test's FAB-MAP model (trained for
    the test scene, shared)."""
    return dataclasses.replace(e, scene=t2.calibration_scene, compare=dataclasses.replace(
        e.compare, fabmap_train_scene=e.compare.train_scene(t2.scene)))


def _table2_part(t2: Table2Config, e: ExperimentConfig, out: Path, part: str, times: dict, progress: bool = True,
                 log=print) -> tuple[np.ndarray, dict, np.ndarray]:
    """One query pass of Table II (:data:`TABLE2_PARTS`) against its scene's build (:func:`_part_source`),
    in ``out/<part>``: which of its queries are inside the map, :func:`compare`'s results and the queries'
    true positions."""
    src, name = _part_source(t2, out, part)
    scene = t2.calibration_scene if src != out else t2.scene
    if src != out:
        e = _calibration_experiment(t2, e)
    db = Sequence.load(src / "rec" / "database")
    q = Sequence.load(src / "rec" / name)
    spacing = e.query_spacing_m if part in ("inside", "outside") else t2.calibration_spacing_m
    sel = spaced_frames(q, spacing, t2.outside_frames if "outside" in part else e.query_frames)
    inside = np.isin(sel, covered_queries(db, q, e.coverage_m))
    (out / part).mkdir(exist_ok=True)
    res = compare(e, e.compare, scene, db, q, sel, src / "build", SatelliteMap.load(src / "rec" / "map"), out / part,
                  {"scene": scene, "part": part}, times, progress, log, fabmap_dir=out)
    return inside, res, np.asarray(q.poses, np.float64)[sel, :2]


def nearest_distance(a: np.ndarray, b: np.ndarray) -> float:
    """The smallest distance between a point of ``a`` (N, 2) and a point of ``b`` (M, 2) (NaN rows ignored)."""
    from scipy.spatial import cKDTree

    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    a, b = a[np.all(np.isfinite(a), axis=1)], b[np.all(np.isfinite(b), axis=1)]
    if not len(a) or not len(b):
        return float("nan")
    return float(cKDTree(b).query(a)[0].min())


def table2(out: str | Path, config: dict | None = None, progress: bool = True, log=print,
           runner: Runner | None = None) -> list[dict]:
    """Outside-the-map detection (the paper's Table II), calibrated on data disjoint from the test.

    Records (stage-stamped) the database pass of ``inside_route`` and four query passes: for the test a
    revisit of the ring (the experiment's query lane, appearance and occluders) and a pass on
    ``outside_route``; for calibration the same two with other seeds and another spacing
    (``calibration_seeds``, ``calibration_spacing_m``) on ``calibration_scene`` (another place, recorded, built
    and learned in ``out/calibration``) or, with ``calibration_scene`` None, on the test scene (the nearest
    distance between a calibration and a test query is then reported: ``calibration_nearest_m``). Runs
    :func:`compare` on each pass against its scene's build; a
    query is *inside* when its true position lies within ``experiment.coverage_m`` of the database path (so
    branch frames where the branch rejoins the ring are inside). Each method's threshold is picked on its PR
    curve over the **calibration** queries (:func:`operating_point`) and frozen; precision and recall are
    those of the **test** queries at it, with 95 % bootstrap intervals. The oracle (the rule applied to the
    test queries' own curve) is reported beside it, labelled. Writes ``table2.csv`` (:data:`TABLE2_COLUMNS`),
    ``table2.md``, ``table2.json`` and ``pr_curves.png`` (the test curves, the frozen operating points) into
    ``out``; returns the rows.

    Units (``runner``, :mod:`satloc_env.experiments.scale`): the recordings (:func:`_record_table2_pass`: the database and
    revisit passes, and each other pass) beside FAB-MAP's training, then the build (:func:`_table2_build`),
    then the four passes (:data:`TABLE2_PARTS`), each compared in its own folder."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t2 = from_dict(Table2Config, dict(config or {}), "table2 config")
    e = t2.experiment
    if scene_label(e.scene) != scene_label(t2.scene):
        e = dataclasses.replace(e, scene=t2.scene)
    runner = runner or Runner()
    # the test scene's recording in out, the calibration scene's (if another) in out/calibration
    places = [(out, e, *_table2_recording(t2))]
    if t2.separate_calibration:
        if scene_label(t2.calibration_scene) == scene_label(e.compare.train_scene(t2.scene)) and uses_fabmap(e.compare):
            raise ConfigError(f"calibration_scene: {t2.calibration_scene!r} is FAB-MAP's training scene too; give "
                              "another (experiment.compare.fabmap_train_scene or calibration_scene)")
        ec = _calibration_experiment(t2, e)
        places.append((out / "calibration", ec, *_table2_recording(t2, calibration=True)))
    units, fresh = [], []
    for d, pe, rec, more, rc in places:
        if _stage_done(d / "record.json", rc):
            continue
        d.mkdir(parents=True, exist_ok=True)
        fresh.append((d, rc))
        log(f"[{rec.scene}] recording the database pass and the passes {['query'] + list(more)} on "
            f"{t2.inside_route} and {t2.outside_route} into {d / 'rec'}")
        units.append(Unit(f"table2 record {rec.scene} database, query", _record_table2_pass, (rec, "query", None, d, rc)))
        units += [Unit(f"table2 record {rec.scene} {name}", _record_table2_pass, (rec, name, p, d, rc))
                  for name, p in more.items()]
    if uses_fabmap(e.compare):   # trained on another scene: beside the recordings
        units.append(Unit("FAB-MAP training", _fabmap_unit, (e.compare, e.scene, out)))
    runner.run(units, progress, log)
    for d, rc in fresh:
        _stamp(d / "record.json", rc)
    built = runner.run([Unit(f"table2 build {pe.scene}", _table2_build, (t2, pe, d, rc, runner.parallel))
                        for d, pe, _, _, rc in places], progress, log)
    times = built[0]
    parts = runner.run([Unit(f"table2 {part}", _table2_part, (t2, e, out, part, built[-1] if part.startswith("calib")
                                                                else times)) for part in TABLE2_PARTS], progress, log)
    res: dict[str, tuple[np.ndarray, dict]] = {part: (r[0], r[1]) for part, r in zip(TABLE2_PARTS, parts)}
    where = {part: r[2] for part, r in zip(TABLE2_PARTS, parts)}

    def joined(parts, method, key):
        return np.concatenate([res[p][1][method][key] for p in parts])

    test, calib = ("inside", "outside"), ("calib_inside", "calib_outside")
    inside_t = np.concatenate([res[p][0] for p in test])
    inside_c = np.concatenate([res[p][0] for p in calib])
    if inside_c.all() or not inside_c.any():
        log(f"[table2] warning: every calibration query is {'inside' if inside_c.all() else 'outside'} the map: "
            "the thresholds are picked without queries on the other side (more outside_frames, or another "
            "calibration_scene)")
    if t2.separate_calibration:
        nearest = None   # another world: no calibration query shares a place with a test query
        apart = "another place than the test queries"
    else:
        nearest = nearest_distance(np.concatenate([where[p] for p in test]), np.concatenate([where[p] for p in calib]))
        apart = f"the test scene: the nearest calibration query {nearest:.2f} m from a test query"
    calibrated_on = (f"{t2.calibration_scene or t2.scene}: calibration passes (seeds {t2.calibration_seeds[0]}, "
                     f"{t2.calibration_seeds[1]}, a query every {t2.calibration_spacing_m:g} m; {len(inside_c)} "
                     f"queries, {int(inside_c.sum())} inside; {apart})")
    rows, curves = [], {}
    # the methods that declare queries off the map: the modes and the baselines (the reference floors and a user's
    # localizers, which may give no inlier score, are graded in Table I and the sweep)
    for method in [m for m in res["inside"][1] if m in e.modes or m in e.compare.baselines]:
        err, sc = joined(test, method, "errors"), joined(test, method, "inlier_score")
        cal = operating_point(joined(calib, method, "errors"), joined(calib, method, "inlier_score"), inside_c,
                              t2.rule, t2.min_precision, t2.radius_m)
        cal.pop("curve")
        pr = precision_recall(err, sc, cal["threshold"], inside_t, t2.radius_m)
        ci = precision_recall_ci(err, sc, cal["threshold"], inside_t, t2.radius_m, method="stationary",
                                 groups=[len(res[p][1][method]["errors"]) for p in test])
        oracle = operating_point(err, sc, inside_t, t2.rule, t2.min_precision, t2.radius_m)
        curves[method_name(method)] = oracle.pop("curve")
        spq = np.mean([res[p][1][method]["s_per_query"] for p in test])
        rows.append({"method": method_name(method), "precision": pr["precision"], "recall": pr["recall"],
                     "threshold": cal["threshold"], "tp": pr["tp"], "declared": pr["declared"],
                     "positives": pr["positives"], "rule": t2.rule,
                     "precision_ci95_low": ci["precision_ci"][0], "precision_ci95_high": ci["precision_ci"][1],
                     "recall_ci95_low": ci["recall_ci"][0], "recall_ci95_high": ci["recall_ci"][1],
                     "oracle_precision": oracle["precision"], "oracle_recall": oracle["recall"],
                     "oracle_threshold": oracle["threshold"], "calibration_precision": cal["precision"],
                     "calibration_recall": cal["recall"], "calibrated_on": calibrated_on,
                     "calibration_scene": t2.calibration_scene or t2.scene, "calibration_nearest_m": nearest,
                     "odometry": odometry_label(e, method), "queries": int(len(err)),
                     "inside_queries": int(inside_t.sum()), "s_per_query": float(spq),
                     "ci_method": ci_method("stationary", ci["block_length"])})
        log(f"[table2] {method_name(method):22s} precision {pr['precision']:.3f} recall {pr['recall']:.3f} at the "
            f"calibrated threshold {cal['threshold']:.4g} (oracle {oracle['precision']:.3f} / {oracle['recall']:.3f})")
    _write_table2(out, rows, curves, t2)
    return rows


#: table2.csv's columns: precision and recall of the test queries at the threshold calibrated on
#: ``calibrated_on`` (``calibration_scene``; ``calibration_nearest_m``: the nearest distance between a
#: calibration and a test query, empty when they drive different scenes), their 95 % bootstrap intervals, the
#: oracle (the rule on the test queries' own curve) and the tracked rows' odometry
TABLE2_COLUMNS = ("method", "precision", "recall", "threshold", "precision_ci95_low", "precision_ci95_high",
                  "recall_ci95_low", "recall_ci95_high", "oracle_precision", "oracle_recall", "calibrated_on",
                  "calibration_scene", "calibration_nearest_m", "odometry", "ci_method")


def _fmt(v: float, f: str = ".3f") -> str:
    return "" if v is None or not np.isfinite(v) else format(v, f)


def _write_table2(out: Path, rows: list[dict], curves: dict, t2: Table2Config) -> None:
    def cell(v, c):
        if isinstance(v, str) or v is None:
            return v or ""
        return _fmt(v, ".6g" if "threshold" in c else ".3f")

    with atomic_path(out / "table2.csv", suffix=".csv") as tmp:
        with open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(TABLE2_COLUMNS)
            for r in rows:
                w.writerow([cell(r.get(c), c) for c in TABLE2_COLUMNS])
    rule = ("maximal F1 = 2PR/(P+R) on the method's PR curve" if t2.rule == "max_f1" else
            f"the highest recall with precision >= {t2.min_precision:.0%}")

    def pct(v):
        return "" if v is None or not np.isfinite(v) else f"{100 * v:.1f} %"

    def ci(r, k):
        lo, hi = r.get(f"{k}_ci95_low"), r.get(f"{k}_ci95_high")
        return "" if lo is None or not np.isfinite(lo) else f"{100 * lo:.1f}-{100 * hi:.1f}"

    lines = [f"Test queries: {rows[0]['queries']} ({rows[0]['inside_queries']} inside the map) on `{t2.scene}`; a "
             f"true positive is declared inside and localized within {t2.radius_m:g} m. Threshold rule: {rule}, "
             f"applied to the calibration queries ({rows[0].get('calibrated_on', '')}) and frozen. The oracle "
             f"applies it to the test queries themselves (optimistic; for comparison only).", "",
             "| method | precision | 95 % CI | recall | 95 % CI | threshold | TP / declared / inside | oracle precision "
             "| oracle recall | odometry | s per query |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['method']} | {pct(r['precision'])} | {ci(r, 'precision')} | {pct(r['recall'])} | "
                     f"{ci(r, 'recall')} | {_fmt(r['threshold'], '.4g')} | {r['tp']} / {r['declared']} / "
                     f"{r['positives']} | {pct(r.get('oracle_precision'))} | {pct(r.get('oracle_recall'))} | "
                     f"{r.get('odometry', '')} | {r['s_per_query']:.3f} |")
    with atomic_path(out / "table2.md", suffix=".md") as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    write_json(out / "table2.json", {"format": "table2", "config": to_dict(t2),
                                     "rows": [_plain(r) for r in rows],
                                     "curves": {k: c.to_dict() for k, c in curves.items()}})
    plot_pr_curves(curves, rows, out / "pr_curves.png")


def plot_pr_curves(curves: dict, rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(13, 5))
    colours = list(plt.get_cmap("tab10").colors) + ["black", "0.55", "darkgoldenrod", "navy"]
    for k, ((name, c), r) in enumerate(zip(curves.items(), rows)):
        # the method's single-image rows solid, its tracked rows dashed, the baselines dotted and thicker
        style = (":", 2.0) if not name.startswith("Ours") else ("--", 1.3) if "track" in name else ("-", 1.3)
        for ax in axes:
            ax.plot(c.recall, np.nan_to_num(c.precision, nan=1.0), style[0], lw=style[1], label=name,
                    color=colours[k % len(colours)])
            if np.isfinite(r["precision"]):
                ax.plot([r["recall"]], [r["precision"]], "o", color=ax.lines[-1].get_color(), ms=5)
    for ax, lim, title in ((axes[0], (0, 1.02), "all methods"), (axes[1], (0.8, 1.005), "zoom: top right")):
        ax.set_xlabel("recall")
        ax.set_ylabel("precision")
        ax.set_xlim(*lim)
        ax.set_ylim(*lim)
        ax.grid(alpha=0.3)
        ax.set_title(title)
    # outside the axes: inside, it covered the curves that matter most (the single images, lower left)
    axes[1].legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
    fig.suptitle("inside/outside the map: the test queries' precision-recall curves (dots: at the thresholds "
                 "calibrated on other passes)")
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)


# --- the sweep over the scene's knobs ----------------------------------------------------------------------------

@dataclass
class SweepConfig:
    """``satloc experiment sweep``: every method of ``experiment`` (modes and ``compare.baselines``, revisit
    protocol) on ``scene`` at every combination of the knobs. Each combination is its own experiment folder
    ``a<aliasing>_o<occlusion>_p<appearance>_g<satellite_gap>`` (recorded and built there, reused on rerun).
    Seeds are fixed: database pass 0, query pass 1 (the revisit recording of
    :mod:`satloc_env.experiments.scene_run`), ``experiment.odometry_seed`` and ``experiment.compare.fabmap.seed``."""

    scene: str = "city"
    aliasing: tuple[float, ...] = (0.0, 0.5, 1.0)
    occlusion: tuple[float, ...] = (0.0, 0.3, 0.6)
    appearance: tuple[float, ...] = (0.5,)
    satellite_gap: tuple[float, ...] = (DEFAULT_GAP,)
    experiment: ExperimentConfig = field(default_factory=lambda: ExperimentConfig(
        database_frames=150, modes=("go", "np", "full", "full+track"), pictures=False))

    def __post_init__(self):
        for name in ("aliasing", "occlusion", "appearance", "satellite_gap"):
            v = getattr(self, name)
            if not v or any(not 0 <= x <= 1 for x in v):
                raise ConfigError(f"{name}: expected a non-empty list of values in [0, 1], got {list(v)}")
            if len({f"{x:g}" for x in v}) != len(v):   # each combination has a folder of its own, named by them
                raise ConfigError(f"{name}: values must differ in their first 6 significant digits (each "
                                  f"combination is the folder a<aliasing>_o<occlusion>_p<appearance>_g<satellite_gap>)"
                                  f", got {list(v)}")

        if self.experiment.satellite_gap is not None:
            raise ConfigError(f"experiment.satellite_gap: the sweep's gap is its own axis; give satellite_gap: "
                              f"[{self.experiment.satellite_gap:g}] instead")

    def combinations(self) -> list[tuple[float, float, float, float]]:
        return [(a, o, p, g) for a in self.aliasing for o in self.occlusion for p in self.appearance
                for g in self.satellite_gap]


SWEEP_COLUMNS = ("scene", "aliasing", "occlusion", "appearance", "satellite_gap", "method", "mean_m", "ci95_low",
                 "ci95_high", "median_m", "within_1m", "recall_10m", "failure_rate", "queries", "odometry", "ci_method")


def _combo_name(a: float, o: float, p: float, g: float) -> str:
    return f"a{a:g}_o{o:g}_p{p:g}_g{g:g}"


def _sweep_config(sc: SweepConfig, a: float, o: float, p: float, g: float) -> ExperimentConfig:
    return from_dict(ExperimentConfig, dict(to_dict(sc.experiment), scene=sc.scene, aliasing=a, occlusion=o,
                                            appearance=p, satellite_gap=g), "sweep config: experiment")


def _sweep_unit(sc: SweepConfig, a: float, o: float, p: float, g: float, out: Path, times: dict,
                progress: bool = True, log=print) -> list[dict]:
    """Every method on one knob combination whose stages are done (:func:`_stages_unit`, ``times``) in its
    folder ``out/a<a>_o<o>_p<p>_g<g>``; its rows of ``sweep.csv``. FAB-MAP's trained model (it depends on none
    of the knobs) is read from ``out``."""
    cfg = _sweep_config(sc, a, o, p, g)
    d = out / _combo_name(a, o, p, g)
    db, q = Sequence.load(d / "rec" / "database"), Sequence.load(d / "rec" / "query")
    res = compare(cfg, cfg.compare, f"{sc.scene} a={a:g} o={o:g} p={p:g} g={g:g}", db, q, _covered(cfg, db, q),
                  d / "build", SatelliteMap.load(d / "rec" / "map"), d, {"scene": sc.scene, "config": to_dict(cfg)},
                  times, progress, log, fabmap_dir=out)
    return [{"scene": sc.scene, "aliasing": a, "occlusion": o, "appearance": p, "satellite_gap": g,
             "method": method_name(m, r), "mean_m": round(float(r["mean_m"]), 4),   # 4 decimals: sweep.md
             "ci95_low": round(float(r["ci95_low"]), 4), "ci95_high": round(float(r["ci95_high"]), 4),  # rounds
             "median_m": round(float(r["median_m"]), 4), "within_1m": round(float(r["within_1m"]), 4),  # them as
             "recall_10m": round(float(r["within_10m"]), 4),   # compare.json's would be
             "failure_rate": round(float(r["failure_rate"]), 4),
             "queries": int(r["queries"]), "odometry": odometry_label(cfg, m, r), "ci_method": r.get("ci_method", "")}
            for m, r in res.items()]


def sweep(out: str | Path, config: dict | None = None, progress: bool = True, log=print,
          runner: Runner | None = None) -> list[dict]:
    """Mean error (with its 95 % bootstrap interval, failures counted as gross errors), 10 m recall (fraction of
    the queries localized within 10 m) and failure rate of every method over aliasing x occlusion x
    appearance. Writes ``sweep.csv`` (:data:`SWEEP_COLUMNS`), ``sweep.md``, ``sweep.json`` (with
    the seeds) and ``sweep.png`` into ``out``; returns the rows.

    Units (``runner``, :mod:`satloc_env.experiments.scale`): FAB-MAP's training (shared by every combination) beside each
    combination's recording and build (:func:`_stages_unit`), then each combination's methods
    (:func:`_sweep_unit`)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    sc = from_dict(SweepConfig, dict(config or {}), "sweep config")
    check_recordings(record_config(from_dict(ExperimentConfig, dict(to_dict(sc.experiment), scene=sc.scene,
                                                                    aliasing=a, satellite_gap=sc.satellite_gap[0]),
                                             "sweep config: experiment"))
                     for a in sc.aliasing)   # before any work: the passes drivable (the roads do not alias, and
                                             # the gap changes the map, not the roads)
    runner = runner or Runner()
    combos = sc.combinations()
    names = [_combo_name(*c) for c in combos]
    stages = [Unit(f"sweep {n} stages", _stages_unit, (_sweep_config(sc, *c), out / n)) for n, c in zip(names, combos)]
    if uses_fabmap(sc.experiment.compare):   # shared by every combination: beside their stages
        stages.append(Unit("FAB-MAP training", _fabmap_unit, (sc.experiment.compare, sc.scene, out)))
    times = runner.run(stages, progress, log)
    units = [Unit(f"sweep {n}", _sweep_unit, (sc, *c, out, t)) for n, c, t in zip(names, combos, times)]
    rows = [r for part in runner.run(units, progress, log) for r in part]
    cols = list(SWEEP_COLUMNS)
    with atomic_path(out / "sweep.csv", suffix=".csv") as tmp:
        with open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(cols)
            for r in rows:
                w.writerow([r[c] for c in cols])
    seeds = {"database_pass": 0, "query_pass": 1, "odometry": sc.experiment.odometry_seed,
             "fabmap": sc.experiment.compare.fabmap.seed}
    lines = [f"Scene `{sc.scene}`; seeds: {seeds}.", "",
             "| aliasing | occlusion | appearance | satellite gap | method | mean m [95 % CI] | median m | within 1 m "
             "| within 10 m | failed | queries | odometry |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['aliasing']:g} | {r['occlusion']:g} | {r['appearance']:g} | {r['satellite_gap']:g} | "
              f"{r['method']} | {r['mean_m']:.2f} [{r['ci95_low']:.2f}-{r['ci95_high']:.2f}] | {r['median_m']:.2f} | "
              f"{100 * r['within_1m']:.0f} % | {100 * r['recall_10m']:.0f} % | {100 * r['failure_rate']:.0f} % | "
              f"{r['queries']} | {r['odometry']} |" for r in rows]
    with atomic_path(out / "sweep.md", suffix=".md") as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    write_json(out / "sweep.json", {"format": "sweep", "config": to_dict(sc), "seeds": seeds, "rows": rows})
    plot_sweep(rows, out / "sweep.png")
    return rows


#: ``satloc experiment gap``: the sweep over the satellite gap alone, on the demo's slice of ``city`` (its first
#: 400 database frames, every mode, the baselines), the other knobs as Table I's revisit protocol has them
GAP_CURVE = {"scene": "city", "aliasing": [0.0], "occlusion": [0.3], "appearance": [0.5],
             "satellite_gap": [0.0, 0.25, 0.5, 0.75, 1.0],
             "experiment": {"database_frames": 400, "modes": list(MODES), "pictures": False}}


def gap_curve(out: str | Path, config: dict | None = None, progress: bool = True, log=print,
              runner: Runner | None = None) -> list[dict]:
    """Each method's error against the satellite gap (:mod:`satloc_env.world.capture`): :func:`sweep` with
    :data:`GAP_CURVE` under ``config`` (its keys replace those of :data:`GAP_CURVE`; ``experiment`` merges),
    then ``gap.png`` (mean and median error, and the fraction within 1 m, against the gap, one line per
    method) beside ``sweep.csv``. Returns the rows."""
    config = dict(config or {})
    merged = {**GAP_CURVE, **config, "experiment": {**GAP_CURVE["experiment"], **(config.get("experiment") or {})}}
    from_dict(SweepConfig, merged, "gap config")   # before any work: an unknown or bad key is named
    rows = sweep(out, merged, progress, log, runner)
    plot_gap(rows, Path(out) / "gap.png")
    return rows


def _line_styles(methods) -> dict[str, dict]:
    """Per method, its line's ``color`` and format ``fmt``: a colour of its own (the 20 of ``tab20`` in turn:
    with matplotlib's default cycle of 10, a sweep's 13 methods and floors shared colours); the baselines
    (ground images only) dashed, the reference floors (:data:`REFERENCE_NAMES`) dotted, the method's own modes
    solid with dots."""
    import matplotlib

    cmap = matplotlib.colormaps["tab20"]
    floors = set(REFERENCE_NAMES.values())
    out = {}
    for i, m in enumerate(dict.fromkeys(methods)):
        style = ":" if m in floors else "--" if m in BASELINE_NAMES.values() else "o-"
        out[m] = {"fmt": style, "color": cmap(i % cmap.N)}
    return out


def plot_gap(rows: list[dict], path: Path) -> None:
    """Mean and median error (log) and the fraction within 1 m against ``satellite_gap``, one line per method
    (rows of :func:`sweep` that differ only in the gap)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(17, 4.8))
    for m, st in _line_styles(r["method"] for r in rows).items():
        part = sorted((r for r in rows if r["method"] == m), key=lambda r: r["satellite_gap"])
        g = [r["satellite_gap"] for r in part]
        fmt, kw = st["fmt"], {"color": st["color"], "label": m}
        axes[0].semilogy(g, [max(r["mean_m"], 1e-2) for r in part], fmt, **kw)
        axes[1].semilogy(g, [max(r["median_m"], 1e-2) for r in part], fmt, **kw)
        axes[2].plot(g, [r["within_1m"] for r in part], fmt, **kw)
    for ax, yl in zip(axes, ("mean error (m)", "median error (m)", "within 1 m")):
        ax.set_xlabel("satellite_gap (0: the map is the rendered ground's copy)")
        ax.set_ylabel(yl)
        ax.grid(alpha=0.3, which="both")
    axes[2].set_ylim(0, 1.02)
    axes[2].legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
    fig.suptitle(f"{rows[0]['scene']}: error against the satellite map's capture gap (dashed: the baselines, "
                 "ground images only; dotted: the prior alone and dead reckoning)" if rows else "")
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def plot_sweep(rows: list[dict], path: Path) -> None:
    """Mean error (log) and 10 m recall against the knob combinations, one line per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    key = ("aliasing", "occlusion", "appearance", "satellite_gap")
    combos = list(dict.fromkeys(tuple(r.get(k, 0.0) for k in key) for r in rows))   # rows before the gap: 0
    labels = [f"a{a:g}\no{o:g}\np{p:g}\ng{g:g}" for a, o, p, g in combos]
    fig, axes = plt.subplots(1, 2, figsize=(max(8, 1.2 * len(combos) + 4), 4.5))
    for m, st in _line_styles(r["method"] for r in rows).items():
        by = {tuple(r.get(k, 0.0) for k in key): r for r in rows if r["method"] == m}
        x = np.arange(len(combos))
        fmt, kw = st["fmt"], {"color": st["color"], "label": m}
        axes[0].semilogy(x, [max(by[c]["mean_m"], 1e-2) if c in by else np.nan for c in combos], fmt, **kw)
        axes[1].plot(x, [by[c]["recall_10m"] if c in by else np.nan for c in combos], fmt, **kw)
    for ax, yl in zip(axes, ("mean error (m)", "within 10 m")):
        ax.set_xticks(np.arange(len(combos)))
        ax.set_xticklabels(labels, fontsize=7)
        ax.set_ylabel(yl)
        ax.grid(alpha=0.3)
    axes[1].set_ylim(0, 1.02)
    axes[0].legend(fontsize=7)
    fig.suptitle("knobs: a = aliasing, o = occlusion, p = appearance, g = satellite gap")
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


# --- Table I: every method under each protocol ------------------------------------------------------

def protocol_split(protocol: str, n: int, fraction: float = 0.4, seed: int = 0, step: int = 8
                   ) -> tuple[np.ndarray, np.ndarray | None]:
    """Database frame indices of a Table I protocol over a pass of ``n`` frames, and for ``city`` and
    ``kitti-city`` the query indices (the rest of the pass): there a random ``round(fraction * n)`` frames
    (seeded by ``seed``), sorted; ``residential``: every ``step``-th frame from the first (queries: a second
    pass)."""
    if protocol in ("city", "kitti-city"):
        perm = np.random.default_rng(seed).permutation(n)
        k = int(round(fraction * n))
        return np.sort(perm[:k]), np.sort(perm[k:])
    if protocol == "residential":
        return np.arange(0, n, max(1, int(step))), None
    raise ConfigError(f"protocol: expected 'city', 'kitti-city' or 'residential', got {protocol!r}")


def _kitti_city_pass(cfg: ExperimentConfig, label: str, pdir: Path, db_full: Sequence, rc: dict, progress: bool,
                     log) -> Sequence:
    """The kitti-city protocol's one pass (:data:`satloc_env.experiments.scene_run.KITTI_CITY_LENGTH_M` or
    ``cfg.kitti_city_length_m`` of the database route, at the database pass's lane and conditions, drifting, at
    :data:`~satloc_env.experiments.scene_run.KITTI_CITY_SPEED_MPS` with a frame at every 0.1 s step: a frame
    every 0.77 m on average), recorded into ``pdir/pass`` unless done for the same settings."""
    from .scene_run import KITTI_CITY_SEED, KITTI_CITY_SPEED_MPS

    db_pass = rc.get("database", {})
    step_m = KITTI_CITY_SPEED_MPS * 0.1
    p = PassConfig(route=db_pass.get("route"), lane_offset_m=db_pass.get("lane_offset_m", -1.75), spacing_m=0.5,
                   max_frames=int(np.ceil(cfg.kitti_city_length_m / step_m)) + 1, seed=KITTI_CITY_SEED,
                   wander_m=cfg.wander_m, speed_wander=cfg.speed_wander)
    prc = {"pass": to_dict(p, stamp=True), "speed_mps": KITTI_CITY_SPEED_MPS, "record": rc}
    if not _stage_done(pdir / "record.json", prc):
        log(f"[{label}] recording the kitti-city pass ({cfg.kitti_city_length_m:g} m, a frame every {step_m:.2f} m)")
        env = make_env(scene=cfg.scene, resolution=rc.get("resolution", "half"), aliasing=cfg.aliasing,
                       speed_mps=KITTI_CITY_SPEED_MPS, depth=p.depth, labels=False, localizer=None,
                       satellite_gap=cfg.satellite_gap)
        try:
            env.reset(seed=p.seed)
            route = p.route or env.scene.spec.database_route
            record_pass(env, p, route, pdir / "pass", "kitti-city pass", progress, dict(db_full.meta))
        finally:
            env.close()
        _stamp(pdir / "record.json", prc)
    return Sequence.load(pdir / "pass")


def _protocol(cfg: ExperimentConfig, protocol: str, label: str, sdir: Path, db_full: Sequence, rc: dict,
              progress: bool, log) -> dict:
    """Table I's ``city``, ``kitti-city`` or ``residential`` protocol on the scene folder ``sdir`` (its recorded
    database pass and its map), in ``sdir/protocol_<protocol>``: the dictionary and the projections of the
    protocol's database frames alone; returns :func:`satloc_env.experiments.tables.compare`. ``kitti-city`` splits
    a pass of its own (:func:`_kitti_city_pass`) as ``city`` splits the database pass."""
    pdir = sdir / f"protocol_{protocol}"
    pdir.mkdir(exist_ok=True)
    if protocol == "kitti-city":
        db_full = _kitti_city_pass(cfg, label, pdir, db_full, rc, progress, log)
    speed = float(rc.get("speed_mps", RecordConfig().speed_mps))
    # one frame per second: the pass's frames as recorded lie further apart than its spacing_m (at most one
    # per simulator step: 1.6 m at 8 m/s for spacing_m 1), so the step is measured on its poses
    xy = np.asarray(db_full.poses, np.float64)[:, :2]
    gaps = np.hypot(*np.diff(xy, axis=0).T)
    gaps = gaps[np.isfinite(gaps) & (gaps > 0)]
    spacing = float(np.median(gaps)) if len(gaps) else float(rc.get("database", {}).get("spacing_m",
                                                                                         PassConfig().spacing_m))
    step = max(1, int(round(speed / spacing)))
    dbi, qi = protocol_split(protocol, len(db_full), cfg.city_database_fraction, cfg.split_seed, step)
    db = db_full.view(dbi, name=f"{protocol} protocol database")
    source = {"record": rc, "protocol": protocol, "database_frames": [int(i) for i in dbi]}
    if protocol == "kitti-city":   # its own pass: a pass recorded anew is built anew
        source["pass"] = read_json(pdir / "record.json")["config"]
    odo = None
    if protocol in ("city", "kitti-city"):
        q, sel = db_full.view(qi, name=f"{protocol} protocol queries"), np.arange(len(qi))
        if is_tracked(cfg):   # over the pass, between the queries
            cache = sdir / "odometry_visual_database.npz" if protocol == "city" else pdir / "odometry_visual.npz"
            odo = tracked_odometry(cfg, db_full, qi, cache)
    else:
        # a second pass over the database's route at one frame per second (the revisit pass's lane,
        # appearance and occluders, another seed; recorded densely for visual odometry)
        p = dense_pass(cfg, PassConfig(lane_offset_m=cfg.query_lane_m, spacing_m=speed, occlusion=cfg.occlusion,
                                       appearance=cfg.appearance, change=cfg.change,
                                       change_parts=cfg.change_parts, seed=SECOND_PASS_SEED,
                                       max_frames=None if cfg.database_frames is None else
                                       int(np.ceil(db_full.path_length() / speed)) + 1,
                                       wander_m=cfg.wander_m, speed_wander=cfg.speed_wander))
        prc = {"pass": to_dict(p, stamp=True), "record": rc}
        if not _stage_done(pdir / "record.json", prc):
            log(f"[{label}] recording the second pass (a frame every {speed:g} m)")
            env = make_env(scene=cfg.scene, resolution=rc.get("resolution", "half"), aliasing=cfg.aliasing,
                           speed_mps=rc.get("speed_mps", RecordConfig().speed_mps), depth=p.depth, labels=False,
                           localizer=None, satellite_gap=cfg.satellite_gap)
            try:
                env.reset(seed=p.seed)
                route = rc.get("database", {}).get("route") or env.scene.spec.database_route
                record_pass(env, p, route, pdir / "second", "second", progress, dict(db_full.meta))
            finally:
                env.close()
            _stamp(pdir / "record.json", prc)
        q = Sequence.load(pdir / "second")
        sel = np.intersect1d(covered_queries(db_full, q, cfg.coverage_m), spaced_frames(q, speed))
        if len(sel) == 0:
            raise ConfigError(f"[{label}] residential protocol: no second-pass frame lies on the database path")
    # the dictionary of the protocol's database and projections learned on it alone: no learned state has seen
    # a query (the city protocol's queries are frames of the database pass)
    bdir, times = build_and_learn(cfg, f"{label} {protocol}", db, sdir / "rec" / "map", pdir, source, progress, log)
    return compare(cfg, cfg.compare, label, db, q, sel, bdir, SatelliteMap.load(sdir / "rec" / "map"), pdir,
                   {"scene": cfg.scene, "protocol": protocol, "config": to_dict(cfg)}, times, progress, log,
                   fabmap_dir=sdir, odometry=odo)


#: table1.csv's columns (failure_rate: queries not answered, counted as gross failures in the mean; ci95_*: the
#: bootstrap interval of the mean, made as ci_method says; odometry: what moved the tracked rows' belief, empty
#: for single images)
TABLE1_COLUMNS = ("method", "scene", "mean_m", "std_m", "protocol", "ci95_low", "ci95_high", "median_m", "within_1m",
                  "within_10m", "failure_rate", "queries", "odometry", "ci_method")


def odometry_label(cfg: ExperimentConfig, method: str, result: dict | None = None) -> str:
    """The odometry a table row used: ``cfg.odometry`` for the tracked modes, what a reference or a user's
    localizer was given (its ``result``'s ``odometry``), empty for the rest."""
    if result is not None and "odometry" in result:
        return result["odometry"] or ""
    return cfg.odometry if "track" in method.split("+") else ""


def _table1_unit(cfg: ExperimentConfig, label: str, sdir: Path, protocol: str, times: dict, progress: bool = True,
                 log=print) -> dict:
    """One protocol of Table I on a scene whose shared stages are done (:func:`_stages_unit`, FAB-MAP's
    training): ``revisit`` in ``sdir``, the others in ``sdir/protocol_<name>`` (:func:`_protocol`);
    :func:`compare`'s results."""
    if protocol == "cross-area":
        return cross_area(cfg, label, sdir, progress, log)
    db = Sequence.load(sdir / "rec" / "database")
    if protocol != "revisit":
        return _protocol(cfg, protocol, label, sdir, db, read_json(sdir / "record.json")["config"], progress, log)
    q = Sequence.load(sdir / "rec" / "query")
    return compare(cfg, cfg.compare, label, db, q, _covered(cfg, db, q), sdir / "build",
                   SatelliteMap.load(sdir / "rec" / "map"), sdir, {"scene": cfg.scene, "config": to_dict(cfg)}, times,
                   progress, log)


def _kept_rows(out: Path, ran: set, log=print) -> list[dict]:
    """The rows of an earlier ``out/table1.json`` whose (scene, protocol) this run did not redo (so that a run
    of some protocols, say ``protocols: [cross-area]`` on a finished table, adds its rows instead of dropping
    the others: :func:`satloc_env.experiments.scene_run.earlier_rows`)."""
    kept, _ = earlier_rows(out / "table1.json", "table1", TABLE1_COLUMNS,
                           lambda r: (r.get("scene"), r.get("protocol")) in ran)
    if kept:
        log(f"table1: keeping {len(kept)} rows of {out / 'table1.json'} (scenes x protocols not run now: "
            + ", ".join(sorted({f"{r['scene']} {r['protocol']}" for r in kept})) + ")")
    return kept


def table1(out: str | Path, scenes: tuple[str, ...] = ("city", "residential"), config: dict | None = None,
           progress: bool = True, log=print, runner: Runner | None = None) -> list[dict]:
    """Every method (the modes and the baselines of ``compare``) under each protocol of ``protocols`` on each
    scene: ``revisit`` in ``out/<scene>`` (as :func:`run_scene`, same stages), ``city`` and ``residential`` in
    ``out/<scene>/protocol_<name>`` (see :func:`protocol_split`). Writes ``table1.csv``
    (method,scene,mean_m,std_m,protocol), ``table1.md`` and ``table1.json`` into ``out``; returns the rows.
    With ``cross-area`` among the protocols (:mod:`satloc_env.experiments.cross_area`) also ``cross_area.csv``
    and ``cross_area.md``: its rows beside every method localized on the same queries. Rows of an earlier
    ``table1.json`` in ``out`` for scenes x protocols not run this time are kept in the files
    (:func:`_kept_rows`); the rows returned are this run's.

    Units (``runner``, :mod:`satloc_env.experiments.scale`): each scene's shared stages (recording, build:
    :func:`_stages_unit`) and FAB-MAP's training, then each scene x protocol (:func:`_table1_unit`)."""
    out = Path(out)
    rows = []
    cfgs = [from_dict(ExperimentConfig, dict(config or {}, scene=scene), "experiment config") for scene in scenes]
    for c in cfgs:   # before any work: every scene's passes drivable by the autopilot
        check_recordings([record_config(c)], second_pass="residential" in c.protocols)
    labels = scene_labels(scenes)
    runner = runner or Runner()
    fabmap = [Unit(f"table1 {label} FAB-MAP training", _fabmap_unit, (cfg.compare, cfg.scene, out / label))
              for cfg, label in zip(cfgs, labels) if uses_fabmap(cfg.compare)]
    times = runner.run([Unit(f"table1 {label} stages", _stages_unit, (cfg, out / label))
                        for cfg, label in zip(cfgs, labels)] + fabmap, progress, log)
    # per scene: revisit first, then the other protocols in the configuration's order
    jobs = [(i, p) for i, cfg in enumerate(cfgs)
            for p in (["revisit"] if "revisit" in cfg.protocols else []) + [p for p in cfg.protocols if p != "revisit"]]
    results = runner.run([Unit(f"table1 {labels[i]} {p}", _table1_unit, (cfgs[i], labels[i], out / labels[i], p,
                                                                          times[i])) for i, p in jobs], progress, log)
    for (i, protocol), res in zip(jobs, results):
        for method, m in res.items():
            rows.append({"method": method_name(method, m), "scene": labels[i], "protocol": protocol,
                         **{k: round(m[k], 3) for k in ("mean_m", "std_m", "median_m", "within_1m",
                                                        "within_10m", "failure_rate", "ci95_low", "ci95_high")},
                         "queries": m["queries"], "s_per_query": round(m["s_per_query"], 4),
                         "odometry": odometry_label(cfgs[i], method, m), "ci_method": m.get("ci_method", "")})
    table = _kept_rows(out, {(labels[i], p) for i, p in jobs}, log) + rows
    write_rows_csv(out / "table1.csv", TABLE1_COLUMNS, table)
    write_json(out / "table1.json", dict(header("table1"), rows=table))
    with atomic_path(out / "table1.md", suffix=".md") as tmp:
        tmp.write_text(markdown_table(table))
    cross = [i for i, c in enumerate(cfgs) if "cross-area" in c.protocols]
    if cross:   # the no-database rows beside every method localized on the same (revisit) queries
        ca = cfgs[cross[0]].cross_area
        write_cross_area(out, [r for i in cross for r in cross_area_rows(out / labels[i], labels[i])],
                         f"the no-database rows from a +-{ca.prior_radius_m:g} m / +-{ca.prior_yaw_deg:g} degree "
                         f"prior drawn per query (seed {ca.seed})")
    return rows
